"""The sim-to-real gap tool: verdicts on null pairs, injected effects and real recordings."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from sim_backend.effects import Bias, GaussMarkov, PositionSeries, Quantization, metres_per_degree
from tests.conftest import dense_baseline_cov, filter_case
from x6wd.app.cli import main as x6wd_main
from x6wd.core.errors import ConfigError, ParseError
from x6wd.gap.diagnose import RW_LR_CELL, Options, diagnose, report_dict
from x6wd.gap.drift import fit_gauss_markov
from x6wd.gap.io import errors_vs_track, parse_truth, read_track, series_to_track, write_csv
from x6wd.gap.null import block_bootstrap, null_model
from x6wd.gap.stats import Cell, allan_var, battery, layout_for
from x6wd.gap.surrogate import BASELINE_EFFECTS, surrogate_run

HERE = Path(__file__).resolve().parent
STATIC = HERE / "data" / "static"
URBAN = HERE / "data" / "urban"
KK1446 = (39 + 49 / 60 + 17.99968 / 3600, -(105 + 5 / 60 + 42.64410 / 3600))  # htdp.txt, WGS84
PRE = BASELINE_EFFECTS[:-1]  # the baseline before NMEA printing
T_S = 1500.0


@pytest.fixture(scope="module")
def baseline() -> list:
    return [surrogate_run(T_S, 1.0, np.random.default_rng(100 + i)) for i in range(16)]


def real_with(*effects: object, seed: int = 7, quantize: bool = True) -> PositionSeries:
    tail = [Quantization(5)] if quantize else []
    return surrogate_run(T_S, 1.0, np.random.default_rng(seed), effects=[*PRE, *effects, *tail])


def test_null_pairs_give_no_significant_gap(baseline: list) -> None:
    for seed in (7, 8, 9):
        d = diagnose(real_with(seed=seed), baseline, np.random.default_rng(seed))
        rep = report_dict(d)
        assert rep["where"] == [] and rep["verdict"] == {"effect": None, "explained": True}


@pytest.mark.slow
def test_injected_gauss_markov_identified_with_parameters(baseline: list) -> None:
    d = diagnose(
        real_with(GaussMarkov(sigma_m=1.0, tau_s=30.0)), baseline, np.random.default_rng(1)
    )
    rep = report_dict(d)
    assert rep["verdict"] == {"effect": "gauss_markov", "explained": True}
    p, se = rep["effects"][0]["params"], d.selected[0].se
    # One log is one draw: each parameter within 2.5 of its standard errors, and those fine
    # enough for the tolerances (tau 30 s between the baseline's 5 s and 120 s
    # components spreads by ~18 % over seeds; the rate within 25 % is the benchmark's figure)
    for k, true, tol in (("tau_s", 30.0, 0.25), ("sigma_m", 1.0, 0.15)):
        assert abs(p[k] - true) <= 2.5 * se[k] and se[k] < tol * true, (k, p[k], se[k])
    assert rep["effects"][0]["closure"] >= 0.7
    assert any(w["statistic"] in ("log_adev", "log_std", "log_step_std") for w in rep["where"])


@pytest.mark.slow
def test_a_smooth_drift_is_closed_by_a_second_order_gauss_markov(baseline: list) -> None:
    # a critically damped drift: an exponential law of its sigma and tau would add 1-8 s
    # noise it does not have and close nothing held out; order 2 names and closes it
    d = diagnose(
        real_with(GaussMarkov(sigma_m=1.0, tau_s=30.0, order=2)), baseline, np.random.default_rng(1)
    )
    rep = report_dict(d)
    assert rep["verdict"] == {"effect": "gauss_markov", "explained": True}
    assert rep["effects"][0]["params"]["order"] == 2
    assert rep["effects"][0]["closure"] >= 0.7


@pytest.fixture(scope="module")
def smooth_drift_round(baseline: list) -> tuple:
    """A pipeline run on a smooth (second-order) drift, its first round rebuilt, and the
    likelihood's fit of each order on the fit part."""
    from x6wd.gap.diagnose import GpsPipeline, window
    from x6wd.gap.pipeline import Round

    real = real_with(GaussMarkov(sigma_m=1.0, tau_s=30.0, order=2))
    pipe = GpsPipeline(Options(), np.random.default_rng(1))
    pipe.run(real, baseline)
    split = pipe.split
    current_fit = [window(s, *split.fit_s) for s in pipe.runs]
    null = pipe.null([pipe.battery(s, split.fit_layout) for s in current_fit])
    this_round = Round(0, [], ["gauss_markov"], pipe.runs, current_fit, null, null.z({}))
    fits = {k: fit_gauss_markov(split.real_fit, current_fit, split.fit_layout, k) for k in (1, 2)}
    return pipe, this_round, fits


@pytest.mark.slow
def test_the_held_out_key_picks_the_gauss_markov_order_and_refines_it(
    smooth_drift_round: tuple,
) -> None:
    # Whichever order the likelihood offers first, consider() keeps the one with the lower
    # held-out key: for a smooth drift, order 2, even when order 1 is put forward. And an
    # optimum the likelihood misplaced (on the simulator: its noise model's slow misfit) is
    # refined by simulation back to where the surrogate's exact likelihood puts it.
    from x6wd.gap.fit import Fit

    pipe, this_round, fits = smooth_drift_round
    for offered, fit in fits.items():
        assert fit is not None and fit.effect.order == offered
        assert pipe._better_gauss_markov(this_round, fit).effect.order == 2
    exact = fits[2].params
    misplaced = GaussMarkov(sigma_m=1.5 * exact["sigma_m"], tau_s=2.0 * exact["tau_s"], order=2)
    refined = pipe._better_gauss_markov(this_round, Fit(misplaced, fits[2].se))
    assert refined.effect.order == 2
    for key in ("sigma_m", "tau_s"):
        assert refined.params[key] == pytest.approx(exact[key], rel=0.15), refined.params


@pytest.mark.slow
def test_a_drift_member_tied_with_the_named_one_competes_with_it(smooth_drift_round: tuple) -> None:
    # Within 2 BIC of the likelihood's pick a member ranks as the pick (both meet the other
    # effects on the held-out key); between 2 and 10 it is tried only when nothing else may
    # enter; beyond 10 never.
    from dataclasses import replace

    pipe, this_round, fits = smooth_drift_round
    run_plan = pipe.plan  # the run's lattice stays: no coarser-lattice path, and restored
    assert run_plan.lattice == pipe.lattice
    try:
        for tied, rank in ((True, 0), (False, 1)):
            pipe.plan = replace(
                run_plan,
                family_best=["random_walk"],
                family_plausible={"random_walk", "gauss_markov"},
                family_tied={"random_walk", "gauss_markov"} if tied else {"random_walk"},
                lattice_fact=False,
            )
            option = pipe.consider(this_round, "gauss_markov", fits[2])
            assert (option.rank, option.eligible) == (rank, True)
        pipe.plan = replace(
            run_plan,
            family_best=["random_walk"],
            family_plausible={"random_walk"},
            family_tied={"random_walk"},
            lattice_fact=False,
        )
        assert not pipe.consider(this_round, "gauss_markov", fits[2]).eligible
    finally:
        pipe.plan = run_plan


@pytest.mark.slow
def test_injected_bias_found_within_standard_errors(baseline: list) -> None:
    real = real_with(Bias(east_m=3.0, north_m=-2.0), seed=12)
    d = diagnose(real, baseline, np.random.default_rng(2))
    rep = report_dict(d)
    assert rep["verdict"]["effect"] == "bias" and rep["verdict"]["explained"]
    fit = d.selected[0]
    for key, true in (("east_m", 3.0), ("north_m", -2.0)):
        assert abs(fit.params[key] - true) <= 0.1 + 2 * fit.se[key]
    assert {w["statistic"] for w in rep["where"]} >= {"mean"}


@pytest.mark.slow
def test_injected_quantization_step_exact(baseline: list) -> None:
    real = real_with(Quantization(4), quantize=False)
    d = diagnose(real, baseline, np.random.default_rng(3))
    rep = report_dict(d)
    assert rep["verdict"]["effect"] == "quantization"
    assert rep["effects"][0]["params"] == {"decimals": 4}


@pytest.mark.slow
def test_two_effects_found_together(baseline: list) -> None:
    # A bias hides under a drift that widens the spread of means; greedy + companion finds both.
    real = real_with(GaussMarkov(sigma_m=1.0, tau_s=60.0), Bias(4.0, 0.0, 0.0), seed=12)
    d = diagnose(real, baseline, np.random.default_rng(4))
    assert {f.name for f in d.selected} == {"gauss_markov", "bias"}
    assert d.explained
    bias = next(f for f in d.selected if f.name == "bias")
    assert bias.params["east_m"] == pytest.approx(4.0, abs=0.1 + 2 * bias.se["east_m"])
    # the drift is most of what was flagged (1-2 s Allan deviations, step spread): it leads
    assert d.selected[0].name == "gauss_markov"


@pytest.mark.slow
def test_the_effect_that_explains_the_flagged_cells_comes_first(baseline: list) -> None:
    # A 3 m offset with a faint 10-s drift: the likelihood names the drift with a bias
    # companion, so the drift entered first, but the flagged cells are the means and the
    # spread about the origin; the faint drift only closes part of the held-out G. The
    # report's answer is the bias (the drift stays, second).
    real = real_with(GaussMarkov(sigma_m=0.15, tau_s=10.0), Bias(3.0, 0.0, 0.0), seed=12)
    d = diagnose(real, baseline, np.random.default_rng(4))
    assert [f.name for f in d.selected] == ["bias", "gauss_markov"]
    assert report_dict(d)["verdict"] == {"effect": "bias", "explained": True}
    assert d.where[0]["statistic"] == "mean"


def test_null_threshold_controls_family_wise_error(baseline: list) -> None:
    lay = layout_for(baseline[0])
    bats = [battery(s, lay) for s in baseline]
    model = null_model(bats[:12])
    held_out = [np.max(np.abs(model.z(b))) for b in bats[12:]]
    assert all(z < model.threshold for z in held_out)
    assert model.threshold > 3.0  # corrected for multiplicity, not a per-cell 1.96


def test_a_heavy_tailed_cell_gets_a_limit_of_its_own() -> None:
    # One cell whose replicates are 0 but for one far-off run (the random walk's likelihood
    # ratio scored out of sample: 0 for most runs, 54 for one) must raise its own limit,
    # not every cell's: through the family-wise maximum of |z| it set the limit of all cells,
    # and a real gap in any other cell went unseen.
    rng = np.random.default_rng(3)
    names = [Cell("mean", f"axis{i}") for i in range(60)]
    values = rng.standard_normal((12, 60))
    light = null_model([dict(zip(names, row, strict=True)) for row in values])
    heavy_cell = Cell("random_walk_lr", "horizontal")
    ratios = np.zeros(12)
    ratios[4] = 54.0
    rows = [
        {**dict(zip(names, row, strict=True)), heavy_cell: r}
        for row, r in zip(values, ratios, strict=True)
    ]
    heavy = null_model(rows)
    limits = heavy.limits()
    assert heavy.apart == 1 and limits[-1] > 2 * heavy.threshold
    assert heavy.threshold == pytest.approx(light.threshold, rel=0.15)
    real = dict(zip(names, values.mean(axis=0), strict=True)) | {heavy_cell: 0.0}
    real[names[0]] += 8.0 * float(heavy.sd[0])  # a gap 8 spreads wide in an ordinary cell
    assert np.abs(heavy.z(real))[0] > limits[0]


def test_simulator_runs_are_scored_out_of_sample() -> None:
    # The real log's random-walk ratio is scored against the noise model of all runs, so
    # each run's must be scored against the model of the OTHER runs: in sample, a model
    # that has seen the run's own slow wander left the cell's null too narrow.
    from x6wd.gap.diagnose import GpsPipeline
    from x6wd.gap.drift import random_walk_lr
    from x6wd.gap.noise import fit_noise_model

    runs = [surrogate_run(900.0, 1.0, np.random.default_rng(300 + i)) for i in range(9)]
    real, runs = runs[0], runs[1:]
    pipe = GpsPipeline(Options(), np.random.default_rng(0))
    pipe.layout = layout_for(real)
    pipe.runs = runs
    bats: list[dict] = [{} for _ in runs]
    real_bat: dict = {}
    pipe.add_whole_log_cells(real, real_bat, bats)
    for i, run in enumerate(runs):
        others = fit_noise_model(runs[:i] + runs[i + 1 :], pipe.layout)
        assert bats[i][RW_LR_CELL] == pytest.approx(random_walk_lr(run, others), abs=1e-6)
    assert real_bat[RW_LR_CELL] == pytest.approx(
        random_walk_lr(real, fit_noise_model(runs, pipe.layout)), abs=1e-6
    )


def test_the_walk_ratio_is_despiked_against_a_few_logs_only() -> None:
    # A few logs' replicates rarely carry a geometry spike, so there the ratio is read
    # despiked; simulator runs show its heavy tail themselves, spikes and all, so there it
    # stays raw (despiked, 9 of 240 no-effect hours were flagged on this cell alone).
    from x6wd.gap.diagnose import GpsPipeline
    from x6wd.gap.drift import random_walk_lr
    from x6wd.gap.noise import noise_model

    logs = [surrogate_run(900.0, 1.0, np.random.default_rng(320 + i)) for i in range(5)]
    real, runs = logs[0], logs[1:]
    north = np.array(real.north_m, dtype=float)
    north[400:402] += 30.0  # two epochs out and back
    real = real.with_(north_m=north)
    pipe = GpsPipeline(Options(), np.random.default_rng(0))
    pipe.layout = layout_for(real)
    pipe.runs = runs
    model = noise_model(runs, pipe.layout)
    raw, despiked = (random_walk_lr(real, model, despike=d) for d in (False, True))
    assert abs(raw - despiked) > 0.5  # the spike moves the ratio
    for inflation, want in ((None, raw), ({("*", "*"): 1.0}, despiked)):
        pipe.inflation = inflation
        real_bat: dict = {}
        pipe.add_whole_log_cells(real, real_bat, [{} for _ in runs])
        assert real_bat[RW_LR_CELL] == pytest.approx(want, abs=1e-6)


def test_block_bootstrap_keeps_length_and_time_structure(baseline: list) -> None:
    reps = block_bootstrap(baseline[:1], 5, np.random.default_rng(0), block_s=400.0)
    assert all(len(r) == len(baseline[0]) for r in reps)
    ms = [1, 8, 64]
    a0 = allan_var(baseline[0].east_m, ms)
    a1 = np.mean([allan_var(r.east_m, ms) for r in reps], axis=0)
    assert np.allclose(np.log(a1), np.log(a0), atol=0.7)


def test_real_urban_rover_against_reference() -> None:
    rover = read_track(URBAN / "rover_1Hz_spp.pos")
    ref = read_track(URBAN / "reference_1Hz.pos")
    # RTKLIB omits unsolved epochs: they come back as no-fix epochs (outages)
    assert len(rover) == 1231 and int(rover.valid.sum()) == 550 and len(ref) == 1231
    err = errors_vs_track(rover, ref)
    h = np.hypot(err.east_m, err.north_m)[err.valid]
    assert 1.5 < float(np.median(h)) < 5.0  # README: median about 2.9 m
    assert err.speed_mps is not None and float(np.max(err.speed_mps)) > 3.0


def test_csv_round_trip_and_bad_input(tmp_path: Path) -> None:
    s = surrogate_run(100.0, 1.0, np.random.default_rng(0))
    write_csv(tmp_path / "s.csv", series_to_track(s, 100.0))
    back = read_track(tmp_path / "s.csv")
    _e_per, n_per = metres_per_degree(s.origin_lat_deg)
    assert np.allclose((back.lat_deg - s.origin_lat_deg) * n_per, s.north_m, atol=1e-3)
    (tmp_path / "bad.csv").write_text("time,lat,lon\n1,abc,2\n")
    with pytest.raises(ParseError, match=r"bad\.csv:2"):
        read_track(tmp_path / "bad.csv")
    with pytest.raises(ConfigError, match=r"LAT,LON"):
        parse_truth("91,0")
    with pytest.raises(ConfigError, match="fit_fraction"):
        Options(fit_fraction=0.95)


def _scenario(tmp_path: Path) -> Path:
    p = tmp_path / "kk1446.toml"
    p.write_text(
        'name = "F9P on KK1446"\nstart_utc = "2020-05-18T16:23:13Z"\nduration_s = 1410.0\n'
        f"[origin]\nlat_deg = {KK1446[0]!r}\nlon_deg = {KK1446[1]!r}\nalt_m = 1724.0\n"
        '[gnss]\nfidelity = "pseudorange"\n'
    )
    return p


@pytest.mark.slow
def test_real_static_f9p_against_scenario_report(tmp_path: Path) -> None:
    out = tmp_path / "out"
    truth = f"{KK1446[0]:.9f},{KK1446[1]:.9f}"
    args = ["gap", "--real", str(STATIC / "mobile.csv"), "--scenario", str(_scenario(tmp_path))]
    code = x6wd_main([*args, "--seeds", "10", "--truth", truth, "--out", str(out), "--quiet"])
    assert code == 0
    rep = json.loads((out / "report.json").read_text())
    assert set(rep) == {"gap", "where", "effects", "verdict"}
    assert set(rep["gap"]) == {"baseline", "floor", "with_effects"}
    # The F9P is far quieter than a NEO-5-class model: the tool must flag short-scale spread
    # (real below the null), say that the simulator is the noisier one, and explain it with a
    # receiver-side layer that makes the simulation quieter (issue 15 item 3), never with an
    # additive error, which can only make it noisier.
    adev = [w for w in rep["where"] if w["statistic"] == "log_adev" and w["scale"] == "tau=1s"]
    assert adev and all(w["z"] < 0 for w in adev)
    assert rep["verdict"]["explained"] is True
    named = set(str(rep["verdict"]["effect"]).split(" + "))
    quieter = {"nav_filter", "noise_scale", "static_hold", "correction"}
    assert named & quieter, rep["verdict"]
    assert not named & {"bias", "gauss_markov", "random_walk", "jumps", "multipath"}
    text = (out / "report.md").read_text()
    assert "the simulator is noisier than the receiver" in text
    for name in (
        "report.md",
        "effects.toml",
        "scatter.png",
        "cdf.png",
        "allan.png",
        "acf.png",
        "time.png",
    ):
        assert (out / name).stat().st_size > 0


def test_cli_with_one_sim_log_uses_bootstrap(tmp_path: Path) -> None:
    # One 15-minute sim log pins the spread of 15-minute means with under 3 degrees of
    # freedom (null.between_log_dof): a 4 m offset (z 8) is no longer enough, 15 m is.
    real = surrogate_run(
        900.0, 1.0, np.random.default_rng(5), effects=[*PRE, Bias(15.0, 0.0, 0.0), Quantization(5)]
    )
    origin = (real.origin_lat_deg, real.origin_lon_deg)
    sim = surrogate_run(900.0, 1.0, np.random.default_rng(6))
    write_csv(tmp_path / "real.csv", series_to_track(real, 100.0))
    write_csv(tmp_path / "sim.csv", series_to_track(sim, 100.0))
    out = tmp_path / "rep"
    code = x6wd_main(
        ["gap", "--real", str(tmp_path / "real.csv"), "--sim", str(tmp_path / "sim.csv"),
         "--truth", f"{origin[0]},{origin[1]},100", "--out", str(out), "--quiet", "--no-figures"]
    )  # fmt: skip
    assert code == 0
    rep = json.loads((out / "report.json").read_text())
    assert rep["verdict"]["effect"] == "bias"
    md = (out / "report.md").read_text()
    assert "made of their innovations" in md and "(alpha 1 %" in md  # the few-logs level
    toml = (out / "effects.toml").read_text()
    assert 'name = "bias"' in toml
    import tomllib

    eff = tomllib.loads(toml)["effects"][0]
    assert math.isclose(eff["east_m"], 15.0, abs_tol=1.0)
    # the fragment is what the simulator's scenario loader accepts
    from sim_backend.world import load_world, merge_fragment

    world = merge_fragment(load_world(_scenario(tmp_path)), out / "effects.toml")
    assert [e.name for e in world.effect_objects()] == ["bias"]


# --- exact likelihood: the drift family (bias / Gauss-Markov / random walk) ---------------------

HOUR_S = 3600.0


@pytest.fixture(scope="module")
def hour_baseline() -> list:
    return [surrogate_run(HOUR_S, 1.0, np.random.default_rng(300 + i)) for i in range(8)]


@pytest.mark.parametrize("order", [1, 2])
def test_the_drift_family_names_the_order_of_a_gauss_markov_drift(
    hour_baseline: list, order: int
) -> None:
    # a smooth (critically damped) drift and an exponential one of the same sigma and tau:
    # each is fitted with its own order, and its parameters, by exact likelihood
    *noise, lattice = BASELINE_EFFECTS
    effects = [*noise, GaussMarkov(sigma_m=1.5, tau_s=60.0, order=order), lattice]
    real = surrogate_run(HOUR_S, 1.0, np.random.default_rng(5), effects=effects)
    fit = fit_gauss_markov(real, hour_baseline, layout_for(hour_baseline[0]))
    assert fit is not None and isinstance(fit.effect, GaussMarkov)
    assert fit.effect.order == order
    assert fit.effect.sigma_m == pytest.approx(1.5, rel=0.2)
    assert fit.effect.tau_s == pytest.approx(60.0, rel=0.25)


def hour_real(*effects: object, seed: int = 7) -> PositionSeries:
    return surrogate_run(
        HOUR_S, 1.0, np.random.default_rng(seed), effects=[*PRE, *effects, Quantization(5)]
    )


def test_kalman_likelihood_is_exact_on_irregular_steps_and_outages() -> None:
    # The filter's likelihood equals the dense multivariate-normal one: baseline components,
    # white noise and a GM or random-walk effect, irregular steps, an outage.
    from scipy.stats import multivariate_normal

    from x6wd.gap.kalman import kalman_terms

    s, model = filter_case()
    tv = s.t_s[s.valid]
    lag = np.abs(tv[:, None] - tv[None, :])
    since = tv - tv[0]
    for eff_var, eff_tau in ((0.8, 10.0), (0.01, math.inf)):
        got = kalman_terms(s, model, np.array([eff_var]), np.array([eff_tau])).loglik(False)
        want = 0.0
        for a, y in enumerate((s.east_m, s.north_m)):
            cov = dense_baseline_cov(model, tv, a)
            if math.isfinite(eff_tau):
                cov = cov + eff_var * np.exp(-lag / eff_tau)
            else:  # a random walk from zero at the first fix
                cov = cov + eff_var * np.minimum(since[:, None], since[None, :])
            mean = np.full(tv.size, model.mean_m[a])
            want += multivariate_normal(mean=mean, cov=cov).logpdf(y[s.valid])
        assert float(got[0]) == pytest.approx(want, rel=1e-9)


def test_gls_bias_and_latency_match_the_dense_likelihood() -> None:
    # The filter's profile likelihood with a bias per axis and one shared latency equals the
    # dense GLS one; the latency regressor is -velocity.
    from scipy.stats import multivariate_normal

    from x6wd.gap.kalman import kalman_terms, latency_regressor

    s, model = filter_case(seed=1, n=50, moving=True)
    v = s.valid
    kt = kalman_terms(s, model, np.array([0.8]), np.array([10.0]))
    tv = s.t_s[v]
    lag = np.abs(tv[:, None] - tv[None, :])
    reg = latency_regressor(s)
    assert reg is not None
    covs, xs, ys = [], [], []
    for a, y in enumerate((s.east_m, s.north_m)):
        covs.append(dense_baseline_cov(model, tv, a) + 0.8 * np.exp(-lag / 10.0))
        x = np.zeros((tv.size, 3))
        x[:, a] = 1.0  # the bias of this axis
        x[:, 2] = reg[a]  # the shared latency
        xs.append(x)
        ys.append(y[v] - model.mean_m[a])
    info = sum(x.T @ np.linalg.solve(c, x) for x, c in zip(xs, covs, strict=True))
    rhs = sum(x.T @ np.linalg.solve(c, yy) for x, c, yy in zip(xs, covs, ys, strict=True))
    beta = np.linalg.solve(info, rhs)
    want = sum(
        multivariate_normal(mean=x @ beta, cov=c).logpdf(yy)
        for x, c, yy in zip(xs, covs, ys, strict=True)
    )
    assert float(kt.loglik(True, True)[0]) == pytest.approx(want, rel=1e-9)
    coef, se = kt.coef(True, True)
    assert np.allclose(coef[0], beta, atol=1e-8)
    assert np.allclose(se[0], np.sqrt(np.diag(np.linalg.inv(info))), rtol=1e-6)


@pytest.mark.slow
def test_gauss_markov_and_latency_found_together_with_joint_parameters() -> None:
    # On a loop, a latency's error (-delay x velocity) turns with the course: a drift alone
    # would soak it up with a longer tau. The joint likelihood names both, fits both.
    from sim_backend.effects import Latency

    base = [
        surrogate_run(HOUR_S, 1.0, np.random.default_rng(500 + i), moving=True) for i in range(10)
    ]
    real = surrogate_run(
        HOUR_S, 1.0, np.random.default_rng(3), moving=True,
        effects=[*PRE, Latency(0.5), GaussMarkov(0.8, 60.0), Quantization(5)],
    )  # fmt: skip
    d = diagnose(real, base, np.random.default_rng(3))
    sel = {f.name: f for f in d.selected}
    assert set(sel) == {"gauss_markov", "latency"} and d.explained
    lat, gm = sel["latency"], sel["gauss_markov"]
    # One log is one draw: judged by its standard error, which must be fine enough for the
    # issue's 100 ms (over ten seeds the fits average 0.50 s with spread 0.055 s; the rate
    # within 100 ms is the injection benchmark's figure)
    d_s, se_d = lat.params["delay_s"], lat.se["delay_s"]
    assert abs(d_s - 0.5) <= 2.5 * se_d and se_d < 0.1 / 1.5, (d_s, se_d)
    # tau 60 s sits between the baseline's 5 s and 120 s components: judged by its own
    # standard error (the Cramer-Rao spread of log tau is ~0.3 here, see docs/gap.md)
    for k, true in (("tau_s", 60.0), ("sigma_m", 0.8)):
        assert abs(gm.params[k] - true) <= 2.5 * gm.se[k], (k, gm.params[k], gm.se[k])
    assert gm.se["tau_s"] < 0.5 * gm.params["tau_s"]


def test_drift_family_told_apart_by_likelihood(hour_baseline: list) -> None:
    # One hour at 1 Hz: a random walk, a bias, a Gauss-Markov drift and nothing are told apart
    # by BIC on top of the baseline's own noise model; parameters within the targets.
    from sim_backend.effects import RandomWalk
    from x6wd.gap.drift import drift_fit

    lay = layout_for(hour_baseline[0])
    rw = drift_fit(hour_real(RandomWalk(0.03)), hour_baseline, lay)
    assert rw.best == "random_walk"
    q, se_q = rw.random_walk[(False, False)]
    assert q == pytest.approx(0.03, abs=2.5 * se_q)
    assert drift_fit(hour_real(Bias(1.5, -1.0, 0.0)), hour_baseline, lay).best == "bias"
    assert drift_fit(hour_real(), hour_baseline, lay).best == "none"
    gm = drift_fit(hour_real(GaussMarkov(sigma_m=1.5, tau_s=60.0)), hour_baseline, lay)
    assert gm.best == "gauss_markov"
    (sigma, tau), (se_s, se_t) = gm.gauss_markov[(False, False)]
    assert tau == pytest.approx(60.0, rel=0.25) and sigma == pytest.approx(1.5, rel=0.15)
    assert 0 < se_t < 0.5 * tau and 0 < se_s < 0.3 * sigma


@pytest.mark.slow
def test_injected_random_walk_identified(hour_baseline: list) -> None:
    from sim_backend.effects import RandomWalk

    d = diagnose(hour_real(RandomWalk(0.08), seed=11), hour_baseline, np.random.default_rng(5))
    rep = report_dict(d)
    assert rep["verdict"] == {"effect": "random_walk", "explained": True}
    assert rep["effects"][0]["params"]["q_m_per_sqrt_s"] == pytest.approx(0.08, rel=0.25)
    assert any("whole log" in n for n in d.notes)


def test_moderate_random_walk_read_by_likelihood_ratio_cell(hour_baseline: list) -> None:
    # A moderate walk (0.03 m/s^0.5) hides under the baseline's 0.8 m / 120 s drift at every
    # scale the Allan deviations reach; the whole-log likelihood-ratio cell reads it (a root
    # of ~6, beyond the 3.6-4.5 of the heaviest no-effect hours its floor was set on) and it
    # is named; a null hour does not trip the cell.
    from sim_backend.effects import RandomWalk

    d = diagnose(hour_real(RandomWalk(0.03), seed=13), hour_baseline, np.random.default_rng(5))
    rep = report_dict(d)
    (walk_z,) = [float(z) for c, z in zip(d.cells, d.z, strict=True) if c == RW_LR_CELL]
    assert walk_z > 5.0
    assert rep["verdict"] == {"effect": "random_walk", "explained": True}
    null = diagnose(hour_real(seed=21), hour_baseline, np.random.default_rng(5))
    assert not any(w["statistic"] == "random_walk_lr" for w in report_dict(null)["where"])


# --- jumps: a step-law mixture on top of the baseline's own steps -------------------------------


def test_jump_fit_recovers_size_and_rate_and_stays_quiet_on_null(hour_baseline: list) -> None:
    from sim_backend.effects import Jumps
    from x6wd.gap.jumps import fit_jumps

    lay = layout_for(hour_baseline[0])
    sig, rate = [], []
    for seed in (31, 32, 33):
        real = hour_real(Jumps(1.0, 0.005, trigger="poisson"), seed=seed)
        f = fit_jumps(real, hour_baseline, lay)
        assert f is not None and f.params["trigger"] == "poisson"
        sig.append(f.params["sigma_m"])
        rate.append(f.params["rate_per_s"])
    # three hours of 18 jumps each: sigma and rate within a third of the truth on average
    assert float(np.mean(sig)) == pytest.approx(1.0, rel=0.3)
    assert float(np.mean(rate)) == pytest.approx(0.005, rel=0.35)
    nulls = [fit_jumps(hour_real(seed=s), hour_baseline, lay) for s in (41, 42, 43, 44)]
    assert sum(f is not None and f.params["rate_per_s"] > 0.001 for f in nulls) <= 1


def test_jump_fit_survives_a_coarse_lattice() -> None:
    # A 2-decimal lattice (18 m) makes almost every step exactly zero: no crash, no fit.
    from x6wd.gap.jumps import fit_jumps

    coarse = [
        surrogate_run(600.0, 1.0, np.random.default_rng(i), effects=[*PRE, Quantization(2)])
        for i in range(4)
    ]
    real = surrogate_run(600.0, 1.0, np.random.default_rng(9), effects=[*PRE, Quantization(2)])
    assert fit_jumps(real, coarse, layout_for(real)) is None


def test_noise_model_slow_component_is_pinned_by_the_runs_means() -> None:
    # A drift far longer than the log (tau 3000 s over 1 h) moves each run's mean; the noise
    # model must predict the runs' spread of hour means, not an unbounded slow component.
    from x6wd.gap.noise import fit_noise_model

    slow = (*PRE, GaussMarkov(sigma_m=0.8, tau_s=3000.0, axes="en"))
    runs = [
        surrogate_run(HOUR_S, 1.0, np.random.default_rng(700 + i), effects=slow) for i in range(16)
    ]
    m = fit_noise_model(runs, layout_for(runs[0]))
    t = HOUR_S
    for a, ax in enumerate(("east_m", "north_m")):
        var_mean = sum(
            m.sigma_m[a, i] ** 2
            * 2
            * m.tau_s[a, i]
            / t
            * (1 - m.tau_s[a, i] / t * (1 - math.exp(-t / m.tau_s[a, i])))
            for i in range(m.sigma_m.shape[1])
        )
        spread = float(np.std([np.mean(getattr(s, ax)) for s in runs], ddof=1))
        # 16 runs: the sample spread is within about +-35 % of the truth (chi, 15 dof)
        assert 0.5 < math.sqrt(var_mean) / spread < 2.0, (ax, math.sqrt(var_mean), spread)


@pytest.mark.slow
def test_drift_under_a_coarse_lattice_is_fitted_through_it(hour_baseline: list) -> None:
    # A 3-decimal lattice (1.85 m) is a fact and enters first; the drift is then fitted by
    # simulation through the rounding (the likelihood alone reads 0.8 m / 60 s as ~20 s).
    real = surrogate_run(
        HOUR_S, 1.0, np.random.default_rng(17),
        effects=[*PRE, GaussMarkov(sigma_m=0.8, tau_s=60.0), Quantization(3)],
    )  # fmt: skip
    d = diagnose(real, hour_baseline, np.random.default_rng(17))
    assert [f.name for f in d.selected] == ["quantization", "gauss_markov"] and d.explained
    gm = d.selected[1].params
    assert gm["tau_s"] == pytest.approx(60.0, rel=0.35) and gm["sigma_m"] == pytest.approx(
        0.8, rel=0.2
    )


def _white_series(sigma_m: float, duration_s: float, seed: int) -> PositionSeries:
    t = np.arange(0.0, duration_s + 0.5)
    rng = np.random.default_rng(seed)
    e, n = sigma_m * rng.standard_normal((2, t.size))
    return PositionSeries(t, e, n, np.zeros(t.size), np.ones(t.size, dtype=bool), 51.7, 19.5)


def test_spectrum_bands_measure_white_noise_density_and_a_drift_s_red_spectrum() -> None:
    from x6wd.gap.stats import spectrum_bands

    white = _white_series(0.5, 3600.0, 1)
    lay = layout_for(white)
    edges, power = spectrum_bands(white.east_m, white.north_m, lay)
    # two-octave bands from the Nyquist frequency down to ten cycles per log
    assert edges[0] == (0.125, 0.5) and all(lo >= 10 / 3600 for lo, _hi in edges)
    # white noise: east + north one-sided density 2 sigma^2 dt in every band
    assert power == pytest.approx([2 * 0.25 * 1.0] * len(edges), rel=0.25)
    drift = GaussMarkov(sigma_m=0.5, tau_s=60.0).apply(
        _white_series(0.0, 3600.0, 2), np.random.default_rng(2)
    )
    edges2, red = spectrum_bands(drift.east_m, drift.north_m, layout_for(drift))
    assert edges2 == edges and red[-1] > 10 * red[0]  # fixed by the layout; power at low f


def test_resampled_null_keeps_the_ensemble_spread() -> None:
    # Closure intervals rebuild the null from members drawn with replacement; without the
    # M/(M-1) correction its spread is (M-1)/M of the ensemble's in expectation (12 % low at
    # M = 8), which biased every interval's closures low.
    from x6wd.gap.null import resample_null

    rng = np.random.default_rng(4)
    values = rng.standard_normal((8, 5)) * 3.0
    names = [Cell("mean", f"axis{i}") for i in range(5)]
    model = null_model([dict(zip(names, row, strict=True)) for row in values])
    var = np.mean([resample_null(model, rng).sd ** 2 for _ in range(4000)], axis=0)
    assert var == pytest.approx(model.sd**2, rel=0.05)


def test_a_plausible_drift_member_enters_when_the_named_one_cannot() -> None:
    # The likelihood names one drift-family member; when its fit cannot enter (it closes
    # less than the first-effect minimum: a look-alike of the log's own noise), a member the
    # likelihood did not reject decisively (rank 1) is tried before "nothing". A first-rank
    # option that may enter is still chosen over a second-rank one with a better key.
    import types

    from sim_backend.effects import RandomWalk
    from x6wd.gap.diagnose import GpsPipeline
    from x6wd.gap.fitted import Fit
    from x6wd.gap.pipeline import Option

    pipe = GpsPipeline(Options(), np.random.default_rng(0))
    pipe.fresh_draws = 0  # decide on each option's own held-out G
    pipe.split = types.SimpleNamespace(g_baseline=11.0, g_floor=1.0)  # type: ignore[assignment]
    null = null_model([{Cell("mean", "east"): v} for v in (0.0, 1.0, 2.0)])

    def offer(fit: Fit, g_test: float, key: float, rank: int) -> Option:
        return Option(fit, key, g_test, null, [fit], g_test, [], True, rank)

    named = offer(Fit(GaussMarkov(sigma_m=0.3, tau_s=7.0)), 10.5, 20.0, 0)  # closes 0.05
    plausible = offer(Fit(Bias(5.0, 1.0, 0.0)), 2.0, 25.0, 1)  # closes 0.9
    best, g_new = pipe._first_to_enter([named, plausible], [], 11.0, 0)
    assert best is plausible and g_new == 2.0
    good = offer(Fit(RandomWalk(q_m_per_sqrt_s=0.05)), 4.0, 30.0, 0)  # closes 0.7
    best, _ = pipe._first_to_enter([good, plausible], [], 11.0, 0)
    assert best is good
    assert pipe._first_to_enter([named], [], 11.0, 0) == (None, 11.0)


def test_simulation_refit_reaches_the_truth_from_a_second_start() -> None:
    # Under a 1.85 m lattice the likelihood can read a 0.8 m / 60 s drift as 0.16 m / 2.3 s,
    # too far for a short local search; a second start (the fit-part fit) that scores better
    # is searched from instead, and a moved parameter carries no standard error.
    from x6wd.gap.diagnose import simulation_refit
    from x6wd.gap.fitted import Fit

    runs = [surrogate_run(1200.0, 1.0, np.random.default_rng(700 + i)) for i in range(6)]
    real = surrogate_run(
        1200.0, 1.0, np.random.default_rng(70),
        effects=[*PRE, GaussMarkov(sigma_m=0.8, tau_s=60.0), Quantization(3)],
    )  # fmt: skip
    lay = layout_for(real)
    quant = Fit(Quantization(3), {"decimals": 0.0})
    wrong = Fit(GaussMarkov(sigma_m=0.16, tau_s=2.3), {"sigma_m": 0.01, "tau_s": 0.2})
    good = Fit(GaussMarkov(sigma_m=0.8, tau_s=60.0), {"sigma_m": 0.1, "tau_s": 10.0})
    real_b = battery(real, lay)
    alone = simulation_refit(wrong, [quant], real_b, runs, lay, 3)
    both = simulation_refit(wrong, [quant], real_b, runs, lay, 3, alt_start=good)
    assert both.params["tau_s"] > 25.0 > alone.params["tau_s"]
    assert math.isnan(both.se["tau_s"]) and math.isnan(both.se["sigma_m"])
    bias = Fit(Bias(1.0, 0.0, 0.0), {"east_m": 0.1})
    assert simulation_refit(bias, [quant], real_b, runs, lay, 3) is bias  # not refitted


def test_blas_pinned_to_one_thread_unless_the_user_chose(monkeypatch: pytest.MonkeyPatch) -> None:
    import os

    from x6wd.app.cli import BLAS_THREAD_VARS, single_thread_blas

    for var in BLAS_THREAD_VARS:
        monkeypatch.delenv(var, raising=False)
    monkeypatch.setenv("OPENBLAS_NUM_THREADS", "2")
    single_thread_blas()
    assert os.environ["OPENBLAS_NUM_THREADS"] == "2"
    assert all(os.environ[v] == "1" for v in BLAS_THREAD_VARS if v != "OPENBLAS_NUM_THREADS")


# --- the null of a few sim logs (issue 15) ---------------------------------------------------

SLOW = (
    *PRE,
    GaussMarkov(sigma_m=1.0, tau_s=2500.0, axes="en"),
)  # a slow error, as the GNSS model's


def test_innovations_whiten_and_colour_are_inverse_on_irregular_steps_and_outages() -> None:
    from x6wd.gap.noise import AxisLaw, colour, whiten

    rng = np.random.default_rng(3)
    t_s = np.cumsum(rng.choice([1.0, 1.0, 2.0, 5.0], 400))
    y_m = np.cumsum(rng.standard_normal(400)) * 0.1
    law = AxisLaw(np.array([0.3, 1.0]), np.array([15.0, 2000.0]), 0.05, 0.2)
    e = whiten(law, t_s, y_m, np.ones(400, dtype=bool))
    assert np.allclose(colour(law, t_s, e[None, :])[0], y_m, atol=1e-9)
    # on draws of the law itself the innovations are white and standard
    draws = colour(law, t_s, rng.standard_normal((1, 400)))[0]
    valid = rng.random(400) > 0.1
    e = whiten(law, t_s, draws, valid)
    assert np.isnan(e[~valid]).all()
    assert abs(np.nanstd(e) - 1.0) < 0.1 and abs(np.nanmean(e)) < 0.15


def test_few_logs_null_has_no_joins_and_the_spread_of_independent_runs() -> None:
    # With three sim logs the null used to be raw blocks of them spliced together: each join
    # a fake step of the slow error's size, which the step-tail and random-walk statistics
    # read as an effect. Replicates made of the logs' innovations have the logs' step law,
    # and the spread of independent runs.
    from x6wd.gap.noise import few_logs_null

    slow = [*SLOW, Quantization(5)]
    runs = [
        surrogate_run(HOUR_S, 1.0, np.random.default_rng(900 + i), effects=slow) for i in range(19)
    ]
    lay = layout_for(runs[0])
    reps, inflation, _dof = few_logs_null(runs[:3], runs[3], lay, 20, np.random.default_rng(0))
    assert all(len(r) == len(runs[3]) and np.array_equal(r.t_s, runs[3].t_s) for r in reps)
    tail = Cell("step_tail", "east")
    step_sd = Cell("log_step_std", "north")
    indep = [battery(r, lay) for r in runs[3:]]
    ours = [battery(r, lay) for r in reps]
    spliced = [
        battery(r, lay) for r in block_bootstrap(runs[:3], 20, np.random.default_rng(0), 900.0)
    ]
    for cell in (tail, step_sd):
        ref = np.array([b[cell] for b in indep])
        got = np.array([b[cell] for b in ours])
        assert abs(got.mean() - ref.mean()) < 1.5 * ref.std(ddof=1)
        # wider than runs of the one law these logs share (1.9x step tail, 2.8x step std
        # here): each replicate's law is drawn from how three logs' laws differ, which three
        # logs of one law can bound but not exclude (the price in power of
        # tests/test_gap_fewlogs.py, docs/gap.md "Few sim logs")
        assert 0.6 < got.std(ddof=1) / ref.std(ddof=1) < 3.2
    # the spliced null's step tail sits far above independent runs (the joins)
    assert np.mean([b[tail] for b in spliced]) > np.mean([b[tail] for b in indep]) + 0.3
    assert all(1.0 < f < 3.0 for f in inflation.values())


def test_inflation_is_one_for_null_draws_and_the_excess_spread_otherwise() -> None:
    from x6wd.gap.null import inflation_from

    rng = np.random.default_rng(2)
    cells = [Cell("log_adev", "east", f"tau={i}s") for i in range(30)] + [Cell("mean", "up")]
    ok = inflation_from(cells, rng.standard_normal((3, 31)), 3)
    assert all(math.sqrt(4 / 3) <= f < 1.3 for f in ok.values())
    z = rng.standard_normal((3, 31))
    z[:, :30] *= 2.0
    wide = inflation_from(cells, z, 3)
    assert 1.6 < wide[("log_adev", "east")] < 2.5


def test_without_a_truth_the_scenario_runs_are_taken_against_their_own_mean(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # The real log's errors are against its own mean when no truth is given; the scenario's
    # runs (errors against the point they simulate) must be too, or CEP50, R95 and the means
    # read the runs' hour offsets as a gap. The diagnosis is observed, not replaced.
    from x6wd.gap import cli as gap_cli
    from x6wd.gap.io import against_own_mean
    from x6wd.gap.stats import lattice_fraction

    run = surrogate_run(600.0, 1.0, np.random.default_rng(3), effects=[*PRE, Quantization(5)])
    own = against_own_mean(run)
    valid = np.asarray(own.valid)
    assert abs(float(np.mean(np.asarray(run.east_m)[valid]))) > 0.01
    for axis in (own.east_m, own.north_m, own.up_m):
        assert abs(float(np.mean(np.asarray(axis)[valid]))) < 1e-9
    assert lattice_fraction(own, 5) == lattice_fraction(run, 5) == 1.0  # positions kept

    scenario = _scenario(tmp_path)
    sim_out = tmp_path / "sim"
    x6wd_main(["sim", str(scenario), "--duration", "300", "--seed", "4", "--out", str(sim_out),
               "--quiet"])  # fmt: skip
    seen: list = []
    real_diagnose = gap_cli.diagnose

    def observe(real: PositionSeries, baseline: list, *args: object, **kw: object) -> object:
        seen.append(baseline)
        return real_diagnose(real, baseline, *args, **kw)  # type: ignore[arg-type]

    monkeypatch.setattr(gap_cli, "diagnose", observe)
    argv = ["gap", "--real", str(sim_out / "gps.nmea"), "--scenario", str(scenario), "--seeds",
            "3", "--out", str(tmp_path / "rep"), "--quiet", "--no-figures"]  # fmt: skip
    assert x6wd_main(argv) == 0
    for s in seen[0]:
        v = np.asarray(s.valid)
        assert abs(float(np.mean(np.asarray(s.east_m)[v]))) < 1e-6
        assert abs(float(np.mean(np.asarray(s.north_m)[v]))) < 1e-6
