"""``x6wd sweep SWEEP.toml``: a grid of scenarios x parameters x seeds, run on Dask.

A sweep file (``config/sweeps/position_source.toml`` is the example)::

    name = "position source"       # optional (default: the file's stem)
    seed = 2026                    # the sweep's seed (default 0)
    seeds = 5                      # missions per cell (replicates), each with its own seed
    scenarios = ["../scenarios/default.toml", "../scenarios/zigzag.toml"]  # relative to this file
    robot_config = "../x6wd.toml"  # optional: laid under every scenario (with_robot_config)
    engine = "auto"                # optional: as x6wd sim --engine (auto, robot, receiver)

    [set]                          # optional: the same value in every run
    duration_s = 300.0

    [grid]                         # every combination of these values
    navigation.position_source = ["ekf", "raw"]
    gnss.rate_hz = [1.0, 2.0]

Keys of ``[set]`` and ``[grid]`` are dotted paths into the scenario's TOML table (any scenario
key: ``duration_s``, ``gnss.rate_hz``, ``vehicle.max_speed_mps``, ``compass.noise_ut``, or a
robot configuration key: ``navigation.position_source``, ``failsafe.stuck_s``, ...). A table
given as a value is merged into the scenario's, key by key, in [grid] as in [set]: ``[grid]
gnss = [{rate_hz = 1.0, mask_deg = 5.0}, {rate_hz = 2.0, mask_deg = 10.0}]`` is two cells that
vary both keys together, the scenario's other [gnss] keys kept (:func:`grid_value`). They are
applied to each scenario's merged table (after its includes and the robot config) *before* the
scenario is validated, so every cell is checked when the sweep starts and a bad key or value
stops it with the scenario's own error message naming the key (``x6wd sweep`` exits 2). A file
given as a value (``almanac``, ``gnss.lce_csv``) is relative to the sweep file, as its
``scenarios`` and ``robot_config`` are; the scenario's own files stay relative to it.

Words: a *cell* is one scenario x one combination of the grid's values; a *run* is one mission
of a cell with one seed. Each run's seed is derived (SHA-256) from the sweep's seed, the
scenario's name, the run's parameters ([set] and [grid] values) and its replicate number, never
from its position in the grid: adding a value, a scenario or more seeds leaves the other runs'
seeds, and so their results, unchanged.

The output directory holds ``runs/RUN_ID.json`` (one per finished run, written atomically by
the client as results arrive), ``cells/CELL_ID.toml`` (each cell's resolved scenario: ``x6wd sim
cells/CELL_ID.toml --seed SEED`` replays a run), ``sweep.json`` (the plan), and at the end the
table and summary of :mod:`sim_backend.sweep_report`. Running the same sweep into the same
directory again (after a crash, Ctrl-C or a change of the grid) skips every run whose file is
there with the same seed and cell fingerprint (:func:`cell_digest`: the resolved scenario and
the contents of the files it names): only the missing runs are simulated (a folder written
before cell ids had 16 hex digits keeps its runs: :func:`migrate_legacy_runs`). A run file of
another results schema (:data:`RESULTS_SCHEMA`: an older x6wd's, without the figures this one
writes) is not done: it is run again, said on stderr, its old file moved to ``older-runs/``
(:func:`stale_reason`), so a summary never pools figures of two schemas; a result a worker of
another x6wd returns is stored as failed (:func:`worker_mismatch`). A directory
that holds another sweep (another name or seed in its ``sweep.json``) is refused
(:func:`check_out_dir`). A run whose
mission raised is recorded with its error (kept on resume unless ``retry_failed``); a run the
cluster lost (:class:`~sim_backend.executor.Outcome` kind "executor") is run again on resume.

The runs are executed by :class:`sim_backend.executor.Executor` (a Dask LocalCluster, an
existing scheduler, or this process). A task carries the resolved scenario as TOML text
(without the packaged almanac's local path, with any LCE CSV inlined, and any other almanac by
its absolute path), so workers need x6wd installed but not the scenario files, and read the
files that were checked whatever their current folder.
"""

from __future__ import annotations

import contextlib
import copy
import fcntl
import hashlib
import itertools
import json
import logging
import math
import os
import socket
import subprocess
import tempfile
import threading
import time
import tomllib
from collections import Counter
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from datetime import UTC, date, datetime
from datetime import time as clock_time
from functools import cache
from pathlib import Path
from typing import Any

from sim_backend.executor import Executor, Outcome, describe_exception
from sim_backend.mission import compass_setup, run_mission
from sim_backend.runs import ENGINES, RunPlan, check_mission_geofence, engine_for, sky_warnings
from sim_backend.survey import run_survey, survey_clock_hz
from sim_backend.sweep_report import (
    FIXED_COLUMNS,
    OLDER_RUNS_DIR,
    RESULT_FIELDS,
    WORKER_MISMATCH,
    json_value,
    record_schema,
)
from sim_backend.world import (
    DEFAULT_ALMANAC,
    World,
    dumps_toml,
    load_world,
    loads_world,
    parse_start_utc,
    with_robot_config,
)
from x6wd import __version__
from x6wd.core.config import check_drive_vs_stuck
from x6wd.core.errors import ConfigError, X6wdError
from x6wd.core.files import read_text_bounded
from x6wd.core.outdir import output_file

log = logging.getLogger(__name__)

SWEEP_KEYS = ("name", "seed", "seeds", "scenarios", "robot_config", "engine", "set", "grid")
PATH_KEYS = ("almanac", "gnss.lce_csv", "mission.file")
"""Scenario keys whose value is a file: given in [set] or [grid], a relative one is relative to
the sweep file's folder (a path is relative to the file that names it, as in a scenario);
so are the files of an ``include`` list."""
SEED_BITS = 48  # run seeds are 0 .. 2**48 - 1 (a collision in 10,000 runs: ~2e-7)

RESULTS_SCHEMA = 2
"""The run records' schema (``"schema"`` in each ``runs/RUN_ID.json`` and in ``sweep.json``):
bump it whenever :func:`run_task` writes other figures, so that a folder's records of an older
x6wd are run again rather than tabled beside new ones (:func:`stale_reason`). 1: before
2026-12-04 (97e4486), no receiver figures; 2: with ``gps_*``, ``filtered_rms_m``,
``fix_fraction``, ``hold_time_s`` (written with the number since 2026-12-06)."""
SCHEMA_LACKS = {1: "without gps_* figures"}
"""What a record of an older schema lacks, in words (the message that runs it again)."""


# ---------------------------------------------------------------------------- the file


@dataclass(frozen=True)
class SweepSpec:
    """A validated sweep file. ``fixed`` ([set]) and ``grid`` ([grid]) map dotted scenario
    keys to a value and to a list of values (file order), as written; ``base_dir`` is the
    folder their relative file names (:data:`PATH_KEYS`) are relative to (the sweep file's)."""

    name: str
    seed: int
    seeds: int
    scenarios: tuple[Path, ...]
    robot_config: Path | None = None
    # as ``x6wd sim --engine``: each cell runs on the engine that command picks, so that
    # ``x6wd sim cells/CELL.toml`` (with ``--engine`` when not auto) replays it
    engine: str = "auto"
    fixed: dict[str, Any] = field(default_factory=dict)
    grid: dict[str, list[Any]] = field(default_factory=dict)
    source: Path | None = None
    base_dir: Path = Path(".")


def load_sweep(path: str | Path) -> SweepSpec:
    """Read and check a sweep file (paths in it are relative to it)."""
    p = Path(path)
    try:
        text = read_text_bounded(p)
    except OSError as exc:
        raise ConfigError(f"{p}: cannot read sweep file: {exc.strerror or exc}") from exc
    except UnicodeDecodeError as exc:  # an editor's Latin-1, or no text at all
        raise ConfigError(
            f"{p}: not a UTF-8 text file (byte 0x{exc.object[exc.start]:02x} at offset"
            f" {exc.start}); save the sweep file as UTF-8"
        ) from exc
    return loads_sweep(text, p.resolve().parent, source=p, default_name=p.stem)


def loads_sweep(
    text: str,
    base_dir: str | Path = ".",
    source: str | Path = "<string>",
    default_name: str = "sweep",
) -> SweepSpec:
    """A sweep from TOML text; relative paths resolve against ``base_dir``."""
    try:  # a leading byte-order mark is no TOML error (as for the robot's config)
        data = tomllib.loads(text.removeprefix("\ufeff"))
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{source}: not valid TOML: {exc}") from exc
    try:
        return _spec(
            data, Path(base_dir), Path(source) if source != "<string>" else None, default_name
        )
    except ConfigError as exc:
        raise ConfigError(f"{source}: {exc}") from exc


def _spec(data: dict[str, Any], base: Path, source: Path | None, default_name: str) -> SweepSpec:
    unknown = sorted(set(data) - set(SWEEP_KEYS))
    if unknown:
        raise ConfigError(f"{unknown[0]}: unknown key (valid keys: {', '.join(SWEEP_KEYS)})")
    name = data.get("name", default_name)
    if not isinstance(name, str) or not name:
        raise ConfigError(f"name: expected a non-empty string, got {name!r}")
    seed = data.get("seed", 0)
    if not isinstance(seed, int) or isinstance(seed, bool) or seed < 0:
        raise ConfigError(f"seed: expected an integer >= 0, got {seed!r}")
    seeds = data.get("seeds", 1)
    if not isinstance(seeds, int) or isinstance(seeds, bool) or not 1 <= seeds <= 1_000_000:
        raise ConfigError(f"seeds: expected an integer 1..1000000 (runs per cell), got {seeds!r}")
    scen = data.get("scenarios")
    if isinstance(scen, str):
        scen = [scen]
    if not isinstance(scen, list) or not scen or not all(isinstance(s, str) for s in scen):
        got = "nothing (the key is missing)" if scen is None else repr(scen)
        raise ConfigError(f"scenarios: expected a non-empty list of scenario files, got {got}")
    paths = tuple((base / s).resolve() for s in scen)
    stems: dict[str, Path] = {}
    for p in paths:
        if p.stem in stems:
            raise ConfigError(f"scenarios: two scenarios named {p.stem!r} ({stems[p.stem]}, {p})")
        stems[p.stem] = p
    robot = data.get("robot_config")
    if robot is not None and (not isinstance(robot, str) or not robot):
        raise ConfigError(f"robot_config: expected a file name, got {robot!r}")
    engine = data.get("engine", "auto")
    if engine not in ENGINES:
        raise ConfigError(f"engine: expected one of {', '.join(ENGINES)}, got {engine!r}")
    fixed = _dotted(data.get("set", {}), "set")
    grid_raw = _dotted(data.get("grid", {}), "grid")
    for where, table in (("set", fixed), ("grid", grid_raw)):
        for key in table:
            if key == "seed":  # each run's own seed would override it, whatever it is
                raise ConfigError(
                    f"{where}.seed: not a parameter: each run's seed comes from the sweep's"
                    " seed (the top-level 'seed') and its replicate number ('seeds' per cell)"
                )
            if key in FIXED_COLUMNS:
                raise ConfigError(
                    f"{where}.{key}: not a parameter: {key!r} is a column of the results"
                )
    grid: dict[str, list[Any]] = {}
    for key, values in grid_raw.items():
        if not isinstance(values, list) or not values:
            raise ConfigError(f"grid.{key}: expected a non-empty list of values, got {values!r}")
        if key in fixed:
            raise ConfigError(f"grid.{key}: also in [set]; give it in one of them")
        seen: dict[str, Any] = {}
        for v in values:  # a repeat would run the same cell twice and count it twice
            flat = grid_value(key, v)
            for k in flat if isinstance(v, dict) else ():  # a table: merged key by key
                if k in fixed:
                    raise ConfigError(
                        f"grid.{key}: sets {k}, also in [set]; give it in one of them"
                    )
                if k in grid_raw:
                    raise ConfigError(
                        f"grid.{key}: sets {k}, also a key of [grid]; give it in one of them"
                    )
            first = seen.setdefault(_value_key(flat if isinstance(v, dict) else v, key), v)
            if first is not v:
                same = "" if _shown(first) == _shown(v) else f" (as {_shown(first)})"
                raise ConfigError(f"grid.{key}: value {_shown(v)} given twice{same}")
        grid[key] = values
    return SweepSpec(
        name=name,
        seed=seed,
        seeds=seeds,
        scenarios=paths,
        robot_config=(base / robot).resolve() if robot else None,
        engine=engine,
        fixed=fixed,
        grid=grid,
        source=source.resolve() if source is not None else None,
        base_dir=base.resolve(),
    )


def _dotted(table: Any, where: str, prefix: str = "") -> dict[str, Any]:
    """Nested tables flattened to dotted keys ({"gnss": {"rate_hz": 1}} -> {"gnss.rate_hz": 1};
    a quoted key "gnss.rate_hz" is the same)."""
    if not isinstance(table, dict):
        raise ConfigError(f"{where}: expected a table, got {table!r}")
    out: dict[str, Any] = {}
    for key, value in table.items():
        full = f"{prefix}{key}"
        flat = _dotted(value, where, f"{full}.") if isinstance(value, dict) else {full: value}
        for k, v in flat.items():
            if k in out:  # gnss.rate_hz and "gnss.rate_hz" both: one would be lost
                raise ConfigError(f"{where}.{k}: given twice")
            out[k] = v
    return out


def grid_value(key: str, value: Any) -> dict[str, Any]:
    """The overrides one value of the [grid] key ``key`` makes: a table is merged into the
    scenario's key by key, as the same table in [set] is ({"compass": {"noise_ut": 0.1}} ->
    {"compass.noise_ut": 0.1}: the scenario's compass.declination_deg stays; a file in it is
    relative to the sweep file), any other value is ``{key: value}``."""
    if isinstance(value, dict):
        return _dotted(value, f"grid.{key}", f"{key}.")
    return {key: value}


def set_dotted(data: dict[str, Any], key: str, value: Any) -> None:
    """``data[a][b][c] = value`` for ``key`` "a.b.c", creating missing tables; a path through
    a value that is not a table is a :class:`ConfigError` naming the key."""
    parts = key.split(".")
    if not all(parts):
        raise ConfigError(f"{key}: not a dotted key")
    node = data
    for i, part in enumerate(parts[:-1]):
        nxt = node.setdefault(part, {})
        if not isinstance(nxt, dict):
            raise ConfigError(f"{key}: {'.'.join(parts[: i + 1])} is not a table")
        node = nxt
    node[parts[-1]] = copy.deepcopy(value)


# ---------------------------------------------------------------------------- the plan


@dataclass(frozen=True)
class Cell:
    """One scenario x one combination of the grid's values. ``params`` are the grid's values
    by dotted key (a table value's keys each on its own: :func:`grid_value`), ``overrides``
    those and [set]; ``world_toml`` the resolved scenario with them applied;
    ``files`` the (path, SHA-256) of every file it names (an almanac other than the packaged
    one), and ``digest`` its fingerprint (:func:`cell_digest`): a run is done only for the
    same digest. ``warnings``: what ``x6wd sim`` would warn about (its sky)."""

    cell_id: str
    scenario: str
    scenario_path: Path
    params: dict[str, Any]
    overrides: dict[str, Any]
    world_toml: str
    digest: str
    files: tuple[tuple[str, str], ...] = ()
    warnings: tuple[str, ...] = ()
    engine: str = "robot"  # the engine its runs run on ("robot" or "receiver")


@dataclass(frozen=True)
class Run:
    """One mission of a cell: replicate ``replicate`` (0-based) with its derived ``seed``."""

    run_id: str
    cell: Cell
    replicate: int
    seed: int


def _canonical(value: Any) -> str:
    return json.dumps(value, sort_keys=True, separators=(",", ":"), default=str)


def _shown(value: Any) -> str:
    """A grid value as the file writes it: a TOML date or time in ISO form, else its repr."""
    return value.isoformat() if isinstance(value, (date, clock_time)) else repr(value)


def _value_key(value: Any, key: str = "") -> str:
    """``value`` for telling two grid values apart: numbers by their value (1 and 1.0 are
    one value, the same in the scenario; true is not 1), in lists and tables too; a
    ``start_utc`` by the instant the scenario takes from it (a string or a TOML datetime,
    any offset). (Seeds and cell ids keep :func:`_canonical` of the value as written.)"""
    if key == "start_utc":
        try:
            return "instant:" + parse_start_utc(value).isoformat()
        except ConfigError:
            pass  # the scenario loader names it when the cell runs

    def norm(v: Any) -> Any:
        if isinstance(v, float) and v.is_integer():
            return int(v)
        if isinstance(v, datetime) and v.tzinfo is not None:  # one instant, any offset
            return v.astimezone(UTC).isoformat()
        if isinstance(v, list):
            return [norm(x) for x in v]
        if isinstance(v, dict):
            return {k: norm(x) for k, x in v.items()}
        return v

    return _canonical(norm(value))


def run_seed(sweep_seed: int, scenario: str, overrides: dict[str, Any], replicate: int) -> int:
    """The seed of a run: SHA-256 of the sweep's seed, the scenario's name, the run's
    parameters (order-free) and its replicate number, as a 48-bit integer."""
    blob = _canonical([sweep_seed, scenario, sorted(overrides.items()), replicate])
    digest = hashlib.sha256(blob.encode("utf-8")).digest()
    return int.from_bytes(digest[: SEED_BITS // 8], "big")


CELL_ID_HEX = 16
"""Hex digits of a cell id's hash (64 bits: two of a 100,000-cell grid share one with a
chance of ~3e-10, and :func:`plan` refuses it). They were 8 (32 bits) until 2026-12-05:
then ~1 % of 10,000-cell grids had two cells of one id, merged silently into one."""
LEGACY_CELL_ID_HEX = 8
"""A cell id's hex digits before 2026-12-05: a run file of a folder made then has that id
(the first digits of today's), and is found under it (:func:`legacy_run_id`)."""


def cell_id(scenario: str, overrides: dict[str, Any]) -> str:
    """A short stable name of a cell: the scenario and a hash of its parameters
    (:data:`CELL_ID_HEX` hex digits)."""
    h = hashlib.sha256(_canonical([scenario, sorted(overrides.items())]).encode("utf-8"))
    return f"{scenario}-{h.hexdigest()[:CELL_ID_HEX]}"


def legacy_cell_id(cid: str) -> str:
    """The id :func:`cell_id` gave the same cell before 2026-12-05 (its hash cut to
    :data:`LEGACY_CELL_ID_HEX` hex digits)."""
    return cid[: len(cid) - (CELL_ID_HEX - LEGACY_CELL_ID_HEX)]


def legacy_run_id(run: Run) -> str:
    """The id of ``run``'s file in a folder made before 2026-12-05 (:func:`legacy_cell_id`);
    since two cells could share that id, such a file is ``run``'s only when its seed and
    cell fingerprint are (:func:`is_done`)."""
    return f"{legacy_cell_id(run.cell.cell_id)}-{run.replicate:03d}"


def base_table(path: Path, robot_config: Path | None) -> tuple[dict[str, Any], Path]:
    """A scenario's merged TOML table (includes expanded, paths absolute, the robot config
    laid underneath) and its folder."""
    world = load_world(path, check_rates=robot_config is None)
    if robot_config is not None:
        try:
            world = with_robot_config(world, robot_config)
        except ConfigError as exc:  # its message may begin with the path already
            said = str(exc)
            if world.source is not None and said.startswith(str(world.source)):
                raise  # the scenario's own key (or both files named): not the robot config's
            where = (
                "robot_config"
                if said.startswith(str(robot_config))
                else f"robot_config {robot_config}"
            )
            raise ConfigError(f"{where}: {said}") from exc
    return copy.deepcopy(world.raw), path.parent


def cell_world(
    table: dict[str, Any],
    base_dir: Path,
    overrides: dict[str, Any],
    source: str,
    values_dir: Path | None = None,
) -> tuple[World, str]:
    """The validated world of ``table`` with ``overrides`` (dotted keys) applied, and its
    portable TOML: the one a worker reads, whatever its current folder. A file named by an
    override (:data:`PATH_KEYS`) is relative to ``values_dir`` (default ``base_dir``); the
    TOML names the almanac by its absolute path (the packaged one is left to each worker's
    own install) and carries an LCE CSV's grid inline (``gnss.lce_sigma_m``) and a mission
    file's waypoints (``mission.waypoints``), so what a worker runs is what was checked
    here. The checks of a mission's start are :func:`start_checks` (:func:`plan` makes
    them)."""
    data = copy.deepcopy(table)
    for key, value in overrides.items():
        if _non_finite(value):  # TOML cannot carry it to a worker; no scenario key takes one
            raise ConfigError(f"{key}: expected a finite number, got {value!r}")
        if key in PATH_KEYS and isinstance(value, str) and value:
            value = str(((values_dir or base_dir) / value).resolve())
        elif key == "include" and isinstance(value, list):  # files too (audit round 21)
            value = [
                str(((values_dir or base_dir) / v).resolve()) if isinstance(v, str) and v else v
                for v in value
            ]
        if key == "gnss.lce_csv" and "gnss.lce_sigma_m" not in overrides:
            gnss = data.get("gnss")  # it replaces the scenario's own map (inlined when read)
            if isinstance(gnss, dict):
                gnss.pop("lce_sigma_m", None)
        set_dotted(data, key, value)
    world = loads_world(dumps_toml(data), base_dir, source=source)
    portable = copy.deepcopy(world.raw)  # paths absolute, the LCE CSV read into the table
    if portable.get("almanac") == str(DEFAULT_ALMANAC):
        del portable["almanac"]
    if world.mission.file:  # the waypoints as read here: a worker needs no mission file
        portable["mission"] = {"waypoints": [list(wp) for wp in world.mission.waypoints]}
    return world, dumps_toml(portable)


def start_checks(
    world: World, sky: dict[tuple[Any, ...], list[str]] | None = None, engine: str = "robot"
) -> list[str]:
    """The checks ``x6wd sim`` makes before a mission moves (a :class:`ConfigError` there is
    its exit 2), called, not copied: :func:`sim_backend.runs.sky_warnings` (it reads the
    almanac), the waypoints against the geofence
    (:func:`sim_backend.runs.check_mission_geofence`), and
    :func:`sim_backend.mission.run_mission`'s start: the drive against the stuck
    failsafe and the [compass] table with the compass effects (both robot engine only), and the
    run's clock
    (:class:`sim_backend.runs.RunPlan`: on the robot ``engine`` the compass rate a whole
    multiple of the GPS rate; the receiver engine takes any pair). Returns the sky's warnings;
    ``sky`` caches them by almanac, start and duration."""
    key = (str(world.almanac_path), world.start_utc.isoformat(), world.duration_s)
    if sky is None or key not in sky:
        found = sky_warnings(world)
        if sky is not None:
            sky[key] = found
    else:
        found = sky[key]
    check_mission_geofence(world)
    if engine == "receiver":  # it reads no robot setting and applies no compass effect
        clock_hz = survey_clock_hz(world)  # (as x6wd sim --engine receiver)
    else:
        check_drive_vs_stuck(world.navigation, world.failsafe)
        clock_hz = compass_setup(world)[0].rate_hz
    RunPlan.of(world, None, None, clock_hz)
    return list(found)


def named_files(table: Any) -> list[Path]:
    """Every existing file a resolved scenario table names by an absolute path (its almanac;
    any file key to come), in table order, once each. The packaged almanac is no input of the
    scenario's: it is the installed x6wd's, like its code, and each worker reads its own."""
    found: dict[Path, None] = {}

    def walk(v: Any) -> None:
        if isinstance(v, dict):
            for x in v.values():
                walk(x)
        elif isinstance(v, list):
            for x in v:
                walk(x)
        elif isinstance(v, str) and v.startswith(os.sep) and "\n" not in v:
            p = Path(v)
            if p != DEFAULT_ALMANAC and p.is_file():
                found.setdefault(p, None)

    walk(table)
    return list(found)


def file_sha256(path: Path) -> str:
    """SHA-256 of a file's bytes (a :class:`ConfigError` naming it when it cannot be read)."""
    try:
        return hashlib.sha256(path.read_bytes()).hexdigest()
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read: {exc.strerror or exc}") from exc


def cell_digest(world_toml: str, files: Sequence[tuple[str, str]] = ()) -> str:
    """A cell's fingerprint: SHA-256 of its resolved scenario (includes, robot config and LCE
    grid are in it) and of the contents of the files it names (``files``: path and SHA-256),
    so a changed almanac is a changed cell; without files, the digest of the text alone (as
    before files were counted, so such folders keep their runs)."""
    blob = world_toml + "".join(f"\0{path}\0{sha}" for path, sha in files)
    return hashlib.sha256(blob.encode("utf-8")).hexdigest()[:16]


def show_value(value: Any) -> str:
    """A value as a cell's label shows it: a TOML date or time as written, others by repr."""
    if isinstance(value, (date, clock_time)):
        return value.isoformat()
    return repr(value)


def _non_finite(value: Any) -> bool:
    """A NaN or infinite float in ``value`` (in its lists and tables too)."""
    if isinstance(value, float):
        return not math.isfinite(value)
    if isinstance(value, list):
        return any(_non_finite(v) for v in value)
    if isinstance(value, dict):
        return any(_non_finite(v) for v in value.values())
    return False


MAX_RUNS = 100_000
"""Default ceiling on a sweep's runs: planning checks each cell (~4.5 ms) and the plan is
written whole, so a mistyped grid or seed count would plan silently for hours."""


def run_count(spec: SweepSpec) -> int:
    """Runs the sweep plans (scenarios x grid combinations x seeds), without planning."""
    return len(spec.scenarios) * math.prod(len(v) for v in spec.grid.values()) * spec.seeds


def plan(spec: SweepSpec) -> list[Run]:
    """Every run of the sweep (scenario, then grid combination, then replicate), each cell
    validated; a bad key or value raises :class:`ConfigError` naming the scenario, the cell's
    parameters and the key."""
    keys = list(spec.grid)
    combos = list(itertools.product(*(spec.grid[k] for k in keys)))
    runs: list[Run] = []
    sky: dict[tuple[Any, ...], list[str]] = {}
    hashes: dict[Path, str] = {}
    ids: dict[str, str] = {}  # cell id -> the label of the cell that has it
    for path in spec.scenarios:
        table, base = base_table(path, spec.robot_config)
        for combo in combos:
            params: dict[str, Any] = {}  # a table's keys each on its own (as [set] has them)
            for k, v in zip(keys, combo, strict=True):
                params.update(grid_value(k, v))
            overrides = {**spec.fixed, **params}
            where = ", ".join(f"{k}={show_value(v)}" for k, v in overrides.items())
            label = f"{path.stem} ({where or 'no overrides'})"
            cid = cell_id(path.stem, overrides)
            if cid in ids:  # one cells/ file, one set of run files: the two would be merged
                raise ConfigError(
                    f"scenario {path}: {label}: its cell id {cid} is also the id of"
                    f" {ids[cid]} (their parameters' hashes agree in {CELL_ID_HEX} hex digits,"
                    f" a chance of {16.0**-CELL_ID_HEX:.0e} per pair: please report it);"
                    " change one of the two values slightly, or rename the scenario file"
                )
            ids[cid] = label
            try:
                world, text = cell_world(table, base, overrides, label, spec.base_dir)
                engine = engine_for(world, spec.engine)
                warnings = start_checks(world, sky, engine)  # x6wd sim's exit 2 is the sweep's
                files = []
                for f in named_files(world.raw):
                    if f not in hashes:
                        hashes[f] = file_sha256(f)
                    files.append((str(f), hashes[f]))
            except X6wdError as exc:  # the scenario's loader names the cell, other checks not
                # (x6wd sim's exit 2 is any X6wdError: an almanac it cannot parse, ...)
                msg = str(exc) if str(exc).startswith(label) else f"{label}: {exc}"
                raise ConfigError(f"scenario {path}: {msg}") from exc
            cell = Cell(
                cid,
                path.stem,
                path,
                params,
                overrides,
                text,
                # a survey run on the receiver engine is another run than on the robot's (no
                # filtered figures): a folder of the other engine's runs runs it again
                cell_digest(text + ("\0engine=receiver" if engine == "receiver" else ""), files),
                tuple(files),
                tuple(warnings),
                engine,
            )
            for r in range(spec.seeds):
                seed = run_seed(spec.seed, path.stem, overrides, r)
                runs.append(Run(f"{cid}-{r:03d}", cell, r, seed))
    return runs


# ---------------------------------------------------------------------------- one run


class _RobotLogKeptQuiet:
    """The robot's log (``x6wd.*``: "state IDLE -> HOLD state: position estimate not ready")
    not printed while a sweep's mission runs (``with ROBOT_LOG_KEPT_QUIET():``). With no
    handler configured (a Dask worker, the sweep's own process), Python's last-resort handler
    wrote each warning to stderr, several per mission, --quiet or not; a run's states are the
    mission's to show (replay it with ``x6wd sim``). Counted, so that the log comes back when
    the last of concurrent missions (a worker of several threads) ends."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._missions = 0
        self._quiet = logging.NullHandler()  # a handler: Python's last resort is not used
        self._propagate = True

    @contextlib.contextmanager
    def __call__(self) -> Iterator[None]:
        logger = logging.getLogger("x6wd")
        with self._lock:
            if not self._missions:
                self._propagate, logger.propagate = logger.propagate, False
                logger.addHandler(self._quiet)
            self._missions += 1
        try:
            yield
        finally:
            with self._lock:
                self._missions -= 1
                if not self._missions:
                    logger.removeHandler(self._quiet)
                    logger.propagate = self._propagate


ROBOT_LOG_KEPT_QUIET = _RobotLogKeptQuiet()


@cache
def x6wd_version() -> str:
    """The x6wd that simulates here, for the records: its version, and in a git checkout its
    commit ("0.1.0+g1c73122a9f0e"; uncommitted changes not shown). Worked out once per
    process (a worker's own: on a cluster, the workers' x6wd is the simulator)."""
    root = Path(__file__).resolve().parent.parent
    if not (root / ".git").exists():  # an installed x6wd: its version says it
        return __version__
    try:
        done = subprocess.run(
            ["git", "-C", str(root), "rev-parse", "--short=12", "HEAD"],
            capture_output=True,
            text=True,
            timeout=10,
            check=False,
        )
    except (OSError, subprocess.SubprocessError):
        return __version__
    commit = done.stdout.strip()
    return f"{__version__}+g{commit}" if done.returncode == 0 and commit else __version__


def run_task(run_id: str, world_toml: str, seed: int, engine: str = "robot") -> dict[str, Any]:
    """One run (on a worker): the scenario TOML with ``seed`` on ``engine`` ("robot": a
    mission, or a survey on the robot's loop; "receiver": a static survey on the receiver
    alone, its files in a temporary folder), its summary only (a sweep keeps the figures).
    Never raises for a failed run: the record's ``status`` is "error" with ``error``."""
    t0 = time.perf_counter()
    rec: dict[str, Any] = {
        "run_id": run_id,
        "status": "ok",
        "error": None,
        "worker": f"{socket.gethostname()}:{os.getpid()}",
        # the worker's x6wd ran the mission and wrote the figures: the client keeps both
        "schema": RESULTS_SCHEMA,
        "x6wd_version": x6wd_version(),
    }
    try:
        world = loads_world(world_toml, source=run_id)
        if engine == "receiver":
            with tempfile.TemporaryDirectory(prefix="x6wd-sweep-") as tmp:
                s = run_survey(world, tmp, seed=int(seed))
        else:
            with ROBOT_LOG_KEPT_QUIET():
                s = run_mission(world, None, seed=int(seed))
        rec.update(
            completed=bool(s.completed),
            waypoints_reached=int(s.waypoints_reached),
            waypoint_count=int(s.waypoint_count),
            path_length_m=s.path_length_m,
            straight_length_m=s.straight_length_m,
            sim_time_s=s.sim_time_s,
            wall_time_s=s.wall_time_s,
            arrivals=[dict(a) for a in s.extra.get("arrivals") or []],
            position_source=s.extra.get("position_source"),
            # the receiver's own figures: a sweep of a static scenario (a survey) or of
            # receiver keys is about these, not about arrivals
            gps_cep50_m=s.raw_error.cep50_m,
            gps_r95_m=s.raw_error.r95_m,
            gps_rms_m=s.raw_error.rms_m,
            filtered_rms_m=s.filtered_error.rms_m,
            engine=engine,
            fix_fraction=s.fixes_valid / s.fixes if s.fixes else math.nan,
            hold_time_s=s.hold_time_s,
        )
    except Exception as exc:  # a failed run is a result, not the end of the sweep
        rec.update(status="error", error=describe_exception(exc), completed=False)
    rec["task_s"] = time.perf_counter() - t0
    return rec


# ---------------------------------------------------------------------------- the store


class RunStore:
    """``OUT/runs/RUN_ID.json``, one per finished run, each written atomically (a temporary
    file in the same folder, then ``os.replace``): a crash leaves a run either whole or
    absent."""

    def __init__(self, out_dir: str | Path) -> None:
        self.dir = Path(out_dir) / "runs"
        self.dir.mkdir(parents=True, exist_ok=True)

    def path(self, run_id: str) -> Path:
        return self.dir / f"{run_id}.json"

    def load(self, run_id: str) -> dict[str, Any] | None:
        try:
            data = json.loads(self.path(run_id).read_text(encoding="utf-8"))
        except (OSError, ValueError):
            return None
        return data if isinstance(data, dict) else None

    def write(self, record: dict[str, Any]) -> None:
        write_atomic(self.path(record["run_id"]), json.dumps(_json_safe(record), indent=1))


def write_atomic(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` so that a reader never sees half of it, with the mode a
    plain ``open`` gives (0666 less the umask): mkstemp's 0600 kept others on a shared folder
    from replaying a cell. An ``OSError`` (a full disk) is a :class:`ConfigError` naming
    ``path``."""
    with output_file(path):
        _write_atomic(path, text)


def _write_atomic(path: Path, text: str) -> None:
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent)
    try:
        umask = os.umask(0o022)  # read it (the only way) and put it back
        os.umask(umask)
        os.fchmod(fd, 0o666 & ~umask)
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def _json_safe(v: Any) -> Any:
    """``v`` as JSON takes it: non-finite floats as null, a TOML date or time as its ISO text
    (:func:`sim_backend.sweep_report.json_value`)."""
    if isinstance(v, float):
        return v if v == v and v not in (float("inf"), float("-inf")) else None
    if isinstance(v, dict):
        return {str(k): _json_safe(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_json_safe(x) for x in v]
    return json_value(v)


def stale_reason(record: dict[str, Any]) -> str | None:
    """Why a stored record is not a result of this x6wd and is run again (None: it is): it is
    of another results schema (:data:`RESULTS_SCHEMA`), a success lacking one of the figures
    this x6wd writes (:data:`RESULT_FIELDS`), or a run whose worker's x6wd returned such
    figures (:func:`worker_mismatch`). Said in words for the message: "from an older x6wd
    (schema 1, without gps_* figures)". Another x6wd version of the same schema is no reason:
    its figures are the same ones (the summary counts the versions). A run that raised and
    has no schema (2026-12-04..06) is of no known schema and no reason either: it has no
    figures, and is kept unless ``retry_failed`` as any run that raised."""
    mismatch = record.get(WORKER_MISMATCH)
    if mismatch:
        return f"that a worker of another x6wd ran ({mismatch})"
    schema = record_schema(record)
    if schema is not None and schema < RESULTS_SCHEMA:
        lacks = SCHEMA_LACKS.get(schema)
        return f"from an older x6wd (schema {schema}{', ' + lacks if lacks else ''})"
    if schema is not None and schema > RESULTS_SCHEMA:
        return f"from a newer x6wd (schema {schema}; this one writes {RESULTS_SCHEMA})"
    missing = [k for k in RESULT_FIELDS if k not in record]
    if record.get("status") == "ok" and missing:
        return f"lacking figures this x6wd writes ({', '.join(missing)})"
    return None


def worker_mismatch(result: dict[str, Any]) -> tuple[str, str] | None:
    """Whether a worker's fresh :func:`run_task` result is of another x6wd than this one
    tables: (what it is, in words: "schema 1, without gps_* figures"; the run's error:
    "the worker's x6wd is too old (...): update it"), or None. A worker of an x6wd before
    2026-12-06 returns no schema: its figures tell it (:func:`record_schema`). Such figures
    were stamped with this x6wd's schema and tabled with blanks; the run is now a failure
    and runs again on the next call. Every x6wd's run_task (since 2026-11-25) names its
    ``worker``: a result without one is no worker's and is not judged here."""
    if "worker" not in result or stale_reason(result) is None:
        return None
    schema = record_schema(result)
    if schema is None:  # a run that raised: judged by the retry_failed rules, not here
        return None
    if schema > RESULTS_SCHEMA:
        what = f"schema {schema}"
        return what, (
            f"the worker's x6wd is newer ({what}; this one tables schema {RESULTS_SCHEMA}):"
            " update this one"
        )
    if schema < RESULTS_SCHEMA:
        what = f"schema {schema}{', ' + SCHEMA_LACKS[schema] if schema in SCHEMA_LACKS else ''}"
        return what, (
            f"the worker's x6wd is too old ({what}; this one tables schema {RESULTS_SCHEMA}):"
            " update it"
        )
    what = f"schema {schema} without {', '.join(k for k in RESULT_FIELDS if k not in result)}"
    return what, f"the worker's x6wd returned {what}, figures this one writes: update it"


def same_run(record: dict[str, Any] | None, run: Run) -> bool:
    """Whether a stored record is of ``run``: the same seed and cell fingerprint."""
    return (
        record is not None
        and record.get("seed") == run.seed
        and record.get("digest") == run.cell.digest
    )


def is_done(record: dict[str, Any] | None, run: Run, retry_failed: bool = False) -> bool:
    """Whether a stored record stands for ``run`` (same seed and configuration), is a result
    of this x6wd's schema (:func:`stale_reason`) and needs no new attempt: a success, or a
    mission that raised (unless ``retry_failed``); a run the cluster lost is always tried
    again."""
    if record is None or not same_run(record, run) or stale_reason(record) is not None:
        return False
    status = record.get("status")
    return status == "ok" or (status == "error" and not retry_failed)


# ---------------------------------------------------------------------------- the sweep


@dataclass
class SweepResult:
    """The records of every planned run (plan order); what this call ran (runs that
    finished, succeeded or raised), of them ``raised`` (the mission raised: no mission ran),
    and skipped (found done); its wall time (s) and the executor's description. A run the
    cluster lost (status "lost") is neither run nor skipped: it is run again by the next
    call."""

    spec: SweepSpec
    runs: list[Run]
    records: list[dict[str, Any]]
    ran: int
    skipped: int
    wall_s: float
    executor: str
    raised: int = 0
    older: dict[str, int] = field(default_factory=dict)
    """Runs whose record was of another schema and that this call ran again, by the reason
    (:func:`stale_reason`)."""

    @property
    def failed(self) -> list[dict[str, Any]]:
        """Every run that did not succeed: its mission raised, or the cluster lost it."""
        return [r for r in self.records if r.get("status") != "ok"]

    @property
    def errors(self) -> list[dict[str, Any]]:
        """The runs whose mission raised (a result, kept on resume)."""
        return [r for r in self.failed if r.get("status") != "lost"]

    @property
    def lost(self) -> list[dict[str, Any]]:
        """The runs the cluster could not finish (no result: the next call runs them)."""
        return [r for r in self.records if r.get("status") == "lost"]

    @property
    def missions_per_min(self) -> float:
        """Missions that ran to their end (completed or not) in this call per wall minute:
        runs that raised (often at once: an unreadable file) and lost runs are no missions
        (NaN when none ran)."""
        missions = self.ran - self.raised
        return missions / self.wall_s * 60.0 if missions and self.wall_s > 0 else float("nan")


WORKER_KEYS = ("worker", "x6wd_version", "task_s")
"""What a run record keeps of a result whose figures are another x6wd's (:func:`_record`)."""


def _record(run: Run, result: dict[str, Any] | None, outcome: Outcome | None) -> dict[str, Any]:
    """The run file of ``run``: its identity, and the worker's result as the worker's x6wd
    wrote it (its schema and version included: never this x6wd's, which did not simulate it).
    A result of another x6wd's figures (:func:`worker_mismatch`) is stored as a failure
    naming it, without its figures, which no table takes."""
    rec: dict[str, Any] = {
        "run_id": run.run_id,
        "cell_id": run.cell.cell_id,
        "scenario": run.cell.scenario,
        "params": _json_safe(run.cell.params),  # as the file has them (a datetime as text)
        "overrides": _json_safe(run.cell.overrides),
        "replicate": run.replicate,
        "seed": run.seed,
        "digest": run.cell.digest,
    }
    mismatch = worker_mismatch(result) if result is not None else None
    if result is not None and mismatch is not None:
        rec.update({k: result[k] for k in WORKER_KEYS if k in result})
        rec.update(schema=record_schema(result), status="error", error=mismatch[1])
        rec.update({WORKER_MISMATCH: mismatch[0], "completed": False})
    elif result is not None:
        rec.update({k: v for k, v in result.items() if k != "run_id"})
    if outcome is not None and not outcome.ok:
        kind = outcome.kind
        rec.update(status="lost" if kind == "executor" else "error", error=outcome.error)
        rec.setdefault("completed", False)
    rec["finished_utc"] = datetime.now(UTC).strftime("%Y-%m-%dT%H:%M:%SZ")
    return rec


def write_plan(spec: SweepSpec, runs: Sequence[Run], out_dir: Path) -> None:
    """``sweep.json`` (the spec and every run) and ``cells/CELL_ID.toml``."""
    cells_dir = out_dir / "cells"
    cells_dir.mkdir(parents=True, exist_ok=True)
    seen: dict[str, Cell] = {}
    for run in runs:
        seen.setdefault(run.cell.cell_id, run.cell)
    for cid, cell in seen.items():
        head = (
            f"# sweep {spec.name!r}, cell {cid}: {cell.scenario_path}"
            f" with {_canonical(_json_safe(cell.overrides))}\n"
            f"# replay a run: x6wd sim {cells_dir / (cid + '.toml')} --seed SEED\n"
            + "".join(f"# reads {path} (sha256 {sha})\n" for path, sha in cell.files)
            + "".join(f"# warning: {w}\n" for w in cell.warnings)
        )
        path = cells_dir / f"{cid}.toml"
        text = head + cell.world_toml
        if not path.exists() or path.read_text(encoding="utf-8") != text:
            write_atomic(path, text)
    plan_data = {
        "name": spec.name,
        "schema": RESULTS_SCHEMA,
        "x6wd_version": x6wd_version(),
        "source": str(spec.source) if spec.source else None,
        "seed": spec.seed,
        "seeds": spec.seeds,
        "scenarios": [str(p) for p in spec.scenarios],
        "robot_config": str(spec.robot_config) if spec.robot_config else None,
        "engine": spec.engine,
        "set": spec.fixed,
        "grid": spec.grid,
        "runs": [
            {
                "run_id": r.run_id,
                "cell_id": r.cell.cell_id,
                "replicate": r.replicate,
                "seed": r.seed,
            }
            for r in runs
        ],
    }
    write_atomic(out_dir / "sweep.json", json.dumps(_json_safe(plan_data), indent=1))


def check_out_dir(spec: SweepSpec, out_dir: str | Path) -> None:
    """Raise :class:`ConfigError` when ``out_dir`` holds another sweep's results: its
    ``sweep.json`` names another sweep (a sweep is known by its name and seed: the same file
    with a grid that grew is the same sweep, a sweep with another seed has other runs).
    Writing there would replace that plan and overwrite the run files of the same run ids
    (a run id is its scenario, parameters and replicate), and mix the two in ``runs/``."""
    path = Path(out_dir) / "sweep.json"
    if not path.exists():
        return
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
        theirs = (data["name"], data["seed"])
    except (OSError, ValueError, TypeError, KeyError) as exc:
        raise ConfigError(
            f"output directory {str(out_dir)!r}: its sweep.json is not a sweep's plan ({exc});"
            " choose another --out"
        ) from None
    if theirs != (spec.name, spec.seed):
        raise ConfigError(
            f"output directory {str(out_dir)!r} holds the results of another sweep:"
            f" {theirs[0]!r} seed {theirs[1]} (from {data.get('source') or '?'}), not"
            f" {spec.name!r} seed {spec.seed}; choose another --out, remove that folder to"
            f" replace them, or (the same sweep renamed) give the file name = {theirs[0]!r}"
            f" and seed = {theirs[1]} back to go on with them"
        )


LOCK_FILE = ".sweep.lock"
"""In the output directory: locked (``flock``) by the sweep writing it, holding its pid."""


@contextlib.contextmanager
def out_dir_lock(out_dir: str | Path) -> Iterator[None]:
    """Hold an exclusive lock on ``OUT/.sweep.lock`` (:data:`LOCK_FILE`) for the block, or
    raise :class:`ConfigError` at once naming the pid of the sweep that holds it: two sweeps
    into one folder both simulated every run and wrote the same files. The lock is the open
    file's, so it goes with its process, however that ends (a SIGKILL leaves no stale lock);
    the file stays."""
    path = Path(out_dir) / LOCK_FILE
    try:  # not through a symlink: its target would be emptied
        fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW, 0o666)
    except OSError as exc:  # another user's lock file, a link: a clear exit 2, no traceback
        raise ConfigError(f"output directory {str(out_dir)!r}: cannot open {path}: {exc}") from None
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            pid = os.pread(fd, 32, 0).decode(errors="replace").strip() or "?"
            raise ConfigError(
                f"output directory {str(out_dir)!r}: another sweep (pid {pid}) is writing it;"
                " wait for it to end, or choose another --out"
            ) from None
        except OSError as exc:  # a file system without locks (some NFS, SMB, FUSE mounts)
            log.warning("%s: not locked (%s): two sweeps into it would both run", path, exc)
        else:
            with output_file(path):  # a full disk: exit 2 naming the file
                os.ftruncate(fd, 0)
                os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        yield
    finally:
        os.close(fd)  # and with it the lock


def _legacy_record(run: Run, store: RunStore) -> dict[str, Any] | None:
    """``run``'s record in a folder made before 2026-12-05, under its old id
    (:func:`legacy_run_id`), if that file is ``run``'s (:func:`same_run`)."""
    old = legacy_run_id(run)
    if old == run.run_id:
        return None
    rec = store.load(old)
    return rec if same_run(rec, run) else None


def older_records(
    runs: Sequence[Run], store: RunStore, retry_failed: bool = False
) -> dict[str, str]:
    """The runs (by run id) whose stored record is theirs (:func:`same_run`) and would be done
    but for its schema (:func:`stale_reason`), with the reason: they are run again, and their
    files are moved to :data:`OLDER_RUNS_DIR` when the new one is written. A lost run, and a
    run stored as failed because its worker's x6wd was another (:func:`worker_mismatch`),
    are run again anyway and not listed."""
    found: dict[str, str] = {}
    for run in runs:
        rec = store.load(run.run_id)
        if rec is None:
            rec = _legacy_record(run, store)
        if rec is None or not same_run(rec, run) or rec.get("status") == "lost":
            continue
        if WORKER_MISMATCH in rec:  # a failure with no figures to keep: simply run again
            continue
        if rec.get("status") == "error" and retry_failed:
            continue  # run again whatever its schema
        why = stale_reason(rec)
        if why is not None:
            found[run.run_id] = why
    return found


def older_text(older: dict[str, int], folder: Path) -> str:
    """The stderr line about the runs :func:`older_records` found, by reason ("" without)."""
    if not older:
        return ""
    parts = [f"{n} run{'' if n == 1 else 's'} {why}" for why, n in older.items()]
    n = sum(older.values())
    return (
        f"sweep: {'; '.join(parts)} {'is' if n == 1 else 'are'} run again (a summary tables"
        f" one schema's figures only); the old record{'' if n == 1 else 's'}"
        f" {'goes' if n == 1 else 'go'} to {folder}"
    )


def split_done(
    runs: Sequence[Run], store: RunStore, retry_failed: bool = False
) -> tuple[dict[str, dict[str, Any]], list[Run]]:
    """The stored records of the runs that are done (by run id) and the runs still to do.
    A run's file is looked up under its id, then under its id of before 2026-12-05
    (:func:`legacy_run_id`; :func:`migrate_legacy_runs` renames such files)."""
    records: dict[str, dict[str, Any]] = {}
    todo: list[Run] = []
    for run in runs:
        rec = store.load(run.run_id)
        if rec is None:
            rec = _legacy_record(run, store)
        if rec is not None and is_done(rec, run, retry_failed):
            # the same cell and seed, labelled as this plan has it (a key moved from [grid]
            # to [set] keeps the run, not its old column; a file of before 2026-12-05 its
            # short id)
            records[run.run_id] = {
                **rec,
                "run_id": run.run_id,
                "cell_id": run.cell.cell_id,
                "params": _json_safe(run.cell.params),
            }
        else:
            todo.append(run)
    return records, todo


def migrate_legacy_runs(runs: Sequence[Run], store: RunStore) -> int:
    """Rename the run files of a folder made before 2026-12-05 (cell ids of 8 hex digits,
    :data:`LEGACY_CELL_ID_HEX`) to the ids of ``runs``: a file under a run's old id whose
    seed and fingerprint are the run's (:func:`same_run`; two cells could share an old id,
    and the file is then the one written last) is written under its new id, relabelled, and
    the old file and the cell's old ``cells/`` file removed. Returns the files renamed."""
    moved = 0
    cells: set[str] = set()
    for run in runs:
        old = legacy_run_id(run)
        if old == run.run_id or not store.path(old).exists():
            continue
        rec = _legacy_record(run, store)
        if rec is None:
            continue
        if not store.path(run.run_id).exists():  # else: renamed, then interrupted
            store.write({**rec, "run_id": run.run_id, "cell_id": run.cell.cell_id})
            moved += 1
        store.path(old).unlink(missing_ok=True)
        cells.add(legacy_cell_id(run.cell.cell_id))
    for cid in cells:
        (store.dir.parent / "cells" / f"{cid}.toml").unlink(missing_ok=True)
    return moved


def run_sweep(
    spec: SweepSpec,
    out_dir: str | Path,
    executor: Executor,
    progress: Callable[[int, int, int], None] | None = None,
    retry_failed: bool = False,
    runs: Sequence[Run] | None = None,
    waiting: Callable[[float, float], None] | None = None,
) -> SweepResult:
    """Plan (unless ``runs`` is given), skip the runs already in ``out_dir``, run the rest on
    ``executor`` (entered by the caller), store each as it finishes, and return every planned
    run's record. ``progress(done, failed, lost)`` counts over all planned runs: ``done``
    the runs with a record (found done, finished or lost), ``failed`` those whose mission
    raised, ``lost`` those the cluster could not finish; ``waiting(waited_s, timeout_s)``
    while no worker is connected (:meth:`~sim_backend.executor.Executor.map_unordered`). The
    report
    (:func:`sim_backend.sweep_report.write_report`) is the caller's next step. A folder that
    holds another sweep is a :class:`ConfigError` (:func:`check_out_dir`)."""
    t0 = time.perf_counter()
    out = Path(out_dir)
    check_out_dir(spec, out)
    runs = list(runs) if runs is not None else plan(spec)
    out.mkdir(parents=True, exist_ok=True)
    write_plan(spec, runs, out)
    store = RunStore(out)
    migrate_legacy_runs(runs, store)
    stale = older_records(runs, store, retry_failed)
    older = dict(Counter(stale.values()))
    older_dir = out / OLDER_RUNS_DIR
    if older:  # the command says it (no logging configured: Python's stderr fallback)
        log.warning("%s", older_text(older, older_dir))
    records, todo = split_done(runs, store, retry_failed)
    skipped = len(records)

    def report() -> None:
        if progress:
            status = [r.get("status") for r in records.values()]
            lost = status.count("lost")
            progress(len(records), len(status) - status.count("ok") - lost, lost)

    report()
    # the engine only where it is not run_task's default: a worker of an x6wd before it
    # (same results schema) still runs the missions (a survey cell's run fails there, named)
    args = []
    for r in todo:
        engine = () if r.cell.engine == "robot" else (r.cell.engine,)
        args.append((r.run_id, r.cell.world_toml, r.seed, *engine))
    ran = raised = 0
    names = [r.run_id for r in todo]
    mismatched = False
    for outcome in executor.map_unordered(run_task, args, names=names, waiting=waiting):
        run = todo[outcome.index]
        rec = _record(run, outcome.value if outcome.ok else None, outcome)
        if WORKER_MISMATCH in rec and not mismatched:  # once: each such run says it too
            mismatched = True
            log.warning(
                "sweep: %s (worker %s); its runs are stored as failed, in no table, and the"
                " next call runs them again",
                rec["error"],
                rec.get("worker", "?"),
            )
        if run.run_id in stale:  # kept for a comparison, out of runs/ and every table
            older_dir.mkdir(exist_ok=True)
            with contextlib.suppress(FileNotFoundError):
                os.replace(store.path(run.run_id), older_dir / f"{run.run_id}.json")
        store.write(rec)
        records[run.run_id] = rec
        ran += rec.get("status") != "lost"
        raised += rec.get("status") == "error"
        report()
    return SweepResult(
        spec=spec,
        runs=runs,
        records=[records[r.run_id] for r in runs],
        ran=ran,
        skipped=skipped,
        wall_s=time.perf_counter() - t0,
        executor=executor.description,
        raised=raised,
        older=older,
    )
