"""Clocks and dates, round 6 (outside audit 8d).

1. A robot without a real-time clock boots at 1970: its runs must not be named (and so
   ordered: retention, ``x6wd plot DIR``, the console's list) before the runs recorded while
   its clock was right. A new run is named one second after the newest one in the directory
   when the clock reads earlier.
2. ``x6wd plot --truth`` of such a recording: the fixes are placed on the recording's own
   clock (dated by the first fix, not by the 1970 ``t_utc``), and the start is the GPS's.
"""

from __future__ import annotations

import logging
from datetime import UTC, datetime, timedelta
from pathlib import Path

import numpy as np
import pytest

from x6wd.app import logview
from x6wd.app.console.server import ConsoleServer
from x6wd.core.recorder import (
    Recorder,
    Retention,
    enforce_retention,
    list_recordings,
    read_recording_parts,
)
from x6wd.core.records import GpsFix

KB = 1024
EPOCH = datetime(1970, 1, 1, tzinfo=UTC)


def _run(directory: Path, at: datetime, size: int = 4 * KB) -> Path:
    """One run created by the recorder with its clock reading ``at``, ``size`` bytes."""
    with Recorder.in_dir(directory, utc_clock=lambda: at) as rec:
        rec.record_event("x", 0.0, pad="y" * size)
    return rec.path


def test_a_run_started_at_1970_sorts_after_the_runs_before_it(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    d = tmp_path / "rec"
    a = _run(d, datetime(2026, 11, 20, 10, 0, 0, tzinfo=UTC))  # office, NTP
    b = _run(d, datetime(2026, 11, 21, 10, 0, 0, tzinfo=UTC))
    assert (a.name, b.name) == ("x6wd-20261120T100000Z.jsonl", "x6wd-20261121T100000Z.jsonl")
    with caplog.at_level(logging.WARNING, "x6wd.core.recorder"):
        c = _run(d, EPOCH + timedelta(seconds=31))  # yesterday's field run, booted at 1970
    assert c.name == "x6wd-20261121T100001Z.jsonl"
    assert "1970-01-01 00:00:31" in caplog.text and "x6wd-20261121T100001Z" in caplog.text
    # its records keep the clock's time: the name is only the order
    assert '"t_utc":"1970-01-01T00:00:31' in c.read_text()
    d2 = _run(d, EPOCH + timedelta(seconds=25))  # today's, booted at 1970 again
    assert d2.name == "x6wd-20261121T100002Z.jsonl"
    created = [a, b, c, d2]
    assert [f.path for f in list_recordings(d)] == created
    # x6wd plot DIR draws the newest run; the console lists them in that order
    assert logview.newest_recording(d) == d2
    assert list(ConsoleServer._list_runs(d)) == [p.name for p in created]
    # retention deletes the oldest-created first, never yesterday's field run before them
    size = sum(p.stat().st_size for p in created)
    gone = enforce_retention(d, Retention(max_total_bytes=size - 1), current=d2, reserve_bytes=0)
    assert gone == [a]
    # the clock right again: named by it
    e = _run(d, datetime(2026, 12, 5, 9, 0, 0, tzinfo=UTC))
    assert e.name == "x6wd-20261205T090000Z.jsonl"
    assert logview.newest_recording(d) == e


def test_the_same_second_keeps_its_counter_and_never_sorts_before(tmp_path: Path) -> None:
    t = datetime(2026, 1, 2, 3, 4, 5, tzinfo=UTC)
    d = tmp_path / "rec"
    a, b, c = _run(d, t), _run(d, t), _run(d, t)
    assert [p.name for p in (a, b, c)] == [
        "x6wd-20260102T030405Z.jsonl",
        "x6wd-20260102T030405Z-1.jsonl",
        "x6wd-20260102T030405Z-2.jsonl",
    ]
    b.unlink()  # retention took -1: the next is -3, not -1 (which sorts before -2)
    assert _run(d, t).name == "x6wd-20260102T030405Z-3.jsonl"
    # only a later part of a run left: its name is not taken again (its parts would mix)
    d3 = tmp_path / "parts"
    d3.mkdir()
    (d3 / "x6wd-20260102T030405Z.1.jsonl").write_text("{}\n")
    assert _run(d3, t).name == "x6wd-20260102T030405Z-1.jsonl"
    assert _run(d3, t - timedelta(days=1)).name == "x6wd-20260102T030406Z.jsonl"
    # a file of another kind under the name is never overwritten
    d4 = tmp_path / "dirs"
    (d4 / "x6wd-20260102T030405Z.jsonl").mkdir(parents=True)
    (d4 / "x6wd-20260102T030405Z-1.jsonl").mkdir()
    assert _run(d4, t).name == "x6wd-20260102T030405Z-2.jsonl"


# --- 2. x6wd plot --truth of a recording whose clock was wrong ------------------------------

GPS_START = datetime(2026, 12, 4, 14, 0, 0, tzinfo=UTC)


def _recording(path: Path, wall0: datetime, latency_s: float = 0.25) -> np.ndarray:
    """A run at 2 m/s north, a fix every 0.5 s dated by the GPS (2026), arriving
    ``latency_s`` after its epoch; the recorder's clock reads ``wall0`` at t_mono 0. Returns
    the true track (epoch t_mono, lat, lon)."""
    now = [wall0]
    t_mono0 = 1000.0
    rows = []
    with Recorder(path, utc_clock=lambda: now[0]) as rec:
        for i in range(120):
            epoch = t_mono0 + 0.5 * i
            lat = 51.75 + (2.0 * 0.5 * i) / 111_320.0
            rows.append((epoch, lat, -1.25))
            arrived = epoch + latency_s
            now[0] = wall0 + timedelta(seconds=arrived)
            fix = GpsFix(
                t_s=arrived,
                utc=GPS_START + timedelta(seconds=0.5 * i),
                lat_deg=lat,
                lon_deg=-1.25,
                quality=1,
                sats_used=9,
                hdop=0.9,
                valid=True,
                mode=3,
            )
            rec.record("fix", fix, t_mono=arrived)
        rec.record_event("shutdown", t_mono0 + 60.0)
    return np.array(rows)


def _fix_error(view: logview.LogView) -> np.ndarray:
    (series,) = [s for s in view.error if s.label == "GPS fix"]
    return series.v


def test_truth_error_of_a_recording_whose_clock_read_1970(tmp_path: Path) -> None:
    """The auditor's check: a truth made of the recording's own fixes (t_s = each fix's
    record time) reads ~0 m, not the 56 years' clamp to the truth's end."""
    rec = tmp_path / "x6wd-19700101T000000Z.jsonl"
    # the recorder's clock: 1970 at t_mono 1000 s (booted 1000 s before)
    _recording(rec, EPOCH - timedelta(seconds=1000.0) + timedelta(seconds=0.8))
    truth = tmp_path / "truth.csv"
    lines = ["t_s,lat,lon"]
    for r in read_recording_parts(rec):
        if r.type == "fix":
            lines.append(f"{r.data['t_s']},{r.data['lat_deg']},{r.data['lon_deg']}")
    truth.write_text("\n".join(lines) + "\n")
    view = logview.load(rec, truth=truth)
    err = _fix_error(view)
    assert err.size > 100 and float(np.max(err)) < 0.01, (np.median(err), np.max(err))
    # the start is the GPS's; the recorder's 1970 is said, not hidden
    assert view.start_utc == "2026-12-04T14:00:00+00:00"  # the first fix's epoch
    assert view.recorder_clock.startswith("1970-01-01T00:00:01")
    assert view.recorder_clock_off_s is not None and view.recorder_clock_off_s < -1e9
    page = logview.html_page(view)
    assert "recorder clock" in page and "behind the GPS" in page


def test_truth_error_of_a_recording_whose_clock_was_right_is_at_the_fix_epoch(
    tmp_path: Path,
) -> None:
    """Documented behaviour kept: with the recorder's clock right, a fix is placed at its
    epoch (its UTC on the recording's clock), not at its arrival 0.25 s later."""
    rec = tmp_path / "x6wd-20261204T134320Z.jsonl"
    wall0 = GPS_START - timedelta(seconds=1000.0)  # the right clock: t_mono 1000 s = GPS_START
    track = _recording(rec, wall0)
    truth = tmp_path / "truth.csv"
    truth.write_text("t_s,lat,lon\n" + "".join(f"{t},{la},{lo}\n" for t, la, lo in track))
    view = logview.load(rec, truth=truth)
    err = _fix_error(view)
    assert float(np.max(err)) < 0.01, np.max(err)  # at arrival: 0.5 m behind
    assert view.recorder_clock == "" and view.recorder_clock_off_s is None
    assert view.start_utc.startswith("2026-12-04T14:00:00.25")
    assert "recorder clock" not in logview.html_page(view)
