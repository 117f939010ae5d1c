"""Safety and security behaviours an outside audit (round 14) removed one at a time without
failing any test (tools/hand-mutations, docs/testing.md "Safety mutations"): each test here
fails with its behaviour removed.

- the systemd watchdog is fed only while every worker thread lives (``dae-wd-alive``);
- a console WebSocket message over ``max_message_bytes`` is refused by its declared length,
  before its payload is buffered (``con-msg-size``);
- the estimate is checked against the geofence after every usable fix (``geo-est-after``);
- a ``start``, ``resume`` or ``return`` received before a ``stop`` is never carried out
  after it (``srv-superseded-*``);
- with the control loop stalled the keep-alive stops the wheels within about the board's
  watchdog, resending no slower than it meanwhile (``mot-keepalive-rate``);
- ``navigation.turn_pct`` over 100 is a configuration error, exit 2 (``cfg-turn-max``);
- the control port refuses TLS 1.0 and 1.1, whatever the ciphers allow (``tls-min-version``).

Real parts: the daemon on its loop thread, the control and console servers on 127.0.0.1
(the console pair on ports 43400-43499, the others on free ports), real TLS sockets, the
runner with the robot's controller (EKF), the ``x6wd run`` process.
"""

from __future__ import annotations

import itertools
import json
import math
import socket
import ssl
import struct
import subprocess
import sys
import threading
import time
import warnings
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from tests.conftest import self_signed_cert
from tests.test_console_flood_round8 import close_frame, connect, reply_to, ws_send
from tests.test_daemon import run_daemon, wait_for
from tests.test_geofence_wild_fix import HOME, M_PER_DEG_LAT, M_PER_DEG_LON, STEP_S, Robot
from tests.test_lockout import lt
from tests.test_network_round6 import ws_upgrade
from tests.test_safety_daemon import BlockableDaemon, notices, notify_socket
from tests.test_safety_server import _calls_after_first_stop, _replies_until, line
from tests.test_server import TOKEN, LoopThread, Raw, RecordingBackend, start_server
from tests.test_shutdown import StampedLink, log_motors_config, stamped
from x6wd.app.client import RemoteClient
from x6wd.app.console.server import ConsoleServer
from x6wd.app.daemon import Daemon
from x6wd.app.notify import Notifier
from x6wd.app.server import ControlServer, server_ssl_context
from x6wd.core.config import ConsoleConfig, SafetyConfig, ServerConfig, loads
from x6wd.core.errors import ConfigError
from x6wd.core.geodesy import great_circle_m
from x6wd.core.mission_files import Waypoint
from x6wd.core.records import Attitude, Mode, WheelOdometry

__all__ = ["lt", "run_daemon", "stamped"]  # fixtures, shared with their test files

PORTS = iter(range(43400, 43500))


# -- the systemd watchdog: fed only while every worker thread lives -----------------------------
class _Returned(Exception):
    """Raised inside the GPS thread's poll to make the thread return (not a failure)."""


class ReturningGpsDaemon(Daemon):
    """Fault injection: once ``armed`` is set, the GPS thread simply returns (a reader loop
    that ends by mistake: no exception reaches the thread's guard, nothing fails)."""

    def __init__(self, *args: Any, **kw: Any) -> None:
        super().__init__(*args, **kw)
        self.armed = threading.Event()

    def _gps_thread(self) -> None:
        reader = self._gps_reader
        poll = reader.poll

        def armed_poll(timeout_s: float) -> Any:
            if self.armed.is_set():
                raise _Returned
            return poll(timeout_s)

        reader.poll = armed_poll
        try:
            super()._gps_thread()
        except _Returned:
            return


def _watchdog_pings(sock: socket.socket, n: int) -> None:
    pings = 0
    for msg in notices(sock):
        pings += msg.get("WATCHDOG") == "1"
        if pings >= n:
            return


def test_a_worker_thread_that_returns_stops_the_systemd_watchdog_feed(
    tmp_path: Path, run_daemon
) -> None:
    """The GPS thread returns (no exception: nothing fails): the loop still turns, but from
    then on no WATCHDOG=1 goes to systemd, which kills and restarts the daemon after
    WatchdogSec. Fed every 0.1 s before."""
    sock, _ = notify_socket(tmp_path)
    notifier = Notifier(str(tmp_path / "notify.sock"), watchdog_usec=200_000)  # every 0.1 s
    d = ReturningGpsDaemon(log_motors_config(tmp_path), notifier=notifier)
    r = run_daemon(d)
    try:
        _watchdog_pings(sock, 3)  # fed while all live
        gps = next(t for t in d._threads if t.name == "x6wd-gps")
        d.armed.set()
        gps.join(5)
        assert not gps.is_alive()
        assert r.thread.is_alive()  # the daemon runs on: only the watchdog can see it
        time.sleep(0.15)  # a feed already under way
        sock.settimeout(0.0)
        while True:  # drain what came before the thread ended
            try:
                sock.recv(4096)
            except BlockingIOError:
                break
        sock.settimeout(0.1)
        deadline = time.monotonic() + 1.0  # 10 feed periods
        while time.monotonic() < deadline:
            try:
                data = sock.recv(4096).decode()
            except TimeoutError:
                continue
            assert "WATCHDOG=1" not in data.split("\n"), "fed with a dead worker thread"
    finally:
        r.loop.call_soon_threadsafe(r.daemon.request_stop)
        r.thread.join(10)
        sock.close()


# -- the console: a message over max_message_bytes refused before it is buffered ----------------
@pytest.fixture
def console(lt: LoopThread) -> Iterator[ConsoleServer]:
    srv = ControlServer(ServerConfig(port=next(PORTS)), RecordingBackend(), token=TOKEN.encode())
    lt.run(srv.start())
    con = ConsoleServer(ConsoleConfig(enabled=True, port=next(PORTS)), srv, dict)
    lt.run(con.start())
    yield con
    lt.run(con.close())
    lt.run(srv.close())


def test_a_page_message_over_max_message_bytes_is_refused_by_its_declared_length(
    console: ConsoleServer,
) -> None:
    """After ``auth``, a frame declaring ``max_message_bytes`` + 1 (1 MiB + 1) with only
    4 KB of it sent: the page is closed with 1009 at once, before the rest arrives (the
    WebSocket's own limit; without it aiohttp would wait for, and buffer, any size)."""
    limit = console.config.max_message_bytes
    s = ws_upgrade(connect(console.port), console.port)
    try:
        ws_send(s, {"id": 1, "cmd": "auth", "token": TOKEN})
        assert reply_to(s, 1)["ok"]
        t0 = time.monotonic()
        head = struct.pack("!BBQ", 0x81, 0x80 | 127, limit + 1) + bytes(4)  # zero mask
        s.sendall(head + b'{"id": 2, "cmd": "hello", "pad": "' + b"x" * 4000)
        s.settimeout(5)
        code, _reason = close_frame(s, 2)
        assert code == 1009 and time.monotonic() - t0 < 3.0
    finally:
        s.close()


# -- the geofence: the estimate after every usable fix -----------------------------------------
def test_the_estimate_is_checked_against_the_geofence_after_every_usable_fix() -> None:
    """The fence's edge runs 3 m east of the start; the robot rolls out on 20 deg (wheels
    and compass agree) while from 4 s the fixes come 25 m west of it: inside the fence,
    usable (HDOP 1.2, every second) and refused by the EKF as a jump. The estimate the
    controller steers by, dead-reckoned on the wheels, crosses the edge: the fix after
    that is a breach on the estimate, motors stopped first. Without the check after a fix,
    the fresh fixes kept the estimate from being checked at all, and the robot drove on
    until the EKF moved to the fixes ("position jumped")."""
    heading_deg, edge_east_m, radius_m = 20.0, 3.0, 500.0
    centre = (HOME[0] + 10.0 / M_PER_DEG_LAT, HOME[1] + (edge_east_m - radius_m) / M_PER_DEG_LON)
    bot = Robot(SafetyConfig(geofence_radius_m=radius_m, geofence_center=centre))
    east_m = travelled_m = 0.0
    sent_before_fix = 0  # motor commands sent before the latest fix

    def step(speed_mps: float, wild_from_s: float = math.inf) -> None:
        nonlocal east_m, travelled_m, sent_before_fix
        bot.now = round(bot.now + STEP_S, 6)
        bot.north_m += speed_mps * STEP_S * math.cos(math.radians(heading_deg))
        east_m += speed_mps * STEP_S * math.sin(math.radians(heading_deg))
        travelled_m += speed_mps * STEP_S
        counts = round(travelled_m / bot.m_per_count)
        bot.runner.odometry(WheelOdometry(bot.now, counts, counts, 0))
        bot.runner.attitude(Attitude(bot.now, heading_deg, 0.0, 0.0))
        if abs(bot.now - round(bot.now)) < 1e-9:
            sent_before_fix = len(bot.motors)
            bot.fix(bot.north_m, east_m - (25.0 if bot.now >= wild_from_s else 0.0))

    bot.fix(0.0)
    for _ in range(round(3.0 / STEP_S)):
        step(0.0)
    bot.runner.load_mission([Waypoint(HOME[0] + 30.0 / M_PER_DEG_LAT, HOME[1])])
    bot.runner.command("start")
    t_start, refused = bot.now, bot.ekf_refused()
    for _ in range(round(15.0 / STEP_S)):
        step(1.0, wild_from_s=t_start + 4.0)
        if bot.runner.controller.mode != Mode.RUNNING:
            break
    assert bot.runner.controller.mode == Mode.PAUSED, bot.states
    why = "geofence breach (estimated position)"
    assert [s.reason for s in bot.states if s.reason.startswith("mode:")][-1] == (
        f"mode: failsafe: {why}"
    )
    assert bot.runner.geofence_breaches == 1
    assert abs(bot.now - round(bot.now)) < 1e-9  # at a fix, not between fixes
    assert bot.ekf_refused() > refused  # the premise: the EKF refused the fixes
    tel = bot.runner.controller.telemetry
    assert tel.filt_lat_deg is not None and tel.filt_lon_deg is not None
    assert great_circle_m(*centre, tel.filt_lat_deg, tel.filt_lon_deg) > radius_m
    after = bot.motors[sent_before_fix:]  # the fix's step: its drive replaced by the stop
    assert after and after[0].is_stop and after[0].reason == why
    assert all(m.is_stop for m in after)
    assert bot.now - t_start < 11.0  # crossed at ~8.8 s; the EKF gave up on its estimate later


# -- the control port: a stop cancels a start, resume or return queued before it --------------
@pytest.mark.parametrize(("cmd", "call"), [("start", "start"), ("resume", "resume"),
                                           ("return", "return")])  # fmt: skip
def test_a_backlog_of_motion_commands_is_not_carried_out_after_the_stop_behind_it(
    lt: LoopThread, cmd: str, call: str
) -> None:
    """docs/protocol.md: a ``drive``, ``start``, ``resume`` or ``return`` received before a
    stop is refused (``stopped``) when its turn comes. A burst of one of them held back by the
    throttle, then ``stop``: none of the burst reaches the robot after the stop."""
    backend = RecordingBackend()
    srv = start_server(lt, backend, rate_per_s=50.0)  # port 0: any free one
    raw = Raw(srv.port)
    try:
        burst = b"".join(line({"id": i, "cmd": cmd}) for i in range(150))
        raw.send(burst + line({"id": "s", "cmd": "stop"}) + line({"id": "after", "cmd": "hello"}))
        replies = _replies_until(raw, "after")
        assert replies["s"]["ok"]
        later = [n for n, _ in _calls_after_first_stop(backend)]
        assert call not in later, later[:5]
        stopped = [r for r in replies.values() if r.get("error", {}).get("reason") == "stopped"]
        assert stopped and srv.stops["superseded"] == len(stopped)
        assert {r["error"]["code"] for r in stopped} == {"rejected"}
        assert any(n == call for n, _ in backend.calls)  # the premise: some ran before
    finally:
        raw.close()
        lt.run(srv.close())


# -- the motor keep-alive: a stalled control loop stops the wheels within the board's watchdog --
def test_with_the_control_loop_stalled_the_keepalive_stops_within_the_boards_watchdog(
    tmp_path: Path, run_daemon, stamped: StampedLink
) -> None:
    """[motors] watchdog_ms = 500 (the default): while the loop is stuck the keep-alive
    resends the drive at least every 0.5 s (the board would stop and jerk between), and its
    own stop comes within about that watchdog after the loop's last command (3 keep-alives
    per period, the stop after 3 silent ones), not seconds later."""
    cfg = log_motors_config(tmp_path)
    assert cfg.motors.watchdog_ms == 500
    d = BlockableDaemon(cfg)
    r = run_daemon(d)
    with RemoteClient("127.0.0.1", r.port) as owner:  # open: its drive holds while it lives
        owner.request("drive", left=40, right=40, duration_s=5)
        wait_for(lambda: stamped.driving(40.0, 40.0), 3, "motors driven")
        d.blocking.set()
        assert d.blocked.wait(5)  # the control loop is stuck from here on
        t_block = time.monotonic()
        wait_for(lambda: stamped.first_stop_after(t_block), 5.0, "the keep-alive's stop")
        t_stop = stamped.first_stop_after(t_block)
        assert t_stop is not None
        stop = next(c for t, c in stamped.stamped if t == t_stop)
        times = [t for t, _c in stamped.stamped if t <= t_stop]
        d.release.set()
    assert stop.reason == "keepalive"
    assert t_stop - t_block < 1.0, t_stop - t_block  # 3 s with one keep-alive a watchdog
    gaps = [b - a for a, b in itertools.pairwise(times) if b >= t_block]
    assert gaps and max(gaps) < 0.5, gaps  # the board's watchdog never ran out meanwhile


# -- the configuration: navigation.turn_pct at most 100 -----------------------------------------
@pytest.mark.parametrize("key", ["cruise_pct", "turn_pct"])
def test_a_navigation_drive_over_100_percent_is_refused_naming_the_key(key: str) -> None:
    with pytest.raises(ConfigError) as ei:
        loads(f"[navigation]\n{key} = {math.nextafter(100.0, math.inf)!r}\n")
    assert str(ei.value).startswith(f"navigation.{key}: must be <= 100"), str(ei.value)
    assert getattr(loads(f"[navigation]\n{key} = 100.0\n").navigation, key) == 100.0


def test_turn_pct_150_stops_x6wd_run_with_exit_2_naming_the_key(tmp_path: Path) -> None:
    cfg = tmp_path / "x6wd.toml"
    cfg.write_text('[gps]\nurl = "sim://"\n[navigation]\nturn_pct = 150\n')
    done = subprocess.run([sys.executable, "-m", "x6wd", "run", "--config", str(cfg)],
                          capture_output=True, text=True, timeout=60)  # fmt: skip
    assert done.returncode == 2, done.stderr
    assert "navigation.turn_pct: must be <= 100" in done.stderr
    assert "Traceback" not in done.stderr


# -- TLS: the control port refuses TLS 1.0 and 1.1 ---------------------------------------------
def _client_context(version: ssl.TLSVersion) -> ssl.SSLContext:
    """A client that offers ``version`` only, at OpenSSL security level 0 (so that its own
    library does not refuse the old protocol first), trusting any certificate."""
    ctx = ssl.SSLContext(ssl.PROTOCOL_TLS_CLIENT)
    ctx.check_hostname = False
    ctx.verify_mode = ssl.CERT_NONE
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        ctx.minimum_version = ctx.maximum_version = version
    ctx.set_ciphers("DEFAULT:@SECLEVEL=0")
    return ctx


@pytest.fixture(scope="module")
def cert_and_key(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    return self_signed_cert(tmp_path_factory.mktemp("tls"))


def test_the_control_port_refuses_tls_1_0_and_1_1_whatever_the_ciphers_allow(
    lt: LoopThread, cert_and_key: tuple[Path, Path]
) -> None:
    """The server's context (``server_ssl_context``, as the daemon builds it) has TLS 1.2 as
    its minimum. Its cipher list then lowered to OpenSSL security level 0, as an
    ``openssl.cnf`` may set it (Debian's default level 2 refuses TLS 1.0/1.1 by their
    ciphers alone, hiding a lost minimum): a client offering only TLS 1.1 or 1.0 is still
    refused by the real control port, TLS 1.2 is served."""
    cert, key = (str(p) for p in cert_and_key)
    ctx = server_ssl_context(cert, key)
    assert ctx.minimum_version == ssl.TLSVersion.TLSv1_2
    ctx.set_ciphers("DEFAULT:@SECLEVEL=0")
    srv = start_server(lt, RecordingBackend(), ssl_context=ctx)  # port 0: any free one
    try:
        for old in ("TLSv1", "TLSv1_1"):
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", DeprecationWarning)
                version = getattr(ssl.TLSVersion, old)
            raw = socket.create_connection(("127.0.0.1", srv.port), timeout=5)
            try:
                with pytest.raises(OSError):  # ssl.SSLError: EOF or the protocol alert
                    _client_context(version).wrap_socket(raw, server_hostname="127.0.0.1")
            finally:
                raw.close()
        raw = socket.create_connection(("127.0.0.1", srv.port), timeout=5)
        with _client_context(ssl.TLSVersion.TLSv1_2).wrap_socket(
            raw, server_hostname="127.0.0.1"
        ) as tls:
            assert tls.version() == "TLSv1.2"
            tls.sendall(line({"id": 1, "cmd": "hello"}))
            reply = json.loads(tls.makefile("rb").readline())
            assert reply["ok"] and reply["id"] == 1
    finally:
        lt.run(srv.close())


# -- the controller: a dead encoder pauses the mission -----------------------------------------
def test_a_dead_left_encoder_pauses_the_mission_naming_the_encoders() -> None:
    """The robot's controller (EKF) on a scripted robot rolling straight north, wheels,
    compass and fixes agreeing; 10 s into the mission the left encoder stops counting. The
    compass turns 0 deg while the wheels say a turn: paused within seconds, named, motors
    stopped (only a whole fast-time mission in tests/test_robot_variations_round5.py
    noticed the pause taken out)."""
    bot = Robot()
    bot.fix(0.0)
    bot.roll(3.0, 0.0)
    bot.runner.load_mission([Waypoint(HOME[0] + 95.0 / M_PER_DEG_LAT, HOME[1])])
    bot.runner.command("start")
    bot.roll(10.0, 1.0)
    t_dead, left_dead = bot.now, round(bot.north_m / bot.m_per_count)
    while bot.runner.controller.mode == Mode.RUNNING and bot.now - t_dead < 10.0:
        bot.now = round(bot.now + STEP_S, 6)
        bot.north_m += STEP_S
        right = round(bot.north_m / bot.m_per_count)
        bot.runner.odometry(WheelOdometry(bot.now, left_dead, right, 0))
        bot.runner.attitude(Attitude(bot.now, 0.0, 0.0, 0.0))
        if abs(bot.now - round(bot.now)) < 1e-9:
            bot.fix(bot.north_m)
    assert bot.runner.controller.mode == Mode.PAUSED, bot.states[-3:]
    assert bot.now - t_dead < 5.0  # 2.6 s, 1.5 m of the right wheel alone
    why = next(s.reason for s in bot.states if s.reason.startswith("mode: failsafe:"))
    assert why.startswith("mode: failsafe: encoders disagree with the compass: left counted 0"), why
    assert bot.motors[-1].is_stop
