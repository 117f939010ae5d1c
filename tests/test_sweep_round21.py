"""x6wd sweep, outside audit round 21: a survey's runs are no missions that failed (the
summary showed every survey cell "0/1 (0 %)" and an empty 0 % bar), and the files of an
``include`` list given in [set] or [grid] are relative to the sweep file, as every other file
a sweep names (they were looked up beside the scenario). Real runs on the inline executor."""

from __future__ import annotations

import math
import subprocess
import time
import tomllib
from pathlib import Path

import pytest

from sim_backend import sweep
from sim_backend.executor import Executor
from sim_backend.sweep_report import cell_stats
from tests.conftest import ROOT
from tests.test_sweep import DEFAULT, X6WD, Cluster, sweep_file

OPEN_FIELD = ROOT / "config" / "scenarios" / "open_field.toml"


def test_a_survey_s_runs_are_not_counted_as_missions_that_did_not_complete(
    tmp_path: Path,
) -> None:
    f = sweep_file(tmp_path, "seeds = 1\n[set]\nduration_s = 5.0\n", (OPEN_FIELD, DEFAULT))
    spec = sweep.load_sweep(f)
    with Executor(inline=True) as ex:
        res = sweep.run_sweep(spec, tmp_path / "out", ex, runs=sweep.plan(spec))
    survey, mission = cell_stats(res.records)
    assert (survey.ok, survey.surveys, survey.completion_text) == (1, 1, "n/a (1 survey)")
    assert math.isnan(survey.completion_pct)
    assert (mission.ok, mission.surveys, mission.completion_text) == (1, 0, "0/1 (0 %)")
    assert mission.completion_pct == 0.0


def test_an_include_in_set_is_relative_to_the_sweep_file(tmp_path: Path) -> None:
    # beside the sweep file, not the scenario: the include sets the compass's rate
    (tmp_path / "inc.toml").write_text("[compass]\nrate_hz = 10.0\n")
    f = sweep_file(tmp_path, 'seeds = 1\n[set]\ninclude = ["inc.toml"]\nduration_s = 5.0\n')
    spec = sweep.load_sweep(f)
    (run,) = sweep.plan(spec)
    assert tomllib.loads(run.cell.world_toml)["compass"]["rate_hz"] == 10.0


def test_further_seeds_of_a_changed_cell_are_not_said_to_be_tabled_unrun(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # the note said "the same command without --seeds tables them; none is run again", and
    # that command then ran all of them: their [set] had changed since
    from x6wd.app.cli import main

    scenario = tmp_path / "field.toml"
    scenario.write_text(DEFAULT.read_text())
    grid = '[grid]\nnavigation.position_source = ["ekf", "raw"]\n'
    f = sweep_file(tmp_path, "seeds = 3\n[set]\nduration_s = 5.0\n" + grid, (scenario,))
    out = tmp_path / "out"
    with Executor(inline=True) as ex:
        assert not sweep.run_sweep(sweep.load_sweep(f), out, ex).failed  # 2 cells x 3 seeds
    # the scenario changed since (the audit's step: its noise)
    scenario.write_text(scenario.read_text().replace("env_noise_db = 1.0", "env_noise_db = 2.0"))
    quick = ["sweep", str(f), "--out", str(out), "--quiet", "--no-figures", "--workers", "1"]
    assert main([*quick, "--seeds", "1"]) == 0
    err = capsys.readouterr().err
    assert (
        "(4 of them further seeds of these cells made with another scenario, file or x6wd:"
        " the sweep that plans them runs them again; none is run now)"
    ) in err, err
    assert "tables them" not in err
    assert main(quick) == 0
    assert "(4 run now, 2 found done)" in capsys.readouterr().out


@pytest.mark.integration
def test_a_scheduler_that_dies_mid_sweep_is_named_and_its_runs_are_lost(
    tmp_path: Path,
) -> None:
    # before: Dask's own "distributed.client - ERROR - Failed to reconnect to scheduler
    # after 30.00 seconds, closing client" and "(the first: task cancelled by the cluster)"
    c = Cluster(tmp_path / "cluster")
    (tmp_path / "cluster").mkdir()
    try:
        c.start(1)
        f = sweep_file(tmp_path, "seeds = 12\n[set]\nduration_s = 120.0\n")
        out = tmp_path / "out"
        proc = subprocess.Popen(
            [*X6WD, "sweep", str(f), "--scheduler", c.address, "--out", str(out), "--quiet"],
            cwd=ROOT,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        deadline = time.monotonic() + 120
        while not list((out / "runs").glob("*.json")):
            assert time.monotonic() < deadline and proc.poll() is None, c.logs()
            time.sleep(0.1)
        c.kill(c.procs[0])  # the scheduler
        stdout, stderr = proc.communicate(timeout=120)
    finally:
        c.stop()
    assert proc.returncode == 1, (stdout, stderr)
    assert f"the connection to the scheduler {c.address} was lost" in stderr, stderr
    assert "Failed to reconnect" not in stderr and "Traceback" not in stderr, stderr
