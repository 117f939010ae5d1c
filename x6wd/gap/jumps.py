"""Jumps by maximum likelihood on the horizontal steps: a normal scale mixture for the
baseline's own heavy-tailed step law, with a wide jump component on top (:func:`fit_jumps`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from sim_backend.effects import Jumps, PositionSeries
from x6wd.gap.fitted import Fit, IdentityCache
from x6wd.gap.stats import STEADY_JUMP_SPREADS, Layout, steady_steps

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
# and the narrowest per-axis variance (m^2) a jump component may have
StepLaw = tuple[np.ndarray, np.ndarray, float, float]
_STEP_LAW_CACHE: IdentityCache[StepLaw | None] = IdentityCache(4)


def _step_law(
    baseline: Sequence[PositionSeries], layout: Layout, steady: bool = False
) -> StepLaw | None:
    """The baseline's step law for :func:`fit_jumps`: (weights, per-axis variances) of a
    two-component scale mixture on the pooled steps (only the steady ones,
    :func:`~x6wd.gap.stats.steady_steps`, when ``steady``), and the jump share the jump fit
    finds in the runs themselves (its floor). Cached on the identity of the runs."""
    return _STEP_LAW_CACHE.get(
        baseline,
        (round(layout.dt_s, 6), steady),
        lambda: _fit_step_law(baseline, layout, steady),
    )


def _step_r2(series: PositionSeries, dt_s: float, steady: bool) -> np.ndarray:
    """Squared horizontal step lengths (m^2): all steps, or the steady ones."""
    steps_m, _end, is_steady = steady_steps(series, dt_s)
    if steady:
        steps_m = steps_m[is_steady]
    return np.sum(steps_m * steps_m, axis=1)


def _fit_step_law(
    baseline: Sequence[PositionSeries], layout: Layout, steady: bool
) -> StepLaw | None:
    run_r2_m2 = [_step_r2(s, layout.dt_s, steady) for s in baseline]
    pooled = np.concatenate(run_r2_m2) if run_r2_m2 else np.zeros(0)
    if pooled.size < 10:
        return None
    # per-axis variance from the median squared step (a Rayleigh length's median)
    var0_m2 = max(float(np.median(pooled)), 1e-10) / (2 * math.log(2.0))
    null_weights, null_vars_m2, _ = scale_mixture(pooled, [var0_m2, 4 * var0_m2])
    jump_var_min_m2 = JUMP_MIN_WIDTH * float(np.max(null_vars_m2))
    if steady:
        # Steady steps are light-tailed: a two-part mixture of them leaves a thin tail (steps
        # of 3-4 robust spreads) that a jump component just above it would take for jumps,
        # in the runs as much as in the log. A jump is a step the "where" test's count would
        # see: at least STEADY_JUMP_SPREADS robust spreads.
        jump_var_min_m2 = max(jump_var_min_m2, STEADY_JUMP_SPREADS**2 * var0_m2)
    # the median run's share: one run whose fit lands on a wide part of its own (an outlier
    # episode; 15 % of one replicate's steady steps) must not set the floor of every log
    baseline_share = float(
        np.median(
            [
                scale_mixture(
                    r2, [2.5 * jump_var_min_m2], null=(null_weights, null_vars_m2),
                    var_min_m2=jump_var_min_m2,
                )[0][0]
                for r2 in run_r2_m2
                if r2.size
            ]
        )
    )  # fmt: skip
    return null_weights, null_vars_m2, baseline_share, jump_var_min_m2


def fit_jumps(
    real: PositionSeries, baseline: Sequence[PositionSeries], layout: Layout
) -> Fit | None:
    """Jumps by maximum likelihood on the horizontal steps: the baseline's own step law is a
    two-component normal scale mixture fitted to its pooled steps (GNSS steps are heavy
    tailed: their spread changes with the geometry); on top of it a jump component, a step
    between two independent N(0, sigma^2) offsets (per-axis variance v + 2 sigma^2), at least
    JUMP_MIN_WIDTH times wider than the null's widest part. The rate is the jump share per
    step less the baseline runs' own share under the same fit. With satellite counts in the
    log and the runs, the steady steps (the same set, or count, at both ends) are tried
    first (trigger "poisson", the rate per second of steady time); otherwise, or when they
    show no jumps, all steps, and the trigger is "sat_change" when the log reports satellite
    counts and most jumps sit on changes of them, else "poisson"."""
    # With satellite counts, jumps are sought among the steady steps (the same set, or count,
    # at both ends) against the baseline's steady steps: the simulator's own big steps fall on count
    # changes (97 % of those over 1 m), so there a moderate jump is one of many, while among
    # steady steps it stands out (a 1.2 m jump fitted as 1.1-1.3 m where all steps gave
    # nothing). Jumps on the changes themselves (trigger sat_change) are sought among all
    # steps when the steady ones show none.
    if real.nsats is not None and all(s.nsats is not None for s in baseline):
        steady_fit = _fit_jumps(real, baseline, layout, steady=True)
        if steady_fit is not None:
            return steady_fit
    return _fit_jumps(real, baseline, layout, steady=False)


def _fit_jumps(
    real: PositionSeries, baseline: Sequence[PositionSeries], layout: Layout, steady: bool
) -> Fit | None:
    steps_m, step_end, is_steady = steady_steps(real, layout.dt_s)
    if steady:
        steps_m, step_end = steps_m[is_steady], step_end[is_steady]
    r2_m2 = np.sum(steps_m * steps_m, axis=1)
    law = _step_law(baseline, layout, steady)
    if r2_m2.size < 10 or law is None:
        return None
    null_weights, null_vars_m2, baseline_share, jump_var_min_m2 = law
    widest_m2 = float(np.max(null_vars_m2))
    null_loglik = float(np.sum(_null_log_dens(r2_m2, null_weights, null_vars_m2)))
    (share,), (jump_var_m2,), loglik = scale_mixture(
        r2_m2, [max(10 * widest_m2, 2.5 * jump_var_min_m2)], null=(null_weights, null_vars_m2),
        var_min_m2=jump_var_min_m2,
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
    if real.nsats is not None and not steady:
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
