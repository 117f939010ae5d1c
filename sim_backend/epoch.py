"""What the simulated receiver knows at one epoch: the GNSS model's output, NMEA's input."""

from __future__ import annotations

from dataclasses import dataclass
from datetime import datetime


@dataclass(frozen=True, slots=True)
class SimSat:
    """One satellite as the receiver would report it in GSV/GSA."""

    prn: int
    el_deg: float
    az_deg: float
    snr_dbhz: float | None  # None: tracked but no SNR (GSV leaves it empty)
    used: bool


@dataclass(frozen=True, slots=True)
class GnssEpoch:
    """The receiver's solution for one epoch (what the NEO-5 would print).

    ``valid`` False means no fix: NMEA then takes the receiver's real no-fix forms.
    ``speed_mps``/``course_deg`` are the receiver's velocity solution; course None at rest.
    ``hdop``/``pdop``/``vdop`` and ``satellites`` are the ones the model USED, so the
    reported accuracy matches the realised error.
    """

    t_s: float  # simulation time, seconds since scenario start
    utc: datetime
    valid: bool
    lat_deg: float
    lon_deg: float
    alt_m: float  # above mean sea level
    geoid_sep_m: float
    speed_mps: float
    course_deg: float | None
    quality: int  # GGA quality: 0 none, 1 GPS SPS
    mode: int  # GSA: 1 no fix, 2 2D, 3 3D
    hdop: float
    pdop: float
    vdop: float
    satellites: tuple[SimSat, ...]
