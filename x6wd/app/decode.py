"""`x6wd decode FILE... | -`: NMEA logs or x6wd recordings -> gpsd-style JSON lines.

Like gpsd's ``gpsdecode``: one compact JSON object per line for every fix (``TPV``) and sky
report (``SKY``), with gpsd's field names and units (lat/lon deg, altMSL/altHAE m, speed
m/s, track deg true). Unknown fields are omitted, never null. A file whose first non-blank
line is a JSON object (not gpsd's own, as ``gpspipe -r`` captures begin), or whose first
intact line after damaged ones is an x6wd record
(``x6wd.core.recorder.looks_like_recording``), is an x6wd recording (JSON lines); its
``nmea`` records are decoded
(files through ``x6wd.core.recorder.read_recording_parts``, every remaining part of a
recording split by ``[recorder] max_file_mb``; standard input by a small line parser that
also takes the flat ``{"type":"nmea","text":...}`` form); its other records are ignored.
Anything else is read as a raw byte stream (binary and line noise tolerated). The decoder's
counters go to standard error, one line per input. A gzip file or stream is decompressed as
it is read (other compressions are refused: exit 2). A path that is not a regular file (a
pipe such as ``<(zcat log.gz)``, a FIFO, a device) is opened once and read as standard input
is; such a stream without any NMEA sentence or UBX frame in its first 16 MiB is given up
(``/dev/zero``). A recording line longer than 1 MiB is dropped and counted bad.

The lines are the text of ``json.dumps(tpv_obj(fix))`` /
``json.dumps(sky_obj(sky, fill_dops=False))`` (``x6wd.app.gpsd``, compact separators; the
receiver's DOPs only, where gpsd and the daemon's port add the geometry's) for the records
of the daemon's decoder (``drivers.gps_nmea.GpsDecoder``), written by :class:`ReportEncoder`
without building the dicts. :class:`ReportDecoder` is that decoder with its fixes and sky
reports written as lines instead of records (same epochs and counters: only the writing
differs);
tests/test_decode_bulk.py checks both, byte for byte, against the reference path in the same
run. bench/bench_decode.py compares the rate with gpsd's ``gpsdecode``.
"""

from __future__ import annotations

import argparse
import contextlib
import functools
import gc
import io
import json
import math
import operator
import os
import re
import sys
from collections.abc import Callable, Iterable, Iterator, Sequence
from datetime import UTC, date, datetime
from itertools import accumulate, chain, compress, repeat
from typing import IO, TYPE_CHECKING, Any, Final, TypeVar, cast

from drivers.gps_nmea import (
    _FRACTION_US,
    _GGA_ALT,
    _GGA_HDOP,
    _GGA_LAT,
    _GGA_LON,
    _GGA_MEMORY_EPOCHS,
    _GGA_QUAL,
    _GGA_SATS,
    _GGA_SEP,
    _GGA_TIME,
    _GLL_TIME,
    _GSA_MODE,
    _GSV_GROUP,
    _GSV_SAT1,
    _HEADS_MAX,
    _MINUTE_US,
    _RMC_COURSE,
    _RMC_DATE,
    _RMC_LAT,
    _RMC_LON,
    _RMC_SPEED,
    _RMC_STATUS,
    _RMC_TIME,
    _SECOND_US,
    _ZDA_DAY,
    _ZDA_TIME,
    SIGNAL_DIGITS,
    STATUS_DGPS,
    DecoderCounters,
    GpsDecoder,
    GpsOutput,
    UbxFrame,
    _gga_alt,
    _gga_hdop,
    _gga_lat,
    _gga_lon,
    _gga_quality,
    _gga_sats,
    _gga_sep,
    _GsaValues,
    _gsv_head,
    _parse_gsa,
    _rmc_course,
    _rmc_date,
    _rmc_lat,
    _rmc_lon,
    _rmc_speed,
    _rmc_status,
    _time_of_day,
    _zda_day,
    _zda_month,
    _zda_year,
    fix_status,
    gpsd_satellite,
    gsv_groups,
    gsv_signal,
    gsv_values,
    talker_system,
)
from drivers.nmea import GSA, MPS_PER_KNOT
from x6wd.core.errors import DeviceUnavailable, ParseError
from x6wd.core.geodesy import wrap360
from x6wd.core.records import GpsFix, GpsSky, SatInfo

if TYPE_CHECKING:  # imported where used: a plain NMEA log never needs the recorder
    from x6wd.core.recorder import InputSize, ReadStats

_CHUNK_BYTES = 1 << 20
UERE_M = 5.0
"""``x6wd.app.gpsd.UERE_M`` (the TPV's eph/epx/epy/epv are DOP x UERE): that module, with
its asyncio server, is imported only for a datetime ``isoformat`` cannot print, so that the
command starts faster (tests/test_decode.py checks that the two agree)."""
MEMO_MAX = 4096
"""Entries per memo of :class:`ReportEncoder` (a memo is cleared when full)."""
_SQRT2 = math.sqrt(2.0)
_dumps_compact = json.JSONEncoder(separators=(",", ":")).encode
_float_json = float.__repr__  # how json.dumps writes a finite float


class ReportEncoder:
    """TPV and SKY lines, the same text as ``json.dumps(tpv_obj(r))`` and
    ``json.dumps(sky_obj(r, fill_dops=False))`` (the receiver's DOPs only) with compact
    separators (``x6wd.app.gpsd``), built directly.

    Building those dicts and encoding them cost more than decoding the NMEA: every number
    goes through ``round`` and ``json`` although most repeat from epoch to epoch (DOPs,
    altitude, a satellite's elevation, azimuth and SNR). Here the text of a group of numbers
    (the DOPs of a sky report, a fix's altitudes, its error estimates, and a fix's altitudes
    and error estimates together) is memoised by value, a satellite's ``{...}`` by the
    ``SatInfo`` object (the decoder reuses one per satellite state, see
    ``drivers.gps_nmea``), and an epoch's time by its datetime; position, speed and track,
    which change from fix to fix, are rounded each time.
    Each memo holds exactly the text the plain path writes for its key (for the floats and
    small ints records hold: equal keys give equal text). Keys containing a zero are never
    memoised: ``0.0 == -0.0`` but they print differently. The memos are bounded (cleared
    when full). ``tests/test_decode.py`` checks the lines against
    ``tpv_obj``/``sky_obj`` + ``json.dumps`` on every corpus log and on random records.
    """

    def __init__(self) -> None:
        # (builder, values) -> text: DOPs, altitudes, error estimates
        self._groups: dict[tuple[Callable[..., str], tuple[Any, ...]], str] = {}
        # id(SatInfo) -> its JSON object. _sat_keep holds every SatInfo memoised, so none of
        # them dies and no other object can take its id meanwhile.
        self._sat_text: dict[int, str] = {}
        self._sat_keep: list[SatInfo] = []
        self._utc: datetime | None = None
        self._utc_text = ""
        # (altitude, separation, HDOP, VDOP) -> a TPV's altitude and error members
        self._tails: dict[tuple[Any, Any, Any, Any], tuple[str, str]] = {}

    @property
    def largest_memo(self) -> int:
        """Entries in the largest memo (at most :data:`MEMO_MAX`)."""
        return max(len(self._sat_text), len(self._groups), len(self._tails))

    def _group(self, key: tuple[Any, ...], build: Callable[..., str]) -> str:
        """``build(*key)``, memoised unless ``key`` holds a zero. The memo's key carries
        ``build``: altitudes, DOPs and error estimates of equal values are different texts."""
        memo_key = (build, key)
        try:
            text = self._groups[memo_key]
        except KeyError:
            pass
        except TypeError:
            return build(*key)
        else:
            return text
        text = build(*key)
        if 0 not in key:
            if len(self._groups) >= MEMO_MAX:
                self._groups.clear()
            self._groups[memo_key] = text
        return text

    def time_member(self, utc: datetime | None) -> str:
        """``,"time":"..."`` (``iso_time``), or empty without a time; fix and sky of one
        epoch share the datetime."""
        if utc is None:
            return ""
        if utc is not self._utc:
            self._utc_text = ',"time":"' + _iso_time(utc) + '"'
            self._utc = utc
        return self._utc_text

    def tpv(self, fix: GpsFix) -> str:
        """The TPV line (no newline) of ``fix``."""
        return self.tpv_line(
            fix.valid,
            fix.mode,
            self.time_member(fix.utc),
            fix.lat_deg,
            fix.lon_deg,
            fix.alt_m,
            fix.geoid_sep_m,
            fix.speed_mps,
            fix.course_deg,
            fix.hdop,
            fix.vdop,
            fix.quality,
        )

    def tpv_line(
        self,
        valid: bool,
        mode: int,
        time: str,
        lat: float | None,
        lon: float | None,
        alt: float | None,
        geoid_sep: float | None,
        speed: float | None,
        course: float | None,
        hdop: float | None,
        vdop: float | None,
        quality: int = 0,
    ) -> str:
        """The TPV line of a fix from its fields (``GpsFix``'s, units alike; its time as
        ``time_member`` writes it)."""
        mode = mode if valid else 1
        head = _tpv_head(quality if valid else 0, mode)
        if not (valid and mode >= 2 and lat is not None and lon is not None):
            return head + time + "}"
        alt_text, err_text = self.fix_tail(mode, alt, geoid_sep, hdop, vdop)
        # Position, speed and track change from fix to fix: not memoised.
        lat_text = _num_text(lat, 9)
        lon_text = _num_text(lon, 9)
        speed_text = None if speed is None else _num_text(speed, 3)
        track_text = None if course is None else _num_text(course, 4)
        return "".join(
            (
                head,
                time,
                "" if lat_text is None else ',"lat":' + lat_text,
                "" if lon_text is None else ',"lon":' + lon_text,
                alt_text,
                "" if speed_text is None else ',"speed":' + speed_text,
                "" if track_text is None else ',"track":' + track_text,
                err_text,
                "}",
            )
        )

    def fix_tail(
        self, mode: int, alt: Any, geoid_sep: Any, hdop: Any, vdop: Any
    ) -> tuple[str, str]:
        """A valid fix's altitude members (m; mode 3 only) and error estimates (m), as
        ``tpv_line`` writes them: one memo for the pair of texts."""
        if mode >= 3:
            key = (alt, None if alt is None else geoid_sep, hdop, vdop)
        else:
            key = (None, None, hdop, None)
        try:
            return self._tails[key]
        except KeyError:
            # A moving receiver's altitude changes while its DOPs hold: each part has its
            # own memo too.
            alt, sep, hdop, vdop = key
            alt_text = "" if alt is None else self._group((alt, sep), _altitudes)
            err_text = self._group((hdop, vdop), _errors)
            if 0 not in key:  # 0.0 == -0.0, but they print differently
                if len(self._tails) >= MEMO_MAX:
                    self._tails.clear()
                self._tails[key] = alt_text, err_text
            return alt_text, err_text
        except TypeError:  # unhashable values: not memoised
            alt, sep, hdop, vdop = key
            return ("" if alt is None else _altitudes(alt, sep)), _errors(hdop, vdop)

    def sky(self, sky: GpsSky) -> str:
        """The SKY line (no newline) of ``sky``."""
        sats = sky.satellites
        found = list(map(self._sat_text.get, map(id, sats)))
        texts = self._add_sats(sats) if None in found else cast("list[str]", found)
        return self.sky_line(texts, self.time_member(sky.utc), sky.hdop, sky.vdop, sky.pdop)

    def sky_line(
        self,
        texts: list[str],
        time: str,
        hdop: float | None,
        vdop: float | None,
        pdop: float | None,
    ) -> str:
        """The SKY line of a sky report from its satellites' texts (``_sat_text``) and
        its time as ``time_member`` writes it."""
        listed = ",".join(texts)
        # A satellite's text has "used":true exactly when sky_obj counts it in uSat (no
        # string in it can hold that text: JSON escapes the quotes).
        n_used = listed.count(_USED)
        dops = self.dops(hdop, vdop, pdop)
        return (
            f'{{"class":"SKY"{time}{dops},"nSat":{len(texts)},"uSat":{n_used},'
            f'"satellites":[{listed}]}}'
        )

    def dops(self, hdop: float | None, vdop: float | None, pdop: float | None) -> str:
        """A SKY line's hdop, vdop and pdop members (memoised by value)."""
        return self._group((hdop, vdop, pdop), _dops)

    def _add_sats(self, sats: tuple[SatInfo, ...]) -> list[str]:
        """Memoise the satellites of ``sats`` not memoised yet; their texts in order."""
        if len(self._sat_keep) + len(sats) > MEMO_MAX:
            self._sat_text.clear()
            self._sat_keep.clear()
        texts = []
        for s in sats:
            text = self._sat_text.get(id(s))
            if text is None:
                text = _sat_text(s)
                self._sat_text[id(s)] = text
                self._sat_keep.append(s)
            texts.append(text)
        return texts


# Text of the clock fields as ``isoformat(timespec="milliseconds")`` writes them: built
# once, so that an epoch's time is a few lookups instead of a call of isoformat.
_HOURS = tuple(f"{h:02d}:" for h in range(24))
_MINUTES = tuple(f"{m // 60:02d}:{m % 60:02d}:" for m in range(1440))  # "HH:MM:" by minute of day
_SIXTY = tuple(f"{m:02d}" for m in range(60))
_MILLIS = tuple(f".{ms:03d}Z" for ms in range(1000))
_day_text: dict[int, str] = {}  # proleptic ordinal -> "YYYY-MM-DDT"


def _iso_time(utc: datetime) -> str:
    """``gpsd.iso_time(utc)``: the text of ``isoformat(timespec="milliseconds")`` with "Z"
    (microseconds cut, not rounded, to milliseconds, as ``iso_time`` does) for a UTC or
    naive datetime of a four-digit year (``strftime``'s ``%Y`` does not pad smaller years),
    from tables; else ``iso_time``. The text has no character JSON escapes."""
    tz = utc.tzinfo
    if type(utc) is datetime and (tz is UTC or tz is None) and utc.year >= 1000:
        ordinal = utc.toordinal()
        day = _day_text.get(ordinal)
        if day is None:
            if len(_day_text) >= MEMO_MAX:
                _day_text.clear()
            day = _day_text[ordinal] = utc.date().isoformat() + "T"
        return (
            day
            + _HOURS[utc.hour]
            + _SIXTY[utc.minute]
            + ":"
            + _SIXTY[utc.second]
            + _MILLIS[utc.microsecond // 1000]
        )
    from x6wd.app.gpsd import iso_time

    return str(iso_time(utc))


def _members(*pairs: tuple[str, str | None]) -> str:
    """``,"key":text`` for each pair whose text is not None (omitted fields)."""
    return "".join(f',"{key}":{text}' for key, text in pairs if text is not None)


def _altitudes(alt: Any, sep: Any) -> str:
    """altMSL, alt, altHAE and geoidSep of ``tpv_obj`` for altitude ``alt`` (not None)."""
    text = _num_text(alt, 3)
    pairs = [("altMSL", text), ("alt", text)]
    if sep is not None:
        pairs += (("altHAE", _num_text(alt + sep, 3)), ("geoidSep", _num_text(sep, 3)))
    return _members(*pairs)


def _errors(hdop: Any, vdop: Any) -> str:
    """eph, epx, epy (from ``hdop``) and epv (from ``vdop``, None below mode 3) of
    ``tpv_obj``."""
    pairs: list[tuple[str, str | None]] = []
    if hdop is not None:
        eph = hdop * UERE_M
        exy = _num_text(eph / _SQRT2, 3)
        pairs += (("eph", _num_text(eph, 3)), ("epx", exy), ("epy", exy))
    if vdop is not None:
        pairs.append(("epv", _num_text(vdop * UERE_M, 3)))
    return _members(*pairs)


def _dops(hdop: Any, vdop: Any, pdop: Any) -> str:
    """hdop, vdop and pdop of ``sky_obj``."""
    return _members(
        *(
            (k, None if v is None else _num_text(v, 2))
            for k, v in zip(("hdop", "vdop", "pdop"), (hdop, vdop, pdop), strict=True)
        )
    )


def _head_text(quality: Any, mode_text: str) -> str:
    """A TPV's text up to its mode: gpsd's ``status`` only from DGPS (``STATUS_DGPS``) up."""
    status = fix_status(quality)
    shown = f'"status":{status},' if status >= STATUS_DGPS else ""
    return '{"class":"TPV",' + shown + '"mode":' + mode_text


# By (GGA quality, mode): the heads of every fix a receiver sends, built once.
_TPV_STATUS_HEADS: Final = {(q, m): _head_text(q, str(m)) for q in range(9) for m in range(4)}


def _tpv_head(quality: Any, mode: Any) -> str:
    """A TPV's text up to its mode: class, gpsd's ``status`` of a fix of GGA ``quality``
    where ``tpv_obj`` writes one (a valid fix's quality; 0 for an invalid fix), mode."""
    try:
        return _TPV_STATUS_HEADS[quality, mode]
    except (KeyError, TypeError):
        pass
    return _head_text(quality, str(mode) if type(mode) is int else _dumps_compact(mode))


_USED = '"used":true'  # in a satellite's text exactly when sky_obj counts it in uSat

# "%.{n}f" formats for _num_text, and the magnitude below which that text is exact.
_FIXED = tuple(f"%.{n}f" for n in range(10))
_FIXED_MAX = tuple(10.0 ** (15 - n) for n in range(10))


def _num_text(v: Any, ndigits: int) -> str | None:
    """JSON text of gpsd's ``_num(v, ndigits)`` (None if not finite: omitted).

    That text is ``repr(round(v, ndigits))``; two float-to-decimal conversions, the
    largest cost of a TPV. ``"%.{ndigits}f" % v`` is the same decimal ``round`` computes
    (both are the correctly rounded decimal of v's exact value, ties to even), written
    with every decimal place: below ``10 ** (15 - ndigits)`` in magnitude it has at most 15
    significant digits, so ``repr`` of the float nearest to it is that decimal itself, and
    without its trailing zeros that is ``repr``'s text; its plain (not exponent) notation
    holds for ``repr`` of a multiple of ``10 ** -ndigits`` when ndigits <= 4 and from 1e-3
    on for more digits. Anything else takes the two conversions.
    """
    if type(v) is float:  # what records hold: finite exactly when v - v is 0
        if v - v != 0.0:
            return None
        if -_FIXED_MAX[ndigits] < v < _FIXED_MAX[ndigits] and (ndigits <= 4 or abs(v) >= 1e-3):
            text = (_FIXED[ndigits] % v).rstrip("0")
            return text + "0" if text[-1] == "." else text
        return _float_json(round(v, ndigits))
    if v is None or not math.isfinite(v):
        return None
    return _float_json(round(float(v), ndigits))


def _sat_text(s: SatInfo) -> str:
    """One satellite of ``sky_obj`` as compact JSON."""
    free, used = _sat_texts(s.prn, s.el_deg, s.az_deg, s.snr_dbhz, s.gnssid, s.svid)
    return used if s.used else free


def _int_text(v: Any) -> str:
    """JSON text of an int (what records hold), or of any other value."""
    return str(v) if type(v) is int else _dumps_compact(v)


def _sat_texts(
    prn: Any, el_deg: Any, az_deg: Any, snr_dbhz: Any, gnssid: Any = None, svid: Any = None
) -> tuple[str, str]:
    """``_sat_text`` of a satellite as not used and as used in the fix: the text of
    ``json.dumps({"PRN": prn, "gnssid": .., "svid": .., "used": used, "el": .., "az": ..,
    "ss": ..})`` (None and non-finite values omitted, the others rounded to 0.1), written
    directly: both texts from one conversion of the numbers, each number's text memoised
    by value (elevations, azimuths and SNRs are a few hundred values)."""
    head = '{"PRN":' + _int_text(prn)
    if gnssid is not None:
        head += ',"gnssid":' + _int_text(gnssid)
    if svid is not None:
        head += ',"svid":' + _int_text(svid)
    head += ',"used":'
    tail: list[str] = []
    for key, v in ((',"el":', el_deg), (',"az":', az_deg), (',"ss":', snr_dbhz)):
        if v is not None:
            text = _tenths(v)
            if text is not None:
                tail += (key, text)
    tail.append("}")
    rest = "".join(tail)
    return head + "false" + rest, head + "true" + rest


_TENTHS: dict[Any, str] = {}  # value -> _num_text(value, 1), for values other than zero


def _tenths(v: Any) -> str | None:
    """``_num_text(v, 1)``, memoised by value: numbers that compare equal convert to the same
    float and so to the same text, except 0.0 and -0.0, never memoised (nor non-finite
    values or unhashable ones)."""
    try:
        return _TENTHS[v]
    except KeyError:
        text = _num_text(v, 1)
        if text is not None and v != 0:
            if len(_TENTHS) >= MEMO_MAX:
                _TENTHS.clear()
            _TENTHS[v] = text
        return text
    except TypeError:
        return _num_text(v, 1)


_GSA_FIELDS = GSA.pos("vdop") + 1  # the GSA fields GpsDecoder reads (a shorter one is padded)
_SatTexts = tuple[int, str, str]
"""A GSV satellite for ``ReportDecoder``: the PRN a GSA marks it used by (0: never, see
``drivers.gps_nmea._Sat``), its ``_sat_text`` not used / used in the fix."""

# How ReportDecoder takes a sentence, by its head (``text[1:7]``): counted only (a known
# type whose fields are not read), one of the types it reads in bulk, or the reference's path.
_SKIP, _DO_GGA, _DO_RMC, _DO_GSA, _DO_GSV, _DO_GLL, _DO_ZDA, _REFERENCE = range(8)  # _SKIP false
_DO_SKY = _REFERENCE + 1  # the parts of a GSV group at once (ReportDecoder._events)
_KIND_CODES: Final = {
    "GGA": _DO_GGA,
    "RMC": _DO_RMC,
    "GSA": _DO_GSA,
    "GSV": _DO_GSV,
    "GLL": _DO_GLL,
    "ZDA": _DO_ZDA,
}
_BULK_MIN: Final = 16  # fewer sentences in one call: the reference's loop, one at a time
_PERIOD_MAX: Final = 64  # longest sentence cycle looked for (see _phases)
_CYCLE_MIN: Final = 4 * _PERIOD_MAX  # fewer sentences: their heads one by one (_cycle)
_HEAD: Final = operator.itemgetter(slice(1, 7))
_GSA_KEY: Final = operator.itemgetter(slice(1, -3))  # a GSA's talker, type and fields

# The fields a handler reads, cut from the sentences of one type joined by "\n", one match
# each: whole fields (a field ends at a comma), grouped as they are memoised, then the rest
# of the line. A field class without "\n" would be slower; instead a match that runs into
# the next line leaves fewer matches than lines, and then each line is matched alone
# (_matches). A sentence with fewer fields than these need takes the reference's path.
_F = "[^,]*"
_L = "[^,*]*"  # the last field of a cut: "*HH" may follow it
_REST = r"(?:,[^\n]*)?\*.."  # the fields not read and the checksum
_GGA_CUT: Final = re.compile(
    rf"\$..GGA,({_F}),({_F},{_F},{_F},{_F}),({_F},{_F},{_F},{_F},{_F},{_L}){_REST}"
)
_RMC_CUT: Final = re.compile(
    rf"\$..RMC,({_F}),({_F}),({_F},{_F},{_F},{_L}),({_F},{_F},{_L}){_REST}"
)
# GLL: its time, then its status and mode when it has them (a valid GLL alone in its epoch
# is the epoch's fix: GpsDecoder._gll_fields)
_GLL_CUT: Final = re.compile(
    rf"\$..GLL,({_F},{_F},{_F},{_F}),({_L})(?:,({_L}))?(?:,({_L}))?{_REST}"
)
_ZDA_CUT: Final = re.compile(rf"\$..ZDA,({_F}),({_F},{_F},{_L}){_REST}")
_GSV_CUT: Final = re.compile(rf"\$(..)GSV,({_F},{_F},{_L})(?:,([^\n]*))?\*..")
assert (_GGA_TIME, _GGA_LAT, _GGA_QUAL, _GGA_SEP) == (0, 1, 5, 10)
assert (_RMC_TIME, _RMC_STATUS, _RMC_LAT, _RMC_SPEED, _RMC_DATE) == (0, 1, 2, 6, 8)
assert (_GLL_TIME, _GSV_SAT1, _ZDA_TIME, _ZDA_DAY) == (4, 3, 0, 1)

_T = TypeVar("_T")
_BAD: Final = object()
"""A memo's value for a text whose parse raised (ValueError): its sentence takes the
reference's path, which raises again and counts it."""
_PER_TEXT: Final = object()  # ReportDecoder._gsv_sats_of: read this text alone
_NO_DATE: Final = object()  # a ZDA's day, month and year that make no date
_STATUS_VALID: Final = {"A": True, "V": False, "": False}  # RMC status letters (_rmc_status)

_Position = tuple[float | None, float | None, str]  # lat, lon, their TPV members
_GgaTail = tuple[int, Any, Any, Any]  # quality, HDOP, altitude, geoid separation
_RmcTail = tuple[str, date | None]  # speed and track members, date
# A GGA or RMC as ReportDecoder holds it (what its fix's line needs):
_GgaTuple = tuple[int | None, _Position, _GgaTail]  # time of day, position, the rest
_RmcTuple = tuple[int | None, bool, _Position, _RmcTail]  # time of day, valid, ...
_GsvTuple = tuple[str, tuple[int, int], list[_SatTexts]]  # talker, count and number, sats


def _position(lat: float | None, lon: float | None) -> _Position:
    """(lat, lon, ``,"lat":..,"lon":..`` as ``tpv_line`` writes them)."""
    lat_text = None if lat is None else _num_text(lat, 9)
    lon_text = None if lon is None else _num_text(lon, 9)
    return (
        lat,
        lon,
        ("" if lat_text is None else ',"lat":' + lat_text)
        + ("" if lon_text is None else ',"lon":' + lon_text),
    )


def _motion(speed: float | None, course: float | None) -> str:
    """A TPV's speed and track members as ``tpv_line`` writes them."""
    speed_text = None if speed is None else _num_text(speed, 3)
    track_text = None if course is None else _num_text(course, 4)
    return ("" if speed_text is None else ',"speed":' + speed_text) + (
        "" if track_text is None else ',"track":' + track_text
    )


def _gga_tail(quality: str, sats: str, hdop: str, alt: str, sep: str) -> _GgaTail:
    """Quality (0 if empty), HDOP, altitude (m) and geoid separation (m) of GGA's fields, as
    ``GpsDecoder._gga_fields`` reads them (the satellites used are checked, not kept)."""
    q = _gga_quality(quality) or 0
    _gga_sats(sats)
    return q, _gga_hdop(hdop), _gga_alt(alt), _gga_sep(sep)


def _rmc_tail(speed: str, course: str, day: str) -> _RmcTail:
    """The speed (m/s) and track (deg) members of RMC's speed (kn) and course fields, and its
    date, as ``GpsDecoder._rmc_fields`` reads them."""
    speed_kn = _rmc_speed(speed)
    course_deg = _rmc_course(course)
    return (
        _motion(
            None if speed_kn is None else speed_kn * MPS_PER_KNOT,
            None if course_deg is None else wrap360(course_deg),
        ),
        _rmc_date(day),
    )


assert _gga_lat is _rmc_lat and _gga_lon is _rmc_lon  # one position memo for GGA and RMC


def _position_of(text: str) -> _Position:
    """The position of the fields ``lat,N/S,lon,E/W`` (GGA and RMC alike)."""
    lat, ns, lon, ew = text.split(",")
    return _position(_gga_lat(lat, ns), _gga_lon(lon, ew))


def _gga_tail_of(text: str) -> _GgaTail:
    """``_gga_tail`` of GGA's fields from quality to geoid separation (``text``)."""
    quality, sats, hdop, alt, _, sep = text.split(",")
    return _gga_tail(quality, sats, hdop, alt, sep)


def _rmc_tail_of(text: str) -> _RmcTail:
    """``_rmc_tail`` of RMC's fields speed, course and date (``text``)."""
    speed, course, day = text.split(",")
    return _rmc_tail(speed, course, day)


def _zda_date_of(text: str) -> date | object | None:
    """A ZDA's date from its fields day, month, year (checked, as ``GpsDecoder._on_zda``
    reads them): None where one is empty or zero (no date), ``_NO_DATE`` where they make
    no date (a bad field when the ZDA has a time)."""
    day_text, month_text, year_text = text.split(",")
    day = _zda_day(day_text)
    month = _zda_month(month_text)
    year = _zda_year(year_text)
    if not (day and month and year):
        return None
    try:
        return date(year, month, day)
    except ValueError:
        return _NO_DATE


def _gsv_counts_of(text: str) -> tuple[int, int]:
    """A GSV's message count and number from its three head fields (``_gsv_head``)."""
    return _gsv_head(*text.split(","))


def _fill(memo: dict[str, Any], keys: Iterable[str], parse: Callable[[str], Any]) -> None:
    """Put ``parse(key)`` in ``memo`` for every key not in it (``_BAD`` where it raises
    ValueError). A memo above MEMO_MAX is cleared first; it holds at least this call's keys,
    so one read of a chunk's keys never misses."""
    for key in _new_keys(memo, keys):
        try:
            memo[key] = parse(key)
        except ValueError:  # FieldError is one
            memo[key] = _BAD


def _read(
    memo: dict[str, Any], keys: Sequence[str], fill: Callable[[dict[str, Any], Sequence[str]], None]
) -> list[Any]:
    """The memo's values of ``keys``, the keys it lacks put in first by ``fill`` (``_fill``
    with a parser, ``_fill_times``, ``_fill_positions``): one pass when every key is known,
    the usual case for all but times and positions."""
    try:
        return list(map(memo.__getitem__, keys))
    except KeyError:
        fill(memo, keys)
        return list(map(memo.__getitem__, keys))


def _filler(parse: Callable[[str], Any]) -> Callable[[dict[str, Any], Sequence[str]], None]:
    """``_fill`` with ``parse``, for ``_read``."""
    return functools.partial(_fill, parse=parse)


def _new_keys(memo: dict[str, Any], keys: Iterable[str]) -> list[str]:
    """The keys not in ``memo``; if they would take it above MEMO_MAX it is cleared first
    and all ``keys`` are new (so it holds every one of them once they are put in)."""
    distinct = set(keys)
    new = distinct.difference(memo)
    if new and len(memo) + len(new) > MEMO_MAX:
        memo.clear()
        return list(distinct)
    return list(new)


_MINUTE_OF: Final = operator.itemgetter(slice(0, 4))
_SECOND_OF: Final = operator.itemgetter(slice(4, 6))
_FRACTION_OF: Final = operator.itemgetter(slice(6, None))
_FRACTION_OR_NONE: Final = {"": 0, **_FRACTION_US}  # "hhmmss" has no fraction


def _fill_times(memo: dict[str, Any], keys: Iterable[str]) -> None:
    """``_fill(memo, keys, _time_of_day)``, the usual forms all at once from its tables:
    a time whose minute, second or fraction is not a key of them is parsed alone."""
    new = _new_keys(memo, keys)
    if not new:
        return
    minutes = map(_MINUTE_US.get, map(_MINUTE_OF, new))
    seconds = map(_SECOND_US.get, map(_SECOND_OF, new))
    fractions = map(_FRACTION_OR_NONE.get, map(_FRACTION_OF, new))
    parts = list(zip(minutes, seconds, fractions, strict=True))
    if any(map(operator.contains, parts, repeat(None))):
        usual = [p if None not in p else None for p in parts]
        for key, part in zip(new, usual, strict=True):
            if part is None:
                try:
                    memo[key] = _time_of_day(key)
                except ValueError:
                    memo[key] = _BAD
        new = [k for k, p in zip(new, usual, strict=True) if p is not None]
        parts = [p for p in usual if p is not None]
    memo.update(zip(new, map(sum, parts), strict=True))  # type: ignore[arg-type]


# A position in its usual form: two (lat) or three (lon) digits of degrees below 90 or 180,
# minutes below 60 with decimals, a hemisphere letter. For these _coord_parser's checks
# hold but one (minutes that round to 60.0), checked after.
_USUAL_POSITION: Final = re.compile(
    r"^(([0-8][0-9])([0-5][0-9]\.[0-9]+),([NS]),"
    r"(0[0-9][0-9]|1[0-7][0-9])([0-5][0-9]\.[0-9]+),([EW]))$",
    re.M,
)
_SIGN: Final = {"N": 1.0, "S": -1.0, "E": 1.0, "W": -1.0}  # -v is v * -1.0, exactly
_DEG9: Final = "%.9f".__mod__
_LAT_LON: Final = ',"lat":%s,"lon":%s'.__mod__


def _degrees(degrees: Iterable[str], minutes: list[float], hemis: Iterable[str]) -> list[float]:
    """Signed degrees as _coord_parser computes them: degrees + minutes / 60, negated in
    the southern or western hemisphere."""
    unsigned = map(operator.add, map(int, degrees), map(operator.truediv, minutes, repeat(60.0)))
    return list(map(operator.mul, unsigned, map(_SIGN.__getitem__, hemis)))


def _texts9(values: list[float]) -> list[str]:
    """``_num_text(v, 9)`` of each value: ``"%.9f"`` without trailing zeros by columns, a
    value below 1e-3 in magnitude or whole through ``_num_text`` (its other branches)."""
    texts = list(map(str.rstrip, map(_DEG9, values), repeat("0")))
    if min(map(abs, values)) < 1e-3 or any(map(str.endswith, texts, repeat("."))):
        for i, v in enumerate(values):
            if abs(v) < 1e-3 or texts[i][-1] == ".":
                texts[i] = cast("str", _num_text(v, 9))  # (finite: never None)
    return texts


def _fill_positions(memo: dict[str, Any], keys: Iterable[str]) -> None:
    """``_fill(memo, keys, _position_of)``, positions in their usual form all at once (the
    numbers converted and written by whole columns), any other alone."""
    new = _new_keys(memo, keys)
    if not new:
        return
    # One findall over the keys joined; each match is a whole key (anchored), first group.
    usual = _USUAL_POSITION.findall("\n".join(new))
    others: Iterable[str] = (
        () if len(usual) == len(new) else set(new).difference(map(_FIRST, usual))
    )
    alone: Iterable[str] = ()
    if usual:
        found, lat_d, lat_m, ns, lon_d, lon_m, ew = zip(*usual, strict=True)
        lat_min = list(map(float, lat_m))
        lon_min = list(map(float, lon_m))
        if max(lat_min) < 60.0 and max(lon_min) < 60.0:
            lats = _degrees(lat_d, lat_min, ns)
            lons = _degrees(lon_d, lon_min, ew)
            texts = map(_LAT_LON, zip(_texts9(lats), _texts9(lons), strict=True))
            memo.update(zip(found, zip(lats, lons, texts, strict=True), strict=True))
        else:
            alone = found
    for key in chain(alone, others):
        try:
            memo[key] = _position_of(key)
        except ValueError:
            memo[key] = _BAD


_GSV_GROUPS: Final = re.compile(r"([^,]*+,[^,]*+,[^,]*+,[^,]*+)(?:,|\Z)")
_GSV_GROUPS_MAX: Final = 9  # most groups of a GSV cut whole by _gsv_cut


@functools.cache
def _gsv_cut(k: int, signal: int = 0) -> re.Pattern[str]:
    """A GSV of exactly k satellite groups and after them nothing, or (``signal`` 1) one
    field, NMEA 4.10's signal id: talker, the three head fields, each group's text (as
    gsv_groups cuts them), the signal id."""
    group = ",([^,]*,[^,]*,[^,]*,[^,*]*)"
    tail = ",([^,*]*)" if signal else ""
    return re.compile(rf"\$(..)GSV,({_F},{_F},{_F}){group * k}{tail}\*..")


def _matches(pattern: re.Pattern[str], texts: list[str], joined: str | None = None) -> list[Any]:
    """``pattern``'s groups in each of ``texts`` (all of one sentence type), or None for a
    text it does not match: one ``findall`` over the texts joined (``joined``, if given:
    ``"\\n".join(texts)``) when every text matches once, else one match per text."""
    found = pattern.findall("\n".join(texts) if joined is None else joined)
    if len(found) == len(texts):  # no match spans two lines, so each is its line's
        return found
    matches = [pattern.fullmatch(text) for text in texts]
    if pattern.groups == 1:
        return [None if m is None else m.group(1) for m in matches]
    return [None if m is None else m.groups("") for m in matches]


def _per_text(
    parse: Callable[[list[str]], list[Any]], texts: list[str], groups: list[Any]
) -> list[Any]:
    """The events of ``texts`` of which some do not match their cut (``groups`` None): those
    take the reference's path (their event is their text), the others ``parse``."""
    matched = iter(parse([t for t, g in zip(texts, groups, strict=True) if g is not None]))
    return [t if g is None else next(matched) for t, g in zip(texts, groups, strict=True)]


def _unparsed(events: list[Any], texts: list[str]) -> list[Any]:
    """``events`` with the text in place of each event that holds ``_BAD``."""
    return [
        t if e is _BAD or (type(e) is tuple and _BAD in e) else e
        for e, t in zip(events, texts, strict=True)
    ]


def _phases(codes: list[_T]) -> list[_T] | None:
    """The codes of one cycle if ``codes`` repeats one of at most ``_PERIOD_MAX`` sentences
    (``codes[i] == codes[i % p]``), else None."""
    n = len(codes)
    if n == 0:  # a read of UBX frames only
        return None
    p = 0
    while True:
        try:
            p = codes.index(codes[0], p + 1)
        except ValueError:
            return None
        if p > _PERIOD_MAX or p >= n:
            return None
        if codes[p : p + 256] == codes[: min(256, n - p)] and codes[p:] == codes[: n - p]:
            return codes[:p]


def _cycle(texts: list[str]) -> tuple[list[str], list[str | None]] | None:
    """(the heads of one cycle, each place's texts joined by "\\n") if the sentences repeat
    one cycle of heads (``text[1:7]``, at most ``_PERIOD_MAX`` sentences) and are all
    ASCII, else None. The cycle is found among the first heads; the rest is checked
    without a head per sentence: the texts of a place joined, whose every line must
    start with that place's head (a text holds one "$", its first character)."""
    n = len(texts)
    if n < _CYCLE_MIN:
        return None
    first = list(map(_HEAD, texts[: 2 * _PERIOD_MAX]))
    phases = _phases(first)
    if phases is None:
        return None
    period = len(phases)
    joined: list[str | None] = []
    for k, head in enumerate(phases):
        text = "\n".join(texts[k::period])
        lines = len(range(k, n, period))
        if not (
            text.startswith(head, 1) and text.count("\n$" + head) == lines - 1 and text.isascii()
        ):
            return None
        joined.append(text)
    return phases, joined


def _gsa_values(talker: str, body: str) -> _GsaValues:
    """A GSA's values from its talker and the text of its fields (``body``): ``_parse_gsa``
    of the fields, split and padded as the reference's handler gets them, and of the rest
    after VDOP (NMEA 4.10's system id)."""
    fields = body.split(",", _GSA_FIELDS)
    if len(fields) < _GSA_FIELDS:
        fields += [""] * (_GSA_FIELDS - len(fields))
    rest = fields[_GSA_FIELDS] if len(fields) > _GSA_FIELDS else ""
    return _parse_gsa(talker, tuple(fields[_GSA_MODE:_GSA_FIELDS]), rest)


def _gsa_values_of(key: str) -> _GsaValues:
    """``_gsa_values`` of a GSA's text from its talker to its last field (``text[1:-3]``)."""
    return _gsa_values(key[:2], key[6:])


def _whole_group(
    phases: list[int], values: list[list[Any]], k: int, full: int
) -> tuple[int, list[tuple[str, tuple[_SatTexts, ...]]]] | None:
    """(number of parts, each cycle's talker and satellites) if the GSVs at places ``k``,
    ``k + 1``, ... of a cycle are, in each of the ``full`` cycles, the parts 1..m of one
    group of m from one talker, all parsed; else None."""
    first = values[k][:full]
    if str in map(type, first):
        return None
    total = first[0][1][0]
    if k + total > len(phases) or phases[k : k + total] != [_DO_GSV] * total:
        return None
    parts = [values[k + i][:full] for i in range(total)]
    talkers = list(map(_FIRST, first))
    sats = list(map(_THIRD, first))
    for i, part in enumerate(parts):
        if str in map(type, part) or set(map(_SECOND, part)) != {(total, i + 1)}:
            return None
        if i:
            if list(map(_FIRST, part)) != talkers:
                return None
            sats = list(map(operator.add, sats, map(_THIRD, part)))
    return total, list(zip(talkers, sats, strict=True))


def _same_time(phases: list[int], values: list[list[Any]], k: int, full: int) -> bool:
    """Whether the GLLs at place ``k`` of each of the ``full`` cycles have the time the
    epoch has then: that of the nearest RMC, GGA or GLL before it in the cycle, which set
    it, with only GSA, GSV or counted-only sentences between."""
    gll = values[k][:full]
    if str in map(type, gll):
        return False
    gll_tods = list(map(_FIRST, gll))  # (its events: time of day, position or None)
    if None in gll_tods:
        return False
    for j in range(k - 1, -1, -1):
        code = phases[j]
        if code in (_SKIP, _DO_GSA, _DO_GSV):
            continue
        if code not in (_DO_RMC, _DO_GGA, _DO_GLL):
            return False
        column = values[j][:full]
        if str in map(type, column):
            return False
        tods = list(map(_FIRST, column))
        return None not in tods and tods == gll_tods
    return False


_FIRST: Final = operator.itemgetter(0)
_SECOND: Final = operator.itemgetter(1)
_THIRD: Final = operator.itemgetter(2)


def _sat_of(system: int, group: str) -> _SatTexts | None:
    """The ``_SatTexts`` of one GSV group of a GSV of ``system`` (``gsv_values``, gpsd's
    numbering as ``drivers.gps_nmea._gsv_sat`` gives it; None without a PRN)."""
    values = gsv_values(group)
    if values is None:
        return None
    number, el, az, snr = values
    prn, gnssid, svid = gpsd_satellite(system, number)
    return (prn if snr else 0, *_sat_texts(prn, el, az, snr, gnssid, svid))


@functools.cache
def _sat_filler(system: int) -> Callable[[dict[str, Any], Sequence[str]], None]:
    """``_fill`` with ``_sat_of`` of ``system``, for ``_read``."""
    return _filler(functools.partial(_sat_of, system))


def _signal_or_bad(text: str) -> str | object:
    """``gsv_signal(text)``, or ``_BAD`` where it raises."""
    try:
        return gsv_signal(text)
    except ValueError:
        return _BAD


_FILL_GGA_TAIL: Final = _filler(_gga_tail_of)
_FILL_RMC_TAIL: Final = _filler(_rmc_tail_of)
_FILL_GSA: Final = _filler(_gsa_values_of)
_FILL_GSV_HEAD: Final = _filler(_gsv_counts_of)
_FILL_ZDA_DATE: Final = _filler(_zda_date_of)


class ReportDecoder(GpsDecoder):
    """``GpsDecoder``'s epochs and counters, its fixes and sky reports written as their TPV
    and SKY lines (``str``, in ``out``), the sentences of a read decoded in bulk.

    Most sentences of a receiver are GGA, RMC, GSA, GSV, GLL and ZDA. Of the sentences one
    read frames (``_decode``), those of each of these types are cut into the groups of
    fields their handlers read by one regex over their texts joined (``_matches``,
    ``_gsv_cut``), and each group's value is read from a memo by its text, the texts new
    to it parsed once each, by whole columns where the form is the usual one (``_read``,
    ``_fill_times``, ``_fill_positions``): a time; a position (lat, lon and their TPV
    members, which GGA, RMC and GLL of an epoch repeat); GGA's quality to geoid separation;
    RMC's speed and track members and date; a ZDA's date; a GSV's head and satellites; a
    GSA. A receiver repeats one cycle of sentences: then each place's texts are a slice of
    the read, found without a head per sentence (``_cycle``), and whole cycles need fewer
    events (``_cycle_events``: counted-only sentences left out, a GLL at its epoch's time
    too, a GSV group's parts as one). Then one loop (``_run_events``) runs
    ``GpsDecoder``'s epoch logic inline over the events in order, compact tuples
    (``_GgaTuple``, ``_RmcTuple``); a sentence whose groups do not parse, of another type
    (proprietary, unknown or odd heads, not ASCII) or of a small read takes
    ``GpsDecoder._decode``, whose GGA and RMC handlers here build the same tuples. Every
    field a handler reads is parsed before any state changes, so the counters and epochs
    are the reference's.

    A fix's line is written from the tuples with the texts memoised beside the values, its
    altitude and error members kept while the GGA fields, GSA mode and VDOP are the same
    (``_emit``, ``ReportEncoder.fix_tail``); a satellite goes from its GSV group straight
    to its two possible JSON texts, the one a sky report takes kept while the PRNs used
    are the same, so a sky report is one join of texts (``_emit_sky``); an epoch's time
    member is written from the time of day and the date's text without a datetime where
    that is exact (``_time_member``). Without ``with_sky`` the sky reports are counted and
    not written. tests/test_decode_bulk.py compares the lines and counters with the
    reference decoder's records through ``tpv_obj``/``sky_obj`` in the same run.
    """

    _gga: _GgaTuple | None  # type: ignore[assignment]
    _rmc: _RmcTuple | None  # type: ignore[assignment]

    def __init__(
        self, encoder: ReportEncoder, *, with_sky: bool = True, accept_unchecksummed: bool = False
    ) -> None:
        super().__init__(emit_sentences=False, accept_unchecksummed=accept_unchecksummed)
        self._encoder = encoder
        self._with_sky = with_sky
        # A GSV group's text -> its _SatTexts, per system (talker_system: the same text is
        # another satellite in another system), for the reference's path (_sats_of).
        self._sat_texts: dict[int, dict[str, _SatTexts]] = {}
        # GSA: the handler gets the text of the fields unsplit (most splits 0), see _gsa_text.
        self._handlers["GSA"] = (self._gsa_text, 1, 0)
        # _time_member's last (time of day, date, date's time of day) and its text.
        self._member_tod: int | None = None
        self._member_day: date | None = None
        self._member_day_tod: int | None = None
        self._member = ""
        # _emit's last GGA fields (by identity), GSA mode and VDOP, and its line's parts
        # from them (head, altitudes, error estimates); _emit_sky's last DOPs and members.
        self._fix_tail: _GgaTail | None = None
        self._fix_mode: int | None = None
        self._fix_vdop: float | None = None
        self._fix_parts = ("", "", "")
        self._sky_hdop: float | None = None
        self._sky_vdop: float | None = None
        self._sky_pdop: float | None = None
        self._sky_dops = encoder.dops(None, None, None)
        self._chosen: dict[Any, str] = {}  # see _emit_sky
        self._chosen_used: frozenset[int] | None = None
        self._ubx_counted = 0  # the framer's UBX count when _decode last took frames
        # Sentence head -> _SKIP .. _REFERENCE (bounded like the reference's routes).
        self._codes: dict[str, int] = {}
        # The memos of the bulk path, by the text of their fields (see _fill).
        self._times: dict[str, int | None] = {}
        self._positions: dict[str, _Position] = {}
        self._gga_tails: dict[str, _GgaTail] = {}
        self._rmc_tails: dict[str, _RmcTail] = {}
        self._gsv_heads: dict[str, tuple[int, int]] = {}
        self._zda_dates: dict[str, date | object | None] = {}
        self._gsv_sat_memos: dict[int, dict[str, _SatTexts | None]] = {}  # likewise
        self._gsa_memo: dict[str, _GsaValues] = {}
        # The bulk parser of each type, by code.
        self._bulk: dict[int, Callable[[list[str], str | None], list[Any]]] = {
            _DO_GGA: self._ggas,
            _DO_RMC: self._rmcs,
            _DO_GSA: self._gsas,
            _DO_GSV: self._gsvs,
            _DO_GLL: self._glls,
            _DO_ZDA: self._zdas,
        }

    # -- the bulk path

    def _decode(self, frames: list[str | UbxFrame], t_s: float, out: list[GpsOutput]) -> None:
        """``GpsDecoder._decode`` of ``frames``: same counters, epochs and state."""
        if len(frames) < _BULK_MIN:
            super()._decode(frames, t_s, out)
            return
        ubx_frames = self.framer.counters.ubx_frames
        if ubx_frames == self._ubx_counted:  # the framer found no UBX frame since
            texts = cast("list[str]", frames)
        else:
            texts = [f for f in frames if type(f) is str]
            self._ubx.extend(f for f in frames if type(f) is not str)  # type: ignore[misc]
            self._ubx_counted = ubx_frames
        cycle = _cycle(texts)
        if cycle is not None:  # the heads repeat one cycle: each place's texts a slice
            heads, joined = cycle
            phases = list(map(self._code_of, heads))
            period = len(phases)
            n_bulk = sum(
                len(range(k, len(texts), period)) for k, c in enumerate(phases) if c != _REFERENCE
            )
            codes, events = self._cycle_events(texts, phases, joined)
        else:
            heads = list(map(_HEAD, texts))
            codes = list(map(self._codes.get, heads))  # type: ignore[arg-type]
            if None in codes:  # (_codes is bounded: the read's heads in a dict of its own)
                known = {h: self._code_of(h) for h in set(heads)}
                codes = list(map(known.__getitem__, heads))
            if not "".join(texts).isascii():  # the reference's path counts them invalid
                ascii_ = list(map(str.isascii, texts))
                codes = [c if a else _REFERENCE for c, a in zip(codes, ascii_, strict=True)]
            n_bulk = len(codes) - codes.count(_REFERENCE)
            codes, events = self._events(texts, codes)
        self._run_events(codes, events, n_bulk, t_s, out)

    def _events(self, texts: list[str], codes: list[int]) -> tuple[list[int], list[Any]]:
        """The codes and events the loop (``_run_events``) takes, in order: a sentence's
        parsed groups (a type read in bulk), its text (the reference's path); counted-only
        sentences are left out. A read whose codes repeat one cycle takes
        ``_cycle_events``."""
        phases = _phases(codes)
        if phases:
            period = len(phases)
            return self._cycle_events(texts, phases, [None] * period)
        bulk = self._bulk
        by_code: dict[int, list[str]] = {}
        for text, code in zip(texts, codes, strict=True):
            try:
                by_code[code].append(text)
            except KeyError:
                by_code[code] = [text]
        by_code.pop(_SKIP, None)  # counted only: left out
        codes = list(compress(codes, codes))  # (_SKIP is 0)
        iters: list[Iterator[Any]] = [iter(())] * (_REFERENCE + 1)
        for code, part in by_code.items():
            parse = bulk.get(code)
            iters[code] = iter(part if parse is None else parse(part, None))
        return codes, list(map(next, map(iters.__getitem__, codes)))

    def _cycle_events(
        self, texts: list[str], phases: list[int], joined: Sequence[str | None]
    ) -> tuple[list[int], list[Any]]:
        """``_events`` of a read whose sentences repeat one cycle of codes (``phases``; the
        texts of place k of the cycle ``texts[k::period]``, joined by "\\n" in
        ``joined[k]`` where known): whole cycles need fewer events: counted-only sentences
        are left out, so is a GLL whose time is that of the RMC or GGA before it in the
        cycle (the epoch is already that time), and the parts of a GSV group that fills
        consecutive places of the cycle are one event (``_DO_SKY``: what the parts do one
        after the other)."""
        n = len(texts)
        bulk = self._bulk
        period = len(phases)
        full = n // period
        values = []
        for k, code in enumerate(phases):
            part = texts[k::period]
            parse = bulk.get(code)
            values.append(part if parse is None else parse(part, joined[k]))
        # Whole cycles: the codes and columns of the events each takes.
        plan_codes: list[int] = []
        columns: list[list[Any]] = []
        k = 0
        while k < period:
            code = phases[k]
            column = values[k][:full]
            if code == _SKIP:
                k += 1
                continue
            if code == _DO_GSV:
                group = _whole_group(phases, values, k, full)
                if group is not None:
                    size, merged = group
                    plan_codes.append(_DO_SKY)
                    columns.append(merged)
                    k += size
                    continue
            elif code == _DO_GLL and _same_time(phases, values, k, full):
                k += 1
                continue
            plan_codes.append(code)
            columns.append(column)
            k += 1
        events = list(chain.from_iterable(zip(*columns, strict=True))) if columns else []
        # The cycle cut by the end of the read: each sentence its own event.
        rest = range(n - full * period)
        codes = plan_codes * full + [phases[k] for k in rest]
        return codes, events + [values[k][full] for k in rest]

    def _run_events(
        self, codes: list[int], events: list[Any], n_bulk: int, t_s: float, out: list[GpsOutput]
    ) -> None:
        """GpsDecoder's epoch logic over the events of ``_events`` in order: ``_on_gga``,
        ``_on_rmc``, ``_on_time``, ``_set_gsa`` and ``_gsv_fields`` after their fields are
        read, inline (``_on_gga_tuple`` etc. are the same for the reference's path).
        ``n_bulk`` sentences are counted as decoded, less those that take the reference's
        path here (which counts them)."""
        c = self._counters
        reference = super()._decode
        emit = self._emit
        emit_sky = self._emit_sky
        n_failed = 0
        try:
            for code, event in zip(codes, events, strict=True):
                if code == _SKIP:
                    continue
                if code == _REFERENCE:
                    reference([event], t_s, out)
                    continue
                if type(event) is str:  # its groups did not parse
                    n_bulk -= 1
                    reference([event], t_s, out)
                    continue
                try:
                    if code == _DO_GGA:  # _on_gga
                        tod = event[0]
                        self._epochs_without_gga = 0
                        self._ggas_seen += 1
                        if tod is None:
                            emit(event, None, out)
                            continue
                        if tod != self._tod_us:  # _on_time
                            if self._gga is not None or self._rmc is not None or self._gll:
                                self._close_epoch(out)
                            self._tod_us = tod
                            self._gsa_fresh = False
                            self._epoch_idx += 1
                        rmc = self._rmc
                        if rmc is not None and rmc[0] == tod:
                            self._rmc = None
                            self._rmc_after_gga = False
                            emit(event, rmc, out)
                        elif self._rmc_after_gga or (self._rmcs_seen == 0 and self._ggas_seen == 1):
                            self._gga = event
                        else:
                            emit(event, None, out)
                    elif code == _DO_RMC:  # _on_rmc
                        tod = event[0]
                        self._rmcs_seen += 1
                        day = event[3][1]
                        if tod is None:
                            if self._epochs_without_gga > _GGA_MEMORY_EPOCHS:
                                emit(None, event, out)
                            continue
                        if tod != self._tod_us:
                            self._epochs_without_gga += 1
                            if self._gga is not None or self._rmc is not None or self._gll:
                                self._close_epoch(out)  # with its own date
                            self._tod_us = tod
                            self._gsa_fresh = False
                            self._epoch_idx += 1
                        if day is not None:
                            self._date = day
                            self._date_tod_us = tod
                        gga = self._gga
                        if gga is not None and gga[0] == tod:
                            self._gga = None
                            self._rmc_after_gga = True
                            emit(gga, event, out)
                        elif self._last_fix_tod == tod and self._last_fix_had_gga:
                            self._rmc_after_gga = True
                        elif self._epochs_without_gga > _GGA_MEMORY_EPOCHS:
                            emit(None, event, out)
                        else:
                            self._rmc = event
                    elif code == _DO_SKY:  # a whole GSV group: its parts one after the other
                        talker, sats = event
                        self._gsv_talker = talker
                        self._gsv_next = 0
                        self._sky[talker] = (self._epoch_idx, sats)
                        emit_sky(t_s, out)
                    elif code == _DO_GSA:  # _set_gsa
                        mode, used, pdop, hdop, vdop = event
                        if self._gsa_fresh:
                            self._used |= used
                        else:
                            self._used = used
                            self._gsa_fresh = True
                        self._gsa_mode = mode
                        self._pdop = pdop
                        self._hdop_gsa = hdop
                        self._vdop = vdop
                    elif code == _DO_GSV:  # GpsDecoder._gsv_fields after its fields are read
                        talker, (total, seq), sats = event
                        if seq == 1:
                            self._gsv_talker = talker
                            self._gsv_sats = list(sats)
                        elif seq == self._gsv_next and talker == self._gsv_talker:
                            self._gsv_sats.extend(sats)
                        else:  # a lost part: drop the group
                            self._gsv_next = 0
                            continue
                        if seq == total:
                            self._gsv_next = 0
                            self._sky[talker] = (self._epoch_idx, self._gsv_sats)
                            self._gsv_sats = []
                            emit_sky(t_s, out)
                        else:
                            self._gsv_next = seq + 1
                    elif code == _DO_ZDA:  # _on_zda
                        tod, day = event
                        if tod is not None and day is not None:  # (not _NO_DATE: _zdas)
                            self._date = day
                            self._date_tod_us = tod
                        self._on_time(tod, out)
                    else:  # _DO_GLL
                        tod, position = event
                        if tod is not None and tod != self._tod_us:
                            self._on_time(tod, out)
                        if position is not None:
                            self._gll = (t_s, tod, position[0], position[1])
                except (IndexError, ValueError):  # as the reference's loop
                    c.invalid_fields += 1
                    n_failed += 1
        finally:
            c.sentences += n_bulk
            c.decoded += n_bulk - n_failed

    def _code_of(self, key: str) -> int:
        """The code of sentence head ``key`` (``_codes``, or ``_code`` on a miss)."""
        try:
            return self._codes[key]
        except KeyError:
            return self._code(key)

    def _code(self, key: str) -> int:
        """The ``_codes`` entry for sentence head ``key`` (computed and stored on a miss)."""
        route = self._route(key)
        if route is None:
            code = _REFERENCE
        elif route[1] is None:
            code = _SKIP
        else:
            code = _KIND_CODES.get(key[2:5], _REFERENCE)
        if len(self._codes) >= _HEADS_MAX:
            self._codes.clear()
        self._codes[key] = code
        return code

    # -- each type's groups, in bulk: one event per text, the text itself where they fail

    def _tods(self, texts: Iterable[str]) -> list[Any]:
        """The times of day of time fields (``_time_of_day``; ``_BAD`` if bad)."""
        texts = list(texts)
        return _read(self._times, texts, _fill_times)

    def _ggas(self, texts: list[str], joined: str | None = None) -> list[Any]:
        groups = _matches(_GGA_CUT, texts, joined)
        if None in groups:
            return _per_text(self._ggas, texts, groups)
        tods_text, positions_text, tails_text = zip(*groups, strict=True)
        tods = self._tods(tods_text)
        positions = _read(self._positions, positions_text, _fill_positions)
        tails = _read(self._gga_tails, tails_text, _FILL_GGA_TAIL)
        events = list(zip(tods, positions, tails, strict=True))
        if _BAD in tods or _BAD in positions or _BAD in tails:
            return _unparsed(events, texts)
        return events

    def _rmcs(self, texts: list[str], joined: str | None = None) -> list[Any]:
        groups = _matches(_RMC_CUT, texts, joined)
        if None in groups:
            return _per_text(self._rmcs, texts, groups)
        tods_text, status, positions_text, tails_text = zip(*groups, strict=True)
        tods = self._tods(tods_text)
        valid = list(map(_STATUS_VALID.get, status, repeat(_BAD)))
        positions = _read(self._positions, positions_text, _fill_positions)
        tails = _read(self._rmc_tails, tails_text, _FILL_RMC_TAIL)
        events = list(zip(tods, valid, positions, tails, strict=True))
        if _BAD in tods or _BAD in valid or _BAD in positions or _BAD in tails:
            return _unparsed(events, texts)
        return events

    def _gsas(self, texts: list[str], joined: str | None = None) -> list[Any]:
        # Keyed by the talker too: it names the system of the PRNs (BD 13 is 413).
        keys = list(map(_GSA_KEY, texts))
        events = _read(self._gsa_memo, keys, _FILL_GSA)
        return _unparsed(events, texts) if _BAD in events else events

    def _gsvs(self, texts: list[str], joined: str | None = None) -> list[Any]:
        """A GSV's event: its group's key (talker and NMEA 4.10 signal id: one group per
        talker and signal), message count and number, satellites."""
        whole = self._whole_gsvs(texts, joined)
        if whole is not None:
            return whole
        groups = _matches(_GSV_CUT, texts, joined)
        if None in groups:
            return _per_text(self._gsvs, texts, groups)
        talkers, heads, rests = zip(*groups, strict=True)
        talker = talkers[0]
        if talkers.count(talker) != len(talkers):  # the talker decides the PRNs: one each
            return self._gsvs_by_talker(texts, talkers)
        counts = _read(self._gsv_heads, heads, _FILL_GSV_HEAD)
        signals = list(map(_signal_or_bad, rests))
        keys = list(map(talker.__add__, signals)) if _BAD not in signals else signals
        sats = self._gsv_sats_of(rests, talker_system(talker))
        if _PER_TEXT in sats:
            sats = [
                self._sats_or_bad(talker, r) if s is _PER_TEXT else s
                for s, r in zip(sats, rests, strict=True)
            ]
        events = list(zip(keys, counts, sats, strict=True))
        if _BAD in counts or _BAD in sats or _BAD in keys:
            return _unparsed(events, texts)
        return events

    def _gsvs_by_talker(self, texts: list[str], talkers: tuple[str, ...]) -> list[Any]:
        """``_gsvs`` of GSVs of several talkers: each talker's apart, in order."""
        by_talker: dict[str, list[str]] = {}
        for text, talker in zip(texts, talkers, strict=True):
            by_talker.setdefault(talker, []).append(text)
        parsed = {t: iter(self._gsvs(part)) for t, part in by_talker.items()}
        return [next(parsed[t]) for t in talkers]

    def _whole_gsvs(self, texts: list[str], joined: str | None) -> list[Any] | None:
        """``_gsvs`` of GSVs of one talker that all hold the same number k of whole
        satellite groups and no other field but an NMEA 4.10 signal id (a place of a cycle,
        mostly): head, groups and signal cut by one findall (``_gsv_cut(k, signal)``), the
        satellites read by columns. None otherwise."""
        k, extra = divmod(texts[0].count(",") - 3, 4)
        if extra > 1 or not 1 <= k <= _GSV_GROUPS_MAX:
            return None
        found = _gsv_cut(k, extra).findall("\n".join(texts) if joined is None else joined)
        if len(found) != len(texts):
            return None
        columns = list(zip(*found, strict=True))
        talkers = columns[0]
        talker = talkers[0]
        if talkers.count(talker) != len(talkers):
            return None
        keys: Sequence[str] = talkers
        if extra:  # the signal ids: each talker's group per signal
            signals = columns.pop()
            if any(map(str.strip, set(signals), repeat(SIGNAL_DIGITS))):
                return None  # not an id: the reference's path rejects it
            keys = list(map(talker.__add__, signals))
        counts = _read(self._gsv_heads, columns[1], _FILL_GSV_HEAD)
        system = talker_system(talker)
        memo = self._gsv_sat_memos.setdefault(system, {})
        _fill(memo, chain.from_iterable(columns[2:]), functools.partial(_sat_of, system))
        sats = [list(map(memo.__getitem__, column)) for column in columns[2:]]
        if any(None in column or _BAD in column for column in sats) or _BAD in counts:
            return None
        return list(zip(keys, counts, zip(*sats, strict=True), strict=True))

    def _glls(self, texts: list[str], joined: str | None = None) -> list[Any]:
        """A GLL's event: (its time of day, its position when it is a valid one, else
        None), as ``GpsDecoder._gll_fields`` reads them."""
        groups = _matches(_GLL_CUT, texts, joined)
        if None in groups:
            return _per_text(self._glls, texts, groups)
        positions_text, times, status, modes = zip(*groups, strict=True)
        tods = self._tods(times)
        valid = [
            tod is not None and st == "A" and mode[:1] != "N"
            for tod, st, mode in zip(tods, status, modes, strict=True)
        ]
        found = iter(_read(self._positions, list(compress(positions_text, valid)), _fill_positions))
        events = [(tod, next(found) if v else None) for tod, v in zip(tods, valid, strict=True)]
        return _unparsed(events, texts)

    def _zdas(self, texts: list[str], joined: str | None = None) -> list[Any]:
        groups = _matches(_ZDA_CUT, texts, joined)
        if None in groups:
            return _per_text(self._zdas, texts, groups)
        tods_text, dates_text = zip(*groups, strict=True)
        tods = self._tods(tods_text)
        dates = _read(self._zda_dates, dates_text, _FILL_ZDA_DATE)
        events = list(zip(tods, dates, strict=True))
        if _BAD in tods or _BAD in dates or _NO_DATE in dates:
            # _on_zda raises for a bad field, and for no date only with a time
            return [
                t if e[0] is _BAD or e[1] is _BAD or (e[1] is _NO_DATE and e[0] is not None) else e
                for e, t in zip(events, texts, strict=True)
            ]
        return events

    def _gsv_sats_of(self, rests: tuple[str, ...], system: int) -> list[Any]:
        """The satellites of GSVs from the text of their satellite fields (``rests``), each
        GSV's a tuple, all at once: the groups of four fields (as ``_sats_of`` cuts them)
        by one ``findall`` over the texts joined by commas when each is of whole groups,
        else one per text; each group's satellite from a memo (``_sat_of``; ``system``,
        the GSVs' talker's). ``_PER_TEXT`` for a text whose last group is partial or a group
        no satellite (``_sats_of`` then reads it)."""
        memo = self._gsv_sat_memos.setdefault(system, {})
        fill = _sat_filler(system)
        commas = list(map(str.count, rests, repeat(",")))
        kinds = set(commas)
        if len(kinds) == 1 and kinds.pop() % 4 == 3:  # the same whole groups in each
            groups = _GSV_GROUPS.findall(",".join(rests))
            found = _read(memo, groups, fill)
            if None not in found and _BAD not in found:
                return list(zip(*[iter(found)] * ((commas[0] + 1) // 4), strict=True))
        per_text = list(map(_GSV_GROUP.findall, rests))
        counts = list(map(len, per_text))
        flat = list(chain.from_iterable(per_text))
        sats = _read(memo, flat, fill)
        ends = list(accumulate(counts))
        out = list(map(tuple, map(sats.__getitem__, map(slice, [0, *ends[:-1]], ends))))
        # gsv_groups adds a partial group to a text of 4k + 2 or 4k + 3 fields and fewer
        # than four groups (4k + 1: the last field is a signal id): such a text, or one
        # with a group that is no satellite, is read alone.
        whole = map((2).__gt__, map(operator.mod, map((1).__add__, commas), repeat(4)))
        if all(map(operator.or_, whole, map((4).__le__, counts))) and (
            None not in sats and _BAD not in sats
        ):
            return out
        return [
            _PER_TEXT
            if ((n_commas + 1) % 4 > 1 and len(part) < 4) or None in part or _BAD in part
            else part
            for n_commas, part in zip(commas, out, strict=True)
        ]

    def _sats_or_bad(self, talker: str, text: str) -> list[_SatTexts] | object:
        """``_sats_of(talker, text)``, or ``_BAD`` where it raises."""
        try:
            return tuple(self._sats_of(talker, text))
        except ValueError:
            return _BAD

    # -- the reference's handlers, for sentences that take its path

    def _gsa_text(self, talker: str, d: list[str], t_s: float, out: list[GpsOutput]) -> None:
        """A GSA from the text of its fields (``d[0]``), see ``_gsa_values``."""
        self._set_gsa(_gsa_values(talker, d[0]))

    def _gga_fields(self, talker: str, d: list[str], t_s: float, out: list[GpsOutput]) -> None:
        tod = _time_of_day(d[_GGA_TIME])
        lat = _gga_lat(d[_GGA_LAT], d[_GGA_LAT + 1])
        lon = _gga_lon(d[_GGA_LON], d[_GGA_LON + 1])
        tail = _gga_tail(d[_GGA_QUAL], d[_GGA_SATS], d[_GGA_HDOP], d[_GGA_ALT], d[_GGA_SEP])
        self._on_gga_tuple((tod, _position(lat, lon), tail), out)

    def _rmc_fields(self, talker: str, d: list[str], t_s: float, out: list[GpsOutput]) -> None:
        status = _rmc_status(d[_RMC_STATUS])
        tail = _rmc_tail(d[_RMC_SPEED], d[_RMC_COURSE], d[_RMC_DATE])
        tod = _time_of_day(d[_RMC_TIME])
        lat = _rmc_lat(d[_RMC_LAT], d[_RMC_LAT + 1])
        lon = _rmc_lon(d[_RMC_LON], d[_RMC_LON + 1])
        self._on_rmc_tuple((tod, status == "A", _position(lat, lon), tail), out)

    # -- epochs: GpsDecoder's logic over the tuples

    def _on_gga_tuple(self, gga: _GgaTuple, out: list[GpsOutput]) -> None:
        # GpsDecoder._on_gga
        self._epochs_without_gga = 0
        self._ggas_seen += 1
        tod = gga[0]
        if tod is None:
            self._emit(gga, None, out)
            return
        if tod != self._tod_us:
            self._on_time(tod, out)
        rmc = self._rmc
        if rmc is not None and rmc[0] == tod:
            self._rmc = None
            self._rmc_after_gga = False
            self._emit(gga, rmc, out)
        elif self._rmc_after_gga or (self._rmcs_seen == 0 and self._ggas_seen == 1):
            self._gga = gga
        else:
            self._emit(gga, None, out)

    def _on_rmc_tuple(self, rmc: _RmcTuple, out: list[GpsOutput]) -> None:
        # GpsDecoder._on_rmc
        self._rmcs_seen += 1
        tod = rmc[0]
        day = rmc[3][1]
        if tod is None:
            if self._epochs_without_gga > _GGA_MEMORY_EPOCHS:
                self._emit(None, rmc, out)
            return
        if tod != self._tod_us:
            self._epochs_without_gga += 1
            self._on_time(tod, out)  # an epoch of another time closes with its own date
        if day is not None:
            self._date = day
            self._date_tod_us = tod
        gga = self._gga
        if gga is not None and gga[0] == tod:
            self._gga = None
            self._rmc_after_gga = True
            self._emit(gga, rmc, out)
        elif self._last_fix_tod == tod and self._last_fix_had_gga:
            self._rmc_after_gga = True
        elif self._epochs_without_gga > _GGA_MEMORY_EPOCHS:
            self._emit(None, rmc, out)
        else:
            self._rmc = rmc

    def _close_epoch(self, out: list[GpsOutput]) -> None:
        # GpsDecoder._close_epoch
        gga = self._gga
        rmc = self._rmc
        gll = self._gll
        self._gga = None
        self._rmc = None
        self._gll = None
        if gga is not None:
            self._emit(gga, rmc if rmc is not None and rmc[0] == gga[0] else None, out)
        elif rmc is not None and rmc[0] != self._last_fix_tod:
            self._emit(None, rmc, out)
        elif gll is not None and gll[1] != self._last_fix_tod and self.gll_fixes:
            _t_s, tod, lat, lon = gll  # a valid GLL alone in its epoch: a fix without motion
            self._emit(None, (tod, True, _position(lat, lon), ("", None)), out)

    def _sats_of(self, talker: str, text: str) -> list[_SatTexts]:  # type: ignore[override]
        """The satellites of a GSV sentence's satellite fields ``text`` from ``talker`` (as
        ``_gsv_sats``: the same groups, skipped or rejected alike)."""
        system = talker_system(talker)
        memo = self._sat_texts.setdefault(system, {})
        groups = _GSV_GROUP.findall(text)
        if len(groups) >= 4 or (text.count(",") + 1) % 4 < 2:  # gsv_groups adds no group
            try:
                return list(map(memo.__getitem__, groups))  # every group seen before
            except KeyError:
                pass
        groups = gsv_groups(text)
        sats = []
        for group in groups:
            entry = memo.get(group)
            if entry is None:
                entry = _sat_of(system, group)
                if entry is None:
                    continue
                if len(memo) >= MEMO_MAX:
                    memo.clear()
                memo[group] = entry
            sats.append(entry)
        return sats

    def _time_member(self, tod: int | None) -> str:
        """``time_member(self._utc(tod))``: the epoch's time as the reports write it. For a
        time of day within 12 h of the date's own (the date is that day's) and not a leap
        second, of a year from 1000 on, that is the date's text and the time of day's
        hours, minutes, seconds and milliseconds (what ``_utc`` gives: midnight plus the
        time of day), from ``_iso_time``'s tables without a datetime; else through
        ``_utc``."""
        day = self._date
        day_tod = self._date_tod_us
        if tod is None or day is None or day_tod is None:
            return ""
        if tod == self._member_tod and day is self._member_day and day_tod == self._member_day_tod:
            return self._member  # fix and sky of one epoch
        if (
            day_tod - 43_200_000_000 <= tod <= day_tod + 43_200_000_000
            and tod < 86_400_000_000
            and day.year >= 1000
        ):
            ordinal = day.toordinal()
            day_text = _day_text.get(ordinal)
            if day_text is None:
                if len(_day_text) >= MEMO_MAX:
                    _day_text.clear()
                day_text = _day_text[ordinal] = day.isoformat() + "T"
            s, us = divmod(tod, 1_000_000)
            m, s = divmod(s, 60)
            text = f',"time":"{day_text}{_MINUTES[m]}{_SIXTY[s]}{_MILLIS[us // 1000]}"'
        else:
            text = self._encoder.time_member(self._utc(tod))
        self._member_tod, self._member_day, self._member_day_tod = tod, day, day_tod
        self._member = text
        return text

    def _emit(self, gga: _GgaTuple | None, rmc: _RmcTuple | None, out: list[GpsOutput]) -> None:  # type: ignore[override]
        # GpsDecoder._fix_head and _emit, writing the line instead of the record.
        if gga is not None:
            tod, (lat, lon, position), tail = gga
            valid = tail[0] > 0 and (rmc is None or rmc[1])
        else:
            assert rmc is not None
            tod, valid, (lat, lon, position), _ = rmc
            tail = None
        if lat is None or lon is None:
            valid = False
        if tod is not None:
            self._last_fix_tod = tod
            self._last_fix_had_gga = gga is not None
        self._counters.fixes += 1
        if (
            tod == self._member_tod
            and self._date is self._member_day
            and self._date_tod_us == self._member_day_tod
        ):
            time = self._member
        else:
            time = self._time_member(tod)
        if not valid:
            out.append(_TPV_STATUS_HEADS[0, 1] + time + "}")  # type: ignore[arg-type]
            return
        motion = "" if rmc is None else rmc[3][0]
        mode = self._gsa_mode
        vdop = self._vdop
        if (
            tail is not None
            and tail is self._fix_tail
            and mode is self._fix_mode
            and vdop is self._fix_vdop
        ):
            head, alt_text, err_text = self._fix_parts  # the same GGA fields, GSA mode and VDOP
        else:
            if tail is None:
                hdop = self._hdop_gsa
                alt = sep = None
            else:
                _, hdop, alt, sep = tail
            fix_mode = (
                mode if mode == 2 or mode == 3 else 3 if gga is not None and alt is not None else 2
            )
            alt_text, err_text = self._encoder.fix_tail(fix_mode, alt, sep, hdop, vdop)
            head = _tpv_head(0 if tail is None else tail[0], fix_mode)  # quality: status
            if tail is not None:
                self._fix_tail, self._fix_mode, self._fix_vdop = tail, mode, vdop
                self._fix_parts = head, alt_text, err_text
        out.append("".join((head, time, position, alt_text, motion, err_text, "}")))  # type: ignore[arg-type]

    def _emit_sky(self, t_s: float, out: list[GpsOutput]) -> None:
        # GpsDecoder._emit_sky, writing the line instead of the record.
        self._counters.skies += 1
        if not self._with_sky:
            return
        used = self._used
        # Each satellite's text as used or not, by the satellite (its memoised tuple), for
        # as long as the PRNs used are the same (a GSA repeated, or several merged alike).
        if used is not self._chosen_used:
            if used != self._chosen_used:
                self._chosen = {}
            self._chosen_used = used
        chosen = self._chosen
        texts: list[str] = []
        oldest = self._epoch_idx - 1  # a constellation that stopped reporting drops out
        for epoch_idx, group in self._sky.values():
            if epoch_idx >= oldest:
                try:
                    texts += list(map(chosen.__getitem__, group))
                except KeyError:
                    if len(chosen) > MEMO_MAX:
                        chosen.clear()
                    for sat in group:
                        prn, free, in_use = cast("_SatTexts", sat)
                        chosen[sat] = in_use if prn in used else free
                    texts += list(map(chosen.__getitem__, group))
        tod = self._tod_us
        if (
            tod == self._member_tod
            and self._date is self._member_day
            and self._date_tod_us == self._member_day_tod
        ):
            time = self._member  # the epoch's fix wrote it
        else:
            time = self._time_member(tod)
        hdop, vdop, pdop = self._hdop_gsa, self._vdop, self._pdop
        if hdop is not self._sky_hdop or vdop is not self._sky_vdop or pdop is not self._sky_pdop:
            self._sky_dops = self._encoder.dops(hdop, vdop, pdop)
            self._sky_hdop, self._sky_vdop, self._sky_pdop = hdop, vdop, pdop
        listed = ",".join(texts)
        line = (
            f'{{"class":"SKY"{time}{self._sky_dops},"nSat":{len(texts)},'
            f'"uSat":{listed.count(_USED)},"satellites":[{listed}]}}'
        )
        out.append(line)  # type: ignore[arg-type]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Register the ``decode`` options."""
    parser.add_argument(
        "files", nargs="+", metavar="FILE", help="NMEA log or recording; - is stdin"
    )
    parser.add_argument("--no-sky", action="store_true", help="print TPV reports only")
    parser.add_argument("--quiet", action="store_true", help="do not print counters on stderr")
    parser.add_argument(
        "--strict",
        action="store_true",
        help="refuse NMEA lines without a '*hh' checksum (by default they are decoded, as gpsd"
        " does, and counted as unchecksummed), as the robot's daemon does",
    )


def report_lines(records: Iterable[GpsOutput], *, with_sky: bool = True) -> Iterator[str]:
    """Compact JSON lines (no newline) for the fixes and sky reports among ``records``."""
    encoder = ReportEncoder()
    for r in records:
        if isinstance(r, GpsFix):
            yield encoder.tpv(r)
        elif with_sky and isinstance(r, GpsSky):
            yield encoder.sky(r)


def _write_reports(
    records: list[GpsOutput], encoder: ReportEncoder, out: IO[str], with_sky: bool
) -> None:
    """Write the lines of ``records`` to ``out`` in one call."""
    lines = []
    tpv, sky = encoder.tpv, encoder.sky
    for r in records:
        kind = type(r)
        if kind is GpsFix:
            lines.append(tpv(r))  # type: ignore[arg-type]
        elif kind is str:  # a line from ReportDecoder
            lines.append(r)  # type: ignore[arg-type]
        elif kind is GpsSky:
            if with_sky:
                lines.append(sky(r))  # type: ignore[arg-type]
        elif isinstance(r, GpsFix):
            lines.append(tpv(r))
        elif with_sky and isinstance(r, GpsSky):
            lines.append(sky(r))
    if lines:
        lines.append("")
        out.write("\n".join(lines))


def _recording_sentences(
    lines: Iterable[bytes | None], stats: ReadStats
) -> Iterator[tuple[float, str]]:
    """(t_s, text) of the raw NMEA records in recording lines; other records are skipped,
    lines that are not a JSON object (None: too long) skipped and counted in
    ``stats.bad_lines``.

    Accepts the recorder's ``{"t_mono":..,"type":"nmea","data":{"text":..}}`` and the flat
    ``{"type":"nmea","text":..}`` form.
    """
    for raw in lines:
        if raw is None:  # longer than any record
            stats.bad_lines += 1
            continue
        if not raw.strip():
            stats.blank_lines += 1
            continue
        try:
            obj = json.loads(raw)
        except (ValueError, UnicodeDecodeError):
            obj = None
        if not isinstance(obj, dict):
            stats.bad_lines += 1
            continue
        stats.records += 1
        if obj.get("type") != "nmea":
            continue
        data = obj.get("data")
        text = data.get("text") if isinstance(data, dict) else obj.get("text")
        t = obj.get("t_mono", 0.0)
        if isinstance(text, str):
            yield (float(t) if isinstance(t, (int, float)) else 0.0), text


def _decode_sentences(
    sentences: Iterable[tuple[float, str]], out: IO[str], with_sky: bool
) -> DecoderCounters:
    encoder = ReportEncoder()
    decoder = ReportDecoder(encoder, with_sky=with_sky)
    feed = decoder.feed_sentence
    records: list[GpsOutput] = []
    for t_s, text in sentences:
        records += feed(text, t_s)
        if len(records) >= 1024:
            _write_reports(records, encoder, out, with_sky)
            records = []
    records += decoder.flush()
    _write_reports(records, encoder, out, with_sky)
    return decoder.counters


def decode_stream(
    stream: IO[bytes],
    out: IO[str],
    *,
    with_sky: bool = True,
    stats: ReadStats | None = None,
    size: InputSize | None = None,
    strict: bool = False,
) -> DecoderCounters:
    """Decode one input (NMEA bytes or a recording) and write report lines to ``out``.
    A recording's lines that are not records are counted in ``stats``, a plain input's
    bytes in ``size`` (if given). NMEA lines without a checksum are decoded (as gpsd does)
    unless ``strict``."""
    from x6wd.core.recorder import (
        MAX_UNTIMED_HEAD_BYTES,
        InputSize,
        compression_of,
        looks_like_recording,
        regular_stream,
    )

    # a stream that may never end (/dev/zero, a FIFO of noise): given up after this much
    # without a sentence or UBX frame; a regular file ends, and is read to its end
    give_up = 0 if regular_stream(stream) else MAX_UNTIMED_HEAD_BYTES
    head = stream.read(_CHUNK_BYTES)
    compressed = compression_of(head)
    if compressed == "gzip":  # read through, a chunk at a time (size: the bytes decompressed)
        stream = cast("IO[bytes]", _Gunzip(head, stream))
        head = stream.read(_CHUNK_BYTES)
    elif compressed is not None:
        raise ParseError(f"compressed ({compressed}): decompress it first")
    if looks_like_recording(head):
        from x6wd.core.recorder import ReadStats

        st = stats if stats is not None else ReadStats()
        lines = _stream_lines(head, stream)
        return _decode_sentences(_recording_sentences(lines, st), out, with_sky)
    decoder = ReportDecoder(ReportEncoder(), with_sky=with_sky, accept_unchecksummed=not strict)
    size = size if size is not None else InputSize()
    chunk = head
    while chunk:
        size.add(chunk)
        _write_lines(decoder.feed(chunk, 0.0), out)
        if give_up and size.bytes > give_up:
            if not (decoder.counters.sentences or decoder.counters.ubx_frames):
                raise ParseError(
                    f"no NMEA sentence or UBX frame in its first {give_up >> 20} MiB and it"
                    " is not a regular file: given up (not a GPS log)"
                )
            give_up = 0
        chunk = stream.read(_CHUNK_BYTES)
    _write_lines(decoder.flush(), out)
    return decoder.counters


class _Prefixed(io.RawIOBase):
    """``head`` (a stream's first bytes, read already), then the rest of ``stream``."""

    def __init__(self, head: bytes, stream: IO[bytes]) -> None:
        self._head = memoryview(head)
        self._stream = stream

    def readable(self) -> bool:
        return True

    def readinto(self, b: Any) -> int:
        if self._head:
            n = min(len(b), len(self._head))
            b[:n] = self._head[:n]
            self._head = self._head[n:]
            return n
        data = self._stream.read(len(b))
        b[: len(data)] = data
        return len(data)


class _Gunzip:
    """The decompressed bytes of a gzip stream whose ``head`` was read already; a damaged
    or cut stream raises :class:`ParseError` (what came before it is decoded)."""

    def __init__(self, head: bytes, stream: IO[bytes]) -> None:
        import gzip

        self._z = gzip.GzipFile(fileobj=_Prefixed(head, stream), mode="rb")
        self._error: ParseError | None = None  # raised once the bytes before it are given

    def read(self, n: int) -> bytes:
        import zlib

        pieces: list[bytes] = []
        got = 0
        while got < n and self._error is None:
            try:
                piece = self._z.read1(n - got)
            except (OSError, EOFError, zlib.error) as exc:
                self._error = ParseError(f"compressed (gzip), damaged or cut: {exc}")
                break
            if not piece:
                break
            pieces.append(piece)
            got += len(piece)
        if not pieces and self._error is not None:
            raise self._error
        return b"".join(pieces)


def _stream_lines(head: bytes, stream: IO[bytes]) -> Iterator[bytes | None]:
    """The lines of ``head`` and the rest of ``stream`` (without their newlines), read a
    chunk at a time: a recording piped in (``decode -``) is held one chunk deep, not whole
    (112 MB took 264 MB). A line longer than ``recorder.MAX_RECORD_LINE_BYTES`` (no record:
    a card's garbage) is None, its bytes dropped as they come up to its newline, as the
    recording reader does for a file (a 100 MB line took 228 MB and quadratic time)."""
    from x6wd.core.recorder import MAX_RECORD_LINE_BYTES as limit

    pending = b""  # the start of a line a chunk's end cut (at most ``limit`` bytes)
    dropping = False  # inside an over-long line: its bytes up to the newline are dropped
    chunk = head
    while chunk:
        if dropping:
            end = chunk.find(b"\n")
            if end < 0:
                chunk = stream.read(_CHUNK_BYTES)
                continue
            dropping, chunk = False, chunk[end + 1 :]
        *lines, rest = chunk.split(b"\n")
        if lines:
            lines[0] = pending + lines[0]
            pending = rest
        else:
            pending += rest
        for line in lines:
            yield None if len(line) > limit else line
        if len(pending) > limit:
            yield None
            pending, dropping = b"", True
        chunk = stream.read(_CHUNK_BYTES)
    if pending:
        yield pending


def _write_lines(records: list[GpsOutput], out: IO[str]) -> None:
    """Write the records of a ``ReportDecoder`` (its report lines, ``str``) in one call."""
    if records:
        lines = cast("list[str]", records)
        lines.append("")  # the last line's end, without copying the text again
        out.write("\n".join(lines))


def _compressed(path: str) -> bool:
    """True for a file that begins as a compressed one does (gzip is read through by
    :func:`decode_stream`, which refuses the others)."""
    from x6wd.core.recorder import compression_of

    try:
        with open(path, "rb") as f:
            return compression_of(f.read(8)) is not None
    except OSError:
        return False  # named by the readers


def decode_path(
    path: str,
    out: IO[str],
    *,
    with_sky: bool = True,
    stats: ReadStats | None = None,
    size: InputSize | None = None,
    strict: bool = False,
) -> DecoderCounters:
    """Decode a file; a recording is read whole, every remaining part of it, through
    ``x6wd.core.recorder.read_recording_parts`` (as replay and plot read it), which counts
    its bad and truncated lines in ``stats``; a plain file's bytes are counted in ``size``
    (if given). ``strict``: see :func:`decode_stream`. An input that is not a regular file
    (a pipe such as ``<(zcat log.gz)``, a FIFO, a serial device) is opened once and read as a
    stream, as ``-`` is: a recording through it is read by the stream's line parser; so is
    a gzip file, decompressed as it is read."""
    from x6wd.core.files import not_regular
    from x6wd.core.recorder import is_recording, read_recording_parts

    # a first part that retention deleted is judged by the rest (is_recording)
    if not_regular(path) is not None or _compressed(path) or not is_recording(path):
        try:
            f = open(path, "rb")  # noqa: SIM115
        except OSError as exc:
            raise DeviceUnavailable(f"cannot open {path}: {exc.strerror}") from exc
        with f:
            return decode_stream(f, out, with_sky=with_sky, size=size, strict=strict)

    sentences = (
        (rec.t_mono, rec.data["text"])
        for rec in read_recording_parts(path, stats=stats)
        if rec.type == "nmea" and isinstance(rec.data.get("text"), str)
    )
    return _decode_sentences(sentences, out, with_sky)


def main(args: argparse.Namespace) -> int:
    """Decode every FILE in order; returns 0, or 2 when a file could not be read or held
    nothing to decode (the other files are still decoded)."""
    # Decoding allocates tuples by the hundred thousand, hardly any in a cycle: the
    # collector's passes over them (and over every object of the imports, each full pass)
    # only cost time. The imports' objects are set aside (gc.freeze) and a pass waits for
    # many more allocations; cycles are still collected. Both undone on return.
    thresholds = gc.get_threshold()
    gc.freeze()
    gc.set_threshold(_GC_THRESHOLD, *thresholds[1:])
    try:
        return _main(args)
    finally:
        gc.set_threshold(*thresholds)
        gc.unfreeze()


_GC_THRESHOLD: Final = 20_000  # allocations between collections (CPython's default: 700)


def _main(args: argparse.Namespace) -> int:
    from x6wd.core.recorder import InputSize, ReadStats, nothing_decoded

    status = 0
    for name in args.files:
        stats = ReadStats()
        size = InputSize()
        try:
            if name == "-":
                counters = decode_stream(
                    sys.stdin.buffer,
                    sys.stdout,
                    with_sky=not args.no_sky,
                    stats=stats,
                    size=size,
                    strict=args.strict,
                )
            else:
                counters = decode_path(
                    name,
                    sys.stdout,
                    with_sky=not args.no_sky,
                    stats=stats,
                    size=size,
                    strict=args.strict,
                )
        except BrokenPipeError:
            # The reader went away (e.g. `| head`): stop quietly like other filters.
            with contextlib.suppress(OSError):
                sys.stdout = open(os.devnull, "w")  # noqa: SIM115
            return status
        except DeviceUnavailable as exc:
            # Exit 2 like every other subcommand's unreadable input; the other files still go.
            print(f"x6wd decode: {exc}", file=sys.stderr)
            status = 2
            continue
        except ParseError as exc:  # what was decoded before is written
            with contextlib.suppress(OSError):
                sys.stdout.flush()
            print(f"x6wd decode: {name}: {exc}", file=sys.stderr)
            status = 2
            continue
        sys.stdout.flush()
        if not args.quiet:
            figures = " ".join(f"{k}={v}" for k, v in counters.as_dict().items())
            if stats.records or stats.bad_lines or stats.truncated:  # a recording
                figures += f" bad_recording_lines={stats.bad_lines + stats.truncated}"
            print(f"{name}: {figures}", file=sys.stderr)
        if what := nothing_decoded(counters.sentences, counters.ubx_frames, stats, size):
            print(
                f"x6wd decode: {name}: no NMEA sentence or x6wd record in {what}", file=sys.stderr
            )
            status = 2
    return status
