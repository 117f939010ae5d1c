"""The sweep's figures (an outside audit, round 23): past 10 cells the arrival error CDF gave
cell i and cell i+10 one colour (the docs' own 16-cell example had six such pairs); a survey
sweep drew three figures with nothing in them and no figure of its CEP50; 1000 cells made
35,000-pixel per-cell images that took most of the report's time."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from sim_backend.sweep_report import (
    CDF_PANEL_CELLS,
    MAX_ROW_CELLS,
    cdf_panels,
    cell_stats,
    write_report,
)

INFO = {
    "name": "t",
    "seed": 0,
    "seeds": 1,
    "scenarios": ["s.toml"],
    "set": {},
    "grid": {},
    "ran": 1,
    "skipped": 0,
    "executor": "in this process",
    "wall_s": 1.0,
    "missions_per_min": 60.0,
}


def mission(i: int) -> dict[str, Any]:
    return {
        "run_id": f"c{i}-0",
        "cell_id": f"c{i}",
        "scenario": "s",
        "params": {"k": i},
        "overrides": {"k": i},
        "seed": i,
        "status": "ok",
        "completed": True,
        "waypoint_count": 4,
        "path_length_m": 11.0,
        "straight_length_m": 10.0,
        "sim_time_s": 5.0,
        "wall_time_s": 0.1,
        "gps_cep50_m": 1.2,
        "arrivals": [{"true_error_m": 1.0 + i / 10, "gps_slow_error_m": 1.5}],
    }


def survey(i: int) -> dict[str, Any]:
    return {**mission(i), "completed": False, "waypoint_count": 0, "arrivals": []}


def test_sixteen_cells_get_one_colour_each_in_panels_of_ten(tmp_path: Path) -> None:
    records = [mission(i) for i in range(16)]
    panels = cdf_panels(cell_stats(records))
    assert [len(p) for p in panels] == [CDF_PANEL_CELLS, 6]
    # a curve's colour is its index in its panel: (panel, index) is one cell's alone
    seen = [c.cell_id for p in panels for c in p]
    assert seen == [f"c{i}" for i in range(16)]
    written = write_report(INFO, records, tmp_path)
    assert {"completion.png", "arrival_cdf.png", "path_ratio.png", "gps_cep50.png"} <= set(written)
    assert "- figures:" not in (tmp_path / "summary.md").read_text()


def test_a_survey_sweep_draws_its_cep50_and_no_empty_figure(tmp_path: Path) -> None:
    write_report(INFO, [mission(0)], tmp_path)  # an earlier call's figures, of other runs
    assert (tmp_path / "completion.png").exists()
    written = write_report(INFO, [survey(i) for i in range(3)], tmp_path)
    drawn = {n for n in written if n.endswith(".png")}
    assert drawn == {"gps_cep50.png"}
    for stale in ("completion.png", "arrival_cdf.png", "path_ratio.png"):
        assert not (tmp_path / stale).exists(), stale
    summary = (tmp_path / "summary.md").read_text()
    assert "![GPS CEP50](gps_cep50.png)" in summary
    assert "- figures: no mission ran" in summary


def test_past_the_row_limit_the_per_cell_figures_are_left_out_and_said(tmp_path: Path) -> None:
    n = MAX_ROW_CELLS + 1
    written = write_report(INFO, [mission(i) for i in range(n)], tmp_path)
    assert not {n for n in written if n.endswith(".png")}
    summary = (tmp_path / "summary.md").read_text()
    assert f"- figures: {n} cells: the per-cell figures" in summary
    cdf = f"- figures: {n} cells with arrivals: the arrival error CDF is drawn for up to"
    assert cdf in summary
