"""The geofence against one wild fix (outside audit 10a, finding A, medium).

In a street canyon the simulated NEO-5 gave three RMC-only fixes (status A) 1.7-3.5 km off
with HDOP 99.99 while the robot was 66-68 m from its start; the loop checked every usable fix
against the 1000 m fence and paused the mission ("geofence breach"). Now a fix is a breach
by itself only when its HDOP is under 20 (``MEANINGLESS_HDOP``: from it on no fix) and the
EKF took it; the estimate after it, and ``FENCE_FIXES_IN_ROW`` usable fixes in a row
outside, are breaches whatever the EKF says. A robot that really drives out is still stopped
at once.

The first tests drive a runner with the robot's own controller (EKF) on a simulated clock: a
scripted robot rolls north at 1 m/s (wheels, compass and fixes agree), whatever the motors
are told. The last one is a whole fast-time mission with the robot's defaults.
"""

from __future__ import annotations

import csv
import json
import logging
import math
from pathlib import Path
from typing import Any

import numpy as np

from sim_backend.geodesy import enu_to_lla
from sim_backend.mission import run_mission
from sim_backend.world import loads_world
from x6wd.core.config import NavigationConfig, OdometryConfig, SafetyConfig
from x6wd.core.geodesy import great_circle_m
from x6wd.core.health import HealthLog
from x6wd.core.mission_files import Waypoint
from x6wd.core.records import Attitude, GpsFix, Mode, MotorCommand, StateChange, WheelOdometry
from x6wd.loop.runner import Runner
from x6wd.nav.controller import Controller

ROOT = Path(__file__).resolve().parent.parent
HOME = (51.7520, -1.2577)
M_PER_DEG_LAT = 111_200.0
M_PER_DEG_LON = M_PER_DEG_LAT * math.cos(math.radians(HOME[0]))
FENCE_M = 100.0
STEP_S = 0.05  # odometry and compass period (s); a fix every whole second


def _quiet() -> logging.Logger:
    lg = logging.getLogger("tests.geofence_wild_fix")
    lg.propagate = False
    return lg


class Robot:
    """A runner with the robot's controller (EKF) and a scripted robot rolling north."""

    def __init__(self, safety: SafetyConfig | None = None) -> None:
        self.now = 0.0
        self.north_m = 0.0
        self.motors: list[MotorCommand] = []
        self.states: list[StateChange] = []
        safety = safety or SafetyConfig(geofence_radius_m=FENCE_M)
        odo = OdometryConfig()
        self.m_per_count = math.pi / odo.counts_per_rev * odo.left_diameter_m
        self.runner = Runner(
            Controller(NavigationConfig(), safety, odometry=odo),
            safety,
            lambda: self.now,
            motors=self.motors.append,
            on_state=self.states.append,
            health_log=HealthLog(_quiet(), clock=lambda: self.now),
        )

    def fix(self, north_m: float, east_m: float = 0.0, hdop: float = 1.2, gga: bool = True) -> None:
        """A valid fix at ``north_m``/``east_m`` (m from home); ``gga`` False: from RMC
        alone (quality 0, no satellite count), as the decoder gives when it drops the GGA."""
        self.runner.gps_record(
            GpsFix(
                t_s=self.now,
                lat_deg=HOME[0] + north_m / M_PER_DEG_LAT,
                lon_deg=HOME[1] + east_m / M_PER_DEG_LON,
                quality=1 if gga else 0,
                sats_used=7 if gga else None,
                hdop=hdop,
                valid=True,
            )
        )

    def roll(self, seconds: float, speed_mps: float, wild: dict[int, Any] | None = None) -> None:
        """``seconds`` of rolling north at ``speed_mps``; at whole second ``s`` the fix is
        ``wild[s]`` (keyword arguments of :meth:`fix`) instead of the true position."""
        for _ in range(round(seconds / STEP_S)):
            self.now = round(self.now + STEP_S, 6)
            self.north_m += speed_mps * STEP_S
            counts = round(self.north_m / self.m_per_count)
            self.runner.odometry(WheelOdometry(self.now, counts, counts, 0))
            self.runner.attitude(Attitude(self.now, 0.0, 0.0, 0.0))
            if abs(self.now - round(self.now)) < 1e-9:
                s = round(self.now)
                if wild is not None and s in wild:
                    self.fix(**wild[s])
                else:
                    self.fix(self.north_m)

    def started(self) -> Robot:
        """Settled at home, then a mission 95 m north started and 30 m driven."""
        self.fix(0.0)
        self.roll(3.0, 0.0)
        self.runner.load_mission([Waypoint(HOME[0] + 95.0 / M_PER_DEG_LAT, HOME[1])])
        self.runner.command("start")
        self.roll(30.0, 1.0)
        assert self.runner.controller.mode == Mode.RUNNING, self.states
        assert self.motors[-1].left_pct > 0
        return self

    def ekf_refused(self) -> int:
        n = self.runner.controller.telemetry.extra["ekf_gps_rejected"]
        assert isinstance(n, int)
        return n


def _offset(north_m: float, east_m: float, **kw: Any) -> dict[str, Any]:
    return {"north_m": north_m, "east_m": east_m, **kw}


def test_meaningless_fixes_far_outside_are_no_breach() -> None:
    """The audit's seed 1: three RMC-only fixes with HDOP 99.99, 2.9-3.5 km off, in a row
    (the fence is 100 m here): the mission drives on."""
    bot = Robot().started()
    t0 = round(bot.now)
    wild = {
        t0 + 1: _offset(-3237.0, 1214.0, hdop=99.99, gga=False),
        t0 + 2: _offset(-2904.0, 1093.0, hdop=99.99, gga=False),
        t0 + 3: _offset(-2752.0, 1039.0, hdop=99.99, gga=False),
    }
    bot.roll(5.0, 1.0, wild)
    assert bot.runner.geofence_breaches == 0
    assert bot.runner.controller.mode == Mode.RUNNING, bot.states
    assert not any("geofence" in m.reason for m in bot.motors)
    assert bot.motors[-1].left_pct > 0  # still driving


def test_a_fix_the_ekf_refuses_is_no_breach_but_three_in_a_row_are() -> None:
    """A good-looking fix 3 km off that the EKF refuses is no breach; meaningful fixes
    outside three times in a row (``FENCE_FIXES_IN_ROW``) are, though the EKF refuses each (a robot
    really out there whose estimate will not follow): stopped before the third can steer."""
    bot = Robot().started()
    refused = bot.ekf_refused()
    t0 = round(bot.now)
    bot.roll(3.0, 1.0, {t0 + 1: _offset(3000.0, 0.0)})
    assert bot.ekf_refused() == refused + 1  # the premise: the EKF refused it
    assert bot.runner.geofence_breaches == 0
    assert bot.runner.controller.mode == Mode.RUNNING, bot.states

    t0 = round(bot.now)
    far = _offset(0.0, 300.0)
    bot.roll(2.0, 1.0, {t0 + 1: far, t0 + 2: far})  # two in a row: not yet
    assert bot.runner.controller.mode == Mode.RUNNING, bot.states
    assert bot.ekf_refused() == refused + 3
    n_before = len(bot.motors)
    bot.now += 1.0
    bot.fix(**far)  # the third
    assert bot.runner.geofence_breaches == 1
    assert bot.runner.controller.mode == Mode.PAUSED
    after = bot.motors[n_before:]
    assert after and after[0].is_stop and after[0].reason == "geofence breach"
    assert all(m.is_stop for m in after)
    assert any(s.reason == "mode: failsafe: geofence breach" for s in bot.states)


def test_a_good_fix_outside_that_the_ekf_takes_is_a_breach_at_once() -> None:
    """The fence's edge 1 m east of the robot: one good fix 2.5 m beyond it, which the EKF
    takes while its estimate stays inside, pauses the mission at that fix; the drive the
    fix's step decided never reaches the motors."""
    centre_n_m, centre_e_m, radius_m = 15.0, -499.0, 500.0  # edge: 0.97 m east at 15 m N
    centre = (HOME[0] + centre_n_m / M_PER_DEG_LAT, HOME[1] + centre_e_m / M_PER_DEG_LON)
    bot = Robot(SafetyConfig(geofence_radius_m=radius_m, geofence_center=centre))
    bot.fix(0.0)
    bot.roll(3.0, 0.0)
    bot.runner.load_mission([Waypoint(HOME[0] + 30.0 / M_PER_DEG_LAT, HOME[1])])
    bot.runner.command("start")
    bot.roll(15.0, 1.0)
    assert bot.runner.controller.mode == Mode.RUNNING, bot.states
    refused, n_before = bot.ekf_refused(), len(bot.motors)
    bot.now += 1.0
    bot.north_m += 1.0
    bot.fix(bot.north_m, 3.5)
    tel = bot.runner.controller.telemetry
    assert tel.filt_lat_deg is not None and tel.filt_lon_deg is not None
    # the premises: the EKF took the fix, and its estimate stays inside
    assert bot.ekf_refused() == refused
    assert great_circle_m(*centre, tel.filt_lat_deg, tel.filt_lon_deg) < radius_m
    assert bot.runner.geofence_breaches == 1
    assert bot.runner.controller.mode == Mode.PAUSED
    after = bot.motors[n_before:]
    assert after and after[0].is_stop and after[0].reason == "geofence breach"
    assert all(m.is_stop for m in after)


def test_a_fix_inside_ends_the_run_of_fixes_outside() -> None:
    """Two fixes outside, one inside, two outside: no three in a row, no breach."""
    bot = Robot().started()
    t0 = round(bot.now)
    far = _offset(0.0, 300.0)
    bot.roll(5.0, 1.0, {t0 + 1: far, t0 + 2: far, t0 + 4: far, t0 + 5: far})
    assert bot.runner.geofence_breaches == 0
    assert bot.runner.controller.mode == Mode.RUNNING, bot.states


# -- a real crossing, fast time --------------------------------------------------------------

SCENARIO = (ROOT / "config" / "scenarios" / "default.toml").read_text(encoding="utf-8")
ORIGIN = (51.7520, -1.2577, 60.0)  # default.toml's [origin]


def test_a_robot_that_really_drives_out_is_stopped_within_seconds(tmp_path: Path) -> None:
    """The robot's defaults (EKF, 1 Hz fixes with the scenario's noise): a fence whose edge
    runs (nearly straight) 1.5 m west of the start and of the one waypoint 30 m north; the
    robot starts facing 310 deg, under the pivot angle, so it arcs out west before it
    follows the leg. Paused within 3 s of truly leaving (measured 1.5 s), under 3 m out
    (1.8 m). Fails with the geofence check taken out of the runner."""
    lat, lon, _alt = enu_to_lla(np.array([1000.0, 15.0, 0.0]), *ORIGIN)
    centre = (float(lat), float(lon))
    radius = great_circle_m(*centre, ORIGIN[0], ORIGIN[1]) + 1.5
    waypoints = "waypoints_enu = [[0.0, 25.0], [25.0, 25.0], [25.0, 0.0], [5.0, 0.0]]"
    assert waypoints in SCENARIO and "start_heading_deg = 0.0\n" in SCENARIO
    text = (
        SCENARIO.replace("duration_s = 400.0", "duration_s = 60.0")
        .replace(waypoints, "waypoints_enu = [[0.0, 30.0]]")
        .replace("start_heading_deg = 0.0\n", "start_heading_deg = 310.0\n")
    )
    extra = (
        f"[safety]\ngeofence_radius_m = {radius!r}\n"
        f"geofence_center = [{centre[0]!r}, {centre[1]!r}]\n"
        '[failsafe]\ngeofence_action = "hold"\n'
    )
    world = loads_world(text + "\n" + extra, base_dir=ROOT / "config" / "scenarios")
    summary = run_mission(world, tmp_path)
    records = [json.loads(x) for x in (tmp_path / "recording.jsonl").open(encoding="utf-8")]
    with (tmp_path / "truth.csv").open(newline="") as f:
        rows = list(csv.DictReader(f))
    t = np.array([float(r["t_s"]) for r in rows])
    out_m = np.array(
        [great_circle_m(*centre, float(r["lat"]), float(r["lon"])) - radius for r in rows]
    )
    assert (out_m > 0.5).any(), "premise: the robot never truly left the fence"
    t_out = float(t[np.argmax(out_m > 0.0)])
    pauses = [
        r["data"]
        for r in records
        if r["type"] == "state" and r["data"]["reason"].startswith("mode: failsafe: geofence")
    ]
    assert pauses, [r["data"] for r in records if r["type"] == "state"]
    t_pause = pauses[0]["t_s"]
    assert t_pause - t_out < 3.0, (t_out, t_pause)
    assert summary.extra["geofence_breaches"] >= 1 and not summary.completed
    assert float(out_m.max()) < 3.0
