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
  the position at the mission's first decision, to the waypoint); OR, for a waypoint with
  more after it where the path goes straight on, when it lies behind the robot (at 90° or
  more from the heading) within the position's error (``BEHIND_M``) and the robot is
  already past it along the path (a point closer than the GPS error to the start is not
  chased round). Inside the windows with the final bearing not yet met, it turns in place
  towards that bearing;
- otherwise pure pursuit of the point ``lookahead_m`` ahead on the segment, carried on along
  the path past waypoints it goes straight on through (``steering.STRAIGHT_ON_DEG``): with α
  the angle from the heading to that point, it pivots in place (TURN_LEFT / TURN_RIGHT) once
  ``|α| > pivot_angle_deg`` and until ``|α| < pivot_resume_deg``, in the direction α's sign
  gave when it started while α stays beyond ``PIVOT_KEEP_DEG`` on the other side; else
  STRAIGHT with the arc's
  curvature ``κ = 2·sin α / d`` and the approach speed in :attr:`NavDecision.curvature_per_m`
  and :attr:`NavDecision.speed_pct`, which the controller mixes into left/right percentages.
  The approach speed slows for each waypoint within ``approach_m`` along the path only to
  the speed its turn allows (:func:`steering.corner_speed_pct`; the last waypoint: to
  ``min_speed_pct``, as before);
- an arrival at a waypoint with more after it carries the next leg's arc in its decision
  (the robot drives on) unless the next leg starts with a pivot.

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
from x6wd.core.geodesy import wrap_rad
from x6wd.core.records import NavState
from x6wd.nav import geo, steering

BEHIND_M = 5.0
"""pivot_arc: a waypoint with more after it where the path goes straight on, behind the
robot and within the position's error radius, counts as reached once the robot is past it
along the path: at the start a first point closer than the GPS error was chased round in a
pivot (an outside audit: -174° on a straight line). The radius is the caller's (the
controller: three standard deviations of its position), never less than this (m: a NEO-5's
error in the open, the controller's ``ARRIVAL_GPS_MIN_M``) nor more than ``BEHIND_MAX_M``.
The same radius decides whether the first leg, from where the mission's first decision was
made, has a direction of its own."""
BEHIND_MAX_M = 10.0
"""The largest radius (m) ``BEHIND_M``'s rule takes from its caller: a position worse than
that (a start on a fix of HDOP 10) says little of where the robot is, and a point further
behind is driven to, as the mission says."""


PIVOT_KEEP_DEG = 135.0
"""pivot_arc: a pivot under way keeps its direction while α lies on the other side but still
beyond this (deg). At a reversal α swings about ±180° with the position's and the compass's
noise, and a direction taken from its sign at each decision flipped the motors between
+turn/-turn and -turn/+turn six times in 0.2 s, twice inside one 50 ms tick (an outside
audit: a 5 m hairpin, α +179°, -180°, +180°, -179°), the forward-to-reverse jump of each
side that ``RETURN_STOP_S`` avoids elsewhere. Either way round is then about as far: going
on costs at most 2 × (180 - 135) = 90° more turn, and the 45° leave room for a fix's jump
against a lookahead point a few metres off. Nearer than this on the other side the target
has moved (a position reset) and the pivot turns the short way, as before."""


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
    # drive speed while STRAIGHT (approach slow-down applied), and on an ARRIVED that drives
    # on into the next leg (curvature and speed are then the next leg's)
    speed_pct: float | None = None
    steer_alpha_rad: float | None = None  # heading error to the steering target
    true_de_m: float | None = None  # waypoint − position, true metres east
    true_dn_m: float | None = None  # ... and north
    # on arrival: "windows" (eq. 7), "passed" (the waypoint's line) or "behind" (BEHIND_M)
    arrived_by: str = ""


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
        self._pivot_sign = 0.0  # the pivot's direction: +1 right, -1 left, 0 not pivoting
        self._keep_rad = math.radians(PIVOT_KEEP_DEG)
        # the path's shape, set at the first decision (the first leg starts there): per
        # waypoint the chord directions in and out (rad, None: unknown), the turn (rad) and
        # the path distance from the first waypoint (m)
        self._dir_in: list[float | None] = []
        self._dir_out: list[float | None] = []
        self._turn: list[float] = []
        self._cum_m: list[float] = []
        self._first_start: tuple[float, float] = (0.0, 0.0)  # where the first leg starts

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
        self._pivot_sign = 0.0
        self._dir_in, self._dir_out, self._turn, self._cum_m = [], [], [], []

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
        self,
        x_m: float,
        y_m: float,
        heading_true_rad: float,
        may_arrive: bool = True,
        behind_m: float = BEHIND_M,
    ) -> NavState:
        """One decision for position (x_m, y_m) and true heading φc (rad, (−π, π]).

        Returns ARRIVED (and advances) or MISSION_DONE on arrival, else TURN_LEFT,
        TURN_RIGHT or STRAIGHT. After the last waypoint it keeps returning MISSION_DONE.
        ``may_arrive`` False: no arrival now, whatever the position says (the caller's
        independent check disagrees: the controller's GPS check of an EKF position).
        ``behind_m`` (pivot_arc): the position's error radius (m), see ``BEHIND_M``; the
        caller may pass a larger one from its position's uncertainty (at most
        ``BEHIND_MAX_M`` is used).
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
            return self._step_pivot_arc(
                x_m,
                y_m,
                heading_true_rad,
                may_arrive,
                min(BEHIND_MAX_M, max(BEHIND_M, float(behind_m))),
            )
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

    def move_first_leg_start(self, before: tuple[float, float], after: tuple[float, float]) -> None:
        """The position source moved its estimate at once from ``before`` to ``after``
        (lat_deg, lon_deg; an EKF reset). On the first leg, which starts where the estimate
        was at the mission's first decision, that start moves the same way: it was the
        robot's place, wrong by as much, not a point of the map (a start on fixes 35 m off
        then drove back 35 m to a line that never was). A later leg starts at a waypoint
        and stays; so does paper steering, which has no legs."""
        ltp = self._ltp
        if ltp is None or self._index != 0 or self._seg_start is None:
            return
        e0, n0 = ltp.to_xy(*before)
        e1, n1 = ltp.to_xy(*after)
        de, dn = float(e1) - float(e0), float(n1) - float(n0)
        if not (math.isfinite(de) and math.isfinite(dn)):
            return
        s = self._seg_start
        self._seg_start = self._first_start = (s[0] + de, s[1] + dn)
        self._path_shape(self._first_start)

    def _path_shape(self, first_start: tuple[float, float]) -> None:
        """The chord directions into and out of each waypoint (``steering.TURN_CHORD_M`` of
        path either side), the path's turn there and the path distance from the first
        waypoint. The first leg starts at ``first_start`` (the first decision's position).
        Within ``BEHIND_M`` (the open-sky error) of the first waypoint the first leg's
        direction is mostly the GPS's noise: it is left out of every chord, and the first
        waypoint's incoming direction is unknown (the path taken as going straight on
        through it) unless the start lies beyond it along the path that follows (the robot
        starts on the next leg: a reversal, which keeps its turn). Never the caller's wider
        radius: a first point 6.5 m to the side then counted as straight on, and the robot
        curved onto the path past it without coming nearer than 6.5 m (a code review)."""
        en = self._en
        near = math.dist(first_start, en[0]) <= BEHIND_M
        pts = en if near else [first_start, *en]
        off = 0 if near else 1
        chord = steering.TURN_CHORD_M
        self._dir_in, self._dir_out, self._turn = [], [], []
        self._cum_m = [0.0]
        for j in range(1, len(en)):
            self._cum_m.append(self._cum_m[-1] + math.dist(en[j - 1], en[j]))
        for j, w in enumerate(en):
            k = j + off
            d_in = steering.chord_bearing_rad(steering.point_along(pts, k, -chord), w)
            d_out = steering.chord_bearing_rad(w, steering.point_along(pts, k, chord))
            if j == 0 and near and d_out is not None:
                beyond = (first_start[0] - w[0]) * math.sin(d_out) + (
                    first_start[1] - w[1]
                ) * math.cos(d_out) > 0.0
                if beyond and math.dist(first_start, w) >= 0.1 * chord:
                    d_in = steering.bearing_rad(first_start, w)
            if d_out is None:
                turn = math.pi  # the end of the path: a stop
            elif d_in is None:
                turn = 0.0
            else:
                turn = abs(wrap_rad(d_out - d_in))
            self._dir_in.append(d_in)
            self._dir_out.append(d_out)
            self._turn.append(turn)

    def _steer(
        self, i: int, p: tuple[float, float], heading_rad: float
    ) -> tuple[float, float | None, float | None, bool]:
        """Towards waypoint ``i`` on the current leg from ``p``: (α rad, curvature 1/m or None,
        speed % or None, pivot now?) given the pivot flag's current value."""
        cfg = self.config
        assert self._seg_start is not None
        start, end = self._seg_start, self._en[i]
        de, dn = end[0] - p[0], end[1] - p[1]
        final = self._final_bearing_rad[i]
        if final is not None and steering.in_windows(de, dn, cfg.delta_x_m, cfg.delta_y_m):
            # In the windows, final bearing not met: turn in place towards it.
            return float(geo.course_deviation(final, heading_rad)), None, None, True
        n = len(self._en)
        # carry the lookahead on past waypoints the path goes straight on through (as far
        # as it can reach: the robot may be past the waypoint, its arrival not yet agreed)
        past_m = max(0.0, steering.along_cross_m(start, end, p)[0])
        end_j = self._straight_run_end(i, past_m + cfg.lookahead_m)
        beyond = self._en[i + 1 : end_j + 1]
        target = steering.lookahead_on_path(start, end, p, cfg.lookahead_m, beyond)
        curvature, alpha = steering.pure_pursuit_curvature(p, heading_rad, target)
        pivot = steering.pivot_update(self._pivoting, alpha, self._pivot_rad, self._resume_rad)
        if pivot:
            return alpha, None, None, True
        # slow for each waypoint within approach_m along the path, to its corner speed
        r = math.hypot(de, dn)
        speed = cfg.cruise_pct
        j = i
        while j < n:
            d = r + self._cum_m[j] - self._cum_m[i]
            if d >= cfg.approach_m:
                break
            corner: float | None = None  # the last waypoint, or the path ends here: stop
            if j + 1 < n and self._dir_out[j] is not None:
                corner = steering.corner_speed_pct(
                    self._turn[j], cfg.cruise_pct, cfg.min_speed_pct, self._pivot_rad
                )
            v = steering.approach_speed_pct(
                d, cfg.cruise_pct, cfg.approach_m, cfg.min_speed_pct, corner
            )
            speed = min(speed, v)
            j += 1
        return alpha, curvature, speed, False

    def _straight_run_end(self, i: int, within_m: float = math.inf) -> int:
        """The last waypoint of the straight run from waypoint ``i``: the path goes straight
        on (``steering.STRAIGHT_ON_DEG``) through every waypoint before it, and keeps within
        that angle of its direction into ``i``; ``within_m``: no further than this along
        the path from ``i`` (m). ``i`` itself at a corner or the end."""
        n = len(self._en)
        ref = self._dir_in[i] if self._dir_in[i] is not None else self._dir_out[i]
        straight_on = math.radians(steering.STRAIGHT_ON_DEG)
        j = i
        while j + 1 < n and self._cum_m[j] - self._cum_m[i] < within_m:
            out = self._dir_out[j]
            if (
                out is None
                or ref is None
                or self._turn[j] > straight_on
                or abs(wrap_rad(out - ref)) > straight_on
            ):
                break
            j += 1
        return j

    @property
    def course_index(self) -> int:
        """The waypoint the current leg leads to for a watch over the whole leg (the
        controller's off-course checks): in pivot_arc, the end of the straight run from the
        current waypoint (:meth:`_straight_run_end`), so a recorded track's points 1-3 m
        apart on a straight are one leg, as a single waypoint would be; otherwise (and
        before the first decision, or when done) :attr:`index`."""
        if self.done or not self._turn:
            return self._index
        return self._straight_run_end(self._index)

    def passed_on_track(self, lat_deg: float, lon_deg: float) -> bool:
        """pivot_arc: is the point (e.g. the latest GPS fix) past the current waypoint along
        the track, where the path goes straight on through it (``steering.STRAIGHT_ON_DEG``):
        on or beyond the line through it perpendicular to its segment, or past it along the
        path that follows? False at a corner, the last waypoint, in paper steering and
        before the first decision. The controller's GPS check of an EKF arrival accepts
        this as well as a fix near the waypoint: a robot that passed a track point a few
        metres to the side must not turn round for it (a corner and the last waypoint keep
        the distance rule)."""
        i = self._index
        if self._ltp is None or self.done or not self._turn or self._seg_start is None:
            return False
        out = self._dir_out[i]
        if i + 1 >= len(self._en) or out is None:
            return False
        if self._turn[i] > math.radians(steering.STRAIGHT_ON_DEG):
            return False
        e, n = self._ltp.to_xy(lat_deg, lon_deg)
        f = (float(e), float(n))
        w = self._en[i]
        if steering.passed_line(self._seg_start, w, f):
            return True
        return (f[0] - w[0]) * math.sin(out) + (f[1] - w[1]) * math.cos(out) >= 0.0

    def _behind(self, i: int, p: tuple[float, float], heading_rad: float, behind_m: float) -> bool:
        """Waypoint ``i`` (with more after it) where the path goes straight on
        (``steering.STRAIGHT_ON_DEG``; also a first waypoint within ``BEHIND_M`` of where the
        mission started, whatever the first leg's direction) lies behind the robot within
        ``behind_m`` (``BEHIND_M`` for the first) and the robot is past it along the path:
        reached (see ``BEHIND_M``). A corner or a reversal further on is not: the robot drives
        to it as the mission says."""
        out = self._dir_out[i]
        if i + 1 >= len(self._en) or out is None:
            return False
        if i == 0:
            # The first point is taken for the start point only within the open-sky error,
            # never the widened radius, whichever side it lies: at start-up the EKF's sigma
            # (3.3 m, a 6.9 m radius) took a sample point 7 m behind the start (or 6 m to
            # the side) for it and skipped it unvisited.
            behind_m = BEHIND_M
        if self._turn[i] > math.radians(steering.STRAIGHT_ON_DEG) and not (
            i == 0 and math.dist(self._en[0], self._first_start) <= behind_m
        ):
            return False
        w = self._en[i]
        de, dn = w[0] - p[0], w[1] - p[1]
        if math.hypot(de, dn) > behind_m:
            return False
        if de * math.sin(heading_rad) + dn * math.cos(heading_rad) > 0.0:
            return False  # ahead of the robot: it drives there
        return -de * math.sin(out) - dn * math.cos(out) >= 0.0

    def _step_pivot_arc(
        self, x_m: float, y_m: float, heading_rad: float, may_arrive: bool, behind_m: float
    ) -> NavState:
        cfg = self.config
        i = self._index
        xi, yi = self._xy[i]
        dx, dy = xi - x_m, yi - y_m
        dist = math.hypot(dx, dy)  # the projection's metres, as telemetry shows them
        p = self.true_en(x_m, y_m)
        if self._seg_start is None:
            self._seg_start = p  # the first leg starts where the mission's first decision was
            self._first_start = p
            self._path_shape(p)
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
        elif self._behind(i, p, heading_rad, behind_m):
            arrived_by = "behind"
        if arrived_by:
            self._index += 1
            self._seg_start = end
            self._pivoting = False
            self._pivot_sign = 0.0
            state = NavState.MISSION_DONE if self.done else NavState.ARRIVED
            alpha = curvature = speed = None
            if not self.done:
                # drive on into the next leg unless it starts with a pivot (then stop for
                # this decision, and the next one pivots)
                a, k, v, pivot = self._steer(self._index, p, heading_rad)
                if not pivot:
                    alpha, curvature, speed = a, k, v
            self.last = NavDecision(
                state, i, dx, dy, dist, None, heading_rad, None,
                curvature_per_m=curvature, speed_pct=speed, steer_alpha_rad=alpha,
                true_de_m=de, true_dn_m=dn, arrived_by=arrived_by,
            )  # fmt: skip
            return state
        phi_i = theta = None
        if dist > 0.0:
            phi_i = float(geo.destination_bearing(x_m, y_m, xi, yi))
            theta = float(geo.course_deviation(phi_i, heading_rad))
        alpha, curvature, speed, pivot = self._steer(i, p, heading_rad)
        # a pivot under way keeps its direction while α swings about ±180° (PIVOT_KEEP_DEG)
        if not pivot:
            self._pivot_sign = 0.0
        elif not (self._pivoting and self._pivot_sign != 0.0 and abs(alpha) >= self._keep_rad):
            self._pivot_sign = 1.0 if alpha > 0 else -1.0
        self._pivoting = pivot
        sign = self._pivot_sign
        if pivot:
            state = NavState.TURN_RIGHT if sign > 0 else NavState.TURN_LEFT
        else:
            state = NavState.STRAIGHT
        self.last = NavDecision(
            state, i, dx, dy, dist, phi_i, heading_rad, theta,
            curvature_per_m=curvature, speed_pct=speed, steer_alpha_rad=alpha,
            true_de_m=de, true_dn_m=dn,
        )  # fmt: skip
        return state
