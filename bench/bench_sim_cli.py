"""The simulator on the CLI's path (issue 16, item 1): ``x6wd sim`` as a user runs it.

Each case is one ``python -m x6wd sim SCENARIO --duration D --out TMP --quiet`` process
(interpreter start, imports, the whole loop through the real decoders, compass driver,
runner and controller, the recording, the NMEA and truth files, the summary and the plot),
timed by its own CPU time (user + system, from ``wait4``, so other load on the machine does
not count) and its peak resident memory (its own ``VmHWM``). Speed = simulated s / CPU s.

Cases and targets:

- ``config/scenarios/open_field.toml`` with its defaults (a static survey: ``auto`` runs it
  on the receiver engine), 10 h: >= 10,000x real time; peak memory <= 300 MB;
- the same with ten buildings (bench_sim's ring: 12 x 8 m, 10 m high, 90 m out), 10 h:
  >= 5,000x; peak memory <= 300 MB;
- both surveys again with ``--engine robot`` (the robot's whole loop at the compass rate
  around the same receiver): the same targets, reported beside the default's;
- a closed-loop 1 h mission: ``default.toml`` (20 Hz compass, the shipped navigation) with
  a route long enough to drive for the whole hour (laps of its 25 m square): >= 3,000x.
- a town: the open field with 100 buildings on five rings (90-250 m out), 10 h, receiver
  engine: no speed target; peak memory <= 300 MB (it peaked at 340 MB for one hour before
  the wall trace worked in blocks of epochs).

Anchors measured in the same run: ``GnssModel.batch`` alone on the open-field case's epochs
(the batched physics, in this process), and the robot's own loop alone (a ``Runner`` with
the shipped controller fed the robot-engine survey's recorded compass, odometry and GPS
records, nothing recorded): what no simulator change can take the robot engine past.
``--quick``: 1 h open field (with and without buildings) and a 10 min mission.
Run: ``python -m bench.bench_sim_cli [--quick]``.

Last measured 2026-12-01 (three full runs on b4d393b; docs/simulator.md, "Speed"): receiver
engine, open field 10 h 18,200x (14,970-19,200x; 0.58-0.65 of the physics anchor, which read
26,000-32,200x), ten buildings 13,800x (12,200-14,400x), 113-114 MB; robot engine 331-409x
and 330-363x, 124 MB; mission 69-78x, 107 MB. The session-start code (ad4fa7e), run twice in
the same session: open field 10,500x and 13,000x (0.34 and 0.37 of its anchors). The
children inherit the environment: with ``PYTHONDONTWRITEBYTECODE=1``, as in that session,
every run compiles the project's modules (0.1-0.17 s of a 10 h survey's ~2 s).
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from bench._common import PEAK_CHILD, Row, cli, print_table

ROOT = Path(__file__).resolve().parent.parent
SCENARIOS = ROOT / "config" / "scenarios"
MB = 1e6


def _buildings_toml(n: int = 10, rings: int = 1) -> str:
    """``n`` closed 12 x 8 m buildings, 10 m high, on ``rings`` rings 90, 130 ... m out (one
    ring: bench_sim's scene)."""
    out = []
    for i in range(n):
        a = 2 * math.pi * i / n
        r = 90 + 40 * (i % rings)
        cx, cy = r * math.cos(a), r * math.sin(a)
        out.append(
            f"[[buildings]]\nx0_m = {cx - 6:.3f}\ny0_m = {cy - 4:.3f}\n"
            f"x1_m = {cx + 6:.3f}\ny1_m = {cy + 4:.3f}\nheight_m = 10.0\n"
        )
    return "\n".join(out)


def _mission_toml(laps: int = 120) -> str:
    """default.toml's 25 m square, driven ``laps`` times (more than an hour of driving)."""
    square = [(0.0, 25.0), (25.0, 25.0), (25.0, 0.0), (0.0, 0.0)]
    pts = ", ".join(f"[{e}, {n}]" for _ in range(laps) for e, n in square)
    return f"[mission]\nwaypoints_enu = [{pts}]\n"


def _scenario(tmp: Path, name: str, base: str, extra: str) -> Path:
    path = tmp / f"{name}.toml"
    path.write_text(f'include = ["{SCENARIOS / base}"]\nname = "{name}"\n{extra}')
    return path


def _run_cli(scenario: Path, duration_s: float, out: Path, *extra: str) -> dict[str, float]:
    """One ``x6wd sim`` process (``extra`` arguments added): its CPU s, peak RSS (bytes),
    simulated s, the run's own wall s (before the plot)."""
    args = ["sim", str(scenario), "--duration", str(duration_s), "--out", str(out), "--quiet"]
    args += list(extra)
    hwm = out.with_suffix(".hwm")
    cmd = [sys.executable, "-c", PEAK_CHILD, str(hwm), *args]
    a = time.perf_counter()
    proc = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.DEVNULL)
    _pid, status, ru = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - a
    proc.returncode = os.waitstatus_to_exitcode(status)
    if proc.returncode not in (0, 1):  # 1: a mission not completed within the duration
        raise RuntimeError(f"x6wd {' '.join(args)} exited {proc.returncode}")
    summary = json.loads((out / "summary.json").read_text())
    return {
        "cpu_s": ru.ru_utime + ru.ru_stime,
        "rss_b": float(hwm.read_text()),
        "sim_s": float(summary["sim_time_s"]),
        "loop_wall_s": float(summary["wall_time_s"]),
        "wall_s": wall,
    }


def _physics_anchor(duration_s: float) -> float:
    """CPU s of ``GnssModel.batch`` alone over the open-field case's epochs (one call)."""
    from sim_backend.receiver import SimRandom, build_gnss_model
    from sim_backend.world import load_world

    world = load_world(SCENARIOS / "open_field.toml")
    model = build_gnss_model(world, SimRandom.from_seed(world.seed).gnss)
    t = np.arange(0.0, duration_s + 1e-9, 1.0 / world.gnss.rate_hz)
    o = world.origin
    n = t.shape[0]
    alt = np.full(n, o.alt_m + world.vehicle.antenna_height_m)
    a = time.process_time()
    model.batch(t, np.full(n, o.lat_deg), np.full(n, o.lon_deg), alt, np.zeros((n, 3)))
    return time.process_time() - a


def _robot_loop_anchor(recording: Path, chunk: int = 50_000) -> tuple[float, float]:
    """CPU s and simulated s of the robot's own loop fed a run's recorded device inputs
    (decoded ``chunk`` records at a time, outside the timing)."""
    from sim_backend.world import load_world
    from x6wd.core.recorder import decode_record, read_recording
    from x6wd.core.records import Attitude, GpsFix, GpsSky, WheelOdometry
    from x6wd.loop.runner import Runner
    from x6wd.nav.controller import Controller

    world = load_world(SCENARIOS / "open_field.toml")
    ctrl = Controller(
        world.navigation, world.safety, float(world.compass.get("declination_deg", 0.0)),
        odometry=world.odometry, gnss_noise=world.gnss_noise, failsafe=world.failsafe,
    )  # fmt: skip
    now = [0.0]
    runner = Runner(ctrl, world.safety, lambda: now[0], motors=lambda _c: None)
    calls: dict[type, Callable[[Any], None]] = {
        Attitude: runner.attitude,
        WheelOdometry: runner.odometry,
        GpsFix: runner.gps_record,
        GpsSky: runner.gps_record,
    }
    cpu_s = 0.0
    batch: list[Any] = []

    def feed() -> float:
        a = time.process_time()
        for x in batch:
            now[0] = x.t_s
            calls[type(x)](x)
        batch.clear()
        return time.process_time() - a

    for rec in read_recording(recording):
        if rec.type in ("attitude", "odometry", "fix", "sky"):
            batch.append(decode_record(rec))
            if len(batch) >= chunk:
                cpu_s += feed()
    cpu_s += feed()
    return cpu_s, now[0]


def _dur(s: float) -> str:
    return f"{s / 3600:g} h" if s >= 3600 else f"{s / 60:g} min"


def run(quick: bool = False) -> list[Row]:
    """All figures; ``quick`` runs 1 h surveys and a 10 min mission instead of 10 h and 1 h."""
    survey_s = 3600.0 if quick else 36000.0
    mission_s = 600.0 if quick else 3600.0
    rows: list[Row] = []
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        open_field = SCENARIOS / "open_field.toml"
        walled = _scenario(tmp, "open-field-10-buildings", "open_field.toml", _buildings_toml())
        town = _scenario(tmp, "open-field-100-buildings", "open_field.toml",
                         _buildings_toml(100, rings=5))  # fmt: skip
        mission = _scenario(tmp, "mission-1h", "default.toml", _mission_toml())
        physics_s = _physics_anchor(survey_s)
        physics_x = survey_s / physics_s
        hours = _dur(survey_s)
        of = _run_cli(open_field, survey_s, tmp / "of")
        wb = _run_cli(walled, survey_s, tmp / "wb")
        tw = _run_cli(town, survey_s, tmp / "tw")
        of_robot = _run_cli(open_field, survey_s, tmp / "ofr", "--engine", "robot")
        loop_cpu_s, loop_sim_s = _robot_loop_anchor(tmp / "ofr" / "recording.jsonl")
        wb_robot = _run_cli(walled, survey_s, tmp / "wbr", "--engine", "robot")
        ms = _run_cli(mission, mission_s, tmp / "ms")
    rows.append(Row("sim_cli", f"anchor: GnssModel.batch alone, {hours} open field",
                    physics_x, "x real time", None, "",
                    f"{physics_s:.2f} s CPU, one call"))  # fmt: skip
    rows.append(Row("sim_cli", "anchor: robot's loop alone on the survey's inputs",
                    loop_sim_s / loop_cpu_s, "x real time", None, "",
                    f"{loop_cpu_s:.1f} s CPU: runner, controller, EKF"))  # fmt: skip
    cases = (
        (f"open_field.toml, {hours} (CLI default: receiver engine)", of, 10_000.0),
        (f"open field + 10 buildings, {hours} (CLI default: receiver engine)", wb, 5_000.0),
        (f"open_field.toml, {hours} (--engine robot)", of_robot, 10_000.0),
        (f"open field + 10 buildings, {hours} (--engine robot)", wb_robot, 5_000.0),
        (f"closed-loop mission 20 Hz compass, {_dur(mission_s)} (CLI)", ms, 3_000.0),
        # no speed target; its memory shows the wall trace works in bounded blocks
        (f"open field + 100 buildings, {hours} (CLI default: receiver engine)", tw, None),
    )
    for label, res, target in cases:
        speed = res["sim_s"] / res["cpu_s"]
        rows.append(Row("sim_cli", label + ", CPU", speed, "x real time", target,
                        "" if target is None else "x target",
                        f"{res['cpu_s']:.1f} s CPU ({res['wall_s']:.1f} s wall, run "
                        f"{res['loop_wall_s']:.1f} s); {speed / physics_x:.3f} of the "
                        f"physics anchor"))  # fmt: skip
    for label, res, _target in cases:
        rows.append(Row("sim_cli", f"peak memory: {label}", res["rss_b"] / MB, "MB", 300.0,
                        "MB limit", "the process's peak resident set"))  # fmt: skip
    return rows


if __name__ == "__main__":
    print_table(run(quick=cli(__doc__).parse_args().quick))
