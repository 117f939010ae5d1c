"""Outside audit, round 5: the shipped robot on ground and hardware nobody tuned.

One side's wheel encoder that fails mid-mission (stops counting, loses a quadrature channel
and counts half, counts backwards) was taken by the EKF for a turn: on the default mission
the robot either completed on the broken odometry without a word, or paused naming the
compass ("compass untrusted") or the GPS course ("a compass fault?"). The encoder watch
(x6wd.nav.encoder_watch) compares the sides' travel difference with the compass's turn on
straight drives and pauses the mission naming the encoders.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

import sim_backend.mission as mission
from sim_backend.odometry import EncoderSim
from sim_backend.world import load_world
from tests.test_controller import att
from tests.test_failsafe_controller import feed, started
from x6wd.core.records import Mode, NavState, WheelOdometry
from x6wd.nav.encoder_watch import EncoderWatch

ROOT = Path(__file__).resolve().parent.parent
DT = 0.05


def _drive(
    watch: EncoderWatch,
    *,
    seconds: float,
    speed_mps: float,
    turn_dps: float,
    track_eff_m: float,
    left_scale: float = 1.0,
    right_scale: float = 1.0,
    cmd: tuple[float, float] = (60.0, 60.0),
    compass: str = "true",
    rng: np.random.Generator | None = None,
) -> list[str]:
    """Wheel increments of a body moving at ``speed_mps`` and turning ``turn_dps`` (cw),
    its wheels on an effective track ``track_eff_m``, each side's count scaled."""
    out, heading = [], 10.0
    for i in range(1, int(seconds / DT) + 1):
        dpsi = math.radians(turn_dps) * DT
        common = speed_mps * DT
        left = (common + 0.5 * dpsi * track_eff_m) * left_scale
        right = (common - 0.5 * dpsi * track_eff_m) * right_scale
        heading = (heading + turn_dps * DT) % 360.0
        if compass == "true":
            bearing: float | None = heading
        elif compass == "frozen":
            bearing = 10.0
        else:
            assert rng is not None
            bearing = float(rng.uniform(0.0, 360.0))
        why = watch.on_increment(i * DT, left, right, cmd[0], cmd[1], bearing)
        if why:
            out.append(why)
    return out


@pytest.mark.parametrize(("left_scale", "name"), [(0.0, "dead"), (0.5, "half"), (-1.0, "reversed")])
def test_one_side_miscounting_on_a_straight_is_named(left_scale: float, name: str) -> None:
    watch = EncoderWatch(track_m=0.245)
    why = _drive(watch, seconds=6.0, speed_mps=2.3, turn_dps=0.0, track_eff_m=0.37,
                 left_scale=left_scale)  # fmt: skip
    assert why, name
    assert "encoder" in why[0]


@pytest.mark.parametrize(
    ("turn_dps", "track_eff_m", "left_scale", "right_scale"),
    [
        (0.0, 0.37, 1.05, 0.97),  # tyres 5 % and 3 % off the configured diameter
        (9.0, 0.37, 1.0, 1.0),  # a pure-pursuit arc, uncalibrated track (1.5x)
        (20.0, 0.6, 1.0, 1.0),  # a tight arc on grass (2.4x)
        (-15.0, 0.2, 1.0, 1.0),  # a track configured wider than it drives
    ],
)
def test_healthy_wheels_are_not_blamed(
    turn_dps: float, track_eff_m: float, left_scale: float, right_scale: float
) -> None:
    watch = EncoderWatch(track_m=0.245)
    assert not _drive(watch, seconds=60.0, speed_mps=2.3, turn_dps=turn_dps,
                      track_eff_m=track_eff_m, left_scale=left_scale,
                      right_scale=right_scale)  # fmt: skip


def test_pivots_and_a_random_compass_say_nothing() -> None:
    # a pivot (a slipping one too: the wheels turn, the body and compass do not) is no
    # straight drive; a compass reading random bearings is the compass watch's to judge
    watch = EncoderWatch(track_m=0.245)
    assert not _drive(watch, seconds=30.0, speed_mps=0.0, turn_dps=36.0, track_eff_m=0.37,
                      cmd=(40.0, -40.0), compass="frozen")  # fmt: skip
    assert not _drive(watch, seconds=30.0, speed_mps=2.3, turn_dps=0.0, track_eff_m=0.37,
                      compass="random", rng=np.random.default_rng(1))  # fmt: skip


class _LeftEncoderDies(EncoderSim):
    """The left encoder stops counting at 30 s (a cut wire, a dead sensor)."""

    def reading(self, t_s: float) -> WheelOdometry:
        r = super().reading(t_s)
        if t_s < 30.0:
            self._left_at_fault = r.left_counts
            return r
        return WheelOdometry(r.t_s, self._left_at_fault, r.right_counts, r.seq)


def test_left_encoder_dying_mid_mission_pauses_naming_the_encoders(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(mission, "EncoderSim", _LeftEncoderDies)
    world = load_world(ROOT / "config" / "scenarios" / "default.toml")
    summary = mission.run_mission(world, tmp_path, seed=1)
    # before the watch: 'mission COMPLETED' on seed 1, the fault never named
    assert not summary.completed
    assert summary.extra["final_mode"] == "PAUSED"
    (t_fs, why), *_ = summary.extra["failsafes"]
    assert why.startswith("encoders disagree with the compass"), why
    assert 30.0 < t_fs < 45.0
    records = [json.loads(line) for line in (tmp_path / "recording.jsonl").read_text().splitlines()]
    paused = next(
        i for i, r in enumerate(records)
        if r["type"] == "state" and "failsafe: encoders disagree" in r["data"]["reason"]
    )  # fmt: skip
    # the motors stop at once: the first command after the pause, and every one after it
    after = [r["data"] for r in records[paused:] if r["type"] == "motor"]
    assert after and all(m["left_pct"] == m["right_pct"] == 0.0 for m in after)
    assert after[0]["t_s"] == pytest.approx(records[paused]["t_mono"])
    tel = [r["data"] for r in records if r["type"] == "telemetry" and r["t_mono"] >= t_fs]
    assert tel and "encoders" in tel[-1]["extra"]["failsafe"]


# ------------------------------------------------------------------ review of the watch
# (a review of the watch above): on default.toml with the left encoder dead from 30 s, seed
# 2 paused as 'compass untrusted' and seed 3 named the encoders 13 s late (5 m of
# straight-commanded travel accrues slowly while the robot fights the phantom turn, pivoting
# and weaving); at a 1 Hz compass the turn was never counted (a bearing held between samples
# restarted it). The watch now takes the compass's turn between its own sample times and
# names a residual at any sample as soon as no healthy 5 m window could leave it.


@pytest.mark.parametrize("seed", [2, 3])
def test_a_dead_encoder_is_named_within_seconds_on_other_seeds(
    seed: int, monkeypatch: pytest.MonkeyPatch
) -> None:
    # before: seed 2 'compass untrusted' at 55 s; seed 3 named at 42.8 s. Not reached: at a
    # 5 Hz compass seed 1 still pauses as 'compass untrusted' (the robot pivots on the
    # phantom turn, which leaves no straight drive to judge), at 1 Hz it is named at 39 s
    monkeypatch.setattr(mission, "EncoderSim", _LeftEncoderDies)
    world = load_world(ROOT / "config" / "scenarios" / "default.toml")
    summary = mission.run_mission(world, None, seed=seed)
    assert summary.extra["final_mode"] == "PAUSED"
    (t_fs, why), *_ = summary.extra["failsafes"]
    assert why.startswith("encoders disagree with the compass"), why
    assert 30.0 <= t_fs < 38.5


def _feed(
    watch: EncoderWatch,
    *,
    seconds: float,
    speed_mps: float,
    turn_dps: float,
    track_eff_m: float,
    compass_hz: float,
    compass_gain: float = 1.0,
    left_scale: float = 1.0,
    cmd: tuple[float, float] = (60.0, 60.0),
) -> list[tuple[float, str]]:
    """Wheel increments at 20 Hz with a compass sampled at ``compass_hz``, fed the way the
    controller does: the latest sample's bearing and time, held between samples (a bearing
    reads the body's turn times ``compass_gain``: a distorted compass)."""
    out = []
    sample: tuple[float, float] | None = None
    for i in range(1, int(seconds / DT) + 1):
        t = i * DT
        dpsi = math.radians(turn_dps) * DT
        left = (speed_mps * DT + 0.5 * dpsi * track_eff_m) * left_scale
        right = speed_mps * DT - 0.5 * dpsi * track_eff_m
        tc = math.floor(t * compass_hz + 1e-9) / compass_hz
        if sample is None or tc > sample[0]:
            sample = (tc, (10.0 + compass_gain * turn_dps * tc) % 360.0)
        why = watch.on_increment(t, left, right, cmd[0], cmd[1], sample[1], sample[0])
        if why:
            out.append((t, why))
    return out


@pytest.mark.parametrize("compass_hz", [1.0, 5.0])
@pytest.mark.parametrize(("left_scale", "name"), [(0.0, "dead"), (0.5, "half"), (-1.0, "rev")])
def test_a_slow_compass_still_names_a_miscounting_side_within_seconds(
    compass_hz: float, left_scale: float, name: str
) -> None:
    watch = EncoderWatch(track_m=0.245)
    why = _feed(watch, seconds=10.0, speed_mps=1.0, turn_dps=0.0, track_eff_m=0.37,
                compass_hz=compass_hz, left_scale=left_scale)  # fmt: skip
    assert why and why[0][0] < 5.0, name


@pytest.mark.parametrize(
    ("turn_dps", "gain", "cmd"),
    [
        (90.0, 1.0, (60.0, 60.0)),  # a 90 deg/s circle (before: a false alarm at 1 Hz)
        (90.0, 2.0, (60.0, 60.0)),  # ... with a compass reading the turn at 2x
        (-60.0, 1.0, (-40.0, 40.0)),  # a pivot with forward travel
    ],
)
@pytest.mark.parametrize("compass_hz", [1.0, 20.0])
def test_a_healthy_tight_circle_is_not_blamed_at_any_compass_rate(
    compass_hz: float, turn_dps: float, gain: float, cmd: tuple[float, float]
) -> None:
    watch = EncoderWatch(track_m=0.245)
    assert not _feed(watch, seconds=30.0, speed_mps=1.0, turn_dps=turn_dps, track_eff_m=0.6,
                     compass_hz=compass_hz, compass_gain=gain, cmd=cmd)  # fmt: skip


@pytest.mark.parametrize("then", ["stop, return_home", "stop, start", "pause, resume"])
def test_an_encoder_verdict_a_hold_beat_does_not_pause_what_comes_after(
    then: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    # the verdict was kept until read: a hold won the step it came in, and after an operator
    # stop and return_home (or start, or a pause and resume) the robot paused at once on it
    c = started()
    feed(c, 0.5, 0.5, counts=0)
    c.sensor_health("gps", False, 0.6, "stale")
    verdict = "encoders disagree with the compass: a verdict the hold beat"
    monkeypatch.setattr(c._enc_watch, "on_increment", lambda *a, **k: verdict)
    c.on_odometry(WheelOdometry(0.7, 100, 100, 1))
    monkeypatch.undo()
    assert c.mode == Mode.RUNNING and c.state == NavState.HOLD
    first, second = then.split(", ")
    getattr(c, first)(1.0)
    c.sensor_health("gps", True, 1.1)
    feed(c, 1.2, 0.5)
    getattr(c, second)(1.3)
    feed(c, 1.4, 0.5)
    # (the return ends at once: the robot is 0.5 m from its launch point)
    assert c.mode in (Mode.RUNNING, Mode.DONE), c.telemetry.extra.get("failsafe")
    assert "encoders" not in str(c.telemetry.extra.get("failsafe", ""))


def test_a_lost_sample_drops_the_wheels_whose_turn_it_held() -> None:
    # a healthy 90 deg/s circle, 1 Hz compass, 20 Hz wheels; every other new sample comes
    # in unusable (None at the tick it arrives): the wheels since the last counted sample
    # stayed in the window while their turn was lost, a false verdict (review of 3b0a0a9)
    watch = EncoderWatch(track_m=0.245)
    out, sample, counted = [], None, 0
    for i in range(1, int(30.0 / DT) + 1):
        t = i * DT
        dpsi = math.radians(90.0) * DT
        left, right = 1.0 * DT + 0.5 * dpsi * 0.6, 1.0 * DT - 0.5 * dpsi * 0.6
        tc = math.floor(t + 1e-9)
        bearing: float | None
        if sample is None or tc > sample[0]:
            sample = (tc, (10.0 + 90.0 * tc) % 360.0)
            counted += 1
            bearing = None if counted % 2 == 0 else sample[1]
        else:
            bearing = sample[1]
        why = watch.on_increment(t, left, right, 60.0, 60.0, bearing, sample[0])
        if why:
            out.append((t, why))
    assert not out, out[:1]


def test_a_compass_stamped_just_after_the_wheels_still_feeds_the_watch(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # the compass read a millisecond after the wheels' reply: the sample was taken for
    # none, and the watch never saw a bearing (review of 3b0a0a9)
    c = started()
    seen: list[float | None] = []

    def spy(*args: object) -> str:
        seen.append(args[5])  # type: ignore[arg-type]
        return ""

    monkeypatch.setattr(c._enc_watch, "on_increment", spy)
    for k in range(1, 6):
        t = 0.1 * k
        c.on_attitude(att(t + 0.001))
        c.on_odometry(WheelOdometry(t, 10 * k, 10 * k, k))
    assert seen and all(b is not None for b in seen[1:]), seen


def test_an_encoder_verdict_pauses_even_where_stuck_action_says_return(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # a return would dead-reckon home on the counts the watch has just found wrong
    from dataclasses import replace

    from tests.test_failsafe_controller import FS

    c = started(replace(FS, stuck_action="return"))
    feed(c, 0.5, 0.5, counts=0)
    verdict = "encoders disagree with the compass: a verdict"
    monkeypatch.setattr(c._enc_watch, "on_increment", lambda *a, **k: verdict)
    feed(c, 0.7, 1.0, counts=100)
    assert c.mode == Mode.PAUSED, c.mode
    assert c.telemetry.extra.get("failsafe") == verdict
    assert c.command.is_stop


class _BothEncodersDie(EncoderSim):
    """Both encoders stop counting at 30 s (a shared connector, the encoder supply)."""

    def reading(self, t_s: float) -> WheelOdometry:
        r = super().reading(t_s)
        if t_s < 30.0:
            self._at_fault = (r.left_counts, r.right_counts)
            return r
        return WheelOdometry(r.t_s, *self._at_fault, r.seq)


@pytest.mark.parametrize(("scenario", "seed"), [("default", 1), ("zigzag", 3)])
def test_both_encoders_dead_are_named_not_the_compass(
    scenario: str, seed: int, monkeypatch: pytest.MonkeyPatch
) -> None:
    # Both sides dead predict no turn while the robot pivots, so the EKF refuses the
    # compass that turns; before, these runs paused as 'compass untrusted (the EKF refused
    # 50 % of 200 readings in 10 s)' at 38.55 s and 42.55 s (the other seeds named the
    # encoders, or a block, through the stuck test)
    monkeypatch.setattr(mission, "EncoderSim", _BothEncodersDie)
    world = load_world(ROOT / "config" / "scenarios" / f"{scenario}.toml")
    summary = mission.run_mission(world, None, seed=seed)
    assert summary.extra["final_mode"] == "PAUSED"
    (t_fs, why), *_ = summary.extra["failsafes"]
    assert why.startswith("encoders: under 0.2 m counted"), why
    assert "the compass shows motion" in why and "refused the compass" in why
    assert 30.0 < t_fs < 45.0
