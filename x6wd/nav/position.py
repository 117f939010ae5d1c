"""Where the robot is: the position (and, for the EKF, the heading) the navigator steers by.

``[navigation] position_source`` picks one of three, all sans-IO (times come with the inputs):

- ``"ekf"`` (the default): :class:`EkfSource`, the :mod:`x6wd.nav.estimator` EKF fusing the
  fixes (noise ``HDOP·sqrt(RE² + ASE² + LCE²)`` from ``[gnss_noise]``), the compass (its lag
  and the declination) and the wheel odometry (``[odometry]``); while no encoder counts arrive
  it predicts from the commanded drive. It gives the heading too, so the compass's 640 ms lag
  no longer makes the robot overshoot its turns.
- ``"constellation"``: :class:`ConstellationSource`, the paper's filter per axis over the last
  ``filter_n`` fixes, reset at each mission start. On a moving robot it returns a position up
  to ``filter_n`` fixes old (docs/navigation.md, "The paper's filter on a moving robot").
- ``"raw"``: :class:`RawSource`, the latest valid fix.

The constellation and raw sources leave the heading to the compass (``heading_deg`` returns
None). Every source answers ``position(t_s)`` with (lat_deg, lon_deg) or None before it has one.
"""

from __future__ import annotations

import math
from typing import Any, NamedTuple, Protocol

from x6wd.core.config import GnssNoiseConfig, NavigationConfig, OdometryConfig
from x6wd.core.records import GpsFix, WheelOdometry
from x6wd.nav import estimator as ekf
from x6wd.nav.constellation import Constellation
from x6wd.nav.geo import LocalTangentPlane
from x6wd.nav.odometry import wheel_travel_m

DEFAULT_HDOP = 2.0
"""HDOP assumed for a fix that carries none (a GGA with an empty field)."""
SLOPE_MIN_DEG = 2.0
"""Below this pitch (deg) the ground counts as level: the compass's tilt noise changes
nothing, and a level robot's estimate is the same as without the slope terms."""
SLOPE_MAX_DEG = 60.0
"""Above this pitch (deg) the reading is no slope a wheeled robot drives (a knock, a fall)."""
SLOPE_SLIP_M = 10.0
"""Extra variance of each wheel's travel per metre on a slope, per sin^2(pitch) (m^2/m):
skid-steer wheels slip uphill or down by an amount nobody calibrated, so on a slope the GPS
leads. Without it the EKF trusted the wheels and ran 1.5-2 m worse than the raw fixes on a
30 %/20 % slope (an outside check). Chosen on the simulator (shipped config, 5 seeds, a
40 m square; mean filtered error against raw 2.85 m): 8 %/5 % slope 3.15 m without, 2.96
with 3.0, 2.88 with 10; 30 %/20 % 3.30 / 3.01 / 2.86; 50 %/30 % 3.28 / 2.96 / 2.84 m."""
MAX_INCREMENT_M = 5.0
"""A wheel travelling further than this between two encoder readings (m; 50 ms apart at
20 Hz) is a board reset or a corrupt reading: the increment is dropped and counted."""


UNCERTAIN_HDOP = 3.0
"""A sky partly blocked: the EKF's position counts as degraded only beyond the error radius
the configured GPS noise gives at this HDOP (:func:`degraded_radius_m`). A site calibrated
with LCE cells of 5-10 m is 16-31 m uncertain at HDOP 1, under an open sky."""


def degraded_radius_m(arrival_max_error_m: float, noise_hdop1_m: float) -> float:
    """The EKF's error radius (m, 3 sigma per axis) beyond which its position counts as
    degraded (poor geometry, not the site's usual noise): ``arrival_max_error_m`` (m) or,
    where larger, 3 sigma of the configured noise at :data:`UNCERTAIN_HDOP`
    (``noise_hdop1_m``: its per-axis sigma at HDOP 1, m)."""
    return max(arrival_max_error_m, 3.0 * UNCERTAIN_HDOP * noise_hdop1_m)


class Jump(NamedTuple):
    """A source's position moved at once (its EKF reset onto fixes it had refused)."""

    moved_m: float  # how far (m)
    # the radius (m) the source's own uncertainty allowed just before (its 99 % ellipse's long
    # axis) when that was degraded (beyond degraded_radius_m: poor geometry, a start on 4
    # satellites): a move within it is the estimate settling, not a surprise. 0 otherwise,
    # and for a move the source holds for a carry (fixes that moved while the wheels stood)
    # or where the noise model alone makes the ellipse wide (a site's LCE of 10 m: a GPS back
    # 40 m away must still pause)
    expected_m: float

    @property
    def surprise(self) -> bool:
        """Farther than the source said it might be off."""
        return self.moved_m > self.expected_m


class PositionSource(Protocol):
    """What the controller asks of a position source (see the module docstring)."""

    def on_fix(self, fix: GpsFix) -> None:
        """A usable fix (valid, coordinates present and in range)."""

    def on_compass(self, t_s: float, bearing_mag_deg: float) -> bool | None:
        """A usable compass sample: magnetic bearing (deg) at ``t_s`` (s). True or False:
        the source took or refused it (the EKF's gate); None: it does not judge this one."""

    def on_odometry(self, rec: WheelOdometry, pitch_deg: float = 0.0) -> None:
        """Cumulative encoder counts at ``rec.t_s`` (s); ``pitch_deg``: the body's pitch
        then (deg, from the compass; 0 when unknown)."""

    def on_command(self, t_s: float, left_pct: float, right_pct: float) -> None:
        """The drive (%) commanded from ``t_s`` (s)."""

    def set_declination_deg(self, declination_deg: float) -> None:
        """The declination (deg, east positive) changed."""

    def reset(self) -> None:
        """A mission starts."""

    def position(self, t_s: float) -> tuple[float, float] | None:
        """(lat_deg, lon_deg) at ``t_s`` (s), or None before the first fix."""

    def heading_deg(self, t_s: float) -> float | None:
        """True heading (deg, clockwise from north, [0, 360)) or None: use the compass."""

    def extra(self) -> dict[str, Any]:
        """Figures for the telemetry's ``extra``."""

    def take_jump(self) -> Jump | None:
        """The largest move of the source's position at once since last asked, to fixes it
        had refused until they agreed (the EKF's reset), or None: none since then."""

    def fixes_taken(self) -> tuple[int, float | None]:
        """(count, t_s): how many fixes the source took into its estimate as agreeing with
        it, and the time (s) of the latest fix it judged when it took that one, else None.
        The EKF takes a fix inside its gate; one it refused, reset on, started on (the
        estimate is then that fix: nothing agreed with it) or dropped as too late is not
        taken (a late one leaves the time as it was: it judged nothing). The raw and
        Constellation sources take every fix."""


class RawSource:
    """The latest valid fix, as it came."""

    def __init__(self) -> None:
        self._pos: tuple[float, float] | None = None
        self._taken: tuple[int, float | None] = (0, None)

    def on_fix(self, fix: GpsFix) -> None:
        assert fix.lat_deg is not None and fix.lon_deg is not None
        self._pos = (fix.lat_deg, fix.lon_deg)
        self._took(fix.t_s)

    def _took(self, t_s: float) -> None:
        self._taken = (self._taken[0] + 1, t_s)

    def fixes_taken(self) -> tuple[int, float | None]:
        return self._taken

    def on_compass(self, t_s: float, bearing_mag_deg: float) -> bool | None:
        return None

    def on_odometry(self, rec: WheelOdometry, pitch_deg: float = 0.0) -> None:
        return None

    def on_command(self, t_s: float, left_pct: float, right_pct: float) -> None:
        return None

    def set_declination_deg(self, declination_deg: float) -> None:
        return None

    def reset(self) -> None:
        return None

    def position(self, t_s: float) -> tuple[float, float] | None:
        return self._pos

    def heading_deg(self, t_s: float) -> float | None:
        return None

    def extra(self) -> dict[str, Any]:
        return {}

    def take_jump(self) -> Jump | None:
        return None  # every fix is taken as it comes: no estimate of its own to jump


class ConstellationSource(RawSource):
    """The paper's Constellation filter on latitude and longitude separately."""

    def __init__(self, n: int, hysteresis: bool) -> None:
        super().__init__()
        self._n, self._hysteresis = n, hysteresis
        self._latest: tuple[float, float] | None = None
        self.reset()

    def reset(self) -> None:
        # At a mission start: the window must not hold fixes from where the robot stood
        # before it was carried or driven to the start; it restarts from the latest fix.
        self._lat = Constellation(self._n, self._hysteresis)
        self._lon = Constellation(self._n, self._hysteresis)
        self._lon_ref: float | None = None  # the window's first longitude (deg)
        latest, self._pos = self._latest, None
        if latest is not None:
            self._add(*latest)

    def _add(self, lat_deg: float, lon_deg: float) -> None:
        self._latest = (lat_deg, lon_deg)
        self._lat.add(lat_deg)
        # The filter averages and compares longitudes as plain numbers: across the 180th
        # meridian they are made continuous with the window's first one (+-360 only there,
        # so every other fix goes in bit for bit), and the output wrapped back.
        if self._lon_ref is None:
            self._lon_ref = lon_deg
        if lon_deg - self._lon_ref > 180.0:
            lon_deg -= 360.0
        elif lon_deg - self._lon_ref < -180.0:
            lon_deg += 360.0
        self._lon.add(lon_deg)
        # filter() once per sample: with hysteresis it is stateful.
        lon_out = self._lon.filter()
        if lon_out > 180.0:
            lon_out -= 360.0
        elif lon_out <= -180.0:
            lon_out += 360.0
        self._pos = (self._lat.filter(), lon_out)

    def on_fix(self, fix: GpsFix) -> None:
        assert fix.lat_deg is not None and fix.lon_deg is not None
        self._add(fix.lat_deg, fix.lon_deg)
        self._took(fix.t_s)

    def extra(self) -> dict[str, Any]:
        return {"filter_samples": len(self._lat)}


def estimator_config(
    nav: NavigationConfig,
    odometry: OdometryConfig,
    gnss: GnssNoiseConfig,
    declination_deg: float,
    lce_m: Any = None,
) -> ekf.EstimatorConfig:
    """The EKF's parameters from the robot's configuration (``lce_m``: the LCE lookup in the
    filter's own plane, east/north m -> m, or None)."""
    full_mps = nav.full_speed_mps
    return ekf.EstimatorConfig(
        mode=ekf.Mode.ODOMETRY,
        odometry=ekf.OdometryParams(
            track_m=odometry.track_m,
            k_left_m=odometry.k_left_m,
            k_right_m=odometry.k_right_m,
            k_slip_rad=odometry.k_slip_rad,
        ),
        command=ekf.CommandParams(
            speed_mps_per_pct=full_mps / 100.0,
            # T = 2·v_full / w_full (steer_track_m), so w_full = 2·v_full / T
            yaw_rate_dps_per_pct=math.degrees(2.0 * full_mps / nav.steer_track_m) / 100.0,
        ),
        compass=ekf.CompassParams(
            lag_s=nav.compass_lag_s,
            declination_deg=declination_deg,
            offset_sigma_deg=nav.compass_offset_sigma_deg,
            deviation_sigma_deg=nav.compass_deviation_sigma_deg,
        ),
        gps=ekf.GpsParams(
            re_m=gnss.re_m,
            ase_m=gnss.ase_m,
            lce_m=lce_m,
            correlation_s=gnss.correlation_s if gnss.correlation_s > 0 else None,
        ),
    )


RUNAWAY_WARN_RESETS = 3
"""Position resets by the EKF's drift rule (the fixes running steadily ahead of, or behind,
the wheels' count) after which the telemetry's ``odometry_warning`` questions the wheels'
calibration (the runner logs it once): one can be a slipping stretch, three in a mission are
a wheel size or a counts per turn set wrong (the drift rule's audit: 3-4 resets with counts
of 10-50 %, 17-19 on a 390 m route at 10 %, none with counts of 75-133 %)."""


def runaway_warning(resets: int) -> str:
    """The operator's warning after ``resets`` odometry-runaway resets."""
    return (
        f"the fixes ran steadily away from the wheels' count ({resets} position resets):"
        " check [odometry] wheel diameters and counts per turn (x6wd calibrate odometry)"
    )


class EkfSource:
    """The EKF in a local tangent plane at the first usable fix."""

    def __init__(
        self,
        nav: NavigationConfig,
        odometry: OdometryConfig,
        gnss: GnssNoiseConfig,
        declination_deg: float,
    ) -> None:
        self._nav, self._odo_cfg, self._gnss = nav, odometry, gnss
        self._decl = declination_deg
        self._plane: LocalTangentPlane | None = None
        self._ekf: ekf.Estimator | None = None
        self._jump: Jump | None = None  # the largest reset since take_jump last asked
        self._last_jump: Jump | None = None  # the latest reset (status)
        # fixes the EKF took inside its gate, and the latest judged fix's time if taken
        self._taken: tuple[int, float | None] = (0, None)
        self._counts: tuple[int, int] | None = None
        self._odo_t: float | None = None
        self.odometry_dropped = 0

    def _lce(self) -> Any:
        g = self._gnss
        if not g.lce_cells and g.lce_default_m == 0.0:
            return None
        plane = self._plane
        assert plane is not None
        if not g.lce_cells:
            return lambda _e, _n: g.lce_default_m
        # the map has its own plane: filter plane -> lat/lon -> map plane
        assert g.lce_origin_lat_deg is not None and g.lce_origin_lon_deg is not None
        mp = LocalTangentPlane(g.lce_origin_lat_deg, g.lce_origin_lon_deg)

        def lce(e_m: float, n_m: float) -> float:
            lat, lon = plane.to_latlon(e_m, n_m)
            me, mn = mp.to_xy(lat, lon)
            return g.lce_m_at(float(me), float(mn))

        return lce

    def on_fix(self, fix: GpsFix) -> None:
        assert fix.lat_deg is not None and fix.lon_deg is not None
        if self._ekf is None:
            self._plane = LocalTangentPlane(fix.lat_deg, fix.lon_deg)
            self._ekf = ekf.Estimator(
                estimator_config(self._nav, self._odo_cfg, self._gnss, self._decl, self._lce())
            )
        assert self._plane is not None
        e, n = self._plane.to_xy(fix.lat_deg, fix.lon_deg)
        hdop = fix.hdop if fix.hdop is not None and fix.hdop > 0 else DEFAULT_HDOP
        reason = self._ekf.on_gps(fix.t_s, float(e), float(n), hdop).reason
        if reason == "ok":
            self._taken = (self._taken[0] + 1, fix.t_s)
        elif reason != "stale":  # refused, a reset, or the fix the EKF starts on
            self._taken = (self._taken[0], None)
        if reason == "reset":
            st = self._ekf.stats
            carry = st.last_reset_reason == "bias"  # fixes moved while the wheels stood
            circle_m = st.last_reset_circle_m
            degraded_m = degraded_radius_m(self._nav.arrival_max_error_m, st.noise_hdop1_m)
            expected = circle_m > degraded_m and not carry
            jump = self._last_jump = Jump(st.last_reset_m, circle_m if expected else 0.0)
            if self._jump is None or jump.moved_m > self._jump.moved_m:
                self._jump = jump

    def take_jump(self) -> Jump | None:
        jump, self._jump = self._jump, None
        return jump

    def fixes_taken(self) -> tuple[int, float | None]:
        return self._taken

    def on_compass(self, t_s: float, bearing_mag_deg: float) -> bool | None:
        if self._ekf is None:
            # the filter starts at the first fix; the heading it needs comes next sample
            return None
        upd = self._ekf.on_compass(t_s, bearing_mag_deg)
        # too late for the filter, or its first heading: no judgement of the compass
        return None if upd.reason in ("stale", "init") else upd.accepted

    def on_odometry(self, rec: WheelOdometry, pitch_deg: float = 0.0) -> None:
        prev, self._counts = self._counts, (rec.left_counts, rec.right_counts)
        prev_t, self._odo_t = self._odo_t, rec.t_s
        if prev is None or prev_t is None or self._ekf is None:
            return
        dl, dr = wheel_travel_m(
            self._odo_cfg, rec.left_counts - prev[0], rec.right_counts - prev[1]
        )
        if not (abs(dl) <= MAX_INCREMENT_M and abs(dr) <= MAX_INCREMENT_M):
            self.odometry_dropped += 1
            return
        slip_m = 0.0
        if SLOPE_MIN_DEG <= abs(pitch_deg) <= SLOPE_MAX_DEG:
            # the wheels roll along the slope: its horizontal part is the EKF's motion, and
            # how far they slip there (uphill, down) is not known: the travel counts for less
            c = math.cos(math.radians(pitch_deg))
            dl, dr = dl * c, dr * c
            slip_m = SLOPE_SLIP_M * (1.0 - c * c)  # x sin^2(pitch)
        self._ekf.on_odometry(rec.t_s, dl, dr, slip_m)

    def on_command(self, t_s: float, left_pct: float, right_pct: float) -> None:
        if self._ekf is not None:
            self._ekf.on_command(t_s, left_pct, right_pct)

    def set_declination_deg(self, declination_deg: float) -> None:
        self._decl = declination_deg
        if self._ekf is not None:
            self._ekf.set_declination_deg(declination_deg)

    def reset(self) -> None:
        # The EKF keeps its state across missions: its gate and recovery rule handle a robot
        # carried elsewhere, and a standing robot's converged heading and bias are worth keeping.
        return None

    def _estimate(self, t_s: float) -> ekf.Estimate | None:
        if self._ekf is None:
            return None
        return self._ekf.predict(t_s)

    def position(self, t_s: float) -> tuple[float, float] | None:
        est = self._estimate(t_s)
        if est is None or self._plane is None:
            return None
        lat, lon = self._plane.to_latlon(est.east_m, est.north_m)
        return float(lat), float(lon)

    def heading_deg(self, t_s: float) -> float | None:
        est = self._estimate(t_s)
        return None if est is None else est.heading_deg

    def extra(self) -> dict[str, Any]:
        if self._ekf is None:
            return {"ekf": "waiting for a fix"}
        est, st = self._ekf.estimate(), self._ekf.stats
        out: dict[str, Any] = {
            "ekf_gps_rejected": st.gps_rejected,
            "ekf_gps_resets": st.gps_resets,
            "ekf_last_reset_m": st.last_reset_m,
            "ekf_last_reset_circle_m": st.last_reset_circle_m,
            "ekf_noise_hdop1_m": st.noise_hdop1_m,
            "ekf_last_reset_expected_m": 0.0
            if self._last_jump is None
            else self._last_jump.expected_m,
            "ekf_odometry_runaway_resets": st.odometry_runaway_resets,
            "ekf_bias_runaway_resets": st.bias_runaway_resets,
            "ekf_last_reset_reason": st.last_reset_reason,
            "ekf_compass_rejected": st.compass_rejected,
        }
        if st.odometry_runaway_resets >= RUNAWAY_WARN_RESETS:
            out["odometry_warning"] = runaway_warning(st.odometry_runaway_resets)
        if est is not None:
            out["ekf_sigma_m"] = math.hypot(est.sigma_east_m, est.sigma_north_m)
            out["ekf_speed_mps"] = est.speed_mps
            out["odometry_turn_scale"] = est.turn_scale
            out["odometry_drift_deg_per_m"] = est.drift_deg_per_m
            out["odometry_travel_scale"] = est.travel_scale
            out["compass_deviation_deg"] = est.compass_deviation_deg
        if self.odometry_dropped:
            out["odometry_dropped"] = self.odometry_dropped
        return out


def make_source(
    nav: NavigationConfig,
    odometry: OdometryConfig,
    gnss: GnssNoiseConfig,
    declination_deg: float,
) -> PositionSource:
    """The source ``nav.position_source`` names."""
    if nav.position_source == "raw":
        return RawSource()
    if nav.position_source == "constellation":
        return ConstellationSource(nav.filter_n, nav.filter_hysteresis)
    return EkfSource(nav, odometry, gnss, declination_deg)
