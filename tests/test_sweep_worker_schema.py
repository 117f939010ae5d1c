"""x6wd sweep, review of 03ef5e3 (findings 4 and 5, low).

4: a cluster worker on an older x6wd returns the figures of its schema (no gps_*, no schema,
no version). The client stamped its own schema on the record and tabled it with blanks, and the
summary said the run came from "an x6wd that did not record its version (before 2026-12-06)".
Now the worker names its schema; a result of another x6wd's figures is stored as failed ("the
worker's x6wd is too old ...: update it"), in no table, said once on stderr, and run again by
the next call.

5: a run that raised, recorded 2026-12-04..06 without a schema, was called schema 1: run again
without --retry-failed and moved to older-runs/. It has no figures to be of a schema by: kept
unless --retry-failed, as any run that raised.

The older worker is this x6wd's real run_task on the inline executor, its result cut to the
keys the 11-27 code returned: a real worker of that code cannot run on this checkout.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any

import pytest

from tests.test_sweep import results, run_cli, run_files
from tests.test_sweep_older_runs import NEW_FIGURES, _sweep

pytest.importorskip("distributed")


def _older_executor(drop: tuple[str, ...]) -> Any:
    from sim_backend.executor import Executor

    class OlderWorkers(Executor):
        """Workers whose run_task returns a result without the keys ``drop``."""

        def map_unordered(self, fn: Any, args_list: Any, **kw: Any) -> Any:
            def older_fn(*a: Any) -> Any:
                return {k: v for k, v in fn(*a).items() if k not in drop}

            return super().map_unordered(older_fn, args_list, **kw)

    return OlderWorkers(inline=True)


@pytest.mark.parametrize(
    ("drop", "error"),
    [
        # the 11-27 code: no schema, no version, no receiver figures
        (
            (*NEW_FIGURES, "schema", "x6wd_version"),
            "the worker's x6wd is too old (schema 1, without gps_* figures; this one tables"
            " schema 2): update it",
        ),
        # the review's repro (/tmp/review10a/old_worker.py): figures gone, its schema kept
        (
            (*NEW_FIGURES, "x6wd_version"),
            "the worker's x6wd returned schema 2 without gps_cep50_m, gps_r95_m, gps_rms_m,"
            " filtered_rms_m, fix_fraction, hold_time_s, figures this one writes: update it",
        ),
    ],
    ids=["no-schema", "schema-kept"],
)
def test_an_older_workers_results_are_failures_not_tabled(
    tmp_path: Path, caplog: pytest.LogCaptureFixture, drop: tuple[str, ...], error: str
) -> None:
    from sim_backend import sweep
    from sim_backend.executor import Executor
    from sim_backend.sweep_report import write_report

    spec = sweep.load_sweep(_sweep(tmp_path))
    out = tmp_path / "out"
    with caplog.at_level(logging.WARNING, logger="sim_backend.sweep"), _older_executor(drop) as ex:
        res = sweep.run_sweep(spec, out, ex)
    # Before: both stored with "schema": 2, status ok, tabled with blank gps_* figures.
    assert res.ran == 2 and res.raised == 2, res.records
    for rec in res.records:
        assert rec["status"] == "error" and rec["error"] == error, rec
        assert rec["schema"] != sweep.RESULTS_SCHEMA or "schema" not in drop, rec
        assert "path_length_m" not in rec and "arrivals" not in rec, rec  # no figure kept
        assert rec["worker"] and rec["completed"] is False
    for p in run_files(out).values():  # as stored
        assert json.loads(p.read_text())["error"] == error
    said = [r.getMessage() for r in caplog.records if "worker's x6wd" in r.getMessage()]
    assert len(said) == 1, said  # once, not per run
    assert error in said[0] and "the next call runs them again" in said[0]

    info: dict[str, Any] = {
        "name": spec.name, "source": None, "seed": spec.seed, "seeds": spec.seeds,
        "scenarios": ["short.toml"], "set": {}, "grid": {}, "ran": res.ran,
        "skipped": res.skipped, "executor": res.executor, "wall_s": res.wall_s,
        "missions_per_min": res.missions_per_min, "raised": res.raised,
    }  # fmt: skip
    write_report(info, res.records, out, figures=False)
    summary = (out / "summary.md").read_text()
    assert "did not record its version" not in summary, summary
    assert "n/a (2 errored)" in summary and error in summary
    for row in results(out):
        assert row["status"] == "error" and row["path_length_m"] == "" and row["gps_cep50_m"] == ""
    assert (out / "arrivals.csv").read_text().count("\n") == 1  # the header only

    # The next call (the workers updated) runs them again, without --retry-failed, and
    # keeps no failure in older-runs/.
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="sim_backend.sweep"), Executor(inline=True) as ex:
        again = sweep.run_sweep(spec, out, ex)
    assert again.ran == 2 and again.skipped == 0 and again.raised == 0
    for rec in again.records:
        assert rec["status"] == "ok" and rec["schema"] == sweep.RESULTS_SCHEMA
        assert rec["gps_cep50_m"] > 0 and rec["x6wd_version"], rec
    assert not (out / "older-runs").exists()
    assert not caplog.records, [r.getMessage() for r in caplog.records]


def _error_record(run: Any) -> dict[str, Any]:
    """A run that raised, as x6wd of 2026-12-04..06 stored it: no schema, no version."""
    return {
        "run_id": run.run_id,
        "cell_id": run.cell.cell_id,
        "scenario": run.cell.scenario,
        "params": {},
        "overrides": {},
        "replicate": run.replicate,
        "seed": run.seed,
        "digest": run.cell.digest,
        "status": "error",
        "error": "OSError: almanac.yuma: cannot read at world.py:321",
        "worker": "vm:8506",
        "completed": False,
        "task_s": 0.01,
        "finished_utc": "2026-12-05T10:00:00Z",
    }


def test_a_schemaless_failed_run_is_kept_unless_retry_failed(tmp_path: Path) -> None:
    from sim_backend import sweep
    from sim_backend.executor import Executor

    f = _sweep(tmp_path)
    runs = sweep.plan(sweep.load_sweep(f))
    out = tmp_path / "out"
    store = sweep.RunStore(out)
    for run in runs:
        store.write(_error_record(run))
    # Before: stale_reason said "from an older x6wd (schema 1, without gps_* figures)".
    assert sweep.stale_reason(_error_record(runs[0])) is None
    assert sweep.older_records(runs, store) == {}
    done, todo = sweep.split_done(runs, store)
    assert sorted(done) == sorted(r.run_id for r in runs) and todo == []
    assert [r.run_id for r in sweep.split_done(runs, store, retry_failed=True)[1]] == [
        r.run_id for r in runs
    ]

    # The command resumes with both kept as failed: nothing run, nothing moved.
    r = run_cli(str(f), "--out", str(out), "--quiet", "--no-figures")
    assert r.returncode == 1, (r.stdout, r.stderr)
    assert "0 run now, 2 found done" in r.stdout and "2 failed" in r.stdout, r.stdout
    assert "older x6wd" not in r.stderr, r.stderr
    assert not (out / "older-runs").exists()
    assert sorted(run_files(out)) == sorted(x.run_id for x in runs)
    summary = (out / "summary.md").read_text()
    assert "results schema not recorded" in summary and "None" not in summary, summary

    # --retry-failed runs them again, and their failures are not kept as older records.
    with Executor(inline=True) as ex:
        res = sweep.run_sweep(sweep.load_sweep(f), out, ex, retry_failed=True)
    assert res.ran == 2 and res.older == {}
    assert all(rec["status"] == "ok" for rec in res.records)
    assert not (out / "older-runs").exists()
