"""NMEA 0183 output as a u-blox NEO-5 (GPS-Bee) prints it (REFERENCE.md §4).

At boot the receiver prints a ``$GPTXT`` banner; then, once per navigation epoch, the burst
RMC, VTG, GGA, GSA, GSV (1-4 messages, 4 satellites each), GLL. NMEA 2.3: RMC, VTG and GLL
carry a mode letter (``A`` autonomous, ``N`` not valid). Latitude/longitude as
``ddmm.mmmmm``/``dddmm.mmmmm`` (5 decimals of minutes; 4, 6 or 7 on request: only the
minutes change, every other field keeps the NEO-5's form), time as
``hhmmss.ss``. Course over ground is EMPTY when the receiver is at rest (course None). Without a
fix the receiver prints its real no-fix forms: all fields empty until it has time from a
satellite, then with time (and date) but status ``V`` / quality 0 / DOP 99.99.

The sentence layouts (field order, unit letters) come from the NMEA table shared with the
decoder (``drivers.nmea``, :meth:`~drivers.nmea.Sentence.template`); this module decides what
the NEO-5 puts in the fields and with how many decimals. Speed is what matters here: one epoch
is filled in by ``%`` templates, coordinates are formatted from integers; a batch of epochs
(:meth:`NmeaFormatter.format_cells`) is built field by field for all its epochs at once, as
numpy blocks of text (:mod:`sim_backend.textblocks`), and checksummed by XOR reductions.
"""

from __future__ import annotations

import math
import operator
from collections.abc import Iterable, Sequence
from datetime import date, datetime, timedelta
from typing import Any, Protocol

import numpy as np

from drivers.nmea import (
    GGA,
    GLL,
    GSA,
    GSV,
    KMH_PER_MPS,
    KNOTS_PER_MPS,
    RMC,
    TRAILERS,
    VTG,
    sentence,
)
from sim_backend.epoch import GnssEpoch, SimSat
from sim_backend.geodesy import leap_midnights_after
from sim_backend.textblocks import (
    compact,
    const_block,
    day_texts,
    filled,
    fixed_block,
    int_block,
    joined,
    put_texts,
    text_block,
)
from x6wd.core.errors import ConfigError
from x6wd.core.geodesy import wrap360

MAX_GSV_SATS = 4 * GSV.groups  # the NEO-5 prints at most 4 GSV messages (16 satellites)
MAX_GSA_SATS = GSA.field("prn").count  # 12
_NO_DOP = "99.99"  # the receiver's DOP without a fix (and its cap)

NEO5_BANNER: tuple[str, ...] = (
    "GPTXT,01,01,02,u-blox ag - www.u-blox.com",
    "GPTXT,01,01,02,HW  UBX-G50xx  00040005 ",
    "GPTXT,01,01,02,EXT CORE 6.00 (33247) May 13 2009 17:35:46",
    "GPTXT,01,01,02,ROM BASE 4.00 (25682) Jan 14 2008 16:29:23",
    "GPTXT,01,01,02,MOD NEO-5Q-0",
    "GPTXT,01,01,02,ANTSUPERV=AC SD PDoS SR",
    "GPTXT,01,01,02,ANTSTATUS=OK",
)
"""Body text of the boot banner (without ``$`` and checksum), u-blox 5 style."""

_D2 = [f"{i:02d}" for i in range(100)]
_D3 = [f"{i:03d}" for i in range(360)]
_SNR_OR_EMPTY = [*_D2, ""]  # index 100: no SNR
_ELAZ: list[str] = []


def _elaz_table() -> list[str]:
    """``"EE,AAA"`` for every whole elevation 0-90 and azimuth 0-359 (built once, lazily)."""
    if not _ELAZ:
        _ELAZ.extend(f"{e:02d},{a:03d}" for e in range(91) for a in range(360))
    return _ELAZ


_PRN = operator.attrgetter("prn")


def wire_time_s(data: bytes | int, baud: int = 9600, bits_per_byte: int = 10) -> float:
    """Seconds ``data`` (bytes, or a byte count) takes on a UART at ``baud`` bit/s.

    8N1 framing costs 10 bits per byte (start + 8 data + stop).
    """
    if baud <= 0:
        raise ConfigError(f"baud must be positive, got {baud}")
    if bits_per_byte <= 0:
        raise ConfigError(f"bits_per_byte must be positive, got {bits_per_byte}")
    n = data if isinstance(data, int) else len(data)
    if n < 0:
        raise ConfigError(f"byte count must be >= 0, got {n}")
    return n * bits_per_byte / baud


MINUTE_DECIMALS = (4, 5, 6, 7)
"""Decimals of NMEA minutes the formatter prints (at 7, 180 degrees in units of the last
digit is 1.1e11: exact in the int64 and double arithmetic both paths use)."""


def _coord(value_deg: float, deg_digits: int, decimals: int, scale: int) -> tuple[str, bool]:
    """``dd(d)mm.mmmmm`` text of |value| and whether it is non-negative."""
    total = round(abs(value_deg) * 60.0 * scale)  # in units of 10**-decimals minutes
    per_deg = 60 * scale
    deg, rem = divmod(total, per_deg)
    mins, frac = divmod(rem, scale)
    if deg_digits == 2:
        return f"{deg:02d}{mins:02d}.{frac:0{decimals}d}", value_deg >= 0.0
    return f"{deg:03d}{mins:02d}.{frac:0{decimals}d}", value_deg >= 0.0


class NmeaFormatter:
    """Formats :class:`GnssEpoch` objects into NEO-5 sentence bursts.

    ``minute_decimals`` 5 (NEO-5 firmware 6), 4, 6 or 7: the minutes' decimals only, the
    rest of every sentence stays the NEO-5's (so 4 is not a u-blox 5 firmware 5.00 stream,
    which also prints ``hhmmss.sss`` and other field widths; 7 gives a receiver with a
    high-precision print, u-blox M8/F9, its 0.2 mm lattice, where 5 decimals add ~0.5 cm of
    rounding noise per axis, more than such a receiver's own 1 s noise); ``time_decimals``
    2 (``hhmmss.ss``) or 3; ``rate_hz`` the navigation rate, 1-4 Hz as the NEO-5 allows (it only
    validates here: epoch times come from the model); ``talker`` is fixed at construction.
    The formatter remembers whether the receiver has time yet: the no-fix forms carry time
    and date once any satellite is tracked with a signal (the receiver decodes time from it)
    or after the first fix.
    """

    def __init__(
        self,
        minute_decimals: int = 5,
        time_decimals: int = 2,
        rate_hz: float = 1.0,
        talker: str = "GP",
    ) -> None:
        if minute_decimals not in MINUTE_DECIMALS:
            raise ConfigError(f"minute_decimals must be 4..7, got {minute_decimals}")
        if time_decimals not in (2, 3):
            raise ConfigError(f"time_decimals must be 2 or 3, got {time_decimals}")
        if not (isinstance(rate_hz, (int, float)) and 1.0 <= rate_hz <= 4.0):
            raise ConfigError(f"rate_hz must be within 1..4 Hz (NEO-5), got {rate_hz!r}")
        if len(talker) != 2 or not talker.isalpha() or not talker.isupper():
            raise ConfigError(f"talker must be two capital letters, got {talker!r}")
        self.minute_decimals = minute_decimals
        self.time_decimals = time_decimals
        self.rate_hz = float(rate_hz)
        self._talker = talker
        self.time_known = False
        self._scale = 10**minute_decimals
        self._tscale = 10**time_decimals
        t = talker
        # Sentence layouts from the shared table, with the letters the NEO-5 always writes
        # bound in (fewer values to format: the batch path formats an hour in milliseconds).
        # With a fix: status and NMEA 2.3 mode "A", GSA in "A"utomatic 2D/3D mode.
        self._rmc = RMC.template(
            t, "time", "lat", "lat_hemi", "lon", "lon_hemi", "speed", "course", "date",
            status="A", mode="A",
        )  # fmt: skip
        self._vtg = VTG.template(t, "course", "speed_kn", "speed_kmh", mode="A")
        self._gga = GGA.template(
            t, "time", "lat", "lat_hemi", "lon", "lon_hemi", "quality", "sats_used", "hdop",
            "alt", "geoid_sep",
        )  # fmt: skip
        self._gsa = GSA.template(t, "fix_type", "prn", "pdop", "hdop", "vdop", op_mode="A")
        self._gll = GLL.template(
            t, "lat", "lat_hemi", "lon", "lon_hemi", "time", status="A", mode="A"
        )
        # GSV: "GPGSV,<messages>,<message>,<in view>," for every count of satellites shown
        # (0-16), by message; the satellites' fields follow.
        gsv = GSV.template(t, "messages", "message", "in_view")
        self._gsv_none = gsv % (1, 1, "00")
        self._gsv_heads = [
            [gsv % ((m + 3) // 4, i + 1, _D2[m]) + "," for i in range((m + 3) // 4)]
            for m in range(MAX_GSV_SATS + 1)
        ]
        # Without a fix the receiver leaves even the unit letters empty.
        self._rmc_v = RMC.template(t, "time", "date", status="V", mode="N", units=False)
        self._vtg_v = VTG.template(t, mode="N", units=False) % ()
        self._gga_v = GGA.template(t, "time", quality=0, sats_used="00", hdop=_NO_DOP, units=False)
        self._gsa_v = (
            GSA.template(
                t, op_mode="A", fix_type=1, pdop=_NO_DOP, hdop=_NO_DOP, vdop=_NO_DOP, units=False
            )
            % ()
        )
        self._gll_v = GLL.template(t, "time", status="V", mode="N", units=False)

    @property
    def talker(self) -> str:
        """The two-letter talker id of every sentence (``GP``)."""
        return self._talker

    def _no_fix_bodies(self, hms: str, dmy: str, gsv: list[str]) -> list[str]:
        """The receiver's no-fix burst (time and date empty until it has time)."""
        return [
            self._rmc_v % (hms, dmy),
            self._vtg_v,
            self._gga_v % hms,
            self._gsa_v,
            *gsv,
            self._gll_v % hms,
        ]

    # --- pieces --------------------------------------------------------------------------

    def banner(self) -> bytes:
        """The ``$GPTXT`` boot banner (printed once when the receiver starts)."""
        return b"".join(sentence(b) for b in NEO5_BANNER)

    def _time(self, utc: datetime, start_utc: datetime) -> tuple[str, str]:
        """(``hhmmss.ss``, ``ddmmyy``) of ``utc`` rounded to the printed decimals, the
        rounding carried into the seconds and on into the date. ``utc`` is read on the
        scenario's clock from ``start_utc`` (``GnssEpoch.utc``), which has no leap seconds:
        one inserted since ``start_utc`` prints as 23:59:60 (:func:`_utc_ticks`)."""
        ts = self._tscale
        us = ((utc.hour * 60 + utc.minute) * 60 + utc.second) * 1_000_000 + utc.microsecond
        unit = 1_000_000 // ts
        ticks = (us + unit // 2) // unit
        leap = False
        starts = _leap_starts(start_utc, utc.date(), ts)
        if starts:
            shifted, in_leap = _utc_ticks(np.array([ticks]), starts, ts)
            ticks, leap = int(shifted[0]), bool(in_leap[0])
        # A time that rounds up to midnight is the next day's 000000.00: the date comes from
        # the rounded time, so the (time, date) pair never steps back 24 h.
        days, ticks = divmod(ticks, 86400 * ts)
        sec_total, frac = divmod(ticks, ts)
        h, rem = divmod(sec_total, 3600)
        m, s = divmod(rem, 60)
        if leap:  # the first second of the day after it: print the day before's 23:59:60
            days, h, m, s = days - 1, 23, 59, 60
        day = utc.date() + timedelta(days=days)
        hms = f"{h:02d}{m:02d}{s:02d}.{frac:0{self.time_decimals}d}"
        return hms, f"{day.day:02d}{day.month:02d}{day.year % 100:02d}"

    def _gsv(self, sats: Sequence[SimSat]) -> list[str]:
        if not sats:
            return [self._gsv_none]
        d2 = _D2
        fields = []
        # Table lookups instead of format specs: this loop runs 10-16 times per epoch.
        for s in sats:
            snr = s.snr_dbhz
            el = s.el_deg
            az = s.az_deg
            prn = d2[s.prn] if 0 <= s.prn < 100 else str(s.prn)
            snr_txt = "" if snr is None else d2[min(99, max(0, int(snr + 0.5)))]
            if el is None or az is None or not (-90.0 <= el <= 90.0) or not math.isfinite(az):
                fields.append(prn + ",,," + snr_txt)
            else:
                e = d2[int(el + 0.5)] if el > 0.0 else "00"
                fields.append(
                    prn + "," + e + "," + _D3[int(wrap360(az) + 0.5) % 360] + "," + snr_txt
                )
        heads = self._gsv_heads[len(sats)]  # at most 16 satellites (see _select)
        return [head + ",".join(fields[4 * i : 4 * i + 4]) for i, head in enumerate(heads)]

    def _gsv_batch(self, selected: Sequence[Sequence[SimSat]]) -> list[list[str]]:
        """GSV bodies of many epochs; numbers rounded by numpy, text from lookup tables."""
        flat = [s for sats in selected for s in sats]
        if not flat:
            return [self._gsv(sats) for sats in selected]
        n = len(flat)
        prn = np.fromiter((s.prn for s in flat), dtype=np.int64, count=n)
        nan = math.nan
        el = np.fromiter((nan if s.el_deg is None else s.el_deg for s in flat), float, n)
        az = np.fromiter((nan if s.az_deg is None else s.az_deg for s in flat), float, n)
        snr = np.fromiter((nan if s.snr_dbhz is None else s.snr_dbhz for s in flat), float, n)
        if np.any((prn < 0) | (prn > 99)):
            return [self._gsv(sats) for sats in selected]  # rare: odd PRNs take the slow path
        fields = _sat_fields(prn, el, az, snr)
        gsv_heads = self._gsv_heads
        out: list[list[str]] = []
        i0 = 0
        for sats in selected:
            m = len(sats)
            if m == 0:
                out.append([self._gsv_none])
                continue
            f = fields[i0 : i0 + m]
            i0 += m
            out.append(
                [head + ",".join(f[4 * i : 4 * i + 4]) for i, head in enumerate(gsv_heads[m])]
            )
        return out

    @staticmethod
    def _select(sats: Sequence[SimSat]) -> list[SimSat]:
        """At most 16 satellites (used ones first), in PRN order as u-blox prints them."""
        if len(sats) > MAX_GSV_SATS:
            sats = sorted(sats, key=lambda s: (not s.used, -(s.snr_dbhz or 0.0), s.prn))[
                :MAX_GSV_SATS
            ]
        return sorted(sats, key=_PRN)

    # --- epochs --------------------------------------------------------------------------

    def epoch_bodies(self, ep: GnssEpoch) -> list[str]:
        """Sentence bodies of one epoch burst (RMC, VTG, GGA, GSA, GSV..., GLL)."""
        sats = self._select(ep.satellites)
        return self._bodies(ep, sats, self._gsv(sats))

    def _bodies(self, ep: GnssEpoch, sats: Sequence[SimSat], gsv: list[str]) -> list[str]:
        if ep.valid or any(s.snr_dbhz is not None for s in sats):
            self.time_known = True
        start_utc = ep.utc - timedelta(seconds=ep.t_s)  # GnssBatch: start_utc + t_s
        if not ep.valid:
            return self._no_fix(ep.utc, start_utc, gsv)
        # GSA lists the used satellites in the order given: the model's, ascending PRN (a
        # real NEO-5 prints its tracking channels' order, which is not modelled).
        used = [s.prn for s in ep.satellites if s.used]
        return self._fix_bodies(
            *self._time(ep.utc, start_utc), ep.lat_deg, ep.lon_deg, ep.speed_mps, ep.course_deg,
            ep.quality if ep.quality > 0 else 1, ep.mode if ep.mode in (2, 3) else 3,
            used, ep.hdop, ep.pdop, ep.vdop, ep.alt_m, ep.geoid_sep_m, gsv,
        )  # fmt: skip

    def _fix_bodies(
        self,
        hms: str,
        dmy: str,
        lat_deg: float,
        lon_deg: float,
        speed_mps: float,
        course_deg: float | None,
        quality: int,
        fix_mode: int,
        used: Sequence[int],
        hdop: float,
        pdop: float,
        vdop: float,
        alt_m: float,
        geoid_sep_m: float,
        gsv: list[str],
    ) -> list[str]:
        lat, north = _coord(lat_deg, 2, self.minute_decimals, self._scale)
        lon, east = _coord(lon_deg, 3, self.minute_decimals, self._scale)
        ns = "N" if north else "S"
        ew = "E" if east else "W"
        speed = max(0.0, speed_mps)
        kn = f"{speed * KNOTS_PER_MPS:.3f}"
        kmh = f"{speed * KMH_PER_MPS:.3f}"
        course = "" if course_deg is None else f"{wrap360(course_deg):.2f}"
        d2 = _D2
        shown = [d2[p] if 0 <= p < 100 else str(p) for p in used[:MAX_GSA_SATS]]
        gsa_prns = ",".join(shown + [""] * (MAX_GSA_SATS - len(shown)))
        nused = d2[min(len(used), 99)]
        h = _dop(hdop)
        alt, sep = f"{alt_m:.1f}", f"{geoid_sep_m:.1f}"
        return [
            self._rmc % (hms, lat, ns, lon, ew, kn, course, dmy),
            self._vtg % (course, kn, kmh),
            self._gga % (hms, lat, ns, lon, ew, quality, nused, h, alt, sep),
            self._gsa % (fix_mode, gsa_prns, _dop(pdop), h, _dop(vdop)),
            *gsv,
            self._gll % (lat, ns, lon, ew, hms),
        ]

    def _no_fix(self, utc: datetime, start_utc: datetime, gsv: list[str]) -> list[str]:
        if self.time_known:
            hms, dmy = self._time(utc, start_utc)
        else:
            hms, dmy = "", ""
        return self._no_fix_bodies(hms, dmy, gsv)

    def format_batch(self, batch: BatchLike) -> list[bytes]:
        """One burst per epoch of a columnar receiver result (``sim_backend.gnss.GnssBatch``),
        identical to ``format_epochs(batch.epochs())`` without building per-satellite objects
        (:meth:`format_cells`, cut at the epochs)."""
        return self.format_cells(batch).bursts()

    def format_cells(self, batch: BatchLike) -> NmeaCells:
        """The sentences of a columnar receiver result as :class:`NmeaCells`: the text of
        ``format_epochs(batch.epochs())``, built column by column with numpy over all epochs
        at once (digits by integer arithmetic, checksums by XOR reductions), not per epoch.

        An epoch with more than 16 satellites in view takes the general path (the receiver's
        16-satellite GSV selection), and so does a whole batch with a PRN outside 0-99.
        """
        n_e = len(batch.t_s)
        if n_e == 0:
            return NmeaCells.of_bursts([])
        prns = np.asarray(batch.prns, dtype=np.int64)
        if np.any((prns < 0) | (prns > 99)):
            return NmeaCells.of_bursts(self.format_epochs(batch.epochs()))
        in_view = np.asarray(batch.in_view, dtype=bool)
        used = np.asarray(batch.used, dtype=bool) & in_view
        snr = np.asarray(batch.snr_dbhz, dtype=float)
        valid = np.asarray(batch.valid, dtype=bool)
        n_view = in_view.sum(axis=1)
        slow = n_view > MAX_GSV_SATS
        has_snr = (in_view & np.isfinite(snr)).any(axis=1)
        # The receiver has time from its first fix or first satellite signal on.
        known = (np.cumsum(valid | has_snr) > 0) | self.time_known
        hms, dmy = self._time_blocks(batch.start_utc, np.asarray(batch.t_s, dtype=float))
        gsv, n_msg = self._gsv_blocks(batch, prns, in_view, n_view)
        slots: list[tuple[_Rows, int, np.ndarray]] = []  # (rows, slot, bodies)
        fix, n_fix = _rows(valid & ~slow)
        nofix, r = _rows(~valid & ~slow)
        if n_fix:
            bodies = self._fix_blocks(batch, fix, n_fix, hms, dmy, prns, used)
            slots += [(fix, k, b) for k, b in zip(_FIX_SLOTS, bodies, strict=True)]
        if r:
            unknown = ~known[nofix]
            hms_v, dmy_v = hms[nofix].copy(), dmy[nofix].copy()
            hms_v[unknown] = 0  # empty time and date until the receiver has time
            dmy_v[unknown] = 0
            bodies = [
                filled(self._rmc_v, [hms_v, dmy_v], r),
                filled(self._vtg_v, [], r),
                filled(self._gga_v, [hms_v], r),
                filled(self._gsa_v, [], r),
                filled(self._gll_v, [hms_v], r),
            ]
            slots += [(nofix, k, b) for k, b in zip(_FIX_SLOTS, bodies, strict=True)]
        for j, body in enumerate(gsv):
            rows, n_rows = _rows(~slow & (n_msg > j))
            if n_rows:
                slots.append((rows, _GSV0 + j, body[rows]))
        # the general path's epochs, in order, with the time state they would have seen
        slow_lines: list[tuple[int, list[bytes]]] = []
        for i in np.flatnonzero(slow).tolist():
            self.time_known = bool(known[i - 1]) if i else self.time_known
            slow_lines.append((i, [sentence(b) for b in self.epoch_bodies(batch.epoch(i))]))
        self.time_known = bool(known[-1])
        width = max(
            [body.shape[1] + _FRAME_BYTES for _, _, body in slots]
            + [len(line) for _, lines in slow_lines for line in lines]
        )
        cells = np.zeros((n_e, _SLOTS, width), dtype=np.uint8)
        for rows, k, body in slots:
            # "$", the body, "*HH" and CR LF, straight into the cells
            w = body.shape[1]
            checksums = np.bitwise_xor.reduce(body, axis=1) if w else 0
            cells[rows, k, 0] = ord("$")
            cells[rows, k, 1 : 1 + w] = body
            cells[rows, k, 1 + w : w + _FRAME_BYTES] = _TRAILER_BLOCK[checksums]
        for i, lines in slow_lines:
            for k, line in _slotted(lines):
                cells[i, k, : len(line)] = np.frombuffer(line, dtype=np.uint8)
        return NmeaCells(cells)

    def _fix_blocks(
        self,
        batch: BatchLike,
        rows: _Rows,
        r: int,
        hms: np.ndarray,
        dmy: np.ndarray,
        prns: np.ndarray,
        used: np.ndarray,
    ) -> list[np.ndarray]:
        """Bodies (RMC, VTG, GGA, GSA, GLL) of the ``r`` epochs ``rows``, which have a fix."""
        hms, dmy = hms[rows], dmy[rows]
        lat, ns = self._coord_blocks(np.asarray(batch.lat_deg, dtype=float)[rows], 2)
        lon, ew = self._coord_blocks(np.asarray(batch.lon_deg, dtype=float)[rows], 3)
        spd = np.fmax(np.asarray(batch.speed_mps, dtype=float)[rows], 0.0)
        kn = fixed_block(spd * KNOTS_PER_MPS, 3)
        kmh = fixed_block(spd * KMH_PER_MPS, 3)
        crs_deg = wrap360(np.asarray(batch.course_deg, dtype=float)[rows])
        crs = fixed_block(np.where(np.isnan(crs_deg), 0.0, crs_deg), 2)
        crs[np.isnan(crs_deg)] = 0  # NaN: at rest, empty
        alt = fixed_block(np.asarray(batch.alt_m, dtype=float)[rows], 1)
        h, p, v = (_dop_block(np.asarray(getattr(batch, k), dtype=float)[rows])
                   for k in ("hdop", "pdop", "vdop"))  # fmt: skip
        u = used[rows]
        n_used = u.sum(axis=1)
        nused = _D2_BLOCK[np.minimum(n_used, 99)]
        # GSA: the used satellites in column order (the model's: ascending PRN), at most 12.
        rank = np.cumsum(u, axis=1) - 1
        ur, uc = np.nonzero(u & (rank < MAX_GSA_SATS))
        gsa = np.zeros((r, MAX_GSA_SATS, 3), dtype=np.uint8)
        gsa[:, :-1, 2] = ord(",")
        gsa[ur, rank[ur, uc], :2] = _D2_BLOCK[prns[uc]]
        gsa_prns = gsa.reshape(r, 3 * MAX_GSA_SATS)[:, :-1]
        geoid = const_block(f"{float(batch.geoid_sep_m):.1f}", r)
        one, three = const_block("1", r), const_block("3", r)
        return [
            filled(self._rmc, [hms, lat, ns, lon, ew, kn, crs, dmy], r),
            filled(self._vtg, [crs, kn, kmh], r),
            filled(self._gga, [hms, lat, ns, lon, ew, one, nused, h, alt, geoid], r),
            filled(self._gsa, [three, gsa_prns, p, h, v], r),
            filled(self._gll, [lat, ns, lon, ew, hms], r),
        ]

    def _gsv_blocks(
        self, batch: BatchLike, prns: np.ndarray, in_view: np.ndarray, n_view: np.ndarray
    ) -> tuple[list[np.ndarray], np.ndarray]:
        """The four GSV message bodies of every epoch (E, w) and each epoch's message count
        (rows of more than 16 satellites are left for the general path)."""
        n_e, n_s = in_view.shape
        order = np.argsort(prns, kind="stable")  # GSV prints in PRN order
        iv = in_view[:, order]
        rank = np.cumsum(iv, axis=1) - 1
        rows, cols = np.nonzero(iv & (rank < MAX_GSV_SATS))
        k = rank[rows, cols]
        cols = order[cols]
        at = rows * n_s + cols
        el = np.asarray(batch.el_deg, dtype=float).reshape(-1).take(at)
        az = np.asarray(batch.az_deg, dtype=float).reshape(-1).take(at)
        snr = np.asarray(batch.snr_dbhz, dtype=float).reshape(-1).take(at)
        # the numbers of _sat_fields: "PP,EE,AAA,SS", position or SNR left empty
        pos_ok = np.isfinite(el) & np.isfinite(az) & (np.abs(el) <= 90.0)
        with np.errstate(invalid="ignore"):
            el_i = np.clip(np.floor(el + 0.5), 0, 90)
            az_i = np.floor(wrap360(az) + 0.5) % 360
            snr_i = np.where(np.isfinite(snr), np.clip(np.floor(snr + 0.5), 0, 99), 100)
        elaz = np.where(pos_ok, el_i * 360 + az_i, _ELAZ_EMPTY).astype(np.int64)
        n = rows.size
        sat = joined(
            (np.where(k % 4 > 0, ord(","), 0).astype(np.uint8)[:, None],
             _D2_BLOCK[prns[cols]], const_block(",", n), _ELAZ_BLOCK[elaz], const_block(",", n),
             _SNR_BLOCK[snr_i.astype(np.int64)])
        )  # fmt: skip
        fields = np.zeros((n_e, MAX_GSV_SATS, 13), dtype=np.uint8)
        fields[rows, k] = sat
        m = np.minimum(n_view, MAX_GSV_SATS)
        n_msg = np.maximum((m + 3) // 4, 1)
        head = GSV.template(self._talker, "messages", "message", "in_view")
        count = _D2_BLOCK[m]
        comma = np.where(m > 0, ord(","), 0).astype(np.uint8)[:, None]
        bodies = []
        for j in range(GSV.groups):
            body = filled(head, [_D1_BLOCK[n_msg], const_block(str(j + 1), n_e), count], n_e)
            sats = fields[:, 4 * j : 4 * j + 4].reshape(n_e, 52)
            bodies.append(joined((body, comma, sats)))
        return bodies, n_msg

    def _time_blocks(self, start_utc: datetime, t_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``hhmmss.ss`` and ``ddmmyy`` blocks of ``start_utc + t_s``, as :meth:`_time`."""
        ts = self._tscale
        s0 = start_utc
        start_us = ((s0.hour * 60 + s0.minute) * 60 + s0.second) * 1_000_000 + s0.microsecond
        total = start_us + np.rint(t_s * 1e6).astype(np.int64)
        unit = 1_000_000 // ts
        ticks = (total + unit // 2) // unit
        starts = _leap_starts(s0, s0.date(), ts)
        leap = None
        if starts:
            ticks, leap = _utc_ticks(ticks, starts, ts)
        # the day from the rounded time (a round-up to midnight is the next day's), as _time
        day, ticks = np.divmod(ticks, 86400 * ts)
        sec_total, frac = np.divmod(ticks, ts)
        hh, rem = np.divmod(sec_total, 3600)
        mm, ss = np.divmod(rem, 60)
        if leap is not None:  # as _time: the day before's 23:59:60
            day, hh, mm = day - leap, np.where(leap, 23, hh), np.where(leap, 59, mm)
            ss = np.where(leap, 60, ss)
        d2 = _D2_BLOCK
        hms = joined(
            (d2[hh], d2[mm], d2[ss], const_block(".", t_s.shape[0]),
             int_block(frac, self.time_decimals))
        )  # fmt: skip
        base = s0.date()

        def ddmmyy(d: int) -> str:
            dt = base + timedelta(days=d)
            return f"{dt.day:02d}{dt.month:02d}{dt.year % 100:02d}"

        return hms, day_texts(day, ddmmyy)

    def _coord_blocks(
        self, value_deg: np.ndarray, deg_digits: int
    ) -> tuple[np.ndarray, np.ndarray]:
        """``dd(d)mm.mmmmm`` and the hemisphere letter, as :func:`_coord` (NaN -> 0)."""
        scale = self._scale
        v = np.where(np.isfinite(value_deg), value_deg, 0.0)
        total = np.rint(np.abs(v) * 60.0 * scale).astype(np.int64)
        deg, rem = np.divmod(total, 60 * scale)
        mins, frac = np.divmod(rem, scale)
        text = joined(
            (int_block(deg, deg_digits), _D2_BLOCK[mins], const_block(".", v.shape[0]),
             int_block(frac, self.minute_decimals))
        )  # fmt: skip
        letters = np.frombuffer(b"NS" if deg_digits == 2 else b"EW", dtype=np.uint8)
        return text, letters[(v < 0.0).astype(np.int64)][:, None]

    def format_epoch(self, ep: GnssEpoch) -> bytes:
        """The complete byte burst of one epoch, CRLF-terminated sentences."""
        return b"".join(sentence(b) for b in self.epoch_bodies(ep))

    def format_epochs(self, epochs: Iterable[GnssEpoch]) -> list[bytes]:
        """One burst per epoch, identical to :meth:`format_epoch` in a loop but faster.

        All checksums of the batch are computed at once with numpy (XOR reduced per
        sentence), which is what makes an hour of 1 Hz output take a few tens of ms.
        """
        eps = list(epochs)
        selected = [self._select(ep.satellites) for ep in eps]
        gsvs = self._gsv_batch(selected)
        return _assemble(
            [self._bodies(ep, sats, gsv) for ep, sats, gsv in zip(eps, selected, gsvs, strict=True)]
        )


def _leap_starts(start_utc: datetime, midnight: date, ticks_per_s: int) -> list[int]:
    """Where each leap second inserted after ``start_utc`` begins, in ticks (1/ticks_per_s s)
    from ``midnight`` on the scenario's clock (``start_utc`` + t). That clock counts no leap
    seconds, as GPS time does, so the k-th (from 0) begins k s after its UTC midnight."""
    return [
        ((m.date() - midnight).days * 86400 + k) * ticks_per_s
        for k, m in enumerate(leap_midnights_after(start_utc))
    ]


def _utc_ticks(
    ticks: np.ndarray, leap_starts: Sequence[int], ticks_per_s: int
) -> tuple[np.ndarray, np.ndarray]:
    """Scenario-clock ticks as UTC ticks (a second fewer after each leap second), and which
    fall inside a leap second: those come out as the first second of the day after it,
    printed as the day before's 23:59:60: every label then names one second of GPS time
    (repeating 23:59:59, as some receivers do, would print one label twice), and the NMEA
    seconds field allows 60 (``drivers.nmea.parse_time`` reads it)."""
    shift = np.zeros(ticks.shape, dtype=np.int64)
    leap = np.zeros(ticks.shape, dtype=bool)
    for b in leap_starts:
        shift += ticks >= b + ticks_per_s
        leap |= (ticks >= b) & (ticks < b + ticks_per_s)
    return ticks - shift * ticks_per_s, leap


def _sat_fields(prn: np.ndarray, el: np.ndarray, az: np.ndarray, snr: np.ndarray) -> list[str]:
    """GSV satellite fields ``PP,EE,AAA,SS`` for flat arrays (NaN: empty field)."""
    pos_ok = np.isfinite(el) & np.isfinite(az) & (np.abs(el) <= 90.0)
    el_i = np.where(pos_ok, np.clip(np.floor(el + 0.5), 0, 90), 0).astype(np.int64)
    az_i = np.where(pos_ok, np.floor(wrap360(az) + 0.5) % 360, 0).astype(np.int64)
    snr_i = np.where(np.isfinite(snr), np.clip(np.floor(snr + 0.5), 0, 99), 100).astype(np.int64)
    # One table entry per (elevation, azimuth): "EE,AAA"; index -1 means no position.
    pos_idx = np.where(pos_ok, el_i * 360 + az_i, -1).tolist()
    d2 = _D2
    elaz = _elaz_table()
    return [
        d2[p] + ("," + elaz[k] + "," if k >= 0 else ",,,") + _SNR_OR_EMPTY[q]
        for p, k, q in zip(prn.tolist(), pos_idx, snr_i.tolist(), strict=True)
    ]


# --- sentences in numpy blocks (sim_backend.textblocks) ----------------------------------

_SLOTS = 9  # sentence slots per epoch: RMC, VTG, GGA, GSA, 4 x GSV, GLL
_GSV0 = 4
_FIX_SLOTS = (0, 1, 2, 3, _SLOTS - 1)  # RMC, VTG, GGA, GSA, GLL
_D1_BLOCK = text_block([str(i) for i in range(10)])
_D2_BLOCK = text_block(_D2)
_D3_BLOCK = text_block(_D3)
_TRAILER_BLOCK = text_block([t.decode("ascii") for t in TRAILERS])  # "*HH\r\n" by checksum
_FRAME_BYTES = 6  # "$" before a body, "*HH" and CR LF after it
_SNR_BLOCK = text_block(_SNR_OR_EMPTY)  # index 100: no SNR
# "EE,AAA" for elevation * 360 + azimuth, and ",," with the numbers left out (no position)
_ELAZ_EMPTY = 91 * 360
_ELAZ_BLOCK = np.zeros((_ELAZ_EMPTY + 1, 6), dtype=np.uint8)
_ELAZ_BLOCK[:-1, :2] = np.repeat(_D2_BLOCK[:91], 360, axis=0)
_ELAZ_BLOCK[:, 2] = ord(",")
_ELAZ_BLOCK[:-1, 3:] = np.tile(_D3_BLOCK, (91, 1))


_Rows = np.ndarray | slice


def _rows(mask: np.ndarray) -> tuple[_Rows, int]:
    """The rows where ``mask`` holds, as an index (a slice when it holds everywhere: no
    copies), and how many."""
    if mask.all():
        return slice(None), int(mask.shape[0])
    index = np.flatnonzero(mask)
    return index, int(index.shape[0])


def _dop_block(values: np.ndarray) -> np.ndarray:
    """:func:`dop_texts` as a block."""
    v = np.asarray(values, dtype=float)
    with np.errstate(invalid="ignore"):
        capped = ~(np.isfinite(v) & (v <= 99.99))
        out = fixed_block(np.where(capped | ~(v > 0.0), 0.0, v), 2)
    rows = np.flatnonzero(capped)
    if rows.size:
        out = put_texts(out, rows, [_NO_DOP.encode("ascii")] * rows.size)
    return out


def _slotted(lines: Sequence[bytes]) -> list[tuple[int, bytes]]:
    """One burst's sentences (RMC, VTG, GGA, GSA, GSV..., GLL) with their slots."""
    n = len(lines)
    if not 0 < n <= _SLOTS:
        raise ValueError(f"a burst of {n} sentences does not fit {_SLOTS} slots")
    return [(k if k < _GSV0 or k < n - 1 else _SLOTS - 1, line) for k, line in enumerate(lines)]


class NmeaCells:
    """Sentences of E epochs in fixed cells: ``cells[e, k]`` is epoch e's k-th sentence slot
    (RMC, VTG, GGA, GSA, GSV 1-4, GLL) as bytes padded with NUL (inside too: each field has
    its widest width), all NUL where the epoch has no such sentence; a sentence's first byte
    is its cell's first."""

    def __init__(self, cells: np.ndarray) -> None:
        self.cells = cells
        self._text: bytes | None = None
        self._lengths: np.ndarray | None = None
        self._plain = False

    @classmethod
    def of_bursts(cls, bursts: Sequence[bytes]) -> NmeaCells:
        """Cells holding ``bursts`` (one per epoch, CRLF-terminated sentences)."""
        split = [b.splitlines(keepends=True) for b in bursts]
        width = max([len(line) for lines in split for line in lines], default=1)
        cells = np.zeros((len(bursts), _SLOTS, width), dtype=np.uint8)
        for i, lines in enumerate(split):
            for k, line in _slotted(lines):
                cells[i, k, : len(line)] = np.frombuffer(line, dtype=np.uint8)
        return cls(cells)

    def text(self) -> bytes:
        """All sentences, in order, as sent."""
        if self._text is None:
            self._text = compact(self.cells)
        return self._text

    @property
    def lengths(self) -> np.ndarray:
        """(E, slots) the bytes of each sentence, 0 where there is none."""
        if self._lengths is None:
            self._scan()
        assert self._lengths is not None
        return self._lengths

    @property
    def plain_lines(self) -> bool:
        """Whether every sentence is printable ASCII up to the CR LF that ends it."""
        if self._lengths is None:
            self._scan()
        return self._plain

    def _scan(self) -> None:
        """The sentences' lengths from where their CR LFs are in the text (when every byte
        outside printable ASCII is such a pair, one per sentence), else by counting."""
        arr = np.frombuffer(self.text(), dtype=np.uint8)
        exists = self.cells[:, :, 0] != 0
        n = int(np.count_nonzero(exists))
        # bytes outside 0x20-0x7E (uint8 arithmetic wraps those below 0x20 round)
        odd = np.flatnonzero(arr - np.uint8(0x20) > 0x5E)
        cr, lf = odd[::2], odd[1::2]
        self._plain = bool(
            n > 0
            and odd.shape[0] == 2 * n
            and lf[-1] == arr.shape[0] - 1
            and np.array_equal(cr + 1, lf)
            and np.all(arr[cr] == 13)
            and np.all(arr[lf] == 10)
        )
        if self._plain:
            lengths = np.zeros(exists.shape, dtype=np.int64)
            lengths[exists] = np.diff(lf, prepend=-1)
            self._lengths = lengths
        else:
            self._lengths = np.count_nonzero(self.cells, axis=2)

    def bursts(self) -> list[bytes]:
        """One burst per epoch (its sentences joined)."""
        text = self.text()
        ends = np.cumsum(self.lengths.sum(axis=1)).tolist()
        return [text[a:b] for a, b in zip([0, *ends[:-1]], ends, strict=True)]


def _assemble(per_epoch: Sequence[Sequence[str]]) -> list[bytes]:
    """Complete sentences (``$``, checksum, CRLF) joined per epoch; checksums computed for
    the whole batch at once with numpy (XOR reduced per sentence)."""
    raw = [b.encode("ascii") for bodies in per_epoch for b in bodies]
    if not raw:
        return [b"" for _ in per_epoch]
    lengths = np.fromiter(map(len, raw), dtype=np.int64, count=len(raw))
    starts = np.zeros(len(raw), dtype=np.int64)
    np.cumsum(lengths[:-1], out=starts[1:])
    buf = np.frombuffer(b"".join(raw), dtype=np.uint8)
    # drivers.nmea.checksum of every body at once: the XOR of each body's bytes.
    sums = np.bitwise_xor.reduceat(buf, starts).tolist()
    trailers = TRAILERS
    lines = [b"$" + r + trailers[c] for r, c in zip(raw, sums, strict=True)]
    out = []
    i = 0
    for bodies in per_epoch:
        n = len(bodies)
        out.append(b"".join(lines[i : i + n]))
        i += n
    return out


class BatchLike(Protocol):
    """The columns of ``sim_backend.gnss.GnssBatch`` that :meth:`NmeaFormatter.format_batch`
    reads: E epochs x S satellites."""

    @property
    def t_s(self) -> np.ndarray: ...

    @property
    def start_utc(self) -> datetime: ...

    @property
    def valid(self) -> np.ndarray: ...

    @property
    def lat_deg(self) -> np.ndarray: ...

    @property
    def lon_deg(self) -> np.ndarray: ...

    @property
    def alt_m(self) -> np.ndarray: ...

    @property
    def speed_mps(self) -> np.ndarray: ...

    @property
    def course_deg(self) -> np.ndarray: ...

    @property
    def hdop(self) -> np.ndarray: ...

    @property
    def pdop(self) -> np.ndarray: ...

    @property
    def vdop(self) -> np.ndarray: ...

    @property
    def prns(self) -> np.ndarray: ...

    @property
    def az_deg(self) -> np.ndarray: ...

    @property
    def el_deg(self) -> np.ndarray: ...

    @property
    def snr_dbhz(self) -> np.ndarray: ...

    @property
    def in_view(self) -> np.ndarray: ...

    @property
    def used(self) -> np.ndarray: ...

    @property
    def geoid_sep_m(self) -> float: ...

    def epoch(self, i: int) -> GnssEpoch: ...

    def epochs(self) -> list[GnssEpoch]: ...


def dop_texts(values: Any) -> list[str]:
    """DOP texts as u-blox prints them (:func:`_dop`) for an array of DOPs: the cap and NaN
    by numpy, the text per value."""
    v = np.asarray(values, dtype=float)
    capped = ~(np.isfinite(v) & (v <= 99.99))
    v = np.where(capped | ~(v > 0.0), 0.0, v)  # max(0.0, v) of _dop: -0.0 prints 0.00
    return [_NO_DOP if c else f"{x:.2f}" for x, c in zip(v.tolist(), capped.tolist(), strict=True)]


def _dop(value: float) -> str:
    """DOP as u-blox prints it: 2 decimals, capped at 99.99 (also for NaN/inf)."""
    if not math.isfinite(value) or value > 99.99:
        return _NO_DOP
    return f"{max(0.0, value):.2f}"
