"""The wheel ships config/ (outside audit 10c, medium): a non-editable install (`pip install
/path/to/x6wd` or the wheel, docs/install.md) had no config/ folder, so `x6wd gap` without
--scenario, hardware in the loop without a [sim] scenario and a copied hil.toml's
"scenarios/default.toml" all looked in .../site-packages/config/ and exited 2.

The real wheel is built (pip with the venv's hatchling, the dev extra's pinned build backend:
offline, no build isolation), its file list is checked against the repository's config/, and
the default scenarios are looked up by a Python that imports x6wd only from the unpacked
wheel, from a working directory outside the repository."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

from tests.conftest import ROOT

# Run by a Python whose x6wd, drivers and sim_backend are the unpacked wheel's (PYTHONPATH
# comes before the venv's editable install of the repository).
LOOKUP = """
import json, sys
from pathlib import Path
import x6wd, sim_backend
from x6wd.core import config
from x6wd.gap import cli as gap_cli
from sim_backend import hil
from sim_backend.world import load_world
copied = Path(sys.argv[1])  # hil.toml copied out of the wheel, alone in its folder
cfg = config.load(copied)
for scenario in (gap_cli.DEFAULT_SCENARIO, hil.resolve_scenario("")):
    load_world(scenario)  # parses: nothing it includes is missing
print(json.dumps({
    "modules": [x6wd.__file__, sim_backend.__file__],
    "packaged": str(config.PACKAGED_CONFIG_DIR),
    "gap_default": str(gap_cli.DEFAULT_SCENARIO),
    "hil_default": str(hil.resolve_scenario("")),
    "hil_relative": str(hil.resolve_scenario("scenarios/default.toml")),
    "copied_hil_scenario": cfg.sim.scenario,
}))
"""


def _config_files() -> dict[str, bytes]:
    """The repository's config/ files by path relative to it (the wheel's source)."""
    base = ROOT / "config"
    return {
        p.relative_to(base).as_posix(): p.read_bytes()
        for p in sorted(base.rglob("*"))
        if p.is_file() and "__pycache__" not in p.parts
    }


# ~2 s of CPU (pip, then a Python importing scipy), 8.6 s on a 2-core machine at load 6
@pytest.mark.slow
@pytest.mark.integration
def test_the_wheel_ships_config_and_finds_its_default_scenarios(tmp_path: Path) -> None:
    dist = tmp_path / "dist"
    env = {**os.environ, "PIP_NO_INDEX": "1"}  # offline: the build uses the venv's hatchling
    subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "--no-build-isolation",
         "-w", str(dist), str(ROOT)],
        check=True, cwd=tmp_path, env=env, timeout=120,
    )  # fmt: skip
    (wheel,) = dist.glob("x6wd-*.whl")
    site = tmp_path / "site"
    with zipfile.ZipFile(wheel) as zf:
        shipped = {
            name.removeprefix("x6wd/_config/"): zf.read(name)
            for name in zf.namelist()
            if name.startswith("x6wd/_config/") and not name.endswith("/")
        }
        zf.extractall(site)
    source = _config_files()
    for must in ("x6wd.toml", "hil.toml", "scenarios/default.toml", "scenarios/open_field.toml"):
        assert must in source, f"config/{must} is gone: this test names it"
    assert sorted(shipped) == sorted(source), "the wheel's x6wd/_config/ is not config/"
    assert shipped == source, "the wheel's copy of config/ differs from the repository's"

    # hil.toml copied out of the wheel, as docs/install.md suggests, with nothing beside it
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "hil.toml").write_bytes(shipped["hil.toml"])
    outside = tmp_path / "cwd"
    outside.mkdir()  # the working directory holds no scenarios/ to fall back on
    out = subprocess.run(
        [sys.executable, "-c", LOOKUP, str(mine / "hil.toml")],
        cwd=outside, env={**env, "PYTHONPATH": str(site)},
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert out.returncode == 0, out.stderr[-2000:]
    got = json.loads(out.stdout)
    packaged = site / "x6wd" / "_config"
    assert [Path(m).resolve().is_relative_to(site.resolve()) for m in got["modules"]] == [
        True,
        True,
    ], f"not the wheel's packages: {got['modules']}"
    assert Path(got["packaged"]) == packaged.resolve()
    assert Path(got["gap_default"]) == packaged.resolve() / "scenarios" / "open_field.toml"
    default = packaged.resolve() / "scenarios" / "default.toml"
    for key in ("hil_default", "hil_relative", "copied_hil_scenario"):
        assert Path(got[key]).resolve() == default, (key, got[key])
        assert Path(got[key]).is_file(), (key, got[key])


def test_a_source_tree_uses_the_repositorys_config() -> None:
    """In a checkout (or an editable install) the folder to edit is the repository's: no
    copy, so an edited scenario is the one that runs."""
    from x6wd.core.config import PACKAGED_CONFIG_DIR

    assert PACKAGED_CONFIG_DIR == ROOT / "config"
    assert not (ROOT / "x6wd" / "_config").exists()
