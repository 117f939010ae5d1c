"""x6wd sweep, outside audit round 7: two cells of one cell id were merged (2); a Ctrl-C
during a LocalCluster sweep printed the workers' heartbeat errors and a NameError from Dask
(4). Real CLI and Dask where a cluster takes part, as in tests/test_sweep.py.
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from tests.conftest import ROOT
from tests.test_sweep import ctrl_c_when, results, run_cli, run_files, sweep_file

pytest.importorskip("distributed")

DEFAULT = ROOT / "config" / "scenarios" / "default.toml"
COLLIDING = (26.2533, 34.3037)
"""Two values of ``duration_s`` whose cells of a scenario named "short" had one cell id of
8 hex digits (short-b85496ec), found by the audit by brute force."""


def _short_scenario(tmp: Path) -> Path:
    """The default scenario as ``short.toml`` (the audit's: a 40 s mission)."""
    text = DEFAULT.read_text().replace("duration_s = 400.0", "duration_s = 40.0")
    p = tmp / "short.toml"
    p.write_text(text)
    return p


def _colliding_sweep(tmp: Path, values: tuple[float, ...] = COLLIDING, seeds: int = 2) -> Path:
    _short_scenario(tmp)
    f = tmp / "sweep.toml"
    f.write_text(
        f'name = "collide"\nseed = 1\nseeds = {seeds}\nscenarios = ["short.toml"]\n'
        f"[grid]\nduration_s = [{', '.join(map(str, values))}]\n"
    )
    return f


# ---------------------------------------------------------------------------- 2: cell ids


@pytest.mark.integration
def test_two_cells_whose_short_ids_agreed_are_two_cells(tmp_path: Path) -> None:
    # Before: one cells/ file and two run files for the two cells; results.csv listed one
    # cell's runs twice under the other's value (sim_time 26.3 labelled 34.3037), exit 0,
    # and every rerun said "2 run now, 2 found done".
    f = _colliding_sweep(tmp_path)
    out = tmp_path / "out"
    r = run_cli(str(f), "--workers", "1", "--out", str(out), "--quiet", "--no-figures")
    assert r.returncode == 0, (r.stdout, r.stderr)
    assert "4 run now, 0 found done" in r.stdout
    cells = sorted(p.stem for p in (out / "cells").glob("*.toml"))
    assert len(cells) == 2 and all(re.fullmatch(r"short-[0-9a-f]{16}", c) for c in cells)
    assert len(run_files(out)) == 4
    rows = results(out)
    assert len({r["run_id"] for r in rows}) == 4
    by_cell: dict[str, set[tuple[str, int]]] = {}
    for row in rows:  # each run's label is its own mission's duration
        by_cell.setdefault(row["cell_id"], set()).add(
            (row["duration_s"], round(float(row["sim_time_s"])))
        )
    assert sorted(by_cell.values(), key=sorted) == [{("26.2533", 26)}, {("34.3037", 34)}]
    again = run_cli(str(f), "--workers", "1", "--out", str(out), "--quiet", "--no-figures")
    assert again.returncode == 0, (again.stdout, again.stderr)
    assert "0 run now, 4 found done" in again.stdout


def test_plan_refuses_two_cells_of_one_id(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    # A 64-bit id collides with a chance of ~3e-10 in a 100,000-cell grid: with the ids cut
    # back to 8 hex digits the audit's pair collides, and plan() says so instead of merging.
    from sim_backend import sweep
    from x6wd.core.errors import ConfigError

    monkeypatch.setattr(sweep, "CELL_ID_HEX", 8, raising=False)
    spec = sweep.load_sweep(_colliding_sweep(tmp_path))
    with pytest.raises(ConfigError) as exc:
        sweep.plan(spec)
    msg = str(exc.value)
    assert "short (duration_s=34.3037): its cell id short-b85496ec is also the id of" in msg
    assert "short (duration_s=26.2533)" in msg


def test_a_folder_made_with_short_ids_resumes(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    # A folder of before the ids grew: its runs are found under their old ids (not run
    # again), renamed to the new ones, and a run file of the other cell of the same old id
    # is not taken for this one's.
    from sim_backend import sweep
    from sim_backend.executor import Executor

    out = tmp_path / "out"
    with monkeypatch.context() as m:  # the old ids: 8 hex digits; one of the two cells
        m.setattr(sweep, "CELL_ID_HEX", 8, raising=False)
        with Executor(inline=True) as ex:
            old = sweep.run_sweep(
                sweep.load_sweep(_colliding_sweep(tmp_path, COLLIDING[1:])), out, ex
            )
    assert sorted(run_files(out)) == ["short-b85496ec-000", "short-b85496ec-001"]
    assert [p.stem for p in (out / "cells").glob("*.toml")] == ["short-b85496ec"]
    old_seeds = sorted(r["seed"] for r in old.records)

    # both cells now: the 34.3037 one is found done under its old id, the other runs
    f = _colliding_sweep(tmp_path)
    with Executor(inline=True) as ex:
        res = sweep.run_sweep(sweep.load_sweep(f), out, ex)
    assert (res.ran, res.skipped) == (2, 2)
    done = [r for r in res.records if r["params"]["duration_s"] == COLLIDING[1]]
    assert sorted(r["seed"] for r in done) == old_seeds
    for rec in res.records:
        assert re.fullmatch(r"short-[0-9a-f]{16}-00[01]", rec["run_id"]), rec["run_id"]
        assert round(rec["sim_time_s"]) == round(rec["params"]["duration_s"])
    assert sorted(run_files(out)) == sorted(r["run_id"] for r in res.records)  # renamed
    assert sorted(p.stem for p in (out / "cells").glob("*.toml")) == sorted(
        {r["cell_id"] for r in res.records}
    )

    # the command: nothing to run, nothing outside the grid
    r = run_cli(str(f), "--out", str(out), "--quiet", "--no-figures")
    assert r.returncode == 0, (r.stdout, r.stderr)
    assert "0 run now, 4 found done" in r.stdout
    assert "outside" not in r.stderr, r.stderr
    assert len(results(out)) == 4


def test_a_file_of_an_old_id_is_found_before_it_is_renamed(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    # The command decides from split_done whether to start a cluster at all: the runs of a
    # folder of before the ids grew are done for it too, before run_sweep renames them.
    from sim_backend import sweep
    from sim_backend.executor import Executor

    f = _colliding_sweep(tmp_path, COLLIDING[1:], seeds=1)
    out = tmp_path / "out"
    with monkeypatch.context() as m:
        m.setattr(sweep, "CELL_ID_HEX", 8, raising=False)
        with Executor(inline=True) as ex:
            sweep.run_sweep(sweep.load_sweep(f), out, ex)
    runs = sweep.plan(sweep.load_sweep(f))
    done, todo = sweep.split_done(runs, sweep.RunStore(out))
    assert not todo
    (rec,) = done.values()
    assert rec["run_id"] == runs[0].run_id and rec["cell_id"] == runs[0].cell.cell_id
    assert json.loads((out / "runs" / "short-b85496ec-000.json").read_text())["seed"] == (
        runs[0].seed
    )


def test_a_quick_look_at_a_folder_of_short_ids_counts_its_other_seeds(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    # --seeds 1 over a folder of before the ids grew: replicate 0 is found (and renamed), the
    # other is still under its old id, and is a further seed of this cell, not of a cell
    # outside the grid.
    from sim_backend import sweep
    from sim_backend.executor import Executor

    f = _colliding_sweep(tmp_path, COLLIDING[1:], seeds=2)
    out = tmp_path / "out"
    with monkeypatch.context() as m:
        m.setattr(sweep, "CELL_ID_HEX", 8, raising=False)
        with Executor(inline=True) as ex:
            sweep.run_sweep(sweep.load_sweep(f), out, ex)
    r = run_cli(str(f), "--out", str(out), "--seeds", "1", "--quiet", "--no-figures")
    assert r.returncode == 0, (r.stdout, r.stderr)
    assert "0 run now, 1 found done" in r.stdout
    assert "1 of them further seeds of these cells" in r.stderr, r.stderr
    assert "not in this grid" not in r.stderr, r.stderr


# ---------------------------------------------------------------------------- 3: tables


def _cell_tables(out: Path) -> dict[str, dict]:
    """Each cell file of ``out`` by its id, as TOML."""
    import tomllib

    return {p.stem: tomllib.loads(p.read_text()) for p in (out / "cells").glob("*.toml")}


@pytest.mark.integration
def test_a_table_in_grid_is_merged_into_the_scenarios_as_in_set(tmp_path: Path) -> None:
    # The audit's: [grid] compass = [{noise_ut = 0.1}, {noise_ut = 0.2}] replaced the
    # scenario's whole [compass] (default.toml's declination_deg = -0.5 dropped, silently)
    # where [set] compass = {noise_ut = 0.1} merged it; the label read compass={"noise_ut": 0.1}.
    from sim_backend import sweep

    f = sweep_file(
        tmp_path,
        "seeds = 1\n[set]\nduration_s = 5.0\n[grid]\n"
        "compass = [{noise_ut = 0.1}, {noise_ut = 0.2}]\n",
    )
    out = tmp_path / "out"
    r = run_cli(str(f), "--workers", "1", "--out", str(out), "--quiet", "--no-figures")
    assert r.returncode == 0, (r.stdout, r.stderr)
    cells = _cell_tables(out)
    assert sorted(c["compass"]["noise_ut"] for c in cells.values()) == [0.1, 0.2]
    for c in cells.values():
        assert c["compass"]["declination_deg"] == -0.5, c["compass"]
    # the same value in [set]: the same cell, the same run (its seed and cell id)
    g = tmp_path / "set" / "sweep.toml"
    g.parent.mkdir()
    g.write_text(
        f.read_text().replace(
            "[grid]\ncompass = [{noise_ut = 0.1}, {noise_ut = 0.2}]",
            "compass = {noise_ut = 0.1}",
        )
    )
    (as_set,) = sweep.plan(sweep.load_sweep(g))
    row = next(r for r in results(out) if r["compass.noise_ut"] == "0.1")
    assert (row["cell_id"], int(row["seed"])) == (as_set.cell.cell_id, as_set.seed)
    assert (out / "cells" / f"{row['cell_id']}.toml").read_text().endswith(as_set.cell.world_toml)
    summary = (out / "summary.md").read_text()
    assert "default noise_ut=0.1 " in summary and "default noise_ut=0.2 " in summary, summary


def test_a_table_in_grid_keeps_the_tables_other_keys_and_varies_keys_together(
    tmp_path: Path,
) -> None:
    # [grid] gnss = [{rate_hz = 2.0}] dropped fidelity, mask_deg, nmea_decimals and baud;
    # a table of two keys is how a sweep varies them together (not every combination).
    import tomllib

    from sim_backend import sweep

    f = sweep_file(
        tmp_path,
        "seeds = 1\n[grid]\n"
        "gnss = [{rate_hz = 1.0, mask_deg = 5.0}, {rate_hz = 2.0, mask_deg = 10.0}]\n",
    )
    runs = sweep.plan(sweep.load_sweep(f))
    assert [r.cell.params for r in runs] == [
        {"gnss.rate_hz": 1.0, "gnss.mask_deg": 5.0},
        {"gnss.rate_hz": 2.0, "gnss.mask_deg": 10.0},
    ]
    for run in runs:
        gnss = tomllib.loads(run.cell.world_toml)["gnss"]
        assert (gnss["fidelity"], gnss["nmea_decimals"], gnss["baud"]) == (
            "pseudorange",
            5,
            9600,
        ), gnss
    assert [tomllib.loads(r.cell.world_toml)["gnss"]["mask_deg"] for r in runs] == [5.0, 10.0]


def test_a_file_in_a_grid_table_is_relative_to_the_sweep_file(tmp_path: Path) -> None:
    # The file key inside a [grid] table (gnss.lce_csv) was resolved against the scenario's
    # folder, not the sweep file's as in [set] and as a dotted [grid] key.
    import tomllib

    from sim_backend import sweep

    sw, scen = tmp_path / "sw", tmp_path / "scen"
    sw.mkdir()
    scen.mkdir()
    (scen / "s.toml").write_text(f'include = ["{DEFAULT}"]\nduration_s = 5.0\n')
    (sw / "a.csv").write_text("1.0,2.0\n3.0,4.0\n")
    f = sw / "sweep.toml"
    f.write_text(
        'seeds = 1\nscenarios = ["../scen/s.toml"]\n[grid]\ngnss = [\n'
        '  {lce_csv = "a.csv", fidelity = "seed", seed_uere = "re_ase_lce"},\n'
        '  {fidelity = "seed", seed_uere = "modelled"},\n]\n'
    )
    runs = sweep.plan(sweep.load_sweep(f))
    first = tomllib.loads(runs[0].cell.world_toml)["gnss"]
    assert first["lce_sigma_m"] == [[1.0, 2.0], [3.0, 4.0]]
    assert first["rate_hz"] == 1.0  # the scenario's, kept
    assert runs[0].cell.params["gnss.lce_csv"] == "a.csv"  # as written


@pytest.mark.parametrize(
    ("body", "named"),
    [
        (
            "[set]\ncompass.noise_ut = 0.1\n[grid]\ncompass = [{noise_ut = 0.2}]\n",
            "grid.compass: sets compass.noise_ut, also in [set]",
        ),
        (
            '[grid]\n"compass.noise_ut" = [0.1]\ncompass = [{noise_ut = 0.2}]\n',
            "grid.compass: sets compass.noise_ut, also a key of [grid]",
        ),
        (  # one table written nested and dotted: one value, given twice
            '[grid]\nvehicle = [{a = {b = 1}}, {"a.b" = 1}]\n',
            "grid.vehicle: value {'a.b': 1} given twice",
        ),
    ],
)
def test_a_grid_table_that_sets_a_key_twice_is_refused(
    tmp_path: Path, body: str, named: str
) -> None:
    from sim_backend import sweep
    from x6wd.core.errors import ConfigError

    with pytest.raises(ConfigError) as exc:
        sweep.load_sweep(sweep_file(tmp_path, body))
    assert named in str(exc.value), str(exc.value)


# ---------------------------------------------------------------------------- 4: Ctrl-C

SLOW_HEARTBEATS = """
# A scheduler that answers each worker heartbeat after 0.4 s, as on a loaded machine (the
# audit's: two cores shared by other work): a heartbeat is then in flight most of the time.
import os

if os.environ.get("X6WD_TEST_SLOW_HEARTBEAT_S"):
    import asyncio

    from distributed import scheduler

    _init = scheduler.Scheduler.__init__
    _delay = float(os.environ["X6WD_TEST_SLOW_HEARTBEAT_S"])

    def __init__(self, *args, **kwargs):
        _init(self, *args, **kwargs)
        answer = self.handlers["heartbeat_worker"]

        async def heartbeat_worker(**msg):
            await asyncio.sleep(_delay)
            return answer(**msg)

        self.handlers["heartbeat_worker"] = heartbeat_worker

    scheduler.Scheduler.__init__ = __init__
"""


def _slow_heartbeats(tmp: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Every Python process started from here on loads :data:`SLOW_HEARTBEATS`."""
    site = tmp / "site"
    site.mkdir()
    (site / "sitecustomize.py").write_text(SLOW_HEARTBEATS)
    path = os.environ.get("PYTHONPATH")
    monkeypatch.setenv("PYTHONPATH", f"{site}{os.pathsep}{path}" if path else str(site))
    monkeypatch.setenv("X6WD_TEST_SLOW_HEARTBEAT_S", "0.4")


def _noise(stderr: str) -> list[str]:
    return [
        line
        for line in stderr.splitlines()
        if line.strip() and not line.startswith("sweep interrupted:")
    ]


@pytest.mark.integration
def test_a_sweep_on_a_slow_scheduler_ends_without_worker_errors(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # A worker's heartbeat in flight when the cluster shut it down failed: "distributed.worker
    # - ERROR - Failed to communicate with scheduler during heartbeat." and a CommClosedError
    # traceback of ~25 lines, per worker, at the end of a sweep that ran to its end too.
    _slow_heartbeats(tmp_path, monkeypatch)
    f = sweep_file(tmp_path, "seeds = 2\n[set]\nduration_s = 5.0\n")
    out = tmp_path / "out"
    r = run_cli(str(f), "--workers", "2", "--out", str(out), "--quiet", "--no-figures")
    assert r.returncode == 0, (r.stdout, r.stderr)
    assert "2 run now" in r.stdout
    assert not _noise(r.stderr), r.stderr


@pytest.mark.integration
def test_a_ctrl_c_to_the_group_during_a_sweep_prints_only_what_it_kept(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # The audit's Ctrl-C (SIGINT to the process group, as a terminal sends it) during a
    # LocalCluster sweep: exit 130 and "sweep interrupted" were right, but ~25 lines of the
    # workers' heartbeat errors came with them.
    _slow_heartbeats(tmp_path, monkeypatch)
    f = sweep_file(tmp_path, "seeds = 40\n[set]\nduration_s = 20.0\n")
    out = tmp_path / "out"
    args = ["sweep", str(f), "--workers", "2", "--out", str(out), "--quiet", "--no-figures"]

    def running(_pid: int) -> bool:  # the cluster is up and its workers busy
        return (out / "runs").is_dir() and len(run_files(out)) >= 1

    returncode, err = ctrl_c_when(args, running, 180.0, group=True)
    assert returncode == 130, err
    assert "sweep interrupted:" in err
    assert not _noise(err), err


PROBE = """
import os, signal, sys, threading, time

from sim_backend.executor import Executor

if __name__ == "__main__":
    with Executor(workers=1) as ex:
        ex._client.loop.add_callback(time.sleep, 1.0)  # the client's event loop busy for 1 s
        threading.Timer(0.3, os.kill, (os.getpid(), signal.SIGINT)).start()
        try:
            ex.worker_count()  # a client call, waiting for that loop
        except KeyboardInterrupt:
            print("interrupted", file=sys.stderr)
        time.sleep(1.5)  # the loop runs what it was given meanwhile
    print("closed", file=sys.stderr)
"""


@pytest.mark.integration
def test_a_ctrl_c_during_a_client_call_is_raised_when_it_returns(tmp_path: Path) -> None:
    # A KeyboardInterrupt raised while the client waited for its event loop made Dask cancel
    # the call on the loop; one that had not begun there failed: "NameError: cannot access
    # free variable 'future' where it is not associated with a value in enclosing scope"
    # with a traceback (the audit saw it once: the executor polls the worker count every
    # second). Here the loop is kept busy so that the call has not begun when the Ctrl-C
    # comes.
    script = tmp_path / "probe.py"
    script.write_text(PROBE)
    r = subprocess.run(
        [sys.executable, str(script)], cwd=ROOT, capture_output=True, text=True, timeout=180
    )
    assert r.returncode == 0, r.stderr
    assert r.stderr.split() == ["interrupted", "closed"], r.stderr
