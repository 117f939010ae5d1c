"""Sim-vs-sim null calibration: what the battery looks like when there is NO gap.

The baseline ensemble is M simulator runs with different seeds; with only one or two sim
logs a circular moving-block bootstrap of them stands in (blocks long compared with the
correlation time, so the time structure inside a block survives). A real log's cell is then
scored as z = (real - null mean) / null spread, and the "where" threshold controls the
family-wise error over all cells: the larger of a Bonferroni-corrected Student-t prediction
bound and the leave-one-out max-|z| quantile of the replicates themselves.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy import stats as sps

from sim_backend.effects import PositionSeries
from x6wd.core.errors import ConfigError
from x6wd.gap.stats import SD_FLOOR, Cell

Z_CLIP = 20.0  # |z| cap inside gap measures, so one degenerate cell cannot dominate G


def block_bootstrap(
    series: Sequence[PositionSeries],
    n_out: int,
    rng: np.random.Generator,
    block_s: float,
    template: PositionSeries | None = None,
) -> list[PositionSeries]:
    """``n_out`` replicates of the same length as ``series[0]`` made of circular blocks of
    ``block_s`` seconds drawn from the given series, on the time stamps (and truth motion) of
    ``template`` (default the first series). Joins are raw,
    so choose blocks long against the correlation time: few joins, little spurious jumping."""
    if not series:
        raise ConfigError("block bootstrap needs at least one sim series")
    base = template if template is not None else series[0]
    n = len(base)
    dt = float(np.median(np.diff(base.t_s))) if n > 1 else 1.0
    b = max(2, min(n, round(block_s / dt)))
    names = ("east_m", "north_m", "up_m", "valid")
    out: list[PositionSeries] = []
    for _ in range(n_out):
        pieces: dict[str, list[np.ndarray]] = {k: [] for k in names}
        pos = 0
        while pos < n:
            src = series[int(rng.integers(len(series)))]
            m = len(src)
            take = min(b, n - pos)
            idx = (int(rng.integers(m)) + np.arange(take)) % m
            for k in names:
                pieces[k].append(np.asarray(getattr(src, k))[idx])
            pos += take
        cat = {k: np.concatenate(v) for k, v in pieces.items()}
        out.append(
            base.with_(
                east_m=cat["east_m"],
                north_m=cat["north_m"],
                up_m=cat["up_m"],
                valid=cat["valid"].astype(bool),
                nsats=None,
            )
        )
    return out


@dataclass(frozen=True)
class NullModel:
    """Per-cell null mean and spread from M replicate batteries, plus the FWER threshold."""

    cells: tuple[Cell, ...]
    values: np.ndarray  # (M, K) replicate batteries
    mean: np.ndarray
    sd: np.ndarray
    threshold: float

    @property
    def m(self) -> int:
        return int(self.values.shape[0])

    def z(self, battery: dict[Cell, float]) -> np.ndarray:
        """Null-calibrated z of one battery (cells missing from it score 0)."""
        x = np.array([battery.get(c, m) for c, m in zip(self.cells, self.mean, strict=True)])
        return (x - self.mean) / self.sd

    def gap(self, battery: dict[Cell, float], ref_sd: np.ndarray | None = None) -> float:
        """G: mean over the cells of clipped z^2 + 2 log(sd / ref_sd), i.e. twice the Gaussian
        negative log predictive density up to a constant. The log term is what stops an
        over-dispersed model (one that widens every spread) from looking like a good fit;
        with ``ref_sd`` None (the model's own spread) G is the mean z^2, about 1 + 1/M for a
        draw from the null law."""
        z = np.clip(self.z(battery), -Z_CLIP, Z_CLIP)
        pen = 0.0 if ref_sd is None else 2.0 * np.log(self.sd / ref_sd)
        return float(np.mean(z * z + pen))

    def floor(self, ref_sd: np.ndarray | None = None) -> float:
        """G_floor: the mean leave-one-out G of the replicates themselves."""
        return float(np.mean(loo_gaps(self.values, self.cells, ref_sd)))


def _floors(cells: Sequence[Cell]) -> np.ndarray:
    return np.array([SD_FLOOR.get(c.statistic, 0.01) for c in cells])


def null_model(batteries: Sequence[dict[Cell, float]], alpha: float = 0.05) -> NullModel:
    """Calibrate the battery on M >= 3 replicate batteries; ``alpha`` the family-wise error
    rate of the "where" threshold."""
    if len(batteries) < 3:
        raise ConfigError(
            f"null calibration needs at least 3 baseline replicates, got {len(batteries)}"
        )
    cells = tuple(batteries[0])
    values = np.array([[b.get(c, np.nan) for c in cells] for b in batteries], dtype=float)
    col_mean = np.nanmean(values, axis=0)
    values = np.where(np.isfinite(values), values, col_mean)
    m, k = values.shape
    mean = values.mean(axis=0)
    sd = np.maximum(values.std(axis=0, ddof=1), _floors(cells))
    # A new draw vs the mean of M: prediction spread sd*sqrt(1+1/M), Student-t with M-1 dof.
    t_bonf = float(sps.t.ppf(1.0 - alpha / (2 * k), m - 1)) * math.sqrt(1.0 + 1.0 / m)
    loo = loo_max_z(values, cells)
    q = float(np.quantile(loo, 1.0 - alpha)) if loo.size else 0.0
    return NullModel(cells, values, mean, sd, max(t_bonf, q))


def _loo_z(values: np.ndarray, cells: Sequence[Cell], i: int) -> np.ndarray:
    rest = np.delete(values, i, axis=0)
    sd = np.maximum(rest.std(axis=0, ddof=1), _floors(cells))
    return (values[i] - rest.mean(axis=0)) / sd


def loo_max_z(values: np.ndarray, cells: Sequence[Cell]) -> np.ndarray:
    """Max |z| of each replicate scored against the others (its own null of the max)."""
    if values.shape[0] < 4:
        return np.zeros(0)
    return np.array([np.max(np.abs(_loo_z(values, cells, i))) for i in range(values.shape[0])])


def loo_gaps(
    values: np.ndarray, cells: Sequence[Cell], ref_sd: np.ndarray | None = None
) -> np.ndarray:
    """G of each replicate scored against the others (see :meth:`NullModel.gap`)."""
    out = []
    floors = _floors(cells)
    for i in range(values.shape[0]):
        z = np.clip(_loo_z(values, cells, i), -Z_CLIP, Z_CLIP)
        pen = 0.0
        if ref_sd is not None:
            sd = np.maximum(np.delete(values, i, axis=0).std(axis=0, ddof=1), floors)
            pen = 2.0 * np.log(sd / ref_sd)
        out.append(float(np.mean(z * z + pen)))
    return np.array(out)


def closure_of(g_baseline: float, g_with: float, g_floor: float) -> float:
    """Closure = (G_baseline - G_with) / (G_baseline - G_floor); 0 when there is no gap."""
    den = g_baseline - g_floor
    if den <= 1e-9:
        return 0.0
    return (g_baseline - g_with) / den


def resample_null(model: NullModel, rng: np.random.Generator) -> NullModel:
    """The null rebuilt from its members drawn with replacement (for closure intervals)."""
    idx = rng.integers(model.m, size=model.m)
    v = model.values[idx]
    # A resample repeats members: its spread (ddof 1) is (M-1)/M of the ensemble's in
    # expectation, which biased closures low (clipped baseline cells do not scale with it,
    # the effect's do): an interval that missed its own estimate.
    sd = np.maximum(
        v.std(axis=0, ddof=1) * math.sqrt(model.m / (model.m - 1)), _floors(model.cells)
    )
    return NullModel(model.cells, v, v.mean(axis=0), sd, model.threshold)


def closure_ci(
    real_b: dict[Cell, float], base: NullModel, eff: NullModel, rng: np.random.Generator, n: int
) -> tuple[float, float]:
    """5-95 % interval of the closure over ``n`` resamples of the ensemble members."""
    ref = base.sd
    vals = []
    for _ in range(n):
        nb = resample_null(base, rng)
        ne = resample_null(eff, rng)
        vals.append(closure_of(nb.gap(real_b, ref), ne.gap(real_b, ref), nb.floor(ref)))
    lo, hi = np.quantile(vals, [0.05, 0.95])
    return float(lo), float(hi)
