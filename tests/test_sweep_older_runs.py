"""x6wd sweep, outside upgrade-path audit 10c (medium): a folder made by an older x6wd was
resumed with its runs "found done" though they lacked the receiver figures (gps_cep50_m ...,
added 2026-12-04) and came from another simulator: summary.md showed "GPS CEP50 median - m"
(or a median over the new runs only, beside "runs 2"), results.csv's gps_* columns were blank,
and nothing was said. Run records now carry a results schema (and the x6wd version); a record
of another schema is run again, said on stderr, its file kept in ``older-runs/``. Real CLI on a
LocalCluster and the inline executor, as in tests/test_sweep_round7.py.
"""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any

import pytest

from tests.test_sweep import DEFAULT, results, run_cli, run_files

pytest.importorskip("distributed")

OLD_PATH_M = 1234.5
"""The old records' path length: a figure no new run of a 40 s mission has."""
NEW_FIGURES = (
    "gps_cep50_m",
    "gps_r95_m",
    "gps_rms_m",
    "filtered_rms_m",
    "fix_fraction",
    "hold_time_s",
)
"""The figures 97e4486 (2026-12-04) added: results schema 2."""


def _sweep(tmp: Path, seeds: int = 2) -> Path:
    """One cell of the default scenario cut to 40 s (under a second a run)."""
    text = DEFAULT.read_text().replace("duration_s = 400.0", "duration_s = 40.0")
    (tmp / "short.toml").write_text(text)
    f = tmp / "sweep.toml"
    f.write_text(f'name = "older"\nseed = 3\nseeds = {seeds}\nscenarios = ["short.toml"]\n')
    return f


def _old_record(run: Any, run_id: str) -> dict[str, Any]:
    """A run file as x6wd of 2026-11-27 (1c73122) wrote it: these keys in this order, no
    schema, no gps_*/filtered_rms_m/fix_fraction/hold_time_s, no version."""
    return {
        "run_id": run_id,
        "cell_id": run_id.rsplit("-", 1)[0],
        "scenario": run.cell.scenario,
        "params": {},
        "overrides": {},
        "replicate": run.replicate,
        "seed": run.seed,
        "digest": run.cell.digest,
        "status": "ok",
        "error": None,
        "worker": "vm:8506",
        "completed": True,
        "waypoints_reached": 4,
        "waypoint_count": 4,
        "path_length_m": OLD_PATH_M,
        "straight_length_m": 1000.0,
        "sim_time_s": 40.0,
        "wall_time_s": 0.9,
        "arrivals": [],
        "position_source": "ekf",
        "task_s": 1.0,
        "finished_utc": "2026-11-27T10:00:00Z",
    }


def _cep50_cells(summary: str) -> list[str]:
    """The GPS CEP50 column of summary.md's table (the 9th of each cell's row)."""
    rows = [ln for ln in summary.splitlines() if ln.startswith("| `")]
    return [ln.split(" | ")[7] for ln in rows]


@pytest.mark.integration
def test_an_old_folders_runs_are_run_again_not_found_done(tmp_path: Path) -> None:
    # The audit's mix: a folder made by the old code with --seeds 1 (its 8-hex ids), resumed
    # with the file's 2 seeds. Before: "1 run now, 1 found done", CEP50 a median over the new
    # run only beside "runs 2", the old run's blank gps_* and its path kept, not a word.
    from sim_backend import sweep

    f = _sweep(tmp_path)
    out = tmp_path / "out"
    (out / "runs").mkdir(parents=True)
    runs = sweep.plan(sweep.load_sweep(f))
    old_id = sweep.legacy_run_id(runs[0])
    (out / "runs" / f"{old_id}.json").write_text(json.dumps(_old_record(runs[0], old_id), indent=1))

    r = run_cli(str(f), "--workers", "1", "--out", str(out), "--quiet", "--no-figures")
    assert r.returncode == 0, (r.stdout, r.stderr)
    assert "2 run now, 0 found done" in r.stdout, r.stdout
    assert "1 run from an older x6wd (schema 1, without gps_* figures) is run again" in r.stderr, (
        r.stderr
    )
    rows = results(out)
    assert len(rows) == 2
    for row in rows:
        assert float(row["gps_cep50_m"]) > 0 and float(row["gps_rms_m"]) > 0, row
        assert row["fix_fraction"] and row["hold_time_s"] and row["filtered_rms_m"], row
        assert float(row["path_length_m"]) != OLD_PATH_M
        assert row["schema"] == "2" and row["x6wd_version"].startswith("0."), row
    summary = (out / "summary.md").read_text()
    (cep,) = _cep50_cells(summary)
    assert re.fullmatch(r"\d+\.\d\d m", cep), cep  # over both runs: no "(1 of 2 runs)"
    assert "- x6wd: every run by 0." in summary
    assert "`older-runs/`: 1 record of another results schema" in summary
    kept = json.loads((out / "older-runs" / f"{runs[0].run_id}.json").read_text())
    assert kept["path_length_m"] == OLD_PATH_M and "schema" not in kept
    assert sorted(run_files(out)) == sorted(r.run_id for r in runs)
    for p in run_files(out).values():
        assert json.loads(p.read_text())["schema"] == sweep.RESULTS_SCHEMA
    plan = json.loads((out / "sweep.json").read_text())
    assert plan["schema"] == sweep.RESULTS_SCHEMA and plan["x6wd_version"]

    again = run_cli(str(f), "--out", str(out), "--quiet", "--no-figures")
    assert again.returncode == 0, (again.stdout, again.stderr)
    assert "0 run now, 2 found done" in again.stdout
    assert "older x6wd" not in again.stderr, again.stderr


def test_records_this_x6wd_cannot_table_are_not_done(tmp_path: Path) -> None:
    # split_done is what the command asks before it starts a cluster (and run_sweep after).
    from sim_backend import sweep

    runs = sweep.plan(sweep.load_sweep(_sweep(tmp_path, seeds=5)))
    store = sweep.RunStore(tmp_path / "out")
    current = {
        **_old_record(runs[0], runs[0].run_id),
        **dict.fromkeys(NEW_FIGURES, 1.0),
        "schema": 2,
        "x6wd_version": "0.1.0+gfeedface",
    }
    recs = [
        current,  # done
        {**current, "x6wd_version": "0.0.9"},  # another version of this schema: done
        {k: v for k, v in current.items() if k not in ("schema", "x6wd_version")},  # 12-04/06
        {k: v for k, v in current.items() if k != "hold_time_s"},  # a figure missing
        {**current, "schema": 3},  # a newer x6wd's
    ]
    for run, rec in zip(runs, recs, strict=True):
        store.write({**rec, "run_id": run.run_id, "replicate": run.replicate, "seed": run.seed})
    done, todo = sweep.split_done(runs, store)
    assert sorted(done) == [r.run_id for r in runs[:3]]
    assert [r.run_id for r in todo] == [r.run_id for r in runs[3:]]
    assert sweep.older_records(runs, store) == {
        runs[3].run_id: "lacking figures this x6wd writes (hold_time_s)",
        runs[4].run_id: "from a newer x6wd (schema 3; this one writes 2)",
    }


def test_a_resumed_folder_of_two_versions_says_so(tmp_path: Path) -> None:
    # A record of this schema by another x6wd version is done (the same figures; a sweep
    # resumed after an update keeps its runs), and the summary says the runs' versions.
    from sim_backend import sweep
    from sim_backend.executor import Executor

    f = _sweep(tmp_path)
    out = tmp_path / "out"
    with Executor(inline=True) as ex:
        first = sweep.run_sweep(sweep.load_sweep(f), out, ex)
    assert first.ran == 2
    path = out / "runs" / f"{first.runs[1].run_id}.json"
    rec = json.loads(path.read_text())
    path.write_text(json.dumps({**rec, "x6wd_version": "0.0.9+gdeadbeef"}))
    r = run_cli(str(f), "--out", str(out), "--quiet", "--no-figures")
    assert r.returncode == 0, (r.stdout, r.stderr)
    assert "0 run now, 2 found done" in r.stdout
    summary = (out / "summary.md").read_text()
    assert "**runs from 2 x6wd versions** (results schema 2): " in summary, summary
    assert "0.0.9+gdeadbeef (1 run)" in summary


def test_a_median_over_part_of_a_cells_runs_says_over_how_many(tmp_path: Path) -> None:
    # Before: a cell of 2 runs, one with a CEP50, showed its median as the cell's ("runs 2").
    from sim_backend.sweep_report import write_report

    def rec(i: int, **kw: Any) -> dict[str, Any]:
        return {
            "run_id": f"c-{i:03d}",
            "cell_id": "c",
            "scenario": "s",
            "status": "ok",
            "completed": True,
            "path_length_m": 110.0,
            "straight_length_m": 100.0,
            "sim_time_s": 40.0,
            "wall_time_s": 1.0,
            "arrivals": [{"true_error_m": 0.5, "gps_slow_error_m": 0.3}],
            "gps_cep50_m": 1.61,
            **kw,
        }

    info: dict[str, Any] = {
        "name": "t", "source": None, "seed": 0, "seeds": 2, "scenarios": ["s.toml"],
        "set": {}, "grid": {}, "ran": 2, "skipped": 0, "executor": "inline", "wall_s": 1.0,
        "missions_per_min": 60.0,
    }  # fmt: skip
    write_report(info, [rec(0), rec(1, gps_cep50_m=None, arrivals=[])], tmp_path, figures=False)
    summary = (tmp_path / "summary.md").read_text()
    (row,) = [ln for ln in summary.splitlines() if ln.startswith("| `c`")]
    cols = row.split(" | ")
    assert cols[5] == "0.50 / 0.50 m (1 of 2 runs)", row
    assert cols[6] == "0.30 m (1 of 2 runs)", row
    assert cols[7] == "1.61 m (1 of 2 runs)", row
    assert cols[8] == "1.100 (1.100)", row  # both runs: no count
    write_report(info, [rec(0), rec(1)], tmp_path, figures=False)
    (row,) = [ln for ln in (tmp_path / "summary.md").read_text().splitlines() if "| `c`" in ln]
    assert "of 2 runs" not in row, row
