"""pivot_arc: a pivot keeps its direction (``x6wd.nav.navigator.PIVOT_KEEP_DEG``).

An outside audit (round 15) ran a 5 m hairpin (``[[0,5],[0,0],[0,5],[0,0]]``, seed 3): at
30.65-30.85 s the motors went 40/-40, -40/40, 40/-40 ... six times in 0.2 s, twice inside
one 50 ms tick, as the heading error α to the lookahead point swung +179°, -180°, +180°,
-179°: the pivot's direction came from α's sign at each decision. Now a pivot under way keeps
its direction while α, on the other side, is still beyond PIVOT_KEEP_DEG. The first test and
the mission on seed 3 failed before; the others guard what must not change."""

from __future__ import annotations

import itertools
import json
import math
from pathlib import Path

import pytest

from sim_backend.mission import run_mission
from sim_backend.world import loads_world
from tests.test_steering import ARC, _nav, _step
from x6wd.core.records import NavState
from x6wd.nav.navigator import PIVOT_KEEP_DEG, Navigator

RIGHT, LEFT, STRAIGHT = NavState.TURN_RIGHT, NavState.TURN_LEFT, NavState.STRAIGHT


def _alpha_deg(nav: Navigator) -> float:
    """The last decision's heading error to the steering target (deg)."""
    last = nav.last
    assert last is not None and last.steer_alpha_rad is not None
    return math.degrees(last.steer_alpha_rad)


def test_a_pivot_at_a_reversal_keeps_its_direction_as_alpha_swings_about_180() -> None:
    # the waypoint 50 m north, the robot facing south: the lookahead point is straight
    # behind, and 0.1 m east or west of the line puts α at about +179.6° or -179.6°
    nav, ltp = _nav(ARC, (51.7, 30.0), [(0.0, 50.0)])
    assert _step(nav, ltp, 0.0, 0.0, 0.0) == STRAIGHT  # sets the leg: (0, 0) -> north
    states, alphas = [], []
    for k in range(8):
        east = 0.1 if k % 2 == 0 else -0.1
        states.append(_step(nav, ltp, east, 10.0, 180.0))
        alphas.append(_alpha_deg(nav))
    assert [a > 0 for a in alphas] == [k % 2 == 0 for k in range(8)], alphas  # it swings
    assert all(abs(a) > 179.0 for a in alphas), alphas
    assert states == [RIGHT] * 8  # the direction it started in, at every decision
    assert nav.pivoting
    # on the other side but beyond PIVOT_KEEP_DEG: still the same way round
    assert _step(nav, ltp, 0.0, 10.0, PIVOT_KEEP_DEG + 1.0) == RIGHT
    assert _alpha_deg(nav) == pytest.approx(-PIVOT_KEEP_DEG - 1.0, abs=0.5)
    # the same way round, the pivot ends as before under pivot_resume_deg
    assert _step(nav, ltp, 0.0, 10.0, 9.0) == STRAIGHT and not nav.pivoting
    # a new pivot takes α's side afresh: -179.6° starts a left one
    assert _step(nav, ltp, -0.1, 10.0, 180.0) == LEFT


def test_a_target_well_on_the_other_side_is_turned_to_the_short_way() -> None:
    # the rule is for a reversal only: a target that moved 100° to the other side under way
    # (a position reset) is turned to as before, not 260° round (passes before the fix too)
    nav, ltp = _nav(ARC, (51.7, 30.0), [(0.0, 50.0)])
    _step(nav, ltp, 0.0, 0.0, 0.0)
    assert _step(nav, ltp, 0.0, 10.0, -90.0) == RIGHT  # α = +90°
    assert _step(nav, ltp, 0.0, 10.0, 100.0) == LEFT  # α = -100°
    assert _alpha_deg(nav) == pytest.approx(-100.0, abs=0.5)
    assert _step(nav, ltp, 0.0, 10.0, 90.0) == LEFT


HAIRPIN = """
name = "hairpin_180_short_5m"
start_utc = "2020-01-01T12:00:00Z"
duration_s = 206
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
declination_deg = -0.5
noise_ut = 0.05
[mission]
waypoints_enu = [[0.0, 5.0], [0.0, 0.0], [0.0, 5.0], [0.0, 0.0]]
"""


def _spin_flips(recording: Path) -> list[str]:
    """Consecutive motor commands whose two sides both change sign (a spin one way straight
    into the other, no 0/0 between)."""
    cmds = []
    for line in recording.read_text().splitlines():
        rec = json.loads(line)
        if rec["type"] == "motor":
            d = rec["data"]
            cmds.append((d["t_s"], d["left_pct"], d["right_pct"], d["reason"]))
    return [
        f"{a[0]:.2f} s {a[1]:+g}/{a[2]:+g} {a[3]} -> {b[0]:.2f} s {b[1]:+g}/{b[2]:+g} {b[3]}"
        for a, b in itertools.pairwise(cmds)
        if a[1] * b[1] < 0.0 and a[2] * b[2] < 0.0
    ]


@pytest.mark.parametrize("seed", [3, 1])
def test_the_5_m_hairpin_never_spins_straight_into_the_other_way(tmp_path: Path, seed: int) -> None:
    s = run_mission(loads_world(HAIRPIN), tmp_path, seed=seed)
    assert s.completed and s.waypoints_reached == 4
    turns = [
        json.loads(line)["data"]["reason"]
        for line in (tmp_path / "recording.jsonl").read_text().splitlines()
        if '"type":"motor"' in line
    ]
    assert "TURN_RIGHT" in turns or "TURN_LEFT" in turns  # it pivoted at the hairpins
    assert _spin_flips(tmp_path / "recording.jsonl") == []
