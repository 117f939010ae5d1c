"""Hardware in the loop: the simulated world behind ``sim://`` device URLs, in real time.

A :class:`HilWorld` is built explicitly from its parameters (:class:`HilParams`, from the
configuration's ``[sim]`` table: :meth:`HilParams.from_config`); there is no world per
process. The ``sim://`` handler (:mod:`sim_backend.protocol_sim`) opens the devices on a
world, and :class:`drivers.registry.Devices` builds one world per configuration on the first
``sim://`` open and shares it between that configuration's GPS, compass and motors. The
world is a scenario file (:func:`sim_backend.world.load_world`; ``[sim] scenario``, default
the packaged ``config/scenarios/default.toml``) with a few ``[sim]`` overrides, and it is the
same physics as fast-time simulation (``x6wd sim``), only in real time:

- the GPS: a pseudo-terminal (:class:`sim_backend.ports.PtyUart`, :attr:`HilWorld.uart`).
  Once per receiver epoch the scenario's receiver
  (:func:`sim_backend.receiver.build_receiver`, the one ``x6wd sim`` and the gap tool build:
  almanac sky, atmosphere, walls, LCE grid, fidelity, every ``[[effects]]`` GPS layer, the
  NEO-5 formatter) turns the vehicle's true antenna position into a solution (a latency
  layer reads the physics thread's true track) and prints it as a NEO-5 does (``$GPTXT``
  banner at start, the real no-fix forms). The sentences go through the receiver's UART
  (:class:`sim_backend.receiver.UartTx`: a bounded transmit buffer drained at the scenario's
  baud rate, dropping whole sentences when full, the same arithmetic ``x6wd sim`` runs) and
  each is written to the pty in 10 ms pieces at the times the model puts its bytes on the
  line, so the bytes arrive as on the real line. What the host writes to the pty reaches
  the receiver's UBX input (:class:`sim_backend.ubx_config.UbxConfigPort`): CFG-RATE and
  CFG-MSG (``[gps] configure_receiver``) are answered with ACK-ACK through the same UART and
  change the rate (the epochs move to the new rate's whole periods of host UTC) and the
  sentences printed; other CFG messages are NAKed.
- the compass: the CMPS10 register map of :mod:`sim_backend.compass`
  (:meth:`HilWorld.compass_bus`) with the scenario's ``[compass]`` field and errors and its
  compass ``[[effects]]`` layers (:func:`sim_backend.mission.compass_setup`); its registers
  follow the simulated vehicle's attitude.
- the motors: a pseudo-terminal per link (:meth:`HilWorld.plug_motor_board`) whose far end
  is a :class:`drivers.motors.MotorBoard` (:func:`drivers.motors.serve_board_fd`): the
  docs/motors.md line protocol crosses the pty byte for byte, the board's left/right drive
  moves the :class:`sim_backend.vehicle.Vehicle`, and the board's watchdog stops it. The
  board's wheel-encoder counters follow the vehicle's true motion through
  :class:`sim_backend.odometry.EncoderSim` (the scenario's ``[encoders]``, as ``x6wd sim``
  builds it, and its own random stream of the scenario seed), stepped with the physics.

Time: the receiver's clock, what its NMEA says, is the host's UTC, as a real receiver's is
true UTC; its epochs fall on the host clock's whole ``1 / rate_hz`` s (:attr:`HilWorld.utc0`
plus ``k / rate_hz``) and each leaves at that instant. So the daemon's fixes carry today's
date, and a gpsd client that compares a fix's time with its own clock (cgps's "time
offset") sees the real latency, not the years back to the almanac's day. The world's own
clock is the device time (seconds since the world started, as the vehicle and the scenario's
timed effects count them): epoch ``k`` is at :meth:`HilWorld.epoch_t_s`, and the sky
(almanac, atmosphere) is the scenario's at ``start_utc`` plus that (the packaged almanac is
for 2020-01-01; the wall clock's date would be years outside it).

``[sim]`` overrides (x6wd.core.config.SimConfig): ``seed``, ``origin_*``, ``start_heading_deg``,
``start_east_m``/``start_north_m``, ``gps_rate_hz``, ``gps_baud``, ``v_max_mps``,
``motor_tau_s`` replace the scenario's value when present; ``physics_hz`` and
``motor_watchdog_ms`` are HIL's own. Receiver errors live in the scenario (``[gnss]``,
``[atmosphere]``, walls, ``[[effects]]``): HIL has no second, simpler GPS model.

Threads: physics (vehicle + compass registers at ``physics_hz``), the receiver (one model
step and one NMEA burst per epoch) and one board server per motor link. Randomness comes
from the scenario's seed, split as ``x6wd sim`` splits it (GNSS, compass noise, I2C faults,
effects).
"""

from __future__ import annotations

import contextlib
import importlib.util
import logging
import math
import os
import threading
import time
import tty
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field, fields, replace
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any

from drivers.motors import MotorBoard, serve_board_fd
from sim_backend.compass import ErrorInjector, SimCmps10
from sim_backend.epoch import GnssEpoch
from sim_backend.mission import compass_setup, vehicle_from_world, vehicle_velocity
from sim_backend.odometry import EncoderSim, encoder_rng
from sim_backend.ports import PACE_CHUNK_S, PtyUart
from sim_backend.receiver import SimRandom, build_receiver
from sim_backend.ubx_config import UbxConfigPort
from sim_backend.world import World, load_world
from x6wd.core.config import PACKAGED_CONFIG_DIR, SimConfig, path_is_file, scenario_candidates
from x6wd.core.errors import ConfigError, DeviceIOError, DeviceUnavailable
from x6wd.core.records import MotorCommand

log = logging.getLogger(__name__)

# Hardware in the loop runs the simulator's models, which need the `sim` extra's scipy (its
# filters are imported on first use, deep in a run): refuse at start-up, not in a device
# thread minutes later. `x6wd run` turns this into its "pip install 'x6wd[sim]'" message.
if importlib.util.find_spec("scipy") is None:
    raise ModuleNotFoundError("No module named 'scipy'", name="scipy")

CONFIG_DIR = PACKAGED_CONFIG_DIR  # where hil.toml and the scenarios ship
DEFAULT_SCENARIO = CONFIG_DIR / "scenarios" / "default.toml"
CLOSE_JOIN_S = 5.0  # how long close() waits for each thread before it gives up on it
WIRE_LOG_LEN = 4096  # motor-board traffic kept for inspection (entries)
HOST_POLL_S = 0.02  # the receiver thread reads what the host wrote at least this often

# [sim] keys that override the scenario when present (None in SimConfig = absent)
_OVERRIDES = (
    "seed",
    "origin_lat_deg",
    "origin_lon_deg",
    "origin_alt_m",
    "start_heading_deg",
    "start_east_m",
    "start_north_m",
    "gps_rate_hz",
    "gps_baud",
    "v_max_mps",
    "motor_tau_s",
)


def resolve_scenario(path: str) -> Path:
    """The scenario file ``[sim] scenario`` names: "" -> the packaged default; else where
    :func:`x6wd.core.config.scenario_candidates` looks (a configuration file's loader has
    already resolved one beside it). ConfigError if it does not exist."""
    if not path:
        return DEFAULT_SCENARIO
    tried = scenario_candidates(path, None)
    for cand in tried:
        if path_is_file(cand):
            return cand.resolve()
    raise ConfigError(
        f"sim.scenario: no such file {path!r} (tried {', '.join(str(c) for c in tried)})"
    )


@dataclass(frozen=True)
class HilParams:
    """The world's settings: a scenario file plus overrides (None = the scenario's value).

    Units and ranges as in :class:`x6wd.core.config.SimConfig`."""

    scenario: str = ""
    seed: int | None = None
    origin_lat_deg: float | None = None
    origin_lon_deg: float | None = None
    origin_alt_m: float | None = None
    start_heading_deg: float | None = None
    start_east_m: float | None = None
    start_north_m: float | None = None
    gps_rate_hz: float | None = None
    gps_baud: int | None = None
    v_max_mps: float | None = None
    motor_tau_s: float | None = None
    physics_hz: float = 50.0
    motor_watchdog_ms: int = 500
    _world: World | None = field(default=None, init=False, repr=False, compare=False)

    @classmethod
    def from_config(cls, cfg: SimConfig) -> HilParams:
        """From ``[sim]`` (see the module docstring for which keys override the scenario).

        Raises ConfigError when the scenario does not load or an override is invalid."""
        own = {f.name for f in fields(cls)}
        over = {
            name: value
            for name in _OVERRIDES
            if name in own and (value := getattr(cfg, name)) is not None
        }
        params = cls(
            scenario=str(resolve_scenario(cfg.scenario)),
            physics_hz=cfg.physics_hz,
            motor_watchdog_ms=cfg.motor_watchdog_ms,
            **over,
        )
        params.load_world()  # fail at configuration time, naming the key
        return params

    def load_world(self) -> World:
        """The scenario with the overrides applied (ConfigError naming the key if invalid),
        loaded once: :meth:`from_config` checks it and :class:`HilWorld` runs the same world,
        so a ``[mission] file`` is read once (a FIFO has nothing left for a second read)."""
        world = self._world
        if world is None:
            world = self._load_world()
            object.__setattr__(self, "_world", world)  # frozen: set once, here
        return world

    def _load_world(self) -> World:
        path = resolve_scenario(self.scenario)
        try:
            w = load_world(path)
        except ConfigError as exc:  # the scenario's own message, under the key that names it
            raise ConfigError(f"sim.scenario: {exc}") from exc

        def pick(value: Any, scenario_value: Any) -> Any:
            return scenario_value if value is None else value

        try:
            origin = replace(
                w.origin,
                lat_deg=float(pick(self.origin_lat_deg, w.origin.lat_deg)),
                lon_deg=float(pick(self.origin_lon_deg, w.origin.lon_deg)),
                alt_m=float(pick(self.origin_alt_m, w.origin.alt_m)),
            )
            gnss = replace(
                w.gnss,
                rate_hz=float(pick(self.gps_rate_hz, w.gnss.rate_hz)),
                baud=int(pick(self.gps_baud, w.gnss.baud)),
            )
            vehicle = replace(
                w.vehicle,
                start_heading_deg=float(pick(self.start_heading_deg, w.vehicle.start_heading_deg)),
                start_east_m=float(pick(self.start_east_m, w.vehicle.start_east_m)),
                start_north_m=float(pick(self.start_north_m, w.vehicle.start_north_m)),
                max_speed_mps=float(pick(self.v_max_mps, w.vehicle.max_speed_mps)),
                motor_tau_s=float(pick(self.motor_tau_s, w.vehicle.motor_tau_s)),
            )
        except (TypeError, ValueError) as exc:
            raise ConfigError(f"sim: bad override for scenario {path}: {exc}") from exc
        if not 1.0 <= gnss.rate_hz <= 4.0:
            raise ConfigError(f"sim.gps_rate_hz: must be within 1..4 Hz, got {gnss.rate_hz}")
        if not 0.0 < self.physics_hz <= 1000.0:
            raise ConfigError(f"sim.physics_hz: must be within (0, 1000], got {self.physics_hz}")
        return replace(
            w,
            seed=int(pick(self.seed, w.seed)),
            origin=origin,
            gnss=gnss,
            vehicle=vehicle,
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


def _drives(data: bytes) -> bool:
    """True if ``data`` holds an ``M`` or ``S`` command line (docs/motors.md)."""
    return any(line.lstrip()[:1] in (b"M", b"m", b"S", b"s") for line in data.split(b"\n"))


class _Board(MotorBoard):
    """The motor board whose drive is the vehicle's: ``on_change(board, t_s, drive)`` runs
    (with the world's lock held) after every executed command or watchdog stop; ``wire``
    keeps the traffic as ("rx" | "tx", t_s, bytes)."""

    def __init__(
        self, watchdog_ms: int, on_change: Callable[[MotorBoard, float, bool], None]
    ) -> None:
        super().__init__(watchdog_ms=watchdog_ms)
        self._on_change = on_change
        self._feeding = False
        self.wire: deque[tuple[str, float, bytes]] = deque(maxlen=WIRE_LOG_LEN)

    def feed(self, data: bytes, t_s: float) -> bytes:
        self._feeding = True
        try:
            out = super().feed(data, t_s)
        finally:
            self._feeding = False
        self.wire.append(("rx", t_s, data))
        if out:
            self.wire.append(("tx", t_s, out))
        self._on_change(self, t_s, _drives(data))
        return out

    def tick(self, t_s: float) -> bytes:
        out = super().tick(t_s)
        if out and not self._feeding:  # a watchdog stop between commands
            self.wire.append(("tx", t_s, out))
            self._on_change(self, t_s, False)
        return out


class HilWorld:
    """Scenario world running in real time: vehicle, compass register map, GNSS receiver
    and motor board.

    ``scenario`` is the :class:`~sim_backend.world.World` in use (overrides applied),
    ``receiver`` its :class:`~sim_backend.receiver.SimReceiver`, ``board`` the motor board.
    Hooks (for benchmarks): ``on_gga(t_s)`` after each GGA, with the time its (single) write
    call started; ``on_motor(cmd, t_s)`` when an ``M``/``S`` line reaches the motor board
    (monotonic clock; called with the world's lock held: keep it short).
    """

    def __init__(self, params: HilParams) -> None:
        self.params = params
        sc = params.load_world()
        self.scenario = sc
        # The compass [[effects]] layers become the emulation's own physics, as in x6wd sim
        # (heading noise is scaled for the physics rate, at which the registers update).
        cset, compass_skipped = compass_setup(sc, params.physics_hz)
        rand = SimRandom.from_seed(sc.seed)
        self.receiver = build_receiver(sc, rand)
        self.vehicle = vehicle_from_world(sc)
        self._lock = threading.Lock()
        self._stop = threading.Event()
        wall, self.t0 = time.time(), time.monotonic()
        # The receiver's clock is the host's UTC and its epochs fall on the host clock's
        # whole 1/rate_hz s, as a NEO-5's fall on GPS time's: epoch k is due at device time
        # epoch_phase_s + k / rate_hz (also its scenario time), at UTC utc0 + k / rate_hz.
        n0 = math.ceil(wall * sc.gnss.rate_hz)
        self.utc0 = datetime.fromtimestamp(n0 / sc.gnss.rate_hz, UTC)
        self.epoch_phase_s = n0 / sc.gnss.rate_hz - wall
        # The epoch schedule from epoch _k_base (device time _phase_base, UTC _utc_base) at
        # _rate_hz: moved by a CFG-RATE the host sends (_set_rate); the same line of device
        # time against UTC as utc0 and epoch_phase_s, so scenario_t_s holds throughout.
        self._k_base, self._phase_base, self._utc_base = 0, self.epoch_phase_s, self.utc0
        self._rate_hz = float(sc.gnss.rate_hz)
        self.ubx = UbxConfigPort(self._rate_hz)  # the receiver's UBX input (host writes)
        s0 = self.vehicle.state
        self.compass = SimCmps10(
            field_model=cset.field_model,
            errors=cset.errors,
            injector=ErrorInjector(p_error=cset.p_error, rng=rand.i2c if cset.p_error else None),
            rng=rand.compass if cset.errors.noise_ut > 0 else None,
            clock=self._device_time,
        )
        self._cset = cset
        h0 = cset.device_heading_deg(s0.heading_deg, s0.pitch_deg, s0.roll_deg)
        self.compass.set_state(0.0, h0, s0.pitch_deg, s0.roll_deg)
        self.board = _Board(params.motor_watchdog_ms, self._board_changed)
        self.encoders = EncoderSim(sc.encoders, rng=encoder_rng(sc.seed), start=s0)
        self.on_gga: Callable[[float], Any] | None = None
        self.on_motor: Callable[[MotorCommand, float], Any] | None = None
        self.epochs = 0
        # The sentences the receiver's UART accepted, with the device time (s) their last
        # byte is due on the line, oldest first (recent ones only).
        self.gps_wire: deque[tuple[float, bytes]] = deque(maxlen=4096)
        self.commands = 0  # M/S lines the board executed
        # Layers the emulation cannot reproduce ("name: reason"); GPS layers all apply.
        self.effects_skipped: tuple[str, ...] = compass_skipped
        if compass_skipped:
            log.warning("HIL: [[effects]] layers not applied: %s", "; ".join(compass_skipped))
        # A delayed receiver needs the true track between epochs: fed by the physics thread.
        self.receiver.observe(0.0, self._antenna_enu(s0), vehicle_velocity(s0))
        self._fds: list[int] = []
        self.uart = PtyUart(sc.gnss.baud, realtime=False)  # paced by the receiver thread
        self._threads = [
            threading.Thread(target=self._guard(self._physics), name="hil-physics", daemon=True),
            threading.Thread(target=self._guard(self._receiver), name="hil-gps", daemon=True),
        ]
        for t in self._threads:
            t.start()
        decl = cset.field_model.declination_deg
        log.info(
            "HIL world: scenario %r (%s, seed %d), GPS %g Hz at %d baud on %s; "
            "magnetic declination %.2f deg (the robot's [compass] declination_deg must say"
            " so: its WMM gives the real field's at this place and date, not the world's)",
            sc.name, sc.gnss.fidelity, sc.seed, sc.gnss.rate_hz, sc.gnss.baud,
            self.uart.port_name, decl,
        )  # fmt: skip

    # --- devices ----------------------------------------------------------------------------

    def compass_bus(self) -> Any:
        """The register map behind the smbus2 method set, safe against the physics thread."""
        return _LockedBus(self.compass, self._lock)

    def plug_motor_board(self) -> str:
        """A new pseudo-terminal served by the world's motor board; returns the path to open
        (raw, any baud). The board keeps its state across plugs, like real hardware."""
        if not self.running:
            raise DeviceUnavailable("the HIL world is closed")
        master, slave = os.openpty()
        try:
            tty.setraw(master)
            tty.setraw(slave)  # no echo, no CR/LF translation
            name = os.ttyname(slave)
        except BaseException:
            os.close(master)
            os.close(slave)
            raise
        # The world keeps the slave open too, so the board serves (and its watchdog ticks)
        # until the world closes, whoever opens or closes the port.
        self._fds += [master, slave]

        def motor_board() -> None:
            serve_board_fd(master, self.board, self._stop, lock=self._lock)

        t = threading.Thread(target=self._guard(motor_board), name="hil-motors", daemon=True)
        self._threads.append(t)
        t.start()
        return name

    @property
    def motor_wire(self) -> list[tuple[str, float, bytes]]:
        """The motor board's recent traffic: ("rx" | "tx", t_s, bytes), oldest first."""
        with self._lock:
            return list(self.board.wire)

    def _board_changed(self, board: MotorBoard, t_s: float, drive: bool) -> None:
        # runs in a board server thread with self._lock held
        left, right = float(board.left_pct), float(board.right_pct)
        if (left, right) != self.vehicle.command_pct:
            self.vehicle.command(left, right)
        if drive:
            self.commands += 1
            hook = self.on_motor
            if hook is not None:
                hook(MotorCommand(t_s, left, right, "board"), t_s)

    # --- state ------------------------------------------------------------------------------

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

    def truth(self) -> tuple[float, float, float, float]:
        """(east_m, north_m, heading_deg, speed_mps) of the vehicle now."""
        with self._lock:
            s = self.vehicle.state
        return s.east_m, s.north_m, s.heading_deg, s.speed_mps

    # --- threads ----------------------------------------------------------------------------

    def _physics(self) -> None:
        period_s = 1.0 / self.params.physics_hz
        t_last = time.monotonic()
        while not self._stop.wait(period_s):
            now = time.monotonic()
            with self._lock:
                s = self.vehicle.step(now - t_last)
                self.board.add_counts(*self.encoders.step(now - t_last, s))
                h = self._cset.device_heading_deg(s.heading_deg, s.pitch_deg, s.roll_deg)
                self.compass.set_state(now - self.t0, h, s.pitch_deg, s.roll_deg)
                if self.receiver.tracks:
                    self.receiver.observe(now - self.t0, self._antenna_enu(s), vehicle_velocity(s))
            t_last = now

    def epoch_t_s(self, k: int) -> float:
        """Device and scenario time (s) of receiver epoch ``k``."""
        return self._phase_base + (k - self._k_base) / self._rate_hz

    def scenario_t_s(self, utc: datetime) -> float:
        """The scenario time (s) of the epoch the receiver stamped ``utc``."""
        return self.epoch_phase_s + (utc - self.utc0).total_seconds()

    def _epoch(self, k: int) -> GnssEpoch:
        """Receiver epoch ``k`` (at :meth:`epoch_t_s`) from the vehicle's truth now."""
        t_s = self.epoch_t_s(k)
        with self._lock:
            s = self.vehicle.state
            pos, vel = self._antenna_enu(s), vehicle_velocity(s)
        # A delayed receiver reads the physics thread's track, whose clock is the device's.
        ep = self.receiver.epoch(t_s, pos, vel, track_t_s=self._device_time())
        return replace(ep, utc=self.epoch_utc(k))

    def epoch_utc(self, k: int) -> datetime:
        """The receiver's UTC of epoch ``k`` (the host's clock when it is due)."""
        return self._utc_base + timedelta(seconds=(k - self._k_base) / self._rate_hz)

    def _set_rate(self, rate_hz: float, k: int) -> None:
        """The receiver navigates at ``rate_hz`` from epoch ``k`` (the next one to compute):
        on the new rate's first whole period of host UTC from now, as a NEO-5's epochs fall
        on whole periods of GPS time."""
        now = self._device_time()
        utc_now = self.utc0 + timedelta(seconds=now - self.epoch_phase_s)
        n = math.ceil(utc_now.timestamp() * rate_hz)
        utc_base = datetime.fromtimestamp(n / rate_hz, UTC)
        self._phase_base = self.epoch_phase_s + (utc_base - self.utc0).total_seconds()
        self._utc_base, self._k_base, self._rate_hz = utc_base, k, rate_hz
        self.receiver.formatter.rate_hz = rate_hz
        log.info("HIL: the receiver took CFG-RATE: %g Hz", rate_hz)

    def _host_bytes(self) -> bytes:
        """What the host wrote to the GPS pty since the last call (b"" when unplugged)."""
        try:
            return self.uart.read(4096)
        except DeviceIOError:
            return b""

    def _antenna_enu(self, s: Any) -> tuple[float, float, float]:
        return s.east_m, s.north_m, s.up_m + self.scenario.vehicle.antenna_height_m

    def _receiver(self) -> None:
        """Epochs on their schedule; their sentences through the receiver's UART model and
        onto the pty in 10 ms pieces, each written when the model says its bytes are on
        the line (device time). An epoch due is computed before any byte still waiting, and
        a thread that fell behind writes what is overdue at once, so the stream keeps the
        model's schedule on a loaded host."""
        rx = self.receiver
        period_s = 1.0 / rx.rate_hz
        piece = max(1, int(rx.baud / 10 * PACE_CHUNK_S))
        pending: deque[tuple[float, bytes]] = deque()  # (first byte leaves, sentence)
        offset = 0  # bytes of pending[0] already written

        def queue(burst: bytes, t_s: float) -> None:
            for t_end, line in rx.arrivals(burst, t_s):
                pending.append((t_end - rx.wire_time_s(len(line)), line))
                self.gps_wire.append((t_end, line))

        ubx = self.ubx
        queue(rx.banner(), 0.0)
        warned = False
        k = 1
        while self.running:
            data = self._host_bytes()
            if data:
                now = time.monotonic() - self.t0
                for answer in ubx.feed(data):
                    # through the receiver's UART, behind the NMEA already queued there
                    for t_end, frame in rx.uart.send([answer.reply], now):
                        pending.append((t_end - rx.wire_time_s(len(frame)), frame))
                    if answer.rate_hz is not None and answer.rate_hz != self._rate_hz:
                        self._set_rate(answer.rate_hz, k)
                        period_s = 1.0 / answer.rate_hz
            t_epoch = self.epoch_t_s(k)
            now = time.monotonic() - self.t0
            if now >= t_epoch:
                dropped = rx.uart.dropped
                lines = rx.sentences(self._epoch(k))
                if ubx.msg_rates:  # CFG-MSG: sentences printed every n epochs, or never
                    lines = [ln for ln in lines if ubx.keeps(ln[3:6].decode("ascii"), k)]
                queue(b"".join(lines), t_epoch)
                self.epochs += 1
                if not warned and rx.uart.dropped > dropped:
                    warned = True
                    log.warning(
                        "HIL: the NMEA output exceeds what %d baud carries at %g Hz; the "
                        "receiver drops whole sentences (raise the baud rate)",
                        rx.baud,
                        rx.rate_hz,
                    )
                # A thread held up (a loaded host) skips epochs rather than running late.
                late_s = time.monotonic() - self.t0 - self._phase_base
                k = max(k + 1, self._k_base + math.floor(late_s / period_s) + 1)
                continue
            due = t_epoch
            if pending:
                t_start, data = pending[0]
                due = min(due, t_start + rx.wire_time_s(offset))
                if now >= due:
                    if offset == 0 and data[3:6] == b"GGA" and self.on_gga is not None:
                        self.on_gga(time.monotonic())  # as the GGA starts to leave
                    with contextlib.suppress(DeviceIOError):  # unplugged: the bytes are lost
                        self.uart.write(data[offset : offset + piece])
                    offset += piece
                    if offset >= len(data):
                        pending.popleft()
                        offset = 0
                    continue
            # (at most 20 ms: the host's UBX is answered within that)
            if self._stop.wait(min(HOST_POLL_S, max(0.0, due - now))):
                return

    def close(self) -> None:
        """Stop the threads and unplug the ptys (idempotent)."""
        self._stop.set()
        alive = []
        for t in list(self._threads):
            if t is not threading.current_thread():
                t.join(CLOSE_JOIN_S)
                if t.is_alive():
                    alive.append(t.name)
        if alive:
            # A live thread would read or write whatever next reuses these fd numbers (a
            # socket, a file): leave them open to the process's exit rather than corrupt that.
            log.error(
                "HIL world: %s still running after %.1f s; its ptys are left open",
                alive,
                CLOSE_JOIN_S,
            )
            return
        self.uart.close()
        fds, self._fds = self._fds, []
        for fd in fds:
            with contextlib.suppress(OSError):
                os.close(fd)
