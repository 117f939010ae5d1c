"""Baseline runs from a scenario: the project's GNSS model driven along the real log's truth.

For each seed a :class:`sim_backend.gnss.GnssModel` (the scenario's almanac, origin, start
time, fidelity, mask, atmosphere and walls) reports positions for a receiver that is truly
where the real one was (the surveyed point, or the truth track at the real log's times);
the scenario's ``[[effects]]`` are added and the positions printed with its NMEA decimals.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from sim_backend.effects import (
    PositionSeries,
    Quantization,
    apply_effects,
    metres_per_degree,
    truth_track_m,
)
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
    motion), each from the scenario's simulator with seed ``base_seed + i``;
    ``extra_effects`` are added after the scenario's own, before NMEA printing (the
    injection benchmark's withheld effects)."""
    try:
        from sim_backend.gnss import GnssModel, ReceiverParams
        from sim_backend.sky import SatelliteSet
        from sim_backend.world import load_world
    except ImportError as exc:  # pragma: no cover - the simulator ships with the package
        raise ConfigError(f"--scenario needs the simulator: {exc}") from exc
    if seeds < 1:
        raise ConfigError(f"--seeds {seeds}: must be >= 1")
    world = load_world(path)
    sky = SatelliteSet.from_file(world.almanac_path, world.start_utc)
    g = world.gnss
    receiver = ReceiverParams(
        seed_uere=g.seed_uere,  # type: ignore[arg-type]
        re_sigma_m=g.re_m,
        ase_sigma_m=g.ase_m,
        max_channels=g.max_channels,
    )
    t = np.asarray(template.t_s, dtype=float)
    t = t - t[0]
    lat0, lon0 = template.origin_lat_deg, template.origin_lon_deg
    alt0 = world.origin.alt_m
    e_per, n_per = metres_per_degree(lat0)
    te, tn = truth_track_m(template)
    lat = lat0 + tn / n_per
    lon = lon0 + te / e_per
    alt = np.full(t.size, alt0)
    vel = np.zeros((t.size, 3))
    if template.speed_mps is not None:
        crs = np.radians(
            np.nan_to_num(
                np.asarray(
                    template.course_deg if template.course_deg is not None else np.zeros(t.size),
                    dtype=float,
                )
            )
        )
        spd = np.nan_to_num(np.asarray(template.speed_mps, dtype=float))
        vel[:, 0], vel[:, 1] = spd * np.sin(crs), spd * np.cos(crs)
    effects = world.effect_objects()
    gps_effects = [
        e for e in effects if isinstance(getattr(e, "name", None), str) and e.name in _GPS
    ]
    out = []
    for i in range(seeds):
        rng = np.random.default_rng(base_seed + i)
        model = GnssModel(
            sky, lat0, lon0, alt0, world.start_utc,
            fidelity=g.fidelity,  # type: ignore[arg-type]
            mask_deg=g.mask_deg, atmosphere=world.atmosphere, walls=world.walls_model(),
            receiver=receiver, rng=rng,
        )  # fmt: skip
        b = model.batch(t, lat, lon, alt, vel)
        err = np.nan_to_num(np.asarray(b.err_enu_m, dtype=float))
        s = template.with_(
            east_m=err[:, 0],
            north_m=err[:, 1],
            up_m=err[:, 2],
            valid=np.asarray(b.valid, dtype=bool),
            nsats=np.asarray(b.n_used),
        )
        s = apply_effects(s, [*gps_effects, *extra_effects], rng)
        s = Quantization(decimals=int(g.nmea_decimals)).apply(s, rng)
        out.append(s)
        if progress:
            progress(i + 1)
    return out


_GPS = (
    "gauss_markov",
    "random_walk",
    "bias",
    "jumps",
    "outages",
    "latency",
    "multipath_zone",
    "quantization",
)
