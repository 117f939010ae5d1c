"""Text built column by column with numpy: many rows of ASCII at once, no Python per row.

A *block* is a (rows, width) ``uint8`` array holding one ASCII text per row, with NUL bytes
where a text is shorter than the block (at its end, or inside: a number narrower than its
column leaves NULs in front of it). Blocks put side by side (:func:`joined`) are texts
concatenated row by row; removing every NUL (:func:`compact`) turns the rows into one text.
The receiver engine writes its NMEA sentences and its recording's lines this way, a chunk of
an hour at a time: its texts never contain NUL.

Numbers come out exactly as Python's own formatting prints them (``f"{x:02d}"``,
``f"{x:.3f}"``, ``repr``); the tests compare them value by value.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np


def text_block(texts: Sequence[str]) -> np.ndarray:
    """ASCII ``texts`` as a block (rows NUL-padded to the longest; width at least 1)."""
    width = max(1, max(map(len, texts), default=1))
    return np.array(texts, dtype=f"S{width}").view(np.uint8).reshape(len(texts), width)


def const_block(text: str, rows: int) -> np.ndarray:
    """``text`` on every one of ``rows`` rows (a read-only broadcast view)."""
    return np.broadcast_to(np.frombuffer(text.encode("ascii"), dtype=np.uint8), (rows, len(text)))


def widened(block: np.ndarray, width: int) -> np.ndarray:
    """``block`` with NUL columns added up to ``width`` (itself when it is that wide)."""
    if block.shape[1] >= width:
        return block
    pad = np.zeros((block.shape[0], width - block.shape[1]), dtype=np.uint8)
    return np.concatenate((block, pad), axis=1)


def put_texts(block: np.ndarray, rows: np.ndarray, texts: Sequence[bytes]) -> np.ndarray:
    """``block`` (widened if needed) with rows ``rows`` replaced by ``texts``."""
    block = widened(block, max(map(len, texts), default=0))
    block[rows] = 0
    for row, text in zip(rows.tolist(), texts, strict=True):
        block[row, : len(text)] = np.frombuffer(text, dtype=np.uint8)
    return block


def int_block(values: np.ndarray, width: int) -> np.ndarray:
    """Integers 0..10**width - 1 as ``width`` zero-padded decimal digits (``f"{x:0{w}d}"``)."""
    v = np.asarray(values, dtype=np.int64)
    if v.size and (v.min() < 0 or v.max() >= 10**width):
        raise ValueError(f"integers outside 0..{10**width - 1}")
    out = np.empty((v.shape[0], width), dtype=np.uint8)
    for k in range(width - 1, -1, -1):
        v, digit = np.divmod(v, 10)
        out[:, k] = digit + 48
    return out


def uint_block(values: np.ndarray) -> np.ndarray:
    """Non-negative integers in decimal without leading zeros (``str(x)``), NUL in front of
    the shorter ones."""
    v = np.asarray(values, dtype=np.int64)
    width = len(str(int(v.max()))) if v.size else 1
    out = int_block(v, width)
    for c in range(width - 1):
        out[v < 10 ** (width - 1 - c), c] = 0
    return out


def fixed_block(values: np.ndarray, decimals: int) -> np.ndarray:
    """``f"{v:.{decimals}f}"`` (``decimals`` >= 1) of every value, as a block.

    The digits are those of ``|v| * 10**decimals`` rounded half to even, which is Python's
    exact decimal rounding wherever that product is not within 1e-6 of a half: below 2**31
    its own rounding error is under 2**-22, so it cannot cross one. Those near-halves,
    non-finite and larger values are formatted by Python."""
    v = np.asarray(values, dtype=float)
    scale = 10**decimals
    with np.errstate(invalid="ignore", over="ignore"):
        x = np.abs(v) * scale
        exact = np.isfinite(x) & (x < 2.0**31)
        exact &= np.abs(x - np.floor(x) - 0.5) > 1e-6
    q = np.rint(np.where(exact, x, 0.0)).astype(np.int64)
    whole, frac = np.divmod(q, scale)
    sign = np.where(np.signbit(v), ord("-"), 0).astype(np.uint8)[:, None]
    point = const_block(".", v.shape[0])
    out = np.concatenate((sign, uint_block(whole), point, int_block(frac, decimals)), axis=1)
    odd = np.flatnonzero(~exact)
    if odd.size:
        texts = [f"{x:.{decimals}f}".encode("ascii") for x in v[odd].tolist()]
        out = put_texts(out, odd, texts)
    return out


def joined(blocks: Sequence[np.ndarray]) -> np.ndarray:
    """Blocks side by side: each row's texts concatenated (one new array)."""
    return np.concatenate(blocks, axis=1)


def filled(template: str, blocks: Sequence[np.ndarray], rows: int) -> np.ndarray:
    """``template % texts`` row by row: the template's constant pieces and one block per
    ``%s`` side by side (no other ``%`` allowed)."""
    pieces = template.split("%s")
    if len(pieces) != len(blocks) + 1 or "%" in "".join(pieces):
        raise ValueError(f"template {template!r} does not take {len(blocks)} texts")
    parts: list[np.ndarray] = []
    for i, piece in enumerate(pieces):
        if piece:
            parts.append(const_block(piece, rows))
        if i < len(blocks):
            parts.append(blocks[i])
    if not parts:
        return np.zeros((rows, 0), dtype=np.uint8)
    return joined(parts)


def compact(block: np.ndarray, table: bytes | None = None, delete: bytes = b"\0") -> bytes:
    """All rows' texts, one after the other, every NUL removed (``bytes.translate``: also
    the bytes of ``delete``, and the others mapped through ``table`` if given)."""
    return np.ascontiguousarray(block).tobytes().translate(table, delete)


def day_texts(days: np.ndarray, text: Callable[[int], str]) -> np.ndarray:
    """``text(d)`` for every whole day number in ``days``, as a block: computed once per day
    between the least and the greatest (a chunk spans one or two)."""
    d = np.asarray(days, dtype=np.int64)
    if not d.size:
        return np.zeros((0, 1), dtype=np.uint8)
    d0 = int(d.min())
    span = int(d.max()) - d0 + 1
    if span > d.size:  # scattered days: one text per distinct day
        unique, inverse = np.unique(d, return_inverse=True)
        return text_block([text(x) for x in unique.tolist()])[inverse.reshape(-1)]
    return text_block([text(d0 + k) for k in range(span)])[d - d0]
