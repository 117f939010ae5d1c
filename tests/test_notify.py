"""sd_notify over a real AF_UNIX datagram socket (filesystem path and abstract namespace)."""

from __future__ import annotations

import os
import socket
import uuid
from pathlib import Path

import pytest

from x6wd.app.notify import Notifier
from x6wd.core.errors import ConfigError


def _recv(sock: socket.socket) -> dict[str, str]:
    sock.settimeout(5.0)
    data = sock.recv(4096).decode()
    return dict(line.split("=", 1) for line in data.split("\n"))


@pytest.fixture
def path_socket(tmp_path: Path):
    path = tmp_path / "notify.sock"
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(str(path))
    yield str(path), sock
    sock.close()


def test_ready_status_watchdog_stopping_arrive_on_path_socket(path_socket) -> None:
    path, sock = path_socket
    with Notifier.from_env({"NOTIFY_SOCKET": path}) as n:
        assert n.enabled
        assert n.ready("up")
        msg = _recv(sock)
        assert msg["READY"] == "1" and msg["STATUS"] == "up"
        assert msg["MAINPID"] == str(os.getpid())
        assert n.status("RUNNING STRAIGHT\nwp 1/3")
        assert _recv(sock) == {"STATUS": "RUNNING STRAIGHT wp 1/3"}
        assert n.watchdog()
        assert _recv(sock) == {"WATCHDOG": "1"}
        assert n.stopping()
        assert _recv(sock) == {"STOPPING": "1"}
        assert n.sent == 4


def test_abstract_namespace_socket() -> None:
    name = f"x6wd-test-{uuid.uuid4().hex}"
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind("\0" + name)
    try:
        n = Notifier.from_env({"NOTIFY_SOCKET": "@" + name})
        assert n.ready()
        assert _recv(sock)["READY"] == "1"
        n.close()
        n.close()  # idempotent
        assert not n.enabled
    finally:
        sock.close()


def test_without_notify_socket_everything_is_a_noop() -> None:
    n = Notifier.from_env({})
    assert not n.enabled
    assert n.ready() is False and n.watchdog() is False
    assert n.watchdog_interval_s is None


def test_watchdog_interval_is_half_of_watchdog_usec_for_this_pid() -> None:
    n = Notifier.from_env({"WATCHDOG_USEC": "3000000", "WATCHDOG_PID": str(os.getpid())})
    assert n.watchdog_interval_s == pytest.approx(1.5)
    other = Notifier.from_env({"WATCHDOG_USEC": "3000000", "WATCHDOG_PID": str(os.getpid() + 1)})
    assert other.watchdog_interval_s is None
    with pytest.raises(ConfigError, match="WATCHDOG_USEC"):
        Notifier.from_env({"WATCHDOG_USEC": "soon"})


def test_relative_notify_socket_is_a_clear_error() -> None:
    with pytest.raises(ConfigError, match="NOTIFY_SOCKET"):
        Notifier.from_env({"NOTIFY_SOCKET": "relative/path"})


def test_missing_listener_is_counted_not_raised(tmp_path: Path) -> None:
    n = Notifier(str(tmp_path / "nobody-listens.sock"))
    assert n.watchdog() is False
    assert n.send_errors == 1


def test_stopping_is_the_last_status_and_a_repeat_is_not_sent(path_socket) -> None:
    # an outside audit (round 19): the shutdown's own state change sent "STATUS=IDLE IDLE"
    # after "STATUS=stopping", and each mode and navigation change sent the same line again
    path, sock = path_socket
    with Notifier.from_env({"NOTIFY_SOCKET": path}) as n:
        assert n.ready("IDLE IDLE")
        _recv(sock)
        assert n.status("RUNNING STRAIGHT wp 1/4")
        assert _recv(sock) == {"STATUS": "RUNNING STRAIGHT wp 1/4"}
        assert not n.status("RUNNING STRAIGHT wp 1/4")  # said already
        assert n.stopping("stopping")
        assert _recv(sock) == {"STOPPING": "1", "STATUS": "stopping"}
        assert not n.status("IDLE IDLE wp 1/4")
        assert n.sent == 3
        sock.settimeout(0.2)
        with pytest.raises(TimeoutError):
            sock.recv(4096)


def test_a_status_whose_send_failed_is_sent_again(tmp_path: Path) -> None:
    # a review (round 19): a failed send was remembered as sent, and never repeated
    path = tmp_path / "late.sock"
    with Notifier.from_env({"NOTIFY_SOCKET": str(path)}) as n:
        assert not n.status("RUNNING STRAIGHT wp 1/4")  # nobody listens yet
        sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        sock.bind(str(path))
        try:
            assert n.status("RUNNING STRAIGHT wp 1/4")
            assert _recv(sock) == {"STATUS": "RUNNING STRAIGHT wp 1/4"}
        finally:
            sock.close()
