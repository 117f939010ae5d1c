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
receiver sends. Whether configured or not, :class:`FixRate` measures the rate the fixes
actually arrive at and, when it is well under the rate the staleness limits were checked
against (``gps.rate_hz``), says so in status and in one WARNING: fixes then go stale between
epochs and the robot holds.

Note that pyserial's ``socket://`` handler discards whatever arrived before ``open()``
returned; a streaming receiver loses nothing but part of one sentence.
"""

from __future__ import annotations

import contextlib
import dataclasses
import errno
import logging
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
    UbxAck,
    cfg_msg,
    cfg_rate,
    parse_ack,
)
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

_CFG_RATE = (UBX_CLASS_CFG, UBX_ID_CFG_RATE)


def neo5_setup(rate_hz: float) -> list[tuple[str, bytes]]:
    """The UBX messages ``configure_receiver`` sends, (name, frame) in order: CFG-RATE for
    ``rate_hz`` (NEO-5: 0.015..4 Hz), then CFG-MSG on the port they arrive on: GGA and RMC
    every epoch (a fix needs both), GSA and GSV about once a second (every
    ``round(rate_hz)`` epochs: the fix mode, DOPs and the sky change slowly), VTG and GLL off
    (RMC carries speed and course, GGA the time). At 4 Hz that is ~850 bytes/s, what 9600 baud
    carries (960); the receiver's default set (~480 bytes per epoch) would not fit past 2 Hz.
    Raises ConfigError for a rate CFG-RATE cannot carry."""
    meas_ms = round(1000.0 / rate_hz)
    every = max(1, round(rate_hz))
    msgs = [(f"CFG-RATE {meas_ms} ms", cfg_rate(meas_ms))]
    for name, rate in (("GGA", 1), ("RMC", 1), ("GSA", every), ("GSV", every), ("VTG", 0),
                       ("GLL", 0)):  # fmt: skip
        msgs.append((f"CFG-MSG {name} {rate}", cfg_msg(name, rate)))
    return msgs


class ReceiverSetup:
    """The configuration ``[gps] configure_receiver`` writes after every open, and what the
    receiver answered.

    :attr:`init_bytes` are the frames of :func:`neo5_setup`; the reader calls :meth:`sent`
    once it wrote them (or :meth:`not_sent`), hands every ACK/NAK to :meth:`on_ack` and calls
    :meth:`check` on each poll. Each message is answered in order (an ACK names only the
    class and id, so the CFG-MSG answers are matched oldest first). :attr:`state`: ``"not
    sent"`` (no port yet), ``"waiting"``, ``"acked"`` (all ACK-ACK), ``"refused"`` (a NAK),
    ``"no answer"`` (nothing within ``ack_timeout_s``: a receiver configured elsewhere
    answers as well, so this is a receiver that does not speak UBX, a wrong port, or a
    line that loses what is sent) or ``"not written"``. A refusal or a missing answer is
    logged as one WARNING per process and kind; the robot goes on with what the receiver
    sends (:class:`FixRate` shows the rate it actually gets)."""

    def __init__(self, rate_hz: float, *, ack_timeout_s: float = ACK_TIMEOUT_S) -> None:
        self.rate_hz = rate_hz
        self.messages = neo5_setup(rate_hz)
        self.init_bytes = b"".join(frame for _, frame in self.messages)
        self.ack_timeout_s = ack_timeout_s
        self.state = "not sent"
        self.rounds = 0  # opens the configuration was written on
        self.answers: dict[str, str] = {}  # the last round's: name -> ack | NAK | no answer
        self.problem: str | None = None  # the last round's refusal or silence, in words
        self.rate_acked = False  # the last round's CFG-RATE was taken (ACK-ACK)
        self._waiting: list[tuple[str, tuple[int, int]]] = []
        self._sent_t = 0.0
        self._warned: set[str] = set()

    def sent(self, t_s: float) -> None:
        """The frames were written at ``t_s``: every message now waits for its answer."""
        self.rounds += 1
        self.state = "waiting"
        self.problem = None
        self.rate_acked = False
        self._sent_t = t_s
        self._waiting = [(name, (frame[2], frame[3])) for name, frame in self.messages]
        self.answers = {name: "waiting" for name, _ in self.messages}

    def not_sent(self, reason: str) -> None:
        """The frames could not be written (``reason``)."""
        self.state = "not written"
        self._waiting = []
        self._problem(f"UBX configuration not written: {reason}", "write")

    def on_ack(self, ack: UbxAck) -> bool:
        """An ACK-ACK or ACK-NAK: True when it answered one of this setup's messages."""
        key = (ack.msg_class, ack.msg_id)
        i = next((i for i, (_, want) in enumerate(self._waiting) if want == key), None)
        if i is None:
            return False
        name = self._waiting.pop(i)[0]
        self.answers[name] = "ack" if ack.acked else "NAK"
        if ack.acked and key == _CFG_RATE:
            self.rate_acked = True
        if not self._waiting:
            self._finish()
        return True

    def check(self, t_s: float) -> None:
        """Messages still unanswered ``ack_timeout_s`` after they were written: no answer."""
        if not self._waiting or t_s - self._sent_t < self.ack_timeout_s:
            return
        for name, _ in self._waiting:
            self.answers[name] = "no answer"
        self._waiting = []
        self._finish()

    def _finish(self) -> None:
        """Every message answered or timed out: the round's state, and its problem told."""
        refused = [name for name, a in self.answers.items() if a == "NAK"]
        silent = [name for name, a in self.answers.items() if a == "no answer"]
        if not refused and not silent:
            self.state = "acked"
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
        """JSON-ready: state, the rate asked, the last round's answers, opens configured."""
        out: dict[str, Any] = {
            "state": self.state,
            "rate_hz": self.rate_hz,
            "rounds": self.rounds,
            "answers": dict(self.answers),
        }
        if self.problem is not None:
            out["problem"] = self.problem
        return out


class FixRate:
    """The rate fixes actually arrive at (Hz, from their receive times: the last
    :data:`RATE_WINDOW`, at least 5), against ``expected_hz`` (what the staleness limits were
    checked against, named ``expected_key`` in messages). :attr:`slow` (and one WARNING per
    process) when it is under :data:`SLOW_RATE_RATIO` of that: fixes then go stale between
    epochs."""

    def __init__(self, expected_hz: float | None, expected_key: str = "gps.rate_hz") -> None:
        self.expected_hz = expected_hz
        self.expected_key = expected_key
        self._times: deque[float] = deque(maxlen=RATE_WINDOW)
        self.measured_hz: float | None = None
        self.slow: str | None = None
        self._warned = False

    def restart(self) -> None:
        """Measure anew (the port reopened, or the receiver took a new rate)."""
        self._times.clear()
        self.measured_hz = None
        self.slow = None

    def add(self, t_s: float) -> None:
        times = self._times
        times.append(t_s)
        if len(times) < 5 or times[-1] <= times[0]:
            return
        hz = (len(times) - 1) / (times[-1] - times[0])
        self.measured_hz = hz
        want = self.expected_hz
        if want is None or hz >= SLOW_RATE_RATIO * want:
            self.slow = None
            return
        self.slow = (
            f"fixes arrive at {hz:.2g} Hz, under {self.expected_key} = {want:g} Hz that "
            f"the staleness limits (safety.fix_stale_s, gps.stale_s) were checked against: "
            f"fixes go stale between epochs and the robot holds; set the receiver's rate "
            f"(gps.configure_receiver = true, or u-center) or lower {self.expected_key}"
        )
        if not self._warned:
            self._warned = True
            log.warning("GPS: %s", self.slow)

    def status(self) -> dict[str, Any]:
        """JSON-ready: measured and expected rate, and the complaint when too slow."""
        out: dict[str, Any] = {
            "measured_rate_hz": None if self.measured_hz is None else round(self.measured_hz, 2),
            "expected_rate_hz": self.expected_hz,
        }
        if self.slow is not None:
            out["slow"] = self.slow
        return out


def _direct_fd(port: object) -> int | None:
    """The descriptor to read directly: only for pyserial's own POSIX ``Serial`` class (not
    a subclass, a wrapper or another URL handler, whose ``read`` may do more), open."""
    try:
        from serial import serialposix
    except ImportError:  # not POSIX, or no pyserial
        return None
    if type(port) is not serialposix.Serial or not getattr(port, "is_open", False):
        return None
    fd = getattr(port, "fd", None)
    return fd if isinstance(fd, int) and fd >= 0 else None


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
    configuration promises, for :attr:`fix_rate` (None: measured, never judged).
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
        self.fix_rate = FixRate(expected_rate_hz)
        """The rate fixes arrive at (measured anew after each open and each CFG-RATE taken)."""
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
            self._tracker.check(now)
            if self.setup is not None:
                self.setup.check(now)

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
        for frame in self.decoder.take_ubx():
            try:
                ack = parse_ack(frame)
            except ParseError:
                continue
            if ack is not None:
                self._acks.append(ack)
                setup = self.setup
                answered = setup is not None and setup.on_ack(ack)
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
