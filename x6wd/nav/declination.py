"""Magnetic declination from the World Magnetic Model (WMM2025), for a position and a date.

The CMPS10 reports a MAGNETIC bearing; the navigator needs a geographic one, so the
declination D (degrees, positive when magnetic north is east of true north) is added:
``true_bearing_deg = magnetic_bearing_deg + D``. When the configuration gives no
declination, this module computes it from the WMM.

The model is evaluated by NOAA/CIRES's own package ``wmm-calculator`` (import name ``wmm``,
MIT licence, with its helper ``geomaglib``; both need only numpy), which ships the WMM2025
coefficients (epoch 2025.0, valid 2024-11-13 to 2030-01-01). It is imported on first use, so
importing :mod:`x6wd.nav` costs nothing when the configuration states a declination.

Dates outside the model's validity are refused (:class:`DeclinationError`) rather than
extrapolated: a new WMM (WMM2030) must be installed then, by raising the pinned version.
"""

from __future__ import annotations

import datetime as _dt
import math
import warnings

from x6wd.core.errors import X6wdError

MODEL_NAME = "WMM2025"
"""The model this module evaluates (the coefficients shipped by ``wmm-calculator``)."""


class DeclinationError(X6wdError, ValueError):
    """Position or date outside what the magnetic model covers, or not a number."""


def decimal_year(date: _dt.date | _dt.datetime | float) -> float:
    """A date (UTC if a datetime; naive datetimes are taken as UTC) as a decimal year.

    The WMM convention: ``year + (day_of_year − 1 + fraction_of_day) / days_in_year``, so
    1 January 00:00 is ``year.0`` and 1 July 2025 is 2025.4959. A float is returned unchanged
    (it is already a decimal year).
    """
    if isinstance(date, bool):
        raise DeclinationError(f"date must be a date, datetime or decimal year, got {date!r}")
    if isinstance(date, (int, float)):
        y = float(date)
        if not math.isfinite(y):
            raise DeclinationError(f"decimal year must be finite, got {date!r}")
        return y
    if isinstance(date, _dt.datetime):
        if date.tzinfo is not None:
            date = date.astimezone(_dt.UTC).replace(tzinfo=None)
        day_s = date.hour * 3600.0 + date.minute * 60.0 + date.second + date.microsecond * 1e-6
        frac_day = day_s / 86400.0
        d = date.date()
    elif isinstance(date, _dt.date):
        frac_day = 0.0
        d = date
    else:
        raise DeclinationError(f"date must be a date, datetime or decimal year, got {date!r}")
    days_in_year = 366.0 if _is_leap(d.year) else 365.0
    return d.year + (d.timetuple().tm_yday - 1 + frac_day) / days_in_year


def _is_leap(year: int) -> bool:
    return year % 4 == 0 and (year % 100 != 0 or year % 400 == 0)


VALID_FROM_YEAR = decimal_year(_dt.date(2024, 11, 13))
"""First decimal year the package accepts (2024-11-13, the WMM2025 release date): 2024.8661."""
VALID_UNTIL_YEAR = 2030.0
"""Last decimal year the package accepts (2030-01-01 00:00)."""


def declination_deg(
    lat_deg: float, lon_deg: float, alt_m: float, date: _dt.date | _dt.datetime | float
) -> float:
    """Magnetic declination (degrees, east positive, in (−180, 180]) from WMM2025.

    ``lat_deg``, ``lon_deg``: geodetic WGS-84 latitude and longitude (degrees);
    ``alt_m``: height above the WGS-84 ellipsoid (metres, as GGA's altitude plus geoid
    separation; using the height above sea level instead changes D by far less than the
    model's own error of about 0.3-0.5 degrees); ``date``: a :class:`datetime.date`, a
    :class:`datetime.datetime` (UTC) or a decimal year (float).

    Raises :class:`DeclinationError` outside the model's validity (2024-11-13 to 2030-01-01)
    or for non-finite or out-of-range coordinates. Near the magnetic poles (the WMM
    "blackout zones") the value is still returned; the compass is useless there anyway.
    """
    try:
        lat, lon, alt = float(lat_deg), float(lon_deg), float(alt_m)
    except (TypeError, ValueError) as exc:
        raise DeclinationError(f"coordinates must be numbers: {exc}") from exc
    if not (math.isfinite(lat) and math.isfinite(lon) and math.isfinite(alt)):
        raise DeclinationError(
            f"coordinates must be finite, got {lat_deg!r}, {lon_deg!r}, {alt_m!r}"
        )
    if abs(lat) > 90.0 or abs(lon) > 360.0:
        raise DeclinationError(f"latitude/longitude out of range: {lat_deg!r}, {lon_deg!r}")
    year = decimal_year(date)
    if not (VALID_FROM_YEAR <= year <= VALID_UNTIL_YEAR):
        if isinstance(date, _dt.datetime):  # ISO, never the object's repr (a log's date)
            when = f"date {date.isoformat(timespec='seconds')} ({year:.4f})"
        elif isinstance(date, _dt.date):
            when = f"date {date.isoformat()} ({year:.4f})"
        else:
            when = f"year {year:.4f}"
        raise DeclinationError(f"{MODEL_NAME} covers 2024-11-13 to 2030-01-01; {when} is outside")
    from wmm import wmm_calc  # imported on first use (see the module docstring)

    model = wmm_calc()
    with warnings.catch_warnings():
        # the package warns near the magnetic poles (blackout zones); documented above
        warnings.simplefilter("ignore", UserWarning)
        try:
            model.setup_time(dyear=year)
            model.setup_env(lat, lon, alt, unit="m")
            dec = float(model.get_Bdec()[0])
        except ValueError as exc:
            raise DeclinationError(f"{MODEL_NAME}: {exc}") from exc
    if not math.isfinite(dec):
        raise DeclinationError(f"{MODEL_NAME} gave no declination at {lat}, {lon}")
    return dec
