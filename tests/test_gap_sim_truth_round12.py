"""The GPS half's ``--sim`` logs of a moving mission (round 12, outside investigation): each
``--sim`` recording of a closed-loop mission drove its own route (each seed steers on its own
GPS error; its laps end at other times), and its errors were taken against the REAL log's
truth track: the route difference read as GNSS error (7.7-14.6 m mean against 1.5-4.6 m
against their own truth.csv) and 22 of 24 unaltered moving logs were false alarms. A ``--sim``
log with its own truth (truth.csv beside it, as ``x6wd sim`` writes) is now scored against it;
one without, that did not drive the real route, stops with exit 2; a static survey is as
before."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from sim_backend.effects import PositionSeries, metres_per_degree
from x6wd.app.cli import main as x6wd_main
from x6wd.gap import cli as gap_cli
from x6wd.gap.surrogate import BASELINE_EFFECTS, surrogate_run

ORIGIN = (51.752, -1.2577)
DURATION_S = 600.0
PRE = BASELINE_EFFECTS[:-1]  # the receiver's errors before NMEA printing (no lattice)


def circle_enu(t_s: np.ndarray, speed_mps: float, delay_s: float) -> tuple[np.ndarray, ...]:
    """East, north (m) of a robot lapping a 12 m circle at ``speed_mps``, standing still for
    ``delay_s`` first: a closed-loop mission whose seeds start and lap at their own times."""
    radius_m = 12.0
    angle = np.maximum(t_s - delay_s, 0.0) * speed_mps / radius_m
    return radius_m * np.sin(angle), radius_m * (1.0 - np.cos(angle))


def write_csv(path: Path, t_s: np.ndarray, east_m: np.ndarray, north_m: np.ndarray) -> Path:
    e_per_deg, n_per_deg = metres_per_degree(ORIGIN[0])
    rows = ["t_s,lat,lon,alt"] + [
        f"{t:.3f},{ORIGIN[0] + n / n_per_deg:.9f},{ORIGIN[1] + e / e_per_deg:.9f},60.0"
        for t, e, n in zip(t_s, east_m, north_m, strict=True)
    ]
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n".join(rows) + "\n")
    return path


def make_run(
    folder: Path, seed: int, speed_mps: float, delay_s: float, *, truth: bool, scale: float = 1.0
) -> Path:
    """A run in ``folder``: gps.csv (its truth plus a receiver's errors) and, with ``truth``,
    truth.csv beside it (as ``x6wd sim`` writes). Returns the log's path."""
    errors = surrogate_run(DURATION_S, 1.0, np.random.default_rng(seed), effects=PRE)
    t_s = np.asarray(errors.t_s, dtype=float)
    east_m, north_m = circle_enu(t_s, speed_mps, delay_s)
    log = write_csv(
        folder / "gps.csv",
        t_s,
        east_m + scale * np.asarray(errors.east_m),
        north_m + scale * np.asarray(errors.north_m),
    )
    if truth:
        write_csv(folder / "truth.csv", t_s, east_m, north_m)
    return log


# the sims' own routes: other speeds and start delays, as three seeds of one mission drive
SIM_ROUTES = ((1.40, 6.0), (1.62, 0.0), (1.47, 14.0))


def make_case(tmp_path: Path, *, sim_truth: bool) -> list[str]:
    real = make_run(tmp_path / "real", 101, 1.5, 3.0, truth=True)
    sims = [
        make_run(tmp_path / f"sim{i}", 1 + i, speed, delay, truth=sim_truth)
        for i, (speed, delay) in enumerate(SIM_ROUTES)
    ]
    return ["gap", "--real", str(real), "--truth-track", str(tmp_path / "real" / "truth.csv"),
            "--sim", *map(str, sims), "--replicates", "5", "--quiet", "--no-figures"]  # fmt: skip


def real_truth_argv(tmp_path: Path, real: Path, sims: list[Path]) -> list[str]:
    """``x6wd gap`` on ``real`` scored against tmp_path/real/truth.csv, ``sims`` as --sim."""
    truth = tmp_path / "real" / "truth.csv"
    return ["gap", "--real", str(real), "--truth-track", str(truth), "--sim", *map(str, sims),
            "--quiet", "--no-figures", "--out", str(tmp_path / "r")]  # fmt: skip


class Scored(Exception):
    """Raised in place of the diagnosis: the errors the logs were scored with are kept."""


@pytest.fixture
def scored(monkeypatch: pytest.MonkeyPatch) -> dict:
    """Stops the CLI at the diagnosis and keeps the real and baseline error series."""
    kept: dict = {}

    def stop(real: object, baseline: object, *args: object, **kwargs: object) -> None:
        kept["real"], kept["baseline"] = real, baseline
        raise Scored

    monkeypatch.setattr(gap_cli, "diagnose", stop)
    return kept


def median_error_m(series: PositionSeries) -> float:
    valid = np.asarray(series.valid, dtype=bool)
    return float(np.median(np.hypot(np.asarray(series.east_m)[valid],
                                    np.asarray(series.north_m)[valid])))  # fmt: skip


def test_sim_logs_of_a_moving_mission_are_scored_against_their_own_truth(
    tmp_path: Path, scored: dict
) -> None:
    # before: against the real truth the sims' route differences made metres of "error"
    argv = make_case(tmp_path, sim_truth=True)
    with pytest.raises(Scored):
        x6wd_main([*argv, "--out", str(tmp_path / "rep")])
    real_m = median_error_m(scored["real"])
    sims_m = [median_error_m(s) for s in scored["baseline"]]
    assert real_m < 3.0
    # each against its own truth: the receiver's error only, as the real log's
    assert all(m < 2.0 * real_m + 0.5 for m in sims_m), (real_m, sims_m)


def test_moving_sim_logs_with_their_truth_have_no_false_gap_and_say_which_truth(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    argv = make_case(tmp_path, sim_truth=True)
    out = tmp_path / "rep"
    assert x6wd_main([*argv, "--out", str(out)]) == 0
    said = capsys.readouterr().out
    assert said.startswith("no significant gap"), said
    md = (out / "report.md").read_text()
    assert "3 of 3 --sim logs are scored against the truth.csv beside them" in md
    notes = json.loads((out / "report.json").read_text())
    assert notes["verdict"]["status"] != "explained"


def test_a_moving_sim_log_without_its_truth_that_drove_another_route_stops(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    argv = make_case(tmp_path, sim_truth=False)
    assert x6wd_main([*argv, "--out", str(tmp_path / "rep")]) == 2
    err = capsys.readouterr().err
    assert str(tmp_path / "sim0" / "gps.csv") in err
    assert "did not drive the real route" in err
    assert "truth.csv" in err and "--scenario" in err
    assert not (tmp_path / "rep" / "report.md").exists()


def test_a_sim_log_without_its_truth_on_the_real_route_is_scored_against_the_real_truth(
    tmp_path: Path, scored: dict
) -> None:
    # a --sim log driven along the real truth (a replay of its route) needs no truth of its own
    real = make_run(tmp_path / "real", 101, 1.5, 3.0, truth=True)
    sims = [make_run(tmp_path / f"sim{i}", 1 + i, 1.5, 3.0, truth=False) for i in range(3)]
    with pytest.raises(Scored):
        x6wd_main(real_truth_argv(tmp_path, real, sims))
    assert all(median_error_m(s) < 3.0 for s in scored["baseline"])


def test_a_static_survey_with_a_worse_sim_receiver_is_not_refused(
    tmp_path: Path, scored: dict
) -> None:
    # a stationary truth track: a sim log far noisier than the real one is a gap to find,
    # not another route
    real = make_run(tmp_path / "real", 101, 0.0, 0.0, truth=True, scale=0.3)
    sims = [make_run(tmp_path / f"sim{i}", 1 + i, 0.0, 0.0, truth=False, scale=8.0)
            for i in range(3)]  # fmt: skip
    with pytest.raises(Scored):
        x6wd_main(real_truth_argv(tmp_path, real, sims))
    real_m = median_error_m(scored["real"])
    assert all(median_error_m(s) > max(5.0, 3.0 * real_m) for s in scored["baseline"])
