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
from typing import Any

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
)
from x6wd.gap.stats import (
    QUANT_DECIMALS,
    Cell,
    Layout,
    latency_slope,
    lattice_fraction,
    regular,
)

# Which battery statistics each effect moves: its fingerprint, used to rank candidates.
FINGERPRINTS: dict[str, tuple[str, ...]] = {
    "bias": ("mean",),
    "gauss_markov": ("log_std", "log_adev", "acf", "log_cep50", "log_r95"),
    "random_walk": ("log_adev", "log_std", "acf"),
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
    (sigma, tau), (se_s, se_t) = d.gm[d.with_bias("gauss_markov")]
    if not (math.isfinite(sigma) and math.isfinite(tau)) or sigma < 1e-4:
        return None
    tau = min(tau, 10 * layout.duration_s)
    return Fit(
        GaussMarkov(sigma_m=round(sigma, 4), tau_s=round(tau, 3), axes="en"),
        {"sigma_m": se_s, "tau_s": se_t},
    )


def fit_random_walk(
    real: PositionSeries, base: Sequence[PositionSeries], layout: Layout
) -> Fit | None:
    """Horizontal random walk q (m/sqrt(s)) by exact likelihood on top of the baseline noise
    model: its increments are white with variance q^2 dt over the baseline's own increments,
    and its level starts at zero and spreads as q^2 t (the filter carries both)."""
    if len(real) < 32:
        return None
    d = drift_fit(real, base, layout)
    q, se_q = d.rw[d.with_bias("random_walk")]
    if not math.isfinite(q) or q < 1e-6:
        return None
    return Fit(RandomWalk(q_m_per_sqrt_s=round(q, 6), axes="en"), {"q_m_per_sqrt_s": se_q})


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


def _steps(s: PositionSeries) -> tuple[np.ndarray, np.ndarray]:
    v = np.asarray(s.valid, dtype=bool)
    return np.diff(np.asarray(s.east_m, dtype=float)[v]), np.diff(
        np.asarray(s.north_m, dtype=float)[v]
    )


def fit_jumps(real: PositionSeries, base: Sequence[PositionSeries], layout: Layout) -> Fit | None:
    """Jumps: at satellite-set changes when the log has nsats, else steps larger than any the
    baseline makes (rate = count / duration). sigma from the jump steps: a step between two
    independent offsets has variance 2 sigma^2 per axis, less the baseline's own step variance."""
    be = np.concatenate([np.hypot(*_steps(s)) for s in base])
    b_var = float(np.mean(np.concatenate([np.concatenate(_steps(s)) ** 2 for s in base])))
    de, dn = _steps(real)
    if de.size < 10:
        return None
    if real.nsats is not None:
        ns = np.asarray(real.nsats)[np.asarray(real.valid, dtype=bool)]
        jump = ns[1:] != ns[:-1]
    else:
        thr = 1.5 * float(np.quantile(be, 0.9995))
        jump = np.hypot(de, dn) > thr
    k = int(np.count_nonzero(jump))
    if k == 0:
        return None
    s2 = (float(np.mean(de[jump] ** 2 + dn[jump] ** 2)) / 2 - b_var) / 2
    if s2 <= 0:
        return None
    sigma = math.sqrt(s2)
    rate = k / max(layout.duration_s, layout.dt_s)
    return Fit(
        Jumps(sigma_m=round(sigma, 4), rate_per_s=round(rate, 6)),
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
    """Latency = -(real slope - baseline slope) of along-track error on true speed."""
    if not layout.moving:
        return None
    r, r_se = latency_slope(real)
    b = np.array([latency_slope(s)[0] for s in base])
    delay = -(r - float(b.mean()))
    if not math.isfinite(r_se) or delay <= 0:
        return None
    se = math.hypot(r_se, float(b.std(ddof=1)) / math.sqrt(len(base)))
    return Fit(Latency(delay_s=round(delay, 4)), {"delay_s": se})


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
        out = 0.0
        for a in range(2):
            spec = np.full(nf, white[a] ** 2)
            for i in range(k):
                spec = spec + sig[a, i] ** 2 * shapes[i]
            spec = np.maximum(spec, 1e-12)
            out += float(np.sum(np.log(spec) + per[a] / spec))
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
    """Per (batch, axis) sums over valid epochs: log S, e^2/S, e*e1/S, e1^2/S (e the data's
    innovations, e1 those of a column of ones) and the number of observations."""

    log_s: np.ndarray
    yy: np.ndarray
    y1: np.ndarray
    oo: np.ndarray
    nobs: int

    def loglik(self, bias: bool) -> np.ndarray:
        """Exact Gaussian log-likelihood per batch element: the mean fixed at the baseline's
        (``bias`` False) or profiled per axis by GLS (``bias`` True)."""
        q = self.yy - (self.y1**2 / np.maximum(self.oo, 1e-300) if bias else 0.0)
        return -0.5 * np.sum(self.log_s + q + self.nobs * _LOG_2PI, axis=-1)

    def bias(self) -> tuple[np.ndarray, np.ndarray]:
        """GLS bias per (batch, axis) and its standard error."""
        oo = np.maximum(self.oo, 1e-300)
        return self.y1 / oo, 1.0 / np.sqrt(oo)


def kalman_terms(
    real: PositionSeries,
    model: NoiseModel,
    eff_var: np.ndarray,
    eff_tau: np.ndarray,
) -> KalmanTerms:
    """Run the Kalman filter of baseline model + one effect component for a batch of effect
    parameters: ``eff_var`` (B,) the stationary variance sigma^2 of a Gauss-Markov effect or,
    where ``eff_tau`` is inf, the random-walk rate q^2 (m^2/s); ``eff_var`` 0 = no effect."""
    v = np.asarray(real.valid, dtype=bool)
    t = np.asarray(real.t_s, dtype=float)[v]
    east = np.asarray(real.east_m, dtype=float)[v]
    north = np.asarray(real.north_m, dtype=float)[v]
    y = np.stack([east, north]) - model.mean_m[:, None]  # (2, n)
    n = t.size
    b = eff_var.size
    k = model.tau_s.shape[1] + 1
    # Layout: state index first, the batch (B parameter sets x 2 axes, flattened, column
    # j = (batch j // 2, axis j % 2)) LAST and contiguous, so that every time step is a
    # handful of vector operations over the whole batch.
    nb = 2 * b
    var = np.empty((k, nb))
    tau = np.empty((k, nb))
    var[:-1] = np.tile(model.sigma_m.T**2, (1, b))
    tau[:-1] = np.tile(model.tau_s.T, (1, b))
    var[-1] = np.repeat(eff_var, 2)
    tau[-1] = np.repeat(eff_tau, 2)
    rw = ~np.isfinite(tau)
    w2 = np.tile(model.white_m**2, b)  # (nb,)
    p0 = np.where(rw, 0.0, var)
    diag = np.eye(k)[:, :, None]

    def step(dt: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        safe_tau = np.where(rw, 1.0, tau)
        phi = np.where(rw, 1.0, np.exp(-dt / safe_tau))
        q = np.where(rw, var * dt, var * -np.expm1(-2.0 * dt / safe_tau))
        return phi[:, None, :], phi[:, None, :] * phi[None, :, :], diag * q[None, :, :]

    dts = np.diff(t)
    uniq, inv = np.unique(np.round(dts, 6), return_inverse=True)
    table = [step(float(d)) for d in uniq] if uniq.size <= 32 else None
    x = np.zeros((k, 2, nb))  # middle axis: [data, ones]
    p = diag * p0[None, :, :]
    obs = np.empty((n, 2, nb))
    obs[:, 0, :] = np.tile(y.T, (1, b))
    obs[:, 1, :] = 1.0
    e_all = np.empty((n, 2, nb))
    s_all = np.empty((n, nb))
    for i in range(n):
        if i > 0:
            phi, pp, dq = table[inv[i - 1]] if table is not None else step(float(dts[i - 1]))
            p = p * pp + dq
            x = x * phi
        pk = p.sum(axis=1)  # (k, nb): P @ 1
        s = pk.sum(axis=0) + w2  # innovation variance
        e = obs[i] - x.sum(axis=0)  # innovations of [data, ones]
        gain = pk / s
        x += gain[:, None, :] * e[None, :, :]
        p -= gain[:, None, :] * pk[None, :, :]
        e_all[i] = e
        s_all[i] = s
    inv_s = 1.0 / s_all

    def per_axis(a: np.ndarray) -> np.ndarray:
        return a.reshape(b, 2)

    return KalmanTerms(
        log_s=per_axis(np.log(s_all).sum(axis=0)),
        yy=per_axis(np.sum(e_all[:, 0] ** 2 * inv_s, axis=0)),
        y1=per_axis(np.sum(e_all[:, 0] * e_all[:, 1] * inv_s, axis=0)),
        oo=per_axis(np.sum(e_all[:, 1] ** 2 * inv_s, axis=0)),
        nobs=n,
    )


# --- the drift family: none / bias / Gauss-Markov / random walk, by exact likelihood ----------

DRIFT_MODELS: dict[str, int] = {
    # model -> number of free parameters (bias: one mean per horizontal axis)
    "none": 0,
    "bias": 2,
    "gauss_markov": 2,
    "gauss_markov+bias": 4,
    "random_walk": 1,
    "random_walk+bias": 3,
}
DRIFT_FAMILY = ("gauss_markov", "random_walk", "bias")


@dataclass(frozen=True)
class DriftFit:
    """Exact-likelihood fits of the drift family to one log on top of the baseline noise
    model. ``loglik`` per model of :data:`DRIFT_MODELS`; ``gm``/``rw`` per bias flag:
    (parameters, standard errors) in the effects' units; ``nobs`` the scalar observations."""

    loglik: dict[str, float]
    gm: dict[bool, tuple[tuple[float, float], tuple[float, float]]]
    rw: dict[bool, tuple[float, float]]
    nobs: int
    model: NoiseModel

    def bic(self, name: str) -> float:
        """Bayesian information criterion (lower is better)."""
        return -2.0 * self.loglik[name] + DRIFT_MODELS[name] * math.log(max(self.nobs, 2))

    @property
    def best(self) -> str:
        """The model with the lowest BIC."""
        return min(DRIFT_MODELS, key=self.bic)

    @property
    def best_effect(self) -> str:
        """The effect model (not "none") with the lowest BIC: which member of the family
        explains a drift, once the battery has said there is a gap to explain."""
        return min((m for m in DRIFT_MODELS if m != "none"), key=self.bic)

    def with_bias(self, name: str) -> bool:
        """Whether ``name`` (gauss_markov or random_walk) is better with a bias beside it."""
        return self.bic(f"{name}+bias") < self.bic(name)


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


_NOISE_CACHE: list[tuple[tuple[int, ...], list[PositionSeries], NoiseModel]] = []
_DRIFT_CACHE: list[tuple[tuple[int, ...], list[PositionSeries], DriftFit]] = []


def noise_model(base: Sequence[PositionSeries], layout: Layout) -> NoiseModel:
    """:func:`fit_noise_model`, cached on the identity of the runs (the candidates of a round
    share one baseline)."""
    key = (*(id(s) for s in base), round(layout.duration_s))
    for k, _keep, m in _NOISE_CACHE:
        if k == key:
            return m
    m = fit_noise_model(base, layout)
    _NOISE_CACHE.append((key, list(base), m))
    del _NOISE_CACHE[:-4]
    return m


def drift_fit(real: PositionSeries, base: Sequence[PositionSeries], layout: Layout) -> DriftFit:
    """Fit the drift family to ``real`` on top of the baseline noise model of ``base``: a
    coarse grid over (sigma, tau) and q, then three zooms around each maximum, all in batched
    exact Kalman likelihoods; standard errors from the curvature of the log-likelihood
    (a quadratic through the last zoom grid, in log-parameters). Cached per (real, base)."""
    key = (id(real), *(id(s) for s in base))
    for k, _keep, f in _DRIFT_CACHE:
        if k == key:
            return f
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
    lik = {b: kt.loglik(b) for b in (False, True)}
    loglik = {"none": float(lik[False][-1]), "bias": float(lik[True][-1])}
    # centres (log sigma, log tau) / log q and zoom half-widths, per bias flag
    gm_c = {b: np.array([g_s[i], g_t[i]]) for b in lik for i in [int(np.argmax(lik[b][:n_gm]))]}
    rw_c = {b: float(lq[int(np.argmax(lik[b][n_gm:-1]))]) for b in lik}
    gm_h = np.array([lq[1] - lq[0], lt[1] - lt[0]])
    rw_h = lq[1] - lq[0]
    lo_t, hi_t = math.log(0.5 * dt), math.log(10 * span)
    u = np.linspace(-1.0, 1.0, 5)
    du_s, du_t = (a.ravel() for a in np.meshgrid(u, u))
    last: dict[str, Any] = {}
    # Zoom: a 5 x 5 (5) grid around each maximum; the grid halves only when the maximum is
    # inside it, otherwise it moves (the coarse grid may have landed off the ridge).
    shrinks = {f"{kind}{b}": 0 for kind in ("gm", "rw") for b in (False, True)}
    halves = {"gmFalse": gm_h, "gmTrue": gm_h.copy(), "rwFalse": rw_h, "rwTrue": rw_h}
    for _zoom in range(8):
        if min(shrinks.values()) >= 3:
            break
        batches = []
        for b in (False, True):
            gm_h, rw_h = halves[f"gm{b}"], halves[f"rw{b}"]
            s_ = gm_c[b][0] + du_s * gm_h[0]
            t_ = np.clip(gm_c[b][1] + du_t * gm_h[1], lo_t, hi_t)
            batches.append((gm_var(s_, t_), np.exp(t_), ("gm", b, np.stack([s_, t_], 1))))
            q_ = rw_c[b] + u * rw_h
            batches.append((np.exp(2 * q_), np.full(u.size, np.inf), ("rw", b, q_[:, None])))
        kt = kalman_terms(
            real,
            model,
            np.concatenate([x[0] for x in batches]),
            np.concatenate([x[1] for x in batches]),
        )
        off = 0
        for ev, _et, (kind, b, pts) in batches:
            ll = kt.loglik(b)[off : off + ev.size]
            off += ev.size
            j = int(np.argmax(ll))
            tag = f"{kind}{b}"
            if tag in last and shrinks[tag] >= 3:
                continue  # this one has converged; keep its last grid
            last[tag] = (pts, ll)
            if kind == "gm":
                gm_c[b] = pts[j]
                at_bound = not lo_t + 1e-9 < pts[j, 1] < hi_t - 1e-9  # tau clipped
                inside = abs(du_s[j]) < 1 and (abs(du_t[j]) < 1 or at_bound)
            else:
                rw_c[b] = float(pts[j, 0])
                inside = abs(u[j]) < 1
            if inside:
                halves[tag] = halves[tag] / 2
                shrinks[tag] += 1
    gm: dict[bool, tuple[tuple[float, float], tuple[float, float]]] = {}
    rw: dict[bool, tuple[float, float]] = {}
    for b in (False, True):
        for kind in ("gm", "rw"):
            pts, ll = last[f"{kind}{b}"]
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
            loglik[name + ("+bias" if b else "")] = best_ll
            if kind == "gm":
                # log sigma = log q + (log tau - log 2) / 2
                sig = math.exp(centre[0] + (centre[1] - math.log(2.0)) / 2)
                tau = math.exp(centre[1])
                se_ls = float("nan")
                if q is not None:
                    cov = q[1]
                    se_ls = math.sqrt(max(cov[0, 0] + cov[1, 1] / 4 + cov[0, 1], 0.0))
                gm[b] = ((sig, tau), (sig * se_ls, tau * float(se[1])))
            else:
                q_val = math.exp(centre[0])
                rw[b] = (q_val, q_val * float(se[0]))
    fit = DriftFit(loglik, gm, rw, 2 * kt.nobs, model)
    _DRIFT_CACHE.append((key, [real, *base], fit))
    del _DRIFT_CACHE[:-6]
    return fit


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
