"""The drift family by exact likelihood: none / bias / Gauss-Markov (first or second order) /
random walk, with a bias and a latency as GLS companions, on top of the baseline noise model.

:func:`drift_fit` evaluates every member on one log with the Kalman filter of
:mod:`x6wd.gap.kalman` (batched grids and zooms) and names the best by BIC; the per-effect
fitters of the family (:func:`fit_bias`, :func:`fit_gauss_markov`, :func:`fit_random_walk`,
:func:`fit_latency`, :func:`joint_drift_fits`) read their layers off it.
:func:`random_walk_lr` is the battery's whole-log likelihood-ratio cell.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from sim_backend.effects import Bias, GaussMarkov, Latency, PositionSeries, RandomWalk
from x6wd.gap.fitted import Fit, IdentityCache
from x6wd.gap.kalman import kalman_terms, latency_regressor, quadratic_peak
from x6wd.gap.noise import NoiseModel, noise_model
from x6wd.gap.stats import Layout, with_despiked

# Model names: a drift ("gauss_markov", "random_walk" or none) with GLS companions "+bias"
# (one mean per horizontal axis) and "+latency" (moving logs); the drift alone reads as its
# name, no drift and no companion as "none", companions alone as "bias", "bias+latency" ...
DRIFT_PARAMS = {"gauss_markov": 2, "random_walk": 1, "bias": 2, "latency": 1}
DRIFTS = ("gauss_markov", "random_walk")  # the drift layers proper
DRIFT_FAMILY = (*DRIFTS, "bias")
COMPANIONS = ("bias", "latency")
Flags = tuple[bool, bool]  # (bias, latency)
GmParams = tuple[tuple[float, float], tuple[float, float]]  # (sigma_m, tau_s), standard errors


def drift_model_name(drift: str | None, flags: Flags) -> str:
    """The model name of a drift ("gauss_markov", "random_walk", None) with companions."""
    parts = [drift] if drift else []
    parts += [c for c, on in zip(COMPANIONS, flags, strict=True) if on]
    return "+".join(parts) or "none"


def _n_params(name: str) -> int:
    return 0 if name == "none" else sum(DRIFT_PARAMS[p] for p in name.split("+"))


@dataclass(frozen=True)
class DriftFit:
    """Exact-likelihood fits of the drift family to one log on top of the baseline noise
    model. ``loglik`` per model name (see :func:`drift_model_name`); per (companion flags
    (bias, latency), order 1 or 2) ``gm_by_order`` ((sigma_m, tau_s), their standard
    errors); per flags ``gm_order``, the order with the higher likelihood (both have two
    parameters), and ``random_walk`` (q_m_per_sqrt_s, its standard error); ``nobs`` the
    scalar observations."""

    loglik: dict[str, float]
    gm_by_order: dict[tuple[Flags, int], GmParams]
    gm_order: dict[Flags, int]
    random_walk: dict[Flags, tuple[float, float]]
    nobs: int
    model: NoiseModel
    # GLS companions at each model's optimum: model name -> (values, standard errors) in the
    # order [bias east (m), bias north (m)] then [latency (s)], as the flags say
    coefs: dict[str, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)

    @property
    def gauss_markov(self) -> dict[Flags, GmParams]:
        """Per companion flags, the likelier order's Gauss-Markov fit."""
        return {flags: self.gm_by_order[(flags, o)] for flags, o in self.gm_order.items()}

    @property
    def models(self) -> list[str]:
        return list(self.loglik)

    def bic(self, name: str) -> float:
        """Bayesian information criterion (lower is better)."""
        return -2.0 * self.loglik[name] + _n_params(name) * math.log(max(self.nobs, 2))

    @property
    def best(self) -> str:
        """The model with the lowest BIC."""
        return min(self.models, key=self.bic)

    @property
    def best_effect(self) -> str:
        """The effect model (not "none") with the lowest BIC: which member of the family
        explains a drift, once the battery has said there is a gap to explain."""
        return min((m for m in self.models if m != "none"), key=self.bic)

    def companions(self, drift: str) -> Flags:
        """The companion flags (bias, latency) with which ``drift`` has the lowest BIC."""
        return min(self.gm_order, key=lambda f: self.bic(drift_model_name(drift, f)))


_DRIFT_CACHE: IdentityCache[DriftFit] = IdentityCache(6)


def drift_fit(real: PositionSeries, baseline: Sequence[PositionSeries], layout: Layout) -> DriftFit:
    """Fit the drift family to ``real`` (errors, m) on top of the noise model of the
    ``baseline`` runs: a coarse grid over (sigma, tau) and q, then zooms around each maximum,
    all in batched exact Kalman likelihoods; standard errors from the curvature of the
    log-likelihood (a quadratic through the last zoom grid, in log-parameters). Cached per
    (real, baseline)."""
    return _DRIFT_CACHE.get([real, *baseline], (), lambda: _fit_drift(real, baseline, layout))


@dataclass
class _Zoom:
    """One zoom of :func:`_fit_drift` (a drift kind under companion flags): its centre and
    half-widths in log-parameters ((log q, log tau) for "gm", (log q,) for "rw"), halvings so
    far, and its last grid (points, log-likelihoods, GLS companions at the best point)."""

    centre: np.ndarray
    half_width: np.ndarray
    halvings: int = 0
    points: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    loglik: np.ndarray = field(default_factory=lambda: np.zeros(0))
    gls: tuple[np.ndarray, np.ndarray] | None = None
    scored: bool = False


def _gm_variance_m2(log_q: np.ndarray, log_tau: np.ndarray) -> np.ndarray:
    """Stationary variance sigma^2 (m^2) of a Gauss-Markov drift of increment rate q
    (m/sqrt(s)) and correlation time tau (s): sigma^2 = q^2 tau / 2."""
    return np.exp(2 * log_q + log_tau) / 2


def _fit_drift(
    real: PositionSeries, baseline: Sequence[PositionSeries], layout: Layout
) -> DriftFit:
    model = noise_model(baseline, layout)
    dt_s = layout.dt_s
    span_s = max(layout.duration_s, 10 * dt_s)
    # A Gauss-Markov drift is searched in (log q, log tau) with q^2 = 2 sigma^2 / tau its
    # short-term increment rate: the likelihood ridge (increments pin q, the levels tau) is
    # then aligned with the grid, and q is on the random walk's scale.
    log_tau_axis = np.linspace(math.log(2 * dt_s), math.log(10 * span_s), 12)
    log_q_axis = np.linspace(math.log(1e-4), math.log(10.0), 15)
    grid_log_tau, grid_log_q = (a.ravel() for a in np.meshgrid(log_tau_axis, log_q_axis))
    n_gm = grid_log_tau.size
    # one batch: the Gauss-Markov grid, the random-walk axis, and no effect (last)
    effect_var = np.concatenate(
        [_gm_variance_m2(grid_log_q, grid_log_tau), np.exp(2 * log_q_axis), [0.0]]
    )
    effect_tau_s = np.concatenate([np.exp(grid_log_tau), np.full(log_q_axis.size, np.inf), [1.0]])
    # the latency companion's regressor is taken at the delay fitted without a drift
    latency = latency_gls(real, model) if layout.moving else None
    near_s = 0.0 if latency is None else latency[0]
    terms = kalman_terms(real, model, effect_var, effect_tau_s, latency_near_s=near_s)
    # the same grid for a critically damped (second-order) drift: its own filter
    terms2 = kalman_terms(
        real, model, effect_var[:n_gm], effect_tau_s[:n_gm], order=2, latency_near_s=near_s
    )
    flag_set: list[Flags] = [(False, False), (True, False)]
    if terms.has_latency:
        flag_set += [(False, True), (True, True)]
    coarse = {flags: terms.loglik(*flags) for flags in flag_set}
    coarse2 = {flags: terms2.loglik(*flags) for flags in flag_set}
    loglik = {drift_model_name(None, flags): float(coarse[flags][-1]) for flags in flag_set}
    coefs: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    for flags in flag_set:
        if any(flags):
            coef, se_coef = terms.coef(*flags)
            coefs[drift_model_name(None, flags)] = (coef[-1], se_coef[-1])
    # Zoom: a 5 x 5 (5) grid around each coarse maximum, per drift kind and companion flags;
    # the grid halves only when the maximum is inside it, otherwise it moves (the coarse grid
    # may have landed off the ridge).
    step_log_q = log_q_axis[1] - log_q_axis[0]
    zooms: dict[tuple[str, Flags], _Zoom] = {}
    for flags in flag_set:
        for kind, grid_loglik in (("gm", coarse[flags][:n_gm]), ("gm2", coarse2[flags])):
            i = int(np.argmax(grid_loglik))
            zooms[(kind, flags)] = _Zoom(
                np.array([grid_log_q[i], grid_log_tau[i]]),
                np.array([step_log_q, log_tau_axis[1] - log_tau_axis[0]]),
            )
    for flags in flag_set:
        i = int(np.argmax(coarse[flags][n_gm:-1]))
        zooms[("rw", flags)] = _Zoom(np.array([log_q_axis[i]]), np.array([step_log_q]))
    log_tau_min, log_tau_max = math.log(0.5 * dt_s), math.log(10 * span_s)
    unit = np.linspace(-1.0, 1.0, 5)
    unit_q, unit_tau = (a.ravel() for a in np.meshgrid(unit, unit))
    for _round in range(8):
        if min(z.halvings for z in zooms.values()) >= 3:
            break
        batches = []
        for flags in flag_set:
            for kind in ("gm", "gm2"):
                gm = zooms[(kind, flags)]
                log_q = gm.centre[0] + unit_q * gm.half_width[0]
                log_tau = np.clip(
                    gm.centre[1] + unit_tau * gm.half_width[1], log_tau_min, log_tau_max
                )
                batches.append(
                    (_gm_variance_m2(log_q, log_tau), np.exp(log_tau), (kind, flags),
                     np.stack([log_q, log_tau], 1))
                )  # fmt: skip
            rw = zooms[("rw", flags)]
            log_q_rw = rw.centre[0] + unit * rw.half_width[0]
            batches.append(
                (np.exp(2 * log_q_rw), np.full(unit.size, np.inf), ("rw", flags),
                 log_q_rw[:, None])
            )  # fmt: skip
        by_order = {
            order: [b for b in batches if (b[2][0] == "gm2") == (order == 2)] for order in (1, 2)
        }
        order_terms = {
            order: kalman_terms(
                real,
                model,
                np.concatenate([b[0] for b in group]),
                np.concatenate([b[1] for b in group]),
                order=order,
                latency_near_s=near_s,
            )
            for order, group in by_order.items()
        }
        offsets = {1: 0, 2: 0}
        for var, _tau, key, points in batches:
            flags, order = key[1], 2 if key[0] == "gm2" else 1
            terms, offset = order_terms[order], offsets[order]
            grid_loglik = terms.loglik(*flags)[offset : offset + var.size]
            offset = offsets[order] = offset + var.size
            j = int(np.argmax(grid_loglik))
            zoom = zooms[key]
            if zoom.scored and zoom.halvings >= 3:
                continue  # this one has converged; keep its last grid
            gls = terms.coef(*flags) if any(flags) else None
            zoom.points, zoom.loglik, zoom.scored = points, grid_loglik, True
            zoom.gls = (
                None if gls is None
                else (gls[0][offset - var.size + j], gls[1][offset - var.size + j])
            )  # fmt: skip
            zoom.centre = points[j]
            if key[0] != "rw":
                at_bound = not log_tau_min + 1e-9 < points[j, 1] < log_tau_max - 1e-9
                inside = abs(unit_q[j]) < 1 and (abs(unit_tau[j]) < 1 or at_bound)
            else:
                inside = abs(unit[j]) < 1
            if inside:
                zoom.half_width = zoom.half_width / 2
                zoom.halvings += 1
    gm_order: dict[Flags, int] = {}
    gm_by_order: dict[tuple[Flags, int], GmParams] = {}
    random_walk: dict[Flags, tuple[float, float]] = {}
    for (kind, flags), zoom in zooms.items():
        peak = quadratic_peak(zoom.points, zoom.loglik)
        centre = zoom.points[int(np.argmax(zoom.loglik))]
        se_log = np.full(zoom.points.shape[1], np.nan)
        if peak is not None:
            vertex, cov = peak
            se_log = np.sqrt(np.clip(np.diag(cov), 0.0, None))
            # the vertex of the local quadratic when it lies inside the zoom grid
            if np.all(np.abs(vertex - zoom.points.mean(axis=0)) <= np.ptp(zoom.points, axis=0) / 2):
                centre = vertex
        name = drift_model_name("random_walk" if kind == "rw" else "gauss_markov", flags)
        if kind == "rw":
            loglik[name] = float(np.max(zoom.loglik))
            if zoom.gls is not None:
                coefs[name] = zoom.gls
            q = math.exp(centre[0])
            random_walk[flags] = (q, q * float(se_log[0]))
            continue
        order = 2 if kind == "gm2" else 1
        # log sigma = log q + (log tau - log 2) / 2
        sigma_m = math.exp(centre[0] + (centre[1] - math.log(2.0)) / 2)
        tau_s = math.exp(centre[1])
        se_log_sigma = float("nan")
        if peak is not None:
            cov = peak[1]
            se_log_sigma = math.sqrt(max(cov[0, 0] + cov[1, 1] / 4 + cov[0, 1], 0.0))
        gm_by_order[(flags, order)] = (
            (sigma_m, tau_s), (sigma_m * se_log_sigma, tau_s * float(se_log[1]))
        )  # fmt: skip
        if order == 2 and float(np.max(zoom.loglik)) <= loglik[name]:
            continue  # "gauss_markov" is whichever order has the higher likelihood
        loglik[name] = float(np.max(zoom.loglik))
        if zoom.gls is not None:
            coefs[name] = zoom.gls
        gm_order[flags] = order
    return DriftFit(loglik, gm_by_order, gm_order, random_walk, 2 * terms.nobs, model, coefs)


# Random-walk rates (m/s^0.5) searched by :func:`random_walk_lr`: from far below anything a
# GNSS log shows over an hour up to a walk that dwarfs every baseline.
RW_LR_Q = np.exp(np.linspace(math.log(3e-4), math.log(1.0), 15))


def random_walk_lr(series: PositionSeries, model: NoiseModel, despike: bool = False) -> float:
    """Signed root of the likelihood ratio "noise model + random walk + bias" against
    "noise model + bias" (exact Kalman likelihood, q profiled on a grid): about half-normal
    when there is no walk. It is the most powerful statistic against a random walk, whose
    variance keeps growing with time where the battery's Allan deviations stop (a tenth of
    the log); its null comes from the baseline runs like any other cell, so it needs no
    asymptotic law. The bias is profiled in both models so a plain offset does not feed it.
    ``despike``: read with the short spikes taken out (:func:`~x6wd.gap.stats.despiked`), for
    a few logs' replicates, which are coloured innovations and rarely carry a spike: one
    epoch's 26 m geometry spike set a no-effect hour's ratio 7 spreads off them. Against
    simulator runs the raw ratio is right: the runs show its heavy tail themselves, spikes
    and all; despiked, most of their ratios fell to 0 while some no-effect hours kept 6-16
    (longer excursions), and 9 of 240 such hours were flagged on this cell alone."""
    if despike:
        series = with_despiked(series)
    effect_var = np.concatenate([RW_LR_Q**2, [0.0]])
    effect_tau_s = np.concatenate([np.full(RW_LR_Q.size, np.inf), [1.0]])
    loglik = kalman_terms(series, model, effect_var, effect_tau_s).loglik(True)
    log_ratio = float(np.max(loglik[:-1]) - loglik[-1])
    return math.sqrt(2.0 * max(log_ratio, 0.0))


def fit_gauss_markov(
    real: PositionSeries,
    baseline: Sequence[PositionSeries],
    layout: Layout,
    order: int | None = None,
) -> Fit | None:
    """Horizontal GM (sigma_m, tau_s) by exact likelihood (Kalman filter on the valid epochs,
    the exact discretisation with the actual steps) on top of the noise model of the
    ``baseline`` runs; with a bias profiled out beside it when that lowers the BIC. Standard
    errors from the curvature of the log-likelihood. ``order`` 1 or 2: that order's best
    fit; None: the order with the higher likelihood."""
    if len(real) < 32:
        return None
    family = drift_fit(real, baseline, layout)
    flags = family.companions("gauss_markov")
    sigma_m, tau_s = family.gm_by_order[(flags, order or family.gm_order[flags])][0]
    if not (math.isfinite(sigma_m) and math.isfinite(tau_s)) or sigma_m < 1e-4:
        return None
    return drift_effect(family, "gauss_markov", flags, layout, order)


def drift_effect(
    family: DriftFit, drift: str, flags: Flags, layout: Layout, order: int | None = None
) -> Fit:
    """The horizontal drift layer of ``family``'s fit with companions ``flags``, rounded for
    the report; a Gauss-Markov tau is capped at ten log lengths (beyond, it is a walk or a
    bias); ``order`` a Gauss-Markov order (None: the likelier)."""
    if drift == "gauss_markov":
        order = order or family.gm_order[flags]
        (sigma_m, tau_s), (se_sigma_m, se_tau_s) = family.gm_by_order[(flags, order)]
        tau_s = min(tau_s, 10 * layout.duration_s)
        return Fit(
            GaussMarkov(sigma_m=round(sigma_m, 4), tau_s=round(tau_s, 3), order=order),
            {"sigma_m": se_sigma_m, "tau_s": se_tau_s},
        )
    q, se_q = family.random_walk[flags]
    return Fit(RandomWalk(q_m_per_sqrt_s=round(q, 6)), {"q_m_per_sqrt_s": se_q})


def joint_drift_fits(
    real: PositionSeries,
    baseline: Sequence[PositionSeries],
    layout: Layout,
    drift: str,
    flags: Flags,
    order: int | None = None,
) -> list[Fit]:
    """The drift ("gauss_markov" or "random_walk") and its GLS companions (bias, latency, as
    ``flags`` say) from ONE exact-likelihood fit on top of the baseline noise model: the
    parameters of each are estimated with the others in the model, so a speed-correlated or
    constant error is not soaked up by the drift (and vice versa). ``order``: a Gauss-Markov
    drift's order (None: the likelier); the companions are those of the likelier order."""
    family = drift_fit(real, baseline, layout)
    name = drift_model_name(drift, flags)
    if name not in family.loglik:
        return []
    out = [drift_effect(family, drift, flags, layout, order)]
    coef, se = family.coefs.get(name, (np.zeros(0), np.zeros(0)))
    if flags[0] and coef.size >= 2:
        up = fit_bias(real, baseline, layout)  # the GLS is horizontal; up from the means
        up_m = float(up.params.get("up_m", 0.0)) if up is not None else 0.0
        se_up_m = float(up.se.get("up_m", 0.0)) if up is not None else 0.0
        east_m, north_m = round(float(coef[0]), 4), round(float(coef[1]), 4)
        out.append(
            Fit(
                Bias(east_m=east_m, north_m=north_m, up_m=up_m),
                {"east_m": float(se[0]), "north_m": float(se[1]), "up_m": se_up_m},
            )
        )
    if flags[1] and coef.size >= 1 and float(coef[-1]) > 0:
        out.append(Fit(Latency(delay_s=round(float(coef[-1]), 4)), {"delay_s": float(se[-1])}))
    return out


def fit_random_walk(
    real: PositionSeries, baseline: Sequence[PositionSeries], layout: Layout
) -> Fit | None:
    """Horizontal random walk q (m/sqrt(s)) by exact likelihood on top of the baseline noise
    model: its increments are white with variance q^2 dt over the baseline's own increments,
    and its level starts at zero and spreads as q^2 t (the filter carries both)."""
    if len(real) < 32:
        return None
    family = drift_fit(real, baseline, layout)
    flags = family.companions("random_walk")
    q = family.random_walk[flags][0]
    if not math.isfinite(q) or q < 1e-6:
        return None
    return drift_effect(family, "random_walk", flags, layout)


def fit_bias(
    real: PositionSeries, baseline: Sequence[PositionSeries], layout: Layout
) -> Fit | None:
    """Bias (m) = real mean - baseline mean per axis; standard error from the baseline's
    spread of means (the honest sampling error of a time-correlated mean)."""
    axes = ("east_m", "north_m", "up_m") if layout.has_up else ("east_m", "north_m")
    bias_m: dict[str, float] = {}
    se_m: dict[str, float] = {}
    valid = np.asarray(real.valid, dtype=bool)
    # A run without a fix in this part (a log with a long hole: its outages shape the runs)
    # has no mean: it is left out; fewer than two runs with one give no standard error.
    runs = [(s, ok) for s in baseline if np.any(ok := np.asarray(s.valid, dtype=bool))]
    if not np.any(valid) or len(runs) < 2:
        return None
    for axis in axes:
        real_mean_m = float(np.mean(np.asarray(getattr(real, axis))[valid]))
        run_means_m = np.array([float(np.mean(np.asarray(getattr(s, axis))[ok])) for s, ok in runs])
        bias_m[axis] = round(real_mean_m - float(run_means_m.mean()), 4)
        se_m[axis] = float(run_means_m.std(ddof=1)) * math.sqrt(1 + 1 / len(runs))
    return Fit(Bias(**bias_m), se_m)


# The latency's regressor is the exact error of a delay over it, taken at the delay fitted
# last (x6wd.gap.kalman.latency_regressor): a fixed point reached in 4-6 rounds on a 234 s
# zigzag's fit part (2 s: 1.49, 1.95, 2.01, 2.02; 4 s: 1.88, 2.70, 3.43, 3.89, 4.04, 4.07)
LATENCY_ROUNDS = 8
LATENCY_TOLERANCE_S = 0.01


def latency_gls(real: PositionSeries, model: NoiseModel) -> tuple[float, float] | None:
    """The delay (s) and its standard error by exact GLS with a bias per axis on top of the
    noise ``model``, iterated to a fixed point of the regressor's delay; None when the log
    does not move or no positive delay fits. Should the iteration leave the log's span
    (a delay beyond a quarter of it), turn non-positive or take growing steps, the first
    round's estimate (-velocity's, as before 2026-12-08) is kept."""
    if latency_regressor(real) is None:
        return None
    t_s = np.asarray(real.t_s, dtype=float)
    limit_s = 0.25 * float(t_s[-1] - t_s[0])
    near_s, step_s = 0.0, math.inf
    first: tuple[float, float] | None = None
    for _ in range(LATENCY_ROUNDS):
        terms = kalman_terms(real, model, np.zeros(1), np.ones(1), latency_near_s=near_s)
        coef, se = terms.coef(True, True)
        delay_s, se_delay_s = float(coef[0, -1]), float(se[0, -1])
        if not (math.isfinite(delay_s) and 0.0 < delay_s <= limit_s):
            return first
        if first is None:  # -velocity's estimate: the iteration starts from it
            first = (delay_s, se_delay_s)
            near_s = delay_s
            continue
        step = abs(delay_s - near_s)
        if step > step_s:  # steps that grow: moving away from a fixed point
            return first
        if step < LATENCY_TOLERANCE_S:
            break
        near_s, step_s = delay_s, step
    return delay_s, se_delay_s


def fit_latency(
    real: PositionSeries, baseline: Sequence[PositionSeries], layout: Layout
) -> Fit | None:
    """Latency by exact GLS (:func:`latency_gls`): the delay (s) whose error, with a bias per
    axis, best explains the log on top of the baseline noise model (Kalman innovations of the
    data, the ones and the delay's regressor; see :class:`x6wd.gap.kalman.KalmanTerms`)."""
    if not layout.moving:
        return None
    gls = latency_gls(real, noise_model(baseline, layout))
    if gls is None:
        return None
    delay_s, se_delay_s = gls
    return Fit(Latency(delay_s=round(delay_s, 4)), {"delay_s": se_delay_s})
