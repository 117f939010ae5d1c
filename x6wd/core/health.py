"""Device health, sans-IO: a tracker each reader fills, and the rate-limited log of it.

:class:`HealthTracker` is the one place a device's health lives. Its owner (the GPS reader,
the compass driver, the motor link) tells it what happened — opened, open failed, link lost,
an I/O error, good data — always with the time ``t_s`` (s, the owner's monotonic clock);
it never reads a monotonic clock itself, only the wall clock for the ISO stamps (injectable).
It keeps an immutable :class:`~x6wd.core.records.DeviceHealth` snapshot (swapped whole, so any
thread may read :attr:`HealthTracker.health`) and queues a :class:`~x6wd.core.records.HealthEvent`
for every state transition and every repeated failed reopen; the owner's thread drains them
with :meth:`HealthTracker.take_events` (as the GPS reader's UBX acknowledgements are).
Corrupt input the owner's decoder counted and skipped (the GPS's NMEA lines with bad
checksums ...) is in the snapshot (``corrupt``), in one ``corrupt`` event at most every
``corrupt_log_s`` while it grows, and in the stale reason when nothing good came meanwhile.

:class:`HealthLog` writes those events to a logger: every transition once (WARNING into a
bad state, INFO back to good), at most ``burst`` lines per device and then one per
``refill_s``, with a count of what it held back; a repeated failed reopen at most once per
``repeat_s``. Nothing here is per sample: errors inside a state only move the counters.
"""

from __future__ import annotations

import logging
import math
import time
from collections import deque
from collections.abc import Callable, Mapping
from datetime import UTC, datetime

from x6wd.core.records import DeviceHealth, DeviceState, HealthEvent

CONNECTED = DeviceState.CONNECTED
DEGRADED = DeviceState.DEGRADED
STALE = DeviceState.STALE
DISCONNECTED = DeviceState.DISCONNECTED
RECONNECTING = DeviceState.RECONNECTING

TRANSITION = "transition"
OPEN_FAILED = "open_failed"
CORRUPT = "corrupt"

CORRUPT_LOG_S = 60.0
"""At most one ``corrupt`` event (a log line, a recorded device event) per this many seconds
(s) per device: a noisy line is a fault to see, but not one line per bad sentence."""

DEFAULT_RECOVER_S = 1.0
"""Error-free time after which a degraded device counts as connected again (s): a device
failing every few samples stays degraded instead of flapping (and logging) per sample."""

_BAD = frozenset({DEGRADED, STALE, DISCONNECTED, RECONNECTING})


def root_oserror(exc: BaseException) -> BaseException:
    """The OSError carrying an errno behind ``exc``, else ``exc`` itself.

    pyserial raises ``SerialException`` (an OSError without errno) from inside its
    ``except OSError``, so the errno that says "transient" is on the chained exception.
    """
    seen: set[int] = set()
    cur: BaseException | None = exc
    while cur is not None and id(cur) not in seen:
        if isinstance(cur, OSError) and cur.errno is not None:
            return cur
        seen.add(id(cur))
        cur = cur.__cause__ or cur.__context__
    return exc


def utc_now_iso() -> str:
    """The wall clock now as ISO 8601 UTC text with milliseconds."""
    return datetime.now(UTC).isoformat(timespec="milliseconds")


class HealthTracker:
    """Health state machine of one device (see the module docstring).

    ``stale_s`` (s, or None: never stale by time) is how long an open sensor may go without
    good data; ``recover_s`` (s) how long a degraded device must run without errors to count
    as connected again. ``t_s`` is the creation time; the device starts ``disconnected``
    (not opened yet). Not thread-safe for writers: one owner thread calls the methods.

    ``corrupt_labels``: the kinds of corrupt input the owner counts (:meth:`corrupt`), each
    with its words for a person ("lines with bad checksums"); they start at 0, so status
    shows them before anything goes wrong. Kinds in ``corrupt_minor`` (bytes of noise: a
    partial first line at every open) are shown but do not on their own make an event.
    """

    def __init__(
        self,
        device: str,
        *,
        t_s: float,
        stale_s: float | None = None,
        recover_s: float = DEFAULT_RECOVER_S,
        wall_clock: Callable[[], str] = utc_now_iso,
        max_events: int = 256,
        corrupt_labels: Mapping[str, str] | None = None,
        corrupt_minor: frozenset[str] = frozenset(),
        corrupt_log_s: float = CORRUPT_LOG_S,
    ) -> None:
        if stale_s is not None and not (stale_s > 0 and math.isfinite(stale_s)):
            raise ValueError(f"stale_s must be > 0 s or None, got {stale_s!r}")
        if not (recover_s >= 0 and math.isfinite(recover_s)):
            raise ValueError(f"recover_s must be >= 0 s, got {recover_s!r}")
        self.device = device
        self._stale_s = stale_s
        self.recover_s = recover_s
        self._wall = wall_clock
        self._events: deque[HealthEvent] = deque(maxlen=max_events)
        self._state = DISCONNECTED
        self._since_t = t_s
        self._since_utc = wall_clock()
        self._errors = 0
        self._consecutive = 0
        self._last_error = ""
        self._last_error_t: float | None = None
        self._last_error_utc = ""
        self._reconnects = 0
        self._opened_once = False
        self._opened_t: float | None = None
        self._quiet_open_t: float | None = None  # first open of the run of data-less ones
        self._last_data_t: float | None = None
        self._next_attempt_t: float | None = None
        self._open_failures = 0  # failed reopens since the link was lost
        self._down_t: float | None = None  # when the link was lost (for the outage length)
        self._errors_in_episode = 0  # errors since the device last left ``connected``
        self._left_connected_t: float | None = None  # when it did (s): the episode's length
        self._reason = "not opened yet"  # why it is in its state now ("" when connected)
        self._corrupt_labels = dict(corrupt_labels or {})
        self._corrupt_minor = corrupt_minor
        self.corrupt_log_s = corrupt_log_s
        # totals since start; at the last good data; at the last corrupt event (replaced
        # whole, never changed in place: the snapshots share them)
        self._corrupt = dict.fromkeys(self._corrupt_labels, 0)
        self._corrupt_at_good = self._corrupt
        self._corrupt_logged = self._corrupt
        self._t_corrupt_log: float | None = None
        self._health = self._snapshot()

    # -- reading -----------------------------------------------------------------------------

    @property
    def health(self) -> DeviceHealth:
        """The latest snapshot (immutable; safe to read from any thread)."""
        return self._health

    @property
    def state(self) -> DeviceState:
        """Shortcut for ``health.state``."""
        return self._state

    @property
    def stale_s(self) -> float | None:
        """The staleness limit (s), or None when the device is never stale by time."""
        return self._stale_s

    @stale_s.setter
    def stale_s(self, value: float | None) -> None:
        if value is not None and not (value > 0 and math.isfinite(value)):
            raise ValueError(f"stale_s must be > 0 s or None, got {value!r}")
        self._stale_s = value
        self._health = self._snapshot()

    def take_events(self) -> list[HealthEvent]:
        """Events since the last call, oldest first (the owner's thread drains them)."""
        out = list(self._events)
        self._events.clear()
        return out

    # -- what happened -----------------------------------------------------------------------

    def opened(self, t_s: float) -> None:
        """The device was opened (first time, or a reconnect: counted) at ``t_s`` (s).

        Staleness counts from here, not from the data before an outage; but from the first
        of several opens in a row that brought no data (a peer that keeps dropping us).
        """
        reconnect = self._opened_once
        if reconnect:
            self._reconnects += 1
        self._opened_once = True
        quiet = self._opened_t is not None and (
            self._last_data_t is None or self._last_data_t < self._opened_t
        )
        # a reconnect after a connection that brought no data keeps the quiet streak's start:
        # a peer that accepts and drops, never sending, must go stale, not look fresh
        if not quiet:
            self._quiet_open_t = t_s
        self._opened_t = t_s
        self._consecutive = 0
        self._open_failures = 0
        self._next_attempt_t = None
        if reconnect:
            why = f"{self.device} reconnected (reconnect {self._reconnects}"
            down_t, self._down_t = self._down_t, None
            why += f", {t_s - down_t:.2f} s after the loss)" if down_t is not None else ")"
        else:
            why = f"{self.device} connected"
        self._go(CONNECTED, t_s, why)

    def open_failed(
        self,
        error: str,
        t_s: float,
        next_attempt_t_s: float | None = None,
        *,
        count_error: bool = True,
    ) -> None:
        """An attempt to (re)open the device failed at ``t_s`` (s); retried at
        ``next_attempt_t_s`` (s) if known. ``count_error=False``: the owner already counted
        the failure with :meth:`error`."""
        if count_error:
            self._error(error, t_s)
        self._open_failures += 1
        self._next_attempt_t = next_attempt_t_s
        retry = ""
        if next_attempt_t_s is not None:
            retry = f", next attempt in {max(0.0, next_attempt_t_s - t_s):.1f} s"
        if self._state == RECONNECTING:
            self._reason = f"{error}{retry}"
            self._health = self._snapshot()
            self._emit(
                OPEN_FAILED,
                RECONNECTING,
                t_s,
                f"{self.device} still reconnecting ({self._open_failures} failed attempts): "
                f"{error}{retry}",
            )
            return
        self._go(RECONNECTING, t_s, f"{self.device} reconnecting: {error}{retry}")

    def lost(
        self,
        error: str,
        t_s: float,
        next_attempt_t_s: float | None = None,
        *,
        count_error: bool = True,
    ) -> None:
        """The open link failed (unplugged, a non-transient error, retries exhausted) at
        ``t_s`` (s); a reopen is due at ``next_attempt_t_s`` (s) if known.
        ``count_error=False``: the owner already counted the failure with :meth:`error`."""
        if count_error:
            self._error(error, t_s)
        self._next_attempt_t = next_attempt_t_s
        self._open_failures = 0
        if self._state in (DISCONNECTED, RECONNECTING):
            self._health = self._snapshot()
            return
        self._down_t = t_s
        self._go(DISCONNECTED, t_s, f"{self.device} disconnected: {error}")

    def error(self, error: str, t_s: float) -> None:
        """A failed attempt on the open device at ``t_s`` (s) that a retry may still save:
        counted, no state change (see :meth:`degrade`). Staleness is checked too."""
        self._error(error, t_s)
        self._health = self._snapshot()
        self.check(t_s)

    def degrade(self, t_s: float) -> None:
        """Data was lost to errors at ``t_s`` (s) (every retry failed): a connected device
        becomes degraded, naming the last error."""
        if self._state == CONNECTED:
            self._go(DEGRADED, t_s, f"{self.device} degraded: {self._last_error}")

    def failed(self, error: str, t_s: float) -> None:
        """An I/O error that lost data on the open device at ``t_s`` (s): :meth:`error`
        then :meth:`degrade`."""
        self.error(error, t_s)
        self.degrade(t_s)

    def good(self, t_s: float) -> None:
        """Good data at ``t_s`` (s): fresh again, and recovered once error-free for
        ``recover_s``. On a device not open yet this counts as opening it."""
        if self._state in (DISCONNECTED, RECONNECTING):
            self.opened(t_s)
        self._consecutive = 0
        self._corrupt_at_good = self._corrupt
        if self._last_data_t is None or t_s > self._last_data_t:
            self._last_data_t = t_s
        recent_error = self._last_error_t is not None and t_s - self._last_error_t < self.recover_s
        if self._state == STALE:
            gap = t_s - self._since_t
            if recent_error:
                self._go(DEGRADED, t_s, f"{self.device} fresh again after {gap:.1f} s (degraded)")
            else:
                self._go(CONNECTED, t_s, f"{self.device} fresh again after {gap:.1f} s")
        elif self._state == DEGRADED and not recent_error:
            self._go(
                CONNECTED,
                t_s,
                f"{self.device} recovered after {self._errors_in_episode} errors "
                f"({t_s - self._episode_start_t():.1f} s degraded)",
            )
        else:
            self._health = self._snapshot()

    def set_stale(self, t_s: float, why: str) -> None:
        """The owner knows the data is unusable (e.g. too many failed samples in a row).
        Said again while stale: the reason is brought up to date (no new event)."""
        if self._state in (CONNECTED, DEGRADED):
            self._go(STALE, t_s, f"{self.device} stale: {why}")
        elif self._state == STALE and why != self._reason:
            self._reason = why
            self._health = self._snapshot()

    def corrupt(self, counts: Mapping[str, int], t_s: float) -> None:
        """The owner's decoder has counted and skipped ``counts`` (totals since start, by the
        kinds of ``corrupt_labels``) by ``t_s`` (s): shown in the snapshot, and a growth is
        a ``corrupt`` event at most every ``corrupt_log_s``."""
        if counts == self._corrupt:
            return
        self._corrupt = dict(counts)
        self._health = self._snapshot()
        self._corrupt_event(t_s)

    def check(self, t_s: float, ended: bool = False, silent: bool = False) -> None:
        """Time passes: an open device without good data for more than ``stale_s`` is stale;
        corrupt input held back by the event interval is reported once it has passed.
        ``ended``: the source has no more data to give (a replayed log at its end);
        ``silent``: the source itself has nothing now but more later (a replayed log's
        silent stretch). Either is said in the stale reason after any corrupt input's
        cause."""
        if self._corrupt is not self._corrupt_logged:
            self._corrupt_event(t_s)
        stale_s = self._stale_s
        if stale_s is None or self._state not in (CONNECTED, DEGRADED, STALE):
            return
        if self._state == STALE and not self._reason.startswith(("no good data", "no data")):
            return  # the owner's own reason (set_stale) stands
        ref = self._last_data_t
        opened = self._quiet_open_t
        if opened is not None and (ref is None or opened > ref):
            ref = opened  # a fresh connection: count from the open, not the outage
        if ref is None:
            ref = self._since_t
        if t_s - ref > stale_s:
            what = "no good data" if self._last_data_t is not None else "no data yet"
            why = f"{what} for {t_s - ref:.2f} s (limit {stale_s:g} s)"
            # the stream may be arriving, every line of it corrupt: say so
            cause = self._describe(self._corrupt, self._corrupt_at_good)
            # the corrupt input, if any, is still named: a log of the wrong kind
            note = ""
            if ended:
                some = cause or self._last_data_t is not None
                note = "the replayed log has ended" if some else "the replayed log has none"
            elif silent:
                note = "the replayed log is silent here"
            if note:
                cause = f"{cause}; {note}" if cause else note
            self.set_stale(t_s, f"{why}: {cause}" if cause else why)

    def closed(self, t_s: float) -> None:
        """Deliberately closed at ``t_s`` (s): disconnected, no error and no event."""
        self._reason = "closed"
        if self._state != DISCONNECTED:
            self._state = DISCONNECTED
            self._since_t = t_s
            self._since_utc = self._wall()
        self._next_attempt_t = None
        self._health = self._snapshot()

    # -- internals ---------------------------------------------------------------------------

    def _describe(self, now: Mapping[str, int], before: Mapping[str, int]) -> str:
        """The growth from ``before`` to ``now`` in words ("40 lines with bad checksums")."""
        return ", ".join(
            f"{n - before.get(k, 0)} {self._corrupt_labels.get(k, k)}"
            for k, n in now.items()
            if n > before.get(k, 0)
        )

    def _corrupt_event(self, t_s: float) -> None:
        """A ``corrupt`` event for the growth since the last one, unless that was less than
        ``corrupt_log_s`` ago or only minor kinds grew."""
        last = self._t_corrupt_log
        if last is not None and t_s - last < self.corrupt_log_s:
            return
        now, before = self._corrupt, self._corrupt_logged
        if not any(n > before.get(k, 0) for k, n in now.items() if k not in self._corrupt_minor):
            return
        what = f"{self.device} corrupt input skipped"
        if last is None:  # the first: since start
            what += f": {self._describe(now, before)}"
        else:
            what += (
                f" in the last {t_s - last:.0f} s: {self._describe(now, before)} "
                f"(since start: {self._describe(now, {})})"
            )
        self._corrupt_logged, self._t_corrupt_log = now, t_s
        self._emit(CORRUPT, self._state, t_s, what)

    def _episode_start_t(self) -> float:
        """When the device last left ``connected`` (s; a time of 0.0 is one: sim and replay
        clocks start there)."""
        left_t = self._left_connected_t
        return self._since_t if left_t is None else left_t

    def _error(self, error: str, t_s: float) -> None:
        self._errors += 1
        self._errors_in_episode += 1
        self._consecutive += 1
        self._last_error = error
        self._last_error_t = t_s
        self._last_error_utc = self._wall()

    def _go(self, new: DeviceState, t_s: float, message: str) -> None:
        old = self._state
        if new == old:
            self._health = self._snapshot()
            return
        if new == CONNECTED:
            self._errors_in_episode = 0
        elif old == CONNECTED:
            # the whole episode, through stale and back (an outside audit: 4.4 s of errors
            # said "1.0 s degraded", the time since the last step back to degraded)
            self._left_connected_t = t_s
        # the transition's own words, without the device's name: the current fault, not
        # the last error (an old open failure while the open port is silent)
        why = message.removeprefix(f"{self.device} ").removeprefix(f"{new}: ")
        self._reason = "" if new == CONNECTED else why
        self._state = new
        self._since_t = t_s
        self._since_utc = self._wall()
        self._health = self._snapshot()
        self._emit(TRANSITION, old, t_s, message)

    def _emit(self, kind: str, old: DeviceState, t_s: float, message: str) -> None:
        self._events.append(
            HealthEvent(t_s, self.device, kind, old, self._state, message, self._health)
        )

    def _snapshot(self) -> DeviceHealth:
        return DeviceHealth(
            device=self.device,
            state=self._state,
            since_t_s=self._since_t,
            since_utc=self._since_utc,
            errors=self._errors,
            consecutive_errors=self._consecutive,
            last_error=self._last_error,
            last_error_t_s=self._last_error_t,
            last_error_utc=self._last_error_utc,
            reconnects=self._reconnects,
            last_data_t_s=self._last_data_t,
            next_attempt_t_s=self._next_attempt_t,
            stale_s=self._stale_s,
            corrupt=self._corrupt,
            reason=self._reason,
        )


class HealthLog:
    """Writes :class:`HealthEvent` to ``logger``, rate-limited per device.

    Transitions: WARNING into degraded/stale/disconnected/reconnecting, INFO back to
    connected; a token bucket of ``burst`` lines per device refilled one per ``refill_s``
    (s), the next line saying how many were held back. Repeated failed reopens: at most one
    line per ``repeat_s`` (s) per device. Corrupt input (its source already rate-limits it):
    WARNING. ``clock`` (s, monotonic) drives the limits.
    """

    def __init__(
        self,
        logger: logging.Logger,
        *,
        burst: int = 10,
        refill_s: float = 5.0,
        repeat_s: float = 30.0,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self._log = logger
        self.burst = burst
        self.refill_s = refill_s
        self.repeat_s = repeat_s
        self._clock = clock
        self._tokens: dict[str, float] = {}
        self._t_tokens: dict[str, float] = {}
        self._held: dict[str, int] = {}
        self._t_repeat: dict[str, float] = {}

    def event(self, ev: HealthEvent) -> bool:
        """Log ``ev`` unless rate-limited; True when a line was written."""
        now = self._clock()
        dev = ev.device
        if ev.kind == OPEN_FAILED and now - self._t_repeat.get(dev, -math.inf) < self.repeat_s:
            return False
        tokens = min(
            float(self.burst),
            self._tokens.get(dev, float(self.burst))
            + (now - self._t_tokens.get(dev, now)) / self.refill_s,
        )
        self._t_tokens[dev] = now
        if tokens < 1.0:
            self._tokens[dev] = tokens
            self._held[dev] = self._held.get(dev, 0) + 1
            return False
        self._tokens[dev] = tokens - 1.0
        if ev.new == RECONNECTING:  # the first failed reopen starts the repeat interval
            self._t_repeat[dev] = now
        held = self._held.pop(dev, 0)
        text = ev.message
        if held:
            text += f" ({held} earlier {dev} health messages suppressed)"
        level = logging.WARNING if ev.new in _BAD or ev.kind == CORRUPT else logging.INFO
        self._log.log(level, "%s", text)
        return True
