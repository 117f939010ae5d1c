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

import pytest

from drivers.cmps10 import REG_BEARING_BYTE, Cmps10


class FlakyBus:
    """A CMPS10's registers behind the smbus2 method set. ``flip`` (register -> mask) XORs
    those registers' bytes in the next block read that covers them, as the clock-stretching
    bug does (``flip_reads`` block reads in a row); ``fail`` makes the next block reads
    raise EREMOTEIO."""

    def __init__(self, bearing_deg: float = 123.4, *, truncate: bool = False) -> None:
        self.regs = [0] * 23
        self.regs[0] = 15
        self.truncate = truncate
        self.set(bearing_deg, 2, -1)
        self.flip: dict[int, int] = {}
        self.flip_reads = 1
        self.fail = 0
        self.block_reads: list[tuple[int, int]] = []

    def set(self, bearing_deg: float, pitch: int, roll: int) -> None:
        tenths = round(bearing_deg * 10) % 3600
        coarse = tenths * 256 // 3600 if self.truncate else round(tenths * 256 / 3600)
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


@pytest.mark.parametrize("truncate", [False, True], ids=["rounded", "truncated"])
def test_every_honest_bearing_passes(truncate: bool) -> None:
    """Register 1 is 1.41 deg coarse (rounded or truncated by the device): every tenth of a
    degree round the circle, 359.9 next to 0.0 included, agrees with it."""
    bus = FlakyBus(0.0, truncate=truncate)
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
