"""The off-course failsafe's watch: does the robot go where it thinks it goes?

Both checks read the GPS fixes alone, not the position estimate, so a fault that the
estimate takes in (a compass knocked round, an offset the EKF has not learnt, a run of
fixes it refused) cannot hide itself:

- *away*: :data:`AWAY_CHECKS` fixes in a row lie ``off_course_m`` farther from the current
  target than the leg's closest fix, and (with wheel encoders) the wheels drove at least
  that far since it: the robot drives away from where it steers to, not a fix beside a wall
  jumping tens of metres while the robot waits;
- *heading*: over the last :data:`COURSE_WINDOW_M` of straight driving, the course the
  fixes made good differs from the heading the robot steered by (its mean over the window)
  by more than ``heading_check_deg``, on :data:`HEADING_CHECKS` windows in a row that do
  not overlap (so over 30 m of straight driving at least). Only
  windows whose fixes could be a straight drive count: a fix that jumped farther than the
  robot can drive (a satellite lost, a reflection beside a wall) starts the window again,
  and a window whose fixes stray more than :data:`STRAY_M` from its chord is skipped.

A leg starts afresh whenever the target changes (the next waypoint, a return to launch) and
on :meth:`CourseWatch.reset` (start, resume, return): the robot may begin anywhere.
"""

from __future__ import annotations

import math
from collections import deque

from x6wd.core.geodesy import EARTH_MEAN_RADIUS_M, great_circle_m, wrap_deg

M_PER_DEG = math.radians(EARTH_MEAN_RADIUS_M)  # m per degree of a great circle

COURSE_WINDOW_M = 10.0
"""Fix-to-fix distance (m) the heading check compares over: at a metre of GPS wander
between fixes a second apart, 10 m keeps the course within about 6 deg."""
HEADING_CHECKS = 3
"""Windows in a row over the limit before the heading check fires (one bad window is a
GPS jump)."""
AWAY_CHECKS = 3
"""Fixes in a row past ``off_course_m`` before the distance check fires (one is a jump)."""
JUMP_M = 3.0
"""A fix farther than this (m) beyond what the robot can drive since the last one is a jump
of the GPS, not motion: the heading window starts again."""
STRAY_M = 2.0
"""The most (m) a window's fixes may lie off its chord: more, and they do not trace one
course (GPS wander, or a tight arc), so the window says nothing of the heading."""


def east_north_m(
    lat0_deg: float, lon0_deg: float, lat_deg: float, lon_deg: float
) -> tuple[float, float]:
    """(east, north) metres of a point from (lat0, lon0) in the local plane at lat0: exact
    enough over the tens of metres the watch compares, and defined up to the poles (unlike
    :class:`x6wd.nav.geo.LocalTangentPlane`, which refuses an origin within 0.1 deg)."""
    k = math.cos(math.radians(lat0_deg)) * M_PER_DEG
    return wrap_deg(lon_deg - lon0_deg) * k, (lat_deg - lat0_deg) * M_PER_DEG


class CourseWatch:
    """The off-course checks, fed one usable fix at a time (sans-IO).

    ``off_course_m`` (m) and ``heading_check_deg`` (deg): 0 turns that check off;
    ``max_speed_mps``: the fastest the robot drives (m/s), to tell motion from a jump."""

    def __init__(self, off_course_m: float, heading_check_deg: float, max_speed_mps: float) -> None:
        self.off_course_m = off_course_m
        self.heading_check_deg = heading_check_deg
        self.max_speed_mps = max_speed_mps
        # straight driving since the last break: (t_s, lat, lon, sin and cos of the
        # headings summed so far)
        self._window: deque[tuple[float, float, float, float, float]] = deque()
        self.reset()

    def reset(self) -> None:
        """Forget the leg and the window (the mission starts, resumes or returns)."""
        self._new_leg(None)

    def _new_leg(self, target: tuple[float, float] | None) -> None:
        self._target = target
        self._best_m = math.inf  # the leg's closest fix to the target (m)
        self._best_travel_m: float | None = None  # the wheels' travel at that fix
        self._window.clear()
        self._bad = 0  # heading windows in a row over the limit
        self._bad_deg = 0.0  # the latest such window's heading error (deg)
        self._away = 0  # fixes in a row past off_course_m

    @property
    def heading_doubt_deg(self) -> float | None:
        """While two or more heading windows in a row lay over ``heading_check_deg`` but the
        check has not fired yet (it needs ``HEADING_CHECKS``): the latest one's heading error
        (deg) from the GPS course, else None. Evidence a failsafe that fires first can name
        (the EKF dead-reckons with a compass mounted 90 deg off and jumps to the fixes); one
        window is not: a GPS drift beside a building bends one stretch of fixes."""
        return self._bad_deg if self._bad >= 2 else None

    def on_fix(
        self,
        t_s: float,
        lat_deg: float,
        lon_deg: float,
        target: tuple[float, float],
        heading_deg: float | None,
        travel_m: float | None = None,
    ) -> str | None:
        """A usable fix at ``t_s`` (s) while running towards ``target`` (lat_deg, lon_deg).
        ``travel_m``: the wheels' distance travelled so far (m, any origin), None without
        encoders.
        ``heading_deg``: the true heading the robot steers by now, when it drives straight
        ahead (None while it pivots, holds or is otherwise not driving straight: the
        heading check's window starts again). The failsafe's reason, or None."""
        target = (float(target[0]), float(target[1]))
        if target != self._target:
            self._new_leg(target)
        d_m = great_circle_m(lat_deg, lon_deg, target[0], target[1])
        if d_m < self._best_m:
            self._best_m, self._best_travel_m = d_m, travel_m
        drove = (
            travel_m is None
            or self._best_travel_m is None
            or travel_m - self._best_travel_m >= self.off_course_m
        )
        if self.off_course_m > 0 and d_m > self._best_m + self.off_course_m and drove:
            self._away += 1
            if self._away >= AWAY_CHECKS:
                self._away = 0
                return (
                    f"off course ({d_m:.0f} m from the target, {d_m - self._best_m:.0f} m "
                    "farther than this leg's closest fix)"
                )
        else:
            self._away = 0
        if self.heading_check_deg <= 0:
            return None
        if heading_deg is None:
            self._window.clear()
            self._bad = 0
            return None
        return self._heading_check(t_s, lat_deg, lon_deg, heading_deg)

    def _heading_check(
        self, t_s: float, lat_deg: float, lon_deg: float, heading_deg: float
    ) -> str | None:
        w = self._window
        h = math.radians(heading_deg)
        s, c = math.sin(h), math.cos(h)
        if w:
            last = w[-1]
            reach_m = self.max_speed_mps * max(0.0, t_s - last[0]) + JUMP_M
            if great_circle_m(last[1], last[2], lat_deg, lon_deg) > reach_m:
                w.clear()  # a jump of the GPS: its course says nothing
            else:
                s += last[3]
                c += last[4]
        w.append((t_s, lat_deg, lon_deg, s, c))
        first = w[0]
        if great_circle_m(first[1], first[2], lat_deg, lon_deg) < COURSE_WINDOW_M:
            return None
        # the mean heading since the window's first fix (cumulative sums: one subtraction)
        mean_deg = math.degrees(math.atan2(s - first[3], c - first[4]))
        east, north = east_north_m(first[1], first[2], lat_deg, lon_deg)
        course = math.degrees(math.atan2(east, north))
        off_deg = abs(wrap_deg(course - mean_deg))
        straight = self._strays_m(course) <= STRAY_M
        while len(w) > 2 and great_circle_m(w[1][1], w[1][2], lat_deg, lon_deg) >= COURSE_WINDOW_M:
            w.popleft()
        if not straight:
            return None  # neither evidence for nor against
        if off_deg <= self.heading_check_deg:
            self._bad = 0
            return None
        self._bad += 1
        self._bad_deg = off_deg
        # the next window starts here: the checks in a row cover fresh stretches (a GPS
        # drift bends one stretch of fixes, not three in turn)
        w.clear()
        w.append((t_s, lat_deg, lon_deg, s, c))
        if self._bad < HEADING_CHECKS:
            return None
        self._bad = 0
        self._window.clear()
        return (
            f"off course (heading {off_deg:.0f} deg from the GPS course over "
            f"{COURSE_WINDOW_M:g} m: a compass fault?)"
        )

    def _strays_m(self, course: float) -> float:
        """How far (m) the window's fixes lie off the line from its first fix along
        ``course`` (deg true), at most."""
        w = self._window
        lat0, lon0 = w[0][1], w[0][2]
        ux, uy = math.sin(math.radians(course)), math.cos(math.radians(course))
        worst = 0.0
        for _t, lat, lon, _s, _c in w:
            east, north = east_north_m(lat0, lon0, lat, lon)
            worst = max(worst, abs(east * uy - north * ux))
        return worst
