"""The level calibration: seed 000's validation as the tool's closing figure.

The selection explains the gap's shape (a navigation filter, outages, ...), but nothing in it
sets the simulator's error LEVEL to the receiver's: one log cannot show that a receiver's slow
error is smaller than the model's with significance (the model's own hour-to-hour spread of
the mean error is some 30 %), so no significance-gated selection will ever hold that scaling.
Seed 000 configured its model for the conditions of its real hour and compared them in
sample; this stage does the same. On top of the selected effects (their whole-log
parameters) a few receiver-side layers (:mod:`sim_backend.effects`, all deterministic) are
fitted by simulation on the WHOLE real log to the validation's own figures:

- ``correction`` (factor and split time): the slow error's level;
- ``noise_scale`` (factor and split time): the fast error's level;
- ``nav_filter`` (time constant; order 2 when the real Allan deviation rises over its two
  shortest octaves by more than tau^0.75 steeper than the model's, else 1): only when the
  real log is quieter than the model at the shortest octave (a filter cannot make it
  noisier);
- ``bias`` (east, north; m) when the errors are against a truth: the real log's mean error
  less the runs' average with the other layers (not a parameter of the search). A level
  the scalings cannot reach: the F9P's horizontal error on its mark is a 1.1 m offset
  (sigma 0.12 m), of the size of its datum question; the scalings alone left its mean
  +33 % off.

The objective is least squares over the validation's discrepancies,
:meth:`~x6wd.gap.validate.Validation.misses`: log(simulated / real) of mean, sigma and the
Allan deviation at every validation octave, each over log(1 + its tolerance), so that mean
and sigma (3 %) weigh about 6 times as much as an octave (20 %) and every figure passes at
about 1. The selected effects' draws are made once (common random numbers) and the layers
draw nothing, so the objective is deterministic; it is solved in log parameters inside
bounds (a factor 0.005-50, as the layers' own fits search; split times from two steps to
the log's length, the correction's to four times it) by trust-region least squares with a
forward-difference Jacobian on a step of 0.05 (the NMEA lattice makes the figures step-wise
on finer ones), from a start read off the figures, then from other starts while an Allan
octave fails, all within :data:`MAX_EVALS` evaluations; it stops once every figure is within
:data:`MARGIN` of its tolerance (fitting one log's realisation closer is not fitting the
receiver better: the layers trade off, a longer filter with more fast noise gives the same
figures).

The outcome is in sample, fitted to the very figures it reports, as seed 000's was: it
shows the simulator CAN be set to this receiver, not that it predicts it. How far one log of
this length lands from its own model is the runs' own spread (``mean_spread``,
``sd_spread``). Mean and sigma together are met only as far as the log's sigma / mean is the
model's: scaling the error per time scale hardly moves it, and one log's varies by the runs'
``ratio_spread`` (7-17 % on 25-minute logs of the NEO-5 surrogate, of which 8 in 15 drawn
from the model itself passed calibrated, every miss on mean and sigma in opposite
directions).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from sim_backend.effects import Bias, Correction, NavFilter, NoiseScale, PositionSeries
from x6wd.gap.fitted import Fit
from x6wd.gap.validate import ADEV_TOL, Validation, own_mean, validate

# The pipeline's way of adding fits to runs, (fits, runs, rng, lattice decimals) -> runs
# (:func:`x6wd.gap.diagnose.apply_fits`), passed in: this module sits below the pipeline.
Apply = Callable[
    [Sequence[Fit], Sequence[PositionSeries], np.random.Generator, "int | None"],
    list[PositionSeries],
]

MAX_EVALS = 100  # simulations of the validation per calibration (each 10-30 ms on 20 runs)
FACTOR_RANGE = (0.005, 50.0)  # the layers' factors (as solution.py's fits search them)
STEP = 0.05  # forward-difference step in log parameters
SEED = 15_005  # the selected effects' draws, shared by both validations (common numbers)
MARGIN = 0.7  # a fit whose figures are all within 0.7 of their tolerances (in log) is kept
ORDER2_SLOPE = 0.75  # real less model log-log Allan slope, two shortest octaves: order 2 above


@dataclass(frozen=True)
class Calibration:
    """The closing figure: the validation of the runs with the selected effects only
    (``selected``) and with the calibration ``layers`` added after them (``calibrated``,
    the layers fitted to it in sample), both on the same draws; ``evaluations``: simulations
    the fit took; ``at_edge``: parameters that ended at a bound of the search (the layer
    would go further)."""

    selected: Validation
    calibrated: Validation
    layers: tuple[Fit, ...]
    evaluations: int
    at_edge: tuple[str, ...] = ()

    def miss_text(self) -> str:
        """The calibrated figures outside their tolerance, each with its difference, and
        when mean and sigma miss in opposite directions, why ("" when all pass)."""
        v = self.calibrated
        out = [
            f"{label} {v.rel_text(sim, real)}"
            for label, real, sim, tol in v.figures()
            if not abs(v.rel(sim, real)) <= tol
        ]
        if not out:
            return ""
        text = "outside the tolerance: " + ", ".join(out)
        rel_mean = v.rel(v.mean_sim_m, v.mean_real_m)
        rel_sd = v.rel(v.sd_sim_m, v.sd_real_m)
        if not (v.mean_ok and v.sd_ok) and rel_mean * rel_sd < 0:
            text += (
                "; mean and sigma miss in opposite directions: the real horizontal error's "
                f"sigma / mean is {v.sd_real_m / v.mean_real_m:.3g}, the calibrated runs' "
                f"{v.sd_sim_m / v.mean_sim_m:.3g}, a shape of the error's distribution that "
                "these layers, which scale it per time scale, did not reach; the runs' own "
                f"spread of it is {v.ratio_spread:.1%} (one log of this length is that far "
                "from its own model)"
            )
        return text


@dataclass(frozen=True)
class _Space:
    """The parameter vector: log factor and log time of the correction and the noise
    scale, then the filter's log time constant (``order`` 1 or 2; 0: no filter)."""

    lo: np.ndarray
    hi: np.ndarray
    order: int

    def layers(self, x: np.ndarray) -> list[Fit]:
        """The calibration layers at ``x`` (parameters rounded as the layers' own fits are,
        so that the reported figure is that of what calibrated.toml holds)."""
        v = [float(np.exp(value)) for value in np.clip(x, self.lo, self.hi)]
        out = [
            Fit(Correction(factor=round(v[0], 5), tau_s=round(v[1], 3), axes="en")),
            Fit(NoiseScale(factor=round(v[2], 5), split_tau_s=round(v[3], 3), axes="en")),
        ]
        if self.order:
            out.append(Fit(NavFilter(tau_s=round(v[4], 3), order=self.order, axes="en")))
        return out

    def edges(self, x: np.ndarray) -> tuple[str, ...]:
        names = ["correction factor", "correction tau_s", "noise_scale factor"]
        names += ["noise_scale split_tau_s", "nav_filter tau_s"][: x.size - 3]
        near = (x <= self.lo + 1e-3) | (x >= self.hi - 1e-3)
        return tuple(name for name, edge in zip(names, near, strict=True) if edge)


class _Objective:
    """The validation of the runs with the selected effects (drawn once) plus a layer set,
    as its scaled discrepancies; keeps the best point it was asked about (a passing one
    before any failing one) and stops the search (:class:`_Stop`) once one passes with
    :data:`MARGIN` or the evaluations run out. ``bias``: a bias layer goes last, the real
    log's mean error (east, north) less the runs' average with the other layers (the
    scalings move the runs' own hour offsets)."""

    def __init__(
        self,
        real: PositionSeries,
        with_effects: list[PositionSeries],
        tail: list[Fit],
        apply: Apply,
        lattice: int | None,
        layout: tuple[float, float],
        bias: bool,
    ) -> None:
        self.real, self.with_effects, self.tail = real, with_effects, tail
        self.apply, self.lattice = apply, lattice
        self.dt_s, self.duration_s = layout
        self.real_mean_m = _mean_en(real) if bias else None
        self.evaluations = 0
        self.best: tuple[float, tuple[Fit, ...], Validation, np.ndarray] | None = None
        self._last: tuple[np.ndarray, np.ndarray] | None = None

    def validation(self, layers: Sequence[Fit]) -> tuple[tuple[Fit, ...], Validation]:
        """The layer set (``layers`` and the bias) and the figures with it after the selected
        effects, printed on the lattice."""
        no_draws = np.random.default_rng(0)
        runs, layers = self.with_effects, list(layers)
        if self.real_mean_m is not None:
            runs = self.apply(layers, runs, no_draws, None)
            offset_m = self.real_mean_m - np.mean([_mean_en(s) for s in runs], axis=0)
            bias = Bias(east_m=round(float(offset_m[0]), 4), north_m=round(float(offset_m[1]), 4))
            runs = self.apply([*self.tail, Fit(bias)], runs, no_draws, self.lattice)
            layers.append(Fit(bias))
        else:
            runs = self.apply([*self.tail, *layers], runs, no_draws, self.lattice)
        return tuple(layers), validate(self.real, runs, self.dt_s, self.duration_s)

    def misses(self, space: _Space, x: np.ndarray) -> np.ndarray:
        if self._last is not None and np.array_equal(self._last[0], x):
            return self._last[1]  # least_squares asks for the Jacobian at the point it just had
        if self.evaluations >= MAX_EVALS or (self.best is not None and self.best[0] <= 0):
            raise _Stop
        self.evaluations += 1
        layers, v = self.validation(space.layers(x))
        misses = v.misses()
        # passed with a margin (every figure within MARGIN of its tolerance, in log): done,
        # cost 0 (going on would fit the one log's realisation closer, not the receiver)
        cost = 0.0 if v.passed and np.max(np.abs(misses)) <= MARGIN else float(misses @ misses)
        if self.best is None or cost < self.best[0] or (v.passed and not self.best[2].passed):
            self.best = (cost, layers, v, np.array(x, dtype=float))
        self._last = (np.array(x, dtype=float), misses)
        return misses


class _Stop(Exception):
    """The search is over: a point passed with the margin, or the evaluations ran out."""


def _log_ratio(real: float, sim: float) -> float:
    return math.log(real / sim) if real > 0 and sim > 0 else 0.0


def _space(v: Validation, dt_s: float, duration_s: float) -> _Space:
    # a filter only where the receiver is quieter than the model at the shortest octave;
    # its order from how much steeper the real Allan deviation rises there than the model's
    # (below its time constant a filter adds tau^0.5 with order 1, tau^1 with order 2)
    order = 0
    if v.adev_real_m and v.adev_real_m[0] < v.adev_sim_m[0] / (1.0 + ADEV_TOL):
        order = 1
        if len(v.taus_s) > 1 and min(*v.adev_real_m[:2], *v.adev_sim_m[:2]) > 0:
            steeper = _log_ratio(v.adev_real_m[1], v.adev_real_m[0]) - _log_ratio(
                v.adev_sim_m[1], v.adev_sim_m[0]
            )
            order = 2 if steeper / math.log(2.0) > ORDER2_SLOPE else 1
    f_lo, f_hi = (math.log(f) for f in FACTOR_RANGE)
    t_lo = math.log(2 * dt_s)
    lo = [f_lo, t_lo, f_lo, t_lo]
    hi = [f_hi, math.log(max(4 * duration_s, 3 * dt_s)), f_hi, math.log(max(duration_s, 3 * dt_s))]
    if order:
        lo.append(math.log(dt_s))
        hi.append(math.log(max(duration_s / 4, 2 * dt_s)))
    return _Space(np.array(lo), np.array(hi), order)


def _starts(v: Validation, space: _Space, dt_s: float, duration_s: float) -> list[np.ndarray]:
    """The first start read off the figures (the slow factor from the mean, the fast one
    from the shortest octave, the layers' default split times), then others with the split
    times moved to the ends of their ranges."""
    slow = _log_ratio(v.mean_real_m, v.mean_sim_m)
    fast = _log_ratio(v.adev_real_m[0], v.adev_sim_m[0]) if v.adev_real_m else 0.0
    first = [slow, math.log(60.0), 0.0 if space.order else fast, math.log(10.0)]
    if space.order:
        first.append(math.log(4 * dt_s))
    lo, hi = space.lo + 1e-6, space.hi - 1e-6
    out = [np.clip(np.array(first), lo, hi)]
    for t_c, t_g in ((duration_s, 2 * dt_s), (4 * dt_s, duration_s / 4)):
        x = np.array(first)
        x[1], x[3] = math.log(max(t_c, dt_s)), math.log(max(t_g, dt_s))
        out.append(np.clip(x, lo, hi))
    return out


def calibrate_level(
    real: PositionSeries,
    runs: Sequence[PositionSeries],
    selected: Sequence[Fit],
    apply: Apply,
    lattice: int | None,
    dt_s: float,
    duration_s: float,
) -> Calibration:
    """Seed 000's validation of ``runs`` (baseline errors, m) with the ``selected`` effects,
    and with the level calibration fitted after them (see the module doc). ``apply`` adds
    fits to runs and prints them on the ``lattice`` (decimals of the NMEA minutes, None: not
    printed); ``dt_s``, ``duration_s``: the log's step and length (s)."""
    from scipy.optimize import least_squares

    tail = [fit for fit in selected if fit.name == "quantization"]
    effects = [fit for fit in selected if fit.name != "quantization"]
    with_effects = apply(effects, runs, np.random.default_rng(SEED), None)
    objective = _Objective(
        real, with_effects, tail, apply, lattice, (dt_s, duration_s), bias=not own_mean(real)
    )
    v_selected = validate(
        real, apply(tail, with_effects, np.random.default_rng(0), lattice), dt_s, duration_s
    )
    space = _space(v_selected, dt_s, duration_s)

    def fun(x: np.ndarray) -> np.ndarray:
        return objective.misses(space, x)

    def jac(x: np.ndarray) -> np.ndarray:
        f0 = fun(x)
        cols = []
        for i in range(x.size):
            h = STEP if x[i] + STEP <= space.hi[i] else -STEP
            step = np.zeros(x.size)
            step[i] = h
            cols.append((fun(x + step) - f0) / h)
        return np.column_stack(cols)

    for x0 in _starts(v_selected, space, dt_s, duration_s):
        try:
            fun(x0)
            least_squares(
                fun, x0, jac=jac, bounds=(space.lo, space.hi), ftol=1e-3, xtol=1e-3, gtol=1e-4
            )
        except _Stop:
            break
        assert objective.best is not None
        if all(objective.best[2].adev_ok):
            # passed, or only mean and sigma miss: the split times of other starts move
            # the Allan deviation, not the shape of the error's distribution
            break
    assert objective.best is not None
    _cost, layers, v_best, x_best = objective.best
    return Calibration(
        selected=v_selected,
        calibrated=v_best,
        layers=layers,
        evaluations=objective.evaluations,
        at_edge=space.edges(x_best),
    )


def _mean_en(series: PositionSeries) -> np.ndarray:
    valid = np.asarray(series.valid, dtype=bool)
    if not np.any(valid):
        return np.zeros(2)
    return np.array([np.mean(np.asarray(a)[valid]) for a in (series.east_m, series.north_m)])
