"""The EKF while the wheels stand still and the robot moves (review s12/r2, item 1): a slow
carry (an operator carrying the powered robot from the shed to the field, a push, a
trailer) brings fixes that each agree with the estimate's gate, so the GPS bias states took
the whole move: carried 70 m at 1 m/s with fixes at 4 Hz, or at 0.5 m/s with fixes at 1 Hz,
the estimate ended 33 m short (the bias ~20 σ_b) with σ reading 2.2 m, 30 s after the
robot was set down. The bias the fixes build while the robot stands still is now held to
its model's size (:data:`x6wd.nav.estimator.BIAS_RUNAWAY_CHI2`): beyond it, the position is
what is wrong and the filter resets onto the fix ("bias"). A standing robot's ordinary GPS
error, and a bias built under a high HDOP that then falls, reset nothing.

Sensors here are exact (no noise) where the figure is about the rule, with seeded
Gauss-Markov GPS error where it is about not firing on ordinary error."""

from __future__ import annotations

import math

import numpy as np
import pytest

from x6wd.nav.estimator import (
    Estimator,
    EstimatorConfig,
    GpsParams,
    Mode,
    OdometryParams,
)

ASE_M = 1.5  # the shipped [gnss_noise] ase_m: σ_b = HDOP x 1.5 m
HDOP = 1.2  # tests/test_controller.py's fix()


def _ekf() -> Estimator:
    return Estimator(
        EstimatorConfig(
            mode=Mode.ODOMETRY,
            odometry=OdometryParams(track_m=0.245),
            gps=GpsParams(re_m=1.0, ase_m=ASE_M, correlation_s=120.0),
        )
    )


def _still(
    est: Estimator, t0_s: float, t1_s: float, gps_hz: float, fix_e, hdop=lambda t: HDOP
) -> list[str]:
    """Wheels still (10 Hz increments of 0 m), compass north (10 Hz), fixes at ``gps_hz`` at
    (``fix_e(t)``, 0): the reasons of the fixes."""
    reasons = []
    every = round(10 / gps_hz)
    for k in range(round(10 * t0_s) + 1, round(10 * t1_s) + 1):
        t = 0.1 * k
        est.on_odometry(t, 0.0, 0.0)
        est.on_compass(t, 0.0)
        if k % every == 0:
            reasons.append(est.on_gps(t, fix_e(t), 0.0, hdop(t)).reason)
    return reasons


@pytest.mark.parametrize(("gps_hz", "speed_mps"), [(4.0, 1.0), (1.0, 0.5), (10.0, 1.0)])
def test_a_slow_carry_while_the_wheels_stand_still_moves_the_estimate(
    gps_hz: float, speed_mps: float
) -> None:
    """Idle 20 s at (0, 0), carried 70 m east at ``speed_mps``, set down, 30 s more. Before:
    the estimate 33.6 m short, no reset, σ 2.2 m. Now: one reset onto the fixes during the
    carry ("bias"), after which the bias stays inside its 99 % circle (3.03 σ_b, 5.5 m here)
    and the estimate ends within 6 m of (70, 0) (measured 5.4-5.5 m short: the circle's
    edge, which the Gauss-Markov bias then forgets over its 120 s)."""
    est = _ekf()
    carry_s = 70.0 / speed_mps
    t1 = 20.0 + carry_s

    def where(t: float) -> float:
        return 0.0 if t < 20.0 else min(70.0, speed_mps * (t - 20.0))

    reasons = _still(est, 0.0, t1 + 30.0, gps_hz, where)
    e = est.estimate()
    assert e is not None
    assert est.stats.bias_runaway_resets >= 1, (e.east_m, est.state[5:7])
    assert est.stats.last_reset_reason == "bias"
    assert "gated" not in reasons  # every fix inside the gate: no step rule could take it
    assert abs(e.east_m - 70.0) < 6.0, (e.east_m, est.state[5:7])
    assert math.hypot(*est.state[5:7]) < 3.1 * ASE_M * HDOP


def test_a_standing_robots_ordinary_gps_error_resets_nothing() -> None:
    """20 min standing, the fixes wandering with a Gauss-Markov error of the model's own
    size (σ_b 1.5 m, τ 120 s, white 1 m), 1 Hz, 3 seeds: no reset, nothing gated."""
    for seed in (1, 2, 3):
        rng = np.random.default_rng(seed)
        phi = math.exp(-1.0 / 120.0)
        b = rng.normal(0.0, ASE_M, 2)
        err = {}
        for s in range(1, 1201):
            b = phi * b + ASE_M * math.sqrt(1 - phi * phi) * rng.normal(0.0, 1.0, 2)
            err[s] = b + rng.normal(0.0, 1.0, 2)
        est = _ekf()
        reasons = []
        for k in range(1, 12001):
            t = 0.1 * k
            est.on_odometry(t, 0.0, 0.0)
            est.on_compass(t, 0.0)
            if k % 10 == 0:
                e_m, n_m = err[k // 10]
                reasons.append(est.on_gps(t, float(e_m), float(n_m), HDOP).reason)
        assert est.stats.gps_resets == 0, (seed, reasons.count("gated"))


def test_a_bias_built_under_a_high_hdop_does_not_reset_when_the_hdop_falls() -> None:
    """Standing beside a building: the fixes drift 25 m east over 120 s at HDOP 3.6 (3.8 σ
    of the fix), then the HDOP falls to 1.2 and the offset fades over 120 s. Against the new
    HDOP's σ_b (1.8 m) the bias (~10 m) is over 5.26 σ_b: the bound is the largest recent
    stationary variance, forgotten over correlation_s, so nothing resets (against the
    current HDOP's alone: a reset onto the fix, the estimate 10.6-12.3 m off at the end
    instead of ~2 m)."""
    off_m, build_s = 25.0, 120.0

    def fix_e(t: float) -> float:
        if t < 20.0:
            return 0.0
        if t < 20.0 + build_s:
            return off_m * (t - 20.0) / build_s
        if t < 30.0 + build_s:
            return off_m
        return off_m * math.exp(-(t - 30.0 - build_s) / 120.0)

    est = _ekf()
    reasons = _still(
        est, 0.0, 230.0 + build_s, 1.0, fix_e, hdop=lambda t: 3.6 if t < 30.0 + build_s else 1.2
    )
    assert est.stats.gps_resets == 0, reasons
    e = est.estimate()
    assert e is not None and abs(e.east_m - fix_e(230.0 + build_s)) < 4.0
