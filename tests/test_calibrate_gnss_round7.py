"""x6wd calibrate gnss, round 7 (an outside audit, /tmp/audit1/repro): a drive matched against
the wrong reference was written as an LCE map of tens of metres, exit 0."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from tests.test_calibrate_gnss import (
    loop_track,
    sim_fixes,
    truth_series,
    world,
    write_recording,
    write_truth_csv,
)
from x6wd.app import cli

ROOT = Path(__file__).resolve().parent.parent


def _one_error_line(err: str) -> str:
    lines = [ln for ln in err.splitlines() if "error" in ln]
    assert len(lines) == 1 and "Traceback" not in err, err
    return lines[0]


def test_a_drive_against_a_standing_robots_reference_is_refused(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # the audit: a zigzag drive against a standing robot's truth.csv -> lce_default_m 77.7 m
    w = world(re=0.8, ase=0.0)
    t, pos = loop_track(laps=2)
    drive = write_recording(tmp_path / "drive.jsonl", sim_fixes(w, 4, t, pos))
    standing = write_truth_csv(tmp_path / "standing.csv", truth_series(w, t, np.zeros_like(pos)))
    out = tmp_path / "gnss.toml"
    argv = ["calibrate", "gnss", "--drive", str(drive), "--reference", str(standing),
            "--re-m", "0.5", "--ase-m", "0.5", "--out", str(out)]  # fmt: skip
    assert cli.main(argv) == 2
    captured = capsys.readouterr()
    line = _one_error_line(captured.err)
    assert str(drive) in line and str(standing) in line, line
    assert "median" in line and "m (at HDOP 1)" in line, line
    assert "lce_default_m" not in captured.out and not out.exists()
    # the drive against its own reference is taken
    own = write_truth_csv(tmp_path / "own.csv", truth_series(w, t, pos))
    argv[5] = str(own)
    assert cli.main(argv) == 0
    capsys.readouterr()


def test_a_reference_covering_a_third_of_the_drive_is_refused(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    w = world(re=0.8, ase=0.0)
    t, pos = loop_track(laps=3)
    drive = write_recording(tmp_path / "drive.jsonl", sim_fixes(w, 4, t, pos))
    n = t.size // 3
    part = write_truth_csv(tmp_path / "part.csv", truth_series(w, t[:n], pos[:n]))
    argv = ["calibrate", "gnss", "--drive", str(drive), "--reference", str(part),
            "--re-m", "0.5", "--ase-m", "0.5"]  # fmt: skip
    assert cli.main(argv) == 2
    line = _one_error_line(capsys.readouterr().err)
    assert str(drive) in line and str(part) in line and "%" in line, line


@pytest.mark.slow
def test_the_audits_zigzag_drive_against_the_default_missions_truth_is_refused(
    tmp_path: Path,
) -> None:
    # repro/r1_gnss_wrong_reference.sh, through the real simulator and the console script
    x6wd = [sys.executable, "-m", "x6wd"]
    for scen, seed, name in (("zigzag", 1, "zz"), ("default", 2, "df")):
        subprocess.run(
            [*x6wd, "sim", str(ROOT / "config" / "scenarios" / f"{scen}.toml"), "--seed",
             str(seed), "--out", str(tmp_path / name), "--quiet"],
            check=True, capture_output=True, cwd=ROOT,
        )  # fmt: skip
    drive, wrong = tmp_path / "zz" / "recording.jsonl", tmp_path / "df" / "truth.csv"
    r = subprocess.run(
        [*x6wd, "calibrate", "gnss", "--drive", str(drive), "--reference", str(wrong),
         "--re-m", "1.0", "--ase-m", "1.5"],
        capture_output=True, text=True, cwd=ROOT,
    )  # fmt: skip
    assert r.returncode == 2 and "lce_default_m" not in r.stdout, r.stdout
    line = _one_error_line(r.stderr)
    assert str(drive) in line and str(wrong) in line and "72 of 234" in line, line
    # its own truth.csv is taken
    r = subprocess.run(
        [*x6wd, "calibrate", "gnss", "--drive", str(drive), "--reference",
         str(tmp_path / "zz" / "truth.csv"), "--re-m", "1.0", "--ase-m", "1.5"],
        capture_output=True, text=True, cwd=ROOT,
    )  # fmt: skip
    assert r.returncode == 0, r.stderr
