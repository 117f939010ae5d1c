"""Typed records that cross module boundaries: device outputs, controller outputs.

Every record carries ``t_s``: the time the host received (or the simulator produced) it,
in seconds on one monotonic clock. The controller never reads a clock; it trusts ``t_s``.
"""

from __future__ import annotations

import enum
import math
from collections.abc import Mapping
from dataclasses import asdict, dataclass, field, replace
from datetime import datetime
from typing import Any


@dataclass(frozen=True, slots=True)
class GpsFix:
    """One receiver epoch assembled from GGA + RMC (+ GSA).

    ``valid`` comes from GGA quality > 0 / RMC status 'A', never from the coordinates.
    ``mode`` follows gpsd: 0 unknown, 1 no fix, 2 2D, 3 3D.
    """

    t_s: float
    utc: datetime | None = None
    lat_deg: float | None = None
    lon_deg: float | None = None
    alt_m: float | None = None  # above mean sea level
    quality: int = 0  # GGA fix quality 0..8
    sats_used: int | None = None
    hdop: float | None = None
    speed_mps: float | None = None
    course_deg: float | None = None  # None when the receiver leaves it empty (at rest)
    valid: bool = False
    mode: int = 1
    pdop: float | None = None
    vdop: float | None = None
    geoid_sep_m: float | None = None


@dataclass(frozen=True, slots=True)
class SatInfo:
    """One satellite in view (from GSV, ``used`` from GSA).

    ``prn`` is gpsd's number, unique across systems (GPS 1-32, SBAS 33-64 and 120-158,
    GLONASS 65-96, QZSS 193-199, Galileo 301-336, BeiDou 401-437), ``gnssid`` and ``svid``
    the system (0 GPS, 1 SBAS, 2 Galileo, 3 BeiDou, 4 IMES, 5 QZSS, 6 GLONASS) and the
    satellite's number within it, as gpsd's SKY reports them; None where the number is in
    no known range.
    """

    prn: int
    el_deg: float | None
    az_deg: float | None
    snr_dbhz: float | None
    used: bool = False
    gnssid: int | None = None
    svid: int | None = None


@dataclass(frozen=True, slots=True)
class GpsSky:
    """Satellites in view and dilution of precision for one epoch."""

    t_s: float
    satellites: tuple[SatInfo, ...] = ()
    pdop: float | None = None
    hdop: float | None = None
    vdop: float | None = None
    utc: datetime | None = None


@dataclass(frozen=True, slots=True)
class Attitude:
    """One CMPS10 sample. ``bearing_deg`` is MAGNETIC, 0 <= b < 360, as the device reports."""

    t_s: float
    bearing_deg: float
    pitch_deg: float
    roll_deg: float
    valid: bool = True


class NavState(enum.StrEnum):
    """Navigator state (the paper's state machine plus ARRIVED / MISSION_DONE / HOLD)."""

    IDLE = "IDLE"
    TURN_LEFT = "TURN_LEFT"
    TURN_RIGHT = "TURN_RIGHT"
    STRAIGHT = "STRAIGHT"
    ARRIVED = "ARRIVED"
    MISSION_DONE = "MISSION_DONE"
    HOLD = "HOLD"


class Mode(enum.StrEnum):
    """What the operator asked for."""

    IDLE = "IDLE"  # no mission running (loaded or not)
    RUNNING = "RUNNING"
    PAUSED = "PAUSED"
    MANUAL = "MANUAL"  # manual drive with a dead-man duration
    DONE = "DONE"  # mission completed


@dataclass(frozen=True, slots=True)
class MotorCommand:
    """Left/right drive in percent of full power, -100..100 (positive = forward)."""

    t_s: float
    left_pct: float
    right_pct: float
    reason: str = ""

    @property
    def is_stop(self) -> bool:
        return self.left_pct == 0.0 and self.right_pct == 0.0


@dataclass(frozen=True, slots=True)
class WheelOdometry:
    """Cumulative wheel-encoder counts per side at ``t_s`` (s, host receive time).

    ``left_counts`` / ``right_counts`` are counts since the link's first sample, already
    unwrapped from the board's 32-bit rollover (plain ints, any size, negative when driven
    backwards more than forwards): consumers difference consecutive records, so a lost
    record loses no distance. ``seq`` is the board's latch number (0..65535, wraps).
    """

    t_s: float
    left_counts: int
    right_counts: int
    seq: int


@dataclass(frozen=True, slots=True)
class StateChange:
    """The controller's mode or navigation state changed."""

    t_s: float
    old: str
    new: str
    reason: str = ""


@dataclass(frozen=True, slots=True)
class Telemetry:
    """Snapshot of the controller after an input; what clients and the recorder see."""

    t_s: float
    mode: Mode
    state: NavState
    hold_reason: str = ""
    waypoint_index: int | None = None  # 0-based index of the current target
    waypoint_count: int = 0
    lat_deg: float | None = None  # raw fix
    lon_deg: float | None = None
    filt_lat_deg: float | None = None  # [navigation] position_source (EKF by default)
    filt_lon_deg: float | None = None
    x_m: float | None = None  # projected filtered position
    y_m: float | None = None
    bearing_deg: float | None = None  # magnetic, as read
    heading_deg: float | None = None  # true, (-180, 180]
    pitch_deg: float | None = None
    roll_deg: float | None = None
    target_bearing_deg: float | None = None  # phi_i, (-180, 180]
    theta_deg: float | None = None  # course deviation, (-180, 180]
    distance_m: float | None = None  # to the current waypoint
    fix_quality: int = 0
    sats_used: int | None = None
    hdop: float | None = None
    fix_age_s: float | None = None
    attitude_age_s: float | None = None
    left_pct: float = 0.0
    right_pct: float = 0.0
    extra: dict[str, Any] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON-ready dict (enums as strings) as clients see it: the heading and the
        target bearing in x6wd's one convention, true degrees 0 <= h < 360 (docs/protocol.md,
        "Headings"); the controller works in (-180, 180]."""
        d = asdict(self)
        d["mode"] = str(self.mode)
        d["state"] = str(self.state)
        for key in ("heading_deg", "target_bearing_deg"):
            if d[key] is not None:
                d[key] = heading_360(d[key])
        return d

    def shown(self) -> Telemetry:
        """This snapshot with the heading and the target bearing as :meth:`to_dict` shows
        them, 0 <= h < 360 (itself when they are already): what the recorder writes."""
        h, b = self.heading_deg, self.target_bearing_deg
        if (h is None or _shown(h)) and (b is None or _shown(b)):
            return self
        return replace(
            self,
            heading_deg=None if h is None else heading_360(h),
            target_bearing_deg=None if b is None else heading_360(b),
        )


def _shown(h_deg: float) -> bool:
    """``h_deg`` is in [0, 360), and not -0.0 (which the JSON would write as such)."""
    return math.copysign(1.0, h_deg) > 0 and h_deg < 360.0


def heading_360(h_deg: float) -> float:
    """A heading (deg) as x6wd shows every one, 0 <= h < 360."""
    h = h_deg % 360.0
    return 0.0 if h >= 360.0 else h  # -1e-17 % 360 rounds to 360.0


ControllerOutput = MotorCommand | Telemetry | StateChange


class DeviceState(enum.StrEnum):
    """Health state of one device link (GPS, compass, motors).

    ``connected``: open, and for a sensor good data within its ``stale_s``. ``degraded``:
    open and the data still fresh, but I/O errors are being retried (it returns to
    ``connected`` after ``recover_s`` without errors). ``stale``: open, but no good data for
    longer than ``stale_s`` (sensors only). ``disconnected``: the link was lost (or never
    opened). ``reconnecting``: at least one attempt to reopen it has failed; retrying.
    """

    CONNECTED = "connected"
    DEGRADED = "degraded"
    STALE = "stale"
    DISCONNECTED = "disconnected"
    RECONNECTING = "reconnecting"


USABLE_STATES = frozenset({DeviceState.CONNECTED, DeviceState.DEGRADED})
"""States in which a device's data may be used (the controller does not hold for it)."""


@dataclass(frozen=True, slots=True)
class DeviceHealth:
    """One device's health at one instant; filled by its reader (``x6wd.core.health``).

    Times: ``*_t_s`` are seconds on the reader's monotonic clock, ``*_utc`` the same instants
    as ISO 8601 UTC wall-clock text ("" when there is none). ``errors`` counts every failed
    I/O attempt since start (open failures included), ``consecutive_errors`` those since the
    last good one; ``reconnects`` counts successful reopens after the first open.
    """

    device: str
    state: DeviceState
    since_t_s: float  # when ``state`` began
    since_utc: str = ""
    errors: int = 0
    consecutive_errors: int = 0
    last_error: str = ""
    last_error_t_s: float | None = None
    last_error_utc: str = ""
    reconnects: int = 0
    last_data_t_s: float | None = None  # last good data (sample, sentence, acknowledgement)
    next_attempt_t_s: float | None = None  # next reopen attempt while (re)connecting
    stale_s: float | None = None  # the staleness limit in use (None: not checked by time)
    # corrupt input counted and skipped since start, by kind (GPS: checksum_failures,
    # framing_errors, invalid_fields, skipped_bytes); empty for a device that has none
    corrupt: Mapping[str, int] = field(default_factory=dict)
    # why the device is in ``state`` now ("" when connected): the current fault, where
    # ``last_error`` may be an older one (an open failure while the open port is silent)
    reason: str = ""

    @property
    def ok(self) -> bool:
        """True when the device's data may be used (connected or degraded)."""
        return self.state in USABLE_STATES

    @property
    def connected(self) -> bool:
        """True while the link is open (connected, degraded or stale)."""
        return self.state not in (DeviceState.DISCONNECTED, DeviceState.RECONNECTING)

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON-ready dict (the state as its string)."""
        d = asdict(self)
        d["state"] = str(self.state)
        return d


@dataclass(frozen=True, slots=True)
class HealthEvent:
    """Something worth one log line happened to a device's health at ``t_s`` (s).

    ``kind`` is ``"transition"`` (``old`` != ``new``), ``"open_failed"`` (another failed
    reopen while already reconnecting: ``old`` == ``new``) or ``"corrupt"`` (corrupt input
    counted and skipped since the last such event: ``old`` == ``new``). ``message`` is the log text;
    ``health`` the snapshot right after the event.
    """

    t_s: float
    device: str
    kind: str
    old: DeviceState
    new: DeviceState
    message: str
    health: DeviceHealth
