"""bench/bench_decode.py: how its rounds become the judged ratio (the figures themselves are
the benchmark's, not checked here)."""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from bench import bench_decode as bd
from tests.conftest import DATA, require_program

LOG = (DATA / "nmea" / "bt451.log").read_bytes()


def _ratio_row(rows: list[bd.Row]) -> bd.Row:
    return next(r for r in rows if r.metric.endswith("x6wd rate / gpsdecode rate"))


def test_a_round_too_short_to_measure_is_left_out(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    good = {"gpsdecode": 0.05, "gpsdecode start": 0.002}
    good |= {"x6wd decode": 0.25, "x6wd decode start": 0.15}
    # a start-up as long as the run (the decoding lost in the start-up's noise): was a
    # ratio of 1e7 in the median and in "rounds a..b"
    noise = good | {"x6wd decode start": 0.25}
    monkeypatch.setattr(bd, "_rounds", lambda *a: [good, noise, good])
    row = _ratio_row(bd._measure("log", LOG, "gpsdecode", tmp_path, 3))
    assert row.value == pytest.approx(0.48) and "rounds 0.480..0.480" in row.note, row.note
    assert "best-run method 0.480" in row.note and "1 of 3 rounds left out" in row.note
    monkeypatch.setattr(bd, "_rounds", lambda *a: [noise])
    row = _ratio_row(bd._measure("log", LOG, "gpsdecode", tmp_path, 1))
    assert math.isnan(row.value) and row.note.startswith("UNRELIABLE"), row.note


def test_x6wd_times_its_own_decoding(tmp_path: Path) -> None:
    gpsdecode = require_program("gpsdecode")
    (tmp_path / "log").write_bytes(LOG * 20)
    (tmp_path / "empty").write_bytes(b"")
    (r,) = bd._rounds(gpsdecode, tmp_path / "log", tmp_path / "empty", 1)
    start, whole = r["x6wd decode start"], r["x6wd decode"]
    assert 0 < start < whole and whole - start > 0.005, r  # imports: more than the decoding
