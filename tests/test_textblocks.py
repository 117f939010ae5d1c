"""Text built with numpy (sim_backend.textblocks) against Python's own formatting, value by
value: what the receiver engine's NMEA text and recording lines are made of."""

from __future__ import annotations

import math

import numpy as np
import pytest

from sim_backend.textblocks import (
    compact,
    const_block,
    day_texts,
    filled,
    fixed_block,
    int_block,
    put_texts,
    text_block,
    uint_block,
)


def _texts(block: np.ndarray) -> list[str]:
    return [row.tobytes().replace(b"\0", b"").decode("ascii") for row in block]


EDGES = [
    0.0, -0.0, 0.5, 1.5, 2.5, -2.5, 0.125, 0.375, 1.005, 2.675, 0.0005, 0.0015, 9.9995,
    99.995, 99.99, 1e-300, -1e-300, 5e-324, 123456.7895, 2.0**31 / 1000, 2.0**40, 1e300,
    math.nan, math.inf, -math.inf, 0.045, -0.045, 359.995, 1e-7,
]  # fmt: skip


@pytest.mark.parametrize("decimals", [1, 2, 3])
def test_fixed_decimals_are_pythons(decimals: int) -> None:
    rng = np.random.default_rng(decimals)
    values = EDGES + rng.uniform(-1000, 1000, 4000).tolist()
    values += (rng.integers(-(10**6), 10**6, 2000) / 10 ** (decimals + 1)).tolist()  # exact ties
    values += (rng.integers(0, 10**5, 2000) / 2 ** rng.integers(1, 12, 2000)).tolist()
    got = _texts(fixed_block(np.array(values), decimals))
    assert got == [f"{v:.{decimals}f}" for v in values]


def test_integers_with_and_without_zeros() -> None:
    v = np.array([0, 7, 42, 99, 100, 12345, 99999])
    assert _texts(int_block(v, 5)) == [f"{x:05d}" for x in v.tolist()]
    assert _texts(uint_block(v)) == [str(x) for x in v.tolist()]
    assert _texts(uint_block(np.array([0, 0]))) == ["0", "0"]
    with pytest.raises(ValueError, match="outside"):
        int_block(np.array([100]), 2)


def test_blocks_side_by_side_and_compacted() -> None:
    n = 3
    a = text_block(["1", "22", ""])
    block = filled("$%s,%s*", [a, const_block("x", n)], n)
    assert _texts(block) == ["$1,x*", "$22,x*", "$,x*"]
    assert compact(block) == b"$1,x*$22,x*$,x*"
    assert compact(block, bytes(range(256)).replace(b"*", b"\n"), b"\0$") == b"1,x\n22,x\n,x\n"
    assert _texts(put_texts(a.copy(), np.array([1]), [b"longer"])) == ["1", "longer", ""]
    with pytest.raises(ValueError, match="does not take"):
        filled("%s %s", [a], n)


def test_day_texts_once_per_day() -> None:
    seen: list[int] = []

    def text(d: int) -> str:
        seen.append(d)
        return f"d{d}"

    assert _texts(day_texts(np.array([5, 5, 6, 6, 6]), text)) == ["d5", "d5", "d6", "d6", "d6"]
    assert seen == [5, 6]
    assert _texts(day_texts(np.array([1, 900, 1]), text)) == ["d1", "d900", "d1"]
