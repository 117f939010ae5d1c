"""Outside audit 10b, findings 4 and 5 (the web console under unauthenticated load).

4. Six threads opening connections with half-sent headers (~330/s) made 5 of 24 page loads
   fail (ContentLengthError): the connection cap closed the oldest connection that was not a
   page's WebSocket, also one sending console.js. Now half-sent requests go first (from the
   address holding the most connections), connections answering a request last.
5. Pages that had not authenticated could send messages of ``max_message_bytes`` (1 MiB),
   each parsed before the throttle refused it: 8 such pages sending 200 KB messages raised
   the control port's stop round trip from 2 ms to 83-461 ms. Now a message over
   ``PRE_AUTH_MESSAGE_BYTES`` before ``auth`` closes the page (1009).

Real sockets on 127.0.0.1 (and 127.0.0.2, a second peer address) against the real console
and control servers on a loop thread (tests.test_server.LoopThread), ports 44100-44199.
"""

from __future__ import annotations

import json
import select
import socket
import ssl
import struct
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

from tests.conftest import self_signed_cert
from tests.test_lockout import lt
from tests.test_network_round6 import ws_upgrade
from tests.test_server import TOKEN, LoopThread, RecordingBackend
from x6wd.app.console import server as console_server
from x6wd.app.console.server import CONNECTION_SLACK, STATIC_DIR, ConsoleServer
from x6wd.app.server import ControlServer, server_ssl_context
from x6wd.core.config import ConsoleConfig, ServerConfig

__all__ = ["lt"]  # the fixture, shared with test_lockout

PORTS = iter(range(44100, 44200))
HALF_SENT = b"GET / HTTP/1.1\r\nHost: 127.0.0.1\r\nX-a: "  # the audit's f_http.py, 'partial'


@pytest.fixture
def pair(lt: LoopThread) -> Iterator[tuple[ControlServer, ConsoleServer]]:
    srv = ControlServer(ServerConfig(port=next(PORTS)), RecordingBackend(), token=TOKEN.encode())
    lt.run(srv.start())
    con = ConsoleServer(ConsoleConfig(enabled=True, port=next(PORTS), max_clients=1), srv, dict)
    lt.run(con.start())
    yield srv, con
    lt.run(con.close())
    lt.run(srv.close())


def wait_until(pred: Callable[[], Any], timeout_s: float = 10.0, what: str = "") -> Any:
    deadline = time.monotonic() + timeout_s
    while True:
        v = pred()
        if v:
            return v
        assert time.monotonic() < deadline, f"not reached within {timeout_s} s: {what}"
        time.sleep(0.01)


def connect(port: int, source: str = "127.0.0.1", rcvbuf: int | None = None) -> socket.socket:
    s = socket.socket()
    if rcvbuf is not None:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, rcvbuf)
    s.bind((source, 0))
    s.settimeout(10)
    s.connect(("127.0.0.1", port))
    return s


def get(s: socket.socket, path: str, port: int) -> None:
    s.sendall(f"GET {path} HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\n\r\n".encode())


def response(s: socket.socket) -> tuple[int, bytes]:
    """One HTTP response (status, body of its Content-Length); AssertionError when the
    connection ends before the whole body (what the audit's page load saw)."""
    data = b""
    while b"\r\n\r\n" not in data:
        chunk = s.recv(65536)
        assert chunk, f"closed in the head: {data!r}"
        data += chunk
    head, body = data.split(b"\r\n\r\n", 1)
    lines = head.decode("latin-1").split("\r\n")
    length = next(int(v) for k, _, v in (h.partition(":") for h in lines[1:])
                  if k.lower() == "content-length")  # fmt: skip
    while len(body) < length:
        chunk = s.recv(65536)
        assert chunk, f"closed after {len(body)} of {length} bytes"
        body += chunk
    return int(lines[0].split()[1]), body


def closed_by_server(s: socket.socket) -> bool:
    """The server has closed ``s`` (it sends these nothing else)."""
    if not select.select([s], [], [], 0)[0]:
        return False
    try:
        return s.recv(1, socket.MSG_PEEK) == b""
    except ConnectionError:
        return True


def small_send_buffer(server: Any, peer_port: int) -> None:
    """Shrink the send buffer of the console's end of the connection from ``peer_port``."""
    for h in server.connections:
        if h.transport.get_extra_info("peername")[1] == peer_port:
            h.transport.get_extra_info("socket").setsockopt(
                socket.SOL_SOCKET, socket.SO_SNDBUF, 4096
            )
            return
    raise AssertionError(f"no connection from port {peer_port}")


def test_half_sent_requests_are_closed_before_a_page_loads_files(
    lt: LoopThread, pair: tuple[ControlServer, ConsoleServer]
) -> None:
    """A page (127.0.0.2) has three connections: one opened and not used yet (the oldest of
    all), one kept alive after ``/``, one receiving console.js over a slow link it does not
    read yet (the response stalls mid-transfer). Then 3 caps' worth of half-sent requests
    from 127.0.0.1. The old cap closed the oldest: the page's three first, console.js cut
    short (the audit's ContentLengthError). Now each close takes a half-sent request (the
    unused connection has sent no request either, but its address holds fewer), and the
    page loads its files."""
    _, con = pair
    port = con.port
    cap = con.config.max_clients + CONNECTION_SLACK
    server: Any = con._runner.server  # type: ignore[union-attr]
    page: list[socket.socket] = []
    flood: list[socket.socket] = []
    try:
        unused = connect(port, "127.0.0.2")
        page.append(unused)
        kept = connect(port, "127.0.0.2")
        page.append(kept)
        get(kept, "/", port)
        assert response(kept)[0] == 200
        js = connect(port, "127.0.0.2", rcvbuf=4096)
        page.append(js)
        wait_until(lambda: lt.call(lambda: len(server.connections)) == 3, what="3 open")
        # a slow link: the robot's side of it queues little, so console.js (46 KB) stays
        # mid-transfer until the page reads (on loopback it would all be queued at once)
        lt.call(lambda: small_send_buffer(server, js.getsockname()[1]))
        get(js, "/static/console.js", port)
        assert js.recv(1, socket.MSG_PEEK) == b"H"  # its response has begun, and stalls
        for _ in range(3 * cap):
            s = connect(port)
            s.sendall(HALF_SENT)
            flood.append(s)
        closes = 3 + 3 * cap - cap
        wait_until(lambda: lt.call(lambda: con.connections_closed) >= closes, what="the closes")
        status, body = response(js)  # the whole file, though the cap closed connections
        assert (status, body) == (200, (STATIC_DIR / "console.js").read_bytes())
        # every close took a half-sent request: as many of them closed as the console closed
        wait_until(lambda: sum(map(closed_by_server, flood)) == closes,
                   what="the half-sent requests closed")  # fmt: skip
        assert lt.call(lambda: con.connections_closed) == closes
        assert not closed_by_server(kept) and not closed_by_server(unused)
        get(kept, "/static/console.css", port)
        assert response(kept) == (200, (STATIC_DIR / "console.css").read_bytes())
        get(unused, "/", port)
        assert response(unused)[0] == 200
    finally:
        for s in page + flood:
            s.close()


def test_over_tls_the_connections_the_cap_closes_are_gone_at_once(
    lt: LoopThread, tmp_path: Path
) -> None:
    """Over TLS the cap's close waited for the peer's close_notify (asyncio: up to 30 s),
    which half-open connections that never read never send: in the audit's churn the
    console listed ~400 connections, all counted, so each new one (a page's too) closed an
    open one, or itself, at once. Now the closed ones are gone at once, and a page loads."""
    cert, key = self_signed_cert(tmp_path)
    ctx = server_ssl_context(str(cert), str(key))
    srv = ControlServer(
        ServerConfig(port=next(PORTS)), RecordingBackend(), token=TOKEN.encode(), ssl_context=ctx
    )
    lt.run(srv.start())
    con = ConsoleServer(
        ConsoleConfig(enabled=True, port=next(PORTS), max_clients=1), srv, dict, ssl_context=ctx
    )
    lt.run(con.start())
    client = ssl.create_default_context(cafile=str(cert))
    cap = con.config.max_clients + CONNECTION_SLACK
    server: Any = con._runner.server  # type: ignore[union-attr]
    flood: list[socket.socket] = []
    try:
        for _ in range(3 * cap):
            half = client.wrap_socket(connect(con.port), server_hostname="127.0.0.1")
            half.sendall(HALF_SENT)
            flood.append(half)  # never read: their close_notify never comes
        wait_until(lambda: lt.call(lambda: con.connections_closed) >= 2 * cap, what="closes")
        wait_until(lambda: lt.call(lambda: len(server.connections)) <= cap, 5.0,
                   "the closed connections gone")  # fmt: skip
        with client.wrap_socket(connect(con.port), server_hostname="127.0.0.1") as page:
            for path in ("/", "/static/console.js", "/static/console.css"):
                get(page, path, con.port)
                assert response(page)[0] == 200, path
    finally:
        for s in flood:
            s.close()
        lt.run(con.close())
        lt.run(srv.close())


# -- 5. the size of a message before auth -------------------------------------------------------
def ws_connect(port: int) -> socket.socket:
    return ws_upgrade(connect(port), port)


def ws_send(s: socket.socket, obj: dict[str, Any]) -> None:
    payload = json.dumps(obj).encode()
    mask = bytes(4)  # a zero masking key (any key is valid): the payload goes as it is
    masked = payload
    n = len(payload)
    if n < 126:
        head = struct.pack("!BB", 0x81, 0x80 | n)
    elif n < 1 << 16:
        head = struct.pack("!BBH", 0x81, 0x80 | 126, n)
    else:
        head = struct.pack("!BBQ", 0x81, 0x80 | 127, n)
    s.sendall(head + mask + masked)


def recv_exact(s: socket.socket, n: int) -> bytes:
    data = b""
    while len(data) < n:
        chunk = s.recv(n - len(data))
        assert chunk, "closed without a close frame"
        data += chunk
    return data


def ws_frame(s: socket.socket) -> tuple[int, bytes]:
    """The next frame from the server (unmasked): its opcode and payload."""
    b0, b1 = recv_exact(s, 2)
    n = b1 & 0x7F
    if n == 126:
        n = struct.unpack("!H", recv_exact(s, 2))[0]
    elif n == 127:
        n = struct.unpack("!Q", recv_exact(s, 8))[0]
    return b0 & 0x0F, recv_exact(s, n)


def reply_to(s: socket.socket, rid: int) -> dict[str, Any]:
    """The reply with id ``rid`` (events before it skipped); AssertionError on a close."""
    while True:
        op, data = ws_frame(s)
        assert op != 8, f"closed: {struct.unpack('!H', data[:2])[0]} {data[2:]!r}"
        if op == 1:
            msg = json.loads(data)
            if msg.get("id") == rid:
                return msg


def close_frame(s: socket.socket, rid: int) -> tuple[int, str]:
    """The close frame's code and reason; AssertionError when request ``rid`` is answered."""
    while True:
        op, data = ws_frame(s)
        if op == 8:
            return struct.unpack("!H", data[:2])[0], data[2:].decode()
        if op == 1:
            msg = json.loads(data)
            assert msg.get("id") != rid, f"answered, not closed: {msg}"


def test_before_auth_a_large_message_closes_the_page_with_1009(
    pair: tuple[ControlServer, ConsoleServer],
) -> None:
    """A 64 KB message before ``auth``: closed, 1009 with its reason (the old console read
    and parsed it, and any number more). Small ones before ``auth`` are answered, and
    after ``auth`` a 64 KB message is handled as ever (``max_message_bytes``)."""
    _, con = pair
    pad = "x" * 64_000
    s = ws_connect(con.port)
    try:
        welcome = json.loads(ws_frame(s)[1])
        ws_send(s, {"id": 1, "cmd": "hello", "pad": "x" * 3000})  # a few KB: taken
        assert reply_to(s, 1)["ok"]
        ws_send(s, {"id": 2, "cmd": "stop", "pad": pad})
        code, reason = close_frame(s, 2)
        assert code == 1009, (code, reason)
        limit = console_server.PRE_AUTH_MESSAGE_BYTES
        assert reason == f"message too big before auth: at most {limit} bytes until then"
        assert welcome["max_message_bytes_before_auth"] == limit
        s.settimeout(5)
        assert s.recv(1) == b""  # and the connection is dropped
    finally:
        s.close()
    s = ws_connect(con.port)
    try:
        ws_send(s, {"id": 1, "cmd": "auth", "token": TOKEN})
        assert reply_to(s, 1)["ok"]
        ws_send(s, {"id": 2, "cmd": "hello", "pad": pad})
        assert reply_to(s, 2)["ok"]  # answered; the page stays open
        ws_send(s, {"id": 3, "cmd": "stop"})
        assert reply_to(s, 3)["ok"]
    finally:
        s.close()
