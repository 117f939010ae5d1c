"""NMEA 0183 sentences as the u-blox NEO-5 speaks them: one table, one checksum.

``SENTENCES`` lists, per sentence type, its fields in order, each with a name, a type (what
a reader makes of it), its text format in NMEA 0183 notation, its unit, the range a reader
accepts and, for unit-letter fields, the fixed letter (REFERENCE.md §4; NMEA 2.3, the NEO-5's
version), as pynmeagps does. Both sides of the wire use it:

- the decoder (``drivers.gps_nmea``) takes field positions and per-field parsers from it
  (:meth:`Sentence.pos`, :func:`field_parser`), built once at import: decoding a sentence
  is a split on commas and one call per field it reads;
- the simulated receiver (``sim_backend.nmea_out``) takes its sentence layouts from it
  (:meth:`Sentence.template`, ``%`` formats built once per formatter): the field order and
  the unit letters come from the table, the values and their precision (the receiver's own
  choice) from the writer.

Fields NMEA 4.1 appended (RMC navigational status, GSA system id, GSV signal id) are listed
as ``extra``: a reader tolerates them, the NEO-5 never writes them.

The checksum (:func:`checksum`) is the XOR of the bytes between ``$`` and ``*``.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from datetime import date
from types import MappingProxyType
from typing import Any, Final

MPS_PER_KNOT: Final = 1852.0 / 3600.0
"""Metres per second in one knot (NMEA speeds are in knots)."""
KNOTS_PER_MPS: Final = 3600.0 / 1852.0
"""Knots in one metre per second (its own constant: ``1 / MPS_PER_KNOT`` rounds differently)."""
KMH_PER_MPS: Final = 3.6
"""Kilometres per hour in one metre per second (VTG's second speed)."""
STANDARD_MAX_CHARS: Final = 82
"""NMEA 0183's limit for one sentence, ``$`` to CR LF inclusive (readers accept more)."""


# ---------------------------------------------------------------------------- checksum


def fold_xor_128(x: int) -> int:
    """``x`` (bytes as a little-endian integer) XOR-folded by 64, 32, ..., 1 bytes: the low
    byte of every 128-byte slot then holds the XOR of that slot's bytes."""
    x ^= x >> 512
    x ^= x >> 256
    x ^= x >> 128
    x ^= x >> 64
    x ^= x >> 32
    x ^= x >> 16
    x ^= x >> 8
    return x


def checksum(data: bytes) -> int:
    """XOR of all bytes of ``data``: the checksum of a body (the bytes between ``$`` and ``*``).

    The framer also folds whole lines with it (``$body*HH``), so it takes any length.
    """
    x = int.from_bytes(data, "little")
    # XOR-fold the bytes as one integer: after folding by 64, 32, ..., 1 bytes the low byte
    # holds the XOR of the bytes at offsets 0..127 (each offset is a unique sum of fold
    # widths). Seven big-int operations instead of a Python operation per byte.
    if len(data) <= 128:  # every sentence (gpsd's cap is 130 characters with '$' and '*HH')
        return fold_xor_128(x) & 0xFF
    width = 64
    while width * 2 < len(data):
        width *= 2
    while width:
        x ^= x >> (8 * width)
        width >>= 1
    return x & 0xFF


def with_checksum(body: str) -> str:
    """``"$" + body + "*HH"`` (upper-case hex), without line ending; non-ASCII counts as ``?``."""
    return f"${body}*{checksum(body.encode('ascii', 'replace')):02X}"


TRAILERS: Final[tuple[bytes, ...]] = tuple(b"*%02X\r\n" % i for i in range(256))
"""What follows a body on the wire, by checksum: ``*HH`` (upper-case hex) and CR LF."""


def sentence(body: str) -> bytes:
    """One complete sentence ``$body*HH\\r\\n`` as sent on the wire.

    ``body`` (``$`` and ``*`` excluded) must be ASCII: UnicodeEncodeError otherwise.
    """
    raw = body.encode("ascii")
    return b"$" + raw + TRAILERS[checksum(raw)]


# ---------------------------------------------------------------------------- the table


@dataclass(frozen=True, slots=True)
class Field:
    """One field of a sentence.

    ``type`` is what a reader makes of it: ``time`` (UTC time of day, microseconds),
    ``date``, ``lat``/``lon`` (signed degrees, with the hemisphere letter field that
    follows), ``letter``, ``int``, ``float`` or ``text``. ``fmt`` is its text in NMEA 0183
    notation as the NEO-5 writes it: ``hhmmss.ss``, ``ddmmyy``, ``llll.ll`` (``ddmm.mm..``),
    ``yyyyy.yy`` (``dddmm.mm..``), ``a`` a letter, ``x`` an integer, ``xx``/``xxx`` zero-padded
    to 2/3 digits, ``x.x`` a decimal number, ``c--c`` text (readers also take decimals in
    ``xx`` fields of type ``float``, as some receivers print them). ``lo``..``hi`` is the
    range a reader accepts (inclusive), in ``unit``; ``letters`` the letters a letter field
    may hold (empty always allowed). ``fixed`` is the text of a unit-letter field in a
    complete sentence (``M`` for metres). ``count`` fields of this kind follow each other
    (GSA: 12 satellite numbers).
    """

    name: str
    type: str
    fmt: str
    unit: str = ""
    lo: float | None = None
    hi: float | None = None
    letters: str = ""
    fixed: str = ""
    count: int = 1
    doc: str = ""


@dataclass(frozen=True)
class Sentence:
    """One sentence type: its fields in order (NMEA 2.3), then an optional repeated group.

    ``group`` is repeated ``groups`` times at most after ``fields`` (GSV: four satellites),
    then come the ``extra`` fields NMEA 4.1 appended.
    """

    type: str
    title: str
    fields: tuple[Field, ...]
    group: tuple[Field, ...] = ()
    groups: int = 0
    extra: tuple[Field, ...] = ()
    _pos: Mapping[str, int] = field(init=False, repr=False, compare=False)
    _by_name: Mapping[str, Field] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        pos: dict[str, int] = {}
        by_name: dict[str, Field] = {}
        i = 0
        for f in (*self.fields, *self.group):
            if f.name in pos:
                raise ValueError(f"{self.type}: field {f.name!r} twice")
            pos[f.name] = i
            by_name[f.name] = f
            i += f.count
        i += (self.groups - 1) * sum(f.count for f in self.group) if self.group else 0
        for f in self.extra:
            pos[f.name] = i
            by_name[f.name] = f
            i += f.count
        object.__setattr__(self, "_pos", MappingProxyType(pos))
        object.__setattr__(self, "_by_name", MappingProxyType(by_name))

    def pos(self, name: str) -> int:
        """Index of field ``name`` among the comma-separated fields after the address
        (``GPGGA``): 0 for the first. Of a group field, its index in the first group."""
        return self._pos[name]

    def field(self, name: str) -> Field:
        """The field called ``name`` (KeyError if the sentence has none)."""
        return self._by_name[name]

    @property
    def names(self) -> tuple[str, ...]:
        """Names of ``fields`` in order (without the group and the extra fields)."""
        return tuple(f.name for f in self.fields)

    def template(self, talker: str, *names: str, units: bool = True, **values: str | int) -> str:
        """A ``%``-format for this sentence's body from ``talker`` (``"GP"``).

        It has one ``%s`` per field in ``names`` (a ``count`` field takes one value, its
        fields already joined with commas), in the order of ``names``; a field given in
        ``values`` is written as that text (a writer's constant, such as the status letter
        of a fix); every other field of ``fields`` as its ``fixed`` text (or empty with
        ``units=False``, as a receiver without a fix writes them) or left empty. The group
        and the extra fields are not part of it. Unknown names raise KeyError.
        """
        for name in (*names, *values):
            if name not in self.names:
                raise KeyError(f"{self.type} has no field {name!r} (fields: {self.names})")
        if len(set(names) | set(values)) != len(names) + len(values):
            raise ValueError(f"{self.type} template names a field twice: {names}, {values}")
        # Placeholders are filled positionally, so named fields must come in table order.
        if list(names) != sorted(names, key=self.names.index):
            raise ValueError(f"{self.type} template fields out of order: {names}")
        parts = [talker + self.type]
        for f in self.fields:
            if f.name in names:
                parts.append("%s")
                continue
            if f.name in values:
                text = str(values[f.name])
            elif f.count > 1:
                text = "," * (f.count - 1)
            else:
                text = f.fixed if units else ""
            parts.append(text.replace("%", "%%"))
        parts[0] = parts[0].replace("%", "%%")
        return ",".join(parts)


def _time(name: str = "time", doc: str = "") -> Field:
    return Field(name, "time", "hhmmss.ss", "UTC", doc=doc or "UTC time of day")


def _lat() -> tuple[Field, Field]:
    return (
        Field("lat", "lat", "llll.ll", "deg", 0.0, 90.0, doc="latitude, ddmm.mmmmm"),
        Field("lat_hemi", "letter", "a", letters="NS", doc="N or S"),
    )


def _lon() -> tuple[Field, Field]:
    return (
        Field("lon", "lon", "yyyyy.yy", "deg", 0.0, 180.0, doc="longitude, dddmm.mmmmm"),
        Field("lon_hemi", "letter", "a", letters="EW", doc="E or W"),
    )


def _dop(name: str) -> Field:
    return Field(
        name, "float", "x.x", "", 0.0, 99.99, doc="dilution of precision; 99.99 without a fix"
    )


_MODE = Field(
    "mode", "letter", "a", letters="ADEMNS", doc="NMEA 2.3 mode: A autonomous, N not valid"
)

GGA: Final = Sentence(
    "GGA",
    "Global positioning system fix data",
    (
        _time(),
        *_lat(),
        *_lon(),
        Field("quality", "int", "x", "", 0, 8, doc="0 no fix, 1 GPS, 2 DGPS, 6 dead reckoning"),
        Field("sats_used", "int", "xx", "", 0, 99, doc="satellites used"),
        _dop("hdop"),
        Field("alt", "float", "x.x", "m", -1500.0, 1.0e6, doc="altitude above mean sea level"),
        Field("alt_unit", "letter", "a", fixed="M"),
        Field("geoid_sep", "float", "x.x", "m", -200.0, 200.0, doc="geoid above the ellipsoid"),
        Field("geoid_sep_unit", "letter", "a", fixed="M"),
        Field("dgps_age", "float", "x.x", "s"),
        Field("dgps_station", "int", "xxxx"),
    ),
)
RMC: Final = Sentence(
    "RMC",
    "Recommended minimum specific GNSS data",
    (
        _time(),
        Field("status", "letter", "a", letters="AV", doc="A valid, V not valid"),
        *_lat(),
        *_lon(),
        Field("speed", "float", "x.x", "kn", 0.0, 4000.0, doc="speed over ground"),
        Field(
            "course",
            "float",
            "x.x",
            "deg",
            0.0,
            360.0,
            doc="course over ground, true; empty at rest",
        ),
        Field("date", "date", "ddmmyy", "UTC"),
        Field("mag_var", "float", "x.x", "deg"),
        Field("mag_var_hemi", "letter", "a", letters="EW"),
        _MODE,
    ),
    extra=(Field("nav_status", "letter", "a"),),
)
GSA: Final = Sentence(
    "GSA",
    "GNSS DOP and active satellites",
    (
        Field("op_mode", "letter", "a", letters="MA", doc="M manual, A automatic 2D/3D"),
        Field("fix_type", "int", "x", "", 1, 3, doc="1 no fix, 2 2D, 3 3D"),
        Field("prn", "int", "xx", "", 1, 999, count=12, doc="satellites used, then empty fields"),
        _dop("pdop"),
        _dop("hdop"),
        _dop("vdop"),
    ),
    extra=(Field("system_id", "int", "x"),),
)
GSV: Final = Sentence(
    "GSV",
    "GNSS satellites in view",
    (
        Field("messages", "int", "x", "", 1, 9, doc="sentences in this group"),
        Field("message", "int", "x", "", 1, 9, doc="number of this sentence, from 1"),
        Field("in_view", "int", "xx", "", 0, 99, doc="satellites in view"),
    ),
    group=(
        Field("prn", "int", "xx", "", 0, 999),
        Field("elevation", "float", "xx", "deg", -90.0, 90.0),
        Field("azimuth", "float", "xxx", "deg", 0.0, 360.0, doc="true"),
        Field("snr", "float", "xx", "dB-Hz", 0.0, 99.0, doc="C/N0; empty when not tracked"),
    ),
    groups=4,
    extra=(Field("signal_id", "int", "x"),),
)
GLL: Final = Sentence(
    "GLL",
    "Geographic position, latitude/longitude",
    (
        *_lat(),
        *_lon(),
        _time(),
        Field("status", "letter", "a", letters="AV", doc="A valid, V not valid"),
        _MODE,
    ),
)
VTG: Final = Sentence(
    "VTG",
    "Course over ground and ground speed",
    (
        Field("course", "float", "x.x", "deg", 0.0, 360.0, doc="true; empty at rest"),
        Field("course_ref", "letter", "a", fixed="T"),
        Field("course_mag", "float", "x.x", "deg", 0.0, 360.0, doc="magnetic"),
        Field("course_mag_ref", "letter", "a", fixed="M"),
        Field("speed_kn", "float", "x.x", "kn", 0.0, 4000.0),
        Field("speed_kn_unit", "letter", "a", fixed="N"),
        Field("speed_kmh", "float", "x.x", "km/h", 0.0, 7408.0),
        Field("speed_kmh_unit", "letter", "a", fixed="K"),
        _MODE,
    ),
)
ZDA: Final = Sentence(
    "ZDA",
    "Time and date",
    (
        _time(),
        Field("day", "int", "xx", "", 1, 31),
        Field("month", "int", "xx", "", 1, 12),
        Field("year", "int", "xxxx", "", 1980, 2200),
        Field("zone_hours", "int", "xx", "h"),
        Field("zone_minutes", "int", "xx", "min"),
    ),
)
TXT: Final = Sentence(
    "TXT",
    "Text transmission",
    (
        Field("messages", "int", "xx", "", 1, 99),
        Field("message", "int", "xx", "", 1, 99),
        Field("text_id", "int", "xx", doc="u-blox: 00 error, 01 warning, 02 notice, 07 user"),
        Field("text", "text", "c--c"),
    ),
)

SENTENCES: Final[Mapping[str, Sentence]] = MappingProxyType(
    {s.type: s for s in (GGA, RMC, GSA, GSV, GLL, VTG, ZDA, TXT)}
)
"""Every sentence type the NEO-5 writes or this project reads, by type (``"GGA"``)."""


# ---------------------------------------------------------------------------- field parsers


class FieldError(ValueError):
    """A field's text does not match its format or range (the sentence is rejected)."""


def _float_parser(lo: float, hi: float) -> Callable[[str], float | None]:
    def parse(s: str) -> float | None:
        """Empty -> None; else a finite float in [lo, hi]; plain decimal notation only.

        ``s`` is ASCII (the decoder rejects other sentences before reading a field).
        """
        if not s:
            return None
        if s.replace(".", "", 1).isdigit():
            # The usual "12.34": float() cannot fail and none of the checks below can trip.
            v = float(s)
            if lo <= v <= hi:
                return v
            raise FieldError(s)
        try:
            v = float(s)
        except ValueError:
            raise FieldError(s) from None
        # float() also takes "1_0", "1e3" and spaces (nan/inf fail the range test).
        if not lo <= v <= hi or "_" in s or "e" in s or "E" in s or " " in s or not s.isascii():
            raise FieldError(s)
        return v

    return parse


def _int_parser(lo: int, hi: int) -> Callable[[str], int | None]:
    def parse(s: str) -> int | None:
        """Empty -> None; else a decimal integer in [lo, hi] (digits only, no sign)."""
        if not s:
            return None
        if not s.isdigit() or not s.isascii():
            raise FieldError(s)
        v = int(s)
        if not lo <= v <= hi:
            raise FieldError(s)
        return v

    return parse


@functools.lru_cache(maxsize=64)  # a time repeats in every sentence of its epoch
def parse_time(s: str) -> int | None:
    """``hhmmss``, ``hhmmss.ss`` or ``hhmmss.sss`` -> microseconds of the day (UTC)."""
    if not s:
        return None
    head = s[:6]
    if len(head) < 6 or not head.isdigit() or not head.isascii():
        raise FieldError(s)
    hh, mmss = divmod(int(head), 10_000)
    mm, ss = divmod(mmss, 100)
    frac = s[6:]
    us = 0
    if frac:
        digits = frac[1:]
        if frac[0] != "." or (digits and (not digits.isdigit() or not digits.isascii())):
            raise FieldError(s)
        us = int((digits + "000000")[:6]) if digits else 0
    if hh > 23 or mm > 59 or ss > 60:  # 60: a leap second
        raise FieldError(s)
    return ((hh * 60 + mm) * 60 + ss) * 1_000_000 + us


@functools.lru_cache(maxsize=64)
def parse_date(s: str) -> date | None:
    """``ddmmyy`` -> date; 2-digit years pivot at 80 (1980..2079)."""
    if not s:
        return None
    if len(s) != 6 or not s.isdigit() or not s.isascii():
        raise FieldError(s)
    yy = int(s[4:])
    try:
        return date(2000 + yy if yy < 80 else 1900 + yy, int(s[2:4]), int(s[:2]))
    except ValueError:
        raise FieldError(s) from None


@functools.cache  # one parser, and so one cache, per axis: GGA and RMC share it
def _coord_parser(deg_max: int, positive: str, negative: str) -> Callable[[str, str], float | None]:
    # One cache per axis: a receiver repeats its coordinates in RMC and GGA of one epoch.
    @functools.lru_cache(maxsize=64)
    def parse(value: str, hemi: str) -> float | None:
        """``(d)ddmm.mmmm...`` + hemisphere letter -> signed degrees (any minute decimals).

        ``value`` is ASCII (the decoder rejects other sentences before reading a field).
        """
        if not value:
            if hemi and hemi not in "NSEW":
                raise FieldError(hemi)
            return None
        dot = value.find(".")
        n_whole = dot if dot >= 0 else len(value)
        # Digits with at most one '.', and at least "dmm" before it.
        if n_whole < 3 or not value.replace(".", "", 1).isdigit():
            raise FieldError(value)
        deg = int(value[: n_whole - 2])
        minutes = float(value[n_whole - 2 :])  # "mm.mmmm", "mm." or "mm"
        if minutes >= 60.0:
            raise FieldError(value)
        v = deg + minutes / 60.0
        if v > deg_max:
            raise FieldError(value)
        if hemi == negative:
            return -v
        if hemi != positive:
            raise FieldError(hemi)
        return v

    return parse


def _letter_parser(letters: str) -> Callable[[str], str]:
    allowed = frozenset(("", *letters))

    def parse(s: str) -> str:
        """The letter (or empty); FieldError for any other text."""
        if s not in allowed:
            raise FieldError(s)
        return s

    return parse


def field_parser(f: Field) -> Callable[..., Any]:
    """The text -> value function for field ``f`` (FieldError on bad text, None if empty).

    Times come as microseconds of the day, dates as ``date``, latitude/longitude as signed
    degrees (the function takes the value and the hemisphere field), numbers in the field's
    unit, letters as the letter. Built once per field, with its range bound in.
    """
    kind = f.type
    if kind == "time":
        return parse_time
    if kind == "date":
        return parse_date
    if kind == "lat":
        return _coord_parser(90, "N", "S")
    if kind == "lon":
        return _coord_parser(180, "E", "W")
    if kind == "letter" and f.letters:
        return functools.lru_cache(maxsize=16)(_letter_parser(f.letters))
    if f.lo is None or f.hi is None:
        raise ValueError(f"field {f.name!r} ({kind}) has no range to check")
    # Memoised like times and coordinates: most numeric fields repeat from epoch to epoch
    # (fix quality, satellites used, DOPs, altitude, geoid separation), and a hit costs less
    # than a call of the parser. A result depends on the text only.
    if kind == "float":
        return functools.lru_cache(maxsize=64)(_float_parser(float(f.lo), float(f.hi)))
    if kind == "int":
        return functools.lru_cache(maxsize=64)(_int_parser(int(f.lo), int(f.hi)))
    raise ValueError(f"field {f.name!r}: no parser for type {kind!r}")


__all__ = [
    "GGA",
    "GLL",
    "GSA",
    "GSV",
    "KMH_PER_MPS",
    "KNOTS_PER_MPS",
    "MPS_PER_KNOT",
    "RMC",
    "SENTENCES",
    "STANDARD_MAX_CHARS",
    "TRAILERS",
    "TXT",
    "VTG",
    "ZDA",
    "Field",
    "FieldError",
    "Sentence",
    "checksum",
    "field_parser",
    "parse_date",
    "parse_time",
    "sentence",
    "with_checksum",
]
