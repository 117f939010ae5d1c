"""Simulated UARTs: an in-memory byte pipe for fast time, a pseudo-terminal for real time.

:class:`MemoryUart` is what the fast-time mission uses: the simulated receiver writes its
burst, the real decoder reads it back, no clocks involved. It behaves like a pyserial port
opened with ``timeout=0`` (``read`` returns what is there, possibly nothing).

:class:`PtyUart` is for hardware-in-the-loop: :attr:`PtyUart.port_name` is a path pyserial
opens exactly like ``/dev/ttyS0``. In real-time mode the writer is paced at the baud rate
(10 bits per byte for 8N1) so a burst arrives over the time it would take on the wire, and
bytes nobody reads are dropped once the kernel buffer is full, as a real UART drops them.
:meth:`PtyUart.close` unplugs the device (the reader sees a hang-up) and
:meth:`PtyUart.reopen` plugs a new one in; with ``link`` the path stays the same.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import os
import select
import termios
import time
import tty
from collections.abc import Callable
from pathlib import Path
from typing import Any

from sim_backend.nmea_out import wire_time_s
from x6wd.core.errors import ConfigError, DeviceIOError

DEFAULT_BAUD = 9600
PACE_CHUNK_S = 0.01  # pacing granularity in real-time mode


def _check_baud(baud: int) -> int:
    if isinstance(baud, bool) or not isinstance(baud, int) or baud <= 0:
        raise ConfigError(f"baudrate must be a positive integer, got {baud!r}")
    return baud


class MemoryUart:
    """In-memory byte pipe with the pyserial read/write surface (non-blocking reads).

    ``max_buffer`` caps unread bytes; beyond it new bytes are dropped (a UART overrun) and
    counted in :attr:`dropped`.
    """

    def __init__(self, baudrate: int = DEFAULT_BAUD, max_buffer: int = 1 << 20) -> None:
        self.baudrate = _check_baud(baudrate)
        if max_buffer <= 0:
            raise ConfigError(f"max_buffer must be positive, got {max_buffer}")
        self.max_buffer = max_buffer
        self._buf = bytearray()
        self._pos = 0
        self.is_open = True
        self.dropped = 0
        self.written = 0

    def _check_open(self) -> None:
        if not self.is_open:
            raise DeviceIOError("MemoryUart is closed")

    @property
    def in_waiting(self) -> int:
        """Bytes written and not yet read."""
        return len(self._buf) - self._pos

    def write(self, data: bytes) -> int:
        """Append ``data`` for the reader; returns the number of bytes accepted."""
        self._check_open()
        room = self.max_buffer - self.in_waiting
        accepted = data if len(data) <= room else data[: max(0, room)]
        self.dropped += len(data) - len(accepted)
        self._buf += accepted
        self.written += len(accepted)
        return len(accepted)

    def read(self, size: int = 1) -> bytes:
        """Up to ``size`` bytes already waiting (b'' when none, like pyserial timeout=0)."""
        self._check_open()
        if size < 0:
            raise ValueError(f"size must be >= 0, got {size}")
        end = min(len(self._buf), self._pos + size)
        out = bytes(self._buf[self._pos : end])
        self._pos = end
        if self._pos > 65536 and self._pos * 2 > len(self._buf):
            del self._buf[: self._pos]  # compact now and then, not on every read
            self._pos = 0
        return out

    def read_all(self) -> bytes:
        """Everything waiting."""
        return self.read(self.in_waiting)

    def readline(self) -> bytes:
        """Up to and including the next ``\\n``, or what is waiting if there is none."""
        self._check_open()
        i = self._buf.find(b"\n", self._pos)
        return self.read((i + 1 - self._pos) if i >= 0 else self.in_waiting)

    def reset_input_buffer(self) -> None:
        """Discard unread bytes."""
        self._buf.clear()
        self._pos = 0

    def flush(self) -> None:
        """Nothing to flush: writes are immediately readable."""

    def close(self) -> None:
        """Close (idempotent); further reads and writes raise :class:`DeviceIOError`."""
        self.is_open = False

    def __enter__(self) -> MemoryUart:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class PtyUart:
    """A pseudo-terminal standing in for the receiver's UART.

    The simulator holds the master side; :attr:`port_name` (the slave, or ``link`` if given)
    is what the daemon opens with pyserial. ``realtime`` paces :meth:`write` at ``baudrate``
    (blocking for the burst's wire time); otherwise writes go straight through.
    ``sleep``/``clock`` are injectable for the pacing.
    """

    def __init__(
        self,
        baudrate: int = DEFAULT_BAUD,
        *,
        realtime: bool = True,
        link: str | os.PathLike[str] | None = None,
        sleep: Callable[[float], Any] = time.sleep,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.baudrate = _check_baud(baudrate)
        self.realtime = realtime
        self.link = None if link is None else Path(link)
        self._sleep = sleep
        self._clock = clock
        self.dropped = 0
        self.written = 0
        self._master = -1
        self._slave = -1
        self._slave_name = ""
        self._wire_free_at = 0.0
        self._open()

    def _open(self) -> None:
        master, slave = os.openpty()
        try:
            # Raw so no byte is translated (CR/LF) or echoed; pyserial sets its own mode too.
            tty.setraw(slave)
            attrs = termios.tcgetattr(slave)
            attrs[4] = attrs[5] = getattr(termios, f"B{self.baudrate}", termios.B9600)
            termios.tcsetattr(slave, termios.TCSANOW, attrs)
            tty.setraw(master)
            flags = fcntl.fcntl(master, fcntl.F_GETFL)
            fcntl.fcntl(master, fcntl.F_SETFL, flags | os.O_NONBLOCK)
            name = os.ttyname(slave)
        except BaseException:
            os.close(master)
            os.close(slave)
            raise
        self._master, self._slave, self._slave_name = master, slave, name
        if self.link is not None:
            tmp = self.link.with_name(self.link.name + ".tmp")
            with contextlib.suppress(FileNotFoundError):
                tmp.unlink()
            tmp.symlink_to(name)
            tmp.replace(self.link)  # atomic: a reader never sees the path missing
        self._wire_free_at = self._clock()

    @property
    def is_open(self) -> bool:
        """True while plugged in."""
        return self._master >= 0

    @property
    def port_name(self) -> str:
        """Path for ``serial.Serial(port_name, baudrate)``: the link if given, else the slave."""
        return str(self.link) if self.link is not None else self._slave_name

    @property
    def slave_name(self) -> str:
        """The current ``/dev/pts/N`` (changes on :meth:`reopen`)."""
        return self._slave_name

    def _check_open(self) -> None:
        if self._master < 0:
            raise DeviceIOError("PtyUart is closed (unplugged)")

    def _write_now(self, data: bytes) -> int:
        try:
            n = os.write(self._master, data)
        except BlockingIOError:
            n = 0
        except OSError as exc:
            if exc.errno == errno.EIO:
                n = 0
            else:
                raise DeviceIOError(f"pty write failed: {exc}") from exc
        self.dropped += len(data) - n  # nobody reading: a real UART loses these too
        self.written += n
        return n

    def write(self, data: bytes) -> int:
        """Send ``data``; in real-time mode blocks until it would have left the wire.

        Returns the number of bytes given (dropped ones included, as a UART does not know).
        """
        self._check_open()
        if not self.realtime:
            self._write_now(data)
            return len(data)
        per_chunk = max(1, int(self.baudrate / 10 * PACE_CHUNK_S))
        for i in range(0, len(data), per_chunk):
            chunk = data[i : i + per_chunk]
            now = self._clock()
            start = max(now, self._wire_free_at)
            if start > now:
                self._sleep(start - now)
            self._write_now(chunk)
            self._wire_free_at = start + wire_time_s(len(chunk), self.baudrate)
        remaining = self._wire_free_at - self._clock()
        if remaining > 0:
            self._sleep(remaining)
        return len(data)

    def read(self, size: int = 1, timeout_s: float = 0.0) -> bytes:
        """Bytes the host sent to the device (e.g. UBX configuration), up to ``size``."""
        self._check_open()
        if timeout_s > 0:
            select.select([self._master], [], [], timeout_s)
        try:
            return os.read(self._master, size)
        except (BlockingIOError, OSError):
            return b""

    def close(self) -> None:
        """Unplug: close both ends (idempotent). An open reader sees a hang-up."""
        for fd in (self._master, self._slave):
            if fd >= 0:
                with contextlib.suppress(OSError):
                    os.close(fd)
        self._master = self._slave = -1

    def reopen(self) -> None:
        """Plug in again (a new pty; ``port_name`` unchanged when a ``link`` is used)."""
        self.close()
        self._open()

    def __enter__(self) -> PtyUart:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
        if self.link is not None:
            with contextlib.suppress(FileNotFoundError):
                self.link.unlink()
