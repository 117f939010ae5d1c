"""A compass that freezes (an outside audit, round 19): a hung CMPS10 or I2C bus returns its
last registers, every reading the same. In a pivot the robot spun in place for 10 s (the
stuck check's time) while status showed the compass connected and fresh. A reading that
stays bit for bit the same while the wheels' counts turn the robot 90° now pauses it at
once, naming the frozen compass; a live compass's noise, a robot at rest and one without
encoders are left to the checks before."""

from __future__ import annotations

import math
from dataclasses import replace

import pytest

from tests.test_controller import NAV, SAFETY, at, att, fix
from tests.test_failsafe_controller import COUNTS_PER_M, FS
from x6wd.core.records import Attitude, Mode, WheelOdometry
from x6wd.nav.controller import FROZEN_WHEEL_TURN_DEG, Controller, _SameReading


def pivot(reading, steps: int = 200, encoders: bool = True, mps: float = 0.1):
    """A right pivot at ``mps`` each side (0.1: 46.8°/s counted); ``reading(k, t)``: the
    compass's Attitude at step k (None: no reading then; compass samples count as fresh
    for 2.5 s, as for a 1 Hz compass). The controller and the time (s) it stopped driving."""
    c = Controller(NAV, replace(SAFETY, attitude_stale_s=2.5), failsafe=FS)
    c.on_fix(fix(0.0))
    c.on_attitude(att(0.0))
    c.load_mission([at(100.0, 0.0)], 0.0)  # east, facing north: a right pivot
    c.start(0.0)
    t = 0.0
    for k in range(1, steps):
        t = 0.1 * k
        if encoders:
            counts = round(mps * t * COUNTS_PER_M)
            c.on_odometry(WheelOdometry(t, counts, -counts, k))
        att_k = reading(k, t)
        if att_k is not None:
            c.on_attitude(att_k)
        if k % 10 == 0:
            c.on_fix(fix(t))
        if c.mode != Mode.RUNNING:
            break
    return c, t


def test_a_frozen_compass_in_a_pivot_pauses_within_a_quarter_turn_of_the_wheels() -> None:
    c, t = pivot(lambda k, t: Attitude(t, 0.0, 1.0, -2.0))
    assert c.mode == Mode.PAUSED and c.command.is_stop
    assert t <= 3.0, t  # 90° at 46.8°/s counted; the stuck check took 10 s
    why = c.telemetry.extra["failsafe"]
    assert why.startswith("compass frozen: the same reading (bearing 0.0°, pitch 1°, roll -2°)")
    turned = float(why.split("wheels' counts turned ")[1].split("°")[0])
    assert FROZEN_WHEEL_TURN_DEG <= turned < FROZEN_WHEEL_TURN_DEG + 10.0, why


@pytest.mark.parametrize(
    "reading",
    [
        lambda k, t: att(t, 0.1 * (k % 2)),  # its noise: not frozen (the stuck check's case)
        lambda k, t: Attitude(t, 0.0, 1.0, -2.0 + (k % 2)),  # the roll changes
    ],
    ids=["bearing-noise", "roll-noise"],
)
def test_a_compass_whose_readings_change_is_not_frozen(reading) -> None:
    c, t = pivot(reading)
    assert t > 9.0 and "frozen" not in c.telemetry.extra.get("failsafe", "")


def test_without_encoders_the_stuck_check_still_judges() -> None:
    c, _t = pivot(lambda k, t: Attitude(t, 0.0, 1.0, -2.0), encoders=False)
    assert "frozen" not in c.telemetry.extra.get("failsafe", ""), c.telemetry.extra


def test_a_slow_live_compass_in_a_fast_pivot_is_not_frozen() -> None:
    # a review (round 19): a 1 Hz compass, 117°/s counted between its readings: the first
    # check called its one reading frozen 1 s after it came, before the next could differ
    c, _t = pivot(lambda k, t: att(t, (117.0 * t) % 360.0) if k % 10 == 0 else None, 60, mps=0.25)
    assert "frozen" not in c.telemetry.extra.get("failsafe", ""), c.telemetry.extra


def test_only_one_unbroken_turn_between_two_same_readings_counts() -> None:
    # a review (round 19): a stuck robot's separate turning attempts added up to 91° over
    # 8 s, and a noise-free compass was blamed for a slip
    same = _SameReading((10.0, 0.0, 0.0), 0.0)
    same.wheels(1.0)
    same.wheels(None)  # the robot is no longer told to turn: the count starts again
    same.wheels(0.5)
    same.again(1.0)
    assert same.confirmed_rad == 0.5 and same.n == 2
    same.wheels(1.0)  # not yet confirmed by a reading after it
    assert same.confirmed_rad == 0.5


# -- round 22: frozen on a straight leg ------------------------------------------------------
# An outside audit (round 22): the compass froze on a straight 400 m leg; steering by the
# frozen heading the robot followed its own drift in a slow arc (commands within 2 % of
# straight, either way), so no told turn added up, and the off-course watch paused it 50-70 s
# later, 14-48 m off the route. A reading the same while the robot drives and its wheels'
# counts turn 90° either way, told or not, is frozen too.
def straight(reading, moving: bool = True, steps: int = 400, turn_dps: float = 15.0):
    """A leg due north, the robot rolling at 1.5 m/s (fixes at 1 Hz with the receiver's speed;
    ``moving`` False: at rest, the wheels slipping) while its counts read a slow left turn of
    ``turn_dps`` (°/s counted) the commands never asked for. ``reading(k, t)``: the compass's
    Attitude at step k (20 Hz). The controller and the time (s) it stopped driving."""
    c = Controller(NAV, SAFETY, failsafe=FS)
    c.on_fix(fix(0.0))
    c.on_attitude(att(0.0))
    c.load_mission([at(0.0, 500.0)], 0.0)
    c.start(0.0)
    track_m = 0.245  # [odometry] track_m's default
    t = 0.0
    for k in range(1, steps):
        t = 0.05 * k
        fwd_m = 1.5 * t
        diff_m = math.radians(turn_dps) * t * track_m  # right minus left travel
        left = round((fwd_m - diff_m / 2) * COUNTS_PER_M)
        right = round((fwd_m + diff_m / 2) * COUNTS_PER_M)
        c.on_odometry(WheelOdometry(t, left, right, k))
        c.on_attitude(reading(k, t))
        if k % 20 == 0:
            north_m = fwd_m if moving else 0.0
            c.on_fix(replace(fix(t, 0.0, north_m), speed_mps=1.5 if moving else 0.0))
        if c.mode != Mode.RUNNING:
            break
    return c, t


def test_a_compass_frozen_on_a_straight_leg_pauses_once_the_counts_turn_a_quarter() -> None:
    c, t = straight(lambda k, t: Attitude(t, 0.0, 1.0, -2.0))
    assert c.mode == Mode.PAUSED and c.command.is_stop
    why = c.telemetry.extra["failsafe"]
    assert why.startswith("compass frozen: the same reading (bearing 0.0°"), why
    assert "the robot drove" in why, why
    assert t <= 8.0, t  # 90° at 15°/s counted: 6 s (the off-course watch: 50-70 s)


@pytest.mark.parametrize(
    ("reading", "moving"),
    [
        (lambda k, t: att(t, 0.1 * (k % 2)), True),  # a live compass's noise
        (lambda k, t: Attitude(t, 0.0, 1.0, -2.0), False),  # at rest, the wheels slipping
    ],
    ids=["live-compass", "at-rest"],
)
def test_a_live_compass_or_a_robot_at_rest_is_not_frozen(reading, moving: bool) -> None:
    c, _t = straight(reading, moving=moving, steps=240)
    assert "frozen" not in c.telemetry.extra.get("failsafe", ""), c.telemetry.extra


@pytest.mark.parametrize("rest_mps", [0.0, 0.1, 0.25])
def test_a_receiver_s_noise_at_rest_is_no_drive(rest_mps: float) -> None:
    # a review (round 22): the receiver's speed at rest (its noise, ~0.1 m/s) added up over a
    # 60 s pause to "5 m driven"; resumed into mud (one side spinning) with a healthy compass
    # repeating its reading, the robot was called frozen 6 s later instead of stuck at 10 s
    c = Controller(NAV, SAFETY, failsafe=FS)
    c.on_fix(fix(0.0))
    c.on_attitude(att(0.0))
    c.load_mission([at(0.0, 500.0)], 0.0)
    c.start(0.0)
    c.pause(0.05)
    t, k = 0.0, 0
    while t < 60.0:  # paused at rest: the same reading, the receiver's noise as speed
        k += 1
        t = 0.05 * k
        c.on_odometry(WheelOdometry(t, 0, 0, k))
        c.on_attitude(Attitude(t, 0.0, 1.0, -2.0))
        if k % 20 == 0:
            c.on_fix(replace(fix(t), speed_mps=rest_mps))
    c.resume(t)
    t0 = t
    while c.mode == Mode.RUNNING and t < t0 + 30.0:  # stuck: the counts run, the body does not
        k += 1
        t = 0.05 * k
        fwd_m, diff_m = 1.5 * (t - t0), math.radians(15.0) * (t - t0) * 0.245
        left = round((fwd_m - diff_m / 2) * COUNTS_PER_M)
        right = round((fwd_m + diff_m / 2) * COUNTS_PER_M)
        c.on_odometry(WheelOdometry(t, left, right, k))
        c.on_attitude(Attitude(t, 0.0, 1.0, -2.0))
        if k % 20 == 0:
            c.on_fix(replace(fix(t), speed_mps=rest_mps))
    why = c.telemetry.extra.get("failsafe", "")
    assert c.mode == Mode.PAUSED and why.startswith("stuck"), why
