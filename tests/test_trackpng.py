"""The receiver engine's track.png, drawn with Pillow (sim_backend.trackpng): what it shows,
where; and matplotlib's figure when Pillow cannot draw text."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

import sim_backend.trackpng as trackpng
from sim_backend.runs import ErrorStats, Summary
from sim_backend.world import load_world

ROOT = Path(__file__).resolve().parent.parent
WINDOW = ROOT / "config" / "scenarios" / "building_window.toml"


def _summary(name: str) -> Summary:
    nan = ErrorStats.of(np.zeros(0))
    return Summary(
        scenario=name, seed=3, completed=False, waypoints_reached=0, waypoint_count=0,
        sim_time_s=10.0, wall_time_s=0.1, path_length_m=0.0, straight_length_m=0.0,
        raw_error=ErrorStats.of(np.array([1.0, 2.0])), filtered_error=nan, hold_periods=0,
        hold_time_s=0.0, fixes=2, fixes_valid=2, dispersion_lat_m=1.0, dispersion_lon_m=1.0,
        mean_hdop=1.0, mean_sats_used=8.0,
    )  # fmt: skip


def _rgb(path: Path) -> np.ndarray:
    with Image.open(path) as im:
        assert im.size == (700, 700)
        return np.asarray(im.convert("RGB")).astype(int)


def test_walls_fixes_truth_and_legend_where_they_belong(tmp_path: Path) -> None:
    world = load_world(WINDOW)
    rng = np.random.default_rng(0)
    fixes = np.column_stack((rng.normal(-30, 1, 400), rng.normal(20, 1, 400)))
    out = tmp_path / "track.png"
    trackpng.plot_survey(out, world, (2.5, 0.0), fixes, _summary(world.name))
    img = _rgb(out)
    red = (img[..., 0] > 150) & (img[..., 1] < 120) & (img[..., 2] < 120)
    blue = (abs(img[..., 0] - 31) < 30) & (abs(img[..., 1] - 119) < 30) & (img[..., 2] > 150)
    dark = (img.max(axis=2) < 100) & (img.max(axis=2) - img.min(axis=2) < 10)
    inside = np.zeros(red.shape, dtype=bool)
    inside[90:620, 90:628] = True  # the axes box, its frame and the legend left out
    inside[85:140, 500:630] = False
    rows, cols = np.nonzero(red & inside)
    # the cloud of fixes up and to the left of the room, the plus on the antenna beside it
    by, bx = np.nonzero(blue & inside)
    assert rows.size > 500 and blue[inside].sum() > 80 and (dark & inside).sum() > 300
    assert np.median(cols) < np.median(bx) - 100 and np.median(rows) < np.median(by) - 50
    # the legend's box (light frame) holds a red dot and a blue plus of its own
    assert red[85:140, 500:630].any() and blue[85:140, 500:630].any()


def test_without_fixes_and_without_walls(tmp_path: Path) -> None:
    world = load_world(ROOT / "config" / "scenarios" / "open_field.toml")
    out = tmp_path / "track.png"
    trackpng.plot_survey(out, world, (0.0, 0.0), np.zeros((0, 2)), _summary(world.name))
    img = _rgb(out)
    assert not ((img[..., 0] > 150) & (img[..., 1] < 120))[90:620, 90:500].any()


def test_ticks_and_their_labels_are_matplotlibs() -> None:
    assert trackpng._ticks(-78.0, 24.0, 9) == [-60.0, -40.0, -20.0, 0.0, 20.0]
    assert trackpng._ticks(-12.1, 9.4, 9) == [-10.0, -7.5, -5.0, -2.5, 0.0, 2.5, 5.0, 7.5]
    assert trackpng._labels([-5.0, -2.5, 0.0, 2.5]) == ["\u22125.0", "\u22122.5", "0.0", "2.5"]
    assert trackpng._labels([-20.0, 0.0, 20.0]) == ["\u221220", "0", "20"]


def test_matplotlib_draws_it_when_pillow_cannot_draw_text(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    drawn: list[Path] = []
    monkeypatch.setattr(trackpng, "_font_file", lambda: None)
    monkeypatch.setattr(trackpng, "plot_track", lambda path, *_a: drawn.append(path))
    world = load_world(WINDOW)
    out = tmp_path / "track.png"
    trackpng.plot_survey(out, world, (0.0, math.pi), np.zeros((3, 2)), _summary(world.name))
    assert drawn == [out]


def test_a_missions_filtered_track_is_named_by_its_position_source() -> None:
    """The legend of a mission's track.png says which estimate the robot steered by (it said
    'Constellation' under the shipped EKF)."""
    from sim_backend.runs import filtered_label

    s = _summary("x")
    labels = {}
    for source in ("ekf", "constellation", "raw"):
        s.extra["position_source"] = source
        labels[source] = filtered_label(s)
    assert labels == {
        "ekf": "filtered (EKF)",
        "constellation": "filtered (Constellation)",
        "raw": "filtered (latest fix)",
    }
