"""A sans-IO extended Kalman filter for the robot's pose: GPS, compass and wheel odometry.

State (local tangent plane, east/north metres; headings are BEARINGS, clockwise from true
north, radians)::

    x = [east_m, north_m, heading_rad, speed_mps, yaw_rate_rps, bias_east_m, bias_north_m,
         turn_scale, drift_rad_per_m, compass_offset_rad, travel_scale,
         dev_sin1_rad, dev_cos1_rad, dev_sin2_rad, dev_cos2_rad]

``yaw_rate_rps`` is clockwise positive (the compass sense). The two bias states are the
slowly varying part of the GPS error (first-order Gauss-Markov); they exist only when
:attr:`GpsParams.correlation_s` is set, otherwise the filter is the seed paper's EKF with white
GPS noise (the bias states are then kept at zero with zero variance).

The last two states calibrate the odometry while the robot drives, so an uncalibrated robot
(the shipped config's nominal wheels and geometric track) still navigates: the heading change
of an increment is ``turn_scale·(dl − dr)/track_m + drift_rad_per_m·ds``. ``turn_scale`` takes
up a wrong effective track (a skid steer turns less than its wheels say: 0.5-0.8), the
compass observing it in turns; ``drift_rad_per_m`` takes up unequal wheel diameters (1 %
apart on a 0.245 m track is 0.04 rad per metre driven), the compass observing it on straights.
Both start at the calibration's values (1, 0) with :class:`OdometryParams`'s uncertainty and
wander slowly (surface, load). In mode GPS_COMPASS they stay where they are.

``travel_scale`` multiplies the wheels' mean travel: ``ds = travel_scale·(dl + dr)/2``. Wheel
diameters a few per cent off (tyre pressure, wear, load, a config rounded) made dead
reckoning run steadily ahead of or behind the fixes; without this state the GPS bias states
took the offset up as "slow GPS error" (10-33 m behind on a 500 m leg with wheels 10 %
small, σ reading 2 m, the robot past its waypoint). The fixes observe it on every straight,
as the along-track innovation grows with the distance driven.

``compass_offset_rad`` is what the compass reads above the true bearing, constant over
headings: its mounting, a declination the robot has wrong (WMM off its dates, a site's
anomaly), residual iron. Without it a compass 10° off pinned the heading 10° off and the
dead reckoning drifted sideways; the GPS bias states took up the drift (27 m at 15 sigma)
until the robot reached its waypoints only in its own estimate. The GPS track observes it on
every leg (:attr:`CompassParams.offset_sigma_deg`; 0 freezes it at 0). Iron near the compass
adds a deviation that varies with the heading, the classic deviation card: hard iron once per
turn, soft iron twice, ``a1·sin ψ + b1·cos ψ + a2·sin 2ψ + b2·cos 2ψ``. A constant offset
cannot follow it, so on a zig-zag the offset was relearnt on every leg and arrivals ended
7-11 m off (GPS 2-4 m) with hard iron worth ±11°; the four ``dev_*`` states learn the card
from the legs' different headings (:attr:`CompassParams.deviation_sigma_deg`; 0: none).

Nothing here reads a clock: every input carries its time ``t_s`` (seconds, one monotonic
clock), and the filter predicts to each input's time before using it. Inputs stamped slightly
earlier than the filter's time (devices interleave) are used at the filter's time when at most
``max_late_s`` late, and refused (``reason="stale"``) otherwise; time never runs backwards.

Inputs (see docs/navigation.md for the equations):

- :meth:`Estimator.on_odometry` (mode ODOMETRY): wheel travel ``d_left_m``, ``d_right_m`` since
  the previous increment. The increment drives the prediction (the paper's odometry motion
  model): ``ds = travel_scale·(dl + dr)/2``, ``dψ = (dl − dr)/track_m`` (left ahead turns
  clockwise), the pose moves along the mid-step heading, and the wheel-travel covariance
  ``diag(k_left·|dl|, k_right·|dr|)`` (seed 003) plus a skid-slip term ``k_slip·|dψ|`` is
  propagated through the Jacobian into the process noise. Speed and yaw rate are set from the
  increment's rates; between increments the pose is extrapolated with them.
- :meth:`Estimator.on_command` (mode GPS_COMPASS, optional): the commanded motor percentages.
  Speed and yaw rate then relax towards the commanded values with the motors' time constant;
  the model error is a Gauss-Markov process of ``sigma_speed_mps``/``sigma_yaw_rate_dps``.
  Without commands, speed and yaw rate are random walks (a constant-velocity model).
- :meth:`Estimator.on_compass`: the CMPS10's magnetic bearing; the declination is added. The
  CMPS10 low-passes its heading (about 640 ms to refresh fully, i.e. a first-order filter of
  time constant ~0.21 s). A first-order filter of a heading turning at a constant rate ω lags
  it by exactly ``τ·ω``, so the measurement model is the delayed heading
  ``h(x) = ψ − τ·ω`` (Jacobian ``[0, 0, 1, 0, −τ, 0, 0]``), and the noise is inflated by
  ``(lag_uncertainty·τ·ω)²`` for the part of the lag the model misses (changing turn rates, the
  datasheet's "about"). This keeps the compass usable, unbiased, while turning, where a plain
  noise inflation would throw its information away exactly when the heading changes fastest.
- :meth:`Estimator.on_gps`: a fix projected to east/north metres (the caller projects, e.g.
  with :class:`x6wd.nav.geo.LocalTangentPlane`) and its HDOP. The fix's total error
  (seed 003, eq. 12) is ``σ = DOP·sqrt(RE² + ASE² + LCE(position)²)``. With
  ``correlation_s`` set, the receiver noise ``DOP·RE`` is the white measurement noise and the
  atmospheric/satellite and local (multipath) parts ``DOP·sqrt(ASE² + LCE²)`` are the
  stationary standard deviation of the Gauss-Markov bias states, so the total stays the
  paper's σ while successive fixes are correlated as a real receiver's are; without it the
  whole σ² is white measurement noise (the paper). ``LCE`` is looked up at the filter's
  predicted position (not at the fix, so an outlier does not set its own noise).

Gating: every update computes the normalised innovation squared ``d² = yᵀ S⁻¹ y`` and is
refused when ``d²`` exceeds the chi-square threshold (``gps_chi2`` with 2 degrees of freedom,
``compass_chi2`` with 1). Refusals are counted (:class:`EstimatorStats`). Recovery: the
innovations of consecutive refused fixes are kept; once ``recover_after`` of them in a row are
consistent with each other (each one's distance from their mean, in its own innovation
covariance, is inside the gate) the filter accepts the step: the position (or the heading) is
re-initialised from the latest measurement with the measurement's covariance and the
``*_resets`` counter goes up. GPS fixes are also accepted when they agree with a steady drift
along the heading instead (each one inside the gate of a straight line in time through their
innovations, its slope within ``DRIFT_ALONG_DEG`` of the heading; across it, the heading is
what is wrong, which the off-course check must see): dead reckoning running away from the
fixes (encoders counting a fraction of the travel, a wrong wheel size) gives innovations that
grow by the same amount every second, which never agree with their mean, so the estimate
drove on the wheels' count while the fixes arrived (167 m off, the mission lost, with
encoders counting 12 %); ``odometry_runaway_resets`` counts those.
For ``correlation_s`` after a reset, the bias beyond its stationary 99 % circle
(:data:`BIAS_BOUND_CHI2`) is moved into the position after every accepted fix
(:meth:`Estimator._bound_bias`): after a reset onto multipath fixes, the fixes' return to the
truth otherwise became a bias of 6 σ_b.
A short NLOS jump (fewer fixes than ``recover_after``) or scattered outliers are thus never
accepted, while a real, persistent step (the robot was moved, the odometry slipped during a
long GPS outage) is accepted after ``recover_after`` fixes. Long outages also open the gate by
themselves, as the predicted covariance grows.
"""

from __future__ import annotations

import enum
import math
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from x6wd.core.config import CMPS10_LAG_S
from x6wd.core.errors import X6wdError

E, N, PSI, V, W, BE, BN, KT, BA, CO, TS, D1S, D1C, D2S, D2C = range(15)
_DEV = (D1S, D1C, D2S, D2C)  # the compass deviation card: sin ψ, cos ψ, sin 2ψ, cos 2ψ
# The drift rule's direction (Estimator._gps_agreement): a steady drift of refused fixes
# within this angle of the heading (either way) is travel counted wrong.
DRIFT_ALONG_DEG = 30.0
DRIFT_ALONG_COS = math.cos(math.radians(DRIFT_ALONG_DEG))
NX = 15
# An odometry increment spanning less than this fraction of the median of the recent spans
# (the poll period) is held back and merged into the next: a reply read late and the next
# poll answered at once gave 20-180 ms of travel over a 0.2-1 ms span, and travel / span as
# the speed (43-540 m/s for a 2.3 m/s robot) broke the fixes' gate
ODO_SHORT_SPAN_FRACTION = 0.5
ODO_SPAN_HISTORY = 9  # increments in that median
_TWO_PI = 2.0 * math.pi
_EYE = np.eye(NX)
_EYE.flags.writeable = False  # copied, never written: np.eye per call cost more than the math


CHI2_2DOF_999 = -2.0 * math.log(1e-3)
"""Chi-square quantile for 2 degrees of freedom at 99.9 % (13.82): ``−2·ln(1 − p)`` exactly."""
CHI2_2DOF_99 = -2.0 * math.log(1e-2)
"""Chi-square quantile for 2 degrees of freedom at 99 % (9.21)."""
CHI2_1DOF_999 = 10.827566170662733
"""Chi-square quantile for 1 degree of freedom at 99.9 % (10.83)."""
BIAS_BOUND_CHI2 = -2.0 * math.log(1e-2)
"""The GPS bias states' bound, ``|b|² / σ_b²`` (9.21: the stationary 2-D distribution's 99 %
circle, |b| ≤ 3.03 σ_b); the part beyond it is taken as position error
(:meth:`Estimator._bound_bias`)."""
BIAS_RUNAWAY_CHI2 = -2.0 * math.log(1e-6)
"""The GPS bias the fixes built while the robot stood still (its speed under
:data:`STILL_MPS`: the wheels' count, or the commanded drive) beyond this, ``|Δb|² / σ_b²``
(27.6: 5.26 σ_b, a chance of 1e-6 for the whole stationary bias, and a bias changes less in
a shorter time), is no GPS error but a move the wheels did not see (carried, pushed, on a
trailer): the filter resets onto the fix (:meth:`Estimator._bias_runaway`). σ_b² is the
largest stationary variance of the recent fixes, forgotten as the bias forgets
(``correlation_s``), so a bias built under a high HDOP does not trip it when the HDOP
falls. Only while still: a bias built while driving is a heading (or travel) the model has
wrong, which the drift rule and the off-course check must see, not a reset hide."""
STILL_MPS = 0.05
"""The estimated speed (m/s) under which the robot counts as standing still."""


class EstimatorError(X6wdError, ValueError):
    """A bad parameter, or an input the configured mode does not take."""


def _wrap(a: float) -> float:
    """Angle (rad) wrapped to [−π, π)."""
    return (a + math.pi) % _TWO_PI - math.pi


def _deviation(psi: float, card: Sequence[float]) -> float:
    """The deviation card ``(a1, b1, a2, b2)`` (rad) at heading ``psi`` (rad), rad."""
    a1, b1, a2, b2 = card
    s1, c1 = math.sin(psi), math.cos(psi)
    return a1 * s1 + b1 * c1 + 2.0 * a2 * s1 * c1 + b2 * (c1 * c1 - s1 * s1)


def _pos(name: str, v: float, zero_ok: bool = False) -> None:
    ok = math.isfinite(v) and (v >= 0 if zero_ok else v > 0)
    if not ok:
        raise EstimatorError(
            f"{name} must be a finite number {'>=' if zero_ok else '>'} 0, got {v!r}"
        )


class Mode(enum.StrEnum):
    """What drives the prediction."""

    ODOMETRY = "odometry"
    """Wheel-encoder increments (:meth:`Estimator.on_odometry`) drive the pose."""
    GPS_COMPASS = "gps_compass"
    """No encoders: a speed/yaw-rate model, driven by commanded motor percentages when given
    (:meth:`Estimator.on_command`), by process noise alone otherwise."""


@dataclass(frozen=True)
class OdometryParams:
    """Calibrated odometry (seed 003, section 2.3).

    ``track_m``: the EFFECTIVE track width from a circle-track calibration (metres; on a skid
    steer often 1.2-2× the geometric one); ``k_left_m``, ``k_right_m``: variance of a wheel's
    travel per metre it travelled (m²/m, so metres); ``k_slip_rad``: extra heading variance per
    radian turned (rad²/rad), the skid-steer slip the encoders do not see.
    ``sigma_turn_scale``, ``sigma_drift_rad_per_m``, ``sigma_travel_scale``: the initial
    uncertainty of the three online calibration states (see the module docstring; 0 freezes
    them at 1, 0 and 1), and their random walks per second (``*_walk_*``, one sigma after
    1 s).
    """

    track_m: float
    k_left_m: float = 2e-4
    k_right_m: float = 2e-4
    k_slip_rad: float = 2e-3
    sigma_turn_scale: float = 0.3
    sigma_drift_rad_per_m: float = 0.1
    turn_scale_walk_per_s: float = 1e-3
    drift_walk_rad_per_m_per_s: float = 1e-5
    sigma_travel_scale: float = 0.1
    travel_scale_walk_per_s: float = 1e-4

    def __post_init__(self) -> None:
        _pos("sigma_travel_scale", self.sigma_travel_scale, zero_ok=True)
        _pos("travel_scale_walk_per_s", self.travel_scale_walk_per_s, zero_ok=True)
        _pos("sigma_turn_scale", self.sigma_turn_scale, zero_ok=True)
        _pos("sigma_drift_rad_per_m", self.sigma_drift_rad_per_m, zero_ok=True)
        _pos("turn_scale_walk_per_s", self.turn_scale_walk_per_s, zero_ok=True)
        _pos("drift_walk_rad_per_m_per_s", self.drift_walk_rad_per_m_per_s, zero_ok=True)
        _pos("track_m", self.track_m)
        _pos("k_left_m", self.k_left_m, zero_ok=True)
        _pos("k_right_m", self.k_right_m, zero_ok=True)
        _pos("k_slip_rad", self.k_slip_rad, zero_ok=True)


@dataclass(frozen=True)
class CommandParams:
    """Commanded drive -> motion, for the GPS_COMPASS mode (as ``sim_backend.vehicle``).

    ``speed_mps_per_pct``: ground speed per percent of mean drive (m/s/%);
    ``yaw_rate_dps_per_pct``: clockwise yaw rate per percent of ``(left − right)/2`` (deg/s/%);
    ``tau_s``: the motors' first-order response (s); ``sigma_speed_mps``,
    ``sigma_yaw_rate_dps``: how far the real motion strays from the commanded one (slip,
    battery, slope), a Gauss-Markov error with correlation time ``error_tau_s`` (s).
    """

    speed_mps_per_pct: float
    yaw_rate_dps_per_pct: float
    tau_s: float = 0.25
    sigma_speed_mps: float = 0.15
    sigma_yaw_rate_dps: float = 10.0
    error_tau_s: float = 5.0

    def __post_init__(self) -> None:
        _pos("speed_mps_per_pct", self.speed_mps_per_pct)
        _pos("yaw_rate_dps_per_pct", self.yaw_rate_dps_per_pct)
        _pos("tau_s", self.tau_s, zero_ok=True)
        _pos("sigma_speed_mps", self.sigma_speed_mps)
        _pos("sigma_yaw_rate_dps", self.sigma_yaw_rate_dps)
        _pos("error_tau_s", self.error_tau_s)


@dataclass(frozen=True)
class CompassParams:
    """The compass: ``sigma_deg`` white noise of one sample (deg); ``lag_s`` the first-order
    lag of its heading filter (s; :data:`CMPS10_LAG_S`, 0 = none); ``lag_uncertainty`` the
    fraction of the lag term ``lag_s·ω`` added as noise; ``declination_deg`` added to the
    magnetic bearing (deg, east positive; see :mod:`x6wd.nav.declination`);
    ``offset_sigma_deg`` the prior one-sigma of the compass's constant offset from the true
    bearing after the declination (deg; 0: none is estimated), ``offset_walk_deg_per_s`` its
    random walk (deg after 1 s); ``deviation_sigma_deg`` the prior one-sigma of each
    coefficient of the heading-dependent deviation (deg; 0: none is estimated),
    ``deviation_walk_deg_per_s`` their random walk (deg after 1 s)."""

    sigma_deg: float = 2.0
    lag_s: float = CMPS10_LAG_S
    lag_uncertainty: float = 0.5
    declination_deg: float = 0.0
    offset_sigma_deg: float = 10.0
    offset_walk_deg_per_s: float = 0.01
    deviation_sigma_deg: float = 2.0
    deviation_walk_deg_per_s: float = 0.001

    def __post_init__(self) -> None:
        _pos("sigma_deg", self.sigma_deg)
        _pos("deviation_sigma_deg", self.deviation_sigma_deg, zero_ok=True)
        _pos("deviation_walk_deg_per_s", self.deviation_walk_deg_per_s, zero_ok=True)
        _pos("offset_sigma_deg", self.offset_sigma_deg, zero_ok=True)
        _pos("offset_walk_deg_per_s", self.offset_walk_deg_per_s, zero_ok=True)
        _pos("lag_s", self.lag_s, zero_ok=True)
        _pos("lag_uncertainty", self.lag_uncertainty, zero_ok=True)
        if not math.isfinite(self.declination_deg):
            raise EstimatorError(f"declination_deg must be finite, got {self.declination_deg!r}")


@dataclass(frozen=True)
class GpsParams:
    """The GPS error model of seed 003: ``σ = DOP·sqrt(RE² + ASE² + LCE(position)²)``.

    ``re_m`` receiver error and ``ase_m`` atmospheric and satellite error (metres, at DOP 1);
    ``lce_m`` the local characteristic error map, ``(east_m, north_m) -> metres`` (``None``:
    0 everywhere); ``correlation_s`` the correlation time of the ASE + LCE part (s; ``None``:
    all white, as in the paper; see the module docstring).
    """

    re_m: float = 1.0
    ase_m: float = 1.5
    lce_m: Callable[[float, float], float] | None = None
    correlation_s: float | None = 120.0

    def __post_init__(self) -> None:
        _pos("re_m", self.re_m)
        _pos("ase_m", self.ase_m, zero_ok=True)
        if self.correlation_s is not None:
            _pos("correlation_s", self.correlation_s)


@dataclass(frozen=True)
class GatingParams:
    """Innovation gates (squared Mahalanobis distances) and the recovery rule (see the module
    docstring): ``recover_after`` consecutive, mutually consistent refused fixes (compass
    samples: ``compass_recover_after``) are accepted as a real step."""

    gps_chi2: float = CHI2_2DOF_999
    compass_chi2: float = CHI2_1DOF_999
    recover_after: int = 8
    compass_recover_after: int = 20

    def __post_init__(self) -> None:
        _pos("gps_chi2", self.gps_chi2)
        _pos("compass_chi2", self.compass_chi2)
        if self.recover_after < 2 or self.compass_recover_after < 2:
            raise EstimatorError("recover_after and compass_recover_after must be >= 2")


@dataclass(frozen=True)
class MotionParams:
    """Process noise of the time prediction: ``accel_sigma_mps2`` (m/s², white acceleration)
    and ``yaw_accel_sigma_dps2`` (deg/s², white yaw acceleration); ``max_step_s`` the longest
    integration sub-step (s); ``max_late_s`` how late an input may be and still be used (s);
    ``odometry_timeout_s``: in mode ODOMETRY, the commanded drive (if given) predicts once no
    increment came for this long (s)."""

    accel_sigma_mps2: float = 0.5
    yaw_accel_sigma_dps2: float = 30.0
    max_step_s: float = 0.1
    max_late_s: float = 0.3
    odometry_timeout_s: float = 0.5

    def __post_init__(self) -> None:
        _pos("odometry_timeout_s", self.odometry_timeout_s)
        _pos("accel_sigma_mps2", self.accel_sigma_mps2)
        _pos("yaw_accel_sigma_dps2", self.yaw_accel_sigma_dps2)
        _pos("max_step_s", self.max_step_s)
        _pos("max_late_s", self.max_late_s, zero_ok=True)


@dataclass(frozen=True)
class EstimatorConfig:
    """Everything the filter needs. ``odometry`` is required in mode ODOMETRY; ``command`` is
    optional in mode GPS_COMPASS (without it speed is a random walk)."""

    mode: Mode = Mode.ODOMETRY
    odometry: OdometryParams | None = None
    command: CommandParams | None = None
    compass: CompassParams = field(default_factory=CompassParams)
    gps: GpsParams = field(default_factory=GpsParams)
    gating: GatingParams = field(default_factory=GatingParams)
    motion: MotionParams = field(default_factory=MotionParams)

    def __post_init__(self) -> None:
        if self.mode == Mode.ODOMETRY and self.odometry is None:
            raise EstimatorError("mode odometry needs OdometryParams")


@dataclass(frozen=True, slots=True)
class Update:
    """What one measurement did: ``accepted``; ``nis`` its normalised innovation squared
    (NaN when none was computed); ``reason``: "ok", "gated", "reset", "init", "stale"."""

    accepted: bool
    nis: float
    reason: str


@dataclass(frozen=True, slots=True)
class Estimate:
    """The filter's state at ``t_s`` (s): position (m), true bearing ``heading_deg`` in
    [0, 360), ``speed_mps``, clockwise ``yaw_rate_dps``, one-sigma uncertainties, and the
    odometry's online calibration (``turn_scale``, ``drift_deg_per_m``, ``travel_scale``), and
    the compass's learnt error from the true bearing: ``compass_offset_deg`` and the
    heading-dependent ``compass_deviation_deg`` at the current heading."""

    t_s: float
    east_m: float
    north_m: float
    heading_deg: float
    speed_mps: float
    yaw_rate_dps: float
    sigma_east_m: float
    sigma_north_m: float
    sigma_heading_deg: float
    turn_scale: float = 1.0
    drift_deg_per_m: float = 0.0
    compass_offset_deg: float = 0.0
    travel_scale: float = 1.0
    compass_deviation_deg: float = 0.0


@dataclass
class EstimatorStats:
    """Counters: accepted and refused (gated) measurements, resets by the recovery rule (the
    measurement that triggers a reset is counted there, not as refused), inputs dropped as too
    late, and the current run of consecutive refused GPS fixes."""

    gps_accepted: int = 0
    gps_rejected: int = 0
    gps_resets: int = 0
    odometry_runaway_resets: int = 0  # of gps_resets: refused fixes that agreed with a steady drift
    gps_consecutive_rejected: int = 0
    last_reset_m: float = 0.0  # how far the latest reset moved the position (m)
    last_reset_reason: str = ""  # "step", "drift" (the refused fixes agreed so) or "bias"
    # the radius (m) of the position's own 99 % ellipse (its long axis) just before that reset:
    # a reset inside it is the estimate settling where it said it might be, not a surprise
    last_reset_circle_m: float = 0.0
    # the GPS model's per-axis sigma (m) at HDOP 1 where the latest fix was judged: RE, ASE
    # and the LCE there (what the configured noise calls normal under an open sky)
    noise_hdop1_m: float = 0.0
    bias_runaway_resets: int = 0  # of gps_resets: fixes taken, the bias beyond BIAS_RUNAWAY_CHI2
    gps_bias_bounded: int = 0  # accepted fixes after which the bias bound moved the position
    compass_accepted: int = 0
    compass_rejected: int = 0
    compass_resets: int = 0
    stale_dropped: int = 0


class Estimator:
    """The EKF; see the module docstring. Feed it inputs in time order (roughly)."""

    def __init__(self, config: EstimatorConfig) -> None:
        self.cfg = config
        self.stats = EstimatorStats()
        self._x = np.zeros(NX)
        self._p = np.zeros((NX, NX))
        self._t: float | None = None  # time of the state (s)
        self._ready = False
        self._pending_fix: tuple[float, float, float, float] | None = None  # t, e, n, var
        self._pending_heading: tuple[float, float] | None = None  # t, psi
        self._t_odo: float | None = None  # end time of the last odometry increment
        self._odo_spans: deque[float] = deque(maxlen=ODO_SPAN_HISTORY)  # recent spans (s)
        self._odo_held: tuple[float, float, float] | None = None  # short increment: dl, dr, slip
        self.odometry_merged = 0  # short increments merged into the next (ODO_SHORT_SPAN_*)
        self._cmd: tuple[float, float] | None = None  # commanded (speed m/s, yaw rate rad/s)
        self._odo_fresh = False  # odometry increments arrived within odometry_timeout_s
        self._bias_var_m2 = 0.0  # stationary variance of the GPS bias states, m²
        self._bias_env_m2 = 0.0  # the largest recent one, forgotten as the bias forgets (m²)
        self._bias_moving = np.zeros(2)  # the bias after the latest fix taken while moving (m)
        self._t_gps_reset: float | None = None  # time of the latest GPS reset (s)
        self._declination_rad = math.radians(config.compass.declination_deg)
        self._gps_refused: deque[tuple[float, npt.NDArray[np.float64], npt.NDArray[np.float64]]] = (
            deque(maxlen=config.gating.recover_after)
        )  # (t s, innovation, its covariance)
        self._compass_refused: deque[tuple[float, float]] = deque(
            maxlen=config.gating.compass_recover_after
        )
        m = config.motion
        self._q_v = m.accel_sigma_mps2**2  # (m/s)² per s
        self._q_w = math.radians(m.yaw_accel_sigma_dps2) ** 2  # (rad/s)² per s
        self._odometry_mode = config.mode == Mode.ODOMETRY
        # The latest Estimate, until the state changes (the controller asks for it several
        # times per input: position, heading, telemetry); None when it must be rebuilt.
        self._est: Estimate | None = None
        # The compass's measurement Jacobian [0, 0, 1, 0, -lag, 0..., 1] (constant; never
        # written): it reads the heading, late by the lag, plus its offset
        self._h_compass = np.zeros(NX)
        self._h_compass[PSI] = 1.0
        self._h_compass[W] = -config.compass.lag_s
        self._estimate_offset = config.compass.offset_sigma_deg > 0
        self._h_compass[CO] = 1.0 if self._estimate_offset else 0.0
        self._q_co = math.radians(config.compass.offset_walk_deg_per_s) ** 2  # rad² per s
        self._dev_on = config.compass.deviation_sigma_deg > 0
        self._q_dev = math.radians(config.compass.deviation_walk_deg_per_s) ** 2
        self._h_compass.flags.writeable = False

    # ------------------------------------------------------------------ read-outs
    @property
    def ready(self) -> bool:
        """True once a GPS fix and a compass sample have initialised the state."""
        return self._ready

    @property
    def t_s(self) -> float | None:
        """Time of the current state (s), ``None`` before any input."""
        return self._t

    @property
    def declination_deg(self) -> float:
        """The declination added to compass bearings (deg, east positive)."""
        return math.degrees(self._declination_rad)

    def set_declination_deg(self, declination_deg: float) -> None:
        """Change the declination (deg, east positive), e.g. from WMM once a fix is known."""
        if not math.isfinite(declination_deg):
            raise EstimatorError(f"declination_deg must be finite, got {declination_deg!r}")
        self._declination_rad = math.radians(declination_deg)

    @property
    def state(self) -> npt.NDArray[np.float64]:
        """A copy of the state vector (see the module docstring for units)."""
        return self._x.copy()

    @property
    def covariance(self) -> npt.NDArray[np.float64]:
        """A copy of the state covariance (units squared, as the state)."""
        return self._p.copy()

    def estimate(self) -> Estimate | None:
        """The current state as an :class:`Estimate`, ``None`` until :attr:`ready`."""
        if not self._ready or self._t is None:
            return None
        est = self._est
        if est is None:
            x = self._x.tolist()
            p = self._p
            est = self._est = Estimate(
                self._t,
                x[E],
                x[N],
                math.degrees(x[PSI]) % 360.0,
                x[V],
                math.degrees(x[W]),
                math.sqrt(max(p.item(E, E), 0.0)),
                math.sqrt(max(p.item(N, N), 0.0)),
                math.degrees(math.sqrt(max(p.item(PSI, PSI), 0.0))),
                x[KT],
                math.degrees(x[BA]),
                math.degrees(x[CO]),
                x[TS],
                math.degrees(_deviation(x[PSI], x[D1S : D2C + 1])),
            )
        return est

    # ------------------------------------------------------------------ time
    def _time(self, t_s: float, what: str) -> float | None:
        """The time to process an input at: ``t_s``, or the state's time when the input is a
        little late; ``None`` when it is too late (counted)."""
        t = float(t_s)
        if not math.isfinite(t):
            raise EstimatorError(f"{what}: t_s must be finite, got {t_s!r}")
        if self._t is None or t >= self._t:
            return t
        if self._t - t <= self.cfg.motion.max_late_s:
            return self._t
        self.stats.stale_dropped += 1
        return None

    def predict(self, t_s: float) -> Estimate | None:
        """Advance the state to ``t_s`` (s) without a measurement and return the estimate
        (``None`` until :attr:`ready`). Earlier times leave the state where it is."""
        t = float(t_s)
        if not math.isfinite(t):
            raise EstimatorError(f"predict: t_s must be finite, got {t_s!r}")
        self._predict_to(t)
        return self.estimate()

    def _predict_to(self, t: float) -> None:
        if self._t is None:
            self._t = t
            self._est = None
            return
        dt = t - self._t
        if dt <= 0:
            return
        self._est = None
        if self._ready:
            # Odometry drives the pose while its increments flow; when they stop (no
            # encoders, a silent board) the commanded drive takes over, if given.
            t_odo = self._t_odo
            self._odo_fresh = (
                self._odometry_mode
                and t_odo is not None
                and self._t - t_odo <= self.cfg.motion.odometry_timeout_s
            )
            steps = max(1, math.ceil(dt / self.cfg.motion.max_step_s))
            h = dt / steps
            for _ in range(steps):
                self._step(h)
        self._t = t

    def _step(self, h: float) -> None:
        """One time-only prediction step of ``h`` seconds (constant speed and yaw rate, or
        relaxing towards the commanded ones)."""
        # Plain floats from the state (numpy scalars do the same IEEE arithmetic, slower);
        # the covariance products stay numpy's, so the results are bit-identical.
        x, cfg = self._x, self.cfg
        xs = x.tolist()
        psi, v, w = xs[PSI], xs[V], xs[W]
        pm = psi + 0.5 * w * h
        s, c = math.sin(pm), math.cos(pm)
        f = _EYE.copy()
        q = np.zeros((NX, NX))  # the process noise, diagonal
        x[E] = xs[E] + v * h * s
        x[N] = xs[N] + v * h * c
        x[PSI] = _wrap(psi + w * h)
        f[E, PSI] = v * h * c
        f[E, V] = h * s
        f[E, W] = 0.5 * v * h * h * c
        f[N, PSI] = -v * h * s
        f[N, V] = h * c
        f[N, W] = -0.5 * v * h * h * s
        f[PSI, W] = h
        q_v = self._q_v * h
        q_w = self._q_w * h
        odo = cfg.odometry
        if odo is not None and self._odometry_mode:
            q[KT, KT] = odo.turn_scale_walk_per_s**2 * h
            q[BA, BA] = odo.drift_walk_rad_per_m_per_s**2 * h
            q[TS, TS] = odo.travel_scale_walk_per_s**2 * h
        q[E, E] = q[N, N] = self._q_v * h**3 / 3.0
        if self._estimate_offset:
            q[CO, CO] = self._q_co * h
        if self._dev_on:
            for i in _DEV:
                q[i, i] = self._q_dev * h
        cmd = cfg.command
        if cmd is not None and self._cmd is not None and not self._odo_fresh:
            # speed and yaw rate relax to the command; their error is Gauss-Markov
            a = math.exp(-h / cmd.tau_s) if cmd.tau_s > 0 else 0.0
            v_c, w_c = self._cmd
            x[V] = v_c + (v - v_c) * a
            x[W] = w_c + (w - w_c) * a
            f[V, V] = a
            f[W, W] = a
            g = math.exp(-2.0 * h / cmd.error_tau_s)
            q_v += cmd.sigma_speed_mps**2 * (1.0 - g)
            q_w += math.radians(cmd.sigma_yaw_rate_dps) ** 2 * (1.0 - g)
        q[V, V] = q_v
        q[W, W] = q_w
        tau_b = cfg.gps.correlation_s
        if tau_b is not None:
            phi = math.exp(-h / tau_b)
            x[BE] = xs[BE] * phi
            x[BN] = xs[BN] * phi
            f[BE, BE] = f[BN, BN] = phi
            q[BE, BE] = q[BN, BN] = self._bias_var_m2 * (1.0 - phi * phi)
        self._p = f @ self._p @ f.T + q

    # ------------------------------------------------------------------ inputs
    def on_odometry(
        self, t_s: float, d_left_m: float, d_right_m: float, slip_m: float = 0.0
    ) -> None:
        """Wheel travel (m, forward positive) on each side since the previous increment, which
        ended at ``t_s`` (s). Mode ODOMETRY only. ``slip_m`` (m²/m) is added to each side's
        ``k_*_m`` for this increment: the travel's extra uncertainty on a slope."""
        odo = self.cfg.odometry
        if self.cfg.mode != Mode.ODOMETRY or odo is None:
            raise EstimatorError("on_odometry needs mode odometry")
        dl, dr = float(d_left_m), float(d_right_m)
        if not (math.isfinite(dl) and math.isfinite(dr)):
            raise EstimatorError(
                f"odometry increments must be finite, got {d_left_m!r}, {d_right_m!r}"
            )
        t1 = float(t_s)
        if not math.isfinite(t1):
            raise EstimatorError(f"odometry: t_s must be finite, got {t_s!r}")
        self._est = None
        t0 = self._t_odo
        if self._odo_held is not None:  # a short one held back: its travel goes with this one
            dl, dr, slip_m = (
                dl + self._odo_held[0],
                dr + self._odo_held[1],
                max(slip_m, self._odo_held[2]),
            )
            self._odo_held = None
        if self._ready and t0 is not None and len(self._odo_spans) >= 3:
            short_s = ODO_SHORT_SPAN_FRACTION * sorted(self._odo_spans)[len(self._odo_spans) // 2]
            if 0.0 <= t1 - t0 < short_s:
                self._odo_held = (dl, dr, slip_m)
                self.odometry_merged += 1
                return
        self._t_odo = t1 if t0 is None else max(t0, t1)
        if t0 is None or t1 <= t0:
            t0 = self._t if self._t is not None and self._t < t1 else t1
        span = t1 - t0
        if 0.0 < span <= self.cfg.motion.odometry_timeout_s:
            self._odo_spans.append(span)
        if self._t is None:
            self._t = t1
        if not self._ready:
            self._t = max(self._t, t1)
            return
        # Between increments the state was (and up to t1 now is) extrapolated with the speed
        # and yaw rate of the previous increment. The increment replaces that guess over its
        # span by what the wheels measured: the correction is the measured motion minus
        # V·span and W·span. (Applying only the part after the state's time, as a first
        # version did, lets the yaw rate lag one increment behind the wheels: the compass then
        # only ever sees the turns stop late, never start late, and biases turn_scale to 0.)
        self._predict_to(t1)
        if span > self.cfg.motion.odometry_timeout_s:
            # after a silence the commanded drive predicted the motion: the wheels' total
            # cannot be split against it, so only their latest rates are taken
            dl_rate, dr_rate = dl, dr
            dl = dr = 0.0
        else:
            dl_rate, dr_rate = dl, dr
        x = self._x
        xs = x.tolist()  # plain floats: the same IEEE arithmetic as numpy scalars, faster
        kt, ba, ts = xs[KT], xs[BA], xs[TS]
        ds_wheels = 0.5 * (dl + dr)
        ds = ts * ds_wheels
        diff = (dl - dr) / odo.track_m  # the wheels' heading change, rad
        dpsi = kt * diff + ba * ds
        ds_corr = ds - xs[V] * span
        psi = _wrap(xs[PSI] + dpsi - xs[W] * span)
        x[PSI] = psi
        pm = psi - 0.5 * dpsi  # mid-increment heading, for the along-track correction
        s, c = math.sin(pm), math.cos(pm)
        x[E] = xs[E] + ds_corr * s
        x[N] = xs[N] + ds_corr * c
        f = _EYE.copy()
        f[PSI, W] = -span
        f[PSI, KT] = diff
        f[PSI, BA] = ds
        f[PSI, TS] = ba * ds_wheels
        f[E, V] = -span * s
        f[N, V] = -span * c
        f[E, PSI] = ds_corr * c
        f[N, PSI] = -ds_corr * s
        f[E, TS] = ds_wheels * s
        f[N, TS] = ds_wheels * c
        # Jacobian of the pose wrt the wheel travels (a, b) and their covariance (seed 003)
        g_a = kt / odo.track_m + 0.5 * ba * ts  # d dpsi / d a
        g_b = -kt / odo.track_m + 0.5 * ba * ts
        j = np.zeros((NX, 2))
        j[E, 0] = j[E, 1] = 0.5 * ts * s
        j[N, 0] = j[N, 1] = 0.5 * ts * c
        j[PSI, 0] = g_a
        j[PSI, 1] = g_b
        k_l, k_r = odo.k_left_m + slip_m, odo.k_right_m + slip_m
        su = np.array([[k_l * abs(dl), 0.0], [0.0, k_r * abs(dr)]])  # diag
        p = f @ self._p @ f.T + j @ su @ j.T
        p[PSI, PSI] += odo.k_slip_rad * abs(dpsi)
        # speed and yaw rate from the whole increment's rates
        dl, dr = dl_rate, dr_rate
        if span > 0:
            x[V] = ts * 0.5 * (dl + dr) / span
            x[W] = (kt * (dl - dr) / odo.track_m + ba * ts * 0.5 * (dl + dr)) / span
            var_v = 0.25 * ts * ts * (k_l * abs(dl) + k_r * abs(dr)) / span**2
            var_w = (k_l * abs(dl) + k_r * abs(dr)) / (odo.track_m * span) ** 2
            var_w += odo.k_slip_rad * abs(dl - dr) / odo.track_m / span**2
            p[V, :] = p[:, V] = 0.0
            p[V, V] = var_v + self._q_v * span
            # W only extrapolates until the next increment replaces the guess: it carries no
            # correlation with the calibration states, which learn from the measured
            # increments alone (through f[PSI, KT], f[PSI, BA], f[E/N, TS] above)
            p[W, :] = p[:, W] = 0.0
            p[W, W] = var_w + self._q_w * span
        self._p = 0.5 * (p + p.T)
        self._t = max(self._t, t1)

    def on_command(self, t_s: float, left_pct: float, right_pct: float) -> None:
        """The drive commanded at ``t_s`` (s), percent per side (with :class:`CommandParams`;
        ignored otherwise). In mode ODOMETRY it drives the prediction only while no odometry
        increment came for ``motion.odometry_timeout_s``."""
        cmd = self.cfg.command
        if cmd is None:
            return
        t = self._time(t_s, "command")
        if t is None:
            return
        self._predict_to(t)
        lp, rp = float(left_pct), float(right_pct)
        if not (math.isfinite(lp) and math.isfinite(rp)):
            raise EstimatorError(f"command must be finite, got {left_pct!r}, {right_pct!r}")
        self._cmd = (
            0.5 * (lp + rp) * cmd.speed_mps_per_pct,
            math.radians(0.5 * (lp - rp) * cmd.yaw_rate_dps_per_pct),
        )

    def on_compass(self, t_s: float, magnetic_bearing_deg: float) -> Update:
        """A compass sample: the MAGNETIC bearing (deg) read at ``t_s`` (s)."""
        t = self._time(t_s, "compass")
        if t is None:
            return Update(False, math.nan, "stale")
        self._est = None
        b = float(magnetic_bearing_deg)
        if not math.isfinite(b):
            raise EstimatorError(f"bearing must be finite, got {magnetic_bearing_deg!r}")
        z = _wrap(math.radians(b) + self._declination_rad)
        self._predict_to(t)
        cp = self.cfg.compass
        if not self._ready:
            self._pending_heading = (t, z)
            self._try_init()
            return Update(True, math.nan, "init")
        x = self._x
        lag = cp.lag_s
        psi, w, co = x.item(PSI), x.item(W), x.item(CO)
        r = math.radians(cp.sigma_deg) ** 2 + (cp.lag_uncertainty * lag * w) ** 2
        h = self._h_compass
        dev = 0.0
        if self._dev_on:  # the deviation card's first two harmonics, at the heading
            s1, c1 = math.sin(psi), math.cos(psi)
            s2, c2 = 2.0 * s1 * c1, c1 * c1 - s1 * s1
            a1, b1, a2, b2 = (x.item(i) for i in _DEV)
            dev = a1 * s1 + b1 * c1 + a2 * s2 + b2 * c2
            h = h.copy()
            h[PSI] = 1.0 + a1 * c1 - b1 * s1 + 2.0 * (a2 * c2 - b2 * s2)
            h[D1S], h[D1C], h[D2S], h[D2C] = s1, c1, s2, c2
        y = _wrap(z - (psi - lag * w + co + dev))
        ph = self._p @ h
        s = float(h @ ph) + r
        nis = y * y / s
        if nis > self.cfg.gating.compass_chi2:
            self._compass_refused.append((y, s))
            if self._compass_consistent():
                self._compass_refused.clear()
                self.stats.compass_resets += 1
                x[PSI] = _wrap(z + lag * w - co - dev)
                p_co = self._p[CO, CO]
                self._p[PSI, :] = self._p[:, PSI] = 0.0
                self._p[PSI, PSI] = r + lag * lag * self._p[W, W] + p_co
                self._p[PSI, CO] = self._p[CO, PSI] = -p_co  # read through the offset
                return Update(True, nis, "reset")
            self.stats.compass_rejected += 1
            return Update(False, nis, "gated")
        self._compass_refused.clear()
        kg = ph / s
        x += kg * y
        x[PSI] = _wrap(x[PSI])
        x[CO] = _wrap(x[CO])
        self._joseph(kg[:, None], h[None, :], np.array([[r]]))
        self.stats.compass_accepted += 1
        return Update(True, nis, "ok")

    def _compass_consistent(self) -> bool:
        n = self.cfg.gating.compass_recover_after
        if len(self._compass_refused) < n:
            return False
        ys = [y for y, _ in self._compass_refused]
        ref = ys[-1]
        d = [_wrap(y - ref) for y in ys]
        mean = ref + sum(d) / len(d)
        gate = self.cfg.gating.compass_chi2
        return all(_wrap(y - mean) ** 2 / s <= gate for y, s in self._compass_refused)

    def on_gps(self, t_s: float, east_m: float, north_m: float, dop: float) -> Update:
        """A GPS fix at ``t_s`` (s), projected to the local plane (east, north metres), with
        its horizontal dilution of precision ``dop`` (HDOP, dimensionless)."""
        t = self._time(t_s, "gps")
        if t is None:
            return Update(False, math.nan, "stale")
        self._est = None
        ze, zn, dp = float(east_m), float(north_m), float(dop)
        if not (math.isfinite(ze) and math.isfinite(zn)):
            raise EstimatorError(f"fix must be finite, got {east_m!r}, {north_m!r}")
        if not (math.isfinite(dp) and dp > 0):
            raise EstimatorError(f"dop must be a finite number > 0, got {dop!r}")
        self._predict_to(t)
        g = self.cfg.gps
        at = (self._x[E], self._x[N]) if self._ready else (ze, zn)
        lce = float(g.lce_m(float(at[0]), float(at[1]))) if g.lce_m is not None else 0.0
        if not (math.isfinite(lce) and lce >= 0):
            raise EstimatorError(f"LCE lookup must give a finite number >= 0 m, got {lce!r}")
        correlated = g.correlation_s is not None
        self.stats.noise_hdop1_m = math.sqrt(g.re_m**2 + g.ase_m**2 + lce * lce)
        slow_var = dp * dp * (g.ase_m**2 + lce * lce)  # m², the ASE + LCE part
        white_var = dp * dp * g.re_m**2 if correlated else dp * dp * g.re_m**2 + slow_var
        if correlated:
            self._bias_var_m2 = slow_var
            self._bias_env_m2 = max(self._bias_env_m2, slow_var)
        if not self._ready:
            self._pending_fix = (t, ze, zn, white_var)
            self._try_init()
            return Update(True, math.nan, "init")
        x = self._x
        hm = np.zeros((2, NX))
        hm[0, E] = hm[1, N] = 1.0
        if correlated:
            hm[0, BE] = hm[1, BN] = 1.0
        rm = np.eye(2) * white_var
        z = np.array([ze, zn])
        y = z - hm @ x
        pht = self._p @ hm.T
        s = hm @ pht + rm
        s_inv = np.linalg.inv(s)
        nis = float(y @ s_inv @ y)
        if nis > self.cfg.gating.gps_chi2:
            self._gps_refused.append((t, y, s))
            agree = self._gps_agreement()
            if agree is not None:
                self.stats.odometry_runaway_resets += agree == "drift"
                return self._gps_reset(t, ze, zn, white_var, nis, agree)
            self.stats.gps_rejected += 1
            self.stats.gps_consecutive_rejected += 1
            return Update(False, nis, "gated")
        self._gps_refused.clear()
        self.stats.gps_consecutive_rejected = 0
        kg = pht @ s_inv
        x += kg @ y
        x[PSI] = _wrap(x[PSI])
        self._joseph(kg, hm, rm)
        if correlated:
            self._bound_bias(t)
            if self._bias_runaway():
                self.stats.bias_runaway_resets += 1
                return self._gps_reset(t, ze, zn, white_var, nis, "bias")
        self.stats.gps_accepted += 1
        return Update(True, nis, "ok")

    def _gps_reset(
        self, t: float, ze: float, zn: float, white_var: float, nis: float, why: str
    ) -> Update:
        """Put the position on the fix (``why``: "step", "drift" or "bias"), counted."""
        x = self._x
        self._gps_refused.clear()
        self.stats.gps_resets += 1
        self.stats.gps_consecutive_rejected = 0
        self.stats.last_reset_m = math.hypot(ze - x[E], zn - x[N])
        self.stats.last_reset_reason = why
        self.stats.last_reset_circle_m = self._position_circle_m()
        self._reset_position(ze, zn, white_var)
        self._bias_moving = np.zeros(2)
        self._t_gps_reset = t
        return Update(True, nis, "reset")

    def _position_circle_m(self) -> float:
        """Radius (m) of the position's 99 % ellipse along its long axis (2 d.o.f.)."""
        pe = self._p[np.ix_((E, N), (E, N))]
        long_var = float(np.linalg.eigvalsh(0.5 * (pe + pe.T))[-1])
        return math.sqrt(CHI2_2DOF_99 * max(long_var, 0.0))

    def _bias_runaway(self) -> bool:
        """While the robot stands still, the GPS bias states moved more than
        :data:`BIAS_RUNAWAY_CHI2` of the largest recent stationary variance since the latest
        fix taken while it moved: the robot moved while its wheels stood still (carried
        slowly, pushed, on a trailer). Each fix came inside the gate then, at any GPS rate,
        and the filter explained the move as slow GPS error: carried 70 m at 1 m/s while
        idle, the estimate ended 33 m short (the bias 20 σ_b) with σ reading 2.2 m."""
        x = self._x
        if abs(float(x[V])) >= STILL_MPS:
            self._bias_moving = np.array([x[BE], x[BN]])
            return False
        bv = self._bias_env_m2
        d = np.array([x[BE], x[BN]]) - self._bias_moving
        return bv > 0.0 and float(d @ d) > BIAS_RUNAWAY_CHI2 * bv

    def _gps_agreement(self) -> str | None:
        """How the last ``recover_after`` refused fixes agree, if they do: "step" (with their
        mean), "drift" (with a straight line in time through them whose slope runs along the
        heading, within :data:`DRIFT_ALONG_DEG`), else None. Only along: the travel counted
        wrong moves the fixes ahead of (or behind) the prediction; a drift across the heading
        is the heading that is wrong (a compass 90 deg off), which resets would hide from
        the off-course check while the robot steers on it."""
        refused = self._gps_refused
        if len(refused) < self.cfg.gating.recover_after:
            return None
        gate = self.cfg.gating.gps_chi2
        ts = np.array([t for t, _, _ in refused])
        ys = np.array([y for _, y, _ in refused])
        mean = ys.mean(axis=0)

        def inside(centres: npt.NDArray[np.float64]) -> bool:
            return all(
                float((y - c) @ np.linalg.solve(s, y - c)) <= gate
                for (_, y, s), c in zip(refused, centres, strict=True)
            )

        if inside(np.broadcast_to(mean, ys.shape)):
            return "step"
        dt = ts - ts.mean()
        if float(dt @ dt) > 0.0:
            slope = (dt @ (ys - mean)) / float(dt @ dt)  # m/s per axis
            along = abs(math.sin(self._x[PSI]) * slope[0] + math.cos(self._x[PSI]) * slope[1])
            if along >= DRIFT_ALONG_COS * float(np.hypot(*slope)) and inside(
                mean + np.outer(dt, slope)
            ):
                return "drift"
        return None

    # ------------------------------------------------------------------ helpers
    def _propagate_bias(self, h: float) -> None:
        """The GPS bias states' Gauss-Markov step over ``h`` seconds (the rest of the state
        is moved by the odometry increment)."""
        tau_b = self.cfg.gps.correlation_s
        if tau_b is None:
            return
        phi = math.exp(-h / tau_b)
        self._est = None
        x, p = self._x, self._p
        for i in (BE, BN):
            x[i] *= phi
            p[i, :] *= phi
            p[:, i] *= phi
            p[i, i] += self._bias_var_m2 * (1.0 - phi * phi)
        self._bias_env_m2 = self._bias_env_m2 * phi * phi + self._bias_var_m2 * (1.0 - phi * phi)
        self._bias_moving *= phi  # what is left of it, as the bias forgets

    def _bound_bias(self, t: float) -> None:
        """Within ``correlation_s`` after a GPS reset (time ``t``, s), move the part of the
        GPS bias beyond :data:`BIAS_BOUND_CHI2` of its stationary variance into the position.
        After a reset onto multipath fixes (position on the fix, bias 0) the fixes coming
        back to the truth were explained as a bias of 10 m (6 σ_b) while odometry held the
        position 9-16 m off for over a minute, σ reading 3 m: the fixes see only the sum, and
        the reset's "bias 0" is the assumption that failed, which the Gauss-Markov bias
        forgets over its correlation time. The fix's prediction (position + bias) is kept;
        the moved part ``m`` becomes the split's uncertainty (``m mᵀ`` on the position and on
        the bias, ``−m mᵀ`` between them), so σ covers the position it may still lack."""
        tau_b = self.cfg.gps.correlation_s
        if self._t_gps_reset is None or tau_b is None or t - self._t_gps_reset > tau_b:
            return
        bv = self._bias_var_m2
        x = self._x
        be, bn = float(x[BE]), float(x[BN])
        b2 = be * be + bn * bn
        if bv <= 0.0 or b2 <= BIAS_BOUND_CHI2 * bv:
            return
        f = 1.0 - math.sqrt(BIAS_BOUND_CHI2 * bv / b2)
        m = np.array([be * f, bn * f])  # m, moved from the bias to the position
        x[E] += m[0]
        x[N] += m[1]
        x[BE] -= m[0]
        x[BN] -= m[1]
        mm = np.outer(m, m)
        p = self._p
        pos, bias = slice(E, N + 1), slice(BE, BN + 1)
        p[pos, pos] += mm
        p[bias, bias] += mm
        p[pos, bias] -= mm
        p[bias, pos] -= mm
        self.stats.gps_bias_bounded += 1

    def _joseph(
        self, k: npt.NDArray[np.float64], h: npt.NDArray[np.float64], r: npt.NDArray[np.float64]
    ) -> None:
        ikh = _EYE - k @ h
        p = ikh @ self._p @ ikh.T + k @ r @ k.T
        self._p = 0.5 * (p + p.T)

    def _reset_position(self, ze: float, zn: float, white_var: float) -> None:
        """Put the position on a fix: bias 0 with its stationary variance, position = fix
        with the fix's total variance (correlated with the bias as z = p + b + noise)."""
        x, p = self._x, self._p
        for i in (E, N, BE, BN):
            p[i, :] = p[:, i] = 0.0
        x[E], x[N] = ze, zn
        x[BE] = x[BN] = 0.0
        bv = self._bias_var_m2 if self.cfg.gps.correlation_s is not None else 0.0
        for pi, bi in ((E, BE), (N, BN)):
            p[pi, pi] = white_var + bv
            p[bi, bi] = bv
            p[pi, bi] = p[bi, pi] = -bv

    def _try_init(self) -> None:
        if self._pending_fix is None or self._pending_heading is None:
            return
        self._est = None
        _, ze, zn, white_var = self._pending_fix
        _, psi = self._pending_heading
        self._x[:] = 0.0
        self._p[:] = 0.0
        self._reset_position(ze, zn, white_var)
        self._x[PSI] = psi
        self._p[PSI, PSI] = math.radians(self.cfg.compass.sigma_deg) ** 2
        if self._estimate_offset:  # the first heading is read through the unknown offset
            var_co = math.radians(self.cfg.compass.offset_sigma_deg) ** 2
            self._p[CO, CO] = var_co
            self._p[PSI, PSI] += var_co
            self._p[PSI, CO] = self._p[CO, PSI] = -var_co
        if self._dev_on:  # ... and the unknown deviation at that heading
            var_d = math.radians(self.cfg.compass.deviation_sigma_deg) ** 2
            s1, c1 = math.sin(psi), math.cos(psi)
            for i, g in zip(_DEV, (s1, c1, 2.0 * s1 * c1, c1 * c1 - s1 * s1), strict=True):
                self._p[i, i] = var_d
                self._p[PSI, PSI] += var_d * g * g
                self._p[PSI, i] = self._p[i, PSI] = -var_d * g
        self._p[V, V] = 1.0  # (m/s)²: unknown speed at start, up to the 1.1 m/s top speed
        self._p[W, W] = math.radians(30.0) ** 2
        self._x[KT] = self._x[TS] = 1.0  # the odometry calibration as configured ...
        odo = self.cfg.odometry
        if odo is not None and self.cfg.mode == Mode.ODOMETRY:  # ... and how far to trust it
            self._p[KT, KT] = odo.sigma_turn_scale**2
            self._p[BA, BA] = odo.sigma_drift_rad_per_m**2
            self._p[TS, TS] = odo.sigma_travel_scale**2
        self._ready = True
        self._pending_fix = self._pending_heading = None
