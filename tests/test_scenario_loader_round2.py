"""The scenario loader after a second outside audit of ``x6wd sim``: a file included twice (a
diamond applied once, a file listed twice refused, a cycle refused); an error in an included
file names that file, the include chain and the key as numbered there; start_utc as a TOML
date or time; effect parameters of 1e300 that crashed the run or printed NMEA positions
hundreds of digits long. Bad configuration must stop with exit 2 and a message naming the
key and the file, never a traceback. Each test was watched to fail on the code before its
fix (except the pins said to pass before)."""

from __future__ import annotations

import dataclasses
import math
import typing
import warnings
from datetime import UTC, datetime
from pathlib import Path

import pytest

from sim_backend.effects import EFFECTS
from sim_backend.world import load_world, loads_world
from x6wd.app import cli
from x6wd.core.errors import ConfigError

BASE = (
    'name = "t"\nstart_utc = "2020-01-01T12:00:00Z"\nduration_s = 3.0\n'
    "[origin]\nlat_deg = 51.75\nlon_deg = -1.25\n"
)
BIAS = '[[effects]]\nname = "bias"\neast_m = 5.0\n'


def _write(folder: Path, name: str, text: str) -> Path:
    path = folder / name
    path.write_text(text)
    return path


def _sim(
    tmp_path: Path, path: Path, capsys: pytest.CaptureFixture[str], *more: str
) -> tuple[int, str]:
    rc = cli.main(["sim", str(path), "--out", str(tmp_path / "o"), "--quiet", *more])
    return rc, capsys.readouterr().err


# --- 1. a file included twice ----------------------------------------------------------------


def test_a_diamond_include_is_applied_once(tmp_path: Path) -> None:
    # site.toml's bias reached the world twice (two bias layers: 10 m instead of 5 m)
    _write(tmp_path, "site.toml", BIAS)
    _write(tmp_path, "a.toml", 'include = ["site.toml"]\n[vehicle]\nmax_speed_mps = 1.0\n')
    _write(tmp_path, "b.toml", 'include = ["site.toml"]\n[vehicle]\nturn_rate_dps = 30.0\n')
    top = _write(tmp_path, "s.toml", 'include = ["a.toml", "b.toml"]\n' + BASE)
    world = load_world(top)
    assert world.effects == ({"name": "bias", "east_m": 5.0},)
    assert (world.vehicle.max_speed_mps, world.vehicle.turn_rate_dps) == (1.0, 30.0)


def test_a_file_listed_twice_is_refused_naming_it_and_the_chain(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    _write(tmp_path, "site.toml", BIAS)
    top = _write(tmp_path, "s.toml", 'include = ["site.toml", "./site.toml"]\n' + BASE)
    rc, err = _sim(tmp_path, top, capsys)
    assert rc == 2 and "Traceback" not in err
    assert f"{top}: include: site.toml ({tmp_path / 'site.toml'}) is listed twice" in err
    mid = _write(tmp_path, "mid.toml", 'include = ["site.toml", "site.toml"]\n')
    top = _write(tmp_path, "s.toml", 'include = ["mid.toml"]\n' + BASE)
    rc, err = _sim(tmp_path, top, capsys)
    assert rc == 2 and f"{mid}: include: site.toml" in err and f"(included from {top})" in err


def test_a_cycle_is_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    # passed before too: a cycle was already refused; the diamond rule must not hide it
    a = _write(tmp_path, "a.toml", 'include = ["b.toml"]\n' + BASE)
    b = _write(tmp_path, "b.toml", 'include = ["a.toml"]\n')
    rc, err = _sim(tmp_path, a, capsys)
    assert rc == 2 and "Traceback" not in err
    assert f"circular include {a} -> {b} -> {a}" in err


# --- 2. an error in an included file names that file ------------------------------------------

INCLUDED_ERRORS = [
    ("[vehicle]\nmax_speed_mps = 100.0\n", "vehicle.max_speed_mps: must be <="),
    ("[vehicle]\nfoo = 1\n", "vehicle.foo: unknown key"),
    ("bogus = 1\n", "bogus: unknown key"),
    ("seed = -1\n", "seed: must be >= 0"),
    ("[gnss]\nre_m = 50.0\n", "gnss.re_m: act only"),
    ('[[effects]]\nname = "bias"\neast_m = "x"\n', "effects[0].east_m: expected a number"),
    ('[[effects]]\nname = "bias"\nnorth = 3.0\n', "effects[0] (bias): unknown parameter"),
    ("[mission]\nwaypoints_enu = [[1.0]]\n", "mission.waypoints_enu[0]: expected a pair"),
]


@pytest.mark.parametrize(("text", "message"), INCLUDED_ERRORS)
def test_an_error_in_an_included_file_names_that_file(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], text: str, message: str
) -> None:
    # the top file was blamed (and, for the effect, one of its own before it was counted)
    inc = _write(tmp_path, "inc.toml", text)
    top = _write(tmp_path, "s.toml", 'include = ["inc.toml"]\n' + BASE + BIAS)
    rc, err = _sim(tmp_path, top, capsys)
    assert rc == 2 and "Traceback" not in err
    assert f"x6wd sim: error: {inc}: {message}" in err
    assert err.rstrip().endswith(f"(included from {top})")


def test_the_chain_of_a_nested_include_and_the_top_files_own_numbering(
    tmp_path: Path,
) -> None:
    inc = _write(tmp_path, "inc.toml", BIAS + '[[effects]]\nname = "bias"\nup_m = "x"\n')
    mid = _write(tmp_path, "mid.toml", 'include = ["inc.toml"]\n')
    top = _write(tmp_path, "s.toml", 'include = ["mid.toml"]\n' + BASE)
    with pytest.raises(ConfigError) as err:
        load_world(top)
    assert str(err.value) == (
        f"{inc}: effects[1].up_m: expected a number, got 'x' (included from {top} -> {mid})"
    )
    # the top file's own [[effects]] come after the included ones, numbered as in the file
    _write(tmp_path, "inc.toml", BIAS + BIAS)
    bad = '[[effects]]\nname = "bias"\nnorth = 3.0\n'
    top = _write(tmp_path, "s.toml", 'include = ["inc.toml"]\n' + BASE + BIAS + bad)
    with pytest.raises(ConfigError, match=rf"^{top}: effects\[1\] \(bias\): unknown parameter"):
        load_world(top)


def test_a_missing_key_blames_the_file_of_its_table_or_the_top_file(tmp_path: Path) -> None:
    inc = _write(tmp_path, "inc.toml", "[origin]\nlat_deg = 1.0\n")
    top = _write(tmp_path, "s.toml", 'include = ["inc.toml"]\nname = "t"\n')
    with pytest.raises(ConfigError, match=rf"^{inc}: origin\.lon_deg: required \(included from"):
        load_world(top)
    top = _write(tmp_path, "s.toml", 'include = ["inc.toml"]\n[origin]\nlon_deg = 1.0\n')
    with pytest.raises(ConfigError, match=rf"^{top}: name: required"):
        load_world(top)


def test_an_unreadable_included_file_names_the_chain(tmp_path: Path) -> None:
    _write(tmp_path, "mid.toml", 'include = ["missing.toml"]\n')
    top = _write(tmp_path, "s.toml", 'include = ["mid.toml"]\n' + BASE)
    with pytest.raises(
        ConfigError,
        match=r"missing\.toml: cannot read .*\(included from .*s\.toml -> .*mid\.toml\)",
    ):
        load_world(top)


# --- 4. start_utc as a TOML datetime, date or time --------------------------------------------


def test_an_unquoted_toml_datetime_with_an_offset_runs(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # passed before too (the audit's report did not reproduce on this code): pinned
    text = BASE.replace('"2020-01-01T12:00:00Z"', "2020-01-01T14:00:00+02:00")
    path = _write(tmp_path, "s.toml", text)
    assert load_world(path).start_utc == datetime(2020, 1, 1, 12, tzinfo=UTC)
    rc, err = _sim(tmp_path, path, capsys)
    assert rc == 0 and "Traceback" not in err
    assert "$GPRMC,120000.00,A," in (tmp_path / "o" / "gps.nmea").read_text()


def test_a_toml_date_is_its_midnight_utc_like_the_string(tmp_path: Path) -> None:
    # was refused: "expected an ISO-8601 time, got datetime.date(2020, 1, 2)", while the
    # string "2020-01-02" loaded as its 00:00 UTC
    world = load_world(
        _write(tmp_path, "s.toml", BASE.replace('"2020-01-01T12:00:00Z"', "2020-01-02"))
    )
    assert world.start_utc == datetime(2020, 1, 2, tzinfo=UTC)
    assert loads_world(world.to_toml()) == world


def test_a_toml_time_of_day_is_refused_saying_it_has_no_date(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = _write(tmp_path, "s.toml", BASE.replace('"2020-01-01T12:00:00Z"', "12:00:00"))
    rc, err = _sim(tmp_path, path, capsys)
    assert rc == 2 and "Traceback" not in err
    assert f"{path}: start_utc: 12:00:00 is a time of day without a date" in err


# --- 5. effect parameters of +-1e300 -----------------------------------------------------------

VALID: dict[str, dict[str, float]] = {
    "gauss_markov": {"sigma_m": 1.0, "tau_s": 10.0},
    "random_walk": {"q_m_per_sqrt_s": 0.1},
    "jumps": {"sigma_m": 1.0},
    "outages": {"mean_up_s": 100.0, "mean_down_s": 5.0},
    "outage": {"start_s": 1.0, "duration_s": 1.0},
    "latency": {"delay_s": 0.2},
    "multipath_zone": {"x1_m": 0.0, "y1_m": 0.0, "x2_m": 10.0, "y2_m": 0.0, "distance_m": 5.0},
    "nav_filter": {"tau_s": 2.0},
    "noise_scale": {"factor": 0.5},
    "static_hold": {"exit_distance_m": 1.0},
    "correction": {"factor": 0.5},
    "hard_iron": {"bx_ut": 1.0, "by_ut": 2.0},
    "soft_iron": {"k": 0.1},
    "declination": {"declination_deg": 2.0},
    "heading_noise": {"sigma_deg": 1.0},
}
# a route, so the robot engine runs (the compass layers act only there)
ROUTE = "[mission]\nwaypoints_enu = [[30.0, 0.0], [30.0, 30.0]]\n"
# sim_backend.effects' bounds, as literals so that this file loads on the code before them
MAX_M, MAX_FACTOR, MAX_FRAME_M = 100_000.0, 1000.0, 1e6
MAX_WALK = MAX_M / math.sqrt(30 * 86400.0)
BOUNDS = {  # the bounded parameters at their bound: still accepted
    ("bias", "east_m"): -MAX_M,
    ("gauss_markov", "sigma_m"): MAX_M,
    ("random_walk", "q_m_per_sqrt_s"): MAX_WALK,
    ("jumps", "sigma_m"): MAX_M,
    ("jumps", "up_sigma_m"): MAX_M,
    ("multipath_zone", "x1_m"): -MAX_FRAME_M,
    ("multipath_zone", "sigma_m"): MAX_M,
    ("multipath_zone", "bias_m"): -MAX_M,
    ("noise_scale", "factor"): MAX_FACTOR,
    ("correction", "factor"): MAX_FACTOR,
    ("static_hold", "exit_distance_m"): MAX_M,
    ("heading_noise", "sigma_deg"): 180.0,
}


def _effect(name: str, params: dict[str, object]) -> str:
    lines = [f'name = "{name}"'] + [f"{k} = {v}" for k, v in params.items()]
    return "[[effects]]\n" + "\n".join(lines) + "\n"


def _huge_cases() -> list[tuple[str, str, str]]:
    out = []
    for name, cls in EFFECTS.items():
        hints = typing.get_type_hints(cls)
        for f in dataclasses.fields(cls):
            if hints[f.name] is float:
                out += [(name, f.name, "1e300"), (name, f.name, "-1e300")]
    return out


@pytest.mark.parametrize(("name", "key", "value"), _huge_cases())
def test_a_huge_effect_parameter_is_refused_or_runs_sanely(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], name: str, key: str, value: str
) -> None:
    # Before: heading_noise.sigma_deg and static_hold.exit_distance_m crashed the run
    # (OverflowError); gauss_markov/jumps/multipath_zone sigma_m, jumps.up_sigma_m,
    # multipath_zone.bias_m, random_walk.q_m_per_sqrt_s and the noise_scale/correction
    # factors printed NMEA fields of hundreds of digits; multipath_zone.x1_m/y1_m overflowed
    # the wall geometry. Either a load-time refusal naming the key (exit 2), or a run whose
    # NMEA sentences are of NMEA's length (<= 82 characters) with finite numbers.
    params = {**VALID.get(name, {}), key: value}
    path = _write(tmp_path, "s.toml", BASE + ROUTE + _effect(name, params))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        rc, err = _sim(tmp_path, path, capsys, "--duration", "20")
    assert "Traceback" not in err
    assert not [w for w in caught if "overflow" in str(w.message)]
    if rc == 2:
        assert f"{path}: effects[0] ({name}): " in err and f"{key}={float(value)!r}: must be" in err
        return
    assert rc in (0, 1), err
    nmea = (tmp_path / "o" / "gps.nmea").read_text().splitlines()
    assert nmea and max(len(s) for s in nmea) <= 82
    assert not any(w in s.lower() for s in nmea for w in ("nan", "inf"))


@pytest.mark.parametrize(("name", "key"), list(BOUNDS))
def test_an_effect_parameter_at_its_bound_loads(tmp_path: Path, name: str, key: str) -> None:
    params = {**VALID.get(name, {}), key: repr(BOUNDS[name, key])}
    if name == "multipath_zone":
        params["x2_m"] = "10.0"
    world = load_world(_write(tmp_path, "s.toml", BASE + _effect(name, params)))
    assert getattr(world.effect_objects()[0], key) == BOUNDS[name, key]


def test_the_bounds_here_are_the_modules() -> None:
    from sim_backend import effects

    assert (effects.MAX_BIAS_M, effects.MAX_FACTOR, effects.MAX_FRAME_M) == (
        MAX_M,
        MAX_FACTOR,
        MAX_FRAME_M,
    )
    assert (effects.MAX_WALK_M_PER_SQRT_S, effects.MAX_HEADING_SIGMA_DEG) == (MAX_WALK, 180.0)


# --- 3. [compass] errors name the file -------------------------------------------------------


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("foo = 1.0\n", "compass.foo: unknown key"),
        ("noise_ut = -1.0\n", "compass.noise_ut: must be within 0..100, got -1.0"),
        ("hard_iron_ut = [1.0, 2.0]\n", "compass.hard_iron_ut needs 3 components"),
        ("hard_iron_ut = [nan, 0.0, 0.0]\n", "compass.hard_iron_ut must be 3 finite"),  # crashed
        ("hard_iron_ut = [0.0, inf, 0.0]\n", "compass.hard_iron_ut must be 3 finite"),
        (
            "soft_iron = [[0.0, 0, 0], [0, 0, 0], [0, 0, 0]]\n",
            "compass.soft_iron matrix is singular",
        ),
    ],
)
def test_a_compass_error_names_the_file(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], text: str, message: str
) -> None:
    # was raised at the run's start, without the file ("x6wd sim: error: compass.foo: ...")
    path = _write(tmp_path, "s.toml", BASE + "[compass]\n" + text)
    rc, err = _sim(tmp_path, path, capsys)
    assert rc == 2 and "Traceback" not in err
    assert f"x6wd sim: error: {path}: {message}" in err
    inc = _write(tmp_path, "inc.toml", "[compass]\n" + text)
    top = _write(tmp_path, "s.toml", 'include = ["inc.toml"]\n' + BASE)
    with pytest.raises(ConfigError, match=rf"^{inc}: compass\."):
        load_world(top)
