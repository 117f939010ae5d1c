"""A fix with HDOP 20 or more is no fix (review 10b of b8922d8, high).

b8922d8 kept such fixes (RMC-only fixes of a street canyon, HDOP 99.99, km off) from being a
geofence breach, but they still counted as fixes: the EKF weighted them to nothing, the GPS
stayed "fresh", and a robot whose wheels under-count (a wrong wheel size, slip) drove on past
the fence on true HDOP-20 fixes, its estimate far behind. Now ``has_usable_position`` refuses
them (``MEANINGLESS_HDOP``): the robot dead-reckons its allowance and holds, as when the
receiver reports no position.

The mission's one waypoint is 99 m north, the fence 100 m. The scripted robot moves only
while its motors are told to move (1 m/s north), its wheels count ``odo_scale`` of the
travel; a fix every whole second at the true position.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import replace
from typing import Any

import pytest

from tests.test_geofence_wild_fix import FENCE_M, HOME, M_PER_DEG_LAT, STEP_S, Robot
from x6wd.core.mission_files import Waypoint
from x6wd.core.records import Attitude, GpsFix, Mode, WheelOdometry
from x6wd.nav.controller import MEANINGLESS_HDOP, has_usable_position


def _drive(pattern: Callable[[int, float], dict[str, Any] | None], odo_scale: float) -> Robot:
    bot = Robot()
    bot.fix(0.0)
    odo_m = 0.0

    def roll(seconds: float, driving: bool) -> None:
        nonlocal odo_m
        for _ in range(round(seconds / STEP_S)):
            bot.now = round(bot.now + STEP_S, 6)
            last = bot.motors[-1] if bot.motors else None
            told = last is not None and (last.left_pct or last.right_pct)
            v_mps = 1.0 if driving and told else 0.0
            bot.north_m += v_mps * STEP_S
            odo_m += v_mps * STEP_S * odo_scale
            counts = round(odo_m / bot.m_per_count)
            bot.runner.odometry(WheelOdometry(bot.now, counts, counts, 0))
            bot.runner.attitude(Attitude(bot.now, 0.0, 0.0, 0.0))
            if abs(bot.now - round(bot.now)) < 1e-9:
                kw = pattern(round(bot.now), bot.north_m)
                if kw is not None:
                    bot.fix(**kw)

    roll(3.0, False)
    bot.runner.load_mission([Waypoint(HOME[0] + 99.0 / M_PER_DEG_LAT, HOME[1])])
    bot.runner.command("start")
    roll(200.0, True)
    return bot


@pytest.mark.parametrize("odo_scale", [0.3, 0.1])
def test_hdop_20_fixes_do_not_carry_an_under_counting_robot_past_the_fence(
    odo_scale: float,
) -> None:
    bot = _drive(lambda _s, n: {"north_m": n, "hdop": MEANINGLESS_HDOP}, odo_scale)
    # before: still RUNNING at 200 s, 100-200 m north with the estimate at 51 m
    assert bot.north_m < FENCE_M, bot.north_m
    assert bot.runner.controller.mode != Mode.RUNNING or not bot.motors[-1].left_pct
    assert any(s.new == "HOLD" and "no valid fix" in s.reason for s in bot.states), bot.states


def test_good_fixes_between_meaningless_ones_still_bound_the_robot() -> None:
    # one good fix in three: the good fixes outside still stop it at the fence
    bot = _drive(lambda s, n: {"north_m": n} if s % 3 == 0 else {"north_m": n, "hdop": 25.0}, 0.3)
    assert bot.north_m < FENCE_M + 5.0, bot.north_m


def test_the_rule() -> None:
    fix = GpsFix(t_s=0.0, valid=True, lat_deg=HOME[0], lon_deg=HOME[1], hdop=19.99)
    assert has_usable_position(fix)
    assert not has_usable_position(replace(fix, hdop=20.0))
    assert not has_usable_position(replace(fix, hdop=99.99))
    assert has_usable_position(replace(fix, hdop=None))


def test_the_log_says_the_fixes_were_refused_for_their_hdop(
    caplog: pytest.LogCaptureFixture,
) -> None:
    # review 10c: "the receiver reports no position" while it reported positions every second
    bot = Robot()
    bot.fix(0.0)
    with caplog.at_level(logging.WARNING, logger="x6wd.loop.runner"):
        for k in range(1, 6):
            bot.now = float(k)
            bot.fix(0.0, hdop=25.0)
            bot.runner.attitude(Attitude(bot.now, 0.0, 0.0, 0.0))
    assert bot.runner.fix_refused_hdop == 25.0
    text = " ".join(r.getMessage() for r in caplog.records)
    assert "no valid fix" in text and "HDOP 25.0" in text, text
    assert "reports no position" not in text
    bot.now = 6.0
    bot.fix(0.0)
    assert bot.runner.fix_refused_hdop is None
