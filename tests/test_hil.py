"""Hardware in the loop: the simulated devices, and the real daemon process driving a mission
through them while `x6wd client` commands it and `gpspipe -w` reads its gpsd port.

The world is the scenario's full model: the NMEA read through the pty must carry the almanac
sky the GNSS model computes for the scenario time, and the motor driver must talk the
docs/motors.md protocol to the simulated board."""

from __future__ import annotations

import contextlib
import json
import os
import re
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from datetime import datetime
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from drivers import registry
from drivers.gps_nmea import GpsDecoder
from drivers.motors import SerialMotorLink
from sim_backend import hil
from sim_backend.geodesy import enu_to_lla
from sim_backend.receiver import build_gnss_model
from tests.conftest import ROOT, require_program
from x6wd.core.config import SimConfig
from x6wd.core.errors import ConfigError
from x6wd.core.records import GpsFix, GpsSky, MotorCommand

DEFAULT_SCENARIO = ROOT / "config" / "scenarios" / "default.toml"
PARAMS = hil.HilParams(gps_rate_hz=4.0, gps_baud=115200, motor_tau_s=0.0, motor_watchdog_ms=300)


@pytest.fixture
def world() -> Iterator[hil.HilWorld]:
    w = hil.HilWorld(PARAMS)
    yield w
    w.close()


@contextlib.contextmanager
def devices_on(params: hil.HilParams) -> Iterator[registry.Devices]:
    """The sim:// devices of a world built from ``params`` (closed on exit)."""
    w = hil.HilWorld(params)
    try:
        yield registry.Devices(backends={"sim": w})
    finally:
        w.close()


def opened(world: hil.HilWorld) -> registry.Devices:
    """sim:// URLs opened on ``world`` (the caller's: the device set never closes it)."""
    return registry.Devices(backends={"sim": world})


def read_records(port: object, seconds: float, n_fixes: int = 1 << 30) -> tuple[list, bytes]:
    """Decoded records and the raw bytes read from ``port`` for ``seconds`` (or n fixes)."""
    dec = GpsDecoder()
    recs: list = []
    raw = bytearray()
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        data = port.read(4096)  # type: ignore[attr-defined]
        raw += data
        recs += dec.feed(data, time.monotonic())
        if sum(isinstance(r, GpsFix) for r in recs) >= n_fixes:
            break
    assert dec.counters.checksum_failures == 0
    return recs, bytes(raw)


def test_gps_port_carries_neo5_nmea_that_the_real_decoder_reads(world: hil.HilWorld) -> None:
    port = registry.open_gps_port("sim://", opened(world))
    try:
        recs, raw = read_records(port, 5.0, n_fixes=3)
    finally:
        port.close()
    fixes = [r for r in recs if isinstance(r, GpsFix)]
    assert len(fixes) >= 3
    f = fixes[-1]
    assert f.valid and f.quality == 1 and f.mode == 3
    # near the scenario's origin, within the full model's metre-level error
    lat0, lon0 = 51.7520, -1.2577
    pos = [(x.lat_deg, x.lon_deg) for x in fixes if x.lat_deg is not None and x.lon_deg]
    err_m = [np.hypot((a - lat0) * 111_200, (b - lon0) * 68_900) for a, b in pos]
    assert len(err_m) == len(fixes) and all(0.0 < e < 15.0 for e in err_m), err_m
    # the receiver's clock is the host's UTC (the sky stays the almanac's day), an epoch on
    # every whole 0.25 s of it, read just after it was due
    assert f.utc is not None and 0.0 <= time.time() - f.utc.timestamp() < 2.0, f.utc
    assert (f.utc.microsecond // 10_000) % 25 == 0
    for talker in (b"$GPRMC", b"$GPVTG", b"$GPGGA", b"$GPGSA", b"$GPGSV", b"$GPGLL"):
        assert talker in raw


def test_gsv_sky_and_hdop_come_from_the_almanac_model(world: hil.HilWorld) -> None:
    port = registry.open_gps_port("sim://", opened(world))
    try:
        recs, _ = read_records(port, 5.0, n_fixes=3)
    finally:
        port.close()
    skies = [r for r in recs if isinstance(r, GpsSky) and r.utc is not None]
    fixes = [r for r in recs if isinstance(r, GpsFix) and r.utc is not None]
    assert skies and fixes
    # an independent model of the same scenario, asked about the same scenario time
    sc = PARAMS.load_world()
    model = build_gnss_model(sc, np.random.default_rng(0))
    o = sc.origin
    lat, lon, alt = enu_to_lla(
        np.array([0.0, 0.0, sc.vehicle.antenna_height_m]), o.lat_deg, o.lon_deg, o.alt_m
    )
    for sky in skies[-2:]:
        assert sky.utc is not None
        t_s = world.scenario_t_s(sky.utc)  # the almanac's day: start_utc + t_s
        ep = model.step(t_s, float(lat), float(lon), float(alt), (0.0, 0.0, 0.0))
        want = sorted(ep.satellites, key=lambda s: s.prn)
        got = sorted(sky.satellites, key=lambda s: s.prn)
        assert [s.prn for s in got] == [s.prn for s in want]
        assert [s.el_deg for s in got] == [float(round(s.el_deg)) for s in want]
        assert [s.az_deg for s in got] == [float(round(s.az_deg) % 360) for s in want]
        # Which satellites are tracked and used depends on the fading draws and the tracking
        # history (not this model's): the HDOP must be the geometry of the ones used.
        used = [s for s in want if s.prn in {g.prn for g in got if g.used}]
        assert len(used) >= 4
        el, az = (np.radians([getattr(s, k) for s in used]) for k in ("el_deg", "az_deg"))
        g = np.column_stack([np.cos(el) * np.sin(az), np.cos(el) * np.cos(az), np.sin(el)])
        q = np.linalg.inv(
            np.column_stack([g, np.ones(len(used))]).T @ np.column_stack([g, np.ones(len(used))])
        )
        assert sky.hdop == pytest.approx(float(np.sqrt(q[0, 0] + q[1, 1])), abs=0.006)
        fix = next(f for f in fixes if f.utc == sky.utc)
        assert fix.sats_used == len(used)
        assert fix.hdop == pytest.approx(sky.hdop, abs=0.006)
    # not the old fixed 8-satellite sky
    assert {s.prn for s in skies[-1].satellites} != {2, 5, 10, 12, 15, 21, 24, 29}


def _wire_sentences(raw: bytes) -> list[bytes]:
    """The complete CRLF-terminated lines of ``raw`` (a partial last line left out)."""
    return [line + b"\r\n" for line in raw.split(b"\r\n")[:-1]]


@pytest.mark.parametrize("baud", [9600, 38400])
def test_gps_line_paces_bytes_and_drops_whole_sentences_when_full(baud: int) -> None:
    """4 Hz of NEO-5 output needs about 2,000 bytes/s; 9600 baud carries 960: the receiver's
    transmit buffer fills and whole sentences are dropped (never torn), and the bytes arrive
    no faster than the line carries them. At 38400 baud everything gets through."""
    w = hil.HilWorld(hil.HilParams(gps_rate_hz=4.0, gps_baud=baud, motor_watchdog_ms=300))
    port = registry.open_gps_port("sim://", opened(w))
    reads: list[tuple[float, int]] = []
    raw = bytearray()
    try:
        deadline = time.monotonic() + 5.0
        while time.monotonic() < deadline:
            data = port.read(4096)  # every few ms, also when nothing came
            reads.append((time.monotonic(), len(data)))
            raw += data
            time.sleep(0.003)
    finally:
        port.close()
        w.close()
    got = _wire_sentences(bytes(raw))
    assert len(got) > 40
    dec = GpsDecoder()
    dec.feed(b"".join(got), 0.0)
    assert dec.counters.checksum_failures == 0  # no torn sentence
    # What crossed the pty is exactly a run of what the receiver's UART model accepted.
    accepted = [line for _t, line in w.gps_wire]
    i = accepted.index(got[1])
    assert got[1:] == accepted[i : i + len(got) - 1]
    # Paced: no byte reaches the host before the UART model has it on the line. By each read,
    # at most what the model's schedule put on the wire by then, plus the one pacing piece
    # written as its first byte is due; a burst written at once would break this. (A cumulative
    # bound: a writer the host held up catches up on its schedule, never ahead of it, so the
    # check does not depend on the host's load; a per-interval bound did, CI 2026-12-06.)
    t = np.array([r[0] for r in reads])
    n = np.array([r[1] for r in reads])
    byte_s = w.receiver.wire_time_s(1)
    starts = np.array([t_end - w.receiver.wire_time_s(len(line)) for t_end, line in w.gps_wire])
    sizes = np.array([len(line) for _t, line in w.gps_wire])
    assert len(w.gps_wire) < w.gps_wire.maxlen  # the whole schedule is still there
    piece = max(1, int(baud / 10 * hil.PACE_CHUNK_S))
    on_wire = np.array([np.clip((ti - w.t0 - starts) / byte_s, 0, sizes).sum() for ti in t])
    assert (np.cumsum(n) <= on_wire + piece + 1).all()
    sent, span_s = n[1:].sum(), t[-1] - t[0]
    kinds = [line[3:6] for line in got]
    if baud == 9600:
        assert w.receiver.uart.dropped > 20
        assert sent / span_s > 0.8 * baud / 10.0  # the line is kept full
        # the first of each burst gets through, the later GSV mostly not (a whole burst
        # carries 2-4 GSV per RMC)
        assert kinds.count(b"RMC") >= 8 and kinds.count(b"GSV") < 1.5 * kinds.count(b"RMC")
    else:
        assert w.receiver.uart.dropped == 0
        assert kinds.count(b"GGA") >= 15 and abs(kinds.count(b"GGA") - kinds.count(b"GLL")) <= 1


def test_scenario_effects_reach_the_receiver_with_real_no_fix_forms(tmp_path: Path) -> None:
    scenario = tmp_path / "outages.toml"
    scenario.write_text(
        DEFAULT_SCENARIO.read_text()
        + '\n[[effects]]\nname = "outages"\nmean_up_s = 0.5\nmean_down_s = 2.0\n'
    )
    with devices_on(hil.HilParams(str(scenario), gps_rate_hz=4.0, gps_baud=115200)) as devices:
        port = registry.open_gps_port("sim://", devices)
        try:
            recs, raw = read_records(port, 3.0)
        finally:
            port.close()
    fixes = [r for r in recs if isinstance(r, GpsFix)]
    assert any(not f.valid for f in fixes)
    # the NEO-5's no-fix forms, with time (the receiver tracks satellites) but no position
    assert re.search(rb"\$GPGGA,\d{6}\.\d\d,,,,,0,00,99\.99,,,,,,\*", raw)
    assert re.search(rb"\$GPRMC,\d{6}\.\d\d,V,,,,,,,\d{6},,,N\*", raw)  # today's date
    assert re.search(rb"\$GPGSA,A,1,,,,,,,,,,,,,99\.99,99\.99,99\.99\*", raw)


def test_every_effect_layer_applies_in_hil_as_in_x6wd_sim(tmp_path: Path) -> None:
    from sim_backend.effects import HardIron, HeadingSeries

    scenario = tmp_path / "layers.toml"
    scenario.write_text(
        DEFAULT_SCENARIO.read_text()
        + '\n[[effects]]\nname = "quantization"\ndecimals = 3\n'
        + '\n[[effects]]\nname = "latency"\ndelay_s = 0.5\n'
        + '\n[[effects]]\nname = "multipath_zone"\nx1_m = -5.0\ny1_m = 0.0\nx2_m = 5.0\n'
        + "y2_m = 0.0\ndistance_m = 3.0\nsigma_m = 0.2\nbias_m = 40.0\n"
        + '\n[[effects]]\nname = "hard_iron"\nbx_ut = 5.0\nby_ut = -3.0\n'
    )
    with devices_on(hil.HilParams(str(scenario), gps_rate_hz=4.0, gps_baud=115200)) as devices:
        assert devices.backend("sim").effects_skipped == ()
        port = registry.open_gps_port("sim://", devices)
        try:
            recs, raw = read_records(port, 3.0, n_fixes=6)
        finally:
            port.close()
        att = registry.open_compass("sim://", devices).read(time.monotonic())
    coords = re.findall(rb"\$GPGGA,[^,]*,(\d{4}\.\d{5}),[NS],(\d{5}\.\d{5}),[EW]", raw)
    assert len(coords) >= 3
    assert all(lat.endswith(b"00") and lon.endswith(b"00") for lat, lon in coords)
    # The robot stands at the origin, on the wall's line: 40 m pushed away from it.
    sc = hil.HilParams(scenario=str(scenario)).load_world()
    o = sc.origin
    fixes = [r for r in recs if isinstance(r, GpsFix) and r.valid]
    north = [(f.lat_deg - o.lat_deg) * 111_200.0 for f in fixes if f.lat_deg is not None]
    assert north and all(abs(n) > 30.0 for n in north)
    # The hard-iron layer reaches the driver's bearing with the layer's heading error.
    magnetic = (sc.vehicle.start_heading_deg - sc.compass["declination_deg"]) % 360.0
    series = HeadingSeries(np.zeros(1), np.array([magnetic]), np.zeros(1), np.zeros(1))
    want = HardIron(5.0, -3.0).apply(series, np.random.default_rng(0)).heading_deg[0]
    assert abs((att.bearing_deg - want + 180.0) % 360.0 - 180.0) < 0.5
    assert abs((att.bearing_deg - magnetic + 180.0) % 360.0 - 180.0) > 5.0


def test_motor_driver_is_the_real_serial_link_to_a_simulated_board(
    world: hil.HilWorld,
) -> None:
    devices = opened(world)
    link = registry.open_motors("sim://", devices)
    compass = registry.open_compass("sim://", devices)
    assert isinstance(link, SerialMotorLink) and link.healthy
    assert link.port.name.startswith("/dev/pts/")
    # Spin clockwise in place, feeding the board's watchdog: the compass registers follow
    # the vehicle's heading. Real time, so the checks wait for outcomes (with deadlines for a
    # loaded machine) rather than assert physics after fixed sleeps; the physics itself is
    # checked in fast time (test_mission, test_vehicle).
    _, _, h0, _ = world.truth()

    def spun_deg() -> float:
        return (world.truth()[2] - h0) % 360.0

    deadline = time.monotonic() + 10.0
    while spun_deg() < 30.0:
        assert time.monotonic() < deadline, f"spun only {spun_deg():.1f} deg in 10 s"
        assert link.send(MotorCommand(time.monotonic(), 60.0, -60.0, "test"))  # board's OK
        time.sleep(0.02)
    assert spun_deg() < 90.0  # still turning at ~54 deg/s, not jumping
    # the driver reads a valid bearing that has turned clockwise too (behind the truth: the
    # CMPS10's filter lags)
    wait_until(lambda: compass.read(time.monotonic()).bearing_deg % 360.0 > 5.0, 5.0, "bearing")
    att = compass.read(time.monotonic())
    assert att.valid and att.bearing_deg < spun_deg() + 15.0
    # no more commands: the simulated board's watchdog (300 ms, set by the driver) stops it
    wait_until(lambda: world.vehicle.command_pct == (0.0, 0.0), 5.0, "watchdog stop")
    assert world.board.watchdog_trips == 1
    e0, n0, _, _ = world.truth()
    assert link.drive(50, 50)
    with pytest.raises(ValueError, match="left_pct"):
        link.send(MotorCommand(0.0, 101.0, 0.0))

    def moved_m() -> float:
        e1, n1, _, _ = world.truth()
        return float(np.hypot(e1 - e0, n1 - n0))

    wait_until(lambda: moved_m() > 0.05, 5.0, "forward motion")
    link.close()
    assert not link.healthy and world.vehicle.command_pct == (0.0, 0.0)

    # what crossed the pty, both ways, is the documented line protocol
    host = [(t, d) for kind, t, d in world.motor_wire if kind == "rx"]
    board = b"".join(d for kind, _, d in world.motor_wire if kind == "tx")
    lines = b"".join(d for _, d in host).decode("ascii").split("\n")
    assert lines[-1] == ""
    cmd = re.compile(r"^(W \d+|M -?\d{1,3} -?\d{1,3}|S|P|Q) #(\d{1,4})$")
    parsed = [cmd.match(line) for line in lines[:-1]]
    assert all(parsed), lines
    seqs = [int(m.group(2)) for m in parsed if m]
    assert seqs == list(range(1, len(seqs) + 1))  # x6wd counts from 1
    assert lines[0] == "W 300 #1" and lines[1] == "M 60 -60 #2"
    assert "M 50 50 #" in "\n".join(lines) and lines[-2].startswith("S #")  # close() stops
    replies = board.decode("ascii").splitlines()
    assert replies.count("EVT WATCHDOG") == 1
    assert [r for r in replies if r.startswith("OK")] == [f"OK #{s}" for s in seqs]


def test_motor_board_pty_answers_the_documented_protocol(world: hil.HilWorld) -> None:
    import serial

    with serial.Serial(world.plug_motor_board(), 115200, timeout=1.0) as port:

        def ask(line: bytes) -> bytes:
            port.write(line)
            return bytes(port.readline())

        assert ask(b"M 150 0 #7\n") == b"ERR #7 range\n"
        assert ask(b"m 10 -20\r\n") == b"OK\n"  # case-insensitive, CR ignored, no sequence
        assert ask(b"Q #8\n") == b"OK #8 10 -20 300\n"
        assert world.vehicle.command_pct == (10.0, -20.0)
        assert ask(b"X #9\n") == b"ERR #9 unknown\n"
        assert port.readline() == b"EVT WATCHDOG\n"  # 300 ms without a valid command
        assert world.vehicle.command_pct == (0.0, 0.0)


def test_sim_urls_take_no_options(world: hil.HilWorld) -> None:
    with pytest.raises(ConfigError, match="no path or options"):
        registry.open_gps_port("sim://?seed=3", opened(world))
    with pytest.raises(ConfigError, match="no path or options"):
        registry.open_motors("sim://board", opened(world))


def test_a_world_is_built_from_the_configuration_not_kept_by_the_module(tmp_path: Path) -> None:
    from sim_backend import protocol_sim
    from x6wd.core.config import Config

    assert not any(hasattr(hil, name) for name in ("configure", "world", "shutdown", "_WORLD"))
    cfg = Config(sim=SimConfig(seed=9, gps_rate_hz=2.0, gps_baud=38400, physics_hz=25.0))
    a, b = protocol_sim.open_backend(cfg), protocol_sim.open_backend(cfg.sim)
    try:
        assert a is not b  # two configurations, two worlds
        for w in (a, b):
            assert (w.scenario.seed, w.receiver.rate_hz, w.receiver.baud) == (9, 2.0, 38400)
            assert w.params.physics_hz == 25.0
    finally:
        a.close()
        b.close()
    with pytest.raises(ConfigError, match=r"sim\.scenario"):
        protocol_sim.check_config(SimConfig(scenario=str(tmp_path / "missing.toml")))


def wait_until(ok: Any, timeout_s: float, what: str) -> None:
    """Poll ``ok()`` until true; fail naming ``what`` after ``timeout_s`` (s)."""
    deadline = time.monotonic() + timeout_s
    while not ok():
        assert time.monotonic() < deadline, f"no {what} within {timeout_s:g} s"
        time.sleep(0.01)


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
        # until it serves and has a fix (the geofence needs one); generous for a loaded machine
        deadline = time.monotonic() + 60
        while True:
            r = client("status", "--json")
            tel = json.loads(r.stdout)["telemetry"] if r.returncode == 0 else None
            if tel and tel["fix_quality"] > 0:
                break
            assert time.monotonic() < deadline, r.stderr
            time.sleep(0.2)
        pipe = subprocess.Popen(
            [gpspipe, "-w", f"127.0.0.1:{gpsd}"], stdout=subprocess.PIPE, text=True
        )
        lines: list[str] = []
        read_at: list[float] = []  # the host's UTC clock when each line came

        def read() -> None:
            for x in pipe.stdout or ():
                read_at.append(time.time())
                lines.append(x)

        reader = threading.Thread(target=read, daemon=True)
        reader.start()
        # 8 m north of the start (the vehicle starts facing north)
        r = client("load", "--wp", "51.752072,-1.2577")
        assert r.returncode == 0, r.stderr
        r = client("start")
        assert r.returncode == 0, r.stderr
        deadline = time.monotonic() + 25
        while True:
            st = json.loads(client("status", "--json").stdout)
            if (st["mode"], st["state"]) == ("DONE", "MISSION_DONE"):
                break
            assert st["state"] != "HOLD", st
            assert time.monotonic() < deadline, st
            time.sleep(0.2)
        tel = st["telemetry"]
        assert tel["lat_deg"] > 51.752072 - 3e-5  # within the 2 m arrival box of the target

        def saw_it_move() -> bool:  # gpspipe's output catches up
            return any('"class":"TPV"' in x and json.loads(x).get("lat", 0) > 51.75204
                       for x in list(lines))  # fmt: skip

        wait_until(saw_it_move, 10.0, "TPV past the start from gpspipe")
        pipe.terminate()
        pipe.wait(10)
        reader.join(10)
        tpvs = [json.loads(x) for x in lines if '"class":"TPV"' in x]
        assert tpvs and all(t["mode"] == 3 for t in tpvs)
        assert max(t["lat"] for t in tpvs) > 51.75204  # the gpsd client saw it move
        # DEVICE: the simulated receiver's pty as opened, at hil.toml's [sim] 38400 baud, 2 Hz
        devices = [json.loads(x)["devices"] for x in lines if '"class":"DEVICES"' in x]
        assert len(devices) == 1 and len(devices[0]) == 1, devices
        dev = devices[0][0]
        assert dev["path"].startswith("/dev/") and (dev["bps"], dev["cycle"]) == (38400, 0.5)
        # the receiver's clock is the host's UTC, on its whole half seconds: cgps's "time
        # offset" (its clock minus TPV time) is the latency, not years back to the almanac's
        # day (gpspipe's output is read late on a loaded machine, never early)
        offsets = [
            t_read - datetime.fromisoformat(json.loads(x)["time"]).timestamp()
            for t_read, x in zip(read_at, lines, strict=True)
            if '"class":"TPV"' in x
        ]
        assert offsets and all(-0.05 < dt < 5.0 for dt in offsets), offsets
        assert sorted(offsets)[len(offsets) // 2] < 1.0, offsets
        assert all(t["time"][-5:] in (".000Z", ".500Z") for t in tpvs)
        # ... and its sky the almanac's
        skies = [json.loads(x) for x in lines if '"class":"SKY"' in x]
        assert skies and all(len(s["satellites"]) >= 8 for s in skies)
        assert {s["PRN"] for s in skies[-1]["satellites"]} != {2, 5, 10, 12, 15, 21, 24, 29}
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

    path = ROOT / "config" / "scenarios" / "open_field.toml"
    w = load_world(path)
    # nothing set in [sim]: the scenario as it is (relative paths: the packaged config/)
    p = hil.HilParams.from_config(SimConfig(scenario="scenarios/open_field.toml"))
    assert p.scenario == str(path) and p.load_world() == w
    # present keys override, even when equal to what another scenario would use
    p = hil.HilParams.from_config(
        SimConfig(scenario=str(path), seed=9, gps_rate_hz=2.0, gps_baud=38400,
                  start_north_m=-4.0)
    )  # fmt: skip
    sc = p.load_world()
    assert (sc.seed, sc.gnss.rate_hz, sc.gnss.baud) == (9, 2.0, 38400)
    assert sc.vehicle.start_north_m == -4.0 and sc.vehicle.start_east_m == w.vehicle.start_east_m
    assert (sc.origin, sc.start_utc, sc.gnss.fidelity) == (w.origin, w.start_utc, w.gnss.fidelity)
    # the packaged default, and the HIL config's own choice
    assert hil.HilParams.from_config(SimConfig()).scenario == str(DEFAULT_SCENARIO)
    from x6wd.core.config import load

    cfg = load(ROOT / "config" / "hil.toml")
    assert hil.HilParams.from_config(cfg.sim).load_world().gnss.rate_hz == 2.0
    with pytest.raises(ConfigError, match=r"sim\.scenario"):
        hil.HilParams.from_config(SimConfig(scenario=str(tmp_path / "missing.toml")))


def test_close_leaves_the_ptys_open_while_a_thread_still_runs(
    world: hil.HilWorld, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    # a thread that outlives close() would read or write whatever next takes its fd numbers
    # (once, the next test's sd_notify socket): those stay open until the thread is gone
    monkeypatch.setattr(hil, "CLOSE_JOIN_S", 0.2)
    world.plug_motor_board()
    fds = list(world._fds)
    release = threading.Event()
    stuck = threading.Thread(target=release.wait, args=(10.0,), name="stuck", daemon=True)
    stuck.start()
    world._threads.append(stuck)
    world.close()
    for fd in fds:
        os.fstat(fd)  # still this world's
    assert "['stuck'] still running" in caplog.text
    release.set()
    stuck.join(5.0)
    world.close()
    assert world._fds == []  # closed now (their numbers may already serve someone else)
