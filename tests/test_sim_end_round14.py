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


def test_a_run_cut_by_its_duration_reports_no_stale_compass(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    scenario = ROOT / "config" / "scenarios" / "default.toml"
    argv = ["sim", str(scenario), "--duration", "30", "--quiet", "--out", str(tmp_path)]
    assert x6wd_main(argv) in (0, 1)  # 1: the mission is not finished in 30 s
    assert "attitude stale" not in capsys.readouterr().err
    recording = (tmp_path / "recording.jsonl").read_text(encoding="utf-8")
    assert '"sim_end"' in recording and "attitude stale" not in recording
