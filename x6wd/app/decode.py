"""`x6wd decode FILE... | -`: NMEA logs or x6wd recordings -> gpsd-style JSON lines.

Like gpsd's ``gpsdecode``: one compact JSON object per line for every fix (``TPV``) and sky
report (``SKY``), with gpsd's field names and units (lat/lon deg, altMSL/altHAE m, speed
m/s, track deg true). Unknown fields are omitted, never null. A file whose first non-blank
character is ``{`` is an x6wd recording (JSON lines); its ``nmea`` records are decoded
(files through ``x6wd.core.recorder.read_recording``; standard input by a small line parser that
also takes the flat ``{"type":"nmea","text":...}`` form); its other records are ignored.
Anything else is read as a raw byte stream (binary and line noise tolerated). The decoder's
counters go to standard error, one line per input.

The lines are the text of ``json.dumps(tpv_obj(fix))`` / ``json.dumps(sky_obj(sky))``
(``x6wd.app.gpsd``, compact separators) for the records of the daemon's decoder
(``drivers.gps_nmea.GpsDecoder``), written by :class:`ReportEncoder` without building the
dicts. :class:`ReportDecoder` is that decoder with its fixes and sky reports written as
lines instead of records (same epochs and counters: only the writing differs);
tests/test_decode_bulk.py checks both, byte for byte, against the reference path in the same
run. bench/bench_decode.py compares the rate with gpsd's ``gpsdecode``.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import sys
from collections.abc import Callable, Iterable, Iterator
from datetime import UTC, date, datetime
from typing import IO, Any, cast

from drivers.gps_nmea import (
    _GSA_MODE,
    _GSV_GROUP,
    DecoderCounters,
    GpsDecoder,
    GpsOutput,
    _Gga,
    _GsaValues,
    _parse_gsa,
    _Rmc,
    gsv_groups,
    gsv_values,
)
from drivers.nmea import GSA
from x6wd.core.errors import DeviceUnavailable
from x6wd.core.records import GpsFix, GpsSky, SatInfo

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
    ``json.dumps(sky_obj(r))`` with compact separators (``x6wd.app.gpsd``), built directly.

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
    ) -> str:
        """The TPV line of a fix from its fields (``GpsFix``'s, units alike; its time as
        ``time_member`` writes it)."""
        mode = mode if valid else 1
        if type(mode) is int and 0 <= mode <= 3:
            head = _TPV_HEADS[mode]
        else:
            mode_text = str(mode) if type(mode) is int else _dumps_compact(mode)
            head = '{"class":"TPV","mode":' + mode_text
        if not (valid and mode >= 2 and lat is not None and lon is not None):
            return head + time + "}"
        # Altitudes (mode 3 only) and error estimates: one memo for the pair of texts.
        if mode >= 3:
            key = (alt, None if alt is None else geoid_sep, hdop, vdop)
        else:
            key = (None, None, hdop, None)
        try:
            alt_text, err_text = self._tails[key]
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
        except TypeError:  # unhashable values: not memoised
            alt, sep, hdop, vdop = key
            alt_text = "" if alt is None else _altitudes(alt, sep)
            err_text = _errors(hdop, vdop)
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
        n_used = listed.count('"used":true')
        dops = self._group((hdop, vdop, pdop), _dops)
        return (
            f'{{"class":"SKY"{time}{dops},"nSat":{len(texts)},"uSat":{n_used},'
            f'"satellites":[{listed}]}}'
        )

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


_TPV_HEADS = tuple(f'{{"class":"TPV","mode":{m}' for m in range(4))

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
    free, used = _sat_texts(s.prn, s.el_deg, s.az_deg, s.snr_dbhz)
    return used if s.used else free


def _sat_texts(prn: Any, el_deg: Any, az_deg: Any, snr_dbhz: Any) -> tuple[str, str]:
    """``_sat_text`` of a satellite as not used and as used in the fix: the text of
    ``json.dumps({"PRN": prn, "used": used, "el": .., "az": .., "ss": ..})`` (non-finite
    values omitted, the others rounded to 0.1), written directly: both texts from one
    conversion of the numbers, each number's text memoised by value (elevations,
    azimuths and SNRs are a few hundred values)."""
    head = '{"PRN":' + (str(prn) if type(prn) is int else _dumps_compact(prn)) + ',"used":'
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
"""A GSV satellite for ``ReportDecoder``: PRN, its ``_sat_text`` not used / used in the fix."""


class ReportDecoder(GpsDecoder):
    """``GpsDecoder`` (the reference, unchanged: same epochs, fixes and counters) whose
    fixes and sky reports come out as their TPV and SKY lines (``str``, in ``out``).

    What a record would have been built for, and then read back by ``ReportEncoder``, is
    skipped: a fix's line is ``ReportEncoder.tpv_line`` of the fields ``_emit`` would store;
    a satellite goes from its GSV group straight to its two possible JSON texts (memoised
    by the group's text, as the reference memoises its ``SatInfo`` pair), so a sky report is
    one join of texts (``sky_line``), and a GSV whose groups are all known is one memo read
    per group; an epoch's time member is written from the time of day and the date's text
    without a datetime where that is exact (``_time_member``); a GSA's values are memoised
    by its text. Without ``with_sky`` the sky reports are counted
    and not written. tests/test_decode_bulk.py compares the lines and counters with the
    reference decoder's records through ``tpv_obj``/``sky_obj`` in the same run.
    """

    def __init__(self, encoder: ReportEncoder, *, with_sky: bool = True) -> None:
        super().__init__(emit_sentences=False)
        self._encoder = encoder
        self._with_sky = with_sky
        self._sat_texts: dict[str, _SatTexts] = {}
        self._sat_text_of = self._sat_texts.__getitem__  # (the memo is cleared, never replaced)
        # GSA: the handler gets the text of the fields unsplit (most splits 0), see _gsa_text.
        self._handlers["GSA"] = (self._gsa_text, 1, 0)
        self._gsa_memo: dict[str, _GsaValues] = {}
        # _time_member's last (time of day, date, date's time of day) and its text.
        self._member_tod: int | None = None
        self._member_day: date | None = None
        self._member_day_tod: int | None = None
        self._member = ""

    def _gsa_text(self, talker: str, d: list[str], t_s: float, out: list[GpsOutput]) -> None:
        """A GSA from the text of its fields (``d[0]``): a receiver repeats its GSA while the
        constellation holds, so its values (``_parse_gsa`` of the fields, split and padded
        as the reference's handler gets them) are memoised by that text. A GSA that fails
        to parse is not memoised: it raises again."""
        body = d[0]
        values = self._gsa_memo.get(body)
        if values is None:
            fields = body.split(",")
            if len(fields) < _GSA_FIELDS:
                fields += [""] * (_GSA_FIELDS - len(fields))
            values = _parse_gsa(tuple(fields[_GSA_MODE:_GSA_FIELDS]))
            if len(self._gsa_memo) >= MEMO_MAX:
                self._gsa_memo.clear()
            self._gsa_memo[body] = values
        self._set_gsa(values)

    def _sats_of(self, text: str) -> list[_SatTexts]:  # type: ignore[override]
        """The satellites of a GSV sentence's satellite fields ``text`` (as ``_gsv_sats``:
        the same groups, skipped or rejected alike)."""
        groups = _GSV_GROUP.findall(text)
        if len(groups) >= 4 or (text.count(",") + 1) % 4 == 0:  # gsv_groups adds no group
            try:
                return list(map(self._sat_text_of, groups))  # every group seen before
            except KeyError:
                pass
        groups = gsv_groups(text)
        memo = self._sat_texts
        sats = []
        for group in groups:
            entry = memo.get(group)
            if entry is None:
                values = gsv_values(group)
                if values is None:
                    continue
                entry = (values[0], *_sat_texts(*values))
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

    def _emit(self, gga: _Gga | None, rmc: _Rmc | None, out: list[GpsOutput]) -> None:
        # GpsDecoder._emit, writing the line instead of the record.
        _, tod, valid, mode, lat, lon = self._fix_head(gga, rmc)  # TPV has no t_s
        if gga is None:
            alt = sep = None
            hdop = self._hdop_gsa
        else:
            alt, sep, hdop = gga.alt_m, gga.sep_m, gga.hdop
        speed = course = None
        if rmc is not None:
            speed, course = rmc.speed_mps, rmc.course_deg
        line = self._encoder.tpv_line(
            valid, mode, self._time_member(tod), lat, lon, alt, sep, speed, course, hdop, self._vdop
        )
        out.append(line)  # type: ignore[arg-type]

    def _emit_sky(self, t_s: float, out: list[GpsOutput]) -> None:
        # GpsDecoder._emit_sky, writing the line instead of the record.
        self._counters.skies += 1
        if not self._with_sky:
            return
        used = self._used
        texts: list[str] = []
        oldest = self._epoch_idx - 1  # a constellation that stopped reporting drops out
        for epoch_idx, group in self._sky.values():
            if epoch_idx >= oldest:
                texts += [in_use if prn in used else free for prn, free, in_use in group]  # type: ignore[misc]
        line = self._encoder.sky_line(
            texts, self._time_member(self._tod_us), self._hdop_gsa, self._vdop, self._pdop
        )
        out.append(line)  # type: ignore[arg-type]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Register the ``decode`` options."""
    parser.add_argument(
        "files", nargs="+", metavar="FILE", help="NMEA log or recording; - is stdin"
    )
    parser.add_argument("--no-sky", action="store_true", help="print TPV reports only")
    parser.add_argument("--quiet", action="store_true", help="do not print counters on stderr")


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


def _recording_sentences(lines: Iterable[bytes]) -> Iterator[tuple[float, str]]:
    """(t_s, text) of the raw NMEA records in recording lines; other lines are skipped.

    Accepts the recorder's ``{"t_mono":..,"type":"nmea","data":{"text":..}}`` and the flat
    ``{"type":"nmea","text":..}`` form.
    """
    for raw in lines:
        try:
            obj = json.loads(raw)
        except (ValueError, UnicodeDecodeError):
            continue
        if not isinstance(obj, dict) or obj.get("type") != "nmea":
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


def decode_stream(stream: IO[bytes], out: IO[str], *, with_sky: bool = True) -> DecoderCounters:
    """Decode one input (NMEA bytes or a recording) and write report lines to ``out``."""
    head = stream.read(_CHUNK_BYTES)
    if head.lstrip()[:1] == b"{":
        lines = (head + stream.read()).splitlines()
        return _decode_sentences(_recording_sentences(lines), out, with_sky)
    decoder = ReportDecoder(ReportEncoder(), with_sky=with_sky)
    chunk = head
    while chunk:
        _write_lines(decoder.feed(chunk, 0.0), out)
        chunk = stream.read(_CHUNK_BYTES)
    _write_lines(decoder.flush(), out)
    return decoder.counters


def _write_lines(records: list[GpsOutput], out: IO[str]) -> None:
    """Write the records of a ``ReportDecoder`` (its report lines, ``str``) in one call."""
    if records:
        out.write("\n".join(cast("list[str]", records)) + "\n")


def decode_path(path: str, out: IO[str], *, with_sky: bool = True) -> DecoderCounters:
    """Decode a file; recordings go through ``x6wd.core.recorder.read_recording``."""
    try:
        f = open(path, "rb")  # noqa: SIM115
    except OSError as exc:
        raise DeviceUnavailable(f"cannot open {path}: {exc.strerror}") from exc
    with f:
        first = f.read(4096).lstrip()
        while not first:
            block = f.read(4096)
            if not block:
                break
            first = block.lstrip()
        f.seek(0)
        if first[:1] != b"{":
            return decode_stream(f, out, with_sky=with_sky)
    from x6wd.core.recorder import read_recording

    sentences = (
        (rec.t_mono, rec.data["text"])
        for rec in read_recording(path)
        if rec.type == "nmea" and isinstance(rec.data.get("text"), str)
    )
    return _decode_sentences(sentences, out, with_sky)


def main(args: argparse.Namespace) -> int:
    """Decode every FILE in order; returns 0, or 1 when a file could not be read."""
    status = 0
    for name in args.files:
        try:
            if name == "-":
                counters = decode_stream(sys.stdin.buffer, sys.stdout, with_sky=not args.no_sky)
            else:
                counters = decode_path(name, sys.stdout, with_sky=not args.no_sky)
        except BrokenPipeError:
            # The reader went away (e.g. `| head`): stop quietly like other filters.
            with contextlib.suppress(OSError):
                sys.stdout = open(os.devnull, "w")  # noqa: SIM115
            return status
        except DeviceUnavailable as exc:
            print(f"x6wd decode: {exc}", file=sys.stderr)
            status = 1
            continue
        sys.stdout.flush()
        if not args.quiet:
            figures = " ".join(f"{k}={v}" for k, v in counters.as_dict().items())
            print(f"{name}: {figures}", file=sys.stderr)
    return status
