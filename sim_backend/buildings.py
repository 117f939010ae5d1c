"""Buildings: line of sight and wall reflections for satellites at infinity (plane waves).

PUBLIC API
- ``Window(u0_m, u1_m, z0_m, z1_m)``: an opening through a wall; ``u`` is the distance along
  the wall's centreline from its start point (x0, y0), ``z`` the height above ground.
- ``Wall(x0_m, y0_m, x1_m, y1_m, thickness_m=0.3, height_m=10.0, windows=())``: a vertical
  box standing on the ground (z = 0); the centreline runs (x0, y0) -> (x1, y1) in the local
  ENU frame (x east, y north, metres); the box extends ``thickness_m / 2`` to each side.
- ``Hole(x0_m, y0_m, x1_m, y1_m)`` and ``Roof(x0_m, y0_m, x1_m, y1_m, height_m, holes=())``:
  a thin horizontal slab (axis-aligned rectangle in ENU) at ``height_m`` with open
  rectangles; it blocks rays from below that cross it outside its holes. Roofs do not reflect.
- ``building(x0_m, y0_m, x1_m, y1_m, height_m, thickness_m=0.3) -> list[Wall]``: the four
  walls of an axis-aligned rectangular building (closed, no windows).
- ``Walls(walls, roofs=(), max_candidates_per_ray=16)`` with
  ``trace(rx_enu_m, az_deg, el_deg, max_reflections=16, max_loss_db=None) -> TraceResult``
  (``visibility(rx_enu_m, az_deg, el_deg)`` is the same with default limits):
  ``rx_enu_m`` is (3,) or (E, 3) (up = antenna height above ground, metres), ``az_deg`` /
  ``el_deg`` are (E, S) or (S,) (azimuth clockwise from north). Everything is vectorised
  over rays x walls; the Python loops run only over reflection depth.
- ``TraceResult``: arrays of the broadcast shape (E, S): ``los`` (bool, direct path clear),
  ``n_reflections`` (int: 0 direct, 1..16 reflections, -1 no viable path = invisible),
  ``extra_path_m`` (range error of the path taken, 0 when direct or invisible),
  ``loss_db`` (3 dB per reflection, ``inf`` when invisible); property ``visible``.

Model: a direct ray is blocked when it enters any wall box below the wall's top (unless it
crosses the wall's centre plane inside a window) or crosses a roof outside its holes.
Reflections use the image method on the vertical walls: a reflection mirrors the horizontal
direction about the wall and keeps the elevation. The search is a breadth-first beam search
over face sequences from the receiver side, shared by all satellites seen from the same
receiver position (an epoch, or all epochs of a static receiver). Each sequence carries the
receiver's image behind its last face and the cone of horizontal directions that pass
through every face so far (beam tracing in plan view). Pruning: (a) a static table of faces
that can see each other; (b) the image must be in front of the next face, and the cone
through it must be non-empty; (c) height: the unfolded path to the next face, rising at the
lowest pending elevation, must still be below that wall's top; (d) stop at the first depth
that yields a viable path (the least extra path of that depth is kept); (e) ``max_loss_db``
bounds the depth (3 dB each); (f) at most ``max_candidates_per_ray`` sequences per receiver
position and depth, nearest image first. A satellite matches a sequence when its direction
lies in the final cone; the path is then back-traced from the receiver and is viable when
every reflection point lies within its wall's extent, below its top and outside its windows,
and every segment between reflections, and the final one to the sky, is unobstructed.
(f) makes the search incomplete in cluttered scenes (a longer path may be reported, or none);
raise ``max_candidates_per_ray`` for completeness at the cost of time. The extra path of one
reflection is 2·d·cos(el)·cos(alpha) (d distance to the reflecting face).
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from x6wd.errors import ConfigError

LOSS_PER_REFLECTION_DB = 3.0
_EPS = 1e-9


def _finite(where: str, **values: float) -> None:
    for name, value in values.items():
        if not isinstance(value, (int, float)) or not math.isfinite(value):
            raise ConfigError(f"{where}.{name}: must be a finite number, got {value!r}")


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

    def __post_init__(self) -> None:
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

    def __post_init__(self) -> None:
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
    x0_m: float, y0_m: float, x1_m: float, y1_m: float, height_m: float, thickness_m: float = 0.3
) -> list[Wall]:
    """The four walls of a closed axis-aligned rectangular building (outer corners given)."""
    if not (x0_m < x1_m and y0_m < y1_m):
        raise ConfigError(
            f"building: need x0_m < x1_m and y0_m < y1_m, got {x0_m, y0_m, x1_m, y1_m}"
        )
    h = thickness_m / 2.0
    # Centrelines inset by half the thickness so the outer faces sit on the given rectangle.
    a, b, c, d = x0_m + h, y0_m + h, x1_m - h, y1_m - h
    return [
        Wall(a, b, c, b, thickness_m, height_m),
        Wall(c, b, c, d, thickness_m, height_m),
        Wall(c, d, a, d, thickness_m, height_m),
        Wall(a, d, a, b, thickness_m, height_m),
    ]


@dataclass(frozen=True)
class TraceResult:
    """Per (epoch, satellite): direct visibility, reflections, extra path (m), loss (dB)."""

    los: np.ndarray
    n_reflections: np.ndarray
    extra_path_m: np.ndarray
    loss_db: np.ndarray

    @property
    def visible(self) -> np.ndarray:
        """True where a direct or reflected path exists."""
        return self.n_reflections >= 0


class Walls:
    """A static scene of walls and roofs, traced for many rays at once."""

    def __init__(
        self,
        walls: Iterable[Wall] = (),
        roofs: Iterable[Roof] = (),
        max_candidates_per_ray: int = 16,
    ) -> None:
        """``max_candidates_per_ray``: beam width of the reflection search, i.e. the face
        sequences kept per receiver position and depth (nearest first)."""
        self.walls: tuple[Wall, ...] = tuple(walls)
        self.roofs: tuple[Roof, ...] = tuple(roofs)
        for i, w in enumerate(self.walls):
            if not isinstance(w, Wall):
                raise ConfigError(f"walls[{i}]: expected a Wall, got {w!r}")
        for i, r in enumerate(self.roofs):
            if not isinstance(r, Roof):
                raise ConfigError(f"roofs[{i}]: expected a Roof, got {r!r}")
        if max_candidates_per_ray < 1:
            raise ConfigError(f"max_candidates_per_ray: must be >= 1, got {max_candidates_per_ray}")
        self.max_candidates_per_ray = int(max_candidates_per_ray)
        n_w = len(self.walls)
        self._p0 = np.array([[w.x0_m, w.y0_m] for w in self.walls], dtype=float).reshape(n_w, 2)
        p1 = np.array([[w.x1_m, w.y1_m] for w in self.walls], dtype=float).reshape(n_w, 2)
        self._len = np.linalg.norm(p1 - self._p0, axis=1)
        self._t = (p1 - self._p0) / np.maximum(self._len, _EPS)[:, None]
        self._n = np.stack([-self._t[:, 1], self._t[:, 0]], axis=1)  # left of the centreline
        self._half = np.array([w.thickness_m / 2.0 for w in self.walls], dtype=float)
        self._height = np.array([w.height_m for w in self.walls], dtype=float)
        k = max([len(w.windows) for w in self.walls], default=0)
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
        self._compat = self._face_compat()

    def __len__(self) -> int:
        return len(self.walls)

    # ------------------------------------------------------------ geometry
    def _face_compat(self) -> np.ndarray:
        """compat[a, b]: face b (index 2*wall + (side > 0)) has a point in front of face a and
        vice versa, so a ray can travel between them (static, direction-free pruning)."""
        n_w = len(self.walls)
        faces = 2 * n_w
        if n_w == 0:
            return np.zeros((0, 0), dtype=bool)
        side = np.tile([-1.0, 1.0], n_w)
        wall = np.repeat(np.arange(n_w), 2)
        normal = self._n[wall] * side[:, None]  # (F, 2)
        offset = np.einsum("fi,fi->f", self._p0[wall], normal) + self._half[wall]
        ends = np.stack(
            [
                self._p0[wall] + normal * self._half[wall][:, None],
                self._p0[wall]
                + self._t[wall] * self._len[wall][:, None]
                + normal * self._half[wall][:, None],
            ],
            axis=1,
        )  # (F, 2 ends, 2)
        # front[a, b]: some end of face b lies strictly in front of face a.
        dist = np.einsum("ai,bki->abk", normal, ends) - offset[:, None, None]
        front = (dist > 1e-6).any(axis=2)
        compat = front & front.T
        compat[wall[:, None] == wall[None, :]] = False
        assert compat.shape == (faces, faces)
        return compat

    def _segment_blocked(
        self,
        o: np.ndarray,
        z0: np.ndarray,
        v: np.ndarray,
        tan_el: np.ndarray,
        s_max: np.ndarray,
        exclude: np.ndarray,
    ) -> np.ndarray:
        """True where the ray o + s·v (horizontal distance s in [0, s_max), rising by tan_el)
        enters a wall box below its top (outside windows) or crosses a roof outside holes.
        ``exclude`` (N,) or (N, m): wall indices ignored per ray (-1 = none)."""
        n = o.shape[0]
        blocked = np.zeros(n, dtype=bool)
        if n == 0:
            return blocked
        if len(self.walls):
            rel = o[:, None, :] - self._p0[None, :, :]  # (N, W, 2)
            ou = np.einsum("nwi,wi->nw", rel, self._t)
            ov = np.einsum("nwi,wi->nw", rel, self._n)
            du = v @ self._t.T  # (N, W)
            dv = v @ self._n.T
            with np.errstate(divide="ignore", invalid="ignore"):
                lo_u, hi_u = _slab(ou, du, 0.0, self._len[None, :])
                lo_v, hi_v = _slab(ov, dv, -self._half[None, :], self._half[None, :])
            s_in = np.maximum(np.maximum(lo_u, lo_v), 0.0)
            s_out = np.minimum(np.minimum(hi_u, hi_v), s_max[:, None])
            z_in = z0[:, None] + s_in * tan_el[:, None]
            hit = (s_in < s_out) & (z_in < self._height[None, :])
            wall_idx = np.arange(len(self.walls))[None, :]
            for col in exclude.reshape(n, -1).T:
                hit &= wall_idx != col[:, None]
            if hit.any() and not np.isnan(self._win).all():
                with np.errstate(divide="ignore", invalid="ignore"):
                    s_c = -ov / dv
                u_c = ou + s_c * du
                z_c = z0[:, None] + s_c * tan_el[:, None]
                win = self._win[None, :, :, :]
                through = (
                    (u_c[..., None] >= win[..., 0])
                    & (u_c[..., None] <= win[..., 1])
                    & (z_c[..., None] >= win[..., 2])
                    & (z_c[..., None] <= win[..., 3])
                ).any(axis=2)
                hit &= ~(through & (s_c >= 0.0) & (s_c <= s_max[:, None]))
            blocked |= hit.any(axis=1)
        if len(self.roofs):
            h_r = self._roof[None, :, 4]
            with np.errstate(divide="ignore", invalid="ignore"):
                s_r = (h_r - z0[:, None]) / tan_el[:, None]  # (N, R)
            reach = (z0[:, None] < h_r) & (tan_el[:, None] > 0.0) & (s_r <= s_max[:, None])
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
            blocked |= (reach & inside & ~in_hole).any(axis=1)
        return blocked

    # ---------------------------------------------------------------- trace
    def trace(
        self,
        rx_enu_m: Any,
        az_deg: Any,
        el_deg: Any,
        max_reflections: int = 16,
        max_loss_db: float | None = None,
    ) -> TraceResult:
        """Direct and reflected paths from satellites at (az_deg, el_deg) to the receiver(s).

        ``rx_enu_m`` (3,) or (E, 3) metres; ``az_deg``/``el_deg`` (E, S) or (S,) degrees.
        ``max_loss_db`` stops the search at the depth whose loss (3 dB each) would exceed it.
        Satellites at or below the horizon are invisible.
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
        rx = np.broadcast_to(rx, (n_e, 3))
        if not (np.isfinite(az).all() and np.isfinite(el).all() and np.isfinite(rx).all()):
            raise ValueError("rx_enu_m, az_deg and el_deg must be finite")
        if max_reflections < 0:
            raise ValueError(f"max_reflections must be >= 0, got {max_reflections}")
        shape = az.shape
        n_s = shape[1]
        az_r = np.radians(az.ravel())
        el_r = np.radians(el.ravel())
        n = az_r.size
        o = np.repeat(rx[:, :2], n_s, axis=0)
        z0 = np.repeat(rx[:, 2], n_s)
        d = np.stack([np.sin(az_r), np.cos(az_r)], axis=1)
        tan_el = np.tan(el_r)
        up = el_r > 0.0

        los = up & ~self._segment_blocked(
            o, z0, d, tan_el, np.full(n, np.inf), np.full(n, -1, dtype=np.int64)
        )
        n_refl = np.where(los, 0, -1).astype(np.int64)
        extra = np.zeros(n)
        depth_max = max_reflections
        if max_loss_db is not None:
            depth_max = min(depth_max, math.floor(max_loss_db / LOSS_PER_REFLECTION_DB))
        pending = np.flatnonzero(up & ~los)
        if len(self.walls) and pending.size and depth_max > 0:
            self._search(o, z0, d, tan_el, el_r, pending, n_s, depth_max, n_refl, extra)
        return TraceResult(
            los=los.reshape(shape),
            n_reflections=n_refl.reshape(shape),
            extra_path_m=extra.reshape(shape),
            loss_db=np.where(
                n_refl >= 0, LOSS_PER_REFLECTION_DB * np.maximum(n_refl, 0), np.inf
            ).reshape(shape),
        )

    def visibility(self, rx_enu_m: Any, az_deg: Any, el_deg: Any) -> TraceResult:
        """:meth:`trace` with the default search limits (the GNSS model's walls interface)."""
        return self.trace(rx_enu_m, az_deg, el_deg)

    def _search(
        self,
        o: np.ndarray,
        z0: np.ndarray,
        d: np.ndarray,
        tan_el: np.ndarray,
        el_r: np.ndarray,
        pending: np.ndarray,
        n_s: int,
        depth_max: int,
        n_refl: np.ndarray,
        extra: np.ndarray,
    ) -> None:
        """Breadth-first search over face sequences from the receiver side, shared by all
        satellites of an epoch; fills ``n_refl``/``extra`` in place for rays that find a path.

        Each candidate carries the receiver's image point behind its last face and the cone
        of horizontal directions (lo -> hi counter-clockwise) that can leave that image
        through every face of the sequence so far. The cone only narrows, so sequences whose
        cone is empty are dropped together with all their extensions."""
        n_w = len(self.walls)
        face_wall = np.repeat(np.arange(n_w), 2)
        face_n = self._n[face_wall] * np.tile([-1.0, 1.0], n_w)[:, None]  # (F, 2)
        face_q = self._p0[face_wall] + face_n * self._half[face_wall][:, None]
        face_e1 = face_q + self._t[face_wall] * self._len[face_wall][:, None]
        face_off = np.einsum("fi,fi->f", face_q, face_n)
        face_height = self._height[face_wall]
        nbr_ptr = np.concatenate([[0], np.cumsum(self._compat.sum(axis=1))])
        nbr_idx = np.nonzero(self._compat)[1]
        # Pending rays grouped by epoch: start offset and count per epoch.
        # Candidates are shared by all pending rays from the same receiver position (one
        # epoch, or every epoch of a static receiver): group the rays by position.
        rx_pos = np.column_stack([o[pending], z0[pending]])
        _uniq, ray_grp = np.unique(rx_pos, axis=0, return_inverse=True)
        ray_grp = ray_grp.ravel()
        by_grp = np.argsort(ray_grp, kind="stable")
        pending, ray_grp = pending[by_grp], ray_grp[by_grp]
        groups, pend_first, counts = np.unique(ray_grp, return_index=True, return_counts=True)
        n_grp = groups.size
        pend_start = np.zeros(n_grp, dtype=np.int64)
        pend_count = np.zeros(n_grp, dtype=np.int64)
        pend_start[groups] = pend_first
        pend_count[groups] = counts
        grp_of_ray = np.full(o.shape[0], -1, dtype=np.int64)
        grp_of_ray[pending] = ray_grp
        tan_min_ep = np.full(n_grp, np.inf)
        np.minimum.at(tan_min_ep, ray_grp, tan_el[pending])
        z_rx_ep = np.zeros(n_grp)
        z_rx_ep[ray_grp] = z0[pending]
        alive_ray = np.zeros(o.shape[0], dtype=bool)
        alive_ray[pending] = True
        # Depth-0 candidates: one per receiver position, image = receiver, cone = everything.
        # (``ep`` below is the position group of a candidate.)
        ep = groups.copy()
        img = o[pending[pend_start[ep]]]
        lo = np.zeros((ep.size, 2))
        hi = np.zeros((ep.size, 2))
        faces = np.zeros((ep.size, 0), dtype=np.int64)
        for depth in range(1, depth_max + 1):
            if ep.size == 0:
                return
            # Extend: the image must be in front of the new face, the face must be able to
            # see the previous one, and the cone through the new face must be non-empty.
            if depth == 1:
                ci, fi = np.nonzero(np.ones((ep.size, face_n.shape[0]), dtype=bool))
            else:
                # Only faces that can see the previous face (static table, as CSR lists).
                last = faces[:, -1]
                deg = nbr_ptr[last + 1] - nbr_ptr[last]
                ci = np.repeat(np.arange(ep.size), deg)
                off = np.arange(ci.size) - np.repeat(np.cumsum(deg) - deg, deg)
                fi = nbr_idx[nbr_ptr[last][ci] + off]
            dist = np.einsum("ci,ci->c", img[ci], face_n[fi]) - face_off[fi]
            # Height pruning: the unfolded path to the new face is at least the distance from
            # the image to the face's plane; a ray rising at the lowest pending elevation of
            # the group must still be below the wall's top there.
            g = ep[ci]
            ok = (dist > 1e-6) & (dist * tan_min_ep[g] < face_height[fi] - z_rx_ep[g])
            ci, fi, dist = ci[ok], fi[ok], dist[ok]
            if ci.size == 0:
                return
            p = img[ci]
            # Cone edges need not be unit vectors: only signs of cross products are used.
            a = face_q[fi] - p
            b = face_e1[fi] - p
            swap = _cross(a, b) < 0.0
            a, b = np.where(swap[:, None], b, a), np.where(swap[:, None], a, b)
            if depth > 1:
                a, b, nonempty = _cone_intersect(lo[ci], hi[ci], a, b)
                ci, fi, a, b, p = ci[nonempty], fi[nonempty], a[nonempty], b[nonempty], p[nonempty]
                dist = dist[nonempty]
            # Beam search: per epoch keep the candidates whose image is nearest to the new
            # face (shortest unfolded paths: most likely below the wall tops, least extra path).
            keep = _cap_index(ep[ci], self.max_candidates_per_ray, dist)
            ci, fi, a, b, p = ci[keep], fi[keep], a[keep], b[keep], p[keep]
            nf = face_n[fi]
            # Mirror about the new face: image point and (orientation-reversing) cone.
            img = p - 2.0 * (np.einsum("ci,ci->c", p, nf) - face_off[fi])[:, None] * nf
            lo, hi = _mirror(b, nf), _mirror(a, nf)
            ep = ep[ci]
            faces = np.concatenate([faces[ci], fi[:, None]], axis=1)
            # Match with the pending satellites of the candidate's epoch: d must lie in the cone.
            cnt = pend_count[ep]
            cand = np.repeat(np.arange(ep.size), cnt)
            if cand.size == 0:
                continue
            off = np.arange(cand.size) - np.repeat(np.cumsum(cnt) - cnt, cnt)
            ray = pending[pend_start[ep[cand]] + off]
            live = alive_ray[ray]
            cand, ray = cand[live], ray[live]
            dd = d[ray]
            inside = (_cross(lo[cand], dd) >= 0.0) & (_cross(dd, hi[cand]) >= 0.0)
            cand, ray = cand[inside], ray[inside]
            if ray.size == 0:
                continue
            v_look = dd[inside]
            seq = faces[cand]
            for j in range(depth - 1, -1, -1):
                nj = face_n[seq[:, j]]
                v_look = v_look - 2.0 * np.einsum("ci,ci->c", v_look, nj)[:, None] * nj
            ok_path, extra_m = self._validate(o, z0, tan_el, el_r, ray, seq, v_look, d)
            if ok_path.any():
                found_rays = ray[ok_path]
                found_extra = extra_m[ok_path]
                # Least extra path per ray among the viable sequences of this depth.
                order = np.lexsort((found_extra, found_rays))
                found_rays, found_extra = found_rays[order], found_extra[order]
                first = np.ones(found_rays.size, dtype=bool)
                first[1:] = found_rays[1:] != found_rays[:-1]
                n_refl[found_rays[first]] = depth
                extra[found_rays[first]] = found_extra[first]
                alive_ray[found_rays] = False
                pend_count_ep = np.bincount(
                    grp_of_ray[pending[alive_ray[pending]]], minlength=n_grp
                )
                if not pend_count_ep.any():
                    return
                # Drop epochs whose satellites are all resolved.
                keep = pend_count_ep[ep] > 0
                ep, img, lo, hi, faces = ep[keep], img[keep], lo[keep], hi[keep], faces[keep]

    def _validate(
        self,
        o_all: np.ndarray,
        z_all: np.ndarray,
        tan_all: np.ndarray,
        el_all: np.ndarray,
        ray: np.ndarray,
        faces: np.ndarray,
        v_look: np.ndarray,
        d_all: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Back-trace each candidate from the receiver; (viable, extra path m) per candidate."""
        c = ray.size
        alive = np.arange(c)
        o = o_all[ray].copy()
        z = z_all[ray].copy()
        tan_el = tan_all[ray]
        v = v_look.copy()
        s_total = np.zeros(c)
        prev = np.full(c, -1, dtype=np.int64)
        for step in range(faces.shape[1]):
            f = faces[alive, step]
            k = f // 2
            side = np.where(f % 2 == 1, 1.0, -1.0)
            nrm = self._n[k] * side[:, None]
            oa, za, va, ta = o[alive], z[alive], v[alive], tan_el[alive]
            rel = oa - self._p0[k]
            ov = np.einsum("ci,ci->c", rel, nrm)  # signed distance from the centre plane
            dist = ov - self._half[k]
            dn = np.einsum("ci,ci->c", va, nrm)
            good = (dist > 1e-6) & (dn < -_EPS)
            with np.errstate(divide="ignore", invalid="ignore"):
                s_hit = np.where(good, dist / -dn, 0.0)
            u_hit = np.einsum("ci,ci->c", rel + s_hit[:, None] * va, self._t[k])
            z_hit = za + s_hit * ta
            good &= (u_hit >= 0.0) & (u_hit <= self._len[k]) & (z_hit < self._height[k])
            win = self._win[k]  # (C, K, 4)
            in_window = (
                (u_hit[:, None] >= win[..., 0])
                & (u_hit[:, None] <= win[..., 1])
                & (z_hit[:, None] >= win[..., 2])
                & (z_hit[:, None] <= win[..., 3])
            ).any(axis=1)
            good &= ~in_window
            idx = np.flatnonzero(good)
            # The target wall is excluded too: a ray meeting a box's face from the front
            # cannot have touched that box before (and rounding must not say otherwise).
            good[idx] = ~self._segment_blocked(
                oa[idx],
                za[idx],
                va[idx],
                ta[idx],
                s_hit[idx],
                np.column_stack([prev[alive][idx], k[idx]]),
            )
            alive, s_hit, va, nrm, k = (
                alive[good],
                s_hit[good],
                va[good],
                nrm[good],
                k[good],
            )
            o[alive] = o[alive] + s_hit[:, None] * va
            z[alive] = z[alive] + s_hit * tan_el[alive]
            s_total[alive] += s_hit
            v[alive] = va - 2.0 * np.einsum("ci,ci->c", va, nrm)[:, None] * nrm
            prev[alive] = k
            if alive.size == 0:
                break
        viable = np.zeros(c, dtype=bool)
        if alive.size:
            escape = ~self._segment_blocked(
                o[alive],
                z[alive],
                v[alive],
                tan_el[alive],
                np.full(alive.size, np.inf),
                prev[alive],
            )
            viable[alive[escape]] = True
        # Extra path: 3-D path length minus the advance of the plane wave front along d.
        el = el_all[ray]
        cos_el = np.cos(el)
        d = d_all[ray]
        start = o_all[ray]
        disp_h = np.einsum("ci,ci->c", o - start, d) * cos_el
        disp_z = (z - z_all[ray]) * np.sin(el)
        extra_m = s_total / np.maximum(cos_el, _EPS) - disp_h - disp_z
        return viable, np.maximum(extra_m, 0.0)


def _slab(o: np.ndarray, dvec: np.ndarray, lo: Any, hi: Any) -> tuple[np.ndarray, np.ndarray]:
    """Parameter interval where o + s·dvec lies in [lo, hi]. A parallel ray gets (-inf, inf)
    inside the slab and an empty (inf, inf) interval outside, through IEEE infinities."""
    inv = 1.0 / dvec
    s1 = (lo - o) * inv
    s2 = (hi - o) * inv
    return np.minimum(s1, s2), np.maximum(s1, s2)


def _cap_index(group: np.ndarray, cap: int, key: np.ndarray) -> np.ndarray:
    """Indices (ascending) keeping at most ``cap`` entries per group value: the ones with the
    smallest ``key``."""
    if group.size == 0 or np.bincount(group).max() <= cap:
        return np.arange(group.size)
    # One float sort key (group major, key minor) is much faster than a lexsort.
    span = float(np.max(key) - np.min(key)) + 1.0
    order = np.argsort(group * span + (key - np.min(key)), kind="stable")
    g = group[order]
    start = np.ones(g.size, dtype=bool)
    start[1:] = g[1:] != g[:-1]
    group_start = np.maximum.accumulate(np.where(start, np.arange(g.size), 0))
    rank = np.arange(g.size) - group_start
    keep = order[rank < cap]
    keep.sort()
    return keep


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]


def _mirror(v: np.ndarray, n: np.ndarray) -> np.ndarray:
    return v - 2.0 * np.einsum("ci,ci->c", v, n)[:, None] * n


def _cone_intersect(
    lo1: np.ndarray, hi1: np.ndarray, lo2: np.ndarray, hi2: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Intersection of counter-clockwise cones lo -> hi (each under 180 degrees):
    (lo, hi, non-empty)."""

    def within(v: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
        return (_cross(lo, v) >= -1e-12) & (_cross(v, hi) >= -1e-12)

    lo2_in = within(lo2, lo1, hi1)
    lo1_in = within(lo1, lo2, hi2)
    hi2_in = within(hi2, lo1, hi1)
    lo = np.where(lo2_in[:, None], lo2, lo1)
    hi = np.where(hi2_in[:, None], hi2, hi1)
    return lo, hi, lo2_in | lo1_in
