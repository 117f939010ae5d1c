"""Simulated odometry calibration runs with known truth (docs/odometry.md, "Calibrating").

The simulated vehicle (:mod:`sim_backend.vehicle`) and its wheel encoders
(:mod:`sim_backend.odometry`) drive scripted legs of (left %, right %, seconds); the reference
fixes are the true positions plus :data:`REF_SIGMA_M` of noise (an RTK receiver). What
``tools/calibration-runs`` writes for trying ``x6wd calibrate odometry`` without a robot, and
what ``tests/test_calibrate_odometry.py`` checks the estimator on: the same seed gives the same
records.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from sim_backend.odometry import EncoderParams, EncoderSim
from sim_backend.vehicle import Vehicle, VehicleParams
from x6wd.core.recorder import Recorder
from x6wd.core.records import GpsFix, WheelOdometry
from x6wd.nav.geo import LocalTangentPlane

ORIGIN = (51.7, 5.0)
"""Latitude and longitude (degrees) of the runs' local plane."""
TRUE = EncoderParams(
    left_diameter_m=0.1212,  # +1 % of the nominal 120 mm
    right_diameter_m=0.1188,  # -1 %
    effective_track_m=0.37,  # 1.5x the geometric 0.245 m
    k_left_m=2e-4,
    k_right_m=3e-4,
)
"""The simulated wheels: what a calibration should find."""
REF_SIGMA_M = 0.02
DT_S = 0.025  # physics step; odometry every 2 steps (20 Hz), a fix every 8 (5 Hz)
STOP = (0.0, 0.0, 4.0)  # the motors' exponential stop creeps for ~2 s
STRAIGHT = [STOP] + [(50.0, 50.0, 10.0), STOP, (-50.0, -50.0, 10.0), STOP] * 6  # 12 x 19 m
CIRCLE = [STOP] + [(60.0, 10.0, 32.0), STOP] * 4  # 4 x 2 laps of radius ~3.5 m, clockwise
CIRCLE_TOUR = [STOP] + [(60.0, 10.0, 32.0), STOP] * 6
"""What ``tools/calibration-runs`` drives: the 6 passes ``x6wd calibrate`` asks for (4 give
standard errors it calls rough); the tests keep :data:`CIRCLE`'s 4, which are quicker."""

Script = Sequence[tuple[float, float, float]]


def simulate(
    script: Script, seed: int, params: EncoderParams = TRUE
) -> tuple[list[WheelOdometry], list[GpsFix]]:
    """Drive (left %, right %, seconds) legs; the odometry records and reference fixes."""
    rng = np.random.default_rng(seed)
    v = Vehicle(VehicleParams(), heading_deg=float(rng.uniform(0, 360)))
    enc = EncoderSim(params, rng=rng, start=v.state)
    plane = LocalTangentPlane(*ORIGIN)
    odo: list[WheelOdometry] = []
    fixes: list[GpsFix] = []
    k = 0
    for left, right, secs in script:
        v.command(left, right)
        for _ in range(round(secs / DT_S)):
            s = v.step(DT_S)
            enc.step(DT_S, s)
            k += 1
            if k % 2 == 0:
                odo.append(WheelOdometry(s.t_s, *enc.counts, seq=(k // 2) % 65536))
            if k % 8 == 0:
                e, n = s.east_m + rng.normal(0, REF_SIGMA_M), s.north_m + rng.normal(0, REF_SIGMA_M)
                lat, lon = plane.to_latlon(e, n)
                fixes.append(
                    GpsFix(
                        s.t_s, lat_deg=float(lat), lon_deg=float(lon), quality=4, valid=True, mode=3
                    )
                )
    return odo, fixes


def write(path: Path, odo: list[WheelOdometry], fixes: list[GpsFix]) -> Path:
    """Write the records as one recording, in time order, as the daemon's recorder does."""
    records: list[WheelOdometry | GpsFix] = [*odo, *fixes]
    with Recorder(path) as rec:
        for r in sorted(records, key=lambda r: r.t_s):
            if isinstance(r, WheelOdometry):
                rec.record_odometry(r)
            else:
                rec.record_fix(r)
    return path


def write_runs(out_dir: Path) -> tuple[Path, Path]:
    """``out_dir``/straight.jsonl (:data:`STRAIGHT`, seed 1) and circle.jsonl
    (:data:`CIRCLE_TOUR`, seed 2): the two recordings docs/odometry.md asks for."""
    out_dir.mkdir(parents=True, exist_ok=True)
    straight = write(out_dir / "straight.jsonl", *simulate(STRAIGHT, 1))
    circle = write(out_dir / "circle.jsonl", *simulate(CIRCLE_TOUR, 2))
    return straight, circle
