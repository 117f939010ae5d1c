"""The battery of statistics the gap tool compares between a real log and the simulator.

Every statistic is a *cell* (statistic, axis, scale, period, place) with one number per
series, on a scale where the sim-vs-sim spread is roughly Gaussian (logs of spreads and Allan
deviations, plain means, fractions). Nothing here is an iid test: the cells only get a
meaning once :mod:`x6wd.gap.null` calibrates them on sim-vs-sim replicates.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from sim_backend.effects import PositionSeries, truth_track_m


class Cell(NamedTuple):
    """One statistic of the battery. ``scale`` e.g. 'tau=8s', 'lag=10s' or 'all'; ``period``
    e.g. 'all' or 't=0-900s'; ``place`` 'all' or a named map region."""

    statistic: str
    axis: str
    scale: str = "all"
    period: str = "all"
    place: str = "all"


# Smallest spread of each statistic across the null (its own unit): guards z against a null
# that happens to be constant (e.g. a lattice fraction that is exactly 1 in every replicate).
SD_FLOOR: dict[str, float] = {
    "mean": 0.01,  # m
    "log_std": 0.02,
    "log_cep50": 0.02,
    "log_r95": 0.02,
    "tail_ratio": 0.02,
    "log_adev": 0.02,
    "acf": 0.01,
    "log_step_std": 0.02,
    "step_tail": 0.05,
    "lattice": 0.02,
    "zero_step": 0.01,
    "availability": 0.005,
    "log_outage_s": 0.05,
    "latency_slope": 0.01,  # s
    "log_rms_place": 0.02,
    "log_step_std_place": 0.02,
    "log_psd": 0.02,
    # Signed root likelihood ratio (x6wd.gap.drift.random_walk_lr): mostly exactly 0 without a
    # walk, so a dozen runs can show no spread at all and this floor sets the alarm level. At
    # 0.7 the family-wise threshold (z ~ 4.9 over ~75 cells) sits near a root of 3.4, whose
    # tail under the asymptotic (chi-bar-square) law is ~0.03 %: this cell's share of the 5 %
    # family-wise budget. Chosen from that budget, not from the benchmark's cases.
    "random_walk_lr": 0.7,
}

QUANT_DECIMALS = (1, 2, 3, 4, 5)
LATTICE_TOL_M = 0.0005
N_PERIODS = 4


@dataclass(frozen=True)
class Layout:
    """What the battery computes for a pair, fixed from the real log so every replicate
    yields the same cells: ``dt_s`` base step, ``duration_s``, ``moving`` (truth speed known and
    non-zero), place split points (east/north medians of the truth, m)."""

    dt_s: float
    duration_s: float
    moving: bool
    place_e_m: float = 0.0
    place_n_m: float = 0.0
    has_up: bool = True


def layout_for(series: PositionSeries) -> Layout:
    """The cell layout a real series implies (its step, length, motion, map split)."""
    t = np.asarray(series.t_s, dtype=float)
    dt = float(np.median(np.diff(t))) if t.size > 1 else 1.0
    moving = series.speed_mps is not None and float(np.nanmax(series.speed_mps, initial=0.0)) > 0.2
    pe = pn = 0.0
    if moving:
        te, tn = truth_track_m(series)
        pe, pn = float(np.median(te)), float(np.median(tn))
    has_up = bool(np.any(np.asarray(series.up_m)[np.asarray(series.valid, dtype=bool)] != 0.0))
    return Layout(dt, float(t[-1] - t[0]) if t.size else 0.0, moving, pe, pn, has_up)


def regular(series: PositionSeries, dt_s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """East/north/up on a regular grid of step ``dt_s`` over the series' span (linear
    interpolation across no-fix epochs): the form Allan deviation and autocorrelation need."""
    v = np.asarray(series.valid, dtype=bool)
    t = np.asarray(series.t_s, dtype=float)[v]
    if t.size < 2:
        z = np.zeros(max(t.size, 1))
        return z, z, z
    grid = np.arange(t[0], t[-1] + 0.5 * dt_s, dt_s)
    e, n, u = (
        np.interp(grid, t, np.asarray(a, dtype=float)[v])
        for a in (series.east_m, series.north_m, series.up_m)
    )
    return e, n, u


def octave_taus(layout: Layout) -> list[int]:
    """Averaging factors m = 1, 2, 4, ... with m*dt at most a tenth of the log (enough
    independent blocks for a stable estimate)."""
    n = int(layout.duration_s / layout.dt_s) + 1
    out, m = [], 1
    while m <= max(1, n // 10):
        out.append(m)
        m *= 2
    return out


def allan_var(y: np.ndarray, ms: list[int]) -> np.ndarray:
    """Overlapping Allan variance of y (treated as frequency data) at averaging factors ms."""
    c = np.concatenate(([0.0], np.cumsum(y - (y.mean() if y.size else 0.0))))
    out = np.full(len(ms), np.nan)
    for i, m in enumerate(ms):
        if 2 * m >= c.size:
            break
        avg = (c[m:] - c[:-m]) / m
        d = avg[m:] - avg[:-m]
        out[i] = 0.5 * float(np.mean(d * d))
    return out


def spectrum_bands(
    east: np.ndarray, north: np.ndarray, layout: Layout
) -> tuple[list[tuple[float, float]], list[float]]:
    """Horizontal power spectral density (m^2/Hz, east + north periodograms, means removed)
    averaged in bands two octaves wide, from the Nyquist frequency down to the band whose
    lower edge is ten cycles per log (fewer cycles are too few independent estimates). The
    bands are fixed by the layout, so every series of a pair yields the same cells."""
    n = round(layout.duration_s / layout.dt_s) + 1
    fs = 1.0 / layout.dt_s
    f_min = 10.0 / max(layout.duration_s, layout.dt_s)
    edges = []
    hi = fs / 2
    while hi / 4 >= f_min:
        edges.append((hi / 4, hi))
        hi /= 4
    m = min(n, east.size, north.size)
    if m < 8 or not edges:
        return edges, [0.0] * len(edges)
    f = np.fft.rfftfreq(m, layout.dt_s)
    psd = np.zeros(f.size)
    for y in (east[:m], north[:m]):
        psd += np.abs(np.fft.rfft(y - y.mean())) ** 2 * layout.dt_s / m
    return edges, [
        float(np.mean(psd[(f > lo) & (f <= hi)])) if np.any((f > lo) & (f <= hi)) else 0.0
        for lo, hi in edges
    ]


def acf(y: np.ndarray, lags: list[int]) -> np.ndarray:
    """Sample autocorrelation at the given lags (mean removed)."""
    x = y - y.mean()
    var = float(np.dot(x, x))
    out = np.zeros(len(lags))
    if var <= 0:
        return out
    for i, k in enumerate(lags):
        if 0 < k < x.size:
            out[i] = float(np.dot(x[:-k], x[k:])) / var
    return out


def _log(x: float) -> float:
    return float(np.log(max(x, 1e-6)))


def lattice_fraction(series: PositionSeries, decimals: int) -> float:
    """Fraction of valid epochs whose latitude AND longitude minutes lie on the
    10^-decimals grid (NMEA printing with that many decimals puts every fix on it)."""
    from sim_backend.effects import metres_per_degree

    v = np.asarray(series.valid, dtype=bool)
    if not np.any(v):
        return 0.0
    e_per, n_per = metres_per_degree(series.origin_lat_deg)
    te, tn = truth_track_m(series)
    lat = series.origin_lat_deg + (tn[v] + np.asarray(series.north_m, dtype=float)[v]) / n_per
    lon = series.origin_lon_deg + (te[v] + np.asarray(series.east_m, dtype=float)[v]) / e_per
    scale = 10.0**decimals
    # An absolute tolerance of 0.5 mm: float round trips through metres stay far inside it,
    # and so does a window's re-based origin over a few hundred metres. Off-lattice data
    # passes with probability 1 mm / step per axis (about 5 % at 5 decimals, nil coarser).
    ok = np.ones(lat.size, dtype=bool)
    for a, m_per_deg in ((lat, n_per), (lon, e_per)):
        u = np.abs(a) * 60.0 * scale
        tol = LATTICE_TOL_M / (m_per_deg / 60.0 / scale)
        ok &= np.abs(u - np.round(u)) < tol
    return float(np.mean(ok))


def _outages(valid: np.ndarray, t: np.ndarray) -> tuple[float, float]:
    """(availability fraction, mean outage length s; 0 when none)."""
    if valid.size == 0:
        return 0.0, 0.0
    avail = float(np.mean(valid))
    d = np.diff(np.concatenate(([1], valid.astype(int), [1])))
    starts, ends = np.flatnonzero(d == -1), np.flatnonzero(d == 1)
    if starts.size == 0:
        return avail, 0.0
    dt = float(np.median(np.diff(t))) if t.size > 1 else 1.0
    return avail, float(np.mean(ends - starts)) * dt


def battery(series: PositionSeries, layout: Layout) -> dict[Cell, float]:
    """Every statistic of the battery for one error series (metres, seconds)."""
    out: dict[Cell, float] = {}
    v = np.asarray(series.valid, dtype=bool)
    t = np.asarray(series.t_s, dtype=float)
    E = np.asarray(series.east_m, dtype=float)
    N = np.asarray(series.north_m, dtype=float)
    U = np.asarray(series.up_m, dtype=float)
    axes = {"east": E[v], "north": N[v]}
    if layout.has_up:
        axes["up"] = U[v]
    if not np.any(v):
        ev = np.zeros(1)
        axes = {k: ev for k in axes}
    for ax, x in axes.items():
        out[Cell("mean", ax)] = float(np.mean(x))
        out[Cell("log_std", ax)] = _log(float(np.std(x)))
    h = np.hypot(axes["east"] - np.mean(axes["east"]), axes["north"] - np.mean(axes["north"]))
    habs = np.hypot(axes["east"], axes["north"])
    cep, r95 = float(np.quantile(habs, 0.5)), float(np.quantile(habs, 0.95))
    out[Cell("log_cep50", "horizontal")] = _log(cep)
    out[Cell("log_r95", "horizontal")] = _log(r95)
    out[Cell("tail_ratio", "horizontal")] = _log(
        float(np.quantile(h, 0.99)) / max(float(np.quantile(h, 0.5)), 1e-6)
    )

    # time structure on a regular grid
    re, rn, ru = regular(series, layout.dt_s)
    grid = {"east": re, "north": rn}
    if layout.has_up:
        grid["up"] = ru
    ms = octave_taus(layout)
    lags_s = [1.0, 10.0, 60.0, 300.0]
    lags = [max(1, round(s / layout.dt_s)) for s in lags_s if s < layout.duration_s / 5]
    for (lo, hi), power in zip(
        *spectrum_bands(np.asarray(grid["east"]), np.asarray(grid["north"]), layout), strict=True
    ):
        out[Cell("log_psd", "horizontal", f"{lo:.3g}-{hi:.3g}Hz")] = _log(power)
    for ax, y in grid.items():
        av = allan_var(y, ms)
        for m, a in zip(ms, av, strict=True):
            out[Cell("log_adev", ax, f"tau={m * layout.dt_s:g}s")] = (
                0.5 * _log(a) if np.isfinite(a) else 0.0
            )
        for k, r in zip(lags, acf(y, lags), strict=True):
            out[Cell("acf", ax, f"lag={k * layout.dt_s:g}s")] = r
    # increments between consecutive valid epochs: step size, jump tails, exact repeats
    for ax, x in (("east", axes["east"]), ("north", axes["north"])):
        d = np.diff(x) if x.size > 1 else np.zeros(1)
        sd = float(np.std(d))
        out[Cell("log_step_std", ax)] = _log(sd)
        mad = float(np.median(np.abs(d - np.median(d)))) * 1.4826
        out[Cell("step_tail", ax)] = _log(float(np.quantile(np.abs(d), 0.999)) / max(mad, 1e-4))
        out[Cell("zero_step", ax)] = float(np.mean(d == 0.0))
    for dec in QUANT_DECIMALS:
        out[Cell("lattice", "horizontal", f"1e-{dec} min")] = lattice_fraction(series, dec)
    avail, outage = _outages(v, t)
    out[Cell("availability", "fix")] = avail
    out[Cell("log_outage_s", "fix")] = float(np.log1p(outage))
    if layout.moving and series.speed_mps is not None:
        out[Cell("latency_slope", "along")] = latency_slope(series)[0]
    # per period: where in time
    edges = np.linspace(0.0, layout.duration_s, N_PERIODS + 1)
    t0 = t - (t[0] if t.size else 0.0)
    for i in range(N_PERIODS):
        sel = (
            v & (t0 >= edges[i]) & (t0 < edges[i + 1] if i < N_PERIODS - 1 else t0 <= edges[i + 1])
        )
        label = f"t={edges[i]:.0f}-{edges[i + 1]:.0f}s"
        if np.count_nonzero(sel) < 3:
            sel = v  # a period without fixes falls back to the whole log (availability flags it)
        out[Cell("mean", "east", period=label)] = float(np.mean(E[sel])) if np.any(sel) else 0.0
        out[Cell("mean", "north", period=label)] = float(np.mean(N[sel])) if np.any(sel) else 0.0
        out[Cell("log_std", "horizontal", period=label)] = _log(
            float(np.sqrt(np.var(E[sel]) + np.var(N[sel]))) if np.any(sel) else 0.0
        )
    # per place (moving logs): where on the map
    if layout.moving:
        te, tn = truth_track_m(series)
        # steps between consecutive valid epochs, attributed to the place of the later one:
        # a local error source (a multipath zone) is fast, so it shows far more in the step
        # size there than in the RMS, which the slow whole-log drift dominates
        iv = np.flatnonzero(v)
        step2 = np.zeros(v.size)
        if iv.size > 1:
            step2[iv[1:]] = np.diff(E[iv]) ** 2 + np.diff(N[iv]) ** 2
        has_step = np.zeros(v.size, dtype=bool)
        has_step[iv[1:]] = True
        for name, in_place in _places(te, tn, layout).items():
            sel = v & in_place
            rms = (
                float(np.sqrt(np.mean(E[sel] ** 2 + N[sel] ** 2)))
                if np.count_nonzero(sel) >= 3
                else 0.0
            )
            out[Cell("log_rms_place", "horizontal", place=name)] = _log(rms)
            ss = has_step & in_place
            out[Cell("log_step_std_place", "horizontal", place=name)] = _log(
                float(np.sqrt(np.mean(step2[ss]))) if np.count_nonzero(ss) >= 3 else 0.0
            )
    return out


def _places(te: np.ndarray, tn: np.ndarray, layout: Layout) -> dict[str, np.ndarray]:
    pe, pn = layout.place_e_m, layout.place_n_m
    return {
        f"{ns}{ew} of ({pe:.0f} m E, {pn:.0f} m N)": ((tn >= pn) == (ns == "N"))
        & ((te >= pe) == (ew == "E"))
        for ns in "NS"
        for ew in "EW"
    }


def latency_slope(series: PositionSeries) -> tuple[float, float]:
    """Least-squares slope (s) of the along-track error on the true speed, and its standard
    error. A receiver reporting the truth of d seconds earlier has slope -d."""
    v = np.asarray(series.valid, dtype=bool)
    if series.speed_mps is None or np.count_nonzero(v) < 5:
        return 0.0, float("inf")
    speed = np.nan_to_num(np.asarray(series.speed_mps, dtype=float))[v]
    crs = np.radians(
        np.nan_to_num(
            np.asarray(
                series.course_deg if series.course_deg is not None else np.zeros(len(series)),
                dtype=float,
            )
        )
    )[v]
    along = np.asarray(series.east_m, dtype=float)[v] * np.sin(crs) + np.asarray(
        series.north_m, dtype=float
    )[v] * np.cos(crs)
    slope, se, resid = _ols(speed, along)
    if resid.size < 5:
        return slope, se
    # GNSS errors are strongly autocorrelated: one Cochrane-Orcutt step (GLS with AR(1)
    # residuals) gives a far tighter and honest slope than plain least squares.
    rho = float(
        np.clip(np.dot(resid[1:], resid[:-1]) / max(float(np.dot(resid, resid)), 1e-12), 0.0, 0.999)
    )
    slope2, se2, _ = _ols(speed[1:] - rho * speed[:-1], along[1:] - rho * along[:-1])
    return (slope2, se2) if math.isfinite(se2) else (slope, se)


def _ols(x: np.ndarray, y: np.ndarray) -> tuple[float, float, np.ndarray]:
    """Slope, its standard error and the residuals of y on x (with intercept)."""
    s = x - x.mean()
    ss = float(np.dot(s, s))
    if ss <= 1e-9:
        return 0.0, float("inf"), np.zeros(0)
    slope = float(np.dot(s, y - y.mean())) / ss
    resid = y - y.mean() - slope * s
    se = float(np.sqrt(np.dot(resid, resid) / max(1, s.size - 2) / ss))
    return slope, se, resid


def window(series: PositionSeries, t0_s: float, t1_s: float) -> PositionSeries:
    """The part of a series with t0_s <= t - t_start < t1_s (same origin; t not reset)."""
    t = np.asarray(series.t_s, dtype=float)
    rel = t - t[0]
    m = (rel >= t0_s) & (rel < t1_s)

    def cut(a: np.ndarray | None) -> np.ndarray | None:
        return None if a is None else np.asarray(a)[m]

    # The origin moves to the truth at the window start so the implied truth track matches.
    te, tn = truth_track_m(series)
    from sim_backend.effects import metres_per_degree

    e_per, n_per = metres_per_degree(series.origin_lat_deg)
    k = int(np.argmax(m)) if np.any(m) else 0
    return PositionSeries(
        t_s=t[m],
        east_m=np.asarray(series.east_m)[m],
        north_m=np.asarray(series.north_m)[m],
        up_m=np.asarray(series.up_m)[m],
        valid=np.asarray(series.valid)[m],
        origin_lat_deg=series.origin_lat_deg + float(tn[k]) / n_per,
        origin_lon_deg=series.origin_lon_deg + float(te[k]) / e_per,
        speed_mps=cut(series.speed_mps),
        course_deg=cut(series.course_deg),
        nsats=cut(series.nsats),
    )
