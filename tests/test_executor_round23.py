"""A task whose worker dies each time it runs it (an outside audit, round 23): Dask gives it
up as KilledWorker, which the executor called lost ("the same command runs it again"), so
every call of the sweep ran it again and killed as many workers. It is the task's failure:
an error with its cause, beside the tasks that ran. A real scheduler and worker, the worker
dying by its own hand (os._exit: no goodbye, as the kernel's OOM killer)."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from sim_backend.executor import Executor
from tests.conftest import ROOT
from tests.test_sweep import Cluster


def die_on(x: int) -> int:
    """x squared, except that 3 kills the process that runs it."""
    if x == 3:
        os._exit(1)
    return x * x


@pytest.mark.integration
def test_a_task_that_kills_its_worker_is_a_failure_and_the_cluster_goes_on(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # the scheduler gives a task up at its first death (3 by default: the same, slower)
    monkeypatch.setenv("DASK_DISTRIBUTED__SCHEDULER__ALLOWED_FAILURES", "0")
    # die_on goes by reference to this module, imported by pytest from tests/ as a top-level
    # module: the scheduler and the worker import it so
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join([str(ROOT / "tests"), str(ROOT)]))
    c = Cluster(tmp_path / "dask")
    c.tmp.mkdir()
    try:
        c.start(1)
        with Executor(scheduler=c.address) as ex:
            (dead,) = ex.map_unordered(die_on, [(3,)])
            # the worker's nanny starts it again: the next tasks run (alone: a task that was
            # on the worker when it died may be given up with it at allowed-failures 0)
            c.wait_for_workers(1)
            rest = {o.index: o for o in ex.map_unordered(die_on, [(x,) for x in (0, 1, 2)])}
    finally:
        c.stop()
    assert dead.kind == "task" and dead.error is not None, dead
    assert dead.error.startswith("KilledWorker") and "worker died" in dead.error
    assert [(rest[i].ok, rest[i].value) for i in range(3)] == [(True, 0), (True, 1), (True, 4)]
