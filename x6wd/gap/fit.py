"""Per-effect fitting: the parameters of an effect that, added to the baseline, best explain
the real log's fit part; each with standard errors.

Fits are moment or likelihood fits against the baseline ensemble, never against a single
sim: an effect adds to whatever the simulator already does (Allan variances of independent
processes add; means add; lattices and outage runs are read off directly).
"""

from __future__ import annotations

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
    allan_var,
    latency_slope,
    lattice_fraction,
    octave_taus,
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


# --- Allan variance models ---------------------------------------------------------------------


def gm_avar(m: np.ndarray, phi: float) -> np.ndarray:
    """Allan variance of a unit-variance first-order GM (lag-1 correlation phi) at averaging
    factors m, exact for the discrete process."""
    m = np.asarray(m, dtype=float)
    one = 1.0 - phi
    s = m * (1 + phi) / one - 2 * phi * (1 - phi**m) / one**2
    c = phi * (1 - phi**m) ** 2 / one**2
    return (s - c) / m**2


def gm_sample_var(n: int, phi: float) -> float:
    """Expected sample variance (1/n normalisation) of n samples of a unit GM."""
    s = n * (1 + phi) / (1 - phi) - 2 * phi * (1 - phi**n) / (1 - phi) ** 2
    return 1.0 - s / n**2


def rw_avar(m: np.ndarray) -> np.ndarray:
    """Allan variance of a random walk with unit step variance at averaging factors m."""
    m = np.asarray(m, dtype=float)
    return (2 * m * m + 1) / (6 * m)


def _horizontal_avar(
    series: PositionSeries, layout: Layout, ms: list[int]
) -> tuple[np.ndarray, float, int]:
    e, n, _u = regular(series, layout.dt_s)
    av = 0.5 * (allan_var(e, ms) + allan_var(n, ms))
    var = 0.5 * (float(np.var(e)) + float(np.var(n)))
    return av, var, e.size


def _excess(
    real: PositionSeries, base: Sequence[PositionSeries], layout: Layout
) -> tuple[list[int], np.ndarray, np.ndarray, float, float, int]:
    ms = octave_taus(layout)
    r_av, r_var, n = _horizontal_avar(real, layout, ms)
    b = [_horizontal_avar(s, layout, ms) for s in base]
    b_av = np.array([x[0] for x in b])
    b_var = np.array([x[1] for x in b])
    ok = np.isfinite(r_av) & np.all(np.isfinite(b_av), axis=0)
    ms_ok = [m for m, k in zip(ms, ok, strict=True) if k]
    return (
        ms_ok,
        r_av[ok] - b_av[:, ok].mean(axis=0),
        b_av[:, ok].std(axis=0, ddof=1),
        r_var - float(b_var.mean()),
        float(b_var.std(ddof=1)),
        n,
    )


def _periodograms(series: PositionSeries, layout: Layout, n: int) -> np.ndarray:
    """Periodograms (2, n//2) of the first n regular samples of east and north (no DC)."""
    e, north, _u = regular(series, layout.dt_s)
    out = []
    for y in (e[:n], north[:n]):
        x = y - y.mean()
        out.append((np.abs(np.fft.rfft(x)) ** 2 / n)[1 : n // 2 + 1])
    return np.array(out)


def _whittle_inputs(
    real: PositionSeries, base: Sequence[PositionSeries], layout: Layout
) -> tuple[np.ndarray, np.ndarray, np.ndarray, int] | None:
    n = min(regular(s, layout.dt_s)[0].size for s in [real, *base])
    if n < 32:
        return None
    i_real = _periodograms(real, layout, n)
    # The baseline's mean periodogram is its expected periodogram for this length: no
    # spectral model of the simulator is needed, and its leakage matches the real log's.
    s_base = np.mean([_periodograms(s, layout, n) for s in base], axis=0)
    freq = np.arange(1, n // 2 + 1) / n  # cycles per sample
    return i_real, s_base, freq, n


def expected_periodogram(acov: np.ndarray, n_freq: int) -> np.ndarray:
    """Expected periodogram at Fourier frequencies 1..n_freq of n = len(acov) samples of a
    stationary process with autocovariance ``acov`` (lags 0..n-1): the finite-length
    (debiased Whittle) form sum_k (1 - |k|/n) c(k) e^(-i w k), exact for any length."""
    n = acov.size
    g = (1.0 - np.arange(n) / n) * acov
    spec = 2.0 * np.fft.rfft(g).real - g[0]
    return spec[1 : n_freq + 1]


def _whittle_fit(
    i_real: np.ndarray,
    s_base: np.ndarray,
    shape: Callable[[np.ndarray], np.ndarray],
    x0: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, float]:
    """Minimise the Whittle negative log-likelihood sum(log S + I/S) over log-parameters;
    returns (log-params, their standard errors from a numerical Hessian, nll)."""
    from scipy.optimize import minimize

    def nll(lp: np.ndarray) -> float:
        s = np.maximum(s_base + shape(lp), 1e-12)
        return float(np.sum(np.log(s) + i_real / s))

    res = minimize(
        nll, x0, method="Nelder-Mead", options={"xatol": 1e-4, "fatol": 1e-6, "maxiter": 800}
    )
    lp = np.asarray(res.x, dtype=float)
    k = lp.size
    h = 1e-3
    hess = np.zeros((k, k))
    f0 = nll(lp)
    for i in range(k):
        for j in range(k):
            ei, ej = np.eye(k)[i] * h, np.eye(k)[j] * h
            hess[i, j] = (nll(lp + ei + ej) - nll(lp + ei) - nll(lp + ej) + f0) / (h * h)
    try:
        cov = np.linalg.inv(hess)
        se = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    except np.linalg.LinAlgError:
        se = np.full(k, np.nan)
    return lp, se, float(res.fun)


def fit_gauss_markov(
    real: PositionSeries, base: Sequence[PositionSeries], layout: Layout
) -> Fit | None:
    """Horizontal GM (sigma_m, tau_s) by debiased Whittle likelihood: the real east/north
    periodograms against S_baseline(f) + E[I_GM(f; sigma, tau)], with S_baseline the mean
    periodogram of the baseline runs and E[I_GM] the expected periodogram of the sampled
    process (autocovariance sigma^2 exp(-|k| dt / tau)) for this record length."""
    w = _whittle_inputs(real, base, layout)
    if w is None:
        return None
    i_real, s_base, freq, n = w
    dt = layout.dt_s
    lags = np.arange(n)

    def shape(lp: np.ndarray) -> np.ndarray:
        s2, tau = math.exp(2 * lp[0]), math.exp(lp[1])
        return expected_periodogram(s2 * np.exp(-lags * dt / tau), freq.size)

    # start from a small grid (the likelihood is multi-modal in tau when sigma is small)
    best = None
    for tau0 in np.geomspace(2 * dt, max(layout.duration_s / 2, 4 * dt), 8):
        for s0 in (0.3, 1.0, 3.0):
            x0 = np.array([math.log(s0), math.log(tau0)])
            s0_spec = np.maximum(s_base + shape(x0), 1e-12)
            val = float(np.sum(np.log(s0_spec) + i_real / s0_spec))
            if best is None or val < best[0]:
                best = (val, x0)
    assert best is not None
    lp, se, _ = _whittle_fit(i_real, s_base, shape, best[1])
    sigma, tau = math.exp(lp[0]), math.exp(lp[1])
    if not (math.isfinite(sigma) and math.isfinite(tau)) or sigma < 1e-4:
        return None
    tau = min(tau, 10 * layout.duration_s)
    return Fit(
        GaussMarkov(sigma_m=round(sigma, 4), tau_s=round(tau, 3), axes="en"),
        {"sigma_m": sigma * float(se[0]), "tau_s": tau * float(se[1])},
    )


def fit_random_walk(
    real: PositionSeries, base: Sequence[PositionSeries], layout: Layout
) -> Fit | None:
    """Horizontal random walk q (m/sqrt(s)) by Whittle likelihood with the spectrum of a
    sampled random walk, q^2 dt / |1 - e^(-i 2 pi f)|^2, on top of the baseline spectrum."""
    w = _whittle_inputs(real, base, layout)
    if w is None:
        return None
    i_real, s_base, freq, _n = w
    dt = layout.dt_s
    den = 2 - 2 * np.cos(2 * np.pi * freq)

    def shape(lp: np.ndarray) -> np.ndarray:
        return math.exp(2 * lp[0]) * dt / den

    lp, se, _ = _whittle_fit(i_real, s_base, shape, np.array([math.log(0.01)]))
    q = math.exp(lp[0])
    if not math.isfinite(q) or q < 1e-6:
        return None
    return Fit(
        RandomWalk(q_m_per_sqrt_s=round(q, 6), axes="en"), {"q_m_per_sqrt_s": q * float(se[0])}
    )


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


FITTERS: dict[str, Callable[[PositionSeries, Sequence[PositionSeries], Layout], Fit | None]] = {
    "bias": fit_bias,
    "gauss_markov": fit_gauss_markov,
    "random_walk": fit_random_walk,
    "quantization": fit_quantization,
    "jumps": fit_jumps,
    "outages": fit_outages,
    "latency": fit_latency,
}
