"""x6wd sweep runs each cell on the engine ``x6wd sim`` picks (an outside audit, round 22): a
survey sweep over ``gnss.rate_hz = [1.0, 2.0]`` of ``open_field.toml`` (a 5 Hz compass) was
exit 2 — the robot engine's clock cannot step 5 Hz and 2 Hz — while ``x6wd sim`` ran it on
the receiver engine, and the summary's replay line ran a survey cell on the other engine than
the sweep had. Real runs on the inline executor, the replay through the real CLI."""

from __future__ import annotations

import json
import math
import subprocess
from pathlib import Path

import pytest

from sim_backend import sweep
from sim_backend.executor import Executor
from tests.conftest import ROOT
from tests.test_sweep import DEFAULT, X6WD, sweep_file
from x6wd.core.errors import ConfigError

OPEN_FIELD = ROOT / "config" / "scenarios" / "open_field.toml"


def test_a_survey_runs_on_the_receiver_engine_and_its_replay_agrees(tmp_path: Path) -> None:
    body = 'seeds = 1\n[set]\nduration_s = 20.0\n[grid]\n"gnss.rate_hz" = [1.0, 2.0]\n'
    spec = sweep.load_sweep(sweep_file(tmp_path, body, (OPEN_FIELD, DEFAULT)))
    out = tmp_path / "out"
    with Executor(inline=True) as ex:
        res = sweep.run_sweep(spec, out, ex)
    assert not res.failed, res.failed
    by_engine: dict[str, list[dict]] = {"receiver": [], "robot": []}
    for rec in res.records:
        by_engine[rec["engine"]].append(rec)
    # the two survey cells (the 2 Hz one included) on the receiver, the missions on the robot
    assert {r["scenario"] for r in by_engine["receiver"]} == {"open_field"}
    assert {r["scenario"] for r in by_engine["robot"]} == {"default"}
    assert len(by_engine["receiver"]) == 2
    rec = next(r for r in by_engine["receiver"] if r["params"]["gnss.rate_hz"] == 2.0)
    assert rec["filtered_rms_m"] is None or math.isnan(rec["filtered_rms_m"])
    # the replay the summary names: x6wd sim on the cell's file, with the run's seed
    replay = tmp_path / "replay"
    done = subprocess.run(
        [*X6WD, "sim", str(out / "cells" / f"{rec['cell_id']}.toml"), "--seed", str(rec["seed"]),
         "--out", str(replay), "--quiet"],
        capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    summary = json.loads((replay / "summary.json").read_text())
    assert summary["extra"]["engine"] == "receiver"
    assert summary["raw_error"]["cep50_m"] == pytest.approx(rec["gps_cep50_m"], rel=1e-9)
    assert summary["fixes"] == 41  # 20 s at 2 Hz, both ends


def test_engine_robot_runs_surveys_on_the_robot_s_loop_and_receiver_refuses_missions(
    tmp_path: Path,
) -> None:
    body = 'seeds = 1\nengine = "robot"\n[set]\nduration_s = 10.0\n'
    spec = sweep.load_sweep(sweep_file(tmp_path, body, (OPEN_FIELD,)))
    with Executor(inline=True) as ex:
        res = sweep.run_sweep(spec, tmp_path / "out", ex)
    (rec,) = res.records
    assert rec["engine"] == "robot" and rec["filtered_rms_m"] > 0
    f = sweep_file(tmp_path, 'engine = "receiver"\n', (DEFAULT,))
    with pytest.raises(ConfigError, match="receiver engine cannot drive a mission"):
        sweep.plan(sweep.load_sweep(f))
    f = sweep_file(tmp_path, 'engine = "fast"\n', (DEFAULT,))
    with pytest.raises(ConfigError, match="engine: expected one of auto, robot, receiver"):
        sweep.load_sweep(f)


def test_runs_kept_from_before_the_engine_column_are_the_robot_s(tmp_path: Path) -> None:
    # a review (round 22): a mission run kept on resume (its cell unchanged) has no "engine":
    # before the column every run went through the robot engine, and the table says so
    from sim_backend.sweep_report import run_rows

    spec = sweep.load_sweep(sweep_file(tmp_path, "seeds = 1\n[set]\nduration_s = 5.0\n"))
    with Executor(inline=True) as ex:
        (rec,) = sweep.run_sweep(spec, tmp_path / "out", ex).records
    old = {k: v for k, v in rec.items() if k != "engine"}
    failed = {**old, "status": "error", "error": "boom"}
    assert [row["engine"] for row in run_rows([rec, old, failed])] == ["robot", "robot", None]


def test_a_receiver_sweep_makes_no_robot_check(tmp_path: Path) -> None:
    # a review (round 22): engine = "receiver" still refused a robot-only value (the drive
    # against the stuck failsafe) that x6wd sim --engine receiver ignores
    body = (
        'engine = "receiver"\nseeds = 1\n[set]\nduration_s = 5.0\n'
        "navigation.cruise_pct = 5.0\nfailsafe.stuck_min_pct = 50.0\n"
    )
    spec = sweep.load_sweep(sweep_file(tmp_path, body, (OPEN_FIELD,)))
    with pytest.raises(ConfigError, match="stuck"):
        sweep.plan(sweep.loads_sweep(
            (tmp_path / "sweep.toml").read_text().replace('engine = "receiver"\n', ""),
            tmp_path,
        ))  # fmt: skip
    assert len(sweep.plan(spec)) == 1
