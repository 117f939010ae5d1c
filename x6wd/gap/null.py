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
    frame = template if template is not None else series[0]
    n_epochs = len(frame)
    dt_s = float(np.median(np.diff(frame.t_s))) if n_epochs > 1 else 1.0
    block_len = max(2, min(n_epochs, round(block_s / dt_s)))
    columns = ("east_m", "north_m", "up_m", "valid")
    out: list[PositionSeries] = []
    for _ in range(n_out):
        pieces: dict[str, list[np.ndarray]] = {k: [] for k in columns}
        filled = 0
        while filled < n_epochs:
            source = series[int(rng.integers(len(series)))]
            n_source = len(source)
            n_take = min(block_len, n_epochs - filled)
            index = (int(rng.integers(n_source)) + np.arange(n_take)) % n_source
            for k in columns:
                pieces[k].append(np.asarray(getattr(source, k))[index])
            filled += n_take
        joined = {k: np.concatenate(v) for k, v in pieces.items()}
        out.append(
            frame.with_(
                east_m=joined["east_m"],
                north_m=joined["north_m"],
                up_m=joined["up_m"],
                valid=joined["valid"].astype(bool),
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
    def n_runs(self) -> int:
        """M, the replicates the null was calibrated on."""
        return int(self.values.shape[0])

    def z(self, battery: dict[Cell, float]) -> np.ndarray:
        """Null-calibrated z of one battery (cells missing from it score 0)."""
        values = np.array(
            [battery.get(c, mean) for c, mean in zip(self.cells, self.mean, strict=True)]
        )
        return (values - self.mean) / self.sd

    def gap(self, battery: dict[Cell, float], ref_sd: np.ndarray | None = None) -> float:
        """G: mean over the cells of clipped z^2 + 2 log(sd / ref_sd), i.e. twice the Gaussian
        negative log predictive density up to a constant. The log term is what stops an
        over-dispersed model (one that widens every spread) from looking like a good fit;
        with ``ref_sd`` None (the model's own spread) G is the mean z^2, about 1 + 1/M for a
        draw from the null law."""
        z = np.clip(self.z(battery), -Z_CLIP, Z_CLIP)
        penalty = 0.0 if ref_sd is None else 2.0 * np.log(self.sd / ref_sd)
        return float(np.mean(z * z + penalty))

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
    cell_means = np.nanmean(values, axis=0)
    values = np.where(np.isfinite(values), values, cell_means)
    n_runs, n_cells = values.shape
    mean = values.mean(axis=0)
    spread = np.maximum(values.std(axis=0, ddof=1), _floors(cells))
    # A new draw vs the mean of M: prediction spread sd*sqrt(1+1/M), Student-t with M-1 dof.
    bonferroni = float(sps.t.ppf(1.0 - alpha / (2 * n_cells), n_runs - 1)) * math.sqrt(
        1.0 + 1.0 / n_runs
    )
    loo_max = loo_max_z(values, cells)
    quantile = float(np.quantile(loo_max, 1.0 - alpha)) if loo_max.size else 0.0
    return NullModel(cells, values, mean, spread, max(bonferroni, quantile))


def _loo_z(values: np.ndarray, cells: Sequence[Cell], i: int) -> np.ndarray:
    rest = np.delete(values, i, axis=0)
    spread = np.maximum(rest.std(axis=0, ddof=1), _floors(cells))
    return (values[i] - rest.mean(axis=0)) / spread


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
        penalty = 0.0
        if ref_sd is not None:
            spread = np.maximum(np.delete(values, i, axis=0).std(axis=0, ddof=1), floors)
            penalty = 2.0 * np.log(spread / ref_sd)
        out.append(float(np.mean(z * z + penalty)))
    return np.array(out)


def closure_of(g_baseline: float, g_with: float, g_floor: float) -> float:
    """Closure = (G_baseline - G_with) / (G_baseline - G_floor); 0 when there is no gap."""
    denominator = g_baseline - g_floor
    if denominator <= 1e-9:
        return 0.0
    return (g_baseline - g_with) / denominator


def resample_null(model: NullModel, rng: np.random.Generator) -> NullModel:
    """The null rebuilt from its members drawn with replacement (for closure intervals)."""
    index = rng.integers(model.n_runs, size=model.n_runs)
    values = model.values[index]
    # A resample repeats members: its spread (ddof 1) is (M-1)/M of the ensemble's in
    # expectation, which biased closures low (clipped baseline cells do not scale with it,
    # the effect's do): an interval that missed its own estimate.
    spread = np.maximum(
        values.std(axis=0, ddof=1) * math.sqrt(model.n_runs / (model.n_runs - 1)),
        _floors(model.cells),
    )
    return NullModel(model.cells, values, values.mean(axis=0), spread, model.threshold)


def closure_ci(
    real_battery: dict[Cell, float],
    baseline: NullModel,
    effect: NullModel,
    rng: np.random.Generator,
    resamples: int,
) -> tuple[float, float]:
    """5-95 % interval of the closure over ``resamples`` resamples of the ensemble members."""
    ref_sd = baseline.sd
    closures = []
    for _ in range(resamples):
        base_draw = resample_null(baseline, rng)
        effect_draw = resample_null(effect, rng)
        closures.append(
            closure_of(
                base_draw.gap(real_battery, ref_sd),
                effect_draw.gap(real_battery, ref_sd),
                base_draw.floor(ref_sd),
            )
        )
    lo, hi = np.quantile(closures, [0.05, 0.95])
    return float(lo), float(hi)
