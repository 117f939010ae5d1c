"""Hardware in the loop: the simulated world behind ``sim://`` device URLs, in real time.

``drivers.registry`` resolves ``sim://`` URLs by calling :func:`open_gps`, :func:`open_compass`
and :func:`open_motors`; all three share ONE world per process (created on first use,
configured from ``[sim]`` by :func:`configure`):

- :func:`open_gps` -> a pyserial ``Serial`` opened on the slave side of a pseudo-terminal
  (:class:`sim_backend.ports.PtyUart`); the world writes NEO-5 NMEA sentences into the master
  side at the GPS rate, each sentence followed by its wire time at ``gps_baud``.
- :func:`open_compass` -> a :class:`drivers.cmps10.Cmps10` over the CMPS10 register map of
  :mod:`sim_backend.compass`, whose registers follow the simulated vehicle's attitude.
- :func:`open_motors` -> a motor link (the :class:`drivers.motors.MotorLink` interface) whose
  commands drive the :class:`sim_backend.vehicle.Vehicle`; like the real board it stops the
  vehicle when no command arrives for ``motor_watchdog_ms``.

The receiver model here is deliberately simple (truth + first-order Gauss-Markov error with
``gps_sigma_m``/``gps_tau_s``, a fixed 8-satellite sky): HIL exercises the daemon's real-time
plumbing; the full GNSS error model belongs to fast-time simulation.
Two threads run the world: physics (vehicle + compass registers at ``physics_hz``) and the
receiver (one NMEA burst per epoch). Randomness comes from one seeded numpy Generator.
"""

from __future__ import annotations

import contextlib
import logging
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, fields, replace
from datetime import UTC, datetime, timedelta
from typing import Any
from urllib.parse import urlsplit

import numpy as np

from sim_backend.compass import SimCmps10
from sim_backend.epoch import GnssEpoch, SimSat
from sim_backend.geodesy import enu_to_lla
from sim_backend.nmea_out import NmeaFormatter, sentence, wire_time_s
from sim_backend.ports import PtyUart
from sim_backend.vehicle import Terrain, Vehicle, VehicleParams
from x6wd.config import SimConfig
from x6wd.errors import ConfigError, DeviceUnavailable
from x6wd.records import MotorCommand

log = logging.getLogger(__name__)

GEOID_SEP_M = 47.0
SKY = (
    SimSat(2, 62.0, 45.0, 44.0, True),
    SimSat(5, 41.0, 120.0, 40.0, True),
    SimSat(10, 33.0, 210.0, 38.0, True),
    SimSat(12, 18.0, 300.0, 33.0, True),
    SimSat(15, 55.0, 260.0, 43.0, True),
    SimSat(21, 25.0, 80.0, 36.0, True),
    SimSat(24, 12.0, 160.0, 30.0, True),
    SimSat(29, 8.0, 340.0, 27.0, False),
)
HDOP, VDOP, PDOP = 0.95, 1.35, 1.65


@dataclass(frozen=True)
class HilParams:
    """The world's settings; see :class:`x6wd.config.SimConfig` for units and ranges."""

    seed: int = 1
    origin_lat_deg: float = 51.7520
    origin_lon_deg: float = -1.2577
    origin_alt_m: float = 60.0
    start_heading_deg: float = 0.0
    gps_rate_hz: float = 1.0
    gps_baud: int = 9600
    gps_sigma_m: float = 0.3
    gps_tau_s: float = 30.0
    physics_hz: float = 50.0
    v_max_mps: float = 3.88
    motor_tau_s: float = 0.25
    motor_watchdog_ms: int = 500
    # only from a scenario file
    start_east_m: float = 0.0
    start_north_m: float = 0.0
    turn_rate_dps: float = 90.0
    slope_east_pct: float = 0.0
    slope_north_pct: float = 0.0

    @classmethod
    def from_config(cls, cfg: SimConfig) -> HilParams:
        """From ``[sim]``. With ``sim.scenario`` set, the scenario's origin, seed, vehicle
        (start pose, speed, turn rate, motor lag, slope) and receiver rate and baud replace
        the ``[sim]`` values; the receiver error stays ``gps_sigma_m``/``gps_tau_s``."""
        own = {f.name for f in fields(SimConfig)}
        params = cls(**{f.name: getattr(cfg, f.name) for f in fields(cls) if f.name in own})
        if not cfg.scenario:
            return params
        from sim_backend.world import load_world

        w = load_world(cfg.scenario)
        v = w.vehicle
        return replace(
            params,
            seed=w.seed,
            origin_lat_deg=w.origin.lat_deg,
            origin_lon_deg=w.origin.lon_deg,
            origin_alt_m=w.origin.alt_m,
            start_heading_deg=v.start_heading_deg,
            start_east_m=v.start_east_m,
            start_north_m=v.start_north_m,
            v_max_mps=v.max_speed_mps,
            turn_rate_dps=v.turn_rate_dps,
            motor_tau_s=v.motor_tau_s,
            slope_east_pct=v.slope_east_pct,
            slope_north_pct=v.slope_north_pct,
            gps_rate_hz=w.gnss.rate_hz,
            gps_baud=w.gnss.baud,
        )


class _LockedBus:
    """smbus2 method set over the register map, serialised with the physics thread."""

    def __init__(self, dev: SimCmps10, lock: threading.Lock) -> None:
        self._dev = dev
        self._lock = lock

    def read_byte_data(self, i2c_addr: int, register: int, force: bool | None = None) -> int:
        with self._lock:
            return self._dev.read_byte_data(i2c_addr, register)

    def write_byte_data(
        self, i2c_addr: int, register: int, value: int, force: bool | None = None
    ) -> None:
        with self._lock:
            self._dev.write_byte_data(i2c_addr, register, value)

    def read_i2c_block_data(
        self, i2c_addr: int, register: int, length: int, force: bool | None = None
    ) -> list[int]:
        with self._lock:
            return list(self._dev.read_i2c_block_data(i2c_addr, register, length))

    def close(self) -> None:
        """The world owns the device; closing the driver's handle does nothing."""


class SimMotorLink:
    """Motor link into the simulated vehicle (the MotorLink interface of drivers.motors)."""

    def __init__(self, world: HilWorld) -> None:
        self._world = world
        self._closed = False
        self._last: MotorCommand | None = None

    @property
    def healthy(self) -> bool:
        """True while open and the world runs."""
        return not self._closed and self._world.running

    @property
    def last_command(self) -> MotorCommand | None:
        """The last command given."""
        return self._last

    def send(self, cmd: MotorCommand) -> bool:
        """Apply a controller command (percent, -100..100); ValueError for bad values."""
        for name, v in (("left_pct", cmd.left_pct), ("right_pct", cmd.right_pct)):
            if not (math.isfinite(v) and -100.0 <= v <= 100.0):
                raise ValueError(f"{name} must be within -100..100 percent, got {v!r}")
        if self._closed:
            return False
        self._last = cmd
        self._world.command(cmd.left_pct, cmd.right_pct, cmd)
        return self._world.running

    def drive(self, left_pct: float, right_pct: float, reason: str = "") -> bool:
        """Set left/right drive in percent."""
        return self.send(MotorCommand(time.monotonic(), float(left_pct), float(right_pct), reason))

    def stop(self, reason: str = "") -> bool:
        """Stop the vehicle; never raises."""
        try:
            return self.send(MotorCommand(time.monotonic(), 0.0, 0.0, reason or "stop"))
        except Exception:
            log.exception("simulated stop failed")
            return False

    def close(self) -> None:
        """Stop, then refuse further commands (idempotent)."""
        if not self._closed:
            self.stop("close")
            self._closed = True

    def __enter__(self) -> SimMotorLink:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class HilWorld:
    """Vehicle, compass register map and receiver running in real time in two threads.

    Hooks (for benchmarks): ``on_gga(t_s)`` after each GGA, with the time its (single) write
    call started;
    ``on_motor(cmd, t_s)`` when a motor command reaches the vehicle (monotonic clock).
    """

    def __init__(self, params: HilParams) -> None:
        self.params = params
        self.rng = np.random.default_rng(params.seed)
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self.t0 = time.monotonic()
        self.utc0 = datetime.now(UTC)
        self.vehicle = Vehicle(
            VehicleParams(
                v_max_mps=params.v_max_mps,
                max_turn_rate_dps=params.turn_rate_dps,
                motor_tau_s=params.motor_tau_s,
            ),
            east_m=params.start_east_m,
            north_m=params.start_north_m,
            heading_deg=params.start_heading_deg,
            terrain=Terrain(params.slope_east_pct / 100.0, params.slope_north_pct / 100.0),
        )
        s0 = self.vehicle.state
        self.compass = SimCmps10(clock=self._device_time)
        self.compass.set_state(0.0, s0.heading_deg, s0.pitch_deg, s0.roll_deg)
        self.uart = PtyUart(params.gps_baud, realtime=False)
        self.formatter = NmeaFormatter(rate_hz=params.gps_rate_hz)
        self._err_en = np.zeros(2)
        self._t_cmd = time.monotonic()
        self._watchdog_tripped = True
        self.on_gga: Callable[[float], Any] | None = None
        self.on_motor: Callable[[MotorCommand, float], Any] | None = None
        self.epochs = 0
        self.commands = 0
        self._threads = [
            threading.Thread(target=self._guard(self._physics), name="hil-physics", daemon=True),
            threading.Thread(target=self._guard(self._receiver), name="hil-gps", daemon=True),
        ]
        for t in self._threads:
            t.start()
        log.info("HIL world: GPS on %s", self.uart.port_name)

    def compass_bus(self) -> Any:
        """The register map behind the smbus2 method set, safe against the physics thread."""
        return _LockedBus(self.compass, self._lock)

    def _device_time(self) -> float:
        return time.monotonic() - self.t0

    @property
    def running(self) -> bool:
        """True until :meth:`close`."""
        return not self._stop.is_set()

    def _guard(self, fn: Callable[[], None]) -> Callable[[], None]:
        def run() -> None:
            try:
                fn()
            except Exception:
                log.exception("HIL world thread %s died", fn.__name__)
                self._stop.set()

        return run

    def command(self, left_pct: float, right_pct: float, cmd: MotorCommand) -> None:
        """Drive the vehicle (the motor board's side)."""
        now = time.monotonic()
        with self._lock:
            self.vehicle.command(left_pct, right_pct)
            self._t_cmd = now
            self._watchdog_tripped = False
            self.commands += 1
        hook = self.on_motor
        if hook is not None:
            hook(cmd, now)

    def truth(self) -> tuple[float, float, float, float]:
        """(east_m, north_m, heading_deg, speed_mps) of the vehicle now."""
        with self._lock:
            s = self.vehicle.state
        return s.east_m, s.north_m, s.heading_deg, s.speed_mps

    def _physics(self) -> None:
        p = self.params
        period_s = 1.0 / p.physics_hz
        t_last = time.monotonic()
        while not self._stop.wait(period_s):
            now = time.monotonic()
            with self._lock:
                if (
                    not self._watchdog_tripped
                    and (now - self._t_cmd) * 1000.0 > p.motor_watchdog_ms
                ):
                    # the board's own watchdog: silence from the host stops the motors
                    self.vehicle.command(0.0, 0.0)
                    self._watchdog_tripped = True
                s = self.vehicle.step(now - t_last)
                self.compass.set_state(now - self.t0, s.heading_deg, s.pitch_deg, s.roll_deg)
            t_last = now

    def _epoch(self, t_rel_s: float) -> GnssEpoch:
        p = self.params
        dt = 1.0 / p.gps_rate_hz
        phi = math.exp(-dt / p.gps_tau_s)
        w = self.rng.standard_normal(2)
        self._err_en = phi * self._err_en + p.gps_sigma_m * math.sqrt(1.0 - phi * phi) * w
        with self._lock:
            s = self.vehicle.state
        enu = np.array([s.east_m + self._err_en[0], s.north_m + self._err_en[1], s.up_m])
        lat, lon, alt = enu_to_lla(enu, p.origin_lat_deg, p.origin_lon_deg, p.origin_alt_m)
        speed = abs(s.speed_mps)
        moving = speed > 0.1
        course = (s.heading_deg if s.speed_mps >= 0 else s.heading_deg + 180.0) % 360.0
        return GnssEpoch(
            t_s=t_rel_s,
            utc=self.utc0 + timedelta(seconds=t_rel_s),
            valid=True,
            lat_deg=float(lat),
            lon_deg=float(lon),
            alt_m=float(alt),
            geoid_sep_m=GEOID_SEP_M,
            speed_mps=speed if moving else 0.0,
            course_deg=course if moving else None,
            quality=1,
            mode=3,
            hdop=HDOP,
            pdop=PDOP,
            vdop=VDOP,
            satellites=SKY,
        )

    def _receiver(self) -> None:
        p = self.params
        period_s = 1.0 / p.gps_rate_hz
        with contextlib.suppress(Exception):
            self.uart.write(self.formatter.banner())
        k = 1
        while not self._stop.wait(max(0.0, self.t0 + k * period_s - time.monotonic())):
            t_rel = time.monotonic() - self.t0
            for body in self.formatter.epoch_bodies(self._epoch(t_rel)):
                data = sentence(body)
                # stamped just before the write: the reader may finish with the fix before
                # this thread runs again, so a later stamp could come after the motor command
                t_write = time.monotonic()
                self.uart.write(data)
                if body[2:5] == "GGA":
                    hook = self.on_gga
                    if hook is not None:
                        hook(t_write)
                # the next sentence leaves the wire after this one
                if self._stop.wait(wire_time_s(len(data), p.gps_baud)):
                    return
            self.epochs += 1
            k = max(k + 1, math.floor((time.monotonic() - self.t0) / period_s) + 1)

    def close(self) -> None:
        """Stop the threads and unplug the pty (idempotent)."""
        self._stop.set()
        for t in self._threads:
            if t is not threading.current_thread():
                t.join(2.0)
        self.uart.close()


_PARAMS = HilParams()
_WORLD: HilWorld | None = None
_GUARD = threading.Lock()


def configure(cfg: SimConfig | HilParams) -> None:
    """Set the world's parameters (before the first device opens; later calls must match).

    Raises ConfigError for a scenario file that does not load."""
    global _PARAMS
    params = cfg if isinstance(cfg, HilParams) else HilParams.from_config(cfg)
    with _GUARD:
        if _WORLD is not None and _WORLD.running and params != _WORLD.params:
            raise ConfigError("sim: the HIL world is already running with other settings")
        _PARAMS = params


def world() -> HilWorld:
    """The process's world, started on first use."""
    global _WORLD
    with _GUARD:
        if _WORLD is None or not _WORLD.running:
            _WORLD = HilWorld(_PARAMS)
        return _WORLD


def shutdown() -> None:
    """Stop the world (tests, benchmarks); the next open starts a fresh one."""
    global _WORLD
    with _GUARD:
        w, _WORLD = _WORLD, None
    if w is not None:
        w.close()


def _check_url(url: str, kind: str) -> None:
    parts = urlsplit(url)
    if parts.scheme != "sim":
        raise ConfigError(f"{kind} URL {url!r}: expected sim://")
    if parts.query or parts.fragment or parts.path not in ("", "/"):
        raise ConfigError(
            f"{kind} URL {url!r}: sim:// takes no path or options; the world is set in [sim]"
        )


def open_gps(url: str) -> Any:
    """A pyserial port on the simulated receiver's pseudo-terminal."""
    _check_url(url, "gps")
    import serial

    w = world()
    try:
        return serial.Serial(w.uart.port_name, baudrate=w.params.gps_baud, timeout=0.1)
    except (serial.SerialException, OSError) as exc:
        raise DeviceUnavailable(f"cannot open simulated GPS {w.uart.port_name}: {exc}") from exc


def open_compass(url: str) -> Any:
    """A CMPS10 driver on the simulated register map."""
    _check_url(url, "compass")
    from drivers.cmps10 import Cmps10

    w = world()
    return Cmps10(w.compass_bus())


def open_motors(url: str) -> SimMotorLink:
    """A motor link driving the simulated vehicle."""
    _check_url(url, "motors")
    return SimMotorLink(world())
