"""The sim summary reports the time the mission stood paused (outside audit 10a, finding B).

A failsafe's pause moves the robot to IDLE with the mission PAUSED, which "HOLD periods"
(the HOLD state) does not count: a 45 s GPS outage printed "HOLD periods 1 (30.0 s)" and
"failsafe at 57.8 s" while the robot stood still 342 s more. Now ``summary.json`` has
``extra.paused_s`` ([start, end, why] per pause) and ``extra.paused_time_s``, and the printed
summary a "paused" line per pause. Fast-time missions on the robot's defaults.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from sim_backend.mission import run_mission
from sim_backend.world import loads_world
from x6wd.loop.runner import Runner

ROOT = Path(__file__).resolve().parent.parent
SCENARIOS = ROOT / "config" / "scenarios"
DEFAULT = (SCENARIOS / "default.toml").read_text(encoding="utf-8")


def _world(duration_s: float, extra: str = "") -> str:
    assert "duration_s = 400.0" in DEFAULT
    return DEFAULT.replace("duration_s = 400.0", f"duration_s = {duration_s}") + "\n" + extra


def test_a_failsafe_pause_to_the_end_is_reported(tmp_path: Path) -> None:
    """A GPS outage from 8 s to the end, sensor timeout 5 s: held from about 8 s, paused
    5 s later until the run's end; the pause is in summary.json and printed."""
    world = loads_world(
        _world(
            30.0,
            '[[effects]]\nname = "outage"\nstart_s = 8.0\nduration_s = 100.0\n'
            "[failsafe]\nsensor_timeout_s = 5.0\n[safety]\ngps_outage_max_m = 0.0\n",
        ),
        base_dir=SCENARIOS,
    )
    summary = run_mission(world, tmp_path)
    fs_t, fs_why = summary.extra["failsafes"][0]
    assert fs_why == "no valid fix for 5 s"
    assert 13.0 <= fs_t <= 15.0
    paused = summary.extra["paused_s"]
    assert len(paused) == 1
    start_s, end_s, why = paused[0]
    assert start_s == pytest.approx(fs_t) and why == fs_why
    assert end_s == summary.sim_time_s  # to the run's end (was half a tick past it)
    assert summary.extra["paused_time_s"] == pytest.approx(end_s - start_s, abs=0.01)
    assert summary.extra["paused_time_s"] > 14.0
    # HOLD periods keep their meaning: the hold before the failsafe only
    assert summary.hold_periods == 1 and summary.hold_time_s == pytest.approx(5.0, abs=1.1)
    on_disk = json.loads((tmp_path / "summary.json").read_text(encoding="utf-8"))
    assert on_disk["extra"]["paused_s"] == paused
    line = f"  paused              {end_s - start_s:.1f} s (since {start_s:.1f} s: {why})"
    assert line in summary.text().splitlines(), summary.text()


def test_an_operator_pause_and_resume_is_reported_with_its_end(tmp_path: Path) -> None:
    """An operator pauses at 5 s and resumes at 12 s: a 7 s pause, printed with both ends;
    a run without a pause prints no "paused" line."""
    world = loads_world(_world(30.0), base_dir=SCENARIOS)

    def operator(t_s: float, runner: Runner) -> None:
        if abs(t_s - 5.0) < 1e-9:
            runner.command("pause")
        elif abs(t_s - 12.0) < 1e-9:
            runner.command("resume")

    summary = run_mission(world, tmp_path / "a", operator=operator)
    assert summary.extra["paused_s"] == [[5.0, 12.0, "pause"]]
    assert summary.extra["paused_time_s"] == pytest.approx(7.0)
    assert "  paused              7.0 s (5.0-12.0 s: pause)" in summary.text().splitlines()

    plain = run_mission(world, tmp_path / "b")
    assert plain.extra["paused_s"] == [] and plain.extra["paused_time_s"] == 0.0
    assert "paused" not in plain.text()
