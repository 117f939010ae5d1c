"""Gap tool, session of 2026-12-08: a receiver latency on a route that stops and turns, and
what the files hold when the selection does not explain the gap.

The audit of 2026-12-07 (round 23): a zigzag mission's 234 s log with every position 2 s late,
against three other seeds as ``--sim``, read "borderline ... not explained (best: correction
0.43)". The latency was fitted as 1.5-1.6 s (its regressor -d v(t) misses the start and end
of every leg), then refused as an "overshoot" (closure 2.1 against the baseline's floor,
while its runs, alike in the same delay on the same route, sat at G 0.36 of each other); and
effects.toml and calibrated.toml held the correction, a factor of 8.35 that put the
simulated mean error at +399 %.
"""

from __future__ import annotations

import dataclasses
import json
import tomllib
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from sim_backend.effects import (
    GaussMarkov,
    Latency,
    NoiseScale,
    PositionSeries,
    Quantization,
    apply_effects,
)
from tests.test_gap_verdict_round3 import _log as _static_log
from x6wd.gap.diagnose import Diagnosis, GpsPipeline, Options, diagnose
from x6wd.gap.drift import fit_latency
from x6wd.gap.fitted import Fit
from x6wd.gap.null import loo_gaps
from x6wd.gap.pipeline import Option
from x6wd.gap.report import effects_toml, write_report
from x6wd.gap.stats import Cell, layout_for
from x6wd.gap.surrogate import BASELINE_EFFECTS

PRE = BASELINE_EFFECTS[:-1]  # the baseline before NMEA printing


def _stop_and_go(duration_s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Times (s), speed (m/s) and course (deg) of a robot's square: 20 s legs at 1 m/s, a
    6 s stop to pivot 90 degrees between them (the shape of the robot's waypoint missions)."""
    t_s = np.arange(0.0, duration_s + 0.5, 1.0)
    phase_s = np.mod(t_s, 26.0)
    speed_mps = np.where(phase_s < 20.0, 1.0, 0.0)
    course_deg = np.mod(90.0 * np.floor(t_s / 26.0), 360.0)
    return t_s, speed_mps, course_deg


def _moving_log(seed: int, *layers: object, duration_s: float = 1200.0) -> PositionSeries:
    t_s, speed_mps, course_deg = _stop_and_go(duration_s)
    zeros = np.zeros(t_s.size)
    series = PositionSeries(
        t_s=t_s, east_m=zeros, north_m=zeros, up_m=zeros, valid=np.ones(t_s.size, dtype=bool),
        origin_lat_deg=51.712345, origin_lon_deg=19.487654,
        speed_mps=speed_mps, course_deg=course_deg,
    )  # fmt: skip
    effects = [*PRE, *layers, Quantization(5)]
    return apply_effects(series, effects, np.random.default_rng(seed))


@pytest.mark.parametrize("delay_s", [2.0, 4.0])
def test_a_latency_on_a_route_that_stops_and_turns_is_fitted_near_its_delay(
    delay_s: float,
) -> None:
    # Before: the regressor -d v(t) alone gave 1.5-1.6 s for 2 s and 1.9-2.3 s for 4 s on the
    # audit's zigzag; now the regressor is the exact error of the delay fitted last.
    base = [_moving_log(900 + i) for i in range(6)]
    real = _moving_log(11, Latency(delay_s))
    fit = fit_latency(real, base, layout_for(real))
    assert fit is not None
    got_s, se_s = fit.params["delay_s"], fit.se["delay_s"]
    assert abs(got_s - delay_s) < max(3.0 * se_s, 0.1 * delay_s), (got_s, se_s)


def test_a_pooled_null_leaves_each_run_out_with_all_its_draws() -> None:
    # 4 draws of an effect that changes nothing are 4 copies of each run: scored against its
    # own copies a run's G fell, and the floor with it (the review of 2026-12-08)
    rng = np.random.default_rng(5)
    cells = [Cell("adev", "east", f"tau={i}s") for i in range(60)]
    one = rng.normal(size=(8, 60))
    pooled = np.tile(one, (4, 1))
    floor_one = float(np.mean(loo_gaps(one, cells)))
    floor_grouped = float(np.mean(loo_gaps(pooled, cells, groups=8)))
    floor_rows = float(np.mean(loo_gaps(pooled, cells)))
    assert abs(floor_grouped - floor_one) < 0.15 * floor_one, (floor_grouped, floor_one)
    assert floor_rows < 0.7 * floor_one  # what leaving out one row at a time gave
    # one draw: the grouping is each row alone, as before
    assert np.array_equal(loo_gaps(one, cells, groups=8), loo_gaps(one, cells))


def _option(effect: object, g_fits: float, null: object) -> Option:
    fit = Fit(effect)
    return Option(fit, g_fits, g_fits, null, [fit], g_fits)  # type: ignore[arg-type]


def test_an_effect_is_judged_past_the_floor_of_its_own_runs() -> None:
    # The audit's figures: G 1.97 against a floor of 0.97; the latency took the held-out G to
    # -0.13, and its runs' own floor was 0.36 (an overshoot only below 0.36 - 1.00)
    pipe = GpsPipeline(Options(), np.random.default_rng(0))
    pipe.fresh_draws = 0  # type: ignore[misc]
    pipe.split = SimpleNamespace(  # type: ignore[assignment]
        g_baseline=1.97, g_floor=0.97, ref_sd_test=None
    )
    own = SimpleNamespace(n_runs=3, floor=lambda ref_sd, groups: 0.36)
    latency = _option(Latency(1.6), g_fits=-0.13, null=own)
    best, g_new = pipe._first_to_enter([latency], [], 1.97, 0)
    assert best is latency and g_new == -0.13, pipe.passed_over
    # runs as spread as the baseline's (their floor 0.97): the same G is an overshoot
    pipe.passed_over = {}
    alike = SimpleNamespace(n_runs=3, floor=lambda ref_sd, groups: 0.97)
    spread = _option(Latency(1.6), g_fits=-0.13, null=alike)
    assert pipe._first_to_enter([spread], [], 1.97, 0)[0] is None
    (reason,) = pipe.passed_over["latency"]
    assert "it overshot: closure 2.10" in reason and "the runs with it, 0.97" in reason


# a drifting receiver with half the model's fast noise, the noise scale alone the candidate:
# it closes 0.45 of the held-out gap (partly explained); _static_log: round 3's 900 s log


@pytest.fixture(scope="module")
def partly() -> Diagnosis:
    base = [_static_log(700 + i) for i in range(8)]
    real = _static_log(11, GaussMarkov(3.0, 60.0), NoiseScale(0.5, 10.0))
    d = diagnose(real, base, np.random.default_rng(0), Options(candidates=("noise_scale",)))
    assert d.selected and not d.explained, (d.selected, d.closure)  # the case itself
    return d


@pytest.mark.slow
def test_a_selection_that_does_not_explain_the_gap_is_not_written(
    partly: Diagnosis, tmp_path: Path
) -> None:
    assert partly.written == []
    text = effects_toml(partly)
    assert "effects" not in tomllib.loads(text), text  # nothing a scenario would take in
    assert "# not written: GPS noise_scale, the best candidate" in text
    assert '#~ [[effects]]\n#~ name = "noise_scale"' in text  # there to uncomment
    # calibrated.toml holds the level layers alone, fitted against the baseline runs alone
    c = partly.calibration
    assert c is not None and partly.validation is c.selected
    calibrated_text = effects_toml(partly, calibrated=True)
    calibrated = tomllib.loads(calibrated_text)
    assert [e["name"] for e in calibrated.get("effects", [])] == [f.name for f in c.layers]
    # named there, not offered: its level was fitted without it (no untested mix to uncomment)
    assert "# not written: GPS noise_scale" in calibrated_text
    assert "#~ " not in calibrated_text
    v = partly.candidate_validation
    assert v is not None and v.mean_sim_m != c.selected.mean_sim_m
    write_report(partly, tmp_path, figures=False)
    md = (tmp_path / "report.md").read_text()
    assert "The selection does not explain the gap" in md
    assert "The best candidate, noise_scale, is not written (held-out closure" in md
    assert "(a) the baseline runs alone (no effect written)" in md
    figures = json.loads((tmp_path / "validation.json").read_text())
    assert figures["candidate"]["figures"][0]["simulated"] == pytest.approx(v.mean_sim_m, 1e-5)
    # the same selection explaining the gap is written, live
    explained = dataclasses.replace(partly, closure=0.9)
    live = tomllib.loads(effects_toml(explained))
    assert [e["name"] for e in live["effects"]] == ["noise_scale"]


# --- the audit's own path: a mission log 2 s late against three other seeds as --sim ---------

POSITION_FIELDS = {"GGA": (1, 2, 6), "RMC": (1, 3, 7), "GLL": (5, 1, 5)}  # time, lat..lon end


def _late(nmea: str, delay_epochs: int) -> str:
    """The log with every sentence's position replaced by its type's position
    ``delay_epochs`` epochs earlier (the first epochs keep the first position)."""
    lines = nmea.splitlines()
    positions: dict[str, list[list[str]]] = {}
    for line in lines:
        fields = line.split("*")[0].split(",")
        kind = fields[0][3:]
        if kind in POSITION_FIELDS:
            _, lo, hi = POSITION_FIELDS[kind]
            positions.setdefault(kind, []).append(fields[lo:hi])
    seen: dict[str, int] = {}
    out = []
    for line in lines:
        fields = line.split("*")[0].split(",")
        kind = fields[0][3:]
        if kind in POSITION_FIELDS and "*" in line:
            _, lo, hi = POSITION_FIELDS[kind]
            i = seen.get(kind, 0)
            seen[kind] = i + 1
            fields[lo:hi] = positions[kind][max(i - delay_epochs, 0)]
            body = ",".join(fields)[1:]
            checksum = 0
            for ch in body.encode():
                checksum ^= ch
            line = f"${body}*{checksum:02X}"
        out.append(line)
    return "\r\n".join(out) + "\r\n"


@pytest.mark.slow
def test_a_mission_log_two_seconds_late_is_named_latency(tmp_path: Path) -> None:
    from x6wd.app.cli import main as x6wd_main

    zigzag = Path(__file__).resolve().parents[1] / "config" / "scenarios" / "zigzag.toml"
    for seed in (201, 202, 203, 204):
        argv = ["sim", str(zigzag), "--out", str(tmp_path / f"zz{seed}"), "--seed", str(seed)]
        assert x6wd_main([*argv, "--quiet"]) == 0
    late = tmp_path / "late.nmea"
    late.write_text(_late((tmp_path / "zz201" / "gps.nmea").read_text(), 2), newline="")
    sims = [str(tmp_path / f"zz{seed}" / "gps.nmea") for seed in (202, 203, 204)]
    out = tmp_path / "gap"
    argv = ["gap", "--real", str(late), "--sim", *sims, "--out", str(out), "--no-figures"]
    argv += ["--truth-track", str(tmp_path / "zz201" / "truth.csv"), "--quiet"]
    assert x6wd_main(argv) == 0
    verdict = json.loads((out / "report.json").read_text())["verdict"]
    assert verdict["effect"] == "latency" and verdict["explained"], verdict
    (effect,) = tomllib.loads((out / "effects.toml").read_text())["effects"]
    assert effect["name"] == "latency" and abs(effect["delay_s"] - 2.0) < 0.3, effect
