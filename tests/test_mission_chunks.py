"""x6wd sim's long-run plumbing: a static survey's receiver in chunks, the packed truth."""

from __future__ import annotations

import csv
import math
from pathlib import Path

import numpy as np
import pytest

import sim_backend.mission as mission
from sim_backend.world import load_world
from x6wd.core.recorder import read_recording

ROOT = Path(__file__).resolve().parent.parent
OPEN_FIELD = ROOT / "config" / "scenarios" / "open_field.toml"


def _fixes_m(out: Path) -> tuple[list[str], np.ndarray]:
    """The fixes' UTC stamps and their east/north (m) from the first one."""
    fixes = [r.data for r in read_recording(out / "recording.jsonl") if r.type == "fix"]
    lat = np.array([f["lat_deg"] for f in fixes])
    lon = np.array([f["lon_deg"] for f in fixes])
    north = np.radians(lat - lat[0]) * 6371e3
    east = np.radians(lon - lon[0]) * 6371e3 * math.cos(math.radians(lat[0]))
    return [f["utc"] for f in fixes], np.column_stack([east, north])


@pytest.mark.slow
def test_a_survey_in_chunks_has_every_epoch_once_and_a_continuous_error(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Three receiver calls of 40 epochs: every epoch's burst once, in order, and the slow
    error carried across the chunk boundaries (a fresh start there would jump by about the
    metre-sized slow error; steps within a chunk are centimetres)."""
    monkeypatch.setattr(mission, "STATIC_CHUNK_EPOCHS", 40)
    world = load_world(OPEN_FIELD)
    s = mission.run_mission(world, tmp_path, seed=3, duration_s=100.0)
    assert s.fixes == s.fixes_valid == 101
    utc, pos = _fixes_m(tmp_path)
    assert utc == [f"2020-01-01T12:{k // 60:02d}:{k % 60:02d}.000000Z" for k in range(101)]
    gga = [ln for ln in (tmp_path / "gps.nmea").read_text().splitlines() if "GGA" in ln]
    assert len(gga) == 101
    step = np.hypot(*np.diff(pos, axis=0).T)  # step[k] is fix k+1 minus fix k
    boundary = step[[39, 79]]  # fixes 40 and 80 start a chunk
    inside = np.delete(step, [39, 79])
    assert boundary.max() <= 3.0 * np.percentile(inside, 99) + 0.05


def test_truth_csv_is_the_same_in_chunks(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """truth.csv written 7 rows at a time is the file written at once (packed doubles in,
    the same conversion per row)."""
    world = load_world(OPEN_FIELD)
    trace = mission._Trace()
    rng = np.random.default_rng(0)
    for k in range(1000):
        trace.t.append(0.05 * k)
        trace.east.append(float(rng.normal(0, 80)))
        trace.north.append(float(rng.normal(0, 80)))
        trace.up.append(float(rng.normal(0, 1)))
        trace.heading.append(float(rng.uniform(0, 360)))
    mission._write_truth(tmp_path / "whole.csv", world, trace, 0.34)
    monkeypatch.setattr(mission, "TRUTH_CHUNK_ROWS", 7)
    mission._write_truth(tmp_path / "chunks.csv", world, trace, 0.34)
    whole = (tmp_path / "whole.csv").read_text()
    assert (tmp_path / "chunks.csv").read_text() == whole
    rows = list(csv.DictReader(whole.splitlines()))
    assert len(rows) == 1000 and rows[1]["t_s"] == "0.050"
