"""The sans-IO core: sensor records and operator requests in (each with its time), motor
commands, telemetry and state changes out.

It never reads a clock, sleeps or touches a socket: the caller passes ``t_s`` (seconds on one
monotonic clock) with every input, so the same inputs always give the same outputs. The
controller's "now" is the latest time it was given; an input stamped earlier (records from
different devices may interleave) is accepted but does not move time backwards.

Every call returns, in this order: zero or more :class:`StateChange` (mode first, then
navigation state; ``old``/``new`` are the enum values, ``reason`` starts with ``mode:`` or
``state:``), then the current :class:`MotorCommand` (so the daemon can feed the motor board's
watchdog with every call, and a fix reaches the motors in the same call), then a
:class:`Telemetry` snapshot.

Pipeline: valid fixes feed one Constellation filter per axis (latitude and longitude); the
filtered position is projected as configured; the compass's magnetic bearing is mapped to the
paper's (−180°, 180°] and corrected by the declination; the :class:`Navigator` decides.

Safety: while RUNNING, the motors stop and the state is HOLD (with ``hold_reason``) when the
motor link is lost, a sensor's reader reports it unusable (:meth:`Controller.sensor_health`:
"gps disconnected", "compass stale", ...; at once, not after the staleness limits), the
latest fix is invalid or the last valid fix is older than ``safety.fix_stale_s`` (except
that the EKF, with the wheel encoders reporting, drives on through such a gap for
``safety.gps_outage_max_m`` of wheel travel: beside a building the fix comes back a few metres
on), the attitude is missing, invalid or older than ``safety.attitude_stale_s``. Navigation
resumes by itself once every input is fresh again; after a sensor comes back, only once
fresh data stamped at or after its return arrived (a valid fix, a valid compass sample).
Manual drive is capped at ``safety.manual_max_s`` and expires (dead-man) into IDLE; a lost
motor link cancels it. Manual drive does NOT depend on the sensors: the operator drives by
sight, the dead-man bounds it, and a GPS or compass fault neither refuses nor cancels it.
:meth:`Controller.stop` works from any state.

Skid-steer mixing (the paper turns on the spot): STRAIGHT -> both sides ``cruise_pct``
(with ``steering = "pivot_arc"``: the navigator's arc, :func:`x6wd.nav.steering.skid_mix` of
its curvature at its approach speed over ``steer_track_m``; its steering numbers are in the
telemetry's ``extra``: ``steer_alpha_deg``, ``curvature_per_m``, ``speed_pct``, ``pivoting``);
TURN_RIGHT -> left ``+turn_pct``, right ``-turn_pct`` (clockwise spin in place); TURN_LEFT ->
left ``-turn_pct``, right ``+turn_pct``; every other state -> stop. ARRIVED stops for the one
decision in which it is reported and the next input turns towards the next waypoint, except
that in pivot_arc an arrival whose next leg does not start with a pivot drives on at once
(the navigator's decision carries the next leg's arc: a recorded track's points 1-3 m apart
stopped the robot at each of them).
A return to launch (a failsafe's or the operator's) begins with a stop: state HOLD, 0/0, at
its first step and for :data:`RETURN_STOP_S`, so a side never flips from forward to reverse
into the return's pivot without a stop between.

Mode rules: a mission loads in IDLE, MANUAL or DONE (not while RUNNING or PAUSED: stop first);
start needs a mission and restarts it from its first waypoint (not while RUNNING or PAUSED);
pause only while RUNNING; resume only while PAUSED; manual drive not while RUNNING or PAUSED
and not with the motor link down. Rejected requests raise :class:`CommandRejected` and change
nothing. The geofence is the loop's (``x6wd.loop.runner``), not the controller's.
"""

from __future__ import annotations

import contextlib
import math
import numbers
from collections.abc import Sequence

from x6wd.core.config import (
    FailsafeConfig,
    GnssNoiseConfig,
    NavigationConfig,
    OdometryConfig,
    SafetyConfig,
)
from x6wd.core.errors import X6wdError
from x6wd.core.geodesy import great_circle_m
from x6wd.core.records import (
    Attitude,
    ControllerOutput,
    GpsFix,
    GpsSky,
    Mode,
    MotorCommand,
    NavState,
    StateChange,
    Telemetry,
    WheelOdometry,
)
from x6wd.nav import geo, steering
from x6wd.nav.compass_trust import CompassTrust
from x6wd.nav.course_watch import CourseWatch
from x6wd.nav.encoder_watch import EncoderWatch
from x6wd.nav.navigator import NavigationError, Navigator
from x6wd.nav.odometry import wheel_travel_m
from x6wd.nav.position import DEFAULT_HDOP, PositionSource, degraded_radius_m, make_source


class CommandRejected(X6wdError):
    """An operator request is invalid in the current state or has bad arguments.

    The controller is unchanged when this is raised.
    """


class InputError(X6wdError, ValueError):
    """A record or call carried an unusable time (not a finite number of seconds) or an
    unknown sensor name."""


ARRIVAL_GPS_SIGMAS = 3.0
"""An EKF arrival needs the latest fix within this many of its standard deviations..."""
ARRIVAL_GPS_MIN_M = 5.0
"""... and never less than this (m) of the waypoint."""
UNCERTAIN_RELEASE = 0.9
"""A wait for a position too uncertain ends once the error radius is under this fraction of
its limit (hysteresis: a radius about the limit made 219 stops and starts in a review)."""
UNCERTAIN_HOLD = "position too uncertain"
"""The start of the hold reason while the next waypoint lies inside the EKF's error radius
and that radius exceeds ``navigation.arrival_max_error_m`` (:meth:`Controller._uncertain_hold`)."""
DEAD_RECKONING_MAX_SIGMA_M = 5.0
"""Largest EKF position uncertainty (m, both axes together) to drive on without a fix."""
DEAD_RECKONING_MIN_SPEED = 0.5
"""Without a fix the robot drives on for at most the time its slowest commanded drive
(cruise, turn, the approach's ``min_speed_pct``) would take at this fraction of its nominal
speed to cover ``safety.gps_outage_max_m``: wheels that count far less than they are driven
(a miscounting or jittering encoder) must not stretch the outage without bound; the bound
on commanded travel (``DEAD_RECKONING_COMMANDED``) ends such a drive first unless the
robot pivots most of the time: this is the last backstop."""
DEAD_RECKONING_COMMANDED = 1.5
"""Without a fix the robot also drives on only until its commanded forward travel since the
last valid fix (``full_speed_mps`` × |mean of the left and right %| / 100, integrated over
time; a pivot adds next to nothing) reaches this many ``safety.gps_outage_max_m``. The real
travel exceeds the commanded one only when the speed model is wrong (``full_speed_mps`` set
too low, a steep downhill), while encoders that count a fraction f of the travel let the
counted limit alone stretch the outage to 1/f of it (an outside audit: 25 % counts drove
44-79 m blind). In a healthy outage the counted travel reaches the limit first (commanded
and counted agree within a few %, and a pivot counts but commands no travel)."""
ODOMETRY_FRESH_S = 0.5
"""Encoder counts older than this (s) do not count as reporting."""
ENCODER_WATCH_AGE_S = 2.5
"""A compass sample older than this (s) gives the encoder watch no turn (a 1 Hz compass
holds its bearing for a second between samples)."""
STUCK_TURN_DEG = 30.0
"""Heading change (deg) that counts as motion for the stuck failsafe while pivoting."""
PIVOT_HEADWAY_DEG = 10.0
"""A pivot must bring its heading error this much (deg) nearer zero every ``stuck_s``: a
compass that swings without following the body (a magnet stronger than the earth's field)
passes the 30° motion test while the robot spins in place for ever."""
ENCODER_FAULT_TURN_DEG = 90.0
"""The wheels' test names the encoders, not a block, when over the time the wheels stood
still the compass turned this far net (deg; its noise cancels in a net turn, a pivot's
rotation adds up) ..."""
ENCODER_FAULT_SIGMAS = 3.0
"""... or the fixes moved ahead along the heading by this many of the GPS's noise σ (from
HDOP and RE/ASE/LCE, at least ``stuck_min_m`` each): a blocked robot's fixes wander or jump
by a few metres in any direction (a second outside audit: two 2 m anchor moves in 5 s named
3 of 3 blocked robots under a 10 m wander 'encoders'), a robot driving on dead encoders at
cruise covers 20 m in 10 s along its heading."""
SLIP_MIN_TRAVEL = 4.0
"""With encoders, the body counts as still (slipping) only once the wheels drove this many
``stuck_min_m`` without it moving: at a slow cruise a drifting GPS can hide 6 m in 10 s."""
PROGRESS_GAIN_M = 2.0
"""The progress watch (``failsafe.progress_timeout_s``): driving counts as progress towards
the waypoint only when the estimate comes this much nearer it than at its latest progress
(m); a robot that swings or circles about its target, each pivot gaining its own 10°, never
does..."""
PROGRESS_GAIN_OF_DISTANCE = 0.5
"""... and never more than this fraction of that distance: a slow robot's approach (15 %
of 0.3 m/s: 2.7 m a minute) counts from 3.4 m on (a review saw it paused 1.4 m short)."""
PROGRESS_TICK_MAX_S = 0.5
"""Time counted per check at most (s): a hold or a pause between two checks is no driving."""

LAUNCH_STILL_M = 2.0
"""Wheel travel (m) under which a robot that jumped is still at its launch point: the
launch point moves with the jump (:meth:`Controller._relaunch_after_jump`)."""
LAUNCH_FIX_FRESH_S = 2.5
"""At a start, the latest fix the source took confirms the launch point only when it is at
most this old (s): over a longer gap the robot may have been carried (a GPS outage while
carried 35 m at 1.4 m/s in 25 s). Fixed, not ``fix_stale_s`` (which the configuration allows
up to 60 s): 2.5 GPS periods at the 1 Hz the receiver is set to, where a carry at walking
pace moves the robot ~3.5 m, inside the fixes' own scatter."""
PIVOT_WHEELS_TURN_DEG = 90.0
"""A pivot the stuck check catches (the compass under ``STUCK_TURN_DEG`` round in
``stuck_s``) is named a compass that does not follow the wheels when the wheels' counts
turned the body this far (deg, their differential travel over ``[odometry] track_m``) in
that time: with the effective track the counts and a healthy compass agree, with the
geometric one (1.2-2x narrower) the counts read up to twice the turn, so 90 deg counted is
45 deg or more of the body's, past the 30 deg a compass that followed would have shown."""

FROZEN_WHEEL_TURN_DEG = 90.0
"""A compass whose every reading (bearing, pitch and roll alike) stays the same while the
wheels' counts turn the robot this far (deg) the way it was told to turn (a pivot or a turn
of ``stuck_min_pct`` or more) and :data:`FROZEN_MIN_S` has passed is frozen:
a hung chip or bus returning its last registers. A live one's readings change with a turn,
and its noise (0.1° steps) changes them at rest. The robot pauses at once; the stuck
check's 10 s of turning (an outside audit: 10 s spinning in place, status "connected") was
the only catch before. Without encoders the stuck check still is."""
FROZEN_MIN_S = 1.0
"""Least time (s) the same reading must last before it can be called frozen."""
FROZEN_DRIVE_MIN_S = 3.0
FROZEN_DRIVE_MIN_M = 5.0
FROZEN_DRIVE_MPS = 0.3
"""A reading the same for this long (s) while the robot drove this far (m: the receiver's
speed, counted while the mission runs and only at this speed (m/s) or more) and the wheels'
counts turned :data:`FROZEN_WHEEL_TURN_DEG` either way, told or not, is frozen too. On a
straight leg the robot, steering by the frozen heading, follows its own drift in a slow arc
that no command asks for (an outside audit, round 22: 50-70 s and 14-48 m off the route
before the off-course watch). Driving rules out a stuck robot's slip and a robot at rest,
whose compass may repeat itself; a receiver at rest reports its noise as speed (about
0.1 m/s, over 0.3 m/s about once in a thousand fixes), which a review saw add up to "5 m"
over a pause."""
PIVOT_CAUSES = "a compass fault, or the wheels spin in place"
"""What a pivot the compass does not follow can be (the stuck reasons say both): the wheels'
counts turn in mud as they do on grass, and only the compass tells the two apart."""

SENSORS = ("gps", "compass")
"""The sensors :meth:`Controller.sensor_health` knows, in the order their holds are named."""

_ARRIVALS = (NavState.ARRIVED, NavState.MISSION_DONE)

RETURN_STOP_S = 0.5
"""A return to launch (a failsafe's or the operator's) begins with the motors stopped (state
HOLD, 0/0) for at least its first step and this long (s): two motor time constants (the
simulator's ``motor_tau_s``, 0.25 s), and the motor worker's newest-command-wins queue sees
several stops, so a mission's forward drive never flips straight into the return's pivot
(an outside audit: ``M 17 13`` then, 25 ms later, ``M 40 -40``)."""
RETURN_STOP_REASON = "stop before the return to launch"  # the reason that stop carries

REVERSE_STOP_S = 0.5
"""A side whose command changes sign (a pivot's start from the straight or an arc, a pivot
that swings the other way, a manual drive flipped) is held at 0 until it has been commanded 0
this long (s): two motor time constants (the simulator's ``motor_tau_s``, 0.25 s), so a
motor never slams from forward to reverse (``+60`` then ``-40`` 50 ms later wears the
gearbox and draws a stall current through the driver). In a mission the other side drives
on (a pivot's start turns the right way meanwhile); in manual drive both sides wait, so the
robot never moves in a way the operator did not ask for."""
REVERSE_STOP_NOTE = "stop before reversing"  # added to the command's reason while held


def _check_t(t_s: float, what: str) -> float:
    try:
        t = float(t_s)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{what}: t_s must be a number of seconds, got {t_s!r}") from exc
    if not math.isfinite(t):
        raise InputError(f"{what}: t_s must be finite, got {t_s!r}")
    return t


def _finite(v: float | None) -> bool:
    return v is not None and math.isfinite(v)


MEANINGLESS_HDOP = 20.0
"""A fix whose HDOP is this or more is no fix: at a NEO-5's ~5 m range error that is ~100 m,
the position-accuracy mask (NAV5 pAcc) above which a u-blox receiver reports none. Such fixes
come from RMC alone in street canyons (HDOP 99.99, 1.7-3.5 km off). Counted as a fix they
were weighted to nothing by the EKF yet kept the GPS "fresh", so a robot whose wheels
under-count drove on past the geofence on HDOP-20 fixes (review 10b); as no fix, the robot
holds after ``fix_stale_s`` as it does when the receiver reports none."""


def has_usable_position(fix: GpsFix) -> bool:
    """The fix may steer the robot, centre or test the geofence: valid, with coordinates
    present, finite and in range, and an HDOP (when given) under :data:`MEANINGLESS_HDOP`
    (the one rule the controller and the loop share)."""
    lat, lon = fix.lat_deg, fix.lon_deg
    hdop = fix.hdop
    return (
        fix.valid
        and (hdop is None or not hdop >= MEANINGLESS_HDOP)
        and lat is not None
        and lon is not None
        and _finite(lat)
        and _finite(lon)
        and abs(lat) <= 90.0
        and abs(lon) <= 180.0
    )


class _SameReading:
    """One compass reading (bearing, pitch, roll) repeated: since ``t0`` (s), last at
    ``t_last`` (s), ``n`` times; the wheels' turn (rad) counted since it began in one
    unbroken turn the robot was told to make (``turn_rad``), and as of its latest repeat
    (``confirmed_rad``: only a turn between two identical readings says the compass did
    not follow it; a 1 Hz compass's reading is not frozen for having no successor yet)."""

    def __init__(self, reading: tuple[float, float, float], t_s: float) -> None:
        self.reading = reading
        self.t0 = self.t_last = t_s
        self.n = 1
        self.turn_rad = self.confirmed_rad = 0.0
        # every turn the counts saw since it began, signed, told or not, and the receiver's
        # travel (m) since, driving (:data:`FROZEN_DRIVE_MIN_S`)
        self.net_rad = self.confirmed_net_rad = 0.0
        self.drove_m = 0.0

    def again(self, t_s: float) -> None:
        """The same reading at ``t_s`` (s)."""
        self.n += 1
        self.t_last = t_s
        self.confirmed_rad = self.turn_rad
        self.confirmed_net_rad = self.net_rad

    def wheels(self, turn_rad: float | None) -> None:
        """The wheels turned ``turn_rad`` (rad) the way the robot is told to; None: it is
        not told to turn (or they turned the other way): the count starts again."""
        if turn_rad is None:
            self.turn_rad = self.confirmed_rad = 0.0
        else:
            self.turn_rad += turn_rad


class Controller:
    """Deterministic robot brain; see the module docstring for the contract."""

    def __init__(
        self,
        nav: NavigationConfig,
        safety: SafetyConfig,
        declination_deg: float = 0.0,
        *,
        odometry: OdometryConfig | None = None,
        gnss_noise: GnssNoiseConfig | None = None,
        failsafe: FailsafeConfig | None = None,
    ) -> None:
        self._nav_cfg = nav
        self._safety = safety
        self._failsafe = failsafe or FailsafeConfig()
        try:
            self._navigator = Navigator(nav, declination_deg)
        except NavigationError as exc:
            raise CommandRejected(str(exc)) from exc
        self._odo_cfg = odometry or OdometryConfig()
        self._gnss_cfg = gnss_noise or GnssNoiseConfig()
        slowest_pct = min(nav.cruise_pct, nav.turn_pct)
        if nav.steering == "pivot_arc":
            slowest_pct = min(slowest_pct, nav.min_speed_pct)
        slowest_mps = DEAD_RECKONING_MIN_SPEED * nav.full_speed_mps * slowest_pct / 100.0
        # 20 m at half of 15 % of 3.888 m/s: 68.6 s
        self._dead_reckoning_max_s = (
            safety.gps_outage_max_m / slowest_mps if slowest_mps > 0 else math.inf
        )
        self._source: PositionSource = make_source(
            nav, self._odo_cfg, self._gnss_cfg, declination_deg
        )
        self._filt: tuple[float, float] | None = None  # the source's (lat_deg, lon_deg)
        self._src_heading_deg: float | None = None  # the source's true heading, if it has one
        self._src_heading_rad: tuple[float | None, float] = (None, 0.0)  # (deg, its rad)
        self._mission_nav: Navigator | None = None  # the operator's mission while returning
        self._returning = ""  # why the robot returns to launch ("" when it does not)
        self._return_stop_until = -math.inf  # the return's first stop lasts until (s)
        self._launch: tuple[float, float] | None = None  # (lat_deg, lon_deg) at mission start
        self._failsafe_why = ""  # the last failsafe that acted (telemetry)
        self._paused_by = ""  # who paused the mission, while PAUSED (telemetry)
        self._operator_t: float | None = None  # latest operator request (s), when watched
        # a sensor's holds since the robot last drove: how long in all (s), the latest tick (s)
        self._sensor_s = 0.0
        self._sensor_t: float | None = None
        # waiting for a position good enough to judge a waypoint (_uncertain_hold): for which
        # (navigator, waypoint index), how long in all (s), since the latest tick (s)
        self._uncertain_at: tuple[Navigator, int] | None = None
        self._uncertain_s = 0.0
        self._uncertain_t: float | None = None
        self._jump_m: float | None = None  # the source's position jump since the last check (m)
        self._launch_wheel_m = 0.0  # the wheels' travel when the launch point was taken (m)
        # a fix the source took agreed with the launch point's estimate (the latest fix
        # before the start, or one after it): until then a jump of the estimate moves the
        # launch point with it (_watch_launch)
        self._launch_confirmed = False
        # the launch point is a raw fix (the source had no estimate yet at the start): it is
        # taken again from the source's first estimate (_retake_raw_launch)
        self._launch_raw = False
        # the stuck failsafe's last progress: (wheel m, t_s) and (lat, lon, bearing, t_s,
        # wheel m, wheel turn rad, receiver m)
        self._stuck_wheels: tuple[float, float] | None = None
        self._stuck_body: tuple[float, float, float, float, float, float, float] | None = None
        self._stuck_forward = False
        # since the wheels' clock last restarted: the compass's net turn (deg), its last
        # bearing, and the first fresh fix (lat, lon): the encoders' evidence
        self._enc_turn_deg = 0.0
        self._enc_bearing: float | None = None
        self._enc_fix: tuple[float, float] | None = None
        # the pivot's headway: (best |heading error| deg, t_s it was reached, waypoint index)
        self._pivot_best: tuple[float, float, int] | None = None
        # the progress watch: (navigator, waypoint index) watched, the nearest the estimate
        # has been to it (m), driving time since it was last beaten (s), the latest check (s)
        self._progress: tuple[Navigator, int, float, float, float] | None = None
        self._course = CourseWatch(
            self._failsafe.off_course_m, self._failsafe.heading_check_deg, nav.full_speed_mps
        )
        self._course_fix: GpsFix | None = None  # the last fix the course watch took
        self._trust = CompassTrust(self._failsafe.compass_refused_s)  # the EKF's refusals
        # the compass's latest reading and how long it has stayed so: FROZEN_WHEEL_TURN_DEG
        self._same: _SameReading | None = None
        # the two sides' encoders against the compass on straight drives, and its verdict
        # for the failsafe check of the mission running ("" while none)
        self._enc_watch = EncoderWatch(self._odo_cfg.track_m)
        self._encoder_fault = ""
        self._wheel_m = 0.0  # |wheel travel| summed over both sides / 2 (m)
        self._wheel_turn_rad = 0.0  # the two sides' differential travel / track (rad, cw +)
        # the receiver's own speed (a fix's speed_mps) integrated over the time between
        # usable fixes (m), and the latest usable fix's time (s): a second witness of motion
        self._rx_m = 0.0
        self._rx_t: float | None = None
        self._wheel_at_fix = 0.0  # _wheel_m at the latest valid fix
        # commanded forward travel (m) summed since the first input, and its value at the
        # latest valid fix: see DEAD_RECKONING_COMMANDED
        self._commanded_m = 0.0
        self._commanded_at_fix = 0.0
        self._odo_prev: WheelOdometry | None = None
        self._mode = Mode.IDLE
        self._state = NavState.IDLE
        self._hold_reason = ""
        self._now: float | None = None
        self._fix: GpsFix | None = None  # latest fix, valid or not
        self._fix_ok = False  # latest fix usable (valid, coordinates present and in range)
        self._valid_fix_t: float | None = None
        self._att: Attitude | None = None
        self._att_ok = False
        # the latest usable sample's time (s): a stale compass's reader hands on an invalid
        # sample stamped now, and the age shown must keep growing from the last good one
        self._good_att_t: float | None = None
        self._sky: GpsSky | None = None
        self._link_ok = True
        # Sensors a reader reported unusable: name -> its state ("disconnected", "stale"...).
        self._sensor_down: dict[str, str] = {}
        # Sensors back since t_s (s) whose fresh data has not arrived yet.
        self._sensor_back: dict[str, float] = {}
        self._manual: tuple[float, float, float] | None = None  # left %, right %, until t_s
        self._has_mission = False
        self._cmd = MotorCommand(0.0, 0.0, 0.0, "idle")
        # the command as decided, before the reversal stop (left %, right %): the stuck and
        # pivot checks judge the drive the robot asked for, so a pivot that swings to and
        # fro, each swing held at 0 a moment, still counts as driving
        self._intent: tuple[float, float] = (0.0, 0.0)
        # per side (left, right): the sign of the last non-zero command, and since when (s)
        # the side has been commanded 0 (None while it drives)
        self._side_sign = [0, 0]
        self._side_zero_t: list[float | None] = [0.0, 0.0]
        self._telemetry = Telemetry(t_s=0.0, mode=self._mode, state=self._state)
        # Memos for the per-call geometry. A compass sample (20 Hz) changes only the heading
        # and a fix (1 Hz) only the position, yet every call needs both, for the decision and
        # again for the telemetry. Keys are the inputs' identities (the navigator, its
        # projection, the attitude record, the filtered-position tuple), so a hit returns the
        # very float the same computation gave before and the outputs stay bit-identical.
        self._xy_key: tuple[object, object, object] | None = None
        self._xy: tuple[float, float] = (0.0, 0.0)
        self._heading_key: tuple[object, object, float] | None = None
        self._heading = 0.0
        # (navigator decision, x, y, heading) of the last Navigator.step, for the snapshot.
        self._decided: tuple[object, float, float, float] | None = None
        # Great-circle distances of the latest fix, memoised with their inputs (identities
        # of the fix and the stuck check's body tuple, the target's coordinates):
        # (fix, target lat, target lon, m) for the arrival check, (body, fix, m) for stuck.
        self._to_target_m: tuple[GpsFix, float, float, float] | None = None
        self._body_to_fix_m: tuple[object, GpsFix, float] | None = None

    # ------------------------------------------------------------------ properties
    @property
    def mode(self) -> Mode:
        """What the operator asked for (IDLE, RUNNING, PAUSED, MANUAL, DONE)."""
        return self._mode

    @property
    def state(self) -> NavState:
        """The navigation state (HOLD while a safety condition stops the motors)."""
        return self._state

    @property
    def attitude_ok(self) -> bool:
        """The latest compass sample is usable (valid, a bearing in [0, 360))."""
        return self._att_ok

    @property
    def telemetry(self) -> Telemetry:
        """The latest telemetry snapshot."""
        return self._telemetry

    @property
    def command(self) -> MotorCommand:
        """The latest motor command."""
        return self._cmd

    @property
    def navigator(self) -> Navigator:
        """The waypoint state machine (read it; drive it through the controller)."""
        return self._navigator

    @property
    def waypoints(self) -> tuple[tuple[float, float], ...]:
        """The loaded mission as (lat_deg, lon_deg); empty when none."""
        return self._navigator.waypoints if self._has_mission else ()

    # ------------------------------------------------------------------ sensor inputs
    def on_fix(self, fix: GpsFix) -> list[ControllerOutput]:
        """A receiver epoch at ``fix.t_s`` (s); valid fixes feed the per-axis filters."""
        t = _check_t(fix.t_s, "fix")
        ok = has_usable_position(fix)
        self._fix = fix
        self._fix_ok = ok
        if ok:
            # a launch point no fix the source took has confirmed yet: a reset may show that
            # the estimate it came from was wrong (_watch_launch)
            watch = self._launch is not None and not self._launch_confirmed
            before = self._source.position(t)
            taken = self._source.fixes_taken()[0]
            self._source.on_fix(fix)
            jump = self._source.take_jump()
            jump_m = None if jump is None else jump.moved_m
            if jump is not None and before is not None and (watch or not jump.surprise):
                # the estimate the first leg started from was wrong by the move (a launch
                # point no fix confirmed, or an estimate that said it was that uncertain):
                # the leg moves with it; a surprise (a GPS back somewhere else) leaves it
                after = self._source.position(t)
                if after is not None:
                    self._navigator.move_first_leg_start(before, after)
            if watch and before is not None:
                self._watch_launch(t, before, taken, jump_m)
            speed = fix.speed_mps
            if (
                self._rx_t is not None
                and speed is not None
                and math.isfinite(speed)
                and speed >= 0.0
                and 0.0 < t - self._rx_t <= self._safety.fix_stale_s
            ):
                self._rx_m += speed * (t - self._rx_t)
                same = self._same
                if same is not None and self._mode == Mode.RUNNING and speed >= FROZEN_DRIVE_MPS:
                    same.drove_m += speed * (t - self._rx_t)
            self._rx_t = t if self._rx_t is None else max(self._rx_t, t)
            if jump is not None and jump.surprise and self._mode in (Mode.RUNNING, Mode.PAUSED):
                # for the failsafe check of the mission running, or resumed: a jump while
                # paused (a GPS back after the sensor timeout paused it) must not be driven on.
                # A move inside the estimate's own 99 % ellipse is no surprise: the estimate
                # said it might be that far off (a start on 4-satellite fixes, HDOP 12, 35 m
                # off, corrected when the sky opens) and the robot drove on it knowing so
                moved_m = jump.moved_m
                self._jump_m = moved_m if self._jump_m is None else max(self._jump_m, moved_m)
            self._wheel_at_fix = self._wheel_m
            self._commanded_at_fix = self._commanded_m
            self._valid_fix_t = t if self._valid_fix_t is None else max(self._valid_fix_t, t)
            back_t = self._sensor_back.get("gps")
            if back_t is not None and t >= back_t:
                del self._sensor_back["gps"]  # a fresh fix since the GPS came back
        return self._step(t, "fix")

    def on_sky(self, sky: GpsSky) -> list[ControllerOutput]:
        """Satellites in view at ``sky.t_s`` (s); stored for telemetry only."""
        t = _check_t(sky.t_s, "sky")
        self._sky = sky
        return self._step(t, "sky")

    def on_attitude(self, att: Attitude) -> list[ControllerOutput]:
        """A compass sample (magnetic bearing, deg) at ``att.t_s`` (s)."""
        t = _check_t(att.t_s, "attitude")
        self._att = att
        self._att_ok = bool(att.valid) and _finite(att.bearing_deg) and 0 <= att.bearing_deg < 360
        if self._att_ok:
            good_t = self._good_att_t
            self._good_att_t = t if good_t is None else max(good_t, t)
            reading = (att.bearing_deg, att.pitch_deg, att.roll_deg)
            same = self._same
            if same is None or same.reading != reading:
                self._same = _SameReading(reading, t)
            else:
                same.again(t)
            took = self._source.on_compass(t, att.bearing_deg)
            if took is not None:
                self._trust.on_reading(t, not took)
        back_t = self._sensor_back.get("compass")
        if back_t is not None and self._att_ok and t >= back_t:
            del self._sensor_back["compass"]  # a fresh sample since the compass came back
        return self._step(t, "attitude")

    def on_odometry(self, rec: WheelOdometry) -> list[ControllerOutput]:
        """Cumulative wheel-encoder counts at ``rec.t_s`` (s): the EKF's motion, and the
        wheels' travel for the stuck failsafe."""
        t = _check_t(rec.t_s, "odometry")
        prev, self._odo_prev = self._odo_prev, rec
        if prev is not None:
            dl, dr = wheel_travel_m(
                self._odo_cfg,
                rec.left_counts - prev.left_counts,
                rec.right_counts - prev.right_counts,
            )
            self._wheel_m += 0.5 * (abs(dl) + abs(dr))
            turn_rad = (dl - dr) / self._odo_cfg.track_m
            self._wheel_turn_rad += turn_rad
            same, (left, right) = self._same, self._intent
            if same is not None:
                # only a turn it is being told to make, without a break: one encoder dead on
                # a straight drive counts a turn the compass rightly does not show (the
                # encoder watch's case), and a stuck robot's separate attempts must not add
                # up (a review: 91° over 8 s of them, the compass blamed for a slip); any
                # turn while driving: FROZEN_DRIVE_MIN_S
                told = 0.5 * abs(left - right) >= self._failsafe.stuck_min_pct
                same.wheels(abs(turn_rad) if told and turn_rad * (left - right) > 0.0 else None)
                same.net_rad += turn_rad
        att = self._att
        fresh = att is not None and self._att_ok and abs(t - att.t_s) <= ODOMETRY_FRESH_S
        if prev is not None:
            cmd = self._cmd
            # the latest sample with its time, held between samples (a slow compass's turn
            # is counted between its samples); none when it is older than a healthy period
            recent = (
                att is not None
                and self._att_ok
                and -ODOMETRY_FRESH_S <= t - att.t_s <= ENCODER_WATCH_AGE_S
            )
            why = self._enc_watch.on_increment(
                t,
                dl,
                dr,
                cmd.left_pct,
                cmd.right_pct,
                att.bearing_deg if recent and att is not None else None,
                att.t_s if recent and att is not None else None,
            )
            if why and self._mode == Mode.RUNNING and not self._encoder_fault:
                self._encoder_fault = why
        pitch = att.pitch_deg if fresh and att is not None and _finite(att.pitch_deg) else 0.0
        self._source.on_odometry(rec, pitch)
        return self._step(t, "odometry")

    def set_declination(self, declination_deg: float, t_s: float) -> list[ControllerOutput]:
        """Use ``declination_deg`` (deg, east positive) from now on, e.g. the World Magnetic
        Model's value once a dated fix says where and when the robot is."""
        t = _check_t(t_s, "set_declination")
        d = float(declination_deg)
        if not (math.isfinite(d) and abs(d) <= 180.0):
            raise InputError(f"declination must be in [-180, 180] deg, got {declination_deg!r}")
        for nav in (self._navigator, self._mission_nav):
            if nav is not None:
                nav.declination_deg = d
        self._source.set_declination_deg(d)
        return self._step(t, "declination")

    def operator_seen(self, t_s: float) -> None:
        """An operator's request arrived over the network at ``t_s`` (s): the operator-link
        failsafe (``failsafe.operator_timeout_s``) watches the time since the latest one while
        a mission started over the network runs."""
        t = _check_t(t_s, "operator_seen")
        self._operator_t = t if self._operator_t is None else max(self._operator_t, t)

    def tick(self, t_s: float) -> list[ControllerOutput]:
        """Time passes without input: staleness and the manual dead-man are checked."""
        return self._step(_check_t(t_s, "tick"), "tick")

    def motor_link(self, ok: bool, t_s: float) -> list[ControllerOutput]:
        """The motor board link went up (``ok``) or down (HOLD, stop) at ``t_s`` (s)."""
        t = _check_t(t_s, "motor_link")
        self._link_ok = bool(ok)
        return self._step(t, "motor link " + ("up" if ok else "lost"))

    def sensor_health(
        self, kind: str, ok: bool, t_s: float, state: str = ""
    ) -> list[ControllerOutput]:
        """A sensor's reader changed its health at ``t_s`` (s).

        ``kind`` is "gps" or "compass"; ``state`` names the condition ("disconnected",
        "reconnecting", "stale", ...). Not ``ok``: a running mission holds at once with
        ``hold_reason`` "<kind> <state>". ``ok`` again: the hold lasts until fresh data
        stamped at or after ``t_s`` arrived (a valid fix; a valid compass sample), so data
        from before the outage never resumes the robot. Manual drive is not affected.
        """
        t = _check_t(t_s, "sensor_health")
        if kind not in SENSORS:
            raise InputError(f"sensor_health: kind must be one of {SENSORS}, got {kind!r}")
        if not ok:
            self._sensor_down[kind] = state or "unavailable"
            self._sensor_back.pop(kind, None)
        elif kind in self._sensor_down:
            del self._sensor_down[kind]
            self._sensor_back[kind] = t
        return self._step(t, f"{kind} {state or ('ok' if ok else 'unavailable')}")

    # ------------------------------------------------------------------ operator requests
    def load_mission(
        self, waypoints: Sequence[tuple[float, float]], t_s: float
    ) -> list[ControllerOutput]:
        """Load (lat_deg, lon_deg) waypoints; not while RUNNING or PAUSED."""
        t = _check_t(t_s, "load_mission")
        if self._mode in (Mode.RUNNING, Mode.PAUSED):
            raise CommandRejected(f"cannot load a mission while {self._mode}: stop first")
        try:
            wps = list(waypoints)
        except TypeError as exc:
            raise CommandRejected(f"waypoints must be a sequence of (lat, lon): {exc}") from exc
        # Validate on a scratch navigator so a bad mission changes nothing.
        trial = Navigator(self._nav_cfg, self._navigator.declination_deg)
        try:
            trial.set_waypoints(wps)
        except NavigationError as exc:
            raise CommandRejected(f"bad mission: {exc}") from exc
        self._navigator = trial
        self._mission_nav = None
        self._returning = ""
        self._has_mission = True
        changes: list[ControllerOutput] = []
        if self._mode == Mode.DONE:
            self._set_mode(Mode.IDLE, "mission loaded", t, changes)
        return self._step(t, "mission loaded", changes)

    def start(self, t_s: float) -> list[ControllerOutput]:
        """Start the loaded mission from its first waypoint."""
        t = _check_t(t_s, "start")
        if not self._has_mission:
            raise CommandRejected("no mission loaded")
        if self._mode == Mode.RUNNING:
            raise CommandRejected("mission already running")
        if self._mode == Mode.PAUSED:
            raise CommandRejected("mission paused: resume it, or stop before starting again")
        changes: list[ControllerOutput] = []
        self._manual = None
        if self._mission_nav is not None:  # after a return to launch: the operator's mission
            self._navigator, self._mission_nav = self._mission_nav, None
        self._returning = self._failsafe_why = ""
        self._return_stop_until = -math.inf  # a return's stop ends with its mission
        self._navigator.restart()
        self._source.reset()
        self._stuck_wheels = self._stuck_body = self._pivot_best = None
        self._progress = None
        self._course.reset()
        self._jump_m = self._sensor_t = None
        self._sensor_s = 0.0
        self._uncertain_at = self._uncertain_t = None
        self._enc_watch.reset()
        self._encoder_fault = ""
        now = t if self._now is None else max(self._now, t)
        pos = self._source.position(now)
        fix = self._fix
        self._launch_raw = pos is None and self._fix_ok and fix is not None
        if self._launch_raw and fix is not None:
            pos = (fix.lat_deg, fix.lon_deg)  # type: ignore[assignment]
        self._launch = pos
        self._launch_wheel_m = self._wheel_m
        self._launch_confirmed = not self._launch_raw and self._fix_confirms(now)
        self._set_mode(Mode.RUNNING, "start", t, changes)
        return self._step(t, "start", changes)

    def return_home(self, t_s: float, why: str = "return") -> list[ControllerOutput]:
        """Drive back to the launch point (where the last mission started) and end there.

        From RUNNING, PAUSED, IDLE or DONE after a mission started; rejected without a launch
        point, in MANUAL, or while already returning. The operator's mission is kept: a later
        ``start`` runs it again from its first waypoint."""
        t = _check_t(t_s, "return")
        if self._launch is None:
            raise CommandRejected("no launch point: no mission has started with a position")
        if self._mode == Mode.MANUAL:
            raise CommandRejected("manual drive in progress: stop first")
        if self._returning and self._mode == Mode.RUNNING:
            raise CommandRejected("already returning to launch")
        changes: list[ControllerOutput] = []
        self._start_return(why, t, changes)
        return self._step(t, why, changes)

    def _start_return(self, why: str, t_s: float, out: list[ControllerOutput]) -> None:
        assert self._launch is not None
        home = Navigator(self._nav_cfg, self._navigator.declination_deg)
        home.set_waypoints([self._launch])
        if self._mission_nav is None:
            self._mission_nav = self._navigator
        self._navigator = home
        self._returning = why
        now = t_s if self._now is None else max(self._now, t_s)
        self._return_stop_until = now + RETURN_STOP_S  # stop first (RETURN_STOP_S)
        self._stuck_wheels = self._stuck_body = self._pivot_best = None
        self._progress = None
        self._course.reset()
        self._sensor_s, self._sensor_t = 0.0, None
        if self._mode == Mode.RUNNING:
            # still RUNNING, towards another target: a mode change with old == new says so
            out.append(
                StateChange(now, str(self._mode), str(self._mode), f"mode: {why}: return to launch")
            )
        self._set_mode(Mode.RUNNING, f"{why}: return to launch", t_s, out)

    def pause(self, t_s: float) -> list[ControllerOutput]:
        """Pause a running mission (motors stop; the waypoint index is kept)."""
        t = _check_t(t_s, "pause")
        if self._mode != Mode.RUNNING:
            raise CommandRejected(f"nothing to pause: mode is {self._mode}")
        changes: list[ControllerOutput] = []
        self._paused_by = "operator"
        self._set_mode(Mode.PAUSED, "pause", t, changes)
        return self._step(t, "pause", changes)

    def resume(self, t_s: float) -> list[ControllerOutput]:
        """Resume a paused mission."""
        t = _check_t(t_s, "resume")
        if self._mode != Mode.PAUSED:
            raise CommandRejected(f"nothing to resume: mode is {self._mode}")
        changes: list[ControllerOutput] = []
        self._course.reset()  # the operator looked and sent it on: a fresh leg
        self._progress = None  # ... and the progress watch's full time again
        self._set_mode(Mode.RUNNING, "resume", t, changes)
        return self._step(t, "resume", changes)

    def stop(self, t_s: float, why: str = "stop") -> list[ControllerOutput]:
        """Stop everything from any state: motors stop, mode IDLE. Never rejected. ``why``
        is the state change's reason (an operator's "stop", a "geofence breach")."""
        try:
            t = _check_t(t_s, "stop")
        except InputError:
            # A stop must never fail: fall back to the controller's own time.
            t = self._now if self._now is not None else 0.0
        changes: list[ControllerOutput] = []
        self._manual = None
        if self._mission_nav is not None:
            # a return stopped: the operator's mission is the robot's again (status and the
            # console showed the launch point as "waypoint 1/1" of an idle robot)
            self._navigator, self._mission_nav = self._mission_nav, None
        self._returning = ""
        self._return_stop_until = -math.inf
        self._jump_m = None  # a mission's: the next one starts from where the robot is
        self._set_mode(Mode.IDLE, why, t, changes)
        return self._step(t, why, changes)

    def geofence_breach(self, t_s: float, why: str = "geofence breach") -> list[ControllerOutput]:
        """The loop found the robot outside the geofence at ``t_s`` (s): a running or paused
        mission gets ``failsafe.geofence_action`` (hold: paused; return: back to launch). A
        return to launch already under way goes on (it leads back inside). ``why`` is the
        failsafe's reason ("geofence breach (estimated position)" without a fix)."""
        t = _check_t(t_s, "geofence_breach")
        changes: list[ControllerOutput] = []
        if self._mode in (Mode.RUNNING, Mode.PAUSED) and not (
            self._returning and self._mode == Mode.RUNNING
        ):
            self._apply_failsafe(why, self._failsafe.geofence_action, t, changes)
        return self._step(t, why, changes)

    @property
    def failsafe_config(self) -> FailsafeConfig:
        """The failsafe actions in force."""
        return self._failsafe

    @property
    def returning(self) -> str:
        """Why the robot is returning to launch ("" when it is not)."""
        return self._returning if self._mode in (Mode.RUNNING, Mode.PAUSED) else ""

    @property
    def launch_point(self) -> tuple[float, float] | None:
        """(lat_deg, lon_deg) where the last mission started (the return target), or None."""
        return self._launch

    def manual_drive(
        self, left_pct: float, right_pct: float, duration_s: float, t_s: float
    ) -> list[ControllerOutput]:
        """Drive left/right (%, -100..100) for ``duration_s`` (capped at manual_max_s)."""
        t = _check_t(t_s, "manual_drive")
        for name, v in (("left_pct", left_pct), ("right_pct", right_pct)):
            if isinstance(v, bool) or not isinstance(v, numbers.Real) or not -100 <= v <= 100:
                raise CommandRejected(f"{name} must be a number in [-100, 100], got {v!r}")
        if (
            isinstance(duration_s, bool)
            or not isinstance(duration_s, numbers.Real)
            or not (math.isfinite(duration_s) and duration_s > 0)
        ):
            raise CommandRejected(f"duration_s must be a positive number, got {duration_s!r}")
        if self._mode in (Mode.RUNNING, Mode.PAUSED):
            raise CommandRejected(f"no manual drive while {self._mode}: stop the mission first")
        if not self._link_ok:
            raise CommandRejected("motor link lost: cannot drive")
        now = t if self._now is None else max(self._now, t)
        until = now + min(float(duration_s), self._safety.manual_max_s)
        self._manual = (float(left_pct), float(right_pct), until)
        changes: list[ControllerOutput] = []
        self._set_mode(Mode.MANUAL, "manual drive", t, changes)
        return self._step(t, "manual drive", changes)

    # ------------------------------------------------------------------ failsafes
    def _apply_failsafe(
        self,
        why: str,
        action: str,
        t_s: float,
        out: list[ControllerOutput],
        keeps_driving: bool = False,
    ) -> None:
        """Act on a failsafe: "return" drives to the launch point (when there is one and the
        robot is not returning already), anything else pauses the mission. A condition that
        does not stop the robot driving (``keeps_driving``: the operator link) leaves a return
        under way alone; one that does (stuck, blind) pauses it."""
        self._failsafe_why = why
        if action == "return" and self._returning and self._mode == Mode.RUNNING and keeps_driving:
            return  # already doing what this failsafe asks, and nothing stops it
        if action == "return" and self._launch is not None and not self._returning:
            self._start_return(f"failsafe: {why}", t_s, out)
        else:
            self._paused_by = f"failsafe: {why}"
            self._set_mode(Mode.PAUSED, f"failsafe: {why}", t_s, out)

    def _failsafe_check(self, now: float, hold: str) -> tuple[str, str] | None:
        """(condition, action) of a failsafe due now while RUNNING, else None."""
        fs = self._failsafe
        jump_m, self._jump_m = self._jump_m, None  # consumed here whatever else fires
        if fs.gps_jump_m > 0 and jump_m is not None and jump_m >= fs.gps_jump_m:
            # farther than the robot can have driven unseen: the operator looks before it
            # drives on either position (a return would trust the new one too)
            self._relaunch_after_jump(now)
            doubt_deg = self._course.heading_doubt_deg
            cause = (
                "GPS back somewhere else, or the robot carried?"
                if doubt_deg is None
                else f"the GPS course lies {doubt_deg:.0f} deg from the compass's heading:"
                " a compass fault?"
            )
            return (
                f"position jumped {jump_m:.0f} m: the fixes disagreed with the estimate until"
                f" it moved to them ({cause})",
                "hold",
            )
        uncertain = hold.startswith(UNCERTAIN_HOLD)
        if uncertain:
            # waiting for the sky (poor geometry): its own patience, the time held for this
            # waypoint in all (the radius about its limit stops and starts the robot), and
            # only a pause follows: a return would steer by the same position
            at = (self._navigator, self._navigator.index)
            last = self._uncertain_at
            if last is None or last[0] is not at[0] or last[1] != at[1]:
                self._uncertain_at, self._uncertain_s = at, 0.0
            elif self._uncertain_t is not None:
                self._uncertain_s += now - self._uncertain_t
            self._uncertain_t = now
            limit_s = fs.position_timeout_s
            if limit_s > 0 and self._uncertain_s >= limit_s:
                self._uncertain_at = self._uncertain_t = None
                return f"{hold} for {limit_s:g} s", "hold"
        else:
            self._uncertain_t = None
        if not hold or hold == "motor link lost":
            self._sensor_s, self._sensor_t = 0.0, None  # it drives (or the link's own rule)
        elif not uncertain:
            # a sensor's hold: its time in all since the robot last drove, so neither a wait
            # for the sky before it (one lost fix after 35 s of waiting fired at once) nor
            # one between its spells (a fix every 29 s, each a wait: 700 s standing, no
            # failsafe) counts or restarts it
            if self._sensor_t is not None:
                self._sensor_s += now - self._sensor_t
            self._sensor_t = now
            if fs.sensor_timeout_s > 0 and self._sensor_s >= fs.sensor_timeout_s:
                self._sensor_s, self._sensor_t = 0.0, None
                return f"{hold} for {fs.sensor_timeout_s:g} s", fs.sensor_action
        else:
            self._sensor_t = None
        op_t = self._operator_t
        if fs.operator_timeout_s > 0 and op_t is not None and now - op_t > fs.operator_timeout_s:
            self._operator_t = None  # re-armed by the operator's next request
            return "operator link lost", fs.operator_action
        if hold in ("no valid fix", "fix stale") and fs.stuck_s > 0:
            blocked = self._blocked_at_commanded_bound(now)
            if blocked is not None:
                return blocked
        if hold:
            return None
        encoder_fault, self._encoder_fault = self._encoder_fault, ""
        if encoder_fault:
            # the EKF dead-reckons on these counts, and so would a return: pause
            return encoder_fault, "hold"
        frozen = self._frozen_check(now)
        if frozen:
            return frozen, "hold"  # as an untrusted compass: a return would steer by it too
        untrusted = self._trust.verdict(now)
        if untrusted:
            # a heading it cannot trust: pause, whatever the actions say (a return would
            # steer by it too)
            return self._untrusted_cause(now, untrusted), "hold"
        if fs.stuck_s > 0:
            fired = self._stuck_check(now) or self._pivot_check(now)
            if fired is not None:
                return fired
        return self._progress_check(now) or self._course_check(now)

    def _fix_confirms(self, now: float) -> bool:
        """At a start (``now``, s): the source took the latest fix it judged, and that fix is
        fresh (within :data:`LAUNCH_FIX_FRESH_S`, whatever ``fix_stale_s`` says): the
        estimate the launch point comes from agreed with the fixes when the mission started.
        Not when that fix was refused (a robot carried while idle, started before the fixes
        agreed), the EKF started on it (a first fix 80 m off) or the fixes stopped (carried
        through a GPS outage)."""
        taken_t = self._source.fixes_taken()[1]
        return taken_t is not None and 0.0 <= now - taken_t <= LAUNCH_FIX_FRESH_S

    def _watch_launch(
        self,
        t_s: float,
        before: tuple[float, float],
        taken: int,
        jump_m: float | None,
    ) -> None:
        """A usable fix at ``t_s`` (s) went to the source while the launch point was not yet
        confirmed; ``before``: the source's position just before it, ``taken``: its count of
        fixes taken then. Taken (the count went up: inside the EKF's gate, not a reset, not
        dropped as late, not the fix it started on): the estimate agrees with the fixes after
        the start, so the launch point stands, and a later jump keeps it (the robot started
        where it started). A reset instead: no fix since the start (nor the latest before
        it) was taken, so the launch point came from the estimate the reset corrected (a
        robot carried while idle and started before the fixes agreed, a first fix 80 m off
        that the EKF started on), and it moves by the reset's offset, however far the robot
        drove since (at 1 Hz the EKF takes the new place 6-8 s later: a started robot has
        driven off)."""
        if jump_m is None:
            if self._source.fixes_taken()[0] > taken:
                self._launch_confirmed = True  # taken (raw and Constellation: every fix)
            return
        after, launch = self._source.position(t_s), self._launch
        if after is None or launch is None:
            return
        # the offset in degrees: across the 180th meridian the two positions are about
        # 360 deg apart in longitude, which _move_launch's wrap takes out
        self._move_launch(launch[0] + after[0] - before[0], launch[1] + after[1] - before[1])

    def _move_launch(self, lat_deg: float, lon_deg: float) -> None:
        """The launch point is now (``lat_deg``, ``lon_deg``), the longitude wrapped to
        (-180, 180]; a return under way heads there. A point that is no position (a
        latitude past a pole) leaves it where it was: called from the sensor inputs, this
        must not raise."""
        if not (math.isfinite(lat_deg) and -90.0 <= lat_deg <= 90.0 and math.isfinite(lon_deg)):
            return
        self._launch = (lat_deg, geo.wrap_deg(lon_deg))
        if self._returning and self._mission_nav is not None:
            with contextlib.suppress(NavigationError):  # no plane within 0.1 deg of a pole
                self._navigator.set_waypoints([self._launch])  # a return under way heads there

    def _retake_raw_launch(self, now: float) -> None:
        """The launch point was the latest raw fix because the source had no estimate at the
        start (the EKF waits for the compass's first sample), and now it has one: while the
        wheels have not driven ``LAUNCH_STILL_M`` since the start the launch point is that
        first estimate (the EKF starts on the latest fix: a first fix 80 m off followed by
        the truth before the heading left the launch point 80 m off, and no reset ever came);
        it stays unconfirmed until a fix the source takes. Further, or without a position,
        the raw fix stays."""
        self._launch_raw = False
        pos = self._source.position(now)
        if pos is not None and self._wheel_m - self._launch_wheel_m < LAUNCH_STILL_M:
            self._move_launch(*pos)

    def _relaunch_after_jump(self, now: float) -> None:
        """A jump before the robot drove from its launch point: that point was the position
        the jump corrected (a robot carried while the daemon idled, started before the
        fixes agreed), so the launch point moves with it; a return would drive to the old
        one. Without encoders nothing says it has not moved: the point stays. (A launch point
        no fix confirmed moved with the reset already, however far the robot drove:
        :meth:`_watch_launch`; this also moves a confirmed one while the wheels stood.)"""
        if self._launch is None or self._odo_prev is None:
            return
        if self._wheel_m - self._launch_wheel_m < LAUNCH_STILL_M:
            pos = self._source.position(now)
            if pos is not None:
                self._launch = pos

    def _course_check(self, now: float) -> tuple[str, str] | None:
        """The off-course watch (:mod:`x6wd.nav.course_watch`), once per fresh usable fix:
        the GPS against where the robot steers, independent of the compass and the wheels."""
        fix, nav = self._fix, self._navigator
        if (
            fix is None
            or fix is self._course_fix
            or not self._fix_ok
            or self._valid_fix_t is None
            or now - self._valid_fix_t > self._safety.fix_stale_s
            or nav.done
        ):
            return None
        self._course_fix = fix
        assert fix.lat_deg is not None and fix.lon_deg is not None
        heading_deg = None
        cmd = self._cmd
        # an arrival that drives on into the next leg (pivot_arc) drives straight too
        straight = self._state in (NavState.STRAIGHT, NavState.ARRIVED)
        if straight and 0.5 * (cmd.left_pct + cmd.right_pct) >= self._failsafe.stuck_min_pct:
            h = self._current_heading_rad()
            heading_deg = None if h is None else math.degrees(h)
        # the leg's end: a recorded track's points on a straight are one leg (a new target
        # every fix restarted both checks, which then never fired)
        target = nav.waypoints[nav.course_index]
        travel_m = self._wheel_m if self._odo_prev is not None else None
        why = self._course.on_fix(fix.t_s, fix.lat_deg, fix.lon_deg, target, heading_deg, travel_m)
        return None if why is None else (why, self._failsafe.off_course_action)

    def _stuck_check(self, now: float) -> tuple[str, str] | None:
        """Driving (the previous command: forward, or a pivot) at ``stuck_min_pct`` or more
        for ``stuck_s`` without progress of the wheels (encoder travel of a tenth of
        ``stuck_min_m``; never missing without encoders) or of the body (the fixes
        ``stuck_min_m`` away, or the compass ``STUCK_TURN_DEG`` round). Each kind of progress
        restarts its own clock, so a stuck robot is caught ``stuck_s`` after it stopped, and
        the reason names what stopped: the wheels (blocked), else the GPS or the compass
        (the wheels turn, the robot does not: slipping), or the encoders when the wheels'
        test fires though the compass turned or the fixes moved ahead well beyond their noise
        in that time (``ENCODER_FAULT_TURN_DEG``, ``ENCODER_FAULT_SIGMAS``). The wheels'
        test also runs without a usable fix or heading (dead-reckoning through an outage);
        the body's clock then restarts with the next fix."""
        fs, fix, att = self._failsafe, self._fix, self._att
        left, right = self._intent  # as decided: a reversal stop is no standstill
        forward = 0.5 * (left + right)
        turning = 0.5 * abs(left - right)
        driving = max(abs(forward), turning) >= fs.stuck_min_pct
        if not driving:
            self._stuck_wheels = self._stuck_body = None
            return None
        wheels = self._stuck_wheels
        if (
            wheels is None
            or self._odo_prev is None
            or self._wheel_m - wheels[0] >= (0.1 * fs.stuck_min_m)
        ):
            wheels = self._stuck_wheels = (self._wheel_m, now)
            self._enc_turn_deg, self._enc_bearing, self._enc_fix = 0.0, None, None
        body = self._stuck_body
        if fix is None or not self._fix_ok or att is None or not self._att_ok:
            # The body tests need a fix and a heading; the wheels' test does not. It used to
            # stop here too, so a robot blocked in a GPS outage, dead-reckoning on wheels
            # that add no travel, drove its motors until the fix came back (1005 s).
            body = self._stuck_body = None
            self._enc_bearing = None  # no turn counted across a heading it cannot read
        else:
            assert fix.lat_deg is not None and fix.lon_deg is not None
            stale = self._valid_fix_t is None or now - self._valid_fix_t > self._safety.fix_stale_s
            if self._enc_bearing is not None:
                self._enc_turn_deg += geo.wrap_deg(att.bearing_deg - self._enc_bearing)
            self._enc_bearing = att.bearing_deg
            if self._enc_fix is None and not stale:
                self._enc_fix = (fix.lat_deg, fix.lon_deg)
            moved = ""
            if body is None or stale:
                pass  # an old fix says nothing of motion: the body's clock waits for a new one
            elif self._body_moved_m(body, fix) >= fs.stuck_min_m:
                moved = "the fixes"
            elif abs(geo.wrap_deg(att.bearing_deg - body[2])) >= STUCK_TURN_DEG:
                moved = "the compass"
            if body is None or stale or moved:
                body = (
                    fix.lat_deg,
                    fix.lon_deg,
                    att.bearing_deg,
                    now,
                    self._wheel_m,
                    self._wheel_turn_rad,
                    self._rx_m,
                )
                self._stuck_body = body
                self._stuck_forward = False
        # did it try to drive forward since the body last moved (else it only pivoted)?
        self._stuck_forward = self._stuck_forward or abs(forward) >= fs.stuck_min_pct
        still_wheels_s = now - wheels[1]
        still_body_s = 0.0 if body is None else now - body[3]
        if max(still_wheels_s, still_body_s) < fs.stuck_s:
            return None
        if (
            still_wheels_s < fs.stuck_s
            and body is not None
            and self._stuck_forward  # the fixes judge it (a pivot: the compass, which is sure)
            and self._odo_prev is not None
            and self._wheel_m - body[4] < SLIP_MIN_TRAVEL * fs.stuck_min_m
        ):
            return None  # the wheels drove too little to tell a slip from the GPS's wander
        self._stuck_wheels = self._stuck_body = None
        if still_wheels_s >= 0.5 * fs.stuck_s:
            seen = self._encoder_evidence(now)
            if seen:
                # the body moved while the wheels counted (almost) nothing: the encoders
                # failed, not the drive. Always a pause, whatever stuck_action says: a
                # return would dead-reckon home on the dead counts (as the disagree watch)
                shows = " and ".join(seen)
                return (
                    f"encoders: under {0.1 * fs.stuck_min_m:g} m counted in {fs.stuck_s:g} s"
                    f" of driving while {shows} {'shows' if shows == 'the compass' else 'show'}"
                    " motion",
                    "hold",
                )
            what = "the wheels"
        else:
            assert body is not None  # the body's clock ran stuck_s (the wheels' did not)
            named = self._sensor_not_following(body, still_body_s)
            if named is not None:
                return named
            what = "the GPS" if self._stuck_forward else "the compass"
        return (
            f"stuck ({what}: no motion in {fs.stuck_s:g} s of driving)",
            fs.stuck_action,
        )

    def _sensor_not_following(
        self, body: tuple[float, ...], still_s: float
    ) -> tuple[str, str] | None:
        """The body's test fired after ``still_s`` (s) since ``body`` while the wheels
        counted: the reason when a witness says the body did move and the sensor that judged
        it did not follow, else None (slipping: "stuck (the GPS ...)" / "(the compass ...)").

        Driving forward: the receiver's own speed (RMC, Doppler; independent of its
        position) integrated over the time adds up to ``SLIP_MIN_TRAVEL`` x ``stuck_min_m``:
        the position froze (an outside audit: fixes valid, time and a 2.4 m/s speed
        advancing, the position frozen, read "no motion" while the wheels counted 20 m). A
        slipping robot's receiver reports about 0 m/s. Always a pause: a return would steer
        home by the same position. Pivoting: the wheels' differential counts turned
        ``PIVOT_WHEELS_TURN_DEG`` or more while the compass stayed within
        ``STUCK_TURN_DEG`` (a compass frozen in a pivot: 2.5 turns read "no motion"), named
        as :meth:`_pivot_check` names a compass that does not follow the wheels."""
        fs, fix, att = self._failsafe, self._fix, self._att
        if self._stuck_forward:
            rx_m = self._rx_m - body[6]
            if fix is None or still_s <= 0 or rx_m < SLIP_MIN_TRAVEL * fs.stuck_min_m:
                return None
            wheels = (
                f"the wheels counted {self._wheel_m - body[4]:.0f} m and "
                if self._odo_prev is not None
                else ""
            )
            return (
                f"GPS position frozen: the fixes moved {self._body_moved_m(body, fix):.1f} m"
                f" in {still_s:.0f} s of driving while {wheels}the receiver reported"
                f" {rx_m / still_s:.1f} m/s",
                "hold",
            )
        turn_deg = abs(math.degrees(self._wheel_turn_rad - body[5]))
        if self._odo_prev is None or att is None or turn_deg < PIVOT_WHEELS_TURN_DEG:
            return None
        compass_deg = abs(geo.wrap_deg(att.bearing_deg - body[2]))
        return (
            f"stuck (the compass: turned {compass_deg:.0f}° in {still_s:.0f} s of pivoting"
            f" while the wheels' counts turned {turn_deg:.0f}°; the compass does not follow"
            f" the wheels: {PIVOT_CAUSES})",
            fs.stuck_action,
        )

    def _untrusted_cause(self, now: float, untrusted: str) -> str:
        """Why the compass lost the EKF's trust. Dead encoders on both sides predict no
        turn while the robot pivots, so the EKF refuses a compass that is right; when the
        wheels have counted (almost) nothing for a quarter of ``stuck_s`` of driving while the
        compass turned or the fixes moved ahead, the encoders are named (an outside audit:
        both sides dead read "compass untrusted" on 2 of 6 runs). A quarter of ``stuck_s``
        suffices here: the verdict is a pause either way, only its name is chosen, and a
        pivot the compass followed 128° in 4 s while the wheels counted nothing is plain."""
        fs = self._failsafe
        if fs.stuck_s > 0 and self._wheels_still_s(now) >= 0.25 * fs.stuck_s:
            seen = self._encoder_evidence(now)
            if seen:
                shows = " and ".join(seen)
                return (
                    f"encoders: under {0.1 * fs.stuck_min_m:g} m counted in"
                    f" {self._wheels_still_s(now):.0f} s of driving while {shows}"
                    f" {'shows' if shows == 'the compass' else 'show'} motion; the EKF then"
                    f" refused the compass ({untrusted})"
                )
        return f"compass untrusted ({untrusted})"

    def _encoder_evidence(self, now: float) -> list[str]:
        """What shows the body moving while the wheels stood still: "the compass" (a net
        turn of ``ENCODER_FAULT_TURN_DEG``), "the fixes" (a fresh fix ahead of the first one
        along the heading by ``ENCODER_FAULT_SIGMAS`` of the GPS's noise)."""
        out = []
        if abs(self._enc_turn_deg) >= ENCODER_FAULT_TURN_DEG:
            out.append("the compass")
        fix, first, heading = self._fix, self._enc_fix, self._current_heading_rad()
        fresh = (
            self._valid_fix_t is not None and now - self._valid_fix_t <= self._safety.fix_stale_s
        )
        if fix is not None and self._fix_ok and fresh and first is not None and heading is not None:
            assert fix.lat_deg is not None and fix.lon_deg is not None
            north_m = great_circle_m(first[0], first[1], fix.lat_deg, first[1])
            north_m = math.copysign(north_m, fix.lat_deg - first[0])
            east_m = great_circle_m(fix.lat_deg, first[1], fix.lat_deg, fix.lon_deg)
            east_m = math.copysign(east_m, geo.wrap_deg(fix.lon_deg - first[1]))
            ahead_m = north_m * math.cos(heading) + east_m * math.sin(heading)
            if 0.5 * (self._cmd.left_pct + self._cmd.right_pct) < 0:
                ahead_m = -ahead_m  # driving backwards
            g = self._gnss_cfg
            hdop = fix.hdop if fix.hdop is not None and fix.hdop > 0 else DEFAULT_HDOP
            sigma_m = hdop * math.sqrt(g.re_m**2 + g.ase_m**2 + g.lce_default_m**2)
            if ahead_m >= ENCODER_FAULT_SIGMAS * max(sigma_m, self._failsafe.stuck_min_m):
                out.append("the fixes")
        return out

    def _wheels_still_s(self, now: float) -> float:
        """How long (s) the wheels' stuck test has seen them count under a tenth of
        ``stuck_min_m`` while driving (0 without encoders or while they count)."""
        wheels = self._stuck_wheels
        if (
            wheels is None
            or self._odo_prev is None
            or self._wheel_m - wheels[0] >= 0.1 * self._failsafe.stuck_min_m
        ):
            return 0.0
        return now - wheels[1]

    def _blocked_at_commanded_bound(self, now: float) -> tuple[str, str] | None:
        """The drive without a fix just ended on its commanded travel while the wheels
        counted (almost) nothing for at least half of ``stuck_s``: a block (or dead
        encoders), which the hold would otherwise hide from the wheels' test (it stops the
        motors) and report only as "no valid fix" ``sensor_timeout_s`` later."""
        fs, limit_m = self._failsafe, self._safety.gps_outage_max_m
        bound_m = DEAD_RECKONING_COMMANDED * limit_m
        if limit_m <= 0 or self._commanded_m - self._commanded_at_fix <= bound_m:
            return None
        still_s = self._wheels_still_s(now)
        if still_s < 0.5 * fs.stuck_s:
            return None
        self._stuck_wheels = self._stuck_body = None
        return (
            f"stuck (the wheels: no motion in {still_s:.0f} s of driving, {bound_m:g} m"
            " commanded without a fix)",
            fs.stuck_action,
        )

    def _pivot_check(self, now: float) -> tuple[str, str] | None:
        """A pivot (the last decision TURN_LEFT or TURN_RIGHT, turning at ``stuck_min_pct``
        or more) whose heading error to its target has not come ``PIVOT_HEADWAY_DEG``
        nearer zero for ``stuck_s``: the compass moves but never towards the target, so the
        robot would spin on. A slow pivot still gains 10° in 10 s at 1°/s."""
        last, (left, right) = self._navigator.last, self._intent
        err_rad = None
        if self._state in (NavState.TURN_LEFT, NavState.TURN_RIGHT) and last is not None:
            err_rad = last.theta_rad if last.steer_alpha_rad is None else last.steer_alpha_rad
        turning = 0.5 * abs(left - right) >= self._failsafe.stuck_min_pct
        if err_rad is None or last is None or not turning:
            self._pivot_best = None
            return None
        err_deg = abs(math.degrees(err_rad))
        best = self._pivot_best
        if best is None or best[2] != last.waypoint_index or err_deg <= best[0] - PIVOT_HEADWAY_DEG:
            self._pivot_best = (err_deg, now, last.waypoint_index)
            return None
        stuck_s = self._failsafe.stuck_s
        if now - best[1] < stuck_s:
            return None
        self._pivot_best = None
        still_s = self._wheels_still_s(now)
        if still_s >= 0.5 * stuck_s:
            # the pivot's clock may start just before the wheels' one: a robot blocked
            # mid-pivot is a block of the wheels, not a compass that fails to follow them
            self._stuck_wheels = self._stuck_body = None
            return (
                f"stuck (the wheels: no motion in {still_s:.0f} s of driving)",
                self._failsafe.stuck_action,
            )
        return (
            f"stuck (the pivot: {best[0]:.0f}° from its heading and no nearer in {stuck_s:g} s"
            f" of turning; the compass does not follow the wheels: {PIVOT_CAUSES})",
            self._failsafe.stuck_action,
        )

    def _frozen_check(self, now: float) -> str:
        """Why the compass is frozen at ``now`` (s): its reading unchanged for
        :data:`FROZEN_MIN_S` or more while the wheels' counts turned
        :data:`FROZEN_WHEEL_TURN_DEG` ("" if not). Said once per such turn."""
        same = self._same
        if same is None or same.n < 2 or same.t_last - same.t0 < FROZEN_MIN_S:
            return ""
        turned_deg = math.degrees(same.confirmed_rad)
        drove = ""
        if turned_deg < FROZEN_WHEEL_TURN_DEG:
            turned_deg = abs(math.degrees(same.confirmed_net_rad))
            if (
                turned_deg < FROZEN_WHEEL_TURN_DEG
                or same.t_last - same.t0 < FROZEN_DRIVE_MIN_S
                or same.drove_m < FROZEN_DRIVE_MIN_M
            ):
                return ""
            drove = f" the robot drove {same.drove_m:.0f} m (the receiver's speed) and"
        same.turn_rad = same.confirmed_rad = 0.0  # the next verdict: another turn
        same.net_rad = same.confirmed_net_rad = same.drove_m = 0.0
        bearing, pitch, roll = same.reading
        return (
            f"compass frozen: the same reading (bearing {bearing:.1f}°, pitch {pitch:g}°,"
            f" roll {roll:g}°) {same.n} times in {same.t_last - same.t0:.1f} s while{drove} the"
            f" wheels' counts turned {turned_deg:.0f}°: a hung compass or I2C bus returning"
            " its last registers (or the wheels spin with the body held)"
        )

    def _progress_check(self, now: float) -> tuple[str, str] | None:
        """Driving (no hold) for ``failsafe.progress_timeout_s`` in all without the estimate
        coming :data:`PROGRESS_GAIN_M` nearer the waypoint than it has been: the robot swings
        or circles about it (an outside audit: a compass lagging 3 s pivoted left and right
        for 700 m about waypoint 2, each pivot gaining its own 10° so the pivot check never
        fired). Always a pause: a return would steer by the same heading."""
        limit_s = self._failsafe.progress_timeout_s
        nav, last = self._navigator, self._navigator.last
        if limit_s <= 0 or last is None or last.phi_i_rad is None or nav.done:
            self._progress = None
            return None
        d_m, index = last.distance_m, last.waypoint_index
        p = self._progress  # its distance is the one at the latest progress (m)
        gain_m = (
            PROGRESS_GAIN_M if p is None else min(PROGRESS_GAIN_M, PROGRESS_GAIN_OF_DISTANCE * p[2])
        )
        if p is None or p[0] is not nav or p[1] != index or d_m <= p[2] - gain_m:
            self._progress = (nav, index, d_m, 0.0, now)
            return None
        driven_s = p[3] + min(max(now - p[4], 0.0), PROGRESS_TICK_MAX_S)
        if driven_s < limit_s:
            self._progress = (nav, index, p[2], driven_s, now)
            return None
        self._progress = None
        return (
            f"no progress to waypoint {index + 1}: {limit_s:g} s of driving without coming"
            f" {gain_m:.3g} m nearer than {p[2]:.1f} m (now {d_m:.1f} m): swinging or"
            f" circling about it (a compass that lags or reads wrong?){self._veto_text(now, d_m)}",
            "hold",
        )

    def _veto_text(self, now: float, estimate_m: float) -> str:
        """Why the robot circles a waypoint its estimate has reached, when that is why: the
        latest fix does not confirm the arrival (:meth:`_gps_agrees`), said with both
        distances ("" otherwise). An outside audit: a pause read "no progress ... (now
        0.3 m)" while the fix lay 15 m off, the estimate drifted from the fixes."""
        fix = self._fix
        if estimate_m > ARRIVAL_GPS_MIN_M or fix is None or not self._fix_ok:
            return ""
        if self._gps_agrees(now):
            return ""
        assert fix.lat_deg is not None and fix.lon_deg is not None
        lat, lon = self._navigator.waypoints[self._navigator.index]
        fix_m = great_circle_m(fix.lat_deg, fix.lon_deg, lat, lon)
        return (
            f"; the estimate is {estimate_m:.1f} m from it but the latest fix {fix_m:.1f} m:"
            " the GPS does not confirm the arrival (the estimate drifted from the fixes)"
        )

    # ------------------------------------------------------------------ internals
    def _set_mode(self, mode: Mode, why: str, t_s: float, out: list[ControllerOutput]) -> None:
        if mode != self._mode:
            now = t_s if self._now is None else max(self._now, t_s)
            out.append(StateChange(now, str(self._mode), str(mode), f"mode: {why}"))
            self._mode = mode
            # an encoder verdict belongs to the drive it came in: one a hold or another
            # failsafe beat must not pause a later start, resume or return (code review)
            self._encoder_fault = ""
            self._enc_watch.reset()

    def _hold_check(self, now: float) -> str:
        """Why the robot must hold now ("" when every input is fresh)."""
        s = self._safety
        if not self._link_ok:
            return "motor link lost"
        down, back = self._sensor_down, self._sensor_back
        if down or back:
            for kind in SENSORS:
                if kind in down:
                    return f"{kind} {down[kind]}"
            if "gps" in back:
                return "gps back, waiting for a fresh fix"
            if "compass" in back:
                return "compass back, waiting for a fresh sample"
        if self._fix is None or self._valid_fix_t is None:
            return "no fix yet"
        gps_gap = ""
        if not self._fix_ok:
            gps_gap = "no valid fix"
        elif now - self._valid_fix_t > s.fix_stale_s:
            gps_gap = "fix stale"
        if gps_gap and not self._dead_reckoning_ok(now):
            return gps_gap
        if self._att is None:
            return "no attitude yet"
        if not self._att_ok:
            return "attitude invalid"
        if now - self._att.t_s > s.attitude_stale_s:
            return "attitude stale"
        if self._filt is None or self._current_heading_rad() is None:
            return "position estimate not ready"
        return self._uncertain_hold()

    def _uncertain_hold(self) -> str:
        """Hold while the EKF's error radius exceeds the degraded radius
        (:func:`~x6wd.nav.position.degraded_radius_m`: ``arrival_max_error_m``, or the site's
        configured noise at HDOP 3 where larger) with the next waypoint inside it: it cannot
        tell whether the robot is there. A town start on 4-satellite fixes (HDOP 12, 35 m
        off, sigma 26 m) otherwise took two waypoints as reached 38-42 m from them; holding,
        the robot drives on once the fixes improve, to where the waypoints are; held, only
        under :data:`UNCERTAIN_RELEASE` of that radius. ``position_timeout_s`` pauses it if
        they never do (:meth:`_failsafe_check`)."""
        cfg, nav, filt = self._nav_cfg, self._navigator, self._filt
        if cfg.arrival_max_error_m <= 0 or cfg.position_source != "ekf" or filt is None or nav.done:
            return ""
        held = self._hold_reason.startswith(UNCERTAIN_HOLD)
        noise_m = self._source.extra().get("ekf_noise_hdop1_m")
        limit_m = degraded_radius_m(
            cfg.arrival_max_error_m, noise_m if isinstance(noise_m, float) else 0.0
        )
        error_m = self._position_error_m()
        # held, it waits until the radius is well under the limit (no stop-and-go about it)
        if error_m <= (UNCERTAIN_RELEASE * limit_m if held else limit_m):
            return ""
        lat, lon = nav.waypoints[nav.index]
        if great_circle_m(filt[0], filt[1], lat, lon) > error_m:
            return ""
        what = "the launch point" if self._returning else f"waypoint {nav.index + 1}"
        return f"{UNCERTAIN_HOLD} to tell whether {what} is reached"

    def _mix(self, state: NavState) -> tuple[float, float]:
        """Left/right percentages for the navigator's decision just made."""
        c = self._nav_cfg
        if state in (NavState.STRAIGHT, NavState.ARRIVED):
            last = self._navigator.last
            if last is not None and last.curvature_per_m is not None:
                # pivot_arc: drive the arc at the approach speed (on an arrival: the next
                # leg's, when it does not start with a pivot).
                speed = c.cruise_pct if last.speed_pct is None else last.speed_pct
                return steering.skid_mix(last.curvature_per_m, speed, c.steer_track_m)
            if state == NavState.ARRIVED:
                return 0.0, 0.0
            return c.cruise_pct, c.cruise_pct
        if state == NavState.TURN_RIGHT:
            return c.turn_pct, -c.turn_pct
        if state == NavState.TURN_LEFT:
            return -c.turn_pct, c.turn_pct
        return 0.0, 0.0

    def _position_xy(self, filt: tuple[float, float]) -> tuple[float, float]:
        """The filtered position in the mission's plane (m), recomputed only when the
        position, the navigator or its projection changed."""
        nav = self._navigator
        key = (filt, nav, nav.projection)
        old = self._xy_key
        if old is None or old[0] is not filt or old[1] is not nav or old[2] is not key[2]:
            self._xy = nav.to_xy(*filt)
            self._xy_key = key
        return self._xy

    def _dead_reckoning_ok(self, now: float) -> bool:
        """May the robot drive on without a valid fix? Only on the EKF while the wheel
        encoders report (fresh), for at most ``safety.gps_outage_max_m`` of wheel travel since
        the last valid fix, at most ``DEAD_RECKONING_COMMANDED`` times that of commanded
        travel, at most ``_dead_reckoning_max_s`` since it (see ``DEAD_RECKONING_MIN_SPEED``)
        and while the estimate's uncertainty stays under
        ``DEAD_RECKONING_MAX_SIGMA_M``: beside a building the fix comes back a few metres on."""
        limit_m = self._safety.gps_outage_max_m
        odo, fix_t = self._odo_prev, self._valid_fix_t
        if limit_m <= 0 or self._nav_cfg.position_source != "ekf" or odo is None:
            return False
        if now - odo.t_s > ODOMETRY_FRESH_S or self._wheel_m - self._wheel_at_fix > limit_m:
            return False
        if self._commanded_m - self._commanded_at_fix > DEAD_RECKONING_COMMANDED * limit_m:
            return False  # the wheels count less than the robot was driven
        if fix_t is not None and now - fix_t > self._dead_reckoning_max_s:
            return False
        sigma_m = self._source.extra().get("ekf_sigma_m")
        return isinstance(sigma_m, float) and sigma_m <= DEAD_RECKONING_MAX_SIGMA_M

    def _gps_agrees(self, now: float) -> bool:
        """May the navigator declare an arrival now? Always with the GPS itself as the
        position; with the EKF only while the latest fix lies within ``ARRIVAL_GPS_SIGMAS``
        of its own noise (at least ``ARRIVAL_GPS_MIN_M``, plus the distance driven since) of
        the target, or (pivot_arc, a waypoint the path goes straight on through) is itself
        past the target along the track (:meth:`Navigator.passed_on_track`): wheels
        spinning on the spot must not carry the estimate to a waypoint the robot never
        reached (the stuck failsafe then acts)."""
        nav, fix = self._navigator, self._fix
        if self._nav_cfg.position_source != "ekf" or nav.done:
            return True
        if fix is None or not self._fix_ok or self._valid_fix_t is None:
            return self._dead_reckoning_ok(now)  # driving on without a fix: trust the EKF
        assert fix.lat_deg is not None and fix.lon_deg is not None
        g = self._gnss_cfg
        hdop = fix.hdop if fix.hdop is not None and fix.hdop > 0 else DEFAULT_HDOP
        sigma_m = hdop * math.sqrt(g.re_m**2 + g.ase_m**2 + g.lce_default_m**2)
        driven_m = self._nav_cfg.full_speed_mps * max(0.0, now - self._valid_fix_t)
        limit_m = max(ARRIVAL_GPS_MIN_M, ARRIVAL_GPS_SIGMAS * sigma_m) + driven_m
        lat, lon = nav.waypoints[nav.index]
        memo = self._to_target_m
        if memo is None or memo[0] is not fix or memo[1] != lat or memo[2] != lon:
            d = great_circle_m(fix.lat_deg, fix.lon_deg, lat, lon)
            memo = self._to_target_m = (fix, lat, lon, d)
        if memo[3] <= limit_m:
            return True
        # a track point the path goes straight on through: the fix past it along the track
        # agrees too (spinning wheels leave the fixes behind it)
        return nav.passed_on_track(fix.lat_deg, fix.lon_deg)

    def _position_error_m(self) -> float:
        """The error radius of the position the navigator steers by (m): ``ARRIVAL_GPS_SIGMAS``
        standard deviations per axis, the EKF's own (the RMS of east and north) or, for the
        other sources, the latest fix's (``HDOP·sqrt(RE² + ASE² + LCE_default²)``). The
        navigator does not chase round a waypoint behind the robot within it (``BEHIND_M``,
        its floor)."""
        if self._nav_cfg.position_source == "ekf":
            sigma_m = self._source.extra().get("ekf_sigma_m")
            if isinstance(sigma_m, float) and math.isfinite(sigma_m):
                return ARRIVAL_GPS_SIGMAS * sigma_m / math.sqrt(2.0)
            return 0.0
        fix = self._fix
        if fix is None or not self._fix_ok:
            return 0.0
        g = self._gnss_cfg
        hdop = fix.hdop if fix.hdop is not None and fix.hdop > 0 else DEFAULT_HDOP
        return ARRIVAL_GPS_SIGMAS * hdop * math.sqrt(g.re_m**2 + g.ase_m**2 + g.lce_default_m**2)

    def _body_moved_m(self, body: tuple[float, ...], fix: GpsFix) -> float:
        """Great-circle distance (m) from the stuck check's last body position to a usable
        fix, computed once per pair (the fix comes at 1 Hz, the check runs at every input)."""
        memo = self._body_to_fix_m
        if memo is None or memo[0] is not body or memo[1] is not fix:
            assert fix.lat_deg is not None and fix.lon_deg is not None
            d = great_circle_m(body[0], body[1], fix.lat_deg, fix.lon_deg)
            memo = self._body_to_fix_m = (body, fix, d)
        return memo[2]

    def _current_heading_rad(self) -> float | None:
        """True heading (rad, (−π, π]): the position source's when it has one (the EKF),
        else the compass's; None without either."""
        h = self._src_heading_deg
        if h is not None:
            # memoised on the source's float itself: the step's decision and its snapshot
            # then hold the very same heading object (the snapshot reuses the decision's
            # numbers only for an identical heading)
            memo = self._src_heading_rad
            if memo[0] is not h:
                memo = self._src_heading_rad = (h, math.radians(h - 360.0 if h > 180.0 else h))
            return memo[1]
        att = self._att
        if att is not None and self._att_ok:
            return self._heading_rad(att)
        return None

    def _heading_rad(self, att: Attitude) -> float:
        """True heading (rad) from a valid attitude, recomputed only for a new sample, a new
        navigator or a changed declination."""
        nav = self._navigator
        old = self._heading_key
        if old is None or old[0] is not att or old[1] is not nav or old[2] != nav.declination_deg:
            self._heading = nav.heading_from_compass(att.bearing_deg)
            self._heading_key = (att, nav, nav.declination_deg)
        return self._heading

    def _step(
        self, t_s: float, why: str, changes: list[ControllerOutput] | None = None
    ) -> list[ControllerOutput]:
        out: list[ControllerOutput] = [] if changes is None else changes
        now = t_s if self._now is None else max(self._now, t_s)
        if self._now is not None:
            # the command in force since the previous input, at its nominal speed
            cmd = self._cmd
            forward = abs(cmd.left_pct + cmd.right_pct) / 200.0
            self._commanded_m += self._nav_cfg.full_speed_mps * forward * (now - self._now)
        self._now = now

        if self._mode == Mode.MANUAL and self._manual is not None:
            if not self._link_ok:
                self._manual = None
                self._set_mode(Mode.IDLE, "manual drive cancelled: motor link lost", now, out)
            elif now >= self._manual[2]:
                self._manual = None
                self._set_mode(Mode.IDLE, "manual drive expired", now, out)

        src = self._source
        self._filt = src.position(now)
        if self._launch_raw and self._filt is not None:
            self._retake_raw_launch(now)
        self._src_heading_deg = src.heading_deg(now)
        hold = ""
        left = right = 0.0
        state: NavState
        if self._mode == Mode.RUNNING:
            hold = self._hold_check(now)
            fired = self._failsafe_check(now, hold)
            if fired is not None:
                why, action = fired
                keeps = why == "operator link lost"
                self._apply_failsafe(why, action, now, out, keeps_driving=keeps)
        stopping = self._mode == Mode.RUNNING and not hold and now < self._return_stop_until
        if self._mode == Mode.RUNNING:
            if hold or stopping:
                state = NavState.HOLD
            else:
                assert self._filt is not None and self._att is not None
                x, y = self._position_xy(self._filt)
                heading = self._current_heading_rad()
                assert heading is not None
                state = self._navigator.step(
                    x, y, heading, self._gps_agrees(now), self._position_error_m()
                )
                self._decided = (self._navigator.last, x, y, heading)
                if state == NavState.MISSION_DONE:
                    done = (
                        "back at the launch point" if self._returning else "last waypoint reached"
                    )
                    self._returning = ""
                    self._set_mode(Mode.DONE, done, now, out)
                left, right = self._mix(state)
        elif self._mode == Mode.MANUAL and self._manual is not None:
            state = NavState.IDLE
            left, right = self._manual[0], self._manual[1]
        elif self._mode == Mode.DONE:
            state = NavState.MISSION_DONE
        else:
            state = NavState.IDLE

        if state != self._state:
            reason = f"state: {hold}" if hold else f"state: {why}"
            if stopping:
                reason = f"state: {self._returning}: {RETURN_STOP_REASON}"
            last = self._navigator.last
            if state in _ARRIVALS and last is not None and last.arrived_by == "behind":
                # no visit: the log says which waypoint was taken as reached, and how far off
                reason += (
                    f"; waypoint {last.waypoint_index + 1} taken as reached"
                    f" {last.distance_m:.1f} m behind, within the position's error"
                )
            out.append(StateChange(now, str(self._state), str(state), reason))
            self._state = state
        elif (
            hold
            and self._hold_reason
            and hold.startswith(UNCERTAIN_HOLD) != self._hold_reason.startswith(UNCERTAIN_HOLD)
        ):
            # a hold that turns into a wait for the sky, or back into a sensor's hold (after
            # "position estimate not ready" at a start on 4 satellites): said, as a hold's
            # start is, so the log names what the robot holds for
            out.append(StateChange(now, str(state), str(state), f"state: {hold}"))
        self._hold_reason = hold
        if self._mode != Mode.RUNNING:
            self._uncertain_t = self._sensor_t = None  # the holds' clocks run only while running

        if hold:
            reason = f"hold: {hold}"
        elif stopping:
            reason = RETURN_STOP_REASON
        elif self._mode == Mode.MANUAL:
            reason = "manual"
        elif self._mode == Mode.RUNNING:
            reason = str(state)
        else:
            reason = str(self._mode).lower()
        self._intent = (left, right)
        held = self._reversal_stop(now, 0, left) | 2 * self._reversal_stop(now, 1, right)
        if held:
            if self._mode == Mode.MANUAL:
                # the operator asked for this motion, not one side of it: a pivot key after
                # driving ahead must not arc, a straight reverse after a pivot not swing
                left = right = 0.0
            else:
                left = 0.0 if held & 1 else left
                right = 0.0 if held & 2 else right
            reason = f"{reason}; {REVERSE_STOP_NOTE}"
        prev = self._cmd
        self._cmd = MotorCommand(now, left, right, reason)
        if prev.left_pct != left or prev.right_pct != right:
            src.on_command(now, left, right)
        self._telemetry = self._snapshot(now)
        out.append(self._cmd)
        out.append(self._telemetry)
        return out

    def _reversal_stop(self, now: float, side: int, pct: float) -> bool:
        """Must ``side`` (0 left, 1 right) be held at 0 instead of ``pct`` (%) at ``now`` (s)?
        Yes while ``pct`` reverses the side's last non-zero command and the side has not yet
        been commanded 0 for ``REVERSE_STOP_S``; bookkeeping for the side otherwise."""
        sign = (pct > 0) - (pct < 0)
        zero_t = self._side_zero_t[side]
        if sign == 0:
            if zero_t is None:
                self._side_zero_t[side] = now
            return False
        last = self._side_sign[side]
        if last and sign != last:
            if zero_t is None:
                self._side_zero_t[side] = now
                return True
            if now - zero_t < REVERSE_STOP_S:
                return True
        self._side_sign[side] = sign
        self._side_zero_t[side] = None
        return False

    def _snapshot(self, now: float) -> Telemetry:
        # Runs on every call (20 Hz from the compass alone): plain locals, no recomputation.
        nav = self._navigator
        fix, att, filt = self._fix, self._att, self._filt
        has_mission = self._has_mission
        done = nav.done
        x = y = target_deg = theta_deg = dist = None
        heading_rad = self._current_heading_rad()
        if has_mission and filt is not None:
            x, y = self._position_xy(filt)
            if not done:
                last = nav.last
                d = self._decided
                if (
                    d is not None
                    and last is not None
                    and d[0] is last
                    and last.phi_i_rad is not None
                    and last.theta_rad is not None
                    and last.waypoint_index == nav.index
                    and d[1] is x
                    and d[2] is y
                    and d[3] is heading_rad
                ):
                    # The navigator just decided on this very position, target and heading
                    # with the same formulas: reuse its numbers instead of recomputing them.
                    dist = last.distance_m
                    target_deg = math.degrees(last.phi_i_rad)
                    theta_deg = math.degrees(last.theta_rad)
                else:
                    xi, yi = nav.target_xy()
                    dx, dy = xi - x, yi - y
                    dist = math.hypot(dx, dy)
                    if dist > 0:
                        phi = geo.destination_bearing(x, y, xi, yi)
                        target_deg = math.degrees(phi)
                        if heading_rad is not None:
                            theta_deg = math.degrees(geo.course_deviation(phi, heading_rad))
        extra: dict[str, object] = self._source.extra()
        if self.returning:
            extra["returning"] = self._returning
        if self._failsafe_why:
            extra["failsafe"] = self._failsafe_why
        if self._mode == Mode.PAUSED:
            # who paused it: "operator" or "failsafe: <why>" (after a resume and the
            # operator's own pause, extra.failsafe still names the last failsafe that acted)
            extra["paused_by"] = self._paused_by
        untrusted = self._trust.verdict(now)
        if untrusted:
            extra["compass_untrusted"] = untrusted
        if self._sky is not None:
            extra["sats_in_view"] = len(self._sky.satellites)
        if not self._link_ok:
            extra["motor_link"] = "lost"
        if self._sensor_down:
            extra["sensors_down"] = dict(self._sensor_down)
        if self._nav_cfg.steering == "pivot_arc" and has_mission:
            last = nav.last
            if last is not None:
                # The steering command behind left_pct/right_pct (no Telemetry field for it).
                a = last.steer_alpha_rad
                extra["steer_alpha_deg"] = math.degrees(a) if a is not None else None
                extra["curvature_per_m"] = last.curvature_per_m
                extra["speed_pct"] = last.speed_pct
                extra["pivoting"] = nav.pivoting
                if last.arrived_by:
                    extra["arrived_by"] = last.arrived_by
        valid_fix_t = self._valid_fix_t
        cmd = self._cmd
        if fix is None:
            lat = lon = sats_used = hdop = None
            quality = 0
        else:
            lat, lon, quality = fix.lat_deg, fix.lon_deg, fix.quality
            sats_used, hdop = fix.sats_used, fix.hdop
        good_att_t = self._good_att_t
        att_age = now - good_att_t if good_att_t is not None else None
        if att is None:
            bearing = pitch = roll = None
        else:
            bearing, pitch, roll = att.bearing_deg, att.pitch_deg, att.roll_deg
        return Telemetry(
            t_s=now,
            mode=self._mode,
            state=self._state,
            hold_reason=self._hold_reason,
            waypoint_index=nav.index if has_mission and not done else None,
            waypoint_count=len(nav.waypoints) if has_mission else 0,
            lat_deg=lat,
            lon_deg=lon,
            filt_lat_deg=filt[0] if filt is not None else None,
            filt_lon_deg=filt[1] if filt is not None else None,
            x_m=x,
            y_m=y,
            bearing_deg=bearing,
            heading_deg=math.degrees(heading_rad) if heading_rad is not None else None,
            pitch_deg=pitch,
            roll_deg=roll,
            target_bearing_deg=target_deg,
            theta_deg=theta_deg,
            distance_m=dist,
            fix_quality=quality,
            sats_used=sats_used,
            hdop=hdop,
            fix_age_s=now - valid_fix_t if valid_fix_t is not None else None,
            attitude_age_s=att_age,
            left_pct=cmd.left_pct,
            right_pct=cmd.right_pct,
            extra=extra,
        )
