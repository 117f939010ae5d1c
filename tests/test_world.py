"""Scenario files: loading, validation naming the key, paths, includes and fragments."""

from __future__ import annotations

import shutil
from datetime import UTC, datetime
from pathlib import Path

import numpy as np
import pytest

from sim_backend.buildings import Walls
from sim_backend.world import DEFAULT_ALMANAC, load_world, loads_world, merge_fragment
from x6wd.core.errors import ConfigError

HERE = Path(__file__).resolve().parent
SHARED_ALMANAC = HERE.parent.parent / "shared" / "data" / "almanac" / "almyuma_01jan2020.txt"

FULL = """
name = "beside a building"
start_utc = "2020-01-01T10:30:00Z"
duration_s = 120
seed = 42

[origin]
lat_deg = 46.47
lon_deg = 30.74
alt_m = 40.0

[gnss]
fidelity = "seed"
mask_deg = 10
rate_hz = 4
nmea_decimals = 4
seed_uere = "re_ase_lce"
re_m = 0.4
ase_m = 1.2
lce_cell_m = 5.0
lce_sigma_m = [[0.5, 1.0], [2.0, 3.0]]

[atmosphere]
tec_tecu = 25.0
cloud = "stratus"
env_noise_db = 10.0

[[walls]]
x0_m = -20.0
y0_m = -8.0
x1_m = 20.0
y1_m = -8.0
height_m = 12.0
windows = [{u0_m = 18.0, u1_m = 21.0, z0_m = 1.0, z1_m = 2.5}]

[[buildings]]
x0_m = 30.0
y0_m = 30.0
x1_m = 50.0
y1_m = 45.0
height_m = 15.0

[roof]
x0_m = -5.0
y0_m = -5.0
x1_m = 5.0
y1_m = 5.0
height_m = 4.0
holes = [{x0_m = -1.0, y0_m = -1.0, x1_m = 1.0, y1_m = 1.0}]

[vehicle]
max_speed_mps = 2.0
turn_rate_dps = 60.0
start_heading_deg = 90.0
slope_east_pct = 5.0

[compass]
declination_deg = 7.5
noise_ut = 1.0

[[effects]]
name = "gauss_markov"
sigma_m = 0.8
tau_s = 60.0

[mission]
waypoints = [[46.4705, 30.7405]]
waypoints_enu = [[10.0, 0.0], [0.0, 25.0]]

[navigation]
delta_x_m = 2.0

[safety]
fix_stale_s = 3.0
"""


def _write(folder: Path, name: str, text: str) -> Path:
    path = folder / name
    path.write_text(text, encoding="utf-8")
    return path


def test_full_scenario_loads(tmp_path: Path) -> None:
    world = load_world(_write(tmp_path, "s.toml", FULL))
    assert world.name == "beside a building"
    assert world.start_utc == datetime(2020, 1, 1, 10, 30, tzinfo=UTC)
    assert world.duration_s == 120.0 and world.seed == 42
    assert world.origin.lat_deg == 46.47 and world.origin.alt_m == 40.0
    assert world.almanac_path == DEFAULT_ALMANAC and DEFAULT_ALMANAC.is_file()
    assert world.gnss.fidelity == "seed" and world.gnss.rate_hz == 4.0
    assert world.gnss.nmea_decimals == 4 and world.gnss.ase_m == 1.2
    lce = world.lce_array()
    assert lce is not None and lce.shape == (2, 2) and lce[1, 1] == 3.0
    assert world.atmosphere.tec_tecu == 25.0 and world.atmosphere.cloud == "stratus"
    assert len(world.walls) == 1 + 4  # one wall plus a four-wall building
    assert world.walls[0].windows[0].u1_m == 21.0
    assert world.roofs[0].holes[0].x1_m == 1.0
    assert world.vehicle.max_speed_mps == 2.0 and world.vehicle.slope_east_pct == 5.0
    assert world.compass == {"declination_deg": 7.5, "noise_ut": 1.0}
    assert world.effects[0]["name"] == "gauss_markov"
    (eff,) = world.effect_objects()
    assert eff.name == "gauss_markov"
    assert world.navigation.delta_x_m == 2.0 and world.safety.fix_stale_s == 3.0
    scene = world.walls_model()
    assert isinstance(scene, Walls) and len(scene) == 5
    # The scene is usable: the wall at y = -8 hides a low southern satellite, except through
    # its window (x = -2 .. 1, 1 .. 2.5 m high).
    rx = np.array([[5.0, 0.0, 0.3], [0.0, 0.0, 0.3]])
    res = scene.trace(rx, np.array([[180.0], [180.0]]), np.array([[10.0], [10.0]]))
    assert not res.los[0, 0] and res.los[1, 0]


def test_waypoints_geographic_and_local(tmp_path: Path) -> None:
    world = load_world(_write(tmp_path, "s.toml", FULL))
    enu = world.waypoints_enu_m()
    ll = world.waypoints_latlon()
    assert enu.shape == (3, 2) and ll.shape == (3, 2)
    np.testing.assert_allclose(enu[1:], [[10.0, 0.0], [0.0, 25.0]])
    # 0.0005 deg north ~ 55.6 m, 0.0005 deg east at 46.47 N ~ 38.4 m.
    assert enu[0, 1] == pytest.approx(55.6, abs=0.3)
    assert enu[0, 0] == pytest.approx(38.4, abs=0.3)
    assert ll[0, 0] == 46.4705
    # 25 m north of the origin ~ 2.25e-4 degrees of latitude.
    assert ll[2, 0] - 46.47 == pytest.approx(25.0 / 111_140.0, rel=0.01)
    assert ll[2, 1] == pytest.approx(30.74, abs=1e-9)


def test_minimal_scenario_defaults() -> None:
    world = loads_world('name = "x"\n[origin]\nlat_deg = 51.7\nlon_deg = 39.2\n')
    assert world.gnss.fidelity == "pseudorange" and world.gnss.mask_deg == 5.0
    assert world.gnss.nmea_decimals == 5 and world.gnss.baud == 9600
    assert world.vehicle.max_speed_mps == pytest.approx(14.0 / 3.6)
    assert world.walls_model() is None and world.lce_array() is None
    assert world.waypoints_enu_m().shape == (0, 2)


@pytest.mark.parametrize(
    ("snippet", "key"),
    [
        ('name = "x"\nbogus = 1\n[origin]\nlat_deg = 1\nlon_deg = 2\n', "bogus"),
        ('name = "x"\n[origin]\nlat_deg = 1\n', r"origin\.lon_deg"),
        ('name = "x"\n[origin]\nlat_deg = 95\nlon_deg = 2\n', r"origin\.lat_deg"),
        ("[origin]\nlat_deg = 1\nlon_deg = 2\n", "name"),
        ('name = "x"\nduration_s = -5\n[origin]\nlat_deg = 1\nlon_deg = 2\n', "duration_s"),
        ('name = "x"\nstart_utc = "yesterday"\n[origin]\nlat_deg = 1\nlon_deg = 2\n', "start_utc"),
        ('name = "x"\n[origin]\nlat_deg = 1\nlon_deg = 2\n[gnss]\nrate_hz = 5\n', r"gnss\.rate_hz"),
        (
            'name = "x"\n[origin]\nlat_deg = 1\nlon_deg = 2\n[gnss]\nfidelity = "best"\n',
            r"gnss\.fidelity",
        ),
        (
            'name = "x"\n[origin]\nlat_deg = 1\nlon_deg = 2\n[gnss]\nnmea_decimals = 8\n',
            r"gnss\.nmea_decimals",
        ),
        (
            'name = "x"\n[origin]\nlat_deg = 1\nlon_deg = 2\n[gnss]\nlce_sigma_m = [[1, 2], [3]]\n',
            r"gnss\.lce_sigma_m",
        ),
        (
            'name = "x"\n[origin]\nlat_deg = 1\nlon_deg = 2\n[atmosphere]\nenv_noise_db = "loud"\n',
            r"atmosphere\.env_noise_db",
        ),
        (
            'name = "x"\n[origin]\nlat_deg = 1\nlon_deg = 2\n[[walls]]\nx0_m = 0\ny0_m = 0\n'
            "x1_m = 5\ny1_m = 0\ncolour = 3\n",
            r"walls\[0\]\.colour",
        ),
        (
            'name = "x"\n[origin]\nlat_deg = 1\nlon_deg = 2\n[[walls]]\nx0_m = 0\ny0_m = 0\n'
            "x1_m = 5\ny1_m = 0\nthickness_m = 0\n",
            r"walls\[0\].*thickness_m",
        ),
        (
            'name = "x"\n[origin]\nlat_deg = 1\nlon_deg = 2\n[[walls]]\nx0_m = 0\ny0_m = 0\n'
            "x1_m = 5\ny1_m = 0\nheight_m = 3\n"
            "windows = [{u0_m = 1, u1_m = 2, z0_m = 0, z1_m = 4}]\n",
            r"walls\[0\].*windows\[0\]",
        ),
        (
            'name = "x"\n[origin]\nlat_deg = 1\nlon_deg = 2\n[roof]\nx0_m = 0\ny0_m = 0\n'
            "x1_m = 5\ny1_m = 5\n",
            r"roofs\[0\]\.height_m",
        ),
        (
            'name = "x"\n[origin]\nlat_deg = 1\nlon_deg = 2\n[vehicle]\nmax_speed_mps = 9\n',
            r"vehicle\.max_speed_mps",
        ),
        (
            'name = "x"\n[origin]\nlat_deg = 1\nlon_deg = 2\n[[effects]]\nname = "teleport"\n',
            r"effects\[0\]",
        ),
        (
            'name = "x"\n[origin]\nlat_deg = 1\nlon_deg = 2\n[[effects]]\nname = "bias"\n'
            "wobble = 2\n",
            r"effects\[0\]",
        ),
        (
            'name = "x"\n[origin]\nlat_deg = 1\nlon_deg = 2\n[mission]\nwaypoints = [[1, 2, 3]]\n',
            r"mission\.waypoints\[0\]",
        ),
        (
            'name = "x"\n[origin]\nlat_deg = 1\nlon_deg = 2\n[navigation]\ndelta_phi_deg = 0\n',
            r"navigation\.delta_phi_deg",
        ),
        (
            'name = "x"\n[origin]\nlat_deg = 1\nlon_deg = 2\n[safety]\nfix_stale_s = true\n',
            r"safety\.fix_stale_s",
        ),
        (
            'name = "x"\n[origin]\nlat_deg = 1\nlon_deg = 2\n[[walls]]\nx0_m = 0\ny0_m = 0\n'
            "x1_m = 5\ny1_m = 0\npenetration_db = -3\n",
            r"walls\[0\].*penetration_db",
        ),
        (
            'name = "x"\n[origin]\nlat_deg = 1\nlon_deg = 2\n[roof]\nx0_m = 0\ny0_m = 0\n'
            "x1_m = 5\ny1_m = 5\nheight_m = 3\nrefractive_index = 0.5\n",
            r"roofs\[0\].*refractive_index",
        ),
        (
            'name = "x"\n[origin]\nlat_deg = 1\nlon_deg = 2\n[[buildings]]\nx0_m = 0\ny0_m = 0\n'
            "x1_m = 5\ny1_m = 5\nheight_m = 3\npenetration_db = -1\n",
            r"buildings\[0\].*penetration_db",
        ),
        ('name = "x"\nalmanac = "nope.txt"\n[origin]\nlat_deg = 1\nlon_deg = 2\n', "almanac"),
        (  # 1e9 m east: every fix invalid and no message, before the bound
            'name = "x"\n[origin]\nlat_deg = 1\nlon_deg = 2\n[vehicle]\nstart_east_m = 1e9\n',
            r"vehicle\.start_east_m",
        ),
        (
            'name = "x"\n[origin]\nlat_deg = 1\nlon_deg = 2\n[vehicle]\nstart_north_m = -2e6\n',
            r"vehicle\.start_north_m",
        ),
        ('name = "x"\n[origin\n', "not valid TOML"),
    ],
)
def test_bad_values_name_the_key(snippet: str, key: str) -> None:
    with pytest.raises(ConfigError, match=key):
        loads_world(snippet)


def test_relative_paths_resolve_against_scenario_folder(tmp_path: Path) -> None:
    sub = tmp_path / "scen"
    (sub / "data").mkdir(parents=True)
    shutil.copy(DEFAULT_ALMANAC, sub / "data" / "alm.txt")
    (sub / "data" / "lce.csv").write_text("# north rows\n0.5,1.5,2.5\n3.0,4.0,5.0\n")
    text = (
        'name = "x"\nalmanac = "data/alm.txt"\n[origin]\nlat_deg = 1\nlon_deg = 2\n'
        '[gnss]\nfidelity = "seed"\nseed_uere = "re_ase_lce"\nlce_csv = "data/lce.csv"\n'
        "lce_cell_m = 2.0\n"
    )
    path = _write(sub, "s.toml", text)
    world = load_world(path)
    assert world.almanac_path == (sub / "data" / "alm.txt").resolve()
    lce = world.lce_array()
    assert lce is not None
    np.testing.assert_array_equal(lce, [[0.5, 1.5, 2.5], [3.0, 4.0, 5.0]])
    # Loading from elsewhere (another working directory) gives the same result.
    assert load_world(str(path)) == world
    # The resolved copy is self-contained: it loads from any folder.
    other = tmp_path / "elsewhere"
    other.mkdir()
    copy_path = _write(other, "copy.toml", world.to_toml())
    again = load_world(copy_path)
    assert again == world
    assert again.almanac_path == world.almanac_path


def test_packaged_almanac_is_the_shared_one() -> None:
    if SHARED_ALMANAC.is_file():
        assert DEFAULT_ALMANAC.read_bytes() == SHARED_ALMANAC.read_bytes()
    assert b"Week 38 almanac for PRN-01" in DEFAULT_ALMANAC.read_bytes()


def test_to_toml_round_trip(tmp_path: Path) -> None:
    world = load_world(_write(tmp_path, "s.toml", FULL))
    text = world.to_toml()
    again = loads_world(text, base_dir="/")
    assert again == world
    changed = loads_world(text.replace("seed = 42", "seed = 43"), base_dir="/")
    assert changed != world


def test_include_merges_and_own_keys_win(tmp_path: Path) -> None:
    _write(
        tmp_path,
        "common.toml",
        'name = "base"\nseed = 5\n[origin]\nlat_deg = 10\nlon_deg = 20\n'
        "[atmosphere]\ntec_tecu = 30\nenv_noise_db = 20\n"
        '[[effects]]\nname = "bias"\neast_m = 1.0\n',
    )
    (tmp_path / "frag").mkdir()
    _write(
        tmp_path / "frag",
        "gm.toml",
        '[[effects]]\nname = "gauss_markov"\nsigma_m = 0.5\ntau_s = 30.0\n',
    )
    main = _write(
        tmp_path,
        "main.toml",
        'include = ["common.toml", "frag/gm.toml"]\nname = "main"\n'
        "[atmosphere]\ntec_tecu = 12\n"
        '[[effects]]\nname = "quantization"\ndecimals = 4\n',
    )
    world = load_world(main)
    assert world.name == "main" and world.seed == 5
    assert world.origin.lat_deg == 10.0
    assert world.atmosphere.tec_tecu == 12.0 and world.atmosphere.env_noise_db == 20.0
    assert [e["name"] for e in world.effects] == ["bias", "gauss_markov", "quantization"]


def test_circular_include_is_an_error(tmp_path: Path) -> None:
    _write(tmp_path, "a.toml", 'include = ["b.toml"]\nname = "a"\n')
    _write(tmp_path, "b.toml", 'include = ["a.toml"]\n')
    with pytest.raises(ConfigError, match="circular include"):
        load_world(tmp_path / "a.toml")
    with pytest.raises(ConfigError, match=r"missing\.toml"):
        loads_world('include = ["missing.toml"]\nname = "x"\n', base_dir=tmp_path)


def test_merge_fragment_appends_effects(tmp_path: Path) -> None:
    world = load_world(_write(tmp_path, "s.toml", FULL))
    frag_dir = tmp_path / "gap_out"
    frag_dir.mkdir()
    frag = _write(
        frag_dir,
        "effects.toml",
        '[[effects]]\nname = "quantization"\ndecimals = 4\n'
        '[[effects]]\nname = "latency"\ndelay_s = 0.5\n'
        "[compass]\nnoise_ut = 2.0\n",
    )
    merged = merge_fragment(world, frag)
    assert [e["name"] for e in merged.effects] == ["gauss_markov", "quantization", "latency"]
    assert merged.compass == {"declination_deg": 7.5, "noise_ut": 2.0}
    assert merged.walls == world.walls and merged.seed == world.seed
    assert world.effects[-1]["name"] == "gauss_markov"  # the original is unchanged
    assert len(merged.effect_objects()) == 3
    bad = _write(frag_dir, "bad.toml", '[[effects]]\nname = "bias"\nnorth = 3\n')
    with pytest.raises(ConfigError, match=r"effects\[1\]"):
        merge_fragment(world, bad)


def test_materials_load_and_the_scene_penetrates(tmp_path: Path) -> None:
    text = (
        'name = "room"\n[origin]\nlat_deg = 51.75\nlon_deg = -1.26\n'
        "[[buildings]]\nx0_m = -5\ny0_m = -5\nx1_m = 5\ny1_m = 5\nheight_m = 3\n"
        "penetration_db = 10.0\nrefractive_index = 2.1\n"
        "[roof]\nx0_m = -4.7\ny0_m = -4.7\nx1_m = 4.7\ny1_m = 4.7\nheight_m = 3\n"
        "penetration_db = 20.0\nthickness_m = 0.2\nrefractive_index = 2.5\n"
    )
    world = loads_world(text)
    assert all(w.penetration_db == 10.0 and w.refractive_index == 2.1 for w in world.walls)
    assert world.roofs[0].penetration_db == 20.0 and world.roofs[0].thickness_m == 0.2
    scene = world.walls_model()
    assert scene is not None and scene.penetrable
    res = scene.trace(np.array([0.0, 0.0, 1.0]), np.array([180.0, 0.0]), np.array([10.0, 80.0]))
    np.testing.assert_allclose(res.loss_db[0], [10.0, 20.0])
    # The resolved copy keeps the materials.
    again = loads_world(world.to_toml())
    assert again == world
    # Without materials a scene is opaque (the seed's model).
    plain = loads_world(text.replace("penetration_db = 10.0\n", "").replace(
        "penetration_db = 20.0\n", ""))  # fmt: skip
    assert not plain.walls_model().penetrable  # type: ignore[union-attr]


def test_shipped_building_window_has_realistic_materials() -> None:
    world = load_world(
        Path(__file__).resolve().parent.parent / "config/scenarios/building_window.toml"
    )
    assert {w.penetration_db for w in world.walls} == {10.0}  # brick
    assert world.roofs[0].penetration_db == 20.0  # concrete slab
