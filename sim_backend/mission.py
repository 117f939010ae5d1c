"""The robot engine of ``x6wd sim``: a whole mission in simulated time, through the real decoders
(:mod:`sim_backend.cli` picks it for every scenario with waypoints; a static survey runs on the
receiver engine, :mod:`sim_backend.survey`, unless ``--engine robot``).

This is the fast-time edge of the one loop (:class:`x6wd.loop.runner.Runner`, the object the
daemon drives in real time): the simulator steps its world at the compass rate (20 Hz by
default; on a mission a whole multiple of it of at least 20 Hz, the daemon's tick, the
compass read at its own rate: :func:`sim_backend.runs.robot_clock`) in simulated seconds
and hands the runner what the devices would::

    vehicle (skid steer) ──> compass register map ──> drivers.cmps10 ──> Runner.attitude
         │                                                                  │
         └─> SimReceiver.epoch (each GPS epoch) ──> NEO-5 bytes ──> MemoryUart │
                 ──> drivers.gps_nmea.GpsDecoder ──> Runner.gps_record
    Runner ──> Controller ──> MotorCommand ──> vehicle; telemetry, states ──> recorder

As an operator does, the mission is loaded (through the runner's geofence check) and
started at the first valid fix; the runner's continuous geofence, manual-drive limit and
routing rules are the robot's own, so a fast-time run exercises them.

The receiver is :func:`sim_backend.receiver.build_receiver`'s, the one HIL and the gap tool
build too (model, error layers, NMEA, UART timing).

The decoded fix is stamped with the time its burst finished on the wire at the scenario's baud
rate, so the controller sees the receiver's real latency. Nothing reads a wall clock except the
progress display and the wall-time figure; the outputs depend only on the scenario and the seed.

Outputs in ``--out DIR``: ``recording.jsonl`` (the :mod:`x6wd.core.recorder` format, ``t_mono`` =
simulated seconds, ``t_utc`` = scenario UTC), ``gps.nmea`` (every byte the receiver emitted),
``truth.csv`` (t_s, lat, lon, alt, heading_deg at each physics step), ``summary.json`` and
``track.png``.

A scenario without waypoints is a static survey: the robot stands for ``duration_s`` (on
this engine its whole loop runs, at about 1/20 of the receiver engine's speed) and the
summary's dispersion figures are the paper's Table 2 quantities (half the spread of the raw
readings, latitude and longitude each converted with the paper's two radii, so longitude is
stretched by 1/cos φ as in the paper).

Scenario-specific settings read here (``[compass]`` is a plain table; keys):
``declination_deg`` (site declination, also given to the controller unless
``robot_declination_deg`` says what the robot believes), ``horizontal_ut``, ``vertical_ut``,
``hard_iron_ut`` [x, y, z], ``soft_iron`` 3x3, ``noise_ut``, ``lag_tau_s``, ``rate_hz``
(default 20), ``p_error`` (I2C error probability per transaction).

Every ``[[effects]]`` layer (e.g. the gap tool's ``effects.toml``) acts in the closed loop:
the GPS ones inside the receiver, each epoch, the one way layers run
(:meth:`sim_backend.effects.GpsLayer.start`: latency moves the position the receiver model
solves for, the multipath zone is evaluated at the true position, quantisation rounds the
reported minutes), the compass ones on the emulation's own physics (:func:`compass_setup`,
each layer's :meth:`~sim_backend.effects.CompassLayer.act_on`). HIL shares both.

How the paper's four situations are configured (config/scenarios) and what came out:
docs/simulator.md, "The paper's four situations".
"""

from __future__ import annotations

import contextlib
import csv
import json
import logging
import math
import time
from array import array
from collections import Counter, deque
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any, BinaryIO, cast

import numpy as np

from drivers.cmps10 import Cmps10
from drivers.gps_nmea import GpsDecoder
from sim_backend.compass import (
    CompassErrors,
    CompassSetup,
    ErrorInjector,
    MagneticField,
    SimCmps10,
)
from sim_backend.effects import (
    CompassPhysics,
    wrap180,
)
from sim_backend.geodesy import EnuFrame, enu_to_lla, lla_to_enu
from sim_backend.odometry import EncoderSim, encoder_rng
from sim_backend.ports import MemoryUart
from sim_backend.receiver import SimRandom, build_receiver
from sim_backend.runs import (  # re-exported: the robot engine's callers import them here
    STATIC_CHUNK_EPOCHS,
    ErrorStats,
    RunPlan,
    Summary,
    dispersion_m,
    plot_track,
    sky_warnings,
    straight_length_m,
    vehicle_from_world,
)
from sim_backend.survey import SIM_OUTPUTS
from sim_backend.world import World
from x6wd.core.config import check_drive_vs_stuck
from x6wd.core.errors import CommandError
from x6wd.core.mission_files import Waypoint
from x6wd.core.outdir import open_output, output_dir, output_file
from x6wd.core.recorder import Recorder
from x6wd.core.records import GpsFix, Mode, NavState, StateChange, Telemetry
from x6wd.loop.runner import Runner
from x6wd.nav.controller import (
    RETURN_STOP_REASON,
    CommandRejected,
    Controller,
    has_usable_position,
)

DONE_TAIL_S = 2.0  # keep simulating this long after MISSION_DONE (the robot settles)
STARTUP_HOLD = "position estimate not ready"
"""The controller's hold reason between the mission's start and its first decision, while
its estimator takes its first fix and compass sample (about one tick): the run's start-up
wait, reported apart from the holds (``extra["startup_wait_s"]``), not as one of them."""
RECORDER_BUFFER_BYTES = 1 << 20
"""The recording is written through a buffer this big: fast time needs no crash durability,
and one ``write()`` per record was a visible share of a run."""


class _StartupHoldHeld(logging.Filter):
    """The robot's "state IDLE -> HOLD state: position estimate not ready" held back while it
    is the start-up wait (every ``x6wd sim`` mission printed it on stderr, README's first
    command included, for a wait its summary says is not a hold). :meth:`release` logs it
    after all when the run counts that wait as a hold (no estimate came, or a fault began
    in it), so a real fault is never hidden."""

    def __init__(self) -> None:
        super().__init__()
        self.held: logging.LogRecord | None = None
        self.done = False  # only the first navigation state change can be the start-up wait

    def filter(self, record: logging.LogRecord) -> bool:
        """False (not logged, kept) for the first state change if it is the start-up hold."""
        args = record.args if isinstance(record.args, tuple) else ()
        if (
            self.held is not None
            and record.msg == "state %s -> %s %s%s"
            and args[:2]
            == (
                NavState.HOLD,
                NavState.HOLD,
            )
        ):
            # the wait turned into another hold (a wait for the sky): it counts as a hold,
            # said now, before the change that follows it
            self.release(logging.getLogger(record.name))
        # a navigation state's change ("state: ..."), not the mode's ("mode: start")
        if (
            self.done
            or record.msg != "state %s -> %s %s%s"
            or not str(args[2]).startswith("state: ")
        ):
            return True
        self.done = True
        if args[1:3] == (NavState.HOLD, f"state: {STARTUP_HOLD}"):
            self.held = record
            return False
        return True

    def release(self, logger: logging.Logger) -> None:
        """Log the held record through ``logger``'s handlers (the run counted it a hold)."""
        if self.held is not None:
            record, self.held = self.held, None
            logger.handle(record)


def _doubles() -> array[float]:
    return array("d")


def _ints() -> array[int]:
    return array("q")


def _col(a: array[Any], dtype: Any = float) -> np.ndarray:
    """A packed column as a numpy array: a view of its buffer, no copy (the column cannot
    grow while the view lives)."""
    return np.frombuffer(a, dtype=dtype)


@dataclass
class _Trace:
    """What the loop keeps for the figures and files, all in packed columns (8 bytes a
    value, not a 32-byte float object, its pointer and a tuple or a dict entry around it).

    Per tick (the loop's clock): t, east, north, up, heading; a 10 h mission at 60 Hz keeps
    2.2 million of each. Per GPS epoch ``i`` (tick ``i * gps_every``): the true antenna's
    east/north (m) and lat/lon (deg). Per valid fix: its epoch tick, the raw lat/lon and the
    filtered lat/lon (deg; NaN for both when the robot had no filtered position), then
    HDOP and satellites used of the fixes that give them."""

    t: array[float] = field(default_factory=_doubles)
    east: array[float] = field(default_factory=_doubles)
    north: array[float] = field(default_factory=_doubles)
    up: array[float] = field(default_factory=_doubles)
    heading: array[float] = field(default_factory=_doubles)
    gps_every: int = 1
    epoch_east: array[float] = field(default_factory=_doubles)
    epoch_north: array[float] = field(default_factory=_doubles)
    epoch_lat: array[float] = field(default_factory=_doubles)
    epoch_lon: array[float] = field(default_factory=_doubles)
    fix_tick: array[int] = field(default_factory=_ints)
    fix_lat: array[float] = field(default_factory=_doubles)
    fix_lon: array[float] = field(default_factory=_doubles)
    filt_lat: array[float] = field(default_factory=_doubles)
    filt_lon: array[float] = field(default_factory=_doubles)
    fixes: int = 0
    fixes_valid: int = 0
    hdop: array[float] = field(default_factory=_doubles)
    sats: array[int] = field(default_factory=_ints)

    def add_epoch(self, tick: int, east_m: float, north_m: float, lat: float, lon: float) -> None:
        """The true antenna at the GPS epoch of ``tick`` (epochs come in order, one each
        ``gps_every`` ticks from tick 0)."""
        if tick != len(self.epoch_east) * self.gps_every:
            raise ValueError(f"GPS epoch at tick {tick} out of order")
        self.epoch_east.append(east_m)
        self.epoch_north.append(north_m)
        self.epoch_lat.append(lat)
        self.epoch_lon.append(lon)

    def epoch_en(self, tick: int) -> tuple[float, float]:
        """The true antenna's east/north (m) at the GPS epoch of ``tick``."""
        i = tick // self.gps_every
        return self.epoch_east[i], self.epoch_north[i]

    def fix_truth(self, lat_lon: bool = False) -> np.ndarray:
        """(n, 2): the truth at each valid fix's epoch, east/north (m) or lat/lon (deg)."""
        i = _col(self.fix_tick, np.int64) // self.gps_every
        a, b = (self.epoch_lat, self.epoch_lon) if lat_lon else (self.epoch_east, self.epoch_north)
        return np.column_stack([_col(a)[i], _col(b)[i]])

    def fix_latlon(self, filtered: bool = False) -> np.ndarray:
        """(n, 2) lat/lon (deg) of the valid fixes, raw or filtered (NaN: none)."""
        a, b = (self.filt_lat, self.filt_lon) if filtered else (self.fix_lat, self.fix_lon)
        return np.column_stack([_col(a), _col(b)])


def run_mission(
    world: World,
    out_dir: str | Path | None,
    seed: int | None = None,
    duration_s: float | None = None,
    progress: Callable[[float, float], None] | None = None,
    operator: Callable[[float, Runner], None] | None = None,
) -> Summary:
    """Run ``world``'s mission in simulated time and write the output files into ``out_dir``
    (None: no files, only the returned :class:`Summary`, whose figures are the same; a sweep
    cell keeps nothing else, and the recording, NMEA, truth and plot were a third of a
    short mission's time).

    ``seed`` overrides the scenario's seed, ``duration_s`` its duration (s, simulated); the run
    ends ``DONE_TAIL_S`` after the mission completes, at the tick the robot rejects the
    mission (``extra["mission_rejected"]`` says why, ``extra["mission_rejected_at_s"]``
    when: nothing would happen after it), or at the duration. ``progress(t_s,
    total_s)`` is called now and then. Same scenario + seed -> identical files (except
    ``summary.json``'s wall-time figure).

    ``operator(t_s, runner)`` scripts an operator: it is called once per simulation tick
    (the loop's clock), right after the runner's tick at simulated time ``t_s`` (s), with the
    run's :class:`~x6wd.loop.runner.Runner`, whose clock then reads ``t_s``. It may make any
    operator request there (``runner.command("return")``, ``"pause"``, ``"resume"``,
    ``runner.operator_seen()``, ``runner.stop()``, ...) exactly as the daemon's control
    port would; what they cause is recorded like everything else. A rejected request raises
    from the hook (``CommandError``, ``CommandRejected``) and ends the run: catch it there to
    go on. None (default): no operator after the automatic load and start at the first fix.
    """
    # the robot as it will drive (scenario and robot config merged): a drive that cannot move
    # it, or that the stuck failsafe cannot watch, is refused before anything runs
    check_drive_vs_stuck(world.navigation, world.failsafe)
    wall0 = time.perf_counter()
    cset, compass_skipped = compass_setup(world)
    plan = RunPlan.of(world, seed, duration_s, cset.rate_hz)
    seed, total_s, dt, gps_every, n_ticks = (
        plan.seed,
        plan.total_s,
        plan.dt_s,
        plan.gps_every,
        plan.n_ticks,
    )
    compass_every = plan.compass_every  # ticks per compass reading (1 at 20 Hz and up)
    out = output_dir(out_dir, clear=SIM_OUTPUTS) if out_dir is not None else None
    rand = SimRandom.from_seed(seed)
    receiver = build_receiver(world, rand)
    uart = MemoryUart(receiver.baud)
    decoder = GpsDecoder(emit_sentences=False)
    injector = ErrorInjector(p_error=cset.p_error, rng=rand.i2c if cset.p_error > 0 else None)
    device = SimCmps10(
        field_model=cset.field_model,
        errors=cset.errors,
        injector=injector,
        rng=rand.compass if cset.errors.noise_ut > 0 else None,
    )
    compass = Cmps10(device, sleep=lambda _s: None, retry_delay_s=0.0)
    ctrl = Controller(
        world.navigation,
        world.safety,
        cset.robot_declination_deg,
        odometry=world.odometry,
        gnss_noise=world.gnss_noise,
        failsafe=world.failsafe,
    )
    vehicle = vehicle_from_world(world)
    # The motor board's encoders, read every tick (at 20 Hz or more on a mission, as the
    # daemon polls them).
    encoders = EncoderSim(world.encoders, rng=encoder_rng(seed), start=vehicle.state)
    origin = world.origin
    antenna_m = world.vehicle.antenna_height_m
    waypoints = [Waypoint(float(a), float(b)) for a, b in world.waypoints_latlon()]
    wp_enu = world.waypoints_enu_m()

    utc0 = world.start_utc
    now = [0.0]
    trace = _Trace(gps_every=gps_every)
    holds: list[list[float]] = []  # [start, end]
    # The start-up wait: the first hold, if it began before any decision drove, for
    # STARTUP_HOLD, and every telemetry in it said only that (a fix lost or a compass gone
    # meanwhile makes it a hold like any other); "ended" once the robot drove out of it.
    startup: dict[str, Any] = {"index": None, "clean": True, "drove": False, "ended": False}
    done_at: float | None = None

    nmea_file: BinaryIO | _NoFiles = _NoFiles()
    rec: Recorder | _NoFiles = _NoFiles()
    if out is not None:
        nmea_file = open_output(out / "gps.nmea")  # closed after the run, or on its error
    # The recorder writes aware times as naive UTC; handing it naive UTC already skips a
    # conversion per record (thousands per mission) and gives the same text.
    utc0_naive = utc0.astimezone(UTC).replace(tzinfo=None) if utc0.tzinfo else utc0
    # One datetime per simulated instant: the recorder formats the same object only once
    # (a tick writes several records at the same time).
    utc_memo: list[Any] = [math.nan, utc0_naive]

    def utc_clock() -> datetime:
        t = now[0]
        if t != utc_memo[0]:
            utc_memo[0], utc_memo[1] = t, utc0_naive + timedelta(seconds=t)
        dt: datetime = utc_memo[1]
        return dt

    if out is not None:
        rec = Recorder(
            out / "recording.jsonl",
            clock=lambda: now[0],
            utc_clock=utc_clock,
            buffer_bytes=RECORDER_BUFFER_BYTES,
        )

    arrivals: list[dict[str, Any]] = []
    last_fix: list[tuple[GpsFix, int] | None] = [None]  # latest usable fix, its epoch tick
    # Sentences the receiver's UART dropped, per type ("GSV": n), and the decoded fixes' delay
    # after their epoch (s): sum, max, count.
    uart_dropped: Counter[str] = Counter()
    fix_delay_s = [0.0, 0.0, 0]

    def note_arrival(t_s: float) -> None:
        # the true position against the waypoint just reached, and the GPS's own error at that
        # moment (the latest fix against the truth at its epoch)
        idx = len(arrivals)
        if idx >= len(wp_enu):
            return
        s = vehicle.state
        wp_e, wp_n = float(wp_enu[idx][0]), float(wp_enu[idx][1])
        row: dict[str, Any] = {
            "index": idx,
            "t_s": round(t_s, 3),
            "true_error_m": math.hypot(s.east_m - wp_e, s.north_m - wp_n),
        }
        latest = last_fix[0]
        if latest is not None:
            fx, tick = latest
            assert fx.lat_deg is not None and fx.lon_deg is not None
            te, tn = trace.epoch_en(tick)
            fe, fn, _ = lla_to_enu(
                fx.lat_deg, fx.lon_deg, origin.alt_m, origin.lat_deg, origin.lon_deg, origin.alt_m
            )
            row["gps_error_m"] = math.hypot(float(fe) - te, float(fn) - tn)
        arrivals.append(row)

    returned: list[float] = []  # when a return to launch began (the mission is then over)
    failsafes: list[list[Any]] = []  # [t_s, why] of each failsafe that acted
    # [start, end, why] of each time the mission stood paused (a failsafe's pause, an
    # operator's): the robot stands still there, in IDLE, which HOLD periods do not count
    pauses: list[list[Any]] = []

    def observe(outputs: list[Any], _important: bool) -> None:
        nonlocal done_at
        for o in outputs:
            kind = type(o)
            if kind is Telemetry:
                if not returned and ctrl.mode != Mode.IDLE:
                    while len(arrivals) < min(ctrl.navigator.index, len(wp_enu)):
                        note_arrival(o.t_s)
                if (
                    o.state == NavState.HOLD
                    and startup["index"] is not None
                    and startup["index"] == len(holds) - 1
                    and holds[-1][1] < 0
                    and o.hold_reason != STARTUP_HOLD
                ):
                    startup["clean"] = False
                if o.state == NavState.MISSION_DONE and done_at is None:
                    done_at = o.t_s
            elif kind is StateChange:
                t = o.t_s
                if o.reason.endswith("return to launch"):
                    returned.append(t)
                if o.reason.startswith("mode: failsafe: "):
                    why = o.reason[len("mode: failsafe: ") :].removesuffix(": return to launch")
                    failsafes.append([round(t, 3), why])
                if o.new == Mode.PAUSED and (not pauses or pauses[-1][1] >= 0):
                    why = o.reason.removeprefix("mode: ").removeprefix("failsafe: ")
                    pauses.append([t, -1.0, why])
                elif o.old == Mode.PAUSED and o.new != Mode.PAUSED and pauses and pauses[-1][1] < 0:
                    pauses[-1][1] = t
                state_change = o.reason.startswith("state: ")
                drives = state_change and o.new not in (NavState.HOLD, NavState.IDLE)
                # a return's designed stop (RETURN_STOP_S) is not a hold for a sensor
                return_stop = o.reason.endswith(RETURN_STOP_REASON)
                if o.new == NavState.HOLD and not return_stop and (not holds or holds[-1][1] >= 0):
                    if not holds and not startup["drove"] and o.reason == f"state: {STARTUP_HOLD}":
                        startup["index"] = 0
                    holds.append([t, -1.0])
                elif o.old == NavState.HOLD != o.new and holds and holds[-1][1] < 0:
                    holds[-1][1] = t
                    if startup["index"] == len(holds) - 1:
                        startup["ended"] = drives
                if drives:
                    startup["drove"] = True
                if o.new == Mode.DONE and done_at is None:
                    done_at = t

    rec_methods: dict[str, Callable[[Any], None]] = {}

    def recorder_call(method: str, arg: Any) -> None:
        fn = rec_methods.get(method)
        if fn is None:
            fn = rec_methods[method] = getattr(rec, method)
        fn(arg)

    # The one loop (x6wd.loop.runner), driven in simulated time: the geofence, the
    # manual-drive limit and every routing rule are the robot's own.
    runner = Runner(
        ctrl,
        world.safety,
        lambda: now[0],
        motors=lambda cmd: vehicle.command(cmd.left_pct, cmd.right_pct),
        record=recorder_call if out is not None else None,
        observe=observe,
    )
    mission_state: dict[str, Any] = {"loaded": not waypoints, "rejected": None, "at": None}

    def load_at_first_fix(fix: GpsFix) -> None:
        # As an operator does: load the mission once the robot has a fix (the geofence is
        # centred on it unless configured) and start it.
        if mission_state["loaded"] or not has_usable_position(fix):
            return  # the runner centres the fence on a usable fix only (HDOP < 20)
        mission_state["loaded"] = True
        try:
            runner.load_mission(waypoints)
            runner.command("start")
        except (CommandError, CommandRejected) as exc:
            mission_state["rejected"] = f"{getattr(exc, 'code', 'rejected')}: {exc}"
            mission_state["at"] = fix.t_s
            rec.record_event("mission_rejected", fix.t_s, reason=str(exc))

    runner_log = logging.getLogger(Runner.__module__)  # the robot's state changes
    startup_log = _StartupHoldHeld()
    runner_log.addFilter(startup_log)
    try:
        rec.record_event("sim_start", 0.0, scenario=world.name, seed=seed, duration_s=total_s)
        banner = receiver.banner()
        nmea_file.write(banner)
        uart.write(banner)
        # it holds the receiver's UART first, as in HIL
        _count_dropped(uart_dropped, banner, receiver.arrivals(banner, 0.0))
        decoder.feed(uart.read_all(), 0.0)
        s0 = vehicle.state
        h0 = cset.device_heading_deg(s0.heading_deg, s0.pitch_deg, s0.roll_deg)
        device.set_state(0.0, h0, s0.pitch_deg, s0.roll_deg)
        runner.attitude(compass.read(0.0))
        report_every = max(1, n_ticks // 50)
        static_bursts: Callable[[int], bytes] | None = None
        if not waypoints:
            # Nothing will move the robot: the survey's epochs in vectorised receiver calls
            # (same physics as step by step, much faster with walls), their NMEA text
            # formatted per call too, STATIC_CHUNK_EPOCHS at a time.
            s0 = vehicle.state
            pos0 = np.array([s0.east_m, s0.north_m, s0.up_m + antenna_m])
            static_bursts = _static_bursts(receiver, plan.epoch_times_s(), pos0)
        truth_lla: dict[tuple[float, float, float], tuple[float, float]] = {}
        frame = EnuFrame(origin.lat_deg, origin.lon_deg, origin.alt_m)  # truth per epoch
        # Sentences in flight on the UART: (time the last byte arrives, epoch tick, bytes).
        in_flight: deque[tuple[float, int, bytes]] = deque()

        def deliver(until_s: float) -> None:
            while in_flight and in_flight[0][0] <= until_s:
                t_rx, tick, line = in_flight.popleft()
                now[0] = t_rx
                uart.write(line)
                rec.record_nmea(line.rstrip(b"\r\n"), t_rx)
                for r in decoder.feed(uart.read_all(), t_rx):
                    if type(r) is GpsFix:
                        delay_s = t_rx - tick * dt
                        fix_delay_s[0] += delay_s
                        fix_delay_s[1] = max(fix_delay_s[1], delay_s)
                        fix_delay_s[2] += 1
                        if has_usable_position(r):
                            last_fix[0] = (r, tick)
                        runner.gps_record(r)
                        load_at_first_fix(r)
                        _note_fix(trace, tick, r, ctrl.telemetry)
                    else:
                        runner.gps_record(r)

        # the per-tick calls, looked up once (thousands of ticks per simulated minute)
        take_compass_events = compass.take_health_events
        t_append, e_append, n_append = trace.t.append, trace.east.append, trace.north.append
        u_append, h_append = trace.up.append, trace.heading.append
        for k in range(n_ticks + 1):
            t = k * dt
            deliver(t)
            now[0] = t
            s = vehicle.step(dt) if k else vehicle.state
            t_append(t)
            e_append(s.east_m)
            n_append(s.north_m)
            u_append(s.up_m)
            h_append(s.heading_deg)
            if receiver.tracks:
                # every physics step, so a delayed position interpolates the real path
                receiver.observe(t, (s.east_m, s.north_m, s.up_m + antenna_m), vehicle_velocity(s))
            if k % compass_every == 0:  # at the compass's rate (the loop's may be higher)
                device.set_state(
                    t, cset.device_heading_deg(s.heading_deg, s.pitch_deg, s.roll_deg),
                    s.pitch_deg, s.roll_deg,
                )  # fmt: skip
                runner.attitude(compass.read(t))
                events = take_compass_events()
                if events:  # the daemon's compass thread hands these over the same way
                    runner.device_events(events)
            if k:
                encoders.step(dt, s)
                runner.odometry(encoders.reading(t))
            runner.tick(t)
            if operator is not None:
                operator(t, runner)
            if k % gps_every == 0:
                antenna = (s.east_m, s.north_m, s.up_m + antenna_m)
                if static_bursts is not None:
                    burst = static_bursts(k // gps_every)
                else:
                    burst = receiver.nmea(receiver.epoch(t, antenna, vehicle_velocity(s)))
                nmea_file.write(burst)
                ll = truth_lla.get(antenna)
                if ll is None:  # a robot standing still asks for the same point each epoch
                    lat, lon, _alt = frame.to_lla(np.array(antenna))
                    if len(truth_lla) > 1000:
                        truth_lla.clear()
                    ll = truth_lla[antenna] = (float(lat), float(lon))
                trace.add_epoch(k, s.east_m, s.north_m, ll[0], ll[1])
                dropped_before = receiver.uart.dropped
                sent = receiver.arrivals(burst, t)
                for t_rx, line in sent:
                    in_flight.append((t_rx, k, line))
                if receiver.uart.dropped != dropped_before:
                    _count_dropped(uart_dropped, burst, sent)
            if progress is not None and k % report_every == 0:
                progress(t, total_s)
            if done_at is not None and t >= done_at + DONE_TAIL_S:
                break
            if mission_state["rejected"] is not None:
                break  # the robot refused the mission: it would stand idle to the end
        # The last burst is still on the wire: up to ~0.5 s after the last physics step at
        # 9600 baud, ~2 s at 4800. The robot reads its compass meanwhile, the world standing
        # at its last state, at the compass rate up to each line's arrival; without it the
        # decision on that fix found the attitude stale, and every run cut by its duration
        # ended in a HOLD "attitude stale", printed and recorded as a compass fault.
        heading_deg = cset.device_heading_deg(s.heading_deg, s.pitch_deg, s.roll_deg)
        t_read = float(trace.t[-1])
        dt_compass = dt * compass_every
        while in_flight:
            t_rx = in_flight[0][0]
            while t_read + dt_compass <= t_rx:
                t_read += dt_compass
                device.set_state(t_read, heading_deg, s.pitch_deg, s.roll_deg)
                runner.attitude(compass.read(t_read))
            deliver(t_rx)
        t_end = max(trace.t[-1], now[0])
        now[0] = t_end
        runner.tick(t_end)
        if holds and holds[-1][1] < 0:
            holds[-1][1] = t_end  # (a hold begun by the last burst's fix counts: see below)
        if pauses and pauses[-1][1] < 0:
            # where the run's time ends (sim_time_s, truth.csv's last row), not at the last
            # burst's arrival half a tick later: the robot stood still that long, no longer
            pauses[-1][1] = max(pauses[-1][0], float(trace.t[-1]))
        # the start-up wait is no hold (it was one in every run's summary); one the robot
        # never drove out of (the run ended in it) is
        startup_wait: list[float] | None = None
        i = startup["index"]
        if i is not None and startup["clean"] and startup["ended"]:
            startup_wait = holds.pop(i)
        runner_log.removeFilter(startup_log)
        if startup_wait is None:
            startup_log.release(runner_log)
        # a hold of no duration stopped nothing: the first decision's wait for the EKF's
        # first estimate, the closing tick's look at a compass sample not yet read
        holds[:] = [h for h in holds if h[1] > h[0]]
        rec.record_event("sim_end", t_end, completed=ctrl.mode == Mode.DONE and not returned)
        if progress is not None:
            progress(t_end, t_end)  # finished (early when the mission is done)
    except BaseException:  # the run's own error is reported, not a close's after it
        for close in (nmea_file.close, rec.close):
            with contextlib.suppress(Exception):
                close()
        raise
    finally:
        runner_log.removeFilter(startup_log)
    with contextlib.ExitStack() as closing:  # both closed; a close's error (a full disk) raised
        closing.callback(rec.close)
        closing.callback(nmea_file.close)

    if out is not None:
        with output_file(out / "truth.csv"):
            _write_truth(out / "truth.csv", world, trace, antenna_m)
    raw_err, filt_err, fix_enu, filt_enu = _errors(world, trace)
    path_len = _path_length_m(trace)
    straight = straight_length_m(world)  # leg by leg on the great circle
    disp_lat, disp_lon = _dispersion(trace)
    # a mission that returned to launch is not completed, whatever the controller's DONE
    completed = ctrl.mode == Mode.DONE and not returned
    summary = Summary(
        scenario=world.name,
        seed=seed,
        completed=completed,
        waypoints_reached=len(arrivals) if returned else _reached(ctrl, len(waypoints)),
        waypoint_count=len(waypoints),
        sim_time_s=float(trace.t[-1]),
        wall_time_s=time.perf_counter() - wall0,
        path_length_m=path_len,
        straight_length_m=straight,
        raw_error=ErrorStats.of(raw_err),
        filtered_error=ErrorStats.of(filt_err),
        hold_periods=len(holds),
        hold_time_s=float(sum(b - a for a, b in holds)),
        fixes=trace.fixes,
        fixes_valid=trace.fixes_valid,
        dispersion_lat_m=disp_lat,
        dispersion_lon_m=disp_lon,
        mean_hdop=float(np.mean(_col(trace.hdop))) if trace.hdop else math.nan,
        mean_sats_used=float(np.mean(_col(trace.sats, np.int64))) if trace.sats else math.nan,
        extra={
            "holds_s": [[round(a, 3), round(b, 3)] for a, b in holds],
            "startup_wait_s": (
                [round(startup_wait[0], 3), round(startup_wait[1], 3)]
                if startup_wait is not None and startup_wait[1] > startup_wait[0]
                else None
            ),
            "mission_rejected": mission_state["rejected"],
            "mission_rejected_at_s": mission_state["at"],
            "final_mode": str(ctrl.mode),
            "warnings": sky_warnings(world, total_s),
            "arrivals": _with_slow_error(arrivals, world, trace, dt),
            "returned_at_s": returned[0] if returned else None,
            "failsafes": failsafes,
            "paused_s": [[round(a, 3), round(b, 3), why] for a, b, why in pauses],
            "paused_time_s": round(float(sum(b - a for a, b, _why in pauses)), 3),
            "position_source": world.navigation.position_source,
            "geofence_breaches": runner.geofence_breaches,
            "ekf_surprise_resets_m": [round(m, 1) for m in runner.surprise_resets_m],
            "i2c_errors_injected": injector.injected,
            "compass_stale_events": compass.counters.stale_events,
            "nmea_bytes": uart.written,
            # what the receiver's UART could not carry (as a survey's), per sentence type, of
            # how many it was given; the decoded fixes' delay after their epoch (s); and the
            # valid fixes that came without their GGA (sentence dropped): those have no
            # satellite count and the HDOP of the last GSA received, which the mean figures hold
            "uart_dropped_sentences": receiver.uart.dropped,
            "uart_dropped_by_type": dict(uart_dropped.most_common()),
            "uart_sentences": receiver.uart.sent + receiver.uart.dropped,
            "fix_delay_s": {
                "mean": fix_delay_s[0] / fix_delay_s[2] if fix_delay_s[2] else None,
                "max": fix_delay_s[1] if fix_delay_s[2] else None,
            },
            "fixes_without_gga": trace.fixes_valid - len(trace.sats),
            "decoder": decoder.counters.as_dict(),
            "fidelity": world.gnss.fidelity,
            "effects_applied": [
                e["name"]
                for e in world.effects
                if not any(x.startswith(f"{e['name']}:") for x in compass_skipped)
            ],
            # Only layers the emulation genuinely cannot reproduce, each with the reason.
            "effects_skipped": list(compass_skipped),
        },
    )
    if out is not None:
        with output_file(out / "summary.json"):
            (out / "summary.json").write_text(json.dumps(summary.to_dict(), indent=2) + "\n")
        truth_e, truth_n = _col(trace.east), _col(trace.north)
        with output_file(out / "track.png"):
            plot_track(
                out / "track.png", world, truth_e, truth_n, fix_enu, filt_enu, wp_enu, summary
            )
    return summary


class _NoFiles:
    """Stands in for the NMEA file and the recorder of a run without files: takes every
    write and record and keeps nothing."""

    def _nothing(self, *_args: Any, **_kwargs: Any) -> None:
        return None

    write = close = record_event = record_nmea = _nothing


def _static_bursts(receiver: Any, t_s: np.ndarray, pos_enu_m: np.ndarray) -> Callable[[int], bytes]:
    """NMEA burst of epoch ``i`` (bytes) of a receiver standing at ``pos_enu_m`` (m, ENU) at
    times ``t_s`` (s): the receiver's epochs and their text are computed
    ``STATIC_CHUNK_EPOCHS`` at a time, when the first epoch of a chunk is asked for (epochs
    must be asked in order)."""
    chunk: dict[str, Any] = {"start": -1, "bursts": []}

    def burst(i: int) -> bytes:
        start = i - i % STATIC_CHUNK_EPOCHS
        if start != chunk["start"]:
            sl = slice(start, start + STATIC_CHUNK_EPOCHS)
            t = t_s[sl]
            n = t.shape[0]
            b = receiver.batch(t, np.tile(pos_enu_m, (n, 1)), np.zeros((n, 3)))
            chunk["start"], chunk["bursts"] = start, receiver.formatter.format_batch(b)
        bursts: list[bytes] = chunk["bursts"]
        return bursts[i - start]

    return burst


def compass_setup(
    world: World, sample_hz: float | None = None
) -> tuple[CompassSetup, tuple[str, ...]]:
    """The ``[compass]`` table with the scenario's compass ``[[effects]]`` mapped onto the
    emulation's own physics, so the registers the real driver reads carry them.

    ``sample_hz`` is the rate ``set_state`` is called at (default the table's ``rate_hz``;
    heading noise is scaled through the device's lag filter at that rate). Returns the setup
    and the layers not applied, as "name: reason" (none today: the list stays for layers
    added to :mod:`sim_backend.effects` later).
    Mapping (same meaning as :mod:`sim_backend.effects`, layers composed in scenario order
    on the body-frame field as an affine map field -> A field + b):

    - hard_iron (bx, by) is an offset in a field of ``horizontal_field_ut``; scaled to the
      emulation's horizontal intensity so the heading error vs heading curve is the layer's;
    - soft_iron (k, axis) is the symmetric matrix R(axis) diag(1+k, 1-k) R(axis)^T on x/y;
    - declination adds to the field's declination (the robot keeps believing the table's);
    - heading_lag adds its tau to the device's filter (a cascade of first-order lags has
      the sum of their delays at low frequency);
    - heading_noise becomes magnetometer noise whose heading effect after the device's
      filter has the layer's standard deviation per sample;
    - tilt (no partial-compensation model in the emulation) is applied in the heading
      domain by :meth:`CompassSetup.device_heading_deg`, before the device's physics.

    Declination rotates the Earth's field, so it acts before the iron whatever its place in
    the list; the other layers compose in list order. Each layer says how it acts
    (:meth:`sim_backend.effects.CompassLayer.act_on`).
    """
    cset = CompassSetup.from_table(world.compass)
    fm, errs = cset.field_model, cset.errors
    layers = [e for e in world.effect_objects() if e.kind == "compass"]
    if not layers:
        return cset, ()
    phys = CompassPhysics(
        horizontal_ut=fm.horizontal_ut,
        a=np.asarray(errs.soft_iron, dtype=float),
        b=np.asarray(errs.hard_iron_ut, dtype=float),
        declination_deg=fm.declination_deg,
        lag_tau_s=errs.lag_tau_s,
    )
    skipped: list[str] = []
    for eff in layers:  # every compass layer has a closed-loop model (an abstract method)
        phys = eff.act_on(phys)
    a_mat, b_vec, decl, tau = phys.a, phys.b, phys.declination_deg, phys.lag_tau_s
    noise_deg2 = phys.noise_deg2
    noise_ut = errs.noise_ut
    if noise_deg2 > 0:
        # White heading noise of variance v through y_k = y_{k-1} + g (x_k - y_{k-1}) keeps
        # g / (2 - g) of it; per-axis field noise sigma_ut gives heading noise sigma_ut / H rad.
        hz = cset.rate_hz if sample_hz is None else sample_hz
        g = 1.0 if tau == 0 else -math.expm1(-1.0 / (hz * tau))
        sigma_rad = math.radians(math.sqrt(noise_deg2)) / math.sqrt(g / (2.0 - g))
        noise_ut = math.hypot(noise_ut, sigma_rad * fm.horizontal_ut)
    errors = CompassErrors(
        hard_iron_ut=cast(tuple[float, float, float], tuple(float(x) for x in b_vec)),
        soft_iron=tuple(tuple(float(x) for x in row) for row in a_mat),
        noise_ut=noise_ut,
        lag_tau_s=tau,
    )
    field_model = MagneticField(fm.horizontal_ut, fm.vertical_ut, wrap180(np.array(decl)).item())
    setup = replace(cset, field_model=field_model, errors=errors, tilt=phys.tilt)
    return setup, tuple(skipped)


def vehicle_velocity(s: Any) -> tuple[float, float, float]:
    """East/north/up velocity (m/s) of a vehicle state (speed along the pitched heading)."""
    h = math.radians(s.heading_deg)
    p = math.radians(s.pitch_deg)
    hs = s.speed_mps * math.cos(p)
    return (hs * math.sin(h), hs * math.cos(h), s.speed_mps * math.sin(p))


def _reached(ctrl: Controller, count: int) -> int:
    """Waypoints reached: all once the mission is done, else the current target's index."""
    if ctrl.mode == Mode.DONE:
        return count
    idx = ctrl.telemetry.waypoint_index
    return 0 if idx is None else min(idx, count)


def _count_dropped(by_type: Counter[str], burst: bytes, sent: list[tuple[float, bytes]]) -> None:
    """Add to ``by_type`` the sentences of ``burst`` the UART did not carry (``sent``: the
    accepted ones, in order, as :meth:`~sim_backend.receiver.SimReceiver.arrivals` gives
    them), counted by type: ``GSV`` for ``$GPGSV``, a proprietary address whole."""
    by_type.update(_sentence_type(line) for line in burst.splitlines())
    by_type.subtract(_sentence_type(line) for _t, line in sent)
    for name in [n for n, c in by_type.items() if c <= 0]:
        del by_type[name]


def _sentence_type(line: bytes) -> str:
    address = line[1:].split(b",", 1)[0].decode("ascii", "replace")
    return address if address.startswith("P") else address[2:]


def _note_fix(trace: _Trace, tick: int, r: GpsFix, tel: Telemetry) -> None:
    trace.fixes += 1
    if r.valid and r.lat_deg is not None and r.lon_deg is not None:
        trace.fixes_valid += 1
        trace.fix_tick.append(tick)
        trace.fix_lat.append(r.lat_deg)
        trace.fix_lon.append(r.lon_deg)
        flat, flon = tel.filt_lat_deg, tel.filt_lon_deg
        if flat is None or flon is None:
            flat = flon = math.nan
        trace.filt_lat.append(flat)
        trace.filt_lon.append(flon)
        if r.hdop is not None:
            trace.hdop.append(r.hdop)
        if r.sats_used is not None:
            trace.sats.append(r.sats_used)


TRUTH_CHUNK_ROWS = 50_000
"""truth.csv is converted and written this many rows at a time (bounded memory)."""

PATH_CHUNK_TICKS = 1 << 16
"""The path length's per-tick steps are computed this many at a time (bounded temporaries)."""


def _path_length_m(trace: _Trace) -> float:
    """Length (m) of the true path, the sum of the horizontal steps between ticks.

    The same float as ``np.sum(np.hypot(np.diff(east), np.diff(north)))`` over the whole
    run: each step is the same elementwise operation whatever the chunk, and the steps are
    summed in one ``np.sum`` call (its pairwise summation over the whole array; summing
    chunk sums would change the last bits). The whole-run temporaries were two copies of
    the series, their two differences and the hypotenuses (40 bytes a tick); this keeps
    the steps (8) and one chunk's temporaries."""
    east, north = _col(trace.east), _col(trace.north)
    steps = np.empty(max(east.size - 1, 0))
    for a in range(0, steps.size, PATH_CHUNK_TICKS):
        b = min(a + PATH_CHUNK_TICKS, steps.size)
        np.hypot(np.diff(east[a : b + 1]), np.diff(north[a : b + 1]), out=steps[a:b])
    return float(np.sum(steps))


def _write_truth(path: Path, world: World, trace: _Trace, antenna_m: float) -> None:
    o = world.origin
    east, north, up = (np.frombuffer(a, dtype=float) for a in (trace.east, trace.north, trace.up))
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["t_s", "lat", "lon", "alt", "heading_deg"])
        for a in range(0, len(trace.t), TRUTH_CHUNK_ROWS):
            sl = slice(a, a + TRUTH_CHUNK_ROWS)
            enu = np.column_stack([east[sl], north[sl], up[sl] + antenna_m])
            lat, lon, alt = enu_to_lla(enu, o.lat_deg, o.lon_deg, o.alt_m)
            # Plain floats (tolist) format several times faster than numpy scalars.
            lats, lons, alts = (np.atleast_1d(v).tolist() for v in (lat, lon, alt))
            w.writerows(
                [f"{t:.3f}", f"{la:.9f}", f"{lo:.9f}", f"{al:.3f}", f"{h:.3f}"]
                for t, la, lo, al, h in zip(
                    trace.t[sl], lats, lons, alts, trace.heading[sl], strict=True
                )
            )


def _errors(world: World, trace: _Trace) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Horizontal errors (m) of raw and filtered fixes against the truth at their epoch."""
    if not trace.fix_tick:
        empty = np.zeros((0, 2))
        return np.zeros(0), np.zeros(0), empty, empty
    o = world.origin
    truth = trace.fix_truth()
    raw = trace.fix_latlon()
    filt = trace.fix_latlon(filtered=True)
    z = np.full(len(raw), o.alt_m)
    raw_enu = np.asarray(lla_to_enu(raw[:, 0], raw[:, 1], z, o.lat_deg, o.lon_deg, o.alt_m))
    filt_enu = np.asarray(lla_to_enu(filt[:, 0], filt[:, 1], z, o.lat_deg, o.lon_deg, o.alt_m))
    raw_err = np.hypot(raw_enu[:, 0] - truth[:, 0], raw_enu[:, 1] - truth[:, 1])
    filt_err = np.hypot(filt_enu[:, 0] - truth[:, 0], filt_enu[:, 1] - truth[:, 1])
    return raw_err, filt_err, raw_enu[:, :2], filt_enu[:, :2]


SLOW_ERROR_WINDOW_S = 5.0
"""Half-width of the window (s) whose mean fix error is the GPS's slow error at an arrival."""


def _with_slow_error(
    arrivals: list[dict[str, Any]], world: World, trace: _Trace, dt_s: float
) -> list[dict[str, Any]]:
    """Each arrival with ``gps_slow_error_m``: the length of the mean fix-error vector (fix
    minus truth at its epoch, m) over the fixes within ±``SLOW_ERROR_WINDOW_S`` of the
    arrival. The white part of the error averages out, the slow part (what no navigation can
    see without a reference) remains: the floor of the true arrival error."""
    if not arrivals or not trace.fix_tick:
        return arrivals
    o = world.origin
    t_ep = _col(trace.fix_tick, np.int64) * dt_s
    truth = trace.fix_truth()
    raw = trace.fix_latlon()
    z = np.full(len(raw), o.alt_m)
    enu = np.asarray(lla_to_enu(raw[:, 0], raw[:, 1], z, o.lat_deg, o.lon_deg, o.alt_m))
    err = enu[:, :2] - truth
    for a in arrivals:
        near = np.abs(t_ep - a["t_s"]) <= SLOW_ERROR_WINDOW_S
        if near.any():
            a["gps_slow_error_m"] = float(np.hypot(*err[near].mean(axis=0)))
    return arrivals


def _dispersion(trace: _Trace) -> tuple[float, float]:
    """The paper's ± half spreads (m) of the raw readings' errors, two-radius converted.

    For a robot standing still (the paper's experiments) this is the spread of the readings
    themselves; for a moving one the truth is taken out first.
    """
    if not trace.fix_tick:
        return math.nan, math.nan
    truth = trace.fix_truth(lat_lon=True)
    dlat = _col(trace.fix_lat) - truth[:, 0]
    dlon = _col(trace.fix_lon) - truth[:, 1]
    return dispersion_m(dlat, dlon)
