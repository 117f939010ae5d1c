"""An effects-only stand-in for the full simulator: a NEO-5-like error series built from the
effect layers (used by the injection benchmark, the tests, and as the baseline when a
scenario cannot be run).

Static error: horizontal Gauss-Markov sigma 0.8 m, tau 120 s plus a fast component
(0.15 m, 5 s), vertical GM 1.5 m / 120 s, NMEA minutes printed with 5 decimals, as the
NEO-5 does. Moving: the truth drives a circle of about 140 m radius with a speed that
swings between 0.5 and 2.5 m/s (so latency shows against speed).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from sim_backend.effects import GaussMarkov, PositionSeries, Quantization, apply_effects

BASELINE_EFFECTS = (
    GaussMarkov(sigma_m=0.8, tau_s=120.0, axes="en"),
    GaussMarkov(sigma_m=0.15, tau_s=5.0, axes="en"),
    GaussMarkov(sigma_m=1.5, tau_s=120.0, axes="u"),
    Quantization(decimals=5),
)


def truth_motion(t_s: np.ndarray, moving: bool) -> tuple[np.ndarray | None, np.ndarray | None]:
    """Speed (m/s) and course (deg) of the surrogate's true motion, None when static."""
    if not moving:
        return None, None
    speed_mps = 1.5 + 1.0 * np.sin(2 * np.pi * t_s / 97.0)
    course_deg = np.mod(360.0 * t_s / 600.0, 360.0)
    return speed_mps, course_deg


def surrogate_run(
    duration_s: float,
    dt_s: float,
    rng: np.random.Generator,
    *,
    moving: bool = False,
    origin: tuple[float, float] = (51.712345, 19.487654),
    effects: Sequence[object] = BASELINE_EFFECTS,
) -> PositionSeries:
    """One baseline error series (m) of ``duration_s`` at step ``dt_s``."""
    t_s = np.arange(0.0, duration_s + 0.5 * dt_s, dt_s)
    speed_mps, course_deg = truth_motion(t_s, moving)
    zeros = np.zeros(t_s.size)
    series = PositionSeries(
        t_s=t_s,
        east_m=zeros,
        north_m=zeros,
        up_m=zeros,
        valid=np.ones(t_s.size, dtype=bool),
        origin_lat_deg=origin[0],
        origin_lon_deg=origin[1],
        speed_mps=speed_mps,
        course_deg=course_deg,
    )
    return apply_effects(series, list(effects), rng)
