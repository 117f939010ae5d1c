"""A mission that runs out of ``--duration`` ends without a false compass fault.

The last GPS burst arrives up to ~0.5 s after the last physics step; the closing tick then
found the compass's last sample stale, and every such run ended with ``state STRAIGHT -> HOLD
state: attitude stale`` on stderr (even with --quiet) and a HOLD with a motor stop for
"attitude stale" in its recording (round 14 benchmark audit). The real CLI, real files."""

from __future__ import annotations

from pathlib import Path

import pytest

from x6wd.app.cli import main as x6wd_main

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize("baud", [9600, 4800])  # the last burst ~0.5 s or ~2 s on the wire
def test_a_run_cut_by_its_duration_reports_no_stale_compass(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], baud: int
) -> None:
    text = (ROOT / "config" / "scenarios" / "default.toml").read_text(encoding="utf-8")
    assert "\nbaud = 9600\n" in text
    scenario = tmp_path / "s.toml"
    scenario.write_text(text.replace("\nbaud = 9600\n", f"\nbaud = {baud}\n"), encoding="utf-8")
    tmp_path = tmp_path / "out"
    argv = ["sim", str(scenario), "--duration", "30", "--quiet", "--out", str(tmp_path)]
    assert x6wd_main(argv) in (0, 1)  # 1: the mission is not finished in 30 s
    assert "attitude stale" not in capsys.readouterr().err
    recording = (tmp_path / "recording.jsonl").read_text(encoding="utf-8")
    assert '"sim_end"' in recording and "attitude stale" not in recording


def test_a_returns_designed_stop_is_not_a_hold_period(tmp_path: Path) -> None:
    # Review of f753111: the return's 0.5 s stop counted as "HOLD periods 1 (0.5 s)" (and
    # in sweeps' hold_time_s), a figure meant for holds on a stale or lost sensor
    from sim_backend.mission import run_mission
    from sim_backend.world import loads_world

    scenarios = ROOT / "config" / "scenarios"
    text = (scenarios / "default.toml").read_text(encoding="utf-8")
    text = text.replace("[vehicle]", "[vehicle]\nstuck_from_s = 20.0\nstuck_until_s = 33.0\n", 1)
    text += '\n[failsafe]\nstuck_action = "return"\n'
    s = run_mission(loads_world(text, scenarios), tmp_path, 1, 60.0)
    assert s.extra["failsafes"] and "stuck" in s.extra["failsafes"][0][1], s.extra["failsafes"]
    assert s.hold_periods == 0, s.extra["holds_s"]
