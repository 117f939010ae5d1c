"""A device node that does not exist yet at start-up (a USB adapter udev is still enumerating,
a native-USB motor board re-enumerating after a reset) is waited for, ``[startup]
device_wait_s``, when systemd starts the daemon: exit 2 would leave the unit failed
(RestartPreventExitStatus=2) and the robot down. Every other device problem is still exit 2
at once. Real ``x6wd run`` processes, a real pty and a real notification socket."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

from tests.conftest import ROOT
from tests.test_startup import assert_config_error, write_config

WAIT_LINE = "does not exist yet: waiting up to"
START_S = 60.0  # a daemon importing numpy on the loaded 2-core CI: seconds, not 60


@pytest.fixture
def notify() -> Iterator[tuple[str, socket.socket]]:
    """A systemd notification socket (abstract: no path length limit) and its address."""
    name = f"@x6wd-test-{uuid.uuid4().hex}"
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind("\0" + name[1:])
    sock.settimeout(0.2)
    yield name, sock
    sock.close()


def start(config: Path, err: Path, notify_socket: str) -> subprocess.Popen[bytes]:
    """``x6wd run`` as systemd starts it (NOTIFY_SOCKET set), stderr to ``err``."""
    env = {**os.environ, "NOTIFY_SOCKET": notify_socket}
    env.pop("WATCHDOG_USEC", None)
    with err.open("wb") as f:
        return subprocess.Popen(
            [sys.executable, "-m", "x6wd", "run", "--config", str(config)],
            stderr=f,
            stdin=subprocess.DEVNULL,
            env=env,
            cwd=ROOT,
        )


def run(config: Path, notify_socket: str) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "NOTIFY_SOCKET": notify_socket}
    return subprocess.run(
        [sys.executable, "-m", "x6wd", "run", "--config", str(config)],
        capture_output=True,
        text=True,
        timeout=START_S,
        env=env,
        cwd=ROOT,
    )


def messages(sock: socket.socket, seen: list[dict[str, str]]) -> None:
    """Append every notification waiting on ``sock`` to ``seen``."""
    while True:
        try:
            data = sock.recv(4096).decode()
        except (TimeoutError, BlockingIOError):
            return
        seen.append(dict(line.split("=", 1) for line in data.split("\n")))


def until(what: str, check: Callable[[], Any], proc: subprocess.Popen[bytes], err: Path) -> None:
    """Poll ``check`` until true (deadline :data:`START_S`); the daemon must not exit."""
    deadline = time.monotonic() + START_S
    while not check():
        assert proc.poll() is None, f"exit {proc.returncode} before {what}: {err.read_text()}"
        assert time.monotonic() < deadline, f"no {what} in {START_S} s: {err.read_text()}"
        time.sleep(0.05)


def stop(proc: subprocess.Popen[bytes]) -> int:
    if proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
    try:
        return proc.wait(START_S)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


@pytest.mark.integration
def test_a_serial_node_that_appears_during_the_wait_starts_the_daemon(
    tmp_path: Path, notify: tuple[str, socket.socket]
) -> None:
    # the board's node comes back (a symlink to a real pty, as udev's by-id link) only once
    # the daemon says it waits: the old start-up stopped with exit 2 at once
    master, slave = os.openpty()
    link = tmp_path / "ttyACM0"
    config = write_config(
        tmp_path, gps={"url": f"serial://{link}?baud=9600"}, startup={"device_wait_s": 60}
    )
    err = tmp_path / "stderr"
    proc = start(config, err, notify[0])
    seen: list[dict[str, str]] = []
    try:
        until("wait line", lambda: WAIT_LINE in err.read_text(), proc, err)
        time.sleep(1.0)  # no race: it only makes the node appear some polls into the wait
        link.symlink_to(os.ttyname(slave))

        def ready() -> bool:
            messages(notify[1], seen)
            return any(m.get("READY") == "1" for m in seen)

        until("READY=1", ready, proc, err)
        assert stop(proc) == 0, err.read_text()
    finally:
        stop(proc)
        os.close(master)
        os.close(slave)
    text = err.read_text()
    assert f"gps.url: {link} {WAIT_LINE} 60 s for it to appear" in text
    assert "startup.device_wait_s" in text and "Traceback" not in text
    waiting = [m for m in seen if "waiting up to 60 s" in m.get("STATUS", "")]
    assert waiting and str(link) in waiting[0]["STATUS"], seen
    assert int(waiting[0]["EXTEND_TIMEOUT_USEC"]) >= 60_000_000  # beyond TimeoutStartSec


@pytest.mark.integration
def test_sigterm_ends_the_wait_at_once(tmp_path: Path, notify: tuple[str, socket.socket]) -> None:
    config = write_config(
        tmp_path,
        motors={"url": f"serial://{tmp_path / 'ttyACM0'}"},
        startup={"device_wait_s": 300},
    )
    err = tmp_path / "stderr"
    proc = start(config, err, notify[0])
    try:
        until("wait line", lambda: WAIT_LINE in err.read_text(), proc, err)
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(START_S) == 0, err.read_text()  # not after the 300 s
    finally:
        stop(proc)
    text = err.read_text()
    assert "x6wd stopped while waiting for motors.url" in text, text
    assert "Traceback" not in text and " ready" not in text


@pytest.mark.integration
def test_nodes_that_never_appear_are_exit_2_after_one_wait(
    tmp_path: Path, notify: tuple[str, socket.socket]
) -> None:
    link = tmp_path / "ttyUSB0"
    config = write_config(
        tmp_path,
        gps={"url": f"serial://{link}?baud=9600"},
        compass={"url": "i2c://97/0x60"},
        startup={"device_wait_s": 1.5},
    )
    proc = run(config, notify[0])
    lines = proc.stderr.splitlines()
    assert proc.returncode == 2, proc.stderr
    # both waited for in one wait: both announced before the one error line
    assert f"gps.url: {link} {WAIT_LINE} 1.5 s" in proc.stderr
    assert f"compass.url: /dev/i2c-97 {WAIT_LINE} 1.5 s" in proc.stderr
    assert lines[-1] == (
        f"x6wd: gps.url: 'serial://{link}?baud=9600': {link} does not exist (waited 1.5 s)"
    )
    assert "Traceback" not in proc.stderr and " ready" not in proc.stderr
    seen: list[dict[str, str]] = []
    messages(notify[1], seen)
    assert "configuration error: gps.url" in seen[-1]["STATUS"], seen
    # 0: the old immediate exit 2, one line, no wait
    zero = write_config(tmp_path, gps={"url": f"serial://{link}"}, startup={"device_wait_s": 0})
    assert_config_error(run(zero, notify[0]), "gps.url", f"{link} does not exist")


@pytest.mark.integration
@pytest.mark.parametrize("what", ["regular file", "/dev/null", "no permission"])
def test_other_device_problems_are_not_waited_for(
    tmp_path: Path, notify: tuple[str, socket.socket], what: str
) -> None:
    master = slave = -1
    if what == "regular file":
        path, reason = tmp_path / "ttyACM0", "is not a character device"
        path.write_text("")
    elif what == "/dev/null":
        path, reason = Path("/dev/null"), "is not a serial port"
    else:
        if os.geteuid() == 0:
            pytest.skip("root may read and write any device")
        master, slave = os.openpty()
        path, reason = Path(os.ttyname(slave)), "this user may not read and write it"
        path.chmod(0)
    try:
        # 300 s: a wait would outlast run()'s timeout
        config = write_config(
            tmp_path, motors={"url": f"serial://{path}"}, startup={"device_wait_s": 300}
        )
        line = assert_config_error(run(config, notify[0]), "motors.url", reason)
        assert "waited" not in line
    finally:
        for fd in (master, slave):
            if fd >= 0:
                os.close(fd)


@pytest.mark.integration
@pytest.mark.parametrize(
    ("value", "reason"),
    [(-1, "must be >= 0"), (301, "must be <= 300"), ("x", "expected a number")],
)
def test_a_bad_device_wait_is_exit_2_naming_the_key(
    tmp_path: Path, notify: tuple[str, socket.socket], value: Any, reason: str
) -> None:
    config = write_config(tmp_path, startup={"device_wait_s": value})
    assert_config_error(run(config, notify[0]), str(config), f"startup.device_wait_s: {reason}")
