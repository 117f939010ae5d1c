"""Ray tracing alone: ``Walls.trace`` on the simulator benchmark's hour among 10 buildings.

The rays are the ones ``GnssModel`` traces in ``bench_sim``'s anchor run (a 60 m circle at
1.5 m/s inside a ring of 10 closed 12 x 8 m buildings, 10 m high, 90 m out; 1 h at 1 Hz, all
satellites above the horizon, each with the loss budget of its own C/N0 margin). Figures:
the whole hour in one call (open loop), and one epoch per call (closed loop, ``step()``).
Budget: the walls' share of the 0.36 s the issue allows the whole open-loop pipeline.
Run: ``python -m bench.bench_buildings [--quick]``.
"""

from __future__ import annotations

import math
import time
from datetime import UTC, datetime
from typing import Any

import numpy as np

from bench._common import Row, cli, print_table
from sim_backend.buildings import TraceResult, Walls, building
from sim_backend.geodesy import enu_to_lla
from sim_backend.gnss import GnssModel
from sim_backend.sky import SatelliteSet, read_yuma
from sim_backend.world import DEFAULT_ALMANAC

START = datetime(2020, 1, 1, 12, 0, tzinfo=UTC)
ORIGIN = (51.7520, -1.2577, 60.0)
BUDGET_MS = 100.0


def _scene(n: int = 10) -> Walls:
    walls = []
    for i in range(n):
        a = 2 * math.pi * i / n
        cx, cy = 90 * math.cos(a), 90 * math.sin(a)
        walls += building(cx - 6, cy - 4, cx + 6, cy + 4, 10.0)
    return Walls(walls)


class _Recorder:
    """Walls stand-in that keeps the arguments the model traces with."""

    def __init__(self, walls: Walls) -> None:
        self.walls = walls
        self.calls: list[tuple[Any, ...]] = []

    def trace(
        self,
        rx_enu_m: Any,
        az_deg: Any,
        el_deg: Any,
        max_reflections: int = 16,
        max_loss_db: Any = None,
    ) -> TraceResult:
        args = (rx_enu_m, az_deg, el_deg, max_loss_db)
        self.calls.append(tuple(np.array(a) for a in args))
        return self.walls.trace(rx_enu_m, az_deg, el_deg, max_reflections, max_loss_db)


def _rays(n_epochs: int, walls: Walls) -> tuple[np.ndarray, ...]:
    """(rx (E, 3), az (E, S), el (E, S), max_loss_db (E, S)) as the model passes them."""
    t = np.arange(n_epochs, dtype=float)
    ang = 1.5 / 60.0 * t
    enu = np.column_stack([60 * np.sin(ang), 60 * np.cos(ang), np.full(n_epochs, 0.34)])
    vel = np.column_stack([1.5 * np.cos(ang), -1.5 * np.sin(ang), np.zeros(n_epochs)])
    lat, lon, alt = enu_to_lla(enu, *ORIGIN)
    sky = SatelliteSet.from_almanac(read_yuma(DEFAULT_ALMANAC, reference=START))
    rec = _Recorder(walls)
    model = GnssModel(sky, *ORIGIN, START, walls=rec, rng=np.random.default_rng(0))
    model.batch(t, np.asarray(lat), np.asarray(lon), np.asarray(alt), vel)
    return rec.calls[0]


def _best(fn: Any, repeat: int) -> float:
    best = math.inf
    for _ in range(repeat):
        a = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - a)
    return best


def run(quick: bool = False) -> list[Row]:
    """Open-loop and per-epoch trace times; ``quick`` uses 600 epochs."""
    n_epochs = 600 if quick else 3600
    repeat = 2 if quick else 5
    walls = _scene()
    rx, az, el, loss = _rays(n_epochs, walls)
    res = walls.trace(rx, az, el, max_loss_db=loss)
    up = int((el > 0).sum())
    blocked = int(((el > 0) & ~res.los).sum())
    reflected = int((res.n_reflections > 0).sum())
    wall_s = _best(lambda: walls.trace(rx, az, el, max_loss_db=loss), repeat)
    rows = [
        Row(
            "buildings",
            f"trace {n_epochs} epochs x {az.shape[1]} sats, 40 walls",
            wall_s * 1e3,
            "ms",
            BUDGET_MS * n_epochs / 3600,
            "ms budget",
            f"{up} rays up, {blocked} blocked, {reflected} reflected",
        )
    ]
    step = max(1, n_epochs // 300)
    idx = range(0, n_epochs, step)

    def per_epoch() -> None:
        for i in idx:
            walls.trace(rx[i], az[i], el[i], max_loss_db=loss[i])

    per_s = _best(per_epoch, 2) / len(idx)
    rows.append(
        Row(
            "buildings",
            "trace one epoch per call (closed loop)",
            per_s * 1e6,
            "us/epoch",
            None,
            "",
            f"{1.0 / per_s:.0f} epochs/s",
        )
    )
    return rows


if __name__ == "__main__":
    print_table(run(quick=cli(__doc__).parse_args().quick))
