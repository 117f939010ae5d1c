"""A static survey's ``track.png`` drawn with Pillow and numpy, without matplotlib.

The receiver engine (:mod:`sim_backend.survey`) plots what :func:`sim_backend.runs.plot_track`
plots for a robot that stands still: the walls and roofs, the raw fixes (red dots, 60 %
opaque), the true position (a blue plus), in scenario ENU metres on equal scales, with ticks,
grid, axis labels, the legend where it hides the fewest points, and the run's title; the same
layout (7 x 7 in at 100 dpi, matplotlib's default margins, DejaVu Sans). Importing matplotlib
alone took a 10 h survey about a fifth of its CPU time; Pillow (which matplotlib itself writes
PNGs with) takes a few hundredths of a second. Without matplotlib's font file or Pillow's
FreeType, :func:`plot_survey` falls back to :func:`~sim_backend.runs.plot_track`.
"""

from __future__ import annotations

import importlib.util
import math
import struct
import zlib
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from sim_backend.runs import Summary, plot_track
from sim_backend.world import World

_SIZE = 700  # px: 7 in at 100 dpi
_PX_PER_PT = 100 / 72
# The axes box (px): matplotlib's default subplot, left 0.125, right 0.9, bottom 0.11, top 0.88.
_LEFT, _RIGHT = 0.125 * _SIZE, 0.9 * _SIZE
_TOP, _BOTTOM = (1 - 0.88) * _SIZE, (1 - 0.11) * _SIZE
_RED = np.array([214, 39, 40], dtype=float)  # tab:red
_BLUE = (31, 119, 180)  # tab:blue
_WALL, _ROOF, _FRAME = (77, 77, 77), (217, 217, 217), (204, 204, 204)
_GRID, _GRID_ALPHA = 176.0, 0.3  # matplotlib's grid: #b0b0b0, 30 % opaque
_ALPHA = 0.6
_MINUS = "\u2212"
DOT_CHUNK = 50_000
"""Fixes turned into pixels at a time (each into nine offsets and weights, about 400 bytes a
fix: 400,000 fixes at once took 166 MB, a 720 h survey's 2.6 million would take 1 GB). The
dots' layers (whole numbers) are counted per chunk and blended once, so the picture is the
same, byte for byte, whatever the chunk."""


def plot_survey(
    path: Path, world: World, truth_en: tuple[float, float], fix_enu: np.ndarray, summary: Summary
) -> None:
    """``track.png`` at ``path`` of a survey whose antenna stood at ``truth_en`` (m, east and
    north) and reported ``fix_enu`` (N, 2+) m."""
    font_file = _font_file()
    try:
        from PIL import Image, ImageDraw, ImageFont, features

        if font_file is None or not features.check("freetype2"):
            raise ImportError("no FreeType or no DejaVu Sans")
    except ImportError:
        e, n = truth_en
        plot_track(
            path, world, np.array([e]), np.array([n]), fix_enu,
            np.full(fix_enu.shape, math.nan), np.zeros((0, 2)), summary,
        )  # fmt: skip
        return

    def font(pt: float) -> Any:
        return ImageFont.truetype(font_file, round(pt * _PX_PER_PT))

    fixes = np.asarray(fix_enu, dtype=float)[:, :2].reshape(-1, 2)
    xs = [truth_en[0]]
    ys = [truth_en[1]]
    segs = [((w.x0_m, w.y0_m), (w.x1_m, w.y1_m)) for w in world.walls]
    boxes = [(r.x0_m, r.y0_m, r.x1_m, r.y1_m) for r in world.roofs]
    for (a, b), (c, d) in segs:
        xs += [a, c]
        ys += [b, d]
    for x0, y0, x1, y1 in boxes:
        xs += [x0, x1]
        ys += [y0, y1]
    lo = np.array([min(xs), min(ys)])
    hi = np.array([max(xs), max(ys)])
    if fixes.shape[0]:
        lo = np.minimum(lo, fixes.min(axis=0))
        hi = np.maximum(hi, fixes.max(axis=0))
    x0, x1, y0, y1 = _limits(float(lo[0]), float(hi[0]), float(lo[1]), float(hi[1]))
    sx = (_RIGHT - _LEFT) / (x1 - x0)
    sy = (_BOTTOM - _TOP) / (y1 - y0)

    def px(x: Any, y: Any) -> tuple[Any, Any]:
        return _LEFT + (np.asarray(x) - x0) * sx, _BOTTOM - (np.asarray(y) - y0) * sy

    img = Image.new("RGB", (_SIZE, _SIZE), "white")
    draw = ImageDraw.Draw(img)
    clip = Image.new("RGB", (_SIZE, _SIZE), "white")  # what is drawn inside the axes box
    inner = ImageDraw.Draw(clip)
    for bx0, by0, bx1, by1 in boxes:
        (a, c), (b, d) = px([bx0, bx1], [by0, by1])
        inner.polygon([(a, b), (c, b), (c, d), (a, d)], fill=_ROOF)
    for (a, b), (c, d) in segs:
        p, q = px([a, c], [b, d])
        inner.polygon(_thick(float(p[0]), float(q[0]), float(p[1]), float(q[1]), 3 * _PX_PER_PT),
                      fill=_WALL)  # fmt: skip
    xticks, yticks = _ticks(x0, x1, 9), _ticks(y0, y1, 9)
    grid = Image.new("L", (_SIZE, _SIZE), 0)  # over the walls: 30 % opaque
    lines = ImageDraw.Draw(grid)
    for v in xticks:
        a = float(px(v, y0)[0])
        lines.line([(a, _TOP), (a, _BOTTOM)], fill=255, width=1)
    for v in yticks:
        b = float(px(x0, v)[1])
        lines.line([(_LEFT, b), (_RIGHT, b)], fill=255, width=1)
    pixels = np.array(clip, dtype=np.uint8)
    on = np.asarray(grid) > 0
    pixels[on] = np.rint(pixels[on] * (1 - _GRID_ALPHA) + _GRID * _GRID_ALPHA).astype(np.uint8)
    if fixes.shape[0]:
        counts = np.zeros(pixels.shape[0] * pixels.shape[1])
        for k in range(0, fixes.shape[0], DOT_CHUNK):
            u, v = px(fixes[k : k + DOT_CHUNK, 0], fixes[k : k + DOT_CHUNK, 1])
            iu, iv = np.rint(u).astype(np.int64), np.rint(v).astype(np.int64)
            counts += _dot_layers(pixels.shape, iu, iv)
        pixels = _blend(pixels, counts)
    clip = Image.fromarray(pixels, "RGB")
    inner = ImageDraw.Draw(clip)
    tx, ty = px(truth_en[0], truth_en[1])
    _plus(inner, float(tx), float(ty), 12 * _PX_PER_PT, _BLUE)
    box = (round(_LEFT), round(_TOP), round(_RIGHT), round(_BOTTOM))
    img.paste(clip.crop(box), box[:2])
    # frame, ticks and their labels
    draw.rectangle(box, outline=(0, 0, 0), width=1)
    tick_font, tick_len = font(10), round(3.5 * _PX_PER_PT)
    for v, text in zip(xticks, _labels(xticks), strict=True):
        a = round(float(px(v, y0)[0]))
        draw.line([(a, box[3]), (a, box[3] + tick_len)], fill=(0, 0, 0), width=1)
        draw.text((a, box[3] + 2 * tick_len), text, font=tick_font, fill=(0, 0, 0), anchor="mt")
    for v, text in zip(yticks, _labels(yticks), strict=True):
        b = round(float(px(x0, v)[1]))
        draw.line([(box[0] - tick_len, b), (box[0], b)], fill=(0, 0, 0), width=1)
        draw.text((box[0] - 2 * tick_len, b), text, font=tick_font, fill=(0, 0, 0), anchor="rm")
    label_font = font(10)
    draw.text(
        ((_LEFT + _RIGHT) / 2, box[3] + 2 * tick_len + 19), "east (m)",
        font=label_font, fill=(0, 0, 0), anchor="mt",
    )  # fmt: skip
    widest = max((draw.textlength(t, font=tick_font) for t in _labels(yticks)), default=0.0)
    ylabel = Image.new("RGBA", (200, 30), (255, 255, 255, 0))
    ImageDraw.Draw(ylabel).text((100, 15), "north (m)", font=label_font, fill="black", anchor="mm")
    ylabel = ylabel.rotate(90, expand=True)
    img.paste(
        ylabel,
        (round(box[0] - 2 * tick_len - widest - 13 - 15), round((_TOP + _BOTTOM) / 2 - 100)),
        ylabel,
    )
    filt = summary.filtered_error.cep50_m
    title = (
        f"{world.name} (seed {summary.seed})\n{summary.waypoints_reached}/"
        f"{summary.waypoint_count} waypoints, raw CEP50 {summary.raw_error.cep50_m:.1f} m"
        + (f", filtered CEP50 {filt:.1f} m" if math.isfinite(filt) else "")
    )
    draw.multiline_text(
        ((_LEFT + _RIGHT) / 2, _TOP - 6 * _PX_PER_PT), title, font=font(9), fill=(0, 0, 0),
        anchor="md", align="center", spacing=2,
    )  # fmt: skip

    def inside(x: float, y: float, w: int, h: int) -> int:
        """The fixes whose points are in the box of (x, y) and size (w, h) px."""
        n = 0
        for k in range(0, fixes.shape[0], DOT_CHUNK):
            a, b = px(fixes[k : k + DOT_CHUNK, 0], fixes[k : k + DOT_CHUNK, 1])
            n += int(np.count_nonzero((a >= x) & (a <= x + w) & (b >= y) & (b <= y + h)))
        return n

    _legend(img, font(8), inside, box)
    Path(path).write_bytes(_png(np.asarray(img)))


def _png(rgb: np.ndarray) -> bytes:
    """An (H, W, 3) uint8 image as PNG bytes: 8-bit RGB, no row filter, deflated by zlib
    (Pillow's own writer loads its other image plugins first, a third of its import)."""
    h, w = rgb.shape[:2]
    rows = np.zeros((h, 1 + 3 * w), dtype=np.uint8)  # a 0 (no filter) before each row
    rows[:, 1:] = rgb.reshape(h, 3 * w)

    def chunk(kind: bytes, data: bytes) -> bytes:
        return (
            struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))
        )

    header = struct.pack(">IIBBBBB", w, h, 8, 2, 0, 0, 0)  # 8 bits, RGB, deflate, no interlace
    return (
        b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header)
        + chunk(b"IDAT", zlib.compress(rows.tobytes(), 3)) + chunk(b"IEND", b"")
    )  # fmt: skip


def _font_file() -> str | None:
    """matplotlib's DejaVu Sans (found without importing matplotlib), or None."""
    spec = importlib.util.find_spec("matplotlib")
    for root in (spec.submodule_search_locations or []) if spec else []:
        file = Path(root) / "mpl-data" / "fonts" / "ttf" / "DejaVuSans.ttf"
        if file.is_file():
            return str(file)
    return None


def _limits(x0: float, x1: float, y0: float, y1: float) -> tuple[float, float, float, float]:
    """Data limits with matplotlib's 5 % margins, widened to equal scales in the axes box
    (``set_aspect("equal", adjustable="datalim")``)."""
    dx, dy = max(x1 - x0, 1e-9), max(y1 - y0, 1e-9)
    if x1 - x0 <= 0 and y1 - y0 <= 0:  # one point: matplotlib's +-0.055 around it
        dx = dy = 0.1
        x0, y0 = x0 - 0.05, y0 - 0.05
    x0, x1, y0, y1 = x0 - 0.05 * dx, x0 + 1.05 * dx, y0 - 0.05 * dy, y0 + 1.05 * dy
    box_w, box_h = _RIGHT - _LEFT, _BOTTOM - _TOP
    per_px = max((x1 - x0) / box_w, (y1 - y0) / box_h)
    cx, cy = (x0 + x1) / 2, (y0 + y1) / 2
    return (
        cx - per_px * box_w / 2,
        cx + per_px * box_w / 2,
        cy - per_px * box_h / 2,
        cy + per_px * box_h / 2,
    )


def _ticks(lo: float, hi: float, bins: int) -> list[float]:
    """Tick values in [lo, hi] at the least step of 1, 2, 2.5, 5 or 10 times a power of ten
    that is at least (hi - lo) / ``bins`` (matplotlib's AutoLocator)."""
    raw = (hi - lo) / bins
    if not raw > 0:
        return [lo]
    scale = 10.0 ** math.floor(math.log10(raw))
    step = next(m * scale for m in (1.0, 2.0, 2.5, 5.0, 10.0) if m * scale >= raw * (1 - 1e-9))
    first, last = math.ceil(lo / step - 1e-9), math.floor(hi / step + 1e-9)
    return [i * step for i in range(first, last + 1)]


def _labels(ticks: list[float]) -> list[str]:
    """Tick texts with the decimals the steps need (a minus sign for negatives)."""
    decimals = 0
    while decimals < 6 and any(
        abs(v * 10**decimals - round(v * 10**decimals)) > 1e-6 for v in ticks
    ):
        decimals += 1
    out = []
    for v in ticks:
        text = f"{abs(v):.{decimals}f}"
        out.append((_MINUS + text) if v < 0 and float(text) != 0 else text)
    return out


def _dot_layers(shape: tuple[int, ...], u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Per pixel of an image of ``shape`` (H, W, ...), flattened: the layers of the 3 x 3 px
    dots at (u, v) px on it (whole numbers, so that chunks add up exactly)."""
    h, w = shape[:2]
    du, dv = np.meshgrid([-1, 0, 1], [-1, 0, 1])
    # a dot's face and its edge, both 60 % opaque, cover its middle twice (matplotlib's '.')
    twice = np.where(du * dv == 0, 2.0, 1.0).ravel()
    uu = (u[:, None] + du.ravel()[None, :]).ravel()
    vv = (v[:, None] + dv.ravel()[None, :]).ravel()
    weight = np.broadcast_to(twice, (u.shape[0], 9)).ravel()
    inside = (uu >= _LEFT) & (uu < _RIGHT) & (vv >= _TOP) & (vv < _BOTTOM)
    return np.bincount(vv[inside] * w + uu[inside], weights=weight[inside], minlength=h * w)


def _blend(pixels: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """``pixels`` (H, W, 3 uint8) under ``counts`` layers of red 60 % opaque per pixel."""
    h, w = pixels.shape[:2]
    hit = np.flatnonzero(counts)
    keep = ((1.0 - _ALPHA) ** counts[hit])[:, None]
    flat = pixels.reshape(h * w, 3)
    flat[hit] = np.rint(flat[hit] * keep + _RED * (1.0 - keep)).astype(np.uint8)
    return pixels


def _thick(x0: float, y0: float, x1: float, y1: float, width: float) -> list[tuple[float, float]]:
    """The outline of a line ``width`` px wide from (x0, y0) to (x1, y1) with projecting caps
    (matplotlib's for solid lines): half the width past each end."""
    length = math.hypot(x1 - x0, y1 - y0) or 1.0
    ux, uy = (x1 - x0) / length * width / 2, (y1 - y0) / length * width / 2
    return [(x0 - ux - uy, y0 - uy + ux), (x1 + ux - uy, y1 + uy + ux),
            (x1 + ux + uy, y1 + uy - ux), (x0 - ux + uy, y0 - uy - ux)]  # fmt: skip


def _plus(draw: Any, x: float, y: float, size: float, color: tuple[int, int, int]) -> None:
    """matplotlib's filled plus marker ('P') of ``size`` px at (x, y), white-edged."""
    a, b = size / 6, size / 2
    shape = [(-a, -b), (a, -b), (a, -a), (b, -a), (b, a), (a, a), (a, b), (-a, b), (-a, a),
             (-b, a), (-b, -a), (-a, -a)]  # fmt: skip
    draw.polygon([(x + p, y + q) for p, q in shape], fill=color, outline=(255, 255, 255))


def _legend(
    img: Any,
    font: Any,
    inside: Callable[[float, float, int, int], int],
    box: tuple[int, int, int, int],
) -> None:
    """The legend (raw GPS, true position) where it covers the fewest points (``inside(x,
    y, w, h)``: those in a box), in matplotlib's order of places to try."""
    from PIL import ImageDraw

    draw = ImageDraw.Draw(img)
    rows = ("raw GPS", "true position")
    em = font.size
    text_w = max(draw.textlength(t, font=font) for t in rows)
    w = round(0.4 * em + 2 * em + 0.8 * em + text_w + 0.4 * em)
    h = round(0.4 * em + len(rows) * em + (len(rows) - 1) * 0.5 * em + 0.4 * em)
    gap = round(0.5 * em)
    left, top, right, bottom = box
    xs = {"l": left + gap, "c": (left + right - w) // 2, "r": right - gap - w}
    ys = {"u": top + gap, "c": (top + bottom - h) // 2, "l": bottom - gap - h}
    places = ["ur", "ul", "ll", "lr", "cr", "cl", "cr", "lc", "uc", "cc"]
    best = None
    for place in places:
        x, y = xs[place[1]], ys[place[0]]
        covered = inside(x, y, w, h)
        if best is None or covered < best[0]:
            best = (covered, x, y)
    assert best is not None
    _, x, y = best
    draw.rounded_rectangle((x, y, x + w, y + h), radius=3, fill=(255, 255, 255), outline=_FRAME)
    cx = x + 0.4 * em + em
    for i, text in enumerate(rows):
        cy = y + 0.4 * em + i * 1.5 * em + em / 2
        if i == 0:
            draw.ellipse((cx - 1.5, cy - 1.5, cx + 1.5, cy + 1.5), fill=tuple(_RED.astype(int)))
        else:
            _plus(draw, cx, cy, 12 * _PX_PER_PT, _BLUE)
        draw.text((cx + em + 0.8 * em, cy), text, font=font, fill=(0, 0, 0), anchor="lm")
