"""The sans-IO controller: outputs per call, HOLD safety, operator requests, determinism."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from x6wd.core.config import NavigationConfig, SafetyConfig
from x6wd.core.errors import X6wdError
from x6wd.core.records import (
    Attitude,
    ControllerOutput,
    GpsFix,
    GpsSky,
    Mode,
    MotorCommand,
    NavState,
    SatInfo,
    StateChange,
    Telemetry,
)
from x6wd.nav import geo
from x6wd.nav.constellation import Constellation
from x6wd.nav.controller import CommandRejected, Controller, InputError

NAV = NavigationConfig.paper(cruise_pct=60.0, turn_pct=40.0, delta_phi_deg=10.0)
SAFETY = SafetyConfig(fix_stale_s=2.5, attitude_stale_s=0.5, manual_max_s=5.0)
ORIGIN = (51.7, 30.0)
LTP = geo.LocalTangentPlane(*ORIGIN)


def at(x_m: float, y_m: float) -> tuple[float, float]:
    """(lat, lon) of a point x_m east and y_m north of ORIGIN (true metres)."""
    lat, lon = LTP.to_latlon(x_m, y_m)
    return float(lat), float(lon)


def fix(t_s: float, x_m: float = 0.0, y_m: float = 0.0, valid: bool = True) -> GpsFix:
    lat, lon = at(x_m, y_m)
    if not valid:
        return GpsFix(t_s=t_s, valid=False, quality=0, mode=1)
    return GpsFix(t_s=t_s, lat_deg=lat, lon_deg=lon, valid=True, quality=1, mode=3, hdop=1.2)


def att(t_s: float, bearing_deg: float = 0.0, valid: bool = True) -> Attitude:
    return Attitude(t_s=t_s, bearing_deg=bearing_deg, pitch_deg=1.0, roll_deg=-2.0, valid=valid)


def split(outs: list[ControllerOutput]) -> tuple[list[StateChange], MotorCommand, Telemetry]:
    """Check the output contract and return (state changes, command, telemetry)."""
    assert len(outs) >= 2
    assert isinstance(outs[-1], Telemetry)
    assert isinstance(outs[-2], MotorCommand)
    changes = outs[:-2]
    assert all(isinstance(c, StateChange) for c in changes)
    return changes, outs[-2], outs[-1]  # type: ignore[return-value]


def running(
    waypoints: list[tuple[float, float]] | None = None,
    t_s: float = 0.0,
    nav: NavigationConfig = NAV,
) -> Controller:
    c = Controller(nav, SAFETY)
    c.load_mission(waypoints or [at(0.0, 100.0)], t_s)
    c.start(t_s)
    return c


def test_every_call_returns_command_and_telemetry() -> None:
    c = Controller(NAV, SAFETY)
    calls = [
        lambda: c.tick(0.0),
        lambda: c.on_fix(fix(0.1)),
        lambda: c.on_sky(GpsSky(t_s=0.2, satellites=(SatInfo(5, 40.0, 120.0, 38.0, True),))),
        lambda: c.on_attitude(att(0.3)),
        lambda: c.load_mission([at(0, 50)], 0.4),
        lambda: c.start(0.5),
        lambda: c.pause(0.6),
        lambda: c.resume(0.7),
        lambda: c.stop(0.8),
        lambda: c.manual_drive(10, 20, 1.0, 0.9),
        lambda: c.motor_link(True, 1.0),
        lambda: c.sensor_health("gps", False, 1.1, "disconnected"),
        lambda: c.sensor_health("gps", True, 1.2, "connected"),
    ]
    for call in calls:
        _, cmd, tel = split(call())
        assert tel is c.telemetry
        assert (tel.left_pct, tel.right_pct) == (cmd.left_pct, cmd.right_pct)
        assert cmd.t_s == tel.t_s
    assert c.telemetry.extra["sats_in_view"] == 1


def test_straight_and_turn_mixing() -> None:
    c = running()  # target 100 m north
    c.on_fix(fix(1.0))
    _, cmd, tel = split(c.on_attitude(att(1.0, 0.0)))
    assert tel.state == NavState.STRAIGHT and (cmd.left_pct, cmd.right_pct) == (60.0, 60.0)
    _, cmd, tel = split(c.on_attitude(att(1.1, 300.0)))  # heading -60: target is clockwise
    # the right side, forward until now, stops before it reverses (REVERSE_STOP_S)
    assert tel.state == NavState.TURN_RIGHT and (cmd.left_pct, cmd.right_pct) == (40.0, 0.0)
    assert cmd.reason == "TURN_RIGHT; stop before reversing"
    _, cmd, tel = split(c.on_attitude(att(1.6, 300.0)))
    assert tel.state == NavState.TURN_RIGHT and (cmd.left_pct, cmd.right_pct) == (40.0, -40.0)
    assert cmd.reason == "TURN_RIGHT"
    _, cmd, tel = split(c.on_attitude(att(1.7, 60.0)))  # the other way: both sides reverse
    assert tel.state == NavState.TURN_LEFT and (cmd.left_pct, cmd.right_pct) == (0.0, 0.0)
    _, cmd, tel = split(c.on_attitude(att(2.2, 60.0)))
    assert tel.state == NavState.TURN_LEFT and (cmd.left_pct, cmd.right_pct) == (-40.0, 40.0)
    assert tel.target_bearing_deg == pytest.approx(0.0, abs=1e-6)
    assert tel.theta_deg == pytest.approx(-60.0, abs=1e-6)
    assert tel.distance_m == pytest.approx(100.0, rel=0.01)  # two-radius north is ~true metres


def test_declination_turns_magnetic_into_true() -> None:
    # Target due (true) north; the compass reads 355 magnetic with 7 deg east declination:
    # true heading +2 -> straight. Without declination -5 -> still straight; at 345 magnetic the
    # true heading is -8 with declination (straight) but -15 without (turn right).
    with_decl = Controller(NAV, SAFETY, declination_deg=7.0)
    without = Controller(NAV, SAFETY, declination_deg=0.0)
    for c in (with_decl, without):
        c.load_mission([at(0.0, 100.0)], 0.0)
        c.start(0.0)
        c.on_fix(fix(0.5))
    assert split(with_decl.on_attitude(att(1.0, 345.0)))[2].state == NavState.STRAIGHT
    assert split(without.on_attitude(att(1.0, 345.0)))[2].state == NavState.TURN_RIGHT
    assert with_decl.telemetry.heading_deg == pytest.approx(-8.0)
    assert with_decl.telemetry.bearing_deg == 345.0


def test_hold_until_inputs_are_fresh_then_resume() -> None:
    c = running()
    changes, cmd, tel = split(c.tick(0.1))
    assert tel.state == NavState.HOLD and cmd.is_stop and tel.hold_reason == "no fix yet"
    c.on_fix(fix(1.0))
    assert c.telemetry.hold_reason == "no attitude yet"
    _, cmd, tel = split(c.on_attitude(att(1.0)))
    assert tel.state == NavState.STRAIGHT and not cmd.is_stop
    # attitude older than 0.5 s -> HOLD
    _, cmd, tel = split(c.tick(1.6))
    assert tel.state == NavState.HOLD and tel.hold_reason == "attitude stale" and cmd.is_stop
    _, cmd, tel = split(c.on_attitude(att(1.7)))
    assert tel.state == NavState.STRAIGHT
    # fix older than 2.5 s -> HOLD (keep the attitude fresh)
    c.on_attitude(att(3.4))
    _, cmd, tel = split(c.on_attitude(att(3.6)))
    assert tel.state == NavState.HOLD and tel.hold_reason == "fix stale" and cmd.is_stop
    assert tel.fix_age_s == pytest.approx(2.6)
    _, cmd, tel = split(c.on_fix(fix(3.7)))
    assert tel.state == NavState.STRAIGHT and not cmd.is_stop
    # an invalid fix holds at once, even though the last valid one is fresh
    changes, cmd, tel = split(c.on_fix(fix(3.8, valid=False)))
    assert tel.hold_reason == "no valid fix" and cmd.is_stop
    assert [(s.old, s.new) for s in changes] == [("STRAIGHT", "HOLD")]
    c.on_attitude(att(3.9))
    c.on_fix(fix(4.0))
    assert c.state == NavState.STRAIGHT
    # an invalid compass sample holds too
    _, cmd, tel = split(c.on_attitude(att(4.1, valid=False)))
    assert tel.hold_reason == "attitude invalid" and cmd.is_stop
    assert c.mode == Mode.RUNNING  # HOLD never changes what the operator asked for


def test_staleness_limits_are_configurable() -> None:
    safety = replace(SAFETY, attitude_stale_s=2.0)
    c = Controller(NAV, safety)
    c.load_mission([at(0.0, 100.0)], 0.0)
    c.start(0.0)
    c.on_fix(fix(1.0))
    c.on_attitude(att(1.0))
    assert split(c.tick(2.9))[2].state == NavState.STRAIGHT  # 1.9 s: still fresh
    assert split(c.tick(3.1))[2].state == NavState.HOLD


def test_motor_link_loss_holds_and_cancels_manual() -> None:
    c = running()
    c.on_fix(fix(1.0))
    c.on_attitude(att(1.0))
    _, cmd, tel = split(c.motor_link(False, 1.1))
    assert tel.state == NavState.HOLD and tel.hold_reason == "motor link lost" and cmd.is_stop
    _, cmd, tel = split(c.motor_link(True, 1.2))
    assert tel.state == NavState.STRAIGHT and not cmd.is_stop
    c.stop(1.3)
    c.manual_drive(50, 50, 3.0, 1.4)
    changes, cmd, tel = split(c.motor_link(False, 1.5))
    assert cmd.is_stop and tel.mode == Mode.IDLE
    assert any(s.new == "IDLE" and "link" in s.reason for s in changes)
    with pytest.raises(CommandRejected, match="motor link"):
        c.manual_drive(50, 50, 3.0, 1.6)


def test_filtered_position_ignores_an_outlier_per_axis() -> None:
    c = running([at(0.0, 200.0)])
    ref_lat, ref_lon = Constellation(NAV.filter_n), Constellation(NAV.filter_n)
    rng = np.random.default_rng(4)
    fixes = [fix(float(i), float(rng.normal(0, 0.5)), float(rng.normal(0, 0.5))) for i in range(8)]
    fixes[5] = fix(5.0, 80.0, -60.0)  # a multipath jump
    for f in fixes:
        _, _, tel = split(c.on_fix(f))
        assert f.lat_deg is not None and f.lon_deg is not None
        ref_lat.add(f.lat_deg)
        ref_lon.add(f.lon_deg)
        assert tel.filt_lat_deg == ref_lat.filter()
        assert tel.filt_lon_deg == ref_lon.filter()
        assert tel.lat_deg == f.lat_deg
    x, y = LTP.to_xy(c.telemetry.filt_lat_deg or 0.0, c.telemetry.filt_lon_deg or 0.0)
    assert math.hypot(float(x), float(y)) < 3.0
    # invalid fixes do not enter the filter
    n_before = c.telemetry.extra["filter_samples"]
    c.on_fix(fix(9.0, valid=False))
    c.on_fix(GpsFix(t_s=9.5, lat_deg=None, lon_deg=30.0, valid=True, quality=1))
    assert c.telemetry.extra["filter_samples"] == n_before


def _drive(c: Controller, start_xy: tuple[float, float], seconds: float) -> list[NavState]:
    """A crude skid-steer robot in true metres: 60 % = 1 m/s, 40 % spin = 45 deg/s."""
    x, y = start_xy
    heading = 0.0  # true, degrees clockwise from north
    states = []
    dt = 0.1
    for i in range(int(seconds / dt)):
        t = i * dt
        if i % 10 == 0:
            states.append(split(c.on_fix(fix(t, x, y)))[2].state)
        _, cmd, tel = split(c.on_attitude(att(t, heading % 360.0)))
        states.append(tel.state)
        if c.mode == Mode.DONE:
            break
        v = (cmd.left_pct + cmd.right_pct) / 2 / 60.0  # m/s
        w = (cmd.left_pct - cmd.right_pct) / 2 / 40.0 * 45.0  # deg/s, clockwise positive
        heading += w * dt
        x += v * dt * math.sin(math.radians(heading))
        y += v * dt * math.cos(math.radians(heading))
    return states


@pytest.mark.parametrize("projection", ["two_radius", "local_tangent_plane"])
def test_closed_loop_mission_reaches_every_waypoint(projection: str) -> None:
    nav = replace(NAV, projection=projection, filter_n=3)
    c = Controller(nav, SAFETY)
    wps = [at(0.0, 30.0), at(25.0, 30.0), at(25.0, 0.0)]
    c.load_mission(wps, 0.0)
    c.start(0.0)
    states = _drive(c, (0.0, 0.0), 400.0)
    assert c.mode == Mode.DONE and c.state == NavState.MISSION_DONE
    assert states.count(NavState.ARRIVED) == 2
    assert NavState.TURN_RIGHT in states  # the square is driven clockwise
    assert c.telemetry.waypoint_index is None and c.telemetry.waypoint_count == 3
    _, cmd, _ = split(c.tick(500.0))
    assert cmd.is_stop


def test_same_inputs_same_outputs() -> None:
    def run() -> list[ControllerOutput]:
        c = Controller(NAV, SAFETY, declination_deg=3.0)
        outs: list[ControllerOutput] = []
        outs += c.load_mission([at(0.0, 30.0), at(20.0, 30.0)], 0.0)
        outs += c.start(0.0)
        rng = np.random.default_rng(9)
        for i in range(200):
            t = i * 0.1
            if i % 10 == 0:
                outs += c.on_fix(fix(t, float(rng.normal(0, 2)), float(rng.normal(0, 2))))
            outs += c.on_attitude(att(t, float(rng.uniform(0, 360))))
            if i == 120:
                outs += c.pause(t)
            if i == 140:
                outs += c.resume(t)
        return outs

    first, second = run(), run()
    assert len(first) > 400
    assert first == second


def test_operator_requests_follow_the_mode_rules() -> None:
    c = Controller(NAV, SAFETY)
    with pytest.raises(CommandRejected, match="no mission"):
        c.start(0.0)
    with pytest.raises(CommandRejected, match="nothing to pause"):
        c.pause(0.0)
    with pytest.raises(CommandRejected, match="nothing to resume"):
        c.resume(0.0)
    c.load_mission([at(0, 10)], 0.0)
    changes, _, tel = split(c.start(0.1))
    assert tel.mode == Mode.RUNNING and changes[0].old == "IDLE" and changes[0].new == "RUNNING"
    with pytest.raises(CommandRejected, match="already running"):
        c.start(0.2)
    with pytest.raises(CommandRejected, match="stop first"):
        c.load_mission([at(0, 20)], 0.2)
    with pytest.raises(CommandRejected, match="stop the mission first"):
        c.manual_drive(10, 10, 1.0, 0.2)
    _, cmd, tel = split(c.pause(0.3))
    assert tel.mode == Mode.PAUSED and cmd.is_stop
    with pytest.raises(CommandRejected, match="resume"):
        c.start(0.4)
    split(c.resume(0.5))
    assert c.mode == Mode.RUNNING
    _, cmd, tel = split(c.stop(0.6))
    assert tel.mode == Mode.IDLE and tel.state == NavState.IDLE and cmd.is_stop
    split(c.stop(0.7))  # stop is always accepted, even when idle
    assert c.mode == Mode.IDLE


@pytest.mark.parametrize(
    ("waypoints", "match"),
    [
        ([], "at least one"),
        ([(95.0, 0.0)], "latitude"),
        ([(51.7, 30.0), (51.7, math.nan)], "waypoint 1"),
        ([(51.7,)], "expected"),
        (None, "sequence"),
    ],
)
def test_bad_missions_are_rejected_and_change_nothing(waypoints: object, match: str) -> None:
    c = Controller(NAV, SAFETY)
    c.load_mission([at(0, 10)], 0.0)
    before = c.telemetry
    with pytest.raises(CommandRejected, match=match):
        c.load_mission(waypoints, 1.0)  # type: ignore[arg-type]
    assert c.telemetry is before
    assert c.waypoints == (at(0, 10),)
    assert issubclass(CommandRejected, X6wdError)


@pytest.mark.parametrize(
    ("left", "right", "duration", "match"),
    [
        (101, 0, 1.0, "left_pct"),
        (0, -100.5, 1.0, "right_pct"),
        (math.nan, 0, 1.0, "left_pct"),
        ("50", 0, 1.0, "left_pct"),
        (10, 10, 0.0, "duration_s"),
        (10, 10, math.inf, "duration_s"),
    ],
)
def test_bad_manual_requests_are_rejected(
    left: object, right: object, duration: float, match: str
) -> None:
    c = Controller(NAV, SAFETY)
    with pytest.raises(CommandRejected, match=match):
        c.manual_drive(left, right, duration, 0.0)  # type: ignore[arg-type]
    assert c.mode == Mode.IDLE and c.command.is_stop


def test_manual_drive_is_capped_and_expires() -> None:
    c = Controller(NAV, SAFETY)
    changes, cmd, tel = split(c.manual_drive(30, -20, 60.0, 10.0))  # asks 60 s, cap 5 s
    assert tel.mode == Mode.MANUAL and (cmd.left_pct, cmd.right_pct) == (30.0, -20.0)
    assert [(s.old, s.new) for s in changes] == [("IDLE", "MANUAL")]
    _, cmd, _ = split(c.tick(14.9))
    assert (cmd.left_pct, cmd.right_pct) == (30.0, -20.0)
    changes, cmd, tel = split(c.tick(15.0))
    assert cmd.is_stop and tel.mode == Mode.IDLE
    assert changes[0].new == "IDLE" and "expired" in changes[0].reason
    # a refreshed command extends the dead-man from the new time
    c.manual_drive(10, 10, 1.0, 20.0)
    c.manual_drive(10, 10, 1.0, 20.8)
    assert not split(c.tick(21.5))[1].is_stop
    assert split(c.tick(21.8))[1].is_stop


def test_stop_ends_manual_drive_and_start_overrides_it() -> None:
    c = Controller(NAV, SAFETY)
    c.manual_drive(50, 50, 3.0, 0.0)
    _, cmd, tel = split(c.stop(0.5))
    assert cmd.is_stop and tel.mode == Mode.IDLE
    c.load_mission([at(0, 10)], 0.6)
    c.manual_drive(50, 50, 3.0, 0.7)
    _, cmd, tel = split(c.start(0.8))
    assert tel.mode == Mode.RUNNING and tel.state == NavState.HOLD and cmd.is_stop


def test_time_never_goes_backwards_and_must_be_finite() -> None:
    c = Controller(NAV, SAFETY)
    c.tick(10.0)
    _, cmd, tel = split(c.on_fix(fix(9.5)))  # a record stamped earlier than "now"
    assert tel.t_s == 10.0 and tel.fix_age_s == pytest.approx(0.5)
    with pytest.raises(InputError, match="finite"):
        c.tick(math.nan)
    _, cmd, tel = split(c.stop(math.nan))  # stop still works
    assert cmd.is_stop and tel.t_s == 10.0


def test_mission_done_then_reload_goes_idle() -> None:
    c = Controller(NAV, SAFETY)
    c.load_mission([at(0.0, 1.0)], 0.0)
    c.start(0.0)
    c.on_fix(fix(0.1))
    changes, cmd, tel = split(c.on_attitude(att(0.2)))
    assert tel.mode == Mode.DONE and tel.state == NavState.MISSION_DONE and cmd.is_stop
    assert [(s.old, s.new) for s in changes] == [("RUNNING", "DONE"), ("HOLD", "MISSION_DONE")]
    changes, _, tel = split(c.load_mission([at(0.0, 50.0)], 0.3))
    assert tel.mode == Mode.IDLE and tel.waypoint_index == 0
    split(c.start(0.4))
    assert c.state == NavState.STRAIGHT


# ---------------------------------------------------------------- memoised geometry
# The controller caches the projected position and the heading between calls and reuses the
# navigator's own bearing/deviation for the telemetry; every snapshot must still be exactly
# what a from-scratch computation gives, whatever changed in between.


def _expected_geometry(c: Controller) -> tuple[float | None, ...]:
    """(x, y, heading_deg, target_deg, theta_deg, distance) computed from scratch."""
    nav = c.navigator
    tel = c.telemetry
    heading = None
    if tel.bearing_deg is not None and c.attitude_ok:
        heading = nav.heading_from_compass(tel.bearing_deg)
    if tel.filt_lat_deg is None or tel.filt_lon_deg is None or not c.waypoints:
        return (None, None, None if heading is None else math.degrees(heading), None, None, None)
    x, y = (float(v) for v in nav.projection.to_xy(tel.filt_lat_deg, tel.filt_lon_deg))
    target = theta = dist = None
    if not nav.done:
        xi, yi = nav.target_xy()
        dist = math.hypot(xi - x, yi - y)
        if dist > 0:
            phi = geo.destination_bearing(x, y, xi, yi)
            target = math.degrees(phi)
            if heading is not None:
                theta = math.degrees(geo.course_deviation(phi, heading))
    return (x, y, None if heading is None else math.degrees(heading), target, theta, dist)


def _geometry(tel: Telemetry) -> tuple[float | None, ...]:
    return (tel.x_m, tel.y_m, tel.heading_deg, tel.target_bearing_deg, tel.theta_deg,
            tel.distance_m)  # fmt: skip


@pytest.mark.parametrize("proj", ["two_radius", "local_tangent_plane"])
def test_telemetry_geometry_is_recomputed_whenever_an_input_changes(proj: str) -> None:
    rng = np.random.default_rng(11)
    square = [at(0, 30), at(30, 30), at(30, 0)]
    c = running(square, nav=replace(NAV, projection=proj))
    t = 0.0
    for k in range(600):
        t += 0.05
        r = rng.random()
        if r < 0.08:
            _, _, tel = split(c.on_fix(fix(t, *rng.normal(10.0, 12.0, 2))))
        elif r < 0.09:
            # Declination changes on the live navigator must reach the heading.
            c.navigator.declination_deg = float(rng.uniform(-10, 10))
            _, _, tel = split(c.tick(t))
        elif r < 0.10:
            # A new mission brings a new navigator and its projection (stop first).
            c.stop(t)
            c.load_mission(list(rng.permutation(square)), t)
            _, _, tel = split(c.start(t))
        elif r < 0.11:
            _, _, tel = split(c.on_attitude(att(t, 400.0)))  # invalid bearing: no heading
        else:
            _, _, tel = split(c.on_attitude(att(t, float(rng.uniform(0, 360)))))
        assert _geometry(tel) == _expected_geometry(c), k


def test_snapshot_reuses_the_navigators_decision_only_for_the_same_inputs() -> None:
    c = running([at(0.0, 100.0), at(50.0, 100.0)])
    c.on_fix(fix(0.0, 0.0, 0.0))
    _, _, tel = split(c.on_attitude(att(0.05, 90.0)))
    last = c.navigator.last
    assert last is not None and last.theta_rad is not None and last.phi_i_rad is not None
    assert tel.theta_deg == math.degrees(last.theta_rad)
    assert tel.target_bearing_deg == math.degrees(last.phi_i_rad)
    assert tel.distance_m == last.distance_m
    # Arriving moves the target on: the snapshot must describe the NEXT waypoint.
    c.on_fix(fix(0.1, 0.0, 100.0))
    c.on_fix(fix(0.2, 0.0, 100.0))
    c.on_fix(fix(0.3, 0.0, 100.0))
    _, _, tel = split(c.on_attitude(att(0.35, 90.0)))
    assert tel.waypoint_index == 1
    assert tel.distance_m is not None and tel.distance_m > 40.0  # 50 m east, projected
    assert _geometry(tel) == _expected_geometry(c)


def driving(t_s: float = 1.0) -> Controller:
    """A running mission with fresh inputs, driving straight at ``t_s``."""
    c = running()
    c.on_fix(fix(t_s))
    c.on_attitude(att(t_s))
    assert c.state == NavState.STRAIGHT
    return c


@pytest.mark.parametrize(
    ("kind", "state"),
    [("gps", "disconnected"), ("gps", "reconnecting"), ("gps", "stale"),
     ("compass", "stale"), ("compass", "disconnected")],
)  # fmt: skip
def test_sensor_unusable_holds_at_once_naming_the_device(kind: str, state: str) -> None:
    c = driving(1.0)
    # everything is fresh (fix and attitude 0.05 s old): only the reader's word can hold
    changes, cmd, tel = split(c.sensor_health(kind, False, 1.05, state))
    assert tel.state == NavState.HOLD and cmd.is_stop
    assert tel.hold_reason == f"{kind} {state}"
    assert [(s.old, s.new, s.reason) for s in changes] == [
        ("STRAIGHT", "HOLD", f"state: {kind} {state}")
    ]
    assert tel.extra["sensors_down"] == {kind: state}
    assert c.mode == Mode.RUNNING
    # fresh data while the reader says the device is down does not resume
    c.on_fix(fix(1.1))
    c.on_attitude(att(1.1))
    assert c.state == NavState.HOLD and c.telemetry.hold_reason == f"{kind} {state}"


def test_gps_back_resumes_only_on_a_fix_stamped_after_its_return() -> None:
    c = driving(1.0)
    c.sensor_health("gps", False, 1.2, "disconnected")
    c.sensor_health("gps", False, 1.3, "reconnecting")
    assert c.telemetry.hold_reason == "gps reconnecting"
    _, cmd, tel = split(c.sensor_health("gps", True, 1.5, "connected"))
    assert tel.state == NavState.HOLD and cmd.is_stop
    assert tel.hold_reason == "gps back, waiting for a fresh fix"
    assert "sensors_down" not in tel.extra
    c.on_attitude(att(1.6))
    c.on_fix(fix(1.45))  # decoded before the return (a queued record): not fresh
    c.on_fix(fix(1.7, valid=False))  # after it, but no fix
    assert c.state == NavState.HOLD and c.telemetry.hold_reason.startswith("gps back")
    _, cmd, tel = split(c.on_fix(fix(1.8)))
    assert tel.state == NavState.STRAIGHT and not cmd.is_stop and tel.hold_reason == ""


def test_compass_back_resumes_only_on_a_valid_sample_after_its_return() -> None:
    c = driving(1.0)
    c.sensor_health("compass", False, 1.1, "stale")
    c.sensor_health("compass", True, 1.3, "degraded")  # degraded data is usable
    assert c.telemetry.hold_reason == "compass back, waiting for a fresh sample"
    c.on_fix(fix(1.35))
    c.on_attitude(att(1.0))  # the driver's held last-good sample keeps its old time
    c.on_attitude(att(1.35, valid=False))
    assert c.state == NavState.HOLD
    assert split(c.on_attitude(att(1.4)))[2].state == NavState.STRAIGHT


def test_a_usable_report_for_a_usable_sensor_changes_nothing() -> None:
    c = driving(1.0)
    # connected -> degraded -> connected: never down, so no wait for fresh data either
    assert split(c.sensor_health("compass", True, 1.1, "degraded"))[2].state == NavState.STRAIGHT
    assert split(c.sensor_health("gps", True, 1.2, "connected"))[2].state == NavState.STRAIGHT


def test_both_sensors_down_name_the_gps_first_then_the_compass() -> None:
    c = driving(1.0)
    c.sensor_health("compass", False, 1.1, "stale")
    c.sensor_health("gps", False, 1.2, "disconnected")
    assert c.telemetry.hold_reason == "gps disconnected"
    assert c.telemetry.extra["sensors_down"] == {"gps": "disconnected", "compass": "stale"}
    c.sensor_health("gps", True, 1.3)
    c.on_fix(fix(1.4))
    assert c.telemetry.hold_reason == "compass stale"
    c.motor_link(False, 1.5)
    assert c.telemetry.hold_reason == "motor link lost"  # the motors come first


def test_manual_drive_does_not_depend_on_the_sensors() -> None:
    # Decision: the operator drives by sight; the dead-man and the motor link protect it.
    c = Controller(NAV, SAFETY)
    c.sensor_health("gps", False, 0.5, "disconnected")
    _, cmd, tel = split(c.manual_drive(30, 30, 2.0, 1.0))
    assert tel.mode == Mode.MANUAL and (cmd.left_pct, cmd.right_pct) == (30.0, 30.0)
    _, cmd, tel = split(c.sensor_health("compass", False, 1.5, "stale"))
    assert tel.mode == Mode.MANUAL and not cmd.is_stop and tel.hold_reason == ""


def test_sensor_health_rejects_unknown_devices_and_bad_times() -> None:
    c = Controller(NAV, SAFETY)
    with pytest.raises(InputError, match="kind"):
        c.sensor_health("motors", False, 1.0)
    with pytest.raises(InputError, match="finite"):
        c.sensor_health("gps", False, math.nan)
