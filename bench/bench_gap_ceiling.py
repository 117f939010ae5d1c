"""What ANY test could find of ``bench_gap_paths``' effects against this simulator (issue 15,
item 2): a detection ceiling for its top-1 targets, measured on the simulator itself.

The gap tool has to find an effect of any class in a log, against ~75 cells at once, from a
few baseline logs, at a 1 % family-wise level. Here every advantage goes to the test instead:

- the null is ``--null`` (default 60) independent simulator hours, not three;
- the class is known: for each class and strength the test uses the one statistic that
  separates that class best on ``--train`` (30) injected hours, out of every cell of the
  tool's battery (``x6wd.gap.stats.battery``, z against the null's mean and spread) and
  every pair of cells (their signed sum, or the sum of their squares: both means at once);
- that statistic alone is tested, at ``--alpha`` (default 1 %, the tool's family-wise
  level) against its own quantile on ``--calib`` (300) further no-effect hours (the
  simulator's hours are heavier-tailed than Gaussian: a Gaussian limit flagged 4-17 % of
  them). The rate at which it flags the test's no-effect hours is printed beside it.

Its power on ``--test`` other injected hours bounds the top-1 of any tool from above: a log
that this test cannot tell from no effect, no tool names right more often than chance.
The effects, their strengths and the scenario are ``bench_gap_paths``' (one static hour at
1 Hz on open sky, the NEO-5 settings); seeds 5,000,000 and up, disjoint from its.
Run: ``python -m bench.bench_gap_ceiling [--quick]``.
"""

from __future__ import annotations

import argparse
import itertools
import math
import time
from concurrent.futures import ProcessPoolExecutor

import numpy as np

from bench._common import Row, print_table, upper95
from bench.bench_gap_paths import KINDS, TOOL_NAME, _sim, inject
from sim_backend.effects import PositionSeries
from x6wd.gap.diagnose import RW_LR_CELL
from x6wd.gap.drift import random_walk_lr
from x6wd.gap.noise import NoiseModel, noise_model
from x6wd.gap.stats import Cell, battery, layout_for

SEED_NULL, SEED_CALIB, SEED_TRAIN, SEED_TEST = 5_000_000, 5_050_000, 5_100_000, 5_200_000
LEVELS = ("moderate", "strong")
TARGET = {"moderate": 0.90, "strong": 0.97}  # issue 15's top-1 targets


def _hours(seed0: int, n: int) -> list[PositionSeries]:
    with ProcessPoolExecutor(max_workers=2) as ex:
        return list(ex.map(_one_hour, range(seed0, seed0 + n)))


def _one_hour(seed: int) -> PositionSeries:
    return _sim([seed])[0]


def _cells_of(s: PositionSeries, cells: list[Cell], model: NoiseModel) -> list[float]:
    b = battery(s, layout_for(s))
    b[RW_LR_CELL] = random_walk_lr(s, model)  # the tool's own walk statistic, whole log
    return [b.get(c, np.nan) for c in cells]


def _battery_rows(series: list[PositionSeries], cells: list[Cell], model: NoiseModel) -> np.ndarray:
    with ProcessPoolExecutor(max_workers=2) as ex:
        rows = ex.map(_cells_of, series, itertools.repeat(cells), itertools.repeat(model))
        return np.array(list(rows), dtype=float)


def _injected(
    hours: list[PositionSeries], kind: str, level: str, seed0: int
) -> list[PositionSeries]:
    rngs = (np.random.default_rng(seed0 + i) for i in range(len(hours)))
    return [inject(s, kind, level, rng)[0] for s, rng in zip(hours, rngs, strict=True)]


def _candidates(z: np.ndarray) -> np.ndarray:
    """Every statistic the test may pick, per hour (rows): each cell's |z|, each pair's
    signed sums |z_j +- z_k| / sqrt(2) and each pair's z_j^2 + z_k^2 (a bias in any
    direction: both means at once)."""
    z = np.nan_to_num(z)
    j, k = np.triu_indices(z.shape[1], 1)
    a, b = z[:, j], z[:, k]
    return np.hstack(
        [np.abs(z), np.abs(a + b) / math.sqrt(2.0), np.abs(a - b) / math.sqrt(2.0), a * a + b * b]
    )


def _candidate_name(cells: list[Cell], i: int) -> str:
    def one(n: int) -> str:
        c = cells[n]
        return f"{c.statistic}/{c.axis}/{c.scale}/{c.period}"

    n_cells = len(cells)
    if i < n_cells:
        return f"|z| {one(i)}"
    j, k = np.triu_indices(n_cells, 1)
    kind, pair = divmod(i - n_cells, j.size)
    form = ("|z1 + z2|", "|z1 - z2|", "z1^2 + z2^2")[kind]
    return f"{form}: {one(int(j[pair]))}, {one(int(k[pair]))}"


def run(
    quick: bool = False,
    n_null: int = 60,
    n_calib: int = 300,
    n_train: int = 30,
    n_test: int = 60,
    alpha: float = 0.01,
) -> list[Row]:
    """Every class's detection ceiling at each strength, and their means against the
    top-1 targets."""
    if quick:
        n_null, n_calib, n_train, n_test = 24, 100, 12, 24
    t0 = time.perf_counter()
    null = _hours(SEED_NULL, n_null)
    calib = _hours(SEED_CALIB, n_calib)
    train = _hours(SEED_TRAIN, n_train)
    test = _hours(SEED_TEST, n_test)
    # the walk's likelihood ratio reads the no-effect hours' noise law, fitted on them all
    model = noise_model(null, layout_for(null[0]))
    cells = [*battery(null[0], layout_for(null[0])), RW_LR_CELL]
    b_null = _battery_rows(null, cells, model)
    keep = np.all(np.isfinite(b_null), axis=0)
    cells = [c for c, k in zip(cells, keep, strict=True) if k]
    b_null = b_null[:, keep]
    mean, sd = b_null.mean(axis=0), np.maximum(b_null.std(axis=0, ddof=1), 1e-9)

    def zs(series: list[PositionSeries]) -> np.ndarray:
        return (_battery_rows(series, cells, model) - mean) / sd

    # each candidate's limit: its own (1 - alpha) quantile on no-effect hours of their own
    limits = np.quantile(_candidates(zs(calib)), 1.0 - alpha, axis=0)
    clean = _candidates(zs(test))
    rows: list[Row] = []
    for level in LEVELS:
        powers = []
        for n, kind in enumerate(KINDS):
            seed = 1000 * n + (0 if level == "moderate" else 500)
            s_train = _candidates(zs(_injected(train, kind, level, SEED_TRAIN + seed)))
            passed = s_train > limits
            ratio = np.divide(s_train, limits, out=np.zeros_like(s_train), where=limits > 0)
            margin = np.median(np.minimum(ratio, 100.0), axis=0)
            pick = int(np.argmax(passed.mean(axis=0) + 1e-3 * margin))  # ties: the wider margin
            s_test = _candidates(zs(_injected(test, kind, level, SEED_TEST + seed)))[:, pick]
            power = float(np.mean(s_test > limits[pick]))
            false_alarm = float(np.mean(clean[:, pick] > limits[pick]))
            powers.append(power)
            rows.append(Row("gap_ceiling", f"{level} {TOOL_NAME.get(kind, kind)}: detection "
                            "ceiling", power, "fraction", None, "",
                            f"{_candidate_name(cells, pick)}; flags {false_alarm:.0%} of the "
                            "test's no-effect hours"))  # fmt: skip
        ceiling = float(np.mean(powers))
        found = round(ceiling * n_test * len(KINDS))
        rows.append(Row("gap_ceiling", f"{level}: mean over the {len(KINDS)} classes", ceiling,
                        "fraction", TARGET[level], "top-1 target",
                        f"{found}/{n_test * len(KINDS)}, one-sided 95 % bound "
                        f"{upper95(found, n_test * len(KINDS)):.3f}: above it, no tool's "
                        "top-1"))  # fmt: skip
    rows.append(Row("gap_ceiling", "wall time", time.perf_counter() - t0, "s", None, "",
                    f"null {n_null}, limits {n_calib}, train {n_train}, test {n_test} hours, "
                    f"alpha {alpha}"))  # fmt: skip
    return rows


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0], allow_abbrev=False)
    ap.add_argument("--quick", action="store_true", help="24 / 100 / 12 / 24 hours")
    ap.add_argument("--null", type=int, default=60, help="no-effect hours: each cell's z")
    ap.add_argument("--calib", type=int, default=300, help="no-effect hours: each limit")
    ap.add_argument("--train", type=int, default=30, help="hours that choose each statistic")
    ap.add_argument("--test", type=int, default=60, help="hours that measure its power")
    ap.add_argument("--alpha", type=float, default=0.01, help="two-sided level of the one test")
    a = ap.parse_args()
    print_table(run(a.quick, a.null, a.calib, a.train, a.test, a.alpha))
