"""systemd service notification (the ``sd_notify`` protocol) without libsystemd.

systemd passes ``NOTIFY_SOCKET`` (a filesystem path, or ``@name`` for the Linux abstract
namespace) to a ``Type=notify`` service; the service sends newline-separated ``KEY=VALUE``
datagrams to it. ``WATCHDOG_USEC`` (and ``WATCHDOG_PID``) ask for keep-alive pings.
Without ``NOTIFY_SOCKET`` every call is a cheap no-op, so the daemon runs the same outside
systemd.
"""

from __future__ import annotations

import os
import socket
from collections.abc import Mapping

from x6wd.core.errors import ConfigError


def _address(raw: str) -> str:
    if raw.startswith("@"):
        # Abstract namespace: a leading NUL byte instead of '@', no filesystem entry.
        return "\0" + raw[1:]
    if raw.startswith("/"):
        return raw
    raise ConfigError(f"NOTIFY_SOCKET: expected an absolute path or @name, got {raw!r}")


class Notifier:
    """Sends sd_notify messages to the socket named by ``NOTIFY_SOCKET``.

    Failures to send are counted, never raised: a notification must not crash the robot.
    """

    def __init__(self, socket_path: str | None, watchdog_usec: int | None = None) -> None:
        """``socket_path``: NOTIFY_SOCKET (None disables); ``watchdog_usec``: WATCHDOG_USEC."""
        self._address = _address(socket_path) if socket_path else None
        self._sock: socket.socket | None = None
        if self._address is not None:
            self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC)
            self._sock.setblocking(False)
        self.watchdog_usec = watchdog_usec
        self.send_errors = 0
        self.sent = 0
        self._status: str | None = None  # the STATUS last sent
        self._stopping = False  # STOPPING=1 sent: its STATUS is the last

    @classmethod
    def from_env(cls, environ: Mapping[str, str] | None = None) -> Notifier:
        """Build from ``NOTIFY_SOCKET``, ``WATCHDOG_USEC`` and ``WATCHDOG_PID``.

        The watchdog is honoured only when WATCHDOG_PID is absent or names this process,
        as systemd documents.
        """
        env = os.environ if environ is None else environ
        path = env.get("NOTIFY_SOCKET") or None
        usec: int | None = None
        raw = env.get("WATCHDOG_USEC")
        pid = env.get("WATCHDOG_PID")
        if raw and (not pid or pid.strip() == str(os.getpid())):
            try:
                usec = int(raw)
            except ValueError as exc:
                raise ConfigError(f"WATCHDOG_USEC: not an integer: {raw!r}") from exc
            if usec <= 0:
                usec = None
        return cls(path, usec)

    @property
    def enabled(self) -> bool:
        """True when a notification socket is configured."""
        return self._sock is not None

    @property
    def watchdog_interval_s(self) -> float | None:
        """Seconds between WATCHDOG=1 pings (half of WATCHDOG_USEC), or None if not asked."""
        if self.watchdog_usec is None:
            return None
        return self.watchdog_usec / 2e6

    def notify(self, fields: Mapping[str, str | int]) -> bool:
        """Send one datagram of ``KEY=VALUE`` lines; returns True if it was sent."""
        if self._sock is None or self._address is None:
            return False
        msg = "\n".join(f"{k}={v}" for k, v in fields.items())
        if "\0" in msg:
            raise ValueError("sd_notify message must not contain NUL bytes")
        try:
            self._sock.sendto(msg.encode("utf-8"), self._address)
        except OSError:
            self.send_errors += 1
            return False
        self.sent += 1
        return True

    def ready(self, status: str | None = None) -> bool:
        """READY=1 (devices open, service up), optionally with a STATUS line."""
        fields: dict[str, str | int] = {"READY": 1}
        line = _with_status(fields, status)
        fields["MAINPID"] = os.getpid()
        return self._sent_status(self.notify(fields), line)

    def status(self, text: str) -> bool:
        """STATUS=<text>: one line shown by ``systemctl status``. Not sent when it says what
        the last did, nor after :meth:`stopping` (the shutdown's own state changes would
        replace "stopping" with "IDLE": an outside audit). True if sent."""
        line = text.replace("\n", " ")
        if self._stopping or line == self._status:
            return False
        return self._sent_status(self.notify({"STATUS": line}), line)

    def _sent_status(self, sent: bool, line: str | None) -> bool:
        """Remember ``line`` as the STATUS systemd has only if it was ``sent`` (a failed
        send is tried again with the next change); returns ``sent``."""
        if sent and line is not None:
            self._status = line
        return sent

    def watchdog(self) -> bool:
        """WATCHDOG=1 keep-alive ping."""
        return self.notify({"WATCHDOG": 1})

    def stopping(self, status: str | None = None) -> bool:
        """STOPPING=1: the service is shutting down."""
        fields: dict[str, str | int] = {"STOPPING": 1}
        line = _with_status(fields, status)
        self._stopping = True
        return self._sent_status(self.notify(fields), line)

    def close(self) -> None:
        """Close the socket (idempotent)."""
        if self._sock is not None:
            self._sock.close()
            self._sock = None

    def __enter__(self) -> Notifier:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _with_status(fields: dict[str, str | int], status: str | None) -> str | None:
    """Add ``status`` as one line to ``fields`` (nothing for None); the line."""
    if status is None:
        return None
    fields["STATUS"] = line = status.replace("\n", " ")
    return line
