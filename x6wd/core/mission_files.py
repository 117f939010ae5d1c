"""Waypoint lists from CSV, GPX or command-line arguments, with errors that say where.

A waypoint is (latitude, longitude) in decimal degrees, WGS-84. Parsers are pure functions
over text; :func:`load_file` picks one by suffix (or by content when the suffix is unknown).
"""

from __future__ import annotations

import csv
import io
import math
import xml.etree.ElementTree as ET
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import NamedTuple

from x6wd.core.errors import ParseError

MAX_WAYPOINTS = 10_000
"""A mission longer than this is almost certainly the wrong file."""


class Waypoint(NamedTuple):
    """One target position in decimal degrees (WGS-84)."""

    lat_deg: float
    lon_deg: float


def make_waypoint(lat: object, lon: object, where: str = "") -> Waypoint:
    """Validate one latitude/longitude pair (degrees); ``where`` prefixes error messages."""
    prefix = f"{where}: " if where else ""
    vals: list[float] = []
    for name, raw in (("latitude", lat), ("longitude", lon)):
        if isinstance(raw, bool):
            raise ParseError(f"{prefix}{name} must be a number, got {raw!r}")
        try:
            v = float(raw)  # type: ignore[arg-type]
        except (TypeError, ValueError):
            raise ParseError(f"{prefix}{name} is not a number: {raw!r}") from None
        if not math.isfinite(v):
            raise ParseError(f"{prefix}{name} must be finite, got {raw!r}")
        vals.append(v)
    lat_deg, lon_deg = vals
    if not -90.0 <= lat_deg <= 90.0:
        raise ParseError(f"{prefix}latitude {lat_deg} outside -90..90")
    if not -180.0 <= lon_deg <= 180.0:
        raise ParseError(f"{prefix}longitude {lon_deg} outside -180..180")
    return Waypoint(lat_deg, lon_deg)


def _check_count(wps: Sequence[Waypoint], source: str) -> list[Waypoint]:
    if not wps:
        raise ParseError(f"{source}: no waypoints")
    if len(wps) > MAX_WAYPOINTS:
        raise ParseError(f"{source}: {len(wps)} waypoints, at most {MAX_WAYPOINTS} allowed")
    return list(wps)


def from_pairs(pairs: Iterable[object], source: str = "waypoints") -> list[Waypoint]:
    """Waypoints from ``[[lat, lon], ...]`` or ``[{"lat":..,"lon":..}, ...]`` (JSON shapes)."""
    if isinstance(pairs, (str, bytes, dict)) or not isinstance(pairs, Iterable):
        raise ParseError(f"{source}: expected a list of [lat, lon] pairs")
    out: list[Waypoint] = []
    for i, item in enumerate(pairs):
        where = f"{source}[{i}]"
        if isinstance(item, dict):
            lat = item.get("lat", item.get("lat_deg"))
            lon = item.get("lon", item.get("lon_deg"))
            if lat is None or lon is None:
                raise ParseError(f"{where}: expected keys 'lat' and 'lon'")
            out.append(make_waypoint(lat, lon, where))
        elif isinstance(item, (list, tuple)) and len(item) == 2:
            out.append(make_waypoint(item[0], item[1], where))
        else:
            raise ParseError(f"{where}: expected [lat, lon], got {item!r}")
        if len(out) > MAX_WAYPOINTS:
            break
    return _check_count(out, source)


def parse_args(args: Sequence[str]) -> list[Waypoint]:
    """Waypoints from ``LAT,LON`` strings (one per argument), e.g. ``51.7,-1.2``."""
    out: list[Waypoint] = []
    for i, arg in enumerate(args):
        parts = arg.split(",")
        if len(parts) != 2:
            raise ParseError(f"--wp #{i + 1}: expected LAT,LON, got {arg!r}")
        out.append(make_waypoint(parts[0].strip(), parts[1].strip(), f"--wp #{i + 1}"))
    return _check_count(out, "--wp")


_LAT_NAMES = ("lat", "latitude", "lat_deg")
_LON_NAMES = ("lon", "lng", "long", "longitude", "lon_deg")


def parse_csv(text: str, source: str = "CSV") -> list[Waypoint]:
    """Waypoints from CSV text.

    Either a header row naming the latitude and longitude columns (``lat``/``latitude``,
    ``lon``/``lng``/``longitude``; other columns ignored) or headerless rows ``lat,lon``.
    Blank lines and lines starting with ``#`` are skipped.
    """
    rows = [
        (n, r)
        for n, r in enumerate(csv.reader(io.StringIO(text)), start=1)
        if r and any(c.strip() for c in r) and not r[0].lstrip().startswith("#")
    ]
    if not rows:
        raise ParseError(f"{source}: no waypoints")
    first = [c.strip().lower() for c in rows[0][1]]
    lat_col, lon_col = 0, 1
    if any(c in _LAT_NAMES or c in _LON_NAMES for c in first):
        lat_col = next((i for i, c in enumerate(first) if c in _LAT_NAMES), -1)
        lon_col = next((i for i, c in enumerate(first) if c in _LON_NAMES), -1)
        if lat_col < 0 or lon_col < 0:
            raise ParseError(f"{source} line {rows[0][0]}: header needs lat and lon columns")
        rows = rows[1:]
    out: list[Waypoint] = []
    for n, row in rows:
        where = f"{source} line {n}"
        if len(row) <= max(lat_col, lon_col):
            raise ParseError(f"{where}: expected at least {max(lat_col, lon_col) + 1} columns")
        out.append(make_waypoint(row[lat_col].strip(), row[lon_col].strip(), where))
        if len(out) > MAX_WAYPOINTS:
            break
    return _check_count(out, source)


def _local(tag: str) -> str:
    return tag.rsplit("}", 1)[-1]


def parse_gpx(text: str, source: str = "GPX") -> list[Waypoint]:
    """Waypoints from GPX 1.0/1.1 text: the first ``<rte>``'s ``<rtept>`` if any, else ``<wpt>``,
    else the first track's ``<trkpt>``.

    DTDs and entities are refused: the content may come from the network.
    """
    head = text[:4096].upper()
    if "<!DOCTYPE" in head or "<!ENTITY" in text.upper():
        raise ParseError(f"{source}: DTDs and entities are not allowed in GPX")
    try:
        root = ET.fromstring(text)
    except ET.ParseError as exc:
        raise ParseError(f"{source}: not valid XML: {exc}") from None
    if _local(root.tag) != "gpx":
        raise ParseError(f"{source}: root element is <{_local(root.tag)}>, expected <gpx>")

    def points(parent: ET.Element, name: str) -> list[ET.Element]:
        return [e for e in parent.iter() if _local(e.tag) == name]

    rtes = [e for e in root if _local(e.tag) == "rte"]
    trks = [e for e in root if _local(e.tag) == "trk"]
    if rtes and points(rtes[0], "rtept"):
        elems, kind = points(rtes[0], "rtept"), "rtept"
    elif any(_local(e.tag) == "wpt" for e in root):
        elems, kind = [e for e in root if _local(e.tag) == "wpt"], "wpt"
    elif trks and points(trks[0], "trkpt"):
        elems, kind = points(trks[0], "trkpt"), "trkpt"
    else:
        raise ParseError(f"{source}: no <rtept>, <wpt> or <trkpt> elements")
    out: list[Waypoint] = []
    for i, e in enumerate(elems):
        lat, lon = e.get("lat"), e.get("lon")
        where = f"{source} <{kind}> #{i + 1}"
        if lat is None or lon is None:
            raise ParseError(f"{where}: missing lat or lon attribute")
        out.append(make_waypoint(lat, lon, where))
        if len(out) > MAX_WAYPOINTS:
            break
    return _check_count(out, source)


def parse_content(text: str, fmt: str | None = None, source: str = "mission") -> list[Waypoint]:
    """Parse mission text as ``fmt`` ("csv" or "gpx"); None guesses from the content."""
    if fmt is None:
        fmt = "gpx" if text.lstrip().startswith("<") else "csv"
    fmt = fmt.lower()
    if fmt == "gpx":
        return parse_gpx(text, source)
    if fmt == "csv":
        return parse_csv(text, source)
    raise ParseError(f"{source}: unknown mission format {fmt!r} (valid: csv, gpx)")


def load_file(path: str | Path, max_bytes: int = 8 * 1024 * 1024) -> list[Waypoint]:
    """Read a ``.csv`` or ``.gpx`` mission file (other suffixes: guessed from the content)."""
    p = Path(path)
    try:
        if p.stat().st_size > max_bytes:
            raise ParseError(f"{p}: larger than {max_bytes} bytes")
        text = p.read_text(encoding="utf-8-sig")
    except OSError as exc:
        raise ParseError(f"{p}: cannot read: {exc.strerror or exc}") from None
    except UnicodeDecodeError as exc:
        raise ParseError(f"{p}: not UTF-8 text: {exc}") from None
    suffix = p.suffix.lower().lstrip(".")
    return parse_content(text, suffix if suffix in ("csv", "gpx") else None, str(p))
