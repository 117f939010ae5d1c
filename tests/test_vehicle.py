"""Six-wheel skid-steer kinematics: exact arcs, motor response, limits, terrain attitude."""

from __future__ import annotations

import math

import pytest

from sim_backend.vehicle import MAX_SPEED_MPS, Terrain, Vehicle, VehicleParams
from x6wd.core.errors import ConfigError

INSTANT = VehicleParams(motor_tau_s=0.0, max_turn_rate_dps=60.0)


def test_straight_line_at_full_drive_is_14_kmh() -> None:
    v = Vehicle(INSTANT, heading_deg=90.0)
    v.command(100, 100)
    s = v.step(10.0)
    assert s.speed_mps == pytest.approx(14 / 3.6)
    assert s.east_m == pytest.approx(10 * 14 / 3.6) and s.north_m == pytest.approx(0, abs=1e-9)
    assert s.odometer_m == pytest.approx(10 * 14 / 3.6)


def test_pivot_turn_spins_in_place_at_the_max_turn_rate() -> None:
    v = Vehicle(INSTANT)
    v.command(-100, 100)  # right forward, left back: counter-clockwise (left turn)
    s = v.step(1.5)
    assert s.heading_deg == pytest.approx(360 - 90.0)
    assert math.hypot(s.east_m, s.north_m) < 1e-12
    v.command(40, -40)
    s = v.step(1.0)
    assert s.yaw_rate_dps == pytest.approx(24.0)
    assert s.heading_deg == pytest.approx(270 + 24.0)


def test_constant_drive_follows_an_exact_circle_whatever_the_step() -> None:
    a, b = Vehicle(INSTANT), Vehicle(INSTANT)
    for v in (a, b):
        v.command(30, 70)
    a.step(6.0)
    for _ in range(600):
        b.step(0.01)
    v_mps = 0.5 * MAX_SPEED_MPS
    w = -math.radians(0.2 * 60.0)  # right side faster: counter-clockwise
    r = v_mps / w
    h = w * 6.0
    assert a.state.east_m == pytest.approx(r * (1 - math.cos(h)), abs=1e-9)
    assert a.state.north_m == pytest.approx(r * math.sin(h), abs=1e-9)
    assert b.state.east_m == pytest.approx(a.state.east_m, abs=1e-9)
    assert b.state.north_m == pytest.approx(a.state.north_m, abs=1e-9)
    assert b.state.heading_deg == pytest.approx(a.state.heading_deg, abs=1e-9)


def test_motor_response_is_first_order() -> None:
    p = VehicleParams(motor_tau_s=0.5)
    v = Vehicle(p)
    v.command(100, 100)
    s = v.step(0.5)
    assert s.left_pct == pytest.approx(100 * (1 - math.exp(-1)))
    # Distance = v_max * (t - tau (1 - e^{-t/tau})) for a step input from rest.
    assert s.north_m == pytest.approx(MAX_SPEED_MPS * (0.5 - 0.5 * (1 - math.exp(-1))), rel=1e-9)
    s = v.step(10.0)
    assert s.speed_mps == pytest.approx(MAX_SPEED_MPS, rel=1e-6)


def test_commands_are_clamped_and_bad_values_rejected() -> None:
    v = Vehicle(INSTANT)
    v.command(250, -300)
    assert v.command_pct == (100.0, -100.0)
    with pytest.raises(ValueError, match="left_pct"):
        v.command(math.nan, 0)
    with pytest.raises(ValueError, match="dt_s"):
        v.step(-1.0)
    with pytest.raises(ConfigError, match="14 km/h"):
        VehicleParams(v_max_mps=5.0)
    with pytest.raises(ConfigError, match="turn_rate"):
        VehicleParams(max_turn_rate_dps=0)
    with pytest.raises(ConfigError, match="slope"):
        Terrain(grad_east=3.0)


@pytest.mark.parametrize(
    "heading,pitch_sign,roll_sign", [(0, 1, 0), (180, -1, 0), (90, 0, 1), (270, 0, -1)]
)
def test_terrain_slope_gives_pitch_and_roll(
    heading: float, pitch_sign: int, roll_sign: int
) -> None:
    # Ground rising to the north (5.7 deg). Facing east, north is on the left: the right side
    # is lower, which is positive roll; facing west the right side is higher.
    v = Vehicle(INSTANT, heading_deg=heading, terrain=Terrain(grad_north=0.1))
    slope = math.degrees(math.atan(0.1))
    assert v.state.pitch_deg == pytest.approx(pitch_sign * slope, abs=1e-9)
    assert v.state.roll_deg == pytest.approx(roll_sign * slope, abs=1e-9)


def test_driving_uphill_climbs_and_moves_less_horizontally() -> None:
    terrain = Terrain(grad_north=0.2, up0_m=10.0)
    v = Vehicle(INSTANT, terrain=terrain)
    v.command(50, 50)
    s = v.step(4.0)
    ground = 4.0 * 0.5 * MAX_SPEED_MPS
    assert s.north_m == pytest.approx(ground * math.cos(math.atan(0.2)))
    assert s.up_m == pytest.approx(10.0 + 0.2 * s.north_m)
    assert s.odometer_m == pytest.approx(ground)


def test_runs_are_deterministic() -> None:
    def run() -> tuple[float, ...]:
        v = Vehicle(VehicleParams(motor_tau_s=0.3), terrain=Terrain(0.05, -0.02))
        for k in range(200):
            v.command(60 - (k % 7) * 10, 40 + (k % 5) * 10)
            v.step(0.05)
        s = v.state
        return (s.east_m, s.north_m, s.up_m, s.heading_deg, s.pitch_deg, s.roll_deg)

    assert run() == run()
