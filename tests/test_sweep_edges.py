"""Edges of ``x6wd sweep`` an outside audit found: a Ctrl-C while the cluster starts, a
finished run whose worker dies afterwards, the workers a report names, non-finite grid values,
an empty --scheduler, file modes, huge grids, a key moved from [grid] to [set]. Real Dask
(a LocalCluster) wherever a cluster takes part."""

from __future__ import annotations

import os
import signal
import time
from pathlib import Path

import pytest

from tests.test_sweep import ctrl_c_when, sweep_file

pytest.importorskip("distributed")


def _children(pid: int) -> list[int]:
    """The child processes of ``pid`` (Linux /proc)."""
    found: list[int] = []
    for task in Path(f"/proc/{pid}/task").glob("*"):
        try:
            found += [int(c) for c in (task / "children").read_text().split()]
        except OSError:
            continue
    return found


def test_a_ctrl_c_while_the_local_cluster_starts_is_exit_130(tmp_path: Path) -> None:
    # SIGINT was ignored in this process too while LocalCluster(...) started its workers (so
    # they would inherit it): a Ctrl-C then was dropped and the whole sweep ran to exit 0.
    f = sweep_file(tmp_path, "seeds = 6\n[set]\nduration_s = 30.0\n")
    args = ["sweep", str(f), "--workers", "1", "--out", str(tmp_path / "o"), "--quiet"]
    # the cluster's first process appears: it is starting
    returncode, err = ctrl_c_when(args, lambda pid: bool(_children(pid)), 60.0, group=True)
    assert returncode == 130, err
    assert "sweep interrupted" in err
    assert "KeyboardInterrupt" not in err  # the workers ignored it: no traceback of theirs


def test_a_finished_run_whose_worker_dies_afterwards_is_not_lost(tmp_path: Path) -> None:
    # Dask marks a finished result whose worker died "lost" and computes it again; the
    # executor recorded it as lost by the cluster (a healthy run of the audit's).
    from sim_backend.executor import Executor

    def task(i: int, delay_s: float, folder: str) -> int:
        pid_file = Path(folder) / f"{i}.pid"
        time.sleep(5.0 if pid_file.exists() else delay_s)  # run again: still running when asked
        pid_file.write_text(str(os.getpid()))
        return i

    with Executor(workers=2) as ex:
        outcomes = ex.map_unordered(task, [(0, 2.0, str(tmp_path)), (1, 0.2, str(tmp_path))])
        first = next(outcomes)
        assert first.ok and first.value == 1
        slow = tmp_path / "0.pid"
        deadline = time.monotonic() + 60
        while not slow.exists():
            assert time.monotonic() < deadline
            time.sleep(0.05)
        time.sleep(0.5)  # its result is on its worker now, not yet collected here
        os.kill(int(slow.read_text()), signal.SIGKILL)
        time.sleep(2.0)  # the scheduler has heard of it: the result is lost, run again
        second = next(outcomes)
    assert second.ok and second.value == 0, second.error


def test_the_report_names_the_workers_the_runs_ran_on() -> None:
    # it named those alive at the end: "LocalCluster, 1 worker" for a 2-worker run whose
    # worker died (or 0 workers)
    from sim_backend.executor import Executor

    with Executor(workers=2) as ex:
        assert [o.value for o in ex.map_unordered(abs, [(-1,), (-2,)])] in ([1, 2], [2, 1])
        assert ex._cluster is not None
        ex._cluster.scale(1)
        deadline = time.monotonic() + 60
        while ex.worker_count() != 1:
            assert time.monotonic() < deadline
            time.sleep(0.1)
        assert ex.description == "LocalCluster, 2 workers (1 at the end)"


@pytest.mark.parametrize("address", ["", "  "])
def test_an_empty_scheduler_address_is_exit_2(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], address: str
) -> None:
    # --scheduler "$DASK_SCHEDULER" with the variable unset ran a LocalCluster instead
    from x6wd.app.cli import main

    f = sweep_file(tmp_path, "seeds = 1\n[set]\nduration_s = 5.0\n")
    assert main(["sweep", str(f), "--scheduler", address, "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err  # "" is refused for every option by x6wd's entry since 08178ff
    assert "scheduler: empty address" in err or "--scheduler: empty value" in err, err
    assert not (tmp_path / "o" / "runs").exists()


def test_the_sweeps_files_honour_the_umask(tmp_path: Path) -> None:
    # sweep.json, runs/*.json and cells/*.toml were 0600 (mkstemp) whatever the umask
    from sim_backend.executor import Executor
    from sim_backend.sweep import load_sweep, run_sweep

    f = sweep_file(tmp_path, "seeds = 1\n[set]\nduration_s = 5.0\n")
    old = os.umask(0o022)
    try:
        with Executor(inline=True) as ex:
            run_sweep(load_sweep(f), tmp_path / "o", ex)
    finally:
        os.umask(old)
    files = [tmp_path / "o" / "sweep.json", *(tmp_path / "o").glob("*/*.*")]
    assert len(files) == 3
    assert {p.name: oct(p.stat().st_mode & 0o777) for p in files} == {
        p.name: "0o644" for p in files
    }


@pytest.mark.parametrize(
    ("body", "extra", "named"),
    [
        (
            "seeds = 10\n[grid]\n"
            + "\n".join(
                f"{k} = [{', '.join(str(5.0 + i) for i in range(100))}]"
                for k in ("duration_s", "navigation.approach_m", "compass.noise_ut")
            ),
            [],
            "10,000,000 runs (scenarios x grid x seeds) over --max-runs 100,000",
        ),
        ("seeds = 1000000\n", [], "1,000,000 runs"),
        ("seeds = 3\n[set]\nduration_s = 5.0\n", ["--max-runs", "2"], "3 runs"),
    ],
)
def test_a_sweep_over_the_run_limit_is_refused_before_planning(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], body: str, extra: list[str], named: str
) -> None:
    # an outside audit: a 100 x 100 x 100 grid planned silently for over an hour (4.5 ms a
    # cell); seeds = 1000000 wrote a 133 MB sweep.json before the first run
    from x6wd.app.cli import main

    f = sweep_file(tmp_path, body)
    t0 = time.monotonic()
    assert main(["sweep", str(f), "--out", str(tmp_path / "o"), *extra]) == 2
    assert time.monotonic() - t0 < 60.0  # from the sizes: planning them would take hours
    err = capsys.readouterr().err
    assert named in err and "--max-runs" in err, err
    assert not (tmp_path / "o").exists()


def test_a_key_moved_from_the_grid_to_set_relabels_the_runs_it_keeps(tmp_path: Path) -> None:
    # an outside audit: the same cell and seed were reused (right) but the summary still
    # labelled them with the old grid key
    from x6wd.app.cli import main

    out = tmp_path / "o"
    f = sweep_file(tmp_path, "seeds = 1\n[grid]\nduration_s = [5.0]\n")
    assert main(["sweep", str(f), "--out", str(out), "--workers", "1", "--quiet"]) == 0
    assert "duration_s=5" in (out / "summary.md").read_text()
    f = sweep_file(tmp_path, "seeds = 1\n[set]\nduration_s = 5.0\n")
    assert main(["sweep", str(f), "--out", str(out), "--quiet", "--no-figures"]) == 0
    assert "duration_s=5" not in (out / "summary.md").read_text()


_SPAWN_INSIDE_THE_HOLD = """
import multiprocessing, sys
from sim_backend.executor import _sigint_held

def blocked(q):  # SIGINT (bit 2 of SigBlk) blocked in this spawned process?
    line = next(l for l in open("/proc/self/status") if l.startswith("SigBlk:"))
    q.put(bool(int(line.split()[1], 16) & 2))

if __name__ == "__main__":
    ctx = multiprocessing.get_context("spawn")  # as Dask's nanny starts its workers
    with _sigint_held():  # the first spawn in this process, as in `x6wd sweep`
        q = ctx.Queue()
        p = ctx.Process(target=blocked, args=(q,))
        p.start()
        print(q.get(timeout=60))
        p.join()
"""


def test_a_process_spawned_while_the_cluster_starts_has_sigint_blocked(tmp_path: Path) -> None:
    # The random-timed Ctrl-C test above caught it 2 times in 15: the resource tracker, started
    # by the first spawn, unblocked SIGINT in the spawning thread, so the workers spawned next
    # died of a Ctrl-C in their site import. This checks the mask itself, every time.
    import subprocess
    import sys

    script = tmp_path / "spawn_inside_the_hold.py"
    script.write_text(_SPAWN_INSIDE_THE_HOLD)
    root = Path(__file__).resolve().parents[1]
    env = {**os.environ, "PYTHONPATH": str(root)}
    done = subprocess.run(
        [sys.executable, str(script)], cwd=root, env=env, capture_output=True, text=True,
        timeout=120,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == "True"
