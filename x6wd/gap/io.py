"""Readers for the gap tool: any log -> a :class:`Track` of positions -> a PositionSeries of
errors against a truth (a fixed point, a truth track, or the log's own mean as a last resort).

Formats, chosen by content then suffix:
- x6wd recordings (JSON lines): ``fix`` records, else their ``nmea`` lines decoded;
- plain NMEA logs from any receiver (decoded by :class:`drivers.gps_nmea.GpsDecoder`);
- CSV with a header naming time, lat, lon[, alt] (case-insensitive; ``latitude``, ``msl`` ...
  accepted) or headerless ``time,lat,lon[,alt]``;
- RTKLIB ``.pos`` solutions (GPST date/time, lat, lon, height, Q, ns).
"""

from __future__ import annotations

import contextlib
import csv
import math
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path

import numpy as np

from sim_backend.effects import PositionSeries, metres_per_degree
from x6wd.core.errors import ConfigError, DeviceUnavailable, ParseError


@dataclass(frozen=True)
class Track:
    """Reported positions of one log. ``t_s`` seconds (UTC/GPST epoch seconds when the log
    has dates, else the log's own clock); ``alt_m`` NaN where unknown; ``valid`` False on
    no-fix epochs; ``nsats`` satellites used (-1 unknown); speed/course NaN where unknown."""

    t_s: np.ndarray
    lat_deg: np.ndarray
    lon_deg: np.ndarray
    alt_m: np.ndarray
    valid: np.ndarray
    nsats: np.ndarray
    speed_mps: np.ndarray
    course_deg: np.ndarray
    source: str = ""

    def __len__(self) -> int:
        return int(self.t_s.shape[0])


def _track(rows: list[tuple[float, ...]], source: str) -> Track:
    """Rows (t, lat, lon, alt, valid, nsats, speed, course) -> Track sorted by time, duplicates
    of a time stamp dropped (first kept)."""
    if not rows:
        raise ParseError(f"{source}: no position epochs found")
    a = np.array(rows, dtype=float)
    order = np.argsort(a[:, 0], kind="stable")
    a = a[order]
    keep = np.concatenate(([True], np.diff(a[:, 0]) > 0))
    a = a[keep]
    valid = (a[:, 4] > 0) & np.isfinite(a[:, 1]) & np.isfinite(a[:, 2])
    return Track(
        t_s=a[:, 0],
        lat_deg=a[:, 1],
        lon_deg=a[:, 2],
        alt_m=a[:, 3],
        valid=valid,
        nsats=a[:, 5],
        speed_mps=a[:, 6],
        course_deg=a[:, 7],
        source=source,
    )


def fill_missing_epochs(track: Track) -> Track:
    """Insert no-fix epochs where a regularly sampled log skips epochs (RTKLIB and CSV logs
    simply omit unsolved epochs; the gap tool must see them as outages). Logs whose times are
    not regular (e.g. NMEA without dates) are returned unchanged."""
    t = track.t_s
    if t.size < 3:
        return track
    d = np.diff(t)
    dt = float(np.min(d)) if d.size else 0.0
    if dt <= 0 or np.mean(np.abs(d / dt - np.round(d / dt)) < 0.1) < 0.9:
        return track
    k = np.round((t - t[0]) / dt).astype(int)
    if k[-1] > 20 * t.size:  # a huge hole is not a run of missed epochs
        return track
    n = int(k[-1]) + 1
    first = np.concatenate(([True], np.diff(k) > 0))
    k, rows = k[first], np.flatnonzero(first)

    def spread(a: np.ndarray, fill: float) -> np.ndarray:
        out = np.full(n, fill, dtype=float)
        out[k] = a[rows]
        return out

    valid = np.zeros(n, dtype=bool)
    valid[k] = track.valid[rows]
    return Track(
        t_s=t[0] + np.arange(n) * dt,
        lat_deg=spread(track.lat_deg, math.nan),
        lon_deg=spread(track.lon_deg, math.nan),
        alt_m=spread(track.alt_m, math.nan),
        valid=valid,
        nsats=spread(track.nsats, 0.0),
        speed_mps=spread(track.speed_mps, math.nan),
        course_deg=spread(track.course_deg, math.nan),
        source=track.source,
    )


def read_track(path: str | Path) -> Track:
    """Read any supported log (see module doc) and mark skipped epochs of a regularly
    sampled log as no-fix. Raises DeviceUnavailable for a missing file, ParseError when
    nothing usable is in it."""
    return fill_missing_epochs(_read_any(path))


def _read_any(path: str | Path) -> Track:
    p = Path(path)
    try:
        raw = p.read_bytes()
    except OSError as exc:
        raise DeviceUnavailable(f"cannot read {p}: {exc}") from exc
    head = raw.lstrip()[:1]
    if head == b"{":
        return _read_recording(p)
    text = raw.decode("utf-8", errors="replace")
    if p.suffix.lower() == ".pos" or text.lstrip().startswith("%"):
        return _read_pos(text, str(p))
    if b"$GP" in raw[:4096] or b"$GN" in raw[:4096] or head == b"$":
        return _read_nmea(raw, str(p))
    return _read_csv(text, str(p))


def _fix_row(fix: object) -> tuple[float, ...]:
    g = fix  # GpsFix or a dict with the same fields
    get = g.get if isinstance(g, dict) else (lambda k, d=None: getattr(g, k, d))
    utc = get("utc")
    t = get("t_s")
    if isinstance(utc, datetime):
        t = utc.replace(tzinfo=UTC).timestamp() if utc.tzinfo is None else utc.timestamp()
    elif isinstance(utc, str) and utc:
        with contextlib.suppress(ValueError):
            t = datetime.fromisoformat(utc.replace("Z", "+00:00")).timestamp()
    lat, lon, alt = get("lat_deg"), get("lon_deg"), get("alt_m")
    valid = bool(get("valid", False)) and lat is not None and lon is not None
    sats = get("sats_used")
    speed, course = get("speed_mps"), get("course_deg")
    if t is None:
        raise ParseError("fix without a time")
    return (
        float(t),
        float(lat) if lat is not None else math.nan,
        float(lon) if lon is not None else math.nan,
        float(alt) if alt is not None else math.nan,
        1.0 if valid else 0.0,
        float(sats) if sats is not None else -1.0,
        float(speed) if speed is not None else math.nan,
        float(course) if course is not None else math.nan,
    )


def _decode_nmea_lines(lines: list[tuple[float, bytes]], source: str) -> Track:
    from drivers.gps_nmea import GpsDecoder
    from x6wd.core.records import GpsFix

    dec = GpsDecoder(emit_sentences=False)
    rows: list[tuple[float, ...]] = []
    for t_s, chunk in lines:
        rows.extend(_fix_row(r) for r in dec.feed(chunk, t_s) if isinstance(r, GpsFix))
    rows.extend(_fix_row(r) for r in dec.flush() if isinstance(r, GpsFix))
    return _track(rows, source)


def _read_nmea(raw: bytes, source: str) -> Track:
    # A plain log has no receive times; the decoder's UTC (when present) supplies them, and
    # the byte position keeps stream order otherwise.
    return _decode_nmea_lines(
        [(float(i), line + b"\n") for i, line in enumerate(raw.splitlines())], source
    )


def _read_recording(p: Path) -> Track:
    from x6wd.core.recorder import read_recording

    rows: list[tuple[float, ...]] = []
    nmea: list[tuple[float, bytes]] = []
    for rec in read_recording(p):
        if rec.type == "fix":
            data = dict(rec.data)
            data.setdefault("t_s", rec.t_mono)
            rows.append(_fix_row(data))
        elif rec.type == "nmea":
            text = rec.data.get("text") or rec.data.get("sentence") or rec.data.get("line") or ""
            nmea.append((rec.t_mono, str(text).encode("ascii", "replace") + b"\r\n"))
    if rows:
        return _track(rows, str(p))
    if nmea:
        return _decode_nmea_lines(nmea, str(p))
    raise ParseError(f"{p}: recording has no fix or nmea records")


_CSV_NAMES = {
    "t": ("time", "t", "t_s", "timestamp", "utc", "epoch"),
    "lat": ("lat", "latitude", "lat_deg"),
    "lon": ("lon", "longitude", "lon_deg", "lng"),
    "alt": ("alt", "alt_m", "msl", "altitude", "height", "h"),
    "valid": ("valid", "fix"),
    "nsats": ("nsats", "sats", "sats_used", "ns"),
}


def _read_csv(text: str, source: str) -> Track:
    reader = csv.reader(
        line for line in text.splitlines() if line.strip() and not line.startswith("#")
    )
    table = [[c.strip().strip('"') for c in row] for row in reader]
    if not table:
        raise ParseError(f"{source}: empty CSV")
    header = [c.lower() for c in table[0]]

    def col(key: str) -> int | None:
        for name in _CSV_NAMES[key]:
            if name in header:
                return header.index(name)
        return None

    has_header = col("lat") is not None and col("lon") is not None
    if has_header:
        ci = {k: col(k) for k in _CSV_NAMES}
        body = table[1:]
        if ci["t"] is None:
            raise ParseError(f"{source}: CSV header has no time column (one of {_CSV_NAMES['t']})")
    else:
        ci = {
            "t": 0,
            "lat": 1,
            "lon": 2,
            "alt": 3 if len(table[0]) > 3 else None,
            "valid": None,
            "nsats": None,
        }
        body = table
    rows: list[tuple[float, ...]] = []
    for lineno, row in enumerate(body, 2 if has_header else 1):
        try:

            def get(key: str, default: float = math.nan, row: list[str] = row) -> float:
                i = ci[key]
                return float(row[i]) if i is not None and i < len(row) and row[i] != "" else default

            t = _parse_time(row[ci["t"]])  # type: ignore[index]
            lat, lon = get("lat"), get("lon")
            rows.append(
                (t, lat, lon, get("alt"), get("valid", 1.0), get("nsats", -1.0), math.nan, math.nan)
            )
        except (ValueError, IndexError) as exc:
            raise ParseError(f"{source}:{lineno}: bad CSV row {row!r}: {exc}") from exc
    return _track(rows, source)


def _parse_time(s: str) -> float:
    try:
        return float(s)
    except ValueError:
        return datetime.fromisoformat(s.replace("Z", "+00:00")).timestamp()


def _read_pos(text: str, source: str) -> Track:
    rows: list[tuple[float, ...]] = []
    for lineno, line in enumerate(text.splitlines(), 1):
        if not line.strip() or line.startswith("%"):
            continue
        f = line.split()
        try:
            t = (
                datetime.strptime(f[0] + " " + f[1], "%Y/%m/%d %H:%M:%S.%f")
                .replace(tzinfo=UTC)
                .timestamp()
            )
            lat, lon, h, q, ns = float(f[2]), float(f[3]), float(f[4]), int(f[5]), int(f[6])
        except (ValueError, IndexError) as exc:
            raise ParseError(f"{source}:{lineno}: not an RTKLIB .pos line: {exc}") from exc
        speed = course = math.nan
        if len(f) >= 17:  # velocity columns vn, ve (m/s) present
            vn, ve = float(f[15]), float(f[16])
            speed, course = math.hypot(vn, ve), math.degrees(math.atan2(ve, vn)) % 360.0
        rows.append((t, lat, lon, h, 1.0 if q > 0 else 0.0, float(ns), speed, course))
    return _track(rows, source)


def parse_truth(text: str) -> tuple[float, float, float]:
    """``LAT,LON[,ALT]`` (degrees, metres) -> (lat, lon, alt or NaN); ConfigError if malformed."""
    parts = [p.strip() for p in text.split(",")]
    try:
        vals = [float(p) for p in parts]
    except ValueError:
        raise ConfigError(f"--truth {text!r}: expected LAT,LON[,ALT] in degrees/metres") from None
    if len(vals) not in (2, 3) or not (-90 <= vals[0] <= 90 and -180 <= vals[1] <= 180):
        raise ConfigError(f"--truth {text!r}: expected LAT,LON[,ALT] with |LAT|<=90, |LON|<=180")
    return vals[0], vals[1], vals[2] if len(vals) == 3 else math.nan


def errors_vs_point(
    track: Track, lat_deg: float, lon_deg: float, alt_m: float = math.nan
) -> PositionSeries:
    """Errors (m) of a static log against a surveyed point; the frame origin is the point.
    Up error is NaN-free: zero when either altitude is unknown."""
    e_per_deg, n_per_deg = metres_per_degree(lat_deg)
    east = (track.lon_deg - lon_deg) * e_per_deg
    north = (track.lat_deg - lat_deg) * n_per_deg
    up = track.alt_m - alt_m
    return _series(track, east, north, up, lat_deg, lon_deg, None, None)


def _series(
    track: Track,
    east: np.ndarray,
    north: np.ndarray,
    up: np.ndarray,
    lat0: float,
    lon0: float,
    speed: np.ndarray | None,
    course: np.ndarray | None,
) -> PositionSeries:
    valid = track.valid & np.isfinite(east) & np.isfinite(north)
    up = np.where(np.isfinite(up), up, 0.0)
    nsats = track.nsats if np.all(track.nsats >= 0) else None
    return PositionSeries(
        t_s=track.t_s - track.t_s[0],
        east_m=np.where(valid, east, 0.0),
        north_m=np.where(valid, north, 0.0),
        up_m=np.where(valid, up, 0.0),
        valid=valid,
        origin_lat_deg=lat0,
        origin_lon_deg=lon0,
        speed_mps=speed,
        course_deg=course,
        nsats=nsats,
    )


def errors_vs_track(track: Track, truth: Track, max_gap_s: float = 1.5) -> PositionSeries:
    """Errors (m) of a log against a truth track matched in time (linear interpolation of the
    truth; epochs farther than ``max_gap_s`` from a valid truth sample are dropped). If the two
    time spans do not overlap, both are taken from their own start (a simulated log).
    The series carries the truth's speed/course (from its positions) and its origin is the
    truth at the first kept epoch, so effect layers see the true motion."""
    tv = truth.valid
    tt, tlat, tlon, talt = truth.t_s[tv], truth.lat_deg[tv], truth.lon_deg[tv], truth.alt_m[tv]
    if tt.size < 2:
        raise ParseError(f"{truth.source}: truth track has fewer than 2 valid epochs")
    t = track.t_s
    if t[-1] < tt[0] or t[0] > tt[-1]:
        t = t - t[0] + tt[0]
    idx = np.clip(np.searchsorted(tt, t), 1, tt.size - 1)
    near = np.minimum(np.abs(tt[idx] - t), np.abs(tt[idx - 1] - t)) <= max_gap_s
    inside = (t >= tt[0]) & (t <= tt[-1]) & near
    if not np.any(inside):
        raise ParseError(f"{track.source}: no epoch matches the truth track {truth.source} in time")
    sel = np.flatnonzero(inside)
    t = t[sel]
    lat_t, lon_t, alt_t = np.interp(t, tt, tlat), np.interp(t, tt, tlon), np.interp(t, tt, talt)
    lat0, lon0 = float(lat_t[0]), float(lon_t[0])
    e_per_deg, n_per_deg = metres_per_degree(lat0)
    sub = Track(
        t_s=t,
        lat_deg=track.lat_deg[sel],
        lon_deg=track.lon_deg[sel],
        alt_m=track.alt_m[sel],
        valid=track.valid[sel],
        nsats=track.nsats[sel],
        speed_mps=track.speed_mps[sel],
        course_deg=track.course_deg[sel],
        source=track.source,
    )
    te, tn = (lon_t - lon0) * e_per_deg, (lat_t - lat0) * n_per_deg
    east = (sub.lon_deg - lon0) * e_per_deg - te
    north = (sub.lat_deg - lat0) * n_per_deg - tn
    # truth velocity from its own positions (central differences)
    if t.size > 1:
        ve, vn = np.gradient(te, t), np.gradient(tn, t)
    else:
        ve, vn = np.zeros(1), np.zeros(1)
    speed = np.hypot(ve, vn)
    course = np.degrees(np.arctan2(ve, vn)) % 360.0
    return _series(sub, east, north, sub.alt_m - alt_t, lat0, lon0, speed, course)


def errors_vs_mean(track: Track) -> PositionSeries:
    """Errors of a static log against its own mean position (no truth: a bias is invisible)."""
    v = track.valid
    if not np.any(v):
        raise ParseError(f"{track.source}: no valid fix")
    alt = track.alt_m[v]
    alt0 = float(np.nanmean(alt)) if np.any(np.isfinite(alt)) else math.nan
    return errors_vs_point(
        track, float(np.mean(track.lat_deg[v])), float(np.mean(track.lon_deg[v])), alt0
    )


def write_csv(path: str | Path, track: Track) -> None:
    """Write a Track as CSV ``time,lat,lon,alt,valid,nsats`` (readable by :func:`read_track`)."""
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["time", "lat", "lon", "alt", "valid", "nsats"])
        for i in range(len(track)):
            w.writerow(
                [
                    f"{track.t_s[i]:.3f}",
                    f"{track.lat_deg[i]:.10f}",
                    f"{track.lon_deg[i]:.10f}",
                    "" if not math.isfinite(track.alt_m[i]) else f"{track.alt_m[i]:.4f}",
                    int(bool(track.valid[i])),
                    int(track.nsats[i]),
                ]
            )


def series_to_track(series: PositionSeries, alt0_m: float = 0.0) -> Track:
    """Absolute positions of an error series (origin + implied truth + error) as a Track."""
    from sim_backend.effects import truth_track_m

    e_per_deg, n_per_deg = metres_per_degree(series.origin_lat_deg)
    te, tn = truth_track_m(series)
    n = len(series)
    return Track(
        t_s=np.asarray(series.t_s, dtype=float),
        lat_deg=series.origin_lat_deg + (tn + series.north_m) / n_per_deg,
        lon_deg=series.origin_lon_deg + (te + series.east_m) / e_per_deg,
        alt_m=alt0_m + np.asarray(series.up_m, dtype=float),
        valid=np.asarray(series.valid, dtype=bool),
        nsats=np.full(n, -1.0) if series.nsats is None else np.asarray(series.nsats, dtype=float),
        speed_mps=np.full(n, math.nan),
        course_deg=np.full(n, math.nan),
    )
