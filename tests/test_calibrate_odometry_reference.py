"""x6wd calibrate odometry looks at what its reference is: the fix records' GGA quality.

An outside audit ran it on a HIL session's recordings (the daemon against the simulated
NEO-5, so ordinary quality-1 GPS fixes, metres off): it printed "reference sigma 0.02 m per
fix" and diameters 4 % high with exit 0. RTK fixed (4) is the reference, float (5) a coarser
one, anything else is refused unless --ref-sigma-m says what the fixes are worth."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import pytest

from sim_backend.calibration_runs import CIRCLE, ORIGIN, STRAIGHT, TRUE, simulate, write
from sim_backend.mission import run_mission
from sim_backend.world import load_world
from tests.conftest import ROOT
from x6wd.app import cli
from x6wd.calibrate.odometry import RTK_SIGMA_M, calibrate, load_track
from x6wd.core.records import GpsFix
from x6wd.nav.geo import LocalTangentPlane


def with_quality(fixes: list[GpsFix], quality: int) -> list[GpsFix]:
    return [dataclasses.replace(f, quality=quality) for f in fixes]


@pytest.fixture(scope="module")
def runs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, tuple[list, list[GpsFix]]]:
    """tools/calibration-runs' two runs (seeds 1 and 2): the truth as RTK fixed fixes."""
    return {"straight": simulate(STRAIGHT, 1), "circle": simulate(CIRCLE, 2)}


def test_gps_fixes_of_the_simulated_neo5_are_refused_naming_quality_and_count(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A recording of `x6wd sim` (the NEO-5 model: quality-1 fixes, odometry at the compass
    rate), as a HIL or a real run with a plain receiver records it, is no reference."""
    run_mission(
        load_world(ROOT / "config" / "scenarios" / "default.toml"), tmp_path, duration_s=30.0
    )
    rec = tmp_path / "recording.jsonl"
    fixes = [json.loads(x)["data"] for x in rec.read_text().splitlines() if '"type":"fix"' in x]
    valid = [f for f in fixes if f["valid"] and f["lat_deg"] is not None]
    assert valid and {f["quality"] for f in valid} == {1}
    argv = ["calibrate", "odometry", "--straight", str(rec), "--circle", str(rec)]
    assert cli.main(argv) == 2
    out, err = capsys.readouterr()
    assert not out
    n = len(valid)
    assert (
        f"the reference is not RTK (straight: {n} fixes of quality 1 (GPS); circle: {n} fixes "
        "of quality 1 (GPS); no fix of quality 4 (RTK fixed) or 5 (RTK float))"
    ) in err
    assert "give --ref-sigma-m SIGMA to take these fixes" in err
    # told what the fixes are worth, it goes on to the passes (a mission has no stops)
    assert cli.main([*argv, "--ref-sigma-m", "3"]) == 2
    err = capsys.readouterr().err
    assert "not RTK" not in err and "straight track: 0 usable passes" in err


def test_given_a_sigma_gps_fixes_are_used_and_the_fragment_says_it_is_no_calibration(
    tmp_path: Path, runs: dict, capsys: pytest.CaptureFixture[str]
) -> None:
    s_odo, s_fix = runs["straight"]
    c_odo, c_fix = runs["circle"]
    straight = write(tmp_path / "s.jsonl", s_odo, with_quality(s_fix, 1))
    circle = write(tmp_path / "c.jsonl", c_odo, with_quality(c_fix, 1))
    argv = ["calibrate", "odometry", "--straight", str(straight), "--circle", str(circle)]
    assert cli.main(argv) == 2
    assert f"straight: {len(s_fix)} fixes of quality 1 (GPS)" in capsys.readouterr().err
    assert cli.main([*argv, "--ref-sigma-m", "2.5"]) == 0
    out, err = capsys.readouterr()
    n = len(s_fix) + len(c_fix)
    assert f"# reference sigma 2.5 m per fix as given with --ref-sigma-m ({n} fixes of " in out
    warning = f"NOT A CALIBRATION: the reference is not RTK ({n} fixes of quality 1 (GPS))"
    assert f"# {warning}" in out and f"x6wd calibrate: {warning}" in err


def test_the_truth_as_rtk_fixed_fixes_keeps_two_centimetres(
    tmp_path: Path, runs: dict, capsys: pytest.CaptureFixture[str]
) -> None:
    """The documented flow: tools/calibration-runs writes the truth as quality 4."""
    straight = write(tmp_path / "s.jsonl", *runs["straight"])
    circle = write(tmp_path / "c.jsonl", *runs["circle"])
    argv = ["calibrate", "odometry", "--straight", str(straight), "--circle", str(circle)]
    assert cli.main(argv) == 0
    out, err = capsys.readouterr()
    n = len(runs["straight"][1]) + len(runs["circle"][1])
    assert f"# reference sigma 0.02 m per fix ({n} fixes of quality 4 (RTK fixed))\n" in out
    assert "RTK" not in err and "NOT A CALIBRATION" not in out


def test_rtk_float_fixes_are_a_coarser_reference_and_said_so(
    tmp_path: Path, runs: dict, capsys: pytest.CaptureFixture[str]
) -> None:
    s_odo, s_fix = runs["straight"]
    c_fix = runs["circle"][1]
    straight = write(tmp_path / "s.jsonl", s_odo, with_quality(s_fix, 5))
    circle = write(tmp_path / "c.jsonl", *runs["circle"])
    argv = ["calibrate", "odometry", "--straight", str(straight), "--circle", str(circle)]
    assert cli.main(argv) == 0
    out, err = capsys.readouterr()
    assert RTK_SIGMA_M[5] == 0.3
    assert (
        f"# reference sigma 0.3 m per fix ({len(c_fix)} fixes of quality 4 (RTK fixed), "
        f"{len(s_fix)} of quality 5 (RTK float))"
    ) in out
    assert f"{len(s_fix)} reference fixes are RTK float (quality 5): sigma 0.3 m per fix" in err


def test_a_few_float_fixes_among_fixed_ones_are_left_out_not_the_sigma_of_all(
    tmp_path: Path, runs: dict, capsys: pytest.CaptureFixture[str]
) -> None:
    # an outside review: one float fix among 1600 fixed set 0.3 m for every fix
    s_odo, s_fix = runs["straight"]
    mixed = [dataclasses.replace(f, quality=5) if i % 50 == 7 else f for i, f in enumerate(s_fix)]
    straight = write(tmp_path / "s.jsonl", s_odo, mixed)
    circle = write(tmp_path / "c.jsonl", *runs["circle"])
    argv = ["calibrate", "odometry", "--straight", str(straight), "--circle", str(circle)]
    assert cli.main(argv) == 0
    out, err = capsys.readouterr()
    n_float = sum(f.quality == 5 for f in mixed)
    assert "# reference sigma 0.02 m per fix (" in out, out
    assert f"{n_float} fixes of quality 5 (RTK float) left out of the reference" in err, err


def test_fixes_that_are_not_rtk_in_an_rtk_run_are_left_out_and_counted(
    tmp_path: Path, runs: dict, capsys: pytest.CaptureFixture[str]
) -> None:
    """A receiver that drops from RTK to GPS (quality 1, metres off) for a while: those fixes
    are not the reference. Every 3rd straight fix is a GPS fix 3 m off to the east; the
    estimates are those of the run without them, to the last digit."""
    s_odo, s_fix = runs["straight"]
    c_odo, c_fix = runs["circle"]
    plane = LocalTangentPlane(*ORIGIN)

    def gps(f: GpsFix) -> GpsFix:
        assert f.lat_deg is not None and f.lon_deg is not None
        e, n = plane.to_xy(f.lat_deg, f.lon_deg)
        lat, lon = plane.to_latlon(float(e) + 3.0, float(n))
        return dataclasses.replace(f, lat_deg=float(lat), lon_deg=float(lon), quality=1)

    mixed = [gps(f) if i % 3 == 1 else f for i, f in enumerate(s_fix)]
    rtk_only = [f for i, f in enumerate(s_fix) if i % 3 != 1]
    straight = write(tmp_path / "s.jsonl", s_odo, mixed)
    circle = write(tmp_path / "c.jsonl", c_odo, c_fix)
    argv = ["calibrate", "odometry", "--straight", str(straight), "--circle", str(circle)]
    assert cli.main(argv) == 0
    out, err = capsys.readouterr()
    n_gps = len(s_fix) - len(rtk_only)
    note = f"straight recording: {n_gps} fixes of quality 1 (GPS) left out of the reference"
    assert f"x6wd calibrate: {note}" in err and f"# {note}" in out
    # the same origin: the first fix of the mixed run is RTK (i = 0)
    got = calibrate(load_track(straight), load_track(circle), counts_per_rev=TRUE.counts_per_rev)
    want = calibrate(
        load_track(write(tmp_path / "rtk.jsonl", s_odo, rtk_only)),
        load_track(circle),
        counts_per_rev=TRUE.counts_per_rev,
    )
    for key in ("left_diameter_m", "right_diameter_m", "track_m"):
        assert getattr(got, key) == getattr(want, key), key
    assert got.reference.used == {4: len(rtk_only) + len(c_fix)}
