"""Skid-steer geometry for the ``pivot_arc`` steering mode (docs/navigation.md, "Steering and
arrival"): pivot hysteresis, the pure-pursuit lookahead point (on a segment, or carried on
along the path past waypoints the path goes straight on through) and curvature, the
waypoint's "passed" line, eq. 7's windows in true metres, the path's turn at a waypoint,
the approach and corner speeds and the mixing of a curvature into left/right percentages.

Plain functions of plain floats, no state and no clock. Plane coordinates are east/north in
TRUE metres (a local tangent plane, :class:`x6wd.nav.geo.LocalTangentPlane`), bearings and
headings in radians clockwise from north, curvature in 1/m with positive = clockwise (a
right-hand turn, the sign of the paper's Θ).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

from x6wd.core.geodesy import wrap_rad

Point = tuple[float, float]
"""(east_m, north_m) in a true-metre plane."""

_DEGENERATE_M = 1e-6

STRAIGHT_ON_DEG = 20.0
"""A waypoint where the path turns by at most this (deg) is one the robot drives through:
no slowing down for it, no stop at its arrival, and the pure-pursuit lookahead carries on
past it along the path (a recorded track's points, 1-3 m apart on a straight or gently
bending path). Beyond it the corner speed falls linearly to ``min_speed_pct`` at the pivot
angle (docs/navigation.md, "Closely spaced waypoints")."""
TURN_CHORD_M = 5.0
"""The path's direction into and out of a waypoint is the chord over this much path (m)
either side of it, not the single legs: with points 1-3 m apart a corner rounded over
several of them still shows its whole turn, and a point a metre off the line does not
look like a corner."""


def pivot_update(pivoting: bool, theta_rad: float, pivot_rad: float, resume_rad: float) -> bool:
    """The pivot flag after one decision, with hysteresis.

    Not pivoting: start when ``|theta_rad| > pivot_rad`` (strictly beyond). Pivoting: go on
    while ``|theta_rad| >= resume_rad``, stop once strictly under it. Angles in radians.
    """
    a = abs(theta_rad)
    if pivoting:
        return a >= resume_rad
    return a > pivot_rad


def bearing_rad(frm: Point, to: Point) -> float:
    """Bearing (rad, clockwise from north, (-π, π]) from ``frm`` to ``to`` (metres); 0 when
    the points coincide."""
    de, dn = to[0] - frm[0], to[1] - frm[1]
    if de == 0.0 and dn == 0.0:
        return 0.0
    return wrap_rad(math.atan2(de, dn))


def along_cross_m(start: Point, end: Point, p: Point) -> tuple[float, float]:
    """Position of ``p`` relative to the segment ``start`` -> ``end`` (metres).

    Returns (along_m, cross_m): ``along_m`` the distance past ``end`` along the segment's
    direction (negative before the line through ``end`` perpendicular to the segment), and
    ``cross_m`` the distance from the segment's line, positive to the RIGHT of the direction
    of travel. A degenerate segment (shorter than 1 µm) gives (-distance to end, 0).
    """
    ue, un = end[0] - start[0], end[1] - start[1]
    seg = math.hypot(ue, un)
    de, dn = p[0] - end[0], p[1] - end[1]
    if seg < _DEGENERATE_M:
        return -math.hypot(de, dn), 0.0
    ue, un = ue / seg, un / seg
    along = de * ue + dn * un
    cross = de * un - dn * ue  # right-hand normal of (ue, un) is (un, -ue)
    return along, cross


def passed_line(start: Point, end: Point, p: Point) -> bool:
    """True once ``p`` is on or beyond the line through ``end`` perpendicular to the segment
    ``start`` -> ``end`` (ArduPilot's "passed the waypoint"); False for a degenerate segment."""
    ue, un = end[0] - start[0], end[1] - start[1]
    if math.hypot(ue, un) < _DEGENERATE_M:
        return False
    return along_cross_m(start, end, p)[0] >= 0.0


def lookahead_point(start: Point, end: Point, p: Point, lookahead_m: float) -> Point:
    """The pure-pursuit target: the point of the segment ``lookahead_m`` ahead of ``p``.

    The intersection, ahead of ``p``'s foot on the segment's line, of the circle of radius
    ``lookahead_m`` around ``p`` with that line; the foot itself when ``p`` is farther than
    ``lookahead_m`` from the line (head for the line first). Never beyond ``end``; ``end``
    for a degenerate segment. Metres.
    """
    if not (lookahead_m > 0.0):
        raise ValueError(f"lookahead_m must be positive, got {lookahead_m!r}")
    ue, un = end[0] - start[0], end[1] - start[1]
    seg = math.hypot(ue, un)
    if seg < _DEGENERATE_M:
        return end
    ue, un = ue / seg, un / seg
    along, cross = along_cross_m(start, end, p)  # along measured from end (<= 0 before it)
    ahead = (
        math.sqrt(lookahead_m * lookahead_m - cross * cross) if abs(cross) < lookahead_m else 0.0
    )
    s = min(along + ahead, 0.0)  # relative to end, clamped at the waypoint
    return end[0] + s * ue, end[1] + s * un


def pure_pursuit_curvature(p: Point, heading_rad: float, target: Point) -> tuple[float, float]:
    """Pure pursuit towards ``target`` from ``p`` heading ``heading_rad`` (true, rad).

    Returns (curvature_per_m, alpha_rad): α the angle from the heading to the target's
    bearing, wrapped to (-π, π], positive clockwise; κ = 2·sin α / d, d the distance to the
    target (m), the arc through ``p`` tangent to the heading that reaches the target; positive
    turns right. A target on ``p`` gives (0, 0).
    """
    d = math.hypot(target[0] - p[0], target[1] - p[1])
    if d < _DEGENERATE_M:
        return 0.0, 0.0
    alpha = wrap_rad(bearing_rad(p, target) - heading_rad)
    return 2.0 * math.sin(alpha) / d, alpha


def lookahead_on_path(
    start: Point, end: Point, p: Point, lookahead_m: float, beyond: Sequence[Point] = ()
) -> Point:
    """:func:`lookahead_point`, except that where that point would lie beyond ``end`` it
    carries on along the polyline ``end`` -> ``beyond[0]`` -> ``beyond[1]`` ... by the same
    distance (measured along the path), never past the last of them. With ``beyond`` empty
    it is :func:`lookahead_point`. Metres."""
    if not (lookahead_m > 0.0):
        raise ValueError(f"lookahead_m must be positive, got {lookahead_m!r}")
    ue, un = end[0] - start[0], end[1] - start[1]
    seg = math.hypot(ue, un)
    if seg < _DEGENERATE_M:
        s = math.hypot(p[0] - end[0], p[1] - end[1])
        s = lookahead_m - s if s < lookahead_m else 0.0  # what is left of the lookahead
    else:
        along, cross = along_cross_m(start, end, p)
        ahead = (
            math.sqrt(lookahead_m * lookahead_m - cross * cross)
            if abs(cross) < lookahead_m
            else 0.0
        )
        s = along + ahead  # relative to end
        if s <= 0.0 or not beyond:
            s = min(s, 0.0)
            return end[0] + s * ue / seg, end[1] + s * un / seg
    cur = end
    for q in beyond:
        leg = math.hypot(q[0] - cur[0], q[1] - cur[1])
        if s <= leg:
            if leg < _DEGENERATE_M:
                return q
            f = s / leg
            return cur[0] + f * (q[0] - cur[0]), cur[1] + f * (q[1] - cur[1])
        s -= leg
        cur = q
    return cur


def point_along(points: Sequence[Point], index: int, distance_m: float) -> Point:
    """The point ``distance_m`` along the polyline ``points`` from ``points[index]``: forward
    (towards the end) for a positive distance, backward for a negative one; the polyline's
    first or last point when it is shorter than that. Metres."""
    step = 1 if distance_m >= 0.0 else -1
    left = abs(distance_m)
    cur = points[index]
    k = index + step
    while 0 <= k < len(points):
        q = points[k]
        leg = math.hypot(q[0] - cur[0], q[1] - cur[1])
        if left <= leg and leg >= _DEGENERATE_M:
            f = left / leg
            return cur[0] + f * (q[0] - cur[0]), cur[1] + f * (q[1] - cur[1])
        left -= leg
        cur = q
        k += step
    return cur


def chord_bearing_rad(frm: Point, to: Point) -> float | None:
    """:func:`bearing_rad` of a chord, or None when it is shorter than
    ``TURN_CHORD_M / 10`` (no direction to speak of)."""
    if math.hypot(to[0] - frm[0], to[1] - frm[1]) < 0.1 * TURN_CHORD_M:
        return None
    return bearing_rad(frm, to)


def corner_speed_pct(
    turn_rad: float, cruise_pct: float, min_speed_pct: float, pivot_rad: float
) -> float:
    """Speed (%) to pass a waypoint where the path turns by ``turn_rad``: ``cruise_pct`` up
    to ``STRAIGHT_ON_DEG``, ``min_speed_pct`` from the pivot angle ``pivot_rad`` on (the
    robot stops and pivots there), linear in between; never over ``cruise_pct``."""
    floor = min(min_speed_pct, cruise_pct)
    t = abs(turn_rad)
    straight = math.radians(STRAIGHT_ON_DEG)
    if t <= straight:
        return cruise_pct
    if t >= pivot_rad:
        return floor
    return cruise_pct - (cruise_pct - floor) * (t - straight) / (pivot_rad - straight)


def in_windows(de_m: float, dn_m: float, delta_x_m: float, delta_y_m: float) -> bool:
    """Eq. 7's position windows: ``|de| <= Δx`` and ``|dn| <= Δy`` (true metres east, north)."""
    return abs(de_m) <= delta_x_m and abs(dn_m) <= delta_y_m


def approach_speed_pct(
    distance_m: float,
    cruise_pct: float,
    approach_m: float,
    min_speed_pct: float,
    corner_pct: float | None = None,
) -> float:
    """Drive speed (%) ``distance_m`` from the waypoint: ``cruise_pct`` beyond ``approach_m``,
    then falling linearly with the distance, never under ``min_speed_pct`` (nor over cruise).
    ``corner_pct`` (:func:`corner_speed_pct`, an intermediate waypoint the path turns at by
    less than the pivot angle) raises that floor: the robot slows only to the speed it may
    pass the waypoint at; None is a stop there (the last waypoint, a pivot)."""
    if approach_m <= 0.0 or distance_m >= approach_m:
        return cruise_pct
    floor = min_speed_pct if corner_pct is None else max(min_speed_pct, corner_pct)
    return min(cruise_pct, max(floor, cruise_pct * distance_m / approach_m))


def skid_mix(curvature_per_m: float, speed_pct: float, track_m: float) -> tuple[float, float]:
    """Left/right percentages for an arc of ``curvature_per_m`` (1/m, positive right) at
    ``speed_pct`` (%) on a skid steer of effective track ``track_m`` (m):
    ``left = s·(1 + κT/2)``, ``right = s·(1 − κT/2)``. When a side would exceed 100 % both are
    scaled down together (the arc is kept, the speed drops), the faster side to exactly
    ±100: ``x * 100 / peak`` alone gives 100.00000000000001 for ~3 % of saturated arcs, which
    the motor link refuses as out of range."""
    k = curvature_per_m * track_m / 2.0
    left, right = speed_pct * (1.0 + k), speed_pct * (1.0 - k)
    peak = max(abs(left), abs(right))
    if peak > 100.0:
        left = _saturate(left, peak)
        right = _saturate(right, peak)
    return left, right


def _saturate(value: float, peak: float) -> float:
    """``value`` (%) scaled by ``100 / peak`` into -100..100: the side at the peak to exactly
    ±100, the other never beyond it."""
    if abs(value) >= peak:
        return math.copysign(100.0, value)
    return max(-100.0, min(100.0, value * 100.0 / peak))
