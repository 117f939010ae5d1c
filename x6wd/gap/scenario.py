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
from x6wd.core.errors import ConfigError


def scenario_baseline(
    path: str | Path,
    template: PositionSeries,
    seeds: int,
    base_seed: int = 1000,
    progress: Callable[[int], None] | None = None,
    extra_effects: Sequence[Any] = (),
) -> list[PositionSeries]:
    """``seeds`` error series (m) shaped like ``template`` (its times, origin and true
    motion), each from the scenario's simulated receiver with seed ``base_seed + i`` (split
    as ``x6wd sim`` splits a seed, so seed N is the receiver ``x6wd sim --seed N`` runs);
    ``extra_effects`` (GPS layers) run after the scenario's own, before the NMEA printing
    (the injection benchmark's withheld effects)."""
    try:
        from sim_backend.receiver import build_receiver
        from sim_backend.world import load_world
    except ImportError as exc:  # pragma: no cover - the simulator ships with the package
        raise ConfigError(f"--scenario needs the simulator: {exc}") from exc
    if seeds < 1:
        raise ConfigError(f"--seeds {seeds}: must be >= 1")
    world = load_world(path)
    # The scenario describes the real log's site: its frame is the log's origin.
    origin = replace(world.origin, lat_deg=template.origin_lat_deg, lon_deg=template.origin_lon_deg)
    world = replace(world, origin=origin)
    out = []
    for i in range(seeds):
        receiver = build_receiver(world, base_seed + i, extra_layers=extra_effects)
        out.append(receiver.errors(template))
        if progress:
            progress(i + 1)
    return out
