"""Whole missions in fast time: completion, arrival error, path ratio, by position source.

Every shipped scenario with waypoints (``config/scenarios/*.toml``: today default, zigzag and
building_route) runs ``sim_backend.mission.run_mission`` for seeds 1..N (default 20) with each
METHOD, a variation of the scenario's own ``[navigation]`` (the NavigationConfig defaults
where the scenario has none) made with ``dataclasses.replace``:

- ``estimator``: position_source = "ekf" (the robot's shipped default);
- ``raw``: position_source = "raw" (the raw GPS fixes);
- ``paper``: position_source = "constellation", filter_n = 20 (the paper's filter, the other
  navigation keys as shipped);
- ``paper-full``: the paper's whole navigation: Constellation N = 20, steering "paper",
  projection "two_radius", 3 m arrival windows (as ``NavigationConfig.paper()``).

Figures per scenario x method (anchors = the targets of issue 14, item 7):

- completion: missions completed / runs (target 100 %, in the open and beside the building);
- arrival error: the true horizontal distance (m) from the antenna to the waypoint when the
  arrival was decided (``summary.extra["arrivals"][i]["true_error_m"]``), pooled over every
  waypoint reached in every run; median and p95. Its anchor is the GPS's own slow error at
  the same moments (``gps_slow_error_m``: the mean fix error over ±5 s of the arrival, whose
  white part averages out; what no navigation can see without a reference), so the ratio is
  median arrival error / median GPS slow error (target <= 1.10: navigation adds almost
  nothing);
- path ratio: true path length / straight polyline start -> waypoints, over completed runs,
  median and max (target <= 1.10 on open ground; no target beside the building);
- time to finish: simulated seconds (median over completed runs); its anchor is the straight
  polyline at the method's cruise speed (``max_speed_mps`` x ``cruise_pct``);
- wall time: the runs' summed wall seconds (they run on ``--jobs`` workers of x6wd's one
  executor, ``sim_backend.executor``: a Dask LocalCluster, or this process with ``--jobs 1``).

A run that raises is a failed run with its error (counted as not completed; the error is in
the completion row's note and on stderr), never a crash of the benchmark.

Usage (from the repository root)::

    python -m bench.bench_mission [--seeds 20] [--jobs J] [--quick] [--md FILE]
        [--scenario NAME ...] [--method NAME ...]

``--quick``: 3 seeds, default and building_route only (about 30 s on 2 cores); the full run
is 3 scenarios x 4 methods x 20 seeds = 240 missions, about 5 min on 2 cores. Prints the
rows (bench/_common) and a markdown table for docs/navigation.md (also written to
``--md FILE``).
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import time
import traceback
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:  # run as a script: make ``bench._common`` importable
    sys.path.insert(0, str(ROOT))

from bench._common import Row, print_table  # noqa: E402

SCENARIO_DIR = ROOT / "config" / "scenarios"
# Method name -> NavigationConfig keys replaced on the scenario's navigation.
METHODS: dict[str, dict[str, Any]] = {
    "estimator": {"position_source": "ekf"},
    "raw": {"position_source": "raw"},
    "paper": {"position_source": "constellation", "filter_n": 20},
    # the paper's whole navigation (NavigationConfig.paper(): its 3 m windows too, which its
    # bang-bang steering needs), at the robot's cruise and turn percentages
    "paper-full": {
        "position_source": "constellation",
        "filter_n": 20,
        "steering": "paper",
        "projection": "two_radius",
        "delta_x_m": 3.0,
        "delta_y_m": 3.0,
    },
}
QUICK_SCENARIOS = ("default", "building_route")
DEFAULT_SEEDS = 20
QUICK_SEEDS = 3
COMPLETION_TARGET_PCT = 100.0
ARRIVAL_RATIO_TARGET = 1.10  # median arrival error / median GPS slow error, same moments
PATH_RATIO_TARGET = 1.10  # in the open


@dataclass
class RunResult:
    """One mission run. Lengths in metres, times in seconds; ``error`` is set (and
    ``completed`` False) when the run raised; ``arrivals`` is None when the summary has no
    ``extra["arrivals"]``."""

    scenario: str
    method: str
    seed: int
    completed: bool = False
    waypoints_reached: int = 0
    waypoint_count: int = 0
    open_ground: bool = True
    path_length_m: float = math.nan
    straight_length_m: float = math.nan
    sim_time_s: float = math.nan
    wall_time_s: float = math.nan
    cruise_mps: float = math.nan
    windows_m: tuple[float, float] = (math.nan, math.nan)  # arrival windows (delta_x, delta_y)
    arrivals: list[dict[str, Any]] | None = None
    position_source: str | None = None  # as the run's summary reports it
    error: str | None = None

    @property
    def path_ratio(self) -> float:
        """True path length / straight polyline (dimensionless; NaN without a length)."""
        if not self.straight_length_m > 0:
            return math.nan
        return self.path_length_m / self.straight_length_m


@dataclass
class Cell:
    """The figures of one scenario x method over its seeds (m, s; ratios dimensionless)."""

    scenario: str
    method: str
    runs: int
    completed: int
    errors: list[str] = field(default_factory=list)
    open_ground: bool = True
    arrivals: int = 0
    arrival_median_m: float = math.nan
    arrival_p95_m: float = math.nan
    gps_median_m: float = math.nan
    gps_p95_m: float = math.nan
    path_ratio_median: float = math.nan
    path_ratio_max: float = math.nan
    sim_time_median_s: float = math.nan
    ideal_time_s: float = math.nan
    wall_time_s: float = 0.0
    wall_median_s: float = math.nan
    missing_arrivals: int = 0
    windows_m: tuple[float, float] = (math.nan, math.nan)

    @property
    def completion_pct(self) -> float:
        """Completed runs in percent of the runs."""
        return 100.0 * self.completed / self.runs if self.runs else math.nan

    @property
    def arrival_ratio(self) -> float:
        """Median true arrival error / median GPS slow error at the same moments."""
        if not self.gps_median_m > 0:
            return math.nan
        return self.arrival_median_m / self.gps_median_m


def scenarios(names: Sequence[str] | None = None) -> list[Path]:
    """The shipped scenario files with waypoints: all (open ground first), or those whose stem
    is in ``names`` (in that order)."""
    from sim_backend.world import load_world

    paths = sorted(SCENARIO_DIR.glob("*.toml"))
    if names:
        by_stem = {p.stem: p for p in paths}
        unknown = [n for n in names if n not in by_stem]
        if unknown:
            raise ValueError(f"unknown scenario {unknown[0]!r} (shipped: {', '.join(by_stem)})")
        paths = [by_stem[n] for n in names]
    worlds = [(p, load_world(p)) for p in paths]
    with_waypoints = [(p, w) for p, w in worlds if len(w.waypoints_enu_m())]
    if not names:  # open ground first, then among buildings; by name within each
        with_waypoints.sort(key=lambda pw: (bool(pw[1].walls or pw[1].roofs), pw[0].stem))
    return [p for p, _w in with_waypoints]


def method_world(world: Any, method: str) -> Any:
    """``world`` with its navigation changed as METHODS[method] says (dataclasses.replace;
    raises TypeError for a key NavigationConfig does not have)."""
    nav = replace(world.navigation, **METHODS[method])
    return replace(world, navigation=nav)


def _finite(values: list[Any]) -> list[float]:
    out = []
    for v in values:
        if isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v):
            out.append(float(v))
    return out


def run_one(scenario: str | Path, method: str, seed: int) -> RunResult:
    """One mission of the scenario file with METHOD ``method`` and ``seed``, its summary
    only (no files). Never raises: an exception becomes ``error``."""
    path = Path(scenario)
    res = RunResult(scenario=path.stem, method=method, seed=int(seed))
    t0 = time.perf_counter()
    try:
        from sim_backend.mission import run_mission
        from sim_backend.world import load_world

        base = load_world(path)
        res.open_ground = not base.walls and not base.roofs
        world = method_world(base, method)
        res.cruise_mps = world.vehicle.max_speed_mps * world.navigation.cruise_pct / 100.0
        res.windows_m = (world.navigation.delta_x_m, world.navigation.delta_y_m)
        s = run_mission(world, None, seed=int(seed))
        res.completed = bool(s.completed)
        res.waypoints_reached = s.waypoints_reached
        res.waypoint_count = s.waypoint_count
        res.path_length_m = s.path_length_m
        res.straight_length_m = s.straight_length_m
        res.sim_time_s = s.sim_time_s
        arrivals = s.extra.get("arrivals")
        res.arrivals = None if arrivals is None else [dict(a) for a in arrivals]
        res.position_source = s.extra.get("position_source")
    except Exception as exc:  # a failed run is a figure, not a crash of the benchmark
        res.completed = False
        last = traceback.extract_tb(exc.__traceback__)[-1:]
        where = f" at {Path(last[0].filename).name}:{last[0].lineno}" if last else ""
        res.error = f"{type(exc).__name__}: {exc}{where}"
    res.wall_time_s = time.perf_counter() - t0
    return res


def run_all(
    paths: Sequence[Path],
    methods: Sequence[str],
    seeds: Sequence[int],
    jobs: int | None = None,
) -> list[RunResult]:
    """Every scenario x method x seed through x6wd's one executor
    (:class:`sim_backend.executor.Executor`, the one ``x6wd sweep`` uses): a Dask LocalCluster
    of ``jobs`` worker processes (default os.cpu_count()); ``jobs`` 1, or no Dask installed,
    runs in this process. A task the cluster could not finish is recorded as that run's
    error."""
    from sim_backend.executor import Executor, dask_available

    tasks = [(str(p), m, s) for p in paths for m in methods for s in seeds]
    jobs = max(1, jobs or os.cpu_count() or 1)
    inline = jobs == 1 or not dask_available()
    if jobs > 1 and inline:
        print("bench_mission: no Dask (pip install 'x6wd[sweep]'): running in this process",
              file=sys.stderr)  # fmt: skip
    results: list[RunResult] = []
    with Executor(workers=None if inline else jobs, inline=inline) as ex:
        names = [f"{Path(p).stem}-{m}-{s}" for p, m, s in tasks]
        for out in ex.map_unordered(run_one, tasks, names=names):
            p, m, s = tasks[out.index]
            if out.ok:
                results.append(out.value)
            else:  # the worker itself failed (run_one never raises)
                results.append(RunResult(Path(p).stem, m, s, error=out.error))
    order = {t: i for i, t in enumerate((Path(p).stem, m, s) for p, m, s in tasks)}
    results.sort(key=lambda r: order.get((r.scenario, r.method, r.seed), len(order)))
    return results


def summarise(results: Sequence[RunResult]) -> list[Cell]:
    """Group the runs by scenario x method (in the order first seen) and compute the figures."""
    import numpy as np  # here, so importing bench (one BLAS thread) always comes first

    groups: dict[tuple[str, str], list[RunResult]] = {}
    for r in results:
        groups.setdefault((r.scenario, r.method), []).append(r)
    cells = []
    for (scen, method), rs in groups.items():
        done = [r for r in rs if r.completed]
        c = Cell(scen, method, runs=len(rs), completed=len(done))
        c.errors = [f"seed {r.seed}: {r.error}" for r in rs if r.error]
        c.open_ground = all(r.open_ground for r in rs if r.error is None)
        c.windows_m = next((r.windows_m for r in rs if r.error is None), c.windows_m)
        true_m: list[float] = []
        gps_m: list[float] = []
        for r in rs:
            if r.error is None and r.arrivals is None:
                c.missing_arrivals += 1
            for a in r.arrivals or []:
                t, g = a.get("true_error_m"), a.get("gps_slow_error_m")
                true_m += _finite([t])
                if _finite([t]) and _finite([g]):
                    gps_m += _finite([g])
        c.arrivals = len(true_m)
        if true_m:
            c.arrival_median_m = float(np.median(true_m))
            c.arrival_p95_m = float(np.percentile(true_m, 95))
        if gps_m:
            c.gps_median_m = float(np.median(gps_m))
            c.gps_p95_m = float(np.percentile(gps_m, 95))
        ratios = _finite([r.path_ratio for r in done])
        if ratios:
            c.path_ratio_median = float(np.median(ratios))
            c.path_ratio_max = float(np.max(ratios))
        times = _finite([r.sim_time_s for r in done])
        if times:
            c.sim_time_median_s = float(np.median(times))
        ideal = _finite([r.straight_length_m / r.cruise_mps for r in rs if r.cruise_mps > 0])
        if ideal:
            c.ideal_time_s = float(np.median(ideal))
        walls = _finite([r.wall_time_s for r in rs])
        c.wall_time_s = float(sum(walls))
        if walls:
            c.wall_median_s = float(np.median(walls))
        cells.append(c)
    return cells


def rows(cells: Sequence[Cell]) -> list[Row]:
    """The bench/_common rows of each cell, each figure with its anchor."""
    out: list[Row] = []
    for c in cells:
        name = f"{c.scenario} / {c.method}"
        where = "open ground" if c.open_ground else "beside a building"
        note = f"{c.completed}/{c.runs} completed ({where})"
        if c.errors:
            note += f"; {len(c.errors)} raised, first: {c.errors[0]}"
        out.append(Row("mission", f"{name}: completion", c.completion_pct, "%",
                       COMPLETION_TARGET_PCT, "% target", note))  # fmt: skip
        arr_note = (
            f"{c.arrivals} arrivals, windows +-{c.windows_m[0]:g}/+-{c.windows_m[1]:g} m;"
            f" target ratio <= {ARRIVAL_RATIO_TARGET:.2f}"
        )
        if c.missing_arrivals:
            arr_note += f"; {c.missing_arrivals} runs without extra['arrivals']"
        out.append(Row("mission", f"{name}: arrival error median", c.arrival_median_m, "m",
                       c.gps_median_m, "m GPS slow error median", arr_note))  # fmt: skip
        out.append(Row("mission", f"{name}: arrival error p95", c.arrival_p95_m, "m",
                       c.gps_p95_m, "m GPS slow error p95", "same arrivals"))  # fmt: skip
        path_anchor = PATH_RATIO_TARGET if c.open_ground else None
        path_note = f"max {c.path_ratio_max:.3f}, over {c.completed} completed runs"
        if not c.open_ground:
            path_note += "; no target beside a building"
        out.append(Row("mission", f"{name}: path ratio median", c.path_ratio_median,
                       "x straight", path_anchor, "x target", path_note))  # fmt: skip
        out.append(Row("mission", f"{name}: path ratio max", c.path_ratio_max, "x straight",
                       path_anchor, "x target", ""))  # fmt: skip
        out.append(Row("mission", f"{name}: time to finish median", c.sim_time_median_s,
                       "s simulated", c.ideal_time_s, "s straight line at cruise",
                       f"over {c.completed} completed runs"))  # fmt: skip
        out.append(Row("mission", f"{name}: wall time", c.wall_time_s, "s", None, "",
                       f"{c.runs} runs, median {c.wall_median_s:.2f} s each"))  # fmt: skip
    return out


def _f(v: float, fmt: str = ".2f") -> str:
    return "-" if not math.isfinite(v) else format(v, fmt)


def markdown(cells: Sequence[Cell], seeds: Sequence[int]) -> str:
    """A markdown table of the cells for docs/navigation.md (with a line saying the seeds)."""
    lo, hi = (min(seeds), max(seeds)) if seeds else (0, 0)
    windows = (
        ", ".join(
            sorted(
                {
                    f"+-{c.windows_m[0]:g}/+-{c.windows_m[1]:g}"
                    for c in cells
                    if math.isfinite(c.windows_m[0])
                }
            )
        )
        or "-"
    )
    lines = [
        f"Seeds {lo}-{hi} ({len(seeds)}) per row; arrival errors pooled over every waypoint "
        "reached; path ratio and time over completed runs. Targets: 100 % completed, arrival "
        f"ratio <= {ARRIVAL_RATIO_TARGET:.2f}, path ratio <= {PATH_RATIO_TARGET:.2f} in the "
        f"open. Arrival windows (delta_x/delta_y): {windows} m.",
        "",
        "| scenario | method | completed | arrival error median / p95 | GPS slow error median "
        "| arrival / GPS | path ratio median (max) | time median | wall |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for c in cells:
        done = f"{c.completed}/{c.runs}" + (f" ({len(c.errors)} raised)" if c.errors else "")
        lines.append(
            f"| {c.scenario} | {c.method} | {done} "
            f"| {_f(c.arrival_median_m)} / {_f(c.arrival_p95_m)} m | {_f(c.gps_median_m)} m "
            f"| {_f(c.arrival_ratio)} | {_f(c.path_ratio_median, '.3f')} "
            f"({_f(c.path_ratio_max, '.3f')}) | {_f(c.sim_time_median_s, '.1f')} s "
            f"| {_f(c.wall_time_s, '.1f')} s |"
        )
    return "\n".join(lines) + "\n"


def measure(
    quick: bool = False,
    seeds: int | None = None,
    jobs: int | None = None,
    scenario_names: Sequence[str] | None = None,
    methods: Sequence[str] | None = None,
) -> tuple[list[Cell], list[RunResult], list[int]]:
    """Run the benchmark; returns the cells, the individual runs and the seeds used."""
    n = seeds if seeds is not None else (QUICK_SEEDS if quick else DEFAULT_SEEDS)
    seed_list = list(range(1, n + 1))
    names = scenario_names or (QUICK_SCENARIOS if quick else None)
    paths = scenarios(names)
    results = run_all(paths, list(methods or METHODS), seed_list, jobs)
    return summarise(results), results, seed_list


def run(quick: bool = False) -> list[Row]:
    """All figures (bench/run.py's entry point): 20 seeds x every scenario with waypoints,
    or 3 seeds x default and building_route with ``quick``."""
    cells, _results, _seeds = measure(quick=quick)
    return rows(cells)


def main(argv: Sequence[str] | None = None) -> int:
    """Command line: run, print the rows and the markdown table; 0 unless a run raised."""
    parser = argparse.ArgumentParser(
        prog="python -m bench.bench_mission",
        description=__doc__.splitlines()[0],
        allow_abbrev=False,
    )
    parser.add_argument(
        "--seeds",
        type=int,
        default=None,
        help=f"seeds 1..N (default {DEFAULT_SEEDS}, {QUICK_SEEDS} with --quick)",
    )
    parser.add_argument(
        "--quick",
        action="store_true",
        help=f"{QUICK_SEEDS} seeds, scenarios {', '.join(QUICK_SCENARIOS)}",
    )
    parser.add_argument(
        "--jobs", type=int, default=None, help="worker processes (default os.cpu_count())"
    )
    parser.add_argument("--md", type=Path, default=None, help="also write the markdown here")
    parser.add_argument(
        "--scenario",
        action="append",
        metavar="NAME",
        help="a scenario file's stem, e.g. zigzag (repeatable)",
    )
    parser.add_argument("--method", action="append", choices=list(METHODS),
                        help="a method (repeatable; default all)")  # fmt: skip
    args = parser.parse_args(argv)
    if args.seeds is not None and args.seeds < 1:
        parser.error("--seeds must be >= 1")
    try:
        cells, results, seed_list = measure(
            args.quick, args.seeds, args.jobs, args.scenario, args.method
        )
    except ValueError as exc:
        parser.error(str(exc))
    print_table(rows(cells))
    md = markdown(cells, seed_list)
    print()
    print(md, end="")
    if args.md is not None:
        args.md.write_text(md)
    failed = [r for r in results if r.error]
    for r in failed:
        print(f"run failed: {r.scenario} / {r.method} seed {r.seed}: {r.error}", file=sys.stderr)
    return 1 if failed else 0


if __name__ == "__main__":
    # Through the package module, so the workers unpickle bench.bench_mission.run_one.
    from bench.bench_mission import main as _main

    sys.exit(_main())
