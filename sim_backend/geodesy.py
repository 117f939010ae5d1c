"""WGS-84 coordinates (geodetic <-> ECEF <-> local ENU) and GPS time <-> UTC.

All functions are vectorised: they accept scalars or numpy arrays and broadcast.
Angles are degrees at the public boundary, distances metres, times seconds.

GPS time here is *continuous* seconds since the GPS epoch 1980-01-06T00:00:00 (no leap
seconds); ``week = floor(s / 604800)``, ``tow = s - week * 604800``. Broadcast messages carry
the week modulo 1024 (10 bits); :func:`resolve_week` unwraps it against a reference date.
"""

from __future__ import annotations

from datetime import UTC, datetime, timedelta

import numpy as np

from x6wd.core.errors import ConfigError
from x6wd.core.geodesy import WGS84_A_M as A_M
from x6wd.core.geodesy import WGS84_B_M as B_M
from x6wd.core.geodesy import WGS84_E2 as E2
from x6wd.core.geodesy import WGS84_EP2 as EP2
from x6wd.core.geodesy import WGS84_F as F

# IS-GPS-200 constants (the ellipsoid's are the core's WGS-84, imported above).
GM_M3PS2 = 3.986005e14  # IS-GPS-200 value (not the WGS-84 EGM one) for orbit propagation
OMEGA_E_RPS = 7.2921151467e-5  # Earth rotation rate, IS-GPS-200
C_MPS = 299792458.0

SECONDS_PER_WEEK = 604800
GPS_EPOCH = datetime(1980, 1, 6, tzinfo=UTC)

# (UTC instant from which it applies, GPS - UTC in seconds). No leap second since 2017.
_LEAP_TABLE: tuple[tuple[datetime, int], ...] = tuple(
    (datetime(y, m, 1, tzinfo=UTC), n)
    for (y, m, n) in (
        (1981, 7, 1),
        (1982, 7, 2),
        (1983, 7, 3),
        (1985, 7, 4),
        (1988, 1, 5),
        (1990, 1, 6),
        (1991, 1, 7),
        (1992, 7, 8),
        (1993, 7, 9),
        (1994, 7, 10),
        (1996, 1, 11),
        (1997, 7, 12),
        (1999, 1, 13),
        (2006, 1, 14),
        (2009, 1, 15),
        (2012, 7, 16),
        (2015, 7, 17),
        (2017, 1, 18),
    )
)


# ---------------------------------------------------------------- coordinates


def lla_to_ecef(
    lat_deg: np.ndarray | float, lon_deg: np.ndarray | float, alt_m: np.ndarray | float
) -> np.ndarray:
    """Geodetic latitude/longitude (deg) and ellipsoidal height (m) -> ECEF (m), shape (..., 3)."""
    lat = np.radians(np.asarray(lat_deg, dtype=float))
    lon = np.radians(np.asarray(lon_deg, dtype=float))
    h = np.asarray(alt_m, dtype=float)
    sl, cl = np.sin(lat), np.cos(lat)
    n = A_M / np.sqrt(1.0 - E2 * sl * sl)
    x = (n + h) * cl * np.cos(lon)
    y = (n + h) * cl * np.sin(lon)
    z = (n * (1.0 - E2) + h) * sl
    return np.stack(np.broadcast_arrays(x, y, z), axis=-1)


def ecef_to_lla(xyz_m: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """ECEF (m), shape (..., 3) -> (lat_deg, lon_deg, alt_m) ellipsoidal.

    Bowring's parametric-latitude start plus two Newton-like refinements: sub-millimetre
    from the ground to GPS orbit altitude.
    """
    xyz = np.asarray(xyz_m, dtype=float)
    x, y, z = xyz[..., 0], xyz[..., 1], xyz[..., 2]
    p = np.hypot(x, y)
    lon = np.arctan2(y, x)
    beta = np.arctan2(z * A_M, p * B_M)
    for _ in range(2):
        sb, cb = np.sin(beta), np.cos(beta)
        lat = np.arctan2(z + EP2 * B_M * sb**3, p - E2 * A_M * cb**3)
        beta = np.arctan2((1.0 - F) * np.sin(lat), np.cos(lat))
    sl, cl = np.sin(lat), np.cos(lat)
    n = A_M / np.sqrt(1.0 - E2 * sl * sl)
    # Two height formulas, each well conditioned away from the poles / the equator.
    with np.errstate(divide="ignore", invalid="ignore"):
        h = np.where(np.abs(cl) > 0.1, p / cl - n, z / sl - n * (1.0 - E2))
    return np.degrees(lat), np.degrees(lon), h


def enu_rotation(lat_deg: np.ndarray | float, lon_deg: np.ndarray | float) -> np.ndarray:
    """Rotation matrix R (..., 3, 3) with ``enu = R @ d_ecef`` at the given place."""
    lat = np.radians(np.asarray(lat_deg, dtype=float))
    lon = np.radians(np.asarray(lon_deg, dtype=float))
    sl, cl = np.sin(lat), np.cos(lat)
    so, co = np.sin(lon), np.cos(lon)
    zero = np.zeros_like(sl * so)
    rows = (
        (-so + zero, co + zero, zero),
        (-sl * co, -sl * so, cl + zero),
        (cl * co, cl * so, sl + zero),
    )
    return np.stack([np.stack(r, axis=-1) for r in rows], axis=-2)


def ecef_to_enu(xyz_m: np.ndarray, lat0_deg: float, lon0_deg: float, alt0_m: float) -> np.ndarray:
    """ECEF points (..., 3) -> east/north/up (m) relative to the origin (deg, deg, m)."""
    origin = lla_to_ecef(lat0_deg, lon0_deg, alt0_m)
    r = enu_rotation(lat0_deg, lon0_deg)
    return (np.asarray(xyz_m, dtype=float) - origin) @ r.T


class EnuFrame:
    """A local east/north/up frame whose origin's ECEF position and rotation are computed
    once: for converting many points (one per epoch) about the same origin."""

    def __init__(self, lat0_deg: float, lon0_deg: float, alt0_m: float) -> None:
        """The origin: latitude and longitude (deg), height (m)."""
        self.origin = (lat0_deg, lon0_deg, alt0_m)
        self.origin_ecef_m = lla_to_ecef(lat0_deg, lon0_deg, alt0_m)
        self.rotation = enu_rotation(lat0_deg, lon0_deg)

    def to_ecef(self, enu_m: np.ndarray) -> np.ndarray:
        """East/north/up (m), shape (..., 3), relative to the origin -> ECEF (m)."""
        return np.asarray(enu_m, dtype=float) @ self.rotation + self.origin_ecef_m

    def to_lla(self, enu_m: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """East/north/up (m), shape (..., 3), relative to the origin -> (lat_deg, lon_deg,
        alt_m)."""
        return ecef_to_lla(self.to_ecef(enu_m))


def enu_to_ecef(enu_m: np.ndarray, lat0_deg: float, lon0_deg: float, alt0_m: float) -> np.ndarray:
    """East/north/up (m), shape (..., 3), relative to the origin -> ECEF (m)."""
    return EnuFrame(lat0_deg, lon0_deg, alt0_m).to_ecef(enu_m)


def lla_to_enu(
    lat_deg: np.ndarray | float,
    lon_deg: np.ndarray | float,
    alt_m: np.ndarray | float,
    lat0_deg: float,
    lon0_deg: float,
    alt0_m: float,
) -> np.ndarray:
    """Geodetic (deg, deg, m) -> ENU (..., 3) metres relative to the origin."""
    return ecef_to_enu(lla_to_ecef(lat_deg, lon_deg, alt_m), lat0_deg, lon0_deg, alt0_m)


def enu_to_lla(
    enu_m: np.ndarray, lat0_deg: float, lon0_deg: float, alt0_m: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """ENU (..., 3) metres relative to the origin -> (lat_deg, lon_deg, alt_m)."""
    return ecef_to_lla(enu_to_ecef(enu_m, lat0_deg, lon0_deg, alt0_m))


# ---------------------------------------------------------------- time


def _as_utc(dt: datetime) -> datetime:
    if dt.tzinfo is None:
        raise ConfigError(f"datetime {dt.isoformat()} has no time zone; give it in UTC")
    return dt.astimezone(UTC)


def leap_seconds(utc: datetime) -> int:
    """GPS - UTC (s) in force at the UTC instant ``utc`` (18 since 2017-01-01)."""
    utc = _as_utc(utc)
    n = 0
    for start, count in _LEAP_TABLE:
        if utc >= start:
            n = count
    return n


def leap_midnights_after(utc: datetime) -> list[datetime]:
    """The UTC midnights later than ``utc`` that follow an inserted leap second (23:59:60
    of the day before), in order."""
    utc = _as_utc(utc)
    return [start for start, _ in _LEAP_TABLE if start > utc]


def utc_to_gps_seconds(utc: datetime) -> float:
    """Aware UTC datetime -> continuous GPS seconds since 1980-01-06 (leap seconds added)."""
    utc = _as_utc(utc)
    return (utc - GPS_EPOCH).total_seconds() + leap_seconds(utc)


def gps_seconds_to_utc(gps_s: float) -> datetime:
    """Continuous GPS seconds -> aware UTC datetime (leap seconds removed).

    During an inserted leap second the result repeats the following second, as most
    receivers do; the table has no leap second after 2017.
    """
    guess = GPS_EPOCH + timedelta(seconds=float(gps_s))
    n = leap_seconds(guess - timedelta(seconds=leap_seconds(guess)))
    return guess - timedelta(seconds=n)


def gps_week_tow(gps_s: np.ndarray | float) -> tuple[np.ndarray, np.ndarray]:
    """Continuous GPS seconds -> (full week number, time of week s in [0, 604800))."""
    s = np.asarray(gps_s, dtype=float)
    week = np.floor(s / SECONDS_PER_WEEK)
    return week.astype(np.int64), s - week * SECONDS_PER_WEEK


def week_tow_to_gps_seconds(week: np.ndarray | int, tow_s: np.ndarray | float) -> np.ndarray:
    """Full GPS week and time of week (s) -> continuous GPS seconds."""
    return np.asarray(week, dtype=float) * SECONDS_PER_WEEK + np.asarray(tow_s, dtype=float)


def resolve_week(week_mod: int, reference: datetime, modulus: int = 1024) -> int:
    """Unwrap a truncated week number (``week mod modulus``) to the full week nearest the
    reference date (e.g. week 38 near 2020-01-01 -> 2086). Within half a rollover period
    (about 9.8 years for 1024 weeks) of the true date the answer is unambiguous."""
    if not 0 <= week_mod < modulus:
        raise ConfigError(f"week {week_mod} is outside 0..{modulus - 1} for modulus {modulus}")
    ref_week = int(utc_to_gps_seconds(reference) // SECONDS_PER_WEEK)
    k = round((ref_week - week_mod) / modulus)
    return week_mod + k * modulus
