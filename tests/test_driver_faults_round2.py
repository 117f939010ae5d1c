"""Device faults a second outside audit found, each on the real part: pseudo-terminals for the
serial devices, the real `x6wd run` process where the behaviour is the daemon's.

- A port another process holds for a moment at start-up is a runtime condition, not a
  configuration error: the GPS reports 'in use' and retries; the motors fail the start-up
  (exit 1, which systemd restarts), as for any motor port that cannot be opened.
- The start-up check opens no serial port (an open and close toggles DTR: an Arduino-class
  board resets).
- A port held exclusively (TIOCEXCL, EBUSY) is reported as in use.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os
import shutil
import struct
import subprocess
import sys
import threading
import time
import tty
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
import serial

from drivers import registry
from tests.conftest import ROOT
from tests.test_shutdown import DaemonProcess
from tests.test_startup import run_x6wd, write_config
from x6wd.app.client import RemoteClient

pytestmark = pytest.mark.integration


def wait_until(cond: Callable[[], Any], limit_s: float, what: str) -> Any:
    end = time.monotonic() + limit_s
    while time.monotonic() < end:
        got = cond()
        if got:
            return got
        time.sleep(0.05)
    raise AssertionError(f"timed out waiting for {what}")


def nmea(body: str) -> bytes:
    c = 0
    for ch in body.encode("ascii"):
        c ^= ch
    return f"${body}*{c:02X}\r\n".encode("ascii")


NO_FIX = nmea("GPGGA,,,,,,0,00,99.9,,,,,,") + nmea("GPRMC,,V,,,,,,,,,,N")


class PtyGps:
    """A receiver on a pseudo-terminal sending no-fix sentences every 0.1 s."""

    def __init__(self) -> None:
        self.master, self.slave = os.openpty()
        tty.setraw(self.master)
        tty.setraw(self.slave)
        self.path = os.ttyname(self.slave)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
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

    def close(self) -> None:
        self._stop.set()
        self._thread.join(5)
        os.close(self.master)
        os.close(self.slave)


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
            gps = wait_until(
                lambda: (
                    (g := c.request("status")["devices"]["gps"])["state"] == "reconnecting" and g
                ),
                10,
                "gps reconnecting",
            )
            assert f"{pty_gps.path} is in use: another process holds it" in gps["reason"], gps
            assert gps["next_attempt_t_s"] is not None
            holder.close()
            wait_until(
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
