"""The daemon's safety duties, each on the behaviour an operator or the motors see: the motor
worker's keep-alive and its stop when the control loop goes silent, an operator stop that
reaches the motors while the control loop is busy, moves refused until the devices are open,
the motors stopped before anything else at exit and on a crash in any thread, the geofence and
the manual time limit at their limits, a lost motor link that holds and then resumes, and the
status and events that make a hold visible. Written against the mutants `tools/mutate daemon`
found surviving (docs/testing.md, "Mutation testing")."""

from __future__ import annotations

import asyncio
import dataclasses
import functools
import itertools
import json
import logging
import math
import os
import re
import socket
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from drivers import registry
from drivers.motors import LogMotorLink
from tests.test_daemon import (
    ORIGIN,
    BoardOnPty,
    hil_config,
    run_daemon,
    run_to_exit,
    wait_for,
)
from tests.test_shutdown import StampedLink, log_motors_config, stamped
from x6wd import __version__
from x6wd.app.client import RemoteClient, RequestFailed
from x6wd.app.daemon import Daemon, _MotorWorker, distance_m
from x6wd.app.notify import Notifier
from x6wd.core.config import Config, GpsConfig, MotorsConfig, SafetyConfig
from x6wd.core.errors import ConfigError, DeviceUnavailable
from x6wd.core.geodesy import EARTH_MEAN_RADIUS_M as EARTH_RADIUS_M
from x6wd.core.records import Attitude, DeviceHealth, HealthEvent, MotorCommand

__all__ = ["run_daemon", "stamped"]  # fixtures, shared with test_daemon and test_shutdown


# -- the motor worker ------------------------------------------------------------------------
class Calls:
    """Records the worker's callbacks: on_health(ok, t_s) and on_events(events)."""

    def __init__(self) -> None:
        self.health: list[tuple[Any, Any]] = []
        self.events: list[HealthEvent] = []

    def on_health(self, ok: bool, t_s: float) -> None:
        self.health.append((ok, t_s))

    def on_events(self, events: list[HealthEvent]) -> None:
        self.events.extend(events)


def quiet_logger() -> logging.Logger:
    lg = logging.getLogger("tests.motors")
    lg.setLevel(logging.WARNING)  # the keep-alive would log every command
    return lg


@pytest.fixture
def quiet_log() -> LogMotorLink:
    return LogMotorLink(logger=quiet_logger())


def worker(link: Any, keepalive_s: float, calls: Calls | None = None) -> _MotorWorker:
    calls = calls or Calls()
    w = _MotorWorker(link, keepalive_s, calls.on_health, calls.on_events)
    w.start()
    return w


def test_a_worker_given_nothing_to_send_stops_the_motors(quiet_log: LogMotorLink) -> None:
    w = worker(quiet_log, 0.02)
    try:
        wait_for(lambda: quiet_log.last_command is not None, 3, "a keep-alive")
        cmd = quiet_log.last_command
        assert cmd is not None and cmd.is_stop and cmd.reason == "keepalive"
        assert isinstance(cmd.t_s, float)
        time.sleep(0.1)
        assert w.thread.is_alive() and all(c.is_stop for c in quiet_log.commands)
    finally:
        w.shutdown("test end")


def test_the_keepalive_resends_a_drive_for_three_periods_then_stops(
    quiet_log: LogMotorLink,
) -> None:
    w = worker(quiet_log, 0.25)
    try:
        drive = MotorCommand(time.monotonic(), 50.0, 50.0, "manual")
        w.submit(drive)
        wait_for(lambda: quiet_log.last_command and quiet_log.last_command.is_stop, 3, "stop")
        sent = list(quiet_log.commands)
        k = next(i for i, c in enumerate(sent) if c.is_stop)
        # sent, then resent at 0.25 and 0.5 s; a worker woken late (a loaded host) resends
        # fewer times, never more: each resend waits a period after the last, and a wake-up
        # 3 periods after the submission stops
        assert 1 <= k <= 3 and sent[:k] == [drive] * k, sent
        stop = sent[k]
        assert stop.is_stop and stop.reason == "keepalive"
        # silent for more than 3 periods (0.75 s): never sooner (the stop's own stamp); at
        # most 2 s, a late wake-up's slack (the drive resent for ever: no stop within 3 s)
        assert 0.74 < stop.t_s - drive.t_s < 2.0
    finally:
        w.shutdown("test end")


class SlowLink(LogMotorLink):
    """A log link whose send of a drive blocks until ``release`` is set."""

    def __init__(self) -> None:
        super().__init__(logger=quiet_logger())
        self.sending = threading.Event()
        self.release = threading.Event()
        self.arrived: list[tuple[float, MotorCommand]] = []

    def send(self, cmd: MotorCommand) -> bool:
        if not cmd.is_stop:
            self.sending.set()
            self.release.wait(5)
        self.arrived.append((time.monotonic(), cmd))
        return super().send(cmd)


def test_a_stop_submitted_during_a_slow_send_goes_out_right_after_it() -> None:
    link = SlowLink()
    w = worker(link, 10.0)  # a stop left waiting for the keep-alive would come 10 s late
    try:
        w.submit(MotorCommand(time.monotonic(), 30.0, 30.0, "drive"))
        assert link.sending.wait(5)
        w.submit(MotorCommand(time.monotonic(), 0.0, 0.0, "operator stop"))
        t_release = time.monotonic()
        link.release.set()
        wait_for(lambda: any(c.is_stop for _t, c in link.arrived), 5, "the stop")
        t_stop, cmd = next((t, c) for t, c in link.arrived if c.is_stop)
        assert cmd.reason == "operator stop" and t_stop - t_release < 3.0  # not a 10 s wait
    finally:
        link.release.set()
        w.shutdown("test end")


def test_a_command_the_link_refuses_stops_the_motors(quiet_log: LogMotorLink) -> None:
    w = worker(quiet_log, 5.0)
    try:
        w.submit(MotorCommand(time.monotonic(), 150.0, 0.0, "bad"))  # out of range
        wait_for(lambda: w.sent == 1, 3, "sent")
        cmd = quiet_log.last_command
        assert cmd is not None and cmd.is_stop and cmd.reason == "invalid command"
    finally:
        w.shutdown("test end")


def test_health_changes_and_events_reach_the_callbacks_once(quiet_log: LogMotorLink) -> None:
    calls = Calls()
    w = worker(quiet_log, 5.0, calls)
    try:
        assert w.health is quiet_log.health
        w.submit(MotorCommand(time.monotonic(), 10.0, 10.0, "a"))
        # idle too: the send's health report (after the count) is done
        wait_for(lambda: w.sent == 1 and w.idle, 3, "sent")
        assert calls.health == []  # healthy from the start: no change to report
        assert [(e.device, e.new) for e in calls.events] == [("motors", "connected")]
        quiet_log.close()  # the link goes away
        for n in (2, 3, 4):
            w.submit(MotorCommand(time.monotonic(), 10.0, 10.0, "a"))
            wait_for(lambda n=n: w.sent == n and w.idle, 3, "sent")
        assert len(calls.health) == 1
        ok, t_s = calls.health[0]
        assert ok is False and isinstance(t_s, float)
    finally:
        w.shutdown("test end")


class BareLink:
    """A motor backend with only the basic calls and no health record of its own (the
    worker keeps one for it); failures are switched on by the test."""

    def __init__(self) -> None:
        self.healthy = True
        self.sent: list[MotorCommand] = []
        self.stops: list[str] = []
        self.fail_send: Exception | None = None
        self.fail_stop: Exception | None = None
        self.fail_close: Exception | None = None
        self.closed = False

    def send(self, cmd: MotorCommand) -> bool:
        if self.fail_send is not None:
            raise self.fail_send
        self.sent.append(cmd)
        return True

    def stop(self, reason: str = "") -> bool:
        self.stops.append(reason)
        if self.fail_stop is not None:
            raise self.fail_stop
        return True

    def close(self) -> None:
        self.closed = True
        if self.fail_close is not None:
            raise self.fail_close


def test_a_link_without_health_gets_health_from_the_worker() -> None:
    link, calls = BareLink(), Calls()
    t0 = time.monotonic()
    w = worker(link, 5.0, calls)
    try:
        h = w.health
        assert isinstance(h, DeviceHealth)
        assert (h.device, h.state) == ("motors", "connected") and t0 <= h.since_t_s
        n = 0

        def send() -> None:
            nonlocal n
            n += 1
            w.submit(MotorCommand(time.monotonic(), 20.0, 20.0, "x"))
            # idle too: the send's health report (after the count) is done
            wait_for(lambda: w.sent == n and w.idle, 3, "sent")

        send()
        link.healthy = False
        send()
        h = w.health
        assert h.state == "disconnected" and h.since_t_s >= t0
        assert [ok for ok, _t in calls.health] == [False]
        link.healthy = True
        send()
        assert [ok for ok, _t in calls.health] == [False, True]
        assert w.health.state == "connected" and w.health.reconnects == 1
        assert [(e.new, e.message.split(" (")[0]) for e in calls.events] == [
            ("connected", "motors connected"),
            ("disconnected", "motors disconnected: link unhealthy"),
            ("connected", "motors reconnected"),
        ]
        # the backend raises, and so does its stop: counted, the worker carries on
        link.fail_send, link.fail_stop = RuntimeError("boom"), OSError("gone")
        send()
        send()
        assert w.link_errors == 2 and link.stops == ["link error", "link error"]
        h = w.health
        assert h.last_error == "send failed: boom" and h.last_error_t_s is not None
        link.fail_send = link.fail_stop = None
        send()
        assert link.sent[-1].left_pct == 20.0 and w.sent == n == 6
    finally:
        w.shutdown("test end")


def test_shutdown_stops_with_its_reason_then_closes_even_if_the_stop_fails() -> None:
    link = BareLink()
    link.fail_stop, link.fail_close = OSError("gone"), OSError("still gone")
    w = worker(link, 5.0)
    w.shutdown("daemon exit")  # no exception
    assert link.stops[-1] == "daemon exit" and link.closed
    assert not w.thread.is_alive()


class OverlapLink(BareLink):
    """A bare link whose sends take ``send_s`` and that notes sends running at once; its
    replies are ``reply`` (False: not acknowledged); stops are timed."""

    def __init__(self, send_s: float = 0.0) -> None:
        super().__init__()
        self.send_s = send_s
        self.reply = True
        self.active = 0
        self.most_active = 0
        self.sent_at: list[tuple[float, float, MotorCommand]] = []  # (start, end, command)
        self.stop_t: list[float] = []
        self._lk = threading.Lock()

    def send(self, cmd: MotorCommand) -> bool:
        with self._lk:
            self.active += 1
            self.most_active = max(self.most_active, self.active)
        t0 = time.monotonic()
        try:
            time.sleep(self.send_s)
            if self.fail_send is not None:
                raise self.fail_send
            self.sent.append(cmd)
            return self.reply
        finally:
            self.sent_at.append((t0, time.monotonic(), cmd))
            with self._lk:
                self.active -= 1

    def stop(self, reason: str = "") -> bool:
        self.stop_t.append(time.monotonic())
        return super().stop(reason)


def drive(left: float = 30.0, reason: str = "drive") -> MotorCommand:
    return MotorCommand(time.monotonic(), left, left, reason)


def test_after_a_send_now_the_keepalive_resends_it_then_stops() -> None:
    link = OverlapLink()
    # a 1 s keep-alive (was 0.05 s): its first resend needs the worker awake within 3
    # periods of the send, which a loaded host did not always give 0.15 s
    w = worker(link, 1.0)
    try:
        assert w.send_now(drive())
        wait_for(lambda: any(c.is_stop for c in link.sent), 10, "the keep-alive's stop")
        resent = [c for c in link.sent if not c.is_stop]
        assert len(resent) >= 2 and link.sent[-1].reason == "keepalive"
        assert w.thread.is_alive()
    finally:
        w.shutdown("test end")


def test_identical_commands_are_all_sent_unless_a_repeat_interval_is_asked_for() -> None:
    link = OverlapLink()
    w = worker(link, 5.0)
    try:
        w.submit(drive())
        wait_for(lambda: w.sent == 1, 3, "the first send")
        w.submit(drive())  # no repeat interval: sent again
        # idle: the send is over (a submit during it is never skipped)
        wait_for(lambda: w.sent == 2 and w.idle, 3, "the repeat")
        # within 5 s of the last send (0.5 s was too short for a loaded host): skipped
        w.submit(drive(), repeat_after_s=5.0)
        assert w.repeats_skipped == 1
        w.submit(drive(left=40.0), repeat_after_s=5.0)  # a different command: sent
        wait_for(lambda: w.sent == 3, 3, "the new command")
        assert [c.left_pct for c in link.sent] == [30.0, 30.0, 40.0]
    finally:
        w.shutdown("test end")


def test_send_now_writes_from_the_caller_only_to_an_idle_link_that_acknowledged() -> None:
    link = OverlapLink()
    w = worker(link, 5.0)
    try:
        assert w.send_now(drive()) and w.direct_sent == 1
        link.reply = False  # not acknowledged (the link still says healthy)
        assert w.send_now(drive(left=35.0)) and link.healthy
        # the last send went unacknowledged: the next goes through the motor thread
        assert not w.send_now(drive(left=40.0)) and w.direct_sent == 2
        wait_for(lambda: link.sent[-1].left_pct == 40.0, 3, "queued send")
        link.reply = True
        link.fail_send = OSError("line noise")  # a send that raises is not acknowledged either
        w.submit(drive(left=45.0))
        wait_for(lambda: w.link_errors == 1, 3, "the failed send")
        link.fail_send = None
        assert not w.send_now(drive(left=50.0))
    finally:
        w.shutdown("test end")


def test_send_now_and_the_motor_thread_never_send_at_once() -> None:
    link = OverlapLink(send_s=0.2)
    w = worker(link, 5.0)
    try:
        t = threading.Thread(target=w.send_now, args=(drive(),))
        t.start()
        wait_for(lambda: link.active == 1, 2, "send_now sending")
        w.submit(drive(left=60.0))  # the motor thread must wait for the send in progress
        t.join(3)
        wait_for(lambda: len(link.sent_at) == 2, 3, "both sends")
        assert link.most_active == 1
        (_a0, a1, first), (b0, _b1, second) = link.sent_at
        assert first.left_pct == 30.0 and second.left_pct == 60.0 and b0 >= a1
    finally:
        w.shutdown("test end")


def test_shutdown_waits_for_a_send_now_in_progress_then_stops() -> None:
    link = OverlapLink(send_s=0.3)
    w = worker(link, 5.0)
    t = threading.Thread(target=w.send_now, args=(drive(),))
    t.start()
    wait_for(lambda: link.active == 1, 2, "send_now sending")
    w.shutdown("daemon exit")
    t.join(3)
    (_s0, s1, cmd) = link.sent_at[0]
    assert not cmd.is_stop and link.stops == ["daemon exit"]
    assert link.stop_t[0] >= s1  # the stop is the last thing the link got
    assert not w.send_now(drive()) and len(link.sent) == 1  # nothing after shutdown


def test_shutdown_stops_the_motors_even_when_a_send_now_never_returns() -> None:
    link = OverlapLink(send_s=30.0)  # a shutdown waiting for the send would take 30 s
    w = worker(link, 5.0)
    threading.Thread(target=w.send_now, args=(drive(),), daemon=True).start()
    wait_for(lambda: link.active == 1, 2, "send_now sending")
    t0 = time.monotonic()
    w.shutdown("daemon exit")
    # it waits 5 s for the send (from after t0: never less), then stops all the same; 8 s
    # leaves a loaded host 3 s of slack and stays far below the 30 s of waiting for the send
    assert link.stops == ["daemon exit"] and 4.5 < time.monotonic() - t0 < 8.0


# -- the running daemon ----------------------------------------------------------------------
class BlockableDaemon(Daemon):
    """Fault injection: once ``blocking`` is set, the next compass sample holds the control
    loop (the event loop) until ``release`` is set, as a stuck computation would."""

    def __init__(self, config: Config) -> None:
        super().__init__(config)
        self.blocking, self.blocked, self.release = (threading.Event() for _ in range(3))

    def _on_attitude(self, att: Attitude) -> None:
        if self.blocking.is_set() and not self.blocked.is_set():
            self.blocked.set()
            self.release.wait(10)
        super()._on_attitude(att)


def slow_keepalive(cfg: Config) -> Config:
    # keep-alive every 1 s, so that its own stop (after 3 s of silence) comes late
    return dataclasses.replace(cfg, motors=MotorsConfig(url="log://", watchdog_ms=3000))


def test_an_operator_stop_reaches_the_motors_while_the_control_loop_is_busy(
    tmp_path: Path, run_daemon, stamped: StampedLink
) -> None:
    d = BlockableDaemon(slow_keepalive(log_motors_config(tmp_path)))
    r = run_daemon(d)
    replies: dict[str, Any] = {}

    def ask(name: str, cmd: str, **args: Any) -> threading.Thread:
        def go() -> None:
            with RemoteClient("127.0.0.1", r.port) as c:
                replies[name] = c.request(cmd, **args)

        t = threading.Thread(target=go, daemon=True)
        t.start()
        return t

    # one operator drives throughout, on one connection: a connection closed while its
    # drive runs is the control port's dead-man (a stop), and another connection's drive
    # is refused while this one's holds (busy)
    owner = RemoteClient("127.0.0.1", r.port)
    owner.request("drive", left=40, right=40, duration_s=5)
    wait_for(lambda: stamped.driving(40.0, 40.0), 3, "motors driven")
    d.blocking.set()
    assert d.blocked.wait(5)  # the control loop is stuck from here on

    def drive_again() -> None:
        replies["drive"] = owner.request("drive", left=10, right=10, duration_s=5)

    drive = threading.Thread(target=drive_again, daemon=True)
    drive.start()
    time.sleep(0.3)
    assert "drive" not in replies and not stamped.driving(10.0, 10.0)  # waits for the loop
    t0 = time.monotonic()
    stop = ask("stop", "stop")
    # the keep-alive's own stop (3 s after the loop's last command, before t0) would come
    # later than this window, and its reason is not the operator's (checked below)
    wait_for(lambda: stamped.first_stop_after(t0), 2.0, "the operator's stop")
    first = next(c for t, c in stamped.stamped if t >= t0 and c.is_stop)
    assert first.reason == "operator stop" and t0 <= first.t_s <= time.monotonic()
    assert "stop" not in replies and d.blocked.is_set()  # the loop is still stuck
    d.release.set()
    drive.join(5)
    stop.join(5)
    assert replies["stop"]["mode"] == "IDLE" and replies["drive"]["left"] == 10
    wait_for(lambda: stamped.stamped[-1][1].is_stop, 3, "stopped at the end")
    owner.close()


def notify_socket(tmp_path: Path) -> tuple[socket.socket, Notifier]:
    path = tmp_path / "notify.sock"
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(str(path))
    sock.settimeout(10)
    return sock, Notifier(str(path))


def notices(sock: socket.socket) -> Iterator[dict[str, str]]:
    while True:
        data = sock.recv(4096).decode()
        yield dict(line.split("=", 1) for line in data.split("\n"))


def test_moves_are_refused_until_the_devices_are_open(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    opened = threading.Event()
    link = LogMotorLink()

    def open_motors(url: str, devices: Any = None, **_kw: Any) -> LogMotorLink:
        opened.wait(10)
        return link

    monkeypatch.setattr(registry, "open_motors", open_motors)
    sock, notifier = notify_socket(tmp_path)
    d = Daemon(log_motors_config(tmp_path), notifier=notifier)
    readied: list[Daemon] = []
    result: dict[str, int] = {}
    loop_box: dict[str, asyncio.AbstractEventLoop] = {}

    async def main() -> None:
        loop_box["loop"] = asyncio.get_running_loop()
        result["code"] = await d.run(ready=readied.append)

    t = threading.Thread(target=lambda: asyncio.run(main()), daemon=True)
    t.start()
    try:
        port = wait_for(lambda: d.server is not None and d.server.port, 10, "listening")
        with RemoteClient("127.0.0.1", port) as c:
            for cmd, args in (("drive", {"left": 10, "right": 10, "duration_s": 1}),
                              ("start", {}), ("resume", {}),
                              ("mission.load", {"waypoints": [list(ORIGIN)]})):  # fmt: skip
                with pytest.raises(RequestFailed) as ei:
                    c.request(cmd, **args)
                assert (ei.value.code, ei.value.message) == (
                    "rejected", "x6wd is starting: devices are not open yet"
                ), cmd  # fmt: skip
            st = c.request("status")
            assert (st["mode"], st["state"], st["telemetry"]) == ("IDLE", "IDLE", None)
            assert st["devices"] == {
                "gps": None, "compass": None, "motors": None, "odometry": None
            }  # fmt: skip
            assert st["links"] == {"gps": "unknown", "gps_reconnects": 0, "compass": "unknown",
                                   "compass_errors": 0, "motors": "lost",
                                   "odometry": "unknown", "recorder": "unknown"}  # fmt: skip
            assert st["recorder"] is None  # not open yet
            assert st["version"] == __version__
            assert isinstance(st["uptime_s"], float) and 0.0 <= st["uptime_s"] < 30.0
            assert c.request("stop")["mode"] == "IDLE"  # always obeyed
            with pytest.raises(RequestFailed) as ei:  # allowed through, refused by the robot
                c.request("pause")
            assert ei.value.message == "nothing to pause: mode is IDLE"
            opened.set()
            msg = next(notices(sock))
            assert msg["READY"] == "1" and msg["STATUS"] == "IDLE IDLE"  # the stop's telemetry
            wait_for(lambda: readied, 10, "ready")
            assert readied == [d]
            reply = c.request("drive", left=10, right=10, duration_s=1)
            assert {k: reply[k] for k in ("left", "right", "duration_s")} == {
                "left": 10, "right": 10, "duration_s": 1
            }  # fmt: skip
        loop_box["loop"].call_soon_threadsafe(d.request_stop)
        t.join(15)
        assert result["code"] == 0
        msg = next(m for m in notices(sock) if "STOPPING" in m)
        assert msg == {"STOPPING": "1", "STATUS": "stopping"}
    finally:
        opened.set()
        if t.is_alive() and "loop" in loop_box:
            loop_box["loop"].call_soon_threadsafe(d.request_stop)
            t.join(15)
        sock.close()
        if d.devices is not None:
            d.devices.close()


def fds_open_on(path: Path) -> list[str]:
    """What this process holds open of ``path`` (a file, or anything in a directory)."""
    out = []
    for fd in os.listdir("/proc/self/fd"):
        try:
            target = os.readlink(f"/proc/self/fd/{fd}")
        except OSError:
            continue
        if target == str(path) or target.startswith(f"{path}/"):
            out.append(target)
    return out


def test_at_exit_the_motors_stop_first_and_nothing_is_left_open(
    tmp_path: Path, run_daemon, stamped: StampedLink
) -> None:
    sock, notifier = notify_socket(tmp_path)
    r = run_daemon(Daemon(log_motors_config(tmp_path), notifier=notifier))
    port = r.port
    world = r.daemon.devices.backend("sim")
    gps_port = Path(world.uart.port_name)
    gps_fds = len(fds_open_on(gps_port))
    assert gps_fds >= 1  # the daemon's GPS reader holds its device
    watcher = RemoteClient("127.0.0.1", port)
    watcher.request("watch", on=True)
    # held open until the motors drove: the robot stops a drive whose client went away
    driver = RemoteClient("127.0.0.1", port)
    driver.request("drive", left=30, right=-30, duration_s=5)
    state = wait_for(lambda: (e := watcher.next_event(2.0))["event"] == "state" and e, 5)
    assert state == {
        "event": "state", "old": "IDLE", "new": "MANUAL", "reason": "mode: manual drive"
    }  # fmt: skip
    tel = wait_for(lambda: (e := watcher.next_event(2.0))["event"] == "telemetry" and e, 5)
    assert set(tel) == {"event", "data", "devices"} and set(tel["devices"]) == {
        "gps", "compass", "motors", "odometry"
    }  # fmt: skip
    assert (tel["data"]["mode"], tel["data"]["left_pct"]) == ("MANUAL", 30.0)
    wait_for(lambda: stamped.driving(30.0, -30.0), 3, "motors driven")
    driver.close()
    # a change of state is also told to systemd (`systemctl status` shows it)
    assert any(m.get("STATUS") == "MANUAL IDLE" for m in itertools.islice(notices(sock), 20))
    # a first fix, and the next epoch's: the first epoch's sky report (its GSV sentences come
    # after the fix) is then decoded and recorded too
    wait_for(
        lambda: r.daemon.first_fix and r.daemon.stats["fixes"] >= 2,
        20,
        "fixes (recorded by the GPS thread)",
    )
    r.loop.call_soon_threadsafe(r.daemon.request_stop)
    t_eof = None
    deadline = time.monotonic() + 10
    while time.monotonic() < deadline:
        try:
            watcher.next_event(1.0)
        except TimeoutError:
            continue
        except Exception:  # closed: ConnectionFailed (with the server's notice) or EOF
            t_eof = time.monotonic()
            break
    watcher.close()
    r.thread.join(10)
    assert r.code == 0 and t_eof is not None
    exits = [(t, c.reason) for t, c in stamped.stamped if c.reason in ("daemon exit", "close")]
    assert [why for _t, why in exits] == ["daemon exit", "close"]
    assert exits[0][0] < t_eof  # the motors stopped before the server let its clients go
    with pytest.raises(OSError):
        socket.create_connection(("127.0.0.1", port), timeout=2).close()
    rec_dir = tmp_path / "rec"
    assert fds_open_on(rec_dir) == []  # the recording is closed
    assert fds_open_on(gps_port) == []  # and the GPS device, by the reader and the world
    assert not world.running  # the simulated world is closed, last
    with pytest.raises(DeviceUnavailable, match="closed"):
        r.daemon.devices.backend("sim")
    sock.close()
    (rec,) = rec_dir.glob("*.jsonl")
    text = rec.read_text()
    # fixes, sentences and sky reports are recorded by the GPS thread's own decisions
    for kind in ("motor", "state", "telemetry", "fix", "nmea", "sky", "attitude"):
        assert f'"type":"{kind}"' in text, kind


class CrashingGpsDaemon(Daemon):
    """Fault injection: once armed, the GPS thread hits a bug."""

    armed = False
    t_boom: float | None = None

    def _gps_thread(self) -> None:
        reader = self._gps_reader
        poll = reader.poll

        def armed_poll(timeout_s: float) -> Any:
            if self.armed:
                self.t_boom = time.monotonic()
                raise RuntimeError("injected bug in the GPS thread")
            return poll(timeout_s)

        reader.poll = armed_poll
        super()._gps_thread()


class CrashingDecisionDaemon(Daemon):
    """Fault injection: once armed, deciding on a GPS record hits a bug (in the GPS thread,
    under the control lock)."""

    armed = False
    t_boom: float | None = None

    def _on_gps_records(self, records: list[Any]) -> None:
        if self.armed and self.t_boom is None:
            self.t_boom = time.monotonic()
            raise RuntimeError("injected bug in a decision")
        super()._on_gps_records(records)


def drive_then_arm_a_bug(d: Any, run_daemon: Any, stamped: StampedLink) -> None:
    """Drive the running daemon ``d``, arm its injected bug, and check it exits 1 with the
    motors stopped after the bug."""
    r = run_daemon(d)
    with RemoteClient("127.0.0.1", r.port) as c:  # open: the robot stops a drive left alone
        c.request("drive", left=25, right=25, duration_s=5)
        wait_for(lambda: stamped.driving(25.0, 25.0), 3, "motors driven")
        d.armed = True
        r.thread.join(10)
    assert r.code == 1
    assert d.t_boom is not None and stamped.first_stop_after(d.t_boom) is not None
    assert stamped.stamped[-1][1].is_stop


def test_a_bug_while_deciding_on_a_fix_stops_the_motors_and_exits_1(
    tmp_path: Path, run_daemon, stamped: StampedLink, caplog: pytest.LogCaptureFixture
) -> None:
    drive_then_arm_a_bug(CrashingDecisionDaemon(log_motors_config(tmp_path)), run_daemon, stamped)
    assert any("injected bug in a decision" in rec.getMessage() or (
        rec.exc_info and "injected bug in a decision" in str(rec.exc_info[1]))
        for rec in caplog.records)  # fmt: skip


def test_a_bug_in_a_device_thread_stops_the_motors_and_exits_1(
    tmp_path: Path, run_daemon, stamped: StampedLink
) -> None:
    drive_then_arm_a_bug(CrashingGpsDaemon(log_motors_config(tmp_path)), run_daemon, stamped)


def test_the_geofence_and_the_manual_limit_hold_at_their_edges(tmp_path: Path, run_daemon) -> None:
    centre = ORIGIN
    edge = (ORIGIN[0] + 0.0009, ORIGIN[1])  # about 100 m north
    radius = distance_m(*centre, *edge)
    cfg = hil_config(tmp_path, safety=SafetyConfig(geofence_radius_m=radius,
                                                   geofence_center=centre))  # fmt: skip
    r = run_daemon(Daemon(cfg))
    with RemoteClient("127.0.0.1", r.port) as c:
        assert c.request("mission.load", waypoints=[list(edge)])["count"] == 1  # on the fence
        beyond = [edge[0] + 1e-6, edge[1]]
        with pytest.raises(RequestFailed) as ei:
            c.request("mission.load", waypoints=[list(edge), beyond])
        assert ei.value.code == "geofence" and ei.value.message.startswith("waypoint 2 (")
        reply = c.request("drive", left=20, right=-20, duration_s=5.0)  # exactly manual_max_s
        assert {k: reply[k] for k in ("left", "right", "duration_s")} == {
            "left": 20, "right": -20, "duration_s": 5.0
        }  # fmt: skip
        with pytest.raises(RequestFailed) as ei:
            c.request("drive", left=20, right=-20, duration_s=5.5)
        assert (ei.value.code, ei.value.message) == ("bad_request", "duration_s 5.5 > limit 5 s")
        with pytest.raises(RequestFailed) as ei:  # just over: said so, not "5 > limit 5"
            c.request("drive", left=20, right=-20, duration_s=5.0000001)
        assert ei.value.message == "duration_s 5.0000001 > limit 5 s"
        st = wait_for(
            lambda: (
                (s := c.request("status"))["links"]["gps"] == "connected" and s["telemetry"] and s
            ),
            10,
            "devices up",
        )
        odometry = st["links"].pop("odometry")  # readings so far: the sim:// board has encoders
        assert isinstance(odometry, int) and odometry >= 0
        assert st["links"] == {"gps": "connected", "gps_reconnects": 0, "compass": "connected",
                               "compass_errors": 0, "motors": "ok",
                               "recorder": "ok"}  # fmt: skip
        assert st["recorder"]["state"] == "ok" and st["recorder"]["records_dropped"] == 0
        assert set(st["devices"]) == {"gps", "compass", "motors", "odometry"}
        assert st["devices"]["odometry"]["state"] == "polling"
        assert st["devices"]["motors"]["state"] == "connected"
        assert (st["mode"], st["state"]) == (st["telemetry"]["mode"], st["telemetry"]["state"])
        assert st["mode"] == "MANUAL" and st["version"] == __version__


def nmea(body: str) -> str:
    checksum = functools.reduce(lambda acc, ch: acc ^ ord(ch), body, 0)
    return f"${body}*{checksum:02X}\r\n"


def test_without_a_fix_or_a_configured_centre_no_mission_is_loaded(
    tmp_path: Path, run_daemon
) -> None:
    log = tmp_path / "nofix.nmea"
    log.write_text("".join(nmea(f"GPRMC,1200{i:02d}.00,V,,,,,,,010124,,,N") for i in range(30)))
    cfg = dataclasses.replace(hil_config(tmp_path), gps=GpsConfig(url=f"replay://{log}?speed=1"))
    r = run_daemon(Daemon(cfg))
    with RemoteClient("127.0.0.1", r.port) as c:
        with pytest.raises(RequestFailed) as ei:
            c.request("mission.load", waypoints=[list(ORIGIN)])
        assert (ei.value.code, ei.value.message) == (
            "geofence", "no fix yet: cannot check waypoints against geofence"
        )  # fmt: skip


def test_a_lost_motor_link_holds_and_its_return_resumes(tmp_path: Path, run_daemon) -> None:
    cfg = hil_config(tmp_path)
    with BoardOnPty() as pb:
        cfg = dataclasses.replace(cfg, motors=dataclasses.replace(cfg.motors, url=pb.url))
        r = run_daemon(Daemon(cfg))
        with RemoteClient("127.0.0.1", r.port) as c:
            wait_for(lambda: r.daemon.first_fix, what="first fix")
            c.request("mission.load", waypoints=[[ORIGIN[0] + 0.0005, ORIGIN[1]]])
            c.request("start")
            wait_for(lambda: pb.board.running, 5, "board driven")
            pb.halt()  # the board stops answering
            # the link's state and the telemetry (the next tick's) may come a moment apart
            # on a loaded host: both, polled (a link loss ignored never holds)
            wait_for(
                lambda: (
                    (s := c.request("status"))["links"]["motors"] == "lost"
                    and s["telemetry"]["hold_reason"] == "motor link lost"
                ),
                10,
                "lost, holding",
            )
            pb.serve()  # and comes back
            st = wait_for(
                lambda: (
                    (s := c.request("status"))["links"]["motors"] == "ok"
                    and s["telemetry"]["hold_reason"] != "motor link lost"
                    and s
                ),
                10,
                "link back",
            )
            assert st["mode"] == "RUNNING"
            wait_for(lambda: pb.board.running, 5, "board driven again")
        assert r.stop() == 0


def test_distance_along_parallels_and_to_the_antipode() -> None:
    assert distance_m(0.0, 0.0, 0.0, 1.0) == pytest.approx(111_195.08, rel=1e-6)
    # along the 60th parallel a degree of longitude spans half as much (cos 60 = 1/2)
    expected = 2 * EARTH_RADIUS_M * math.asin(0.5 * math.sin(math.radians(0.5)))
    assert distance_m(60.0, 10.0, 60.0, 11.0) == pytest.approx(expected, rel=1e-12)
    assert distance_m(-60.0, 10.0, -60.0, 9.0) == pytest.approx(expected, rel=1e-12)
    for lat, lon in ((0.0, 0.0), (45.0, 10.0), (-33.87, 151.21), (51.752, -1.2577)):
        other = lon + 180.0 if lon <= 0 else lon - 180.0
        assert distance_m(lat, lon, -lat, other) == pytest.approx(math.pi * EARTH_RADIUS_M)


def test_a_configuration_error_is_logged_and_told_to_systemd(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    sock, notifier = notify_socket(tmp_path)
    cfg = hil_config(tmp_path)  # an error only the start-up checks find: the device URL's
    d = Daemon(dataclasses.replace(cfg, gps=GpsConfig(url="nosuch://x")), notifier=notifier)
    try:
        with caplog.at_level(logging.ERROR, logger="x6wd.app.daemon"):
            assert run_to_exit(d) == 2
        why = (
            "gps.url: 'nosuch://x': unknown scheme 'nosuch' "
            "(valid for gps: serial://, tcp://, replay://, sim://)"
        )
        assert [rec.getMessage() for rec in caplog.records] == [why]
        assert next(notices(sock)) == {"STOPPING": "1", "STATUS": f"configuration error: {why}"}
    finally:
        sock.close()
        if d.devices is not None:
            d.devices.close()


@pytest.mark.parametrize(
    ("centre", "why"),
    [
        ((91.0, 0.0), "latitude 91 outside [-90, 90] deg"),
        ((51.7, -181.0), "longitude -181 outside [-180, 180] deg"),
        ((float("nan"), 0.0), "latitude nan outside [-90, 90] deg"),
    ],
)
def test_a_geofence_centre_out_of_range_names_the_coordinate(
    centre: tuple[float, float], why: str
) -> None:
    # an outside audit: [91, 0] got "expected [lat_deg, lon_deg], got (91.0, 0.0)"; the
    # config itself refuses it now (so x6wd sim and sweeps do too), before any daemon
    with pytest.raises(ConfigError, match=re.escape(f"safety.geofence_center: {why}")):
        SafetyConfig(geofence_center=centre)


def test_a_motor_board_that_cannot_be_reached_is_exit_1(tmp_path: Path) -> None:
    s = socket.create_server(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()  # nothing listens there now
    cfg = dataclasses.replace(
        hil_config(tmp_path), motors=MotorsConfig(url=f"tcp://127.0.0.1:{port}")
    )
    d = Daemon(cfg)
    try:
        assert run_to_exit(d) == 1
    finally:
        if d.devices is not None:
            d.devices.close()


class LateConfigErrorDaemon(Daemon):
    """Fault injection: a setting only the opened device can judge is wrong, found after the
    motor link opened (its worker already runs)."""

    async def _open_devices(self) -> None:
        await super()._open_devices()
        raise ConfigError("compass.url: the device on the bus is not a CMPS10")


def test_a_configuration_error_found_when_the_devices_open_is_exit_2_motors_stopped(
    tmp_path: Path, stamped: StampedLink, caplog: pytest.LogCaptureFixture
) -> None:
    # exit 2, not 1: the unit's RestartPreventExitStatus=2 keeps systemd from restarting a
    # daemon whose settings no restart can fix
    d = LateConfigErrorDaemon(log_motors_config(tmp_path))
    try:
        with caplog.at_level(logging.ERROR, logger="x6wd.app.daemon"):
            assert run_to_exit(d) == 2
    finally:
        if d.devices is not None:
            d.devices.close()
    assert stamped.stamped and stamped.stamped[-1][1].is_stop
    assert any("not a CMPS10" in rec.getMessage() for rec in caplog.records)


def _gpsd_lines(port: int, watch: str, want: Any, timeout_s: float = 20.0) -> list[str]:
    """Lines from the daemon's gpsd port after ``watch``, until ``want(lines)``."""
    lines: list[str] = []
    with socket.create_connection(("127.0.0.1", port), timeout=timeout_s) as s:
        s.sendall(watch.encode() + b"\n")
        buf = b""
        deadline = time.monotonic() + timeout_s
        while not want(lines):
            assert time.monotonic() < deadline, (
                f"gpsd port: not seen in {timeout_s} s: {lines[-5:]}"
            )
            chunk = s.recv(65536)
            assert chunk, "gpsd port closed"
            buf += chunk
            *done, buf = buf.split(b"\n")
            lines += [d.decode().rstrip("\r") for d in done]
    return lines


def test_the_gpsd_port_relays_the_running_daemons_fixes_sky_attitude_and_sentences(
    tmp_path: Path, run_daemon
) -> None:
    d = Daemon(hil_config(tmp_path))
    run_daemon(d)
    assert d.gpsd is not None
    port = d.gpsd.port

    def classes(lines: list[str]) -> set[str]:
        return {json.loads(x)["class"] for x in lines if x.startswith("{")}

    both = _gpsd_lines(
        port,
        '?WATCH={"enable":true,"json":true,"nmea":true};',
        lambda ls: {"TPV", "SKY", "ATT"} <= classes(ls) and any(x.startswith("$GPGGA") for x in ls),
    )
    tpv = next(json.loads(x) for x in both if x.startswith('{"class":"TPV"'))
    assert tpv["mode"] >= 2 and abs(tpv["lat"] - ORIGIN[0]) < 1e-3
    gga = next(x for x in both if x.startswith("$GPGGA"))
    body, star, checksum = gga[1:].partition("*")
    assert star and int(checksum, 16) == functools.reduce(lambda a, c: a ^ ord(c), body, 0)
    # JSON only: no sentences; sentences only: no JSON objects after the WATCH reply
    json_only = _gpsd_lines(port, '?WATCH={"enable":true,"json":true};',
                            lambda ls: {"TPV", "SKY", "ATT"} <= classes(ls))  # fmt: skip
    assert not any(x.startswith("$") for x in json_only)
    nmea_only = _gpsd_lines(port, '?WATCH={"enable":true,"nmea":true};',
                            lambda ls: sum(x.startswith("$GPGGA") for x in ls) >= 2)  # fmt: skip
    after_watch = nmea_only[next(i for i, x in enumerate(nmea_only) if '"WATCH"' in x) + 1 :]
    assert after_watch and not any(x.startswith("{") for x in after_watch)


def test_the_systemd_watchdog_is_fed_while_the_loop_turns(tmp_path: Path, run_daemon) -> None:
    sock, _ = notify_socket(tmp_path)
    notifier = Notifier(str(tmp_path / "notify.sock"), watchdog_usec=200_000)  # ping every 0.1 s
    r = run_daemon(Daemon(log_motors_config(tmp_path), notifier=notifier))
    t0 = time.monotonic()
    pings = 0
    for msg in notices(sock):
        pings += msg.get("WATCHDOG") == "1"
        if pings >= 5:
            break
    assert time.monotonic() - t0 < 3.0  # ~0.1 s apart, not at the tick rate nor never
    r.loop.call_soon_threadsafe(r.daemon.request_stop)
    r.thread.join(10)
    assert r.code == 0
    sock.close()


class FailingWatchdogDaemon(Daemon):
    """Fault injection: once armed, feeding the systemd watchdog (a task of the control
    loop's task group) hits a bug."""

    armed = False

    def _feed_watchdog(self, now_s: float) -> None:
        if self.armed:
            raise RuntimeError("injected bug in a control-loop task")
        super()._feed_watchdog(now_s)


def test_a_bug_in_a_control_loop_task_stops_the_motors_and_exits_1(
    tmp_path: Path, run_daemon, stamped: StampedLink
) -> None:
    sock, _ = notify_socket(tmp_path)
    notifier = Notifier(str(tmp_path / "notify.sock"), watchdog_usec=200_000)
    d = FailingWatchdogDaemon(log_motors_config(tmp_path), notifier=notifier)
    r = run_daemon(d)
    with RemoteClient("127.0.0.1", r.port) as c:  # kept open: its drive would stop with it
        c.request("drive", left=25, right=25, duration_s=5)
        wait_for(lambda: stamped.driving(25.0, 25.0), 3, "motors driven")
        t_armed = time.monotonic()
        d.armed = True
        r.thread.join(10)
    assert r.code == 1
    assert stamped.first_stop_after(t_armed) is not None and stamped.stamped[-1][1].is_stop
    sock.close()


def test_with_no_fix_coming_the_loop_collects_the_garbage(tmp_path: Path, run_daemon) -> None:
    master, slave = os.openpty()  # a GPS port on which nothing ever arrives
    try:
        cfg = log_motors_config(tmp_path)
        cfg = dataclasses.replace(cfg, gps=GpsConfig(url=f"serial://{os.ttyname(slave)}"))
        d = Daemon(cfg)
        r = run_daemon(d)
        pacer = d.gc_pacer
        assert pacer is not None
        n0 = pacer.collections
        wait_for(lambda: pacer.collections > n0, 8, "a collection without fixes")
        assert d.first_fix is None
        slave_path = Path(os.ttyname(slave))
        assert len(fds_open_on(slave_path)) == 2  # this test's and the daemon's GPS reader
        r.loop.call_soon_threadsafe(d.request_stop)
        r.thread.join(10)
        assert r.code == 0
        assert len(fds_open_on(slave_path)) == 1  # at exit the daemon closed its serial port
    finally:
        os.close(master)
        os.close(slave)


def test_an_in_process_mission_drives_to_its_waypoint(tmp_path: Path, run_daemon) -> None:
    d = Daemon(hil_config(tmp_path))
    r = run_daemon(d)
    world = d.devices.backend("sim")
    wait_for(lambda: d.first_fix, 20, "first fix")
    with RemoteClient("127.0.0.1", r.port) as c:
        c.request("mission.load", waypoints=[[ORIGIN[0] + 20.0 / 111_200.0, ORIGIN[1]]])
        c.request("start")
        st = wait_for(
            lambda: (s := c.request("status"))["mode"] == "DONE" and s, 90, "mission done"
        )
    assert st["state"] == "MISSION_DONE"
    # The robot's own estimate ends at the waypoint 20 m north (arrival window) ...
    assert abs((st["telemetry"]["filt_lat_deg"] - ORIGIN[0]) * 111_200.0 - 20.0) < 4.0
    # ... and it truly drove there, give or take the simulated NEO-5's slowly varying error
    # (metres: CEP50 2.5 m, a few metres of bias over a mission).
    _e, north_m, _h, _v = world.truth()
    assert 10.0 < north_m < 30.0
    assert d.motors is not None and d.motors.direct_sent > 0  # fixes' commands sent directly
    assert d.motors.link_errors == 0
