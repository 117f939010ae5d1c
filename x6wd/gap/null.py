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
    # Per-cell factor (>= 1) on the spread a real log is scored with (z, G), where the
    # replicates are draws from a model fitted to a few logs: the model's own spread misses
    # the parameter uncertainty and its misfit (:func:`inflation_from`). None: 1.
    inflation: np.ndarray | None = None

    @property
    def n_runs(self) -> int:
        """M, the replicates the null was calibrated on."""
        return int(self.values.shape[0])

    def z(self, battery: dict[Cell, float]) -> np.ndarray:
        """Null-calibrated z of one battery (cells missing from it score 0)."""
        values = np.array(
            [battery.get(c, mean) for c, mean in zip(self.cells, self.mean, strict=True)]
        )
        sd = self.sd if self.inflation is None else self.sd * self.inflation
        return (values - self.mean) / sd

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


# Spread factors by (statistic, axis); the key ("*", "*") holds the factor of any other cell.
Inflation = dict[tuple[str, str], float]
INFLATION_PRIOR = 6.0  # pseudo-cells of the global factor each group's factor is shrunk with
CHI2_MEDIAN = 0.454936  # median of a chi-square with 1 degree of freedom


def inflation_from(cells: Sequence[Cell], z: np.ndarray, n_logs: int) -> Inflation:
    """Spread factors for a null made of ``n_logs`` logs, from the z (rows: those logs,
    columns: ``cells``) of each log scored against replicates made WITHOUT it (leave-one-out).

    Every replicate is made of the logs' own material, so its cells sit near the logs'
    average: a new log differs from that average by its own spread and the average's, a
    factor sqrt(1 + 1/n) the replicates' spread cannot show (the prediction interval of one
    more draw); that is the floor. Where the logs vary more than that (a misfit of the noise
    model, the uncertainty of its parameters), their leave-one-out z^2, rescaled from n - 1
    logs to n, says by how much: medians pooled by (statistic, axis) and shrunk toward the
    median over all cells (``INFLATION_PRIOR`` pseudo-cells), so that a group of a few
    cells seen on two or three logs is not taken at its word."""
    n = max(int(n_logs), 1)
    floor = math.sqrt(1.0 + 1.0 / n)
    # a cell the logs were not scored on (a whole-log likelihood cell with its own floor)
    out: Inflation = {("*", "*"): floor}
    if n < 2:
        return out  # scored against their own replicates: no measure of the excess
    # z^2 / its median under the null (chi-square, 1 dof): robust, since a log scored
    # against replicates of n - 1 logs has heavy tails where n - 1 logs barely pin a spread
    # (the slow error's, from one or two hour means), which n logs pin better
    z2 = np.asarray(z, dtype=float) ** 2 * (1.0 + 1.0 / n) / (1.0 + 1.0 / (n - 1)) / CHI2_MEDIAN
    z2 = np.where(np.isfinite(z2), z2, np.nan)
    overall = float(np.nanmedian(z2)) if np.any(np.isfinite(z2)) else 1.0
    groups: dict[tuple[str, str], list[int]] = {}
    for j, c in enumerate(cells):
        groups.setdefault((c.statistic, c.axis), []).append(j)
    for key, cols in groups.items():
        values = z2[:, cols]
        values = values[np.isfinite(values)]
        group = float(np.median(values)) if values.size else overall
        pooled = (values.size * group + INFLATION_PRIOR * overall) / (values.size + INFLATION_PRIOR)
        out[key] = max(floor, math.sqrt(pooled))
    return out


def _inflation_array(cells: Sequence[Cell], inflation: Inflation | None) -> np.ndarray | None:
    if inflation is None:
        return None
    default = inflation.get(("*", "*"), 1.0)
    return np.array([inflation.get((c.statistic, c.axis), default) for c in cells])


def null_model(
    batteries: Sequence[dict[Cell, float]],
    alpha: float = 0.05,
    inflation: Inflation | None = None,
) -> NullModel:
    """Calibrate the battery on M >= 3 replicate batteries; ``alpha`` the family-wise error
    rate of the "where" threshold; ``inflation`` the spread factors of a parametric null
    (:func:`inflation_from`; None for replicates that are runs of the simulator)."""
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
    return NullModel(
        cells, values, mean, spread, max(bonferroni, quantile), _inflation_array(cells, inflation)
    )


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
    return NullModel(
        model.cells, values, values.mean(axis=0), spread, model.threshold, model.inflation
    )


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
