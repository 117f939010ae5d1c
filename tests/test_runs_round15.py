"""The sim summary's straight-line length (``sim_backend.runs.straight_length_m``) for a start
far from the scenario's origin (an outside audit, round 15: the default square beside a start
at (30000, -20000) m ENU printed "straight line 174.8 m" for its 95 m route, path ratio 0.55).
The start was placed at ENU up = 0, the origin's flat plane, 102 m above the ground there,
while the waypoints sit at the origin's altitude: the first leg counted that drop."""

from __future__ import annotations

import pytest

from sim_backend.runs import straight_length_m
from sim_backend.world import World, loads_world

SQUARE_M = ((0.0, -25.0), (25.0, -25.0), (25.0, 0.0), (5.0, 0.0))  # default.toml's, from 0,0
ROUTE_M = 25.0 + 25.0 + 25.0 + 20.0  # start -> each waypoint in turn


def _world(east_m: float, north_m: float) -> World:
    """Oxford's origin, the vehicle starting at (east_m, north_m) ENU and the square beside it."""
    wps = ", ".join(f"[{east_m + e}, {north_m + n}]" for e, n in SQUARE_M)
    return loads_world(
        'name = "far"\nstart_utc = "2020-01-01T12:00:00Z"\nduration_s = 5.0\n'
        "[origin]\nlat_deg = 51.752\nlon_deg = -1.2577\nalt_m = 60.0\n"
        f"[vehicle]\nstart_east_m = {east_m}\nstart_north_m = {north_m}\n"
        f"[mission]\nwaypoints_enu = [{wps}]\n"
    )


@pytest.mark.parametrize(
    ("east_m", "north_m"), [(0.0, 0.0), (3000.0, -3000.0), (30000.0, -20000.0), (-60000.0, 0.0)]
)
def test_a_far_start_measures_its_route_on_the_ground(east_m: float, north_m: float) -> None:
    # the route is 95 m wherever it lies (the plane's own distortion at 60 km is ~1e-5)
    got = straight_length_m(_world(east_m, north_m))
    assert got == pytest.approx(ROUTE_M, abs=0.05), (east_m, north_m, got)


def test_one_waypoint_25_m_from_a_start_36_km_out_is_25_m() -> None:
    # 25 m north of the start: the 102 m drop made it 104.8 m
    w = loads_world(
        'name = "far"\nstart_utc = "2020-01-01T12:00:00Z"\nduration_s = 5.0\n'
        "[origin]\nlat_deg = 51.752\nlon_deg = -1.2577\nalt_m = 60.0\n"
        "[vehicle]\nstart_east_m = 30000.0\nstart_north_m = -20000.0\n"
        "[mission]\nwaypoints_enu = [[30000.0, -19975.0]]\n"
    )
    assert straight_length_m(w) == pytest.approx(25.0, abs=0.01)
