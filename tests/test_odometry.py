"""Wheel odometry: the simulated encoders (sim_backend.odometry), the dead reckoning and its
covariance (x6wd.nav.odometry), and the encoders behind the HIL motor board."""

from __future__ import annotations

import math
import time
from collections.abc import Iterator, Sequence

import numpy as np
import pytest

from drivers import registry
from drivers.motors import SerialMotorLink
from sim_backend import hil
from sim_backend.odometry import EncoderParams, EncoderSim, encoder_rng
from sim_backend.vehicle import Terrain, Vehicle, VehicleParams, VehicleState
from x6wd.core.config import OdometryConfig
from x6wd.core.errors import ConfigError
from x6wd.core.records import WheelOdometry
from x6wd.nav.odometry import DeadReckoning, increment, wheel_travel_m

TRUE = EncoderParams()
CALIBRATED = OdometryConfig(
    counts_per_rev=TRUE.counts_per_rev,
    left_diameter_m=TRUE.left_diameter_m,
    right_diameter_m=TRUE.right_diameter_m,
    track_m=TRUE.effective_track_m,
    k_left_m=TRUE.k_left_m,
    k_right_m=TRUE.k_right_m,
)


def drive(
    legs: Sequence[tuple[float, float, float]],
    enc: EncoderSim,
    *,
    terrain: Terrain | None = None,
    dt_s: float = 0.02,
    heading_deg: float = 0.0,
) -> tuple[Vehicle, list[tuple[VehicleState, int, int]]]:
    """Drive (left %, right %, seconds) legs; every physics step's state and its counts."""
    v = Vehicle(VehicleParams(motor_tau_s=0.0), heading_deg=heading_deg, terrain=terrain)
    enc.step(0.0, v.state)
    out = []
    for left, right, secs in legs:
        v.command(left, right)
        for _ in range(round(secs / dt_s)):
            s = v.step(dt_s)
            dl, dr = enc.step(dt_s, s)
            out.append((s, dl, dr))
    return v, out


# --- simulated encoders ----------------------------------------------------------------------


def test_straight_counts_follow_the_true_wheel_diameters() -> None:
    enc = EncoderSim()  # no rng: systematic errors only
    v, steps = drive([(50, 50, 10.0)], enc)
    dist_m = v.state.odometer_m
    left, right = enc.counts
    assert sum(dl for _, dl, _ in steps) == left
    assert abs(left - dist_m * TRUE.counts_per_m("left")) <= 1
    assert abs(right - dist_m * TRUE.counts_per_m("right")) <= 1
    assert right > left  # the smaller right wheel turns more often for the same distance
    # with the nominal wheel the odometry reads long on the right, short on the left
    nominal = OdometryConfig(counts_per_rev=TRUE.counts_per_rev)
    left_m, right_m = wheel_travel_m(nominal, left, right)
    assert left_m == pytest.approx(dist_m * 0.120 / 0.1212, rel=1e-4)
    assert right_m == pytest.approx(dist_m * 0.120 / 0.1188, rel=1e-4)


def test_turning_wheels_roll_the_effective_track() -> None:
    enc = EncoderSim()
    v, _ = drive([(60, -60, 2.0)], enc)  # pivot clockwise: 108 degrees
    turned_rad = math.radians(v.state.heading_deg)
    left_m, right_m = enc.wheel_travel_m
    assert left_m == pytest.approx(0.5 * turned_rad * TRUE.effective_track_m, rel=1e-9)
    assert right_m == pytest.approx(-left_m, rel=1e-9)
    # what a calibrated odometry makes of the counts is the true turn
    inc = increment(CALIBRATED, *enc.counts)
    assert inc.heading_change_deg == pytest.approx(v.state.heading_deg, abs=0.05)
    assert abs(inc.distance_m) < 1e-3


@pytest.mark.parametrize("heading_deg", [0.0, 180.0])
def test_wheels_slip_uphill_and_skid_downhill(heading_deg: float) -> None:
    slope = Terrain(grad_north=math.tan(math.radians(10)))  # rises northward
    enc = EncoderSim(EncoderParams(slope_slip=0.3))
    v, _ = drive([(50, 50, 4.0)], enc, terrain=slope, heading_deg=heading_deg)
    ratio = enc.wheel_travel_m[0] / v.state.odometer_m
    uphill = heading_deg == 0.0
    assert ratio == pytest.approx(1 + (0.3 if uphill else -0.3) * math.sin(math.radians(10)))


def test_backwards_counts_down() -> None:
    enc = EncoderSim()
    v, _ = drive([(-40, -40, 3.0)], enc)
    assert enc.counts[0] < 0 and enc.counts[1] < 0
    assert -enc.wheel_travel_m[0] == pytest.approx(v.state.odometer_m)


def test_noise_variance_grows_with_distance_not_with_the_step_rate() -> None:
    """Seed 003: a side's travel error has variance k·|travel|, whatever the step rate."""
    p = EncoderParams(k_left_m=1e-3, k_right_m=4e-3)

    def errors(dist_m: float, n_steps: int, seed: int) -> tuple[float, float]:
        enc = EncoderSim(p, rng=np.random.default_rng(seed))
        s0 = Vehicle().state
        enc.step(0.0, s0)
        for k in range(1, n_steps + 1):
            enc.step(0.1, _moved(s0, dist_m * k / n_steps))
        return enc.wheel_travel_m[0] - dist_m, enc.wheel_travel_m[1] - dist_m

    runs = 400
    for dist_m, n_steps in ((5.0, 50), (20.0, 50), (20.0, 10)):
        err = np.array([errors(dist_m, n_steps, seed) for seed in range(runs)])
        var = err.var(axis=0)
        rel_se = math.sqrt(2 / runs)  # of a sample variance
        assert var[0] == pytest.approx(1e-3 * dist_m, rel=4 * rel_se)
        assert var[1] == pytest.approx(4e-3 * dist_m, rel=4 * rel_se)
        assert abs(np.corrcoef(err.T)[0, 1]) < 4 / math.sqrt(runs)  # sides independent


def _moved(s: VehicleState, dist_m: float, heading_deg: float = 0.0) -> VehicleState:
    h = math.radians(heading_deg)
    return VehicleState(
        s.t_s, dist_m * math.sin(h), dist_m * math.cos(h), 0.0, heading_deg, 1.0, 0.0,
        50.0, 50.0, 0.0, 0.0, dist_m,
    )  # fmt: skip


def test_reading_is_what_the_link_reports() -> None:
    enc = EncoderSim()
    drive([(50, 50, 1.0)], enc)
    first, second = enc.reading(1.0), enc.reading(1.05)
    assert (first.left_counts, first.right_counts) == enc.counts
    assert (first.seq, second.seq, second.t_s) == (1, 2, 1.05)


def test_odometry_section_is_range_checked() -> None:
    from x6wd.core import config

    cfg = config.loads("[odometry]\ntrack_m = 0.4\nk_left_m = 0.0\n").odometry
    assert (cfg.track_m, cfg.k_left_m, cfg.counts_per_rev) == (0.4, 0.0, 1632)
    with pytest.raises(ConfigError, match=r"odometry\.track_m: must be >= 0\.05"):
        config.loads("[odometry]\ntrack_m = 0.0\n")
    with pytest.raises(ConfigError, match=r"odometry\.counts_per_rev: expected an integer"):
        config.loads("[odometry]\ncounts_per_rev = 1632.5\n")


def test_encoder_params_are_checked() -> None:
    with pytest.raises(ConfigError, match="effective_track_m"):
        EncoderParams(effective_track_m=0.2)  # narrower than the wheels: impossible
    with pytest.raises(ConfigError, match="left_diameter_m"):
        EncoderParams(left_diameter_m=0.0)
    with pytest.raises(ConfigError, match="k_left_m"):
        EncoderParams(k_left_m=-1e-4)


def test_encoder_stream_is_its_own() -> None:
    a, b = encoder_rng(7).normal(size=3), encoder_rng(7).normal(size=3)
    assert np.array_equal(a, b)
    others = np.random.SeedSequence(7).spawn(4)  # SimRandom's streams
    assert not any(np.array_equal(a, np.random.default_rng(s).normal(size=3)) for s in others)


# --- dead reckoning --------------------------------------------------------------------------


def test_increment_and_its_covariance() -> None:
    cfg = OdometryConfig(counts_per_rev=1000, left_diameter_m=0.1, right_diameter_m=0.1,
                         track_m=0.5, k_left_m=1e-3, k_right_m=3e-3)  # fmt: skip
    inc = increment(cfg, 2000, 1000)  # left 2 turns: 0.628 m, right 0.314 m
    assert inc.left_m == pytest.approx(0.2 * math.pi)
    assert inc.distance_m == pytest.approx(0.15 * math.pi)
    assert inc.heading_change_deg == pytest.approx(math.degrees(0.1 * math.pi / 0.5))  # clockwise
    q_l, q_r = 1e-3 * 0.2 * math.pi, 3e-3 * 0.1 * math.pi
    assert inc.var_distance_m2 == pytest.approx((q_l + q_r) / 4)
    assert inc.var_heading_rad2 == pytest.approx((q_l + q_r) / 0.25)
    assert inc.cov_distance_heading_m_rad == pytest.approx((q_l - q_r) / 1.0)


def _records(steps: list[tuple[VehicleState, int, int]], every: int = 5) -> Iterator[WheelOdometry]:
    left = right = 0
    for k, (s, dl, dr) in enumerate(steps):
        left, right = left + dl, right + dr
        if k % every == every - 1:
            yield WheelOdometry(s.t_s, left, right, k // every + 1)


def test_calibrated_dead_reckoning_follows_the_true_path() -> None:
    legs = [(50, 50, 4.0), (60, 20, 6.0), (-30, 30, 2.0), (40, 40, 3.0)]
    enc = EncoderSim()
    v, steps = drive(legs, enc, heading_deg=30.0)
    dr = DeadReckoning(CALIBRATED, heading_deg=30.0)
    dr.update(WheelOdometry(0.0, 0, 0, 0))
    for rec in _records(steps):
        pose = dr.update(rec)
    s = v.state
    assert math.hypot(pose.east_m - s.east_m, pose.north_m - s.north_m) < 0.01
    assert (pose.heading_deg - s.heading_deg + 180) % 360 - 180 == pytest.approx(0, abs=0.1)
    # the nominal wheels and the geometric track get it badly wrong
    nominal = DeadReckoning(OdometryConfig(), heading_deg=30.0)
    nominal.update(WheelOdometry(0.0, 0, 0, 0))
    for rec in _records(steps):
        bad = nominal.update(rec)
    assert math.hypot(bad.east_m - s.east_m, bad.north_m - s.north_m) > 1.0


def test_covariance_matches_the_scatter_of_noisy_runs() -> None:
    """The propagated covariance (seed 003's k_l, k_r through the motion model) predicts the
    scatter of the dead-reckoned end pose over independent noisy runs. The noise is small
    enough (heading σ ~5°) for the linearised propagation to hold."""
    legs = [(50, 50, 3.0), (60, 30, 4.0)]
    p = EncoderParams(k_left_m=3e-5, k_right_m=6e-5)
    cfg = OdometryConfig(
        counts_per_rev=p.counts_per_rev, left_diameter_m=p.left_diameter_m,
        right_diameter_m=p.right_diameter_m, track_m=p.effective_track_m,
        k_left_m=p.k_left_m, k_right_m=p.k_right_m,
    )  # fmt: skip
    truth, _ = drive(legs, EncoderSim(p))
    ends = []
    for seed in range(300):
        _, steps = drive(legs, EncoderSim(p, rng=np.random.default_rng(seed)), dt_s=0.05)
        dr = DeadReckoning(cfg)
        dr.update(WheelOdometry(0.0, 0, 0, 0))
        for rec in _records(steps, every=4):
            pose = dr.update(rec)
        ends.append((pose.east_m, pose.north_m, math.radians(pose.heading_deg)))
    scatter = np.cov(np.array(ends).T)
    predicted = np.array(pose.cov)  # nearly the same path every run
    for i in range(3):
        assert scatter[i, i] == pytest.approx(predicted[i, i], rel=0.25)
    corr = predicted[0, 2] / math.sqrt(predicted[0, 0] * predicted[2, 2])
    emp = scatter[0, 2] / math.sqrt(scatter[0, 0] * scatter[2, 2])
    assert emp == pytest.approx(corr, abs=0.15)
    mean = np.array(ends).mean(axis=0)
    s = truth.state
    # unbiased but for the second-order pull of heading noise (E cos δψ ≈ 1 − σψ²/2: ~5 cm)
    assert math.hypot(mean[0] - s.east_m, mean[1] - s.north_m) < 0.1


# --- HIL: the daemon's motor link reads the simulated encoders ---------------------------------


@pytest.mark.integration
def test_hil_board_counts_the_simulated_wheels() -> None:
    w = hil.HilWorld(hil.HilParams(gps_rate_hz=1.0, gps_baud=115200, motor_tau_s=0.0))
    try:
        link = registry.open_motors("sim://", registry.Devices(backends={"sim": w}))
        assert isinstance(link, SerialMotorLink)
        first = link.read_odometry()
        assert first is not None
        e0, n0, _, _ = w.truth()
        deadline = time.monotonic() + 10.0
        while math.hypot(w.truth()[0] - e0, w.truth()[1] - n0) < 0.5:
            assert time.monotonic() < deadline, "the simulated robot did not move"
            assert link.drive(40, 40)
            time.sleep(0.02)
        link.stop()
        time.sleep(0.1)  # let the physics settle the last step
        last = link.read_odometry()
        assert last is not None and last.seq > first.seq
        e1, n1, _, _ = w.truth()
        moved_m = math.hypot(e1 - e0, n1 - n0)
        left_m, right_m = wheel_travel_m(CALIBRATED, last.left_counts - first.left_counts,
                                         last.right_counts - first.right_counts)  # fmt: skip
        # noise of sqrt(k·d) ~ 1 cm, plus the part of a physics step around each reading
        assert left_m == pytest.approx(moved_m, abs=0.05)
        assert right_m == pytest.approx(moved_m, abs=0.05)
        link.close()
    finally:
        w.close()
