"""Buildings: line of sight and wall reflections for satellites at infinity (plane waves).

PUBLIC API
- ``Window(u0_m, u1_m, z0_m, z1_m)``: an opening through a wall; ``u`` is the distance along
  the wall's centreline from its start point (x0, y0), ``z`` the height above ground.
- ``Wall(x0_m, y0_m, x1_m, y1_m, thickness_m=0.3, height_m=10.0, windows=(),
  penetration_db=None, refractive_index=1.0)``: a vertical box standing on the ground
  (z = 0); the centreline runs (x0, y0) -> (x1, y1) in the local ENU frame (x east, y north,
  metres); the box extends ``thickness_m / 2`` to each side.
- ``Hole(x0_m, y0_m, x1_m, y1_m)`` and ``Roof(x0_m, y0_m, x1_m, y1_m, height_m, holes=(),
  penetration_db=None, thickness_m=0.0, refractive_index=1.0)``: a thin horizontal slab
  (axis-aligned rectangle in ENU) at ``height_m`` with open rectangles; it blocks rays from
  below that cross it outside its holes. Roofs do not reflect.
- Materials (optional, default off): ``penetration_db`` is the L1 loss of one crossing
  (None: opaque, the seed's model); ``refractive_index`` n gives the extra delay
  (n - 1) x the path length inside (a roof's ``thickness_m`` is used only for that).
- ``building(x0_m, y0_m, x1_m, y1_m, height_m, thickness_m=0.3, penetration_db=None,
  refractive_index=1.0) -> list[Wall]``: the four walls of an axis-aligned rectangular
  building (closed, no windows, one material).
- ``Walls(walls, roofs=(), max_directions=4096)`` with
  ``trace(rx_enu_m, az_deg, el_deg, max_reflections=16, max_loss_db=None) -> TraceResult``
  (``visibility(rx_enu_m, az_deg, el_deg)`` is the same with default limits):
  ``rx_enu_m`` is (3,) or (E, 3) (up = antenna height above ground, metres), ``az_deg`` /
  ``el_deg`` are (E, S) or (S,) (azimuth clockwise from north); ``max_loss_db`` is one
  number or an array broadcastable to (E, S) (a loss budget per ray). Everything is
  vectorised over rays x walls; the Python loops run only over reflection depth.
- ``TraceResult``: arrays of the broadcast shape (E, S): ``los`` (bool, direct path clear),
  ``n_reflections`` (int: 0 direct, 1..16 reflections, -1 no viable path = invisible),
  ``extra_path_m`` (range error of the path taken, 0 when direct or invisible),
  ``loss_db`` (3 dB per reflection, the summed material loss through obstructions, ``inf``
  when invisible), ``n_penetrations`` (obstructions a through path crosses, else 0);
  property ``visible``. ``Walls.penetrable``: some wall or roof has a material.

Model: a direct ray is blocked when it enters any wall box below the wall's top (unless it
crosses the wall's centre plane inside a window) or crosses a roof outside its holes.
Reflections use the image method on the vertical walls: a reflection mirrors the horizontal
direction about the wall and keeps the elevation. A path with reflections off the faces
f1..fk (from the receiver side) is viable when every reflection point lies within its wall's
extent, below its top and outside its windows, and every segment between reflections, and
the final one to the sky, is unobstructed. The satellite gets the path of the least number of
reflections (then the least extra path), up to ``max_reflections`` and ``max_loss_db``
(3 dB each). The extra path of one reflection is 2·d·cos(el)·cos(alpha) (d distance to the
reflecting face).

Penetration (only when some wall or roof has ``penetration_db``): a blocked ray may instead
arrive straight THROUGH what blocks it. Its loss is the sum of the crossed walls' and roofs'
losses (inf if any of them is opaque), its extra path the material delay
sum((n - 1) x path inside) (centimetres: the slower propagation in the material; the much
larger indoor multipath delay is the receiver model's, see ``sim_backend.gnss``). Of a
reflected and a penetrating path the one with the stronger received power (the smaller loss)
is taken; on equal power the penetrating one (straight, so earlier). A penetrating path is
viable only within ``max_loss_db``. Not modelled: paths that both reflect and penetrate,
diffraction, frequency-dependent or angle-dependent loss (one loss per crossing whatever the
incidence), windows with glass (a window is an opening). Where two wall boxes overlap (the
corners of ``building``) a ray through the overlap crosses both, i.e. thicker material.
Without materials the trace takes exactly the seed model's code path (tested against the
same scene with opaque materials, in the same run).

Method (exact: it finds what a brute-force search over all wall sequences finds).
- Line of sight: a slab test of each ray against each wall box, after exact (conservative)
  prefilters: the ray's line must pass the box's bounding circle in plan, and (per receiver
  position) its rise over the distance to the box must still be below the wall's top.
- Reflections ("shooting"): for plane waves a path's reflections only mirror its horizontal
  direction, so the receiver must look along ``G·d`` where ``d`` is the satellite's
  horizontal direction and ``G`` the product of the mirrors of the reflecting walls. The
  distinct products of at most k mirrors are few and depend only on the walls' orientations
  (4 for axis-aligned buildings: d, d mirrored in x, in y, in both); they are enumerated
  once per scene. From each such look direction the path is determined: follow the ray,
  reflect off the first face it meets, and so on, until it escapes, is blocked, or runs out
  of depth budget; it is viable when it escapes along ``d``. All shots of all blocked rays
  advance together one reflection per step (breadth first), so a ray stops at the first
  depth that gives a viable path. A ray that meets a face outside a window but crosses the
  wall's centre plane inside it both reflects and passes (the model allows both): the shot
  forks there.
- Penetration reuses the line-of-sight candidate pairs (slab entry/exit per wall box) and
  caps each ray's reflection depth at the deepest level still stronger than its
  penetrating path, so materials also shorten the reflection search.
- ``max_directions`` bounds the enumeration for scenes with many wall orientations (the
  count grows with the depth when orientations are not multiples of 90 deg). The search is
  then complete only up to the deepest level whose look directions all fit
  (``direction_depth``); deeper paths are found only along the directions enumerated.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass, field, fields
from typing import Any

import numpy as np

from x6wd.core.errors import ConfigError

LOSS_PER_REFLECTION_DB = 3.0
_EPS = 1e-9


def _finite(where: str, **values: float) -> None:
    for name, value in values.items():
        if not isinstance(value, (int, float)) or not math.isfinite(value):
            raise ConfigError(f"{where}.{name}: must be a finite number, got {value!r}")


def _material(where: str, penetration_db: float | None, refractive_index: float) -> None:
    """Validate the optional material of a wall or roof (None: opaque, the seed's model)."""
    if penetration_db is not None:
        _finite(where, penetration_db=penetration_db)
        if penetration_db < 0.0:
            raise ConfigError(f"{where}.penetration_db: must be >= 0 dB, got {penetration_db}")
    _finite(where, refractive_index=refractive_index)
    if refractive_index < 1.0:
        raise ConfigError(f"{where}.refractive_index: must be >= 1, got {refractive_index}")


@dataclass(frozen=True)
class Window:
    """Opening through a wall: ``u`` along the centreline from (x0, y0), ``z`` above ground (m)."""

    u0_m: float
    u1_m: float
    z0_m: float
    z1_m: float

    def __post_init__(self) -> None:
        _finite("window", u0_m=self.u0_m, u1_m=self.u1_m, z0_m=self.z0_m, z1_m=self.z1_m)
        if not self.u0_m < self.u1_m:
            raise ConfigError(f"window.u1_m: must be > u0_m ({self.u0_m}), got {self.u1_m}")
        if not 0.0 <= self.z0_m < self.z1_m:
            raise ConfigError(
                f"window.z1_m: need 0 <= z0_m < z1_m, got z0_m={self.z0_m}, z1_m={self.z1_m}"
            )


@dataclass(frozen=True)
class Wall:
    """Vertical box on the ground; centreline (x0, y0) -> (x1, y1) in local ENU metres."""

    x0_m: float
    y0_m: float
    x1_m: float
    y1_m: float
    thickness_m: float = 0.3
    height_m: float = 10.0
    windows: tuple[Window, ...] = field(default=())
    penetration_db: float | None = None
    refractive_index: float = 1.0

    def __post_init__(self) -> None:
        _material("wall", self.penetration_db, self.refractive_index)
        _finite(
            "wall",
            x0_m=self.x0_m,
            y0_m=self.y0_m,
            x1_m=self.x1_m,
            y1_m=self.y1_m,
            thickness_m=self.thickness_m,
            height_m=self.height_m,
        )
        if self.length_m <= 0.0:
            raise ConfigError("wall: (x0_m, y0_m) and (x1_m, y1_m) must differ")
        if self.thickness_m <= 0.0:
            raise ConfigError(f"wall.thickness_m: must be > 0, got {self.thickness_m}")
        if self.height_m <= 0.0:
            raise ConfigError(f"wall.height_m: must be > 0, got {self.height_m}")
        object.__setattr__(self, "windows", tuple(self.windows))
        for i, w in enumerate(self.windows):
            if not isinstance(w, Window):
                raise ConfigError(f"wall.windows[{i}]: expected a Window, got {w!r}")
            if w.u0_m < 0.0 or w.u1_m > self.length_m or w.z1_m > self.height_m:
                raise ConfigError(
                    f"wall.windows[{i}]: must lie within the wall (0..{self.length_m:.3f} m "
                    f"along, 0..{self.height_m} m high), got {w}"
                )

    @property
    def length_m(self) -> float:
        """Centreline length (m)."""
        return math.hypot(self.x1_m - self.x0_m, self.y1_m - self.y0_m)


@dataclass(frozen=True)
class Hole:
    """Open rectangle in a roof (axis-aligned in ENU, metres)."""

    x0_m: float
    y0_m: float
    x1_m: float
    y1_m: float

    def __post_init__(self) -> None:
        _finite("hole", x0_m=self.x0_m, y0_m=self.y0_m, x1_m=self.x1_m, y1_m=self.y1_m)
        if not (self.x0_m < self.x1_m and self.y0_m < self.y1_m):
            raise ConfigError(f"hole: need x0_m < x1_m and y0_m < y1_m, got {self}")


@dataclass(frozen=True)
class Roof:
    """Thin horizontal slab at ``height_m`` over an axis-aligned ENU rectangle, with holes."""

    x0_m: float
    y0_m: float
    x1_m: float
    y1_m: float
    height_m: float
    holes: tuple[Hole, ...] = field(default=())
    penetration_db: float | None = None
    thickness_m: float = 0.0
    refractive_index: float = 1.0

    def __post_init__(self) -> None:
        _material("roof", self.penetration_db, self.refractive_index)
        _finite("roof", thickness_m=self.thickness_m)
        if self.thickness_m < 0.0:
            raise ConfigError(f"roof.thickness_m: must be >= 0, got {self.thickness_m}")
        _finite(
            "roof",
            x0_m=self.x0_m,
            y0_m=self.y0_m,
            x1_m=self.x1_m,
            y1_m=self.y1_m,
            height_m=self.height_m,
        )
        if not (self.x0_m < self.x1_m and self.y0_m < self.y1_m):
            raise ConfigError(f"roof: need x0_m < x1_m and y0_m < y1_m, got {self}")
        if self.height_m <= 0.0:
            raise ConfigError(f"roof.height_m: must be > 0, got {self.height_m}")
        object.__setattr__(self, "holes", tuple(self.holes))
        for i, h in enumerate(self.holes):
            if not isinstance(h, Hole):
                raise ConfigError(f"roof.holes[{i}]: expected a Hole, got {h!r}")


def building(
    x0_m: float,
    y0_m: float,
    x1_m: float,
    y1_m: float,
    height_m: float,
    thickness_m: float = 0.3,
    penetration_db: float | None = None,
    refractive_index: float = 1.0,
) -> list[Wall]:
    """The four walls of a closed axis-aligned rectangular building (outer corners given),
    all of one material (``penetration_db`` None: opaque)."""
    if not (x0_m < x1_m and y0_m < y1_m):
        raise ConfigError(
            f"building: need x0_m < x1_m and y0_m < y1_m, got {x0_m, y0_m, x1_m, y1_m}"
        )
    h = thickness_m / 2.0
    # Centrelines inset by half the thickness so the outer faces sit on the given rectangle.
    a, b, c, d = x0_m + h, y0_m + h, x1_m - h, y1_m - h
    mat: dict[str, Any] = {"penetration_db": penetration_db, "refractive_index": refractive_index}
    return [
        Wall(a, b, c, b, thickness_m, height_m, **mat),
        Wall(c, b, c, d, thickness_m, height_m, **mat),
        Wall(c, d, a, d, thickness_m, height_m, **mat),
        Wall(a, d, a, b, thickness_m, height_m, **mat),
    ]


@dataclass(frozen=True)
class TraceResult:
    """Per (epoch, satellite): direct visibility, reflections, extra path (m), loss (dB)."""

    los: np.ndarray
    n_reflections: np.ndarray
    extra_path_m: np.ndarray
    loss_db: np.ndarray
    # Obstructions (walls, roofs) a through-obstruction path crosses; 0 for direct and
    # reflected paths (all 0 in a scene without materials).
    n_penetrations: np.ndarray

    @property
    def visible(self) -> np.ndarray:
        """True where a direct, reflected or penetrating path exists."""
        return self.n_reflections >= 0


DEFAULT_MAX_DIRECTIONS = 4096
# (epoch x satellite, wall) pairs one trace call works on at once: 2^22, ~40 MB of temporaries.
TRACE_BLOCK_ELEMENTS = 1 << 22
# A shot escapes "along d" when its final horizontal direction is within this (components).
# Mirror products accumulate ~1e-15 of rounding; distinct look directions differ by far more.
_DIR_TOL = 1e-9
# Prefilters must never drop a wall the exact test would hit: pad them well beyond rounding.
_REACH_MARGIN_M = 1e-6


@dataclass(frozen=True)
class _Legs:
    """Straight legs (rays from a point, rising at tan_el) tested against candidate walls.

    Per leg: ``blocked`` (the leg cannot reach the sky). Per reflection option (a face the
    leg reaches with nothing in between): ``leg``, ``wall`` and the horizontal distance
    ``s`` to the reflection point."""

    blocked: np.ndarray
    leg: np.ndarray
    wall: np.ndarray
    s: np.ndarray


class Walls:
    """A static scene of walls and roofs, traced for many rays at once."""

    def __init__(
        self,
        walls: Iterable[Wall] = (),
        roofs: Iterable[Roof] = (),
        max_directions: int = DEFAULT_MAX_DIRECTIONS,
    ) -> None:
        """``max_directions``: budget of distinct look directions (mirror products) that the
        reflection search enumerates; only scenes with many wall orientations reach it."""
        self.walls: tuple[Wall, ...] = tuple(walls)
        self.roofs: tuple[Roof, ...] = tuple(roofs)
        for i, w in enumerate(self.walls):
            if not isinstance(w, Wall):
                raise ConfigError(f"walls[{i}]: expected a Wall, got {w!r}")
        for i, r in enumerate(self.roofs):
            if not isinstance(r, Roof):
                raise ConfigError(f"roofs[{i}]: expected a Roof, got {r!r}")
        if max_directions < 1:
            raise ConfigError(f"max_directions: must be >= 1, got {max_directions}")
        self.max_directions = int(max_directions)
        n_w = len(self.walls)
        self._p0 = np.array([[w.x0_m, w.y0_m] for w in self.walls], dtype=float).reshape(n_w, 2)
        p1 = np.array([[w.x1_m, w.y1_m] for w in self.walls], dtype=float).reshape(n_w, 2)
        self._len = np.linalg.norm(p1 - self._p0, axis=1)
        self._t = (p1 - self._p0) / np.maximum(self._len, _EPS)[:, None]
        self._n = np.stack([-self._t[:, 1], self._t[:, 0]], axis=1)  # left of the centreline
        self._half = np.array([w.thickness_m / 2.0 for w in self.walls], dtype=float)
        self._height = np.array([w.height_m for w in self.walls], dtype=float)
        k = max([len(w.windows) for w in self.walls], default=0)
        self._has_windows = k > 0
        self._win = np.full((n_w, max(k, 1), 4), np.nan)
        for i, w in enumerate(self.walls):
            for j, win in enumerate(w.windows):
                self._win[i, j] = (win.u0_m, win.u1_m, win.z0_m, win.z1_m)
        n_r = len(self.roofs)
        self._roof = np.array(
            [[r.x0_m, r.y0_m, r.x1_m, r.y1_m, r.height_m] for r in self.roofs], dtype=float
        ).reshape(n_r, 5)
        k = max([len(r.holes) for r in self.roofs], default=0)
        self._holes = np.full((n_r, max(k, 1), 4), np.nan)
        for i, r in enumerate(self.roofs):
            for j, h in enumerate(r.holes):
                self._holes[i, j] = (h.x0_m, h.y0_m, h.x1_m, h.y1_m)
        # Materials: loss per crossing (inf: opaque) and the (n - 1) delay factor. The
        # penetration search runs only when some obstruction has a finite loss, so a scene
        # without materials is traced exactly as the seed's model (same code path).
        self._pen_w = np.array(
            [math.inf if w.penetration_db is None else w.penetration_db for w in self.walls],
            dtype=float,
        ).reshape(n_w)
        self._nm1_w = np.array([w.refractive_index - 1.0 for w in self.walls]).reshape(n_w)
        self._pen_r = np.array(
            [math.inf if r.penetration_db is None else r.penetration_db for r in self.roofs],
            dtype=float,
        ).reshape(n_r)
        self._delay_r = np.array(
            [(r.refractive_index - 1.0) * r.thickness_m for r in self.roofs]
        ).reshape(n_r)
        self.penetrable = bool(np.isfinite(self._pen_w).any() or np.isfinite(self._pen_r).any())
        # Bounding circles of the boxes in plan, for the prefilter.
        self._centre = self._p0 + self._t * (self._len / 2.0)[:, None]
        self._radius = np.hypot(self._len / 2.0, self._half) + _REACH_MARGIN_M
        # Look directions: level L holds the mirror products of word length exactly L.
        mirrors: dict[tuple[float, ...], np.ndarray] = {}
        for nx, ny in self._n:
            xy = -2.0 * nx * ny
            m = np.array([[1.0 - 2.0 * nx * nx, xy], [xy, 1.0 - 2.0 * ny * ny]])
            mirrors.setdefault(tuple(np.round(m, 12).ravel().tolist()), m)
        self._mirrors = np.array(list(mirrors.values())).reshape(-1, 2, 2)
        self._dir_levels: list[np.ndarray] = [np.eye(2)[None]]
        self._dir_seen = {_map_key(np.eye(2))}
        self._dir_count = 1
        self._dir_closed = len(mirrors) == 0  # no new products can appear
        self._dir_truncated = False
        # Enumerate the default depth now: a shared scene is then only read while tracing.
        self.directions(16)

    def __len__(self) -> int:
        return len(self.walls)

    # ------------------------------------------------------------ look directions
    @property
    def direction_depth(self) -> int | None:
        """Deepest reflection count the look-direction set covers (None: every depth)."""
        return len(self._dir_levels) - 1 if self._dir_truncated else None

    def directions(self, depth: int) -> tuple[np.ndarray, np.ndarray]:
        """All distinct products of at most ``depth`` wall mirrors (G, 2, 2) and each one's
        shortest word length (G,), breadth first; cached per scene."""
        while len(self._dir_levels) <= depth and not (self._dir_closed or self._dir_truncated):
            cand = np.einsum("mij,gjk->mgik", self._mirrors, self._dir_levels[-1]).reshape(-1, 2, 2)
            new = []
            for g in cand:
                key = _map_key(g)
                if key not in self._dir_seen:
                    self._dir_seen.add(key)
                    new.append(g)
            if not new:
                self._dir_closed = True  # the group is finite and complete
                break
            if self._dir_count + len(new) > self.max_directions:
                self._dir_truncated = True
                break
            self._dir_count += len(new)
            self._dir_levels.append(np.array(new))
        levels = self._dir_levels[: depth + 1]
        maps = np.concatenate(levels, axis=0)
        word = np.repeat(np.arange(len(levels)), [lv.shape[0] for lv in levels])
        return maps, word

    # ------------------------------------------------------------ geometry
    def _sight(self, o: np.ndarray, z: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Prefilter table for rays leaving points ``o`` (M, 2) at heights ``z`` (M,):
        ``tan_max`` (M, W), a ray rising at tan_el >= this passes over the wall, its row
        maximum (M,), and ``o`` itself."""
        rel_x = o[:, 0, None] - self._p0[None, :, 0]
        rel_y = o[:, 1, None] - self._p0[None, :, 1]
        ou = rel_x * self._t[:, 0] + rel_y * self._t[:, 1]
        ov = rel_x * self._n[:, 0] + rel_y * self._n[:, 1]
        du = np.maximum(np.maximum(-ou, ou - self._len), 0.0)
        dv = np.maximum(np.abs(ov) - self._half, 0.0)
        dist = np.sqrt(du * du + dv * dv)
        # The ray enters the box no nearer than ``dist``, where it is already this high;
        # inside or touching a box (dist 0) every ray is a candidate.
        rise = self._height[None, :] - z[:, None] + _REACH_MARGIN_M
        tan_max = np.full(dist.shape, np.inf)
        np.divide(rise, dist, out=tan_max, where=dist > 0.0)
        tan_max[rise <= 0.0] = -np.inf  # the receiver is above the wall's top
        return tan_max, tan_max.max(axis=1, initial=-np.inf), o

    def _candidates(
        self,
        sight: tuple[np.ndarray, np.ndarray, np.ndarray] | None,
        origin: np.ndarray,
        v: np.ndarray,
        tan_el: np.ndarray,
        prev: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray]:
        """(leg, wall) pairs, sorted by leg, that the prefilter cannot rule out. With a
        ``sight`` table, ``origin`` (N,) indexes its rows the legs start from; without,
        ``origin`` holds the legs' start points (N, 2). Exact-conservative: a wall is dropped
        only when the leg misses its bounding circle in plan, or (with a table) passes over
        it."""
        if sight is None:
            rows = np.arange(v.shape[0])
            start = origin
        else:
            _, tan_top, o = sight
            rows = np.flatnonzero(tan_el < tan_top[origin])
            start = o[origin[rows]]
        vx, vy = v[rows, 0], v[rows, 1]
        # Dense over (legs, walls), cheapest strong test first: the leg's line passes the
        # bounding circle, |v x (c - start)| <= r, written to broadcast without temporaries
        # of the centre offsets.
        across = vx[:, None] * self._centre[None, :, 1] - vy[:, None] * self._centre[None, :, 0]
        across -= (vx * start[:, 1] - vy * start[:, 0])[:, None]
        near = np.abs(across, out=across) <= self._radius[None, :]
        left = np.flatnonzero(prev[rows] >= 0)
        near[left, prev[rows[left]]] = False  # a ray leaving a face cannot meet that box again
        i, wall = np.nonzero(near)
        # Then per pair: the circle is ahead, and the leg is still below the wall's top.
        leg = rows[i]
        ahead = (self._centre[wall] - start[i]) * v[leg]
        keep = ahead[:, 0] + ahead[:, 1] >= -self._radius[wall]
        if sight is not None:
            tan_max = sight[0]
            keep &= tan_el[leg] < tan_max[origin[leg], wall]
        return leg[keep], wall[keep]

    def _enter(
        self,
        o: np.ndarray,
        z: np.ndarray,
        v: np.ndarray,
        tan_el: np.ndarray,
        leg: np.ndarray,
        wall: np.ndarray,
    ) -> tuple[np.ndarray, ...]:
        """Per (leg, wall) pair: the leg's start in the wall's frame (ou along, ov across),
        its direction there (du, dv), the horizontal distances where it enters and leaves
        the box in plan (s_in, s_out), whether it enters the box below its top (``hit``),
        whether it passes a window at the centre plane (``through``) and where it crosses
        that plane (s_c)."""
        oo, vv = o[leg], v[leg]
        t, nn = self._t[wall], self._n[wall]
        rel = oo - self._p0[wall]
        ou = rel[:, 0] * t[:, 0] + rel[:, 1] * t[:, 1]
        ov = rel[:, 0] * nn[:, 0] + rel[:, 1] * nn[:, 1]
        du = vv[:, 0] * t[:, 0] + vv[:, 1] * t[:, 1]
        dv = vv[:, 0] * nn[:, 0] + vv[:, 1] * nn[:, 1]
        half = self._half[wall]
        height = self._height[wall]
        z0, tz = z[leg], tan_el[leg]
        with np.errstate(divide="ignore", invalid="ignore"):
            lo_u, hi_u = _slab(ou, du, 0.0, self._len[wall])
            lo_v, hi_v = _slab(ov, dv, -half, half)
        s_in = np.maximum(np.maximum(lo_u, lo_v), 0.0)
        s_out = np.minimum(hi_u, hi_v)
        hit = (s_in < s_out) & (z0 + s_in * tz < height)
        # Through a window: the ray crosses the centre plane inside the opening.
        through = np.zeros(leg.size, dtype=bool)
        s_c = np.full(leg.size, np.inf)
        if self._has_windows and leg.size:
            with np.errstate(divide="ignore", invalid="ignore"):
                s_c = -ov / dv
            through = _in_window(self._win[wall], ou + s_c * du, z0 + s_c * tz) & (s_c >= 0.0)
        return ou, ov, du, dv, s_in, s_out, hit, through, s_c

    def _penetration(
        self,
        o: np.ndarray,
        z: np.ndarray,
        v: np.ndarray,
        el_r: np.ndarray,
        leg: np.ndarray,
        wall: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The straight ray of each leg (N,) taken THROUGH everything that blocks it:
        summed loss (dB; inf if an opaque obstruction is crossed), the material delay
        sum((n - 1) x path length inside) (m) and the number of obstructions crossed.
        ``leg``/``wall`` are the candidate pairs of the line-of-sight test."""
        n = o.shape[0]
        tan_el = np.tan(el_r)
        _ou, _ov, _du, _dv, s_in, s_out, hit, through, _s_c = self._enter(
            o, z, v, tan_el, leg, wall
        )
        crossed = hit & ~through
        lc, wc = leg[crossed], wall[crossed]
        # (float even when empty: bincount of no weights returns integers)
        loss = np.bincount(lc, weights=self._pen_w[wc], minlength=n).astype(float)
        count = np.bincount(lc, minlength=n)
        # Length inside the box: from entry to where the ray leaves it in plan or rises over
        # its top; straight, since refraction in a slab only offsets the ray sideways.
        tz = tan_el[lc]
        with np.errstate(divide="ignore", invalid="ignore"):
            s_top = np.where(tz > 0.0, (self._height[wc] - z[lc]) / tz, np.inf)
        inside = np.maximum(np.minimum(s_out[crossed], s_top) - s_in[crossed], 0.0)
        delay = np.bincount(
            lc, weights=self._nm1_w[wc] * inside / np.maximum(np.cos(el_r[lc]), _EPS), minlength=n
        ).astype(float)
        if len(self.roofs):
            _s_r, cross = self._roof_cross(o, z, v, tan_el)
            loss += np.where(cross, self._pen_r[None, :], 0.0).sum(axis=1)
            count += cross.sum(axis=1)
            # A thin slab crossed at elevation el: thickness / sin(el) inside it.
            delay += np.where(cross, self._delay_r[None, :], 0.0).sum(axis=1) / np.maximum(
                np.sin(el_r), _EPS
            )
        return loss, delay, count

    def _legs(
        self,
        o: np.ndarray,
        z: np.ndarray,
        v: np.ndarray,
        tan_el: np.ndarray,
        leg: np.ndarray,
        wall: np.ndarray,
        reflect: np.ndarray | None,
    ) -> _Legs:
        """Walk each leg (o, z, horizontal unit v, tan_el) against its candidate walls
        (pairs ``leg``/``wall`` sorted by leg). ``reflect`` (N,) says which legs may still
        reflect (None: none; line of sight only)."""
        n = o.shape[0]
        ou, ov, du, dv, s_in, _s_out, hit, through, s_c = self._enter(o, z, v, tan_el, leg, wall)
        half = self._half[wall]
        z0, tz = z[leg], tan_el[leg]
        blocked = np.bincount(leg[hit & ~through], minlength=n) > 0
        roof_s = self._roof_block(o, z, v, tan_el)
        blocked |= np.isfinite(roof_s)
        empty = np.zeros(0, dtype=np.int64)
        if reflect is None:
            return _Legs(blocked, empty, empty, np.zeros(0))
        # Reflection off the face on the leg's side: in front of it, heading into it, the
        # point within the wall's extent, below its top and outside its windows.
        side_ov = np.abs(ov)
        dist = side_ov - half
        dn = np.where(ov >= 0.0, dv, -dv)
        ok = reflect[leg] & hit & (dist > 1e-6) & (dn < -_EPS)
        c = np.flatnonzero(ok)
        s = dist[c] / -dn[c]
        u_hit = ou[c] + s * du[c]
        z_hit = z0[c] + s * tz[c]
        w_c = wall[c]
        good = (u_hit >= 0.0) & (u_hit <= self._len[w_c]) & (z_hit < self._height[w_c])
        if self._has_windows:
            good &= ~_in_window(self._win[w_c], u_hit, z_hit)
        c, s = c[good], s[good]
        if c.size == 0:
            return _Legs(blocked, empty, empty, np.zeros(0))
        # Nothing between the leg's start and the face: every other candidate wall of the
        # same leg that the ray enters before s blocks it, unless it passes its window
        # before s; a roof crossed before s blocks it too.
        cnt = np.bincount(leg, minlength=n)
        start = np.concatenate(([0], np.cumsum(cnt)[:-1]))
        lc = leg[c]
        k = cnt[lc]
        rep = np.repeat(np.arange(c.size), k)
        j = start[lc][rep] + np.arange(rep.size) - np.repeat(np.cumsum(k) - k, k)
        sr = s[rep]
        stop = hit[j] & (wall[j] != wall[c][rep]) & (s_in[j] < sr) & ~(through[j] & (s_c[j] <= sr))
        clear = (np.bincount(rep[stop], minlength=c.size) == 0) & (roof_s[lc] > s)
        return _Legs(blocked, lc[clear], wall[c][clear], s[clear])

    def _roof_block(
        self, o: np.ndarray, z: np.ndarray, v: np.ndarray, tan_el: np.ndarray
    ) -> np.ndarray:
        """Horizontal distance (N,) at which each ray first crosses a roof outside its holes
        from below (inf: never)."""
        n = o.shape[0]
        if not len(self.roofs) or n == 0:
            return np.full(n, np.inf)
        s_r, cross = self._roof_cross(o, z, v, tan_el)
        return np.where(cross, s_r, np.inf).min(axis=1)

    def _roof_cross(
        self, o: np.ndarray, z: np.ndarray, v: np.ndarray, tan_el: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """Per ray and roof (N, R): horizontal distance to the roof's plane and whether the
        ray crosses the roof there from below, outside its holes."""
        h_r = self._roof[None, :, 4]
        with np.errstate(divide="ignore", invalid="ignore"):
            s_r = (h_r - z[:, None]) / tan_el[:, None]  # (N, R)
        reach = (z[:, None] < h_r) & (tan_el[:, None] > 0.0)
        qx = o[:, 0, None] + s_r * v[:, 0, None]
        qy = o[:, 1, None] + s_r * v[:, 1, None]
        r = self._roof[None, :, :]
        inside = (qx >= r[..., 0]) & (qx <= r[..., 2]) & (qy >= r[..., 1]) & (qy <= r[..., 3])
        hl = self._holes[None, :, :, :]
        in_hole = (
            (qx[..., None] >= hl[..., 0])
            & (qx[..., None] <= hl[..., 2])
            & (qy[..., None] >= hl[..., 1])
            & (qy[..., None] <= hl[..., 3])
        ).any(axis=2)
        return s_r, reach & inside & ~in_hole

    # ---------------------------------------------------------------- trace
    def trace(
        self,
        rx_enu_m: Any,
        az_deg: Any,
        el_deg: Any,
        max_reflections: int = 16,
        max_loss_db: Any = None,
    ) -> TraceResult:
        """Direct and reflected paths from satellites at (az_deg, el_deg) to the receiver(s).

        ``rx_enu_m`` (3,) or (E, 3) metres; ``az_deg``/``el_deg`` (E, S) or (S,) degrees.
        ``max_loss_db`` (one value, or per ray broadcastable to (E, S)) stops the search at
        the depth whose loss (3 dB each) would exceed it. Satellites at or below the horizon
        are invisible.
        """
        rx = np.asarray(rx_enu_m, dtype=float)
        az = np.asarray(az_deg, dtype=float)
        el = np.asarray(el_deg, dtype=float)
        if az.shape != el.shape:
            raise ValueError(f"az_deg {az.shape} and el_deg {el.shape} must have the same shape")
        if rx.ndim not in (1, 2) or rx.shape[-1] != 3:
            raise ValueError(f"rx_enu_m must be (3,) or (E, 3), got {rx.shape}")
        if az.ndim == 1:
            az = az[None, :]
            el = el[None, :]
        if az.ndim != 2:
            raise ValueError(f"az_deg/el_deg must be (S,) or (E, S), got {az.shape}")
        if rx.ndim == 1:
            rx = rx[None, :]
        if rx.shape[0] not in (1, az.shape[0]) and az.shape[0] != 1:
            raise ValueError(f"{rx.shape[0]} receiver positions for {az.shape[0]} epochs")
        n_e = max(rx.shape[0], az.shape[0])
        az = np.broadcast_to(az, (n_e, az.shape[1]))
        el = np.broadcast_to(el, (n_e, az.shape[1]))
        if not (np.isfinite(az).all() and np.isfinite(el).all() and np.isfinite(rx).all()):
            raise ValueError("rx_enu_m, az_deg and el_deg must be finite")
        if max_reflections < 0:
            raise ValueError(f"max_reflections must be >= 0, got {max_reflections}")
        # The prefilters are dense over (rays, walls): trace many epochs in blocks, so memory
        # stays bounded however many walls there are (rays are traced independently).
        per_epoch = az.shape[1] * (len(self.walls) + len(self.roofs))
        if n_e > 1 and n_e * per_epoch > TRACE_BLOCK_ELEMENTS:
            step = max(1, TRACE_BLOCK_ELEMENTS // per_epoch)
            lim = None if max_loss_db is None else np.broadcast_to(max_loss_db, az.shape)
            parts = [
                self.trace(
                    rx if rx.shape[0] == 1 else rx[a : a + step],
                    az[a : a + step],
                    el[a : a + step],
                    max_reflections,
                    None if lim is None else lim[a : a + step],
                )
                for a in range(0, n_e, step)
            ]
            return TraceResult(
                *(np.concatenate([getattr(p, f.name) for p in parts]) for f in fields(TraceResult))
            )
        shape = az.shape
        n_s = shape[1]
        n = az.size
        el_r = np.radians(el.ravel())
        up = el_r > 0.0
        # Only rays above the horizon are traced: work on their compact list from here.
        rays = np.flatnonzero(up)
        depth = np.full(rays.size, int(max_reflections), dtype=np.int64)
        if max_loss_db is not None:
            loss = np.broadcast_to(np.asarray(max_loss_db, dtype=float), shape).ravel()
            if np.isnan(loss).any():
                raise ValueError("max_loss_db must not be NaN")
            bound = np.floor(loss[rays] / LOSS_PER_REFLECTION_DB)
            depth = np.clip(np.minimum(bound, max_reflections), 0, None).astype(np.int64)
        # Receiver positions: a static receiver is one position for all epochs.
        pos = rx if rx.shape[0] == 1 else np.broadcast_to(rx, (n_e, 3))
        origin = rays // n_s if pos.shape[0] > 1 else np.zeros(rays.size, dtype=np.int64)
        az_r = np.radians(az.ravel()[rays])
        el_r = el_r[rays]
        d = np.stack([np.sin(az_r), np.cos(az_r)], axis=1)
        tan_el = np.tan(el_r)

        los = up.copy()
        n_refl = np.where(up, 0, -1).astype(np.int64)
        extra = np.zeros(n)
        n_pen = np.zeros(n, dtype=np.int64)
        pen_rays = np.zeros(0, dtype=np.int64)
        pen_loss = pen_delay = np.zeros(0)
        pen_count = np.zeros(0, dtype=np.int64)
        if len(self.walls) or len(self.roofs):
            o, z = pos[origin, :2], pos[origin, 2]
            sight = self._sight(pos[:, :2], pos[:, 2])
            prev = np.full(rays.size, -1, dtype=np.int64)
            leg, wall = self._candidates(sight, origin, d, tan_el, prev)
            blocked = self._legs(o, z, d, tan_el, leg, wall, None).blocked
            los[rays] = ~blocked
            n_refl[rays[blocked]] = -1
            if self.penetrable:
                b = np.flatnonzero(blocked)
                # The blocked rays' straight path through the obstructions (compact indices).
                where = np.full(rays.size, -1, dtype=np.int64)
                where[b] = np.arange(b.size)
                keep = blocked[leg]
                p_loss, p_delay, p_count = self._penetration(
                    o[b], z[b], d[b], el_r[b], where[leg[keep]], wall[keep]
                )
                ok = np.isfinite(p_loss)
                if max_loss_db is not None:
                    ok &= p_loss <= loss[rays[b]]
                # The stronger path wins: a reflected path only when its loss (3 dB per
                # bounce) is strictly below the penetration loss, so the reflection search
                # needs no deeper level than that; on equal power the straight, earlier
                # penetrating path is kept.
                cap = np.ceil(p_loss[ok] / LOSS_PER_REFLECTION_DB) - 1.0
                depth[b[ok]] = np.minimum(depth[b[ok]], np.clip(cap, 0, None).astype(np.int64))
                pen_rays, pen_loss = b[ok], p_loss[ok]
                pen_delay, pen_count = p_delay[ok], p_count[ok]
            pend = np.flatnonzero(blocked & (depth > 0))
            if pend.size and len(self.walls):
                n_p, x_p = self._reflections(
                    sight, pos, origin[pend], d[pend], el_r[pend], depth[pend]
                )
                n_refl[rays[pend]] = n_p
                extra[rays[pend]] = x_p
            if pen_rays.size:
                # Penetrating where no (stronger) reflected path was found.
                use = n_refl[rays[pen_rays]] < 0
                r = rays[pen_rays[use]]
                n_refl[r] = 0
                extra[r] = pen_delay[use]
                n_pen[r] = pen_count[use]
                pen_loss = pen_loss[use]
                pen_rays = r
        loss_db = np.where(n_refl >= 0, LOSS_PER_REFLECTION_DB * np.maximum(n_refl, 0), np.inf)
        if pen_rays.size:
            loss_db[pen_rays] = pen_loss
        return TraceResult(
            los=los.reshape(shape),
            n_reflections=n_refl.reshape(shape),
            extra_path_m=extra.reshape(shape),
            loss_db=loss_db.reshape(shape),
            n_penetrations=n_pen.reshape(shape),
        )

    def visibility(self, rx_enu_m: Any, az_deg: Any, el_deg: Any) -> TraceResult:
        """:meth:`trace` with the default search limits (the GNSS model's walls interface)."""
        return self.trace(rx_enu_m, az_deg, el_deg)

    def _reflections(
        self,
        sight: tuple[np.ndarray, np.ndarray, np.ndarray],
        pos: np.ndarray,
        origin: np.ndarray,
        d: np.ndarray,
        el_r: np.ndarray,
        depth: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Reflected paths of blocked rays (receiver ``pos[origin]``, horizontal direction
        ``d``, elevation ``el_r``, depth budget ``depth``): (reflections or -1, extra path)."""
        n_p = d.shape[0]
        tan_el = np.tan(el_r)
        maps, word = self.directions(int(depth.max()))
        # One shot per ray and look direction whose shortest word fits the ray's budget.
        ray, g = np.nonzero(word[None, :] <= depth[:, None])
        v = np.einsum("nij,nj->ni", maps[g], d[ray])
        o = pos[origin[ray], :2].copy()
        z = pos[origin[ray], 2].copy()
        prev = np.full(ray.size, -1, dtype=np.int64)
        s_tot = np.zeros(ray.size)
        found_n = np.full(n_p, -1, dtype=np.int64)
        found_x = np.full(n_p, np.inf)
        for step in range(int(depth.max()) + 1):
            if ray.size == 0:
                break
            t = tan_el[ray]
            if step == 0:  # still at the receivers: their prefilter tables apply
                leg, wall = self._candidates(sight, origin[ray], v, t, prev)
            else:  # from reflection points: one origin per leg, no height table (cheaper)
                leg, wall = self._candidates(None, o, v, t, prev)
            legs = self._legs(o, z, v, t, leg, wall, depth[ray] > step)
            # Escaped along the satellite's direction after ``step`` reflections: viable.
            # (Step 0 is the direct ray, already known blocked.)
            if step > 0:
                esc = np.flatnonzero(~legs.blocked & (np.abs(v - d[ray]).max(axis=1) < _DIR_TOL))
                if esc.size:
                    r = ray[esc]
                    cos_el, sin_el = np.cos(el_r[r]), np.sin(el_r[r])
                    start = pos[origin[r]]
                    # 3-D path length minus the advance of the plane wave front along d.
                    x = (
                        s_tot[esc] / np.maximum(cos_el, _EPS)
                        - np.einsum("ci,ci->c", o[esc] - start[:, :2], d[r]) * cos_el
                        - (z[esc] - start[:, 2]) * sin_el
                    )
                    found_n[r] = step
                    np.minimum.at(found_x, r, np.maximum(x, 0.0))
            # Reflect the legs that met a face, for rays still without a path.
            keep = found_n[ray[legs.leg]] < 0
            c, w, s = legs.leg[keep], legs.wall[keep], legs.s[keep]
            nrm = self._n[w]
            vc = v[c]
            ray = ray[c]
            o = o[c] + s[:, None] * vc
            z = z[c] + s * tan_el[ray]
            v = vc - 2.0 * np.einsum("ci,ci->c", vc, nrm)[:, None] * nrm
            prev = w
            s_tot = s_tot[c] + s
        return found_n, np.where(found_n >= 0, found_x, 0.0)


def _map_key(g: np.ndarray) -> tuple[int, ...]:
    """Hashable identity of a 2x2 orthogonal map, robust to accumulated rounding."""
    return tuple(np.round(g.ravel() * 1e10).astype(np.int64).tolist())


def _in_window(win: np.ndarray, u: np.ndarray, z: np.ndarray) -> np.ndarray:
    """True where (u, z) lies in one of the windows ``win`` (N, K, 4; NaN rows: none)."""
    inside = (
        (u[:, None] >= win[..., 0])
        & (u[:, None] <= win[..., 1])
        & (z[:, None] >= win[..., 2])
        & (z[:, None] <= win[..., 3])
    )
    return np.asarray(inside.any(axis=1))


def _slab(o: np.ndarray, dvec: np.ndarray, lo: Any, hi: Any) -> tuple[np.ndarray, np.ndarray]:
    """Parameter interval where o + s·dvec lies in [lo, hi]. A parallel ray gets (-inf, inf)
    inside the slab and an empty (inf, inf) interval outside, through IEEE infinities."""
    inv = 1.0 / dvec
    s1 = (lo - o) * inv
    s2 = (hi - o) * inv
    return np.minimum(s1, s2), np.maximum(s1, s2)
