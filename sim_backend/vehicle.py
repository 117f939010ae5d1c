"""Six-wheel skid-steer kinematics of the X6WD in a local east/north/up frame (metres).

Commands are left/right drive in percent (-100..100). Each side's effective drive follows its
command with a first-order motor response (``motor_tau_s``). The ground speed is
``v = (l + r) / 2 / 100 * v_max`` and the counter-clockwise yaw rate
``ω = (r - l) / 2 / 100 * max_turn_rate`` (skid steer: a pivot turn at full opposite drive gives
the maximum turn rate). Headings and ``yaw_rate_dps`` are clockwise from north (compass sense),
so ``yaw_rate_dps = (l - r) / 200 * max_turn_rate``: left ahead of right turns right. ``v_max`` is
capped at the robot's 14 km/h.

Integration is exact for constant wheel drive: over a step the vehicle follows a circular
arc (a straight line when ω = 0). While the motors are still responding, the step is split
into sub-steps no longer than ``max_substep_s``, each integrated as an arc with the exact
mean speed and yaw rate of the exponential response over that sub-step. Everything is
deterministic (no randomness here).

Terrain is a plane with gradients ``dz/dE`` and ``dz/dN``; the vehicle follows it, its pitch
and roll follow from its heading and the gradient, and the horizontal speed is the ground
speed times cos(pitch).

Fault injection (to exercise the robot's "stuck" failsafe): from ``stuck_from_s`` until
``stuck_until_s`` (vehicle time, s; None = never / for good) the vehicle is stuck.
``stuck_mode = "blocked"``: neither the body nor the wheels move (the motors stall, the drive
is 0 and the encoders count nothing). ``"slipping"``: the wheels turn as commanded (motor
response as usual) but the body stays where it is, as in mud; the wheel travel the ground did
not take is kept in the state (``slip_m``, ``slip_cw_deg``) so the encoders still count it
(:class:`sim_backend.odometry.EncoderSim`). A step that crosses either time is split there.
Without a fault the state and every number are those of the plain model.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from x6wd.core.errors import ConfigError
from x6wd.core.geodesy import wrap360

MAX_SPEED_MPS = 14.0 / 3.6  # the X6WD's top speed on even ground
STUCK_MODES = ("blocked", "slipping")


@dataclass(frozen=True)
class VehicleParams:
    """Limits and response: ``v_max_mps`` (≤ 14 km/h), ``max_turn_rate_dps`` (pivot turn at
    full opposite drive), ``motor_tau_s`` (first-order motor response; 0 = instant); the
    injected fault ``stuck_from_s`` / ``stuck_until_s`` / ``stuck_mode`` (module docstring)."""

    v_max_mps: float = MAX_SPEED_MPS
    max_turn_rate_dps: float = 90.0
    motor_tau_s: float = 0.25
    max_substep_s: float = 0.05
    stuck_from_s: float | None = None
    stuck_until_s: float | None = None
    stuck_mode: str = "blocked"

    def __post_init__(self) -> None:
        if not (0 < self.v_max_mps <= MAX_SPEED_MPS + 1e-9):
            raise ConfigError(
                f"vehicle.v_max_mps must be within (0, {MAX_SPEED_MPS:.3f}] (14 km/h), "
                f"got {self.v_max_mps}"
            )
        if not (0 < self.max_turn_rate_dps <= 720):
            raise ConfigError(
                f"vehicle.max_turn_rate_dps must be within (0, 720], got {self.max_turn_rate_dps}"
            )
        if not (0 <= self.motor_tau_s <= 10):
            raise ConfigError(f"vehicle.motor_tau_s must be within 0..10, got {self.motor_tau_s}")
        if not (0 < self.max_substep_s <= 1):
            raise ConfigError(
                f"vehicle.max_substep_s must be within (0, 1], got {self.max_substep_s}"
            )
        check_stuck(self.stuck_from_s, self.stuck_until_s, self.stuck_mode)

    def stuck_at(self, t_s: float) -> bool:
        """The injected fault holds the vehicle at time ``t_s`` (s)."""
        a, b = self.stuck_from_s, self.stuck_until_s
        return a is not None and t_s >= a and (b is None or t_s < b)


def check_stuck(from_s: float | None, until_s: float | None, mode: str) -> None:
    """Validate the stuck fault's settings (:class:`ConfigError` naming the vehicle key)."""
    for name, v in (("stuck_from_s", from_s), ("stuck_until_s", until_s)):
        if v is not None and not (math.isfinite(v) and v >= 0):
            raise ConfigError(f"vehicle.{name} must be a finite number >= 0, got {v!r}")
    if until_s is not None and (from_s is None or until_s <= from_s):
        raise ConfigError(
            f"vehicle.stuck_until_s ({until_s}) needs stuck_from_s and must be after it "
            f"(stuck_from_s = {from_s})"
        )
    if mode not in STUCK_MODES:
        raise ConfigError(
            f"vehicle.stuck_mode must be one of {', '.join(STUCK_MODES)}, got {mode!r}"
        )


@dataclass(frozen=True)
class Terrain:
    """A plane: height ``up0_m + grad_east * east + grad_north * north`` (gradients dz/dx)."""

    grad_east: float = 0.0
    grad_north: float = 0.0
    up0_m: float = 0.0

    def __post_init__(self) -> None:
        for name in ("grad_east", "grad_north", "up0_m"):
            if not math.isfinite(getattr(self, name)):
                raise ConfigError(f"terrain.{name} must be finite")
        if math.hypot(self.grad_east, self.grad_north) > math.tan(math.radians(60)):
            raise ConfigError("terrain slope steeper than 60 degrees: the robot cannot drive it")

    def height_m(self, east_m: float, north_m: float) -> float:
        """Ground height (m) at a point."""
        return self.up0_m + self.grad_east * east_m + self.grad_north * north_m

    def attitude_deg(self, heading_deg: float) -> tuple[float, float]:
        """(pitch, roll) in degrees of a vehicle on this plane with the given true heading.

        Pitch positive nose up; roll positive right side down.
        """
        h = math.radians(heading_deg)
        slope_fwd = self.grad_east * math.sin(h) + self.grad_north * math.cos(h)
        slope_right = self.grad_east * math.cos(h) - self.grad_north * math.sin(h)
        pitch = math.atan(slope_fwd)
        # Ground rising to the right lifts the right side: negative roll.
        roll = -math.atan(slope_right / math.sqrt(1.0 + slope_fwd * slope_fwd))
        return math.degrees(pitch), math.degrees(roll)


@dataclass(frozen=True, slots=True)
class VehicleState:
    """Pose and motion at ``t_s``: position (m, local ENU), true heading (deg, clockwise from
    north, 0..360), ground speed (m/s), yaw rate (deg/s), effective drive (%), attitude (deg),
    and the distance driven so far (m). ``slip_m`` / ``slip_cw_deg``: the wheels' travel
    (signed, forward positive) and clockwise turn the body did not make while stuck in
    "slipping" mode, summed since the start (0 without that fault)."""

    t_s: float
    east_m: float
    north_m: float
    up_m: float
    heading_deg: float
    speed_mps: float
    yaw_rate_dps: float
    left_pct: float
    right_pct: float
    pitch_deg: float
    roll_deg: float
    odometer_m: float
    slip_m: float = 0.0
    slip_cw_deg: float = 0.0


def _check_pct(name: str, v: float) -> float:
    if not math.isfinite(v):
        raise ValueError(f"{name} must be finite, got {v!r}")
    return max(-100.0, min(100.0, float(v)))


class Vehicle:
    """The simulated X6WD. :meth:`command` sets the drive, :meth:`step` advances time."""

    def __init__(
        self,
        params: VehicleParams | None = None,
        *,
        east_m: float = 0.0,
        north_m: float = 0.0,
        heading_deg: float = 0.0,
        terrain: Terrain | None = None,
        t_s: float = 0.0,
    ) -> None:
        self.params = params or VehicleParams()
        self.terrain = terrain or Terrain()
        self._cmd_left = 0.0
        self._cmd_right = 0.0
        pitch, roll = self.terrain.attitude_deg(heading_deg)
        self._state = VehicleState(
            t_s=t_s,
            east_m=east_m,
            north_m=north_m,
            up_m=self.terrain.height_m(east_m, north_m),
            heading_deg=wrap360(heading_deg),
            speed_mps=0.0,
            yaw_rate_dps=0.0,
            left_pct=0.0,
            right_pct=0.0,
            pitch_deg=pitch,
            roll_deg=roll,
            odometer_m=0.0,
        )

    @property
    def state(self) -> VehicleState:
        """The current state."""
        return self._state

    @property
    def command_pct(self) -> tuple[float, float]:
        """The commanded (left, right) drive, percent."""
        return self._cmd_left, self._cmd_right

    def command(self, left_pct: float, right_pct: float) -> None:
        """Set the drive (percent, -100..100, clamped; positive forward)."""
        self._cmd_left = _check_pct("left_pct", left_pct)
        self._cmd_right = _check_pct("right_pct", right_pct)

    def _rates(self, left: float, right: float) -> tuple[float, float]:
        p = self.params
        # Heading is clockwise from north, so the right side driving faster turns it negative.
        return (left + right) / 200.0 * p.v_max_mps, (left - right) / 200.0 * p.max_turn_rate_dps

    def step(self, dt_s: float) -> VehicleState:
        """Advance by ``dt_s`` seconds (≥ 0) and return the new state."""
        if not (dt_s >= 0 and math.isfinite(dt_s)):
            raise ValueError(f"dt_s must be a finite number >= 0, got {dt_s!r}")
        p = self.params
        if p.stuck_from_s is not None:
            t0 = self._state.t_s
            for edge in (p.stuck_from_s, p.stuck_until_s):
                if edge is not None and t0 < edge < t0 + dt_s:
                    self.step(edge - t0)  # the fault starts or ends inside this step
                    return self.step(t0 + dt_s - edge)
            if p.stuck_at(t0):
                return self._step_stuck(dt_s)
        return self._step_free(dt_s)

    def _step_free(self, dt_s: float) -> VehicleState:
        s = self._state
        p = self.params
        left, right = s.left_pct, s.right_pct
        cl, cr = self._cmd_left, self._cmd_right
        settled = p.motor_tau_s == 0 or (abs(cl - left) < 1e-9 and abs(cr - right) < 1e-9)
        n = 1 if settled else max(1, math.ceil(dt_s / p.max_substep_s))
        h = dt_s / n
        east, north, heading, odo = s.east_m, s.north_m, s.heading_deg, s.odometer_m
        for _ in range(n):
            if settled or p.motor_tau_s == 0:
                mean_l = new_l = cl
                mean_r = new_r = cr
            else:
                decay = math.exp(-h / p.motor_tau_s)
                new_l = cl + (left - cl) * decay
                new_r = cr + (right - cr) * decay
                # Exact mean of the exponential response over the sub-step.
                frac = (1.0 - decay) * p.motor_tau_s / h if h > 0 else 1.0
                mean_l = cl + (left - cl) * frac
                mean_r = cr + (right - cr) * frac
            v, w_dps = self._rates(mean_l, mean_r)
            pitch, _ = self.terrain.attitude_deg(heading)
            v_h = v * math.cos(math.radians(pitch))
            east, north, heading = _arc(east, north, heading, v_h, w_dps, h)
            odo += abs(v) * h
            left, right = new_l, new_r
        if abs(left - cl) < 1e-6 and abs(right - cr) < 1e-6:
            left, right = cl, cr
        v_end, w_end = self._rates(left, right)
        pitch, roll = self.terrain.attitude_deg(heading)
        # Built directly (every field changes): dataclasses.replace costs more than the
        # physics at the compass rate of a simulated mission.
        self._state = VehicleState(
            t_s=s.t_s + dt_s,
            east_m=east,
            north_m=north,
            up_m=self.terrain.height_m(east, north),
            heading_deg=wrap360(heading),
            speed_mps=v_end,
            yaw_rate_dps=w_end,
            left_pct=left,
            right_pct=right,
            pitch_deg=pitch,
            roll_deg=roll,
            odometer_m=odo,
            slip_m=s.slip_m,
            slip_cw_deg=s.slip_cw_deg,
        )
        return self._state

    def _step_stuck(self, dt_s: float) -> VehicleState:
        """A step with the body held in place: "blocked" stalls the wheels too (drive 0),
        "slipping" turns them as the motors respond and sums their travel in ``slip_*``."""
        s = self._state
        p = self.params
        slip_m, slip_cw = s.slip_m, s.slip_cw_deg
        if p.stuck_mode == "blocked":
            left = right = 0.0
        else:
            left, right = s.left_pct, s.right_pct
            cl, cr = self._cmd_left, self._cmd_right
            if p.motor_tau_s == 0:
                mean_l = new_l = cl
                mean_r = new_r = cr
            else:  # the exact mean of the exponential response over the step
                decay = math.exp(-dt_s / p.motor_tau_s)
                frac = (1.0 - decay) * p.motor_tau_s / dt_s if dt_s > 0 else 1.0
                new_l, new_r = cl + (left - cl) * decay, cr + (right - cr) * decay
                mean_l, mean_r = cl + (left - cl) * frac, cr + (right - cr) * frac
            v, w_dps = self._rates(mean_l, mean_r)
            slip_m += v * dt_s
            slip_cw += w_dps * dt_s
            left, right = new_l, new_r
            if abs(left - cl) < 1e-6 and abs(right - cr) < 1e-6:
                left, right = cl, cr
        self._state = VehicleState(
            t_s=s.t_s + dt_s,
            east_m=s.east_m,
            north_m=s.north_m,
            up_m=s.up_m,
            heading_deg=s.heading_deg,
            speed_mps=0.0,
            yaw_rate_dps=0.0,
            left_pct=left,
            right_pct=right,
            pitch_deg=s.pitch_deg,
            roll_deg=s.roll_deg,
            odometer_m=s.odometer_m,
            slip_m=slip_m,
            slip_cw_deg=slip_cw,
        )
        return self._state


def _arc(
    east: float, north: float, heading_deg: float, v_mps: float, w_dps: float, dt_s: float
) -> tuple[float, float, float]:
    """Exact pose after ``dt_s`` at constant speed and yaw rate (heading clockwise from N)."""
    h0 = math.radians(heading_deg)
    w = math.radians(w_dps)
    dh = w * dt_s
    if abs(dh) < 1e-9:
        d = v_mps * dt_s
        return east + d * math.sin(h0), north + d * math.cos(h0), heading_deg
    r = v_mps / w
    h1 = h0 + dh
    east += r * (math.cos(h0) - math.cos(h1))
    north += r * (math.sin(h1) - math.sin(h0))
    return east, north, wrap360(math.degrees(h1))
