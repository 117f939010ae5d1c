"""Scenario files an outside audit of ``x6wd sim`` found accepted wrongly: [gnss] keys that act
only in the seed-003 form, given where they do nothing; effect parameters that are not finite
numbers (NaN, infinities, strings, lists, booleans) or are missing; a start too late for the
date range. Each must be a ConfigError naming the key (``x6wd sim`` exit 2), never a traceback
nor a silent no-op. Each test was watched to fail on the code before its fix."""

from __future__ import annotations

import dataclasses
import typing
from pathlib import Path

import pytest

from sim_backend.effects import EFFECTS
from sim_backend.world import load_world
from x6wd.app import cli
from x6wd.core.errors import ConfigError

BASE = (
    'name = "t"\nstart_utc = "2020-01-01T12:00:00Z"\nduration_s = 3.0\n'
    "[origin]\nlat_deg = 51.75\nlon_deg = -1.25\n"
)


def _write(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "s.toml"
    path.write_text(text)
    return path


def _sim(tmp_path: Path, path: Path, capsys: pytest.CaptureFixture[str]) -> tuple[int, str]:
    rc = cli.main(["sim", str(path), "--out", str(tmp_path / "o"), "--quiet"])
    return rc, capsys.readouterr().err


# --- 1. [gnss] keys of the seed-003 form (fidelity "seed", seed_uere "re_ase_lce") -----------

SEED_003 = [
    "re_m = 50.0",
    "ase_m = 2.0",
    "lce_sigma_m = [[1.0, 2.0]]",
    'lce_csv = "map.csv"',
    "lce_cell_m = 5.0",
    "lce_east0_m = 1.0",
    "lce_north0_m = 1.0",
    "lce_outside_m = 1.0",
]
ELSEWHERE = [
    "",
    'fidelity = "pseudorange"\n',
    'fidelity = "seed"\n',
    'fidelity = "seed"\nseed_uere = "modelled"\n',
]


@pytest.mark.parametrize("setting", ELSEWHERE)
@pytest.mark.parametrize("line", SEED_003)
def test_seed_003_keys_are_refused_where_they_do_not_act(
    tmp_path: Path, setting: str, line: str
) -> None:
    (tmp_path / "map.csv").write_text("1.0,2.0\n")
    key = line.split(" =")[0]
    path = _write(tmp_path, f"{BASE}[gnss]\n{setting}{line}\n")
    with pytest.raises(ConfigError, match=rf"gnss\.{key}\b.*seed_uere = \"re_ase_lce\""):
        load_world(path)


def test_seed_003_keys_load_where_they_act(tmp_path: Path) -> None:
    (tmp_path / "map.csv").write_text("1.0,2.0\n")
    for line in SEED_003:
        if line.startswith("lce_sigma_m"):
            continue  # lce_csv gives the grid here (not both)
        text = f'{BASE}[gnss]\nfidelity = "seed"\nseed_uere = "re_ase_lce"\n{line}\n'
        assert load_world(_write(tmp_path, text)).gnss.fidelity == "seed"


@pytest.mark.parametrize("value", ["re_ase_lce", "modelled"])
def test_seed_uere_is_refused_under_the_pseudorange_fidelity(tmp_path: Path, value: str) -> None:
    path = _write(tmp_path, f'{BASE}[gnss]\nseed_uere = "{value}"\n')
    with pytest.raises(ConfigError, match=r"gnss\.seed_uere\b.*fidelity = \"seed\""):
        load_world(path)


def test_sim_refuses_re_m_under_the_default_fidelity(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # the audit: re_m = 50 gave output byte-identical to none
    path = _write(tmp_path, f"{BASE}[gnss]\nre_m = 50.0\nase_m = 3.0\n")
    rc, err = _sim(tmp_path, path, capsys)
    assert rc == 2 and "Traceback" not in err
    assert "gnss.re_m, gnss.ase_m" in err and 'fidelity = "pseudorange"' in err


# --- 2. and 3. effect parameters: finite real numbers, required ones present -----------------

# a valid table for every effect (its required parameters)
VALID: dict[str, dict[str, object]] = {
    "gauss_markov": {"sigma_m": 1.0, "tau_s": 10.0},
    "random_walk": {"q_m_per_sqrt_s": 0.1},
    "bias": {},
    "quantization": {},
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
    "tilt": {},
    "declination": {"declination_deg": 2.0},
    "heading_lag": {},
    "heading_noise": {"sigma_deg": 1.0},
}
BAD_NUMBERS = ["nan", "inf", "-inf", '"1"', "[1.0]", "true"]


def _effect(name: str, params: dict[str, object]) -> str:
    lines = [f'name = "{name}"'] + [f"{k} = {v}" for k, v in params.items()]
    return "[[effects]]\n" + "\n".join(lines) + "\n"


def _number_fields() -> list[tuple[str, str]]:
    out = []
    for name, cls in EFFECTS.items():
        hints = typing.get_type_hints(cls)
        out += [(name, f.name) for f in dataclasses.fields(cls) if hints[f.name] is float]
    return out


def _required_fields() -> list[tuple[str, str]]:
    return [
        (name, f.name)
        for name, cls in EFFECTS.items()
        for f in dataclasses.fields(cls)
        if f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING
    ]


def test_every_effect_has_a_valid_table_that_loads(tmp_path: Path) -> None:
    assert set(VALID) == set(EFFECTS)
    text = BASE + "".join(_effect(n, p) for n, p in VALID.items())
    assert len(load_world(_write(tmp_path, text)).effect_objects()) == len(EFFECTS)


@pytest.mark.parametrize("bad", BAD_NUMBERS)
@pytest.mark.parametrize(("name", "key"), _number_fields())
def test_an_effect_number_that_is_not_a_finite_number_is_named(
    tmp_path: Path, name: str, key: str, bad: str
) -> None:
    params = {**VALID[name], key: bad}
    path = _write(tmp_path, BASE + _effect("bias", {}) + _effect(name, params))
    with pytest.raises(ConfigError, match=rf"effects\[1\]\.{key}: "):
        load_world(path)


@pytest.mark.parametrize(("name", "key"), _required_fields())
def test_a_missing_effect_parameter_is_named(tmp_path: Path, name: str, key: str) -> None:
    params = {k: v for k, v in VALID[name].items() if k != key}
    path = _write(tmp_path, BASE + _effect(name, params))
    with pytest.raises(ConfigError, match=rf"effects\[0\]\.{key}: required \({name}\b") as err:
        load_world(path)
    assert "__init__" not in str(err.value)


def test_sim_names_the_effect_key_of_a_string_sigma(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # the audit: "'>=' not supported between instances of 'str' and 'int'"
    path = _write(tmp_path, BASE + _effect("gauss_markov", {"sigma_m": '"1"', "tau_s": 10.0}))
    rc, err = _sim(tmp_path, path, capsys)
    assert rc == 2 and "Traceback" not in err and "not supported" not in err
    assert "effects[0].sigma_m: expected a number, got '1'" in err


def test_sim_refuses_a_nan_zone_and_an_infinite_declination(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # the audit: a NaN zone never acted; an infinite declination crashed the run
    zone = {**VALID["multipath_zone"], "x1_m": "nan"}
    rc, err = _sim(tmp_path, _write(tmp_path, BASE + _effect("multipath_zone", zone)), capsys)
    assert rc == 2 and "Traceback" not in err
    assert "effects[0].x1_m: must be finite, got nan" in err
    decl = _effect("declination", {"declination_deg": "inf"})
    rc, err = _sim(tmp_path, _write(tmp_path, BASE + decl), capsys)
    assert rc == 2 and "Traceback" not in err and "effects[0].declination_deg" in err


# --- 4. a start whose run would leave the date range ----------------------------------------


def test_a_start_at_the_end_of_the_date_range_is_refused(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    late = BASE.replace("2020-01-01T12:00:00Z", "9999-12-31T23:59:50Z").replace("3.0", "20.0")
    rc, err = _sim(tmp_path, _write(tmp_path, late), capsys)
    assert rc == 2 and "Traceback" not in err and "start_utc" in err
    assert "9999-11-30T00:00:00" in err  # the bound is said
    ok = BASE.replace("2020-01-01T12:00:00Z", "9999-11-30T00:00:00Z")
    assert load_world(_write(tmp_path, ok)).start_utc.year == 9999


def test_sim_refuses_a_bias_beyond_any_receivers_error(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # the audit's fixer: east_m = 1e300 passed the finite check and crashed the NMEA output
    path = _write(tmp_path, BASE + _effect("bias", {"east_m": 1e300}))
    rc, err = _sim(tmp_path, path, capsys)
    assert rc == 2 and "Traceback" not in err and "east_m" in err and "100000" in err
    assert load_world(_write(tmp_path, BASE + _effect("bias", {"north_m": -99_999.0})))
