"""Wheel odometry, sans-IO: encoder counts -> wheel travel -> distance and heading change,
and the pose it dead-reckons with its covariance (seed 003, section 2.3).

Conventions are the house's: east/north metres, headings clockwise from north (the compass
sense), so the left side rolling further turns the robot clockwise:

    s_l = Δc_l · π · D_l / counts_per_rev        (likewise s_r)
    Δs  = (s_l + s_r) / 2        Δψ = (s_l − s_r) / B          (B: the EFFECTIVE track)

Non-systematic error (seed 003): the sides' travels are independent with variance
``k_l·|s_l|`` and ``k_r·|s_r|``; it is propagated through the differential-drive motion
model (mid-step heading ψm = ψ + Δψ/2; east += Δs·sin ψm, north += Δs·cos ψm):

    P' = F_x P F_xᵀ + F_u diag(k_l|s_l|, k_r|s_r|) F_uᵀ

``x6wd.nav.estimator`` runs the same model inside its Kalman filter from wheel travel in
metres; this module turns the counts into that travel with the calibrated
:class:`~x6wd.core.config.OdometryConfig`, and dead-reckons alone (no GPS) when asked.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from x6wd.core.config import OdometryConfig
from x6wd.core.records import WheelOdometry

Matrix3 = tuple[tuple[float, ...], ...]  # 3x3, row-major
ZERO3: Matrix3 = ((0.0, 0.0, 0.0), (0.0, 0.0, 0.0), (0.0, 0.0, 0.0))


def wheel_travel_m(
    cfg: OdometryConfig, d_left_counts: int, d_right_counts: int
) -> tuple[float, float]:
    """(left, right) wheel travel in metres, forward positive, for count increments."""
    per_count = math.pi / cfg.counts_per_rev
    return (
        d_left_counts * per_count * cfg.left_diameter_m,
        d_right_counts * per_count * cfg.right_diameter_m,
    )


@dataclass(frozen=True, slots=True)
class OdometryIncrement:
    """One increment: distance (m, forward positive) and heading change (deg, clockwise
    positive), the sides' travel (m), and the covariance of (distance m, heading change rad)
    from the non-systematic error."""

    distance_m: float
    heading_change_deg: float
    left_m: float
    right_m: float
    var_distance_m2: float
    var_heading_rad2: float
    cov_distance_heading_m_rad: float


def increment(cfg: OdometryConfig, d_left_counts: int, d_right_counts: int) -> OdometryIncrement:
    """Distance and heading change for count increments, with their covariance
    (``Var Δs = (q_l + q_r)/4``, ``Var Δψ = (q_l + q_r)/B²``, ``Cov = (q_l − q_r)/(2B)``,
    ``q = k·|s|``)."""
    left_m, right_m = wheel_travel_m(cfg, d_left_counts, d_right_counts)
    q_l, q_r = cfg.k_left_m * abs(left_m), cfg.k_right_m * abs(right_m)
    b = cfg.track_m
    return OdometryIncrement(
        distance_m=0.5 * (left_m + right_m),
        heading_change_deg=math.degrees((left_m - right_m) / b),
        left_m=left_m,
        right_m=right_m,
        var_distance_m2=0.25 * (q_l + q_r),
        var_heading_rad2=(q_l + q_r) / (b * b),
        cov_distance_heading_m_rad=0.5 * (q_l - q_r) / b,
    )


@dataclass(frozen=True, slots=True)
class OdometryPose:
    """Dead-reckoned pose at ``t_s``: east/north (m), heading (deg, clockwise from north,
    0..360), distance rolled (m, signed sum), and the 3x3 covariance of (east m, north m,
    heading rad)."""

    t_s: float
    east_m: float
    north_m: float
    heading_deg: float
    distance_m: float
    cov: Matrix3

    @property
    def sigma_heading_deg(self) -> float:
        """Standard deviation of the heading (deg)."""
        return math.degrees(math.sqrt(max(self.cov[2][2], 0.0)))


def _mul(a: Matrix3, b: Matrix3) -> Matrix3:
    return tuple(
        tuple(sum(a[i][k] * b[k][j] for k in range(3)) for j in range(3)) for i in range(3)
    )


def _t(a: Matrix3) -> Matrix3:
    return tuple(tuple(a[j][i] for j in range(3)) for i in range(3))


class DeadReckoning:
    """Integrates :class:`WheelOdometry` records into a pose and its covariance.

    The first record only sets the counts' baseline. The start pose is exact (zero
    covariance) unless ``cov`` is given.
    """

    def __init__(
        self,
        cfg: OdometryConfig,
        *,
        east_m: float = 0.0,
        north_m: float = 0.0,
        heading_deg: float = 0.0,
        cov: Matrix3 = ZERO3,
        t_s: float = 0.0,
    ) -> None:
        self.cfg = cfg
        self.pose = OdometryPose(t_s, east_m, north_m, heading_deg % 360.0, 0.0, cov)
        self._last: WheelOdometry | None = None

    def update(self, odo: WheelOdometry) -> OdometryPose:
        """Advance by the counts since the previous record; the new pose."""
        last, self._last = self._last, odo
        if last is None:
            self.pose = OdometryPose(odo.t_s, *_pose_tail(self.pose))
            return self.pose
        return self.apply(
            odo.t_s, odo.left_counts - last.left_counts, odo.right_counts - last.right_counts
        )

    def apply(self, t_s: float, d_left_counts: int, d_right_counts: int) -> OdometryPose:
        """Advance by count increments at ``t_s`` (s); the new pose."""
        p = self.pose
        inc = increment(self.cfg, d_left_counts, d_right_counts)
        ds, dpsi = inc.distance_m, math.radians(inc.heading_change_deg)
        psi = math.radians(p.heading_deg)
        pm = psi + 0.5 * dpsi
        s, c = math.sin(pm), math.cos(pm)
        b = self.cfg.track_m
        f_x: Matrix3 = ((1.0, 0.0, ds * c), (0.0, 1.0, -ds * s), (0.0, 0.0, 1.0))
        # d(east, north, psi) / d(s_l, s_r): Δs moves along ψm, Δψ = (s_l − s_r)/B turns it
        g = 0.5 * ds / b
        f_u = (
            (0.5 * s + g * c, 0.5 * s - g * c),
            (0.5 * c - g * s, 0.5 * c + g * s),
            (1.0 / b, -1.0 / b),
        )
        q = (self.cfg.k_left_m * abs(inc.left_m), self.cfg.k_right_m * abs(inc.right_m))
        noise = tuple(
            tuple(sum(f_u[i][k] * q[k] * f_u[j][k] for k in range(2)) for j in range(3))
            for i in range(3)
        )
        prop = _mul(_mul(f_x, p.cov), _t(f_x))
        cov = tuple(tuple(prop[i][j] + noise[i][j] for j in range(3)) for i in range(3))
        self.pose = OdometryPose(
            t_s,
            p.east_m + ds * s,
            p.north_m + ds * c,
            math.degrees(psi + dpsi) % 360.0,
            p.distance_m + ds,
            cov,
        )
        return self.pose


def _pose_tail(p: OdometryPose) -> tuple[float, float, float, float, Matrix3]:
    return p.east_m, p.north_m, p.heading_deg, p.distance_m, p.cov
