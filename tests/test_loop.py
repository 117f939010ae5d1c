"""The one loop (x6wd.loop.runner): its rules on a simulated clock, and in a fast-time mission.

The runner is the object the daemon drives in real time and ``x6wd sim`` in simulated time,
so these tests need no sleeps: time is whatever the test says it is.
"""

from __future__ import annotations

import asyncio
import math
from dataclasses import replace
from pathlib import Path
from typing import Any

import pytest

from sim_backend.mission import run_mission
from sim_backend.world import load_world
from x6wd.core.config import NavigationConfig, SafetyConfig
from x6wd.core.errors import CommandError
from x6wd.core.geodesy import great_circle_m
from x6wd.core.health import HealthLog, HealthTracker
from x6wd.core.mission_files import Waypoint
from x6wd.core.records import (
    Attitude,
    GpsFix,
    Mode,
    MotorCommand,
    NavState,
    StateChange,
    Telemetry,
)
from x6wd.loop.runner import TELEMETRY_RECORD_HZ, Runner, run_realtime
from x6wd.nav.controller import Controller

ROOT = Path(__file__).resolve().parent.parent
SCENARIOS = ROOT / "config" / "scenarios"
HOME = (51.7520, -1.2577)
M_PER_DEG_LAT = 111_200.0


class Loop:
    """A runner with a real controller, a simulated clock and list sinks."""

    def __init__(self, safety: SafetyConfig | None = None) -> None:
        self.now = 0.0
        self.motors: list[MotorCommand] = []
        self.records: list[tuple[str, Any]] = []
        self.events: list[dict[str, Any]] = []
        self.states: list[StateChange] = []
        self.safety = safety or SafetyConfig(geofence_radius_m=100.0)
        nav = NavigationConfig(filter_n=3, projection="local_tangent_plane")
        self.runner = Runner(
            Controller(nav, self.safety),
            self.safety,
            lambda: self.now,
            motors=self.motors.append,
            record=lambda m, a: self.records.append((m, a)),
            publish=self.events.append,
            on_state=self.states.append,
            health_log=HealthLog(_quiet(), clock=lambda: self.now),
        )

    def fix(self, north_m: float = 0.0, valid: bool = True) -> None:
        self.runner.gps_record(
            GpsFix(
                t_s=self.now,
                lat_deg=HOME[0] + north_m / M_PER_DEG_LAT,
                lon_deg=HOME[1],
                quality=1 if valid else 0,
                valid=valid,
                sats_used=8,
                hdop=1.0,
            )
        )

    def compass(self, bearing_deg: float = 0.0) -> None:
        self.runner.attitude(Attitude(self.now, bearing_deg, 0.0, 0.0))

    def kinds(self) -> list[str]:
        return [m for m, _a in self.records]


def _quiet() -> Any:
    import logging

    lg = logging.getLogger("tests.loop.health")
    lg.propagate = False
    return lg


def north(m: float) -> Waypoint:
    return Waypoint(HOME[0] + m / M_PER_DEG_LAT, HOME[1])


def test_mission_load_needs_a_geofence_centre_and_every_waypoint_inside() -> None:
    lp = Loop()
    with pytest.raises(CommandError) as exc:
        lp.runner.load_mission([north(10)])
    assert exc.value.code == "geofence" and "no fix yet" in str(exc.value)
    lp.fix()
    assert lp.runner.geofence_centre() == pytest.approx(HOME)
    with pytest.raises(CommandError, match=r"waypoint 2 .* limit 100 m"):
        lp.runner.load_mission([north(10), north(150)])
    assert lp.runner.load_mission([north(10), north(99)]) == {"count": 2}


def test_a_configured_centre_wins_over_the_first_fix() -> None:
    far = (HOME[0] + 1.0, HOME[1])  # ~111 km north
    lp = Loop(SafetyConfig(geofence_radius_m=100.0, geofence_center=far))
    lp.fix()
    assert lp.runner.geofence_centre() == far
    with pytest.raises(CommandError, match="geofence centre"):
        lp.runner.load_mission([north(10)])


def test_a_running_mission_outside_the_geofence_is_stopped_motors_first() -> None:
    lp = Loop()
    lp.fix()
    lp.compass(0.0)
    lp.runner.load_mission([north(90)])
    lp.runner.command("start")
    lp.now = 1.0
    lp.compass(0.0)
    lp.fix(50.0)
    assert lp.runner.controller.mode == Mode.RUNNING and lp.motors[-1].left_pct > 0
    lp.now = 2.0
    lp.compass(0.0)
    n_before = len(lp.motors)
    lp.fix(101.0)  # 101 m from home: outside
    assert lp.runner.geofence_breaches == 1
    assert lp.runner.controller.mode == Mode.IDLE
    first_after = lp.motors[n_before]
    assert first_after.is_stop and first_after.reason == "geofence breach"
    assert all(m.is_stop for m in lp.motors[n_before:])
    assert any(s.reason == "mode: geofence breach" for s in lp.states)
    # starting again out there is refused; manual drive (the way back) is allowed
    lp.runner.load_mission([north(10)])
    with pytest.raises(CommandError, match=r"cannot start.*drive it back by hand"):
        lp.runner.command("start")
    lp.runner.drive(-30.0, -30.0, 2.0)
    assert lp.runner.controller.mode == Mode.MANUAL


def test_the_geofence_edge_is_inclusive() -> None:
    lp = Loop()
    lp.fix()
    lp.compass(0.0)
    lp.runner.load_mission([north(90)])
    lp.runner.command("start")
    lp.now = 1.0
    d_m = great_circle_m(*HOME, HOME[0] + 100.0 / M_PER_DEG_LAT, HOME[1])
    lp.fix(100.0 * 100.0 / d_m - 1e-6)  # just inside 100 m
    assert lp.runner.geofence_breaches == 0 and lp.runner.controller.mode == Mode.RUNNING


def test_manual_drive_limit_and_stop_that_reaches_the_motors_first() -> None:
    lp = Loop(SafetyConfig(manual_max_s=5.0))
    with pytest.raises(CommandError) as exc:
        lp.runner.drive(20.0, 20.0, 5.01)
    assert exc.value.code == "bad_request"
    lp.runner.drive(20.0, 20.0, 5.0)
    assert lp.motors[-1].left_pct == 20.0
    lp.now = 1.0
    n = len(lp.motors)
    lp.runner.stop()
    assert lp.motors[n].reason == "operator stop" and lp.motors[n].is_stop
    assert lp.runner.controller.mode == Mode.IDLE
    lp.now = 1.01
    lp.runner.tick()
    assert lp.motors[-1].is_stop


def test_the_dead_man_and_staleness_act_on_ticks_of_the_injected_clock() -> None:
    lp = Loop(SafetyConfig(manual_max_s=5.0))
    lp.runner.drive(40.0, 40.0, 1.0)
    for k in range(1, 30):
        lp.now = k * 0.05
        lp.runner.tick()
    assert lp.runner.controller.mode == Mode.IDLE and lp.motors[-1].is_stop
    # a running mission holds once the fix is older than fix_stale_s
    lp2 = Loop()
    lp2.fix()
    lp2.compass()
    lp2.runner.load_mission([north(50)])
    lp2.runner.command("start")
    stale_s = lp2.safety.fix_stale_s
    t = 0.0
    while t < stale_s + 0.2:
        t += 0.05
        lp2.now = t
        lp2.compass()
        lp2.runner.tick()
    assert lp2.runner.controller.state == NavState.HOLD
    assert lp2.runner.last_telemetry is not None
    assert lp2.runner.last_telemetry.hold_reason == "fix stale"


def test_a_sensor_reported_down_holds_at_once() -> None:
    lp = Loop()
    lp.fix()
    lp.compass()
    lp.runner.load_mission([north(50)])
    lp.runner.command("start")
    lp.now = 0.1
    tracker = HealthTracker("gps", t_s=0.0)
    tracker.opened(0.0)
    tracker.lost("unplugged", 0.1)
    lp.runner.device_events(tracker.take_events())
    assert lp.runner.controller.state == NavState.HOLD and lp.motors[-1].is_stop


def test_outputs_are_routed_and_telemetry_is_rate_limited_but_forced_by_fixes() -> None:
    lp = Loop()
    lp.fix()
    for k in range(1, 41):  # 2 s of compass samples at 20 Hz
        lp.now = k * 0.05
        lp.compass()
    kinds = lp.kinds()
    assert kinds.count("record_attitude") == 40 and kinds.count("record_fix") == 1
    n_tel = kinds.count("record_telemetry")
    # one forced by the fix, then at most TELEMETRY_RECORD_HZ per second of compass samples
    assert 1 < n_tel <= 1 + 2 * TELEMETRY_RECORD_HZ + 1
    # motor records only when the command changes
    assert kinds.count("record_motor") == 1
    assert all(e["event"] in ("telemetry", "state") for e in lp.events)
    assert isinstance(lp.runner.last_telemetry, Telemetry)


def test_a_tick_at_the_time_of_the_last_step_is_skipped() -> None:
    lp = Loop()
    lp.compass()
    n = len(lp.motors)
    lp.runner.tick(0.0)
    assert len(lp.motors) == n
    lp.runner.tick(0.05)
    assert len(lp.motors) == n + 1


def test_run_realtime_ticks_until_stopped_and_a_failing_task_propagates() -> None:
    lp = Loop()

    async def go() -> int:
        stop = asyncio.Event()
        loop = asyncio.get_running_loop()
        lp.runner.clock = loop.time
        loop.call_later(0.25, stop.set)
        await run_realtime(lp.runner, stop, tick_hz=40.0)
        return len(lp.motors)

    assert asyncio.run(go()) >= 3

    async def failing() -> None:
        raise RuntimeError("injected")

    async def go_fail() -> None:
        await run_realtime(lp.runner, asyncio.Event(), tick_hz=40.0, tasks=[failing])

    with pytest.raises(ExceptionGroup) as eg:
        asyncio.run(go_fail())
    assert eg.group_contains(RuntimeError, match="injected")


# -- the same rules in a fast-time mission ------------------------------------------------
def test_fast_time_mission_loads_through_the_geofence_and_is_refused_beyond_it(
    tmp_path: Path,
) -> None:
    world = load_world(SCENARIOS / "default.toml")
    small = replace(world, safety=replace(world.safety, geofence_radius_m=20.0))
    s = run_mission(small, tmp_path / "refused", duration_s=30.0)
    assert not s.completed and s.path_length_m < 0.5
    assert s.extra["mission_rejected"].startswith("geofence:")
    assert "waypoint" in s.extra["mission_rejected"]


def test_fast_time_mission_is_stopped_when_it_leaves_the_geofence(tmp_path: Path) -> None:
    world = load_world(SCENARIOS / "default.toml")
    # The four waypoints (a 25 m square) lie within 17.7 m of its centre, but the robot
    # turns only once inside a 3 m arrival window and reads a fix with metres of error, so a
    # 19 m fence around the centre is crossed at a corner: the mission is stopped there.
    o = world.origin
    m_per_deg_lon = M_PER_DEG_LAT * math.cos(math.radians(o.lat_deg))
    centre = (o.lat_deg + 12.5 / M_PER_DEG_LAT, o.lon_deg + 12.5 / m_per_deg_lon)
    fence = replace(world.safety, geofence_radius_m=19.0, geofence_center=centre)
    s = run_mission(replace(world, safety=fence), tmp_path / "breach")
    assert s.extra["mission_rejected"] is None
    if s.extra["geofence_breaches"] == 0:
        pytest.fail(f"the robot never left the 19 m fence: {s.text()}")
    assert not s.completed
