"""The paper's waypoint state machine (REFERENCE.md §1) and compass heading conventions.

Each :meth:`Navigator.step` takes the (filtered) position in the plane of the configured
projection and the TRUE heading, and decides:

- arrival at the current waypoint when ``|xi − xc| <= Δx`` and ``|yi − yc| <= Δy`` (eq. 7):
  ARRIVED and on to the next waypoint, or MISSION_DONE after the last one;
- otherwise with Θ = course deviation (eqs. 5-6): ``Θ > Δφ`` -> TURN_RIGHT (clockwise),
  ``Θ < −Δφ`` -> TURN_LEFT, else STRAIGHT.

With ``navigation.steering = "pivot_arc"`` (default "paper", exactly the above) the
decision is :meth:`Navigator.step`'s other branch (geometry in :mod:`x6wd.nav.steering`,
all of it in TRUE metres on a local tangent plane at the first waypoint, whatever the
projection):

- arrival when eq. 7's windows hold in true metres (``|Δe| <= Δx``, ``|Δn| <= Δy``) and, if
  the waypoint carries a final bearing, the heading is within Δφ of it; OR when the robot has
  passed the line through the waypoint perpendicular to its segment (previous waypoint, or
  the position at the mission's first decision, to the waypoint). Inside the windows with the
  final bearing not yet met, it turns in place towards that bearing;
- otherwise pure pursuit of the point ``lookahead_m`` ahead on the segment: with α the angle
  from the heading to that point, it pivots in place (TURN_LEFT / TURN_RIGHT) once
  ``|α| > pivot_angle_deg`` and until ``|α| < pivot_resume_deg``; else STRAIGHT with the arc's
  curvature ``κ = 2·sin α / d`` and the approach speed in :attr:`NavDecision.curvature_per_m`
  and :attr:`NavDecision.speed_pct`, which the controller mixes into left/right percentages.

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
from x6wd.nav import geo, steering


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
    # pivot_arc steering only (None / "" in paper mode):
    curvature_per_m: float | None = None  # arc to drive while STRAIGHT, positive right
    speed_pct: float | None = None  # drive speed while STRAIGHT (approach slow-down applied)
    steer_alpha_rad: float | None = None  # heading error to the steering target
    true_de_m: float | None = None  # waypoint − position, true metres east
    true_dn_m: float | None = None  # ... and north
    arrived_by: str = ""  # "windows" (eq. 7) or "passed" (the waypoint's line) on arrival


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
        # pivot_arc: waypoints in true metres, optional final bearings, the current segment's
        # start (None until the first decision) and the pivot flag (hysteresis).
        self._pivot_rad = math.radians(config.pivot_angle_deg)
        self._resume_rad = math.radians(config.pivot_resume_deg)
        self._ltp: geo.LocalTangentPlane | None = None
        self._en: list[tuple[float, float]] = []
        self._final_bearing_rad: list[float | None] = []
        self._seg_start: tuple[float, float] | None = None
        self._pivoting = False

    # -------------------------------------------------------------- mission
    def set_waypoints(
        self,
        waypoints: Sequence[tuple[float, float]],
        final_bearings_deg: Sequence[float | None] | None = None,
    ) -> None:
        """Replace the mission with (lat_deg, lon_deg) waypoints and restart at the first.

        ``final_bearings_deg`` (optional, one per waypoint, a true bearing in degrees or None):
        in pivot_arc steering, arrival by eq. 7's windows then also needs the heading within
        Δφ of it; paper steering ignores it. The projection named in the config is built
        here; a local tangent plane takes the first waypoint as its origin.
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
        bearings: list[float | None] = [None] * len(wps)
        if final_bearings_deg is not None:
            fbs = list(final_bearings_deg)
            if len(fbs) != len(wps):
                raise NavigationError(
                    f"{len(fbs)} final bearings for {len(wps)} waypoints: give one per waypoint"
                )
            for i, fb in enumerate(fbs):
                if fb is None:
                    continue
                if (
                    isinstance(fb, bool)
                    or not isinstance(fb, (int, float))
                    or not (math.isfinite(fb) and -360.0 <= fb <= 360.0)
                ):
                    raise NavigationError(
                        f"waypoint {i}: final bearing {fb!r} must be a number in [-360, 360] deg"
                    )
                bearings[i] = math.radians(float(geo.wrap_deg(float(fb))))
        try:
            proj = geo.make_projection(self.config.projection, wps[0][0], wps[0][1])
        except geo.GeoError as exc:
            raise NavigationError(str(exc)) from exc
        ltp: geo.LocalTangentPlane | None = None
        en: list[tuple[float, float]] = []
        if self.config.steering == "pivot_arc":
            try:
                ltp = geo.LocalTangentPlane(wps[0][0], wps[0][1])
            except geo.GeoError as exc:
                raise NavigationError(f"pivot_arc steering: {exc}") from exc
            en = [(float(e), float(n)) for e, n in (ltp.to_xy(a, b) for a, b in wps)]
        self.projection = proj
        self._xy = [(float(x), float(y)) for x, y in (proj.to_xy(a, b) for a, b in wps)]
        self._waypoints = tuple(wps)
        self._ltp = ltp
        self._en = en
        self._final_bearing_rad = bearings
        self.restart()

    def restart(self) -> None:
        """Go back to the first waypoint."""
        self._index = 0
        self.last = None
        self._seg_start = None
        self._pivoting = False

    @property
    def waypoints(self) -> tuple[tuple[float, float], ...]:
        """The mission as (lat_deg, lon_deg)."""
        return self._waypoints

    @property
    def final_bearings_deg(self) -> tuple[float | None, ...]:
        """Each waypoint's final true bearing (deg, (-180, 180]) or None."""
        return tuple(None if b is None else math.degrees(b) for b in self._final_bearing_rad)

    @property
    def pivoting(self) -> bool:
        """pivot_arc: the last decision was a pivot in place (the hysteresis flag)."""
        return self._pivoting

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
    def step(
        self, x_m: float, y_m: float, heading_true_rad: float, may_arrive: bool = True
    ) -> NavState:
        """One decision for position (x_m, y_m) and true heading φc (rad, (−π, π]).

        Returns ARRIVED (and advances) or MISSION_DONE on arrival, else TURN_LEFT,
        TURN_RIGHT or STRAIGHT. After the last waypoint it keeps returning MISSION_DONE.
        ``may_arrive`` False: no arrival now, whatever the position says (the caller's
        independent check disagrees: the controller's GPS check of an EKF position).
        """
        if not (math.isfinite(x_m) and math.isfinite(y_m)):
            raise NavigationError(f"position must be finite, got ({x_m!r}, {y_m!r})")
        if not (math.isfinite(heading_true_rad) and -math.pi < heading_true_rad <= math.pi):
            raise NavigationError(f"heading must be in (-pi, pi] rad, got {heading_true_rad!r}")
        if not self._xy:
            raise NavigationError("no mission loaded")
        if self.done:
            return NavState.MISSION_DONE
        if self.config.steering == "pivot_arc":
            return self._step_pivot_arc(x_m, y_m, heading_true_rad, may_arrive)
        i = self._index
        xi, yi = self._xy[i]
        dx, dy = xi - x_m, yi - y_m
        dist = math.hypot(dx, dy)
        cfg = self.config
        if may_arrive and abs(dx) <= cfg.delta_x_m and abs(dy) <= cfg.delta_y_m:
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

    def true_en(self, x_m: float, y_m: float) -> tuple[float, float]:
        """A point of the projection plane (m) in the pivot_arc's true-metre plane (east,
        north m from the first waypoint); NavigationError in paper steering."""
        ltp = self._ltp
        if ltp is None:
            raise NavigationError("true-metre plane only in pivot_arc steering")
        proj = self.projection
        if (
            isinstance(proj, geo.LocalTangentPlane)
            and proj.origin_lat_deg == ltp.origin_lat_deg
            and proj.origin_lon_deg == ltp.origin_lon_deg
        ):
            return x_m, y_m
        lat, lon = proj.to_latlon(x_m, y_m)
        e, n = ltp.to_xy(float(lat), float(lon))
        return float(e), float(n)

    def _step_pivot_arc(
        self, x_m: float, y_m: float, heading_rad: float, may_arrive: bool = True
    ) -> NavState:
        cfg = self.config
        i = self._index
        xi, yi = self._xy[i]
        dx, dy = xi - x_m, yi - y_m
        dist = math.hypot(dx, dy)  # the projection's metres, as telemetry shows them
        p = self.true_en(x_m, y_m)
        if self._seg_start is None:
            self._seg_start = p  # the first leg starts where the mission's first decision was
        start, end = self._seg_start, self._en[i]
        de, dn = end[0] - p[0], end[1] - p[1]
        final = self._final_bearing_rad[i]
        windows = steering.in_windows(de, dn, cfg.delta_x_m, cfg.delta_y_m)
        bearing_err = None if final is None else float(geo.course_deviation(final, heading_rad))
        arrived_by = ""
        if not may_arrive:
            pass
        elif windows and (bearing_err is None or abs(bearing_err) <= self._delta_phi_rad):
            arrived_by = "windows"
        elif steering.passed_line(start, end, p):
            arrived_by = "passed"
        if arrived_by:
            self._index += 1
            self._seg_start = end
            self._pivoting = False
            state = NavState.MISSION_DONE if self.done else NavState.ARRIVED
            self.last = NavDecision(
                state, i, dx, dy, dist, None, heading_rad, None,
                true_de_m=de, true_dn_m=dn, arrived_by=arrived_by,
            )  # fmt: skip
            return state
        phi_i = theta = None
        if dist > 0.0:
            phi_i = float(geo.destination_bearing(x_m, y_m, xi, yi))
            theta = float(geo.course_deviation(phi_i, heading_rad))
        curvature = speed = None
        if windows and bearing_err is not None:
            # In the windows, final bearing not met: turn in place towards it.
            alpha = bearing_err
            self._pivoting = True
        else:
            target = steering.lookahead_point(start, end, p, cfg.lookahead_m)
            curvature, alpha = steering.pure_pursuit_curvature(p, heading_rad, target)
            self._pivoting = steering.pivot_update(
                self._pivoting, alpha, self._pivot_rad, self._resume_rad
            )
            if not self._pivoting:
                speed = steering.approach_speed_pct(
                    math.hypot(de, dn), cfg.cruise_pct, cfg.approach_m, cfg.min_speed_pct
                )
        if self._pivoting:
            state = NavState.TURN_RIGHT if alpha > 0 else NavState.TURN_LEFT
            curvature = None
        else:
            state = NavState.STRAIGHT
        self.last = NavDecision(
            state, i, dx, dy, dist, phi_i, heading_rad, theta,
            curvature_per_m=curvature, speed_pct=speed, steer_alpha_rad=alpha,
            true_de_m=de, true_dn_m=dn,
        )  # fmt: skip
        return state
