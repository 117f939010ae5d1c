"""x6wd sweep, outside audit round 4: runs whose mission raised are no missions — apart from
the completion rate (M1) and the throughput (M2); a dead scheduler port is named at once, and a
silent one after the timeout, with the reason (M3); a scheduler without workers says that the
sweep waits for them (M4); the robot's log stays out of a sweep's output (L1); two sweeps into
one folder at once are refused (L2). Real processes, sockets and Dask, as in
tests/test_sweep.py.
"""

from __future__ import annotations

import contextlib
import json
import logging
import math
import os
import shutil
import signal
import socket
import subprocess
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from tests.conftest import ROOT
from tests.test_sweep import X6WD, Cluster, results, run_cli, run_files, sweep_file
from tests.test_sweep_round3 import bare_cluster  # noqa: F401 - a fixture
from x6wd.core.errors import ConfigError

pytest.importorskip("distributed")


# ---------------------------------------------------------------------------- M1, M2


def _almanac_grid(tmp_path: Path) -> tuple[Path, Path, bytes]:
    """A sweep of two cells of 3 seeds, one per almanac (good.txt, bad.txt: both the packaged
    one now); missions of 5 s, which complete none of the default scenario's waypoints."""
    from sim_backend.world import DEFAULT_ALMANAC

    for name in ("good.txt", "bad.txt"):
        shutil.copy(DEFAULT_ALMANAC, tmp_path / name)
    f = sweep_file(
        tmp_path,
        'seeds = 3\n[set]\nduration_s = 5.0\n[grid]\nalmanac = ["good.txt", "bad.txt"]\n',
    )
    return f, tmp_path / "bad.txt", (tmp_path / "bad.txt").read_bytes()


def test_runs_that_raised_are_not_in_the_completion_rate_nor_the_throughput(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    # The almanac of one cell became unreadable after planning: its 3 runs raised at once.
    # The cell showed "0/3 (0 %)", as three missions that ran and did not complete, and the
    # throughput counted them as missions.
    from sim_backend import sweep
    from sim_backend.executor import Executor
    from sim_backend.sweep_report import cell_stats
    from x6wd.app import sweep as app
    from x6wd.app.cli import main

    f, bad, good = _almanac_grid(tmp_path)
    spec = sweep.load_sweep(f)
    runs = sweep.plan(spec)
    bad.write_text("garbage\n")
    with Executor(inline=True) as ex:
        res = sweep.run_sweep(spec, tmp_path / "lib", ex, runs=runs)
    assert (res.ran, res.raised, len(res.errors)) == (6, 3, 3)
    assert res.missions_per_min == pytest.approx(3 * 60.0 / res.wall_s)  # not 6 per wall
    ran, raised = cell_stats(res.records)
    assert (ran.ok, ran.completed, ran.failed, ran.completion_text) == (3, 0, 0, "0/3 (0 %)")
    assert (raised.ok, raised.failed, raised.completion_text) == (0, 3, "n/a (3 errored)")
    assert math.isnan(raised.completion_pct) and ran.completion_pct == 0.0

    # the command, on a LocalCluster: the almanac spoiled between its planning and its runs
    bad.write_bytes(good)

    def plan_then_spoil(spec: Any) -> Any:
        planned = sweep.plan(spec)
        bad.write_text("garbage\n")
        return planned

    monkeypatch.setattr(app, "plan", plan_then_spoil)
    out = tmp_path / "out"
    assert main(["sweep", str(f), "--out", str(out), "--workers", "1", "--quiet"]) == 1
    said = capsys.readouterr().out
    assert "6 runs (6 run now, 0 found done), 3 failed; " in said, said
    assert " missions/min on LocalCluster, 1 worker (3 runs that raised not counted);" in said
    summary = (out / "summary.md").read_text()
    assert "| 3 | 0/3 (0 %) | 0 | 0 |" in summary, summary
    assert "| 3 | n/a (3 errored) | 3 | 0 |" in summary, summary
    assert " missions/min (3 runs that raised not counted)" in summary
    assert {r["status"] for r in results(out)} == {"ok", "error"}


def _ink(png: Path) -> int:
    """The pixels of ``png`` that are not white."""
    import matplotlib.image as mpimg

    rgb = mpimg.imread(png)[..., :3]
    return int((rgb.min(axis=-1) < 0.95).sum())


def test_a_cell_where_no_mission_ran_is_marked_in_the_completion_figure(tmp_path: Path) -> None:
    # 6 runs that raised drew the same empty bar and "0/6" as 6 missions that did not complete
    from sim_backend.sweep_report import write_report

    def records(status: str) -> list[dict[str, Any]]:
        return [
            {
                "run_id": f"c0-{i}",
                "cell_id": "c0",
                "scenario": "s",
                "params": {"a.b": 1},
                "overrides": {"a.b": 1},
                "seed": i,
                "status": status,
                "completed": False,
                "error": "ValueError: unreadable at sky.py:1" if status == "error" else None,
            }
            for i in range(6)
        ]

    info = {
        "name": "t", "seed": 0, "seeds": 6, "scenarios": ["s.toml"], "set": {}, "grid": {},
        "ran": 6, "skipped": 0, "executor": "x", "wall_s": 1.0, "missions_per_min": math.nan,
    }  # fmt: skip
    drawn = {}
    for status in ("ok", "error"):
        (tmp_path / status).mkdir()
        write_report(info, records(status), tmp_path / status)
        drawn[status] = tmp_path / status / "completion.png"
    assert drawn["ok"].read_bytes() != drawn["error"].read_bytes()
    assert _ink(drawn["error"]) > _ink(drawn["ok"]) + 2000  # the hatched bar
    assert "| 6 | n/a (6 errored) | 6 | 0 |" in (tmp_path / "error" / "summary.md").read_text()
    assert "| 6 | 0/6 (0 %) | 0 | 0 |" in (tmp_path / "ok" / "summary.md").read_text()


# ---------------------------------------------------------------------------- M3


def test_a_dead_scheduler_port_is_refused_at_once_naming_why(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # it waited the whole 30 s and said "... within 30 s: TimeoutError"
    from x6wd.app.cli import main

    with socket.create_server(("127.0.0.1", 0)) as s:  # a port nothing listens on any more
        port = s.getsockname()[1]
    f = sweep_file(tmp_path, "seeds = 1\n[set]\nduration_s = 5.0\n")
    address = f"tcp://127.0.0.1:{port}"
    t0 = time.monotonic()
    assert main(["sweep", str(f), "--scheduler", address, "--out", str(tmp_path / "o")]) == 2
    assert time.monotonic() - t0 < 10
    err = capsys.readouterr().err
    assert f"cannot reach a Dask scheduler at {address}: connection refused by" in err, err
    assert "TimeoutError" not in err


def test_a_scheduler_host_that_does_not_answer_is_named_after_the_timeout() -> None:
    # a listener whose queue is full drops the SYNs, as a host that is down or a firewall:
    # the connect timeout holds, and the error says what did not answer
    from sim_backend.executor import Executor

    server = socket.socket()
    server.bind(("127.0.0.1", 0))
    server.listen(0)
    port = server.getsockname()[1]
    fillers = []
    try:
        for _ in range(4):
            c = socket.socket()
            c.setblocking(False)
            with contextlib.suppress(BlockingIOError):
                c.connect(("127.0.0.1", port))
            fillers.append(c)
        time.sleep(0.2)
        t0 = time.monotonic()
        with (
            pytest.raises(ConfigError) as err,
            Executor(f"tcp://127.0.0.1:{port}", connect_timeout_s=2.0),
        ):
            pass
        waited_s = time.monotonic() - t0
    finally:
        for c in fillers:
            c.close()
        server.close()
    assert 1.5 < waited_s < 10
    said = str(err.value)
    assert f"within 2 s: 127.0.0.1:{port} did not answer a TCP connect" in said, said


# ---------------------------------------------------------------------------- M4


@pytest.mark.integration
def test_a_scheduler_without_workers_says_the_sweep_waits_for_them(
    tmp_path: Path,
    bare_cluster: Cluster,  # noqa: F811 - the fixture imported above
) -> None:
    # the bar sat at "0/2 runs, 0 failed, 0 s, 0.0/min" for the whole worker timeout
    f = sweep_file(tmp_path, "seeds = 2\n[set]\nduration_s = 5.0\n")
    r = run_cli(
        str(f), "--scheduler", bare_cluster.address, "--out", str(tmp_path / "o"),
        "--worker-timeout", "8", timeout=120,
    )  # fmt: skip
    assert r.returncode == 1, (r.stdout, r.stderr)
    waiting = [
        line
        for line in r.stderr.splitlines()
        if "0/2 runs, waiting for workers (0 connected) for " in line
    ]
    assert len(waiting) >= 2, r.stderr  # refreshed: a line at most every 5 s in a log
    assert waiting[0].endswith("s; the runs left are given up after 8 s without one"), waiting
    assert "0/2 runs, no worker connected for 8 s: the runs left are lost" in r.stderr
    assert "2 runs lost by the cluster" in r.stderr


def test_the_waiting_line_is_refreshed_in_place_on_a_terminal(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    import io

    from sim_backend import executor

    class Tty(io.StringIO):
        def isatty(self) -> bool:
            return True

    clock = [10.0]
    monkeypatch.setattr(executor.time, "monotonic", lambda: clock[0])
    columns = [200]
    monkeypatch.setattr(executor.shutil, "get_terminal_size",
                        lambda: os.terminal_size((columns[0], 24)))  # fmt: skip
    stream = Tty()
    bar = executor.TextProgress(4, stream=stream)
    bar(1)
    for waited_s in (0.0, 1.0, 2.0):
        clock[0] += 1.0
        bar.waiting(waited_s, 60.0)
    text = stream.getvalue()
    assert text.count("\r") == 4 and "\n" not in text
    assert text.endswith(
        "1/4 runs, waiting for workers (0 connected) for 2 s; the runs left are given up after"
        " 60 s without one" + executor.CLEAR_TO_EOL
    )
    bar(2)  # a worker came: the shorter line clears the rest of the waiting one
    assert stream.getvalue().split("\r")[-1].endswith(executor.CLEAR_TO_EOL)
    # never wider than the terminal: a wrapped line is not redrawn in place by "\r"
    columns[0] = 80
    bar.waiting(3.0, 60.0)
    last = stream.getvalue().split("\r")[-1]
    assert len(last.removesuffix(executor.CLEAR_TO_EOL)) == 79


# ---------------------------------------------------------------------------- L1


def test_a_sweeps_missions_print_no_robot_log(
    tmp_path: Path, capfd: pytest.CaptureFixture[str], caplog: pytest.LogCaptureFixture
) -> None:
    # "state IDLE -> HOLD state: position estimate not ready", a line per state change of
    # every mission, from each worker (and this process), --quiet or not
    from sim_backend.executor import Executor
    from sim_backend.sweep import load_sweep, run_sweep

    f = sweep_file(
        tmp_path,
        f'robot_config = "{ROOT / "config" / "x6wd.toml"}"\nseeds = 2\n[set]\nduration_s = 10.0\n'
        '[grid]\nnavigation.position_source = ["ekf", "raw"]\n',
    )
    with caplog.at_level(logging.INFO), Executor(inline=True) as ex:
        res = run_sweep(load_sweep(f), tmp_path / "inline", ex)
    assert not res.failed
    # in this process: to no handler (pytest's own, or Python's last resort: stderr)
    assert not [r.getMessage() for r in caplog.records if r.name.startswith("x6wd")]
    err = capfd.readouterr().err
    assert " -> HOLD" not in err, err
    robot_log = logging.getLogger("x6wd")  # given back as it was
    assert robot_log.propagate and not robot_log.handlers
    # the states are the robot's to log elsewhere: x6wd sim shows them (a real hold's:
    # tests/test_sim_scenario_mission.py; the start-up wait is no fault and not shown)
    sim = subprocess.run(
        [*X6WD, "sim", str(next((tmp_path / "inline" / "cells").glob("*.toml"))),
         "--out", str(tmp_path / "sim"), "--seed", str(res.records[0]["seed"])],
        cwd=ROOT, capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert sim.returncode == 1, sim.stderr  # (a mission of 10 s completes none)
    assert "position estimate not ready" not in sim.stderr, sim.stderr
    for quiet in ([], ["--quiet"]):  # on a LocalCluster's worker
        out = tmp_path / f"cluster{len(quiet)}"
        r = run_cli(str(f), "--out", str(out), "--workers", "1", *quiet)
        assert r.returncode == 0, (r.stdout, r.stderr)
        assert " -> HOLD" not in r.stderr, r.stderr
        assert "4 run now" in r.stdout


# ---------------------------------------------------------------------------- L2


@contextlib.contextmanager
def _sweep_process(args: list[str]) -> Iterator[subprocess.Popen[str]]:
    """``x6wd sweep ARGS`` in a session of its own; killed with its cluster at the end."""
    proc = subprocess.Popen(
        [*X6WD, "sweep", *args], cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
        text=True, start_new_session=True,
    )  # fmt: skip
    try:
        yield proc
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGKILL)
        proc.communicate(timeout=60)


def test_a_second_sweep_into_a_folder_being_written_is_refused(tmp_path: Path) -> None:
    # two identical sweeps into one --out both simulated every run, writing the same files
    f = sweep_file(tmp_path, "seeds = 12\n[set]\nduration_s = 60.0\n")
    out = tmp_path / "out"
    args = [str(f), "--out", str(out), "--workers", "1", "--quiet", "--no-figures"]
    with _sweep_process(args) as first:
        deadline = time.monotonic() + 120
        while not run_files(out):  # under way: its cluster runs the runs
            assert first.poll() is None, first.communicate()
            assert time.monotonic() < deadline
            time.sleep(0.02)
        t0 = time.monotonic()
        second = run_cli(*args)
        assert second.returncode == 2, (second.stdout, second.stderr)
        assert first.poll() is None, "the first sweep ended before the second was refused"
        assert time.monotonic() - t0 < 30  # at once: no cluster, no run
        assert f"output directory {str(out)!r}: another sweep (pid {first.pid}) is writing it" in (
            second.stderr
        )
        # killed with no chance to clean up (SIGKILL): the lock went with it
        os.killpg(first.pid, signal.SIGKILL)
        first.wait(timeout=30)
    again = run_cli(*args)
    assert again.returncode == 0, (again.stdout, again.stderr)
    assert "12 runs (" in again.stdout and ", 0 failed;" in again.stdout
    assert len(run_files(out)) == 12
    assert (out / ".sweep.lock").read_text().strip().isdigit()  # the file stays, unlocked
    assert json.loads((out / "sweep.json").read_text())["name"] == "test"


def test_a_lock_file_that_is_a_link_is_refused_and_its_target_kept(tmp_path: Path) -> None:
    # the lock was opened through a symlink and truncated: the link's target was emptied
    from sim_backend.sweep import LOCK_FILE, out_dir_lock

    target = tmp_path / "precious.txt"
    target.write_text("keep me\n")
    out = tmp_path / "out"
    out.mkdir()
    (out / LOCK_FILE).symlink_to(target)
    with pytest.raises(ConfigError, match="cannot open"), out_dir_lock(out):
        pass
    assert target.read_text() == "keep me\n"
