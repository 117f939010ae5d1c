"""The truths the GPS half scores logs against (round 13, outside audit of the --sim truth.csv
of round 12): a --sim log's own truth.csv was never checked (another run's truth, shared
truths and a copy of the real truth all passed silently), an unreadable one was named nowhere
in the exit-2 message, a far one blamed --truth-track, a short one read as a short log, the
real log as its own --truth-track gave all-zero errors and a verdict, and a moving log scored
against a point --truth or a static truth track was accepted (its route counted as error)."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from sim_backend.effects import metres_per_degree
from tests.test_gap_sim_truth_round12 import (
    DURATION_S,
    ORIGIN,
    PRE,
    SIM_ROUTES,
    Scored,
    circle_enu,
    make_case,
    make_run,
    real_truth_argv,
    write_csv,
)
from x6wd.app.cli import main as x6wd_main
from x6wd.gap import cli as gap_cli
from x6wd.gap.surrogate import surrogate_run

POINT = "51.752,-1.2577,60"


@pytest.fixture
def stop_at_diagnosis(monkeypatch: pytest.MonkeyPatch) -> None:
    """The CLI raises Scored where it would diagnose: a refusal must come before."""

    def stop(*args: object, **kwargs: object) -> None:
        raise Scored

    monkeypatch.setattr(gap_cli, "diagnose", stop)


def run_gap(argv: list[str]) -> int | str:
    """x6wd's exit code, or "scored" when it reached the diagnosis."""
    try:
        return x6wd_main(argv)
    except Scored:
        return "scored"


@pytest.mark.usefixtures("stop_at_diagnosis")
def test_a_sim_log_with_another_runs_truth_stops_naming_it(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # before: sim0 scored against sim1's route (metres of "GNSS error"), no word
    argv = make_case(tmp_path, sim_truth=True)
    t_s = np.arange(0.0, 600.0)
    write_csv(tmp_path / "sim0" / "truth.csv", t_s, *circle_enu(t_s, 1.62, 30.0))  # another run's
    assert run_gap([*argv, "--out", str(tmp_path / "r")]) == 2
    err = capsys.readouterr().err
    assert "sim0/gps.csv: its fixes lie a median" in err
    assert str(tmp_path / "sim0" / "truth.csv") in err and "not its run's true path" in err
    assert str(tmp_path / "sim2" / "gps.csv") not in err


@pytest.mark.usefixtures("stop_at_diagnosis")
def test_sim_logs_sharing_one_moving_truth_stop(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    argv = make_case(tmp_path, sim_truth=True)
    # copies: the same bytes beside two logs
    shutil.copy(tmp_path / "sim1" / "truth.csv", tmp_path / "sim2" / "truth.csv")
    assert run_gap([*argv, "--out", str(tmp_path / "r")]) == 2
    err = capsys.readouterr().err
    assert "share" in err and "identical copies" in err
    assert str(tmp_path / "sim1" / "gps.csv") in err and str(tmp_path / "sim2" / "gps.csv") in err
    # one file: two logs in one folder
    shutil.copy(tmp_path / "sim1" / "gps.csv", tmp_path / "sim0" / "again.csv")
    argv[argv.index("--sim") + 1 :] = [str(tmp_path / "sim0" / n) for n in ("gps.csv", "again.csv")]
    assert run_gap([*argv, "--quiet", "--out", str(tmp_path / "r")]) == 2
    assert f"share {tmp_path / 'sim0' / 'truth.csv'}." in capsys.readouterr().err


@pytest.mark.usefixtures("stop_at_diagnosis")
def test_a_copy_of_the_real_truth_beside_sim_logs_is_route_checked(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # before: the copy read as each log's own truth, so the route check was skipped
    argv = make_case(tmp_path, sim_truth=False)
    for i in range(len(SIM_ROUTES)):
        shutil.copy(tmp_path / "real" / "truth.csv", tmp_path / f"sim{i}" / "truth.csv")
    assert run_gap([*argv, "--out", str(tmp_path / "r")]) == 2
    assert "did not drive the real route" in capsys.readouterr().err


@pytest.mark.usefixtures("stop_at_diagnosis")
def test_an_unreadable_sim_truth_is_named_with_its_error(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    argv = make_case(tmp_path, sim_truth=True)
    for i in range(len(SIM_ROUTES)):  # times in ms under a t_ms header
        truth = tmp_path / f"sim{i}" / "truth.csv"
        truth.write_text(truth.read_text().replace("t_s,", "t_ms,", 1))
    assert run_gap([*argv, "--out", str(tmp_path / "r")]) == 2
    err = capsys.readouterr().err
    assert f"{tmp_path / 'sim0' / 'truth.csv'}: CSV header has no time column" in err
    assert "readable truth" in err


@pytest.mark.usefixtures("stop_at_diagnosis")
def test_a_far_own_truth_is_named_not_the_truth_track(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    argv = make_case(tmp_path, sim_truth=True)
    t_s = np.arange(0.0, 600.0)
    east_m, north_m = circle_enu(t_s, *SIM_ROUTES[0])
    write_csv(tmp_path / "sim0" / "truth.csv", t_s, east_m, north_m + 11_000.0)
    assert run_gap([*argv, "--out", str(tmp_path / "r")]) == 2
    err = capsys.readouterr().err
    assert str(tmp_path / "sim0" / "truth.csv") in err and "--truth-track right" not in err


@pytest.mark.usefixtures("stop_at_diagnosis")
def test_a_short_sim_truth_is_said_to_be_the_short_part(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    argv = make_case(tmp_path, sim_truth=True)
    for i in range(len(SIM_ROUTES)):  # the truth covers the first 40 % of the log
        truth = tmp_path / f"sim{i}" / "truth.csv"
        truth.write_text("\n".join(truth.read_text().splitlines()[:241]) + "\n")
    assert run_gap([*argv, "--out", str(tmp_path / "r")]) == "scored"
    err = capsys.readouterr().err
    assert f"(of its 600 s: its truth {tmp_path / 'sim0' / 'truth.csv'} covers no more)" in err


@pytest.mark.usefixtures("stop_at_diagnosis")
def test_the_real_log_as_its_own_truth_track_stops(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    real = make_run(tmp_path / "real", 101, 1.5, 3.0, truth=True)
    sims = [make_run(tmp_path / f"sim{i}", 1 + i, 1.5, 3.0, truth=False) for i in range(3)]
    argv = real_truth_argv(tmp_path, real, sims)
    argv[argv.index("--truth-track") + 1] = str(real)  # the file itself
    assert run_gap(argv) == 2
    assert "is the real log" in capsys.readouterr().err
    # the same fixes under another header: not the same bytes, every error zero
    converted = tmp_path / "converted.csv"
    converted.write_text(real.read_text().replace("t_s,", "time,", 1))
    argv[argv.index("--truth-track") + 1] = str(converted)
    assert run_gap(argv) == 2
    assert "mm from the truth track" in capsys.readouterr().err


@pytest.fixture(scope="module")
def sim_runs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """Short x6wd sim runs (60 s): a moving mission (NMEA with RMC speeds) and a static
    survey, with their truth.csv."""
    root = tmp_path_factory.mktemp("runs")
    runs = {"moving": ("default.toml", 1), "static": ("open_field.toml", 2)}
    for name, (scenario, seed) in runs.items():
        path = gap_cli.PACKAGED_CONFIG_DIR / "scenarios" / scenario
        argv = ["sim", str(path), "--seed", str(seed), "--duration", "60", "--quiet"]
        x6wd_main([*argv, "--out", str(root / name)])  # 1: the mission is not finished
        assert (root / name / "gps.nmea").is_file() and (root / name / "truth.csv").is_file()
    return {name: root / name for name in runs}


@pytest.mark.usefixtures("stop_at_diagnosis")
def test_a_moving_real_log_against_a_point_truth_stops(
    tmp_path: Path, sim_runs: dict[str, Path], capsys: pytest.CaptureFixture[str]
) -> None:
    real = str(sim_runs["moving"] / "gps.nmea")
    argv = ["gap", "--real", real, "--truth", POINT, "--quiet", "--out", str(tmp_path / "r")]
    assert run_gap(argv) == 2
    err = capsys.readouterr().err
    assert f"{real}: the log moves" in err and "point --truth" in err
    # a static survey against its point is diagnosed as before
    argv[2] = str(sim_runs["static"] / "gps.nmea")
    assert run_gap([*argv, "--scenario", str(gap_cli.DEFAULT_SCENARIO), "--seeds", "1"]) == (
        "scored"
    )


@pytest.mark.usefixtures("stop_at_diagnosis")
def test_moving_sim_logs_against_a_static_truth_track_stop(
    tmp_path: Path, sim_runs: dict[str, Path], capsys: pytest.CaptureFixture[str]
) -> None:
    # before: a static survey's truth exempted them from every check (24 m "errors")
    moving = tmp_path / "m" / "gps.nmea"
    moving.parent.mkdir()
    shutil.copy(sim_runs["moving"] / "gps.nmea", moving)  # no truth.csv beside it
    static = sim_runs["static"]
    real = str(static / "gps.nmea")
    argv = ["gap", "--real", real, "--truth-track", str(static / "truth.csv"),
            "--sim", str(moving), real, "--quiet", "--out", str(tmp_path / "r")]  # fmt: skip
    assert run_gap(argv) == 2
    err = capsys.readouterr().err
    assert f"{moving}: the log moves" in err and "static truth track" in err
    assert f"{static / 'gps.nmea'}: the log moves" not in err


def _nmea(body: str) -> str:
    checksum = 0
    for char in body:
        checksum ^= ord(char)
    return f"${body}*{checksum:02X}\r\n"


def write_nmea(path: Path, t_s: np.ndarray, east_m: np.ndarray, north_m: np.ndarray,
               speed_mps: np.ndarray, course_deg: np.ndarray) -> Path:  # fmt: skip
    """GGA + RMC at 1 Hz from 2020-01-01 12:00:00 UTC: positions and reported speeds."""
    e_per_deg, n_per_deg = metres_per_degree(ORIGIN[0])
    lines = []
    for t, e, n, v, c in zip(t_s, east_m, north_m, speed_mps, course_deg, strict=True):
        lat, lon = ORIGIN[0] + n / n_per_deg, ORIGIN[1] + e / e_per_deg
        hms = f"{12 + int(t) // 3600:02d}{int(t) % 3600 // 60:02d}{int(t) % 60:02d}.00"
        ll = (f"{int(lat):02d}{(lat % 1) * 60:08.5f},N,"
              f"{int(-lon):03d}{(-lon % 1) * 60:08.5f},W")  # fmt: skip
        lines.append(_nmea(f"GPGGA,{hms},{ll},1,08,1.0,60.0,M,47.0,M,,"))
        lines.append(_nmea(f"GPRMC,{hms},A,{ll},{v / 0.514444:.2f},{c:.1f},010120,,,A"))
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("".join(lines))
    return path


def nmea_run(folder: Path, seed: int, truth_wobble_m: float = 0.0) -> Path:
    """A run at 1.5 m/s round a 12 m circle: gps.nmea (its truth plus a receiver's errors,
    speeds 0.05 m/s off) and truth.csv beside it; with ``truth_wobble_m`` the truth.csv is
    another run's, on the same circle, its distance along it swinging that far (10 s
    period): positions within metres, speeds a median of tenths of m/s apart."""
    rng = np.random.default_rng(seed)
    errors = surrogate_run(DURATION_S, 1.0, rng, effects=PRE)
    t_s = np.asarray(errors.t_s, dtype=float)
    east_m, north_m = circle_enu(t_s, 1.5, 0.0)
    angle = t_s * 1.5 / 12.0
    speed_mps = 1.5 + rng.normal(0.0, 0.05, t_s.size)
    course_deg = (90.0 - np.degrees(angle)) % 360.0  # east = 12 sin(angle): heading 90 - angle
    log = write_nmea(folder / "gps.nmea", t_s, east_m + np.asarray(errors.east_m),
                     north_m + np.asarray(errors.north_m), speed_mps, course_deg)  # fmt: skip
    along_m = 1.5 * t_s + truth_wobble_m * np.sin(2.0 * np.pi * t_s / 10.0)
    truth_angle = along_m / 12.0
    write_csv(folder / "truth.csv", t_s, 12.0 * np.sin(truth_angle),
              12.0 * (1.0 - np.cos(truth_angle)))  # fmt: skip
    return log


@pytest.mark.usefixtures("stop_at_diagnosis")
def test_a_sim_truth_whose_speeds_are_another_runs_stops(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # another seed's truth of the same laps lies within metres of a log (4.3 m against 4.1 m
    # from its own): its speeds tell (0.6 m/s off against 0.06)
    real = nmea_run(tmp_path / "real", 101)
    sims = [nmea_run(tmp_path / f"sim{i}", 1 + i, 1.3 if i == 0 else 0.0) for i in range(3)]
    argv = real_truth_argv(tmp_path, real, sims)
    assert run_gap(argv) == 2
    err = capsys.readouterr().err
    assert (
        f"{sims[0]}: its reported velocity (speed and course) differs" in err
        and str(sims[1]) not in err
    )
    # the right truths: scored
    nmea_run(tmp_path / "sim0", 1)
    assert run_gap(argv) == "scored"


# round 13 review of cfd44fc: three false refusals of legitimate logs


def circling_run(
    folder: Path,
    seed: int,
    radius_m: float,
    *,
    noise: float = 1.0,
    truth_hz: float = 1.0,
    truth_decimals: int = 9,
    cut_s: int = 0,
) -> Path:
    """A robot circling ``radius_m`` round a point at 1.5 m/s for 600 s, from ``seed`` m along
    the circle (each run its own path): gps.nmea (its truth plus a receiver's errors times
    ``noise``, speeds 0.05 m/s off, true courses; its first
    ``cut_s`` seconds left out) and truth.csv beside it, sampled at ``truth_hz`` and written
    with ``truth_decimals``."""
    rng = np.random.default_rng(seed)
    errors = surrogate_run(DURATION_S, 1.0, rng, effects=PRE)
    t_s = np.asarray(errors.t_s, dtype=float)

    def circle(t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        angle = (t * 1.5 + seed) / radius_m
        return radius_m * np.sin(angle), radius_m * (1.0 - np.cos(angle)), angle

    east_m, north_m, angle = circle(t_s)
    keep = t_s >= cut_s
    log = write_nmea(folder / "gps.nmea", t_s[keep],
                     (east_m + noise * np.asarray(errors.east_m))[keep],
                     (north_m + noise * np.asarray(errors.north_m))[keep],
                     (1.5 + rng.normal(0.0, 0.05, t_s.size))[keep],
                     ((90.0 - np.degrees(angle)) % 360.0)[keep])  # fmt: skip
    truth_t_s = np.arange(0.0, DURATION_S, 1.0 / truth_hz)
    e_per_deg, n_per_deg = metres_per_degree(ORIGIN[0])
    te_m, tn_m, _ = circle(truth_t_s)
    rows = ["t_s,lat,lon,alt"] + [
        f"{t:.3f},{ORIGIN[0] + n / n_per_deg:.{truth_decimals}f},"
        f"{ORIGIN[1] + e / e_per_deg:.{truth_decimals}f},60.0"
        for t, e, n in zip(truth_t_s, te_m, tn_m, strict=True)
    ]
    (folder / "truth.csv").write_text("\n".join(rows) + "\n")
    return log


@pytest.mark.usefixtures("stop_at_diagnosis")
def test_a_sim_noisier_than_the_real_receiver_is_scored_against_its_own_truth(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # before: sims 6x noisier (a median ~15 m against the real log's ~3 m, as building_route's
    # urban runs are against their own truth) stopped as "not its run's true path"
    real = circling_run(tmp_path / "real", 101, 12.0)
    sims = [circling_run(tmp_path / f"sim{i}", 1 + i, 12.0, noise=6.0) for i in range(3)]
    argv = real_truth_argv(tmp_path, real, sims)
    assert run_gap(argv) == "scored", capsys.readouterr().err
    # a wrong own truth still stops: a log cut 20 s into its truth (the speed alone stays
    # 1.5 m/s round a circle: its course tells) ...
    circling_run(tmp_path / "sim0", 1, 12.0, cut_s=20)
    assert run_gap(argv) == 2
    assert f"{sims[0]}: its reported velocity (speed and course) differs" in (
        capsys.readouterr().err
    )
    # ... and a truth of another route, 100 m off, its velocities alike
    circling_run(tmp_path / "sim0", 1, 12.0)
    truth = tmp_path / "sim1" / "truth.csv"
    rows = truth.read_text().splitlines()
    shifted = [rows[0]] + [f"{t},{float(lat) + 0.0009:.9f},{rest}"
                           for t, lat, rest in (r.split(",", 2) for r in rows[1:])]  # fmt: skip
    truth.write_text("\n".join(shifted) + "\n")
    assert run_gap(argv) == 2
    err = capsys.readouterr().err
    assert f"{sims[1]}: its fixes lie a median" in err and "over 10 times" in err


@pytest.mark.usefixtures("stop_at_diagnosis")
def test_a_log_circling_round_a_point_is_scored_against_its_true_circle(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # before: a 4 m circle (a compass check) was "the static truth track (reaching 4.0 m)"
    real = circling_run(tmp_path / "real", 101, 4.0)
    sims = [circling_run(tmp_path / f"sim{i}", 1 + i, 4.0) for i in range(3)]
    assert run_gap(real_truth_argv(tmp_path, real, sims)) == "scored", capsys.readouterr().err
    # a truth that stands still is static as before: a moving log against it stops
    still = tmp_path / "still.csv"
    still.write_text("t_s,lat,lon,alt\n" + "".join(
        f"{t:.1f},{ORIGIN[0]:.9f},{ORIGIN[1]:.9f},60.0\n" for t in range(600)))  # fmt: skip
    argv = real_truth_argv(tmp_path, real, sims)
    argv[argv.index("--truth-track") + 1] = str(still)
    assert run_gap(argv) == 2
    assert "the static truth track" in capsys.readouterr().err


@pytest.mark.parametrize(("truth_hz", "decimals"), [(50.0, 6), (100.0, 6), (20.0, 5)])
@pytest.mark.usefixtures("stop_at_diagnosis")
def test_an_own_truth_sampled_fast_and_rounded_is_not_a_speed_mismatch(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], truth_hz: float, decimals: int
) -> None:
    # before: truth speeds differenced sample to sample read the rounding (0.11 m at 6
    # decimals) as 0.6-1.9 m/s of speed mismatch: "not its run's true path"
    real = circling_run(tmp_path / "real", 101, 12.0)
    sims = [circling_run(tmp_path / f"sim{i}", 1 + i, 12.0, truth_hz=truth_hz,
                         truth_decimals=decimals) for i in range(2)]  # fmt: skip
    assert run_gap(real_truth_argv(tmp_path, real, sims)) == "scored", capsys.readouterr().err
