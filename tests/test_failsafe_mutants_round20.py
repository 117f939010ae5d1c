"""The controller's failsafes at their edges (round 20: mutmut's area ``failsafes``).

The failsafes that came with the EKF had been checked by hand mutations only, which remove a
whole behaviour; mutmut's first run over them (docs/testing.md, "Mutation testing") left 282
survivors (27 %) in their edges, directions and settings: the direction and the noise a dead
encoder is judged by, the GPS's agreement with an EKF arrival, the progress a watch wants,
timeouts at 0 (off), a return's declination. Each test here fails on such mutants; sans-IO,
fast.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import replace

import pytest

from tests.test_compass_frozen_round19 import pivot
from tests.test_controller import NAV, SAFETY, at, att, fix
from tests.test_failsafe_controller import COUNTS_PER_M, FS
from x6wd.core.config import FailsafeConfig, GnssNoiseConfig, NavigationConfig, SafetyConfig
from x6wd.core.records import GpsFix, Mode, NavState, WheelOdometry
from x6wd.nav.controller import (
    ARRIVAL_GPS_SIGMAS,
    ENCODER_FAULT_SIGMAS,
    UNCERTAIN_RELEASE,
    Controller,
)
from x6wd.nav.position import DEFAULT_HDOP, degraded_radius_m

# re, ase and lce where each of their squares differs from twice them and from their cube
NOISE = GnssNoiseConfig(re_m=1.5, ase_m=2.5, lce_default_m=3.0)
NOISE_M = math.sqrt(1.5**2 + 2.5**2 + 3.0**2)


def fix_at(t_s: float, x_m: float, y_m: float, hdop: float | None) -> GpsFix:
    lat, lon = at(x_m, y_m)
    return GpsFix(t_s=t_s, lat_deg=lat, lon_deg=lon, valid=True, quality=1, mode=3, hdop=hdop)


def dead_encoder_reason(
    bearing_deg: float, jump_m: float, hdop: float | None, noise: GnssNoiseConfig = NOISE
) -> str:
    """A mission 300 m away along ``bearing_deg``, the robot facing it, its encoders counting
    nothing: the fixes stand at the start for 5 s, then ``jump_m`` ahead along the bearing
    (an exact net move, whatever second the wheels' test fires at); the off-course watch off
    (a jump back would trip it). The pause's reason."""
    b = math.radians(bearing_deg)
    c = Controller(NAV, SAFETY, failsafe=replace(FS, off_course_m=0.0), gnss_noise=noise)
    c.on_fix(fix_at(0.0, 0.0, 0.0, hdop))
    c.on_attitude(att(0.0, bearing_deg))
    c.load_mission([at(300.0 * math.sin(b), 300.0 * math.cos(b))], 0.0)
    c.start(0.0)
    for k in range(1, 30):
        s_m = 0.0 if k <= 5 else jump_m
        t = float(k)
        c.on_attitude(att(t, bearing_deg))
        c.on_fix(fix_at(t, s_m * math.sin(b), s_m * math.cos(b), hdop))
        c.on_odometry(WheelOdometry(t, 0, 0, k))
        if c.mode != Mode.RUNNING:
            break
    assert c.mode == Mode.PAUSED
    return str(c.telemetry.extra["failsafe"])


def ekf_started(
    north_m: float,
    nav: NavigationConfig | None = None,
    safety: SafetyConfig = SAFETY,
    fs: FailsafeConfig = FS,
    noise: GnssNoiseConfig | None = None,
    hdop: float | None = 1.2,
) -> Controller:
    """The robot's EKF with a mission ``north_m`` north, started at 2 s after a fix at the
    origin (``hdop``) and 2 s of compass samples facing north."""
    c = Controller(
        nav or NavigationConfig(), safety, 0.0, failsafe=fs, gnss_noise=noise or GnssNoiseConfig()
    )
    c.on_fix(fix_at(0.0, 0.0, 0.0, hdop))
    for k in range(1, 21):
        c.on_attitude(att(0.1 * k))
    c.load_mission([at(0.0, north_m)], 2.0)
    c.start(2.0)
    return c


def drive_north_fixes_off(
    c: Controller, off_m: float, hdop: float | None = 1.2, until: Mode | None = None
) -> Iterator[float]:
    """Drive ``c`` (started at 2 s) north at 2 m/s for 14 s, encoders and compass at 10 Hz,
    fixes at 1 Hz ``off_m`` east of the track from 9.5 s on; yields each step's time, and
    stops early once the mode is ``until``."""
    for k in range(1, 141):
        t, y_m = 2.0 + 0.1 * k, 0.2 * k
        counts = round(y_m * COUNTS_PER_M)
        c.on_odometry(WheelOdometry(t, counts, counts, k))
        c.on_attitude(att(t))
        if k % 10 == 0:
            c.on_fix(fix_at(t, off_m if t > 9.5 else 0.0, y_m, hdop))
        yield t
        if until is not None and c.mode == until:
            return


ENCODERS = "encoders: under 0.2 m counted in 10 s of driving while the fixes show motion"
BLOCKED = "stuck (the wheels: no motion in 10 s of driving)"


def threshold_m(hdop: float | None) -> float:
    h = hdop if hdop is not None and hdop > 0 else DEFAULT_HDOP
    return ENCODER_FAULT_SIGMAS * max(h * NOISE_M, FS.stuck_min_m)


@pytest.mark.parametrize("bearing_deg", [0.0, 45.0, 90.0, 180.0, 225.0, 270.0])
@pytest.mark.parametrize("hdop", [1.2, 0.9, 0.0, None])
def test_fixes_ahead_of_dead_encoders_name_them_only_beyond_3_sigma_in_any_direction(
    bearing_deg: float, hdop: float | None
) -> None:
    """Just beyond 3 sigma of the GPS's noise (HDOP x sqrt(RE^2 + ASE^2 + LCE^2); HDOP 2
    where the fix has none or 0) ahead along the heading, the encoders are named; just short
    of it, or as far behind, the wheels are blocked."""
    edge_m = threshold_m(hdop)
    assert edge_m > 3.0 * FS.stuck_min_m  # the noise decides, not stuck_min_m
    assert dead_encoder_reason(bearing_deg, 1.01 * edge_m, hdop) == ENCODERS
    assert dead_encoder_reason(bearing_deg, 0.99 * edge_m, hdop) == BLOCKED
    assert dead_encoder_reason(bearing_deg, -1.01 * edge_m, hdop) == BLOCKED


def test_a_small_noise_is_floored_at_stuck_min_m() -> None:
    quiet = replace(NOISE, re_m=0.1, ase_m=0.1, lce_default_m=0.0)
    edge_m = ENCODER_FAULT_SIGMAS * FS.stuck_min_m
    assert dead_encoder_reason(0.0, 1.01 * edge_m, 1.0, quiet) == ENCODERS
    assert dead_encoder_reason(0.0, 0.99 * edge_m, 1.0, quiet) == BLOCKED


# ------------------------------------------------------------ driving on without a fix


def outage(
    nav: NavigationConfig,
    safety: SafetyConfig,
    fs: FailsafeConfig = FS,
    blocked_from_s: float | None = None,
) -> tuple[float, str, str]:
    """A mission 1 km north, driven at 2 m/s (encoders and compass at 10 Hz) with fixes at
    1 Hz until 20 s and none after; the wheels count nothing from ``blocked_from_s``. The
    first time after the last fix the robot held or paused, its state's reason and the
    failsafe's (empty if none)."""
    c = ekf_started(1000.0, nav, safety, fs)
    y_m = 0.0
    for k in range(1, 1201):
        t = 2.0 + 0.1 * k
        if blocked_from_s is None or t < blocked_from_s:
            y_m += 0.2
        counts = round(y_m * COUNTS_PER_M)
        c.on_odometry(WheelOdometry(t, counts, counts, k))
        c.on_attitude(att(t))
        if k % 10 == 0 and t <= 20.0 + 1e-9:
            c.on_fix(fix(t, 0.0, y_m))
        tel = c.telemetry
        if t > 20.0 and (tel.state == NavState.HOLD or c.mode != Mode.RUNNING):
            return t, tel.hold_reason, str(tel.extra.get("failsafe", ""))
    raise AssertionError("never held")


STALE_AT_S = 20.0 + SAFETY.fix_stale_s


@pytest.mark.parametrize(
    ("source", "outage_m"), [("ekf", 0.0), ("constellation", 20.0), ("raw", 20.0)]
)
def test_without_the_ekf_or_with_no_outage_allowed_the_robot_holds_once_the_fix_is_stale(
    source: str, outage_m: float
) -> None:
    """Dead reckoning needs the EKF (another source has no estimate of its own to drive on:
    it steers by the last fix) and ``gps_outage_max_m`` over 0 (0: the paper's hold at once),
    the encoders reporting in both."""
    nav = replace(NavigationConfig(), position_source=source)
    t, why, _ = outage(nav, replace(SAFETY, gps_outage_max_m=outage_m))
    assert why == "fix stale" and t == pytest.approx(STALE_AT_S, abs=0.15), (t, why)


def test_the_ekf_drives_on_without_a_fix_until_its_allowance() -> None:
    t, why, _ = outage(NavigationConfig(), replace(SAFETY, gps_outage_max_m=20.0))
    assert why == "fix stale" and t == pytest.approx(20.0 + 10.0, abs=0.15), (t, why)


def test_a_robot_blocked_in_an_outage_pauses_on_its_wheels_before_the_commanded_bound() -> None:
    """Blocked 1 s into the outage, 22 m driven with fixes before it: the wheels' own test
    pauses it 10 s after the block, with its own reason. The commanded bound (1.5 x 20 m of
    commanded travel since the last fix, at 60 % of 3.888 m/s: 12.9 s) is not reached, and
    the travel commanded before the last fix does not count towards it."""
    t, _why, failsafe = outage(
        NavigationConfig(), replace(SAFETY, gps_outage_max_m=20.0), blocked_from_s=21.0
    )
    assert failsafe == "stuck (the wheels: no motion in 10 s of driving)", (t, failsafe)
    assert t == pytest.approx(31.0, abs=0.25)


# ------------------------------------------------------------------ the stuck check


def stuck_reason(
    fs: FailsafeConfig,
    bearing_deg: float = 0.0,
    wheels_mps: float = 0.0,
    fixes_mps: float = 0.0,
    seconds: float = 25.0,
) -> str:
    """A mission 300 m along ``bearing_deg``, the robot facing it at cruise (60 %): the wheels
    count ``wheels_mps`` and the fixes move ``fixes_mps`` along it (encoders and compass at
    10 Hz, fixes at 1 Hz). The failsafe's reason ("" if none in ``seconds``)."""
    b = math.radians(bearing_deg)
    c = Controller(NAV, SAFETY, failsafe=replace(fs, off_course_m=0.0))
    c.on_fix(fix(0.0))
    c.on_attitude(att(0.0, bearing_deg))
    c.on_odometry(WheelOdometry(0.0, 0, 0, 0))
    c.load_mission([at(300.0 * math.sin(b), 300.0 * math.cos(b))], 0.0)
    c.start(0.0)
    for k in range(1, round(10 * seconds) + 1):
        t = 0.1 * k
        counts = round(wheels_mps * t * COUNTS_PER_M)
        c.on_odometry(WheelOdometry(t, counts, counts, k))
        c.on_attitude(att(t, bearing_deg))
        if k % 10 == 0:
            s_m = fixes_mps * t
            c.on_fix(fix(t, s_m * math.sin(b), s_m * math.cos(b)))
        if c.mode != Mode.RUNNING:
            return str(c.telemetry.extra["failsafe"])
    return ""


WHEELS = "stuck (the wheels: no motion in 10 s of driving)"
SLIPPING = "stuck (the GPS: no motion in 10 s of driving)"


@pytest.mark.parametrize("bearing_deg", [0.0, 90.0, 270.0])
def test_a_blocked_or_slipping_robot_is_stuck_facing_any_way(bearing_deg: float) -> None:
    """Blocked (nothing moves) or slipping (the wheels count 2 m/s, the fixes stand): facing
    north, east or west, the compass standing still is no motion."""
    assert stuck_reason(FS, bearing_deg) == WHEELS
    assert stuck_reason(FS, bearing_deg, wheels_mps=2.0) == SLIPPING


def test_a_drive_under_stuck_min_pct_is_never_stuck_and_one_at_it_is() -> None:
    """Cruise is 60 %: with ``stuck_min_pct`` 61 (or 85, under 1.5 x 60) the blocked robot
    is not judged; at 60 exactly it is."""
    assert stuck_reason(replace(FS, stuck_min_pct=61.0)) == ""
    assert stuck_reason(replace(FS, stuck_min_pct=85.0)) == ""
    assert stuck_reason(replace(FS, stuck_min_pct=60.0)) == WHEELS


def test_wheels_creeping_under_a_tenth_of_stuck_min_m_are_still() -> None:
    """0.1 m counted in 10 s (under 0.2 m, a tenth of ``stuck_min_m``; over a twentieth):
    the wheels stood still."""
    assert stuck_reason(FS, wheels_mps=0.01) == WHEELS


def test_a_pivot_under_stuck_min_pct_is_never_stuck_and_one_at_it_is() -> None:
    """The target behind the robot: it pivots at ``turn_pct`` (40 %), blocked (the wheels
    and the compass stand still). With ``stuck_min_pct`` 50 (under 1.5 x 40) the pivot is not
    judged; at 40 it is, by the compass."""

    def reason(fs: FailsafeConfig) -> str:
        c = Controller(NAV, SAFETY, failsafe=replace(fs, off_course_m=0.0))
        c.on_fix(fix(0.0))
        c.on_attitude(att(0.0, 180.0))
        c.on_odometry(WheelOdometry(0.0, 0, 0, 0))
        c.load_mission([at(0.0, 300.0)], 0.0)
        c.start(0.0)
        for k in range(1, 251):
            t = 0.1 * k
            c.on_odometry(WheelOdometry(t, 0, 0, k))
            c.on_attitude(att(t, 180.0))
            if k % 10 == 0:
                c.on_fix(fix(t))
            if c.mode != Mode.RUNNING:
                return str(c.telemetry.extra["failsafe"])
        return ""

    assert reason(replace(FS, stuck_min_pct=50.0)) == ""
    assert reason(replace(FS, stuck_min_pct=40.0)).startswith("stuck (")


# ------------------------------------------------------------------ return to launch


def test_a_return_steers_by_the_compass_corrected_for_declination() -> None:
    """Declination 20°: the robot 20 m north of its launch point reads magnetic 160°, true
    180°, straight at it: the return drives straight on (read as magnetic, 20° off, it would
    pivot first)."""
    c = Controller(NAV, SAFETY, 20.0, failsafe=FS)
    c.on_fix(fix(0.0))
    c.on_attitude(att(0.0, 340.0))  # true north
    c.load_mission([at(0.0, 100.0)], 0.0)
    c.start(0.0)
    for k in range(1, 11):
        c.on_attitude(att(float(k), 340.0))
        c.on_fix(fix(float(k), 0.0, 2.0 * k))
    assert c.state == NavState.STRAIGHT
    c.return_home(10.5)
    c.on_attitude(att(11.0, 160.0))
    c.on_fix(fix(11.0, 0.0, 20.0))
    assert c.returning == "return" and c.state == NavState.STRAIGHT, c.state


# ------------------------------------------------------------------ a frozen compass


def test_the_same_reading_for_under_a_second_in_a_fast_pivot_is_not_frozen() -> None:
    """A compass whose reading holds 0.9 s at a time (a slow or filtered one) while the
    wheels' counts turn the robot 234°/s: over 90° between two equal readings, but for
    under ``FROZEN_MIN_S``; it then moves on 20°. Not frozen."""
    c, _t = pivot(lambda k, t: att(t, (20.0 * (k // 9)) % 360.0), 100, mps=0.5)
    assert "frozen" not in c.telemetry.extra.get("failsafe", ""), c.telemetry.extra


# ------------------------------------------------------------------ the EKF's arrival


@pytest.mark.parametrize("off_m", [15.0, 12.0])
def test_the_ekf_does_not_arrive_where_the_latest_fix_disagrees(off_m: float) -> None:
    """The EKF, a waypoint 20 m north, driven at 2 m/s; from 9.5 s the fixes run ``off_m``
    east of the track (the EKF refuses them as outliers and runs on on its wheels). At 12 s
    the estimate is on the waypoint but the fix is 12-15 m from it, over max(5 m, 3 sigma at
    HDOP 1.2) plus the 3.9 m drivable in the second since the fix: not reached. (Wheels
    spinning on the spot are not the case to test it with: the EKF learns their slip, so its
    estimate stays within metres of the standing fixes.)"""
    c = ekf_started(20.0)
    nearest_m = math.inf
    for t in drive_north_fixes_off(c, off_m):
        nearest_m = min(nearest_m, c.telemetry.distance_m or math.inf)
        assert c.mode == Mode.RUNNING and c.telemetry.waypoint_index == 0, (t, c.mode)
    assert nearest_m < 1.0  # the estimate did reach it


@pytest.mark.parametrize(
    ("second", "reached"), [((0.0, 60.0), True), ((40.0, 20.0), False), ((-40.0, 20.0), False)]
)
@pytest.mark.parametrize("off_m", [15.0, -15.0])
def test_the_ekf_arrives_at_a_track_point_the_fix_has_passed_but_not_at_a_corner(
    second: tuple[float, float], reached: bool, off_m: float
) -> None:
    """pivot_arc, waypoint 1 20 m north and the fixes 15 m to either side from 9.5 s (over
    the 3 sigma agreement): where the path goes straight on (waypoint 2 60 m north), the fix
    on the waypoint's line at 12 s is past it along the track and the robot drives on; at a
    corner (waypoint 2 40 m east or west of it) the distance rule holds it to waypoint 1."""
    c = Controller(NavigationConfig(), SAFETY, 0.0, failsafe=FS, gnss_noise=GnssNoiseConfig())
    c.on_fix(fix_at(0.0, 0.0, 0.0, 1.2))
    for k in range(1, 21):
        c.on_attitude(att(0.1 * k))
    c.load_mission([at(0.0, 20.0), at(*second)], 2.0)
    c.start(2.0)
    passed_s = None
    for t in drive_north_fixes_off(c, off_m):
        if passed_s is None and c.telemetry.waypoint_index == 1:
            passed_s = t
    assert passed_s == (pytest.approx(12.0) if reached else None)


# ------------------------------------------------------------------ the progress watch


def test_a_robot_spiralling_in_too_slowly_pauses_for_no_progress() -> None:
    """Circling its waypoint at 1 m/s, 30 m out, the circle shrinking 1 m every 20 s: the
    progress watch (20 s here) wants 2 m nearer (or half the distance, were that less) in
    that time, not any gain at all."""
    fs = replace(FS, stuck_s=0.0, progress_timeout_s=20.0, off_course_m=0.0)
    c = Controller(NAV, SAFETY, failsafe=fs)
    c.on_fix(fix(0.0, 0.0, 30.0))
    c.on_attitude(att(0.0, 90.0))
    c.load_mission([at(0.0, 60.0)], 0.0)
    c.start(0.0)
    t, a = 0.1, 0.0
    while t <= 60.0 and c.mode == Mode.RUNNING:
        r_m = 30.0 - t / 20.0
        a += 0.1 / r_m
        c.on_attitude(att(t, math.degrees(a + math.pi / 2) % 360.0))
        if abs(t - round(t)) < 1e-6:
            c.on_fix(fix(t, r_m * math.sin(a), 60.0 - r_m * math.cos(a)))
        t = round(t + 0.1, 1)
    assert c.mode == Mode.PAUSED, c.telemetry
    why = str(c.telemetry.extra["failsafe"])
    assert why.startswith("no progress to waypoint 1: 20 s of driving without coming 2 m"), why
    assert t < 25.0, t


def test_the_progress_watch_starts_again_at_each_waypoint() -> None:
    """Two legs of 40 s each (40 m at 1 m/s, straight at each waypoint): 80 s of driving in
    all, over the watch's 60 s, yet each leg made steady progress. Completed, no pause."""
    c = Controller(NAV, SAFETY, failsafe=replace(FS, progress_timeout_s=60.0))
    c.on_fix(fix(0.0))
    c.on_attitude(att(0.0))
    targets = [(0.0, 40.0), (40.0, 40.0)]
    c.load_mission([at(*p) for p in targets], 0.0)
    c.start(0.0)
    x, y, t = 0.0, 0.0, 0.0
    while t < 120.0 and c.mode == Mode.RUNNING:
        t = round(t + 0.1, 1)
        i = c.telemetry.waypoint_index or 0
        tx, ty = targets[min(i, 1)]
        d = math.hypot(tx - x, ty - y)
        if d > 1e-9:
            step = min(0.1, d)
            x, y = x + step * (tx - x) / d, y + step * (ty - y) / d
        c.on_attitude(att(t, math.degrees(math.atan2(tx - x, ty - y)) % 360.0 if d > 0.2 else 0.0))
        if abs(t - round(t)) < 1e-6:
            c.on_fix(fix(t, x, y))
    assert c.mode == Mode.DONE, (t, c.mode, c.telemetry.extra.get("failsafe"))
    assert t > 70.0


@pytest.mark.parametrize("off_m", [4.0, 8.0])
def test_the_ekf_arrives_where_the_latest_fix_agrees_within_its_noise_and_drive(
    off_m: float,
) -> None:
    """As above with the fixes 4 m (under the 5 m floor) or 8 m off: 8 m is over 3 sigma at
    HDOP 1.2 (6.5 m) but within it plus the distance drivable since the fix (3.9 m/s) from
    0.4 s after it. The waypoint is reached within 1.5 s of the estimate getting there."""
    c = ekf_started(20.0)
    t = max(drive_north_fixes_off(c, off_m, until=Mode.DONE))
    assert c.mode == Mode.DONE and t <= 13.5, (t, c.mode)


@pytest.mark.parametrize(
    ("hdop", "factor"),
    [(1.2, 0.99), (1.2, 1.01), (0.9, 1.01), (None, 0.99), (0.0, 0.99)],
)
def test_the_ekf_arrival_s_agreement_is_3_sigma_of_the_gps_noise(
    hdop: float | None, factor: float
) -> None:
    """The same with a site's noise (RE 1.5, ASE 2.5, LCE 3 m) and a slow robot
    (``full_speed_mps`` 0.01: nothing drivable between fixes): the fix ``factor`` x 3 sigma
    (HDOP x sqrt(RE^2 + ASE^2 + LCE^2); HDOP 2 for a fix without one or with 0: an RMC-only
    receiver) off agrees at 0.99, not at 1.01."""
    c = ekf_started(20.0, replace(NavigationConfig(), full_speed_mps=0.01), noise=NOISE)
    h = hdop if hdop is not None and hdop > 0 else DEFAULT_HDOP
    off_m = factor * ARRIVAL_GPS_SIGMAS * h * NOISE_M
    for _t in drive_north_fixes_off(c, off_m, hdop, until=Mode.DONE):
        pass
    assert (c.mode == Mode.DONE) == (factor < 1.0), (c.mode, c.telemetry.extra.get("failsafe"))


# ------------------------------------------------------------------ too uncertain to arrive


def uncertain_states(
    hdops: list[float], noise: GnssNoiseConfig, waypoint_m: float
) -> list[tuple[NavState, str]]:
    """The EKF started at rest on fixes at ``hdops[0]``, a waypoint ``waypoint_m`` north;
    each later HDOP held for 8 s (the fixes at the start, the wheels still, the stuck check
    off). The (state, hold reason) at the end of each HDOP's spell."""
    c = ekf_started(waypoint_m, fs=replace(FS, stuck_s=0.0), noise=noise, hdop=hdops[0])
    out, k = [], 0
    for hdop in hdops:
        for _ in range(80):
            k += 1
            t = 2.0 + 0.1 * k
            c.on_odometry(WheelOdometry(t, 0, 0, k))
            c.on_attitude(att(t))
            if k % 10 == 0:
                c.on_fix(fix_at(t, 0.0, 0.0, hdop))
        out.append((c.telemetry.state, c.telemetry.hold_reason))
    return out


TOO_UNCERTAIN = "position too uncertain to tell whether waypoint 1 is reached"


def test_a_site_s_own_noise_widens_the_radius_a_waypoint_may_be_judged_in() -> None:
    """A site with RE 1.5, ASE 2.5, LCE 3 m: 3 sigma of its noise at HDOP 3 is 37.6 m, over
    ``arrival_max_error_m`` (30 m). Started at HDOP 3 the EKF's radius is 35 m, the waypoint
    25 m off inside it: within the site's usual noise, the robot drives. Started at HDOP 4
    (47 m) it holds."""
    assert uncertain_states([3.0], NOISE, 25.0) == [(NavState.STRAIGHT, "")]
    assert uncertain_states([4.0], NOISE, 25.0) == [(NavState.HOLD, TOO_UNCERTAIN)]


def test_a_waypoint_outside_the_error_radius_is_driven_to_however_poor_the_fixes() -> None:
    """HDOP 12 (a radius of 55 m with the default noise), the waypoint 200 m off: the robot
    can tell it has not arrived, so it drives."""
    assert uncertain_states([12.0], GnssNoiseConfig(), 200.0) == [(NavState.STRAIGHT, "")]


def test_a_held_robot_drives_on_only_once_the_radius_is_under_release_of_its_limit() -> None:
    """Started on HDOP 4 fixes at a site whose noise sets the limit (37.6 m), the robot holds
    for waypoint 1, 25 m off; HDOP 1 fixes from 10 s shrink the EKF's radius slowly (the slow
    errors do not average out). At every input the hold follows its rule: once held, until
    the radius is at most ``UNCERTAIN_RELEASE`` of the limit (no stop-and-go about the
    limit), else while it exceeds the limit. The radius passes through the band between the
    two while held, and the robot drives on within a minute."""
    c = ekf_started(25.0, fs=replace(FS, stuck_s=0.0), noise=NOISE, hdop=4.0)
    held = banded = False
    for k in range(10, 601):  # from the first fix after the start's (2.5 s stale)
        t = 2.0 + 0.1 * k
        c.on_odometry(WheelOdometry(t, 0, 0, k))
        c.on_attitude(att(t))
        if k % 10 == 0:
            c.on_fix(fix_at(t, 0.0, 0.0, 4.0 if t < 10.0 else 1.0))
        tel = c.telemetry
        radius_m = ARRIVAL_GPS_SIGMAS * tel.extra["ekf_sigma_m"] / math.sqrt(2.0)
        limit_m = degraded_radius_m(
            NavigationConfig().arrival_max_error_m, tel.extra["ekf_noise_hdop1_m"]
        )
        in_band = UNCERTAIN_RELEASE * limit_m < radius_m <= limit_m
        banded |= held and in_band
        held = (held and radius_m > UNCERTAIN_RELEASE * limit_m) or radius_m > limit_m
        assert tel.hold_reason == (TOO_UNCERTAIN if held else ""), (t, radius_m, limit_m)
    assert banded, "the radius never lay between the release and the limit while held"
    assert c.telemetry.state == NavState.STRAIGHT


def test_the_uncertain_hold_s_patience_starts_again_for_a_return_to_launch() -> None:
    """``position_timeout_s`` is the time held for one target in all: held 20 s for
    waypoint 1, then sent home (the robot stands at the launch point, inside the same
    radius), the return waits its own 30 s before the pause, not the 10 s left."""
    c = ekf_started(
        25.0, fs=replace(FS, stuck_s=0.0, position_timeout_s=30.0), noise=NOISE, hdop=4.0
    )
    for k in range(1, 1001):
        t = 2.0 + 0.1 * k
        if k == 200:
            c.return_home(t)
        c.on_odometry(WheelOdometry(t, 0, 0, k))
        c.on_attitude(att(t))
        if k % 10 == 0:
            c.on_fix(fix_at(t, 0.0, 0.0, 4.0))
        if c.mode != Mode.RUNNING:
            break
    assert c.mode == Mode.PAUSED
    assert c.telemetry.extra["failsafe"] == (
        "position too uncertain to tell whether the launch point is reached for 30 s"
    )
    assert t == pytest.approx(22.0 + 30.0, abs=0.15)


# ------------------------------------------------------------------ timeouts at 0: off


def test_position_timeout_s_0_waits_for_the_sky_without_end() -> None:
    fs = replace(FS, stuck_s=0.0, position_timeout_s=0.0)
    c = ekf_started(25.0, fs=fs, noise=NOISE, hdop=4.0)
    for k in range(1, 1501):  # 150 s, over the default 120 s
        t = 2.0 + 0.1 * k
        c.on_odometry(WheelOdometry(t, 0, 0, k))
        c.on_attitude(att(t))
        if k % 10 == 0:
            c.on_fix(fix_at(t, 0.0, 0.0, 4.0))
    assert c.mode == Mode.RUNNING and c.telemetry.hold_reason == TOO_UNCERTAIN


def raw_started(fs: FailsafeConfig) -> Controller:
    """The raw GPS source (no dead reckoning), a mission 300 m north started facing it."""
    c = Controller(NAV, SAFETY, failsafe=fs)
    c.on_fix(fix(0.0))
    c.on_attitude(att(0.0))
    c.load_mission([at(0.0, 300.0)], 0.0)
    c.start(0.0)
    return c


@pytest.mark.parametrize("timeout_s", [0.0, 30.0])
def test_sensor_timeout_s_0_holds_until_the_fix_comes_back(timeout_s: float) -> None:
    """The fixes stop for 60 s (the raw GPS: no dead reckoning): a hold, then a pause after
    ``sensor_timeout_s``; at 0 the hold lasts, and the robot drives on with the fix."""
    c = raw_started(replace(FS, stuck_s=0.0, sensor_timeout_s=timeout_s))
    for k in range(1, 801):
        t = 0.1 * k
        c.on_attitude(att(t))
        if k % 10 == 0 and not 5.0 < t < 65.0:
            c.on_fix(fix(t))
    if timeout_s == 0.0:
        assert c.mode == Mode.RUNNING and c.state == NavState.STRAIGHT, c.telemetry
    else:
        assert c.mode == Mode.PAUSED
        assert c.telemetry.extra["failsafe"] == "fix stale for 30 s"


def test_a_lost_motor_link_holds_without_a_failsafe_and_drives_on_when_it_returns() -> None:
    """The motor board's link lost for 60 s: the robot holds (its board's own watchdog
    stops the wheels), but no sensor's timeout pauses the mission: it drives on after."""
    c = raw_started(replace(FS, stuck_s=0.0))
    for k in range(1, 801):
        t = 0.1 * k
        if k == 50:
            c.motor_link(False, t)
        if k == 650:
            c.motor_link(True, t)
        c.on_attitude(att(t))
        if k % 10 == 0:
            c.on_fix(fix(t))
        if 6.0 < t < 64.0:
            assert c.state == NavState.HOLD and c.telemetry.hold_reason == "motor link lost"
    assert c.mode == Mode.RUNNING and c.state == NavState.STRAIGHT, c.telemetry


def test_a_robot_blocked_in_an_outage_is_paused_at_the_commanded_bound_on_a_stale_fix() -> None:
    """Blocked 5 s into the outage (the fixes stop: stale, not invalid): at the commanded
    bound (30 m since the last fix, 12.9 s) the wheels have stood 7.9 s, under ``stuck_s``:
    paused at once, named, rather than held until the sensor's timeout."""
    t, _why, failsafe = outage(
        NavigationConfig(), replace(SAFETY, gps_outage_max_m=20.0), blocked_from_s=25.0
    )
    assert failsafe.startswith("stuck (the wheels: no motion in 8 s of driving, 30 m commanded"), (
        t,
        failsafe,
    )


def test_with_the_stuck_check_off_a_robot_blocked_in_an_outage_waits_for_the_sensor() -> None:
    """``stuck_s`` 0 turns the stuck checks off, the commanded bound's pause too: the robot
    holds at the bound and the sensor's timeout pauses it 30 s later."""
    t, why, failsafe = outage(
        NavigationConfig(),
        replace(SAFETY, gps_outage_max_m=20.0),
        fs=replace(FS, stuck_s=0.0),
        blocked_from_s=25.0,
    )
    assert why == "fix stale" and failsafe == "", (t, why, failsafe)


def test_an_arc_on_a_straight_is_not_judged_as_a_pivot() -> None:
    """pivot_arc steering drives a straight as an arc when the heading is off (here a steady
    8°, the sides 3-10 % apart): not a pivot, even with ``stuck_min_pct`` 2 so the arc counts
    as turning. The pivot check judges only the TURN states (a steady 8° never comes 10°
    nearer, so it would pause)."""
    c = ekf_started(300.0, fs=replace(FS, stuck_min_pct=2.0))
    x_m = y_m = 0.0
    b = math.radians(8.0)
    for k in range(1, 251):
        t = 2.0 + 0.1 * k
        x_m, y_m = x_m + 0.2 * math.sin(b), y_m + 0.2 * math.cos(b)
        counts = round(0.2 * k * COUNTS_PER_M)
        c.on_odometry(WheelOdometry(t, counts, counts, k))
        c.on_attitude(att(t, 8.0))
        if k % 10 == 0:
            c.on_fix(fix(t, x_m, y_m))
        assert c.state == NavState.STRAIGHT, (t, c.state)
    cmd = c.command
    assert c.mode == Mode.RUNNING and 0.5 * abs(cmd.left_pct - cmd.right_pct) > 2.0
