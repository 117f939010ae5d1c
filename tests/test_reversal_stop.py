"""A side never flips from forward to reverse without a stop (controller.REVERSE_STOP_S).

The motor board takes whatever it is sent: ``+60`` then ``-40`` 50 ms later slams the gearbox
and draws a stall current through the driver. Every pivot start from the straight or an arc
did that to one side, and a pivot that swings the other way to both. Sans-IO cases for the
rule's edges, a blocked robot whose pivot swings to and fro (the stuck check judges the drive
asked for, not the held one), and whole missions on the shipped config, whose motor records
are checked side by side.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from sim_backend.mission import run_mission
from sim_backend.world import load_world, loads_world, with_robot_config
from tests.test_controller import NAV, SAFETY, at, att, fix, running, split
from tests.test_failsafe_controller import FS
from x6wd.core.records import Mode, NavState, WheelOdometry
from x6wd.nav.controller import REVERSE_STOP_NOTE, REVERSE_STOP_S, Controller

ROOT = Path(__file__).resolve().parents[1]
SCENARIOS = ROOT / "config" / "scenarios"


def test_a_pivot_from_the_straight_holds_the_reversing_side_for_the_stop() -> None:
    c = running()  # 100 m north
    c.on_fix(fix(1.0))
    _, cmd, _ = split(c.on_attitude(att(1.0, 0.0)))
    assert (cmd.left_pct, cmd.right_pct) == (60.0, 60.0)
    _, cmd, tel = split(c.on_attitude(att(1.05, 300.0)))  # the target 60° clockwise
    assert tel.state == NavState.TURN_RIGHT
    # the left side drives on into the pivot; the right one stops first
    assert (cmd.left_pct, cmd.right_pct) == (40.0, 0.0)
    assert cmd.reason == f"TURN_RIGHT; {REVERSE_STOP_NOTE}"
    t = 1.05
    while t + 0.05 < 1.05 + REVERSE_STOP_S - 1e-9:
        t += 0.05
        _, cmd, _ = split(c.on_attitude(att(t, 300.0)))
        assert (cmd.left_pct, cmd.right_pct) == (40.0, 0.0), t
    _, cmd, _ = split(c.on_attitude(att(1.05 + REVERSE_STOP_S, 300.0)))
    assert (cmd.left_pct, cmd.right_pct) == (40.0, -40.0) and cmd.reason == "TURN_RIGHT"


def test_a_side_that_stood_still_long_enough_reverses_at_once_and_a_stop_is_never_late() -> None:
    c = Controller(NAV, SAFETY)
    _, cmd, _ = split(c.manual_drive(50.0, 50.0, 2.0, 0.0))
    assert (cmd.left_pct, cmd.right_pct) == (50.0, 50.0)
    _, cmd, _ = split(c.stop(0.1))  # a stop is never held back
    assert cmd.is_stop
    _, cmd, _ = split(c.manual_drive(-50.0, -50.0, 2.0, 0.1 + REVERSE_STOP_S))
    assert (cmd.left_pct, cmd.right_pct) == (-50.0, -50.0) and cmd.reason == "manual"
    # a pivot key while reversing: the left side must reverse; in manual drive both sides
    # wait (one side alone would swing the robot where the operator did not ask), and the
    # stop counts from the flip
    _, cmd, _ = split(c.manual_drive(50.0, -50.0, 2.0, 1.0))
    assert (cmd.left_pct, cmd.right_pct) == (0.0, 0.0)
    _, cmd, _ = split(c.manual_drive(50.0, -50.0, 2.0, 1.0 + 0.6 * REVERSE_STOP_S))
    assert (cmd.left_pct, cmd.right_pct) == (0.0, 0.0)
    _, cmd, _ = split(c.tick(1.0 + REVERSE_STOP_S))
    assert (cmd.left_pct, cmd.right_pct) == (50.0, -50.0)
    # a flip back before the stop ended: the side never reversed, so it drives at once
    c.manual_drive(-50.0, 50.0, 2.0, 2.0)  # both held
    _, cmd, _ = split(c.manual_drive(50.0, -50.0, 2.0, 2.1))
    assert (cmd.left_pct, cmd.right_pct) == (50.0, -50.0)


def test_a_blocked_robot_whose_pivot_swings_to_and_fro_is_still_caught_stuck() -> None:
    """The target dead behind: the paper's steering turns right at 179° and left at 181°,
    and a compass wavering across the wrap swings the pivot every 0.2 s. Held at 0 at each
    swing the robot never moves; the stuck check judges the pivot asked for, so it pauses
    (judged on the held command the clocks restarted at every swing: it spun on for ever)."""
    c = Controller(NAV, SAFETY, failsafe=FS)
    c.load_mission([at(0.0, 100.0)], 0.0)
    c.start(0.0)
    held = 0
    for i in range(int(20.0 / 0.05)):
        t = 0.05 * i
        if i % 20 == 0:
            c.on_fix(fix(t))
        c.on_odometry(WheelOdometry(t, 0, 0, i))  # the wheels count nothing: blocked
        _, cmd, _ = split(c.on_attitude(att(t, 179.0 if (i // 4) % 2 else 181.0)))
        held += cmd.reason.endswith(REVERSE_STOP_NOTE)
        if c.mode != Mode.RUNNING:
            break
    assert held > 20  # the premise: the swings were held
    assert c.mode == Mode.PAUSED, c.telemetry.extra
    assert str(c.telemetry.extra["failsafe"]).startswith("stuck (the wheels: no motion in 10 s")


def _flips_without_stop(records: list[dict[str, object]]) -> list[str]:
    """Each side's sign changes in the motor records with less than REVERSE_STOP_S of
    commanded 0 before them."""
    bad = []
    motors = [r["data"] for r in records if r["type"] == "motor"]
    for side in ("left_pct", "right_pct"):
        sign, zero_t = 0, None
        for m in motors:
            assert isinstance(m, dict)
            v, t = m[side], m["t_s"]
            s = (v > 0) - (v < 0)
            if s == 0:
                zero_t = t if zero_t is None else zero_t
                continue
            if sign and s != sign and (zero_t is None or t - zero_t < REVERSE_STOP_S - 1e-6):
                bad.append(f"{side} {sign:+d} -> {v:+.0f} at {t:.2f} s (0 since {zero_t})")
            sign, zero_t = s, None
    return bad


@pytest.mark.parametrize("steering", ["shipped", "paper"])
def test_missions_on_the_shipped_config_never_reverse_a_side_without_a_stop(
    tmp_path: Path, steering: str
) -> None:
    """The default scenario with the robot's own config (pivot_arc) and with the paper's
    steering: many pivots, each starting from the straight; on the code before, 267 flips
    without a stop in 20 seeds of the first."""
    world = load_world(SCENARIOS / "default.toml")
    if steering == "paper":  # the scenario's own key, over the robot's (with its Δφ)
        text = (SCENARIOS / "default.toml").read_text(encoding="utf-8")
        assert "\n[navigation]" not in text
        text += '\n[navigation]\nsteering = "paper"\ndelta_x_m = 3.0\ndelta_y_m = 3.0\n'
        world = loads_world(text, base_dir=SCENARIOS, source=str(SCENARIOS / "default.toml"))
    world = with_robot_config(world, ROOT / "config" / "x6wd.toml")
    summary = run_mission(world, tmp_path, seed=3)
    records = [json.loads(line) for line in (tmp_path / "recording.jsonl").open()]
    assert sum(r["type"] == "motor" for r in records) > 50  # the premise: it drove
    assert any(REVERSE_STOP_NOTE in str(r["data"].get("reason")) for r in records)
    assert _flips_without_stop(records) == []
    assert summary.completed


def test_a_gps_drift_over_one_stretch_then_a_jump_does_not_blame_the_compass() -> None:
    """The jump's reason names the compass only when the heading check has doubted it over
    two stretches: one bent by a GPS drift beside a building (2 m/s east for 8 s while the
    robot drives north, compass right) is the GPS's, and so is the 40 m jump after it (an
    outside review: "a compass fault?" after one window)."""
    from tests.test_failsafe_controller import COUNTS_PER_M, drive_north, ekf_driving_north

    c = ekf_driving_north(FS)
    assert drive_north(c, 2.0, 10.0, lambda t: 0.0) is None

    def east_m(t: float) -> float:
        return 0.0 if t < 12.0 else 2.0 * (t - 12.0) if t < 20.0 else 16.0 + 40.0

    for k in range(1, 400):
        t = 12.0 + 0.1 * k
        counts = round((t - 2.0) * COUNTS_PER_M)
        c.on_odometry(WheelOdometry(t, counts, counts, k))
        c.on_attitude(att(t, 0.0))
        if k % 10 == 0:
            c.on_fix(fix(t, east_m(t), t - 2.0))
        if c.mode != Mode.RUNNING:
            break
    why = str(c.telemetry.extra["failsafe"])
    assert why.startswith("position jumped") and "GPS back somewhere else" in why, why
