"""The compass half of the gap tool: verdicts on withheld compass effects and null pairs.

"Real" heading logs are the project's CMPS10 emulation driven along a robot's weaving
drive on rough sloped ground (every heading, both turn directions, varying pitch/roll) with
another seed, plus a compass layer the tool is not told about.

Tolerances: the fits' own standard errors (from the sim-vs-sim spread of the regression
cells, 600 s at 10 Hz) are about 0.02 deg for the declination, 0.02 uT for hard iron,
3e-4 for soft iron k, 0.003 for the tilt fraction and 0.005 s for the lag; the small-angle
starts are refined by a simulation fit, so what is left is mostly that noise. The bounds
below are a few standard errors plus a relative margin for the remaining model mismatch
(the effect is applied to a measured heading that already carries noise and the CMPS10 lag).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from sim_backend.compass import CompassErrors
from sim_backend.effects import (
    Declination,
    HardIron,
    HeadingLag,
    HeadingSeries,
    SoftIron,
    Tilt,
)
from x6wd.gap.compass import (
    CompassOptions,
    baseline_along,
    battery,
    compass_report_dict,
    diagnose_compass,
    drive_track,
    heading_error_deg,
    layout_for,
    read_heading_series,
    simulate_compass,
)
from x6wd.gap.null import null_model

T_S, DT_S = 600.0, 0.1
OPT = CompassOptions(ci_resamples=40)


@pytest.fixture(scope="module")
def truth() -> HeadingSeries:
    return drive_track(T_S, DT_S, np.random.default_rng(1))


@pytest.fixture(scope="module")
def baseline(truth: HeadingSeries) -> list[HeadingSeries]:
    return [simulate_compass(truth, np.random.default_rng(100 + i)) for i in range(10)]


def real_with(truth: HeadingSeries, *effects: object, seed: int = 7) -> HeadingSeries:
    s = simulate_compass(truth, np.random.default_rng(seed))
    for e in effects:
        s = e.apply(s, np.random.default_rng(seed + 1))  # type: ignore[attr-defined]
    return s


def run(real: HeadingSeries, base: list[HeadingSeries], seed: int = 5) -> dict:
    return compass_report_dict(diagnose_compass(real, base, np.random.default_rng(seed), OPT))


def test_null_pairs_give_no_significant_gap(truth: HeadingSeries, baseline: list) -> None:
    for seed in (7, 8, 9):
        rep = run(real_with(truth, seed=seed), baseline, seed)
        assert rep["where"] == [] and rep["verdict"] == {"effect": None, "explained": True}


def test_baseline_runs_along_the_real_logs_inputs() -> None:
    # A recording has the true heading (truth.csv) and the registers' whole-degree pitch/roll,
    # never the continuous tilt: the baseline must be driven by exactly those, so that without
    # noise it reproduces the real log's heading error up to the bearing's 0.1-degree steps.
    quiet = CompassErrors(noise_ut=0.0)
    drive = drive_track(60.0, DT_S, np.random.default_rng(3))
    real = simulate_compass(drive, np.random.default_rng(0), errors=quiet)
    assert not np.allclose(real.pitch_deg, drive.pitch_deg)  # the registers rounded the tilt
    (base,) = baseline_along(real, 1, errors=quiet)
    for k in ("t_s", "true_heading_deg", "pitch_deg", "roll_deg"):
        assert np.array_equal(getattr(base, k), getattr(real, k)), k
    assert np.max(np.abs(heading_error_deg(base) - heading_error_deg(real))) <= 0.1 + 1e-9


def test_short_null_pairs_are_centred_and_within_the_threshold() -> None:
    # Null pairs built as the CLI builds them (another seed along the same drive, baseline
    # along the real log). A systematic real-vs-baseline mismatch shows as a shifted mean z
    # of some cell and as family-wise alarms above alpha. Bounds fixed from the null law, not
    # from these seeds: |mean z| < 4 standard errors per cell; at most 3 alarms in 16 pairs
    # (P(>= 4) = 0.007 at the nominal 5 %).
    n = 16
    zs, alarms = [], 0
    for k in range(n):
        drive = drive_track(60.0, DT_S, np.random.default_rng(300 + k))
        real = simulate_compass(drive, np.random.default_rng(400 + k))
        base = baseline_along(real, 10, base_seed=1000 + 20 * k)
        layout = layout_for(real)
        null = null_model([battery(s, layout) for s in base], OPT.alpha)
        z = null.z(battery(real, layout))
        zs.append(z)
        alarms += bool(np.max(np.abs(z)) > null.threshold)
    za = np.array(zs)
    se = za.std(axis=0, ddof=1) / np.sqrt(n)
    assert np.all(np.abs(za.mean(axis=0)) < 4 * np.maximum(se, 0.05)), dict(
        zip([f"{c.statistic}@{c.scale}" for c in null.cells], za.mean(axis=0), strict=True)
    )
    assert alarms <= 3


def test_hard_iron_identified_and_recovered(truth: HeadingSeries, baseline: list) -> None:
    rep = run(real_with(truth, HardIron(bx_ut=1.5, by_ut=-1.0)), baseline)
    assert rep["verdict"] == {"effect": "hard_iron", "explained": True}
    top = rep["effects"][0]
    assert top["params"]["bx_ut"] == pytest.approx(1.5, abs=0.1)
    assert top["params"]["by_ut"] == pytest.approx(-1.0, abs=0.1)
    assert top["closure"] >= 0.7
    # the field magnitude moves once per turn: hard iron's own signature
    assert any(w["statistic"].startswith("field_harmonic") for w in rep["where"])
    assert all(w["axis"] == "heading" for w in rep["where"])


def test_hard_iron_vs_tilt_told_apart_by_pitch_roll(truth: HeadingSeries, baseline: list) -> None:
    # Without the field magnitude (a recording has none) only the pitch/roll correlation
    # separates them: tilt moves the tilt gain, hard iron the once-per-turn harmonic.
    no_field = [s.with_(field_ut=None) for s in baseline]
    rep_t = run(real_with(truth, Tilt(fraction=0.25)).with_(field_ut=None), no_field)
    assert rep_t["verdict"] == {"effect": "tilt", "explained": True}
    assert rep_t["effects"][0]["params"]["fraction"] == pytest.approx(0.25, abs=0.02)
    assert {w["statistic"] for w in rep_t["where"]} >= {"tilt_gain"}
    assert "harmonic_cos" not in {w["statistic"] for w in rep_t["where"] if w["scale"] == "1/turn"}
    hard = next((e for e in rep_t["effects"] if e["name"] == "hard_iron"), None)
    assert hard is None or hard["closure"] <= 0.2

    rep_h = run(real_with(truth, HardIron(bx_ut=-2.0, by_ut=0.5)).with_(field_ut=None), no_field)
    assert rep_h["verdict"]["effect"] == "hard_iron"
    assert "tilt_gain" not in {w["statistic"] for w in rep_h["where"]}
    tilt = next((e for e in rep_h["effects"] if e["name"] == "tilt"), None)
    assert tilt is None or tilt["closure"] <= 0.2


@pytest.mark.slow
@pytest.mark.parametrize(
    ("effect", "key", "true", "tol"),
    [
        (SoftIron(k=0.03, axis_deg=20.0), "k", 0.03, 0.003),
        (Declination(declination_deg=1.5), "declination_deg", 1.5, 0.1),
        (HeadingLag(tau_s=0.3), "tau_s", 0.3, 0.05),
    ],
)
def test_other_effects_identified_and_recovered(
    truth: HeadingSeries, baseline: list, effect: object, key: str, true: float, tol: float
) -> None:
    rep = run(real_with(truth, effect), baseline)
    assert rep["verdict"] == {"effect": effect.name, "explained": True}  # type: ignore[attr-defined]
    assert rep["effects"][0]["params"][key] == pytest.approx(true, abs=tol)
    assert rep["effects"][0]["closure"] >= 0.7


def test_declination_identified(truth: HeadingSeries, baseline: list) -> None:
    rep = run(real_with(truth, Declination(declination_deg=-1.0)), baseline)
    assert rep["verdict"] == {"effect": "declination", "explained": True}
    assert rep["effects"][0]["params"]["declination_deg"] == pytest.approx(-1.0, abs=0.1)
    assert rep["where"][0]["statistic"] == "heading_mean"


def test_single_baseline_uses_block_bootstrap(truth: HeadingSeries, baseline: list) -> None:
    d = diagnose_compass(
        real_with(truth, HardIron(bx_ut=0.0, by_ut=2.0)),
        baseline[:1],
        np.random.default_rng(3),
        CompassOptions(ci_resamples=20, replicates=12),
    )
    assert d.bootstrap and len(d.baseline) == 12
    assert compass_report_dict(d)["verdict"]["effect"] == "hard_iron"


def _write_recording(path: Path, s: HeadingSeries, with_truth: bool, gps_seed: int = 0) -> None:
    """An x6wd recording: the compass samples as attitude records and, with ``gps_seed``,
    1 Hz fixes of a static NEO-5-like receiver (the GPS half needs them)."""
    from x6wd.core.recorder import Recorder
    from x6wd.core.records import Attitude
    from x6wd.gap.io import series_to_track
    from x6wd.gap.surrogate import surrogate_run

    gps = None
    if gps_seed:
        dur = float(s.t_s[-1])
        gps = series_to_track(surrogate_run(dur, 1.0, np.random.default_rng(gps_seed)), 60.0)
    with Recorder(path, clock=lambda: 0.0) as rec:
        for i in range(len(s)):
            t = float(s.t_s[i])
            rec.record_attitude(
                Attitude(t, float(s.heading_deg[i]), float(s.pitch_deg[i]), float(s.roll_deg[i]))
            )
            if gps is not None and i % 10 == 0 and i // 10 < len(gps):
                k = i // 10
                fix = {
                    "t_s": t,
                    "lat_deg": float(gps.lat_deg[k]),
                    "lon_deg": float(gps.lon_deg[k]),
                    "alt_m": float(gps.alt_m[k]),
                    "valid": True,
                    "sats_used": 8,
                    "speed_mps": 0.0,
                    "course_deg": None,
                }
                rec.record("fix", fix, t)
    if with_truth:
        assert s.true_heading_deg is not None
        rows = ["t_s,lat,lon,alt,heading_deg"] + [
            f"{t:.3f},51.75,-1.25,60.0,{h:.3f}"
            for t, h in zip(s.t_s, s.true_heading_deg, strict=True)
        ]
        (path.parent / "truth.csv").write_text("\n".join(rows) + "\n")


def test_recording_round_trip_with_truth_csv(tmp_path: Path, truth: HeadingSeries) -> None:
    s = simulate_compass(drive_track(60.0, 0.1, np.random.default_rng(2)), np.random.default_rng(1))
    _write_recording(tmp_path / "recording.jsonl", s, with_truth=True)
    back = read_heading_series(tmp_path / "recording.jsonl")
    assert back is not None and len(back) == len(s)
    assert np.allclose(heading_error_deg(back), heading_error_deg(s), atol=2e-3)
    (tmp_path / "truth.csv").unlink()
    # no truth.csv and no moving GPS fixes: no heading truth, no compass diagnosis
    assert read_heading_series(tmp_path / "recording.jsonl") is None
    assert json.loads(json.dumps(back.t_s.tolist()))[0] == 0.0


@pytest.mark.slow
def test_cli_merges_compass_into_the_report(tmp_path: Path) -> None:
    import tomllib

    from x6wd.app.cli import main as x6wd_main
    from x6wd.gap.surrogate import surrogate_run

    drive = drive_track(300.0, 0.1, np.random.default_rng(4))
    real = HardIron(bx_ut=0.0, by_ut=2.5).apply(
        simulate_compass(drive, np.random.default_rng(1)), np.random.default_rng(0)
    )
    (tmp_path / "real").mkdir()
    (tmp_path / "sim").mkdir()
    _write_recording(tmp_path / "real" / "recording.jsonl", real, True, gps_seed=11)
    sim = simulate_compass(drive, np.random.default_rng(2))
    # the same GPS log in both: the GPS half has no gap, the verdict is the compass one
    _write_recording(tmp_path / "sim" / "recording.jsonl", sim, True, gps_seed=11)
    s0 = surrogate_run(10.0, 1.0, np.random.default_rng(0))
    out = tmp_path / "rep"
    code = x6wd_main(
        ["gap", "--real", str(tmp_path / "real" / "recording.jsonl"),
         "--sim", str(tmp_path / "sim" / "recording.jsonl"),
         "--truth", f"{s0.origin_lat_deg},{s0.origin_lon_deg},60", "--replicates", "10",
         "--out", str(out), "--quiet"]
    )  # fmt: skip
    assert code == 0
    rep = json.loads((out / "report.json").read_text())
    assert set(rep) == {"gap", "where", "effects", "verdict"}
    assert set(rep["gap"]["heading"]) == {"baseline", "floor", "with_effects"}
    verdict = rep["verdict"]
    assert (verdict["effect"], verdict["explained"], verdict["status"]) == (
        "hard_iron",
        True,
        "explained",
    )
    # the compass half computes no closure interval: none, not [0, 0]
    assert verdict["halves"]["heading"]["closure_ci"] is None
    assert any(w["axis"] == "heading" for w in rep["where"])
    hard = next(e for e in rep["effects"] if e["name"] == "hard_iron")
    assert hard["params"]["by_ut"] == pytest.approx(2.5, abs=0.3)
    text = (out / "report.md").read_text()
    assert "## Compass (heading)" in text and "compass.png" in text
    assert (out / "compass.png").stat().st_size > 0
    toml = tomllib.loads((out / "effects.toml").read_text())
    assert [e["name"] for e in toml["effects"]] == ["hard_iron"]


def test_scenario_baseline_carries_the_scenarios_compass_effects(
    tmp_path: Path, truth: HeadingSeries
) -> None:
    from tests.conftest import ROOT
    from x6wd.gap.compass import scenario_compass_baseline

    plain = ROOT / "config" / "scenarios" / "default.toml"
    with_iron = tmp_path / "iron.toml"
    with_iron.write_text(
        f'include = ["{plain}"]\n\n[[effects]]\nname = "hard_iron"\nbx_ut = 4.0\nby_ut = 0.0\n'
    )
    short = truth.with_(**{k: getattr(truth, k)[:600] for k in ("t_s", "heading_deg",
                                                                 "pitch_deg", "roll_deg",
                                                                 "true_heading_deg")})  # fmt: skip
    (base,), _ = scenario_compass_baseline(plain, short, seeds=1)
    (iron,), _ = scenario_compass_baseline(with_iron, short, seeds=1)
    # 4 uT of hard iron in a 19 uT horizontal field: up to ~12 deg of error, once per turn
    expected = HardIron(4.0, 0.0).apply(base, np.random.default_rng(0))
    diff = np.abs(heading_error_deg(iron) - heading_error_deg(base))
    assert diff.max() > 6.0
    assert np.median(np.abs(((iron.heading_deg - expected.heading_deg) + 180) % 360 - 180)) < 1.5
