"""Simulated wheel encoders of the X6WD: counts from the simulated vehicle's true motion.

The vehicle model (:mod:`sim_backend.vehicle`) moves the body; this module says how far each
side's wheels rolled to make that motion, and what the encoders count for it:

- body travel ``s`` along the ground (from the state's odometer, signed by the direction of
  motion) and clockwise heading change ``Δψ`` over the step;
- slope slip: climbing, the wheels turn more than the body advances, descending less:
  wheel travel ``s + slope_slip · sin(pitch) · |s|`` (pitch from the terrain, nose up > 0);
- skid-steer turning: the sides' wheel travels differ by ``Δψ · effective_track_m``, the
  effective track being wider than the wheel-centre distance because the wheels slip
  sideways in a turn (REFERENCE.md §7: often 1.2-2x); left = common + Δψ·B/2 (clockwise
  turn: the left side is outside);
- non-systematic error per side (seed 003): zero-mean Gaussian with variance
  ``k · |wheel travel|``, so it grows with distance and not with the step rate (clipped to
  the step's own travel, which only matters for steps shorter than k);
- systematic error: counts are wheel travel over the ACTUAL circumference
  (``π · left_diameter_m``), while odometry assumes the nominal one.
- a vehicle stuck and slipping (:mod:`sim_backend.vehicle`'s injected fault) moves its
  wheels but not its body: the state's ``slip_m`` / ``slip_cw_deg`` carry the travel and
  turn the wheels made without the body, and they are counted like the body's.

Counts accumulate as reals and are emitted as whole counts (quantisation as in hardware).

Defaults (documented guesses: the papers name neither wheels nor encoders): 120 mm wheels; a
12-line quadrature encoder (48 edges per motor turn) behind a 34:1 gearbox = 1632 counts per
wheel turn, 4329 counts per metre; geometric track 0.245 m (the 305 mm wide body less a
60 mm tyre); effective track 0.37 m (1.5x); tyres 1 % apart (left +1 %, right -1 %).

Fast time: call :meth:`EncoderSim.step` after each physics step and either add the counts
to a board (:meth:`drivers.motors.MotorBoard.add_counts`, as HIL does) or take
:meth:`EncoderSim.reading` at the host's poll rate (20 Hz): the record
:meth:`drivers.motors.SerialMotorLink.read_odometry` would return.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

import numpy as np

from sim_backend.vehicle import VehicleState
from x6wd.core.errors import ConfigError
from x6wd.core.geodesy import wrap_deg
from x6wd.core.records import WheelOdometry

ENCODER_STREAM = 4  # SeedSequence child of the scenario seed (SimRandom uses children 0..3)


@dataclass(frozen=True)
class EncoderParams:
    """The simulated encoders' truth (lengths in m, slip as a fraction per unit sin(pitch)).

    ``k_left_m`` / ``k_right_m``: non-systematic error, the variance (m²) of a side's travel
    per metre that side rolls (seed 003's k_l, k_r; unit m²/m = m).
    """

    counts_per_rev: int = 1632
    nominal_diameter_m: float = 0.120
    left_diameter_m: float = 0.1212
    right_diameter_m: float = 0.1188
    geometric_track_m: float = 0.245
    effective_track_m: float = 0.37
    k_left_m: float = 2e-4
    k_right_m: float = 2e-4
    slope_slip: float = 0.3

    def __post_init__(self) -> None:
        if not 1 <= self.counts_per_rev <= 1_000_000:
            raise ConfigError(f"encoders.counts_per_rev must be 1..1e6, got {self.counts_per_rev}")
        for f in fields(self):
            v = getattr(self, f.name)
            if not math.isfinite(v):
                raise ConfigError(f"encoders.{f.name} must be finite, got {v!r}")
        for name in ("nominal_diameter_m", "left_diameter_m", "right_diameter_m"):
            if not 0.01 <= getattr(self, name) <= 2.0:
                raise ConfigError(f"encoders.{name} must be within 0.01..2 m")
        if not 0.05 <= self.geometric_track_m <= self.effective_track_m <= 10.0:
            raise ConfigError(
                "encoders: need 0.05 m <= geometric_track_m <= effective_track_m <= 10 m "
                "(skid steer slips outward in turns, never inward)"
            )
        if not (0 <= self.k_left_m <= 0.1 and 0 <= self.k_right_m <= 0.1):
            raise ConfigError("encoders.k_left_m / k_right_m must be within 0..0.1 m")
        if not 0 <= self.slope_slip <= 5:
            raise ConfigError(f"encoders.slope_slip must be within 0..5, got {self.slope_slip}")

    def counts_per_m(self, side: str) -> float:
        """True counts per metre of wheel travel on ``side`` ("left" or "right")."""
        d = self.left_diameter_m if side == "left" else self.right_diameter_m
        return self.counts_per_rev / (math.pi * d)


def encoder_rng(seed: int) -> np.random.Generator:
    """The encoders' random stream of a scenario seed (independent of SimRandom's four)."""
    return np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(ENCODER_STREAM,)))


class EncoderSim:
    """Both sides' encoders, stepped along the vehicle's states.

    ``start`` is the state the counting begins at (else the first :meth:`step` only sets
    it). ``rng`` draws the non-systematic error (None: none, systematic errors only).
    """

    def __init__(
        self,
        params: EncoderParams | None = None,
        *,
        rng: np.random.Generator | None = None,
        start: VehicleState | None = None,
    ) -> None:
        self.params = params or EncoderParams()
        self._rng = rng
        self._prev = start
        self._real = [0.0, 0.0]  # counts as reals (left, right)
        self._whole = [0, 0]
        self._latches = 0
        self.wheel_travel_m = [0.0, 0.0]  # true signed travel per side, noise included
        # (params, its (left, right) counts per metre): computed once per parameter set
        self._cpm: tuple[EncoderParams, tuple[float, float]] | None = None

    @property
    def counts(self) -> tuple[int, int]:
        """(left, right) whole counts since the start, signed (no rollover here)."""
        return self._whole[0], self._whole[1]

    def reading(self, t_s: float) -> WheelOdometry:
        """The counts now as the host link reports them (continuous since the start, the
        latch number counting 1, 2, ... and wrapping at 2**16), stamped ``t_s`` (s)."""
        self._latches += 1
        return WheelOdometry(t_s, self._whole[0], self._whole[1], self._latches % 65536)

    def step(self, dt_s: float, state: VehicleState) -> tuple[int, int]:
        """Move the wheels from the previous state to ``state`` (``dt_s`` s later); the whole
        (left, right) counts of this step, signed, forward positive."""
        if not (dt_s >= 0 and math.isfinite(dt_s)):
            raise ValueError(f"dt_s must be a finite number >= 0, got {dt_s!r}")
        prev, self._prev = self._prev, state
        if prev is None:
            return 0, 0
        p = self.params
        ds_m = state.odometer_m - prev.odometer_m  # >= 0: the model integrates |v|
        # direction of motion over the step (the speed does not reverse within one step
        # unless the command does, and then the step's travel is ~0)
        s_m = -ds_m if prev.speed_mps + state.speed_mps < 0 else ds_m
        dpsi_cw_rad = math.radians(wrap_deg(state.heading_deg - prev.heading_deg))
        pitch_rad = math.radians(0.5 * (prev.pitch_deg + state.pitch_deg))
        common_m = s_m + p.slope_slip * math.sin(pitch_rad) * abs(s_m)
        if state.slip_m != prev.slip_m or state.slip_cw_deg != prev.slip_cw_deg:
            # stuck and slipping: the wheels turned where the body did not
            common_m += state.slip_m - prev.slip_m
            dpsi_cw_rad += math.radians(state.slip_cw_deg - prev.slip_cw_deg)
        half_turn_m = 0.5 * dpsi_cw_rad * p.effective_track_m
        travel = [common_m + half_turn_m, common_m - half_turn_m]
        if self._rng is not None:
            for i, k in enumerate((p.k_left_m, p.k_right_m)):
                if k > 0 and travel[i] != 0:
                    # clipped so that a wheel never rolls against its motion: √(k·|s|) grows
                    # past |s| itself in a motor's creeping tail (|s| < k), where the counts
                    # would otherwise jitter; at walking pace (|s| ≫ k) it never binds
                    mag = abs(travel[i])
                    err = float(self._rng.normal(0.0, math.sqrt(k * mag)))
                    travel[i] += max(-mag, min(mag, err))
        cpm = self._cpm
        if cpm is None or cpm[0] is not p:
            cpm = self._cpm = (p, (p.counts_per_m("left"), p.counts_per_m("right")))
        out = [0, 0]
        for i in range(2):
            self.wheel_travel_m[i] += travel[i]
            self._real[i] += travel[i] * cpm[1][i]
            whole = math.floor(self._real[i])
            out[i] = whole - self._whole[i]
            self._whole[i] = whole
        return out[0], out[1]
