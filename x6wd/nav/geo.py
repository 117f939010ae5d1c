"""Plane coordinates for navigation: the paper's two-radius conversion, a local tangent
plane, the destination bearing φi and the course deviation Θ (REFERENCE.md §1).

Degrees at the API for latitude/longitude, metres for x/y, radians for bearings. x points
east, y north; bearings are clockwise from north in (-π, π] (negative = west).
Every function accepts scalars or numpy arrays (broadcasting) and returns floats for
scalar input.

Scalar fast paths: the controller calls these functions with plain floats several times per
compass sample (20 Hz on the robot, thousands of times per simulated mission), where building
0-d arrays cost far more than the arithmetic. Each function therefore first tries a
``math`` version for real-number scalars that does the same IEEE operations in the same
order, so the result is bit-identical to the array path (tests/test_geo.py checks this; the
one library call that could differ is arccos, where numpy may use its own SIMD version on
AVX-512 machines: within an ulp there, identical where numpy uses the C library's).
The fast path only handles valid input: anything non-finite, out of range or degenerate
falls through to the array path, which raises the usual error with the usual message.
"""

from __future__ import annotations

import math
from typing import Protocol, TypeGuard, overload

import numpy as np
import numpy.typing as npt

from x6wd.core.errors import X6wdError
from x6wd.core.geodesy import WGS84_A_M, WGS84_E2, wrap_rad
from x6wd.core.geodesy import wrap_deg as _wrap_deg

R1_M = 6378160.0
"""Equatorial radius used by the paper for x (east), metres."""
R2_M = 6356770.0
"""Polar radius used by the paper for y (north), metres."""

PROJECTIONS = ("two_radius", "local_tangent_plane")
"""Names accepted by :func:`make_projection` (and ``navigation.projection`` in the config)."""

ArrayLike = float | npt.NDArray[np.floating]

POLE_ROUNDING_DEG = 1e-9
"""An inverse projection may land this far (deg, about 0.1 mm) past a pole through rounding
alone; such a latitude is put back on the pole instead of failing the range check."""


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
        raise GeoError(f"{name} must be finite, got {_first_bad(a, ~np.isfinite(a))}")
    return a


def _first_bad(a: npt.NDArray[np.float64], bad: npt.NDArray[np.bool_]) -> str:
    """The bad value itself, or for an array the count and the first (not 12 kB of it)."""
    if a.ndim == 0:
        return repr(float(a))
    i = int(np.flatnonzero(bad)[0])
    n_bad = int(np.count_nonzero(bad))
    return f"{n_bad} of {a.size} values, the first {float(a.flat[i])!r} at index {i}"


def _check_latlon(lat: npt.NDArray[np.float64], lon: npt.NDArray[np.float64]) -> None:
    if np.any(np.abs(lat) > 90.0):
        raise GeoError(
            f"latitude must be within [-90, 90] deg, got {_first_bad(lat, np.abs(lat) > 90.0)}"
        )
    if np.any(np.abs(lon) > 180.0):
        raise GeoError(
            f"longitude must be within [-180, 180] deg, got {_first_bad(lon, np.abs(lon) > 180.0)}"
        )


def _snap_poles(lat: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
    # lat0 + (lat - lat0)·k / k is not exactly lat: at ±90° it can come back an ulp past the
    # pole. Only rounding-sized overshoots are clipped; anything further still fails.
    return np.where(np.abs(lat) <= 90.0 + POLE_ROUNDING_DEG, np.clip(lat, -90.0, 90.0), lat)


def _is_scalar(*values: object) -> bool:
    return all(np.ndim(v) == 0 for v in values)  # type: ignore[arg-type]


def _real(v: object) -> TypeGuard[float]:
    """A real-number scalar the ``math`` fast paths can take (float, np.float64 or int; not
    bool, arrays or other numpy scalars, which keep the array path's conversions)."""
    return isinstance(v, float) or type(v) is int


def _hypot(a: float, b: float) -> float:
    # numpy's hypot is the C library's; math.hypot uses its own algorithm and differs in
    # the last bit for about 0.5 % of inputs, which would change the bearings.
    return float(np.hypot(a, b))


@overload
def latlon_to_xy(lat_deg: float, lon_deg: float) -> tuple[float, float]: ...
@overload
def latlon_to_xy(lat_deg: ArrayLike, lon_deg: ArrayLike) -> tuple[ArrayLike, ArrayLike]: ...
def latlon_to_xy(lat_deg: ArrayLike, lon_deg: ArrayLike) -> tuple[ArrayLike, ArrayLike]:
    """Two-radius conversion (paper eqs. 1-2): ``x = Λ·R1``, ``y = Φ·R2`` in metres.

    No cos Φ factor: east distances come out stretched by 1/cos Φ, as in the paper.
    """
    if _real(lat_deg) and _real(lon_deg):
        la, lo = float(lat_deg), float(lon_deg)
        if -90.0 <= la <= 90.0 and -180.0 <= lo <= 180.0:
            return math.radians(lo) * R1_M, math.radians(la) * R2_M
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
    if _real(x_m) and _real(y_m):
        la = math.degrees(float(y_m) / R2_M)
        lo = math.degrees(float(x_m) / R1_M)
        if -90.0 <= la <= 90.0 and -180.0 <= lo <= 180.0:
            return la, lo
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
    if _real(xc) and _real(yc) and _real(xi) and _real(yi):
        ddx = float(xi) - float(xc)
        ddy = float(yi) - float(yc)
        if math.isfinite(ddx) and math.isfinite(ddy):
            d = _hypot(ddx, ddy)
            if d != 0.0:
                p = math.acos(min(max(ddy / d, -1.0), 1.0))
                if ddx < 0.0:
                    p = -p
                return math.pi if p == -math.pi else p
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
    if _real(phi_i) and _real(phi_c):
        t = float(phi_i) - float(phi_c)
        if math.isfinite(t):
            # The same two corrections as below, then the general wrap if still outside.
            if t > math.pi:
                t = -(2.0 * math.pi - t)
            if t <= -math.pi:
                t = 2.0 * math.pi + t
            if t > math.pi or t <= -math.pi:
                t = wrap_rad(t)
            return t
    a = _as_array("phi_i", phi_i)
    b = _as_array("phi_c", phi_c)
    scalar = _is_scalar(phi_i, phi_c)
    theta = a - b
    theta = np.where(theta > math.pi, -(2.0 * math.pi - theta), theta)
    theta = np.where(theta <= -math.pi, 2.0 * math.pi + theta, theta)
    out_of_range = (theta > math.pi) | (theta <= -math.pi)
    if np.any(out_of_range):
        theta = np.where(out_of_range, wrap_rad(theta), theta)
    return _out(theta, scalar)


@overload
def wrap_deg(angle_deg: float) -> float: ...
@overload
def wrap_deg(angle_deg: ArrayLike) -> ArrayLike: ...
def wrap_deg(angle_deg: ArrayLike) -> ArrayLike:
    """Any finite angle in degrees wrapped to (-180, 180] (:func:`x6wd.core.geodesy.wrap_deg`,
    which this checks the input for: GeoError unless finite)."""
    if _real(angle_deg):
        f = float(angle_deg)
        if math.isfinite(f):
            return _wrap_deg(f)
    a = _as_array("angle_deg", angle_deg)
    return _out(_wrap_deg(a), _is_scalar(angle_deg))


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
    """The paper's projection (:func:`latlon_to_xy`), absolute: x and y are the paper's.

    A mission across the 180th meridian would put two points metres apart 40,000 km apart
    in x, so a longitude more than 180° from ``origin_lon_deg`` (the first waypoint's) is
    taken one turn round (x ± 2π·R1) and comes back wrapped from :meth:`to_latlon`. Anywhere
    else the figures are the paper's, bit for bit.
    """

    name = "two_radius"

    def __init__(self, origin_lon_deg: float = 0.0) -> None:
        lon0 = float(origin_lon_deg)
        if not (math.isfinite(lon0) and -180.0 <= lon0 <= 180.0):
            raise GeoError(f"two-radius origin longitude {origin_lon_deg!r} outside [-180, 180]")
        self.origin_lon_deg = lon0

    def to_xy(self, lat_deg: ArrayLike, lon_deg: ArrayLike) -> tuple[ArrayLike, ArrayLike]:
        """(lat_deg, lon_deg) -> (x_m, y_m) by the two-radius formulas, x continuous
        within 180° of the origin's longitude."""
        x, y = latlon_to_xy(lat_deg, lon_deg)
        if isinstance(x, float):
            d = float(lon_deg) - self.origin_lon_deg
            if d > 180.0:
                return x - _TURN_X_M, y
            if d < -180.0:
                return x + _TURN_X_M, y
            return x, y
        d_arr = np.asarray(lon_deg, dtype=float) - self.origin_lon_deg
        xa = np.asarray(x)
        xa = np.where(d_arr > 180.0, xa - _TURN_X_M, np.where(d_arr < -180.0, xa + _TURN_X_M, xa))
        return (xa if xa.ndim else float(xa)), y

    def to_latlon(self, x_m: ArrayLike, y_m: ArrayLike) -> tuple[ArrayLike, ArrayLike]:
        """(x_m, y_m) -> (lat_deg, lon_deg), longitude wrapped to [-180, 180]."""
        if _real(x_m):
            xf = float(x_m)
            if xf > _HALF_TURN_X_M:
                xf -= _TURN_X_M
            elif xf < -_HALF_TURN_X_M:
                xf += _TURN_X_M
            return xy_to_latlon(xf, y_m)
        x = _as_array("x_m", x_m)
        x = np.where(
            x > _HALF_TURN_X_M, x - _TURN_X_M, np.where(x < -_HALF_TURN_X_M, x + _TURN_X_M, x)
        )
        return xy_to_latlon(x if x.ndim else float(x), y_m)


_HALF_TURN_X_M = math.pi * R1_M
_TURN_X_M = 2.0 * math.pi * R1_M


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
        if _real(lat_deg) and _real(lon_deg):
            la, lo = float(lat_deg), float(lon_deg)
            if -90.0 <= la <= 90.0 and -180.0 <= lo <= 180.0:
                dl = _wrap_deg(lo - self.origin_lon_deg)
                return dl * self._kx_m_per_deg, (la - self.origin_lat_deg) * self._ky_m_per_deg
        lat = _as_array("lat_deg", lat_deg)
        lon = _as_array("lon_deg", lon_deg)
        _check_latlon(lat, lon)
        scalar = _is_scalar(lat_deg, lon_deg)
        dlon = wrap_deg(lon - self.origin_lon_deg)
        x = np.asarray(dlon) * self._kx_m_per_deg
        y = (lat - self.origin_lat_deg) * self._ky_m_per_deg
        return _out(x, scalar), _out(y, scalar)

    def to_latlon(self, x_m: ArrayLike, y_m: ArrayLike) -> tuple[ArrayLike, ArrayLike]:
        """(x_m, y_m) metres relative to the origin -> (lat_deg, lon_deg) degrees.

        Longitude comes back wrapped to (-180, 180] (so -180° returns as 180°, the same
        meridian). A latitude past a pole by rounding only (``POLE_ROUNDING_DEG``) is put on
        the pole; further past it is a :class:`GeoError`.
        """
        if _real(x_m) and _real(y_m):
            xf, yf = float(x_m), float(y_m)
            if math.isfinite(xf) and math.isfinite(yf):
                la = self.origin_lat_deg + yf / self._ky_m_per_deg
                lo = self.origin_lon_deg + xf / self._kx_m_per_deg
                if math.isfinite(lo):
                    lo = _wrap_deg(lo)
                    if abs(la) <= 90.0 + POLE_ROUNDING_DEG:
                        return min(max(la, -90.0), 90.0), lo  # as _snap_poles
        x = _as_array("x_m", x_m)
        y = _as_array("y_m", y_m)
        scalar = _is_scalar(x_m, y_m)
        lat = _snap_poles(self.origin_lat_deg + y / self._ky_m_per_deg)
        lon = np.asarray(wrap_deg(self.origin_lon_deg + x / self._kx_m_per_deg))
        _check_latlon(lat, lon)
        return _out(lat, scalar), _out(lon, scalar)


def make_projection(name: str, origin_lat_deg: float, origin_lon_deg: float) -> Projection:
    """The projection called ``name`` (see :data:`PROJECTIONS`); the origin (deg) is used by
    the local tangent plane; the two-radius conversion stays absolute and uses the origin's
    longitude only to keep x continuous across the 180th meridian."""
    if name == "two_radius":
        return TwoRadius(origin_lon_deg)
    if name == "local_tangent_plane":
        return LocalTangentPlane(origin_lat_deg, origin_lon_deg)
    raise GeoError(f"unknown projection {name!r} (valid: {', '.join(PROJECTIONS)})")
