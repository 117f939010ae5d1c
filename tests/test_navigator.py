"""The paper's waypoint state machine and the compass heading conventions."""

from __future__ import annotations

import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from x6wd.core.config import NavigationConfig
from x6wd.core.records import NavState
from x6wd.nav import geo
from x6wd.nav.navigator import (
    NavigationError,
    Navigator,
    cmps_to_paper_deg,
    magnetic_to_true,
)

CFG = NavigationConfig.paper(delta_phi_deg=10.0, delta_x_m=3.0, delta_y_m=2.0)
ORIGIN = (51.7, 30.0)


def nav_with(waypoints: list[tuple[float, float]], cfg: NavigationConfig = CFG) -> Navigator:
    nav = Navigator(cfg, declination_deg=0.0)
    nav.set_waypoints(waypoints)
    return nav


def offset(x_m: float, y_m: float) -> tuple[float, float]:
    """(lat, lon) of a point x_m, y_m from ORIGIN in the two-radius plane."""
    x0, y0 = geo.latlon_to_xy(*ORIGIN)
    lat, lon = geo.xy_to_latlon(x0 + x_m, y0 + y_m)
    return float(lat), float(lon)


def test_cmps_bearing_maps_to_the_paper_convention() -> None:
    assert cmps_to_paper_deg(0.0) == 0.0
    assert cmps_to_paper_deg(90.0) == 90.0
    assert cmps_to_paper_deg(180.0) == 180.0  # the range is (-180, 180]
    assert cmps_to_paper_deg(180.1) == pytest.approx(-179.9)
    assert cmps_to_paper_deg(270.0) == -90.0
    assert cmps_to_paper_deg(359.9) == pytest.approx(-0.1)
    for bad in (-0.1, 360.0, math.nan):
        with pytest.raises(NavigationError, match="compass bearing"):
            cmps_to_paper_deg(bad)


def test_declination_is_east_positive() -> None:
    assert magnetic_to_true(10.0, 5.0) == 15.0  # east declination: true is clockwise of mag
    assert magnetic_to_true(10.0, -12.0) == -2.0
    assert magnetic_to_true(178.0, 5.0) == -177.0  # wrapped into (-180, 180]
    assert magnetic_to_true(-178.0, -2.0) == 180.0
    nav = Navigator(CFG, declination_deg=7.0)
    assert nav.heading_from_compass(355.0) == pytest.approx(math.radians(2.0))
    assert nav.heading_from_compass(90.0) == pytest.approx(math.radians(97.0))


@pytest.mark.parametrize(
    ("heading_deg", "expected"),
    [
        (0.0, NavState.STRAIGHT),  # target due north, heading north
        (9.9, NavState.STRAIGHT),  # within Δφ = 10
        (-9.9, NavState.STRAIGHT),
        (-20.0, NavState.TURN_RIGHT),  # heading west of north: Θ = +20 -> clockwise
        (20.0, NavState.TURN_LEFT),
        (179.0, NavState.TURN_LEFT),  # Θ = -179
        (-179.0, NavState.TURN_RIGHT),  # Θ = +179
    ],
)
def test_turn_decisions(heading_deg: float, expected: NavState) -> None:
    nav = nav_with([offset(0.0, 100.0)])
    x, y = nav.to_xy(*ORIGIN)
    assert nav.step(x, y, math.radians(heading_deg)) == expected
    assert nav.last is not None
    assert nav.last.phi_i_rad == pytest.approx(0.0, abs=1e-9)
    assert nav.last.distance_m == pytest.approx(100.0, rel=1e-6)


def test_turn_decision_across_the_dateline_of_angles() -> None:
    # Target to the south-west (φi ≈ -135°), heading south-east-ish (+170°): Θ = -305 -> +55:
    # turning right (through south) is the short way.
    nav = nav_with([offset(-100.0, -100.0)])
    x, y = nav.to_xy(*ORIGIN)
    assert nav.step(x, y, math.radians(170.0)) == NavState.TURN_RIGHT
    assert nav.last is not None and nav.last.theta_rad is not None
    assert math.degrees(nav.last.theta_rad) == pytest.approx(55.0, abs=1e-6)


def test_arrival_window_is_per_axis_and_inclusive() -> None:
    nav = nav_with([offset(0.0, 0.0), offset(50.0, 0.0)])
    x0, y0 = geo.latlon_to_xy(*ORIGIN)
    # |dx| = 3.5 > Δx = 3 although the distance would fit a 4 m circle: not arrived
    assert nav.step(float(x0) - 3.5, float(y0), 0.0) != NavState.ARRIVED
    # |dy| = 2.5 > Δy = 2: not arrived
    assert nav.step(float(x0), float(y0) - 2.5, 0.0) != NavState.ARRIVED
    assert nav.index == 0
    # inside both (|dx| = 2.9, |dy| = 1.9): arrived, on to the next waypoint
    assert nav.step(float(x0) - 2.9, float(y0) + 1.9, 0.0) == NavState.ARRIVED
    assert nav.index == 1
    # the next decision is about waypoint 1, 50 m east: turn right from north
    assert nav.step(float(x0) - 2.9, float(y0) + 1.9, 0.0) == NavState.TURN_RIGHT
    assert nav.last is not None and nav.last.waypoint_index == 1


def test_mission_sequence_ends_in_mission_done() -> None:
    wps = [offset(0.0, 20.0), offset(20.0, 20.0), offset(20.0, 0.0)]
    nav = nav_with(wps)
    states = []
    for lat, lon in wps:
        x, y = nav.to_xy(lat, lon)
        states.append(nav.step(x, y, 0.0))
    assert states == [NavState.ARRIVED, NavState.ARRIVED, NavState.MISSION_DONE]
    assert nav.done
    assert nav.step(0.0, 0.0, 0.0) == NavState.MISSION_DONE  # stays done
    nav.restart()
    assert nav.index == 0 and not nav.done


def test_local_tangent_plane_projection_by_config() -> None:
    cfg = NavigationConfig.paper(projection="local_tangent_plane", delta_x_m=3.0, delta_y_m=3.0)
    nav = nav_with([ORIGIN, (51.7, 30.001)], cfg)
    assert nav.projection.name == "local_tangent_plane"
    assert nav.to_xy(*ORIGIN) == (0.0, 0.0)
    # 0.001 deg of longitude is ~69 m east here in true metres (two-radius says ~111 m)
    nav.step(0.0, 0.0, 0.0)
    assert nav.last is not None and nav.last.state == NavState.ARRIVED
    nav.step(0.0, 0.0, 0.0)
    assert nav.last is not None
    assert nav.last.distance_m == pytest.approx(69.1, abs=0.2)


def test_bad_missions_and_inputs_are_rejected() -> None:
    nav = Navigator(CFG)
    with pytest.raises(NavigationError, match="no mission"):
        nav.step(0.0, 0.0, 0.0)
    with pytest.raises(NavigationError, match="at least one"):
        nav.set_waypoints([])
    with pytest.raises(NavigationError, match="waypoint 1: latitude"):
        nav.set_waypoints([ORIGIN, (91.0, 0.0)])
    with pytest.raises(NavigationError, match="waypoint 0: longitude"):
        nav.set_waypoints([(0.0, math.inf)])
    with pytest.raises(NavigationError, match=r"waypoint 0: expected \(lat, lon\)"):
        nav.set_waypoints([(1.0, 2.0, 3.0)])  # type: ignore[list-item]
    nav.set_waypoints([ORIGIN])
    with pytest.raises(NavigationError, match="heading"):
        nav.step(0.0, 0.0, -math.pi)  # -π is outside (-π, π]
    with pytest.raises(NavigationError, match="position"):
        nav.step(math.nan, 0.0, 0.0)
    with pytest.raises(NavigationError, match="declination"):
        Navigator(CFG, declination_deg=200.0)


@settings(max_examples=200, deadline=None)
@given(
    dx=st.floats(-500, 500),
    dy=st.floats(-500, 500),
    heading_deg=st.floats(-179.999, 180.0),
)
def test_decision_matches_the_paper_rules(dx: float, dy: float, heading_deg: float) -> None:
    nav = nav_with([offset(dx, dy)])
    x0, y0 = geo.latlon_to_xy(*ORIGIN)
    state = nav.step(float(x0), float(y0), math.radians(heading_deg))
    assert nav.last is not None
    ddx, ddy = nav.last.dx_m, nav.last.dy_m
    if abs(ddx) <= CFG.delta_x_m and abs(ddy) <= CFG.delta_y_m:
        assert state == NavState.MISSION_DONE
        return
    phi_i = math.copysign(1.0, 1.0 if ddx >= 0 else -1.0) * math.acos(ddy / math.hypot(ddx, ddy))
    theta = math.degrees(phi_i) - heading_deg
    theta = (theta + 180.0) % 360.0 - 180.0
    if abs(abs(theta) - CFG.delta_phi_deg) < 1e-6 or abs(abs(theta) - 180) < 1e-6:
        return  # on a boundary: rounding decides
    if abs(theta) <= CFG.delta_phi_deg:
        assert state == NavState.STRAIGHT
    else:
        assert state == (NavState.TURN_RIGHT if theta > 0 else NavState.TURN_LEFT)
