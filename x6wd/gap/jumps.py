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


def _steps(series: PositionSeries, dt_s: float) -> tuple[np.ndarray, np.ndarray]:
    """Horizontal steps (n, 2; m) between consecutive valid epochs no more than 1.5 dt_s
    apart (a step across an outage is drift, not a jump) and the epoch index each ends at."""
    valid_idx = np.flatnonzero(np.asarray(series.valid, dtype=bool))
    if valid_idx.size < 2:
        return np.zeros((0, 2)), np.zeros(0, dtype=int)
    t_s = np.asarray(series.t_s, dtype=float)[valid_idx]
    keep = np.diff(t_s) <= 1.5 * dt_s
    steps_m = np.stack(
        [
            np.diff(np.asarray(series.east_m, dtype=float)[valid_idx]),
            np.diff(np.asarray(series.north_m)[valid_idx]),
        ],
        1,
    )
    return steps_m[keep], valid_idx[1:][keep]


STEP_VAR_FLOOR_M2 = 1e-6  # (1 mm)^2: smallest per-axis step variance of a mixture component


def _log_dens2(r2_m2: np.ndarray, var_m2: float) -> np.ndarray:
    """Log density of a 2-D isotropic normal step (per-axis variance ``var_m2``) at squared
    length ``r2_m2``."""
    return -r2_m2 / (2.0 * var_m2) - math.log(2.0 * math.pi * var_m2)


def _null_log_dens(r2_m2: np.ndarray, weights: np.ndarray, vars_m2: np.ndarray) -> np.ndarray:
    """Log density of a fixed scale mixture (weights, per-axis variances) at each r2."""
    return np.logaddexp.reduce(
        [
            math.log(w) + _log_dens2(r2_m2, v)
            for w, v in zip(weights, vars_m2, strict=True)
            if w > 0
        ],
        axis=0,
    )


def scale_mixture(
    r2_m2: np.ndarray,
    var_init_m2: Sequence[float],
    null: tuple[np.ndarray, np.ndarray] | None = None,
    var_min_m2: float = 0.0,
    iters: int = 300,
) -> tuple[np.ndarray, np.ndarray, float]:
    """EM for a mixture of 2-D isotropic normal steps on squared lengths ``r2_m2`` (m^2).
    Free components start at per-axis variances ``var_init_m2`` (kept >= ``var_min_m2``);
    ``null`` (weights, variances) is a fixed law that takes the remaining weight. Returns
    (weights, variances) of the free components and the total log-likelihood."""
    k = len(var_init_m2)
    weight = np.full(k, 1.0 / k if null is None else 0.01 / k)
    var_min_m2 = max(var_min_m2, STEP_VAR_FLOOR_M2)  # a lattice makes most steps exactly zero
    var_m2 = np.maximum(np.asarray(var_init_m2, dtype=float), var_min_m2)
    null_log_dens = None if null is None else _null_log_dens(r2_m2, *null)
    loglik = -math.inf
    # (element-wise sums, not np.dot: BLAS calls on 1-D arrays are where threads contend)
    for _ in range(iters):
        parts = np.log(np.maximum(weight, 1e-300))[:, None] - r2_m2[None, :] / (
            2.0 * var_m2[:, None]
        )
        parts -= np.log(2.0 * math.pi * var_m2)[:, None]
        if null_log_dens is not None:
            rest = math.log(max(1.0 - weight.sum(), 1e-300))
            parts = np.vstack([parts, rest + null_log_dens[None, :]])
        total = np.logaddexp.reduce(parts, axis=0)
        new_loglik = float(total.sum())
        resp = np.exp(parts[:k] - total[None, :])
        mass = resp.sum(axis=1)
        weight = mass / r2_m2.size
        var_m2 = np.maximum(
            (resp * r2_m2[None, :]).sum(axis=1) / (2.0 * np.maximum(mass, 1e-12)), var_min_m2
        )
        if new_loglik - loglik < 1e-4:  # EM climbs monotonically: converged to 1e-4 nats
            loglik = new_loglik
            break
        loglik = new_loglik
    return weight, var_m2, loglik


JUMP_MIN_WIDTH = 4.0  # a jump step is at least this much wider (variance) than the null's widest
JUMP_MAX_SHARE = 0.05  # at most one step in 20 is a jump
# (weights, per-axis variances m^2) of the baseline's step mixture, its own jump share
StepLaw = tuple[np.ndarray, np.ndarray, float]
_STEP_LAW_CACHE: IdentityCache[StepLaw | None] = IdentityCache(4)


def _step_law(baseline: Sequence[PositionSeries], layout: Layout) -> StepLaw | None:
    """The baseline's step law for :func:`fit_jumps`: (weights, per-axis variances) of a
    two-component scale mixture on the pooled steps, and the jump share the jump fit finds in
    the runs themselves (its floor). Cached on the identity of the runs."""
    return _STEP_LAW_CACHE.get(
        baseline, (round(layout.dt_s, 6),), lambda: _fit_step_law(baseline, layout)
    )


def _fit_step_law(baseline: Sequence[PositionSeries], layout: Layout) -> StepLaw | None:
    run_r2_m2 = [np.sum(_steps(s, layout.dt_s)[0] ** 2, axis=1) for s in baseline]
    pooled = np.concatenate(run_r2_m2) if run_r2_m2 else np.zeros(0)
    if pooled.size < 10:
        return None
    # per-axis variance from the median squared step (a Rayleigh length's median)
    var0_m2 = max(float(np.median(pooled)), 1e-10) / (2 * math.log(2.0))
    null_weights, null_vars_m2, _ = scale_mixture(pooled, [var0_m2, 4 * var0_m2])
    jump_var_min_m2 = JUMP_MIN_WIDTH * float(np.max(null_vars_m2))
    baseline_share = float(
        np.mean(
            [
                scale_mixture(
                    r2, [2.5 * jump_var_min_m2], null=(null_weights, null_vars_m2),
                    var_min_m2=jump_var_min_m2,
                )[0][0]
                for r2 in run_r2_m2
            ]
        )
    )  # fmt: skip
    return null_weights, null_vars_m2, baseline_share


def fit_jumps(
    real: PositionSeries, baseline: Sequence[PositionSeries], layout: Layout
) -> Fit | None:
    """Jumps by maximum likelihood on the horizontal steps: the baseline's own step law is a
    two-component normal scale mixture fitted to its pooled steps (GNSS steps are heavy
    tailed: their spread changes with the geometry); on top of it a jump component, a step
    between two independent N(0, sigma^2) offsets (per-axis variance v + 2 sigma^2), at least
    JUMP_MIN_WIDTH times wider than the null's widest part. The rate is the jump share per
    step less the baseline runs' own share under the same fit. The trigger is "sat_change"
    when the log reports satellite counts and most jumps sit on changes of them, else
    "poisson"."""
    steps_m, step_end = _steps(real, layout.dt_s)
    r2_m2 = np.sum(steps_m * steps_m, axis=1)
    law = _step_law(baseline, layout)
    if r2_m2.size < 10 or law is None:
        return None
    null_weights, null_vars_m2, baseline_share = law
    widest_m2 = float(np.max(null_vars_m2))
    null_loglik = float(np.sum(_null_log_dens(r2_m2, null_weights, null_vars_m2)))
    (share,), (jump_var_m2,), loglik = scale_mixture(
        r2_m2, [10 * widest_m2], null=(null_weights, null_vars_m2),
        var_min_m2=JUMP_MIN_WIDTH * widest_m2,
    )  # fmt: skip
    n_jumps = (float(share) - baseline_share) * r2_m2.size
    # Jumps are rare: a step law wider than the baseline's in a large share of the steps is
    # continuous noise (Gauss-Markov, white), whose covariance a dense jump process would only
    # mimic (Poisson jumps of rate r have the autocorrelation of a Gauss-Markov tau = 1/r).
    if loglik - null_loglik < 3.0 or n_jumps < 1.0 or share > JUMP_MAX_SHARE:
        return None  # no step law beyond the baseline's
    ref_var_m2 = float(np.dot(null_weights, null_vars_m2))  # the baseline's mean step variance
    sigma_m = math.sqrt(max(float(jump_var_m2) - ref_var_m2, 1e-12) / 2.0)
    rate_per_s = n_jumps / (r2_m2.size * layout.dt_s)
    trigger = "poisson"
    if real.nsats is not None:
        nsats = np.asarray(real.nsats)
        change = np.zeros(nsats.size, dtype=bool)
        change[1:] = nsats[1:] != nsats[:-1]
        null_log = math.log1p(-share) + _null_log_dens(r2_m2, null_weights, null_vars_m2)
        jump = math.log(share) + _log_dens2(r2_m2, float(jump_var_m2)) > null_log
        if np.any(jump) and float(np.mean(change[step_end[jump]])) >= 0.5:
            trigger = "sat_change"
    return Fit(
        Jumps(sigma_m=round(sigma_m, 4), rate_per_s=round(rate_per_s, 6), trigger=trigger),
        {
            "sigma_m": sigma_m / math.sqrt(2 * n_jumps),
            "rate_per_s": rate_per_s / math.sqrt(n_jumps),
        },
    )
