"""The baseline's own horizontal error law: K first-order Gauss-Markov components plus white
noise per axis, fitted to the baseline runs by debiased Whittle likelihood.

Every exact-likelihood fit (:mod:`x6wd.gap.drift`, :mod:`x6wd.gap.zone`) estimates its effect
ON TOP of this model, so the simulator's own variance is never credited to the effect.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from sim_backend.effects import PositionSeries, Quantization
from x6wd.gap.fitted import IdentityCache
from x6wd.gap.null import Inflation, inflation_from, null_model
from x6wd.gap.stats import Cell, Layout, find_lattice, regular, with_twin

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

    runs, n = _spectral_runs(baseline, layout)
    periodogram = np.mean([_periodograms(s, layout, n) for s in runs], axis=0)  # (2, n//2)
    n_freq = periodogram.shape[1]
    # Zero frequency: n (run mean - grand mean)^2, whose debiased expectation is n Var(mean).
    # Without it nothing bounds the slowest component (each run's own mean is removed above):
    # on the GNSS model the fit put 10-13 m on a drift far longer than the log, where the
    # runs' hour means actually spread by under a metre, and every bias looked like noise.
    run_means_m = np.array(
        [[float(np.mean(c[:n])) for c in regular(s, layout.dt_s)[:2]] for s in runs]
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
        values = np.concatenate(valid_values) if valid_values else np.zeros(0)
        mean_m.append(float(np.mean(values)) if values.size else 0.0)  # no fix in any run: 0
    span_s = max(layout.duration_s, 4 * dt_s)
    k = BASE_COMPONENTS
    # total power per axis; a constant run (a coarse lattice) has none
    total_m2 = np.maximum(periodogram.mean(axis=1), 1e-8)

    # log-parameters: K correlation times shared by the two axes (the same physical
    # processes), then per axis K sigmas and the white noise
    # Without the zero-frequency term (one run) a component slower than the log is not
    # identified (only sigma^2 / tau is): no correlation time beyond the log, rather than an
    # arbitrary one far beyond it.
    tau_cap_s = 100 * span_s if zero_freq_m2 is not None else span_s

    def unpack(log_params: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        log_params = np.clip(log_params, -25.0, 25.0)  # keeps a wild line-search step finite
        tau_s = np.minimum(np.exp(log_params[:k]), tau_cap_s)
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


MIN_SPECTRUM_SAMPLES = 8  # regular samples a run needs for its periodogram to count


def _spectral_runs(
    baseline: Sequence[PositionSeries], layout: Layout
) -> tuple[list[PositionSeries], int]:
    """(runs, n): the runs whose periodograms are averaged, and the common number of regular
    samples each contributes (the shortest of them).

    A run's regular grid spans its valid fixes only, so an outage effect (a fitted 20-minute
    fix loss, or a log of two sessions) leaves some runs short or empty: a run lost whole has
    one sample. Runs under :data:`MIN_SPECTRUM_SAMPLES` or under half the longest run are
    left out (a few hundred samples would shorten every run's periodogram to theirs, and an
    empty run has none: periodograms of different lengths cannot be averaged). When no run
    is long enough, the longest ones are kept and padded (:func:`_periodograms`)."""
    lengths = [regular(s, layout.dt_s)[0].size for s in baseline]
    longest = max(lengths)
    floor = max(MIN_SPECTRUM_SAMPLES, longest // 2)
    kept = [s for s, size in zip(baseline, lengths, strict=True) if size >= floor]
    if not kept:
        kept = [s for s, size in zip(baseline, lengths, strict=True) if size == longest]
        return kept, MIN_SPECTRUM_SAMPLES
    return kept, min(size for size in lengths if size >= floor)


def _periodograms(series: PositionSeries, layout: Layout, n: int) -> np.ndarray:
    """Periodograms (2, n//2; m^2) of the first n regular samples of east and north (no DC);
    a run shorter than n is padded with its mean (no power added), so that every run gives
    the same frequencies."""
    east_m, north_m, _up_m = regular(series, layout.dt_s)
    out = []
    for y in (east_m[:n], north_m[:n]):
        x = np.zeros(n)
        x[: y.size] = y - y.mean()
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


# --- the null of a few baseline logs: their innovations through the noise model ----------------
#
# With fewer sim logs than an ensemble needs, replicates are made by the innovations
# representation of each axis' noise model (two Gauss-Markov components + white noise): a log
# is whitened by the model's Kalman filter, its standardised innovations are resampled in
# blocks taken at the SAME times from the given logs (the sky, hence the noise level and the
# satellite-set changes, is a function of time), and the filter's recursion colours them
# again. Innovations are nearly white, so a join is no jump; the slow error is regenerated
# whole by the recursion instead of being cut and spliced (a raw join of two logs is a fake
# step of the slow error's size, ~1.5 m on the GNSS model, which every step, walk and drift
# statistic reads as an effect). Heavy tails, satellite changes and fix losses of the logs
# survive; so does how the law itself differs between logs (the next section). What the
# replicates' spread still misses (their laws come from a few logs) is measured on the logs
# themselves, each scored against replicates of the others, and widens the null's spread
# (:func:`x6wd.gap.null.inflation_from`).


@dataclass(frozen=True)
class AxisLaw:
    """One axis' law: Gauss-Markov components ``sigma_m``/``tau_s`` (2,), white noise
    ``white_m`` and mean ``mean_m`` (m, s)."""

    sigma_m: np.ndarray
    tau_s: np.ndarray
    white_m: float
    mean_m: float


def axis_laws(logs: Sequence[PositionSeries], layout: Layout) -> list[AxisLaw]:
    """The laws of east, north (one :class:`NoiseModel`) and, when the layout has it, up
    (the same model fitted to the vertical), fitted to ``logs``."""
    models: list[tuple[NoiseModel, tuple[int, ...]]] = [(fit_noise_model(logs, layout), (0, 1))]
    if layout.has_up:
        ups = [s.with_(east_m=np.asarray(s.up_m), north_m=np.asarray(s.up_m)) for s in logs]
        models.append((fit_noise_model(ups, layout), (0,)))
    return [
        AxisLaw(m.sigma_m[a], m.tau_s[a], float(m.white_m[a]), float(m.mean_m[a]))
        for m, axes in models
        for a in axes
    ]


def _gains(law: AxisLaw, dt_s: np.ndarray, update: np.ndarray) -> tuple[np.ndarray, ...]:
    """The Kalman filter of ``law`` over steps ``dt_s`` (n - 1,) with measurement updates
    where ``update`` (n,): per epoch the innovation spread sqrt(S) and the gains k1, k2 of
    the two components, and per step the transitions phi1, phi2. The gains do not depend on
    the data: computed once, used to whiten and to colour."""
    n = update.size
    phi = np.exp(-np.asarray(dt_s)[None, :] / law.tau_s[:, None])  # (2, n-1)
    q = law.sigma_m[:, None] ** 2 * (1.0 - phi * phi)
    r = law.white_m**2
    p11, p12, p22 = float(law.sigma_m[0] ** 2), 0.0, float(law.sigma_m[1] ** 2)
    sd = np.ones(n)
    k1 = np.zeros(n)
    k2 = np.zeros(n)
    phi1, phi2, q1, q2 = phi[0].tolist(), phi[1].tolist(), q[0].tolist(), q[1].tolist()
    for t in range(n):
        if update[t]:
            s_t = p11 + 2.0 * p12 + p22 + r
            a, b = (p11 + p12) / s_t, (p12 + p22) / s_t
            sd[t], k1[t], k2[t] = math.sqrt(s_t), a, b
            p11, p12, p22 = p11 - a * a * s_t, p12 - a * b * s_t, p22 - b * b * s_t
        if t < n - 1:
            f1, f2 = phi1[t], phi2[t]
            p11, p12, p22 = f1 * f1 * p11 + q1[t], f1 * f2 * p12, f2 * f2 * p22 + q2[t]
    return sd, k1, k2, phi[0], phi[1]


def whiten(law: AxisLaw, t_s: np.ndarray, y_m: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Standardised innovations of ``y_m`` under ``law`` (NaN where not ``valid``)."""
    sd, k1, k2, phi1, phi2 = _gains(law, np.diff(t_s), valid)
    x1 = x2 = 0.0
    out = np.full(y_m.size, np.nan)
    for t, y in enumerate((np.asarray(y_m, dtype=float) - law.mean_m).tolist()):
        if valid[t]:
            e = y - x1 - x2
            out[t] = e / sd[t]
            x1, x2 = x1 + k1[t] * e, x2 + k2[t] * e
        if t < y_m.size - 1:
            x1, x2 = phi1[t] * x1, phi2[t] * x2
    return out


def colour(law: AxisLaw, t_s: np.ndarray, innovations: np.ndarray) -> np.ndarray:
    """The inverse of :func:`whiten` with every epoch updated: series (rows of
    ``innovations``, standardised; NaN drawn afresh from N(0, 1) by the caller) of ``law``."""
    n = t_s.size
    sd, k1, k2, phi1, phi2 = _gains(law, np.diff(t_s), np.ones(n, dtype=bool))
    if innovations.shape[0] == 1:  # one series: plain floats, far faster than 1-wide arrays
        return _colour_one(sd, k1, k2, phi1, phi2, innovations[0])[None, :] + law.mean_m
    x1 = np.zeros(innovations.shape[0])
    x2 = np.zeros_like(x1)
    out = np.empty_like(innovations)
    for t in range(n):
        e = sd[t] * innovations[:, t]
        out[:, t] = x1 + x2 + e
        x1, x2 = x1 + k1[t] * e, x2 + k2[t] * e
        if t < n - 1:
            x1, x2 = phi1[t] * x1, phi2[t] * x2
    return out + law.mean_m


def _colour_one(
    sd: np.ndarray, k1: np.ndarray, k2: np.ndarray, phi1: np.ndarray, phi2: np.ndarray,
    innovations: np.ndarray,
) -> np.ndarray:  # fmt: skip
    """:func:`colour`'s recursion for one series, on Python floats."""
    n = innovations.size
    gains = zip(sd.tolist(), k1.tolist(), k2.tolist(), innovations.tolist(), strict=True)
    f1 = [*phi1.tolist(), 0.0]
    f2 = [*phi2.tolist(), 0.0]
    out = [0.0] * n
    x1 = x2 = 0.0
    for t, (s_t, a, b, u) in enumerate(gains):
        e = s_t * u
        out[t] = x1 + x2 + e
        x1, x2 = f1[t] * (x1 + a * e), f2[t] * (x2 + b * e)
    return np.array(out)


def lattice_of(logs: Sequence[PositionSeries]) -> Quantization | None:
    """The coarsest lattice (NMEA minutes or decimal degrees) every one of ``logs`` lies on,
    as the layer that prints on it (None: none)."""
    return find_lattice(logs)


def _on(template_t_s: np.ndarray, log: PositionSeries) -> np.ndarray:
    """Index into ``log`` of the epoch at the same time from the start as each template
    epoch (nearest; cyclic when the log is shorter)."""
    t_s = np.asarray(log.t_s, dtype=float)
    rel_s = np.mod(template_t_s - template_t_s[0], max(t_s[-1] - t_s[0], 1e-9) + 1e-9)
    return np.clip(np.searchsorted(t_s - t_s[0], rel_s - 1e-9), 0, t_s.size - 1)


AXES = ("east_m", "north_m", "up_m")


def innovation_replicates(
    logs: Sequence[PositionSeries],
    laws: Sequence[AxisLaw],
    template: PositionSeries,
    n_out: int,
    block_s: float,
    jitter_s: float,
    rng: np.random.Generator,
    lattice: Quantization | None,
    replicate_laws: Sequence[Sequence[AxisLaw]] | None = None,
) -> list[PositionSeries]:
    """``n_out`` replicates on ``template``'s times: the laws' recursion driven by the
    ``logs``' standardised innovations, in blocks of ``block_s`` each from one log at about
    the same times (shifted by up to ``jitter_s``, so that n logs offer more than n choices;
    its fix losses and satellite counts come with it), printed on the logs' lattice.
    ``replicate_laws`` (one list of axis laws per replicate) colours each replicate with a
    law of its own (:func:`drawn_laws`); None: every one with ``laws``."""
    t_s = np.asarray(template.t_s, dtype=float)
    n = t_s.size
    index = [_on(t_s, log) for log in logs]
    valid_of = [np.asarray(log.valid, dtype=bool)[ix] for log, ix in zip(logs, index, strict=True)]
    shocks = []  # per log, (axes, n): its innovations at the template's times
    for log, ix in zip(logs, index, strict=True):
        v = np.asarray(log.valid, dtype=bool)
        rows = [
            whiten(law, np.asarray(log.t_s, dtype=float), np.asarray(getattr(log, ax)), v)[ix]
            for law, ax in zip(laws, AXES, strict=False)
        ]
        shocks.append(np.array(rows))
    dt_s = float(np.median(np.diff(t_s))) if n > 1 else 1.0
    block = max(2, round(block_s / dt_s))
    jitter = max(0, round(jitter_s / dt_s))
    n_blocks = -(-n // block)
    # per epoch of each replicate: the log and the epoch its innovations come from
    src_log = np.repeat(rng.integers(len(logs), size=(n_out, n_blocks)), block, axis=1)[:, :n]
    shift = np.repeat(rng.integers(-jitter, jitter + 1, size=(n_out, n_blocks)), block, axis=1)
    src_t = (np.arange(n)[None, :] + shift[:, :n]) % n
    stacked = np.array(shocks)  # (logs, axes, n)
    e = np.moveaxis(stacked[src_log, :, src_t], -1, 0)  # (axes, n_out, n)
    valid = np.array(valid_of)[src_log, src_t]
    # the satellites used travel with the innovations they explain (a set change's step)
    labels: dict[str, np.ndarray | None] = {}
    for name in ("nsats", "sat_set"):
        labels[name] = None
        if all(getattr(log, name) is not None for log in logs):
            per_log = np.array(
                [np.asarray(getattr(log, name))[ix] for log, ix in zip(logs, index, strict=True)]
            )
            labels[name] = per_log[src_log, src_t]
    nsats, sat_set = labels["nsats"], labels["sat_set"]
    missing = ~np.isfinite(e)
    e[missing] = rng.standard_normal(int(missing.sum()))
    twins = None
    if replicate_laws is None:
        paths = [colour(law, t_s, e[a]) for a, law in enumerate(laws)]
    else:
        paths = [
            np.array([colour(replicate_laws[j][a], t_s, e[a][j : j + 1])[0] for j in range(n_out)])
            for a in range(len(laws))
        ]
        twins = [  # east and north only: the robust fast cells are horizontal
            np.array(
                [
                    colour(fast_pooled(replicate_laws[j][a], law), t_s, e[a][j : j + 1])[0]
                    for j in range(n_out)
                ]
            )
            for a, law in enumerate(laws[:2])
        ]
    if len(paths) < 3:
        paths.append(np.zeros((n_out, n)))
    out = []
    for j in range(n_out):
        series = template.with_(
            east_m=paths[0][j], north_m=paths[1][j], up_m=paths[2][j], valid=valid[j],
            nsats=None if nsats is None else nsats[j],
            sat_set=None if sat_set is None else sat_set[j],
        )  # fmt: skip
        twin = None
        if twins is not None:
            twin = series.with_(east_m=twins[0][j], north_m=twins[1][j])
        if lattice is not None:
            series = lattice.apply(series, rng)
            twin = None if twin is None else lattice.apply(twin, rng)
        out.append(with_twin(series, twin))
    return out


def fast_pooled(law: AxisLaw, pooled: AxisLaw) -> AxisLaw:
    """``law`` with its fast part (the faster Gauss-Markov component and the white noise)
    taken from ``pooled``: what a replicate's twin is coloured with (:class:`Twinned`)."""
    sigma_m = np.array(law.sigma_m, dtype=float)
    tau_s = np.array(law.tau_s, dtype=float)
    fast, fast_pooled_ = int(np.argmin(tau_s)), int(np.argmin(pooled.tau_s))
    sigma_m[fast] = pooled.sigma_m[fast_pooled_]
    tau_s[fast] = pooled.tau_s[fast_pooled_]
    return AxisLaw(sigma_m, tau_s, pooled.white_m, law.mean_m)


# --- how the law itself differs from log to log --------------------------------------------
#
# One law fitted to n logs, coloured with their innovations, makes replicates that differ
# only by chance within that law. The simulator's hours differ more: fitted alone, three
# one-hour logs of the same scenario give short correlation times of 9-18 s, and the next
# hour 5 s. A statistic that reads the whole log against a model (the random walk's
# likelihood ratio) grows with the log's length times that misfit, so its spread between
# logs is heavy-tailed and three logs' leave-one-out z cannot pin it. So every replicate
# is coloured with a law of its own, drawn from the spread of the laws fitted to each log
# alone, less the scatter a one-log fit has anyway (measured on parametric draws of the
# pooled law, which the replicates already carry): each cell's null spread, heavy tails
# included, then comes from the replicates instead of from n logs.

LAW_DRAWS = 6  # parametric logs of the pooled law that measure a one-log fit's own scatter


def _law_vector(laws: Sequence[AxisLaw]) -> np.ndarray:
    """The laws' parameters as one vector of logs (per axis: sigmas, taus by increasing
    tau, white noise)."""
    parts = []
    for law in laws:
        order = np.argsort(law.tau_s)
        parts.append(np.concatenate([law.sigma_m[order], law.tau_s[order], [law.white_m]]))
    return np.log(np.concatenate(parts))


def _laws_from(vector: np.ndarray, like: Sequence[AxisLaw], tau_max_s: float) -> list[AxisLaw]:
    """The inverse of :func:`_law_vector` (means from ``like``)."""
    out = []
    start = 0
    for law in like:
        k = law.sigma_m.size  # Gauss-Markov components: k sigmas, k taus, the white noise
        v = np.exp(vector[start : start + 2 * k + 1])
        start += 2 * k + 1
        tau_s = np.clip(v[k : 2 * k], 1e-3, tau_max_s)
        out.append(AxisLaw(v[:k], tau_s, float(v[2 * k]), law.mean_m))
    return out


@dataclass(frozen=True)
class LawSpread:
    """The laws fitted to each log alone (rows of log-parameters, :func:`_law_vector`) and
    the variance of a one-log fit's own scatter per parameter."""

    per_log: np.ndarray  # (logs, parameters)
    fit_var: np.ndarray  # (parameters,)


def law_spread(
    logs: Sequence[PositionSeries],
    pooled: Sequence[AxisLaw],
    template: PositionSeries,
    layout: Layout,
    rng: np.random.Generator,
) -> LawSpread:
    """Each log's own law, and the scatter of a one-log fit measured on :data:`LAW_DRAWS`
    parametric draws of the ``pooled`` laws on ``template``'s times."""
    per_log = np.array([_law_vector(axis_laws([log], layout)) for log in logs])
    t_s = np.asarray(template.t_s, dtype=float)
    paths = [colour(law, t_s, rng.standard_normal((LAW_DRAWS, t_s.size))) for law in pooled]
    draws = []
    for j in range(LAW_DRAWS):
        up = paths[2][j] if len(paths) > 2 else np.zeros(t_s.size)
        series = template.with_(
            east_m=paths[0][j], north_m=paths[1][j], up_m=up, valid=np.ones(t_s.size, dtype=bool)
        )
        draws.append(_law_vector(axis_laws([series], layout)))
    return LawSpread(per_log, np.var(np.array(draws), axis=0, ddof=1))


# How far beyond the span of the logs' own laws a drawn law's parameter may go (a factor).
# The draws are Gaussian in log-parameters, and a parameter that one log's fit puts near 0
# (the white noise, when the fast Gauss-Markov component takes it over) spreads by many
# units in log: on three simulated NEO-5 hours whose north white noise came out 0, 0.39 and
# 0 m, 3 of 20 drawn laws had 21-190 m of it, and their replicates (up to 29 "steady
# jumps" where the logs had none) widened every cell's spread and limit, hiding jumps of
# 2-2.5 m that the logs' own hours tell apart at once.
LAW_DRAW_MARGIN = 2.0


def drawn_laws(
    spread: LawSpread,
    pooled: Sequence[AxisLaw],
    n_out: int,
    layout: Layout,
    rng: np.random.Generator,
) -> list[list[AxisLaw]] | None:
    """``n_out`` sets of axis laws around ``pooled``: the logs' deviations from their mean
    law, each parameter's shrunk by the part a one-log fit's scatter explains, combined with
    Gaussian weights (the covariance of the logs' laws, parameters' correlations kept) and
    widened by sqrt(1 + 1/n), as for one more log; each parameter kept within
    ``LAW_DRAW_MARGIN`` times the span of the logs' and the pooled law's. None with fewer
    than two logs."""
    n = spread.per_log.shape[0]
    if n < 2:
        return None
    dev = spread.per_log - spread.per_log.mean(axis=0)
    between = np.var(spread.per_log, axis=0, ddof=1)
    keep = np.sqrt(np.clip(1.0 - spread.fit_var / np.maximum(between, 1e-12), 0.0, 1.0))
    scale = math.sqrt((1.0 + 1.0 / n) / (n - 1))
    centre = _law_vector(pooled)
    margin = math.log(LAW_DRAW_MARGIN)
    low = np.minimum(spread.per_log.min(axis=0), centre) - margin
    high = np.maximum(spread.per_log.max(axis=0), centre) + margin
    tau_max_s = 100.0 * max(layout.duration_s, layout.dt_s)
    weights = rng.standard_normal((n_out, n))
    return [
        _laws_from(np.clip(centre + scale * (w @ (dev * keep)), low, high), pooled, tau_max_s)
        for w in weights
    ]


# adds whole-log cells to replicate batteries and a log's battery, in place
WholeLogCells = Callable[
    [Sequence[PositionSeries], Sequence[dict[Cell, float]], PositionSeries, dict[Cell, float]],
    None,
]


AXIS_NAMES = ("east", "north", "up")  # the order of :func:`axis_laws`


# The shortest correlation time assumed for the slowest error (s). GNSS's slow errors
# (ionosphere, troposphere, orbit and clock; the simulator's run at 1800-3600 s) decorrelate
# over about an hour, which an hour's fit cannot see: on three simulated NEO-5 hours it found
# 300-450 s (the multipath's 300 s) and so counted three times the draws the hours hold.
SLOW_TAU_FLOOR_S = 3600.0
# The fewest degrees of freedom given: a t law with 2 or fewer has no finite variance, and
# its family-wise limit runs to hundreds of spreads (one sim log would then flag no bias of
# any size; 3 dof is about what one 15-minute log of a 2-minute drift pins).
MIN_SLOW_DOF = 3.0


def slow_error_dof(laws: Sequence[AxisLaw], n_logs: int, duration_s: float) -> dict[str, float]:
    """Per axis, the degrees of freedom with which ``n_logs`` logs of ``duration_s`` (s) pin
    the spread of their per-log statistics (means, spread, autocorrelation: the slow error's
    low-frequency level), read from the periodogram ordinates below its corner 1 / (2 pi tau):
    duration / (2 pi tau) per log and two dof each, at least one per log, and no fewer than
    :data:`MIN_SLOW_DOF` in all. tau is the longest fitted correlation time, but no shorter
    than :data:`SLOW_TAU_FLOOR_S`: one per log for logs of up to about three hours.
    "horizontal": the smaller of east and north."""
    dof = {}
    for name, law in zip(AXIS_NAMES, laws, strict=False):
        tau_s = max(float(np.max(law.tau_s)), SLOW_TAU_FLOOR_S)
        dof[name] = max(MIN_SLOW_DOF, n_logs * max(1.0, duration_s / (math.pi * tau_s)))
    dof["horizontal"] = min(dof["east"], dof["north"])  # whole-plane cells
    return dof


def few_logs_null(
    logs: Sequence[PositionSeries],
    template: PositionSeries,
    layout: Layout,
    n_out: int,
    rng: np.random.Generator,
    block_s: float | None = None,
    jitter_s: float | None = None,
    whole_log_cells: WholeLogCells | None = None,
) -> tuple[list[PositionSeries], Inflation, dict[str, float]]:
    """The null ensemble of a few baseline ``logs`` (see the section's comment): ``n_out``
    replicates on ``template``'s times, each coloured with a law of its own drawn from how
    the logs' laws differ (:func:`drawn_laws`; with one log the pooled law), the spread
    factors that make it honest
    (:func:`x6wd.gap.null.inflation_from`: each log scored against replicates of the
    others; with one log only the floor) and the degrees of freedom of the per-log statistics
    per axis (:func:`slow_error_dof`). ``block_s`` the innovation blocks (default 1/30 of the
    log, at least 30 steps), ``jitter_s`` how far from the same time a block may come
    (default 1/12 of the log): innovations at exactly the same times of n logs would give
    only n choices per epoch, and replicates that cluster around the logs' own values.
    ``whole_log_cells(runs, run_batteries, log, log_battery)`` adds the sensor's whole-log
    cells (in place), so that they are scored as well."""
    from x6wd.gap.stats import battery

    block_s = block_s or max(layout.duration_s / 30.0, 30 * layout.dt_s)
    jitter_s = layout.duration_s / 12.0 if jitter_s is None else jitter_s
    lattice = lattice_of(logs)
    pooled = axis_laws(logs, layout)
    spread = law_spread(logs, pooled, template, layout, rng) if len(logs) > 1 else None
    runs = innovation_replicates(
        logs, pooled, template, n_out, block_s, jitter_s, rng, lattice,
        drawn_laws(spread, pooled, n_out, layout, rng) if spread is not None else None,
    )  # fmt: skip
    rows = []
    cells: tuple[Cell, ...] = ()
    for i, log in enumerate(logs if len(logs) > 1 else []):
        others = [s for j, s in enumerate(logs) if j != i]
        laws = axis_laws(others, layout)
        assert spread is not None
        # the same procedure on n - 1 logs: their own laws, the one-log fit scatter as above
        spread_i = LawSpread(np.delete(spread.per_log, i, axis=0), spread.fit_var)
        draws = innovation_replicates(
            others, laws, log, n_out, block_s, jitter_s, rng, lattice,
            drawn_laws(spread_i, laws, n_out, layout, rng),
        )  # fmt: skip
        draw_batteries = [battery(s, layout) for s in draws]
        log_battery = battery(log, layout)
        if whole_log_cells is not None:
            whole_log_cells(draws, draw_batteries, log, log_battery)
        null = null_model(draw_batteries)
        cells = null.cells
        rows.append(null.z(log_battery))
    dof = slow_error_dof(pooled, len(logs), layout.duration_s)
    return runs, inflation_from(cells, np.array(rows), len(logs)), dof
