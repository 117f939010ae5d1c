"""Composable error layers with physical parameters (used by the simulator AND by x6wd.gap).

INTERFACE (fixed; implementations are filled in below it):

- :class:`PositionSeries`: a time series of position ERRORS or positions in a local
  east/north/up frame (metres), with a per-epoch ``valid`` mask (False = no fix).
- :class:`HeadingSeries`: compass samples: measured heading, pitch, roll (deg), with the
  true heading and the true tilt used by the compass layers.
- An effect is a frozen dataclass with a class attribute ``name`` (one of ``EFFECT_NAMES``)
  and ``apply(series, rng) -> series`` returning a NEW series (inputs are never modified).
  Parameters keep their meaning at any sample rate (e.g. Gauss-Markov uses tau_s, sigma_m
  and the exact discretisation phi = exp(-dt/tau)).
- ``EFFECTS``: name -> effect class, so the gap tool can construct effects by name and
  write them into a simulator config fragment (``to_params()`` / ``from_params()``).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from typing import Any, ClassVar

import numpy as np

from x6wd.core.errors import ConfigError

GPS_EFFECT_NAMES = (
    "gauss_markov",
    "random_walk",
    "bias",
    "quantization",
    "jumps",
    "outages",
    "latency",
    "multipath_zone",
)
COMPASS_EFFECT_NAMES = ("hard_iron", "soft_iron", "tilt", "declination", "heading_lag")
EFFECT_NAMES = GPS_EFFECT_NAMES + COMPASS_EFFECT_NAMES


@dataclass(frozen=True)
class PositionSeries:
    """Positions (or position errors) in a local tangent frame, metres.

    ``t_s`` strictly increasing seconds; ``east_m``/``north_m``/``up_m`` same length;
    ``valid`` False where the receiver had no fix (values there are meaningless).
    ``origin_lat_deg``/``origin_lon_deg`` place the frame (needed by quantisation,
    which acts on NMEA minutes). ``speed_mps``/``course_deg`` of the TRUE motion are
    optional (latency and the gap tool's error-vs-speed use them).
    ``nsats`` optional satellites-used count (jumps at satellite-set changes).
    """

    t_s: np.ndarray
    east_m: np.ndarray
    north_m: np.ndarray
    up_m: np.ndarray
    valid: np.ndarray
    origin_lat_deg: float = 0.0
    origin_lon_deg: float = 0.0
    speed_mps: np.ndarray | None = None
    course_deg: np.ndarray | None = None
    nsats: np.ndarray | None = None

    def __len__(self) -> int:
        return int(self.t_s.shape[0])

    def with_(self, **changes: object) -> PositionSeries:
        """Copy with some arrays replaced."""
        return replace(self, **changes)  # type: ignore[arg-type]


@dataclass(frozen=True)
class HeadingSeries:
    """Compass samples, degrees. ``heading_deg`` is the MEASURED magnetic heading 0..360;
    ``true_heading_deg`` the truth (if known); pitch/roll measured (deg)."""

    t_s: np.ndarray
    heading_deg: np.ndarray
    pitch_deg: np.ndarray
    roll_deg: np.ndarray
    true_heading_deg: np.ndarray | None = None
    field_ut: np.ndarray | None = None  # measured field magnitude (microtesla), if known
    extra: dict[str, np.ndarray] = field(default_factory=dict)

    def __len__(self) -> int:
        return int(self.t_s.shape[0])

    def with_(self, **changes: object) -> HeadingSeries:
        return replace(self, **changes)  # type: ignore[arg-type]


# ---------------------------------------------------------------------------------------------
# Implementation.
#
# Convention for GPS layers: a PositionSeries given to an effect holds position ERRORS
# (reported minus true position) in the local east/north/up frame of the origin. The true
# track, when the vehicle moves, is implied by ``speed_mps``/``course_deg`` (integrated from
# zero at the first epoch, so the origin is the true position at t_s[0]); without them the
# truth is the origin itself. Layers that depend on where the vehicle is (quantisation,
# latency, multipath_zone) use that implied truth.
#
# Compass layers act on the measured heading of a HeadingSeries; each returns pitch/roll
# clamped to the CMPS10's +/-85 deg range.
# ---------------------------------------------------------------------------------------------

# WGS84: radii of curvature turn degrees into metres in the local frame.
_WGS84_A_M = 6378137.0
_WGS84_E2 = 6.69437999014e-3
PITCH_ROLL_LIMIT_DEG = 85.0


def radii_of_curvature_m(lat_deg: float) -> tuple[float, float]:
    """Meridian (north) and prime-vertical (east) radii of curvature at ``lat_deg``, metres."""
    s = math.sin(math.radians(lat_deg))
    w = math.sqrt(1.0 - _WGS84_E2 * s * s)
    return _WGS84_A_M * (1.0 - _WGS84_E2) / w**3, _WGS84_A_M / w


def metres_per_degree(lat_deg: float) -> tuple[float, float]:
    """(east, north) metres per degree of longitude/latitude at ``lat_deg``."""
    m_m, n_m = radii_of_curvature_m(lat_deg)
    k = math.pi / 180.0
    return n_m * math.cos(math.radians(lat_deg)) * k, m_m * k


def quantization_step_m(decimals: int, lat_deg: float) -> tuple[float, float]:
    """(east, north) lattice step in metres of NMEA minutes printed with ``decimals`` places."""
    east_per_deg, north_per_deg = metres_per_degree(lat_deg)
    step_deg = 10.0 ** (-decimals) / 60.0
    return east_per_deg * step_deg, north_per_deg * step_deg


def _dt_s(t_s: np.ndarray) -> np.ndarray:
    dt = np.diff(np.asarray(t_s, dtype=float))
    if dt.size and not np.all(dt > 0):
        raise ValueError("t_s must be strictly increasing")
    return dt


def truth_velocity_mps(series: PositionSeries) -> tuple[np.ndarray, np.ndarray]:
    """True east/north velocity (m/s) per epoch from speed_mps/course_deg (missing values
    read as 0; no course reads as north). Zero everywhere when the series has no speed."""
    n = len(series)
    if series.speed_mps is None:
        return np.zeros(n), np.zeros(n)
    speed = np.nan_to_num(np.asarray(series.speed_mps, dtype=float))
    course = series.course_deg
    crs = np.zeros(n) if course is None else np.nan_to_num(np.asarray(course, dtype=float))
    return speed * np.sin(np.radians(crs)), speed * np.cos(np.radians(crs))


def truth_track_m(series: PositionSeries) -> tuple[np.ndarray, np.ndarray]:
    """True east/north (m) relative to the origin, integrated from speed_mps/course_deg.

    Zero everywhere when the series carries no velocity (a static receiver at the origin).
    Trapezoidal integration of the velocity components.
    """
    n = len(series)
    if series.speed_mps is None or n == 0:
        return np.zeros(n), np.zeros(n)
    ve, vn = truth_velocity_mps(series)
    dt = _dt_s(series.t_s)
    east = np.concatenate(([0.0], np.cumsum(0.5 * (ve[1:] + ve[:-1]) * dt)))
    north = np.concatenate(([0.0], np.cumsum(0.5 * (vn[1:] + vn[:-1]) * dt)))
    return east, north


def gauss_markov_noise(
    t_s: np.ndarray, sigma: float, tau_s: float, rng: np.random.Generator, size: int = 1
) -> np.ndarray:
    """Stationary first-order Gauss-Markov samples at times ``t_s`` (shape (size, n)).

    Exact discretisation with the actual step: phi_k = exp(-dt_k/tau_s), innovation
    sigma*sqrt(1-phi_k^2); the first sample is drawn from the stationary law N(0, sigma^2).
    The unit of the output is the unit of ``sigma``.
    """
    t = np.asarray(t_s, dtype=float)
    n = t.shape[0]
    out = np.empty((size, n))
    if n == 0:
        return out
    w = rng.standard_normal((size, n))
    dt = _dt_s(t)
    phi = np.exp(-dt / tau_s)
    innov = sigma * np.sqrt(-np.expm1(-2.0 * dt / tau_s))
    out[:, 0] = sigma * w[:, 0]
    if n > 1 and np.all(dt == dt[0]):
        # One step everywhere: the recursion is a first-order IIR filter, run in C by lfilter
        # (the same multiply-adds in the same order: bit-identical to the loop below).
        from scipy.signal import lfilter

        out[:, 1:] = lfilter(
            [1.0], [1.0, -phi[0]], innov[0] * w[:, 1:], axis=1, zi=(phi[0] * out[:, 0])[:, None]
        )[0]
        return out
    # Variable steps: a Python loop over time is the honest cost of exact variable-step
    # discretisation; it is vectorised across axes/ensembles instead.
    x = out[:, 0].copy()
    for k in range(1, n):
        x = phi[k - 1] * x + innov[k - 1] * w[:, k]
        out[:, k] = x
    return out


_AXES = {"e": (0,), "n": (1,), "u": (2,), "en": (0, 1), "enu": (0, 1, 2)}


def _axes(axes: str) -> tuple[int, ...]:
    try:
        return _AXES[axes]
    except KeyError:
        raise ConfigError(f"axes={axes!r}: expected one of {sorted(_AXES)}") from None


def _positive(name: str, value: float, allow_zero: bool = False) -> None:
    ok = value >= 0 if allow_zero else value > 0
    if not (math.isfinite(value) and ok):
        raise ConfigError(f"{name}={value!r}: must be {'>= 0' if allow_zero else '> 0'}")


def _add(series: PositionSeries, delta: np.ndarray) -> PositionSeries:
    """Series plus a (3, n) east/north/up error."""
    return series.with_(
        east_m=np.asarray(series.east_m, dtype=float) + delta[0],
        north_m=np.asarray(series.north_m, dtype=float) + delta[1],
        up_m=np.asarray(series.up_m, dtype=float) + delta[2],
    )


class _Params:
    """to_params/from_params shared by all layers: the dataclass fields minus ``name``."""

    name: ClassVar[str]

    def to_params(self) -> dict[str, Any]:
        """Parameters as a TOML-ready table including ``name``."""
        out: dict[str, Any] = {"name": self.name}
        for key in self.__dataclass_fields__:  # type: ignore[attr-defined]
            value = getattr(self, key)
            out[key] = list(value) if isinstance(value, tuple) else value
        return out

    @classmethod
    def from_params(cls, params: Mapping[str, Any]) -> Any:
        """Build from a table (``name`` optional; unknown keys are a ConfigError)."""
        data = {k: v for k, v in params.items() if k != "name"}
        if "name" in params and params["name"] != cls.name:
            raise ConfigError(f"effect name {params['name']!r} given to {cls.name}")
        fields_ = cls.__dataclass_fields__  # type: ignore[attr-defined]
        unknown = sorted(set(data) - set(fields_))
        if unknown:
            raise ConfigError(
                f"effect {cls.name}: unknown parameter(s) {unknown}; valid: {sorted(fields_)}"
            )
        for key, value in list(data.items()):
            if isinstance(value, list):
                data[key] = tuple(value)
        try:
            return cls(**data)
        except TypeError as exc:
            raise ConfigError(f"effect {cls.name}: {exc}") from None


# --- GPS layers -------------------------------------------------------------------------------


@dataclass(frozen=True)
class GaussMarkov(_Params):
    """First-order Gauss-Markov drift, independent per axis: sigma_m (stationary std, m),
    tau_s (correlation time, s); axes 'en' (horizontal, default), 'enu', 'e', 'n' or 'u'."""

    name: ClassVar[str] = "gauss_markov"
    sigma_m: float
    tau_s: float
    axes: str = "en"

    def __post_init__(self) -> None:
        _positive("sigma_m", self.sigma_m, allow_zero=True)
        _positive("tau_s", self.tau_s)
        _axes(self.axes)

    def apply(self, series: PositionSeries, rng: np.random.Generator) -> PositionSeries:
        idx = _axes(self.axes)
        delta = np.zeros((3, len(series)))
        delta[list(idx)] = gauss_markov_noise(series.t_s, self.sigma_m, self.tau_s, rng, len(idx))
        return _add(series, delta)


@dataclass(frozen=True)
class RandomWalk(_Params):
    """Random walk starting at zero: q_m_per_sqrt_s (m/sqrt(s)): increment std q*sqrt(dt)."""

    name: ClassVar[str] = "random_walk"
    q_m_per_sqrt_s: float
    axes: str = "en"

    def __post_init__(self) -> None:
        _positive("q_m_per_sqrt_s", self.q_m_per_sqrt_s, allow_zero=True)
        _axes(self.axes)

    def apply(self, series: PositionSeries, rng: np.random.Generator) -> PositionSeries:
        idx = _axes(self.axes)
        n = len(series)
        delta = np.zeros((3, n))
        if n:
            steps = (
                self.q_m_per_sqrt_s
                * np.sqrt(_dt_s(series.t_s))
                * rng.standard_normal((len(idx), n - 1))
            )
            delta[list(idx), 1:] = np.cumsum(steps, axis=1)
        return _add(series, delta)


@dataclass(frozen=True)
class Bias(_Params):
    """Constant offset (m) east, north, up."""

    name: ClassVar[str] = "bias"
    east_m: float = 0.0
    north_m: float = 0.0
    up_m: float = 0.0

    def apply(self, series: PositionSeries, rng: np.random.Generator) -> PositionSeries:
        n = len(series)
        delta = np.array([[self.east_m], [self.north_m], [self.up_m]]) * np.ones((1, n))
        return _add(series, delta)


@dataclass(frozen=True)
class Quantization(_Params):
    """NMEA rounding of latitude/longitude minutes to ``decimals`` places (4 or 5 on u-blox 5).

    Acts on the absolute position (origin + implied truth + error); the error becomes the
    rounded position minus the truth, so the reported positions lie exactly on the lattice
    of :func:`quantization_step_m`. Up is untouched (altitude has its own 0.1 m format).
    """

    name: ClassVar[str] = "quantization"
    decimals: int = 5

    def __post_init__(self) -> None:
        if not isinstance(self.decimals, int) or not 0 <= self.decimals <= 9:
            raise ConfigError(f"decimals={self.decimals!r}: must be an integer 0..9")

    def apply(self, series: PositionSeries, rng: np.random.Generator) -> PositionSeries:
        lat0, lon0 = series.origin_lat_deg, series.origin_lon_deg
        e_per_deg, n_per_deg = metres_per_degree(lat0)
        te, tn = truth_track_m(series)
        lat = lat0 + (tn + np.asarray(series.north_m, dtype=float)) / n_per_deg
        lon = lon0 + (te + np.asarray(series.east_m, dtype=float)) / e_per_deg
        qlat = quantize_degrees(lat, self.decimals)
        qlon = quantize_degrees(lon, self.decimals)
        return series.with_(
            east_m=(qlon - lon0) * e_per_deg - te,
            north_m=(qlat - lat0) * n_per_deg - tn,
        )


def quantize_degrees(deg: np.ndarray, decimals: int) -> np.ndarray:
    """Degrees as NMEA prints them: |deg| in minutes rounded to ``decimals``, sign kept."""
    d = np.asarray(deg, dtype=float)
    minutes = np.round(np.abs(d) * 60.0, decimals)
    return np.sign(d) * minutes / 60.0


JUMP_TRIGGERS = ("auto", "poisson", "sat_change")


@dataclass(frozen=True)
class Jumps(_Params):
    """Position jumps when the satellite set changes.

    Each satellite set has its own solution offset, so at every change of ``nsats`` (or, when
    the series has no nsats, at Poisson events of ``rate_per_s``) a fresh offset
    N(0, sigma_m^2) per horizontal axis (N(0, up_sigma_m^2) up) replaces the previous one.
    The first set starts with an offset from the same law (stationary). ``trigger`` "auto"
    is that rule; "poisson" always uses Poisson events (a receiver that re-solves for reasons
    the satellite count does not show: multipath switching, RAIM exclusions), "sat_change"
    always uses set changes (none without nsats).
    """

    name: ClassVar[str] = "jumps"
    sigma_m: float
    rate_per_s: float = 0.01
    up_sigma_m: float = 0.0
    trigger: str = "auto"

    def __post_init__(self) -> None:
        _positive("sigma_m", self.sigma_m, allow_zero=True)
        _positive("rate_per_s", self.rate_per_s, allow_zero=True)
        _positive("up_sigma_m", self.up_sigma_m, allow_zero=True)
        if self.trigger not in JUMP_TRIGGERS:
            raise ConfigError(f"trigger={self.trigger!r}: expected one of {list(JUMP_TRIGGERS)}")

    def change_mask(self, series: PositionSeries, rng: np.random.Generator) -> np.ndarray:
        """Boolean per epoch: True where a new satellite set (new offset) begins."""
        n = len(series)
        mask = np.zeros(n, dtype=bool)
        if n < 2:
            return mask
        if self.trigger == "sat_change" and series.nsats is None:
            return mask
        if series.nsats is not None and self.trigger != "poisson":
            ns = np.asarray(series.nsats)
            mask[1:] = ns[1:] != ns[:-1]
        else:
            p = -np.expm1(-self.rate_per_s * _dt_s(series.t_s))
            mask[1:] = rng.random(n - 1) < p
        return mask

    def apply(self, series: PositionSeries, rng: np.random.Generator) -> PositionSeries:
        n = len(series)
        mask = self.change_mask(series, rng)
        seg = np.cumsum(mask)
        nseg = int(seg[-1]) + 1 if n else 0
        offs = rng.standard_normal((3, nseg)) * np.array(
            [[self.sigma_m], [self.sigma_m], [self.up_sigma_m]]
        )
        return _add(series, offs[:, seg] if n else np.zeros((3, 0)))


@dataclass(frozen=True)
class Outages(_Params):
    """Fix outages: a two-state continuous-time Markov chain (mean_up_s, mean_down_s), exact
    transition probabilities over each actual step, stationary start. Down -> valid False."""

    name: ClassVar[str] = "outages"
    mean_up_s: float
    mean_down_s: float

    def __post_init__(self) -> None:
        _positive("mean_up_s", self.mean_up_s)
        _positive("mean_down_s", self.mean_down_s)

    def states(self, t_s: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """True where the receiver has a fix, at times ``t_s``."""
        a, b = 1.0 / self.mean_up_s, 1.0 / self.mean_down_s  # up->down, down->up rates
        n = len(t_s)
        up = np.zeros(n, dtype=bool)
        if n == 0:
            return up
        e = np.exp(-(a + b) * _dt_s(t_s))
        stay_up = (b + a * e) / (a + b)
        stay_down = (a + b * e) / (a + b)
        u = rng.random(n)
        state = bool(u[0] < b / (a + b))
        up[0] = state
        for k in range(1, n):
            state = bool(u[k] < stay_up[k - 1]) if state else bool(u[k] >= stay_down[k - 1])
            up[k] = state
        return up

    def apply(self, series: PositionSeries, rng: np.random.Generator) -> PositionSeries:
        up = self.states(series.t_s, rng)
        return series.with_(valid=np.asarray(series.valid, dtype=bool) & up)


@dataclass(frozen=True)
class Latency(_Params):
    """Reported position is the truth of ``delay_s`` earlier (plus the existing error).

    Error added = truth(t - delay_s) - truth(t), with the truth track implied by
    speed_mps/course_deg (before the first epoch the vehicle is taken to move with its
    first velocity). A static series is unchanged.
    """

    name: ClassVar[str] = "latency"
    delay_s: float

    def __post_init__(self) -> None:
        _positive("delay_s", self.delay_s, allow_zero=True)

    def apply(self, series: PositionSeries, rng: np.random.Generator) -> PositionSeries:
        n = len(series)
        if series.speed_mps is None or n == 0:
            return series.with_()
        te, tn = truth_track_m(series)
        t = np.asarray(series.t_s, dtype=float)
        tq = t - self.delay_s
        ve, vn = truth_velocity_mps(series)
        ve0, vn0 = float(ve[0]), float(vn[0])
        pe = np.interp(tq, t, te)
        pn = np.interp(tq, t, tn)
        early = tq < t[0]
        pe[early] = (tq[early] - t[0]) * ve0
        pn[early] = (tq[early] - t[0]) * vn0
        delta = np.vstack([pe - te, pn - tn, np.zeros(n)])
        return _add(series, delta)


@dataclass(frozen=True)
class MultipathZone(_Params):
    """Extra error near a wall: the wall is the segment (x1_m, y1_m)-(x2_m, y2_m) in the
    local frame; within ``distance_m`` of it the horizontal error gains a bias ``bias_m``
    pointing away from the wall (reflected paths are longer) and Gauss-Markov noise of
    ``sigma_m`` per axis with correlation time ``tau_s``."""

    name: ClassVar[str] = "multipath_zone"
    x1_m: float
    y1_m: float
    x2_m: float
    y2_m: float
    distance_m: float
    sigma_m: float = 1.0
    bias_m: float = 0.0
    tau_s: float = 10.0

    def __post_init__(self) -> None:
        _positive("distance_m", self.distance_m)
        _positive("sigma_m", self.sigma_m, allow_zero=True)
        _positive("tau_s", self.tau_s)
        if (self.x1_m, self.y1_m) == (self.x2_m, self.y2_m):
            raise ConfigError("multipath_zone: wall end points coincide")

    def distance_to_wall_m(
        self, east_m: np.ndarray, north_m: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Distance (m) of points to the wall segment and the unit vector away from it."""
        ax, ay = self.x1_m, self.y1_m
        dx, dy = self.x2_m - ax, self.y2_m - ay
        s = np.clip(((east_m - ax) * dx + (north_m - ay) * dy) / (dx * dx + dy * dy), 0.0, 1.0)
        rx, ry = east_m - (ax + s * dx), north_m - (ay + s * dy)
        dist = np.hypot(rx, ry)
        # On the wall line itself use the left-hand normal (any side is as good).
        nx, ny = -dy / math.hypot(dx, dy), dx / math.hypot(dx, dy)
        safe = dist > 1e-9
        ux = np.where(safe, rx / np.where(safe, dist, 1.0), nx)
        uy = np.where(safe, ry / np.where(safe, dist, 1.0), ny)
        return dist, ux, uy

    def apply(self, series: PositionSeries, rng: np.random.Generator) -> PositionSeries:
        te, tn = truth_track_m(series)
        dist, ux, uy = self.distance_to_wall_m(te, tn)
        inside = dist <= self.distance_m
        noise = gauss_markov_noise(series.t_s, self.sigma_m, self.tau_s, rng, 2)
        delta = np.zeros((3, len(series)))
        delta[0] = np.where(inside, self.bias_m * ux + noise[0], 0.0)
        delta[1] = np.where(inside, self.bias_m * uy + noise[1], 0.0)
        return _add(series, delta)


# --- compass layers ---------------------------------------------------------------------------


def wrap360(deg: np.ndarray) -> np.ndarray:
    """Angle(s) wrapped to [0, 360)."""
    return np.mod(np.asarray(deg, dtype=float), 360.0)


def wrap180(deg: np.ndarray) -> np.ndarray:
    """Angle(s) wrapped to [-180, 180)."""
    return np.mod(np.asarray(deg, dtype=float) + 180.0, 360.0) - 180.0


def _compass_out(
    series: HeadingSeries, heading_deg: np.ndarray, **changes: object
) -> HeadingSeries:
    return series.with_(
        heading_deg=wrap360(heading_deg),
        pitch_deg=np.clip(
            np.asarray(series.pitch_deg, dtype=float), -PITCH_ROLL_LIMIT_DEG, PITCH_ROLL_LIMIT_DEG
        ),
        roll_deg=np.clip(
            np.asarray(series.roll_deg, dtype=float), -PITCH_ROLL_LIMIT_DEG, PITCH_ROLL_LIMIT_DEG
        ),
        **changes,
    )


def _field_magnitude(series: HeadingSeries, horizontal_ut: float) -> np.ndarray:
    if series.field_ut is not None:
        return np.asarray(series.field_ut, dtype=float)
    return np.full(len(series), horizontal_ut)


@dataclass(frozen=True)
class Declination(_Params):
    """Magnetic declination (deg, east positive): the compass reads heading - declination."""

    name: ClassVar[str] = "declination"
    declination_deg: float

    def apply(self, series: HeadingSeries, rng: np.random.Generator) -> HeadingSeries:
        return _compass_out(series, np.asarray(series.heading_deg) - self.declination_deg)


@dataclass(frozen=True)
class HardIron(_Params):
    """A hard-iron offset (bx_ut forward, by_ut right, microtesla) added in the body frame to
    the horizontal Earth field ``horizontal_field_ut``. The body sees the field
    (H cos h + bx, -H sin h + by) at magnetic heading h; the heading it computes is
    atan2(-y, x), an error repeating once per turn; the horizontal field magnitude it
    measures varies with heading (what tells hard iron from tilt)."""

    name: ClassVar[str] = "hard_iron"
    bx_ut: float
    by_ut: float
    horizontal_field_ut: float = 19.0

    def __post_init__(self) -> None:
        _positive("horizontal_field_ut", self.horizontal_field_ut)

    def apply(self, series: HeadingSeries, rng: np.random.Generator) -> HeadingSeries:
        h = np.radians(np.asarray(series.heading_deg, dtype=float))
        H = self.horizontal_field_ut
        x = H * np.cos(h) + self.bx_ut
        y = -H * np.sin(h) + self.by_ut
        scale = _field_magnitude(series, H) / H
        return _compass_out(series, np.degrees(np.arctan2(-y, x)), field_ut=np.hypot(x, y) * scale)


@dataclass(frozen=True)
class SoftIron(_Params):
    """Soft iron: the horizontal field is multiplied by a symmetric matrix with principal
    gains (1 + k, 1 - k) along body axes rotated by ``axis_deg``: error twice per turn,
    amplitude about k rad."""

    name: ClassVar[str] = "soft_iron"
    k: float
    axis_deg: float = 0.0

    def __post_init__(self) -> None:
        if not -0.9 < self.k < 0.9:
            raise ConfigError(f"soft_iron k={self.k!r}: must be in (-0.9, 0.9)")

    def apply(self, series: HeadingSeries, rng: np.random.Generator) -> HeadingSeries:
        h = np.radians(np.asarray(series.heading_deg, dtype=float))
        a = math.radians(self.axis_deg)
        x, y = np.cos(h), -np.sin(h)
        # rotate into the principal axes, scale, rotate back
        p = x * math.cos(a) + y * math.sin(a)
        q = -x * math.sin(a) + y * math.cos(a)
        p, q = p * (1 + self.k), q * (1 - self.k)
        x2 = p * math.cos(a) - q * math.sin(a)
        y2 = p * math.sin(a) + q * math.cos(a)
        scale = np.hypot(x2, y2)
        return _compass_out(
            series, np.degrees(np.arctan2(-y2, x2)), field_ut=_field_magnitude(series, 1.0) * scale
        )


def tilted_heading_deg(
    heading_deg: np.ndarray, pitch_deg: np.ndarray, roll_deg: np.ndarray, inclination_deg: float
) -> np.ndarray:
    """Heading computed WITHOUT tilt compensation by a magnetometer tilted by pitch/roll.

    Earth field in the magnetic NED frame (cos I, 0, sin I); body components from the
    rotation Rz(h) Ry(pitch) Rx(roll); heading = atan2(-B_y, B_x). Error ~ tilt * tan(I).
    """
    h = np.radians(np.asarray(heading_deg, dtype=float))
    th = np.radians(np.asarray(pitch_deg, dtype=float))
    ph = np.radians(np.asarray(roll_deg, dtype=float))
    inc = math.radians(inclination_deg)
    bn, bd = math.cos(inc), math.sin(inc)
    # NED -> body: (Rz Ry Rx)^T applied to (bn, 0, bd)
    x1 = np.cos(h) * bn  # Rz^T
    y1 = -np.sin(h) * bn
    z1 = np.full_like(h, bd)
    x2 = np.cos(th) * x1 - np.sin(th) * z1  # Ry^T
    z2 = np.sin(th) * x1 + np.cos(th) * z1
    y3 = np.cos(ph) * y1 + np.sin(ph) * z2  # Rx^T
    return np.degrees(np.arctan2(-y3, x2))


@dataclass(frozen=True)
class Tilt(_Params):
    """Imperfect tilt compensation: a fraction (0 = perfect, 1 = none) of the measured
    pitch/roll is left uncompensated; the heading error is that of an untilted-computed
    heading at inclination ``inclination_deg`` (about tilt * tan(inclination), once per turn)."""

    name: ClassVar[str] = "tilt"
    fraction: float = 1.0
    inclination_deg: float = 66.0

    def __post_init__(self) -> None:
        if not 0.0 <= self.fraction <= 1.0:
            raise ConfigError(f"tilt fraction={self.fraction!r}: must be in [0, 1]")
        if not -89.0 <= self.inclination_deg <= 89.0:
            raise ConfigError(
                f"tilt inclination_deg={self.inclination_deg!r}: must be in [-89, 89]"
            )

    def apply(self, series: HeadingSeries, rng: np.random.Generator) -> HeadingSeries:
        h = np.asarray(series.heading_deg, dtype=float)
        pitch = np.clip(
            np.asarray(series.pitch_deg, dtype=float), -PITCH_ROLL_LIMIT_DEG, PITCH_ROLL_LIMIT_DEG
        )
        roll = np.clip(
            np.asarray(series.roll_deg, dtype=float), -PITCH_ROLL_LIMIT_DEG, PITCH_ROLL_LIMIT_DEG
        )
        err = wrap180(
            tilted_heading_deg(h, self.fraction * pitch, self.fraction * roll, self.inclination_deg)
            - h
        )
        return _compass_out(series, h + err)


@dataclass(frozen=True)
class HeadingNoise(_Params):
    """White heading noise, sigma_deg (deg) per sample."""

    name: ClassVar[str] = "heading_noise"
    sigma_deg: float

    def __post_init__(self) -> None:
        _positive("sigma_deg", self.sigma_deg, allow_zero=True)

    def apply(self, series: HeadingSeries, rng: np.random.Generator) -> HeadingSeries:
        noise = self.sigma_deg * rng.standard_normal(len(series))
        return _compass_out(series, np.asarray(series.heading_deg, dtype=float) + noise)


@dataclass(frozen=True)
class HeadingLag(_Params):
    """First-order lag of the heading filter, time constant tau_s (CMPS10: its filter takes
    about 640 ms to refresh fully, i.e. tau about 0.21 s). Exact for a heading held between
    samples: y_k = y_{k-1} + (1 - exp(-dt/tau)) * wrap(x_k - y_{k-1}), across north."""

    name: ClassVar[str] = "heading_lag"
    tau_s: float = 0.64 / 3.0

    def __post_init__(self) -> None:
        _positive("tau_s", self.tau_s)

    def apply(self, series: HeadingSeries, rng: np.random.Generator) -> HeadingSeries:
        x = np.asarray(series.heading_deg, dtype=float)
        n = x.shape[0]
        y = np.empty(n)
        if n:
            gain = -np.expm1(-_dt_s(series.t_s) / self.tau_s)
            y[0] = x[0]
            for k in range(1, n):
                y[k] = y[k - 1] + gain[k - 1] * ((x[k] - y[k - 1] + 180.0) % 360.0 - 180.0)
        return _compass_out(series, y)


GpsEffect = (
    GaussMarkov | RandomWalk | Bias | Quantization | Jumps | Outages | Latency | MultipathZone
)
CompassEffect = Declination | HardIron | SoftIron | Tilt | HeadingNoise | HeadingLag
Effect = GpsEffect | CompassEffect

EFFECTS: dict[str, type[Any]] = {
    cls.name: cls
    for cls in (
        GaussMarkov,
        RandomWalk,
        Bias,
        Quantization,
        Jumps,
        Outages,
        Latency,
        MultipathZone,
        HardIron,
        SoftIron,
        Tilt,
        Declination,
        HeadingLag,
        HeadingNoise,
    )
}


def effect_from_params(params: Mapping[str, Any]) -> Any:
    """Construct an effect from a table with a ``name`` key (as in a scenario's [[effects]])."""
    name = params.get("name")
    if name not in EFFECTS:
        raise ConfigError(f"effects: unknown name {name!r}; valid: {sorted(EFFECTS)}")
    return EFFECTS[str(name)].from_params(params)


def apply_effects(series: Any, effects: Any, rng: np.random.Generator) -> Any:
    """Apply a sequence of effects in order; GPS effects to a PositionSeries, compass ones to
    a HeadingSeries (an effect of the other kind is a ConfigError)."""
    for eff in effects:
        gps = eff.name in GPS_EFFECT_NAMES
        if gps != isinstance(series, PositionSeries):
            raise ConfigError(f"effect {eff.name} cannot act on a {type(series).__name__}")
        series = eff.apply(series, rng)
    return series
