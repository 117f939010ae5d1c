"""WGS-84 constants and angle wrapping shared by every layer (x6wd.core.geodesy)."""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np
import pytest

from x6wd.core.geodesy import (
    WGS84_A_M,
    WGS84_B_M,
    WGS84_E2,
    WGS84_EP2,
    WGS84_F,
    wrap360,
    wrap_deg,
    wrap_rad,
)


def test_wgs84_follows_from_its_two_defining_constants() -> None:
    close = math.isclose
    assert WGS84_A_M == 6378137.0 and close(1.0 / WGS84_F, 298.257223563, rel_tol=1e-15)
    assert close(WGS84_B_M, 6356752.314245, abs_tol=1e-6)  # NIMA TR8350.2
    assert close(WGS84_E2, 6.69437999014e-3, rel_tol=1e-12)
    assert close(WGS84_EP2, 6.73949674228e-3, rel_tol=1e-11)
    assert close(WGS84_E2, 1.0 - (WGS84_B_M / WGS84_A_M) ** 2, rel_tol=1e-13)


def test_wrap_deg_ends_and_turns() -> None:
    assert wrap_deg(180.0) == 180.0 and wrap_deg(-180.0) == 180.0
    assert wrap_deg(190.0) == -170.0 and wrap_deg(-540.0) == 180.0 and wrap_deg(540.0) == 180.0
    assert wrap_deg(0.0) == 0.0 and wrap_deg(-179.5) == -179.5 and wrap_deg(359) == -1.0
    assert math.isnan(wrap_deg(math.nan)) and math.isnan(wrap_deg(math.inf))


def test_wrap_rad_ends_and_turns() -> None:
    assert wrap_rad(math.pi) == math.pi and wrap_rad(-math.pi) == math.pi
    assert wrap_rad(3 * math.pi) == pytest.approx(math.pi)
    assert wrap_rad(-0.5) == -0.5 and wrap_rad(2 * math.pi + 0.25) == pytest.approx(0.25)


def test_wrap360() -> None:
    assert wrap360(360.0) == 0.0 and wrap360(-90.0) == 270.0 and wrap360(725) == 5.0
    assert wrap360(-0.0) == 0.0 and math.copysign(1.0, wrap360(-0.0)) == 1.0
    assert wrap360(-1e-20) == 360.0  # float rounding, as with `%`: the only way to 360


@pytest.mark.parametrize("wrap", [wrap_deg, wrap_rad, wrap360])
def test_scalar_and_array_paths_are_bit_identical(wrap: Callable[[Any], Any]) -> None:
    rng = np.random.default_rng(3)
    a = np.concatenate(
        [rng.uniform(-1e4, 1e4, 2000), rng.uniform(-7, 7, 2000), [-180.0, 180.0, 540.0, 0.0]]
    )
    a = np.concatenate([a, a * math.pi / 180.0, [-math.pi, math.pi, 3 * math.pi]])
    arr = wrap(a)
    assert isinstance(arr, np.ndarray) and arr.shape == a.shape
    scalars = [wrap(float(x)) for x in a]
    assert all(type(s) is float for s in scalars)
    assert np.array_equal(arr, np.array(scalars))
    zero_d = wrap(np.array(190.0))  # numpy in, numpy out (.item() works)
    assert isinstance(zero_d, np.ndarray | np.floating) and np.ndim(zero_d) == 0


def test_wrap_deg_is_the_navigation_papers_wrap() -> None:
    # The formula the navigator's geometry used before it moved here, for a spread of angles.
    rng = np.random.default_rng(5)
    for a in rng.uniform(-2000.0, 2000.0, 5000).tolist():
        w = 180.0 - (180.0 - a) % 360.0
        assert wrap_deg(a) == (180.0 if w <= -180.0 else w)
