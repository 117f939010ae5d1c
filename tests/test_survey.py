"""The receiver engine of ``x6wd sim`` (a static survey without the robot): judged against the
robot engine on the same scenario and seed, run in the same test."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

import sim_backend.mission as mission
import sim_backend.runs as runs
from drivers.gps_nmea import GpsDecoder
from sim_backend.gnss import ar1_filter
from sim_backend.runs import engine_for
from sim_backend.survey import run_survey
from sim_backend.world import load_world, loads_world
from x6wd.core.recorder import read_recording
from x6wd.core.records import GpsFix

ROOT = Path(__file__).resolve().parent.parent
SCENARIOS = ROOT / "config" / "scenarios"
OPEN_FIELD = SCENARIOS / "open_field.toml"

# 4 Hz at 9600 baud: more text than the line carries, so the transmit buffer drops sentences;
# a GPS effect the receiver applies and a compass effect it cannot (no compass here).
LOADED_UART = f"""include = ["{OPEN_FIELD}"]
name = "open field, 4 Hz at 9600 baud, with effects"
[gnss]
rate_hz = 4.0
baud = 9600
[compass]
rate_hz = 20.0
[[effects]]
name = "gauss_markov"
sigma_m = 1.5
tau_s = 30.0
[[effects]]
name = "hard_iron"
bx_ut = 2.0
by_ut = 0.0
"""


def _nmea_records(out: Path) -> list[str]:
    with open(out / "recording.jsonl") as f:
        return [line for line in f if '"type":"nmea"' in line]


def _summary(out: Path) -> dict[str, Any]:
    d: dict[str, Any] = json.loads((out / "summary.json").read_text())
    return d


def _both(world: Any, tmp: Path, seed: int, duration_s: float) -> tuple[Path, Path]:
    robot, receiver = tmp / "robot", tmp / "receiver"
    mission.run_mission(world, robot, seed=seed, duration_s=duration_s)
    run_survey(world, receiver, seed=seed, duration_s=duration_s)
    return robot, receiver


def _assert_same_receiver(robot: Path, receiver: Path) -> None:
    """The receiver's bytes, what the recorder kept of them, and every raw-GPS figure."""
    assert (receiver / "gps.nmea").read_bytes() == (robot / "gps.nmea").read_bytes()
    assert _nmea_records(receiver) == _nmea_records(robot)
    a, b = _summary(robot), _summary(receiver)
    for key in ("fixes", "fixes_valid", "sim_time_s", "waypoint_count"):
        assert a[key] == b[key], key
    for key in ("dispersion_lat_m", "dispersion_lon_m", "mean_hdop", "mean_sats_used"):
        assert b[key] == pytest.approx(a[key], rel=1e-9, abs=1e-9), key
    for key, v in a["raw_error"].items():
        assert b["raw_error"][key] == pytest.approx(v, rel=1e-9, abs=1e-9), key
    assert b["extra"]["nmea_bytes"] == a["extra"]["nmea_bytes"]
    assert b["filtered_error"]["n"] == 0 and b["extra"]["engine"] == "receiver"
    ends = [
        [r.t_mono for r in read_recording(d / "recording.jsonl") if r.type == "event"][-1]
        for d in (robot, receiver)
    ]
    assert ends[1] == ends[0]


@pytest.mark.parametrize("name", ["open_field", "building_window"])
def test_a_survey_matches_the_robot_engine(tmp_path: Path, name: str) -> None:
    """Open sky and the room by the window (walls, roof, materials): the same bytes, records
    and raw figures as the robot engine, which decodes them with the daemon's decoder."""
    world = load_world(SCENARIOS / f"{name}.toml")
    _assert_same_receiver(*_both(world, tmp_path, seed=7, duration_s=90.0))


def test_both_recordings_give_the_same_fixes_to_their_readers(tmp_path: Path) -> None:
    """The robot engine records the daemon's fixes, the receiver engine the sentences only:
    `drivers.gps_recording.recorded_gps` (what `x6wd calibrate gnss` reads) gives the same
    fixes and sky views from both."""
    from drivers.gps_recording import recorded_gps

    robot, receiver = _both(load_world(OPEN_FIELD), tmp_path, seed=4, duration_s=30.0)
    from_robot = list(recorded_gps(robot / "recording.jsonl"))
    assert len(from_robot) == 62
    assert list(recorded_gps(receiver / "recording.jsonl")) == from_robot


def test_a_loaded_uart_and_effects_match_the_robot_engine(tmp_path: Path) -> None:
    """4 Hz at 9600 baud (sentences dropped by the transmit buffer) with a GPS layer: the
    same sentences dropped; the compass layer is reported as not run."""
    world = loads_world(LOADED_UART, base_dir=ROOT)
    robot, receiver = _both(world, tmp_path, seed=2, duration_s=40.0)
    _assert_same_receiver(robot, receiver)
    extra = _summary(receiver)["extra"]
    assert extra["uart_dropped_sentences"] > 0
    assert extra["effects_applied"] == ["gauss_markov"]
    assert extra["effects_skipped"] == ["hard_iron: no compass in the receiver engine"]


SEED_LEVEL = f"""include = ["{OPEN_FIELD}"]
name = "seed-level receiver, 2 Hz, 4 decimals, 4800 baud, delayed and held"
[gnss]
fidelity = "seed"
rate_hz = 2.0
nmea_decimals = 4
baud = 4800
[compass]
rate_hz = 10.0
[[effects]]
name = "latency"
delay_s = 0.7
[[effects]]
name = "outages"
mean_up_s = 20.0
mean_down_s = 5.0
[[effects]]
name = "static_hold"
exit_distance_m = 0.3
"""


def test_the_seed_level_receiver_with_delay_outages_and_hold_matches(tmp_path: Path) -> None:
    """The other fidelity, another rate, print and baud, and layers that look at the antenna's
    past (latency) or hold the position: still the robot engine's bytes and figures."""
    world = loads_world(SEED_LEVEL, base_dir=ROOT)
    _assert_same_receiver(*_both(world, tmp_path, seed=5, duration_s=120.0))


def test_a_high_precision_print_matches(tmp_path: Path) -> None:
    """7 decimals of minutes (a scenario of a u-blox M8/F9 in high-precision NMEA mode): the
    robot engine's bytes, and raw figures computed from the printed positions."""
    world = loads_world(
        f'include = ["{OPEN_FIELD}"]\nname = "7 decimals"\n[gnss]\nnmea_decimals = 7\n',
        base_dir=ROOT,
    )
    robot, receiver = _both(world, tmp_path, seed=6, duration_s=40.0)
    _assert_same_receiver(robot, receiver)
    gga = next(ln for ln in (robot / "gps.nmea").read_text().splitlines() if "GGA," in ln)
    assert len(gga.split(",")[2].split(".")[1]) == 7


@pytest.mark.slow
def test_chunked_surveys_match_too(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Chunk boundaries (40 epochs here) fall on the same epochs in both engines."""
    monkeypatch.setattr(mission, "STATIC_CHUNK_EPOCHS", 40)
    monkeypatch.setattr(runs, "STATIC_CHUNK_EPOCHS", 40)
    import sim_backend.survey as survey

    monkeypatch.setattr(survey, "STATIC_CHUNK_EPOCHS", 40)
    _assert_same_receiver(*_both(load_world(OPEN_FIELD), tmp_path, seed=3, duration_s=100.0))


def test_the_recording_decodes_to_the_summarys_fixes(tmp_path: Path) -> None:
    """The recording's sentences, fed to the daemon's decoder at their arrival times, give one
    valid fix per epoch at the positions whose errors the summary states."""
    world = load_world(OPEN_FIELD)
    s = run_survey(world, tmp_path, seed=11, duration_s=60.0)
    dec = GpsDecoder(emit_sentences=False)
    fixes: list[GpsFix] = []
    for r in read_recording(tmp_path / "recording.jsonl"):
        if r.type == "nmea":
            line = (r.data["text"] + "\r\n").encode()
            fixes += [x for x in dec.feed(line, r.t_mono) if type(x) is GpsFix]
    assert dec.counters.checksum_failures == 0
    assert len(fixes) == s.fixes == 61 and all(f.valid for f in fixes)
    assert s.raw_error.n == 61 and 0.1 < s.raw_error.cep50_m < 20.0


def test_auto_picks_the_receiver_engine_only_for_a_survey() -> None:
    assert engine_for(load_world(OPEN_FIELD)) == "receiver"
    assert engine_for(load_world(SCENARIOS / "default.toml")) == "robot"
    assert engine_for(load_world(OPEN_FIELD), "robot") == "robot"
    with pytest.raises(ValueError, match="engine must be one of"):
        engine_for(load_world(OPEN_FIELD), "fast")


def _sim(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "x6wd", "sim", *args, "--quiet"],
        capture_output=True, text=True, timeout=300, cwd=ROOT,
    )  # fmt: skip


def test_cli_default_is_the_receiver_engine_and_robot_runs_the_ekf(tmp_path: Path) -> None:
    """``x6wd sim`` on a survey: the receiver engine, without importing the robot's code;
    ``--engine robot``: the robot's loop with its filtered row; a bad engine: exit 2."""
    probe = (
        "import sys, runpy\n"
        f"sys.argv = ['x6wd', 'sim', {str(OPEN_FIELD)!r}, '--duration', '20', '--out',"
        f" {str(tmp_path / 'r')!r}, '--quiet']\n"
        "from x6wd.app.cli import main\n"
        "code = main()\n"
        "robot = [m for m in sys.modules if m.startswith(('x6wd.nav.controller', 'x6wd.loop'))]\n"
        "print('ROBOT-MODULES', robot, code)\n"
    )
    p = subprocess.run(
        [sys.executable, "-c", probe], capture_output=True, text=True, timeout=300, cwd=ROOT
    )
    assert p.returncode == 0, p.stderr
    assert "ROBOT-MODULES [] 0" in p.stdout
    assert "filtered         not run" in p.stdout
    p = _sim(str(OPEN_FIELD), "--duration", "20", "--out", str(tmp_path / "b"), "--engine", "robot")
    assert p.returncode == 0, p.stderr
    filtered = next(line for line in p.stdout.splitlines() if "filtered" in line)
    assert math.isfinite(float(filtered.split()[1]))
    p = _sim(str(OPEN_FIELD), "--out", str(tmp_path / "c"), "--engine", "fast")
    assert p.returncode == 2 and "--engine" in p.stderr


@pytest.mark.parametrize("tau_s", [0.05, 0.4, 1.0, 7.0, 300.0, 1e6])
@pytest.mark.parametrize("cols", [0, 3])
def test_ar1_filter_is_the_recursion(tau_s: float, cols: int) -> None:
    """The numpy first-order filter against the step-by-step recursion (1-D and 2-D)."""
    rng = np.random.default_rng(int(tau_s * 100) + cols)
    n = 5000
    x = rng.standard_normal((n, cols) if cols else n)
    y0 = rng.standard_normal(cols) if cols else np.array(rng.standard_normal())
    phi, gain = math.exp(-1.0 / tau_s), math.sqrt(-math.expm1(-2.0 / tau_s))
    want = np.empty_like(x)
    prev = np.array(y0, dtype=float)
    for k in range(n):
        prev = phi * prev + gain * x[k]
        want[k] = prev
    got = ar1_filter(x, phi, gain, y0)
    assert got.shape == x.shape
    assert np.max(np.abs(got - want)) < 1e-12
    assert ar1_filter(x[:0], phi, gain, y0).shape == x[:0].shape


@pytest.mark.parametrize(
    "lines",
    [
        [b"$GPGGA,1*00\r\n", b"$GPRMC,2*00\r\n"],
        [b'$GPTXT,"quoted" \\ back\r\n', b"\xff\xfe binary\r\n", b"tab\there\r\n"],
        [b"$GPGSA,ok\r\r\n", b"$GPVTG,lf only\n"],
    ],
)
def test_bulk_nmea_records_are_the_recorders_lines(tmp_path: Path, lines: list[bytes]) -> None:
    """The receiver engine's bulk writer against the daemon's Recorder, line for line, for
    plain sentences, text JSON must escape, and odd line endings; across a day boundary."""
    from datetime import datetime, timedelta
    from io import StringIO

    from sim_backend.survey import _RecordLines
    from x6wd.core.recorder import Recorder

    start = datetime(2020, 12, 31, 23, 59, 59)
    times = [0.4125 + 0.3 * k for k in range(len(lines))]
    now = [0.0]
    rec = Recorder(
        tmp_path / "r.jsonl", clock=lambda: now[0],
        utc_clock=lambda: start + timedelta(seconds=now[0]),
    )  # fmt: skip
    for t, line in zip(times, lines, strict=True):
        now[0] = t
        rec.record_nmea(line.rstrip(b"\r\n"), t)
    rec.close()
    out = StringIO()
    pairs = list(zip(times, lines, strict=True))
    n = _RecordLines(np.datetime64(start, "us")).write_nmea(out, pairs)
    assert n == sum(map(len, lines))
    assert out.getvalue() == (tmp_path / "r.jsonl").read_text()


def test_a_reader_that_goes_away_is_exit_141_without_a_traceback(tmp_path: Path) -> None:
    """``x6wd sim ... | head -1`` when head has already gone: the summary cannot be printed;
    the run's files are written, the exit code is the shell's for SIGPIPE, and nothing is
    dumped on stderr. (The pipe's reader is closed before the run starts: no race.)"""
    read_fd, write_fd = os.pipe()
    os.close(read_fd)
    try:
        p = subprocess.run(
            [sys.executable, "-m", "x6wd", "sim", str(OPEN_FIELD), "--duration", "5",
             "--out", str(tmp_path / "o"), "--quiet"],
            stdout=write_fd, stderr=subprocess.PIPE, cwd=ROOT, timeout=120,
        )  # fmt: skip
    finally:
        os.close(write_fd)
    err = p.stderr.decode()
    assert p.returncode == 141, err
    assert "Traceback" not in err
    assert (tmp_path / "o" / "summary.json").exists()


def test_recording_lines_from_cells_are_the_general_writers(tmp_path: Path) -> None:
    """The recording's ``nmea`` lines built as text blocks from a chunk's sentence cells
    against the general writer on the same (arrival, sentence) pairs: a real receiver's
    chunk across midnight with a banner still on the wire, one whose UART drops sentences,
    and sentences JSON must escape (the general writer's path then)."""
    from dataclasses import replace

    from sim_backend.nmea_out import NmeaCells, NmeaFormatter
    from sim_backend.receiver import SimRandom, UartTx, build_receiver
    from sim_backend.survey import _RecordLines

    world = replace(load_world(OPEN_FIELD), start_utc=load_world(OPEN_FIELD).start_utc.replace(
        hour=23, minute=58))  # fmt: skip
    rx = build_receiver(world, SimRandom.from_seed(3))
    t = np.arange(0.0, 300.0)
    b = rx.batch(t, np.zeros((t.size, 3)), np.zeros((t.size, 3)))
    start = np.datetime64(world.start_utc.replace(tzinfo=None), "us")
    for baud in (9600, 2400):
        cells = NmeaFormatter().format_cells(b)
        uart = UartTx(baud)
        uart.send([b"$GPTXT,banner*00\r\n"] * 5, 0.0)
        arrive, sent = uart.send_table(cells.lengths, t)
        assert (uart.dropped == 0) == (baud == 9600)
        text = cells.text()
        lines = [
            row.tobytes().replace(b"\0", b"")
            for row in cells.cells.reshape(-1, cells.cells.shape[2])
        ]
        pairs = [
            (float(a), x) for a, x, s in zip(arrive.ravel(), lines, sent.ravel(), strict=True) if s
        ]
        want, carried = _RecordLines(start).nmea_lines(pairs)
        assert _RecordLines(start).nmea_cells(text, cells, arrive, sent) == (
            want.encode(), carried,
        )  # fmt: skip
    odd = NmeaCells.of_bursts([b'$GPTXT,"q" \\ x*00\r\n$GPRMC,\xff*00\r\n', b"$A*00\r\n"])
    arrive, sent = np.zeros((2, 9)), np.zeros((2, 9), dtype=bool)
    arrive[0, :2], arrive[1, 0] = (1.5, 2.25), 3.0
    sent[0, :2] = sent[1, 0] = True
    pairs = [(1.5, b'$GPTXT,"q" \\ x*00\r\n'), (2.25, b"$GPRMC,\xff*00\r\n"), (3.0, b"$A*00\r\n")]
    want, carried = _RecordLines(start).nmea_lines(pairs)
    got = _RecordLines(start).nmea_cells(b"".join(x for _t, x in pairs), odd, arrive, sent)
    assert got == (want.encode(), carried)


def test_float_reprs_in_a_block_are_pythons() -> None:
    """The recording's ``t_mono`` texts: ``repr`` once per binade and fraction."""
    from sim_backend.survey import _repr_pieces
    from sim_backend.textblocks import joined

    rng = np.random.default_rng(1)
    values = np.concatenate(
        (
            rng.random(5000) * 1e5, rng.random(2000), np.arange(0, 600, 0.25),
            2.0 ** np.arange(-30, 60), np.cumsum(rng.integers(30, 80, 20000) / 960.0) + 2040.0,
            [0.0, -0.0, 1e-5, 1e16, 2**52 - 0.5, 2**52 + 1.0, math.nan, math.inf, -1.5,
             9.999999999999998, 10.000000000000002, 1.0000000000000002, 0.9999999999999999],
        )
    )  # fmt: skip
    got = [row.tobytes().replace(b"\0", b"").decode() for row in joined(_repr_pieces(values))]
    assert got == [repr(v) for v in values.tolist()]


def test_the_summarys_dops_are_the_gga_texts_read_back() -> None:
    """The mean HDOP's values as numbers equal the GGA texts read back, edges included."""
    from sim_backend.nmea_out import dop_texts
    from sim_backend.survey import _printed_dops

    rng = np.random.default_rng(0)
    edges = [math.nan, math.inf, -math.inf, -0.0, 0.0, -1.0, 0.005, 0.015, 99.99, 99.990001]
    values = np.concatenate(
        (edges, [1e-300, 1.125, 2.675, 0.125], rng.uniform(-5, 120, 20000),
         rng.integers(0, 10000, 5000) / 100 + 0.005)
    )  # fmt: skip
    assert np.array_equal(_printed_dops(values), np.array(dop_texts(values), dtype=float))


def test_a_gps_rate_the_robot_loop_cannot_step_runs_on_the_receiver_engine(
    tmp_path: Path,
) -> None:
    """compass 5 Hz, GPS 4 Hz: the robot engine's loop (a whole number of compass ticks per
    epoch) cannot step it and says so; the receiver engine has no loop and runs it, its
    epochs those of a robot whose compass steps at the GPS rate."""
    scenario = tmp_path / "four_hz.toml"
    scenario.write_text(f'include = ["{OPEN_FIELD}"]\n[gnss]\nrate_hz = 4.0\n')
    p = _sim(str(scenario), "--duration", "5", "--out", str(tmp_path / "r"))
    assert p.returncode == 0, p.stderr
    p = _sim(str(scenario), "--duration", "5", "--out", str(tmp_path / "b"), "--engine", "robot")
    assert p.returncode == 2
    assert "the robot engine's loop steps at it" in p.stderr, p.stderr
    # (attitude_stale_s over 2.5 periods of a 4 Hz compass, as a scenario's limits must be)
    robot = loads_world(
        scenario.read_text() + "[compass]\nrate_hz = 4.0\n[safety]\nattitude_stale_s = 1.0\n",
        tmp_path,
    )
    mission.run_mission(robot, tmp_path / "robot", seed=1, duration_s=5.0)
    _assert_same_receiver(tmp_path / "robot", tmp_path / "r")
