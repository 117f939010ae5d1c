"""Jumps by maximum likelihood on the horizontal steps: a normal scale mixture for the
baseline's own heavy-tailed step law, with a wide jump component on top (:func:`fit_jumps`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from sim_backend.effects import Jumps, PositionSeries
from x6wd.gap.fitted import Fit, IdentityCache
from x6wd.gap.stats import Layout


def _steps(s: PositionSeries, dt_s: float) -> tuple[np.ndarray, np.ndarray]:
    """Horizontal steps (m) between consecutive valid epochs no more than 1.5 dt_s apart (a
    step across an outage is drift, not a jump) and the epoch index each step ends at."""
    v = np.flatnonzero(np.asarray(s.valid, dtype=bool))
    if v.size < 2:
        return np.zeros((0, 2)), np.zeros(0, dtype=int)
    t = np.asarray(s.t_s, dtype=float)[v]
    keep = np.diff(t) <= 1.5 * dt_s
    d = np.stack(
        [np.diff(np.asarray(s.east_m, dtype=float)[v]), np.diff(np.asarray(s.north_m)[v])], 1
    )
    return d[keep], v[1:][keep]


STEP_VAR_FLOOR_M2 = 1e-6  # (1 mm)^2: smallest per-axis step variance of a mixture component


def _log_dens2(r2: np.ndarray, v: float) -> np.ndarray:
    """Log density of a 2-D isotropic normal step (per-axis variance v) at squared length r2."""
    return -r2 / (2.0 * v) - math.log(2.0 * math.pi * v)


def _null_log_dens(r2: np.ndarray, weights: np.ndarray, variances: np.ndarray) -> np.ndarray:
    """Log density of a fixed scale mixture (weights, per-axis variances) at each r2."""
    return np.logaddexp.reduce(
        [math.log(a) + _log_dens2(r2, b) for a, b in zip(weights, variances, strict=True) if a > 0],
        axis=0,
    )


def scale_mixture(
    r2: np.ndarray,
    v_init: Sequence[float],
    null: tuple[np.ndarray, np.ndarray] | None = None,
    v_min: float = 0.0,
    iters: int = 300,
) -> tuple[np.ndarray, np.ndarray, float]:
    """EM for a mixture of 2-D isotropic normal steps on squared lengths ``r2`` (m^2).
    Free components start at per-axis variances ``v_init`` (kept >= ``v_min``); ``null``
    (weights, variances) is a fixed law that takes the remaining weight. Returns (weights,
    variances) of the free components and the total log-likelihood."""
    k = len(v_init)
    w = np.full(k, 1.0 / k if null is None else 0.01 / k)
    v_min = max(v_min, STEP_VAR_FLOOR_M2)  # a lattice makes most steps exactly zero
    v = np.maximum(np.asarray(v_init, dtype=float), v_min)
    nl = None if null is None else _null_log_dens(r2, *null)
    ll = -math.inf
    # (element-wise sums, not np.dot: BLAS calls on 1-D arrays are where threads contend)
    for _ in range(iters):
        parts = np.log(np.maximum(w, 1e-300))[:, None] - r2[None, :] / (2.0 * v[:, None])
        parts -= np.log(2.0 * math.pi * v)[:, None]
        if nl is not None:
            parts = np.vstack([parts, math.log(max(1.0 - w.sum(), 1e-300)) + nl[None, :]])
        tot = np.logaddexp.reduce(parts, axis=0)
        new_ll = float(tot.sum())
        resp = np.exp(parts[:k] - tot[None, :])
        mass = resp.sum(axis=1)
        w = mass / r2.size
        v = np.maximum((resp * r2[None, :]).sum(axis=1) / (2.0 * np.maximum(mass, 1e-12)), v_min)
        if new_ll - ll < 1e-4:  # EM climbs monotonically: converged to 1e-4 nats
            ll = new_ll
            break
        ll = new_ll
    return w, v, ll


JUMP_MIN_WIDTH = 4.0  # a jump step is at least this much wider (variance) than the null's widest
JUMP_MAX_SHARE = 0.05  # at most one step in 20 is a jump
StepLaw = tuple[np.ndarray, np.ndarray, float]
_STEP_LAW_CACHE: IdentityCache[StepLaw | None] = IdentityCache(4)


def _step_law(base: Sequence[PositionSeries], layout: Layout) -> StepLaw | None:
    """The baseline's step law for :func:`fit_jumps`: (weights, per-axis variances) of a
    two-component scale mixture on the pooled steps, and the jump share the jump fit finds in
    the runs themselves (its floor). Cached on the identity of the runs."""
    return _STEP_LAW_CACHE.get(base, (round(layout.dt_s, 6),), lambda: _fit_step_law(base, layout))


def _fit_step_law(base: Sequence[PositionSeries], layout: Layout) -> StepLaw | None:
    bsteps = [np.sum(_steps(s, layout.dt_s)[0] ** 2, axis=1) for s in base]
    pooled = np.concatenate(bsteps) if bsteps else np.zeros(0)
    out: StepLaw | None = None
    if pooled.size >= 10:
        med = max(float(np.median(pooled)), 1e-10) / (2 * math.log(2.0))  # Rayleigh median
        nw, nv, _ = scale_mixture(pooled, [med, 4 * med])
        v_min = JUMP_MIN_WIDTH * float(np.max(nv))
        p_base = float(
            np.mean(
                [scale_mixture(b, [2.5 * v_min], null=(nw, nv), v_min=v_min)[0][0] for b in bsteps]
            )
        )
        out = (nw, nv, p_base)
    return out


def fit_jumps(real: PositionSeries, base: Sequence[PositionSeries], layout: Layout) -> Fit | None:
    """Jumps by maximum likelihood on the horizontal steps: the baseline's own step law is a
    two-component normal scale mixture fitted to its pooled steps (GNSS steps are heavy
    tailed: their spread changes with the geometry); on top of it a jump component, a step
    between two independent N(0, sigma^2) offsets (per-axis variance v + 2 sigma^2), at least
    JUMP_MIN_WIDTH times wider than the null's widest part. The rate is the jump share per
    step less the baseline runs' own share under the same fit. The trigger is "sat_change"
    when the log reports satellite counts and most jumps sit on changes of them, else
    "poisson"."""
    d, at = _steps(real, layout.dt_s)
    r2 = np.sum(d * d, axis=1)
    law = _step_law(base, layout)
    if r2.size < 10 or law is None:
        return None
    nw, nv, p_base = law
    wide = float(np.max(nv))
    ll0 = float(np.sum(_null_log_dens(r2, nw, nv)))
    (p,), (v1,), ll = scale_mixture(r2, [10 * wide], null=(nw, nv), v_min=JUMP_MIN_WIDTH * wide)
    k = (float(p) - p_base) * r2.size
    # Jumps are rare: a step law wider than the baseline's in a large share of the steps is
    # continuous noise (Gauss-Markov, white), whose covariance a dense jump process would only
    # mimic (Poisson jumps of rate r have the autocorrelation of a Gauss-Markov tau = 1/r).
    if ll - ll0 < 3.0 or k < 1.0 or p > JUMP_MAX_SHARE:
        return None  # no step law beyond the baseline's
    v_ref = float(np.dot(nw, nv))  # the baseline's mean step variance under a jump
    sigma = math.sqrt(max(float(v1) - v_ref, 1e-12) / 2.0)
    rate = k / (r2.size * layout.dt_s)
    trigger = "poisson"
    if real.nsats is not None:
        ns = np.asarray(real.nsats)
        change = np.zeros(ns.size, dtype=bool)
        change[1:] = ns[1:] != ns[:-1]
        l_null = math.log1p(-p) + _null_log_dens(r2, nw, nv)
        big = math.log(p) + _log_dens2(r2, float(v1)) > l_null  # steps called jumps
        if np.any(big) and float(np.mean(change[at[big]])) >= 0.5:
            trigger = "sat_change"
    return Fit(
        Jumps(sigma_m=round(sigma, 4), rate_per_s=round(rate, 6), trigger=trigger),
        {"sigma_m": sigma / math.sqrt(2 * k), "rate_per_s": rate / math.sqrt(k)},
    )
