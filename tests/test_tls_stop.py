"""A stop over TLS reaches the motors whatever state the other connections are in.

An outside audit of the live daemon (the setup docs/install.md recommends: a token and
``tls_cert``/``tls_key``) found ``stop`` answered ``internal error: AttributeError`` with the
motors still running, 7 stops in 8: every stop first updated the stop fence of every client
the server knew, and asyncio's SSL transport of a connection that had closed (closed twice:
the peer's hang-up, then the server's) raises AttributeError from ``get_extra_info``, before
the stop was sent. The same error took the console's STOP over WSS, the Ctrl-C of
``x6wd client drive``, the dead-man of a driving client that went away (its log line said
"motors stopped"; the motors ran on, and the crashed handler left the connection in the
pools) and the deadline sweep (no auth timeout, idle timeout or slow-reader close any more).

Real TLS sockets on 127.0.0.1 and a fresh self-signed certificate (``openssl req``, as
tests/test_safety_server.py): the control server with a backend that keeps the motors'
state, the web console on the same server over HTTPS/WSS, the command-line client as a
subprocess, and the whole daemon (``sim://`` devices) for the audit's own reproductions.
"""

from __future__ import annotations

import asyncio
import dataclasses
import logging
import signal
import socket
import ssl
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import aiohttp
import pytest

from tests.conftest import self_signed_cert
from tests.test_lockout import lt, wait_until
from tests.test_server import TOKEN, LoopThread, Raw, RecordingBackend
from x6wd.app.console.server import ConsoleServer
from x6wd.app.server import ControlServer, server_ssl_context
from x6wd.core.config import ConsoleConfig, ServerConfig

__all__ = ["lt"]  # the fixture, shared with test_lockout

pytestmark = pytest.mark.integration

DRIVE = {"cmd": "drive", "left": 40, "right": 40, "duration_s": 30}


@pytest.fixture(scope="module")
def tls_files(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, Path]:
    """A throwaway self-signed certificate for localhost/127.0.0.1, its key, and a token
    file (mode 600, as the daemon and the client require)."""
    d = tmp_path_factory.mktemp("tls")
    cert, key = self_signed_cert(d)
    token = d / "token"
    token.write_text(TOKEN + "\n")
    token.chmod(0o600)
    return cert, key, token


class MotorBackend(RecordingBackend):
    """The daemon's side, reduced to the motors: a drive sets them, a stop zeroes them."""

    def __init__(self) -> None:
        super().__init__()
        self.motors = (0.0, 0.0)

    def drive(self, left_pct: float, right_pct: float, duration_s: float) -> dict[str, Any]:
        reply = super().drive(left_pct, right_pct, duration_s)
        self.motors = (left_pct, right_pct)
        return reply

    def stop(self) -> dict[str, Any]:
        self.motors = (0.0, 0.0)
        super().stop()
        return {"mode": "IDLE", "state": "IDLE"}


@dataclasses.dataclass
class Tls:
    """A started control server on TLS with a token, its backend, and a client context."""

    srv: ControlServer
    backend: MotorBackend
    ctx: ssl.SSLContext
    cert: Path
    token_file: Path


@pytest.fixture
def tls_server(lt: LoopThread, tls_files: tuple[Path, Path, Path]) -> Iterator[Callable[..., Tls]]:
    started: list[ControlServer] = []
    cert, key, token_file = tls_files

    def serve(**cfg: Any) -> Tls:
        backend = MotorBackend()
        srv = ControlServer(
            ServerConfig(**{"port": 0, **cfg}), backend, token=TOKEN.encode(),
            ssl_context=server_ssl_context(str(cert), str(key)),
        )  # fmt: skip
        lt.run(srv.start())
        started.append(srv)
        return Tls(srv, backend, ssl.create_default_context(cafile=str(cert)), cert, token_file)

    yield serve
    for srv in started:
        lt.run(srv.close())


class TlsRaw(Raw):
    """:class:`Raw` over TLS."""

    def __init__(self, port: int, ctx: ssl.SSLContext) -> None:
        sock = socket.create_connection(("127.0.0.1", port), timeout=5)
        self.sock = ctx.wrap_socket(sock, server_hostname="localhost")
        self.f = self.sock.makefile("rb")


def closed_tls_client_known(lt: LoopThread, t: Tls) -> Any:
    """A TLS operator that authenticated, asked ``status`` and hung up, the server's end of
    it closed too, yet still known to the server (every client of every transport is in
    its stop fence's weak set until the garbage collector frees it; the reference returned
    keeps it there for the test, as a cycle or a slow collector does in the daemon)."""
    srv = t.srv
    before = lt.call(lambda: set(srv._fenced))
    raw = TlsRaw(srv.port, t.ctx)
    assert raw.ask({"id": 1, "cmd": "auth", "token": TOKEN})["ok"]
    assert raw.ask({"id": 2, "cmd": "status"})["ok"]
    mine = lt.call(lambda: [c for c in srv._fenced if c not in before])
    assert len(mine) == 1
    raw.close()
    client = mine[0]
    wait_until(
        lambda: lt.call(lambda: client.closed and client not in srv.connections),
        5, "the server hung up the closed connection",
    )  # fmt: skip
    assert lt.call(lambda: client.writer.transport.is_closing() and client in srv._fenced)
    return client


def stopped_soon(backend: MotorBackend, timeout_s: float = 2.0) -> None:
    wait_until(lambda: backend.motors == (0.0, 0.0), timeout_s, "the motors stopped")


def x6wd_client(t: Tls, *args: str, **kw: Any) -> list[str]:
    return [
        sys.executable, "-m", "x6wd", "client", "--port", str(t.srv.port), "--cafile",
        str(t.cert), "--token-file", str(t.token_file), *args,
    ]  # fmt: skip


# -- (a) stop: the operator's own, another connection's, the command line's --------------------
def test_a_stop_is_acknowledged_and_reaches_the_motors_while_a_closed_tls_client_is_known(
    lt: LoopThread, tls_server: Callable[..., Tls]
) -> None:
    t = tls_server()
    driver = TlsRaw(t.srv.port, t.ctx)
    try:
        assert driver.ask({"id": 0, "cmd": "auth", "token": TOKEN})["ok"]
        for i in range(3):  # the audit: 7 stops in 8 failed once the state was there
            known = closed_tls_client_known(lt, t)
            assert driver.ask({"id": f"d{i}", **DRIVE})["ok"]
            assert t.backend.motors == (40.0, 40.0)
            # another connection's stop, unauthenticated as the command line sends it
            stopper = TlsRaw(t.srv.port, t.ctx)
            reply = stopper.ask({"id": "s", "cmd": "stop"})
            stopper.close()
            assert reply == {"id": "s", "ok": True, "mode": "IDLE", "state": "IDLE"}, reply
            assert t.backend.motors == (0.0, 0.0)
            # the driver's own stop
            assert driver.ask({"id": f"d{i}b", **DRIVE})["ok"]
            assert driver.ask({"id": f"s{i}", "cmd": "stop"})["ok"]
            assert t.backend.motors == (0.0, 0.0)
            del known
        # `x6wd client stop` over TLS
        closed_tls_client_known(lt, t)
        assert driver.ask({"id": "d", **DRIVE})["ok"]
        r = subprocess.run(x6wd_client(t, "stop"), capture_output=True, text=True, timeout=30)
        assert r.returncode == 0 and "stop: ok" in r.stdout, r.stderr
        assert t.backend.motors == (0.0, 0.0)
        stats = lt.call(t.srv.server_stats)
        assert stats["stops"]["sent"] == stats["stops"]["requested"] == 7
    finally:
        driver.close()


def test_a_stop_sent_during_a_tls_back_off_goes_out_at_once_while_a_closed_client_is_known(
    lt: LoopThread, tls_server: Callable[..., Tls]
) -> None:
    """The early stop (read ahead while the connection sleeps out a wrong token's back-off)
    takes the same path: the motors first."""
    # a 4 s back-off: the stop goes out within 2 s (~0.01 s here), where one held behind the
    # back-off goes out when it ends (~4 s) and a crashed one never
    t = tls_server(auth_fail_delay_s=4.0)
    closed_tls_client_known(lt, t)
    driver = TlsRaw(t.srv.port, t.ctx)
    raw = TlsRaw(t.srv.port, t.ctx)
    try:
        assert driver.ask({"id": 0, "cmd": "auth", "token": TOKEN})["ok"]
        assert driver.ask({"id": 1, **DRIVE})["ok"]
        t_auth = time.monotonic()  # the back-off begins after this
        assert raw.ask({"id": 1, "cmd": "auth", "token": "wrong-token"})["error"]["code"] == (
            "auth_failed"
        )
        t0 = time.monotonic()
        raw.send(b'{"id": 2, "cmd": "stop"}\n')  # read during the 4 s back-off
        stopped_soon(t.backend, 10.0)
        assert time.monotonic() - t0 < 2.0
        assert lt.call(lambda: t.srv.server_stats()["stops"]["early"]) == 1
        assert raw.line() == {"id": 2, "ok": True, "mode": "IDLE", "state": "IDLE"}
        assert time.monotonic() - t_auth >= 3.96  # answered in its turn, after the back-off
    finally:
        raw.close()
        driver.close()


# -- (b) the dead-man: a driving TLS client that goes away ---------------------------------------
@pytest.mark.parametrize("how", ["close", "reset"])
def test_a_driving_tls_client_that_goes_away_stops_the_motors(
    how: str, lt: LoopThread, tls_server: Callable[..., Tls], caplog: pytest.LogCaptureFixture
) -> None:
    t = tls_server()
    closed_tls_client_known(lt, t)
    driver = TlsRaw(t.srv.port, t.ctx)
    assert driver.ask({"id": 0, "cmd": "auth", "token": TOKEN})["ok"]
    assert driver.ask({"id": 1, **DRIVE})["ok"]
    assert t.backend.motors == (40.0, 40.0)
    if how == "reset":  # killed, or its laptop left the network: no TLS close_notify, no FIN
        driver.sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, b"\1\0\0\0\0\0\0\0")
    with caplog.at_level(logging.WARNING, logger="x6wd.app.server"):
        driver.close()
        stopped_soon(t.backend)
        # the handler ended normally: the connection left the pools (the crashed one stayed,
        # and the deadline sweep failed on it from then on)
        wait_until(lambda: lt.call(lambda: t.srv.connections) == (), 2, "the pools empty")
    assert lt.call(lambda: t.srv.server_stats()["stops"]["orphaned"]) == 1
    assert "went away while driving" in caplog.text
    assert "Traceback" not in caplog.text and "failed" not in caplog.text, caplog.text


def test_ctrl_c_on_x6wd_client_drive_over_tls_stops_the_motors(
    lt: LoopThread, tls_server: Callable[..., Tls]
) -> None:
    t = tls_server()
    closed_tls_client_known(lt, t)
    proc = subprocess.Popen(
        x6wd_client(t, "drive", "40", "40", "20"), stderr=subprocess.PIPE, text=True,
        # a background job may inherit SIGINT ignored: give the child Ctrl-C's default
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )  # fmt: skip
    try:
        wait_until(lambda: t.backend.motors == (40.0, 40.0) or proc.poll() is not None, 20, "drive")
        assert proc.poll() is None
        proc.send_signal(signal.SIGINT)
        _, stderr = proc.communicate(timeout=10)
    finally:
        proc.kill()
    assert t.backend.motors == (0.0, 0.0), stderr
    assert proc.returncode == 130 and "stop sent (the robot confirmed it)" in stderr, stderr
    assert [n for n, _ in t.backend.calls] == ["drive", "stop"]


# -- (c) the deadline sweep ----------------------------------------------------------------------
def _closed_within(t: Tls, seconds: float) -> tuple[dict[str, Any], float]:
    """A TLS connection that never sends: the notice the server closes it with, and after
    how long (s)."""
    silent = TlsRaw(t.srv.port, t.ctx)
    t0 = time.monotonic()
    try:
        silent.sock.settimeout(seconds)
        try:
            notice = silent.line()
        except TimeoutError:
            pytest.fail(f"a silent TLS connection was still open after {seconds:g} s")
        return notice, time.monotonic() - t0
    finally:
        silent.close()


def test_the_sweep_closes_a_silent_tls_connection_in_time_while_a_closed_tls_client_is_known(
    lt: LoopThread, tls_server: Callable[..., Tls], caplog: pytest.LogCaptureFixture
) -> None:
    # the audit's state: a closed TLS client known, and a driving client gone since
    # a 1 s deadline: closed within 3 s after it (the sweep runs every 0.25 s); a sweep
    # that has died never closes it (given up after 15 s)
    t = tls_server(auth_timeout_s=1.0)
    closed_tls_client_known(lt, t)
    driver = TlsRaw(t.srv.port, t.ctx)
    assert driver.ask({"id": 0, "cmd": "auth", "token": TOKEN})["ok"]
    assert driver.ask({"id": 1, **DRIVE})["ok"]
    driver.close()
    stopped_soon(t.backend, 10.0)  # its hang-up is handled (the dead-man: the test above)
    with caplog.at_level(logging.ERROR, logger="x6wd.app"):
        for _ in range(2):
            notice, after_s = _closed_within(t, 15.0)
            assert notice["error"]["reason"] == "auth_timeout", notice
            assert after_s < 1.0 + 3.0, after_s
    assert "sweep" not in caplog.text, caplog.text


class _BrokenWriter:
    """A connection's writer in a state nobody foresaw: every question about it raises."""

    @property
    def transport(self) -> Any:
        raise RuntimeError("writer.transport: broken")

    def __getattr__(self, name: str) -> Any:
        raise RuntimeError(f"writer.{name}: broken")


def test_the_sweep_goes_on_past_a_connection_it_cannot_check(
    lt: LoopThread, tls_server: Callable[..., Tls], caplog: pytest.LogCaptureFixture
) -> None:
    """One bad connection (here: the closed TLS client put back in the pools as if its
    handler had died, and its transport made to fail every call) is logged and skipped;
    every other connection's deadlines still hold, and a stop still works."""
    # a 1 s deadline: closed within 3 s after it; a sweep that stops at the bad connection
    # never closes it (given up after 15 s)
    t = tls_server(auth_timeout_s=1.0)
    zombie = closed_tls_client_known(lt, t)

    def haunt() -> None:
        zombie.closed = False
        zombie.evicted = ""
        zombie.session = False
        zombie.t_connect_s = zombie.t_active_s = t.srv._clock() - 60.0  # long past its deadline
        zombie.writer = _BrokenWriter()
        t.srv._clients.add(zombie)
        t.srv._pending[zombie] = None

    lt.call(haunt)
    with caplog.at_level(logging.ERROR, logger="x6wd.app"):
        for _ in range(2):
            notice, after_s = _closed_within(t, 15.0)
            assert notice["error"]["reason"] == "auth_timeout", notice
            assert after_s < 1.0 + 3.0, after_s
        stopper = TlsRaw(t.srv.port, t.ctx)
        assert stopper.ask({"id": 1, "cmd": "stop"})["ok"]
        stopper.close()
    assert "the sweep goes on" in caplog.text and zombie.peer in caplog.text, caplog.text
    assert "deadline sweep failed" not in caplog.text


# -- the web console over HTTPS/WSS ------------------------------------------------------------
def test_the_consoles_stop_over_wss_reaches_the_motors_while_a_closed_tls_client_is_known(
    lt: LoopThread, tls_server: Callable[..., Tls], caplog: pytest.LogCaptureFixture
) -> None:
    t = tls_server()
    cert, key = t.cert, t.cert.with_name("key.pem")
    console = ConsoleServer(
        ConsoleConfig(enabled=True, port=0, deadman_s=5.0), t.srv, lambda: {},
        ssl_context=server_ssl_context(str(cert), str(key)),
    )  # fmt: skip
    lt.run(console.start())
    url = console.url.replace("https", "wss", 1) + "ws"

    async def page(session: aiohttp.ClientSession) -> Any:
        ws = await session.ws_connect(url, ssl=t.ctx)
        n = 0

        async def ask(cmd: str, **args: Any) -> dict[str, Any]:
            nonlocal n
            n += 1
            await ws.send_json({"id": n, "cmd": cmd, **args})
            while True:
                msg = await asyncio.wait_for(ws.receive_json(), 10)
                if msg.get("id") == n:
                    return msg

        assert (await ask("auth", token=TOKEN))["ok"]
        return ws, ask

    async def program() -> None:
        async with aiohttp.ClientSession() as session:
            ws, ask = await page(session)
            for _ in range(3):
                await asyncio.to_thread(closed_tls_client_known, lt, t)
                reply = await ask("drive", left=40, right=40, duration_s=5)
                assert reply["ok"] and t.backend.motors == (40.0, 40.0), reply
                reply = await ask("stop")  # the STOP button
                assert reply["ok"], reply
                assert t.backend.motors == (0.0, 0.0)
            # the console's dead-man: a page closed while it drives
            await asyncio.to_thread(closed_tls_client_known, lt, t)
            assert (await ask("drive", left=40, right=40, duration_s=5))["ok"]
            await ws.close()
            await asyncio.to_thread(stopped_soon, t.backend)

    try:
        with caplog.at_level(logging.WARNING, logger="x6wd.app"):
            asyncio.run(program())
            wait_until(lambda: console.deadman_stops == 1, 2, "the dead-man counted")
        assert "went away while driving: motors stopped" in caplog.text, caplog.text
        assert "Traceback" not in caplog.text and "internal" not in caplog.text, caplog.text
    finally:
        lt.run(console.close())


# -- the whole daemon, as the audit ran it ------------------------------------------------------
def test_the_daemon_with_tls_stops_its_motors_from_the_client_ctrl_c_and_the_console(
    tmp_path: Path,
) -> None:
    """The audit's reproduction on the real daemon (``sim://`` motors, token, TLS on the
    control port and the console): after a TLS operator has come and gone, `x6wd client
    stop`, the Ctrl-C of `x6wd client drive`, a killed driving client and the console's
    STOP over WSS each leave the vehicle's motors at 0."""
    from tests.test_console import TOKEN as TOKEN_OF_CONSOLE
    from tests.test_console import console_config, daemon_with, vehicle_pct, ws_to
    from x6wd.app.client import RemoteClient

    # The drives last drive_s (safety.manual_max_s raised to allow it), far past stop_bound_s
    # after the stop: a stop that never reaches the motors, or a dead-man that does not stop,
    # leaves them running until the drive's own end and fails however slowly the host started
    # the client (the stop itself is seen well within stop_bound_s even on a loaded host).
    drive_s, stop_bound_s = 60.0, 10.0
    cfg = console_config(tmp_path, token=True, tls=True)
    cfg = dataclasses.replace(cfg, safety=dataclasses.replace(cfg.safety, manual_max_s=drive_s))
    cert = tmp_path / "cert.pem"
    ctx = ssl.create_default_context(cafile=str(cert))
    token_file = tmp_path / "token"

    def cli(r: Any, *args: str) -> list[str]:
        return [
            sys.executable, "-m", "x6wd", "client", "--port", str(r.port), "--cafile",
            str(cert), "--token-file", str(token_file), *args,
        ]  # fmt: skip

    def come_and_go(r: Any) -> None:  # a TLS operator who asked the status and left
        with RemoteClient("127.0.0.1", r.port, ssl_context=ctx, token=TOKEN_OF_CONSOLE) as c:
            c.request("status")
        time.sleep(0.2)

    def driving(r: Any) -> RemoteClient:
        c = RemoteClient("127.0.0.1", r.port, ssl_context=ctx, token=TOKEN_OF_CONSOLE)
        assert c.request("drive", left=40, right=40, duration_s=drive_s)["ok"]
        wait_until(lambda: vehicle_pct(r) == (40.0, 40.0), 10, "driving")
        return c

    def stopped(r: Any, since: float) -> None:
        """The motors at 0 within stop_bound_s of ``since`` (the stop sent, confirmed or the
        client gone), not when the drive_s drive ends (the bug: only then)."""
        left_s = since + stop_bound_s - time.monotonic()
        wait_until(lambda: vehicle_pct(r) == (0.0, 0.0), left_s, "the vehicle's motors at 0")

    with daemon_with(cfg) as r:
        for _ in range(2):
            come_and_go(r)
            with driving(r):
                done = subprocess.run(cli(r, "stop"), capture_output=True, text=True, timeout=30)
                assert done.returncode == 0 and "stop: ok" in done.stdout, done.stderr
                stopped(r, time.monotonic())
        come_and_go(r)
        proc = subprocess.Popen(
            cli(r, "drive", "40", "40", f"{drive_s:g}"), stderr=subprocess.PIPE, text=True,
            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
        )  # fmt: skip
        try:
            wait_until(lambda: vehicle_pct(r) == (40.0, 40.0), 20, "the client's drive")
            proc.send_signal(signal.SIGINT)
            _, stderr = proc.communicate(timeout=10)
        finally:
            proc.kill()
        stopped(r, time.monotonic())
        assert proc.returncode == 130, stderr
        come_and_go(r)
        proc = subprocess.Popen(cli(r, "drive", "40", "40", f"{drive_s:g}"), stderr=subprocess.PIPE)
        try:
            wait_until(lambda: vehicle_pct(r) == (40.0, 40.0), 20, "the client's drive")
            proc.kill()  # the dead-man
            proc.wait(10)
        finally:
            proc.kill()
        stopped(r, time.monotonic())

        async def page() -> None:
            async with ws_to(r, ctx) as w:
                assert (await w.request("auth", token=TOKEN_OF_CONSOLE))["ok"]
                for _ in range(2):
                    await asyncio.to_thread(come_and_go, r)
                    assert (await w.request("drive", left=40, right=40, duration_s=0.5))["ok"]
                    reply = await w.request("stop")
                    assert reply["ok"], reply
                    await asyncio.to_thread(stopped, r, time.monotonic())

        asyncio.run(page())
        assert r.daemon.server is not None
        stops = r.daemon.server.server_stats()["stops"]
        assert stops["orphaned"] == 1, stops
