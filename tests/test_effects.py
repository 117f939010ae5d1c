"""The composable error layers of sim_backend.effects: physics, exactness, parameters."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from sim_backend.effects import (
    EFFECT_NAMES,
    EFFECTS,
    Bias,
    CompassPhysics,
    Correction,
    Declination,
    GaussMarkov,
    HardIron,
    HeadingLag,
    HeadingNoise,
    HeadingSeries,
    Jumps,
    Latency,
    MultipathZone,
    NavFilter,
    NoiseScale,
    Outages,
    PositionSeries,
    Quantization,
    RandomWalk,
    SoftIron,
    StaticHold,
    Tilt,
    delay_errors,
    effect_from_params,
    interp_track,
    quantization_step_m,
    tilted_heading_deg,
    truth_track_m,
    wrap180,
)
from x6wd.core.errors import ConfigError


def zeros(n: int, dt: float = 1.0, **kw: object) -> PositionSeries:
    t = np.arange(n) * dt
    z = np.zeros(n)
    return PositionSeries(t, z, z, z, np.ones(n, dtype=bool), 51.7, 19.5, **kw)  # type: ignore[arg-type]


def compass(h: np.ndarray, pitch: float = 0.0, roll: float = 0.0) -> HeadingSeries:
    n = h.size
    return HeadingSeries(
        np.arange(n) * 0.1, h, np.full(n, pitch), np.full(n, roll), true_heading_deg=h
    )


def gm_estimates(x: np.ndarray, dt: float) -> tuple[float, float]:
    """(sigma, tau) of an ensemble of GM rows: pooled std and tau from lag-1 correlation."""
    sigma = float(np.sqrt(np.mean(x**2)))
    r1 = float(np.mean(x[:, 1:] * x[:, :-1]) / np.mean(x**2))
    return sigma, -dt / math.log(r1)


@pytest.mark.parametrize("rate_hz", [1.0, 4.0])
def test_gauss_markov_reproduces_sigma_and_tau_at_any_rate(rate_hz: float) -> None:
    dt = 1.0 / rate_hz
    sigma_m, tau_s = 0.7, 30.0
    eff = GaussMarkov(sigma_m=sigma_m, tau_s=tau_s, axes="e")
    rows = np.array(
        [
            eff.apply(zeros(int(600 * rate_hz), dt), np.random.default_rng(i)).east_m
            for i in range(200)
        ]
    )
    sigma, tau = gm_estimates(rows, dt)
    assert sigma == pytest.approx(sigma_m, rel=0.03)
    assert tau == pytest.approx(tau_s, rel=0.08)
    # stationary start: the first sample already has the full variance
    assert float(np.std(rows[:, 0])) == pytest.approx(sigma_m, rel=0.15)


def test_gauss_markov_exact_with_irregular_steps() -> None:
    rng = np.random.default_rng(3)
    t = np.cumsum(rng.uniform(0.2, 3.0, 400))
    base = PositionSeries(t, np.zeros(400), np.zeros(400), np.zeros(400), np.ones(400, dtype=bool))
    eff = GaussMarkov(sigma_m=1.0, tau_s=5.0, axes="n")
    x = np.array([eff.apply(base, np.random.default_rng(i)).north_m for i in range(300)])
    phi = np.exp(-np.diff(t) / 5.0)
    # E[x_k x_{k+1}] = phi_k for unit variance: check the regression on the exact phi
    c = np.mean(x[:, 1:] * x[:, :-1], axis=0)
    assert float(np.mean(c / phi)) == pytest.approx(1.0, abs=0.05)
    assert float(np.mean(x**2)) == pytest.approx(1.0, abs=0.06)


def test_random_walk_variance_grows_as_q2_t() -> None:
    eff = RandomWalk(q_m_per_sqrt_s=0.1, axes="e")
    x = np.array([eff.apply(zeros(401, 0.5), np.random.default_rng(i)).east_m for i in range(300)])
    assert float(np.var(x[:, -1])) == pytest.approx(0.01 * 200.0, rel=0.2)
    assert np.all(x[:, 0] == 0.0)


@pytest.mark.parametrize("decimals", [4, 5])
def test_quantization_step_is_exact(decimals: int) -> None:
    rng = np.random.default_rng(1)
    s = GaussMarkov(3.0, 20.0).apply(zeros(500), rng)
    q = Quantization(decimals).apply(s, rng)
    step_e, step_n = quantization_step_m(decimals, 51.7)
    for vals, step, orig in ((q.north_m, step_n, s.north_m), (q.east_m, step_e, s.east_m)):
        # lattice positions relative to the origin's own rounding: integer multiples of the step
        k = (vals - vals[0]) / step
        assert np.max(np.abs(k - np.round(k))) < 1e-6
        assert np.max(np.abs(vals - orig)) <= step / 2 + 1e-9
    # the step itself: 1e-4 minute of latitude is 0.185 m (REFERENCE §6)
    assert quantization_step_m(4, 51.7)[1] == pytest.approx(0.1855, abs=0.0005)


def test_quantization_idempotent_and_moving() -> None:
    rng = np.random.default_rng(2)
    s = GaussMarkov(1.0, 20.0).apply(
        zeros(300, speed_mps=np.full(300, 2.0), course_deg=np.full(300, 45.0)), rng
    )
    q = Quantization(5).apply(s, rng)
    q2 = Quantization(5).apply(q, rng)
    assert np.allclose(q.east_m, q2.east_m, atol=1e-9) and np.allclose(
        q.north_m, q2.north_m, atol=1e-9
    )
    assert not np.allclose(q.east_m, s.east_m)


def test_bias_and_gm_commute_and_inputs_unchanged() -> None:
    s = zeros(200)
    before = s.east_m.copy()
    a = Bias(1.0, -2.0, 0.5).apply(
        GaussMarkov(0.5, 10.0).apply(s, np.random.default_rng(5)), np.random.default_rng(9)
    )
    b = GaussMarkov(0.5, 10.0).apply(
        Bias(1.0, -2.0, 0.5).apply(s, np.random.default_rng(9)), np.random.default_rng(5)
    )
    assert (
        np.allclose(a.east_m, b.east_m)
        and np.allclose(a.north_m, b.north_m)
        and np.allclose(a.up_m, b.up_m)
    )
    assert np.array_equal(s.east_m, before)
    assert float(np.mean(a.north_m)) == pytest.approx(-2.0, abs=0.5)


def test_jumps_at_satellite_set_changes_only() -> None:
    nsats = np.array([7] * 50 + [8] * 50 + [6] * 50)
    s = zeros(150, nsats=nsats)
    j = Jumps(sigma_m=2.0).apply(s, np.random.default_rng(1))
    steps = np.flatnonzero(np.diff(j.east_m) != 0.0) + 1
    assert set(steps) <= {50, 100} and len(steps) >= 1
    # without nsats: Poisson changes at about rate * duration
    k = [
        np.count_nonzero(
            np.diff(Jumps(1.0, rate_per_s=0.05).apply(zeros(2000), np.random.default_rng(i)).east_m)
        )
        for i in range(20)
    ]
    assert float(np.mean(k)) == pytest.approx(0.05 * 1999, rel=0.15)
    # trigger "poisson" ignores the satellite count; "sat_change" never jumps without one
    s2 = zeros(2000, nsats=np.full(2000, 8))
    k = [
        np.count_nonzero(np.diff(Jumps(1.0, 0.05, trigger="poisson").apply(s2, rng).east_m))
        for rng in map(np.random.default_rng, range(20))
    ]
    assert float(np.mean(k)) == pytest.approx(0.05 * 1999, rel=0.15)
    flat = Jumps(1.0, 0.05, trigger="sat_change").apply(zeros(500), np.random.default_rng(0))
    assert np.count_nonzero(np.diff(flat.east_m)) == 0
    with pytest.raises(ConfigError, match="trigger"):
        Jumps(1.0, trigger="sometimes")


def test_outages_two_state_means() -> None:
    eff = Outages(mean_up_s=60.0, mean_down_s=10.0)
    up = np.concatenate(
        [eff.states(np.arange(20000) * 0.5, np.random.default_rng(i)) for i in range(3)]
    )
    assert float(np.mean(up)) == pytest.approx(60 / 70, abs=0.03)
    d = np.diff(np.concatenate(([1], up.astype(int), [1])))
    downs = (np.flatnonzero(d == 1) - np.flatnonzero(d == -1)) * 0.5
    assert float(np.mean(downs)) == pytest.approx(10.0, rel=0.2)
    assert not Outages(60, 10).apply(zeros(5000), np.random.default_rng(1)).valid.all()


def test_latency_reports_the_truth_of_delay_earlier() -> None:
    s = zeros(100, speed_mps=np.full(100, 2.0), course_deg=np.full(100, 90.0))
    out = Latency(delay_s=0.5).apply(s, np.random.default_rng(0))
    assert np.allclose(out.east_m, -1.0) and np.allclose(out.north_m, 0.0)
    assert np.array_equal(
        Latency(0.5).apply(zeros(10), np.random.default_rng(0)).east_m, np.zeros(10)
    )


def test_truth_track_integrates_velocity() -> None:
    s = zeros(11, speed_mps=np.full(11, 3.0), course_deg=np.full(11, 0.0))
    e, n = truth_track_m(s)
    assert np.allclose(n, 3.0 * np.arange(11)) and np.allclose(e, 0.0)


def test_multipath_zone_only_near_the_wall() -> None:
    # drive east along y=0 from x=0 at 1 m/s; wall along x=50..60 at y=-2
    s = zeros(120, speed_mps=np.full(120, 1.0), course_deg=np.full(120, 90.0))
    mz = MultipathZone(50.0, -2.0, 60.0, -2.0, distance_m=3.0, sigma_m=0.0, bias_m=1.5)
    out = mz.apply(s, np.random.default_rng(0))
    inside = (np.arange(120) >= 50) & (np.arange(120) <= 60)
    assert np.allclose(out.north_m[inside], 1.5)  # pushed away from the wall (north)
    assert np.allclose(out.north_m[~inside & (np.abs(np.arange(120) - 55) > 8)], 0.0)


def test_hard_iron_once_per_turn_and_field_magnitude() -> None:
    h = np.arange(0.0, 360.0, 1.0)
    out = HardIron(bx_ut=2.0, by_ut=0.0, horizontal_field_ut=20.0).apply(
        compass(h), np.random.default_rng(0)
    )
    err = np.radians(wrap180(out.heading_deg - h))
    spec = np.abs(np.fft.rfft(err))
    assert int(np.argmax(spec[1:])) + 1 == 1  # dominant harmonic: once per turn
    assert float(np.max(np.abs(err))) == pytest.approx(math.asin(0.1), rel=0.02)
    assert out.field_ut is not None and np.ptp(out.field_ut) == pytest.approx(4.0, rel=0.01)


def test_soft_iron_twice_per_turn() -> None:
    h = np.arange(0.0, 360.0, 1.0)
    out = SoftIron(k=0.05, axis_deg=20.0).apply(compass(h), np.random.default_rng(0))
    err = np.radians(wrap180(out.heading_deg - h))
    spec = np.abs(np.fft.rfft(err))
    assert int(np.argmax(spec[1:])) + 1 == 2
    assert float(np.max(np.abs(err))) == pytest.approx(0.05, rel=0.1)


def test_tilt_error_is_tilt_times_tan_inclination() -> None:
    # nose up 2 deg heading east: the classic uncompensated error ~ pitch * tan(I) * sin(h)
    err = wrap180(
        tilted_heading_deg(np.array([90.0]), np.array([2.0]), np.array([0.0]), 66.0) - 90.0
    )
    assert abs(float(err[0])) == pytest.approx(2.0 * math.tan(math.radians(66.0)), rel=0.1)
    h = np.arange(0.0, 360.0, 2.0)
    out = Tilt(fraction=1.0, inclination_deg=66.0).apply(
        compass(h, pitch=2.0), np.random.default_rng(0)
    )
    spec = np.abs(np.fft.rfft(np.radians(wrap180(out.heading_deg - h))))
    assert int(np.argmax(spec[1:])) + 1 == 1
    flat = Tilt(fraction=1.0).apply(compass(h), np.random.default_rng(0))
    assert np.allclose(wrap180(flat.heading_deg - h), 0.0, atol=1e-9)


def test_pitch_roll_clamped_to_85() -> None:
    out = HeadingNoise(0.0).apply(
        compass(np.zeros(3), pitch=89.0, roll=-120.0), np.random.default_rng(0)
    )
    assert np.all(out.pitch_deg == 85.0) and np.all(out.roll_deg == -85.0)


def test_declination_and_noise_commute() -> None:
    s = compass(np.linspace(0, 359, 50))
    a = HeadingNoise(1.0).apply(
        Declination(4.0).apply(s, np.random.default_rng(0)), np.random.default_rng(1)
    )
    b = Declination(4.0).apply(
        HeadingNoise(1.0).apply(s, np.random.default_rng(1)), np.random.default_rng(0)
    )
    assert np.allclose(wrap180(a.heading_deg - b.heading_deg), 0.0, atol=1e-9)


def test_heading_lag_exact_first_order_across_north() -> None:
    t = np.arange(0, 3.0, 0.05)
    h = np.where(t < 0.5, 350.0, 10.0)  # a 20 deg step across north at t = 0.5 s
    s = HeadingSeries(t, h, np.zeros(t.size), np.zeros(t.size))
    out = HeadingLag(tau_s=0.3).apply(s, np.random.default_rng(0))
    k = np.flatnonzero(t >= 0.5)
    expected = 10.0 - 20.0 * np.exp(-(t[k] - t[k[0] - 1]) / 0.3)
    assert np.allclose(wrap180(out.heading_deg[k] - expected), 0.0, atol=1e-9)


def test_params_round_trip_for_every_effect() -> None:
    examples = {
        "gauss_markov": GaussMarkov(0.5, 60.0, "enu"),
        "random_walk": RandomWalk(0.01),
        "bias": Bias(1.0, 2.0, 3.0),
        "quantization": Quantization(4),
        "jumps": Jumps(1.0, 0.02, 0.5),
        "outages": Outages(100.0, 5.0),
        "latency": Latency(0.3),
        "multipath_zone": MultipathZone(0, 0, 10, 0, 5.0, 1.0, 0.5, 20.0),
        "nav_filter": NavFilter(20.0, 2, "enu"),
        "noise_scale": NoiseScale(0.3, 8.0),
        "static_hold": StaticHold(0.4, 0.2),
        "correction": Correction(0.5, 120.0),
        "hard_iron": HardIron(1.0, -2.0),
        "soft_iron": SoftIron(0.03, 10.0),
        "tilt": Tilt(0.5, 60.0),
        "declination": Declination(5.5),
        "heading_lag": HeadingLag(0.21),
    }
    assert set(examples) == set(EFFECT_NAMES) and set(EFFECT_NAMES) <= set(EFFECTS)
    for name, eff in examples.items():
        table = eff.to_params()
        assert table["name"] == name
        assert effect_from_params(table) == eff


def test_bad_parameters_are_named_errors() -> None:
    with pytest.raises(ConfigError, match="tau_s"):
        GaussMarkov(1.0, 0.0)
    with pytest.raises(ConfigError, match="unknown parameter"):
        effect_from_params({"name": "bias", "east": 1.0})
    with pytest.raises(ConfigError, match="unknown name"):
        effect_from_params({"name": "nope"})
    with pytest.raises(ConfigError, match="axes"):
        GaussMarkov(1.0, 1.0, axes="x")


# --- one way to run a GPS layer: start(rng) -> step(batch) ---------------------------------


GPS_LAYERS = [
    GaussMarkov(1.0, 20.0, axes="enu"),
    RandomWalk(0.1),
    Bias(1.0, -2.0, 0.5),
    Quantization(4),
    Jumps(2.0, rate_per_s=0.05, up_sigma_m=1.0),
    Outages(30.0, 5.0),
    Latency(0.7),
    MultipathZone(0.0, -3.0, 50.0, -3.0, distance_m=30.0, sigma_m=1.0, bias_m=2.0),
    NavFilter(5.0, order=2),
    NoiseScale(2.0, split_tau_s=4.0),
    Correction(0.4, tau_s=30.0),
    StaticHold(0.3, speed_threshold_mps=2.0),
]


@pytest.mark.parametrize("layer", GPS_LAYERS, ids=lambda e: e.name)
def test_apply_is_the_run_stepped_once(layer: object) -> None:
    s = zeros(300, 0.5, speed_mps=np.full(300, 1.5), course_deg=np.full(300, 80.0),
              nsats=np.repeat([7, 8, 6], 100))  # fmt: skip
    got = layer.apply(s, np.random.default_rng(4))  # type: ignore[attr-defined]
    run = layer.start(np.random.default_rng(4))  # type: ignore[attr-defined]
    want = run.step(s)
    if run.delay_s:  # a delay moves what the receiver solves for; on errors: delay_errors
        assert run.delay_s == 0.7 and np.array_equal(want.east_m, s.east_m)
        want = delay_errors(want, run.delay_s)
    for name in ("east_m", "north_m", "up_m", "valid"):
        assert np.array_equal(getattr(got, name), getattr(want, name)), name
    assert layer.kind == "gps"  # type: ignore[attr-defined]


def _stepwise(layer: object, s: PositionSeries, rng: np.random.Generator) -> PositionSeries:
    """``layer`` run on ``s`` one epoch at a time (as the receiver runs it in closed loop)."""
    run = layer.start(rng)  # type: ignore[attr-defined]
    parts = [run.step(_epoch(s, i)) for i in range(len(s))]
    return s.with_(
        east_m=np.concatenate([p.east_m for p in parts]),
        north_m=np.concatenate([p.north_m for p in parts]),
        up_m=np.concatenate([p.up_m for p in parts]),
        valid=np.concatenate([p.valid for p in parts]),
    )


def _epoch(s: PositionSeries, i: int) -> PositionSeries:
    one = slice(i, i + 1)
    te, tn = truth_track_m(s)
    return s.with_(
        t_s=s.t_s[one], east_m=s.east_m[one], north_m=s.north_m[one], up_m=s.up_m[one],
        valid=s.valid[one], true_east_m=te[one], true_north_m=tn[one],
        speed_mps=None if s.speed_mps is None else s.speed_mps[one],
        course_deg=None if s.course_deg is None else s.course_deg[one],
        nsats=None if s.nsats is None else s.nsats[one],
    )  # fmt: skip


@pytest.mark.parametrize(
    "layer",
    [
        Bias(1.0, -2.0, 0.5),
        Quantization(3),
        NavFilter(4.0, order=2, axes="enu"),
        NoiseScale(0.2, 6.0),
        Correction(3.0, 20.0),
        StaticHold(0.5, speed_threshold_mps=1.3),
    ],
    ids=lambda e: e.name,
)
def test_stateless_layers_epoch_by_epoch_equal_the_batch(layer: object) -> None:
    s = GaussMarkov(2.0, 10.0).apply(
        zeros(200, speed_mps=np.full(200, 1.2), course_deg=np.full(200, 30.0)),
        np.random.default_rng(1),
    )
    batch = layer.apply(s, np.random.default_rng(0))  # type: ignore[attr-defined]
    steps = _stepwise(layer, s, np.random.default_rng(0))
    np.testing.assert_allclose(steps.east_m, batch.east_m, rtol=0, atol=1e-9)
    np.testing.assert_allclose(steps.north_m, batch.north_m, rtol=0, atol=1e-9)


def test_gauss_markov_run_epoch_by_epoch_keeps_sigma_and_tau() -> None:
    dt, sigma_m, tau_s = 0.5, 0.7, 10.0
    eff = GaussMarkov(sigma_m, tau_s, axes="e")
    rows = np.array(
        [_stepwise(eff, zeros(400, dt), np.random.default_rng(i)).east_m for i in range(200)]
    )
    sigma, tau = gm_estimates(rows, dt)
    assert sigma == pytest.approx(sigma_m, rel=0.04)
    assert tau == pytest.approx(tau_s, rel=0.1)


def test_random_walk_run_continues_the_walk() -> None:
    eff = RandomWalk(q_m_per_sqrt_s=0.1, axes="e")
    x = np.array(
        [_stepwise(eff, zeros(201, 0.5), np.random.default_rng(i)).east_m for i in range(300)]
    )
    assert np.all(x[:, 0] == 0.0)
    assert float(np.var(x[:, -1])) == pytest.approx(0.01 * 100.0, rel=0.2)


def test_jumps_run_changes_only_with_the_satellite_set_across_steps() -> None:
    nsats = np.array([7] * 30 + [8] * 30 + [6] * 30)
    j = _stepwise(Jumps(sigma_m=2.0), zeros(90, nsats=nsats), np.random.default_rng(1))
    steps = set(np.flatnonzero(np.diff(j.east_m) != 0.0) + 1)
    assert steps == {30, 60}
    # Poisson events at about rate * duration when the series has no satellite count
    k = [
        np.count_nonzero(np.diff(_stepwise(Jumps(1.0, 0.05), zeros(400), rng).east_m))
        for rng in map(np.random.default_rng, range(20))
    ]
    assert float(np.mean(k)) == pytest.approx(0.05 * 399, rel=0.2)


def test_outages_run_keeps_the_two_state_means() -> None:
    eff = Outages(mean_up_s=20.0, mean_down_s=5.0)
    up = np.concatenate(
        [_stepwise(eff, zeros(3000), np.random.default_rng(i)).valid for i in range(3)]
    )
    assert float(np.mean(up)) == pytest.approx(0.8, abs=0.04)


def test_multipath_zone_run_uses_the_explicit_truth() -> None:
    # the truth given with each epoch (no velocity to integrate): inside 50..60 m east
    east = np.arange(120, dtype=float)
    s = zeros(120).with_(true_east_m=east, true_north_m=np.zeros(120))
    mz = MultipathZone(50.0, -2.0, 60.0, -2.0, distance_m=3.0, sigma_m=0.0, bias_m=1.5)
    out = _stepwise(mz, s, np.random.default_rng(0))
    inside = (east >= 50) & (east <= 60)
    assert np.allclose(out.north_m[inside], 1.5)
    assert np.allclose(out.north_m[np.abs(east - 55) > 8], 0.0)


def test_quantization_is_the_print_stage() -> None:
    assert Quantization(5).stage == 1
    assert all(e.stage == 0 for e in GPS_LAYERS if e.name != "quantization")


def test_delay_errors_with_an_explicit_truth_track() -> None:
    # truth given explicitly (east 2 m/s): half a second late is 1 m behind
    t = np.arange(10.0)
    s = zeros(10, speed_mps=np.full(10, 2.0), course_deg=np.full(10, 90.0)).with_(
        true_east_m=100.0 + 2.0 * t, true_north_m=np.zeros(10)
    )
    out = delay_errors(s, 0.5)
    assert np.allclose(out.east_m, -1.0) and np.allclose(out.north_m, 0.0)
    assert interp_track(t, np.column_stack([t]), np.array([3.0]), np.array([-1.0]))[0, 0] == -3.0


def test_compass_layers_act_on_the_emulations_physics() -> None:
    phys = CompassPhysics(20.0, np.eye(3), np.zeros(3), 1.0, 0.2)
    for layer in (Declination(2.0), HardIron(1.9, 0.0, 19.0), HeadingLag(0.1),
                  HeadingNoise(3.0), HeadingNoise(4.0), Tilt(0.5)):  # fmt: skip
        assert layer.kind == "compass"
        phys = layer.act_on(phys)
    assert phys.declination_deg == 3.0 and phys.lag_tau_s == pytest.approx(0.3)
    assert np.allclose(phys.b, [2.0, 0.0, 0.0])  # scaled to the emulation's 20 uT
    assert phys.noise_deg2 == pytest.approx(25.0) and [t.name for t in phys.tilt] == ["tilt"]
    k = SoftIron(0.1, 90.0).act_on(phys)
    assert np.allclose(np.diag(k.a), [0.9, 1.1, 1.0]) and np.allclose(k.b, [1.8, 0.0, 0.0])


# --- receiver-side layers: either direction against the model -------------------------------


def _white(n: int, sigma_m: float, seed: int, dt: float = 1.0, **kw: object) -> PositionSeries:
    rng = np.random.default_rng(seed)
    s = zeros(n, dt, **kw)
    return s.with_(
        east_m=sigma_m * rng.standard_normal(n),
        north_m=sigma_m * rng.standard_normal(n),
        up_m=sigma_m * rng.standard_normal(n),
    )


@pytest.mark.parametrize("dt", [0.2, 1.0])
def test_nav_filter_first_order_is_a_gauss_markov_of_the_white_noise(dt: float) -> None:
    # white noise of variance s^2 through y += g (x - y), g = 1 - exp(-dt/tau): a first-order
    # process of variance s^2 g / (2 - g) and lag-1 correlation 1 - g, at any rate
    tau_s, sigma_m = 6.0, 1.0
    out = NavFilter(tau_s).apply(_white(40_000, sigma_m, 3, dt), np.random.default_rng(0))
    g = -math.expm1(-dt / tau_s)
    x = out.east_m[100:]
    assert np.var(x) == pytest.approx(sigma_m**2 * g / (2 - g), rel=0.06)
    r1 = np.mean(x[1:] * x[:-1]) / np.mean(x * x)
    assert r1 == pytest.approx(1 - g, abs=0.01)
    assert np.array_equal(out.up_m, _white(40_000, sigma_m, 3, dt).up_m)  # axes "en"


def test_nav_filter_second_order_is_smoother_and_skips_outages() -> None:
    s = _white(4000, 1.0, 5)
    one = NavFilter(10.0).apply(s, np.random.default_rng(0))
    two = NavFilter(10.0, order=2).apply(s, np.random.default_rng(0))
    assert np.std(np.diff(two.east_m)) < 0.5 * np.std(np.diff(one.east_m))
    # no fix: the value there is passed through and the filter holds its state across it
    valid = np.ones(len(s), dtype=bool)
    valid[1000:1010] = False
    gap = NavFilter(10.0).apply(s.with_(valid=valid), np.random.default_rng(0))
    assert np.array_equal(gap.east_m[1000:1010], s.east_m[1000:1010])
    g = -math.expm1(-11.0 / 10.0)  # 11 s since the last fix
    want = gap.east_m[999] + g * (s.east_m[1010] - gap.east_m[999])
    assert gap.east_m[1010] == pytest.approx(want, abs=1e-12)


@pytest.mark.parametrize("factor", [0.25, 3.0])
def test_noise_scale_scales_the_fast_part_both_ways(factor: float) -> None:
    # a slow drift (tau 300 s) plus white noise: the steps scale by the factor (up to the
    # first-order split's leak: the low-passed white noise keeps some steps of its own),
    # the slow part (the spread of 60 s means) is kept
    base = GaussMarkov(3.0, 300.0).apply(_white(20_000, 0.5, 6), np.random.default_rng(7))
    out = NoiseScale(factor, split_tau_s=20.0).apply(base, np.random.default_rng(0))
    step_ratio = np.std(np.diff(out.east_m)) / np.std(np.diff(base.east_m))
    assert step_ratio == pytest.approx(factor, rel=0.12)
    means = [s.east_m[: 60 * 333].reshape(333, 60).mean(axis=1) for s in (base, out)]
    assert np.std(means[1]) == pytest.approx(np.std(means[0]), rel=0.12)


@pytest.mark.parametrize("factor", [0.3, 2.0])
def test_correction_scales_the_slow_part_both_ways(factor: float) -> None:
    base = GaussMarkov(3.0, 600.0).apply(_white(20_000, 0.5, 8), np.random.default_rng(9))
    out = Correction(factor, tau_s=10.0).apply(base, np.random.default_rng(0))
    means = [s.east_m[: 120 * 166].reshape(166, 120).mean(axis=1) for s in (base, out)]
    assert np.std(means[1]) / np.std(means[0]) == pytest.approx(factor, rel=0.1)
    # the fast part (steps) is that of the model
    assert np.std(np.diff(out.east_m)) == pytest.approx(np.std(np.diff(base.east_m)), rel=0.1)


def test_static_hold_freezes_until_the_exit_distance_and_releases_when_moving() -> None:
    base = RandomWalk(0.05).apply(_white(3000, 0.02, 10), np.random.default_rng(11))
    out = StaticHold(0.3).apply(base, np.random.default_rng(0))
    steps = np.hypot(np.diff(out.east_m), np.diff(out.north_m))
    assert np.mean(steps == 0.0) > 0.9  # held most of the time
    # each release moves to the current solution, at least exit_distance_m from the hold
    moved = np.flatnonzero(steps > 0) + 1
    assert moved.size > 5
    assert np.allclose(out.east_m[moved], base.east_m[moved])
    assert np.all(steps[moved - 1] > 0.3 - 1e-9)
    # a held fix never lies farther than exit_distance_m from the solution
    assert np.all(np.hypot(out.east_m - base.east_m, out.north_m - base.north_m) <= 0.3 + 1e-9)
    # moving above the threshold: no hold at all
    fast = base.with_(speed_mps=np.full(3000, 1.0), course_deg=np.zeros(3000))
    free = StaticHold(0.3, speed_threshold_mps=0.5).apply(fast, np.random.default_rng(0))
    assert np.array_equal(free.east_m, fast.east_m)


@pytest.mark.parametrize(
    ("table", "key"),
    [
        ({"name": "nav_filter", "tau_s": 0.0}, "tau_s"),
        ({"name": "nav_filter", "tau_s": 1.0, "order": 3}, "order"),
        ({"name": "noise_scale", "factor": -1.0}, "factor"),
        ({"name": "correction", "factor": 0.5, "tau_s": 0.0}, "tau_s"),
        ({"name": "static_hold", "exit_distance_m": 0.0}, "exit_distance_m"),
        ({"name": "static_hold", "exit_distance_m": 1.0, "speed_threshold_mps": -1}, "speed"),
    ],
)
def test_receiver_layers_name_a_bad_parameter(table: dict[str, object], key: str) -> None:
    with pytest.raises(ConfigError, match=key):
        effect_from_params(table)


@pytest.mark.parametrize("tau_s", [0.05, 3.0, 400.0])
def test_low_pass_over_outages_is_the_recursion(tau_s: float) -> None:
    # the vectorised closed form over irregular steps (outages of up to 300 s, blocks of 500
    # time constants) against the recursion it replaces, y += g (x - y) with the actual step
    rng = np.random.default_rng(3)
    s = _white(3000, 2.0, 8)
    valid = rng.random(len(s)) > 0.3
    valid[1000:1300] = False
    out = NavFilter(tau_s).apply(s.with_(valid=valid), rng)
    idx = np.flatnonzero(valid)
    y, want = s.east_m[idx[0]], [s.east_m[idx[0]]]
    for prev, k in itertools.pairwise(idx):
        y += -math.expm1(-(s.t_s[k] - s.t_s[prev]) / tau_s) * (s.east_m[k] - y)
        want.append(y)
    assert np.allclose(out.east_m[idx], want, rtol=0, atol=1e-9)
    assert np.array_equal(out.east_m[~valid], s.east_m[~valid])


def test_second_order_gauss_markov_is_smooth_with_its_sigma_and_tau() -> None:
    # critically damped: autocorrelation (1 + lag/tau) exp(-lag/tau), steps far smaller than
    # a first-order drift's of the same sigma and tau; run whole or epoch by epoch alike
    dt, sigma_m, tau_s = 1.0, 0.7, 20.0
    smooth, rough = GaussMarkov(sigma_m, tau_s, "e", order=2), GaussMarkov(sigma_m, tau_s, "e")
    rngs = [np.random.default_rng(i) for i in range(200)]
    rows = np.array([smooth.apply(zeros(600, dt), rng).east_m for rng in rngs])
    stepped = np.array([_stepwise(smooth, zeros(600, dt), rng).east_m for rng in rngs])
    first = np.array([rough.apply(zeros(600, dt), rng).east_m for rng in rngs])
    for x in (rows, stepped):
        assert float(np.sqrt(np.mean(x**2))) == pytest.approx(sigma_m, rel=0.05)
        acf_tau = float(np.mean(x[:, 20:] * x[:, :-20]) / np.mean(x**2))
        assert acf_tau == pytest.approx(2.0 * math.exp(-1.0), abs=0.05)
        assert float(np.std(x[:, 0])) == pytest.approx(sigma_m, rel=0.15)  # stationary start
    assert float(np.std(np.diff(rows))) < 0.25 * float(np.std(np.diff(first)))
    with pytest.raises(ConfigError, match="order"):
        GaussMarkov(1.0, 1.0, order=3)
    assert effect_from_params(smooth.to_params()) == smooth


@pytest.mark.parametrize("tau_s", [5.0, 60.0, 3000.0])
def test_second_order_regular_steps_in_c_match_the_recursion(tau_s: float) -> None:
    # one step everywhere runs as IIR filters plus F^k x0 in closed form: the same numbers
    # as the 2 x 2 recursion on the same noise
    from sim_backend.effects import _gm2_regular, gm2_transition

    rng = np.random.default_rng(0)
    x0, w = rng.normal(size=(2, 3)), rng.normal(size=(500, 2, 3))
    f, q = gm2_transition(1.0, tau_s, 4.0)
    chol = np.linalg.cholesky(q)
    fast = np.empty((3, 500))
    last = _gm2_regular(x0, 1.0, tau_s, f, chol, w, fast)
    x, loop = x0.copy(), np.empty((3, 500))
    for k in range(500):
        x = f @ x + chol @ w[k]
        loop[:, k] = x[0]
    np.testing.assert_allclose(fast, loop, rtol=0, atol=1e-9)
    np.testing.assert_allclose(last, x, rtol=0, atol=1e-9)
