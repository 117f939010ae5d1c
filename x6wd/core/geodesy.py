"""The Earth and the angle conventions every layer shares: WGS-84 and angle wrapping.

One definition of each, so that the navigator's plane, the simulator's ECEF geometry and
the simulated sensors use the same ellipsoid, and an angle on the boundary of a range lands
on the same end everywhere.

The wraps take a Python number (a float back, without numpy's per-call cost: the simulated
compass and vehicle wrap a scalar every step) or anything numpy takes (numpy back: an array,
or a 0-d array or numpy scalar for 0-d input). Non-finite input gives NaN, never an error:
callers that must reject it (``x6wd.nav.geo``) check first.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any, Final, overload

if TYPE_CHECKING:  # numpy is imported on first use: `x6wd decode` never needs it
    import numpy as np
    import numpy.typing as npt

    Angles = npt.ArrayLike

# WGS-84 (NIMA TR8350.2): the two defining constants and what follows from them exactly.
WGS84_A_M: Final = 6378137.0
"""Semi-major axis (equatorial radius), metres."""
WGS84_F: Final = 1.0 / 298.257223563
"""Flattening (dimensionless)."""
WGS84_B_M: Final = WGS84_A_M * (1.0 - WGS84_F)
"""Semi-minor axis (polar radius), metres."""
WGS84_E2: Final = WGS84_F * (2.0 - WGS84_F)
"""First eccentricity squared (dimensionless)."""
WGS84_EP2: Final = WGS84_E2 / (1.0 - WGS84_E2)
"""Second eccentricity squared (dimensionless)."""

EARTH_MEAN_RADIUS_M: Final = (2.0 * WGS84_A_M + WGS84_B_M) / 3.0
"""Mean radius R1 = (2a + b) / 3 of the WGS-84 ellipsoid (IUGG), metres: ~6,371,008.8."""

_TWO_PI: Final = 2.0 * math.pi
_NUMBER: Final = (float, int)


@overload
def wrap_deg(angle_deg: float) -> float: ...
@overload
def wrap_deg(angle_deg: npt.NDArray[Any]) -> npt.NDArray[np.float64]: ...
@overload
def wrap_deg(angle_deg: Angles) -> float | npt.NDArray[np.float64]: ...
def wrap_deg(angle_deg: Angles) -> float | npt.NDArray[np.float64]:
    """Angle(s) in degrees wrapped to (-180, 180] (so -180 comes back as +180).

    ``180 - (180 - a) mod 360`` rather than ``(a + 180) mod 360 - 180``: the same in exact
    arithmetic, but this form puts the boundary at +180, the navigation paper's convention.
    """
    if isinstance(angle_deg, _NUMBER):
        w = 180.0 - (180.0 - angle_deg) % 360.0  # float % has np.mod's sign rule
        return 180.0 if w <= -180.0 else w
    import numpy as np

    a = np.asarray(angle_deg, dtype=float)
    w = 180.0 - np.mod(180.0 - a, 360.0)
    return np.where(w <= -180.0, 180.0, w)


@overload
def wrap_rad(angle_rad: float) -> float: ...
@overload
def wrap_rad(angle_rad: npt.NDArray[Any]) -> npt.NDArray[np.float64]: ...
@overload
def wrap_rad(angle_rad: Angles) -> float | npt.NDArray[np.float64]: ...
def wrap_rad(angle_rad: Angles) -> float | npt.NDArray[np.float64]:
    """Angle(s) in radians wrapped to (-π, π] (as :func:`wrap_deg`)."""
    if isinstance(angle_rad, _NUMBER):
        w = math.pi - (math.pi - angle_rad) % _TWO_PI
        return math.pi if w <= -math.pi else w
    import numpy as np

    a = np.asarray(angle_rad, dtype=float)
    w = math.pi - np.mod(math.pi - a, _TWO_PI)
    return np.where(w <= -math.pi, math.pi, w)


@overload
def wrap360(angle_deg: float) -> float: ...
@overload
def wrap360(angle_deg: npt.NDArray[Any]) -> npt.NDArray[np.float64]: ...
@overload
def wrap360(angle_deg: Angles) -> float | npt.NDArray[np.float64]: ...
def wrap360(angle_deg: Angles) -> float | npt.NDArray[np.float64]:
    """Angle(s) in degrees wrapped to [0, 360): a bearing or course (0 = north).

    As with ``%``, an angle less than half an ulp of 360 below a multiple of 360 rounds to
    360.0 itself (``-1e-20`` gives 360.0).
    """
    if isinstance(angle_deg, _NUMBER):
        return angle_deg % 360.0
    import numpy as np

    return np.mod(np.asarray(angle_deg, dtype=float), 360.0)


__all__ = [
    "WGS84_A_M",
    "WGS84_B_M",
    "WGS84_E2",
    "WGS84_EP2",
    "WGS84_F",
    "wrap360",
    "wrap_deg",
    "wrap_rad",
]


def great_circle_m(lat1_deg: float, lon1_deg: float, lat2_deg: float, lon2_deg: float) -> float:
    """Great-circle (haversine) distance in metres on the mean Earth sphere: within 0.5 % of
    the ellipsoid's, plenty for a geofence."""
    p1, p2 = math.radians(lat1_deg), math.radians(lat2_deg)
    dp, dl = p2 - p1, math.radians(lon2_deg - lon1_deg)
    a = math.sin(dp / 2) ** 2 + math.cos(p1) * math.cos(p2) * math.sin(dl / 2) ** 2
    return 2 * EARTH_MEAN_RADIUS_M * math.asin(min(1.0, math.sqrt(a)))
