"""Simulator speed: simulated seconds per wall second.

Open loop (the anchor figure): one robot, 1 h at 1 Hz over a truth track (a 60 m circle at
1.5 m/s among 10 buildings), the full pseudorange model (sky, atmosphere, walls with
reflections, per-satellite error processes, least squares) through ``GnssModel.batch``, and
the NEO-5 NMEA text of every epoch (``NmeaFormatter.format_batch``). Anchor: 10,000x real
time. Then how it scales with epochs, with satellites (elevation mask) and with walls, and,
as a second figure, the closed-loop mission (real decoders, compass driver, controller,
recorder, files and plot) on the default scenario.
"""

from __future__ import annotations

import math
import tempfile
import time
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, cast

import numpy as np

from bench._common import Row, cli, print_table
from sim_backend.buildings import Walls, building
from sim_backend.geodesy import enu_to_lla
from sim_backend.gnss import GnssModel
from sim_backend.nmea_out import NmeaFormatter
from sim_backend.sky import SatelliteSet, read_yuma
from sim_backend.world import DEFAULT_ALMANAC, load_world

ROOT = Path(__file__).resolve().parent.parent
START = datetime(2020, 1, 1, 12, 0, tzinfo=UTC)
ORIGIN = (51.7520, -1.2577, 60.0)
ANCHOR_X = 10_000.0


def _buildings(n: int) -> Walls | None:
    """``n`` closed 12 x 8 m buildings, 10 m high, on a ring 90 m out (4 walls each)."""
    if n == 0:
        return None
    walls = []
    for i in range(n):
        a = 2 * math.pi * i / n
        cx, cy = 90 * math.cos(a), 90 * math.sin(a)
        walls += building(cx - 6, cy - 4, cx + 6, cy + 4, 10.0)
    return Walls(walls)


def _track(n_epochs: int, rate_hz: float = 1.0) -> tuple[np.ndarray, ...]:
    """Truth: a 60 m radius circle at 1.5 m/s (time s, lat, lon, alt, ENU velocity)."""
    t = np.arange(n_epochs) / rate_hz
    w = 1.5 / 60.0
    ang = w * t
    enu = np.column_stack([60 * np.sin(ang), 60 * np.cos(ang), np.full(n_epochs, 0.34)])
    vel = np.column_stack([1.5 * np.cos(ang), -1.5 * np.sin(ang), np.zeros(n_epochs)])
    lat, lon, alt = enu_to_lla(enu, *ORIGIN)
    return t, np.asarray(lat), np.asarray(lon), np.asarray(alt), vel


_SKY: SatelliteSet | None = None


def _sky() -> SatelliteSet:
    global _SKY
    if _SKY is None:
        _SKY = SatelliteSet.from_almanac(read_yuma(DEFAULT_ALMANAC, reference=START))
    return _SKY


def open_loop(
    n_epochs: int, n_buildings: int = 10, mask_deg: float = 5.0, repeat: int = 3
) -> tuple[float, float, float, float]:
    """Best-of-``repeat`` wall time (s) for model + NMEA; also model-only time, NMEA bytes and
    mean satellites used."""
    t, lat, lon, alt, vel = _track(n_epochs)
    walls = _buildings(n_buildings)
    best = best_model = math.inf
    nbytes = 0
    sats = 0.0
    for k in range(repeat):
        model = GnssModel(
            _sky(),
            *ORIGIN,
            START,
            fidelity="pseudorange",
            mask_deg=mask_deg,
            walls=cast(Any, walls),
            rng=np.random.default_rng(k),
        )
        fmt = NmeaFormatter()
        a = time.perf_counter()
        batch = model.batch(t, lat, lon, alt, vel)
        b = time.perf_counter()
        out = fmt.format_batch(batch)
        c = time.perf_counter()
        best = min(best, c - a)
        best_model = min(best_model, b - a)
        nbytes = sum(map(len, out))
        sats = float(np.asarray(batch.n_used).mean())
    return best, best_model, float(nbytes), sats


def closed_loop(duration_s: float) -> tuple[float, float]:
    """Wall time (s) and simulated time (s) of the default scenario's mission."""
    from sim_backend.mission import run_mission

    world = load_world(ROOT / "config" / "scenarios" / "default.toml")
    with tempfile.TemporaryDirectory() as d:
        a = time.perf_counter()
        summary = run_mission(world, d, duration_s=duration_s)
        wall = time.perf_counter() - a
    return wall, summary.sim_time_s


def run(quick: bool = False) -> list[Row]:
    """All figures; ``quick`` uses fewer epochs and repetitions."""
    rows: list[Row] = []
    repeat = 1 if quick else 2
    hour = 600 if quick else 3600
    wall, model_s, nbytes, sats = open_loop(hour, 10, repeat=repeat)
    rows.append(
        Row(
            "sim",
            f"open loop {hour} s @1 Hz, 10 buildings, + NMEA",
            hour / wall,
            "x real time",
            ANCHOR_X,
            "x target",
            f"{wall * 1e3:.0f} ms wall, {nbytes / 1e6:.2f} MB NMEA, {sats:.1f} sats used",
        )
    )
    rows.append(
        Row(
            "sim",
            "  of which GnssModel.batch",
            hour / model_s,
            "x real time",
            ANCHOR_X,
            "x target",
            f"{model_s * 1e3:.0f} ms; NMEA {(wall - model_s) * 1e3:.0f} ms",
        )
    )
    rows.append(
        Row(
            "sim",
            f"NMEA text only, {hour} epochs (format_batch)",
            (wall - model_s) * 1e3,
            "ms",
            100.0 * hour / 3600,
            "ms budget",
            f"{(wall - model_s) / hour * 1e6:.0f} us/epoch",
        )
    )
    for n in (600, 1800, 3600) if quick else (600, 1800, 3600, 7200):
        w, _m, _b, _s = open_loop(n, 10, repeat=repeat)
        rows.append(Row("sim", f"scaling: {n} epochs", n / w, "x real time", ANCHOR_X, "x target",
                        f"{w / n * 1e6:.0f} us/epoch"))  # fmt: skip
    n = 600 if quick else 1800
    for mask in (0.0, 5.0, 15.0, 30.0):
        w, _m, _b, s = open_loop(n, 10, mask_deg=mask, repeat=repeat)
        rows.append(Row("sim", f"scaling: mask {mask:.0f} deg", n / w, "x real time", ANCHOR_X,
                        "x target", f"{s:.1f} sats used"))  # fmt: skip
    for nb in (0, 1, 5, 10, 25):
        w, _m, _b, _s = open_loop(n, nb, repeat=repeat)
        rows.append(Row("sim", f"scaling: {4 * nb} walls", n / w, "x real time", ANCHOR_X,
                        "x target", f"{nb} buildings"))  # fmt: skip
    dur = 60.0 if quick else 400.0
    wall_cl, sim_cl = closed_loop(dur)
    rows.append(
        Row(
            "sim",
            "closed loop mission (default.toml)",
            sim_cl / wall_cl,
            "x real time",
            None,
            "",
            f"{sim_cl:.0f} s simulated in {wall_cl:.2f} s incl. files + plot",
        )
    )
    return rows


if __name__ == "__main__":
    cli(__doc__, quick=False).parse_args()
    print_table(run())
