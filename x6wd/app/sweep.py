"""``x6wd sweep SWEEP.toml [--scheduler ADDRESS] [--workers N] [--out DIR]``.

A grid of scenarios x parameters x seeds (:mod:`sim_backend.sweep`: the file format, the
seeds, resuming), run on Dask's distributed scheduler through the one executor
(:class:`sim_backend.executor.Executor`): a LocalCluster of ``--workers`` processes on this
machine by default, or ``--scheduler tcp://HOST:PORT`` for a running cluster. Writes
``OUT/runs/*.json`` as runs finish and at the end ``results.csv`` (and ``results.parquet`` with
pyarrow), ``arrivals.csv``, three figures and ``summary.md`` (:mod:`sim_backend.sweep_report`).
Usage and costs: docs/sweeps.md.

Exit codes: 0 every run succeeded; 1 some run failed (recorded with its error) or was lost by
the cluster (run again by the same command); 2 a bad sweep file, scenario key or value, no
Dask, an --out folder holding another sweep (another name or seed) or that another sweep is
writing (its lock, ``OUT/.sweep.lock``, is held), or a --scheduler that is
malformed, unknown or silent (checked even when nothing is left to run); 130 interrupted
(finished runs are kept: run the same command again to finish).
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import signal
import socket
import sys
import threading
from collections.abc import Sequence
from pathlib import Path

from sim_backend.executor import Executor, TextProgress, probe_scheduler
from sim_backend.sweep import (
    LOCK_FILE,
    MAX_RUNS,
    Run,
    RunStore,
    SweepSpec,
    check_out_dir,
    legacy_cell_id,
    load_sweep,
    out_dir_lock,
    plan,
    run_count,
    run_sweep,
    split_done,
    stale_reason,
)
from sim_backend.sweep_report import write_report
from x6wd.core.errors import ConfigError, X6wdError
from x6wd.core.outdir import output_dir


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("sweep", help="sweep file (TOML), e.g. config/sweeps/position_source.toml")
    parser.add_argument(
        "--scheduler",
        metavar="ADDRESS",
        default=None,
        help="a running Dask scheduler (tcp://host:8786); default: a LocalCluster here",
    )
    parser.add_argument(
        "--workers",
        type=int,
        default=None,
        metavar="N",
        help="LocalCluster worker processes (default: CPU count); with --scheduler, wait until"
        " N workers have joined",
    )
    parser.add_argument(
        "--out",
        default=None,
        help="output directory (default out/sweeps/SWEEP_FILE_STEM); one that holds another"
        " sweep's results (another name or seed) is refused",
    )
    parser.add_argument(
        "--retry-failed",
        action="store_true",
        help="run again the runs whose mission raised (kept as failed otherwise)",
    )
    parser.add_argument(
        "--seeds",
        type=int,
        default=None,
        metavar="N",
        help="missions per cell instead of the file's seeds (the first N of them: a quick"
        " look with 1; the same command without it adds the rest). The tables are of these"
        " runs; finished runs of the folder outside them are kept, counted on stderr and in"
        " summary.md",
    )
    parser.add_argument(
        "--max-runs",
        type=int,
        default=MAX_RUNS,
        metavar="N",
        help=f"refuse a sweep of more than N runs (default {MAX_RUNS:,}): a mistyped grid or"
        " seed count would otherwise plan for hours",
    )
    parser.add_argument(
        "--worker-timeout",
        type=float,
        default=None,
        metavar="S",
        help="give up the runs left once no worker has been connected for S seconds (default"
        " 60; they are lost, exit 1, and the same command runs them); also how long --workers"
        " N waits for N workers to join a --scheduler",
    )
    parser.add_argument(
        "--dashboard",
        default=None,
        metavar="ADDRESS",
        help="open the LocalCluster's Dask dashboard at ADDRESS: HOST:PORT (e.g."
        " 127.0.0.1:8787) or a bare PORT, which listens on all interfaces; IPv6 addresses"
        " are not supported; default none",
    )
    parser.add_argument("--no-figures", action="store_true", help="skip the PNG figures")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")


def _runs(n: int) -> str:
    return f"{n} run{'' if n == 1 else 's'}"


def outside_runs(runs: Sequence[Run], store: RunStore) -> dict[str, int]:
    """The finished runs (succeeded or raised) in ``store`` that ``runs`` do not plan, and so
    are in no table of this call: ``count``; ``more_seeds`` of them replicates of a planned
    cell past this plan's seeds (a quick look with ``--seeds 1`` at a finished sweep), the
    highest such replicate + 1 as ``seeds`` (0 without any); the rest are of cells not in
    this grid (a value or a scenario since left out). Their files are kept: the sweep that
    plans them again tables them, without running them."""
    planned = {r.run_id for r in runs}
    digests = {r.cell.cell_id: r.cell.digest for r in runs}
    for c in list(digests):  # a folder of before 2026-12-05's runs
        digests[legacy_cell_id(c)] = digests[c]
    count = more = stale = seeds = 0
    for path in sorted(store.dir.glob("*.json")):
        if path.stem in planned:
            continue
        rec = store.load(path.stem)
        if rec is None or rec.get("status") not in ("ok", "error"):
            continue
        count += 1
        replicate, cell = rec.get("replicate"), rec.get("cell_id")
        if cell in digests and isinstance(replicate, int):
            if rec.get("digest") != digests[cell] or stale_reason(rec) is not None:
                stale += 1  # a changed scenario or file, or an older x6wd: run again
                continue
            more += 1
            seeds = max(seeds, replicate + 1)
    return {"count": count, "more_seeds": more, "stale_seeds": stale, "seeds": seeds}


def _outside_text(outside: dict[str, int], runs_dir: Path, file_seeds: int, seeds: int) -> str:
    """The stderr line about :func:`outside_runs` ("" when there are none)."""
    n, more, stale = outside["count"], outside["more_seeds"], outside.get("stale_seeds", 0)
    if not n:
        return ""
    why = []
    if more:
        again = (
            "the same command without --seeds tables them"
            if seeds < file_seeds and outside["seeds"] <= file_seeds
            else f"--seeds {outside['seeds']} tables them"
        )
        why.append(f"{more} of them further seeds of these cells: {again}")
    if stale:
        why.append(
            f"{stale} of them further seeds of these cells made with another scenario, file"
            " or x6wd: the sweep that plans them runs them again"
        )
    if n - more - stale:
        why.append(
            f"{n - more - stale} of cells not in this grid: the sweep file that planned them"
            " tables them"
        )
    return (
        f"sweep: {_runs(n)} finished in {runs_dir} {'is' if n == 1 else 'are'} outside this"
        f" sweep's grid and not in results.csv or summary.md ({'; '.join(why)}; none is run"
        " now)"
    )


def _check_dashboard(address: str) -> None:
    """Refuse a ``--dashboard`` that is neither HOST:PORT nor a bare PORT (all interfaces, as
    Dask takes it) with a port 0..65535 and a host that resolves, or whose host is an IPv6
    address (Dask's dashboard address cannot hold one): a LocalCluster given one fails
    minutes later with a long traceback."""
    host, _, port = address.rpartition(":")
    why = ""
    if not port.isdigit() or int(port) > 65535:
        why = "expected HOST:PORT or PORT with a port 0..65535 (e.g. 127.0.0.1:8787)"
    elif ":" in host or "[" in host:
        why = (
            "an IPv6 address (a host with ':' or in [brackets]) is not supported for the"
            " dashboard (Dask cannot parse it): give an IPv4 address or a host name, e.g."
            " 127.0.0.1:8787 or localhost:8787"
        )
    elif host:
        try:
            socket.getaddrinfo(host, int(port))
        except (OSError, UnicodeError) as exc:
            why = f"host {host!r} does not resolve ({getattr(exc, 'strerror', None) or exc})"
    if why:
        raise ConfigError(f"--dashboard {address}: {why}")


def main(args: argparse.Namespace) -> int:
    """Plan (validating every cell), run what is missing, write the report."""
    if args.dashboard is not None:
        _check_dashboard(args.dashboard)
    spec = load_sweep(args.sweep)
    file_seeds = spec.seeds
    if args.seeds is not None:
        if args.seeds < 1:
            raise ConfigError(f"--seeds: expected an integer >= 1, got {args.seeds}")
        spec = dataclasses.replace(spec, seeds=args.seeds)
    total = run_count(spec)
    if total > args.max_runs:
        raise ConfigError(
            f"{args.sweep}: {total:,} runs (scenarios x grid x seeds) over --max-runs"
            f" {args.max_runs:,}; raise --max-runs to run it"
        )
    runs = plan(spec)  # a bad key or value stops here, before any cluster starts
    wanted = Path(args.out) if args.out else Path("out") / "sweeps" / Path(args.sweep).stem
    created = _made_here(wanted)
    out = output_dir(wanted)
    with out_dir_lock(out):  # a second sweep into this folder (the same one, even): exit 2
        try:
            check_out_dir(spec, out)  # another sweep's results are not replaced
            return _run(args, spec, runs, out, file_seeds)
        except X6wdError:
            if created:  # a wrong --scheduler, --workers ...: no folder of nothing left behind
                _remove_if_empty(out)  # under this call's own lock, never another's
            raise


def _made_here(path: Path) -> bool:
    """Make ``path`` (and its parents); True only when this call made ``path`` itself, so
    that two sweeps started at once into a new folder never both take it as theirs."""
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.mkdir()
    except OSError:  # there already, or not makeable: output_dir says why
        return False
    return True


def _remove_if_empty(out: Path) -> None:
    """Remove ``out`` when it holds nothing but its lock file (held by the caller) and an
    empty ``runs/``."""
    for step in (
        lambda: (out / "runs").rmdir(),
        lambda: (out / LOCK_FILE).unlink(),
        lambda: out.rmdir(),
    ):
        with contextlib.suppress(OSError):  # not empty: a run was written, kept
            step()


class Terminated(KeyboardInterrupt):
    """SIGTERM (a batch scheduler's, ``timeout``'s): the sweep ends as on Ctrl-C (the cluster
    shut down, the finished runs kept and said), with exit code 143."""


def _terminated(_signum: int, _frame: object) -> None:
    raise Terminated


def _run(
    args: argparse.Namespace, spec: SweepSpec, runs: list[Run], out: Path, file_seeds: int
) -> int:
    """Run what is missing of ``runs`` into ``out`` (locked by :func:`main`), write the
    report, say what was done; the exit code."""
    progress = None if args.quiet else TextProgress(len(runs), "runs")
    # checks --workers and an empty --scheduler before RunStore makes OUT/runs
    executor = Executor(
        scheduler=args.scheduler,
        workers=args.workers,
        worker_timeout_s=args.worker_timeout,
        dashboard=args.dashboard,
    )
    _done, todo = split_done(runs, RunStore(out), args.retry_failed)
    # Nothing left to run (a finished sweep run again): no cluster to start, only the report;
    # but a --scheduler that is wrong is said so (exit 2), as it would be with runs to do.
    if not todo:
        if args.scheduler:
            probe_scheduler(args.scheduler, executor.connect_timeout_s)
        executor = Executor(inline=True)
    previous = None
    if threading.current_thread() is threading.main_thread():
        previous = signal.signal(signal.SIGTERM, _terminated)
    try:
        with executor:
            result = run_sweep(
                spec,
                out,
                executor,
                progress=progress,
                retry_failed=args.retry_failed,
                runs=runs,
                waiting=progress.waiting if progress else None,
            )
    except KeyboardInterrupt as exc:
        kept = len(split_done(runs, RunStore(out), args.retry_failed)[0])
        print(
            f"\nsweep interrupted: {kept}/{len(runs)} runs are done in {out / 'runs'};"
            " the same command finishes the rest",
            file=sys.stderr,
        )
        if isinstance(exc, Terminated):
            return 128 + signal.SIGTERM
        raise
    finally:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)
    outside = outside_runs(runs, RunStore(out))
    info = {
        "name": spec.name,
        "source": str(spec.source) if spec.source else None,
        "seed": spec.seed,
        "seeds": spec.seeds,
        "engine": spec.engine,
        "scenarios": [str(p) for p in spec.scenarios],
        "set": spec.fixed,
        "grid": spec.grid,
        "ran": result.ran,
        "skipped": result.skipped,
        "executor": result.executor,
        "wall_s": result.wall_s,
        "missions_per_min": result.missions_per_min,
        "raised": result.raised,
        "outside": outside,
    }
    write_report(info, result.records, out, figures=not args.no_figures)
    errors, lost = result.errors, result.lost
    raised_text = f" ({_runs(result.raised)} that raised not counted)" if result.raised else ""
    if result.ran > result.raised:
        rate = f"{result.missions_per_min:.1f} missions/min on {result.executor}{raised_text}"
    elif result.ran:
        rate = f"no mission ran on {result.executor}: {_runs(result.raised)} raised"
    elif lost:
        rate = f"no run finished on {result.executor}"
    else:
        rate = "nothing left to run"
    lost_text = f", {len(lost)} lost: the same command runs them" if lost else ""
    print(
        f"sweep {spec.name!r}: {_runs(len(result.records))} ({result.ran} run now, {result.skipped}"
        f" found done{lost_text}), {len(errors)} failed; {rate};"
        f" summary in {out / 'summary.md'}"
    )
    said = _outside_text(outside, out / "runs", file_seeds, spec.seeds)
    if said:
        print(said, file=sys.stderr)
    for rec in errors[:10]:
        print(
            f"run failed: {rec['run_id']} seed {rec['seed']}: {rec.get('error')}", file=sys.stderr
        )
    if lost:
        print(
            f"{_runs(len(lost))} lost by the cluster (the first: {lost[0].get('error')}):"
            " run the same command again to finish them",
            file=sys.stderr,
        )
    return 1 if errors or lost else 0
