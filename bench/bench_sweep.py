"""Sweep throughput: missions per minute through x6wd's executor, in process and on Dask.

The same missions (``config/scenarios/default.toml``: four waypoints, ~70 s simulated, the
full pseudorange model, the estimator) are run as a sweep (:func:`sim_backend.sweep.run_sweep`
into a temporary directory, so the figure includes planning, task transfer and writing each
run's record) by

- the executor in this process (no Dask): the anchor, one core's throughput;
- a Dask LocalCluster with 1 worker: anchored on the in-process figure (ratio = what the
  scheduler and the transfers cost);
- a LocalCluster with 2 workers: anchored on twice the 1-worker figure (ratio = scaling
  efficiency on this machine; the client and the scheduler share its cores).

Throughput excludes the cluster's start-up, reported on its own row (it is paid once per sweep).
The per-mission CPU cost (median wall seconds of a mission in process) is the figure
docs/sweeps.md uses to cost a 10,000-run sweep on N machines.

Usage (from the repository root)::

    python -m bench.bench_sweep [--quick] [--missions N]

``--quick``: one sweep of 4 missions per configuration (about 30 s on 2 cores); the default is
the best of two sweeps of 12 missions each (about 1.5 min).
"""

from __future__ import annotations

import argparse
import math
import os
import statistics
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:  # run as a script: make ``bench._common`` importable
    sys.path.insert(0, str(ROOT))

from bench._common import MissingExtra, Row, print_table, require_modules  # noqa: E402

if TYPE_CHECKING:
    from sim_backend.sweep import SweepSpec

SCENARIO = ROOT / "config" / "scenarios" / "default.toml"
DEFAULT_MISSIONS = 12
QUICK_MISSIONS = 4
REPEATS = 2  # timed sweeps per configuration (the best counts: the machine may be shared)


def _sweep(missions: int, seed: int) -> SweepSpec:
    from sim_backend.sweep import loads_sweep

    text = f'name = "bench"\nseed = {seed}\nseeds = {missions}\nscenarios = ["{SCENARIO}"]\n'
    return loads_sweep(text, ROOT)


def measure(missions: int, repeats: int = 1) -> dict[str, float]:
    """Missions per minute in process and on 1 and 2 LocalCluster workers (the best of
    ``repeats`` timed sweeps of ``missions`` missions, after one untimed mission per worker
    that pays the imports), the clusters' start-up with that warm-up (s), and the median
    mission wall time in process (s). Every sweep has its own sweep seed, so none reuses
    another's results."""
    # the LocalClusters need Dask: said now, not after the in-process sweeps
    require_modules("sweep", "dask", "distributed")
    from sim_backend.executor import Executor
    from sim_backend.sweep import run_sweep

    out: dict[str, float] = {}
    configs: list[tuple[str, int, dict[str, Any]]] = [
        ("inline", 1, {"inline": True}),
        ("1 worker", 1, {"workers": 1}),
        ("2 workers", 2, {"workers": 2}),
    ]
    seed = 100
    for name, n_workers, kw in configs:
        with tempfile.TemporaryDirectory(prefix="bench_sweep_") as tmp:
            t0 = time.perf_counter()
            with Executor(**kw) as ex:
                run_sweep(_sweep(n_workers, seed), Path(tmp) / "warm-up", ex)
                out[f"{name} start"] = time.perf_counter() - t0
                best = 0.0
                for r in range(repeats):
                    seed += 1
                    res = run_sweep(_sweep(missions, seed), Path(tmp) / str(r), ex)
                    if res.failed:
                        first = res.failed[0]["error"]
                        raise RuntimeError(f"{name}: {len(res.failed)} runs failed: {first}")
                    best = max(best, res.missions_per_min)
                    if name == "inline":
                        walls = [rec["wall_time_s"] for rec in res.records]
                        out["mission s"] = statistics.median(walls)
        out[name] = best
    return out


def rows(m: dict[str, float], missions: int) -> list[Row]:
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else math.nan
    note = f"best of the sweeps of {missions} missions of {SCENARIO.name}; load {load:.1f}"
    start = "once per sweep: the cluster and one warm-up mission per worker"
    per = "missions/min"
    return [
        Row(
            "sweep",
            "mission wall time (in process)",
            m["mission s"],
            "s",
            note=f"median of {missions}; ~70 s simulated each",
        ),
        Row("sweep", "throughput in process (no Dask)", m["inline"], per, note=note),
        Row(
            "sweep",
            "throughput LocalCluster 1 worker",
            m["1 worker"],
            per,
            m["inline"],
            f"{per} in process",
            note,
        ),
        Row(
            "sweep",
            "throughput LocalCluster 2 workers",
            m["2 workers"],
            per,
            2 * m["1 worker"],
            f"{per} = 2 x 1 worker",
            note + "; ratio = scaling efficiency",
        ),
        Row("sweep", "LocalCluster start-up, 1 worker", m["1 worker start"], "s", note=start),
        Row("sweep", "LocalCluster start-up, 2 workers", m["2 workers start"], "s", note=start),
    ]


def run(quick: bool = False) -> list[Row]:
    """bench/run.py's entry point."""
    n = QUICK_MISSIONS if quick else DEFAULT_MISSIONS
    return rows(measure(n, 1 if quick else REPEATS), n)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m bench.bench_sweep", description=__doc__.splitlines()[0], allow_abbrev=False
    )
    parser.add_argument("--quick", action="store_true", help=f"{QUICK_MISSIONS} missions each")
    parser.add_argument("--missions", type=int, default=None, help="missions per configuration")
    args = parser.parse_args(argv)
    n = args.missions or (QUICK_MISSIONS if args.quick else DEFAULT_MISSIONS)
    if n < 1:
        parser.error("--missions must be >= 1")
    try:
        print_table(rows(measure(n, 1 if args.quick else REPEATS), n))
    except MissingExtra as exc:
        print(exc, file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    from bench.bench_sweep import main as _main

    sys.exit(_main())
