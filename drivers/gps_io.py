"""The GPS I/O edge: a reader over a pyserial-like port that survives unplugging.

``GpsReader.poll(timeout_s)`` is the only call that touches the port. It opens the port when
needed (with capped exponential backoff between failed attempts), waits for bytes at most
about ``timeout_s`` seconds, hands them to the sans-IO ``GpsDecoder`` with the receive time,
and returns the decoded records. A read error (pyserial's ``SerialException`` is an
``OSError``; a pty whose far end closed raises EIO; a socket peer that left reads EOF)
closes the port, marks the GPS disconnected and schedules a reopen: a device fault is data,
never an exception to the caller.

The reader sets ``port.timeout = 0`` on every port it opens and waits with ``select()``
itself, so a port opened blocking cannot hang it. Note that pyserial's ``socket://`` handler
discards whatever arrived before ``open()`` returned; a streaming receiver loses nothing
but part of one sentence.
"""

from __future__ import annotations

import contextlib
import select
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

from drivers.gps_nmea import GpsDecoder, Record, UbxAck, parse_ack
from x6wd.errors import ConfigError, ParseError, X6wdError

STATE_OK = "ok"
STATE_STALE = "stale"
STATE_DISCONNECTED = "disconnected"
_IDLE_POLL_S = 0.01  # wait step for ports that cannot be select()ed


class PortLike(Protocol):
    """What the reader needs of a port: a pyserial ``Serial`` or ``serial_for_url`` object."""

    def read(self, size: int = 1) -> bytes: ...

    @property
    def in_waiting(self) -> int: ...

    def close(self) -> None: ...


@dataclass(frozen=True, slots=True)
class GpsHealth:
    """Reader health at one instant (times in seconds on the reader's clock).

    ``state``: 'ok' (a valid sentence within ``stale_s``), 'stale' (port open, nothing
    valid within ``stale_s``) or 'disconnected' (port closed, reopening with backoff).
    ``reconnects`` counts successful opens after the first one.
    """

    state: str
    connected: bool
    reconnects: int
    last_data_t_s: float | None
    last_error: str
    next_attempt_t_s: float | None


class GpsReader:
    """Poll-driven GPS reader: opens, decodes, reconnects with capped exponential backoff.

    ``open_port`` returns an open port or raises (OSError, pyserial's SerialException or an
    ``X6wdError``). ``init_bytes`` (e.g. UBX ``cfg_rate(...)``) are written after every
    (re)connect; ACK/NAK answers are collected for ``take_acks()``.
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
        self._open_port = open_port
        self.stale_s = stale_s
        self.backoff_initial_s = backoff_initial_s
        self.backoff_max_s = backoff_max_s
        self._clock = clock
        self._sleep = sleep
        self.decoder = decoder if decoder is not None else GpsDecoder()
        self.init_bytes = init_bytes
        self._read_max = read_max
        self._port: PortLike | None = None
        self._opened_once = False
        self._reconnects = 0
        self._backoff_s = backoff_initial_s
        self._next_attempt = clock()
        self._last_data: float | None = None
        self._last_error = ""
        self._acks: deque[UbxAck] = deque(maxlen=64)
        self._closed = False
        self._nonblocking = False

    # -- public

    def poll(self, timeout_s: float = 0.1) -> list[Record]:
        """Wait at most about ``timeout_s`` (s) for bytes; return the records they complete.

        Returns early as soon as one read produced data. Never raises on device faults;
        after ``close()`` it returns an empty list.
        """
        if self._closed:  # shutdown races with a polling thread: not an error
            return []
        timeout_s = max(0.0, timeout_s)
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
        remaining = max(0.0, timeout_s - (self._clock() - start))
        return self._read_once(remaining) or []

    @property
    def health(self) -> GpsHealth:
        """Current state (ok / stale / disconnected), reconnect count, last data time."""
        now = self._clock()
        if self._port is None:
            state = STATE_DISCONNECTED
        elif self._last_data is None or now - self._last_data > self.stale_s:
            state = STATE_STALE
        else:
            state = STATE_OK
        return GpsHealth(
            state=state,
            connected=self._port is not None,
            reconnects=self._reconnects,
            last_data_t_s=self._last_data,
            last_error=self._last_error,
            next_attempt_t_s=None if self._port is not None else self._next_attempt,
        )

    @property
    def state(self) -> str:
        """Shortcut for ``health.state``."""
        return self.health.state

    def take_acks(self) -> list[UbxAck]:
        """UBX ACK/NAK answers received since the last call, oldest first."""
        out = list(self._acks)
        self._acks.clear()
        return out

    def close(self) -> None:
        """Close the port; idempotent."""
        self._closed = True
        self._drop_port("closed")

    def __enter__(self) -> GpsReader:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- internals

    def _try_open(self, now: float) -> None:
        try:
            port = self._open_port()
        except (OSError, X6wdError) as exc:
            self._last_error = f"open failed: {exc}"
            self._next_attempt = now + self._backoff_s
            self._backoff_s = min(self._backoff_s * 2.0, self.backoff_max_s)
            return
        self._port = port
        # Non-blocking reads: this reader waits with select() itself and must never hang in
        # read() (a pyserial port opened with timeout=None blocks until ``size`` bytes).
        try:
            port.timeout = 0  # type: ignore[attr-defined]
            self._nonblocking = True
        except (AttributeError, ValueError, OSError):
            self._nonblocking = False
        self.decoder.reset()
        if self._opened_once:
            self._reconnects += 1
        self._opened_once = True
        self._backoff_s = self.backoff_initial_s
        # Fresh connection: staleness counts from now, not from before the outage.
        self._last_data = None
        if self.init_bytes:
            write = getattr(port, "write", None)
            if write is None:
                self._last_error = "port cannot write: UBX configuration not sent"
            else:
                try:
                    write(self.init_bytes)
                except OSError as exc:
                    self._fail(f"write failed: {exc}")

    def _read_once(self, wait_s: float) -> list[Record] | None:
        """One wait+read; None when nothing arrived (or the port failed)."""
        port = self._port
        assert port is not None
        try:
            n = port.in_waiting
            if n <= 0:
                if not self._wait_readable(port, wait_s):
                    return None
                n = max(1, port.in_waiting)
            data = port.read(max(n, self._read_max) if self._nonblocking else n)
        except (OSError, ValueError, X6wdError) as exc:  # ValueError: fd closed under us
            self._fail(f"read failed: {exc}")
            return None
        if not data:
            return None
        t_s = self._clock()
        before = self.decoder.framer.counters
        seen = before.sentences + before.ubx_frames
        records = self.decoder.feed(data, t_s)
        after = self.decoder.framer.counters
        if after.sentences + after.ubx_frames > seen:
            self._last_data = t_s
        for frame in self.decoder.take_ubx():
            try:
                ack = parse_ack(frame)
            except ParseError:
                continue
            if ack is not None:
                self._acks.append(ack)
        return records

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
        self._last_error = reason
        self._drop_port(reason)
        now = self._clock()
        self._next_attempt = now + self._backoff_s
        self._backoff_s = min(self._backoff_s * 2.0, self.backoff_max_s)

    def _drop_port(self, reason: str) -> None:
        port = self._port
        self._port = None
        if port is not None:
            with contextlib.suppress(Exception):
                port.close()
        self.decoder.reset()
