"""``x6wd sim``'s engine choice for a survey that sets robot-only keys, the ``sim://`` motor
link's reopen after a port error, and config/hil.toml's [sim] examples (outside audits:
fresh-machine item 2, live-path items 2 and 5).

- docs/navigation.md's recipe (``[navigation] position_source = "constellation"`` added to
  open_field.toml, then ``x6wd sim``) ran on the receiver engine, which ignored the table
  without a word and named the EKF in its "filtered not run" line;
- the ``sim://`` motors were built without a reopen: after a pty hang-up the link stayed
  lost for good, a write attempt per command (about 44 a second);
- config/hil.toml's example ``v_max_mps = 1.5`` was not the simulated robot's 3.89 m/s.
"""

from __future__ import annotations

import argparse
import errno
import fcntl
import json
import os
import re
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from drivers import registry
from drivers.motors import SerialMotorLink
from sim_backend import cli, hil, runs
from sim_backend.world import load_world, loads_world
from tests.conftest import ROOT
from tests.test_hil import world

__all__ = ["world"]  # the fixture, shared with test_hil

SCENARIOS = ROOT / "config" / "scenarios"
OPEN_FIELD = SCENARIOS / "open_field.toml"
TIOCVHANGUP = 0x5437  # linux/asm-generic/ioctls.h: hang up every open file of the tty


# ------------------------------------------------------------------ the engine choice


def _open_field_with(tmp_path: Path, extra: str, name: str = "of.toml") -> Path:
    """open_field.toml with ``extra`` TOML appended, as docs/navigation.md's recipe does."""
    path = tmp_path / name
    path.write_text(OPEN_FIELD.read_text() + "\n" + extra)
    return path


def _sim(*argv: str) -> int:
    parser = argparse.ArgumentParser()
    cli.add_arguments(parser)
    return cli.main(parser.parse_args([*argv, "--quiet"]))


@pytest.mark.parametrize(
    "extra, named",
    [
        ('[navigation]\nposition_source = "constellation"\n', "navigation.position_source"),
        ("[safety]\nfix_stale_s = 3.0\n", "safety.fix_stale_s"),
        ("[failsafe]\nstuck_s = 20.0\n", "failsafe.stuck_s"),
        ("[odometry]\ntrack_m = 0.3\n", "odometry.track_m"),
        ("[gnss_noise]\nre_m = 1.5\n", "gnss_noise.re_m"),
        ("[encoders]\nk_left_m = 3e-4\n", "encoders.k_left_m"),
        (
            '[[effects]]\nname = "declination"\ndeclination_deg = 5.0\n',
            "effects[0] (declination)",
        ),
    ],
)
def test_a_survey_that_sets_what_only_the_robot_reads_runs_on_the_robot_engine(
    tmp_path: Path, extra: str, named: str
) -> None:
    try:
        world = load_world(_open_field_with(tmp_path, extra))
    except Exception as exc:  # the key's name in this test is off, not the rule
        pytest.fail(f"the test's TOML is not a valid scenario: {exc}")
    assert runs.robot_only_settings(world) == [named]
    assert runs.engine_for(world) == "robot"
    assert runs.engine_for(world, "receiver") == "receiver"  # asked for: run, with a warning
    kind, text = runs.engine_note(world, "auto") or ("", "")
    assert kind == "note" and named in text and "--engine receiver" in text
    kind, text = runs.engine_note(world, "receiver") or ("", "")
    assert kind == "warning" and f"ignores {named}" in text
    assert runs.engine_note(world, "robot") is None


def test_shipped_surveys_still_run_on_the_receiver_engine() -> None:
    # they set [compass] and [vehicle] (read in part by the receiver engine), nothing else
    # only the robot reads, so their outputs stay the receiver engine's
    for path in sorted(SCENARIOS.glob("*.toml")):
        world = load_world(path)
        if len(world.waypoints_enu_m()):
            assert runs.engine_for(world) == "robot", path.name
            assert runs.engine_note(world, "auto") is None
            continue
        assert runs.robot_only_settings(world) == [], path.name
        assert runs.engine_for(world) == "receiver", path.name
        assert runs.engine_note(world, "auto") is None
        assert runs.engine_note(world, "receiver") is None


def test_the_navigation_recipe_runs_the_constellation_filter(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    # docs/navigation.md: open_field.toml with position_source = "constellation", x6wd sim
    monkeypatch.chdir(tmp_path)
    scen = _open_field_with(tmp_path, '[navigation]\nposition_source = "constellation"\n')
    assert _sim(str(scen), "--out", "o", "--duration", "30") == 0
    out, err = capsys.readouterr()
    notes = [line for line in err.splitlines() if line.startswith("x6wd sim: note:")]
    assert len(notes) == 1, err
    assert "robot engine" in notes[0] and "navigation.position_source" in notes[0]
    assert "warning" not in err
    summary = json.loads((tmp_path / "o" / "summary.json").read_text())
    assert summary["extra"].get("engine") != "receiver"
    assert summary["extra"]["position_source"] == "constellation"
    assert summary["filtered_error"]["n"] > 0  # the filter ran
    assert "not run" not in out


def test_engine_receiver_warns_naming_the_ignored_keys_and_the_source(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.chdir(tmp_path)
    scen = _open_field_with(
        tmp_path, '[navigation]\nposition_source = "constellation"\nfilter_n = 10\n'
    )
    assert _sim(str(scen), "--out", "o", "--duration", "30", "--engine", "receiver") == 0
    out, err = capsys.readouterr()
    warnings = [line for line in err.splitlines() if line.startswith("x6wd sim: warning:")]
    assert len(warnings) == 1, err
    assert "navigation.position_source, navigation.filter_n" in warnings[0]
    assert "note:" not in err
    line = next(x for x in out.splitlines() if x.strip().startswith("filtered"))
    assert "not run" in line and "Constellation filter" in line and "EKF" not in line
    summary = json.loads((tmp_path / "o" / "summary.json").read_text())
    assert summary["extra"]["engine"] == "receiver"


def test_filtered_not_run_names_the_configured_source() -> None:
    def line(source: str | None) -> str:
        extra = {"engine": "receiver"}
        if source is not None:
            extra["position_source"] = source
        s = runs.Summary(
            "s", 1, False, 0, 0, 1.0, 1.0, 0.0, 0.0, runs.ErrorStats.of(np.ones(1)),
            runs.ErrorStats.of(np.zeros(0)), 0, 0.0, 1, 1, 0.0, 0.0, 1.0, 7.0, extra,
        )  # fmt: skip
        return next(x for x in s.text().splitlines() if "filtered" in x)

    assert "its EKF" in line("ekf") and "its EKF" in line(None)
    assert "Constellation filter" in line("constellation") and "EKF" not in line("constellation")
    assert "latest fix" in line("raw") and "EKF" not in line("raw")


def test_a_robot_config_counts_too_and_is_named_as_the_config(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.chdir(tmp_path)
    robot = tmp_path / "robot.toml"
    robot.write_text('[navigation]\nposition_source = "raw"\ncruise_pct = 50.0\n')
    args = (str(OPEN_FIELD), "--config", str(robot), "--duration", "20")
    assert _sim(*args, "--out", "a") == 0
    _out, err = capsys.readouterr()
    notes = [line for line in err.splitlines() if line.startswith("x6wd sim: note:")]
    assert len(notes) == 1 and "2 keys of [navigation] from --config" in notes[0], err
    assert str(robot) in notes[0]
    assert json.loads((tmp_path / "a" / "summary.json").read_text())["extra"].get("engine") != (
        "receiver"
    )
    assert _sim(*args, "--out", "b", "--engine", "receiver") == 0
    out, err = capsys.readouterr()
    assert "x6wd sim: warning: --engine receiver ignores the 2 keys of [navigation]" in err
    assert "latest fix" in out


def test_a_robot_config_without_robot_sections_keeps_the_receiver_engine(
    tmp_path: Path,
) -> None:
    from sim_backend.world import with_robot_config

    robot = tmp_path / "robot.toml"
    robot.write_text('[gps]\nurl = "sim://"\n')
    world = with_robot_config(load_world(OPEN_FIELD), robot)
    assert runs.engine_for(world) == "receiver" and runs.engine_note(world, "receiver") is None
    text = OPEN_FIELD.read_text() + "\n[navigation]\n"  # an empty table sets nothing
    assert runs.engine_for(loads_world(text, SCENARIOS)) == "receiver"


# ------------------------------------------------------------------ the sim:// motor link


def hang_up(path: str) -> None:
    """``TIOCVHANGUP`` on the tty at ``path``, as the auditor's inject.py did (a USB-serial
    adapter pulled out); skips without the capability it needs (CAP_SYS_ADMIN)."""
    fd = os.open(path, os.O_RDWR | os.O_NOCTTY)
    try:
        fcntl.ioctl(fd, TIOCVHANGUP)
    except OSError as exc:
        if exc.errno in (errno.EPERM, errno.EACCES):
            pytest.skip(f"TIOCVHANGUP needs CAP_SYS_ADMIN: {exc}")
        raise
    finally:
        os.close(fd)


def drive_for(link: SerialMotorLink, seconds: float, until: object = None) -> float | None:
    """Send drive 30/30 every 20 ms (the daemon's loop sends about 44 a second) for
    ``seconds``; the time (s) of the first acknowledged one if ``until`` is set (then stop)."""
    t0 = time.monotonic()
    while time.monotonic() - t0 < seconds:
        if link.drive(30, 30) and until:
            return time.monotonic() - t0
        time.sleep(0.02)
    return None


@pytest.mark.integration
def test_sim_motor_link_reopens_its_pty_after_a_hangup(world: hil.HilWorld) -> None:
    link = registry.open_motors("sim://", registry.Devices(backends={"sim": world}))
    assert isinstance(link, SerialMotorLink)
    try:
        path = link.port.name
        assert link.drive(30, 30) and world.vehicle.command_pct == (30.0, 30.0)
        hang_up(path)
        back_s = drive_for(link, 5.0, until=True)
        assert back_s is not None, f"the link never recovered: {link.health}"
        assert back_s < 2.0  # 0.5 s of EIO ridden out, then the first reopen 0.2 s later
        assert link.healthy and link.health.connected and link.counters.reopens == 1
        assert link.health.reconnects == 1 and link.port.name == path  # the same pty again
        assert world.vehicle.command_pct == (30.0, 30.0)  # the board drives again
    finally:
        link.close()
    assert world.vehicle.command_pct == (0.0, 0.0)


@pytest.mark.integration
def test_sim_motor_link_retries_with_backoff_while_the_board_is_gone(
    world: hil.HilWorld,
) -> None:
    link = registry.open_motors("sim://", registry.Devices(backends={"sim": world}))
    assert isinstance(link, SerialMotorLink)
    try:
        assert link.drive(30, 30)
        world.close()  # the pty's far end goes away for good: EIO, and no reopen works
        drive_for(link, 1.0)  # the transient errors ridden out (0.5 s), then lost
        assert not link.healthy
        errors = link.health.errors
        drive_for(link, 3.0)  # 150 commands
        attempts = link.health.errors - errors
        # reopen attempts 0.2, 0.4, 0.8, 1.6 s apart (capped at 5 s): about 3 in 3 s; before,
        # every command wrote to the dead port
        assert attempts <= 5, (attempts, link.health)
        assert "reopening the port failed" in link.health.last_error
        assert link.health.next_attempt_t_s is not None
    finally:
        link.close()


def _free_ports(n: int) -> list[int]:
    import socket

    socks = [socket.socket() for _ in range(n)]
    try:
        for s in socks:
            s.bind(("127.0.0.1", 0))
        return [int(s.getsockname()[1]) for s in socks]
    finally:
        for s in socks:
            s.close()


@pytest.mark.slow
@pytest.mark.integration
def test_hil_mission_goes_on_after_the_motor_pty_hangs_up(tmp_path: Path) -> None:
    ctl, console, gpsd = _free_ports(3)
    text = (ROOT / "config" / "hil.toml").read_text()
    for old, new in ((7601, ctl), (7602, console), (2947, gpsd)):
        text, n = re.subn(rf"(?m)^port = {old}$", f"port = {new}", text)
        assert n == 1, old
    text = re.sub(r'(?m)^dir = "recordings"$', f'dir = "{tmp_path / "rec"}"', text)
    cfg = tmp_path / "hil.toml"
    cfg.write_text(text)
    log_path = tmp_path / "daemon.log"
    x6wd = [sys.executable, "-m", "x6wd"]
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    with open(log_path, "w") as log_file:
        daemon = subprocess.Popen(
            [*x6wd, "run", "--config", str(cfg)], env=env, stderr=log_file, cwd=tmp_path
        )

    def status() -> dict:
        r = subprocess.run(
            [*x6wd, "client", "--port", str(ctl), "status", "--json"],
            capture_output=True, text=True, timeout=30,
        )  # fmt: skip
        return json.loads(r.stdout) if r.returncode == 0 else {}

    def client(*args: str) -> None:
        r = subprocess.run(
            [*x6wd, "client", "--port", str(ctl), *args], capture_output=True, text=True,
            timeout=30,
        )  # fmt: skip
        assert r.returncode == 0, r.stderr

    def wait(ok: object, timeout_s: float, what: str) -> dict:
        deadline = time.monotonic() + timeout_s
        while True:
            st = status()
            if st and ok(st):  # type: ignore[operator]
                return st
            assert time.monotonic() < deadline, f"no {what} in {timeout_s} s: {st}"
            time.sleep(0.2)

    try:
        wait(lambda st: (st.get("telemetry") or {}).get("fix_quality", 0) > 0, 60, "fix")
        client("load", "--wp", "51.75227,-1.2577")  # 30 m north of the start
        client("start")
        st0 = wait(lambda st: st["state"] not in ("IDLE", "HOLD"), 20, "drive")
        lat0 = st0["telemetry"]["lat_deg"]
        wait(lambda st: st["telemetry"]["lat_deg"] > lat0 + 2e-5, 20, "motion")  # 2 m on
        # the motor pty: the daemon's /dev/pts/* other than the GPS's (named in its log)
        gps = re.search(r"on (/dev/pts/\d+);", log_path.read_text())
        assert gps, log_path.read_text()
        fds = Path(f"/proc/{daemon.pid}/fd")
        ptys = {os.readlink(fds / fd) for fd in os.listdir(fds)}
        motor = sorted(p for p in ptys if p.startswith("/dev/pts/") and p != gps.group(1))
        assert len(motor) == 1, (ptys, gps.group(1))
        hang_up(motor[0])
        done = wait(lambda st: (st["mode"], st["state"]) == ("DONE", "MISSION_DONE"), 60, "end")
        assert done["devices"]["motors"]["reconnects"] >= 1, done["devices"]["motors"]
        assert done["links"]["motors"] == "ok"
        daemon.terminate()
        assert daemon.wait(15) == 0
    finally:
        if daemon.poll() is None:
            daemon.kill()
            daemon.wait()
    log = log_path.read_text()
    assert "motor port reopened" in log and "MISSION_DONE" in log


# ------------------------------------------------------------------ config/hil.toml


def test_hil_toml_sim_examples_are_the_simulated_robots_values(tmp_path: Path) -> None:
    """config/hil.toml's commented [sim] overrides show the values HIL uses now: uncommented,
    they change nothing (the auditor read ``v_max_mps = 1.5`` and measured 3.89 m/s)."""
    from sim_backend.vehicle import Vehicle, VehicleParams
    from x6wd.core.config import NavigationConfig, load

    path = ROOT / "config" / "hil.toml"
    text = path.read_text()
    examples = dict(re.findall(r"(?m)^# ([a-z_]+) = ([-0-9.]+)\s", text.split("\n[sim]\n", 1)[1]))
    assert set(examples) >= set(hil._OVERRIDES) - {"seed", "gps_rate_hz", "gps_baud"}, examples
    as_is = tmp_path / "as_is.toml"
    as_is.write_text(text)
    used = hil.HilParams.from_config(load(as_is).sim).load_world()
    now = {
        "origin_lat_deg": used.origin.lat_deg,
        "origin_lon_deg": used.origin.lon_deg,
        "origin_alt_m": used.origin.alt_m,
        "start_heading_deg": used.vehicle.start_heading_deg,
        "start_east_m": used.vehicle.start_east_m,
        "start_north_m": used.vehicle.start_north_m,
        "v_max_mps": used.vehicle.max_speed_mps,
        "motor_tau_s": used.vehicle.motor_tau_s,
    }
    for key, value in examples.items():
        assert float(value) == pytest.approx(now[key], rel=1e-3, abs=1e-9), key
    # uncommented, they load (within their ranges) and leave the world as it was
    on = tmp_path / "on.toml"
    on.write_text(re.sub(r"(?m)^# ([a-z_]+ = [-0-9.]+\s)", r"\1", text))
    with_them = hil.HilParams.from_config(load(on).sim).load_world()
    assert with_them.origin == used.origin
    for name in ("start_heading_deg", "start_east_m", "start_north_m", "motor_tau_s"):
        assert getattr(with_them.vehicle, name) == getattr(used.vehicle, name), name
    assert with_them.vehicle.max_speed_mps == pytest.approx(now["v_max_mps"], rel=1e-3)
    # ... and the speeds the comment gives are the vehicle's: at 100 % and at 60 % cruise
    v = Vehicle(VehicleParams(v_max_mps=used.vehicle.max_speed_mps, motor_tau_s=0.0))
    v.command(100.0, 100.0)
    for _ in range(100):
        v.step(0.05)
    assert v.state.speed_mps == pytest.approx(float(examples["v_max_mps"]), rel=1e-3)
    said = re.search(r"(\d+) % cruise the simulated robot drives ([0-9.]+) m/s", text)
    assert said, "the comment's speed at the robot's cruise"
    assert float(said.group(1)) == NavigationConfig().cruise_pct  # the robot's default
    assert 0.6 * v.state.speed_mps == pytest.approx(float(said.group(2)), abs=0.05)
