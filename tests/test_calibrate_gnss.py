"""x6wd calibrate gnss: RE, ASE (static) and the LCE map (drives) of seed 003.

Known truth, two ways:

- synthetic fix series built here with exactly the estimator's model (RE white, ASE a
  Gauss-Markov process, both scaled by a varying HDOP, 5 % of epochs missing): the estimates
  must land within their standard errors, and the SEs must match the scatter over seeds;
- the simulator (sim_backend, seed fidelity): its seed-003 form draws each axis WHITE with
  ``HDOP·sqrt(re_m² + ase_m² + LCE²)/√2``, so RE and ASE cannot be told apart by time scale
  there. Static: the simulator's white draw is RE (re_m/√2 per axis) and a ``gauss_markov``
  layer (sigma_m, tau_s; not scaled by HDOP) is the slow ASE: known ASE = sigma_m·sqrt(mean
  (1/HDOP²)) over the run's epochs. Drives: the scenario's LCE grid / √2 is the known LCE per
  cell, its re_m and ase_m (/√2) the subtracted RE and ASE.

And the real urban drive (tests/data/urban, taroz/MatRTKLIB, MIT): a map with sane values.
"""

from __future__ import annotations

import csv
import dataclasses
import io
import json
import math
import re
import subprocess
import sys
import tomllib
from datetime import UTC, datetime
from pathlib import Path

import numpy as np
import pytest

from sim_backend.geodesy import enu_to_lla
from sim_backend.receiver import build_receiver
from sim_backend.world import World, loads_world
from tests.conftest import option_help
from x6wd.app import cli
from x6wd.app.decode import decode_path
from x6wd.calibrate import gnss
from x6wd.calibrate.rtklib import parse_pos, read_pos
from x6wd.core import config
from x6wd.core.errors import ConfigError, ParseError
from x6wd.core.recorder import Recorder
from x6wd.core.records import GpsFix
from x6wd.nav.geo import LocalTangentPlane

ROOT = Path(__file__).resolve().parent.parent
URBAN = ROOT / "tests" / "data" / "urban"
STATIC = ROOT / "tests" / "data" / "static"
NMEA = ROOT / "tests" / "data" / "nmea"
# NGS mark KK1446 in WGS84(G730), tests/data/static/htdp.txt: 39 49 17.99968 N, 105 05 42.64410 W
KK1446 = (39 + 49 / 60 + 17.99968 / 3600, -(105 + 5 / 60 + 42.64410 / 3600))
ORIGIN = (51.7, 5.0)
SQRT2 = math.sqrt(2.0)

WORLD = """
name = "gnss calibration"
start_utc = "2020-01-01T12:00:00Z"
[origin]
lat_deg = 51.7
lon_deg = 5.0
alt_m = 10.0
[gnss]
fidelity = "seed"
seed_uere = "re_ase_lce"
rate_hz = 1.0
re_m = {re}
ase_m = {ase}
lce_cell_m = 10.0
lce_sigma_m = {grid}
{effects}
"""
# row i = north cell i, column j = east cell j (sim_backend.gnss.LceGrid), metres of range error
GRID = [
    [0.0, 1.0, 2.0, 3.0, 4.0, 5.0],
    [6.0, 0.0, 0.0, 0.0, 0.0, 2.0],
    [1.5, 0.0, 0.0, 0.0, 0.0, 8.0],
    [3.0, 2.5, 4.5, 1.0, 0.5, 0.0],
]
GM = '[[effects]]\nname = "gauss_markov"\nsigma_m = 1.2\ntau_s = 60.0'


def world(re: float, ase: float, effects: str = "", grid: list[list[float]] = GRID) -> World:
    return loads_world(WORLD.format(re=re, ase=ase, grid=grid, effects=effects))


def synthetic_static(
    seed: int, re_m: float = 0.5, ase_m: float = 1.5, tau_s: float = 60.0, n: int = 7200
) -> gnss.FixSeries:
    """Fixes at 1 Hz around ORIGIN: (white RE + Gauss-Markov ASE) per axis times HDOP."""
    rng = np.random.default_rng(seed)
    t = np.arange(n, dtype=float)
    hdop = 1.0 + 0.3 * np.sin(2 * np.pi * t / 3000.0) + 0.05 * rng.standard_normal(n)
    rho = math.exp(-1.0 / tau_s)
    drive = rng.standard_normal((n, 2)) * ase_m * math.sqrt(1 - rho * rho)
    drive[0] = rng.standard_normal(2) * ase_m
    slow = np.zeros((n, 2))
    slow[0] = drive[0]
    for i in range(1, n):
        slow[i] = rho * slow[i - 1] + drive[i]
    err = (slow + re_m * rng.standard_normal((n, 2))) * hdop[:, None]
    lat, lon = LocalTangentPlane(*ORIGIN).to_latlon(err[:, 0], err[:, 1])
    keep = rng.random(n) > 0.05
    return gnss.FixSeries(
        t[keep], np.full(int(keep.sum()), np.nan), np.asarray(lat)[keep],
        np.asarray(lon)[keep], hdop[keep], True,
    )  # fmt: skip


def loop_track(laps: int) -> tuple[np.ndarray, np.ndarray]:
    """1 Hz along a 50 x 30 m rectangle at 1 m/s (160 s a lap), off the cell borders."""

    def at(s: float) -> tuple[float, float, float]:
        s %= 160.0
        if s < 50:
            return 5.5 + s, 5.5, 0.0
        if s < 80:
            return 55.5, 5.5 + (s - 50), 0.0
        if s < 130:
            return 55.5 - (s - 80), 35.5, 0.0
        return 5.5, 35.5 - (s - 130), 0.0

    t = np.arange(160 * laps, dtype=float)
    return t, np.array([at(x) for x in t])


def sim_fixes(w: World, seed: int, t: np.ndarray, pos: np.ndarray) -> list[GpsFix]:
    b = build_receiver(w, seed).batch(t, pos, np.gradient(pos, axis=0))
    return [
        GpsFix(float(t[i]), lat_deg=float(b.lat_deg[i]), lon_deg=float(b.lon_deg[i]),
               hdop=float(b.hdop[i]), quality=1, valid=True, mode=3)
        for i in np.flatnonzero(b.valid)
    ]  # fmt: skip


def truth_series(w: World, t: np.ndarray, pos: np.ndarray) -> gnss.FixSeries:
    o = w.origin
    lat, lon, _ = enu_to_lla(pos, o.lat_deg, o.lon_deg, o.alt_m)
    n = t.shape[0]
    return gnss.FixSeries(
        t, np.full(n, np.nan), np.asarray(lat, float), np.asarray(lon, float), np.ones(n), True
    )


def write_recording(path: Path, fixes: list[GpsFix]) -> Path:
    with Recorder(path) as rec:
        for f in fixes:
            rec.record_fix(f)
    return path


def write_truth_csv(path: Path, ref: gnss.FixSeries) -> Path:
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["t_s", "lat", "lon", "alt", "heading_deg"])
        for t, la, lo in zip(ref.t_s, ref.lat_deg, ref.lon_deg, strict=True):
            w.writerow([f"{t:.3f}", f"{la:.9f}", f"{lo:.9f}", "10.0", "0.0"])
    return path


# ------------------------------------------------------------------------------ static


def test_static_recovers_re_and_ase_of_the_estimators_model_within_their_ses() -> None:
    r = gnss.static_noise(synthetic_static(1), *ORIGIN)
    assert abs(r.re_m.value - 0.5) < 3 * r.re_m.se and r.re_m.se < 0.02
    assert abs(r.ase_m.value - 1.5) < 3 * r.ase_m.se and r.ase_m.se < 0.15
    assert 30.0 < r.correlation_s < 120.0  # true 60 s; rough by design
    assert r.hdop_known and r.fixes > 6700


def test_static_standard_errors_are_honest_over_seeds() -> None:
    runs = [gnss.static_noise(synthetic_static(s), *ORIGIN) for s in range(24)]
    for key, truth in (("re_m", 0.5), ("ase_m", 1.5)):
        est = np.array([getattr(r, key).value for r in runs])
        se = np.array([getattr(r, key).se for r in runs])
        assert abs(est.mean() - truth) < 3 * est.std() / math.sqrt(len(runs)), key  # unbiased
        assert 0.6 < se.mean() / est.std() < 1.6, (key, se.mean(), est.std())


def test_static_white_error_is_all_re_and_a_constant_offset_is_ase() -> None:
    white = synthetic_static(3, re_m=1.0, ase_m=1e-6)
    r = gnss.static_noise(white, *ORIGIN)
    assert r.re_m.value == pytest.approx(1.0, abs=3 * r.re_m.se)
    assert r.ase_m.value < 0.2
    # the same white noise 2 m east of the reference: the offset is slow error (ASE)
    shifted = LocalTangentPlane(*ORIGIN)
    x, y = shifted.to_xy(white.lat_deg, white.lon_deg)
    lat, lon = shifted.to_latlon(np.asarray(x) + 2.0 * white.hdop, np.asarray(y))
    r2 = gnss.static_noise(
        gnss.FixSeries(white.t_s, white.t_gpst_s, np.asarray(lat), np.asarray(lon), white.hdop,
                       True),
        *ORIGIN,
    )  # fmt: skip
    assert r2.re_m.value == pytest.approx(r.re_m.value, abs=0.02)
    assert r2.ase_m.value == pytest.approx(math.sqrt(2.0), abs=0.1)  # 2 m on one axis of two
    assert r2.bias_east_m > 1.9


@pytest.mark.parametrize("seed", [0, 4])
def test_a_static_run_without_white_noise_still_writes_a_fragment_the_daemon_loads(
    seed: int,
) -> None:
    # A receiver that smooths its fixes has no white part: RE comes out as 0, which the
    # daemon refuses (re_m > 0). The fragment carries its one-SE upper bound and says so.
    r = gnss.static_noise(synthetic_static(seed, re_m=0.0, ase_m=1.5, n=3600), *ORIGIN)
    assert r.re_m.value == 0.0 and r.re_m.se > 0.0  # the resolution, not 0
    cal = gnss.GnssCalibration(r.re_m, r.ase_m, r.correlation_s, r, None)
    text = cal.toml()
    got = config.loads(text).gnss_noise
    # the bound that holds whatever the split: gamma(1) = RE² + ASE²(1 - rho) >= RE²
    assert got.re_m == pytest.approx(math.sqrt(r.gamma1_m2), abs=1e-4)
    assert "not resolved: RE = 0 ± " in text and "its upper bound sqrt(variogram lag 1)" in text
    assert got.ase_m == pytest.approx(1.5, rel=0.2)


def test_static_on_the_simulator_recovers_its_white_and_gauss_markov_parts() -> None:
    w = world(re=0.8, ase=0.0, effects=GM, grid=[[0.0]])
    n = 7200
    t, pos = np.arange(n, dtype=float), np.zeros((n, 3))
    fixes = sim_fixes(w, 5, t, pos)
    series = gnss.FixSeries.from_fixes(fixes)
    r = gnss.static_noise(series, w.origin.lat_deg, w.origin.lon_deg)
    known_re = 0.8 / SQRT2  # the seed form's white draw per axis at HDOP 1
    known_ase = 1.2 * math.sqrt(float(np.mean(1.0 / series.hdop**2)))  # GM not scaled by HDOP
    assert abs(r.re_m.value - known_re) < 3 * r.re_m.se, (r.re_m, known_re)
    assert abs(r.ase_m.value - known_ase) < 3 * r.ase_m.se, (r.ase_m, known_ase)
    assert 30.0 < r.correlation_s < 150.0  # the layer's tau_s = 60


def test_static_refuses_too_little_data() -> None:
    with pytest.raises(ConfigError, match="need at least 100"):
        gnss.static_noise(synthetic_static(1, n=80), *ORIGIN)
    every_10_s = synthetic_static(1, n=3000)
    sparse = gnss.FixSeries(
        every_10_s.t_s[::10], every_10_s.t_gpst_s[::10], every_10_s.lat_deg[::10],
        every_10_s.lon_deg[::10], every_10_s.hdop[::10], True,
    )  # fmt: skip
    with pytest.raises(ConfigError, match="pairs"):
        gnss.static_noise(sparse, *ORIGIN, epoch_s=1.0)


def test_static_refuses_a_moving_recording_or_a_reference_far_from_the_fixes(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # an outside audit: the zigzag mission's recording as --static wrote ase_m 78 m (exit 0),
    # and swapped --ref-lat/--ref-lon ended in "gnss_noise.re_m: must be <= 100.0"
    still = synthetic_static(1, n=600)
    plane = LocalTangentPlane(*ORIGIN)
    x, y = plane.to_xy(still.lat_deg, still.lon_deg)
    lat, lon = plane.to_latlon(np.asarray(x) + 0.5 * still.t_s, np.asarray(y))  # 0.5 m/s east
    moving = dataclasses.replace(still, lat_deg=np.asarray(lat), lon_deg=np.asarray(lon))
    with pytest.raises(ConfigError, match=r"the recording moves: its fixes lie a median \d+"):
        gnss.static_noise(moving, *ORIGIN)
    # a reference 60 m north of where the receiver stood; 30 m is still taken (as ASE)
    north_60 = plane.to_latlon(0.0, 60.0)
    with pytest.raises(ConfigError, match=r"is 6\d m from the reference .* beyond 50 m"):
        gnss.static_noise(still, *north_60)
    assert gnss.static_noise(still, *plane.to_latlon(0.0, 30.0)).bias_north_m < -29.0
    # swapped on the command line: refused before any fragment is written
    csv_path = write_truth_csv(tmp_path / "still.csv", still)
    argv = ["calibrate", "gnss", "--static", str(csv_path), "--ref-lat", "5.0", "--ref-lon",
            "51.7"]  # fmt: skip
    assert cli.main(argv) == 2
    out, err = capsys.readouterr()
    assert not out and f"static {csv_path}: the fixes' median position" in err
    assert "km from the reference (5.0, 51.7)" in err and "swapped" in err


# ------------------------------------------------------------------------------ LCE map


def test_lce_map_recovers_the_simulators_grid_within_its_ses() -> None:
    w = world(re=0.6, ase=0.9)
    t, pos = loop_track(laps=12)
    fixes = gnss.FixSeries.from_fixes(sim_fixes(w, 1, t, pos))
    lm = gnss.drives_lce_map(
        [(fixes, truth_series(w, t, pos))], re_m=0.6 / SQRT2, ase_m=0.9 / SQRT2, origin=ORIGIN
    )
    grid = np.array(GRID) / SQRT2
    mapped = lm.mapped()
    assert len(mapped) == 16 and all(c.visits in (12, 13) for c in mapped)  # start cell: 13
    z = []
    for c in mapped:
        truth = grid[c.north_index, c.east_index]
        assert abs(c.lce_m - truth) < 4 * c.se_m, (c, truth)
        if truth > 0:
            z.append((c.lce_m - truth) / c.se_m)
    assert 0.3 < float(np.mean(np.square(z))) < 2.5  # SEs of the right size
    # a cell of LCE 8/√2 = 5.66 m is told from one of 0
    big = next(c for c in mapped if (c.east_index, c.north_index) == (5, 2))
    assert big.lce_m > 4.5 and big.se_m < 0.5


def test_lce_cells_need_enough_fixes_and_visits() -> None:
    w = world(re=0.6, ase=0.9)
    t, pos = loop_track(laps=1)
    lm = gnss.drives_lce_map(
        [(gnss.FixSeries.from_fixes(sim_fixes(w, 2, t, pos)), truth_series(w, t, pos))],
        re_m=0.4, ase_m=0.6, origin=ORIGIN,
    )  # fmt: skip
    assert lm.cells and not lm.mapped()  # one lap: one visit per cell (the start cell two)
    others = [c for c in lm.cells if (c.east_index, c.north_index) != (0, 0)]
    assert all(c.visits == 1 and c.se_over == "fixes" for c in others)
    text = gnss.GnssCalibration(
        gnss.Estimate(0.4, 0.0), gnss.Estimate(0.6, 0.0), 120.0, None, lm
    ).toml()
    assert "lce_cells = [\n]" in text and "too little data" in text
    got = config.loads(text).gnss_noise
    assert got.lce_m_at(10.0, 5.0) == got.lce_default_m
    assert got.lce_default_m == pytest.approx(lm.default.value, abs=1e-3)


def test_cli_static_and_drive_write_a_fragment_the_daemon_loads(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    static_w = world(re=0.8, ase=0.0, effects=GM, grid=[[0.0]])
    n = 3600
    static = write_recording(
        tmp_path / "static.jsonl",
        sim_fixes(static_w, 3, np.arange(n, dtype=float), np.zeros((n, 3))),
    )
    w = world(re=0.8, ase=0.0)
    t, pos = loop_track(laps=6)
    drive = write_recording(tmp_path / "drive.jsonl", sim_fixes(w, 4, t, pos))
    truth = write_truth_csv(tmp_path / "truth.csv", truth_series(w, t, pos))
    out, png, table = tmp_path / "gnss.toml", tmp_path / "map.png", tmp_path / "map.csv"
    argv = [
        "calibrate", "gnss", "--static", str(static), "--ref-lat", "51.7", "--ref-lon", "5.0",
        "--drive", str(drive), "--reference", str(truth), "--origin", "51.7,5.0",
        "--min-fixes", "20", "--out", str(out), "--plot", str(png), "--map-csv", str(table),
    ]  # fmt: skip
    assert cli.main(argv) == 0
    printed = capsys.readouterr().out
    assert printed == out.read_text()
    got = config.loads(printed).gnss_noise  # the daemon loads it as it is
    # since round 7 re_m is the drive's white part when larger than the static RE (the
    # estimator runs on a moving robot); the seed form draws the LCE white too, so it holds
    # RE and the LCE's mean, and the map the excess over it
    standing = re.search(r"the static white part \(RE ([0-9.]+)", printed)
    assert standing and float(standing[1]) == pytest.approx(0.8 / SQRT2, abs=0.03)
    assert 1.5 < got.re_m < 4.0 and "re_m from the drives (moving)" in printed
    assert 0.8 < got.ase_m < 1.6 and got.correlation_s > 10
    assert (got.lce_origin_lat_deg, got.lce_origin_lon_deg, got.lce_cell_m) == (51.7, 5.0, 10.0)
    assert len(got.lce_cells) == 16
    # the lookup the estimator would take: cell (5, 2) is LCE 8/√2, (1, 0) 1/√2
    assert got.lce_m_at(55.5, 25.0) == pytest.approx(8 / SQRT2, rel=0.25)
    assert got.lce_m_at(15.0, 5.0) < 1.5
    assert got.lce_m_at(-500.0, 0.0) == got.lce_default_m
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    rows = list(csv.DictReader(table.open()))
    assert len(rows) >= 16 and {"lce_m", "se_m", "fixes", "visits", "enough"} <= set(rows[0])


def test_cli_says_why_no_cell_was_mapped_instead_of_a_nan_median(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # an outside audit: with no cell mapped the fragment said "median LCE nan m, 95 % nan m"
    w = world(re=0.8, ase=0.0)
    t, pos = loop_track(laps=1)
    drive = write_recording(tmp_path / "drive.jsonl", sim_fixes(w, 4, t, pos))
    truth = write_truth_csv(tmp_path / "truth.csv", truth_series(w, t, pos))
    argv = ["calibrate", "gnss", "--drive", str(drive), "--reference", str(truth),
            "--re-m", "0.5", "--ase-m", "0.5"]  # fmt: skip
    assert cli.main(argv) == 0
    out, err = capsys.readouterr()
    why = re.search(r"no cell mapped: (\d+) of (\d+) cells have fewer than 10 fixes, "
                    r"(\d+) fewer than 2 visits \(the most in a cell: \d+ fixes, \d+ visits\)",
                    out)  # fmt: skip
    assert why and int(why[3]) >= int(why[2]) - 1, out  # one lap: the start cell seen twice
    assert "nan" not in out and "only lce_default_m applies" in err
    config.loads(out)  # the daemon loads it: the pooled default stands for every cell


def test_cli_refuses_a_drive_without_its_reference(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    rec = write_recording(tmp_path / "d.jsonl", [GpsFix(1.0, lat_deg=51.7, lon_deg=5.0,
                                                        valid=True)])  # fmt: skip
    assert cli.main(["calibrate", "gnss", "--drive", str(rec)]) == 2
    assert "one reference per drive" in capsys.readouterr().err
    assert cli.main(["calibrate", "gnss", "--static", str(rec)]) == 2
    assert "--ref-lat" in capsys.readouterr().err


def test_cli_refuses_flags_out_of_range_before_any_work_and_a_short_csv_row(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # --re-m -1 was squared into the LCE map while the fragment said 0.0001; a short row of
    # a CSV reference was a TypeError traceback
    drive = ["calibrate", "gnss", "--drive", "no.pos", "--reference", "no.pos"]
    for flag, value in (("--re-m", "-1"), ("--ase-m", "nan"), ("--visit-gap-s", "-1"),
                        ("--min-fixes", "0"), ("--min-visits", "0"), ("--max-gap-s", "nan"),
                        ("--cell-m", "0")):  # fmt: skip
        assert cli.main([*drive, flag, value]) == 2
        assert f"{flag} must be" in capsys.readouterr().err
    ref = tmp_path / "ref.csv"
    ref.write_text("t_s,lat,lon\n0.0,51.75,-1.25\n1.0,51.75\n")
    argv = ["calibrate", "gnss", "--static", str(ref), "--ref-lat", "51.75", "--ref-lon", "-1.25"]
    assert cli.main(argv) == 2
    assert "not a number" in capsys.readouterr().err


def test_a_header_only_csv_and_a_nan_position_are_refused_naming_the_file(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # an outside audit: a header-only CSV was told it lacks the columns its header has; a
    # NaN in a CSV or a recording's fix said "origin_lat_deg must be finite" and no file
    header_only = tmp_path / "header.csv"
    header_only.write_text("t_s,lat,lon,alt,heading_deg\n")
    nan_csv = tmp_path / "nan.csv"
    nan_csv.write_text("t_s,lat,lon\n0.0,51.75,-1.25\n1.0,nan,-1.25\n")
    good = tmp_path / "good.csv"
    good.write_text("t_s,lat,lon\n0.0,51.75,-1.25\n1.0,51.75,-1.25\n")
    fixes = [GpsFix(float(t), lat_deg=51.75, lon_deg=-1.25, valid=True) for t in range(200)]
    nan_rec = write_recording(tmp_path / "nan.jsonl", fixes)
    text = nan_rec.read_text()  # the recorder writes NaN as null (no fix): a hand edit
    nan_rec.write_text(text.replace('"lon_deg":-1.25', '"lon_deg":NaN', 1))
    for path, message in (
        (header_only, f"{header_only}: no rows of data, only the header (t_s, lat, lon, alt"),
        (nan_csv, f"{nan_csv}:3: lat_deg must be finite and within ±90, got nan"),
        (nan_rec, f"{nan_rec}: the fix at t_s 0.000: lon_deg must be finite"),
    ):
        static = ["--static", str(path), "--ref-lat", "51.75", "--ref-lon", "-1.25"]
        for args in (static, ["--drive", str(good), "--reference", str(path)]):
            assert cli.main(["calibrate", "gnss", *args]) == 2, args
            err = capsys.readouterr().err
            assert message in err, (args, err)


# ------------------------------------------------------------------------------ config


def test_gnss_noise_section_is_range_checked() -> None:
    origin = "lce_origin_lat_deg = 51.7\nlce_origin_lon_deg = 5.0\n"
    ok = config.loads(f"[gnss_noise]\nre_m = 0.4\n{origin}lce_cells = [[0, -1, 2.5], [3, 4, 0]]\n")
    assert ok.gnss_noise.lce_m_at(5.0, -5.0) == 2.5
    assert ok.gnss_noise.lce_m_at(35.0, 45.0) == 0.0
    assert config.Config().gnss_noise.re_m == 1.0  # the estimator's default
    for bad, why in (
        ("re_m = 0", "must be > 0"),
        ("ase_m = -1", ">= 0"),
        ("lce_cell_m = 0", ">= 0.1"),
        (f"{origin}lce_cells = [[0, 0]]", "expected \\[east index"),
        (f"{origin}lce_cells = [[0.5, 0, 1]]", "integers"),
        (f"{origin}lce_cells = [[0, 0, -1]]", "0..1000"),
        (f"{origin}lce_cells = [[0, 0, 1], [0, 0, 2]]", "twice"),
        # a hand-written map without its origin sat at 0 N 0 E and was never looked up
        ("lce_cells = [[0, 0, 1]]", r"^gnss_noise\.lce_origin_lat_deg: required with lce_cells"),
        (
            "lce_origin_lat_deg = 51.7\nlce_cells = [[0, 0, 1]]",
            r"^gnss_noise\.lce_origin_lon_deg: required",
        ),
        ("correlation_s = -5", ">= 0"),
        ("lce_origin_lat_deg = 91", "<= 85"),
    ):
        with pytest.raises(ConfigError, match=why):
            config.loads(f"[gnss_noise]\n{bad}\n")


def test_the_commented_example_in_the_robot_config_loads() -> None:
    text = (ROOT / "config" / "x6wd.toml").read_text()
    block = text[text.index("[gnss_noise]") :].split("\n\n")[0]
    example = [
        line.removeprefix("# ").split("  #")[0]
        for line in block.splitlines()
        if line.startswith(("# lce_", "#   [", "# ]"))
    ]
    assert len(example) == 9
    got = config.loads("[gnss_noise]\n" + "\n".join(example)).gnss_noise
    assert got.lce_m_at(15.0, 15.0) == 6.8 and got.lce_m_at(-1.0, 0.0) == got.lce_default_m


# ------------------------------------------------------------------------------ real data


def test_rtklib_reader_reads_the_urban_files_and_refuses_other_formats() -> None:
    rover, ref = read_pos(URBAN / "rover_1Hz_spp.pos"), read_pos(URBAN / "reference_1Hz.pos")
    assert (len(rover), len(ref)) == (550, 1231)
    assert set(rover.quality.tolist()) == {5} and set(ref.quality.tolist()) == {1}
    assert rover.sdn_m[0] == pytest.approx(3.4239) and rover.n_sats[0] == 20
    assert ref.t_gpst_s[-1] - ref.t_gpst_s[0] == pytest.approx(1230.0)
    with pytest.raises(ParseError, match=r"x\.pos:2: not an RTKLIB"):
        parse_pos("% header\n2023/07/11 06:04:30.000 1 2\n", "x.pos")
    with pytest.raises(ParseError, match="no solution lines"):
        parse_pos("% only a header\n")
    # a solution written in UTC would be 18 s off against GPST stamps: named, not read
    utc = (URBAN / "reference_1Hz.pos").read_text().replace("%  GPST ", "%  UTC  ", 1)
    with pytest.raises(ParseError, match=r"^u\.pos:\d+: times in UTC; this reader takes GPST"):
        parse_pos(utc, "u.pos")


def test_urban_drive_gives_a_sane_lce_map(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """One real drive (550 single-point fixes against RTK): README figures median 2.9 m,
    95 % 27 m horizontal. RE and ASE of that receiver are unknown, so they are set
    negligible (0.1 m) and the LCE holds the whole error; one pass, so min_visits 1."""
    out, png = tmp_path / "urban.toml", tmp_path / "urban.png"
    argv = [
        "calibrate", "gnss", "--drive", str(URBAN / "rover_1Hz_spp.pos"),
        "--reference", str(URBAN / "reference_1Hz.pos"), "--re-m", "0.1", "--ase-m", "0.1",
        "--cell-m", "50", "--min-fixes", "5", "--min-visits", "1",
        "--out", str(out), "--plot", str(png),
    ]  # fmt: skip
    assert cli.main(argv) == 0
    capsys.readouterr()
    got = config.loads(out.read_text()).gnss_noise
    assert 10 <= len(got.lce_cells) <= 40
    lce = np.array([c[2] for c in got.lce_cells])
    assert 1.5 < float(np.median(lce)) < 4.5  # per axis; 2.9 m horizontal median ~ 2.5 m
    assert 8.0 < float(np.percentile(lce, 95)) < 40.0
    assert 5.0 < got.lce_default_m < 15.0  # all fixes pooled: RMS, pulled up by the tail
    assert "550 fixes matched (0 without reference)" in out.read_text()
    assert png.stat().st_size > 10_000
    header = tomllib.loads(out.read_text())["gnss_noise"]
    assert header["lce_cell_m"] == 50.0


def test_an_x6wd_recording_matches_a_pos_reference_through_its_utc_stamp() -> None:
    """A recording's fixes carry a monotonic t_s and the receiver's UTC; a .pos file GPST:
    UTC + 18 s puts them on one clock."""
    rover, ref = (gnss.load_fixes(URBAN / f) for f in ("rover_1Hz_spp.pos", "reference_1Hz.pos"))
    fixes = [
        GpsFix(
            1000.0 + i,  # the daemon's monotonic clock: unrelated to GPST
            utc=datetime.fromtimestamp(t - gnss.GPS_UTC_LEAP_S, UTC),
            lat_deg=float(la), lon_deg=float(lo), valid=True,
        )
        for i, (t, la, lo) in enumerate(
            zip(rover.t_gpst_s, rover.lat_deg, rover.lon_deg, strict=True)
        )
    ]  # fmt: skip
    fixes.append(GpsFix(5000.0, lat_deg=35.0, lon_deg=136.0, valid=True))  # no UTC: unmatched
    plane = LocalTangentPlane(35.1654, 136.8814)
    got, missed = gnss.match_reference(gnss.FixSeries.from_fixes(fixes), ref, plane)
    want, _ = gnss.match_reference(rover, ref, plane)
    assert (len(got), missed) == (550, 1)
    assert np.allclose(got.err_east_m, want.err_east_m, atol=1e-6)
    assert np.allclose(got.err_north_m, want.err_north_m, atol=1e-6)


def test_plot_without_its_extra_stops_before_any_work(tmp_path: Path) -> None:
    # it made the map, wrote the fragment, then stopped at the plot (an outside check)
    script = "import sys\nsys.modules['matplotlib'] = None\nfrom x6wd.app.cli import main\n"
    script += "sys.exit(main(sys.argv[1:]))\n"
    urban = ROOT / "tests" / "data" / "urban"
    out = tmp_path / "g.toml"
    r = subprocess.run(
        [sys.executable, "-c", script, "calibrate", "gnss", "--drive",
         str(urban / "rover_1Hz_spp.pos"), "--reference", str(urban / "reference_1Hz.pos"),
         "--re-m", "0.1", "--ase-m", "0.1", "--out", str(out), "--plot", str(tmp_path / "m.png")],
        capture_output=True, text=True, timeout=120, cwd=ROOT,
    )  # fmt: skip
    assert r.returncode == 2 and "x6wd[plot]" in r.stderr and "Traceback" not in r.stderr
    assert not out.exists() and r.stdout == ""


def test_static_reads_a_receivers_csv_layout_and_says_what_it_left_out(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The real ZED-F9P on NGS mark KK1446 (tests/data/static): its CSV (TIME, LATITUDE,
    LONGITUDE, spaces after the commas) is read as it is; 341 of 1406 rows repeat the time
    stamp of the row before (the logger read a stale TIME, the next row jumps 2 s): they are
    left out and counted. An outside check found the layout refused ("needs the columns t_s,
    lat, lon"), the rows dropped without a word and RE written as 0.0001 ± 0.0000."""
    out = tmp_path / "f9p.toml"
    argv = ["calibrate", "gnss", "--static", str(STATIC / "mobile.csv"), "--ref-lat",
            str(KK1446[0]), "--ref-lon", str(KK1446[1]), "--out", str(out)]  # fmt: skip
    assert cli.main(argv) == 0
    err = capsys.readouterr().err
    assert "341 static fixes sharing an epoch with the fix before" in err
    text = out.read_text()
    assert "1065 fixes over 1404 s" in text and "341 fixes sharing an epoch" in text
    r = gnss.static_noise(gnss.load_fixes(STATIC / "mobile.csv"), *KK1446)
    # the receiver smooths: epoch-to-epoch steps of millimetres, the variogram's nugget
    # below 0. RE is not resolved; sqrt(gamma(1)) = 3.1 mm bounds it, not 0.1 mm
    assert r.re_m.value == 0.0 and 0.0003 < r.re_m.se < 0.003
    assert math.sqrt(r.gamma1_m2) == pytest.approx(0.0031, abs=0.0001)
    got = config.loads(text).gnss_noise
    assert got.re_m == 0.0031 and "re_m = 0.0031  # not resolved: RE = 0 ± 0.0010" in text
    assert got.ase_m == pytest.approx(0.81, abs=0.01)  # incl. the ~1 m datum offset (README)
    # the header written with spaces after the commas, t_s, lat, lon
    spaced = tmp_path / "spaced.csv"
    spaced.write_text("t_s, lat, lon, hdop\n" + "".join(
        f"{i}.0, {KK1446[0]:.9f}, {KK1446[1] + 1e-6 * (i % 7):.9f}, 1.2\n" for i in range(200)
    ))  # fmt: skip
    series = gnss.load_fixes(spaced)
    assert len(series) == 200 and series.hdop_known and series.hdop[0] == 1.2


def test_static_reads_plain_nmea_logs_as_x6wd_decode_does(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """gpsd's logs (tests/data/nmea, BSD-2-Clause) were refused with "no valid fix with a
    position" although x6wd decode reads them; now the same decoder gives the same fixes,
    timed by their UTC."""
    for name, n in (("ublox-zed-f9p_hpg1.11.log", 655), ("ublox-lea-5h.log", 20)):
        series = gnss.load_fixes(NMEA / name)
        buf = io.StringIO()
        decode_path(str(NMEA / name), buf, with_sky=False)
        tpv = [o for o in map(json.loads, buf.getvalue().splitlines()) if "lat" in o]
        assert len(series) == len(tpv) == n
        assert np.allclose(series.lat_deg, [o["lat"] for o in tpv], atol=1e-9)
        first = datetime.fromisoformat(tpv[0]["time"].replace("Z", "+00:00"))
        assert series.t_s[0] == pytest.approx(first.timestamp())
    # 655 s of a static ZED-F9P (no surveyed position: its mean stands in)
    zed = gnss.load_fixes(NMEA / "ublox-zed-f9p_hpg1.11.log")
    lat, lon = float(zed.lat_deg.mean()), float(zed.lon_deg.mean())
    argv = ["calibrate", "gnss", "--static", str(NMEA / "ublox-zed-f9p_hpg1.11.log"),
            "--ref-lat", str(lat), "--ref-lon", str(lon)]  # fmt: skip
    assert cli.main(argv) == 0
    assert "655 fixes over 654 s" in capsys.readouterr().out
    # 18 s of a LEA-5H: read, then refused for what it is, too short
    argv[3] = str(NMEA / "ublox-lea-5h.log")
    assert cli.main(argv) == 2
    assert "20 fixes; need at least 100" in capsys.readouterr().err
    noise = tmp_path / "noise.log"
    noise.write_bytes(b"not nmea at all\n$GPTXT,01,01,02,hello*00\n")
    with pytest.raises(ParseError, match="no NMEA fix with a date and time"):
        gnss.load_fixes(noise)


def test_help_gives_the_default_of_every_lce_map_option(
    capsys: pytest.CaptureFixture[str],
) -> None:
    # an outside audit: --visit-gap-s and --max-gap-s showed no default (docs: 30 s, 1.5 s)
    argv = ["calibrate", "gnss"]
    for option, shown in (
        ("--visit-gap-s", "a new pass after this long away, s (30)"),
        ("--max-gap-s", "longest reference gap to interpolate, s (1.5)"),
        ("--cell-m", "LCE map cell size, m (10)"),
        ("--min-fixes", "fixes a mapped cell needs (10)"),
        ("--min-visits", "separate passes a mapped cell needs (2)"),
    ):
        assert option_help(argv, option, capsys).endswith(shown), option


def test_a_large_white_part_does_not_swamp_the_correlation_time() -> None:
    # An outside audit (round 22): with 1.5 m of white noise added to a standing log, tau
    # came out as 86400 s ("the record is too short"); from lags 1 and 2 alone the slow
    # part's rise is the small difference gamma(1) - RE², which the white part swamps (8 of
    # these 12 seeds gave no decay, the rest 19-48 s). Fitted over lags up to a quarter of the
    # record (when RE² is most of gamma(1)), it is read as without the white part (true 100 s).
    for re_m in (0.0, 1.5):
        taus = [
            gnss.static_noise(
                synthetic_static(s, re_m=re_m, ase_m=1.5, tau_s=100.0, n=1800), *ORIGIN
            ).correlation_s
            for s in range(12)
        ]
        assert all(math.isfinite(t) for t in taus), (re_m, taus)
        assert 60.0 < float(np.median(taus)) < 160.0, (re_m, taus)
        assert sum(40.0 < t < 250.0 for t in taus) >= 10, (re_m, taus)
