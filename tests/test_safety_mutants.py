"""Safety behaviours an outside mutation audit removed one at a time without any test failing:
the motor thread's own stop when it dies, the constant-time token comparison, the console's
refusal of a non-loopback bind without a token, ``gps_outage_max_m = 0`` as "hold at once",
and the ranges of the safety, failsafe and console keys. One test (or family) per survivor,
each checked to fail with its behaviour removed."""

from __future__ import annotations

import dataclasses
import hashlib
import hmac
import logging
import math
import time
import typing
from pathlib import Path
from typing import Any

import pytest

import x6wd.app.server as server_module
from tests.test_controller import at, att, fix
from tests.test_daemon import hil_config, run_to_exit
from tests.test_safety_server import lt, servers  # noqa: F401 (fixtures)
from tests.test_server import TOKEN, Raw
from tests.test_shutdown import StampedLink
from x6wd.app.daemon import Daemon, _MotorWorker
from x6wd.core.config import (
    ConsoleConfig,
    FailsafeConfig,
    SafetyConfig,
    ServerConfig,
    check_plaintext,
    loads,
)
from x6wd.core.errors import ConfigError
from x6wd.core.records import HealthEvent, Mode, MotorCommand, NavState, WheelOdometry
from x6wd.nav.controller import Controller


# -- 1i: a dying motor thread stops the motors itself -----------------------------------------
class DyingLink(StampedLink):
    """A recording link whose health read raises once armed: the motor thread dies in
    ``_after_io`` (outside the send's own error handling), as a bug there would kill it."""

    armed = False

    def take_health_events(self) -> list[HealthEvent]:
        if self.armed:
            raise RuntimeError("a bug in the motor thread")
        return super().take_health_events()


def test_a_dying_motor_thread_stops_the_motors_without_waiting_for_the_daemon() -> None:
    # the outside mutation audit removed `link.stop("motor thread died")` from _died and no
    # test failed: the daemon's later _close stops the link too. Nothing here shuts down, so
    # only _died can bring that stop, and it must come at once (the board is fed no more).
    link = DyingLink()
    deaths: list[BaseException] = []
    w = _MotorWorker(link, 5.0, lambda _ok, _t: None, on_death=deaths.append)
    w.start()
    try:
        link.armed = True
        drive = MotorCommand(time.monotonic(), 40.0, 40.0, "manual")
        w.submit(drive)
        # the loop ends at the stop; without it nothing ever stops the motors here (no
        # shutdown, no keep-alive in a dead thread): 5 s is a loaded host's slack
        t_end = time.monotonic() + 5.0
        while time.monotonic() < t_end and not any(
            c.reason == "motor thread died" for _t, c in link.stamped
        ):
            time.sleep(0.005)
        sent = [c for _t, c in link.stamped]
        assert sent[0] == drive, sent
        assert sent[-1].is_stop and sent[-1].reason == "motor thread died", sent
        assert [str(e) for e in deaths] == ["a bug in the motor thread"]
        w.thread.join(5.0)
        assert not w.thread.is_alive()
        # after the death nothing more may reach the motors
        assert w.send_now(MotorCommand(time.monotonic(), 40.0, 40.0, "manual")) is False
        time.sleep(0.05)
        assert [c for _t, c in link.stamped] == sent
    finally:
        link.armed = False
        w.shutdown("test end")


# -- 2b: the token is compared in constant time -----------------------------------------------
def test_the_token_is_compared_with_hmac_compare_digest(
    servers: Any,  # noqa: F811 (the fixture imported above)
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # the outside mutation audit replaced hmac.compare_digest with `==` and no test failed
    # (both give the same answers; only the timing differs): the spy sees the comparisons.
    real = hmac.compare_digest
    seen: list[tuple[Any, Any, bool]] = []

    def spy(a: Any, b: Any) -> bool:
        ok = real(a, b)
        seen.append((a, b, ok))
        return ok

    monkeypatch.setattr(server_module.hmac, "compare_digest", spy)
    srv = servers(auth_fail_delay_s=0.0)
    raw = Raw(srv.port)
    try:
        wrong = raw.ask({"id": 1, "cmd": "auth", "token": "not-the-token"})
        assert wrong["ok"] is False and wrong["error"]["code"] == "auth_failed"
        assert raw.ask({"id": 2, "cmd": "auth", "token": TOKEN}) == {
            "id": 2, "ok": True, "authenticated": True
        }  # fmt: skip
    finally:
        raw.close()
    digest = hashlib.sha256(TOKEN.encode()).digest()
    assert seen == [
        (hashlib.sha256(b"not-the-token").digest(), digest, False),
        (digest, digest, True),
    ]


# -- 3f: the console's own refusal of a non-loopback bind without a token ---------------------
def test_a_console_beyond_loopback_without_a_token_is_refused_by_the_console(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    # the outside mutation audit removed ConsoleServer's check and no test failed: without
    # TLS, check_plaintext refuses the bind first. With server.allow_plaintext it lets the
    # bind through (asserted below), so only the console's own check stands in the way.
    cfg = hil_config(
        tmp_path,
        server=ServerConfig(port=0, allow_plaintext=True),  # loopback, no token_file
        console=ConsoleConfig(enabled=True, bind="0.0.0.0", port=0),
    )
    check_plaintext(cfg)
    d = Daemon(cfg)
    try:
        with caplog.at_level(logging.ERROR, logger="x6wd.app.daemon"):
            assert run_to_exit(d, timeout_s=10.0) == 2
    finally:
        if d.devices is not None:
            d.devices.close()
    assert [r.getMessage() for r in caplog.records if r.levelno >= logging.ERROR] == [
        "console.bind: 0.0.0.0 is not loopback: the console needs the control server's token "
        "(server.token_file)"
    ]


# -- 5j: gps_outage_max_m = 0 holds at once without a fix -------------------------------------
def test_no_outage_allowance_holds_a_pivot_as_soon_as_the_fix_is_stale() -> None:
    # The outside mutation audit removed `limit_m <= 0` from _dead_reckoning_ok and no test
    # failed. With a speed floor the time bound (0 m / slowest speed = 0 s) holds at once
    # anyway; with min_speed_pct = 0 (valid with the stuck test off) that bound is infinite,
    # and a pivot adds neither wheel nor commanded travel: only the check holds it then.
    cfg = loads(
        "[navigation]\nmin_speed_pct = 0\n[failsafe]\nstuck_s = 0\n"
        "[safety]\ngps_outage_max_m = 0\nfix_stale_s = 2.5\n"
    )
    assert cfg.navigation.position_source == "ekf" and cfg.navigation.steering == "pivot_arc"
    c = Controller(cfg.navigation, cfg.safety, 3.0, failsafe=cfg.failsafe)
    c.on_fix(fix(0.0))
    c.on_attitude(att(0.0, 357.0))  # 357 magnetic + 3 declination: north
    c.load_mission([at(0.0, -200.0)], 0.0)  # due south: the robot pivots on the spot
    c.start(0.0)
    last_fix_s = 1.0
    held_s = None
    for k in range(1, 61):  # encoders (never counting) and compass at 10 Hz, fixes to 1 s
        t = 0.1 * k
        c.on_odometry(WheelOdometry(t, 0, 0, k))
        c.on_attitude(att(t, 357.0))
        if t <= last_fix_s + 1e-9 and k % 5 == 0:
            c.on_fix(fix(t))
        assert c.mode == Mode.RUNNING, c.telemetry.extra.get("failsafe")
        if t <= last_fix_s + cfg.safety.fix_stale_s:
            assert c.state in (NavState.TURN_LEFT, NavState.TURN_RIGHT), (t, c.state)
        elif c.state == NavState.HOLD:
            held_s = t
            break
    assert held_s is not None, "drove on without a fix with gps_outage_max_m = 0"
    assert held_s == pytest.approx(last_fix_s + cfg.safety.fix_stale_s, abs=0.15)
    assert c.telemetry.hold_reason == "fix stale"
    assert c.command.is_stop and (c.command.left_pct, c.command.right_pct) == (0.0, 0.0)


# -- 8b/8c/8e: every safety, failsafe and console number is bounded ---------------------------
RANGED = (("safety", SafetyConfig), ("failsafe", FailsafeConfig), ("console", ConsoleConfig))
# the safety keys that must stay bounded: a hand list, so that deleting a key's metadata
# (which drops it from the derived lists below too) still fails here
MUST_BE_BOUNDED = (
    "manual_max_s",
    "fix_stale_s",
    "attitude_stale_s",
    "geofence_radius_m",
    "gps_outage_max_m",
)


def _numeric_fields(cls: type) -> list[tuple[dataclasses.Field[Any], type]]:
    hints = typing.get_type_hints(cls)
    return [(f, hints[f.name]) for f in dataclasses.fields(cls) if hints[f.name] in (int, float)]


def _past_bounds() -> list[Any]:
    cases = []
    for section, cls in RANGED:
        for f, tp in _numeric_fields(cls):
            for side, bound in (("min", f.metadata.get("min")), ("max", f.metadata.get("max"))):
                if bound is None:
                    continue
                if tp is int:
                    text = str(int(bound) + (1 if side == "max" else -1))
                else:  # the nearest double beyond the bound
                    text = repr(
                        math.nextafter(float(bound), math.inf if side == "max" else -math.inf)
                    )
                cases.append(pytest.param(section, f.name, text, id=f"{section}.{f.name}-{side}"))
    return cases


@pytest.mark.parametrize(("section", "key", "text"), _past_bounds())
def test_a_value_just_past_its_bound_is_refused_naming_the_key(
    section: str, key: str, text: str
) -> None:
    # the outside mutation audit removed the ranges of manual_max_s, fix_stale_s and
    # geofence_radius_m and no test failed: a 0 s stale limit or a 1e9 m fence would load
    with pytest.raises(ConfigError) as ei:
        loads(f"[{section}]\n{key} = {text}\n")
    assert str(ei.value).startswith(f"{section}.{key}: must be "), str(ei.value)


def test_every_numeric_safety_failsafe_and_console_key_has_both_bounds() -> None:
    # the derived cases above lose a bound's case with the bound: this keeps the bound
    for section, cls in RANGED:
        for f, _tp in _numeric_fields(cls):
            lo, hi = f.metadata.get("min"), f.metadata.get("max")
            assert lo is not None and hi is not None, f"{section}.{f.name}: range {lo}..{hi}"
            assert lo < hi and lo <= f.default <= hi, f"{section}.{f.name}"
    safety = {f.name: f for f, _tp in _numeric_fields(SafetyConfig)}
    for key in MUST_BE_BOUNDED:
        assert key in safety, f"safety.{key}: not a number any more"
        meta = safety[key].metadata
        assert meta.get("min") is not None and meta.get("max") is not None, f"safety.{key}"
