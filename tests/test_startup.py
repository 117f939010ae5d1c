"""Start-up errors of the real `x6wd run` process: a bad setting is exit 2 with ONE line on
stderr naming the key, no traceback, before any device is opened or any file created."""

from __future__ import annotations

import asyncio
import dataclasses
import json
import logging
import os
import re
import socket
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

from tests.conftest import ROOT
from tests.test_daemon import hil_config
from x6wd.app.daemon import Daemon, _dir_problem
from x6wd.app.server import CommandError
from x6wd.core.config import RecorderConfig

LEA5H = ROOT / "tests" / "data" / "recorder" / "ublox-lea-5h.log"
UNIT = ROOT / "systemd" / "x6wd.service"

# A configuration that starts: simulated devices, free ports, a recorder dir in tmp.
GOOD: dict[str, dict[str, Any]] = {
    "gps": {"url": "sim://"},
    "compass": {"url": "sim://"},
    "motors": {"url": "sim://"},
    "server": {"port": 0},
    "gpsd": {"port": 0},
    "sim": {"gps_rate_hz": 4.0, "gps_baud": 115200},
}


def toml(sections: dict[str, dict[str, Any]]) -> str:
    return "".join(
        f"[{name}]\n" + "".join(f"{k} = {json.dumps(v)}\n" for k, v in table.items())
        for name, table in sections.items()
    )


def write_config(tmp_path: Path, **changes: dict[str, Any]) -> Path:
    sections = {name: dict(table) for name, table in GOOD.items()}
    sections["recorder"] = {"dir": str(tmp_path / "rec")}
    for name, table in changes.items():
        sections.setdefault(name, {}).update(table)
    path = tmp_path / "x6wd.toml"
    path.write_text(toml(sections), encoding="utf-8")
    return path


def run_x6wd(config: Path, timeout_s: float = 30.0) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "x6wd", "run", "--config", str(config)],
        capture_output=True,
        text=True,
        timeout=timeout_s,
        cwd=ROOT,
    )


def assert_config_error(proc: subprocess.CompletedProcess[str], key: str, *reason: str) -> str:
    """Exit 2, exactly one stderr line ``x6wd: <key>...`` with the reason, no traceback."""
    lines = proc.stderr.splitlines()
    assert proc.returncode == 2, proc.stderr
    assert len(lines) == 1, proc.stderr
    assert lines[0].startswith(f"x6wd: {key}"), lines[0]
    for part in reason:
        assert part in lines[0], lines[0]
    assert "Traceback" not in proc.stderr and not said_ready(proc.stderr)
    return lines[0]


def said_ready(stderr: str) -> bool:
    return re.search(r"\bready\b", stderr) is not None


def files_under(path: Path) -> list[Path]:
    return sorted(p for p in path.rglob("*") if p.is_file()) if path.exists() else []


@pytest.mark.integration
@pytest.mark.parametrize(
    ("changes", "key", "reason"),
    [
        (
            {"gps": {"url": "bogus://x"}},
            "gps.url: 'bogus://x'",
            ["unknown scheme 'bogus' (valid for gps: serial://, tcp://, replay://, sim://)"],
        ),
        (
            {"gps": {"url": "serial:///dev/ttyNOPE?baud=9600"}},
            "gps.url",
            ["/dev/ttyNOPE does not exist"],
        ),
        (
            {"motors": {"url": "tcp://127.0.0.1:9?baud=9600"}},
            "motors.url",
            ["unknown option 'baud' for tcp://", "watchdog_ms"],
        ),
        ({"motors": {"url": "serial:///dev/ttyUSB97"}}, "motors.url", ["/dev/ttyUSB97"]),
        # an outside audit (round 19): found only at the motors' open, after the ports bound
        (
            {"motors": {"url": "tcp://127.0.0.1:9?watchdog_ms=800", "watchdog_ms": 600}},
            "motors.watchdog_ms",
            ["600 ms, but motors.url says watchdog_ms=800: set one of them"],
        ),
        ({"compass": {"url": "i2c://97/0x60"}}, "compass.url", ["/dev/i2c-97 does not exist"]),
        ({"compass": {"url": "sim://?noise=2"}}, "compass.url", ["sim:// takes no path"]),
        ({"gps": {"url": "replay:///nonexistent/a.nmea"}}, "gps.url", ["does not exist"]),
        ({"gps": {"url": f"serial://{LEA5H}"}}, "gps.url", ["not a character device"]),
        ({"navigation": {"delta_z_m": 1.0}}, "", ["navigation.delta_z_m: unknown key"]),
        ({"sim": {"scenario": "no/such/world.toml"}}, "", ["sim.scenario: no such file"]),
        (  # checked as the file is read now (x6wd sim and sweeps too): the file, then the key
            {"safety": {"geofence_center": [1.0]}},
            "",
            ["safety.geofence_center: expected [] or [lat_deg, lon_deg], got [1]"],
        ),
        # what urlsplit, int() and os.stat raise on, not our own checks (an outside check)
        ({"gps": {"url": "tcp://[::1:2947"}}, "gps.url", ["malformed URL"]),
        ({"motors": {"url": "tcp://localhost:\u00b2"}}, "motors.url", ["HOST:PORT"]),
        ({"gps": {"url": "serial:///dev/tty%00S0"}}, "gps.url", ["NUL"]),
        ({"recorder": {"dir": "/tmp/a\u0000b"}}, "", ["recorder.dir: must not contain a NUL"]),
        # two servers on one port: both keys named, before binding blames another program
        (
            {"server": {"port": 47710}, "gpsd": {"port": 47710}},
            "",
            ["gpsd.port: 47710 is server.port too: each server needs a port of its own"],
        ),
        (
            {"server": {"port": 47711}, "console": {"enabled": True, "port": 47711}},
            "",
            ["console.port: 47711 is server.port too"],
        ),
        # an outside check: an empty recorder.dir recorded into the working directory
        (
            {"recorder": {"dir": ""}},
            "",
            ["recorder.dir: empty: name a directory, or set recorder.enabled = false"],
        ),
        # the GPS and the motor board on one line (an outside check: the daemon started,
        # the GPS flapped and the motor commands went down the GPS line)
        (
            {
                "gps": {"url": "serial:///dev/ttyS0?baud=9600"},
                "motors": {"url": "serial:///dev/../dev/ttyS0?baud=115200"},
            },
            "",
            ["motors.url: serial:///dev/../dev/ttyS0?baud=115200 opens /dev/ttyS0, as gps.url"],
        ),
        (
            {"gps": {"url": "tcp://Robot.local:4001"}, "motors": {"url": "tcp://robot.local:4001"}},
            "",
            ["as gps.url does: each device needs a line of its own"],
        ),
    ],
)
def test_bad_setting_is_one_line_and_exit_2(
    tmp_path: Path, changes: dict[str, dict[str, Any]], key: str, reason: list[str]
) -> None:
    config = write_config(tmp_path, **changes)
    proc = run_x6wd(config)
    if key:
        assert_config_error(proc, key, *reason)
    else:  # errors found while reading the file name the file first
        assert_config_error(proc, str(config), *reason)
    assert files_under(tmp_path / "rec") == []
    assert not (tmp_path / "rec").exists()


@pytest.mark.integration
def test_a_scenario_that_cannot_be_read_is_named_by_its_key(tmp_path: Path) -> None:
    # an outside check: "x6wd: /path/scen.toml: cannot read scenario: ..." named no key
    bad = tmp_path / "scen.toml"
    bad.write_text("name = [\n", encoding="utf-8")
    config = write_config(tmp_path, sim={"scenario": str(bad)})
    assert_config_error(run_x6wd(config), "sim.scenario: ", str(bad), "not valid TOML")


@pytest.mark.integration
def test_malformed_and_non_utf8_config(tmp_path: Path) -> None:
    bad = tmp_path / "bad.toml"
    bad.write_text('[gps\nurl = "sim://"\n', encoding="utf-8")
    assert_config_error(run_x6wd(bad), str(bad), "not valid TOML", "line 1")
    latin1 = tmp_path / "latin1.toml"
    latin1.write_bytes(b'[recorder]\ndir = "/tmp/r\xe9cordings"\n')
    assert_config_error(run_x6wd(latin1), str(latin1), "not UTF-8", "0xe9", "line 2")
    missing = tmp_path / "missing.toml"
    assert_config_error(run_x6wd(missing), str(missing), "cannot read configuration")


@pytest.mark.integration
@pytest.mark.parametrize("section", ["server", "gpsd"])
def test_busy_port_is_exit_2_before_any_device_or_file(
    tmp_path: Path, listening: int, section: str
) -> None:
    proc = run_x6wd(write_config(tmp_path, **{section: {"port": listening}}))
    assert_config_error(proc, f"{section}.port", f"127.0.0.1:{listening}", "address already in use")
    assert files_under(tmp_path / "rec") == []


@pytest.mark.integration
def test_bad_token_files(tmp_path: Path) -> None:
    token = tmp_path / "token"
    token.write_text("0123456789abcdef")
    token.chmod(0o644)
    proc = run_x6wd(write_config(tmp_path, server={"token_file": str(token)}))
    assert_config_error(proc, "server.token_file", "chmod 600")
    proc = run_x6wd(write_config(tmp_path, server={"token_file": str(tmp_path / "none")}))
    assert_config_error(proc, "server.token_file", "cannot read")
    assert files_under(tmp_path / "rec") == []


@pytest.mark.integration
def test_recorder_dir_that_cannot_be_created(tmp_path: Path) -> None:
    blocker = tmp_path / "a_file"
    blocker.write_text("not a directory\n")
    proc = run_x6wd(write_config(tmp_path, recorder={"dir": str(blocker / "rec")}))
    assert_config_error(proc, "recorder.dir", f"{blocker} is not a directory")
    assert blocker.read_text() == "not a directory\n"


@pytest.mark.integration
@pytest.mark.skipif(os.geteuid() == 0, reason="root may write in any directory")
def test_recorder_dir_without_write_permission(tmp_path: Path) -> None:
    locked = tmp_path / "locked"
    locked.mkdir(mode=0o555)
    try:
        proc = run_x6wd(write_config(tmp_path, recorder={"dir": str(locked)}))
        assert_config_error(proc, "recorder.dir", "may not write")
        assert list(locked.iterdir()) == []
    finally:
        locked.chmod(0o755)


@pytest.mark.integration
@pytest.mark.parametrize("directory", ["/proc/x6wd", "/proc"])
def test_recorder_dir_where_no_file_can_be_created(tmp_path: Path, directory: str) -> None:
    # the permission bits say yes to root everywhere; procfs takes no file all the same: the
    # preflight tries (and leaves nothing), instead of start-up failing later with exit 1
    proc = run_x6wd(write_config(tmp_path, recorder={"dir": directory}))
    assert_config_error(proc, "recorder.dir", repr(directory))


def test_the_recorder_dir_check_leaves_nothing_behind(tmp_path: Path) -> None:
    assert _dir_problem(tmp_path / "new" / "rec") == ""  # created later, by the recorder
    assert _dir_problem(tmp_path) == ""
    assert list(tmp_path.iterdir()) == []


@pytest.mark.integration
def test_device_that_fails_to_open_is_exit_1_without_a_recording(tmp_path: Path) -> None:
    # the URL is valid and names nothing local, but nobody answers there
    sock = socket.create_server(("127.0.0.1", 0))
    port = sock.getsockname()[1]
    sock.close()
    proc = run_x6wd(write_config(tmp_path, motors={"url": f"tcp://127.0.0.1:{port}"}))
    assert proc.returncode == 1, proc.stderr
    assert f"cannot open tcp://127.0.0.1:{port}" in proc.stderr
    assert not said_ready(proc.stderr) and "Traceback" not in proc.stderr
    assert files_under(tmp_path / "rec") == []


# -- in process -----------------------------------------------------------------------------


def test_the_one_line_also_goes_to_the_log(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    cfg = hil_config(tmp_path)
    cfg = dataclasses.replace(cfg, gps=dataclasses.replace(cfg.gps, url="bogus://x"))
    with caplog.at_level(logging.INFO):
        assert asyncio.run(Daemon(cfg).run()) == 2
    errors = [r for r in caplog.records if r.levelno >= logging.ERROR]
    assert [r.getMessage() for r in errors] == [
        "gps.url: 'bogus://x': unknown scheme 'bogus' (valid for gps: serial://, tcp://, "
        "replay://, sim://)"
    ]
    assert not any("ready" in r.getMessage() for r in caplog.records)


def test_moving_commands_are_refused_until_ready(tmp_path: Path) -> None:
    d = Daemon(hil_config(tmp_path, recorder=RecorderConfig(enabled=False)))
    try:
        d._preflight()  # what exists while the ports listen and the devices open
        for call in (lambda: d.drive(20, 20, 1), d.start, d.resume):
            with pytest.raises(CommandError) as info:
                call()
            assert info.value.code == "rejected" and "starting" in str(info.value)
        assert d.stop()["mode"] == "IDLE"  # stop and status always answer
        assert d.status()["state"] == "IDLE"
    finally:
        if d.devices is not None:
            d.devices.close()  # preflight builds no world; close whatever the set holds


def test_systemd_does_not_restart_on_a_configuration_error() -> None:
    lines = [line.strip() for line in UNIT.read_text().splitlines()]
    assert "Restart=on-failure" in lines  # exit 1 (device, crash, watchdog) is retried
    assert "RestartPreventExitStatus=2" in lines
