"""The Constellation filter of the X6WD paper (C++ ``TConstellation``), streaming and vectorised.

A window of the last N samples of one axis (latitude or longitude, in degrees, filtered
separately). With 3 or more samples the output is the midpoint of the closest pair: over all
ORDERED pairs (h, k), h != k, in h-major order, the pair with the smallest ``|Buf[h] − Buf[k]|``
found with a ``>=`` scan, so among tied distances the LAST pair wins. Buf[0] is the oldest
sample. Because the distance is symmetric, the winner is the tied pair with the newest later
sample, then the newest earlier sample — this matters for NMEA data quantised to 1e-5 minute,
where ties are common. With 2 samples the output is their mean, with 1 the sample itself.
The result is bit-identical to that O(N²) scan but is found in O(N log N) (see the comment
above ``_closest_pair_sorted``), per sample when streaming and per window when vectorised.

Departures from the C++: an empty filter raises :class:`EmptyFilterError` instead of returning
the −1 sentinel (−1 is a valid longitude), and non-finite samples are rejected.

Hysteresis (``hysteresis=True``, default off so the port stays faithful): once more than N
samples have been added (the buffer has slid at least once), the previous output is kept unless
``|previous − candidate| >= |pair difference|``. The C++ has this branch but it is dead code —
its sample counter stops at N, so ``BufCounter <= N`` always holds — while the comparison only
makes sense for a sliding buffer; we read it as the intended behaviour, made optional.
"""

from __future__ import annotations

import math
import operator
from collections import deque
from collections.abc import Iterable, Sequence

import numpy as np
import numpy.typing as npt

from x6wd.core.errors import X6wdError

DEFAULT_N = 20

# Window elements processed per chunk in filter_series (bounds the temporary memory).
_CHUNK_ELEMENTS = 1 << 18


class ConstellationError(X6wdError, ValueError):
    """Bad filter parameter or sample (window too small, non-finite value)."""


class EmptyFilterError(ConstellationError):
    """The filter holds no sample yet, so it has no value (the C++ returned −1)."""


def _check_n(n: int) -> int:
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)):
        raise ConstellationError(f"window n must be an integer, got {n!r}")
    if n < 3:
        raise ConstellationError(f"window n must be >= 3, got {n}")
    return int(n)


# Why sorted neighbours give exactly the C++ winner (both implementations rely on it):
# rounded subtraction is monotone, so the smallest rounded difference d is always between
# neighbours in sorted order. A zero difference means exactly equal values; a stable sort keeps
# a run of equal values in chronological order, so the run's best pair (newest, second newest)
# is its last two neighbours. A positive d cannot be tied by non-neighbours a < b < c: b − a and
# c − b are each at least d·(1 − 2⁻⁵³) exactly, so c − a rounds to about 2d. The winner is
# therefore the neighbour pair with gap d maximising (later index, earlier index) — the last
# tied pair of the C++ h-major scan — found in O(c log c) instead of O(c²).


def _closest_pair_sorted(buf: Sequence[float]) -> tuple[float, float]:
    """(midpoint, |difference|) of the C++ winner for one window of c >= 3 samples."""
    c = len(buf)
    order = sorted(range(c), key=buf.__getitem__)  # stable
    s = [buf[i] for i in order]
    gaps = list(map(operator.sub, s[1:], s[:-1]))
    d = min(gaps)
    best = -1
    for j, g in enumerate(gaps):
        if g == d:
            a, b = order[j], order[j + 1]
            code = b * c + a if b > a else a * c + b
            if code > best:
                best = code
    h, k = divmod(best, c)
    # Operand order as in the C++ (Buf[proxE1] + Buf[proxE2]) / 2, proxE1 = h > k.
    return (buf[h] + buf[k]) / 2, abs(buf[h] - buf[k])


def _closest_pairs(
    windows: npt.NDArray[np.float64],
) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
    """Per row of ``windows`` (shape (m, c), c >= 3): (midpoint, |difference|) of the winner.

    The vectorised twin of :func:`_closest_pair_sorted` (same rule, same operand order).
    """
    m, c = windows.shape
    order = np.argsort(windows, axis=1, kind="stable")
    s = np.take_along_axis(windows, order, axis=1)
    with np.errstate(over="ignore"):  # a gap across ±DBL_MAX is inf, never the minimum
        gaps = s[:, 1:] - s[:, :-1]
    d = gaps.min(axis=1, keepdims=True)
    later = np.maximum(order[:, 1:], order[:, :-1])
    earlier = np.minimum(order[:, 1:], order[:, :-1])
    best = np.where(gaps == d, later * c + earlier, -1).max(axis=1)
    h, k = np.divmod(best, c)
    rows = np.arange(m)
    bh = windows[rows, h]
    bk = windows[rows, k]
    with np.errstate(over="ignore"):  # the C++ overflows to inf near ±DBL_MAX; so do we
        return (bh + bk) / 2, np.abs(bh - bk)


class Constellation:
    """Streaming filter for one axis; see the module docstring for the exact rule.

    ``n`` is the window length (samples, >= 3). Values are in whatever unit is added
    (degrees for the robot).
    """

    __slots__ = ("_buf", "_count", "_hysteresis", "_mean", "_n")

    def __init__(self, n: int = DEFAULT_N, hysteresis: bool = False) -> None:
        self._n = _check_n(n)
        self._hysteresis = bool(hysteresis)
        self._buf: deque[float] = deque(maxlen=self._n)
        self._count = 0  # samples ever added (the C++ counter, but not capped at N)
        self._mean: float | None = None

    @property
    def n(self) -> int:
        """Window length in samples."""
        return self._n

    @property
    def hysteresis(self) -> bool:
        """Whether the (optional) hysteresis rule is on."""
        return self._hysteresis

    def __len__(self) -> int:
        """Number of samples held (at most n)."""
        return len(self._buf)

    def add(self, value: float) -> None:
        """Append one sample; the oldest is dropped once n are held (C++ ``Add``)."""
        v = float(value)
        if not math.isfinite(v):
            raise ConstellationError(f"sample must be finite, got {value!r}")
        self._buf.append(v)
        self._count += 1

    def clear(self) -> None:
        """Forget every sample and the previous output."""
        self._buf.clear()
        self._count = 0
        self._mean = None

    def filter(self) -> float:
        """The filtered value (C++ ``Filter``); raises :class:`EmptyFilterError` when empty."""
        buf = self._buf
        c = len(buf)
        if c == 0:
            raise EmptyFilterError("Constellation filter has no samples")
        if c == 1:
            mean = buf[0]
        elif c == 2:
            mean = (buf[0] + buf[1]) / 2
        else:
            cand, diff = _closest_pair_sorted(list(buf))  # list indexing beats deque
            prev = self._mean
            if (
                self._hysteresis
                and self._count > self._n
                and prev is not None
                and not abs(prev - cand) >= diff
            ):
                mean = prev
            else:
                mean = cand
        self._mean = mean
        return mean

    def average(self) -> float:
        """Arithmetic mean of the samples held (C++ ``Average``, summed oldest first)."""
        if not self._buf:
            raise EmptyFilterError("Constellation filter has no samples")
        total = 0.0
        for v in self._buf:
            total = total + v
        return total / len(self._buf)

    def buffer(self, index: int) -> float:
        """Sample ``index`` (0 = oldest held); IndexError outside 0..max_index()."""
        if not 0 <= index < len(self._buf):
            raise IndexError(f"buffer index {index} outside 0..{len(self._buf) - 1}")
        return self._buf[index]

    def max_index(self) -> int:
        """Largest valid :meth:`buffer` index (−1 when empty, as the C++ ``MaxIndex``)."""
        return len(self._buf) - 1


def filter_series(
    values: Iterable[float] | npt.NDArray[np.floating], n: int = DEFAULT_N, hysteresis: bool = False
) -> npt.NDArray[np.float64]:
    """Bit-identical to calling ``Constellation(n, hysteresis).add(v); .filter()`` per value.

    ``values`` is a 1-D sequence (e.g. degrees); returns a float64 array of the same length.
    Vectorised over sliding windows (a stable sort per window, O(len · n log n)), in chunks.
    """
    n = _check_n(n)
    x = np.asarray(values if isinstance(values, np.ndarray) else list(values), dtype=float)
    if x.ndim != 1:
        raise ConstellationError(f"values must be one-dimensional, got shape {x.shape}")
    if not np.all(np.isfinite(x)):
        bad = int(np.flatnonzero(~np.isfinite(x))[0])
        raise ConstellationError(f"sample {bad} must be finite, got {x[bad]!r}")
    length = x.shape[0]
    out = np.empty(length, dtype=float)
    diff = np.zeros(length, dtype=float)
    if length >= 1:
        out[0] = x[0]
    if length >= 2:
        out[1] = (float(x[0]) + float(x[1])) / 2
    # Partial windows (3 .. n-1 samples): few, each its own pair set.
    for c in range(3, min(n, length + 1)):
        m, d = _closest_pairs(x[:c].reshape(1, c))
        out[c - 1], diff[c - 1] = m[0], d[0]
    if length >= n:
        windows = np.lib.stride_tricks.sliding_window_view(x, n)
        step = max(1, _CHUNK_ELEMENTS // n)
        for s in range(0, windows.shape[0], step):
            m, d = _closest_pairs(windows[s : s + step])
            out[n - 1 + s : n - 1 + s + m.shape[0]] = m
            diff[n - 1 + s : n - 1 + s + m.shape[0]] = d
    if hysteresis and length > n:
        # Sequential by nature: each output depends on the previous one.
        prev = float(out[n - 1])
        res = out.tolist()
        dl = diff.tolist()
        for i in range(n, length):
            cand = res[i]
            if not abs(prev - cand) >= dl[i]:
                res[i] = prev
            prev = res[i]
        out = np.asarray(res, dtype=float)
    return out
