"""Manual drive belongs to the client whose drive started it (outside audit, round 7, item 2).

The audit's two pages, one holding forward and one holding left, had the motors switch
between 40/40 and -28/28 18-37 times in 4-5 s, and neither page was told: every client's
``drive`` replaced the last one. Now the drive of another client is refused (``rejected``,
reason ``busy``, naming who drives and for how long its drive holds) while the owner's drive
runs; the owner's dead-man expiry, any ``stop`` (from anyone) or the owner's disconnection
ends the ownership, and the next drive from anyone takes it. ``status`` says who drives.

Item 3: a held drive (resent ~3 times a second) no longer logs a line per resend."""

from __future__ import annotations

import io
import logging
import threading
import time
from pathlib import Path
from typing import Any

import pytest

from tests.test_daemon import hil_config, run_daemon, wait_for
from tests.test_loop import Loop
from tests.test_server import loop_thread
from x6wd.app.client import EXIT_REFUSED, RemoteClient, RequestFailed, _hold_drive, render_status
from x6wd.app.daemon import Daemon

__all__ = ["loop_thread", "run_daemon"]  # the fixtures, imported for pytest

A_DRIVE = (40.0, 40.0)
B_DRIVE = (-28.0, 28.0)


def _name(c: RemoteClient) -> str:
    """How the robot names this client's connection ("host:port" of its end)."""
    assert c._sock is not None
    host, port = c._sock.getsockname()[:2]
    return f"{host}:{port}"


def _drive(c: RemoteClient, pct: tuple[float, float], duration_s: float = 2.0) -> dict:
    return c.request("drive", left=pct[0], right=pct[1], duration_s=duration_s)


def _refused_busy(c: RemoteClient, pct: tuple[float, float], owner: str) -> RequestFailed:
    with pytest.raises(RequestFailed) as ei:
        _drive(c, pct)
    err = ei.value
    assert (err.code, err.reason) == ("rejected", "busy"), err
    assert owner in err.message and "another client" in err.message, err.message
    assert " s" in err.message and "stop" in err.message, err.message  # how long; the way out
    return err


@pytest.fixture
def patient_sim_motors(monkeypatch: pytest.MonkeyPatch) -> None:
    """The simulated motor board's link waits 1 s for an acknowledgement, not 0.1 s: on a
    loaded host its board thread answered late twice in a row, the link was lost and A's
    drive refused (``motor link lost``), which is not what these tests are about."""
    from drivers import motors

    class PatientLink(motors.SerialMotorLink):
        def __init__(self, port: Any, **kw: Any) -> None:
            kw["ack_timeout_s"] = max(1.0, kw.get("ack_timeout_s", 0.1))
            super().__init__(port, **kw)

    monkeypatch.setattr(motors, "SerialMotorLink", PatientLink)


@pytest.mark.usefixtures("patient_sim_motors")
def test_a_drive_from_another_client_is_refused_while_the_owners_drive_holds(
    tmp_path: Path, run_daemon
) -> None:
    r = run_daemon(Daemon(hil_config(tmp_path)))
    world = r.daemon.devices.backend("sim")  # the world the daemon's sim:// devices share

    def motors() -> tuple[float, float]:
        return tuple(world.vehicle.command_pct)

    with RemoteClient("127.0.0.1", r.port) as a, RemoteClient("127.0.0.1", r.port) as b:
        a_name, b_name = _name(a), _name(b)
        # drives of manual_max_s (5 s), not 2 s: a loaded host's stall between two requests
        # does not end one before the checks that follow it
        _drive(a, A_DRIVE, 5.0)
        wait_for(lambda: motors() == A_DRIVE, 3, "A's drive reaches the motors")
        err = _refused_busy(b, B_DRIVE, a_name)
        assert "holds for" in err.message
        st = b.request("status")
        assert st["mode"] == "MANUAL"
        md = st["manual_drive"]
        assert md["owner"] == a_name and md["yours"] is False and 0.0 < md["holds_s"] <= 5.0
        assert a.request("status")["manual_drive"]["yours"] is True

        # the audit's fight: both hold their key (each resends every 0.1 s), 15 times each
        # (a count, not a wall-clock window a loaded host fills with fewer): the motors
        # never take B's command, and each of B's drives is refused as busy. A's
        # drives hold 5 s, so a host stall of a loop pass does not end A's ownership (2 s
        # did once beside busy loops: B's drive was taken); a
        # starved keep-alive may let the board's own watchdog stop the motors (0, 0; seen
        # under load), which is not B driving
        seen: set[tuple[float, float]] = set()
        done = threading.Event()

        def sample() -> None:
            while not done.is_set():
                seen.add(motors())
                time.sleep(0.005)

        sampler = threading.Thread(target=sample, daemon=True)
        sampler.start()
        refused = 0
        try:
            for _ in range(15):
                _drive(a, A_DRIVE, 5.0)
                try:
                    _drive(b, B_DRIVE, 0.5)
                except RequestFailed as exc:
                    assert exc.reason == "busy", exc
                    refused += 1
                time.sleep(0.1)
        finally:
            done.set()
            sampler.join(2)
        assert A_DRIVE in seen and seen <= {A_DRIVE, (0.0, 0.0)}, seen
        assert refused >= 5

        # any stop (B's here) is obeyed at once and ends A's ownership: B's drive then takes it
        b.request("stop")
        wait_for(lambda: motors() == (0.0, 0.0), 3, "B's stop reaches the motors")
        assert b.request("status")["manual_drive"] is None
        _drive(b, B_DRIVE, 5.0)
        wait_for(lambda: motors() == B_DRIVE, 3, "B's drive reaches the motors")
        assert a.request("status")["manual_drive"]["owner"] == b_name
        _refused_busy(a, A_DRIVE, b_name)
        assert motors() == B_DRIVE

        # the owner's own stop ends it too
        b.request("stop")
        wait_for(lambda: motors() == (0.0, 0.0), 3, "B's own stop")
        _drive(a, A_DRIVE, 1.0)  # (0.4 s: a starved poll could miss the whole drive)
        wait_for(lambda: motors() == A_DRIVE, 3, "A drives again")

        # the owner's dead-man expiry ends it: then B's drive is taken
        wait_for(lambda: a.request("status")["mode"] == "IDLE", 5, "A's drive expires")
        # (the control port's deadline for it is the robot's, give or take its reply's trip;
        # 3 s is a loaded host's slack: an ownership that outlived its drive never ends)
        wait_for(lambda: a.request("status")["manual_drive"] is None, 3, "A's ownership ends")
        _drive(b, B_DRIVE)
        wait_for(lambda: motors() == B_DRIVE, 3, "B drives after A's expiry")

    assert r.stop() == 0


def test_the_owners_disconnection_ends_its_drive_and_the_next_drive_takes_it(
    tmp_path: Path, run_daemon
) -> None:
    r = run_daemon(Daemon(hil_config(tmp_path)))
    world = r.daemon.devices.backend("sim")
    with RemoteClient("127.0.0.1", r.port) as b:
        a = RemoteClient("127.0.0.1", r.port)
        try:
            a_name = _name(a)
            _drive(a, A_DRIVE, 5.0)
            wait_for(lambda: tuple(world.vehicle.command_pct) == A_DRIVE, 3, "A drives")
            _refused_busy(b, B_DRIVE, a_name)
        finally:
            a.close()  # A goes away while its drive runs: the dead-man stops the motors
        wait_for(lambda: b.request("status")["mode"] == "IDLE", 3, "A's dead-man stop")
        _drive(b, B_DRIVE)
        wait_for(lambda: tuple(world.vehicle.command_pct) == B_DRIVE, 3, "B drives")
        assert b.request("status")["manual_drive"]["owner"] == _name(b)
    assert r.stop() == 0


@pytest.mark.usefixtures("patient_sim_motors")
def test_x6wd_client_drive_says_so_when_another_client_drives_after_a_stop(
    tmp_path: Path, run_daemon
) -> None:
    """``x6wd client drive`` holds its connection while its drive runs and asks ``status``:
    a stop then another client's drive left the robot in MANUAL, which it took for its own
    drive running on. Now status says whose drive it is; and ``status`` prints who drives."""
    r = run_daemon(Daemon(hil_config(tmp_path)))
    err = io.StringIO()
    with (
        RemoteClient("127.0.0.1", r.port) as a,
        RemoteClient("127.0.0.1", r.port) as b,
        RemoteClient("127.0.0.1", r.port) as c,
    ):
        reply = _drive(a, A_DRIVE, 3.0)
        # B stops and drives, then A's holder starts (its first status 0.5 s later): started
        # first, a loaded host could let its status fall between B's stop and B's drive
        b.request("stop")
        _drive(b, B_DRIVE, 3.0)
        result: list[int | None] = []
        holder = threading.Thread(target=lambda: result.append(_hold_drive(a, reply, err)))
        holder.start()
        # another client's view (A's connection is the holder's: a request of this thread
        # on it could have its reply read, and dropped, by the holder's)
        shown = render_status(c.request("status"))
        holder.join(5)
        assert result == [EXIT_REFUSED], err.getvalue()
        assert f"the robot is driven by another client ({_name(b)})" in err.getvalue()
        assert f"driving    by {_name(b)}, " in shown
        assert "driving    by this connection, " in render_status(b.request("status"))
    assert r.stop() == 0


def test_a_held_drive_is_logged_once_per_press_not_per_resend(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """A page resends a held drive ~3 times a second: that was a log line each (10,800 an
    hour of holding). Now: the press's first drive, a change of speeds (at most one line a
    second), and the press's end (the state change's line)."""
    lp = Loop()
    with caplog.at_level(logging.INFO, logger="x6wd.loop.runner"):
        for i in range(30):  # 10 s held, resent every 0.33 s
            lp.now = i / 3.0
            lp.runner.drive(40.0, 40.0, 0.5)
        lp.now = 10.5
        lp.runner.tick()  # the last resend's dead-man expires: the press ended
        for i in range(6):  # a second press, turning half-way through (two changes in 0.3 s)
            lp.now = 20.0 + i / 3.0
            pct = (40.0, 40.0) if i < 3 else (-28.0, 28.0) if i < 5 else (-30.0, 30.0)
            lp.runner.drive(*pct, 0.5)
        lp.now = 30.0
        lp.runner.stop()
    said = [r.getMessage() for r in caplog.records if r.name == "x6wd.loop.runner"]
    drives = [m for m in said if m.startswith("operator: drive")]
    assert drives == [
        "operator: drive L+40 R+40 for 0.5 s",
        "operator: drive L+40 R+40 for 0.5 s",
        "operator: drive L-28 R+28 for 0.5 s (changed while driving)",
    ], drives
    ends = [m for m in said if m.startswith("state MANUAL -> IDLE")]
    assert ends == [  # the end names the press's last speeds (-30/30: only counted above)
        "state MANUAL -> IDLE mode: manual drive expired (last drive L+40 R+40)",
        "state MANUAL -> IDLE mode: stop (last drive L-30 R+30)",
    ]


def test_a_drive_the_robot_ended_itself_no_longer_holds_off_another_clients_drive(
    tmp_path: Path, run_daemon
) -> None:
    """Review of a1a7005: the owner's drive ended by the robot (its motor link lost: the
    controller stops the manual drive) kept every other client refused ``busy`` until the
    drive's deadline (up to manual_max_s, 60 s configurable), naming an owner that no longer
    drove (or whose connection was dead, half-open). Now another client's drive is taken at
    once, while the owner is still connected and its deadline far off."""
    import dataclasses

    from tests.test_daemon import BoardOnPty

    cfg = hil_config(tmp_path)
    with BoardOnPty() as pb:
        cfg = dataclasses.replace(
            cfg,
            motors=dataclasses.replace(cfg.motors, url=pb.url),
            safety=dataclasses.replace(cfg.safety, manual_max_s=60.0),
        )
        r = run_daemon(Daemon(cfg))
        with RemoteClient("127.0.0.1", r.port) as a, RemoteClient("127.0.0.1", r.port) as b:
            a_name, b_name = _name(a), _name(b)
            _drive(a, A_DRIVE, 30.0)
            wait_for(lambda: pb.board.running, 5, "A's drive reaches the board")
            _refused_busy(b, B_DRIVE, a_name)  # the robot drives A's: refused, as before
            pb.halt()  # the board dies: the controller ends A's drive
            wait_for(lambda: b.request("status")["mode"] == "IDLE", 10, "the robot stops")
            pb.serve()  # it comes back: the robot could drive again
            wait_for(lambda: b.request("status")["links"]["motors"] != "lost", 10, "the link is up")
            assert a.request("status")["mode"] == "IDLE"  # A connected, its 30 s not run out
            t0 = time.monotonic()

            def taken() -> bool:  # was: refused busy, naming A, for up to 30 s more
                try:  # (a control loop slower than OWNER_CHECK_S: the next try takes it)
                    _drive(b, B_DRIVE, 2.0)
                except RequestFailed as exc:
                    assert exc.reason == "busy", exc
                    return False
                return True

            # at once, give or take a loaded host's round trips (10 s); the bug: 30 s more
            wait_for(taken, 10.0, "B's drive taken")
            assert time.monotonic() - t0 < 10.0
            st = a.request("status")
            assert st["mode"] == "MANUAL" and st["manual_drive"]["owner"] == b_name, st
            wait_for(lambda: pb.board.running, 5, "B's drive reaches the board")
            _refused_busy(a, A_DRIVE, b_name)  # B owns it now, as any owner
        assert r.stop() == 0


def test_a_busy_control_loop_does_not_hold_a_non_owners_stop(loop_thread: Any) -> None:
    """review of 97faaf1: before refusing another client's drive the server asks the
    robot's mode; that question waited for a busy control loop without limit, and the
    refused client's next line, its stop, waited behind it (2 s in the review). The
    question is now bounded (OWNER_CHECK_S) and shared with the status requests."""
    import asyncio
    import socket

    from tests.test_server import RecordingBackend, start_server
    from x6wd.app.server import OWNER_CHECK_S

    class SlowLoop(RecordingBackend):
        t_stop: float | None = None
        status_calls = 0

        def status(self):  # type: ignore[no-untyped-def]
            self.status_calls += 1
            mode = super().status()

            async def late() -> dict:  # type: ignore[type-arg]
                await asyncio.sleep(2.0)  # the control loop busy, its lock held
                return mode

            return late()

        def stop(self):  # type: ignore[no-untyped-def]
            self.t_stop = time.monotonic()
            return super().stop()

    backend = SlowLoop()
    srv = start_server(loop_thread, backend)
    try:
        a = socket.create_connection(("127.0.0.1", srv.port), 5)
        b = socket.create_connection(("127.0.0.1", srv.port), 5)
        a.sendall(b'{"id":1,"cmd":"drive","left":40,"right":40,"duration_s":30}\n')
        assert b'"ok":true' in a.makefile("rb").readline()
        t0 = time.monotonic()
        b.sendall(
            b'{"id":2,"cmd":"drive","left":-30,"right":30,"duration_s":1}\n{"id":3,"cmd":"stop"}\n'
        )
        rb = b.makefile("rb")
        first, second = rb.readline(), rb.readline()
        assert b'"busy"' in first, first  # the owner's drive still holds (no answer in time)
        assert b'"ok":true' in second, second
        assert backend.t_stop is not None and backend.t_stop - t0 < OWNER_CHECK_S + 0.4
        a.close()
        b.close()
    finally:
        loop_thread.run(srv.close())
