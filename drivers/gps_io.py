"""The GPS I/O edge: a reader over a pyserial-like port that survives unplugging.

``GpsReader.poll(timeout_s)`` is the only call that touches the port. It opens the port when
needed (with capped exponential backoff between failed attempts), waits for bytes at most
about ``timeout_s`` seconds, hands them to the sans-IO ``GpsDecoder`` with the receive time,
and returns the decoded records. A read error with a transient errno
(:data:`x6wd.core.errors.TRANSIENT_ERRNOS`: EIO, EAGAIN, EBUSY, EINTR, EPROTO ... — pyserial wraps
the OSError in a ``SerialException`` without errno; the errno is taken from the wrapped one)
is counted and retried on the same port, ``retry_delay_s`` later within the same poll, up to
``transient_limit`` in a row. Any other error, too many transient ones, or EOF (a socket peer
that left) closes the port, marks the GPS disconnected and schedules a reopen: a device
fault is data, never an exception to the caller. The backoff is reset only once a reopened
port yields bytes; a port that reopens twice or more in a row but fails each time before it
does stays ``reconnecting`` ("the port reopened N times in a row without a byte read: ...")
and is reopened ever more slowly.

Health: :attr:`GpsReader.health` is a :class:`~x6wd.core.records.DeviceHealth` (connected,
degraded, stale when no valid sentence arrived for ``stale_s`` (a checksum-valid sentence
with invalid fields is not valid: it is counted in ``invalid_fields``), disconnected,
reconnecting, with error and reconnect counts, and the decoder's counts of corrupt input,
which also make a ``corrupt`` event at most once a minute and name the cause when the GPS
goes stale); :meth:`GpsReader.take_health_events` hands each transition to the caller at
once (the daemon holds the robot on it, without waiting for a fix timeout).

The reader sets ``port.timeout = 0`` on every port it opens and waits with ``select()``
itself, so a port opened blocking cannot hang it. On a plain pyserial POSIX port (a UART, or
the simulator's pseudo-terminal) it then reads the descriptor itself: one ``select()`` and
one ``read()`` per burst of bytes, instead of pyserial's ``in_waiting`` ioctl and its own
``select()`` + ``read()`` + ``select()`` — each system call lets another Python thread take
the GIL, and the GPS thread then waits for it back before the fix can be decided.

GPS week rollover: the legacy GPS message counts weeks in 10 bits, so a receiver whose
firmware predates a rollover (a u-blox NEO-5 with old firmware, ...) reports dates 1024 weeks
(19.6 years) in the past after it. The reader corrects them (:class:`WeekRolloverCorrection`):
a fix or sky view dated before :data:`WEEK_ROLLOVER_FLOOR_UTC` (this software's release: no
true date can be earlier, as gpsd does with its build date) gets 1024 weeks added, as often as
needed, with one WARNING naming the receiver's date and the corrected one. Only the live path
corrects (the daemon gives its reader one unless the GPS is a ``replay://`` log):
``x6wd decode`` and ``x6wd replay`` decode recorded sentences as they are.

Receiver configuration (``[gps] configure_receiver = true``): a :class:`ReceiverSetup` given to
the reader is written after every open of the port (start-up and each reopen: a receiver
that lost power forgets it): UBX CFG-RATE for ``[gps] rate_hz`` and CFG-MSG for the NMEA
the decoder uses (:func:`neo5_setup`). Every message must be answered by ACK-ACK within
:data:`ACK_TIMEOUT_S`; a NAK or no answer is shown in the setup's :meth:`ReceiverSetup.status`
(``status``'s ``gps_receiver``) and logged as one WARNING; the robot goes on with whatever the
receiver sends. A receiver that resets while the port stays open (a NEO-5 brown-out on the
Pi's UART) loses the setup without a reopen: its start-up ``$GPTXT`` banner, a sentence the
setup turned off (GLL, VTG) coming back, or the ACKed rate not kept for 5 s mark the setup
lost (status, one WARNING at most a minute) and it is written again, at most once per 10 s
(:meth:`ReceiverSetup.lost`). Whether configured or not, :class:`FixRate` measures the rate the
fixes actually arrive at (falling to 0 while the GPS is silent) and, when it is well under the
rate the staleness limits were checked against (``gps.rate_hz``), says so in status and in a
WARNING each time it falls: fixes then go stale between epochs and the robot holds; and
:class:`LineLoad` measures how full a UART's line is (bytes read against baud / 10 per
second; not a line its baud does not pace, a native-USB receiver: ``paced`` false): a
receiver that prints more than the line carries makes every fix late, which status and a
WARNING then say (the slow-rate text blames the line only while it is measured full).

Note that pyserial's ``socket://`` handler discards whatever arrived before ``open()``
returned; a streaming receiver loses nothing but part of one sentence.
"""

from __future__ import annotations

import contextlib
import dataclasses
import errno
import logging
import math
import os
import select
import time
from collections import deque
from collections.abc import Callable
from datetime import UTC, datetime, timedelta
from typing import Any, Protocol

from drivers.gps_nmea import (
    UBX_CLASS_CFG,
    UBX_ID_CFG_RATE,
    UBX_SYNC,
    GpsDecoder,
    GpsOutput,
    NmeaSentence,
    UbxAck,
    cfg_msg,
    cfg_rate,
    parse_ack,
)
from x6wd.core.config import NMEA_FIX_BUDGET_B
from x6wd.core.errors import ConfigError, ParseError, X6wdError, is_transient
from x6wd.core.health import HealthTracker, root_oserror
from x6wd.core.records import DeviceHealth, DeviceState, GpsFix, GpsSky, HealthEvent

log = logging.getLogger("drivers.gps_io")

_IDLE_POLL_S = 0.01  # wait step for ports that cannot be select()ed
JOIN_MAX_B = 512
"""Bytes after an open that may precede the first frame start as the tail of a sentence the
port was opened in (NMEA lines are at most 82 bytes; UBX frames a few hundred): beyond
this without a start they are line noise."""
CORRUPT_LABELS = {
    "checksum_failures": "lines with bad checksums",
    "framing_errors": "malformed lines",
    "invalid_fields": "sentences with invalid fields",
    "skipped_bytes": "bytes of noise",
}
"""The decoder's counts of corrupt input that health shows (``DeviceHealth.corrupt``), in
words. Noise bytes alone make no log line: every open starts in a partial line."""
TRANSIENT_LIMIT = 3
"""Transient port errors in a row (:data:`x6wd.core.errors.TRANSIENT_ERRNOS`) after which a port
counts as broken, is closed and opened again: the GPS reader's default ``transient_limit``,
and the motor link's (an EIO that never ends is a device that went away)."""
_NO_DATA_ERRNOS = frozenset({errno.EAGAIN, errno.EWOULDBLOCK, errno.EINTR, errno.EINPROGRESS,
                             errno.EALREADY})  # fmt: skip
"""Read errors that only mean "nothing to read yet" (pyserial's read ignores them too)."""

GPS_WEEK_ROLLOVER = timedelta(weeks=1024)
"""The span of the legacy GPS week number (10 bits): 1024 weeks, 19.6 years. A receiver with
firmware older than a rollover (1999-08-22, 2019-04-07, next 2038-11-21) dates its fixes this
much too early after it."""
WEEK_ROLLOVER_FLOOR_UTC = datetime(2026, 1, 1, tzinfo=UTC)
"""The earliest date a live receiver can truly report: this software's release (raise it with
each release; gpsd uses its build date the same way). A fix dated before it is a receiver week
rollover and gets :data:`GPS_WEEK_ROLLOVER` added (repeatedly) until it is not before it."""


class WeekRolloverCorrection:
    """Corrects the dates of a receiver whose firmware predates a GPS week rollover.

    :meth:`apply` returns the records with every ``GpsFix``/``GpsSky`` dated before ``floor``
    moved forward by whole multiples of :data:`GPS_WEEK_ROLLOVER` (the least that puts it at
    or after ``floor``); other records and undated ones pass unchanged. Where the system
    ``clock`` is past ``floor`` (it has been set), only a correction that brings the date
    nearer to it is made: the simulator's receiver in hardware in the loop (a scenario in
    2020) is not moved to 2039; a robot booted at 1970 corrects by the floor alone. The
    first corrected record (and any whose correction differs from the last one) makes one
    WARNING. Counts:
    :meth:`status` (``corrected``: records corrected since start, ``weeks_added``, the last
    ``receiver_utc`` and ``corrected_utc``, ``floor_utc``).
    """

    def __init__(
        self,
        floor: datetime = WEEK_ROLLOVER_FLOOR_UTC,
        clock: Callable[[], datetime] = lambda: datetime.now(UTC),
    ) -> None:
        self.floor = floor
        # the system clock: once it is past the floor (set), a date is corrected only where
        # that brings it nearer the clock; a receiver of the simulator (hardware in the
        # loop, its scenario in 2020) or a log fed through a pty is not a rollover
        self.clock = clock
        self.corrected = 0
        self.weeks_added = 0  # weeks added to the latest corrected record
        self.receiver_utc: datetime | None = None  # the latest corrected record's date, as read
        self.corrected_utc: datetime | None = None  # ... and as corrected

    def apply(self, records: list[GpsOutput]) -> list[GpsOutput]:
        floor = self.floor
        out: list[GpsOutput] | None = None
        for i, rec in enumerate(records):
            if not isinstance(rec, (GpsFix, GpsSky)):
                continue
            utc = rec.utc
            if utc is None or utc >= floor:
                continue
            n = 0
            fixed = utc
            while fixed < floor:
                fixed += GPS_WEEK_ROLLOVER
                n += 1
            now = self.clock()
            if now >= floor and abs(fixed - now) >= abs(utc - now):
                continue  # the clock is set and the receiver's own date is the nearer
            if out is None:
                out = list(records)
            out[i] = dataclasses.replace(rec, utc=fixed)
            self.corrected += 1
            self.receiver_utc, self.corrected_utc = utc, fixed
            if n * 1024 != self.weeks_added:
                self.weeks_added = n * 1024
                log.warning(
                    "GPS date %s is before %s (this software's release): a receiver week "
                    "rollover: firmware older than the GPS week rollover of %s; dates "
                    "corrected by %d weeks (%s)",
                    utc.isoformat(timespec="seconds"),
                    floor.date().isoformat(),
                    _rollover_before(utc + GPS_WEEK_ROLLOVER),
                    n * 1024,
                    fixed.isoformat(timespec="seconds"),
                )
        return records if out is None else out

    def status(self) -> dict[str, Any]:
        """``status``'s ``gps_week_rollover`` (JSON-ready)."""

        def iso(t: datetime | None) -> str | None:
            return None if t is None else t.isoformat(timespec="seconds")

        return {
            "corrected": self.corrected,
            "weeks_added": self.weeks_added,
            "receiver_utc": iso(self.receiver_utc),
            "corrected_utc": iso(self.corrected_utc),
            "floor_utc": self.floor.date().isoformat(),
        }


_GPS_EPOCH = datetime(1980, 1, 6, tzinfo=UTC)


def _rollover_before(t: datetime) -> str:
    """The latest GPS week rollover at or before ``t`` (a date, ISO)."""
    n = (t - _GPS_EPOCH) // GPS_WEEK_ROLLOVER
    return (_GPS_EPOCH + n * GPS_WEEK_ROLLOVER).date().isoformat()


ACK_TIMEOUT_S = 3.0
"""Seconds a configuration message may wait for its ACK after it was written. A NEO-5 answers
within milliseconds, but its answer queues behind the NMEA already in its transmit buffer (a
full second of output at 9600 baud)."""
SLOW_RATE_RATIO = 0.8
"""Fixes arriving at under this fraction of the expected rate are "too slow" (:class:`FixRate`):
1 Hz against ``rate_hz = 4`` is, 3.5 Hz (a dropped epoch now and then) is not."""
RATE_WINDOW = 9
"""Fixes the measured rate is taken over (the last ones); at least 5 make a measurement."""
RATE_HORIZON_S = 10.0
"""Fixes older than this (s) no longer count: a GPS that went silent on an open port measures
0 Hz, not the rate it last had (:class:`FixRate`)."""
SILENT_INTERVALS = 3.0
"""No fix for this many of the last interval between two fixes is the GPS gone silent, not
slow: the rate is still measured (it falls to 0) but no receiver rate is
blamed; the GPS's health (stale, disconnected, noise) says what happened (an outside audit:
a cut line read "the receiver runs slower than gps.rate_hz: set its rate")."""
RESEND_MIN_S = 10.0
"""The least time (s) between two writes of the setup on one port: a receiver that lost it
(:meth:`ReceiverSetup.lost`) is configured again at most this often."""
RESEND_MAX_S = 300.0
"""The longest wait (s) between two writes of the setup: a receiver that loses it again for the
same reason (not a restart) soon after it took it does not keep it, and each such loss
doubles the wait from :data:`RESEND_MIN_S` up to this (:meth:`ReceiverSetup.lost`)."""
LOST_WARN_MIN_S = 60.0
"""The least time (s) between two WARNINGs that the receiver lost its setup (the ones between
are counted in the next)."""
RATE_LOST_S = 5.0
"""A measured rate under :data:`SLOW_RATE_RATIO` of the rate the receiver ACKed, for this long
(s) while fixes still come, after it had been met: the receiver lost its CFG-RATE."""
OFF_GRACE_S = 1.0
"""A sentence the setup turned off that arrives more than this (s) after the setup's last ACK
was sent back by a receiver that lost the setup (the ACK queues behind what the receiver had
already printed, so anything later was printed after it took the setting)."""
BOOT_BANNER = ("u-blox ag", "rom core", "rom base", "ext core")
"""How the text of a u-blox start-up ``$GPTXT`` line begins (lower case; the ``HW  UBX-...``
line is matched apart). A u-blox receiver prints these once at power-up or after a reset,
never otherwise: ``u-blox ag - www.u-blox.com``, ``HW  UBX-G50xx 00040005`` (``G60xx``,
``G70xx``: the hardware generation), ``EXT CORE 6.00 (...)`` / ``ROM BASE ...`` (u-blox 5 and
6 with flash firmware) or ``ROM CORE 7.03 (...)`` (ROM firmware), then ``MOD ...``,
``ANTSUPERV=...``, ``ANTSTATUS=...`` (which also come on their own: not matched). Other
software counts the first line as the receiver's reboot the same way (Meshtastic's GPS
driver)."""
_OFF_TYPES = frozenset({"GLL", "VTG"})  # what neo5_setup turns off
_WATCHED_TYPES = _OFF_TYPES | {"TXT"}


def is_boot_banner(sentence: str) -> bool:
    """Whether ``sentence`` (``$GPTXT,01,01,02,text*HH``) is a line of a u-blox receiver's
    start-up banner (:data:`BOOT_BANNER`)."""
    if sentence[3:6] != "TXT":
        return False
    parts = sentence.split(",", 4)
    if len(parts) < 5:
        return False
    text = parts[4].rsplit("*", 1)[0].strip().lower()
    return text.startswith(BOOT_BANNER) or (text.startswith("hw ") and "ubx-" in text)


_CFG_RATE = (UBX_CLASS_CFG, UBX_ID_CFG_RATE)


DEFAULT_BAUD = 9600
"""The line rate assumed when the port does not say (a NEO-5's default, the Pi UART's)."""
NMEA_BUDGET_B = {**NMEA_FIX_BUDGET_B, "GSA": 66, "GSV": 280}
"""The most bytes each sentence (GSV: the whole group) takes on the line, for the line budget
of :func:`neo5_setup` (and :func:`fix_line_short`): RMC with course 75, GGA 77, GSA with 12
satellites used 66, GSV of 16 satellites in view (the NEO-5's 16 channels) 4 sentences of up
to 70. The simulated NEO-5
prints RMC 73-74, GGA 74, GSA 50-58 and GSV 183-195 (3 sentences, 12 satellites)."""


def line_bytes_per_epoch(rate_hz: float, baud: int = DEFAULT_BAUD) -> float:
    """Bytes the line carries (8N1) between two epochs at ``rate_hz``."""
    return baud / 10.0 / rate_hz


def fix_line_short(rate_hz: float, baud: int) -> str | None:
    """Why an epoch of ``baud`` (8N1) at ``rate_hz`` cannot carry RMC + GGA, the sentences
    every fix needs (:data:`NMEA_FIX_BUDGET_B`), in words; None when it can. Each fix then
    queues behind the last one's and arrives ever later (4 Hz at 4800 baud: ~2 s)."""
    need_b = sum(NMEA_FIX_BUDGET_B.values())
    room_b = line_bytes_per_epoch(rate_hz, baud)
    if room_b >= need_b:
        return None
    return (
        f"{baud} baud at {rate_hz:g} Hz carries {room_b:.0f} bytes an epoch, under the "
        f"{need_b} of RMC + GGA that every fix needs"
    )


def neo5_setup(rate_hz: float, baud: int = DEFAULT_BAUD) -> list[tuple[str, bytes]]:
    """The UBX messages ``configure_receiver`` sends, (name, frame) in order: CFG-RATE for
    ``rate_hz`` (NEO-5: 0.015..4 Hz), then CFG-MSG on the port they arrive on: GGA and RMC
    every epoch (a fix needs both), VTG and GLL off (RMC carries speed and course, GGA the
    time), and GSA and GSV about once a second (every ``round(rate_hz)`` epochs: the fix
    mode, DOPs and the sky change slowly) where the epoch that carries them still leaves the
    line (``baud``, 8N1) before the next epoch starts (:data:`NMEA_BUDGET_B`); else off.

    A CFG-MSG rate counts epochs: a GSV group goes out whole in one epoch, whatever its rate,
    so a slower GSV rate makes the overflow rarer, never smaller. An epoch's bytes beyond
    what the line carries before the next epoch delay that epoch's fix (stamped at arrival).
    At 9600 baud (960 bytes/s): 4 Hz leaves 240 bytes an epoch: RMC + GGA (152) + GSA (66)
    fit, GSV (up to 280 more) does not: GSV off (the simulated receiver's GSV epoch was 400
    bytes, the next fix 0.17 s late); 2 Hz 480 bytes: RMC + GGA + GSA + GSV up to 498: GSV
    off; 1 Hz: all. The receiver's default set (RMC, VTG, GGA, GSA, GSV, GLL each epoch,
    ~480 bytes) would not fit past 2 Hz. Raises ConfigError for a rate CFG-RATE cannot
    carry."""
    meas_ms = round(1000.0 / rate_hz)
    every = max(1, round(rate_hz))
    room = line_bytes_per_epoch(rate_hz, baud)
    b = NMEA_BUDGET_B
    gsa = every if b["RMC"] + b["GGA"] + b["GSA"] <= room else 0
    gsv = every if gsa and b["RMC"] + b["GGA"] + b["GSA"] + b["GSV"] <= room else 0
    msgs = [(f"CFG-RATE {meas_ms} ms", cfg_rate(meas_ms))]
    for name, rate in (("GGA", 1), ("RMC", 1), ("GSA", gsa), ("GSV", gsv), ("VTG", 0),
                       ("GLL", 0)):  # fmt: skip
        msgs.append((f"CFG-MSG {name} {rate}", cfg_msg(name, rate)))
    return msgs


def _loss_kind(reason: str) -> str:
    """What a loss's reason (:meth:`ReceiverSetup.lost`) is, without its numbers: a
    ``restart`` (a start-up banner), ``sentences`` (GLL or VTG back) or ``rate``."""
    if "start-up banner" in reason:
        return "restart"
    if "sentences came back" in reason:
        return "sentences"
    return "rate"


class ReceiverSetup:
    """The configuration ``[gps] configure_receiver`` writes after every open, and what the
    receiver answered.

    :attr:`init_bytes` are the frames of :func:`neo5_setup`; the reader calls :meth:`sent`
    once it wrote them (or :meth:`not_sent`), hands every ACK/NAK to :meth:`on_ack`, the
    sentences a lost setup shows in (start-up banner, GLL, VTG) to :meth:`on_sentence`, and
    calls :meth:`check` and :meth:`on_rate` on each poll. Each message is answered in order
    (an ACK names only the class and id, so the CFG-MSG answers are matched oldest first).
    :attr:`state`: ``"not sent"`` (no port yet), ``"waiting"``, ``"acked"`` (all ACK-ACK),
    ``"refused"`` (a NAK), ``"no answer"`` (nothing within ``ack_timeout_s``: a receiver
    configured elsewhere answers as well, so this is a receiver that does not speak UBX, a
    wrong port, or a line that loses what is sent), ``"not written"`` or ``"lost"``.

    Lost: a NEO-5 keeps the setup in RAM only, and one that resets while the port stays open
    (a brown-out of its supply on the Pi's UART) comes back at 1 Hz with its default
    sentences, the host none the wiser. So the setup counts as lost (:meth:`lost`) when the
    receiver prints its start-up banner (:func:`is_boot_banner`) after it was configured, a
    sentence the setup turned off (GLL, VTG) comes back after the ACKs, or the fix rate, once
    met, stays under :data:`SLOW_RATE_RATIO` of the ACKed rate for :data:`RATE_LOST_S` while
    fixes come. Each loss is one WARNING (at most one per :data:`LOST_WARN_MIN_S`), is
    counted in the status (``losses``, the last one's reason in ``lost``), and makes
    :meth:`resend_due` true: the reader writes the setup again, at most once per
    :data:`RESEND_MIN_S`, and its answers are tracked as at an open.

    A receiver that does not keep its setup (GLL/VTG come back after each ACK: something else
    re-enables them, or it ACKs CFG-MSG and ignores it; or its rate falls again) would be
    configured every 10 s for ever: a loss with the same reason as the last one (not a
    restart: a banner is a reset, each one needs the setup), less than :data:`RESEND_MAX_S`
    after the receiver took the setup, doubles the wait before the next write, up to
    :data:`RESEND_MAX_S`; it is one WARNING that the receiver does not keep its setup, and the
    status's ``not_kept`` says so (with ``resend_s``, the wait). A setup kept for
    :data:`RESEND_MAX_S`, or another reason, starts again at :data:`RESEND_MIN_S`.

    A refusal or a missing answer is logged as one WARNING per process and kind; the robot
    goes on with what the receiver sends (:class:`FixRate` shows the rate it actually gets)."""

    def __init__(
        self,
        rate_hz: float,
        *,
        ack_timeout_s: float = ACK_TIMEOUT_S,
        resend_min_s: float = RESEND_MIN_S,
    ) -> None:
        self.rate_hz = rate_hz
        self.baud = DEFAULT_BAUD
        self.messages = neo5_setup(rate_hz, self.baud)
        self.init_bytes = b"".join(frame for _, frame in self.messages)
        self.ack_timeout_s = ack_timeout_s
        self.resend_min_s = resend_min_s
        self.state = "not sent"
        self.rounds = 0  # times the configuration was written (opens and resends)
        self.answers: dict[str, str] = {}  # the last round's: name -> ack | NAK | no answer
        self.problem: str | None = None  # the last round's refusal or silence, in words
        self.rate_acked = False  # the last round's CFG-RATE was taken (ACK-ACK)
        self.losses = 0  # times the receiver lost the setup (lost())
        self.lost_reason: str | None = None  # the last loss, in words
        self._waiting: list[tuple[str, tuple[int, int]]] = []
        self._sent_t = -math.inf
        self._acked_t = 0.0  # when the last round's last ACK arrived
        self._banner_in_round = False  # a start-up banner before any answer of this round
        self._rate_met = False  # the ACKed rate was measured since the round
        self._slow_since: float | None = None
        self._warned: set[str] = set()
        self._lost_warn_t = -math.inf
        self._lost_unwarned = 0  # losses not warned about (LOST_WARN_MIN_S)
        self.resend_s = resend_min_s  # the wait before the next write (RESEND_MAX_S)
        self.not_kept: str | None = None  # the receiver does not keep its setup, in words
        self._loss_kind: str | None = None  # the last loss's kind (lost(): backing off)
        self._repeats = 0  # losses of that kind in a row, each soon after the setup was taken
        self.line_short: str | None = None  # the line cannot carry RMC + GGA at rate_hz
        self.baud_key = "gps.url's baud"  # the setting of the line's baud (GpsReader's)

    def use_baud(self, baud: object, paced: bool = True) -> None:
        """The line rate of the port just opened (pyserial's ``baudrate``; anything but a
        positive int, a socket's none: :data:`DEFAULT_BAUD`): the sentences are chosen for
        it (:func:`neo5_setup`). A line too slow for RMC + GGA at the rate asked
        (:func:`fix_line_short`; the configuration refuses what it knows of: a ``sim://``
        GPS at its scenario's baud is known only now) is one WARNING per baud, naming
        :attr:`baud_key`, and shows in :attr:`line_short`; not on a line its baud does not
        pace (``paced`` false: a native-USB receiver, :func:`_native_usb`)."""
        b = baud if isinstance(baud, int) and not isinstance(baud, bool) and baud > 0 else None
        b = DEFAULT_BAUD if b is None else b
        short = fix_line_short(self.rate_hz, b) if paced else None
        if short is not None:
            short = (
                f"{short}: gps.rate_hz = {self.rate_hz:g} Hz (gps.configure_receiver = true) "
                "makes each fix wait behind the last one's sentences and arrive late, "
                f"sentences lost; lower gps.rate_hz or raise the line's baud rate "
                f"({self.baud_key})"
            )
            if short != self.line_short:
                log.warning("GPS: %s", short)
        self.line_short = short
        if b != self.baud:
            self.baud = b
            self.messages = neo5_setup(self.rate_hz, b)
            self.init_bytes = b"".join(frame for _, frame in self.messages)

    def sent(self, t_s: float) -> None:
        """The frames were written at ``t_s``: every message now waits for its answer."""
        self.rounds += 1
        self.state = "waiting"
        self.problem = None
        self.rate_acked = False
        self._sent_t = t_s
        self._banner_in_round = False
        self._rate_met = False
        self._slow_since = None
        self._waiting = [(name, (frame[2], frame[3])) for name, frame in self.messages]
        self.answers = {name: "waiting" for name, _ in self.messages}

    def not_sent(self, reason: str) -> None:
        """The frames could not be written (``reason``)."""
        self.state = "not written"
        self._waiting = []
        self._problem(f"UBX configuration not written: {reason}", "write")

    def on_ack(self, ack: UbxAck, t_s: float = 0.0) -> bool:
        """An ACK-ACK or ACK-NAK received at ``t_s``: True when it answered one of this
        setup's messages."""
        key = (ack.msg_class, ack.msg_id)
        i = next((i for i, (_, want) in enumerate(self._waiting) if want == key), None)
        if i is None:
            return False
        name = self._waiting.pop(i)[0]
        self.answers[name] = "ack" if ack.acked else "NAK"
        if ack.acked and key == _CFG_RATE:
            self.rate_acked = True
        if not self._waiting:
            self._acked_t = t_s
            self._finish()
        return True

    def on_sentence(self, sentence: str, t_s: float) -> None:
        """A TXT, GLL or VTG sentence received at ``t_s``: a start-up banner, or a sentence
        the setup turned off, after the receiver took the setup means it lost it."""
        kind = sentence[3:6]
        if kind == "TXT":
            if not is_boot_banner(sentence):
                return
            if self.state == "waiting" and all(a == "waiting" for a in self.answers.values()):
                # printed before the receiver read this round's frames, or it restarted on
                # them: the answers (or their absence) tell which (_finish)
                self._banner_in_round = True
            elif self.state in ("acked", "refused", "no answer", "waiting"):
                text = sentence.split(",", 4)[-1].rsplit("*", 1)[0].strip()
                self.lost(t_s, f"the receiver restarted (its start-up banner {text!r})")
        elif (
            self.state == "acked"
            and self.answers.get(f"CFG-MSG {kind} 0") == "ack"
            and t_s - self._acked_t > OFF_GRACE_S
        ):
            self.lost(t_s, f"{kind} sentences came back, which the setup turned off")

    def on_rate(self, t_s: float, rate: FixRate) -> None:
        """Each poll: the fix rate the receiver keeps once it ACKed CFG-RATE. Under
        :data:`SLOW_RATE_RATIO` of it for :data:`RATE_LOST_S`, after it was met, while fixes
        still come (a silent receiver is not a reset one): lost."""
        hz = rate.measured_hz
        if self.state != "acked" or not self.rate_acked or hz is None:
            return
        if hz >= SLOW_RATE_RATIO * self.rate_hz:
            self._rate_met, self._slow_since = True, None
            return
        if not self._rate_met or rate.silent_s(t_s) > 2.0 / max(hz, 0.5):
            self._slow_since = None
            return
        if self._slow_since is None:
            self._slow_since = t_s
        elif t_s - self._slow_since >= RATE_LOST_S:
            self.lost(
                t_s,
                f"fixes arrive at {hz:.2g} Hz for {t_s - self._slow_since:.0f} s after the "
                f"receiver took CFG-RATE for {self.rate_hz:g} Hz",
            )

    def lost(self, t_s: float, reason: str) -> None:
        """The receiver lost the setup (``reason``): counted, told, and due to be sent again
        (:meth:`resend_due`). Nothing new while a loss waits for its resend. The same
        reason again soon after the receiver took the setup doubles the wait (the class's
        doc)."""
        if self.state == "lost":
            return
        kind = _loss_kind(reason)
        soon = self.state == "acked" and t_s - self._acked_t < RESEND_MAX_S
        self.state = "lost"
        self._waiting = []
        self.losses += 1
        self.lost_reason = reason
        if kind != "restart" and kind == self._loss_kind and soon:
            self._repeats += 1
            self.resend_s = min(RESEND_MAX_S, self.resend_s * 2.0)
            text = (
                f"the receiver does not keep its setup: lost {self._repeats + 1} times in a "
                f"row for the same reason soon after it took it (last: {reason}; something "
                "else re-enables them, or it ACKs CFG-MSG and ignores it); written again "
                f"{self.resend_s:.0f} s after the last write (the wait doubles, at most "
                f"{RESEND_MAX_S:.0f} s)"
            )
            if self.not_kept is None:
                log.warning("GPS: %s", text)
            self.not_kept = text
            self._loss_kind = kind
            return  # its own warning, not one a minute on top
        self._loss_kind, self._repeats = kind, 0
        self.resend_s, self.not_kept = self.resend_min_s, None
        if t_s - self._lost_warn_t < LOST_WARN_MIN_S:
            self._lost_unwarned += 1
            return
        more = (
            f" ({self._lost_unwarned} more losses since the last warning)"
            if self._lost_unwarned
            else ""
        )
        self._lost_warn_t, self._lost_unwarned = t_s, 0
        after = max(0.0, self._sent_t + self.resend_s - t_s)
        log.warning(
            "GPS: the receiver lost its configuration: %s%s; gps.configure_receiver: "
            "sending it again%s",
            reason,
            more,
            f" in {after:.0f} s" if after >= 0.5 else "",
        )

    def resend_due(self, t_s: float) -> bool:
        """The setup was lost and the last write is :attr:`resend_s` old: write it again."""
        return self.state == "lost" and t_s - self._sent_t >= self.resend_s

    def check(self, t_s: float) -> None:
        """Messages still unanswered ``ack_timeout_s`` after they were written: no answer."""
        if not self._waiting or t_s - self._sent_t < self.ack_timeout_s:
            return
        for name, _ in self._waiting:
            self.answers[name] = "no answer"
        self._waiting = []
        self._finish(t_s)

    def _finish(self, t_s: float | None = None) -> None:
        """Every message answered or timed out: the round's state, and its problem told."""
        refused = [name for name, a in self.answers.items() if a == "NAK"]
        silent = [name for name, a in self.answers.items() if a == "no answer"]
        if not refused and not silent:
            self.state = "acked"
            return
        if self._banner_in_round:  # it restarted on the frames: not a refusal
            self.state = "waiting"  # (for lost(): a round in progress)
            self.lost(
                self._acked_t if t_s is None else t_s,
                "the receiver restarted while it was being configured (its start-up banner "
                f"came before the answers; {', '.join(refused + silent)} not taken)",
            )
            return
        parts = []
        if refused:
            parts.append(f"the receiver refused (ACK-NAK) {', '.join(refused)}")
        if silent:
            parts.append(
                f"no UBX ACK from the receiver within {self.ack_timeout_s:g} s for "
                f"{', '.join(silent)} (not a u-blox receiver, or the line loses what is sent)"
            )
        self.state = "refused" if refused else "no answer"
        self._problem(
            f"{'; '.join(parts)}: gps.configure_receiver = true, gps.rate_hz = "
            f"{self.rate_hz:g} Hz not set; the receiver goes on as it was configured",
            self.state,
        )

    def _problem(self, text: str, kind: str) -> None:
        self.problem = text
        if kind not in self._warned:  # once per process and kind (each reopen sends again)
            self._warned.add(kind)
            log.warning("GPS: %s", text)

    def status(self) -> dict[str, Any]:
        """JSON-ready: state, the rate asked, the last round's answers, times written, and
        the losses (``losses``; the last one's reason in ``lost``)."""
        out: dict[str, Any] = {
            "state": self.state,
            "rate_hz": self.rate_hz,
            "baud": self.baud,
            "rounds": self.rounds,
            "answers": dict(self.answers),
            "losses": self.losses,
        }
        if self.problem is not None:
            out["problem"] = self.problem
        if self.lost_reason is not None:
            out["lost"] = self.lost_reason
        if self.not_kept is not None:
            out["not_kept"] = self.not_kept
            out["resend_s"] = self.resend_s
        if self.line_short is not None:
            out["line_short"] = self.line_short
        return out


LINE_WINDOW_S = 5.0
"""The span (s) the line's load is measured over (:class:`LineLoad`)."""
LINE_MIN_S = 2.0
"""The least time (s) after an open before the line's load is measured."""
LINE_FULL_RATIO = 0.9
"""A line carrying at least this fraction of what its baud rate can (8N1: baud / 10 bytes/s)
is full (:class:`LineLoad`): the receiver prints more than it carries. A NEO-5 with
:func:`neo5_setup`'s sentences at 4 Hz on 9600 baud loads it 0.7; its defaults at 1 Hz 0.5."""
LINE_CLEAR_RATIO = 0.8
"""A full line is no longer full under this fraction (no WARNING again for a load that
wavers about :data:`LINE_FULL_RATIO`)."""
UNPACED_RATIO = 1.1
"""A load above this for a whole :data:`LINE_WINDOW_S` proves the line is not paced by its
baud rate (a UART cannot carry more than baud / 10 bytes/s; the bytes a late read catches up
on inflate a window only while it spans them): a native-USB receiver (CDC-ACM) opened at any
baud, whose load is then not judged (:class:`LineLoad`)."""


class LineLoad:
    """How full the receiver's serial line is: the bytes read over the last
    :data:`LINE_WINDOW_S` against the ``baud / 10`` bytes/s the line carries (8N1).

    The reader calls :meth:`restart` after each open (``baud`` None: a port whose line rate
    is not known, a socket or a replay: nothing is measured), :meth:`add` with each read (the
    first after an open is what waited in the port: not counted) and :meth:`tick` each poll.
    :attr:`load` is the fraction; :attr:`full` says, while it is at least
    :data:`LINE_FULL_RATIO` (until under :data:`LINE_CLEAR_RATIO`), that the receiver prints
    more than the line carries: each fix then waits behind the sentences before it and
    arrives late, or sentences are lost (4 Hz at 9600 baud with a NEO-5's default sentences:
    every fix ~0.9 s late). A WARNING each time it becomes full, naming ``rate_key`` and
    ``baud_key`` (the settings to change); with :attr:`configured` (the daemon writes the
    setup, which sends only the sentences that fit) it does not advise fewer sentences, and
    with :attr:`known_short` (the setup's ``line_short`` already warned of that cause) the
    full line is logged at INFO, not as a second WARNING.

    A line its baud does not pace (:attr:`paced` false): a native-USB receiver (CDC-ACM,
    ``/dev/ttyACM*``: :func:`_native_usb`, known at the open) or a load above
    :data:`UNPACED_RATIO` for a whole window (a UART cannot carry that; until then a load
    above it is not called full): its bytes/s are still measured, its load is not judged
    (never full), status says ``paced: false`` and one INFO line says so.

    The load, not the fix's latency: a fix's arrival against its UTC time of day needs a
    system clock set to GPS time, which the robot's Pi (no RTC, often no network) and
    hardware in the loop (the scenario's own date and time) do not have; a full line is what
    makes the fixes late, and its load needs only the baud rate."""

    def __init__(
        self,
        rate_key: str = "gps.rate_hz",
        baud_key: str = "the receiver's, in u-center, and gps.url's baud",
    ) -> None:
        self.rate_key, self.baud_key = rate_key, baud_key
        self.baud: int | None = None
        self._reads: deque[tuple[float, int]] = deque()
        self._bytes = 0  # the sum of _reads' sizes
        self._t_open = 0.0
        self._first = True  # the next read is the first since the open
        self.bytes_per_s: float | None = None
        self.load: float | None = None
        self.full: str | None = None
        self._warned = False  # warned, and the load not cleared since
        self.paced = True  # the baud paces the line (a UART, the simulator's pty)
        self.configured = False  # gps.configure_receiver: the daemon chose the sentences
        self.known_short = False  # the setup's line_short already warned of this line
        self._over_since: float | None = None  # the load above UNPACED_RATIO since
        self._unpaced_told = False

    def restart(self, baud: int | None, t_s: float, paced: bool = True) -> None:
        """A port opened at ``t_s`` on a line of ``baud`` (None: not measured); ``paced``
        false: a port its baud does not pace (:func:`_native_usb`)."""
        self.baud = baud
        self._reads.clear()
        self._bytes = 0
        self._t_open, self._first = t_s, True
        self.bytes_per_s = self.load = self.full = None
        self._over_since = None
        self.paced = paced
        if not paced and baud is not None:
            self._not_paced("the port is a native-USB one (CDC-ACM, /dev/ttyACM*)")

    def add(self, n_bytes: int, t_s: float) -> None:
        """``n_bytes`` read at ``t_s``."""
        if self.baud is None:
            return
        if self._first:  # the backlog the port held at the open
            self._first = False
            return
        self._reads.append((t_s, n_bytes))
        self._bytes += n_bytes

    def tick(self, t_s: float) -> None:
        """The load at ``t_s`` (and :attr:`full`, and its WARNING)."""
        if self.baud is None:
            return
        span_s = min(LINE_WINDOW_S, t_s - self._t_open)
        if span_s < LINE_MIN_S:
            return
        reads = self._reads
        while reads and reads[0][0] <= t_s - LINE_WINDOW_S:
            self._bytes -= reads.popleft()[1]
        capacity = self.baud / 10.0
        self.bytes_per_s = self._bytes / span_s
        if not self.paced:
            return  # its load means nothing: never full
        self.load = self.bytes_per_s / capacity
        if self.load < LINE_CLEAR_RATIO:
            self.full, self._warned = None, False
        if self.load > UNPACED_RATIO:  # no UART carries that: not full, and not paced if it lasts
            self.full, self._warned = None, False
            if self._over_since is None:
                self._over_since = t_s
            elif t_s - self._over_since >= LINE_WINDOW_S:
                self.paced, self.load = False, None
                self._not_paced(
                    f"it carried {self.bytes_per_s:.0f} bytes/s for {LINE_WINDOW_S:g} s, more "
                    f"than {self.baud} baud can ({capacity:.0f}): not a UART paced by its baud "
                    "(a native-USB receiver?)"
                )
            return
        self._over_since = None
        if self.load < LINE_FULL_RATIO:
            return
        fewer = (
            "" if self.configured
            else ", send fewer sentences (gps.configure_receiver = true sends those that fit)"
        )  # fmt: skip
        self.full = (
            f"the line is full ({self.used()}, the last {span_s:.0f} s): the receiver prints "
            "more than the line carries, so each fix waits behind the sentences before it and "
            "arrives late (stamped at arrival: its position that much old), or sentences are "
            f"lost; raise the baud rate ({self.baud_key}){fewer}, or lower {self.rate_key}"
        )
        if not self._warned:
            self._warned = True
            # a line the setup already said is short (one WARNING for one cause)
            log.log(logging.INFO if self.known_short else logging.WARNING, "GPS: %s", self.full)

    def _not_paced(self, why: str) -> None:
        """The line is not paced by its baud (``why``): one INFO line per reader."""
        if not self._unpaced_told:
            self._unpaced_told = True
            log.info(
                "GPS: the line is not paced by its baud rate: %s; its load is not judged "
                "(status gps_receiver.line.paced = false)",
                why,
            )

    def used(self) -> str:
        """The load in words: ``"949 of the 960 bytes/s that 9600 baud carries"``."""
        return (
            f"{self.bytes_per_s or 0:.0f} of the {(self.baud or 0) / 10:.0f} bytes/s that "
            f"{self.baud} baud carries"
        )

    def status(self) -> dict[str, Any]:
        """JSON-ready: ``line`` (baud, bytes/s, load, ``paced``; no load when not paced)
        once measured, ``line_full`` when full."""
        if self.baud is None or self.bytes_per_s is None:
            return {}
        line: dict[str, Any] = {"baud": self.baud, "bytes_per_s": round(self.bytes_per_s)}
        if self.load is not None:
            line["load"] = round(self.load, 2)
        line["paced"] = self.paced
        out: dict[str, Any] = {"line": line}
        if self.full is not None:
            out["line_full"] = self.full
        return out


class FixRate:
    """The rate fixes actually arrive at (Hz), against ``expected_hz`` (what the staleness
    limits were checked against, named ``expected_key`` in messages).

    :meth:`add` each fix's receive time, :meth:`tick` on every poll. The rate is that of the
    last :data:`RATE_WINDOW` fixes (at least 5 since :meth:`restart` make a measurement),
    bounded by the time since the oldest of them (n fixes in the time from the first to now):
    it falls while the GPS is silent, and fixes older than :data:`RATE_HORIZON_S` no longer
    count (none left: 0 Hz). :attr:`slow` when it is under :data:`SLOW_RATE_RATIO` of the
    expected rate: fixes then go stale between epochs. A WARNING each time the rate becomes
    slow having been met (or at the first measurement), not again while it stays slow. With
    a :attr:`line` (the reader's :class:`LineLoad`) the text blames the line only while it is
    measured full (the more so when it is too slow for RMC + GGA at the expected rate);
    otherwise the receiver runs slower than the expected rate (:attr:`configured`: though
    the daemon asked it for that rate), and a paced line too slow for it is added (both
    its baud and the receiver's rate need changing); the WARNING waits for the line's first
    measurement."""

    def __init__(self, expected_hz: float | None, expected_key: str = "gps.rate_hz") -> None:
        self.expected_hz = expected_hz
        self.expected_key = expected_key
        self.line: LineLoad | None = None
        self._times: deque[float] = deque(maxlen=RATE_WINDOW)
        self._measuring = False  # 5 fixes since the restart
        self._last_fix_t: float | None = None
        self._interval_s: float | None = None  # between the last two fixes (s)
        self.measured_hz: float | None = None
        self.slow: str | None = None
        self._slow_warned = False  # warned, and the rate not met since
        self.configured = False  # gps.configure_receiver: the daemon asks for expected_hz

    def restart(self) -> None:
        """Measure anew (the port reopened, or the receiver took a new rate)."""
        self._times.clear()
        self._interval_s = None
        self._measuring = False
        self.measured_hz = None
        self.slow = None

    def silent_s(self, t_s: float) -> float:
        """Seconds since the last fix (inf: none yet)."""
        last = self._last_fix_t
        return math.inf if last is None else t_s - last

    def add(self, t_s: float) -> None:
        self._times.append(t_s)
        if self._last_fix_t is not None and t_s > self._last_fix_t:
            self._interval_s = t_s - self._last_fix_t
        self._last_fix_t = t_s
        if len(self._times) >= 5:
            self._measuring = True
        self.tick(t_s)

    def tick(self, t_s: float) -> None:
        """The rate at ``t_s`` (and :attr:`slow`, and its WARNING)."""
        if not self._measuring:
            return
        times = self._times
        while times and times[0] < t_s - RATE_HORIZON_S:
            times.popleft()
        n = len(times)
        if n < 2:
            hz = n / RATE_HORIZON_S
        else:
            span = times[-1] - times[0]
            hz = (n - 1) / span if span > 0 else math.inf
            since = t_s - times[0]
            if since > 0:
                hz = min(hz, n / since)  # the next fix comes no sooner than now
            if math.isinf(hz):
                return
        self.measured_hz = hz
        want = self.expected_hz
        # silent: no fix for SILENT_INTERVALS of the last interval between two (a receiver
        # at 0.09 Hz is slow, steadily, not silent between each of its fixes: a review)
        last_t, interval_s = self._last_fix_t, self._interval_s
        silent = (
            n == 0
            if last_t is None or interval_s is None
            else t_s - last_t > SILENT_INTERVALS * interval_s
        )
        if want is None or hz >= SLOW_RATE_RATIO * want or silent:
            self.slow = None
            self._slow_warned = silent and self._slow_warned  # a slow rate again after: no repeat
            return
        got = f"fixes arrive at {hz:.2g} Hz"
        key = self.expected_key
        head = (
            f"{got}, under {key} = {want:g} Hz that the staleness limits (safety.fix_stale_s, "
            "gps.stale_s) were checked against: fixes go stale between epochs and the robot "
            "holds"
        )
        line = self.line
        baud = line.baud if line is not None and line.paced else None
        load = None if line is None else line.load
        if baud is not None and load is None:
            return  # its first measurement, for the WARNING, comes within seconds
        if load is not None and load > UNPACED_RATIO:
            load = None  # not a UART's (LineLoad): its baud says nothing
        short = None if baud is None or load is None else fix_line_short(want, baud)
        baud_key = "" if line is None else line.baud_key
        if line is not None and line.full is not None:  # measured full: the line's fault
            fewer = "" if self.configured else ", send fewer sentences"
            if short is not None:
                cause = f"the line is the cause: {short}: raise the baud rate ({baud_key})"
            else:
                cause = (
                    f"the line may be the cause: it is full ({line.used()}): raise the baud "
                    f"rate ({baud_key}){fewer}"
                )
            cause += f" or lower {key}"
        else:
            if self.configured:
                cause = (
                    f"the receiver runs slower than {key} though gps.configure_receiver = "
                    f"true asked it for {want:g} Hz (gps_receiver.setup: its answers); lower "
                    f"{key}"
                )
            else:
                cause = (
                    f"the receiver runs slower than {key}: set its rate "
                    f"(gps.configure_receiver = true, or u-center) or lower {key}"
                )
            if line is not None and load is not None:
                cause += f" (the line is not full: {line.used()})"
            if short is not None:
                cause += (
                    f"; the line could not carry {key} either: {short}: raise the baud rate "
                    f"({baud_key}) as well"
                )
        self.slow = f"{head}; {cause}"
        if not self._slow_warned:
            self._slow_warned = True
            log.warning("GPS: %s", self.slow)

    def status(self) -> dict[str, Any]:
        """JSON-ready: measured and expected rate, and the complaint when too slow."""
        out: dict[str, Any] = {
            "measured_rate_hz": None if self.measured_hz is None else round(self.measured_hz, 2),
            "expected_rate_hz": self.expected_hz,
        }
        if self.slow is not None:
            out["slow"] = self.slow
        if self.line is not None:
            out.update(self.line.status())
        return out


def _direct_fd(port: object) -> int | None:
    """The descriptor to read directly: only for pyserial's own POSIX ``Serial`` class (not
    a subclass, a wrapper or another URL handler, whose ``read`` may do more), open."""
    port = _posix_serial(port)
    fd = getattr(port, "fd", None)
    return fd if isinstance(fd, int) and fd >= 0 else None


def _line_baud(port: object) -> int | None:
    """The baud rate of a UART (or pty) opened by pyserial's own POSIX ``Serial``; None for
    anything else (a ``socket://`` port says 9600 of a network stream)."""
    baud = getattr(_posix_serial(port), "baudrate", None)
    return baud if isinstance(baud, int) and baud > 0 else None


def native_usb_path(path: str) -> bool:
    """Whether the serial device ``path`` is a native-USB (CDC-ACM) one, ``/dev/ttyACM*``
    (also through a link: ``/dev/serial/by-id/usb-u-blox_...``), whose baud rate does not
    pace it."""
    return os.path.basename(os.path.realpath(path)).startswith("ttyACM")


def _native_usb(port: object) -> bool:
    """Whether pyserial's own POSIX ``Serial`` ``port`` is at a :func:`native_usb_path`."""
    name = getattr(_posix_serial(port), "port", None)
    return isinstance(name, str) and native_usb_path(name)


def _posix_serial(port: object) -> object:
    """``port`` when it is pyserial's own POSIX ``Serial`` and open, else None."""
    try:
        from serial import serialposix
    except ImportError:  # not POSIX, or no pyserial
        return None
    if type(port) is not serialposix.Serial or not getattr(port, "is_open", False):
        return None
    return port


class PortLike(Protocol):
    """What the reader needs of a port: a pyserial ``Serial`` or ``serial_for_url`` object."""

    def read(self, size: int = 1) -> bytes: ...

    @property
    def in_waiting(self) -> int: ...

    def close(self) -> None: ...


class GpsReader:
    """Poll-driven GPS reader: opens, decodes, reconnects with capped exponential backoff.

    ``open_port`` returns an open port or raises (OSError, pyserial's SerialException or an
    ``X6wdError``). ``init_bytes`` (e.g. UBX ``cfg_rate(...)``) are written after every
    (re)connect; ACK/NAK answers are collected for ``take_acks()``. ``stale_s`` (s): no
    valid sentence for this long makes the health stale; ``transient_limit`` transient read
    errors in a row (``retry_delay_s`` apart) drop the port. ``week_rollover``: a
    :class:`WeekRolloverCorrection` for a live receiver's dates (the daemon's), or None.
    ``setup``: a :class:`ReceiverSetup` written after every open (its bytes after
    ``init_bytes``) and told the answers. ``expected_rate_hz``: the fix rate the
    configuration promises, for :attr:`fix_rate` (None: measured, never judged), set by
    ``expected_rate_key``; ``baud_key``: the setting of the line's baud rate, both named
    when the fixes come too slowly or the line is full (:attr:`line_load`).
    """

    def __init__(
        self,
        open_port: Callable[[], PortLike],
        *,
        stale_s: float = 2.0,
        backoff_initial_s: float = 0.1,
        backoff_max_s: float = 5.0,
        clock: Callable[[], float] = time.monotonic,
        sleep: Callable[[float], None] = time.sleep,
        decoder: GpsDecoder | None = None,
        init_bytes: bytes = b"",
        read_max: int = 4096,
        transient_limit: int = TRANSIENT_LIMIT,
        retry_delay_s: float = 0.01,
        week_rollover: WeekRolloverCorrection | None = None,
        setup: ReceiverSetup | None = None,
        expected_rate_hz: float | None = None,
        expected_rate_key: str = "gps.rate_hz",
        baud_key: str = "the receiver's, in u-center, and gps.url's baud",
    ) -> None:
        if not stale_s > 0:
            raise ConfigError(f"GpsReader stale_s must be > 0 s, got {stale_s!r}")
        if not 0 < backoff_initial_s <= backoff_max_s:
            raise ConfigError(
                "GpsReader backoff must satisfy 0 < backoff_initial_s <= backoff_max_s, got "
                f"{backoff_initial_s!r} and {backoff_max_s!r}"
            )
        if read_max < 1:
            raise ConfigError(f"GpsReader read_max must be >= 1 byte, got {read_max!r}")
        if transient_limit < 1 or not retry_delay_s >= 0:
            raise ConfigError(
                "GpsReader needs transient_limit >= 1 and retry_delay_s >= 0 s, got "
                f"{transient_limit!r} and {retry_delay_s!r}"
            )
        self._open_port = open_port
        self.stale_s = stale_s
        self.backoff_initial_s = backoff_initial_s
        self.backoff_max_s = backoff_max_s
        self._clock = clock
        self._sleep = sleep
        self.decoder = decoder if decoder is not None else GpsDecoder()
        self.init_bytes = init_bytes
        self.setup = setup
        self.fix_rate = FixRate(expected_rate_hz, expected_rate_key)
        """The rate fixes arrive at (measured anew after each open and each CFG-RATE taken)."""
        self.line_load = LineLoad(expected_rate_key, baud_key)
        """How full the receiver's line is (a UART or pty only), measured anew after each open."""
        self.fix_rate.line = self.line_load
        configured = setup is not None
        self.fix_rate.configured = self.line_load.configured = configured
        if setup is not None:
            setup.baud_key = baud_key
        self._read_max = read_max
        self.transient_limit = transient_limit
        self.retry_delay_s = retry_delay_s
        self._port: PortLike | None = None
        self._backoff_s = backoff_initial_s
        self._next_attempt = clock()
        self._tracker = HealthTracker(
            "gps",
            t_s=self._next_attempt,
            stale_s=stale_s,
            corrupt_labels=CORRUPT_LABELS,
            corrupt_minor=frozenset({"skipped_bytes"}),
        )
        self._corrupt_seen = (0, 0, 0, 0)  # the decoder's CORRUPT_LABELS counts, last told
        self._transient_run = 0  # transient read errors in a row on the open port
        self._opened_before = False
        self._data_since_open = False  # bytes read on the port opened last
        self._joining = True  # no frame start seen since the open: the line is joined mid-way
        self._joined_b = 0  # bytes without a frame start since the open
        self.joined_mid_sentence_bytes = 0  # bytes before the first frame start after opens
        self._quiet_reopens = 0  # reopens in a row that read nothing before failing
        self._acks: deque[UbxAck] = deque(maxlen=64)
        self._closed = False
        self._nonblocking = False
        self._fd: int | None = None  # read directly (see _direct_fd), else through the port
        self.week_rollover = week_rollover
        """Moves the dates of a receiver past a GPS week rollover forward (module docstring);
        None: records pass as decoded (a replayed log keeps its own dates)."""

    # -- public

    def poll(self, timeout_s: float = 0.1) -> list[GpsOutput]:
        """Wait at most about ``timeout_s`` (s) for bytes; return the records they complete.

        Returns early as soon as one read produced data. Never raises on device faults;
        after ``close()`` it returns an empty list.
        """
        if self._closed:  # shutdown races with a polling thread: not an error
            return []
        try:
            return self._poll(max(0.0, timeout_s))
        finally:
            # Staleness by time, once per poll: the health never waits for a caller to ask.
            now = self._clock()
            self._tracker.check(now, self.at_end, self.log_silent)
            self.line_load.tick(now)
            self.fix_rate.tick(now)
            setup = self.setup
            if setup is not None:
                if not self.line_load.paced:
                    setup.line_short = None  # measured: its baud does not limit the line
                setup.check(now)
                setup.on_rate(now, self.fix_rate)
                port = self._port
                if port is not None and setup.resend_due(now):
                    self._write_setup(port, now)  # the receiver lost it: again

    def _poll(self, timeout_s: float) -> list[GpsOutput]:
        start = self._clock()
        if self._port is None:
            # At most one open attempt per poll: the wait before it stays within timeout_s.
            if start < self._next_attempt:
                self._sleep(min(self._next_attempt - start, timeout_s))
            now = self._clock()
            if now < self._next_attempt:
                return []
            self._try_open(now)
            if self._port is None:
                return []
        while True:
            remaining = max(0.0, timeout_s - (self._clock() - start))
            run = self._transient_run
            records = self._read_once(remaining)
            if records is not None:
                return records
            if self._port is None or self._transient_run <= run or remaining <= 0:
                return []  # nothing arrived, or the port was dropped
            # A transient error: retry on the same port shortly, within this poll.
            self._sleep(min(self.retry_delay_s, remaining))

    @property
    def health(self) -> DeviceHealth:
        """The GPS link's health (state, error and reconnect counts, times); any thread
        may read it. Updated by :meth:`poll`."""
        return self._tracker.health

    @property
    def state(self) -> DeviceState:
        """Shortcut for ``health.state``."""
        return self._tracker.health.state

    @property
    def at_end(self) -> bool:
        """True when the open port has no more data to give: a ``replay://`` log played to
        its end (a port with an ``eof`` attribute that is true); a live line never is. Any
        thread may read it."""
        return bool(getattr(self._port, "eof", False))

    @property
    def log_silent(self) -> bool:
        """True while a ``replay://`` log is itself silent (its receiver sent nothing then,
        more data follows: the port's ``log_silent``); a live line never is. Any thread may
        read it."""
        return bool(getattr(self._port, "log_silent", False))

    def take_health_events(self) -> list[HealthEvent]:
        """Health transitions (and repeated failed reopens) since the last call, oldest
        first; call from the polling thread."""
        return self._tracker.take_events()

    def take_acks(self) -> list[UbxAck]:
        """UBX ACK/NAK answers received since the last call, oldest first."""
        out = list(self._acks)
        self._acks.clear()
        return out

    def close(self) -> None:
        """Close the port; idempotent."""
        self._closed = True
        self._drop_port("closed")
        self._tracker.closed(self._clock())

    def __enter__(self) -> GpsReader:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- internals

    def _try_open(self, now: float) -> None:
        try:
            port = self._open_port()
        except (OSError, X6wdError) as exc:
            self._next_attempt = now + self._backoff_s
            self._backoff_s = min(self._backoff_s * 2.0, self.backoff_max_s)
            self._tracker.open_failed(f"open failed: {exc}", now, self._next_attempt)
            return
        self._port = port
        self._transient_run = 0
        # Non-blocking reads: this reader waits with select() itself and must never hang in
        # read() (a pyserial port opened with timeout=None blocks until ``size`` bytes).
        try:
            port.timeout = 0  # type: ignore[attr-defined]
            self._nonblocking = True
        except (AttributeError, ValueError, OSError):
            self._nonblocking = False
        self._fd = _direct_fd(port) if self._nonblocking else None
        self.decoder.reset()
        # The backoff is reset only once bytes are read (_read_once): a port that opens but
        # fails before yielding anything is reopened ever more slowly, and is not reported
        # connected while it does (a first open is: staleness then counts from it).
        quiet = self._opened_before and not self._data_since_open
        self._opened_before = True
        self._data_since_open = False
        self._joining, self._joined_b = True, 0
        self._quiet_reopens = self._quiet_reopens + 1 if quiet else 0
        if self._quiet_reopens >= 2:  # one data-less port may be bad luck; two in a row not
            last = self._tracker.health.last_error
            self._tracker.open_failed(
                f"the port reopened {self._quiet_reopens} times in a row without a byte read:"
                f" {last}",
                now,
                count_error=False,
            )
        else:
            self._tracker.opened(now)
        self.fix_rate.restart()
        paced = not _native_usb(port)
        self.line_load.restart(_line_baud(port), now, paced)
        if self.setup is not None:  # the sentences that fit this line (neo5_setup)
            self.setup.use_baud(getattr(port, "baudrate", None), paced)
            self.line_load.known_short = self.setup.line_short is not None
        self._write_setup(port, now)

    def _write_setup(self, port: PortLike, now: float) -> None:
        """Write ``init_bytes`` and the setup's frames (after an open, or again when the
        receiver lost the setup) and tell the setup."""
        setup = self.setup
        out = self.init_bytes + (setup.init_bytes if setup is not None else b"")
        if out:
            write = getattr(port, "write", None)
            if write is None:
                self._tracker.error("port cannot write: UBX configuration not sent", now)
                if setup is not None:
                    setup.not_sent("the port cannot write")
            else:
                try:
                    write(out)
                except OSError as exc:
                    if setup is not None:
                        setup.not_sent(f"write failed: {exc}")
                    self._fail(f"write failed: {exc}")
                else:
                    if setup is not None:
                        setup.sent(now)

    def _read_once(self, wait_s: float) -> list[GpsOutput] | None:
        """One wait+read; None when nothing arrived (or the port failed)."""
        port = self._port
        assert port is not None
        fd = self._fd
        try:
            if fd is not None:  # one select() and one read(): see the module's docstring
                ready, _, _ = select.select([fd], [], [], wait_s)
                if not ready:
                    return None
                try:
                    data = os.read(fd, self._read_max)
                except OSError as exc:
                    if exc.errno in _NO_DATA_ERRNOS:
                        return None
                    raise
                if not data:  # a pty or USB adapter that went away
                    _ = port.in_waiting  # its errno (EIO ...), as pyserial's path reports it
                    raise OSError(
                        "read failed: device reports readiness to read but returned no data "
                        "(device disconnected or multiple access on port?)"
                    )
            else:
                n = port.in_waiting
                if n <= 0:
                    if not self._wait_readable(port, wait_s):
                        return None
                    n = max(1, port.in_waiting)
                data = port.read(max(n, self._read_max) if self._nonblocking else n)
        except (OSError, ValueError, X6wdError) as exc:  # ValueError: fd closed under us
            text = str(exc) if str(exc).startswith("read failed") else f"read failed: {exc}"
            if is_transient(root_oserror(exc)):
                self._transient_run += 1
                if self._transient_run < self.transient_limit:
                    self._tracker.failed(text, self._clock())
                    return None
                text += f" ({self._transient_run} transient errors in a row)"
            self._fail(text)
            return None
        if not data:
            return None
        t_s = self._clock()
        self._transient_run = 0
        self.line_load.add(len(data), t_s)
        if not self._data_since_open:
            self._data_since_open = True
            self._backoff_s = self.backoff_initial_s  # the port works: a break starts anew
            self._quiet_reopens = 0
            if not self._tracker.health.connected:
                self._tracker.opened(t_s)  # connected now that it yields bytes
        if self._joining:
            data = self._join(data)
            if not data:
                return None
        decoded = self.decoder.counters  # the decoder's own counters (updated in place)
        # Good data: sentences whose content was valid (a GGA without a fix is: a receiver
        # still searching says so) and UBX frames; checksum-valid sentences with invalid
        # fields (a latitude of 99 degrees) are not, and leave the GPS to go stale.
        seen = decoded.decoded + self.decoder.framer.counters.ubx_frames
        records = self.decoder.feed(data, t_s)
        after = self.decoder.framer.counters
        invalid = decoded.invalid_fields
        bad = (after.checksum_failures, after.framing_errors, invalid, after.skipped_bytes)
        if bad != self._corrupt_seen:  # rare on a healthy line: the tuple compare is the cost
            self._corrupt_seen = bad
            self._tracker.corrupt(dict(zip(CORRUPT_LABELS, bad, strict=True)), t_s)
        if decoded.decoded + after.ubx_frames > seen:
            self._tracker.good(t_s)
        setup = self.setup
        if setup is not None:
            # before this read's ACKs: the decoder keeps the UBX frames apart from the
            # sentences, so their order within one read is not known, and a banner read
            # with the ACKs is taken as one that came first (a receiver that restarted,
            # then took the setup), not as a loss (a reset within milliseconds of its
            # answers)
            for rec in records:
                if isinstance(rec, NmeaSentence) and rec.text[3:6] in _WATCHED_TYPES:
                    setup.on_sentence(rec.text, t_s)  # a banner, or what the setup turned off
        for frame in self.decoder.take_ubx():
            try:
                ack = parse_ack(frame)
            except ParseError:
                continue
            if ack is not None:
                self._acks.append(ack)
                answered = setup is not None and setup.on_ack(ack, t_s)
                if answered and ack.acked and (ack.msg_class, ack.msg_id) == _CFG_RATE:
                    self.fix_rate.restart()  # the receiver takes the new rate now
        rate = self.fix_rate
        for rec in records:
            if type(rec) is GpsFix:
                rate.add(t_s)
        if self.week_rollover is not None:
            records = self.week_rollover.apply(records)
        return records

    def _join(self, data: bytes) -> bytes:
        """The bytes from the first frame start (an NMEA ``$`` or the UBX sync) on: a port
        opened while the receiver talks starts inside a sentence, and that tail is not line
        noise (every clean HIL start reported "7 skipped bytes"). Counted in
        :attr:`joined_mid_sentence_bytes`; past :data:`JOIN_MAX_B` without a start the bytes
        are decoded as they are (and counted as noise there)."""
        starts = [i for i in (data.find(b"$"), data.find(UBX_SYNC)) if i >= 0]
        at = min(starts) if starts else len(data)
        if self._joined_b + at > JOIN_MAX_B:
            self._joining = False  # too long for a sentence's tail: noise, for the decoder
            return data
        self.joined_mid_sentence_bytes += at
        if not starts:
            self._joined_b += len(data)
            return b""
        self._joining = False
        return data[at:]

    def _wait_readable(self, port: PortLike, wait_s: float) -> bool:
        fileno = getattr(port, "fileno", None)
        if fileno is not None:
            try:
                fd = fileno()
            except (OSError, ValueError, AttributeError):
                fd = None
            if isinstance(fd, int) and fd >= 0:
                ready, _, _ = select.select([fd], [], [], wait_s)
                return bool(ready)
        # No descriptor (in-memory ports): poll in_waiting in small steps.
        step = min(_IDLE_POLL_S, wait_s)
        if step > 0:
            self._sleep(step)
        return port.in_waiting > 0

    def _fail(self, reason: str) -> None:
        self._drop_port(reason)
        now = self._clock()
        self._next_attempt = now + self._backoff_s
        self._backoff_s = min(self._backoff_s * 2.0, self.backoff_max_s)
        self._tracker.lost(reason, now, self._next_attempt)

    def _drop_port(self, reason: str) -> None:
        port = self._port
        self._port = None
        self._fd = None
        if port is not None:
            with contextlib.suppress(Exception):
                port.close()
        self.decoder.reset()
