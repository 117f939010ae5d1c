"""A newcomer's walkthrough, round 11: what a first user of the README's tour runs into.

1. ``x6wd calibrate gnss --static`` alone wrote a standing receiver's ``re_m`` without a word,
   although pasted into the robot's configuration it makes the EKF worse
   (docs/gnss_calibration.md, "--static alone").
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np

from tests.test_calibrate_gnss import (
    loop_track,
    sim_fixes,
    truth_series,
    world,
    write_recording,
    write_truth_csv,
)
from x6wd.core import config

ROOT = Path(__file__).resolve().parent.parent
X6WD = [sys.executable, "-m", "x6wd"]


def _run(argv: list[str], cwd: Path, timeout: float = 240.0) -> subprocess.CompletedProcess[str]:
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    return subprocess.run(
        [*X6WD, *argv], cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout
    )


# ------------------------------------------------------------------ 1. calibrate gnss --static


def test_static_alone_warns_above_re_m_and_on_stderr(tmp_path: Path) -> None:
    # the README's tour: 10 min standing on a known point, then the static calibration
    sim = _run([
        "sim", str(ROOT / "config" / "scenarios" / "open_field.toml"), "--out",
        str(tmp_path / "static"), "--quiet",
    ], tmp_path)  # fmt: skip
    assert sim.returncode == 0, sim.stderr
    out = tmp_path / "gnss.toml"
    r = _run([
        "calibrate", "gnss", "--static", str(tmp_path / "static" / "recording.jsonl"),
        "--ref-lat", "51.752", "--ref-lon", "-1.2577", "--out", str(out),
    ], tmp_path)  # fmt: skip
    assert r.returncode == 0, r.stderr
    warn = [ln for ln in r.stderr.splitlines() if "WARNING" in ln]
    assert len(warn) == 1, r.stderr
    assert warn[0].startswith("x6wd calibrate: WARNING: re_m is a standing receiver's white part")
    for part in ("--drive", "Experiment 3", "do not paste it alone", "re_m (1.0 as shipped)"):
        assert part in warn[0], warn[0]
    lines = out.read_text().splitlines()
    at = next(i for i, ln in enumerate(lines) if ln.startswith("re_m = "))
    # the comment line right above re_m, the same text as on stderr
    assert lines[at - 1] == "# WARNING: " + warn[0].removeprefix("x6wd calibrate: WARNING: ")
    assert lines[at - 2] == "[gnss_noise]"
    # still a fragment the daemon loads (its measured value kept, with the warning over it)
    assert 0.0 < config.loads(out.read_text()).gnss_noise.re_m < 0.5


def test_static_with_drives_writes_no_standing_warning(tmp_path: Path) -> None:
    w_static = world(re=0.8, ase=0.0, grid=[[0.0]])
    n = 600
    static = write_recording(
        tmp_path / "static.jsonl", sim_fixes(w_static, 3, np.arange(n, dtype=float),
                                             np.zeros((n, 3)))
    )  # fmt: skip
    w = world(re=0.8, ase=0.0)
    t, pos = loop_track(laps=2)
    drive = write_recording(tmp_path / "drive.jsonl", sim_fixes(w, 4, t, pos))
    ref = write_truth_csv(tmp_path / "truth.csv", truth_series(w, t, pos))
    o = w_static.origin
    r = _run([
        "calibrate", "gnss", "--static", str(static), "--ref-lat", str(o.lat_deg),
        "--ref-lon", str(o.lon_deg), "--drive", str(drive), "--reference", str(ref),
    ], tmp_path)  # fmt: skip
    assert r.returncode == 0, r.stderr
    assert "standing receiver" not in r.stderr and "standing receiver" not in r.stdout
    assert "[gnss_noise]" in r.stdout


# ------------------------------------------------------------------ 3. sim summary: paused


def test_a_run_ending_paused_says_paused_with_its_start_and_reason(tmp_path: Path) -> None:
    # the default scenario with a 45 s GPS outage from 20 s and a robot that holds at once
    # without a fix: the failsafe pauses the mission at ~50 s and it stays paused to 400 s
    scenario = tmp_path / "outage.toml"
    scenario.write_text(
        (ROOT / "config" / "scenarios" / "default.toml").read_text()
        + '\n[[effects]]\nname = "outage"\nstart_s = 20.0\nduration_s = 45.0\n'
    )
    robot = (ROOT / "config" / "x6wd.toml").read_text()
    assert "\ngps_outage_max_m = 20.0" in robot
    cfg = tmp_path / "robot.toml"
    cfg.write_text(robot.replace("\ngps_outage_max_m = 20.0", "\ngps_outage_max_m = 0.0"))
    r = _run(["sim", str(scenario), "--config", str(cfg), "--quiet", "--out",
              str(tmp_path / "out")], tmp_path)  # fmt: skip
    assert r.returncode == 1, r.stderr  # 1: the mission not completed
    head = next(ln for ln in r.stdout.splitlines() if ln.startswith("scenario "))
    paused = next(ln for ln in r.stdout.splitlines() if ln.strip().startswith("paused "))
    # the detail line: "paused 349.9 s (since 50.1 s: no valid fix for 30 s)"
    since = paused[paused.index("(since ") : paused.rindex(")") + 1]
    assert "no valid fix for 30 s" in since, paused
    assert head.endswith(f"mission NOT completed: the mission was paused {since} when the run "
                         "ended at 400 s"), head  # fmt: skip
    assert "on hold" not in head
