"""A scenario's mission in ``x6wd sim`` (faults an outside navigation audit found; each test
watched to fail on the code before, but the last two, which hold the docs' corrected claim):

- a waypoint beyond the geofence is refused before the run, exit 2, one line naming the key
  and ``safety.geofence_radius_m``, measured from the configured centre or else the known
  start (not the seed's first fix); a mission the robot still rejects in the run stops it;
- ``[mission] waypoints = []`` is refused (it ran a static survey);
- ``[mission] file = "route.gpx"`` reads a mission file with the project's own readers;
- the start-up wait for the first position estimate is not counted as a hold (every run
  reported one), while a real hold still is;
- what docs/simulator.md says about a seed's realisation and ``--duration``, per engine.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np
import pytest

from sim_backend import mission, runs
from sim_backend.geodesy import enu_to_lla
from sim_backend.mission import STARTUP_HOLD, run_mission
from sim_backend.survey import run_survey
from sim_backend.sweep import cell_world
from sim_backend.world import load_world, loads_world, with_robot_config
from x6wd.app import cli
from x6wd.core.errors import ConfigError
from x6wd.core.mission_files import Waypoint, format_csv, format_gpx, format_wpl, load_file

SCENARIOS = Path(__file__).resolve().parents[1] / "config" / "scenarios"
ORIGIN = (51.752, -1.2577, 60.0)
HEAD = (
    'name = "t"\nstart_utc = "2020-01-01T12:00:00Z"\nduration_s = 30.0\nseed = 1\n'
    f"[origin]\nlat_deg = {ORIGIN[0]}\nlon_deg = {ORIGIN[1]}\nalt_m = {ORIGIN[2]}\n"
)


def _latlon(east_m: float, north_m: float) -> tuple[float, float]:
    lat, lon, _alt = enu_to_lla(np.array([east_m, north_m, 0.0]), *ORIGIN)
    return float(lat), float(lon)


def _write(folder: Path, text: str, name: str = "s.toml") -> Path:
    path = folder / name
    path.write_text(text, encoding="utf-8")
    return path


def _sim(tmp_path: Path, scenario: Path, *extra: str) -> int:
    argv = ["sim", str(scenario), "--out", str(tmp_path / "out"), "--quiet", *extra]
    return cli.main(argv)


# -- the geofence, before the run ---------------------------------------------------------


def test_a_waypoint_beyond_the_geofence_is_refused_before_the_run_with_exit_2(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # the audit's beyond_fence: the second waypoint 1200 m north, the default 1000 m fence;
    # it ran the whole 800 s and exited 1 (a failed drive's code)
    near, far = _latlon(0.0, 600.0), _latlon(0.0, 1200.0)
    scen = _write(
        tmp_path,
        HEAD.replace("30.0", "800.0") + f"[mission]\nwaypoints = [{list(near)}, {list(far)}]\n",
    )
    assert _sim(tmp_path, scen) == 2
    out, err = capsys.readouterr()
    assert out == "" and not (tmp_path / "out").exists()  # refused before anything ran
    (line,) = err.strip().splitlines()
    assert line.startswith(f"x6wd sim: error: {scen}: mission.waypoints[1] (")
    assert "safety.geofence_radius_m is 1000 m" in line and "start position" in line


def test_swapped_latitude_and_longitude_are_refused_before_the_run(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    scen = _write(tmp_path, HEAD + f"[mission]\nwaypoints = [[{ORIGIN[1]}, {ORIGIN[0]}]]\n")
    assert _sim(tmp_path, scen) == 2
    assert "mission.waypoints[0] (-1.2577000, 51.7520000) is " in capsys.readouterr().err


def test_the_fence_is_centred_on_the_known_start_else_the_configured_centre(
    tmp_path: Path,
) -> None:
    # the start 500 m north of the origin: a waypoint 1400 m north of the origin is 900 m
    # from the start (accepted, whatever the seed's first fix), 1600 m is 1100 m (refused)
    start = "[vehicle]\nstart_north_m = 500.0\n"
    for north, refused in ((1400.0, False), (1600.0, True)):
        world = loads_world(
            HEAD + start + f"[mission]\nwaypoints_enu = [[0.0, 10.0], [0.0, {north}]]\n"
        )
        if refused:
            with pytest.raises(ConfigError, match=r"^mission\.waypoints_enu\[1\] \[0\.0, 1600"):
                runs.check_mission_geofence(world)
        else:
            runs.check_mission_geofence(world)
    # a configured centre: the distance is from it, and the start must lie inside too
    centre = _latlon(0.0, 1000.0)
    fence = f"[safety]\ngeofence_center = {list(centre)}\ngeofence_radius_m = 600.0\n"
    world = loads_world(HEAD + start + fence + "[mission]\nwaypoints_enu = [[0.0, 1500.0]]\n")
    runs.check_mission_geofence(world)  # 500 m from the centre; the start 500 m too
    world = loads_world(HEAD + start + fence + "[mission]\nwaypoints_enu = [[0.0, 1700.0]]\n")
    with pytest.raises(ConfigError, match=r"is 700 m from the geofence centre, safety\.geofence_c"):
        runs.check_mission_geofence(world)
    far_start = start.replace("500.0", "300.0")
    world = loads_world(HEAD + far_start + fence + "[mission]\nwaypoints_enu = [[0.0, 1000.0]]\n")
    with pytest.raises(ConfigError, match=r"^vehicle\.start_east_m/start_north_m: .* 700 m"):
        runs.check_mission_geofence(world)


def test_the_robot_configs_fence_is_the_one_checked(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # 1200 m is beyond the built-in 1000 m, inside a robot config's 5000 m, and beyond a
    # scenario's own 500 m: the check runs on the merged configuration
    far = _latlon(0.0, 1200.0)
    scen = _write(tmp_path, HEAD + f"[mission]\nwaypoints = [{list(far)}]\n")
    robot = _write(tmp_path, "[safety]\ngeofence_radius_m = 5000.0\n", "robot.toml")
    runs.check_mission_geofence(with_robot_config(load_world(scen), robot))
    small = _write(tmp_path, HEAD + "[safety]\ngeofence_radius_m = 500.0\n", "small.toml")
    small.write_text(small.read_text() + f"[mission]\nwaypoints = [{list(far)}]\n")
    with pytest.raises(ConfigError, match=r"safety\.geofence_radius_m is 500 m"):
        runs.check_mission_geofence(with_robot_config(load_world(small), robot))


def test_a_mission_the_robot_rejects_in_the_run_stops_the_run_with_exit_2(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # The robot centres its fence on its first fix; the default scenario's seed 1 fixes
    # first 7.5 m north of the truth. A waypoint 25 m south of the start, a 28 m fence:
    # inside from the start (the check before the run passes), 32.5 m from the first fix
    # (the robot rejects it). The run idled to its end; now it stops at the rejection.
    text = (SCENARIOS / "default.toml").read_text()
    text = text.split("[mission]")[0] + "[mission]\nwaypoints_enu = [[0.0, -25.0]]\n"
    scen = _write(tmp_path, text + "[safety]\ngeofence_radius_m = 28.0\n")
    runs.check_mission_geofence(load_world(scen))
    assert _sim(tmp_path, scen, "--seed", "1") == 2
    out = capsys.readouterr().out
    assert "mission NOT completed: the robot rejected it at 0.5 s (geofence: waypoint 1" in out
    assert "the run stopped there" in out
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    at = summary["extra"]["mission_rejected_at_s"]
    assert 0.5 <= at < 0.6 and summary["sim_time_s"] < at + 0.1  # not the 400 s duration
    assert summary["extra"]["mission_rejected"].startswith("geofence:")


# -- an empty mission ---------------------------------------------------------------------


@pytest.mark.parametrize(
    ("table", "key"),
    [
        ("waypoints = []", "mission.waypoints: empty"),
        ("waypoints_enu = []", "mission.waypoints_enu: empty"),
        ("waypoints = [[51.7521, -1.2577]]\nwaypoints_enu = []", "mission.waypoints_enu: empty"),
        ("", "mission: no waypoints"),
    ],
)
def test_an_empty_mission_is_refused_not_run_as_a_survey(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], table: str, key: str
) -> None:
    scen = _write(tmp_path, HEAD + f"[mission]\n{table}\n")
    assert _sim(tmp_path, scen, "--duration", "5") == 2
    (line,) = capsys.readouterr().err.strip().splitlines()
    assert line.startswith(f"x6wd sim: error: {scen}: {key}")
    assert line.endswith("leave [mission] out for a static survey")
    assert not (tmp_path / "out").exists()


# -- a mission file -----------------------------------------------------------------------

SQUARE = [(0.0, 25.0), (25.0, 25.0), (25.0, 0.0), (5.0, 0.0)]  # default.toml's, east/north


def test_a_mission_file_runs_as_the_same_waypoints_inline(tmp_path: Path) -> None:
    points = [_latlon(e, n) for e, n in SQUARE]
    (tmp_path / "m").mkdir()
    (tmp_path / "m" / "route.csv").write_text(format_csv([Waypoint(a, b) for a, b in points]))
    head = (SCENARIOS / "default.toml").read_text().split("[mission]")[0]
    by_file = _write(tmp_path, head + '[mission]\nfile = "m/route.csv"\n', "file.toml")
    inline = _write(tmp_path, head + f"[mission]\nwaypoints = {[list(p) for p in points]}\n")
    w_file, w_inline = load_world(by_file), load_world(inline)
    assert w_file.mission.file == str(tmp_path / "m" / "route.csv")
    assert w_file.mission.waypoints == w_inline.mission.waypoints
    run_mission(w_file, tmp_path / "a", 1, 12.0)
    run_mission(w_inline, tmp_path / "b", 1, 12.0)
    a, b = ((tmp_path / d / "recording.jsonl").read_bytes() for d in "ab")
    assert a == b and b"STRAIGHT" in a
    assert loads_world(w_file.to_toml()) == w_file  # the copy names the file by its path
    # a sweep's cell carries the waypoints, so its workers need no mission file
    _world, portable = cell_world(dict(w_file.raw), tmp_path, {}, "cell")
    assert "route.csv" not in portable and loads_world(portable).mission.waypoints == tuple(points)


@pytest.mark.parametrize("ext", ["gpx", "waypoints", "kml"])
def test_every_mission_format_is_read_by_the_projects_reader(tmp_path: Path, ext: str) -> None:
    points = [_latlon(e, n) for e, n in SQUARE]
    route = tmp_path / f"route.{ext}"
    if ext == "gpx":
        route.write_text(format_gpx([Waypoint(a, b) for a, b in points]))
    elif ext == "waypoints":
        route.write_text(format_wpl([Waypoint(a, b) for a, b in points]))
    else:
        coords = " ".join(f"{lon!r},{lat!r},0" for lat, lon in points)
        route.write_text(
            '<kml xmlns="http://www.opengis.net/kml/2.2"><Placemark><LineString><coordinates>'
            f"{coords}</coordinates></LineString></Placemark></kml>"
        )
    world = loads_world(HEAD + f'[mission]\nfile = "route.{ext}"\n', tmp_path)
    expected = [(w.lat_deg, w.lon_deg) for w in load_file(route)]
    assert list(world.mission.waypoints) == expected and len(expected) == 4
    assert np.allclose(world.waypoints_enu_m(), SQUARE, atol=0.01)


def test_a_mission_file_is_relative_to_the_file_that_names_it(tmp_path: Path) -> None:
    (tmp_path / "site").mkdir()
    (tmp_path / "site" / "route.csv").write_text("51.7521,-1.2577\n")
    _write(tmp_path / "site", '[mission]\nfile = "route.csv"\n', "site.toml")
    top = _write(tmp_path, 'include = ["site/site.toml"]\n' + HEAD)
    assert load_world(top).mission.waypoints == ((51.7521, -1.2577),)


def test_a_mission_file_with_inline_waypoints_names_both_keys(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    (tmp_path / "route.csv").write_text("51.7521,-1.2577\n")
    scen = _write(tmp_path, HEAD + '[mission]\nfile = "route.csv"\nwaypoints_enu = [[1.0, 2.0]]\n')
    assert _sim(tmp_path, scen) == 2
    err = capsys.readouterr().err
    assert f"{scen}: mission.file, mission.waypoints_enu: give either" in err


@pytest.mark.parametrize(
    ("name", "content", "why"),
    [
        ("empty.csv", "lat,lon\n", "no waypoints"),
        ("missing.gpx", None, "cannot read"),
        ("route.txt", "51.7,-1.2\n", "unknown mission format"),
        ("nan.csv", "nan,-1.2577\n", "latitude must be finite"),
    ],
)
def test_a_bad_mission_file_is_exit_2_naming_the_file(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], name: str, content: str | None, why: str
) -> None:
    if content is not None:
        (tmp_path / name).write_text(content)
    scen = _write(tmp_path, HEAD + f'[mission]\nfile = "{name}"\n')
    assert _sim(tmp_path, scen) == 2
    (line,) = capsys.readouterr().err.strip().splitlines()
    assert line.startswith(f"x6wd sim: error: {scen}: mission.file: {tmp_path / name}")
    assert why in line


def test_a_waypoint_of_a_mission_file_beyond_the_fence_names_the_file(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    far = _latlon(0.0, 1500.0)
    (tmp_path / "route.csv").write_text(f"51.7521,-1.2577\n{far[0]!r},{far[1]!r}\n")
    scen = _write(tmp_path, HEAD + '[mission]\nfile = "route.csv"\n')
    assert _sim(tmp_path, scen) == 2
    err = capsys.readouterr().err
    assert f"mission.file: {tmp_path / 'route.csv'}: waypoint 2 (" in err


# -- holds --------------------------------------------------------------------------------


def test_the_start_up_wait_is_not_a_hold(tmp_path: Path) -> None:
    # every run reported "HOLD periods 1 (0.0 s)": the 24 ms between the mission's start at
    # the first fix and the estimator's first estimate
    s = run_mission(load_world(SCENARIOS / "default.toml"), None, 1, 15.0)
    assert s.hold_periods == 0 and s.hold_time_s == 0.0 and s.extra["holds_s"] == []
    a, b = s.extra["startup_wait_s"]
    assert 0.5 < a < b < a + 0.1
    assert "HOLD periods        0 (0.0 s); start-up wait 0.02 s" in s.text()


def test_a_real_hold_is_still_counted_beside_the_start_up_wait(
    caplog: pytest.LogCaptureFixture,
) -> None:
    # a 60 s GPS outage from 5 s: the robot dead-reckons, then holds until the fix returns
    text = (SCENARIOS / "default.toml").read_text()
    text += '\n[[effects]]\nname = "outage"\nstart_s = 5.0\nduration_s = 60.0\n'
    with caplog.at_level(logging.WARNING, logger="x6wd"):
        s = run_mission(loads_world(text, SCENARIOS), None, 1, 75.0)
    warned = [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING]
    assert "state STRAIGHT -> HOLD state: no valid fix" in warned, warned  # logged, as ever
    assert s.hold_periods >= 1 and s.hold_time_s > 20.0
    assert all(a > 5.0 for a, _b in s.extra["holds_s"])
    assert s.extra["startup_wait_s"] is not None


def test_a_run_that_ends_in_the_start_up_wait_counts_it_as_a_hold() -> None:
    # a robot that never gets an estimate holds: every compass read fails, and the run ends
    # in the hold that began at its first decision
    text = (
        (SCENARIOS / "default.toml").read_text().replace("[compass]", "[compass]\np_error = 1.0", 1)
    )
    s = run_mission(loads_world(text, SCENARIOS), None, 1, 5.0)
    assert s.hold_periods == 1 and s.extra["startup_wait_s"] is None
    # a run of 0.5 s ends with the first fix's burst (0.84 s): the compass is read while it
    # is on the wire, so the first estimate comes and the wait ends (round 14: the closing
    # tick found the compass stale, and that false hold was counted here)
    s = run_mission(load_world(SCENARIOS / "default.toml"), None, 1, 0.5)
    assert s.hold_periods == 0 and s.extra["startup_wait_s"] is not None


def test_the_start_up_wait_is_not_logged_as_a_fault(caplog: pytest.LogCaptureFixture) -> None:
    # every `x6wd sim` mission (README's first command) printed "state IDLE -> HOLD state:
    # position estimate not ready" on stderr for the wait its summary does not count
    with caplog.at_level(logging.INFO, logger="x6wd"):
        s = run_mission(load_world(SCENARIOS / "default.toml"), None, 1, 15.0)
    assert s.extra["startup_wait_s"] is not None
    said = [r.getMessage() for r in caplog.records if r.name == "x6wd.loop.runner"]
    assert said and not any(STARTUP_HOLD in m for m in said), said
    assert any(m.startswith("state HOLD -> ") for m in said)  # the way out is still logged
    assert not any(
        isinstance(f, mission._StartupHoldHeld)
        for f in logging.getLogger("x6wd.loop.runner").filters
    )  # the robot's log is left as it was


def test_a_start_up_wait_counted_as_a_hold_is_logged_after_all() -> None:
    # the held line is released when the run counts the wait as a hold (a fault began in it,
    # or the run ended in it): the filter's own contract, as run_mission uses it
    held = mission._StartupHoldHeld()
    logger = logging.getLogger("x6wd.test.startup")
    seen: list[str] = []
    handler = logging.Handler()
    handler.emit = lambda r: seen.append(r.getMessage())  # type: ignore[method-assign]
    logger.addHandler(handler)
    logger.addFilter(held)
    try:
        start = f"state IDLE -> HOLD state: {STARTUP_HOLD}"
        logger.warning("state %s -> %s %s%s", "IDLE", "HOLD", f"state: {STARTUP_HOLD}", "")
        assert seen == []  # held: the start-up wait, so far
        # it turns into another hold (a fault, a wait for the sky): said at once, in order
        logger.warning("state %s -> %s %s%s", "HOLD", "HOLD", "state: compass stale", "")
        assert seen == [start, "state HOLD -> HOLD state: compass stale"]
        held.release(logger)
        assert len(seen) == 2  # once
        # a run that ends in the wait: released at its end
        logger.removeFilter(held)
        ended = mission._StartupHoldHeld()
        logger.addFilter(ended)
        logger.warning("state %s -> %s %s%s", "IDLE", "HOLD", f"state: {STARTUP_HOLD}", "")
        assert len(seen) == 2
        logger.removeFilter(ended)
        ended.release(logger)
        assert seen[-1] == start and len(seen) == 3
    finally:
        logger.removeFilter(held)
        logger.removeHandler(handler)
    # a first state change that is not the start-up wait is never held
    other = mission._StartupHoldHeld()
    rec = logging.LogRecord("x", logging.WARNING, "", 0, "state %s -> %s %s%s",
                            ("IDLE", "HOLD", "state: compass stale", ""), None)  # fmt: skip
    assert other.filter(rec) and other.held is None


# -- a seed's realisation and the run's duration (docs/simulator.md) ----------------------


def test_a_missions_shorter_run_is_the_start_of_a_longer_one(tmp_path: Path) -> None:
    world = load_world(SCENARIOS / "default.toml")
    run_mission(world, tmp_path / "short", 3, 4.0)
    run_mission(world, tmp_path / "long", 3, 9.0)
    short, long = ((tmp_path / d / "gps.nmea").read_bytes() for d in ("short", "long"))
    assert short and long.startswith(short) and len(long) > len(short)


def test_a_surveys_realisation_depends_on_its_duration(tmp_path: Path) -> None:
    world = load_world(SCENARIOS / "open_field.toml")
    first = []
    for duration in (3.0, 30.0):
        run_survey(world, tmp_path / f"d{duration:g}", 1, duration)
        nmea = (tmp_path / f"d{duration:g}" / "gps.nmea").read_text(errors="replace")
        first.append(next(line for line in nmea.splitlines() if line.startswith("$GPGGA")))
    assert first[0] != first[1]
