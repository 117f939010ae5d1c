"""x6wd sweep (issue 16, items 2-3): the grid, per-run seeds, resuming, failed runs, and a real
Dask cluster on 127.0.0.1 (a ``dask scheduler`` and two ``dask worker`` processes, as a user
starts them) that loses a worker in the middle of a sweep.

Missions are kept short (``duration_s`` 15-40 s simulated, under a second each) so the file
runs in well under a minute on two cores. Every process a test starts is in its own session
and is killed (the whole group) by the fixture's finaliser, whatever the test's outcome.
"""

from __future__ import annotations

import contextlib
import csv
import json
import math
import os
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

import pytest

from tests.conftest import ROOT
from x6wd.core.errors import ConfigError

DEFAULT = ROOT / "config" / "scenarios" / "default.toml"
ZIGZAG = ROOT / "config" / "scenarios" / "zigzag.toml"
DASK = Path(sys.executable).parent / "dask"
X6WD = [sys.executable, "-m", "x6wd"]

try:
    import distributed  # noqa: F401
except ImportError:  # skipped on a developer machine without the extra, fatal in CI
    if os.environ.get("CI"):
        raise
    pytest.skip("the sweep extra (dask[distributed]) is not installed", allow_module_level=True)
if not DASK.exists():  # a venv elsewhere: the dask command on PATH
    DASK = Path(shutil.which("dask") or DASK)


# ---------------------------------------------------------------------------- a real cluster


class Cluster:
    """A ``dask scheduler`` and ``dask worker`` processes on 127.0.0.1 (free ports: the
    scheduler picks its own and writes it to a scheduler file), each in its own session so a
    worker can be killed with everything it started (nanny and worker process)."""

    def __init__(self, tmp: Path) -> None:
        self.tmp = tmp
        self.procs: list[subprocess.Popen[bytes]] = []
        self.workers: list[subprocess.Popen[bytes]] = []
        self.address = ""

    def _spawn(self, name: str, argv: list[str]) -> subprocess.Popen[bytes]:
        log = open(self.tmp / f"{name}.log", "wb")  # noqa: SIM115 - owned by the process
        env = {**os.environ, "OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1"}
        p = subprocess.Popen(
            argv, stdout=log, stderr=subprocess.STDOUT, cwd=ROOT, start_new_session=True, env=env
        )
        log.close()
        self.procs.append(p)
        return p

    def start(self, n_workers: int) -> None:
        sched_file = self.tmp / "scheduler.json"
        self._spawn(
            "scheduler",
            [
                str(DASK),
                "scheduler",
                "--host",
                "127.0.0.1",
                "--port",
                "0",
                "--no-dashboard",
                "--scheduler-file",
                str(sched_file),
            ],
        )
        deadline = time.monotonic() + 60
        while not sched_file.exists() or not sched_file.read_text().strip():
            assert time.monotonic() < deadline, self.logs()
            assert self.procs[0].poll() is None, self.logs()
            time.sleep(0.1)
        time.sleep(0.1)
        self.address = json.loads(sched_file.read_text())["address"]
        for i in range(n_workers):
            self.add_worker(f"w{i}")
        self.wait_for_workers(n_workers)

    def add_worker(self, name: str) -> None:
        self.workers.append(
            self._spawn(
                name,
                [
                    str(DASK),
                    "worker",
                    self.address,
                    "--host",
                    "127.0.0.1",
                    "--nthreads",
                    "1",
                    "--nworkers",
                    "1",
                    "--name",
                    name,
                    "--no-dashboard",
                    "--memory-limit",
                    "0",
                    "--death-timeout",
                    "60",
                    "--local-directory",
                    str(self.tmp / name),
                ],
            )
        )

    def worker_count(self) -> int:
        from distributed import Client

        with Client(self.address, timeout=30) as client:
            return len(client.scheduler_info()["workers"])

    def wait_for_workers(self, n: int) -> None:
        from distributed import Client

        with Client(self.address, timeout=30) as client:
            client.wait_for_workers(n, timeout=60)

    def kill(self, p: subprocess.Popen[bytes]) -> None:
        """SIGKILL to the process's whole group (a machine that dies: no goodbye)."""
        with contextlib.suppress(ProcessLookupError):
            os.killpg(p.pid, signal.SIGKILL)
        p.wait(timeout=30)

    def stop(self) -> None:
        for p in reversed(self.procs):
            if p.poll() is None:
                try:
                    os.killpg(p.pid, signal.SIGTERM)
                except ProcessLookupError:
                    continue
        deadline = time.monotonic() + 10
        for p in self.procs:
            try:
                p.wait(timeout=max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                self.kill(p)
        for p in self.procs:  # anything the group left behind
            with contextlib.suppress(ProcessLookupError, PermissionError):
                os.killpg(p.pid, signal.SIGKILL)

    def logs(self) -> str:
        return "\n".join(
            f"--- {p.name}\n{p.read_text(errors='replace')[-2000:]}"
            for p in sorted(self.tmp.glob("*.log"))
        )


@pytest.fixture(scope="module")
def cluster(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Cluster]:
    """One scheduler and two workers shared by the module's tests that do not kill any."""
    c = Cluster(tmp_path_factory.mktemp("dask"))
    try:
        c.start(2)
        yield c
    finally:
        c.stop()


@pytest.fixture
def own_cluster(tmp_path: Path) -> Iterator[Cluster]:
    c = Cluster(tmp_path / "dask")
    c.tmp.mkdir()
    try:
        c.start(2)
        yield c
    finally:
        c.stop()


# ---------------------------------------------------------------------------- helpers


def sweep_file(tmp: Path, body: str, scenarios: tuple[Path, ...] = (DEFAULT,)) -> Path:
    scen = ", ".join(json.dumps(str(s)) for s in scenarios)
    p = tmp / "sweep.toml"
    p.write_text(f'name = "test"\nseed = 7\nscenarios = [{scen}]\n{body}')
    return p


def ctrl_c_when(
    args: list[str],
    ready: Callable[[int], bool],
    timeout_s: float,
    *,
    group: bool,
    sig: int = signal.SIGINT,
) -> tuple[int, str]:
    """Run ``x6wd ARGS`` as a terminal would (SIGINT not ignored: a child of a shell's
    background job inherits it ignored, and Python then never raises KeyboardInterrupt), send
    it SIGINT (or ``sig``) once ``ready(pid)`` (to its whole process group with ``group``, as
    a terminal's Ctrl-C does), and return its exit code and stderr."""
    proc = subprocess.Popen(
        [*X6WD, *args], cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        start_new_session=True,
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )  # fmt: skip
    try:
        deadline = time.monotonic() + timeout_s
        while not ready(proc.pid):
            assert proc.poll() is None, proc.communicate()
            assert time.monotonic() < deadline
            time.sleep(0.01)
        if group:
            os.killpg(proc.pid, sig)
        else:
            proc.send_signal(sig)
        _out, err = proc.communicate(timeout=90)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    return proc.returncode, err


def run_cli(*args: str, timeout: float = 240) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [*X6WD, "sweep", *args], cwd=ROOT, capture_output=True, text=True, timeout=timeout
    )


def results(out: Path) -> list[dict[str, str]]:
    with open(out / "results.csv", newline="") as f:
        return list(csv.DictReader(f))


def run_files(out: Path) -> dict[str, Path]:
    return {p.stem: p for p in (out / "runs").glob("*.json")}


def workers_seen(out: Path) -> set[str]:
    return set(run_workers(out).values())


def run_workers(out: Path) -> dict[str, str]:
    """Run id -> the worker (host:pid) that ran it, for the runs finished so far."""
    found = {}
    for run_id, p in run_files(out).items():
        with contextlib.suppress(OSError, ValueError, KeyError):
            found[run_id] = json.loads(p.read_text())["worker"]
    return found


def planned_ids(out: Path) -> list[str]:
    return [r["run_id"] for r in json.loads((out / "sweep.json").read_text())["runs"]]


# ---------------------------------------------------------------------------- fast: no cluster


def test_run_seeds_come_from_the_parameters_not_the_order(tmp_path: Path) -> None:
    from sim_backend.sweep import loads_sweep, plan

    def seeds(text: str) -> dict[tuple[str, str, int], int]:
        spec = loads_sweep(text, ROOT)
        return {
            (r.cell.scenario, json.dumps(r.cell.overrides, sort_keys=True), r.replicate): r.seed
            for r in plan(spec)
        }

    base = seeds(
        f'seed = 3\nseeds = 2\nscenarios = ["{DEFAULT}", "{ZIGZAG}"]\n[set]\nduration_s = 30.0\n'
        '[grid]\nnavigation.position_source = ["ekf", "raw"]\n'
    )
    assert len(base) == 8 and len(set(base.values())) == 8
    assert all(0 <= s < 2**48 for s in base.values())
    # other order of scenarios and values, one more value, more seeds, quoted dotted keys:
    # every run of the first plan keeps its seed
    wider = seeds(
        f'seed = 3\nseeds = 3\nscenarios = ["{ZIGZAG}", "{DEFAULT}"]\n[set]\nduration_s = 30.0\n'
        '[grid]\n"navigation.position_source" = ["constellation", "raw", "ekf"]\n'
    )
    assert len(wider) == 18
    assert {k: wider[k] for k in base} == base
    # another sweep seed: every run's seed changes
    other = seeds(
        f'seed = 4\nseeds = 2\nscenarios = ["{DEFAULT}", "{ZIGZAG}"]\n[set]\nduration_s = 30.0\n'
        '[grid]\nnavigation.position_source = ["ekf", "raw"]\n'
    )
    assert other.keys() == base.keys() and not set(other.values()) & set(base.values())


def test_a_run_is_the_same_mission_wherever_it_runs() -> None:
    from sim_backend.sweep import loads_sweep, plan, run_task

    spec = loads_sweep(f'seeds = 1\nscenarios = ["{DEFAULT}"]\n[set]\nduration_s = 20.0\n', ROOT)
    (run,) = plan(spec)
    a = run_task(run.run_id, run.cell.world_toml, run.seed)
    b = run_task(run.run_id, run.cell.world_toml, run.seed)
    drop = {"wall_time_s", "task_s"}
    assert a["status"] == "ok" and a["arrivals"]
    assert {k: v for k, v in a.items() if k not in drop} == {
        k: v for k, v in b.items() if k not in drop
    }


def test_a_file_named_by_a_sweep_value_is_the_one_the_worker_reads(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # A relative file name in [set] or [grid] is relative to the sweep file (as in a
    # scenario: to the file that names it). It was checked against the scenario's folder
    # and read by the worker from its own current folder: every run failed, or silently
    # used a same-named file there. The cell's TOML carries the LCE grid inline and the
    # almanac by its absolute path.
    import tomllib

    from sim_backend.sweep import load_sweep, plan, run_task
    from sim_backend.world import DEFAULT_ALMANAC

    sw, scen, worker_cwd = tmp_path / "sw", tmp_path / "scen", tmp_path / "worker"
    for d in (sw, scen, worker_cwd):
        d.mkdir()
    # the scenario has its own LCE map: a sweep value replaces it
    (scen / "s.toml").write_text(
        f'include = ["{DEFAULT}"]\nduration_s = 5.0\n[gnss]\nlce_csv = "own.csv"\n'
        # the map acts (and so may be given) in the seed-003 form only
        'fidelity = "seed"\nseed_uere = "re_ase_lce"\n'
    )
    (scen / "own.csv").write_text("9.0,9.0\n9.0,9.0\n")
    (sw / "a.csv").write_text("1.0,2.0\n3.0,4.0\n")
    (sw / "b.csv").write_text("5.0,6.0\n7.0,8.0\n")
    shutil.copy(DEFAULT_ALMANAC, sw / "alm.txt")
    (worker_cwd / "a.csv").write_text("not, a grid\n")  # never to be read
    f = sw / "sweep.toml"
    f.write_text(
        'seeds = 1\nscenarios = ["../scen/s.toml"]\n[set]\nalmanac = "alm.txt"\n'
        '[grid]\ngnss.lce_csv = ["a.csv", "b.csv"]\n'
    )
    monkeypatch.chdir(worker_cwd)
    runs = plan(load_sweep(f))
    assert [r.cell.params for r in runs] == [{"gnss.lce_csv": "a.csv"}, {"gnss.lce_csv": "b.csv"}]
    grids = []
    for run in runs:
        data = tomllib.loads(run.cell.world_toml)
        assert data["almanac"] == str(sw / "alm.txt") and "lce_csv" not in data["gnss"]
        grids.append(data["gnss"]["lce_sigma_m"])
        rec = run_task(run.run_id, run.cell.world_toml, run.seed)
        assert rec["status"] == "ok", rec["error"]
    assert grids == [[[1.0, 2.0], [3.0, 4.0]], [[5.0, 6.0], [7.0, 8.0]]]


@pytest.mark.parametrize(
    ("grid", "named"),
    [
        ("navigation.bogus = [1]", "navigation.bogus: unknown key"),
        ('gnss.rate_hz = [1.0, "fast"]', "gnss.rate_hz"),
        ("compass.bogus = [1]", "compass.bogus"),
        ("name.sub = [1]", "name.sub: name is not a table"),
        ("failsafe.stuck_s = []", "grid.failsafe.stuck_s: expected a non-empty list"),
        # a repeat would run each mission twice and count it twice in its cell
        ('navigation.position_source = ["ekf", "ekf"]', "'ekf' given twice"),
        ('gnss.rate_hz = [1.0]\n"gnss.rate_hz" = [2.0]', "grid.gnss.rate_hz: given twice"),
        # the same number, written twice (1 Hz both)
        ("gnss.rate_hz = [1, 2.0, 1.0]", "grid.gnss.rate_hz: value 1.0 given twice (as 1)"),
        # the scenario's seed: each run's own seed overrode it, and its column took the
        # place of the run's seed in the tables
        ("seed = [1, 2]", "grid.seed: not a parameter: each run's seed comes from"),
        ('status = ["a", "b"]', "grid.status: not a parameter: 'status' is a column"),
        # an outside audit: a NaN or inf said "cannot write a non-finite number nan to TOML"
        # (no key, no cell); the compass's own check named the key but not the cell
        ("gnss.rate_hz = [nan]", "default (gnss.rate_hz=nan): gnss.rate_hz: expected a finite"),
        ("duration_s = [inf]", "default (duration_s=inf): duration_s: expected a finite"),
        ("vehicle.max_speed_mps = [-inf]", "(vehicle.max_speed_mps=-inf): vehicle.max_speed_mps"),
        ("compass.noise_ut = [-1.0]", "default (compass.noise_ut=-1.0): compass.noise_ut: must"),
    ],
)
def test_a_bad_key_or_value_stops_the_sweep_naming_it(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], grid: str, named: str
) -> None:
    from x6wd.app.cli import main

    f = sweep_file(tmp_path, f"seeds = 1\n[grid]\n{grid}\n")
    assert main(["sweep", str(f), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert named in err, err
    assert not (tmp_path / "out" / "runs").exists()  # stopped before anything ran


@pytest.mark.parametrize(
    ("body", "named"),
    [
        ("seed = 3", "set.seed: not a parameter"),
        ('run_id = "x"', "set.run_id: not a parameter"),
        ("true_error_m = 1.0", "set.true_error_m: not a parameter"),  # arrivals.csv's
    ],
)
def test_a_parameter_never_takes_the_place_of_a_column(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], body: str, named: str
) -> None:
    from sim_backend.sweep_report import write_report
    from x6wd.app.cli import main

    f = sweep_file(tmp_path, f"seeds = 1\n[set]\nduration_s = 5.0\n{body}\n")
    assert main(["sweep", str(f), "--out", str(tmp_path / "out")]) == 2
    assert named in capsys.readouterr().err
    # and records that have one anyway make no table with two such columns
    key = body.split(" ")[0]
    rec = {"run_id": "c-000", "cell_id": "c", "seed": 9, "overrides": {key: 1}, "status": "ok"}
    with pytest.raises(ValueError, match=f"parameter '{key}'"):
        write_report({}, [rec], tmp_path, figures=False)
    assert not (tmp_path / "results.csv").exists()


def test_the_daemon_and_x6wd_sim_never_import_dask() -> None:
    code = (
        "import sys, x6wd.app.daemon, x6wd.app.cli, sim_backend.mission, sim_backend.sweep, "
        "sim_backend.executor, x6wd.app.sweep, x6wd.gap.cli\n"
        "bad = sorted(m for m in sys.modules if m.split('.')[0] in ('dask', 'distributed'))\n"
        "assert not bad, bad"
    )
    subprocess.run([sys.executable, "-c", code], cwd=ROOT, check=True, timeout=120)


# ---------------------------------------------------------------------------- on the cluster


@pytest.mark.integration
@pytest.mark.slow
def test_a_sweep_through_the_scheduler_loses_nothing_when_a_worker_is_killed(
    tmp_path: Path, own_cluster: Cluster
) -> None:
    f = sweep_file(
        tmp_path,
        "seeds = 5\n[set]\nduration_s = 40.0\n"
        '[grid]\nnavigation.position_source = ["ekf", "raw"]\n',
    )
    out = tmp_path / "out"
    proc = subprocess.Popen(
        [*X6WD, "sweep", str(f), "--scheduler", own_cluster.address, "--out", str(out)],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
    )
    try:
        deadline = time.monotonic() + 120
        while len(workers_seen(out)) < 2:  # both workers have finished a mission
            assert proc.poll() is None, proc.communicate()
            assert time.monotonic() < deadline
            time.sleep(0.05)
        before_kill = set(run_files(out))
        own_cluster.kill(own_cluster.workers[1])
        stdout, stderr = proc.communicate(timeout=180)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    assert proc.returncode == 0, (stdout, stderr, own_cluster.logs())
    assert len(before_kill) < 10  # the worker died in the middle of the sweep
    assert own_cluster.worker_count() == 1
    rows = results(out)
    ids = [r["run_id"] for r in rows]
    assert sorted(ids) == sorted(planned_ids(out)) and len(set(ids)) == 10  # each exactly once
    assert all(r["status"] == "ok" and r["error"] == "" for r in rows)
    assert set(run_files(out)) == set(ids)
    # the survivor ran the rest (give or take a result already on its way at the kill)
    after = [w for k, w in run_workers(out).items() if k not in before_kill]
    assert after and max(after.count(w) for w in after) >= len(after) - 1
    assert "10 run now, 0 found done), 0 failed" in stdout


@pytest.mark.integration
@pytest.mark.slow
def test_a_sweep_resumes_with_only_the_missing_runs(tmp_path: Path, cluster: Cluster) -> None:
    f = sweep_file(
        tmp_path,
        "seeds = 3\n[set]\nduration_s = 15.0\n"
        '[grid]\nnavigation.position_source = ["ekf", "raw"]\n',
    )
    out = tmp_path / "out"
    first = run_cli(str(f), "--scheduler", cluster.address, "--out", str(out), "--quiet")
    assert first.returncode == 0, (first.stdout, first.stderr, cluster.logs())
    assert "6 run now, 0 found done" in first.stdout
    files = run_files(out)
    assert len(files) == 6
    before = {k: (p.stat().st_mtime_ns, p.read_bytes()) for k, p in files.items()}
    gone = sorted(files)[1:3]
    for k in gone:
        files[k].unlink()
    second = run_cli(str(f), "--scheduler", cluster.address, "--out", str(out), "--quiet")
    assert second.returncode == 0, second.stderr
    assert "2 run now, 4 found done" in second.stdout
    after = run_files(out)
    assert set(after) == set(before)
    for k, p in after.items():
        same = (p.stat().st_mtime_ns, p.read_bytes()) == before[k]
        assert same == (k not in gone), k  # untouched unless it was missing
        rec = json.loads(p.read_text())
        if k in gone:  # the same mission again: same seed, same figures
            old = json.loads(before[k][1])
            assert rec["seed"] == old["seed"] and rec["path_length_m"] == old["path_length_m"]
    rows = results(out)
    assert sorted(r["run_id"] for r in rows) == sorted(before)
    for name in ("arrivals.csv", "completion.png", "gps_cep50.png"):
        assert (out / name).stat().st_size > 0, name
    # a figure only with something in it (15 s: arrivals maybe, no completed run)
    has_arrivals = len((out / "arrivals.csv").read_text().splitlines()) > 1
    assert (out / "arrival_cdf.png").exists() == has_arrivals
    assert (out / "path_ratio.png").exists() == any(r["completed"] == "True" for r in rows)
    summary = (out / "summary.md").read_text()
    assert "position_source=ekf" in summary and "position_source=raw" in summary
    # the parameter is a column of the table; the arrivals are counted (15 s: the first
    # waypoint or none)
    assert {r["navigation.position_source"] for r in rows} == {"ekf", "raw"}
    assert all(int(r["arrivals"]) in (0, 1) for r in rows)
    # a cell's replay file is the mission: the sweep's figures from x6wd sim
    rec = json.loads(next(iter(after.values())).read_text())
    replay = subprocess.run(
        [
            *X6WD,
            "sim",
            str(out / "cells" / f"{rec['cell_id']}.toml"),
            "--seed",
            str(rec["seed"]),
            "--out",
            str(tmp_path / "replay"),
        ],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert replay.returncode in (0, 1), replay.stderr  # 1: not completed in 15 s
    summ = json.loads((tmp_path / "replay" / "summary.json").read_text())
    assert summ["path_length_m"] == pytest.approx(rec["path_length_m"], abs=1e-9)


@pytest.mark.integration
@pytest.mark.slow
@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["ctrl-c", "sigterm"])
def test_an_interrupted_sweep_finishes_on_the_next_call(
    tmp_path: Path, cluster: Cluster, sig: int
) -> None:
    # SIGTERM (a batch scheduler's, timeout's) ends it as Ctrl-C does, said the same way,
    # with its own exit code (an audit, round 18: it exited 143 without a word)
    # enough runs that the two workers cannot finish them all between the second file and
    # the Ctrl-C on a loaded machine (with 8 they once did: exit 0, not 130)
    n_runs = 24
    f = sweep_file(tmp_path, f"seeds = {n_runs}\n[set]\nduration_s = 30.0\n")
    out = tmp_path / "out"
    args = ["sweep", str(f), "--scheduler", cluster.address, "--out", str(out), "--quiet"]
    returncode, stderr = ctrl_c_when(
        args,
        lambda _pid: (out / "runs").exists() and len(run_files(out)) >= 2,
        120.0,
        group=False,
        sig=sig,
    )
    assert returncode == 128 + sig, stderr
    assert "the same command finishes the rest" in stderr
    kept = run_files(out)
    assert 2 <= len(kept) < n_runs
    for p in kept.values():  # whole files only
        assert json.loads(p.read_text())["status"] == "ok"
    assert not list((out / "runs").glob(".*"))  # no temporary file left
    again = run_cli(str(f), "--scheduler", cluster.address, "--out", str(out), "--quiet")
    assert again.returncode == 0, again.stderr
    assert f"{n_runs - len(kept)} run now, {len(kept)} found done" in again.stdout
    assert sorted(r["run_id"] for r in results(out)) == sorted(planned_ids(out))


@pytest.mark.integration
def test_a_failed_run_is_recorded_with_its_error_and_the_sweep_goes_on(
    tmp_path: Path, cluster: Cluster
) -> None:
    # What planning cannot see (it runs x6wd sim's start-up checks per cell): the almanac
    # spoiled between planning and the runs. Planned, spoiled, run in-process; then the
    # CLI on the cluster finds those runs done and failed, and --retry-failed reruns them.
    import shutil

    from sim_backend.executor import Executor
    from sim_backend.sweep import load_sweep, plan, run_sweep
    from sim_backend.world import DEFAULT_ALMANAC

    alm = tmp_path / "alm.txt"
    shutil.copy(DEFAULT_ALMANAC, alm)
    good = alm.read_bytes()
    f = sweep_file(
        tmp_path,
        'seeds = 2\n[set]\nduration_s = 10.0\nalmanac = "alm.txt"\n'
        "[grid]\ngnss.rate_hz = [1.0, 2.0]\n",
    )
    out = tmp_path / "out"
    spec = load_sweep(f)
    runs = plan(spec)
    alm.write_text("garbage\n")
    with Executor(workers=1) as ex:
        res = run_sweep(spec, out, ex, runs=runs)
    assert len(res.records) == 4 and len(res.errors) == 4 and not res.lost
    alm.write_bytes(good)  # the cells as planned again
    r = run_cli(str(f), "--scheduler", cluster.address, "--out", str(out), "--quiet")
    assert r.returncode == 1, (r.stdout, r.stderr)
    assert "0 run now, 4 found done), 4 failed" in r.stdout  # a failure is a result
    rows = results(out)
    assert len(rows) == 4 and all(
        row["status"] == "error" and "too short for a SEM almanac" in row["error"] for row in rows
    )
    assert "Failed runs (4)" in (out / "summary.md").read_text()
    retry = run_cli(
        str(f), "--scheduler", cluster.address, "--out", str(out), "--quiet", "--retry-failed"
    )
    assert retry.returncode == 0, (retry.stdout, retry.stderr)
    assert "4 run now, 0 found done), 0 failed" in retry.stdout
    assert all(row["status"] == "ok" and row["sim_time_s"] for row in results(out))


def test_a_rate_the_compass_loop_cannot_step_stops_the_sweep_at_planning(
    tmp_path: Path,
) -> None:
    # 3 GPS epochs a second pass the scenario's checks, but the 20 Hz compass loop needs a
    # whole multiple: x6wd sim refuses it at start (exit 2), so the sweep does at planning
    # instead of starting a cluster whose every such run fails
    f = sweep_file(
        tmp_path, "seeds = 2\n[set]\nduration_s = 10.0\n[grid]\ngnss.rate_hz = [1.0, 3.0]\n"
    )
    out = tmp_path / "out"
    r = run_cli(str(f), "--out", str(out), "--quiet")
    assert r.returncode == 2, (r.stdout, r.stderr)
    assert "whole multiple" in r.stderr and "rate_hz" in r.stderr
    assert not (out / "results.csv").exists()


@pytest.mark.integration
def test_gap_baseline_seeds_through_the_cluster_equal_the_in_process_ones(
    cluster: Cluster,
) -> None:
    import numpy as np

    from sim_backend.effects import PositionSeries
    from sim_backend.executor import Executor
    from sim_backend.world import load_world
    from x6wd.gap.scenario import scenario_baseline

    o = load_world(DEFAULT).origin
    t = np.arange(0.0, 60.0)
    z = np.zeros(t.size)
    template = PositionSeries(t, z, z, z, np.ones(t.size, dtype=bool), o.lat_deg, o.lon_deg)
    here = scenario_baseline(DEFAULT, template, 3)
    with Executor(scheduler=cluster.address) as ex:
        there = scenario_baseline(DEFAULT, template, 3, executor=ex)
    assert len(there) == 3
    for a, b in zip(here, there, strict=True):
        np.testing.assert_array_equal(a.east_m, b.east_m)
        np.testing.assert_array_equal(a.north_m, b.north_m)
    assert not np.array_equal(here[0].east_m, here[1].east_m)


def test_results_table_and_report_from_records(tmp_path: Path) -> None:
    from sim_backend.sweep_report import cell_stats, write_report

    def rec(i: int, status: str = "ok", **kw: Any) -> dict[str, Any]:
        base = {
            "run_id": f"c{i % 2}-{i:03d}",
            "cell_id": f"c{i % 2}",
            "scenario": "s",
            "params": {"a.b": i % 2},
            "overrides": {"a.b": i % 2, "duration_s": 5.0},
            "seed": i,
            "status": status,
            "completed": True,
            "path_length_m": 11.0,
            "straight_length_m": 10.0,
            "sim_time_s": 5.0,
            "wall_time_s": 0.1,
            "arrivals": [{"true_error_m": 1.0 + i, "gps_slow_error_m": 1.5}],
        }
        base.update(kw)
        return base

    records = [
        rec(0),
        rec(1),
        rec(2),
        rec(3, "error", error="ValueError: x at y.py:1", completed=False, arrivals=[]),
    ]
    info = {
        "name": "t",
        "seed": 0,
        "seeds": 2,
        "scenarios": ["s.toml"],
        "set": {},
        "grid": {},
        "ran": 4,
        "skipped": 0,
        "executor": "in this process",
        "wall_s": 1.0,
        "missions_per_min": 240.0,
    }
    written = write_report(info, records, tmp_path)
    assert {"results.csv", "arrivals.csv", "summary.md", "completion.png"} <= set(written)
    rows = results(tmp_path)
    assert [r["a.b"] for r in rows] == ["0", "1", "0", "1"]
    assert rows[0]["path_ratio"] == "1.1" and rows[3]["error"] == "ValueError: x at y.py:1"
    cells = cell_stats(records)
    assert [(c.cell_id, c.runs, c.completed, c.failed) for c in cells] == [
        ("c0", 2, 2, 0),
        ("c1", 2, 1, 1),
    ]
    try:
        import pyarrow  # noqa: F401
    except ImportError:
        assert "results.parquet" not in written
    else:
        assert "results.parquet" in written
    assert "![completion](completion.png)" in (tmp_path / "summary.md").read_text()
    # the same directory without figures: no stale figure of other runs, no dangling link
    written = write_report({**info, "ran": 1}, records[:1], tmp_path, figures=False)
    assert not list(tmp_path.glob("*.png")) and not any(w.endswith(".png") for w in written)
    assert "![" not in (tmp_path / "summary.md").read_text()


def test_runs_the_cluster_lost_are_no_missions_and_no_throughput(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    # The scheduler died (kill -9) after one run: the 7 others came back "lost". They were
    # counted as run (8 run now, the missions/min over 8) and as runs of the robot that did
    # not complete (1/4 = 25 % and 0/4 = 0 %).
    from sim_backend import sweep
    from sim_backend.executor import Executor, Outcome
    from sim_backend.sweep_report import cell_stats
    from x6wd.app import sweep as app
    from x6wd.app.cli import main

    class SchedulerDies(Executor):
        def __init__(self, *_args: Any, **_kwargs: Any) -> None:  # the CLI's options
            super().__init__(inline=True)

        def map_unordered(
            self,
            fn: Any,
            args_list: Sequence[tuple[Any, ...]],
            names: Sequence[str] | None = None,
            reraise: bool = False,
            waiting: Any = None,
        ) -> Iterator[Outcome]:
            run_id = args_list[0][0]
            time.sleep(0.2)  # the one mission this cluster finished
            yield Outcome(0, value={"run_id": run_id, "status": "ok", "completed": True})
            for i in range(1, len(args_list)):
                yield Outcome(i, error="task cancelled by the cluster", kind="executor")

    monkeypatch.setattr(app, "Executor", SchedulerDies)
    f = sweep_file(
        tmp_path, "seeds = 4\n[set]\nduration_s = 5.0\n[grid]\ngnss.rate_hz = [1.0, 2.0]\n"
    )
    out = tmp_path / "out"
    assert main(["sweep", str(f), "--out", str(out)]) == 1
    cap = capsys.readouterr()
    assert "] 8/8 runs, 0 failed, 7 lost, " in cap.err  # the progress bar's last line
    assert "8 runs (1 run now, 0 found done, 7 lost: the same command runs them), 0 failed" in (
        cap.out
    )
    rate = float(cap.out.split("failed; ")[1].split(" missions/min")[0])
    assert 0 < rate <= 60 / 0.2  # one mission in at least 0.2 s
    assert "7 runs lost by the cluster" in cap.err and "run failed:" not in cap.err
    records = [json.loads(p.read_text()) for p in sorted(run_files(out).values())]
    cells = cell_stats(records)
    assert [(c.runs, c.ok, c.completed, c.failed, c.lost) for c in cells] == [
        (4, 1, 1, 0, 3),
        (4, 0, 0, 0, 4),
    ]
    assert cells[0].completion_pct == 100.0 and math.isnan(cells[1].completion_pct)
    summary = (out / "summary.md").read_text()
    assert "| 4 | 1/1 (100 %) | 0 | 3 |" in summary and "| 4 | n/a (4 lost) | 0 | 4 |" in summary
    assert "## Lost runs (7)" in summary and "Failed runs" not in summary
    assert (out / "completion.png").stat().st_size > 0
    # the library's own count, as the benchmark reads it
    with SchedulerDies() as ex:
        res = sweep.run_sweep(sweep.load_sweep(f), tmp_path / "again", ex)
    assert res.ran == 1 and len(res.lost) == 7 and not res.errors and len(res.failed) == 7
    assert res.missions_per_min == pytest.approx(60.0 / res.wall_s)


def test_an_out_folder_of_another_sweep_is_refused(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # Another sweep's folder used to be taken over: its sweep.json replaced, and its run files
    # overwritten where the run ids were the same (same scenario, parameters, replicate).
    from sim_backend.executor import Executor
    from sim_backend.sweep import load_sweep, run_sweep
    from x6wd.app.cli import main

    body = "seeds = 1\n[set]\nduration_s = 5.0\n"
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    a = sweep_file(tmp_path / "a", body)
    b = sweep_file(tmp_path / "b", body)
    b.write_text(b.read_text().replace('name = "test"', 'name = "other"'))
    reseeded = sweep_file(tmp_path, body)
    reseeded.write_text(reseeded.read_text().replace("seed = 7", "seed = 8"))
    out = tmp_path / "out"
    with Executor(inline=True) as ex:
        run_sweep(load_sweep(a), out, ex)
    before = {p: p.read_bytes() for p in [out / "sweep.json", *run_files(out).values()]}
    assert len(before) == 2
    for other, named in ((b, "'other' seed 7"), (reseeded, "'test' seed 8")):
        assert main(["sweep", str(other), "--out", str(out), "--quiet"]) == 2
        err = capsys.readouterr().err
        assert f"output directory {str(out)!r} holds the results of another sweep:" in err
        assert f"'test' seed 7 (from {a})" in err and named in err, err
        assert "give the file name = 'test' and seed = 7 back to go on with them" in err
        with Executor(inline=True) as ex, pytest.raises(ConfigError, match="another sweep"):
            run_sweep(load_sweep(other), out, ex)
    assert {p: p.read_bytes() for p in before} == before
    assert set(run_files(out)) == {p.stem for p in before if p.parent.name == "runs"}
    # the sweep itself (its grid may grow): welcome
    assert main(["sweep", str(a), "--out", str(out), "--quiet", "--no-figures"]) == 0


def test_the_executor_counts_its_workers_in_words() -> None:
    from sim_backend.executor import Executor

    assert Executor(workers=1).description == "LocalCluster, 1 worker"  # not "1 workers"
    assert (
        Executor("tcp://127.0.0.1:18799").description == "scheduler tcp://127.0.0.1:18799, 1 worker"
    )
    assert Executor(inline=True).description == "in this process"


def test_the_progress_rate_counts_only_the_runs_run_here(monkeypatch: pytest.MonkeyPatch) -> None:
    # 19 of 20 runs found done, one run in a minute: 1/min, not 20/min; and 10 to go is an
    # ETA of 600 s, not 30 s
    import io

    from sim_backend import executor

    clock = [100.0]
    monkeypatch.setattr(executor.time, "monotonic", lambda: clock[0])
    stream = io.StringIO()
    bar = executor.TextProgress(30, stream=stream, every_s=0.0)
    clock[0] += 5.0  # starting the cluster
    bar(19)  # found done
    clock[0] += 60.0
    bar(20)
    clock[0] += 30.0
    bar(21, 1)
    lines = stream.getvalue().splitlines()
    assert lines[1].endswith("20/30 runs, 0 failed, 65 s, 1.0/min, ETA 600 s"), lines
    assert lines[2].endswith("21/30 runs, 1 failed, 95 s, 1.3/min, ETA 405 s"), lines
    assert "0.0/min" in lines[0] and "ETA" not in lines[0]
    # the scheduler dies: 8 runs lost at once are no throughput (shown as "lost", not
    # "failed": 302/min for 3 runs in 4 s)
    bar(30, 1, 8)
    last = stream.getvalue().splitlines()[-1]
    assert last.endswith("30/30 runs, 1 failed, 8 lost, 95 s, 2.0/min"), last


@pytest.mark.parametrize("peer", ["silent", "garbage"])
def test_a_scheduler_address_that_is_no_scheduler_is_a_clear_error_in_time(peer: str) -> None:
    # an HTTP server waits for a request (the dashboard's port, a typo): Client alone waited
    # for ever; a peer that speaks something else made it allocate exabytes
    from sim_backend.executor import Executor

    server = socket.create_server(("127.0.0.1", 0))
    held: list[socket.socket] = []

    def serve() -> None:
        with contextlib.suppress(OSError):
            while True:
                conn, _ = server.accept()
                held.append(conn)
                if peer == "garbage":
                    conn.sendall(b"HTTP/1.0 400 Bad Request\r\n\r\n" + b"x" * 64)

    threading.Thread(target=serve, daemon=True).start()
    t0 = time.monotonic()
    try:
        with (
            pytest.raises(ConfigError, match="Dask scheduler"),
            Executor(f"tcp://127.0.0.1:{server.getsockname()[1]}", connect_timeout_s=2.0),
        ):
            pass
    finally:
        server.close()
        for conn in held:
            conn.close()
    assert time.monotonic() - t0 < 10


BAD_SCHEDULERS = [
    "nonsense",
    "foo://bar",
    # a host no resolver knows: socket.gaierror, a traceback and exit 1
    "tcp://nosuchhost.invalid:18786",
    "tcp://256.1.1.1:8786",
    # a protocol no cluster listens on (ucx: a traceback, exit 1), a port out of range
    # (30 s of waiting, then 'cannot reach ... TimeoutError')
    "ucx://127.0.0.1:18201",
    "inproc://x",
    "tcp://127.0.0.1:99999",
]


@pytest.mark.parametrize("address", BAD_SCHEDULERS)
def test_a_malformed_scheduler_address_is_exit_2(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], address: str
) -> None:
    from x6wd.app.cli import main

    f = sweep_file(tmp_path, "seeds = 1\n[set]\nduration_s = 5.0\n")
    t0 = time.monotonic()
    assert main(["sweep", str(f), "--scheduler", address, "--out", str(tmp_path / "o")]) == 2
    assert time.monotonic() - t0 < 15  # named at once, not after the connect timeout
    err = capsys.readouterr().err
    assert "scheduler" in err and address.split("://")[-1] in err, err
    assert "Traceback" not in err


def test_a_bad_scheduler_is_exit_2_on_a_finished_sweep_too(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # nothing left to run used to mean no look at --scheduler at all: exit 0
    from sim_backend.executor import Executor
    from sim_backend.sweep import load_sweep, run_sweep
    from x6wd.app.cli import main

    f = sweep_file(tmp_path, "seeds = 1\n[set]\nduration_s = 5.0\n")
    out = tmp_path / "o"
    with Executor(inline=True) as ex:
        assert not run_sweep(load_sweep(f), out, ex).failed
    assert main(["sweep", str(f), "--out", str(out), "--quiet"]) == 0  # finished: the report
    said = capsys.readouterr().out  # it said "nothing to run on in this process"
    assert ": 1 run (0 run now, 1 found done), 0 failed; nothing left to run; summary in" in said
    for address in BAD_SCHEDULERS[::2]:
        assert main(["sweep", str(f), "--scheduler", address, "--out", str(out)]) == 2
        assert address.split("://")[-1] in capsys.readouterr().err
