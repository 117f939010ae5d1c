"""Fits of the receiver-side layers: what a real receiver does to its own solution, in either
direction against the model (:class:`sim_backend.effects.NavFilter`, ``NoiseScale``,
``Correction``, ``StaticHold``).

Every other GPS effect ADDS error, so a receiver that is smoother or better than the model
(a navigation filter, SBAS corrections, static hold, simply a quieter front end) could not be
explained at all. These layers transform the baseline's own error, so there is no additive
likelihood to write down: each is fitted by simulation. The layer (deterministic: it draws
nothing) is applied to the baseline runs, printed on their NMEA lattice again, and its
parameters (in log) minimise the squared z of the real log's fingerprint cells against the
mean of those runs, z scaled by the BASELINE's spread (the reference every G uses). A coarse
grid first (the objective has plateaus: a short filter and none look alike), then a local
refinement. Standard errors come from the objective's curvature in log parameters (it is
-2 log likelihood if the cells were independent; neighbouring Allan octaves are not, so they
are on the optimistic side).

A fit is returned only when the layer moves the fingerprint closer by a real margin
(:data:`MIN_GAIN`): identity (no filter, factor 1, no hold) is always a candidate.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import numpy as np

from sim_backend.effects import (
    Correction,
    NavFilter,
    NoiseScale,
    PositionSeries,
    Quantization,
    StaticHold,
)
from x6wd.gap.fitted import Fit
from x6wd.gap.pipeline import EffectFitter
from x6wd.gap.stats import (
    Layout,
    allan_var,
    carry_twin,
    find_lattice,
    median_increments,
    octave_taus,
    regular,
    twin_of,
)

MIN_GAIN = 9.0  # objective (sum of z^2) a fit must gain over no layer: a 3-sigma improvement
MAX_RUNS = 6  # baseline runs used in a fit (the layers draw nothing: the mean settles fast)
GRID_POINTS = 7  # per log-parameter axis of the coarse grid
FACTOR_Z = 2.5  # |log factor| must exceed this many of one log's spread of the level it scales
# a curvature at steps 0.1 and 0.2 in log that differ by more than this is no parabola: no SE
QUADRATIC_CURVATURE_RATIO = 2.0
SHRINK = 0.5  # of the features' correlation matrix toward the identity
CORRECTION_TAU_S = 60.0  # the slow/fast split of the correction fit (s; the layer's default)

# The cells each layer moves (its fingerprint), by statistic.
FAST = ("log_adev", "log_step_std", "log_step_med", "log_incr_med", "log_psd", "acf")
FINGERPRINTS: dict[str, tuple[str, ...]] = {
    "nav_filter": FAST,
    "noise_scale": (*FAST, "log_std"),
    "correction": ("log_std", "log_cep50", "log_r95", "log_adev", "log_psd"),
    "static_hold": ("zero_step", "log_step_std", "step_tail", "log_adev"),
}


def _lattice(runs: Sequence[PositionSeries]) -> Quantization | None:
    """The printing of the lattice (NMEA minutes or decimal degrees) the runs lie on."""
    return find_lattice(runs[:3])


def _log(x: float) -> float:
    return math.log(max(x, 1e-6))


def features(series: PositionSeries, layout: Layout) -> tuple[np.ndarray, np.ndarray]:
    """The second-order structure the receiver-side layers change, and the floor of each
    one's spread: log overlapping Allan deviation east and north at every octave of the
    battery, log step spread east and north, the share of exactly repeated fixes, log spread
    east and north, log CEP50 and R95, log median horizontal step and increments (m); with a
    vertical, its Allan deviation, step spread and spread. A light cut of the battery (the
    fits evaluate it hundreds of times)."""
    valid = np.asarray(series.valid, dtype=bool)
    east_m = np.asarray(series.east_m, dtype=float)[valid]
    north_m = np.asarray(series.north_m, dtype=float)[valid]
    if east_m.size < 3:
        east_m = north_m = np.zeros(3)
    grid_e, grid_n, _grid_u = regular(series, layout.dt_s)
    factors = octave_taus(layout)
    out: list[float] = []
    floors: list[float] = []
    for grid in (grid_e, grid_n):
        avar = allan_var(grid, factors)
        out += [0.5 * _log(float(v)) if np.isfinite(v) else 0.0 for v in avar]
    floors += [0.02] * (2 * len(factors))
    step_e, step_n = np.diff(east_m), np.diff(north_m)
    radial_m = np.hypot(east_m, north_m)
    out += [
        _log(float(np.std(step_e))),
        _log(float(np.std(step_n))),
        float(np.mean((step_e == 0.0) & (step_n == 0.0))),
        _log(float(np.std(east_m))),
        _log(float(np.std(north_m))),
        _log(float(np.quantile(radial_m, 0.5))),
        _log(float(np.quantile(radial_m, 0.95))),
    ]
    floors += [0.02, 0.02, 0.01, 0.02, 0.02, 0.02, 0.02]
    # the robust fast level (the battery's median step and increments, stats.INCR_LAGS_S):
    # the short Allan octaves are second moments, which a few satellite-change steps rule
    twin = twin_of(series)
    fast_e, fast_n = (grid_e, grid_n) if twin is None else regular(twin, layout.dt_s)[:2]
    for median_m in median_increments(fast_e, fast_n, layout):
        out.append(_log(median_m))
        floors.append(0.02)
    if layout.has_up:  # the vertical: whether a layer acts on it too is part of the fit
        up_m = np.asarray(series.up_m, dtype=float)[valid]
        if up_m.size < 3:
            up_m = np.zeros(3)
        avar = allan_var(_grid_u, factors)
        out += [0.5 * _log(float(v)) if np.isfinite(v) else 0.0 for v in avar]
        out += [_log(float(np.std(np.diff(up_m)))), _log(float(np.std(up_m)))]
        floors += [0.02] * (len(factors) + 2)
    return np.array(out), np.array(floors)


class _Objective:
    """z' C^-1 z + sum 2 log(sd / sd0) over :func:`features`: z = (real - mean of the runs
    with the layer) / sd, sd the larger of the baseline runs' spread sd0 (with a floor) and
    the spread of the runs with the layer, C the baseline's shrunk feature correlation."""

    def __init__(
        self, real: PositionSeries, runs: Sequence[PositionSeries], layout: Layout
    ) -> None:
        self.layout = layout
        self.runs = list(runs[:MAX_RUNS])
        self.lattice = _lattice(self.runs)
        base = np.array([features(s, layout)[0] for s in runs])
        self.real, floors = features(real, layout)
        self.sd0 = np.maximum(np.std(base, axis=0, ddof=1) if len(runs) > 1 else floors, floors)
        self.base_mean = base.mean(axis=0)
        # The features are strongly correlated (neighbouring Allan octaves see the same slow
        # error): a plain sum of z^2 counts one realisation's offset many times and pulls the
        # fit to whatever absorbs it. Their correlation across the baseline runs, shrunk
        # halfway to the identity (few runs, many features), weighs the residual instead.
        corr = np.eye(base.shape[1])
        if len(runs) > 2:
            spread = np.where(np.std(base, axis=0) > 0, np.std(base, axis=0), 1.0)
            centred = (base - self.base_mean) / spread
            corr = (1 - SHRINK) * (centred.T @ centred / len(runs)) + SHRINK * np.eye(base.shape[1])
        self.inv_corr = np.linalg.inv(corr)
        self.identity = self._score(base[: len(self.runs)])

    @property
    def agrees(self) -> bool:
        """The real features are within what the baseline's own spread allows (sum of z^2 no
        more than its count plus MIN_GAIN): no layer can gain enough to be fitted."""
        return self.identity <= self.real.size + MIN_GAIN

    def _score(self, values: np.ndarray) -> float:
        # The runs' spread WITH the layer where it is wider than the baseline's, plus the
        # Gaussian penalty for widening (as in G): a smoothed series printed on a lattice
        # repeats fixes and steps by whole lattice cells, far more variable than the raw
        # baseline's, and holding the real log to the baseline's spread there would pull the
        # fit to another filter.
        sd = self.sd0
        if values.shape[0] > 1:
            sd = np.maximum(sd, np.std(values, axis=0, ddof=1))
        z = (self.real - values.mean(axis=0)) / sd
        return float(z @ self.inv_corr @ z + 2.0 * np.sum(np.log(sd / self.sd0)))

    def _with(
        self, effect: object, run: PositionSeries, rng: np.random.Generator
    ) -> PositionSeries:
        s = effect.apply(run, rng)  # type: ignore[attr-defined]
        if self.lattice is not None:
            s = self.lattice.apply(s, rng)
        return carry_twin(run, s, lambda twin: self._with(effect, twin, rng))

    def __call__(self, effect: object) -> float:
        rng = np.random.default_rng(0)  # the layers draw nothing; apply wants a stream
        out = []
        for run in self.runs:
            out.append(features(self._with(effect, run, rng), self.layout)[0])
        return self._score(np.array(out))


def _search(
    objective: Callable[[np.ndarray], float], grids: Sequence[np.ndarray]
) -> tuple[np.ndarray, float]:
    """Coarse grid over log parameters, then Nelder-Mead from its best point, both inside the
    grid's box (a parameter outside it means another layer: a correction whose slow part is
    faster than a few steps scales the whole error)."""
    from scipy.optimize import minimize

    lo = np.array([g.min() for g in grids])
    hi = np.array([g.max() for g in grids])

    def clipped(x: np.ndarray) -> float:
        return objective(np.clip(x, lo, hi))

    mesh = np.array(np.meshgrid(*grids, indexing="ij")).reshape(len(grids), -1).T
    scores = np.array([clipped(x) for x in mesh])
    x0 = mesh[int(np.argmin(scores))]
    steps = np.array([(g[1] - g[0]) / 2 if g.size > 1 else 0.3 for g in grids])
    result = minimize(
        clipped,
        x0,
        method="Nelder-Mead",
        options={
            "maxfev": 10 * len(grids),
            "xatol": 0.02,
            "fatol": 0.05,
            "initial_simplex": np.vstack([x0, x0 + np.diag(steps)]),
        },
    )
    if result.fun < scores.min():
        return np.clip(np.asarray(result.x), lo, hi), float(result.fun)
    return x0, float(scores.min())


def _log_se(objective: Callable[[np.ndarray], float], x: np.ndarray, f0: float) -> np.ndarray:
    """Standard errors of the log parameters from the diagonal curvature (h = 0.1), only
    where the objective is locally quadratic: the second difference at twice the step must
    give the same curvature within a factor of :data:`QUADRATIC_CURVATURE_RATIO`, else the
    parameter gets none (NaN, not reported). A curvature is a standard error only for a
    parabola; the objective is step-wise where a layer meets the NMEA lattice or a
    hold's exit distance meets the steps, and there a cliff next to the optimum read as
    a precision of 0.02 %: a log rounded to 1e-5 degree (1.1 m) got a static hold of
    0.5575 +- 0.00011 m on the whole log where its first 60 % gave 1.1163 m."""
    h = 0.1
    out = np.full(x.size, math.nan)
    for i in range(x.size):
        if not np.isfinite(x[i]):
            continue
        e = np.zeros(x.size)
        e[i] = h
        curv = (objective(x + e) - 2 * f0 + objective(x - e)) / h**2
        if not curv > 0:
            continue
        wide = (objective(x + 2 * e) - 2 * f0 + objective(x - 2 * e)) / (2 * h) ** 2
        if wide > 0 and max(curv / wide, wide / curv) <= QUADRATIC_CURVATURE_RATIO:
            out[i] = math.sqrt(2.0 / curv)
    return out


def _axes_options(layout: Layout) -> tuple[str, ...]:
    """The axes a fitted layer may act on: horizontal, and with a vertical in the log also all
    three (a receiver's filter and noise act on every axis; a layer given as horizontal only
    leaves the vertical alone). The better fit is kept."""
    return ("en", "enu") if layout.has_up else ("en",)


def _short_adev_ratio(obj: _Objective) -> float:
    """Real over baseline Allan deviation at the shortest octave, east and north (> 1: the
    real receiver is noisier there)."""
    n_oct = len(octave_taus(obj.layout))
    short = [0, n_oct]
    return math.exp(float(np.mean(obj.real[short] - obj.base_mean[short])))


def fit_nav_filter(
    real: PositionSeries, baseline: Sequence[PositionSeries], layout: Layout
) -> Fit | None:
    """A navigation filter (time constant, order 1 or 2) when the real log is smoother than
    the baseline at the shortest scale (a filter cannot make it noisier)."""
    obj = _Objective(real, baseline, layout)
    if obj.agrees or _short_adev_ratio(obj) >= 1.0:
        return None
    tau_grid = np.linspace(
        math.log(layout.dt_s),
        math.log(max(layout.duration_s / 4, 2 * layout.dt_s)),
        GRID_POINTS + 1,
    )
    best: tuple[float, int, str, np.ndarray, Callable[[np.ndarray], float]] | None = None
    for axes in _axes_options(layout):
        for order in (1, 2):

            def f(x: np.ndarray, order: int = order, axes: str = axes) -> float:
                return obj(NavFilter(tau_s=math.exp(float(x[0])), order=order, axes=axes))

            x, score = _search(f, [tau_grid])
            if best is None or score < best[0]:
                best = (score, order, axes, x, f)
    assert best is not None
    score, order, axes, x, f_best = best
    if score > obj.identity - MIN_GAIN:
        return None
    se = _log_se(f_best, x, score)
    tau_s = math.exp(float(x[0]))
    return Fit(
        NavFilter(tau_s=round(tau_s, 4), order=order, axes=axes), {"tau_s": float(tau_s * se[0])}
    )


def _split_scale_fit(
    real: PositionSeries,
    baseline: Sequence[PositionSeries],
    layout: Layout,
    name: str,
    make: Callable[[float, float, str], object],
    tau_lo_s: float,
    tau_hi_s: float,
) -> tuple[float, float, str, float, float] | None:
    """(factor, tau_s, axes, se factor, se tau_s) of a split-scale layer, None without a
    gain or with a factor within :data:`FACTOR_Z` of one log's own spread of the level it
    scales from 1 (one realisation of the slow error is off its model's average by that much
    on every log). The factor's standard error is at least what one log's own spread of the
    statistic it scales allows (the baseline runs' spread of the log median step for the
    fast part, of the log spread for the slow part): the features are many views of one
    realisation, and their curvature alone overstates the information."""
    obj = _Objective(real, baseline, layout)
    if obj.agrees:
        return None
    n_oct = len(octave_taus(layout))
    # feature indices (see features): the fast level is the median step (its robust read:
    # the step spreads, second moments, spread between simulated hours by up to 0.7 in log,
    # which kept a doubled fast noise out of reach), the slow level the spreads east/north
    one_log = obj.sd0[[2 * n_oct + 7] if name == "noise_scale" else [2 * n_oct + 3, 2 * n_oct + 4]]
    floor_log_se = float(np.mean(one_log)) / math.sqrt(2.0)
    best: tuple[float, str, np.ndarray, Callable[[np.ndarray], float]] | None = None
    for axes in _axes_options(layout):

        def f(x: np.ndarray, axes: str = axes) -> float:
            return obj(make(math.exp(float(x[0])), math.exp(float(x[1])), axes))

        x, score = _fit_grid(f, tau_lo_s, tau_hi_s)
        if best is None or score < best[0]:
            best = (score, axes, x, f)
    assert best is not None
    score, axes, x, f_best = best
    if score > obj.identity - MIN_GAIN:
        return None
    se = _log_se(f_best, x, score)
    factor, tau_s = math.exp(float(x[0])), math.exp(float(x[1]))
    if abs(float(x[0])) < FACTOR_Z * float(np.mean(one_log)):
        # within what one log's own level varies by: a factor of 1 fits as well
        return None
    # none where the curvature gives none (flat, or no parabola: _log_se); the floor is a
    # lower bound on a standard error, not one of its own
    se_factor = factor * max(float(se[0]), floor_log_se) if math.isfinite(se[0]) else math.nan
    return factor, tau_s, axes, se_factor, float(tau_s * se[1])


def _fit_grid(
    f: Callable[[np.ndarray], float], tau_lo_s: float, tau_hi_s: float
) -> tuple[np.ndarray, float]:
    grids = [
        np.linspace(math.log(0.005), math.log(50.0), GRID_POINTS + 2),
        np.linspace(
            math.log(tau_lo_s), math.log(max(tau_hi_s, tau_lo_s)), 4 if tau_hi_s > tau_lo_s else 1
        ),
    ]
    return _search(f, grids)


def fit_noise_scale(
    real: PositionSeries, baseline: Sequence[PositionSeries], layout: Layout
) -> Fit | None:
    """Short-term noise ``factor`` times the model's (either way) and the split time."""
    got = _split_scale_fit(
        real, baseline, layout, "noise_scale",
        lambda factor, tau_s, axes: NoiseScale(factor=factor, split_tau_s=tau_s, axes=axes),
        2 * layout.dt_s, layout.duration_s / 16,
    )  # fmt: skip
    if got is None:
        return None
    factor, tau_s, axes, se_factor, se_tau_s = got
    effect = NoiseScale(factor=round(factor, 5), split_tau_s=round(tau_s, 3), axes=axes)
    return Fit(effect, {"factor": se_factor, "split_tau_s": se_tau_s})


def fit_correction(
    real: PositionSeries, baseline: Sequence[PositionSeries], layout: Layout
) -> Fit | None:
    """The slow error ``factor`` times the model's (< 1: SBAS / differential corrections), the
    slow part taken as slower than :data:`CORRECTION_TAU_S` (at most an eighth of the log).
    The split itself is not fitted: one log does not tell it from the factor (on a log with a
    120 s drift, factor 0.49 at 54 s and 0.02 at 145 s fit equally well)."""
    tau_s = min(CORRECTION_TAU_S, max(layout.duration_s / 8, 2 * layout.dt_s))
    got = _split_scale_fit(
        real, baseline, layout, "correction",
        lambda factor, tau_s, axes: Correction(factor=factor, tau_s=tau_s, axes=axes),
        tau_s, tau_s,
    )  # fmt: skip
    if got is None:
        return None
    factor, tau_s, axes, se_factor, _se_tau_s = got
    effect = Correction(factor=round(factor, 5), tau_s=round(tau_s, 3), axes=axes)
    return Fit(effect, {"factor": se_factor})


def _zero_steps(series: PositionSeries) -> float:
    valid = np.asarray(series.valid, dtype=bool)
    e, n = np.asarray(series.east_m)[valid], np.asarray(series.north_m)[valid]
    if e.size < 2:
        return 0.0
    return float(np.mean((np.diff(e) == 0.0) & (np.diff(n) == 0.0)))


def fit_static_hold(
    real: PositionSeries, baseline: Sequence[PositionSeries], layout: Layout
) -> Fit | None:
    """Static hold when the real log repeats fixes exactly more often than the baseline: the
    exit distance by simulation; the speed threshold, on a moving log, just above the fastest
    true speed at which the real log repeats a fix (a static log cannot tell it: 0.5 m/s)."""
    real_zero = _zero_steps(real)
    base_zero = float(np.mean([_zero_steps(s) for s in baseline]))
    if real_zero <= base_zero + 0.02:
        return None
    threshold_mps = 0.5
    if layout.moving and real.speed_mps is not None:
        valid = np.asarray(real.valid, dtype=bool)
        e, n = np.asarray(real.east_m), np.asarray(real.north_m)
        idx = np.flatnonzero(valid)
        repeat = idx[1:][(np.diff(e[idx]) == 0.0) & (np.diff(n[idx]) == 0.0)]
        speeds = np.nan_to_num(np.asarray(real.speed_mps, dtype=float))[repeat]
        threshold_mps = round(float(np.quantile(speeds, 0.95)) + 0.05, 3) if speeds.size else 0.05
    obj = _Objective(real, baseline, layout)
    if obj.agrees:
        return None

    def f(x: np.ndarray) -> float:
        return obj(
            StaticHold(exit_distance_m=math.exp(float(x[0])), speed_threshold_mps=threshold_mps)
        )

    grid = np.linspace(math.log(0.005), math.log(10.0), 2 * GRID_POINTS)
    x, score = _search(f, [grid])
    if score > obj.identity - MIN_GAIN:
        return None
    se = _log_se(f, x, score)
    exit_m = math.exp(float(x[0]))
    effect = StaticHold(exit_distance_m=round(exit_m, 4), speed_threshold_mps=threshold_mps)
    return Fit(effect, {"exit_distance_m": float(exit_m * se[0])})


# Registry rows (fitter, fingerprint) in the shape of :data:`x6wd.gap.fit.EFFECTS`; none is
# refitted through a coarse lattice (each is already fitted by simulation through it).
EFFECTS: dict[str, EffectFitter[PositionSeries, Layout]] = {
    "nav_filter": EffectFitter(fit_nav_filter, FINGERPRINTS["nav_filter"]),
    "noise_scale": EffectFitter(fit_noise_scale, FINGERPRINTS["noise_scale"]),
    "correction": EffectFitter(fit_correction, FINGERPRINTS["correction"]),
    "static_hold": EffectFitter(fit_static_hold, FINGERPRINTS["static_hold"]),
}
