"""Configuration cross-checks from an outside audit: a staleness limit against its sensor's
rate, the approach floor against the cruise, a file with a UTF-8 byte-order mark, and port 0."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from tests.conftest import ROOT
from tests.test_startup import assert_config_error, run_x6wd
from x6wd.core.config import (
    PACKAGED_CONFIG_DIR,
    Config,
    ConfigError,
    SafetyConfig,
    check_drive_vs_stuck,
    load,
    loads,
)
from x6wd.nav.steering import approach_speed_pct

SHIPPED = sorted(PACKAGED_CONFIG_DIR.glob("*.toml"))  # the robot configs (not scenarios/sweeps)


@pytest.mark.parametrize("path", SHIPPED, ids=lambda p: p.name)
def test_the_shipped_robot_configs_load(path: Path) -> None:
    assert {p.name for p in SHIPPED} >= {"x6wd.toml", "hil.toml"}
    load(path)


# -- 1: a staleness limit shorter than a few of its sensor's periods --------------------------
def test_the_audits_attitude_limit_under_the_compass_period_stops_startup_with_exit_2(
    tmp_path: Path,
) -> None:
    # the audit: 0.01 s against a 20 Hz compass (a sample every 0.05 s) started, then flipped
    # HOLD/STRAIGHT 179 times in 5 s
    config = tmp_path / "x6wd.toml"
    config.write_text("[compass]\nrate_hz = 20\n[safety]\nattitude_stale_s = 0.01\n")
    line = assert_config_error(
        run_x6wd(config), str(config), "safety.attitude_stale_s: 0.01 s", "compass.rate_hz = 20"
    )
    assert "at least 0.125 s" in line


@pytest.mark.parametrize(
    ("text", "key"),
    [
        # 2.5 periods of 20 Hz: 0.125 s
        ("[compass]\nrate_hz = 20\n[safety]\nattitude_stale_s = 0.12\n", "attitude_stale_s"),
        ("[compass]\nrate_hz = 75\n[safety]\nattitude_stale_s = 0.03\n", "attitude_stale_s"),
        # 2.5 periods of 1 Hz: 2.5 s (the shipped value)
        ("[safety]\nfix_stale_s = 2.4\n", "fix_stale_s"),
        ("[gps]\nrate_hz = 0.5\n", "fix_stale_s"),  # the default 2.5 s under 5 s
        ("[gps]\nrate_hz = 4\n[safety]\nfix_stale_s = 0.6\n", "fix_stale_s"),
    ],
)
def test_a_stale_limit_under_two_and_a_half_periods_is_refused(text: str, key: str) -> None:
    with pytest.raises(ConfigError, match=rf"^safety\.{key}: .* so a single late sample"):
        loads(text)


@pytest.mark.parametrize(
    "text",
    [
        "[compass]\nrate_hz = 20\n[safety]\nattitude_stale_s = 0.125\n",
        "[compass]\nrate_hz = 75\n[safety]\nattitude_stale_s = 0.034\n",
        "[safety]\nfix_stale_s = 2.5\n",
        "[gps]\nrate_hz = 4\n[safety]\nfix_stale_s = 0.625\n",
        "[gps]\nrate_hz = 3\n[safety]\nfix_stale_s = 0.834\n",  # the minimum the error names
    ],
)
def test_a_stale_limit_of_two_and_a_half_periods_or_more_loads(text: str) -> None:
    loads(text)


def test_the_minimum_the_message_names_loads() -> None:
    with pytest.raises(ConfigError) as ei:
        loads("[gps]\nrate_hz = 3\n[safety]\nfix_stale_s = 0.8\n")
    least = re.search(r"at least ([0-9.]+) s$", str(ei.value))
    assert least is not None, str(ei.value)
    loads(f"[gps]\nrate_hz = 3\n[safety]\nfix_stale_s = {least[1]}\n")


def test_a_simulated_gps_is_checked_at_the_sims_rate() -> None:
    sim = '[gps]\nurl = "sim://"\nrate_hz = 1\n[safety]\nfix_stale_s = 1.0\n'
    # [sim] gps_rate_hz is the simulated receiver's rate, not [gps] rate_hz: 1 s spans 4 fixes
    assert loads(sim + "[sim]\ngps_rate_hz = 4\n").safety.fix_stale_s == 1.0
    with pytest.raises(ConfigError, match=r"^safety\.fix_stale_s: .*sim\.gps_rate_hz = 2 Hz"):
        loads(sim + "[sim]\ngps_rate_hz = 2\n")
    # unset: the scenario's rate, taken at the slowest a simulated receiver runs (1 Hz)
    with pytest.raises(ConfigError, match=r"^safety\.fix_stale_s: .*sim\.gps_rate_hz unset"):
        loads(sim)
    # a real GPS is checked at [gps] rate_hz whatever [sim] says
    real = sim.replace("sim://", "serial:///dev/ttyS0")
    with pytest.raises(ConfigError, match=r"gps\.rate_hz = 1 Hz"):
        loads(real + "[sim]\ngps_rate_hz = 4\n")


def test_a_config_built_in_code_is_checked_too() -> None:
    # x6wd sim, the HIL tests and the benches build Config directly
    with pytest.raises(ConfigError, match=r"^safety\.attitude_stale_s: "):
        Config(safety=SafetyConfig(attitude_stale_s=0.01))


# -- 2: min_speed_pct over cruise_pct -----------------------------------------------------------
def test_an_approach_floor_over_the_cruise_never_slows_the_robot() -> None:
    # why it is refused: the approach speed is clamped to cruise, so 1 m before the last
    # waypoint the robot still drives at cruise
    assert approach_speed_pct(1.0, cruise_pct=20.0, approach_m=10.0, min_speed_pct=30.0) == 20.0
    assert approach_speed_pct(1.0, cruise_pct=20.0, approach_m=10.0, min_speed_pct=15.0) == 15.0


@pytest.mark.parametrize("failsafe", ["", "[failsafe]\nstuck_s = 0\n"])
def test_min_speed_over_cruise_is_refused_naming_both_and_their_values(
    failsafe: str, tmp_path: Path
) -> None:
    text = "[navigation]\ncruise_pct = 20\nmin_speed_pct = 30\n" + failsafe
    with pytest.raises(ConfigError) as ei:
        loads(text)
    assert str(ei.value).startswith(
        "navigation.min_speed_pct: 30 % is over navigation.cruise_pct (20 %)"
    ), str(ei.value)
    config = tmp_path / "x6wd.toml"
    config.write_text(text)
    assert_config_error(run_x6wd(config), str(config), "navigation.min_speed_pct: 30 %")


def test_min_speed_equal_to_cruise_loads() -> None:
    nav = loads("[navigation]\ncruise_pct = 20\nmin_speed_pct = 20\n").navigation
    assert (nav.cruise_pct, nav.min_speed_pct) == (20.0, 20.0)


def test_a_cruise_under_the_stuck_floor_is_still_named_first() -> None:
    # cruise 5 % is under both stuck_min_pct and the default min_speed_pct 15: raising the
    # cruise is what fixes both
    with pytest.raises(ConfigError, match=r"^navigation\.cruise_pct: must be >= failsafe"):
        loads("[navigation]\ncruise_pct = 5\n")


def test_a_scenario_with_the_floor_over_its_cruise_is_refused(tmp_path: Path) -> None:
    # scenarios, sweeps and x6wd sim call the same check on their merged sections
    from sim_backend.world import load_world

    scenario = tmp_path / "s.toml"
    default = PACKAGED_CONFIG_DIR / "scenarios" / "default.toml"
    scenario.write_text(f'include = ["{default}"]\n[navigation]\nmin_speed_pct = 70.0\n')
    world = load_world(scenario)
    with pytest.raises(ConfigError, match=r"^navigation\.min_speed_pct: 70 % is over"):
        check_drive_vs_stuck(world.navigation, world.failsafe)


@pytest.mark.parametrize(
    ("extra", "key", "rate"),
    [
        ("[safety]\nfix_stale_s = 0.7\n", "safety.fix_stale_s", "gnss.rate_hz = 1 Hz"),
        ("[safety]\nattitude_stale_s = 0.1\n", "safety.attitude_stale_s", "compass.rate_hz"),
    ],
)
def test_a_scenarios_stale_limits_are_checked_at_its_own_rates(
    tmp_path: Path, extra: str, key: str, rate: str
) -> None:
    # a scenario's [safety] runs against its own [gnss] and [compass] rates, not the robot's
    from sim_backend.world import load_world

    scenario = tmp_path / "s.toml"
    default = PACKAGED_CONFIG_DIR / "scenarios" / "default.toml"
    scenario.write_text(f'include = ["{default}"]\n{extra}')
    with pytest.raises(ConfigError, match=rf"{re.escape(key)}: .* periods of {re.escape(rate)}"):
        load_world(scenario)
    fast = tmp_path / "fast.toml"  # the same limit at a rate it covers loads
    fast.write_text(
        f'include = ["{default}"]\n{extra}'
        + ("[gnss]\nrate_hz = 4.0\n" if "fix" in key else "[compass]\nrate_hz = 50.0\n")
    )
    load_world(fast)


@pytest.mark.parametrize(
    ("text", "key"),
    [
        ("[gps]\nstale_s = 1.5\n", "gps.stale_s"),  # 1 Hz: 1.5 periods
        ("[compass]\nstale_s = 0.1\n", "compass.stale_s"),  # 20 Hz: 2 periods
    ],
)
def test_the_readers_own_stale_limits_are_checked_at_their_rates(text: str, key: str) -> None:
    # the readers report a sensor stale after these: one late sample must not
    with pytest.raises(ConfigError, match=rf"^{re.escape(key)}: .* sample periods of"):
        loads(text)


# -- 3: a UTF-8 byte-order mark -----------------------------------------------------------------
BOM = b"\xef\xbb\xbf"


def test_a_file_with_a_byte_order_mark_loads_as_without(tmp_path: Path) -> None:
    # the audit: "not valid TOML: Invalid statement (at line 1, column 1)"
    body = (ROOT / "config" / "x6wd.toml").read_bytes()
    with_bom = tmp_path / "bom.toml"
    with_bom.write_bytes(BOM + body)
    assert load(with_bom) == load(ROOT / "config" / "x6wd.toml")
    # a first line that is a table, not a comment, as a Windows editor may save it
    first_table = tmp_path / "table.toml"
    first_table.write_bytes(BOM + b"[safety]\nfix_stale_s = 3.0\n")
    assert load(first_table).safety.fix_stale_s == 3.0
    assert loads("\ufeff[safety]\nfix_stale_s = 3.0\n").safety.fix_stale_s == 3.0


def test_a_file_with_a_byte_order_mark_is_still_validated(tmp_path: Path) -> None:
    bad = tmp_path / "bom.toml"
    for text, said in (
        (
            BOM + b"[navigation]\ndelta_phi_deg = 0.0\n",
            r"bom\.toml: navigation\.delta_phi_deg: must be >=",
        ),
        (BOM + b"[safety]\nattitude_stale_s = 0.01\n", r"bom\.toml: safety\.attitude_stale_s: "),
        # TOML errors keep their line and column, as without the mark
        (BOM + b"[gps]\nurl = 'sim://'\n[compass\n", r"not valid TOML.*line 3"),
        (BOM + b"[gps]\nurl = = 1\n", r"not valid TOML.*line 2, column 7"),
        # a mark anywhere but first is no mark: a character TOML refuses
        (b"\n" + BOM + b"[gps]\n", r"not valid TOML.*line 2, column 1"),
    ):
        bad.write_bytes(text)
        with pytest.raises(ConfigError, match=said):
            load(bad)


# -- 4: port 0 ------------------------------------------------------------------------------
def test_port_0_loads_and_is_documented_as_any_free_port() -> None:
    # Kept: the daemon and start-up tests write TOML files with port = 0 (tests/test_daemon.py,
    # test_startup.py, test_packaging.py, test_tls_required.py) so that parallel runs never
    # collide; each server logs the port it got ("... listening on 127.0.0.1:PORT").
    cfg = loads("[server]\nport = 0\n[console]\nenabled = true\nport = 0\n[gpsd]\nport = 0\n")
    assert (cfg.server.port, cfg.console.port, cfg.gpsd.port) == (0, 0, 0)
    lines = (ROOT / "config" / "x6wd.toml").read_text(encoding="utf-8").splitlines()
    port_lines = [ln for ln in lines if ln.startswith("port = ")]
    assert len(port_lines) == 3
    for ln in port_lines:
        assert "0: any free port, logged at start-up (for tests)" in ln, ln


def test_scenario_sweep_and_robot_files_with_a_byte_order_mark_load(tmp_path: Path) -> None:
    # an outside review: the BOM fix covered the robot config only
    from sim_backend.sweep import load_sweep
    from sim_backend.world import load_world, with_robot_config

    for name in ("default.toml", "zigzag.toml"):
        src = PACKAGED_CONFIG_DIR / "scenarios" / name
        dst = tmp_path / name
        dst.write_bytes(BOM + src.read_bytes())
        assert load_world(dst) == load_world(src)
    robot = tmp_path / "robot.toml"
    robot.write_bytes(BOM + (ROOT / "config" / "x6wd.toml").read_bytes())
    world = load_world(PACKAGED_CONFIG_DIR / "scenarios" / "default.toml")
    assert with_robot_config(world, robot) == with_robot_config(
        world, ROOT / "config" / "x6wd.toml"
    )
    sweep = ROOT / "config" / "sweeps" / "position_source.toml"
    bom_sweep = tmp_path / "position_source.toml"
    bom_sweep.write_bytes(BOM + sweep.read_bytes())
    assert load_sweep(bom_sweep).name == load_sweep(sweep).name
