"""CMPS10 driver against a register-map test double that follows the datasheet.

The double (``Cmps10Double``) holds the 23 registers, answers block reads from consecutive
registers, executes the command sequences written to register 22 only when their bytes come
far enough apart in (virtual) time, and can be told to fail transactions with Linux errnos.
"""

from __future__ import annotations

import errno
import itertools
from collections.abc import Callable

import numpy as np
import pytest

from drivers.cmps10 import Cmps10
from x6wd.errors import DeviceIOError, DeviceUnavailable

MIN_COMMAND_GAP_S = 0.09  # the double ignores a sequence whose bytes come faster than this


class VirtualClock:
    """Time that only moves when the driver sleeps: tests run instantly and see the spacing."""

    def __init__(self) -> None:
        self.now_s = 0.0
        self.sleeps: list[float] = []

    def sleep(self, dt_s: float) -> None:
        self.sleeps.append(dt_s)
        self.now_s += dt_s


class Cmps10Double:
    """A CMPS10 on an I2C bus, with the smbus2 method set."""

    VERSION = 15

    def __init__(self, clock: VirtualClock, address: int = 0x60) -> None:
        self.clock = clock
        self.address = address
        self.regs = [0] * 23
        self.regs[0] = self.VERSION
        self.transactions: list[tuple[str, int, int]] = []  # (method, register, length)
        self.fail: Callable[[], int | None] = lambda: None  # errno to raise, or None
        self.injected = 0
        self.commands: list[tuple[float, int]] = []
        self.factory_restored = 0
        self.calibration_mode = False
        self.calibration_points: list[float] = []  # bearing (deg) at each 0xF5
        self.calibrated = False
        self.set_attitude(0.0, 0, 0)

    # physical state -> registers
    def set_attitude(self, bearing_deg: float, pitch_deg: int, roll_deg: int) -> None:
        tenths = round(bearing_deg * 10)
        self.set_raw_attitude(tenths, pitch_deg, roll_deg)

    def set_raw_attitude(self, tenths: int, pitch: int, roll: int) -> None:
        self.regs[1] = (tenths * 256 // 3600) & 0xFF
        self.regs[2], self.regs[3] = (tenths >> 8) & 0xFF, tenths & 0xFF
        self.regs[4], self.regs[5] = pitch & 0xFF, roll & 0xFF

    def set_raw_sensors(self, mag: tuple[int, ...], acc: tuple[int, ...]) -> None:
        for i, v in enumerate((*mag, *acc)):
            self.regs[10 + 2 * i] = (v >> 8) & 0xFF
            self.regs[11 + 2 * i] = v & 0xFF

    def _bearing_deg(self) -> float:
        return ((self.regs[2] << 8) | self.regs[3]) / 10

    # bus side
    def _enter(self, method: str, addr: int, register: int, length: int) -> None:
        code = self.fail()
        if code is not None:
            self.injected += 1
            raise OSError(code, f"injected {errno.errorcode.get(code, code)}")
        if addr != self.address:
            raise OSError(errno.EREMOTEIO, "Remote I/O error")  # nobody ACKs
        self.transactions.append((method, register, length))

    def read_byte_data(self, i2c_addr: int, register: int) -> int:
        self._enter("read_byte_data", i2c_addr, register, 1)
        return self.regs[register] if register < len(self.regs) else 0

    def read_i2c_block_data(self, i2c_addr: int, register: int, length: int) -> list[int]:
        self._enter("read_i2c_block_data", i2c_addr, register, length)
        return [
            self.regs[r] if r < len(self.regs) else 0 for r in range(register, register + length)
        ]

    def write_byte_data(self, i2c_addr: int, register: int, value: int) -> None:
        self._enter("write_byte_data", i2c_addr, register, 1)
        if register == 22:
            self._command(value)

    def _command(self, value: int) -> None:
        now = self.clock.now_s
        too_fast = bool(self.commands) and now - self.commands[-1][0] < MIN_COMMAND_GAP_S
        self.commands.append((now, value))
        if too_fast:
            self.commands = [(now, value)]  # the device drops the half-received sequence
        tail = [v for _, v in self.commands]
        if value == 0xF0:
            self.calibration_mode = True
            self.calibration_points = []
        elif value == 0xF5 and self.calibration_mode and not too_fast:
            self.calibration_points.append(self._bearing_deg())
            if len(self.calibration_points) == 4:
                self.calibration_mode = False
                self.calibrated = True
        elif tail[-3:] == [0x20, 0x2A, 0x60]:
            self.factory_restored += 1
        elif tail[-4:-1] == [0xA0, 0xAA, 0xA5] and value in range(0xC0, 0xD0, 2):
            self.address = value >> 1


@pytest.fixture
def clock() -> VirtualClock:
    return VirtualClock()


@pytest.fixture
def dev(clock: VirtualClock) -> Cmps10Double:
    return Cmps10Double(clock)


def make(dev: Cmps10Double, clock: VirtualClock, **kw: object) -> Cmps10:
    return Cmps10(dev, dev.address, sleep=clock.sleep, **kw)  # type: ignore[arg-type]


@pytest.mark.parametrize(
    ("bearing", "pitch", "roll"),
    [(0.0, 0, 0), (359.9, 85, -85), (25.6, -1, 1), (180.5, -60, 60), (0.1, 12, -128 + 43)],
)
def test_read_decodes_high_byte_first_and_signed_tilt(
    dev: Cmps10Double, clock: VirtualClock, bearing: float, pitch: int, roll: int
) -> None:
    dev.set_attitude(bearing, pitch, roll)
    att = make(dev, clock).read(12.5)
    assert att.valid
    assert att.t_s == 12.5
    assert att.bearing_deg == pytest.approx(bearing, abs=1e-9)
    assert (att.pitch_deg, att.roll_deg) == (pitch, roll)


def test_one_block_read_of_registers_2_to_5_per_sample(
    dev: Cmps10Double, clock: VirtualClock
) -> None:
    c = make(dev, clock)
    for i in range(5):
        c.read(float(i))
    assert dev.transactions == [("read_i2c_block_data", 2, 4)] * 5


@pytest.mark.parametrize(
    ("tenths", "pitch", "roll"), [(3600, 0, 0), (0xFFFF, 0, 0), (10, 86, 0), (10, 0, -86)]
)
def test_out_of_range_values_are_failed_reads(
    dev: Cmps10Double, clock: VirtualClock, tenths: int, pitch: int, roll: int
) -> None:
    dev.set_raw_attitude(tenths, pitch, roll)
    c = make(dev, clock, retries=2, stale_after=1)
    att = c.read(1.0)
    assert not att.valid
    assert c.stale
    assert c.counters.range_errors == 3  # first attempt + 2 retries
    assert c.counters.good_samples == 0


@pytest.mark.parametrize("code", [errno.EIO, errno.ENXIO, errno.ETIMEDOUT, errno.EREMOTEIO])
def test_transient_errnos_are_retried(dev: Cmps10Double, clock: VirtualClock, code: int) -> None:
    plan = [code, code]
    dev.fail = lambda: plan.pop() if plan else None
    dev.set_attitude(90.0, 3, -4)
    c = make(dev, clock, retries=3)
    att = c.read(2.0)
    assert att.valid and att.bearing_deg == 90.0
    assert c.counters.io_errors == 2
    assert c.counters.retries == 2
    assert c.counters.failed_samples == 0


def test_other_errnos_raise_device_io_error(dev: Cmps10Double, clock: VirtualClock) -> None:
    dev.fail = lambda: errno.EACCES
    with pytest.raises(DeviceIOError, match="0x60"):
        make(dev, clock).read(0.0)


def test_stale_after_consecutive_failures_then_recovery(
    dev: Cmps10Double, clock: VirtualClock
) -> None:
    dev.set_attitude(45.0, 1, 2)
    c = make(dev, clock, retries=1, stale_after=3)
    good = c.read(1.0)
    assert good.valid
    dev.fail = lambda: errno.EREMOTEIO
    held = [c.read(2.0), c.read(3.0)]
    # before the limit: the last good sample, with its own (ageing) time
    assert held == [good, good]
    assert not c.stale
    stale = c.read(4.0)
    assert not stale.valid and stale.t_s == 4.0 and c.stale
    assert not c.read(5.0).valid
    assert c.counters.stale_events == 1
    dev.fail = lambda: None
    dev.set_attitude(50.0, 0, 0)
    back = c.read(6.0)
    assert back.valid and back.bearing_deg == 50.0 and not c.stale
    assert c.counters.failed_samples == 4


def test_no_good_sample_yet_is_invalid(dev: Cmps10Double, clock: VirtualClock) -> None:
    dev.fail = lambda: errno.ETIMEDOUT
    att = make(dev, clock, stale_after=10).read(7.0)
    assert not att.valid and att.t_s == 7.0


def test_errno_storm_never_raises_and_never_lies(dev: Cmps10Double, clock: VirtualClock) -> None:
    rng = np.random.default_rng(20261122)
    codes = [errno.EIO, errno.ENXIO, errno.ETIMEDOUT, errno.EREMOTEIO]
    dev.fail = lambda: int(rng.choice(codes)) if rng.random() < 0.6 else None
    c = make(dev, clock, retries=2, stale_after=4)
    consecutive_failed = 0
    for k in range(2000):
        truth = (float(rng.integers(0, 3600)) / 10, int(rng.integers(-85, 86)), 0)
        dev.set_attitude(*truth)
        before = c.counters.good_samples
        att = c.read(float(k))
        if c.counters.good_samples > before:
            consecutive_failed = 0
            assert (att.t_s, att.bearing_deg, att.pitch_deg) == (float(k), truth[0], truth[1])
        else:
            consecutive_failed += 1
            assert att.valid == (consecutive_failed < 4 and c.last_good is not None)
            assert att.t_s != float(k) or not att.valid  # a held sample keeps its old time
    assert c.counters.io_errors == dev.injected
    assert c.counters.good_samples + c.counters.failed_samples == 2000
    assert c.counters.stale_events > 0 and c.counters.good_samples > 1000


def test_check_version(dev: Cmps10Double, clock: VirtualClock) -> None:
    assert make(dev, clock).check_version() == Cmps10Double.VERSION
    assert dev.transactions == [("read_byte_data", 0, 1)]


def test_check_version_without_device(dev: Cmps10Double, clock: VirtualClock) -> None:
    c = Cmps10(dev, 0x61, sleep=clock.sleep)
    with pytest.raises(DeviceUnavailable, match="0x61"):
        c.check_version()


@pytest.mark.parametrize("version", [0x00, 0xFF])
def test_check_version_absurd(dev: Cmps10Double, clock: VirtualClock, version: int) -> None:
    dev.regs[0] = version
    with pytest.raises(DeviceUnavailable, match="not a CMPS10"):
        make(dev, clock).check_version()


def test_raw_sensors_signed_big_endian(dev: Cmps10Double, clock: VirtualClock) -> None:
    mag, acc = (-1, 32767, -32768), (256, -300, 1)
    dev.set_raw_sensors(mag, acc)
    assert make(dev, clock).raw() == (mag, acc)
    assert dev.transactions == [("read_i2c_block_data", 10, 12)]


def test_bearing_byte(dev: Cmps10Double, clock: VirtualClock) -> None:
    dev.set_attitude(180.0, 0, 0)
    assert make(dev, clock).bearing_byte() == 128


def test_calibration_sequence_and_timing(dev: Cmps10Double, clock: VirtualClock) -> None:
    headings = {"N": 0.0, "E": 90.0, "S": 180.0, "W": 270.0}
    visited: list[tuple[int, str]] = []

    def rotate(i: int, name: str) -> None:
        visited.append((i, name))
        dev.set_attitude(headings[name], 0, 0)
        clock.sleep(3.0)  # the operator takes a while

    make(dev, clock).calibrate(rotate)
    assert visited == [(0, "N"), (1, "E"), (2, "S"), (3, "W")]
    assert [v for _, v in dev.commands] == [0xF0, 0xF5, 0xF5, 0xF5, 0xF5]
    assert dev.calibrated and dev.calibration_points == [0.0, 90.0, 180.0, 270.0]


def test_calibration_aborted_by_callback(dev: Cmps10Double, clock: VirtualClock) -> None:
    def give_up(i: int, name: str) -> None:
        if i == 2:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        make(dev, clock).calibrate(give_up)
    assert [v for _, v in dev.commands] == [0xF0, 0xF5, 0xF5]
    assert not dev.calibrated


def test_restore_factory_spaced_commands(dev: Cmps10Double, clock: VirtualClock) -> None:
    make(dev, clock).restore_factory()
    assert [v for _, v in dev.commands] == [0x20, 0x2A, 0x60]
    times = [t for t, _ in dev.commands]
    assert all(b - a >= MIN_COMMAND_GAP_S for a, b in itertools.pairwise(times))
    assert dev.factory_restored == 1


def test_restore_factory_without_spacing_is_ignored_by_device(dev: Cmps10Double) -> None:
    # the double really enforces the gap: a driver that did not sleep would not restore
    Cmps10(dev, sleep=lambda _dt: None).restore_factory()
    assert dev.factory_restored == 0


def test_change_address_moves_device_and_driver(dev: Cmps10Double, clock: VirtualClock) -> None:
    dev.set_attitude(123.4, 5, 6)
    c = make(dev, clock)
    c.change_address(0x63)
    assert [v for _, v in dev.commands] == [0xA0, 0xAA, 0xA5, 0xC6]
    assert dev.address == 0x63 and c.address == 0x63
    assert c.read(1.0).bearing_deg == 123.4


@pytest.mark.parametrize("bad", [0x5F, 0x68, 0xC0])
def test_change_address_rejects_bad_addresses(
    dev: Cmps10Double, clock: VirtualClock, bad: int
) -> None:
    with pytest.raises(ValueError, match=r"0x60\.\.0x67"):
        make(dev, clock).change_address(bad)
    assert dev.commands == []


def test_command_failure_raises_after_retries(dev: Cmps10Double, clock: VirtualClock) -> None:
    dev.fail = lambda: errno.EREMOTEIO
    with pytest.raises(DeviceIOError, match="not accepted after 3 attempts"):
        make(dev, clock, retries=2).restore_factory()


def test_constructor_validates(dev: Cmps10Double) -> None:
    with pytest.raises(ValueError, match="address"):
        Cmps10(dev, 0x20)
    with pytest.raises(ValueError, match="stale_after"):
        Cmps10(dev, stale_after=0)
