"""The baseline's own horizontal error law: K first-order Gauss-Markov components plus white
noise per axis, fitted to the baseline runs by debiased Whittle likelihood.

Every exact-likelihood fit (:mod:`x6wd.gap.drift`, :mod:`x6wd.gap.zone`) estimates its effect
ON TOP of this model, so the simulator's own variance is never credited to the effect.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from sim_backend.effects import PositionSeries
from x6wd.gap.fitted import IdentityCache
from x6wd.gap.stats import Layout, regular

BASE_COMPONENTS = 2  # Gauss-Markov components of the baseline noise model (plus white noise)
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


def fit_noise_model(baseline: Sequence[PositionSeries], layout: Layout) -> NoiseModel:
    """Fit the baseline noise model (K Gauss-Markov components + white noise per axis) to the
    ``baseline`` runs (errors, m) by debiased Whittle likelihood on their mean periodogram.
    With M runs of thousands of samples the Whittle approximation error is negligible here;
    the exact likelihood is kept for the single real log, where the effect is estimated."""
    from scipy.optimize import minimize

    n = max(min(regular(s, layout.dt_s)[0].size for s in baseline), 8)  # samples per run
    periodogram = np.mean([_periodograms(s, layout, n) for s in baseline], axis=0)  # (2, n//2)
    n_freq = periodogram.shape[1]
    # Zero frequency: n (run mean - grand mean)^2, whose debiased expectation is n Var(mean).
    # Without it nothing bounds the slowest component (each run's own mean is removed above):
    # on the GNSS model the fit put 10-13 m on a drift far longer than the log, where the
    # runs' hour means actually spread by under a metre, and every bias looked like noise.
    run_means_m = np.array(
        [[float(np.mean(c[:n])) for c in regular(s, layout.dt_s)[:2]] for s in baseline]
    )
    n_runs = run_means_m.shape[0]
    zero_freq_m2 = (
        n * np.mean((run_means_m - run_means_m.mean(axis=0)) ** 2, axis=0) * n_runs / (n_runs - 1)
        if n_runs > 1
        else None
    )
    dt_s = layout.dt_s
    mean_m = []
    for axis in ("east_m", "north_m"):
        valid_values = [
            np.asarray(getattr(s, axis), dtype=float)[np.asarray(s.valid, dtype=bool)]
            for s in baseline
        ]
        mean_m.append(float(np.mean(np.concatenate(valid_values))) if valid_values else 0.0)
    span_s = max(layout.duration_s, 4 * dt_s)
    k = BASE_COMPONENTS
    # total power per axis; a constant run (a coarse lattice) has none
    total_m2 = np.maximum(periodogram.mean(axis=1), 1e-8)

    # log-parameters: K correlation times shared by the two axes (the same physical
    # processes), then per axis K sigmas and the white noise
    def unpack(log_params: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        log_params = np.clip(log_params, -25.0, 25.0)  # keeps a wild line-search step finite
        tau_s = np.minimum(np.exp(log_params[:k]), 100 * span_s)
        sigma_m = np.exp(log_params[k:].reshape(2, k + 1))
        return tau_s, sigma_m[:, :k], sigma_m[:, k]

    def neg_loglik(log_params: np.ndarray) -> float:
        tau_s, sigma_m, white_m = unpack(log_params)
        shapes = [_gm_expected_periodogram(n, n_freq, math.exp(-dt_s / t)) for t in tau_s]
        zero = [_gm_expected_dc(n, dt_s / t) for t in tau_s]
        out = 0.0
        for a in range(2):
            spec = np.full(n_freq, white_m[a] ** 2)
            for i in range(k):
                spec = spec + sigma_m[a, i] ** 2 * shapes[i]
            spec = np.maximum(spec, 1e-12)
            out += float(np.sum(np.log(spec) + periodogram[a] / spec))
            if zero_freq_m2 is not None:
                spec0 = white_m[a] ** 2 + sum(sigma_m[a, i] ** 2 * zero[i] for i in range(k))
                spec0 = max(spec0, 1e-12)
                out += math.log(spec0) + float(zero_freq_m2[a]) / spec0
        return out

    best: tuple[float, np.ndarray] | None = None
    # two starts: the short and long components' times as fractions of the step and the log
    for short, long_ in ((2.0, 0.05), (5.0, 0.2)):
        x0 = [math.log(short * dt_s), math.log(long_ * span_s)]
        for a in range(2):
            rms_m = math.sqrt(float(total_m2[a]))
            x0 += [math.log(rms_m * 0.2), math.log(rms_m * 0.8), math.log(rms_m * 0.05)]
        res = minimize(neg_loglik, np.array(x0), method="BFGS", options={"gtol": 1e-3})
        if best is None or res.fun < best[0]:
            best = (float(res.fun), np.asarray(res.x))
    assert best is not None
    tau_s, sigma_m, white_m = unpack(best[1])
    return NoiseModel(
        sigma_m, np.tile(tau_s, (2, 1)), np.maximum(white_m, WHITE_FLOOR_M), np.array(mean_m)
    )


def _periodograms(series: PositionSeries, layout: Layout, n: int) -> np.ndarray:
    """Periodograms (2, n//2; m^2) of the first n regular samples of east and north (no DC)."""
    east_m, north_m, _up_m = regular(series, layout.dt_s)
    out = []
    for y in (east_m[:n], north_m[:n]):
        x = y - y.mean()
        out.append((np.abs(np.fft.rfft(x)) ** 2 / n)[1 : n // 2 + 1])
    return np.array(out)


def expected_periodogram(acov: np.ndarray, n_freq: int) -> np.ndarray:
    """Expected periodogram at Fourier frequencies 1..n_freq of n = len(acov) samples of a
    stationary process with autocovariance ``acov`` (lags 0..n-1): the finite-length
    (debiased Whittle) form sum_k (1 - |k|/n) c(k) e^(-i w k), exact for any length."""
    n = acov.size
    weighted = (1.0 - np.arange(n) / n) * acov
    spec = 2.0 * np.fft.rfft(weighted).real - weighted[0]
    return spec[1 : n_freq + 1]


_NOISE_CACHE: IdentityCache[NoiseModel] = IdentityCache(4)


def noise_model(baseline: Sequence[PositionSeries], layout: Layout) -> NoiseModel:
    """:func:`fit_noise_model`, cached on the identity of the runs (the candidates of a round
    share one baseline)."""
    return _NOISE_CACHE.get(
        baseline, (round(layout.duration_s),), lambda: fit_noise_model(baseline, layout)
    )
