"""The compass half of the gap tool: heading error of a real CMPS10 log against the simulator.

Inputs are :class:`sim_backend.effects.HeadingSeries`: the MEASURED (magnetic) heading,
pitch and roll of the compass, the TRUE heading, and the field magnitude when raw
magnetometer values exist. The heading error is ``wrap180(measured - true)``.

Battery (axis "heading"; one joint least-squares regression per series, because the
compass effects overlap in heading and can only be told apart jointly)::

    error = m + a1 cos h + b1 sin h + a2 cos 2h + b2 sin 2h + g * x_tilt + c * rate + noise

with h the true heading, ``x_tilt`` the heading error an UNcompensated compass would make at
this heading, pitch and roll (exact formula, :func:`sim_backend.effects.tilted_heading_deg`),
and ``rate`` the true turn rate (deg/s). The cells are m (declination), the once-per-turn
harmonic a1/b1 (hard iron), the twice-per-turn harmonic a2/b2 (soft iron), the tilt gain g
(the fraction of tilt left uncompensated: what tells tilt from hard iron, REFERENCE.md §6),
the lag -c in seconds (a first-order lag of tau makes an error of about -tau * rate), the log
spread of the residual (noise) and, when the field magnitude is known, the once-per-turn
harmonic of log |B| (hard iron moves it, tilt cannot).

Everything else is the pipeline the GPS side runs too (:mod:`x6wd.gap.pipeline`, with this
module's battery, windows, block bootstrap and :data:`EFFECTS` plugged in): each cell is
scored against a sim-vs-sim null (baseline runs with other seeds, or a block bootstrap of
fewer), never an iid p-value; candidates are fitted on the first part, added to every
baseline run, and scored on the held-out last part after a guard gap by G
(:meth:`NullModel.gap`); closure = (G_baseline - G_with) / (G_baseline - G_floor); greedy
add-one-in.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from sim_backend.compass import CompassErrors, MagneticField, SimCmps10
from sim_backend.effects import (
    Declination,
    HardIron,
    HeadingLag,
    HeadingSeries,
    SoftIron,
    Tilt,
    tilted_heading_deg,
    wrap180,
    wrap360,
)
from x6wd.core.errors import ConfigError
from x6wd.core.files import read_text_bounded
from x6wd.gap import pipeline
from x6wd.gap.fitted import Fit
from x6wd.gap.pipeline import (
    Battery,
    Candidate,
    EffectFitter,
    Outcome,
    Pipeline,
    PipelineOptions,
    Progress,
)
from x6wd.gap.stats import Cell

AXIS = "heading"
SD_FLOOR = 0.01  # smallest null spread of any compass cell (deg, s, or log units)
COG_MIN_SPEED_MPS = 1.0  # course over ground stands in for heading only above this speed
COG_MAX_GAP_S = 1.0  # ... and only within this long of such a fix
# Several selected layers are refitted jointly (backfitting): at most this many passes, until
# no parameter moves by more than this many of its standard errors
JOINT_PASSES = 5
JOINT_TOL_SE = 0.1


@dataclass(frozen=True)
class CompassLayout:
    """Fixed from the real log so every replicate yields the same cells: sample step,
    duration, whether the field magnitude is used, and the field the fits assume (only the
    ratio hard iron / horizontal field and tilt * tan(inclination) are identifiable)."""

    dt_s: float
    duration_s: float
    has_field: bool
    inclination_deg: float = 66.0
    horizontal_field_ut: float = 19.0


@dataclass(kw_only=True)
class CompassDiagnosis(Outcome[HeadingSeries, CompassLayout]):
    """Everything the report needs for the compass half."""


# --- series helpers ---------------------------------------------------------------------------


def heading_error_deg(series: HeadingSeries) -> np.ndarray:
    """Measured minus true heading, wrapped to [-180, 180)."""
    if series.true_heading_deg is None:
        raise ConfigError("heading series has no true heading")
    return wrap180(
        np.asarray(series.heading_deg, dtype=float) - np.asarray(series.true_heading_deg)
    )


def turn_rate_dps(series: HeadingSeries) -> np.ndarray:
    """True turn rate (deg/s); a bootstrap replicate carries its own in ``extra['rate_dps']``
    (its block joins would make spurious spikes)."""
    if "rate_dps" in series.extra:
        return np.asarray(series.extra["rate_dps"], dtype=float)
    assert series.true_heading_deg is not None
    t_s = np.asarray(series.t_s, dtype=float)
    if t_s.size < 3:
        return np.zeros(t_s.size)
    return np.gradient(np.unwrap(np.radians(series.true_heading_deg)), t_s) * 180.0 / math.pi


def hwindow(series: HeadingSeries, t0_s: float, t1_s: float) -> HeadingSeries:
    """Samples with t0_s <= t - t_start < t1_s."""
    t_s = np.asarray(series.t_s, dtype=float)
    inside = (t_s - t_s[0] >= t0_s) & (t_s - t_s[0] < t1_s)

    def cut(a: np.ndarray | None) -> np.ndarray | None:
        return None if a is None else np.asarray(a)[inside]

    return HeadingSeries(
        t_s=t_s[inside],
        heading_deg=np.asarray(series.heading_deg)[inside],
        pitch_deg=np.asarray(series.pitch_deg)[inside],
        roll_deg=np.asarray(series.roll_deg)[inside],
        true_heading_deg=cut(series.true_heading_deg),
        field_ut=cut(series.field_ut),
        extra={k: np.asarray(v)[inside] for k, v in series.extra.items()},
    )


def finite_samples(series: HeadingSeries) -> tuple[HeadingSeries, int]:
    """``series`` without the samples that have a non-finite time, heading, true heading,
    pitch, roll or ``extra`` value, and how many those were (a field magnitude with one is
    dropped whole, as the reader drops it)."""
    columns = [series.t_s, series.heading_deg, series.pitch_deg, series.roll_deg]
    columns += [series.true_heading_deg] if series.true_heading_deg is not None else []
    columns += [np.asarray(v, dtype=float) for v in series.extra.values()]
    keep = np.logical_and.reduce([np.isfinite(np.asarray(c, dtype=float)) for c in columns])
    field_ut = series.field_ut
    if field_ut is not None and not np.all(np.isfinite(np.asarray(field_ut)[keep])):
        field_ut = None
    n_dropped = int(keep.size - np.count_nonzero(keep))
    if n_dropped == 0:
        return series.with_(field_ut=field_ut), 0

    def cut(a: np.ndarray | None) -> np.ndarray | None:
        return None if a is None else np.asarray(a)[keep]

    return (
        HeadingSeries(
            t_s=np.asarray(series.t_s)[keep],
            heading_deg=np.asarray(series.heading_deg)[keep],
            pitch_deg=np.asarray(series.pitch_deg)[keep],
            roll_deg=np.asarray(series.roll_deg)[keep],
            true_heading_deg=cut(series.true_heading_deg),
            field_ut=cut(field_ut),
            extra={k: np.asarray(v)[keep] for k, v in series.extra.items()},
        ),
        n_dropped,
    )


STUCK_RESULTANT = 0.95
"""A compass whose readings' mean resultant length is above this (all within a circular
standard deviation of about 18 deg) while the true heading's is below TURNING_RESULTANT
does not turn with the robot (:func:`not_turning_text`)."""
TURNING_RESULTANT = 0.7


def _resultant(heading_deg: np.ndarray) -> tuple[float, float]:
    """(mean resultant length, circular mean deg) of headings."""
    mean = np.mean(np.exp(1j * np.radians(np.asarray(heading_deg, dtype=float))))
    return float(abs(mean)), float(np.degrees(np.angle(mean)) % 360.0)


def not_turning_text(series: HeadingSeries) -> str | None:
    """Why ``series``' compass readings cannot be diagnosed for compass effects, when they do
    not turn while its true heading turns through the circle (a dead or stuck sensor, or
    iron that swamps the Earth's field); None when they turn, or the truth does not. No
    compass layer fits such readings: before round 12 a compass stuck at 123.4 deg was
    "explained by hard_iron" of bx -347, by -622 uT."""
    if series.true_heading_deg is None or len(series) == 0:
        return None
    r_true, _ = _resultant(np.asarray(series.true_heading_deg))
    if r_true > TURNING_RESULTANT:
        return None
    measured = np.asarray(series.heading_deg, dtype=float)
    values = np.unique(measured)
    tail = (
        "while the true heading turns through the circle: a dead or stuck sensor (or iron"
        " that swamps the Earth's field), not a compass effect; no effect is fitted"
    )
    if values.size == 1:
        return f"the compass readings never change (every bearing {values[0]:g} deg) {tail}"
    r_measured, mean_deg = _resultant(measured)
    if r_measured > STUCK_RESULTANT:
        spread_deg = math.degrees(math.sqrt(-2.0 * math.log(r_measured)))
        return (
            f"the compass does not turn with the robot: its {values.size} distinct readings"
            f" stay around {mean_deg:.1f} deg (circular standard deviation {spread_deg:.1f}"
            f" deg) {tail}"
        )
    return None


def layout_for(
    real: HeadingSeries, inclination_deg: float = 66.0, horizontal_field_ut: float = 19.0
) -> CompassLayout:
    t_s = np.asarray(real.t_s, dtype=float)
    dt_s = float(np.median(np.diff(t_s))) if t_s.size > 1 else 1.0
    return CompassLayout(
        dt_s,
        float(t_s[-1] - t_s[0]) if t_s.size else 0.0,
        real.field_ut is not None and bool(np.all(np.isfinite(real.field_ut))),
        inclination_deg,
        horizontal_field_ut,
    )


# --- battery ----------------------------------------------------------------------------------


Design = tuple[np.ndarray, np.ndarray]


def design(series: HeadingSeries, layout: CompassLayout) -> Design:
    """Regressor matrices of a series: heading error (module doc) and log field magnitude
    (1, cos h, sin h). They depend only on the true heading, pitch, roll and turn rate, which
    no compass layer changes, so a simulation fit computes them once per baseline run."""
    assert series.true_heading_deg is not None
    heading_deg = np.asarray(series.true_heading_deg, dtype=float)
    heading_rad = np.radians(heading_deg)
    tilt_error_deg = wrap180(
        tilted_heading_deg(heading_deg, series.pitch_deg, series.roll_deg, layout.inclination_deg)
        - heading_deg
    )
    one, cos1, sin1 = np.ones(heading_deg.size), np.cos(heading_rad), np.sin(heading_rad)
    heading_design = np.column_stack(
        [
            one,
            cos1,
            sin1,
            np.cos(2 * heading_rad),
            np.sin(2 * heading_rad),
            tilt_error_deg,
            turn_rate_dps(series),
        ]
    )
    return heading_design, np.column_stack([one, cos1, sin1])


def _lsq(design_matrix: np.ndarray, target: np.ndarray) -> np.ndarray:
    # Normal equations: the 7x7 system is well conditioned for a log that turns through
    # every heading, and ~50x faster than an SVD on thousands of rows.
    try:
        return np.asarray(
            np.linalg.solve(design_matrix.T @ design_matrix, design_matrix.T @ target)
        )
    except np.linalg.LinAlgError:
        return np.asarray(np.linalg.lstsq(design_matrix, target, rcond=None)[0])


def regression(
    series: HeadingSeries, layout: CompassLayout, designs: Design | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """(coefficients, residuals) of the joint heading-error regression (module doc)."""
    heading_design = (designs or design(series, layout))[0]
    error_deg = heading_error_deg(series)
    coef = _lsq(heading_design, error_deg)
    return coef, error_deg - heading_design @ coef


def residual_trend(series: HeadingSeries, resid_deg: np.ndarray) -> float:
    """The least-squares slope of the regression's residual against time, in degrees per
    100 s: a compass bias that drifts over the log (no compass layer makes one; before
    round 12 a bias drifting 0 -> 4 deg was "explained by declination", closure 0.53, with
    most of the held-out part's offset left)."""
    t_s = np.asarray(series.t_s, dtype=float)
    if t_s.size < 3:
        return 0.0
    centred_s = t_s - t_s.mean()
    denominator = float(centred_s @ centred_s)
    if denominator <= 0.0:
        return 0.0
    return float(centred_s @ (resid_deg - resid_deg.mean())) / denominator * 100.0


def battery(
    series: HeadingSeries, layout: CompassLayout, designs: Design | None = None
) -> dict[Cell, float]:
    """The compass cells of one series (degrees, seconds, log units)."""
    designs = designs or design(series, layout)
    coef, resid_deg = regression(series, layout, designs)
    out = {
        Cell("heading_mean", AXIS, "all"): float(coef[0]),
        Cell("harmonic_cos", AXIS, "1/turn"): float(coef[1]),
        Cell("harmonic_sin", AXIS, "1/turn"): float(coef[2]),
        Cell("harmonic_cos", AXIS, "2/turn"): float(coef[3]),
        Cell("harmonic_sin", AXIS, "2/turn"): float(coef[4]),
        Cell("tilt_gain", AXIS, "pitch/roll"): float(coef[5]),
        Cell("lag_s", AXIS, "turn rate"): float(-coef[6]),
        Cell("residual_log_std", AXIS, "all"): float(np.log(max(np.std(resid_deg), 1e-6))),
        Cell("residual_trend", AXIS, "deg/100 s"): residual_trend(series, resid_deg),
    }
    if layout.has_field:
        if series.field_ut is None:
            raise ConfigError("baseline heading series lacks the field magnitude the real has")
        field_coef = _lsq(designs[1], np.log(np.maximum(series.field_ut, 1e-9)))
        # in degree-equivalents (rad * 180/pi), so a hard iron moves its field cells and its
        # heading cells on one scale
        out[Cell("field_harmonic_cos", AXIS, "1/turn")] = float(math.degrees(field_coef[1]))
        out[Cell("field_harmonic_sin", AXIS, "1/turn")] = float(math.degrees(field_coef[2]))
    return out


# --- null from one or few baseline logs -------------------------------------------------------


def block_bootstrap(
    series: Sequence[HeadingSeries],
    n_out: int,
    rng: np.random.Generator,
    block_s: float,
    template: HeadingSeries,
) -> list[HeadingSeries]:
    """Replicates on ``template``'s times made of circular blocks of ``block_s`` taken jointly
    (true heading, measured heading, pitch, roll, field, turn rate) from the given series:
    the error stays paired with the heading and tilt it belongs to."""
    if not series:
        raise ConfigError("block bootstrap needs at least one baseline heading series")
    n_samples = len(template)
    block_len = max(
        2, min(n_samples, round(block_s / max(float(np.median(np.diff(template.t_s))), 1e-9)))
    )
    has_field = all(s.field_ut is not None for s in series)
    out = []
    for _ in range(n_out):
        pieces: dict[str, list[np.ndarray]] = {
            k: [] for k in ("heading", "true", "pitch", "roll", "field", "rate")
        }
        filled = 0
        while filled < n_samples:
            source = series[int(rng.integers(len(series)))]
            n_take = min(block_len, n_samples - filled)
            index = (int(rng.integers(len(source))) + np.arange(n_take)) % len(source)
            pieces["heading"].append(np.asarray(source.heading_deg)[index])
            pieces["true"].append(np.asarray(source.true_heading_deg)[index])
            pieces["pitch"].append(np.asarray(source.pitch_deg)[index])
            pieces["roll"].append(np.asarray(source.roll_deg)[index])
            pieces["rate"].append(turn_rate_dps(source)[index])
            if has_field:
                pieces["field"].append(np.asarray(source.field_ut)[index])
            filled += n_take
        joined = {k: np.concatenate(v) if v else None for k, v in pieces.items()}
        out.append(
            HeadingSeries(
                t_s=np.asarray(template.t_s, dtype=float),
                heading_deg=joined["heading"],  # type: ignore[arg-type]
                pitch_deg=joined["pitch"],  # type: ignore[arg-type]
                roll_deg=joined["roll"],  # type: ignore[arg-type]
                true_heading_deg=joined["true"],
                field_ut=joined["field"],
                extra={"rate_dps": joined["rate"]},  # type: ignore[dict-item]
            )
        )
    return out


# --- fits -------------------------------------------------------------------------------------


def _coef_diff(
    real: HeadingSeries, baseline: Sequence[HeadingSeries], layout: CompassLayout
) -> tuple[dict[Cell, float], dict[Cell, float]]:
    """Real minus mean baseline, per cell, and the baseline's prediction spread."""
    real_cells = battery(real, layout)
    run_cells = [battery(s, layout) for s in baseline]
    n_runs = len(run_cells)
    diff = {
        c: real_cells[c] - float(np.mean([cells[c] for cells in run_cells])) for c in real_cells
    }
    se = {
        c: max(float(np.std([cells[c] for cells in run_cells], ddof=1)), SD_FLOOR)
        * math.sqrt(1 + 1 / n_runs)
        for c in real_cells
    }
    return diff, se


def _refine(
    make: Callable[[np.ndarray], Any],
    params0: np.ndarray,
    name: str,
    real: HeadingSeries,
    baseline: Sequence[HeadingSeries],
    layout: CompassLayout,
    after: Sequence[Any] = (),
) -> np.ndarray:
    """Simulation fit: parameters whose effect, added to every baseline run (and followed by
    the layers ``after`` it, as the model applies them), brings the mean of the fingerprint
    cells to the real log's (in null-spread units). Starts from the linear estimate; corrects
    its small-angle bias for strong effects."""
    from scipy.optimize import minimize

    fingerprint = EFFECTS[name].fingerprint
    cells = [Cell(k[0], AXIS, k[1]) for k in fingerprint if isinstance(k, tuple)]
    real_cells = battery(real, layout)
    cells = [c for c in cells if c in real_cells]
    run_cells = [battery(s, layout) for s in baseline]
    spread = np.array(
        [max(float(np.std([run[c] for run in run_cells], ddof=1)), SD_FLOOR) for c in cells]
    )
    target = np.array([real_cells[c] for c in cells])
    rng = np.random.default_rng(0)  # the compass layers fitted here are deterministic
    designs = [design(s, layout) for s in baseline]

    def loss(params: np.ndarray) -> float:
        try:
            layer = make(params)
        except ConfigError:
            return 1e12
        values = []
        for run, run_design in zip(baseline, designs, strict=True):
            run = layer.apply(run, rng)
            for later in after:
                run = later.apply(run, rng)
            values.append(battery(run, layout, run_design))
        mean = np.array([np.mean([value[c] for value in values]) for c in cells])
        return float(np.sum(((mean - target) / spread) ** 2))

    result = minimize(loss, params0, method="Nelder-Mead", options={"maxiter": 60, "xatol": 1e-3})
    return np.asarray(result.x, dtype=float) if result.fun <= loss(params0) else params0


def fit_declination(
    real: HeadingSeries,
    baseline: Sequence[HeadingSeries],
    layout: CompassLayout,
    after: Sequence[Any] = (),
) -> Fit | None:
    """The compass reads heading - declination: declination = -(mean error difference)
    (the layers ``after`` it do not move a mean)."""
    diff, se = _coef_diff(real, baseline, layout)
    cell = Cell("heading_mean", AXIS, "all")
    return Fit(Declination(declination_deg=round(-diff[cell], 3)), {"declination_deg": se[cell]})


def fit_hard_iron(
    real: HeadingSeries,
    baseline: Sequence[HeadingSeries],
    layout: CompassLayout,
    after: Sequence[Any] = (),
) -> Fit | None:
    """Small-angle: error = -(by cos h + bx sin h) / H rad; then a simulation fit."""
    diff, se = _coef_diff(real, baseline, layout)
    horizontal_ut = layout.horizontal_field_ut
    rad_per_deg = math.pi / 180.0
    cos1, sin1 = Cell("harmonic_cos", AXIS, "1/turn"), Cell("harmonic_sin", AXIS, "1/turn")
    b0_ut = np.array(
        [-horizontal_ut * diff[sin1] * rad_per_deg, -horizontal_ut * diff[cos1] * rad_per_deg]
    )

    def make(b_ut: np.ndarray) -> HardIron:
        if math.hypot(*b_ut) >= horizontal_ut:  # beyond the bound: the refinement stays in
            raise ConfigError("hard iron beyond the horizontal field")
        return HardIron(
            bx_ut=float(b_ut[0]), by_ut=float(b_ut[1]), horizontal_field_ut=horizontal_ut
        )

    b_ut = _refine(make, b0_ut, "hard_iron", real, baseline, layout, after)
    if math.hypot(*b_ut) >= horizontal_ut:
        # A hard iron as strong as the horizontal field keeps the heading from turning
        # through the circle (the field the compass sees never points behind it): no such
        # layer explains a compass that turns, and a compass that does not is named in
        # CompassPipeline.same_observables (a stuck one was "hard iron" of 712 uT).
        raise ConfigError(
            f"hard iron |b| {math.hypot(*b_ut):.1f} uT is not below the horizontal field"
            f" {horizontal_ut:g} uT: with it the heading would not turn through the circle"
        )
    return Fit(
        HardIron(
            bx_ut=round(float(b_ut[0]), 4),
            by_ut=round(float(b_ut[1]), 4),
            horizontal_field_ut=horizontal_ut,
        ),
        {
            "bx_ut": horizontal_ut * se[sin1] * rad_per_deg,
            "by_ut": horizontal_ut * se[cos1] * rad_per_deg,
        },
    )


def fit_soft_iron(
    real: HeadingSeries,
    baseline: Sequence[HeadingSeries],
    layout: CompassLayout,
    after: Sequence[Any] = (),
) -> Fit | None:
    """Small-angle: error = -k sin(2h + 2a) rad; (k, a) and (-k, a + 90) are the same layer,
    so k >= 0 is reported; then a simulation fit."""
    diff, se = _coef_diff(real, baseline, layout)
    rad_per_deg = math.pi / 180.0
    cos2, sin2 = Cell("harmonic_cos", AXIS, "2/turn"), Cell("harmonic_sin", AXIS, "2/turn")
    k = math.hypot(diff[cos2], diff[sin2]) * rad_per_deg
    axis_deg = 0.5 * math.degrees(math.atan2(-diff[cos2], -diff[sin2]))
    if k < 1e-5:
        return None
    if k >= 0.9:  # the layer's own bound (SoftIron: |k| < 0.9)
        raise ConfigError(f"soft iron k {k:.2f} is not below 0.9, the layer's bound")

    def make(params: np.ndarray) -> SoftIron:
        return SoftIron(k=float(np.clip(params[0], -0.85, 0.85)), axis_deg=float(params[1]))

    params = _refine(
        make, np.array([min(k, 0.85), axis_deg]), "soft_iron", real, baseline, layout, after
    )
    k, axis_deg = float(np.clip(params[0], -0.85, 0.85)), float(params[1])
    if k < 0:
        k, axis_deg = -k, axis_deg + 90.0
    axis_deg = (axis_deg + 90.0) % 180.0 - 90.0
    se_k = 0.5 * (se[cos2] + se[sin2]) * rad_per_deg
    return Fit(
        SoftIron(k=round(k, 5), axis_deg=round(axis_deg, 2)),
        {"k": se_k, "axis_deg": math.degrees(0.5 * se_k / max(k, 1e-9))},
    )


def fit_tilt(
    real: HeadingSeries,
    baseline: Sequence[HeadingSeries],
    layout: CompassLayout,
    after: Sequence[Any] = (),
) -> Fit | None:
    """The tilt gain difference is the uncompensated fraction (at the layout's inclination)."""
    diff, se = _coef_diff(real, baseline, layout)
    cell = Cell("tilt_gain", AXIS, "pitch/roll")
    if diff[cell] > 1.0 + 3.0 * se[cell]:  # more than a compass without tilt compensation
        raise ConfigError(
            f"tilt gain difference {diff[cell]:.2f} is beyond 1 (a compass with no tilt"
            " compensation at all)"
        )
    fraction0 = float(np.clip(diff[cell], 0.0, 1.0))
    if fraction0 <= 0.0:
        return None
    inclination_deg = layout.inclination_deg

    def make(params: np.ndarray) -> Tilt:
        return Tilt(fraction=float(np.clip(params[0], 0.0, 1.0)), inclination_deg=inclination_deg)

    fraction = float(
        np.clip(
            _refine(make, np.array([fraction0]), "tilt", real, baseline, layout, after)[0],
            0.0,
            1.0,
        )
    )
    return Fit(
        Tilt(fraction=round(fraction, 4), inclination_deg=inclination_deg), {"fraction": se[cell]}
    )


class _FastLag:
    """The :class:`HeadingLag` layer's recursion as a linear filter on the unwrapped heading
    (the same values while a step of the heading and the lag stay under 180 deg, and the
    samples evenly spaced): the simulation fit of the lag applies it hundreds of times."""

    def __init__(self, tau_s: float) -> None:
        if not tau_s > 0.0:
            raise ConfigError("heading lag tau must be > 0")
        self.layer = HeadingLag(tau_s=tau_s)

    def apply(self, series: HeadingSeries, rng: np.random.Generator) -> HeadingSeries:
        from scipy.signal import lfilter

        t_s = np.asarray(series.t_s, dtype=float)
        steps_s = np.diff(t_s)
        if steps_s.size == 0 or np.ptp(steps_s) > 1e-6 * max(float(np.median(steps_s)), 1e-9):
            return self.layer.apply(series, rng)
        gain = -math.expm1(-float(np.median(steps_s)) / self.layer.tau_s)
        x_deg = np.degrees(np.unwrap(np.radians(np.asarray(series.heading_deg, dtype=float))))
        y_deg = lfilter([gain], [1.0, gain - 1.0], x_deg, zi=[(1.0 - gain) * x_deg[0]])[0]
        return series.with_(heading_deg=wrap360(y_deg))


def fit_heading_lag(
    real: HeadingSeries,
    baseline: Sequence[HeadingSeries],
    layout: CompassLayout,
    after: Sequence[Any] = (),
) -> Fit | None:
    """Lags add at low frequency (group delays of cascaded first-order filters sum), so the
    extra lag is about the lag-cell difference; that linear estimate is the start of a
    simulation fit. The linear estimate alone is unbiased only for turn rates that change
    slowly against tau: on the robot's drives (straight legs, turns in place whose rate
    steps) it sized a 0.5 s lag as 0.30 s and 1.0 s as 0.36 s (outside audit, round 12), so
    the lag is refined as the other layers are, with the layer added to every baseline run."""
    diff, se = _coef_diff(real, baseline, layout)
    cell = Cell("lag_s", AXIS, "turn rate")
    lag_s = diff[cell]
    if lag_s <= 1e-3:
        return None
    # The layer's exact discretisation y_k = y_(k-1) + (1 - phi)(x_k - y_(k-1)) lags a ramp
    # by dt phi / (1 - phi), not tau: invert that (tau = dt / ln(1 + dt / lag)).
    dt_s = layout.dt_s
    tau0_s = dt_s / math.log1p(dt_s / lag_s)
    dtau_dlag = (
        dt_s * dt_s / (lag_s * (lag_s + dt_s) * math.log1p(dt_s / lag_s) ** 2)
    )  # d tau / d lag
    tau_s = float(
        _refine(
            lambda p: _FastLag(float(p[0])), np.array([tau0_s]), "heading_lag", real,
            baseline, layout, after,
        )[0]
    )  # fmt: skip
    # the standard error scales with the refined tau as the linear one does
    se_tau_s = se[cell] * dtau_dlag * tau_s / tau0_s
    return Fit(HeadingLag(tau_s=round(tau_s, 4)), {"tau_s": se_tau_s})


# The compass effects: fitter and fingerprint (the (statistic, scale) cells each moves: what
# ranks candidates and what a simulation fit matches). A new effect is one row here (the
# order is the default candidates' order).
EFFECTS: dict[str, EffectFitter[HeadingSeries, CompassLayout]] = {
    "declination": EffectFitter(fit_declination, (("heading_mean", "all"),)),
    "hard_iron": EffectFitter(
        fit_hard_iron,
        (
            ("harmonic_cos", "1/turn"),
            ("harmonic_sin", "1/turn"),
            ("field_harmonic_cos", "1/turn"),
            ("field_harmonic_sin", "1/turn"),
        ),
    ),
    "soft_iron": EffectFitter(
        fit_soft_iron, (("harmonic_cos", "2/turn"), ("harmonic_sin", "2/turn"))
    ),
    "tilt": EffectFitter(fit_tilt, (("tilt_gain", "pitch/roll"),)),
    "heading_lag": EffectFitter(fit_heading_lag, (("lag_s", "turn rate"),)),
}
COMPASS_CANDIDATES = tuple(EFFECTS)
# The fitters again, taking the layers applied after the fitted one (the joint refit of
# several selected layers: CompassPipeline.report_fits)
JOINT_FITTERS: dict[str, Callable[..., Fit | None]] = {
    "declination": fit_declination,
    "hard_iron": fit_hard_iron,
    "soft_iron": fit_soft_iron,
    "tilt": fit_tilt,
    "heading_lag": fit_heading_lag,
}


def apply_fits(
    fits: Sequence[Fit], runs: Sequence[HeadingSeries], rng: np.random.Generator
) -> list[HeadingSeries]:
    """Each run with the fitted compass layers applied in order."""
    out = []
    for run in runs:
        for fit in fits:
            run = fit.effect.apply(run, rng)
        out.append(run)
    return out


# --- the pipeline -----------------------------------------------------------------------------


@dataclass(frozen=True)
class CompassOptions(PipelineOptions):
    """As :class:`x6wd.gap.diagnose.Options`, for the compass: at most two layers, and the
    field the fits assume (inclination, deg; horizontal field, µT)."""

    candidates: tuple[str, ...] = COMPASS_CANDIDATES
    max_effects: int = 2
    inclination_deg: float = 66.0
    horizontal_field_ut: float = 19.0

    def __post_init__(self) -> None:
        super().__post_init__()
        unknown = sorted(set(self.candidates) - set(COMPASS_CANDIDATES))
        if unknown:
            raise ConfigError(f"compass candidates {unknown}: known {list(COMPASS_CANDIDATES)}")


class CompassPipeline(Pipeline[HeadingSeries, CompassLayout, CompassDiagnosis]):
    """The compass half's plug-ins: its regression battery, heading windows and joint block
    bootstrap. The compass layers are deterministic (no fresh draws) and at most two are
    selected (no leave-one-out); a layer refitted in a later round is reported with the
    selection's closure."""

    label = "compass: "
    refits_take_selection_closure = True
    closure_of_reported = True

    def __init__(
        self, options: CompassOptions, rng: np.random.Generator, progress: Progress | None = None
    ) -> None:
        super().__init__(EFFECTS, options, rng, progress)
        self.compass_options = options

    def check(self, real: HeadingSeries, baseline: Sequence[HeadingSeries]) -> None:
        if real.true_heading_deg is None or len(real) < 100:
            raise ConfigError("compass diagnosis needs >= 100 samples with a true heading")
        if not baseline:
            raise ConfigError("compass diagnosis needs baseline heading series")

    def same_observables(
        self, real: HeadingSeries, baseline: Sequence[HeadingSeries]
    ) -> tuple[HeadingSeries, list[HeadingSeries], list[str]]:
        """The samples with a non-finite value in any column left out (of the real log and of
        each baseline run), and said: one NaN made every regression of the log NaN before
        round 12 (a 3-degree hard iron read as no gap)."""
        real_kept, n_real = finite_samples(real)
        runs_kept = [finite_samples(s) for s in baseline]
        if len(real_kept) < 100:
            raise ConfigError(
                f"compass diagnosis needs >= 100 samples with a true heading; {n_real} of"
                f" {len(real)} have a value that is not finite (NaN or infinite)"
            )
        not_turning = not_turning_text(real_kept)
        if not_turning is not None:
            raise ConfigError(not_turning)
        notes = []
        if n_real:
            notes.append(
                f"compass: {n_real} of {len(real)} samples of the real log had a value that is"
                " not finite (NaN or infinite) and were left out"
            )
        n_runs = sum(n for _, n in runs_kept)
        if n_runs:
            notes.append(
                f"compass: {n_runs} sample{'s' if n_runs > 1 else ''} of the baseline runs had"
                " a value that is not finite (NaN or infinite) and"
                f" {'were' if n_runs > 1 else 'was'} left out"
            )
        return real_kept, [s for s, _ in runs_kept], notes

    def layout_for(self, real: HeadingSeries, baseline: Sequence[HeadingSeries]) -> CompassLayout:
        opt = self.compass_options
        layout = layout_for(real, opt.inclination_deg, opt.horizontal_field_ut)
        if layout.has_field and any(s.field_ut is None for s in baseline):
            layout = dataclasses.replace(layout, has_field=False)
        return layout

    def input_notes(self, real: HeadingSeries, layout: CompassLayout) -> list[str]:
        # Harmonics need the log to turn through the circle: say so when it did not (a square
        # mission visits four headings), because the null then has no power, not no gap.
        sectors = np.bincount(
            (wrap360(np.asarray(real.true_heading_deg)) // 45.0).astype(int) % 8, minlength=8
        )
        if np.count_nonzero(sectors >= 0.02 * len(real)) < 6:
            return [
                "compass: the log covers few headings (fewer than 6 of 8 45-degree sectors), "
                "so the harmonics are poorly determined and the test has little power"
            ]
        return []

    def battery(self, series: HeadingSeries, layout: CompassLayout) -> Battery:
        return battery(series, layout)

    def window(self, series: HeadingSeries, t0_s: float, t1_s: float) -> HeadingSeries:
        return hwindow(series, t0_s, t1_s)

    def block_bootstrap(
        self, runs: Sequence[HeadingSeries], n_out: int, block_s: float, template: HeadingSeries
    ) -> list[HeadingSeries]:
        return block_bootstrap(runs, n_out, self.rng, block_s, template)

    def bootstrap_note(self, n_logs: int, block_s: float) -> str:
        return (
            f"compass baseline: {n_logs} log(s), null from a circular block bootstrap "
            f"({self.options.replicates} replicates, blocks of {block_s:.0f} s)"
        )

    def apply_fits(self, fits: Sequence[Fit], runs: Sequence[HeadingSeries]) -> list[HeadingSeries]:
        return apply_fits(fits, runs, self.rng)

    def new_outcome(self, **fields: Any) -> CompassDiagnosis:
        return CompassDiagnosis(**fields)

    def report_fits(
        self, selected: list[Fit], scored: dict[str, Candidate], outcome: CompassDiagnosis
    ) -> list[Fit]:
        """Several selected layers refitted jointly on the fit part, each on top of the
        baseline plus the others, pass after pass (backfitting) until none moves by more than
        ``JOINT_TOL_SE`` of a standard error (at most ``JOINT_PASSES``); the selection's
        closure is then theirs. Before 2026-12-06 each was fitted on top of those selected
        before it only: the first, fitted alone, took up part of the second's signature (soft
        iron k 0.08 at 30 deg beside a 0.4 s lag: k 0.0732 at 32.8 deg, 37-40 standard errors
        off), and a re-run with its effects.toml found soft iron and lag again."""
        if len(selected) < 2:
            return selected
        split, fits = self.split, list(selected)
        passes = 0
        while passes < JOINT_PASSES:
            passes += 1
            moved = False
            for i, fit in enumerate(fits):
                # the layers before it under it, those after it over it, as the model applies them
                runs = [self.window(s, *split.fit_s) for s in self.apply_fits(fits[:i], self.runs)]
                after = [later.effect for later in fits[i + 1 :]]
                try:
                    refit = JOINT_FITTERS[fit.name](split.real_fit, runs, split.fit_layout, after)
                except ConfigError:  # beyond the layer's bounds: the fit in turn stays
                    refit = None
                if refit is not None:
                    moved = moved or _moved(fit, refit)
                    fits[i] = refit
            if not moved:
                break
        outcome.notes.append(
            f"compass: the {len(fits)} selected layers were refitted on the fit part each on"
            f" top of the others ({passes} passes), and the closure is theirs; fitted in turn,"
            " each on those before it: " + "; ".join(f"{f.name} {f.params}" for f in selected)
        )
        return fits


def _moved(old: Fit, new: Fit) -> bool:
    """Whether a parameter of ``new`` is more than ``JOINT_TOL_SE`` standard errors from
    ``old``'s (a parameter without a finite positive error: any change)."""
    for key, value in new.params.items():
        before = old.params.get(key)
        if not isinstance(value, int | float) or not isinstance(before, int | float):
            continue
        se = new.se.get(key, math.nan)
        tol = JOINT_TOL_SE * se if math.isfinite(se) and se > 0 else 0.0
        if abs(float(value) - float(before)) > tol:
            return True
    return False


def diagnose_compass(
    real: HeadingSeries,
    baseline: Sequence[HeadingSeries],
    rng: np.random.Generator,
    options: CompassOptions | None = None,
    progress: Progress | None = None,
) -> CompassDiagnosis:
    """Where the heading gap lies, which compass effect explains it, how far it closes."""
    return CompassPipeline(options or CompassOptions(), rng, progress).run(real, baseline)


def compass_report_dict(diagnosis: CompassDiagnosis) -> dict[str, Any]:
    """The compass half in report.json's shape (keys as the GPS side's)."""
    return pipeline.report_dict(diagnosis)


def compass_verdict_text(diagnosis: CompassDiagnosis) -> str:
    if not diagnosis.significant:
        return "compass: no significant gap"
    if diagnosis.explained:
        names = " + ".join(f.name for f in diagnosis.selected)
        return f"compass: gap explained by {names} (held-out closure {diagnosis.closure:.2f})"
    return "compass: gap not explained by any known compass effect"


# --- the simulator's heading series (baseline, tests, benchmark) ------------------------------


def drive_track(
    duration_s: float,
    dt_s: float,
    rng: np.random.Generator,
    *,
    slope: tuple[float, float] = (0.04, -0.03),
    bump_deg: float = 3.0,
    bump_tau_s: float = 4.0,
) -> HeadingSeries:
    """A robot's true attitude: weaving circles (turn rate 4 + 30 sin(2 pi t / 97 s) deg/s,
    so it turns both ways, passes every heading many times and its turn rate is not
    constant, which keeps the lag apart from the mean) on a plane of gradients ``slope``
    (dz/dE, dz/dN) with rough ground (Gauss-Markov pitch/roll bumps, ``bump_deg``,
    ``bump_tau_s``), so pitch/roll vary independently of heading. Measured = true."""
    from sim_backend.effects import gauss_markov_noise
    from sim_backend.vehicle import Terrain

    t_s = np.arange(0.0, duration_s + 0.5 * dt_s, dt_s)
    rate_dps = 4.0 + 30.0 * np.sin(2 * np.pi * t_s / 97.0) + 8.0 * np.sin(2 * np.pi * t_s / 23.0)
    heading_deg = wrap360(
        np.concatenate(([0.0], np.cumsum(0.5 * (rate_dps[1:] + rate_dps[:-1]) * dt_s)))
    )
    terrain = Terrain(slope[0], slope[1])
    pitch_roll_deg = np.array([terrain.attitude_deg(float(heading)) for heading in heading_deg])
    bumps = gauss_markov_noise(t_s, bump_deg, bump_tau_s, rng, 2)
    return HeadingSeries(
        t_s=t_s,
        heading_deg=heading_deg.copy(),
        pitch_deg=pitch_roll_deg[:, 0] + bumps[0],
        roll_deg=pitch_roll_deg[:, 1] + bumps[1],
        true_heading_deg=heading_deg,
    )


def simulate_compass(
    truth: HeadingSeries,
    rng: np.random.Generator,
    field_model: MagneticField | None = None,
    errors: CompassErrors | None = None,
    device_heading: Callable[[float, float, float], float] | None = None,
) -> HeadingSeries:
    """The project's CMPS10 emulation (:class:`sim_backend.compass.SimCmps10`) driven along a
    true attitude: measured magnetic bearing as the registers show it (tenths of a degree),
    pitch/roll whole degrees, and |B| of the raw magnetometer (µT). ``device_heading`` maps
    the true (heading, pitch, roll) to the heading handed to the device (a scenario's tilt
    layers, as ``x6wd sim`` applies them); None: the true heading."""
    errs = errors or CompassErrors(noise_ut=0.3)
    device = SimCmps10(
        field_model=field_model or MagneticField(),
        errors=errs,
        rng=rng if errs.noise_ut > 0 else None,
    )
    assert truth.true_heading_deg is not None
    n_samples = len(truth)
    bearing_deg, field_ut = np.empty(n_samples), np.empty(n_samples)
    t_s = np.asarray(truth.t_s, dtype=float)
    heading_deg, pitch_deg, roll_deg = (
        np.asarray(a, dtype=float)
        for a in (truth.true_heading_deg, truth.pitch_deg, truth.roll_deg)
    )
    for i in range(n_samples):
        device_heading_deg = (
            float(heading_deg[i])
            if device_heading is None
            else device_heading(heading_deg[i], pitch_deg[i], roll_deg[i])
        )
        device.set_state(float(t_s[i]), device_heading_deg, float(pitch_deg[i]), float(roll_deg[i]))
        bearing_deg[i] = device.bearing_deg
        field_ut[i] = float(np.linalg.norm(device._mag_body))
    return truth.with_(
        heading_deg=np.round(bearing_deg, 1) % 360.0,
        pitch_deg=np.clip(np.round(pitch_deg), -85, 85),
        roll_deg=np.clip(np.round(roll_deg), -85, 85),
        field_ut=field_ut,
    )


# --- reading logs -----------------------------------------------------------------------------


def read_heading_truth(path: str | Path) -> tuple[np.ndarray, np.ndarray] | None:
    """(t_s, true heading deg) from a CSV with ``t_s``/``time`` and ``heading_deg`` columns
    (``x6wd sim``'s truth.csv); None when the file has no heading column
    (:func:`read_heading_truth_notes` also says what was set aside)."""
    return read_heading_truth_notes(path)[0]


def read_heading_truth_notes(
    path: str | Path,
) -> tuple[tuple[np.ndarray, np.ndarray] | None, list[str]]:
    """:func:`read_heading_truth` and notes on its rows: those whose time or heading is not a
    finite number are left out and counted; rows out of time order are sorted (before round
    12 np.interp was fed them unsorted: headings up to 12 deg wrong, a reversed file none)
    and a time given twice keeps its first row; both counted."""
    import csv

    csv_path = Path(path)
    try:
        rows = list(csv.reader(read_text_bounded(csv_path).splitlines()))
    except (OSError, UnicodeDecodeError):
        return None, []
    if not rows:
        return None, []
    header = [c.strip().lower() for c in rows[0]]
    t_col = next((header.index(k) for k in ("t_s", "time", "t") if k in header), None)
    heading_col = next((header.index(k) for k in ("heading_deg", "heading") if k in header), None)
    if t_col is None or heading_col is None:
        return None, []
    pairs = []
    n_rows = n_bad = 0
    for r in rows[1:]:
        if not any(c.strip() for c in r):
            continue  # a blank line is no row
        n_rows += 1
        try:  # a row whose time or heading is not a finite number is not a truth
            pair = [float(r[t_col]), float(r[heading_col])]
        except (IndexError, ValueError):
            n_bad += 1
            continue
        if math.isfinite(pair[0]) and math.isfinite(pair[1]):
            pairs.append(pair)
        else:
            n_bad += 1
    notes = []
    name = csv_path.name
    if n_bad:
        notes.append(
            f"{n_bad} of {n_rows} {name} rows were left out (a time or heading that is not a"
            " finite number)"
        )
    table = np.array(pairs).reshape(-1, 2)
    if table.shape[0]:
        times = table[:, 0]
        out_of_order = int(np.count_nonzero(times[1:] <= np.maximum.accumulate(times)[:-1]))
        order = np.argsort(times, kind="stable")
        table = table[order]
        first = np.concatenate(([True], np.diff(table[:, 0]) > 0))
        repeated = int(np.count_nonzero(~first))
        table = table[first]
        if out_of_order:
            notes.append(
                f"{out_of_order} {name} rows out of time order were sorted by time"
                + (f" ({repeated} with a time already given, left out)" if repeated else "")
            )
    if table.shape[0] < 2:
        return None, notes
    return (table[:, 0], table[:, 1]), notes


def _interp_heading(
    t_s: np.ndarray, truth_t_s: np.ndarray, truth_heading_deg: np.ndarray
) -> np.ndarray:
    """Heading interpolated along the shorter way round (unwrap, interpolate, wrap)."""
    return wrap360(np.interp(t_s, truth_t_s, np.degrees(np.unwrap(np.radians(truth_heading_deg)))))


HEADING_REFERENCES = {
    "truth": "a heading truth (truth.csv beside the recording, or the truth track's heading"
    " column)",
    "cog": f"the GPS course over ground while moving at >= {COG_MIN_SPEED_MPS:g} m/s",
}
"""The kinds of heading truth a recording is read against (:func:`read_heading_log`)."""


class NoHeadingReference(ConfigError):
    """A recording with compass samples but no heading truth to read them against (the
    message says why): the compass half is not diagnosed, and says so."""


@dataclass(frozen=True)
class HeadingLog:
    """A recording's compass samples with their true heading (``series``), the kind of that
    heading truth (``reference``: a key of :data:`HEADING_REFERENCES`) and notes on what was
    set aside while reading."""

    series: HeadingSeries
    reference: str
    notes: tuple[str, ...] = ()


def _number(value: object) -> float | None:
    """A JSON value as a finite float, or None (null, a string, a boolean, NaN, infinite)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return None
    try:  # an integer beyond a float (a JSON 1 followed by 400 zeros): OverflowError
        number = float(value)
    except OverflowError:
        return None
    return number if math.isfinite(number) else None


def _attitude_sample(
    data: dict[str, Any], t_mono: float
) -> tuple[float, float, float, float, float] | str:
    """(t_s, bearing, pitch, roll, |B| or NaN) of an attitude record's data, or why it is
    left out: a missing, null, non-numeric, non-finite or out-of-range value (a bearing is
    0..360 deg, pitch and roll -90..90 deg). Such a value poisoned every regression of the
    log before round 12 (one NaN in 11,266 hid a 3-degree hard iron)."""
    if "bearing_deg" not in data:
        return "without bearing_deg"
    t_s = _number(data.get("t_s", t_mono))
    if t_s is None:
        return "with a t_s that is not a finite number"
    values = {k: data.get(k, 0.0) for k in ("bearing_deg", "pitch_deg", "roll_deg")}
    for key, value in values.items():
        if isinstance(value, float) and not math.isfinite(value):
            return f"with a {key} that is not finite (NaN or infinite)"
        if isinstance(value, int) and not isinstance(value, bool) and _number(value) is None:
            return f"with a {key} that is not finite (an integer beyond a float)"
        if _number(value) is None:
            return f"with a {key} that is not a number ({_json_text(value)})"
    bearing_deg, pitch_deg, roll_deg = (float(v) for v in values.values())
    if not 0.0 <= bearing_deg <= 360.0:
        return "with a bearing_deg outside 0..360 deg"
    if not (abs(pitch_deg) <= 90.0 and abs(roll_deg) <= 90.0):
        return "with a pitch_deg or roll_deg outside -90..90 deg"
    mag_ut = data.get("mag_ut")
    field_ut = math.nan
    if isinstance(mag_ut, list) and len(mag_ut) == 3:
        parts = [_number(v) for v in mag_ut]
        if all(p is not None for p in parts):
            field_ut = float(np.linalg.norm([float(p) for p in parts if p is not None]))
    return t_s, bearing_deg, pitch_deg, roll_deg, field_ut


def _json_text(value: object) -> str:
    """A JSON value as the recording spells it (null, true, "a string")."""
    import json

    return json.dumps(value)[:20]


def read_heading_series(
    recording: str | Path,
    truth: str | Path | None = None,
    min_speed_mps: float = COG_MIN_SPEED_MPS,
    reference: str | None = None,
) -> HeadingSeries | None:
    """The series of :func:`read_heading_log` (None when it reads none)."""
    try:
        log = read_heading_log(recording, truth, min_speed_mps, reference)
    except NoHeadingReference:
        return None
    return None if log is None else log.series


def read_heading_log(
    recording: str | Path,
    truth: str | Path | None = None,
    min_speed_mps: float = COG_MIN_SPEED_MPS,
    reference: str | None = None,
) -> HeadingLog | None:
    """The compass samples of an x6wd recording with their true heading, or None when the
    recording has no attitude records or no heading truth of the kind asked for.

    Truth (``reference`` None): ``truth`` (a CSV with a heading column), else ``truth.csv``
    beside the recording (what ``x6wd sim`` writes), else the GPS course over ground of the
    recording's fixes while moving at >= ``min_speed_mps``: only attitude samples within
    COG_MAX_GAP_S of such a fix are kept. ``reference="truth"``: only the first two;
    ``reference="cog"``: only the course over ground (a heading truth beside it is not read).
    COG equals heading only without sideslip, so this truth is noisier (a skid-steer robot
    slips in turns): the baseline logs must be read against the kind of truth the real log
    has (the CLI passes the real log's ``reference``), or their null lacks that noise and the
    real log's shows as a gap (an outside audit, round 12: a -31 deg "declination").
    Attitude records with a value that is not a bearing are left out and counted in
    ``notes`` (:func:`_attitude_sample`); ConfigError when that leaves fewer than 100 of
    100 or more (the log had compass samples, none usable: said, not passed over). So are
    valid fixes whose t_s, speed_mps or course_deg is there but not a finite number (when
    the course is the reference), and truth.csv rows (:func:`read_heading_truth_notes`).
    A heading truth that covers fewer than 100 compass samples gives way to the course over
    ground (``reference`` None, noted); NoHeadingReference (a ConfigError: the CLI's note)
    when ``reference`` is None and neither serves, saying why; None for a ``reference``
    asked for and not there (a baseline log: the caller notes it).
    """
    from x6wd.core.recorder import is_recording, read_recording

    if reference is not None and reference not in HEADING_REFERENCES:
        raise ConfigError(f"heading reference {reference!r}: known {list(HEADING_REFERENCES)}")
    path = Path(recording)
    if not path.is_file() or not is_recording(path):
        return None
    attitude: list[tuple[float, float, float, float, float]] = []
    course: list[tuple[float, float]] = []
    n_attitude = n_fixes = fixes_bad = 0
    top_speed_mps = -math.inf  # of the fixes with a course
    left_out: dict[str, int] = {}  # why -> how many attitude records
    for rec in read_recording(path):
        data = rec.data if isinstance(rec.data, dict) else {}
        if rec.type == "attitude" and data.get("valid", True):
            n_attitude += 1
            sample = _attitude_sample(data, rec.t_mono)
            if isinstance(sample, str):
                left_out[sample] = left_out.get(sample, 0) + 1
            else:
                attitude.append(sample)
        elif rec.type == "fix" and data.get("valid"):
            n_fixes += 1
            raw = {k: data.get(k) for k in ("speed_mps", "course_deg")}
            raw["t_s"] = data.get("t_s", rec.t_mono)
            numbers = {k: _number(v) for k, v in raw.items()}
            if any(n is None and raw[k] is not None for k, n in numbers.items()):
                fixes_bad += 1  # null is no course (at rest); NaN, 1e400, "x" are malformed
                continue
            t_fix_s, speed_mps, course_deg = (
                numbers[k] for k in ("t_s", "speed_mps", "course_deg")
            )
            if t_fix_s is None or speed_mps is None or course_deg is None:
                continue
            top_speed_mps = max(top_speed_mps, speed_mps)
            if speed_mps >= min_speed_mps:
                course.append((t_fix_s, course_deg % 360.0))
    notes = []
    if left_out:
        why = ", ".join(f"{n} {reason}" for reason, n in sorted(left_out.items()))
        notes.append(
            f"{sum(left_out.values())} of {n_attitude} attitude records were left out ({why})"
        )
    if len(attitude) < 100:
        if len(attitude) + sum(left_out.values()) >= 100:  # there were samples: say why
            raise ConfigError(f"{path}: {notes[0]}; fewer than 100 samples remain")
        return None
    table = np.array(sorted(attitude))
    table = table[np.concatenate(([True], np.diff(table[:, 0]) > 0))]
    t_s = table[:, 0]
    fixes_note = (
        f"{fixes_bad} of {n_fixes} fixes were left out of the course over ground (a t_s,"
        " speed_mps or course_deg that is not a finite number)"
    )
    truth_table = None
    truth_name = "truth.csv"
    why_no_truth = f"no {truth_name}"
    if reference != "cog":
        for candidate in (truth, path.parent / "truth.csv"):
            if candidate is None or not Path(candidate).is_file():
                continue
            truth_table, truth_notes = read_heading_truth_notes(candidate)
            truth_name = Path(candidate).name
            if truth_table is not None:
                notes += truth_notes
                break
            why_no_truth = f"{truth_name} has no usable heading column"
    keep = np.zeros(len(t_s), dtype=bool)
    used = None
    if truth_table is not None:
        used = "truth"
        truth_t_s, truth_heading_deg = truth_table
        # different clocks (no overlap): both are taken from their own start
        overlap = not (t_s[-1] < truth_t_s[0] or t_s[0] > truth_t_s[-1])
        t_aligned_s = t_s if overlap else t_s - t_s[0] + truth_t_s[0]
        keep = (t_aligned_s >= truth_t_s[0]) & (t_aligned_s <= truth_t_s[-1])
        true_heading_deg = _interp_heading(t_aligned_s[keep], truth_t_s, truth_heading_deg)
        if np.count_nonzero(keep) < 100:
            span_s = max(0.0, min(t_s[-1], truth_t_s[-1]) - max(t_s[0], truth_t_s[0]))
            if not overlap:
                span_s = min(t_s[-1] - t_s[0], truth_t_s[-1] - truth_t_s[0])
            why_no_truth = (
                f"{truth_name} covers {span_s:.0f} s of the log's {t_s[-1] - t_s[0]:.0f} s"
                f" ({np.count_nonzero(keep)} compass samples, 100 needed)"
            )
            used = None
    if used is None and len(course) >= 10 and reference not in ("truth",):
        course_table = np.array(sorted(course))
        index = np.clip(np.searchsorted(course_table[:, 0], t_s), 1, len(course_table) - 1)
        near = (
            np.minimum(
                np.abs(course_table[index, 0] - t_s), np.abs(course_table[index - 1, 0] - t_s)
            )
            <= COG_MAX_GAP_S
        )
        keep = near & (t_s >= course_table[0, 0]) & (t_s <= course_table[-1, 0])
        true_heading_deg = _interp_heading(t_s[keep], course_table[:, 0], course_table[:, 1])
        if np.count_nonzero(keep) >= 100:
            used = "cog"
            if truth_table is not None or why_no_truth != f"no {truth_name}":
                notes.append(f"{why_no_truth}: read against the GPS course over ground instead")
            if fixes_bad:
                notes.append(fixes_note)
    if used is None:
        if reference is not None:  # a baseline log read by the real log's kind: the caller says
            return None
        if not course:
            cog_why = (
                "no fix with a course over ground"
                if top_speed_mps == -math.inf
                else f"the fixes' speed never reaches {min_speed_mps:g} m/s"
                f" (at most {top_speed_mps:.2g} m/s)"
            )
        elif len(course) < 10:
            cog_why = f"only {len(course)} fixes at >= {min_speed_mps:g} m/s (10 needed)"
        else:
            cog_why = (
                f"only {np.count_nonzero(keep)} compass samples within {COG_MAX_GAP_S:g} s of a"
                f" fix at >= {min_speed_mps:g} m/s (100 needed)"
            )
        if fixes_bad:
            cog_why += f"; {fixes_note}"
        raise NoHeadingReference(
            f"{path}: no heading reference: {why_no_truth} (a heading truth: --truth-track with"
            f" a heading column or truth.csv beside the recording) and {cog_why}"
        )
    table = table[keep]
    field_ut = table[:, 4]
    series = HeadingSeries(
        t_s=table[:, 0] - table[0, 0],
        heading_deg=table[:, 1],
        pitch_deg=table[:, 2],
        roll_deg=table[:, 3],
        true_heading_deg=true_heading_deg,
        field_ut=field_ut if np.all(np.isfinite(field_ut)) else None,
    )
    return HeadingLog(series, used, tuple(notes))


def baseline_along(
    real: HeadingSeries,
    seeds: int,
    base_seed: int = 2000,
    field_model: MagneticField | None = None,
    errors: CompassErrors | None = None,
    device_heading: Callable[[float, float, float], float] | None = None,
) -> list[HeadingSeries]:
    """``seeds`` runs of the CMPS10 emulation (:func:`simulate_compass`, seeds ``base_seed``,
    ``base_seed + 1``, ...) along what a recording tells of the robot's attitude: the real
    log's times (s), its TRUE heading and its MEASURED pitch/roll (degrees; the whole degrees
    of the registers are the best estimate of the true tilt a recording has). The CLI's
    scenario baseline and the benchmark both come from here, so the benchmark's null is the
    one the CLI builds from a real log."""
    if real.true_heading_deg is None:
        raise ConfigError("a compass baseline needs the real log's true heading")
    truth = real.with_(heading_deg=np.asarray(real.true_heading_deg), field_ut=None)
    return [
        simulate_compass(
            truth, np.random.default_rng(base_seed + i), field_model, errors, device_heading
        )
        for i in range(seeds)
    ]


def scenario_compass_baseline(
    path: str | Path, template: HeadingSeries, seeds: int, base_seed: int = 2000
) -> tuple[list[HeadingSeries], MagneticField]:
    """``seeds`` runs of the scenario's CMPS10 (its ``[compass]`` table and its compass
    ``[[effects]]``, mapped as ``x6wd sim`` maps them) along the real log
    (:func:`baseline_along`), and the field model (for the fits' inclination)."""
    from sim_backend.mission import compass_setup
    from sim_backend.world import load_world

    world = load_world(path)
    cset, _ = compass_setup(world)
    runs = baseline_along(
        template,
        seeds,
        base_seed,
        cset.field_model,
        cset.errors,
        cset.device_heading_deg if cset.tilt else None,
    )
    return runs, cset.field_model
