"""The detection-ceiling benchmark's statistics (bench/bench_gap_ceiling.py): every
candidate is what its name says, so the figures it prints name the statistic they used."""

from __future__ import annotations

import math

import numpy as np

from bench.bench_gap_ceiling import _candidate_name, _candidates
from x6wd.gap.stats import Cell


def test_each_candidate_is_the_statistic_its_name_gives() -> None:
    cells = [Cell("mean", "east"), Cell("mean", "north"), Cell("log_adev", "east", "tau=64s")]
    z = np.array([[1.0, -2.0, 0.5], [3.0, 4.0, -1.0]])
    got = _candidates(z)
    assert got.shape == (2, 3 + 3 * 3)  # 3 cells, 3 pairs in 3 forms
    by_name = {_candidate_name(cells, i): got[:, i] for i in range(got.shape[1])}
    assert len(by_name) == got.shape[1]
    np.testing.assert_allclose(by_name["|z| mean/north/all/all"], [2.0, 4.0])
    both = "mean/east/all/all, mean/north/all/all"
    np.testing.assert_allclose(by_name[f"|z1 + z2|: {both}"], np.abs([-1.0, 7.0]) / math.sqrt(2))
    np.testing.assert_allclose(by_name[f"|z1 - z2|: {both}"], np.abs([3.0, -1.0]) / math.sqrt(2))
    np.testing.assert_allclose(by_name[f"z1^2 + z2^2: {both}"], [5.0, 25.0])


def test_a_missing_cell_counts_as_no_departure() -> None:
    got = _candidates(np.array([[np.nan, 2.0]]))
    np.testing.assert_allclose(got, [[0.0, 2.0, 2 / math.sqrt(2), 2 / math.sqrt(2), 4.0]])
