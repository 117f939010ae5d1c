"""Failsafes while the robot dead-reckons through a GPS outage (an outside audit): the
wheels' stuck test without a fix, the time bound of a drive without one, dead encoders
named as such, the geofence checked on the estimate. Fast-time missions reuse the harness
of tests/test_failsafe_sim.py; the rest drive the controller with real records."""

from __future__ import annotations

import logging
import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from sim_backend.geodesy import enu_to_lla
from sim_backend.world import loads_world
from tests.test_controller import NAV, SAFETY, at, att, fix
from tests.test_failsafe_controller import COUNTS_PER_M, FS, feed, started
from tests.test_failsafe_sim import LONG_LEG, ORIGIN, STUCK_S, _mission, _outside, _world
from x6wd.core.config import NavigationConfig
from x6wd.core.geodesy import great_circle_m
from x6wd.core.records import Mode, NavState, WheelOdometry
from x6wd.nav import controller as controller_module
from x6wd.nav.controller import DEAD_RECKONING_COMMANDED, DEAD_RECKONING_MIN_SPEED, Controller

OUTAGE_FROM_S = 8.0


def _outage(start_s: float, duration_s: float) -> str:
    return f'[[effects]]\nname = "outage"\nstart_s = {start_s}\nduration_s = {duration_s}\n'


@pytest.mark.parametrize(
    ("block_after_s", "why", "within_s"),
    [
        (1.0, "stuck (the wheels: no motion in 10 s of driving)", (STUCK_S - 1.0, STUCK_S + 1.0)),
        (
            4.0,
            "stuck (the wheels: no motion in 8 s of driving, 30 m commanded without a fix)",
            (0.5 * STUCK_S, STUCK_S),
        ),
    ],
    ids=["wheels-test", "commanded-bound"],
)
def test_a_robot_blocked_in_a_gps_outage_pauses_on_its_wheels(
    tmp_path: Path, block_after_s: float, why: str, within_s: tuple[float, float]
) -> None:
    """Blocked early in a long outage: its wheels add no travel, so the outage never became
    a hold and the motors ran at 60 % until the fix came back. The wheels' test needs no
    fix: paused within stuck_s. Blocked 4 s in (about 9 m driven), the commanded travel
    (2.33 m/s) reaches its 30 m bound 8 s after the block, before the wheels' test: the
    hold it would bring is named for the wheels instead (a pause, stuck_action), not left
    to say "no valid fix" 30 s later."""
    block_s = OUTAGE_FROM_S + block_after_s
    world = _world(
        60.0,
        vehicle=f'stuck_from_s = {block_s}\nstuck_mode = "blocked"',
        waypoints=LONG_LEG,
        extra=_outage(OUTAGE_FROM_S, 500.0) + "[safety]\ngps_outage_max_m = 20.0\n",
    )
    run = _mission(tmp_path, world)
    # dead-reckoning, no hold, when it blocked and until the pause
    assert not any(s["new"] == "HOLD" for s in run.states if s["t_s"] > 1.0), run.states
    paused = run.first("PAUSED", f"failsafe: {why}")
    assert block_s + within_s[0] <= paused["t_s"] <= block_s + within_s[1]
    assert run.mode_changes()[-1][1] == "PAUSED"
    motors = [m for m in run.of("motor") if m["t_s"] >= paused["t_s"]]
    assert motors and all(m["left_pct"] == m["right_pct"] == 0.0 for m in motors)
    assert [w for _t, w in run.summary.extra["failsafes"]] == [why]


def test_a_drive_without_a_fix_is_bounded_in_time_as_well_as_in_wheel_travel(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Wheels that count 5 cm/s while driven at 60 % (a miscounting encoder): enough for the
    stuck test (0.2 m in 10 s), 20 m of travel only after 400 s. The bound on commanded
    travel (tested below) would end this drive after 30 m; lifted, the time limit, the last
    backstop, holds once the slowest drive at half its nominal speed would have covered 20 m."""
    monkeypatch.setattr(controller_module, "DEAD_RECKONING_COMMANDED", math.inf)
    nav = NavigationConfig()
    safety = replace(SAFETY, gps_outage_max_m=20.0)
    c = Controller(nav, safety, 3.0, failsafe=FS)
    c.on_fix(fix(0.0))
    for k in range(1, 21):
        c.on_attitude(att(0.05 * k, 357.0))  # 357 magnetic + 3 declination = north
    c.load_mission([at(0.0, 900.0)], 1.0)
    c.start(1.0)
    last_fix_s = 5.0
    limit_s = 20.0 / (DEAD_RECKONING_MIN_SPEED * nav.full_speed_mps * nav.min_speed_pct / 100)
    assert limit_s == pytest.approx(68.6, abs=0.1)
    t_hold = None
    for k in range(1, 2001):  # encoders and compass at 10 Hz, fixes at 1 Hz until 5 s
        t = 1.0 + 0.1 * k
        counts = round(0.005 * k * COUNTS_PER_M)
        c.on_odometry(WheelOdometry(t, counts, counts, k))
        c.on_attitude(att(t, 357.0))
        if k % 10 == 0:
            c.on_fix(fix(t, 0.0, 0.005 * k) if t <= last_fix_s + 1e-9 else fix(t, valid=False))
        assert c.mode == Mode.RUNNING, c.telemetry.extra.get("failsafe")
        if c.state == NavState.HOLD:
            t_hold = t
            break
    assert t_hold is not None, "never held: the drive without a fix has no time bound"
    assert c.telemetry.hold_reason == "no valid fix" and c.command.is_stop
    assert t_hold == pytest.approx(last_fix_s + limit_s, abs=0.15)
    assert math.isclose(c.telemetry.left_pct, 0.0)


@pytest.mark.parametrize(
    ("counts_per_rev", "lo_m", "hi_m"),
    [(1632, 18.0, 22.0), (408, 28.0, 32.0), (196, 28.0, 32.0)],
    ids=["healthy", "25%", "12%"],
)
def test_a_drive_without_a_fix_is_bounded_by_its_commanded_travel(
    tmp_path: Path, counts_per_rev: int, lo_m: float, hi_m: float
) -> None:
    """Encoders counting a quarter or an eighth of the travel (408 or 196 counts a wheel
    turn where the robot's config expects 1632), the GPS out from 8 s on a 300 m leg:
    20 m counted took 80-160 m of real driving (an outside audit: 44-79 m, 135-158 m blind).
    The commanded travel (cruise 60 %: 2.33 m/s) ends the drive after 1.5 x 20 m; healthy
    encoders end it on their counted 20 m as before."""
    world = _world(
        45.0,
        waypoints="[[0.0, 300.0]]",
        extra=_outage(OUTAGE_FROM_S, 500.0)
        + f"[encoders]\ncounts_per_rev = {counts_per_rev}\n[safety]\ngps_outage_max_m = 20.0\n",
    )
    run = _mission(tmp_path, world)
    last_fix_s = max(f["t_s"] for f in run.of("fix") if f["valid"])
    assert last_fix_s < OUTAGE_FROM_S + 0.5
    hold = run.first("HOLD", "no valid fix")
    k = (run.t >= last_fix_s) & (run.t <= hold["t_s"] + 2.0)
    driven_m = float(np.sum(np.hypot(np.diff(run.east[k]), np.diff(run.north[k]))))
    assert lo_m <= driven_m <= hi_m, driven_m
    assert run.moved_after(hold["t_s"] + 2.0) < 0.05
    assert DEAD_RECKONING_COMMANDED * 20.0 == 30.0


# ------------------------------------------------------------------- dead encoders


def test_dead_encoders_are_named_as_such_not_a_block(tmp_path: Path) -> None:
    """Encoders counting once a wheel turn (the robot's config expects 1632): the wheels'
    test stops the robot, as it must (no odometry), but the fixes show it drove about 23 m
    in those 10 s, so the reason names the encoders, not a block."""
    world = _world(30.0, waypoints=LONG_LEG, extra="[encoders]\ncounts_per_rev = 1\n")
    run = _mission(tmp_path, world)
    why = "encoders: under 0.2 m counted in 10 s of driving while the fixes show motion"
    paused = run.first("PAUSED", f"failsafe: {why}")
    assert paused["t_s"] <= STUCK_S + 1.5
    assert [w for _t, w in run.summary.extra["failsafes"]] == [why]
    assert not any("stuck" in r for _t, _n, r in run.mode_changes())
    motors = [m for m in run.of("motor") if m["t_s"] >= paused["t_s"]]
    assert motors and all(m["left_pct"] == m["right_pct"] == 0.0 for m in motors)


def test_a_blocked_robot_whose_fix_lags_and_wanders_is_still_blocked() -> None:
    """Blocked: the wheels count nothing. The fixes move the body's anchor on twice in the
    first seconds (the receiver's lag behind the last metres driven) and once more later
    (wander): not the strong evidence that names the encoders."""
    c = started()
    ys = {1: 2.5, 2: 5.0, 7: 7.5}  # metres north of the start, from t = 1, 2 and 7 s
    y = 0.0
    for k in range(1, 16):
        y = ys.get(k, y)
        feed(c, float(k), y, counts=0)
        if c.mode != Mode.RUNNING:
            break
    assert c.mode == Mode.PAUSED and c.command.is_stop
    assert c.telemetry.extra["failsafe"] == "stuck (the wheels: no motion in 10 s of driving)"


def test_a_blocked_robot_whose_fixes_hop_about_is_still_blocked() -> None:
    """Blocked, the wheels count nothing, and the fixes hop 2.5-3.5 m back and forth in the
    second half of the 10 s (a second outside audit: a wandering or jumping GPS, a robot
    against a building's wall): the anchor moved on three times, which named the encoders.
    Their net move ahead is within the GPS's noise: a block."""
    c = started()
    ys = {6: 2.5, 7: 0.0, 8: 3.5, 9: 0.5}
    for k in range(1, 16):
        feed(c, float(k), ys.get(k, 0.5 if k > 9 else 0.0), counts=0)
        if c.mode != Mode.RUNNING:
            break
    assert c.mode == Mode.PAUSED and c.command.is_stop
    assert c.telemetry.extra["failsafe"] == "stuck (the wheels: no motion in 10 s of driving)"


@pytest.mark.parametrize("stuck_action", ["hold", "return"])
def test_encoders_that_stop_counting_in_a_pivot_are_named_by_the_compass(
    stuck_action: str,
) -> None:
    """Encoders frozen from the start: the robot pivots 20 deg/s from north towards a target
    south, then drives south at 2.3 m/s. The compass turned 180° net while the wheels stood
    still; the fixes moved too little (a few metres) to be told from their noise. A pause
    even where ``stuck_action`` says return: a return would dead-reckon on the dead counts."""
    c = Controller(NAV, SAFETY, failsafe=replace(FS, stuck_action=stuck_action))
    c.on_fix(fix(0.0))
    c.on_attitude(att(0.0))
    c.load_mission([at(0.0, -200.0)], 0.0)
    c.start(0.0)
    heading, y, states = 0.0, 0.0, set()
    for k in range(1, 60):
        t = 0.5 * k
        if c.state in (NavState.TURN_LEFT, NavState.TURN_RIGHT):
            heading += 10.0 if c.state == NavState.TURN_RIGHT else -10.0
        elif c.state == NavState.STRAIGHT:
            y -= 0.5 * 2.3
        states.add(c.state)
        c.on_attitude(att(t, heading % 360.0))
        c.on_fix(fix(t, 0.0, y))
        c.on_odometry(WheelOdometry(t, 0, 0, k))
        if c.mode != Mode.RUNNING:
            break
    assert c.mode == Mode.PAUSED
    assert NavState.STRAIGHT in states and NavState.TURN_RIGHT in states, states
    assert c.telemetry.extra["failsafe"] == (
        "encoders: under 0.2 m counted in 10 s of driving while the compass shows motion"
    )


# ------------------------------------------------------------------- the geofence


def test_the_geofence_is_checked_on_the_estimate_while_dead_reckoning(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """The fence's edge runs (nearly straight) 3 m west of the start; the robot starts
    heading 305 deg, so it arcs about 4.6 m west before following its leg north. The GPS
    is out from 1 s (the robot still about 3 m inside) for the whole run: the loop checked
    the fence only at valid fixes, so the robot left it unseen. The EKF's estimate is
    checked: paused, motors stopped, "estimated" in the reason and the log."""
    margin_m = 3.0
    lat, lon, _alt = enu_to_lla(np.array([1000.0, 15.0, 0.0]), *ORIGIN)
    centre = (float(lat), float(lon))
    radius = great_circle_m(*centre, ORIGIN[0], ORIGIN[1]) + margin_m
    world = _world(
        40.0,
        heading_deg=305.0,
        waypoints="[[0.0, 30.0]]",
        extra=f"[safety]\ngeofence_radius_m = {radius!r}\n"
        f"geofence_center = [{centre[0]!r}, {centre[1]!r}]\n"
        f'[failsafe]\ngeofence_action = "hold"\n' + _outage(1.0, 100.0),
    )
    with caplog.at_level(logging.WARNING, logger="x6wd.loop.runner"):
        run = _mission(tmp_path, world)
    why = "geofence breach (estimated position)"
    paused = run.first("PAUSED", f"failsafe: {why}")
    t = paused["t_s"]
    assert not any(f["valid"] for f in run.of("fix") if 1.5 <= f["t_s"] <= t)  # blind
    assert t < 5.0 and run.summary.extra["geofence_breaches"] == 1
    assert [w for _t, w in run.summary.extra["failsafes"]] == [why]
    assert run.mode_changes()[-1][1] == "PAUSED"
    outside = _outside(run, centre, radius)
    assert outside.any() and not outside[run.t <= 1.0].any()  # the route led out
    motors = [m for m in run.of("motor") if m["t_s"] >= t]
    assert motors and all(m["left_pct"] == m["right_pct"] == 0.0 for m in motors)
    assert run.moved_after(t + 1.5) < 0.05
    lat_t, lon_t, _alt = enu_to_lla(np.stack([run.east, run.north, 0 * run.east], axis=-1), *ORIGIN)
    beyond_m = (
        max(great_circle_m(*centre, a, b) for a, b in zip(lat_t, lon_t, strict=True)) - radius
    )
    assert beyond_m < 1.0, beyond_m  # the free arc goes 1.6 m beyond the fence
    logged = [r.getMessage() for r in caplog.records if r.name == "x6wd.loop.runner"]
    assert any(m.startswith(f"{why}: ") and "no fresh fix: failsafe hold" in m for m in logged)


PIVOT_BLOCK = """
name = "blocked while pivoting, inside an outage (a second outside audit, seed 1)"
start_utc = "2020-01-01T12:00:00Z"
duration_s = 45
seed = 1
[origin]
lat_deg = 51.752
lon_deg = -1.2577
alt_m = 60.0
[gnss]
fidelity = "pseudorange"
[atmosphere]
env_noise_db = 1.0
[vehicle]
start_heading_deg = 0.0
stuck_from_s = 26.0
[compass]
declination_deg = -0.5
noise_ut = 0.05
horizontal_ut = 18.5
vertical_ut = 46.0
[mission]
waypoints_enu = [[17.1, 47.0], [46.0, 12.5], [88.2, 47.9]]
[[effects]]
name = "outage"
start_s = 24.0
duration_s = 200.0
"""


def test_a_robot_blocked_mid_pivot_is_a_block_of_the_wheels_not_the_pivot(
    tmp_path: Path,
) -> None:
    """Blocked at 26 s while pivoting (outage from 24 s): the pivot's headway clock had
    started just before the wheels' one, so the pivot check fired first and blamed the
    compass ("the compass does not follow the wheels") with the encoders counting nothing.
    The wheels' block is named when they stood still for half of stuck_s."""
    run = _mission(tmp_path, loads_world(PIVOT_BLOCK, base_dir=tmp_path))
    why = [w for _t, w in run.summary.extra["failsafes"]]
    assert why == ["stuck (the wheels: no motion in 10 s of driving)"], why
