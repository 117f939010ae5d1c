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

import dataclasses
import math
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from sim_backend.effects import (
    Bias,
    Correction,
    NavFilter,
    NoiseScale,
    PositionSeries,
    Quantization,
)
from x6wd.gap.fitted import Fit
from x6wd.gap.stats import window
from x6wd.gap.validate import ADEV_TOL, Validation, against_own_mean, own_mean, validate

# The pipeline's way of adding fits to runs, (fits, runs, rng, lattice) -> runs, the lattice
# the layer printing on it (an int: decimals of NMEA minutes; None: not printed)
# (:func:`x6wd.gap.diagnose.apply_fits`), passed in: this module sits below the pipeline.
Lattice = Quantization | int | None
Apply = Callable[
    [Sequence[Fit], Sequence[PositionSeries], np.random.Generator, Lattice],
    list[PositionSeries],
]

MAX_EVALS = 100  # simulations of the validation per calibration (each 10-30 ms on 20 runs)
FACTOR_RANGE = (0.005, 50.0)  # the layers' factors (as solution.py's fits search them)
STEP = 0.05  # forward-difference step in log parameters
SEED = 15_005  # the selected effects' draws, shared by both validations (common numbers)
MARGIN = 0.7  # a fit whose figures are all within 0.7 of their tolerances (in log) is kept
ORDER2_SLOPE = 0.75  # real less model log-log Allan slope, two shortest octaves: order 2 above
# The level layers, in the order calibrated.toml writes them
LEVEL_LAYERS = ("correction", "noise_scale", "nav_filter", "bias")


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
    # the level layers not written, each with why (:func:`calibrate_checked`): neither part
    # of the explanation nor flagged by the test, or further from the real log held out
    left_out: tuple[tuple[str, str], ...] = ()
    # the held-out check of the layers kept: (without, with) the layers fitted on the fit
    # part, validated on the held-out part; None when not checked (:func:`calibrate_level`)
    held_out: tuple[Validation, Validation] | None = None
    held_out_s: tuple[float, float] | None = None  # that part, s from the log's start

    def miss_text(self) -> str:
        """The calibrated figures outside their tolerance, each with its difference, and
        when mean and sigma miss in opposite directions, why ("" when all pass)."""
        v = self.calibrated
        out = [
            f"{label} {v.rel_text(sim, real)}"
            for label, real, sim, tol in v.figures()
            if v.within(sim, real, tol) is False
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
                + (
                    f"spread of it is {v.ratio_spread:.1%} (one log of this length is that far "
                    "from its own model)"
                    if v.n_runs >= 2
                    else "spread of it is not defined for one log"
                )
            )
        return text


@dataclass(frozen=True)
class _Space:
    """The parameter vector: log factor and log time of the correction and the noise
    scale, then the filter's log time constant (``order`` 1 or 2; 0: no filter)."""

    lo: np.ndarray
    hi: np.ndarray
    order: int
    allowed: frozenset[str] = frozenset(LEVEL_LAYERS)
    # the parameters searched (a scaling not allowed stays out of the search and the layers)
    free: np.ndarray | None = None

    def full(self, x_free: np.ndarray, like: np.ndarray) -> np.ndarray:
        """The whole parameter vector: ``like`` with the searched parameters ``x_free``."""
        if self.free is None:
            return np.asarray(x_free, dtype=float)
        out = np.array(like, dtype=float)
        out[self.free] = x_free
        return out

    def reduce(self, x: np.ndarray) -> np.ndarray:
        return np.asarray(x, dtype=float) if self.free is None else np.asarray(x)[self.free]

    def layers(self, x: np.ndarray) -> list[Fit]:
        """The calibration layers at ``x`` (parameters rounded as the layers' own fits are,
        so that the reported figure is that of what calibrated.toml holds); a scaling not
        allowed is left out (its factor is held at 1)."""
        v = [float(np.exp(value)) for value in np.clip(x, self.lo, self.hi)]
        out = []
        if "correction" in self.allowed:
            out.append(Fit(Correction(factor=round(v[0], 5), tau_s=round(v[1], 3), axes="en")))
        if "noise_scale" in self.allowed:
            out.append(
                Fit(NoiseScale(factor=round(v[2], 5), split_tau_s=round(v[3], 3), axes="en"))
            )
        if self.order:
            out.append(Fit(NavFilter(tau_s=round(v[4], 3), order=self.order, axes="en")))
        return out

    def edges(self, x: np.ndarray) -> tuple[str, ...]:
        names = ["correction factor", "correction tau_s", "noise_scale factor"]
        names += ["noise_scale split_tau_s", "nav_filter tau_s"][: x.size - 3]
        near = (x <= self.lo + 1e-3) | (x >= self.hi - 1e-3)
        return tuple(
            name
            for name, edge in zip(names, near, strict=True)
            if edge and name.split()[0] in self.allowed
        )


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
        lattice: Lattice,
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


def _space(
    v: Validation, dt_s: float, duration_s: float, layers: frozenset[str] = frozenset(LEVEL_LAYERS)
) -> _Space:
    # a filter only where the receiver is quieter than the model at the shortest octave;
    # its order from how much steeper the real Allan deviation rises there than the model's
    # (below its time constant a filter adds tau^0.5 with order 1, tau^1 with order 2).
    # A scaling not in ``layers`` is held at 1 (its factor's bounds closed there).
    order = 0
    if (
        "nav_filter" in layers
        and v.adev_real_m
        and v.adev_real_m[0] < v.adev_sim_m[0] / (1.0 + ADEV_TOL)
    ):
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
    free = [*["correction" in layers] * 2, *["noise_scale" in layers] * 2]
    if order:
        lo.append(math.log(dt_s))
        hi.append(math.log(max(duration_s / 4, 2 * dt_s)))
        free.append(True)
    return _Space(np.array(lo), np.array(hi), order, frozenset(layers), np.array(free))


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
    lattice: Lattice,
    dt_s: float,
    duration_s: float,
    layers: Iterable[str] = LEVEL_LAYERS,
) -> Calibration:
    """Seed 000's validation of ``runs`` (baseline errors, m) with the ``selected`` effects,
    and with the level calibration fitted after them (see the module doc). ``apply`` adds
    fits to runs and prints them on the ``lattice`` (the :class:`Quantization` printing on
    it, of NMEA minutes or decimal degrees; an int: decimals of NMEA minutes; None: not
    printed); ``dt_s``, ``duration_s``: the log's step and length (s); ``layers``: the level
    layers the fit may use (of :data:`LEVEL_LAYERS`; the filter only where the receiver is
    quieter at the shortest octave, the bias only against a truth). In sample, unchecked:
    the tool calls :func:`calibrate_checked`."""
    from scipy.optimize import least_squares

    allowed = frozenset(layers)
    tail = [fit for fit in selected if fit.name == "quantization"]
    effects = [fit for fit in selected if fit.name != "quantization"]
    with_effects = apply(effects, runs, np.random.default_rng(SEED), None)
    objective = _Objective(
        real,
        with_effects,
        tail,
        apply,
        lattice,
        (dt_s, duration_s),
        bias="bias" in allowed and not own_mean(real),
    )
    v_selected = validate(
        real, apply(tail, with_effects, np.random.default_rng(0), lattice), dt_s, duration_s
    )
    space = _space(v_selected, dt_s, duration_s, allowed)
    if not any(name in allowed for name in ("correction", "noise_scale")) and not space.order:
        # nothing to search: the bias alone (or nothing), computed once
        chosen, v_best = objective.validation([])
        return Calibration(v_selected, v_best, chosen, evaluations=1)

    starts = _starts(v_selected, space, dt_s, duration_s)
    like = starts[0]  # the values of the parameters not searched (unused by the layers)

    def fun(x: np.ndarray) -> np.ndarray:
        return objective.misses(space, space.full(x, like))

    lo, hi = space.reduce(space.lo), space.reduce(space.hi)

    def jac(x: np.ndarray) -> np.ndarray:
        f0 = fun(x)
        cols = []
        for i in range(x.size):
            h = STEP if x[i] + STEP <= hi[i] else -STEP
            step = np.zeros(x.size)
            step[i] = h
            cols.append((fun(x + step) - f0) / h)
        return np.column_stack(cols)

    for x0_full in starts:
        x0 = space.reduce(x0_full)
        try:
            fun(x0)
            least_squares(fun, x0, jac=jac, bounds=(lo, hi), ftol=1e-3, xtol=1e-3, gtol=1e-4)
        except _Stop:
            break
        assert objective.best is not None
        best_v = objective.best[2]
        if all(ok for ok, r in zip(best_v.adev_ok, best_v.adev_reached, strict=True) if r):
            # passed, or only mean and sigma miss: the split times of other starts move
            # the Allan deviation, not the shape of the error's distribution
            break
    assert objective.best is not None
    _cost, chosen_layers, v_best, x_best = objective.best
    return Calibration(
        selected=v_selected,
        calibrated=v_best,
        layers=chosen_layers,
        evaluations=objective.evaluations,
        at_edge=space.edges(x_best),
    )


def _mean_en(series: PositionSeries) -> np.ndarray:
    valid = np.asarray(series.valid, dtype=bool)
    if not np.any(valid):
        return np.zeros(2)
    return np.array([np.mean(np.asarray(a)[valid]) for a in (series.east_m, series.north_m)])


# --- which level layers calibrated.toml may hold (outside audit, 2026-12-04) -----------------
#
# Fitted in sample to every figure, the calibration wrote level layers where the gap had
# nothing to do with the level: on the simulator's own output with six 30-s outages (the
# verdict "outages, closure 1.00") calibrated.toml carried a correction of 0.005-0.01 (99 % of
# the slow error removed), a 2.2-2.4 m bias, a noise scale and a filter, fitted to how one
# log's slow error happened to fall (the runs' own spread of the mean is 34 %); on the urban
# drive the "calibrated" figures were further from the receiver than without (Allan octaves
# within 20 %: 5 of 9 -> 1 of 9; mean +27 % -> +38 %). A user takes calibrated.toml to bring
# the simulator closer to the receiver, never further, so a level layer is now written only
# when (1) it belongs to the explanation (the selected effects shape what it sets the level
# of) or the "where" test flags, at its family-wise limits, a whole-log horizontal statistic
# the layer moves, and (2) fitted on the whole log, the calibrated figures are no further
# from the real than the selected effects' alone (:func:`no_further`). Every layer left out
# is named, with why, in the report.

# The selected effects whose level a layer sets (it belongs to that explanation)
BELONGS_WITH: dict[str, tuple[str, ...]] = {
    "correction": ("correction", "gauss_markov", "random_walk"),
    "noise_scale": ("noise_scale", "nav_filter", "static_hold"),
    "nav_filter": ("nav_filter", "noise_scale", "static_hold"),
    "bias": ("bias",),
}
HORIZONTAL = ("east", "north", "horizontal")


def _statistics(layer: str) -> tuple[str, ...]:
    """The battery statistics a level layer moves: the receiver-side layers' fingerprints
    (:data:`x6wd.gap.solution.FINGERPRINTS`), the bias's the whole-log mean."""
    from x6wd.gap.solution import FINGERPRINTS

    return ("mean",) if layer == "bias" else FINGERPRINTS[layer]


def level_layers_allowed(
    selected: Sequence[str], where: Sequence[Mapping[str, object]], own: bool
) -> tuple[dict[str, str], dict[str, str]]:
    """Gate (1): which of :data:`LEVEL_LAYERS` the calibration may fit, and why each may or
    may not (``allowed``, ``refused``: layer -> reason). ``selected``: the selected effects'
    names; ``where``: the "where" test's flagged cells (report.json's ``where``); ``own``:
    the errors are against the log's own mean (no bias can be seen)."""
    allowed: dict[str, str] = {}
    refused: dict[str, str] = {}
    for layer in LEVEL_LAYERS:
        if layer == "bias" and own:
            refused[layer] = (
                "the errors are against the log's own mean (no truth): a bias is invisible"
            )
            continue
        owners = [name for name in selected if name in BELONGS_WITH[layer]]
        statistics = _statistics(layer)
        flagged = [
            cell
            for cell in where
            if cell["statistic"] in statistics
            and cell["axis"] in HORIZONTAL
            and cell["period"] == "all"
            and cell["place"] == "all"
        ]
        if owners:
            allowed[layer] = f"it sets the level of the selected {' + '.join(owners)}"
        elif flagged:
            top = max(flagged, key=lambda c: abs(float(c["z"])))  # type: ignore[arg-type]
            allowed[layer] = (
                f"the test flags {len(flagged)} statistic(s) it moves (strongest: "
                f"{top['statistic']} {top['axis']} {top['scale']}, z {float(top['z']):+.1f})"  # type: ignore[arg-type]
            )
        else:
            why = " + ".join(selected) if selected else "nothing selected"
            refused[layer] = (
                f"not part of the explanation ({why}) and no whole-log horizontal statistic it "
                f"moves ({', '.join(statistics)}) is beyond its family-wise limit: a level "
                "fitted here would be fitted to how this one log happened to fall"
            )
    return allowed, refused


def _groups(v: Validation) -> tuple[tuple[float, int], tuple[float, int]]:
    """(RMS miss in tolerance units, figures within tolerance) of the level figures (mean,
    sigma) and of the Allan octaves the simulated logs reach."""
    misses = v.misses()
    reached = np.array([True, True, *v.adev_reached])
    within = [v.mean_ok, v.sd_ok, *v.adev_ok]
    out = []
    for part in (slice(0, 2), slice(2, None)):
        m = misses[part][reached[part]]
        rms = float(np.sqrt(np.mean(m**2))) if m.size else 0.0
        out.append(
            (rms, int(sum(w for w, r in zip(within[part], reached[part], strict=True) if r)))
        )
    return out[0], out[1]


def at_least_as_close(with_: Validation, without: Validation) -> bool:
    """Whether ``with_`` is at least as close to the real log as ``without`` on the level
    figures (mean and sigma) and on the Allan octaves alike: in each group no larger RMS miss
    (in tolerance units) and no fewer figures within tolerance."""
    return all(
        rms_w <= rms_o + 1e-9 and n_w >= n_o
        for (rms_w, n_w), (rms_o, n_o) in zip(_groups(with_), _groups(without), strict=True)
    )


def no_further(with_: Validation, without: Validation) -> bool:
    """The calibration's keep rule: ``with_`` has no fewer figures within tolerance than
    ``without`` in either group (mean and sigma; Allan octaves) and no larger summed RMS miss
    (tolerance units). Stricter, :func:`at_least_as_close` refused the MAX-M8Q's correction
    and noise scale, which brought mean and sigma from 0 to 2 of 2 within (10.9 -> 0.5
    tolerances) while its five Allan octaves stayed within (miss 0.30 -> 0.40)."""
    groups_w, groups_o = _groups(with_), _groups(without)
    return all(n_w >= n_o for (_, n_w), (_, n_o) in zip(groups_w, groups_o, strict=True)) and (
        sum(r for r, _ in groups_w) <= sum(r for r, _ in groups_o) + 1e-9
    )


def closeness_text(v: Validation) -> str:
    """The two groups' figures in words, e.g. "mean and sigma 1.9 tolerances off (RMS, 0 of 2
    within), Allan octaves 0.8 off (6 of 9 within)"."""
    (rms_l, n_l), (rms_a, n_a) = _groups(v)
    return (
        f"mean and sigma {rms_l:.2f} tolerances off (RMS; {n_l} of 2 within), Allan octaves "
        f"{rms_a:.2f} off ({n_a} of {sum(v.adev_reached)} within)"
    )


def _part(series: PositionSeries, span_s: tuple[float, float], own: bool) -> PositionSeries:
    part = window(series, *span_s)
    return against_own_mean(part) if own else part


def validate_with(
    real: PositionSeries,
    runs: Sequence[PositionSeries],
    fits: Sequence[Fit],
    apply: Apply,
    lattice: Lattice,
    layout: tuple[float, float],
) -> Validation:
    """Seed 000's validation of ``runs`` with ``fits`` added (a lattice last, on it) against
    ``real``; ``layout``: the log's step and length (s)."""
    tail = [fit for fit in fits if fit.name == "quantization"]
    effects = [fit for fit in fits if fit.name != "quantization"]
    with_fits = apply(effects, runs, np.random.default_rng(SEED), None)
    return validate(real, apply(tail, with_fits, np.random.default_rng(0), lattice), *layout)


def calibrate_checked(
    real: PositionSeries,
    runs: Sequence[PositionSeries],
    selected: Sequence[Fit],
    apply: Apply,
    lattice: Lattice,
    layout: tuple[float, float],
    split_s: tuple[tuple[float, float], tuple[float, float]],
    allowed: Mapping[str, str],
    refused: Mapping[str, str],
) -> Calibration:
    """The level calibration the tool writes (gate (2) above): the ``allowed`` layers
    (:func:`level_layers_allowed`; ``refused`` carries the others' reasons) are fitted on the
    whole log, in sample, and kept only while the calibrated figures are no further from the
    real log than the selected effects' alone (:func:`no_further`);
    otherwise the last layer in :data:`LEVEL_LAYERS` order is left out and the rest refitted.
    ``layout``: the log's step and length (s). ``held_out`` reports, without gating, how the
    kept layers fitted on the fit part of ``split_s`` ((fit start, end), (held-out start,
    end), s from the log's start) carry to the held-out part."""
    dt_s, duration_s = layout
    (fit0_s, fit1_s), (test0_s, test1_s) = split_s
    own = own_mean(real)
    left_out = dict(refused)
    tail = [fit for fit in selected if fit.name == "quantization"]
    effects = [fit for fit in selected if fit.name != "quantization"]
    real_test = _part(real, (test0_s, test1_s), own)
    runs_test = apply(
        effects, [window(s, test0_s, test1_s) for s in runs], np.random.default_rng(SEED), None
    )
    test_len_s = min(test1_s, duration_s + dt_s) - test0_s
    real_fit = _part(real, (fit0_s, fit1_s), own)
    runs_fit = [window(s, fit0_s, fit1_s) for s in runs]
    fit_len_s = min(fit1_s, duration_s + dt_s) - fit0_s

    def held_out(layers: Sequence[Fit]) -> Validation:
        with_layers = apply([*tail, *layers], runs_test, np.random.default_rng(0), lattice)
        return validate(real_test, with_layers, dt_s, test_len_s)

    without = held_out([])
    evaluations = 0
    names = [name for name in LEVEL_LAYERS if name in allowed]
    whole: Calibration | None = None
    check: tuple[Validation, Validation] | None = None
    # Decided on the whole log, in sample (as seed 000 set its model to its hour). A held-out
    # gate was tried (2026-12-04): on short logs it halves what is fitted and is as noisy as
    # the runs' own spread (11-46 %), and it refused the MAX-M8Q's and the F9P's layers that
    # bring their mean and sigma within 3 % (71 s and 1404 s logs); it is reported, not gated.
    while names:
        fit_all = calibrate_level(real, runs, selected, apply, lattice, dt_s, duration_s, names)
        evaluations += fit_all.evaluations
        got = {fit.name for fit in fit_all.layers}
        for name in [n for n in names if n not in got]:
            # not applicable on this log (a filter where the receiver is not quieter at the
            # shortest octave): nothing fitted
            left_out[name] = "not applicable: the receiver is not quieter at the shortest octave"
        names = [n for n in names if n in got]
        if not names:
            break
        if no_further(fit_all.calibrated, fit_all.selected):
            whole = fit_all
            break
        drop = names[-1]  # the last in LEVEL_LAYERS' order: bias, filter, scale, correction
        left_out[drop] = (
            f"fitted on the whole log with {' + '.join(names)} it left the figures further "
            f"from the real than the selected effects alone ({closeness_text(fit_all.calibrated)}"
            f" against {closeness_text(fit_all.selected)})"
        )
        names = [n for n in names if n != drop]
    if whole is not None:  # how the kept layers carry to data they were not fitted on
        on_fit = calibrate_level(
            real_fit, runs_fit, selected, apply, lattice, dt_s, fit_len_s, names
        )
        evaluations += on_fit.evaluations
        check = (without, held_out(list(on_fit.layers)))
    order = {name: i for i, name in enumerate(LEVEL_LAYERS)}
    reasons = tuple(sorted(left_out.items(), key=lambda item: order[item[0]]))
    if whole is None:
        v_selected = validate_with(real, runs, selected, apply, lattice, layout)
        return Calibration(
            v_selected, v_selected, (), evaluations, left_out=reasons, held_out_s=(test0_s, test1_s)
        )
    return dataclasses.replace(
        whole,
        evaluations=evaluations,
        left_out=reasons,
        held_out=check,
        held_out_s=(test0_s, test1_s),
    )
