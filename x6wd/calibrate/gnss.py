"""GNSS error calibration (seed 003, section 3): RE, ASE and the LCE map from reference runs.

The seed paper writes the GPS fix's uncertainty as ``σ = DOP·sqrt(RE² + ASE² + LCE(position)²)``
(eq. 12) and measures its three terms in three experiments: RE (receiver error) with the
receiver standing in the open with ASE removed (RTK), ASE (atmosphere, satellite clock and
orbit) standing in the open without RTK, and LCE (local characteristic error: multipath,
foliage) per area of a map by repeated driving with the first two subtracted.

Units and convention, the same as :class:`x6wd.nav.estimator.GpsParams`, which uses the
result: every term is a standard deviation PER HORIZONTAL AXIS (east, north) in metres at
HDOP 1; a fix with HDOP ``h`` has per-axis variance ``h²·(RE² + ASE² + LCE²)``. (The
simulator's seed-003 form draws each axis with ``h·UERE/√2``: its ``re_m``, ``ase_m`` and
LCE grid are √2 times these.) Fixes without an HDOP (RTKLIB files) are taken at HDOP 1.

**Static recording, known position: RE and ASE** (:func:`static_noise`). With one receiver
and no RTK, RE and ASE are told apart by their time scales, as the estimator models them:
RE is the WHITE part of the error (receiver noise decorrelates from one epoch to the next),
ASE the SLOW part (a first-order Gauss-Markov process, correlation time τ of minutes; a
constant offset counts as slow). With ``z = error / HDOP`` per axis, epoch spacing ``Δt``,
``ρ = exp(−Δt/τ)`` and both axes pooled:

- the mean square about the known position, ``M = mean(z²) → RE² + ASE²`` (the reference is
  known, so a bias is kept in it, not removed with a sample mean);
- the variogram at lags of one and two epochs, ``γ(k) = ½·mean((z(t+kΔt) − z(t))²) →
  RE² + ASE²·(1 − ρ^k)``. RE² is the variogram's nugget, its value extrapolated to lag 0⁺;
  from lags 1 and 2, ``RE² = 2γ(1) − γ(2) + ASE²·(1 − ρ)²`` (the last term is the exponential's
  curvature, a few per mille of ASE² for τ ≥ 20 Δt);
- ``ASE² = M − RE²`` with ``ρ = 1 − (γ(1) − RE²)/ASE²``; the three equations are solved by
  fixed-point iteration (they converge in a few steps);
- ``τ = −Δt / ln ρ``; when RE² is most of γ(1), from a least-squares fit of the variogram
  over lags up to a quarter of the record instead (:func:`_variogram_tau`): there the slow
  part's rise γ(1) − RE² is a small difference of noisy terms (a white part of a metre gave
  infinite τ), and the fit's ρ is the one M's law below uses.

Pairs for the variogram are only epochs exactly k·Δt apart, so gaps cost pairs, not bias.
Standard errors: RE² by a delete-one-block jackknife over 20 contiguous blocks (the variogram
at lag 1 and 2 is local in time); M from the Gauss-Markov model itself,
``Var(M) = [ASE⁴·(1 + ρ²)/(1 − ρ²) + 2·RE²·ASE² + RE⁴] / n`` with n fixes (per axis, then the two
axes averaged), the factor (1 + ρ²)/(1 − ρ²) capped at n (a record shorter than τ is one
sample of the slow error). ASE² carries both. An estimate that comes out negative is set to 0
(the jackknife runs over the nugget before that clamp, so a 0 still gets its resolution as SE).
An RE of 0 cannot be written (the daemon needs white noise > 0): the fragment then carries
RE's hard bound sqrt(γ(1)), since γ(1) = RE² + ASE²·(1 − ρ) ≥ RE² (docs/gnss_calibration.md).
Fixes on the same epoch as the fix before (repeated time stamps) are left out and counted.
τ is given without a standard error: it is rough unless the record lasts many τ.

**Drives with a reference trajectory: the LCE map** (:func:`lce_map`). Each fix is matched
with the reference at its time (linear interpolation between reference epochs no more than
``max_gap_s`` apart; an x6wd recording matches a GPST ``.pos`` reference through its UTC
stamp plus the GPS-UTC leap seconds), its error ``z² = (e_E² + e_N²) / (2·HDOP²)`` and its
cell from the REFERENCE position: cells of ``cell_m`` in the local tangent plane at
``origin``, indexed ``(floor(east/cell), floor(north/cell))``. Per cell::

    LCE² = mean(z²) − RE² − ASE²        (0 when negative)

with the count of fixes, the count of VISITS (fixes in the cell less than ``visit_gap_s``
apart belong to one pass; passes are the independent repetitions of the paper's "repeated
driving") and a standard error. The SE of mean(z²) is cluster-robust over visits (fixes within
one pass are correlated); with a single visit it is the naive one over fixes, which is too
small when the errors are correlated: such cells are marked by ``min_visits`` (default 2).
``SE(LCE) = sqrt(LCE² + SE(LCE²)) − LCE`` (the delta method's ``SE(LCE²)/(2·LCE)`` for a clear
LCE, ``sqrt(SE(LCE²))`` at 0). Cells with fewer than ``min_fixes`` fixes or ``min_visits``
visits are marked (kept in the table, left out of the configuration). ``lce_default_m``, for
marked and unvisited cells, is the same estimate pooled over every matched fix.

**Drives: the white part of a moving receiver** (:func:`moving_white`). A static recording's
RE is the white part of a receiver standing still; moving, the error also has a part that
changes in tens of seconds, which the estimator's one slow state cannot follow and must take
as white. With drives, ``re_m`` is written from their variogram when that is larger
(:attr:`GnssCalibration.re_m_written`; docs/gnss_calibration.md).
"""

from __future__ import annotations

import csv
import itertools
import math
import sys
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import numpy.typing as npt

from drivers.gps_nmea import GpsDecoder
from drivers.gps_recording import recorded_gps
from x6wd.calibrate.rtklib import looks_like_pos, read_pos
from x6wd.core.config import GnssNoiseConfig, build
from x6wd.core.errors import ConfigError, DeviceUnavailable, ParseError
from x6wd.core.files import require_regular
from x6wd.core.geodesy import great_circle_m, wrap_deg
from x6wd.core.motion import MAX_STATIC_SPEED_MPS, MOVE_SIGNIFICANCE, steady_speed_mps
from x6wd.core.recorder import gpsd_json_error, is_gpsd_json, is_recording
from x6wd.core.records import GpsFix
from x6wd.nav.geo import LocalTangentPlane

Array = npt.NDArray[np.float64]

GPS_UTC_LEAP_S = 18.0
"""GPS time minus UTC since 2017-01-01 (s): turns an x6wd fix's UTC into GPST for a ``.pos``
reference. Recordings from before 2017 would need the older value."""

JACKKNIFE_BLOCKS = 20

MAX_STATIC_SPREAD_M = 20.0
"""Largest median distance (m, at HDOP 1) of a static recording's fixes from their median
position. A receiver standing still scatters about 1.18 times its per-axis error (the median
of a 2-D normal's radius): 1-4 m for a NEO-5 in the open, 20 m is a per-axis error of 17 m,
which no open-sky receiver shows, but a robot that drove a few tens of metres does. The
median, not the mean square, so a few multipath jumps of a still receiver do not count."""

MAX_CORRELATION_S = 86400.0
"""The largest ``correlation_s`` the configuration takes (s); an estimate beyond it (a record
far shorter than the slow part's correlation time) is written as this bound, and said so."""

MAX_STATIC_OFFSET_M = 50.0
"""Largest distance (m) of a static recording's median position from the given reference.
A NEO-5's slow error is a few metres (10 m at worst in the open); a reference in another
datum (ED50 vs WGS-84: 100-200 m in Europe), a slip in the third decimal (111 m) or swapped
latitude and longitude are far beyond it, and would be written as an ASE of that size."""

MIN_MATCHED_FRACTION = 0.5
"""Smallest share of a drive's fixes that its reference must cover (a time within it, no
gap over ``max_gap_s``). A drive's own reference covers it whole (a simulated run and its
``truth.csv``: 233 of 234 fixes, the first fix coming before the reference's second epoch;
the urban drive against RTK: 550 of 550); another run's reference covers only the span the
two share (a zigzag drive against the default mission's truth.csv: 72 of 234, 31 %), and
its positions there are of another path."""

MAX_DRIVE_MEDIAN_ERROR_M = 20.0
"""Largest median horizontal distance (m, at HDOP 1) of a drive's matched fixes from their
reference. The same bound as a static recording's spread (:data:`MAX_STATIC_SPREAD_M`): a
median of 20 m is a per-axis error of 17 m, which no receiver shows against its own
reference, even in a street canyon (the urban drive, single-point fixes against RTK: median
2.9 m, its worst 5 % beyond 27 m); the median, so a stretch of multipath does not count. A
drive matched against another run's reference reads its distance from that other path:
tens of metres (a zigzag drive against a standing robot's truth.csv: written as an LCE of
78 m before the check), which would be written as the LCE."""


@dataclass(frozen=True)
class Estimate:
    """A value and its standard error (same unit)."""

    value: float
    se: float


# ------------------------------------------------------------------------------ inputs


@dataclass(frozen=True)
class FixSeries:
    """Positions with their times: ``t_s`` on the source's own clock (s), ``t_gpst_s`` GPST
    (s, as :mod:`x6wd.calibrate.rtklib` counts it; NaN where unknown), latitude/longitude
    (deg) and HDOP (dimensionless; 1 where the source has none, see ``hdop_known``)."""

    t_s: Array
    t_gpst_s: Array
    lat_deg: Array
    lon_deg: Array
    hdop: Array
    hdop_known: bool
    source: str = ""

    def __len__(self) -> int:
        return int(self.t_s.shape[0])

    @classmethod
    def from_fixes(cls, fixes: Sequence[GpsFix], source: str = "") -> FixSeries:
        """Valid fixes with a position, sorted by time; a missing HDOP reads as 1."""
        good = sorted(
            (f for f in fixes if f.valid and f.lat_deg is not None and f.lon_deg is not None),
            key=lambda f: f.t_s,
        )
        if not good:
            raise ParseError(f"{source or 'fixes'}: no valid fix with a position")
        for f in good:
            why = _bad_position(f.t_s, f.lat_deg, f.lon_deg)  # type: ignore[arg-type]
            if why:
                raise ParseError(f"{source or 'fixes'}: the fix at t_s {f.t_s:.3f}: {why}")
        hd = [f.hdop for f in good]
        return cls(
            t_s=np.array([f.t_s for f in good], float),
            t_gpst_s=np.array(
                [
                    f.utc.timestamp() + GPS_UTC_LEAP_S if f.utc is not None else math.nan
                    for f in good
                ]
            ),
            lat_deg=np.array([f.lat_deg for f in good], float),
            lon_deg=np.array([f.lon_deg for f in good], float),
            hdop=np.array([h if h is not None and h > 0 else 1.0 for h in hd], float),
            hdop_known=all(h is not None and h > 0 for h in hd),
            source=source,
        )


def load_fixes(path: str | Path) -> FixSeries:
    """Fixes from an RTKLIB ``.pos`` file (every solved epoch, HDOP 1), a CSV (see
    :func:`_load_csv`), an x6wd recording (its valid fixes, all parts: the ``fix`` records,
    or the ``nmea`` ones decoded) or a plain NMEA log (a file whose first non-blank character
    is not ``{``: decoded as ``x6wd decode`` does, its fixes timed by their UTC)."""
    p = Path(path)
    try:
        require_regular(p)  # /dev/zero has no line end: one endless line
    except OSError as exc:
        raise DeviceUnavailable(f"cannot read {p}: {exc.strerror}") from exc
    if looks_like_pos(p):
        sol = read_pos(p)
        order = np.argsort(sol.t_gpst_s, kind="stable")
        return FixSeries(
            t_s=sol.t_gpst_s[order],
            t_gpst_s=sol.t_gpst_s[order],
            lat_deg=sol.lat_deg[order],
            lon_deg=sol.lon_deg[order],
            hdop=np.ones(len(sol)),
            hdop_known=False,
            source=str(p),
        )
    if p.suffix.lower() == ".csv":
        return _load_csv(p)
    if not _is_recording(p):
        return _load_nmea(p)
    fixes = [r for r in recorded_gps(p) if isinstance(r, GpsFix)]
    return FixSeries.from_fixes(fixes, str(p))


def _is_recording(p: Path) -> bool:
    """An x6wd recording (the test ``x6wd decode`` uses); a directory or a missing file is
    left to the recording reader, which names the fault."""
    if not p.is_file():
        return True
    try:
        return is_recording(p)
    except DeviceUnavailable as exc:
        raise ParseError(str(exc)) from exc


def _load_nmea(p: Path) -> FixSeries:
    """A plain NMEA log (u-blox and others; binary and line noise tolerated) through the
    daemon's decoder. A log carries no receive clock, so a fix's time is its UTC (s): the
    first dated sentence (RMC, ZDA) dates the epochs before it too; epochs without a time
    are dropped. ``t_gpst_s`` is that UTC + :data:`GPS_UTC_LEAP_S`."""

    def fixes(decoder: GpsDecoder) -> Iterator[GpsFix]:
        with open(p, "rb") as f:
            while chunk := f.read(1 << 16):
                yield from (o for o in decoder.feed(chunk, 0.0) if isinstance(o, GpsFix))
        yield from (o for o in decoder.flush() if isinstance(o, GpsFix))

    try:
        first = next((f.utc for f in fixes(GpsDecoder(emit_sentences=False)) if f.utc), None)
        decoder = GpsDecoder(emit_sentences=False)
        if first is not None:  # a GGA before the log's first RMC has a time but no date
            decoder.assume_utc(first)
        timed = [replace(f, t_s=f.utc.timestamp()) for f in fixes(decoder) if f.utc is not None]
    except OSError as exc:
        raise ParseError(f"cannot read {p}: {exc.strerror or exc}") from exc
    if not timed:
        if is_gpsd_json(p):  # it starts with '{' too: not a recording all the same
            raise ParseError(gpsd_json_error(p, "x6wd calibrate gnss"))
        raise ParseError(
            f"{p}: no NMEA fix with a date and time (an x6wd recording starts with '{{'; "
            "a plain log needs RMC or ZDA sentences for its dates)"
        )
    return FixSeries.from_fixes(timed, str(p))


CSV_COLUMNS = {"t_s": ("t_s", "time"), "lat": ("lat", "latitude"), "lon": ("lon", "longitude")}
"""The CSV columns (any case, spaces around names and values ignored): ``x6wd sim``'s
``truth.csv`` (t_s, lat, lon[, hdop]) and a receiver-log layout (TIME, LATITUDE, LONGITUDE,
as in the ZED-F9P log of coverclock/com-diag-hazer, tests/data/static: TIME in UTC epoch
seconds; its HORIZONTAL is an accuracy in metres, not an HDOP, and is not read)."""


def _bad_position(t_s: float, lat_deg: float, lon_deg: float) -> str | None:
    """What is wrong with a fix's time or position (a NaN from a writer, a value out of
    range), or None; the caller names the file and the line or fix."""
    for name, v, limit in (("t_s", t_s, math.inf), ("lat_deg", lat_deg, 90.0),
                           ("lon_deg", lon_deg, 180.0)):  # fmt: skip
        if not (math.isfinite(v) and abs(v) <= limit):
            within = f" and within ±{limit:g}" if limit < math.inf else ""
            return f"{name} must be finite{within}, got {v}"
    return None


def _load_csv(p: Path) -> FixSeries:
    """A CSV of times (s), latitudes and longitudes (deg), optional ``hdop``
    (:data:`CSV_COLUMNS`); no HDOP column: HDOP 1. The time is the file's own clock (no GPST:
    such a file does not match a ``.pos`` reference)."""
    try:
        with open(p, newline="", encoding="utf-8") as f:
            reader = csv.reader(f, skipinitialspace=True)
            header = [h.strip().lower() for h in next(reader, [])]
            lines, rows = [], []  # each row's line number, for the errors
            for row in reader:
                lines.append(reader.line_num)
                rows.append(row)
    except OSError as exc:
        raise ParseError(f"cannot read {p}: {exc.strerror or exc}") from exc
    col: dict[str, int] = {}
    for key, names in CSV_COLUMNS.items():
        found = next((header.index(n) for n in names if n in header), None)
        if found is not None:
            col[key] = found
    if len(col) < 3:
        raise ParseError(
            f"{p}: a CSV reference needs the columns t_s, lat, lon (or TIME, LATITUDE, "
            f"LONGITUDE); the header has {', '.join(header) or 'nothing'}"
        )
    if not rows:
        raise ParseError(f"{p}: no rows of data, only the header ({', '.join(header)})")
    hd = header.index("hdop") if "hdop" in header else None
    try:
        t = np.array([float(r[col["t_s"]]) for r in rows])
        lat = np.array([float(r[col["lat"]]) for r in rows])
        lon = np.array([float(r[col["lon"]]) for r in rows])
        hdop = np.array([float(r[hd].strip() or 1.0) if hd is not None else 1.0 for r in rows])
    except (ValueError, IndexError) as exc:  # IndexError: a short row
        raise ParseError(f"{p}: not a number: {exc}") from exc
    bad = ~np.isfinite(t + lat + lon + hdop) | (np.abs(lat) > 90.0) | (np.abs(lon) > 180.0)
    if bad.any():
        i = int(np.argmax(bad))
        why = _bad_position(t[i], lat[i], lon[i]) or f"hdop must be finite, got {hdop[i]}"
        raise ParseError(f"{p}:{lines[i]}: {why}")
    order = np.argsort(t, kind="stable")
    return FixSeries(
        t[order], np.full(t.shape, math.nan), lat[order], lon[order], hdop[order],
        hd is not None, str(p),
    )  # fmt: skip


# ------------------------------------------------------------------------------ RE and ASE


@dataclass(frozen=True)
class StaticResult:
    """RE and ASE (m per axis at HDOP 1) with their standard errors, the correlation time of
    the slow part (s, rough), and what they came from."""

    re_m: Estimate
    ase_m: Estimate
    correlation_s: float
    mean_square_m2: float  # M, per axis at HDOP 1
    gamma1_m2: float
    gamma2_m2: float
    bias_east_m: float  # mean error, m (at the recording's HDOPs)
    bias_north_m: float
    fixes: int
    duration_s: float
    epoch_s: float
    hdop_known: bool
    mean_hdop: float
    duplicates: int = 0  # fixes dropped for sharing an epoch with the fix before

    @property
    def re_bound_m(self) -> float:
        """A hard upper bound on RE (m): ``γ(1) = RE² + ASE²·(1 − ρ) ≥ RE²``, so RE is at
        most sqrt(γ(1)) however the split comes out."""
        return math.sqrt(max(self.gamma1_m2, 0.0))


def _variogram_sums(z: Array, idx: npt.NDArray[np.int64], lag: int) -> tuple[Array, Array]:
    """Per-pair squared differences (both axes summed) at ``lag`` epochs and the pair's
    first index. ``idx`` the epoch numbers of the fixes (increasing integers)."""
    pos = np.searchsorted(idx, idx + lag)
    ok = pos < idx.shape[0]
    ok[ok] = idx[pos[ok]] == idx[ok] + lag
    i = np.flatnonzero(ok)
    d = z[pos[ok]] - z[i]
    return (d * d).sum(axis=1), i.astype(float)


TAU_FIT_LAGS = 40
"""Lags (a geometric grid from one epoch to a quarter of the record) the variogram is fitted
over for τ (:func:`_variogram_tau`)."""


def _variogram_tau(z: Array, idx: npt.NDArray[np.int64], dt_s: float) -> float:
    """The slow part's correlation time (s): the τ of the least-squares fit of
    ``γ(k) = a + b·(1 − exp(−kΔt/τ))`` (a, b ≥ 0) to the variogram at :data:`TAU_FIT_LAGS`
    lags from one epoch to a quarter of the record, τ on a geometric grid from Δt to
    :data:`MAX_CORRELATION_S` (inf when the best fit is still rising there: no decay seen).
    Lags 1 and 2 alone measure the slow part's rise by the difference γ(1) − RE², which a
    white part of a metre swamps: τ came out 20-40 s or infinite for a true 100 s (an outside
    audit: 86400 s written for a log with 1.5 m of white noise added; 123 s without)."""
    span = int(idx[-1] - idx[0])
    lags = np.unique(np.round(np.geomspace(1, max(span // 4, 2), TAU_FIT_LAGS)).astype(np.int64))
    g = np.array([_variogram_sums(z, idx, int(k))[0] for k in lags], dtype=object)
    keep = np.array([x.size >= 10 for x in g])
    if keep.sum() < 3:
        return math.nan
    lags = lags[keep]
    gam = np.array([float(x.mean()) / 4.0 for x in g[keep]])
    taus = np.geomspace(dt_s, MAX_CORRELATION_S, 400)
    e = 1.0 - np.exp(-np.outer(dt_s / taus, lags))  # (tau, lag)
    # per tau, the 2 x 2 normal equations of (a, b), solved at once
    n, se, see = float(lags.size), e.sum(axis=1), (e * e).sum(axis=1)
    sg, seg = float(gam.sum()), e @ gam
    det = n * see - se * se
    with np.errstate(divide="ignore", invalid="ignore"):
        a = (see * sg - se * seg) / det
        b = (n * seg - se * sg) / det
    resid = ((gam[None, :] - a[:, None] - b[:, None] * e) ** 2).sum(axis=1)
    ok = np.isfinite(resid) & (a >= 0.0) & (b > 0.0)
    if not ok.any():
        return math.nan
    best = int(np.flatnonzero(ok)[np.argmin(resid[ok])])
    return math.inf if best == taus.size - 1 else float(taus[best])


def _solve_re_ase(m: float, g1: float, g2: float) -> tuple[float, float, float, float]:
    """RE², ASE² and ρ from M, γ(1), γ(2) (module docstring), negatives clamped to 0, and
    the nugget before its clamp (m², may be negative: the jackknife needs its spread)."""
    re2 = max(2.0 * g1 - g2, 0.0)
    ase2 = max(m - re2, 0.0)
    rho = 0.0
    raw = 2.0 * g1 - g2
    for _ in range(50):
        rho = 1.0 - (g1 - re2) / ase2 if ase2 > 0 else 0.0
        rho = min(max(rho, 0.0), 1.0)
        raw = 2.0 * g1 - g2 + ase2 * (1.0 - rho) ** 2
        new = min(max(raw, 0.0), m)
        if abs(new - re2) < 1e-12 * max(m, 1e-12):
            re2 = new
            break
        re2 = new
        ase2 = max(m - re2, 0.0)
    return re2, max(m - re2, 0.0), rho, raw


def static_noise(
    fixes: FixSeries, ref_lat_deg: float, ref_lon_deg: float, *, epoch_s: float | None = None
) -> StaticResult:
    """RE and ASE from a static recording at a known position (module docstring).

    ``epoch_s``: the receiver's epoch spacing (s); default the median spacing of the fixes.
    Needs at least 100 fixes and 50 pairs at lags 1 and 2."""
    n = len(fixes)
    what = f"static {fixes.source}" if fixes.source else "static"
    if n < 100:
        raise ConfigError(f"{what}: {n} fixes; need at least 100 (an hour at 1 Hz is better)")
    plane = LocalTangentPlane(ref_lat_deg, ref_lon_deg)
    _check_standing(fixes, ref_lat_deg, ref_lon_deg)
    x, y = plane.to_xy(fixes.lat_deg, fixes.lon_deg)
    err = np.column_stack([np.asarray(x, float), np.asarray(y, float)])
    z = err / fixes.hdop[:, None]
    t = fixes.t_s - fixes.t_s[0]
    dt = float(np.median(np.diff(t))) if epoch_s is None else float(epoch_s)
    if not (dt > 0 and math.isfinite(dt)):
        raise ConfigError(f"{what}: epoch spacing must be > 0 s, got {dt!r}")
    idx = np.round(t / dt).astype(np.int64)
    keep = np.concatenate(([True], np.diff(idx) > 0))  # one fix per epoch
    z, idx, t = z[keep], idx[keep], t[keep]
    n = z.shape[0]
    d1, i1 = _variogram_sums(z, idx, 1)
    d2, i2 = _variogram_sums(z, idx, 2)
    if d1.size < 50 or d2.size < 50:
        raise ConfigError(
            f"{what}: {d1.size} pairs one epoch apart and {d2.size} two apart; need 50 each "
            f"(epoch {dt:g} s: are the fixes that far apart?)"
        )
    zz = (z * z).sum(axis=1)
    m = float(zz.mean()) / 2.0
    g1, g2 = float(d1.mean()) / 4.0, float(d2.mean()) / 4.0  # ½·mean over pairs and axes
    re2, ase2, rho, _ = _solve_re_ase(m, g1, g2)

    # RE²: delete-one-block jackknife (the estimate depends on M only through the small
    # curvature term, which the jackknife carries too). Over the unclamped nugget: replicates
    # clamped at 0 would give an unresolved RE an SE of 0 (a ZED-F9P did: "0.0001 ± 0.0000")
    edges = np.linspace(0, n, JACKKNIFE_BLOCKS + 1).astype(int)
    reps = []
    for b in range(JACKKNIFE_BLOCKS):
        lo, hi = edges[b], edges[b + 1]
        k1 = (i1 < lo) | (i1 >= hi)
        k2 = (i2 < lo) | (i2 >= hi)
        kz = np.ones(n, bool)
        kz[lo:hi] = False
        if k1.sum() < 10 or k2.sum() < 10:
            continue
        *_, raw2 = _solve_re_ase(
            float(zz[kz].mean()) / 2.0, float(d1[k1].mean()) / 4.0, float(d2[k2].mean()) / 4.0
        )
        reps.append(raw2)
    nb = len(reps)
    var_re2 = (nb - 1) / nb * float(np.sum((np.array(reps) - np.mean(reps)) ** 2)) if nb > 1 else 0
    tau = -dt / math.log(rho) if 0.0 < rho < 1.0 else (math.inf if rho >= 1.0 else 0.0)
    if re2 > g1 - re2:
        # the white part is most of γ(1): the slow part's rise, γ(1) − RE², is a small
        # difference of noisy terms; τ (and M's ρ) from the variogram over many lags instead
        fitted = _variogram_tau(z, idx, dt)
        if not math.isnan(fitted):
            tau = fitted
            rho = math.exp(-dt / tau) if tau > 0.0 else 0.0
    # M: the Gauss-Markov law (per axis, then the mean of two independent axes)
    factor = min((1.0 + rho * rho) / (1.0 - rho * rho), float(n)) if rho < 1.0 else float(n)
    var_m = (ase2 * ase2 * factor + 2.0 * re2 * ase2 + re2 * re2) / n
    var_ase2 = var_m + var_re2
    return StaticResult(
        re_m=_root(re2, var_re2),
        ase_m=_root(ase2, var_ase2),
        correlation_s=tau,
        mean_square_m2=m,
        gamma1_m2=g1,
        gamma2_m2=g2,
        bias_east_m=float(err[keep, 0].mean()),
        bias_north_m=float(err[keep, 1].mean()),
        fixes=n,
        duration_s=float(t[-1] - t[0]),
        epoch_s=dt,
        hdop_known=fixes.hdop_known,
        mean_hdop=float(fixes.hdop.mean()),
        duplicates=int((~keep).sum()),
    )


def _check_standing(fixes: FixSeries, ref_lat_deg: float, ref_lon_deg: float) -> None:
    """ConfigError when a static recording moves (:data:`MAX_STATIC_SPREAD_M`, or
    :data:`MAX_STATIC_SPEED_MPS` for motion within that spread) or lies far
    from its reference (:data:`MAX_STATIC_OFFSET_M`): either would be written as an ASE of
    tens of metres that passes the configuration's checks and misleads the estimator."""
    what = f"static {fixes.source}" if fixes.source else "static"
    # the longitudes' median the short way round the 180th meridian (a receiver on it has
    # fixes on both sides; their plain median is near 0 deg)
    lat_m, lon_m = float(np.median(fixes.lat_deg)), float(np.median(fixes.lon_deg))
    if np.ptp(fixes.lon_deg) > 180.0:
        lon0 = float(fixes.lon_deg[0])
        lon_m = float(wrap_deg(lon0 + float(np.median(wrap_deg(fixes.lon_deg - lon0)))))
    x, y = LocalTangentPlane(lat_m, lon_m).to_xy(fixes.lat_deg, fixes.lon_deg)
    spread_m = float(np.median(np.hypot(x, y) / fixes.hdop))
    if spread_m > MAX_STATIC_SPREAD_M:
        raise ConfigError(
            f"{what}: the recording moves: its fixes lie a median {spread_m:.1f} m (at HDOP 1) "
            f"from their median position; a receiver standing still shows a few metres "
            f"(refused above {MAX_STATIC_SPREAD_M:g} m)"
        )
    speed = _steady_speed_mps(fixes, x, y)
    if speed is not None and speed[0] > MAX_STATIC_SPEED_MPS and speed[1] >= MOVE_SIGNIFICANCE:
        raise ConfigError(
            f"{what}: the recording moves: a steady speed of {speed[0]:.2f} m/s over "
            f"{len(fixes):,} fixes (successive 1 s steps point the same way "
            f"as a drive's do, {speed[1]:.0f} standard errors above noise); a receiver "
            f"standing still shows under 0.2 m/s (refused above {MAX_STATIC_SPEED_MPS:g} m/s)"
        )
    off_m = great_circle_m(lat_m, lon_m, ref_lat_deg, ref_lon_deg)
    if off_m > MAX_STATIC_OFFSET_M:
        far = f"{off_m:.0f} m" if off_m < 10_000 else f"{off_m / 1000:.0f} km"
        raise ConfigError(
            f"{what}: the fixes' median position ({lat_m:.6f}, {lon_m:.6f}) is {far} from the "
            f"reference ({ref_lat_deg}, {ref_lon_deg}); a receiver's error is a few metres "
            f"(refused beyond {MAX_STATIC_OFFSET_M:g} m): a typo, latitude and longitude "
            "swapped, or a reference in another datum?"
        )


def _steady_speed_mps(
    fixes: FixSeries, x: npt.ArrayLike, y: npt.ArrayLike
) -> tuple[float, float] | None:
    """:func:`x6wd.core.motion.steady_speed_mps` of a recording's positions ``x``, ``y``
    (m)."""
    return steady_speed_mps(fixes.t_s, x, y, JACKKNIFE_BLOCKS)


def _root(v2: float, var_v2: float) -> Estimate:
    """sqrt of a variance estimate with its SE: ``sqrt(v² + SE(v²)) − v`` (module docstring)."""
    v = math.sqrt(max(v2, 0.0))
    s2 = math.sqrt(max(var_v2, 0.0))
    return Estimate(v, math.sqrt(v * v + s2) - v)


# ------------------------------------------------------------------------------ LCE map


@dataclass(frozen=True)
class Matched:
    """Fixes matched with the reference: time (s, the fix's clock), reference east/north
    (m, in the map's plane), error east/north (m), HDOP, and which drive they came from."""

    t_s: Array
    ref_east_m: Array
    ref_north_m: Array
    err_east_m: Array
    err_north_m: Array
    hdop: Array
    drive: npt.NDArray[np.int64]

    def __len__(self) -> int:
        return int(self.t_s.shape[0])


def match_reference(
    fixes: FixSeries, reference: FixSeries, plane: LocalTangentPlane, *, max_gap_s: float = 1.5
) -> tuple[Matched, int]:
    """Each fix against the reference at its time; (matched fixes, how many had no reference).

    Clock: GPST when the reference has it and the fixes do (fixes without a UTC stamp then go
    unmatched), else each source's own ``t_s`` (the same clock, e.g. a simulated run and its
    ``truth.csv``). The reference is interpolated linearly between its
    two epochs around the fix when they are at most ``max_gap_s`` apart (an exact time match
    needs no neighbour)."""
    use_gpst = bool(np.isfinite(reference.t_gpst_s).all() and np.isfinite(fixes.t_gpst_s).any())
    tf = fixes.t_gpst_s if use_gpst else fixes.t_s
    tr = reference.t_gpst_s if use_gpst else reference.t_s
    rx, ry = (np.asarray(v, float) for v in plane.to_xy(reference.lat_deg, reference.lon_deg))
    fx, fy = (np.asarray(v, float) for v in plane.to_xy(fixes.lat_deg, fixes.lon_deg))
    j = np.searchsorted(tr, tf)  # tr[j-1] < tf <= tr[j]
    jr = np.clip(j, 0, tr.size - 1)
    jl = np.clip(j - 1, 0, tr.size - 1)
    exact = np.abs(tr[jr] - tf) <= 1e-3
    inside = (j > 0) & (j < tr.size)
    span = tr[jr] - tr[jl]
    ok = (exact | (inside & (span <= max_gap_s) & (span > 0))) & np.isfinite(tf)
    w = np.where(exact | (span <= 0), 1.0, (tf - tr[jl]) / np.where(span > 0, span, 1.0))
    ex = np.where(exact, rx[jr], rx[jl] + w * (rx[jr] - rx[jl]))
    ey = np.where(exact, ry[jr], ry[jl] + w * (ry[jr] - ry[jl]))
    m = Matched(
        t_s=tf[ok],
        ref_east_m=ex[ok],
        ref_north_m=ey[ok],
        err_east_m=(fx - ex)[ok],
        err_north_m=(fy - ey)[ok],
        hdop=fixes.hdop[ok],
        drive=np.zeros(int(ok.sum()), np.int64),
    )
    return m, int((~ok).sum())


def concat(parts: Sequence[Matched]) -> Matched:
    """Matched fixes of several drives, each drive numbered (visits never span drives)."""

    def cat(name: str) -> Array:
        return np.concatenate([getattr(p, name) for p in parts])

    return Matched(
        t_s=cat("t_s"),
        ref_east_m=cat("ref_east_m"),
        ref_north_m=cat("ref_north_m"),
        err_east_m=cat("err_east_m"),
        err_north_m=cat("err_north_m"),
        hdop=cat("hdop"),
        drive=np.concatenate([np.full(len(p), k, np.int64) for k, p in enumerate(parts)]),
    )


@dataclass(frozen=True)
class Cell:
    """One map cell: indices (east, north), LCE (m) ± SE, fixes and visits, the RMS error per
    axis at HDOP 1 (m), whether it has enough data, and how its SE was formed."""

    east_index: int
    north_index: int
    lce_m: float
    se_m: float
    fixes: int
    visits: int
    rms_m: float
    enough: bool
    se_over: str  # "visits" (cluster-robust) or "fixes" (one visit: assumes independence)


@dataclass(frozen=True)
class LceMap:
    """The LCE map: plane origin (deg), cell size (m), RE/ASE used (m), the cells with any
    fix, the pooled LCE for cells without a value, the rules and the matched fixes."""

    origin_lat_deg: float
    origin_lon_deg: float
    cell_m: float
    re_m: float
    ase_m: float
    cells: tuple[Cell, ...]
    default: Estimate
    min_fixes: int
    min_visits: int
    matched: Matched
    unmatched: int
    hdop_known: bool = True
    sources: tuple[str, ...] = field(default=())
    tracks: tuple[Array, ...] = field(default=())  # (n, 2) reference east/north per drive, m
    moving: MovingWhite | None = None  # the white part the drives need (:func:`moving_white`)
    visit_gap_s: float = 30.0

    def mapped(self) -> list[Cell]:
        """The cells with enough data (the ones written to the configuration)."""
        return [c for c in self.cells if c.enough]

    def spread_text(self) -> str:
        """The mapped cells' median and 95th percentile LCE, or, with none mapped, why: how
        many cells lack fixes or visits, and the most any has (no percentile of nothing)."""
        v = np.array([c.lce_m for c in self.mapped()])
        if v.size:
            return f"median LCE {np.median(v):.2f} m, 95 % {np.percentile(v, 95):.2f} m"
        few_fixes = sum(c.fixes < self.min_fixes for c in self.cells)
        few_visits = sum(c.visits < self.min_visits for c in self.cells)
        most = (max(c.fixes for c in self.cells), max(c.visits for c in self.cells))
        return (
            f"no cell mapped: {few_fixes} of {len(self.cells)} cells have fewer than "
            f"{self.min_fixes} fixes, {few_visits} fewer than {self.min_visits} visits (the "
            f"most in a cell: {most[0]} fixes, {most[1]} visits)"
            if self.cells
            else "no cell mapped: no fix matched"
        )

    def summary(self) -> dict[str, float]:
        """Cells (all, mapped), fixes, and the median, 95th percentile and max LCE (m) over
        the mapped cells."""
        v = np.array([c.lce_m for c in self.mapped()])
        q = (lambda p: float(np.percentile(v, p))) if v.size else (lambda p: math.nan)
        return {
            "cells": float(len(self.cells)),
            "mapped": float(v.size),
            "fixes": float(len(self.matched)),
            "median_lce_m": q(50),
            "p95_lce_m": q(95),
            "max_lce_m": float(v.max()) if v.size else math.nan,
            "default_lce_m": self.default.value,
        }


@dataclass(frozen=True)
class MovingWhite:
    """The drives' fast error (:func:`moving_white`): the fit ``γ(k) = W + S·(1 − e^(−k·Δt/τ))``
    of their variogram (m² per axis at HDOP 1; τ in s) and the white part the estimator needs,
    ``sqrt(W + S·(1 − e^(−L/τ)))`` with ``L`` = :data:`MOVING_MAX_LAG_S` (m, with a
    leave-one-drive-out SE; NaN with fewer than 3 drives)."""

    nugget_m2: float
    sill_m2: float
    tau_s: float
    fast_fraction: float  # 1 − e^(−L/τ): the share of S that comes and goes within L
    white: Estimate
    pairs: int
    max_lag_s: float


MOVING_MAX_LAG_S = 60.0
"""Longest lag (s) of the drives' variogram that :func:`moving_white` fits: a quarter of a
short drive (the simulated zigzag: 230 s), and far below the slow part's correlation time
(the static calibration's τ: minutes; the shipped 120 s), so the estimator's bias state is
near constant over it and whatever varies within it must be its white part. It is also the lag
``L`` at which :func:`moving_white` reads the white part: ``W + S·(1 − e^(−L/τ))``."""

MOVING_WARN_RATIO = 2.0
"""The drives' white part more than this many times the ``re_m`` written (a given ``--re-m`` or
``--config``) is warned about on stderr: the estimator on a moving robot would read the rest
as motion."""


def _drive_variogram(m: Matched, lag_s: Array) -> tuple[Array, Array]:
    """γ(k) (m² per axis at HDOP 1; ½·mean over pairs and axes) and pair counts at each lag
    (s), over pairs of fixes of one drive exactly that far apart (on each drive's median
    epoch)."""
    z = np.column_stack([m.err_east_m, m.err_north_m]) / m.hdop[:, None]
    sums, counts = np.zeros(len(lag_s)), np.zeros(len(lag_s))
    for d in np.unique(m.drive):
        sel = m.drive == d
        t = m.t_s[sel]
        if t.size < 3:
            continue
        order = np.argsort(t, kind="stable")
        t, zd = t[order], z[sel][order]
        steps = np.diff(t)
        if not (steps > 0).any():
            continue
        dt = float(np.median(steps[steps > 0]))
        idx = np.round((t - t[0]) / dt).astype(np.int64)
        keep = np.concatenate(([True], np.diff(idx) > 0))
        idx, zd = idx[keep], zd[keep]
        for j, lag in enumerate(lag_s):
            k = round(lag / dt)
            if k < 1:
                continue
            dd, _ = _variogram_sums(zd, idx, k)
            sums[j] += float(dd.sum())
            counts[j] += dd.size
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(counts > 0, sums / (4.0 * np.maximum(counts, 1)), np.nan), counts


def _nnls(a: Array, y: Array) -> tuple[Array, float]:
    """Least squares with every coefficient >= 0, for a few columns (all active sets)."""
    best: tuple[Array, float] = (np.zeros(a.shape[1]), float(y @ y))
    for r in range(1, a.shape[1] + 1):
        for cols in itertools.combinations(range(a.shape[1]), r):
            c = np.linalg.lstsq(a[:, cols], y, rcond=None)[0]
            if (c < 0).any():
                continue
            x = np.zeros(a.shape[1])
            x[list(cols)] = c
            sse = float(((a @ x - y) ** 2).sum())
            if sse < best[1]:
                best = (x, sse)
    return best


def _fit_nugget_exponential(lag_s: Array, gamma: Array) -> tuple[float, float, float, float]:
    """``W, S, τ, b`` (W, S, b >= 0) of ``γ = W + S·(1 − e^(−lag/τ)) + b·lag`` by least
    squares, τ on a grid from 0.5 s to 8 times the longest lag (linear in W, S and b for a
    given τ). ``b·lag`` is the slow part, whose variogram ``ASE²·(1 − e^(−lag/τ_slow))`` is
    ``ASE²/τ_slow·lag`` at lags far below its correlation time."""
    best = (math.inf, 0.0, 0.0, 0.0, 0.0)
    for tau in np.geomspace(0.5, 8.0 * float(lag_s.max()), 120):
        a = np.column_stack([np.ones_like(lag_s), 1.0 - np.exp(-lag_s / tau), lag_s])
        x, sse = _nnls(a, gamma)
        if sse < best[0]:
            best = (sse, float(x[0]), float(x[1]), float(tau), float(x[2]))
    return best[1], best[2], best[3], best[4]


def moving_white(m: Matched) -> MovingWhite | None:
    """The white part the estimator needs for a MOVING receiver, from drives against their
    reference (None with fewer than 50 pairs of fixes one epoch apart).

    The estimator models the fix error as white noise (re_m) plus ONE slow Gauss-Markov state
    (ase_m and the LCE, correlation_s: minutes). A static recording measures RE as the white
    part of a receiver standing still, but a moving receiver's error has a part that changes
    in tens of seconds (multipath and satellites' geometry change as it moves: the simulated
    zigzag drives show 0.8 m² per axis decorrelating in ~17 s, against a standing RE of
    0.05 m). The slow state cannot follow it; taken as nothing, the estimator reads it as the
    robot's motion (an outside audit: standing RE 0.048 m written, filtered RMS 3.18 -> 3.33
    m over 12 seeds, worse than raw GPS). So the drives' variogram over lags 1 epoch to
    :data:`MOVING_MAX_LAG_S` is fitted with a nugget W, an exponential of sill S and time
    τ, and a straight line (the slow part, which over lags far below its correlation time
    grows linearly). The white variance the estimator needs is what of W and S comes and goes
    within ``L`` = :data:`MOVING_MAX_LAG_S`, over which its slow state is near constant: the
    exponential part's variogram at ``L``, ``RE² = W + S·(1 − e^(−L/τ))``. It is continuous in
    τ: all of S for τ of a few seconds, 92 % at τ = 24 s, 74 % at 45 s, 14 % at 400 s (a slow
    part the fit put in S rather than in the line). Until a review it was ``W + S`` when τ <=
    30 s and ``W`` above: the fitted τ runs a little above the true one, so a fast part of true
    τ 28 s already fell back to the standing RE (0.0495 m written instead of ~1.0). The
    estimator puts the LCE in its slow state's variance, so the LCE cannot stand for this
    part: when it is written, the map is made again with it subtracted
    (:class:`GnssCalibration`)."""
    lags = np.arange(1.0, MOVING_MAX_LAG_S + 1.0)
    gamma, counts = _drive_variogram(m, lags)
    if not counts[0] >= 50:
        return None
    ok = counts >= 20
    w, s_, tau, _slope = _fit_nugget_exponential(lags[ok], gamma[ok])

    def white2(w_: float, s2: float, tau_: float) -> float:
        return w_ + s2 * -math.expm1(-MOVING_MAX_LAG_S / tau_)

    est = white2(w, s_, tau)
    drives = np.unique(m.drive)
    var = math.nan
    if drives.size >= 3:  # leave one drive out
        reps = []
        for d in drives:
            keep = m.drive != d
            sub = Matched(*(getattr(m, f)[keep] for f in ("t_s", "ref_east_m", "ref_north_m",
                          "err_east_m", "err_north_m", "hdop", "drive")))  # fmt: skip
            g, c = _drive_variogram(sub, lags)
            okd = c >= 20
            if okd.sum() >= 3:
                wd, sd, td, _ = _fit_nugget_exponential(lags[okd], g[okd])
                reps.append(white2(wd, sd, td))
        r = np.array(reps)
        if r.size >= 3:
            var = (r.size - 1) / r.size * float(((r - r.mean()) ** 2).sum())
    white = _root(est, var) if math.isfinite(var) else Estimate(math.sqrt(max(est, 0.0)), math.nan)
    frac = -math.expm1(-MOVING_MAX_LAG_S / tau)
    return MovingWhite(w, s_, tau, frac, white, int(counts[0]), MOVING_MAX_LAG_S)


def _mean_se(z2: Array, groups: npt.NDArray[np.int64]) -> tuple[float, float, int, str]:
    """Mean of z² with its SE: cluster-robust over groups when there are 2 or more, else
    the naive SE over the values; (mean, SE, groups, kind)."""
    n = z2.size
    mean = float(z2.mean())
    ug, inv = np.unique(groups, return_inverse=True)
    g = ug.size
    if g >= 2:
        s = np.bincount(inv, weights=z2 - mean)
        return mean, math.sqrt(g / (g - 1) * float(s @ s)) / n, g, "visits"
    se = math.sqrt(float(np.var(z2, ddof=1)) / n) if n > 1 else math.inf
    return mean, se, g, "fixes"


def lce_map(
    matched: Matched,
    *,
    re_m: float,
    ase_m: float,
    origin: tuple[float, float],
    cell_m: float = 10.0,
    min_fixes: int = 10,
    min_visits: int = 2,
    visit_gap_s: float = 30.0,
    unmatched: int = 0,
    hdop_known: bool = True,
    sources: tuple[str, ...] = (),
) -> LceMap:
    """The LCE map from matched fixes (module docstring). ``re_m``, ``ase_m``: the static
    calibration's (m per axis at HDOP 1); ``origin`` (lat, lon deg) the plane of ``matched``."""
    if not (cell_m > 0 and math.isfinite(cell_m)):
        raise ConfigError(f"cell_m must be > 0 m, got {cell_m!r}")
    if len(matched) == 0:
        raise ConfigError("drive: no fix could be matched with the reference (times, clocks?)")
    base = re_m * re_m + ase_m * ase_m
    z2 = (matched.err_east_m**2 + matched.err_north_m**2) / (2.0 * matched.hdop**2)
    ie = np.floor(matched.ref_east_m / cell_m).astype(np.int64)
    jn = np.floor(matched.ref_north_m / cell_m).astype(np.int64)
    order = np.lexsort((matched.t_s, matched.drive, jn, ie))
    ie, jn, z2s = ie[order], jn[order], z2[order]
    ts, dr = matched.t_s[order], matched.drive[order]
    key_change = np.concatenate(([True], (np.diff(ie) != 0) | (np.diff(jn) != 0)))
    starts = np.flatnonzero(key_change)
    ends = np.concatenate((starts[1:], [ie.size]))
    cells = []
    for a, b in zip(starts, ends, strict=True):
        new_visit = np.concatenate(
            ([True], (np.diff(ts[a:b]) > visit_gap_s) | (np.diff(dr[a:b]) != 0))
        )
        visit = np.cumsum(new_visit)
        mean, se, visits, kind = _mean_se(z2s[a:b], visit)
        lce = _root(mean - base, se * se)
        n = int(b - a)
        cells.append(
            Cell(int(ie[a]), int(jn[a]), lce.value, lce.se, n, visits, math.sqrt(mean),
                 n >= min_fixes and visits >= min_visits, kind)
        )  # fmt: skip
    # pooled over everything: visits = (drive, cell, pass) clusters
    cluster = np.zeros(ie.size, np.int64)
    for k, (a, b) in enumerate(zip(starts, ends, strict=True)):
        gaps = np.concatenate(([True], (np.diff(ts[a:b]) > visit_gap_s) | (np.diff(dr[a:b]) != 0)))
        cluster[a:b] = k * (b - a + 1) + np.cumsum(gaps)
    mean_all, se_all, _, _ = _mean_se(z2s, cluster)
    return LceMap(
        origin_lat_deg=origin[0],
        origin_lon_deg=origin[1],
        cell_m=float(cell_m),
        re_m=re_m,
        ase_m=ase_m,
        cells=tuple(cells),
        default=_root(mean_all - base, se_all * se_all),
        min_fixes=min_fixes,
        min_visits=min_visits,
        matched=matched,
        unmatched=unmatched,
        hdop_known=hdop_known,
        sources=sources,
        visit_gap_s=visit_gap_s,
    )


def drives_lce_map(
    drives: Sequence[tuple[FixSeries, FixSeries]],
    *,
    re_m: float,
    ase_m: float,
    origin: tuple[float, float] | None = None,
    max_gap_s: float = 1.5,
    cell_m: float = 10.0,
    min_fixes: int = 10,
    min_visits: int = 2,
    visit_gap_s: float = 30.0,
) -> LceMap:
    """:func:`lce_map` over (fixes, reference) pairs, matched by :func:`match_reference`
    (``max_gap_s``, s); ``origin`` (lat, lon deg) defaults to the first reference point
    (rounded to 1e-4 deg, so repeated calibrations share a grid); ``cell_m`` (m),
    ``min_fixes``, ``min_visits`` and ``visit_gap_s`` (s) as in :func:`lce_map`."""
    if not drives:
        raise ConfigError("drive: no recordings")
    if origin is None:
        ref0 = drives[0][1]
        origin = (round(float(ref0.lat_deg[0]), 4), round(float(ref0.lon_deg[0]), 4))
    plane = LocalTangentPlane(*origin)
    parts, missed, tracks = [], 0, []
    for fixes, ref in drives:
        m, miss = match_reference(fixes, ref, plane, max_gap_s=max_gap_s)
        _check_matched(m, miss, fixes, ref)
        parts.append(m)
        missed += miss
        x, y = plane.to_xy(ref.lat_deg, ref.lon_deg)
        tracks.append(np.column_stack([np.asarray(x, float), np.asarray(y, float)]))
    lm = lce_map(
        concat(parts),
        re_m=re_m,
        ase_m=ase_m,
        origin=origin,
        unmatched=missed,
        hdop_known=all(f.hdop_known for f, _ in drives),
        sources=tuple(f"{f.source} vs {r.source}" for f, r in drives),
        cell_m=cell_m,
        min_fixes=min_fixes,
        min_visits=min_visits,
        visit_gap_s=visit_gap_s,
    )
    return replace(lm, tracks=tuple(tracks), moving=moving_white(lm.matched))


def _check_matched(m: Matched, missed: int, fixes: FixSeries, ref: FixSeries) -> None:
    """ConfigError when a drive does not fit its reference: too few of its fixes matched
    (:data:`MIN_MATCHED_FRACTION`) or a median error no receiver shows against its own
    reference (:data:`MAX_DRIVE_MEDIAN_ERROR_M`). Either is another run's reference (or a
    clock that does not meet it), whose distances would be written as an LCE of tens of
    metres that loads and makes the estimator distrust every fix."""
    what = f"drive {fixes.source or '(fixes)'} vs reference {ref.source or '(reference)'}"
    total = len(m) + missed
    if len(m) == 0:
        raise ConfigError(
            f"{what}: no fix could be matched with the reference (times, clocks? the drive's "
            f"fixes span t_s {fixes.t_s[0]:.1f}-{fixes.t_s[-1]:.1f}, the reference's "
            f"{ref.t_s[0]:.1f}-{ref.t_s[-1]:.1f})"
        )
    if len(m) < MIN_MATCHED_FRACTION * total:
        raise ConfigError(
            f"{what}: only {len(m)} of {total} fixes ({100.0 * len(m) / total:.0f} %) fall "
            f"within the reference's times (refused below {100 * MIN_MATCHED_FRACTION:.0f} %): "
            "the reference of another run, or clocks that do not meet?"
        )
    med = float(np.median(np.hypot(m.err_east_m, m.err_north_m) / m.hdop))
    if med > MAX_DRIVE_MEDIAN_ERROR_M:
        raise ConfigError(
            f"{what}: the matched fixes lie a median {med:.1f} m (at HDOP 1) from the "
            f"reference; a receiver against its own reference shows a few metres (refused "
            f"above {MAX_DRIVE_MEDIAN_ERROR_M:g} m): the reference of another run, or clocks "
            "that do not meet?"
        )


# ------------------------------------------------------------------------------ outputs


@dataclass(frozen=True)
class GnssCalibration:
    """What one ``x6wd calibrate gnss`` run found: the static result (or given RE/ASE), the
    correlation time, and the LCE map (or none)."""

    re_m: Estimate
    ase_m: Estimate
    correlation_s: float
    static: StaticResult | None
    lce: LceMap | None
    # where the values came from when not measured by ``static`` (said in the fragment)
    re_from: str = "given, not estimated here"
    ase_from: str = "given, not estimated here"
    tau_from: str = "given, not estimated here"

    @property
    def re_resolved(self) -> bool:
        """False when the white part came out as nothing (a receiver that smooths its
        fixes, or one too quiet for the variogram to see)."""
        return round(self.re_m.value, 4) > 0.0

    def __post_init__(self) -> None:
        """With a static RE and drives whose white part is larger, the map is made again with
        that part subtracted: the estimator gets it as white noise, and the LCE is the excess
        beyond it and ASE (else the same variance would be counted twice)."""
        note = self.drives_warning
        if note is not None:
            print(f"x6wd calibrate: warning: {note}", file=sys.stderr)
        mv = self.moving
        lm = self.lce
        if mv is None or lm is None:
            return
        again = lce_map(
            lm.matched, re_m=mv.white.value, ase_m=lm.ase_m,
            origin=(lm.origin_lat_deg, lm.origin_lon_deg), cell_m=lm.cell_m,
            min_fixes=lm.min_fixes, min_visits=lm.min_visits, visit_gap_s=lm.visit_gap_s,
            unmatched=lm.unmatched, hdop_known=lm.hdop_known, sources=lm.sources,
        )  # fmt: skip
        object.__setattr__(self, "lce", replace(again, tracks=lm.tracks, moving=lm.moving))

    @property
    def moving(self) -> MovingWhite | None:
        """The drives' white part when it is larger than a MEASURED (static) RE: the one the
        estimator needs for a moving robot (:func:`moving_white`), else None."""
        mv = self.drives_white
        return mv if self.static is not None else None

    @property
    def drives_white(self) -> MovingWhite | None:
        """The drives' white part when it is larger than RE, whatever RE came from (a given
        ``--re-m`` is written as given, the fragment's comment names the drives' figure)."""
        mv = self.lce.moving if self.lce is not None else None
        if mv is None or not round(mv.white.value, 4) > round(self.re_m.value, 4):
            return None
        return mv

    @property
    def drives_warning(self) -> str | None:
        """Why the ``re_m`` written is much smaller (:data:`MOVING_WARN_RATIO`) than the drives'
        white part, when it is (a given ``--re-m`` or ``--config``), else None."""
        mv = self.lce.moving if self.lce is not None else None
        if mv is None or self.moving is not None:
            return None
        written = self.re_m_written
        if not mv.white.value > MOVING_WARN_RATIO * written:
            return None
        return (
            f"the drives' white part (moving) is {mv.white.value:.4f} m, "
            f"{mv.white.value / written:.1f} times the re_m written ({written:g} m, "
            f"{self.re_from}): on a moving robot the estimator would read the rest of that error "
            "as motion; calibrate with --static and the drives to write the drives' figure "
            "(docs/gnss_calibration.md)"
        )

    @property
    def re_m_written(self) -> float:
        """``re_m`` as written (m): the estimate, or when it is not resolved an upper bound
        (at least 0.1 mm, rounded up): the daemon needs white noise > 0. From a static
        recording the bound is sqrt(γ(1)) (:attr:`StaticResult.re_bound_m`), which holds
        whatever the split; a one-SE bound would lean on a nugget that came out negative,
        i.e. on a model the data did not fit (a ZED-F9P: 0 ± 1.0 mm, bound 3.1 mm).

        With drives whose white part (:attr:`moving`) is larger, that one: the estimator
        runs on a moving robot."""
        if self.moving is not None:
            return round(self.moving.white.value, 4)
        if self.re_resolved:
            return round(self.re_m.value, 4)
        bound = (
            self.static.re_bound_m if self.static is not None else self.re_m.value + self.re_m.se
        )
        return max(math.ceil(round(bound * 1e4, 6)) / 1e4, 0.0001)

    @property
    def standing_warning(self) -> str | None:
        """Why ``re_m`` must not go into the robot's configuration as written, when it comes
        from a static recording and no drive measured the moving white part (no drives, or
        drives too short for it: :func:`moving_white` None), else None. A standing receiver's
        white part is centimetres (u-blox filters its fixes); moving, the error has a part that
        changes in seconds which the estimator's one slow state cannot follow, so it needs that
        part as white noise: with the standing figure it reads it as motion and gets worse than
        the shipped configuration (docs/gnss_calibration.md, Experiment 3)."""
        if self.static is None or (self.lce is not None and self.lce.moving is not None):
            return None
        short = (
            " (the drives given are too short to measure it: fewer than 50 pairs of fixes one "
            "epoch apart)"
            if self.lce is not None
            else ""
        )
        return (
            "re_m is a standing receiver's white part: a moving robot needs it from --drive"
            f"{short} "
            '(docs/gnss_calibration.md, Experiment 3, "The white part of a moving receiver"); '
            "do not paste it alone into the robot's configuration: keep the robot's re_m "
            f"({GnssNoiseConfig().re_m} as shipped) until drives measure it"
        )

    @property
    def tau_bound_note(self) -> str | None:
        """Why ``correlation_s`` is written as the configuration's limit, when a static
        record's estimate is beyond it (or the slow part did not decay at all), else None."""
        tau = self.correlation_s
        if self.static is None or (math.isfinite(tau) and tau <= MAX_CORRELATION_S):
            return None
        est = f"the estimate {tau:.3g} s" if math.isfinite(tau) else "no decay seen"
        return (
            f"{est}: the record ({self.static.duration_s:.0f} s) is too short to measure a "
            f"correlation time beyond {MAX_CORRELATION_S:g} s; written as that bound (the slow "
            "part taken as near constant)"
        )

    def table(self) -> dict[str, object]:
        """The ``[gnss_noise]`` keys and values."""
        tau = self.correlation_s
        t: dict[str, object] = {
            "re_m": self.re_m_written,
            "ase_m": round(self.ase_m.value, 4),
            "correlation_s": round(min(tau, MAX_CORRELATION_S), 1)
            if math.isfinite(tau)
            else MAX_CORRELATION_S,
        }
        if self.lce is not None:
            lm = self.lce
            t |= {
                "lce_origin_lat_deg": lm.origin_lat_deg,
                "lce_origin_lon_deg": lm.origin_lon_deg,
                "lce_cell_m": lm.cell_m,
                "lce_default_m": round(lm.default.value, 3),
                "lce_cells": [
                    [c.east_index, c.north_index, round(c.lce_m, 3)] for c in lm.mapped()
                ],
            }
        return t

    def config(self) -> GnssNoiseConfig:
        """The ``[gnss_noise]`` section (range-checked: ConfigError if an estimate is absurd)."""
        return build(GnssNoiseConfig, self.table(), "gnss_noise.")

    def toml(self, header: str = "") -> str:
        """A TOML fragment with the ``[gnss_noise]`` section; standard errors, counts and the
        marked cells in comments."""
        self.config()  # refuse to write what the daemon would refuse to load
        t = self.table()
        lines = [f"# {line}" for line in header.splitlines()]
        st = self.static
        if st is not None:
            lines += [
                f"# static: {st.fixes} fixes over {st.duration_s:.0f} s, epoch {st.epoch_s:g} s, "
                f"mean HDOP {st.mean_hdop:.2f}{'' if st.hdop_known else ' (no HDOP: taken as 1)'}",
                f"# mean error east {st.bias_east_m:+.3f} m, north {st.bias_north_m:+.3f} m; "
                f"per axis at HDOP 1: mean square {st.mean_square_m2:.4f} m², variogram "
                f"lag 1 {st.gamma1_m2:.4g} m², lag 2 {st.gamma2_m2:.4g} m²",
            ]
            if st.duplicates:
                lines.append(
                    f"# {st.duplicates} fixes sharing an epoch with the fix before (a repeated "
                    "time stamp) left out"
                )
            src = ase_src = "static recording"
            tau_note = "of the slow part; " + (
                f"not measured: {self.tau_bound_note}" if self.tau_bound_note else "rough"
            )
        else:
            src, ase_src = self.re_from, self.ase_from
            tau_note = f"of the slow part ({self.tau_from})"
        mv = self.moving
        dmv = self.lce.moving if self.lce is not None else None
        if dmv is not None:
            lines.append(
                f"# the drives (moving): their variogram over 1-{dmv.max_lag_s:g} s fits nugget "
                f"{dmv.nugget_m2:.3f} m² + {dmv.sill_m2:.3f} m² decorrelating in "
                f"{dmv.tau_s:.0f} s ({dmv.pairs} pairs one epoch apart); what of it comes and "
                f"goes within {dmv.max_lag_s:g} s (W + {100 * dmv.fast_fraction:.0f} % of S), "
                "which the estimator's slow state cannot follow: white part "
                f"{dmv.white.value:.4f} m"
                + ("" if math.isnan(dmv.white.se) else f" ± {dmv.white.se:.4f}")
            )
        if mv is not None:
            lines.append(
                "# re_m from the drives (moving): the LCE map below is the excess beyond it and "
                f"ASE; the static white part (RE {self.re_m.value:.4f} ± {self.re_m.se:.4f} m, "
                f"{src}) is smaller, and taken alone makes the estimator read that error as motion"
            )
        dw = self.drives_white
        if mv is None and dw is not None:
            lines.append(
                f"# the drives' white part (moving) is {dw.white.value:.4f} m, larger than this "
                f"re_m ({src}): the estimator on a moving robot needs it (docs/gnss_calibration"
                ".md); measured with --static, the drives' figure is written"
            )
        elif dmv is not None and mv is None:
            lines.append(
                f"# the drives' white part is not larger than this re_m ({src}): re_m as below"
            )
        se_mv = (
            "no SE: fewer than 3 drives"
            if mv is not None and not math.isfinite(mv.white.se)
            else (f"± {mv.white.se:.4f} over drives" if mv is not None else "")
        )
        lines += [
            "# seed 003: sigma per axis = HDOP * sqrt(re_m^2 + ase_m^2 + LCE^2)",
            "[gnss_noise]",
        ]
        if self.standing_warning is not None:
            lines.append(f"# WARNING: {self.standing_warning}")
        lines += [
            f"re_m = {t['re_m']}  # {se_mv} (drives: the white part of a moving receiver)"
            if mv is not None
            else f"re_m = {t['re_m']}  # ± {self.re_m.se:.4f} ({src}: the white part)"
            if self.re_resolved
            else f"re_m = {t['re_m']}  # not resolved: RE = 0 ± {self.re_m.se:.4f} ({src}: the "
            "white part); written: its upper bound"
            + (" sqrt(variogram lag 1)" if st is not None else " (estimate + SE)"),
            f"ase_m = {t['ase_m']}  # ± {self.ase_m.se:.4f} ({ase_src}: the slow part)",
            f"correlation_s = {t['correlation_s']}  # {tau_note}",
        ]
        lm = self.lce
        if lm is not None:
            s = lm.summary()
            lines += [
                f"# LCE map: {len(lm.matched)} fixes matched ({lm.unmatched} without reference)"
                f", {int(s['cells'])} cells visited, {int(s['mapped'])} with >= {lm.min_fixes} "
                f"fixes and >= {lm.min_visits} visits; {lm.spread_text()}"
                + ("" if lm.hdop_known else "; no HDOP in the drive: taken as 1"),
                f"lce_origin_lat_deg = {t['lce_origin_lat_deg']}",
                f"lce_origin_lon_deg = {t['lce_origin_lon_deg']}",
                f"lce_cell_m = {t['lce_cell_m']}",
                f"lce_default_m = {t['lce_default_m']}  # ± {lm.default.se:.3f}: pooled over "
                "every fix; for cells without a value",
                "# [east index, north index, LCE m]: cell = floor(east / lce_cell_m), "
                "floor(north / lce_cell_m)",
                "lce_cells = [",
            ]
            lines += [
                f"  [{c.east_index}, {c.north_index}, {round(c.lce_m, 3)}],  # ± {c.se_m:.3f}, "
                f"{c.fixes} fixes, {c.visits} visits"
                + ("" if c.se_over == "visits" else " (SE over fixes: too small if correlated)")
                for c in lm.mapped()
            ]
            lines.append("]")
            marked = [c for c in lm.cells if not c.enough]
            if marked:
                lines.append(
                    f"# {len(marked)} cells with too little data (left to lce_default_m): "
                    + ", ".join(f"[{c.east_index}, {c.north_index}]" for c in marked[:40])
                    + (" ..." if len(marked) > 40 else "")
                )
        return "\n".join(lines) + "\n"


def write_map_csv(lm: LceMap, path: str | Path) -> None:
    """Every visited cell: indices, centre (m), LCE ± SE, counts, RMS, marked or not."""
    with open(path, "w", newline="", encoding="utf-8") as f:
        w = csv.writer(f)
        w.writerow(["east_index", "north_index", "east_m", "north_m", "lce_m", "se_m",
                    "fixes", "visits", "rms_m", "enough", "se_over"])  # fmt: skip
        for c in lm.cells:
            w.writerow([
                c.east_index, c.north_index, f"{(c.east_index + 0.5) * lm.cell_m:.2f}",
                f"{(c.north_index + 0.5) * lm.cell_m:.2f}", f"{c.lce_m:.4f}", f"{c.se_m:.4f}",
                c.fixes, c.visits, f"{c.rms_m:.4f}", int(c.enough), c.se_over,
            ])  # fmt: skip


def plot_lce_map(lm: LceMap, path: str | Path, title: str = "") -> None:
    """PNG of the map: mapped cells coloured by LCE (m), marked cells hatched grey, the
    reference track of the drives on top (Agg, no display)."""
    import matplotlib
    from matplotlib.cm import ScalarMappable
    from matplotlib.colors import Normalize
    from matplotlib.figure import Figure
    from matplotlib.patches import Rectangle

    pts = np.vstack([*lm.tracks, np.column_stack([lm.matched.ref_east_m, lm.matched.ref_north_m])])
    span = np.ptp(pts, axis=0) + 2 * lm.cell_m
    aspect = float(np.clip(span[1] / max(span[0], 1e-9), 0.5, 2.5))
    fig = Figure(figsize=(5.5 + 3.5 / aspect, 3.5 + 3.5 * aspect), dpi=100)
    ax = fig.subplots()
    mapped = lm.mapped()
    vmax = max([c.lce_m for c in mapped], default=1.0)
    vmax = float(np.percentile([c.lce_m for c in mapped], 95)) if len(mapped) > 5 else vmax
    norm = Normalize(0.0, max(vmax, 1e-3))
    cm = matplotlib.colormaps["viridis"]
    s = lm.cell_m
    for c in lm.cells:
        x0, y0 = c.east_index * s, c.north_index * s
        if c.enough:
            ax.add_patch(Rectangle((x0, y0), s, s, facecolor=cm(norm(c.lce_m)), edgecolor="none"))
        else:
            ax.add_patch(Rectangle((x0, y0), s, s, facecolor="0.85", edgecolor="0.6",
                                   hatch="//", linewidth=0.3))  # fmt: skip
    for k, tr in enumerate(lm.tracks):
        ax.plot(tr[:, 0], tr[:, 1], "-", color="crimson", lw=0.6,
                label="reference track" if k == 0 else None)  # fmt: skip
    m = lm.matched
    ax.plot(m.ref_east_m, m.ref_north_m, ".", color="black", ms=1.5,
            label="fixes (at their reference position)")  # fmt: skip
    fig.colorbar(ScalarMappable(norm=norm, cmap=cm), ax=ax, label="LCE (m, per axis at HDOP 1)",
                 extend="max")  # fmt: skip
    ax.set_aspect("equal")
    ax.autoscale_view()
    ax.set_xlabel(f"east (m) of {lm.origin_lat_deg:.5f}, {lm.origin_lon_deg:.5f}")
    ax.set_ylabel("north (m)")
    summ = lm.summary()
    ax.set_title(
        (title + "\n" if title else "")
        + f"LCE map, {lm.cell_m:g} m cells: {int(summ['mapped'])} mapped (hatched: too little "
        f"data), {lm.spread_text()}",
        fontsize=9,
    )
    ax.legend(loc="best", fontsize=8)
    fig.savefig(path)
