"""Constellation filter speed: streaming (per fix, as on the robot) vs the vectorised series.

Input: NMEA-like latitudes around 51.7 deg on the 1e-5-minute lattice with time-correlated
noise (many exact ties, as real receivers give). Streaming is ``add`` + ``filter`` per sample
with N = 20; the series form filters the whole array in one call. The anchor of the series
rate is the streaming rate, so the ratio is the speed-up of the vectorised form. For scale,
the seed's O(N²) scan written plainly in Python is timed too (anchor: the streaming time).
Run: ``python -m bench.bench_filter`` or ``python bench/run.py --only filter``.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable

import numpy as np

from bench._common import Row, cli, print_table
from x6wd.nav.constellation import Constellation, filter_series

N = 20
NMEA_STEP_DEG = 1e-5 / 60


def _latitudes(count: int, seed: int = 1) -> list[float]:
    rng = np.random.default_rng(seed)
    # first-order Gauss-Markov, sigma 1.5 m, tau 60 s at 1 Hz, quantised like NMEA
    phi = math.exp(-1 / 60)
    w = rng.normal(0.0, 1.5 * math.sqrt(1 - phi * phi), count)
    e = np.empty(count)
    acc = 0.0
    for i in range(count):
        acc = phi * acc + w[i]
        e[i] = acc
    deg = 51.7 + e / 111_000.0
    return list(51.7 + np.round((deg - 51.7) / NMEA_STEP_DEG) * NMEA_STEP_DEG)


def _best_of(repeats: int, fn: Callable[[], object]) -> float:
    best = math.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def _stream(values: list[float]) -> None:
    f = Constellation(N)
    for v in values:
        f.add(v)
        f.filter()


def _scan_cpp(values: list[float]) -> None:
    """The C++ Filter() loop as written, over a shifting buffer (the seed's cost model)."""
    buf: list[float] = []
    for v in values:
        buf.append(v)
        if len(buf) > N:
            del buf[0]
        c = len(buf)
        if c < 3:
            continue
        best = math.inf
        bh = bk = 0
        for h in range(c):
            for k in range(c):
                if h != k:
                    d = abs(buf[h] - buf[k])
                    if best >= d:
                        best, bh, bk = d, h, k
        _ = (buf[bh] + buf[bk]) / 2


def run(quick: bool = False) -> list[Row]:
    """Measure; ``quick`` uses smaller inputs (seconds instead of tens of seconds)."""
    n_stream = 5_000 if quick else 50_000
    n_series = 100_000 if quick else 1_000_000
    n_scan = 1_000 if quick else 5_000
    repeats = 2 if quick else 3
    stream_vals = _latitudes(n_stream)
    series_vals = np.asarray(_latitudes(n_series, seed=2))

    t_stream = _best_of(repeats, lambda: _stream(stream_vals)) / n_stream
    t_series = _best_of(repeats, lambda: filter_series(series_vals, N)) / n_series
    t_hyst = _best_of(repeats, lambda: filter_series(series_vals, N, hysteresis=True)) / n_series
    t_scan = _best_of(1, lambda: _scan_cpp(stream_vals[:n_scan])) / n_scan

    stream_rate = 1.0 / t_stream
    return [
        Row("filter", "streaming add+filter, N=20", t_stream * 1e6, "us/sample"),
        Row("filter", "streaming rate, N=20", stream_rate, "samples/s"),
        Row(
            "filter",
            "filter_series rate, N=20",
            1.0 / t_series,
            "samples/s",
            anchor=stream_rate,
            anchor_label="streaming",
            note="ratio = vectorised speed-up",
        ),
        Row(
            "filter",
            "filter_series hysteresis rate",
            1.0 / t_hyst,
            "samples/s",
            anchor=stream_rate,
            anchor_label="streaming",
        ),
        Row(
            "filter",
            "C++-style O(N^2) scan in Python",
            t_scan * 1e6,
            "us/sample",
            anchor=t_stream * 1e6,
            anchor_label="streaming",
            note="ratio = cost of the plain port",
        ),
    ]


if __name__ == "__main__":
    cli(__doc__, quick=False).parse_args()
    print_table(run())
