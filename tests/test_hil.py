"""Hardware in the loop: the simulated devices, and the real daemon process driving a mission
through them while `x6wd client` commands it and `gpspipe -w` reads its gpsd port."""

from __future__ import annotations

import json
import os
import re
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from drivers.gps_nmea import GpsDecoder
from sim_backend import hil
from tests.conftest import ROOT, require_program
from x6wd.errors import ConfigError
from x6wd.records import GpsFix, MotorCommand


@pytest.fixture
def world() -> Iterator[hil.HilWorld]:
    hil.configure(hil.HilParams(gps_rate_hz=4.0, gps_baud=115200, gps_sigma_m=0.0,
                                motor_tau_s=0.0, motor_watchdog_ms=300))  # fmt: skip
    w = hil.world()
    yield w
    hil.shutdown()
    hil.configure(hil.HilParams())


def test_gps_port_carries_neo5_nmea_that_the_real_decoder_reads(world: hil.HilWorld) -> None:
    port = hil.open_gps("sim://")
    dec = GpsDecoder()
    fixes: list[GpsFix] = []
    deadline = time.monotonic() + 5
    try:
        while len(fixes) < 2 and time.monotonic() < deadline:
            data = port.read(4096)
            fixes += [r for r in dec.feed(data, time.monotonic()) if isinstance(r, GpsFix)]
    finally:
        port.close()
    assert len(fixes) >= 2
    f = fixes[-1]
    assert f.valid and f.quality == 1 and f.sats_used == 7
    assert f.lat_deg == pytest.approx(51.7520, abs=1e-6)
    assert f.lon_deg == pytest.approx(-1.2577, abs=1e-6)
    assert dec.counters.checksum_failures == 0


def test_motor_commands_move_the_vehicle_and_the_board_watchdog_stops_it(
    world: hil.HilWorld,
) -> None:
    link = hil.open_motors("sim://")
    compass = hil.open_compass("sim://")
    assert link.healthy
    # spin clockwise in place: the compass registers follow the vehicle's heading
    t_end = time.monotonic() + 0.6
    while time.monotonic() < t_end:
        link.send(MotorCommand(time.monotonic(), 60.0, -60.0, "test"))
        time.sleep(0.05)
    _, _, heading_deg, _ = world.truth()
    assert 20.0 < heading_deg < 60.0  # 54 deg/s for 0.6 s
    att = compass.read(time.monotonic())
    assert att.valid and 5.0 < att.bearing_deg < 60.0  # lags: the CMPS10 filter
    # no more commands: the simulated board's watchdog (300 ms) stops the vehicle
    time.sleep(0.5)
    assert world.vehicle.command_pct == (0.0, 0.0)
    e0, n0, _, _ = world.truth()
    link.drive(50, 50)
    with pytest.raises(ValueError, match="left_pct"):
        link.send(MotorCommand(0.0, 101.0, 0.0))
    time.sleep(0.2)
    e1, n1, _, _ = world.truth()
    assert (e1 - e0) ** 2 + (n1 - n0) ** 2 > 0.05**2  # moved forward
    link.close()
    assert not link.healthy and world.vehicle.command_pct == (0.0, 0.0)


def test_sim_urls_take_no_options() -> None:
    with pytest.raises(ConfigError, match="no path or options"):
        hil.open_gps("sim://?seed=3")
    with pytest.raises(ConfigError, match="expected sim://"):
        hil.open_motors("log://")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@pytest.mark.slow
@pytest.mark.integration
def test_daemon_runs_a_mission_in_real_time(tmp_path: Path) -> None:
    gpspipe = require_program("gpspipe")
    ctl, gpsd = free_port(), free_port()
    text = (ROOT / "config" / "hil.toml").read_text()
    text = re.sub(r"(?m)^port = 7601$", f"port = {ctl}", text)
    text = re.sub(r"(?m)^port = 2947$", f"port = {gpsd}", text)
    text = re.sub(r'(?m)^dir = "recordings"$', f'dir = "{tmp_path / "rec"}"', text)
    assert f"port = {ctl}" in text and f"port = {gpsd}" in text and str(tmp_path) in text
    cfg = tmp_path / "hil.toml"
    cfg.write_text(text)
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    x6wd = [sys.executable, "-m", "x6wd"]
    daemon = subprocess.Popen(
        [*x6wd, "run", "--config", str(cfg)], env=env, stderr=subprocess.PIPE, text=True
    )

    def client(*args: str) -> subprocess.CompletedProcess[str]:
        return subprocess.run(
            [*x6wd, "client", "--port", str(ctl), *args],
            capture_output=True, text=True, timeout=30,
        )  # fmt: skip

    try:
        deadline = time.monotonic() + 20
        while True:  # until it serves and has a fix (the geofence needs one)
            r = client("status")
            tel = json.loads(r.stdout)["telemetry"] if r.returncode == 0 else None
            if tel and tel["fix_quality"] > 0:
                break
            assert time.monotonic() < deadline, r.stderr
            time.sleep(0.2)
        pipe = subprocess.Popen(
            [gpspipe, "-w", f"127.0.0.1:{gpsd}"], stdout=subprocess.PIPE, text=True
        )
        lines: list[str] = []
        reader = threading.Thread(target=lambda: lines.extend(pipe.stdout or ()), daemon=True)
        reader.start()
        # 8 m north of the start (the vehicle starts facing north)
        r = client("load", "--wp", "51.752072,-1.2577")
        assert r.returncode == 0, r.stderr
        r = client("start")
        assert r.returncode == 0, r.stderr
        deadline = time.monotonic() + 25
        while True:
            st = json.loads(client("status").stdout)
            if (st["mode"], st["state"]) == ("DONE", "MISSION_DONE"):
                break
            assert st["state"] != "HOLD", st
            assert time.monotonic() < deadline, st
            time.sleep(0.2)
        tel = st["telemetry"]
        assert tel["lat_deg"] > 51.752072 - 3e-5  # within the 2 m arrival box of the target
        time.sleep(1.0)  # let gpspipe's output catch up
        pipe.terminate()
        pipe.wait(10)
        reader.join(10)
        tpvs = [json.loads(x) for x in lines if '"class":"TPV"' in x]
        assert tpvs and all(t["mode"] == 3 for t in tpvs)
        assert max(t["lat"] for t in tpvs) > 51.75204  # the gpsd client saw it move
        daemon.terminate()
        assert daemon.wait(15) == 0
    finally:
        if daemon.poll() is None:
            daemon.kill()
            daemon.wait()
    err = daemon.stderr.read() if daemon.stderr else ""
    assert "MISSION_DONE" in err and "x6wd stopped" in err


def test_params_from_a_scenario_file(tmp_path: Path) -> None:
    from sim_backend.world import load_world
    from x6wd.config import SimConfig

    path = ROOT / "config" / "scenarios" / "open_field.toml"
    w = load_world(path)
    p = hil.HilParams.from_config(SimConfig(scenario=str(path), gps_sigma_m=0.7))
    assert (p.origin_lat_deg, p.origin_lon_deg) == (w.origin.lat_deg, w.origin.lon_deg)
    assert (p.gps_rate_hz, p.gps_baud, p.seed) == (w.gnss.rate_hz, w.gnss.baud, w.seed)
    assert p.v_max_mps == w.vehicle.max_speed_mps and p.gps_sigma_m == 0.7
    with pytest.raises(ConfigError):
        hil.HilParams.from_config(SimConfig(scenario=str(tmp_path / "missing.toml")))
