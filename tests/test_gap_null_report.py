"""What the gap tool's report claims on a log without a significant gap (an outside audit of
``x6wd gap``, findings 2 and 3): no direction the "where" test refused, a header that says
what the null was made of, and no level calibration of layers fitted to one log's chance
departure (nor a FAIL that reads as the tool failing)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from x6wd.gap.diagnose import diagnose
from x6wd.gap.report import write_report
from x6wd.gap.stats import Cell
from x6wd.gap.surrogate import surrogate_run
from x6wd.gap.validate import Band, gap_direction

ROOT = Path(__file__).resolve().parents[1]
SCENARIO = ROOT / "config" / "scenarios" / "open_field.toml"


@pytest.fixture(scope="module")
def null_run(tmp_path_factory: pytest.TempPathFactory) -> tuple[str, Path]:
    """The audit's repro: the simulator's own 10 minutes of the open field (seed 7) against
    three of its seeds, no truth; the output directory holds an earlier run's
    calibrated.toml. (stdout, output directory)."""
    sim = tmp_path_factory.mktemp("sim7")
    subprocess.run(
        [sys.executable, "-m", "x6wd", "sim", str(SCENARIO), "--seed", "7", "--out", str(sim),
         "--quiet"],
        check=True, capture_output=True, timeout=300,
    )  # fmt: skip
    out = tmp_path_factory.mktemp("report")
    (out / "calibrated.toml").write_text(
        '# x6wd gap: fitted effects (x), then the level calibration\n[[effects]]\nname = "bias"\n'
    )
    done = subprocess.run(
        [sys.executable, "-m", "x6wd", "gap", "--real", str(sim / "gps.nmea"), "--scenario",
         str(SCENARIO), "--seeds", "3", "--out", str(out), "--quiet", "--no-figures"],
        check=True, capture_output=True, text=True, timeout=600,
    )  # fmt: skip
    assert done.stdout.startswith("no significant gap;"), done.stdout
    return done.stdout, out


def test_no_direction_is_claimed_without_a_gap(null_run: tuple[str, Path]) -> None:
    # it said "the simulator is quieter than the receiver from 1 to 32 s", read at |z| > 3
    # on octaves the family-wise test had just found within the spread
    _stdout, out = null_run
    md = (out / "report.md").read_text()
    way = md.split("## Which way", 1)[1].split("##", 1)[0]
    assert "Allan deviation within the test's family-wise limits at every octave" in way, way
    assert "(nearest: " in way, way
    assert "quieter than" not in way and "noisier than" not in way


def test_the_header_says_what_the_null_was_made_of(null_run: tuple[str, Path]) -> None:
    # it said "baseline: 20 runs (block bootstrap)" above a note on 3 logs' innovations
    _stdout, out = null_run
    md = (out / "report.md").read_text()
    header = next(line for line in md.splitlines() if line.startswith("- baseline: "))
    assert header.startswith(
        "- baseline: 3 sim log(s), fewer than 8: 20 replicates made of their innovations"
    ), header
    assert "block bootstrap" not in md


def test_no_calibration_is_offered_without_a_gap(null_run: tuple[str, Path]) -> None:
    # it wrote (and recommended "INSTEAD of effects.toml") a calibrated.toml of a 1.4-1.6 m
    # bias, a 0.38 correction and a 2.2 noise scale fitted to the simulator's own output,
    # and printed "validation ... FAIL"
    stdout, out = null_run
    assert "FAIL" not in stdout and "calibrated" not in stdout, stdout
    assert not (out / "calibrated.toml").exists()  # not even an earlier run's
    md = (out / "report.md").read_text()
    assert "no level calibration is fitted and no calibrated.toml written" in md
    assert "**FAIL**" not in md and "INSTEAD" not in md
    assert "| figure | real | simulated | difference | within tolerance | target |" in md
    validation = json.loads((out / "validation.json").read_text())
    assert validation["calibrated"] is None and validation["calibration"] == []
    # the scenario's 3 seeds themselves, not the few-logs null's 20 replicates (2026-12-03)
    assert validation["selected"]["runs"] == 3 and "not_calibrated" in validation
    assert "INSTEAD" not in (out / "effects.toml").read_text()


def test_direction_is_read_at_the_tests_limits_without_a_gap() -> None:
    cells = [Cell("log_adev", axis, f"tau={tau}s") for tau in (1, 2) for axis in ("east", "north")]
    z = np.array([4.0, 4.5, 1.0, -0.5])
    limits = np.full(4, 5.0)
    assert gap_direction(cells, z, limits, significant=False) == [Band("agrees", 1, 2)]
    assert gap_direction(cells, z, limits, significant=True) == [
        Band("quieter", 1, 1),
        Band("agrees", 2, 2),
    ]


def test_the_header_of_a_null_of_runs_and_of_few_logs(tmp_path: Path) -> None:
    runs = [surrogate_run(900.0, 1.0, np.random.default_rng(300 + i)) for i in range(8)]
    real = surrogate_run(900.0, 1.0, np.random.default_rng(8))
    for baseline, text in (
        (runs, "- baseline: 8 sim runs; "),
        (runs[:2], "- baseline: 2 sim log(s), fewer than 8: 20 replicates made of their "),
    ):
        d = diagnose(real, baseline, np.random.default_rng(0))
        assert not d.significant and d.calibration is None
        write_report(d, tmp_path, figures=False)
        assert text in (tmp_path / "report.md").read_text()


def test_a_calibrated_toml_the_tool_did_not_write_is_kept(tmp_path: Path) -> None:
    """Only an earlier run's file is removed on a log without a gap: a user's own
    hand-tuned calibrated.toml went too, unsaid (a second outside check)."""
    from x6wd.gap.report import remove_earlier_calibration

    mine = tmp_path / "calibrated.toml"
    mine.write_text("# my own hand-tuned calibration, keep\n")
    assert not remove_earlier_calibration(tmp_path) and mine.exists()
    mine.write_text("# x6wd gap: fitted effects (bias), then the level calibration\n")
    assert remove_earlier_calibration(tmp_path) and not mine.exists()
    assert not remove_earlier_calibration(tmp_path)  # none: nothing to do
