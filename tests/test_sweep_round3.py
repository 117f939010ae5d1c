"""x6wd sweep, outside audit of issue 16 (round 3): a cluster with no working worker (D1), an
almanac whose contents changed (D2), a TOML datetime as a value (D3), the start-up checks of
``x6wd sim`` at planning (D4), no dashboard on port 8787 (D6), labels of keys that end alike
(D7). Where the defect is the cluster's, real ``dask scheduler`` / ``dask worker`` processes
(tests/test_sweep.py's :class:`Cluster`); the sweep itself as a user runs it (``x6wd sweep``
in a process of its own) with a worker timeout of a few seconds instead of 60.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
import time
import warnings
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

from tests.conftest import ROOT
from tests.test_sweep import DEFAULT, Cluster, results, run_files, sweep_file
from x6wd.core.errors import ConfigError

pytest.importorskip("distributed")

SWEEP_WITH_TIMEOUT = (
    "import sys\n"
    "import sim_backend.executor as executor\n"
    "executor.WORKER_TIMEOUT_S = float(sys.argv[1])\n"
    "from x6wd.app.cli import main\n"
    "sys.exit(main(['sweep', *sys.argv[2:]]))\n"
)


def sweep_cli(
    *args: str, worker_timeout_s: float | None = None, timeout: float = 180
) -> subprocess.CompletedProcess[str]:
    """``x6wd sweep ARGS`` in its own process; ``worker_timeout_s`` replaces the 60 s default
    (no command-line option for it in x6wd/app/sweep.py yet)."""
    if worker_timeout_s is None:
        argv = [sys.executable, "-m", "x6wd", "sweep", *args]
    else:
        argv = [sys.executable, "-c", SWEEP_WITH_TIMEOUT, str(worker_timeout_s), *args]
    return subprocess.run(argv, cwd=ROOT, capture_output=True, text=True, timeout=timeout)


class BareCluster(Cluster):
    """:class:`Cluster` that may start with no worker (Dask waits for 1 or more only)."""

    def wait_for_workers(self, n: int) -> None:
        if n:
            super().wait_for_workers(n)


@pytest.fixture
def bare_cluster(tmp_path: Path) -> Iterator[Cluster]:
    """A ``dask scheduler`` with no worker (the test adds them)."""
    c = BareCluster(tmp_path / "dask")
    c.tmp.mkdir()
    try:
        c.start(0)
        yield c
    finally:
        c.stop()


def wait_until(cond: Callable[[], bool], timeout_s: float = 60.0, what: str = "") -> None:
    deadline = time.monotonic() + timeout_s
    while not cond():
        assert time.monotonic() < deadline, what
        time.sleep(0.05)


# ---------------------------------------------------------------------------- D1: no worker


@pytest.mark.integration
def test_a_scheduler_without_workers_gives_up_in_time_and_resumes_when_one_joins(
    tmp_path: Path, bare_cluster: Cluster
) -> None:
    from sim_backend.executor import Executor

    # --workers N: the scheduler was reached; it said "cannot reach tcp://...: Only 0/2
    # workers arrived after 30 s"
    t0 = time.monotonic()
    with (
        pytest.raises(ConfigError) as err,
        Executor(bare_cluster.address, workers=2, worker_timeout_s=2.0),
    ):
        pass
    assert time.monotonic() - t0 < 20
    said = str(err.value)
    assert "cannot reach" not in said, said
    assert f"scheduler {bare_cluster.address} answered, but only 0 of the 2 workers" in said
    assert "within 2 s" in said

    # no worker at all: 0/N for ever before; now the runs are lost after the timeout, exit 1
    f = sweep_file(tmp_path, "seeds = 3\n[set]\nduration_s = 10.0\n")
    out = tmp_path / "out"
    t0 = time.monotonic()
    r = sweep_cli(
        str(f), "--scheduler", bare_cluster.address, "--out", str(out), "--quiet",
        worker_timeout_s=4.0, timeout=90,
    )  # fmt: skip
    assert r.returncode == 1, (r.stdout, r.stderr)
    assert time.monotonic() - t0 < 60
    assert "3 lost: the same command runs them" in r.stdout
    assert f"no Dask worker connected to the scheduler {bare_cluster.address} for 4 s" in r.stderr
    assert "run the same command again" in r.stderr
    assert {row["status"] for row in results(out)} == {"lost"}
    assert "## Lost runs (3)" in (out / "summary.md").read_text()
    # a worker joins: the same command runs them
    bare_cluster.add_worker("late")
    bare_cluster.wait_for_workers(1)
    again = sweep_cli(str(f), "--scheduler", bare_cluster.address, "--out", str(out), "--quiet")
    assert again.returncode == 0, (again.stdout, again.stderr)
    assert "3 run now, 0 found done), 0 failed" in again.stdout
    assert {row["status"] for row in results(out)} == {"ok"}


@pytest.mark.integration
def test_workers_that_close_on_their_first_task_are_no_workers(
    tmp_path: Path, bare_cluster: Cluster, monkeypatch: pytest.MonkeyPatch
) -> None:
    # a worker whose x6wd cannot be imported (another version, a broken install): the task
    # cannot be unpickled, the worker closes, and the sweep waited at 0/N for ever
    broken = tmp_path / "broken" / "sim_backend"
    broken.mkdir(parents=True)
    (broken / "__init__.py").write_text('raise ImportError("x6wd version mismatch here")\n')
    with monkeypatch.context() as m:
        m.setenv("PYTHONPATH", str(broken.parent))
        bare_cluster.add_worker("broken")
    bare_cluster.wait_for_workers(1)
    f = sweep_file(tmp_path, "seeds = 2\n[set]\nduration_s = 10.0\n")
    out = tmp_path / "out"
    r = sweep_cli(
        str(f), "--scheduler", bare_cluster.address, "--out", str(out), "--quiet",
        worker_timeout_s=4.0, timeout=90,
    )  # fmt: skip
    assert r.returncode == 1, (r.stdout, r.stderr, bare_cluster.logs())
    assert "no Dask worker connected" in r.stderr and "cannot import" in r.stderr, r.stderr
    assert "2 lost: the same command runs them" in r.stdout
    assert "x6wd version mismatch here" in bare_cluster.logs()  # it did close on the task


@pytest.mark.integration
@pytest.mark.slow
def test_the_last_worker_killed_mid_sweep_keeps_the_finished_runs(
    tmp_path: Path, bare_cluster: Cluster
) -> None:
    bare_cluster.add_worker("w0")
    bare_cluster.wait_for_workers(1)
    n = 12
    f = sweep_file(tmp_path, f"seeds = {n}\n[set]\nduration_s = 15.0\n")
    out = tmp_path / "out"
    proc = subprocess.Popen(
        [sys.executable, "-c", SWEEP_WITH_TIMEOUT, "4", str(f), "--scheduler",
         bare_cluster.address, "--out", str(out), "--quiet"],
        cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        wait_until(lambda: (out / "runs").exists() and len(run_files(out)) >= 2, 120)
        bare_cluster.kill(bare_cluster.workers[0])
        stdout, stderr = proc.communicate(timeout=90)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 1, (stdout, stderr)
    rows = results(out)
    ok = [row["run_id"] for row in rows if row["status"] == "ok"]
    lost = [row for row in rows if row["status"] == "lost"]
    assert 2 <= len(ok) < n and len(ok) + len(lost) == n
    assert all("no Dask worker connected" in row["error"] for row in lost)
    # a worker again: only the lost runs run
    bare_cluster.add_worker("w1")
    bare_cluster.wait_for_workers(1)
    again = sweep_cli(str(f), "--scheduler", bare_cluster.address, "--out", str(out), "--quiet")
    assert again.returncode == 0, again.stderr
    assert f"{len(lost)} run now, {len(ok)} found done), 0 failed" in again.stdout


@pytest.mark.integration
@pytest.mark.slow
def test_a_worker_back_within_the_timeout_finishes_the_sweep(
    tmp_path: Path, bare_cluster: Cluster
) -> None:
    bare_cluster.add_worker("w0")
    bare_cluster.wait_for_workers(1)
    n = 8
    f = sweep_file(tmp_path, f"seeds = {n}\n[set]\nduration_s = 15.0\n")
    out = tmp_path / "out"
    proc = subprocess.Popen(  # the default timeout (60 s)
        [sys.executable, "-m", "x6wd", "sweep", str(f), "--scheduler", bare_cluster.address,
         "--out", str(out), "--quiet"],
        cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        wait_until(lambda: (out / "runs").exists() and len(run_files(out)) >= 1, 120)
        bare_cluster.kill(bare_cluster.workers[0])
        time.sleep(3.0)  # the sweep has no worker for a while
        bare_cluster.add_worker("w1")
        stdout, stderr = proc.communicate(timeout=180)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 0, (stdout, stderr, bare_cluster.logs())
    assert f"{n} run now, 0 found done), 0 failed" in stdout
    assert len({row["worker"] for row in results(out)}) == 2  # both ran some


# ---------------------------------------------------------------------------- D2: file contents


def _almanac_sweep(tmp_path: Path) -> tuple[Path, Path]:
    from sim_backend.world import DEFAULT_ALMANAC

    alm = tmp_path / "alm.txt"
    shutil.copy(DEFAULT_ALMANAC, alm)
    f = sweep_file(tmp_path, 'seeds = 1\n[set]\nduration_s = 5.0\nalmanac = "alm.txt"\n')
    return f, alm


def test_a_changed_almanac_is_a_changed_cell(tmp_path: Path) -> None:
    # the done-check hashed the cell's text, which names the almanac by its path only: an
    # edited almanac reused the old results ("1 found done")
    from sim_backend.executor import Executor
    from sim_backend.sweep import load_sweep, plan, run_sweep

    f, alm = _almanac_sweep(tmp_path)
    out = tmp_path / "out"
    with Executor(inline=True) as ex:
        first = run_sweep(load_sweep(f), out, ex)
        assert first.ran == 1 and not first.failed
        os.utime(alm, (1, 1))  # a new mtime, the same bytes: the same cell
        assert run_sweep(load_sweep(f), out, ex).skipped == 1
        text = alm.read_text()
        assert "0.9250164032E-002" in text  # PRN 1's eccentricity
        alm.write_text(text.replace("0.9250164032E-002", "0.9350164032E-002", 1))
        second = run_sweep(load_sweep(f), out, ex)
    assert (second.ran, second.skipped) == (1, 0)
    (run,) = plan(load_sweep(f))
    assert run.cell.files == ((str(alm), run.cell.files[0][1]),)
    assert f"# reads {alm} (sha256 " in next((out / "cells").glob("*.toml")).read_text()


def test_a_cell_that_names_no_file_keeps_its_digest() -> None:
    # folders made before files were fingerprinted keep their runs (the packaged almanac is
    # the install's, like the code)
    import hashlib

    from sim_backend.sweep import loads_sweep, plan

    (run,) = plan(loads_sweep(f'seeds = 1\nscenarios = ["{DEFAULT}"]\n', ROOT))
    assert run.cell.files == ()
    assert run.cell.digest == hashlib.sha256(run.cell.world_toml.encode()).hexdigest()[:16]


# ---------------------------------------------------------------------------- D3: datetimes


def _report_info(res: Any, scenarios: list[Path], seeds: int, ran: int) -> dict[str, Any]:
    """What the CLI hands write_report about a sweep run here (sweep seed 7, inline)."""
    return {
        "name": "t", "seed": 7, "seeds": seeds, "scenarios": [str(p) for p in scenarios],
        "set": res.spec.fixed, "grid": res.spec.grid, "ran": ran, "skipped": 0,
        "executor": "x", "wall_s": 1.0, "missions_per_min": 1.0,
    }  # fmt: skip


@pytest.mark.parametrize("table", ["grid", "set"])
def test_a_toml_datetime_is_a_value(tmp_path: Path, table: str) -> None:
    # TypeError: Object of type datetime is not JSON serializable (sweep.json), exit 1
    from sim_backend.executor import Executor
    from sim_backend.sweep import load_sweep, run_sweep
    from sim_backend.sweep_report import write_report

    value = "2020-01-01T12:00:00Z"
    body = "seeds = 1\n[set]\nduration_s = 5.0\n"
    if table == "grid":
        body += f"[grid]\nstart_utc = [{value}, 2020-01-01T13:00:00+00:00]\n"
    else:
        body += f"start_utc = {value}\n"
    f = sweep_file(tmp_path, body)
    out = tmp_path / "out"
    with Executor(inline=True) as ex:
        res = run_sweep(load_sweep(f), out, ex)
        assert not res.failed, res.failed
        assert run_sweep(load_sweep(f), out, ex).skipped == len(res.runs)  # resumes
    plan = json.loads((out / "sweep.json").read_text())
    written = plan[table]["start_utc"]
    assert (written[0] if table == "grid" else written) == "2020-01-01T12:00:00+00:00"
    write_report(_report_info(res, [DEFAULT], seeds=1, ran=1), res.records, out, figures=False)
    assert {row["start_utc"] for row in results(out)} >= {"2020-01-01T12:00:00+00:00"}
    cell = next((out / "cells").glob("*.toml")).read_text()
    assert re.search(r"^start_utc = 2020-01-01T1[23]:00:00\+00:00$", cell, re.M), cell
    if table == "grid":
        assert "start_utc=2020-01-01T13:00:00+00:00" in (out / "summary.md").read_text()
        assert len({json.loads(p.read_text())["seed"] for p in run_files(out).values()}) == 2


def test_one_instant_written_twice_in_a_grid_is_one_value() -> None:
    from sim_backend.sweep import loads_sweep

    head = f'scenarios = ["{DEFAULT}"]\n[grid]\n'
    # shown as the file writes it (ISO), not as Python's datetime(...) repr
    twice = r"grid\.start_utc: value 2020-01-01T13:00:00\+01:00 given twice \(as 2020-01-01T12"
    with pytest.raises(ConfigError, match=twice):
        loads_sweep(head + "start_utc = [2020-01-01T12:00:00Z, 2020-01-01T13:00:00+01:00]\n")
    # an outside audit: the same instant as a string and as a TOML datetime ran twice
    for values in ('"2020-01-01T12:00:00Z", 2020-01-01T12:00:00Z',
                   '"2020-01-01T12:00:00Z", "2020-01-01T13:00:00+01:00"',
                   '2020-01-01, "2020-01-01T00:00:00Z"'):  # fmt: skip
        with pytest.raises(ConfigError, match=r"grid\.start_utc: value .* given twice"):
            loads_sweep(head + f"start_utc = [{values}]\n")
    loads_sweep(head + 'start_utc = ["2020-01-01T12:00:00Z", 2020-01-01T12:00:01Z]\n')


# ---------------------------------------------------------------------------- D4: start checks


@pytest.mark.parametrize(
    ("body", "named"),
    [
        # a mission's loop steps at 20 Hz for a 5 Hz compass: a 3 Hz GPS is no whole number
        # of ticks (4 Hz is, since 2026-12-07: the loop no longer steps at 5 Hz)
        (
            "[grid]\ncompass.rate_hz = [5.0]\ngnss.rate_hz = [3.0, 4.0]\n",
            "default (compass.rate_hz=5.0, gnss.rate_hz=3.0): 20 Hz on a mission"
            " (compass.rate_hz (5) times 4: the daemon's 20 Hz tick or more), which must be a"
            " whole multiple of gnss.rate_hz (3)",
        ),
        # an almanac x6wd sim cannot read (its sky warnings read it first)
        ('[set]\nalmanac = "bad.txt"\n', "bad.txt: too short for a SEM almanac"),
        # a drive the stuck failsafe cannot watch (run_mission checks it when it starts)
        (
            "[grid]\nfailsafe.stuck_min_pct = [90.0]\n",
            "default (failsafe.stuck_min_pct=90.0): navigation.cruise_pct: must be >=",
        ),
    ],
)
def test_what_x6wd_sim_refuses_at_start_stops_the_sweep_at_planning(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], body: str, named: str
) -> None:
    from sim_backend.sweep import load_sweep, plan
    from x6wd.app.cli import main

    (tmp_path / "bad.txt").write_text("garbage\n")
    f = sweep_file(tmp_path, f"seeds = 1\n{body}")
    with pytest.raises(ConfigError, match=re.escape(named)):
        plan(load_sweep(f))  # before: planned, then every such run failed on the cluster
    assert main(["sweep", str(f), "--out", str(tmp_path / "out"), "--workers", "1"]) == 2
    assert named in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


def test_x6wd_sim_refuses_the_same_cell(tmp_path: Path) -> None:
    # the check is x6wd sim's own: the scenario the sweep refuses is refused by x6wd sim
    scen = tmp_path / "s.toml"
    scen.write_text(
        f'include = ["{DEFAULT}"]\nduration_s = 5.0\n[compass]\nrate_hz = 5.0\n'
        "[gnss]\nrate_hz = 3.0\n"
    )
    r = subprocess.run(
        [sys.executable, "-m", "x6wd", "sim", str(scen), "--out", str(tmp_path / "o")],
        cwd=ROOT, capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert r.returncode == 2 and "whole multiple" in r.stderr, r.stderr


def test_a_mission_that_raises_on_the_cluster_is_still_a_recorded_failure(tmp_path: Path) -> None:
    # what planning cannot see: the almanac spoiled between planning and the run (the runs
    # read it by its path). The run is recorded with its error, the sweep goes on.
    from sim_backend.executor import Executor
    from sim_backend.sweep import load_sweep, plan, run_sweep

    f, alm = _almanac_sweep(tmp_path)
    spec = load_sweep(f)
    runs = plan(spec)
    alm.write_text("garbage\n")
    with Executor(workers=1) as ex:
        res = run_sweep(spec, tmp_path / "out", ex, runs=runs)
    (rec,) = res.records
    assert rec["status"] == "error" and "too short for a SEM almanac" in rec["error"], rec
    assert res.errors and not res.lost


# ---------------------------------------------------------------------------- D6: dashboard


def _listening(pid: int) -> list[str]:
    """The local addresses ``pid`` listens on (TCP), from ``ss -ltnp``."""
    out = subprocess.run(["ss", "-ltnp"], capture_output=True, text=True, check=True).stdout
    return [line.split()[3] for line in out.splitlines() if f"pid={pid}," in line]


def test_a_local_cluster_opens_no_dashboard_unless_asked() -> None:
    # dashboard_address=None still put the scheduler's HTTP server on 8787 (a second sweep:
    # "UserWarning: Port 8787 is already in use")
    from sim_backend.executor import Executor

    if not shutil.which("ss"):
        pytest.skip("no ss")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        with Executor(workers=1):
            here = _listening(os.getpid())
    assert not [w for w in caught if "8787" in str(w.message)], [str(w.message) for w in caught]
    assert here and not [a for a in here if a.endswith(":8787")], here
    assert all(a.startswith("127.0.0.1:") for a in here), here
    # asked for: there
    with Executor(workers=1, dashboard="127.0.0.1:39251"):
        assert "127.0.0.1:39251" in _listening(os.getpid())
    with pytest.raises(ConfigError, match="dashboard"):
        Executor("tcp://127.0.0.1:39252", dashboard="127.0.0.1:39251")


# ---------------------------------------------------------------------------- D7: labels


def test_cell_labels_tell_keys_that_end_alike_apart() -> None:
    from sim_backend.sweep_report import cell_stats, markdown, short_keys

    assert short_keys(["gnss.rate_hz", "compass.rate_hz", "navigation.position_source"]) == {
        "gnss.rate_hz": "gnss.rate_hz",
        "compass.rate_hz": "compass.rate_hz",
        "navigation.position_source": "position_source",
    }
    assert short_keys(["rate_hz", "gnss.rate_hz", "a.b.c", "x.b.c", "duration_s"]) == {
        "rate_hz": "rate_hz",
        "gnss.rate_hz": "gnss.rate_hz",
        "a.b.c": "a.b.c",
        "x.b.c": "x.b.c",
        "duration_s": "duration_s",
    }
    records = [
        {
            "run_id": f"c{i}-000",
            "cell_id": f"c{i}",
            "scenario": "default",
            "params": {"gnss.rate_hz": g, "compass.rate_hz": c},
            "status": "ok",
        }
        for i, (g, c) in enumerate([(1.0, 10.0), (2.0, 20.0)])
    ]
    labels = [c.label for c in cell_stats(records)]
    assert labels == [
        "default gnss.rate_hz=1.0 compass.rate_hz=10.0",
        "default gnss.rate_hz=2.0 compass.rate_hz=20.0",
    ]
    # one key alone is its last part, as before
    solo = [{**records[0], "params": {"navigation.position_source": "ekf"}}]
    assert [c.label for c in cell_stats(solo)] == ["default position_source=ekf"]
    info = {
        "name": "t", "seed": 0, "seeds": 1, "scenarios": ["s"], "set": {}, "grid": {},
        "ran": 2, "skipped": 0, "executor": "x", "wall_s": 1.0, "missions_per_min": 1.0,
    }  # fmt: skip
    assert "gnss.rate_hz=1.0 compass.rate_hz=10.0" in markdown(
        info, cell_stats(records), records, ()
    )


def test_the_cli_passes_its_worker_timeout_and_dashboard(tmp_path: Path) -> None:
    # a scheduler no worker joins: --worker-timeout 3 gives up in seconds, not the default 60
    sched = subprocess.Popen(
        [str(Path(sys.executable).parent / "dask"), "scheduler", "--host", "127.0.0.1",
         "--port", "0", "--no-dashboard", "--scheduler-file", str(tmp_path / "s.json")],
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
    )  # fmt: skip
    try:
        for _ in range(300):
            if (tmp_path / "s.json").exists() and (tmp_path / "s.json").read_text().strip():
                break
            time.sleep(0.1)
        address = json.loads((tmp_path / "s.json").read_text())["address"]
        f = sweep_file(tmp_path, "seeds = 1\n[set]\nduration_s = 5.0\n")
        a = time.monotonic()
        r = subprocess.run(
            [sys.executable, "-m", "x6wd", "sweep", str(f), "--scheduler", address,
             "--out", str(tmp_path / "out"), "--quiet", "--worker-timeout", "3"],
            capture_output=True, text=True, timeout=120, cwd=ROOT,
        )  # fmt: skip
        assert r.returncode == 1 and "for 3 s" in r.stderr, (r.stdout, r.stderr)
        assert time.monotonic() - a < 50
        bad = subprocess.run(
            [sys.executable, "-m", "x6wd", "sweep", str(f), "--scheduler", address,
             "--out", str(tmp_path / "out2"), "--dashboard", "127.0.0.1:0"],
            capture_output=True, text=True, timeout=120, cwd=ROOT,
        )  # fmt: skip
        assert bad.returncode == 2 and "dashboard" in bad.stderr, (bad.stdout, bad.stderr)
    finally:
        sched.terminate()
        sched.wait(timeout=30)


# ---------------------------------------------------------------------------- the GPS's figures


def test_a_survey_sweep_tabulates_the_receivers_error(tmp_path: Path) -> None:
    # a sweep of a static scenario (or of receiver keys) had no column about the GPS at all:
    # completion and arrivals are a mission's. Each run's raw CEP50 / R95 / RMS, the filtered
    # RMS, the fix fraction and the hold time are in results.csv, the CEP50 in the summary.
    from sim_backend.executor import Executor
    from sim_backend.sweep import load_sweep, run_sweep
    from sim_backend.sweep_report import write_report

    survey = ROOT / "config" / "scenarios" / "open_field.toml"
    # on the robot's loop (engine "robot"), which runs its filter at rest too
    body = (
        'seeds = 2\nengine = "robot"\n[set]\nduration_s = 60.0\n'
        '[grid]\n"gnss.mask_deg" = [5.0, 25.0]\n'
    )
    f = sweep_file(tmp_path, body, (survey,))
    out = tmp_path / "out"
    with Executor(inline=True) as ex:
        res = run_sweep(load_sweep(f), out, ex)
    assert not res.failed, res.failed
    write_report(_report_info(res, [survey], seeds=2, ran=4), res.records, out, figures=False)
    rows = results(out)
    cep = {row["gnss.mask_deg"]: [] for row in rows}
    for row in rows:
        assert 0.0 < float(row["gps_cep50_m"]) < float(row["gps_r95_m"])
        assert float(row["gps_rms_m"]) > 0 and float(row["filtered_rms_m"]) > 0
        assert float(row["fix_fraction"]) == 1.0 and float(row["hold_time_s"]) >= 0.0
        cep[row["gnss.mask_deg"]].append(float(row["gps_cep50_m"]))
    assert min(cep["25.0"]) > max(cep["5.0"])  # a high mask leaves a poor geometry
    summary = (out / "summary.md").read_text()
    assert "| GPS CEP50 median |" in summary
