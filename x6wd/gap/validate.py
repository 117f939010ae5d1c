"""The tool's closing figures: which way the gap runs per time scale, and seed 000's validation
(the paper's "mean and standard deviation of the error within 3.256 %") of the simulator with
the fitted effects against the real log, extended with the overlapping Allan deviation per
octave so that a model cannot pass on the error's level alone while getting its time
structure wrong.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from sim_backend.effects import PositionSeries
from x6wd.gap.stats import Cell, allan_var, regular

# |z| of an Allan octave that says which way it runs: a per-octave reading once the gap is
# established (the family-wise threshold answers "is there a gap"; with 8 runs it is |z| 27)
DIRECTION_Z = 3.0
MEAN_SD_TOL = 0.03  # seed 000 reached 3.256 % on mean and sigma of the error
ADEV_TOL = 0.20  # per octave of the overlapping Allan deviation


@dataclass(frozen=True)
class Band:
    """A run of consecutive Allan octaves (s) where the simulator is ``noisier`` or
    ``quieter`` than the real receiver, or ``agrees`` (within the family-wise threshold)."""

    kind: str
    tau_lo_s: float
    tau_hi_s: float


def direction_bands(
    cells: Sequence[Cell], z: np.ndarray, threshold: float, last_tau_s: float | None = None
) -> list[Band]:
    """The Allan deviation cells (east and north) by octave: where the real log's z is beyond
    ``threshold`` the simulator is noisier (z < 0: the receiver is quieter) or quieter (z > 0)
    than the receiver; octaves where the axes disagree beyond it are "mixed". Consecutive
    octaves of one kind are merged."""
    by_tau: dict[float, list[float]] = {}
    for cell, zc in zip(cells, z, strict=True):
        if cell.statistic == "log_adev" and cell.axis in ("east", "north"):
            tau_s = float(cell.scale.removeprefix("tau=").removesuffix("s"))
            by_tau.setdefault(tau_s, []).append(float(zc))
    bands: list[Band] = []
    for tau_s in sorted(by_tau):
        zs = [zc for zc in by_tau[tau_s] if abs(zc) > threshold]
        if not zs:
            kind = "agrees"
        elif all(zc < 0 for zc in zs):
            kind = "noisier"
        elif all(zc > 0 for zc in zs):
            kind = "quieter"
        else:
            kind = "mixed"
        if bands and bands[-1].kind == kind:
            bands[-1] = Band(kind, bands[-1].tau_lo_s, tau_s)
        else:
            bands.append(Band(kind, tau_s, tau_s))
    return bands


def direction_text(bands: Sequence[Band]) -> str:
    """One clause per band, e.g. "the simulator is noisier than the receiver from 1 to 16 s;
    agrees with it from 32 to 64 s; quieter than it at 128 s"."""
    if not bands:
        return ""
    words = {
        "noisier": "noisier than the receiver",
        "quieter": "quieter than the receiver",
        "agrees": "within the seed-to-seed spread",
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
        return "Allan deviation within the seed-to-seed spread at every octave"
    return "the simulator is " + "; ".join(parts)


@dataclass(frozen=True)
class Validation:
    """Real against simulated (the baseline runs with the fitted effects) horizontal error:
    mean and standard deviation (m; the simulated figures are the runs' averages, each run
    being one log like the real one) and the overlapping Allan deviation of east and north
    combined, sqrt(AVAR_e + AVAR_n) (m), at octaves ``taus_s`` from one step to a quarter of
    the log (simulated: the root of the runs' mean Allan variance). ``mean_spread`` and
    ``sd_spread`` are the runs' own relative spread (standard deviation over runs / their
    average) of the mean and sigma."""

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

    @staticmethod
    def rel(sim: float, real: float) -> float:
        """(sim - real) / real (inf when real is 0 and sim is not)."""
        if real == 0:
            return 0.0 if sim == 0 else math.inf
        return (sim - real) / real

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

    def summary(self) -> str:
        """One line: pass/fail with the worst figures."""
        worst_adev = max(
            (abs(self.rel(s, r)) for s, r in zip(self.adev_sim_m, self.adev_real_m, strict=True)),
            default=0.0,
        )
        return (
            f"validation {'PASS' if self.passed else 'FAIL'}: horizontal error mean "
            f"{self.rel(self.mean_sim_m, self.mean_real_m):+.1%}, sigma "
            f"{self.rel(self.sd_sim_m, self.sd_real_m):+.1%} (within {MEAN_SD_TOL:.0%}?), "
            f"Allan deviation worst octave {worst_adev:.0%} off, {sum(self.adev_ok)} of "
            f"{len(self.adev_ok)} octaves within {ADEV_TOL:.0%} (the simulated runs' own "
            f"spread: mean {self.mean_spread:.1%}, sigma {self.sd_spread:.1%})"
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
    m on the real log's times) against ``real``."""
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
    )
