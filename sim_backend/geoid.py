"""Geoid separation: the height of mean sea level above the WGS84 ellipsoid (m).

A receiver prints this in GGA field 11 and reports the altitude above MSL in field 9, so the
ellipsoidal height it solves for is altitude + separation. u-blox 5 receivers carry a coarse
built-in geoid model for it; the simulator does the same with a 5 deg x 5 deg grid of EGM2008
geoid heights (``data/geoid_5deg_cm.csv``, 37 x 73 values in cm, from gpsd's ``geoid.c``,
BSD-2-Clause, values computed with GeographicLib's GeoidEval), interpolated bilinearly.

Accuracy: against the six published EGM96 check values of NGA's ``OUTINTPT.DAT`` the grid is
within 0.9 m (tests/test_geoid.py); EGM96 and EGM2008 differ by well under a metre at these
wavelengths, so the error is mostly the 5 deg interpolation, which can reach a few metres
over steep geoid gradients (mountain ranges, trenches). That is the class of a receiver's
own built-in model, and far below the receiver's vertical error budget.
"""

from __future__ import annotations

import functools
from pathlib import Path

import numpy as np

from x6wd.core.errors import ConfigError

GRID_DEG = 5.0
_DATA = Path(__file__).with_name("data") / "geoid_5deg_cm.csv"


@functools.lru_cache(maxsize=1)
def _grid_m() -> np.ndarray:
    """The (37, 73) grid in metres: row i latitude -90 + 5 i, column j longitude -180 + 5 j."""
    grid = np.loadtxt(_DATA, delimiter=",", comments="#", dtype=float) / 100.0
    if grid.shape != (37, 73):
        raise ConfigError(f"{_DATA}: geoid grid must be 37 x 73, got {grid.shape}")
    return grid


def geoid_separation_m(
    lat_deg: float | np.ndarray, lon_deg: float | np.ndarray
) -> float | np.ndarray:
    """Geoid height N (m, MSL above the WGS84 ellipsoid) at latitude/longitude (deg),
    vectorised; any longitude (wrapped), latitude in -90..90."""
    lat = np.asarray(lat_deg, dtype=float)
    lon = np.asarray(lon_deg, dtype=float)
    if np.any(~np.isfinite(lat)) or np.any(np.abs(lat) > 90.0) or np.any(~np.isfinite(lon)):
        raise ConfigError("geoid: latitude must be in -90..90 deg and longitude finite")
    grid = _grid_m()
    y = (lat + 90.0) / GRID_DEG
    x = ((lon + 180.0) % 360.0) / GRID_DEG
    i = np.minimum(np.floor(y).astype(np.int64), grid.shape[0] - 2)
    j = np.minimum(np.floor(x).astype(np.int64), grid.shape[1] - 2)
    fy, fx = y - i, x - j
    n = (
        grid[i, j] * (1 - fy) * (1 - fx)
        + grid[i, j + 1] * (1 - fy) * fx
        + grid[i + 1, j] * fy * (1 - fx)
        + grid[i + 1, j + 1] * fy * fx
    )
    return float(n) if n.ndim == 0 else n
