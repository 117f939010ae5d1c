"""A log faster than the analysis rate is read at it (x6wd.gap.rate): one hour at 20 Hz passed
1 GB and 7 minutes when every epoch was simulated and read (outside audit, 2026-12-05). The
peak memory of the hour is a benchmark's (bench/bench_gap_memory.py); here a 10-minute
20 Hz log is read at 2 Hz, its runs simulated at 2 Hz, and the report says so (13 s; 47 s
with every epoch read, and both diagnosis tests fail then)."""

from __future__ import annotations

import json
import math
from datetime import UTC, datetime, timedelta
from pathlib import Path

import numpy as np
import pytest

from drivers.nmea import sentence
from sim_backend.effects import PositionSeries, truth_track_m
from x6wd.app.cli import main as x6wd_main
from x6wd.core.errors import ConfigError
from x6wd.gap.cli import DEFAULT_SCENARIO
from x6wd.gap.diagnose import diagnose
from x6wd.gap.rate import (
    MAX_ANALYSIS_HZ,
    at_analysis_rate,
    at_step,
    baseline_at,
    decimation_factor,
)
from x6wd.gap.scenario import scenario_baseline

LAT0, LON0 = 44.0689, -121.3143


def _nmea_log(path: Path, rate_hz: float, seconds: float, seed: int = 1) -> Path:
    """A static receiver's RMC + GGA at ``rate_hz``: a 60 s, 1.5 m Gauss-Markov wander."""
    rng = np.random.default_rng(seed)
    n = round(seconds * rate_hz)
    phi = math.exp(-1.0 / (rate_hz * 60.0))
    e = n_m = 0.0
    lines = []
    for k in range(n):
        e = phi * e + math.sqrt(1 - phi * phi) * 1.5 * rng.standard_normal()
        n_m = phi * n_m + math.sqrt(1 - phi * phi) * 1.5 * rng.standard_normal()
        t = datetime(2020, 1, 3, 20, tzinfo=UTC) + timedelta(seconds=k / rate_hz)
        hms = f"{t:%H%M%S}.{t.microsecond // 10000:02d}"
        lat, lon = LAT0 + n_m / 111320.0, LON0 + e / (111320.0 * math.cos(math.radians(LAT0)))
        la = f"{int(lat):02d}{(lat - int(lat)) * 60:08.5f},N"
        lo = f"{int(-lon):03d}{(-lon - int(-lon)) * 60:08.5f},W"
        lines.append(sentence(f"GPRMC,{hms},A,{la},{lo},0.0,,030120,,,A"))
        lines.append(sentence(f"GPGGA,{hms},{la},{lo},1,08,1.0,1144.8,M,-21.4,M,,"))
    path.write_bytes(b"".join(lines))
    return path


def _series(rate_hz: float, seconds: float, moving: bool = False) -> PositionSeries:
    n = round(seconds * rate_hz)
    t_s = 1000.0 + np.arange(n) / rate_hz
    rng = np.random.default_rng(0)
    return PositionSeries(
        t_s=t_s,
        east_m=rng.standard_normal(n),
        north_m=rng.standard_normal(n),
        up_m=np.zeros(n),
        valid=np.ones(n, dtype=bool),
        speed_mps=np.full(n, 3.0) + np.sin(t_s) if moving else None,
        course_deg=(t_s * 7.0) % 360.0 if moving else None,
    )


@pytest.mark.parametrize(
    ("rate_hz", "factor"), [(1.0, 1), (2.0, 1), (4.0, 2), (5.0, 3), (10.0, 5), (20.0, 10)]
)
def test_the_analysis_step_is_the_first_multiple_of_the_logs_at_most_the_bounded_rate(
    rate_hz: float, factor: int
) -> None:
    assert decimation_factor(1.0 / rate_hz) == factor
    assert rate_hz / factor <= MAX_ANALYSIS_HZ + 1e-9


def test_a_1_hz_log_is_read_as_it_is() -> None:
    real = _series(1.0, 600.0)
    base = [_series(1.0, 600.0)]
    out, runs, notes = baseline_at(real, base)
    assert out is real and runs[0] is base[0] and notes == []


def test_a_20_hz_log_keeps_its_own_epochs_at_2_hz_and_its_true_track() -> None:
    real = _series(20.0, 120.0, moving=True)
    out, note = at_analysis_rate(real)
    assert note is not None and "read at 2 Hz of its 20 Hz" in note
    assert len(out) == 240
    np.testing.assert_allclose(np.diff(out.t_s), 0.5, atol=1e-9)
    # stamps and values are the log's own (no averaging)
    idx = np.searchsorted(real.t_s, out.t_s)
    np.testing.assert_array_equal(real.t_s[idx], out.t_s)
    np.testing.assert_array_equal(real.east_m[idx], out.east_m)
    # the true track is the one integrated at 20 Hz, carried
    np.testing.assert_allclose(truth_track_m(out)[0], truth_track_m(real)[0][idx])
    # a baseline log at 10 Hz is read at the real log's analysis step
    np.testing.assert_allclose(np.diff(at_step(_series(10.0, 120.0), 0.5).t_s), 0.5)


def test_a_log_whose_rate_falls_keeps_its_fixes() -> None:
    # A code review: 20 Hz from .05 s for 100 s, then 1 Hz on whole seconds, the gaps filled
    # with fixless epochs at 20 Hz (as the reader does): every 10th slot from the first was
    # a fixless one, and all 600 fixes of the 1 Hz part were lost.
    fast_s = 0.05 + np.arange(2000) * 0.05
    filled_s = 100.05 + np.arange(12000) * 0.05
    t_s = np.concatenate((fast_s, filled_s))
    valid = np.concatenate((np.ones(2000, bool), np.isclose(filled_s % 1.0, 0.0, atol=1e-6)
                            | np.isclose(filled_s % 1.0, 1.0, atol=1e-6)))  # fmt: skip
    assert valid[2000:].sum() == 600
    n = len(t_s)
    real = PositionSeries(t_s=t_s, east_m=np.zeros(n), north_m=np.zeros(n), up_m=np.zeros(n),
                          valid=valid)  # fmt: skip
    out, note = at_analysis_rate(real)
    assert note is not None
    assert int(np.asarray(out.valid)[out.t_s > 100.0].sum()) == 600
    assert int(np.asarray(out.valid)[out.t_s < 100.0].sum()) == 200  # 2 Hz of the 20 Hz part
    assert np.all(np.diff(out.t_s) > 0.0)


def test_a_3_hz_log_stamped_to_a_hundredth_keeps_even_steps() -> None:
    # .00, .33, .67 against a 0.33 s median: slots counted from the first epoch gained one
    # every 100 epochs, and each left a 1-s hole (109 an hour)
    t_s = np.round(np.arange(3 * 3600) / 3.0, 2)
    n = len(t_s)
    real = PositionSeries(t_s=t_s, east_m=np.zeros(n), north_m=np.zeros(n), up_m=np.zeros(n),
                          valid=np.ones(n, bool))  # fmt: skip
    out, _note = at_analysis_rate(real)
    assert len(out) == n // 2
    assert float(np.max(np.diff(out.t_s))) <= 0.68


def test_a_20_hz_log_too_short_at_the_analysis_rate_says_so() -> None:
    # 20 s at 20 Hz: 400 epochs, 40 at 2 Hz
    with pytest.raises(ConfigError, match=r"400 epochs \(400 with a fix\) 0.05 s apart .* are 40"):
        diagnose(_series(20.0, 20.0), [_series(20.0, 20.0)], np.random.default_rng(0))
    # enough epochs but too few fixes at 2 Hz: named with the rate too (a code review: a
    # bare "too few fixes: 58 of 1200" left the 2 Hz reading out)
    sparse = _series(20.0, 600.0)
    sparse = sparse.with_(valid=np.arange(len(sparse)) % 400 == 0)  # 30 fixes
    with pytest.raises(ConfigError, match=r"12000 epochs \(30 with a fix\).* are 1200 \(30 with"):
        diagnose(sparse, [_series(20.0, 600.0)], np.random.default_rng(0))


def test_the_runs_of_a_20_hz_template_are_simulated_at_2_hz() -> None:
    template = _series(20.0, 120.0).with_(origin_lat_deg=LAT0, origin_lon_deg=LON0)
    (run,) = scenario_baseline(DEFAULT_SCENARIO, template, 1)
    np.testing.assert_array_equal(run.t_s, at_analysis_rate(template)[0].t_s)
    assert len(run) == 240


def test_a_20_hz_log_is_diagnosed_at_2_hz_with_runs_simulated_at_2_hz(tmp_path: Path) -> None:
    log = _nmea_log(tmp_path / "r20.nmea", 20.0, 600.0)
    out = tmp_path / "out"
    argv = ["gap", "--real", str(log), "--seeds", "2", "--no-figures", "--quiet",
            "--out", str(out)]  # fmt: skip
    assert x6wd_main(argv) in (0, 1)
    report = (out / "report.md").read_text()
    assert "log: 600 s at 0.5 s steps" in report  # the time axis is the kept epochs'
    assert "the log was read at 2 Hz of its 20 Hz (one epoch in 10: 1200 of 12000" in report
    data = json.loads((out / "report.json").read_text())
    assert data["verdict"]["status"]
