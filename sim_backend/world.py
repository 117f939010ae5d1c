"""Scenario files: TOML -> a validated, frozen :class:`World`.

PUBLIC API
- ``load_world(path) -> World``: read a scenario (following ``include = [...]``).
- ``loads_world(text, base_dir=".", source="<string>") -> World``: same from text.
- ``merge_fragment(world, path) -> World``: merge a TOML fragment (e.g. the gap tool's
  ``effects.toml``) on top of a loaded world and validate again.
- ``World.to_toml() -> str``: a resolved, self-contained copy (absolute almanac and mission
  file paths, includes merged, the LCE CSV inlined) that loads back to an equal world.
- ``World.walls_model() -> buildings.Walls | None``, ``World.waypoints_latlon()``,
  ``World.waypoints_enu_m()``, ``World.effect_objects()``, ``World.lce_array()``.
- ``DEFAULT_ALMANAC``: the packaged YUMA almanac (USCG, GPS week 2086, 2020-01-01).

Scenario layout (every key optional unless stated; errors name the dotted key)::

    name = "open field"          # required
    start_utc = "2020-01-01T12:00:00Z"   # ISO-8601 string or TOML datetime; without an
                                         # offset = UTC, a date alone = its 00:00 UTC;
                                         # GPS epoch (1980-01-06) .. 9999-11-30T00:00:00Z
    duration_s = 600.0
    seed = 1
    almanac = "almanac.txt"      # relative to the scenario file; default DEFAULT_ALMANAC
    include = ["effects.toml"]   # merged first; this file's own keys win
    [origin]  lat_deg, lon_deg (required), alt_m
    [gnss]    fidelity "seed"|"pseudorange", mask_deg, rate_hz 1..4, nmea_decimals 4..7, baud,
              seed_uere "modelled"|"re_ase_lce", re_m, ase_m, max_channels,
              lce_cell_m, lce_east0_m, lce_north0_m, lce_outside_m,
              lce_sigma_m = [[...], ...] (row i = north cell i) or lce_csv = "map.csv";
              re_m, ase_m and the lce_* keys only with fidelity = "seed" and
              seed_uere = "re_ase_lce", seed_uere only with fidelity = "seed" (given
              elsewhere they would do nothing: a ConfigError)
    [atmosphere]  the fields of sim_backend.atmosphere.Atmosphere
    [[walls]]     x0_m, y0_m, x1_m, y1_m, thickness_m, height_m,
                  windows = [{u0_m, u1_m, z0_m, z1_m}, ...], penetration_db, refractive_index
    [[buildings]] x0_m, y0_m, x1_m, y1_m, height_m, thickness_m, penetration_db,
                  refractive_index  (four closed walls of one material)
    [roof] or [[roofs]]  x0_m, y0_m, x1_m, y1_m, height_m, holes = [{x0_m, y0_m, x1_m, y1_m}],
                  penetration_db, thickness_m, refractive_index
    Materials are optional: without ``penetration_db`` a wall or roof is opaque (the seed's
    model); with it, a blocked ray may arrive through it with that loss (dB per crossing) and
    a delay of (refractive_index - 1) x the path inside (see sim_backend.buildings).
    [vehicle] max_speed_mps, turn_rate_dps, motor_tau_s, start_heading_deg, start_east_m,
              start_north_m, slope_east_pct, slope_north_pct, antenna_height_m,
              stuck_from_s, stuck_until_s, stuck_mode "blocked"|"slipping" (a fault)
    [compass] a plain table handed to the compass emulation
    [[effects]] {name = "...", params...}: sim_backend.effects layers (validated by name)
    [mission] waypoints = [[lat, lon], ...] and/or waypoints_enu = [[east_m, north_m], ...],
              or file = "route.gpx" (relative to the scenario file; .waypoints, .plan, .gpx,
              .csv, .kml, read by x6wd.core.mission_files as ``x6wd mission show`` reads them);
              an empty list or table is refused (leave [mission] out for a static survey)
    [navigation], [safety], [failsafe], [odometry], [gnss_noise]: the robot's configuration
              (x6wd.core.config), each key defaulting to the robot's default, so a scenario
              overrides only what it means to; :func:`with_robot_config` lays a robot
              config file underneath instead
    [encoders] the simulated wheel encoders' truth (sim_backend.odometry.EncoderParams)

Merging (includes and fragments): tables merge key by key, arrays of tables (walls,
buildings, roofs, effects) are concatenated, any other value is replaced by the later file.
A file reached by two includes (a diamond: both include a shared site file) is applied once,
at its first include (twice would double its effects, walls and roofs); a file named twice
in one ``include`` list and a circular include are errors. An error names the file that
holds the key, an included one with its include chain, and numbers arrays of tables as in
that file.
"""

from __future__ import annotations

import copy
import csv
import dataclasses
import json
import math
import re
import tomllib
from dataclasses import dataclass, field
from datetime import UTC, date, datetime, timedelta
from datetime import time as dt_time
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np

from sim_backend.atmosphere import Atmosphere
from sim_backend.buildings import Hole, Roof, Wall, Walls, Window, building
from sim_backend.compass import CompassSetup
from sim_backend.nmea_out import MINUTE_DECIMALS
from sim_backend.odometry import EncoderParams
from sim_backend.vehicle import STUCK_MODES, check_stuck
from x6wd.core.config import (
    FailsafeConfig,
    GnssNoiseConfig,
    NavigationConfig,
    OdometryConfig,
    SafetyConfig,
    build,
    check_drive_vs_stuck,
    check_stale_vs_rate,
)
from x6wd.core.errors import ConfigError, ParseError
from x6wd.core.files import read_text_bounded, require_regular
from x6wd.core.mission_files import load_file

DEFAULT_ALMANAC = Path(__file__).resolve().parent / "data" / "almyuma_01jan2020.txt"
DEFAULT_ALMANAC_DATE = datetime(2020, 1, 1, tzinfo=UTC)
"""The packaged almanac's real date: its 10-bit week (38) is read as week 2086 near it."""
GPS_EPOCH_UTC = datetime(1980, 1, 6, tzinfo=UTC)
"""GPS time starts here; the simulated sky (GPS seconds, almanac weeks) has no earlier time."""
MAX_DURATION_S = 30 * 86400.0
"""The longest run (s): ``duration_s`` and ``x6wd sim --duration`` are capped here (a run's
per-tick arrays grow with it)."""
LATEST_START_UTC = datetime(9999, 12, 31, tzinfo=UTC) - timedelta(seconds=MAX_DURATION_S, days=1)
"""The latest ``start_utc`` (9999-11-30T00:00:00Z): a run of the longest duration (a
scenario's or ``x6wd sim --duration``'s), with a day to spare, still ends inside the dates
Python (and so the NMEA date fields) can hold, which end with the year 9999."""
MAX_SPEED_MPS = 14.0 / 3.6
_LIST_TABLES = ("walls", "buildings", "roofs", "effects")


def _rng(lo: float | None = None, hi: float | None = None, **kw: Any) -> dict[str, Any]:
    return {"min": lo, "max": hi, **kw}


@dataclass(frozen=True)
class Origin:
    """Origin of the local ENU frame (WGS-84 degrees, metres above mean sea level)."""

    lat_deg: float = field(default=0.0, metadata=_rng(-89.0, 89.0))
    lon_deg: float = field(default=0.0, metadata=_rng(-180.0, 180.0))
    alt_m: float = field(default=0.0, metadata=_rng(-500.0, 9000.0))


@dataclass(frozen=True)
class GnssSettings:
    """The simulated receiver: fidelity, mask, output format and seed-003 error terms."""

    fidelity: str = field(default="pseudorange", metadata={"choices": ("seed", "pseudorange")})
    mask_deg: float = field(default=5.0, metadata=_rng(0.0, 60.0))
    rate_hz: float = field(default=1.0, metadata=_rng(1.0, 4.0))
    nmea_decimals: int = field(default=5, metadata={"choices": MINUTE_DECIMALS})
    baud: int = field(default=9600, metadata={"choices": (4800, 9600, 19200, 38400, 57600, 115200)})
    seed_uere: str = field(default="modelled", metadata={"choices": ("modelled", "re_ase_lce")})
    re_m: float = field(default=0.5, metadata=_rng(0.0, 100.0))
    ase_m: float | None = field(default=None, metadata=_rng(0.0, 100.0))
    max_channels: int = field(default=12, metadata=_rng(4, 64))
    lce_cell_m: float = field(default=10.0, metadata=_rng(0.01, 10000.0))
    lce_east0_m: float = 0.0
    lce_north0_m: float = 0.0
    lce_outside_m: float = field(default=0.0, metadata=_rng(0.0, 1000.0))
    lce_sigma_m: tuple[tuple[float, ...], ...] = ()
    lce_csv: str = ""


@dataclass(frozen=True)
class VehicleSettings:
    """The robot in the scenario: limits, start pose, terrain slope (percent = 100·dz/dx),
    and an injected fault: stuck from ``stuck_from_s`` (simulated s; None: never) until
    ``stuck_until_s`` (None: for good), ``stuck_mode`` "blocked" (neither body nor wheels
    move) or "slipping" (the wheels turn and the encoders count, the body stays)."""

    max_speed_mps: float = field(default=MAX_SPEED_MPS, metadata=_rng(0.01, MAX_SPEED_MPS))
    turn_rate_dps: float = field(default=90.0, metadata=_rng(1.0, 720.0))
    motor_tau_s: float = field(default=0.25, metadata=_rng(0.0, 10.0))
    start_heading_deg: float = field(default=0.0, metadata=_rng(0.0, 360.0))
    # the same bounds as mission.waypoints_enu: the scenario's flat-earth frame
    start_east_m: float = field(default=0.0, metadata=_rng(-1e6, 1e6))
    start_north_m: float = field(default=0.0, metadata=_rng(-1e6, 1e6))
    slope_east_pct: float = field(default=0.0, metadata=_rng(-170.0, 170.0))
    slope_north_pct: float = field(default=0.0, metadata=_rng(-170.0, 170.0))
    antenna_height_m: float = field(default=0.34, metadata=_rng(0.0, 100.0))
    stuck_from_s: float | None = field(default=None, metadata=_rng(0.0, 30 * 86400.0))
    stuck_until_s: float | None = field(default=None, metadata=_rng(0.0, 30 * 86400.0))
    stuck_mode: str = field(default="blocked", metadata={"choices": STUCK_MODES})

    def __post_init__(self) -> None:
        check_stuck(self.stuck_from_s, self.stuck_until_s, self.stuck_mode)


@dataclass(frozen=True)
class MissionSettings:
    """Waypoints as geographic (lat, lon) degrees and/or local (east, north) metres, or read
    from a mission ``file`` (its absolute path once loaded; ``waypoints`` then holds what the
    project's reader, :func:`x6wd.core.mission_files.load_file`, read from it)."""

    waypoints: tuple[tuple[float, ...], ...] = ()
    waypoints_enu: tuple[tuple[float, ...], ...] = ()
    file: str = ""


@dataclass(frozen=True)
class _Top:
    name: str = ""
    start_utc: str = "2020-01-01T12:00:00Z"
    duration_s: float = field(default=600.0, metadata=_rng(0.001, MAX_DURATION_S))
    seed: int = field(default=1, metadata=_rng(0, 2**63 - 1))
    almanac: str = ""


@dataclass(frozen=True, eq=False)
class World:
    """A validated scenario. ``raw`` is the merged TOML table it was built from (with paths
    resolved); ``source`` the file it came from (None for text)."""

    name: str
    origin: Origin
    start_utc: datetime
    duration_s: float
    seed: int
    almanac_path: Path
    gnss: GnssSettings
    atmosphere: Atmosphere
    walls: tuple[Wall, ...]
    roofs: tuple[Roof, ...]
    vehicle: VehicleSettings
    compass: dict[str, Any]
    effects: tuple[dict[str, Any], ...]
    mission: MissionSettings
    navigation: NavigationConfig
    safety: SafetyConfig
    raw: dict[str, Any] = field(repr=False)
    failsafe: FailsafeConfig = field(default_factory=FailsafeConfig)
    odometry: OdometryConfig = field(default_factory=OdometryConfig)
    gnss_noise: GnssNoiseConfig = field(default_factory=GnssNoiseConfig)
    encoders: EncoderParams = field(default_factory=EncoderParams)
    source: Path | None = None
    mission_notes: tuple[str, ...] = ()
    """What the mission file's reader read but the robot does not drive (a GPX route's
    waypoints beside it, ...), one sentence each: ``x6wd sim`` prints them."""

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, World):
            return NotImplemented
        skip = {"raw", "source", "mission_notes"}
        return all(
            getattr(self, f.name) == getattr(other, f.name)
            for f in dataclasses.fields(self)
            if f.name not in skip
        )

    __hash__ = None  # type: ignore[assignment]

    @cached_property
    def _walls_model(self) -> Walls | None:
        if not self.walls and not self.roofs:
            return None
        return Walls(self.walls, self.roofs)

    def walls_model(self) -> Walls | None:
        """The buildings scene for ray tracing, or None when there are no walls or roofs."""
        return self._walls_model

    def waypoints_enu_m(self) -> np.ndarray:
        """All waypoints as (N, 2) local east/north metres: geographic ones first (projected
        on the origin's tangent plane), then ``waypoints_enu``."""
        from sim_backend.geodesy import lla_to_enu

        rows: list[np.ndarray] = []
        if self.mission.waypoints:
            ll = np.array(self.mission.waypoints, dtype=float)
            enu = lla_to_enu(
                ll[:, 0],
                ll[:, 1],
                np.full(len(ll), self.origin.alt_m),
                self.origin.lat_deg,
                self.origin.lon_deg,
                self.origin.alt_m,
            )
            rows.append(np.asarray(enu, dtype=float).reshape(-1, 3)[:, :2])
        if self.mission.waypoints_enu:
            rows.append(np.array(self.mission.waypoints_enu, dtype=float))
        return np.concatenate(rows) if rows else np.zeros((0, 2))

    def waypoints_latlon(self) -> np.ndarray:
        """All waypoints as (N, 2) latitude/longitude degrees (same order as
        :meth:`waypoints_enu_m`; local ones converted from the origin's ENU frame)."""
        from sim_backend.geodesy import enu_to_lla

        rows: list[np.ndarray] = []
        if self.mission.waypoints:
            rows.append(np.array(self.mission.waypoints, dtype=float))
        if self.mission.waypoints_enu:
            en = np.array(self.mission.waypoints_enu, dtype=float)
            enu = np.column_stack([en, np.zeros(len(en))])
            lat, lon, _alt = enu_to_lla(
                enu, self.origin.lat_deg, self.origin.lon_deg, self.origin.alt_m
            )
            rows.append(np.column_stack([np.atleast_1d(lat), np.atleast_1d(lon)]))
        return np.concatenate(rows) if rows else np.zeros((0, 2))

    def effect_objects(self) -> list[Any]:
        """The ``[[effects]]`` tables as :mod:`sim_backend.effects` layer objects, in order."""
        from sim_backend.effects import effect_from_params

        return [effect_from_params(e) for e in self.effects]

    def lce_array(self) -> np.ndarray | None:
        """The LCE grid (rows north, columns east, 1-sigma m) or None when not configured."""
        if not self.gnss.lce_sigma_m:
            return None
        return np.array(self.gnss.lce_sigma_m, dtype=float)

    def to_toml(self) -> str:
        """A resolved, self-contained TOML copy of this scenario."""
        return dumps_toml(self.raw)


# ------------------------------------------------------------------ loading


def _regular_or_said(path: str | Path, what: str) -> None:
    """:class:`ConfigError` naming ``path`` when it is not a regular file (a pipe, a FIFO, a
    device): a scenario is read more than once (its includes, its folder)."""
    try:
        require_regular(path)
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read {what}: {exc.strerror}") from None


def load_world(path: str | Path, check_rates: bool = True) -> World:
    """Read, merge (``include``) and validate a scenario file. An error names the file where
    the key is (an included file's with its include chain) and the key as written there.
    ``check_rates=False`` leaves out the [safety] staleness limits against the scenario's
    rates, for a robot config laid under it next (:func:`with_robot_config` checks them on
    the merged table: its [safety] may be what the rates need)."""
    _regular_or_said(path, "scenario")  # before resolve(): a pipe's /dev/fd/N resolves to
    p = Path(path).resolve()  # a /proc/PID/fd/pipe:[N] that does not exist
    src = _Sources()
    data, src.tree = src.read(p, (), None)
    try:
        return _build_world(data, p.parent, p, check_rates=check_rates)
    except ConfigError as exc:
        raise src.blame(exc, str(p)) from exc


def loads_world(text: str, base_dir: str | Path = ".", source: str = "<string>") -> World:
    """Validate scenario TOML text; relative paths resolve against ``base_dir``."""
    base = Path(base_dir).resolve()
    src = _Sources()
    data, src.tree = src.expand(_parse(text, source), base, (), source)
    try:
        return _build_world(data, base, None)
    except ConfigError as exc:
        raise src.blame(exc, source) from exc


def merge_fragment(world: World, path: str | Path) -> World:
    """A new world: ``world`` with the TOML fragment at ``path`` merged on top (its arrays of
    tables such as ``[[effects]]`` are appended, other keys replace)."""
    _regular_or_said(path, "scenario fragment")
    p = Path(path).resolve()
    fragment, _ = _Sources().read(p, (), None)
    _resolve_paths(fragment, p.parent)
    merged = _merge(world.raw, fragment)
    base = world.source.parent if world.source is not None else p.parent
    try:
        return _build_world(merged, base, world.source, known=world)
    except ConfigError as exc:  # keys numbered in the merged scenario (effects appended)
        raise ConfigError(f"{p}: {exc}") from exc


def _parse(text: str, source: str) -> dict[str, Any]:
    try:  # a leading byte-order mark (a Windows editor's) is no TOML error, as for the robot's
        return tomllib.loads(text.removeprefix("\ufeff"))
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{source}: not valid TOML: {exc}") from exc


def _tag(value: Any, file: str, key: str = "") -> Any:
    """``value``'s shape with every leaf replaced by (``file``, its dotted key in that file)."""
    if isinstance(value, dict):
        return {k: _tag(v, file, f"{key}.{k}" if key else k) for k, v in value.items()}
    if isinstance(value, list):
        return [_tag(v, file, f"{key}[{i}]") for i, v in enumerate(value)]
    return (file, key)


def _leaves(node: Any, rel: str = "") -> list[tuple[tuple[str, str], str]]:
    """The (file, key) leaves under a tagged node, each with its key relative to the node."""
    if isinstance(node, tuple):
        return [(node, rel)]
    if isinstance(node, dict):
        return [leaf for k, v in node.items() for leaf in _leaves(v, f"{rel}.{k}")]
    return [leaf for i, v in enumerate(node) for leaf in _leaves(v, f"{rel}[{i}]")]


_LEADING_KEY = re.compile(r"[A-Za-z_]\w*(?:\[\d+\]|\.[A-Za-z_]\w*)*")
_KEY_STEP = re.compile(r"\.?([A-Za-z_]\w*)|\[(\d+)\]")


class _Sources:
    """Reads a scenario and its includes, and remembers where each key came from.

    Validation runs on the merged table, so without this an error blamed the top file for a
    key of an included one, and numbered an ``[[effects]]`` table by its place in the merged
    list. ``tree`` has the merged table's shape, each leaf (file, key in that file); ``by``
    maps an included file to the file that included it."""

    def __init__(self) -> None:
        self.tree: dict[str, Any] = {}
        self.by: dict[str, str | None] = {}

    def read(
        self, path: Path, stack: tuple[Path, ...], by: str | None
    ) -> tuple[dict[str, Any], dict[str, Any]]:
        if path in stack:
            chain = " -> ".join(str(s) for s in (*stack, path))
            raise ConfigError(f"include: circular include {chain}")
        if str(path) in self.by:
            # a diamond (two includes that both include it): a shared file is applied once,
            # at its first include; twice would double its [[effects]], walls and roofs
            return {}, {}
        self.by[str(path)] = by
        try:
            text = read_text_bounded(path)
            data = _parse(text, str(path))
        except OSError as exc:
            raise ConfigError(
                f"{path}: cannot read scenario: {exc.strerror or exc}{self.via(str(path))}"
            ) from exc
        except UnicodeDecodeError as exc:  # TOML is UTF-8: a binary or Latin-1 file is no scenario
            raise ConfigError(
                f"{path}: not a scenario: not UTF-8 text (byte {exc.start}: {exc.reason})"
                + self.via(str(path))
            ) from exc
        except ConfigError as exc:
            raise ConfigError(f"{exc}{self.via(str(path))}") from exc
        return self.expand(data, path.parent, (*stack, path), str(path))

    def expand(
        self, data: dict[str, Any], base: Path, stack: tuple[Path, ...], source: str
    ) -> tuple[dict[str, Any], dict[str, Any]]:
        """``data`` (from ``source``) with its includes merged underneath, and its tree."""
        includes = data.pop("include", [])
        if isinstance(includes, str):
            includes = [includes]
        if not isinstance(includes, list) or not all(isinstance(i, str) for i in includes):
            raise ConfigError(
                f"{source}: include: expected a list of file names, got {includes!r}"
                + self.via(source)
            )
        _resolve_paths(data, base)
        paths = [(base / inc).resolve() for inc in includes]
        for inc, inc_path in zip(includes, paths, strict=True):
            if paths.count(inc_path) > 1:
                raise ConfigError(
                    f"{source}: include: {inc} ({inc_path}) is listed twice{self.via(source)}"
                )
        merged: dict[str, Any] = {}
        tree: dict[str, Any] = {}
        for inc_path in paths:
            part, part_tree = self.read(inc_path, stack, source)
            _resolve_paths(part, inc_path.parent)
            merged, tree = _merge(merged, part), _merge(tree, part_tree)
        return _merge(merged, data), _merge(tree, _tag(data, source))

    def blame(self, exc: ConfigError, default: str) -> ConfigError:
        """``exc`` (a message leading with the merged table's dotted key) prefixed with the
        file that holds that key (or its table), the key renumbered as in that file; else
        ``default``, the top file (a top-level key missing, a table from two files)."""
        msg = str(exc)
        lead = _LEADING_KEY.match(msg)
        if lead and lead.group().startswith("roofs[") and "roof" in self.tree:
            return ConfigError(f"{default}: {msg}")  # roofs[0] is then [roof] (_build_walls)
        node: Any = self.tree
        rest = ""
        for step in _KEY_STEP.finditer(lead.group() if lead else ""):
            name, index = step.groups()
            if name is not None and isinstance(node, dict) and name in node:
                node = node[name]
            elif index is not None and isinstance(node, list) and int(index) < len(node):
                node = node[int(index)]
            else:
                rest = step.string[step.start() :]
                break
        leaves = _leaves(node) if node is not self.tree else []
        files = {file for (file, _), _ in leaves}
        if len(files) != 1:
            return ConfigError(f"{default}: {msg}")
        (file, key), rel = leaves[0]
        assert lead is not None  # a node was reached
        msg = key[: len(key) - len(rel)] + rest + msg[lead.end() :]
        return ConfigError(f"{file}: {msg}{self.via(file)}")

    def via(self, file: str) -> str:
        """`` (included from top -> ... -> includer)`` for an included file, else ''."""
        chain = []
        by = self.by.get(file)
        while by is not None:
            chain.append(by)
            by = self.by.get(by)
        return f" (included from {' -> '.join(reversed(chain))})" if chain else ""


def _resolve_paths(data: dict[str, Any], base: Path) -> None:
    """Make file paths absolute against the folder of the file that named them."""
    if isinstance(data.get("almanac"), str) and data["almanac"]:
        data["almanac"] = str((base / data["almanac"]).resolve())
    gnss = data.get("gnss")
    if isinstance(gnss, dict) and isinstance(gnss.get("lce_csv"), str) and gnss["lce_csv"]:
        gnss["lce_csv"] = str((base / gnss["lce_csv"]).resolve())
    mission = data.get("mission")
    if isinstance(mission, dict) and isinstance(mission.get("file"), str) and mission["file"]:
        mission["file"] = str((base / mission["file"]).resolve())


def _merge(a: dict[str, Any], b: dict[str, Any]) -> dict[str, Any]:
    out = copy.deepcopy(a)
    for key, value in b.items():
        if key in out and isinstance(out[key], dict) and isinstance(value, dict):
            out[key] = _merge(out[key], value)
        elif key in _LIST_TABLES and isinstance(out.get(key), list) and isinstance(value, list):
            out[key] = out[key] + copy.deepcopy(value)
        else:
            out[key] = copy.deepcopy(value)
    return out


def _table(data: dict[str, Any], key: str) -> dict[str, Any]:
    value = data.get(key, {})
    if not isinstance(value, dict):
        raise ConfigError(f"{key}: expected a table, got {value!r}")
    return value


def _table_list(data: dict[str, Any], key: str) -> list[dict[str, Any]]:
    value = data.get(key, [])
    if isinstance(value, dict):
        value = [value]
    if not isinstance(value, list) or not all(isinstance(v, dict) for v in value):
        raise ConfigError(f"{key}: expected an array of tables ([[{key}]]), got {value!r}")
    return value


def _plain(cls: type, data: Any, prefix: str, required: tuple[str, ...] = ()) -> Any:
    """Validate a table into a dataclass of plain fields (walls, windows, roofs, holes)."""
    if not isinstance(data, dict):
        raise ConfigError(f"{prefix}: expected a table, got {data!r}")
    names = [f.name for f in dataclasses.fields(cls)]
    for key in data:
        if key not in names:
            raise ConfigError(f"{prefix}.{key}: unknown key (valid keys: {', '.join(names)})")
    for key in required:
        if key not in data:
            raise ConfigError(f"{prefix}.{key}: required")
    kwargs: dict[str, Any] = {}
    for key, value in data.items():
        if isinstance(value, (list, dict)):
            kwargs[key] = value
            continue
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{prefix}.{key}: expected a number, got {value!r}")
        if not math.isfinite(value):
            raise ConfigError(f"{prefix}.{key}: must be finite, got {value!r}")
        kwargs[key] = float(value)
    try:
        return cls(**kwargs)
    except ConfigError as exc:
        raise ConfigError(f"{prefix}: {exc}") from exc


def _build_walls(data: dict[str, Any]) -> tuple[tuple[Wall, ...], tuple[Roof, ...]]:
    walls: list[Wall] = []
    for i, spec in enumerate(_table_list(data, "walls")):
        spec = dict(spec)
        raw_windows = spec.pop("windows", [])
        if not isinstance(raw_windows, list):
            raise ConfigError(f"walls[{i}].windows: expected an array of tables")
        windows = tuple(
            _plain(Window, w, f"walls[{i}].windows[{j}]", ("u0_m", "u1_m", "z0_m", "z1_m"))
            for j, w in enumerate(raw_windows)
        )
        wall = _plain(Wall, spec, f"walls[{i}]", ("x0_m", "y0_m", "x1_m", "y1_m"))
        try:
            walls.append(dataclasses.replace(wall, windows=windows))
        except ConfigError as exc:
            raise ConfigError(f"walls[{i}]: {exc}") from exc
    keys = (
        "x0_m",
        "y0_m",
        "x1_m",
        "y1_m",
        "height_m",
        "thickness_m",
        "penetration_db",
        "refractive_index",
    )
    for i, spec in enumerate(_table_list(data, "buildings")):
        for key in spec:
            if key not in keys:
                raise ConfigError(
                    f"buildings[{i}].{key}: unknown key (valid keys: {', '.join(keys)})"
                )
        for key in keys[:5]:
            if key not in spec:
                raise ConfigError(f"buildings[{i}].{key}: required")
            if isinstance(spec[key], bool) or not isinstance(spec[key], (int, float)):
                raise ConfigError(f"buildings[{i}].{key}: expected a number, got {spec[key]!r}")
        try:
            walls.extend(building(**{k: float(v) for k, v in spec.items()}))
        except ConfigError as exc:
            raise ConfigError(f"buildings[{i}]: {exc}") from exc
    roof_specs = _table_list(data, "roofs")
    if "roof" in data:
        roof_specs = [_table(data, "roof"), *roof_specs]
    roofs: list[Roof] = []
    for i, spec in enumerate(roof_specs):
        spec = dict(spec)
        raw_holes = spec.pop("holes", [])
        if not isinstance(raw_holes, list):
            raise ConfigError(f"roofs[{i}].holes: expected an array of tables")
        holes = tuple(
            _plain(Hole, h, f"roofs[{i}].holes[{j}]", ("x0_m", "y0_m", "x1_m", "y1_m"))
            for j, h in enumerate(raw_holes)
        )
        roof = _plain(Roof, spec, f"roofs[{i}]", ("x0_m", "y0_m", "x1_m", "y1_m", "height_m"))
        roofs.append(dataclasses.replace(roof, holes=holes))
    return tuple(walls), tuple(roofs)


def parse_start_utc(value: Any) -> datetime:
    """``start_utc``: an ISO-8601 string or a TOML datetime; one with an offset is converted
    to UTC, one without (naive) is taken as UTC, as is a date alone (its 00:00). A TOML time
    of day alone has no date: refused."""
    if isinstance(value, datetime):
        dt = value
    elif isinstance(value, date):  # a TOML date (1979-05-27): as the string "1979-05-27"
        dt = datetime.combine(value, dt_time())
    elif isinstance(value, dt_time):
        raise ConfigError(
            f"start_utc: {value.isoformat()} is a time of day without a date; give a date "
            "and time, e.g. 2020-01-01T12:00:00Z"
        )
    elif isinstance(value, str):
        try:
            dt = datetime.fromisoformat(value.replace("Z", "+00:00"))
        except ValueError as exc:
            raise ConfigError(f"start_utc: not an ISO-8601 time: {value!r}") from exc
    else:
        raise ConfigError(f"start_utc: expected an ISO-8601 time, got {value!r}")
    dt = dt.replace(tzinfo=UTC) if dt.tzinfo is None else dt.astimezone(UTC)
    if dt < GPS_EPOCH_UTC:
        raise ConfigError(
            f"start_utc: {dt.isoformat()} is before the GPS epoch (1980-01-06T00:00:00Z): "
            "there is no GPS time, and so no simulated sky, before it"
        )
    if dt > LATEST_START_UTC:
        raise ConfigError(
            f"start_utc: {dt.isoformat()} is after {LATEST_START_UTC.isoformat()}, the latest "
            "start from which a run of up to 30 days ends inside the supported date range "
            "(up to the year 9999)"
        )
    return dt


def _read_lce_csv(path: str) -> tuple[tuple[float, ...], ...]:
    try:
        require_regular(path)
        with open(path, encoding="utf-8", newline="") as fh:
            rows = [r for r in csv.reader(fh) if r and not r[0].lstrip().startswith("#")]
    except OSError as exc:
        raise ConfigError(f"gnss.lce_csv: cannot read {path}: {exc.strerror or exc}") from exc
    except UnicodeDecodeError as exc:
        raise ConfigError(f"gnss.lce_csv: {path}: not UTF-8 text ({exc.reason})") from exc
    try:
        grid = tuple(tuple(float(c) for c in row) for row in rows)
    except ValueError as exc:
        raise ConfigError(f"gnss.lce_csv: {path}: not a grid of numbers ({exc})") from exc
    return grid


SEED_003_KEYS = (
    "re_m",
    "ase_m",
    "lce_sigma_m",
    "lce_csv",
    "lce_cell_m",
    "lce_east0_m",
    "lce_north0_m",
    "lce_outside_m",
)
"""The [gnss] keys of the seed-003 error form: they act only under ``fidelity = "seed"`` with
``seed_uere = "re_ase_lce"`` (sim_backend.gnss.GnssModel)."""


def _check_gnss_form(gnss: GnssSettings, given: set[str]) -> None:
    """Refuse [gnss] keys given where the fidelity and error form make them do nothing (a
    ``re_m = 50`` under the pseudorange fidelity gave the output of none)."""
    if gnss.fidelity != "seed" and "seed_uere" in given:
        raise ConfigError(
            f'gnss.seed_uere: acts only under fidelity = "seed" (this scenario has fidelity = '
            f'"{gnss.fidelity}"); remove it or set fidelity = "seed"'
        )
    idle = [k for k in SEED_003_KEYS if k in given]
    if idle and not (gnss.fidelity == "seed" and gnss.seed_uere == "re_ase_lce"):
        keys = ", ".join(f"gnss.{k}" for k in idle)
        raise ConfigError(
            f'{keys}: act only under fidelity = "seed" with seed_uere = "re_ase_lce" (this '
            f'scenario has fidelity = "{gnss.fidelity}", seed_uere = "{gnss.seed_uere}"), '
            "where they would be ignored; remove them or set those two keys"
        )


def _check_grid(grid: tuple[tuple[float, ...], ...], key: str) -> None:
    widths = {len(r) for r in grid}
    if len(widths) > 1 or 0 in widths:
        raise ConfigError(f"{key}: rows must be non-empty and of equal length")
    for row in grid:
        for v in row:
            if not (math.isfinite(v) and v >= 0.0):
                raise ConfigError(f"{key}: values must be finite and >= 0 m, got {v!r}")


_TOP_KEYS = {
    "name",
    "start_utc",
    "duration_s",
    "seed",
    "almanac",
    "origin",
    "gnss",
    "atmosphere",
    "walls",
    "buildings",
    "roof",
    "roofs",
    "vehicle",
    "compass",
    "effects",
    "mission",
    "navigation",
    "safety",
    "failsafe",
    "odometry",
    "gnss_noise",
    "encoders",
}

ROBOT_SECTIONS = ("navigation", "safety", "failsafe", "odometry", "gnss_noise")
"""The robot configuration's sections a scenario may carry (and a robot config provides)."""


def _build_world(
    data: dict[str, Any],
    base: Path,
    source: Path | None,
    known: World | None = None,
    check_rates: bool = True,
) -> World:
    """The world of the scenario table ``data``; ``known``: a world built before whose mission
    file is not read again if ``data``'s ``[mission]`` is the same (:func:`_build_mission`);
    ``check_rates``: the [safety] staleness limits against the scenario's rates."""
    unknown = sorted(set(data) - _TOP_KEYS)
    if unknown:
        raise ConfigError(f"{unknown[0]}: unknown key (valid keys: {', '.join(sorted(_TOP_KEYS))})")
    data = copy.deepcopy(data)
    start = data.get("start_utc", _Top.start_utc)
    start_utc = parse_start_utc(start)
    top_data = {k: data[k] for k in ("name", "duration_s", "seed", "almanac") if k in data}
    top = build(_Top, top_data)
    if not top.name:
        raise ConfigError("name: required (a non-empty string)")
    origin_data = _table(data, "origin")
    for key in ("lat_deg", "lon_deg"):
        if key not in origin_data:
            raise ConfigError(f"origin.{key}: required")
    origin = build(Origin, origin_data, "origin.")
    almanac = Path(top.almanac) if top.almanac else DEFAULT_ALMANAC
    if not almanac.is_absolute():
        almanac = (base / almanac).resolve()
    if not almanac.is_file():
        raise ConfigError(f"almanac: no such file: {almanac}")
    data["almanac"] = str(almanac)
    gnss_data = dict(_table(data, "gnss"))
    if gnss_data.get("lce_csv") and gnss_data.get("lce_sigma_m"):
        raise ConfigError("gnss.lce_csv: give either lce_csv or lce_sigma_m, not both")
    gnss = build(GnssSettings, gnss_data, "gnss.")
    given_gnss = set(gnss_data)
    if gnss.lce_csv:
        csv_path = Path(gnss.lce_csv)
        if not csv_path.is_absolute():
            csv_path = (base / csv_path).resolve()
        grid = _read_lce_csv(str(csv_path))
        gnss = dataclasses.replace(gnss, lce_sigma_m=grid, lce_csv="")
        gnss_data.pop("lce_csv")
        gnss_data["lce_sigma_m"] = [list(r) for r in grid]
        data["gnss"] = gnss_data
    if gnss.lce_sigma_m:
        _check_grid(gnss.lce_sigma_m, "gnss.lce_sigma_m")
    _check_gnss_form(gnss, given_gnss)
    atmosphere = build(Atmosphere, _table(data, "atmosphere"), "atmosphere.")
    walls, roofs = _build_walls(data)
    vehicle = build(VehicleSettings, _table(data, "vehicle"), "vehicle.")
    compass = dict(_table(data, "compass"))
    try:  # checked here, not at the run's start, so an error names the file like any other
        compass_rate_hz = CompassSetup.from_table(compass).rate_hz
    except ConfigError as exc:
        msg = str(exc)  # CompassErrors' own messages lead with the bare key
        raise ConfigError(msg if msg.startswith("compass.") else f"compass.{msg}") from exc
    effects = tuple(dict(e) for e in _table_list(data, "effects"))
    _check_effects(effects)
    mission, mission_notes = _build_mission(data, known)
    for key, points, lo, hi in (
        ("mission.waypoints", mission.waypoints, (-90.0, -180.0), (90.0, 180.0)),
        ("mission.waypoints_enu", mission.waypoints_enu, (-1e6, -1e6), (1e6, 1e6)),
    ):
        for i, pt in enumerate(points):
            if len(pt) != 2:
                raise ConfigError(f"{key}[{i}]: expected a pair, got {list(pt)}")
            if not all(math.isfinite(v) and lo[j] <= v <= hi[j] for j, v in enumerate(pt)):
                raise ConfigError(f"{key}[{i}]: out of range, got {list(pt)}")
    navigation = build(NavigationConfig, _table(data, "navigation"), "navigation.")
    safety = build(SafetyConfig, _table(data, "safety"), "safety.")
    if check_rates:  # the scenario's own rates: the robot config knows only its own
        check_stale_vs_rate(
            "safety.fix_stale_s",
            safety.fix_stale_s,
            gnss.rate_hz,
            f"gnss.rate_hz = {gnss.rate_hz:g} Hz",
        )
        check_stale_vs_rate(
            "safety.attitude_stale_s",
            safety.attitude_stale_s,
            compass_rate_hz,
            f"compass.rate_hz = {compass_rate_hz:g} Hz",
        )
    failsafe = build(FailsafeConfig, _table(data, "failsafe"), "failsafe.")
    odometry = build(OdometryConfig, _table(data, "odometry"), "odometry.")
    gnss_noise = build(GnssNoiseConfig, _table(data, "gnss_noise"), "gnss_noise.")
    encoders = build(EncoderParams, _table(data, "encoders"), "encoders.")
    return World(
        name=top.name,
        origin=origin,
        start_utc=start_utc,
        duration_s=top.duration_s,
        seed=top.seed,
        almanac_path=almanac,
        gnss=gnss,
        atmosphere=atmosphere,
        walls=walls,
        roofs=roofs,
        vehicle=vehicle,
        compass=compass,
        effects=effects,
        mission=mission,
        navigation=navigation,
        safety=safety,
        failsafe=failsafe,
        odometry=odometry,
        gnss_noise=gnss_noise,
        encoders=encoders,
        raw=data,
        source=source,
        mission_notes=mission_notes,
    )


MISSION_POINT_KEYS = ("waypoints", "waypoints_enu")


def _build_mission(
    data: dict[str, Any], known: World | None = None
) -> tuple[MissionSettings, tuple[str, ...]]:
    """The ``[mission]`` table: inline waypoints, or a mission file read with the project's
    own readers (the ones ``x6wd mission show`` and ``x6wd client load`` use). An explicitly
    empty list or table is refused: a static survey is a scenario without ``[mission]``.
    Returns the settings and the file reader's notes (what it read but does not drive).

    The file is read once: a world rebuilt from ``known`` (``--config``, a fragment) with the
    same ``[mission]`` keeps ``known``'s waypoints and notes (a FIFO or pipe has nothing
    left to read a second time, and a file read twice could differ)."""
    table = _table(data, "mission")
    if "mission" in data and not table:
        raise ConfigError(
            "mission: no waypoints (give waypoints, waypoints_enu or file); leave [mission] "
            "out for a static survey"
        )
    mission = build(MissionSettings, table, "mission.")
    for key in MISSION_POINT_KEYS:
        if key in table and not getattr(mission, key):
            raise ConfigError(f"mission.{key}: empty; leave [mission] out for a static survey")
    if "file" not in table:
        return mission, ()
    inline = [f"mission.{k}" for k in MISSION_POINT_KEYS if k in table]
    if inline:
        raise ConfigError(
            f"mission.file, {', '.join(inline)}: give either a mission file or inline "
            "waypoints, not both"
        )
    if not mission.file:
        raise ConfigError("mission.file: empty; name a .waypoints, .plan, .gpx, .csv or .kml file")
    if known is not None and known.raw.get("mission") == data.get("mission"):
        return known.mission, known.mission_notes
    try:
        read = load_file(mission.file)
    except ParseError as exc:  # its message leads with the file's path
        raise ConfigError(f"mission.file: {exc}") from exc
    points = tuple((wp.lat_deg, wp.lon_deg) for wp in read)
    return dataclasses.replace(mission, waypoints=points), tuple(read.notes)


def with_robot_config(world: World, robot_config: str | Path) -> World:
    """``world`` driven by the robot configuration file ``robot_config`` (e.g.
    config/x6wd.toml): its [navigation], [safety], [failsafe], [odometry] and [gnss_noise]
    keys, under the scenario's own keys of those sections (a scenario overrides on purpose).
    A bad robot config raises :class:`ConfigError` naming the file and key."""
    from x6wd.core.config import load

    p = Path(robot_config)
    load(p)  # validates the whole file, with its error messages
    robot = _robot_table(p)
    data = copy.deepcopy(world.raw)
    for sec in ROBOT_SECTIONS:
        merged = dict(robot.get(sec, {}))
        merged.update(data.get(sec, {}))
        if merged:
            data[sec] = merged
    base = world.source.parent if world.source is not None else Path(".")
    try:  # the rates' checks on the merged [safety] (load_world's check_rates=False)
        merged_world = _build_world(data, base, world.source, known=world)
    except ConfigError as exc:
        raise _merged_blame(exc, world, p) from exc
    check_drive_vs_stuck(merged_world.navigation, merged_world.failsafe)
    return merged_world


def _robot_table(path: Path) -> dict[str, Any]:
    """The robot config file's TOML as written (a byte-order mark allowed, as the robot's
    loader allows it); validate it with :func:`x6wd.core.config.load` first."""
    return tomllib.loads(path.read_text(encoding="utf-8").removeprefix("\ufeff"))


def _merged_blame(exc: ConfigError, world: World, robot_config: Path) -> ConfigError:
    """``exc`` of the scenario ``world`` merged with ``robot_config``, naming the file that
    holds its key: the scenario's own key by the scenario's own check (its file, through
    its includes), a robot section's key the scenario does not set by the robot config,
    anything else by both."""
    said = str(exc)
    sec, _, name = said.split(":", 1)[0].partition(".")
    if sec in ROBOT_SECTIONS and name:
        if name in (world.raw.get(sec) or {}) and world.source is not None:
            try:
                load_world(world.source)  # the scenario alone, with its rates' checks
            except ConfigError as own:
                return own
        else:
            where = world.source or "the scenario"
            return ConfigError(f"{robot_config}: {said} (the rates of {where})")
    return ConfigError(f"{world.source or 'the scenario'} with {robot_config}: {said}")


def robot_config_notes(world: World, robot_config: str | Path) -> list[str]:
    """What ``robot_config`` sets that :func:`with_robot_config` does not lay under the
    scenario, said rather than dropped: its GPS and compass rates, where it sets them to other
    than the scenario's (the simulated receiver and compass are the scenario's; an outside
    audit's 4 Hz GPS and 5 Hz compass ran at 1 and 20 Hz without a word)."""
    from sim_backend.compass import CompassSetup
    from x6wd.core.config import load

    p = Path(robot_config)
    cfg = load(p)
    written = _robot_table(p)
    notes = []
    pairs = (
        ("gps.rate_hz", cfg.gps.rate_hz, "[gnss] rate_hz", world.gnss.rate_hz),
        ("compass.rate_hz", cfg.compass.rate_hz, "[compass] rate_hz",
         CompassSetup.from_table(world.compass).rate_hz),
    )  # fmt: skip
    for key, robot_hz, scenario_key, scenario_hz in pairs:
        sec, name = key.split(".")
        if name not in (written.get(sec) or {}):
            continue  # the file does not set it: nothing of its to say
        if abs(robot_hz - scenario_hz) > 1e-9:
            notes.append(
                f"{p}: {key} = {robot_hz:g} Hz is not the scenario's {scenario_key} ="
                f" {scenario_hz:g} Hz: the run's is the scenario's (the simulated device is"
                f" the scenario's): set {scenario_key} in the scenario to run at {robot_hz:g} Hz"
            )
    return notes


def _check_effects(effects: tuple[dict[str, Any], ...]) -> None:
    from sim_backend.effects import effect_from_params

    for i, eff in enumerate(effects):
        if "name" not in eff:
            raise ConfigError(f"effects[{i}].name: required")
        try:
            effect_from_params(eff, f"effects[{i}]")  # its errors name effects[i].key
        except (TypeError, ValueError) as exc:
            raise ConfigError(f"effects[{i}] ({eff.get('name')}): {exc}") from exc


# ------------------------------------------------------------------ TOML writer


def _toml_key(key: str) -> str:
    bare = key.replace("_", "").replace("-", "").isalnum() and key.isascii()
    return key if bare else json.dumps(key)


def _toml_value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        if not math.isfinite(value):
            raise ConfigError(f"cannot write a non-finite number {value!r} to TOML")
        return repr(value)
    if isinstance(value, str):
        return json.dumps(value, ensure_ascii=False)
    if isinstance(value, date):  # a datetime or a date (start_utc)
        return value.isoformat()
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    if isinstance(value, dict):
        inner = ", ".join(f"{_toml_key(k)} = {_toml_value(v)}" for k, v in value.items())
        return "{" + inner + "}"
    raise ConfigError(f"cannot write {type(value).__name__} {value!r} to TOML")


def dumps_toml(data: dict[str, Any]) -> str:
    """Serialise a TOML table (top-level tables as sections, arrays of tables as [[...]])."""
    lines: list[str] = []
    sections: list[str] = []
    for key, value in data.items():
        if isinstance(value, dict):
            sections.append(f"\n[{_toml_key(key)}]")
            sections.extend(f"{_toml_key(k)} = {_toml_value(v)}" for k, v in value.items())
        elif isinstance(value, list) and value and all(isinstance(v, dict) for v in value):
            for item in value:
                sections.append(f"\n[[{_toml_key(key)}]]")
                sections.extend(f"{_toml_key(k)} = {_toml_value(v)}" for k, v in item.items())
        else:
            lines.append(f"{_toml_key(key)} = {_toml_value(value)}")
    return "\n".join(lines + sections) + "\n"
