"""The exact Gaussian likelihood of a log under the baseline noise model plus one effect
component: a Kalman filter over the valid epochs, batched over effect parameters.

The real error is modelled as the baseline's own error process plus the effect:
  y_c(t) = mean_c + sum_i g_ci(t) + e(t) + w_c(t),   c = east, north
with g_ci the baseline's first-order Gauss-Markov components (fitted to the baseline runs),
w_c its white part, and e(t) the effect: a Gauss-Markov drift (phi = exp(-dt/tau), innovation
variance sigma^2 (1 - phi^2), stationary start) or a random walk (phi = 1, innovation variance
q^2 dt, starting at zero as the simulator's layer does). Every component is propagated with the
ACTUAL step between valid epochs, so outages and irregular sampling are exact. A constant bias
is profiled out by generalised least squares: the innovations are linear in the data, so the
filter run on a column of ones gives the regressor's innovations at no extra Riccati cost.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator
from dataclasses import dataclass

import numpy as np

from sim_backend.effects import (
    PositionSeries,
    delay_errors,
    gm2_transition,
    truth_velocity_mps,
)
from x6wd.gap.noise import NoiseModel

_LOG_2PI = math.log(2.0 * math.pi)


@dataclass(frozen=True)
class KalmanTerms:
    """Per (batch, axis): sum of log S over the valid epochs, the Gram matrix
    sum e_c e_d / S of the innovations of the columns [data, ones, latency regressor] (the
    last only for moving logs) and the number of observations per axis."""

    log_s: np.ndarray  # (B, 2)
    gram: np.ndarray  # (B, 2, C, C)
    nobs: int

    @property
    def has_latency(self) -> bool:
        return self.gram.shape[-1] > 2

    def _normal_equations(self, bias: bool, latency: bool) -> tuple[np.ndarray, np.ndarray]:
        """(A (B, P, P), c (B, P)) of the GLS regression of the data on the chosen regressors:
        a bias per axis (column 1 of that axis) and one latency shared by both axes (column 2
        of each axis: the error a delay makes is -delay x velocity)."""
        gram = self.gram
        # each parameter: the axis it acts on (None: both) and its regressor column
        params = ([(0, 1), (1, 1)] if bias else []) + (
            [(None, 2)] if latency and self.has_latency else []
        )
        n_params = len(params)
        a = np.zeros((gram.shape[0], n_params, n_params))
        c = np.zeros((gram.shape[0], n_params))
        for i, (axis_i, col_i) in enumerate(params):
            axes_i = {0, 1} if axis_i is None else {axis_i}
            c[:, i] = sum(gram[:, ax, 0, col_i] for ax in axes_i)
            for j, (axis_j, col_j) in enumerate(params):
                common = axes_i & ({0, 1} if axis_j is None else {axis_j})
                a[:, i, j] = sum(gram[:, ax, col_i, col_j] for ax in common)
        return a, c

    def loglik(self, bias: bool, latency: bool = False) -> np.ndarray:
        """Exact Gaussian log-likelihood per batch element: the mean fixed at the baseline's,
        or with a bias per axis (``bias``) and/or a latency (``latency``, moving logs)
        profiled out by GLS."""
        q = self.gram[:, :, 0, 0].sum(axis=-1)
        a, c = self._normal_equations(bias, latency)
        if c.shape[1]:
            beta = np.linalg.solve(a + 1e-12 * np.eye(c.shape[1]), c[..., None])[..., 0]
            q = q - np.sum(c * beta, axis=-1)
        return -0.5 * (self.log_s.sum(axis=-1) + q + 2 * self.nobs * _LOG_2PI)

    def coef(self, bias: bool, latency: bool) -> tuple[np.ndarray, np.ndarray]:
        """GLS coefficients (B, P) and their standard errors: [bias east, bias north] (m)
        when ``bias``, then the latency (s) when ``latency``."""
        a, c = self._normal_equations(bias, latency)
        cov = np.linalg.inv(a + 1e-12 * np.eye(c.shape[1]))
        return (cov @ c[..., None])[..., 0], np.sqrt(np.diagonal(cov, axis1=1, axis2=2))


def latency_regressor(series: PositionSeries, near_s: float = 0.0) -> np.ndarray | None:
    """(2, n) the east/north error (m) per second of delay at the valid epochs. Near 0 s
    (``near_s`` 0) it is -velocity, since a receiver that is d s late reports truth(t - d) ~
    truth(t) - d v(t); near a delay ``near_s`` > 0 it is the exact error of that delay over
    it, (truth(t - near_s) - truth(t)) / near_s (:func:`~sim_backend.effects.delay_errors`,
    what the Latency layer adds): on a route that stops and turns, -d v(t) misses the start
    and end of every leg, and the delay fitted with it was 1.5-1.6 s for 2 s. None at rest."""
    if series.speed_mps is None:
        return None
    valid = np.asarray(series.valid, dtype=bool)
    if not np.any(np.nan_to_num(np.asarray(series.speed_mps, dtype=float))[valid] > 0):
        return None
    if near_s > 0.0:
        delayed = delay_errors(series, near_s)
        return np.stack(
            [
                (np.asarray(delayed.east_m) - np.asarray(series.east_m))[valid] / near_s,
                (np.asarray(delayed.north_m) - np.asarray(series.north_m))[valid] / near_s,
            ]
        )
    v_east_mps, v_north_mps = truth_velocity_mps(series)
    return -np.stack([v_east_mps[valid], v_north_mps[valid]])


Transition = tuple[np.ndarray, np.ndarray, np.ndarray]


def component_law(
    model: NoiseModel, effect_var: np.ndarray, effect_tau_s: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Stationary variances (m^2; for a random walk, tau inf, its rate m^2/s) and correlation
    times (s), each (K + 1, C), of the baseline's K Gauss-Markov components and one effect,
    for C = 2 B filter columns (column j = batch j // 2, axis j % 2); ``effect_var`` and
    ``effect_tau_s`` are given per column (C,)."""
    reps = effect_var.size // 2
    var = np.vstack([np.tile(model.sigma_m.T**2, (1, reps)), effect_var[None, :]])
    tau_s = np.vstack([np.tile(model.tau_s.T, (1, reps)), effect_tau_s[None, :]])
    return var, tau_s


def transitions(
    var: np.ndarray, tau_s: np.ndarray, steps_s: np.ndarray
) -> Callable[[int], Transition]:
    """Step i (from valid epoch i to i + 1, ``steps_s[i]`` s apart) of independent
    first-order components (``var``/``tau_s`` (K, C), see :func:`component_law`): (phi
    (K, 1, C), phi phi' (K, K, C), process noise Q (K, K, C)) for x <- phi x,
    P <- phi phi' P + Q. Exact discretisation with the actual step (phi = exp(-dt/tau); a
    random walk where tau is inf), so outages and irregular sampling are exact; tabulated when
    the log has few distinct steps (a regular log has one)."""
    walk = ~np.isfinite(tau_s)
    safe_tau_s = np.where(walk, 1.0, tau_s)
    diag = np.eye(var.shape[0])[:, :, None]

    def step(dt_s: float) -> Transition:
        phi = np.where(walk, 1.0, np.exp(-dt_s / safe_tau_s))
        q = np.where(walk, var * dt_s, var * -np.expm1(-2.0 * dt_s / safe_tau_s))
        return phi[:, None, :], phi[:, None, :] * phi[None, :, :], diag * q[None, :, :]

    distinct, index = np.unique(np.round(steps_s, 6), return_inverse=True)
    if distinct.size <= 32:
        table = [step(float(d)) for d in distinct]
        return lambda i: table[index[i]]
    return lambda i: step(float(steps_s[i]))


def kalman_terms(
    real: PositionSeries,
    model: NoiseModel,
    effect_var: np.ndarray,
    effect_tau_s: np.ndarray,
    order: int = 1,
    latency_near_s: float = 0.0,
) -> KalmanTerms:
    """Run the Kalman filter of baseline model + one effect component for a batch of effect
    parameters: ``effect_var`` (B,) the stationary variance sigma^2 (m^2) of a Gauss-Markov
    effect of correlation time ``effect_tau_s`` (s) or, where that is inf, the random-walk
    rate q^2 (m^2/s); ``effect_var`` 0 = no effect; ``order`` 2: the Gauss-Markov effect is
    critically damped (:func:`sim_backend.effects.gm2_transition`, two states). The
    innovations are linear in the data, so the filter run on a column of ones and on the
    latency regressor gives their innovations for GLS at no extra Riccati cost."""
    valid = np.asarray(real.valid, dtype=bool)
    t_s = np.asarray(real.t_s, dtype=float)[valid]
    east_m = np.asarray(real.east_m, dtype=float)[valid]
    north_m = np.asarray(real.north_m, dtype=float)[valid]
    error_m = np.stack([east_m, north_m]) - model.mean_m[:, None]  # (2, n)
    latency = latency_regressor(real, latency_near_s)
    n_epochs = t_s.size
    batch = effect_var.size
    n_cols = 2 if latency is None else 3
    # Layout: state index first, the batch (B parameter sets x 2 axes, flattened, column
    # j = (batch j // 2, axis j % 2)) LAST and contiguous, so that every time step is a
    # handful of vector operations over the whole batch.
    var, tau_s = component_law(model, np.repeat(effect_var, 2), np.repeat(effect_tau_s, 2))
    white_var_m2 = np.tile(model.white_m**2, batch)  # (n_filters,)
    columns = [error_m] if latency is None else [error_m, latency]

    def rows(a: int, b: int) -> np.ndarray:
        """The filter's observations of epochs a..b (b - a, cols, filters): [data, ones
        (, latency regressor)] per axis, repeated over the batch."""
        obs = np.empty((b - a, n_cols, 2 * batch))
        obs[:, 0, :] = np.tile(columns[0][:, a:b].T, (1, batch))
        obs[:, 1, :] = 1.0
        if latency is not None:
            obs[:, 2, :] = np.tile(columns[1][:, a:b].T, (1, batch))
        return obs

    # The innovations are summed into the Gram matrix block by block of epochs, never held
    # for the whole log: they are epochs x columns x filters (a batch of ~200 parameter sets
    # over a 1 h log at 10 Hz is 0.2 GB per array; three such arrays made the peak).
    gram = np.zeros((2 * batch, n_cols, n_cols))
    log_s = np.zeros(2 * batch)
    run = _filter_diagonal if order == 1 else _filter_coupled
    for e_block, s_block in run(rows, n_epochs, var, tau_s, white_var_m2, np.diff(t_s)):
        scaled = e_block / np.sqrt(s_block)[:, None, :]
        gram += np.einsum("ncj,ndj->jcd", scaled, scaled)  # (n_filters, C, C)
        log_s += np.log(s_block).sum(axis=0)
    return KalmanTerms(
        log_s=log_s.reshape(batch, 2),
        gram=gram.reshape(batch, 2, n_cols, n_cols),
        nobs=n_epochs,
    )


KALMAN_BLOCK_BYTES = 16 * 2**20
"""Size (bytes) of one block of a filter's observations or innovations: the epochs a filter
holds at once are as many as fit (at least 16)."""


def _block_len(n_cols: int, n_filters: int) -> int:
    return max(16, KALMAN_BLOCK_BYTES // (8 * n_cols * n_filters))


Rows = Callable[[int, int], np.ndarray]


def _filter_diagonal(
    rows: Rows, n_epochs: int, var: np.ndarray, tau_s: np.ndarray, white_var_m2: np.ndarray,
    steps_s: np.ndarray,
) -> Iterator[tuple[np.ndarray, np.ndarray]]:  # fmt: skip
    """Innovations (n, cols, filters) and their variances (n, filters), block by block of
    epochs, of independent first-order components (:func:`transitions`), all observed:
    x, P, S, e the usual Kalman state, its covariance, the innovation variance and the
    innovations. ``rows(a, b)``: the observations (b - a, cols, filters) of epochs a..b."""
    n_states, n_filters = var.shape
    p0 = np.where(np.isfinite(tau_s), var, 0.0)  # a walk starts at zero
    trans = transitions(var, tau_s, steps_s)
    x: np.ndarray | None = None
    p = np.eye(n_states)[:, :, None] * p0[None, :, :]
    block = _block_len(3, n_filters)
    for a in range(0, n_epochs, block):
        obs = rows(a, min(n_epochs, a + block))
        if x is None:
            x = np.zeros((n_states, obs.shape[1], n_filters))  # middle: [data, ones(, latency)]
        e_all = np.empty_like(obs)
        s_all = np.empty((obs.shape[0], n_filters))
        for k in range(obs.shape[0]):
            i = a + k
            if i > 0:
                phi, phi2, q = trans(i - 1)
                p = p * phi2 + q
                x = x * phi
            e_all[k], s_all[k] = _update(x, p, obs[k], white_var_m2, n_states)
        yield e_all, s_all


def _update(
    x: np.ndarray, p: np.ndarray, obs: np.ndarray, white_var_m2: np.ndarray, observed: int
) -> tuple[np.ndarray, np.ndarray]:
    """One measurement update in place (the first ``observed`` states summed are seen, plus
    white noise): the innovations of every column and their variance."""
    pk = p[:, :observed].sum(axis=1)  # (n_states, n_filters): P H' with H = [1 ... 1, 0 ...]
    s = pk[:observed].sum(axis=0) + white_var_m2  # innovation variance
    e = obs - x[:observed].sum(axis=0)  # innovations of every column
    gain = pk / s
    x += gain[:, None, :] * e[None, :, :]
    p -= gain[:, None, :] * pk[None, :, :]
    return e, s


def _filter_coupled(
    rows: Rows, n_epochs: int, var: np.ndarray, tau_s: np.ndarray, white_var_m2: np.ndarray,
    steps_s: np.ndarray,
) -> Iterator[tuple[np.ndarray, np.ndarray]]:  # fmt: skip
    """As :func:`_filter_diagonal` with the effect (the last row of ``var``/``tau_s``) a
    critically damped second-order process: two states (position, observed; rate, not)
    coupled by a full 2 x 2 transition, so P moves as F P F' + Q."""
    n_base, n_filters = var.shape[0] - 1, var.shape[1]
    n_states = n_base + 2
    observed = n_base + 1  # the baseline components and the effect's position
    effect_var, effect_tau_s = var[-1], tau_s[-1]

    def step(dt_s: float) -> tuple[np.ndarray, np.ndarray]:
        f = np.zeros((n_states, n_states, n_filters))
        q = np.zeros_like(f)
        base = np.arange(n_base)
        f[base, base] = np.exp(-dt_s / tau_s[:-1])
        q[base, base] = var[:-1] * -np.expm1(-2.0 * dt_s / tau_s[:-1])
        f[n_base:, n_base:], q[n_base:, n_base:] = gm2_transition(dt_s, effect_tau_s, effect_var)
        return f, q

    distinct, index = np.unique(np.round(steps_s, 6), return_inverse=True)
    table = [step(float(d)) for d in distinct] if distinct.size <= 32 else None
    x: np.ndarray | None = None
    p = np.zeros((n_states, n_states, n_filters))
    stationary = np.concatenate([var[:-1], [effect_var, effect_var / effect_tau_s**2]])
    p[np.arange(n_states), np.arange(n_states)] = stationary
    block = _block_len(3, n_filters)
    for a in range(0, n_epochs, block):
        obs = rows(a, min(n_epochs, a + block))
        if x is None:
            x = np.zeros((n_states, obs.shape[1], n_filters))
        e_all = np.empty_like(obs)
        s_all = np.empty((obs.shape[0], n_filters))
        for k in range(obs.shape[0]):
            i = a + k
            if i > 0:
                f, q = table[index[i - 1]] if table is not None else step(float(steps_s[i - 1]))
                x = np.einsum("ijc,jkc->ikc", f, x)
                p = np.einsum("ijc,kjc->ikc", np.einsum("ijc,jkc->ikc", f, p), f) + q
            e_all[k], s_all[k] = _update(x, p, obs[k], white_var_m2, observed)
        yield e_all, s_all


def quadratic_peak(points: np.ndarray, values: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """Least-squares quadratic surface through (``points`` (N, d), ``values`` (N,); e.g.
    log-parameters and log-likelihoods): its vertex and the covariance -H^-1 (None when the
    surface is not concave): standard errors from the curvature of a likelihood."""
    d = points.shape[1]
    cols = [np.ones(len(points))] + [points[:, i] for i in range(d)]
    pairs = [(i, j) for i in range(d) for j in range(i, d)]
    cols += [points[:, i] * points[:, j] for i, j in pairs]
    coef, *_ = np.linalg.lstsq(np.stack(cols, axis=1), values, rcond=None)
    grad = coef[1 : d + 1]
    hess = np.zeros((d, d))
    for c, (i, j) in zip(coef[d + 1 :], pairs, strict=True):
        if i == j:
            hess[i, i] = 2 * c
        else:
            hess[i, j] = hess[j, i] = c
    if np.any(np.linalg.eigvalsh(hess) >= 0):
        return None
    cov = -np.linalg.inv(hess)
    return cov @ grad, cov
