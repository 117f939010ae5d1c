"""x6wd calibrate odometry on simulated runs with known truth: the simulated vehicle and its
encoders (sim_backend.odometry) drive a straight and a circular track; the reference fixes are
the true positions plus 2 cm of noise (an RTK receiver); the estimates must land within their
standard errors of the truth, and those standard errors must be honest over many seeds."""

from __future__ import annotations

import dataclasses
import math
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from sim_backend.calibration_runs import (
    CIRCLE,
    CIRCLE_TOUR,
    ORIGIN,
    REF_SIGMA_M,
    STOP,
    STRAIGHT,
    TRUE,
    simulate,
    write,
)
from tests.conftest import ROOT, option_help
from x6wd.app import cli
from x6wd.calibrate.odometry import (
    OdometryCalibration,
    Track,
    calibrate,
    find_passes,
    fit_circle,
    load_track,
)
from x6wd.core import config
from x6wd.core.errors import ConfigError
from x6wd.core.records import GpsFix


def run(seed: int) -> OdometryCalibration:
    s_odo, s_fix = simulate(STRAIGHT, seed)
    c_odo, c_fix = simulate(CIRCLE, seed + 10_000)
    return calibrate(
        Track.from_records(s_odo, s_fix, ORIGIN),
        Track.from_records(c_odo, c_fix, ORIGIN),
        counts_per_rev=TRUE.counts_per_rev,
        ref_sigma_m=REF_SIGMA_M,
    )


def z_scores(cal: OdometryCalibration) -> dict[str, float]:
    truth = {
        "left_diameter_m": TRUE.left_diameter_m,
        "right_diameter_m": TRUE.right_diameter_m,
        "track_m": TRUE.effective_track_m,
        "k_left_m": TRUE.k_left_m,
        "k_right_m": TRUE.k_right_m,
    }
    return {k: (getattr(cal, k).value - t) / getattr(cal, k).se for k, t in truth.items()}


def test_cli_writes_a_fragment_whose_estimates_hold_the_truth(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    straight = write(tmp_path / "straight.jsonl", *simulate(STRAIGHT, 1))
    circle = write(tmp_path / "circle.jsonl", *simulate(CIRCLE, 2))
    out = tmp_path / "odometry.toml"
    argv = ["calibrate", "odometry", "--straight", str(straight), "--circle", str(circle)]
    assert cli.main([*argv, "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert printed == out.read_text()
    assert "# straight: 12 passes" in printed and "circle: 4 passes" in printed
    got = config.loads(out.read_text()).odometry  # the daemon loads it as it is
    assert got.counts_per_rev == TRUE.counts_per_rev
    # within 3 standard errors (the SEs are in the fragment's comments)
    cal = run_from_files(straight, circle)
    for key, z in z_scores(cal).items():
        assert abs(z) < 3.0, (key, z, cal)
    assert got.left_diameter_m == pytest.approx(cal.left_diameter_m.value, abs=1e-6)
    # the systematic errors are resolved: each wheel's 1 % and the 1.5x track
    assert cal.left_diameter_m.se < 0.0003 and cal.right_diameter_m.se < 0.0003
    assert cal.left_diameter_m.value - cal.right_diameter_m.value > 10 * math.hypot(
        cal.left_diameter_m.se, cal.right_diameter_m.se
    )
    assert cal.track_m.se < 0.02 and abs(cal.track_m.value - 0.245) > 5 * cal.track_m.se


def run_from_files(straight: Path, circle: Path) -> OdometryCalibration:
    from x6wd.calibrate.odometry import load_track

    return calibrate(
        load_track(straight), load_track(circle), counts_per_rev=TRUE.counts_per_rev,
        ref_sigma_m=REF_SIGMA_M,
    )  # fmt: skip


def test_standard_errors_are_honest_over_seeds() -> None:
    """Over independent runs the errors divided by their standard errors have a mean square
    near 1 (chi-square with 8 degrees of freedom over 8: 99 % within 0.17..2.5)."""
    zs = [z_scores(run(seed)) for seed in range(100, 108)]
    for key in ("left_diameter_m", "right_diameter_m", "track_m"):
        msq = float(np.mean([z[key] ** 2 for z in zs]))
        assert 0.17 < msq < 2.5, (key, msq, [round(z[key], 2) for z in zs])
    for key in ("k_left_m", "k_right_m"):  # cruder: a variance from a dozen passes
        assert all(abs(z[key]) < 4.0 for z in zs), (key, [round(z[key], 2) for z in zs])


def test_cli_skips_and_counts_damaged_records_and_refuses_bad_flags(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # an outside check: a count of "abc" was a traceback, 859 torn lines went unmentioned,
    # --stop-s 0 was blamed on the recording
    straight = write(tmp_path / "straight.jsonl", *simulate(STRAIGHT, 1))
    circle = write(tmp_path / "circle.jsonl", *simulate(CIRCLE, 2))
    lines = straight.read_text().splitlines(keepends=True)
    odo_at = [i for i, ln in enumerate(lines) if '"type":"odometry"' in ln]
    lines[odo_at[5]] = re.sub(r'"left_counts":-?\d+', '"left_counts":"abc"', lines[odo_at[5]])
    lines[odo_at[9]] = lines[odo_at[9]][:30] + "\n"  # torn
    straight.write_text("".join(lines))
    argv = ["calibrate", "odometry", "--straight", str(straight), "--circle", str(circle)]
    assert cli.main(argv) == 0
    assert "2 unreadable lines or records of the straight recording skipped" in (
        capsys.readouterr().err
    )
    for flag, value in (("--stop-s", "0"), ("--min-pass-m", "nan"), ("--ref-sigma-m", "-1")):
        assert cli.main([*argv, flag, value]) == 2
        assert f"{flag} must be" in capsys.readouterr().err
    assert cli.main(["calibrate", "odometry", "--straight", str(tmp_path), "--circle", "x"]) == 2
    assert "a directory, not a recording" in capsys.readouterr().err


def test_no_fix_epochs_are_not_counted_as_unreadable(tmp_path: Path) -> None:
    # a fix record without a position is a receiver's no-fix epoch, which every real
    # recording has: dropped, not reported as damage
    odo, fixes = simulate(STRAIGHT, 1)
    no_fix = [GpsFix(f.t_s + 0.5, valid=False) for f in fixes[::10]]
    track = load_track(write(tmp_path / "s.jsonl", odo, [*fixes, *no_fix]))
    assert track.skipped == 0 and track.t_ref_s.size == len(fixes)


def test_a_fix_with_hdop_20_or_more_is_no_reference() -> None:
    # the robot takes such a fix for none (x6wd.nav.controller.MEANINGLESS_HDOP): a
    # receiver's 99.99 is a solution without geometry, km off in a street canyon
    odo, fixes = simulate(STRAIGHT, 1)
    wild = [dataclasses.replace(f, t_s=f.t_s + 0.5, lat_deg=f.lat_deg + 0.02, hdop=99.99)
            for f in fixes[::10]]  # fmt: skip
    track = Track.from_records(odo, [*fixes, *wild], ORIGIN)
    assert track.t_ref_s.size == len(fixes)


def test_passes_are_the_motion_between_stops() -> None:
    odo, fixes = simulate(STRAIGHT[:5], 3)
    passes, dropped = find_passes(Track.from_records(odo, fixes, ORIGIN))
    assert len(passes) == 2 and dropped == 0
    fwd, back = passes
    assert fwd.d_left_counts > 0 and back.d_left_counts < 0
    assert math.dist(fwd.start_m, back.end_m) < 0.05  # back where it started
    assert fwd.n_start >= 5 and fwd.n_end >= 2  # stationary fixes averaged


def test_fit_circle_recovers_a_noisy_circle() -> None:
    rng = np.random.default_rng(0)
    a = rng.uniform(0, 2 * math.pi, 200)
    xy = np.column_stack([3 + 4 * np.cos(a), -2 + 4 * np.sin(a)]) + rng.normal(0, 0.01, (200, 2))
    xc, yc, r = fit_circle(xy)
    assert (xc, yc, r) == pytest.approx((3, -2, 4), abs=0.005)


def test_too_few_passes_are_refused_with_the_reason() -> None:
    odo, fixes = simulate(STRAIGHT[:3], 4)  # one pass
    c_odo, c_fix = simulate(CIRCLE[:3], 5)
    with pytest.raises(ConfigError, match="straight track: 1 usable passes"):
        calibrate(
            Track.from_records(odo, fixes, ORIGIN),
            Track.from_records(c_odo, c_fix, ORIGIN),
            counts_per_rev=TRUE.counts_per_rev,
        )


def test_cli_reports_a_recording_without_reference(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    odo, _ = simulate(STRAIGHT[:3], 6)
    rec = write(tmp_path / "r.jsonl", odo, [])
    assert cli.main(["calibrate", "odometry", "--straight", str(rec), "--circle", str(rec)]) == 2
    assert "no reference" in capsys.readouterr().err


def test_a_circle_pass_with_a_gps_gap_of_more_than_a_quarter_lap_is_left_out(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # an outside check: 10 s without fixes (0.6 lap) inside a circle pass made np.unwrap
    # lose a whole lap; the track came out 0.426 m (truth 0.37) and the run stopped with
    # "k_left_m must be <= 0.1"
    def no_fixes(fixes: list[GpsFix], t0: float, t1: float) -> list[GpsFix]:
        return [f for f in fixes if not t0 <= f.t_s <= t1]

    s_odo, s_fix = simulate(STRAIGHT, 1)
    c_odo, c_fix = simulate(CIRCLE, 2)
    straight = write(tmp_path / "straight.jsonl", s_odo, s_fix)
    circle = write(tmp_path / "circle.jsonl", c_odo, no_fixes(c_fix, 50.0, 60.0))
    argv = ["calibrate", "odometry", "--straight", str(straight), "--circle", str(circle)]
    assert cli.main(argv) == 0
    err = capsys.readouterr().err
    assert "1 circle passes with reference fixes more than a quarter lap apart" in err
    cal = run_from_files(straight, circle)
    assert cal.gap_passes == 1 and cal.circle.passes == 3
    assert abs(cal.track_m.value - TRUE.effective_track_m) < 4 * cal.track_m.se
    # a gap of 0.85 lap aliases to a small backward step: the time between fixes tells
    circle = write(tmp_path / "c2.jsonl", c_odo, no_fixes(c_fix, 50.0, 63.6))
    assert run_from_files(straight, circle).gap_passes == 1
    # every pass with a gap: the error says why, not "no pass of half a lap" alone
    gappy = no_fixes(c_fix, 0.0, -1.0)
    for t0 in (14.0, 50.0, 86.0, 122.0):
        gappy = no_fixes(gappy, t0, t0 + 10.0)
    circle = write(tmp_path / "c3.jsonl", c_odo, gappy)
    with pytest.raises(ConfigError, match="4 passes left out: reference fixes more than a quar"):
        run_from_files(straight, circle)


def test_odometry_and_fixes_without_common_time_are_named_as_such() -> None:
    # an outside check: fixes 10000 s off the odometry's clock were reported as
    # "straight track: 0 usable passes", and why only after a successful run
    s_odo, s_fix = simulate(STRAIGHT, 1)
    c_odo, c_fix = simulate(CIRCLE, 2)
    late = [dataclasses.replace(f, t_s=f.t_s + 10_000.0) for f in c_fix]
    with pytest.raises(ConfigError, match=r"circle track: no reference fix during the odometry: "
                       r"odometry 0\.1 to 148\.0 s, fixes 10000\.2 to 10148\.0 s"):  # fmt: skip
        calibrate(
            Track.from_records(s_odo, s_fix, ORIGIN),
            Track.from_records(c_odo, late, ORIGIN),
            counts_per_rev=TRUE.counts_per_rev,
        )
    # fixes for part of the run only: the pass count says how many went and why
    early = [f for f in s_fix if f.t_s < 40.0]
    with pytest.raises(ConfigError, match=r"2 usable passes .* 10 passes left out: no reference"):
        calibrate(
            Track.from_records(s_odo, early, ORIGIN),
            Track.from_records(c_odo, c_fix, ORIGIN),
            counts_per_rev=TRUE.counts_per_rev,
        )


def test_a_nan_or_fractional_number_is_refused_naming_the_file_and_record(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # an outside check: a NaN count was a traceback ("cannot convert float NaN to integer"),
    # 1234.5 counts were truncated unmentioned, a NaN first fix named neither file nor record
    odo, fixes = simulate(STRAIGHT[:3], 7)
    good = write(tmp_path / "good.jsonl", odo, fixes)
    lines = good.read_text().splitlines(keepends=True)
    odo_at = [i for i, ln in enumerate(lines) if '"type":"odometry"' in ln]
    fix_at = [i for i, ln in enumerate(lines) if '"type":"fix"' in ln]
    for name, at, pattern, value, message in (
        ("nan_count", odo_at[40], r'"left_counts":-?\d+', '"left_counts":NaN',
         "odometry record 41 (t_mono 2.050 s): left_counts must be a whole number of counts, "
         "got nan"),
        ("half_count", odo_at[40], r'"right_counts":-?\d+', '"right_counts":1234.5',
         "odometry record 41 (t_mono 2.050 s): right_counts must be a whole number of counts, "
         "got 1234.5"),
        ("huge_count", odo_at[40], r'"left_counts":-?\d+', '"left_counts":' + "1" + "0" * 30,
         "odometry record 41 (t_mono 2.050 s): left_counts must be within +-1e+15 counts, "
         "got 1" + "0" * 30),  # an outside audit: an OverflowError traceback
        ("nan_first_fix", fix_at[0], r'"lat_deg":[-\d.e]+', '"lat_deg":NaN',
         "fix record 1 (t_mono 0.200 s): lat_deg must be finite, got nan"),
    ):  # fmt: skip
        bad = tmp_path / f"{name}.jsonl"
        edited = list(lines)
        edited[at] = re.sub(pattern, value, edited[at])
        assert edited[at] != lines[at]
        bad.write_text("".join(edited))
        argv = ["calibrate", "odometry", "--straight", str(bad), "--circle", str(good)]
        assert cli.main(argv) == 2, name
        assert f"{bad}: {message}" in capsys.readouterr().err, name


def test_runs_merged_by_a_short_stop_are_left_out_and_the_passes_used_are_said(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # an outside audit: with 3 s stops (under 1 s truly still after the motors' lag) a
    # forward and a return run merged into one "pass", silently left out or, forwards-back-
    # forwards, fitted with its net length; only the fragment's pass count showed it
    out_and_back = [(50.0, 50.0, 10.0), STOP, (-50.0, -50.0, 10.0), STOP]
    merged = [(50.0, 50.0, 10.0), (0.0, 0.0, 0.5), (-50.0, -50.0, 10.0), STOP]
    thrice = [(50.0, 50.0, 10.0), (0.0, 0.0, 0.5), (-50.0, -50.0, 10.0), (0.0, 0.0, 0.5),
              (50.0, 50.0, 10.0), STOP, (-50.0, -50.0, 10.0), STOP]  # fmt: skip
    script = [STOP, *out_and_back * 2, *merged, *thrice]
    straight = write(tmp_path / "straight.jsonl", *simulate(script, 8))
    circle = write(tmp_path / "circle.jsonl", *simulate(CIRCLE, 9))
    argv = ["calibrate", "odometry", "--straight", str(straight), "--circle", str(circle)]
    assert cli.main(argv) == 0
    out, err = capsys.readouterr()
    assert "straight track: 5 of 7 passes used; 2 counted backwards within the pass" in err
    assert "0 shorter than --min-pass-m 2 m" in err
    assert "# straight: 5 passes of " in out and " m (of 7 between stops); circle" in out


def test_the_calibration_runs_tool_needs_no_test_tools_and_writes_the_tested_runs(
    tmp_path: Path,
) -> None:
    """tools/calibration-runs (a README tour line) runs with the `sim` extra alone: no pytest
    (only `dev` has it), nothing imported from tests/ (an outside audit: it imported its
    simulator from this file, which imports pytest: a traceback). Its recordings are the
    runs this file checks the estimator on (seeds 1 and 2), record for record."""
    out = tmp_path / "calibration"
    wrapper = (
        "import runpy, sys\n"
        "sys.modules['pytest'] = sys.modules['_pytest'] = None  # as without the dev extra\n"
        f"sys.argv = ['tools/calibration-runs', {str(out)!r}]\n"
        "runpy.run_path('tools/calibration-runs', run_name='__main__')\n"
        f"tests = sorted(n for n, m in list(sys.modules.items()) if m is not None\n"
        f"    and str(getattr(m, '__file__', None) or '').startswith({str(ROOT / 'tests')!r}))\n"
        "sys.exit(f'imported from tests/: {tests}' if tests else 0)\n"
    )
    res = subprocess.run(
        [sys.executable, "-c", wrapper], cwd=ROOT, capture_output=True, text=True, timeout=120
    )
    assert res.returncode == 0, res.stderr
    assert "Traceback" not in res.stderr
    assert res.stdout.split() == [str(out / "straight.jsonl"), str(out / "circle.jsonl")]
    assert "truth: left diameter 121.2 mm, right 118.8 mm, effective track 0.37 m" in res.stderr

    def records(path: Path) -> list[str]:  # the wall-clock stamp t_utc is the writer's time
        return [re.sub(r'"t_utc":"[^"]*"', "", line) for line in path.read_text().splitlines()]

    for name, script, seed in (("straight", STRAIGHT, 1), ("circle", CIRCLE_TOUR, 2)):
        here = write(tmp_path / f"{name}.jsonl", *simulate(script, seed))
        assert records(out / f"{name}.jsonl") == records(here), name
    # the tour's next line calibrates them: enough passes for the command, not "rough"
    # (4 circle passes were, against its own advice of 6)
    res = subprocess.run(
        [sys.executable, "-m", "x6wd", "calibrate", "odometry", "--straight",
         str(out / "straight.jsonl"), "--circle", str(out / "circle.jsonl")],
        cwd=ROOT, capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert res.returncode == 0, res.stderr
    assert "rough" not in res.stderr + res.stdout, res.stderr
    track_m = float(re.search(r"track_m = ([0-9.]+)", res.stdout).group(1))  # type: ignore[union-attr]
    assert abs(track_m - 0.37) < 0.015, res.stdout


def test_help_gives_the_defaults_of_stop_and_pass_length(
    capsys: pytest.CaptureFixture[str],
) -> None:
    # an outside audit: docs/odometry.md gives 1 s and 2 m, --help gave neither
    argv = ["calibrate", "odometry"]
    assert option_help(argv, "--stop-s", capsys).endswith("at least this, s (default 1)")
    assert option_help(argv, "--min-pass-m", capsys).endswith("are ignored, m (default 2)")
    # an outside audit: the 0.02 m default claimed RTK for any fixes; now the fixes' quality's
    assert option_help(argv, "--ref-sigma-m", capsys).endswith(
        "(default: from the fixes' GGA quality: 0.02 for RTK fixed, 0.3 for RTK float; other "
        "fixes are left out, and a recording without RTK fixes refused)"
    )
