"""Fitting the multipath_zone effect: where, which wall, how strong, and nothing on null logs."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from sim_backend.effects import MultipathZone, PositionSeries, Quantization, truth_track_m
from tests.conftest import dense_baseline_cov, filter_case
from x6wd.gap.fit import FINGERPRINTS, FITTERS
from x6wd.gap.stats import layout_for
from x6wd.gap.surrogate import BASELINE_EFFECTS, surrogate_run
from x6wd.gap.zone import ZoneFit, fit_zone, zone_terms

PRE = BASELINE_EFFECTS[:-1]  # the baseline before NMEA printing
T_S = 1800.0  # three laps of the surrogate's 140 m loop
# A 60 m wall just outside the top of the loop (which peaks near y = 160 m): the track
# passes within 20 m of it for about 100 m per lap, partly beside the wall, partly round
# its ends (where the bias turns with the direction away from the wall end).
WALL = (113.0, 170.0, 173.0, 170.0)


def zone_of(sigma_m: float, bias_m: float, tau_s: float = 10.0) -> MultipathZone:
    return MultipathZone(*WALL, distance_m=20.0, sigma_m=sigma_m, bias_m=bias_m, tau_s=tau_s)


def log_with(*effects: object, seed: int, moving: bool = True) -> PositionSeries:
    return surrogate_run(
        T_S,
        1.0,
        np.random.default_rng(seed),
        moving=moving,
        effects=[*PRE, *effects, Quantization(5)],
    )


def true_zone(series: PositionSeries) -> tuple[np.ndarray, np.ndarray]:
    """The epochs inside the injected zone, and the unit vectors away from its wall."""
    te, tn = truth_track_m(series)
    dist, ux, uy = zone_of(1.0, 0.0).distance_to_wall_m(te, tn)
    return dist <= 20.0, np.stack([ux, uy])


@pytest.fixture(scope="module")
def runs() -> list[PositionSeries]:
    return [surrogate_run(T_S, 1.0, np.random.default_rng(400 + i), moving=True) for i in range(10)]


@pytest.fixture(scope="module")
def moderate(runs: list[PositionSeries]) -> tuple[PositionSeries, ZoneFit | None]:
    real = log_with(zone_of(1.5, 1.5), seed=31)
    return real, fit_zone(real, runs, layout_for(real))


def test_zone_likelihood_is_exact_with_a_masked_effect() -> None:
    # The masked filter's likelihood equals the dense multivariate-normal one: baseline
    # components, white noise, a Gauss-Markov effect that runs all the time but is seen only
    # in the zone, irregular steps, an outage (inside the zone too); with the bias vector
    # profiled by GLS, and its magnitude along given unit vectors.
    from scipy.stats import multivariate_normal

    s, model = filter_case()
    n, v, y = len(s), s.valid, np.stack([s.east_m, s.north_m])
    rng = np.random.default_rng(0)
    zone = np.zeros(n, dtype=bool)
    zone[5:12] = zone[25:33] = True
    ang = rng.uniform(0, 2 * math.pi, n)
    away = np.stack([np.cos(ang), np.sin(ang)])
    tv = s.t_s[v]
    lag = np.abs(tv[:, None] - tv[None, :])
    m = zone[v].astype(float)
    for eff_var, eff_tau in ((0.8, 10.0), (0.0, 1.0), (2.0, 3.0)):
        terms = zone_terms(s, model, np.array([eff_var]), np.array([eff_tau]), zone)
        shared = zone_terms(s, model, np.array([eff_var]), np.array([eff_tau]), zone, away)
        covs, resid = [], []
        for a in range(2):
            cov = dense_baseline_cov(model, tv, a)
            covs.append(cov + eff_var * np.exp(-lag / eff_tau) * np.outer(m, m))
            resid.append(y[a][v] - model.mean_m[a])
        want = sum(
            multivariate_normal(mean=np.zeros(tv.size), cov=c).logpdf(r)
            for c, r in zip(covs, resid, strict=True)
        )
        assert float(terms.loglik(False)[0]) == pytest.approx(want, rel=1e-9)
        # GLS bias per axis (regressor: in zone), and one magnitude along `away` (shared)
        want_b = 0.0
        for a in range(2):
            ci = np.linalg.inv(covs[a])
            b = (m @ ci @ resid[a]) / (m @ ci @ m)
            assert float(terms.bias()[0][0, a]) == pytest.approx(b, rel=1e-9)
            want_b += multivariate_normal(mean=b * m, cov=covs[a]).logpdf(resid[a])
        assert float(terms.loglik(True)[0]) == pytest.approx(want_b, rel=1e-9)
        xs = [away[a][v] * m for a in range(2)]
        cis = [np.linalg.inv(c) for c in covs]
        b_sh = sum(x @ ci @ r for x, ci, r in zip(xs, cis, resid, strict=True)) / sum(
            x @ ci @ x for x, ci in zip(xs, cis, strict=True)
        )
        want_sh = sum(
            multivariate_normal(mean=b_sh * x, cov=c).logpdf(r)
            for x, c, r in zip(xs, covs, resid, strict=True)
        )
        assert float(shared.bias(shared=True)[0][0]) == pytest.approx(b_sh, rel=1e-9)
        assert float(shared.loglik(True, shared=True)[0]) == pytest.approx(want_sh, rel=1e-9)


def test_fitted_zone_covers_the_zone_with_its_parameters(
    moderate: tuple[PositionSeries, ZoneFit | None],
) -> None:
    real, fit = moderate
    assert fit is not None
    inside, away = true_zone(real)
    assert np.mean(fit.in_zone[inside]) >= 0.8
    assert np.mean(fit.in_zone[~inside]) <= 0.1
    eff, se = fit.effect, fit.se
    assert set(se) == set(fit.effect.to_params()) - {"name"}
    assert all(math.isfinite(se[k]) and se[k] > 0 for k in ("sigma_m", "tau_s", "bias_m"))
    assert 1.5 / 1.5 <= eff.sigma_m <= 1.5 * 1.5
    assert abs(eff.sigma_m - 1.5) <= 3 * se["sigma_m"]
    assert 5.0 <= eff.tau_s <= 20.0
    # the bias: its size along the fitted wall's normal, and the freely fitted in-zone
    # vector's direction against the mean away-from-wall direction of the true zone
    assert abs(eff.bias_m - 1.5) <= 2.5 * se["bias_m"]
    want = away[:, inside].mean(axis=1)
    got = fit.bias_en_m
    err = math.atan2(got[0] * want[1] - got[1] * want[0], got @ want)
    se_dir = math.sqrt(float(np.max(np.diag(fit.bias_cov)))) / float(np.hypot(*got))
    assert abs(err) <= 2.5 * se_dir
    # the wall is on the side opposite the bias: away from it is the bias direction
    te, tn = truth_track_m(real)
    _d, ux, uy = eff.distance_to_wall_m(te, tn)
    assert np.all(ux[fit.in_zone] * got[0] + uy[fit.in_zone] * got[1] > 0)


def test_adding_the_fitted_zone_matches_the_real_rms_in_the_zone(
    runs: list[PositionSeries], moderate: tuple[PositionSeries, ZoneFit | None]
) -> None:
    real, fit = moderate
    assert fit is not None
    inside, _away = true_zone(real)
    rng = np.random.default_rng(5)

    def rms(s: PositionSeries, sel: np.ndarray) -> float:
        return float(np.sqrt(np.mean(s.east_m[sel] ** 2 + s.north_m[sel] ** 2)))

    real_rms = rms(real, inside)
    base = np.mean([rms(s, inside) for s in runs])
    fitted = np.mean([rms(fit.effect.apply(s, rng), inside) for s in runs])
    outside = np.mean([rms(fit.effect.apply(s, rng), ~inside) for s in runs])
    assert real_rms / base > 1.5  # the zone is a gap the baseline does not close
    assert abs(math.log(fitted / real_rms)) < 0.15
    assert abs(math.log(outside / np.mean([rms(s, ~inside) for s in runs]))) < 0.02


def test_zone_without_bias_and_weak_zone(runs: list[PositionSeries]) -> None:
    real = log_with(zone_of(0.5, 0.0), seed=32)
    fit = fit_zone(real, runs, layout_for(real))
    assert fit is not None
    inside, _away = true_zone(real)
    assert np.mean(fit.in_zone[inside]) >= 0.8 and np.mean(fit.in_zone[~inside]) <= 0.1
    assert abs(fit.effect.sigma_m - 0.5) <= 3 * fit.se["sigma_m"]
    assert abs(fit.effect.bias_m) <= 3 * fit.se["bias_m"]


def test_null_and_static_logs_give_no_zone(runs: list[PositionSeries]) -> None:
    for seed in (41, 42, 43):
        real = log_with(seed=seed)
        fit = fit_zone(real, runs, layout_for(real))
        assert fit is None or np.mean(fit.in_zone) < 0.02
    static = log_with(zone_of(1.5, 1.5), seed=44, moving=False)
    static_runs = [surrogate_run(T_S, 1.0, np.random.default_rng(500 + i)) for i in range(3)]
    assert not layout_for(static).moving
    assert FITTERS["multipath_zone"](static, static_runs, layout_for(static)) is None


def test_null_logs_rarely_give_a_zone(runs: list[PositionSeries]) -> None:
    found = 0
    for seed in range(600, 620):
        real = log_with(seed=seed)
        fit = fit_zone(real, runs, layout_for(real))
        found += fit is not None and np.mean(fit.in_zone) >= 0.02
    assert found <= 1


def test_registered_as_a_gap_candidate(
    runs: list[PositionSeries], moderate: tuple[PositionSeries, ZoneFit | None]
) -> None:
    real, fit = moderate
    assert fit is not None
    assert set(FINGERPRINTS["multipath_zone"]) == {"log_rms_place", "log_step_std_place"}
    got = FITTERS["multipath_zone"](real, runs, layout_for(real))
    assert got is not None and got.name == "multipath_zone"
    assert got.params == {k: v for k, v in fit.effect.to_params().items() if k != "name"}


@pytest.mark.slow
def test_diagnosis_names_the_zone_and_writes_it_in_the_scenario_frame(
    runs: list[PositionSeries], tmp_path: Path
) -> None:
    # The whole pipeline on a log with a zone: the verdict names it, map.png draws it, and
    # effects.toml moves the wall from the log's frame into the scenario origin's frame.
    import tomllib

    from sim_backend.effects import metres_per_degree
    from x6wd.gap.diagnose import diagnose, report_dict
    from x6wd.gap.report import write_report

    real = log_with(zone_of(1.5, 1.0), seed=32)
    d = diagnose(real, runs, np.random.default_rng(1))
    rep = report_dict(d)
    assert rep["verdict"] == {"effect": "multipath_zone", "explained": True}
    assert any(w["place"] != "all" for w in rep["where"])  # the gap is local on the map
    zone = d.selected[0].effect
    origin = (real.origin_lat_deg - 0.001, real.origin_lon_deg - 0.002)  # south-west
    write_report(d, tmp_path, figures=True, origin_deg=origin)
    eff = tomllib.loads((tmp_path / "effects.toml").read_text())["effects"][0]
    e_per, n_per = metres_per_degree(origin[0])
    assert eff["x1_m"] == pytest.approx(zone.x1_m + 0.002 * e_per, abs=0.01)
    assert eff["y2_m"] == pytest.approx(zone.y2_m + 0.001 * n_per, abs=0.01)
    assert (tmp_path / "map.png").stat().st_size > 0
    # the same origin written across the antimeridian (lon + 360 or - 360): the same frame
    from x6wd.gap.report import effects_toml

    for turn_deg in (360.0, -360.0):
        text = effects_toml(d, origin_deg=(origin[0], origin[1] + turn_deg))
        assert tomllib.loads(text)["effects"][0]["x1_m"] == pytest.approx(eff["x1_m"], abs=0.01)
