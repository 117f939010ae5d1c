"""TOML configuration: every error names the key; the shipped robot config loads."""

from __future__ import annotations

import dataclasses
import tomllib
from pathlib import Path

import pytest

from x6wd.core.config import (
    PACKAGED_CONFIG_DIR,
    Config,
    ConfigError,
    NavigationConfig,
    load,
    loads,
    scenario_candidates,
)

ROBOT_TOML = Path(__file__).resolve().parent.parent / "config" / "x6wd.toml"


def test_robot_config_loads_and_covers_every_section() -> None:
    cfg = load(ROBOT_TOML)
    raw = tomllib.loads(ROBOT_TOML.read_text(encoding="utf-8"))
    sections = {f.name for f in dataclasses.fields(Config)}
    assert set(raw) == sections
    assert cfg.motors.url == "log://"
    assert cfg.gps.url == "serial:///dev/ttyS0?baud=9600"
    assert cfg.compass.url == "i2c://1/0x60"
    # what the file says is what the program gets, key by key
    for section, table in raw.items():
        for key, value in table.items():
            got = getattr(getattr(cfg, section), key)
            assert got == (tuple(value) if isinstance(value, list) else value), f"{section}.{key}"


def test_empty_file_gives_the_defaults() -> None:
    assert loads("") == Config()


def test_values_are_converted_and_validated() -> None:
    cfg = loads("[navigation]\ndelta_x_m = 2\nprojection = 'local_tangent_plane'\n")
    assert cfg.navigation.delta_x_m == 2.0 and isinstance(cfg.navigation.delta_x_m, float)
    assert cfg.navigation.projection == "local_tangent_plane"
    assert cfg.navigation.delta_y_m == NavigationConfig().delta_y_m


@pytest.mark.parametrize(
    ("text", "pattern"),
    [
        # unknown keys, top level and inside a section
        ("[navigaton]\n", r"^navigaton: unknown key"),
        ("[navigation]\ndelta_z_m = 1.0\n", r"^navigation\.delta_z_m: unknown key.*delta_x_m"),
        # wrong types
        ("[navigation]\nfilter_n = 'twenty'\n", r"^navigation\.filter_n: expected an integer"),
        ("[navigation]\nfilter_n = 20.0\n", r"^navigation\.filter_n: expected an integer"),
        ("[navigation]\nfilter_hysteresis = 1\n", r"^navigation\.filter_hysteresis: expected true"),
        ("[safety]\nfix_stale_s = true\n", r"^safety\.fix_stale_s: expected a number"),
        ("[gps]\nurl = 5\n", r"^gps\.url: expected a string"),
        ("navigation = 3\n", r"^navigation: expected a table"),
        ("[safety]\ngeofence_center = 'here'\n", r"^safety\.geofence_center: expected a list"),
        ("[safety]\ngeofence_center = [51.7, 'x']\n", r"^safety\.geofence_center\[1\]: expected"),
        # checked by the config itself, so x6wd sim, scenarios and sweeps refuse them too
        ("[safety]\ngeofence_center = [51.7]\n", r"^safety\.geofence_center: expected \[\] or"),
        ("[safety]\ngeofence_center = [95.0, 0.0]\n", r"^safety\.geofence_center: latitude 95"),
        ("[safety]\ngeofence_center = [51.7, -181]\n", r"^safety\.geofence_center: longitude"),
        ("[safety]\ngeofence_center = [nan, 0.0]\n", r"^safety\.geofence_center\[0\]: must be fin"),
        # out of range
        ("[navigation]\nfilter_n = 2\n", r"^navigation\.filter_n: must be >= 3, got 2"),
        ("[navigation]\ncruise_pct = 100.5\n", r"^navigation\.cruise_pct: must be <= 100"),
        # a drive under stuck_min_pct: the robot sat in RUNNING at 0 % for good, unnoticed
        ("[navigation]\ncruise_pct = 5\n", r"^navigation\.cruise_pct: must be >= failsafe\.stuck"),
        ("[navigation]\nturn_pct = 0\n", r"^navigation\.turn_pct: must be > 0"),
        (
            "[navigation]\ncruise_pct = 20\n[failsafe]\nstuck_min_pct = 25\n",
            r"^navigation\.cruise_pct: .*\(25 %\).*got 20$",
        ),
        ("[navigation]\nmin_speed_pct = 5\n", r"^navigation\.min_speed_pct: must be >= fail"),
        # with the stuck check off only a drive of 0 is refused
        ("[navigation]\ncruise_pct = 0\n[failsafe]\nstuck_s = 0\n", r"cruise_pct: must be > 0"),
        ('[console]\ntile_url = "tile.osm.org/{z}/{x}/{y}.png"\n', r"^console\.tile_url: .*http"),
        (
            '[console]\ntile_url = "https://t.org/{z}/{x}.png"\n',
            r"^console\.tile_url: .*\{y\} missing",
        ),
        ("[server]\nport = 70000\n", r"^server\.port: must be <= 65535"),
        ("[compass]\ndeclination_deg = nan\n", r"^compass\.declination_deg: must be finite"),
        # bad choice
        ("[navigation]\nprojection = 'utm'\n", r"^navigation\.projection: must be one of two_rad"),
    ],
)
def test_errors_name_the_key(text: str, pattern: str) -> None:
    with pytest.raises(ConfigError, match=pattern):
        loads(text)


def test_bad_toml_names_the_source() -> None:
    with pytest.raises(ConfigError, match=r"^robot\.toml: not valid TOML"):
        loads("[navigation\n", "robot.toml")


def test_file_errors_name_the_file_and_the_key(tmp_path: Path) -> None:
    missing = tmp_path / "nope.toml"
    with pytest.raises(ConfigError, match=r"nope\.toml: cannot read configuration"):
        load(missing)
    bad = tmp_path / "bad.toml"
    bad.write_text("[navigation]\ndelta_phi_deg = 0.0\n", encoding="utf-8")
    with pytest.raises(ConfigError, match=r"bad\.toml: navigation\.delta_phi_deg: must be >= 0\.1"):
        load(bad)
    broken = tmp_path / "broken.toml"
    broken.write_text("a = = 1\n", encoding="utf-8")
    with pytest.raises(ConfigError, match=r"broken\.toml.*not valid TOML"):
        load(broken)


def test_sim_scenario_resolves_against_the_config_folder(tmp_path: Path) -> None:
    (tmp_path / "worlds").mkdir()
    (tmp_path / "worlds" / "here.toml").write_text("name = 'x'\n")
    cfg_file = tmp_path / "robot.toml"
    cfg_file.write_text('[sim]\nscenario = "worlds/here.toml"\n')
    cfg = load(cfg_file)
    assert cfg.sim.scenario == str((tmp_path / "worlds" / "here.toml").resolve())
    assert cfg.sim.seed is None and cfg.sim.gps_rate_hz is None  # absent: the scenario's own


def test_a_missing_scenario_lists_every_path_tried_in_order(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # the audit's case: started from another folder, the config file's own folder (searched
    # first) was left out of the error
    (tmp_path / "cfg").mkdir()
    (tmp_path / "elsewhere").mkdir()
    monkeypatch.chdir(tmp_path / "elsewhere")
    cfg_file = tmp_path / "cfg" / "e1.toml"
    cfg_file.write_text('[gps]\nurl = "sim://"\n[sim]\nscenario = "scenarios/nope.toml"\n')
    with pytest.raises(ConfigError) as ei:
        load(cfg_file)
    tried = [
        tmp_path / "cfg" / "scenarios" / "nope.toml",
        PACKAGED_CONFIG_DIR / "scenarios" / "nope.toml",
        tmp_path / "elsewhere" / "scenarios" / "nope.toml",
    ]
    assert str(ei.value) == (
        f"{cfg_file}: sim.scenario: no such file 'scenarios/nope.toml' "
        f"(tried {', '.join(str(t) for t in tried)})"
    )
    # a scenario no sim:// device uses is not looked for
    cfg_file.write_text('[sim]\nscenario = "scenarios/nope.toml"\n')
    assert load(cfg_file).sim.scenario == "scenarios/nope.toml"


def test_a_scenario_is_found_where_the_error_says_it_is_looked_for(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from sim_backend.hil import CONFIG_DIR, resolve_scenario

    assert PACKAGED_CONFIG_DIR == CONFIG_DIR  # one folder, named in two layers
    with pytest.raises(ConfigError) as exc:  # a Config not from a file: the same search
        resolve_scenario("scenarios/nope.toml")
    assert str(exc.value).endswith(
        f"(tried {', '.join(map(str, scenario_candidates('scenarios/nope.toml', None)))})"
    )
    monkeypatch.chdir(tmp_path)
    cfg_file = tmp_path / "robot.toml"
    cfg_file.write_text('[gps]\nurl = "sim://"\n[sim]\nscenario = "scenarios/default.toml"\n')
    packaged = PACKAGED_CONFIG_DIR / "scenarios" / "default.toml"
    assert load(cfg_file).sim.scenario == str(packaged.resolve())  # not beside the config
    (tmp_path / "scenarios").mkdir()
    (tmp_path / "scenarios" / "default.toml").write_text("name = 'mine'\n")
    mine = tmp_path / "scenarios" / "default.toml"
    assert load(cfg_file).sim.scenario == str(mine.resolve())  # beside it: first


def test_retired_sim_keys_stop_startup_with_the_key() -> None:
    with pytest.raises(ConfigError, match=r"sim\.gps_sigma_m: unknown key"):
        loads("[sim]\ngps_sigma_m = 0.3\n")


def test_non_utf8_file_is_one_line_naming_the_place(tmp_path: Path) -> None:
    latin1 = tmp_path / "latin1.toml"
    latin1.write_bytes(b'[gps]\nurl = "sim://"\n[recorder]\ndir = "/var/r\xe9c"\n')
    with pytest.raises(ConfigError) as info:
        load(latin1)
    msg = str(info.value)
    assert "\n" not in msg and msg.startswith(f"{latin1}: not UTF-8")
    assert "0xe9" in msg and "line 4" in msg


def test_bad_toml_in_a_file_names_it_once_on_one_line(tmp_path: Path) -> None:
    broken = tmp_path / "broken.toml"
    broken.write_text("[gps]\nurl = 'sim://'\n[compass\n", encoding="utf-8")
    with pytest.raises(ConfigError) as info:
        load(broken)
    msg = str(info.value)
    assert msg.startswith(f"{broken}: not valid TOML") and msg.count(str(broken)) == 1
    assert "line 3" in msg and "\n" not in msg


def test_the_compass_offset_prior_reaches_the_ekf() -> None:
    """[navigation] compass_offset_sigma_deg is the EKF's prior on a constant compass offset;
    0 turns that state off (beside walls a well-calibrated compass does better without it)."""
    from x6wd.core.config import GnssNoiseConfig, OdometryConfig
    from x6wd.nav.estimator import Estimator
    from x6wd.nav.position import estimator_config

    shipped = load(Path(__file__).resolve().parent.parent / "config" / "x6wd.toml")
    assert shipped.navigation.compass_offset_sigma_deg == 10.0
    off = loads("[navigation]\ncompass_offset_sigma_deg = 0.0\n").navigation
    for nav, sigma in ((shipped.navigation, 10.0), (off, 0.0)):
        cfg = estimator_config(nav, OdometryConfig(), GnssNoiseConfig(), 2.0)
        assert cfg.compass.offset_sigma_deg == sigma and cfg.compass.declination_deg == 2.0
    for nav, learns in ((shipped.navigation, True), (off, False)):
        est = Estimator(estimator_config(nav, OdometryConfig(), GnssNoiseConfig(), 0.0))
        est.on_gps(0.0, 0.0, 0.0, 1.0)
        est.on_compass(0.0, 0.0)
        assert (est.covariance[9, 9] > 0.0) == learns  # state 9: the offset (0: frozen)
    with pytest.raises(ConfigError, match="compass_offset_sigma_deg"):
        loads("[navigation]\ncompass_offset_sigma_deg = -1\n")


def test_slow_drives_load_with_the_stuck_check_off_or_below_them(tmp_path: Path) -> None:
    """The drive check follows the failsafe it protects: off (stuck_s 0), or a lower
    stuck_min_pct, and an 8 % cruise is a robot's own choice (with an approach floor no faster:
    min_speed_pct <= cruise_pct)."""
    slow = "[navigation]\ncruise_pct = 8\nmin_speed_pct = 8\n[failsafe]\nstuck_s = 0\n"
    assert loads(slow).navigation.cruise_pct == 8
    low = "[navigation]\ncruise_pct = 8\nmin_speed_pct = 5\n[failsafe]\nstuck_min_pct = 5\n"
    assert loads(low).failsafe.stuck_min_pct == 5
    # a scenario's slow cruise under a robot config whose stuck_min_pct allows it: judged merged
    from sim_backend.world import load_world, with_robot_config

    scenario = tmp_path / "slow.toml"
    default = PACKAGED_CONFIG_DIR / "scenarios" / "default.toml"
    scenario.write_text(
        f'include = ["{default}"]\n[navigation]\ncruise_pct = 8.0\nmin_speed_pct = 5.0\n'
    )
    robot = tmp_path / "robot.toml"
    robot.write_text("[failsafe]\nstuck_min_pct = 5.0\n")
    assert with_robot_config(load_world(scenario), robot).navigation.cruise_pct == 8.0
    robot.write_text("[failsafe]\nstuck_min_pct = 9.0\n")
    with pytest.raises(ConfigError, match=r"cruise_pct: must be >= failsafe\.stuck_min_pct \(9"):
        with_robot_config(load_world(scenario), robot)


def test_a_scenario_name_the_os_refuses_is_a_config_error(tmp_path: Path) -> None:
    cfg_file = tmp_path / "robot.toml"
    cfg_file.write_text(f'[gps]\nurl = "sim://"\n[sim]\nscenario = "{"x" * 300}.toml"\n')
    with pytest.raises(ConfigError, match=r"sim\.scenario: no such file"):
        load(cfg_file)


def test_a_scenario_whose_own_drive_the_stuck_check_cannot_watch_does_not_run(
    tmp_path: Path,
) -> None:
    """Without a robot config the scenario's sections are the robot: refused at the run's
    start (x6wd sim: exit 2), not driven at 5 % unwatched."""
    from sim_backend.mission import run_mission
    from sim_backend.world import load_world

    scenario = tmp_path / "slow.toml"
    default = PACKAGED_CONFIG_DIR / "scenarios" / "default.toml"
    scenario.write_text(f'include = ["{default}"]\n[navigation]\ncruise_pct = 5.0\n')
    with pytest.raises(ConfigError, match=r"^navigation\.cruise_pct: must be >= failsafe"):
        run_mission(load_world(scenario), None, duration_s=5.0)


def test_the_compass_deviation_prior_reaches_the_ekf() -> None:
    """[navigation] compass_deviation_sigma_deg is the EKF's prior on each coefficient of the
    heading-dependent deviation card (states 11-14); 0 turns them off."""
    from x6wd.core.config import GnssNoiseConfig, OdometryConfig
    from x6wd.nav.estimator import Estimator
    from x6wd.nav.position import estimator_config

    shipped = load(Path(__file__).resolve().parent.parent / "config" / "x6wd.toml")
    assert shipped.navigation.compass_deviation_sigma_deg == 2.0
    off = loads("[navigation]\ncompass_deviation_sigma_deg = 0.0\n").navigation
    for nav, learns in ((shipped.navigation, True), (off, False)):
        cfg = estimator_config(nav, OdometryConfig(), GnssNoiseConfig(), 0.0)
        est = Estimator(cfg)
        est.on_gps(0.0, 0.0, 0.0, 1.0)
        est.on_compass(0.0, 30.0)
        assert all((est.covariance[i, i] > 0.0) == learns for i in range(11, 15))
    with pytest.raises(ConfigError, match="compass_deviation_sigma_deg"):
        loads("[navigation]\ncompass_deviation_sigma_deg = -1\n")
