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
- ONE way to run a GPS layer (:class:`GpsLayer`): ``layer.start(rng)`` is the layer running
  over a receiver's output (:class:`LayerRun`) with its own state and random stream;
  ``run.step(batch)`` transforms the next epochs (one or many) of an error series, continuing
  from the state, and ``run.delay_s`` is the receiver latency it adds. ``apply`` is that run
  stepped once over a whole series; the simulator's receiver (:mod:`sim_backend.receiver`) runs
  every GPS layer the same way, one epoch at a time in closed loop and over a whole log for the
  gap tool's baselines.
- A compass layer (:class:`CompassLayer`) also says how it changes the compass emulation's
  own physics in closed loop: ``act_on(CompassPhysics) -> CompassPhysics``.
- ``EFFECTS``: name -> effect class, so the gap tool can construct effects by name and
  write them into a simulator config fragment (``to_params()`` / ``from_params()``).
"""

from __future__ import annotations

import abc
import dataclasses
import math
import typing
import zlib
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field, replace
from typing import Any, ClassVar, Protocol

import numpy as np

from x6wd.core.config import check_value  # the one type check of every configuration key
from x6wd.core.errors import ConfigError
from x6wd.core.geodesy import WGS84_A_M, WGS84_E2, wrap360, wrap_deg
from x6wd.core.geodesy import wrap_deg as wrap180  # the name gap and mission import

GPS_EFFECT_NAMES = (
    "gauss_markov",
    "random_walk",
    "bias",
    "quantization",
    "jumps",
    "outages",
    "latency",
    "multipath_zone",
    "nav_filter",
    "noise_scale",
    "static_hold",
    "correction",
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
    ``sat_set`` optional identity of the set of satellites used (equal values: the same
    set; -1 unknown; :func:`satellite_set_id`), where the log tells which (an NMEA GSA):
    the count alone misses a satellite swapped for another.
    ``true_east_m``/``true_north_m`` optional TRUE position (m, the origin's local frame):
    when given, the layers that depend on where the vehicle is use it instead of integrating
    speed/course (the simulator's receiver hands its layers one epoch at a time, with the
    truth it knows).
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
    sat_set: np.ndarray | None = None
    true_east_m: np.ndarray | None = None
    true_north_m: np.ndarray | None = None

    def __len__(self) -> int:
        return int(self.t_s.shape[0])

    def with_(self, **changes: object) -> PositionSeries:
        """Copy with some arrays replaced."""
        return replace(self, **changes)  # type: ignore[arg-type]


def satellite_set_id(prns: Iterable[int]) -> float:
    """An identity of a set of satellites (PRN or NMEA ids): the CRC-32 of the sorted ids, a
    whole number below 2^32, so it is exact in a float array. Two different sets share one
    with probability 2^-32."""
    ids = np.array(sorted({int(p) for p in prns}), dtype="<u2")
    return float(zlib.crc32(ids.tobytes()))


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

PITCH_ROLL_LIMIT_DEG = 85.0


def radii_of_curvature_m(lat_deg: float) -> tuple[float, float]:
    """Meridian (north) and prime-vertical (east) radii of curvature at ``lat_deg``, metres
    (WGS-84): they turn degrees into metres in the local frame."""
    s = math.sin(math.radians(lat_deg))
    w = math.sqrt(1.0 - WGS84_E2 * s * s)
    return WGS84_A_M * (1.0 - WGS84_E2) / w**3, WGS84_A_M / w


def metres_per_degree(lat_deg: float) -> tuple[float, float]:
    """(east, north) metres per degree of longitude/latitude at ``lat_deg``."""
    m_m, n_m = radii_of_curvature_m(lat_deg)
    k = math.pi / 180.0
    return n_m * math.cos(math.radians(lat_deg)) * k, m_m * k


QUANT_UNITS = ("min", "deg")  # NMEA minutes (ddmm.mmmm), decimal degrees (dd.ddddd)


def lattice_step_deg(decimals: int, unit: str = "min") -> float:
    """The lattice step in degrees of a coordinate printed with ``decimals`` places of
    ``unit`` ("min": NMEA minutes; "deg": decimal degrees)."""
    return 10.0 ** (-decimals) / (60.0 if unit == "min" else 1.0)


def quantization_step_m(decimals: int, lat_deg: float, unit: str = "min") -> tuple[float, float]:
    """(east, north) lattice step in metres of NMEA minutes (``unit`` "min") or decimal
    degrees ("deg") printed with ``decimals`` places."""
    east_per_deg, north_per_deg = metres_per_degree(lat_deg)
    step_deg = lattice_step_deg(decimals, unit)
    return east_per_deg * step_deg, north_per_deg * step_deg


def _dt_s(t_s: np.ndarray) -> np.ndarray:
    t = np.asarray(t_s, dtype=float)
    dt = np.diff(t)
    if dt.size and not np.all(dt > 0):
        raise ValueError(_not_rising_text(t, dt))
    return dt


def _not_rising_text(t_s: np.ndarray, dt_s: np.ndarray) -> str:
    """The error of a time axis (s) that does not rise: where, so that a caller's log can be
    looked at (the bare "t_s must be strictly increasing" named no epoch)."""
    k = int(np.flatnonzero(~(dt_s > 0))[0])
    return (
        f"t_s must be strictly increasing: samples {k} and {k + 1} are at {t_s[k]:.6f} s and"
        f" {t_s[k + 1]:.6f} s"
    )


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
    """True east/north (m) relative to the origin: ``true_east_m``/``true_north_m`` when the
    series carries them, else integrated from speed_mps/course_deg.

    Zero everywhere when the series carries neither (a static receiver at the origin).
    Trapezoidal integration of the velocity components.
    """
    if series.true_east_m is not None and series.true_north_m is not None:
        return (
            np.asarray(series.true_east_m, dtype=float),
            np.asarray(series.true_north_m, dtype=float),
        )
    n = len(series)
    if series.speed_mps is None or n == 0:
        return np.zeros(n), np.zeros(n)
    ve, vn = truth_velocity_mps(series)
    dt = _dt_s(series.t_s)
    east = np.concatenate(([0.0], np.cumsum(0.5 * (ve[1:] + ve[:-1]) * dt)))
    north = np.concatenate(([0.0], np.cumsum(0.5 * (vn[1:] + vn[:-1]) * dt)))
    return east, north


def interp_track(
    t_s: np.ndarray, values: np.ndarray, first_rate: np.ndarray, t_query: np.ndarray
) -> np.ndarray:
    """A true track sampled at ``t_s`` (s, increasing), read at ``t_query`` (s).

    ``values`` (n, k) are positions (m) or velocities; between samples they are interpolated
    linearly, after the last sample held, and before the first the first sample is moved at
    ``first_rate`` (k,) per second (the vehicle taken to move with its first velocity). The
    law of every receiver delay: :func:`delay_errors` and the simulator's receiver."""
    t = np.asarray(t_s, dtype=float)
    tq = np.asarray(t_query, dtype=float)
    v = np.asarray(values, dtype=float).reshape(t.shape[0], -1)
    out = np.empty((tq.shape[0], v.shape[1]))
    early = tq < t[0]
    for j in range(v.shape[1]):
        col = np.interp(tq, t, v[:, j])
        col[early] = v[0, j] + (tq[early] - t[0]) * float(first_rate[j])
        out[:, j] = col
    return out


def delay_errors(series: PositionSeries, delay_s: float) -> PositionSeries:
    """The errors of a receiver that reports the truth ``delay_s`` (s) earlier: each epoch's
    error plus truth(t - delay_s) - truth(t), with the truth of :func:`truth_track_m` read by
    :func:`interp_track`. A series without a true track (no speed, no truth) is unchanged."""
    n = len(series)
    has_truth = series.true_east_m is not None and series.true_north_m is not None
    if (series.speed_mps is None and not has_truth) or n == 0:
        return series.with_()
    te, tn = truth_track_m(series)
    t = np.asarray(series.t_s, dtype=float)
    ve, vn = truth_velocity_mps(series)
    then = interp_track(t, np.column_stack([te, tn]), np.array([ve[0], vn[0]]), t - float(delay_s))
    delta = np.vstack([then[:, 0] - te, then[:, 1] - tn, np.zeros(n)])
    return _add(series, delta)


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


def gm2_transition(
    dt_s: np.ndarray | float, tau_s: np.ndarray | float, var_m2: np.ndarray | float
) -> tuple[np.ndarray, np.ndarray]:
    """Exact discretisation over ``dt_s`` (s) of a critically damped second-order
    Gauss-Markov process, state (position m, rate m/s), correlation time ``tau_s`` (s),
    stationary position variance ``var_m2`` (m^2); the arguments broadcast together.
    Returns the transition F and the process noise Q, each (2, 2, *shape).

    Its spectrum falls as f^-4 beyond 1/(2 pi tau) where a first-order process falls as
    f^-2: a smooth drift (a receiver's filtered slow error, a slowly moving reflector)
    whose steps a first-order law would make far too large. With a = 1/tau the rate's
    stationary variance is a^2 var, and Q = P_inf - F P_inf F'."""
    dt, tau, var = np.broadcast_arrays(
        np.asarray(dt_s, float), np.asarray(tau_s, float), np.asarray(var_m2, float)
    )
    a = 1.0 / tau
    x = dt * a
    e2 = np.exp(-2.0 * x)
    e = np.exp(-x)
    f = np.array([[e * (1.0 + x), e * dt], [-e * a * x, e * (1.0 - x)]])
    q11 = var * (-np.expm1(-2.0 * x) - e2 * (2.0 * x + 2.0 * x * x))
    q22 = var * a * a * (-np.expm1(-2.0 * x) - e2 * (-2.0 * x + 2.0 * x * x))
    q12 = 2.0 * e2 * var * a * x * x
    return f, np.array([[q11, q12], [q12, q22]])


class _Gm2Process:
    """A stationary critically damped second-order Gauss-Markov process of ``size`` axes
    carried across calls (:func:`gm2_transition`); the first call starts from the
    stationary law."""

    def __init__(self, sigma: float, tau_s: float, rng: np.random.Generator, size: int) -> None:
        self.sigma, self.tau_s, self.rng, self.size = sigma, tau_s, rng, size
        self._x: np.ndarray | None = None  # (2, size): position, rate
        self._t_s = 0.0

    def draw(self, t_s: np.ndarray) -> np.ndarray:
        """Position samples (size, n) at the times ``t_s`` (s, after any earlier call's)."""
        t = np.asarray(t_s, dtype=float)
        out = np.empty((self.size, t.shape[0]))
        if t.shape[0] == 0:
            return out
        first = self._x is None
        if self._x is None:  # the stationary law at the first epoch, then steps from it
            sd = np.array([self.sigma, self.sigma / self.tau_s])[:, None]
            self._x = sd * self.rng.standard_normal((2, self.size))
            self._t_s = float(t[0])
        dt = _dt_s(np.concatenate(([self._t_s], t[1:] if first else t)))
        w = self.rng.standard_normal((dt.size, 2, self.size))
        distinct, index = np.unique(np.round(dt, 9), return_inverse=True)
        steps = []
        for d in distinct:
            f, q = gm2_transition(float(d), self.tau_s, self.sigma**2)
            steps.append((f, np.linalg.cholesky(q + 1e-18 * np.eye(2))))
        x = self._x
        if first:
            out[:, 0] = x[0]
        if distinct.size == 1 and dt.size > 1:
            x = _gm2_regular(x, float(dt[0]), self.tau_s, *steps[0], w, out[:, int(first) :])
        else:
            # variable steps: a loop over time, vectorised across axes
            for k in range(dt.size):
                f, chol = steps[index[k]]
                x = f @ x + chol @ w[k]
                out[:, k + int(first)] = x[0]
        self._x, self._t_s = x, float(t[-1])
        return out


def _gm2_regular(
    x0: np.ndarray,
    dt_s: float,
    tau_s: float,
    f: np.ndarray,
    chol: np.ndarray,
    w: np.ndarray,
    out: np.ndarray,
) -> np.ndarray:
    """The recursion x <- F x + chol w_k of :class:`_Gm2Process` for one step ``dt_s``
    everywhere (F, chol from :func:`gm2_transition` at ``dt_s``, ``tau_s``), run in C: F's
    characteristic polynomial is (1 - lam B)^2 (lam = exp(-dt/tau)), so each state is an IIR
    filter of the noise (numerator from adj(I - F B)) plus F^k x0, which has a closed form.
    Writes the positions into ``out`` (size, n) and returns the last state."""
    from scipy.signal import lfilter

    n = np.einsum("ij,kjs->kis", chol, w)  # (steps, 2, size) noise per step
    lag = np.zeros_like(n)
    lag[1:] = n[:-1]
    x = dt_s / tau_s
    lam = math.exp(-x)
    den = [1.0, -2.0 * lam, lam * lam]
    u_pos = n[:, 0] - f[1, 1] * lag[:, 0] + f[0, 1] * lag[:, 1]
    u_rate = n[:, 1] - f[0, 0] * lag[:, 1] + f[1, 0] * lag[:, 0]
    pos, rate = lfilter([1.0], den, u_pos, axis=0), lfilter([1.0], den, u_rate, axis=0)
    # F^k = lam^k [[1 + k x, k dt], [-k x / tau, 1 - k x]]
    k = np.arange(1, n.shape[0] + 1)[:, None]
    power = lam**k
    pos += power * ((1.0 + k * x) * x0[0] + k * dt_s * x0[1])
    rate += power * (-k * x / tau_s * x0[0] + (1.0 - k * x) * x0[1])
    out[:, :] = pos.T
    return np.stack([pos[-1], rate[-1]])


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


# Magnitude bounds. A finite but huge parameter (1e300) passed the finite check and then
# crashed the run (OverflowError squaring it) or printed NMEA positions hundreds of digits
# long; beyond these no receiver or compass is modelled. (A sum of many layers each within
# its bound is not bounded.)
MAX_BIAS_M = 100_000.0
"""The largest error magnitude (m): a bias per axis, a sigma, a multipath bias, a distance."""
MAX_WALK_M_PER_SQRT_S = MAX_BIAS_M / math.sqrt(30 * 86400.0)
"""The largest random walk (~62 m/sqrt(s)): 1 sigma after the longest run (30 days) within
MAX_BIAS_M."""
MAX_FACTOR = 1000.0
"""The largest noise_scale / correction factor (the gap tool's fits search 0.005-50)."""
MAX_FRAME_M = 1e6
"""The largest coordinate (m) in the scenario's local frame (as its waypoints_enu)."""
MAX_HEADING_SIGMA_DEG = 180.0
"""The largest heading noise (deg): beyond it the heading is all noise anyway."""


def _bounded(name: str, value: float, bound: float, unit: str, signed: bool = False) -> None:
    if not abs(value) <= bound:  # NaN fails too
        rule = f"within +-{bound:g}" if signed else f"<= {bound:g}"
        raise ConfigError(f"{name}={value!r}: must be {rule} {unit}".rstrip())


def _add(series: PositionSeries, delta: np.ndarray) -> PositionSeries:
    """Series plus a (3, n) east/north/up error."""
    return series.with_(
        east_m=np.asarray(series.east_m, dtype=float) + delta[0],
        north_m=np.asarray(series.north_m, dtype=float) + delta[1],
        up_m=np.asarray(series.up_m, dtype=float) + delta[2],
    )


def _gm_continue(
    t_s: np.ndarray,
    x0: np.ndarray,
    t0_s: float,
    sigma: float,
    tau_s: float,
    rng: np.random.Generator,
) -> np.ndarray:
    """Gauss-Markov samples at ``t_s`` continuing from the values ``x0`` (size,) at ``t0_s``
    (s, before ``t_s[0]``): the exact discretisation of :func:`gauss_markov_noise`."""
    t = np.asarray(t_s, dtype=float)
    size, n = x0.shape[0], t.shape[0]
    dt = _dt_s(np.concatenate(([t0_s], t)))
    phi = np.exp(-dt / tau_s)
    innov = sigma * np.sqrt(-np.expm1(-2.0 * dt / tau_s))
    w = rng.standard_normal((size, n))
    out = np.empty((size, n))
    x = np.asarray(x0, dtype=float).copy()
    for k in range(n):
        x = phi[k] * x + innov[k] * w[:, k]
        out[:, k] = x
    return out


class _GmProcess:
    """A stationary first-order Gauss-Markov process of ``size`` axes carried across calls:
    the first call starts from the stationary law, later ones continue from the last value."""

    def __init__(self, sigma: float, tau_s: float, rng: np.random.Generator, size: int) -> None:
        self.sigma, self.tau_s, self.rng, self.size = sigma, tau_s, rng, size
        self._x: np.ndarray | None = None
        self._t_s = 0.0

    def draw(self, t_s: np.ndarray) -> np.ndarray:
        """Samples (size, n) at the times ``t_s`` (s, after any earlier call's)."""
        t = np.asarray(t_s, dtype=float)
        if t.shape[0] == 0:
            return np.empty((self.size, 0))
        if self._x is None:
            out = gauss_markov_noise(t, self.sigma, self.tau_s, self.rng, self.size)
        else:
            out = _gm_continue(t, self._x, self._t_s, self.sigma, self.tau_s, self.rng)
        self._x, self._t_s = out[:, -1].copy(), float(t[-1])
        return out


class LayerRun(Protocol):
    """A GPS layer running over a receiver's output (from :meth:`GpsLayer.start`).

    ``step(batch)`` returns the next epochs of an error series (a :class:`PositionSeries`,
    times after the previous batch's) with the layer acting, continuing from its state;
    ``delay_s`` (s) is the latency it adds: the receiver solves for the truth that long before
    each epoch (``step`` itself leaves the errors of a pure delay alone)."""

    delay_s: float

    def step(self, batch: PositionSeries) -> PositionSeries: ...


class _Run:
    """A stateless running layer: ``step`` is a pure function of the batch."""

    delay_s: float = 0.0

    def __init__(self, fn: Callable[[PositionSeries], PositionSeries] | None = None) -> None:
        self._fn = fn

    def step(self, batch: PositionSeries) -> PositionSeries:
        assert self._fn is not None  # subclasses with state override step
        return self._fn(batch)


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
    def from_params(cls, params: Mapping[str, Any], where: str = "") -> Any:
        """Build from a table (``name`` optional). Unknown and missing parameters are a
        ConfigError, and so is a value not of its parameter's type, checked as every
        configuration key is (``x6wd.core.config``): a number real and finite (not a bool),
        an integer, a string. Errors name the key as ``where.key`` (``where`` as
        ``effects[0]``; default: the effect's name)."""
        label = f"{where} ({cls.name})" if where else f"effect {cls.name}"
        prefix = f"{where}." if where else ""
        data = {k: v for k, v in params.items() if k != "name"}
        if "name" in params and params["name"] != cls.name:
            raise ConfigError(f"{label}: effect name {params['name']!r} given to {cls.name}")
        fields_ = dataclasses.fields(cls)  # type: ignore[arg-type]
        names = [f.name for f in fields_]
        unknown = sorted(set(data) - set(names))
        if unknown:
            raise ConfigError(f"{label}: unknown parameter(s) {unknown}; valid: {sorted(names)}")
        required = [
            f.name
            for f in fields_
            if f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING
        ]
        for key in required:
            if key not in data:
                raise ConfigError(
                    f"{prefix}{key}: required ({cls.name} needs {', '.join(required)})"
                )
        hints = typing.get_type_hints(cls)
        for key, value in list(data.items()):
            data[key] = check_value(f"{prefix}{key}", value, hints[key], {})
        try:
            return cls(**data)
        except ConfigError as exc:
            raise ConfigError(f"{label}: {exc}") from None


class GpsLayer(_Params, abc.ABC):
    """A layer on the receiver's position output.

    ``stage`` orders the layers in a receiver: 0 acts on the solution, 1 on how it is
    printed (the NMEA minutes' rounding, the last thing a receiver does): every stage-1 layer
    runs after every stage-0 one, each stage in list order."""

    kind: ClassVar[str] = "gps"
    stage: ClassVar[int] = 0

    @abc.abstractmethod
    def start(self, rng: np.random.Generator) -> LayerRun:
        """The layer running over a receiver's output, drawing from ``rng`` (its own)."""

    def apply(self, series: PositionSeries, rng: np.random.Generator) -> PositionSeries:
        """The layer over a whole error series: :meth:`start` stepped once, a delay shown on
        the errors as :func:`delay_errors` does."""
        run = self.start(rng)
        out = run.step(series)
        return delay_errors(out, run.delay_s) if run.delay_s > 0 else out


@dataclass
class CompassPhysics:
    """The compass emulation's own physics as the compass layers change it in closed loop.

    The body-frame field is mapped field -> ``a`` field + ``b`` (3x3, and uT);
    ``declination_deg`` rotates the Earth's field (deg); ``lag_tau_s`` is the device filter's
    time constant (s); ``noise_deg2`` white heading noise to add (deg^2 per sample); ``tilt``
    the layers left to the heading domain. ``horizontal_ut`` (uT) is the emulation's
    horizontal field, to which hard-iron offsets are scaled.
    """

    horizontal_ut: float
    a: np.ndarray
    b: np.ndarray
    declination_deg: float
    lag_tau_s: float
    noise_deg2: float = 0.0
    tilt: tuple[Tilt, ...] = ()


class CompassLayer(_Params, abc.ABC):
    """A layer on the compass heading."""

    kind: ClassVar[str] = "compass"

    @abc.abstractmethod
    def act_on(self, phys: CompassPhysics) -> CompassPhysics:
        """``phys`` with this layer acting on the emulation's physics (same meaning as
        :meth:`apply` on a heading series)."""


# --- GPS layers -------------------------------------------------------------------------------


@dataclass(frozen=True)
class GaussMarkov(GpsLayer):
    """Gauss-Markov drift, independent per axis: sigma_m (stationary std, m), tau_s
    (correlation time, s); axes 'en' (horizontal, default), 'enu', 'e', 'n' or 'u'; order 1
    (exponential, default) or 2 (critically damped: smooth, :func:`gm2_transition`)."""

    name: ClassVar[str] = "gauss_markov"
    sigma_m: float
    tau_s: float
    axes: str = "en"
    order: int = 1

    def __post_init__(self) -> None:
        _positive("sigma_m", self.sigma_m, allow_zero=True)
        _bounded("sigma_m", self.sigma_m, MAX_BIAS_M, "m")
        _positive("tau_s", self.tau_s)
        _axes(self.axes)
        if self.order not in (1, 2):
            raise ConfigError(f"order={self.order!r}: must be 1 or 2")

    def start(self, rng: np.random.Generator) -> LayerRun:
        """The drift running on: one Gauss-Markov process per axis (stationary start)."""
        return _GaussMarkovRun(self, rng)


class _GaussMarkovRun(_Run):
    def __init__(self, layer: GaussMarkov, rng: np.random.Generator) -> None:
        self.idx = list(_axes(layer.axes))
        process = _GmProcess if layer.order == 1 else _Gm2Process
        self.gm = process(layer.sigma_m, layer.tau_s, rng, len(self.idx))

    def step(self, batch: PositionSeries) -> PositionSeries:
        delta = np.zeros((3, len(batch)))
        delta[self.idx] = self.gm.draw(batch.t_s)
        return _add(batch, delta)


@dataclass(frozen=True)
class RandomWalk(GpsLayer):
    """Random walk starting at zero: q_m_per_sqrt_s (m/sqrt(s)): increment std q*sqrt(dt)."""

    name: ClassVar[str] = "random_walk"
    q_m_per_sqrt_s: float
    axes: str = "en"

    def __post_init__(self) -> None:
        _positive("q_m_per_sqrt_s", self.q_m_per_sqrt_s, allow_zero=True)
        _bounded("q_m_per_sqrt_s", self.q_m_per_sqrt_s, MAX_WALK_M_PER_SQRT_S, "m/sqrt(s)")
        _axes(self.axes)

    def start(self, rng: np.random.Generator) -> LayerRun:
        """The walk running on from zero at the first epoch."""
        return _RandomWalkRun(self, rng)


class _RandomWalkRun(_Run):
    def __init__(self, layer: RandomWalk, rng: np.random.Generator) -> None:
        self.q, self.rng = layer.q_m_per_sqrt_s, rng
        self.idx = list(_axes(layer.axes))
        self._value: np.ndarray | None = None  # the walk at the last epoch (m)
        self._t_s = 0.0

    def step(self, batch: PositionSeries) -> PositionSeries:
        n, k = len(batch), len(self.idx)
        delta = np.zeros((3, n))
        if n:
            t = np.asarray(batch.t_s, dtype=float)
            if self._value is None:
                steps = self.q * np.sqrt(_dt_s(t)) * self.rng.standard_normal((k, n - 1))
                delta[self.idx, 1:] = np.cumsum(steps, axis=1)
            else:
                dt = _dt_s(np.concatenate(([self._t_s], t)))
                steps = self.q * np.sqrt(dt) * self.rng.standard_normal((k, n))
                delta[self.idx] = self._value[:, None] + np.cumsum(steps, axis=1)
            self._value, self._t_s = delta[self.idx, -1].copy(), float(t[-1])
        return _add(batch, delta)


@dataclass(frozen=True)
class Bias(GpsLayer):
    """Constant offset (m) east, north, up."""

    name: ClassVar[str] = "bias"
    east_m: float = 0.0
    north_m: float = 0.0
    up_m: float = 0.0

    def __post_init__(self) -> None:
        for key in ("east_m", "north_m", "up_m"):
            _bounded(key, getattr(self, key), MAX_BIAS_M, "m", signed=True)

    def start(self, rng: np.random.Generator) -> LayerRun:
        """The constant offset (no state, no draws)."""
        return _Run(self._offset)

    def _offset(self, series: PositionSeries) -> PositionSeries:
        n = len(series)
        delta = np.array([[self.east_m], [self.north_m], [self.up_m]]) * np.ones((1, n))
        return _add(series, delta)


@dataclass(frozen=True)
class Quantization(GpsLayer):
    """Rounding of the printed latitude/longitude to ``decimals`` places of ``unit``: NMEA
    minutes ("min", the default: ``ddmm.mmmmm``, 4 or 5 decimals on u-blox 5) or decimal
    degrees ("deg": ``dd.ddddd``, as CSV loggers, phone apps and many data sets print them;
    5 decimals are a 1.1 m x 0.7 m grid at 51.75 N).

    Acts on the absolute position (origin + implied truth + error); the error becomes the
    rounded position minus the truth, so the reported positions lie exactly on the lattice
    of :func:`quantization_step_m`. Up is untouched (altitude has its own 0.1 m format).
    """

    name: ClassVar[str] = "quantization"
    stage = 1  # the print stage (not annotated: a class constant, not a parameter)
    decimals: int = 5
    unit: str = "min"

    def __post_init__(self) -> None:
        if not isinstance(self.decimals, int) or not 0 <= self.decimals <= 9:
            raise ConfigError(f"decimals={self.decimals!r}: must be an integer 0..9")
        if self.unit not in QUANT_UNITS:
            raise ConfigError(
                f'unit={self.unit!r}: must be "min" (NMEA minutes, the default) or '
                '"deg" (decimal degrees)'
            )

    def to_params(self) -> dict[str, Any]:
        """As every layer's, without ``unit`` when it is the default minutes (the tables
        written before the unit existed, and NMEA ones now, read the same)."""
        out = super().to_params()
        if self.unit == "min":
            del out["unit"]
        return out

    @property
    def step_text(self) -> str:
        """The lattice in words, e.g. "1e-5 deg", "1e-4 min"."""
        return f"1e-{self.decimals} {self.unit}" if self.decimals else f"1 {self.unit}"

    def start(self, rng: np.random.Generator) -> LayerRun:
        """The rounding (no state, no draws)."""
        return _Run(self._round)

    def _round(self, series: PositionSeries) -> PositionSeries:
        lat0, lon0 = series.origin_lat_deg, series.origin_lon_deg
        e_per_deg, n_per_deg = metres_per_degree(lat0)
        te, tn = truth_track_m(series)
        lat = lat0 + (tn + np.asarray(series.north_m, dtype=float)) / n_per_deg
        lon = lon0 + (te + np.asarray(series.east_m, dtype=float)) / e_per_deg
        qlat = quantize_degrees(lat, self.decimals, self.unit)
        qlon = quantize_degrees(lon, self.decimals, self.unit)
        return series.with_(
            east_m=(qlon - lon0) * e_per_deg - te,
            north_m=(qlat - lat0) * n_per_deg - tn,
        )


def quantize_degrees(deg: np.ndarray, decimals: int, unit: str = "min") -> np.ndarray:
    """Degrees as printed: |deg| in minutes (NMEA, ``unit`` "min") or in degrees ("deg")
    rounded to ``decimals``, sign kept."""
    d = np.asarray(deg, dtype=float)
    if unit == "deg":
        return np.sign(d) * np.round(np.abs(d), decimals)
    minutes = np.round(np.abs(d) * 60.0, decimals)
    return np.sign(d) * minutes / 60.0


JUMP_TRIGGERS = ("auto", "poisson", "sat_change")


@dataclass(frozen=True)
class Jumps(GpsLayer):
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
        _bounded("sigma_m", self.sigma_m, MAX_BIAS_M, "m")
        _bounded("up_sigma_m", self.up_sigma_m, MAX_BIAS_M, "m")
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

    def start(self, rng: np.random.Generator) -> LayerRun:
        """The jumps running on: the current set's offset and satellite count are kept."""
        return _JumpsRun(self, rng)


class _JumpsRun(_Run):
    def __init__(self, layer: Jumps, rng: np.random.Generator) -> None:
        self.layer, self.rng = layer, rng
        self._scale = np.array([[layer.sigma_m], [layer.sigma_m], [layer.up_sigma_m]])
        self._offset: np.ndarray | None = None  # the current set's offset (3,), m
        self._nsats: Any = None  # satellites used at the last epoch
        self._t_s = 0.0

    def _changes(self, batch: PositionSeries, t: np.ndarray) -> np.ndarray:
        """New sets at each epoch of a batch after the first (epoch 0 against the last)."""
        n, layer = len(batch), self.layer
        mask = np.zeros(n, dtype=bool)
        if layer.trigger == "sat_change" and batch.nsats is None:
            return mask
        if batch.nsats is not None and layer.trigger != "poisson":
            ns = np.asarray(batch.nsats)
            mask[0] = self._nsats is not None and bool(ns[0] != self._nsats)
            mask[1:] = ns[1:] != ns[:-1]
        else:
            p = -np.expm1(-layer.rate_per_s * _dt_s(np.concatenate(([self._t_s], t))))
            mask[:] = self.rng.random(n) < p
        return mask

    def step(self, batch: PositionSeries) -> PositionSeries:
        n = len(batch)
        if n == 0:
            return _add(batch, np.zeros((3, 0)))
        t = np.asarray(batch.t_s, dtype=float)
        if self._offset is None:
            seg = np.cumsum(self.layer.change_mask(batch, self.rng))
            offs = self.rng.standard_normal((3, int(seg[-1]) + 1)) * self._scale
        else:
            seg = np.cumsum(self._changes(batch, t))
            new = self.rng.standard_normal((3, int(seg[-1]))) * self._scale
            offs = np.concatenate((self._offset[:, None], new), axis=1)
        self._offset, self._t_s = offs[:, -1].copy(), float(t[-1])
        self._nsats = None if batch.nsats is None else np.asarray(batch.nsats)[-1]
        return _add(batch, offs[:, seg])


@dataclass(frozen=True)
class Outages(GpsLayer):
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

    def start(self, rng: np.random.Generator) -> LayerRun:
        """The outage chain running on from its state at the last epoch."""
        return _OutagesRun(self, rng)


class _OutagesRun(_Run):
    def __init__(self, layer: Outages, rng: np.random.Generator) -> None:
        self.layer, self.rng = layer, rng
        self._up: bool | None = None  # the chain's state at the last epoch
        self._t_s = 0.0

    def step(self, batch: PositionSeries) -> PositionSeries:
        t = np.asarray(batch.t_s, dtype=float)
        n = t.shape[0]
        if self._up is None or n == 0:
            up = self.layer.states(t, self.rng)
        else:
            a, b = 1.0 / self.layer.mean_up_s, 1.0 / self.layer.mean_down_s
            e = np.exp(-(a + b) * _dt_s(np.concatenate(([self._t_s], t))))
            stay_up = (b + a * e) / (a + b)
            stay_down = (a + b * e) / (a + b)
            u = np.asarray(self.rng.random(n))
            up = np.zeros(n, dtype=bool)
            state = self._up
            for k in range(n):
                state = bool(u[k] < stay_up[k]) if state else bool(u[k] >= stay_down[k])
                up[k] = state
        if n:
            self._up, self._t_s = bool(up[-1]), float(t[-1])
        return batch.with_(valid=np.asarray(batch.valid, dtype=bool) & up)


@dataclass(frozen=True)
class Outage(GpsLayer):
    """One scripted fix outage: no fix (valid False) from ``start_s`` for ``duration_s``
    (seconds on the series' clock: simulated seconds since the scenario's start in ``x6wd
    sim`` and hardware in the loop), e.g. to test the robot's reaction to losing the GPS at a
    known time. A test fault, not a fitted effect: the gap tool does not look for it (it is
    not in ``GPS_EFFECT_NAMES``; ``outages`` is the random one)."""

    name: ClassVar[str] = "outage"
    start_s: float
    duration_s: float

    def __post_init__(self) -> None:
        _positive("start_s", self.start_s, allow_zero=True)
        _positive("duration_s", self.duration_s)

    def start(self, rng: np.random.Generator) -> LayerRun:
        """The outage window (no state, no draws)."""
        return _Run(self._cut)

    def _cut(self, series: PositionSeries) -> PositionSeries:
        t = np.asarray(series.t_s, dtype=float)
        down = (t >= self.start_s) & (t < self.start_s + self.duration_s)
        return series.with_(valid=np.asarray(series.valid, dtype=bool) & ~down)


@dataclass(frozen=True)
class Latency(GpsLayer):
    """Reported position is the truth of ``delay_s`` earlier (plus the existing error).

    In the simulator's receiver the delay moves what the receiver solves for (position and
    velocity: :attr:`LayerRun.delay_s`). On an error series (:meth:`apply`) the error added is
    truth(t - delay_s) - truth(t) (:func:`delay_errors`; the truth track explicit or implied by
    speed_mps/course_deg, before the first epoch the vehicle taken to move with its first
    velocity). A static series is unchanged.
    """

    name: ClassVar[str] = "latency"
    delay_s: float

    def __post_init__(self) -> None:
        _positive("delay_s", self.delay_s, allow_zero=True)

    def start(self, rng: np.random.Generator) -> LayerRun:
        """A pure delay: the receiver solves for the truth ``delay_s`` earlier."""
        return _DelayRun(self.delay_s)


class _DelayRun(_Run):
    def __init__(self, delay_s: float) -> None:
        self.delay_s = float(delay_s)

    def step(self, batch: PositionSeries) -> PositionSeries:
        return batch.with_()


@dataclass(frozen=True)
class MultipathZone(GpsLayer):
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
        for key in ("x1_m", "y1_m", "x2_m", "y2_m"):  # 1e300 overflowed the wall's geometry
            _bounded(key, getattr(self, key), MAX_FRAME_M, "m", signed=True)
        _bounded("sigma_m", self.sigma_m, MAX_BIAS_M, "m")
        _bounded("bias_m", self.bias_m, MAX_BIAS_M, "m", signed=True)
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

    def start(self, rng: np.random.Generator) -> LayerRun:
        """The zone running on: its Gauss-Markov noise is drawn at every epoch (so the random
        stream does not depend on the path) and acts where the TRUE position is near."""
        return _MultipathRun(self, rng)


class _MultipathRun(_Run):
    def __init__(self, layer: MultipathZone, rng: np.random.Generator) -> None:
        self.layer = layer
        self.gm = _GmProcess(layer.sigma_m, layer.tau_s, rng, 2)

    def step(self, batch: PositionSeries) -> PositionSeries:
        z = self.layer
        te, tn = truth_track_m(batch)
        dist, ux, uy = z.distance_to_wall_m(te, tn)
        inside = dist <= z.distance_m
        noise = self.gm.draw(batch.t_s)
        delta = np.zeros((3, len(batch)))
        delta[0] = np.where(inside, z.bias_m * ux + noise[0], 0.0)
        delta[1] = np.where(inside, z.bias_m * uy + noise[1], 0.0)
        return _add(batch, delta)


# --- receiver-side layers: what a receiver does to its own solution -------------------------
#
# These act in either direction against the model: a real receiver's navigation filter,
# static hold and SBAS / differential corrections make it SMOOTHER or BETTER than a raw
# single-epoch solution, and a noise or slow-error factor above 1 makes it worse. They are
# deterministic transforms of the error (no random draws), each running over the valid
# epochs only (a receiver without a fix keeps its filter state; the next fix continues
# from it with the actual time step).


class _LowPass:
    """First-order low-pass (time constant ``tau_s``) of ``k`` axes over the valid epochs,
    carried across batches: y_k = y_{k-1} + (1 - exp(-dt/tau)) (x_k - y_{k-1}), exact for an
    input held between samples; the first valid sample starts it (no start-up transient)."""

    def __init__(self, tau_s: float, k: int) -> None:
        self.tau_s, self.k = float(tau_s), k
        self._y: np.ndarray | None = None  # (k,) the output at the last valid epoch
        self._t_s = 0.0

    def run(self, t_s: np.ndarray, x: np.ndarray, valid: np.ndarray) -> np.ndarray:
        """Outputs (k, n) for inputs ``x`` (k, n) at ``t_s``; invalid epochs pass ``x``."""
        out = np.array(x, dtype=float, copy=True)
        idx = np.flatnonzero(valid)
        if idx.size == 0:
            return out
        xv = out[:, idx]
        tv = np.asarray(t_s, dtype=float)[idx]
        if self._y is None:
            y0, t_prev, first = xv[:, 0], tv[0], 1
            yv = np.empty_like(xv)
            yv[:, 0] = y0
        else:
            y0, t_prev, first = self._y, self._t_s, 0
            yv = np.empty_like(xv)
        dt = np.diff(np.concatenate(([t_prev], tv[first:]))) if tv.size > first else np.zeros(0)
        if dt.size and np.any(dt <= 0):
            raise ValueError(_not_rising_text(np.concatenate(([t_prev], tv[first:])), dt))
        gain = -np.expm1(-dt / self.tau_s)
        if dt.size and np.all(dt == dt[0]):
            # one step everywhere: a first-order IIR filter, run in C by lfilter
            from scipy.signal import lfilter

            g = gain[0]
            yv[:, first:] = lfilter(
                [g], [1.0, -(1.0 - g)], xv[:, first:], axis=1, zi=((1.0 - g) * y0)[:, None]
            )[0]
        elif dt.size:
            yv[:, first:] = _irregular_low_pass(y0, xv[:, first:], dt / self.tau_s, gain)
        out[:, idx] = yv
        self._y, self._t_s = yv[:, -1].copy(), float(tv[-1])
        return out


def _irregular_low_pass(
    y0: np.ndarray, x: np.ndarray, decay: np.ndarray, gain: np.ndarray
) -> np.ndarray:
    """y_j = y_{j-1} + gain_j (x_j - y_{j-1}) from y0, gain_j = 1 - exp(-decay_j), vectorised
    (a Python loop cost 5 us a sample, the bulk of a calibration on a log with outages): in
    closed form y_j = exp(-s_j) (y0 + sum_i<=j gain_i x_i exp(s_i)), s the cumulative decay,
    taken in blocks spanning at most 500 time constants and written relative to each block's
    end, so that no exponential overflows; rounding error stays at the loop's level."""
    s = np.cumsum(decay)
    out = np.empty_like(x)
    y, start, base = np.asarray(y0, dtype=float), 0, 0.0
    while start < s.size:
        stop = max(int(np.searchsorted(s, s[start] + 500.0, side="right")), start + 1)
        end = s[stop - 1]
        weighted = np.cumsum(gain[start:stop] * x[:, start:stop] * np.exp(s[start:stop] - end), 1)
        out[:, start:stop] = np.exp(end - s[start:stop]) * (
            y[:, None] * np.exp(base - end) + weighted
        )
        y, start, base = out[:, stop - 1], stop, end
    return out


def _axis_rows(series: PositionSeries, idx: list[int]) -> np.ndarray:
    rows = (series.east_m, series.north_m, series.up_m)
    return np.vstack([np.asarray(rows[i], dtype=float) for i in idx])


def _with_rows(series: PositionSeries, idx: list[int], rows: np.ndarray) -> PositionSeries:
    names = ("east_m", "north_m", "up_m")
    return series.with_(**{names[i]: rows[j] for j, i in enumerate(idx)})


@dataclass(frozen=True)
class NavFilter(GpsLayer):
    """The receiver's navigation filter smoothing its solution: the error passes ``order``
    cascaded first-order low-passes of time constant ``tau_s / order`` each, on ``axes``;
    ``tau_s`` (s) is the filter's total time constant (its delay at low frequencies), the
    same for either order, which is what one log pins down best (the order less so).

    A Kalman navigation filter predicts with the Doppler velocity, so the motion itself is
    not lagged: only the error is smoothed (this layer acts on the error series). Order 1
    turns white code noise into a Gauss-Markov error (Allan deviation rising as tau^0.5 below
    ``tau_s``); order 2 makes it smooth (rising as tau^1), as a constant-velocity filter does.
    Makes the receiver quieter than the model at scales shorter than ``tau_s``; never louder.
    """

    name: ClassVar[str] = "nav_filter"
    tau_s: float
    order: int = 1
    axes: str = "en"

    def __post_init__(self) -> None:
        _positive("tau_s", self.tau_s)
        if self.order not in (1, 2):
            raise ConfigError(f"nav_filter order={self.order!r}: must be 1 or 2")
        _axes(self.axes)

    def start(self, rng: np.random.Generator) -> LayerRun:
        """The filter running on from its state (no draws)."""
        return _NavFilterRun(self)


class _NavFilterRun(_Run):
    def __init__(self, layer: NavFilter) -> None:
        self.idx = list(_axes(layer.axes))
        tau_stage_s = layer.tau_s / layer.order
        self.stages = [_LowPass(tau_stage_s, len(self.idx)) for _ in range(layer.order)]

    def step(self, batch: PositionSeries) -> PositionSeries:
        valid = np.asarray(batch.valid, dtype=bool)
        x = _axis_rows(batch, self.idx)
        for stage in self.stages:
            x = stage.run(batch.t_s, x, valid)
        return _with_rows(batch, self.idx, x)


class _SplitScaleRun(_Run):
    """y = slow * lp(x) + fast * (x - lp(x)), lp a first-order low-pass of ``tau_s``."""

    def __init__(self, tau_s: float, slow: float, fast: float, axes: str) -> None:
        self.idx = list(_axes(axes))
        self.lp = _LowPass(tau_s, len(self.idx))
        self.slow, self.fast = float(slow), float(fast)

    def step(self, batch: PositionSeries) -> PositionSeries:
        valid = np.asarray(batch.valid, dtype=bool)
        x = _axis_rows(batch, self.idx)
        low = self.lp.run(batch.t_s, x, valid)
        y = np.where(valid, self.slow * low + self.fast * (x - low), x)
        return _with_rows(batch, self.idx, y)


@dataclass(frozen=True)
class NoiseScale(GpsLayer):
    """Short-term noise ``factor`` times the model's (dimensionless; < 1 a quieter receiver,
    > 1 a noisier one): the part of the error faster than ``split_tau_s`` (s; a first-order
    high-pass of the error) is multiplied by ``factor``, the slower part kept."""

    name: ClassVar[str] = "noise_scale"
    factor: float
    split_tau_s: float = 10.0
    axes: str = "en"

    def __post_init__(self) -> None:
        _positive("factor", self.factor, allow_zero=True)
        _bounded("factor", self.factor, MAX_FACTOR, "")
        _positive("split_tau_s", self.split_tau_s)
        _axes(self.axes)

    def start(self, rng: np.random.Generator) -> LayerRun:
        """The split filter running on (no draws)."""
        return _SplitScaleRun(self.split_tau_s, 1.0, self.factor, self.axes)


@dataclass(frozen=True)
class Correction(GpsLayer):
    """SBAS or differential correction: the slow error (the part slower than ``tau_s``, s: a
    first-order low-pass of the error, which holds the ionosphere, orbit and clock terms a
    correction removes) multiplied by ``factor`` (dimensionless; < 1 corrected, e.g. 0.5 for
    SBAS halving it; > 1 a receiver whose slow error is larger than the model's). The fast
    part is kept."""

    name: ClassVar[str] = "correction"
    factor: float
    tau_s: float = 60.0
    axes: str = "en"

    def __post_init__(self) -> None:
        _positive("factor", self.factor, allow_zero=True)
        _bounded("factor", self.factor, MAX_FACTOR, "")
        _positive("tau_s", self.tau_s)
        _axes(self.axes)

    def start(self, rng: np.random.Generator) -> LayerRun:
        """The split filter running on (no draws)."""
        return _SplitScaleRun(self.tau_s, self.factor, 1.0, self.axes)


@dataclass(frozen=True)
class StaticHold(GpsLayer):
    """Static hold: while the true speed is below ``speed_threshold_mps`` (m/s) the reported
    position is frozen; it is let go (and held again at the new solution) when the solution
    has moved more than ``exit_distance_m`` (m, horizontal) from it, or at once when the speed
    reaches the threshold. All three axes are held together. A static receiver's log becomes
    runs of identical fixes with steps of about ``exit_distance_m``."""

    name: ClassVar[str] = "static_hold"
    exit_distance_m: float
    speed_threshold_mps: float = 0.5

    def __post_init__(self) -> None:
        _positive("exit_distance_m", self.exit_distance_m)
        _bounded("exit_distance_m", self.exit_distance_m, MAX_BIAS_M, "m")
        _positive("speed_threshold_mps", self.speed_threshold_mps, allow_zero=True)

    def start(self, rng: np.random.Generator) -> LayerRun:
        """The hold running on from the position held at the last epoch (no draws)."""
        return _StaticHoldRun(self)


class _StaticHoldRun(_Run):
    def __init__(self, layer: StaticHold) -> None:
        self.layer = layer
        self._held: np.ndarray | None = None  # held absolute position (3,), m

    def step(self, batch: PositionSeries) -> PositionSeries:
        n = len(batch)
        te, tn = truth_track_m(batch)
        truth = np.vstack([te, tn, np.zeros(n)])
        err = _axis_rows(batch, [0, 1, 2])
        pos = truth + err
        speed = (
            np.zeros(n)
            if batch.speed_mps is None
            else np.nan_to_num(np.asarray(batch.speed_mps, dtype=float))
        )
        valid = np.asarray(batch.valid, dtype=bool)
        out = pos.copy()
        held = self._held
        exit2 = self.layer.exit_distance_m**2
        thr = self.layer.speed_threshold_mps
        for k in range(n):
            if not valid[k]:
                continue
            if speed[k] >= thr:
                held = None
                continue
            p = pos[:, k]
            if held is None or (p[0] - held[0]) ** 2 + (p[1] - held[1]) ** 2 > exit2:
                held = p.copy()
            out[:, k] = held
        self._held = held
        return _with_rows(batch, [0, 1, 2], out - truth)


# --- compass layers ---------------------------------------------------------------------------


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
class Declination(CompassLayer):
    """Magnetic declination (deg, east positive): the compass reads heading - declination."""

    name: ClassVar[str] = "declination"
    declination_deg: float

    def act_on(self, phys: CompassPhysics) -> CompassPhysics:
        """The site's field rotated: declination adds up (it acts before any iron, as the
        Earth's field does, whatever the layer's place in the list)."""
        return replace(phys, declination_deg=phys.declination_deg + self.declination_deg)

    def apply(self, series: HeadingSeries, rng: np.random.Generator) -> HeadingSeries:
        return _compass_out(series, np.asarray(series.heading_deg) - self.declination_deg)


@dataclass(frozen=True)
class HardIron(CompassLayer):
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

    def act_on(self, phys: CompassPhysics) -> CompassPhysics:
        """The offset, scaled from ``horizontal_field_ut`` to the emulation's horizontal
        field, so the heading error against heading is the layer's."""
        scale = phys.horizontal_ut / self.horizontal_field_ut
        return replace(phys, b=phys.b + np.array([self.bx_ut * scale, self.by_ut * scale, 0.0]))

    def apply(self, series: HeadingSeries, rng: np.random.Generator) -> HeadingSeries:
        h = np.radians(np.asarray(series.heading_deg, dtype=float))
        H = self.horizontal_field_ut
        x = H * np.cos(h) + self.bx_ut
        y = -H * np.sin(h) + self.by_ut
        scale = _field_magnitude(series, H) / H
        return _compass_out(series, np.degrees(np.arctan2(-y, x)), field_ut=np.hypot(x, y) * scale)


@dataclass(frozen=True)
class SoftIron(CompassLayer):
    """Soft iron: the horizontal field is multiplied by a symmetric matrix with principal
    gains (1 + k, 1 - k) along body axes rotated by ``axis_deg``: error twice per turn,
    amplitude about k rad."""

    name: ClassVar[str] = "soft_iron"
    k: float
    axis_deg: float = 0.0

    def __post_init__(self) -> None:
        if not -0.9 < self.k < 0.9:
            raise ConfigError(f"soft_iron k={self.k!r}: must be in (-0.9, 0.9)")

    def act_on(self, phys: CompassPhysics) -> CompassPhysics:
        """The symmetric matrix R(axis) diag(1+k, 1-k) R(axis)^T on x/y, after the map so far."""
        c, s = math.cos(math.radians(self.axis_deg)), math.sin(math.radians(self.axis_deg))
        rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        m = rot @ np.diag([1.0 + self.k, 1.0 - self.k, 1.0]) @ rot.T
        return replace(phys, a=m @ phys.a, b=m @ phys.b)

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
class Tilt(CompassLayer):
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

    def act_on(self, phys: CompassPhysics) -> CompassPhysics:
        """No partial-compensation model in the emulation: applied in the heading domain
        before the device's physics (``compass.CompassSetup.device_heading_deg``)."""
        return replace(phys, tilt=(*phys.tilt, self))

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
class HeadingNoise(CompassLayer):
    """White heading noise, sigma_deg (deg) per sample."""

    name: ClassVar[str] = "heading_noise"
    sigma_deg: float

    def __post_init__(self) -> None:
        _positive("sigma_deg", self.sigma_deg, allow_zero=True)
        _bounded("sigma_deg", self.sigma_deg, MAX_HEADING_SIGMA_DEG, "deg")

    def act_on(self, phys: CompassPhysics) -> CompassPhysics:
        """White heading noise adds up in variance (turned into field noise by the caller)."""
        return replace(phys, noise_deg2=phys.noise_deg2 + self.sigma_deg**2)

    def apply(self, series: HeadingSeries, rng: np.random.Generator) -> HeadingSeries:
        noise = self.sigma_deg * rng.standard_normal(len(series))
        return _compass_out(series, np.asarray(series.heading_deg, dtype=float) + noise)


@dataclass(frozen=True)
class HeadingLag(CompassLayer):
    """First-order lag of the heading filter, time constant tau_s (CMPS10: its filter takes
    about 640 ms to refresh fully, i.e. tau about 0.21 s). Exact for a heading held between
    samples: y_k = y_{k-1} + (1 - exp(-dt/tau)) * wrap(x_k - y_{k-1}), across north."""

    name: ClassVar[str] = "heading_lag"
    tau_s: float = 0.64 / 3.0

    def __post_init__(self) -> None:
        _positive("tau_s", self.tau_s)

    def act_on(self, phys: CompassPhysics) -> CompassPhysics:
        """Added to the device's filter: a cascade of first-order lags has the sum of their
        delays at low frequency."""
        return replace(phys, lag_tau_s=phys.lag_tau_s + self.tau_s)

    def apply(self, series: HeadingSeries, rng: np.random.Generator) -> HeadingSeries:
        x = np.asarray(series.heading_deg, dtype=float)
        n = x.shape[0]
        y = np.empty(n)
        if n:
            gain = -np.expm1(-_dt_s(series.t_s) / self.tau_s)
            y[0] = x[0]
            for k in range(1, n):
                y[k] = y[k - 1] + gain[k - 1] * wrap_deg(x[k] - y[k - 1])
        return _compass_out(series, y)


GpsEffect = (
    GaussMarkov
    | RandomWalk
    | Bias
    | Quantization
    | Jumps
    | Outages
    | Outage
    | Latency
    | MultipathZone
    | NavFilter
    | NoiseScale
    | StaticHold
    | Correction
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
        Outage,
        Latency,
        MultipathZone,
        NavFilter,
        NoiseScale,
        StaticHold,
        Correction,
        HardIron,
        SoftIron,
        Tilt,
        Declination,
        HeadingLag,
        HeadingNoise,
    )
}


def effect_from_params(params: Mapping[str, Any], where: str = "") -> Any:
    """Construct an effect from a table with a ``name`` key (as in a scenario's [[effects]]);
    errors name the key as ``where.key`` (``where`` as ``effects[0]``)."""
    name = params.get("name")
    if not isinstance(name, str) or name not in EFFECTS:
        raise ConfigError(
            f"{where or 'effects'}.name: unknown name {name!r}; valid: {sorted(EFFECTS)}"
        )
    return EFFECTS[name].from_params(params, where)


def apply_effects(series: Any, effects: Any, rng: np.random.Generator) -> Any:
    """Apply a sequence of effects in order; GPS effects to a PositionSeries, compass ones to
    a HeadingSeries (an effect of the other kind is a ConfigError)."""
    for eff in effects:
        gps = eff.kind == "gps"
        if gps != isinstance(series, PositionSeries):
            raise ConfigError(f"effect {eff.name} cannot act on a {type(series).__name__}")
        series = eff.apply(series, rng)
    return series
