"""The simulated GPS receiver: the full error model at two fidelity levels.

``GnssModel`` is built from explicit parts (a :class:`~sim_backend.sky.SatelliteSet`, the
origin, the start time, an :class:`~sim_backend.atmosphere.Atmosphere`, optional walls, the
receiver parameters and a ``numpy.random.Generator``) and turns true positions into what a
u-blox NEO-5 would report (:class:`~sim_backend.epoch.GnssEpoch`):

- ``step(t_s, lat, lon, alt, vel_enu)``: one epoch, closed loop (keeps process state).
- ``batch(t_s[], lat[], lon[], alt[], vel_enu[])``: all epochs at once, vectorised over
  (epochs x satellites); returns a columnar :class:`GnssBatch` (``.epoch(i)``, ``.epochs()``).

Both share the same per-epoch physics; the common part is the *sky pipeline*: satellite
positions, az/el from the true receiver position, the elevation mask, walls (line of sight,
reflections: extra path and -3 dB per bounce), per-satellite C/N0 from the atmosphere, the
tracking cutoff, and a channel limit (the strongest ``max_channels`` satellites are used).

Fidelity ``"seed"`` (the seed papers' model): the position error is drawn WHITE per epoch,
east/north each N(0, (HDOP*sigma_UERE)^2 / 2), up N(0, (VDOP*sigma_UERE)^2). sigma_UERE is
either ``"modelled"`` (RMS over the used satellites of the per-satellite error budget:
residual ionosphere and troposphere, satellite clock/ephemeris, multipath, receiver code noise,
and the squared extra path of reflected signals) or the seed-003 form
``sqrt(RE^2 + ASE^2 + LCE(position)^2)`` with LCE read from an :class:`LceGrid`. White draws
are what the papers do; real errors are strongly time-correlated (lag-1 autocorrelation
0.95-0.999 at 1 Hz in real static logs) because the dominant sources (atmosphere, orbits,
multipath geometry) change over minutes, so the seed level is right in distribution per epoch
but wrong in its time structure.

Fidelity ``"pseudorange"``: per-satellite range errors, each a first-order Gauss-Markov process
with an exact discretisation (meaning independent of the update rate), plus the walls'
deterministic NLOS extra path; the position is the weighted least-squares solution (E, N, U,
receiver clock) of those errors. Signals that arrive THROUGH walls or roofs (buildings with
materials) have the C/N0 lowered by the materials' loss (so larger code noise and a smaller
WLS weight) and an indoor NLOS/multipath delay: positive, exponentially distributed with a
mean that grows with the materials' loss on the path (``indoor_delay_scale_m``),
time-correlated (Gauss-Markov, tau ``tau_indoor_s``); the receiver does not know which signals
those are. The solve is linearised at the true position: for metre-level errors over 20,000 km
ranges this equals the receiver's iterated solution to better than a micrometre. DOP,
rising/setting and blocked satellites, satellite-set jumps and time correlation then come out
of the physics.

Conventions: ``t_s`` seconds since the scenario start; ``alt_m`` above mean sea level with a
constant ``geoid_sep_m`` (ellipsoid = MSL + separation); ENU frames are the origin's.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from datetime import UTC, datetime, timedelta
from typing import Any, Literal, Protocol

import numpy as np

from sim_backend.atmosphere import Atmosphere
from sim_backend.epoch import GnssEpoch, SimSat
from sim_backend.geodesy import (
    ecef_to_lla,
    enu_rotation,
    lla_to_ecef,
    utc_to_gps_seconds,
)
from sim_backend.geoid import geoid_separation_m
from sim_backend.sky import DEFAULT_MASK_DEG, SatelliteSet, batched_inverse
from x6wd.core.errors import ConfigError

Fidelity = Literal["seed", "pseudorange"]
FIDELITIES: tuple[str, ...] = ("seed", "pseudorange")
NAV5_PDOP_MASK = 25.0
"""A NEO-5's default NAV5 PDOP mask: a solution with a larger PDOP is reported as no fix
(docs/simulator.md)."""
CA_CHIP_M = 293.0522  # C/A code chip length (c / 1.023 MHz)
FADE_UP_DB = 5.0  # fading above the mean C/N0 allowed for when bounding a reflection search


# ---------------------------------------------------------------- parameters


@dataclass(frozen=True, eq=False)  # eq by identity: it holds an array
class LceGrid:
    """Seed-003 local characteristic error map: 1-sigma range error (m) per grid cell.

    ``sigma_m[i, j]`` covers north in ``[north0_m + i*cell_m, +cell_m)`` and east in
    ``[east0_m + j*cell_m, +cell_m)`` of the origin's ENU frame; ``outside_m`` applies
    beyond the map.
    """

    east0_m: float
    north0_m: float
    cell_m: float
    sigma_m: np.ndarray
    outside_m: float = 0.0

    def __post_init__(self) -> None:
        grid = np.asarray(self.sigma_m, dtype=float)
        if grid.ndim != 2 or grid.size == 0:
            raise ConfigError(f"lce.sigma_m must be a non-empty 2-D grid, got shape {grid.shape}")
        if not np.all(np.isfinite(grid)) or np.any(grid < 0):
            raise ConfigError("lce.sigma_m must be finite and >= 0 m")
        if not self.cell_m > 0:
            raise ConfigError(f"lce.cell_m must be > 0 m, got {self.cell_m}")
        if not self.outside_m >= 0:
            raise ConfigError(f"lce.outside_m must be >= 0 m, got {self.outside_m}")
        object.__setattr__(self, "sigma_m", grid)

    def at(self, east_m: np.ndarray | float, north_m: np.ndarray | float) -> np.ndarray:
        """LCE 1-sigma (m) at local east/north positions (m), vectorised."""
        j = np.floor((np.asarray(east_m, dtype=float) - self.east0_m) / self.cell_m)
        i = np.floor((np.asarray(north_m, dtype=float) - self.north0_m) / self.cell_m)
        n_i, n_j = self.sigma_m.shape
        inside = (i >= 0) & (i < n_i) & (j >= 0) & (j < n_j)
        ii = np.where(inside, i, 0).astype(np.int64)
        jj = np.where(inside, j, 0).astype(np.int64)
        return np.where(inside, self.sigma_m[ii, jj], self.outside_m)


@dataclass(frozen=True)
class ReceiverParams:
    """Error budget and behaviour of the receiver. Sigmas are 1-sigma metres of range error;
    ``tau_*_s`` are Gauss-Markov correlation times (s)."""

    # Seed level
    seed_uere: Literal["modelled", "re_ase_lce"] = "modelled"
    re_sigma_m: float = 0.5  # seed-003 RE (receiver error: noise + receiver multipath)
    ase_sigma_m: float | None = None  # seed-003 ASE; None: the modelled atmosphere+orbit part
    lce: LceGrid | None = None  # seed-003 local characteristic error map
    # Residual ionosphere after the broadcast (Klobuchar) correction, as a fraction of the
    # modelled delay; Klobuchar removes about half of it (RMS). Split into a part common to all
    # satellites (mostly absorbed by the clock and height) and a per-satellite part.
    iono_residual_frac: float = 0.5
    iono_common_share: float = 0.7  # fraction of the residual variance that is common
    tau_iono_s: float = 1800.0
    tropo_residual_frac: float = 0.05  # after the receiver's standard troposphere model
    tau_tropo_s: float = 3600.0
    # Broadcast satellite clock + ephemeris error per satellite. 1.8 m is above the broadcast
    # SISRE of the u-blox 5 era (about 1-1.5 m RMS): it also stands for what the model leaves
    # out (the receiver's own filter and residual models), tuned with the multipath below so
    # the open-sky CEP50 over 24 h is the NEO-5 datasheet's 2.5 m (tests/test_gnss.py).
    sisre_sigma_m: float = 1.8
    tau_sisre_s: float = 3600.0
    # Line-of-sight code multipath at zenith, x(1+3 exp(-el/15 deg)): a small patch antenna
    # low above the ground, no choke ring. Its correlation time is that of a static antenna
    # (ground and nearby reflectors change their phase over minutes as the satellite moves):
    # real static u-blox logs step 2-18 cm per second (tests/test_gnss.py).
    multipath_sigma_m: float = 1.3
    tau_multipath_s: float = 300.0
    nlos_sigma_frac: float = 0.1  # jitter of a reflected path, fraction of its extra length
    # Indoor (through-obstruction) NLOS/multipath delay, used only for signals that arrive
    # through walls or roofs (buildings with materials): a positive, exponentially distributed,
    # time-correlated extra delay whose mean is indoor_delay_m at indoor_ref_loss_db of
    # material loss on the path and grows as the amplitude ratio 10^((loss - ref)/20),
    # capped at indoor_delay_max_m; correlation time tau_indoor_s. See indoor_delay_scale_m.
    indoor_delay_m: float = 3.0
    indoor_ref_loss_db: float = 10.0
    indoor_delay_max_m: float = 100.0
    tau_indoor_s: float = 60.0
    # Code tracking (DLL) noise: sigma = chip * sqrt(Bn d / (2 C/N0) (1 + 2 / (T C/N0 (2-d))))
    dll_bandwidth_hz: float = 0.5
    correlator_spacing_chips: float = 0.5
    integration_s: float = 0.02
    smoothing_tau_s: float = 100.0  # carrier smoothing (Hatch filter); 0: raw code noise
    max_channels: int = 12  # satellites in the solution (GSA lists 12)
    vel_sigma_mps: float = 0.08  # Doppler velocity noise per horizontal axis
    vel_up_sigma_mps: float = 0.15
    course_min_speed_mps: float = 0.3  # below this the course is left empty (u-blox at rest)
    # Geoid separation (m, MSL above the ellipsoid) printed in GGA; None: the geoid model
    # (sim_backend.geoid) at the origin, as a receiver's built-in model gives.
    geoid_sep_m: float | None = None
    # Signal: C/N0 = the atmosphere's received power (isotropic antenna) - N0 + the antenna's
    # gain pattern - implementation loss + multipath fading. Patch antenna pattern (dBic):
    # G(el) = zenith - (zenith - horizon) (1 - sin el)^shape.
    antenna_zenith_dbic: float = -2.0
    antenna_horizon_dbic: float = -22.0
    antenna_shape: float = 1.5
    # Front end and correlation losses (quantisation, filtering, a passive patch's feed):
    # with the antenna pattern, calibrated so that the C/N0 medians match real u-blox 5 GSV.
    implementation_loss_db: float = 5.0
    # Multipath fading: Rician with K factor (dB) rising linearly in sin(el) from the horizon
    # value to the zenith value; the diffuse part is complex Gauss-Markov (tau_fade_s), so
    # the fade in dB is time-correlated. Mean power is kept (the fade averages 0 dB in power).
    fade_k_zenith_db: float = 12.0
    fade_k_horizon_db: float = 0.0
    tau_fade_s: float = 30.0
    # Tracking: a satellite is acquired when its C/N0 reaches the atmosphere's cutoff (the
    # tracking threshold) + acquire_margin_db and kept until it falls below the cutoff (a
    # warm receiver knows the satellites' orbits, so reacquiring needs only a few dB more).
    acquire_margin_db: float = 3.0

    def __post_init__(self) -> None:
        if self.seed_uere not in ("modelled", "re_ase_lce"):
            raise ConfigError(
                f"receiver.seed_uere must be 'modelled' or 're_ase_lce', got {self.seed_uere!r}"
            )
        nonneg = (
            "re_sigma_m",
            "iono_residual_frac",
            "tropo_residual_frac",
            "sisre_sigma_m",
            "multipath_sigma_m",
            "nlos_sigma_frac",
            "indoor_delay_m",
            "indoor_ref_loss_db",
            "indoor_delay_max_m",
            "smoothing_tau_s",
            "vel_sigma_mps",
            "vel_up_sigma_mps",
            "course_min_speed_mps",
            "implementation_loss_db",
            "acquire_margin_db",
            "antenna_shape",
        )
        for name in nonneg:
            v = getattr(self, name)
            if not (np.isfinite(v) and v >= 0):
                raise ConfigError(f"receiver.{name} must be finite and >= 0, got {v!r}")
        for name in (
            "tau_iono_s",
            "tau_tropo_s",
            "tau_sisre_s",
            "tau_multipath_s",
            "tau_indoor_s",
            "tau_fade_s",
            "dll_bandwidth_hz",
            "integration_s",
        ):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise ConfigError(f"receiver.{name} must be finite and > 0, got {v!r}")
        if self.ase_sigma_m is not None and not self.ase_sigma_m >= 0:
            raise ConfigError(f"receiver.ase_sigma_m must be >= 0, got {self.ase_sigma_m}")
        if not 0.0 <= self.iono_common_share <= 1.0:
            raise ConfigError(
                f"receiver.iono_common_share must be in 0..1, got {self.iono_common_share}"
            )
        if not 0.0 < self.correlator_spacing_chips <= 1.0:
            raise ConfigError("receiver.correlator_spacing_chips must be in (0, 1]")
        for name in (
            "antenna_zenith_dbic",
            "antenna_horizon_dbic",
            "fade_k_zenith_db",
            "fade_k_horizon_db",
        ):
            if not np.isfinite(getattr(self, name)):
                raise ConfigError(f"receiver.{name} must be finite, got {getattr(self, name)!r}")
        if self.geoid_sep_m is not None and not abs(self.geoid_sep_m) <= 200.0:
            raise ConfigError(f"receiver.geoid_sep_m must be in -200..200, got {self.geoid_sep_m}")
        if not 4 <= self.max_channels <= 64:
            raise ConfigError(f"receiver.max_channels must be 4..64, got {self.max_channels}")


# ---------------------------------------------------------------- walls interface


class TraceLike(Protocol):
    """Per (epoch, satellite) paths, as :class:`sim_backend.buildings.TraceResult` gives."""

    # Read-only members, so that frozen dataclasses (TraceResult) match.
    @property
    def los(self) -> np.ndarray:
        """bool, direct path clear"""
        ...

    @property
    def n_reflections(self) -> np.ndarray:
        """0 direct, 1..16 reflections, -1 no viable path"""
        ...

    @property
    def extra_path_m(self) -> np.ndarray:
        """range error of the path taken (m)"""
        ...

    @property
    def loss_db(self) -> np.ndarray:
        """3 dB per reflection"""
        ...


class Walls(Protocol):
    """What the model needs from :class:`sim_backend.buildings.Walls`."""

    def trace(
        self,
        rx_enu_m: Any,
        az_deg: Any,
        el_deg: Any,
        max_reflections: int = 16,
        max_loss_db: Any = None,
    ) -> TraceLike:
        """Paths from satellites at az/el (E, S) deg to receivers at ``rx_enu_m`` (E, 3) m;
        ``max_loss_db`` one value or one per (E, S) ray bounds the reflection depth."""
        ...


@dataclass(frozen=True)
class Visibility:
    """Per (epoch, satellite) signal path: ``reachable`` False means no path at all."""

    los: np.ndarray  # bool, direct line of sight
    reachable: np.ndarray  # bool, LOS or a reflected or penetrating path exists
    extra_path_m: np.ndarray  # >= 0; 0 for LOS
    loss_db: np.ndarray  # >= 0; 3 dB per reflection, or the materials' loss
    penetrated: np.ndarray  # bool, the path goes through walls/roofs


def _visibility(
    walls: Walls | None,
    rx_enu_m: np.ndarray,
    az_deg: np.ndarray,
    el_deg: np.ndarray,
    max_loss_db: np.ndarray | float | None,
) -> Visibility:
    shape = az_deg.shape
    if walls is None:
        ones = np.ones(shape, dtype=bool)
        zeros = np.zeros(shape)
        return Visibility(ones, ones, zeros, zeros, np.zeros(shape, dtype=bool))
    res = walls.trace(rx_enu_m, az_deg, el_deg, max_loss_db=max_loss_db)
    los = np.broadcast_to(np.asarray(res.los, dtype=bool), shape)
    reachable = los | np.broadcast_to(np.asarray(res.n_reflections) >= 0, shape)
    extra = np.broadcast_to(np.asarray(res.extra_path_m, dtype=float), shape)
    loss = np.broadcast_to(np.asarray(res.loss_db, dtype=float), shape)
    # Walls without materials (or a walls model that predates them) give no such paths.
    n_pen = getattr(res, "n_penetrations", None)
    penetrated = (
        np.zeros(shape, dtype=bool)
        if n_pen is None
        else np.broadcast_to(np.asarray(n_pen) > 0, shape) & reachable & ~los
    )
    return Visibility(
        los=los,
        reachable=reachable,
        extra_path_m=np.where(los | ~reachable, 0.0, np.nan_to_num(extra)),
        loss_db=np.where(los | ~reachable, 0.0, np.nan_to_num(loss, posinf=0.0)),
        penetrated=penetrated,
    )


# ---------------------------------------------------------------- noise processes


def gauss_markov_unit(
    t_s: np.ndarray,
    tau_s: float | np.ndarray,
    n: int,
    rng: np.random.Generator,
    x_prev: np.ndarray | None = None,
    t_prev: float | None = None,
) -> np.ndarray:
    """Unit-variance first-order Gauss-Markov samples (E, n) at increasing times ``t_s`` (s)
    with correlation time ``tau_s`` (s; one value or one per column), exact for any (also
    uneven) spacing: ``x[k] = phi x[k-1] + sqrt(1 - phi^2) w``, ``phi = exp(-dt/tau)``.

    Continues from ``x_prev`` (n,) at ``t_prev``; without it starts stationary at t_s[0].
    Even spacing runs the recursion through :func:`ar1_filter`; uneven spacing uses a scaled
    cumulative sum in blocks of 50 tau. No per-epoch Python loop.
    """
    t = np.asarray(t_s, dtype=float)
    tau = np.broadcast_to(np.asarray(tau_s, dtype=float), (n,))
    if np.any(~(tau > 0)):
        raise ConfigError("Gauss-Markov tau_s must be > 0")
    n_e = t.shape[0]
    out = np.empty((n_e, n))
    if n_e == 0:
        return out
    if x_prev is None or t_prev is None:
        x_prev, t_prev = rng.standard_normal(n), float(t[0])
    dt = np.diff(t, prepend=t_prev)
    if np.any(dt < 0):
        raise ConfigError("times must be non-decreasing")
    z = rng.standard_normal((n_e, n))
    # q = sqrt(1 - phi^2) via expm1: accurate for steps much shorter than tau.
    out[0] = np.asarray(x_prev, dtype=float) * np.exp(-dt[0] / tau)
    out[0] += np.sqrt(-np.expm1(-2.0 * dt[0] / tau)) * z[0]
    if n_e == 1:
        return out
    dt1 = dt[1:]
    even = float(np.ptp(dt1)) <= 1e-9 * float(dt1.max())
    for tau_g in np.unique(tau):
        cols = np.nonzero(tau == tau_g)[0]
        if even:
            phi = float(np.exp(-dt1[0] / tau_g))
            q = float(np.sqrt(-np.expm1(-2.0 * dt1[0] / tau_g)))
            out[1:, cols] = ar1_filter(z[1:, cols], phi, q, out[0, cols])
        else:
            out[1:, cols] = _gm_uneven(t, dt, tau_g, out[0, cols], z[1:, cols])
    return out


# phi^-B up to 1e12 within a block: the scaled sum then loses at most ~1e-4 of a unit sample
# to rounding relative to the step-by-step recursion's ~1e-16 (measured: <= 1e-13).
_AR1_BLOCK_GROWTH = 12.0 * math.log(10.0)
# Below this phi the response is gone after a few samples: a truncated sum is cheaper.
_AR1_SHORT_TERMS = 16


def ar1_filter(x: np.ndarray, phi: float, gain: float, y0: np.ndarray) -> np.ndarray:
    """``y[k] = phi y[k-1] + gain x[k]`` down axis 0 of ``x`` (n, m), from ``y[-1] = y0`` (m,).

    The first-order recursion of every Gauss-Markov process here, in numpy: blocks whose
    closed form (a cumulative sum scaled by powers of ``phi``) stays well conditioned, so a
    long series costs a few vector operations, not a Python step per sample. It replaces
    ``scipy.signal.lfilter``, whose import alone (~1 s) cost more than a 10 h survey's noise.
    Agrees with the step-by-step recursion to ~1e-13 of the samples' scale.
    """
    x = np.asarray(x, dtype=float)
    y = np.empty_like(x)
    prev = np.array(y0, dtype=float)
    n = x.shape[0]
    if n == 0:
        return y
    if not 0.0 <= phi < 1.0:
        raise ValueError(f"ar1_filter needs 0 <= phi < 1, got {phi!r}")
    if phi == 0.0:
        return gain * x
    decay = -math.log(phi)  # per sample
    terms = math.ceil(37.0 / decay)  # phi^terms < 1e-16
    if terms <= _AR1_SHORT_TERMS:
        # y[k] = sum_m phi^m gain x[k-m] (+ phi^(k+1) y0 while it is not yet negligible)
        y[:] = gain * x
        for m in range(1, min(terms, n) + 1):
            y[m:] += (phi**m * gain) * x[:-m]
        k = np.arange(1, min(terms, n) + 1)
        y[: k.size] += (phi**k)[:, None] * prev[None, :] if x.ndim == 2 else phi**k * prev
        return y
    block = max(1, int(_AR1_BLOCK_GROWTH / decay))
    for s in range(0, n, block):
        e = min(n, s + block)
        i = np.arange(e - s, dtype=float)
        if x.ndim == 2:
            grow = np.exp(decay * i)[:, None]  # phi^-i
            shrink = np.exp(-decay * i)[:, None]  # phi^i
            y[s:e] = shrink * (gain * np.cumsum(grow * x[s:e], axis=0) + phi * prev[None, :])
        else:
            grow, shrink = np.exp(decay * i), np.exp(-decay * i)
            y[s:e] = shrink * (gain * np.cumsum(grow * x[s:e]) + phi * prev)
        prev = y[e - 1].copy()
    return y


def _gm_uneven(
    t: np.ndarray, dt: np.ndarray, tau_s: float, x0: np.ndarray, z: np.ndarray
) -> np.ndarray:
    """Samples 1.. of a unit Gauss-Markov process at uneven times (see gauss_markov_unit)."""
    n_e = t.shape[0]
    phi = np.exp(-dt / tau_s)
    w = np.vstack((x0[None, :], z * np.sqrt(-np.expm1(-2.0 * dt[1:, None] / tau_s))))
    x = np.empty_like(w)
    x[0] = x0
    span = 50.0 * tau_s
    b = 1
    while b < n_e:
        # One exact step to t[b] (safe across any gap), then the block relative to t[b]:
        # x_k = exp(-(t_k - t_b)/tau) (x_b + sum_j exp((t_j - t_b)/tau) q_j w_j).
        x[b] = phi[b] * x[b - 1] + w[b]
        end = max(int(np.searchsorted(t, t[b] + span, side="right")), b + 1)
        if end > b + 1:
            grow = np.exp((t[b + 1 : end] - t[b]) / tau_s)[:, None]
            x[b + 1 : end] = (x[b] + np.cumsum(w[b + 1 : end] * grow, axis=0)) / grow
        b = end
    return x[1:]


def code_noise_sigma_m(cn0_dbhz: np.ndarray, p: ReceiverParams) -> np.ndarray:
    """Code tracking (DLL, early-minus-late) 1-sigma range noise (m) at C/N0 (dB-Hz), after
    carrier smoothing with time constant ``p.smoothing_tau_s`` (variance x tau_c/tau with the
    DLL noise correlation time tau_c = 1/(4 Bn))."""
    cn0 = 10.0 ** (np.asarray(cn0_dbhz, dtype=float) / 10.0)
    d = p.correlator_spacing_chips
    var_chips = (
        p.dll_bandwidth_hz * d / (2.0 * cn0) * (1.0 + 2.0 / (p.integration_s * cn0 * (2 - d)))
    )
    sigma = CA_CHIP_M * np.sqrt(var_chips)
    if p.smoothing_tau_s > 0:
        tau_c = 1.0 / (4.0 * p.dll_bandwidth_hz)
        sigma = sigma * np.sqrt(min(1.0, tau_c / p.smoothing_tau_s))
    return sigma


def indoor_delay_scale_m(loss_db: np.ndarray, p: ReceiverParams) -> np.ndarray:
    """Mean extra delay (m) of a signal received through walls or roofs that cost it
    ``loss_db`` (dB, the materials' summed loss on the path).

    Indoors the direct ray is attenuated by the material while the diffuse paths scattered
    by the room (through its openings, off other buildings) are not attenuated as much, so
    the delayed energy grows relative to the direct path as the material weakens it; the
    code tracking bias of a delayed path scales with its amplitude relative to the direct
    one. The mean therefore grows as the amplitude ratio 10^((loss - ref) / 20): 3 m behind
    10 dB (brick) gives 9.5 m behind 20 dB (a concrete slab) and 17 m behind 25 dB, the
    size of the indoor pseudorange errors measured with high-sensitivity receivers. It is
    a ratio of two signals from the same satellite, so it depends on the loss, not on the
    absolute C/N0 (which the antenna pattern, elevation and noise floor move for the direct
    and the diffuse energy alike). Capped at ``indoor_delay_max_m`` (the correlator cannot
    be pulled by more than about one chip)."""
    ratio = 10.0 ** ((np.asarray(loss_db, dtype=float) - p.indoor_ref_loss_db) / 20.0)
    return np.minimum(p.indoor_delay_m * ratio, p.indoor_delay_max_m)


def multipath_sigma_m(el_deg: np.ndarray, p: ReceiverParams) -> np.ndarray:
    """Line-of-sight code multipath 1-sigma (m): grows toward the horizon."""
    return p.multipath_sigma_m * (1.0 + 3.0 * np.exp(-np.asarray(el_deg) / 15.0))


def antenna_gain_dbic(el_deg: np.ndarray | float, p: ReceiverParams) -> np.ndarray:
    """The patch antenna's gain (dBic) toward elevation ``el_deg`` (deg): the zenith value
    falling as (1 - sin el)^shape to the horizon value (a patch's broad main lobe and its
    steep roll-off near the horizon); below the horizon it stays at the horizon value."""
    s = np.sin(np.radians(np.clip(np.asarray(el_deg, dtype=float), 0.0, 90.0)))
    drop = p.antenna_zenith_dbic - p.antenna_horizon_dbic
    return np.asarray(p.antenna_zenith_dbic - drop * (1.0 - s) ** p.antenna_shape)


def fade_k_db(el_deg: np.ndarray | float, p: ReceiverParams) -> np.ndarray:
    """Rician K factor (dB, direct over diffuse power) at elevation ``el_deg`` (deg): low
    satellites see more reflected power from the ground and nearby objects."""
    s = np.sin(np.radians(np.clip(np.asarray(el_deg, dtype=float), 0.0, 90.0)))
    return np.asarray(p.fade_k_horizon_db + (p.fade_k_zenith_db - p.fade_k_horizon_db) * s)


def rician_fade_db(x_i: np.ndarray, x_q: np.ndarray, k_db: np.ndarray) -> np.ndarray:
    """Fade (dB) of a Rician channel from unit-variance in-phase/quadrature samples of the
    diffuse part: power |1 + (x_i + j x_q) / sqrt(2 K)|^2 normalised by its mean 1 + 1/K,
    so the mean received power is unchanged and a lower K fades deeper and more often."""
    inv_k = 10.0 ** (-np.asarray(k_db, dtype=float) / 10.0)
    a = np.sqrt(inv_k / 2.0)
    power = (1.0 + a * x_i) ** 2 + (a * x_q) ** 2
    return 10.0 * np.log10(np.maximum(power, 1e-6) / (1.0 + inv_k))


def track_hysteresis(
    acquire: np.ndarray, lose: np.ndarray, prev: np.ndarray | None = None
) -> np.ndarray:
    """Tracking state (E, S) from per-epoch events, vectorised over epochs: a satellite is
    tracked from an epoch where ``acquire`` holds until one where ``lose`` holds (the two
    never hold together); before any event it keeps ``prev`` (S,) (default untracked)."""
    n_e, n_s = acquire.shape
    idx = np.arange(n_e)[:, None]
    last_acq = np.maximum.accumulate(np.where(acquire, idx, -1), axis=0)
    last_lose = np.maximum.accumulate(np.where(lose, idx, -1), axis=0)
    before = np.zeros(n_s, dtype=bool) if prev is None else np.asarray(prev, dtype=bool)
    return np.where(last_acq == last_lose, before[None, :], last_acq > last_lose)


# ---------------------------------------------------------------- results


@dataclass(frozen=True)
class GnssBatch:
    """Columnar receiver output for E epochs and the S satellites of the sky.

    Positions are NaN where ``valid`` is False; ``course_deg`` NaN means empty (at rest);
    ``snr_dbhz`` NaN means no signal. ``err_enu_m`` is the realised error (solution minus
    truth, m) and ``sigma_uere_m`` the per-epoch UERE the seed level used (pseudorange level:
    the RMS over the used satellites of the modelled per-satellite sigmas).
    """

    t_s: np.ndarray
    start_utc: datetime
    valid: np.ndarray
    lat_deg: np.ndarray
    lon_deg: np.ndarray
    alt_m: np.ndarray
    speed_mps: np.ndarray
    course_deg: np.ndarray
    hdop: np.ndarray
    pdop: np.ndarray
    vdop: np.ndarray
    n_used: np.ndarray
    prns: np.ndarray
    az_deg: np.ndarray
    el_deg: np.ndarray
    snr_dbhz: np.ndarray
    in_view: np.ndarray
    used: np.ndarray
    err_enu_m: np.ndarray
    sigma_uere_m: np.ndarray
    geoid_sep_m: float = 0.0

    def __len__(self) -> int:
        return int(self.t_s.shape[0])

    def epoch(self, i: int) -> GnssEpoch:
        """The receiver's report at epoch ``i`` as a :class:`GnssEpoch`."""
        if not -len(self) <= i < len(self):
            raise IndexError(f"epoch {i} out of range 0..{len(self) - 1}")
        i = i % len(self)
        return self._epoch(i, self._sats(i))

    def epochs(self) -> list[GnssEpoch]:
        """All epochs as :class:`GnssEpoch` objects (satellite tuples built in one flat pass:
        this runs per epoch of a long simulation, so it avoids per-epoch numpy calls)."""
        ee, kk = np.nonzero(self.in_view)
        nan_snr = np.isnan(self.snr_dbhz[ee, kk]).tolist()
        flat = [
            SimSat(p, e, a, None if no else s, u)
            for p, e, a, s, no, u in zip(
                self.prns[kk].tolist(),
                self.el_deg[ee, kk].tolist(),
                self.az_deg[ee, kk].tolist(),
                self.snr_dbhz[ee, kk].tolist(),
                nan_snr,
                self.used[ee, kk].tolist(),
                strict=True,
            )
        ]
        bounds = np.concatenate(([0], np.cumsum(self.in_view.sum(axis=1)))).tolist()
        return [self._epoch(i, tuple(flat[bounds[i] : bounds[i + 1]])) for i in range(len(self))]

    def _sats(self, i: int) -> tuple[SimSat, ...]:
        prns = self.prns
        idx = np.nonzero(self.in_view[i])[0]
        el = self.el_deg[i, idx].tolist()
        az = self.az_deg[i, idx].tolist()
        snr = self.snr_dbhz[i, idx].tolist()
        used = self.used[i, idx].tolist()
        return tuple(
            SimSat(p, e, a, None if s != s else s, u)  # s != s: NaN, no signal
            for p, e, a, s, u in zip(prns[idx].tolist(), el, az, snr, used, strict=True)
        )

    def _epoch(self, i: int, sats: tuple[SimSat, ...]) -> GnssEpoch:
        valid = bool(self.valid[i])
        course = float(self.course_deg[i])
        t = float(self.t_s[i])
        return GnssEpoch(
            t_s=t,
            utc=self.start_utc + timedelta(seconds=t),
            valid=valid,
            lat_deg=float(self.lat_deg[i]),
            lon_deg=float(self.lon_deg[i]),
            alt_m=float(self.alt_m[i]),
            geoid_sep_m=self.geoid_sep_m,
            speed_mps=float(self.speed_mps[i]),
            course_deg=None if course != course else course,
            quality=1 if valid else 0,
            mode=3 if valid else 1,
            hdop=float(self.hdop[i]) if valid else 99.99,
            pdop=float(self.pdop[i]) if valid else 99.99,
            vdop=float(self.vdop[i]) if valid else 99.99,
            satellites=sats,
        )


# ---------------------------------------------------------------- the model


class GnssModel:
    """The simulated receiver. See the module docstring for the two fidelity levels."""

    def __init__(
        self,
        sky: SatelliteSet,
        origin_lat_deg: float,
        origin_lon_deg: float,
        origin_alt_m: float,
        start_utc: datetime,
        fidelity: Fidelity = "pseudorange",
        mask_deg: float = DEFAULT_MASK_DEG,
        atmosphere: Atmosphere | None = None,
        walls: Walls | None = None,
        receiver: ReceiverParams | None = None,
        rng: np.random.Generator | None = None,
    ) -> None:
        """``origin_*``: the local frame (deg, deg, m above MSL); ``start_utc`` (aware) is
        scenario time 0; ``mask_deg`` the elevation mask; ``atmosphere`` defaults to
        ``Atmosphere()``; ``walls`` None means open sky; ``rng`` is required."""
        if fidelity not in FIDELITIES:
            raise ConfigError(f"gnss fidelity must be one of {FIDELITIES}, got {fidelity!r}")
        if not -90.0 <= origin_lat_deg <= 90.0 or not -180.0 <= origin_lon_deg <= 360.0:
            raise ConfigError(f"origin ({origin_lat_deg}, {origin_lon_deg}) is not a lat/lon")
        if not 0.0 <= mask_deg < 90.0:
            raise ConfigError(f"mask_deg must be in 0..90 deg, got {mask_deg}")
        if rng is None:
            raise ConfigError("GnssModel needs an explicit numpy.random.Generator (rng=)")
        if start_utc.tzinfo is None:
            raise ConfigError("start_utc must be timezone-aware (UTC)")
        self.sky = sky
        self.origin = (float(origin_lat_deg), float(origin_lon_deg), float(origin_alt_m))
        self.start_utc = start_utc.astimezone(UTC)
        self.fidelity: Fidelity = fidelity
        self.mask_deg = float(mask_deg)
        self.atmosphere = atmosphere if atmosphere is not None else Atmosphere()
        self.walls = walls
        self.params = receiver if receiver is not None else ReceiverParams()
        self.rng = rng
        self._gps0_s = utc_to_gps_seconds(self.start_utc)
        self._doy = float(self.start_utc.timetuple().tm_yday)
        geoid = self.params.geoid_sep_m
        if geoid is None:
            geoid = float(geoid_separation_m(self.origin[0], self.origin[1]))
        self.geoid_sep_m = float(geoid)  # constant: it changes by cm over a robot's range
        self._origin_ecef = lla_to_ecef(self.origin[0], self.origin[1], self.origin[2] + geoid)
        self._rot0 = enu_rotation(self.origin[0], self.origin[1])
        # Delays and C/N0 depend (for one site and day) on elevation only: tabulate them once
        # (0.05 deg steps; linear interpolation error < 5 mm of delay, < 0.001 dB).
        atm, lat0, h0 = self.atmosphere, self.origin[0], self.origin[2]
        self._el_grid = np.linspace(0.0, 90.0, 1801)
        el_delay = np.clip(self._el_grid, 1.0, 90.0)  # delays are not defined at the horizon
        self._iono_tab = np.asarray(atm.iono_delay_m(el_delay), dtype=float)
        self._tropo_tab = np.asarray(atm.tropo_delay_m(el_delay, lat0, self._doy, h0), dtype=float)
        p = self.params
        self._snr_tab = np.asarray(
            atm.snr_dbhz(self._el_grid, 0.0, h0)
            + antenna_gain_dbic(self._el_grid, p)
            - p.implementation_loss_db,
            dtype=float,
        )
        self._k_tab = fade_k_db(self._el_grid, p)
        # Gauss-Markov state carried between calls: (values, time).
        self._state: tuple[np.ndarray, float] | None = None
        # Signals can arrive through walls/roofs only when some have a material; only then
        # is the indoor delay process drawn, so a scene without materials consumes the
        # random stream exactly as before (the seed's model; tested in the same run).
        self._penetrable = bool(getattr(walls, "penetrable", False))
        self._indoor_state: tuple[np.ndarray, float] | None = None
        # Fading (I/Q Gauss-Markov) state and which satellites are tracked, between calls.
        self._fade_state: tuple[np.ndarray, float] | None = None
        self._tracked: np.ndarray | None = None
        self._t_last: float | None = None

    # -------------------------------------------------------------- public

    def step(
        self,
        t_s: float,
        lat_deg: float,
        lon_deg: float,
        alt_m: float,
        vel_enu_mps: Sequence[float] | np.ndarray,
    ) -> GnssEpoch:
        """One epoch at scenario time ``t_s`` (s, increasing between calls) for a receiver
        truly at (deg, deg, m MSL) moving at ``vel_enu_mps`` (m/s east, north, up)."""
        v = np.asarray(vel_enu_mps, dtype=float).reshape(1, 3)
        res = self.batch(
            np.array([t_s], dtype=float),
            np.array([lat_deg]),
            np.array([lon_deg]),
            np.array([alt_m]),
            v,
        )
        return res.epoch(0)

    def batch(
        self,
        t_s: np.ndarray,
        lat_deg: np.ndarray,
        lon_deg: np.ndarray,
        alt_m: np.ndarray,
        vel_enu_mps: np.ndarray,
    ) -> GnssBatch:
        """All epochs at once (vectorised): times (E,) s increasing and continuing after any
        earlier call, true positions (E,) deg/deg/m MSL and velocities (E, 3) m/s ENU."""
        t = np.atleast_1d(np.asarray(t_s, dtype=float))
        n_e = t.shape[0]
        lat = np.broadcast_to(np.asarray(lat_deg, dtype=float), (n_e,))
        lon = np.broadcast_to(np.asarray(lon_deg, dtype=float), (n_e,))
        alt = np.broadcast_to(np.asarray(alt_m, dtype=float), (n_e,))
        vel = np.asarray(vel_enu_mps, dtype=float)
        if vel.shape == (3,):
            vel = np.broadcast_to(vel, (n_e, 3))
        self._check_inputs(t, lat, lon, alt, vel)
        p = self.params
        geo = self._geometry(t, lat, lon, alt)
        n_s = self.sky.n_sats
        el, az = geo["el"], geo["az"]
        # Modelled per-satellite delays and sigmas (m).
        el_c = np.clip(el, 1.0, 90.0)
        iono = np.interp(el_c, self._el_grid, self._iono_tab)
        tropo = np.interp(el_c, self._el_grid, self._tropo_tab)
        snr = geo["snr"]
        sig_code = code_noise_sigma_m(np.where(np.isfinite(snr), snr, 0.0), p)
        sig_mp = multipath_sigma_m(el_c, p)
        sig_iono = p.iono_residual_frac * iono
        sig_tropo = p.tropo_residual_frac * tropo
        var_model = sig_iono**2 + sig_tropo**2 + p.sisre_sigma_m**2 + sig_mp**2 + sig_code**2
        used = geo["used"]
        n_used = used.sum(axis=1)
        ok = n_used >= 4
        g = geo["g"]
        gu = g * used[..., None]
        q, ok = batched_inverse(np.matmul(np.swapaxes(gu, 1, 2), g), ok)
        qd = np.diagonal(q, axis1=1, axis2=2)
        hdop = np.sqrt(qd[:, 0] + qd[:, 1])
        vdop = np.sqrt(qd[:, 2])
        pdop = np.sqrt(qd[:, :3].sum(axis=1))
        ok = ok & (pdop <= NAV5_PDOP_MASK)  # NaN (singular) fails too

        pen = geo["penetrated"]
        if self._penetrable:
            indoor_mean = np.where(pen, indoor_delay_scale_m(geo["pen_loss_db"], p), 0.0)
        if self.fidelity == "seed":
            var_sat = var_model + geo["extra"] ** 2
            if self._penetrable:
                var_sat = var_sat + 2.0 * indoor_mean**2  # E[d^2] of an exponential delay
            nu = np.maximum(n_used, 1)
            uere = np.sqrt(np.where(used, var_sat, 0.0).sum(axis=1) / nu)
            if p.seed_uere == "re_ase_lce":
                ase2 = (
                    np.where(used, sig_iono**2 + sig_tropo**2 + p.sisre_sigma_m**2, 0.0).sum(1) / nu
                    if p.ase_sigma_m is None
                    else np.full(n_e, p.ase_sigma_m**2)
                )
                lce = (
                    p.lce.at(geo["rx_enu"][:, 0], geo["rx_enu"][:, 1])
                    if p.lce is not None
                    else np.zeros(n_e)
                )
                uere = np.sqrt(p.re_sigma_m**2 + ase2 + lce**2)
            z = self.rng.standard_normal((n_e, 3))
            err = np.stack(
                (
                    z[:, 0] * hdop * uere / np.sqrt(2.0),
                    z[:, 1] * hdop * uere / np.sqrt(2.0),
                    z[:, 2] * vdop * uere,
                ),
                axis=1,
            )
        else:
            x = self._processes(t, n_s)
            gm = {
                "iono_common": x[:, :1],
                "tropo": x[:, 1:2],
                **{
                    name: x[:, 2 + k * n_s : 2 + (k + 1) * n_s]
                    for k, name in enumerate(("iono_sat", "sisre", "multipath", "code", "nlos"))
                },
            }
            share = p.iono_common_share
            eps = (
                sig_iono
                * (np.sqrt(share) * gm["iono_common"] + np.sqrt(1 - share) * gm["iono_sat"])
                + sig_tropo * gm["tropo"]
                + p.sisre_sigma_m * gm["sisre"]
                + sig_mp * gm["multipath"]
                + sig_code * gm["code"]
                + geo["extra"] * (1.0 + p.nlos_sigma_frac * gm["nlos"])
            )
            if self._penetrable:
                eps = eps + indoor_mean * self.indoor_unit_delay(t, n_s)
            w = np.where(used, 1.0 / var_model, 0.0)
            gw = g * w[..., None]
            qw, ok = batched_inverse(np.matmul(np.swapaxes(gw, 1, 2), g), ok)
            sol = np.matmul(qw, np.matmul(np.swapaxes(gw, 1, 2), np.nan_to_num(eps)[..., None]))
            err = sol[:, :3, 0]
            uere = np.sqrt(np.where(used, var_model, 0.0).sum(1) / np.maximum(n_used, 1))

        err = np.where(ok[:, None], err, np.nan)
        sol_ecef = geo["rx_ecef"] + np.matmul(err[:, None, :], geo["rot"])[:, 0, :]
        f_lat, f_lon, f_h = ecef_to_lla(sol_ecef)
        # Velocity from Doppler: truth plus white noise; course empty at rest.
        dv = self.rng.standard_normal((n_e, 3)) * np.array(
            [p.vel_sigma_mps, p.vel_sigma_mps, p.vel_up_sigma_mps]
        )
        v_meas = vel + dv
        speed = np.hypot(v_meas[:, 0], v_meas[:, 1])
        course = np.degrees(np.arctan2(v_meas[:, 0], v_meas[:, 1])) % 360.0
        course = np.where(speed >= p.course_min_speed_mps, course, np.nan)
        nan = np.full(n_e, np.nan)
        return GnssBatch(
            t_s=t.copy(),
            start_utc=self.start_utc,
            valid=ok,
            lat_deg=np.where(ok, f_lat, nan),
            lon_deg=np.where(ok, f_lon, nan),
            alt_m=np.where(ok, f_h - self.geoid_sep_m, nan),
            speed_mps=np.where(ok, speed, 0.0),
            course_deg=np.where(ok, course, nan),
            hdop=np.where(ok, hdop, nan),
            pdop=np.where(ok, pdop, nan),
            vdop=np.where(ok, vdop, nan),
            n_used=np.where(ok, n_used, 0),
            prns=self.sky.prns,
            az_deg=az,
            el_deg=el,
            snr_dbhz=snr,
            in_view=geo["in_view"],
            used=used & ok[:, None],
            err_enu_m=err,
            sigma_uere_m=uere,
            geoid_sep_m=self.geoid_sep_m,
        )

    # -------------------------------------------------------------- internals

    def _check_inputs(
        self, t: np.ndarray, lat: np.ndarray, lon: np.ndarray, alt: np.ndarray, vel: np.ndarray
    ) -> None:
        n_e = t.shape[0]
        if t.ndim != 1 or n_e == 0:
            raise ConfigError(f"t_s must be a non-empty 1-D array, got shape {t.shape}")
        if vel.shape != (n_e, 3):
            raise ConfigError(f"vel_enu_mps must have shape ({n_e}, 3), got {vel.shape}")
        for name, arr in (
            ("t_s", t),
            ("lat_deg", lat),
            ("lon_deg", lon),
            ("alt_m", alt),
            ("vel_enu_mps", vel),
        ):
            if not np.all(np.isfinite(arr)):
                raise ConfigError(f"{name} contains non-finite values")
        if np.any(np.diff(t) <= 0):
            raise ConfigError("t_s must be strictly increasing")
        if self._t_last is not None and t[0] <= self._t_last:
            raise ConfigError(f"t_s {t[0]} does not follow the previous epoch {self._t_last}")
        if np.any(np.abs(lat) > 90.0):
            raise ConfigError("lat_deg outside -90..90")
        self._t_last = float(t[-1])

    def _processes(self, t: np.ndarray, n_s: int) -> np.ndarray:
        """All error processes as one (E, 2 + 5 S) unit Gauss-Markov array, continuing from
        the previous call: common iono, common tropo, then per satellite iono, SISRE,
        multipath, smoothed code noise, NLOS jitter."""
        p = self.params
        tau = np.concatenate(
            (
                [p.tau_iono_s, p.tau_tropo_s],
                np.repeat(
                    [
                        p.tau_iono_s,
                        p.tau_sisre_s,
                        p.tau_multipath_s,
                        max(p.smoothing_tau_s, 1e-3),  # 0: white code noise
                        p.tau_multipath_s,
                    ],
                    n_s,
                ),
            )
        )
        prev = self._state
        x = gauss_markov_unit(t, tau, tau.size, self.rng, *(prev if prev else (None, None)))
        self._state = (x[-1].copy(), float(t[-1]))
        return x

    def indoor_unit_delay(self, t: np.ndarray, n_s: int) -> np.ndarray:
        """Unit-mean, positive, time-correlated delay factors (E, S): (x1^2 + x2^2) / 2 of two
        unit Gauss-Markov processes is exponentially distributed with mean 1 (the
        exponential excess-delay law of indoor and land-mobile channel models) and its
        autocorrelation is the square of theirs, so they run at 2 tau to give tau_indoor_s."""
        prev = self._indoor_state
        x = gauss_markov_unit(
            t, 2.0 * self.params.tau_indoor_s, 2 * n_s, self.rng, *(prev if prev else (None, None))
        )
        self._indoor_state = (x[-1].copy(), float(t[-1]))
        return 0.5 * (x[:, :n_s] ** 2 + x[:, n_s:] ** 2)

    def _fading(self, t: np.ndarray, el: np.ndarray) -> np.ndarray:
        """Multipath fade (dB) per (epoch, satellite): Rician with the elevation's K factor,
        its diffuse I/Q parts unit Gauss-Markov processes (tau_fade_s) continuing from the
        previous call."""
        n_s = el.shape[1]
        prev = self._fade_state
        x = gauss_markov_unit(
            t, self.params.tau_fade_s, 2 * n_s, self.rng, *(prev if prev else (None, None))
        )
        self._fade_state = (x[-1].copy(), float(t[-1]))
        k_db = np.interp(el, self._el_grid, self._k_tab)
        return rician_fade_db(x[:, :n_s], x[:, n_s:], k_db)

    def _geometry(
        self, t: np.ndarray, lat: np.ndarray, lon: np.ndarray, alt: np.ndarray
    ) -> dict[str, np.ndarray]:
        """The sky pipeline: az/el, visibility, SNR, in-view / usable / used masks and
        the design matrix, all (E, S)."""
        p = self.params
        rx_ecef = lla_to_ecef(lat, lon, alt + self.geoid_sep_m)
        rot = enu_rotation(lat, lon)  # (E, 3, 3) local frame at the receiver
        st = self.sky.state(self._gps0_s + t)
        d = st.ecef_m - rx_ecef[:, None, :]
        enu = np.matmul(d, np.swapaxes(rot, 1, 2))
        rng_m = np.linalg.norm(enu, axis=-1)
        los_u = enu / rng_m[..., None]
        az = np.degrees(np.arctan2(los_u[..., 0], los_u[..., 1])) % 360.0
        el = np.degrees(np.arcsin(np.clip(los_u[..., 2], -1.0, 1.0)))
        rx_enu = (rx_ecef - self._origin_ecef) @ self._rot0.T
        above = st.available & (el > 0.0)
        # Mean open-sky C/N0: the atmosphere's value + antenna pattern - implementation loss.
        snr_open = np.interp(el, self._el_grid, self._snr_tab)
        # A path is tracked only while its C/N0 (reflection losses subtracted, 3 dB each)
        # stays >= the cutoff, so each ray's margin bounds its reflection search (deeper
        # paths would be dropped anyway) and a satellite already under it needs no tracing.
        # The margin allows FADE_UP_DB of fading above the mean (a Rician fade seldom
        # lifts a signal more); the tiny pad keeps rounding from cutting a search short.
        cutoff = self.atmosphere.snr_cutoff_dbhz
        margin = snr_open + FADE_UP_DB - cutoff
        trace = above & (margin >= 0.0)
        vis = _visibility(self.walls, rx_enu, az, np.where(trace, el, -1.0), margin + 1e-9)
        snr = snr_open - vis.loss_db + self._fading(t, el)
        # Tracking with hysteresis: acquired at cutoff + acquire_margin_db, lost below cutoff.
        cand = above & vis.reachable
        tracked = track_hysteresis(
            cand & (snr >= cutoff + p.acquire_margin_db), ~cand | (snr < cutoff), self._tracked
        )
        self._tracked = tracked[-1].copy()
        snr = np.where(tracked, snr, np.nan)
        usable = tracked & (el >= self.mask_deg)
        used = usable
        if p.max_channels < self.sky.n_sats:
            # Keep the strongest max_channels usable satellites per epoch.
            key = np.where(usable, snr, -np.inf)
            kth = -np.partition(-key, p.max_channels - 1, axis=1)[:, p.max_channels - 1]
            used = usable & (key >= kth[:, None])
            # Ties at the threshold could exceed the limit: cut by rank.
            over = used.sum(1) > p.max_channels
            if np.any(over):
                rank = np.argsort(np.argsort(-key[over], axis=1, kind="stable"), axis=1)
                used[over] &= rank < p.max_channels
        g = np.concatenate((-los_u, np.ones((*el.shape, 1))), axis=-1)
        return {
            "az": az,
            "el": el,
            "snr": snr,
            "in_view": above,
            "used": used,
            "g": g,
            "extra": np.where(used, vis.extra_path_m, 0.0),
            "penetrated": used & vis.penetrated,
            "pen_loss_db": np.where(used & vis.penetrated, vis.loss_db, 0.0),
            "rx_ecef": rx_ecef,
            "rot": rot,
            "rx_enu": rx_enu,
        }
