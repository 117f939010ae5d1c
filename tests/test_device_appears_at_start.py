"""A device node that does not exist yet at start-up (a USB adapter udev is still enumerating,
a native-USB motor board re-enumerating after a reset), or that this user may not read and
write yet (udev gives a new node its group a moment after creating it), is waited for,
``[startup] device_wait_s``, when systemd starts the daemon: exit 2 would leave the unit failed
(RestartPreventExitStatus=2) and the robot down. Every other device problem is still exit 2
at once, also one that turns up during the wait. Real ``x6wd run`` processes, a real pty and a
real notification socket; the permission cases run the daemon as user nobody (setpriv) when
the tests run as root, whom no permission bit stops."""

from __future__ import annotations

import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

from tests.conftest import ROOT
from tests.test_startup import assert_config_error, write_config

WAIT_LINE = "does not exist yet: waiting up to"
NOT_READY_LINE = "is not accessible yet (this user may not read and write it): waiting up to"
NOBODY = 65534
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


def start(
    config: Path, err: Path, notify_socket: str, pre: tuple[str, ...] = ()
) -> subprocess.Popen[bytes]:
    """``x6wd run`` as systemd starts it (NOTIFY_SOCKET set), stderr to ``err``; ``pre``:
    e.g. :func:`unprivileged`'s setpriv."""
    env = {**os.environ, "NOTIFY_SOCKET": notify_socket, "PYTHONDONTWRITEBYTECODE": "1"}
    env.pop("WATCHDOG_USEC", None)
    with err.open("wb") as f:
        return subprocess.Popen(
            [*pre, sys.executable, "-m", "x6wd", "run", "--config", str(config)],
            stderr=f,
            stdin=subprocess.DEVNULL,
            env=env,
            cwd=ROOT,
        )


def run(
    config: Path, notify_socket: str | None, pre: tuple[str, ...] = ()
) -> subprocess.CompletedProcess[str]:
    """``x6wd run`` to its end: as systemd starts it, or by hand (``notify_socket`` None)."""
    env = {**os.environ, "PYTHONDONTWRITEBYTECODE": "1"}
    env.pop("NOTIFY_SOCKET", None)
    env.pop("WATCHDOG_USEC", None)
    if notify_socket is not None:
        env["NOTIFY_SOCKET"] = notify_socket
    return subprocess.run(
        [*pre, sys.executable, "-m", "x6wd", "run", "--config", str(config)],
        capture_output=True,
        text=True,
        timeout=START_S,
        env=env,
        cwd=ROOT,
    )


@pytest.fixture
def unprivileged() -> Iterator[tuple[tuple[str, ...], Path]]:
    """How to run a process that a device node's permission bits stop, and a directory it
    can use: as root (whom no permission bit stops), ``setpriv`` to user nobody and a
    directory under /tmp it may enter (pytest's tmp_path is root's alone), its recorder dir
    ``rec`` its own; otherwise this user and a directory of ours."""
    top = Path(tempfile.mkdtemp(prefix="x6wd-perm-"))
    try:
        (top / "rec").mkdir()
        if os.geteuid() != 0:
            yield (), top
            return
        if shutil.which("setpriv") is None:
            pytest.skip("no setpriv to run as another user")
        top.chmod(0o755)
        os.chown(top / "rec", NOBODY, NOBODY)
        yield ("setpriv", f"--reuid={NOBODY}", f"--regid={NOBODY}", "--clear-groups"), top
    finally:
        shutil.rmtree(top, ignore_errors=True)


@pytest.fixture
def locked_pty() -> Iterator[Path]:
    """A real serial port (the slave of a pty) no one but root may use (mode 000), as udev
    leaves a node between creating it and giving it its group; ``chmod`` it to let the
    test's daemon in."""
    master, slave = os.openpty()
    path = Path(os.ttyname(slave))
    path.chmod(0)
    try:
        yield path
    finally:
        os.close(master)
        os.close(slave)


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
@pytest.mark.parametrize("what", ["regular file", "/dev/null"])
def test_other_device_problems_are_not_waited_for(
    tmp_path: Path, notify: tuple[str, socket.socket], what: str
) -> None:
    if what == "regular file":
        path, reason = tmp_path / "ttyACM0", "is not a character device"
        path.write_text("")
    else:
        path, reason = Path("/dev/null"), "is not a serial port"
    # 300 s: a wait would outlast run()'s timeout
    config = write_config(
        tmp_path, motors={"url": f"serial://{path}"}, startup={"device_wait_s": 300}
    )
    line = assert_config_error(run(config, notify[0]), "motors.url", reason)
    assert "waited" not in line


@pytest.mark.integration
@pytest.mark.parametrize("what", ["regular file", "/dev/null"])
def test_a_node_that_appears_as_something_else_ends_the_wait_at_once(
    tmp_path: Path, notify: tuple[str, socket.socket], what: str
) -> None:
    # missing at the start, then there, but not a serial port: waiting cannot mend that (the
    # old wait went on to its end, 30 s, then named the new problem)
    node = tmp_path / "ttyACM0"
    config = write_config(
        tmp_path, motors={"url": f"serial://{node}"}, startup={"device_wait_s": 30}
    )
    err = tmp_path / "stderr"
    proc = start(config, err, notify[0])
    try:
        until("wait line", lambda: WAIT_LINE in err.read_text(), proc, err)
        time.sleep(0.5)
        if what == "regular file":
            node.write_text("")
            reason = f"{node} is not a character device"
        else:
            node.symlink_to("/dev/null")
            reason = f"{node} is not a serial port"
        t0 = time.monotonic()
        try:
            code = proc.wait(15.0)  # seconds on a loaded CI; the old wait: the 30 s
        except subprocess.TimeoutExpired:
            pytest.fail(f"still waiting 15 s after {node} appeared as {what}: {err.read_text()}")
        took_s = time.monotonic() - t0
    finally:
        stop(proc)
    text = err.read_text()
    assert code == 2, text
    last = text.splitlines()[-1]
    assert last.startswith(f"x6wd: motors.url: 'serial://{node}': {reason}"), last
    waited_s = float(re.fullmatch(r".* \(waited (\d+\.\d) s\)", last).group(1))  # type: ignore[union-attr]
    assert 0.3 < waited_s < 30.0, last
    assert took_s < 15.0 and "Traceback" not in text and " ready" not in text


@pytest.mark.integration
def test_a_node_this_user_may_not_use_yet_is_waited_for_until_it_may(
    notify: tuple[str, socket.socket],
    unprivileged: tuple[tuple[str, ...], Path],
    locked_pty: Path,
) -> None:
    # the node is there (udev created it) but still root's, mode 000 here: the old start-up
    # stopped with exit 2 at once; once the daemon says it waits, the node is opened up
    pre, top = unprivileged
    config = write_config(
        top, gps={"url": f"serial://{locked_pty}?baud=9600"}, startup={"device_wait_s": 60}
    )
    config.chmod(0o644)
    err = top / "stderr"
    proc = start(config, err, notify[0], pre)
    seen: list[dict[str, str]] = []
    try:
        until("wait line", lambda: NOT_READY_LINE in err.read_text(), proc, err)
        time.sleep(1.0)  # no race: it only makes the change come some polls into the wait
        locked_pty.chmod(0o666)  # udev gave it its group

        def ready() -> bool:
            messages(notify[1], seen)
            return any(m.get("READY") == "1" for m in seen)

        until("READY=1", ready, proc, err)
        assert stop(proc) == 0, err.read_text()
    finally:
        stop(proc)
    text = err.read_text()
    assert f"gps.url: {locked_pty} {NOT_READY_LINE} 60 s (udev setting its group?" in text
    assert "Traceback" not in text
    waiting = [m for m in seen if "waiting up to 60 s" in m.get("STATUS", "")]
    assert waiting and f"{locked_pty} to be accessible" in waiting[0]["STATUS"], seen


@pytest.mark.integration
def test_a_node_this_user_may_never_use_is_exit_2_after_the_wait_and_at_once_by_hand(
    notify: tuple[str, socket.socket],
    unprivileged: tuple[tuple[str, ...], Path],
    locked_pty: Path,
) -> None:
    pre, top = unprivileged
    url = f"serial://{locked_pty}"
    reason = f"{locked_pty}: this user may not read and write it (is the user in group dialout?)"
    config = write_config(top, motors={"url": url}, startup={"device_wait_s": 1.5})
    config.chmod(0o644)
    proc = run(config, notify[0], pre)
    assert proc.returncode == 2, proc.stderr
    assert f"motors.url: {locked_pty} {NOT_READY_LINE} 1.5 s" in proc.stderr
    assert proc.stderr.splitlines()[-1] == f"x6wd: motors.url: {url!r}: {reason} (waited 1.5 s)"
    # by hand, even with a long wait configured: the operator gets the line at once
    config = write_config(top, motors={"url": url}, startup={"device_wait_s": 300})
    config.chmod(0o644)
    line = assert_config_error(run(config, None, pre), "motors.url", reason)
    assert "waited" not in line


def test_the_start_up_check_tells_a_device_node_not_accessible_yet(
    unprivileged: tuple[tuple[str, ...], Path], locked_pty: Path
) -> None:
    # registry: a character device this user may not read and write is NodeNotReady (the
    # daemon may wait for it); an unreadable replay file stays a plain UrlError
    pre, top = unprivileged
    replay = top / "gps.log"
    replay.write_text("")
    replay.chmod(0)
    code = (
        "import sys\n"
        f"sys.path.insert(0, {str(ROOT)!r})\n"
        "from drivers import registry\n"
        "for url in sys.argv[1:]:\n"
        "    try:\n"
        "        registry.check_available(url, 'gps')\n"
        "    except registry.UrlError as e:\n"
        "        print(type(e).__name__, getattr(e, 'path', '-'), e.reason)\n"
    )
    out = subprocess.run(
        [*pre, sys.executable, "-c", code, f"serial://{locked_pty}", f"replay://{replay}"],
        capture_output=True,
        text=True,
        timeout=START_S,
        cwd="/tmp",
        env={**os.environ, "PYTHONDONTWRITEBYTECODE": "1"},
    )
    assert out.returncode == 0 and "Traceback" not in out.stderr, out.stderr
    assert out.stdout.splitlines() == [
        f"NodeNotReady {locked_pty} {locked_pty}: this user may not read and write it "
        "(is the user in group dialout?)",
        f"UrlError - {replay}: this user may not read it",
    ]


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
