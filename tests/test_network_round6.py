"""Outside audit 8a (network services): the gpsd port's session pool under a connect/close
storm, and the web console's closes (a connect storm, a page that never reads).

Real sockets on 127.0.0.1 against the real servers, each on its own loop thread
(tests.test_server.LoopThread), on ports 8570-8599.
"""

from __future__ import annotations

import base64
import gc
import json
import logging
import os
import re
import socket
import struct
import threading
import time
from collections.abc import Iterator
from typing import Any

import pytest

from tests.test_gpsd_port import FIX
from tests.test_lockout import wait_until
from tests.test_server import TOKEN, LoopThread, RecordingBackend
from x6wd.app.console import server as console_server
from x6wd.app.console.server import CONNECTION_SLACK, ConsoleServer
from x6wd.app.gpsd import GpsdServer
from x6wd.app.lineserver import unacknowledged_bytes
from x6wd.app.server import ControlServer
from x6wd.core.config import ConsoleConfig, ServerConfig
from x6wd.core.ratelog import RateLimitedLog
from x6wd.core.records import GpsSky, SatInfo

PORTS = iter(range(8570, 8600))
WATCH = b'?WATCH={"enable":true,"json":true};\n'


@pytest.fixture
def lt() -> Iterator[LoopThread]:
    loop_thread = LoopThread()
    errors: list[dict[str, Any]] = []
    loop_thread.errors = errors  # type: ignore[attr-defined]
    # what asyncio would log as "Task exception was never retrieved" and the like
    loop_thread.loop.call_soon_threadsafe(
        loop_thread.loop.set_exception_handler, lambda _loop, ctx: errors.append(ctx)
    )
    yield loop_thread
    loop_thread.close()


def hold_loop(lt: LoopThread) -> tuple[threading.Event, threading.Event]:
    """Block the server's loop (what a busy daemon's loop does) until the first event is
    set (at most 20 s): connections made meanwhile wait in the kernel's backlog and are
    handed over at once, however long a loaded host takes to make them. Returns once the
    loop is held; the second event is set when it is released."""
    held, go, released = threading.Event(), threading.Event(), threading.Event()

    def hold() -> None:
        held.set()
        go.wait(20)
        released.set()

    lt.loop.call_soon_threadsafe(hold)
    assert held.wait(5)
    return go, released


class Watcher:
    """A gpsd watcher that reads everything, in a thread; notes the server's closing notice."""

    def __init__(self, port: int, rcvbuf: int | None = None, read: bool = True) -> None:
        self.sock = socket.socket()
        if rcvbuf is not None:
            self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, rcvbuf)
        self.sock.settimeout(10)
        self.sock.connect(("127.0.0.1", port))
        self.sock.sendall(WATCH)
        self.port = self.sock.getsockname()[1]
        self.tpvs = 0
        self.notice = b""
        self.eof = threading.Event()
        if read:
            threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        f = self.sock.makefile("rb")
        try:
            for line in f:
                self.tpvs += line.startswith(b'{"class":"TPV"')
                if b"closing" in line:
                    self.notice = line.strip()
        except OSError:
            pass
        self.eof.set()

    def close(self) -> None:
        self.sock.close()


def gpsd_server(lt: LoopThread, **kw: Any) -> GpsdServer:
    srv = GpsdServer("127.0.0.1", next(PORTS), "/dev/ttyS0", **kw)
    lt.run(srv.start())
    return srv


def session_of(lt: LoopThread, srv: GpsdServer, w: Watcher) -> Any:
    return lt.call(
        lambda: next((c for c in srv.connections if c.peer.endswith(f":{w.port}")), None)
    )


def admitted(lt: LoopThread, srv: GpsdServer, w: Watcher) -> bool:
    c = session_of(lt, srv, w)
    return c is not None and c.session


# -- 1. the gpsd port: a connect/close storm ---------------------------------------------------
def test_a_connect_close_storm_does_not_close_healthy_gpsd_watchers(lt: LoopThread) -> None:
    """The audit: 4 threads connecting, sending ?WATCH and closing (FIN) at ~200/s closed
    5/5 healthy watchers within 3 s ("sessions_full: 32 sessions open"): the kernel hands
    over many waiting connections at once, each admitted before its close is read, and the
    watchers, which had once dropped events, lost the tie to the storm's dead ones. Here:
    2 watchers that read (each dropped events in a burst long ago), 4 sessions at most, and
    12 connect/?WATCH/close connections handed over at once. Before: both watchers closed."""
    srv = gpsd_server(lt, max_clients=4, queue_len=4)
    watchers = [Watcher(srv.port) for _ in range(2)]
    try:
        wait_until(lambda: lt.call(lambda: srv.client_count) == 2, what="2 watchers admitted")
        lt.call(lambda: [srv.publish_fix(FIX) for _ in range(20)])  # a burst: events dropped
        wait_until(lambda: all(w.tpvs >= 4 for w in watchers), what="the watchers read")
        assert lt.call(lambda: srv.dropped_total) > 0
        go, released = hold_loop(lt)
        for _ in range(12):
            s = socket.create_connection(("127.0.0.1", srv.port), timeout=5)
            s.sendall(WATCH)
            s.close()
        go.set()
        assert released.wait(5)
        time.sleep(0.3)  # the storm is admitted and leaves
        n = [w.tpvs for w in watchers]
        for _ in range(5):
            lt.call(lambda: srv.publish_fix(FIX))
            time.sleep(0.05)
        wait_until(lambda: all(w.tpvs > k for w, k in zip(watchers, n, strict=True)),
                   what="the watchers still get TPVs")  # fmt: skip
        assert [w.notice for w in watchers] == [b"", b""]
        assert not any(w.eof.is_set() for w in watchers)
        assert lt.call(lambda: srv.closed_counts["sessions_full"]) == 0
        wait_until(lambda: lt.call(lambda: srv.client_count) == 2, what="the storm gone")
    finally:
        for w in watchers:
            w.close()
        lt.run(srv.close())


def test_a_full_gpsd_pool_closes_the_stalled_watcher_then_the_newest_not_an_old_reader(
    lt: LoopThread,
) -> None:
    """Among watchers: one that does not read goes first; among those that read, the newest
    (it has not shown it reads), not an established reader that dropped events long ago
    (before: the cumulative drops condemned it)."""
    # pending_timeout_s 0.4: a sweep every 0.1 s (a stall shows after 0.2 s)
    srv = gpsd_server(lt, max_clients=3, queue_len=4, pending_timeout_s=0.4, slow_client_s=60.0)
    old = Watcher(srv.port)
    stuck = Watcher(srv.port, rcvbuf=4096, read=False)
    everyone = [old, stuck]
    try:
        wait_until(lambda: lt.call(lambda: srv.client_count) == 2, what="admitted")
        lt.call(lambda: [srv.publish_fix(FIX) for _ in range(20)])  # old drops events
        wait_until(lambda: session_of(lt, srv, old).dropped > 0, what="old dropped events")
        middle = Watcher(srv.port)
        everyone.append(middle)
        wait_until(lambda: lt.call(lambda: srv.client_count) == 3, what="middle admitted")
        # the stuck watcher's window shuts (large reports hurry its tiny buffer along)
        sats = tuple(SatInfo(i + 1, 45.0, float(i), 40.0, True) for i in range(200))
        big_sky = GpsSky(t_s=1.0, satellites=sats, pdop=2.1, hdop=1.1, vdop=1.8)
        c = session_of(lt, srv, stuck)

        def stuck_acked() -> tuple[int, int]:
            t = c.writer.transport
            waiting = (unacknowledged_bytes(t) or 0) + t.get_write_buffer_size()
            return c.bytes_out - waiting, waiting

        seen = None
        deadline = time.monotonic() + 10
        while True:
            lt.call(lambda: srv.publish_sky(big_sky))
            now = lt.call(stuck_acked)
            if seen is not None and now[0] == seen[0] and now[1] > 0:
                break
            assert time.monotonic() < deadline, "the stuck watcher kept reading"
            seen = now
            time.sleep(0.2)
        wait_until(lambda: lt.call(lambda: c.stalled_since_s is not None), what="stall seen")
        time.sleep(0.5)  # stalled well past the sweep's noise
        first = Watcher(srv.port)  # the pool is full: the stalled watcher goes
        everyone.append(first)
        wait_until(lambda: lt.call(lambda: srv.closed_counts["sessions_full"]) == 1)
        assert lt.call(lambda: c.evicted) == "sessions_full"
        wait_until(lambda: admitted(lt, srv, first), what="the first one admitted")
        time.sleep(0.2)
        second = Watcher(srv.port)  # full again: the newest reader goes, not the old one
        everyone.append(second)
        wait_until(lambda: lt.call(lambda: srv.closed_counts["sessions_full"]) == 2)
        assert first.eof.wait(5)
        assert b"closing: sessions_full" in first.notice
        n = (old.tpvs, middle.tpvs, second.tpvs)
        for _ in range(5):
            lt.call(lambda: srv.publish_fix(FIX))
            time.sleep(0.05)
        wait_until(lambda: all(w.tpvs > k for w, k in zip((old, middle, second), n, strict=True)),
                   what="the rest read on")  # fmt: skip
        assert old.notice == middle.notice == second.notice == b""
    finally:
        for w in everyone:
            w.close()
        lt.run(srv.close())


# -- 2. and 3. the web console ---------------------------------------------------------------------
def console_pair(lt: LoopThread, **console: Any) -> tuple[ControlServer, ConsoleServer]:
    srv = ControlServer(ServerConfig(port=next(PORTS)), RecordingBackend(), token=TOKEN.encode())
    lt.run(srv.start())
    con = ConsoleServer(ConsoleConfig(enabled=True, port=next(PORTS), **console), srv, lambda: {})
    lt.run(con.start())
    return srv, con


class Clock:
    """A settable monotonic clock (s)."""

    def __init__(self) -> None:
        self.now = 1000.0

    def __call__(self) -> float:
        return self.now


def test_a_connection_over_the_console_cap_closes_without_a_traceback_counted_and_logged(
    lt: LoopThread, caplog: pytest.LogCaptureFixture, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The audit: a connect storm (~3000 connections in 10 s) wrote 514 "Task exception was
    never retrieved ... assert manager is not None" tracebacks. The cap closed the very
    connection being opened when every older one was closing already (their peers' FINs
    read in the same turn of the loop), before aiohttp had started its handler. Here that
    turn is made to happen: ``cap`` idle connections, then, the loop held, a new one
    accepted in one turn and the idle ones' FINs read in the next. Then a burst of 60
    connections: each close counted, logged at most once a second."""
    # the console's rate-limited log runs on a clock that stands still: the closes fall in
    # one period of it however long a loaded host takes over them (one line; unlimited, 60)
    clock = Clock()
    monkeypatch.setattr(
        console_server,
        "RateLimitedLog",
        lambda logger, period_s: RateLimitedLog(logger, period_s, clock),
    )
    srv, con = console_pair(lt, max_clients=1)
    cap = 1 + CONNECTION_SLACK
    server = con._runner.server  # type: ignore[union-attr]
    caplog.set_level(logging.INFO, logger="x6wd.app.console.server")
    idle = [socket.create_connection(("127.0.0.1", con.port), timeout=5) for _ in range(cap)]
    new: socket.socket | None = None
    burst: list[socket.socket] = []
    try:
        wait_until(lambda: lt.call(lambda: len(server.connections)) == cap, what="cap open")
        first, second = threading.Event(), threading.Event()
        go_first, go_second = threading.Event(), threading.Event()

        def hold_second() -> None:  # the turn in which the new connection is accepted
            second.set()
            go_second.wait(5)

        def hold_first() -> None:
            first.set()
            go_first.wait(5)
            lt.loop.call_soon(hold_second)

        lt.loop.call_soon_threadsafe(hold_first)
        assert first.wait(5)
        new = socket.create_connection(("127.0.0.1", con.port), timeout=5)  # in the backlog
        go_first.set()
        assert second.wait(5)
        for s in idle:  # their FINs are read in the turn after the accept
            s.close()
        time.sleep(0.05)
        go_second.set()
        wait_until(lambda: lt.call(lambda: con.connections_closed) >= 1, what="a cap close")
        assert new.recv(1) == b""  # the new one was the one closed (all others were going)
        for _ in range(60):
            burst.append(socket.create_connection(("127.0.0.1", con.port), timeout=5))
        wait_until(lambda: lt.call(lambda: con.connections_closed) >= 60 - cap + 1, 20.0, "burst")

        def logged() -> list[str]:
            return [r.getMessage() for r in caplog.records if "cap closes" in r.getMessage()
                    or "connections open" in r.getMessage()]  # fmt: skip

        assert len(logged()) == 1, logged()  # the first close; the others counted
        clock.now += 1.0  # a period later: the console's tick flushes the "N more"
        wait_until(lambda: len(logged()) == 2, 10.0, "the tick's N more")
        more = re.fullmatch(r"console: connection cap closes: (\d+) more in the last 1\.0 s",
                            logged()[1])  # fmt: skip
        assert more is not None, logged()
        assert 60 - cap <= int(more[1]) <= lt.call(lambda: con.connections_closed) - 1
        lt.call(gc.collect)  # a failed task is reported when it is collected
        time.sleep(0.1)
        errors = lt.errors  # type: ignore[attr-defined]
        assert errors == [], f"{len(errors)} loop errors, the first: {errors[0]}"
        assert not [r for r in caplog.records if r.levelno >= logging.ERROR]
        assert len(logged()) == 2, logged()
        assert lt.call(con.stats)["connections_closed"] >= 60 - cap + 1
    finally:
        for s in [*idle, *burst, *([new] if new else [])]:
            s.close()
        lt.run(con.close())
        lt.run(srv.close())


def ws_connect(port: int) -> socket.socket:
    """A raw WebSocket to the console's /ws (nothing read after the handshake's reply)."""
    s = socket.socket()
    s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    s.settimeout(5)
    s.connect(("127.0.0.1", port))
    return ws_upgrade(s, port)


def ws_upgrade(s: socket.socket, port: int) -> socket.socket:
    """``s``, connected to the console on ``port``, upgraded to a WebSocket on /ws (the
    handshake's reply read, nothing more)."""
    key = base64.b64encode(os.urandom(16)).decode()
    s.sendall(
        f"GET /ws HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nUpgrade: websocket\r\n"
        f"Connection: Upgrade\r\nSec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\n\r\n"
        .encode()
    )  # fmt: skip
    head = b""
    while b"\r\n\r\n" not in head:
        chunk = s.recv(1)
        assert chunk, "closed during the handshake"
        head += chunk
    assert head.startswith(b"HTTP/1.1 101"), head
    return s


def ws_send(s: socket.socket, obj: dict[str, Any]) -> None:
    payload = json.dumps(obj).encode()
    mask = os.urandom(4)
    masked = bytes(b ^ mask[i % 4] for i, b in enumerate(payload))
    assert len(payload) < 126
    s.sendall(struct.pack("!BB", 0x81, 0x80 | len(payload)) + mask + masked)


def test_a_page_that_authenticates_then_never_reads_is_closed_counted_and_logged(
    lt: LoopThread, caplog: pytest.LogCaptureFixture, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The audit: such a page was closed after 7-10 s by aiohttp's heartbeat (no pong) with
    no log line, and the console's counters stayed 0. Now it is counted (``slow_pages`` in
    the console's stats, so in ``status``) and logged, as the console's other slow-page
    close. (The heartbeat is shortened to 0.4 s here.)"""
    monkeypatch.setattr(console_server, "HEARTBEAT_S", 0.4)
    caplog.set_level(logging.INFO, logger="x6wd.app.console.server")
    srv, con = console_pair(lt)
    s = ws_connect(con.port)
    try:
        ws_send(s, {"id": 1, "cmd": "auth", "token": TOKEN})
        wait_until(lambda: lt.call(lambda: any(p.client.authenticated for p in con._pages)),
                   what="authenticated")  # fmt: skip
        wait_until(lambda: lt.call(lambda: not con._pages), 5.0, "the page closed")
        stats = lt.call(con.stats)
        assert stats["slow_pages"] == 1, stats
        logged = [r.getMessage() for r in caplog.records if "no pong" in r.getMessage()]
        assert len(logged) == 1 and "slow_pages 1" in logged[0], logged
    finally:
        s.close()
        lt.run(con.close())
        lt.run(srv.close())
