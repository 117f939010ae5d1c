"""What both engines of ``x6wd sim`` share: a run's plan (seed, length, clock), the
scenario's vehicle at its start pose, the summary with its error statistics, and the track plot.

The robot engine (:mod:`sim_backend.mission`) runs the robot's whole loop; the receiver
engine (:mod:`sim_backend.survey`) runs a static survey on the receiver alone. Kept apart
from both so the receiver engine starts without importing the robot's code.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from datetime import timedelta
from pathlib import Path
from typing import Any

import numpy as np

from sim_backend.vehicle import Terrain, Vehicle, VehicleParams
from sim_backend.world import (
    DEFAULT_ALMANAC,
    DEFAULT_ALMANAC_DATE,
    MAX_DURATION_S,
    ROBOT_SECTIONS,
    World,
)
from x6wd.core.errors import ConfigError
from x6wd.core.geodesy import EARTH_MEAN_RADIUS_M
from x6wd.core.thinning import thinned_indices
from x6wd.nav.geo import R1_M, R2_M  # the paper's two radii (x = Λ·R1, y = Φ·R2)

ENGINES = ("auto", "robot", "receiver")
"""``x6wd sim --engine``: ``auto`` (default) runs a scenario without waypoints on the
receiver engine unless it sets what only the robot reads (:func:`robot_only_settings`), and
any other on the robot engine."""

ROBOT_ONLY_TABLES = (*ROBOT_SECTIONS, "encoders")
"""A scenario's tables (and ``--config``'s: :func:`sim_backend.world.with_robot_config` lays
its robot sections under the scenario's) of which the receiver engine reads no key: the
robot's configuration ([navigation], [safety], [failsafe], [odometry], [gnss_noise]) and the
simulated wheel encoders ([encoders]): that engine runs no robot. Not here: [compass] and
[vehicle], which every scenario sets and the receiver engine reads in part (its clock from
``compass.rate_hz``, the antenna's place from the vehicle's start pose and
``antenna_height_m``); their other keys act on a robot that moves or steers."""

MAX_NAMED = 6
"""At most this many settings are named in ``x6wd sim``'s engine note (then "and N more")."""


def robot_only_settings(world: World) -> list[str]:
    """What ``world`` sets that only the robot engine reads, by name, in file order: each key
    of its :data:`ROBOT_ONLY_TABLES` (``navigation.position_source``) and each compass
    ``[[effects]]`` layer (``effects[2] (compass_bias)``: no compass in the receiver engine).
    Empty for a survey the receiver engine runs in full."""
    names = [
        f"{sec}.{key}"
        for sec in ROBOT_ONLY_TABLES
        if isinstance(table := world.raw.get(sec), dict)
        for key in table
    ]
    names += [
        f"effects[{i}] ({layer.name})"
        for i, layer in enumerate(world.effect_objects())
        if layer.kind != "gps"
    ]
    return names


def engine_for(world: World, engine: str = "auto") -> str:
    """``"robot"`` or ``"receiver"``: the engine that runs ``world`` for the ``--engine``
    choice (``auto``: the receiver engine for a survey, a scenario without waypoints, unless
    it sets what only the robot reads, :func:`robot_only_settings`; the robot engine
    otherwise). ConfigError for ``receiver`` on a scenario with waypoints: that engine has no
    robot, so it would stand at the start and drop the mission without a word."""
    if engine not in ENGINES:
        raise ValueError(f"engine must be one of {', '.join(ENGINES)}, got {engine!r}")
    n_wp = len(world.waypoints_enu_m())
    if engine == "receiver" and n_wp:
        raise ConfigError(
            f"--engine receiver: the scenario has {n_wp} waypoint(s), and the receiver engine "
            "cannot drive a mission (it only runs a static survey): use --engine robot or auto"
        )
    if engine != "auto":
        return engine
    if n_wp:
        return "robot"
    return "robot" if robot_only_settings(world) else "receiver"


def _seconds(t_s: float) -> str:
    """A run's length (s) in words: whole seconds from 10 s, three digits under (a 0.5 s
    run is not "0 s")."""
    return f"{t_s:.0f}" if t_s >= 10.0 else f"{t_s:.3g}"


def _named(settings: list[str], scenario: World | None, robot_config: str | Path | None) -> str:
    """``settings`` (:func:`robot_only_settings` of a run's world) in words: the scenario's
    own by name (at most :data:`MAX_NAMED`), then what ``--config`` added, counted by
    table."""
    own = settings if scenario is None else robot_only_settings(scenario)
    added = [s for s in settings if s not in own]
    mine = [s for s in settings if s in own]
    parts = []
    if mine:
        more = len(mine) - MAX_NAMED
        parts.append(", ".join(mine[:MAX_NAMED]) + (f" and {more} more" if more > 0 else ""))
    if added:
        tables = ", ".join(dict.fromkeys(f"[{s.split('.')[0]}]" for s in added))
        keys = "key" if len(added) == 1 else "keys"
        parts.append(f"the {len(added)} {keys} of {tables} from --config {robot_config}")
    return " and ".join(parts)


def engine_note(
    world: World,
    engine: str = "auto",
    *,
    scenario: World | None = None,
    robot_config: str | Path | None = None,
) -> tuple[str, str] | None:
    """What ``x6wd sim`` says on stderr about its engine choice for ``world`` (the run's,
    ``--config`` laid under it) and ``--engine`` ``engine``: ``("note", text)`` when ``auto``
    picks the robot engine for a survey because of :func:`robot_only_settings`,
    ``("warning", text)`` when ``--engine receiver`` runs a survey that sets some (they are
    ignored), None otherwise. ``scenario`` (the world before ``--config``) and
    ``robot_config`` (the file) tell the scenario's settings from the file's."""
    if len(world.waypoints_enu_m()):
        return None
    settings = robot_only_settings(world)
    if not settings or engine == "robot":
        return None
    what = _named(settings, scenario, robot_config)
    them = "it" if len(settings) == 1 else "them"
    if engine == "receiver":
        source = world.navigation.position_source
        return (
            "warning",
            f"--engine receiver ignores {what}: only the robot engine reads {them}, and no "
            "robot runs here (no filtered row; --engine robot or auto runs "
            f"{_SOURCE_RUNS.get(source, source)})",
        )
    return (
        "note",
        f"the robot engine runs this survey: only the robot reads {what} (the receiver "
        f"engine, the default for a survey, would ignore {them}); --engine receiver runs "
        f"the receiver alone, about 20x faster, without {them}",
    )


_SOURCE_RUNS = {
    "ekf": "its EKF",
    "constellation": "its Constellation filter",
    "raw": "the robot on the latest fix, position_source raw",
}
"""The robot's position source (``navigation.position_source``) as ``x6wd sim`` names it."""


def check_mission_geofence(world: World) -> None:
    """Refuse, before a run, a mission the robot would refuse to load or start: a
    :class:`ConfigError` naming the waypoint's key (``mission.waypoints[i]``,
    ``mission.waypoints_enu[i]``, or the waypoint of ``mission.file``) and
    ``safety.geofence_radius_m`` when a waypoint lies farther than that from the geofence
    centre; with a configured ``safety.geofence_center``, also when the start position lies
    outside the fence.

    The centre is ``safety.geofence_center`` if configured, else the scenario's known start
    position (the truth): the robot centres its fence on its first fix, which is the start
    plus the GPS error, so a check on the fix would refuse a waypoint near the limit for
    some seeds and not others. Distances are the robot's own (great circle,
    :func:`x6wd.core.geodesy.great_circle_m`); NaN fails closed, as in the robot. A waypoint
    within the GPS error of the limit can still be refused by the robot at run time; the run
    then stops there (:func:`sim_backend.mission.run_mission`)."""
    from sim_backend.geodesy import enu_to_lla
    from x6wd.core.geodesy import great_circle_m

    ll = world.waypoints_latlon()
    if len(ll) == 0:
        return
    safety, o, v = world.safety, world.origin, world.vehicle
    radius_m = safety.geofence_radius_m
    lat0, lon0, _alt = enu_to_lla(
        np.array([v.start_east_m, v.start_north_m, 0.0]), o.lat_deg, o.lon_deg, o.alt_m
    )
    start = (float(lat0), float(lon0))
    where = f"{world.source}: " if world.source is not None else ""
    limit = f"safety.geofence_radius_m is {radius_m:g} m: the robot would refuse the mission"
    if len(safety.geofence_center) == 2:
        centre = (safety.geofence_center[0], safety.geofence_center[1])
        named = f"safety.geofence_center ({centre[0]:.7f}, {centre[1]:.7f})"
        d = great_circle_m(centre[0], centre[1], start[0], start[1])
        if not d <= radius_m:
            raise ConfigError(
                f"{where}vehicle.start_east_m/start_north_m: the start position "
                f"({start[0]:.7f}, {start[1]:.7f}) is {d:.0f} m from the geofence centre, "
                f"{named}; safety.geofence_radius_m is {radius_m:g} m: the robot would refuse "
                "to start the mission"
            )
    else:
        centre = start
        named = "the start position (no safety.geofence_center)"
    m = world.mission
    n_geo = len(m.waypoints)
    for i, (lat, lon) in enumerate(ll.tolist()):
        d = great_circle_m(centre[0], centre[1], lat, lon)
        if d <= radius_m:
            continue
        if m.file:
            key = f"mission.file: {m.file}: waypoint {i + 1}"
        elif i < n_geo:
            key = f"mission.waypoints[{i}]"
        else:
            key = f"mission.waypoints_enu[{i - n_geo}] {list(m.waypoints_enu[i - n_geo])} m ="
        raise ConfigError(
            f"{where}{key} ({lat:.7f}, {lon:.7f}) is {d:.0f} m from the geofence centre, "
            f"{named}; {limit}"
        )


ALMANAC_MAX_AGE_S = 28 * 86400.0
"""A run farther than this (s) from its almanac's reference time gets a warning: an almanac
propagated for weeks drifts by tens of km along track, and the real constellation changes
(satellites set unhealthy, moved, launched), so the sky is no longer that day's."""


def sky_warnings(world: World, total_s: float | None = None) -> list[str]:
    """Warnings about the scenario's sky for a run of ``total_s`` s (default: the scenario's
    duration): one when the run lies more than :data:`ALMANAC_MAX_AGE_S` from the almanac's
    reference time (YUMA and SEM almanacs; a RINEX navigation file limits itself, its
    satellites vanish 2 h from any toe). Empty when the sky is the almanac's own epoch's."""
    from sim_backend.geodesy import gps_seconds_to_utc, utc_to_gps_seconds
    from sim_backend.sky import _read_text, read_sem, read_yuma

    path = world.almanac_path
    text = _read_text(path)
    if "RINEX VERSION" in text[:200]:
        return []
    # The files' weeks are 10-bit; the packaged almanac's real date is known, a user's is
    # taken as the sky takes it: the week nearest the start.
    reference = DEFAULT_ALMANAC_DATE if path == DEFAULT_ALMANAC else world.start_utc
    yuma = "almanac for PRN" in text[:200] or "ID:" in text[:200]
    almanacs = (read_yuma if yuma else read_sem)(path, reference)
    if not almanacs:
        return []
    toa_s = float(np.median([a.toa_gps_s for a in almanacs]))
    total = world.duration_s if total_s is None else total_s
    t0 = utc_to_gps_seconds(world.start_utc)
    far_s = max(abs(t0 - toa_s), abs(t0 + total - toa_s))
    if far_s <= ALMANAC_MAX_AGE_S:
        return []
    toa_utc = gps_seconds_to_utc(toa_s)
    age = timedelta(seconds=round(far_s))
    which = "the packaged almanac" if path == DEFAULT_ALMANAC else f"the almanac {path}"
    return [
        f"start_utc {world.start_utc:%Y-%m-%d %H:%M}Z is {age.days} days from the reference "
        f"time of {which} ({toa_utc:%Y-%m-%d %H:%M}Z): the sky is that almanac propagated far "
        "from its epoch, so the satellite positions (and the satellites in view, DOP and the "
        "errors they cause) are not those a real receiver saw then. To compare with a real "
        'log of that date, give the scenario an almanac of that date: almanac = "FILE" '
        "(a YUMA or SEM almanac from within a few weeks, or the day's RINEX navigation file; "
        "the path is relative to the scenario file)"
    ]


STATIC_CHUNK_EPOCHS = 3600
"""A static survey's receiver runs this many epochs per vectorised call (1 h at 1 Hz), so a
long survey's memory stays bounded (10 h with walls in one call took over 1 GB). A survey of
at most this many epochs is one call, as it always was; a longer one draws its random
numbers chunk by chunk, so it differs from the single call by the draw order only."""


@dataclass(frozen=True)
class ErrorStats:
    """Horizontal position error (m) against the truth: count, mean, RMS, CEP50, R95, max."""

    n: int
    mean_m: float
    rms_m: float
    cep50_m: float
    r95_m: float
    max_m: float

    @classmethod
    def of(cls, err_m: np.ndarray) -> ErrorStats:
        """Statistics of horizontal error magnitudes (m); NaN figures when empty."""
        e = np.asarray(err_m, dtype=float)
        e = e[np.isfinite(e)]
        if e.size == 0:
            nan = math.nan
            return cls(0, nan, nan, nan, nan, nan)
        return cls(
            int(e.size),
            float(e.mean()),
            float(np.sqrt(np.mean(e * e))),
            float(np.percentile(e, 50)),
            float(np.percentile(e, 95)),
            float(e.max()),
        )


@dataclass(frozen=True)
class Summary:
    """What a mission run printed (also written as summary.json). Times in seconds, lengths
    in metres; ``dispersion_*_m`` are the paper's ± half spreads of the raw readings."""

    scenario: str
    seed: int
    completed: bool
    waypoints_reached: int
    waypoint_count: int
    sim_time_s: float
    wall_time_s: float
    path_length_m: float
    straight_length_m: float
    raw_error: ErrorStats
    filtered_error: ErrorStats
    hold_periods: int
    hold_time_s: float
    fixes: int
    fixes_valid: int
    dispersion_lat_m: float
    dispersion_lon_m: float
    mean_hdop: float
    mean_sats_used: float
    extra: dict[str, Any] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dict (NaN as None)."""
        return _json_safe(asdict(self))

    def _not_completed_why(self) -> str:
        returned_s, mode = self.extra.get("returned_at_s"), self.extra.get("final_mode")
        if returned_s is not None:
            return f"a failsafe returned the robot to its launch point at {returned_s:.0f} s"
        if mode == "PAUSED":  # a pause, not a HOLD: the robot stands in IDLE (docs/simulator.md)
            last = (self.extra.get("paused_s") or [None])[-1]
            since = (
                f" (since {last[0]:.1f} s: {last[2]})"
                if last is not None and last[1] >= round(self.sim_time_s, 3)
                else ""
            )
            return (
                f"the mission was paused{since} when the run ended at {_seconds(self.sim_time_s)} s"
            )
        if mode == "RUNNING":
            return f"the run's {_seconds(self.sim_time_s)} s ended before the last waypoint"
        return f"the run ended at {_seconds(self.sim_time_s)} s with the robot {mode or 'stopped'}"

    def _paused_lines(self) -> list[str]:
        """The time the mission stood paused (the robot still, in IDLE: no HOLD period),
        one line per pause, none without: "paused 342.2 s (since 57.8 s: <why>)" to the
        run's end, else "paused 12.0 s (57.8-69.8 s: <why>)". A pause open at the end was
        closed at the run's last step and stored rounded to 3 decimals, as the run's end is
        compared here (a fractional --duration's k*dt is not: 100.30000000000001)."""
        out = []
        for start_s, end_s, why in self.extra.get("paused_s") or ():
            when = (
                f"since {start_s:.1f} s"
                if end_s >= round(self.sim_time_s, 3)
                else f"{start_s:.1f}-{end_s:.1f} s"
            )
            out.append(f"  paused              {end_s - start_s:.1f} s ({when}: {why})")
        return out

    def _startup_wait_text(self) -> str:
        wait = self.extra.get("startup_wait_s")
        if not wait:
            return ""
        return f"; start-up wait {wait[1] - wait[0]:.2f} s for the first estimate, not counted"

    def _source_text(self) -> str:
        """The robot's configured position source, as the receiver engine's summary names
        what it did not run."""
        source = str(self.extra.get("position_source", "ekf"))
        return _SOURCE_RUNS.get(source, source)

    def text(self) -> str:
        """The human-readable summary printed by ``x6wd sim``."""
        r, f = self.raw_error, self.filtered_error
        speed = self.sim_time_s / self.wall_time_s if self.wall_time_s > 0 else math.inf
        rejected = self.extra.get("mission_rejected")
        if self.waypoint_count == 0:
            outcome = "static survey (no waypoints)"
        elif rejected:  # the robot refused the mission: say why, not only that it failed
            at_s = self.extra.get("mission_rejected_at_s")
            when = f" at {at_s:.1f} s" if at_s is not None else ""
            outcome = (
                f"mission NOT completed: the robot rejected it{when} ({rejected}); "
                "the run stopped there"
            )
        elif self.completed:
            outcome = "mission COMPLETED"
        else:  # say why (an outside audit: a run cut by its duration said nothing)
            outcome = f"mission NOT completed: {self._not_completed_why()}"
        lines = [
            f"scenario {self.scenario!r} seed {self.seed}: {outcome}",
            f"  waypoints reached   {self.waypoints_reached}/{self.waypoint_count}",
            f"  time                {self.sim_time_s:.1f} s simulated in {self.wall_time_s:.2f} s"
            f" wall ({speed:.0f}x)",
            f"  path length         {self.path_length_m:.1f} m"
            f" (straight line {self.straight_length_m:.1f} m)",
            f"  fixes               {self.fixes_valid}/{self.fixes} valid, mean HDOP"
            f" {self.mean_hdop:.2f}, mean satellites used {self.mean_sats_used:.1f}",
            "  horizontal error    mean    RMS     CEP50   R95     max   (m)",
            f"    raw GPS          {r.mean_m:6.2f}  {r.rms_m:6.2f}  {r.cep50_m:6.2f}"
            f"  {r.r95_m:6.2f}  {r.max_m:6.2f}",
            (
                f"    filtered         {f.mean_m:6.2f}  {f.rms_m:6.2f}  {f.cep50_m:6.2f}"
                f"  {f.r95_m:6.2f}  {f.max_m:6.2f}"
                if math.isfinite(f.mean_m)
                else "    filtered         no estimate: the run ended before the first"
            )
            if self.extra.get("engine") != "receiver"
            else "    filtered         not run: no robot on the receiver engine"
            f" (--engine robot runs {self._source_text()})",
            f"  dispersion (paper)  ±{self.dispersion_lat_m:.2f} m lat,"
            f" ±{self.dispersion_lon_m:.2f} m lon (two-radius)",
            f"  HOLD periods        {self.hold_periods} ({self.hold_time_s:.1f} s)"
            + self._startup_wait_text(),
        ]
        for t_s, why in self.extra.get("failsafes") or ():  # what stopped the mission, and when
            lines.append(f"  failsafe            at {t_s:.1f} s: {why}")
        surprises = self.extra.get("ekf_surprise_resets_m") or ()
        if surprises:  # the estimate far wrong and sure of itself: a compass off its calibration?
            lines.append(
                f"  EKF resets          {len(surprises)} beyond its own ellipse (largest"
                f" {max(surprises):.1f} m): the heading or the wheels led it astray, or the"
                " fixes jumped (the log's WARNING lines say when)"
            )
        lines.extend(self._paused_lines())
        return "\n".join(lines)


def _json_safe(v: Any) -> Any:
    if isinstance(v, float):
        return v if math.isfinite(v) else None
    if isinstance(v, dict):
        return {k: _json_safe(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_json_safe(x) for x in v]
    return v


# ---------------------------------------------------------------------------- building


def vehicle_from_world(world: World) -> Vehicle:
    """The scenario's vehicle at its start pose (shared by fast time and HIL)."""
    v = world.vehicle
    return Vehicle(
        VehicleParams(
            v_max_mps=v.max_speed_mps,
            max_turn_rate_dps=v.turn_rate_dps,
            motor_tau_s=v.motor_tau_s,
            stuck_from_s=v.stuck_from_s,
            stuck_until_s=v.stuck_until_s,
            stuck_mode=v.stuck_mode,
        ),
        east_m=v.start_east_m,
        north_m=v.start_north_m,
        heading_deg=v.start_heading_deg,
        terrain=Terrain(v.slope_east_pct / 100.0, v.slope_north_pct / 100.0),
    )


# ---------------------------------------------------------------------------- the run


def steps_evenly(clock_hz: float, gnss_hz: float) -> bool:
    """Whether a clock of ``clock_hz`` (Hz) has a GPS epoch of ``gnss_hz`` every whole
    number of ticks."""
    return abs(clock_hz / gnss_hz - max(1, round(clock_hz / gnss_hz))) <= 1e-9


ROBOT_TICK_HZ = 20.0
"""The daemon's controller tick and wheel-count polling rate (``x6wd.app.daemon``'s TICK_HZ
and ODOMETRY_HZ, a layer above; a test keeps them equal). On a mission the robot engine's
loop steps at least this fast whatever the compass rate: stepping the motors, the wheels and
the controller at a 1 Hz compass's rate drove 145-183 m for a 95 m route with EKF resets,
where the daemon on the same compass drove it as at 20 Hz (an outside audit)."""


def robot_clock(compass_hz: float, gnss_hz: float, drives: bool) -> tuple[float, int] | None:
    """The robot engine's clock (Hz) and its ticks per compass reading: the compass rate, on
    a mission (``drives``) times the smallest whole number that makes it at least
    :data:`ROBOT_TICK_HZ` (a survey steps at the compass rate: the robot stands, and its
    loop's rate changes no figure). None when the clock is no whole multiple of ``gnss_hz``."""
    m = compass_ticks(compass_hz, drives)
    return (compass_hz * m, m) if steps_evenly(compass_hz * m, gnss_hz) else None


def compass_ticks(compass_hz: float, drives: bool) -> int:
    """The robot engine's ticks per compass reading (:func:`robot_clock`)."""
    return max(1, math.ceil(ROBOT_TICK_HZ / compass_hz - 1e-9)) if drives else 1


@dataclass(frozen=True)
class RunPlan:
    """A run's seed, length and clock: the loop steps every ``dt_s`` (s; :func:`robot_clock`),
    reads the compass every ``compass_every`` ticks and has a GPS epoch every ``gps_every``
    ticks, ``n_ticks`` + 1 ticks from 0 to ``total_s`` (s)."""

    seed: int
    total_s: float
    dt_s: float
    gps_every: int
    n_ticks: int
    compass_every: int = 1

    @classmethod
    def of(
        cls, world: World, seed: int | None, duration_s: float | None, compass_hz: float
    ) -> RunPlan:
        """The plan for ``world`` with optional seed and duration (s) overrides, stepping at
        ``compass_hz`` (Hz); ConfigError names a bad seed, duration or rate pair."""
        seed = world.seed if seed is None else int(seed)
        if seed < 0:
            raise ConfigError(f"seed must be >= 0, got {seed}")
        total_s = world.duration_s if duration_s is None else float(duration_s)
        if not (total_s > 0 and math.isfinite(total_s)):
            raise ConfigError(f"duration must be a positive number of seconds, got {duration_s!r}")
        if total_s > MAX_DURATION_S:  # as the scenario's duration_s: the run's arrays grow
            raise ConfigError(
                f"duration must be at most {MAX_DURATION_S:.0f} s (30 days), got {duration_s!r}"
            )
        gnss_hz = world.gnss.rate_hz
        drives = len(world.waypoints_enu_m()) > 0
        clock = robot_clock(compass_hz, gnss_hz, drives)
        if clock is None:
            m = compass_ticks(compass_hz, drives)
            steps = (
                f"compass.rate_hz ({compass_hz:g})"
                if m == 1
                else f"{compass_hz * m:g} Hz on a mission (compass.rate_hz ({compass_hz:g}) times"
                f" {m}: the daemon's {ROBOT_TICK_HZ:g} Hz tick or more), which"
            )
            raise ConfigError(
                f"{steps} must be a whole multiple of gnss.rate_hz ({gnss_hz:g}): the robot"
                " engine's loop steps at it (the receiver engine, a static survey, takes any"
                " pair)"
            )
        clock_hz, compass_every = clock
        dt = 1.0 / clock_hz
        gps_every = max(1, round(clock_hz / gnss_hz))  # ticks per GPS epoch
        n_ticks = math.ceil(total_s / dt - 1e-9)
        return cls(seed, total_s, dt, gps_every, n_ticks, compass_every)

    def epoch_times_s(self) -> np.ndarray:
        """The GPS epochs' times (s): the ticks that carry one, exactly as the loop computes
        them (tick index times ``dt_s``)."""
        return np.arange(0, self.n_ticks + 1, self.gps_every) * self.dt_s


def straight_length_m(world: World) -> float:
    """The planned route's length (m): from the vehicle's start through every waypoint, each
    leg along the great circle (the ground's ECEF chord turned into the arc on the mean
    Earth sphere: equal to the flat distance on a field, and meaningful for a waypoint on
    another continent, where a tangent-plane east/north chord is not). 0 without waypoints.
    The start is placed as an ENU waypoint is: its point of the origin's flat plane turned
    into latitude/longitude, at the origin's altitude. The plane's point itself lies above
    the ground far out (102 m at 36 km), and that drop counted in the first leg (an outside
    audit: "straight line 174.8 m" for a 95 m route)."""
    from sim_backend.geodesy import enu_to_lla, lla_to_ecef

    ll = world.waypoints_latlon()
    if len(ll) == 0:
        return 0.0
    o, v = world.origin, world.vehicle
    s_lat, s_lon, _alt = enu_to_lla(np.array([v.start_east_m, v.start_north_m, 0.0]),
                                    o.lat_deg, o.lon_deg, o.alt_m)  # fmt: skip
    lat = np.concatenate([np.atleast_1d(s_lat), ll[:, 0]])
    lon = np.concatenate([np.atleast_1d(s_lon), ll[:, 1]])
    pts = np.reshape(lla_to_ecef(lat, lon, np.full(len(lat), o.alt_m)), (-1, 3))
    chord = np.linalg.norm(np.diff(pts, axis=0), axis=1)
    r = EARTH_MEAN_RADIUS_M
    return float(np.sum(2.0 * r * np.arcsin(np.minimum(1.0, chord / (2.0 * r)))))


def dispersion_m(dlat_deg: np.ndarray, dlon_deg: np.ndarray) -> tuple[float, float]:
    """The paper's ± half spreads (m, latitude and longitude) of readings minus truth (deg),
    two-radius converted; NaN for no readings. A longitude difference is taken the short
    way round: a fix at -179.99999 against a truth of +179.99999 is 0.00002 deg off, not
    360 (it read half the earth's circumference on a route over the 180th meridian)."""
    if len(dlat_deg) == 0:
        return math.nan, math.nan
    dlon_deg = (np.asarray(dlon_deg, dtype=float) + 180.0) % 360.0 - 180.0
    half_lat = math.radians(float(np.max(dlat_deg) - np.min(dlat_deg))) * R2_M / 2.0
    half_lon = math.radians(float(np.max(dlon_deg) - np.min(dlon_deg))) * R1_M / 2.0
    return half_lat, half_lon


MAX_WAYPOINT_LABELS = 40
"""The plot numbers at most this many waypoints: a long route's labels would cover it (and
took matplotlib about a second per 200)."""
MAX_PATH_POINTS = 50_000
"""The true path is drawn through at most this many of its ticks (a 10 h mission at 20 Hz
has 720,000; on 700 px a tick in 15 is no visible loss)."""


def waypoint_labels(wp_enu: np.ndarray, most: int = MAX_WAYPOINT_LABELS) -> list[tuple[int, str]]:
    """The waypoint numbers the plot prints, as (index of the first waypoint at the place,
    text), for the waypoints ``wp_enu`` (N, 2) m. The numbers at one place (to the
    centimetre: a route that comes back, or laps) share a label, "1,5,9..." after three; of
    more than ``most`` (>= 2) places, ``most`` spread evenly along the route are labelled,
    the first and the last among them."""
    if most < 2:
        raise ValueError(f"most must be at least 2, got {most}")
    at: dict[tuple[float, float], list[int]] = {}
    for i, (e, n) in enumerate(np.asarray(wp_enu, dtype=float)[:, :2].tolist()):
        at.setdefault((round(e, 2), round(n, 2)), []).append(i)
    places = list(at.values())  # in the order of their first visit
    if len(places) > most:
        picks = sorted({round(k * (len(places) - 1) / (most - 1)) for k in range(most)})
        places = [places[k] for k in picks]
    return [
        (idx[0], ",".join(str(i + 1) for i in idx[:3]) + ("..." if len(idx) > 3 else ""))
        for idx in places
    ]


_SOURCE_LABELS = {"ekf": " (EKF)", "constellation": " (Constellation)", "raw": " (latest fix)"}


def filtered_label(summary: Summary) -> str:
    """The filtered track's legend: the robot's position source (navigation.position_source)
    as the run's summary records it."""
    return "filtered" + _SOURCE_LABELS.get(str(summary.extra.get("position_source")), "")


def plot_track(
    path: Path,
    world: World,
    truth_e: np.ndarray,
    truth_n: np.ndarray,
    fix_enu: np.ndarray,
    filt_enu: np.ndarray,
    wp_enu: np.ndarray,
    summary: Summary,
) -> None:
    """The run's track plot (PNG at ``path``): walls, raw fixes, filtered track, the true path
    and the waypoints, all in scenario ENU metres."""
    # A bare Figure renders with Agg like pyplot would, without pyplot's figure manager and
    # global state (cheaper per mission; the gap tool plots one per seed).
    from matplotlib.figure import Figure

    fig = Figure(figsize=(7, 7), dpi=100)
    ax = fig.subplots()
    try:
        for w in world.walls:
            ax.plot([w.x0_m, w.x1_m], [w.y0_m, w.y1_m], color="0.3", lw=3, zorder=1)
        for r in world.roofs:
            ax.fill(
                [r.x0_m, r.x1_m, r.x1_m, r.x0_m], [r.y0_m, r.y0_m, r.y1_m, r.y1_m],
                color="0.85", zorder=0,
            )  # fmt: skip
        if len(fix_enu):
            ax.plot(fix_enu[:, 0], fix_enu[:, 1], ".", ms=3, color="tab:red", alpha=0.6,
                    label="raw GPS", zorder=2)  # fmt: skip
            ok = np.all(np.isfinite(filt_enu), axis=1)
            if ok.any():  # the receiver engine runs no robot: nothing filtered
                ax.plot(filt_enu[ok, 0], filt_enu[ok, 1], "-", lw=1, color="tab:orange",
                        label=filtered_label(summary), zorder=3)  # fmt: skip
        if np.ptp(truth_e) == 0 and np.ptp(truth_n) == 0:  # standing still: a point, not a path
            ax.plot(truth_e[:1], truth_n[:1], "P", ms=12, color="tab:blue", mec="white",
                    label="true position", zorder=4)  # fmt: skip
        else:
            keep = thinned_indices(truth_e.size, MAX_PATH_POINTS)
            ax.plot(truth_e[keep], truth_n[keep], "-", lw=2, color="tab:blue", label="true path",
                    zorder=4)  # fmt: skip
        if len(wp_enu):
            ax.plot(wp_enu[:, 0], wp_enu[:, 1], "k*", ms=12, label="waypoints", zorder=5)
            for i, text in waypoint_labels(wp_enu):
                e, n = wp_enu[i]
                ax.annotate(text, (e, n), textcoords="offset points", xytext=(6, 6))
        ax.set_xlabel("east (m)")
        ax.set_ylabel("north (m)")
        ax.set_aspect("equal", adjustable="datalim")
        ax.grid(True, alpha=0.3)
        ax.legend(loc="best", fontsize=8)
        filt = summary.filtered_error.cep50_m
        ax.set_title(
            f"{world.name} (seed {summary.seed})\n{summary.waypoints_reached}/"
            f"{summary.waypoint_count} waypoints, raw CEP50 {summary.raw_error.cep50_m:.1f} m"
            + (f", filtered CEP50 {filt:.1f} m" if math.isfinite(filt) else ""),
            fontsize=9,
        )
        fig.savefig(path)
    finally:
        fig.clear()
