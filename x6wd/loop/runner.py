"""The one control loop: device records and operator requests in, through the controller, out
to the motors, the telemetry watchers and the recorder.

Every edge drives this same object (docs/architecture.md, "The loop and its edges"):

- the robot (``x6wd run``): device threads post records to the daemon's event loop, which
  calls :meth:`Runner.gps`, :meth:`Runner.attitude`, :meth:`Runner.device_events`; a task
  calls :meth:`Runner.tick` at the control rate; the clock is ``time.monotonic``;
- hardware in the loop: the same daemon with ``sim://`` devices;
- fast time (``x6wd sim``): the simulator calls the same methods with its own clock.

So every safety rule lives either in the sans-IO controller or here, and a fast-time run
exercises all of them: the geofence (waypoints checked when a mission is loaded; while a
mission runs, every usable fix the EKF takes unless its HDOP says it is meaningless, three
meaningful fixes in a row whether the EKF takes them or not, and the controller's estimate
after every usable fix and a few times a second without a fresh one; a breach gets
``failsafe.geofence_action``),
the manual-drive limit, the hold on a sensor its reader reports down, the stop that reaches
the motors first.

The runner never reads a device, sleeps or touches a socket. Its outputs go to callables the
edge supplies: ``motors(cmd)`` must not block (the daemon queues it for the motor thread,
the simulator moves its vehicle), ``record(method, arg)`` calls ``Recorder.<method>(arg)``
(the daemon on its recorder thread), ``publish(event)`` sends a JSON-ready event to watching
clients.
"""

from __future__ import annotations

import asyncio
import logging
import math
from collections import deque
from collections.abc import Callable, Coroutine, Iterable, Sequence
from contextvars import ContextVar
from dataclasses import replace
from typing import Any

from drivers.gps_nmea import NmeaSentence
from x6wd.core.config import SafetyConfig
from x6wd.core.errors import CommandError
from x6wd.core.geodesy import great_circle_m
from x6wd.core.health import TRANSITION, HealthLog
from x6wd.core.mission_files import Waypoint
from x6wd.core.ratelog import RateLimitedLog
from x6wd.core.records import (
    USABLE_STATES,
    Attitude,
    GpsFix,
    GpsSky,
    HealthEvent,
    Mode,
    MotorCommand,
    StateChange,
    Telemetry,
    WheelOdometry,
)
from x6wd.nav.controller import MEANINGLESS_HDOP, Controller, has_usable_position
from x6wd.nav.declination import DeclinationError, declination_deg

log = logging.getLogger("x6wd.loop.runner")

TELEMETRY_EVENT_HZ = 10.0
"""Most telemetry events per second to watching clients (fixes and state changes always go)."""
TELEMETRY_RECORD_HZ = 1.0
"""Most telemetry snapshots per second to the recorder (fixes and state changes always go)."""
ESTIMATE_FENCE_PERIOD_S = 0.25
"""Without a fresh usable fix the geofence is checked on the controller's position estimate
at most this often (s): the robot drives on its wheels through an outage (up to
``safety.gps_outage_max_m``) and must not leave the fence unseen until the next fix."""

FENCE_FIXES_IN_ROW = 3
"""Usable fixes in a row outside the geofence that are a breach whatever the EKF and the
estimate say (each within ``safety.fix_stale_s`` of the one before: at 1 Hz the third comes
2 s after the first). Catches a robot really outside whose estimate refuses to follow."""
Clock = Callable[[], float]
"""Seconds on one monotonic clock: ``time.monotonic`` on the robot, simulated time in fast time."""

LOOP_LATE_WINDOW_S = 60.0
"""``loop_status()["late_max_s"]``: the most a tick started late within this many seconds (s)."""
LOOP_LATE_LOG_S = 10.0
"""At most one "control loop late" warning per this many seconds (s); the rest are counted."""
_STALE_HOLDS = {"attitude stale": "attitude", "fix stale": "fix"}
"""The controller's holds on a sample too old, and which sample (its age in telemetry)."""

_TICK_DUE: ContextVar[tuple[float, float] | None] = ContextVar("x6wd_tick_due", default=None)
"""(due_s, period_s) of the step :func:`every` is calling now: :meth:`Runner.tick` learns
how late it started through any wrapper (the daemon's locked ticks) without a parameter."""


class LoopLateness:
    """How late the control loop's ticks start against their schedule (s): the loop's own
    lateness. A CPU-starved core shows here first: an outside audit (3 CPU hogs at nice -10
    on the daemon's core) saw ticks 0.6 s late hold the robot on "attitude stale" while the
    compass's samples sat in the loop's queue."""

    def __init__(self, window_s: float = LOOP_LATE_WINDOW_S) -> None:
        self.window_s = window_s
        self.ticks = 0
        self.overruns = 0
        """Ticks that started more than one period late."""
        self.late_holds = 0
        """Stale-sensor holds that began while the loop was late (``Runner._late_note``)."""
        self.period_s: float | None = None  # the ticks' period (s); None before the first
        self.last_late_s = 0.0
        self._peaks: deque[tuple[float, float]] = deque()  # (t_s, late_s), late decreasing
        self._next_due_s: float | None = None  # the next tick's due time, at the latest (s)

    def tick(self, t_s: float, due_s: float, period_s: float) -> float:
        """A tick due at ``due_s`` started at ``t_s`` (s; ticks every ``period_s``): its
        lateness (s, at least 0) is kept; returns it."""
        late_s = max(0.0, t_s - due_s)
        self.ticks += 1
        self.period_s = period_s
        self.last_late_s = late_s
        if late_s > period_s:
            self.overruns += 1
        while self._peaks and self._peaks[-1][1] <= late_s:
            self._peaks.pop()
        self._peaks.append((t_s, late_s))
        self._expire(t_s)
        # every() starts its schedule afresh after a long stall: the next tick is due then
        # at the latest, so between ticks the lateness read from it is never overstated
        self._next_due_s = max(due_s + period_s, t_s)
        return late_s

    def overdue_s(self, now_s: float) -> float:
        """How late the next tick is already at ``now_s`` (s; 0 on time or before any)."""
        due_s = self._next_due_s
        return 0.0 if due_s is None else max(0.0, now_s - due_s)

    def max_s(self, now_s: float) -> float:
        """The most a tick started late (s) within ``window_s`` before ``now_s``."""
        self._expire(now_s)
        return self._peaks[0][1] if self._peaks else 0.0

    def status(self, now_s: float) -> dict[str, Any]:
        """JSON-ready figures for ``status``'s ``loop``. Read-only: the daemon calls it from
        its network thread while the control thread ticks (a snapshot of the peaks, taken
        in one C call, is read; nothing is expired here)."""
        peaks = tuple(self._peaks)
        late_max_s = max((late for t, late in peaks if t >= now_s - self.window_s), default=0.0)
        return {
            "tick_period_s": self.period_s,
            "ticks": self.ticks,
            "late_last_s": round(self.last_late_s, 4),
            "late_max_s": round(late_max_s, 4),
            "late_window_s": self.window_s,
            "overruns": self.overruns,
            "stale_holds_while_late": self.late_holds,
        }

    def _expire(self, now_s: float) -> None:
        while self._peaks and self._peaks[0][0] < now_s - self.window_s:
            self._peaks.popleft()


FENCE_EDGE_MARGIN_M = 5.0
"""A waypoint this near the geofence's edge (m) is loaded with a note: the GPS's error (2-7 m
on a NEO-5) and the arrival's overshoot may take the robot across the edge."""

SURPRISE_WARN_OF_JUMP = 0.4
"""A reset of the EKF beyond its own 99 % ellipse is a WARNING from this fraction of
``failsafe.gps_jump_m`` (10 m of the default 25 m; the failsafe itself pauses from 1)."""


def _nothing(*_args: Any) -> None:
    return None


def _never() -> bool:
    return False


def _metres_beyond(d_m: float, limit_m: float, least: int = 0) -> str:
    """``d_m`` (m, beyond ``limit_m``) with the fewest decimals (``least`` to 6) that still
    read beyond the limit: "102" past 100, "15.03" past 15, never "15" past 15."""
    for decimals in range(least, 7):
        text = f"{d_m:.{decimals}f}"
        if float(text) > limit_m:
            return text
    return f"{d_m:.12g}"  # NaN, or a hair's breadth beyond


class Runner:
    """Routes every input through the controller and every output to its sink.

    ``controller``: the sans-IO brain. ``safety``: the geofence and manual-drive limits.
    ``clock()``: now (s) for operator requests and ticks. ``motors(cmd)``: hand a motor
    command over (must not block). ``record(method, arg)``: one recorder call, or None.
    ``publish(event)``: a telemetry or state event for watching clients, or None.
    ``devices()``: every device's health as a JSON-ready dict, sent with telemetry events.
    ``on_state(change)``: called after each state change (the daemon tells systemd).
    ``observe(outputs, important)``: sees every controller output list (the simulator keeps
    its trace with it; tests watch with it). ``wmm_declination``: the configuration gives no
    declination, so the World Magnetic Model's value for the first dated fix is used.
    """

    def __init__(
        self,
        controller: Controller,
        safety: SafetyConfig,
        clock: Clock,
        *,
        motors: Callable[[MotorCommand], bool | None],
        record: Callable[[str, Any], None] | None = None,
        publish: Callable[[dict[str, Any]], None] | None = None,
        devices: Callable[[], dict[str, Any]] | None = None,
        on_state: Callable[[StateChange], None] | None = None,
        observe: Callable[[list[Any], bool], None] | None = None,
        health_log: HealthLog | None = None,
        wmm_declination: bool = False,
    ) -> None:
        self.controller = controller
        self.safety = safety
        self.clock = clock
        self._motors = motors
        self._record = record or _nothing
        self._publish = publish
        self._devices = devices or dict
        self._on_state = on_state
        self._observe = observe
        self._health_log = health_log or HealthLog(
            logging.getLogger("x6wd.core.health"), clock=clock
        )
        self._operator_log = RateLimitedLog(log, 1.0, clock)
        self.loop = LoopLateness()
        """The control loop's own lateness: ticks started late (see :meth:`loop_status`)."""
        self._loop_log = RateLimitedLog(log, LOOP_LATE_LOG_S, clock)
        self._tick_late_s: float | None = None  # the running tick's lateness (s)
        self._raw_hold = ""  # the controller's hold reason in its latest telemetry
        self._hold_note = ""  # what the runner adds to that hold's reason ("": nothing)
        self._drive_pct: tuple[float, float] | None = None  # the latest manual drive (%)
        self.last_telemetry: Telemetry | None = None
        self._compass_untrusted = False  # the controller's verdict, logged as it changes
        self._odometry_warned = False  # the wheels-vs-fixes warning, logged once
        self._no_fix_since: float | None = None  # no valid fix from then (s; None: have one)
        self._no_fix_warned = False  # "no valid fix" logged for the current spell
        self._gps_data_t: float | None = None  # the latest GPS record's receive time (s)
        self.gps_at_end: Callable[[], bool] = _never
        """True once the GPS source has no more data to give (a ``replay://`` log played to
        its end): the quiet line is then named for that, not for its wiring. Set by the
        daemon."""
        self.gps_log_silent: Callable[[], bool] = _never
        """True while a ``replay://`` log is itself silent (more data follows): named so
        too. Set by the daemon."""
        self._resets_seen = 0  # EKF resets logged so far
        self.first_fix: tuple[float, float] | None = None
        """(lat_deg, lon_deg) of the first valid fix: the geofence centre unless configured."""
        self.geofence_breaches = 0
        self.surprise_resets_m: list[float] = []
        """The EKF's resets (m) under ``failsafe.gps_jump_m`` but beyond its own ellipse and
        :data:`SURPRISE_WARN_OF_JUMP` of that limit or more: each a WARNING."""
        self.compass_repeats = 0
        """Compass samples not newer than the last one taken: seen, not used (see
        :meth:`attitude`)."""
        self._att_t: float | None = None  # t_s of the last compass sample taken (s)
        self._last_pos: tuple[float, float] | None = None  # latest valid fix (lat, lon deg)
        self._last_pos_t: float | None = None  # its time (s)
        self._fix_usable = False  # the latest fix record had a usable position
        self._fix_hdop_refused: float | None = None  # its HDOP when only that refused it
        self._t_fence_est = -math.inf  # the latest geofence check of the estimate (s)
        self._fence_run = 0  # usable fixes in a row outside the geofence
        self._fence_run_t: float | None = None  # the latest of them (s)
        self._last_motor_rec: tuple[float, float] | None = None
        self._t_pub = -math.inf
        self._t_rec = -math.inf
        self._t_stepped: float | None = None  # time of the controller's latest step (s)
        self.stats: dict[str, int] = {"fixes": 0, "attitudes": 0, "odometry": 0}
        self._wmm_pending = wmm_declination
        self.declination: dict[str, Any] = {"source": "wmm" if wmm_declination else "config"}
        """Where the declination came from; with WMM also its value or why there is none."""

    # -- device inputs ------------------------------------------------------------------------
    def gps(self, records: Iterable[Any]) -> None:
        """Records from the GPS decoder (``drivers.gps_nmea.GpsOutput``): fixes, satellites in
        view, the raw sentences (recorded); anything else is ignored."""
        for rec in records:
            self.gps_record(rec)

    def gps_record(self, rec: Any) -> None:
        """One record from the GPS decoder (see :meth:`gps`)."""
        if isinstance(rec, GpsFix):
            self._gps_data(rec.t_s)
            self.stats["fixes"] += 1
            self._record("record_fix", rec)
            self._fix_usable = has_usable_position(rec)
            hdop = rec.hdop
            refused_for_hdop = (
                not self._fix_usable and hdop is not None and hdop >= MEANINGLESS_HDOP
            )
            self._fix_hdop_refused = hdop if refused_for_hdop and rec.valid else None
            refused_before = self._ekf_refused()  # None: the source takes every fix
            if self._fix_usable:
                assert rec.lat_deg is not None and rec.lon_deg is not None
                self._last_pos = (rec.lat_deg, rec.lon_deg)
                self._last_pos_t = rec.t_s
                if self.first_fix is None:
                    self.first_fix = self._last_pos
                if self._wmm_pending and rec.utc is not None:
                    self._set_wmm_declination(rec)
                fence = self._fence_before_fix(rec)
                if fence is not None:  # before the fix can steer: a breach stops first
                    self._breach(*fence, rec.t_s)
            else:
                self._check_estimate(rec.t_s)
            outputs = self.controller.on_fix(rec)
            self._t_stepped = rec.t_s
            fence = None
            if self._fix_usable:
                refused_after = self._ekf_refused()
                taken = None  # the source takes every fix: judged before the step
                if refused_before is not None and refused_after is not None:
                    taken = refused_after == refused_before
                fence = self._fence_after_fix(rec, taken)
            if fence is None:
                self._handle(outputs, True)
                return
            # the breach's stop replaces this step's drive: the motors never get it
            self._handle([o for o in outputs if type(o) is not MotorCommand], True)
            self._breach(*fence, rec.t_s)
        elif isinstance(rec, GpsSky):
            self._gps_data(rec.t_s)
            self._record("record_sky", rec)
            self._handle(self.controller.on_sky(rec), False)
        elif isinstance(rec, NmeaSentence):
            self._gps_data(rec.t_s)
            self._record("record_nmea", rec.text)

    def _gps_data(self, t_s: float) -> None:
        """A GPS record (a checksum-valid sentence, a fix, a sky report) came at ``t_s``."""
        last = self._gps_data_t
        if last is None or t_s > last:
            self._gps_data_t = t_s

    def gps_line_quiet(self, t_s: float) -> str:
        """Why there is no fix when the GPS line delivers nothing decodable: no record (a
        checksum-valid sentence, a fix, a sky report) for more than
        :data:`GPS_QUIET_OF_FIX_STALE` of ``safety.fix_stale_s`` by ``t_s`` (s): a line
        silent, at the wrong baud or every sentence corrupt. "" while the receiver talks
        (searching, the sky blocked: its sentences say there is no position)."""
        last = self._gps_data_t
        if last is None:
            if self.gps_at_end():
                return "no data from the receiver: the replayed log has none that decodes"
            return "no data from the receiver: check the line's wiring, baud and power"
        quiet_s = t_s - last
        if quiet_s <= GPS_QUIET_OF_FIX_STALE * self.safety.fix_stale_s:
            return ""
        if self.gps_at_end():
            return f"no data from the receiver for {quiet_s:.1f} s: the replayed log has ended"
        if self.gps_log_silent():
            return f"no data from the receiver for {quiet_s:.1f} s: the replayed log is silent here"
        return (
            f"no good data from the receiver for {quiet_s:.1f} s: check the line's wiring,"
            " baud and power"
        )

    def _set_wmm_declination(self, fix: GpsFix) -> None:
        """The World Magnetic Model's declination at the first dated fix (once). On the robot
        the fix's date has already been corrected for a receiver past a GPS week rollover
        (1024 weeks early) by the daemon's GPS reader: ``drivers.gps_io.WeekRolloverCorrection``.
        """
        self._wmm_pending = False
        assert fix.lat_deg is not None and fix.lon_deg is not None and fix.utc is not None
        alt_m = (fix.alt_m or 0.0) + (fix.geoid_sep_m or 0.0)
        try:
            d = declination_deg(fix.lat_deg, fix.lon_deg, alt_m, fix.utc)
        except DeclinationError as exc:
            # the robot still navigates by the compass, but its heading is off by the
            # unknown declination: say so in the log and in status
            self.declination["error"] = str(exc)
            log.warning(
                "no declination from the World Magnetic Model (%s): using 0; set "
                "compass.declination_deg",
                exc,
            )
            return
        self.declination["deg"] = round(d, 3)
        log.info(
            "declination %.2f deg from the World Magnetic Model at %.5f, %.5f",
            d,
            fix.lat_deg,
            fix.lon_deg,
        )
        self._handle(self.controller.set_declination(d, fix.t_s), False)

    def odometry(self, rec: WheelOdometry) -> None:
        """Wheel-encoder counts from the motor board (recorded)."""
        self.stats["odometry"] += 1
        self._record("record_odometry", rec)
        self._check_estimate(rec.t_s)
        outputs = self.controller.on_odometry(rec)
        self._t_stepped = rec.t_s
        self._handle(outputs, False)

    def operator_seen(self) -> None:
        """An operator's request came over the network (the operator-link failsafe)."""
        self.controller.operator_seen(self.clock())

    def attitude(self, att: Attitude) -> None:
        """A compass sample (counted in ``stats["attitudes"]``).

        One whose ``t_s`` is not newer than the last one taken is a repeat, counted in
        :attr:`compass_repeats` and otherwise dropped (neither recorded nor given to the
        controller): the driver answers a failed read with its last good attitude, old
        ``t_s`` and all, and the daemon posts whatever it answers every period. Given to
        the controller again, the same bearing reached the EKF each time, which takes an
        input up to 0.3 s late as if it were now: a stale bearing fused several times over
        while the robot turned. The compass's staleness does not need the repeats: the
        controller judges it by the time of the last sample it took
        (``safety.attitude_stale_s``), the driver by its own count and age (a ``stale``
        health event and an invalid sample, stamped now)."""
        self.stats["attitudes"] += 1
        last_t = self._att_t
        if last_t is not None and att.t_s <= last_t:
            self.compass_repeats += 1
            return
        self._record("record_attitude", att)
        self._check_estimate(att.t_s)
        outputs = self.controller.on_attitude(att)
        self._att_t = att.t_s
        self._t_stepped = att.t_s
        self._handle(outputs, False)

    def device_events(self, events: Sequence[HealthEvent]) -> None:
        """Health events from a device's reader: each logged (rate-limited per device) and
        recorded (``x6wd plot`` draws them); a sensor's transition reaches the controller at
        once, so an unplugged GPS holds the robot within this call, not after the fix
        timeout."""
        for ev in events:
            self._health_log.event(ev)
            self._record("record_health", ev)
            if ev.kind == TRANSITION and ev.device in ("gps", "compass"):
                ok = ev.new in USABLE_STATES
                self._handle(self.controller.sensor_health(ev.device, ok, ev.t_s, str(ev.new)))

    def motor_link(self, ok: bool, t_s: float) -> None:
        """The motor link went up or down at ``t_s`` (s); logged by its health events."""
        self._handle(self.controller.motor_link(ok, t_s))

    def tick(self, t_s: float | None = None) -> None:
        """Time passes (default: the clock): staleness and the dead-man are checked. A tick at
        the very time of the controller's latest step is skipped: it would decide the same.
        Called by :func:`every`, how late it started is kept in :attr:`loop` first."""
        t = self.clock() if t_s is None else t_s
        due = _TICK_DUE.get()  # called by every(): on a schedule whose lateness is measured
        late_s = None if due is None else self.loop.tick(t, *due)
        if due is not None and late_s is not None and late_s > due[1]:  # an overrun
            self._loop_log.log(
                "late",
                logging.WARNING,
                "control loop late by %.2f s (CPU starved?): a tick due every %.3g s; %d "
                "ticks late by more than that so far",
                late_s,
                due[1],
                self.loop.overruns,
            )
        if t == self._t_stepped:
            return
        self._tick_late_s = late_s
        try:
            self._check_estimate(t)
            outputs = self.controller.tick(t)
            self._t_stepped = t
            self._handle(outputs, False)
        finally:
            self._tick_late_s = None

    @property
    def fix_refused_hdop(self) -> float | None:
        """The latest fix record's HDOP when the receiver called it valid and only its HDOP
        (20 or more, ``MEANINGLESS_HDOP``) made it no fix; else None."""
        return self._fix_hdop_refused

    def loop_status(self) -> dict[str, Any]:
        """The control loop's lateness for ``status``: the period of its ticks
        (``tick_period_s``), how late the latest started (``late_last_s``) and the most one
        started late within ``late_window_s`` (``late_max_s``), ticks late by more than a period
        (``overruns``) and stale-sensor holds that began while it was late
        (``stale_holds_while_late``); all s or counts. Without :func:`every` driving the
        ticks (fast time) everything stays 0."""
        return self.loop.status(self.clock())

    # -- operator requests --------------------------------------------------------------------
    def load_mission(self, waypoints: Sequence[Waypoint]) -> dict[str, Any]:
        """Check every waypoint against the geofence, then hand them to the controller."""
        near = self._check_geofence(waypoints)
        pairs = [(w.lat_deg, w.lon_deg) for w in waypoints]
        self._handle(self.controller.load_mission(pairs, self.clock()))
        log.info("mission loaded: %d waypoints", len(pairs))
        if not near:
            return {"count": len(pairs)}
        radius_m = self.safety.geofence_radius_m
        shown = ", ".join(f"{i + 1} ({inside_m:.1f} m)" for i, inside_m in near[:5])
        more = f" and {len(near) - 5} more" if len(near) > 5 else ""
        note = (
            f"waypoint{'s' if len(near) > 1 else ''} {shown}{more} within"
            f" {FENCE_EDGE_MARGIN_M:g} m of the geofence's edge ({radius_m:.12g} m): the GPS's"
            " error or the arrival may take the robot across it, and a breach pauses the"
            " mission"
        )
        log.warning("mission: %s", note)
        return {"count": len(pairs), "notes": [note]}

    def command(self, name: str) -> dict[str, Any]:
        """``start``, ``pause``, ``resume``, ``return`` (to the launch point) or ``stop`` the
        mission; returns mode and state."""
        if name not in ("start", "pause", "resume", "return", "stop"):
            raise CommandError("bad_request", f"unknown mission command {name!r}")
        if name in ("start", "resume") and self._fence_applies(name):
            self._check_inside(name)
        method = self.controller.return_home if name == "return" else getattr(self.controller, name)
        self._handle(method(self.clock()))
        # a stop storm must not flood the log (the server coalesces, but still ~100/s)
        self._operator_log.log(name, logging.INFO, "operator: %s", name)
        tel = self.controller.telemetry
        return {"mode": str(tel.mode), "state": str(tel.state)}

    def stop(self) -> dict[str, Any]:
        """Stop from any state; the stop command goes to the motors first."""
        self._motors(MotorCommand(self.clock(), 0.0, 0.0, "operator stop"))
        return self.command("stop")

    def shutdown(self, reason: str) -> None:
        """The edge is shutting down (a signal, a fatal error): the motors get a stop with
        ``reason`` and the controller stops (mode IDLE, the state change's reason
        ``reason``). The stop is recorded even when the motors stood still already, so a
        recording that ends this way says so: a clean exit, not a crash or a power cut."""
        t = self.clock()
        cmd = MotorCommand(t, 0.0, 0.0, reason)
        try:
            self._motors(cmd)
        finally:  # a failing motor sink must not keep the stop out of the recording
            self._last_motor_rec = (cmd.left_pct, cmd.right_pct)
            self._record("record_motor", cmd)
            self._handle(self.controller.stop(t, reason))

    def drive(self, left_pct: float, right_pct: float, duration_s: float) -> dict[str, Any]:
        """Manual drive (%) for ``duration_s`` (s); refused above ``safety.manual_max_s``."""
        limit = self.safety.manual_max_s
        if duration_s > limit:
            # 12 digits: "5.0000001 > limit 5", never "5 > limit 5"
            raise CommandError("bad_request", f"duration_s {duration_s:.12g} > limit {limit:g} s")
        renewal = self.controller.mode == Mode.MANUAL  # a held key's resend, or a new key
        self._handle(self.controller.manual_drive(left_pct, right_pct, duration_s, self.clock()))
        # One line per press, not per drive: a held key is resent ~3 times a second (a line
        # each made 10,800 an hour: outside audit, round 7). The press's first drive is
        # logged, a change of speeds while driving at most once a second, the resends of the
        # same speeds not at all; its end is the state change's line (MANUAL -> IDLE), which
        # names the press's last speeds (a second change within a second is only counted).
        pct = (float(left_pct), float(right_pct))
        what = "operator: drive L%+.0f R%+.0f for %.1f s"
        if not renewal:
            log.info(what, left_pct, right_pct, duration_s)
        elif pct != self._drive_pct:
            self._operator_log.log(
                "drive", logging.INFO, what + " (changed while driving)", *pct, duration_s
            )
        self._drive_pct = pct
        return {"left": left_pct, "right": right_pct, "duration_s": duration_s}

    # -- the geofence -------------------------------------------------------------------------
    def geofence_centre(self) -> tuple[float, float] | None:
        """(lat_deg, lon_deg): ``safety.geofence_center``, else the first valid fix, else None."""
        c = self.safety.geofence_center
        if len(c) == 2:
            return (c[0], c[1])
        return self.first_fix

    def _check_geofence(self, waypoints: Sequence[Waypoint]) -> list[tuple[int, float]]:
        """Refuse a waypoint outside the geofence; (index, metres inside the edge) of those
        within :data:`FENCE_EDGE_MARGIN_M` of it (an audit: one 0.5 m inside was accepted,
        then the robot paused 1 m short of it, outside)."""
        centre = self.geofence_centre()
        if centre is None:
            raise CommandError("geofence", "no fix yet: cannot check waypoints against geofence")
        radius_m = self.safety.geofence_radius_m
        near: list[tuple[int, float]] = []
        for i, wp in enumerate(waypoints):
            d = great_circle_m(centre[0], centre[1], wp.lat_deg, wp.lon_deg)
            if not d <= radius_m:  # fails closed: NaN is outside
                raise CommandError(
                    "geofence",
                    f"waypoint {i + 1} ({wp.lat_deg:.7f}, {wp.lon_deg:.7f}) is "
                    f"{_metres_beyond(d, radius_m)} m from the geofence centre; limit "
                    f"{radius_m:.12g} m",
                )
            if radius_m - d < FENCE_EDGE_MARGIN_M:
                near.append((i, radius_m - d))
        return near

    def _fence_applies(self, what: str) -> bool:
        """Whether ``start`` or ``resume`` (``what``) is judged against the geofence: not
        where the controller refuses it anyway (no mission, nothing paused, already
        running: its own reason is the useful one), and not for a paused return to launch,
        which leads back inside and which the fence does not stop while it runs (a second
        ``return`` restarts it outside the fence too)."""
        ctl = self.controller
        if what == "resume":
            return ctl.mode == Mode.PAUSED and not ctl.returning
        return ctl.mode not in (Mode.RUNNING, Mode.PAUSED) and bool(ctl.waypoints)

    def _check_inside(self, what: str) -> None:
        """Refuse ``what`` while the latest valid fix lies outside the geofence; the refusal
        names the ways back that the robot accepts from where it is."""
        centre, pos = self.geofence_centre(), self._last_pos
        if centre is None or pos is None:
            return
        d = great_circle_m(centre[0], centre[1], pos[0], pos[1])
        radius_m = self.safety.geofence_radius_m
        if d <= radius_m:  # fails closed: NaN is outside
            return
        where = (
            f"cannot {what}: the robot is {_metres_beyond(d, radius_m)} m from the geofence "
            f"centre; limit {radius_m:.12g} m"
        )
        if what != "resume":  # idle, done or driving by hand: manual drive is allowed
            raise CommandError("geofence", f"{where} (drive it back by hand: 'drive')")
        # a paused mission: resumed, it would drive on from outside (and pause again at the
        # next fix); 'drive' is refused while a mission is paused
        ways = []
        launch = self.controller.launch_point
        if launch is not None and great_circle_m(*centre, *launch) <= radius_m:
            away_m = great_circle_m(pos[0], pos[1], launch[0], launch[1])
            ways.append(
                f"'return' (to the launch point, {away_m:.1f} m away, inside the fence: the "
                "fence does not stop a return; the mission ends there)"
            )
        ways.append(
            "'stop', then drive it back by hand ('drive') and 'start' the mission again "
            "(from its first waypoint)"
        )
        raise CommandError(
            "geofence",
            f"{where}: resumed, the mission would drive on from outside the fence. Ways back: "
            + ", or ".join(ways),
        )

    def _outside_m(self, lat_deg: float, lon_deg: float) -> float | None:
        """How far (m) from the geofence centre a position outside the fence lies; None
        inside it or without a centre. Fails closed: NaN is outside."""
        centre = self.geofence_centre()
        if centre is None:
            return None
        d = great_circle_m(centre[0], centre[1], lat_deg, lon_deg)
        return None if d <= self.safety.geofence_radius_m else d

    def _fence_armed(self) -> bool:
        """A breach is acted on: a mission runs, and it is not a return to launch (which
        leads back inside: let it)."""
        ctl = self.controller
        return ctl.mode == Mode.RUNNING and not ctl.returning

    def _ekf_refused(self) -> int | None:
        """The EKF's count of fixes it refused so far; None when the position source takes
        every fix (raw, Constellation, the EKF before its first fix)."""
        n = self.controller.telemetry.extra.get("ekf_gps_rejected")
        return n if isinstance(n, int) else None

    def _fence_before_fix(self, fix: GpsFix) -> tuple[str, float, str] | None:
        """Count the run of fixes outside the fence (``fix`` among them); the
        ``FENCE_FIXES_IN_ROW``-th is a breach before the fix can steer, whatever the EKF and
        the estimate say. Only usable fixes come here: one with HDOP 20 or more
        (``x6wd.nav.controller.MEANINGLESS_HDOP``) is no fix, neither counts nor ends a run.
        Returns the breach (reason, metres out, log detail)."""
        assert fix.lat_deg is not None and fix.lon_deg is not None
        d = self._outside_m(fix.lat_deg, fix.lon_deg)
        if d is None:
            self._fence_run = 0
            return None
        last_t = self._fence_run_t
        # in a row: no usable fix inside between them, none older than fix_stale_s before
        fresh = last_t is not None and fix.t_s - last_t <= self.safety.fix_stale_s
        self._fence_run = self._fence_run + 1 if fresh else 1
        self._fence_run_t = fix.t_s
        if d is None or not self._fence_armed():
            return None
        if self._fence_run >= FENCE_FIXES_IN_ROW:
            return "geofence breach", d, f", {self._fence_run} fixes in a row outside"
        if self._ekf_refused() is None:  # the source takes it: it will steer by it
            return "geofence breach", d, ""
        return None  # the EKF may refuse it: judged after the step

    def _fence_after_fix(self, fix: GpsFix, taken: bool | None) -> tuple[str, float, str] | None:
        """After ``fix`` stepped the controller (its motor commands not yet sent): a breach
        when the fix lies outside (a usable one: HDOP under 20) and the EKF took it
        (``taken``; None: a source that takes every fix, judged before the step), or when the
        estimate the controller now steers by lies outside."""
        if not self._fence_armed():
            return None
        assert fix.lat_deg is not None and fix.lon_deg is not None
        d = self._outside_m(fix.lat_deg, fix.lon_deg)
        if d is not None and taken:
            return "geofence breach", d, ""
        tel = self.controller.telemetry
        if tel.filt_lat_deg is None or tel.filt_lon_deg is None:
            return None
        d_est = self._outside_m(tel.filt_lat_deg, tel.filt_lon_deg)
        if d_est is None:
            return None
        return "geofence breach (estimated position)", d_est, ", the estimate after a fix"

    def _check_estimate(self, t_s: float) -> None:
        """Without a fresh usable fix (the latest fix record unusable, or the last usable one
        older than ``safety.fix_stale_s``), the position the controller steers by (the EKF
        dead-reckoning on its wheels) is checked against the geofence, at most every
        ``ESTIMATE_FENCE_PERIOD_S``. Called before an input steps the controller, on the
        estimate of its previous step, so that a breach stops the motors before the input
        can drive them (as a fix is checked before it steers)."""
        if (
            self.controller.mode != Mode.RUNNING
            or t_s - self._t_fence_est < ESTIMATE_FENCE_PERIOD_S
        ):
            return
        fix_t = self._last_pos_t
        if self._fix_usable and fix_t is not None and t_s - fix_t <= self.safety.fix_stale_s:
            return
        tel = self.controller.telemetry
        if tel.filt_lat_deg is None or tel.filt_lon_deg is None:
            return
        self._t_fence_est = t_s
        d = self._outside_m(tel.filt_lat_deg, tel.filt_lon_deg)
        if d is not None and self._fence_armed():
            self._breach("geofence breach (estimated position)", d, ", no fresh fix", t_s)

    def _breach(self, why: str, d_m: float, detail: str, t_s: float) -> None:
        """The robot is ``d_m`` (m) from the geofence centre, outside: the motors stop
        first, then the mission gets ``failsafe.geofence_action`` (pause, or return to
        launch; the operator may also drive back by hand: manual drive is bounded by its
        own dead-man). ``why``: the reason; ``detail``: what the log adds."""
        self.geofence_breaches += 1
        radius_m = self.safety.geofence_radius_m
        try:
            self._motors(MotorCommand(t_s, 0.0, 0.0, why))
        finally:  # a failing motor sink must not leave the mission running
            log.warning(
                "%s: %s m from the centre, limit %.12g m%s: failsafe %s",
                why,
                _metres_beyond(d_m, radius_m, 1),
                radius_m,
                detail,
                self.controller.failsafe_config.geofence_action,
            )
            self._handle(self.controller.geofence_breach(t_s, why))

    # -- outputs ------------------------------------------------------------------------------
    def _handle(self, outputs: list[Any], important: bool = True) -> None:
        """Route controller outputs. ``important`` (a fix or an operator request) forces the
        telemetry out; otherwise (compass samples, ticks) it is rate-limited for clients and
        the recorder, since the controller emits a snapshot on every input."""
        outputs = self._note_late_hold(outputs)
        changes: list[StateChange] = []
        for out in outputs:
            if type(out) is MotorCommand:
                if self._motors(out) is False:
                    # the motors refused it (a drive while an operator stop holds them): the
                    # recording shows what reached them, not what the controller decided
                    continue
                key = (out.left_pct, out.right_pct)
                if key != self._last_motor_rec:
                    self._last_motor_rec = key
                    self._record("record_motor", out)
            elif type(out) is Telemetry:
                self.last_telemetry = out
                untrusted = out.extra.get("compass_untrusted")
                if bool(untrusted) != self._compass_untrusted:  # its reader cannot see this
                    self._compass_untrusted = bool(untrusted)
                    if untrusted:
                        log.warning("compass untrusted: %s", untrusted)
                    else:
                        log.info("compass trusted again: the EKF takes its readings")
                self._watch_fix(out)
                self._watch_resets(out)
                if not self._odometry_warned and "odometry_warning" in out.extra:
                    self._odometry_warned = True  # once: the count in it keeps rising
                    log.warning("odometry: %s", out.extra["odometry_warning"])
                now = out.t_s
                force = important or bool(changes)
                if self._publish is not None and (
                    force or now - self._t_pub >= 1.0 / TELEMETRY_EVENT_HZ
                ):
                    self._t_pub = now
                    self._publish(
                        {"event": "telemetry", "data": out.to_dict(), "devices": self._devices()}
                    )
                if force or now - self._t_rec >= 1.0 / TELEMETRY_RECORD_HZ:
                    self._t_rec = now
                    self._record("record_telemetry", out)
            elif type(out) is StateChange:
                changes.append(out)
                # into a hold or a failsafe's pause: a fault, logged as one (the way back: info)
                fault = out.new == "HOLD" or out.reason.startswith("mode: failsafe")
                # a press's end names its last speeds: a change within a second of the one
                # before is only counted by the operator limiter (drive), never lost here
                last = ""
                if out.old == "MANUAL" and self._drive_pct is not None:
                    left, right = self._drive_pct
                    last = f" (last drive L{left:+.0f} R{right:+.0f})"
                log.log(
                    logging.WARNING if fault else logging.INFO,
                    "state %s -> %s %s%s",
                    out.old,
                    out.new,
                    out.reason,
                    last,
                )
                self._record("record_state", out)
                if self._publish is not None:
                    self._publish(
                        {"event": "state", "old": out.old, "new": out.new, "reason": out.reason}
                    )
        if self._on_state is not None:
            for change in changes:  # after the routing: the telemetry is the new one
                self._on_state(change)
        if self._observe is not None:
            self._observe(outputs, important)

    def _note_late_hold(self, outputs: list[Any]) -> list[Any]:
        """A hold on a stale sample that began while the control loop itself was late gets
        "(the control loop itself was X s late: CPU starved?)" in its state change's reason
        and, while it lasts, in telemetry's ``hold_reason``: the sample may be in the loop's
        queue, its sensor fine (outside audit: 21 such holds, each read as a compass fault).
        Judged when the hold begins."""
        tels = [o for o in outputs if type(o) is Telemetry]
        if not tels:
            return outputs
        hold = tels[-1].hold_reason
        if hold != self._raw_hold:
            self._raw_hold = hold
            self._hold_note = self._late_note(tels[-1])
        note = self._hold_note
        if not note:
            return outputs
        marked: list[Any] = []
        for out in outputs:
            if type(out) is Telemetry and out.hold_reason == hold:
                out = replace(out, hold_reason=hold + note)
            elif type(out) is StateChange and out.new == "HOLD" and out.reason == f"state: {hold}":
                out = replace(out, reason=out.reason + note)
            marked.append(out)
        return marked

    def _late_note(self, tel: Telemetry) -> str:
        """The note for a hold beginning in ``tel`` ("": none). Only for a stale sample, and
        only when the loop was late by more than a tick period and by at least the sample's
        excess over its limit (``safety.attitude_stale_s`` or ``fix_stale_s``): when the
        tick was due the sample was still fresh, so the hold became due while the loop
        stood still. A sensor already stale then is left to its own reason."""
        kind = _STALE_HOLDS.get(tel.hold_reason)
        period_s = self.loop.period_s
        if kind is None or period_s is None:
            return ""
        if kind == "attitude":
            age_s, limit_s = tel.attitude_age_s, self.safety.attitude_stale_s
        else:
            age_s, limit_s = tel.fix_age_s, self.safety.fix_stale_s
        late_s = self._tick_late_s
        if late_s is None:  # decided on an input between ticks: how overdue the next one is
            late_s = self.loop.overdue_s(self.clock())
        if age_s is None or late_s <= period_s or late_s < age_s - limit_s:
            return ""
        self.loop.late_holds += 1
        return f" (the control loop itself was {late_s:.2f} s late: CPU starved?)"

    def _watch_resets(self, tel: Telemetry) -> None:
        """Log each EKF reset with how far it moved and why (the EKF's reason: fixes it had
        refused until they agreed, or fixes that moved while the wheels stood still): a
        warning from ``gps_jump_m`` on (the jump failsafe's size, also while no mission
        runs), else info."""
        resets = tel.extra.get("ekf_gps_resets")
        if not isinstance(resets, int) or resets <= self._resets_seen:
            return
        self._resets_seen = resets
        jump_m = float(tel.extra.get("ekf_last_reset_m") or 0.0)
        limit_m = self.controller.failsafe_config.gps_jump_m
        warn = 0 < limit_m <= jump_m
        if tel.extra.get("ekf_last_reset_reason") == "bias":
            to = "to fixes that moved while the wheels stood still (carried or pushed?)"
        else:
            to = "to fixes it had refused until they agreed"
            expected_m = float(tel.extra.get("ekf_last_reset_expected_m") or 0.0)
            if 0 < jump_m <= expected_m:  # the jump failsafe leaves it (Jump.surprise)
                to += (
                    f", inside its own 99 % ellipse ({expected_m:.0f} m: poor geometry made"
                    " it that uncertain)"
                )
            elif not warn and jump_m >= SURPRISE_WARN_OF_JUMP * limit_m > 0:
                # under the jump failsafe, but the estimate was far wrong while sure of
                # itself: said (an audit: a compass 12 uT off its calibration took the robot
                # 20 m off its route on good fixes, and only an INFO line told)
                warn = True
                self.surprise_resets_m.append(jump_m)
                to += (
                    ", beyond its own 99 % ellipse: the heading or the wheels led it astray"
                    " (a compass off its calibration? wheels slipping?) or the fixes jumped"
                )
        log.log(
            logging.WARNING if warn else logging.INFO,
            "gps: the estimate moved %.1f m %s (EKF reset %d)",
            jump_m,
            to,
            resets,
        )

    def _watch_fix(self, tel: Telemetry) -> None:
        """Log a spell without a valid fix once, as a warning, after ``fix_stale_s`` (the
        receiver may talk on, its link healthy, and report no position: searching, the sky
        blocked; or the line delivers nothing decodable, which :meth:`gps_line_quiet` names
        before the reader's own ``gps.stale_s`` may have run out), and its end: the robot
        holds or dead-reckons meanwhile, which the state changes say, but not outside a
        mission."""
        age_s = tel.fix_age_s
        if age_s is not None and age_s <= self.safety.fix_stale_s:
            if self._no_fix_warned and self._no_fix_since is not None:
                log.info("gps: valid fix again after %.1f s without", tel.t_s - self._no_fix_since)
            self._no_fix_since, self._no_fix_warned = None, False
            return
        if self._no_fix_since is None:
            self._no_fix_since = tel.t_s if age_s is None else tel.t_s - age_s
        # before the first fix a receiver is searching: a cold start takes up to a minute
        limit_s = self.safety.fix_stale_s if age_s is not None else FIRST_FIX_GRACE_S
        if not self._no_fix_warned and tel.t_s - self._no_fix_since > limit_s:
            self._no_fix_warned = True
            hdop = self._fix_hdop_refused
            why = self.gps_line_quiet(tel.t_s) or (
                "the receiver reports no position: searching, or the sky blocked"
                if hdop is None
                else f"the receiver's fixes have HDOP {hdop:.1f}: from {MEANINGLESS_HDOP:g} on"
                " a position means nothing (street canyon, few satellites)"
            )
            log.warning(
                "gps: no valid fix for %.1f s%s (%s)",
                tel.t_s - self._no_fix_since,
                " since start-up" if age_s is None else "",
                why,
            )


GPS_QUIET_OF_FIX_STALE = 0.6
"""No GPS record (a checksum-valid sentence, a fix, a sky report) for longer than this
fraction of ``safety.fix_stale_s`` (1.5 s of the default 2.5 s): the line delivers nothing
decodable (silent, the wrong baud, every checksum wrong). A receiver talks at every epoch,
with a fix or without, and ``fix_stale_s`` spans at least 2.5 epochs (the configuration
checks it against ``gps.rate_hz``), so one talking waits at most 0.4 of it. An outside audit:
a silent line was first reported as "searching, or the sky blocked", for up to 0.5 s before
the reader's own ``gps.stale_s`` ran out."""

FIRST_FIX_GRACE_S = 60.0
"""No valid fix since start-up is a warning only after this (s): a receiver's cold start
(the NEO-5's datasheet: 29 s; longer under trees) is no fault."""


async def every(period_s: float, clock: Clock, step: Callable[[float], None]) -> None:
    """Call ``step(now_s)`` every ``period_s`` (s) on the running event loop, on a fixed
    schedule; after a stall longer than a period (suspend, a slow callback) it starts afresh
    instead of bursting to catch up. During ``step`` the time it was due and the period are
    in ``_TICK_DUE`` (the runner's tick measures its lateness with them)."""
    t_next = clock()
    while True:
        due = _TICK_DUE.set((t_next, period_s))  # how late this step starts: see Runner.tick
        try:
            step(clock())
        finally:
            _TICK_DUE.reset(due)
        t_next += period_s
        delay_s = t_next - clock()
        if delay_s < -period_s:
            t_next = clock()
            delay_s = 0.0
        await asyncio.sleep(max(0.0, delay_s))


async def run_realtime(
    runner: Runner,
    stop: asyncio.Event,
    *,
    tick_hz: float,
    tasks: Sequence[Callable[[], Coroutine[Any, Any, None]]] = (),
) -> None:
    """The real-time edge of the loop: tick ``runner`` at ``tick_hz`` (Hz) and run the extra
    ``tasks`` in one TaskGroup until ``stop`` is set. Device inputs reach the runner from the
    edge's own threads through ``loop.call_soon_threadsafe``; an exception in any task ends
    the group and propagates (the daemon then stops the motors and exits non-zero)."""

    async def until_stop() -> None:
        await stop.wait()
        raise _Stopped

    try:
        async with asyncio.TaskGroup() as group:
            group.create_task(every(1.0 / tick_hz, runner.clock, runner.tick), name="x6wd-tick")
            for make in tasks:
                group.create_task(make())
            group.create_task(until_stop(), name="x6wd-stop")
    except* _Stopped:
        pass


class _Stopped(Exception):
    """Ends :func:`run_realtime`'s task group when its stop event is set."""
