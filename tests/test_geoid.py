"""The geoid model (sim_backend.geoid) against published EGM96 values, and in GGA."""

from __future__ import annotations

import numpy as np
import pytest

from sim_backend.geoid import geoid_separation_m
from x6wd.core.errors import ConfigError

# NGA's EGM96 check points (OUTINTPT.DAT, the sample output of the EGM96 grid program):
# latitude, longitude (deg, 0..360 east), geoid height (m).
NGA_EGM96 = (
    (38.6281550, 269.7791550, -31.628),
    (-14.6212170, 305.0211140, -2.969),
    (46.8743190, 102.4487290, -43.575),
    (-23.6174460, 133.8747120, 15.871),
    (38.6254730, 359.9995000, 50.066),
    (-0.4667440, 0.0023000, 17.329),
)


@pytest.mark.parametrize(("lat", "lon", "n_m"), NGA_EGM96)
def test_within_a_metre_of_the_published_egm96_values(lat: float, lon: float, n_m: float) -> None:
    assert geoid_separation_m(lat, lon) == pytest.approx(n_m, abs=1.0)
    # Longitude given east of 180 or as negative west: the same place.
    assert geoid_separation_m(lat, lon - 360.0) == pytest.approx(geoid_separation_m(lat, lon))


def test_vectorised_continuous_and_checked() -> None:
    lat = np.array([51.752, 0.0, -90.0, 90.0])
    lon = np.array([-1.2577, 180.0, 10.0, 0.0])
    n = np.asarray(geoid_separation_m(lat, lon))
    assert n.shape == (4,) and np.isfinite(n).all()
    assert n[0] == pytest.approx(47.7, abs=1.0)  # Oxford, the default scenario's origin
    # Across the dateline and a grid line the surface has no jump.
    assert geoid_separation_m(0.0, 179.9999) == pytest.approx(
        geoid_separation_m(0.0, -179.9999), abs=0.01
    )
    assert geoid_separation_m(44.9999, 7.0) == pytest.approx(
        geoid_separation_m(45.0001, 7.0), abs=0.01
    )
    with pytest.raises(ConfigError, match="latitude"):
        geoid_separation_m(91.0, 0.0)
