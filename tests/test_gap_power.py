"""The gap tool's power devices (issue 15, item 2): the "where" test's weighted levels and the
jumps read between satellite-set changes."""

from __future__ import annotations

import math

import numpy as np
import pytest

from sim_backend.effects import Jumps, PositionSeries, apply_effects
from x6wd.gap.jumps import fit_jumps
from x6wd.gap.null import cell_shares, null_model
from x6wd.gap.stats import (
    PRIMARY_SHARE,
    Cell,
    battery,
    cell_weights,
    is_primary,
    layout_for,
    steady_jump_count,
    steady_steps,
)
from x6wd.gap.surrogate import BASELINE_EFFECTS, surrogate_run

PRE = BASELINE_EFFECTS[:-1]
HOUR_S = 3600.0


def _flickering_nsats(n: int, rng: np.random.Generator) -> np.ndarray:
    """A satellites-used count that changes every ~10 s (low satellites fading in and out),
    as the GNSS model's does."""
    nsats = np.empty(n)
    value = 8.0
    for i in range(n):
        if rng.random() < 0.1:
            value = float(np.clip(value + rng.choice([-1.0, 1.0]), 5, 11))
        nsats[i] = value
    return nsats


def _log(seed: int, *effects: object) -> PositionSeries:
    """An hour whose solution steps at every satellite-set change (each set its own offset,
    0.9 m), like the GNSS model's, plus ``effects``; printed with 5 decimals."""
    from sim_backend.effects import Quantization

    rng = np.random.default_rng(seed)
    base = surrogate_run(HOUR_S, 1.0, rng, effects=[])
    base = base.with_(nsats=_flickering_nsats(len(base), rng))
    layers = [*PRE, Jumps(0.9, trigger="sat_change"), *effects, Quantization(5)]
    return apply_effects(base, layers, rng)


@pytest.fixture(scope="module")
def set_change_baseline() -> list[PositionSeries]:
    return [_log(500 + i) for i in range(6)]


def test_steady_steps_leave_out_the_steps_at_satellite_changes() -> None:
    real = _log(1)
    steps_m, _end, steady = steady_steps(real, 1.0)
    nsats = np.asarray(real.nsats)
    assert steps_m.shape[0] == len(real) - 1
    assert np.array_equal(steady, nsats[1:] == nsats[:-1])
    radial = np.hypot(*steps_m.T)
    # the big steps are where the set changes; between changes the steps are small
    assert np.quantile(radial[~steady], 0.9) > 3 * np.quantile(radial[steady], 0.9)
    # without counts every step is steady
    assert np.all(steady_steps(real.with_(nsats=None), 1.0)[2])


def test_the_steady_jump_count_sees_jumps_the_satellite_count_does_not_explain() -> None:
    nulls = [steady_jump_count(_log(10 + i), 1.0) for i in range(4)]
    jumpy = [
        steady_jump_count(_log(10 + i, Jumps(1.2, 0.004, trigger="poisson")), 1.0) for i in range(4)
    ]
    assert max(nulls) <= 3
    assert min(jumpy) >= 5 and np.mean(jumpy) > 3 * max(np.mean(nulls), 1.0)
    # counted among all steps (no satellite counts), the set changes swamp them
    blind = [steady_jump_count(_log(10 + i).with_(nsats=None), 1.0) for i in range(4)]
    assert min(blind) > max(jumpy)


def test_jump_fit_reads_jumps_between_satellite_changes(
    set_change_baseline: list[PositionSeries],
) -> None:
    lay = layout_for(set_change_baseline[0])
    sigmas, rates = [], []
    for seed in (21, 22, 23):
        real = _log(seed, Jumps(1.2, 0.004, trigger="poisson"))
        fit = fit_jumps(real, set_change_baseline, lay)
        assert fit is not None and fit.params["trigger"] == "poisson"
        sigmas.append(fit.params["sigma_m"])
        rates.append(fit.params["rate_per_s"])
        # among all steps (no satellite counts) the set changes' own steps hide them
        blind = [s.with_(nsats=None) for s in set_change_baseline]
        assert fit_jumps(real.with_(nsats=None), blind, lay) is None
    # about 14 jumps an hour, a few of them hidden on set changes: within 35 % on average
    assert float(np.mean(sigmas)) == pytest.approx(1.2, rel=0.35)
    assert float(np.mean(rates)) == pytest.approx(0.004, rel=0.35)
    nulls = [fit_jumps(_log(seed), set_change_baseline, lay) for seed in (31, 32, 33, 34)]
    assert sum(f is not None and f.params["rate_per_s"] > 0.001 for f in nulls) <= 1


def test_weighted_levels_lower_the_primary_limits_and_keep_the_family_wise_level() -> None:
    rng = np.random.default_rng(5)
    cells = [Cell("mean", "east"), Cell("mean", "north")] + [
        Cell("acf", "east", f"lag={i}s") for i in range(60)
    ]
    weights = cell_weights(cells)
    assert weights[:2] == pytest.approx([PRIMARY_SHARE / 2] * 2)
    assert float(np.sum(cell_shares(weights))) == pytest.approx(1.0)
    rows = rng.standard_normal((20, len(cells)))
    batteries = [dict(zip(cells, row, strict=True)) for row in rows]
    even = null_model(batteries, 0.05)
    weighted = null_model(batteries, 0.05, weights=weights)
    assert np.all(weighted.limits()[:2] < even.limits()[:2] - 0.4)
    assert np.all(weighted.limits()[2:] > even.limits()[2:])
    assert weighted.limit_of(True) < weighted.limit_of(False)
    assert weighted.apart == 0
    # new draws of the same law: the family-wise false-alarm rate stays near alpha
    draws = rng.standard_normal((4000, len(cells)))
    for model in (even, weighted):
        z = (draws - model.mean) / model.sd
        alarms = np.mean(np.any(np.abs(z) > model.limits(), axis=1))
        assert alarms <= 0.08


def test_every_kind_of_gap_has_a_primary_cell() -> None:
    real = _log(3)
    cells = list(battery(real, layout_for(real)))
    primary = {c.statistic for c in cells if is_primary(c)}
    for statistic in ("mean", "log_psd", "steady_jumps", "availability", "log_step_std"):
        assert statistic in primary
    # the descriptive cells (octaves, lags, periods, the vertical) are not; the walk's
    # likelihood ratio only against independent runs (a few logs cannot estimate its null)
    assert not any(
        is_primary(c) for c in cells if c.statistic in ("log_adev", "acf") or c.axis == "up"
    )
    walk = Cell("random_walk_lr", "horizontal")  # added to the battery by the pipeline
    assert is_primary(walk) and not is_primary(walk, few_logs=True)
    with_walk = [*cells, walk]
    few = cell_weights(with_walk, few_logs=True)
    assert math.isclose(float(np.sum(few)), 1.0)
    assert few[-1] < cell_weights(with_walk)[-1]
    assert not any(is_primary(c) for c in cells if c.period != "all")
    assert math.isclose(float(np.sum(cell_weights(cells))), 1.0)


def test_satellite_sets_from_the_nmea_gsa_are_the_model_s(tmp_path) -> None:
    # `x6wd sim --seed 3`'s NMEA read back (GSA's used PRNs per epoch) gives the same set
    # identity as the scenario baseline of seed 3 computes from the model's own used mask
    import subprocess
    import sys

    from x6wd.gap.io import errors_vs_point, read_track
    from x6wd.gap.scenario import scenario_baseline

    scenario = "config/scenarios/open_field.toml"
    out = tmp_path / "sim"
    subprocess.run(
        [sys.executable, "-m", "x6wd", "sim", scenario, "--duration", "3600", "--seed", "3",
         "--out", str(out), "--quiet"],
        check=True, capture_output=True,
    )  # fmt: skip
    track = read_track(out / "gps.nmea")
    assert track.sat_set is not None and np.all(track.sat_set >= 0)
    real = errors_vs_point(track, 51.7520, -1.2577, 60.0)
    run = scenario_baseline(scenario, real, 1, base_seed=3)[0]
    assert run.sat_set is not None and real.sat_set is not None
    assert np.array_equal(run.sat_set, real.sat_set)
    same_set = np.diff(real.sat_set) == 0
    same_count = np.diff(np.asarray(real.nsats)) == 0
    assert np.count_nonzero(~same_set) > 5
    assert np.count_nonzero(~same_set & same_count) > 0  # swaps: a set change, the same count
    # steady means the same set (and count): a swap is not steady
    assert np.array_equal(steady_steps(real, 1.0)[2], same_set & same_count)


def _jumps_early(seed: int, until_s: float, sigma_m: float = 1.5, rate_per_s: float = 0.008):
    """A set-change log whose offset is redrawn at Poisson events before ``until_s`` only, and
    back to none after it: the gap lives in the log's first part."""
    rng = np.random.default_rng(seed + 1000)
    real = _log(seed)
    t_s = np.asarray(real.t_s)
    offset = np.zeros((2, t_s.size))
    events = np.cumsum(rng.exponential(1 / rate_per_s, 200))
    events = events[events < until_s]
    for start_s, stop_s in zip(events, [*events[1:], until_s], strict=True):
        inside = (t_s >= start_s) & (t_s < stop_s)
        offset[:, inside] = rng.normal(0.0, sigma_m, (2, 1))
    return real.with_(
        east_m=np.asarray(real.east_m) + offset[0], north_m=np.asarray(real.north_m) + offset[1]
    )


def test_a_gap_only_in_the_first_part_is_held_out_there(
    set_change_baseline: list[PositionSeries],
) -> None:
    # Jumps before 55 % of the hour only: the forward held-out part (the last 35 %) shows
    # no gap, so it could tell no effect from none (every closure 0). The reversed split
    # holds out the first 35 % (jumps) and fits on the last 60 % (jumps from 40 to 55 %).
    from x6wd.gap.diagnose import Options, diagnose, verdict_text

    runs = set_change_baseline + [_log(600 + i) for i in range(2)]
    real = _jumps_early(71, until_s=0.55 * HOUR_S)
    d = diagnose(real, runs, np.random.default_rng(0), Options())
    (fit0_s, _fit1_s), (test0_s, _test1_s) = d.split_s
    assert test0_s == 0.0 and fit0_s > 0.0  # the start is held out
    assert d.explained and d.selected[0].name == "jumps", verdict_text(d)


def test_the_gps_pipeline_weighs_the_walk_cell_by_its_null() -> None:
    """Against a few logs' replicates (spread factors set) the walk's likelihood ratio gets a
    descriptive cell's share, against simulator runs a primary one."""
    from x6wd.gap.diagnose import RW_LR_CELL, GpsPipeline, Options

    real = _log(3)
    cells = [*battery(real, layout_for(real)), RW_LR_CELL]
    pipe = GpsPipeline(Options(), np.random.default_rng(0))
    runs = pipe.cell_weights(cells)[-1]
    pipe.inflation = {("*", "*"): 1.0}
    assert pipe.cell_weights(cells)[-1] < 0.5 * runs
    assert pipe.level() == 0.01  # the few-logs level, 1 % as against runs


def test_a_flight_recordings_sky_records_give_the_nmea_s_satellite_sets(tmp_path) -> None:
    # The robot engine's recording keeps the decoder's sky records: read from them, the set
    # identity per fix is the one read from the same run's NMEA (its GSA)
    from x6wd.app.cli import main as x6wd_main
    from x6wd.gap.io import read_track

    out = tmp_path / "mission"
    argv = ["sim", "config/scenarios/default.toml", "--seed", "3", "--out", str(out), "--quiet"]
    assert x6wd_main(argv) == 0
    from_nmea = read_track(out / "gps.nmea").sat_set
    from_recording = read_track(out / "recording.jsonl").sat_set
    assert from_nmea is not None and from_recording is not None
    assert np.all(from_recording >= 0) and np.array_equal(from_recording, from_nmea)
