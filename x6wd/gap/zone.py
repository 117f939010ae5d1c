"""Fit of the ``multipath_zone`` effect: where along the truth track the real log has more
error than the baseline, a wall whose zone covers those places, and the zone's Gauss-Markov
noise and bias by exact likelihood.

Only moving logs are fitted. A static receiver is always or never inside a zone, and a zone
around it is indistinguishable from ``gauss_markov`` + ``bias``; those fitters answer it.

1. **Places.** The truth track is binned in square cells (:data:`CELL_M`). Per series and
   cell: the log mean squared step between consecutive fixes (the zone's noise is much
   faster than the baseline's drift, and its bias switches on and off in a step) and the
   mean over passes of the log mean squared level (the zone's level variance and bias; per
   pass, so that one pass on a large excursion of the slow drift does not make a place).
   Each is compared with the other baseline runs in the SAME cell (they share the truth
   track and epochs: a per-place null), in units of the runs' pooled spread, and smoothed
   over neighbouring cells at three scales.
2. **Detection.** The real log's highest smoothed cell must beat those of every baseline
   run scored the same way (leave-one-out): calibrated on sim-vs-sim, no asymptotic law.
   The located places are the connected cells around it above the runs' 99 % cell quantile.
3. **Boundaries.** Every entry into and exit out of the located places is moved to its most
   likely epoch (exact likelihood, twice, the parameters refitted in between); runs of
   located epochs that the likelihood does not want are dropped.
4. **Geometry.** Only the zone's intersection with the track is identifiable. Candidate
   walls lie on the side opposite the in-zone bias (so "away from the wall" is the bias
   direction), at several distances behind the located places, each the shortest segment
   whose zone covers every located epoch with the fewest others (:func:`fit_walls`); the
   likelihood picks one and a pattern search on it moves the wall's orientation, offset,
   ends and distance (:func:`_refine_wall`).
5. **Parameters.** Exact likelihood (:func:`zone_terms`): the baseline noise model
   (:func:`x6wd.gap.noise.noise_model`: Gauss-Markov components + white noise per axis) + a
   Gauss-Markov component (sigma, tau) that runs all the time but is observed only in the
   zone, as the simulator's layer generates it, + the bias along the wall's away vectors
   in the zone, profiled by GLS; a Kalman filter whose observation of the effect state is
   switched by the in-zone mask, batched over parameter sets and zones. Grid and zooms in
   (log sigma, log tau). Standard errors from the curvature of the log-likelihood; for the
   geometry one parameter moved at a time (conditional on the others; NaN where the track
   does not feel it).
6. **Decision.** None unless the zone's likelihood gain over "no zone" beats BIC with every
   parameter, geometry included, counted.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace

import numpy as np

from sim_backend.effects import MultipathZone, PositionSeries, truth_track_m
from x6wd.gap.fitted import Fit
from x6wd.gap.kalman import component_law, quadratic_peak, transitions
from x6wd.gap.noise import NoiseModel, noise_model
from x6wd.gap.stats import Layout

CELL_M = 5.0  # place bin (m): about 2-3 epochs of travel per pass at walking to cycling speed
SCALES = (1, 2, 4)  # smoothing half-widths (cells): zones from ~15 m to ~45 m across
REGION_QUANTILE = 0.99  # a cell joins the zone above this quantile of the runs' cells
MAX_SHARE = 0.5  # excess on more than half the track is not a place: that is gauss_markov
WALL_GAP_M = 1.0  # keeps the nearest in-zone point off the wall line (away vector defined)
BEHIND_COST = 1e3  # log-likelihood per in-zone track point behind the wall: not allowed
STARTS = 3  # local maxima of the coarse (sigma, tau) grid zoomed in on
# Starting walls: stepped back from the located places by these distances (m), each with
# the zone reaching this much (m) beyond the farthest located point.
WALL_BACK_M = (0.0, 2.0, 4.0, 6.0, 8.0, 12.0, 16.0, 24.0, 32.0)
WALL_REACH_M = (0.0, 1.0, 2.0, 4.0, 6.0, 8.0, 12.0, 16.0, 24.0)
ZONE_PARAMS = 8  # x1, y1, x2, y2, distance, sigma, tau, bias: counted in the BIC


# --- the masked Kalman filter ------------------------------------------------------------------


@dataclass(frozen=True)
class ZoneTerms:
    """Per (batch, axis) sums over valid epochs of log S, e^2/S, e*e1/S, e1^2/S (e the data's
    innovations, e1 those of the bias regressor) and the observation counts."""

    log_s: np.ndarray
    yy: np.ndarray
    y1: np.ndarray
    oo: np.ndarray
    nobs: np.ndarray

    def _gls(self, shared: bool) -> tuple[np.ndarray, np.ndarray]:
        y1, oo = (self.y1.sum(-1), self.oo.sum(-1)) if shared else (self.y1, self.oo)
        return y1, np.maximum(oo, 1e-300)

    def loglik(self, bias: bool, shared: bool = False) -> np.ndarray:
        """Exact Gaussian log-likelihood per batch element, with the bias at zero (``bias``
        False) or profiled by GLS: per axis, or one coefficient of both axes' regressors
        (``shared``: the magnitude along given unit vectors)."""
        q = np.sum(self.log_s + self.yy + self.nobs * math.log(2 * math.pi), axis=-1)
        if bias:
            y1, oo = self._gls(shared)
            explained = y1**2 / oo
            q = q - (explained if shared else explained.sum(axis=-1))
        return -0.5 * q

    def bias(self, shared: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """GLS bias (m) per (batch, axis), or per batch when ``shared``, and its standard
        error (m)."""
        y1, oo = self._gls(shared)
        return y1 / oo, 1.0 / np.sqrt(oo)


def _filter(
    t_s: np.ndarray,
    error_m: np.ndarray,
    valid: np.ndarray,
    model: NoiseModel,
    effect_var: np.ndarray,
    effect_tau_s: np.ndarray,
    zone: np.ndarray | None,
    regressor: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Kalman filter of baseline model + a Gauss-Markov effect seen only where ``zone``.

    Columns j = (batch j // 2, axis j % 2): ``error_m`` (C, n) data minus the baseline mean
    (m), ``valid`` (C, n), ``effect_var`` (m^2) / ``effect_tau_s`` (C,), ``zone`` (C, n) or
    None (always seen), ``regressor`` (C, n) a bias regressor (default: ``zone``). Returns
    the innovations of the data and of the regressor, and their variance, each (n, C). Every
    component is propagated with the actual step, so outages and irregular sampling are
    exact."""
    n_cols, n_epochs = error_m.shape
    n_states = model.tau_s.shape[1] + 1
    var, tau_s = component_law(model, effect_var, effect_tau_s)
    white_var_m2 = np.tile(model.white_m**2, n_cols // 2)
    trans = transitions(var, tau_s, np.diff(t_s))
    seen_by = np.ones((n_epochs, n_cols)) if zone is None else np.asarray(zone, dtype=float).T
    seen = np.asarray(seen_by.any(axis=1))  # most epochs are outside every zone: skip there
    obs = np.empty((n_epochs, 2, n_cols))
    obs[:, 0] = error_m.T
    # the bias regressor rides along: its innovations are linear in it, no extra Riccati
    obs[:, 1] = seen_by if regressor is None else regressor.T
    valid_by = np.asarray(valid, dtype=float).T
    all_valid = np.asarray(valid_by.all(axis=1))
    x = np.zeros((n_states, 2, n_cols))
    p = np.eye(n_states)[:, :, None] * var[None, :, :]
    e_all = np.empty((n_epochs, 2, n_cols))
    s_all = np.empty((n_epochs, n_cols))

    two = n_states == 3  # the usual two baseline components: plain adds beat reductions here
    for i in range(n_epochs):
        if i > 0:
            phi, phi2, q = trans(i - 1)
            p *= phi2
            p += q
            x *= phi
        pk = p[:, 0] + p[:, 1] if two else p[:, :-1].sum(axis=1)  # P h, h = (1, .., 1, m)
        if seen[i]:
            pk += p[:, -1] * seen_by[i]
        s = pk[0] + pk[1] if two else pk[:-1].sum(axis=0)
        e = obs[i] - x[0] - x[1] if two else obs[i] - x[:-1].sum(axis=0)
        if seen[i]:
            s += pk[-1] * seen_by[i]
            e -= x[-1] * seen_by[i]
        s += white_var_m2
        gain = pk / s if all_valid[i] else pk * (valid_by[i] / s)  # no update at a no-fix epoch
        x += gain[:, None, :] * e[None, :, :]
        p -= gain[:, None, :] * pk[None, :, :]
        e_all[i] = e
        s_all[i] = s
    return e_all[:, 0], e_all[:, 1], s_all


def zone_terms(
    series: PositionSeries,
    model: NoiseModel,
    effect_var: np.ndarray,
    effect_tau_s: np.ndarray,
    zone: np.ndarray,
    away: np.ndarray | None = None,
) -> ZoneTerms:
    """Likelihood terms of ``series`` under the baseline noise model plus, for each of B
    batch elements, a horizontal Gauss-Markov effect (``effect_var`` (B,) stationary variance
    m^2, 0 = none; ``effect_tau_s`` (B,) s) observed only at the epochs where ``zone`` ((n,) or
    (B, n) bool) is True, and an in-zone bias: a free vector (per-axis GLS), or with
    ``away`` ((2, n) or (B, 2, n) unit vectors east/north) the magnitude along them
    (``loglik(True, shared=True)``)."""
    batch = effect_var.size
    n_epochs = len(series)
    valid = np.asarray(series.valid, dtype=bool)
    error_m = np.stack([series.east_m, series.north_m]).astype(float) - model.mean_m[:, None]
    error_m = np.where(valid, error_m, 0.0)
    zone_cols = np.repeat(
        np.broadcast_to(np.asarray(zone, dtype=bool), (batch, n_epochs)), 2, axis=0
    )
    regressor = None
    if away is not None:
        regressor = (
            np.broadcast_to(away, (batch, 2, n_epochs)).reshape(2 * batch, n_epochs) * zone_cols
        )
    e, e1, s = _filter(
        np.asarray(series.t_s, dtype=float),
        np.tile(error_m, (batch, 1)),
        np.broadcast_to(valid, (2 * batch, n_epochs)),
        model,
        np.repeat(effect_var, 2),
        np.repeat(effect_tau_s, 2),
        zone_cols,
        regressor,
    )
    weight = valid[:, None] / s

    def per_axis(a: np.ndarray) -> np.ndarray:
        return a.reshape(batch, 2)

    return ZoneTerms(
        log_s=per_axis(np.sum(np.log(s) * valid[:, None], axis=0)),
        yy=per_axis(np.sum(e**2 * weight, axis=0)),
        y1=per_axis(np.sum(e * e1 * weight, axis=0)),
        oo=per_axis(np.sum(e1**2 * weight, axis=0)),
        nobs=np.full((batch, 2), int(np.count_nonzero(valid))),
    )


# --- locating the zone: per-place excess against the baseline runs -----------------------------


def _on_epochs(run: PositionSeries, t_s: np.ndarray) -> PositionSeries:
    """A baseline run on the real log's epochs: as is when they match, else interpolated
    (valid where the nearest run epoch is valid)."""
    run_t_s = np.asarray(run.t_s, dtype=float)
    if run_t_s.shape == t_s.shape and np.allclose(run_t_s, t_s):
        return run
    valid = np.asarray(run.valid, dtype=bool)
    near = np.clip(np.searchsorted(run_t_s, t_s), 0, run_t_s.size - 1)
    prev = np.clip(near - 1, 0, run_t_s.size - 1)
    near = np.where(np.abs(run_t_s[prev] - t_s) < np.abs(run_t_s[near] - t_s), prev, near)
    east_m, north_m = (
        np.interp(t_s, run_t_s[valid], np.asarray(a, dtype=float)[valid])
        for a in (run.east_m, run.north_m)
    )
    return run.with_(
        t_s=t_s, east_m=east_m, north_m=north_m, up_m=np.zeros(t_s.size), valid=valid[near]
    )


def _local_stats(
    series: Sequence[PositionSeries], mean_m: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per series (S, n), summed over east and north: squared steps from the previous epoch
    and squared levels about the baseline mean (m^2), and where each is defined. Both are
    memoryless on purpose: a filter's innovations would carry a zone's exit on along the
    track for as long as the filter takes to forget it, and smear the located places."""
    error_m = np.stack([np.stack([s.east_m, s.north_m]).astype(float) for s in series])
    error_m -= mean_m[None, :, None]
    valid = np.stack([np.asarray(s.valid, dtype=bool) for s in series])
    level2_m2 = np.sum(error_m**2, axis=1)
    step2_m2 = np.zeros_like(level2_m2)
    step2_m2[:, 1:] = np.sum(np.diff(error_m, axis=2) ** 2, axis=1)
    has_step = np.zeros_like(valid)
    has_step[:, 1:] = valid[:, 1:] & valid[:, :-1]  # consecutive fixes only: an outage is no step
    return step2_m2, has_step, level2_m2, valid


@dataclass(frozen=True)
class _Cells:
    """The truth track binned in square cells: ``of`` (n,) cell per epoch, ``ij`` (C, 2)."""

    of: np.ndarray
    ij: np.ndarray

    def neighbours(self, radius: int) -> np.ndarray:
        """(C, (2r+1)^2) indices of the cells within r cells (Chebyshev) of each; -1 none."""
        span = int(self.ij.max()) + 2 * radius + 2
        keys = self.ij[:, 0] * span + self.ij[:, 1]  # sorted: ij comes from np.unique
        out = []
        for di in range(-radius, radius + 1):
            for dj in range(-radius, radius + 1):
                want = keys + di * span + dj
                pos = np.clip(np.searchsorted(keys, want), 0, keys.size - 1)
                out.append(np.where(keys[pos] == want, pos, -1))
        return np.stack(out, axis=1)


def _cells(east_m: np.ndarray, north_m: np.ndarray, size_m: float) -> _Cells:
    ij = np.stack([np.floor(east_m / size_m), np.floor(north_m / size_m)], axis=1).astype(np.int64)
    ij -= ij.min(axis=0)
    distinct, cell_of = np.unique(ij, axis=0, return_inverse=True)
    return _Cells(cell_of.ravel(), distinct)


def _cell_means(
    values: np.ndarray, valid: np.ndarray, bin_of: np.ndarray, n_cells: int
) -> tuple[np.ndarray, np.ndarray]:
    """Per series and cell: mean of ``vals`` (S, n) over valid epochs, and the counts."""
    sums = np.zeros((values.shape[0], n_cells))
    counts = np.zeros((values.shape[0], n_cells))
    for i in range(values.shape[0]):
        sums[i] = np.bincount(bin_of, weights=np.where(valid[i], values[i], 0.0), minlength=n_cells)
        counts[i] = np.bincount(bin_of, weights=valid[i].astype(float), minlength=n_cells)
    return sums / np.maximum(counts, 1.0), counts


def _place_z(logs: np.ndarray, has: np.ndarray, weight: np.ndarray) -> np.ndarray:
    """z (S, C) of a per-cell log statistic, the real log in row 0 and the runs below: each
    row's difference to the mean of the OTHER runs in the same cell (the runs share the
    truth track, so this is a per-place null), less the row's median over cells (an excess
    everywhere is not a place), times sqrt(weight) (its precision: epochs or passes), in
    units of the runs' pooled spread. ``has`` False: the series never saw that cell."""
    values = np.where(has, logs, 0.0)
    runs, n_runs = values[1:], has[1:].sum(axis=0)
    total = runs.sum(axis=0)
    diff = np.empty_like(values)
    diff[0] = (values[0] - total / np.maximum(n_runs, 1)) / np.sqrt(1 + 1 / np.maximum(n_runs, 1))
    others = np.maximum(n_runs - has[1:], 1)
    diff[1:] = (runs - (total - runs) / others) / np.sqrt(1 + 1 / others)
    diff = np.where(has & (n_runs >= 2), diff, 0.0)
    diff -= np.median(diff, axis=1, keepdims=True)
    diff *= np.sqrt(weight)
    spread = float(np.sqrt(np.mean(diff[1:] ** 2)))
    return diff / max(spread, 1e-12)


def _smooth(z: np.ndarray, neighbours: np.ndarray) -> np.ndarray:
    """Sum of z over each cell's neighbourhood / sqrt(count), rescaled to unit rms over the
    runs (neighbouring level cells are correlated: one pass sees them all)."""
    exists = neighbours >= 0
    total = np.sum(np.where(exists[None], z[:, np.where(exists, neighbours, 0)], 0.0), axis=2)
    out = total / np.sqrt(exists.sum(axis=1))[None]
    return out / max(float(np.sqrt(np.mean(out[1:] ** 2))), 1e-12)


def _passes(t_s: np.ndarray, cell_of: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pass index of every epoch (a pass: a cell's epochs less than a minute apart) and the
    cell of every pass."""
    order = np.lexsort((t_s, cell_of))
    starts_pass = np.ones(order.size, dtype=bool)
    starts_pass[1:] = (cell_of[order][1:] != cell_of[order][:-1]) | (np.diff(t_s[order]) > 60.0)
    pass_of = np.empty(order.size, dtype=np.int64)
    pass_of[order] = np.cumsum(starts_pass) - 1
    return pass_of, cell_of[order][starts_pass]


@dataclass(frozen=True)
class Location:
    """Where the real log shows excess: ``in_zone`` (n,) epochs, the peak score of the real
    log and the threshold the baseline runs set (both in smoothed z units)."""

    in_zone: np.ndarray
    peak: float
    threshold: float


def locate_zone(
    real: PositionSeries, runs: Sequence[PositionSeries], mean_m: np.ndarray
) -> Location | None:
    """Locate the places where ``real`` shows excess error over ``runs`` (on the real log's
    epochs and truth track; ``mean_m`` the baseline's mean error east, north, m); None when
    the real log's peak does not beat the runs'."""
    true_east_m, true_north_m = truth_track_m(real)
    step2_m2, has_step, level2_m2, valid = _local_stats([real, *runs], mean_m)
    cells = _cells(true_east_m, true_north_m, CELL_M)
    n_cells = cells.ij.shape[0]
    step_mean, counts = _cell_means(step2_m2, has_step, cells.of, n_cells)
    z_step = _place_z(np.log(np.maximum(step_mean, 1e-12)), counts > 0, counts.mean(axis=0))
    # levels: the mean over passes of each pass's log mean square, so that one pass on a
    # large excursion of the slow drift does not make a place (a zone is there every time)
    pass_of, pass_cell = _passes(np.asarray(real.t_s, dtype=float), cells.of)
    level_pass, level_counts = _cell_means(level2_m2, valid, pass_of, pass_cell.size)
    seen = level_counts > 0
    log_sum = np.zeros((level2_m2.shape[0], n_cells))
    n_pass = np.zeros((level2_m2.shape[0], n_cells))
    for s in range(level2_m2.shape[0]):
        weight = seen[s].astype(float)
        log_sum[s] = np.bincount(
            pass_cell, np.log(np.maximum(level_pass[s], 1e-12)) * weight, n_cells
        )
        n_pass[s] = np.bincount(pass_cell, weight, n_cells)
    z_level = _place_z(log_sum / np.maximum(n_pass, 1), n_pass > 0, n_pass.mean(axis=0))
    maps = {
        r: np.maximum(_smooth(z_step, neighbours), _smooth(z_level, neighbours))
        for r in SCALES
        for neighbours in [cells.neighbours(r)]
    }
    peaks = np.max([smoothed.max(axis=1) for smoothed in maps.values()], axis=0)  # (S,)
    run_peaks = peaks[1:]
    threshold = max(float(run_peaks.max()), float(run_peaks.mean() + 3 * run_peaks.std(ddof=1)))
    if peaks[0] <= threshold:
        return None
    # the located places: connected cells above the runs' 99 % cell quantile (finest scale),
    # grown from the best fine cell in the neighbourhood of the peak
    fine = maps[SCALES[0]]
    radius_peak, map_peak = max(maps.items(), key=lambda kv: float(kv[1][0].max()))
    around = cells.neighbours(radius_peak)[int(np.argmax(map_peak[0]))]
    around = around[around >= 0]
    seed = int(around[np.argmax(fine[0, around])])
    cut = float(np.quantile(fine[1:], REGION_QUANTILE))
    above = fine[0] > cut
    adjacent = cells.neighbours(1)
    region = np.zeros(n_cells, dtype=bool)
    region[seed] = True
    frontier = [seed]
    while frontier:
        grown = adjacent[frontier].ravel()
        grown = np.unique(grown[grown >= 0])
        grown = grown[above[grown] & ~region[grown]]
        region[grown] = True
        frontier = list(grown)
    return Location(region[cells.of], float(peaks[0]), threshold)


# --- geometry: a wall whose zone covers the located places -------------------------------------


@dataclass(frozen=True)
class Wall:
    """A zone geometry in wall coordinates: the unit normal at angle ``theta_rad`` (rad from
    east, counter-clockwise) points AWAY from the wall on the zone's side, the wall line lies
    at ``offset_m`` along it, the segment runs from ``along1_m`` to ``along2_m`` along the
    wall, and the zone reaches ``distance_m`` from it."""

    theta_rad: float
    offset_m: float
    along1_m: float
    along2_m: float
    distance_m: float

    def normal(self) -> np.ndarray:
        return np.array([math.cos(self.theta_rad), math.sin(self.theta_rad)])

    def tangent(self) -> np.ndarray:
        return np.array([-math.sin(self.theta_rad), math.cos(self.theta_rad)])

    def moved(self, name: str, by: float) -> Wall:
        """The wall with one parameter changed: ``theta_rad`` (rad, turning about the
        segment's middle), ``offset_m``, ``along1_m``, ``along2_m`` or ``distance_m`` (m;
        lengths kept positive), or ``back`` (m): the wall steps back from the track and the
        zone's far edge stays, a move along which the covered track barely changes (single
        moves cannot follow it)."""
        if name == "back":
            return self.moved("offset_m", -by).moved("distance_m", by)
        if name == "theta_rad":
            mid = (
                self.offset_m * self.normal() + (self.along1_m + self.along2_m) / 2 * self.tangent()
            )
            turned = replace(self, theta_rad=self.theta_rad + by)
            half = (self.along2_m - self.along1_m) / 2
            offset_m, along_m = float(mid @ turned.normal()), float(mid @ turned.tangent())
            return replace(
                turned, offset_m=offset_m, along1_m=along_m - half, along2_m=along_m + half
            )
        out = replace(self, **{name: getattr(self, name) + by})
        if out.along2_m - out.along1_m < 1.0 or out.distance_m < 1.0:
            return self
        return out

    def effect(self, sigma_m: float, tau_s: float, bias_m: float) -> MultipathZone:
        """The simulator's layer with this wall (end points in the local frame, m)."""
        normal, tangent = self.normal(), self.tangent()
        p1, p2 = (
            self.offset_m * normal + self.along1_m * tangent,
            self.offset_m * normal + self.along2_m * tangent,
        )
        return MultipathZone(
            x1_m=round(float(p1[0]), 2), y1_m=round(float(p1[1]), 2),
            x2_m=round(float(p2[0]), 2), y2_m=round(float(p2[1]), 2),
            distance_m=round(self.distance_m, 2), sigma_m=round(sigma_m, 4),
            bias_m=round(bias_m, 4), tau_s=round(tau_s, 3),
        )  # fmt: skip

    def coords(self, east_m: np.ndarray, north_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Offset along the normal and position along the wall of points (m)."""
        normal, tangent = self.normal(), self.tangent()
        return east_m * normal[0] + north_m * normal[1], east_m * tangent[0] + north_m * tangent[1]

    def zone(self, east_m: np.ndarray, north_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """In-zone mask and the (2, n) unit vectors away from the wall at the track points,
        exactly as the simulator's layer computes them."""
        eff = self.effect(1.0, 1.0, 0.0)
        dist_m, away_east, away_north = eff.distance_to_wall_m(east_m, north_m)
        return dist_m <= eff.distance_m, np.stack([away_east, away_north])


WALL_PARAMS = ("theta_rad", "offset_m", "along1_m", "along2_m", "distance_m")


def fit_walls(
    true_east_m: np.ndarray,
    true_north_m: np.ndarray,
    in_zone: np.ndarray,
    valid: np.ndarray,
    thetas_rad: np.ndarray,
) -> list[Wall]:
    """Walls whose zones cover every valid in-zone track point and as few valid out-of-zone
    ones as possible, the normal among angles ``thetas_rad`` (rad) pointing away from the wall.

    Only the zone's intersection with the track is identifiable, and many walls cut the
    same track alike: one per distance of the wall behind the located places
    (:data:`WALL_BACK_M`), from just behind them (a zone bounded by its far edge, the bias
    the same everywhere) to well back (bounded by its round ends, the bias turning there as
    near a real wall's end). For a wall line and a distance the shortest segment covering
    every located point has a closed form; orientation and distance are searched on a grid.
    The likelihood chooses among the returned walls."""
    in_pts, out_pts = valid & in_zone, valid & ~in_zone
    cos_t, sin_t = np.cos(thetas_rad)[:, None], np.sin(thetas_rad)[:, None]
    offset_in_m, along_in_m = (
        true_east_m[in_pts] * cos_t + true_north_m[in_pts] * sin_t,
        -true_east_m[in_pts] * sin_t + true_north_m[in_pts] * cos_t,
    )  # (T, n_in)
    offset_out_m, along_out_m = (
        true_east_m[out_pts] * cos_t + true_north_m[out_pts] * sin_t,
        -true_east_m[out_pts] * sin_t + true_north_m[out_pts] * cos_t,
    )
    out = []
    for back_m in WALL_BACK_M:
        offset_m = offset_in_m.min(axis=1, keepdims=True) - WALL_GAP_M - back_m  # (T, 1)
        best: tuple[float, float, Wall] | None = None
        for extra_m in WALL_REACH_M:
            distance_m = offset_in_m.max(axis=1, keepdims=True) - offset_m + extra_m
            # a point at offset a from the wall line is within d of the segment when the
            # segment reaches within r = sqrt(d^2 - a^2) of it along the wall
            reach_m = np.sqrt(np.maximum(distance_m**2 - (offset_in_m - offset_m) ** 2, 0.0))
            along1_m, along2_m = (
                (along_in_m + reach_m).min(axis=1, keepdims=True),
                (along_in_m - reach_m).max(axis=1, keepdims=True),
            )
            middle_m = (along1_m + along2_m) / 2  # a disc when no segment covers them all: 1 m wall
            along1_m, along2_m = (
                np.minimum(along1_m, middle_m - 0.5),
                np.maximum(along2_m, middle_m + 0.5),
            )
            beyond_m = np.maximum(0.0, np.maximum(along1_m - along_out_m, along_out_m - along2_m))
            false_pos = np.count_nonzero(
                np.hypot(offset_out_m - offset_m, beyond_m) <= distance_m, axis=1
            )
            area_m2 = (distance_m * (along2_m - along1_m + 2 * distance_m)).ravel()
            j = int(np.lexsort((area_m2, false_pos))[0])
            key = (float(false_pos[j]), float(area_m2[j]))
            if best is None or key < best[:2]:
                wall = Wall(
                    float(thetas_rad[j]),
                    *(float(v[j, 0]) for v in (offset_m, along1_m, along2_m, distance_m)),
                )
                best = (*key, wall)
        assert best is not None
        out.append(best[2])
    return out


THETA_STEPS = np.radians([-4.0, -2.0, -1.0, 1.0, 2.0, 4.0])
LENGTH_STEPS_M = np.array([-4.0, -2.0, -1.0, 1.0, 2.0, 4.0])


def _pattern_search(
    wall: Wall, cost: Callable[[Sequence[Wall]], np.ndarray], passes: int
) -> tuple[Wall, list[tuple[str, float]], np.ndarray]:
    """Minimise ``cost`` over walls: each pass tries every parameter moved by a few steps,
    plus the previous pass's best step of every parameter at once, and keeps the best wall,
    until nothing helps. Returns the wall, the single moves of the last pass and their costs
    (first entry: the wall itself)."""
    names = (*WALL_PARAMS, "back")
    moves = [("", 0.0)] + [
        (name, float(by))
        for name in names
        for by in (THETA_STEPS if name == "theta_rad" else LENGTH_STEPS_M)
    ]
    costs = np.zeros(len(moves))
    combined: Wall | None = None
    for _ in range(passes):
        walls = [wall.moved(name, by) if name else wall for name, by in moves]
        every = cost([*walls, *([combined] if combined else [])])
        costs = every[: len(moves)]
        j = int(np.argmin(every))
        if every[j] >= costs[0] - 1e-6:
            break
        # the next pass also tries the best improving step of every parameter together
        combined = walls[j] if j < len(moves) else combined
        assert combined is not None
        new = combined
        for name in names:
            sel = [i for i, m in enumerate(moves) if m[0] == name]
            i = sel[int(np.argmin(costs[sel]))]
            if costs[i] < costs[0] - 1e-6 and i != j:
                new = new.moved(*moves[i])
        wall, combined = combined, (new if new != combined else None)
    return wall, moves, costs


# --- parameters by exact likelihood ------------------------------------------------------------


def _loglik(
    real: PositionSeries,
    model: NoiseModel,
    zones: Sequence[tuple[np.ndarray, np.ndarray | None]],
    log_sigma: np.ndarray,
    log_tau: np.ndarray,
) -> tuple[np.ndarray, ZoneTerms]:
    """Bias-profiled log-likelihood (G, P) for every zone (G masks (n,), each with its away
    vectors (2, n) for a bias along them, or None for a free in-zone bias vector) x
    parameter pair (P,). The G zones must all have away vectors or none. A bias along the
    away vectors is held >= 0 (reflected paths are longer: the layer's bias points away
    from the wall), so a wall on the wrong side of the bias gains nothing from it."""
    n_zones, n_params = len(zones), log_sigma.size
    masks = np.stack([m for m, _a in zones])
    shared = zones[0][1] is not None
    away = np.stack([a for _m, a in zones]) if shared else None  # type: ignore[misc]
    terms = zone_terms(
        real,
        model,
        np.tile(np.exp(2 * log_sigma), n_zones),
        np.tile(np.exp(log_tau), n_zones),
        np.repeat(masks, n_params, axis=0),
        None if away is None else np.repeat(away, n_params, axis=0),
    )
    loglik = terms.loglik(True, shared)
    if shared:
        loglik = np.where(terms.bias(shared=True)[0] >= 0, loglik, terms.loglik(False))
    return loglik.reshape(n_zones, n_params), terms


@dataclass(frozen=True)
class _Params:
    """(log sigma, log tau) at the maximum, their covariance (NaN when the surface is not
    concave), the maximum log-likelihood and the GLS bias there (per axis, or the magnitude
    along the away vectors) with its standard error."""

    centre: np.ndarray
    cov: np.ndarray
    loglik: float
    bias: np.ndarray
    bias_se: np.ndarray
    starts: list[tuple[np.ndarray, np.ndarray]]  # where each zoom ended: centre, half-width


@dataclass
class _Zoom:
    """One zoom of :func:`_fit_sigma_tau`: its centre and half_width-widths (log sigma, log tau),
    halvings so far, and its last grid (points, log-likelihoods, GLS bias and errors)."""

    centre: np.ndarray
    half_width: np.ndarray
    halvings: int = 0
    points: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    loglik: np.ndarray = field(default_factory=lambda: np.zeros(0))
    bias: tuple[np.ndarray, np.ndarray] = (np.zeros(0), np.zeros(0))


def _fit_sigma_tau(
    real: PositionSeries,
    model: NoiseModel,
    zone: tuple[np.ndarray, np.ndarray | None],
    layout: Layout,
    zooms: int = 6,
    starts: Sequence[tuple[np.ndarray, np.ndarray]] = (),
) -> _Params:
    """Maximise the likelihood over (log sigma, log tau) for one zone: a coarse 10 x 10 grid
    (or the given ``starts``: centres and half-widths, from an earlier fit), then 5 x 5 zooms
    around each of its best STARTS local maxima at once (the surface can have a second mode:
    a large, slow noise that lets every pass's level float), each halving when its maximum
    is inside it and moving otherwise (as :func:`x6wd.gap.drift.drift_fit`); covariance from a
    quadratic through the winner's last grid. A filter batch of ~100 costs little more than
    one, so the starts are zoomed together."""
    dt_s = layout.dt_s
    log_tau_min, log_tau_max = (
        math.log(0.5 * dt_s),
        math.log(10 * max(layout.duration_s, 10 * dt_s)),
    )
    shared = zone[1] is not None
    if not starts:
        log_sigma_axis = np.linspace(math.log(0.03), math.log(20.0), 10)
        log_tau_axis = np.linspace(math.log(dt_s), log_tau_max, 10)
        grid_log_sigma, grid_log_tau = (
            a.ravel() for a in np.meshgrid(log_sigma_axis, log_tau_axis, indexing="ij")
        )
        loglik, terms = _loglik(real, model, [zone], grid_log_sigma, grid_log_tau)
        n_sigma, n_tau = log_sigma_axis.size, log_tau_axis.size
        grid = loglik[0].reshape(n_sigma, n_tau)
        pad = np.pad(grid, 1, constant_values=-np.inf)
        peak = np.ones(grid.shape, dtype=bool)  # local maxima of the grid
        for di in (-1, 0, 1):
            for dj in (-1, 0, 1):
                if di or dj:
                    peak &= grid >= pad[1 + di : 1 + di + n_sigma, 1 + dj : 1 + dj + n_tau]
        order = [int(i) for i in np.argsort(-loglik[0]) if peak.ravel()[i]][:STARTS]
        step = np.array([log_sigma_axis[1] - log_sigma_axis[0], log_tau_axis[1] - log_tau_axis[0]])
        starts = [(np.array([grid_log_sigma[i], grid_log_tau[i]]), step) for i in order]
        if zooms == 0:
            bias, bias_se = terms.bias(shared)
            j = order[0]
            return _Params(
                starts[0][0],
                np.full((2, 2), np.nan),
                float(loglik[0, j]),
                bias[j],
                bias_se[j],
                starts,
            )
    zoom_runs = [_Zoom(c.copy(), h.copy()) for c, h in starts]
    unit = np.linspace(-1.0, 1.0, 5)
    unit_sigma, unit_tau = (a.ravel() for a in np.meshgrid(unit, unit))
    for _ in range(max(zooms, 1)):
        live = [z for z in zoom_runs if z.halvings < 3]
        if not live:
            break
        log_sigma = np.concatenate([z.centre[0] + unit_sigma * z.half_width[0] for z in live])
        log_tau = np.concatenate(
            [
                np.clip(z.centre[1] + unit_tau * z.half_width[1], log_tau_min, log_tau_max)
                for z in live
            ]
        )
        loglik, terms = _loglik(real, model, [zone], log_sigma, log_tau)
        bias_all, bias_se_all = terms.bias(shared)
        for i, z in enumerate(live):
            part = slice(i * unit_sigma.size, (i + 1) * unit_sigma.size)
            z.points, z.loglik, z.bias = (
                np.stack([log_sigma[part], log_tau[part]], 1),
                loglik[0][part],
                (bias_all[part], bias_se_all[part]),
            )
            j = int(np.argmax(z.loglik))
            z.centre = z.points[j]
            at_bound = not log_tau_min + 1e-9 < z.points[j, 1] < log_tau_max - 1e-9
            if abs(unit_sigma[j]) < 1 and (abs(unit_tau[j]) < 1 or at_bound):
                z.half_width = z.half_width / 2
                z.halvings += 1
    winner = max(zoom_runs, key=lambda z: float(z.loglik.max()))
    j = int(np.argmax(winner.loglik))
    cov = np.full((2, 2), np.nan)
    best = winner.centre
    quadratic = quadratic_peak(winner.points, winner.loglik)
    if quadratic is not None:
        vertex, cov = quadratic
        if np.all(np.abs(vertex - winner.points.mean(axis=0)) <= np.ptp(winner.points, axis=0) / 2):
            best = vertex
    return _Params(
        best, cov, float(winner.loglik[j]), winner.bias[0][j], winner.bias[1][j],
        [(z.centre, z.half_width) for z in zoom_runs],
    )  # fmt: skip


def _refine_wall(
    real: PositionSeries,
    model: NoiseModel,
    wall: Wall,
    params: _Params,
    true_east_m: np.ndarray,
    true_north_m: np.ndarray,
    passes: int = 4,
) -> tuple[Wall, dict[str, float]]:
    """Pattern search on the exact likelihood (sigma, tau held, the bias magnitude profiled
    along the wall's away vectors; one batched filter per pass). Returns the wall and each
    parameter's standard error from the curvature of the log-likelihood along it, the others
    held (NaN when flat: the track does not feel that parameter)."""
    log_sigma, log_tau = params.centre[:1], params.centre[1:]

    def cost(walls: Sequence[Wall]) -> np.ndarray:
        zones = [w.zone(true_east_m, true_north_m) for w in walls]
        # a wall with track inside its zone behind it would turn their bias round
        behind = [
            np.count_nonzero(z[0] & (w.coords(true_east_m, true_north_m)[0] < w.offset_m))
            for w, z in zip(walls, zones, strict=True)
        ]
        return -_loglik(real, model, zones, log_sigma, log_tau)[0][:, 0] + BEHIND_COST * np.array(
            behind
        )

    wall, moves, costs = _pattern_search(wall, cost, passes)
    se: dict[str, float] = {}
    for name in WALL_PARAMS:
        moves_of = [0] + [i for i, m in enumerate(moves) if m[0] == name]
        steps = np.array([moves[i][1] for i in moves_of])
        curvature = 2 * float(np.polyfit(steps, costs[moves_of], 2)[0])  # -d2 loglik / dx2
        se[name] = 1 / math.sqrt(curvature) if curvature > 0 else math.nan
    return wall, se


BOUNDARY_SHIFTS = np.concatenate([[-32, -24, -16, -12], np.arange(-8, 9), [12, 16, 24, 32]])


def _refine_boundaries(
    real: PositionSeries, model: NoiseModel, in_zone: np.ndarray, params: _Params
) -> np.ndarray:
    """Move each entry into and exit out of the located zone to its most likely epoch.

    One batched filter: every boundary shifted by the same number of epochs (sigma, tau and
    the in-zone bias vector held at ``params``); each boundary then takes the shift whose
    per-epoch log-likelihood is highest in a window around it. Passes are minutes apart,
    longer than the filter's memory of a boundary, so the windows barely interact. A bias
    makes this sharp: a misplaced boundary leaves a step of the bias's size unexplained."""
    n_epochs = in_zone.size
    edge = np.diff(np.concatenate(([0], in_zone.astype(int), [0])))
    starts, ends = np.flatnonzero(edge == 1), np.flatnonzero(edge == -1)
    masks = np.zeros((BOUNDARY_SHIFTS.size, n_epochs), dtype=bool)
    for i, shift in enumerate(BOUNDARY_SHIFTS):
        for run_start, run_end in zip(starts, ends, strict=True):
            masks[i, max(run_start + shift, 0) : min(run_end + shift, n_epochs)] = True
    valid = np.asarray(real.valid, dtype=bool)
    error_m = np.stack([real.east_m, real.north_m]).astype(float) - model.mean_m[:, None]
    n_shifts = masks.shape[0]
    zone_cols = np.repeat(masks, 2, axis=0)
    e, e1, s = _filter(
        np.asarray(real.t_s, dtype=float),
        np.tile(np.where(valid, error_m, 0.0), (n_shifts, 1)),
        np.broadcast_to(valid, (2 * n_shifts, n_epochs)),
        model,
        np.full(2 * n_shifts, math.exp(2 * params.centre[0])),
        np.full(2 * n_shifts, math.exp(params.centre[1])),
        zone_cols,
    )
    resid = e - np.tile(params.bias, n_shifts)[None] * e1
    loglik = -0.5 * (np.log(s) + resid**2 / s) * valid[:, None]
    loglik = loglik.reshape(n_epochs, n_shifts, 2).sum(axis=2).T  # (shift, epoch)
    cum_loglik = np.concatenate([np.zeros((n_shifts, 1)), np.cumsum(loglik, axis=1)], axis=1)

    def best_shift(lo: int, hi: int) -> int:
        lo, hi = max(lo, 0), min(hi, n_epochs)
        return int(BOUNDARY_SHIFTS[int(np.argmax(cum_loglik[:, hi] - cum_loglik[:, lo]))])

    out = np.zeros(n_epochs, dtype=bool)
    span = int(BOUNDARY_SHIFTS.max())
    for entry, exit_ in zip(starts.tolist(), ends.tolist(), strict=True):
        reach = min(2 * span, max((exit_ - entry) // 2, 1))  # windows stay in their half
        new_entry = entry + best_shift(entry - 2 * span, entry + reach)
        new_exit = exit_ + best_shift(exit_ - reach, exit_ + 2 * span)
        out[max(new_entry, 0) : min(max(new_exit, new_entry + 1), n_epochs)] = True
    return out


def _prune_runs(
    real: PositionSeries, model: NoiseModel, in_zone: np.ndarray, params: _Params
) -> np.ndarray:
    """Drop every run of located epochs whose removal costs the likelihood less than BIC's
    price of its two boundaries (one batched filter: each run left out in turn, sigma, tau
    held, in-zone bias vector profiled): a patch of noise that grew onto the located
    places in the place map."""
    edge = np.diff(np.concatenate(([0], in_zone.astype(int), [0])))
    starts, ends = np.flatnonzero(edge == 1), np.flatnonzero(edge == -1)
    masks = np.repeat(in_zone[None], starts.size + 1, axis=0)
    for i, (entry, exit_) in enumerate(zip(starts, ends, strict=True)):
        masks[i + 1, entry:exit_] = False
    loglik = _loglik(real, model, [(m, None) for m in masks], params.centre[:1], params.centre[1:])[
        0
    ]
    nobs = 2 * int(np.count_nonzero(real.valid))
    keep = loglik[0, 0] - loglik[1:, 0] > math.log(nobs)  # two boundary epochs: BIC 2 x log(n) / 2
    out = np.zeros_like(in_zone)
    for entry, exit_, i in zip(starts, ends, keep, strict=True):
        out[entry:exit_] = i
    return out


# --- the fitter --------------------------------------------------------------------------------


@dataclass(frozen=True)
class ZoneFit:
    """A fitted zone: the layer and its standard errors (keys of its parameters), the epochs
    its zone covers, the in-zone bias vector (east, north, m) fitted freely on them with its
    covariance (m^2), the log-likelihood gain over "no zone" and the BIC penalty it beat, and
    the location it started from."""

    effect: MultipathZone
    se: dict[str, float]
    in_zone: np.ndarray
    bias_en_m: np.ndarray
    bias_cov: np.ndarray
    loglik_gain: float
    penalty: float
    location: Location


def fit_zone(
    real: PositionSeries, baseline: Sequence[PositionSeries], layout: Layout
) -> ZoneFit | None:
    """Fit a multipath zone to ``real`` (errors, m) on top of the ``baseline`` runs (same
    truth track and epochs): see the module docstring. None for a static log, when no
    place shows excess error beyond the runs' own, or when the zone does not beat BIC."""
    if not layout.moving or len(real) < 60 or len(baseline) < 3:
        return None
    t_s = np.asarray(real.t_s, dtype=float)
    valid = np.asarray(real.valid, dtype=bool)
    model = noise_model(baseline, layout)
    location = locate_zone(real, [_on_epochs(s, t_s) for s in baseline], model.mean_m)
    if location is None or np.mean(location.in_zone[valid]) > MAX_SHARE:
        return None
    true_east_m, true_north_m = truth_track_m(real)
    # entries and exits to the epoch, twice: the first parameters come from the coarse
    # located places, whose blurred edges understate a bias
    first = _fit_sigma_tau(real, model, (location.in_zone, None), layout, zooms=0)
    located = _refine_boundaries(real, model, location.in_zone, first)
    first = _fit_sigma_tau(real, model, (located, None), layout, zooms=2, starts=first.starts)
    located = _prune_runs(real, model, _refine_boundaries(real, model, located, first), first)
    if not np.any(located[valid]):
        return None
    # the wall goes on the side opposite the bias: its normal within two standard errors of
    # the bias direction, or anywhere on that side when the bias is not significant
    bias_m, bias_se_m = first.bias, first.bias_se
    bias_size_m = float(np.hypot(*bias_m))
    bias_rad = math.atan2(bias_m[1], bias_m[0])
    spread_rad = math.pi / 2
    bias_size_se_m = float(np.hypot(*(bias_m * bias_se_m))) / max(bias_size_m, 1e-12)
    if bias_size_m > 2 * bias_size_se_m:
        spread_rad = min(2 * float(np.hypot(*bias_se_m)) / bias_size_m, math.pi / 4)
    thetas_rad = bias_rad + np.linspace(
        -spread_rad, spread_rad, max(9, int(spread_rad / math.radians(5)) + 1)
    )
    walls = fit_walls(true_east_m, true_north_m, located, valid, thetas_rad)
    start_loglik = _loglik(
        real,
        model,
        [w.zone(true_east_m, true_north_m) for w in walls],
        first.centre[:1],
        first.centre[1:],
    )[0]
    wall, geo_se = _refine_wall(
        real, model, walls[int(np.argmax(start_loglik[:, 0]))], first, true_east_m, true_north_m
    )
    in_zone, away = wall.zone(true_east_m, true_north_m)
    if not np.any(in_zone[valid]) or np.mean(in_zone[valid]) > MAX_SHARE:
        return None
    params = _fit_sigma_tau(real, model, (in_zone, away), layout, zooms=4)  # a fresh coarse grid
    sigma_m, tau_s = (math.exp(v) for v in params.centre)
    # at the fitted sigma, tau: "no zone", the bias along the away vectors, and the in-zone
    # bias as a free vector (for its direction)
    var_m2, taus_s = np.array([0.0, sigma_m**2]), np.array([1.0, tau_s])
    along = zone_terms(real, model, var_m2, taus_s, in_zone, away)
    free = zone_terms(real, model, var_m2[1:], taus_s[1:], in_zone)
    bias_away_m, bias_away_se_m = (float(a[1]) for a in along.bias(shared=True))
    bias_away_m = max(bias_away_m, 0.0)  # held >= 0 as in the search (see _loglik)
    loglik_gain = float(along.loglik(bias_away_m > 0, shared=True)[1] - along.loglik(False)[0])
    penalty = 0.5 * ZONE_PARAMS * math.log(2 * int(np.count_nonzero(valid)))
    if loglik_gain < penalty:
        return None
    free_bias_m, free_bias_se_m = (a[0] for a in free.bias())
    # end points: P1,2 = c n + s1,2 t, turning about the middle (dP/dtheta = -/+ L/2 n). A
    # boundary between two fixes is known to a step of travel at best (uniform: step/sqrt 12)
    step_m = float(np.median(np.hypot(np.diff(true_east_m), np.diff(true_north_m)))) / math.sqrt(12)
    normal, tangent = wall.normal(), wall.tangent()
    half_length_m = (wall.along2_m - wall.along1_m) / 2
    se = {"distance_m": max(geo_se["distance_m"], step_m)}
    for i, s_name in ((1, "along1_m"), (2, "along2_m")):
        for a, axis in enumerate("xy"):
            se[f"{axis}{i}_m"] = math.hypot(
                normal[a] * max(geo_se["offset_m"], step_m),
                tangent[a] * max(geo_se[s_name], step_m),
                half_length_m * normal[a] * geo_se["theta_rad"],
            )
    se |= {
        "sigma_m": sigma_m * math.sqrt(max(params.cov[0, 0], 0.0)),
        "tau_s": tau_s * math.sqrt(max(params.cov[1, 1], 0.0)),
        "bias_m": bias_away_se_m,
    }
    return ZoneFit(
        wall.effect(sigma_m, tau_s, bias_away_m), se, in_zone, free_bias_m,
        np.diag(free_bias_se_m**2), loglik_gain, penalty, location,
    )  # fmt: skip


def fit_multipath_zone(
    real: PositionSeries, baseline: Sequence[PositionSeries], layout: Layout
) -> Fit | None:
    """``multipath_zone`` fitted to a moving log (see :func:`fit_zone`): wall end points and
    distance (m) of the tightest zone over the located places, Gauss-Markov sigma_m (m) and
    tau_s (s), bias_m (m, away from the wall). None for static logs: a static receiver inside
    a zone is indistinguishable from gauss_markov + bias."""
    zone = fit_zone(real, baseline, layout)
    return None if zone is None else Fit(zone.effect, zone.se)
