"""The controller's failsafes, return to launch and position sources, sans-IO (docs/navigation.md,
"Failsafes"). Fast-time and HIL runs of the same rules: tests/test_failsafe_sim.py and
tests/test_hil_failsafe.py."""

from __future__ import annotations

import math
import re
from dataclasses import replace
from typing import Any

import numpy as np
import pytest

from tests.test_controller import LTP, NAV, SAFETY, at, att, fix, split
from x6wd.core.config import FailsafeConfig, NavigationConfig, OdometryConfig
from x6wd.core.records import GpsFix, Mode, NavState, WheelOdometry
from x6wd.nav.controller import CommandRejected, Controller, has_usable_position

FS = FailsafeConfig(stuck_s=10.0, stuck_min_m=2.0, sensor_timeout_s=30.0)
COUNTS_PER_M = 1632 / (math.pi * 0.120)  # the default [odometry] wheel


def started(
    fs: FailsafeConfig = FS, nav: NavigationConfig = NAV, north_m: float = 100.0
) -> Controller:
    """A mission ``north_m`` north started at the origin with a fix and a compass sample."""
    c = Controller(nav, SAFETY, failsafe=fs)
    c.on_fix(fix(0.0))
    c.on_attitude(att(0.0))
    c.load_mission([at(0.0, north_m)], 0.0)
    c.start(0.0)
    assert c.launch_point == pytest.approx(at(0.0, 0.0))
    return c


def feed(c: Controller, t_s: float, y_m: float, counts: int | None = None) -> None:
    """A fix at (0, y_m), a compass sample pointing north and, if given, encoder counts."""
    c.on_attitude(att(t_s))  # first: at 1 Hz the fix would otherwise find it stale
    c.on_fix(fix(t_s, 0.0, y_m))
    if counts is not None:
        c.on_odometry(WheelOdometry(t_s, counts, counts, 0))


# ------------------------------------------------------------------ return to launch


def test_return_needs_a_launch_point_and_is_refused_in_manual_drive() -> None:
    c = Controller(NAV, SAFETY)
    c.load_mission([at(0.0, 50.0)], 0.0)
    with pytest.raises(CommandRejected, match="no launch point"):
        c.return_home(0.0)
    c = started()
    c.stop(1.0)
    c.manual_drive(20, 20, 1.0, 1.0)
    with pytest.raises(CommandRejected, match="manual"):
        c.return_home(1.1)


def test_return_drives_to_the_launch_point_ends_there_and_keeps_the_mission() -> None:
    c = started()
    for k in range(1, 11):
        feed(c, float(k), 2.0 * k)  # 20 m north
    changes, _cmd, tel = split(c.return_home(10.5))
    assert c.mode == Mode.RUNNING and c.returning == "return"
    assert [s.reason for s in changes if s.reason.startswith("mode:")] == [
        "mode: return: return to launch"
    ]
    assert tel.extra["returning"] == "return" and tel.waypoint_count == 1
    with pytest.raises(CommandRejected, match="already returning"):
        c.return_home(10.6)
    # the robot turns south and comes back
    for k in range(11, 30):
        y = max(0.0, 20.0 - 2.0 * (k - 10))
        c.on_fix(fix(float(k), 0.0, y))
        changes, _cmd, tel = split(c.on_attitude(att(float(k), 180.0)))
        if c.mode == Mode.DONE:
            break
    assert c.mode == Mode.DONE and c.returning == ""
    assert any(s.reason == "mode: back at the launch point" for s in changes)
    # the operator's mission is still there: start runs it again from its first waypoint
    c.start(40.0)
    assert c.telemetry.waypoint_count == 1 and c.waypoints == (at(0.0, 100.0),)
    assert "returning" not in c.telemetry.extra


def test_a_paused_mission_may_return_and_stop_cancels_the_return() -> None:
    c = started()
    feed(c, 1.0, 10.0)
    c.pause(1.5)
    c.return_home(2.0)
    assert c.mode == Mode.RUNNING and c.returning == "return"
    c.stop(3.0)
    assert c.mode == Mode.IDLE and c.returning == ""


def test_a_stopped_return_shows_the_operators_mission_again() -> None:
    # an audit (round 18): after a return was stopped, status and the console showed the
    # launch point as "waypoint 1/1" of an idle robot beside "4 waypoints on the robot"
    c = Controller(NAV, SAFETY, failsafe=FS)
    c.on_fix(fix(0.0))
    c.on_attitude(att(0.0))
    c.load_mission([at(0.0, 50.0), at(10.0, 100.0), at(0.0, 150.0), at(-10.0, 200.0)], 0.0)
    c.start(0.0)
    feed(c, 1.0, 10.0)
    c.return_home(2.0)
    feed(c, 3.0, 9.0)
    assert c.telemetry.waypoint_count == 1  # the launch point, while returning
    c.stop(4.0)
    feed(c, 5.0, 9.0)
    tel = c.telemetry
    assert c.mode == Mode.IDLE and tel.waypoint_count == 4, tel
    c.start(6.0)  # the mission from its start again, not the way home
    feed(c, 7.0, 9.0)
    assert c.telemetry.waypoint_count == 4 and c.telemetry.waypoint_index == 0


# ------------------------------------------------------------------ geofence (from the loop)


def test_geofence_breach_holds_or_returns_as_configured() -> None:
    c = started(replace(FS, geofence_action="hold"))
    feed(c, 1.0, 2.0)
    changes, cmd, _tel = split(c.geofence_breach(1.0))
    assert c.mode == Mode.PAUSED and cmd.is_stop
    assert changes[0].reason == "mode: failsafe: geofence breach"
    assert c.telemetry.extra["failsafe"] == "geofence breach"

    c = started(replace(FS, geofence_action="return"))
    feed(c, 1.0, 10.0)
    c.geofence_breach(1.0)
    assert c.mode == Mode.RUNNING and c.returning == "failsafe: geofence breach"
    # the return leads back inside: another breach report does not stop it
    c.geofence_breach(2.0)
    assert c.mode == Mode.RUNNING and c.returning


def test_geofence_breach_outside_a_mission_does_nothing() -> None:
    c = Controller(NAV, SAFETY, failsafe=replace(FS, geofence_action="return"))
    c.on_fix(fix(0.0))
    c.geofence_breach(0.5)
    assert c.mode == Mode.IDLE and "failsafe" not in c.telemetry.extra


# ------------------------------------------------------------------ operator link


def test_operator_link_lost_fires_only_once_armed() -> None:
    fs = replace(FS, operator_timeout_s=5.0, operator_action="hold", stuck_s=0.0)
    c = started(fs)
    for k in range(1, 12):  # never armed: no operator request ever came over the network
        feed(c, float(k), 0.5 * k)
    assert c.mode == Mode.RUNNING
    c.operator_seen(11.0)
    for k in range(12, 17):
        feed(c, float(k), 0.5 * k)
    assert c.mode == Mode.RUNNING  # 5 s since the operator: not yet past the limit
    feed(c, 16.5, 8.25)
    assert c.mode == Mode.PAUSED
    assert c.telemetry.extra["failsafe"] == "operator link lost"
    assert c.telemetry.extra["paused_by"] == "failsafe: operator link lost"
    c.operator_seen(17.0)
    c.resume(17.0)
    feed(c, 18.0, 9.0)
    assert c.mode == Mode.RUNNING  # re-armed by the operator's request, fresh
    assert "paused_by" not in c.telemetry.extra
    # the operator's own pause: extra.failsafe still names the last failsafe that acted,
    # paused_by says who holds it now (the console could not tell them apart)
    c.operator_seen(18.5)
    c.pause(18.5)
    assert c.telemetry.extra["failsafe"] == "operator link lost"
    assert c.telemetry.extra["paused_by"] == "operator"


def test_operator_link_lost_returns_when_configured() -> None:
    c = started(replace(FS, operator_timeout_s=2.0, operator_action="return", stuck_s=0.0))
    c.operator_seen(0.0)
    feed(c, 1.0, 10.0)
    feed(c, 2.5, 20.0)
    assert c.returning == "failsafe: operator link lost"


# ------------------------------------------------------------------ stuck


def test_stuck_with_the_wheels_blocked_pauses() -> None:
    c = started()
    for k in range(1, 16):  # wheels still, fixes still, driving forward
        feed(c, float(k), 0.0, counts=0)
        if c.mode != Mode.RUNNING:
            break
    assert c.mode == Mode.PAUSED and c.command.is_stop
    assert c.telemetry.extra["failsafe"] == "stuck (the wheels: no motion in 10 s of driving)"


def test_stuck_with_the_wheels_slipping_pauses_naming_the_gps() -> None:
    c = started()
    for k in range(1, 16):  # the wheels turn 2.3 m/s, the fixes do not move
        feed(c, float(k), 0.0, counts=round(2.3 * k * COUNTS_PER_M))
        if c.mode != Mode.RUNNING:
            break
    assert c.mode == Mode.PAUSED
    assert c.telemetry.extra["failsafe"] == "stuck (the GPS: no motion in 10 s of driving)"


def pivoting(fs: FailsafeConfig = FS) -> Controller:
    """A mission whose target is east while the robot faces north: it pivots right."""
    c = Controller(NAV, SAFETY, failsafe=fs)
    c.on_fix(fix(0.0))
    c.on_attitude(att(0.0))
    c.load_mission([at(100.0, 0.0)], 0.0)
    c.start(0.0)
    return c


def test_a_moving_robot_or_a_turning_pivot_is_never_stuck() -> None:
    c = started()
    for k in range(1, 40):
        feed(c, float(k), 2.0 * k, counts=round(2.0 * k * COUNTS_PER_M))
    assert c.mode in (Mode.RUNNING, Mode.DONE) and "failsafe" not in c.telemetry.extra
    # pivoting slowly (3 deg/s: 30 deg in 10 s) towards a target 90 deg away: never stuck
    c = pivoting()
    for k in range(1, 26):  # (at 81 deg the robot is within the pivot's resume angle)
        t = float(k)
        c.on_attitude(att(t, 3.0 * k))
        c.on_fix(fix(t))
        assert c.state == NavState.TURN_RIGHT, k
    assert c.mode == Mode.RUNNING


def test_a_pivot_that_does_not_turn_is_stuck_naming_the_compass() -> None:
    c = pivoting()
    for k in range(1, 20):
        t = float(k)
        c.on_attitude(att(t, 0.0))
        c.on_fix(fix(t))
        if c.mode != Mode.RUNNING:
            break
    assert c.mode == Mode.PAUSED and t == pytest.approx(11.0, abs=1.0)
    assert c.telemetry.extra["failsafe"] == "stuck (the compass: no motion in 10 s of driving)"


def test_a_pivot_whose_compass_swings_without_nearing_the_target_is_stuck() -> None:
    # A magnet stronger than the earth's field: as the body spins the bearing swings +-40 deg
    # round north and never reaches the target 90 deg east. The swing passes the 30 deg
    # motion test; the robot spun for 500 s with no failsafe.
    c = pivoting()
    for k in range(1, 600):
        t = 0.05 * k
        c.on_attitude(att(t, 40.0 * math.sin(2 * math.pi * t / 4.0) % 360.0))
        if k % 20 == 0:
            c.on_fix(fix(t))
        if c.mode != Mode.RUNNING:
            break
    assert c.mode == Mode.PAUSED and c.command.is_stop
    assert 10.0 <= t <= 20.0  # stuck_s after its best (the EKF's heading settles first)
    why = c.telemetry.extra["failsafe"]
    assert why.startswith("stuck (the pivot: ") and "no nearer in 10 s of turning" in why


def test_a_slow_or_wavering_pivot_that_nears_its_target_is_not_stuck() -> None:
    # 3.5 deg/s with +-20 deg of swing on top: every 10 s it is 35 deg nearer its target
    c = pivoting()
    for k in range(1, 1100):
        t = 0.05 * k
        c.on_attitude(att(t, (3.5 * t + 20.0 * math.sin(2 * math.pi * t / 3.0)) % 360.0))
        if k % 20 == 0:
            c.on_fix(fix(t))
        if c.state != NavState.TURN_RIGHT:
            break
    assert c.mode == Mode.RUNNING and "failsafe" not in c.telemetry.extra
    assert t > 15.0  # it pivoted for longer than stuck_s


def test_stuck_is_caught_stuck_s_after_the_robot_stopped_moving() -> None:
    c = started()
    for k in range(1, 8):  # 7 s of good progress
        feed(c, float(k), 2.0 * k, counts=round(2.0 * k * COUNTS_PER_M))
    for k in range(8, 40):  # then blocked
        feed(c, float(k), 14.0, counts=round(14.0 * COUNTS_PER_M))
        if c.mode != Mode.RUNNING:
            break
    assert c.mode == Mode.PAUSED
    # within stuck_s of the last progress (2 m, one second before it stopped): not up to
    # twice stuck_s as with fixed windows
    assert 6.0 + 10.0 <= k <= 7.0 + 10.0 + 1.0


def test_operator_link_lost_during_a_return_lets_it_go_on() -> None:
    fs = replace(FS, operator_timeout_s=2.0, operator_action="return", stuck_s=0.0)
    c = started(fs)
    feed(c, 1.0, 10.0)
    c.operator_seen(1.0)
    c.return_home(1.0)  # the operator sends return and goes away
    for t in (2.0, 3.0, 4.0, 5.0):
        c.on_attitude(att(t, 180.0))
        c.on_fix(fix(t, 0.0, 10.0 - t))
    assert c.mode == Mode.RUNNING and c.returning == "return"


def test_stuck_detection_is_off_at_zero() -> None:
    c = started(replace(FS, stuck_s=0.0))
    for k in range(1, 30):
        feed(c, float(k), 0.0, counts=0)
    assert c.mode == Mode.RUNNING


def test_stuck_action_return() -> None:
    c = started(replace(FS, stuck_action="return"))
    feed(c, 1.0, 10.0, counts=round(10 * COUNTS_PER_M))
    for k in range(2, 16):
        feed(c, float(k), 10.0, counts=round(10 * COUNTS_PER_M))  # stuck 10 m out
        if c.returning:
            break
    assert c.returning.startswith("failsafe: stuck")


# ------------------------------------------------------------------ sensors


def test_a_sensor_down_longer_than_the_timeout_pauses_a_short_one_resumes() -> None:
    c = started(replace(FS, sensor_timeout_s=5.0, stuck_s=0.0))
    feed(c, 1.0, 1.0)
    c.sensor_health("gps", False, 1.0, "disconnected")
    for t in (2.0, 4.0):
        c.tick(t)
    assert c.state == NavState.HOLD and c.mode == Mode.RUNNING
    c.sensor_health("gps", True, 4.5, "connected")
    feed(c, 4.6, 2.0)
    assert c.state == NavState.STRAIGHT  # a short outage: resumed by itself
    c.sensor_health("compass", False, 5.0, "stale")
    for t in (6.0, 8.0, 10.0, 10.5):
        c.tick(t)
    assert c.mode == Mode.PAUSED and c.command.is_stop
    assert c.telemetry.extra["failsafe"] == "compass stale for 5 s"


def test_a_sensor_timeout_with_return_still_holds_while_blind() -> None:
    c = started(replace(FS, sensor_timeout_s=2.0, sensor_action="return", stuck_s=0.0))
    feed(c, 1.0, 1.0)
    c.sensor_health("gps", False, 1.0, "disconnected")
    c.tick(3.5)
    assert c.returning.startswith("failsafe: gps disconnected")
    assert c.state == NavState.HOLD and c.command.is_stop  # no navigating without the GPS
    for t in (4.0, 5.0, 6.0):
        c.tick(t)  # still blind after another timeout: the return gives way to a pause
    assert c.mode == Mode.PAUSED


# ------------------------------------------------------------------ position sources


def test_has_usable_position() -> None:
    assert has_usable_position(fix(0.0))
    assert not has_usable_position(fix(0.0, valid=False))
    for lat, lon in ((math.nan, 0.0), (0.0, math.inf), (91.0, 0.0), (0.0, 181.0), (None, 0.0)):
        assert not has_usable_position(GpsFix(0.0, lat_deg=lat, lon_deg=lon, valid=True))


def test_the_constellation_restarts_from_the_latest_fix_at_mission_start() -> None:
    c = Controller(NAV, SAFETY)
    for k in range(10):
        c.on_fix(fix(float(k), 0.0, 0.1 * k))
    c.on_attitude(att(9.0))
    assert c.telemetry.extra["filter_samples"] == 10
    c.load_mission([at(0.0, 50.0)], 9.0)
    c.start(9.0)
    assert c.telemetry.extra["filter_samples"] == 1
    assert c.telemetry.filt_lat_deg == pytest.approx(at(0.0, 0.9)[0])


def test_the_ekf_follows_a_straight_drive_and_steers_by_its_heading() -> None:
    nav = NavigationConfig()  # the robot's: ekf, pivot_arc
    assert nav.position_source == "ekf"
    c = Controller(nav, SAFETY, 3.0)
    c.on_fix(fix(0.0))
    for k in range(1, 21):
        t = 0.05 * k
        c.on_attitude(att(t, 357.0))  # 357 magnetic + 3 declination = north
    c.load_mission([at(0.0, 100.0)], 1.0)
    c.start(1.0)
    for k in range(1, 301):  # 1 m/s north for 30 s: encoders and compass at 10 Hz, fixes 1 Hz
        t = 1.0 + 0.1 * k
        counts = round(0.1 * k * COUNTS_PER_M)
        c.on_odometry(WheelOdometry(t, counts, counts, k))
        c.on_attitude(att(t, 357.0))
        if k % 10 == 0:
            c.on_fix(fix(t, 0.0, 0.1 * k))
    tel = c.telemetry
    est = ltp_xy(tel.filt_lat_deg, tel.filt_lon_deg)
    assert est[1] == pytest.approx(30.0, abs=1.0) and abs(est[0]) < 1.0
    assert tel.heading_deg == pytest.approx(0.0, abs=1.0)
    assert tel.extra["ekf_sigma_m"] < 3.0 and tel.extra["ekf_gps_rejected"] == 0
    assert tel.state == NavState.STRAIGHT


def test_dead_reckoning_through_a_gps_gap_stops_once_the_ekf_sigma_passes_5_m() -> None:
    """docs/navigation.md, "Driving on without a fix": with the EKF and the encoders the robot
    drives on without a fix only while the EKF's position sigma stays under 5 m, however far
    ``gps_outage_max_m`` would let it go. Very noisy wheels (0.1 m²/m per side) make the
    sigma grow within metres once the fixes stop."""
    safety = replace(SAFETY, gps_outage_max_m=1000.0)
    odometry = OdometryConfig(k_left_m=0.1, k_right_m=0.1)
    c = Controller(NavigationConfig(), safety, 3.0, odometry=odometry)
    c.on_fix(fix(0.0))
    for k in range(1, 21):
        c.on_attitude(att(0.05 * k, 357.0))  # 357 magnetic + 3 declination = north
    c.load_mission([at(0.0, 900.0)], 1.0)
    c.start(1.0)
    last_fix_s, seen = 21.0, []  # (t_s, state, ekf_sigma_m) after the last fix
    for k in range(1, 601):  # 2 m/s north: encoders and compass at 10 Hz, fixes at 1 Hz
        t = 1.0 + 0.1 * k
        counts = round(0.2 * k * COUNTS_PER_M)
        c.on_odometry(WheelOdometry(t, counts, counts, k))
        c.on_attitude(att(t, 357.0))
        if k % 10 == 0 and t <= last_fix_s + 1e-9:
            c.on_fix(fix(t, 0.0, 0.2 * k))
        tel = c.telemetry
        if t > last_fix_s:
            seen.append((t, tel.state, tel.extra["ekf_sigma_m"]))
        if tel.state == NavState.HOLD:
            break
    t_hold, _, sigma_hold = seen[-1]
    assert seen[-1][1] == NavState.HOLD, "never held: the sigma cap is gone"
    stale_s = last_fix_s + safety.fix_stale_s
    assert t_hold > stale_s + 1.0  # it drove on past the stale fix ...
    assert all(s == NavState.STRAIGHT for _t, s, _sig in seen[:-1])
    assert all(sig <= 5.0 for _t, _s, sig in seen[:-1])  # ... while the sigma was under 5 m
    assert sigma_hold > 5.0
    assert 2.0 * (t_hold - last_fix_s) < 100.0  # far short of gps_outage_max_m


def test_set_declination_turns_the_heading() -> None:
    c = Controller(NAV, SAFETY, 0.0)
    c.on_attitude(att(0.0, 10.0))
    assert c.telemetry.heading_deg == pytest.approx(10.0)
    c.set_declination(-4.0, 0.1)
    assert c.telemetry.heading_deg == pytest.approx(6.0)


def ltp_xy(lat: float | None, lon: float | None) -> tuple[float, float]:

    assert lat is not None and lon is not None
    x, y = LTP.to_xy(lat, lon)
    return float(x), float(y)


# ------------------------------------------------------------------ off course


def drive(c: Controller, bearing_deg: float, course_deg: float, steps: int) -> int:
    """1 Hz: the compass reads ``bearing_deg`` while the fixes go 2 m a second along
    ``course_deg`` (true) from the origin. The step a failsafe acted at, else -1."""
    s, co = math.sin(math.radians(course_deg)), math.cos(math.radians(course_deg))
    for k in range(1, steps + 1):
        c.on_attitude(att(float(k), bearing_deg))
        c.on_fix(fix(float(k), 2.0 * k * s, 2.0 * k * co))
        if c.mode != Mode.RUNNING or c.returning:
            return k
    return -1


def test_a_heading_the_fixes_do_not_follow_stops_the_mission() -> None:
    """A compass knocked 90 deg round: the robot steers 'north' by it while the fixes go
    east (the target 1 km north: it stays within the straight's tolerance for a while)."""
    c = started(replace(FS, stuck_s=0.0), north_m=1000.0)
    k = drive(c, 0.0, 90.0, 30)
    assert c.mode == Mode.PAUSED and c.command.is_stop
    why = c.telemetry.extra["failsafe"]
    assert why.startswith("off course (heading 90 deg from the GPS course"), why
    # three windows of 10 m in a row over the limit, none overlapping: 30 m at 2 m/s
    assert 15 <= k <= 20, k


def test_a_robot_on_its_course_is_never_off_course() -> None:
    c = started(replace(FS, stuck_s=0.0), north_m=1000.0)
    assert drive(c, 0.0, 8.0, 40) == -1  # 8 deg off: within the navigator's tolerance
    assert c.mode == Mode.RUNNING and "failsafe" not in c.telemetry.extra


def test_driving_away_from_the_target_stops_the_mission() -> None:
    """The fixes go south while the target is north (the heading check off, so the distance
    check alone must catch it): on the third fix in a row over 25 m past the leg's closest.
    One fix that far (a GPS jump) is not enough."""
    c = started(replace(FS, stuck_s=0.0, heading_check_deg=0.0))
    k = drive(c, 0.0, 180.0, 30)
    assert c.mode == Mode.PAUSED
    assert c.telemetry.extra["failsafe"].startswith("off course (130 m from the target, 30 m")
    assert k == 15  # 2 m a second: past 25 m farther at 13 s, the third such fix at 15 s
    c = started(replace(FS, stuck_s=0.0, heading_check_deg=0.0, off_course_m=0.0))
    assert drive(c, 0.0, 180.0, 30) == -1  # both checks off
    c = started(replace(FS, stuck_s=0.0, heading_check_deg=0.0))
    for k in range(1, 12):  # on course north, one fix of them 40 m off
        c.on_attitude(att(float(k), 0.0))
        c.on_fix(fix(float(k), 40.0 if k == 6 else 0.0, 2.0 * k))
    assert c.mode == Mode.RUNNING


def test_fixes_that_jump_away_while_the_wheels_stand_still_are_no_runaway() -> None:
    """Beside a wall the fix can sit 30-40 m off for many seconds while the robot waits: with
    encoders, 'farther away' counts only once the wheels drove that far."""
    c = started(replace(FS, stuck_s=0.0, heading_check_deg=0.0), north_m=1000.0)
    for k in range(1, 11):  # on course north at 2 m/s, the wheels counting it
        feed(c, float(k), 2.0 * k, counts=round(2.0 * k * COUNTS_PER_M))
    for k in range(11, 21):  # the fixes jump 40 m south; the wheels: 2 m more in all
        feed(c, float(k), 20.0 - 40.0, counts=round(22.0 * COUNTS_PER_M))
    assert c.mode == Mode.RUNNING
    for k in range(21, 40):  # now the wheels drive on while the fixes recede
        y = -20.0 - 2.0 * (k - 20)
        feed(c, float(k), y, counts=round((22.0 + 2.0 * (k - 20)) * COUNTS_PER_M))
        if c.mode != Mode.RUNNING:
            break
    assert c.mode == Mode.PAUSED and c.telemetry.extra["failsafe"].startswith("off course (")


def test_off_course_action_return_drives_back() -> None:
    c = started(replace(FS, stuck_s=0.0, off_course_action="return"), north_m=1000.0)
    drive(c, 0.0, 90.0, 30)
    assert c.mode == Mode.RUNNING and c.returning.startswith("failsafe: off course (heading")


def test_a_stale_fix_is_no_evidence_of_being_stuck() -> None:
    """Fixes gone for longer than stuck_s while the EKF dead-reckons on the wheels (garbage
    on the NMEA line): the wheels turn and the compass is fine, so the robot is not stuck,
    whatever the last fix says."""
    safety = replace(SAFETY, gps_outage_max_m=1000.0)
    c = Controller(NavigationConfig(), safety, 3.0, failsafe=FS)
    c.on_fix(fix(0.0))
    for k in range(1, 21):
        c.on_attitude(att(0.05 * k, 357.0))
    c.load_mission([at(0.0, 900.0)], 1.0)
    c.start(1.0)
    for k in range(1, 301):  # 1 m/s north; the fixes stop after 5 s, for 25 s
        t = 1.0 + 0.1 * k
        counts = round(0.1 * k * COUNTS_PER_M)
        c.on_odometry(WheelOdometry(t, counts, counts, k))
        c.on_attitude(att(t, 357.0))
        if k % 10 == 0 and (t <= 6.0 or t > 30.0):
            c.on_fix(fix(t, 0.0, 0.1 * k))
        assert c.mode == Mode.RUNNING, (t, c.telemetry.extra.get("failsafe"))


def test_a_slow_robot_on_a_drifting_gps_is_not_stuck_until_its_wheels_drove_far() -> None:
    """At 0.5 m/s the robot covers 5 m in stuck_s; a GPS drifting against it keeps the fixes
    within stuck_min_m. With encoders the body counts as still only once the wheels drove
    SLIP_MIN_TRAVEL x stuck_min_m (8 m) without it moving."""
    from x6wd.nav.controller import SLIP_MIN_TRAVEL

    c = started(replace(FS, off_course_m=0.0, heading_check_deg=0.0))
    for k in range(1, 40):  # fixes stay put, the wheels count 0.5 m/s
        feed(c, float(k), 0.0, counts=round(0.5 * k * COUNTS_PER_M))
        if c.mode != Mode.RUNNING:
            break
    assert c.mode == Mode.PAUSED
    assert c.telemetry.extra["failsafe"] == "stuck (the GPS: no motion in 10 s of driving)"
    # not at stuck_s (10 s, 5 m driven) but once 8 m were: 16-17 s
    assert SLIP_MIN_TRAVEL * FS.stuck_min_m / 0.5 <= k <= 18, k


# ------------------------------------------------------------------ compass untrusted


def ekf_driving_north(fs: FailsafeConfig) -> Controller:
    """The robot's EKF with a mission 1 km north, started after 2 s of compass samples."""
    c = Controller(NavigationConfig(), SAFETY, 0.0, failsafe=fs)
    c.on_fix(fix(0.0))
    for k in range(1, 21):
        c.on_attitude(att(0.1 * k))
    c.load_mission([at(0.0, 1000.0)], 2.0)
    c.start(2.0)
    return c


def drive_north(c: Controller, t0_s: float, seconds: float, bearing: Any) -> float | None:
    """1 m/s north from ``t0_s``: encoders and compass (``bearing(t_s)``, magnetic deg) at
    10 Hz, fixes at 1 Hz. The time the mission left RUNNING, else None."""
    for k in range(1, round(10 * seconds) + 1):
        t = t0_s + 0.1 * k
        counts = round((t - 2.0) * COUNTS_PER_M)
        c.on_odometry(WheelOdometry(t, counts, counts, k))
        c.on_attitude(att(t, bearing(t)))
        if k % 10 == 0:
            c.on_fix(fix(t, 0.0, t - 2.0))
        if c.mode != Mode.RUNNING:
            return t
    return None


def test_a_compass_the_ekf_refuses_pauses_the_mission_and_keeps_it_paused() -> None:
    """A compass reading a random valid bearing every time: its reader and the controller's
    checks see nothing wrong, the EKF refuses nearly all of it. After ``compass_refused_s``
    of that the mission pauses; a resume while it lasts pauses again at once."""
    fs = replace(FS, compass_refused_s=10.0)
    c = ekf_driving_north(fs)
    # healthy for 15 s, then a 90 deg step (the EKF takes it after 20 refusals: the
    # off-course watch's fault, not this one), healthy again
    assert drive_north(c, 2.0, 15.0, lambda t: 0.0) is None
    assert drive_north(c, 17.0, 5.0, lambda t: 90.0) is None
    assert drive_north(c, 22.0, 10.0, lambda t: 0.0) is None
    assert "compass_untrusted" not in c.telemetry.extra
    rng = np.random.default_rng(3)
    erratic = lambda t: float(rng.uniform(0.0, 360.0))  # noqa: E731
    t_paused = drive_north(c, 32.0, 20.0, erratic)
    assert t_paused is not None and 32.0 + 5.0 <= t_paused <= 32.0 + 11.0
    assert c.mode == Mode.PAUSED and c.command.is_stop
    why = c.telemetry.extra["failsafe"]
    assert re.fullmatch(
        r"compass untrusted \(the EKF refused \d\d % of 10\d readings in 10 s\)", why
    )
    assert c.telemetry.extra["compass_untrusted"] == why[len("compass untrusted (") : -1]
    c.resume(t_paused + 1.0)
    assert drive_north(c, t_paused + 1.0, 1.0, erratic) is not None
    assert c.mode == Mode.PAUSED  # the next sample paused it again: never driven
    # the compass sound again: trusted once the window no longer holds the refusals
    for k in range(1, 121):
        t = t_paused + 2.0 + 0.1 * k
        c.on_attitude(att(t, 0.0))
        if k % 10 == 0:
            c.on_fix(fix(t, 0.0, t_paused - 2.0))
    assert "compass_untrusted" not in c.telemetry.extra
    c.resume(t_paused + 15.0)
    assert drive_north(c, t_paused + 15.0, 2.0, lambda t: 0.0) is None


def test_the_compass_refusal_watch_is_off_at_zero() -> None:
    c = ekf_driving_north(replace(FS, compass_refused_s=0.0, stuck_s=0.0))
    rng = np.random.default_rng(3)
    assert drive_north(c, 2.0, 15.0, lambda t: float(rng.uniform(0.0, 360.0))) is None
    assert "compass_untrusted" not in c.telemetry.extra


# ------------------------------------------------------------------ position jump


def drive_north_fixes_off(
    c: Controller, t0_s: float, seconds: float, east_m: float, paused: bool = False
) -> float | None:
    """:func:`drive_north` with every fix ``east_m`` to the east of the robot (a receiver
    back somewhere else): the time the mission left RUNNING, else None. ``paused``: the
    inputs go on in any mode (the wheels as if driving: only the fixes matter there)."""
    for k in range(1, round(10 * seconds) + 1):
        t = t0_s + 0.1 * k
        counts = round((t - 2.0) * COUNTS_PER_M)
        c.on_odometry(WheelOdometry(t, counts, counts, k))
        c.on_attitude(att(t, 0.0))
        if k % 10 == 0:
            c.on_fix(fix(t, east_m, t - 2.0))
        if c.mode != Mode.RUNNING and not paused:
            return t
    return None


@pytest.mark.parametrize("east_m", [112.0, 30.0])
def test_a_position_jump_the_ekf_takes_pauses_the_mission(east_m: float) -> None:
    """An outside HIL audit: the GPS came back 112 m away (another device on the port); the
    EKF refused the fixes until they agreed, moved to them, and the robot resumed on its
    own and drove 27 m the wrong way until the off-course watch paused it. A jump of
    ``gps_jump_m`` or more now pauses the mission at the reset, motors stopped, naming it."""
    c = ekf_driving_north(FS)
    assert drive_north(c, 2.0, 10.0, lambda t: 0.0) is None
    t_paused = drive_north_fixes_off(c, 12.0, 30.0, east_m)
    assert t_paused is not None and t_paused <= 12.0 + 12.0  # the reset after 8 refusals
    assert c.mode == Mode.PAUSED and c.command.is_stop
    why = c.telemetry.extra["failsafe"]
    assert why.startswith(f"position jumped {east_m:.0f} m: "), why
    assert c.telemetry.extra["ekf_gps_resets"] == 1
    assert c.telemetry.extra["ekf_last_reset_m"] == pytest.approx(east_m, abs=3.0)
    c.resume(t_paused + 1.0)  # the operator looked: it drives on from the new position
    assert drive_north_fixes_off(c, t_paused + 1.0, 10.0, east_m) is None


def test_a_jump_under_gps_jump_m_or_with_the_check_off_drives_on() -> None:
    for fs, east_m in ((FS, 15.0), (replace(FS, gps_jump_m=0.0), 112.0)):
        c = ekf_driving_north(fs)
        assert drive_north(c, 2.0, 10.0, lambda t: 0.0) is None
        assert drive_north_fixes_off(c, 12.0, 15.0, east_m) is None, (fs, east_m)
        assert c.telemetry.extra["ekf_gps_resets"] == 1
        assert "failsafe" not in c.telemetry.extra


def test_a_jump_while_paused_pauses_again_at_the_resume() -> None:
    """An outside review: the shipped sensor timeout pauses a mission 30 s into a GPS loss;
    a GPS back 112 m away then reset the EKF while PAUSED, the jump was dropped, and the
    operator's resume drove on the untrusted position. Now the resume pauses again naming
    the jump; the next resume (the operator has seen it) drives."""
    c = ekf_driving_north(FS)
    assert drive_north(c, 2.0, 10.0, lambda t: 0.0) is None
    c.pause(12.0)
    drive_north_fixes_off(c, 12.0, 12.0, 112.0, paused=True)
    assert c.mode == Mode.PAUSED and c.telemetry.extra["ekf_gps_resets"] == 1
    c.resume(24.5)
    assert c.mode == Mode.PAUSED and c.command.is_stop
    assert c.telemetry.extra["failsafe"].startswith("position jumped 112 m: ")
    c.resume(25.0)
    assert drive_north_fixes_off(c, 25.0, 5.0, 112.0) is None


def test_a_jump_pending_from_a_stopped_mission_never_fires_in_the_next() -> None:
    c = ekf_driving_north(FS)
    assert drive_north(c, 2.0, 10.0, lambda t: 0.0) is None
    c.pause(12.0)
    drive_north_fixes_off(c, 12.0, 12.0, 112.0, paused=True)
    c.stop(24.5)
    c.load_mission([at(112.0, 1000.0)], 24.6)
    c.start(24.6)
    assert drive_north_fixes_off(c, 24.6, 5.0, 112.0) is None, c.telemetry.extra


def test_a_robot_carried_before_its_start_takes_its_launch_point_along() -> None:
    """Carried 100 m east while idle and started before the fixes agreed: the launch point
    was the old position, and a return would drive there. The jump moves it, the robot's
    wheels having stood still."""
    c = Controller(NavigationConfig(), SAFETY, 0.0, failsafe=FS)
    for k in range(0, 21):
        t = 0.1 * k
        c.on_odometry(WheelOdometry(t, 0, 0, k))
        c.on_attitude(att(t))
        if k % 10 == 0:
            c.on_fix(fix(t))
    c.load_mission([at(0.0, 500.0)], 2.0)
    for k in range(21, 201):  # carried: the fixes now 100 m east, the wheels still
        t = 0.1 * k
        c.on_odometry(WheelOdometry(t, 0, 0, k))
        c.on_attitude(att(t))
        if k % 10 == 0:
            c.on_fix(fix(t, 100.0, 0.0))
        if k == 25:
            c.start(t)  # before 8 fixes agreed
            assert c.launch_point == pytest.approx(at(0.0, 0.0), abs=1e-5)
        if k > 25 and c.mode != Mode.RUNNING:
            break
    assert c.mode == Mode.PAUSED
    assert c.telemetry.extra["failsafe"].startswith("position jumped 100 m: ")
    assert c.launch_point == pytest.approx(at(100.0, 0.0), abs=2e-5)


def test_the_clients_status_says_who_paused() -> None:
    """`x6wd client status` ends the state line with who paused: the telemetry's paused_by."""
    from x6wd.app.client import render_status

    def state_line(extra: dict[str, Any]) -> str:
        tel = {"mode": "PAUSED", "state": "IDLE", "extra": extra}
        return next(ln for ln in render_status({"telemetry": tel}).splitlines() if "PAUSED" in ln)

    line = state_line({"paused_by": "operator", "failsafe": "operator link lost"})
    assert line.endswith("(paused by the operator)"), line
    line = state_line({"paused_by": "failsafe: stuck", "failsafe": "stuck"})
    assert line.endswith("(paused by failsafe: stuck)"), line


# ------------------------------------------------------------------ progress (round 18)


def _circling(c: Controller, until_s: float, radius_m: float = 30.0) -> None:
    """Fixes and headings of a robot circling waypoint (0, 60) at 1 m/s, ``radius_m`` out:
    each heading the fixes' own course, so no other check has a cause."""
    w = 1.0 / radius_m
    t = 0.1
    while t <= until_s and c.mode == Mode.RUNNING:
        a = w * t
        c.on_attitude(att(t, math.degrees(a + math.pi / 2) % 360.0))
        if abs(t - round(t)) < 1e-6:
            c.on_fix(fix(t, radius_m * math.sin(a), 60.0 - radius_m * math.cos(a)))
        t = round(t + 0.1, 1)


def test_a_robot_circling_its_waypoint_pauses_for_no_progress() -> None:
    # an outside audit: a compass lagging 3 s swung the robot about waypoint 2 for 700 m,
    # each pivot gaining its own 10 degrees, and nothing fired
    fs = replace(FS, stuck_s=0.0, progress_timeout_s=20.0)
    c = Controller(NAV, SAFETY, failsafe=fs)
    c.on_fix(fix(0.0, 0.0, 30.0))
    c.on_attitude(att(0.0, 90.0))
    c.load_mission([at(0.0, 60.0)], 0.0)
    c.start(0.0)
    _circling(c, 60.0)
    assert c.mode == Mode.PAUSED, c.telemetry
    why = c.telemetry.extra["failsafe"]
    assert str(why).startswith("no progress to waypoint 1: 20 s of driving"), why
    # off (0): it circles on
    c = Controller(NAV, SAFETY, failsafe=replace(fs, progress_timeout_s=0.0))
    c.on_fix(fix(0.0, 0.0, 30.0))
    c.on_attitude(att(0.0, 90.0))
    c.load_mission([at(0.0, 60.0)], 0.0)
    c.start(0.0)
    _circling(c, 60.0)
    assert c.mode == Mode.RUNNING and "failsafe" not in c.telemetry.extra
