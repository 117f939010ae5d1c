"""The jump failsafe and the estimate's own uncertainty (docs/navigation.md, "Failsafes"): a
reset that lands inside the position's 99 % ellipse is the estimate settling where it said
it might be, so the mission drives on; one beyond it pauses as before
(tests/test_failsafe_controller.py)."""

from __future__ import annotations

import json
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import pytest

from tests.test_controller import SAFETY, at, att, fix
from tests.test_failsafe_controller import COUNTS_PER_M, FS
from x6wd.core.config import FailsafeConfig, GnssNoiseConfig, NavigationConfig
from x6wd.core.records import Mode, StateChange, WheelOdometry
from x6wd.nav.controller import Controller

ROOT = Path(__file__).resolve().parent.parent


def _stand_then_start(c: Controller, east_m: float, hdop: float, north_m: float) -> None:
    """5 s standing (compass 10 Hz, fixes 1 Hz ``east_m`` east of the robot at ``hdop``),
    then a mission to one waypoint ``north_m`` north of the robot started."""
    for k in range(0, 51):
        t = 0.1 * k
        c.on_odometry(WheelOdometry(t, 0, 0, k))
        c.on_attitude(att(t))
        if k % 10 == 0:
            sats = 4 if hdop > 5.0 else 8
            c.on_fix(replace(fix(t, east_m, 0.0), hdop=hdop, sats_used=sats))
    c.load_mission([at(0.0, north_m)], 5.0)
    c.start(5.0)


def _town_start(first_hdop: float) -> Controller:
    """Started on 5 s of fixes 35 m east of the robot with HDOP ``first_hdop``, then driven
    north 40 s at 1 m/s with fixes on the robot (HDOP 1.4)."""
    c = Controller(NavigationConfig(), SAFETY, 0.0, failsafe=FS)
    _stand_then_start(c, 35.0, first_hdop, 1000.0)
    for k in range(51, 451):
        t = 0.1 * k
        counts = round((t - 5.0) * COUNTS_PER_M)
        c.on_odometry(WheelOdometry(t, counts, counts, k))
        c.on_attitude(att(t))
        if k % 10 == 0:
            c.on_fix(replace(fix(t, 0.0, t - 5.0), hdop=1.4, sats_used=6))
        if c.mode != Mode.RUNNING:
            break
    return c


def test_a_start_on_poor_fixes_corrected_by_good_ones_drives_on() -> None:
    """An outside audit (town radio noise, the shipped route, 3 of 20 seeds): the EKF started
    on 4-satellite fixes 35 m off (HDOP 12, its σ 26 m), refused the good fixes that followed
    until 8 agreed, moved 35 m to them, and the jump failsafe paused the mission as "GPS back
    somewhere else, or the robot carried?" — neither was true."""
    c = _town_start(12.0)
    extra = c.telemetry.extra
    assert extra["ekf_gps_resets"] >= 1
    assert 30.0 < extra["ekf_last_reset_m"] < extra["ekf_last_reset_circle_m"], extra
    assert c.mode == Mode.RUNNING and "failsafe" not in extra, extra.get("failsafe")


def test_the_same_move_from_a_confident_start_still_pauses() -> None:
    """HDOP 1.2 at the start: the estimate said it was within a few metres; 35 m is a
    surprise (another device on the port, a carried robot) and pauses as before."""
    c = _town_start(1.2)
    extra = c.telemetry.extra
    assert extra["ekf_last_reset_m"] > extra["ekf_last_reset_circle_m"], extra
    assert c.mode == Mode.PAUSED and c.command.is_stop
    assert extra["failsafe"].startswith("position jumped 3"), extra["failsafe"]


@pytest.mark.parametrize("seed", [4, 13])
def test_the_shipped_route_in_town_noise_reaches_its_waypoints_with_the_shipped_config(
    tmp_path: Path, seed: int
) -> None:
    """The audit's command: default.toml at the shipped building scenarios' noise level
    (env_noise_db 10), config/x6wd.toml. Seed 4 paused on "position jumped"; seed 13 too,
    after taking two waypoints as reached 41 and 38 m from them (the jump rule alone made
    that a "completed" mission)."""
    text = (ROOT / "config/scenarios/default.toml").read_text()
    town = text.replace("env_noise_db = 1.0", "env_noise_db = 10.0", 1)
    assert town != text
    scen = tmp_path / "town.toml"
    scen.write_text(town)
    out = tmp_path / "out"
    cmd = [sys.executable, "-m", "x6wd", "sim", str(scen), "--seed", str(seed), "--quiet"]
    cmd += ["--config", str(ROOT / "config/x6wd.toml"), "--out", str(out)]
    proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=300)
    summary = json.loads((out / "summary.json").read_text())
    assert summary["completed"], (proc.stdout, proc.stderr)
    errors_m = [a["true_error_m"] for a in summary["extra"]["arrivals"]]
    assert len(errors_m) == 4 and max(errors_m) < 8.0, errors_m
    if seed == 13:  # it waited 40-50 s for the sky at the start: a hold the summary counts,
        # and the log says so in order (the start-up wait's line had come at the run's end)
        assert summary["hold_periods"] >= 1 and summary["hold_time_s"] >= 30.0, summary
        start = proc.stderr.index("state IDLE -> HOLD state: position estimate not ready")
        wait = proc.stderr.index("state HOLD -> HOLD state: position too uncertain to tell")
        assert start < wait, proc.stderr
    assert "inside its own 99 % ellipse" in proc.stderr, proc.stderr


# --- no waypoint taken as reached inside a 50 m error radius ---------------------------------


def _poor_start(
    fs: FailsafeConfig = FS, nav: NavigationConfig | None = None, poor_s: float = 20.0
) -> tuple[Controller, list[tuple[float, str, str]]]:
    """Standing 5 s on 4-satellite fixes 35 m east (HDOP 12), a mission to a waypoint 25 m
    north started, the poor fixes going on ``poor_s`` more seconds, then 30 s of good ones
    on the robot (HDOP 1.4). The wheels count as if driving at 1 m/s whenever commanded.
    Returns the controller and its (t, mode, hold_reason) each second."""
    c = Controller(nav or NavigationConfig(), SAFETY, 0.0, failsafe=fs)
    seen: list[tuple[float, str, str]] = []
    counts = 0
    for k in range(0, round(10 * (5.0 + poor_s + 30.0))):
        t = 0.1 * k
        if k == 50:
            c.load_mission([at(0.0, 25.0)], t)
            c.start(t)
        if not c.command.is_stop:
            counts += round(0.1 * COUNTS_PER_M)
        c.on_odometry(WheelOdometry(t, counts, counts, k))
        c.on_attitude(att(t))
        if k % 10 == 0:
            if t < 5.0 + poor_s:
                c.on_fix(replace(fix(t, 35.0, 0.0), hdop=12.0, sats_used=4))
            else:
                c.on_fix(replace(fix(t, 0.0, counts / COUNTS_PER_M), hdop=1.4, sats_used=6))
            seen.append((t, str(c.mode), c.telemetry.hold_reason))
    return c, seen


def test_a_waypoint_inside_a_50_m_error_radius_is_not_reached_the_robot_waits() -> None:
    """An outside check (town noise, seed 13): started on 4-satellite fixes 35-45 m off
    (sigma 24 m), the robot took its first two waypoints as reached 41 and 38 m from them.
    Now it holds, naming why, and drives on once the fixes are good."""
    c, seen = _poor_start()
    held = [t for t, mode, why in seen if why.startswith("position too uncertain to tell")]
    assert held and min(held) <= 6.0 and max(held) >= 24.0, seen
    assert all(mode == "RUNNING" for t, mode, _ in seen if t >= 5.0), seen
    assert not [o for o in seen if o[0] > 40.0 and o[2]], seen  # good fixes: it drives
    assert c.telemetry.extra.get("ekf_gps_resets", 0) >= 1


def test_the_wait_ends_in_a_pause_after_position_timeout_s_even_with_return_configured() -> None:
    fs = replace(FS, position_timeout_s=10.0, sensor_action="return")
    c, seen = _poor_start(fs, poor_s=40.0)
    paused = [t for t, mode, _ in seen if mode == "PAUSED"]
    assert paused and 15.0 <= paused[0] <= 17.0, seen
    assert c.mode == Mode.PAUSED and c.command.is_stop
    why = c.telemetry.extra["failsafe"]
    assert why == "position too uncertain to tell whether waypoint 1 is reached for 10 s", why


def test_arrival_max_error_m_0_drives_on_as_before() -> None:
    _c, seen = _poor_start(nav=NavigationConfig(arrival_max_error_m=0.0))
    assert not [o for o in seen if o[2].startswith("position too uncertain")], seen


# --- a review of the above: a calibrated site's LCE, and the hold timers ---------------------


def _north_then_elsewhere(lce_m: float, hdop: float, jump_m: float) -> Controller:
    """A calibrated site (``lce_default_m`` = ``lce_m``): driving north at 1 m/s towards a
    waypoint 1 km away on fixes on the robot (HDOP ``hdop``), and from t = 40 s every fix
    ``jump_m`` east (a receiver back somewhere else). Returns the controller at 90 s."""
    c = Controller(
        NavigationConfig(),
        SAFETY,
        0.0,
        failsafe=FS,
        gnss_noise=GnssNoiseConfig(lce_default_m=lce_m),
    )
    counts = 0
    _stand_then_start(c, 0.0, hdop, 1000.0)
    for k in range(51, 900):
        t = 0.1 * k
        if not c.command.is_stop:
            counts += round(0.1 * COUNTS_PER_M)
        c.on_odometry(WheelOdometry(t, counts, counts, k))
        c.on_attitude(att(t))
        if k % 10 == 0:
            east_m = jump_m if t >= 40.0 else 0.0
            c.on_fix(replace(fix(t, east_m, counts / COUNTS_PER_M), hdop=hdop))
    return c


@pytest.mark.parametrize(("lce_m", "hdop", "jump_m"), [(10.1, 2.0, 40.0), (8.0, 1.5, 30.0)])
def test_a_gps_back_elsewhere_at_a_noisy_site_still_pauses(
    lce_m: float, hdop: float, jump_m: float
) -> None:
    """A review: with a calibrated LCE of 8-10 m (docs/gnss_calibration.md's urban example)
    the ellipse before the reset was 36-59 m wide from the noise model alone, and a GPS back
    30-40 m away drove on. Only poor geometry (an ellipse beyond what the site's noise gives
    at HDOP 3) makes a reset expected."""
    c = _north_then_elsewhere(lce_m, hdop, jump_m)
    extra = c.telemetry.extra
    assert extra["ekf_last_reset_m"] < extra["ekf_last_reset_circle_m"], extra  # inside ...
    assert c.mode == Mode.PAUSED, extra.get("failsafe")  # ... and still a surprise
    assert extra["failsafe"].startswith(f"position jumped {jump_m:.0f} m: ")


@pytest.mark.parametrize("lce_m", [5.0, 8.0, 10.0])
def test_a_calibrated_site_under_an_open_sky_reaches_its_waypoints_without_waiting(
    tmp_path: Path, lce_m: float
) -> None:
    """A review: with ``lce_default_m`` 8 or 10 the EKF's radius under an open sky (HDOP 1.1)
    was over the 20 m limit: default.toml paused at 0/4 after 120 s, zigzag stopped and
    started 219 times. The limit is at least what the site's noise gives at HDOP 3."""
    text = (ROOT / "config/x6wd.toml").read_text()
    cfg = text.replace("ase_m = 1.5 ", f"lce_default_m = {lce_m}\nase_m = 1.5 ", 1)
    assert cfg != text
    (tmp_path / "x6wd.toml").write_text(cfg)
    out = tmp_path / "out"
    cmd = [sys.executable, "-m", "x6wd", "sim", str(ROOT / "config/scenarios/default.toml")]
    cmd += ["--config", str(tmp_path / "x6wd.toml"), "--out", str(out), "--quiet"]
    proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=300)
    summary = json.loads((out / "summary.json").read_text())
    assert summary["completed"] and summary["hold_periods"] == 0, (proc.stdout, proc.stderr)


def test_a_lost_fix_after_a_long_wait_is_timed_from_its_own_start() -> None:
    """A review: held 35 s for a poor position, one invalid fix fired "no valid fix for 30 s"
    at once (the hold timer was shared), and with sensor_action "return" a return started on
    that position. Now each wait has its own clock; the poor position's is the time held for
    this waypoint in all, so the single fixes lost every 10 s neither fire the sensor timeout
    nor restart the wait."""
    fs = replace(FS, sensor_action="return")
    c = Controller(NavigationConfig(), SAFETY, 0.0, failsafe=fs)
    _stand_then_start(c, 35.0, 12.0, 25.0)
    fired: list[tuple[float, str]] = []
    for k in range(51, 1600):
        t = 0.1 * k
        c.on_odometry(WheelOdometry(t, 0, 0, k))
        c.on_attitude(att(t))
        if k % 10 == 0:
            lost = k % 100 == 0  # one fix in ten invalid
            c.on_fix(fix(t, valid=False) if lost else replace(fix(t, 35.0, 0.0), hdop=12.0))
        why = c.telemetry.extra.get("failsafe")
        if why and (not fired or fired[-1][1] != why):
            fired.append((round(t, 1), why))
    assert fired, "the wait never ended"
    t_fired, why = fired[0]
    assert why.startswith("position too uncertain to tell whether waypoint 1 is reached for"), fired
    assert (
        t_fired >= 5.0 + 120.0 and c.mode == Mode.PAUSED and not c.telemetry.extra.get("returning")
    ), fired


def test_a_lost_fix_and_the_wait_taking_turns_still_end_in_the_sensor_timeout() -> None:
    """A second review: a receiver that gives a 4-satellite fix (HDOP 18) one second in 29,
    and no fix between, had the robot hold 700 s with no failsafe: each fix turned the hold
    into a wait for the sky, which restarted the sensor's clock, and the wait's own clock ran
    only a second each time. A sensor's hold now counts its time in all since the robot
    last drove; and the log names each turn."""
    c = Controller(NavigationConfig(), SAFETY, 0.0, failsafe=FS)
    _stand_then_start(c, 35.0, 18.0, 25.0)
    turns: list[str] = []
    for k in range(51, 3000):
        t = 0.1 * k
        c.on_odometry(WheelOdometry(t, 0, 0, k))
        outs = c.on_attitude(att(t))
        if k % 10 == 0:
            second = round(t) % 29
            valid = replace(fix(t, 35.0, 0.0), hdop=18.0, sats_used=4)
            outs += c.on_fix(valid if second == 10 else fix(t, valid=False))
        turns += [o.reason for o in outs if isinstance(o, StateChange) and o.old == o.new]
        if c.mode != Mode.RUNNING:
            break
    assert c.mode == Mode.PAUSED and t < 5.0 + 60.0, (t, turns)
    assert c.telemetry.extra["failsafe"] == "no valid fix for 30 s"
    assert "state: no valid fix" in turns, turns
