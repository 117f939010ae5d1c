"""--sim logs must move as the real log does: a static survey scored against moving runs
with their own truth.csv (or a driven log against static runs) was accepted, and the motion
difference (the navigation filter's lag, static hold) would be reported as the receiver's
gap. Real files through the real CLI; the diagnosis itself is replaced by a stop."""

from __future__ import annotations

from pathlib import Path

import pytest

from tests.test_gap_sim_truth_round12 import make_run
from tests.test_gap_truth_round13 import run_gap, stop_at_diagnosis  # noqa: F401


def case(tmp_path: Path, real_mps: float, sims_mps: tuple[float, ...]) -> list[str]:
    real = make_run(tmp_path / "real", 101, real_mps, 3.0, truth=True)
    sims = [
        make_run(tmp_path / f"sim{i}", 1 + i, mps, 2.0 + i, truth=True)
        for i, mps in enumerate(sims_mps)
    ]
    return ["gap", "--real", str(real), "--truth-track", str(tmp_path / "real" / "truth.csv"),
            "--sim", *map(str, sims), "--quiet", "--no-figures",
            "--out", str(tmp_path / "r")]  # fmt: skip


@pytest.mark.usefixtures("stop_at_diagnosis")
def test_moving_sims_against_a_static_real_log_stop_naming_them(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert run_gap(case(tmp_path, 0.0, (0.0, 1.5, 1.5))) == 2
    err = capsys.readouterr().err
    assert "stands still but the truth.csv beside each of these moves" in err
    assert str(tmp_path / "sim1" / "gps.csv") in err and str(tmp_path / "sim2" / "gps.csv") in err
    assert str(tmp_path / "sim0" / "gps.csv") not in err


@pytest.mark.usefixtures("stop_at_diagnosis")
def test_a_static_sim_against_a_driven_real_log_stops(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert run_gap(case(tmp_path, 1.5, (1.5, 0.0, 1.6))) == 2
    err = capsys.readouterr().err
    assert "moves but the truth.csv beside this --sim log stands still" in err
    assert str(tmp_path / "sim1" / "gps.csv") in err


@pytest.mark.usefixtures("stop_at_diagnosis")
@pytest.mark.parametrize("mps", [0.0, 1.5])
def test_runs_that_move_as_the_real_log_does_are_scored(tmp_path: Path, mps: float) -> None:
    assert run_gap(case(tmp_path, mps, (mps, mps, mps))) == "scored"


@pytest.mark.usefixtures("stop_at_diagnosis")
@pytest.mark.parametrize("shape", ["walk-in", "one-float-epoch"])
def test_a_still_survey_with_a_reference_that_moved_outside_the_log_is_scored(
    tmp_path: Path, shape: str
) -> None:
    # Review of 5cc3bad: a reference logged from power-on (the antenna carried 40 m to the
    # mark before the log began) or with one RTK float epoch 6 m off was judged "moves" by
    # its largest distance over the whole track, and static --sim runs were refused
    import numpy as np

    from tests.test_gap_sim_truth_round12 import DURATION_S, write_csv

    argv = case(tmp_path, 0.0, (0.0, 0.0, 0.0))
    t_s = np.arange(0.0, DURATION_S)
    east_m, north_m = np.zeros_like(t_s), np.zeros_like(t_s)
    if shape == "walk-in":
        before_s = np.arange(-300.0, 0.0)
        walk_m = np.minimum(before_s + 300.0, 40.0) - 40.0  # 40 m at 1 m/s, then standing
        t_s, east_m = np.concatenate((before_s, t_s)), np.concatenate((walk_m, east_m))
        north_m = np.zeros_like(t_s)
    else:
        east_m[len(t_s) // 2] = 6.0
    write_csv(tmp_path / "real" / "truth.csv", t_s, east_m, north_m)
    assert run_gap(argv) == "scored"
