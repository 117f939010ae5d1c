"""A return to launch stops the motors first (docs/navigation.md, "Failsafes": every failsafe
"stops the motors first and then takes its configured action").

An outside audit (round 14) saw the operator-link failsafe with operator_action = "return"
take the motor board from the mission's ``M 17 13`` to the return's pivot ``M 40 -40`` 25 ms
later, one side forward to reverse with no stop between: ``_apply_failsafe`` switched the
navigator and the same step drove it. Here the real Controller is driven into each failsafe
whose action is "return" (and the operator's own return), and the real daemon in hardware in
the loop: the first command at the return is 0/0 and no side changes sign without a 0
between; after ``RETURN_STOP_S`` the return drives."""

from __future__ import annotations

import itertools
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

import pytest

from tests.test_controller import NAV, SAFETY, at, att, fix
from tests.test_daemon import ORIGIN, hil_config, run_daemon, wait_for
from tests.test_failsafe_controller import COUNTS_PER_M, FS
from x6wd.app.client import RemoteClient
from x6wd.app.daemon import Daemon
from x6wd.core.config import FailsafeConfig
from x6wd.core.records import Mode, MotorCommand, StateChange, WheelOdometry
from x6wd.nav.controller import RETURN_STOP_S, Controller

__all__ = ["run_daemon"]  # a fixture

STEP_S = 0.1  # a compass sample every step, a fix every second


def flips(cmds: list[tuple[float, float, float]]) -> list[str]:
    """Each command after which a side's drive changed sign with no 0 between."""
    bad = []
    for (t0, l0, r0), (t1, l1, r1) in itertools.pairwise(cmds):
        if l0 * l1 < 0 or r0 * r1 < 0:
            bad.append(f"{t0:.2f} s {l0:+g}/{r0:+g} -> {t1:.2f} s {l1:+g}/{r1:+g}")
    return bad


def run(
    fs: FailsafeConfig,
    pos_m: Callable[[float], tuple[float, float]],
    *,
    north_m: float = 100.0,
    counts_m: Callable[[float], float] | None = None,
    at_step: Callable[[Controller, float], list[Any] | None] | None = None,
    until_s: float = 40.0,
) -> tuple[list[tuple[float, float, float]], float, MotorCommand]:
    """Drive the real Controller on a mission ``north_m`` north (the compass north, a fix at
    ``pos_m(t)`` every second, encoder counts of ``counts_m(t)`` metres if given, and
    ``at_step(c, t)``'s outputs) until a return has gone on for a second. Returns every motor
    command as (t, left, right), the return's time and the command given with it."""
    c = Controller(NAV, SAFETY, failsafe=fs)
    c.on_fix(fix(0.0))
    c.on_attitude(att(0.0))
    c.load_mission([at(0.0, north_m)], 0.0)
    c.operator_seen(0.0)
    outs: list[Any] = list(c.start(0.0))
    t_return: float | None = None
    at_return: MotorCommand | None = None
    cmds: list[tuple[float, float, float]] = []
    for k in range(1, round(until_s / STEP_S)):
        t = round(k * STEP_S, 6)
        outs += c.on_attitude(att(t))
        if k % round(1 / STEP_S) == 0:
            outs += c.on_fix(fix(t, *pos_m(t)))
            if counts_m is not None:
                n = round(counts_m(t) * COUNTS_PER_M)
                outs += c.on_odometry(WheelOdometry(t, n, n, 0))
        if at_step is not None:
            outs += at_step(c, t) or []
        for i, o in enumerate(outs):
            if type(o) is MotorCommand:
                cmds.append((o.t_s, o.left_pct, o.right_pct))
            elif (
                type(o) is StateChange
                and o.reason.endswith("return to launch")
                and o.reason.startswith("mode:")
                and t_return is None
            ):
                t_return = o.t_s
                at_return = next(m for m in outs[i:] if type(m) is MotorCommand)
        outs = []
        if t_return is not None and t - t_return >= 1.0:
            break
    assert t_return is not None and at_return is not None, "no return to launch"
    assert c.mode == Mode.RUNNING and c.returning
    return cmds, t_return, at_return


def check_stop_first(
    cmds: list[tuple[float, float, float]], t_return: float, at_return: MotorCommand
) -> None:
    assert any(left > 0 and right > 0 for _t, left, right in cmds if _t < t_return), (
        "the mission drove before the failsafe"
    )
    assert (at_return.left_pct, at_return.right_pct) == (0.0, 0.0), (
        f"the return's first command is {at_return.left_pct:+g}/{at_return.right_pct:+g}"
        f" ({at_return.reason}), not a stop"
    )
    assert at_return.reason == "stop before the return to launch"
    assert flips(cmds) == []
    after = [(t, lf, rt) for t, lf, rt in cmds if t > t_return]
    first_drive = next(t for t, lf, rt in after if (lf, rt) != (0.0, 0.0))
    # stopped for RETURN_STOP_S, then the return pivots towards the launch point (south)
    assert t_return + RETURN_STOP_S <= first_drive <= t_return + RETURN_STOP_S + STEP_S + 1e-9
    assert any(lf * rt < 0 for t, lf, rt in after), "the return never pivoted"


def north(speed_mps: float) -> Callable[[float], tuple[float, float]]:
    return lambda t: (0.0, speed_mps * t)


def test_the_operator_link_failsafe_returns_after_a_stop() -> None:
    fs = replace(FS, operator_timeout_s=10.0, operator_action="return", stuck_s=0.0)
    cmds, t_ret, first = run(fs, north(3.0))
    assert 10.0 < t_ret <= 10.0 + STEP_S + 1e-9
    check_stop_first(cmds, t_ret, first)


def test_a_geofence_breach_configured_to_return_stops_first() -> None:
    fs = replace(FS, geofence_action="return", stuck_s=0.0)

    def breach(c: Controller, t: float) -> list[Any] | None:
        return c.geofence_breach(t) if t == 10.5 else None

    cmds, t_ret, first = run(fs, north(3.0), at_step=breach)
    assert t_ret == pytest.approx(10.5)
    check_stop_first(cmds, t_ret, first)


def test_the_stuck_failsafe_configured_to_return_stops_first() -> None:
    fs = replace(FS, stuck_action="return")
    cmds, t_ret, first = run(
        fs, lambda t: (0.0, min(20.0, 2.0 * t)), counts_m=lambda t: min(20.0, 2.0 * t)
    )
    check_stop_first(cmds, t_ret, first)


def test_the_off_course_failsafe_configured_to_return_stops_first() -> None:
    """The compass north, the fixes going east: off course; home is west, a left pivot."""
    fs = replace(FS, stuck_s=0.0, off_course_action="return")
    cmds, t_ret, first = run(fs, lambda t: (2.0 * t, 0.0), north_m=1000.0)
    check_stop_first(cmds, t_ret, first)
    assert any(lf < 0 < rt for t, lf, rt in cmds if t > t_ret)  # the left side reversed


def test_the_operators_return_from_a_running_mission_stops_first() -> None:
    fs = replace(FS, stuck_s=0.0)

    def ret(c: Controller, t: float) -> list[Any] | None:
        return c.return_home(t) if t == 10.5 else None

    cmds, t_ret, first = run(fs, north(3.0), at_step=ret)
    check_stop_first(cmds, t_ret, first)


def test_a_sensor_timeout_return_is_a_stop_and_drives_home_once_the_sensor_is_back() -> None:
    fs = replace(FS, sensor_timeout_s=2.0, sensor_action="return", stuck_s=0.0)

    def gps_loss(c: Controller, t: float) -> list[Any] | None:
        if t == 2.5:
            return c.sensor_health("gps", False, t, "disconnected")
        if t == 4.7:
            return c.sensor_health("gps", True, t, "connected")
        return None

    cmds, t_ret, first = run(fs, north(2.0), at_step=gps_loss, until_s=8.0)
    assert t_ret == pytest.approx(4.5)  # 2 s after the loss: blind, a stop
    assert (first.left_pct, first.right_pct) == (0.0, 0.0)
    assert flips(cmds) == []
    assert any(lf * rt < 0 for t, lf, rt in cmds if t > 5.0), "no return once the gps was back"


# -- end to end: the real daemon, the simulated motor board's wire --------------------------


def board_drives(world: Any) -> list[tuple[float, int, int]]:
    """The motor board's received drive lines as (t_s, left, right); ``S`` is 0/0."""
    got = []
    for direction, t_s, data in world.motor_wire:
        if direction != "rx":
            continue
        for line in data.decode("ascii", "replace").splitlines():
            parts = line.partition("#")[0].split()  # "M 17 13 #42": its sequence number
            if parts[:1] == ["S"]:
                got.append((t_s, 0, 0))
            elif parts[:1] == ["M"] and len(parts) == 3:
                got.append((t_s, int(parts[1]), int(parts[2])))
    return got


def test_the_daemons_operator_link_return_reaches_the_board_after_a_stop(
    tmp_path: Path, run_daemon: Any
) -> None:
    """HIL: a mission started over the network, no request for operator_timeout_s: the board
    receives a stop between the mission's forward drive and the return's pivot."""
    cfg = hil_config(
        tmp_path, failsafe=replace(FailsafeConfig(), operator_timeout_s=4.0, stuck_s=0.0)
    )
    r = run_daemon(Daemon(cfg))
    world = r.daemon.devices.backend("sim")
    with RemoteClient("127.0.0.1", r.port) as c:
        wait_for(lambda: r.daemon.first_fix, 15, "first fix")
        c.request("mission.load", waypoints=[[ORIGIN[0] + 0.0008, ORIGIN[1]]])  # ~90 m north
        c.request("start")  # the last operator request: no status polls (they would re-arm it)
        ctl = r.daemon.runner.controller
        wait_for(lambda: ctl.returning, 15, "the operator-link return")
        time.sleep(RETURN_STOP_S + 1.0)
    cmds = [(t, float(lf), float(rt)) for t, lf, rt in board_drives(world)]
    assert any(lf > 0 and rt > 0 for _t, lf, rt in cmds), f"the mission never drove: {cmds}"
    assert any(lf * rt < 0 for _t, lf, rt in cmds), "the return never pivoted"
    assert flips(cmds) == [], cmds


def test_a_stop_ends_the_returns_stop_a_new_mission_drives_at_once() -> None:
    # Review: return, stop, start within RETURN_STOP_S: the new mission (no return) began in
    # HOLD "stop before the return to launch" (the window was cleared nowhere)
    c = Controller(NAV, SAFETY)
    c.on_fix(fix(0.0))
    c.on_attitude(att(0.0))
    c.load_mission([at(0.0, 100.0)], 0.0)
    c.start(0.0)
    for k in range(1, 50):
        t = k * 0.1
        c.on_attitude(att(t))
        if k % 10 == 0:
            c.on_fix(fix(t, 0.0, 2.0 * t))
    c.return_home(5.0)
    c.stop(5.1)
    c.load_mission([at(0.0, 100.0)], 5.15)
    outs = [*c.start(5.2), *c.on_attitude(att(5.3))]
    reasons = [o.reason for o in outs if isinstance(o, (StateChange, MotorCommand))]
    assert not any("before the return" in r for r in reasons), reasons
    assert c.returning == ""
