"""Plane coordinates: the paper's two-radius conversion, bearing φi, deviation Θ, local plane."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from x6wd.nav import geo
from x6wd.nav.geo import (
    GeoError,
    LocalTangentPlane,
    course_deviation,
    destination_bearing,
    latlon_to_xy,
    make_projection,
    xy_to_latlon,
)

# Table 2 of the paper: dispersion of latitude/longitude in degrees -> ± metres (half the
# full extent). The degrees are printed to 1e-8, i.e. ± 0.5e-8 deg of rounding, which is up to
# ± 0.5e-8 · π/180 · R / 2 = ± 2.78e-4 m at the half extent. The metre figures are printed to
# 1e-8 m and were computed from the dispersions in MINUTES (0.0133' = 0.00022167° ...), the
# unit of the NMEA data; from those they agree to the printed rounding (± 5e-9 m).
TABLE2_LAT = [  # (deg as printed, minutes, ± m)
    (0.00022167, 0.0133, 12.29657776),
    (0.00019, 0.0114, 10.5399238),
    (0.00015167, 0.0091, 8.41344794),
    (0.00001833, 0.0011, 1.01701019),
]
TABLE2_LON = [
    (0.000545, 0.0327, 30.33467063),
    (0.000065, 0.0039, 3.6178965),
    (0.0002, 0.012, 11.13198922),
    (0.00001833, 0.0011, 1.02043235),
]
DEG_ROUNDING_TOL_M = 0.5e-8 * math.pi / 180 * geo.R1_M / 2  # 2.78e-4 m
METRE_ROUNDING_TOL_M = 0.5e-8 + 1e-12


@pytest.mark.parametrize(("deg", "minutes", "half_m"), TABLE2_LAT)
def test_table2_latitude_dispersions(deg: float, minutes: float, half_m: float) -> None:
    y0 = latlon_to_xy(51.7, 30.0)[1]
    y_deg = latlon_to_xy(51.7 + deg, 30.0)[1]
    y_min = latlon_to_xy(51.7 + minutes / 60, 30.0)[1]
    # differences at 51.7 deg lose ~1e-9 m to the absolute y of 5.7e6 m
    assert (y_deg - y0) / 2 == pytest.approx(half_m, abs=DEG_ROUNDING_TOL_M + 1e-8)
    assert (y_min - y0) / 2 == pytest.approx(half_m, abs=METRE_ROUNDING_TOL_M + 2e-9)
    # x does not move with latitude in the two-radius conversion
    assert latlon_to_xy(51.7 + deg, 30.0)[0] == latlon_to_xy(51.7, 30.0)[0]


@pytest.mark.parametrize(("deg", "minutes", "half_m"), TABLE2_LON)
def test_table2_longitude_dispersions(deg: float, minutes: float, half_m: float) -> None:
    # Absolute from longitude 0 so nothing cancels: x = Λ·R1 exactly, no cos Φ factor.
    x_deg = latlon_to_xy(51.7, deg)[0]
    x_min = latlon_to_xy(51.7, minutes / 60)[0]
    assert x_deg / 2 == pytest.approx(half_m, abs=DEG_ROUNDING_TOL_M)
    assert x_min / 2 == pytest.approx(half_m, abs=METRE_ROUNDING_TOL_M)


def test_two_radius_constants_and_axes() -> None:
    x, y = latlon_to_xy(1.0, 1.0)
    assert x == pytest.approx(math.radians(1) * 6378160.0, rel=1e-15)
    assert y == pytest.approx(math.radians(1) * 6356770.0, rel=1e-15)
    # the same longitude step gives the same x at any latitude (the paper's stretch)
    assert latlon_to_xy(0.0, 0.001)[0] == latlon_to_xy(60.0, 0.001)[0]
    # east and north are positive, west and south negative
    xw, ys = latlon_to_xy(-10.0, -20.0)
    assert xw < 0 and ys < 0


@settings(max_examples=200, deadline=None)
@given(lat=st.floats(-90, 90), lon=st.floats(-180, 180))
def test_two_radius_round_trip(lat: float, lon: float) -> None:
    x, y = latlon_to_xy(lat, lon)
    lat2, lon2 = xy_to_latlon(x, y)
    assert lat2 == pytest.approx(lat, abs=1e-12)
    assert lon2 == pytest.approx(lon, abs=1e-12)


def test_arrays_are_accepted() -> None:
    lat = np.array([51.7, 51.8, -3.0])
    lon = np.array([30.0, -0.5, 179.9])
    x, y = latlon_to_xy(lat, lon)
    assert isinstance(x, np.ndarray) and isinstance(y, np.ndarray) and x.shape == (3,)
    for i in range(3):
        assert (x[i], y[i]) == latlon_to_xy(float(lat[i]), float(lon[i]))
    phi = destination_bearing(0.0, 0.0, np.array([1.0, -1.0]), np.array([0.0, 0.0]))
    assert np.allclose(phi, [math.pi / 2, -math.pi / 2])


@pytest.mark.parametrize(
    ("lat", "lon", "what"),
    [(90.5, 0.0, "latitude"), (0.0, -181.0, "longitude"), (math.nan, 0.0, "finite")],
)
def test_bad_coordinates_are_rejected(lat: float, lon: float, what: str) -> None:
    with pytest.raises(GeoError, match=what):
        latlon_to_xy(lat, lon)


# Bearings: clockwise from north, east positive, west negative, south +π (sign(0) = +1).
@pytest.mark.parametrize(
    ("dx", "dy", "expected"),
    [
        (0.0, 1.0, 0.0),
        (1.0, 1.0, math.pi / 4),
        (1.0, 0.0, math.pi / 2),
        (1.0, -1.0, 3 * math.pi / 4),
        (0.0, -1.0, math.pi),
        (-1.0, -1.0, -3 * math.pi / 4),
        (-1.0, 0.0, -math.pi / 2),
        (-1.0, 1.0, -math.pi / 4),
    ],
)
def test_destination_bearing_quadrants(dx: float, dy: float, expected: float) -> None:
    xc, yc = 3339596.77, 5735937.48  # somewhere at 51.7 N, 30 E
    phi = destination_bearing(xc, yc, xc + dx, yc + dy)
    assert phi == pytest.approx(expected, abs=1e-9)


def test_destination_bearing_matches_the_paper_formula() -> None:
    rng = np.random.default_rng(5)
    dx, dy = rng.normal(0, 50, (2, 500))
    phi = destination_bearing(0.0, 0.0, dx, dy)
    paper = np.where(dx >= 0, 1.0, -1.0) * np.arccos(dy / np.sqrt(dx**2 + dy**2))
    assert np.allclose(phi, paper, rtol=0, atol=1e-12)
    assert np.all((phi > -math.pi) & (phi <= math.pi))


def test_destination_bearing_stays_in_half_open_range() -> None:
    # A negative dx too small to move the arccos gives exactly -π, which must become +π.
    assert destination_bearing(0.0, 0.0, -1e-300, -1.0) == math.pi


def test_destination_bearing_of_coincident_points_is_an_error() -> None:
    with pytest.raises(GeoError, match="coincide"):
        destination_bearing(1.0, 2.0, 1.0, 2.0)


@pytest.mark.parametrize(
    ("phi_i", "phi_c", "expected"),
    [
        (0.5, 0.2, 0.3),  # destination clockwise of the heading: turn right
        (0.2, 0.5, -0.3),
        (3.0, -3.0, -(2 * math.pi - 6.0)),  # Θ = 6 > π -> −(2π − Θ)
        (-3.0, 3.0, 2 * math.pi - 6.0),  # Θ = −6 <= −π -> 2π + Θ
        (math.pi, 0.0, math.pi),  # exactly π stays π
        (0.0, math.pi, math.pi),  # Θ = −π is not in range: 2π + Θ = π
        (-math.pi / 2, math.pi / 2, math.pi),
    ],
)
def test_course_deviation_wraps_like_the_paper(phi_i: float, phi_c: float, expected: float) -> None:
    assert course_deviation(phi_i, phi_c) == pytest.approx(expected, abs=1e-15)


@settings(max_examples=300, deadline=None)
@given(
    a=st.floats(-math.pi, math.pi, exclude_min=True),
    b=st.floats(-math.pi, math.pi, exclude_min=True),
)
def test_course_deviation_is_the_paper_formula_in_range(a: float, b: float) -> None:
    theta = a - b
    if theta > math.pi:
        theta = -(2 * math.pi - theta)
    if theta <= -math.pi:
        theta = 2 * math.pi + theta
    assert course_deviation(a, b) == theta
    assert -math.pi < course_deviation(a, b) <= math.pi


@settings(max_examples=200, deadline=None)
@given(a=st.floats(-1e4, 1e4), b=st.floats(-1e4, 1e4))
def test_course_deviation_wraps_any_finite_angle(a: float, b: float) -> None:
    theta = course_deviation(a, b)
    assert -math.pi < theta <= math.pi
    # same direction as a − b: the difference is a whole number of turns
    turns = (a - b - theta) / (2 * math.pi)
    assert turns == pytest.approx(round(turns), abs=1e-9)


def test_wrap_deg() -> None:
    assert geo.wrap_deg(180.0) == 180.0
    assert geo.wrap_deg(-180.0) == 180.0
    assert geo.wrap_deg(190.0) == -170.0
    assert geo.wrap_deg(-540.0) == 180.0
    assert geo.wrap_deg(359.9) == pytest.approx(-0.1)


def test_local_tangent_plane_scales_east_by_cos_origin_latitude() -> None:
    ltp = LocalTangentPlane(51.7, 30.0)
    assert ltp.to_xy(51.7, 30.0) == (0.0, 0.0)
    x_east, y_east = ltp.to_xy(51.7, 30.001)
    _, y_north = ltp.to_xy(51.701, 30.0)
    assert y_east == 0.0
    # on the equator one degree east and one degree north differ only by the ellipsoid
    x_eq, _ = LocalTangentPlane(0.0, 30.0).to_xy(0.0, 30.001)
    assert x_east == pytest.approx(x_eq * math.cos(math.radians(51.7)), rel=5e-3)
    assert x_east / y_north == pytest.approx(math.cos(math.radians(51.7)), rel=5e-3)


def test_local_tangent_plane_distance_agrees_with_the_ellipsoid() -> None:
    # Reference: WGS-84 geodetic -> ECEF -> local ENU, an independent exact route.
    a, e2 = 6378137.0, 6.69437999014e-3

    def ecef(lat_deg: float, lon_deg: float) -> np.ndarray:
        p, lam = math.radians(lat_deg), math.radians(lon_deg)
        n = a / math.sqrt(1 - e2 * math.sin(p) ** 2)
        return np.array(
            [
                n * math.cos(p) * math.cos(lam),
                n * math.cos(p) * math.sin(lam),
                n * (1 - e2) * math.sin(p),
            ]
        )

    lat0, lon0 = 51.7, 30.0
    p0, l0 = math.radians(lat0), math.radians(lon0)
    east = np.array([-math.sin(l0), math.cos(l0), 0.0])
    north = np.array([-math.sin(p0) * math.cos(l0), -math.sin(p0) * math.sin(l0), math.cos(p0)])
    ltp = LocalTangentPlane(lat0, lon0)
    for dlat, dlon in [(0.0, 0.0015), (0.0009, 0.0), (-0.0006, 0.001), (0.004, -0.006)]:
        d = ecef(lat0 + dlat, lon0 + dlon) - ecef(lat0, lon0)
        x, y = ltp.to_xy(lat0 + dlat, lon0 + dlon)
        dist = math.hypot(float(d @ east), float(d @ north))
        # within 1e-4 of the distance (0.2 % off with the paper radii; two-radius is 61 % long)
        assert x == pytest.approx(float(d @ east), abs=1e-4 * dist + 1e-3)
        assert y == pytest.approx(float(d @ north), abs=1e-4 * dist + 1e-3)
    x2r = latlon_to_xy(lat0, lon0 + 0.0015)[0] - latlon_to_xy(lat0, lon0)[0]
    x_ltp = ltp.to_xy(lat0, lon0 + 0.0015)[0]
    assert x2r / x_ltp == pytest.approx(1 / math.cos(p0), rel=5e-3)  # the paper's stretch


@settings(max_examples=200, deadline=None)
@given(
    lat0=st.floats(-80, 80),
    lon0=st.floats(-180, 180),
    dlat=st.floats(-0.05, 0.05),
    dlon=st.floats(-0.05, 0.05),
)
def test_local_tangent_plane_round_trip(lat0: float, lon0: float, dlat: float, dlon: float) -> None:
    ltp = LocalTangentPlane(lat0, lon0)
    lat = lat0 + dlat
    lon = float(geo.wrap_deg(lon0 + dlon))
    x, y = ltp.to_xy(lat, lon)
    assert math.hypot(x, y) < 20_000  # crossing ±180° stays local
    lat2, lon2 = ltp.to_latlon(x, y)
    assert lat2 == pytest.approx(lat, abs=1e-9)
    assert float(geo.wrap_deg(lon2 - lon)) == pytest.approx(0.0, abs=1e-9)


_POLES = st.sampled_from([90.0, -90.0, 89.99999999999999, -89.99999999999999])
_DATELINE = st.sampled_from([180.0, -180.0, 179.99999999999997, -179.99999999999997, 0.0, -0.0])


@settings(max_examples=400, deadline=None)
@given(
    # origins up to the constructor's limit (|lat0| < 89.9), where the round trip's rounding
    # past a pole is largest
    lat0=st.floats(-89.899, 89.899) | st.sampled_from([89.899, -89.899, 45.0, 0.0]),
    lon0=st.floats(-180, 180) | _DATELINE,
    lat=st.floats(-90, 90) | _POLES,
    lon=st.floats(-180, 180) | _DATELINE,
)
@example(lat0=-89.89, lon0=10.0, lat=90.0, lon=180.0)  # came back as 90.00000000000001
@example(lat0=89.89, lon0=-170.0, lat=-90.0, lon=-180.0)
def test_local_tangent_plane_round_trip_over_the_whole_globe(
    lat0: float, lon0: float, lat: float, lon: float
) -> None:
    ltp = LocalTangentPlane(lat0, lon0)
    for scalar in (True, False):
        if scalar:
            lat2, lon2 = (float(v) for v in ltp.to_latlon(*ltp.to_xy(lat, lon)))
        else:
            la, lo = ltp.to_latlon(*ltp.to_xy(np.array([lat, lat0]), np.array([lon, lon0])))
            lat2, lon2 = float(np.asarray(la)[0]), float(np.asarray(lo)[0])
        # On the globe's ranges, poles included; longitude wrapped to (-180, 180].
        assert -90.0 <= lat2 <= 90.0 and -180.0 < lon2 <= 180.0
        assert lat2 == pytest.approx(lat, abs=1e-9)
        # -180 and 180 are one meridian: compare longitudes around the circle.
        assert float(geo.wrap_deg(lon2 - lon)) == pytest.approx(0.0, abs=1e-9)


def test_local_tangent_plane_inverse_past_a_pole_is_still_an_error() -> None:
    ltp = LocalTangentPlane(-89.89, 10.0)
    _x, y = ltp.to_xy(90.0, 10.0)
    assert ltp.to_latlon(0.0, y)[0] == pytest.approx(90.0, abs=1e-12)
    # A micrometre past it (1e-11 deg) is rounding: put back on the pole, on both paths.
    assert ltp.to_latlon(0.0, y + 1e-6)[0] == 90.0
    assert float(np.asarray(ltp.to_latlon(np.array([0.0]), np.array([y + 1e-6]))[0])[0]) == 90.0
    # A metre past the pole is not rounding: both paths refuse it.
    with pytest.raises(GeoError, match="latitude"):
        ltp.to_latlon(0.0, y + 1.0)
    with pytest.raises(GeoError, match="latitude"):
        ltp.to_latlon(np.array([0.0]), np.array([y + 1.0]))


def test_make_projection_by_config_name() -> None:
    assert make_projection("two_radius", 51.7, 30.0).to_xy(51.7, 30.0) == latlon_to_xy(51.7, 30.0)
    p = make_projection("local_tangent_plane", 51.7, 30.0)
    assert p.name == "local_tangent_plane"
    assert p.to_xy(51.7, 30.0) == (0.0, 0.0)
    assert set(geo.PROJECTIONS) == {"two_radius", "local_tangent_plane"}
    with pytest.raises(GeoError, match="two_radius, local_tangent_plane"):
        make_projection("mercator", 0.0, 0.0)
    with pytest.raises(GeoError, match="pole"):
        LocalTangentPlane(90.0, 0.0)


# ---------------------------------------------------------------- scalar fast paths
# Scalars take a math-module path; it must give exactly the bits of the array path (the
# mission outputs and recordings depend on it), and bad scalars must raise the same errors.


def _same(a: float, b: float) -> bool:
    return (a == b and math.copysign(1.0, a) == math.copysign(1.0, b)) or (a != a and b != b)


def _one(v: float) -> np.ndarray:
    return np.array([v])


def _first(a: object) -> float:
    """Element 0 of an array result, as a float."""
    return float(np.asarray(a).ravel()[0])


_ANY = st.floats(allow_nan=False, allow_infinity=False, min_value=-1e6, max_value=1e6)
_EDGES = [0.0, -0.0, 1e-300, -1e-300, math.pi, -math.pi, 2 * math.pi, 180.0, -180.0, 540.0]


@settings(max_examples=400, deadline=None)
@given(
    xc=_ANY | st.sampled_from(_EDGES),
    yc=_ANY | st.sampled_from(_EDGES),
    xi=_ANY | st.sampled_from(_EDGES),
    yi=_ANY | st.sampled_from(_EDGES),
)
def test_scalar_bearing_and_deviation_are_bit_identical_to_arrays(
    xc: float, yc: float, xi: float, yi: float
) -> None:
    if xc == xi and yc == yi:
        return
    phi = destination_bearing(xc, yc, xi, yi)
    assert type(phi) is float
    # math.acos is the C library's; numpy may use its own SIMD arccos (AVX-512), so allow
    # an ulp there. Everything else is plain IEEE arithmetic and must match exactly.
    ref = _first(destination_bearing(_one(xc), _one(yc), _one(xi), _one(yi)))
    assert _same(phi, ref) or abs(phi - ref) <= 2 * math.ulp(ref)
    for a, b in ((phi, yc), (xc, yc), (xi, yi), (phi, math.pi)):
        theta = course_deviation(a, b)
        assert type(theta) is float
        assert _same(theta, _first(course_deviation(_one(a), _one(b))))
    w = geo.wrap_deg(xc)
    assert _same(w, _first(geo.wrap_deg(_one(xc))))


@settings(max_examples=300, deadline=None)
@given(
    lat0=st.floats(-89, 89),
    lon0=st.floats(-180, 180),
    lat=st.floats(-90, 90),
    lon=st.floats(-180, 180) | st.sampled_from([180.0, -180.0, 0.0, -0.0]),
)
def test_scalar_projections_are_bit_identical_to_arrays(
    lat0: float, lon0: float, lat: float, lon: float
) -> None:
    for proj in (LocalTangentPlane(lat0, lon0), geo.TwoRadius(lon0)):
        x, y = (float(v) for v in proj.to_xy(lat, lon))
        xa, ya = proj.to_xy(_one(lat), _one(lon))
        assert all(type(v) is float for v in proj.to_xy(lat, lon))
        assert _same(x, _first(xa)) and _same(y, _first(ya))
        la, lo = (float(v) for v in proj.to_latlon(x, y))
        laa, loa = proj.to_latlon(_one(x), _one(y))
        assert _same(la, _first(laa)) and _same(lo, _first(loa))


def test_scalar_paths_accept_ints_and_numpy_floats() -> None:
    assert latlon_to_xy(1, 2) == latlon_to_xy(1.0, 2.0)
    assert destination_bearing(np.float64(0.0), 0, 1, np.float64(1.0)) == pytest.approx(math.pi / 4)
    assert geo.wrap_deg(np.float64(190.0)) == -170.0


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_bad_scalars_raise_the_array_paths_errors(bad: float) -> None:
    with pytest.raises(GeoError, match="finite"):
        latlon_to_xy(bad, 0.0)
    with pytest.raises(GeoError, match="finite"):
        destination_bearing(0.0, 0.0, bad, 1.0)
    with pytest.raises(GeoError, match="finite"):
        course_deviation(bad, 0.0)
    with pytest.raises(GeoError, match="finite"):
        geo.wrap_deg(bad)
    with pytest.raises(GeoError, match="finite"):
        LocalTangentPlane(51.7, 30.0).to_xy(51.7, bad)
    with pytest.raises(GeoError, match="finite"):
        LocalTangentPlane(51.7, 30.0).to_latlon(bad, 0.0)
    with pytest.raises(GeoError, match="latitude"):
        xy_to_latlon(0.0, 1e8)
    with pytest.raises(GeoError, match="latitude"):
        LocalTangentPlane(51.7, 30.0).to_latlon(0.0, 1e8)


def test_two_radius_is_continuous_across_the_180th_meridian() -> None:
    # A mission 21 m across ±180° (outside audit): x was +20,037,569 m for one waypoint and
    # -20,037,569 m for the other, so the robot would have headed round the earth.
    p = make_projection("two_radius", -16.5, 179.9999)
    (xa, ya), (xb, yb) = p.to_xy(-16.5, 179.9999), p.to_xy(-16.5, -179.9999)
    assert ya == yb and 0.0 < xb - xa < 25.0  # 22.3 m: the paper's x, stretched by 1/cos Φ
    xs, ys = p.to_xy(np.array([-16.5, -16.5]), np.array([179.9999, -179.9999]))
    assert np.array_equal(xs, [xa, xb]) and np.array_equal(ys, [ya, yb])
    lat, lon = p.to_latlon(xb, yb)
    assert lat == pytest.approx(-16.5) and lon == pytest.approx(-179.9999, abs=1e-9)
    lats, lons = p.to_latlon(np.array([xa, xb]), np.array([ya, yb]))
    assert np.allclose(lons, [179.9999, -179.9999], atol=1e-9) and np.allclose(lats, -16.5)
    # away from the meridian: the paper's absolute figures, bit for bit
    assert make_projection("two_radius", 51.7, -1.25).to_xy(51.7, -1.26) == latlon_to_xy(
        51.7, -1.26
    )


def test_navigator_heads_across_the_180th_meridian_with_two_radius() -> None:
    import dataclasses

    from x6wd.core.config import NavigationConfig
    from x6wd.nav.navigator import Navigator

    for steering in ("paper", "pivot_arc"):
        cfg = dataclasses.replace(NavigationConfig(), projection="two_radius", steering=steering)
        nav = Navigator(cfg, 0.0)
        nav.set_waypoints([(-16.5, 179.9999), (-16.5, -179.9999)])
        nav.step(*nav.to_xy(-16.5, 179.9999), math.pi / 2)  # on the first: arrives
        # the second lies 21 m east; heading east must be (nearly) straight on
        x, y = nav.to_xy(-16.5, 179.99992)
        tx, ty = nav.target_xy()
        assert 0.0 < tx - x < 25.0 and abs(ty - y) < 1e-6
        assert abs(float(geo.destination_bearing(x, y, tx, ty)) - math.pi / 2) < 1e-6
