"""Mission files in and out, with errors that say where.

A waypoint is (latitude, longitude) in decimal degrees, WGS-84 (altitudes in the files are
ignored: the robot drives on the ground). Parsers and writers are pure functions over text;
:func:`load_file` and :func:`save_file` pick the format by the file's extension:

- ``.waypoints``: QGroundControl / Mission Planner plain text, ``QGC WPL 110`` (read, write);
- ``.gpx``: GPX 1.0/1.1, the route, else the waypoints, else the track (read; written as one
  route);
- ``.csv``: ``lat,lon`` rows, or a header naming the columns (read, write);
- ``.kml``: KML 2.2 (Google Earth), the ``LineString`` or ``gx:Track``, else every ``Point``
  (read); QGroundControl's "Save as KML" has its path start at the planned home, which is
  skipped;
- ``.plan``: QGroundControl's own mission file (JSON), its NAV_WAYPOINT items (read).

A GPX file with two routes (or tracks) with points, or a KML file with two paths or an area,
is refused naming them: x6wd drives one path, and never silently drops part of a file (what
it reads but does not drive is named in the result's :attr:`Mission.notes`). GPX and
KML files are read in the encoding their XML declaration or byte-order mark names (UTF-8 if
none); ``.waypoints``, ``.csv`` and ``.plan`` files are UTF-8.

Also the command-line form ``LAT,LON`` (:func:`parse_args`) and the protocol's JSON pairs
(:func:`from_pairs`).

Every number read from a file goes through :func:`to_float`: one that is not a number or is
too large for a float (a 400-digit JSON integer) is a :class:`ParseError` naming the line or
item, as a non-finite coordinate (``1e400``) is, also a JSON integer of more digits than
Python converts (4300); messages quote at most 40 characters of a field, with "..." and the
field's size (:func:`_shown`). :func:`load_file` reads at most :data:`MAX_FILE_BYTES` (8 MiB)
of any input, once: a regular file, a pipe (``--from csv <(zcat m.csv.gz)``, ``/dev/stdin``)
or a device (``/dev/zero`` is refused at the limit); a FIFO that no writer has open is
refused at once, never waited for; an empty input is "empty: no waypoints".
"""

from __future__ import annotations

import codecs
import csv
import io
import json
import math
import os
import re
import stat
import xml.etree.ElementTree as ET
from collections.abc import Callable, Iterable, Sequence
from decimal import Decimal
from pathlib import Path
from typing import NamedTuple
from xml.parsers import expat

from x6wd.core.errors import ParseError

MAX_WAYPOINTS = 10_000
"""A mission longer than this is almost certainly the wrong file."""


class Waypoint(NamedTuple):
    """One target position in decimal degrees (WGS-84)."""

    lat_deg: float
    lon_deg: float


class _LongInt:
    """A JSON integer of more digits than Python converts (4300, ``sys.int_info``): kept as its
    size, so that the reader names the item that holds it (:func:`_json_int`)."""

    def __init__(self, digits: int) -> None:
        self.digits = digits

    def __repr__(self) -> str:
        return f"an integer of {self.digits} digits"


def _json_int(text: str) -> int | _LongInt:
    """``int(text)`` for :func:`json.loads`, or a :class:`_LongInt` where Python refuses the
    conversion (past 4300 digits: 'use sys.set_int_max_str_digits()' is no advice for a file)."""
    try:
        return int(text)
    except ValueError:
        return _LongInt(len(text.lstrip("-")))


def _shown(raw: object, limit: int = 40, *, quote: bool = True) -> str:
    """A field of a file (or any input) as an error message quotes it: ``repr(raw)`` (``str``
    without ``quote``), cut to ``limit`` characters with "..." and the field's own size (a
    field may be megabytes long, a JSON integer hundreds of digits). Every message that
    quotes an input goes through here."""
    if isinstance(raw, _LongInt):
        return repr(raw)
    if isinstance(raw, int) and not isinstance(raw, bool):
        digits = str(raw)  # an int read from a file: within the 4300 digits int() reads
        size = f"{len(digits.lstrip('-'))} digits"
        text = digits
    else:
        text = repr(raw) if quote else str(raw)
        size = f"{len(raw) if isinstance(raw, str) else len(text)} characters"
    return text if len(text) <= limit else f"{text[:limit]}... ({size})"


def to_float(raw: object, what: str) -> float:
    """``float(raw)`` of a number read from a file (a string, a JSON number): a
    :class:`ParseError` naming ``what`` for one that is not a number, a bool, or an integer
    too large for a float (a 400-digit JSON integer), never OverflowError. Not checked for
    finiteness: ``float("1e400")`` is inf, the caller's to refuse or note."""
    if isinstance(raw, bool):
        raise ParseError(f"{what} must be a number, got {_shown(raw)}")
    try:
        return float(raw)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        if isinstance(raw, _LongInt):  # a JSON integer of over 4300 digits
            raise ParseError(f"{what} is too large for a number: {_shown(raw)}") from None
        raise ParseError(f"{what} is not a number: {_shown(raw)}") from None
    except OverflowError:
        raise ParseError(f"{what} is too large for a number: {_shown(raw)}") from None


def make_waypoint(lat: object, lon: object, where: str = "") -> Waypoint:
    """Validate one latitude/longitude pair (degrees); ``where`` prefixes error messages."""
    prefix = f"{where}: " if where else ""
    vals: list[float] = []
    for name, raw in (("latitude", lat), ("longitude", lon)):
        v = to_float(raw, prefix + name)
        if not math.isfinite(v):
            raise ParseError(f"{prefix}{name} must be finite, got {_shown(raw)}")
        vals.append(v)
    lat_deg, lon_deg = vals
    if not -90.0 <= lat_deg <= 90.0:
        raise ParseError(f"{prefix}latitude {lat_deg} outside -90..90")
    if not -180.0 <= lon_deg <= 180.0:
        raise ParseError(f"{prefix}longitude {lon_deg} outside -180..180")
    return Waypoint(lat_deg, lon_deg)


class Mission(list[Waypoint]):
    """The waypoints read from a file (a list), with what else the reader has to say.

    ``home``: a ``.waypoints`` file's home row, kept so that converting to ``.waypoints``
    writes it back. ``notes``: what in the file x6wd read but does not use (a GPX route's
    waypoints beside it, a ``.waypoints`` acceptance radius ...), one sentence each, for the
    user to see (``x6wd mission show`` prints them): nothing in a file is dropped silently.
    """

    def __init__(
        self,
        waypoints: Iterable[Waypoint] = (),
        home: Waypoint | None = None,
        notes: Iterable[str] = (),
    ) -> None:
        super().__init__(waypoints)
        self.home = home
        self.notes = list(notes)


def _check_count(
    wps: Sequence[Waypoint],
    source: str,
    home: Waypoint | None = None,
    notes: Iterable[str] = (),
) -> Mission:
    if not wps:
        raise ParseError(f"{source}: no waypoints")
    if len(wps) > MAX_WAYPOINTS:  # the parsers stop reading one past the limit
        raise ParseError(f"{source}: more than {MAX_WAYPOINTS} waypoints, the most allowed")
    return Mission(wps, home, notes)


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
            raise ParseError(f"{where}: expected [lat, lon], got {_shown(item)}")
        if len(out) > MAX_WAYPOINTS:
            break
    return _check_count(out, source)


def parse_args(args: Sequence[str]) -> list[Waypoint]:
    """Waypoints from ``LAT,LON`` strings (one per argument), e.g. ``51.7,-1.2``."""
    out: list[Waypoint] = []
    for i, arg in enumerate(args):
        parts = arg.split(",")
        if len(parts) != 2:
            raise ParseError(f"--wp #{i + 1}: expected LAT,LON, got {_shown(arg)}")
        out.append(make_waypoint(parts[0].strip(), parts[1].strip(), f"--wp #{i + 1}"))
    return _check_count(out, "--wp")


_LAT_NAMES = ("lat", "latitude", "lat_deg")
_LON_NAMES = ("lon", "lng", "long", "longitude", "lon_deg")


def parse_csv(text: str, source: str = "CSV") -> Mission:
    """Waypoints from CSV text.

    Either a header row naming the latitude and longitude columns (``lat``/``latitude``,
    ``lon``/``lng``/``longitude``; other columns ignored) or headerless rows ``lat,lon``.
    Blank lines and lines starting with ``#`` are skipped.
    """
    reader = csv.reader(io.StringIO(text))
    try:
        rows = [
            (n, r)
            for n, r in enumerate(reader, start=1)
            if r and any(c.strip() for c in r) and not r[0].lstrip().startswith("#")
        ]
    except csv.Error as exc:  # e.g. a field over the csv module's 128 KiB
        raise ParseError(f"{source}: line {reader.line_num}: {exc}") from None
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
        _csv_separator(where, row, (lat_col, lon_col))
        if len(row) <= max(lat_col, lon_col):
            raise ParseError(f"{where}: expected at least {max(lat_col, lon_col) + 1} columns")
        out.append(make_waypoint(row[lat_col].strip(), row[lon_col].strip(), where))
        if len(out) > MAX_WAYPOINTS:
            break
    return _check_count(out, source)


_DECIMAL_COMMA = re.compile(r"^\s*[+-]?\d+,\d+\s*$")


def _csv_separator(where: str, row: list[str], cols: tuple[int, int]) -> None:
    """Refuse a row written with another separator or decimal commas, saying so: a
    spreadsheet in a locale with decimal commas writes ``51,752;-1,2577``, which read with
    commas is a short row or a latitude of 51 and a longitude of 752."""
    used = [row[c] for c in cols if c < len(row)]
    if len(row) <= max(cols) or any(not _is_number(f) for f in used):
        if any(";" in f for f in row):
            raise ParseError(
                f"{where}: the separator must be a comma, and ';' was found (a spreadsheet "
                "set to decimal commas writes ';'): save the file with ',' between columns "
                "and '.' as the decimal point"
            )
        if "\t" in "".join(row):
            raise ParseError(f"{where}: the separator must be a comma, and a tab was found")
        if bad := next((f for f in used if _DECIMAL_COMMA.match(f)), None):
            raise ParseError(
                f"{where}: {_shown(bad.strip())} has a decimal comma: write a decimal point "
                f"({_shown(bad.strip().replace(',', '.'), quote=False)})"
            )


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def _local(tag: str) -> str:
    return tag.rsplit("}", 1)[-1]


_GPX_NAMESPACES = ("http://www.topografix.com/GPX/1/1", "http://www.topografix.com/GPX/1/0", "")
# GPX's own namespace as exporters write it: https (OsmAnd 5's format docs), a trailing "/"
# (Garmin-style headers, Onloc), any case of the host. Another schema's namespace is not.
_GPX_NAMESPACE_RE = re.compile(r"(?i:https?://www\.topografix\.com)/GPX/1/[01]/?")


def parse_gpx(text: str, source: str = "GPX") -> Mission:
    """Waypoints from GPX 1.0/1.1 text: the route's ``<rtept>`` if it has a route (the
    ``<wpt>`` beside it are its points of interest), else every ``<wpt>``, else the track's
    ``<trkpt>`` (all its ``<trkseg>`` in order: a track split where the receiver lost its fix
    is still one track). Waypoints and a track without a route are refused: which is the
    path is the user's to say.

    Routes and tracks without points are ignored. Two routes with points, or two tracks, are
    refused with their names and sizes: x6wd drives one path, and reading only the first
    would silently drop the other's waypoints. Waypoints or a track beside the route are
    named in the result's ``notes``.

    Only elements of the GPX namespace (1.1, 1.0, or none in a file without one) are read,
    and only where GPX puts them (``gpx/rte/rtept``, ``gpx/trk/trkseg/trkpt``, ``gpx/wpt``):
    an ``<extensions>`` element's content is another schema's, never the path.

    DTDs and entities are refused: the content may come from the network.
    """
    _no_dtd(text, source, "GPX")
    try:
        root = ET.fromstring(text)
    except ET.ParseError as exc:
        raise ParseError(f"{source}: not valid XML: {exc}") from None
    if _local(root.tag) != "gpx":
        tag = _shown(_local(root.tag), quote=False)
        raise ParseError(f"{source}: root element is <{tag}>, expected <gpx>")
    ns = root.tag[1:].split("}", 1)[0] if root.tag.startswith("{") else ""
    if ns not in _GPX_NAMESPACES and not _GPX_NAMESPACE_RE.fullmatch(ns):
        raise ParseError(
            f"{source}: <gpx> is in the namespace {_shown(ns)}, not GPX 1.1's "
            f"{_GPX_NAMESPACES[0]!r} (nor 1.0's, nor none)"
        )

    def children(parent: ET.Element, name: str) -> list[ET.Element]:
        """``parent``'s own ``<name>`` children in the GPX namespace: never what an
        ``<extensions>`` holds, nor another schema's element of the same name (a Garmin
        ``<gpxx:rpt>``, an ``<x:rtept>``), which are not the file's path."""
        return [e for e in parent if e.tag == (f"{{{ns}}}{name}" if ns else name)]

    def points(parent: ET.Element, kind: str) -> list[ET.Element]:
        if kind == "rtept":  # rte/rtept; trk/trkseg/trkpt, the segments in order
            return children(parent, "rtept")
        return [p for seg in children(parent, "trkseg") for p in children(seg, "trkpt")]

    def path(tag: str, what: str, kind: str) -> list[ET.Element]:
        """The points of the one ``tag`` (rte, trk) that has any; [] if none has, refused if
        several have."""
        found = [
            (n, e, pts)
            for n, e in enumerate(children(root, tag), start=1)
            if (pts := points(e, kind))
        ]
        if len(found) > 1:
            listed = ", ".join(
                f"<{tag}> #{n} {_name(e)}({_points(len(pts))})" for n, e, pts in found
            )
            raise ParseError(
                f"{source}: {len(found)} {what}s with points: {listed}; x6wd drives one {what}: "
                f"delete the others from the file, or join them into one"
            )
        return found[0][2] if found else []

    notes: list[str] = []
    if elems := path("rte", "route", "rtept"):
        kind = "rtept"
        # the route wins: what is beside it is not driven, and the user is told so
        wpts = children(root, "wpt")
        beside = [f"{_points(len(wpts))} as <wpt>"] if wpts else []
        beside += [
            f"a <trk> of {_points(len(pts))}"
            for trk in children(root, "trk")
            if (pts := points(trk, "trkpt"))
        ]
        if beside:
            notes.append(
                f"{source}: the <rte> is driven; beside it, not driven: {' and '.join(beside)} "
                "(a route wins over waypoints and tracks)"
            )
    elif elems := children(root, "wpt"):
        kind = "wpt"
        if track := path("trk", "track", "trkpt"):  # a handheld's marks beside its track
            raise ParseError(
                f"{source}: {_points(len(elems))} as <wpt> and a <trk> of "
                f"{_points(len(track))}, no <rte>: x6wd drives one path: delete the waypoints "
                "or the track from the file, or make the path a route"
            )
    elif elems := path("trk", "track", "trkpt"):
        kind = "trkpt"
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
    return _check_count(out, source, notes=notes)


def _points(n: int) -> str:
    return f"{n} point" if n == 1 else f"{n} points"


def _name(e: ET.Element) -> str:
    """``'NAME' `` from an element's ``<name>`` child, quoted, with a trailing space; or ''."""
    name = next((c.text for c in e if _local(c.tag) == "name" and c.text), None)
    return f"{_shown(name.strip())} " if name and name.strip() else ""


_BOMS = (  # UTF-32 before UTF-16: UTF-32-LE's mark begins with UTF-16-LE's
    (codecs.BOM_UTF8, "utf-8-sig"),
    (codecs.BOM_UTF32_LE, "utf-32"),
    (codecs.BOM_UTF32_BE, "utf-32"),
    (codecs.BOM_UTF16_LE, "utf-16"),
    (codecs.BOM_UTF16_BE, "utf-16"),
)
_XML_ENCODING = re.compile(rb"""^\s*<\?xml[^>]*?\sencoding\s*=\s*["']([A-Za-z][\w.-]*)["']""")


def decode_xml(data: bytes, source: str = "XML") -> str:
    """An XML file's bytes as text, in the encoding its byte-order mark or XML declaration
    names (``encoding="ISO-8859-1"``, UTF-16 with a BOM ...), else UTF-8 as XML says; a
    :class:`ParseError` for an unknown encoding or bytes that are not in it."""
    declared = None
    encoding, how = next(
        ((enc, "its byte-order mark") for bom, enc in _BOMS if data.startswith(bom)), (None, "")
    )
    if encoding is None and data[:4] in (b"<\0?\0", b"\0<\0?"):  # UTF-16 without a BOM
        encoding, how = ("utf-16-le" if data[0] else "utf-16-be"), "its first bytes"
    if encoding is None:
        m = _XML_ENCODING.match(data[:1024])
        declared = m.group(1).decode("ascii") if m else None
        # '<?xml' was read one byte a character: a declared UTF-16 or -32 cannot be true (a
        # string saved as UTF-8 by a tool that wrote the declaration for the string)
        if declared and not re.sub(r"[-_]", "", declared.lower()).startswith(("utf16", "utf32")):
            encoding, how = declared, "its XML declaration"
        else:
            encoding, how = "UTF-8", "XML's default"
    try:
        return data.decode(encoding)
    except LookupError:
        raise ParseError(
            f"{source}: unknown encoding {_shown(declared)} in its XML declaration"
        ) from None
    except UnicodeDecodeError as exc:
        raise ParseError(f"{source}: not {encoding} text ({how}): {exc}") from None


class _HasDtd(Exception):
    """Raised from expat's handler at the first DOCTYPE or entity declaration."""


def _no_dtd(text: str, source: str, kind: str) -> None:
    """Refuse DTDs and entities: the content may come from the network (billion laughs), and
    a DTD's default attributes can add waypoints written nowhere in the visible file. Expat
    finds the declaration wherever the prolog puts it (after a long comment or whitespace);
    a text search of the file's head did not."""
    if "<!ENTITY" in text.upper():
        raise ParseError(f"{source}: DTDs and entities are not allowed in {kind}")

    def refuse(*_: object) -> None:
        raise _HasDtd

    scan = expat.ParserCreate()
    scan.StartDoctypeDeclHandler = refuse
    scan.EntityDeclHandler = refuse
    try:
        scan.Parse(text, True)
    except _HasDtd:
        raise ParseError(f"{source}: DTDs and entities are not allowed in {kind}") from None
    except expat.ExpatError:
        pass  # not well-formed: the real parse says where


# -- QGC WPL 110 (QGroundControl, Mission Planner, ArduPilot) ---------------------------------
# One mission item per line, 12 tab-separated columns: index, current (0/1), frame, command,
# param1..param4, param5 = latitude, param6 = longitude, param7 = altitude, autocontinue.
# In version 110 the item of index 0 is the home position (QGroundControl's planned home,
# ArduPilot's index 0), not a place to drive to.

WPL_HEADER = "QGC WPL 110"
MAV_CMD_NAV_WAYPOINT = 16
_WPL_COLUMNS = 12
# MAV_FRAME values whose param5/param6 are latitude/longitude in degrees (in the text file
# the *_INT frames are written as degrees too)
_GLOBAL_FRAMES = {
    0: "GLOBAL",
    3: "GLOBAL_RELATIVE_ALT",
    5: "GLOBAL_INT",
    6: "GLOBAL_RELATIVE_ALT_INT",
    10: "GLOBAL_TERRAIN_ALT",
    11: "GLOBAL_TERRAIN_ALT_INT",
}
# names of common MAV_CMDs, for the error message of an unsupported one
_MAV_CMD_NAMES = {
    16: "NAV_WAYPOINT",
    17: "NAV_LOITER_UNLIM",
    18: "NAV_LOITER_TURNS",
    19: "NAV_LOITER_TIME",
    20: "NAV_RETURN_TO_LAUNCH",
    21: "NAV_LAND",
    22: "NAV_TAKEOFF",
    82: "NAV_SPLINE_WAYPOINT",
    93: "NAV_DELAY",
    112: "CONDITION_DELAY",
    114: "CONDITION_DISTANCE",
    115: "CONDITION_YAW",
    177: "DO_JUMP",
    178: "DO_CHANGE_SPEED",
    179: "DO_SET_HOME",
    181: "DO_SET_RELAY",
    183: "DO_SET_SERVO",
    189: "DO_LAND_START",
    201: "DO_SET_ROI",
    203: "DO_DIGICAM_CONTROL",
    206: "DO_SET_CAM_TRIGG_DIST",
}


def parse_wpl(text: str, source: str = "QGC WPL") -> Mission:
    """Waypoints from a QGC WPL 110 (``.waypoints``) mission: its NAV_WAYPOINT (16) items.

    The items' indices must count up by one from the first: from 0 if the file has a home row
    (index 0, skipped as QGroundControl and ArduPilot do; kept as the result's ``home``), from 1
    if it has none (a hand-made or trimmed file: its first item is a waypoint). Out-of-order or
    repeated indices are refused: which order is meant is the user's to say.

    Every other command is refused with its line: x6wd drives to waypoints and nothing else,
    so a mission that loiters, jumps or changes speed would silently mean something else. So
    is a waypoint with a hold time (param1 > 0) or autocontinue 0 (stop there): x6wd does not
    hold at waypoints. An acceptance radius (param2) is not used (x6wd arrives by its own
    window, ``[navigation] delta_x_m``/``delta_y_m``): the result's ``notes`` say so.
    ``QGC WPL 120`` (QGroundControl's older files, no home row) is read too.
    """
    lines = text.splitlines()
    first = next((n for n, line in enumerate(lines, start=1) if line.strip()), None)
    if first is None:
        raise ParseError(f"{source}: empty file, expected the header {WPL_HEADER!r}")
    header = " ".join(lines[first - 1].split())
    if header not in ("QGC WPL 110", "QGC WPL 120"):
        raise ParseError(
            f"{source} line {first}: expected the header {WPL_HEADER!r}, got {_shown(header)}"
        )
    may_have_home = header == "QGC WPL 110"
    out: list[Waypoint] = []
    notes: list[str] = []
    home: Waypoint | None = None
    expected: int | None = None  # the next item's index; None before the first item
    for n, line in enumerate(lines[first:], start=first + 1):
        if not line.strip():
            continue
        where = f"{source} line {n}"
        cols = line.rstrip("\r\n").split("\t") if "\t" in line else line.split()
        cols = [c.strip() for c in cols]
        if len(cols) != _WPL_COLUMNS:
            raise ParseError(
                f"{where}: expected {_WPL_COLUMNS} tab-separated columns (index, current, frame, "
                f"command, param1-4, latitude, longitude, altitude, autocontinue), "
                f"got {len(cols)}"
            )
        ints: list[int] = []
        for name, raw in zip(("index", "current", "frame", "command"), cols[:4], strict=True):
            try:
                ints.append(int(raw))
            except ValueError:
                if re.fullmatch(r"[+-]?\d+", raw):  # past the 4300 digits Python converts
                    big = _shown(_LongInt(len(raw.lstrip("+-"))))
                    raise ParseError(f"{where}: {name} is too large for a number: {big}") from None
                raise ParseError(f"{where}: {name} is not an integer: {_shown(raw)}") from None
        index, _current, frame, command = ints
        params: list[float] = []
        for i, raw in enumerate(cols[4:8] + cols[10:12], start=1):
            name = f"param{i}" if i <= 4 else ("altitude", "autocontinue")[i - 5]
            params.append(to_float(raw, f"{where}: {name}"))
        hold_s, accept_radius_m, _pass_radius_m, _yaw_deg, _alt_m, autocontinue = params
        if expected is None:
            # QGC writes the home as index 0 and the items from 1; a file without a home row
            # starts at 1 (in version 120, which has none, the first item is index 0)
            if index not in (0, 1):
                raise ParseError(
                    f"{where}: index {_shown(index)}, expected 0 (the home row) or 1 (the first "
                    "waypoint): the items are numbered 0, 1, 2 ... in file order"
                )
            expected = index + 1
            if may_have_home and index == 0:
                try:  # kept only to be written back; a bad one is never driven to
                    home = make_waypoint(cols[8], cols[9], where)
                except ParseError as exc:
                    notes.append(f"{exc}: the home row is not kept")
                continue  # the home position: where the vehicle was, not a waypoint
        elif index != expected:
            raise ParseError(
                f"{where}: index {_shown(index)}, expected {expected}: the items must be numbered "
                "0 (home), 1, 2 ... in the order they are driven, without gaps or repeats; "
                "renumber them, or save the mission again from QGroundControl"
            )
        else:
            expected += 1
        if command != MAV_CMD_NAV_WAYPOINT:
            name = _MAV_CMD_NAMES.get(command, "unknown")
            raise ParseError(
                f"{where}: command {command} ({name}) is not supported: x6wd missions are "
                f"NAV_WAYPOINT ({MAV_CMD_NAV_WAYPOINT}) items only"
            )
        if frame not in _GLOBAL_FRAMES:
            raise ParseError(
                f"{where}: frame {frame} is not a global latitude/longitude frame "
                f"(valid: {', '.join(f'{k} {v}' for k, v in _GLOBAL_FRAMES.items())})"
            )
        # a hold or a stop would change where and when the robot waits; it never waits
        if hold_s > 0:
            raise ParseError(
                f"{where}: hold time (param1) {_shown(cols[4], quote=False)} s: x6wd does not "
                "hold at waypoints (it drives on when it arrives); set param1 to 0 (Hold in "
                "QGroundControl, Delay in Mission Planner)"
            )
        if autocontinue != 1:
            raise ParseError(
                f"{where}: autocontinue (the last column) {_shown(cols[11], quote=False)}: 0 "
                "stops the mission at this waypoint and x6wd does not hold at waypoints (it "
                "drives on); set it to 1"
            )
        wp = make_waypoint(cols[8], cols[9], where)
        if wp.lat_deg == 0.0 and wp.lon_deg == 0.0:
            # ArduPilot reads a waypoint at 0, 0 as "where the vehicle is now"; x6wd would
            # drive to the Gulf of Guinea
            raise ParseError(
                f"{where}: latitude and longitude are 0, 0 (ArduPilot's 'current position'): "
                "give the waypoint's real position"
            )
        if accept_radius_m != 0 and not math.isnan(accept_radius_m):  # NaN: MAVLink's unset
            notes.append(
                f"{where}: acceptance radius (param2) {_shown(cols[5], quote=False)} m not "
                "used: x6wd arrives by its own window from the config ([navigation] "
                "delta_x_m, delta_y_m)"
            )
        out.append(wp)
        if len(out) > MAX_WAYPOINTS:
            break
    return _check_count(out, source, home, notes)


# -- QGroundControl .plan (JSON) ----------------------------------------------------------------
# {"fileType": "Plan", "mission": {"plannedHomePosition": [lat, lon, alt], "items": [
#   {"type": "SimpleItem", "command": 16, "frame": 3, "autoContinue": true,
#    "params": [hold, accept radius, pass radius, yaw, lat, lon, alt], ...},
#   {"type": "ComplexItem", "complexItemType": "survey", ...}, ...]}, "geoFence": ..., ...}
# (QGroundControl's mission version 2; version 1 gave a SimpleItem "coordinate": [lat, lon,
# alt] and four params). QGroundControl cannot save .waypoints (mavlink/qgroundcontrol#8097).


def parse_plan(text: str, source: str = "QGC plan") -> Mission:
    """Waypoints from a QGroundControl ``.plan`` file: the NAV_WAYPOINT (16) SimpleItems of
    its mission, in order. ``plannedHomePosition`` is where the vehicle was when planned, not a
    place to drive to (as a ``.waypoints`` file's home row): kept as the result's ``home``.

    The rules are the ``.waypoints`` reader's (:func:`parse_wpl`): any other command (takeoff,
    loiter, jump, change speed ...) is refused naming the item, so is a hold time (params[0]
    > 0), ``autoContinue`` false or a frame that is not latitude/longitude; an acceptance
    radius (params[1]) is read with a note. A ComplexItem (survey, corridor scan, structure
    scan ...) is refused naming it: its path is computed by QGroundControl from a polygon and
    is not in the file as waypoints. The geofence and rally points are not part of the path:
    a note names them when the file has any."""
    try:
        doc = json.loads(text, parse_int=_json_int)
    except (ValueError, RecursionError) as exc:
        why = _shown(str(exc), 200, quote=False)
        raise ParseError(f"{source}: not valid JSON: {why}") from None
    if not isinstance(doc, dict) or doc.get("fileType") != "Plan":
        got = doc.get("fileType") if isinstance(doc, dict) else type(doc).__name__
        raise ParseError(
            f'{source}: not a QGroundControl plan (expected "fileType": "Plan", got {_shown(got)})'
        )
    mission = doc.get("mission")
    if not isinstance(mission, dict) or not isinstance(mission.get("items"), list):
        raise ParseError(f'{source}: no "mission" with a list of "items"')
    notes: list[str] = []
    home: Waypoint | None = None
    planned = mission.get("plannedHomePosition")
    if planned is not None:
        try:  # kept only to be written back (.waypoints); never driven to
            if not isinstance(planned, list) or len(planned) < 2:
                raise ParseError(f"{source} plannedHomePosition: expected [lat, lon, alt]")
            home = make_waypoint(planned[0], planned[1], f"{source} plannedHomePosition")
        except ParseError as exc:
            notes.append(f"{exc}: the planned home is not kept")
    out: list[Waypoint] = []
    for i, item in enumerate(mission["items"]):
        where = f"{source} mission item {i + 1}"
        if not isinstance(item, dict):
            raise ParseError(f"{where}: expected an object, got {type(item).__name__}")
        kind = item.get("type")
        if kind == "ComplexItem":
            what = item.get("complexItemType", "unknown")
            raise ParseError(
                f"{where}: a ComplexItem ({_shown(what, quote=False)}) is not supported: "
                "QGroundControl computes its path from a polygon, and x6wd drives waypoints "
                "only; draw the path as waypoints, or delete the item"
            )
        if kind != "SimpleItem":
            raise ParseError(f'{where}: type {_shown(kind)}, expected "SimpleItem"')
        command, frame = item.get("command"), item.get("frame")
        if isinstance(command, _LongInt):
            raise ParseError(f"{where}: command is too large for a number: {_shown(command)}")
        if not isinstance(command, int) or isinstance(command, bool):
            raise ParseError(f"{where}: command is not an integer: {_shown(command)}")
        if command != MAV_CMD_NAV_WAYPOINT:
            name = _MAV_CMD_NAMES.get(command, "unknown")
            raise ParseError(
                f"{where}: command {_shown(command)} ({name}) is not supported: x6wd missions "
                f"are NAV_WAYPOINT ({MAV_CMD_NAV_WAYPOINT}) items only"
            )
        if frame not in _GLOBAL_FRAMES or isinstance(frame, bool):
            raise ParseError(
                f"{where}: frame {_shown(frame)} is not a global latitude/longitude frame "
                f"(valid: {', '.join(f'{k} {v}' for k, v in _GLOBAL_FRAMES.items())})"
            )
        params = item.get("params")
        if not isinstance(params, list) or len(params) not in (4, 7):
            got = _shown(params, 60)
            raise ParseError(f"{where}: params: expected a list of 7 values, got {got}")
        nums: list[float | None] = []  # hold time, acceptance radius; None: null, unset
        for k, what in ((0, "hold time"), (1, "acceptance radius")):
            name = f"{where}: params[{k}] ({what})"
            if params[k] is not None and not isinstance(params[k], (int, float, _LongInt)):
                raise ParseError(f"{name} is not a number: {_shown(params[k])}")
            nums.append(None if params[k] is None else to_float(params[k], name))
        hold_s, accept_m = nums
        if hold_s is not None and hold_s > 0:
            raise ParseError(
                f"{where}: hold time (params[0]) {hold_s:g} s: x6wd does not hold at waypoints "
                "(it drives on when it arrives); set Hold to 0 in QGroundControl"
            )
        if item.get("autoContinue", True) is not True:
            raise ParseError(
                f"{where}: autoContinue {_shown(item.get('autoContinue'))}: false stops the "
                "mission at this waypoint and x6wd does not hold at waypoints (it drives on); "
                "set it true"
            )
        if len(params) == 7:
            lat, lon = params[4], params[5]
        else:  # mission version 1
            coord = item.get("coordinate")
            if not isinstance(coord, list) or len(coord) < 2:
                raise ParseError(f"{where}: no position (params[4], params[5] or coordinate)")
            lat, lon = coord[0], coord[1]
        wp = make_waypoint(lat, lon, where)
        if wp.lat_deg == 0.0 and wp.lon_deg == 0.0:
            raise ParseError(
                f"{where}: latitude and longitude are 0, 0 (ArduPilot's 'current position'): "
                "give the waypoint's real position"
            )
        if accept_m is not None and accept_m != 0 and math.isfinite(accept_m):
            notes.append(
                f"{where}: acceptance radius (params[1]) {accept_m:g} m not used: x6wd arrives by "
                "its own window from the config ([navigation] delta_x_m, delta_y_m)"
            )
        out.append(wp)
        if len(out) > MAX_WAYPOINTS:
            break
    other = []
    fence = doc.get("geoFence")
    if isinstance(fence, dict) and (fence.get("polygons") or fence.get("circles")):
        other.append("a geofence")
    rally = doc.get("rallyPoints")
    if isinstance(rally, dict) and rally.get("points"):
        other.append(f"{len(rally['points'])} rally points")
    if other:
        notes.append(f"{source}: {' and '.join(other)} not used: x6wd drives the mission only")
    if not out:
        raise ParseError(f"{source}: no waypoints (the mission has no items)")
    return _check_count(out, source, home, notes)


def _num(v: float) -> str:
    """A coordinate as the shortest decimal that reads back to the same float, in fixed
    notation (``0.00001``, not ``1e-05``: some readers of these formats take no exponent)."""
    s = format(Decimal(repr(float(v))), "f")
    return "0" if float(s) == 0.0 else s


def format_wpl(waypoints: Sequence[Waypoint], home: Waypoint | None = None) -> str:
    """A QGC WPL 110 mission: line 0 the home (``home``, else the home row the waypoints were
    read with (:class:`Mission`), else the first waypoint), then one NAV_WAYPOINT per waypoint
    in frame GLOBAL_RELATIVE_ALT (3) at altitude 0, as QGroundControl writes them (it replaces
    the home line with the vehicle's on upload)."""
    wps = _check_count(list(waypoints), "mission")
    for i, w in enumerate(wps, start=1):
        if w[0] == 0.0 and w[1] == 0.0:  # ArduPilot would read it as "where the vehicle is"
            raise ParseError(f"waypoint {i} is at 0, 0, which a .waypoints file cannot hold")
    if home is None and isinstance(waypoints, Mission):
        home = waypoints.home  # a .waypoints file's own home row, converted back
    h = home if home is not None else wps[0]
    rows = [
        WPL_HEADER,
        "\t".join(["0", "1", "0", "16", "0", "0", "0", "0", _num(h[0]), _num(h[1]), "0", "1"]),
    ]
    for i, w in enumerate(wps, start=1):
        rows.append(
            "\t".join(
                [str(i), "0", "3", "16", "0", "0", "0", "0", _num(w[0]), _num(w[1]), "0", "1"]
            )
        )
    return "\n".join(rows) + "\n"


def format_gpx(waypoints: Sequence[Waypoint], name: str = "x6wd mission") -> str:
    """A GPX 1.1 document with the waypoints as one route (``<rte>``/``<rtept>``)."""
    wps = _check_count(list(waypoints), "mission")
    gpx_ns = "http://www.topografix.com/GPX/1/1"
    root = ET.Element("gpx", {"xmlns": gpx_ns, "version": "1.1", "creator": "x6wd"})
    rte = ET.SubElement(root, "rte")
    ET.SubElement(rte, "name").text = name
    for i, w in enumerate(wps, start=1):
        pt = ET.SubElement(rte, "rtept", {"lat": _num(w[0]), "lon": _num(w[1])})
        ET.SubElement(pt, "name").text = f"WP{i}"
    ET.indent(root)
    return '<?xml version="1.0" encoding="UTF-8"?>\n' + ET.tostring(root, "unicode") + "\n"


def format_csv(waypoints: Sequence[Waypoint]) -> str:
    """CSV with a ``lat,lon`` header and one waypoint per row."""
    wps = _check_count(list(waypoints), "mission")
    return "lat,lon\n" + "".join(f"{_num(w[0])},{_num(w[1])}\n" for w in wps)


# -- KML (Google Earth, Google My Maps, most GIS tools) ----------------------------------------


def parse_kml(text: str, source: str = "KML") -> Mission:
    """Waypoints from KML: the path if there is one (a ``<LineString>``, or a ``<gx:Track>``'s
    ``<gx:coord>`` in order: a drawn or recorded path is the route, as a GPX route wins over
    its waypoints), else the ``<Point>`` of every ``<Placemark>`` in document order. KML
    writes ``lon,lat[,alt]`` (a gx:coord ``lon lat [alt]``); the altitude is ignored.

    Nothing is dropped silently: Points beside the path are named in the result's ``notes``;
    two paths with coordinates (two placemarks, a ``<MultiGeometry>``'s or a
    ``<gx:MultiTrack>``'s parts) are refused with their placemarks and sizes (x6wd drives
    one path); an area (``<Polygon>``, ``<LinearRing>``) or a ``<Model>``, which x6wd does not
    drive, is refused naming its placemark (a ring is no route: where it starts and which
    way round are not the file's to say).
    """
    _no_dtd(text, source, "KML")
    try:
        root = ET.fromstring(text)
    except ET.ParseError as exc:
        raise ParseError(f"{source}: not valid XML: {exc}") from None
    if _local(root.tag) != "kml":
        tag = _shown(_local(root.tag), quote=False)
        raise ParseError(f"{source}: root element is <{tag}>, expected <kml>")
    placemarks = [e for e in root.iter() if _local(e.tag) == "Placemark"]

    def place(i: int, pm: ET.Element) -> str:
        name = next((c.text for c in pm if _local(c.tag) == "name" and c.text), None)
        return f"<Placemark> #{i + 1}" + (f" {_shown(name.strip())}" if name else "")

    def label(i: int, pm: ET.Element) -> str:
        return f"{source} {place(i, pm)}"

    def coords(pm_label: str, geom: ET.Element) -> list[Waypoint]:
        kind = _local(geom.tag)
        if kind == "Track":  # gx:Track: one <gx:coord>lon lat [alt]</gx:coord> a point
            kind = "gx:Track"
            tuples = [(c.text or "").split() for c in geom if _local(c.tag) == "coord"]
            if not tuples:
                raise ParseError(f"{pm_label} <{kind}>: no <gx:coord>")
        else:
            el = next((c for c in geom.iter() if _local(c.tag) == "coordinates"), None)
            if el is None or not (el.text or "").strip():
                raise ParseError(f"{pm_label} <{kind}>: no <coordinates>")
            tuples = [tup.split(",") for tup in (el.text or "").split()]
        out: list[Waypoint] = []
        for k, parts in enumerate(tuples, start=1):
            where = f"{pm_label} <{kind}> coordinate {k}"
            if len(parts) not in (2, 3):
                shown = _shown((" " if kind == "gx:Track" else ",").join(parts), 60)
                raise ParseError(f"{where}: expected lon,lat[,alt], got {shown}")
            out.append(make_waypoint(parts[1], parts[0], where))
            if len(out) > MAX_WAYPOINTS:
                break
        return out

    for i, pm in enumerate(placemarks):  # areas and models: refused, never dropped
        in_polygon = {id(e) for g in pm.iter() if _local(g.tag) == "Polygon" for e in g.iter()}
        for g in pm.iter():
            kind = _local(g.tag)
            if kind in ("Polygon", "Model") or (kind == "LinearRing" and id(g) not in in_polygon):
                raise ParseError(
                    f"{label(i, pm)} <{kind}>: x6wd drives one path (a <LineString> or a "
                    "<gx:Track>) or <Point>s, not an area or a model: draw the path as a line, "
                    f"or delete the <{kind}> from the file"
                )

    # every path with coordinates, a MultiGeometry's one by one: (placemark, kind, waypoints)
    lines: list[tuple[str, str, list[Waypoint]]] = []
    for i, pm in enumerate(placemarks):
        geoms = [
            g
            for g in pm.iter()
            if (_local(g.tag) == "LineString" and _has_coordinates(g))
            or (_local(g.tag) == "Track" and any(_local(c.tag) == "coord" for c in g))
        ]
        for k, line in enumerate(geoms, start=1):
            kind = "<LineString>" if _local(line.tag) == "LineString" else "<gx:Track>"
            lines.append(
                (
                    place(i, pm),
                    kind + (f" #{k}" if len(geoms) > 1 else ""),
                    coords(label(i, pm), line),
                )
            )
    if len(lines) > 1:
        only_lines = all(kind.startswith("<LineString>") for _, kind, _ in lines)
        listed = ", ".join(
            f"{pm}{'' if kind == '<LineString>' else ' ' + kind} ({_points(len(pts))})"
            if only_lines
            else f"{pm} {kind} ({_points(len(pts))})"
            for pm, kind, pts in lines
        )
        raise ParseError(
            f"{source}: {len(lines)} {'<LineString> ' if only_lines else ''}paths: {listed}; "
            "x6wd drives one path: delete the others from the file, or join them into one"
        )
    points = [
        (i, pm, point)
        for i, pm in enumerate(placemarks)
        for point in pm.iter()
        if _local(point.tag) == "Point"
    ]
    if lines:
        notes = []
        if points:  # the path wins, as a GPX route over its waypoints: said, not silent
            names = ", ".join(dict.fromkeys(place(i, pm) for i, pm, _ in points))
            notes.append(
                f"{source}: the path {lines[0][0]} {lines[0][1]} is driven; beside it, not driven: "
                f"{len(points)} <Point> ({_shown(names, 200, quote=False)}) (a path wins over "
                "points)"
            )
        path = lines[0][2]
        if _is_qgc_plan_kml(root) and len(path) >= 2:
            # QGroundControl's "Save as KML" starts its flight path at the planned home (its
            # mission item 0): where the vehicle was, not a waypoint (as a .waypoints home row)
            notes.append(
                f"{source}: QGroundControl's plan KML: its path's first point "
                f"({path[0].lat_deg}, {path[0].lon_deg}) is the planned home, not driven"
            )
            return _check_count(path[1:], source, home=path[0], notes=notes)
        return _check_count(path, source, notes=notes)
    out: list[Waypoint] = []
    for i, pm, point in points:
        pts = coords(label(i, pm), point)
        if len(pts) != 1:
            raise ParseError(f"{label(i, pm)} <Point>: {len(pts)} coordinates, expected one")
        out.extend(pts)
        if len(out) > MAX_WAYPOINTS:
            break
    if not out:
        raise ParseError(
            f"{source}: no <Placemark> with a <Point>, a <LineString> or a <gx:Track> that has "
            "coordinates"
        )
    return _check_count(out, source)


QGC_KML_NAME = "QGroundControl Plan KML"
"""The ``<Document><name>`` of QGroundControl's "Save as KML" (KMLPlanDomDocument)."""


def _is_qgc_plan_kml(root: ET.Element) -> bool:
    doc = next((c for c in root if _local(c.tag) == "Document"), None)
    name = next((c.text for c in doc if _local(c.tag) == "name"), None) if doc is not None else None
    return (name or "").strip() == QGC_KML_NAME


def _has_coordinates(geom: ET.Element) -> bool:
    return any(_local(c.tag) == "coordinates" and (c.text or "").strip() for c in geom.iter())


# -- choosing by extension -------------------------------------------------------------------

PARSERS: dict[str, Callable[[str, str], Mission]] = {
    "waypoints": parse_wpl,
    "gpx": parse_gpx,
    "csv": parse_csv,
    "kml": parse_kml,
    "plan": parse_plan,
}
"""format name (= file extension) -> parser"""
WRITERS: dict[str, Callable[[Sequence[Waypoint]], str]] = {
    "waypoints": format_wpl,
    "gpx": format_gpx,
    "csv": format_csv,
}
"""format name (= file extension) -> writer"""
_HINTS = {
    "kmz": "unzip it (its doc.kml) and load the .kml",
    "txt": "if it is a Mission Planner file (first line 'QGC WPL 110'), rename it to .waypoints",
}


def format_of(path: str | Path, fmt: str | None = None, *, writing: bool = False) -> str:
    """The format of ``path``: ``fmt`` if given, else its extension; a clear error otherwise."""
    table = WRITERS if writing else PARSERS
    what = "written" if writing else "read"
    name = (fmt or Path(path).suffix).lower().lstrip(".")
    if name in table:
        return name
    valid = ", ".join(f".{k}" for k in table)
    if not name:
        problem = "has no extension"
    elif writing and name in PARSERS:
        problem = f"is {name.upper()}, which x6wd reads but does not write"
    else:
        problem = f"has an unknown mission format {_shown(name)}"
    hint = f" ({_HINTS[name]})" if name in _HINTS and not writing else ""
    raise ParseError(f"{path}: {problem}{hint}; missions are {what} as {valid}")


def parse_content(text: str, fmt: str | None = None, source: str = "mission") -> Mission:
    """Parse mission text as ``fmt`` (``waypoints``, ``gpx``, ``csv``, ``kml``, ``plan``); None
    guesses from the content (a ``QGC WPL`` header, ``<kml``, other XML as GPX, ``{`` a
    QGroundControl plan, else CSV)."""
    if fmt is None:
        head = text.lstrip("\ufeff \t\r\n")[:4096]
        if head.startswith("QGC WPL"):
            fmt = "waypoints"
        elif head.startswith("{"):
            fmt = "plan"
        elif head.startswith("<"):
            fmt = "kml" if re.search(r"<(\w+:)?kml[\s>]", head) else "gpx"
        else:
            fmt = "csv"
    parser = PARSERS.get(fmt.lower().lstrip("."))
    if parser is None:
        valid = ", ".join(PARSERS)
        raise ParseError(f"{source}: unknown mission format {_shown(fmt)} (valid: {valid})")
    return parser(text, source)


def format_content(waypoints: Sequence[Waypoint], fmt: str) -> str:
    """Mission text in ``fmt`` (``waypoints``, ``gpx`` or ``csv``)."""
    writer = WRITERS.get(fmt.lower().lstrip("."))
    if writer is None:
        raise ParseError(f"cannot write mission format {_shown(fmt)} (valid: {', '.join(WRITERS)})")
    return writer(waypoints)


MAX_FILE_BYTES = 8 * 1024 * 1024
"""Most a mission file (or pipe) may hold: 10 000 waypoints are well under 1 MiB."""


def read_capped(path: str | Path, max_bytes: int = MAX_FILE_BYTES) -> bytes:
    """A mission file's bytes, at most ``max_bytes`` (a :class:`ParseError` beyond, read no
    further than one byte past it). Anything that can be opened is read once, as a stream:
    a regular file, a pipe (``<(zcat mission.csv.gz)``, ``/dev/stdin``), a device
    (``/dev/zero`` is refused after ``max_bytes``). A named FIFO is read only if a writer has
    it open already: one without a writer is refused at once, never waited for; an anonymous
    pipe at end of file is empty (b""). OSError from opening or reading."""
    p = Path(path)
    fd = os.open(p, os.O_RDONLY | os.O_NONBLOCK)  # (a FIFO without a writer: no wait here)
    try:
        st = os.fstat(fd)
        if stat.S_ISREG(st.st_mode) and st.st_size > max_bytes:
            raise ParseError(f"{p}: larger than {max_bytes} bytes")
        chunks: list[bytes] = []
        if stat.S_ISFIFO(st.st_mode):
            try:
                chunks.append(os.read(fd, 1 << 16))
            except BlockingIOError:  # a writer has it open, and has not written yet
                pass
            else:
                # end of file at once: a named FIFO has no writer; an anonymous pipe's writer
                # (<(zcat ...), ': |') ran and wrote nothing, which is an empty input
                if not chunks[0] and _is_named_fifo(p, st):
                    raise ParseError(
                        f"{p}: a FIFO with nothing to read: no writer has it open "
                        "(x6wd does not wait for one: start the writer first)"
                    )
        os.set_blocking(fd, True)
        size = sum(map(len, chunks))
        while size <= max_bytes and (chunk := os.read(fd, min(1 << 20, max_bytes + 1 - size))):
            chunks.append(chunk)
            size += len(chunk)
        if size > max_bytes:
            raise ParseError(f"{p}: larger than {max_bytes} bytes")
        return b"".join(chunks)
    finally:
        os.close(fd)


def _is_named_fifo(path: Path, st: os.stat_result) -> bool:
    """Whether ``st`` (a FIFO opened at ``path``) is a FIFO in the file system (``mkfifo``), not
    an anonymous pipe reached through ``/dev/stdin``, ``/dev/fd/N`` or ``/proc/self/fd/N``
    (whose link resolves to ``pipe:[inode]``, no path)."""
    try:
        return os.path.samestat(st, os.stat(os.path.realpath(path)))
    except OSError:
        return False


def load_file(path: str | Path, fmt: str | None = None, max_bytes: int = MAX_FILE_BYTES) -> Mission:
    """Read a mission file (:func:`read_capped`: at most ``max_bytes``, a pipe too); its
    format from ``fmt`` or else its extension (:data:`PARSERS`)."""
    p = Path(path)
    kind = format_of(p, fmt)
    try:
        data = read_capped(p, max_bytes)
    except OSError as exc:
        raise ParseError(f"{p}: cannot read: {exc.strerror or exc}") from None
    if not data:  # an empty file, or a pipe whose writer wrote nothing: every format alike
        raise ParseError(f"{p}: empty: no waypoints")
    if kind in ("gpx", "kml"):  # XML names its encoding
        return parse_content(decode_xml(data, str(p)), kind, str(p))
    try:
        text = data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise ParseError(f"{p}: not UTF-8 text: {exc}") from None
    return parse_content(text, kind, str(p))


def save_file(
    path: str | Path, waypoints: Sequence[Waypoint], fmt: str | None = None, *, force: bool = False
) -> str:
    """Write a mission file in ``fmt`` or the format of its extension (:data:`WRITERS`);
    returns the format written. An existing file is replaced only with ``force`` (a
    mistyped output name must not wipe the mission it names)."""
    p = Path(path)
    kind = format_of(p, fmt, writing=True)
    text = format_content(waypoints, kind)
    if p.is_dir():  # --force could not help: say so rather than suggest it
        raise ParseError(f"{p}: is a directory; give a file name to write the mission to")
    try:
        with open(p, "w" if force else "x", encoding="utf-8", newline="") as f:
            f.write(text)
    except FileExistsError:
        raise ParseError(f"{p}: exists; give --force to replace it") from None
    except OSError as exc:
        raise ParseError(f"{p}: cannot write: {exc.strerror or exc}") from None
    return kind
