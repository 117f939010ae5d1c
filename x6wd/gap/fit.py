"""Per-effect fitting: the parameters of an effect that, added to the baseline, best explain
a log; each with standard errors.

Fits are made against the baseline ensemble, never against a single sim: an effect adds to
whatever the simulator already does. The drift family (bias, Gauss-Markov, random walk) is
fitted by EXACT Gaussian likelihood: the baseline's own horizontal error law is first fitted
to the baseline runs as a sum of first-order Gauss-Markov components plus white noise
(:func:`fit_noise_model`), and the effect is then estimated on top of it with a Kalman filter
on the log's valid epochs (:func:`kalman_terms`, :func:`drift_fit`), so the baseline's own
variance is never attributed to the effect. Bias, quantisation, jumps, outages and latency are
moment or direct fits (means add; lattices and outage runs are read off directly).
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, Generic, TypeVar

import numpy as np

from sim_backend.effects import (
    Bias,
    GaussMarkov,
    Jumps,
    Latency,
    Outages,
    PositionSeries,
    Quantization,
    RandomWalk,
    truth_velocity_mps,
)
from x6wd.gap.stats import (
    QUANT_DECIMALS,
    Cell,
    Layout,
    lattice_fraction,
    regular,
)

T = TypeVar("T")


class _IdentityCache(Generic[T]):
    """The last few results of an expensive fit, keyed on the identity of the series it was
    given (plus ``extra``): the candidates of a round all fit against one baseline. Each entry
    keeps its series alive, so their ids cannot be reused while it exists."""

    def __init__(self, size: int) -> None:
        self.size = size
        self.entries: list[tuple[tuple[Any, ...], list[PositionSeries], T]] = []

    def get(
        self, series: Sequence[PositionSeries], extra: tuple[Any, ...], compute: Callable[[], T]
    ) -> T:
        key = (*(id(s) for s in series), *extra)
        for k, _keep, value in self.entries:
            if k == key:
                return value
        value = compute()
        self.entries.append((key, list(series), value))
        del self.entries[: -self.size]
        return value


# Which battery statistics each effect moves: its fingerprint, used to rank candidates.
FINGERPRINTS: dict[str, tuple[str, ...]] = {
    "bias": ("mean",),
    "gauss_markov": ("log_std", "log_adev", "log_psd", "acf", "log_cep50", "log_r95"),
    "random_walk": ("log_adev", "log_psd", "log_std", "acf"),
    "quantization": ("lattice", "zero_step"),
    "jumps": ("step_tail", "log_step_std", "tail_ratio"),
    "outages": ("availability", "log_outage_s"),
    "latency": ("latency_slope",),
    # per-place spread and step size (moving logs): a zone makes one place noisier
    "multipath_zone": ("log_rms_place", "log_step_std_place"),
}
FITTABLE = tuple(FINGERPRINTS)


@dataclass(frozen=True)
class Fit:
    """A fitted effect: the layer, its parameters as a table, standard errors (same keys)."""

    effect: Any
    se: dict[str, float] = field(default_factory=dict)

    @property
    def name(self) -> str:
        return str(self.effect.name)

    @property
    def params(self) -> dict[str, Any]:
        return {k: v for k, v in self.effect.to_params().items() if k != "name"}


def fingerprint_score(
    name: str, cells: Sequence[Cell], z: np.ndarray, threshold: float = 2.0
) -> float:
    """Evidence for an effect: sum over its fingerprint cells of max(0, z^2 - threshold^2)."""
    stats = FINGERPRINTS.get(name, ())
    sel = np.array([c.statistic in stats for c in cells], dtype=bool)
    if not np.any(sel):
        return 0.0
    return float(np.sum(np.maximum(0.0, z[sel] ** 2 - threshold**2)))


def _periodograms(series: PositionSeries, layout: Layout, n: int) -> np.ndarray:
    """Periodograms (2, n//2) of the first n regular samples of east and north (no DC)."""
    e, north, _u = regular(series, layout.dt_s)
    out = []
    for y in (e[:n], north[:n]):
        x = y - y.mean()
        out.append((np.abs(np.fft.rfft(x)) ** 2 / n)[1 : n // 2 + 1])
    return np.array(out)


def expected_periodogram(acov: np.ndarray, n_freq: int) -> np.ndarray:
    """Expected periodogram at Fourier frequencies 1..n_freq of n = len(acov) samples of a
    stationary process with autocovariance ``acov`` (lags 0..n-1): the finite-length
    (debiased Whittle) form sum_k (1 - |k|/n) c(k) e^(-i w k), exact for any length."""
    n = acov.size
    g = (1.0 - np.arange(n) / n) * acov
    spec = 2.0 * np.fft.rfft(g).real - g[0]
    return spec[1 : n_freq + 1]


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
    return _drift_effect(d, "gauss_markov", flags, layout)


def _drift_effect(d: DriftFit, drift: str, flags: Flags, layout: Layout) -> Fit:
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
    out = [_drift_effect(d, drift, flags, layout)]
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
    return _drift_effect(d, "random_walk", flags, layout)


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


def fit_quantization(
    real: PositionSeries, base: Sequence[PositionSeries], layout: Layout
) -> Fit | None:
    """The coarsest NMEA minute lattice all real fixes lie on (exact), when the baseline is
    not already on it."""
    for dec in QUANT_DECIMALS:
        if lattice_fraction(real, dec) >= 0.99:
            if np.mean([lattice_fraction(s, dec) for s in base]) >= 0.99:
                return None
            return Fit(Quantization(decimals=dec), {"decimals": 0.0})
    return None


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
_STEP_LAW_CACHE: _IdentityCache[StepLaw | None] = _IdentityCache(4)


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


def fit_outages(real: PositionSeries, base: Sequence[PositionSeries], layout: Layout) -> Fit | None:
    """Two-state Markov outages by maximum likelihood from the real log's valid/invalid runs
    (mean run lengths), when the real log loses its fix more often than the baseline."""
    v = np.asarray(real.valid, dtype=bool)
    if v.size < 3:
        return None
    base_avail = float(np.mean([np.mean(np.asarray(s.valid, dtype=bool)) for s in base]))
    if np.mean(v) >= base_avail:
        return None
    d = np.diff(np.concatenate(([1], v.astype(int), [1])))
    n_down = int(np.count_nonzero(d == -1))
    if n_down == 0:
        return None
    dt = layout.dt_s
    up_s = float(np.count_nonzero(v)) * dt
    down_s = float(np.count_nonzero(~v)) * dt
    mean_up, mean_down = up_s / n_down, down_s / n_down
    return Fit(
        Outages(mean_up_s=round(mean_up, 3), mean_down_s=round(max(mean_down, dt), 3)),
        {"mean_up_s": mean_up / math.sqrt(n_down), "mean_down_s": mean_down / math.sqrt(n_down)},
    )


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


# --- exact state-space likelihood (Kalman filter) ----------------------------------------------
#
# The real error is modelled as the baseline's own error process plus the effect:
#   y_c(t) = mean_c + sum_i g_ci(t) + e(t) + w_c(t),   c = east, north
# with g_ci the baseline's first-order Gauss-Markov components (fitted to the baseline runs),
# w_c its white part, and e(t) the effect: a Gauss-Markov drift (phi = exp(-dt/tau), innovation
# variance sigma^2 (1 - phi^2), stationary start) or a random walk (phi = 1, innovation variance
# q^2 dt, starting at zero as the simulator's layer does). Every component is propagated with the
# ACTUAL step between valid epochs, so outages and irregular sampling are exact. A constant bias
# is profiled out by generalised least squares: the innovations are linear in the data, so the
# filter run on a column of ones gives the regressor's innovations at no extra Riccati cost.

BASE_COMPONENTS = 2  # Gauss-Markov components of the baseline noise model (plus white noise)
_LOG_2PI = math.log(2.0 * math.pi)
WHITE_FLOOR_M = 1e-3  # keeps the innovation variance positive when a run is exactly constant


@dataclass(frozen=True)
class NoiseModel:
    """The baseline's horizontal error law, per axis (east, north): Gauss-Markov components
    ``sigma_m``/``tau_s`` (shape (2, K)), white noise ``white_m`` (2,), mean ``mean_m`` (2,)."""

    sigma_m: np.ndarray
    tau_s: np.ndarray
    white_m: np.ndarray
    mean_m: np.ndarray


def _gm_expected_periodogram(n: int, n_freq: int, phi: float) -> np.ndarray:
    """Closed form of :func:`expected_periodogram` for a unit AR(1) (lag-1 correlation phi)
    at the Fourier frequencies 1..n_freq: 1 + 2 Re sum_{k=1}^{n-1} (1 - k/n) z^k with
    z = phi e^(-i w), summed as geometric series (no FFT: cheap inside an optimiser)."""
    rot, rot_n1 = _fourier_rotations(n, n_freq)
    z = phi * rot
    one = 1.0 - z
    zn1 = phi ** (n - 1) * rot_n1  # z^(n-1)
    s0 = z * (1.0 - zn1) / one  # sum z^k, k = 1..n-1
    s1 = z * (1.0 - n * zn1 + (n - 1) * zn1 * z) / one**2  # sum k z^k
    return 1.0 + 2.0 * (s0 - s1 / n).real


def _gm_expected_dc(n: int, dt_over_tau: float) -> float:
    """The zero-frequency term of :func:`_gm_expected_periodogram`, n Var(mean of n samples)
    of a unit AR(1) with phi = exp(-dt/tau): 1 + 2 sum_{k=1}^{n-1} (1 - k/n) phi^k, with
    1 - phi from expm1 so that correlation times far beyond the log stay exact."""
    phi = math.exp(-dt_over_tau)
    one = -math.expm1(-dt_over_tau)  # 1 - phi
    if one < 1e-300:
        return float(n)
    pn1 = phi ** (n - 1)
    s0 = phi * (1.0 - pn1) / one
    s1 = phi * (1.0 - n * pn1 + (n - 1) * pn1 * phi) / one**2
    return 1.0 + 2.0 * (s0 - s1 / n)


@functools.lru_cache(maxsize=8)
def _fourier_rotations(n: int, n_freq: int) -> tuple[np.ndarray, np.ndarray]:
    """e^(-i w) and e^(-i w (n-1)) at the Fourier frequencies w = 2 pi j / n, j = 1..n_freq."""
    j = np.arange(1, n_freq + 1)
    return np.exp(-2j * np.pi * j / n), np.exp(-2j * np.pi * ((j * (n - 1)) % n) / n)


def fit_noise_model(base: Sequence[PositionSeries], layout: Layout) -> NoiseModel:
    """Fit the baseline noise model (K Gauss-Markov components + white noise per axis) to the
    baseline runs by debiased Whittle likelihood on their mean periodogram. With M runs of
    thousands of samples the Whittle approximation error is negligible here; the exact
    likelihood is kept for the single real log, where the effect is estimated."""
    from scipy.optimize import minimize

    n = min(regular(s, layout.dt_s)[0].size for s in base)
    n = max(n, 8)
    per = np.mean([_periodograms(s, layout, n) for s in base], axis=0)  # (2, n//2)
    nf = per.shape[1]
    # Zero frequency: n (run mean - grand mean)^2, whose debiased expectation is n Var(mean).
    # Without it nothing bounds the slowest component (each run's own mean is removed above):
    # on the GNSS model the fit put 10-13 m on a drift far longer than the log, where the
    # runs' hour means actually spread by under a metre, and every bias looked like noise.
    run_means = np.array(
        [[float(np.mean(c[:n])) for c in regular(s, layout.dt_s)[:2]] for s in base]
    )
    m_runs = run_means.shape[0]
    dc = (
        n * np.mean((run_means - run_means.mean(axis=0)) ** 2, axis=0) * m_runs / (m_runs - 1)
        if m_runs > 1
        else None
    )
    dt = layout.dt_s
    means = []
    for ax in ("east_m", "north_m"):
        vals = [
            np.asarray(getattr(s, ax), dtype=float)[np.asarray(s.valid, dtype=bool)] for s in base
        ]
        means.append(float(np.mean(np.concatenate(vals))) if vals else 0.0)
    span = max(layout.duration_s, 4 * dt)
    k = BASE_COMPONENTS
    totals = np.maximum(per.mean(axis=1), 1e-8)  # a constant run (a coarse lattice) has none

    # log-parameters: K correlation times shared by the two axes (the same physical
    # processes), then per axis K sigmas and the white noise
    def unpack(lp: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        lp = np.clip(lp, -25.0, 25.0)  # keeps a wild line-search step finite
        taus = np.minimum(np.exp(lp[:k]), 100 * span)
        sig = np.exp(lp[k:].reshape(2, k + 1))
        return taus, sig[:, :k], sig[:, k]

    def nll(lp: np.ndarray) -> float:
        taus, sig, white = unpack(lp)
        shapes = [_gm_expected_periodogram(n, nf, math.exp(-dt / t_i)) for t_i in taus]
        zero = [_gm_expected_dc(n, dt / t_i) for t_i in taus]
        out = 0.0
        for a in range(2):
            spec = np.full(nf, white[a] ** 2)
            for i in range(k):
                spec = spec + sig[a, i] ** 2 * shapes[i]
            spec = np.maximum(spec, 1e-12)
            out += float(np.sum(np.log(spec) + per[a] / spec))
            if dc is not None:
                s0 = max(white[a] ** 2 + sum(sig[a, i] ** 2 * zero[i] for i in range(k)), 1e-12)
                out += math.log(s0) + float(dc[a]) / s0
        return out

    best: tuple[float, np.ndarray] | None = None
    for short, long_ in ((2.0, 0.05), (5.0, 0.2)):
        x0 = [math.log(short * dt), math.log(long_ * span)]
        for a in range(2):
            root = math.sqrt(float(totals[a]))
            x0 += [math.log(root * 0.2), math.log(root * 0.8), math.log(root * 0.05)]
        res = minimize(nll, np.array(x0), method="BFGS", options={"gtol": 1e-3})
        if best is None or res.fun < best[0]:
            best = (float(res.fun), np.asarray(res.x))
    assert best is not None
    taus, sig, white = unpack(best[1])
    tau = np.tile(taus, (2, 1))
    white = np.maximum(white, WHITE_FLOOR_M)
    return NoiseModel(sig, tau, white, np.array(means))


@dataclass(frozen=True)
class KalmanTerms:
    """Per (batch, axis): sum of log S over the valid epochs, the Gram matrix
    sum e_c e_d / S of the innovations of the columns [data, ones, latency regressor] (the
    last only for moving logs) and the number of observations per axis."""

    log_s: np.ndarray  # (B, 2)
    gram: np.ndarray  # (B, 2, C, C)
    nobs: int

    @property
    def has_latency(self) -> bool:
        return self.gram.shape[-1] > 2

    def _normal_equations(self, bias: bool, latency: bool) -> tuple[np.ndarray, np.ndarray]:
        """(A (B, P, P), c (B, P)) of the GLS regression of the data on the chosen regressors:
        a bias per axis (column 1 of that axis) and one latency shared by both axes (column 2
        of each axis: the error a delay makes is -delay x velocity)."""
        g = self.gram
        params = ([(0, 1), (1, 1)] if bias else []) + (
            [(None, 2)] if latency and self.has_latency else []
        )
        m = len(params)
        a = np.zeros((g.shape[0], m, m))
        c = np.zeros((g.shape[0], m))
        for i, (ax_i, col_i) in enumerate(params):
            axes_i = {0, 1} if ax_i is None else {ax_i}
            c[:, i] = sum(g[:, ax, 0, col_i] for ax in axes_i)
            for j, (ax_j, col_j) in enumerate(params):
                common = axes_i & ({0, 1} if ax_j is None else {ax_j})
                a[:, i, j] = sum(g[:, ax, col_i, col_j] for ax in common)
        return a, c

    def loglik(self, bias: bool, latency: bool = False) -> np.ndarray:
        """Exact Gaussian log-likelihood per batch element: the mean fixed at the baseline's,
        or with a bias per axis (``bias``) and/or a latency (``latency``, moving logs)
        profiled out by GLS."""
        q = self.gram[:, :, 0, 0].sum(axis=-1)
        a, c = self._normal_equations(bias, latency)
        if c.shape[1]:
            beta = np.linalg.solve(a + 1e-12 * np.eye(c.shape[1]), c[..., None])[..., 0]
            q = q - np.sum(c * beta, axis=-1)
        return -0.5 * (self.log_s.sum(axis=-1) + q + 2 * self.nobs * _LOG_2PI)

    def coef(self, bias: bool, latency: bool) -> tuple[np.ndarray, np.ndarray]:
        """GLS coefficients (B, P) and their standard errors: [bias east, bias north] (m)
        when ``bias``, then the latency (s) when ``latency``."""
        a, c = self._normal_equations(bias, latency)
        cov = np.linalg.inv(a + 1e-12 * np.eye(c.shape[1]))
        return (cov @ c[..., None])[..., 0], np.sqrt(np.diagonal(cov, axis1=1, axis2=2))


def latency_regressor(series: PositionSeries) -> np.ndarray | None:
    """(2, n) the east/north error (m) per second of delay at the valid epochs: -velocity,
    since a receiver that is d s late reports truth(t - d) ~ truth(t) - d v(t). None at rest."""
    if series.speed_mps is None:
        return None
    v = np.asarray(series.valid, dtype=bool)
    if not np.any(np.nan_to_num(np.asarray(series.speed_mps, dtype=float))[v] > 0):
        return None
    ve, vn = truth_velocity_mps(series)
    return -np.stack([ve[v], vn[v]])


Transition = tuple[np.ndarray, np.ndarray, np.ndarray]


def component_law(
    model: NoiseModel, eff_var: np.ndarray, eff_tau: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Stationary variances (m^2; for a random walk, tau inf, its rate m^2/s) and correlation
    times (s), each (K + 1, C), of the baseline's K Gauss-Markov components and one effect,
    for C = 2 B filter columns (column j = batch j // 2, axis j % 2); ``eff_var`` and
    ``eff_tau`` are given per column (C,)."""
    reps = eff_var.size // 2
    var = np.vstack([np.tile(model.sigma_m.T**2, (1, reps)), eff_var[None, :]])
    tau = np.vstack([np.tile(model.tau_s.T, (1, reps)), eff_tau[None, :]])
    return var, tau


def transitions(var: np.ndarray, tau: np.ndarray, dts: np.ndarray) -> Callable[[int], Transition]:
    """Step i (from valid epoch i to i + 1, ``dts`` s apart) of independent first-order
    components (``var``/``tau`` (K, C), see :func:`component_law`): (phi (K, 1, C),
    phi phi' (K, K, C), process noise Q (K, K, C)) for x <- phi x, P <- phi phi' P + Q.
    Exact discretisation with the actual step (phi = exp(-dt/tau); a random walk where tau is
    inf), so outages and irregular sampling are exact; tabulated when the log has few
    distinct steps (a regular log has one)."""
    rw = ~np.isfinite(tau)
    safe_tau = np.where(rw, 1.0, tau)
    diag = np.eye(var.shape[0])[:, :, None]

    def step(dt: float) -> Transition:
        phi = np.where(rw, 1.0, np.exp(-dt / safe_tau))
        q = np.where(rw, var * dt, var * -np.expm1(-2.0 * dt / safe_tau))
        return phi[:, None, :], phi[:, None, :] * phi[None, :, :], diag * q[None, :, :]

    uniq, inv = np.unique(np.round(dts, 6), return_inverse=True)
    if uniq.size <= 32:
        table = [step(float(d)) for d in uniq]
        return lambda i: table[inv[i]]
    return lambda i: step(float(dts[i]))


def kalman_terms(
    real: PositionSeries,
    model: NoiseModel,
    eff_var: np.ndarray,
    eff_tau: np.ndarray,
) -> KalmanTerms:
    """Run the Kalman filter of baseline model + one effect component for a batch of effect
    parameters: ``eff_var`` (B,) the stationary variance sigma^2 of a Gauss-Markov effect or,
    where ``eff_tau`` is inf, the random-walk rate q^2 (m^2/s); ``eff_var`` 0 = no effect.
    The innovations are linear in the data, so the filter run on a column of ones and on the
    latency regressor gives their innovations for GLS at no extra Riccati cost."""
    v = np.asarray(real.valid, dtype=bool)
    t = np.asarray(real.t_s, dtype=float)[v]
    east = np.asarray(real.east_m, dtype=float)[v]
    north = np.asarray(real.north_m, dtype=float)[v]
    y = np.stack([east, north]) - model.mean_m[:, None]  # (2, n)
    lat = latency_regressor(real)
    n = t.size
    b = eff_var.size
    k = model.tau_s.shape[1] + 1
    cols = 2 if lat is None else 3
    # Layout: state index first, the batch (B parameter sets x 2 axes, flattened, column
    # j = (batch j // 2, axis j % 2)) LAST and contiguous, so that every time step is a
    # handful of vector operations over the whole batch.
    nb = 2 * b
    var, tau = component_law(model, np.repeat(eff_var, 2), np.repeat(eff_tau, 2))
    w2 = np.tile(model.white_m**2, b)  # (nb,)
    p0 = np.where(np.isfinite(tau), var, 0.0)  # a walk starts at zero
    dts = np.diff(t)
    trans = transitions(var, tau, dts)
    x = np.zeros((k, cols, nb))  # middle axis: [data, ones(, latency)]
    p = np.eye(k)[:, :, None] * p0[None, :, :]
    obs = np.empty((n, cols, nb))
    obs[:, 0, :] = np.tile(y.T, (1, b))
    obs[:, 1, :] = 1.0
    if lat is not None:
        obs[:, 2, :] = np.tile(lat.T, (1, b))
    e_all = np.empty((n, cols, nb))
    s_all = np.empty((n, nb))
    for i in range(n):
        if i > 0:
            phi, pp, dq = trans(i - 1)
            p = p * pp + dq
            x = x * phi
        pk = p.sum(axis=1)  # (k, nb): P @ 1
        s = pk.sum(axis=0) + w2  # innovation variance
        e = obs[i] - x.sum(axis=0)  # innovations of every column
        gain = pk / s
        x += gain[:, None, :] * e[None, :, :]
        p -= gain[:, None, :] * pk[None, :, :]
        e_all[i] = e
        s_all[i] = s
    scaled = e_all / np.sqrt(s_all)[:, None, :]
    gram = np.einsum("ncj,ndj->jcd", scaled, scaled)  # (nb, C, C)
    return KalmanTerms(
        log_s=np.log(s_all).sum(axis=0).reshape(b, 2),
        gram=gram.reshape(b, 2, cols, cols),
        nobs=n,
    )


# --- the drift family: none / bias / Gauss-Markov / random walk, by exact likelihood ----------

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


def _quad_fit(pts: np.ndarray, vals: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """Least-squares quadratic surface through (pts (N, d), vals (N,)): its vertex and the
    covariance -H^-1 (None when the surface is not concave)."""
    d = pts.shape[1]
    cols = [np.ones(len(pts))] + [pts[:, i] for i in range(d)]
    pairs = [(i, j) for i in range(d) for j in range(i, d)]
    cols += [pts[:, i] * pts[:, j] for i, j in pairs]
    coef, *_ = np.linalg.lstsq(np.stack(cols, axis=1), vals, rcond=None)
    g = coef[1 : d + 1]
    h = np.zeros((d, d))
    for c, (i, j) in zip(coef[d + 1 :], pairs, strict=True):
        if i == j:
            h[i, i] = 2 * c
        else:
            h[i, j] = h[j, i] = c
    if np.any(np.linalg.eigvalsh(h) >= 0):
        return None
    cov = -np.linalg.inv(h)
    return cov @ g, cov


_NOISE_CACHE: _IdentityCache[NoiseModel] = _IdentityCache(4)
_DRIFT_CACHE: _IdentityCache[DriftFit] = _IdentityCache(6)


def noise_model(base: Sequence[PositionSeries], layout: Layout) -> NoiseModel:
    """:func:`fit_noise_model`, cached on the identity of the runs (the candidates of a round
    share one baseline)."""
    return _NOISE_CACHE.get(
        base, (round(layout.duration_s),), lambda: fit_noise_model(base, layout)
    )


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
        q = _quad_fit(pts, ll)
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


def _fit_multipath_zone(
    real: PositionSeries, base: Sequence[PositionSeries], layout: Layout
) -> Fit | None:
    """:func:`x6wd.gap.zone.fit_multipath_zone`, imported on first use (zone.py builds on
    this module)."""
    from x6wd.gap.zone import fit_multipath_zone

    return fit_multipath_zone(real, base, layout)


FITTERS: dict[str, Callable[[PositionSeries, Sequence[PositionSeries], Layout], Fit | None]] = {
    "bias": fit_bias,
    "gauss_markov": fit_gauss_markov,
    "random_walk": fit_random_walk,
    "quantization": fit_quantization,
    "jumps": fit_jumps,
    "outages": fit_outages,
    "latency": fit_latency,
    "multipath_zone": _fit_multipath_zone,
}
