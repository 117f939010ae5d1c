"""The tool's closing figures: which way the gap runs per time scale, and seed 000's validation
(the paper's "mean and standard deviation of the error within 3.256 %") of the simulator with
the fitted effects against the real log, extended with the overlapping Allan deviation per
octave so that a model cannot pass on the error's level alone while getting its time
structure wrong.

A real log without a truth has its errors taken against its own mean (``x6wd gap`` without
``--truth``): each simulated run is then taken against its own mean too, or the runs' hour
offsets (which the real log cannot show) would count as error (on gpsd's ZED-F9P log the
simulated mean was +84 % against the real, +14 % with both against their own means).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from sim_backend.effects import PositionSeries
from x6wd.gap.stats import Cell, allan_var, regular

# |z| of an Allan octave that says which way it runs: a per-octave reading once the gap is
# established (the family-wise threshold answers "is there a gap"; with 8 runs it is |z| 27).
# Without a gap no octave is read at it (:func:`gap_direction`).
DIRECTION_Z = 3.0
MEAN_SD_TOL = 0.03  # seed 000 reached 3.256 % on mean and sigma of the error
ADEV_TOL = 0.20  # per octave of the overlapping Allan deviation
OWN_MEAN_M = 1e-6  # |mean error| (m) below which a log's errors are against its own mean


@dataclass(frozen=True)
class Band:
    """A run of consecutive Allan octaves (s) where the simulator is ``noisier`` or
    ``quieter`` than the real receiver, or ``agrees`` (within the family-wise threshold)."""

    kind: str
    tau_lo_s: float
    tau_hi_s: float
    # the band's cell closest to (or furthest beyond) its limit: (z, limit, axis, tau s), so
    # "within the limits" can say how close an octave came (a slow drift reads z 6.7 at a
    # family-wise limit of 8 on one hour: within, but not "within the spread")
    closest: tuple[float, float, str, float] | None = field(default=None, compare=False)


def direction_bands(
    cells: Sequence[Cell],
    z: np.ndarray,
    threshold: float | np.ndarray,
    last_tau_s: float | None = None,
) -> list[Band]:
    """The Allan deviation cells (east and north) by octave: where the real log's z is beyond
    ``threshold`` (one for all cells, or one per cell) the simulator is noisier (z < 0: the
    receiver is quieter) or quieter (z > 0) than the receiver; octaves where the axes
    disagree beyond it are "mixed". Consecutive octaves of one kind are merged."""
    limits = np.broadcast_to(np.asarray(threshold, dtype=float), (len(cells),))
    by_tau: dict[float, list[float]] = {}
    closest: dict[float, tuple[float, float, str, float]] = {}
    for cell, zc, limit in zip(cells, z, limits, strict=True):
        if cell.statistic == "log_adev" and cell.axis in ("east", "north"):
            tau_s = float(cell.scale.removeprefix("tau=").removesuffix("s"))
            # a cell within its limit reads as 0: it says neither way
            by_tau.setdefault(tau_s, []).append(float(zc) if abs(zc) > limit else 0.0)
            here = (float(zc), float(limit), cell.axis, tau_s)
            if math.isfinite(zc) and _nearer(here, closest.get(tau_s)):
                closest[tau_s] = here
    bands: list[Band] = []
    for tau_s in sorted(by_tau):
        zs = [zc for zc in by_tau[tau_s] if zc != 0.0]
        if not zs:
            kind = "agrees"
        elif all(zc < 0 for zc in zs):
            kind = "noisier"
        elif all(zc > 0 for zc in zs):
            kind = "quieter"
        else:
            kind = "mixed"
        near = closest.get(tau_s)
        if bands and bands[-1].kind == kind:
            last = bands[-1]
            keep = near if _nearer(near, last.closest) else last.closest
            bands[-1] = Band(kind, last.tau_lo_s, tau_s, keep)
        else:
            bands.append(Band(kind, tau_s, tau_s, near))
    return bands


def _nearer(
    a: tuple[float, float, str, float] | None, b: tuple[float, float, str, float] | None
) -> bool:
    """Whether cell ``a`` (z, limit, ...) lies nearer its limit than ``b`` (|z| / limit)."""
    if a is None:
        return False
    return b is None or abs(a[0]) / a[1] > abs(b[0]) / b[1]


def gap_direction(
    cells: Sequence[Cell], z: np.ndarray, limits: np.ndarray, significant: bool
) -> list[Band]:
    """Which way the gap runs per Allan octave (:func:`direction_bands`): once the "where"
    test has found a gap (``significant``), each octave read at |z| > ``DIRECTION_Z``; without
    one, at the test's own family-wise ``limits`` (one per cell), so that no octave claims a
    direction the test has just refused (read at 3, the simulator was "quieter from 1 to
    32 s" on its own output, three runs); the text then names the octave nearest its limit."""
    return direction_bands(cells, z, DIRECTION_Z if significant else limits)


def direction_text(bands: Sequence[Band]) -> str:
    """One clause per band, e.g. "the simulator is noisier than the receiver from 1 to 16 s;
    agrees with it from 32 to 64 s; quieter than it at 128 s"."""
    if not bands:
        return ""
    words = {
        "noisier": "noisier than the receiver",
        "quieter": "quieter than the receiver",
        "agrees": "within the test's limits",
        "mixed": "noisier on one axis and quieter on the other",
    }
    parts = []
    for band in bands:
        span = (
            f"at {band.tau_lo_s:g} s"
            if band.tau_lo_s == band.tau_hi_s
            else f"from {band.tau_lo_s:g} to {band.tau_hi_s:g} s"
        )
        parts.append(f"{words[band.kind]} {span}")
    if all(b.kind == "agrees" for b in bands):
        text = "Allan deviation within the test's family-wise limits at every octave"
        near = [b.closest for b in bands if b.closest is not None]
        if near:
            z, limit, axis, tau_s = max(near, key=lambda c: abs(c[0]) / c[1])
            text += f" (nearest: {axis} at {tau_s:g} s, z {z:+.1f} against {limit:.1f})"
        return text
    return "the simulator is " + "; ".join(parts)


@dataclass(frozen=True)
class Validation:
    """Real against simulated (the baseline runs with the fitted effects) horizontal error:
    mean and standard deviation (m; the simulated figures are the runs' averages, each run
    being one log like the real one) and the overlapping Allan deviation of east and north
    combined, sqrt(AVAR_e + AVAR_n) (m), at octaves ``taus_s`` from one step to a quarter of
    the log (simulated: the root of the runs' mean Allan variance). ``mean_spread`` and
    ``sd_spread`` are the runs' own relative spread (standard deviation over runs / their
    average) of the mean and sigma, ``ratio_spread`` that of each run's sigma / mean (the
    shape of one log's error distribution, which no scaling of the error changes)."""

    n_runs: int
    mean_real_m: float
    mean_sim_m: float
    sd_real_m: float
    sd_sim_m: float
    taus_s: tuple[float, ...]
    adev_real_m: tuple[float, ...]
    adev_sim_m: tuple[float, ...]
    # the runs' own relative spread of their mean and sigma: how close one log of this
    # length can be expected to come to its own model
    mean_spread: float = math.nan
    sd_spread: float = math.nan
    ratio_spread: float = math.nan

    @staticmethod
    def rel(sim: float, real: float) -> float:
        """(sim - real) / real (inf when real is 0 and sim is not)."""
        if real == 0:
            return 0.0 if sim == 0 else math.inf
        return (sim - real) / real

    @staticmethod
    def rel_text(sim: float, real: float) -> str:
        """:meth:`rel` as a signed percentage; "n/a, the real is 0" where it is infinite (a
        log whose position never changes has a real sigma and Allan deviation of 0)."""
        rel = Validation.rel(sim, real)
        return f"{rel:+.1%}" if math.isfinite(rel) else "n/a, the real is 0"

    @property
    def mean_ok(self) -> bool:
        return abs(self.rel(self.mean_sim_m, self.mean_real_m)) <= MEAN_SD_TOL

    @property
    def sd_ok(self) -> bool:
        return abs(self.rel(self.sd_sim_m, self.sd_real_m)) <= MEAN_SD_TOL

    @property
    def adev_ok(self) -> tuple[bool, ...]:
        return tuple(
            abs(self.rel(s, r)) <= ADEV_TOL
            for s, r in zip(self.adev_sim_m, self.adev_real_m, strict=True)
        )

    @property
    def passed(self) -> bool:
        return self.mean_ok and self.sd_ok and all(self.adev_ok)

    def figures(self) -> list[tuple[str, float, float, float]]:
        """(label, real, simulated, tolerance) of every figure: mean, sigma, then the Allan
        deviation per octave."""
        return [
            ("mean", self.mean_real_m, self.mean_sim_m, MEAN_SD_TOL),
            ("sigma", self.sd_real_m, self.sd_sim_m, MEAN_SD_TOL),
            *(
                (f"Allan deviation at {tau_s:g} s", real, sim, ADEV_TOL)
                for tau_s, real, sim in zip(
                    self.taus_s, self.adev_real_m, self.adev_sim_m, strict=True
                )
            ),
        ]

    def misses(self) -> np.ndarray:
        """log(simulated / real) of each figure over log(1 + its tolerance): within about
        +-1 passes. Dimensionless; a figure without a value counts as a miss of 100."""
        out = []
        for _label, real, sim, tol in self.figures():
            ratio = sim / real if real > 0 and sim > 0 else math.nan
            out.append(math.log(ratio) / math.log1p(tol) if math.isfinite(ratio) else 100.0)
        return np.array(out)

    def worst(self) -> tuple[str, float]:
        """The figure furthest outside its tolerance (relative to it; the largest if all are
        within) and its difference (simulated - real) / real."""
        label, real, sim, _tol = max(self.figures(), key=lambda f: abs(self.rel(f[2], f[1])) / f[3])
        return label, self.rel(sim, real)

    def worst_text(self) -> str:
        """The figure furthest off and which way it misses, e.g. "Allan deviation at 1 s:
        simulated 43.4 % above the real, the simulator noisier there"."""
        label, rel = self.worst()
        if not math.isfinite(rel):
            return f"{label}: n/a, the real is 0"
        text = f"{label}: simulated {abs(rel):.1%} {'above' if rel > 0 else 'below'} the real"
        if label.startswith("Allan"):
            text += ", the simulator noisier there" if rel > 0 else ", the simulator quieter there"
        return text

    def summary(self) -> str:
        """One line: pass/fail with the figures and the one furthest off."""
        return (
            f"{'PASS' if self.passed else 'FAIL'}: horizontal error mean "
            f"{self.rel_text(self.mean_sim_m, self.mean_real_m)}, sigma "
            f"{self.rel_text(self.sd_sim_m, self.sd_real_m)} (within {MEAN_SD_TOL:.0%}?), "
            f"{sum(self.adev_ok)} of {len(self.adev_ok)} Allan octaves within {ADEV_TOL:.0%}; "
            f"furthest off: {self.worst_text()}"
        )


def own_mean(series: PositionSeries) -> bool:
    """Whether the errors are against the log's own mean (their east and north means are
    zero to rounding: no truth was given)."""
    valid = np.asarray(series.valid, dtype=bool)
    if not np.any(valid):
        return False
    means = [abs(float(np.mean(np.asarray(a)[valid]))) for a in (series.east_m, series.north_m)]
    return max(means) < OWN_MEAN_M


def against_own_mean(series: PositionSeries) -> PositionSeries:
    """The errors against the series' own mean position (east and north; m)."""
    valid = np.asarray(series.valid, dtype=bool)
    if not np.any(valid):
        return series
    east_m, north_m = np.asarray(series.east_m), np.asarray(series.north_m)
    return series.with_(
        east_m=east_m - np.mean(east_m[valid]), north_m=north_m - np.mean(north_m[valid])
    )


def _horizontal(series: PositionSeries) -> np.ndarray:
    valid = np.asarray(series.valid, dtype=bool)
    return np.hypot(np.asarray(series.east_m)[valid], np.asarray(series.north_m)[valid])


def _avar(series: PositionSeries, dt_s: float, factors: list[int]) -> np.ndarray:
    east_m, north_m, _up_m = regular(series, dt_s)
    return allan_var(east_m, factors) + allan_var(north_m, factors)


def _relative_spread(values: np.ndarray) -> float:
    if values.size < 2 or np.mean(values) == 0:
        return math.nan
    return float(np.std(values, ddof=1) / np.mean(values))


def validation_taus(duration_s: float, dt_s: float) -> list[int]:
    """Averaging factors 1, 2, 4, ... with factor * dt_s at most a quarter of the log."""
    out, factor = [], 1
    while factor * dt_s <= duration_s / 4.0:
        out.append(factor)
        factor *= 2
    return out


def validate(
    real: PositionSeries, sim_runs: Sequence[PositionSeries], dt_s: float, duration_s: float
) -> Validation:
    """Seed 000's validation of ``sim_runs`` (the simulator with the fitted effects, errors in
    m on the real log's times) against ``real``; runs against their own means when the real
    log is (:func:`own_mean`)."""
    if own_mean(real):
        sim_runs = [against_own_mean(s) for s in sim_runs]
    radial_real = _horizontal(real)
    radial_sims = [_horizontal(s) for s in sim_runs]
    factors = validation_taus(duration_s, dt_s)
    adev_real = np.sqrt(_avar(real, dt_s, factors))
    adev_sim = np.sqrt(np.nanmean([_avar(s, dt_s, factors) for s in sim_runs], axis=0))
    means = np.array([np.mean(r) for r in radial_sims if r.size])
    sds = np.array([np.std(r) for r in radial_sims if r.size])
    return Validation(
        n_runs=len(sim_runs),
        mean_real_m=float(np.mean(radial_real)) if radial_real.size else math.nan,
        mean_sim_m=float(np.mean(means)),
        sd_real_m=float(np.std(radial_real)) if radial_real.size else math.nan,
        sd_sim_m=float(np.mean(sds)),
        taus_s=tuple(f * dt_s for f in factors),
        adev_real_m=tuple(float(a) for a in adev_real),
        adev_sim_m=tuple(float(a) for a in adev_sim),
        mean_spread=_relative_spread(means),
        sd_spread=_relative_spread(sds),
        ratio_spread=_relative_spread(sds / np.where(means > 0, means, np.nan)),
    )
