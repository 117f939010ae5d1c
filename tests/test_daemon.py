"""The daemon with real devices: the HIL world (pty GPS, register-map compass, simulated
vehicle), a real motor board behind a pty, real sockets and a real sd_notify socket."""

from __future__ import annotations

import asyncio
import dataclasses
import gc
import itertools
import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
import tty
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

from x6wd.app.client import RemoteClient, RequestFailed
from x6wd.app.daemon import Daemon, distance_m
from x6wd.core.config import (
    Config,
    GpsdConfig,
    MotorsConfig,
    RecorderConfig,
    SafetyConfig,
    ServerConfig,
    SimConfig,
)
from x6wd.core.errors import ConfigError
from x6wd.core.records import Attitude, MotorCommand

ORIGIN = (51.7520, -1.2577)


def hil_config(tmp_path: Path, **sections: Any) -> Config:
    base = Config(
        server=ServerConfig(port=0),
        gpsd=GpsdConfig(port=0),
        recorder=RecorderConfig(dir=str(tmp_path / "rec")),
        sim=SimConfig(gps_rate_hz=4.0, gps_baud=115200),
        safety=SafetyConfig(geofence_radius_m=100.0),
    )
    cfg = dataclasses.replace(
        base,
        gps=dataclasses.replace(base.gps, url="sim://"),
        compass=dataclasses.replace(base.compass, url="sim://"),
        motors=dataclasses.replace(base.motors, url="sim://"),
    )
    return dataclasses.replace(cfg, **sections)


class Running:
    """A Daemon on its own event-loop thread."""

    def __init__(self, daemon: Daemon, ready_s: float = 15.0) -> None:
        self.daemon = daemon
        self.ready = threading.Event()
        self.code: int | None = None
        self.thread = threading.Thread(target=self._main, daemon=True)
        self.thread.start()
        assert self.ready.wait(ready_s), "daemon did not become ready"

    def _main(self) -> None:
        async def go() -> int:
            self.loop = asyncio.get_running_loop()
            return await self.daemon.run(ready=lambda _d: self.ready.set())

        self.code = asyncio.run(go())
        self.ready.set()

    @property
    def port(self) -> int:
        assert self.daemon.server is not None
        return self.daemon.server.port

    def stop(self) -> int | None:
        if self.thread.is_alive():
            self.loop.call_soon_threadsafe(self.daemon.request_stop)
            self.thread.join(15)
        return self.code


@pytest.fixture
def run_daemon(request: pytest.FixtureRequest) -> Iterator[Callable[[Daemon], Running]]:
    """Starts daemons (each a :class:`Running`) and stops them after the test. A module that
    imports it may allow its daemons longer to become ready with ``DAEMON_READY_S``."""
    started: list[Running] = []
    ready_s = float(getattr(request.module, "DAEMON_READY_S", 15.0))

    def start(d: Daemon) -> Running:
        r = Running(d, ready_s)
        started.append(r)
        return r

    yield start
    for r in started:
        r.stop()
        if r.daemon.devices is not None:
            r.daemon.devices.close()  # also when the daemon did not get to close it


def wait_for(
    pred: Callable[[], Any], timeout_s: float = 10.0, what: str = "", poll_s: float = 0.05
) -> Any:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        v = pred()
        if v:
            return v
        time.sleep(poll_s)
    raise AssertionError(f"timed out waiting for {what or pred}")


def status(c: RemoteClient) -> dict[str, Any]:
    return c.request("status")


def test_dead_man_expiry_stops_the_motors(tmp_path: Path, run_daemon) -> None:
    r = run_daemon(Daemon(hil_config(tmp_path)))
    world = r.daemon.devices.backend("sim")  # the world the daemon's sim:// devices share
    with RemoteClient("127.0.0.1", r.port) as c:
        wait_for(
            lambda: status(c)["telemetry"] and status(c)["telemetry"]["fix_quality"], what="fix"
        )
        c.request("drive", left=50, right=50, duration_s=0.6)
        wait_for(lambda: world.vehicle.command_pct == (50.0, 50.0), 3, "drive reaches vehicle")
        assert status(c)["mode"] == "MANUAL"
        wait_for(lambda: status(c)["mode"] == "IDLE", 5, "dead-man expiry")
        wait_for(lambda: world.vehicle.command_pct == (0.0, 0.0), 3, "motors stopped")
        with pytest.raises(RequestFailed) as ei:
            c.request("drive", left=10, right=10, duration_s=60)  # over safety.manual_max_s
        assert ei.value.code == "bad_request"
    assert r.stop() == 0


def test_geofence_from_first_fix_and_from_configured_centre(tmp_path: Path, run_daemon) -> None:
    r = run_daemon(Daemon(hil_config(tmp_path)))
    with RemoteClient("127.0.0.1", r.port) as c:
        wait_for(lambda: r.daemon.first_fix, what="first fix")
        far = [ORIGIN[0] + 0.01, ORIGIN[1]]  # ~1.1 km north, limit 100 m
        with pytest.raises(RequestFailed) as ei:
            c.request("mission.load", waypoints=[[ORIGIN[0] + 0.0002, ORIGIN[1]], far])
        assert ei.value.code == "geofence" and "waypoint 2" in ei.value.message
        assert c.request("mission.load", waypoints=[[ORIGIN[0] + 0.0002, ORIGIN[1]]])["count"] == 1
    r.stop()
    centre = SafetyConfig(geofence_radius_m=100.0, geofence_center=(ORIGIN[0] + 0.01, ORIGIN[1]))
    r2 = run_daemon(Daemon(hil_config(tmp_path, safety=centre)))
    with RemoteClient("127.0.0.1", r2.port) as c:
        # the configured centre applies even before a fix
        assert c.request("mission.load", waypoints=[far])["count"] == 1
        with pytest.raises(RequestFailed):
            c.request("mission.load", waypoints=[list(ORIGIN)])


class BoardOnPty:
    """A motor board (drivers.motors.MotorBoard) served on a pseudo-terminal: ``url`` for
    [motors]; :meth:`serve` and :meth:`halt` start and stop its answering (a board that
    dies and comes back); the context closes the pty, the server thread joined first (a live
    one would read whatever next reuses the fd number)."""

    def __init__(self, watchdog_ms: int = 500) -> None:
        from drivers.motors import MotorBoard

        self.master, self.slave = os.openpty()
        tty.setraw(self.master)
        tty.setraw(self.slave)
        self.board = MotorBoard(watchdog_ms=watchdog_ms)
        self.url = f"serial://{os.ttyname(self.slave)}"
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def serve(self) -> None:
        from drivers.motors import serve_board_fd

        self._stop = threading.Event()
        args = (self.master, self.board, self._stop)
        self._thread = threading.Thread(target=serve_board_fd, args=args, daemon=True)
        self._thread.start()

    def halt(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(5)

    def __enter__(self) -> BoardOnPty:
        self.serve()
        return self

    def __exit__(self, *exc: object) -> None:
        self.halt()
        os.close(self.master)
        os.close(self.slave)


def test_lost_motor_link_holds_the_mission(tmp_path: Path, run_daemon) -> None:
    cfg = hil_config(tmp_path)
    with BoardOnPty() as pb:
        cfg = dataclasses.replace(cfg, motors=dataclasses.replace(cfg.motors, url=pb.url))
        r = run_daemon(Daemon(cfg))
        with RemoteClient("127.0.0.1", r.port) as c:
            wait_for(lambda: r.daemon.first_fix, what="first fix")
            c.request("mission.load", waypoints=[[ORIGIN[0] + 0.0005, ORIGIN[1]]])
            c.request("start")
            wait_for(lambda: pb.board.running, 5, "board driven")
            pb.halt()  # the board dies: no more acknowledgements
            tel = wait_for(
                lambda: (t := status(c)["telemetry"]) and t["state"] == "HOLD" and t,
                10,
                "HOLD on lost link",
            )
            assert tel["hold_reason"] == "motor link lost"
            assert (tel["left_pct"], tel["right_pct"]) == (0.0, 0.0)
            assert status(c)["links"]["motors"] == "lost"
        # the dead board cannot acknowledge the stop at exit: said, and the exit is 1
        assert r.stop() == 1


def test_the_configured_watchdog_reaches_the_motor_board(tmp_path: Path, run_daemon) -> None:
    # Found by an outside check: [motors] watchdog_ms only set the daemon's keep-alive; the
    # board was always sent W 500 (the URL option's default), so an owner's 100 ms (a faster
    # stop on a lost link) was 500 ms on the board
    with BoardOnPty() as pb:
        motors = MotorsConfig(url=pb.url, watchdog_ms=2000)
        r = run_daemon(Daemon(dataclasses.replace(hil_config(tmp_path), motors=motors)))
        wait_for(lambda: pb.board.watchdog_ms == 2000, 5, "W 2000 on the board")
        assert r.stop() == 0


def test_in_hil_the_configured_watchdog_reaches_the_simulated_board(
    tmp_path: Path, run_daemon
) -> None:
    # a second outside check: with sim:// motors the driver sent [sim] motor_watchdog_ms and
    # [motors] watchdog_ms was silently ignored (HIL runs the real daemon)
    cfg = hil_config(tmp_path)
    r = run_daemon(Daemon(dataclasses.replace(cfg, motors=MotorsConfig("sim://", 2000))))
    board = r.daemon.devices.backend("sim").board
    wait_for(lambda: board.watchdog_ms == 2000, 5, "W 2000 on the simulated board")
    assert r.stop() == 0


class FaultyDaemon(Daemon):
    """Fault injection: the 10th compass sample hits a bug."""

    def _on_attitude(self, att: Attitude) -> None:
        if self.stats["attitudes"] >= 10:
            raise RuntimeError("injected bug")
        super()._on_attitude(att)


def test_unexpected_exception_stops_motors_and_exits_non_zero(tmp_path: Path, run_daemon) -> None:
    d = FaultyDaemon(hil_config(tmp_path))
    r = run_daemon(d)
    world = d.devices.backend("sim")
    r.thread.join(15)
    assert r.code == 1
    assert world.vehicle.command_pct == (0.0, 0.0)
    assert d.motors is not None and d.motors.link.last_command.is_stop


def run_to_exit(daemon: Daemon, timeout_s: float = 30.0) -> int:
    """Run ``daemon`` in this thread to its exit code, for cases that must end by themselves
    (a refused start): bounded, so a daemon that ran on fails here, not at the suite timeout."""
    return asyncio.run(asyncio.wait_for(daemon.run(), timeout_s))


def test_bad_geofence_centre_is_a_startup_error(tmp_path: Path) -> None:
    cfg_path = tmp_path / "bad.toml"  # the file the daemon is started with: exit 2, named
    cfg_path.write_text('[gps]\nurl = "sim://"\n[safety]\ngeofence_center = [1.0]\n')
    done = subprocess.run([sys.executable, "-m", "x6wd", "run", "--config", str(cfg_path)],
                          capture_output=True, text=True, timeout=60)  # fmt: skip
    assert done.returncode == 2, done.stderr
    assert "safety.geofence_center: expected [] or [lat_deg, lon_deg], got [1]" in done.stderr
    with pytest.raises(ConfigError, match=r"safety\.geofence_center"):
        SafetyConfig(geofence_center=(1.0,))  # the config itself refuses it


def test_distance() -> None:
    # one degree of latitude is about 111.2 km on the mean sphere
    assert distance_m(0.0, 0.0, 1.0, 0.0) == pytest.approx(111_195, rel=1e-4)
    assert distance_m(51.0, 10.0, 51.0, 10.0) == 0.0


# -- the real process: sd_notify, signals, recorder ------------------------------------------


def write_config(tmp_path: Path, **server: Any) -> Path:
    server_lines = "\n".join(f"{k} = {json.dumps(v)}" for k, v in server.items())
    text = f"""
[gps]
url = "sim://"
[compass]
url = "sim://"
[motors]
url = "sim://"
[server]
port = 0
{server_lines}
[gpsd]
port = 0
[recorder]
dir = "{tmp_path / "rec"}"
[sim]
gps_rate_hz = 4.0
gps_baud = 115200
"""
    p = tmp_path / "x6wd.toml"
    p.write_text(text)
    return p


def daemon_cmd(config: Path) -> list[str]:
    return [sys.executable, "-m", "x6wd", "run", "--config", str(config)]


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_process_notifies_systemd_and_exits_cleanly_on_signal(tmp_path: Path, sig: int) -> None:
    sock_path = tmp_path / "notify.sock"
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(str(sock_path))
    sock.settimeout(15)
    env = {**os.environ, "NOTIFY_SOCKET": str(sock_path), "WATCHDOG_USEC": "200000"}
    proc = subprocess.Popen(
        daemon_cmd(write_config(tmp_path)), env=env, stderr=subprocess.PIPE, text=True
    )
    try:
        msgs: list[dict[str, str]] = []

        def recv() -> dict[str, str]:
            data = sock.recv(4096).decode()
            m = dict(line.split("=", 1) for line in data.split("\n"))
            msgs.append(m)
            return m

        first = recv()
        assert first["READY"] == "1" and first["MAINPID"] == str(proc.pid)
        watchdogs = 0
        while watchdogs < 10:  # about 1 s: a few GPS epochs reach the recorder
            watchdogs += recv().get("WATCHDOG") == "1"
        proc.send_signal(sig)
        while "STOPPING" not in recv():
            pass
        assert proc.wait(15) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        sock.close()
    err = proc.stderr.read() if proc.stderr else ""
    assert "x6wd stopped" in err
    (rec,) = (tmp_path / "rec").glob("*.jsonl")
    types = {json.loads(line)["type"] for line in rec.read_text().splitlines()}
    assert {"fix", "nmea", "attitude", "telemetry"} <= types


def test_group_readable_token_file_is_a_clear_startup_error(tmp_path: Path) -> None:
    token = tmp_path / "token"
    token.write_text("0123456789abcdef")
    token.chmod(0o644)
    proc = subprocess.run(
        daemon_cmd(write_config(tmp_path, token_file=str(token))),
        capture_output=True,
        text=True,
        timeout=30,
    )
    assert proc.returncode == 2
    assert "token_file" in proc.stderr and "chmod 600" in proc.stderr


def test_motor_keepalive_stops_when_the_control_loop_goes_silent() -> None:
    from drivers.motors import LogMotorLink
    from x6wd.app.daemon import _MotorWorker

    link = LogMotorLink()
    worker = _MotorWorker(link, keepalive_s=0.02, on_health=lambda ok, t: None)
    worker.start()
    try:
        worker.submit(MotorCommand(time.monotonic(), 50.0, 50.0, "drive"))
        # fresh command: re-sent as keep-alive for a while, then silence means stop
        wait_for(lambda: link.last_command is not None and link.last_command.is_stop, 3, "stop")
        sent = list(link.commands)
        assert sent[0].left_pct == 50.0 and sum(c.left_pct == 50.0 for c in sent) >= 2
        assert sent[-1].reason == "keepalive"
    finally:
        worker.shutdown("test end")
    assert link.commands[-1].is_stop


class ThreadWatch(Daemon):
    """Notes which thread runs each controller input and whether it holds the control lock,
    and which thread sends each motor command."""

    def __init__(self, config: Config) -> None:
        super().__init__(config)
        self.calls: list[tuple[str, str, bool]] = []  # (input, thread, lock held)
        self.sends: list[tuple[str, MotorCommand]] = []

    def _held(self) -> bool:
        # an RLock held by the calling thread can be taken again without blocking; one held
        # elsewhere cannot: so this tells "mine" from "free" only with _is_owned
        return bool(self._control_lock._is_owned())  # type: ignore[attr-defined]

    def _on_gps_records(self, records: list[Any]) -> None:
        self.calls.append(("gps", threading.current_thread().name, self._held()))
        super()._on_gps_records(records)

    def _on_attitude(self, att: Attitude) -> None:
        self.calls.append(("attitude", threading.current_thread().name, self._held()))
        super()._on_attitude(att)


def test_fixes_are_decided_and_sent_on_the_gps_thread_under_the_control_lock(
    tmp_path: Path, run_daemon
) -> None:
    d = ThreadWatch(hil_config(tmp_path))
    r = run_daemon(d)
    assert d.motors is not None
    send = d.motors._send

    def watched(cmd: MotorCommand) -> None:
        d.sends.append((threading.current_thread().name, cmd))
        send(cmd)

    d.motors._send = watched  # type: ignore[method-assign]
    wait_for(lambda: sum(k == "gps" for k, _t, _h in d.calls) >= 4, 20, "four GPS inputs")
    wait_for(lambda: any(t == "x6wd-gps" for t, _c in d.sends), 5, "a send on the GPS thread")
    calls = list(d.calls)
    assert {t for k, t, _h in calls if k == "gps"} == {"x6wd-gps"}
    assert {t for k, t, _h in calls if k == "attitude"} - {"x6wd-gps"}  # on the event loop
    assert all(held for _k, _t, held in calls)  # every controller input under the lock
    # counted after the send returns, so a moment after the watch above has seen it
    wait_for(lambda: d.motors is not None and d.motors.direct_sent >= 1, 5, "a direct send")
    assert d.gc_pacer is not None  # it collects after a fix's send, in the same thread
    wait_for(lambda: d.gc_pacer.collections >= 1, 5, "a paced collection")
    if sys.platform == "linux":  # the network thread yields the processor to the others
        assert d._net is not None and d._net.thread.native_id is not None
        net_nice = os.getpriority(os.PRIO_PROCESS, d._net.thread.native_id)
        assert net_nice > os.getpriority(os.PRIO_PROCESS, threading.get_native_id()) or (
            net_nice == 19
        )
    assert not gc.isenabled()  # paced while running
    assert r.stop() == 0
    assert gc.isenabled()  # given back at exit


class BlockingLink:
    """A motor link whose sends of a drive wait for ``release``; stops go through."""

    def __init__(self) -> None:
        self.healthy = True
        self.sent: list[tuple[str, MotorCommand]] = []
        self.sending = threading.Event()
        self.release = threading.Event()
        self.stops: list[str] = []

    def send(self, cmd: MotorCommand) -> bool:
        if not cmd.is_stop and cmd.reason == "slow":
            self.sending.set()
            self.release.wait(5)
        self.sent.append((threading.current_thread().name, cmd))
        return True

    def stop(self, reason: str = "") -> bool:
        self.stops.append(reason)
        return True

    def close(self) -> None:
        pass


def test_send_now_sends_in_the_callers_thread_when_idle_else_queues() -> None:
    from x6wd.app.daemon import _MotorWorker

    link = BlockingLink()
    w = _MotorWorker(link, keepalive_s=5.0, on_health=lambda ok, t: None)
    w.start()
    try:
        me = threading.current_thread().name
        assert w.send_now(MotorCommand(time.monotonic(), 10.0, 10.0, "fix")) is True
        assert link.sent[-1][0] == me and w.direct_sent == 1 and w.idle
        w.submit(MotorCommand(time.monotonic(), 20.0, 20.0, "slow"))  # the worker is busy
        assert link.sending.wait(2)
        assert w.send_now(MotorCommand(time.monotonic(), 30.0, 30.0, "fix")) is False  # queued
        link.release.set()
        wait_for(lambda: link.sent[-1][1].left_pct == 30.0, 3, "the queued command")
        assert link.sent[-1][0] == "x6wd-motors"
        w.shutdown("test end")
        assert w.send_now(MotorCommand(time.monotonic(), 40.0, 40.0, "fix")) is False
        assert all(c.left_pct != 40.0 for _t, c in link.sent)  # nothing after shutdown
        assert link.stops == ["test end"]
    finally:
        link.release.set()
        w.shutdown("test end")


def test_a_repeated_command_is_not_resent_within_the_repeat_time() -> None:
    from x6wd.app.daemon import _MotorWorker

    link = BlockingLink()
    w = _MotorWorker(link, keepalive_s=5.0, on_health=lambda ok, t: None)
    w.start()
    try:
        w.submit(MotorCommand(time.monotonic(), 10.0, 10.0, "tick"), repeat_after_s=10.0)
        wait_for(lambda: w.sent == 1, 3, "first send")
        for _ in range(5):
            w.submit(MotorCommand(time.monotonic(), 10.0, 10.0, "tick"), repeat_after_s=10.0)
        assert w.repeats_skipped == 5 and w.sent == 1
        w.submit(MotorCommand(time.monotonic(), 10.0, 10.0, "other"), repeat_after_s=10.0)
        wait_for(lambda: w.sent == 2, 3, "a different command goes at once")
        w.submit(MotorCommand(time.monotonic(), 10.0, 10.0, "other"))  # no repeat time: sent
        wait_for(lambda: w.sent == 3, 3, "sent without a repeat time")
    finally:
        w.shutdown("test end")


class EncoderLink(BlockingLink):
    """A motor link with wheel encoders: ``read_odometry`` answers (or not, as told);
    ``overlaps`` counts sends and reads that began while another was in progress."""

    def __init__(self, answers: bool = True, supported: bool | None = None) -> None:
        super().__init__()
        self.answers = answers
        self.odometry_supported = supported
        self.reads: list[float] = []
        self.busy = threading.Lock()
        self.overlaps = 0
        self.reading = threading.Event()  # a read has begun
        self.release_read = threading.Event()  # reads return (cleared: they wait for it)
        self.release_read.set()

    def _enter(self) -> None:
        if not self.busy.acquire(blocking=False):
            self.overlaps += 1
            self.busy.acquire()
        time.sleep(0.002)  # a line's round trip: long enough for an overlap to show

    def send(self, cmd: MotorCommand) -> bool:
        self._enter()
        try:
            return super().send(cmd)
        finally:
            self.busy.release()

    def read_odometry(self) -> Any:
        from x6wd.core.records import WheelOdometry

        self._enter()
        try:
            self.reading.set()
            self.release_read.wait(5)
            self.reads.append(time.monotonic())
            if not self.answers:
                return None
            n = len(self.reads)
            return WheelOdometry(time.monotonic(), 10 * n, 11 * n, n)
        finally:
            self.busy.release()


def encoder_worker(link: Any, got: list[Any], keepalive_s: float, odometry_s: float) -> Any:
    """A started motor thread on ``link`` polling its encoders into ``got``."""
    from x6wd.app.daemon import _MotorWorker

    w = _MotorWorker(
        link, keepalive_s=keepalive_s, on_health=lambda ok, t: None, on_odometry=got.append,
        odometry_s=odometry_s,
    )  # fmt: skip
    w.start()
    return w


def test_the_motor_thread_polls_the_encoders_at_the_rate_between_sends() -> None:

    link = EncoderLink()
    got: list[Any] = []
    w = encoder_worker(link, got, keepalive_s=0.1, odometry_s=0.05)
    try:
        t0 = time.monotonic()
        for k in range(40):  # commands from another thread meanwhile
            if not w.send_now(MotorCommand(time.monotonic(), 10.0, 10.0, f"fix {k}")):
                w.submit(MotorCommand(time.monotonic(), 10.0, 10.0, f"tick {k}"))
            time.sleep(0.025)
        dt = time.monotonic() - t0
        assert w.odometry_state == "polling" and w.odometry_failures == 0
        assert 0.5 * dt / 0.05 <= len(got) <= dt / 0.05 + 2, (len(got), dt)
        assert [r.seq for r in got] == list(range(1, len(got) + 1))
        assert w.odometry_readings == len(got)
        assert link.overlaps == 0  # never two on the link at once
        gaps = [b - a for a, b in itertools.pairwise(link.reads)]
        assert min(gaps) > 0.02  # a fixed schedule: no bursts
    finally:
        w.shutdown("test end")


@pytest.mark.parametrize(
    ("make_link", "reason"),
    [
        (BlockingLink, "the motor backend has no wheel encoders"),
        (lambda: EncoderLink(answers=False, supported=False), "the motor board refuses"),
        (lambda: EncoderLink(answers=False), "the motor board did not answer"),
    ],
)
def test_a_board_without_encoders_is_given_up_on_and_logged_once(
    make_link: Callable[[], Any], reason: str, caplog: pytest.LogCaptureFixture
) -> None:
    from x6wd.app.daemon import ODOMETRY_GIVE_UP_AFTER

    link = make_link()
    got: list[Any] = []
    w = encoder_worker(link, got, keepalive_s=0.05, odometry_s=0.02)
    try:
        wait_for(lambda: w.odometry_state == "unavailable", 3, "unavailable")
        time.sleep(0.3)  # the keep-alive goes on, the encoders are not asked again (10 s)
        reads = getattr(link, "reads", None)
        assert reads is None or len(reads) == ODOMETRY_GIVE_UP_AFTER
        assert w.odometry_reason.startswith(reason) and got == []
        assert len(link.sent) >= 3  # the motors are not affected
        logged = [r for r in caplog.records if "wheel odometry unavailable" in r.getMessage()]
        assert len(logged) == 1 and reason in logged[0].getMessage()
    finally:
        w.shutdown("test end")


class FlakyEncoderLink(EncoderLink):
    """Refuses ``E`` (ERR) for its first ``refuse_first`` requests and while ``refusing``
    is set, answers otherwise."""

    def __init__(self, refuse_first: int = 0) -> None:
        super().__init__()
        self.refusing = threading.Event()
        self.refuse_first = refuse_first

    def read_odometry(self) -> Any:
        rec = super().read_odometry()
        if self.refusing.is_set() or len(self.reads) <= self.refuse_first:
            self.odometry_supported = False
            return None
        self.odometry_supported = True
        return rec


def test_a_refusal_or_two_does_not_end_the_odometry_and_it_comes_back(
    monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    """A board that answers ERR to a few E requests (booting, a glitch) is polled on; one that
    refuses long enough is unavailable, asked again every ODOMETRY_RETRY_S, and polled again
    once it answers."""
    import x6wd.app.daemon as daemon_module
    from x6wd.app.daemon import ODOMETRY_GIVE_UP_AFTER

    monkeypatch.setattr(daemon_module, "ODOMETRY_RETRY_S", 0.3)
    assert ODOMETRY_GIVE_UP_AFTER > 3
    link = FlakyEncoderLink(refuse_first=3)  # a board still booting
    got: list[Any] = []
    w = encoder_worker(link, got, keepalive_s=0.05, odometry_s=0.02)
    try:
        wait_for(lambda: len(got) >= 3, 3, "readings after a few refusals")
        assert w.odometry_state == "polling" and w.odometry_failures == 3
        assert not [r for r in caplog.records if "wheel odometry" in r.getMessage()]
        link.refusing.set()
        wait_for(lambda: w.odometry_state == "unavailable", 3, "unavailable")
        assert w.odometry_reason.startswith("the motor board refuses")
        n = len(link.reads)
        time.sleep(0.15)
        assert len(link.reads) == n  # not at the polling rate any more
        link.refusing.clear()
        wait_for(lambda: w.odometry_state == "polling", 3, "asked again and back")
        n = len(got)
        wait_for(lambda: len(got) >= n + 5, 3, "polled at its rate again")
        msgs = [r.getMessage() for r in caplog.records if "wheel odometry" in r.getMessage()]
        assert len(msgs) == 2 and "back" in msgs[1], msgs
    finally:
        w.shutdown("test end")


def test_status_shows_the_odometry_and_the_declination(tmp_path: Path, run_daemon) -> None:
    cfg = hil_config(tmp_path)
    r = run_daemon(Daemon(dataclasses.replace(cfg, motors=dataclasses.replace(
        cfg.motors, url="log://"))))  # fmt: skip
    with RemoteClient("127.0.0.1", r.port) as c:
        st = wait_for(lambda: (s := status(c))["telemetry"] and s, 10, "telemetry")
        assert st["links"]["odometry"] == "unavailable"
        assert st["devices"]["odometry"] == {
            "state": "unavailable", "readings": 0, "failures": 0,
            "reason": "the motor backend has no wheel encoders",
        }  # fmt: skip
        assert st["declination"]["source"] == "wmm"  # [compass] declination_deg absent
        # the control loop's own lateness (a CPU-starved host; outside audit 10e)
        loop = wait_for(lambda: (s := status(c)["loop"])["ticks"] and s, 10, "ticks counted")
        assert loop["tick_period_s"] > 0 and loop["late_window_s"] == 60.0
        assert {"late_last_s", "late_max_s", "overruns", "stale_holds_while_late"} <= set(loop)
    assert r.stop() == 0


def test_the_encoders_are_not_polled_while_the_link_is_lost() -> None:

    link = EncoderLink()
    link.healthy = False
    got: list[Any] = []
    w = encoder_worker(link, got, keepalive_s=0.05, odometry_s=0.02)
    try:
        wait_for(lambda: len(link.sent) >= 4, 3, "keep-alives to the lost link")
        assert link.reads == [] and w.odometry_state == "polling"  # not given up either
        link.healthy = True  # the board answers again: seen at the next send
        wait_for(lambda: len(got) >= 3, 3, "polling again")
        assert w.odometry_failures == 0
    finally:
        w.shutdown("test end")


def test_an_encoder_poll_leaves_the_link_idle_for_the_gc_but_a_command_waits_for_it() -> None:
    from x6wd.app.daemon import _MotorWorker

    link = EncoderLink()
    link.release_read.clear()
    w = _MotorWorker(
        link, keepalive_s=5.0, on_health=lambda ok, t: None, on_odometry=lambda rec: None,
        odometry_s=0.02,
    )  # fmt: skip
    w.start()
    try:
        assert link.reading.wait(3)
        assert w.idle  # no command sent or queued: the GPS thread may collect garbage
        assert w.send_now(MotorCommand(time.monotonic(), 10.0, 10.0, "fix")) is False
        assert not w.idle  # queued behind the poll
        link.release_read.set()
        wait_for(lambda: any(c.reason == "fix" for _t, c in link.sent), 3, "the queued fix")
        assert link.sent[-1][0] == "x6wd-motors" and link.overlaps == 0
    finally:
        link.release_read.set()
        w.shutdown("test end")


def test_gpsd_device_is_the_gps_as_configured_or_opened() -> None:
    from x6wd.app.daemon import _gps_device

    # the robot: [gps] url's device and baud, and [gps] rate_hz
    assert _gps_device("serial:///dev/ttyAMA0?baud=38400", 4.0) == ("/dev/ttyAMA0", 38400, 0.25)
    assert _gps_device("serial:///dev/ttyS0", 1.0) == ("/dev/ttyS0", 9600, 1.0)
    # not serial lines: no baud rate; a replay runs at its URL's rate
    assert _gps_device("tcp://gw:5000", 2.0) == ("tcp://gw:5000", None, 0.5)
    assert _gps_device("replay:///tmp/a.nmea?rate=5", 1.0) == ("/tmp/a.nmea", None, 0.2)
    # a simulated receiver: its world's pty, baud rate and rate, not [gps]'s
    world = type("W", (), {})()
    world.uart = type("U", (), {"port_name": "/dev/pts/9"})()
    world.receiver = type("R", (), {"baud": 38400, "rate_hz": 2.0})()
    assert _gps_device("sim://", 1.0, world) == ("/dev/pts/9", 38400, 0.5)


def test_gpsd_device_and_times_of_the_simulated_receiver(tmp_path: Path, run_daemon) -> None:
    r = run_daemon(Daemon(hil_config(tmp_path)))
    d = r.daemon
    world = d.devices.backend("sim")
    assert d.gpsd is not None
    with RemoteClient("127.0.0.1", r.port) as c:
        wait_for(lambda: status(c)["telemetry"], 10, "telemetry")
    with socket.create_connection(("127.0.0.1", d.gpsd.port), timeout=5) as s:
        f = s.makefile("rb")
        f.readline()
        s.sendall(b'?WATCH={"enable":true,"json":true};\n')
        dev = json.loads(f.readline())["devices"][0]
        # hil_config's [sim] gps_baud 115200 and gps_rate_hz 4, on the world's pty
        assert (dev["path"], dev["bps"], dev["cycle"]) == (world.uart.port_name, 115200, 0.25)
        tpv: dict[str, Any] = {}
        while "lat" not in tpv:
            obj = json.loads(f.readline())
            tpv = obj if obj["class"] == "TPV" else tpv
            t_read = time.time()
    # the receiver's UTC is the host's clock (cgps's "time offset" = the latency)
    from datetime import datetime

    assert 0.0 <= t_read - datetime.fromisoformat(tpv["time"]).timestamp() < 2.0, tpv
    assert r.stop() == 0
