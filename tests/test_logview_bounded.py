"""The log viewer reads a recording of any length in bounded memory (found by an outside
audit: ``x6wd plot`` and the console's page of a 10 h run held every record, 400 MB).

Proved without measuring memory: with the reader's sample size made small, what it keeps of a
long recording stays within a constant, and what the page relies on (the first and last
points, each series' extremes, the holds, the counts) is what reading all of it gives."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from x6wd.app import logview

EPOCHS = 1500  # 1 s epochs: each a fix, a sky report, telemetry, an attitude and NMEA
SPIKE = 700  # the epoch of an HDOP spike and a position outlier
LIMIT = 64  # the reader's sample size in the bounded read


def _line(t_s: float, kind: str, data: dict[str, Any]) -> str:
    utc = f"2020-01-01T{12 + int(t_s) // 3600:02d}:{int(t_s) // 60 % 60:02d}:{int(t_s) % 60:02d}"
    return json.dumps({"t_mono": t_s, "t_utc": utc + ".000000Z", "type": kind, "data": data})


def _long_recording(path: Path) -> None:
    """A recording of :data:`EPOCHS` epochs, an outlier at :data:`SPIKE`, a hold (epochs
    300-400, its reason changing at 350) and every line's NMEA sentence, and its true track."""
    lines = []
    for k in range(EPOCHS):
        t = float(k)
        lat = 51.752 + 1e-6 * (k % 7) + (1e-3 if k == SPIKE else 0.0)
        lon = -1.2577 - 1e-6 * (k % 5) - (2e-3 if k == SPIKE + 1 else 0.0)
        hdop = 42.0 if k == SPIKE else 1.0 + 0.01 * (k % 3)
        utc = f"2020-01-01T{12 + k // 3600:02d}:{k // 60 % 60:02d}:{k % 60:02d}.000000Z"
        fix = {
            "t_s": t, "utc": utc, "lat_deg": lat, "lon_deg": lon, "alt_m": 55.7, "quality": 1,
            "sats_used": 3 if k == SPIKE + 2 else 8, "hdop": hdop, "speed_mps": 0.2,
            "course_deg": float(k % 360), "valid": True, "mode": 3, "pdop": None,
            "vdop": None, "geoid_sep_m": 47.7,
        }  # fmt: skip
        sats = [{"prn": p, "el_deg": 40.0, "az_deg": 90.0, "snr_dbhz": 40.0, "used": True,
                 "gnssid": 0, "svid": p} for p in range(1, 10)]  # fmt: skip
        sky = {"t_s": t, "satellites": sats, "pdop": None, "hdop": hdop, "vdop": None,
               "utc": utc}  # fmt: skip
        hold = "gps stale" if 300 <= k < 350 else "no valid fix" if 350 <= k < 400 else ""
        tel = {"t_s": t, "mode": "RUNNING", "state": "HOLD" if hold else "STRAIGHT",
               "hold_reason": hold, "filt_lat_deg": lat, "filt_lon_deg": lon,
               "heading_deg": float(k % 360)}  # fmt: skip
        lines += [
            _line(
                t, "nmea", {"text": "$GPRMC,120000.00,A,5145.12,N,00115.46,W,0.3,,010120,,,A*67"}
            ),
            _line(t, "fix", fix),
            _line(t, "sky", sky),
            _line(t + 0.5, "telemetry", tel),
            _line(t + 0.5, "attitude", {"t_s": t + 0.5, "bearing_deg": 10.0, "valid": True}),
        ]
    path.write_text("\n".join(lines) + "\n")
    # the true track goes 0.01 deg north and back: the largest error is at its turn (750 s),
    # where no position is an extreme and no stride a sample's
    path.with_name("truth.csv").write_text(
        f"t_s,lat,lon\n0,51.752,-1.2577\n{EPOCHS / 2},51.762,-1.2577\n{EPOCHS},51.752,-1.2577\n"
    )


def _all_series(view: logview.LogView) -> list[logview.Series]:
    return [*view.error, *view.hdop, *view.satellites, *view.heading]


def test_a_long_recording_is_read_in_bounded_memory(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    rec = tmp_path / "recording.jsonl"
    _long_recording(rec)
    whole = logview.load(rec)  # the default sample holds all of it
    assert len(whole.hdop[0].t_s) == EPOCHS
    monkeypatch.setattr(logview, "SAMPLE_ROWS", LIMIT, raising=False)
    view = logview.load(rec)

    # what is kept of each series is bounded: a stride's rows, the last, each key's extremes
    bound = LIMIT + 1 + 2 * 4
    for s in _all_series(view):
        assert len(s.t_s) <= bound, s.label
    for label, (e, n) in view.track.items():
        assert len(e) == len(n) <= bound, label
    # ... and the reader holds no more, however long the recording (NMEA, telemetry, marks)
    raw = logview._Raw()
    logview._read_recording(rec, raw, [])
    assert raw.held() <= 7 * bound + 1100  # seven series, hold marks: 1024 + the last minute

    # what the page relies on is what reading all of it gives: the counts, the time axis
    # and each panel's range (the first and last points, the extremes), the holds
    assert view.counts == whole.counts
    assert view.time_range() == whole.time_range() == (0.0, EPOCHS - 0.5)
    for a, b in zip(_all_series(view), _all_series(whole), strict=True):
        assert a.label == b.label
        assert (a.t_s[0], a.t_s[-1]) == (b.t_s[0], b.t_s[-1]), a.label
        if a not in view.heading:  # its axis is 0-360 whatever it holds
            assert (np.nanmin(a.v), np.nanmax(a.v)) == (np.nanmin(b.v), np.nanmax(b.v)), a.label
        assert set(zip(a.t_s.tolist(), a.v.tolist(), strict=True)) <= set(
            zip(b.t_s.tolist(), b.v.tolist(), strict=True)
        ), a.label  # a sample of the series, not new points
    assert max(view.hdop[0].v) == 42.0
    assert [s.label for s in view.error] == ["GPS fix", "position estimate"]
    assert [s.t_s[np.argmax(s.v)] for s in view.error] == [EPOCHS / 2, EPOCHS / 2 + 0.5]
    for label, (e, n) in view.track.items():
        we, wn = whole.track[label]
        assert (e.min(), e.max(), n.min(), n.max()) == (we.min(), we.max(), wn.min(), wn.max())
    assert [h.to_json() for h in view.holds] == [h.to_json() for h in whole.holds]
    assert [h.label for h in view.holds] == ["gps stale", "no valid fix"]
    assert logview.panel_svgs(view)["holds"] == logview.panel_svgs(whole)["holds"]


def test_a_sample_keeps_its_first_last_and_extremes() -> None:
    sample = logview._Sample(lambda r: r[1])
    sample._limit = 8
    rows = [(i, float((i * 37) % 101)) for i in range(1000)]
    for r in rows:
        sample.add(r)
    kept = sample.rows()
    assert sample.held() <= 8 + 1 + 2 and len(kept) <= 8 + 1 + 2
    assert kept[0] == rows[0] and kept[-1] == rows[-1]
    assert kept == sorted(kept)  # file order
    assert min(r[1] for r in kept) == 0.0 and max(r[1] for r in kept) == 100.0
    # a series no longer than the sample is kept whole
    whole = logview._Sample(lambda r: r[1])
    for r in rows[:300]:
        whole.add(r)
    assert whole.rows() == rows[:300]
