"""The simulated NEO-5 applies its default NAV5 PDOP mask (25): a solution with a larger PDOP
is no fix (outside audit 10a, finding A, the simulator's part).

In a 30 m street between 15 m buildings (the audit's ``canyon30``, seed 1) the receiver gave
4-satellite solutions with PDOP over 99 as valid fixes, 1.7-3.5 km off at 29-31 s, which
paused the robot on its geofence. A real NEO-5 reports no fix for them.
"""

from __future__ import annotations

import json
from pathlib import Path

from sim_backend.mission import run_mission
from sim_backend.world import loads_world
from x6wd.core.geodesy import great_circle_m

BUILDING_PAIRS_Y_M = [(-20.0, 10.0), (20.0, 50.0), (60.0, 90.0), (100.0, 130.0)]

CANYON = """name = "canyon30"
start_utc = "2020-01-01T12:00:00Z"
duration_s = 40
seed = 1
[origin]
lat_deg = 51.752
lon_deg = -1.2577
alt_m = 60.0
[gnss]
fidelity = "pseudorange"
mask_deg = 5.0
rate_hz = 1.0
nmea_decimals = 5
baud = 9600
[atmosphere]
env_noise_db = 1.0
[vehicle]
turn_rate_dps = 90.0
motor_tau_s = 0.25
start_heading_deg = 0.0
[compass]
declination_deg = 0.0
noise_ut = 0.05
[mission]
waypoints_enu = [[0, 100], [0, 200], [0, 0]]
""" + "".join(
    f"[[buildings]]\nx0_m = {x0}\ny0_m = {y0}\nx1_m = {x0 + 15.0}\ny1_m = {y1}\nheight_m = 15\n"
    for y0, y1 in BUILDING_PAIRS_Y_M
    for x0 in (15.0, -30.0)
)


def test_no_valid_fix_beyond_the_pdop_mask_in_a_street_canyon(tmp_path: Path) -> None:
    world = loads_world(CANYON, base_dir=tmp_path)
    run_mission(world, tmp_path)
    fixes = [
        r["data"]
        for r in map(json.loads, (tmp_path / "recording.jsonl").open(encoding="utf-8"))
        if r["type"] == "fix"
    ]
    valid = [f for f in fixes if f["valid"] and f["lat_deg"] is not None]
    assert len(valid) > 20  # premise: the street still has fixes
    # HDOP <= PDOP <= 25 for every solution now (a fix's PDOP may be the GSA of the epoch
    # before, a no-fix one, so the fix's own HDOP is what is checked)
    assert all(f["hdop"] is not None and f["hdop"] <= 25.0 for f in valid), [
        (f["t_s"], f["hdop"]) for f in valid if f["hdop"] is None or f["hdop"] > 25.0
    ]
    # the robot stays within about 100 m of its start in 40 s; every fix near it
    far = [f for f in valid if great_circle_m(51.752, -1.2577, f["lat_deg"], f["lon_deg"]) > 300]
    assert not far, far
