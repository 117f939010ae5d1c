"""Plane coordinates for navigation: the paper's two-radius conversion, a local tangent
plane, the destination bearing φi and the course deviation Θ (REFERENCE.md §1).

Degrees at the API for latitude/longitude, metres for x/y, radians for bearings. x points
east, y north; bearings are clockwise from north in (-π, π] (negative = west).
Every function accepts scalars or numpy arrays (broadcasting) and returns floats for
scalar input.
"""

from __future__ import annotations

import math
from typing import Protocol, overload

import numpy as np
import numpy.typing as npt

from x6wd.errors import X6wdError

R1_M = 6378160.0
"""Equatorial radius used by the paper for x (east), metres."""
R2_M = 6356770.0
"""Polar radius used by the paper for y (north), metres."""

WGS84_A_M = 6378137.0
"""WGS-84 semi-major axis, metres (for the local tangent plane)."""
WGS84_E2 = 6.69437999014e-3
"""WGS-84 first eccentricity squared."""

PROJECTIONS = ("two_radius", "local_tangent_plane")
"""Names accepted by :func:`make_projection` (and ``navigation.projection`` in the config)."""

ArrayLike = float | npt.NDArray[np.floating]


class GeoError(X6wdError, ValueError):
    """Coordinates out of range, not finite, or a bearing between coincident points."""


@overload
def _out(a: float, scalar: bool) -> float: ...
@overload
def _out(a: npt.NDArray[np.floating], scalar: bool) -> ArrayLike: ...
def _out(a: ArrayLike, scalar: bool) -> ArrayLike:
    return float(a) if scalar else np.asarray(a, dtype=float)


def _as_array(name: str, value: ArrayLike) -> npt.NDArray[np.float64]:
    a = np.asarray(value, dtype=float)
    if not np.all(np.isfinite(a)):
        raise GeoError(f"{name} must be finite, got {value!r}")
    return a


def _check_latlon(lat: npt.NDArray[np.float64], lon: npt.NDArray[np.float64]) -> None:
    if np.any(np.abs(lat) > 90.0):
        raise GeoError(f"latitude must be within [-90, 90] deg, got {lat}")
    if np.any(np.abs(lon) > 180.0):
        raise GeoError(f"longitude must be within [-180, 180] deg, got {lon}")


def _is_scalar(*values: object) -> bool:
    return all(np.ndim(v) == 0 for v in values)  # type: ignore[arg-type]


@overload
def latlon_to_xy(lat_deg: float, lon_deg: float) -> tuple[float, float]: ...
@overload
def latlon_to_xy(lat_deg: ArrayLike, lon_deg: ArrayLike) -> tuple[ArrayLike, ArrayLike]: ...
def latlon_to_xy(lat_deg: ArrayLike, lon_deg: ArrayLike) -> tuple[ArrayLike, ArrayLike]:
    """Two-radius conversion (paper eqs. 1-2): ``x = Λ·R1``, ``y = Φ·R2`` in metres.

    No cos Φ factor: east distances come out stretched by 1/cos Φ, as in the paper.
    """
    lat = _as_array("lat_deg", lat_deg)
    lon = _as_array("lon_deg", lon_deg)
    _check_latlon(lat, lon)
    scalar = _is_scalar(lat_deg, lon_deg)
    x = np.radians(lon) * R1_M
    y = np.radians(lat) * R2_M
    return _out(x, scalar), _out(y, scalar)


@overload
def xy_to_latlon(x_m: float, y_m: float) -> tuple[float, float]: ...
@overload
def xy_to_latlon(x_m: ArrayLike, y_m: ArrayLike) -> tuple[ArrayLike, ArrayLike]: ...
def xy_to_latlon(x_m: ArrayLike, y_m: ArrayLike) -> tuple[ArrayLike, ArrayLike]:
    """Inverse of :func:`latlon_to_xy`: metres -> (lat_deg, lon_deg)."""
    x = _as_array("x_m", x_m)
    y = _as_array("y_m", y_m)
    scalar = _is_scalar(x_m, y_m)
    lat = np.degrees(y / R2_M)
    lon = np.degrees(x / R1_M)
    _check_latlon(lat, lon)
    return _out(lat, scalar), _out(lon, scalar)


@overload
def destination_bearing(xc: float, yc: float, xi: float, yi: float) -> float: ...
@overload
def destination_bearing(
    xc: ArrayLike, yc: ArrayLike, xi: ArrayLike, yi: ArrayLike
) -> ArrayLike: ...
def destination_bearing(xc: ArrayLike, yc: ArrayLike, xi: ArrayLike, yi: ArrayLike) -> ArrayLike:
    """Bearing φi (rad, (-π, π], clockwise from north) from (xc, yc) to (xi, yi), metres.

    Paper eqs. 3-4: ``sign(xi − xc) · arccos((yi − yc) / distance)`` with sign(0) = +1, so due
    south is +π. Coincident points have no bearing: :class:`GeoError`.
    """
    dx = _as_array("xi - xc", np.subtract(xi, xc))
    dy = _as_array("yi - yc", np.subtract(yi, yc))
    scalar = _is_scalar(xc, yc, xi, yi)
    dist = np.hypot(dx, dy)
    if np.any(dist == 0.0):
        raise GeoError("destination bearing is undefined: the two points coincide")
    # hypot is within an ulp; the clip keeps arccos defined whatever the rounding.
    phi = np.where(dx >= 0.0, 1.0, -1.0) * np.arccos(np.clip(dy / dist, -1.0, 1.0))
    # A negative dx far smaller than dy rounds to exactly -π, outside (-π, π].
    phi = np.where(phi == -math.pi, math.pi, phi)
    return _out(phi, scalar)


@overload
def course_deviation(phi_i: float, phi_c: float) -> float: ...
@overload
def course_deviation(phi_i: ArrayLike, phi_c: ArrayLike) -> ArrayLike: ...
def course_deviation(phi_i: ArrayLike, phi_c: ArrayLike) -> ArrayLike:
    """Course deviation Θ = φi − φc wrapped to (-π, π] (paper eqs. 5-6), radians.

    Θ > 0: the destination is clockwise of the heading (turn right). For inputs in (-π, π]
    this is exactly the paper's single correction; other finite inputs are wrapped too.
    """
    a = _as_array("phi_i", phi_i)
    b = _as_array("phi_c", phi_c)
    scalar = _is_scalar(phi_i, phi_c)
    theta = a - b
    theta = np.where(theta > math.pi, -(2.0 * math.pi - theta), theta)
    theta = np.where(theta <= -math.pi, 2.0 * math.pi + theta, theta)
    out_of_range = (theta > math.pi) | (theta <= -math.pi)
    if np.any(out_of_range):
        wrapped = math.pi - np.mod(math.pi - theta, 2.0 * math.pi)
        wrapped = np.where(wrapped <= -math.pi, math.pi, wrapped)
        theta = np.where(out_of_range, wrapped, theta)
    return _out(theta, scalar)


@overload
def wrap_deg(angle_deg: float) -> float: ...
@overload
def wrap_deg(angle_deg: ArrayLike) -> ArrayLike: ...
def wrap_deg(angle_deg: ArrayLike) -> ArrayLike:
    """Any finite angle in degrees wrapped to (-180, 180]."""
    a = _as_array("angle_deg", angle_deg)
    w = 180.0 - np.mod(180.0 - a, 360.0)
    w = np.where(w <= -180.0, 180.0, w)
    return _out(w, _is_scalar(angle_deg))


class Projection(Protocol):
    """Latitude/longitude (deg) <-> plane x east / y north (m)."""

    name: str

    def to_xy(self, lat_deg: ArrayLike, lon_deg: ArrayLike) -> tuple[ArrayLike, ArrayLike]:
        """(lat_deg, lon_deg) -> (x_m, y_m)."""
        ...

    def to_latlon(self, x_m: ArrayLike, y_m: ArrayLike) -> tuple[ArrayLike, ArrayLike]:
        """(x_m, y_m) -> (lat_deg, lon_deg)."""
        ...


class TwoRadius:
    """The paper's projection (:func:`latlon_to_xy`); absolute, no origin."""

    name = "two_radius"

    def to_xy(self, lat_deg: ArrayLike, lon_deg: ArrayLike) -> tuple[ArrayLike, ArrayLike]:
        """(lat_deg, lon_deg) -> (x_m, y_m) by the two-radius formulas."""
        return latlon_to_xy(lat_deg, lon_deg)

    def to_latlon(self, x_m: ArrayLike, y_m: ArrayLike) -> tuple[ArrayLike, ArrayLike]:
        """(x_m, y_m) -> (lat_deg, lon_deg)."""
        return xy_to_latlon(x_m, y_m)


class LocalTangentPlane:
    """Local east/north plane at an origin, in true metres on the WGS-84 ellipsoid.

    ``x = ΔΛ · N(Φ0) · cos Φ0``, ``y = ΔΦ · M(Φ0)`` (angles in radians), with N and M the
    prime-vertical and meridional radii of curvature at the origin latitude Φ0. Unlike the
    two-radius conversion, east metres are not stretched by 1/cos Φ. Scale error is about
    d·tan Φ0 / R: a few millimetres at 100 m and centimetres at 1-2 km from the origin, the
    robot's working area. The longitude difference is wrapped, so missions may cross ±180°.
    """

    name = "local_tangent_plane"

    def __init__(self, origin_lat_deg: float, origin_lon_deg: float) -> None:
        lat0 = _as_array("origin_lat_deg", origin_lat_deg)
        lon0 = _as_array("origin_lon_deg", origin_lon_deg)
        _check_latlon(lat0, lon0)
        if abs(float(lat0)) >= 89.9:
            raise GeoError(f"local tangent plane origin too close to a pole: {float(lat0)} deg")
        self.origin_lat_deg = float(lat0)
        self.origin_lon_deg = float(lon0)
        phi0 = math.radians(self.origin_lat_deg)
        w = 1.0 - WGS84_E2 * math.sin(phi0) ** 2
        n_m = WGS84_A_M / math.sqrt(w)
        m_m = WGS84_A_M * (1.0 - WGS84_E2) / (w * math.sqrt(w))
        self._kx_m_per_deg = math.radians(1.0) * n_m * math.cos(phi0)
        self._ky_m_per_deg = math.radians(1.0) * m_m

    def to_xy(self, lat_deg: ArrayLike, lon_deg: ArrayLike) -> tuple[ArrayLike, ArrayLike]:
        """(lat_deg, lon_deg) -> (x_m, y_m) relative to the origin."""
        lat = _as_array("lat_deg", lat_deg)
        lon = _as_array("lon_deg", lon_deg)
        _check_latlon(lat, lon)
        scalar = _is_scalar(lat_deg, lon_deg)
        dlon = wrap_deg(lon - self.origin_lon_deg)
        x = np.asarray(dlon) * self._kx_m_per_deg
        y = (lat - self.origin_lat_deg) * self._ky_m_per_deg
        return _out(x, scalar), _out(y, scalar)

    def to_latlon(self, x_m: ArrayLike, y_m: ArrayLike) -> tuple[ArrayLike, ArrayLike]:
        """(x_m, y_m) relative to the origin -> (lat_deg, lon_deg)."""
        x = _as_array("x_m", x_m)
        y = _as_array("y_m", y_m)
        scalar = _is_scalar(x_m, y_m)
        lat = self.origin_lat_deg + y / self._ky_m_per_deg
        lon = np.asarray(wrap_deg(self.origin_lon_deg + x / self._kx_m_per_deg))
        _check_latlon(lat, lon)
        return _out(lat, scalar), _out(lon, scalar)


def make_projection(name: str, origin_lat_deg: float, origin_lon_deg: float) -> Projection:
    """The projection called ``name`` (see :data:`PROJECTIONS`); the origin (deg) is used by
    the local tangent plane and ignored by the absolute two-radius conversion."""
    if name == "two_radius":
        return TwoRadius()
    if name == "local_tangent_plane":
        return LocalTangentPlane(origin_lat_deg, origin_lon_deg)
    raise GeoError(f"unknown projection {name!r} (valid: {', '.join(PROJECTIONS)})")
