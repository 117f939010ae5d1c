"""The drift family by exact likelihood: none / bias / Gauss-Markov / random walk, with a
bias and a latency as GLS companions, on top of the baseline noise model.

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
from typing import Any

import numpy as np

from sim_backend.effects import Bias, GaussMarkov, Latency, PositionSeries, RandomWalk
from x6wd.gap.fitted import Fit, IdentityCache
from x6wd.gap.kalman import kalman_terms, latency_regressor, quadratic_peak
from x6wd.gap.noise import NoiseModel, noise_model
from x6wd.gap.stats import Layout

# Model names: a drift ("gauss_markov", "random_walk" or none) with GLS companions "+bias"
# (one mean per horizontal axis) and "+latency" (moving logs); the drift alone reads as its
# name, no drift and no companion as "none", companions alone as "bias", "bias+latency" ...
DRIFT_PARAMS = {"gauss_markov": 2, "random_walk": 1, "bias": 2, "latency": 1}
DRIFTS = ("gauss_markov", "random_walk")  # the drift layers proper
DRIFT_FAMILY = (*DRIFTS, "bias")
COMPANIONS = ("bias", "latency")
Flags = tuple[bool, bool]  # (bias, latency)


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
    model. ``loglik`` per model name (see :func:`drift_model_name`); ``gm``/``rw`` per
    companion flags (bias, latency): (parameters, standard errors) in the effects' units;
    ``nobs`` the scalar observations."""

    loglik: dict[str, float]
    gm: dict[Flags, tuple[tuple[float, float], tuple[float, float]]]
    rw: dict[Flags, tuple[float, float]]
    nobs: int
    model: NoiseModel
    # GLS companions at each model's optimum: model name -> (values, standard errors) in the
    # order [bias east (m), bias north (m)] then [latency (s)], as the flags say
    coefs: dict[str, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)

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
        return min(self.gm, key=lambda f: self.bic(drift_model_name(drift, f)))


_DRIFT_CACHE: IdentityCache[DriftFit] = IdentityCache(6)


def drift_fit(real: PositionSeries, base: Sequence[PositionSeries], layout: Layout) -> DriftFit:
    """Fit the drift family to ``real`` on top of the baseline noise model of ``base``: a
    coarse grid over (sigma, tau) and q, then three zooms around each maximum, all in batched
    exact Kalman likelihoods; standard errors from the curvature of the log-likelihood
    (a quadratic through the last zoom grid, in log-parameters). Cached per (real, base)."""
    return _DRIFT_CACHE.get([real, *base], (), lambda: _fit_drift(real, base, layout))


def _fit_drift(real: PositionSeries, base: Sequence[PositionSeries], layout: Layout) -> DriftFit:
    model = noise_model(base, layout)
    dt = layout.dt_s
    span = max(layout.duration_s, 10 * dt)
    # A Gauss-Markov drift is searched in (log q, log tau) with q^2 = 2 sigma^2 / tau its
    # short-term increment rate: the likelihood ridge (increments pin q, the levels tau) is
    # then aligned with the grid, and q is on the random walk's scale.
    lt = np.linspace(math.log(2 * dt), math.log(10 * span), 12)
    lq = np.linspace(math.log(1e-4), math.log(10.0), 15)
    g_t, g_s = (a.ravel() for a in np.meshgrid(lt, lq))
    n_gm = g_t.size

    def gm_var(lq_: np.ndarray, lt_: np.ndarray) -> np.ndarray:
        return np.exp(2 * lq_ + lt_) / 2  # sigma^2 = q^2 tau / 2

    eff_var = np.concatenate([gm_var(g_s, g_t), np.exp(2 * lq), [0.0]])
    eff_tau = np.concatenate([np.exp(g_t), np.full(lq.size, np.inf), [1.0]])
    kt = kalman_terms(real, model, eff_var, eff_tau)
    flag_set: list[Flags] = [(False, False), (True, False)]
    if kt.has_latency:
        flag_set += [(False, True), (True, True)]
    lik = {f: kt.loglik(*f) for f in flag_set}
    loglik = {drift_model_name(None, f): float(lik[f][-1]) for f in flag_set}
    coefs: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    for f in flag_set:
        if any(f):
            c, se_c = kt.coef(*f)
            coefs[drift_model_name(None, f)] = (c[-1], se_c[-1])
    # centres (log q, log tau) / log q and zoom half-widths, per companion flags
    gm_c = {f: np.array([g_s[i], g_t[i]]) for f in lik for i in [int(np.argmax(lik[f][:n_gm]))]}
    rw_c = {f: float(lq[int(np.argmax(lik[f][n_gm:-1]))]) for f in lik}
    gm_h = np.array([lq[1] - lq[0], lt[1] - lt[0]])
    rw_h = lq[1] - lq[0]
    lo_t, hi_t = math.log(0.5 * dt), math.log(10 * span)
    u = np.linspace(-1.0, 1.0, 5)
    du_s, du_t = (a.ravel() for a in np.meshgrid(u, u))
    last: dict[tuple[str, Flags], Any] = {}
    # Zoom: a 5 x 5 (5) grid around each maximum; the grid halves only when the maximum is
    # inside it, otherwise it moves (the coarse grid may have landed off the ridge).
    tags = [(kind, f) for kind in ("gm", "rw") for f in flag_set]
    shrinks = dict.fromkeys(tags, 0)
    halves: dict[tuple[str, Flags], Any] = {
        t: (gm_h.copy() if t[0] == "gm" else rw_h) for t in tags
    }
    for _zoom in range(8):
        if min(shrinks.values()) >= 3:
            break
        batches = []
        for f in flag_set:
            gh, rh = halves[("gm", f)], halves[("rw", f)]
            s_ = gm_c[f][0] + du_s * gh[0]
            t_ = np.clip(gm_c[f][1] + du_t * gh[1], lo_t, hi_t)
            batches.append((gm_var(s_, t_), np.exp(t_), ("gm", f, np.stack([s_, t_], 1))))
            q_ = rw_c[f] + u * rh
            batches.append((np.exp(2 * q_), np.full(u.size, np.inf), ("rw", f, q_[:, None])))
        kt = kalman_terms(
            real,
            model,
            np.concatenate([x[0] for x in batches]),
            np.concatenate([x[1] for x in batches]),
        )
        off = 0
        for ev, _et, (kind, f, pts) in batches:
            ll = kt.loglik(*f)[off : off + ev.size]
            off += ev.size
            j = int(np.argmax(ll))
            tag = (kind, f)
            if tag in last and shrinks[tag] >= 3:
                continue  # this one has converged; keep its last grid
            cf = kt.coef(*f) if any(f) else None
            last[tag] = (
                pts,
                ll,
                None if cf is None else (cf[0][off - ev.size + j], cf[1][off - ev.size + j]),
            )
            if kind == "gm":
                gm_c[f] = pts[j]
                at_bound = not lo_t + 1e-9 < pts[j, 1] < hi_t - 1e-9  # tau clipped
                inside = abs(du_s[j]) < 1 and (abs(du_t[j]) < 1 or at_bound)
            else:
                rw_c[f] = float(pts[j, 0])
                inside = abs(u[j]) < 1
            if inside:
                halves[tag] = halves[tag] / 2
                shrinks[tag] += 1
    gm: dict[Flags, tuple[tuple[float, float], tuple[float, float]]] = {}
    rw: dict[Flags, tuple[float, float]] = {}
    for kind, f in tags:
        pts, ll, cf = last[(kind, f)]
        best_ll = float(np.max(ll))
        q = quadratic_peak(pts, ll)
        centre = pts[int(np.argmax(ll))]
        se = np.full(pts.shape[1], np.nan)
        if q is not None:
            vertex, cov = q
            se = np.sqrt(np.clip(np.diag(cov), 0.0, None))
            # the vertex of the local quadratic when it lies inside the zoom grid
            if np.all(np.abs(vertex - pts.mean(axis=0)) <= np.ptp(pts, axis=0) / 2):
                centre = vertex
        name = "gauss_markov" if kind == "gm" else "random_walk"
        loglik[drift_model_name(name, f)] = best_ll
        if cf is not None:
            coefs[drift_model_name(name, f)] = cf
        if kind == "gm":
            # log sigma = log q + (log tau - log 2) / 2
            sig = math.exp(centre[0] + (centre[1] - math.log(2.0)) / 2)
            tau = math.exp(centre[1])
            se_ls = float("nan")
            if q is not None:
                cov = q[1]
                se_ls = math.sqrt(max(cov[0, 0] + cov[1, 1] / 4 + cov[0, 1], 0.0))
            gm[f] = ((sig, tau), (sig * se_ls, tau * float(se[1])))
        else:
            q_val = math.exp(centre[0])
            rw[f] = (q_val, q_val * float(se[0]))
    return DriftFit(loglik, gm, rw, 2 * kt.nobs, model, coefs)


# Random-walk rates (m/s^0.5) searched by :func:`random_walk_lr`: from far below anything a
# GNSS log shows over an hour up to a walk that dwarfs every baseline.
RW_LR_Q = np.exp(np.linspace(math.log(3e-4), math.log(1.0), 15))


def random_walk_lr(series: PositionSeries, model: NoiseModel) -> float:
    """Signed root of the likelihood ratio "noise model + random walk + bias" against
    "noise model + bias" (exact Kalman likelihood, q profiled on a grid): about half-normal
    when there is no walk. It is the most powerful statistic against a random walk, whose
    variance keeps growing with time where the battery's Allan deviations stop (a tenth of
    the log); its null comes from the baseline runs like any other cell, so it needs no
    asymptotic law. The bias is profiled in both models so a plain offset does not feed it."""
    eff_var = np.concatenate([RW_LR_Q**2, [0.0]])
    eff_tau = np.concatenate([np.full(RW_LR_Q.size, np.inf), [1.0]])
    ll = kalman_terms(series, model, eff_var, eff_tau).loglik(True)
    lr = float(np.max(ll[:-1]) - ll[-1])
    return math.sqrt(2.0 * max(lr, 0.0))


def fit_gauss_markov(
    real: PositionSeries, base: Sequence[PositionSeries], layout: Layout
) -> Fit | None:
    """Horizontal GM (sigma_m, tau_s) by exact likelihood (Kalman filter on the valid epochs,
    phi = exp(-dt/tau) with the actual steps) on top of the baseline noise model fitted to
    ``base``; with a bias profiled out beside it when that lowers the BIC. Standard errors from
    the curvature of the log-likelihood."""
    if len(real) < 32:
        return None
    d = drift_fit(real, base, layout)
    flags = d.companions("gauss_markov")
    sigma, tau = d.gm[flags][0]
    if not (math.isfinite(sigma) and math.isfinite(tau)) or sigma < 1e-4:
        return None
    return drift_effect(d, "gauss_markov", flags, layout)


def drift_effect(d: DriftFit, drift: str, flags: Flags, layout: Layout) -> Fit:
    """The horizontal drift layer of ``d``'s fit with companions ``flags``, rounded for the
    report; a Gauss-Markov tau is capped at ten log lengths (beyond, it is a walk or bias)."""
    if drift == "gauss_markov":
        (sigma, tau), (se_s, se_t) = d.gm[flags]
        return Fit(
            GaussMarkov(sigma_m=round(sigma, 4), tau_s=round(min(tau, 10 * layout.duration_s), 3)),
            {"sigma_m": se_s, "tau_s": se_t},
        )
    q, se_q = d.rw[flags]
    return Fit(RandomWalk(q_m_per_sqrt_s=round(q, 6)), {"q_m_per_sqrt_s": se_q})


def joint_drift_fits(
    real: PositionSeries,
    base: Sequence[PositionSeries],
    layout: Layout,
    drift: str,
    flags: Flags,
) -> list[Fit]:
    """The drift ("gauss_markov" or "random_walk") and its GLS companions (bias, latency, as
    ``flags`` say) from ONE exact-likelihood fit on top of the baseline noise model: the
    parameters of each are estimated with the others in the model, so a speed-correlated or
    constant error is not soaked up by the drift (and vice versa)."""
    d = drift_fit(real, base, layout)
    name = drift_model_name(drift, flags)
    if name not in d.loglik:
        return []
    out = [drift_effect(d, drift, flags, layout)]
    coef, se = d.coefs.get(name, (np.zeros(0), np.zeros(0)))
    if flags[0] and coef.size >= 2:
        up = fit_bias(real, base, layout)  # the GLS is horizontal; up from the means
        up_m = float(up.params.get("up_m", 0.0)) if up is not None else 0.0
        up_se = float(up.se.get("up_m", 0.0)) if up is not None else 0.0
        out.append(
            Fit(
                Bias(east_m=round(float(coef[0]), 4), north_m=round(float(coef[1]), 4), up_m=up_m),
                {"east_m": float(se[0]), "north_m": float(se[1]), "up_m": up_se},
            )
        )
    if flags[1] and coef.size >= 1 and float(coef[-1]) > 0:
        out.append(Fit(Latency(delay_s=round(float(coef[-1]), 4)), {"delay_s": float(se[-1])}))
    return out


def fit_random_walk(
    real: PositionSeries, base: Sequence[PositionSeries], layout: Layout
) -> Fit | None:
    """Horizontal random walk q (m/sqrt(s)) by exact likelihood on top of the baseline noise
    model: its increments are white with variance q^2 dt over the baseline's own increments,
    and its level starts at zero and spreads as q^2 t (the filter carries both)."""
    if len(real) < 32:
        return None
    d = drift_fit(real, base, layout)
    flags = d.companions("random_walk")
    q = d.rw[flags][0]
    if not math.isfinite(q) or q < 1e-6:
        return None
    return drift_effect(d, "random_walk", flags, layout)


def fit_bias(real: PositionSeries, base: Sequence[PositionSeries], layout: Layout) -> Fit | None:
    """Bias = real mean - baseline mean per axis; standard error from the baseline's spread of
    means (the honest sampling error of a time-correlated mean)."""
    axes = ("east_m", "north_m", "up_m") if layout.has_up else ("east_m", "north_m")
    vals: dict[str, float] = {}
    se: dict[str, float] = {}
    v = np.asarray(real.valid, dtype=bool)
    if not np.any(v):
        return None
    for ax in axes:
        r = float(np.mean(np.asarray(getattr(real, ax))[v]))
        b = np.array(
            [
                float(np.mean(np.asarray(getattr(s, ax))[np.asarray(s.valid, dtype=bool)]))
                for s in base
            ]
        )
        vals[ax] = round(r - float(b.mean()), 4)
        se[ax] = float(b.std(ddof=1)) * math.sqrt(1 + 1 / len(base))
    return Fit(Bias(**vals), se)


def fit_latency(real: PositionSeries, base: Sequence[PositionSeries], layout: Layout) -> Fit | None:
    """Latency by exact GLS: the delay d whose error -d x velocity, with a bias per axis,
    best explains the log on top of the baseline noise model (Kalman innovations of the
    data, the ones and the velocity regressor; see :class:`KalmanTerms`)."""
    if not layout.moving or latency_regressor(real) is None:
        return None
    kt = kalman_terms(real, noise_model(base, layout), np.zeros(1), np.ones(1))
    coef, se = kt.coef(True, True)
    delay, se_d = float(coef[0, -1]), float(se[0, -1])
    if not math.isfinite(delay) or delay <= 0:
        return None
    return Fit(Latency(delay_s=round(delay, 4)), {"delay_s": se_d})
