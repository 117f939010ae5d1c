"""Operator findings of the outside audit, round 6 (HIL daemon on a 15 m geofence, and the
command-line client):

1. outside the fence a paused return to launch could not be resumed, and the refusal of a
   paused mission's resume said "drive it back by hand", which the paused mission refuses
   (only a second `return` worked, and nothing said so; at the fence's edge only stop+start);
2. `x6wd client load --wp -33.8,151.2` was "expected one argument" (argparse took the
   southern latitude for an option), and so was a drive speed like `-1e1`;
3. a long recorded track was refused as "request line longer than 65536 bytes", naming no
   waypoint count;
4. `resume` with nothing paused got the geofence's refusal instead of "nothing to resume",
   and a distance rounded to whole metres read "15 m from the geofence centre; limit 15 m".

The runner with its real controller on a simulated clock (tests/test_loop.py's Loop), the
whole daemon (``sim://`` devices, real time) over TCP, and the client as a subprocess against
a real server.
"""

from __future__ import annotations

import re
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import pytest

from tests.test_daemon import hil_config, run_daemon, wait_for
from tests.test_lockout import lt
from tests.test_loop import HOME, M_PER_DEG_LAT, Loop, north
from tests.test_server import LoopThread, RecordingBackend, start_server
from x6wd.app.client import RemoteClient, RequestFailed
from x6wd.app.daemon import Daemon
from x6wd.core.config import SafetyConfig
from x6wd.core.errors import CommandError
from x6wd.core.geodesy import great_circle_m
from x6wd.core.mission_files import Waypoint
from x6wd.core.records import Mode
from x6wd.nav.controller import CommandRejected

__all__ = ["lt", "run_daemon"]  # fixtures, shared with test_lockout and test_daemon

FENCE_M = 15.0


def fenced() -> Loop:
    return Loop(SafetyConfig(geofence_radius_m=FENCE_M))


def at(lp: Loop, t_s: float, north_m: float) -> None:
    """A compass sample and a fix ``north_m`` north of home at ``t_s``."""
    lp.now = t_s
    lp.compass(0.0)
    lp.fix(north_m)


def refusal(lp: Loop, cmd: str) -> CommandError:
    with pytest.raises(CommandError) as exc:
        lp.runner.command(cmd)
    return exc.value


def paused_by_the_fence(north_m: float) -> Loop:
    """A mission towards the fence's edge, paused by a geofence breach ``north_m`` out."""
    lp = fenced()
    lp.start_mission(north(14.6))
    at(lp, 1.0, 10.0)
    assert lp.runner.controller.mode == Mode.RUNNING
    at(lp, 2.0, north_m)
    assert lp.runner.controller.mode == Mode.PAUSED and lp.runner.geofence_breaches == 1
    return lp


# -- 1: a paused return resumes outside the fence; a paused mission names the ways back --------
def test_a_paused_return_to_launch_resumes_outside_the_fence() -> None:
    """s21: driven by hand 19 m out, `return`, `pause`, `resume`: the return goes on."""
    lp = fenced()
    lp.start_mission(north(10.0))  # the launch point: home
    lp.runner.command("stop")
    lp.runner.drive(60.0, 60.0, 5.0)  # by hand, out of the fence
    at(lp, 1.0, 8.0)
    at(lp, 2.0, 19.0)
    lp.runner.command("stop")
    assert lp.runner.command("return")["mode"] == "RUNNING"
    at(lp, 3.0, 19.0)
    assert lp.runner.command("pause")["mode"] == "PAUSED"
    assert lp.runner.controller.returning == "return"
    assert lp.runner.command("resume")["mode"] == "RUNNING"  # was: geofence refusal
    assert lp.runner.controller.returning == "return"
    at(lp, 4.0, 18.5)  # still outside: a return is not stopped by the fence
    assert lp.runner.controller.mode == Mode.RUNNING and lp.runner.geofence_breaches == 0
    assert not lp.motors[-1].is_stop


def test_a_paused_mission_outside_stays_paused_and_the_refusal_names_the_ways_back() -> None:
    """s17: a geofence hold at the fence's edge. Resuming the mission stays refused (its leg
    may lead on outwards, and the next fix would pause it again); the message names what the
    robot accepts there, and each of those works."""
    lp = paused_by_the_fence(15.04)
    err = refusal(lp, "resume")
    assert err.code == "geofence"
    msg = str(err)
    assert msg.startswith("cannot resume: the robot is 15.04 m from the geofence centre; limit")
    assert "'return' (to the launch point, 15.0 m away, inside the fence" in msg
    assert "'stop', then drive it back by hand ('drive') and 'start' the mission again" in msg
    assert lp.runner.controller.mode == Mode.PAUSED  # nothing changed
    # 'drive' alone is refused while paused: which is why the message does not offer it
    with pytest.raises(CommandRejected, match="stop the mission first"):
        lp.runner.drive(-30.0, -30.0, 2.0)
    # way 1: return (and it may be paused and resumed out here too)
    assert lp.runner.command("return")["mode"] == "RUNNING"
    assert lp.runner.controller.returning == "return"
    lp.runner.command("pause")
    assert lp.runner.command("resume")["mode"] == "RUNNING"
    # way 2: stop, then drive back by hand
    lp = paused_by_the_fence(15.04)
    lp.runner.command("stop")
    lp.runner.drive(-30.0, -30.0, 2.0)
    assert lp.runner.controller.mode == Mode.MANUAL


def test_without_a_launch_point_inside_the_fence_return_is_not_offered() -> None:
    lp = paused_by_the_fence(16.0)
    lp.runner.controller._launch = (HOME[0] + 20.0 / M_PER_DEG_LAT, HOME[1])  # outside
    msg = str(refusal(lp, "resume"))
    assert "'return'" not in msg and "'stop', then drive it back by hand ('drive')" in msg


# -- 4: the controller's own reasons first; distances that show the breach -------------------
def test_resume_or_start_the_controller_refuses_says_why_not_the_fence() -> None:
    lp = fenced()
    lp.fix()  # the fence's centre
    at(lp, 1.0, 19.0)  # carried out of the fence, nothing loaded
    with pytest.raises(CommandRejected, match=r"^no mission loaded$"):
        lp.runner.command("start")
    with pytest.raises(CommandRejected, match=r"^nothing to resume: mode is IDLE$"):
        lp.runner.command("resume")
    lp.runner.load_mission([north(10.0)])
    with pytest.raises(CommandRejected, match=r"^nothing to resume: mode is IDLE$"):
        lp.runner.command("resume")
    err = refusal(lp, "start")  # a mission to start: the fence is the reason now
    assert err.code == "geofence"
    assert str(err) == (
        "cannot start: the robot is 19 m from the geofence centre; limit 15 m "
        "(drive it back by hand: 'drive')"
    )
    lp.runner.drive(-30.0, -30.0, 2.0)  # which is allowed
    # a paused mission outside: start says "resume it, or stop" (the controller's reason)
    lp = paused_by_the_fence(15.5)
    with pytest.raises(CommandRejected, match=r"^mission paused"):
        lp.runner.command("start")


def number_before_m(text: str, what: str) -> float:
    m = re.search(r"(\d+(?:\.\d+)?) m " + what, text)
    assert m, text
    return float(m.group(1))


@pytest.mark.parametrize("north_m", [15.004, 15.04, 15.4])
def test_the_distance_in_a_refusal_reads_beyond_the_limit(north_m: float) -> None:
    lp = fenced()
    lp.fix()
    at(lp, 1.0, north_m)
    lp.runner.load_mission([north(10.0)])
    d = great_circle_m(*HOME, HOME[0] + north_m / M_PER_DEG_LAT, HOME[1])
    shown = number_before_m(str(refusal(lp, "start")), "from the geofence centre; limit 15 m")
    assert shown > FENCE_M and abs(shown - d) < 0.5
    with pytest.raises(CommandError) as exc:  # a waypoint just outside, at load
        lp.runner.load_mission([north(north_m)])
    shown = number_before_m(str(exc.value), "from the geofence centre; limit 15 m")
    assert shown > FENCE_M and abs(shown - d) < 0.5


def test_the_breach_in_the_log_reads_beyond_the_limit(caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level("WARNING", logger="x6wd.loop.runner")
    paused_by_the_fence(15.04)
    (line,) = [r.getMessage() for r in caplog.records if "geofence breach:" in r.getMessage()]
    assert number_before_m(line, "from the centre, limit 15 m") > FENCE_M


# -- 1, the whole daemon: s21 over TCP, in real time ---------------------------------------
@pytest.mark.integration
def test_the_daemon_resumes_a_paused_return_outside_the_fence(tmp_path: Path, run_daemon) -> None:
    radius_m = 5.0
    cfg = hil_config(tmp_path, safety=SafetyConfig(geofence_radius_m=radius_m))
    r = run_daemon(Daemon(cfg))
    with RemoteClient("127.0.0.1", r.port) as c:

        def out_m() -> float:
            tel = c.request("status")["telemetry"] or {}
            centre = r.daemon.runner.geofence_centre() if r.daemon.runner else None
            if centre is None or tel.get("lat_deg") is None:
                return 0.0
            return great_circle_m(*centre, tel["lat_deg"], tel["lon_deg"])

        wait_for(lambda: r.daemon.first_fix and c.request("status")["telemetry"], 15, "a fix")
        wait_for(lambda: c.request("status")["mode"] == "IDLE", 5, "idle")
        lat, lon = r.daemon.first_fix
        c.request("mission.load", waypoints=[[lat + 3.0 / M_PER_DEG_LAT, lon]])
        c.request("start")  # the launch point: here, inside
        c.request("stop")
        t0 = time.monotonic()
        while out_m() < radius_m + 4.0:  # by hand, out of the fence
            assert time.monotonic() - t0 < 20, f"still {out_m():.1f} m from the centre"
            c.request("drive", left=60, right=60, duration_s=1.0)
            time.sleep(0.3)
        c.request("stop")
        with pytest.raises(RequestFailed) as ei:
            c.request("resume")
        assert (ei.value.code, ei.value.message) == ("rejected", "nothing to resume: mode is IDLE")
        assert c.request("return")["mode"] == "RUNNING"
        time.sleep(0.5)
        assert c.request("pause")["mode"] == "PAUSED"
        assert c.request("resume")["mode"] == "RUNNING"  # was: geofence refusal
        st = c.request("status")
        assert st["telemetry"]["extra"].get("returning") == "return"
        t1 = time.monotonic()
        while (mode := c.request("status")["mode"]) == "RUNNING" and time.monotonic() - t1 < 40:
            time.sleep(0.2)
        assert mode == "DONE" and out_m() < radius_m, (mode, out_m())
        assert r.daemon.runner.geofence_breaches == 0


# -- 2 and 3: the client --------------------------------------------------------------------
def x6wd_client(port: int, *args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "x6wd", "client", "--port", str(port), *args],
        capture_output=True,
        text=True,
        timeout=60,
    )


def test_negative_coordinates_and_speeds_need_no_equals_sign(lt: LoopThread) -> None:
    backend = RecordingBackend()
    srv = start_server(lt, backend)
    try:
        r = x6wd_client(srv.port, "load", "--wp", "-33.8,151.2", "--wp", "-33.81,-151.2")
        assert r.returncode == 0, r.stderr
        r = x6wd_client(srv.port, "load", "--wp", "-.5,-0.5")
        assert r.returncode == 0, r.stderr
        r = x6wd_client(srv.port, "drive", "-1e1", "-.5", "0.2")
        assert r.returncode == 0, r.stderr
        r = x6wd_client(srv.port, "load", "--wp", "-33.8;151.2")  # still checked
        assert r.returncode == 2 and "LAT,LON" in r.stderr, r.stderr
    finally:
        lt.run(srv.close())
    assert backend.calls == [
        ("load_mission", [Waypoint(-33.8, 151.2), Waypoint(-33.81, -151.2)]),
        ("load_mission", [Waypoint(-0.5, -0.5)]),
        ("drive", (-10.0, -0.5, 0.2)),
    ]


def track(path: Path, n: int) -> Path:
    """A recorded track of ``n`` points, 7 decimals (the audit's p2800.csv)."""
    rows = [f"{51.752 + i * 2e-7:.7f},{-1.2575549:.7f}" for i in range(n)]
    path.write_text("lat,lon\n" + "\n".join(rows) + "\n")
    return path


def test_a_track_longer_than_the_robot_reads_is_refused_before_sending(
    lt: LoopThread, tmp_path: Path
) -> None:
    long = track(tmp_path / "p2800.csv", 2800)
    backend = RecordingBackend()
    srv = start_server(lt, backend)
    try:
        r = x6wd_client(srv.port, "load", str(long))
        assert r.returncode == 2, r.stderr
        said = r.stderr
        assert "the mission has 2800 waypoints" in said and "at most 65536 bytes" in said, said
        assert "[server] max_line_bytes" in said and "--max-line-bytes" in said, said
        fit = int(re.search(r"about (\d+) waypoints", said).group(1))  # type: ignore[union-attr]
        assert 2600 < fit < 2800
        assert backend.calls == [] and lt.call(lambda: srv.requests_total) == 0  # never sent
        # as many as it says fit do go
        r = x6wd_client(srv.port, "load", str(track(tmp_path / "fit.csv", fit)))
        assert r.returncode == 0, r.stderr
    finally:
        lt.run(srv.close())
    # a robot whose limit is raised takes it, given the same value
    big = RecordingBackend()
    srv = start_server(lt, big, max_line_bytes=200_000)
    try:
        r = x6wd_client(srv.port, "load", "--max-line-bytes", "200000", str(long))
        assert r.returncode == 0, r.stderr
    finally:
        lt.run(srv.close())
    loads: list[Any] = [arg for name, arg in big.calls if name == "load_mission"]
    assert len(loads) == 1 and len(loads[0]) == 2800


def test_a_robot_that_reads_less_gets_its_refusal_explained(lt: LoopThread, tmp_path: Path) -> None:
    backend = RecordingBackend()
    srv = start_server(lt, backend, max_line_bytes=4096)
    try:
        r = x6wd_client(srv.port, "load", str(track(tmp_path / "p300.csv", 300)))
        assert r.returncode == 1, r.stderr
        said = r.stderr
        assert "bad_request (line_too_long): request line longer than 4096 bytes" in said, said
        assert "the mission has 300 waypoints" in said and "at most 4096 bytes" in said, said
        assert backend.calls == []
    finally:
        lt.run(srv.close())
