"""The gap tool's static logs, round 18 (an outside audit): the robot's own mission log,
driving at 0.94 m/s within 14.5 m of its centre, passed the speed and spread limits as a
static receiver and its route was scored as error ("no significant gap", its own table at
-94 %); and mission --sim runs were taken against a static real log given a point truth or
none. Both are now refused (exit 2), by the steady speed that x6wd calibrate gnss already
used (x6wd.core.motion) and by the truth.csv beside each --sim log."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from x6wd.gap.io import moving_text, read_track

ROOT = Path(__file__).resolve().parents[1]
SCENARIOS = ROOT / "config" / "scenarios"


def _sim(out: Path, scenario: str, *extra: str) -> Path:
    """``x6wd sim`` as a user runs it; its gps.nmea (truth.csv beside it)."""
    proc = subprocess.run(
        [sys.executable, "-m", "x6wd", "sim", str(SCENARIOS / scenario), "--out", str(out),
         "--quiet", *extra],
        capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert proc.returncode in (0, 1), proc.stderr
    return out / "gps.nmea"


@pytest.fixture(scope="module")
def runs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    tmp = tmp_path_factory.mktemp("runs")
    return {
        "mission1": _sim(tmp / "m1", "default.toml"),
        "mission2": _sim(tmp / "m2", "default.toml", "--seed", "2"),
        "static": _sim(tmp / "s", "open_field.toml", "--duration", "600"),
    }


def test_a_robot_driving_within_the_old_limits_is_a_moving_log(runs: dict[str, Path]) -> None:
    said = moving_text(read_track(runs["mission1"]))
    assert said is not None and "steady speed" in said, said
    assert moving_text(read_track(runs["static"])) is None


def test_the_gap_tool_refuses_a_mission_log_without_its_truth_track(
    runs: dict[str, Path], tmp_path: Path
) -> None:
    proc = subprocess.run(
        [sys.executable, "-m", "x6wd", "gap", "--real", str(runs["mission1"]), "--scenario",
         str(SCENARIOS / "open_field.toml"), "--seeds", "3", "--out", str(tmp_path / "g")],
        capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert proc.returncode == 2, proc.stderr[-1500:]
    assert "the log moves (a steady speed" in proc.stderr and "--truth-track" in proc.stderr


@pytest.mark.parametrize("truth", [["--truth", "51.752,-1.2577"], []], ids=["point", "none"])
def test_mission_runs_against_a_static_real_log_are_refused(
    runs: dict[str, Path], tmp_path: Path, truth: list[str]
) -> None:
    sims = [runs["mission1"], runs["mission2"]]
    proc = subprocess.run(
        [sys.executable, "-m", "x6wd", "gap", "--real", str(runs["static"]), *truth,
         "--sim", *map(str, sims), "--out", str(tmp_path / "g")],
        capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert proc.returncode == 2, proc.stderr[-1500:]
    assert "beside each of these moves, but the real log stands still" in proc.stderr
    # without their truth.csv they are judged by their own steps: refused all the same
    for sim in sims:
        shutil.move(sim.parent / "truth.csv", sim.parent / "truth.csv.away")
    proc = subprocess.run(
        [sys.executable, "-m", "x6wd", "gap", "--real", str(runs["static"]), *truth,
         "--sim", *map(str, sims), "--out", str(tmp_path / "g2")],
        capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    for sim in sims:
        shutil.move(sim.parent / "truth.csv.away", sim.parent / "truth.csv")
    assert proc.returncode == 2, proc.stderr[-1500:]
    assert "steady speed" in proc.stderr, proc.stderr[-1500:]
