"""Devantech CMPS10 tilt-compensated compass over I2C (REFERENCE.md §4).

Works over any object with the smbus2 method set (``smbus2.SMBus`` on the robot, the
simulator's register map in tests). One sample is ONE block read of registers 1-5, so the
bearing bytes and pitch/roll come from the same device update (two reads can tear).

The Raspberry Pi's I2C master mishandles clock stretching: a transaction can hand back a
corrupted byte with no errno at all (one flipped bit in the bearing's high byte turned
123.4 deg into 174.6 deg, in range). So the sample carries the bearing twice: register 1
(0-255 for a full circle, 1.41 deg a step) and registers 2-3 (tenths of a degree); a sample
whose two bearings are more than :data:`BEARING_AGREE_DEG` apart (round the circle) is
corrupt: counted (``bearing_mismatches``; in the health's ``corrupt`` counts, which status
shows) and treated as a failed attempt (retried; if every attempt fails, a failed sample).

Linux reports I2C trouble as ``OSError``; the errnos of :data:`x6wd.core.errors.TRANSIENT_ERRNOS`
(EIO, ENXIO, EAGAIN, EBUSY, EINTR, EPROTO, ETIMEDOUT, EREMOTEIO) are retried. After
``stale_after`` consecutive failed samples, or when no good sample arrived for ``stale_s``
seconds (by the sample times, whatever the count), the driver reports the attitude as stale
(``valid=False``) until a good read: a device fault is data, not a crash. Any other errno is a
real fault: the health says disconnected and :class:`DeviceIOError` is raised.

Health: :attr:`Cmps10.health` (a :class:`~x6wd.core.records.DeviceHealth`) counts every failed
attempt, and says connected / degraded (errors being retried, data fresh) / stale /
disconnected; :meth:`Cmps10.take_health_events` hands its transitions to the caller's log.
"""

from __future__ import annotations

import contextlib
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, NamedTuple, Protocol

from x6wd.core.errors import DeviceIOError, DeviceUnavailable, is_transient
from x6wd.core.health import HealthTracker
from x6wd.core.records import Attitude, DeviceHealth, HealthEvent

DEFAULT_ADDRESS = 0x60
VALID_ADDRESSES = tuple(range(0x60, 0x68))

REG_VERSION = 0
REG_BEARING_BYTE = 1
REG_BEARING_WORD = 2  # 2-3 bearing (tenths of a degree, high byte first), 4 pitch, 5 roll
SAMPLE_LENGTH = 5  # one block read from register 1: bearing byte, bearing word, pitch, roll
REG_MAG = 10  # 10-15 magnetometer X/Y/Z, signed 16-bit big-endian
REG_ACC = 16  # 16-21 accelerometer X/Y/Z, signed 16-bit big-endian
REG_COMMAND = 22

CMD_CALIBRATE_START = 0xF0
CMD_CALIBRATE_POINT = 0xF5
FACTORY_RESTORE_SEQUENCE = (0x20, 0x2A, 0x60)
CHANGE_ADDRESS_SEQUENCE = (0xA0, 0xAA, 0xA5)
CALIBRATION_POINTS = ("N", "E", "S", "W")

MAX_BEARING_DEG = 359.9
MAX_TILT_DEG = 85.0
COMMAND_GAP_S = 0.1  # datasheet: one command byte per write, about 100 ms apart
BEARING_BYTE_STEP_DEG = 360.0 / 256.0  # register 1's resolution
BEARING_BYTE_STEPS = (256, 255)
"""Steps of register 1 per turn: the datasheet says "0-255 for a full circle", which a
firmware may scale by 256 (255 = 358.6 deg) or by 255 (255 = 360 deg); both are accepted, as
which one the CMPS10 uses is not published: one scale only, a truncating device of the other
would have 494 of the 3600 bearings (175-360 deg) refused on every try."""
BEARING_AGREE_DEG = 2.0
"""Most the bearing of registers 2-3 may differ from register 1's (deg, round the circle).
Register 1 is 1.41 deg a step: rounded by the device it is within 0.7 deg of the true
bearing, truncated within 1.41 deg (plus the word's 0.05 deg rounding). A bit flipped in the
word's high byte is 25.6 deg or more, bits 7-5 of its low byte 12.8, 6.4 and 3.2 deg: caught
(3.2 deg near north only by one of the two scales); the smaller ones are within the coarse
register's resolution and do little harm."""

CORRUPT_LABELS = {
    "bearing_mismatches": "samples whose two bearing registers disagree",
    "range_errors": "samples outside the datasheet ranges",
}
"""The driver's counts of corrupt samples that health shows (``DeviceHealth.corrupt``)."""


class SMBusLike(Protocol):
    """The part of the smbus2 ``SMBus`` method set this driver uses."""

    def read_byte_data(self, i2c_addr: int, register: int) -> int: ...

    def write_byte_data(self, i2c_addr: int, register: int, value: int) -> None: ...

    def read_i2c_block_data(self, i2c_addr: int, register: int, length: int) -> list[int]: ...


@dataclass
class Cmps10Counters:
    """What went wrong and how often (for telemetry and the gap tool)."""

    samples: int = 0  # read() calls
    good_samples: int = 0
    failed_samples: int = 0  # every attempt of the sample failed
    io_errors: int = 0  # transient OSErrors seen (each attempt)
    retries: int = 0  # attempts after the first one of a sample/command
    range_errors: int = 0  # block reads whose values were outside the datasheet ranges
    bearing_mismatches: int = 0  # block reads whose register 1 and 2-3 bearings disagreed
    stale_events: int = 0  # transitions into the stale state


def _s8(b: int) -> int:
    return b - 256 if b >= 128 else b


class _Corrupt(NamedTuple):
    """A block read whose bytes are no sample: its :data:`CORRUPT_LABELS` kind, and why."""

    kind: str
    why: str


def bearing_disagreement_deg(bearing_byte: int, bearing_deg: float) -> float:
    """How far (deg, 0-180, round the circle) register 1's coarse bearing ``bearing_byte``
    (0-255, read on the nearer of :data:`BEARING_BYTE_STEPS`' scales) lies from the fine
    bearing ``bearing_deg`` of registers 2-3."""
    out = 180.0
    for steps in BEARING_BYTE_STEPS:
        d = abs(bearing_deg - bearing_byte * 360.0 / steps) % 360.0
        out = min(out, d, 360.0 - d)
    return out


def _s16(hi: int, lo: int) -> int:
    v = (hi << 8) | lo
    return v - 65536 if v >= 32768 else v


class Cmps10:
    """CMPS10 driver: attitude samples, raw sensors, calibration and address commands.

    ``retries`` is the number of extra attempts per sample or command after a transient
    error; ``stale_after`` the number of consecutive failed samples before the attitude is
    reported stale; ``stale_s`` (s, or None) the longest time without a good sample before
    it is stale anyway; ``sleep`` (seconds) is used for command spacing and retry back-off so
    tests and the simulator can run without waiting. Health times are the ``t_s`` given to
    :meth:`read`.
    """

    def __init__(
        self,
        bus: SMBusLike,
        address: int = DEFAULT_ADDRESS,
        *,
        retries: int = 3,
        stale_after: int = 5,
        sleep: Callable[[float], Any] = time.sleep,
        retry_delay_s: float = 0.001,
        stale_s: float | None = None,
    ) -> None:
        if address not in VALID_ADDRESSES:
            raise ValueError(f"CMPS10 address must be 0x60..0x67 (7-bit), got {address:#x}")
        if retries < 0:
            raise ValueError(f"retries must be >= 0, got {retries}")
        if stale_after < 1:
            raise ValueError(f"stale_after must be >= 1, got {stale_after}")
        if retry_delay_s < 0:
            raise ValueError(f"retry_delay_s must be >= 0, got {retry_delay_s}")
        self.bus = bus
        self.address = address
        self.retries = retries
        self.stale_after = stale_after
        self.retry_delay_s = retry_delay_s
        self._sleep = sleep
        self.counters = Cmps10Counters()
        self._consecutive_failures = 0
        self._last_good: Attitude | None = None
        self._stale_by_time = False
        # The bus object exists, so the device counts as opened; staleness starts with the
        # first read (the constructor knows no sample time).
        self.health_tracker = HealthTracker(
            "compass", t_s=0.0, stale_s=stale_s, corrupt_labels=CORRUPT_LABELS
        )
        self._started = False

    # --- health -----------------------------------------------------------------------------

    @property
    def stale_s(self) -> float | None:
        """Longest time without a good sample before the attitude is stale (s), or None."""
        return self.health_tracker.stale_s

    @stale_s.setter
    def stale_s(self, value: float | None) -> None:
        if value is not None and not (value > 0 and math.isfinite(value)):
            raise ValueError(f"stale_s must be > 0 s or None, got {value!r}")
        self.health_tracker.stale_s = value

    @property
    def health(self) -> DeviceHealth:
        """The compass's health now (immutable snapshot; any thread may read it)."""
        return self.health_tracker.health

    def take_health_events(self) -> list[HealthEvent]:
        """Health transitions since the last call, oldest first (for the caller's log)."""
        return self.health_tracker.take_events()

    @property
    def needs_reopen(self) -> bool:
        """True after a non-transient error lost the device, until :meth:`attach_bus`."""
        return self._started and not self.health_tracker.health.connected

    def attach_bus(self, bus: SMBusLike, t_s: float) -> None:
        """Replace the bus after a reopen at ``t_s`` (s); counts as a reconnect. The old bus
        is closed; counters and health carry on."""
        old, self.bus = self.bus, bus
        if old is not bus:
            close = getattr(old, "close", None)
            if close is not None:
                with contextlib.suppress(OSError):  # the old bus is broken anyway
                    close()
        self._consecutive_failures = 0
        self._started = True
        self.health_tracker.opened(t_s)

    def _start(self, t_s: float) -> None:
        if not self._started:
            self._started = True
            self.health_tracker.opened(t_s)

    # --- transport -------------------------------------------------------------------------

    def _attempt(self, op: Callable[[], Any], what: str) -> Any:
        """Run ``op`` with retries on transient errnos; raise OSError after the last one."""
        for attempt in range(self.retries + 1):
            if attempt:
                self.counters.retries += 1
                if self.retry_delay_s:
                    self._sleep(self.retry_delay_s)
            try:
                return op()
            except OSError as exc:
                if not is_transient(exc):
                    raise DeviceIOError(
                        f"CMPS10 at {self.address:#04x}: {what} failed: {exc}"
                    ) from exc
                self.counters.io_errors += 1
                if attempt == self.retries:
                    raise
        raise AssertionError("unreachable")  # pragma: no cover

    def _write_command(self, value: int) -> None:
        def op() -> None:
            self.bus.write_byte_data(self.address, REG_COMMAND, value)

        try:
            self._attempt(op, f"command {value:#04x}")
        except OSError as exc:
            raise DeviceIOError(
                f"CMPS10 at {self.address:#04x}: command {value:#04x} not accepted "
                f"after {self.retries + 1} attempts: {exc}"
            ) from exc

    def _command_sequence(self, values: Sequence[int]) -> None:
        for i, value in enumerate(values):
            if i:
                self._sleep(COMMAND_GAP_S)
            self._write_command(value)

    # --- samples ----------------------------------------------------------------------------

    @property
    def stale(self) -> bool:
        """True after ``stale_after`` consecutive failed samples, or once the last failed
        sample came more than ``stale_s`` after the last good one, until the next good one."""
        return self._consecutive_failures >= self.stale_after or self._stale_by_time

    @property
    def last_good(self) -> Attitude | None:
        """The last valid attitude read, or None before the first."""
        return self._last_good

    def _read_once(self) -> tuple[float, int, int] | _Corrupt:
        """One block read of registers 1-5: (bearing deg, pitch deg, roll deg), or why the
        bytes are no sample."""
        data = self.bus.read_i2c_block_data(self.address, REG_BEARING_BYTE, SAMPLE_LENGTH)
        if len(data) != SAMPLE_LENGTH:
            return _Corrupt("range_errors", f"{len(data)} bytes read, expected {SAMPLE_LENGTH}")
        bearing_deg = ((data[1] << 8) | data[2]) / 10.0
        pitch_deg, roll_deg = _s8(data[3]), _s8(data[4])
        if (
            bearing_deg > MAX_BEARING_DEG
            or abs(pitch_deg) > MAX_TILT_DEG
            or abs(roll_deg) > MAX_TILT_DEG
        ):
            return _Corrupt("range_errors", "attitude registers out of range")
        if bearing_disagreement_deg(data[0], bearing_deg) > BEARING_AGREE_DEG:
            return _Corrupt(
                "bearing_mismatches",
                f"bearing registers disagree: {bearing_deg:.1f} deg (2-3) vs "
                f"{data[0] * BEARING_BYTE_STEP_DEG:.1f} deg (1)",
            )
        return bearing_deg, pitch_deg, roll_deg

    def read(self, t_s: float) -> Attitude:
        """One attitude sample taken at ``t_s`` (s, monotonic clock).

        A good sample returns ``Attitude(t_s, bearing_deg, pitch_deg, roll_deg, valid=True)``
        (bearing magnetic, 0-359.9 deg; pitch/roll whole degrees). A failed sample (bus errors
        on every attempt, values outside the datasheet ranges, or the two bearing registers
        disagreeing: corrupt bytes) returns the last good
        attitude unchanged, so its ``t_s`` keeps ageing honestly; with no good sample yet, or
        once ``stale_after`` samples in a row failed or the last good one is more than
        ``stale_s`` old, it returns ``valid=False`` at ``t_s`` (holding the last good values,
        or zeros; the controller's ``attitude_age_s`` still counts from the last good one).
        Raises :class:`DeviceIOError` for non-transient errors (health: disconnected).
        """
        self._start(t_s)
        self.counters.samples += 1
        sample: tuple[float, int, int] | None = None
        for attempt in range(self.retries + 1):
            if attempt:
                self.counters.retries += 1
                if self.retry_delay_s:
                    self._sleep(self.retry_delay_s)
            try:
                got = self._attempt_block_read(t_s)
            except OSError:
                continue
            if not isinstance(got, _Corrupt):
                sample = got
                break
            c = self.counters
            if got.kind == "bearing_mismatches":
                c.bearing_mismatches += 1
            else:
                c.range_errors += 1
            self.health_tracker.error(got.why, t_s)
            self.health_tracker.corrupt(
                {"bearing_mismatches": c.bearing_mismatches, "range_errors": c.range_errors}, t_s
            )
        if sample is not None:
            self._consecutive_failures = 0
            self._stale_by_time = False
            self.counters.good_samples += 1
            att = Attitude(t_s, sample[0], float(sample[1]), float(sample[2]), True)
            self._last_good = att
            self.health_tracker.good(t_s)
            return att
        self.counters.failed_samples += 1
        was_stale = self.stale
        self._consecutive_failures += 1
        last = self._last_good
        stale_s = self.stale_s
        if stale_s is not None and last is not None and t_s - last.t_s > stale_s:
            self._stale_by_time = True
        if self.stale and not was_stale:
            self.counters.stale_events += 1
        self.health_tracker.degrade(t_s)  # every attempt failed: this sample is lost
        if self.stale:
            self.health_tracker.set_stale(
                t_s, f"{self._consecutive_failures} failed samples in a row"
            )
        last = self._last_good
        if last is not None and not self.stale:
            return last
        if last is None:
            return Attitude(t_s, 0.0, 0.0, 0.0, valid=False)
        return Attitude(t_s, last.bearing_deg, last.pitch_deg, last.roll_deg, valid=False)

    def _attempt_block_read(self, t_s: float) -> tuple[float, int, int] | _Corrupt:
        """One bus transaction at sample time ``t_s`` (s); transient OSErrors are counted
        (driver counters and health) and re-raised, others raise DeviceIOError."""
        try:
            return self._read_once()
        except OSError as exc:
            if not is_transient(exc):
                msg = f"CMPS10 at {self.address:#04x}: attitude read failed: {exc}"
                self.health_tracker.lost(msg, t_s)
                raise DeviceIOError(msg) from exc
            self.counters.io_errors += 1
            self.health_tracker.error(f"attitude read failed: {exc}", t_s)
            raise

    def bearing_byte(self) -> int:
        """Register 1: bearing scaled 0-255 for a full circle (coarse, 1.41 deg per step)."""
        try:
            return int(
                self._attempt(
                    lambda: self.bus.read_byte_data(self.address, REG_BEARING_BYTE),
                    "bearing byte read",
                )
            )
        except OSError as exc:
            raise DeviceIOError(f"CMPS10 at {self.address:#04x}: no answer: {exc}") from exc

    def raw(self) -> tuple[tuple[int, int, int], tuple[int, int, int]]:
        """Raw magnetometer and accelerometer X/Y/Z (signed 16-bit counts, registers 10-21).

        One block read of 12 bytes, so both vectors belong to the same update.
        """
        try:
            data = self._attempt(
                lambda: self.bus.read_i2c_block_data(self.address, REG_MAG, 12), "raw read"
            )
        except OSError as exc:
            raise DeviceIOError(
                f"CMPS10 at {self.address:#04x}: raw read failed after "
                f"{self.retries + 1} attempts: {exc}"
            ) from exc
        if len(data) != 12:
            raise DeviceIOError(f"CMPS10 raw read returned {len(data)} bytes, expected 12")
        v = [_s16(data[i], data[i + 1]) for i in range(0, 12, 2)]
        return (v[0], v[1], v[2]), (v[3], v[4], v[5])

    # --- identity and commands --------------------------------------------------------------

    def version(self) -> int:
        """Software version byte (register 0)."""
        try:
            return int(
                self._attempt(
                    lambda: self.bus.read_byte_data(self.address, REG_VERSION), "version read"
                )
            )
        except OSError as exc:
            raise DeviceIOError(f"CMPS10 at {self.address:#04x}: no answer: {exc}") from exc

    def check_version(self) -> int:
        """Confirm a CMPS10 answers at the address; return its software version.

        Raises :class:`DeviceUnavailable` when nothing answers or the version byte is absurd
        (0x00 or 0xFF: a floating or shorted bus, not a compass).
        """
        try:
            ver = self.version()
        except DeviceIOError as exc:
            raise DeviceUnavailable(
                f"no CMPS10 answering at I2C address {self.address:#04x}: {exc}"
            ) from exc
        if ver in (0x00, 0xFF):
            raise DeviceUnavailable(
                f"device at I2C address {self.address:#04x} reports software version "
                f"{ver:#04x}: not a CMPS10 (floating or shorted bus?)"
            )
        return ver

    def calibrate(
        self,
        at_point: Callable[[int, str], Any],
        *,
        points: Sequence[str] = CALIBRATION_POINTS,
    ) -> None:
        """Run the calibration: 0xF0, then at each point (N, E, S, W) 0xF5.

        ``at_point(index, name)`` is called before each point's command; it returns once the
        robot is level and pointing there (rotate it, or ask an operator to confirm). If it
        raises, calibration stops and the exception propagates (power-cycle the compass to
        leave calibration mode). Commands are spaced ``COMMAND_GAP_S`` apart.
        """
        if len(points) != 4:
            raise ValueError(f"CMPS10 calibration needs 4 points, got {len(points)}")
        self._write_command(CMD_CALIBRATE_START)
        for i, name in enumerate(points):
            self._sleep(COMMAND_GAP_S)
            at_point(i, name)
            self._write_command(CMD_CALIBRATE_POINT)

    def restore_factory(self) -> None:
        """Restore the factory calibration: 0x20, 0x2A, 0x60 about 100 ms apart."""
        self._command_sequence(FACTORY_RESTORE_SEQUENCE)

    def change_address(self, new_address: int) -> None:
        """Move the device to 7-bit ``new_address`` (0x60-0x67); this driver follows it.

        Sends 0xA0, 0xAA, 0xA5, then the new address in 8-bit notation, ~100 ms apart. The
        new address is kept by the device across power cycles.
        """
        if new_address not in VALID_ADDRESSES:
            raise ValueError(f"CMPS10 address must be 0x60..0x67 (7-bit), got {new_address:#x}")
        self._command_sequence((*CHANGE_ADDRESS_SEQUENCE, new_address << 1))
        self._sleep(COMMAND_GAP_S)
        self.address = new_address

    def close(self) -> None:
        """Close the underlying bus if it has a ``close`` method (idempotent)."""
        close = getattr(self.bus, "close", None)
        if close is not None:
            close()

    def __enter__(self) -> Cmps10:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
