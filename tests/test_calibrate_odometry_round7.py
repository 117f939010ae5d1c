"""x6wd calibrate odometry, an outside audit's round-7 findings, on the simulated vehicle and
encoders (sim_backend.calibration_runs: true wheels 121.2 / 118.8 mm, effective track
0.370 m, 2 cm RTK reference fixes): a pivot merged into a straight pass, bowed "straight"
passes, an encoder counting backwards or the sides swapped."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest

from sim_backend.calibration_runs import (
    CIRCLE,
    ORIGIN,
    REF_SIGMA_M,
    STOP,
    STRAIGHT,
    TRUE,
    simulate,
    write,
)
from x6wd.app import cli
from x6wd.calibrate.odometry import OdometryCalibration, Track, calibrate
from x6wd.core.errors import ConfigError

PIVOT_S = 4.25  # a 180-degree pivot at 50/-50 % on the simulated vehicle
OUT_AND_BACK = [(50.0, 50.0, 10.0), STOP, (-50.0, -50.0, 10.0), STOP]


def fit(straight_script: list[tuple[float, float, float]], seed: int = 1) -> OdometryCalibration:
    return calibrate(
        Track.from_records(*simulate(straight_script, seed), ORIGIN),
        Track.from_records(*simulate(CIRCLE, 2), ORIGIN),
        counts_per_rev=TRUE.counts_per_rev,
        ref_sigma_m=REF_SIGMA_M,
    )


def assert_true_within(cal: OdometryCalibration, ses: float = 3.0) -> None:
    for key, truth in (
        ("left_diameter_m", TRUE.left_diameter_m),
        ("right_diameter_m", TRUE.right_diameter_m),
        ("track_m", TRUE.effective_track_m),
    ):
        e = getattr(cal, key)
        assert abs(e.value - truth) < ses * e.se, (key, e.value, e.se, truth)


# ----------------------------------------------------------------- 1: a pivot merged in


def test_passes_with_a_pivot_flowing_into_the_drive_are_refused_naming_them() -> None:
    # audit r6: a 180-degree pivot at 50/-50 % straight into the drive, no stop between:
    # diameters 10 SEs off in opposite directions, track 0.163 +- 0.018 m, exit 0
    script = [STOP] + [(50.0, -50.0, PIVOT_S), (50.0, 50.0, 10.0), STOP] * 6
    with pytest.raises(ConfigError) as err:
        fit(script)
    msg = str(err.value)
    assert "straight track: 0 usable passes" in msg
    assert "6 left out: pass 4." in msg and "a pivot merged into the drive" in msg
    assert "right " in msg and "between a pivot and the drive" in msg


def test_pivot_passes_among_good_ones_are_left_out_and_named_in_the_fragment(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    pivot_drive = [(50.0, -50.0, PIVOT_S), (50.0, 50.0, 10.0), STOP]
    straight = write(
        tmp_path / "s.jsonl", *simulate([STOP, *OUT_AND_BACK * 4, *pivot_drive * 3], 1)
    )
    circle = write(tmp_path / "c.jsonl", *simulate(CIRCLE, 2))
    argv = ["calibrate", "odometry", "--straight", str(straight), "--circle", str(circle)]
    assert cli.main(argv) == 0
    out, err = capsys.readouterr()
    assert "# straight: 8 passes of " in out and "(of 11 between stops)" in out
    assert out.count("# left out: pass ") == 3 and "a pivot merged into the drive" in out
    assert "straight track: 8 of 11 passes used" in err
    # stderr names them too, not as runs "shorter than --min-pass-m"
    assert err.count("x6wd calibrate: left out: pass ") == 3, err
    cal = fit([STOP, *OUT_AND_BACK * 4, *pivot_drive * 3])
    assert cal.straight.pivoted == 3
    assert_true_within(cal)


def test_passes_with_a_turn_merged_in_are_left_out_as_bending_sharply() -> None:
    # a turn at 50/0 % for 2 s flowing into the drive: no side counts back, but the path
    # kinks (25 deg), which a smooth fit of the path smooths over: left diameter 2.3 SEs low
    turn_drive = [(50.0, 0.0, 2.0), (50.0, 50.0, 10.0), STOP, (-50.0, 0.0, 2.0)]
    cal = fit([STOP, *OUT_AND_BACK * 3, *turn_drive, (-50.0, -50.0, 10.0), STOP])
    assert cal.straight.passes == 6 and cal.straight.turned == 2
    assert all("its reference path bends sharply (fixes 0.0" in w for w in cal.straight.left_out)
    assert "x the reference's 0.02 m)" in cal.straight.left_out[0]
    assert_true_within(cal)


# ----------------------------------------------------------------- 4: bowed "straight" passes


def test_bowed_straight_passes_give_the_true_wheels_and_track() -> None:
    # audit r2: 50/45 % bows 0.9 m over 17.7 m (23 deg between the ends): the chord taken as
    # the rolled length, and both sides as rolling it, gave left 0.12006 +- 0.00008 (14 SEs
    # low) and track 0.344 m (truth 0.370)
    cal = fit([STOP] + [(50.0, 45.0, 10.0), STOP, (-50.0, -45.0, 10.0), STOP] * 6)
    assert_true_within(cal)
    assert cal.straight.passes == 12 and 20 < cal.straight.turn_deg < 26
    assert "# the straight passes bow: up to 2" in cal.toml()


def test_straight_passes_turning_more_than_30_deg_are_refused_naming_them() -> None:
    # 50/40 %: 45 deg between the ends is no straight drive
    with pytest.raises(ConfigError) as err:
        fit([STOP] + [(50.0, 40.0, 10.0), STOP, (-50.0, -40.0, 10.0), STOP] * 2)
    msg = str(err.value)
    assert "0 usable passes" in msg and "4 left out: pass 4.0-" in msg
    assert "its reference path turned +4" in msg and "more than 30 deg" in msg


# ----------------------------------------------------------------- 6: encoder direction


@pytest.fixture(scope="module")
def documented_runs() -> tuple[Track, Track]:
    return (
        Track.from_records(*simulate(STRAIGHT, 1), ORIGIN),
        Track.from_records(*simulate(CIRCLE, 2), ORIGIN),
    )


def _calibrate(straight: Track, circle: Track) -> OdometryCalibration:
    return calibrate(straight, circle, counts_per_rev=TRUE.counts_per_rev)


@pytest.mark.parametrize("side", ["right", "left"])
def test_an_encoder_counting_backwards_is_named(
    documented_runs: tuple[Track, Track], side: str
) -> None:
    # audit r4: the right encoder reversed gave "odometry.left_diameter_m: must be >= 0.01,
    # got -0.1213", exit 2, naming the wrong wheel
    straight, circle = (
        dataclasses.replace(t, **{f"{side}_counts": -getattr(t, f"{side}_counts")})
        for t in documented_runs
    )
    with pytest.raises(ConfigError) as err:
        _calibrate(straight, circle)
    msg = str(err.value)
    assert msg.startswith(f"the {side} encoder counts backwards: on 12 of 12 straight passes")
    assert "opposite signs (pass 4.0-" in msg and "swap its A and B channel wires" in msg
    assert "circle gives a track of 0.37" in msg


def test_swapped_sides_are_named(documented_runs: tuple[Track, Track]) -> None:
    # audit r4: swapped sides gave "odometry.track_m: must be >= 0.05, got -0.373"
    straight, circle = (
        dataclasses.replace(t, left_counts=t.right_counts, right_counts=t.left_counts)
        for t in documented_runs
    )
    with pytest.raises(ConfigError) as err:
        _calibrate(straight, circle)
    msg = str(err.value)
    assert msg.startswith("left and right swapped: the circle gives a negative effective track")
    assert "(-0.37" in msg and "swap the two encoders' connections" in msg
    cal = _calibrate(*documented_runs)  # the same runs wired right
    assert_true_within(cal)


def test_a_compressed_run_is_named_as_compressed(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # round 21's audit: a .jsonl.gz was "no odometry: fewer than 2 odometry records"
    import gzip

    straight = write(tmp_path / "s.jsonl", *simulate(STRAIGHT, 1))
    packed = tmp_path / "s.jsonl.gz"
    packed.write_bytes(gzip.compress(straight.read_bytes()))
    circle = write(tmp_path / "c.jsonl", *simulate(CIRCLE, 2))
    argv = ["calibrate", "odometry", "--straight", str(packed), "--circle", str(circle)]
    assert cli.main(argv) == 2
    err = capsys.readouterr().err
    assert "s.jsonl.gz: compressed (gzip): decompress it first" in err, err
