"""Silent sensor faults (well-formed, wrong data) against the controller's failsafes, sans-IO:
an outside audit's findings (a launch point taken from a position a jump then corrected; a
compass frozen in a pivot and a GPS position frozen while driving, both reported "no
motion"). docs/navigation.md, "Failsafes"."""

from __future__ import annotations

from dataclasses import replace

import pytest

from tests.test_controller import LTP, SAFETY, at, att, fix
from tests.test_failsafe_controller import COUNTS_PER_M, FS, pivoting, started
from x6wd.core.config import GnssNoiseConfig, NavigationConfig, OdometryConfig
from x6wd.core.records import GpsFix, Mode, WheelOdometry
from x6wd.nav import geo
from x6wd.nav.controller import Controller
from x6wd.nav.position import EkfSource

# ------------------------------------------------------------------ launch point and jumps


def drive(
    c: Controller,
    t0_s: float,
    t1_s: float,
    fix_at: tuple[float, float] | None,
    v_mps: float = 1.0,
    t_start_s: float | None = None,
) -> float | None:
    """10 Hz encoders (``v_mps`` north from ``t_start_s``, still before it or when None) and
    compass (north); 1 Hz fixes at ``fix_at`` (east, north m) plus the distance driven.
    The time the mission left RUNNING, else None."""
    k0, k1 = round(10 * t0_s), round(10 * t1_s)
    for k in range(k0 + 1, k1 + 1):
        t = 0.1 * k
        driven = 0.0 if t_start_s is None else max(0.0, v_mps * (t - t_start_s))
        counts = round(driven * COUNTS_PER_M)
        c.on_odometry(WheelOdometry(t, counts, counts, k))
        c.on_attitude(att(t))
        if k % 10 == 0 and fix_at is not None:
            c.on_fix(fix(t, fix_at[0], fix_at[1] + driven))
        if c.mode == Mode.PAUSED:
            return t
    return None


def east_north_m(latlon: tuple[float, float] | None) -> tuple[float, float]:
    assert latlon is not None
    e, n = LTP.to_xy(*latlon)
    return float(e), float(n)


def test_a_robot_carried_while_idle_that_drives_off_before_the_jump_moves_its_launch() -> None:
    """The audit: carried 100 m east while idle, started before the fixes agreed, and the
    mission drove on (1 m/s: 2 m in 2 s, the EKF takes the jump 6-8 s later). The launch
    point came from the estimate the jump corrected; it moves with the jump, although the
    wheels drove over 2 m before it."""
    c = Controller(NavigationConfig(), SAFETY, 0.0, failsafe=FS)
    drive(c, -0.1, 2.0, (0.0, 0.0))
    c.load_mission([at(100.0, 500.0)], 2.0)
    # carried: the fixes now 100 m east (the one of 3 s refused), the wheels still
    drive(c, 2.0, 3.5, (100.0, 0.0))
    c.start(3.5)
    assert east_north_m(c.launch_point) == pytest.approx((0.0, 0.0), abs=0.5)
    t_paused = drive(c, 3.5, 20.0, (100.0, 0.0), t_start_s=3.5)
    assert t_paused is not None and c.mode == Mode.PAUSED
    assert c.telemetry.extra["failsafe"].startswith("position jumped 100 m: ")
    e, n = east_north_m(c.launch_point)
    assert (e, n) == pytest.approx((100.0, 0.0), abs=1.5), (e, n, t_paused)
    # the return heads for where the robot started, not for the old position 100 m west
    c.return_home(t_paused + 0.5)
    assert c.navigator.waypoints == (c.launch_point,)


def test_a_return_under_way_heads_for_the_moved_launch_point() -> None:
    """As above, but the operator sent it home before the reset: the return under way (and
    its resume after the jump's pause) heads for the moved launch point."""
    c = Controller(NavigationConfig(), SAFETY, 0.0, failsafe=FS)
    drive(c, -0.1, 2.0, (0.0, 0.0))
    c.load_mission([at(100.0, 500.0)], 2.0)
    drive(c, 2.0, 3.5, (100.0, 0.0))
    c.start(3.5)
    drive(c, 3.5, 5.0, (100.0, 0.0), t_start_s=3.5)
    c.return_home(5.0)
    assert c.navigator.waypoints == (c.launch_point,)
    t_paused = drive(c, 5.0, 20.0, (100.0, 0.0), t_start_s=3.5)
    assert t_paused is not None and c.returning
    assert east_north_m(c.launch_point) == pytest.approx((100.0, 0.0), abs=1.5)
    c.resume(t_paused + 0.5)
    assert c.navigator.waypoints == (c.launch_point,)


def test_a_first_fix_80_m_off_moves_the_launch_point_with_the_jump() -> None:
    """The audit's first fix was an 80 m outlier: the EKF started on it, the launch point
    was taken there, the robot drove off, and after 8 refused fixes the EKF moved to the
    truth. A `return` drove 83 m north to a place the robot never was; the launch point now
    moves with the jump."""
    c = Controller(NavigationConfig(), SAFETY, 0.0, failsafe=FS)
    c.on_odometry(WheelOdometry(0.0, 0, 0, 0))
    c.on_fix(fix(0.0, 0.0, 80.0))
    drive(c, 0.0, 0.5, None)  # the encoders (still) and the compass; no fix yet
    c.load_mission([at(0.0, 500.0)], 0.5)
    c.start(0.5)
    assert east_north_m(c.launch_point) == pytest.approx((0.0, 80.0), abs=0.5)
    t_paused = drive(c, 0.5, 20.0, (0.0, 0.0), t_start_s=0.5)
    assert t_paused is not None
    assert c.telemetry.extra["failsafe"].startswith("position jumped 80 m: ")
    e, n = east_north_m(c.launch_point)
    assert (e, n) == pytest.approx((0.0, 0.0), abs=1.5), (e, n, t_paused)


@pytest.mark.parametrize("drive_s", [3.0, 10.0])
def test_a_jump_after_a_correct_launch_keeps_the_launch_point(drive_s: float) -> None:
    """The opposite case: the launch point agreed with the fixes after the start (the EKF
    took them) and the robot drove off; then the fixes jump 60 m east (a receiver back
    somewhere else). The robot started where it started: the launch point stays."""
    c = Controller(NavigationConfig(), SAFETY, 0.0, failsafe=FS)
    drive(c, -0.1, 2.0, (0.0, 0.0))
    c.load_mission([at(0.0, 500.0)], 2.0)
    c.start(2.0)
    assert drive(c, 2.0, 2.0 + drive_s, (0.0, 0.0), t_start_s=2.0) is None
    t_paused = drive(c, 2.0 + drive_s, 30.0, (60.0, 0.0), t_start_s=2.0)
    assert t_paused is not None
    assert c.telemetry.extra["failsafe"].startswith("position jumped 60 m: ")
    assert east_north_m(c.launch_point) == pytest.approx((0.0, 0.0), abs=0.5)


def test_a_jump_just_after_a_start_the_fixes_agreed_with_keeps_the_launch_point() -> None:
    """Review: the EKF took every fix at the launch point for 20 s up to the start, and the
    fixes stepped 60 m east before the first fix after it (multipath, a receiver back
    somewhere else). The estimate the launch point came from was confirmed by the fix just
    before the start: the robot started where it started, the launch point stays (it moved
    to (60, 0) when only a fix after the start could confirm it)."""
    c = Controller(NavigationConfig(), SAFETY, 0.0, failsafe=FS)
    drive(c, -0.1, 20.0, (0.0, 0.0))
    c.load_mission([at(0.0, 500.0)], 20.0)
    c.start(20.0)
    t_paused = drive(c, 20.0, 40.0, (60.0, 0.0), t_start_s=20.0)
    assert t_paused is not None
    assert c.telemetry.extra["failsafe"].startswith("position jumped 60 m: ")
    assert east_north_m(c.launch_point) == pytest.approx((0.0, 0.0), abs=0.5)


def test_a_robot_carried_through_a_gps_outage_moves_its_launch_point() -> None:
    """The fix the EKF took last before the start is old (the GPS lost while the robot was
    carried 100 m east): nothing confirmed the estimate at the start, and the launch point
    moves with the reset when the fixes come back elsewhere."""
    c = Controller(NavigationConfig(), SAFETY, 0.0, failsafe=FS)
    drive(c, -0.1, 2.0, (0.0, 0.0))
    c.load_mission([at(100.0, 500.0)], 2.0)
    drive(c, 2.0, 29.5, None)  # no fix for 27.5 s (the sensor hold is idle's business)
    c.start(29.5)
    t_paused = drive(c, 29.5, 50.0, (100.0, 0.0), t_start_s=29.5)
    assert t_paused is not None
    assert c.telemetry.extra["failsafe"].startswith("position jumped 100 m: ")
    assert east_north_m(c.launch_point) == pytest.approx((100.0, 0.0), abs=1.5)


def test_a_second_mission_started_after_a_carry_moves_its_own_launch_point() -> None:
    """Mission 1's launch point was confirmed; the robot, stopped, was carried 100 m east
    and mission 2 started before the fixes agreed: its launch point is judged afresh (the
    fix before its start was refused) and moves with the reset."""
    c = Controller(NavigationConfig(), SAFETY, 0.0, failsafe=FS)
    drive(c, -0.1, 2.0, (0.0, 0.0))
    c.load_mission([at(100.0, 500.0)], 2.0)
    c.start(2.0)
    assert drive(c, 2.0, 4.0, (0.0, 0.0), v_mps=0.0) is None  # fixes taken: confirmed
    c.stop(4.0)
    drive(c, 4.0, 6.0, (0.0, 0.0))
    drive(c, 6.0, 7.5, (100.0, 0.0))  # carried while idle: the fix of 7 s refused
    c.start(7.5)
    assert east_north_m(c.launch_point) == pytest.approx((0.0, 0.0), abs=0.5)
    t_paused = drive(c, 7.5, 30.0, (100.0, 0.0), t_start_s=7.5)
    assert t_paused is not None
    assert c.telemetry.extra["failsafe"].startswith("position jumped 100 m: ")
    assert east_north_m(c.launch_point) == pytest.approx((100.0, 0.0), abs=1.5)


def test_a_fix_the_ekf_drops_as_late_does_not_confirm_the_launch_point() -> None:
    """Review: the first fix after the start reached the controller 0.5 s late (the EKF
    dropped it, beyond its max_late_s: its refused count unchanged) and was read as taken,
    confirming a launch point the reset 7 s later then no longer moved."""
    c = Controller(NavigationConfig(), SAFETY, 0.0, failsafe=FS)
    drive(c, -0.1, 2.0, (0.0, 0.0))
    c.load_mission([at(100.0, 500.0)], 2.0)
    drive(c, 2.0, 3.5, (100.0, 0.0))  # carried: the fix of 3 s refused
    c.start(3.5)
    drive(c, 3.5, 4.4, None, t_start_s=3.5)  # encoders and compass to 4.4 s, no fix
    c.on_fix(fix(3.9, 100.0, 0.4))  # the fix of 3.9 s arrives late
    t_paused = drive(c, 4.4, 20.0, (100.0, 0.0), t_start_s=3.5)
    assert t_paused is not None
    assert c.telemetry.extra["failsafe"].startswith("position jumped 100 m: ")
    assert east_north_m(c.launch_point) == pytest.approx((100.0, 0.0), abs=1.5)


def test_a_launch_point_taken_from_an_outlier_before_the_ekf_had_a_heading_is_retaken() -> None:
    """Review: the first fix was 80 m off and the mission started before the compass's
    first sample, so the EKF had no estimate and the launch point was that raw fix. The
    next fix (the truth) came before the heading, the EKF started on it, no reset ever
    came: the launch point stayed 80 m off. It is now taken again from the EKF's first
    estimate (the wheels had not moved)."""
    c = Controller(NavigationConfig(), SAFETY, 0.0, failsafe=FS)
    c.on_odometry(WheelOdometry(0.0, 0, 0, 0))
    c.on_fix(fix(0.0, 0.0, 80.0))  # the outlier, no compass yet
    c.load_mission([at(0.0, 500.0)], 0.1)
    c.start(0.2)
    assert east_north_m(c.launch_point) == pytest.approx((0.0, 80.0), abs=0.5)
    c.on_fix(fix(0.9, 0.0, 0.0))  # the truth, still no heading
    assert drive(c, 1.0, 30.0, (0.0, 0.0), t_start_s=1.0) is None
    assert east_north_m(c.launch_point) == pytest.approx((0.0, 0.0), abs=1.5)


# the 180th meridian: a plane 3 m east of it (Fiji), fixes wrapped to [-180, 180]
MERIDIAN = geo.LocalTangentPlane(-16.0, -179.99997)


def meridian_fix(t_s: float, e_m: float) -> GpsFix:
    lat, lon = MERIDIAN.to_latlon(e_m, 0.0)
    return GpsFix(
        t_s=t_s, lat_deg=float(lat), lon_deg=float(lon), valid=True, quality=1, mode=3, hdop=1.2
    )


def drive_west(
    c: Controller, t0_s: float, t1_s: float, e_m: float | None, t_start_s: float | None = None
) -> float | None:
    """As :func:`drive`, heading west (270 deg) along the plane's east axis: fixes at
    ``e_m`` less the distance driven."""
    for k in range(round(10 * t0_s) + 1, round(10 * t1_s) + 1):
        t = 0.1 * k
        driven = 0.0 if t_start_s is None else max(0.0, t - t_start_s)
        counts = round(driven * COUNTS_PER_M)
        c.on_odometry(WheelOdometry(t, counts, counts, k))
        c.on_attitude(att(t, 270.0))
        if k % 10 == 0 and e_m is not None:
            c.on_fix(meridian_fix(t, e_m - driven))
        if c.mode == Mode.PAUSED:
            return t
    return None


@pytest.mark.parametrize("return_first", [False, True])
def test_a_launch_point_moved_across_the_180th_meridian_stays_a_longitude(
    return_first: bool,
) -> None:
    """Review: carried 60 m east while idle 3 m east of the 180th meridian, started before
    the fixes agreed, and driven west across it before the reset. The launch point moved by
    the positions' difference in degrees (about -360 deg of longitude): -539.9994 deg;
    `return` raised a NavigationError, and with a return under way `on_fix` itself raised.
    The offset is wrapped: the launch point is 60 m east of the old one, and the return
    heads there."""
    c = Controller(NavigationConfig(), SAFETY, 0.0, failsafe=FS)
    drive_west(c, -0.1, 2.0, 0.0)
    lat, lon = MERIDIAN.to_latlon(-400.0, 0.0)
    c.load_mission([(float(lat), float(lon))], 2.0)
    drive_west(c, 2.0, 3.5, 60.0)  # carried: the fix of 3 s refused
    c.start(3.5)
    if return_first:
        drive_west(c, 3.5, 5.0, 60.0, t_start_s=3.5)
        c.return_home(5.0)
    t_paused = drive_west(c, 5.0 if return_first else 3.5, 20.0, 60.0, t_start_s=3.5)
    assert t_paused is not None
    assert c.telemetry.extra["failsafe"].startswith("position jumped 60 m: ")
    assert c.launch_point is not None
    assert -180.0 <= c.launch_point[1] <= 180.0, c.launch_point
    e, n = MERIDIAN.to_xy(*c.launch_point)
    assert (float(e), float(n)) == pytest.approx((60.0, 0.0), abs=1.5)
    if not return_first:
        c.return_home(t_paused + 0.5)
    else:
        c.resume(t_paused + 0.5)
    assert c.navigator.waypoints == (c.launch_point,)


# ------------------------------------------------------------------ a compass frozen in a pivot


def test_a_frozen_compass_in_a_pivot_is_named_as_not_following_the_wheels() -> None:
    """The audit: the compass froze as the robot pivoted at a waypoint; it spun ~2.5 turns
    in 10 s (the encoders counted it) and paused "stuck (the compass: no motion ...)". The
    reason now says the compass did not follow the wheels' turn; the pause stays. (A
    compass whose readings stay bit for bit the same is caught sooner, as frozen: this one
    still reads its noise, test_compass_frozen_round19.py.)"""
    c = pivoting()  # target east, facing north: a right pivot (left forward, right back)
    t = 0.0
    for k in range(1, 200):
        t = 0.1 * k
        counts = round(0.1 * t * COUNTS_PER_M)  # 0.1 m/s each side: 46.8 deg/s counted
        c.on_odometry(WheelOdometry(t, counts, -counts, k))
        c.on_attitude(att(t, 0.1 * (k % 2)))  # it does not follow the turn, only its noise
        if k % 10 == 0:
            c.on_fix(fix(t))
        if c.mode != Mode.RUNNING:
            break
    assert c.mode == Mode.PAUSED and c.command.is_stop
    why = c.telemetry.extra["failsafe"]
    assert "no motion" not in why, why
    assert why.startswith("stuck (the compass: turned 0° in 10 s of pivoting while the"), why
    assert "the compass does not follow the wheels" in why, why
    turned = float(why.split("wheels' counts turned ")[1].split("°")[0])
    assert 440.0 <= turned <= 490.0, why  # 0.2 m/s apart over the 0.245 m track, 10 s


# ------------------------------------------------------------------ a GPS position frozen


def feed_speed(c: Controller, t_s: float, counts: int, speed_mps: float | None) -> None:
    """A compass sample north, a fix at the origin carrying the receiver's ``speed_mps``,
    the encoder counts."""
    c.on_attitude(att(t_s))
    c.on_fix(replace(fix(t_s), speed_mps=speed_mps))
    c.on_odometry(WheelOdometry(t_s, counts, counts, 0))


@pytest.mark.parametrize("action", ["hold", "return"])
def test_a_frozen_gps_position_with_the_receiver_reporting_speed_is_a_gps_fault(
    action: str,
) -> None:
    """The audit: the fix stayed valid, its time and RMC speed advancing, its position
    frozen; the wheels counted 20 m in 10 s and the receiver said 2.4 m/s, yet the pause
    read "stuck (the GPS: no motion ...)". Two witnesses of motion against one: the reason
    names the GPS. Always a pause: a return would steer home by the frozen position."""
    c = started(replace(FS, stuck_action=action))
    k = 0
    for k in range(1, 20):
        feed_speed(c, float(k), round(2.3 * k * COUNTS_PER_M), 2.4)
        if c.mode != Mode.RUNNING:
            break
    assert c.mode == Mode.PAUSED and c.command.is_stop and not c.returning
    why = c.telemetry.extra["failsafe"]
    assert why.startswith("GPS position frozen: the fixes moved 0.0 m in 10 s of driving"), why
    wheels_m = float(why.split("the wheels counted ")[1].split(" m")[0])
    assert 20.0 <= wheels_m <= 24.0, why  # 2.3 m/s for 10 s (the last count comes after)
    assert why.endswith("and the receiver reported 2.4 m/s"), why
    assert "stuck" not in why and "no motion" not in why, why


def test_slipping_wheels_with_the_receiver_at_rest_are_still_stuck() -> None:
    """The receiver's own speed near zero agrees with the fixes: the wheels slip, the robot
    is stuck, named as before."""
    c = started()
    for k in range(1, 20):
        feed_speed(c, float(k), round(2.3 * k * COUNTS_PER_M), 0.05)
        if c.mode != Mode.RUNNING:
            break
    assert c.mode == Mode.PAUSED
    assert c.telemetry.extra["failsafe"] == "stuck (the GPS: no motion in 10 s of driving)"


# ------------------------------------------------------------------ review s12/r2


def test_a_slow_carry_while_idle_moves_the_estimate_and_the_launch_point() -> None:
    """Review s12/r2 (1): carried 70 m east at 1 m/s while idle, the wheels still, the fixes
    at 4 Hz, each inside the EKF's gate: the GPS bias states took the move (33 m, ~20 σ_b),
    the estimate stayed 33.6 m short with σ 2.2 m, start() confirmed the launch point at
    (33.5, 0) and `return` ended 38 m from the true start. The EKF now resets onto the
    fixes when the bias the fixes built while the robot stood still runs past its model's
    size ("bias"): the launch point is within the bias's 99 % circle (5.5 m at HDOP 1.2)."""
    c = Controller(NavigationConfig(), SAFETY, 0.0, failsafe=FS)
    for k in range(0, 1250):  # 20 s idle, 70 s carried, 35 s set down
        t = 0.1 * k
        e = min(70.0, max(0.0, t - 20.0))
        c.on_odometry(WheelOdometry(t, 0, 0, k))
        c.on_attitude(att(t))
        if k % 10 in (0, 3, 5, 8):  # 4 Hz on the 0.1 s grid (0.25 s -> 0.3, 0.75 -> 0.8)
            c.on_fix(fix(t, e, 0.0))
    c.load_mission([at(70.0, 60.0)], 125.0)
    c.start(125.0)
    e, n = east_north_m(c.launch_point)
    assert abs(e - 70.0) < 6.0 and abs(n) < 1.0, (e, n)
    extra = c.telemetry.extra
    assert extra["ekf_bias_runaway_resets"] >= 1, extra
    assert extra["ekf_last_reset_reason"] == "bias"


def test_a_long_fix_stale_s_does_not_confirm_a_launch_point_across_a_carry() -> None:
    """Review s12/r2 (2): with fix_stale_s = 30 (the configuration allows up to 60) the
    latest fix taken 25 s before the start, across a GPS outage in which the robot was
    carried 35 m, confirmed the launch point, which then stayed at the old place. The
    freshness that confirms is now a fixed LAUNCH_FIX_FRESH_S (2.5 s), not fix_stale_s."""
    c = Controller(NavigationConfig(), replace(SAFETY, fix_stale_s=30.0), 0.0, failsafe=FS)
    drive(c, -0.1, 20.0, (0.0, 0.0))
    c.load_mission([at(35.0, 500.0)], 20.0)
    drive(c, 20.0, 45.0, None)  # no fix for 25 s: carried 35 m east meanwhile
    c.start(45.0)
    t_paused = drive(c, 45.0, 70.0, (35.0, 0.0), t_start_s=45.0)
    assert t_paused is not None
    assert c.telemetry.extra["failsafe"].startswith("position jumped 35 m: ")
    assert east_north_m(c.launch_point) == pytest.approx((35.0, 0.0), abs=1.5)


def test_a_pivot_the_compass_does_not_follow_names_both_causes() -> None:
    """Review s12/r2 (3): wheels spinning in place in mud count a pivot exactly as a frozen
    compass's do; the reason said "the compass does not follow the wheels" as if the
    compass were the fault. It now names both."""
    c = pivoting()
    for k in range(1, 200):
        t = 0.1 * k
        counts = round(0.1 * t * COUNTS_PER_M)
        c.on_odometry(WheelOdometry(t, counts, -counts, k))
        c.on_attitude(att(t, 0.1 * (k % 2)))  # a live compass's noise (frozen: round 19)
        if k % 10 == 0:
            c.on_fix(fix(t))
        if c.mode != Mode.RUNNING:
            break
    why = c.telemetry.extra["failsafe"]
    assert why.endswith(
        "the compass does not follow the wheels: a compass fault, or the wheels spin in place)"
    ), why


# ------------------------------------------------------------------ untested guards (review s12/r2)


def test_a_late_fix_leaves_the_time_of_the_last_fix_taken() -> None:
    """A fix the EKF drops as too late judged nothing: the time of the latest fix taken
    stays (PositionSource.fixes_taken), else a late fix just before a start would leave the
    launch point unconfirmed."""
    src = EkfSource(NavigationConfig(), OdometryConfig(), GnssNoiseConfig(), 0.0)
    for k in range(0, 51):
        t = 0.1 * k
        src.on_odometry(WheelOdometry(t, 0, 0, k))
        if k % 10 == 0:
            src.on_fix(fix(t))
        src.on_compass(t, 0.0)
    count, taken_t = src.fixes_taken()
    assert taken_t == pytest.approx(5.0) and count >= 4
    src.on_fix(fix(4.0))  # 1 s late (max_late_s 0.3 s): dropped
    assert src.fixes_taken() == (count, taken_t)


def test_a_raw_launch_point_is_not_retaken_after_the_wheels_drove_2_m() -> None:
    """The raw-fix launch point (the EKF had no heading at the start) is taken again from
    the EKF's first estimate only while the wheels drove under LAUNCH_STILL_M since the
    start; after 3 m the raw fix stays (docs/navigation.md: not handled)."""
    c = Controller(NavigationConfig(), SAFETY, 0.0, failsafe=FS)
    c.on_odometry(WheelOdometry(0.0, 0, 0, 0))
    c.on_fix(fix(0.0, 0.0, 80.0))  # the outlier, no compass yet
    c.load_mission([at(0.0, 500.0)], 0.1)
    c.start(0.2)
    for k in range(1, 31):  # 1 m/s north for 3 s, no compass: no estimate yet
        t = 0.1 * k
        c.on_odometry(WheelOdometry(t, round(t * COUNTS_PER_M), round(t * COUNTS_PER_M), k))
        if k % 10 == 0:
            c.on_fix(fix(t, 0.0, t))
    drive(c, 3.0, 10.0, (0.0, 0.0), t_start_s=0.0)  # the compass now: the EKF starts
    assert c.telemetry.extra.get("ekf") != "waiting for a fix"
    assert east_north_m(c.launch_point) == pytest.approx((0.0, 80.0), abs=0.5)


def test_out_of_order_fixes_do_not_add_receiver_speed_twice() -> None:
    """Slipping wheels, the receiver at 0.7 m/s (7 m in the 10 s window, under the 8 m that
    names a frozen GPS), and each fix followed by a copy 0.5 s late: the speed is summed
    from the latest fix's time, so the late copies add nothing and the robot is "stuck (the
    GPS ...)" as without them (summed from the late copy: 10.5 m, "GPS position frozen")."""
    c = started()
    for k in range(1, 20):
        t = float(k)
        c.on_attitude(att(t))
        c.on_fix(replace(fix(t), speed_mps=0.7))
        c.on_fix(replace(fix(t - 0.5), speed_mps=0.7))  # out of order
        c.on_odometry(
            WheelOdometry(t, round(2.3 * k * COUNTS_PER_M), round(2.3 * k * COUNTS_PER_M), 0)
        )
        if c.mode != Mode.RUNNING:
            break
    assert c.mode == Mode.PAUSED
    assert c.telemetry.extra["failsafe"] == "stuck (the GPS: no motion in 10 s of driving)"


def test_a_launch_point_past_a_pole_is_not_taken() -> None:
    """_move_launch leaves the launch point where it was when the moved one is no position
    (a latitude past 90 deg: a reset's offset near a pole); it must not raise either."""
    c = started()
    before = c.launch_point
    c._move_launch(90.5, 10.0)
    assert c.launch_point == before
    c._move_launch(-90.5, 10.0)
    assert c.launch_point == before
