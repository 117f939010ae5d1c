"""Remote-control protocol server over real TCP sockets (and TLS with an openssl certificate)."""

from __future__ import annotations

import asyncio
import json
import os
import socket
import ssl
import subprocess
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

from tests.conftest import require_program
from x6wd.app.client import RemoteClient, RequestFailed
from x6wd.app.server import CommandError, ControlServer, load_token
from x6wd.core.config import ServerConfig
from x6wd.core.errors import ConfigError
from x6wd.core.mission_files import Waypoint

TOKEN = "s3cret-token-for-tests"


class RecordingBackend:
    """The daemon's side of the protocol, reduced to recording what it was asked."""

    def __init__(self) -> None:
        self.calls: list[tuple[str, Any]] = []
        self.fail_next: Exception | None = None
        self.seen = 0

    def _call(self, name: str, arg: Any = None) -> dict[str, Any]:
        self.calls.append((name, arg))
        if self.fail_next is not None:
            exc, self.fail_next = self.fail_next, None
            raise exc
        return {"did": name}

    manual_until = 0.0  # time.monotonic() when the latest drive ends (MANUAL until then)

    def status(self) -> dict[str, Any]:
        mode = "MANUAL" if time.monotonic() < self.manual_until else "IDLE"
        return {"mode": mode, "state": "IDLE", "links": {"gps": "ok", "motors": "ok"}}

    def load_mission(self, waypoints: list[Waypoint]) -> dict[str, Any]:
        self._call("load_mission", waypoints)
        return {"count": len(waypoints)}

    def start(self) -> dict[str, Any]:
        return self._call("start")

    def pause(self) -> dict[str, Any]:
        return self._call("pause")

    def resume(self) -> dict[str, Any]:
        return self._call("resume")

    def return_home(self) -> dict[str, Any]:
        return self._call("return")

    def operator_seen(self) -> None:
        self.seen += 1  # not a call: every request of an operator makes one

    def stop(self) -> dict[str, Any]:
        self.manual_until = 0.0
        return self._call("stop")

    def drive(self, left_pct: float, right_pct: float, duration_s: float) -> dict[str, Any]:
        self._call("drive", (left_pct, right_pct, duration_s))
        self.manual_until = time.monotonic() + duration_s
        return {"left": left_pct, "right": right_pct, "duration_s": duration_s}  # the daemon's

    def log_tail(self, n: int) -> list[str]:
        return [f"line {i}" for i in range(n)]


class LoopThread:
    """An asyncio loop in a thread, so blocking test clients can talk to the server."""

    def __init__(self) -> None:
        self.loop = asyncio.new_event_loop()
        self.thread = threading.Thread(target=self.loop.run_forever, daemon=True)
        self.thread.start()

    def run(self, coro: Any) -> Any:
        return asyncio.run_coroutine_threadsafe(coro, self.loop).result(10)

    def call(self, fn: Callable[[], Any]) -> Any:
        async def wrap() -> Any:
            return fn()

        return self.run(wrap())

    def close(self) -> None:
        async def cancel_rest() -> None:
            me = asyncio.current_task()
            rest = [t for t in asyncio.all_tasks() if t is not me]
            for t in rest:
                t.cancel()
            await asyncio.gather(*rest, return_exceptions=True)

        self.run(cancel_rest())
        self.loop.call_soon_threadsafe(self.loop.stop)
        self.thread.join(5)
        self.loop.close()


@pytest.fixture
def loop_thread() -> Iterator[LoopThread]:
    lt = LoopThread()
    yield lt
    lt.close()


def start_server(lt: LoopThread, backend: RecordingBackend, **kw: Any) -> ControlServer:
    token = kw.pop("token", None)
    ctx = kw.pop("ssl_context", None)
    cfg = ServerConfig(**{"port": 0, **kw})
    srv = ControlServer(cfg, backend, token=token, ssl_context=ctx)
    lt.run(srv.start())
    return srv


@pytest.fixture
def served(loop_thread: LoopThread) -> Iterator[tuple[ControlServer, RecordingBackend]]:
    backend = RecordingBackend()
    # a short failed-auth back-off keeps the suite fast (test_lockout checks the default's)
    srv = start_server(loop_thread, backend, token=TOKEN.encode(), auth_fail_delay_s=0.05)
    yield srv, backend
    loop_thread.run(srv.close())


class Raw:
    """A bare line-oriented TCP client, for requests the real client would never send."""

    def __init__(self, port: int) -> None:
        self.sock = socket.create_connection(("127.0.0.1", port), timeout=5)
        self.f = self.sock.makefile("rb")

    def send(self, data: bytes) -> None:
        self.sock.sendall(data)

    def line(self) -> dict[str, Any]:
        raw = self.f.readline()
        assert raw, "server closed the connection"
        return json.loads(raw)

    def ask(self, obj: dict[str, Any]) -> dict[str, Any]:
        self.send(json.dumps(obj).encode() + b"\n")
        return self.line()

    def close(self) -> None:
        self.f.close()
        self.sock.close()


def test_hello_reports_version_and_auth_state(served) -> None:
    srv, _ = served
    with RemoteClient("127.0.0.1", srv.port) as c:
        r = c.request("hello")
    assert r["server"] == "x6wd" and r["protocol"] == 1
    assert r["auth_required"] is True and r["authenticated"] is False


def test_unauthenticated_only_hello_auth_status_stop(served) -> None:
    srv, backend = served
    raw = Raw(srv.port)
    try:
        for cmd in ("start", "pause", "resume", "return", "watch", "log"):
            r = raw.ask({"id": cmd, "cmd": cmd})
            assert r == {
                "id": cmd,
                "ok": False,
                "error": {"code": "unauthorized", "message": r["error"]["message"]},
            }
        assert raw.ask({"id": 1, "cmd": "status"})["ok"] is True
        assert raw.ask({"id": 2, "cmd": "stop"})["ok"] is True
        assert backend.calls == [("stop", None)]
        assert raw.ask({"id": 3, "cmd": "auth", "token": "wrong"})["error"]["code"] == "auth_failed"
        assert raw.ask({"id": 4, "cmd": "start"})["error"]["code"] == "unauthorized"
        assert raw.ask({"id": 5, "cmd": "auth", "token": TOKEN})["ok"] is True
        assert raw.ask({"id": 6, "cmd": "start"}) == {"id": 6, "ok": True, "did": "start"}
    finally:
        raw.close()


def test_return_and_every_operator_request_is_seen(served) -> None:
    srv, backend = served
    raw = Raw(srv.port)
    try:
        assert raw.ask({"id": 1, "cmd": "status"})["ok"] is True
        assert raw.ask({"id": 2, "cmd": "stop"})["ok"] is True
        assert raw.ask({"id": 3, "cmd": "return"})["error"]["code"] == "unauthorized"
        assert raw.ask({"id": 4, "cmd": "auth", "token": "wrong"})["error"]["code"] == "auth_failed"
        assert backend.seen == 0  # nobody allowed to command has spoken yet
        assert raw.ask({"id": 5, "cmd": "auth", "token": TOKEN})["ok"] is True
        assert backend.seen == 1
        assert raw.ask({"id": 6, "cmd": "status"})["ok"] is True  # status counts too
        assert backend.seen == 2
        assert raw.ask({"id": 7, "cmd": "return"}) == {"id": 7, "ok": True, "did": "return"}
        assert raw.ask({"id": 8, "cmd": "stop"})["ok"] is True
        assert backend.seen == 4
        # return is a motion command: the stop after it reached the backend again
        assert backend.calls == [("stop", None), ("return", None), ("stop", None)]
    finally:
        raw.close()


def test_bad_requests_get_error_replies_and_the_connection_carries_on(served) -> None:
    srv, _ = served
    raw = Raw(srv.port)

    def bad(reason: str) -> None:
        err = raw.line()["error"]
        assert (err["code"], err["reason"]) == ("bad_request", reason), err

    try:
        raw.send(b"this is not json\n")
        bad("bad_json")
        raw.send(b"[1, 2]\n")
        bad("not_object")
        assert raw.ask({"id": 7})["error"]["code"] == "bad_request"
        r = raw.ask({"id": 8, "cmd": "fly"})
        assert r["id"] == 8 and r["error"]["code"] == "unknown_command"
        raw.send(b"\xff\xfe\n")
        bad("bad_utf8")
        assert raw.ask({"id": 9, "cmd": "hello"})["ok"] is True
    finally:
        raw.close()


def test_a_garbage_flood_is_answered_in_full_but_at_the_request_rate(loop_thread) -> None:
    import time

    backend = RecordingBackend()
    srv = start_server(loop_thread, backend, rate_per_s=200.0, input_bytes_per_s=1 << 24)
    flood, other = Raw(srv.port), Raw(srv.port)
    try:
        t0 = time.monotonic()
        flood.send(b"not json\n" * 400)
        assert other.ask({"id": 1, "cmd": "hello"})["ok"] is True  # others are not held up
        codes = [flood.line()["error"]["reason"] for _ in range(400)]
        elapsed = time.monotonic() - t0
        assert codes == ["bad_json"] * 400  # every line answered, none lost
        # 200 within the burst, the other 200 at 200/s: about a second (0.9 for timer slack)
        assert elapsed >= 0.9
        assert flood.ask({"id": 2, "cmd": "stop"})["ok"] is True
    finally:
        flood.close()
        other.close()
        loop_thread.run(srv.close())


def test_oversized_line_is_rejected_once_then_service_continues(loop_thread) -> None:
    backend = RecordingBackend()
    srv = start_server(loop_thread, backend, max_line_bytes=1024, input_bytes_per_s=1 << 24)
    raw = Raw(srv.port)
    try:
        raw.send(b'{"id":1,"cmd":"hello","pad":"' + b"x" * 200_000 + b'"}\n')
        r = raw.line()
        assert r["id"] is None and r["error"]["code"] == "bad_request"
        assert r["error"]["reason"] == "line_too_long"
        assert raw.ask({"id": 2, "cmd": "hello"})["id"] == 2
    finally:
        raw.close()
        loop_thread.run(srv.close())


def test_rate_limit_refuses_excess_but_never_stop(loop_thread) -> None:
    backend = RecordingBackend()
    now = [0.0]
    cfg = ServerConfig(port=0, rate_per_s=1.0)
    srv = ControlServer(cfg, backend, clock=lambda: now[0])
    loop_thread.run(srv.start())
    raw = Raw(srv.port)
    try:
        codes = [raw.ask({"id": i, "cmd": "status"}).get("error", {}).get("code") for i in range(8)]
        assert codes[:5] == [None] * 5  # the burst
        assert codes[5:] == ["rate_limited"] * 3
        assert raw.ask({"id": "s", "cmd": "stop"})["ok"] is True
        now[0] += 1.0  # one more token after a second
        assert raw.ask({"id": 9, "cmd": "status"})["ok"] is True
        assert raw.ask({"id": 10, "cmd": "status"})["error"]["code"] == "rate_limited"
    finally:
        raw.close()
        loop_thread.run(srv.close())


def test_full_session_pool_makes_room_for_a_new_session(loop_thread) -> None:
    """Never refused: the idle session gives way to the newcomer, with a closing notice."""
    backend = RecordingBackend()
    srv = start_server(loop_thread, backend, max_clients=2)
    a, b = Raw(srv.port), Raw(srv.port)
    try:
        assert a.ask({"id": 1, "cmd": "hello"})["ok"]
        assert b.ask({"id": 1, "cmd": "hello"})["ok"]
        assert b.ask({"id": 2, "cmd": "watch"})["ok"]  # a watcher is worth more than idle a
        c = Raw(srv.port)
        assert c.ask({"id": 1, "cmd": "hello"})["ok"]
        notice = a.line()
        assert notice["id"] is None and notice["error"]["code"] == "closed"
        assert notice["error"]["reason"] == "sessions_full"
        assert a.f.readline() == b""  # and closed
        assert b.ask({"id": 3, "cmd": "hello"})["ok"]
        stats = c.ask({"id": 2, "cmd": "status"})["server"]
        assert stats["clients"] == 2 and stats["closed"] == {"sessions_full": 1}
        c.close()
    finally:
        a.close()
        b.close()
        loop_thread.run(srv.close())


def test_mission_load_from_list_gpx_and_csv(loop_thread) -> None:
    backend = RecordingBackend()
    srv = start_server(loop_thread, backend)
    gpx = (
        '<?xml version="1.0"?><gpx version="1.1" xmlns="http://www.topografix.com/GPX/1/1">'
        '<rte><rtept lat="51.1" lon="-1.5"/><rtept lat="51.2" lon="-1.6"/></rte></gpx>'
    )
    with RemoteClient("127.0.0.1", srv.port) as c:
        assert c.request("mission.load", waypoints=[[51.0, -1.0], [51.0, -1.1]])["count"] == 2
        assert c.request("mission.load", gpx=gpx)["count"] == 2
        assert c.request("mission.load", csv="lat,lon\n51.3,-1.7\n")["count"] == 1
        for bad in (
            {"waypoints": [[95.0, 0.0]]},
            {"waypoints": "51,0"},
            {"csv": "lat,lon\n51,abc\n"},
            {"gpx": "<gpx><wpt lat='1'/></gpx>"},
            {},
            {"waypoints": [[1, 2]], "csv": "1,2"},
        ):
            with pytest.raises(RequestFailed) as ei:
                c.request("mission.load", **bad)
            assert ei.value.code == "bad_request"
    loads = [arg for name, arg in backend.calls if name == "load_mission"]
    assert loads == [
        [Waypoint(51.0, -1.0), Waypoint(51.0, -1.1)],
        [Waypoint(51.1, -1.5), Waypoint(51.2, -1.6)],
        [Waypoint(51.3, -1.7)],
    ]
    loop_thread.run(srv.close())


def test_drive_is_validated_and_backend_refusals_become_error_codes(loop_thread) -> None:
    backend = RecordingBackend()
    srv = start_server(loop_thread, backend)
    with RemoteClient("127.0.0.1", srv.port) as c:
        assert c.request("drive", left=50, right=-50, duration_s=1.5)["duration_s"] == 1.5
        for bad in (
            {"left": 150, "right": 0, "duration_s": 1},
            {"left": True, "right": 0, "duration_s": 1},
            {"left": 0, "right": 0},
            {"left": 0, "right": 0, "duration_s": -1},
        ):
            with pytest.raises(RequestFailed) as ei:
                c.request("drive", **bad)
            assert ei.value.code == "bad_request"
        backend.fail_next = CommandError("geofence", "too far")
        with pytest.raises(RequestFailed) as ei:
            c.request("start")
        assert (ei.value.code, ei.value.message) == ("geofence", "too far")
        backend.fail_next = RuntimeError("bug")
        with pytest.raises(RequestFailed) as ei:
            c.request("pause")
        assert ei.value.code == "internal"
        assert c.request("resume")["did"] == "resume"  # still serving
        assert c.request("log", n=3)["lines"] == ["line 0", "line 1", "line 2"]
    assert ("drive", (50.0, -50.0, 1.5)) in backend.calls
    loop_thread.run(srv.close())


def test_watch_delivers_events_and_stuck_client_drops_oldest(loop_thread) -> None:
    backend = RecordingBackend()
    srv = start_server(loop_thread, backend, queue_len=8)
    with RemoteClient("127.0.0.1", srv.port) as c:
        c.request("watch", on=True)
        loop_thread.call(lambda: srv.publish({"event": "telemetry", "data": {"n": 1}}))
        assert c.next_event(5.0) == {"event": "telemetry", "data": {"n": 1}}
        # a client that never reads: its socket buffers fill, then its queue drops the oldest
        stuck = Raw(srv.port)
        stuck.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
        stuck.ask({"id": 1, "cmd": "watch", "on": True})
        big = {"event": "telemetry", "data": {"pad": "y" * 20_000}}
        for _ in range(50):  # the loop runs between these: the socket buffers fill
            loop_thread.call(lambda: srv.publish(big))

        def burst() -> None:  # the control loop publishing without ever yielding
            for _ in range(200):
                srv.publish(big)

        loop_thread.call(burst)
        queued = loop_thread.call(lambda: max(len(cl.events) for cl in srv.connections))
        assert queued <= 8
        assert srv.dropped_total > 0
        status = c.request("status")
        assert status["server"]["dropped"] == srv.dropped_total
        # the reading client still gets the latest events
        assert c.request("hello")["ok"]
        stuck.close()
    loop_thread.run(srv.close())


def test_token_file_must_not_be_group_or_world_readable(tmp_path: Path) -> None:
    p = tmp_path / "token"
    p.write_text(TOKEN + "\n")
    p.chmod(0o640)
    with pytest.raises(ConfigError, match="chmod 600"):
        load_token(p)
    p.chmod(0o600)
    assert load_token(p) == TOKEN.encode()
    with pytest.raises(ConfigError, match="cannot read"):
        load_token(tmp_path / "missing")


def test_non_loopback_bind_requires_a_token() -> None:
    with pytest.raises(ConfigError, match="token_file"):
        ControlServer(ServerConfig(bind="0.0.0.0"), RecordingBackend())


def test_tls_with_openssl_certificate(tmp_path: Path, loop_thread: LoopThread) -> None:
    openssl = require_program("openssl")
    cert, key = tmp_path / "cert.pem", tmp_path / "key.pem"
    subprocess.run(
        [openssl, "req", "-x509", "-newkey", "rsa:2048", "-nodes", "-days", "2",
         "-subj", "/CN=localhost", "-addext", "subjectAltName=DNS:localhost,IP:127.0.0.1",
         "-keyout", str(key), "-out", str(cert)],
        check=True, capture_output=True,
    )  # fmt: skip
    os.chmod(key, 0o600)
    token_file = tmp_path / "token"
    token_file.write_text(TOKEN)
    token_file.chmod(0o600)
    cfg = ServerConfig(port=0, tls_cert=str(cert), tls_key=str(key), token_file=str(token_file))
    backend = RecordingBackend()
    srv = ControlServer.from_config(cfg, backend)
    loop_thread.run(srv.start())
    ctx = ssl.create_default_context(cafile=str(cert))
    with RemoteClient("127.0.0.1", srv.port, ssl_context=ctx, token=TOKEN) as c:
        assert c.request("hello")["tls"] is True
        assert c.request("start")["did"] == "start"
    # a plain-text client gets nothing useful from a TLS port
    raw = socket.create_connection(("127.0.0.1", srv.port), timeout=5)
    raw.sendall(b'{"id":1,"cmd":"hello"}\n')
    assert b'"ok"' not in raw.recv(4096)
    raw.close()
    loop_thread.run(srv.close())


def test_a_drive_over_the_robots_limit_is_a_bad_argument_like_every_other(loop_thread) -> None:
    """The backend's refusal of ``duration_s`` over ``[safety] manual_max_s`` (the runner's
    CommandError("bad_request", ...)) carries reason bad_argument, as the server's own
    range checks do; other refusals keep their code without a reason."""
    backend = RecordingBackend()
    srv = start_server(loop_thread, backend)
    raw = Raw(srv.port)
    try:
        backend.fail_next = CommandError("bad_request", "duration_s 99 > limit 5 s")
        r = raw.ask({"id": 7, "cmd": "drive", "left": 1, "right": 1, "duration_s": 99})
        assert r == {
            "id": 7,
            "ok": False,
            "error": {
                "code": "bad_request",
                "message": "duration_s 99 > limit 5 s",
                "reason": "bad_argument",
            },
        }
        r = raw.ask({"id": 8, "cmd": "drive", "left": 150, "right": 1, "duration_s": 1})
        assert r["error"]["reason"] == "bad_argument"  # the server's own check: the same
        backend.fail_next = CommandError("rejected", "motor link down")
        r = raw.ask({"id": 9, "cmd": "start"})
        assert r["error"] == {"code": "rejected", "message": "motor link down"}
    finally:
        raw.close()
        loop_thread.run(srv.close())


def test_an_integer_too_long_to_convert_is_a_number_out_of_range(served) -> None:
    srv, _ = served
    raw = Raw(srv.port)
    try:
        assert raw.ask({"id": 1, "cmd": "auth", "token": TOKEN})["ok"] is True
        for digits in ("1" * 5000, "-" + "9" * 4301):
            raw.send(b'{"id":7,"cmd":"drive","left":' + digits.encode() + b',"right":1}\n')
            err = raw.line()["error"]
            assert (err["code"], err["reason"]) == ("bad_request", "bad_number"), err
            assert "out of range" in err["message"] and "integer of" in err["message"], err
            assert "sys." not in err["message"] and "Exceeds" not in err["message"], err
        # the longest integer that converts is a number like any other (here: out of range)
        raw.send(b'{"id":8,"cmd":"drive","left":' + b"1" * 4300 + b',"right":1}\n')
        assert raw.line()["error"]["reason"] == "bad_argument"
        assert raw.ask({"id": 9, "cmd": "hello"})["ok"] is True  # the connection carries on
    finally:
        raw.close()


def test_status_does_not_count_its_own_asker_as_pending(loop_thread) -> None:
    """Without a token a connection is pending until one valid request: a status is one, so
    the figures in its reply show the asker admitted (a session), not pending. With a token
    an unauthenticated asker is pending, and counted so."""
    backend = RecordingBackend()
    srv = start_server(loop_thread, backend)  # no token
    raw, silent = Raw(srv.port), Raw(srv.port)

    def until_pending(n: int) -> None:
        deadline = time.monotonic() + 5
        while loop_thread.call(lambda: srv.pending_count) != n:
            assert time.monotonic() < deadline
            time.sleep(0.01)

    try:
        until_pending(2)
        stats = raw.ask({"id": 1, "cmd": "status"})["server"]
        assert (stats["clients"], stats["pending"]) == (1, 1)  # the silent one is pending
        silent.close()
        until_pending(0)
        stats = raw.ask({"id": 2, "cmd": "status"})["server"]
        assert (stats["clients"], stats["pending"]) == (1, 0)
        other = Raw(srv.port)
        stats = other.ask({"id": 1, "cmd": "status"})["server"]  # a first status too
        assert (stats["clients"], stats["pending"]) == (2, 0)
        other.close()
    finally:
        raw.close()
        loop_thread.run(srv.close())
    srv = start_server(loop_thread, backend, token=TOKEN.encode())
    raw = Raw(srv.port)
    try:
        stats = raw.ask({"id": 1, "cmd": "status"})["server"]
        assert (stats["clients"], stats["pending"]) == (0, 1)  # not authenticated: pending
        assert raw.ask({"id": 2, "cmd": "auth", "token": TOKEN})["ok"] is True
        stats = raw.ask({"id": 3, "cmd": "status"})["server"]
        assert (stats["clients"], stats["pending"]) == (1, 0)
    finally:
        raw.close()
        loop_thread.run(srv.close())
