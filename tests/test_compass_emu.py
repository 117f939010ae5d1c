"""The simulated CMPS10 register map, read through the real drivers.cmps10 driver."""

from __future__ import annotations

import errno
import math

import numpy as np
import pytest

from drivers.cmps10 import Cmps10
from sim_backend.compass import (
    CompassErrors,
    ErrorInjector,
    MagneticField,
    SimClock,
    SimCmps10,
)
from x6wd.core.errors import ConfigError, DeviceIOError

DECL = 4.0


def _wrap(a: float) -> float:
    return (a + 180.0) % 360.0 - 180.0


def _device(clock: SimClock | None = None, **kw: object) -> SimCmps10:
    return SimCmps10(
        field_model=MagneticField.from_total(49.0, 66.0, DECL),
        clock=None if clock is None else clock.now,
        **kw,  # type: ignore[arg-type]
    )


def _settle(
    dev: SimCmps10, t0: float, heading: float, pitch: float = 0.0, roll: float = 0.0
) -> float:
    """Hold an attitude for 3 s so the heading filter has settled; returns the end time."""
    for k in range(4):
        dev.set_state(t0 + k, heading, pitch, roll)
    return t0 + 3.0


def test_driver_reads_magnetic_bearing_and_attitude_over_a_sweep() -> None:
    dev = _device()
    drv = Cmps10(dev, sleep=lambda _s: None)
    assert drv.check_version() == 15
    t = 0.0
    for heading in range(0, 360, 15):
        for pitch, roll in ((0, 0), (25, -10), (-40, 30)):
            t = _settle(dev, t + 1, heading, pitch, roll)
            att = drv.read(t)
            assert att.valid
            # No iron errors: tilt compensation is exact, only the 0.1 deg register step.
            assert abs(_wrap(att.bearing_deg - (heading - DECL))) <= 0.051
            assert (att.pitch_deg, att.roll_deg) == (pitch, roll)
            assert drv.bearing_byte() == round(((heading - DECL) % 360) * 256 / 360) % 256


def test_pitch_and_roll_are_clamped_to_85_and_signed() -> None:
    dev = _device()
    _settle(dev, 0.0, 10.0, 89.0, -88.0)
    regs = dev.registers
    assert regs[4] == 85 and regs[5] == (-85) & 0xFF
    att = Cmps10(dev, sleep=lambda _s: None).read(5.0)
    assert att.valid and att.pitch_deg == 85 and att.roll_deg == -85


def test_raw_registers_follow_the_field_and_gravity() -> None:
    dev = _device()
    drv = Cmps10(dev, sleep=lambda _s: None)
    for heading, pitch, roll in ((0, 0, 0), (123, 15, -20), (250, -30, 5)):
        _settle(dev, 10.0 * heading + 100, heading, pitch, roll)
        mag, acc = drv.raw()
        # 10 counts per microtesla, 1000 counts per g (documented scales).
        assert math.hypot(*mag) == pytest.approx(490.0, abs=2.0)
        assert math.hypot(*acc) == pytest.approx(1000.0, abs=2.0)
        assert acc[0] == pytest.approx(-1000 * math.sin(math.radians(pitch)), abs=1.0)
    _settle(dev, 5000.0, 0.0)
    mag, _ = drv.raw()
    # Level, pointing true north: the field's vertical part is +z (down), dip 66 deg.
    assert math.degrees(math.atan2(mag[2], math.hypot(mag[0], mag[1]))) == pytest.approx(
        66, abs=0.3
    )


def test_big_endian_words_and_why_read_word_data_is_wrong() -> None:
    dev = _device()
    _settle(dev, 0.0, 200.0)
    hi, lo = dev.read_i2c_block_data(0x60, 2, 2)
    tenths = (hi << 8) | lo
    assert tenths == round((200.0 - DECL) * 10)
    word = dev.read_word_data(0x60, 2)
    assert word == (lo << 8) | hi != tenths


def test_block_reads_auto_increment_and_respect_the_32_byte_limit() -> None:
    dev = _device()
    _settle(dev, 0.0, 77.0, 3.0, -2.0)
    regs = dev.registers
    assert dev.read_i2c_block_data(0x60, 0, 23) == list(regs)
    assert dev.read_i2c_block_data(0x60, 4, 2) == [regs[4], regs[5]]
    assert dev.read_i2c_block_data(0x60, 20, 5) == [regs[20], regs[21], regs[22], 0, 0]
    assert len(dev.read_i2c_block_data(0x60, 0, 32)) == 32
    with pytest.raises(ValueError, match="32"):
        dev.read_i2c_block_data(0x60, 0, 33)
    with pytest.raises(ValueError, match="32"):
        dev.write_i2c_block_data(0x60, 22, [0] * 33)


def test_wrong_address_and_closed_bus_fail_like_linux() -> None:
    dev = _device()
    with pytest.raises(OSError) as exc:
        dev.read_byte_data(0x61, 0)
    assert exc.value.errno == errno.EREMOTEIO
    with dev:
        pass
    with pytest.raises(OSError):
        dev.read_byte_data(0x60, 0)


def test_heading_lag_is_first_order_with_exact_discretisation() -> None:
    a = _device()
    b = _device()
    for dev in (a, b):
        _settle(dev, 0.0, 0.0 + DECL)  # magnetic 0
    tau = a.errors.lag_tau_s
    a.set_state(3.64, 90.0 + DECL, 0, 0)  # one step of 640 ms
    for k in range(1, 65):
        b.set_state(3.0 + 0.01 * k, 90.0 + DECL, 0, 0)  # 64 steps of 10 ms
    expected = 90.0 * (1 - math.exp(-0.64 / tau))
    assert a.bearing_deg == pytest.approx(expected, abs=1e-9)
    assert b.bearing_deg == pytest.approx(expected, abs=1e-9)
    assert a.bearing_deg > 0.9 * 90  # "refreshes fully" in about 640 ms


def _sweep_errors(dev: SimCmps10, t0: float) -> np.ndarray:
    errs = []
    for k, heading in enumerate(np.arange(0.0, 360.0, 10.0)):
        _settle(dev, t0 + 10 * k, float(heading))
        errs.append(_wrap(dev.bearing_deg - (heading - DECL)))
    return np.array(errs)


def test_hard_iron_repeats_once_and_soft_iron_twice_per_turn() -> None:
    hard = _device(errors=CompassErrors(hard_iron_ut=(4.0, 2.0, 0.0)))
    soft = _device(errors=CompassErrors(soft_iron=((1.15, 0, 0), (0, 0.85, 0), (0, 0, 1))))
    for dev, harmonic in ((hard, 1), (soft, 2)):
        spectrum = np.abs(np.fft.rfft(_sweep_errors(dev, 0.0)))
        assert spectrum[1:6].argmax() + 1 == harmonic
        assert spectrum[harmonic] > 5 * np.delete(spectrum[1:6], harmonic - 1).max()


def test_calibration_through_the_driver_removes_hard_iron_and_restore_brings_it_back() -> None:
    clock = SimClock(100.0)
    dev = _device(clock, errors=CompassErrors(hard_iron_ut=(5.0, -3.0, 2.0)))
    drv = Cmps10(dev, sleep=clock.sleep)
    before = np.abs(_sweep_errors(dev, 0.0)).max()
    assert before > 5.0
    points = {"N": 0.0, "E": 90.0, "S": 180.0, "W": 270.0}

    def at_point(_i: int, name: str) -> None:
        # Point the robot at the magnetic direction and hold it still.
        clock.sleep(3.0)
        _settle(dev, clock.now(), points[name] + DECL)
        clock.sleep(3.0)

    clock.t_s = 1000.0
    dev.set_state(clock.now(), 0.0, 0.0, 0.0)
    drv.calibrate(at_point)
    assert not dev.calibrating
    after = np.abs(_sweep_errors(dev, clock.now() + 10)).max()
    assert after < 0.2
    clock.t_s = 2000.0
    drv.restore_factory()
    restored = np.abs(_sweep_errors(dev, clock.now() + 10)).max()
    assert restored == pytest.approx(before, rel=1e-6)


def test_commands_too_fast_are_ignored_and_address_change_follows_the_timing() -> None:
    clock = SimClock(0.0)
    dev = _device(clock)
    for value in (0xA0, 0xAA, 0xA5, 0xC2):  # no time between bytes
        dev.write_byte_data(0x60, 22, value)
    assert dev.address == 0x60 and dev.commands_ignored >= 3
    clock.sleep(1.0)
    drv = Cmps10(dev, sleep=clock.sleep)
    drv.change_address(0x61)
    assert dev.address == 0x61 and drv.address == 0x61
    assert drv.version() == 15
    with pytest.raises(DeviceIOError):
        Cmps10(dev, 0x60, sleep=clock.sleep, retries=0).version()


def test_scripted_errno_storm_is_retried_then_reported_stale() -> None:
    inj = ErrorInjector()
    dev = _device(injector=inj)
    _settle(dev, 0.0, 50.0)
    drv = Cmps10(dev, retries=3, stale_after=2, sleep=lambda _s: None)
    inj.push([121, 110, 5])  # three failures, the fourth attempt succeeds
    att = drv.read(3.0)
    assert att.valid and drv.counters.io_errors == 3 and drv.counters.retries == 3
    inj.push([121] * 8)  # two whole samples fail (4 attempts each)
    assert drv.read(3.1).valid  # first failure: last good kept
    stale = drv.read(3.2)
    assert not stale.valid and drv.stale
    assert drv.read(3.3).valid and not drv.stale  # bus quiet again
    assert inj.injected == 11


def test_probabilistic_errors_hit_the_expected_fraction_and_are_reproducible() -> None:
    def run(seed: int) -> tuple[int, list[bool]]:
        inj = ErrorInjector(p_error=0.3, rng=np.random.default_rng(seed))
        dev = _device(injector=inj)
        _settle(dev, 0.0, 50.0)
        drv = Cmps10(dev, retries=1, stale_after=3, sleep=lambda _s: None)
        valid = [drv.read(3.0 + 0.05 * k).valid for k in range(400)]
        return inj.injected, valid

    injected, valid = run(11)
    assert run(11) == (injected, valid)
    attempts = 400 + injected * 1.0  # lower bound on transactions (retries add more)
    frac = injected / attempts
    assert 0.2 < frac < 0.35
    assert sum(valid) > 350  # a retry almost always rescues the sample


def test_bad_parameters_and_inputs_are_rejected() -> None:
    with pytest.raises(ConfigError, match="singular"):
        CompassErrors(soft_iron=((1, 0, 0), (0, 0, 0), (0, 0, 1)))
    with pytest.raises(ConfigError, match="rng"):
        ErrorInjector(p_error=0.1)
    with pytest.raises(ConfigError, match="rng"):
        SimCmps10(errors=CompassErrors(noise_ut=0.5))
    with pytest.raises(ConfigError, match="address"):
        SimCmps10(address=0x70)
    dev = _device()
    with pytest.raises(ValueError, match="finite"):
        dev.set_state(0.0, math.nan, 0, 0)
    dev.set_state(5.0, 0, 0, 0)
    with pytest.raises(ValueError, match="backwards"):
        dev.set_state(4.0, 0, 0, 0)


def test_noise_is_driven_by_the_generator() -> None:
    def bearings(seed: int) -> list[int]:
        dev = SimCmps10(
            errors=CompassErrors(noise_ut=0.5, lag_tau_s=0.0), rng=np.random.default_rng(seed)
        )
        out = []
        for k in range(50):
            dev.set_state(0.05 * k, 30.0, 0, 0)
            out.append(dev.read_i2c_block_data(0x60, 2, 2)[1])
        return out

    assert bearings(1) == bearings(1) != bearings(2)


# ---------------------------------------------------------------- float fast path
# set_state works on plain floats for speed; it must reproduce the numpy formulation of the
# physics. On the reference machine it does so bit for bit (the mission outputs did not move),
# but numpy's small matrix products go through the platform's BLAS, whose summation order is
# not ours to fix, so the floats are compared to 1e-12 here and the registers exactly.


def _reference_step(
    dev: SimCmps10, rng: np.random.Generator, state: dict[str, float | None], t_s: float,
    heading: float, pitch: float, roll: float,
) -> tuple[float, bytes, list[float]]:  # fmt: skip
    """The emulator's physics written with numpy vectors, as it was before the fast path."""
    from sim_backend.compass import MAG_COUNTS_PER_UT, _rot_body_to_ned, _s16be

    rot = _rot_body_to_ned(heading, pitch, roll)
    soft = np.asarray(dev.errors.soft_iron, dtype=float)
    m = soft @ (rot.T @ dev.field_model.ned_ut()) + np.asarray(dev.errors.hard_iron_ut)
    if dev.errors.noise_ut > 0:
        m = m + rng.normal(0.0, dev.errors.noise_ut, 3)
    h = _rot_body_to_ned(0.0, pitch, roll) @ (m - dev.cal_offset_ut)
    raw = math.degrees(math.atan2(-h[1], h[0])) % 360.0
    filt, t_prev = state["filt"], state["t"]
    if filt is None or t_prev is None:
        filt = raw
    else:
        tau = dev.errors.lag_tau_s
        alpha = 1.0 if tau == 0 else 1.0 - math.exp(-(t_s - t_prev) / tau)
        filt = (filt + alpha * _wrap(raw - filt)) % 360.0
    state["filt"], state["t"] = filt, t_s
    regs = bytearray(23)
    tenths = round(filt * 10.0) % 3600
    regs[1] = round(filt * 256.0 / 360.0) % 256
    regs[2], regs[3] = tenths >> 8, tenths & 0xFF
    regs[4] = round(max(-85.0, min(85.0, pitch))) & 0xFF
    regs[5] = round(max(-85.0, min(85.0, roll))) & 0xFF
    counts = m * MAG_COUNTS_PER_UT
    acc = rot.T @ np.array([0.0, 0.0, -1.0]) * -1000.0
    for i in range(3):
        regs[10 + 2 * i], regs[11 + 2 * i] = _s16be(counts[i])
        regs[16 + 2 * i], regs[17 + 2 * i] = _s16be(acc[i])
    return filt, bytes(regs[1:]), m.tolist()


@pytest.mark.parametrize(
    ("errors", "tilt"),
    [
        (CompassErrors(noise_ut=0.05), False),
        (CompassErrors(noise_ut=0.0), True),
        (CompassErrors(noise_ut=0.2, hard_iron_ut=(3.0, -2.0, 1.0)), True),
        (
            CompassErrors(
                noise_ut=0.1, soft_iron=((1.05, 0.02, 0.0), (0.02, 0.97, 0.01), (0.0, 0.01, 1.0))
            ),
            False,
        ),
    ],
)
def test_set_state_matches_the_numpy_formulation(errors: CompassErrors, tilt: bool) -> None:
    dev = _device(errors=errors, rng=np.random.default_rng(3))
    ref_rng = np.random.default_rng(3)
    if errors.noise_ut > 0:
        ref_rng.normal(0.0, errors.noise_ut, 3)  # the constructor's own set_state drew these
    motion = np.random.default_rng(4)
    state: dict[str, float | None] = {"filt": None, "t": None}
    heading = 10.0
    for k in range(400):
        t = 0.05 * k
        heading = (heading + float(motion.normal(0, 8))) % 360.0
        pitch, roll = (float(v) for v in motion.normal(0, 5, 2)) if tilt else (0.0, 0.0)
        dev.set_state(t, heading, pitch, roll)
        filt, regs, mag = _reference_step(dev, ref_rng, state, t, heading, pitch, roll)
        assert dev.bearing_deg == pytest.approx(filt, rel=1e-12, abs=1e-12)
        assert dev.registers[1:] == regs
        assert list(dev.mag_body_ut) == pytest.approx(mag, rel=1e-12, abs=1e-12)
