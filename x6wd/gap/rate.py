"""The analysis rate: a log sampled faster than :data:`MAX_ANALYSIS_HZ` is read at a bounded rate.

Every statistic of the battery, the likelihood fits and the simulations that make the
baseline are computed per epoch, so their time and memory grow with the epoch count: one hour
at 20 Hz (72,000 epochs) passed 1 GB and ran for more than 7 minutes (outside audit,
2026-12-05), against 190 MB and 42 s at 1 Hz. What the tool reads does not need the rate:
its time scales are set by the analysis step (the Allan octaves and the spectrum's top band
start at it, the autocorrelation lags are 1, 10, 60 and 300 s, the increments 4, 16, 64 s),
and the layers it fits act over seconds (a navigation filter's or a noise scale's time
constant is searched from one analysis step up, a latency is a delay times the true speed
at any rate). So a log whose step is shorter than ``1 / MAX_ANALYSIS_HZ`` keeps every k-th
epoch of its time grid (k the smallest integer with k steps at least that long): 20 Hz is
read at 2 Hz, 10 Hz at 2 Hz, 5 Hz at 1.67 Hz, and a log of 2 Hz or slower as it is.

The epochs kept are the log's own, with their own stamps and values (no averaging: an average
of fixes would be quieter than the receiver and off its NMEA lattice). What a faster rate
alone shows is not read: structure shorter than the analysis step (a filter of a 0.2 s time
constant), and outages or jumps out and back that fall between kept epochs. The report's
notes say at which rate the log was read.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from sim_backend.effects import PositionSeries, truth_track_m

MAX_ANALYSIS_HZ = 2.0
"""The fastest rate a log is analysed at (Hz). 2 Hz keeps a half-second structure (a
receiver's navigation filter of 0.5 s and up) and the 1-s autocorrelation lag two steps
long, at twice the epochs of a 1 Hz log: an hour stays within the 500 MB of issue 15 item 4
and about twice the time of an hour at 1 Hz (docs/gap.md, Limits)."""

STEP_TOLERANCE = 1e-3  # a step this close (relative) to the analysis step is taken as it


def median_step_s(series: PositionSeries) -> float:
    """The log's median step (s; nan with fewer than two epochs)."""
    t_s = np.asarray(series.t_s, dtype=float)
    return float(np.median(np.diff(t_s))) if t_s.size > 1 else math.nan


def decimation_factor(step_s: float, max_hz: float = MAX_ANALYSIS_HZ) -> int:
    """Every how many slots of a ``step_s`` grid an epoch is kept (1: the log as it is)."""
    if not math.isfinite(step_s) or step_s <= 0.0:
        return 1
    return max(1, math.ceil((1.0 / max_hz) / step_s * (1.0 - STEP_TOLERANCE)))


def _take(series: PositionSeries, keep: np.ndarray) -> PositionSeries:
    def cut(a: np.ndarray | None) -> np.ndarray | None:
        return None if a is None else np.asarray(a)[keep]

    changes: dict[str, object] = {
        name: cut(getattr(series, name))
        for name in ("t_s", "east_m", "north_m", "up_m", "valid", "speed_mps", "course_deg",
                     "nsats", "sat_set", "true_east_m", "true_north_m")
    }  # fmt: skip
    if series.speed_mps is not None and series.true_east_m is None:
        # the true track is integrated from the true velocity at the log's own rate: carried
        # as it is, not integrated again over the coarser steps
        true_east_m, true_north_m = truth_track_m(series)
        changes["true_east_m"], changes["true_north_m"] = true_east_m[keep], true_north_m[keep]
    return series.with_(**changes)


def decimate(series: PositionSeries, factor: int) -> PositionSeries:
    """``series`` with one epoch in each span of ``factor`` slots of its time grid (its median
    step from its first epoch): the span's first epoch with a fix, else its first; stamps
    and values as they are. By span, not by every ``factor``-th slot: a log whose rate fell
    (20 Hz from .05 s, then 1 Hz on whole seconds, the gaps filled with fixless epochs) kept
    only fixless slots and lost all 600 of its 1 Hz fixes."""
    if factor <= 1 or len(series) < 2:
        return series
    t_s = np.asarray(series.t_s, dtype=float)
    # slots counted step by step: a 3 Hz log's stamps to 0.01 s (.00, .33, .67) against its
    # 0.33 s median gained a slot every 100 epochs, a 1-s hole in the kept epochs each time
    steps = np.rint(np.diff(t_s) / median_step_s(series)).astype(np.int64)
    span = np.concatenate(([0], np.cumsum(steps))) // factor
    valid = np.asarray(series.valid, dtype=bool)
    order = np.lexsort((np.arange(len(t_s)), ~valid, span))  # by span, fixes first, in time
    first = np.concatenate(([True], span[order][1:] != span[order][:-1]))
    keep = np.zeros(len(t_s), dtype=bool)
    keep[order[first]] = True
    return _take(series, keep)


def at_step(series: PositionSeries, step_s: float) -> PositionSeries:
    """``series`` read at ``step_s`` (s) when its own step is shorter (a baseline log next
    to a real log read at its analysis step), else as it is."""
    own_s = median_step_s(series)
    if not own_s < step_s * (1.0 - STEP_TOLERANCE):
        return series
    return decimate(series, max(1, round(step_s / own_s)))


def at_analysis_rate(series: PositionSeries) -> tuple[PositionSeries, str | None]:
    """``series`` read at the analysis rate, and the note saying so (None: read as it is)."""
    step_s = median_step_s(series)
    factor = decimation_factor(step_s)
    if factor == 1:
        return series, None
    out = decimate(series, factor)
    note = (
        f"the log was read at {1.0 / (factor * step_s):.3g} Hz of its {1.0 / step_s:.3g} Hz"
        f" (one epoch in {factor}: {len(out)} of {len(series)}, stamps and values as logged;"
        f" x6wd.gap.rate.MAX_ANALYSIS_HZ = {MAX_ANALYSIS_HZ:g}): every statistic and fit, and"
        " the simulated runs, are at that rate, so structure faster than"
        f" {factor * step_s:g} s and outages shorter than it are not seen"
    )
    return out, note


def baseline_at(
    real: PositionSeries, baseline: Sequence[PositionSeries]
) -> tuple[PositionSeries, list[PositionSeries], list[str]]:
    """The real log at the analysis rate and the baseline logs at its analysis step, with the
    note (none when the real log is read as it is)."""
    step_s = median_step_s(real)
    out, note = at_analysis_rate(real)
    if note is None:
        return real, list(baseline), []
    analysis_s = decimation_factor(step_s) * step_s
    return out, [at_step(s, analysis_s) for s in baseline], [note]
