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


def _reference_figures(
    world: object,
    epochs: dict[int, tuple[float, float, float, float]],
    rows: list[tuple[int, float, float, float | None, float | None]],
    east: list[float],
    north: list[float],
    dt_s: float,
    arrival_t: list[float],
) -> dict[str, object]:
    """The figures as run_mission computed them before the packed columns: an epoch dict,
    fix tuples, whole-run copies of the path (issue 16's reference)."""
    from sim_backend.geodesy import lla_to_enu
    from sim_backend.runs import dispersion_m

    o = world.origin  # type: ignore[attr-defined]
    truth = np.array([epochs[r[0]][:2] for r in rows])
    raw = np.array([[r[1], r[2]] for r in rows])
    filt = np.array(
        [[math.nan, math.nan] if r[3] is None or r[4] is None else [r[3], r[4]] for r in rows]
    )
    z = np.full(len(rows), o.alt_m)
    raw_enu = np.asarray(lla_to_enu(raw[:, 0], raw[:, 1], z, o.lat_deg, o.lon_deg, o.alt_m))
    filt_enu = np.asarray(lla_to_enu(filt[:, 0], filt[:, 1], z, o.lat_deg, o.lon_deg, o.alt_m))
    t_ep = np.array([r[0] * dt_s for r in rows])
    err = raw_enu[:, :2] - truth
    slow = []
    for t in arrival_t:
        near = np.abs(t_ep - t) <= mission.SLOW_ERROR_WINDOW_S
        slow.append(float(np.hypot(*err[near].mean(axis=0))))
    tll = np.array([epochs[r[0]][2:] for r in rows])
    e, n = np.array(east), np.array(north)
    return {
        "raw_err": np.hypot(raw_enu[:, 0] - truth[:, 0], raw_enu[:, 1] - truth[:, 1]),
        "filt_err": np.hypot(filt_enu[:, 0] - truth[:, 0], filt_enu[:, 1] - truth[:, 1]),
        "fix_enu": raw_enu[:, :2],
        "filt_enu": filt_enu[:, :2],
        "slow": slow,
        "dispersion": dispersion_m(
            np.array([r[1] for r in rows]) - tll[:, 0], np.array([r[2] for r in rows]) - tll[:, 1]
        ),
        "path": float(np.sum(np.hypot(np.diff(e), np.diff(n)))),
    }


def test_packed_epochs_and_fixes_give_the_figures_of_the_tuples(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Issue 16: the per-epoch truth and the per-fix rows are packed columns (NaN for a
    missing filtered position), the path length is summed from steps computed in chunks.
    Every figure is the float the dict of epochs, the fix tuples and the whole-run arrays
    gave, bit for bit: errors, positions, slow errors, dispersion, path, HDOP, satellites."""
    from types import SimpleNamespace

    from x6wd.core.records import GpsFix

    world = load_world(OPEN_FIELD)
    o = world.origin
    rng = np.random.default_rng(7)
    gps_every, dt_s = 3, 0.05
    trace = mission._Trace(gps_every=gps_every)
    east: list[float] = []
    north: list[float] = []
    epochs: dict[int, tuple[float, float, float, float]] = {}
    rows: list[tuple[int, float, float, float | None, float | None]] = []
    hdop: list[float] = []
    sats: list[int] = []
    e = n = 0.0
    for k in range(20_001):
        e += float(rng.normal(0.02, 0.03))
        n += float(rng.normal(0.0, 0.03))
        east.append(e)
        north.append(n)
        trace.east.append(e)
        trace.north.append(n)
        if k % gps_every:
            continue
        lat = o.lat_deg + n / 111_000.0
        lon = o.lon_deg + e / 69_000.0
        epochs[k] = (e, n, lat, lon)
        trace.add_epoch(k, e, n, lat, lon)
        if rng.random() < 0.2:  # no fix decoded for this epoch
            continue
        valid = rng.random() > 0.05
        flat: float | None = lat + float(rng.normal(0, 1e-5))
        flon: float | None = lon + float(rng.normal(0, 1e-5))
        if rng.random() < 0.1:  # no filtered position (the EKF not started, or one missing)
            flat, flon = (None, flon) if rng.random() < 0.5 else (None, None)
        fix = GpsFix(
            t_s=k * dt_s,
            lat_deg=lat + float(rng.normal(0, 3e-5)),
            lon_deg=lon + float(rng.normal(0, 3e-5)),
            valid=valid,
            hdop=None if rng.random() < 0.1 else round(float(rng.uniform(0.7, 2.5)), 2),
            sats_used=None if rng.random() < 0.1 else int(rng.integers(4, 12)),
        )
        mission._note_fix(trace, k, fix, SimpleNamespace(filt_lat_deg=flat, filt_lon_deg=flon))  # type: ignore[arg-type]
        if valid:
            assert fix.lat_deg is not None and fix.lon_deg is not None
            rows.append((k, fix.lat_deg, fix.lon_deg, flat, flon))
            if fix.hdop is not None:
                hdop.append(fix.hdop)
            if fix.sats_used is not None:
                sats.append(fix.sats_used)
    assert trace.fixes > trace.fixes_valid == len(rows) > 4000
    assert any(r[3] is None and r[4] is not None for r in rows)
    arrival_t = [100.0, 333.3, 712.05]
    want = _reference_figures(world, epochs, rows, east, north, dt_s, arrival_t)

    def same(a: object, b: object) -> bool:
        return np.array_equal(np.asarray(a), np.asarray(b), equal_nan=True)

    raw_err, filt_err, fix_enu, filt_enu = mission._errors(world, trace)
    assert same(raw_err, want["raw_err"]) and same(filt_err, want["filt_err"])
    assert same(fix_enu, want["fix_enu"]) and same(filt_enu, want["filt_enu"])
    assert np.isnan(filt_err).sum() == sum(r[3] is None or r[4] is None for r in rows) > 0
    arrivals = mission._with_slow_error([{"t_s": t} for t in arrival_t], world, trace, dt_s)
    assert [a["gps_slow_error_m"] for a in arrivals] == want["slow"]
    assert mission._dispersion(trace) == want["dispersion"]
    assert float(np.mean(mission._col(trace.hdop))) == float(np.mean(hdop))
    assert float(np.mean(mission._col(trace.sats, np.int64))) == float(np.mean(sats))
    k = rows[123][0]
    assert trace.epoch_en(k) == epochs[k][:2]
    # the path: steps in chunks of 7 and of the default size, one np.sum over them
    assert mission._path_length_m(trace) == want["path"]
    monkeypatch.setattr(mission, "PATH_CHUNK_TICKS", 7)
    assert mission._path_length_m(trace) == want["path"]
    with pytest.raises(ValueError, match="out of order"):
        trace.add_epoch(k, 0.0, 0.0, 0.0, 0.0)
