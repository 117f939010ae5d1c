"""Device faults a second outside audit found, each on the real part: pseudo-terminals for the
serial devices, the real `x6wd run` process where the behaviour is the daemon's.

- A port another process holds for a moment at start-up is a runtime condition, not a
  configuration error: the GPS reports 'in use' and retries; the motors fail the start-up
  (exit 1, which systemd restarts), as for any motor port that cannot be opened.
- The start-up check opens no serial port (an open and close toggles DTR: an Arduino-class
  board resets).
- A port held exclusively (TIOCEXCL, EBUSY) is reported as in use.
- The motor link rides out a short EIO hiccup on the same port, backs off a port that
  reopens but keeps failing (counted in status, logged once), and is degraded while most
  commands need a retry.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import errno
import logging
import os
import re
import select
import shutil
import struct
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
import serial

from drivers import registry
from drivers.motors import SerialMotorLink
from tests.conftest import ROOT
from tests.test_daemon import wait_for
from tests.test_driver_faults_audit import PluggedBoard, PtyPeer, plugged
from tests.test_shutdown import DaemonProcess
from tests.test_startup import run_x6wd, write_config
from x6wd.app.client import RemoteClient

__all__ = ["plugged"]  # the fixture, shared with test_driver_faults_audit

pytestmark = pytest.mark.integration


def nmea(body: str) -> bytes:
    c = 0
    for ch in body.encode("ascii"):
        c ^= ch
    return f"${body}*{c:02X}\r\n".encode("ascii")


NO_FIX = nmea("GPGGA,,,,,,0,00,99.9,,,,,,") + nmea("GPRMC,,V,,,,,,,,,,N")


class PtyGps(PtyPeer):
    """A receiver on a pseudo-terminal sending no-fix sentences every 0.1 s."""

    def __init__(self) -> None:
        super().__init__()
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.wait(0.1):
            try:
                os.write(self.master, NO_FIX)
            except OSError:
                return
            try:  # nobody reading: drop what piled up, as a UART's FIFO overruns
                while os.read(self.master, 4096):
                    pass
            except BlockingIOError:
                pass
            except OSError:
                pass


@pytest.fixture
def pty_gps() -> Iterator[PtyGps]:
    g = PtyGps()
    os.set_blocking(g.master, False)
    yield g
    g.close()


def test_a_gps_port_held_at_start_up_is_retried_and_connects_once_released(
    tmp_path: Path, pty_gps: PtyGps
) -> None:
    holder = serial.Serial(pty_gps.path, exclusive=True)  # gpsd hot-plug, a terminal program
    p: DaemonProcess | None = None
    try:
        p = DaemonProcess(write_config(tmp_path, gps={"url": f"serial://{pty_gps.path}"}))
        assert p.port is not None
        with RemoteClient("127.0.0.1", p.port) as c:
            gps = wait_for(
                lambda: (
                    (g := c.request("status")["devices"]["gps"])["state"] == "reconnecting" and g
                ),
                10,
                "gps reconnecting",
            )
            assert f"{pty_gps.path} is in use: another process holds it" in gps["reason"], gps
            assert gps["next_attempt_t_s"] is not None
            holder.close()
            wait_for(
                lambda: c.request("status")["devices"]["gps"]["state"] == "connected",
                15,
                "gps connected once released",
            )
        assert p.proc.poll() is None
    finally:
        holder.close()
        if p is not None:
            p.stop()


def test_a_motor_port_held_at_start_up_fails_the_start_up_for_a_restart(
    tmp_path: Path, pty_gps: PtyGps
) -> None:
    path = pty_gps.path  # any terminal will do: it is never reached
    holder = serial.Serial(path, exclusive=True)
    try:
        proc = run_x6wd(write_config(tmp_path, motors={"url": f"serial://{path}"}), 30)
    finally:
        holder.close()
    assert proc.returncode == 1, proc.stderr  # not 2: systemd restarts exit 1
    assert f"{path} is in use: another process holds it" in proc.stderr, proc.stderr
    assert "startup failed" in proc.stderr and "Traceback" not in proc.stderr


IN_OPEN = 0x20


def opens_of(path: str, action: Callable[[], object]) -> int:
    """How many times ``path`` was opened during ``action`` (inotify's IN_OPEN)."""
    libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
    fd = libc.inotify_init1(os.O_NONBLOCK | os.O_CLOEXEC)
    assert fd >= 0, os.strerror(ctypes.get_errno())
    try:
        assert libc.inotify_add_watch(fd, os.fsencode(path), IN_OPEN) >= 0
        action()
        data = b""
        try:
            while chunk := os.read(fd, 4096):
                data += chunk
        except BlockingIOError:
            pass
        n, i = 0, 0
        while i < len(data):
            _wd, mask, _cookie, length = struct.unpack_from("iIII", data, i)
            n += bool(mask & IN_OPEN)
            i += 16 + length
        return n
    finally:
        os.close(fd)


def test_the_start_up_check_opens_no_serial_port(pty_gps: PtyGps) -> None:
    url = f"serial://{pty_gps.path}?baud=115200"
    assert opens_of(pty_gps.path, lambda: registry.check_available(url, "motors")) == 0
    port = None

    def really_open() -> None:
        nonlocal port
        port = registry.open_gps_port(url.replace("115200", "9600"))

    assert opens_of(pty_gps.path, really_open) == 1  # the watch sees an open
    assert port is not None
    port.close()


@pytest.mark.skipif(
    os.geteuid() != 0 or shutil.which("setpriv") is None,
    reason="TIOCEXCL binds only an unprivileged opener: needs root to run one as nobody",
)
def test_a_port_held_exclusively_is_reported_in_use(pty_gps: PtyGps) -> None:
    import fcntl
    import termios

    os.chmod(pty_gps.path, 0o666)
    fcntl.ioctl(pty_gps.slave, termios.TIOCEXCL)  # as gpsd and ModemManager hold a port
    code = (
        f"import sys; sys.path.insert(0, {str(ROOT)!r})\n"
        "from drivers import registry\n"
        f"try: registry.open_gps_port('serial://{pty_gps.path}')\n"
        "except Exception as e: print(type(e).__name__, e)\n"
    )
    out = subprocess.run(
        ["setpriv", "--reuid=65534", "--regid=65534", "--clear-groups", sys.executable, "-c", code],
        capture_output=True,
        text=True,
        timeout=30,
        cwd="/tmp",
    )
    assert out.stdout.startswith("DeviceUnavailable"), out
    assert f"{pty_gps.path} is in use: another process holds it (opened exclusively" in (
        out.stdout
    ), out.stdout


# --- the motor link: transient errors, reopens, retries --------------------------------------


class EioWrites:
    """pyserial writes to one port failing with EIO on demand, raised as pyserial raises it
    (a SerialException while handling the OSError): the OS boundary, which a pty cannot be
    made to fail at will. ``next(n)``: the next n writes fail; ``until``: every write
    before that monotonic time fails; ``always``."""

    def __init__(self, monkeypatch: pytest.MonkeyPatch, path: str) -> None:
        import serial.serialposix as sp

        self.path = os.path.realpath(path)
        self.next_n = 0
        self.until = 0.0
        self.always = False
        self.failed = 0
        original = sp.Serial.write

        def write(port: Any, data: bytes) -> int | None:
            if os.path.realpath(port.portstr) == self.path and (
                self.always or self.next_n > 0 or time.monotonic() < self.until
            ):
                self.failed += 1
                self.next_n = max(0, self.next_n - 1)
                try:
                    raise OSError(errno.EIO, "Input/output error")
                except OSError as e:
                    raise serial.SerialException(f"write failed: {e}") from e
            result: int | None = original(port, data)
            return result

        monkeypatch.setattr(sp.Serial, "write", write)


def transitions(link: SerialMotorLink) -> list[str]:
    return [e.new for e in link.take_health_events() if e.kind == "transition"]


def test_a_short_eio_hiccup_is_ridden_out_on_the_same_port(
    plugged: PluggedBoard, monkeypatch: pytest.MonkeyPatch
) -> None:
    eio = EioWrites(monkeypatch, str(plugged.link))
    link = registry.open_motors(f"serial://{plugged.link}?baud=115200&retries=2")
    assert isinstance(link, SerialMotorLink)
    try:
        assert link.drive(10, 10)
        link.take_health_events()
        eio.next_n = 3  # one command's three back-to-back attempts fail
        assert not link.ping()
        assert link.ping()  # the same port carries the next one
        assert "disconnected" not in transitions(link)  # not closed: one command lost
        eio.until = time.monotonic() + 0.06  # a 60 ms hiccup across commands
        end = time.monotonic() + 0.3
        while time.monotonic() < end:
            link.ping()
            time.sleep(0.02)
        assert eio.failed >= 5
        assert link.ping() and link.drive(20, 20) and plugged.board.left_pct == 20
        assert link.counters.reopens == 0  # the port was never closed
    finally:
        link.close()


def test_a_port_that_reopens_but_keeps_failing_backs_off(
    plugged: PluggedBoard, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    eio = EioWrites(monkeypatch, str(plugged.link))
    link = registry.open_motors(f"serial://{plugged.link}?baud=115200")
    assert isinstance(link, SerialMotorLink)
    try:
        assert link.drive(10, 10)
        eio.always = True  # every write fails, every reopen succeeds
        with caplog.at_level(logging.INFO, logger="drivers.motors"):
            end = time.monotonic() + 4.0
            while time.monotonic() < end:
                link.ping()
                time.sleep(0.05)
        # broken after 0.5 s, then reopened 0.2, 0.4, 0.8, 1.6 s apart: 3 or 4 in 4 s (the
        # backoff was reset by every open: 15 and more)
        assert 2 <= link.counters.reopens <= 4, link.counters
        lines = [r for r in caplog.records if "motor port reopened" in r.getMessage()]
        assert len(lines) == 1, [r.getMessage() for r in lines]
        h = link.health
        assert h.state == "reconnecting", h
        assert h.next_attempt_t_s is not None, h
        assert f"reopened {link.counters.reopens} times and still fails" in h.reason, h.reason
        eio.always = False
        wait_for(lambda: link.ping(), 8, "the board reached once writes work")
        assert link.health.state == "connected"
        assert link.drive(20, 20) and plugged.board.left_pct == 20
        # a command went through: the next break starts the backoff at 0.2 s again
        assert link._reopen_backoff_s == link.reopen_initial_s
    finally:
        link.close()


class FlakyBoard(PluggedBoard):
    """A MotorBoard that ignores every other command while :attr:`flaky`."""

    def __init__(self, link: Path) -> None:
        super().__init__(link)
        self.flaky = True
        self.lines = 0

    def plug(self) -> None:
        master = self.new_port()
        self._thread = threading.Thread(target=self._serve, args=(master,), daemon=True)
        self._thread.start()

    def _serve(self, fd: int) -> None:
        buf = b""
        while not self._stop.is_set():
            ready, _, _ = select.select([fd], [], [], 0.005)
            if not ready:
                continue
            try:
                buf += os.read(fd, 4096)
            except OSError:
                return
            while b"\n" in buf:
                line, buf = buf.split(b"\n", 1)
                self.lines += 1
                if self.flaky and self.lines % 2:
                    continue  # lost
                reply = self.board.feed(line + b"\n", time.monotonic())
                if reply:
                    os.write(fd, reply)


def test_a_board_answering_every_other_command_is_degraded(tmp_path: Path) -> None:
    board = FlakyBoard(tmp_path / "ttyACM-board")
    board.plug()
    link = registry.open_motors(f"serial://{board.link}?baud=115200&retries=1")
    assert isinstance(link, SerialMotorLink)
    try:
        for _ in range(25):
            assert link.ping()  # every command gets through, at its retry
        h = link.health
        assert h.state == "degraded", h
        assert re.search(r"^1\d of the last [12]\d commands needed a retry", h.reason), h.reason
        board.flaky = False
        end = time.monotonic() + 1.5
        while time.monotonic() < end:
            assert link.ping()
            time.sleep(0.05)
        assert link.health.state == "connected", link.health
    finally:
        link.close()
        board.unplug()


# --- the GPS reader: a port that opens but yields nothing ------------------------------------


class DroppingPeer:
    """A ser2net-like TCP GPS that accepts and closes at once (the reader reads EOF) until
    :attr:`streaming`, then sends no-fix sentences."""

    def __init__(self) -> None:
        import socket

        self.sock = socket.create_server(("127.0.0.1", 0))
        self.port = self.sock.getsockname()[1]
        self.accepts = 0
        self.streaming = False
        self._stop = threading.Event()
        self.sock.settimeout(0.05)
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                conn, _ = self.sock.accept()
            except TimeoutError:
                continue
            self.accepts += 1
            with conn:
                while self.streaming and not self._stop.is_set():
                    try:
                        conn.sendall(NO_FIX)
                    except OSError:
                        break
                    time.sleep(0.1)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(5)
        self.sock.close()


def test_a_gps_port_that_reopens_but_yields_nothing_backs_off_and_is_not_connected() -> None:
    from drivers.gps_io import GpsReader

    peer = DroppingPeer()
    reader = GpsReader(lambda: registry.open_gps_port(f"tcp://127.0.0.1:{peer.port}"), stale_s=2.0)
    try:
        states = []
        end = time.monotonic() + 3.0
        while time.monotonic() < end:
            reader.poll(0.05)
            states.append(reader.health.state)
        h = reader.health
        assert h.state == "reconnecting", h
        assert "times in a row without a byte read" in h.reason, h.reason
        assert "connected" not in states[len(states) // 2 :]
        # opened at 0, 0.1, 0.3, 0.7, 1.5 s (with the backoff reset at every open: 8)
        assert 3 <= peer.accepts <= 6, peer.accepts
        peer.streaming = True
        wait_for(
            lambda: reader.poll(0.05) is not None and reader.health.state == "connected",
            10,
            "gps connected once it streams",
        )
        assert reader._backoff_s == reader.backoff_initial_s  # bytes read: reset
    finally:
        reader.close()
        peer.close()
