"""``x6wd sweep ... --seeds 1`` on a finished sweep (an outside fresh-machine audit): the
tables are of the runs this command plans, and the finished runs of the folder outside them
are kept and said to be there, on stderr and in summary.md, with the command that tables
them again. In this process: nothing is left to run, so no cluster starts."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import pytest

from tests.test_sweep import sweep_file


def _table(out: Path) -> list[dict[str, str]]:
    with open(out / "results.csv", newline="") as f:
        return list(csv.DictReader(f))


def test_a_quick_look_at_a_finished_sweep_says_which_runs_it_leaves_out(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from sim_backend.executor import Executor
    from sim_backend.sweep import load_sweep, run_sweep
    from x6wd.app.cli import main

    grid = '[set]\nduration_s = 5.0\n[grid]\nnavigation.position_source = ["ekf", "raw"]\n'
    f = sweep_file(tmp_path, "seeds = 3\n" + grid)
    out = tmp_path / "out"
    with Executor(inline=True) as ex:
        assert not run_sweep(load_sweep(f), out, ex).failed  # 2 cells x 3 seeds
    runs = sorted(p.name for p in (out / "runs").glob("*.json"))
    assert len(runs) == 6
    quick = ["sweep", str(f), "--out", str(out), "--quiet", "--no-figures"]

    # the quick look: 2 rows, the 4 other runs kept and said to be there
    assert main([*quick, "--seeds", "1"]) == 0
    said = capsys.readouterr()
    assert ": 2 runs (0 run now, 2 found done), 0 failed" in said.out
    assert said.err.splitlines() == [
        f"sweep: 4 runs finished in {out / 'runs'} are outside this sweep's grid and not in"
        " results.csv or summary.md (4 of them further seeds of these cells: the same command"
        " without --seeds tables them; none is run now)"
    ]
    assert len(_table(out)) == 2
    summary = (out / "summary.md").read_text()
    assert (
        "- **not in this summary**: 4 finished runs in `runs/` outside this sweep's grid (4"
        " further seeds of these cells (a sweep of 3 seeds tables them)); their files are kept"
        ", and the sweep that plans them tables the current ones without running them again"
    ) in summary
    assert sorted(p.name for p in (out / "runs").glob("*.json")) == runs

    # a grid value left out of the file: that cell's runs are outside too
    f.write_text(f.read_text().replace('["ekf", "raw"]', '["ekf"]'))
    assert main(quick) == 0
    err = capsys.readouterr().err
    assert "sweep: 3 runs finished in" in err
    assert "(3 of cells not in this grid: the sweep file that planned them tables them;" in err
    assert "3 of cells not in this grid" in (out / "summary.md").read_text()
    assert len(_table(out)) == 3

    # the whole sweep again: every run tabled, nothing said, nothing run
    f.write_text(f.read_text().replace('["ekf"]', '["ekf", "raw"]'))
    assert main(quick) == 0
    said = capsys.readouterr()
    assert said.err == "" and "(0 run now, 6 found done)" in said.out
    assert len(_table(out)) == 6
    assert "not in this summary" not in (out / "summary.md").read_text()
    assert len(json.loads((out / "sweep.json").read_text())["runs"]) == 6
