"""A compass that freezes (an outside audit, round 19): a hung CMPS10 or I2C bus returns its
last registers, every reading the same. In a pivot the robot spun in place for 10 s (the
stuck check's time) while status showed the compass connected and fresh. A reading that
stays bit for bit the same while the wheels' counts turn the robot 90° now pauses it at
once, naming the frozen compass; a live compass's noise, a robot at rest and one without
encoders are left to the checks before."""

from __future__ import annotations

import pytest

from tests.test_controller import att, fix
from tests.test_failsafe_controller import COUNTS_PER_M, pivoting
from x6wd.core.records import Attitude, Mode, WheelOdometry
from x6wd.nav.controller import FROZEN_WHEEL_TURN_DEG


def pivot(reading, steps: int = 200, encoders: bool = True):  # type: ignore[no-untyped-def]
    """A right pivot at 0.1 m/s each side (46.8°/s counted); ``reading(k, t)``: the
    compass's Attitude at step k. The controller and the time (s) it stopped driving."""
    c = pivoting()
    t = 0.0
    for k in range(1, steps):
        t = 0.1 * k
        if encoders:
            counts = round(0.1 * t * COUNTS_PER_M)
            c.on_odometry(WheelOdometry(t, counts, -counts, k))
        c.on_attitude(reading(k, t))
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
def test_a_compass_whose_readings_change_is_not_frozen(reading) -> None:  # type: ignore[no-untyped-def]
    c, t = pivot(reading)
    assert t > 9.0 and "frozen" not in c.telemetry.extra.get("failsafe", "")


def test_without_encoders_the_stuck_check_still_judges() -> None:
    c, _t = pivot(lambda k, t: Attitude(t, 0.0, 1.0, -2.0), encoders=False)
    assert "frozen" not in c.telemetry.extra.get("failsafe", ""), c.telemetry.extra
