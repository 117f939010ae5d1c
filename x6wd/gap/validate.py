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
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from sim_backend.effects import PositionSeries
from x6wd.gap.stats import Cell, allan_var, regular

# |z| of an Allan octave read descriptively once the "where" test has found a gap: per octave,
# with no correction for the ~18 octave cells tested, so the text labels it as such beside the
# reading at the test's own family-wise limits (:func:`direction_text`)
DIRECTION_Z = 3.0
MEAN_SD_TOL = 0.03  # seed 000 reached 3.256 % on mean and sigma of the error
ADEV_TOL = 0.20  # per octave of the overlapping Allan deviation
OWN_MEAN_M = 1e-6  # |mean error| (m) below which a log's errors are against its own mean
# An Allan octave the simulated logs do not reach (they end before a quarter of the real
# log): no simulated figure, neither passed nor failed
NOT_REACHED = "n/a: the simulated logs are shorter"


@dataclass(frozen=True)
class Band:
    """A run of consecutive Allan octaves (s) where the simulator is ``noisier`` or
    ``quieter`` than the real receiver, or ``agrees`` (within the family-wise threshold)."""

    kind: str
    tau_lo_s: float
    tau_hi_s: float
    # the kind at the "where" test's family-wise limits, where ``kind`` is read at a lower
    # descriptive threshold (:data:`DIRECTION_Z`); None: ``kind`` is read at the limits
    firm_kind: str | None = field(default=None, compare=False)
    # the band's cell closest to (or furthest beyond) its limit: (z, limit, axis, tau s), so
    # "within the limits" can say how close an octave came (a slow drift reads z 6.7 at a
    # family-wise limit of 8 on one hour: within, but not "within the spread")
    closest: tuple[float, float, str, float] | None = field(default=None, compare=False)


def direction_bands(
    cells: Sequence[Cell],
    z: np.ndarray,
    threshold: float | np.ndarray,
    last_tau_s: float | None = None,
    limits: float | np.ndarray | None = None,
) -> list[Band]:
    """The Allan deviation cells (east and north) by octave: where the real log's z is beyond
    ``threshold`` (one for all cells, or one per cell) the simulator is noisier (z < 0: the
    receiver is quieter) or quieter (z > 0) than the receiver; octaves where the axes
    disagree beyond it are "mixed". Consecutive octaves of one kind are merged. With
    ``limits`` (the test's family-wise limits, per cell) ``threshold`` is a descriptive
    reading: each band also holds its kind at the limits (``firm_kind``), and the nearest
    cell is judged, and quoted, against its limit."""
    reading = np.broadcast_to(np.asarray(threshold, dtype=float), (len(cells),))
    family = (
        reading
        if limits is None
        else np.broadcast_to(np.asarray(limits, dtype=float), (len(cells),))
    )
    by_tau: dict[float, list[tuple[float, float]]] = {}
    closest: dict[float, tuple[float, float, str, float]] = {}
    for cell, zc, read_at, limit in zip(cells, z, reading, family, strict=True):
        if cell.statistic == "log_adev" and cell.axis in ("east", "north"):
            tau_s = float(cell.scale.removeprefix("tau=").removesuffix("s"))
            # a cell within its limit reads as 0: it says neither way
            by_tau.setdefault(tau_s, []).append(
                (float(zc) if abs(zc) > read_at else 0.0, float(zc) if abs(zc) > limit else 0.0)
            )
            here = (float(zc), float(limit), cell.axis, tau_s)
            if math.isfinite(zc) and _nearer(here, closest.get(tau_s)):
                closest[tau_s] = here
    bands: list[Band] = []
    for tau_s in sorted(by_tau):
        kind = _kind([read for read, _firm in by_tau[tau_s]])
        firm = None if limits is None else _kind([f for _read, f in by_tau[tau_s]])
        near = closest.get(tau_s)
        if bands and bands[-1].kind == kind and bands[-1].firm_kind == firm:
            last = bands[-1]
            keep = near if _nearer(near, last.closest) else last.closest
            bands[-1] = Band(kind, last.tau_lo_s, tau_s, firm, keep)
        else:
            bands.append(Band(kind, tau_s, tau_s, firm, near))
    return bands


def _kind(zs_all: Sequence[float]) -> str:
    zs = [zc for zc in zs_all if zc != 0.0]
    if not zs:
        return "agrees"
    if all(zc < 0 for zc in zs):
        return "noisier"
    if all(zc > 0 for zc in zs):
        return "quieter"
    return "mixed"


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
    """Which way the gap runs per Allan octave (:func:`direction_bands`), at the "where"
    test's own family-wise ``limits`` (one per cell). Once the test has found a gap
    (``significant``) each octave is also read descriptively at |z| > :data:`DIRECTION_Z`
    (``Band.kind``; the limits' reading is ``Band.firm_kind``), and the text says which is
    which. Until 2026-12-04 that descriptive reading was the verdict's "which way" with no
    word of it (the simulator's own output with 10 % bad checksums: the test flagged only the
    outage length, the verdict said "quieter than the receiver from 8 to 32 s") and the
    nearest octave was quoted "against 3.0", called the family-wise limit (it was 8.0).
    Without a gap no octave is read below the limits (read at 3, the simulator was "quieter
    from 1 to 32 s" on its own output, three runs)."""
    if not significant:
        return direction_bands(cells, z, limits)
    return direction_bands(cells, z, DIRECTION_Z, limits=limits)


def direction_text(bands: Sequence[Band]) -> str:
    """One clause per band at the test's family-wise limits, e.g. "the simulator is noisier
    than the receiver from 1 to 16 s; within the test's limits from 32 to 64 s"; then, where
    the bands were also read at the descriptive |z| > :data:`DIRECTION_Z` and that reading
    says more, that reading, labelled as such."""
    if not bands:
        return ""
    words = {
        "noisier": "noisier than the receiver",
        "quieter": "quieter than the receiver",
        "agrees": "within the test's limits",
        "mixed": "noisier on one axis and quieter on the other",
    }

    def span(lo_s: float, hi_s: float) -> str:
        return f"at {lo_s:g} s" if lo_s == hi_s else f"from {lo_s:g} to {hi_s:g} s"

    # the reading at the limits, consecutive octaves of one kind merged
    firm: list[tuple[str, float, float]] = []
    for band in bands:
        kind = band.kind if band.firm_kind is None else band.firm_kind
        if firm and firm[-1][0] == kind:
            firm[-1] = (kind, firm[-1][1], band.tau_hi_s)
        else:
            firm.append((kind, band.tau_lo_s, band.tau_hi_s))
    if all(kind == "agrees" for kind, _lo, _hi in firm):
        text = "Allan deviation within the test's family-wise limits at every octave"
        near = [b.closest for b in bands if b.closest is not None]
        if near:
            z, limit, axis, tau_s = max(near, key=lambda c: abs(c[0]) / c[1])
            text += f" (nearest: {axis} at {tau_s:g} s, z {z:+.1f} against {limit:.1f})"
    else:
        text = "the simulator is " + "; ".join(
            f"{words[kind]} {span(lo, hi)}" for kind, lo, hi in firm
        )
    extra = [
        f"{words[b.kind]} {span(b.tau_lo_s, b.tau_hi_s)}"
        for b in bands
        if b.firm_kind is not None and b.kind != b.firm_kind and b.kind != "agrees"
    ]
    if extra:
        text += (
            f"; read descriptively, octave by octave at |z| > {DIRECTION_Z:g} without "
            "correction for the octaves tested (not the test's finding), the simulator is "
            + "; ".join(extra)
        )
    return text


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
        """(sim - real) / real (inf when real is 0 and sim is not; NaN without a simulated
        value)."""
        if math.isnan(sim):
            return math.nan
        if real == 0:
            return 0.0 if sim == 0 else math.inf
        return (sim - real) / real

    @staticmethod
    def rel_text(sim: float, real: float) -> str:
        """:meth:`rel` as a signed percentage; "n/a, the real is 0" where it is infinite (a
        log whose position never changes has a real sigma and Allan deviation of 0), and
        :data:`NOT_REACHED` where there is no simulated value (an octave longer than a
        quarter of the simulated logs: the runs are on the real log's times but end
        earlier; before, it read "n/a, the real is 0" beside a real value of 1.583 m)."""
        if math.isnan(sim) and not math.isnan(real):
            return NOT_REACHED
        rel = Validation.rel(sim, real)
        return f"{rel:+.1%}" if math.isfinite(rel) else "n/a, the real is 0"

    @staticmethod
    def within(sim: float, real: float, tol: float) -> bool | None:
        """Whether ``sim`` is within ``tol`` of ``real`` (relative); None where there is no
        simulated value (:data:`NOT_REACHED`): such a figure is neither passed nor failed."""
        if math.isnan(sim) and not math.isnan(real):
            return None
        return abs(Validation.rel(sim, real)) <= tol

    @property
    def mean_ok(self) -> bool:
        return abs(self.rel(self.mean_sim_m, self.mean_real_m)) <= MEAN_SD_TOL

    @property
    def sd_ok(self) -> bool:
        return abs(self.rel(self.sd_sim_m, self.sd_real_m)) <= MEAN_SD_TOL

    @property
    def adev_reached(self) -> tuple[bool, ...]:
        """Per octave, whether the simulated logs give it a value (they may end earlier)."""
        return tuple(not math.isnan(s) for s in self.adev_sim_m)

    @property
    def adev_ok(self) -> tuple[bool, ...]:
        """Per octave, within :data:`ADEV_TOL` (False where not reached: see
        :attr:`adev_reached`)."""
        return tuple(
            bool(self.within(s, r, ADEV_TOL))
            for s, r in zip(self.adev_sim_m, self.adev_real_m, strict=True)
        )

    @property
    def passed(self) -> bool:
        """Mean, sigma and every octave the simulated logs reach within tolerance."""
        return (
            self.mean_ok
            and self.sd_ok
            and all(ok for ok, r in zip(self.adev_ok, self.adev_reached, strict=True) if r)
        )

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
            if self.within(sim, real, tol) is None:
                out.append(0.0)  # not reached by the simulated logs: nothing to fit
            else:
                out.append(math.log(ratio) / math.log1p(tol) if math.isfinite(ratio) else 100.0)
        return np.array(out)

    def worst(self) -> tuple[str | None, float]:
        """The figure furthest outside its tolerance (relative to it; the largest if all are
        within) and its difference (simulated - real) / real; ``(None, nan)`` when the
        simulated logs reach no figure (all shorter than the part validated)."""
        reached = [f for f in self.figures() if self.within(f[2], f[1], f[3]) is not None]
        if not reached:
            return None, math.nan
        label, real, sim, _tol = max(reached, key=lambda f: abs(self.rel(f[2], f[1])) / f[3])
        return label, self.rel(sim, real)

    def worst_text(self) -> str:
        """The figure furthest off and which way it misses, e.g. "Allan deviation at 1 s:
        simulated 43.4 % above the real, the simulator noisier there"."""
        label, rel = self.worst()
        if label is None:
            return "none: the simulated logs reach no figure (they are shorter than the real log)"
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
            f"{sum(self.adev_ok)} of {sum(self.adev_reached)} Allan octaves within "
            f"{ADEV_TOL:.0%}{self._not_reached_text()}; furthest off: {self.worst_text()}"
        )

    def _not_reached_text(self) -> str:
        missing = [t for t, r in zip(self.taus_s, self.adev_reached, strict=True) if not r]
        if not missing:
            return ""
        return (
            f" ({len(missing)} more, from {missing[0]:g} s, not reached: the simulated logs are"
            " shorter)"
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
    with warnings.catch_warnings():  # an octave no run reaches: NaN (NOT_REACHED), no warning
        warnings.simplefilter("ignore", RuntimeWarning)
        adev_sim = np.sqrt(np.nanmean([_avar(s, dt_s, factors) for s in sim_runs], axis=0))
    means = np.array([np.mean(r) for r in radial_sims if r.size])
    sds = np.array([np.std(r) for r in radial_sims if r.size])
    return Validation(
        n_runs=len(sim_runs),
        mean_real_m=float(np.mean(radial_real)) if radial_real.size else math.nan,
        mean_sim_m=float(np.mean(means)) if means.size else math.nan,  # no run had a fix
        sd_real_m=float(np.std(radial_real)) if radial_real.size else math.nan,
        sd_sim_m=float(np.mean(sds)) if sds.size else math.nan,
        taus_s=tuple(f * dt_s for f in factors),
        adev_real_m=tuple(float(a) for a in adev_real),
        adev_sim_m=tuple(float(a) for a in adev_sim),
        mean_spread=_relative_spread(means),
        sd_spread=_relative_spread(sds),
        ratio_spread=_relative_spread(sds / np.where(means > 0, means, np.nan)),
    )
