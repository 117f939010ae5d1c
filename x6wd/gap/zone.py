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
    y: np.ndarray,
    valid: np.ndarray,
    model: NoiseModel,
    eff_var: np.ndarray,
    eff_tau: np.ndarray,
    zone: np.ndarray | None,
    reg: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Kalman filter of baseline model + a Gauss-Markov effect seen only where ``zone``.

    Columns j = (batch j // 2, axis j % 2): ``y`` (C, n) data minus the baseline mean,
    ``valid`` (C, n), ``eff_var``/``eff_tau`` (C,), ``zone`` (C, n) or None (always seen),
    ``reg`` (C, n) a bias regressor (default: ``zone``). Returns the innovations of the data
    and of the regressor, and their variance, each (n, C). Every component is propagated
    with the actual step, so outages and irregular sampling are exact."""
    c, n = y.shape
    k = model.tau_s.shape[1] + 1
    var, tau = component_law(model, eff_var, eff_tau)
    w2 = np.tile(model.white_m**2, c // 2)
    trans = transitions(var, tau, np.diff(t_s))
    m_all = np.ones((n, c)) if zone is None else np.asarray(zone, dtype=float).T
    seen = np.asarray(m_all.any(axis=1))  # most epochs are outside every zone: skip there
    obs = np.empty((n, 2, c))
    obs[:, 0] = y.T
    # the bias regressor rides along: its innovations are linear in it, no extra Riccati
    obs[:, 1] = m_all if reg is None else reg.T
    v_all = np.asarray(valid, dtype=float).T
    full = np.asarray(v_all.all(axis=1))
    x = np.zeros((k, 2, c))
    p = np.eye(k)[:, :, None] * var[None, :, :]
    e_all = np.empty((n, 2, c))
    s_all = np.empty((n, c))

    two = k == 3  # the usual two baseline components: plain adds beat reductions here
    for i in range(n):
        if i > 0:
            phi, pp, dq = trans(i - 1)
            p *= pp
            p += dq
            x *= phi
        pk = p[:, 0] + p[:, 1] if two else p[:, :-1].sum(axis=1)  # P h, h = (1, .., 1, m)
        if seen[i]:
            pk += p[:, -1] * m_all[i]
        s = pk[0] + pk[1] if two else pk[:-1].sum(axis=0)
        e = obs[i] - x[0] - x[1] if two else obs[i] - x[:-1].sum(axis=0)
        if seen[i]:
            s += pk[-1] * m_all[i]
            e -= x[-1] * m_all[i]
        s += w2
        gain = pk / s if full[i] else pk * (v_all[i] / s)  # no update at a no-fix epoch
        x += gain[:, None, :] * e[None, :, :]
        p -= gain[:, None, :] * pk[None, :, :]
        e_all[i] = e
        s_all[i] = s
    return e_all[:, 0], e_all[:, 1], s_all


def zone_terms(
    series: PositionSeries,
    model: NoiseModel,
    eff_var: np.ndarray,
    eff_tau: np.ndarray,
    zone: np.ndarray,
    away: np.ndarray | None = None,
) -> ZoneTerms:
    """Likelihood terms of ``series`` under the baseline noise model plus, for each of B
    batch elements, a horizontal Gauss-Markov effect (``eff_var`` (B,) stationary variance
    m^2, 0 = none; ``eff_tau`` (B,) s) observed only at the epochs where ``zone`` ((n,) or
    (B, n) bool) is True, and an in-zone bias: a free vector (per-axis GLS), or with
    ``away`` ((2, n) or (B, 2, n) unit vectors east/north) the magnitude along them
    (``loglik(True, shared=True)``)."""
    b = eff_var.size
    n = len(series)
    v = np.asarray(series.valid, dtype=bool)
    y = np.stack([series.east_m, series.north_m]).astype(float) - model.mean_m[:, None]
    y = np.where(v, y, 0.0)
    zb = np.repeat(np.broadcast_to(np.asarray(zone, dtype=bool), (b, n)), 2, axis=0)
    reg = None
    if away is not None:
        reg = np.broadcast_to(away, (b, 2, n)).reshape(2 * b, n) * zb
    e, e1, s = _filter(
        np.asarray(series.t_s, dtype=float),
        np.tile(y, (b, 1)),
        np.broadcast_to(v, (2 * b, n)),
        model,
        np.repeat(eff_var, 2),
        np.repeat(eff_tau, 2),
        zb,
        reg,
    )
    inv_s = v[:, None] / s

    def per_axis(a: np.ndarray) -> np.ndarray:
        return a.reshape(b, 2)

    return ZoneTerms(
        log_s=per_axis(np.sum(np.log(s) * v[:, None], axis=0)),
        yy=per_axis(np.sum(e**2 * inv_s, axis=0)),
        y1=per_axis(np.sum(e * e1 * inv_s, axis=0)),
        oo=per_axis(np.sum(e1**2 * inv_s, axis=0)),
        nobs=np.full((b, 2), int(np.count_nonzero(v))),
    )


# --- locating the zone: per-place excess against the baseline runs -----------------------------


def _on_epochs(run: PositionSeries, t_s: np.ndarray) -> PositionSeries:
    """A baseline run on the real log's epochs: as is when they match, else interpolated
    (valid where the nearest run epoch is valid)."""
    rt = np.asarray(run.t_s, dtype=float)
    if rt.shape == t_s.shape and np.allclose(rt, t_s):
        return run
    v = np.asarray(run.valid, dtype=bool)
    near = np.clip(np.searchsorted(rt, t_s), 0, rt.size - 1)
    prev = np.clip(near - 1, 0, rt.size - 1)
    near = np.where(np.abs(rt[prev] - t_s) < np.abs(rt[near] - t_s), prev, near)
    e, n = (np.interp(t_s, rt[v], np.asarray(a, dtype=float)[v]) for a in (run.east_m, run.north_m))
    return run.with_(t_s=t_s, east_m=e, north_m=n, up_m=np.zeros(t_s.size), valid=v[near])


def _local_stats(
    series: Sequence[PositionSeries], mean_m: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per series (S, n), summed over east and north: squared steps from the previous epoch
    and squared levels about the baseline mean (m^2), and where each is defined. Both are
    memoryless on purpose: a filter's innovations would carry a zone's exit on along the
    track for as long as the filter takes to forget it, and smear the located places."""
    y = np.stack([np.stack([s.east_m, s.north_m]).astype(float) for s in series])
    y -= mean_m[None, :, None]
    v = np.stack([np.asarray(s.valid, dtype=bool) for s in series])
    lev2 = np.sum(y**2, axis=1)
    step2 = np.zeros_like(lev2)
    step2[:, 1:] = np.sum(np.diff(y, axis=2) ** 2, axis=1)
    has_step = np.zeros_like(v)
    has_step[:, 1:] = v[:, 1:] & v[:, :-1]  # consecutive fixes only: an outage is no step
    return step2, has_step, lev2, v


@dataclass(frozen=True)
class _Cells:
    """The truth track binned in square cells: ``of`` (n,) cell per epoch, ``ij`` (C, 2)."""

    of: np.ndarray
    ij: np.ndarray

    def neighbours(self, r: int) -> np.ndarray:
        """(C, (2r+1)^2) indices of the cells within r cells (Chebyshev) of each; -1 none."""
        span = int(self.ij.max()) + 2 * r + 2
        keys = self.ij[:, 0] * span + self.ij[:, 1]  # sorted: ij comes from np.unique
        out = []
        for di in range(-r, r + 1):
            for dj in range(-r, r + 1):
                want = keys + di * span + dj
                pos = np.clip(np.searchsorted(keys, want), 0, keys.size - 1)
                out.append(np.where(keys[pos] == want, pos, -1))
        return np.stack(out, axis=1)


def _cells(te: np.ndarray, tn: np.ndarray, size_m: float) -> _Cells:
    ij = np.stack([np.floor(te / size_m), np.floor(tn / size_m)], axis=1).astype(np.int64)
    ij -= ij.min(axis=0)
    uniq, of = np.unique(ij, axis=0, return_inverse=True)
    return _Cells(of.ravel(), uniq)


def _cell_means(
    vals: np.ndarray, valid: np.ndarray, of: np.ndarray, n_cells: int
) -> tuple[np.ndarray, np.ndarray]:
    """Per series and cell: mean of ``vals`` (S, n) over valid epochs, and the counts."""
    sums = np.zeros((vals.shape[0], n_cells))
    cnt = np.zeros((vals.shape[0], n_cells))
    for s in range(vals.shape[0]):
        sums[s] = np.bincount(of, weights=np.where(valid[s], vals[s], 0.0), minlength=n_cells)
        cnt[s] = np.bincount(of, weights=valid[s].astype(float), minlength=n_cells)
    return sums / np.maximum(cnt, 1.0), cnt


def _place_z(logs: np.ndarray, has: np.ndarray, weight: np.ndarray) -> np.ndarray:
    """z (S, C) of a per-cell log statistic, the real log in row 0 and the runs below: each
    row's difference to the mean of the OTHER runs in the same cell (the runs share the
    truth track, so this is a per-place null), less the row's median over cells (an excess
    everywhere is not a place), times sqrt(weight) (its precision: epochs or passes), in
    units of the runs' pooled spread. ``has`` False: the series never saw that cell."""
    la = np.where(has, logs, 0.0)
    runs, n_runs = la[1:], has[1:].sum(axis=0)
    tot = runs.sum(axis=0)
    d = np.empty_like(la)
    d[0] = (la[0] - tot / np.maximum(n_runs, 1)) / np.sqrt(1 + 1 / np.maximum(n_runs, 1))
    others = np.maximum(n_runs - has[1:], 1)
    d[1:] = (runs - (tot - runs) / others) / np.sqrt(1 + 1 / others)
    d = np.where(has & (n_runs >= 2), d, 0.0)
    d -= np.median(d, axis=1, keepdims=True)
    d *= np.sqrt(weight)
    sd = float(np.sqrt(np.mean(d[1:] ** 2)))
    return d / max(sd, 1e-12)


def _smooth(z: np.ndarray, nbrs: np.ndarray) -> np.ndarray:
    """Sum of z over each cell's neighbourhood / sqrt(count), rescaled to unit rms over the
    runs (neighbouring level cells are correlated: one pass sees them all)."""
    has = nbrs >= 0
    tot = np.sum(np.where(has[None], z[:, np.where(has, nbrs, 0)], 0.0), axis=2)
    out = tot / np.sqrt(has.sum(axis=1))[None]
    return out / max(float(np.sqrt(np.mean(out[1:] ** 2))), 1e-12)


def _passes(t_s: np.ndarray, of: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pass index of every epoch (a pass: a cell's epochs less than a minute apart) and the
    cell of every pass."""
    order = np.lexsort((t_s, of))
    new = np.ones(order.size, dtype=bool)
    new[1:] = (of[order][1:] != of[order][:-1]) | (np.diff(t_s[order]) > 60.0)
    pid = np.empty(order.size, dtype=np.int64)
    pid[order] = np.cumsum(new) - 1
    return pid, of[order][new]


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
    te, tn = truth_track_m(real)
    step2, has_step, lev2, valid = _local_stats([real, *runs], mean_m)
    cells = _cells(te, tn, CELL_M)
    nc = cells.ij.shape[0]
    step_mean, cnt = _cell_means(step2, has_step, cells.of, nc)
    z_step = _place_z(np.log(np.maximum(step_mean, 1e-12)), cnt > 0, cnt.mean(axis=0))
    # levels: the mean over passes of each pass's log mean square, so that one pass on a
    # large excursion of the slow drift does not make a place (a zone is there every time)
    pid, pass_cell = _passes(np.asarray(real.t_s, dtype=float), cells.of)
    lev_pass, lev_cnt = _cell_means(lev2, valid, pid, pass_cell.size)
    seen = lev_cnt > 0
    log_sum = np.zeros((lev2.shape[0], nc))
    n_pass = np.zeros((lev2.shape[0], nc))
    for s in range(lev2.shape[0]):
        w = seen[s].astype(float)
        log_sum[s] = np.bincount(pass_cell, np.log(np.maximum(lev_pass[s], 1e-12)) * w, nc)
        n_pass[s] = np.bincount(pass_cell, w, nc)
    z_lev = _place_z(log_sum / np.maximum(n_pass, 1), n_pass > 0, n_pass.mean(axis=0))
    maps = {
        r: np.maximum(_smooth(z_step, nb), _smooth(z_lev, nb))
        for r in SCALES
        for nb in [cells.neighbours(r)]
    }
    peaks = np.max([m.max(axis=1) for m in maps.values()], axis=0)  # (S,)
    null = peaks[1:]
    threshold = max(float(null.max()), float(null.mean() + 3 * null.std(ddof=1)))
    if peaks[0] <= threshold:
        return None
    # the located places: connected cells above the runs' 99 % cell quantile (finest scale),
    # grown from the best fine cell in the neighbourhood of the peak
    fine = maps[SCALES[0]]
    r_pk, m_pk = max(maps.items(), key=lambda kv: float(kv[1][0].max()))
    around = cells.neighbours(r_pk)[int(np.argmax(m_pk[0]))]
    around = around[around >= 0]
    seed = int(around[np.argmax(fine[0, around])])
    cut = float(np.quantile(fine[1:], REGION_QUANTILE))
    ok = fine[0] > cut
    adj = cells.neighbours(1)
    region = np.zeros(nc, dtype=bool)
    region[seed] = True
    frontier = [seed]
    while frontier:
        nxt = adj[frontier].ravel()
        nxt = np.unique(nxt[nxt >= 0])
        nxt = nxt[ok[nxt] & ~region[nxt]]
        region[nxt] = True
        frontier = list(nxt)
    return Location(region[cells.of], float(peaks[0]), threshold)


# --- geometry: a wall whose zone covers the located places -------------------------------------


@dataclass(frozen=True)
class Wall:
    """A zone geometry in wall coordinates: the unit normal at angle ``theta`` (rad from
    east, counter-clockwise) points AWAY from the wall on the zone's side, the wall line lies
    at offset ``c_m`` along it, the segment runs from ``s1_m`` to ``s2_m`` along the wall,
    and the zone reaches ``d_m`` from it."""

    theta: float
    c_m: float
    s1_m: float
    s2_m: float
    d_m: float

    def normal(self) -> np.ndarray:
        return np.array([math.cos(self.theta), math.sin(self.theta)])

    def tangent(self) -> np.ndarray:
        return np.array([-math.sin(self.theta), math.cos(self.theta)])

    def moved(self, name: str, by: float) -> Wall:
        """The wall with one parameter changed: ``theta`` (rad, turning about the segment's
        middle), ``c_m``, ``s1_m``, ``s2_m`` or ``d_m`` (m; lengths kept positive), or
        ``back`` (m): the wall steps back from the track and the zone's far edge stays, a
        move along which the covered track barely changes (single moves cannot follow it)."""
        if name == "back":
            return self.moved("c_m", -by).moved("d_m", by)
        if name == "theta":
            mid = self.c_m * self.normal() + (self.s1_m + self.s2_m) / 2 * self.tangent()
            turned = replace(self, theta=self.theta + by)
            half = (self.s2_m - self.s1_m) / 2
            c, s = float(mid @ turned.normal()), float(mid @ turned.tangent())
            return replace(turned, c_m=c, s1_m=s - half, s2_m=s + half)
        out = replace(self, **{name: getattr(self, name) + by})
        if out.s2_m - out.s1_m < 1.0 or out.d_m < 1.0:
            return self
        return out

    def effect(self, sigma_m: float, tau_s: float, bias_m: float) -> MultipathZone:
        """The simulator's layer with this wall (end points in the local frame, m)."""
        n, t = self.normal(), self.tangent()
        p1, p2 = self.c_m * n + self.s1_m * t, self.c_m * n + self.s2_m * t
        return MultipathZone(
            x1_m=round(float(p1[0]), 2), y1_m=round(float(p1[1]), 2),
            x2_m=round(float(p2[0]), 2), y2_m=round(float(p2[1]), 2),
            distance_m=round(self.d_m, 2), sigma_m=round(sigma_m, 4),
            bias_m=round(bias_m, 4), tau_s=round(tau_s, 3),
        )  # fmt: skip

    def coords(self, te: np.ndarray, tn: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Offset along the normal and position along the wall of points (m)."""
        n, t = self.normal(), self.tangent()
        return te * n[0] + tn * n[1], te * t[0] + tn * t[1]

    def zone(self, te: np.ndarray, tn: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """In-zone mask and the (2, n) unit vectors away from the wall at the track points,
        exactly as the simulator's layer computes them."""
        eff = self.effect(1.0, 1.0, 0.0)
        dist, ux, uy = eff.distance_to_wall_m(te, tn)
        return dist <= eff.distance_m, np.stack([ux, uy])


WALL_PARAMS = ("theta", "c_m", "s1_m", "s2_m", "d_m")


def fit_walls(
    te: np.ndarray, tn: np.ndarray, in_zone: np.ndarray, valid: np.ndarray, thetas: np.ndarray
) -> list[Wall]:
    """Walls whose zones cover every valid in-zone track point and as few valid out-of-zone
    ones as possible, the normal among angles ``thetas`` (rad) pointing away from the wall.

    Only the zone's intersection with the track is identifiable, and many walls cut the
    same track alike: one per distance of the wall behind the located places
    (:data:`WALL_BACK_M`), from just behind them (a zone bounded by its far edge, the bias
    the same everywhere) to well back (bounded by its round ends, the bias turning there as
    near a real wall's end). For a wall line and a distance the shortest segment covering
    every located point has a closed form; orientation and distance are searched on a grid.
    The likelihood chooses among the returned walls."""
    pin, pout = valid & in_zone, valid & ~in_zone
    ct, st = np.cos(thetas)[:, None], np.sin(thetas)[:, None]
    a_in, s_in = te[pin] * ct + tn[pin] * st, -te[pin] * st + tn[pin] * ct  # (T, n_in)
    a_out, s_out = te[pout] * ct + tn[pout] * st, -te[pout] * st + tn[pout] * ct
    out = []
    for back in WALL_BACK_M:
        c = a_in.min(axis=1, keepdims=True) - WALL_GAP_M - back  # (T, 1)
        best: tuple[float, float, Wall] | None = None
        for extra in WALL_REACH_M:
            d = a_in.max(axis=1, keepdims=True) - c + extra
            # a point at offset a from the wall line is within d of the segment when the
            # segment reaches within r = sqrt(d^2 - a^2) of it along the wall
            r = np.sqrt(np.maximum(d**2 - (a_in - c) ** 2, 0.0))
            s1, s2 = (s_in + r).min(axis=1, keepdims=True), (s_in - r).max(axis=1, keepdims=True)
            mid = (s1 + s2) / 2  # a disc when no segment covers them all: 1 m wall
            s1, s2 = np.minimum(s1, mid - 0.5), np.maximum(s2, mid + 0.5)
            along = np.maximum(0.0, np.maximum(s1 - s_out, s_out - s2))
            false_pos = np.count_nonzero(np.hypot(a_out - c, along) <= d, axis=1)
            area = (d * (s2 - s1 + 2 * d)).ravel()
            j = int(np.lexsort((area, false_pos))[0])
            key = (float(false_pos[j]), float(area[j]))
            if best is None or key < best[:2]:
                wall = Wall(float(thetas[j]), *(float(v[j, 0]) for v in (c, s1, s2, d)))
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
        for by in (THETA_STEPS if name == "theta" else LENGTH_STEPS_M)
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
    g, p = len(zones), log_sigma.size
    masks = np.stack([m for m, _a in zones])
    shared = zones[0][1] is not None
    away = np.stack([a for _m, a in zones]) if shared else None  # type: ignore[misc]
    terms = zone_terms(
        real,
        model,
        np.tile(np.exp(2 * log_sigma), g),
        np.tile(np.exp(log_tau), g),
        np.repeat(masks, p, axis=0),
        None if away is None else np.repeat(away, p, axis=0),
    )
    ll = terms.loglik(True, shared)
    if shared:
        ll = np.where(terms.bias(shared=True)[0] >= 0, ll, terms.loglik(False))
    return ll.reshape(g, p), terms


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
    """One zoom of :func:`_fit_sigma_tau`: its centre and half-widths (log sigma, log tau),
    halvings so far, and its last grid (points, log-likelihoods, GLS bias and errors)."""

    centre: np.ndarray
    half: np.ndarray
    shrinks: int = 0
    pts: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    vals: np.ndarray = field(default_factory=lambda: np.zeros(0))
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
    dt = layout.dt_s
    lo_t, hi_t = math.log(0.5 * dt), math.log(10 * max(layout.duration_s, 10 * dt))
    shared = zone[1] is not None
    if not starts:
        ls = np.linspace(math.log(0.03), math.log(20.0), 10)
        lt = np.linspace(math.log(dt), hi_t, 10)
        gs, gt = (a.ravel() for a in np.meshgrid(ls, lt, indexing="ij"))
        ll, terms = _loglik(real, model, [zone], gs, gt)
        grid = ll[0].reshape(ls.size, lt.size)
        pad = np.pad(grid, 1, constant_values=-np.inf)
        peak = np.ones(grid.shape, dtype=bool)
        for di in (-1, 0, 1):
            for dj in (-1, 0, 1):
                if di or dj:
                    peak &= grid >= pad[1 + di : 1 + di + ls.size, 1 + dj : 1 + dj + lt.size]
        order = [int(i) for i in np.argsort(-ll[0]) if peak.ravel()[i]][:STARTS]
        step = np.array([ls[1] - ls[0], lt[1] - lt[0]])
        starts = [(np.array([gs[i], gt[i]]), step) for i in order]
        if zooms == 0:
            b, se = terms.bias(shared)
            j = order[0]
            return _Params(
                starts[0][0], np.full((2, 2), np.nan), float(ll[0, j]), b[j], se[j], starts
            )
    runs = [_Zoom(c.copy(), h.copy()) for c, h in starts]
    u = np.linspace(-1.0, 1.0, 5)
    du_s, du_t = (a.ravel() for a in np.meshgrid(u, u))
    for _ in range(max(zooms, 1)):
        live = [z for z in runs if z.shrinks < 3]
        if not live:
            break
        s_ = np.concatenate([z.centre[0] + du_s * z.half[0] for z in live])
        t_ = np.concatenate([np.clip(z.centre[1] + du_t * z.half[1], lo_t, hi_t) for z in live])
        ll, terms = _loglik(real, model, [zone], s_, t_)
        b_all, se_all = terms.bias(shared)
        for i, z in enumerate(live):
            sl = slice(i * du_s.size, (i + 1) * du_s.size)
            z.pts, z.vals, z.bias = (
                np.stack([s_[sl], t_[sl]], 1),
                ll[0][sl],
                (b_all[sl], se_all[sl]),
            )
            j = int(np.argmax(z.vals))
            z.centre = z.pts[j]
            at_bound = not lo_t + 1e-9 < z.pts[j, 1] < hi_t - 1e-9
            if abs(du_s[j]) < 1 and (abs(du_t[j]) < 1 or at_bound):
                z.half = z.half / 2
                z.shrinks += 1
    win = max(runs, key=lambda z: float(z.vals.max()))
    j = int(np.argmax(win.vals))
    cov = np.full((2, 2), np.nan)
    best = win.centre
    q = quadratic_peak(win.pts, win.vals)
    if q is not None:
        vertex, cov = q
        if np.all(np.abs(vertex - win.pts.mean(axis=0)) <= np.ptp(win.pts, axis=0) / 2):
            best = vertex
    return _Params(
        best, cov, float(win.vals[j]), win.bias[0][j], win.bias[1][j],
        [(z.centre, z.half) for z in runs],
    )  # fmt: skip


def _refine_wall(
    real: PositionSeries,
    model: NoiseModel,
    wall: Wall,
    params: _Params,
    te: np.ndarray,
    tn: np.ndarray,
    passes: int = 4,
) -> tuple[Wall, dict[str, float]]:
    """Pattern search on the exact likelihood (sigma, tau held, the bias magnitude profiled
    along the wall's away vectors; one batched filter per pass). Returns the wall and each
    parameter's standard error from the curvature of the log-likelihood along it, the others
    held (NaN when flat: the track does not feel that parameter)."""
    ls, lt = params.centre[:1], params.centre[1:]

    def cost(walls: Sequence[Wall]) -> np.ndarray:
        zones = [w.zone(te, tn) for w in walls]
        # a wall with track inside its zone behind it would turn their bias round
        behind = [
            np.count_nonzero(z[0] & (w.coords(te, tn)[0] < w.c_m))
            for w, z in zip(walls, zones, strict=True)
        ]
        return -_loglik(real, model, zones, ls, lt)[0][:, 0] + BEHIND_COST * np.array(behind)

    wall, moves, costs = _pattern_search(wall, cost, passes)
    se: dict[str, float] = {}
    for name in WALL_PARAMS:
        sel = [0] + [i for i, m in enumerate(moves) if m[0] == name]
        x = np.array([moves[i][1] for i in sel])
        curv = 2 * float(np.polyfit(x, costs[sel], 2)[0])  # -d2 loglik / dx2
        se[name] = 1 / math.sqrt(curv) if curv > 0 else math.nan
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
    n = in_zone.size
    edge = np.diff(np.concatenate(([0], in_zone.astype(int), [0])))
    starts, ends = np.flatnonzero(edge == 1), np.flatnonzero(edge == -1)
    masks = np.zeros((BOUNDARY_SHIFTS.size, n), dtype=bool)
    for k, sh in enumerate(BOUNDARY_SHIFTS):
        for a, b in zip(starts, ends, strict=True):
            masks[k, max(a + sh, 0) : min(b + sh, n)] = True
    v = np.asarray(real.valid, dtype=bool)
    y = np.stack([real.east_m, real.north_m]).astype(float) - model.mean_m[:, None]
    g = masks.shape[0]
    zb = np.repeat(masks, 2, axis=0)
    e, e1, s = _filter(
        np.asarray(real.t_s, dtype=float),
        np.tile(np.where(v, y, 0.0), (g, 1)),
        np.broadcast_to(v, (2 * g, n)),
        model,
        np.full(2 * g, math.exp(2 * params.centre[0])),
        np.full(2 * g, math.exp(params.centre[1])),
        zb,
    )
    resid = e - np.tile(params.bias, g)[None] * e1
    ll = -0.5 * (np.log(s) + resid**2 / s) * v[:, None]
    ll = ll.reshape(n, g, 2).sum(axis=2).T  # (shift, epoch)
    cum = np.concatenate([np.zeros((g, 1)), np.cumsum(ll, axis=1)], axis=1)

    def best_shift(lo: int, hi: int) -> int:
        lo, hi = max(lo, 0), min(hi, n)
        return int(BOUNDARY_SHIFTS[int(np.argmax(cum[:, hi] - cum[:, lo]))])

    out = np.zeros(n, dtype=bool)
    span = int(BOUNDARY_SHIFTS.max())
    for entry, exit_ in zip(starts.tolist(), ends.tolist(), strict=True):
        reach = min(2 * span, max((exit_ - entry) // 2, 1))  # windows stay in their half
        a2 = entry + best_shift(entry - 2 * span, entry + reach)
        b2 = exit_ + best_shift(exit_ - reach, exit_ + 2 * span)
        out[max(a2, 0) : min(max(b2, a2 + 1), n)] = True
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
    for k, (a, b) in enumerate(zip(starts, ends, strict=True)):
        masks[k + 1, a:b] = False
    ll = _loglik(real, model, [(m, None) for m in masks], params.centre[:1], params.centre[1:])[0]
    nobs = 2 * int(np.count_nonzero(real.valid))
    keep = ll[0, 0] - ll[1:, 0] > math.log(nobs)  # two boundary epochs: BIC 2 x log(n) / 2
    out = np.zeros_like(in_zone)
    for a, b, k in zip(starts, ends, keep, strict=True):
        out[a:b] = k
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
    real: PositionSeries, base: Sequence[PositionSeries], layout: Layout
) -> ZoneFit | None:
    """Fit a multipath zone to ``real`` (errors, m) on top of the baseline runs ``base``
    (same truth track and epochs): see the module docstring. None for a static log, when no
    place shows excess error beyond the runs' own, or when the zone does not beat BIC."""
    if not layout.moving or len(real) < 60 or len(base) < 3:
        return None
    t = np.asarray(real.t_s, dtype=float)
    valid = np.asarray(real.valid, dtype=bool)
    model = noise_model(base, layout)
    loc = locate_zone(real, [_on_epochs(s, t) for s in base], model.mean_m)
    if loc is None or np.mean(loc.in_zone[valid]) > MAX_SHARE:
        return None
    te, tn = truth_track_m(real)
    # entries and exits to the epoch, twice: the first parameters come from the coarse
    # located places, whose blurred edges understate a bias
    first = _fit_sigma_tau(real, model, (loc.in_zone, None), layout, zooms=0)
    located = _refine_boundaries(real, model, loc.in_zone, first)
    first = _fit_sigma_tau(real, model, (located, None), layout, zooms=2, starts=first.starts)
    located = _prune_runs(real, model, _refine_boundaries(real, model, located, first), first)
    if not np.any(located[valid]):
        return None
    # the wall goes on the side opposite the bias: its normal within two standard errors of
    # the bias direction, or anywhere on that side when the bias is not significant
    b, b_se = first.bias, first.bias_se
    size = float(np.hypot(*b))
    ang = math.atan2(b[1], b[0])
    spread = math.pi / 2
    if size > 2 * float(np.hypot(*(b * b_se))) / max(size, 1e-12):  # |b| > 2 se(|b|)
        spread = min(2 * float(np.hypot(*b_se)) / size, math.pi / 4)
    thetas = ang + np.linspace(-spread, spread, max(9, int(spread / math.radians(5)) + 1))
    walls = fit_walls(te, tn, located, valid, thetas)
    start = _loglik(
        real, model, [w.zone(te, tn) for w in walls], first.centre[:1], first.centre[1:]
    )[0]
    wall, geo_se = _refine_wall(real, model, walls[int(np.argmax(start[:, 0]))], first, te, tn)
    in_zone, away = wall.zone(te, tn)
    if not np.any(in_zone[valid]) or np.mean(in_zone[valid]) > MAX_SHARE:
        return None
    p = _fit_sigma_tau(real, model, (in_zone, away), layout, zooms=4)  # a fresh coarse grid
    sigma, tau = (math.exp(v) for v in p.centre)
    # at the fitted sigma, tau: "no zone", the bias along the away vectors, and the in-zone
    # bias as a free vector (for its direction)
    var, taus = np.array([0.0, sigma**2]), np.array([1.0, tau])
    along = zone_terms(real, model, var, taus, in_zone, away)
    free = zone_terms(real, model, var[1:], taus[1:], in_zone)
    bias, bias_se = (float(a[1]) for a in along.bias(shared=True))
    bias = max(bias, 0.0)  # held >= 0 as in the search (see _loglik)
    gain = float(along.loglik(bias > 0, shared=True)[1] - along.loglik(False)[0])
    penalty = 0.5 * ZONE_PARAMS * math.log(2 * int(np.count_nonzero(valid)))
    if gain < penalty:
        return None
    free_b, free_se = (a[0] for a in free.bias())
    # end points: P1,2 = c n + s1,2 t, turning about the middle (dP/dtheta = -/+ L/2 n). A
    # boundary between two fixes is known to a step of travel at best (uniform: step/sqrt 12)
    step = float(np.median(np.hypot(np.diff(te), np.diff(tn)))) / math.sqrt(12)
    n, tg = wall.normal(), wall.tangent()
    half = (wall.s2_m - wall.s1_m) / 2
    se = {"distance_m": max(geo_se["d_m"], step)}
    for i, s_name in ((1, "s1_m"), (2, "s2_m")):
        for a, ax in enumerate("xy"):
            se[f"{ax}{i}_m"] = math.hypot(
                n[a] * max(geo_se["c_m"], step),
                tg[a] * max(geo_se[s_name], step),
                half * n[a] * geo_se["theta"],
            )
    se |= {
        "sigma_m": sigma * math.sqrt(max(p.cov[0, 0], 0.0)),
        "tau_s": tau * math.sqrt(max(p.cov[1, 1], 0.0)),
        "bias_m": bias_se,
    }
    return ZoneFit(
        wall.effect(sigma, tau, bias), se, in_zone, free_b, np.diag(free_se**2), gain,
        penalty, loc,
    )  # fmt: skip


def fit_multipath_zone(
    real: PositionSeries, base: Sequence[PositionSeries], layout: Layout
) -> Fit | None:
    """``multipath_zone`` fitted to a moving log (see :func:`fit_zone`): wall end points and
    distance (m) of the tightest zone over the located places, Gauss-Markov sigma_m (m) and
    tau_s (s), bias_m (m, away from the wall). None for static logs: a static receiver inside
    a zone is indistinguishable from gauss_markov + bias."""
    z = fit_zone(real, base, layout)
    return None if z is None else Fit(z.effect, z.se)
