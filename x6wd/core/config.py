"""TOML settings validated into frozen dataclasses.

Every section is a frozen dataclass; a field's ``metadata`` may carry ``min``, ``max``
(inclusive) and ``choices``. Unknown keys, wrong types and out-of-range values raise
:class:`ConfigError` naming the dotted key, so a bad file stops startup with a reason.
"""

from __future__ import annotations

import dataclasses
import functools
import ipaddress
import math
import os
import re
import tomllib
import types
import typing
import urllib.parse
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Final, TypeVar
from urllib.parse import urlsplit

from x6wd.core.errors import ConfigError
from x6wd.core.files import read_bytes_bounded

T = TypeVar("T")


def _rng(lo: float | None = None, hi: float | None = None, **kw: Any) -> dict[str, Any]:
    return {"min": lo, "max": hi, **kw}


@dataclass(frozen=True)
class GpsConfig:
    url: str = "serial:///dev/ttyS0?baud=9600"
    stale_s: float = field(default=2.5, metadata=_rng(0.1, 60))
    # true: UBX CFG-RATE (rate_hz) and CFG-MSG after every open of the port, answers checked
    # (drivers.gps_io.ReceiverSetup); false: nothing is sent (a receiver set up in u-center)
    configure_receiver: bool = False
    # the receiver's navigation rate: asked of it (configure_receiver), else what it was set
    # to; the staleness limits are checked against it, and status compares the measured rate
    rate_hz: float = field(default=1.0, metadata=_rng(0.1, 10))

    def __post_init__(self) -> None:
        if self.configure_receiver and self.rate_hz > NEO5_MAX_RATE_HZ:
            raise ConfigError(
                f"gps.rate_hz: {self.rate_hz:g} Hz cannot be asked of the NEO-5 "
                f"(gps.configure_receiver = true): it navigates at most at "
                f"{NEO5_MAX_RATE_HZ:g} Hz"
            )


NEO5_MAX_RATE_HZ = 4.0
"""The u-blox NEO-5's fastest navigation rate (CFG-RATE 250 ms)."""
NEO5_BAUDS = (4800, 9600, 19200, 38400, 57600, 115200)
"""The baud rates a u-blox NEO-5's UART runs at (the simulated receiver's, a scenario's [gnss]
baud, alike): ``[sim] gps_baud``, and ``gps.url``'s baud where the daemon configures the
receiver (another receiver, not configured, may run at any standard rate)."""
NMEA_FIX_BUDGET_B = {"RMC": 75, "GGA": 77}
"""The most bytes each sentence a fix needs takes on the line (RMC with course, GGA): an
epoch's line (baud / 10 / rate bytes, 8N1) must carry at least these, or every fix arrives
later than the one before (``drivers.gps_io.NMEA_BUDGET_B`` adds GSA and GSV)."""


def check_gps_line(cfg: Config, url_baud: int | None = None) -> None:
    """With ``gps.configure_receiver = true`` the daemon asks the receiver for ``gps.rate_hz``
    on a line whose baud it knows: ``url_baud``, a ``serial://`` GPS's (the device registry
    takes the URL apart: the daemon passes it at start-up), or a ``sim://`` GPS's ``[sim]
    gps_baud`` when set (checked with the configuration). A ConfigError when the url's baud
    is not a NEO-5's (:data:`NEO5_BAUDS`), or when an epoch's line cannot carry RMC + GGA
    (:data:`NMEA_FIX_BUDGET_B`): each fix would queue behind the last and arrive ever later
    (4 Hz at 4800 baud: 120 bytes an epoch for 152, fixes ~2 s late, a GGA in 4 lost)."""
    gps = cfg.gps
    if not gps.configure_receiver:
        return  # the receiver's rate and sentences are not the daemon's: checked at run time
    if url_baud is not None:
        baud = url_baud
        key, fix = (
            f"gps.url's baud={baud}",
            "raise the baud rate (the receiver's, in u-center, and the url's)",
        )
        if baud not in NEO5_BAUDS:
            raise ConfigError(
                f"gps.url: baud={baud} with gps.configure_receiver = true: the NEO-5 the daemon "
                f"configures runs at {', '.join(map(str, NEO5_BAUDS))} baud; set the "
                "receiver's baud rate (u-center) and the url's baud to one of them, or "
                "configure_receiver = false for another receiver"
            )
    elif gps.url.strip().lower().startswith("sim:") and cfg.sim.gps_baud is not None:
        baud, key, fix = (
            cfg.sim.gps_baud,
            f"sim.gps_baud = {cfg.sim.gps_baud}",
            "raise sim.gps_baud",
        )
    else:
        return  # tcp://, replay://, or the scenario's baud: told at run time if it is short
    need_b = sum(NMEA_FIX_BUDGET_B.values())
    room_b = baud / 10.0 / gps.rate_hz
    if room_b < need_b:
        most_hz = math.floor(baud / 10.0 / need_b * 10.0) / 10.0
        raise ConfigError(
            f"gps.rate_hz: {gps.rate_hz:g} Hz on a {baud}-baud line ({key}) leaves "
            f"{room_b:.0f} bytes an epoch, under the {need_b} of RMC + GGA that every fix "
            "needs (gps.configure_receiver = true would ask for it): each fix would wait "
            "behind the last and arrive late, sentences lost; lower gps.rate_hz to "
            f"{most_hz:g} Hz or less, or {fix}"
        )


CMPS10_LAG_S: Final = 0.640 / 3.0
"""The CMPS10's heading filter as a first-order lag (s): ~640 ms to refresh fully, about 3
time constants (the simulator's compass uses the same figure)."""


@dataclass(frozen=True)
class CompassConfig:
    url: str = "i2c://1/0x60"
    rate_hz: float = field(default=20.0, metadata=_rng(1, 75))
    stale_s: float = field(default=0.5, metadata=_rng(0.01, 10))
    # East positive (true = magnetic + declination). None (the key absent): the World
    # Magnetic Model's value at the first dated fix (x6wd.nav.declination).
    declination_deg: float | None = field(default=None, metadata=_rng(-180, 180))


@dataclass(frozen=True)
class MotorsConfig:
    url: str = "log://"
    # the board's watchdog (ms): sent to it as W at start; the URL's watchdog_ms overrides
    watchdog_ms: int = field(default=500, metadata=_rng(50, 60_000))


@dataclass(frozen=True)
class OdometryConfig:
    """Wheel odometry (seed 003): the encoders' resolution, the calibrated wheel diameters
    and effective track, and the non-systematic error per side (variance of a side's travel
    per metre it rolls, m²/m = m). ``x6wd calibrate odometry`` writes this section."""

    counts_per_rev: int = field(default=1632, metadata=_rng(1, 1_000_000))
    left_diameter_m: float = field(default=0.120, metadata=_rng(0.01, 2.0))
    right_diameter_m: float = field(default=0.120, metadata=_rng(0.01, 2.0))
    track_m: float = field(default=0.245, metadata=_rng(0.05, 10.0))
    k_left_m: float = field(default=1e-3, metadata=_rng(0.0, 0.1))
    k_right_m: float = field(default=1e-3, metadata=_rng(0.0, 0.1))
    # heading variance per radian turned (rad²/rad): the skid-steer slip the encoders miss
    k_slip_rad: float = field(default=0.02, metadata=_rng(0.0, 1.0))


@dataclass(frozen=True)
class GnssNoiseConfig:
    """The GPS error model of seed 003 (eq. 12): a fix's standard deviation PER HORIZONTAL
    AXIS is ``HDOP·sqrt(re_m² + ase_m² + LCE(position)²)`` (m). ``re_m`` the receiver error
    (the white part), ``ase_m`` the atmospheric and satellite error (the slow part, a
    Gauss-Markov process of ``correlation_s``; 0: white, as in the paper); the LCE map in the
    local tangent plane at ``lce_origin_*``: ``lce_cells`` rows ``[east index, north index,
    LCE m]`` for the cell ``floor(east / lce_cell_m), floor(north / lce_cell_m)``, and
    ``lce_default_m`` everywhere else. ``x6wd calibrate gnss`` writes this section;
    :meth:`lce_m_at` is the lookup :class:`x6wd.nav.estimator.GpsParams` takes as ``lce_m``."""

    re_m: float = field(default=1.0, metadata=_rng(0.0, 100.0))
    ase_m: float = field(default=1.5, metadata=_rng(0.0, 100.0))
    correlation_s: float = field(default=120.0, metadata=_rng(0.0, 86400.0))
    # the map's origin: required with lce_cells (a map at 0 N 0 E would never be looked up)
    lce_origin_lat_deg: float | None = field(default=None, metadata=_rng(-85.0, 85.0))
    lce_origin_lon_deg: float | None = field(default=None, metadata=_rng(-180.0, 180.0))
    lce_cell_m: float = field(default=10.0, metadata=_rng(0.1, 10000.0))
    lce_default_m: float = field(default=0.0, metadata=_rng(0.0, 1000.0))
    lce_cells: tuple[tuple[float, ...], ...] = ()

    def __post_init__(self) -> None:
        if self.re_m <= 0.0:
            raise ConfigError(f"gnss_noise.re_m: must be > 0 (white noise), got {self.re_m}")
        if self.lce_cells:
            for key in ("lce_origin_lat_deg", "lce_origin_lon_deg"):
                if getattr(self, key) is None:
                    raise ConfigError(
                        f"gnss_noise.{key}: required with lce_cells (the map's origin, as "
                        "x6wd calibrate gnss writes it)"
                    )
        seen: set[tuple[int, int]] = set()
        for k, cell in enumerate(self.lce_cells):
            key = f"gnss_noise.lce_cells[{k}]"
            if len(cell) != 3:
                raise ConfigError(f"{key}: expected [east index, north index, LCE m], got {cell}")
            ie, jn, lce = cell
            if ie != int(ie) or jn != int(jn) or max(abs(ie), abs(jn)) > 1_000_000:
                raise ConfigError(f"{key}: cell indices must be integers, got {ie}, {jn}")
            if not 0.0 <= lce <= 1000.0:
                raise ConfigError(f"{key}: LCE must be in 0..1000 m, got {lce}")
            if (int(ie), int(jn)) in seen:
                raise ConfigError(f"{key}: cell [{int(ie)}, {int(jn)}] given twice")
            seen.add((int(ie), int(jn)))

    @functools.cached_property
    def _lce_lookup(self) -> dict[tuple[int, int], float]:
        return {(int(c[0]), int(c[1])): float(c[2]) for c in self.lce_cells}

    def lce_m_at(self, east_m: float, north_m: float) -> float:
        """LCE (m) at a point of the map's plane (east/north m of ``lce_origin_*``)."""
        if not self.lce_cells or not (math.isfinite(east_m) and math.isfinite(north_m)):
            return self.lce_default_m
        key = (math.floor(east_m / self.lce_cell_m), math.floor(north_m / self.lce_cell_m))
        return self._lce_lookup.get(key, self.lce_default_m)


@dataclass(frozen=True)
class NavigationConfig:
    delta_phi_deg: float = field(default=10.0, metadata=_rng(0.1, 90))
    # Arrival windows (eq. 7). pivot_arc also arrives on passing the waypoint's line, so a
    # tight window costs no circling; with "paper" steering use ~3 m (the GPS's accuracy).
    delta_x_m: float = field(default=0.25, metadata=_rng(0.01, 1000))
    delta_y_m: float = field(default=0.25, metadata=_rng(0.01, 1000))
    # "ekf": the estimator (x6wd.nav.position); "constellation": the paper's filter over
    # filter_n fixes; "raw": the latest fix.
    position_source: str = field(
        default="ekf", metadata={"choices": ("ekf", "constellation", "raw")}
    )
    filter_n: int = field(default=20, metadata=_rng(3, 1000))
    filter_hysteresis: bool = False
    projection: str = field(
        default="local_tangent_plane",
        metadata={"choices": ("two_radius", "local_tangent_plane")},
    )
    cruise_pct: float = field(default=60.0, metadata=_rng(0, 100))
    turn_pct: float = field(default=40.0, metadata=_rng(0, 100))
    # Steering (x6wd.nav.steering, docs/navigation.md "Steering and arrival"): "paper" is the
    # paper's bang-bang spin-or-straight with eq. 7 in the projection's metres, unchanged;
    # "pivot_arc" pivots only beyond pivot_angle_deg (until under pivot_resume_deg) and
    # otherwise follows the segment by pure pursuit, arriving by eq. 7 in true metres or by
    # passing the waypoint's perpendicular line. The keys below matter to pivot_arc only.
    steering: str = field(default="pivot_arc", metadata={"choices": ("paper", "pivot_arc")})
    pivot_angle_deg: float = field(default=60.0, metadata=_rng(1, 180))
    pivot_resume_deg: float = field(default=10.0, metadata=_rng(0, 180))
    lookahead_m: float = field(default=15.0, metadata=_rng(0.5, 100))
    approach_m: float = field(default=10.0, metadata=_rng(0, 100))
    min_speed_pct: float = field(default=15.0, metadata=_rng(0, 100))
    # Effective track for percent commands (m): curvature k -> left = s(1 + k·T/2),
    # right = s(1 - k·T/2). T = 2·v_full / w_full: v_full the speed (m/s) at +100/+100 %, w_full
    # the pivot rate (rad/s) at +100/-100 %. The default is the simulator's vehicle
    # (14 km/h, 90 deg/s: 4.95 m); calibrate it on the robot.
    steer_track_m: float = field(default=4.95, metadata=_rng(0.05, 100))
    # ground speed at +100/+100 % (m/s); with steer_track_m it predicts the motion from the
    # commands when no encoder counts arrive (the simulator's robot: 14 km/h)
    full_speed_mps: float = field(default=3.888, metadata=_rng(0.05, 20))
    # the EKF's prior one-sigma (deg) of a constant compass offset (mounting, a declination
    # off) that it learns from the GPS track; 0: the compass is taken as it reads
    compass_offset_sigma_deg: float = field(default=10.0, metadata=_rng(0, 90))
    # ... and of each coefficient of a heading-dependent deviation (iron near the compass:
    # once and twice per turn); 0: none is learnt
    compass_deviation_sigma_deg: float = field(default=2.0, metadata=_rng(0, 45))
    # the compass's heading filter as a first-order lag (s): the EKF reads its heading as
    # that far behind in a turn. The CMPS10 refreshes fully in ~640 ms (3 time constants);
    # a compass that smooths more must say so (2 s taken as 0.21 s: the robot circled)
    compass_lag_s: float = field(default=CMPS10_LAG_S, metadata=_rng(0, 10))
    # the EKF's position error radius (m, 3 sigma per axis) beyond which no waypoint inside it
    # is taken as reached: the robot holds until the fixes improve (0: off; docs/navigation.md)
    arrival_max_error_m: float = field(default=30.0, metadata=_rng(0, 100_000))

    @classmethod
    def paper(cls, **overrides: Any) -> NavigationConfig:
        """The paper's navigation as published: the Constellation filter (N = 20), the
        two-radius projection, bang-bang steering and 3 m arrival windows; ``overrides``
        change single keys. (The defaults are the robot's: EKF, pivot_arc, true metres.)"""
        keys: dict[str, Any] = {
            "position_source": "constellation",
            "filter_n": 20,
            "projection": "two_radius",
            "steering": "paper",
            "delta_x_m": 3.0,
            "delta_y_m": 3.0,
        }
        keys.update(overrides)
        return cls(**keys)

    def __post_init__(self) -> None:
        if self.pivot_resume_deg <= 0:  # a pivot ends once |α| is strictly under it: never
            raise ConfigError(
                f"navigation.pivot_resume_deg: must be > 0 (a pivot stops once the heading "
                f"error is under it; at 0 it never would), got {self.pivot_resume_deg}"
            )
        if self.pivot_resume_deg >= self.pivot_angle_deg:
            raise ConfigError(
                f"navigation.pivot_resume_deg: must be < pivot_angle_deg "
                f"({self.pivot_angle_deg}), got {self.pivot_resume_deg}"
            )


@dataclass(frozen=True)
class SafetyConfig:
    fix_stale_s: float = field(default=2.5, metadata=_rng(0.1, 60))
    attitude_stale_s: float = field(default=0.5, metadata=_rng(0.01, 10))
    manual_max_s: float = field(default=5.0, metadata=_rng(0.1, 60))
    # with the EKF and the wheel encoders reporting, drive on without a valid fix for this
    # much wheel travel (m) since the last one (0: hold at once, as the paper's robot)
    gps_outage_max_m: float = field(default=20.0, metadata=_rng(0, 1000))
    geofence_radius_m: float = field(default=1000.0, metadata=_rng(1, 1e6))
    # [lat_deg, lon_deg]; empty: the geofence is centred on the first valid fix
    geofence_center: tuple[float, ...] = ()

    def __post_init__(self) -> None:
        # here, not only in the daemon's preflight: x6wd sim, scenarios and sweeps build this
        # too (an outside audit: [95, 0] drove a whole run, then the fence refused it)
        gc = self.geofence_center
        shown = "[" + ", ".join(f"{v:g}" for v in gc) + "]"  # as the TOML wrote it
        if len(gc) not in (0, 2):
            raise ConfigError(
                f"safety.geofence_center: expected [] or [lat_deg, lon_deg], got {shown}"
            )
        if len(gc) == 2 and not -90.0 <= gc[0] <= 90.0:
            raise ConfigError(f"safety.geofence_center: latitude {gc[0]:g} outside [-90, 90] deg")
        if len(gc) == 2 and not -180.0 <= gc[1] <= 180.0:
            raise ConfigError(
                f"safety.geofence_center: longitude {gc[1]:g} outside [-180, 180] deg"
            )


FAILSAFE_ACTIONS = ("hold", "return")


@dataclass(frozen=True)
class FailsafeConfig:
    """What a running mission does when something goes wrong (docs/navigation.md,
    "Failsafes"). Every action stops the motors first. "hold": the mission pauses (the
    operator resumes, returns or stops it); "return": the robot drives back to where the
    mission started (its launch point) and the mission ends there.

    Conditions: the robot left the geofence (``geofence_action``); no operator request for
    ``operator_timeout_s`` after an operator started the mission over the network (0: off,
    as for a robot sent on its way and left alone); stuck: driving forward at
    ``stuck_min_pct`` or more for ``stuck_s`` while neither the wheels nor the GPS moved
    ``stuck_min_m``; a sensor stale or down for ``sensor_timeout_s`` (the robot already
    holds from the first moment; the action is what follows); off course: a fix
    ``off_course_m`` farther from the target than the leg's closest, or the fixes' course
    ``heading_check_deg`` from the heading steered by (``off_course_action``); the EKF
    refused half or more of the compass readings over ``compass_refused_s`` (0: off;
    always a pause: a return needs the heading it cannot trust); the position jumped
    ``gps_jump_m`` or more at once: the EKF moved to fixes it had refused until they agreed
    (a receiver that came back somewhere else, another device on the port, a robot carried;
    0: off; always a pause: the operator looks before the robot drives on either
    position); the robot held ``position_timeout_s`` with its next waypoint inside the
    EKF's error radius (``navigation.arrival_max_error_m``: the fixes too poor to tell
    whether it is there; 0: wait for them; always a pause: a return needs that position);
    the robot drove ``progress_timeout_s`` in all without coming 2 m nearer its waypoint
    (swinging or circling about it; 0: off; always a pause: a return steers the same way)."""

    geofence_action: str = field(default="hold", metadata={"choices": FAILSAFE_ACTIONS})
    operator_timeout_s: float = field(default=0.0, metadata=_rng(0, 3600))
    operator_action: str = field(default="return", metadata={"choices": FAILSAFE_ACTIONS})
    stuck_s: float = field(default=10.0, metadata=_rng(0, 600))  # 0: off
    stuck_min_m: float = field(default=2.0, metadata=_rng(0.1, 100))
    stuck_min_pct: float = field(default=10.0, metadata=_rng(1, 100))
    stuck_action: str = field(default="hold", metadata={"choices": FAILSAFE_ACTIONS})
    sensor_timeout_s: float = field(default=30.0, metadata=_rng(0, 3600))  # 0: off
    sensor_action: str = field(default="hold", metadata={"choices": FAILSAFE_ACTIONS})
    # off course, from the fixes alone (x6wd/nav/course_watch.py); 0: that check off
    off_course_m: float = field(default=25.0, metadata=_rng(0, 10_000))
    heading_check_deg: float = field(default=45.0, metadata=_rng(0, 180))
    off_course_action: str = field(default="hold", metadata={"choices": FAILSAFE_ACTIONS})
    # compass untrusted, from the EKF's refusals (x6wd/nav/compass_trust.py); 0: off
    compass_refused_s: float = field(default=10.0, metadata=_rng(0, 600))
    # the EKF's position reset by this much or more at once (m); 0: off
    gps_jump_m: float = field(default=25.0, metadata=_rng(0, 100_000))
    # held this long (s) for a position too uncertain to tell a waypoint is reached; 0: off
    position_timeout_s: float = field(default=120.0, metadata=_rng(0, 3600))
    # driving this long (s) in all without coming 2 m nearer the waypoint; 0: off
    progress_timeout_s: float = field(default=60.0, metadata=_rng(0, 3600))


@dataclass(frozen=True)
class ServerConfig:
    enabled: bool = True
    bind: str = "127.0.0.1"
    # 0: any free port, logged at start-up (for tests: the daemon tests' TOML files use it)
    port: int = field(default=7601, metadata=_rng(0, 65535))
    token_file: str = ""  # empty: no authentication required (only on loopback binds)
    tls_cert: str = ""
    tls_key: str = ""
    # Listening beyond loopback needs TLS (check_plaintext); true lets an owner on an isolated
    # network listen there without it: the token and every command then travel in clear text
    # (logged at start-up, and in status as plaintext_beyond_loopback)
    allow_plaintext: bool = False
    max_clients: int = field(default=16, metadata=_rng(1, 10000))
    max_line_bytes: int = field(default=65536, metadata=_rng(256, 16 * 1024 * 1024))
    rate_per_s: float = field(default=50.0, metadata=_rng(0.1, 1e6))
    queue_len: int = field(default=256, metadata=_rng(1, 1_000_000))
    # per-client input budget: a flooding client is read no faster than this (TCP pushes back)
    input_bytes_per_s: int = field(default=65536, metadata=_rng(1024, 1 << 30))
    # Lock-out protection. Connections that have not authenticated yet (without a token: not
    # yet sent one valid request) live in their own pool of ``max_pending``; when it is full
    # the oldest is closed, so they never take an operator's slot among ``max_clients``.
    max_pending: int = field(default=32, metadata=_rng(1, 10000))
    auth_timeout_s: float = field(default=5.0, metadata=_rng(0.1, 300))
    # a session that is not watching and sends nothing for this long is closed
    idle_timeout_s: float = field(default=300.0, metadata=_rng(1, 86400))
    # a client whose socket has not drained for this long (it never reads) is closed
    slow_client_s: float = field(default=10.0, metadata=_rng(0.1, 3600))
    # failed authentication: the connection waits this long before its next line (doubling
    # per failure) and is closed after ``max_auth_failures``
    auth_fail_delay_s: float = field(default=1.0, metadata=_rng(0, 60))
    max_auth_failures: int = field(default=3, metadata=_rng(1, 100))


HOSTNAME_PATTERN = (
    r"[a-z0-9_](?:[a-z0-9_-]{0,61}[a-z0-9_])?(?:\.[a-z0-9_](?:[a-z0-9_-]{0,61}[a-z0-9_])?)*"
)
"""A host name as the console takes it in a ``Host`` and in ``[console] hostnames`` (ASCII,
case-insensitive): dot-separated labels of letters, digits, ``-`` (not first or last) and
``_`` (which DNS names lack but host names have: ``socket.gethostname()`` may say
``my_robot``); a dotted IPv4 address is one too."""


@dataclass(frozen=True)
class ConsoleConfig:
    """The operator's web console (x6wd.app.console): the control server's token, TLS and
    commands over a WebSocket, and the page that uses them."""

    enabled: bool = False  # opt-in: one more listening port that can drive the robot
    bind: str = "127.0.0.1"
    # 0: any free port, logged at start-up (for tests)
    port: int = field(default=7602, metadata=_rng(0, 65535))
    watch_only: bool = False  # every command that acts (stop included) refused by the server
    # map tiles under the local frame: an http(s) XYZ URL with {z} {x} {y}; empty: no tiles
    tile_url: str = ""
    # manual drive from the page: each drive command lasts this long and the page repeats it
    # while the operator holds a key; a closed page or link stops the motors (the dead-man)
    deadman_s: float = field(default=0.5, metadata=_rng(0.1, 60))
    max_clients: int = field(default=8, metadata=_rng(1, 1000))
    max_message_bytes: int = field(default=1 << 20, metadata=_rng(1024, 64 << 20))
    queue_len: int = field(default=64, metadata=_rng(1, 100_000))  # events per page
    # names (besides an IP address, localhost and this machine's hostname[.local]) by which
    # the operator opens the page: any other Host is refused, so that a site whose name is
    # made to point here (DNS rebinding) cannot use the console from the operator's browser
    hostnames: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        for name in self.hostnames:
            if len(name) > 253 or not re.fullmatch(HOSTNAME_PATTERN, name, re.ASCII | re.I):
                raise ConfigError(
                    f"console.hostnames: {name!r} is not a host name (labels of letters, "
                    "digits, '-' and '_' joined by dots; no port, no scheme, no trailing dot)"
                )
        url = self.tile_url
        if url:
            parts = urlsplit(url)
            if parts.scheme not in ("http", "https") or not parts.netloc:
                raise ConfigError(
                    f"console.tile_url: must be an http:// or https:// URL, got {url!r}"
                )
            missing = [p for p in ("{z}", "{x}", "{y}") if p not in url]
            if missing:
                raise ConfigError(
                    f"console.tile_url: must hold {{z}}, {{x}} and {{y}} (XYZ tiles); "
                    f"{', '.join(missing)} missing in {url!r}"
                )


@dataclass(frozen=True)
class GpsdConfig:
    enabled: bool = True
    bind: str = "127.0.0.1"
    # 0: any free port, logged at start-up (for tests)
    port: int = field(default=2947, metadata=_rng(0, 65535))
    max_clients: int = field(default=32, metadata=_rng(1, 10000))
    queue_len: int = field(default=64, metadata=_rng(1, 1_000_000))
    # a client that is not watching and sends no command for this long is closed
    idle_timeout_s: float = field(default=60.0, metadata=_rng(1, 86400))
    # a watcher whose socket has not drained for this long (it never reads) is closed
    slow_client_s: float = field(default=10.0, metadata=_rng(0.1, 3600))
    # ATT (the compass) to each JSON watcher at most this often (Hz), the newest reading each
    # time; 0: no ATT. The compass's every reading (compass.rate_hz, 20) would be ~90 % of the
    # stream and leave a client handling ~10 reports/s ever further behind (gpsd clients
    # cannot turn ATT off); the default is about the GPS's rate. >= compass.rate_hz: all.
    attitude_rate_hz: float = field(default=2.0, metadata=_rng(0, 75))


@dataclass(frozen=True)
class RecorderConfig:
    enabled: bool = True
    dir: str = "/var/lib/x6wd"
    # Retention, sized for an SD card: a recording is split into parts of ``max_file_mb``;
    # the oldest recordings in ``dir`` are deleted while all of them together exceed
    # ``max_total_mb`` or the file system has less than ``min_free_mb`` free.
    max_file_mb: float = field(default=64.0, metadata=_rng(0.01, 1e6))
    max_total_mb: float = field(default=2048.0, metadata=_rng(0.1, 1e9))
    min_free_mb: float = field(default=256.0, metadata=_rng(0, 1e9))


@dataclass(frozen=True)
class StartupConfig:
    """How ``x6wd run`` starts (the daemon's start-up check, docs/install.md)."""

    # Started by systemd (NOTIFY_SOCKET set), a device node that does not exist (a serial
    # path, /dev/i2c-N), or one this user may not open yet, is waited for this long (s)
    # before it is a configuration error (exit 2, which the unit does not restart): a USB
    # adapter udev has not enumerated (or given its group) yet at boot, a native-USB board
    # re-enumerating after a reset. 0, or started by hand: exit 2 at once.
    device_wait_s: float = field(default=10.0, metadata=_rng(0, 300))


@dataclass(frozen=True)
class SimConfig:
    """Hardware-in-the-loop: the simulated world behind the sim:// device URLs."""

    # a relative path: in the config file's folder, then in PACKAGED_CONFIG_DIR, then in the
    # working directory (scenario_candidates)
    scenario: str = ""
    seed: int | None = field(default=None, metadata=_rng(0, 2**63 - 1))
    # Overrides of the scenario's own values; absent (None) means "as the scenario says".
    origin_lat_deg: float | None = field(default=None, metadata=_rng(-85, 85))
    origin_lon_deg: float | None = field(default=None, metadata=_rng(-180, 180))
    origin_alt_m: float | None = field(default=None, metadata=_rng(-500, 9000))
    start_heading_deg: float | None = field(default=None, metadata=_rng(0, 360))
    gps_rate_hz: float | None = field(default=None, metadata=_rng(1, 4))
    # one of a NEO-5's (NEO5_BAUDS), as the scenario's [gnss] baud
    gps_baud: int | None = field(default=None, metadata={"choices": NEO5_BAUDS})
    physics_hz: float = field(default=50.0, metadata=_rng(5, 1000))
    v_max_mps: float | None = field(default=None, metadata=_rng(0.1, 3.888))
    motor_tau_s: float | None = field(default=None, metadata=_rng(0, 10))
    motor_watchdog_ms: int = field(default=500, metadata=_rng(50, 60000))
    # start position in the scenario's local frame (m); unset: the scenario's [vehicle] one
    start_east_m: float | None = field(default=None, metadata=_rng(-1e5, 1e5))
    start_north_m: float | None = field(default=None, metadata=_rng(-1e5, 1e5))


@dataclass(frozen=True)
class Config:
    gps: GpsConfig = field(default_factory=GpsConfig)
    compass: CompassConfig = field(default_factory=CompassConfig)
    motors: MotorsConfig = field(default_factory=MotorsConfig)
    odometry: OdometryConfig = field(default_factory=OdometryConfig)
    gnss_noise: GnssNoiseConfig = field(default_factory=GnssNoiseConfig)
    navigation: NavigationConfig = field(default_factory=NavigationConfig)
    safety: SafetyConfig = field(default_factory=SafetyConfig)
    failsafe: FailsafeConfig = field(default_factory=FailsafeConfig)
    server: ServerConfig = field(default_factory=ServerConfig)
    console: ConsoleConfig = field(default_factory=ConsoleConfig)
    gpsd: GpsdConfig = field(default_factory=GpsdConfig)
    recorder: RecorderConfig = field(default_factory=RecorderConfig)
    startup: StartupConfig = field(default_factory=StartupConfig)
    sim: SimConfig = field(default_factory=SimConfig)

    def __post_init__(self) -> None:
        check_drive_vs_stuck(self.navigation, self.failsafe)
        gps_rate = _gps_rate(self)
        check_stale_vs_rate("safety.fix_stale_s", self.safety.fix_stale_s, *gps_rate)
        check_stale_vs_rate("gps.stale_s", self.gps.stale_s, *gps_rate)  # the reader's own
        check_gps_line(self)
        rate_hz = self.compass.rate_hz
        compass_rate = (rate_hz, f"compass.rate_hz = {rate_hz:g} Hz")
        check_stale_vs_rate("safety.attitude_stale_s", self.safety.attitude_stale_s, *compass_rate)
        check_stale_vs_rate("compass.stale_s", self.compass.stale_s, *compass_rate)


def check_drive_vs_stuck(nav: NavigationConfig, failsafe: FailsafeConfig) -> None:
    """The mission's drives must move the robot: cruise and turn above 0 %, and, with the
    stuck failsafe on (``stuck_s`` > 0), cruise, turn and the approach's ``min_speed_pct`` at
    ``failsafe.stuck_min_pct`` or more: below it a robot that does not move is never judged
    stuck (a cruise of 0 % sat in RUNNING for good, unnoticed). And ``min_speed_pct`` not over
    ``cruise_pct``: the approach speed is clamped to at most cruise, so a floor above it never
    slowed the robot for a waypoint (an outside audit). Raises :class:`ConfigError` naming the
    key."""
    for key in ("cruise_pct", "turn_pct"):
        if getattr(nav, key) <= 0:
            raise ConfigError(f"navigation.{key}: must be > 0 (the robot would not move)")
    if failsafe.stuck_s > 0:
        for key in ("cruise_pct", "turn_pct", "min_speed_pct"):
            pct = getattr(nav, key)
            if pct < failsafe.stuck_min_pct:
                raise ConfigError(
                    f"navigation.{key}: must be >= failsafe.stuck_min_pct "
                    f"({failsafe.stuck_min_pct:g} %) while the stuck check is on "
                    "(failsafe.stuck_s > 0), else a robot that does not move at that drive is "
                    f"never found stuck; got {pct:g}"
                )
    # last, so that a cruise under stuck_min_pct is named as that (the key to change first);
    # whatever the steering: a "paper" config switched to pivot_arc keeps its speeds
    if nav.min_speed_pct > nav.cruise_pct:
        raise ConfigError(
            f"navigation.min_speed_pct: {nav.min_speed_pct:g} % is over navigation.cruise_pct "
            f"({nav.cruise_pct:g} %): the robot would never slow down for a waypoint; make "
            "min_speed_pct <= cruise_pct"
        )


STALE_MIN_PERIODS = 2.5
"""A staleness limit ([safety] fix_stale_s, attitude_stale_s) must span at least this many
of its sensor's sample periods. With one sample lost the newest is two periods old when the
next arrives; the half period more covers that arrival's jitter and the control loop's tick.
Shorter, a single late sample holds the robot, and under one period every sample does (an
outside audit: attitude_stale_s 0.01 s against a 20 Hz compass flipped HOLD/STRAIGHT 179 times
in 5 s, the motor board getting drive and stop in turn). The shipped 2.5 s against a 1 Hz GPS
is the tightest this allows."""


def check_stale_vs_rate(stale_key: str, stale_s: float, rate_hz: float, rate_what: str) -> None:
    """A ConfigError naming ``stale_key`` when ``stale_s`` is under :data:`STALE_MIN_PERIODS`
    periods of a sensor sampled at ``rate_hz`` (``rate_what``: where that rate comes from, for
    the message)."""
    if stale_s * rate_hz >= STALE_MIN_PERIODS - 1e-9:  # 1e-9: 0.125 s at 20 Hz is allowed
        return
    period_s = 1.0 / rate_hz
    least_s = math.ceil(STALE_MIN_PERIODS * period_s * 1000.0) / 1000.0  # enterable as shown
    raise ConfigError(
        f"{stale_key}: {stale_s:g} s is under {STALE_MIN_PERIODS:g} sample periods of "
        f"{rate_what} (a sample every {period_s:g} s), so a single late sample would stop the "
        f"robot; make it at least {least_s:g} s"
    )


SIM_GPS_SLOWEST_HZ = 1.0
"""The slowest simulated receiver (a scenario's [gnss] rate_hz, 1..4 Hz; [sim] gps_rate_hz
likewise): the rate a sim:// GPS is checked at when [sim] gps_rate_hz leaves it to the
scenario, which is not read yet when the configuration is."""


def _gps_rate(cfg: Config) -> tuple[float, str]:
    """The rate (Hz) the fixes arrive at, and where it comes from (for the message): with a
    sim:// GPS not configured by the daemon ``[sim] gps_rate_hz`` (unset: the scenario's,
    taken at :data:`SIM_GPS_SLOWEST_HZ`), else ``[gps] rate_hz`` (what the gpsd port's
    DEVICE reports too; a replay:// file plays at its own times, and is checked against it
    all the same)."""
    if cfg.gps.configure_receiver or not cfg.gps.url.strip().lower().startswith("sim:"):
        # (a simulated receiver takes CFG-RATE as the real one: sim_backend.hil)
        return cfg.gps.rate_hz, f"gps.rate_hz = {cfg.gps.rate_hz:g} Hz"
    if cfg.sim.gps_rate_hz is None:
        return SIM_GPS_SLOWEST_HZ, (
            f"the simulated GPS at {SIM_GPS_SLOWEST_HZ:g} Hz (sim.gps_rate_hz unset: the "
            "scenario's rate, taken at its slowest)"
        )
    return cfg.sim.gps_rate_hz, f"sim.gps_rate_hz = {cfg.sim.gps_rate_hz:g} Hz"


def check_value(key: str, value: Any, tp: Any, meta: Any) -> Any:
    """``value`` checked against type ``tp`` (a number real and finite, not a bool; an int; a
    str; a list or tuple of them; ``meta`` a field's range metadata), converted as the
    configuration stores it; a ConfigError naming ``key`` otherwise. Every configuration key
    goes through it, and so do the simulator's effect parameters."""
    origin = typing.get_origin(tp)
    if origin in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        if len(args) != 1:
            raise TypeError(f"unsupported config type {tp}")  # programming error
        tp = args[0]
    if tp is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{key}: expected true or false, got {value!r}")
    elif tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{key}: expected an integer, got {value!r}")
    elif tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{key}: expected a number, got {value!r}")
        value = float(value)
        if not math.isfinite(value):
            raise ConfigError(f"{key}: must be finite, got {value!r}")
    elif tp is str:
        if not isinstance(value, str):
            raise ConfigError(f"{key}: expected a string, got {value!r}")
        if "\x00" in value:  # no path, URL or name may hold one; the OS refuses it late
            raise ConfigError(f"{key}: must not contain a NUL character")
    elif typing.get_origin(tp) in (tuple, list):
        if not isinstance(value, list):
            raise ConfigError(f"{key}: expected a list, got {value!r}")
        (item_tp, *_rest) = typing.get_args(tp) or (Any,)
        if item_tp is not Any and item_tp is not Ellipsis:
            value = [check_value(f"{key}[{i}]", v, item_tp, {}) for i, v in enumerate(value)]
        value = tuple(value)
    lo, hi = meta.get("min"), meta.get("max")
    if lo is not None and value < lo:
        raise ConfigError(f"{key}: must be >= {lo}, got {value!r}")
    if hi is not None and value > hi:
        raise ConfigError(f"{key}: must be <= {hi}, got {value!r}")
    choices = meta.get("choices")
    if choices is not None and value not in choices:
        raise ConfigError(f"{key}: must be one of {', '.join(map(str, choices))}, got {value!r}")
    return value


def build(cls: type[T], data: Any, prefix: str = "") -> T:
    """Validate a TOML table into the frozen dataclass ``cls``; errors name the dotted key."""
    where = prefix.rstrip(".") or "top level"
    if not isinstance(data, dict):
        raise ConfigError(f"{where}: expected a table, got {data!r}")
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls)}  # type: ignore[arg-type]
    unknown = sorted(set(data) - set(fields))
    if unknown:
        raise ConfigError(
            f"{prefix}{unknown[0]}: unknown key (valid keys in {where}: {', '.join(fields)})"
        )
    kwargs: dict[str, Any] = {}
    for name, value in data.items():
        tp = hints[name]
        key = f"{prefix}{name}"
        if dataclasses.is_dataclass(tp):
            kwargs[name] = build(tp, value, key + ".")  # type: ignore[arg-type]
        else:
            kwargs[name] = check_value(key, value, tp, fields[name].metadata)
    return cls(**kwargs)


def _packaged_config_dir() -> Path:
    """The shipped ``config/`` folder: ``x6wd/_config`` in an installed wheel (pyproject.toml
    force-includes the repository's config/ there), else the source tree's ``config/`` (a
    checkout or an editable install, where the repository's folder is the one to edit)."""
    package = Path(__file__).resolve().parents[1]  # .../x6wd
    in_wheel = package / "_config"
    return in_wheel if in_wheel.is_dir() else package.parent / "config"


PACKAGED_CONFIG_DIR = _packaged_config_dir()
"""The ``config/`` folder that ships with x6wd (x6wd.toml, hil.toml, scenarios/, sweeps/): the
default scenarios of ``x6wd gap`` and of hardware in the loop, and the second place a relative
``[sim] scenario`` is looked for (``sim_backend.hil.CONFIG_DIR``, the same folder)."""


def scenario_candidates(scenario: str, config_dir: Path | None) -> list[Path]:
    """Where the ``[sim] scenario`` of a configuration file in ``config_dir`` (None: a
    configuration not read from a file) is looked for, in order: an absolute path (``~``
    expanded) as it is; a relative one in ``config_dir``, then in
    :data:`PACKAGED_CONFIG_DIR`, then in the working directory."""
    path = Path(scenario).expanduser()
    if path.is_absolute():
        return [path]
    dirs = [PACKAGED_CONFIG_DIR, Path.cwd()]
    if config_dir is not None:
        dirs.insert(0, config_dir)
    return [d / path for d in dirs]


def path_is_file(path: Path) -> bool:
    """``path.is_file()``, False where the OS refuses the name itself (over 255 bytes, ...)."""
    try:
        return path.is_file()
    except OSError:
        return False


def _uses_world(cfg: Config) -> bool:
    """Whether a device URL is ``sim://``: the simulated world, built from the scenario."""
    return any(
        url.strip().lower().startswith("sim:")
        for url in (cfg.gps.url, cfg.compass.url, cfg.motors.url)
    )


def _parse(text: str, source: str) -> dict[str, Any]:
    # a UTF-8 byte-order mark (Windows editors write one) is no TOML statement: tomllib
    # refused it as "Invalid statement (at line 1, column 1)"; a file's first line keeps its
    # number and column without it
    text = text.removeprefix("\ufeff")
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        # one line: the message already says "(at line L, column C)"
        raise ConfigError(f"{source}: not valid TOML: {_one_line(str(exc))}") from exc


def _one_line(text: str) -> str:
    return " ".join(text.split())


def loads(text: str, source: str = "<string>") -> Config:
    """Parse and validate TOML text into a :class:`Config`.

    Raises :class:`ConfigError` naming ``source`` for malformed TOML, else the dotted key.
    """
    return build(Config, _parse(text, source))


def _check_ports(cfg: Config) -> None:
    """Two enabled servers given one TCP port: a ConfigError naming both keys (binding
    would blame another program holding the port)."""
    seen: dict[int, str] = {}
    for section in ("server", "console", "gpsd"):
        sec = getattr(cfg, section)
        if not sec.enabled or sec.port == 0:  # 0: the system picks a free port for each
            continue
        other = seen.setdefault(sec.port, section)
        if other != section:
            raise ConfigError(
                f"{section}.port: {sec.port} is {other}.port too: each server needs a port "
                "of its own"
            )


def is_loopback_bind(host: str) -> bool:
    """True for a bind address only this machine reaches: "localhost" (any case), 127.0.0.0/8,
    ::1 written as addresses (as ``x6wd.app.server.is_loopback``, which decides who may run
    without a token, but for the case of "localhost"). Other names (a hostname that
    /etc/hosts maps to 127.0.0.1) and short forms (127.1) are not resolved: False."""
    if host.lower() == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def plaintext_binds(cfg: Config) -> tuple[str, ...]:
    """The bind keys (``server.bind``, ``console.bind``) of the enabled servers that would
    listen beyond loopback without TLS: the control server without ``[server] tls_cert`` and
    ``tls_key``, and the console, which uses the server's TLS (and needs the server)."""
    srv = cfg.server
    if not srv.enabled or (srv.tls_cert and srv.tls_key):
        return ()
    out = []
    if not is_loopback_bind(srv.bind):
        out.append("server.bind")
    if cfg.console.enabled and not is_loopback_bind(cfg.console.bind):
        out.append("console.bind")
    return tuple(out)


def check_plaintext(cfg: Config) -> None:
    """Listening beyond loopback without TLS: a ConfigError naming ``server.tls_cert`` (or
    ``console.bind`` when only the console does), unless ``[server] allow_plaintext``. There
    the ``auth`` line with the token and every drive command would travel in clear text:
    anyone on the network could take the token and drive the robot. The daemon calls this
    after checking that the bind addresses are addresses (a typo is named as such)."""
    binds = plaintext_binds(cfg)
    if not binds or cfg.server.allow_plaintext:
        return
    srv = cfg.server
    why = (
        "without TLS the token and every command travel in clear text; set server.tls_cert "
        "and server.tls_key, or server.allow_plaintext = true (an isolated network only)"
    )
    if not srv.token_file:
        why += "; server.token_file is needed too"
    value, clause = _not_loopback(srv.bind if binds[0] == "server.bind" else cfg.console.bind)
    if binds[0] == "server.bind":
        key = "server.tls_key" if srv.tls_cert else "server.tls_cert"
        raise ConfigError(f"{key}: required when server.bind = {value} {clause}: {why}")
    raise ConfigError(
        f"console.bind: {value} {clause}: the console needs the control server's TLS; {why}"
    )


def _not_loopback(bind: str) -> tuple[str, str]:
    """A bind address beyond loopback for a message, and why it counts as such: an address
    is not loopback; a name or short form (127.1) is not called beyond loopback, only not
    checked."""
    if bind in ("", "0.0.0.0", "::"):
        return f"{bind!r} (all interfaces)", "is not loopback"
    try:
        ipaddress.ip_address(bind)
    except ValueError:
        return repr(bind), (
            "is not a literal loopback address (x6wd checks only literal loopback addresses "
            "and 'localhost'; use 127.0.0.1)"
        )
    return repr(bind), "is not loopback"


def _device_node(url: str) -> str | None:
    """The node a serial or tcp device URL opens (a resolved path, or host:port), else None
    (also for a malformed URL: the device's own check names what is wrong with it)."""
    try:
        parts = urllib.parse.urlsplit(url)
        if parts.scheme == "serial" and parts.path:
            return os.path.realpath(urllib.parse.unquote(parts.path))
    except ValueError:
        return None
    if parts.scheme == "tcp" and parts.netloc:
        return "tcp://" + parts.netloc.lower()
    return None


def _check_devices(cfg: Config) -> None:
    """The GPS and the motor board on one node: a ConfigError naming both keys (each reader
    would take the other's bytes, the motor commands going down the GPS line)."""
    gps, motors = _device_node(cfg.gps.url), _device_node(cfg.motors.url)
    if gps is not None and gps == motors:
        raise ConfigError(
            f"motors.url: {cfg.motors.url} opens {gps}, as gps.url does: each device needs"
            " a line of its own"
        )


def _check_recorder(cfg: Config) -> None:
    """An enabled recorder with no directory would write wherever the daemon was started."""
    if cfg.recorder.enabled and not cfg.recorder.dir.strip():
        raise ConfigError("recorder.dir: empty: name a directory, or set recorder.enabled = false")


def load(path: str | Path) -> Config:
    """Read and validate a TOML configuration file (UTF-8, as TOML requires; a leading
    byte-order mark is skipped).

    Every problem is a one-line :class:`ConfigError` starting with the file's path: it
    cannot be read, is not UTF-8 (with the line and byte offset), is not valid TOML (with
    line and column), a key is unknown, of the wrong type or out of range (the dotted key),
    or the ``[sim] scenario`` that sim:// devices need is found nowhere (every path tried).
    A scenario found becomes an absolute path (:func:`scenario_candidates`).
    """
    p = Path(path)
    try:
        blob = read_bytes_bounded(p)
    except OSError as exc:
        raise ConfigError(f"{p}: cannot read configuration: {exc.strerror or exc}") from exc
    try:
        text = blob.decode("utf-8")
    except UnicodeDecodeError as exc:
        line = blob.count(b"\n", 0, exc.start) + 1
        raise ConfigError(
            f"{p}: not UTF-8 text (TOML must be UTF-8): byte {blob[exc.start]:#04x} at offset "
            f"{exc.start}, line {line}"
        ) from None
    data = _parse(text, str(p))
    try:
        cfg = build(Config, data)
        _check_ports(cfg)
        _check_devices(cfg)
        _check_recorder(cfg)
    except ConfigError as exc:
        raise ConfigError(f"{p}: {exc}") from exc
    if not cfg.sim.scenario:
        return cfg
    # The scenario, found where scenario_candidates says: a file next to the config file does
    # not depend on the working directory. Not found while sim:// devices need it: the
    # error lists every path tried, in order.
    tried = scenario_candidates(cfg.sim.scenario, p.parent)
    found = next((c for c in tried if path_is_file(c)), None)
    if found is not None:
        sim = dataclasses.replace(cfg.sim, scenario=str(found.resolve()))
        return dataclasses.replace(cfg, sim=sim)
    if _uses_world(cfg):
        raise ConfigError(
            f"{p}: sim.scenario: no such file {cfg.sim.scenario!r} (tried "
            f"{', '.join(str(c) for c in tried)})"
        )
    return cfg
