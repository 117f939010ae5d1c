"""The runtime failsafes in fast time (issue 14, item 5), with the robot's default
configuration: whole missions through ``run_mission`` with a fault injected in the simulated
world (a stuck vehicle, a GPS outage, a small geofence) or an operator scripted by the
``operator`` hook, each checked on the recording, the summary and the true track.

The first tests check the injections themselves (the vehicle's stuck fault with its
encoders, the scripted ``outage`` layer); the rest run missions (about 0.5-2 s of wall time
each). Each mission test fails when the behaviour it checks is taken out of
``x6wd/nav/controller.py`` or ``x6wd/loop/runner.py`` (checked by breaking each on purpose).
A test whose scenario did not set up what it needs (the fault began while pivoting, ...)
raises :class:`PremiseError`, an error rather than a failure of the behaviour.
"""

from __future__ import annotations

import csv
import json
import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from sim_backend.effects import Outage, PositionSeries, effect_from_params
from sim_backend.geodesy import enu_to_lla, lla_to_enu
from sim_backend.mission import Summary, run_mission, vehicle_from_world
from sim_backend.odometry import EncoderSim
from sim_backend.vehicle import Vehicle, VehicleParams
from sim_backend.world import World, loads_world
from x6wd.core.errors import ConfigError
from x6wd.core.geodesy import great_circle_m
from x6wd.loop.runner import Runner

ROOT = Path(__file__).resolve().parent.parent
SCENARIOS = ROOT / "config" / "scenarios"
DEFAULT = (SCENARIOS / "default.toml").read_text(encoding="utf-8")
DEFAULT_WAYPOINTS = "waypoints_enu = [[0.0, 25.0], [25.0, 25.0], [25.0, 0.0], [5.0, 0.0]]"
ORIGIN = (51.7520, -1.2577, 60.0)  # default.toml's [origin]; the robot starts there
STUCK_S = 10.0  # failsafe.stuck_s, the default
STUCK_FROM_S = 9.5  # the vehicle sticks here (a phase the window-based check meets in time)
LONG_LEG = "[[0.0, 60.0]]"  # one straight 60 m leg: the robot cruises for 26 s
SENSOR_TIMEOUT_S = 5.0  # [failsafe] sensor_timeout_s for the outage tests (default 30 s)
OUTAGE_FROM_S = 8.0


def _world(
    duration_s: float,
    *,
    vehicle: str = "",
    heading_deg: float = 0.0,
    waypoints: str | None = None,
    extra: str = "",
) -> World:
    """default.toml (no [navigation] override: the robot's defaults) shortened to
    ``duration_s``, with ``vehicle`` keys added to its [vehicle], another start heading,
    other waypoints and ``extra`` tables appended."""
    text = DEFAULT.replace("duration_s = 400.0", f"duration_s = {duration_s}")
    assert DEFAULT_WAYPOINTS in text and "[vehicle]\n" in text
    assert "start_heading_deg = 0.0\n" in text
    text = text.replace("start_heading_deg = 0.0\n", f"start_heading_deg = {heading_deg}\n")
    if waypoints is not None:
        text = text.replace(DEFAULT_WAYPOINTS, f"waypoints_enu = {waypoints}")
    if vehicle:
        text = text.replace("[vehicle]\n", f"[vehicle]\n{vehicle}\n")
    world = loads_world(text + "\n" + extra, base_dir=SCENARIOS)
    assert world.navigation == type(world.navigation)()  # the robot's own navigation
    return world


@dataclass
class Run:
    """A finished mission: the summary, the recording by record type, the true track."""

    summary: Summary
    records: list[dict[str, Any]]
    t: np.ndarray  # truth.csv times (s)
    east: np.ndarray  # true position (m, the origin's local frame)
    north: np.ndarray

    def of(self, kind: str) -> list[dict[str, Any]]:
        return [r["data"] for r in self.records if r["type"] == kind]

    @property
    def states(self) -> list[dict[str, Any]]:
        return self.of("state")

    def first(self, new: str, reason: str = "") -> dict[str, Any]:
        """The first state change to ``new`` whose reason contains ``reason``."""
        for s in self.states:
            if s["new"] == new and reason in s["reason"]:
                return s
        raise AssertionError(
            f"no state change to {new} with {reason!r}: "
            + "; ".join(f"{s['t_s']:.2f} {s['old']}->{s['new']} {s['reason']}" for s in self.states)
        )

    def mode_changes(self) -> list[tuple[float, str, str]]:
        """(t_s, new, reason) of every mode change."""
        return [
            (s["t_s"], s["new"], s["reason"])
            for s in self.states
            if s["reason"].startswith("mode:")
        ]

    def at(self, t_s: float) -> tuple[float, float]:
        """True (east, north) at the physics step nearest ``t_s``."""
        i = int(np.argmin(np.abs(self.t - t_s)))
        return float(self.east[i]), float(self.north[i])

    def moved_after(self, t_s: float) -> float:
        """Largest true distance (m) from the position at ``t_s`` to any later one."""
        e0, n0 = self.at(t_s)
        later = self.t >= t_s
        return float(np.max(np.hypot(self.east[later] - e0, self.north[later] - n0)))

    def final_from_start_m(self) -> float:
        return float(math.hypot(self.east[-1] - self.east[0], self.north[-1] - self.north[0]))

    def counts(self, t_s: float) -> tuple[int, int]:
        """Encoder counts of the last odometry record at or before ``t_s``."""
        last = (0, 0)
        for r in self.of("odometry"):
            if r["t_s"] > t_s:
                break
            last = (r["left_counts"], r["right_counts"])
        return last


def _mission(
    out: Path, world: World, operator: Callable[[float, Runner], None] | None = None
) -> Run:
    summary = run_mission(world, out, operator=operator)
    records = [json.loads(line) for line in (out / "recording.jsonl").open(encoding="utf-8")]
    with (out / "truth.csv").open(newline="") as f:
        rows = list(csv.DictReader(f))
    lat = np.array([float(r["lat"]) for r in rows])
    lon = np.array([float(r["lon"]) for r in rows])
    enu = np.asarray(lla_to_enu(lat, lon, np.full(lat.shape, ORIGIN[2]), *ORIGIN))
    t = np.array([float(r["t_s"]) for r in rows])
    return Run(summary, records, t, enu[:, 0], enu[:, 1])


class PremiseError(RuntimeError):
    """A test's set-up did not happen as it needs (an error, not a failure of the behaviour)."""


def _require(ok: bool, what: str) -> None:
    if not ok:
        raise PremiseError(what)


def _premise(run: Run, new: str, reason: str = "") -> dict[str, Any]:
    """:meth:`Run.first`, raising :class:`PremiseError` when there is none."""
    try:
        return run.first(new, reason)
    except AssertionError as exc:
        raise PremiseError(str(exc)) from None


def _pivoting(run: Run, t_s: float) -> bool:
    """The navigation state at ``t_s`` is a turn on the spot."""
    state = "IDLE"
    for s in run.states:
        if s["t_s"] > t_s:
            break
        if not s["reason"].startswith("mode:"):
            state = s["new"]
    return state in ("TURN_LEFT", "TURN_RIGHT")


def _at(t_target: float, action: Callable[[Runner], Any]) -> Callable[[float, Runner], None]:
    """An operator doing ``action`` once, at the first tick at or after ``t_target`` (s)."""
    done = [False]

    def operator(t_s: float, runner: Runner) -> None:
        if not done[0] and t_s >= t_target - 1e-9:
            done[0] = True
            action(runner)

    return operator


# ------------------------------------------------------------------- the injections


def _drive(params: VehicleParams, seconds: float, dt: float = 0.05) -> tuple[Vehicle, EncoderSim]:
    v = Vehicle(params)
    enc = EncoderSim(start=v.state)  # no random error: systematic only
    v.command(60.0, 60.0)
    for _ in range(round(seconds / dt)):
        enc.step(dt, v.step(dt))
    return v, enc


def test_blocked_vehicle_and_its_wheels_do_not_move() -> None:
    free, free_enc = _drive(VehicleParams(), 2.0)
    v, enc = _drive(VehicleParams(stuck_from_s=0.0, stuck_mode="blocked"), 10.0)
    assert free.state.north_m > 3.0 and min(free_enc.counts) > 10_000
    s = v.state
    assert (s.east_m, s.north_m, s.heading_deg, s.odometer_m) == (0.0, 0.0, 0.0, 0.0)
    assert (s.speed_mps, s.left_pct, s.right_pct) == (0.0, 0.0, 0.0)
    assert enc.counts == (0, 0)


def test_slipping_vehicle_stays_while_its_wheels_count_the_commanded_travel() -> None:
    free, free_enc = _drive(VehicleParams(), 5.0)
    v, enc = _drive(VehicleParams(stuck_from_s=0.0, stuck_mode="slipping"), 5.0)
    s = v.state
    assert (s.east_m, s.north_m, s.odometer_m, s.speed_mps) == (0.0, 0.0, 0.0, 0.0)
    assert s.left_pct == pytest.approx(60.0)  # the motors run
    assert s.slip_m == pytest.approx(free.state.odometer_m, rel=1e-9)
    assert enc.counts[0] == pytest.approx(free_enc.counts[0], abs=2)
    assert enc.counts[1] == pytest.approx(free_enc.counts[1], abs=2)


def test_slipping_pivot_counts_what_a_free_pivot_counts() -> None:
    counts = []
    for p in (VehicleParams(), VehicleParams(stuck_from_s=0.0, stuck_mode="slipping")):
        v = Vehicle(p)
        enc = EncoderSim(start=v.state)
        v.command(40.0, -40.0)
        for _ in range(20):
            enc.step(0.05, v.step(0.05))
        counts.append(enc.counts)
        turned = v.state.heading_deg if p.stuck_from_s is None else v.state.slip_cw_deg
        assert 25.0 < turned < 36.0  # 1 s at 40 % of 90 deg/s, less the motors' lag
    assert v.state.heading_deg == 0.0  # the slipping one did not turn
    (fl, fr), (sl, sr) = counts
    assert fl > 300 and fr < -300
    assert sl == pytest.approx(fl, abs=2) and sr == pytest.approx(fr, abs=2)


def test_stuck_window_splits_the_step_and_frees_the_vehicle() -> None:
    p = VehicleParams(motor_tau_s=0.0, stuck_from_s=1.02, stuck_until_s=3.01)
    v = Vehicle(p)
    v.command(50.0, 50.0)
    for _ in range(20):
        v.step(0.05)
    speed = 0.5 * p.v_max_mps
    assert v.state.north_m == pytest.approx(1.0 * speed)
    v.step(0.05)  # 1.00 -> 1.05: moves until 1.02 only
    assert v.state.north_m == pytest.approx(1.02 * speed)
    for _ in range(39):
        v.step(0.05)  # to 3.00: stuck
    assert v.state.north_m == pytest.approx(1.02 * speed)
    v.step(0.05)  # 3.00 -> 3.05: free from 3.01
    assert v.state.north_m == pytest.approx((1.02 + 0.04) * speed)
    assert v.state.t_s == pytest.approx(3.05)


def test_stuck_keys_are_validated_and_reach_the_shared_vehicle() -> None:
    world = _world(10.0, vehicle='stuck_from_s = 4\nstuck_until_s = 6.5\nstuck_mode = "slipping"')
    p = vehicle_from_world(world).params  # fast time and HIL build the vehicle here
    assert (p.stuck_from_s, p.stuck_until_s, p.stuck_mode) == (4.0, 6.5, "slipping")
    assert vehicle_from_world(_world(10.0)).params.stuck_from_s is None
    for bad, key in (
        ('stuck_mode = "sunk"', "vehicle.stuck_mode"),
        ("stuck_from_s = -1.0", "vehicle.stuck_from_s"),
        ("stuck_until_s = 5.0", "vehicle.stuck_until_s"),
        ("stuck_from_s = 5.0\nstuck_until_s = 5.0", "vehicle.stuck_until_s"),
    ):
        with pytest.raises(ConfigError, match=key):
            _world(10.0, vehicle=bad)


def test_outage_layer_removes_the_fix_in_its_window() -> None:
    layer = effect_from_params({"name": "outage", "start_s": 2.0, "duration_s": 3.0})
    assert layer == Outage(2.0, 3.0) and layer.kind == "gps"
    t = np.arange(0.0, 8.0)
    z = np.zeros_like(t)
    out = layer.start(np.random.default_rng(0)).step(
        PositionSeries(t, z, z, z, np.ones(t.shape, dtype=bool))
    )
    assert out.valid.tolist() == [True, True, False, False, False, True, True, True]
    with pytest.raises(ConfigError, match="duration_s"):
        effect_from_params({"name": "outage", "start_s": 2.0, "duration_s": 0.0})


# ------------------------------------------------------------------- operator: return


@pytest.fixture(scope="module")
def returned(tmp_path_factory: pytest.TempPathFactory) -> Run:
    out = tmp_path_factory.mktemp("return")
    return _mission(out, _world(90.0), _at(20.0, lambda r: r.command("return")))


def test_return_command_drives_back_to_launch_and_ends_there(returned: Run) -> None:
    run = returned
    ret = run.first("RUNNING", "return to launch")
    assert ret["t_s"] == pytest.approx(20.0)
    done = run.first("DONE")
    assert done["reason"] == "mode: back at the launch point"
    assert done["t_s"] > 25.0  # it drove back (about 20 m at 2.3 m/s, a turn first)
    assert run.mode_changes()[-1][1] == "DONE"
    assert not any(new == "PAUSED" for _t, new, _r in run.mode_changes())
    assert run.final_from_start_m() < 3.0  # the true end point against the true start
    assert run.at(20.0)[1] > 15.0  # it had left: 20 s into the mission, over 15 m north
    assert any(
        t["extra"].get("returning") == "return" for t in run.of("telemetry") if t["t_s"] > 20.0
    )


def test_summary_after_an_early_return_counts_no_waypoint(tmp_path: Path) -> None:
    run = _mission(tmp_path, _world(60.0), _at(5.0, lambda r: r.command("return")))
    done = _premise(run, "DONE")
    _require(done["reason"] == "mode: back at the launch point", "did not end at launch")
    assert run.summary.extra["arrivals"] == []
    assert run.summary.waypoints_reached == 0
    assert not run.summary.completed
    assert run.summary.extra["returned_at_s"] == pytest.approx(5.0, abs=0.06)


# ------------------------------------------------------------------- the geofence

FENCE_MARGIN_M = 1.5  # the start lies this far inside the fence


def _fence_world(action: str) -> tuple[World, tuple[float, float], float]:
    """A fence whose edge runs (nearly straight) 1.5 m west of the start and of the one
    waypoint 30 m north; the robot starts heading 310 deg, under the pivot angle, so it arcs
    out west (about 4 m) before it follows the leg: the mission leaves the fence."""
    lat, lon, _alt = enu_to_lla(np.array([1000.0, 15.0, 0.0]), *ORIGIN)
    centre = (float(lat), float(lon))
    radius = great_circle_m(*centre, ORIGIN[0], ORIGIN[1]) + FENCE_MARGIN_M
    world = _world(
        40.0,
        heading_deg=310.0,
        waypoints="[[0.0, 30.0]]",
        extra=f"[safety]\ngeofence_radius_m = {radius!r}\n"
        f"geofence_center = [{centre[0]!r}, {centre[1]!r}]\n"
        f'[failsafe]\ngeofence_action = "{action}"\n',
    )
    return world, centre, radius


def _outside(run: Run, centre: tuple[float, float], radius: float) -> np.ndarray:
    """Per physics step: the true position lies outside the fence."""
    lat, lon, _alt = enu_to_lla(np.stack([run.east, run.north, 0 * run.east], axis=-1), *ORIGIN)
    d = np.array([great_circle_m(*centre, a, b) for a, b in zip(lat, lon, strict=True)])
    return d > radius


def test_geofence_breach_with_hold_pauses_and_stops_the_robot(tmp_path: Path) -> None:
    world, centre, radius = _fence_world("hold")
    run = _mission(tmp_path, world)
    assert run.summary.extra["mission_rejected"] is None  # the waypoint lies inside
    paused = run.first("PAUSED", "failsafe: geofence breach")
    t = paused["t_s"]
    assert t < 10.0 and run.summary.extra["geofence_breaches"] >= 1
    assert run.mode_changes()[-1][1] == "PAUSED"
    assert _outside(run, centre, radius).any()
    # motors stopped: the last command is a stop, and the robot stays (after it coasts)
    motors = [m for m in run.of("motor") if m["t_s"] >= t]
    assert motors and all(m["left_pct"] == m["right_pct"] == 0.0 for m in motors)
    assert run.moved_after(t + 1.5) < 0.05
    assert run.at(40.0)[1] < 20.0  # never went on to the waypoint
    assert run.summary.completed is False


def test_geofence_breach_with_return_drives_back_inside_to_launch(tmp_path: Path) -> None:
    world, centre, radius = _fence_world("return")
    run = _mission(tmp_path, world)
    ret = run.first("RUNNING", "failsafe: geofence breach: return to launch")
    assert ret["t_s"] < 10.0
    done = run.first("DONE")
    assert done["reason"] == "mode: back at the launch point" and done["t_s"] > ret["t_s"]
    assert not any(new == "PAUSED" for _t, new, _r in run.mode_changes())
    # the return is not interrupted by the fence it is leading back into: one breach only
    assert run.summary.extra["geofence_breaches"] == 1
    outside = _outside(run, centre, radius)
    assert outside.any() and not outside[-1]
    assert run.final_from_start_m() < 3.0
    telem = [x for x in run.of("telemetry") if x["t_s"] > ret["t_s"]]
    assert any(x["extra"].get("failsafe") == "geofence breach" for x in telem)


# ------------------------------------------------------------------- stuck


def _stuck_world(
    mode: str, action: str = "hold", duration_s: float = 30.0, from_s: float = STUCK_FROM_S
) -> World:
    """Stuck on the long leg, far from its end: the robot drives forward into the fault,
    and a slipping robot's estimate (its wheels turn) does not reach the waypoint first."""
    return _world(
        duration_s,
        vehicle=f'stuck_from_s = {from_s}\nstuck_mode = "{mode}"',
        waypoints=LONG_LEG,
        extra=f'[failsafe]\nstuck_action = "{action}"\n',
    )


@pytest.mark.parametrize(("mode", "what"), [("blocked", "the wheels"), ("slipping", "the GPS")])
def test_stuck_vehicle_is_paused(tmp_path: Path, mode: str, what: str) -> None:
    run = _mission(tmp_path, _stuck_world(mode))
    paused = run.first("PAUSED", "failsafe: stuck")
    assert what in paused["reason"], paused["reason"]
    t = paused["t_s"]
    # not before the robot had been stuck for stuck_s (it covers 2 m in under 1 s), and
    # soon after
    assert STUCK_FROM_S + STUCK_S - 1.0 <= t <= STUCK_FROM_S + STUCK_S + 3.0
    assert run.mode_changes()[-1][1] == "PAUSED"
    assert run.moved_after(STUCK_FROM_S) < 1e-9  # the fault held the body
    left0, right0 = run.counts(STUCK_FROM_S)
    left1, right1 = run.counts(t)
    if mode == "blocked":
        assert (left1, right1) == (left0, right0)  # the encoders count nothing
    else:
        travel = 10.0 * 2.3  # about 10 s at 60 % of 3.9 m/s
        per_m = 4329  # counts per metre of the default encoders
        assert min(left1 - left0, right1 - right0) > 0.5 * travel * per_m
    motors = [m for m in run.of("motor") if m["t_s"] >= t]
    assert motors and all(m["left_pct"] == m["right_pct"] == 0.0 for m in motors)


OUT_AND_BACK = "[[0.0, 100.0], [0.0, -40.0]]"  # out 100 m north, then back past the launch
HOMEWARD_FROM_S = 60.0  # on the way back (the pivot at the far waypoint ends by ~53 s)


@pytest.mark.slow
@pytest.mark.parametrize(("mode", "what"), [("blocked", "the wheels"), ("slipping", "the GPS")])
def test_stuck_with_return_acts_then_still_stuck_is_paused(
    tmp_path: Path, mode: str, what: str
) -> None:
    """Stuck on the way back, the launch point ahead: the return drives forward (no pivot),
    the robot does not move, and the second stuck detection pauses it (a stuck robot cannot
    return). Far from home, so a slipping robot's estimate, which creeps on with its wheels,
    cannot reach the launch point first."""
    world = _world(
        100.0,
        vehicle=f'stuck_from_s = {HOMEWARD_FROM_S}\nstuck_mode = "{mode}"',
        waypoints=OUT_AND_BACK,
        extra='[failsafe]\nstuck_action = "return"\n',
    )
    run = _mission(tmp_path, world)
    ret = run.first("RUNNING", f"failsafe: stuck ({what}")
    assert ret["reason"].endswith("return to launch")
    assert HOMEWARD_FROM_S + STUCK_S - 1.0 <= ret["t_s"] <= HOMEWARD_FROM_S + STUCK_S + 3.0
    paused = run.first("PAUSED", "failsafe: stuck")
    assert ret["t_s"] + STUCK_S - 1.0 <= paused["t_s"] <= ret["t_s"] + STUCK_S + 1.0
    assert [new for _t, new, _r in run.mode_changes()][-2:] == ["RUNNING", "PAUSED"]
    assert run.moved_after(HOMEWARD_FROM_S) < 1e-9
    telem = [x for x in run.of("telemetry") if ret["t_s"] < x["t_s"] < paused["t_s"]]
    assert telem and all(x["extra"].get("returning", "").startswith("failsafe") for x in telem)


def test_slipping_robot_does_not_complete_its_mission_on_its_wheels(tmp_path: Path) -> None:
    """Slipping on its last leg, about 8 m before the last waypoint: the stuck failsafe must
    pause it; the mission must not end "last waypoint reached" with the robot stuck (the
    EKF's estimate follows the spinning wheels; the controller's GPS check of an EKF
    arrival refuses it)."""
    world = _world(
        60.0,
        vehicle='stuck_from_s = 23.0\nstuck_mode = "slipping"',
        waypoints="[[0.0, 30.0], [0.0, 8.0]]",
    )
    run = _mission(tmp_path, world)
    _require(not _pivoting(run, 23.0), "not driving forward when the fault begins")
    east, north = run.at(23.0)
    _require(math.hypot(east, north - 8.0) > 5.0, "stuck too near the last waypoint")
    assert not any(new == "DONE" for _t, new, _r in run.mode_changes()), run.mode_changes()
    assert run.first("PAUSED", "failsafe: stuck (the GPS")["t_s"] <= 23.0 + 2 * STUCK_S + 1.0


def test_stuck_with_return_while_pivoting_is_paused(tmp_path: Path) -> None:
    """The launch point lies behind: the return starts with a pivot that never ends."""
    run = _mission(tmp_path, _stuck_world("slipping", "return", duration_s=40.0))
    ret = _premise(run, "RUNNING", "failsafe: stuck")
    _require(ret["reason"].endswith("return to launch"), "the return was not taken")
    _require(_pivoting(run, ret["t_s"] + 0.5), "the return does not start with a pivot")
    paused = run.first("PAUSED", "failsafe: stuck")
    assert paused["t_s"] <= ret["t_s"] + STUCK_S + 5.0


def test_stuck_during_a_pivot_at_a_waypoint_is_paused(tmp_path: Path) -> None:
    """Blocked while it turns round at its first waypoint (a pivot of about 17.6-22.4 s when
    free): the encoders count nothing while the motors are driven at turn_pct."""
    world = _world(
        40.0,
        vehicle='stuck_from_s = 19.5\nstuck_mode = "blocked"',
        waypoints="[[0.0, 30.0], [0.0, 8.0]]",
    )
    run = _mission(tmp_path, world)
    _require(_pivoting(run, 19.5), "not pivoting when the fault begins")
    paused = run.first("PAUSED", "failsafe: stuck (the wheels")
    assert paused["t_s"] <= 19.5 + STUCK_S + 3.0


def test_stuck_is_detected_within_stuck_s_whatever_the_phase(tmp_path: Path) -> None:
    run = _mission(tmp_path, _stuck_world("blocked", duration_s=35.0, from_s=12.5))
    _require(not _pivoting(run, 12.5), "not driving forward when the fault begins")
    paused = run.first("PAUSED", "failsafe: stuck")
    assert paused["t_s"] <= 12.5 + STUCK_S + 3.0


# ------------------------------------------------------------------- sensor stale


def _outage_world(duration_s: float, outage_s: float, outage_max_m: float = 0.0) -> World:
    """A GPS outage from OUTAGE_FROM_S; ``outage_max_m``: [safety] gps_outage_max_m (0: hold
    at once, as the paper's robot; the robot's default lets the EKF drive on 20 m)."""
    return _world(
        duration_s,
        extra=f'[[effects]]\nname = "outage"\nstart_s = {OUTAGE_FROM_S}\n'
        f"duration_s = {outage_s}\n"
        f"[failsafe]\nsensor_timeout_s = {SENSOR_TIMEOUT_S}\n"
        f"[safety]\ngps_outage_max_m = {outage_max_m}\n",
    )


def test_gps_outage_longer_than_the_sensor_timeout_holds_then_pauses(tmp_path: Path) -> None:
    run = _mission(tmp_path, _outage_world(30.0, 30.0))
    hold = run.first("HOLD", "no valid fix")
    assert OUTAGE_FROM_S <= hold["t_s"] <= OUTAGE_FROM_S + 1.5  # at once: the next epoch
    paused = run.first("PAUSED", "failsafe: no valid fix")
    assert paused["t_s"] == pytest.approx(hold["t_s"] + SENSOR_TIMEOUT_S, abs=0.1)
    assert run.mode_changes()[-1][1] == "PAUSED"
    motors = [m for m in run.of("motor") if m["t_s"] >= hold["t_s"]]
    assert motors and all(m["left_pct"] == m["right_pct"] == 0.0 for m in motors)
    assert run.moved_after(hold["t_s"] + 1.5) < 0.05


@pytest.mark.slow
def test_short_gps_outage_holds_then_resumes_and_completes(tmp_path: Path) -> None:
    run = _mission(tmp_path, _outage_world(120.0, 3.0))
    hold = run.first("HOLD", "no valid fix")
    assert OUTAGE_FROM_S <= hold["t_s"] <= OUTAGE_FROM_S + 1.5
    resumed = next(s for s in run.states if s["old"] == "HOLD" and s["t_s"] > hold["t_s"])
    assert resumed["t_s"] <= OUTAGE_FROM_S + 3.0 + 1.5
    assert not any("failsafe" in r for _t, _n, r in run.mode_changes())
    assert run.summary.completed and run.first("DONE")["reason"] == "mode: last waypoint reached"
    assert len(run.summary.extra["arrivals"]) == 4


# ------------------------------------------------------------------- operator link


def test_operator_link_lost_returns_to_launch(tmp_path: Path) -> None:
    def operator(t_s: float, runner: Runner) -> None:
        if t_s <= 15.0:
            runner.operator_seen()  # an operator's requests over the network, then silence

    world = _world(60.0, extra="[failsafe]\noperator_timeout_s = 5.0\n")
    run = _mission(tmp_path, world, operator)
    ret = run.first("RUNNING", "failsafe: operator link lost")
    assert ret["reason"].endswith("return to launch")
    assert 15.0 + 5.0 < ret["t_s"] <= 15.0 + 5.5  # the last request + operator_timeout_s
    assert not any("failsafe" in r for t, _n, r in run.mode_changes() if t < 20.0)
    done = run.first("DONE")
    assert done["reason"] == "mode: back at the launch point"
    assert run.final_from_start_m() < 3.0


def test_the_ekf_drives_through_a_short_gps_outage(tmp_path: Path) -> None:
    """The robot's default (gps_outage_max_m = 20): wheels and compass carry it on."""
    run = _mission(tmp_path, _outage_world(120.0, 3.0, outage_max_m=20.0))
    assert not any(s["new"] == "HOLD" and "fix" in s["reason"] for s in run.states)
    assert run.moved_after(OUTAGE_FROM_S + 2.5) > 1.0  # moving while the GPS is out
    assert run.summary.completed and len(run.summary.extra["arrivals"]) == 4


def test_a_long_gps_outage_holds_after_the_dead_reckoning_distance(tmp_path: Path) -> None:
    run = _mission(tmp_path, _outage_world(60.0, 40.0, outage_max_m=10.0))
    hold = run.first("HOLD", "no valid fix")
    # about 10 m of wheel travel (it slows down approaching a waypoint), then the hold
    assert OUTAGE_FROM_S + 3.0 <= hold["t_s"] <= OUTAGE_FROM_S + 20.0
    k = (run.t >= OUTAGE_FROM_S) & (run.t <= hold["t_s"] + 1.5)
    driven_m = float(np.sum(np.hypot(np.diff(run.east[k]), np.diff(run.north[k]))))
    assert 8.0 <= driven_m <= 12.0, driven_m
    assert run.moved_after(hold["t_s"] + 1.5) < 0.05
    paused = run.first("PAUSED", "failsafe: no valid fix")
    assert paused["t_s"] == pytest.approx(hold["t_s"] + SENSOR_TIMEOUT_S, abs=0.1)


# ------------------------------------------------------------------- off course


def _compass_off_world(offset_deg: float) -> World:
    """One 60 m leg north with the compass mounted ``offset_deg`` round (it reads the true
    heading minus the offset: the robot steers that far off by it)."""
    assert "declination_deg = -0.5\n" in DEFAULT
    text = DEFAULT.replace("duration_s = 400.0", "duration_s = 60.0")
    text = text.replace(DEFAULT_WAYPOINTS, f"waypoints_enu = {LONG_LEG}")
    robot = f"robot_declination_deg = {-0.5 - offset_deg}\n"
    text = text.replace("declination_deg = -0.5\n", f"declination_deg = -0.5\n{robot}")
    return loads_world(text, base_dir=SCENARIOS)


def test_a_compass_90_degrees_off_pauses_the_robot_before_it_goes_far(tmp_path: Path) -> None:
    """The robot steers by a compass 90 deg off: it drives sideways while its heading says it
    goes north. The fixes' course shows it: paused, motors stopped, within metres. Either the
    heading check fires (three fresh 10 m windows) or, first, the EKF's jump to the fixes it
    dead-reckoned away from; that reason names the compass too (the heading check's doubt)."""
    run = _mission(tmp_path, _compass_off_world(90.0))
    paused = run.first("PAUSED", "failsafe: ")
    reason = paused["reason"].removeprefix("mode: failsafe: ")
    assert reason.startswith("off course (heading") or (
        reason.startswith("position jumped")
        and "from the compass's heading: a compass fault?)" in reason
    ), reason
    assert paused["t_s"] < 25.0  # three fresh 10 m windows: about 30 m of driving
    ((t_s, why),) = run.summary.extra["failsafes"]  # in the summary, and said by x6wd sim
    assert t_s == pytest.approx(paused["t_s"], abs=1e-3) and why == reason
    assert f"  failsafe            at {t_s:.1f} s: {reason[:20]}" in run.summary.text()
    assert run.mode_changes()[-1][1] == "PAUSED"
    assert run.final_from_start_m() < 45.0
    motors = [m for m in run.of("motor") if m["t_s"] >= paused["t_s"]]
    assert motors and all(m["left_pct"] == m["right_pct"] == 0.0 for m in motors)


def test_a_compass_20_degrees_off_still_completes(tmp_path: Path) -> None:
    run = _mission(tmp_path, _compass_off_world(20.0))
    assert not any("failsafe" in r for _t, _n, r in run.mode_changes())
    assert run.summary.completed


def test_compass_faults_reach_the_recording_as_the_daemons_do(tmp_path: Path) -> None:
    """The simulated loop hands the compass driver's health events to the runner, as the
    daemon's compass thread does: I2C errors are device records, drawn by x6wd plot."""
    text = DEFAULT.replace("duration_s = 400.0", "duration_s = 30.0")
    text = text.replace("declination_deg = -0.5\n", "declination_deg = -0.5\np_error = 0.3\n")
    run = _mission(tmp_path, loads_world(text, base_dir=SCENARIOS))
    devices = [e for e in run.of("event") if e["event"] == "device"]
    assert devices and all(d["device"] == "compass" for d in devices), devices[:3]
    assert {d["new"] for d in devices} >= {"connected", "degraded"}


def test_a_compass_overwhelmed_by_hard_iron_pauses_a_pivot_that_cannot_finish(
    tmp_path: Path,
) -> None:
    """A 30 uT hard iron (stronger than the earth's field): the bearing swings round a fixed
    direction as the body spins, enough for the stuck check's 30 deg of motion, so the robot
    pivoted in place until the mission's time ran out. The pivot's headway check pauses it."""
    text = DEFAULT.replace("duration_s = 400.0", "duration_s = 90.0")
    text = text.replace("start_heading_deg = 0.0\n", "start_heading_deg = 90.0\n")
    text = text.replace(
        "declination_deg = -0.5\n", "declination_deg = -0.5\nhard_iron_ut = [30.0, 0.0, 0.0]\n"
    )
    run = _mission(tmp_path, loads_world(text, base_dir=SCENARIOS))
    paused = run.first("PAUSED", "failsafe: stuck (the pivot: ")
    assert paused["t_s"] < 30.0
    assert run.mode_changes()[-1][1] == "PAUSED"
    motors = [m for m in run.of("motor") if m["t_s"] >= paused["t_s"]]
    assert motors and all(m["left_pct"] == m["right_pct"] == 0.0 for m in motors)
    assert run.moved_after(paused["t_s"] + 1.0) < 0.5


def test_a_compass_that_lags_pauses_for_no_progress_instead_of_swinging_on(
    tmp_path: Path,
) -> None:
    # an outside audit (round 18): a compass whose heading lags 3 s (a heavy filter; the
    # CMPS10's own is 0.21 s) swung the robot left and right about waypoint 2 for 700 m with
    # no failsafe, each pivot gaining its own 10 degrees
    text = DEFAULT.replace("duration_s = 400.0", "duration_s = 200.0")
    assert "[compass]\n" in text
    world = loads_world(text.replace("[compass]\n", "[compass]\nlag_tau_s = 3.0\n"),
                        base_dir=SCENARIOS)  # fmt: skip
    run = _mission(tmp_path, world)
    paused = run.first("PAUSED", "failsafe: no progress to waypoint")
    t = paused["t_s"]
    assert "swinging or circling" in paused["reason"] and t < 150.0, paused
    motors = [m for m in run.of("motor") if m["t_s"] >= t]
    assert motors and all(m["left_pct"] == m["right_pct"] == 0.0 for m in motors)
    assert run.moved_after(t + 1.5) < 0.05
    assert run.summary.completed is False


def test_an_estimate_led_far_astray_under_the_jump_limit_is_a_warning(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    # an outside audit (round 18): a compass 12 uT off its calibration (hard iron) took the
    # robot 20 m off its route on good fixes; the EKF refused them, then jumped 18.7 m onto
    # them, under the 25 m jump failsafe, and only an INFO line said so. Still no pause (the
    # fixes may have jumped), but a WARNING and a line in the summary.
    import logging

    text = DEFAULT.replace("duration_s = 400.0", "duration_s = 200.0")
    world = loads_world(text.replace("[compass]\n", "[compass]\nhard_iron_ut = [0.0, 12.0, 0.0]\n"),
                        base_dir=SCENARIOS)  # fmt: skip
    with caplog.at_level(logging.INFO, logger="x6wd"):
        run = _mission(tmp_path, world)
    surprises = run.summary.extra["ekf_surprise_resets_m"]
    assert surprises and all(10.0 <= m < 25.0 for m in surprises), surprises
    warned = [r for r in caplog.records if "beyond its own 99 % ellipse" in r.getMessage()]
    assert warned and all(r.levelno == logging.WARNING for r in warned)
    assert "EKF resets" in run.summary.text() and "beyond its own ellipse" in run.summary.text()


def test_a_slow_robot_nearing_its_waypoint_is_progress_not_a_failsafe(tmp_path: Path) -> None:
    # a review (round 18): a robot of 0.3 m/s at its 15 % approach speed gained less than
    # 2 m in a minute 3.4 m from waypoint 1 and was paused 1.4 m short of it; near a
    # waypoint half the distance now counts as progress
    text = DEFAULT.replace("duration_s = 400.0", "duration_s = 1000.0")
    world = loads_world(text.replace("[vehicle]\n", "[vehicle]\nmax_speed_mps = 0.3\n"),
                        base_dir=SCENARIOS)  # fmt: skip
    run = _mission(tmp_path, world)
    assert run.summary.extra["failsafes"] == [], run.summary.extra["failsafes"]
    assert run.summary.completed, run.summary.text()
