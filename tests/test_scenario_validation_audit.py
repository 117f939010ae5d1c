"""Scenario files an outside audit of ``x6wd sim`` found accepted wrongly: [gnss] keys that act
only in the seed-003 form, given where they do nothing; effect parameters that are not finite
numbers (NaN, infinities, strings, lists, booleans) or are missing; a start too late for the
date range. Each must be a ConfigError naming the key (``x6wd sim`` exit 2), never a traceback
nor a silent no-op. Each test was watched to fail on the code before its fix."""

from __future__ import annotations

from pathlib import Path

import pytest

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
