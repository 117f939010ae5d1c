"""The paper's waypoint state machine (REFERENCE.md §1) and compass heading conventions.

Each :meth:`Navigator.step` takes the (filtered) position in the plane of the configured
projection and the TRUE heading, and decides:

- arrival at the current waypoint when ``|xi − xc| <= Δx`` and ``|yi − yc| <= Δy`` (eq. 7):
  ARRIVED and on to the next waypoint, or MISSION_DONE after the last one;
- otherwise with Θ = course deviation (eqs. 5-6): ``Θ > Δφ`` -> TURN_RIGHT (clockwise),
  ``Θ < −Δφ`` -> TURN_LEFT, else STRAIGHT.

Headings: the CMPS10 reports a MAGNETIC bearing 0..359.9°; the paper's compass angle φc is in
(−180°, 180°] (bearings above 180° become negative, i.e. west). The destination bearing φi is
geographic, so the declination (east positive) is added: true = magnetic + declination.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

from x6wd.core.config import NavigationConfig
from x6wd.core.errors import X6wdError
from x6wd.core.records import NavState
from x6wd.nav import geo


class NavigationError(X6wdError, ValueError):
    """Bad waypoints, headings or positions given to the navigator."""


def cmps_to_paper_deg(bearing_deg: float) -> float:
    """CMPS10 bearing 0 <= b < 360 (deg, clockwise from north) -> the paper's (−180, 180]."""
    b = float(bearing_deg)
    if not (math.isfinite(b) and 0.0 <= b < 360.0):
        raise NavigationError(f"compass bearing must be in [0, 360) deg, got {bearing_deg!r}")
    # Not x6wd.core.geodesy.wrap_deg: on [0, 360) one subtraction is exact, while the
    # general wrap's 180 - (180 - b) rounds (0.1 would come back as 0.09999999999999432).
    return b - 360.0 if b > 180.0 else b


def magnetic_to_true(bearing_mag_deg: float, declination_deg: float) -> float:
    """Magnetic bearing (deg) + declination (deg, east positive) -> true, in (−180, 180]."""
    m = float(bearing_mag_deg)
    d = float(declination_deg)
    if not (math.isfinite(m) and math.isfinite(d)):
        raise NavigationError(f"bearing and declination must be finite, got {m!r}, {d!r}")
    return float(geo.wrap_deg(m + d))


@dataclass(frozen=True, slots=True)
class NavDecision:
    """What the last :meth:`Navigator.step` saw and decided (angles rad, lengths m)."""

    state: NavState
    waypoint_index: int  # the waypoint the decision was about (0-based)
    dx_m: float  # xi − xc
    dy_m: float  # yi − yc
    distance_m: float
    phi_i_rad: float | None  # destination bearing; None once arrived
    phi_c_rad: float  # true heading used
    theta_rad: float | None  # course deviation; None once arrived


class Navigator:
    """Waypoint sequencing with the paper's thresholds from :class:`NavigationConfig`.

    ``declination_deg`` (east positive) converts compass readings with
    :meth:`heading_from_compass`; :meth:`step` itself takes a true heading.
    """

    def __init__(self, config: NavigationConfig, declination_deg: float = 0.0) -> None:
        self.config = config
        if not math.isfinite(declination_deg) or abs(declination_deg) > 180.0:
            raise NavigationError(f"declination must be in [-180, 180] deg, got {declination_deg}")
        self.declination_deg = float(declination_deg)
        self._delta_phi_rad = math.radians(config.delta_phi_deg)
        self._waypoints: tuple[tuple[float, float], ...] = ()
        self._xy: list[tuple[float, float]] = []
        self._index = 0
        self.projection: geo.Projection = geo.TwoRadius()
        self.last: NavDecision | None = None

    # -------------------------------------------------------------- mission
    def set_waypoints(self, waypoints: Sequence[tuple[float, float]]) -> None:
        """Replace the mission with (lat_deg, lon_deg) waypoints and restart at the first.

        The projection named in the config is built here; a local tangent plane takes the
        first waypoint as its origin.
        """
        wps: list[tuple[float, float]] = []
        for i, wp in enumerate(waypoints):
            try:
                lat, lon = (float(v) for v in wp)
            except (TypeError, ValueError) as exc:
                raise NavigationError(f"waypoint {i}: expected (lat, lon), got {wp!r}") from exc
            if not (math.isfinite(lat) and -90.0 <= lat <= 90.0):
                raise NavigationError(f"waypoint {i}: latitude {lat!r} outside [-90, 90] deg")
            if not (math.isfinite(lon) and -180.0 <= lon <= 180.0):
                raise NavigationError(f"waypoint {i}: longitude {lon!r} outside [-180, 180] deg")
            wps.append((lat, lon))
        if not wps:
            raise NavigationError("a mission needs at least one waypoint")
        try:
            proj = geo.make_projection(self.config.projection, wps[0][0], wps[0][1])
        except geo.GeoError as exc:
            raise NavigationError(str(exc)) from exc
        self.projection = proj
        self._xy = [(float(x), float(y)) for x, y in (proj.to_xy(a, b) for a, b in wps)]
        self._waypoints = tuple(wps)
        self._index = 0
        self.last = None

    def restart(self) -> None:
        """Go back to the first waypoint."""
        self._index = 0
        self.last = None

    @property
    def waypoints(self) -> tuple[tuple[float, float], ...]:
        """The mission as (lat_deg, lon_deg)."""
        return self._waypoints

    @property
    def index(self) -> int:
        """0-based index of the current target (== len(waypoints) when done)."""
        return self._index

    @property
    def done(self) -> bool:
        """True once the last waypoint was reached (or before any mission is loaded)."""
        return self._index >= len(self._xy)

    def target_xy(self) -> tuple[float, float]:
        """Current target in the projection plane (m); NavigationError when done."""
        if self.done:
            raise NavigationError("no current waypoint: mission done or not loaded")
        return self._xy[self._index]

    def to_xy(self, lat_deg: float, lon_deg: float) -> tuple[float, float]:
        """Project a position (deg) into the mission's plane (m)."""
        x, y = self.projection.to_xy(lat_deg, lon_deg)
        return float(x), float(y)

    # -------------------------------------------------------------- headings
    def heading_from_compass(self, bearing_mag_deg: float) -> float:
        """CMPS10 magnetic bearing [0, 360) deg -> true heading φc in rad, (−π, π]."""
        paper = cmps_to_paper_deg(bearing_mag_deg)
        true_deg = magnetic_to_true(paper, self.declination_deg)
        return math.radians(true_deg)

    # -------------------------------------------------------------- decision
    def step(self, x_m: float, y_m: float, heading_true_rad: float) -> NavState:
        """One decision for position (x_m, y_m) and true heading φc (rad, (−π, π]).

        Returns ARRIVED (and advances) or MISSION_DONE on arrival, else TURN_LEFT,
        TURN_RIGHT or STRAIGHT. After the last waypoint it keeps returning MISSION_DONE.
        """
        if not (math.isfinite(x_m) and math.isfinite(y_m)):
            raise NavigationError(f"position must be finite, got ({x_m!r}, {y_m!r})")
        if not (math.isfinite(heading_true_rad) and -math.pi < heading_true_rad <= math.pi):
            raise NavigationError(f"heading must be in (-pi, pi] rad, got {heading_true_rad!r}")
        if not self._xy:
            raise NavigationError("no mission loaded")
        if self.done:
            return NavState.MISSION_DONE
        i = self._index
        xi, yi = self._xy[i]
        dx, dy = xi - x_m, yi - y_m
        dist = math.hypot(dx, dy)
        cfg = self.config
        if abs(dx) <= cfg.delta_x_m and abs(dy) <= cfg.delta_y_m:
            self._index += 1
            state = NavState.MISSION_DONE if self.done else NavState.ARRIVED
            self.last = NavDecision(state, i, dx, dy, dist, None, heading_true_rad, None)
            return state
        phi_i = float(geo.destination_bearing(x_m, y_m, xi, yi))
        theta = float(geo.course_deviation(phi_i, heading_true_rad))
        if abs(theta) > self._delta_phi_rad:
            state = NavState.TURN_RIGHT if theta > 0 else NavState.TURN_LEFT
        else:
            state = NavState.STRAIGHT
        self.last = NavDecision(state, i, dx, dy, dist, phi_i, heading_true_rad, theta)
        return state
