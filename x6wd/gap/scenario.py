"""Baseline runs from a scenario: the simulator's own receiver driven along the real log's truth.

For each seed the scenario's receiver (:func:`sim_backend.receiver.build_receiver`, the one
``x6wd sim`` and HIL run: almanac sky, start time, fidelity, mask, atmosphere, walls, LCE
grid, every ``[[effects]]`` GPS layer, the NMEA minutes' decimals) reports positions for a
receiver that is truly where the real one was (the surveyed point, or the truth track at the
real log's times), placed at the real log's origin.

:func:`place_at_log` puts the scenario where and when the real log was: its origin at the
log's (the truth's) position and the log's mean altitude, its ``start_utc`` at the log's first
epoch when the log is dated. The sky (satellites in view, their elevations, DOP, the hour's
atmosphere) is the log's only at the log's own time, so the log's date wins over the
scenario's ``start_utc``, and the notes say so, with the almanac's age at that date
(:func:`sim_backend.runs.sky_warnings`). A log without a date (a receive clock, seconds from
its start) keeps the scenario's, also said.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import replace
from datetime import UTC, datetime
from pathlib import Path
from typing import TYPE_CHECKING, Any

from drivers.gps_io import GPS_WEEK_ROLLOVER
from sim_backend.effects import PositionSeries
from sim_backend.executor import Executor
from x6wd.core.errors import ConfigError
from x6wd.gap.rate import at_analysis_rate

if TYPE_CHECKING:
    from sim_backend.world import World

ORIGIN_ALT_RANGE_M = (-500.0, 9000.0)
"""Altitudes (m) a scenario's origin takes (sim_backend.world.Origin): a log's mean outside
them (a bad altitude column) leaves the scenario's."""


def place_at_log(
    world: World,
    template: PositionSeries,
    start_utc_s: float | None = None,
    alt_m: float = math.nan,
    alt_from: str = "the real log's mean altitude",
) -> tuple[World, list[str]]:
    """``world`` (a loaded scenario) placed where and when the real log was, and notes for
    the report saying what the runs simulate and what was taken from the log.

    The origin's latitude and longitude are ``template``'s (the truth's, or the log's mean);
    its altitude ``alt_m`` when finite and within :data:`ORIGIN_ALT_RANGE_M` (``alt_from``
    says whose); ``start_utc`` the log's first epoch ``start_utc_s`` (UTC s) when given,
    whatever the scenario says (a scenario describes a receiver and a site; the sky must be
    that log's). The notes end with the almanac's age at that date, when it is far."""
    from sim_backend.runs import sky_warnings

    notes: list[str] = []
    said = world.start_utc
    origin = replace(world.origin, lat_deg=template.origin_lat_deg, lon_deg=template.origin_lon_deg)
    lo_m, hi_m = ORIGIN_ALT_RANGE_M
    if math.isfinite(alt_m) and lo_m <= alt_m <= hi_m:
        origin = replace(origin, alt_m=float(alt_m))
        alt_text = f"{alt_m:.0f} m ({alt_from})"
    elif math.isfinite(alt_m):
        alt_text = (
            f"{origin.alt_m:.0f} m (the scenario's: {alt_from}, {alt_m:.0f} m, is outside"
            f" {lo_m:.0f}..{hi_m:.0f} m)"
        )
    else:
        alt_text = f"{origin.alt_m:.0f} m (the scenario's; the log gives none)"
    if start_utc_s is not None:
        start = datetime.fromtimestamp(start_utc_s, UTC)
        world = replace(world, start_utc=start)
        when = (
            f"{start:%Y-%m-%d %H:%M:%S}Z, the real log's first epoch"
            + ("" if start == said else f" (the scenario's start_utc {said:%Y-%m-%d %H:%M}Z is"
               " not used: the sky must be the log's)")
        )  # fmt: skip
    else:
        when = (
            f"{said:%Y-%m-%d %H:%M:%S}Z, the scenario's start_utc: the real log has no date (a"
            " receive clock or seconds from its start), so the simulated sky may not be the"
            " one it saw"
        )
    world = replace(world, origin=origin)
    notes.append(
        f"the scenario's runs simulate {when}; at {origin.lat_deg:.6f}, {origin.lon_deg:.6f}"
        f" (the truth, or the log's mean), altitude {alt_text}"
    )
    rolled = week_rollover_hint(start_utc_s)  # said with the sky's warnings (stderr too)
    if rolled:
        notes.append(rolled)
    duration_s = float(template.t_s[-1] - template.t_s[0]) if len(template) else 0.0
    notes += [f"simulated sky: {w}" for w in sky_warnings(world, duration_s)]
    return world, notes


LAST_ROLLOVER_UTC = datetime(2019, 4, 7, tzinfo=UTC)


def week_rollover_hint(start_utc_s: float | None, now: datetime | None = None) -> str:
    """A note for a log dated before the last GPS week rollover whose date plus 1024 weeks
    is not in the future (``now``, default the clock): a receiver whose firmware predates a
    rollover prints such dates (one that predates two, 2048 weeks early), and the simulated
    sky is then 19.6 years off or more. It names every such date up to ``now``. Else ""."""
    if start_utc_s is None:
        return ""
    start = datetime.fromtimestamp(start_utc_s, UTC)
    end = now or datetime.now(UTC)
    later = []
    k = 1
    while start < LAST_ROLLOVER_UTC and start + k * GPS_WEEK_ROLLOVER <= end:
        later.append(f"{1024 * k} weeks later, on {start + k * GPS_WEEK_ROLLOVER:%Y-%m-%d}")
        k += 1
    if not later:
        return ""
    return (
        f"the real log is dated {start:%Y-%m-%d}: if its receiver's firmware predates a GPS"
        f" week rollover (1999-08-22, 2019-04-07) it was recorded {' or '.join(later)}, and"
        " the runs simulate the wrong sky (add those weeks to the log's dates to simulate its"
        " own)"
    )


def scenario_baseline(
    path: str | Path | World,
    template: PositionSeries,
    seeds: int,
    base_seed: int = 1000,
    progress: Callable[[int], None] | None = None,
    extra_effects: Sequence[Any] = (),
    executor: Executor | None = None,
) -> list[PositionSeries]:
    """``seeds`` error series (m) shaped like ``template`` (its times, origin and true
    motion; a template faster than the analysis rate at that rate, as the diagnosis reads it:
    :func:`x6wd.gap.rate.at_analysis_rate`), each from the scenario's simulated receiver
    with seed ``base_seed + i`` (split as ``x6wd sim`` splits a seed, so seed N is the
    receiver ``x6wd sim --seed N`` runs);
    ``extra_effects`` (GPS layers) run after the scenario's own, before the NMEA printing
    (the injection benchmark's withheld effects). The seeds run on ``executor`` (entered by
    the caller: x6wd's one executor, e.g. a Dask cluster), or one after another in this
    process; the list is in seed order either way. ``progress(k)``: k seeds done.
    ``path``: a scenario file, or a scenario already loaded (:func:`place_at_log`'s); a file
    keeps its own start_utc and altitude."""
    try:
        from sim_backend.world import World, load_world
    except ImportError as exc:  # pragma: no cover - the simulator ships with the package
        raise ConfigError(f"--scenario needs the simulator: {exc}") from exc
    if seeds < 1:
        raise ConfigError(f"--seeds {seeds}: must be >= 1")
    world = path if isinstance(path, World) else load_world(path)
    # The scenario describes the real log's site: its frame is the log's origin.
    origin = replace(world.origin, lat_deg=template.origin_lat_deg, lon_deg=template.origin_lon_deg)
    world = replace(world, origin=origin)
    # The runs are made at the real log's analysis rate (x6wd.gap.rate): the diagnosis reads
    # a faster log at that rate, so epochs between are never read (20 Hz: 10x the time and
    # memory of the runs for nothing)
    template, _note = at_analysis_rate(template)
    ex = executor if executor is not None else Executor(inline=True)
    args = [(world, base_seed + i, template, tuple(extra_effects)) for i in range(seeds)]
    out: list[PositionSeries | None] = [None] * seeds
    runs = ex.map_unordered(_baseline_run, args, reraise=True)
    for done, outcome in enumerate(runs, start=1):
        if not outcome.ok:  # the cluster lost it (a failing seed raises its own error)
            raise ConfigError(f"baseline seed {base_seed + outcome.index}: {outcome.error}")
        out[outcome.index] = outcome.value
        if progress:
            progress(done)
    return [s for s in out if s is not None]


def _baseline_run(
    world: Any, seed: int, template: PositionSeries, extra_effects: Sequence[Any]
) -> PositionSeries:
    """One baseline seed (a task of the executor)."""
    from sim_backend.receiver import build_receiver

    return build_receiver(world, seed, extra_layers=extra_effects).errors(template)
