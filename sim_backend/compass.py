"""The Devantech CMPS10 as an I2C register map with the smbus2 method set (REFERENCE.md §4).

The simulated device sits behind the same calls as ``smbus2.SMBus``: ``read_byte_data``,
``write_byte_data``, ``read_i2c_block_data`` (at most 32 bytes), ``write_i2c_block_data``,
``read_word_data`` (an SMBus word is LITTLE-endian, so it byte-swaps the CMPS10's big-endian
registers: that is what a driver must not use), ``close`` and the context manager. Each
transaction starts at its register and auto-increments the pointer.

Registers: 0 software version; 1 bearing 0-255; 2-3 bearing 0-3599 tenths (high byte first);
4 pitch, 5 roll (signed degrees, clamped to ±85); 10-15 magnetometer X/Y/Z, 16-21 accelerometer
X/Y/Z (signed 16-bit, high byte first); 22 command register.

Physics (implemented here on vectors, because the raw registers need the field vector, not
just a heading): the Earth field is given by its horizontal and vertical intensity and the
declination (:class:`MagneticField`). It is rotated into the body frame (x forward, y right,
z down) by the true heading, pitch and roll, distorted by soft iron (a 3x3 matrix) and offset
by hard iron (µT), plus white noise. The device levels the measured vector with its own
pitch/roll, subtracts the offset its calibration found, and computes the MAGNETIC bearing;
that bearing passes a first-order filter (the CMPS10 takes about 640 ms to refresh fully;
exact discretisation over the caller's time step). The calibration sequence (0xF0, then 0xF5
at N, E, S, W) estimates the hard-iron offset as the mean of the four horizontal readings, so
a calibration done with the robot pointing the right ways removes hard iron, as on the real
device; factory restore forgets it.

Raw scales (not in the datasheet; chosen here): magnetometer 10 counts per µT, accelerometer
1000 counts per g (x forward, y right, z down; level at rest reads z = +1000).
"""

from __future__ import annotations

import errno
import math
import struct
from collections import deque
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any, cast

import numpy as np

from sim_backend.effects import PITCH_ROLL_LIMIT_DEG, Tilt, tilted_heading_deg, wrap180
from x6wd.core.errors import ConfigError
from x6wd.core.geodesy import wrap360, wrap_deg

VERSION = 15
DEFAULT_ADDRESS = 0x60
VALID_ADDRESSES = tuple(range(0x60, 0x68))
NUM_REGISTERS = 23
REG_COMMAND = 22
MAX_BLOCK = 32  # SMBus block transfer limit
MAX_TILT_DEG = 85.0
HEADING_REFRESH_S = 0.640  # datasheet: about 640 ms for the filter to refresh fully
MIN_COMMAND_GAP_S = 0.08  # command bytes closer than this are ignored (datasheet asks ~100 ms)
MAG_COUNTS_PER_UT = 10.0
ACC_COUNTS_PER_G = 1000.0
I2C_ERRNOS = (errno.EREMOTEIO, errno.ETIMEDOUT, errno.EIO)  # 121, 110, 5

CALIBRATION_START = 0xF0
CALIBRATION_POINT = 0xF5
FACTORY_RESTORE = (0x20, 0x2A, 0x60)
ADDRESS_CHANGE = (0xA0, 0xAA, 0xA5)


@dataclass(frozen=True)
class MagneticField:
    """The local geomagnetic field: horizontal and vertical (down) intensity in µT and the
    declination (degrees east of true north)."""

    horizontal_ut: float = 18.5
    vertical_ut: float = 46.0
    declination_deg: float = 0.0

    def __post_init__(self) -> None:
        for name in ("horizontal_ut", "vertical_ut", "declination_deg"):
            if not math.isfinite(getattr(self, name)):
                raise ConfigError(f"magnetic field {name} must be finite")
        if self.horizontal_ut <= 0:
            raise ConfigError(f"horizontal_ut must be > 0, got {self.horizontal_ut}")

    @classmethod
    def from_total(
        cls, total_ut: float, inclination_deg: float, declination_deg: float = 0.0
    ) -> MagneticField:
        """From total intensity (µT) and inclination (degrees, positive down)."""
        i = math.radians(inclination_deg)
        return cls(total_ut * math.cos(i), total_ut * math.sin(i), declination_deg)

    @property
    def inclination_deg(self) -> float:
        """Dip angle, degrees (positive: field points down, northern hemisphere)."""
        return math.degrees(math.atan2(self.vertical_ut, self.horizontal_ut))

    @property
    def total_ut(self) -> float:
        """Total intensity, µT."""
        return math.hypot(self.horizontal_ut, self.vertical_ut)

    def ned_ut(self) -> np.ndarray:
        """Field vector in the geographic north/east/down frame, µT."""
        d = math.radians(self.declination_deg)
        return np.array(
            [self.horizontal_ut * math.cos(d), self.horizontal_ut * math.sin(d), self.vertical_ut]
        )


@dataclass(frozen=True)
class CompassErrors:
    """The compass's physical imperfections.

    ``hard_iron_ut`` body-frame offset (x fwd, y right, z down); ``soft_iron`` 3x3 matrix
    applied to the body-frame field (identity = none); ``noise_ut`` white noise per axis;
    ``lag_tau_s`` the heading filter's time constant (default: 640 ms is ~3 time constants).
    """

    hard_iron_ut: tuple[float, float, float] = (0.0, 0.0, 0.0)
    soft_iron: tuple[tuple[float, ...], ...] = (
        (1.0, 0.0, 0.0),
        (0.0, 1.0, 0.0),
        (0.0, 0.0, 1.0),
    )
    noise_ut: float = 0.0
    lag_tau_s: float = HEADING_REFRESH_S / 3.0

    def __post_init__(self) -> None:
        if len(self.hard_iron_ut) != 3:
            raise ConfigError("hard_iron_ut needs 3 components (x, y, z)")
        if not all(math.isfinite(x) for x in self.hard_iron_ut):  # a NaN crashed the run
            raise ConfigError(f"hard_iron_ut must be 3 finite numbers, got {self.hard_iron_ut}")
        m = np.asarray(self.soft_iron, dtype=float)
        if m.shape != (3, 3) or not np.all(np.isfinite(m)):
            raise ConfigError("soft_iron must be a finite 3x3 matrix")
        if abs(np.linalg.det(m)) < 1e-6:
            raise ConfigError("soft_iron matrix is singular")
        if not (self.noise_ut >= 0 and math.isfinite(self.noise_ut)):
            raise ConfigError(f"noise_ut must be >= 0, got {self.noise_ut}")
        if not (self.lag_tau_s >= 0 and math.isfinite(self.lag_tau_s)):
            raise ConfigError(f"lag_tau_s must be >= 0, got {self.lag_tau_s}")


@dataclass
class ErrorInjector:
    """I2C faults: each transaction fails with probability ``p_error`` (errno drawn from
    ``errnos``), and ``script`` (errno or None per transaction, consumed first) forces them.
    A probability > 0 needs ``rng``."""

    p_error: float = 0.0
    errnos: tuple[int, ...] = I2C_ERRNOS
    rng: np.random.Generator | None = None
    script: deque[int | None] = field(default_factory=deque)
    injected: int = 0

    def __post_init__(self) -> None:
        if not 0.0 <= self.p_error <= 1.0:
            raise ConfigError(f"p_error must be within 0..1, got {self.p_error}")
        if self.p_error > 0 and self.rng is None:
            raise ConfigError("p_error > 0 needs an explicit numpy Generator (rng)")
        if not self.errnos:
            raise ConfigError("errnos must not be empty")

    def push(self, items: Iterable[int | None]) -> None:
        """Script the next transactions: an errno makes one fail, None lets one through."""
        self.script.extend(items)

    def check(self, what: str) -> None:
        """Raise the OSError due for this transaction, if any."""
        code: int | None = None
        if self.script:
            code = self.script.popleft()
        elif self.p_error > 0 and self.rng is not None and self.rng.random() < self.p_error:
            code = self.errnos[int(self.rng.integers(len(self.errnos)))]
        if code is not None:
            self.injected += 1
            raise OSError(code, f"{os_strerror(code)} ({what}, simulated)")


def os_strerror(code: int) -> str:
    """Text of an errno."""
    import os

    return os.strerror(code)


_Rot = tuple[float, float, float, float, float, float, float, float, float]


def _rot_entries(heading_deg: float, pitch_deg: float, roll_deg: float) -> _Rot:
    """The entries of :func:`_rot_body_to_ned`, row by row, as plain floats."""
    y, p, r = math.radians(heading_deg), math.radians(pitch_deg), math.radians(roll_deg)
    cy, sy, cp, sp, cr, sr = (
        math.cos(y),
        math.sin(y),
        math.cos(p),
        math.sin(p),
        math.cos(r),
        math.sin(r),
    )
    return (
        cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr,
        sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr,
        -sp, cp * sr, cp * cr,
    )  # fmt: skip


def _rot_body_to_ned(heading_deg: float, pitch_deg: float, roll_deg: float) -> np.ndarray:
    """R such that v_ned = R @ v_body (yaw-pitch-roll, aerospace convention)."""
    return np.array(_rot_entries(heading_deg, pitch_deg, roll_deg)).reshape(3, 3)


def _s16be(v: float) -> tuple[int, int]:
    i = max(-32768, min(32767, round(v))) & 0xFFFF
    return i >> 8, i & 0xFF


_SIX_S16BE = struct.Struct(">6h")
"""Registers 10-21: the three field axes, then the three accelerometer axes, each a signed
big-endian 16-bit value (what :func:`_s16be` gives, one at a time)."""


class SimCmps10:
    """CMPS10 register map with the smbus2 method set.

    ``clock`` gives the device's time (s) for the command timing; by default the time of the
    last :meth:`set_state`. ``rng`` drives the magnetometer noise (needed if noise > 0).
    """

    def __init__(
        self,
        *,
        address: int = DEFAULT_ADDRESS,
        version: int = VERSION,
        field_model: MagneticField | None = None,
        errors: CompassErrors | None = None,
        injector: ErrorInjector | None = None,
        rng: np.random.Generator | None = None,
        clock: Callable[[], float] | None = None,
    ) -> None:
        if address not in VALID_ADDRESSES:
            raise ConfigError(f"CMPS10 address must be 0x60..0x67, got {address:#x}")
        if not 0 < version < 255:
            raise ConfigError(f"version must be 1..254, got {version}")
        self.address = address
        self.version = version
        self.field_model = field_model or MagneticField()
        self.errors = errors or CompassErrors()
        if self.errors.noise_ut > 0 and rng is None:
            raise ConfigError("compass noise needs an explicit numpy Generator (rng)")
        self.injector = injector or ErrorInjector()
        self._rng = rng
        self._clock = clock
        self._soft = np.asarray(self.errors.soft_iron, dtype=float)
        self._hard = np.asarray(self.errors.hard_iron_ut, dtype=float)
        # Without iron errors the soft/hard step is the identity: set_state skips it.
        self._no_iron = bool(np.array_equal(self._soft, np.eye(3)) and not self._hard.any())
        self._field_ned = self.field_model.ned_ut()
        self._field_ned_f = cast(tuple[float, float, float], tuple(self._field_ned.tolist()))
        self.cal_offset_ut = np.zeros(3)  # what the device subtracts (its calibration)
        self._regs = bytearray(NUM_REGISTERS)
        self._regs[0] = version
        self._t_s: float | None = None
        self._filt_deg: float | None = None
        self._pitch_deg = 0.0
        self._roll_deg = 0.0
        self._mag_body: tuple[float, float, float] = (0.0, 0.0, 0.0)  # µT, as measured
        self.closed = False
        # command state
        self._last_cmd_t: float | None = None
        self._seq: list[int] = []
        self.calibrating = False
        self._cal_points: list[np.ndarray] = []
        self.commands_ignored = 0
        self.transactions = 0
        self.set_state(0.0, 0.0, 0.0, 0.0)
        self._t_s = None  # the first real set_state starts the filter fresh

    # --- physics ---------------------------------------------------------------------------

    @property
    def now_s(self) -> float:
        """The device's notion of time (s)."""
        if self._clock is not None:
            return self._clock()
        return 0.0 if self._t_s is None else self._t_s

    def measured_field_ut(
        self, true_heading_deg: float, pitch_deg: float, roll_deg: float
    ) -> np.ndarray:
        """Body-frame magnetometer reading (µT) for an attitude, with iron errors, no noise."""
        rot = _rot_body_to_ned(true_heading_deg, pitch_deg, roll_deg)
        return self._soft @ (rot.T @ self._field_ned) + self._hard

    @property
    def mag_body_ut(self) -> tuple[float, float, float]:
        """The body-frame field the device measures now (x, y, z in µT, errors included)."""
        return self._mag_body

    def set_state(
        self, t_s: float, true_heading_deg: float, pitch_deg: float, roll_deg: float
    ) -> None:
        """Update the device at time ``t_s`` (s) to the vehicle's attitude (degrees; heading
        geographic, clockwise from north; pitch nose-up, roll right-side-down positive).

        The registers then show the MAGNETIC bearing after iron errors, noise and filter lag.
        """
        # This runs at the compass rate for a whole simulated mission, so it works on plain
        # floats where that reproduces the numpy formulation (measured_field_ut, then the
        # tilt): ``rot.T @ field`` is summed in the order numpy's product of a transposed
        # matrix uses (identical bits on the reference machine), and the identity steps (no
        # iron errors, a level device) are skipped, which changes at most the sign of an
        # exact zero, invisible in the bearing and the registers. The products numpy hands to
        # the BLAS dot kernel (soft iron, the tilt) stay numpy, so their rounding is kept.
        # tests/test_compass_emu.py compares the two formulations.
        if not (
            math.isfinite(t_s)
            and math.isfinite(true_heading_deg)
            and math.isfinite(pitch_deg)
            and math.isfinite(roll_deg)
        ):
            for name, v in (
                ("t_s", t_s),
                ("true_heading_deg", true_heading_deg),
                ("pitch_deg", pitch_deg),
                ("roll_deg", roll_deg),
            ):
                if not math.isfinite(v):
                    raise ValueError(f"set_state: {name} must be finite, got {v!r}")
        if self._t_s is not None and t_s < self._t_s:
            raise ValueError(f"set_state: time went backwards ({t_s} < {self._t_s})")
        rot = _rot_entries(true_heading_deg, pitch_deg, roll_deg)
        f0, f1, f2 = self._field_ned_f
        # v_body = rot.T @ field_ned
        mx = rot[0] * f0 + rot[3] * f1 + rot[6] * f2
        my = rot[1] * f0 + rot[4] * f1 + rot[7] * f2
        mz = rot[2] * f0 + rot[5] * f1 + rot[8] * f2
        if not self._no_iron:
            mx, my, mz = (self._soft @ np.array((mx, my, mz)) + self._hard).tolist()
        if self.errors.noise_ut > 0 and self._rng is not None:
            nx, ny, nz = self._rng.normal(0.0, self.errors.noise_ut, 3).tolist()
            mx, my, mz = mx + nx, my + ny, mz + nz
        self._mag_body = (mx, my, mz)
        # The device levels with its accelerometer's pitch/roll (taken as exact here).
        c0, c1, c2 = self.cal_offset_ut.tolist()
        if pitch_deg == 0 and roll_deg == 0:
            h0, h1 = mx - c0, my - c1  # the levelling rotation is the identity
        else:
            rot_tilt = _rot_body_to_ned(0.0, pitch_deg, roll_deg)
            h0, h1, _ = (rot_tilt @ np.array((mx - c0, my - c1, mz - c2))).tolist()
        raw_bearing = wrap360(math.degrees(math.atan2(-h1, h0)))
        if self._filt_deg is None or self._t_s is None:
            self._filt_deg = raw_bearing
        else:
            dt = t_s - self._t_s
            tau = self.errors.lag_tau_s
            alpha = 1.0 if tau == 0 else 1.0 - math.exp(-dt / tau)
            turn = wrap_deg(raw_bearing - self._filt_deg)  # the short way round
            self._filt_deg = wrap360(self._filt_deg + alpha * turn)
        self._t_s = t_s
        self._pitch_deg = max(-MAX_TILT_DEG, min(MAX_TILT_DEG, pitch_deg))
        self._roll_deg = max(-MAX_TILT_DEG, min(MAX_TILT_DEG, roll_deg))
        # The gravity direction (NED down, +1 g) in body axes, rot.T @ [0, 0, 1]: the
        # rotation's bottom row, so level reads z = +1000 (the module's convention), not
        # the specific force a real accelerometer senses (the opposite sign).
        self._write_registers(
            (mx, my, mz),
            (rot[6] * ACC_COUNTS_PER_G, rot[7] * ACC_COUNTS_PER_G, rot[8] * ACC_COUNTS_PER_G),
        )

    def _write_registers(
        self, mag_ut: tuple[float, float, float], acc_counts: tuple[float, float, float]
    ) -> None:
        assert self._filt_deg is not None
        tenths = round(self._filt_deg * 10.0) % 3600
        r = self._regs
        r[1] = round(self._filt_deg * 256.0 / 360.0) % 256
        r[2], r[3] = tenths >> 8, tenths & 0xFF
        r[4] = round(self._pitch_deg) & 0xFF
        r[5] = round(self._roll_deg) & 0xFF
        r[10:22] = _SIX_S16BE.pack(
            *[
                max(-32768, min(32767, round(v)))
                for v in (
                    mag_ut[0] * MAG_COUNTS_PER_UT,
                    mag_ut[1] * MAG_COUNTS_PER_UT,
                    mag_ut[2] * MAG_COUNTS_PER_UT,
                    *acc_counts,
                )
            ]
        )

    @property
    def bearing_deg(self) -> float:
        """The filtered magnetic bearing (degrees) the registers show (before rounding)."""
        return 0.0 if self._filt_deg is None else self._filt_deg

    @property
    def registers(self) -> bytes:
        """A copy of the 23 registers."""
        return bytes(self._regs)

    # --- commands --------------------------------------------------------------------------

    def _command(self, value: int) -> None:
        now = self.now_s
        if self._last_cmd_t is not None and now - self._last_cmd_t < MIN_COMMAND_GAP_S:
            # Too fast: the device misses the byte and any sequence in progress.
            self.commands_ignored += 1
            self._seq.clear()
            self._last_cmd_t = now
            return
        self._last_cmd_t = now
        if self.calibrating:
            if value == CALIBRATION_POINT:
                self._cal_points.append(np.array(self._mag_body))
                if len(self._cal_points) == 4:
                    pts = np.array(self._cal_points)
                    offset = pts.mean(axis=0)
                    offset[2] = self.cal_offset_ut[2]  # 4 level points cannot see the z offset
                    self.cal_offset_ut = offset
                    self.calibrating = False
                    self._cal_points.clear()
            return
        if value == CALIBRATION_START and not self._seq:
            self.calibrating = True
            self._cal_points.clear()
            return
        self._seq.append(value)
        seq = tuple(self._seq)
        if seq == FACTORY_RESTORE:
            self.cal_offset_ut = np.zeros(3)
            self._seq.clear()
        elif len(seq) == 4 and seq[:3] == ADDRESS_CHANGE:
            new = value >> 1
            if value & 1 == 0 and new in VALID_ADDRESSES:
                self.address = new
            self._seq.clear()
        elif not (FACTORY_RESTORE[: len(seq)] == seq or ADDRESS_CHANGE[: len(seq)] == seq[:3]):
            self._seq = [value] if value in (FACTORY_RESTORE[0], ADDRESS_CHANGE[0]) else []

    # --- smbus2 method set -----------------------------------------------------------------

    def _begin(self, i2c_addr: int, register: int, what: str) -> None:
        if self.closed:
            raise OSError(errno.EBADF, "bus closed")
        self.transactions += 1
        if i2c_addr != self.address:
            raise OSError(errno.EREMOTEIO, f"no ACK from {i2c_addr:#04x} ({what})")
        if not 0 <= register < 256:
            raise ValueError(f"register must be 0..255, got {register}")
        self.injector.check(what)

    def _read(self, register: int, length: int) -> list[int]:
        # Registers beyond the map read as 0 (auto-increment keeps going on the device).
        return [
            self._regs[r] if r < NUM_REGISTERS else 0 for r in range(register, register + length)
        ]

    def read_byte_data(self, i2c_addr: int, register: int, force: bool | None = None) -> int:
        """One register."""
        self._begin(i2c_addr, register, "read_byte_data")
        return self._read(register, 1)[0]

    def read_byte(self, i2c_addr: int, force: bool | None = None) -> int:
        """Register 0 (a bare read starts at the pointer, reset to 0 here)."""
        return self.read_byte_data(i2c_addr, 0)

    def write_byte_data(
        self, i2c_addr: int, register: int, value: int, force: bool | None = None
    ) -> None:
        """Write one register; only the command register (22) is writable."""
        self._begin(i2c_addr, register, "write_byte_data")
        if not 0 <= value < 256:
            raise ValueError(f"value must be 0..255, got {value}")
        if register == REG_COMMAND:
            self._command(value)

    def read_i2c_block_data(
        self, i2c_addr: int, register: int, length: int, force: bool | None = None
    ) -> list[int]:
        """``length`` (1..32) registers from ``register`` on, pointer auto-incrementing."""
        if not 1 <= length <= MAX_BLOCK:
            raise ValueError(
                f"Desired block length over {MAX_BLOCK} bytes"
                if length > 0
                else f"block length must be >= 1, got {length}"
            )
        self._begin(i2c_addr, register, "read_i2c_block_data")
        return self._read(register, length)

    def write_i2c_block_data(
        self, i2c_addr: int, register: int, data: Sequence[int], force: bool | None = None
    ) -> None:
        """Write consecutive registers (the command register takes each byte in turn)."""
        if len(data) > MAX_BLOCK:
            raise ValueError(f"Data length cannot exceed {MAX_BLOCK} bytes")
        self._begin(i2c_addr, register, "write_i2c_block_data")
        for i, v in enumerate(data):
            if not 0 <= v < 256:
                raise ValueError(f"value must be 0..255, got {v}")
            if register + i == REG_COMMAND:
                self._command(v)

    def read_word_data(self, i2c_addr: int, register: int, force: bool | None = None) -> int:
        """SMBus word: LOW byte first. On the CMPS10's big-endian registers the result is
        byte-swapped (bearing 2-3 reads 256x wrong): shown here, never use it for this device."""
        self._begin(i2c_addr, register, "read_word_data")
        lo, hi = self._read(register, 2)
        return lo | (hi << 8)

    def close(self) -> None:
        """Close the bus (idempotent)."""
        self.closed = True

    def open(self, bus: int | str) -> None:
        """Reopen after :meth:`close` (the smbus2 signature; the bus number is ignored)."""
        self.closed = False

    def __enter__(self) -> SimCmps10:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class SimClock:
    """A manual clock for the device and the driver's ``sleep`` (time advances only by sleep)."""

    def __init__(self, t0_s: float = 0.0) -> None:
        self.t_s = t0_s

    def now(self) -> float:
        """Current time, s."""
        return self.t_s

    def sleep(self, dt_s: float) -> None:
        """Advance by ``dt_s`` seconds (negative values are an error)."""
        if dt_s < 0:
            raise ValueError(f"cannot sleep a negative time: {dt_s}")
        self.t_s += dt_s


# ---------------------------------------------------------------- the scenario's [compass] table


_COMPASS_KEYS = frozenset(
    {
        "declination_deg",
        "robot_declination_deg",
        "horizontal_ut",
        "vertical_ut",
        "hard_iron_ut",
        "soft_iron",
        "noise_ut",
        "lag_tau_s",
        "rate_hz",
        "p_error",
    }
)


def _num(table: dict[str, Any], key: str, default: float, lo: float, hi: float) -> float:
    v = table.get(key, default)
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise ConfigError(f"compass.{key}: expected a number, got {v!r}")
    if not lo <= v <= hi:
        raise ConfigError(f"compass.{key}: must be within {lo}..{hi}, got {v}")
    return float(v)


@dataclass(frozen=True)
class CompassSetup:
    """The ``[compass]`` table, validated (plus any ``[[effects]]`` tilt layers: see
    :meth:`device_heading_deg`)."""

    field_model: MagneticField
    errors: CompassErrors
    rate_hz: float
    p_error: float
    robot_declination_deg: float
    tilt: tuple[Tilt, ...] = ()

    def device_heading_deg(self, heading_deg: float, pitch_deg: float, roll_deg: float) -> float:
        """The heading to hand the emulation's ``set_state`` for a true attitude (deg).

        The emulation levels with exact pitch/roll; a tilt layer (imperfect compensation)
        is its heading error (``effects.Tilt``: the untilted-computed heading at the layer's
        fraction of the tilt and its inclination, at the magnetic heading) added to the
        attitude, so it then passes the device's iron, noise and lag like the real error.
        Without tilt layers the heading is returned unchanged (bit for bit).
        """
        if not self.tilt or (pitch_deg == 0.0 and roll_deg == 0.0):
            return heading_deg
        h = heading_deg
        for layer in self.tilt:
            mag = np.array([h - self.field_model.declination_deg])
            p = max(-PITCH_ROLL_LIMIT_DEG, min(PITCH_ROLL_LIMIT_DEG, pitch_deg))
            r = max(-PITCH_ROLL_LIMIT_DEG, min(PITCH_ROLL_LIMIT_DEG, roll_deg))
            tilted = tilted_heading_deg(
                mag, np.array([layer.fraction * p]), np.array([layer.fraction * r]),
                layer.inclination_deg,
            )  # fmt: skip
            h += float(wrap180(tilted - mag)[0])
        return h % 360.0

    @classmethod
    def from_table(cls, table: dict[str, Any]) -> CompassSetup:
        """Validate the scenario's ``[compass]`` table (errors name the key)."""
        unknown = sorted(set(table) - _COMPASS_KEYS)
        if unknown:
            raise ConfigError(
                f"compass.{unknown[0]}: unknown key (valid: {', '.join(sorted(_COMPASS_KEYS))})"
            )
        decl = _num(table, "declination_deg", 0.0, -180, 180)
        field_model = MagneticField(
            _num(table, "horizontal_ut", 18.5, 0.1, 100),
            _num(table, "vertical_ut", 46.0, -100, 100),
            decl,
        )
        hard = table.get("hard_iron_ut", [0.0, 0.0, 0.0])
        soft = table.get("soft_iron", [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
        try:
            errors = CompassErrors(
                hard_iron_ut=cast(tuple[float, float, float], tuple(float(x) for x in hard)),
                soft_iron=tuple(tuple(float(x) for x in row) for row in soft),
                noise_ut=_num(table, "noise_ut", 0.0, 0, 100),
                lag_tau_s=_num(table, "lag_tau_s", 0.64 / 3.0, 0, 10),
            )
        except (TypeError, ValueError) as exc:
            raise ConfigError(f"compass.hard_iron_ut / soft_iron: {exc}") from exc
        return cls(
            field_model=field_model,
            errors=errors,
            rate_hz=_num(table, "rate_hz", 20.0, 1, 75),
            p_error=_num(table, "p_error", 0.0, 0, 1),
            robot_declination_deg=_num(table, "robot_declination_deg", decl, -180, 180),
        )
