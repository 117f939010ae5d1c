"""bench/bench_mission.py (issue 14, item 7): one run's result structure, and the figures and
tables built from results (the figures themselves are the benchmark's, not checked here)."""

from __future__ import annotations

import math

import pytest

from bench import bench_mission as bm
from bench._common import Row
from tests.conftest import ROOT

DEFAULT = ROOT / "config" / "scenarios" / "default.toml"


@pytest.mark.slow
def test_one_run_of_the_default_scenario_has_the_result_structure() -> None:
    r = bm.run_one(DEFAULT, "estimator", 1)
    assert r.error is None
    assert (r.scenario, r.method, r.seed) == ("default", "estimator", 1)
    assert isinstance(r.completed, bool)
    assert r.waypoint_count == 4 and 0 <= r.waypoints_reached <= 4
    assert r.open_ground and r.position_source == "ekf"
    for v in (r.path_length_m, r.straight_length_m, r.sim_time_s, r.wall_time_s, r.cruise_mps):
        assert math.isfinite(v) and v > 0
    assert math.isfinite(r.path_ratio)
    assert isinstance(r.arrivals, list) and len(r.arrivals) == r.waypoints_reached
    for a in r.arrivals:
        assert {"index", "t_s", "true_error_m", "gps_error_m", "gps_slow_error_m"} <= set(a)
    cells = bm.summarise([r])
    assert len(cells) == 1 and cells[0].runs == 1
    rows = bm.rows(cells)
    assert rows and all(isinstance(x, Row) and x.bench == "mission" for x in rows)


def test_a_run_that_raises_is_a_failure_with_its_error(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(bm.METHODS, "bogus", {"no_such_key": 1})
    r = bm.run_one(DEFAULT, "bogus", 1)  # dataclasses.replace raises TypeError
    assert not r.completed and r.error and r.error.startswith("TypeError")
    r = bm.run_one(ROOT / "config" / "scenarios" / "no_such_scenario.toml", "raw", 1)
    assert not r.completed and r.error
    cell = bm.summarise([r])[0]
    assert (cell.completed, cell.runs, len(cell.errors)) == (0, 1, 1)
    assert "1 raised" in bm.markdown([cell], [1])


def test_figures_pool_the_arrivals_and_take_path_ratios_of_completed_runs() -> None:
    def run(seed: int, done: bool, true_m: list[float], gps_m: list[float]) -> bm.RunResult:
        arrivals = [
            {"index": i, "t_s": 10.0 * i, "true_error_m": t, "gps_slow_error_m": g}
            for i, (t, g) in enumerate(zip(true_m, gps_m, strict=True))
        ]
        return bm.RunResult(
            "s", "m", seed, completed=done, waypoints_reached=len(arrivals), waypoint_count=2,
            path_length_m=110.0 if done else 500.0, straight_length_m=100.0, sim_time_s=50.0,
            wall_time_s=1.0, cruise_mps=2.0, arrivals=arrivals,
        )  # fmt: skip

    cells = bm.summarise([run(1, True, [1.0, 2.0], [2.0, 2.0]), run(2, False, [3.0], [2.0])])
    (c,) = cells
    assert (c.completed, c.runs, c.arrivals) == (1, 2, 3)
    assert c.arrival_median_m == 2.0 and c.gps_median_m == 2.0 and c.arrival_ratio == 1.0
    assert c.path_ratio_median == pytest.approx(1.1) and c.path_ratio_max == pytest.approx(1.1)
    assert c.ideal_time_s == 50.0 and c.wall_time_s == 2.0
    table = bm.markdown(cells, [1, 2])
    assert "| s | m | 1/2 |" in table and "2.00 / " in table
