"""Whether a receiver's record moves: the steady speed in its positions, which a receiver
standing still cannot show whatever its noise (used by ``x6wd calibrate gnss --static`` and
``x6wd gap``'s static logs: a robot driving at 0.94 m/s lay within the gap tool's old
speed and spread limits and its route was scored as receiver error)."""

from __future__ import annotations

import itertools
import math

import numpy as np
import numpy.typing as npt

MAX_STATIC_SPEED_MPS = 0.5
"""Largest steady speed (m/s) a static recording may show (:func:`steady_speed_mps`). A
robot circling inside the spread limit (3.5 m circles at 1 m/s, 5 s stops: read as 0.79 m/s,
12.7 SEs; ASE written as 3.2 m before the check) shows its speed; a receiver standing still
does not: real static logs read 0.005 m/s (ZED-F9P on KK1446) and 0.064 m/s (ZED-F9P, gpsd),
a Gauss-Markov error cannot read above 0 on average (its steps revert), whatever its ASE and
τ: 10 seeds of ASE 1.5 m τ 60 s and of ASE 5 m τ 600 s read at most 0.18 m/s by chance
(2.3 SEs), ASE 3 m τ 15 s and ASE 5 m τ 5 s read 0."""

MOVE_SIGNIFICANCE = 3.0
"""The steady-speed evidence must also stand this many jackknife SEs above 0: a short record
of a noisy receiver (white 2-3 m, 100 fixes) scatters its speed estimate to 0.9-1.3 m/s by
chance, but never to 2 SEs; a drive, even with a 0.5 m reference, stands at 6 SEs or more."""


def steady_speed_mps(
    t_s: npt.ArrayLike, x: npt.ArrayLike, y: npt.ArrayLike, blocks: int = 20
) -> tuple[float, float] | None:
    """The steady speed (m/s) in a recording's positions ``x``, ``y`` (m) and how many
    jackknife SEs it stands above 0; None when there are too few pairs to tell.

    The mean dot product of two 1 s displacements that share no fix, 2 s apart
    (p(t+1)−p(t))·(p(t+3)−p(t+2)): a robot moving at v along a smooth path gives v²·cos(its
    turn in 2 s), while a receiver standing still cannot make it positive: white noise gives
    0 (the two steps are independent) and a slow, mean-reverting (Gauss-Markov) error
    −σ²·φ(1−φ)² per axis (φ = e^(−1/τ): its steps revert), however large its spread σ and
    however long its correlation time τ. The comparison of d(3 s) with d(1 s) used before
    read a slow error as motion (ASE 3 m, τ 15 s: 0.61 m/s) because its displacement still
    grows between those lags. A smooth error (a receiver's filter) does give a positive
    product, but only its own speed squared, hundredths of a m/s. The mean, not the median:
    a jump or a spike sits in one of the two steps and averages out, and the median of these
    products is biased low for a noisy drive. Lags in epochs for records slower than 1 Hz;
    ``t_s`` (s) in time order, ``blocks`` the jackknife's."""
    t = np.asarray(t_s, float)
    t = t - t[0]
    steps = np.diff(t)
    if not (steps > 0).any():
        return None
    dt = float(np.median(steps[steps > 0]))
    idx = np.round(t / dt).astype(np.int64)
    keep = np.concatenate(([True], np.diff(idx) > 0))
    xy = np.column_stack([np.asarray(x, float), np.asarray(y, float)])[keep]
    idx = idx[keep]
    k = max(1, round(1.0 / dt))

    def at(lag: int) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.bool_]]:
        pos = np.searchsorted(idx, idx + lag)
        ok = pos < idx.size
        ok[ok] = idx[pos[ok]] == idx[ok] + lag
        return np.where(ok, pos, 0), ok

    (p1, o1), (p2, o2), (p3, o3) = at(k), at(2 * k), at(3 * k)
    first = np.flatnonzero(o1 & o2 & o3)
    if first.size < 50:
        return None
    dots = ((xy[p1[first]] - xy[first]) * (xy[p3[first]] - xy[p2[first]])).sum(axis=1)
    mean = float(dots.mean())
    edges = np.linspace(0, idx.size, blocks + 1).astype(int)
    reps = []
    for lo, hi in itertools.pairwise(edges):
        out = (first < lo) | (first >= hi)
        if out.any():
            reps.append(float(dots[out].mean()))
    r = np.array(reps)
    se = math.sqrt((r.size - 1) / r.size * float(((r - r.mean()) ** 2).sum()))
    speed = math.sqrt(max(mean, 0.0)) / (k * dt)
    return speed, (mean / se if se > 0 else (math.inf if mean > 0 else 0.0))
