"""Outside audit 10b, findings 2 and 3 (x6wd.app.lineserver): a storm of watchers from one
address filling the session pool, and the memory of connections the server closed.

Real sockets against the real servers, each on its own loop thread
(tests.test_server.LoopThread), on ports the kernel picks. A second loopback address
(127.0.0.2, which Linux routes to lo) stands for another host.
"""

from __future__ import annotations

import json
import socket
import time
from collections.abc import Callable, Iterator
from typing import Any

import pytest

from tests.test_gpsd_port import FIX
from tests.test_server import TOKEN, LoopThread, RecordingBackend
from x6wd.app.gpsd import GpsdServer
from x6wd.app.server import ControlServer
from x6wd.core.config import ServerConfig

WATCH = b'?WATCH={"enable":true,"json":true};\n'
STORM_HOST = "127.0.0.1"
OPERATOR_HOST = "127.0.0.2"


@pytest.fixture
def lt() -> Iterator[LoopThread]:
    loop_thread = LoopThread()
    yield loop_thread
    loop_thread.close()


def wait_until(pred: Callable[[], Any], timeout_s: float = 10.0, what: str = "") -> Any:
    deadline = time.monotonic() + timeout_s
    while True:
        v = pred()
        if v:
            return v
        assert time.monotonic() < deadline, f"condition not reached: {what}"
        time.sleep(0.01)


def connect(port: int, source: str, first: bytes) -> socket.socket:
    """A connection from ``source`` that sends ``first`` and then never reads."""
    s = socket.socket()
    s.bind((source, 0))
    s.settimeout(10)
    s.connect(("127.0.0.1", port))
    s.sendall(first)
    return s


def read_lines_until(s: socket.socket, pred: Callable[[bytes], bool], timeout_s: float) -> bytes:
    """Read ``s`` until a line satisfies ``pred`` (returned) or the stream ends (b"")."""
    deadline = time.monotonic() + timeout_s
    buf = b""
    while time.monotonic() < deadline:
        while b"\n" in buf:
            line, buf = buf.split(b"\n", 1)
            if pred(line):
                return line
        s.settimeout(max(0.01, deadline - time.monotonic()))
        try:
            chunk = s.recv(65536)
        except TimeoutError:
            break
        if not chunk:
            return b""
        buf += chunk
    raise AssertionError("no such line in time")


def storm(lt: LoopThread, srv: Any, first: bytes, n: int, held: list[socket.socket]) -> None:
    """``n`` connections from STORM_HOST, each admitted (sending ``first``) before the next:
    watchers that never read, which to the server look as if they keep up."""

    def admitted() -> int:
        return int(srv.client_count + srv.closed_counts["sessions_full"])

    for _ in range(n):
        before = lt.call(admitted)
        held.append(connect(srv.port, STORM_HOST, first))
        wait_until(
            lambda b=before: lt.call(lambda: admitted() == b + 1 and srv.pending_count == 0),
            what="the storm's connection admitted",
        )


# -- finding 2: the session pool under a storm from one address --------------------------------
def test_a_gpsd_watcher_from_another_address_survives_a_storm_of_watchers_from_one(
    lt: LoopThread,
) -> None:
    """The audit: 60 never-reading ?WATCH connections from one address (50 new a second)
    closed a real watcher joining during it within 0.01 s in 2 of 3 tries ("sessions_full":
    it was the newest watcher, and the storm's, their kernel buffers taking the stream,
    looked as if they kept up). Here: 4 sessions, 4 storm watchers, the operator's from
    another address, then 8 more storm watchers: the storm's own are closed, the operator
    reads on. Before: the operator's was closed by the next one."""
    srv = GpsdServer("127.0.0.1", 0, "/dev/ttyS0", max_clients=4)
    lt.run(srv.start())
    held: list[socket.socket] = []
    op = None
    try:
        storm(lt, srv, WATCH, 4, held)
        op = connect(srv.port, OPERATOR_HOST, WATCH)
        wait_until(lambda: lt.call(lambda: srv.closed_counts["sessions_full"]) == 1,
                   what="the operator admitted")  # fmt: skip
        storm(lt, srv, WATCH, 8, held)
        assert lt.call(lambda: srv.closed_counts["sessions_full"]) == 9
        hosts = lt.call(lambda: sorted(c.host for c in srv._sessions))
        assert hosts == [STORM_HOST] * 3 + [OPERATOR_HOST]
        lt.call(lambda: srv.publish_fix(FIX))
        line = read_lines_until(op, lambda ln: b"TPV" in ln or b"closing" in ln, 5.0)
        assert b'"class":"TPV"' in line, line
    finally:
        for s in held + ([op] if op else []):
            s.close()
        lt.run(srv.close())


def test_a_control_port_watcher_from_another_address_survives_a_storm_from_one(
    lt: LoopThread,
) -> None:
    """The same rule on the control port (the same pool code): 4 sessions full of watchers
    from one address, the operator's watcher from another survives 8 more from it."""
    cfg = ServerConfig(port=0, max_clients=4)
    srv = ControlServer(cfg, RecordingBackend(), token=TOKEN.encode())
    lt.run(srv.start())
    auth_watch = (
        json.dumps({"id": 1, "cmd": "auth", "token": TOKEN}).encode() + b"\n"
        + json.dumps({"id": 2, "cmd": "watch", "on": True}).encode() + b"\n"
    )  # fmt: skip
    held: list[socket.socket] = []
    op = None
    try:
        storm(lt, srv, auth_watch, 4, held)
        op = connect(srv.port, OPERATOR_HOST, auth_watch)
        wait_until(lambda: lt.call(lambda: srv.closed_counts["sessions_full"]) == 1,
                   what="the operator admitted")  # fmt: skip
        storm(lt, srv, auth_watch, 8, held)
        assert lt.call(lambda: srv.closed_counts["sessions_full"]) == 9
        hosts = lt.call(lambda: sorted(c.host for c in srv._sessions))
        assert hosts == [STORM_HOST] * 3 + [OPERATOR_HOST]
        op.sendall(json.dumps({"id": 3, "cmd": "hello"}).encode() + b"\n")
        line = read_lines_until(op, lambda ln: b'"id": 3' in ln or b'"id":3' in ln
                                or b"closed" in ln, 5.0)  # fmt: skip
        assert json.loads(line)["ok"] is True, line
    finally:
        for s in held + ([op] if op else []):
            s.close()
        lt.run(srv.close())
