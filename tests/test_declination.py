"""Magnetic declination from WMM2025 (x6wd.nav.declination) against the official test values.

Sources of the expected values:
- The WMM2025 test value table of the WMM2025 technical report (NOAA NCEI / BGS, December
  2024), published as ``WMM2025_TEST_VALUES.txt`` and ``WMM2025testvalues.pdf`` on the NCEI
  WMM page (www.ncei.noaa.gov/products/world-magnetic-model): 12 points, dates 2025.0 and
  2027.5, heights 0 and 100 km above the ellipsoid, at (80°N, 0°E), (0°, 120°E),
  (80°S, 240°E = 120°W); declination printed to 0.01°.
- NOAA/CIRES's longer table ``WMM2025_FINAL_TEST_VALUES.txt`` (100 points over 2025.0-2029.5,
  in the CIRES-Geomagnetism/wmm repository, the source of the ``wmm-calculator`` package):
  a few rows far from the report's points (field 1 decimal year, 2 height km, 3-4 lat/lon,
  5 declination, printed to 0.01°).
The printed values are rounded to 0.01°, so the tolerance is 0.005° plus a little.
"""

from __future__ import annotations

import datetime as dt
import math

import pytest

from x6wd.nav.declination import (
    VALID_FROM_YEAR,
    DeclinationError,
    decimal_year,
    declination_deg,
)

PRINTED_TOL_DEG = 0.0051  # half the last printed digit (0.01°), plus float slack

# (decimal year, height km, lat deg, lon deg, declination deg): WMM2025 report table
REPORT_TABLE = [
    (2025.0, 0, 80, 0, 1.28),
    (2025.0, 0, 0, 120, -0.16),
    (2025.0, 0, -80, 240, 68.78),
    (2025.0, 100, 80, 0, 0.85),
    (2025.0, 100, 0, 120, -0.15),
    (2025.0, 100, -80, 240, 68.21),
    (2027.5, 0, 80, 0, 2.59),
    (2027.5, 0, 0, 120, -0.24),
    (2027.5, 0, -80, 240, 68.49),
    (2027.5, 100, 80, 0, 2.16),
    (2027.5, 100, 0, 120, -0.23),
    (2027.5, 100, -80, 240, 67.93),
]

# rows of WMM2025_FINAL_TEST_VALUES.txt (same columns)
FINAL_TABLE_ROWS = [
    (2025.0, 65, 43, 93, 0.50),
    (2025.0, 51, -33, 109, -5.49),
    (2025.5, 44, 33, -118, 11.10),
    (2026.0, 82, -64, 87, -81.74),
    (2026.5, 12, -79, 115, -137.58),
    (2027.5, 0, -13, -59, -17.49),
    (2028.5, 11, 34, 0, 1.57),
    (2029.0, 57, 34, -13, -1.89),
    (2029.0, 41, 42, -19, -4.13),
]


def _lon180(lon_deg: float) -> float:
    return (lon_deg + 180.0) % 360.0 - 180.0


@pytest.mark.parametrize(("year", "h_km", "lat", "lon", "dec"), REPORT_TABLE)
def test_wmm2025_report_test_values(year, h_km, lat, lon, dec):
    got = declination_deg(lat, _lon180(lon), h_km * 1000.0, year)
    assert got == pytest.approx(dec, abs=PRINTED_TOL_DEG)


@pytest.mark.parametrize(("year", "h_km", "lat", "lon", "dec"), FINAL_TABLE_ROWS)
def test_wmm2025_final_test_values(year, h_km, lat, lon, dec):
    assert declination_deg(lat, lon, h_km * 1000.0, year) == pytest.approx(dec, abs=PRINTED_TOL_DEG)


def test_dates_and_datetimes_are_decimal_years():
    assert decimal_year(dt.date(2025, 1, 1)) == 2025.0
    assert decimal_year(dt.date(2025, 7, 2)) == pytest.approx(2025.0 + 182 / 365)
    assert decimal_year(dt.date(2028, 12, 31)) == pytest.approx(2028.0 + 365 / 366)  # leap
    noon = dt.datetime(2027, 7, 2, 12, 0, tzinfo=dt.UTC)
    assert decimal_year(noon) == pytest.approx(2027.0 + 182.5 / 365)
    cest = dt.datetime(2027, 7, 2, 14, 0, tzinfo=dt.timezone(dt.timedelta(hours=2)))
    assert decimal_year(cest) == pytest.approx(decimal_year(noon))
    # a date and its decimal year give the same declination (the report's 2027.5 is 2 July 12:00)
    d1 = declination_deg(80.0, 0.0, 0.0, noon)
    assert d1 == pytest.approx(2.59, abs=PRINTED_TOL_DEG)
    assert declination_deg(80.0, 0.0, 0.0, dt.date(2025, 1, 1)) == pytest.approx(1.28, abs=0.0051)


def test_a_robot_site_is_plausible():
    # Wrocław-like site (51.1°N, 17.0°E) in 2026: a small eastern declination (~+6.5°);
    # sign convention: east positive, true = magnetic + D.
    d = declination_deg(51.1, 17.0, 150.0, dt.date(2026, 6, 1))
    assert 5.0 < d < 8.0


@pytest.mark.parametrize(
    "date", [dt.date(2024, 11, 1), dt.date(2030, 1, 2), 2031.0, 2020.0, math.nan]
)
def test_outside_the_model_is_refused(date):
    with pytest.raises(DeclinationError):
        declination_deg(45.0, 10.0, 0.0, date)


@pytest.mark.parametrize(
    ("date", "shown"),
    [
        # a replayed 2010 log's fix time: was "datetime.datetime(2010, 8, 21, 8, 37, ...)"
        (dt.datetime(2010, 8, 21, 8, 37, 23, tzinfo=dt.UTC), "date 2010-08-21T08:37:23+00:00"),
        (dt.date(2010, 8, 21), "date 2010-08-21"),
        (2010.5, "year 2010.5000"),
    ],
)
def test_a_date_outside_the_model_is_named_in_iso_form(date, shown):
    with pytest.raises(DeclinationError, match="covers 2024-11-13 to 2030-01-01; ") as info:
        declination_deg(45.0, 10.0, 0.0, date)
    assert f"; {shown} " in str(info.value) and "datetime" not in str(info.value), info.value


def test_bad_inputs_are_refused():
    for args in [(math.nan, 0, 0), (0, math.inf, 0), (91, 0, 0), (0, 0, "x")]:
        with pytest.raises(DeclinationError):
            declination_deg(*args, 2026.0)
    with pytest.raises(DeclinationError):
        declination_deg(0, 0, 0, "2026-01-01")  # type: ignore[arg-type]
    assert 2024.86 < VALID_FROM_YEAR < 2024.87
