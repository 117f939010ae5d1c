"""The controller's safety contract to the letter: holds and their reasons, staleness limits
at their exact boundaries, fix and compass validity, the manual dead-man, stop from any state
and the time stamps of every output. Written against the mutants `tools/mutate controller`
found surviving (docs/testing.md, "Mutation testing"); sans-IO, so every time is given."""

from __future__ import annotations

import math
from dataclasses import replace
from typing import Any

import numpy as np
import pytest

from tests.test_controller import NAV, SAFETY, at, att, driving, fix, running, split
from x6wd.core.records import (
    GpsFix,
    GpsSky,
    Mode,
    MotorCommand,
    NavState,
    SatInfo,
    Telemetry,
)
from x6wd.nav.constellation import Constellation
from x6wd.nav.controller import CommandRejected, Controller, InputError

ORIGIN_LAT = 51.7
SKY = GpsSky(t_s=0.0, satellites=(SatInfo(5, 40.0, 120.0, 38.0, True),))


def changes_of(outs: list[Any]) -> list[tuple[float, str, str, str]]:
    return [(s.t_s, s.old, s.new, s.reason) for s in split(outs)[0]]


def test_a_new_controller_commands_a_stop() -> None:
    c = Controller(NAV, SAFETY)
    assert c.command == MotorCommand(0.0, 0.0, 0.0, "idle")
    assert c.telemetry == Telemetry(t_s=0.0, mode=Mode.IDLE, state=NavState.IDLE)


# -- time -----------------------------------------------------------------------------------
ENTRY_POINTS = {
    "fix": lambda c, t: c.on_fix(replace(fix(1.0), t_s=t)),
    "sky": lambda c, t: c.on_sky(replace(SKY, t_s=t)),
    "attitude": lambda c, t: c.on_attitude(replace(att(1.0), t_s=t)),
    "tick": lambda c, t: c.tick(t),
    "motor_link": lambda c, t: c.motor_link(True, t),
    "sensor_health": lambda c, t: c.sensor_health("gps", True, t),
    "load_mission": lambda c, t: c.load_mission([at(0, 10)], t),
    "start": lambda c, t: c.start(t),
    "pause": lambda c, t: c.pause(t),
    "resume": lambda c, t: c.resume(t),
    "manual_drive": lambda c, t: c.manual_drive(10, 10, 1.0, t),
}


@pytest.mark.parametrize("name", list(ENTRY_POINTS))
@pytest.mark.parametrize(("bad", "problem"), [(math.nan, "finite"), ("soon", "a number")])
def test_every_input_with_a_bad_time_is_refused_naming_the_call(
    name: str, bad: object, problem: str
) -> None:
    c = Controller(NAV, SAFETY)
    with pytest.raises(InputError, match=rf"^{name}: t_s must be {problem}"):
        ENTRY_POINTS[name](c, bad)
    assert c.command.is_stop and c.mode == Mode.IDLE


def test_stop_never_fails_and_stamps_the_latest_time() -> None:
    _, cmd, tel = split(Controller(NAV, SAFETY).stop(math.nan))  # the very first call
    assert cmd == MotorCommand(0.0, 0.0, 0.0, "idle") and tel.t_s == 0.0
    c = Controller(NAV, SAFETY)
    c.manual_drive(50, 50, 3.0, 10.0)
    changes = changes_of(c.stop(12.0))  # a valid time is used, not the controller's old one
    assert changes == [(12.0, "MANUAL", "IDLE", "mode: stop")]
    assert c.command == MotorCommand(12.0, 0.0, 0.0, "idle")
    c.manual_drive(50, 50, 3.0, 12.5)
    changes = changes_of(c.stop("garbage"))  # type: ignore[arg-type]
    assert changes == [(12.5, "MANUAL", "IDLE", "mode: stop")]
    assert c.command.is_stop and c.command.t_s == 12.5


def test_outputs_of_a_late_input_carry_the_controllers_time() -> None:
    c = Controller(NAV, SAFETY)
    c.tick(10.0)
    assert changes_of(c.manual_drive(20, 20, 1.0, 9.0)) == [
        (10.0, "IDLE", "MANUAL", "mode: manual drive")
    ]
    # the dead-man runs from the controller's "now" (10 s), not from the late stamp (9 s)
    assert not split(c.tick(10.9))[1].is_stop
    assert split(c.tick(11.0))[1].is_stop


# -- what the robot reports while it runs ----------------------------------------------------
def test_a_session_reports_every_mode_and_state_change_with_its_time_and_reason() -> None:
    c = Controller(NAV, SAFETY)
    c.load_mission([at(0.0, 100.0)], 0.0)

    def step(outs: list[Any], changes: list[tuple[float, str, str, str]], cmd: MotorCommand):
        assert changes_of(outs) == changes
        assert split(outs)[1] == cmd

    step(c.start(1.0), [(1.0, "IDLE", "RUNNING", "mode: start"),
                        (1.0, "IDLE", "HOLD", "state: no fix yet")],
         MotorCommand(1.0, 0.0, 0.0, "hold: no fix yet"))  # fmt: skip
    step(c.on_fix(fix(1.5)), [], MotorCommand(1.5, 0.0, 0.0, "hold: no attitude yet"))
    step(c.on_attitude(att(2.0)), [(2.0, "HOLD", "STRAIGHT", "state: attitude")],
         MotorCommand(2.0, 60.0, 60.0, "STRAIGHT"))  # fmt: skip
    step(c.tick(2.6), [(2.6, "STRAIGHT", "HOLD", "state: attitude stale")],
         MotorCommand(2.6, 0.0, 0.0, "hold: attitude stale"))  # fmt: skip
    step(c.on_attitude(att(2.7)), [(2.7, "HOLD", "STRAIGHT", "state: attitude")],
         MotorCommand(2.7, 60.0, 60.0, "STRAIGHT"))  # fmt: skip
    step(c.motor_link(False, 2.8), [(2.8, "STRAIGHT", "HOLD", "state: motor link lost")],
         MotorCommand(2.8, 0.0, 0.0, "hold: motor link lost"))  # fmt: skip
    step(c.motor_link(True, 2.9), [(2.9, "HOLD", "STRAIGHT", "state: motor link up")],
         MotorCommand(2.9, 60.0, 60.0, "STRAIGHT"))  # fmt: skip
    step(c.pause(3.0), [(3.0, "RUNNING", "PAUSED", "mode: pause"),
                        (3.0, "STRAIGHT", "IDLE", "state: pause")],
         MotorCommand(3.0, 0.0, 0.0, "paused"))  # fmt: skip
    step(c.resume(3.1), [(3.1, "PAUSED", "RUNNING", "mode: resume"),
                         (3.1, "IDLE", "STRAIGHT", "state: resume")],
         MotorCommand(3.1, 60.0, 60.0, "STRAIGHT"))  # fmt: skip
    step(c.on_fix(fix(3.2, valid=False)), [(3.2, "STRAIGHT", "HOLD", "state: no valid fix")],
         MotorCommand(3.2, 0.0, 0.0, "hold: no valid fix"))  # fmt: skip
    c.on_attitude(att(3.25))
    step(c.on_fix(fix(3.3)), [(3.3, "HOLD", "STRAIGHT", "state: fix")],
         MotorCommand(3.3, 60.0, 60.0, "STRAIGHT"))  # fmt: skip
    step(c.stop(3.4), [(3.4, "RUNNING", "IDLE", "mode: stop"),
                       (3.4, "STRAIGHT", "IDLE", "state: stop")],
         MotorCommand(3.4, 0.0, 0.0, "idle"))  # fmt: skip
    step(c.manual_drive(20, -20, 1.0, 3.5), [(3.5, "IDLE", "MANUAL", "mode: manual drive")],
         MotorCommand(3.5, 0.0, 0.0, "manual; stop before reversing"))  # fmt: skip
    step(c.tick(4.5), [(4.5, "MANUAL", "IDLE", "mode: manual drive expired")],
         MotorCommand(4.5, 0.0, 0.0, "idle"))  # fmt: skip
    c.manual_drive(10, 10, 2.0, 5.0)
    step(c.motor_link(False, 5.5),
         [(5.5, "MANUAL", "IDLE", "mode: manual drive cancelled: motor link lost")],
         MotorCommand(5.5, 0.0, 0.0, "idle"))  # fmt: skip


def test_start_and_manual_drive_name_themselves_in_the_state_change() -> None:
    c = Controller(NAV, SAFETY)
    c.load_mission([at(0.0, 100.0)], 0.0)
    c.on_fix(fix(0.1))
    c.on_attitude(att(0.2))  # fresh inputs before the start: no hold
    assert changes_of(c.start(0.3)) == [
        (0.3, "IDLE", "RUNNING", "mode: start"),
        (0.3, "IDLE", "STRAIGHT", "state: start"),
    ]
    c.stop(0.4)
    c.load_mission([at(0.0, 1.0)], 0.5)
    c.start(0.6)
    c.on_attitude(att(0.7))  # at the only waypoint: done
    assert c.mode == Mode.DONE
    assert changes_of(c.manual_drive(10, 10, 1.0, 0.8)) == [
        (0.8, "DONE", "MANUAL", "mode: manual drive"),
        (0.8, "MISSION_DONE", "IDLE", "state: manual drive"),
    ]


def test_mission_done_and_reload_report_their_changes() -> None:
    c = Controller(NAV, SAFETY)
    c.load_mission([at(0.0, 1.0)], 0.0)
    c.start(0.0)
    c.on_fix(fix(0.1))
    outs = c.on_attitude(att(0.2))
    assert changes_of(outs) == [
        (0.2, "RUNNING", "DONE", "mode: last waypoint reached"),
        (0.2, "HOLD", "MISSION_DONE", "state: attitude"),
    ]
    assert split(outs)[1] == MotorCommand(0.2, 0.0, 0.0, "done")
    assert changes_of(c.load_mission([at(0.0, 50.0)], 0.3)) == [
        (0.3, "DONE", "IDLE", "mode: mission loaded"),
        (0.3, "MISSION_DONE", "IDLE", "state: mission loaded"),
    ]


NEXT_INPUT = {
    "tick": (lambda c: c.tick(0.2), "tick"),
    "sky": (lambda c: c.on_sky(replace(SKY, t_s=0.2)), "sky"),
    "attitude": (lambda c: c.on_attitude(att(0.2)), "attitude"),
    "fix": (lambda c: c.on_fix(fix(0.2)), "fix"),
    "motor link": (lambda c: c.motor_link(True, 0.2), "motor link up"),
    "gps report": (lambda c: c.sensor_health("gps", True, 0.2, "connected"), "gps connected"),
    "compass report": (lambda c: c.sensor_health("compass", True, 0.2), "compass ok"),
}


@pytest.mark.parametrize("name", list(NEXT_INPUT))
def test_any_input_after_an_arrival_turns_to_the_next_waypoint(name: str) -> None:
    c = Controller(NAV, SAFETY)
    c.load_mission([at(0.0, 1.0), at(0.0, 100.0)], 0.0)
    c.start(0.0)
    c.on_attitude(att(0.0))
    outs = c.on_fix(fix(0.1))  # 1 m from the first waypoint: arrived
    assert changes_of(outs) == [(0.1, "HOLD", "ARRIVED", "state: fix")]
    assert split(outs)[1] == MotorCommand(0.1, 0.0, 0.0, "ARRIVED")
    call, why = NEXT_INPUT[name]
    outs = call(c)
    assert changes_of(outs) == [(0.2, "ARRIVED", "STRAIGHT", f"state: {why}")]
    assert split(outs)[1] == MotorCommand(0.2, 60.0, 60.0, "STRAIGHT")


# -- holds -----------------------------------------------------------------------------------
def test_a_fix_exactly_fix_stale_s_old_is_fresh_and_older_holds() -> None:
    c = running()
    c.on_fix(fix(1.0))
    _, cmd, tel = split(c.on_attitude(att(3.5)))  # the fix is exactly 2.5 s old
    assert tel.state == NavState.STRAIGHT and not cmd.is_stop and tel.fix_age_s == 2.5
    _, cmd, tel = split(c.on_attitude(att(3.5 + 1e-6)))
    assert tel.hold_reason == "fix stale" and cmd == MotorCommand(
        3.5 + 1e-6, 0, 0, "hold: fix stale"
    )


def test_an_attitude_exactly_attitude_stale_s_old_is_fresh_and_older_holds() -> None:
    c = running()
    c.on_attitude(att(1.0))
    _, cmd, tel = split(c.on_fix(fix(1.5)))  # the attitude is exactly 0.5 s old
    assert tel.state == NavState.STRAIGHT and tel.attitude_age_s == 0.5
    _, cmd, tel = split(c.tick(1.5 + 1e-6))
    assert tel.hold_reason == "attitude stale" and cmd.is_stop


def test_the_attitude_age_counts_from_the_last_good_sample() -> None:
    """A compass stale from I2C errors: its reader hands on invalid samples stamped with the
    time of each read; the age shown keeps growing from the last good one (it read 0.00 s)."""
    c = running()
    c.on_attitude(att(1.0))
    for t in (1.1, 1.6, 2.5):
        c.on_fix(fix(t))
        _, cmd, tel = split(c.on_attitude(att(t, valid=False)))
    assert tel.attitude_age_s == pytest.approx(1.5) and tel.hold_reason == "attitude invalid"
    assert cmd.is_stop
    _, _, tel = split(c.on_attitude(att(2.6)))
    assert tel.attitude_age_s == 0.0
    c = Controller(NAV, SAFETY)
    assert c.on_attitude(att(1.0, valid=False))[-1].attitude_age_s is None  # none good yet


def test_a_late_fix_does_not_make_the_position_look_older() -> None:
    c = running()
    c.on_attitude(att(5.0))
    c.on_fix(fix(5.0))
    _, _, tel = split(c.on_fix(fix(4.0)))  # decoded late: stamped before the last one
    assert tel.fix_age_s == 0.0 and tel.state == NavState.STRAIGHT
    _, _, tel = split(c.on_attitude(att(7.4)))
    assert tel.fix_age_s == pytest.approx(2.4) and tel.state == NavState.STRAIGHT


def test_no_valid_fix_ever_is_no_fix_yet_even_after_an_invalid_one() -> None:
    c = running()
    c.on_attitude(att(0.1))
    _, cmd, tel = split(c.on_fix(fix(0.2, valid=False)))
    assert tel.hold_reason == "no fix yet" and cmd.is_stop


def test_an_invalid_fix_with_coordinates_holds_and_stays_out_of_the_filter() -> None:
    # a receiver that lost its fix may still print its last position (RMC status V)
    c = driving(1.0)
    lat, lon = at(0.0, 30.0)
    n = c.telemetry.extra["filter_samples"]
    stale = GpsFix(t_s=1.1, lat_deg=lat, lon_deg=lon, valid=False, quality=0, mode=1)
    _, cmd, tel = split(c.on_fix(stale))
    assert tel.hold_reason == "no valid fix" and cmd.is_stop
    assert tel.extra["filter_samples"] == n
    assert tel.lat_deg == lat  # still reported as received


@pytest.mark.parametrize(
    ("lat", "lon", "usable"),
    [(90.0, 0.0, True), (-90.0, 0.0, True), (0.0, 180.0, True), (0.0, -180.0, True),
     (90.000001, 0.0, False), (-90.000001, 0.0, False), (0.0, 180.000001, False),
     (0.0, -180.000001, False), (90.5, 0.0, False), (0.0, 180.5, False),
     (math.nan, 0.0, False), (0.0, math.inf, False), (None, 0.0, False), (0.0, None, False)],
)  # fmt: skip
def test_a_fix_is_usable_only_with_coordinates_on_the_globe(
    lat: float | None, lon: float | None, usable: bool
) -> None:
    c = Controller(NAV, SAFETY)
    c.on_fix(fix(0.0))
    _, _, tel = split(c.on_fix(GpsFix(t_s=1.0, lat_deg=lat, lon_deg=lon, valid=True, quality=1)))
    assert tel.extra["filter_samples"] == (2 if usable else 1)
    assert (tel.fix_age_s == 0.0) is usable


@pytest.mark.parametrize(
    ("bearing", "usable"),
    [(0.0, True), (359.999, True), (360.0, False), (360.5, False), (-0.001, False),
     (math.nan, False), (math.inf, False)],
)  # fmt: skip
def test_a_compass_bearing_is_usable_only_in_0_to_360(bearing: float, usable: bool) -> None:
    c = driving(1.0)
    _, cmd, tel = split(c.on_attitude(att(1.1, bearing)))
    assert (tel.hold_reason == "") is usable
    if not usable:
        assert tel.hold_reason == "attitude invalid" and cmd.is_stop and tel.heading_deg is None


def test_a_sensor_back_resumes_on_data_stamped_exactly_at_its_return() -> None:
    c = driving(1.0)
    c.sensor_health("gps", False, 1.2, "disconnected")
    c.sensor_health("gps", True, 1.5, "connected")
    c.on_attitude(att(1.5))
    assert c.telemetry.hold_reason == "gps back, waiting for a fresh fix"
    assert split(c.on_fix(fix(1.5)))[2].state == NavState.STRAIGHT
    c.sensor_health("compass", False, 1.6, "stale")
    c.sensor_health("compass", True, 1.7, "connected")
    c.on_fix(fix(1.7))
    assert c.telemetry.hold_reason == "compass back, waiting for a fresh sample"
    assert split(c.on_attitude(att(1.7)))[2].state == NavState.STRAIGHT


def test_a_sensor_reported_down_without_a_state_is_unavailable() -> None:
    c = driving(1.0)
    _, cmd, tel = split(c.sensor_health("compass", False, 1.1))
    assert tel.hold_reason == "compass unavailable" and cmd.is_stop
    assert tel.extra["sensors_down"] == {"compass": "unavailable"}


def test_a_lost_motor_link_shows_in_telemetry_in_every_mode() -> None:
    c = Controller(NAV, SAFETY)
    assert "motor_link" not in c.tick(0.0)[-1].extra
    _, cmd, tel = split(c.motor_link(False, 1.0))
    assert tel.extra["motor_link"] == "lost" and cmd.is_stop and tel.mode == Mode.IDLE
    assert "motor_link" not in split(c.motor_link(True, 2.0))[2].extra


# -- manual drive ----------------------------------------------------------------------------
def test_manual_drive_takes_full_power_both_ways() -> None:
    c = Controller(NAV, SAFETY)
    _, cmd, _ = split(c.manual_drive(-100, 100, 1.0, 0.0))
    assert (cmd.left_pct, cmd.right_pct) == (-100.0, 100.0)
    _, cmd, _ = split(c.manual_drive(100.0, -100.0, 1.0, 0.1))
    # both sides flip: each stops for REVERSE_STOP_S first, the operator's drive too
    assert (cmd.left_pct, cmd.right_pct) == (0.0, 0.0)
    assert cmd.reason == "manual; stop before reversing"
    _, cmd, _ = split(c.tick(0.6))
    assert (cmd.left_pct, cmd.right_pct) == (100.0, -100.0) and cmd.reason == "manual"


@pytest.mark.parametrize(
    ("left", "right", "duration", "message"),
    [(101, 0, 1.0, r"^left_pct must be a number in \[-100, 100\], got 101$"),
     (0, -101, 1.0, r"^right_pct must be a number in \[-100, 100\], got -101$"),
     (10, 10, True, r"^duration_s must be a positive number, got True$"),
     (10, 10, "5", r"^duration_s must be a positive number, got '5'$"),
     (10, 10, -1.0, r"^duration_s must be a positive number, got -1.0$")],
)  # fmt: skip
def test_bad_manual_requests_say_what_is_wrong(
    left: object, right: object, duration: object, message: str
) -> None:
    c = Controller(NAV, SAFETY)
    with pytest.raises(CommandRejected, match=message):
        c.manual_drive(left, right, duration, 0.0)  # type: ignore[arg-type]
    assert c.mode == Mode.IDLE and c.command.is_stop


def test_rejections_say_why() -> None:
    c = Controller(NAV, SAFETY)
    with pytest.raises(CommandRejected, match=r"^no mission loaded$"):
        c.start(0.0)
    c.motor_link(False, 0.0)
    with pytest.raises(CommandRejected, match=r"^motor link lost: cannot drive$"):
        c.manual_drive(10, 10, 1.0, 0.1)
    c.motor_link(True, 0.2)
    c.load_mission([at(0.0, 10.0)], 0.3)
    c.start(0.4)
    with pytest.raises(CommandRejected, match=r"^mission already running$"):
        c.start(0.5)
    c.pause(0.6)
    with pytest.raises(
        CommandRejected, match=r"^mission paused: resume it, or stop before starting again$"
    ):
        c.start(0.7)
    with pytest.raises(CommandRejected, match=r"^declination must be in"):
        Controller(NAV, SAFETY, declination_deg=200.0)


# -- filter and telemetry --------------------------------------------------------------------
def test_the_filters_hysteresis_setting_is_used_on_both_axes() -> None:
    rng = np.random.default_rng(3)
    pos = [at(float(x), float(y)) for x, y in rng.normal(0.0, 2.0, (40, 2))]
    refs = {h: (Constellation(5, h), Constellation(5, h)) for h in (False, True)}
    outs: dict[bool, list[tuple[float, float]]] = {h: [] for h in refs}
    c = Controller(replace(NAV, filter_n=5, filter_hysteresis=True), SAFETY)
    for i, (lat, lon) in enumerate(pos):
        tel = split(c.on_fix(GpsFix(t_s=float(i), lat_deg=lat, lon_deg=lon, valid=True)))[2]
        for h, (flat, flon) in refs.items():
            flat.add(lat)
            flon.add(lon)
            outs[h].append((flat.filter(), flon.filter()))
        assert (tel.filt_lat_deg, tel.filt_lon_deg) == outs[True][-1]
    # the data tells the two settings apart, on each axis
    for axis in (0, 1):
        assert [o[axis] for o in outs[True]] != [o[axis] for o in outs[False]]


def test_telemetry_reports_the_latest_inputs_as_given() -> None:
    c = Controller(NAV, SAFETY)
    tel = c.tick(0.0)[-1]
    assert (tel.waypoint_count, tel.fix_quality, tel.lat_deg, tel.bearing_deg) == (0, 0, None, None)
    lat, lon = at(0.0, 0.0)
    c.on_fix(GpsFix(t_s=1.0, lat_deg=lat, lon_deg=lon, valid=True, quality=2, sats_used=7,
                    hdop=0.9))  # fmt: skip
    _, _, tel = split(c.on_attitude(att(1.25, 90.0)))
    assert (tel.lat_deg, tel.lon_deg, tel.fix_quality, tel.sats_used, tel.hdop) == (
        lat, lon, 2, 7, 0.9
    )  # fmt: skip
    assert (tel.bearing_deg, tel.pitch_deg, tel.roll_deg) == (90.0, 1.0, -2.0)
    assert (tel.fix_age_s, tel.attitude_age_s) == (0.25, 0.0)
    _, _, tel = split(c.tick(1.5))
    assert tel.attitude_age_s == 0.25
    # a mission loaded but not started: the way to its first waypoint is reported
    c.load_mission([at(0.0, 0.5)], 1.6)
    tel = c.telemetry
    assert tel.waypoint_count == 1 and tel.target_bearing_deg == pytest.approx(0.0, abs=1e-6)
    c.load_mission([(lat, lon)], 1.7)  # standing on it: distance 0, no bearing to it
    tel = c.telemetry
    assert tel.distance_m == 0.0 and tel.target_bearing_deg is None and tel.theta_deg is None


# -- pivot_arc: what the wheels do and what the operator sees ---------------------------------
# Written against the `_mix` and `_snapshot` survivors of the steering mode: the numbers below
# are the docs/navigation.md formulas worked by hand (pure pursuit κ = 2·sin α / d towards the
# lookahead point, the approach speed, left = s·(1 + κT/2), right = s·(1 − κT/2), both scaled
# down together when a side would pass 100 %), not a call of the code under test.
ARC = replace(
    NAV,
    steering="pivot_arc",
    cruise_pct=60.0,
    turn_pct=40.0,
    delta_x_m=1.0,
    delta_y_m=1.0,
    lookahead_m=8.0,
    approach_m=10.0,
    min_speed_pct=15.0,
    steer_track_m=2.0,
)
STEER_KEYS = {"steer_alpha_deg", "curvature_per_m", "speed_pct", "pivoting"}


def arc_decision(
    nav: Any = ARC,
    *,
    north_m: float = 0.0,
    bearing_deg: float = 0.0,
    east_m: float = 0.0,
    waypoints: list[tuple[float, float]] | None = None,
) -> tuple[Controller, MotorCommand, Telemetry]:
    """A pivot_arc mission towards 100 m north; the first decision (which starts the leg, so
    the robot is on the leg's line) at (east_m, north_m) with the compass at bearing_deg."""
    c = Controller(nav, SAFETY)
    c.load_mission(waypoints or [at(0.0, 100.0)], 0.0)
    c.start(0.0)
    c.on_fix(fix(1.0, east_m, north_m))
    _, cmd, tel = split(c.on_attitude(att(1.0, bearing_deg)))
    return c, cmd, tel


def mixed(speed: float, curvature: float, track_m: float) -> tuple[float, float]:
    k = curvature * track_m / 2.0
    left, right = speed * (1.0 + k), speed * (1.0 - k)
    peak = max(abs(left), abs(right))
    return (left, right) if peak <= 100.0 else (100.0 * left / peak, 100.0 * right / peak)


@pytest.mark.parametrize(("bearing", "alpha_deg"), [(340.0, 20.0), (20.0, -20.0), (0.0, 0.0)])
def test_arc_percentages_at_cruise_with_their_sign_per_side(
    bearing: float, alpha_deg: float
) -> None:
    # 100 m from the waypoint: cruise speed; the lookahead point 8 m ahead on the line
    _, cmd, tel = arc_decision(bearing_deg=bearing)
    k = 2.0 * math.sin(math.radians(alpha_deg)) / 8.0
    assert tel.state == NavState.STRAIGHT and cmd.reason == "STRAIGHT"
    assert (cmd.left_pct, cmd.right_pct) == pytest.approx((60.0 * (1 + k), 60.0 * (1 - k)))
    if alpha_deg > 0:  # waypoint to the right: the left side drives faster
        assert cmd.left_pct == pytest.approx(65.130302, abs=1e-5)
        assert cmd.right_pct == pytest.approx(54.869698, abs=1e-5)
    elif alpha_deg < 0:
        assert cmd.left_pct == pytest.approx(54.869698, abs=1e-5)
        assert cmd.right_pct == pytest.approx(65.130302, abs=1e-5)
    else:
        assert (cmd.left_pct, cmd.right_pct) == pytest.approx((60.0, 60.0))
    assert (tel.left_pct, tel.right_pct) == (cmd.left_pct, cmd.right_pct)
    assert set(tel.extra) == {"filter_samples", *STEER_KEYS}
    assert tel.extra["steer_alpha_deg"] == pytest.approx(alpha_deg, abs=1e-9)
    assert tel.extra["curvature_per_m"] == pytest.approx(k, abs=1e-12)
    assert tel.extra["speed_pct"] == 60.0 and tel.extra["pivoting"] is False


@pytest.mark.parametrize("track_m", [0.5, 2.0, 4.95])
def test_arc_percentages_use_steer_track_m(track_m: float) -> None:
    _, cmd, _ = arc_decision(replace(ARC, steer_track_m=track_m), bearing_deg=340.0)
    k = 2.0 * math.sin(math.radians(20.0)) / 8.0
    assert (cmd.left_pct, cmd.right_pct) == pytest.approx(mixed(60.0, k, track_m))
    assert cmd.left_pct - cmd.right_pct == pytest.approx(60.0 * k * track_m)


def test_arc_on_the_approach_drives_at_the_approach_speed() -> None:
    # 5 m before the waypoint (approach_m 10): 60 % × 5/10 = 30 %; the target is the
    # waypoint itself, 5 m away
    _, cmd, tel = arc_decision(north_m=95.0, bearing_deg=340.0)
    k = 2.0 * math.sin(math.radians(20.0)) / 5.0
    assert tel.state == NavState.STRAIGHT
    assert (cmd.left_pct, cmd.right_pct) == pytest.approx((30.0 * (1 + k), 30.0 * (1 - k)))
    assert cmd.left_pct == pytest.approx(34.104242, abs=1e-5)
    assert tel.extra["speed_pct"] == pytest.approx(30.0)
    assert tel.extra["curvature_per_m"] == pytest.approx(k)
    # never under min_speed_pct: 1.5 m before it, 15 % (not 9 %)
    _, cmd, tel = arc_decision(north_m=98.5, bearing_deg=0.0)
    assert (cmd.left_pct, cmd.right_pct) == pytest.approx((15.0, 15.0))
    assert tel.extra["speed_pct"] == 15.0


@pytest.mark.parametrize(("cruise", "bearing"), [(100.0, 320.0), (100.0, 40.0), (80.0, 310.0)])
def test_arc_saturates_at_100_keeping_the_arc(cruise: float, bearing: float) -> None:
    # a short lookahead and a wide track: the inner side reverses
    nav = replace(ARC, cruise_pct=cruise, lookahead_m=2.0, steer_track_m=4.95)
    _, cmd, tel = arc_decision(nav, bearing_deg=bearing)
    alpha = -cmd_heading_deg(bearing)
    k = 2.0 * math.sin(math.radians(alpha)) / 2.0
    assert tel.state == NavState.STRAIGHT and tel.extra["pivoting"] is False
    left, right = mixed(cruise, k, 4.95)
    assert (cmd.left_pct, cmd.right_pct) == pytest.approx((left, right))
    assert max(abs(cmd.left_pct), abs(cmd.right_pct)) == pytest.approx(100.0)
    outer, inner = (cmd.left_pct, cmd.right_pct) if alpha > 0 else (cmd.right_pct, cmd.left_pct)
    assert outer == pytest.approx(100.0) and -100.0 < inner < 0.0  # the inner side backs
    assert inner / outer == pytest.approx((1 - abs(k) * 2.475) / (1 + abs(k) * 2.475))


def cmd_heading_deg(bearing: float) -> float:
    """The compass bearing as the controller's true heading (declination 0), (-180, 180]."""
    return bearing - 360.0 if bearing > 180.0 else bearing


@pytest.mark.parametrize(("bearing", "state", "left"), [
    (270.0, NavState.TURN_RIGHT, 40.0), (90.0, NavState.TURN_LEFT, -40.0),
    (299.0, NavState.TURN_RIGHT, 40.0), (61.0, NavState.TURN_LEFT, -40.0),
])  # fmt: skip
def test_beyond_the_pivot_angle_it_turns_on_the_spot(
    bearing: float, state: NavState, left: float
) -> None:
    _, cmd, tel = arc_decision(bearing_deg=bearing)
    assert tel.state == state and (cmd.left_pct, cmd.right_pct) == (left, -left)
    assert set(tel.extra) == {"filter_samples", *STEER_KEYS}
    assert tel.extra["pivoting"] is True
    assert tel.extra["curvature_per_m"] is None and tel.extra["speed_pct"] is None
    assert tel.extra["steer_alpha_deg"] == pytest.approx(-cmd_heading_deg(bearing))


def test_arc_pivot_hysteresis_reaches_the_wheels() -> None:
    c, cmd, _ = arc_decision(bearing_deg=270.0)  # 90° off: pivot
    assert (cmd.left_pct, cmd.right_pct) == (40.0, -40.0)
    _, cmd, tel = split(c.on_attitude(att(1.1, 340.0)))  # 20° off: still pivoting (> 10°)
    assert (cmd.left_pct, cmd.right_pct) == (40.0, -40.0) and tel.extra["pivoting"] is True
    _, cmd, tel = split(c.on_attitude(att(1.2, 355.0)))  # 5° off: drive the arc again
    k = 2.0 * math.sin(math.radians(5.0)) / 8.0
    # ... the right side once it has stopped before reversing (REVERSE_STOP_S)
    assert (cmd.left_pct, cmd.right_pct) == pytest.approx((60.0 * (1 + k), 0.0))
    assert tel.extra["pivoting"] is False
    _, cmd, tel = split(c.on_attitude(att(1.7, 355.0)))
    assert (cmd.left_pct, cmd.right_pct) == pytest.approx((60.0 * (1 + k), 60.0 * (1 - k)))


def test_arc_stops_in_hold_pause_arrival_and_done() -> None:
    c, cmd, _ = arc_decision(bearing_deg=340.0)
    assert cmd.left_pct > 0 and cmd.right_pct > 0
    _, cmd, tel = split(c.tick(1.6))  # the compass is 0.6 s old: hold
    assert tel.state == NavState.HOLD and cmd == MotorCommand(1.6, 0.0, 0.0, "hold: attitude stale")
    c.on_attitude(att(1.7, 340.0))
    assert c.command.left_pct > 0
    _, cmd, _ = split(c.pause(1.8))
    assert cmd == MotorCommand(1.8, 0.0, 0.0, "paused")
    # arriving in the windows of the last waypoint: stopped, mission done
    c2, cmd, tel = arc_decision(north_m=99.5, bearing_deg=340.0)
    assert tel.state == NavState.MISSION_DONE and c2.mode == Mode.DONE
    assert cmd == MotorCommand(1.0, 0.0, 0.0, "done")
    _, cmd, _ = split(c2.on_attitude(att(1.1, 340.0)))
    assert cmd == MotorCommand(1.1, 0.0, 0.0, "done")


def test_arc_telemetry_names_how_a_waypoint_was_reached() -> None:
    # in the windows (1 m): "windows"; the arrival decision has no steering numbers
    c, _, tel = arc_decision(north_m=99.5, bearing_deg=340.0)
    assert tel.extra == {
        "filter_samples": 1, "steer_alpha_deg": None, "curvature_per_m": None,
        "speed_pct": None, "pivoting": False, "arrived_by": "windows",
    }  # fmt: skip
    # past the waypoint's line, 5 m beside it: "passed". The path goes straight on, so the
    # arrival drives on into the next leg at once (it stopped for that decision until a
    # recorded track's points 1-3 m apart made every point a stop; docs/navigation.md)
    c = Controller(replace(ARC, filter_n=3), SAFETY)
    c.load_mission([at(0.0, 100.0), at(0.0, 200.0)], 0.0)
    c.start(0.0)
    c.on_fix(fix(1.0, 0.0, 50.0))
    _, cmd, tel = split(c.on_attitude(att(1.0, 0.0)))  # starts the leg at (0, 50)
    assert "arrived_by" not in tel.extra and cmd.left_pct == pytest.approx(60.0)
    for t in (1.8, 1.9, 2.0):  # the filter's three samples all there
        c.on_fix(fix(t, 5.0, 100.5))
    _, cmd, tel = split(c.on_attitude(att(2.0, 0.0)))
    # the next leg's lookahead point: 8 m from the robot on the line 5 m to the west
    alpha = math.atan2(-5.0, math.sqrt(8.0**2 - 5.0**2))
    assert tel.state == NavState.ARRIVED and tel.extra["arrived_by"] == "passed"
    assert tel.extra["steer_alpha_deg"] == pytest.approx(math.degrees(alpha), abs=0.01)
    assert (cmd.left_pct, cmd.right_pct) == pytest.approx(
        mixed(60.0, 2.0 * math.sin(alpha) / 8.0, 2.0), abs=0.01
    )  # the next leg's line is to the west: arc left
    assert tel.waypoint_index == 1
    # the next decision drives towards the second waypoint: no arrival any more
    _, cmd, tel = split(c.on_attitude(att(2.1, 0.0)))
    assert tel.state == NavState.STRAIGHT and "arrived_by" not in tel.extra
    assert cmd.left_pct < cmd.right_pct
    # where the next leg starts with a pivot (a corner of 90 deg), ARRIVED stops for that
    # decision as before, and the next one pivots
    c = Controller(replace(ARC, filter_n=3), SAFETY)
    c.load_mission([at(0.0, 100.0), at(100.0, 100.0)], 0.0)
    c.start(0.0)
    c.on_fix(fix(1.0, 0.0, 50.0))
    c.on_attitude(att(1.0, 0.0))
    for t in (1.8, 1.9, 2.0):
        c.on_fix(fix(t, -2.0, 101.5))  # past the line, beside the 1 m windows
    _, cmd, tel = split(c.on_attitude(att(2.0, 0.0)))
    assert tel.state == NavState.ARRIVED and (cmd.left_pct, cmd.right_pct) == (0.0, 0.0)
    assert tel.extra["arrived_by"] == "passed" and tel.extra["steer_alpha_deg"] is None
    _, cmd, tel = split(c.on_attitude(att(2.1, 0.0)))
    # the right side drove forward 1.1 s ago and stopped only at 2.0: held until 2.5
    assert tel.state == NavState.TURN_RIGHT and (cmd.left_pct, cmd.right_pct) == (40.0, 0.0)
    _, cmd, tel = split(c.on_attitude(att(2.5, 0.0)))
    assert tel.state == NavState.TURN_RIGHT and (cmd.left_pct, cmd.right_pct) == (40.0, -40.0)


def test_steering_numbers_only_in_pivot_arc_and_after_a_decision() -> None:
    # pivot_arc, mission loaded and started, no decision yet: no steering keys
    c = Controller(ARC, SAFETY)
    _, _, tel = split(c.load_mission([at(0.0, 100.0)], 0.0))
    assert set(tel.extra) == {"filter_samples"}
    _, _, tel = split(c.start(0.0))
    assert set(tel.extra) == {"filter_samples"}
    _, _, tel = split(c.on_fix(fix(1.0)))  # holding: no attitude yet
    assert set(tel.extra) == {"filter_samples"}
    # pivot_arc without a mission: none either
    _, _, tel = split(Controller(ARC, SAFETY).on_attitude(att(1.0, 340.0)))
    assert set(tel.extra) == {"filter_samples"}
    # paper steering, running: the paper's mixing and no steering keys
    c = driving(1.0)
    _, cmd, tel = split(c.on_attitude(att(1.1, 5.0)))
    assert tel.state == NavState.STRAIGHT and (cmd.left_pct, cmd.right_pct) == (60.0, 60.0)
    assert set(tel.extra) == {"filter_samples"}
