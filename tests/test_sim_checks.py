"""``x6wd sim``'s checks of what it is given: unreadable scenarios, run lengths, dates the
sky cannot stand for, an engine that cannot run the scenario, and what a rejected mission
prints (faults an outside check found; each test watched to fail on the code before)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from sim_backend.runs import RunPlan, engine_for, sky_warnings, straight_length_m
from sim_backend.world import DEFAULT_ALMANAC, load_world, loads_world
from x6wd.app import cli
from x6wd.core.errors import ConfigError
from x6wd.core.geodesy import great_circle_m

SCENARIOS = Path(__file__).resolve().parents[1] / "config" / "scenarios"
OXFORD = "[origin]\nlat_deg = 51.75\nlon_deg = -1.25\nalt_m = 60.0\n"


def _scenario(
    tmp_path: Path, start: str = "2020-01-01T12:00:00Z", extra: str = "", top: str = ""
) -> Path:
    """A 5 s scenario at Oxford starting at ``start``, with ``top`` keys and ``extra`` tables."""
    path = tmp_path / "s.toml"
    path.write_text(f'name = "t"\nstart_utc = "{start}"\nduration_s = 5.0\n{top}{OXFORD}{extra}')
    return path


@pytest.mark.parametrize("included", [False, True])
def test_a_scenario_that_is_not_utf8_is_named_not_a_traceback(
    tmp_path: Path, included: bool, capsys: pytest.CaptureFixture[str]
) -> None:
    bad = tmp_path / "b.toml"
    bad.write_bytes(b"\xff\xfe")
    path = bad
    if included:
        path = tmp_path / "top.toml"
        path.write_text(f'include = ["b.toml"]\nname = "t"\n{OXFORD}')
    assert cli.main(["sim", str(path), "--out", str(tmp_path / "o"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert f"{bad}: not a scenario: not UTF-8" in err and "Traceback" not in err


def test_an_lce_csv_that_is_not_utf8_is_named(tmp_path: Path) -> None:
    (tmp_path / "map.csv").write_bytes(b"1.0,\xff\n")
    with pytest.raises(ConfigError, match=r"gnss\.lce_csv: .*map\.csv: not UTF-8"):
        load_world(_scenario(tmp_path, extra='[gnss]\nlce_csv = "map.csv"\n'))


@pytest.mark.parametrize("value", ["1e12", "2592001", "nan", "inf", "0", "-5", "ten"])
def test_the_duration_override_is_capped_as_the_scenario_key(
    tmp_path: Path, value: str, capsys: pytest.CaptureFixture[str]
) -> None:
    argv = ["sim", str(_scenario(tmp_path)), "--out", str(tmp_path / "o"), "--quiet"]
    with pytest.raises(SystemExit) as stop:  # argparse: usage and exit 2, before any work
        cli.main([*argv, "--duration", value])
    assert stop.value.code == 2
    assert "argument --duration" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()
    # the API refuses it too (a numpy memory error before)
    with pytest.raises(ConfigError, match="at most 2592000 s"):
        RunPlan.of(load_world(_scenario(tmp_path)), None, 1e12, 1.0)
    assert RunPlan.of(load_world(_scenario(tmp_path)), None, 2592000.0, 1.0).total_s == 2592000.0


def test_a_start_before_the_gps_epoch_is_refused(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = _scenario(tmp_path, "1975-01-01T00:00:00Z")
    assert cli.main(["sim", str(path), "--out", str(tmp_path / "o"), "--quiet"]) == 2
    assert "start_utc" in capsys.readouterr().err
    with pytest.raises(ConfigError, match=r"start_utc: .* before the GPS epoch"):
        loads_world(f'name = "t"\nstart_utc = 1980-01-05T23:59:59Z\n{OXFORD}')
    assert loads_world(f'name = "t"\nstart_utc = 1980-01-06T00:00:00Z\n{OXFORD}')


@pytest.mark.parametrize("start", ["2025-06-01T12:00:00Z", "2009-07-24T12:00:00Z"])
def test_a_start_far_from_the_almanac_warns_once_on_stderr_and_in_the_summary(
    tmp_path: Path, start: str, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "o"
    assert cli.main(["sim", str(_scenario(tmp_path, start)), "--out", str(out), "--quiet"]) == 0
    err = capsys.readouterr().err
    assert err.count("warning") == 1 and "propagated far from its epoch" in err
    assert 'almanac = "FILE"' in err  # how to give a matching almanac
    warnings = json.loads((out / "summary.json").read_text())["extra"]["warnings"]
    assert len(warnings) == 1 and warnings[0] in err
    assert sky_warnings(load_world(SCENARIOS / "default.toml")) == []  # the packaged date


def test_the_robot_engine_summary_carries_the_warning(tmp_path: Path) -> None:
    from sim_backend.mission import run_mission

    world = load_world(_scenario(tmp_path, "2025-06-01T12:00:00Z"))
    summary = run_mission(world, tmp_path / "o", duration_s=2.0)
    assert summary.extra["warnings"] == sky_warnings(world, 2.0) and summary.extra["warnings"]


def test_the_almanac_age_counts_from_its_reference_time(tmp_path: Path) -> None:
    near = load_world(_scenario(tmp_path, "2020-01-20T00:00:00Z"))  # 16 days after its toa
    assert sky_warnings(near) == []
    assert len(sky_warnings(near, 30 * 86400.0)) == 1  # the run's end is 46 days out
    # a user's almanac (here a copy) is named; its 10-bit week is taken as the sky takes it
    shutil.copy(DEFAULT_ALMANAC, tmp_path / "mine.txt")
    far = load_world(_scenario(tmp_path, "2021-06-01T00:00:00Z", top='almanac = "mine.txt"\n'))
    (warning,) = sky_warnings(far)
    assert str(tmp_path / "mine.txt") in warning


def test_the_receiver_engine_refuses_a_scenario_with_waypoints(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    argv = ["sim", str(SCENARIOS / "default.toml"), "--out", str(tmp_path / "o"), "--quiet"]
    assert cli.main([*argv, "--engine", "receiver"]) == 2
    err = capsys.readouterr().err
    assert "--engine receiver" in err and "--engine robot or auto" in err
    assert not (tmp_path / "o").exists()
    with pytest.raises(ConfigError, match="cannot drive a mission"):
        engine_for(load_world(SCENARIOS / "default.toml"), "receiver")
    assert engine_for(load_world(SCENARIOS / "open_field.toml"), "receiver") == "receiver"


def test_a_mission_beyond_the_fence_is_refused_and_its_length_is_a_great_circle(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = _scenario(tmp_path, extra="[mission]\nwaypoints = [[-33.0, 151.0]]\n")
    # refused before the run, exit 2 (it ran and exited 1: tests/test_sim_scenario_mission.py)
    assert cli.main(["sim", str(path), "--out", str(tmp_path / "o"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert f"{path}: mission.waypoints[0] (-33.0000000, 151.0000000) is " in err
    # Oxford to Sydney is about 16,960 km on the great circle (the ENU chord said 2,964 km)
    straight = straight_length_m(load_world(path))
    assert straight == pytest.approx(great_circle_m(51.75, -1.25, -33.0, 151.0), rel=0.005)


def test_the_straight_length_of_a_field_route_is_its_flat_length() -> None:
    world = load_world(SCENARIOS / "default.toml")
    v = world.vehicle
    pts = np.vstack([[v.start_east_m, v.start_north_m], world.waypoints_enu_m()])
    flat = float(np.sum(np.hypot(*np.diff(pts, axis=0).T)))
    assert straight_length_m(world) == pytest.approx(flat, abs=1e-3)


@pytest.mark.parametrize(
    ("duration", "said"),
    [
        ("20", ["the run's 20 s ended before the last waypoint"]),
        # round 21: "the run's 0 s ended" and a filtered row of five nan
        (
            "0.5",
            [
                "the run's 0.5 s ended before the last waypoint",
                "filtered         no estimate: the run ended before the first",
            ],
        ),
    ],
)
def test_a_mission_cut_by_the_runs_duration_says_so(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], duration: str, said: list[str]
) -> None:
    # an outside audit: "mission NOT completed" and nothing more
    argv = ["sim", str(SCENARIOS / "default.toml"), "--duration", duration, "--quiet"]
    assert cli.main([*argv, "--out", str(tmp_path / "o")]) == 1
    out = capsys.readouterr().out
    assert f"mission NOT completed: {said[0]}" in out
    assert all(line in out for line in said) and "nan" not in out, out


@pytest.mark.parametrize("seed", ["-1", str(2**63), "99999999999999999999999", "1.5"])
def test_a_seed_outside_a_scenarios_seed_range_is_refused(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], seed: str
) -> None:
    argv = ["sim", str(SCENARIOS / "default.toml"), "--seed", seed, "--out", str(tmp_path / "o")]
    with pytest.raises(SystemExit) as exc:
        cli.main(argv)
    assert exc.value.code == 2 and "argument --seed: " in capsys.readouterr().err
