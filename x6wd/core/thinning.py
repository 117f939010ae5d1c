"""Thinning a long series for a plot: every k-th sample and the last, so a line drawn through
them keeps its shape and its end. Shared by the simulator's track.png and ``x6wd logview``."""

from __future__ import annotations

import math

import numpy as np


def thinned_indices(n: int, limit: int) -> np.ndarray:
    """Indices into a series of ``n`` samples: all of them when ``n <= limit``, else every
    ``ceil(n / limit)``-th from the first, and the last (at most ``limit + 1``)."""
    if limit < 1:
        raise ValueError(f"limit must be at least 1, got {limit}")
    if n <= limit:
        return np.arange(n)
    stride = math.ceil(n / limit)
    return np.r_[np.arange(0, n - 1, stride), n - 1]
