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
    table = np.array(rows, dtype=float)
    order = np.argsort(table[:, 0], kind="stable")
    table = table[order]
    keep = np.concatenate(([True], np.diff(table[:, 0]) > 0))
    table = table[keep]
    valid = (table[:, 4] > 0) & np.isfinite(table[:, 1]) & np.isfinite(table[:, 2])
    return Track(
        t_s=table[:, 0],
        lat_deg=table[:, 1],
        lon_deg=table[:, 2],
        alt_m=table[:, 3],
        valid=valid,
        nsats=table[:, 5],
        speed_mps=table[:, 6],
        course_deg=table[:, 7],
        source=source,
    )


def fill_missing_epochs(track: Track) -> Track:
    """Insert no-fix epochs where a regularly sampled log skips epochs (RTKLIB and CSV logs
    simply omit unsolved epochs; the gap tool must see them as outages). Logs whose times are
    not regular (e.g. NMEA without dates) are returned unchanged."""
    t_s = track.t_s
    if t_s.size < 3:
        return track
    steps_s = np.diff(t_s)
    dt_s = float(np.min(steps_s)) if steps_s.size else 0.0
    if dt_s <= 0 or np.mean(np.abs(steps_s / dt_s - np.round(steps_s / dt_s)) < 0.1) < 0.9:
        return track
    slot = np.round((t_s - t_s[0]) / dt_s).astype(int)
    if slot[-1] > 20 * t_s.size:  # a huge hole is not a run of missed epochs
        return track
    n_slots = int(slot[-1]) + 1
    first = np.concatenate(([True], np.diff(slot) > 0))
    slot, rows = slot[first], np.flatnonzero(first)

    def spread(a: np.ndarray, fill: float) -> np.ndarray:
        out = np.full(n_slots, fill, dtype=float)
        out[slot] = a[rows]
        return out

    valid = np.zeros(n_slots, dtype=bool)
    valid[slot] = track.valid[rows]
    return Track(
        t_s=t_s[0] + np.arange(n_slots) * dt_s,
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
    log_path = Path(path)
    try:
        raw = log_path.read_bytes()
    except OSError as exc:
        raise DeviceUnavailable(f"cannot read {log_path}: {exc}") from exc
    first_byte = raw.lstrip()[:1]
    if first_byte == b"{":
        return _read_recording(log_path)
    text = raw.decode("utf-8", errors="replace")
    if log_path.suffix.lower() == ".pos" or text.lstrip().startswith("%"):
        return _read_pos(text, str(log_path))
    if b"$GP" in raw[:4096] or b"$GN" in raw[:4096] or first_byte == b"$":
        return _read_nmea(raw, str(log_path))
    return _read_csv(text, str(log_path))


def _fix_row(fix: object) -> tuple[float, ...]:
    """(t s, lat deg, lon deg, alt m, valid 0/1, satellites used (-1 unknown), speed m/s,
    course deg) of a GpsFix or a dict with the same fields."""
    get = fix.get if isinstance(fix, dict) else (lambda k, d=None: getattr(fix, k, d))
    utc = get("utc")
    t_s = get("t_s")
    if isinstance(utc, datetime):
        t_s = utc.replace(tzinfo=UTC).timestamp() if utc.tzinfo is None else utc.timestamp()
    elif isinstance(utc, str) and utc:
        with contextlib.suppress(ValueError):
            t_s = datetime.fromisoformat(utc.replace("Z", "+00:00")).timestamp()
    lat_deg, lon_deg, alt_m = get("lat_deg"), get("lon_deg"), get("alt_m")
    valid = bool(get("valid", False)) and lat_deg is not None and lon_deg is not None
    sats_used = get("sats_used")
    speed_mps, course_deg = get("speed_mps"), get("course_deg")
    if t_s is None:
        raise ParseError("fix without a time")
    return (
        float(t_s),
        float(lat_deg) if lat_deg is not None else math.nan,
        float(lon_deg) if lon_deg is not None else math.nan,
        float(alt_m) if alt_m is not None else math.nan,
        1.0 if valid else 0.0,
        float(sats_used) if sats_used is not None else -1.0,
        float(speed_mps) if speed_mps is not None else math.nan,
        float(course_deg) if course_deg is not None else math.nan,
    )


def _decode_nmea_lines(lines: list[tuple[float, bytes]], source: str) -> Track:
    from drivers.gps_nmea import GpsDecoder
    from x6wd.core.records import GpsFix

    decoder = GpsDecoder(emit_sentences=False)
    rows: list[tuple[float, ...]] = []
    for t_s, chunk in lines:
        rows.extend(
            _fix_row(record) for record in decoder.feed(chunk, t_s) if isinstance(record, GpsFix)
        )
    rows.extend(_fix_row(record) for record in decoder.flush() if isinstance(record, GpsFix))
    return _track(rows, source)


def _read_nmea(raw: bytes, source: str) -> Track:
    # A plain log has no receive times; the decoder's UTC (when present) supplies them, and
    # the byte position keeps stream order otherwise.
    return _decode_nmea_lines(
        [(float(i), line + b"\n") for i, line in enumerate(raw.splitlines())], source
    )


def _read_recording(path: Path) -> Track:
    from x6wd.core.recorder import read_recording

    rows: list[tuple[float, ...]] = []
    nmea: list[tuple[float, bytes]] = []
    for rec in read_recording(path):
        if rec.type == "fix":
            data = dict(rec.data)
            data.setdefault("t_s", rec.t_mono)
            rows.append(_fix_row(data))
        elif rec.type == "nmea":
            text = rec.data.get("text") or rec.data.get("sentence") or rec.data.get("line") or ""
            nmea.append((rec.t_mono, str(text).encode("ascii", "replace") + b"\r\n"))
    if rows:
        return _track(rows, str(path))
    if nmea:
        return _decode_nmea_lines(nmea, str(path))
    raise ParseError(f"{path}: recording has no fix or nmea records")


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
        column = {k: col(k) for k in _CSV_NAMES}
        body = table[1:]
        if column["t"] is None:
            raise ParseError(
                f"{source}: CSV header has no time column (one of {_CSV_NAMES['t_s']})"
            )
    else:
        column = {
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
                i = column[key]
                return float(row[i]) if i is not None and i < len(row) and row[i] != "" else default

            t_s = _parse_time(row[column["t"]])  # type: ignore[index]
            lat_deg, lon_deg = get("lat"), get("lon")
            rows.append(
                (
                    t_s,
                    lat_deg,
                    lon_deg,
                    get("alt"),
                    get("valid", 1.0),
                    get("nsats", -1.0),
                    math.nan,
                    math.nan,
                )
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
        fields = line.split()
        try:
            t_s = (
                datetime.strptime(fields[0] + " " + fields[1], "%Y/%m/%d %H:%M:%S.%f")
                .replace(tzinfo=UTC)
                .timestamp()
            )
            lat_deg, lon_deg, height_m, quality, n_sats = (
                float(fields[2]),
                float(fields[3]),
                float(fields[4]),
                int(fields[5]),
                int(fields[6]),
            )
        except (ValueError, IndexError) as exc:
            raise ParseError(f"{source}:{lineno}: not an RTKLIB .pos line: {exc}") from exc
        speed_mps = course_deg = math.nan
        if len(fields) >= 17:  # velocity columns vn, ve (m/s) present
            v_north_mps, v_east_mps = float(fields[15]), float(fields[16])
            speed_mps, course_deg = (
                math.hypot(v_north_mps, v_east_mps),
                math.degrees(math.atan2(v_east_mps, v_north_mps)) % 360.0,
            )
        rows.append(
            (
                t_s,
                lat_deg,
                lon_deg,
                height_m,
                1.0 if quality > 0 else 0.0,
                float(n_sats),
                speed_mps,
                course_deg,
            )
        )
    return _track(rows, source)


def parse_truth(text: str) -> tuple[float, float, float]:
    """``LAT,LON[,ALT]`` (degrees, metres) -> (lat, lon, alt or NaN); ConfigError if malformed."""
    parts = [p.strip() for p in text.split(",")]
    try:
        values = [float(p) for p in parts]
    except ValueError:
        raise ConfigError(f"--truth {text!r}: expected LAT,LON[,ALT] in degrees/metres") from None
    if len(values) not in (2, 3) or not (-90 <= values[0] <= 90 and -180 <= values[1] <= 180):
        raise ConfigError(f"--truth {text!r}: expected LAT,LON[,ALT] with |LAT|<=90, |LON|<=180")
    return values[0], values[1], values[2] if len(values) == 3 else math.nan


def errors_vs_point(
    track: Track, lat_deg: float, lon_deg: float, alt_m: float = math.nan
) -> PositionSeries:
    """Errors (m) of a static log against a surveyed point; the frame origin is the point.
    Up error is NaN-free: zero when either altitude is unknown."""
    e_per_deg, n_per_deg = metres_per_degree(lat_deg)
    east_m = (track.lon_deg - lon_deg) * e_per_deg
    north_m = (track.lat_deg - lat_deg) * n_per_deg
    up_m = track.alt_m - alt_m
    return _series(track, east_m, north_m, up_m, lat_deg, lon_deg, None, None)


def _series(
    track: Track,
    east_m: np.ndarray,
    north_m: np.ndarray,
    up_m: np.ndarray,
    lat0_deg: float,
    lon0_deg: float,
    speed_mps: np.ndarray | None,
    course_deg: np.ndarray | None,
) -> PositionSeries:
    valid = track.valid & np.isfinite(east_m) & np.isfinite(north_m)
    up_m = np.where(np.isfinite(up_m), up_m, 0.0)
    nsats = track.nsats if np.all(track.nsats >= 0) else None
    return PositionSeries(
        t_s=track.t_s - track.t_s[0],
        east_m=np.where(valid, east_m, 0.0),
        north_m=np.where(valid, north_m, 0.0),
        up_m=np.where(valid, up_m, 0.0),
        valid=valid,
        origin_lat_deg=lat0_deg,
        origin_lon_deg=lon0_deg,
        speed_mps=speed_mps,
        course_deg=course_deg,
        nsats=nsats,
    )


def errors_vs_track(track: Track, truth: Track, max_gap_s: float = 1.5) -> PositionSeries:
    """Errors (m) of a log against a truth track matched in time (linear interpolation of the
    truth; epochs farther than ``max_gap_s`` from a valid truth sample are dropped). If the two
    time spans do not overlap, both are taken from their own start (a simulated log).
    The series carries the truth's speed/course (from its positions) and its origin is the
    truth at the first kept epoch, so effect layers see the true motion."""
    truth_valid = truth.valid
    truth_t_s, truth_lat_deg, truth_lon_deg, truth_alt_m = (
        truth.t_s[truth_valid],
        truth.lat_deg[truth_valid],
        truth.lon_deg[truth_valid],
        truth.alt_m[truth_valid],
    )
    if truth_t_s.size < 2:
        raise ParseError(f"{truth.source}: truth track has fewer than 2 valid epochs")
    t_s = track.t_s
    if t_s[-1] < truth_t_s[0] or t_s[0] > truth_t_s[-1]:
        t_s = t_s - t_s[0] + truth_t_s[0]
    index = np.clip(np.searchsorted(truth_t_s, t_s), 1, truth_t_s.size - 1)
    near = (
        np.minimum(np.abs(truth_t_s[index] - t_s), np.abs(truth_t_s[index - 1] - t_s)) <= max_gap_s
    )
    inside = (t_s >= truth_t_s[0]) & (t_s <= truth_t_s[-1]) & near
    if not np.any(inside):
        raise ParseError(f"{track.source}: no epoch matches the truth track {truth.source} in time")
    kept = np.flatnonzero(inside)
    t_s = t_s[kept]
    true_lat_deg, true_lon_deg, true_alt_m = (
        np.interp(t_s, truth_t_s, truth_lat_deg),
        np.interp(t_s, truth_t_s, truth_lon_deg),
        np.interp(t_s, truth_t_s, truth_alt_m),
    )
    lat0_deg, lon0_deg = float(true_lat_deg[0]), float(true_lon_deg[0])
    e_per_deg, n_per_deg = metres_per_degree(lat0_deg)
    sub = Track(
        t_s=t_s,
        lat_deg=track.lat_deg[kept],
        lon_deg=track.lon_deg[kept],
        alt_m=track.alt_m[kept],
        valid=track.valid[kept],
        nsats=track.nsats[kept],
        speed_mps=track.speed_mps[kept],
        course_deg=track.course_deg[kept],
        source=track.source,
    )
    true_east_m, true_north_m = (
        (true_lon_deg - lon0_deg) * e_per_deg,
        (true_lat_deg - lat0_deg) * n_per_deg,
    )
    east_m = (sub.lon_deg - lon0_deg) * e_per_deg - true_east_m
    north_m = (sub.lat_deg - lat0_deg) * n_per_deg - true_north_m
    # truth velocity from its own positions (central differences)
    if t_s.size > 1:
        v_east_mps, v_north_mps = np.gradient(true_east_m, t_s), np.gradient(true_north_m, t_s)
    else:
        v_east_mps, v_north_mps = np.zeros(1), np.zeros(1)
    speed_mps = np.hypot(v_east_mps, v_north_mps)
    course_deg = np.degrees(np.arctan2(v_east_mps, v_north_mps)) % 360.0
    return _series(
        sub, east_m, north_m, sub.alt_m - true_alt_m, lat0_deg, lon0_deg, speed_mps, course_deg
    )


def errors_vs_mean(track: Track) -> PositionSeries:
    """Errors of a static log against its own mean position (no truth: a bias is invisible)."""
    valid = track.valid
    if not np.any(valid):
        raise ParseError(f"{track.source}: no valid fix")
    alt_m = track.alt_m[valid]
    alt0_m = float(np.nanmean(alt_m)) if np.any(np.isfinite(alt_m)) else math.nan
    return errors_vs_point(
        track, float(np.mean(track.lat_deg[valid])), float(np.mean(track.lon_deg[valid])), alt0_m
    )


def write_csv(path: str | Path, track: Track) -> None:
    """Write a Track as CSV ``time,lat,lon,alt,valid,nsats`` (readable by :func:`read_track`)."""
    with open(path, "w", newline="") as file:
        writer = csv.writer(file)
        writer.writerow(["time", "lat", "lon", "alt", "valid", "nsats"])
        for i in range(len(track)):
            writer.writerow(
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
    true_east_m, true_north_m = truth_track_m(series)
    n_epochs = len(series)
    return Track(
        t_s=np.asarray(series.t_s, dtype=float),
        lat_deg=series.origin_lat_deg + (true_north_m + series.north_m) / n_per_deg,
        lon_deg=series.origin_lon_deg + (true_east_m + series.east_m) / e_per_deg,
        alt_m=alt0_m + np.asarray(series.up_m, dtype=float),
        valid=np.asarray(series.valid, dtype=bool),
        nsats=np.full(n_epochs, -1.0)
        if series.nsats is None
        else np.asarray(series.nsats, dtype=float),
        speed_mps=np.full(n_epochs, math.nan),
        course_deg=np.full(n_epochs, math.nan),
    )
