"""Review of fdb4cad (x6wd.app.lineserver): which session a full pool closes for a newly
admitted peer. fdb4cad chose among the busiest address's sessions first; that closed an
operator's driving session (its own ``watch`` on the same address made the address the
busiest) before an idle session elsewhere, and the dead-man stopped the drive.

Real sockets against the real servers on their loop thread (tests.test_server.LoopThread);
127.0.0.2 and 127.0.0.3 (routed to lo by Linux) stand for other hosts.
"""

from __future__ import annotations

import json
import socket
from typing import Any

import pytest

from tests.test_lineserver_flood_round8 import connect, read_lines_until, wait_until
from tests.test_lockout import lt
from tests.test_server import TOKEN, LoopThread, RecordingBackend
from x6wd.app.gpsd import GpsdServer
from x6wd.app.server import ControlServer
from x6wd.core.config import ServerConfig

__all__ = ["lt"]  # the fixture, shared with test_lockout

pytestmark = pytest.mark.integration

OPERATOR_HOST = "127.0.0.1"
OTHER_HOST = "127.0.0.2"
NEW_HOST = "127.0.0.3"


def line(**req: Any) -> bytes:
    return json.dumps(req).encode() + b"\n"


AUTH = line(id=1, cmd="auth", token=TOKEN)


def admitted(lt: LoopThread, srv: Any, n: int) -> None:
    """Wait until ``n`` sessions were admitted so far (open or closed for room)."""
    wait_until(
        lambda: lt.call(lambda: srv.client_count + srv.closed_counts["sessions_full"]) == n
        and lt.call(lambda: srv.pending_count) == 0,
        what=f"{n} sessions admitted",
    )


def reply_to(s: socket.socket, req_id: int) -> dict[str, Any]:
    got = read_lines_until(s, lambda ln: json.loads(ln).get("id", 0) in (req_id, None), 5.0)
    return dict(json.loads(got))


def test_a_full_control_port_never_closes_the_session_that_is_driving(lt: LoopThread) -> None:
    """The review's case, max_clients 3: an operator on one address drives (30 s) and
    watches on a second connection; an idle session from another address; a third address
    authenticates. The idle session is closed, the drive goes on (no dead-man stop). The
    driver is the oldest idle session of the busiest address, so only its protection saves
    it (before: it was closed and the motors stopped)."""
    backend = RecordingBackend()
    srv = ControlServer(ServerConfig(port=0, max_clients=3), backend, token=TOKEN.encode())
    lt.run(srv.start())
    socks: list[socket.socket] = []
    try:
        driver = connect(srv.port, OPERATOR_HOST, AUTH + line(id=2, cmd="drive", left=30,
                                                              right=30, duration_s=30))  # fmt: skip
        socks.append(driver)
        assert reply_to(driver, 2)["ok"] is True
        socks.append(connect(srv.port, OPERATOR_HOST, AUTH + line(id=2, cmd="watch", on=True)))
        admitted(lt, srv, 2)
        wait_until(lambda: lt.call(lambda: sum(c.watching for c in srv._sessions)) == 1,
                   what="the operator's watch")  # fmt: skip
        idle = connect(srv.port, OTHER_HOST, AUTH)
        socks.append(idle)
        admitted(lt, srv, 3)
        socks.append(connect(srv.port, NEW_HOST, AUTH))
        admitted(lt, srv, 4)
        assert lt.call(lambda: srv.closed_counts["sessions_full"]) == 1
        hosts = lt.call(lambda: sorted(c.host for c in srv._sessions))
        assert hosts == [OPERATOR_HOST, OPERATOR_HOST, NEW_HOST], hosts
        notice = json.loads(read_lines_until(idle, lambda ln: b"closed" in ln, 5.0))
        assert notice["error"]["reason"] == "sessions_full", notice
        assert srv.stops["orphaned"] == 0 and ("stop", None) not in backend.calls
        driver.sendall(line(id=3, cmd="status"))
        st = reply_to(driver, 3)
        assert st["ok"] is True and st["manual_drive"]["yours"] is True, st
    finally:
        for s in socks:
            s.close()
        lt.run(srv.close())


def test_with_one_session_slot_the_driver_still_makes_room_and_the_motors_stop(
    lt: LoopThread,
) -> None:
    """max_clients 1 and that session drives: an admitted peer still gets in (an operator
    who lost the connection must get back), and closing the driver stops the motors."""
    backend = RecordingBackend()
    srv = ControlServer(ServerConfig(port=0, max_clients=1), backend, token=TOKEN.encode())
    lt.run(srv.start())
    socks: list[socket.socket] = []
    try:
        driver = connect(srv.port, OPERATOR_HOST, AUTH + line(id=2, cmd="drive", left=30,
                                                              right=30, duration_s=30))  # fmt: skip
        socks.append(driver)
        assert reply_to(driver, 2)["ok"] is True
        socks.append(connect(srv.port, OTHER_HOST, AUTH))
        admitted(lt, srv, 2)
        assert lt.call(lambda: [c.host for c in srv._sessions]) == [OTHER_HOST]
        wait_until(lambda: srv.stops["orphaned"] == 1, what="the dead-man's stop")
    finally:
        for s in socks:
            s.close()
        lt.run(srv.close())


def test_a_full_gpsd_port_closes_an_idle_session_before_a_live_watcher(lt: LoopThread) -> None:
    """max_clients 3: two watchers on one address, a session that asked ``?VERSION`` once on
    another, a third address joins: the idle one goes, not a watcher of the busiest address
    (before: the newest watcher was closed)."""
    srv = GpsdServer("127.0.0.1", 0, "/dev/ttyS0", max_clients=3)
    lt.run(srv.start())
    watch = b'?WATCH={"enable":true,"json":true};\n'
    socks: list[socket.socket] = []
    try:
        for n in (1, 2):
            socks.append(connect(srv.port, OPERATOR_HOST, watch))
            admitted(lt, srv, n)
        idle = connect(srv.port, OTHER_HOST, b"?VERSION;\n")
        socks.append(idle)
        admitted(lt, srv, 3)
        socks.append(connect(srv.port, NEW_HOST, b"?VERSION;\n"))
        admitted(lt, srv, 4)
        hosts = lt.call(lambda: sorted(c.host for c in srv._sessions))
        assert hosts == [OPERATOR_HOST, OPERATOR_HOST, NEW_HOST], hosts
        assert b"sessions_full" in read_lines_until(idle, lambda ln: b"closing" in ln, 5.0)
    finally:
        for s in socks:
            s.close()
        lt.run(srv.close())


# -- review 10c of cd61371: kind first everywhere let a storm close other addresses' sessions --
def test_a_gpsd_storm_of_watchers_from_one_address_closes_its_own_not_an_idle_client(
    lt: LoopThread,
) -> None:
    """The review's case, max_clients 3: a client on one address asked ``?VERSION`` once; three
    never-reading watchers from another address join. The third closes one of its own
    address's, the idle client is served on (before: it was closed, being the cheapest
    kind, and so was every non-watcher by each further storm connection)."""
    srv = GpsdServer("127.0.0.1", 0, "/dev/ttyS0", max_clients=3)
    lt.run(srv.start())
    watch = b'?WATCH={"enable":true,"json":true};\n'
    socks: list[socket.socket] = []
    try:
        poller = connect(srv.port, OPERATOR_HOST, b"?VERSION;\n")
        socks.append(poller)
        admitted(lt, srv, 1)
        for n in (2, 3, 4):
            socks.append(connect(srv.port, OTHER_HOST, watch))
            admitted(lt, srv, n)
        hosts = lt.call(lambda: sorted(c.host for c in srv._sessions))
        assert hosts == [OPERATOR_HOST, OTHER_HOST, OTHER_HOST], hosts
        poller.sendall(b"?DEVICES;\n")
        got = read_lines_until(poller, lambda ln: b"DEVICES" in ln or b"closing" in ln, 5.0)
        assert b'"class":"DEVICES"' in got, got
    finally:
        for s in socks:
            s.close()
        lt.run(srv.close())


def test_an_operator_from_a_fresh_address_keeps_its_session_through_a_watcher_storm(
    lt: LoopThread,
) -> None:
    """max_clients 3 full of never-reading watchers from one address; an operator from a
    fresh address authenticates (not watching) and gets in, closing one of them; three more
    storm connections close their own address's, the operator's session answers on
    (before: the next storm connection closed it, the cheapest kind)."""
    srv = ControlServer(ServerConfig(port=0, max_clients=3), RecordingBackend(),
                        token=TOKEN.encode())  # fmt: skip
    lt.run(srv.start())
    storm = AUTH + line(id=2, cmd="watch", on=True)
    socks: list[socket.socket] = []
    try:
        for n in (1, 2, 3):
            socks.append(connect(srv.port, OTHER_HOST, storm))
            admitted(lt, srv, n)
        op = connect(srv.port, NEW_HOST, AUTH)
        socks.append(op)
        admitted(lt, srv, 4)
        assert lt.call(lambda: sorted(c.host for c in srv._sessions)) == [
            OTHER_HOST, OTHER_HOST, NEW_HOST]  # fmt: skip
        for n in (5, 6, 7):
            socks.append(connect(srv.port, OTHER_HOST, storm))
            admitted(lt, srv, n)
        hosts = lt.call(lambda: sorted(c.host for c in srv._sessions))
        assert hosts == [OTHER_HOST, OTHER_HOST, NEW_HOST], hosts
        op.sendall(line(id=3, cmd="status"))
        assert reply_to(op, 3)["ok"] is True
    finally:
        for s in socks:
            s.close()
        lt.run(srv.close())


def test_an_operator_from_a_fresh_address_gets_in_when_every_address_holds_one_session(
    lt: LoopThread,
) -> None:
    """max_clients 2, one idle session on each of two addresses: the operator's address
    ties as the busiest (one, counted) but has no session of its own to close, so the
    one idle longest goes and the operator gets in."""
    srv = ControlServer(ServerConfig(port=0, max_clients=2), RecordingBackend(),
                        token=TOKEN.encode())  # fmt: skip
    lt.run(srv.start())
    socks: list[socket.socket] = []
    try:
        for n, host in enumerate((OPERATOR_HOST, OTHER_HOST), start=1):
            socks.append(connect(srv.port, host, AUTH))
            admitted(lt, srv, n)
        op = connect(srv.port, NEW_HOST, AUTH)
        socks.append(op)
        admitted(lt, srv, 3)
        hosts = lt.call(lambda: sorted(c.host for c in srv._sessions))
        assert hosts == [OTHER_HOST, NEW_HOST], hosts
        op.sendall(line(id=3, cmd="status"))
        assert reply_to(op, 3)["ok"] is True
    finally:
        for s in socks:
            s.close()
        lt.run(srv.close())
