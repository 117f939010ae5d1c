"""Baseline runs from a scenario: the simulator's own receiver driven along the real log's truth.

For each seed the scenario's receiver (:func:`sim_backend.receiver.build_receiver`, the one
``x6wd sim`` and HIL run: almanac sky, start time, fidelity, mask, atmosphere, walls, LCE
grid, every ``[[effects]]`` GPS layer, the NMEA minutes' decimals) reports positions for a
receiver that is truly where the real one was (the surveyed point, or the truth track at the
real log's times), placed at the real log's origin.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

from sim_backend.effects import PositionSeries
from sim_backend.executor import Executor
from x6wd.core.errors import ConfigError


def scenario_baseline(
    path: str | Path,
    template: PositionSeries,
    seeds: int,
    base_seed: int = 1000,
    progress: Callable[[int], None] | None = None,
    extra_effects: Sequence[Any] = (),
    executor: Executor | None = None,
) -> list[PositionSeries]:
    """``seeds`` error series (m) shaped like ``template`` (its times, origin and true
    motion), each from the scenario's simulated receiver with seed ``base_seed + i`` (split
    as ``x6wd sim`` splits a seed, so seed N is the receiver ``x6wd sim --seed N`` runs);
    ``extra_effects`` (GPS layers) run after the scenario's own, before the NMEA printing
    (the injection benchmark's withheld effects). The seeds run on ``executor`` (entered by
    the caller: x6wd's one executor, e.g. a Dask cluster), or one after another in this
    process; the list is in seed order either way. ``progress(k)``: k seeds done."""
    try:
        from sim_backend.world import load_world
    except ImportError as exc:  # pragma: no cover - the simulator ships with the package
        raise ConfigError(f"--scenario needs the simulator: {exc}") from exc
    if seeds < 1:
        raise ConfigError(f"--seeds {seeds}: must be >= 1")
    world = load_world(path)
    # The scenario describes the real log's site: its frame is the log's origin.
    origin = replace(world.origin, lat_deg=template.origin_lat_deg, lon_deg=template.origin_lon_deg)
    world = replace(world, origin=origin)
    ex = executor if executor is not None else Executor(inline=True)
    args = [(world, base_seed + i, template, tuple(extra_effects)) for i in range(seeds)]
    out: list[PositionSeries | None] = [None] * seeds
    runs = ex.map_unordered(_baseline_run, args, reraise=True)
    for done, outcome in enumerate(runs, start=1):
        if not outcome.ok:  # the cluster lost it (a failing seed raises its own error)
            raise ConfigError(f"baseline seed {base_seed + outcome.index}: {outcome.error}")
        out[outcome.index] = outcome.value
        if progress:
            progress(done)
    return [s for s in out if s is not None]


def _baseline_run(
    world: Any, seed: int, template: PositionSeries, extra_effects: Sequence[Any]
) -> PositionSeries:
    """One baseline seed (a task of the executor)."""
    from sim_backend.receiver import build_receiver

    return build_receiver(world, seed, extra_layers=extra_effects).errors(template)
