"""Sim-vs-sim null calibration: what the battery looks like when there is NO gap.

The baseline ensemble is M simulator runs with different seeds; with only one or two sim
logs a circular moving-block bootstrap of them stands in (blocks long compared with the
correlation time, so the time structure inside a block survives). A real log's cell is then
scored as z = (real - null mean) / null spread, and the "where" limits control the
family-wise error over all cells: each cell's Bonferroni-corrected Student-t prediction bound,
with a tail of its own where the replicates show that cell's tail to be heavier than the rest
(:func:`tail_dof`), raised if need be to the leave-one-out family-wise quantile of the
replicates themselves measured in units of those per-cell bounds. A replicate that is an
outlier of one cell (:func:`single_run_outliers`: far beyond the cell's other replicates by
median and MAD) raises that cell's limit alone, and the pooled tail is fitted robustly to one
odd replicate; the null lists such outliers (``NullModel.outliers``) for the report.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping, Sequence
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
                sat_set=None,
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
    threshold: float  # |z| limit of the cells that share the pooled tail
    # Per-cell factor (>= 1) on the spread a real log is scored with (z, G), where the
    # replicates are draws from a model fitted to a few logs: the model's own spread misses
    # the parameter uncertainty and its misfit (:func:`inflation_from`). None: 1.
    inflation: np.ndarray | None = None
    # Per-cell |z| limits (>= threshold: higher for a cell whose own tail is heavier than
    # the rest's, :func:`tail_dof`, or whose share of the level is smaller). None:
    # ``threshold`` for every cell.
    cell_threshold: np.ndarray | None = None
    # Which cells keep a heavier tail of their own (None: none).
    tail_apart: np.ndarray | None = None
    # Each cell's share of the family-wise level (None: equal shares).
    share: np.ndarray | None = None
    # (replicate index, cell, its leave-one-out z) of each replicate that is an outlier of
    # one cell (:func:`single_run_outliers`): that cell's limit covers it, no other's does.
    outliers: tuple[tuple[int, Cell, float], ...] = ()

    def limits(self) -> np.ndarray:
        """The |z| limit of every cell (the "where" test)."""
        if self.cell_threshold is None:
            return np.full(len(self.cells), self.threshold)
        return self.cell_threshold

    @property
    def apart(self) -> int:
        """How many cells are tested at a limit of their own (a heavier tail)."""
        return 0 if self.tail_apart is None else int(np.sum(self.tail_apart))

    def primary(self) -> np.ndarray | None:
        """Which cells have the larger share of the level (None: equal shares)."""
        if self.share is None:
            return None
        return self.share > float(np.min(self.share)) * (1 + 1e-9)

    def limit_of(self, primary: bool) -> float:
        """The lowest |z| limit of the cells with the larger share of the level (``primary``)
        or of the others (nan when there are none)."""
        limits = self.limits()
        mask = self.primary()
        if mask is None:
            return float(np.min(limits)) if primary else math.nan
        mask = mask if primary else ~mask
        return float(np.min(limits[mask])) if np.any(mask) else math.nan

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
        """G: the mean over the cells (weighted by their ``share`` of the "where" test's
        level, where the cells have shares) of clipped z^2 + 2 log(sd / ref_sd), i.e. twice
        the Gaussian negative log predictive density up to a constant. The log term is what
        stops an over-dispersed model (one that widens every spread) from looking like a
        good fit; with ``ref_sd`` None (the model's own spread) G is the mean z^2, about
        1 + 1/M for a draw from the null law. The weights are the test's: a gap found in a
        primary cell (a jump count) weighs in G as it weighed in finding it, not as one
        cell in ~75."""
        z = np.clip(self.z(battery), -Z_CLIP, Z_CLIP)
        penalty = 0.0 if ref_sd is None else 2.0 * np.log(self.sd / ref_sd)
        return float(np.average(z * z + penalty, weights=gap_weights(self.share)))

    def floor(self, ref_sd: np.ndarray | None = None, groups: int | None = None) -> float:
        """G_floor: the mean leave-one-out G of the replicates themselves (``groups``: of
        pooled draws of that many runs, each left out with its run's, :func:`loo_gaps`)."""
        weights = gap_weights(self.share)
        return float(np.mean(loo_gaps(self.values, self.cells, ref_sd, weights, groups)))


# How much of G's weighting follows the "where" test's shares (the rest is equal over cells).
GAP_SHARE_MIX = 0.5


def gap_weights(share: np.ndarray | None) -> np.ndarray | None:
    """G's weight per cell: GAP_SHARE_MIX of the test's shares and the rest equal (None:
    equal weights)."""
    if share is None:
        return None
    return GAP_SHARE_MIX * share + (1.0 - GAP_SHARE_MIX) / share.size


def _floors(cells: Sequence[Cell]) -> np.ndarray:
    return np.array([SD_FLOOR.get(c.statistic, 0.01) for c in cells])


def _parts_of(cells: Sequence[Cell]) -> dict[int, list[int]]:
    """Each whole-log mean cell (period "all") with the columns of its equal periods (the
    same statistic, axis, scale and place), where the battery has two or more of them."""
    parts: dict[tuple[str, str, str, str], list[int]] = {}
    for j, c in enumerate(cells):
        if c.statistic == "mean" and c.period != "all":
            parts.setdefault((c.statistic, c.axis, c.scale, c.place), []).append(j)
    out: dict[int, list[int]] = {}
    for j, c in enumerate(cells):
        if c.statistic == "mean" and c.period == "all":
            cols = parts.get((c.statistic, c.axis, c.scale, c.place), [])
            if len(cols) >= 2:
                out[j] = cols
    return out


def spread_of(values: np.ndarray, cells: Sequence[Cell]) -> np.ndarray:
    """Each cell's spread over the replicates (rows of ``values``), at least its statistic's
    :data:`SD_FLOOR`; a whole-log mean at least 1 / sqrt(k) of the pooled spread of its k
    equal periods' means.

    A slow error (a Gauss-Markov of minutes, an ionosphere of an hour) gives a short log's
    mean few independent draws, so M runs pin its spread with only M - 1 degrees of freedom:
    on 15-minute NEO-5 surrogate logs, 8 runs (seeds 300-307) spread their east means by
    0.11 m against the 0.40 m the surrogate gives, and half of the simulator's own logs came
    out "gap explained by bias" (|z| 11 at a limit of 6.3). Where the error is positively
    correlated in time (a slow error is), the mean of k equal periods varies by at least the
    average of their variances over k, and those k periods' spreads are pinned with k times
    the degrees of freedom: a floor that is right on average and rarely far low."""
    spread = np.maximum(values.std(axis=0, ddof=1), _floors(cells))
    for j, cols in _parts_of(cells).items():
        pooled = float(np.mean(values[:, cols].var(axis=0, ddof=1)))
        spread[j] = max(spread[j], math.sqrt(pooled / len(cols)))
    return spread


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
    logs to n, says by how much: medians pooled by (statistic, axis) (per scale too,
    :func:`inflation_key`) and shrunk toward the median over all cells (``INFLATION_PRIOR``
    pseudo-cells), so that a group of a few cells seen on two or three logs is not taken at
    its word."""
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
        groups.setdefault(inflation_key(c), []).append(j)
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
    return np.array([inflation.get(inflation_key(c), default) for c in cells])


# Statistics whose spread factor is measured per scale: the robust increments at 4 and 64 s
# read different parts of the law (logs whose fast correlation times differ, 9-18 s, differ
# at 4 s and agree at 64 s), and pooled over the scales their median z^2 hid the 4-s excess.
PER_SCALE_INFLATION = frozenset({"log_incr_med"})


def inflation_key(cell: Cell) -> tuple[str, str]:
    """The group whose spread factor ``cell`` takes: (statistic, axis), and the scale for
    :data:`PER_SCALE_INFLATION`."""
    if cell.statistic in PER_SCALE_INFLATION:
        return (cell.statistic, f"{cell.axis} {cell.scale}")
    return (cell.statistic, cell.axis)


# Tail degrees of freedom tried per cell (plus the Gaussian cell's M - 2, that of a replicate
# scored against the M - 1 others); the pooled tail clips |z| here, so that one replicate of
# one heavy cell does not set every cell's tail.
TAIL_DOF_GRID = (0.5, 0.75, 1.0, 1.5, 2.0, 3.0, 4.0, 6.0, 8.0, 12.0, 16.0, 24.0, 32.0, 64.0)
TAIL_CLIP_Z = 10.0
TAIL_APART_ALPHA = 0.05  # family-wise level of the test that sets a cell's tail apart


def tail_dof(z_loo: np.ndarray, outlier: np.ndarray | None = None) -> np.ndarray:
    """Per-cell Student-t degrees of freedom of the replicates' leave-one-out z (rows:
    replicates, columns: cells), the scale fixed at a Gaussian cell's sqrt(1 + 1/(M - 1)).

    A Gaussian cell's leave-one-out z is Student-t with M - 2 degrees of freedom; a cell
    whose replicates now and then differ by far more (a whole-log likelihood ratio that is
    0 for most runs and 54 for one) has a heavier tail. The cells share one tail, fitted to
    all their z pooled (each clipped at ``TAIL_CLIP_Z``), unless a cell's own z reject it
    by a likelihood-ratio test at ``TAIL_APART_ALPHA`` over all cells: then that cell keeps
    the heavier tail of its own. So one heavy cell raises its own limit, not every cell's
    (through the family-wise maximum it did: one run's random-walk ratio set the limit of
    every cell, and gpsd's ZED-F9P log came out "no significant gap").

    ``outlier`` (same shape; :func:`single_run_outliers`) marks z the pooled tail leaves
    out, and the pooled tail is fitted without the runs that have one (while 4 runs are
    left): such an odd run that also sits 7-8 spreads off in twenty correlated cells (the
    fast-noise octaves, lags and bands all read its noisier hour) is one event, not twenty,
    and had set every cell's tail to 3 degrees of freedom at M = 8 (limits 13 where the
    runs without it give 8); :func:`null_model`'s family-wise step still covers that run."""
    n_runs, n_cells = z_loo.shape
    gaussian = float(n_runs - 2)
    grid = np.array([g for g in TAIL_DOF_GRID if g < gaussian] + [gaussian])
    u = z_loo / math.sqrt(1.0 + 1.0 / (n_runs - 1))
    own = np.array([sps.t.logpdf(u, nu).sum(axis=0) for nu in grid])  # (grid, cells)
    kept = np.ones(u.shape, bool) if outlier is None else ~outlier
    clipped = np.where(kept, np.clip(u, -TAIL_CLIP_Z, TAIL_CLIP_Z), np.nan)
    # a run with an outlier cell is an odd run: its other cells do not set the pooled tail
    # either (with none flagged, the fit is over every run, as it always was: a lightest
    # fit over the runs left out in turn lowered every limit of a plain null, 6.6 -> 5.1 at
    # M = 12)
    odd = np.flatnonzero(np.any(~kept, axis=1))
    rows = np.delete(clipped, odd, axis=0) if 0 < odd.size <= n_runs - 4 else clipped
    pooled = int(np.argmax([np.nansum(sps.t.logpdf(rows, nu)) for nu in grid]))
    best = np.argmax(own, axis=0)
    gain = own[best, np.arange(n_cells)] - own[pooled]
    critical = float(sps.chi2.ppf(1.0 - TAIL_APART_ALPHA / max(n_cells, 1), 1)) / 2.0
    apart = (gain > critical) & (best < pooled)
    return np.where(apart, grid[best], grid[pooled])


# A replicate's leave-one-out z this many robust spreads (1.4826 MAD of the cell's z over the
# replicates, at least a Gaussian cell's sqrt(1 + 1/(M - 1))) from the cell's median, and
# beyond the cell's Gaussian limit, is an outlier of that cell alone (:func:`single_run_outliers`).
OUTLIER_SPREADS = 8.0


def single_run_outliers(
    z_loo: np.ndarray, gaussian_limit: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Which leave-one-out z (rows: replicates, columns: cells) are outliers of their cell,
    and each cell's bound of |z|: the larger of the cell's median's size plus
    ``OUTLIER_SPREADS`` robust spreads of its z over the replicates and ``gaussian_limit``
    (a Gaussian cell's family-wise bound, so that its t tail at a small M is no outlier: at
    M = 4 that is ~90 and one run cannot be told from it).

    A statistic with a point mass and a long tail (the random walk's likelihood ratio: 0 on
    most runs, 84 on one 15-minute run whose fast noise was five times the others') gives one
    replicate a z of 35 against the others' 0.4; the family-wise step took it as the tail of
    every cell and set every limit to 32.5 (a 4 m jump layer at z 14 read "no significant
    gap"). Median and MAD are robust to that one run, so it stands out of its cell even at
    M = 4-12, where the tail test (:func:`tail_dof`) has too few runs to set the cell apart."""
    n_runs = z_loo.shape[0]
    center = np.median(z_loo, axis=0)
    mad = 1.4826 * np.median(np.abs(z_loo - center), axis=0)
    spread = np.maximum(mad, math.sqrt(1.0 + 1.0 / (n_runs - 1)))
    bound = np.maximum(np.abs(center) + OUTLIER_SPREADS * spread, gaussian_limit)
    return np.abs(z_loo) > bound, bound


# Statistics an hour holds only a few independent draws of, so that n logs pin their spread
# with few degrees of freedom, whatever the replicates made of them say
# (:func:`between_log_dof`): the means, the spread about the origin (std, CEP50, R95), the
# autocorrelation (normalised by the hour's variance) and the random walk's likelihood
# ratio all read the slow error, most of an hour's variance and a correlation time of about
# an hour; the step tail reads the few bad-geometry episodes.
PER_LOG_STATISTICS = frozenset(
    {"mean", "log_std", "log_cep50", "log_r95", "acf", "random_walk_lr", "step_tail"}
)


def between_log_dof(cells: Sequence[Cell], dof_by_axis: Mapping[str, float] | None) -> np.ndarray:
    """Degrees of freedom of each cell's spread as a few baseline logs pin it: for the
    :data:`PER_LOG_STATISTICS` cells ``dof_by_axis[axis]`` (see
    :func:`x6wd.gap.noise.slow_error_dof`), inf for the rest (the replicates alone decide) and
    for every cell when ``dof_by_axis`` is None (a null of simulator runs).

    Replicates drawn from a law fitted to n logs spread their means by what that law's slow
    error implies, and a law fitted to a few hours pins that poorly: on three simulated NEO-5
    hours the replicates' spread of hour means was 0.4-3.1 m against the simulator's 1.3 m
    (east), and with the spread factors the real hour's z had heavy tails (sd 1.4, kurtosis
    6-11). A t limit with the logs' degrees of freedom is what they support."""
    if dof_by_axis is None:
        return np.full(len(cells), np.inf)
    return np.array(
        [
            dof_by_axis.get(c.axis, np.inf) if c.statistic in PER_LOG_STATISTICS else np.inf
            for c in cells
        ],
        dtype=float,
    )


def null_model(
    batteries: Sequence[dict[Cell, float]],
    alpha: float = 0.05,
    inflation: Inflation | None = None,
    weights: np.ndarray | None = None,
    dof_by_axis: Mapping[str, float] | None = None,
) -> NullModel:
    """Calibrate the battery on M >= 3 replicate batteries; ``alpha`` the family-wise error
    rate of the "where" test; ``inflation`` the spread factors of a parametric null
    (:func:`inflation_from`; None for replicates that are runs of the simulator);
    ``weights`` each cell's share of ``alpha`` (in the batteries' cell order; normalised
    here; None: equal shares).

    Each cell's limit is the weighted-Bonferroni Student-t prediction bound of one more
    draw against the mean of M (a Gaussian cell: M - 1 degrees of freedom; a cell with a
    heavier tail of its own, :func:`tail_dof`: fewer): a cell with share w is tested at
    level alpha w, so the family-wise level stays alpha whatever the shares, and a battery
    can spend most of it on the few cells most sensitive to each kind of gap instead of
    spreading it evenly over dozens of descriptive ones. The limits are then raised together,
    if need be, to the 1 - alpha quantile of the replicates' own leave-one-out family-wise
    maximum of |z| / limit: the cells are not exactly Student-t (an hour of the simulator
    can sit 8 spreads off in several cells at once), though with M replicates that
    quantile is coarse, hence the parametric bounds beneath it; a replicate's outlier of one
    cell (:func:`single_run_outliers`) raises its own cell's limit to itself and that run
    leaves the step (with M <= 20 the quantile is about the maximum, so one run's one cell
    had set every limit; with fewer than 3 other runs its outlier counts at its cell's
    outlier bound). ``dof_by_axis``: a few-logs
    null's degrees of freedom of its per-log statistics per axis; those cells
    (:func:`between_log_dof`) get a t limit with them (the two dof combined as
    1 / (1 / tail + 1 / logs))."""
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
    spread = spread_of(values, cells)
    # A new draw vs the mean of M: prediction spread sd*sqrt(1+1/M), Student-t with M-1 dof.
    share = np.full(n_cells, 1.0 / n_cells) if weights is None else cell_shares(weights)
    level = 1.0 - alpha * share / 2
    widen = math.sqrt(1.0 + 1.0 / n_runs)
    few = between_log_dof(cells, dof_by_axis)
    limits = sps.t.ppf(level, _with_logs(np.full(n_cells, n_runs - 1.0), few)) * widen
    apart = None
    outliers: tuple[tuple[int, Cell, float], ...] = ()
    if n_runs >= 4:
        z_loo = np.array([_loo_z(values, cells, i) for i in range(n_runs)])
        # a Gaussian cell's leave-one-out z: Student-t, M - 2 dof, family-wise over M runs
        gaussian = sps.t.ppf(1.0 - alpha * share / (2 * n_runs), _with_logs(n_runs - 2.0, few))
        loo_scale = math.sqrt(1.0 + 1.0 / (n_runs - 1))
        outlier, bound = single_run_outliers(z_loo, gaussian * loo_scale)
        own_dof = tail_dof(z_loo, outlier)
        apart = (own_dof < float(np.max(own_dof))) | np.any(outlier, axis=0)
        # from the M - 1 replicates of a leave-one-out z to the M the real log is scored on
        dof = _with_logs(own_dof * (n_runs - 1) / (n_runs - 2), few)
        limits = sps.t.ppf(level, dof) * widen
        # a run with an outlier raises its own cell's limit to itself and sets no other: its
        # other cells leave the family-wise step too (its z there is the same odd run's: one
        # run z +33 in one cell and -12 in another set every limit 1.25x, hiding a jumps
        # layer); with too few ordinary runs left, its outlier counts at its cell's bound
        size = np.abs(z_loo)
        odd_run = np.any(outlier, axis=1)
        if n_runs - int(np.count_nonzero(odd_run)) >= 3:
            excess = np.max(size[~odd_run] / limits, axis=1)
        else:
            excess = np.max(np.where(outlier, np.minimum(size, bound), size) / limits, axis=1)
        limits = limits * max(1.0, float(np.quantile(excess, 1.0 - alpha)))
        limits = np.maximum(limits, np.max(np.where(outlier, size, 0.0), axis=0))
        outliers = tuple((int(i), cells[j], float(z_loo[i, j])) for i, j in np.argwhere(outlier))
    return NullModel(
        cells,
        values,
        mean,
        spread,
        float(np.min(limits)),
        _inflation_array(cells, inflation),
        limits,
        apart,
        None if weights is None else share,
        outliers,
    )


def _with_logs(dof: np.ndarray, few: np.ndarray) -> np.ndarray:
    # two sources of spread uncertainty: the replicates' tail and the logs behind the law
    return 1.0 / (1.0 / dof + 1.0 / few)


def cell_shares(weights: np.ndarray) -> np.ndarray:
    """Weights (>= 0, at least one > 0) as shares of a family-wise level (summing to 1)."""
    w = np.asarray(weights, dtype=float)
    if w.ndim != 1 or not np.all(np.isfinite(w)) or np.any(w < 0) or not np.any(w > 0):
        raise ConfigError(f"cell weights must be finite, >= 0 and not all 0: {w!r}")
    return w / float(w.sum())


def _loo(
    values: np.ndarray, cells: Sequence[Cell], i: int, groups: int | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Replicate ``i``'s z against the others and their spread; ``groups``: without every
    draw of its run (:func:`loo_gaps`)."""
    rows = np.arange(values.shape[0])
    rest = values[rows % groups != i % groups] if groups else np.delete(values, i, axis=0)
    spread = spread_of(rest, cells)
    return (values[i] - rest.mean(axis=0)) / spread, spread


def _loo_z(values: np.ndarray, cells: Sequence[Cell], i: int) -> np.ndarray:
    return _loo(values, cells, i)[0]


def loo_gaps(
    values: np.ndarray,
    cells: Sequence[Cell],
    ref_sd: np.ndarray | None = None,
    share: np.ndarray | None = None,
    groups: int | None = None,
) -> np.ndarray:
    """G of each replicate scored against the others (see :meth:`NullModel.gap`; ``share``
    the cells' weights, None: equal). ``groups``: the rows are draws of that many runs
    (row r of run r % groups), and a replicate is scored without every draw of its run: a
    pooled null's other draws of the same run are copies of it where the effect is fixed,
    and scoring against them lowered the floor of an effect that does nothing (60 cells,
    8 runs x 4 draws: 0.98 against one draw's 1.73)."""
    out = []
    for i in range(values.shape[0]):
        z, spread = _loo(values, cells, i, groups)
        z = np.clip(z, -Z_CLIP, Z_CLIP)
        penalty = 0.0 if ref_sd is None else 2.0 * np.log(spread / ref_sd)
        out.append(float(np.average(z * z + penalty, weights=share)))
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
    spread = spread_of(values, model.cells) * math.sqrt(model.n_runs / (model.n_runs - 1))
    spread = np.maximum(spread, _floors(model.cells))
    return dataclasses.replace(model, values=values, mean=values.mean(axis=0), sd=spread)


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
