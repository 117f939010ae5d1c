"""CMPS10 driver against a register-map test double that follows the datasheet.

The double (``Cmps10Double``) holds the 23 registers, answers block reads from consecutive
registers, executes the command sequences written to register 22 only when their bytes come
far enough apart in (virtual) time, and can be told to fail transactions with Linux errnos.
"""

from __future__ import annotations

import errno
import itertools
import os
from collections.abc import Callable

import numpy as np
import pytest

from drivers.cmps10 import Cmps10
from sim_backend.compass import ErrorInjector, SimCmps10
from x6wd.core.errors import TRANSIENT_ERRNOS, DeviceIOError, DeviceUnavailable

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


def test_one_block_read_of_registers_1_to_5_per_sample(
    dev: Cmps10Double, clock: VirtualClock
) -> None:
    c = make(dev, clock)
    for i in range(5):
        c.read(float(i))
    # register 1 (the coarse bearing) too: the driver checks the two bearings agree
    assert dev.transactions == [("read_i2c_block_data", 1, 5)] * 5


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


TRANSIENT = [errno.EIO, errno.ENXIO, errno.EAGAIN, errno.EBUSY, errno.EINTR, errno.EPROTO,
             errno.ETIMEDOUT, errno.EREMOTEIO]  # fmt: skip
NOT_TRANSIENT = [errno.ENOENT, errno.EACCES, errno.EBADF, errno.ENODEV]


def test_the_transient_class_is_the_projects_one() -> None:
    assert set(TRANSIENT) == TRANSIENT_ERRNOS
    assert not set(NOT_TRANSIENT) & TRANSIENT_ERRNOS


@pytest.mark.parametrize("code", TRANSIENT, ids=lambda c: errno.errorcode[c])
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
    # counted in the health, but a retry saved the sample: still connected
    h = c.health
    assert (h.state, h.errors, h.consecutive_errors) == ("connected", 2, 0)
    assert errno.errorcode[code] in h.last_error and h.last_error_t_s == 2.0


@pytest.mark.parametrize("code", NOT_TRANSIENT, ids=lambda c: errno.errorcode[c])
def test_other_errnos_raise_device_io_error(
    dev: Cmps10Double, clock: VirtualClock, code: int
) -> None:
    dev.fail = lambda: code
    c = make(dev, clock)
    with pytest.raises(DeviceIOError, match="0x60"):
        c.read(3.0)
    assert dev.injected == 1  # not retried
    h = c.health
    assert h.state == "disconnected" and h.errors == 1
    assert errno.errorcode[code] in h.last_error
    events = c.take_health_events()
    assert [(e.old, e.new) for e in events] == [
        ("disconnected", "connected"),  # the first read opens it
        ("connected", "disconnected"),
    ]
    assert events[-1].t_s == 3.0 and events[-1].message.startswith("compass disconnected: ")


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


# --- health over the simulator's register map (sim_backend.compass) ---------------------------


class StormBus:
    """The simulated CMPS10's smbus2 methods, failing every transaction with ``code`` while a
    storm is on (the register map itself stays untouched)."""

    def __init__(self, dev: SimCmps10) -> None:
        self.dev = dev
        self.code: int | None = None
        self.failed = 0

    def _check(self) -> None:
        if self.code is not None:
            self.failed += 1
            raise OSError(self.code, f"{os.strerror(self.code)} (storm)")

    def read_byte_data(self, i2c_addr: int, register: int) -> int:
        self._check()
        return self.dev.read_byte_data(i2c_addr, register)

    def write_byte_data(self, i2c_addr: int, register: int, value: int) -> None:
        self._check()
        self.dev.write_byte_data(i2c_addr, register, value)

    def read_i2c_block_data(self, i2c_addr: int, register: int, length: int) -> list[int]:
        self._check()
        return self.dev.read_i2c_block_data(i2c_addr, register, length)


def sim_compass(**kw: object) -> tuple[SimCmps10, StormBus, Cmps10]:
    dev = SimCmps10(errors=None, injector=ErrorInjector())
    dev.set_state(0.0, 123.0, 0.0, 0.0)
    dev.set_state(5.0, 123.0, 0.0, 0.0)  # the heading filter has settled
    bus = StormBus(dev)
    return dev, bus, Cmps10(bus, sleep=lambda _s: None, **kw)  # type: ignore[arg-type]


def test_errno_storm_is_counted_degrades_and_recovers() -> None:
    _, bus, c = sim_compass(retries=2, stale_after=100, stale_s=0.5)
    t = 0.0
    for _ in range(5):  # 20 Hz, all good
        t += 0.05
        assert c.read(t).valid
    assert c.health.state == "connected" and c.health.errors == 0
    bus.code = errno.EREMOTEIO
    for _ in range(4):  # 0.2 s storm: every attempt of 4 samples fails
        t += 0.05
        att = c.read(t)
        assert att.valid and att.t_s == 0.25  # the last good sample, ageing honestly
    h = c.health
    assert h.state == "degraded"
    assert h.errors == bus.failed == 12 and h.consecutive_errors == 12
    assert "Remote I/O error" in h.last_error and h.last_error_t_s == pytest.approx(0.45)
    assert h.last_error_utc.endswith("+00:00")
    bus.code = None
    t += 0.05
    assert c.read(t).valid
    assert c.health.state == "degraded" and c.health.consecutive_errors == 0  # not yet: recover_s
    while t < 1.5:
        t += 0.05
        c.read(t)
    assert c.health.state == "connected" and c.health.errors == 12
    events = c.take_health_events()
    assert [(e.old, e.new) for e in events] == [
        ("disconnected", "connected"),
        ("connected", "degraded"),
        ("degraded", "connected"),
    ]
    assert "Remote I/O error" in events[1].message
    assert events[2].message.startswith("compass recovered after 12 errors")


def test_stale_by_time_whatever_the_failure_count() -> None:
    # stale_after is far away: only [compass] stale_s (by the sample times) makes it stale
    _, bus, c = sim_compass(retries=0, stale_after=10_000, stale_s=0.5)
    assert c.read(10.0).valid
    bus.code = errno.EIO
    assert c.read(10.45).valid  # 0.45 s old: still usable
    assert c.health.state == "degraded"
    att = c.read(10.55)  # 0.55 s since the last good sample
    assert not att.valid and att.t_s == 10.55 and att.bearing_deg == pytest.approx(123.0, abs=0.2)
    assert c.stale and c.health.state == "stale"
    assert c.counters.stale_events == 1
    bus.code = None
    back = c.read(10.6)
    assert back.valid and not c.stale and c.health.state == "degraded"  # errors 0.05 s ago
    msgs = [e.message for e in c.take_health_events()]
    assert msgs[2].startswith("compass stale: ") and msgs[3].startswith("compass fresh again")


def test_slow_sampling_is_stale_by_time_before_the_count() -> None:
    # 2 Hz samples, stale_after 5: without stale_s the compass would look usable for 2.5 s
    _, bus, c = sim_compass(retries=0, stale_after=5, stale_s=0.5)
    assert c.read(0.0).valid
    bus.code = errno.ETIMEDOUT
    assert c.read(0.4).valid
    assert not c.read(0.8).valid  # 2 failed samples only, but 0.8 s old
    c.stale_s = None
    assert c.read(1.2).valid is False  # stays stale until a good sample
    with pytest.raises(ValueError, match="stale_s"):
        c.stale_s = 0.0


def test_reopened_bus_counts_a_reconnect() -> None:
    dev, bus, c = sim_compass(stale_s=0.5)
    assert c.read(1.0).valid
    bus.code = errno.EACCES
    with pytest.raises(DeviceIOError):
        c.read(1.05)
    assert not c.health.connected
    c.attach_bus(StormBus(dev), 2.0)
    assert c.read(2.05).valid
    h = c.health
    assert (h.state, h.reconnects, h.errors) == ("connected", 1, 1)
    assert (
        c.take_health_events()[-1].message
        == "compass reconnected (reconnect 1, 0.95 s after the loss)"
    )
