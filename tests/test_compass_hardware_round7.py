"""Compass faults a real CMPS10 on a Raspberry Pi shows (code review, round 7).

1. The BCM2835's I2C master mishandles clock stretching: a transaction can return a
   corrupted byte without any errno. One bit flipped in the bearing's high byte turned
   123.4 deg into 174.6 deg, in range, and the driver returned it as a valid sample. The
   driver now reads register 1 (the bearing as 0-255 for a full circle) in the same block
   read as registers 2-5 and refuses a sample whose two bearings disagree. A real bus cannot
   be made to do this on demand: a fake smbus object flips the bit.
2. A failed sample returns the driver's last good attitude (its old ``t_s``), and the daemon
   posts it every compass period: the runner fed it to the controller again, and the EKF,
   which takes inputs up to 0.3 s late and moves them to now, fused the same stale bearing
   several times while the robot turned. The runner now hands a compass sample that is not
   newer than the last one on to nobody (counted), and a compass that keeps failing still
   ends in the documented hold and the sensor-timeout pause.
"""

from __future__ import annotations

import errno
import logging

import pytest

from drivers.cmps10 import REG_BEARING_BYTE, Cmps10
from x6wd.core.config import FailsafeConfig, NavigationConfig, SafetyConfig
from x6wd.core.health import HealthLog
from x6wd.core.mission_files import Waypoint
from x6wd.core.records import GpsFix, Mode
from x6wd.loop.runner import Runner
from x6wd.nav.controller import Controller


class FlakyBus:
    """A CMPS10's registers behind the smbus2 method set. ``flip`` (register -> mask) XORs
    those registers' bytes in the next block read that covers them, as the clock-stretching
    bug does (``flip_reads`` block reads in a row); ``fail`` makes the next block reads
    raise EREMOTEIO."""

    def __init__(
        self, bearing_deg: float = 123.4, *, truncate: bool = False, steps: int = 256
    ) -> None:
        self.regs = [0] * 23
        self.regs[0] = 15
        self.truncate, self.steps = truncate, steps
        self.set(bearing_deg, 2, -1)
        self.flip: dict[int, int] = {}
        self.flip_reads = 1
        self.fail = 0
        self.block_reads: list[tuple[int, int]] = []

    def set(self, bearing_deg: float, pitch: int, roll: int) -> None:
        tenths = round(bearing_deg * 10) % 3600
        n = self.steps  # a turn is 256 steps, or 255 ("0-255" may mean 255 is 360 deg)
        coarse = tenths * n // 3600 if self.truncate else round(tenths * n / 3600)
        self.regs[1] = coarse % 256
        self.regs[2], self.regs[3] = tenths >> 8, tenths & 0xFF
        self.regs[4], self.regs[5] = pitch & 0xFF, roll & 0xFF

    def read_byte_data(self, i2c_addr: int, register: int) -> int:
        return self.regs[register]

    def write_byte_data(self, i2c_addr: int, register: int, value: int) -> None:
        pass

    def read_i2c_block_data(self, i2c_addr: int, register: int, length: int) -> list[int]:
        self.block_reads.append((register, length))
        if self.fail:
            self.fail -= 1
            raise OSError(errno.EREMOTEIO, "Remote I/O error")
        data = list(self.regs[register : register + length])
        hit = False
        for reg, mask in self.flip.items():
            if register <= reg < register + length:
                data[reg - register] ^= mask
                hit = True
        if hit:
            self.flip_reads -= 1
            if self.flip_reads <= 0:
                self.flip, self.flip_reads = {}, 1
        return data


def driver(bus: FlakyBus, **kw: object) -> Cmps10:
    return Cmps10(bus, sleep=lambda _s: None, retry_delay_s=0.0, **kw)  # type: ignore[arg-type]


# -- 1. corrupted, in-range bytes --------------------------------------------------------------


def test_a_flipped_bit_in_the_bearing_is_not_a_valid_sample() -> None:
    """The review's case: 0x02 in the high byte, 123.4 -> 174.6 deg. The retry's clean read
    is the sample; the corrupt one is counted, in the counters and in the health status
    shows."""
    bus = FlakyBus(123.4)
    c = driver(bus)
    assert c.read(1.0).bearing_deg == pytest.approx(123.4)
    bus.flip = {2: 0x02}
    att = c.read(1.05)
    assert att.valid and att.t_s == 1.05
    assert att.bearing_deg == pytest.approx(123.4)  # not 174.6
    assert c.counters.bearing_mismatches == 1
    assert c.counters.good_samples == 2 and c.counters.failed_samples == 0
    h = c.health
    assert h.errors == 1 and "disagree" in h.last_error
    assert h.corrupt["bearing_mismatches"] == 1
    assert h.to_dict()["corrupt"]["bearing_mismatches"] == 1  # what status shows


def test_a_bearing_corrupt_on_every_attempt_is_a_failed_sample() -> None:
    bus = FlakyBus(123.4)
    c = driver(bus, retries=2, stale_after=1)
    bus.flip, bus.flip_reads = {2: 0x02}, 10
    att = c.read(2.0)
    assert not att.valid  # stale_after=1: no last good one to hold, and not 174.6 anyway
    assert att.bearing_deg != pytest.approx(174.6)
    assert c.counters.bearing_mismatches == 3  # the first attempt and 2 retries
    assert c.counters.failed_samples == 1 and c.counters.good_samples == 0
    assert c.last_good is None


def test_one_block_read_from_register_1_per_sample() -> None:
    """Both bearings come from the same transaction (two reads could tear across an update)."""
    bus = FlakyBus(10.0)
    c = driver(bus)
    for i in range(3):
        assert c.read(float(i)).valid
    assert bus.block_reads == [(REG_BEARING_BYTE, 5)] * 3


@pytest.mark.parametrize("steps", [256, 255], ids=["256-scale", "255-scale"])
@pytest.mark.parametrize("truncate", [False, True], ids=["rounded", "truncated"])
def test_every_honest_bearing_passes(truncate: bool, steps: int) -> None:
    """Register 1 is 1.41 deg coarse (rounded or truncated by the device, a turn 256 or 255
    steps: the datasheet says only "0-255"): every tenth of a degree round the circle, 359.9
    next to 0.0 included, agrees with it. A truncating 255 scale read as 256 steps refused
    494 of the 3600 bearings (175-360 deg) on every try: the compass stale there."""
    bus = FlakyBus(0.0, truncate=truncate, steps=steps)
    c = driver(bus, retries=0, stale_after=1)
    for tenths in range(3600):
        bus.set(tenths / 10, 0, 0)
        att = c.read(float(tenths))
        assert att.valid and att.bearing_deg == pytest.approx(tenths / 10), tenths
    assert c.counters.bearing_mismatches == 0


@pytest.mark.parametrize(
    ("reg", "mask", "deg"),
    [(2, 0x01, 25.6), (2, 0x02, 51.2), (2, 0x04, 102.4), (3, 0x80, 12.8), (3, 0x40, 6.4),
     (3, 0x20, 3.2)],
)  # fmt: skip
def test_flips_of_a_few_degrees_or_more_are_caught(reg: int, mask: int, deg: float) -> None:
    """Bits of the high byte are 25.6 deg and up; bits 7-5 of the low byte 12.8, 6.4 and
    3.2 deg (smaller flips are within the coarse register's resolution: harmless)."""
    bus = FlakyBus(200.0)
    c = driver(bus, retries=0, stale_after=10)
    assert c.read(0.0).valid
    bus.flip = {reg: mask}
    att = c.read(0.05)
    assert c.counters.bearing_mismatches == 1, deg
    assert att.t_s == 0.0 and att.bearing_deg == pytest.approx(200.0)  # the last good one


# -- 2. a failed sample's last good attitude, re-sent ------------------------------------------

HOME = (51.7520, -1.2577)
M_PER_DEG_LAT = 111_200.0
PERIOD_S = 0.05  # the compass thread's period at the default 20 Hz


class Robot:
    """The daemon's compass path, in fast time: the real driver over ``FlakyBus``, its
    samples and health events posted to the real runner and controller (EKF) every period
    as the daemon's compass thread does, fixes at 1 Hz, a tick each period."""

    def __init__(self, **driver_kw: object) -> None:
        self.now = 0.0
        self.safety = SafetyConfig()
        self.ctrl = Controller(NavigationConfig(), self.safety, failsafe=FailsafeConfig(stuck_s=0))
        self.runner = Runner(
            self.ctrl,
            self.safety,
            lambda: self.now,
            motors=lambda _cmd: None,
            health_log=HealthLog(logging.getLogger("test.round7.quiet"), clock=lambda: self.now),
        )
        self.bus = FlakyBus(0.0)
        self.compass = driver(self.bus, **driver_kw)
        self.fused: list[float] = []  # t_s of every bearing the EKF was handed
        src = self.ctrl._source
        on_compass = src.on_compass

        def spy(t_s: float, bearing_mag_deg: float) -> bool | None:
            self.fused.append(t_s)
            return on_compass(t_s, bearing_mag_deg)

        src.on_compass = spy  # type: ignore[method-assign]
        self.sample()
        self.fix()
        self.runner.load_mission([Waypoint(HOME[0] + 200 / M_PER_DEG_LAT, HOME[1])])
        self.runner.command("start")

    def fix(self) -> None:
        fix = GpsFix(self.now, lat_deg=HOME[0], lon_deg=HOME[1], quality=1, valid=True)
        self.runner.gps_record(fix)

    def sample(self) -> None:
        """One period of the daemon's compass thread: read, post the events, post the
        attitude (daemon._compass_thread)."""
        att = self.compass.read(self.now)
        events = self.compass.take_health_events()
        if events:
            self.runner.device_events(events)
        self.runner.attitude(att)

    def run(self, duration_s: float) -> None:
        for _ in range(round(duration_s / PERIOD_S)):
            self.now = round(self.now + PERIOD_S, 6)
            if self.now % 1.0 < 1e-6:
                self.fix()
            self.sample()
            self.runner.tick(self.now)

    def fail_samples(self, n: int) -> None:
        """The next ``n`` samples fail on every attempt (bus errors)."""
        self.bus.fail = n * (self.compass.retries + 1)


def test_a_failed_samples_last_good_attitude_is_not_fused_again() -> None:
    """Four failed samples (0.2 s, under the driver's stale_after=5): the driver hands back
    its last good attitude four times, the daemon posts it each time; the EKF took it each
    time (up to 0.3 s late is moved to now: a stale bearing fused 5 times while turning)."""
    robot = Robot(stale_s=0.5)
    robot.run(2.0)
    assert robot.ctrl.mode == Mode.RUNNING
    assert robot.fused and len(set(robot.fused)) == len(robot.fused)
    before = len(robot.fused)
    robot.fail_samples(4)
    robot.run(0.2)
    assert robot.compass.counters.failed_samples == 4 and not robot.compass.stale
    assert len(robot.fused) == before, "the last good bearing was fused again"
    robot.run(1.0)
    assert len(set(robot.fused)) == len(robot.fused)
    assert robot.runner.compass_repeats == 4
    assert robot.runner.stats["attitudes"] == 1 + 64  # every sample seen is counted
    assert robot.ctrl.mode == Mode.RUNNING and robot.ctrl.telemetry.hold_reason in ("", None)


def test_a_failing_compass_still_holds_and_then_pauses() -> None:
    """The driver turns stale after 5 failed samples: the hold is at once ("compass stale",
    its health), and after safety's sensor_timeout_s the failsafe pauses the mission."""
    robot = Robot(stale_s=0.5)
    robot.run(2.0)
    robot.fail_samples(10_000)
    robot.run(0.3)
    tel = robot.ctrl.telemetry
    assert tel.state == "HOLD" and "compass" in str(tel.hold_reason), tel.hold_reason
    timeout_s = robot.ctrl.failsafe_config.sensor_timeout_s
    robot.run(timeout_s + 1.0)
    assert robot.ctrl.mode == Mode.PAUSED
    assert "compass" in robot.ctrl.telemetry.extra["failsafe"]


def test_only_repeats_still_read_as_a_stale_attitude() -> None:
    """A driver that never says stale (no stale_s, a huge stale_after): only repeats of the
    last good sample come. The controller's own staleness (safety.attitude_stale_s, from the
    last sample it took) still holds the robot, and the sensor timeout still pauses it."""
    robot = Robot(stale_after=1_000_000)
    robot.run(2.0)
    robot.fail_samples(10_000)
    robot.run(robot.safety.attitude_stale_s + 0.1)
    assert not robot.compass.stale and robot.runner.compass_repeats > 5
    tel = robot.ctrl.telemetry
    assert tel.state == "HOLD" and tel.hold_reason == "attitude stale"
    robot.run(robot.ctrl.failsafe_config.sensor_timeout_s + 1.0)
    assert robot.ctrl.mode == Mode.PAUSED
    assert robot.ctrl.telemetry.extra["failsafe"].startswith("attitude stale")
