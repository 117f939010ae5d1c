"""``x6wd sim``'s engine choice for a survey that sets robot-only keys (outside
fresh-machine audit, item 2): docs/navigation.md's recipe (``[navigation] position_source =
"constellation"`` added to open_field.toml, then ``x6wd sim``) ran on the receiver engine,
which ignored the table without a word and named the EKF in its "filtered not run" line.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import pytest

from sim_backend import cli, runs
from sim_backend.world import load_world, loads_world
from tests.conftest import ROOT

SCENARIOS = ROOT / "config" / "scenarios"
OPEN_FIELD = SCENARIOS / "open_field.toml"


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
