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
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from sim_backend.effects import PositionSeries, truth_velocity_mps
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
        g = self.gram
        params = ([(0, 1), (1, 1)] if bias else []) + (
            [(None, 2)] if latency and self.has_latency else []
        )
        m = len(params)
        a = np.zeros((g.shape[0], m, m))
        c = np.zeros((g.shape[0], m))
        for i, (ax_i, col_i) in enumerate(params):
            axes_i = {0, 1} if ax_i is None else {ax_i}
            c[:, i] = sum(g[:, ax, 0, col_i] for ax in axes_i)
            for j, (ax_j, col_j) in enumerate(params):
                common = axes_i & ({0, 1} if ax_j is None else {ax_j})
                a[:, i, j] = sum(g[:, ax, col_i, col_j] for ax in common)
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


def latency_regressor(series: PositionSeries) -> np.ndarray | None:
    """(2, n) the east/north error (m) per second of delay at the valid epochs: -velocity,
    since a receiver that is d s late reports truth(t - d) ~ truth(t) - d v(t). None at rest."""
    if series.speed_mps is None:
        return None
    v = np.asarray(series.valid, dtype=bool)
    if not np.any(np.nan_to_num(np.asarray(series.speed_mps, dtype=float))[v] > 0):
        return None
    ve, vn = truth_velocity_mps(series)
    return -np.stack([ve[v], vn[v]])


Transition = tuple[np.ndarray, np.ndarray, np.ndarray]


def component_law(
    model: NoiseModel, eff_var: np.ndarray, eff_tau: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Stationary variances (m^2; for a random walk, tau inf, its rate m^2/s) and correlation
    times (s), each (K + 1, C), of the baseline's K Gauss-Markov components and one effect,
    for C = 2 B filter columns (column j = batch j // 2, axis j % 2); ``eff_var`` and
    ``eff_tau`` are given per column (C,)."""
    reps = eff_var.size // 2
    var = np.vstack([np.tile(model.sigma_m.T**2, (1, reps)), eff_var[None, :]])
    tau = np.vstack([np.tile(model.tau_s.T, (1, reps)), eff_tau[None, :]])
    return var, tau


def transitions(var: np.ndarray, tau: np.ndarray, dts: np.ndarray) -> Callable[[int], Transition]:
    """Step i (from valid epoch i to i + 1, ``dts`` s apart) of independent first-order
    components (``var``/``tau`` (K, C), see :func:`component_law`): (phi (K, 1, C),
    phi phi' (K, K, C), process noise Q (K, K, C)) for x <- phi x, P <- phi phi' P + Q.
    Exact discretisation with the actual step (phi = exp(-dt/tau); a random walk where tau is
    inf), so outages and irregular sampling are exact; tabulated when the log has few
    distinct steps (a regular log has one)."""
    rw = ~np.isfinite(tau)
    safe_tau = np.where(rw, 1.0, tau)
    diag = np.eye(var.shape[0])[:, :, None]

    def step(dt: float) -> Transition:
        phi = np.where(rw, 1.0, np.exp(-dt / safe_tau))
        q = np.where(rw, var * dt, var * -np.expm1(-2.0 * dt / safe_tau))
        return phi[:, None, :], phi[:, None, :] * phi[None, :, :], diag * q[None, :, :]

    uniq, inv = np.unique(np.round(dts, 6), return_inverse=True)
    if uniq.size <= 32:
        table = [step(float(d)) for d in uniq]
        return lambda i: table[inv[i]]
    return lambda i: step(float(dts[i]))


def kalman_terms(
    real: PositionSeries,
    model: NoiseModel,
    eff_var: np.ndarray,
    eff_tau: np.ndarray,
) -> KalmanTerms:
    """Run the Kalman filter of baseline model + one effect component for a batch of effect
    parameters: ``eff_var`` (B,) the stationary variance sigma^2 of a Gauss-Markov effect or,
    where ``eff_tau`` is inf, the random-walk rate q^2 (m^2/s); ``eff_var`` 0 = no effect.
    The innovations are linear in the data, so the filter run on a column of ones and on the
    latency regressor gives their innovations for GLS at no extra Riccati cost."""
    v = np.asarray(real.valid, dtype=bool)
    t = np.asarray(real.t_s, dtype=float)[v]
    east = np.asarray(real.east_m, dtype=float)[v]
    north = np.asarray(real.north_m, dtype=float)[v]
    y = np.stack([east, north]) - model.mean_m[:, None]  # (2, n)
    lat = latency_regressor(real)
    n = t.size
    b = eff_var.size
    k = model.tau_s.shape[1] + 1
    cols = 2 if lat is None else 3
    # Layout: state index first, the batch (B parameter sets x 2 axes, flattened, column
    # j = (batch j // 2, axis j % 2)) LAST and contiguous, so that every time step is a
    # handful of vector operations over the whole batch.
    nb = 2 * b
    var, tau = component_law(model, np.repeat(eff_var, 2), np.repeat(eff_tau, 2))
    w2 = np.tile(model.white_m**2, b)  # (nb,)
    p0 = np.where(np.isfinite(tau), var, 0.0)  # a walk starts at zero
    dts = np.diff(t)
    trans = transitions(var, tau, dts)
    x = np.zeros((k, cols, nb))  # middle axis: [data, ones(, latency)]
    p = np.eye(k)[:, :, None] * p0[None, :, :]
    obs = np.empty((n, cols, nb))
    obs[:, 0, :] = np.tile(y.T, (1, b))
    obs[:, 1, :] = 1.0
    if lat is not None:
        obs[:, 2, :] = np.tile(lat.T, (1, b))
    e_all = np.empty((n, cols, nb))
    s_all = np.empty((n, nb))
    for i in range(n):
        if i > 0:
            phi, pp, dq = trans(i - 1)
            p = p * pp + dq
            x = x * phi
        pk = p.sum(axis=1)  # (k, nb): P @ 1
        s = pk.sum(axis=0) + w2  # innovation variance
        e = obs[i] - x.sum(axis=0)  # innovations of every column
        gain = pk / s
        x += gain[:, None, :] * e[None, :, :]
        p -= gain[:, None, :] * pk[None, :, :]
        e_all[i] = e
        s_all[i] = s
    scaled = e_all / np.sqrt(s_all)[:, None, :]
    gram = np.einsum("ncj,ndj->jcd", scaled, scaled)  # (nb, C, C)
    return KalmanTerms(
        log_s=np.log(s_all).sum(axis=0).reshape(b, 2),
        gram=gram.reshape(b, 2, cols, cols),
        nobs=n,
    )


def quadratic_peak(pts: np.ndarray, vals: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """Least-squares quadratic surface through (pts (N, d), vals (N,)): its vertex and the
    covariance -H^-1 (None when the surface is not concave)."""
    d = pts.shape[1]
    cols = [np.ones(len(pts))] + [pts[:, i] for i in range(d)]
    pairs = [(i, j) for i in range(d) for j in range(i, d)]
    cols += [pts[:, i] * pts[:, j] for i, j in pairs]
    coef, *_ = np.linalg.lstsq(np.stack(cols, axis=1), vals, rcond=None)
    g = coef[1 : d + 1]
    h = np.zeros((d, d))
    for c, (i, j) in zip(coef[d + 1 :], pairs, strict=True):
        if i == j:
            h[i, i] = 2 * c
        else:
            h[i, j] = h[j, i] = c
    if np.any(np.linalg.eigvalsh(h) >= 0):
        return None
    cov = -np.linalg.inv(h)
    return cov @ g, cov
