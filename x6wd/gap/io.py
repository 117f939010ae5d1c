"""Readers for the gap tool: any log -> a :class:`Track` of positions -> a PositionSeries of
errors against a truth (a fixed point, a truth track, or the log's own mean as a last resort).

Formats, chosen by content then suffix:
- x6wd recordings (JSON lines): ``fix`` records, else their ``nmea`` lines decoded;
- plain NMEA logs from any receiver (decoded by :class:`drivers.gps_nmea.GpsDecoder`), binary
  protocols interleaved or not;
- CSV with a header naming time, lat, lon[, alt] (case-insensitive; ``latitude``, ``msl`` ...
  accepted) or headerless ``time,lat,lon[,alt]``;
- RTKLIB ``.pos`` solutions (date/time or GPS week/seconds, lat, lon, height, Q, ns), in the
  time system their header's column legend names (``GPST``, RTKLIB's default and what a
  header-less file is taken to be; ``UTC``; ``JST``), turned into UTC (GPST less the GPS-UTC
  leap seconds in force then: 18 s since 2017), so that a truth track from RTKLIB lines up
  with an NMEA log's UTC.

Robust input (the tool's arrays are sized from the time axis, so a bad axis is a memory
bomb): a log is read in chunks, never whole, and a line longer than :data:`MAX_LINE_BYTES`
is an error. One log has one time axis: for NMEA it comes from dated sentences only (RMC
with a date, ZDA); epochs before the first date are dated from it, epochs without any time
are dropped and counted, and a log without a date is an error naming what is missing. A
recording without UTC uses its receive clock for every epoch, never a mix of the two. Times
are then sorted (out-of-order epochs counted) and repeated time stamps resolved
(:func:`_resolve_repeats`: a row that repeats the one before it whole is dropped; a distinct fix
stamped with a neighbour's time by a jittery logger clock is moved onto the empty slot beside
it, as are the rows between, never by more than one step; counted in the notes) and the axis
is bounded: the regular grid the tool builds over a log holds at most :data:`GRID_FACTOR`
slots per epoch read; a log whose holes exceed that is cut at its largest hole, the part
with more epochs kept (said in ``Track.notes``), until it fits.
"""

from __future__ import annotations

import csv
import math
import re
import tempfile
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass, replace
from dataclasses import fields as dataclass_fields
from datetime import UTC, datetime, timedelta
from datetime import time as dt_time
from pathlib import Path
from typing import Any

import numpy as np

from sim_backend.effects import PositionSeries, metres_per_degree, satellite_set_id
from x6wd.core.errors import ConfigError, DeviceUnavailable, ParseError
from x6wd.core.files import not_regular, not_text
from x6wd.core.geodesy import EARTH_MEAN_RADIUS_M
from x6wd.core.motion import MAX_STATIC_SPEED_MPS, MOVE_SIGNIFICANCE, steady_speed_mps
from x6wd.core.recorder import compression_of, gpsd_json_error, is_gpsd_json

MAX_LINE_BYTES = 1 << 16
"""Longest line of a text log (CSV, .pos) read (bytes); longer is not such a log."""
GRID_FACTOR = 10
MAX_ABS_TIME_S = 1e11  # a time stamp beyond it (s) is not a time: the epoch is dropped
# Beyond these a log is no static receiver (errors against its own mean would count its
# route as error): a static receiver's reported speed is noise of a few cm/s to a few dm/s,
# and even a poor urban fix lies a few tens of metres from its median.
STATIC_MAX_SPEED_MPS = 1.0
STATIC_MAX_SPREAD_M = 100.0
# Errors against a truth beyond this (m, the median) are no GNSS error: the log was made
# elsewhere (a simulation of another place) or the truth is wrong.
MAX_ERROR_FROM_TRUTH_M = 1000.0
"""Most slots of the log's regular time grid (span / median step + 1) per epoch read."""
_CHUNK_BYTES = 1 << 20
_SNIFF_BYTES = 1 << 16
_MAX_CUTS = 64  # a time axis needing more cuts than this is rejected, not searched
# An NMEA sentence with its checksum ("$GPGGA,...*hh", "!AIVDM,...*hh") anywhere in a line
# of the first 64 KiB: what makes a file an NMEA log. Not only at a line's start: loggers
# prefix lines with a time stamp or a second "$" (gpsd's ST Teseo log), and the framer skips
# such bytes.
_NMEA_HEAD = re.compile(rb"[$!][A-Z][A-Z0-9]{1,5},[^\r\n$!]*\*[0-9A-Fa-f]{2}")
# A line that starts as an NMEA sentence does ("$GPGGA,"), with or without its checksum:
# also NMEA after comment lines ("# Name: ..." as gpsd's logs begin) or gpsd's JSON
# preamble (gpspipe -r writes VERSION, DEVICES and WATCH objects before the NMEA).
_NMEA_LINE = re.compile(rb"(?m)^[ \t]*[$!][A-Z][A-Z0-9]{1,5},")
_NMEA_LINE_CHECKED = re.compile(rb"(?m)^[ \t]*" + _NMEA_HEAD.pattern)  # at a line start
_TEXT_BYTES = frozenset(b"\t\n\r\f") | frozenset(range(0x20, 0x7F)) | frozenset(range(0x80, 0x100))


@dataclass(frozen=True)
class Track:
    """Reported positions of one log. ``t_s`` seconds (UTC epoch seconds when the log has
    dates, RTKLIB's GPST turned into UTC too; else the log's own clock), strictly
    increasing; ``alt_m`` NaN where unknown; ``valid`` False on no-fix epochs; ``nsats``
    satellites used (-1 unknown); speed/course NaN where unknown; ``notes`` what reading
    dropped, cut or re-timed, for the report; ``sat_set`` the identity of the satellites used
    (:func:`sim_backend.effects.satellite_set_id`, -1 unknown; None when the log never lists
    them)."""

    t_s: np.ndarray
    lat_deg: np.ndarray
    lon_deg: np.ndarray
    alt_m: np.ndarray
    valid: np.ndarray
    nsats: np.ndarray
    speed_mps: np.ndarray
    course_deg: np.ndarray
    source: str = ""
    notes: tuple[str, ...] = ()
    sat_set: np.ndarray | None = None
    time_column: str = ""  # a CSV's column of numeric times, as its header names it

    def __len__(self) -> int:
        return int(self.t_s.shape[0])


GLITCH_M = 1000.0
"""A fix further than this (m) from the median of its neighbours (:data:`GLITCH_WINDOW`
valid fixes) is a receiver's glitch: no GNSS error lies a kilometre off for a moment.
Further still where the window spans more time than a ground vehicle at
:data:`GLITCH_SPEED_MPS` crosses it (sparse fixes of a moving log)."""
GLITCH_WINDOW = 11
GLITCH_SPEED_MPS = 100.0


def _glitches(
    t_s: np.ndarray, lat_deg: np.ndarray, lon_deg: np.ndarray, valid: np.ndarray
) -> np.ndarray:
    """Per epoch, how far (m) a valid fix lies from the median of the :data:`GLITCH_WINDOW`
    valid fixes around it where that is beyond its glitch limit (:data:`GLITCH_M`); 0
    elsewhere. A log of fewer valid fixes than the window has none."""
    out = np.zeros(t_s.shape[0])
    idx = np.flatnonzero(valid)
    if idx.size < GLITCH_WINDOW:
        return out
    half = GLITCH_WINDOW // 2
    lat, lon, t = lat_deg[idx], lon_deg[idx], t_s[idx]
    lon_rel = (lon - lon[0] + 180.0) % 360.0 - 180.0  # continuous across ±180
    pad = [np.pad(a, half, mode="edge") for a in (lat, lon_rel, t)]
    win = [np.lib.stride_tricks.sliding_window_view(a, GLITCH_WINDOW) for a in pad]
    med_lat, med_lon = np.median(win[0], axis=1), np.median(win[1], axis=1)
    m_per_deg_lat = math.radians(EARTH_MEAN_RADIUS_M)  # a kilometre test needs no ellipsoid
    north_m = (lat - med_lat) * m_per_deg_lat
    east_m = (lon_rel - med_lon) * m_per_deg_lat * np.cos(np.radians(med_lat))
    off_m = np.hypot(north_m, east_m)
    span_s = win[2][:, -1] - win[2][:, 0]
    limit_m = np.maximum(GLITCH_M, GLITCH_SPEED_MPS * span_s / 2.0)
    out[idx] = np.where(off_m > limit_m, off_m, 0.0)
    return out


def _track(rows: list[tuple[float, ...]], source: str, notes: Iterable[str] = ()) -> Track:
    """Rows (t, lat, lon, alt, valid, nsats, speed, course[, satellite set]) in log order ->
    Track sorted by time, duplicates of a time stamp dropped (first kept), the span bounded
    (module doc)."""
    notes = list(notes)
    if not rows:
        raise ParseError(f"{source}: no position epochs found")
    table = np.array(rows, dtype=float)
    # beyond MAX_ABS_TIME_S no clock of a log lies (1e11 s: year 5138 as Unix time)
    finite = np.isfinite(table[:, 0]) & (np.abs(table[:, 0]) < MAX_ABS_TIME_S)
    if not np.all(finite):
        notes.append(f"{int(np.count_nonzero(~finite))} epochs without a usable time dropped")
        times = table[:, 0][np.isfinite(table[:, 0])]
        table = table[finite]
        if not table.size:
            raise ParseError(f"{source}: no epoch has a usable time{_ms_hint(times)}")
    t_s = table[:, 0]
    back = int(np.count_nonzero(t_s[1:] < np.maximum.accumulate(t_s)[:-1]))
    order = np.argsort(t_s, kind="stable")
    table = table[order]
    if np.any(np.diff(table[:, 0]) <= 0):
        table, repeat_notes = _resolve_repeats(table)
        notes += repeat_notes
    if back:
        notes.append(f"{back} epochs went back in time in the log (sorted by time)")
    lo, hi, cuts = _bounded_span(table[:, 0], source)
    if cuts:
        notes.append(
            f"time axis cut at {cuts} hole(s) (a regular grid over it would hold more than"
            f" {GRID_FACTOR} slots per epoch): {hi - lo} of {len(table)} epochs kept,"
            f" {_utc_text(table[lo, 0])} to {_utc_text(table[hi - 1, 0])}"
        )
        table = table[lo:hi]
    valid = (table[:, 4] > 0) & np.isfinite(table[:, 1]) & np.isfinite(table[:, 2])
    unplaced = int(np.count_nonzero((table[:, 4] > 0) & ~valid))
    if unplaced:  # a CSV row of nan (or an empty) latitude or longitude: no position
        notes.append(
            f"{unplaced} of {len(table)} epochs have no finite latitude or longitude (nan, inf"
            " or empty): taken as no fix"
        )
    on_earth = (np.abs(table[:, 1]) <= 90.0) & (np.abs(table[:, 2]) <= 180.0)
    if np.any(valid & ~on_earth) and not np.any(valid & on_earth):
        off = table[valid & ~on_earth][0]
        raise ParseError(
            f"{source}: every fix has a latitude beyond ±90° or a longitude beyond ±180°"
            f" (the first: {off[1]:g}, {off[2]:g}): degrees and minutes (ddmm.mmmm, as NMEA"
            " writes them)? give decimal degrees (51° 45.12' is 51.752)"
        )
    if np.any(valid & ~on_earth):
        notes.append(
            f"{int(np.count_nonzero(valid & ~on_earth))} fixes with a latitude beyond"
            " ±90° or a longitude beyond ±180° taken as no fix"
        )
        valid &= on_earth
    glitches = _glitches(table[:, 0], table[:, 1], table[:, 2], valid)
    if np.any(glitches):
        worst_km = float(np.max(glitches[glitches > 0])) / 1000.0
        notes.append(
            f"{int(np.count_nonzero(glitches))} fixes lie more than {GLITCH_M / 1000:g} km"
            f" (up to {worst_km:.1f} km) from the median of their neighbours: a receiver's"
            " glitch, no error of the GNSS model: taken as no fix"
        )
        valid &= glitches == 0
    return Track(
        t_s=table[:, 0],
        lat_deg=table[:, 1],
        lon_deg=table[:, 2],
        alt_m=table[:, 3],
        valid=valid,
        nsats=table[:, 5],
        speed_mps=table[:, 6],
        course_deg=table[:, 7],
        source=source,
        notes=tuple(notes),
        sat_set=table[:, 8] if table.shape[1] > 8 and np.any(table[:, 8] >= 0) else None,
    )


def _ms_hint(times: np.ndarray) -> str:
    """A hint when finite times beyond MAX_ABS_TIME_S read as dates once divided by 1000
    (milliseconds since 1970), else ""."""
    if times.size and np.all(np.abs(times) >= MAX_ABS_TIME_S):
        seconds = float(np.median(times)) / 1000.0
        if is_date(seconds):
            return (
                f" (times such as {float(times[0]):.0f} are milliseconds since 1970:"
                f" {_utc_text(float(times[0]) / 1000.0)} as seconds; give seconds)"
            )
    return ""


_NO_SLOT = -(1 << 62)  # "no row assigned yet" in _retime_segment
# Slots from a repeated stamp within which an empty slot may be filled: a logger clock late
# for up to this many fixes in a row (static/mobile.csv: of its 340 empty seconds 269 lie
# next to a repeat, 53 two away, the last 18 three to five). Farther holes are outages.
MAX_RETIME_REACH = 5


def _resolve_repeats(table: np.ndarray) -> tuple[np.ndarray, list[str]]:
    """Rows sorted by time (stable: file order within a time stamp) -> the same without
    repeated time stamps, and notes saying what was done.

    A row equal to the one before it in every field both know (NaN: unknown) is the same
    epoch logged twice: dropped, the fields only it knows kept (an RMC+GGA pair logged
    twice decodes as a fix with a speed, then one without: not another fix). Distinct fixes
    under one time stamp are different epochs whose stamp is off: a host logger stamping
    each fix with its own clock in whole seconds stamps two fixes with one second and none
    with the next when its clock jitters across a second
    (gpsd's ``gpxlogger``/CSV loggers on a loaded host; ``static/mobile.csv``: 341 repeated
    stamps and 340 empty seconds in 1406 rows). Dropping them would leave those seconds empty
    and read them as the receiver's outages. On a regular time axis they are re-timed: each
    row may move by at most one step, rows keep their order, and the assignment keeps the
    most rows, then moves the fewest (:func:`_retime_segment`), so a fix next to an empty slot
    takes it, and the rows between a repeat and an empty slot up to MAX_RETIME_REACH steps
    away shift by one step each; an empty slot farther from every repeat is a real outage
    and stays one. A repeat with no empty slot within reach is dropped. When most stamps
    repeat (a row per sentence, a rate finer than the stamps), nothing is re-timed: each
    stamp keeps its most complete row. An irregular axis (no step to re-time by) keeps the
    first row of each stamp, as before."""
    notes: list[str] = []
    t_s = table[:, 0]
    same_stamp = np.concatenate(([False], np.diff(t_s) <= 0))
    exact = np.zeros(len(table), dtype=bool)  # equal in every field, NaN to NaN
    whole = np.zeros(len(table), dtype=bool)  # equal where both rows know the field
    merged = table.copy()
    for i in np.flatnonzero(same_stamp):
        exact[i] = np.array_equal(table[i], table[i - 1], equal_nan=True)
        into = i - 1
        while whole[into]:  # the row the earlier copies of this epoch were merged into
            into -= 1
        a, b = merged[into], merged[i]
        known = ~np.isnan(a) & ~np.isnan(b)
        if np.array_equal(a[known], b[known]):
            whole[i] = True
            merged[into] = np.where(np.isnan(a), b, a)
    if np.count_nonzero(whole & ~exact) > 0.5 * np.unique(t_s).size:
        # most stamps hold rows that complete each other: a row per sentence (RMC, then
        # GGA), not copies logged twice; the several-rows rule below keeps the fullest
        whole = exact
    else:
        table = merged
    if np.any(whole):
        notes.append(
            f"{int(np.count_nonzero(whole))} epochs repeating a time stamp with the same fix"
            " (logged twice) dropped"
        )
        table = table[~whole]
        t_s = table[:, 0]
    if not np.any(np.diff(t_s) <= 0):
        return table, notes
    unique_t = np.unique(t_s)
    steps_s = np.diff(unique_t)
    dt_s = float(np.median(steps_s)) if steps_s.size else 0.0
    ratio = steps_s / dt_s if dt_s > 0 else steps_s
    if dt_s <= 0 or np.mean(np.abs(ratio - np.round(ratio)) < 0.1) < 0.9:
        keep = np.concatenate(([True], np.diff(t_s) > 0))
        notes.append(
            f"{int(np.count_nonzero(~keep))} epochs repeating a time stamp with another fix"
            " dropped (the time axis has no regular step to re-time them by)"
        )
        return table[keep], notes
    slot = np.round((t_s - t_s[0]) / dt_s).astype(np.int64)
    repeated = np.flatnonzero(np.diff(slot) == 0) + 1
    if repeated.size > 0.5 * unique_t.size:
        # most epochs carry several rows (one per sentence, or a rate above the stamps'
        # resolution): no jitter to undo, and moving rows would fill real outages. Each
        # stamp keeps its most complete row (the fewest missing fields; the first of equals).
        missing = np.count_nonzero(np.isnan(table), axis=1)
        order = np.lexsort((np.arange(len(table)), missing, slot))
        first = order[np.concatenate(([True], np.diff(slot[order]) > 0))]
        notes.append(
            f"{repeated.size} rows sharing a time stamp with another fix: most epochs carry"
            " several rows, so each stamp keeps its most complete row (none re-timed)"
        )
        return table[np.sort(first)], notes
    # An empty slot may take a moved row only near a repeat (MAX_RETIME_REACH slots): a
    # jittering clock leaves its hole beside the doubled stamp, while a real outage farther
    # away must stay an outage, not be filled by a chain of rows each shifted by one.
    occupied = np.zeros(int(slot[-1]) + 1, dtype=bool)
    occupied[slot] = True
    near = np.zeros_like(occupied)
    for r in np.unique(slot[repeated]):
        near[max(0, r - MAX_RETIME_REACH) : r + MAX_RETIME_REACH + 1] = True
    allowed = occupied | near
    assigned = slot.copy()
    kept = np.ones(len(slot), dtype=bool)
    lo_slot, hi_slot = int(slot[0]), int(slot[-1])
    # Rows more than two slots apart cannot compete for a slot: solve each stretch alone,
    # and only the stretches that hold a repeated stamp (elsewhere nothing moves).
    bounds = np.flatnonzero(np.diff(slot) >= 3) + 1
    for start, end in zip(
        np.concatenate(([0], bounds)), np.concatenate((bounds, [len(slot)])), strict=True
    ):
        part = slot[start:end]
        if part.size > 1 and np.any(np.diff(part) == 0):
            assigned[start:end], kept[start:end] = _retime_segment(part, lo_slot, hi_slot, allowed)
    moved = kept & (assigned != slot)
    repeats = int(np.count_nonzero(np.diff(slot) == 0))
    dropped = int(np.count_nonzero(~kept))
    if repeats - dropped > 0:
        notes.append(
            f"{repeats - dropped} epochs repeating a time stamp with another fix kept, re-timed"
            " onto the empty slot beside them as a logger clock jittering by a step stamps"
            f" them ({int(np.count_nonzero(moved))} rows moved by one step of {dt_s:g} s)"
        )
    if dropped:
        notes.append(
            f"{dropped} epochs repeating a time stamp with another fix dropped: no empty slot"
            f" within {MAX_RETIME_REACH} steps (one farther is a real outage, kept)"
        )
    table = table.copy()
    table[:, 0] += (assigned - slot) * dt_s
    return table[kept], notes


def _retime_segment(
    slot: np.ndarray, lo: int, hi: int, allowed: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """(assigned slot, kept) of rows at grid slots ``slot`` (non-decreasing): each kept row
    moves to its slot or one beside it that ``allowed[a]`` permits, within [lo, hi], kept
    rows strictly increasing; the most rows kept, then the fewest moved (dynamic programming
    over the last slot taken)."""
    # state: last slot taken -> ((kept, -moved), back-pointer (previous, row, slot) or None)
    states: dict[int, tuple[tuple[int, int], Any]] = {_NO_SLOT: ((0, 0), None)}
    for row, s in enumerate(slot.tolist()):
        merged: dict[int, tuple[tuple[int, int], Any]] = {}
        for last, entry in states.items():  # a last slot below s - 1 constrains nothing now
            key = last if last >= s - 1 else _NO_SLOT
            if key not in merged or entry[0] > merged[key][0]:
                merged[key] = entry
        nxt: dict[int, tuple[tuple[int, int], Any]] = {}
        for last, (score, node) in merged.items():
            options = [(last, score, node)]  # the row dropped
            options += [
                (a, (score[0] + 1, score[1] - abs(a - s)), (node, row, a))
                for a in (s, s - 1, s + 1)
                if lo <= a <= hi and a > last and (a == s or allowed[a])
            ]
            for key, new_score, new_node in options:
                if key not in nxt or new_score > nxt[key][0]:
                    nxt[key] = (new_score, new_node)
        states = nxt
    _, node = max(states.values(), key=lambda entry: entry[0])
    assigned = slot.copy()
    kept = np.zeros(slot.size, dtype=bool)
    while node is not None:
        node, row, a = node
        assigned[row], kept[row] = a, True
    return assigned, kept


def grid_slots(t_s: np.ndarray) -> float:
    """Slots of a regular grid over ``t_s`` (sorted, s) at its median step: what the gap
    tool allocates per array for this time axis."""
    if t_s.size < 2:
        return float(t_s.size)
    return float((t_s[-1] - t_s[0]) / np.median(np.diff(t_s))) + 1.0


def _bounded_span(t_s: np.ndarray, source: str) -> tuple[int, int, int]:
    """(first, end, cuts): the part ``t_s[first:end]`` (sorted, strictly increasing) whose
    grid holds at most GRID_FACTOR slots per epoch, cutting at the largest hole each time
    and keeping the side with more epochs. ParseError if no such part is found quickly."""
    lo, hi = 0, t_s.size
    for cuts in range(_MAX_CUTS + 1):
        part = t_s[lo:hi]
        if grid_slots(part) <= GRID_FACTOR * part.size:
            return lo, hi, cuts
        k = int(np.argmax(np.diff(part)))  # the hole is between part[k] and part[k + 1]
        if k + 1 >= part.size - k - 1:
            hi = lo + k + 1
        else:
            lo = lo + k + 1
    raise ParseError(
        f"{source}: time axis too irregular: {t_s.size} epochs over"
        f" {t_s[-1] - t_s[0]:.6g} s, and {_MAX_CUTS} cuts at its largest holes leave no part"
        f" whose grid holds at most {GRID_FACTOR} slots per epoch"
    )


def _utc_text(t_s: float) -> str:
    """An epoch time as UTC ISO text when it looks like one (after 1980), else seconds."""
    if t_s >= 315_964_800.0 and t_s < 4e9:
        return datetime.fromtimestamp(t_s, UTC).isoformat(timespec="seconds")
    return f"{t_s:.3f} s"


def fill_missing_epochs(track: Track) -> Track:
    """Insert no-fix epochs where a regularly sampled log skips epochs (RTKLIB and CSV logs
    simply omit unsolved epochs; the gap tool must see them as outages). Logs whose times are
    not regular (e.g. NMEA without dates) are returned unchanged."""
    t_s = track.t_s
    if t_s.size < 3:
        return track
    steps_s = np.diff(t_s)
    dt_s = float(np.min(steps_s)) if steps_s.size else 0.0
    if dt_s <= 0 or np.mean(np.abs(steps_s / dt_s - np.round(steps_s / dt_s)) < 0.1) < 0.9:
        return track
    slot = np.round((t_s - t_s[0]) / dt_s).astype(int)
    if slot[-1] > GRID_FACTOR * t_s.size:  # a huge hole is not a run of missed epochs
        return track
    if slot[-1] > 0:  # the step over the whole log: the smallest step is off by ~2e-7 s
        dt_s = float(t_s[-1] - t_s[0]) / float(slot[-1])
        slot = np.round((t_s - t_s[0]) / dt_s).astype(int)
    n_slots = int(slot[-1]) + 1
    first = np.concatenate(([True], np.diff(slot) > 0))
    slot, rows = slot[first], np.flatnonzero(first)

    def spread(a: np.ndarray, fill: float) -> np.ndarray:
        out = np.full(n_slots, fill, dtype=float)
        out[slot] = a[rows]
        return out

    valid = np.zeros(n_slots, dtype=bool)
    valid[slot] = track.valid[rows]
    notes = track.notes
    if n_slots > rows.size:  # always said: a filled hole reads as the receiver's outage
        longest = int(np.max(np.diff(slot))) - 1
        notes = (
            *notes,
            f"{n_slots - rows.size} epochs missing from the log's regular {dt_s:.6g} s steps"
            f" inserted as no-fix epochs, read as outages (the longest hole {longest}"
            f" epoch{'s' if longest != 1 else ''}, {longest * dt_s:.6g} s)",
        )
    # the log's own times where it has epochs, the grid only in its holes: t0 + k dt from the
    # smallest step drifted 3.4 ms over a 1 h 10 Hz log, and its steps were then uneven
    times_s = t_s[0] + np.arange(n_slots) * dt_s
    times_s[slot] = t_s[rows]
    return Track(
        t_s=times_s,
        lat_deg=spread(track.lat_deg, math.nan),
        lon_deg=spread(track.lon_deg, math.nan),
        alt_m=spread(track.alt_m, math.nan),
        valid=valid,
        nsats=spread(track.nsats, 0.0),
        speed_mps=spread(track.speed_mps, math.nan),
        course_deg=spread(track.course_deg, math.nan),
        source=track.source,
        notes=notes,
        sat_set=None if track.sat_set is None else spread(track.sat_set, -1.0),
        time_column=track.time_column,
    )


def read_track(path: str | Path) -> Track:
    """Read any supported log (see module doc), mark skipped epochs of a regularly
    sampled log as no-fix, and settle its satellite counts and heights
    (:func:`settle_counts`, :func:`settle_heights`). Raises DeviceUnavailable for a missing
    file, ParseError (naming the file and the problem) when nothing usable is in it."""
    return settle_heights(settle_counts(fill_missing_epochs(_read_any(path))))


MAX_MISSING_FRACTION = 0.05
"""Fixes of a log without a satellite count (or a height), at most this fraction of them,
are filled from their neighbours; more, and the log's counts (heights) are not used."""


def _fill_from_neighbours(t_s: np.ndarray, values: np.ndarray, known: np.ndarray) -> np.ndarray:
    """``values`` where ``known``, elsewhere the value of the nearest known epoch in time
    (the earlier one on a tie)."""
    at = np.flatnonzero(known)
    index = np.clip(np.searchsorted(t_s[at], t_s), 1, at.size - 1) if at.size > 1 else None
    if index is None:
        return np.where(known, values, values[at[0]])
    before, after = at[index - 1], at[index]
    nearest = np.where(np.abs(t_s[after] - t_s) < np.abs(t_s - t_s[before]), after, before)
    return np.where(known, values, values[nearest])


def settle_counts(track: Track) -> Track:
    """``track`` with satellite counts the gap tool can read, and notes saying what was done.

    The counts matter at the fixes (the steady steps are those between equal counts). A
    count that never changes over the log, with no GSA listing the satellites, tells no
    satellite change (multi-GNSS receivers cap GGA's count at 12): taken as no counts, as a
    bare CSV gives, or every step would be "steady" while the baseline runs' counts change.
    A few fixes without a count (at most :data:`MAX_MISSING_FRACTION`) take their nearest
    neighbour's; more, and the counts are not used. Epochs without a fix get 0."""
    valid = track.valid
    nsats = track.nsats
    known = valid & (nsats >= 0)
    n_valid = int(np.count_nonzero(valid))
    n_known = int(np.count_nonzero(known))
    if n_known == 0:
        return replace(track, nsats=np.full(len(track), -1.0)) if np.any(nsats >= 0) else track
    notes = list(track.notes)
    counts = nsats[known]
    if track.sat_set is None and n_known > 1 and np.all(counts == counts[0]):
        notes.append(
            f"every fix's satellite count is {counts[0]:g} and no GSA lists the satellites"
            " used: a count that never changes (multi-GNSS receivers cap GGA's at 12) tells no"
            " satellite change, so it is taken as no counts (the baseline's are then set"
            " aside too)"
        )
        return replace(track, nsats=np.full(len(track), -1.0), notes=tuple(notes))
    missing = n_valid - n_known
    if missing == 0:
        return replace(track, nsats=np.where(valid, nsats, np.maximum(nsats, 0.0)))
    share = missing / n_valid
    if share > MAX_MISSING_FRACTION:
        notes.append(
            f"{missing} of {n_valid} fixes ({share:.1%}) have no satellite count: the counts"
            f" are not used (at most {MAX_MISSING_FRACTION:.0%} missing are filled from their"
            " neighbours)"
        )
        return replace(track, nsats=np.full(len(track), -1.0), notes=tuple(notes))
    notes.append(
        f"{missing} of {n_valid} fixes ({share:.1%}) have no satellite count: each takes its"
        " nearest neighbour's"
    )
    filled = _fill_from_neighbours(track.t_s, nsats, known)
    return replace(track, nsats=np.where(valid, filled, np.maximum(nsats, 0.0)), notes=tuple(notes))


def settle_heights(track: Track) -> Track:
    """``track`` with a height at every fix or at none, and notes saying what was done: a
    few fixes without a height (at most :data:`MAX_MISSING_FRACTION`) are interpolated in
    time from their neighbours; more, and the log's heights are not used (NaN). A fix without
    a height used to be an up error of 0: a perfect height amid the real ones."""
    valid = track.valid
    known = valid & np.isfinite(track.alt_m)
    n_valid = int(np.count_nonzero(valid))
    n_known = int(np.count_nonzero(known))
    missing = n_valid - n_known
    if n_known == 0 or missing == 0:
        return track
    notes = list(track.notes)
    share = missing / n_valid
    if share > MAX_MISSING_FRACTION or n_known < 2:
        notes.append(
            f"{missing} of {n_valid} fixes ({share:.1%}) have no height: the log's heights are"
            f" not used (at most {MAX_MISSING_FRACTION:.0%} missing are interpolated)"
        )
        return replace(track, alt_m=np.full(len(track), math.nan), notes=tuple(notes))
    notes.append(
        f"{missing} of {n_valid} fixes ({share:.1%}) have no height: interpolated from their"
        " neighbours'"
    )
    alt_m = track.alt_m.copy()
    fill = valid & ~known
    alt_m[fill] = np.interp(track.t_s[fill], track.t_s[known], track.alt_m[known])
    return replace(track, alt_m=alt_m, notes=tuple(notes))


MAX_PIPE_BYTES = 1 << 30
"""Most a log that is not a regular file (a pipe, ``<(zcat log.gz)``, a FIFO) may hold: it
is copied to a temporary file first, as it can be read only once (beyond, a clear error:
save it to a file; ``/dev/zero`` would fill the disk)."""


def _read_any(path: str | Path) -> Track:
    log_path = Path(path)
    if not_regular(log_path) is not None:  # a missing file: _read_file names it
        return _read_pipe(log_path)
    return _read_file(log_path)


def _read_pipe(log_path: Path) -> Track:
    """A log that can be read only once (the sniffing below reads a file twice: on a pipe
    that lost its first 64 KB), through a temporary copy; messages name ``log_path``."""
    try:
        tmp_dir = tempfile.TemporaryDirectory(prefix="x6wd-gap-")
    except OSError as exc:
        raise _copy_failed(log_path, tempfile.gettempdir(), exc) from exc
    with tmp_dir as tmp:
        copy = Path(tmp) / (log_path.name or "log")
        try:
            src = open(log_path, "rb")  # noqa: SIM115 (closed below; its open's errors only)
        except OSError as exc:
            raise DeviceUnavailable(f"cannot read {log_path}: {exc}") from exc
        with src:
            _copy_pipe(src, copy, log_path)
        try:
            return replace(_read_file(copy), source=str(log_path))
        except (ParseError, ConfigError, DeviceUnavailable) as exc:
            raise type(exc)(str(exc).replace(str(copy), str(log_path))) from exc


def _copy_pipe(src: Any, copy: Path, log_path: Path) -> None:
    """Copy ``src`` (the open pipe ``log_path``) into the file ``copy``, at most
    :data:`MAX_PIPE_BYTES`; the copy's errors (a full $TMPDIR) are DeviceUnavailable naming
    the temporary directory, not the pipe (reading it did not fail)."""
    try:
        with open(copy, "wb", buffering=0) as dst:  # unbuffered: no flush to fail at close
            n = 0
            while True:
                try:
                    chunk = src.read(1 << 20)
                except OSError as exc:  # the pipe's own: not an OSError past here
                    raise DeviceUnavailable(f"cannot read {log_path}: {exc}") from exc
                if not chunk:
                    return
                n += len(chunk)
                if n > MAX_PIPE_BYTES:
                    raise ParseError(
                        f"{log_path}: not a regular file and longer than "
                        f"{MAX_PIPE_BYTES >> 20} MiB: save it to a file first"
                    )
                view = memoryview(chunk)
                while view:  # a raw write may take part of it
                    view = view[dst.write(view) or 0 :]
    except OSError as exc:
        raise _copy_failed(log_path, copy.parent.parent, exc) from exc


def _copy_failed(log_path: Path, tmp_dir: str | Path, exc: OSError) -> DeviceUnavailable:
    """The error of a pipe's temporary copy that could not be made in ``tmp_dir``."""
    return DeviceUnavailable(
        f"{log_path}: not a regular file, so it is copied to a temporary file first, and that"
        f" copy could not be written in {tmp_dir}: {exc.strerror or exc} (free room there, or"
        " set TMPDIR to a directory with room)"
    )


def _read_file(log_path: Path) -> Track:
    source = str(log_path)
    try:
        with open(log_path, "rb") as f:
            head = f.read(_SNIFF_BYTES)
    except OSError as exc:
        raise DeviceUnavailable(f"cannot read {log_path}: {exc}") from exc
    kind = compression_of(head)
    if kind is not None:
        raise ParseError(f"{source}: compressed ({kind}): decompress it first")
    start = head.lstrip()[:1]
    if not start:
        raise ParseError(f"{source}: empty file" if not head else f"{source}: only blank lines")
    if start == b"{":
        if _NMEA_LINE_CHECKED.search(head):
            # gpspipe -r: gpsd's JSON preamble, then the NMEA (an x6wd recording's lines
            # all start with "{"; its NMEA is inside them); the framer skips the JSON
            return _read_nmea(log_path)
        return _read_recording(log_path)
    if log_path.suffix.lower() == ".pos" or start == b"%":
        return _read_pos(log_path)
    if (
        start == b"$"
        or _NMEA_HEAD.search(head)
        or _NMEA_LINE.search(head)
        or not _looks_like_text(head)
    ):
        # Binary (UBX, RTCM...) goes to the NMEA framer too: it skips what is not NMEA and
        # its counters say what was there when no position is found.
        return _read_nmea(log_path)
    return _read_csv(log_path)


def _looks_like_text(head: bytes) -> bool:
    """No NUL and at most 1 % other control bytes (binary protocols are full of them)."""
    control = len(head.translate(None, bytes(_TEXT_BYTES)))
    return b"\0" not in head and control <= 0.01 * len(head)


def _chunks(path: Path) -> Iterator[bytes]:
    """The file's bytes in chunks of _CHUNK_BYTES (a log is never held whole)."""
    with open(path, "rb") as f:
        while chunk := f.read(_CHUNK_BYTES):
            yield chunk


def _text_lines(path: Path) -> Iterator[tuple[int, str]]:
    """(line number from 1, text without its line ending) of a text log, UTF-8 with
    replacement; ParseError at a line longer than MAX_LINE_BYTES."""
    rest = b""
    lineno = 0
    for chunk in _chunks(path):
        lines = (rest + chunk).split(b"\n")
        rest = lines.pop()
        for line in lines:
            lineno += 1
            yield lineno, _line_text(line, path, lineno)
        if len(rest) > MAX_LINE_BYTES:
            _line_text(rest, path, lineno + 1)
    if rest:
        yield lineno + 1, _line_text(rest, path, lineno + 1)


def _line_text(line: bytes, path: Path, lineno: int) -> str:
    if len(line) > MAX_LINE_BYTES:
        raise ParseError(
            f"{path}:{lineno}: line longer than {MAX_LINE_BYTES} bytes: not a CSV or .pos log"
        )
    text = line.decode("utf-8", "replace").rstrip("\r")
    return text.removeprefix("\ufeff") if lineno == 1 else text  # Excel's byte-order mark


def _utc_s(utc: object) -> float | None:
    """Epoch seconds of a datetime or ISO text (naive means UTC), None if absent or bad."""
    if isinstance(utc, str) and utc:
        try:
            utc = datetime.fromisoformat(utc.replace("Z", "+00:00"))
        except ValueError:
            return None
    if isinstance(utc, datetime):
        return (utc if utc.tzinfo is not None else utc.replace(tzinfo=UTC)).timestamp()
    return None


def _fix_row(fix: object, t_s: float) -> tuple[float, ...]:
    """(t s, lat deg, lon deg, alt m, valid 0/1, satellites used (-1 unknown), speed m/s,
    course deg) of a GpsFix or a dict with the same fields, at time ``t_s``."""
    get = fix.get if isinstance(fix, dict) else (lambda k, d=None: getattr(fix, k, d))
    lat_deg, lon_deg, alt_m = get("lat_deg"), get("lon_deg"), get("alt_m")
    valid = bool(get("valid", False)) and lat_deg is not None and lon_deg is not None
    sats_used = get("sats_used")
    speed_mps, course_deg = get("speed_mps"), get("course_deg")
    return (
        float(t_s),
        float(lat_deg) if lat_deg is not None else math.nan,
        float(lon_deg) if lon_deg is not None else math.nan,
        float(alt_m) if alt_m is not None else math.nan,
        1.0 if valid else 0.0,
        float(sats_used) if sats_used is not None else -1.0,
        float(speed_mps) if speed_mps is not None else math.nan,
        float(course_deg) if course_deg is not None else math.nan,
    )


def _decoded_fixes(
    decoder: Any, feed: Iterable[tuple[float, bytes]], skies: dict[float, float] | None = None
) -> Iterator[Any]:
    """The GpsFix records ``decoder`` makes of ``feed`` ((receive time s, bytes) pairs);
    ``skies``, when given, receives each sky's UTC (s) -> the identity of the satellites
    its GSA lists as used."""
    from x6wd.core.records import GpsFix, GpsSky

    def records() -> Iterator[Any]:
        for t_s, data in feed:
            yield from decoder.feed(data, t_s)
        yield from decoder.flush()

    for r in records():
        if type(r) is GpsFix:
            yield r
        elif skies is not None and type(r) is GpsSky:
            utc = _utc_s(r.utc)
            used = [sat.prn for sat in r.satellites if sat.used]
            if utc is not None and used:
                skies[utc] = satellite_set_id(used)


def _with_sets(
    rows: list[tuple[float, ...]], utc_s: Sequence[float | None], skies: dict[float, float]
) -> list[tuple[float, ...]]:
    """Fix rows with the identity of the satellites used at their UTC (s; None or NaN:
    undated) appended, -1 where no sky of that time lists them; unchanged when no sky does."""
    if not skies:
        return rows
    return [
        (*row, -1.0 if utc is None or not math.isfinite(utc) else skies.get(utc, -1.0))
        for row, utc in zip(rows, utc_s, strict=True)
    ]


_SENTENCE_ADDRESS = re.compile(rb"[$!]([A-Z][A-Z0-9]{1,5})[,*]")
_TYPES_SHOWN = 6


def _sentence_types(feed: Any) -> str:
    """ " (GSA 600, GSV 600)": the most frequent sentence types in ``feed()`` (the talker
    dropped: GPGSV and GNGSV are both GSV; proprietary addresses whole), for the error that
    names what a log without positions holds (a receiver set to satellites only)."""
    tally: dict[str, int] = {}
    for _t_s, data in feed():
        for m in _SENTENCE_ADDRESS.finditer(data):
            a = m.group(1).decode("ascii")
            kind = a[2:] if len(a) == 5 and a[0] != "P" else a
            tally[kind] = tally.get(kind, 0) + 1
    top = sorted(tally.items(), key=lambda kv: (-kv[1], kv[0]))
    more = f", {len(top) - _TYPES_SHOWN} more types" if len(top) > _TYPES_SHOWN else ""
    shown = ", ".join(f"{k} {n}" for k, n in top[:_TYPES_SHOWN])
    return f" ({shown}{more})" if top else ""


def _chained_decoder() -> Any:
    """A GpsDecoder whose epochs without a date of their own (GGA, between RMC dates) are
    dated from the epoch before them, not from the last dated sentence: the time of day
    rises, and falling back by over 12 h is the next day. Dated from the last RMC alone, a
    GGA-only log with one RMC at 02:00 that runs 20 h put every epoch after 14:00 on the
    day before (28,801 epochs went back in time). A sentence with a date still sets it."""
    from drivers.gps_nmea import GpsDecoder

    class ChainedDecoder(GpsDecoder):
        # a GLL- or GNS-only log is read by _gll_gns_track, which dates each position from
        # the epoch before it (its notes say how): the decoder's GLL fixes would bypass it
        gll_fixes = False
        # the UTCs the decoder gave leap seconds (23:59:60 as 23:59:59.999999: datetime cannot
        # hold it), to be left out: 1 us before the next epoch, no time axis can hold both
        leap_utc: set[datetime]
        # before any date: the first undated epoch's time of day (us) and how far (us) the
        # time of day has advanced since, a fall of over 12 h counting as midnight passed
        undated_first_tod: int | None
        undated_elapsed_us: int
        _undated_last_tod: int | None

        def _fix_head(self, gga: Any, rmc: Any) -> Any:
            head = super()._fix_head(gga, rmc)
            tod = head[1]
            if self._date is None and tod is not None and tod < 86_400_000_000:
                self._advance_undated(tod)
            return head

        def _advance_undated(self, tod: int) -> None:
            last = self._undated_last_tod
            if last is None:
                self.undated_first_tod = tod
            else:
                step = tod - last  # into [-12 h, 12 h): a day's wrap is midnight passing
                self.undated_elapsed_us += (step + 43_200_000_000) % 86_400_000_000 - 43_200_000_000
            self._undated_last_tod = tod

        def _utc_compute(self, tod: int, day: Any, date_tod_us: int) -> datetime:
            utc: datetime = super()._utc_compute(tod, day, date_tod_us)
            if tod < 86_400_000_000:  # a leap second (23:59:60) moves no date
                self._date, self._date_tod_us = utc.date(), tod
            else:
                self.leap_utc.add(utc)
            return utc

    # NMEA lines without '*hh' are read as gpsd reads them (a log written without checksums)
    decoder = ChainedDecoder(emit_sentences=False, accept_unchecksummed=True)
    decoder.leap_utc = set()
    decoder.undated_first_tod = decoder._undated_last_tod = None
    decoder.undated_elapsed_us = 0
    return decoder


def _first_undated_utc(probe: Any, first: datetime) -> datetime:
    """The UTC of a log's first epoch from its first dated epoch's UTC ``first``: the time of
    day of the undated epochs before it (``probe``: the chained decoder that read up to it)
    accumulated back from ``first``, a fall of over 12 h counting as midnight passed. Dated
    from ``first`` alone (within 12 h either side), a GGA-only log from 10:00 to 23:00 put
    every epoch before 11:00 on the next day."""
    if probe.undated_first_tod is None:
        return first
    tod_us = (first.hour * 3600 + first.minute * 60 + first.second) * 1_000_000 + first.microsecond
    probe._advance_undated(tod_us)  # the step from the last undated epoch to the first dated
    return first - timedelta(microseconds=probe.undated_elapsed_us)


def _nmea_track(feed: Any, source: str, *, receive_clock: bool, notes: Iterable[str] = ()) -> Track:
    """Decode the NMEA of ``feed()`` (an iterable of (receive time s, bytes), read twice).

    The time axis is UTC from dated sentences: a first pass finds the first dated epoch,
    and the second pass dates the epochs before it from it (GpsDecoder.assume_date).
    Epochs without a time are dropped and counted. Without any date, the receive times
    are used when they are a clock (``receive_clock``, a recording), else ParseError.
    """
    probe = _chained_decoder()
    first: datetime | None = None
    n_fixes = 0
    for fix in _decoded_fixes(probe, feed()):
        n_fixes += 1
        if fix.utc is not None:
            first = fix.utc
            break
    corrupt_text = _bad_text(probe.counters).rstrip(", ")
    corrupt_hint = (
        f"; NMEA sentences skipped as corrupt: {corrupt_text} (the log's GGA and RMC"
        " sentences may be among them: are they cut or altered on the way?)"
        if corrupt_text and first is None
        else ""
    )
    if n_fixes == 0:
        # GGA and RMC are what the daemon's decoder makes fixes of; a receiver set to send
        # only GLL or GNS positions is read here instead (GLL/GNS with ZDA or RMC dates)
        try:
            fallback = _gll_gns_track(feed, source, receive_clock=receive_clock, notes=notes)
        except ParseError as exc:
            raise ParseError(f"{exc}{corrupt_hint}") from None
        if fallback is not None:
            if corrupt_text:
                note = _corrupt_note(probe.counters)
                return replace(fallback, notes=(*fallback.notes, note))
            return fallback
    if first is None and not receive_clock:
        counts = probe.counters
        if n_fixes == 0:
            found = _sentence_types(feed) if counts.sentences else ""
            raise ParseError(
                f"{source}: no NMEA position sentence (GGA, RMC, GLL or GNS) decoded"
                f" ({counts.sentences} NMEA sentences{found}, {_bad_text(counts)}"
                f"{counts.ubx_frames} UBX frames, {counts.skipped_bytes} other bytes): the gap"
                " tool reads NMEA, x6wd recordings, CSV and RTKLIB .pos"
            )
        raise ParseError(
            f"{source}: no dated sentence: {n_fixes} position epochs but no RMC with a date"
            f" and no ZDA, so no UTC time axis (the gap tool does not guess a date){corrupt_hint}"
        )
    decoder = _chained_decoder()
    if first is not None:
        # the first epoch's UTC: each later undated one is dated from the one before it
        decoder.assume_utc(_first_undated_utc(probe, first))
    rows: list[tuple[float, ...]] = []
    timeless = 0
    skies: dict[float, float] = {}  # UTC s -> the set the epoch's GSA lists as used
    fix_utc: list[float | None] = []
    leap = 0
    timeless_after: list[float] = []  # per epoch without a time: the time of the one before
    for fix in _decoded_fixes(decoder, feed(), skies):
        if first is not None and fix.utc in decoder.leap_utc:
            leap += 1
            continue
        t_s = fix.t_s if first is None else _utc_s(fix.utc)
        if t_s is None:
            timeless += 1
            if rows:  # the receiver was sending: a hole around it is its own (an outage)
                timeless_after.append(rows[-1][0])
        else:
            rows.append(_fix_row(fix, t_s))
            fix_utc.append(_utc_s(fix.utc))
    rows, fix_utc, unset_after, unset = drop_clock_excursions(rows, fix_utc)
    timeless_after += unset_after
    rows, fix_utc, merged = _merge_split_stamps(rows, fix_utc)
    rows = _with_sets(rows, fix_utc, skies)
    notes = list(notes)
    if unset:
        notes.append(unset)
    if merged:
        notes.append(merged)
    corrupt = _corrupt_note(decoder.counters)
    if corrupt:
        notes.append(corrupt)
    if unchecked := decoder.counters.unchecksummed:
        notes.append(
            f"{unchecked} NMEA sentences without a checksum ('*hh') read as they are, as gpsd"
            " reads them (a log written without checksums)"
        )
    if timeless:
        notes.append(
            f"{timeless} epochs without a time (e.g. no-fix GGA with empty fields) dropped"
        )
    if leap:
        notes.append(
            f"{leap} leap-second epoch{'s' if leap != 1 else ''} (23:59:60 UTC) left out (a UTC"
            " time axis has no place for it)"
        )
    if first is None:
        notes.append("no dated NMEA sentence: the recording's receive clock is the time axis")
    return cut_silent_holes(_track(rows, source, notes), timeless_after)


CLOCK_EXCURSION_S = 600.0
"""A step of an NMEA log's time of over this between successive epochs, out and back again,
is the receiver's clock, not the log: a receiver restarted without its time (cold, no backup
battery) dates its sentences 1980-01-06, its firmware's build date or a rolled-over week, or
counts the time of day from 00:00, until it has decoded the time. Such a stretch is dropped
(:func:`drop_clock_excursions`)."""

CLOCK_RETURN_MAX_S = 3600.0
"""Most (s) the log's time may have moved on across a clock excursion: the receiver off
(a receiver without a backup battery loses its clock so) and restarting. The whole hole is
then read as its outage, the silence before the restart too."""


def drop_clock_excursions(
    rows: list[tuple[float, ...]], fix_utc: list[float | None]
) -> tuple[list[tuple[float, ...]], list[float | None], list[float], str]:
    """``rows`` (time s first, in log order) without their clock excursions: stretches
    without a fix, entered by a step of over :data:`CLOCK_EXCURSION_S` and left by one back
    to the log's own time, later than the epoch before the stretch by no more than
    :data:`CLOCK_RETURN_MAX_S`. Returns the kept rows and their ``fix_utc``; for each epoch
    the hole misses (at least each dropped row) the time (s) of the kept epoch before it
    (the receiver was on: :func:`cut_silent_holes` reads the hole as its outage); and a
    note ("" when none). Sorted, such epochs went to the log's far end, and the hole they
    left was read as the logger's: half a log was dropped."""
    t_s = np.fromiter((r[0] for r in rows), dtype=float, count=len(rows))
    if t_s.size < 3:
        return rows, fix_utc, [], ""
    steps_s = np.diff(t_s)
    jumps = np.flatnonzero(np.abs(steps_s) > CLOCK_EXCURSION_S) + 1
    if jumps.size < 2:
        return rows, fix_utc, [], ""
    forward = steps_s[steps_s > 0]
    dt_s = float(np.median(forward)) if forward.size else 1.0
    drop = np.zeros(t_s.size, dtype=bool)
    after: list[float] = []
    far: list[float] = []
    k = 0
    while k < jumps.size:
        start = int(jumps[k])
        before_s = t_s[start - 1]
        # ... and never a fix: a receiver with a fix knows the time (a session of fixes
        # out of order is the log's, sorted as before)
        first_fix = next((i for i in range(start, t_s.size) if rows[i][4] > 0), t_s.size)
        back = next(
            (
                m
                for m in range(k + 1, jumps.size)
                if jumps[m] <= first_fix and 0.0 <= t_s[jumps[m]] - before_s <= CLOCK_RETURN_MAX_S
            ),
            None,
        )
        if back is None:
            k += 1
            continue
        end = int(jumps[back])
        drop[start:end] = True
        # the receiver was on across the whole hole, as far as the log can tell: as many
        # "sent" epochs as the hole misses (cut_silent_holes), at least the stretch's own
        missing = round(float(t_s[end] - before_s) / dt_s) if dt_s > 0 else 0
        after += [float(before_s)] * max(end - start, missing)
        far += [float(t_s[start:end].min()), float(t_s[start:end].max())]
        k = back + 1  # the step back may also start the next stretch
    if not drop.any():
        return rows, fix_utc, [], ""
    keep = np.flatnonzero(~drop)
    note = (
        f"{int(drop.sum())} epochs dated away from the log's own time ({_utc_text(min(far))} to"
        f" {_utc_text(max(far))}) between epochs of it dropped: a receiver restarted without"
        " its clock (cold, no backup battery) dates its sentences so until it has decoded"
        " the time; the hole they leave is read as its outage"
    )
    return [rows[i] for i in keep], [fix_utc[i] for i in keep], after, note


SPLIT_STAMP_MAX_S = 0.25
"""Most (s) by which an RMC's and a GGA's time stamps of one fix may differ (a receiver or
logger stamping each sentence as it goes out): such rows are one epoch
(:func:`_merge_split_stamps`)."""
SPLIT_STAMP_SAME_DEG = 1e-6
"""Positions (deg, ~0.1 m) within which an RMC's and a GGA's fixes are the same fix."""


def _merge_split_stamps(
    rows: list[tuple[float, ...]], fix_utc: list[float | None]
) -> tuple[list[tuple[float, ...]], list[float | None], str]:
    """Rows (log order) with each fix whose RMC and GGA carry time stamps a little apart
    (at most :data:`SPLIT_STAMP_MAX_S`, the same position and fix state; one row with speed
    and no satellite count or height, the other without speed) made one epoch, at the earlier
    stamp; and a note ("" when none). Decoded as two epochs, a 1 Hz log whose GGA is stamped
    50 ms after its RMC read as a 20 Hz log with 19 of every 20 epochs missing (filled as
    outages). The other ``fix_utc`` of a merged pair is dropped with it."""

    def rmc_only(r: tuple[float, ...]) -> bool:
        return math.isfinite(r[6]) and r[5] < 0 and math.isnan(r[3])

    def gga_only(r: tuple[float, ...]) -> bool:
        return math.isnan(r[6]) and math.isnan(r[7])

    def same_fix(a: tuple[float, ...], b: tuple[float, ...]) -> bool:
        if a[4] != b[4]:
            return False
        return all(
            (math.isnan(x) and math.isnan(y)) or abs(x - y) <= SPLIT_STAMP_SAME_DEG
            for x, y in ((a[1], b[1]), (a[2], b[2]))
        )

    out: list[tuple[float, ...]] = []
    out_utc: list[float | None] = []
    merged = 0
    largest_s = 0.0
    i = 0
    while i < len(rows):
        a = rows[i]
        if i + 1 < len(rows):
            b = rows[i + 1]
            dt_s = b[0] - a[0]
            pair = (rmc_only(a) and gga_only(b)) or (gga_only(a) and rmc_only(b))
            if 0.0 < dt_s <= SPLIT_STAMP_MAX_S and pair and same_fix(a, b):
                gga, rmc = (b, a) if rmc_only(a) else (a, b)
                out.append((a[0], *gga[1:6], *rmc[6:8]))
                out_utc.append(fix_utc[i])
                merged += 1
                largest_s = max(largest_s, dt_s)
                i += 2
                continue
        out.append(a)
        out_utc.append(fix_utc[i])
        i += 1
    if not merged:
        return rows, fix_utc, ""
    note = (
        f"{merged} fixes whose RMC and GGA are stamped up to {largest_s:.3g} s apart (the same"
        " position) each read as one epoch, at the earlier stamp"
    )
    return out, out_utc, note


MAX_SILENT_HOLE_STEPS = 5
MAX_SILENT_HOLE_S = 5.0
"""A hole in an NMEA log's time axis with no sentence at all (no epoch, timed or not) of more
than MAX_SILENT_HOLE_STEPS missing epochs and more than MAX_SILENT_HOLE_S seconds is not a
receiver's outage (a receiver without a fix still sends its no-fix sentences): the logger
was off, lost the port, or two sessions were joined (:func:`cut_silent_holes`). Shorter ones
(a few lines lost) are filled as no-fix epochs, as in any log."""


def cut_silent_holes(track: Track, timeless_after_s: Sequence[float] = ()) -> Track:
    """An NMEA ``track`` cut at its long holes with no sentence (:data:`MAX_SILENT_HOLE_STEPS`),
    the part with the most epochs kept and a note saying so; unchanged without one.
    ``timeless_after_s``: per epoch without a time (a no-fix GGA with empty fields), the time
    (s) of the timed epoch before it: a hole holding such epochs for at least half of its
    missing steps is the receiver's outage (it was sending), not cut."""
    t_s = track.t_s
    if t_s.size < 3:
        return track
    steps_s = np.diff(t_s)
    dt_s = float(np.median(steps_s))
    if dt_s <= 0:
        return track
    missing = np.round(steps_s / dt_s) - 1.0
    long = (missing > MAX_SILENT_HOLE_STEPS) & (steps_s > MAX_SILENT_HOLE_S)
    if not np.any(long):
        return track
    at = np.flatnonzero(long)
    # epochs without a time that the receiver sent in each long hole (after its first epoch)
    sent = np.searchsorted(np.sort(np.asarray(timeless_after_s, dtype=float)), t_s, "left")
    in_hole = sent[at + 1] - sent[at]
    silent = at[in_hole < missing[at] / 2.0]
    if not silent.size:
        return track
    bounds = np.concatenate(([0], silent + 1, [t_s.size]))
    sizes = np.diff(bounds)
    k = int(np.argmax(sizes))
    lo, hi = int(bounds[k]), int(bounds[k + 1])
    longest_s = float(np.max(steps_s[silent]))
    note = (
        f"time axis cut at {silent.size} hole(s) with no NMEA sentence at all (the longest"
        f" {_duration_text(longest_s)}, over {MAX_SILENT_HOLE_STEPS} epochs of {dt_s:g} s): a"
        " receiver without a fix still sends its no-fix sentences, so such a hole is the"
        " logger's (switched off, the port lost, sessions joined), not an outage:"
        f" {hi - lo} of {t_s.size} epochs kept, {_utc_text(t_s[lo])} to {_utc_text(t_s[hi - 1])}"
    )
    cut = {
        f.name: getattr(track, f.name)[lo:hi]
        for f in dataclass_fields(track)
        if isinstance(getattr(track, f.name), np.ndarray)
    }
    return replace(track, **cut, notes=(*track.notes, note))


def _bad_text(counts: Any) -> str:
    """The corrupt sentences of a decoder's counters as text for a message ("" when none)."""
    parts = []
    if counts.checksum_failures:
        parts.append(f"{counts.checksum_failures} with a bad checksum")
    if counts.framing_errors:
        parts.append(
            f"{counts.framing_errors} malformed (too long, cut short or without a checksum)"
        )
    return "".join(f"{part}, " for part in parts)


def _corrupt_note(counts: Any) -> str:
    """A note on the NMEA sentences the decoder skipped as corrupt ("" when none)."""
    bad = _bad_text(counts).rstrip(", ")
    if not bad:
        return ""
    return f"corrupt NMEA sentences skipped: {bad} (their fixes, if any, are missing)"


_LEAP_TIME = re.compile(r"^\s*235960(?:\.\d*)?\s*$")  # hhmmss[.ss] of a leap second
_GLL_GNS = re.compile(r"\$(?:[A-Z]{2})(GLL|GNS|ZDA|RMC),[^*$]*\*[0-9A-Fa-f]{2}")


def _nmea_lines(feed: Any) -> Iterator[tuple[float, str]]:
    """(receive time s, sentence text) of the NMEA lines of ``feed()``, joined across its
    chunks; lines over MAX_LINE_BYTES are skipped (no NMEA sentence is that long)."""
    rest, rest_t = b"", 0.0
    for t_s, data in feed():
        lines = (rest + data).split(b"\n")
        rest, rest_t = lines.pop(), t_s
        if len(rest) > MAX_LINE_BYTES:
            rest = b""
        for line in lines:
            if len(line) <= MAX_LINE_BYTES:
                yield t_s, line.decode("ascii", "replace").strip()
    if rest:
        yield rest_t, rest.decode("ascii", "replace").strip()


def _gll_gns_track(
    feed: Any, source: str, *, receive_clock: bool, notes: Iterable[str]
) -> Track | None:
    """The positions of a log's GLL or GNS sentences (None when it has none with a valid
    checksum), dated by its ZDA or RMC dates; for logs without GGA or RMC positions.

    GLL and GNS carry the time of day only: each is dated from the epoch before it, or
    the last ZDA (or RMC) date when one came since (the first one for those before any), a
    day added when the time of day falls back by over 12 h (midnight). GLL gives no
    satellite count or height; GNS gives both (its count covers every constellation).
    Without any date a recording's receive times are used; a plain log is an error, as for
    GGA."""
    import pynmea2

    positions: list[tuple[float, str, Any]] = []  # (receive time, type, sentence)
    dates: list[tuple[int, datetime]] = []  # (index in positions, a dated time)
    for t_s, line in _nmea_lines(feed):
        match = _GLL_GNS.search(line)
        if match is None:
            continue
        try:
            msg = pynmea2.parse(match.group(0), check=True)
        except (pynmea2.ParseError, ValueError, TypeError, AttributeError):
            continue
        kind = match.group(1)
        try:
            if kind in ("GLL", "GNS"):
                positions.append((t_s, kind, msg))
            elif kind == "ZDA" and msg.datetime is not None:
                dates.append((len(positions), msg.datetime))
            elif kind == "RMC" and msg.datestamp is not None and msg.timestamp is not None:
                dates.append((len(positions), datetime.combine(msg.datestamp, msg.timestamp)))
        except (ValueError, TypeError, AttributeError):
            continue
    if not positions:
        return None
    if not dates and not receive_clock:
        raise ParseError(
            f"{source}: no dated sentence: {len(positions)} GLL/GNS positions but no RMC with"
            " a date and no ZDA, so no UTC time axis (the gap tool does not guess a date)"
        )
    rows: list[tuple[float, ...]] = []
    timeless = leap = 0
    timeless_after: list[float] = []  # per epoch without a time: the time of the one before
    next_date = 0
    day: datetime | None = _gll_gns_start(positions, dates) if dates else None
    for i, (t_s, kind, msg) in enumerate(positions):
        while next_date < len(dates) and dates[next_date][0] <= i:
            day = dates[next_date][1]
            next_date += 1
        row = _gll_gns_row(kind, msg)
        if day is None:
            rows.append((t_s, *row))
            continue
        stamp = getattr(msg, "timestamp", None)
        if not isinstance(stamp, dt_time):
            # pynmea2 gives the raw text of a time it cannot parse: 23:59:60 is a leap
            # second (left out, as the GGA path leaves it), anything else no time
            if isinstance(stamp, str) and _LEAP_TIME.match(stamp):
                leap += 1
            else:
                timeless += 1
                if rows:  # the receiver was sending (cut_silent_holes)
                    timeless_after.append(rows[-1][0])
            continue
        at = datetime.combine(day.date(), stamp).replace(tzinfo=UTC)
        when = at.timestamp()
        ref_s = day.replace(tzinfo=day.tzinfo or UTC).timestamp()
        if when < ref_s - 43_200.0:
            when += 86_400.0  # past midnight since the date
        elif when > ref_s + 43_200.0:
            when -= 86_400.0
        rows.append((when, *row))
        day = datetime.fromtimestamp(when, UTC)  # the next is dated from this epoch
    rows, _, unset_after, unset = drop_clock_excursions(rows, [None] * len(rows))
    timeless_after += unset_after
    kinds = sorted({kind for _, kind, _ in positions})
    read_notes = [
        *notes,
        *([unset] if unset else []),
        f"positions read from {' and '.join(kinds)} sentences (the log has no GGA or RMC"
        " position)" + ("; GLL gives no satellite count or height" if "GLL" in kinds else ""),
    ]
    if timeless:
        read_notes.append(f"{timeless} epochs without a (valid) time dropped")
    if leap:
        read_notes.append(
            f"{leap} leap-second epoch{'s' if leap != 1 else ''} (23:59:60 UTC) left out (a UTC"
            " time axis has no place for it)"
        )
    if not dates:
        read_notes.append("no dated NMEA sentence: the recording's receive clock is the time axis")
    return cut_silent_holes(_track(rows, source, read_notes), timeless_after)


def _gll_gns_start(
    positions: list[tuple[float, str, Any]], dates: list[tuple[int, datetime]]
) -> datetime:
    """The reference UTC the GLL/GNS positions before the first date are dated from: that
    date less how far the time of day advanced over them (a fall of over 12 h is midnight
    passed), so that positions more than 12 h before it are not put on the next day."""
    first_at, first = dates[0]
    seconds = [
        t.hour * 3600.0 + t.minute * 60.0 + t.second + t.microsecond / 1e6
        for _, _, msg in positions[:first_at]
        if isinstance(t := getattr(msg, "timestamp", None), dt_time)
    ]
    if not seconds:
        return first
    seconds.append(
        first.hour * 3600.0 + first.minute * 60.0 + first.second + first.microsecond / 1e6
    )
    steps = (np.diff(seconds) + 43_200.0) % 86_400.0 - 43_200.0
    return first - timedelta(seconds=float(np.sum(steps)))


def _gll_gns_row(kind: str, msg: Any) -> tuple[float, ...]:
    """(lat, lon, alt, valid, satellites used, speed, course) of a GLL or GNS sentence."""

    def number(text: object) -> float:
        try:
            return float(str(text))
        except ValueError:
            return math.nan

    try:
        lat_deg, lon_deg = float(msg.latitude), float(msg.longitude)
    except (ValueError, TypeError, AttributeError):
        lat_deg = lon_deg = math.nan
    has_position = bool(getattr(msg, "lat", "")) and bool(getattr(msg, "lon", ""))
    if kind == "GLL":
        mode = str(getattr(msg, "faa_mode", "") or "")
        valid = has_position and msg.status == "A" and mode[:1] != "N"
        return (lat_deg, lon_deg, math.nan, float(valid), -1.0, math.nan, math.nan)
    mode = str(getattr(msg, "mode_indicator", "") or "")
    valid = has_position and any(c not in "N" for c in mode) and mode != ""
    nsats = number(msg.num_sats)
    return (
        lat_deg,
        lon_deg,
        number(msg.altitude),
        float(valid),
        nsats if math.isfinite(nsats) else -1.0,
        math.nan,
        math.nan,
    )


def _read_nmea(path: Path) -> Track:
    return _nmea_track(
        lambda: ((0.0, chunk) for chunk in _chunks(path)), str(path), receive_clock=False
    )


def _read_recording(path: Path) -> Track:
    """``fix`` records (their UTC when any has one, else their receive time ``t_mono`` for
    all), else the ``nmea`` records decoded (see _nmea_track)."""
    from x6wd.core.recorder import ReadStats, read_recording

    rows: list[tuple[float, ...]] = []
    utc_s: list[float] = []
    skies: dict[float, float] = {}  # UTC s -> the identity of the satellites used
    has_nmea = False
    malformed = 0  # records whose fields have the wrong type (a hand-edited or foreign file)
    stats = ReadStats()
    for rec in read_recording(path, stats=stats):
        try:
            if rec.type == "fix":
                t_s = rec.data.get("t_s", rec.t_mono)
                row = _fix_row(rec.data, t_s if isinstance(t_s, (int, float)) else math.nan)
                utc = _utc_s(rec.data.get("utc"))
                rows.append(row)
                utc_s.append(math.nan if utc is None else utc)
            elif rec.type == "sky":
                utc = _utc_s(rec.data.get("utc"))
                sats = rec.data.get("satellites") or []
                used = [
                    x["prn"] for x in sats if isinstance(x, dict) and x.get("used") and "prn" in x
                ]
                if utc is not None and used:
                    skies[utc] = satellite_set_id(used)
            elif rec.type == "nmea":
                has_nmea = True
        except (TypeError, ValueError, AttributeError):
            malformed += 1
    skipped = malformed + stats.bad_lines + stats.truncated
    notes_read = [f"{skipped} recording lines or records not readable, skipped"] * bool(skipped)
    rows = _with_sets(rows, utc_s, skies)
    if rows:
        dated = np.isfinite(utc_s)
        if not np.any(dated):
            notes_read.append("no fix has a UTC time: receive times used")
            return _track(rows, str(path), notes_read)
        kept = [(t, *row[1:]) for t, row, ok in zip(utc_s, rows, dated, strict=True) if ok]
        notes = [f"{len(rows) - len(kept)} fixes without a UTC time dropped"] * (
            len(kept) < len(rows)
        )
        return _track(kept, str(path), notes_read + notes)
    if has_nmea:

        def feed() -> Iterator[tuple[float, bytes]]:
            for rec in read_recording(path):
                if rec.type == "nmea":
                    text = rec.data.get("text") or rec.data.get("sentence") or rec.data.get("line")
                    yield rec.t_mono, str(text or "").encode("ascii", "replace") + b"\r\n"

        return _nmea_track(feed, str(path), receive_clock=True)
    if is_gpsd_json(path):
        raise ParseError(gpsd_json_error(path, "the gap tool"))
    raise ParseError(f"{path}: recording has no fix or nmea records")


_CSV_NAMES = {
    "t": ("time", "t", "t_s", "timestamp", "utc", "epoch"),
    "lat": ("lat", "latitude", "lat_deg"),
    "lon": ("lon", "longitude", "lon_deg", "lng"),
    "alt": ("alt", "alt_m", "msl", "altitude", "height", "h"),
    # read only without one of the above: heights above the WGS-84 ellipsoid (mobile.csv's
    # WGS84 beside its MSL; RTKLIB's), tens of metres from those above sea level
    "ellipsoidal": ("wgs84", "hae", "ellipsoidal", "ellipsoid_height", "height_ellipsoid"),
    "valid": ("valid", "fix"),
    "nsats": ("nsats", "sats", "sats_used", "ns"),
}


def _read_csv(path: Path) -> Track:
    source = str(path)
    numbered = (
        (lineno, line)
        for lineno, line in _text_lines(path)
        if line.strip() and not line.startswith("#")
    )
    linenos: list[int] = []

    def lines() -> Iterator[str]:
        for lineno, line in numbered:
            linenos.append(lineno)
            yield line

    reader = csv.reader(lines())
    try:
        first = next(reader, None)
        if first is None:
            raise ParseError(f"{source}: empty CSV")
        header = [c.strip().strip('"').lower() for c in first]

        def col(key: str) -> int | None:
            for name in _CSV_NAMES[key]:
                if name in header:
                    return header.index(name)
            return None

        has_header = col("lat") is not None and col("lon") is not None
        notes = []
        if has_header:
            column = {k: col(k) for k in _CSV_NAMES}
            notes = [note for note in [_height_note(first, column)] if note]
            if column["alt"] is None:
                column["alt"] = column["ellipsoidal"]
            if column["t"] is None:
                raise ParseError(
                    f"{source}: CSV header has no time column (one of {', '.join(_CSV_NAMES['t'])})"
                )
            body: Iterable[list[str]] = reader
        else:
            column = {
                "t": 0,
                "lat": 1,
                "lon": 2,
                "alt": 3 if len(first) > 3 else None,
                "valid": None,
                "nsats": None,
            }
            body = _chain_row(first, reader)
        # A row with fewer fields than the header (headerless: than the first row, and at
        # least time,lat,lon) lost its end: a logger killed while writing leaves its last
        # line so, and its last field read may be cut inside a number (-105.09 of
        # -105.095171686): skipped and named, never filled with NaN as a fix.
        n_fields = len(first) if has_header else max(_MIN_CSV_FIELDS, len(first))
        open_last = _open_last_line(path)
        read = {i for i in column.values() if i is not None}
        if not has_header and len(first) < _MIN_CSV_FIELDS:
            _csv_row(first, column, source, linenos)  # a row not of numbers is named so
            raise _not_a_log(
                f"{source}:{linenos[-1]}", first, f"{len(first)} fields, time,lat,lon are 3"
            )
        rows, numeric, short = [], False, []
        cut_last = zoneless_first = ""
        zoneless = 0
        for row in body:
            lineno = linenos[-1]
            if len(row) < n_fields:
                short.append((lineno, len(row)))
                continue
            if lineno == open_last and len(row) - 1 in read:
                # every field there, but no line ending: the last one may be cut short
                field = _field_name(first, has_header, len(row) - 1)
                cut_last = (
                    f"line {lineno}, the last, has no line ending: a logger stopped while"
                    f" writing it may have cut its last field ({field}), which is read: skipped"
                )
                continue
            rows.append(_csv_row(row, column, source, linenos))
            stamp = row[column["t"]].strip().strip('"')  # type: ignore[index]
            if _is_number(stamp):
                numeric = True
            elif _without_zone(stamp):
                zoneless += 1
                zoneless_first = zoneless_first or stamp
    except csv.Error as exc:
        raise ParseError(f"{source}:{linenos[-1] if linenos else 1}: not CSV: {exc}") from exc
    skipped = [n for n in [_short_note(short, n_fields, has_header, open_last), cut_last] if n]
    if not rows and skipped:
        raise ParseError(f"{source}: no position epochs found: {'; '.join(skipped)}")
    notes += skipped
    if zoneless:
        notes.append(
            f"{zoneless} times without a time zone (the first {zoneless_first!r}) read as UTC:"
            " a log written in local time would be off by its zone's offset"
        )
    name = first[column["t"]].strip().strip('"') if has_header else "1 (no header)"  # type: ignore[index]
    return replace(_track(rows, source, notes), time_column=name if numeric else "")


_MIN_CSV_FIELDS = 3  # time, lat, lon


def _open_last_line(path: Path) -> int | None:
    """The number (from 1) of the file's last line when it has no line ending (a logger
    killed while writing it), else None."""
    with open(path, "rb") as f:
        f.seek(0, 2)
        size = f.tell()
        if size == 0:
            return None
        f.seek(size - 1)
        if f.read(1) == b"\n":
            return None
    return sum(chunk.count(b"\n") for chunk in _chunks(path)) + 1


def _field_name(first: list[str], has_header: bool, i: int) -> str:
    if has_header and i < len(first):
        return repr(first[i].strip().strip('"'))
    return f"field {i + 1}"


def _short_note(
    short: list[tuple[int, int]], n_fields: int, has_header: bool, open_last: int | None
) -> str:
    """The note naming the CSV rows skipped for having fewer fields than ``n_fields``."""
    if not short:
        return ""
    if len(short) == 1:
        lineno, n = short[0]
        last = "; the last line, without a line ending" if lineno == open_last else ""
        return f"line {lineno}: {n} of {n_fields} fields (cut off{last}): skipped"
    than = f"the header's {n_fields}" if has_header else f"the first row's {n_fields}"
    shown = ", ".join(f"line {lineno} ({n} of {n_fields})" for lineno, n in short[:5])
    more = f" and {len(short) - 5} more" if len(short) > 5 else ""
    return f"{len(short)} rows with fewer fields than {than} (cut off), skipped: {shown}{more}"


def _height_note(header: list[str], column: dict[str, int | None]) -> str:
    """Which column of a CSV the heights are read from, and in which height system: a
    --truth ALT is compared with them as they are."""

    def name(key: str) -> str:
        return repr(header[column[key]].strip().strip('"'))  # type: ignore[index]

    if column["alt"] is not None and column["ellipsoidal"] is not None:
        msl = " (above mean sea level, as NMEA's)" if name("alt").lower() == "'msl'" else ""
        return (
            f"heights from column {name('alt')}{msl}, not from {name('ellipsoidal')} (above the"
            " WGS-84 ellipsoid): a --truth ALT is compared with them"
        )
    if column["ellipsoidal"] is not None:
        return (
            f"heights from column {name('ellipsoidal')}, above the WGS-84 ellipsoid (as"
            " RTKLIB's): a --truth ALT is compared with them"
        )
    if column["alt"] is not None:
        return ""
    known = ", ".join(_CSV_NAMES["alt"] + _CSV_NAMES["ellipsoidal"])
    return f"no height column (one of {known}): heights not compared"


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def _without_zone(text: str) -> bool:
    """True for ISO 8601 text of a time without a zone (no Z, no offset)."""
    try:
        return datetime.fromisoformat(text.replace("Z", "+00:00")).tzinfo is None
    except ValueError:
        return False


def _chain_row(first: list[str], rest: Iterable[list[str]]) -> Iterator[list[str]]:
    yield first
    yield from rest


def _csv_row(
    raw: list[str], column: dict[str, int | None], source: str, linenos: list[int]
) -> tuple[float, ...]:
    row = [c.strip().strip('"') for c in raw]

    def get(key: str, default: float = math.nan) -> float:
        i = column[key]
        return float(row[i]) if i is not None and i < len(row) and row[i] != "" else default

    try:
        return (
            _parse_time(row[column["t"]]),  # type: ignore[index]
            get("lat"),
            get("lon"),
            get("alt"),
            get("valid", 1.0),
            get("nsats", -1.0),
            math.nan,
            math.nan,
        )
    except (ValueError, IndexError) as exc:
        where = f"{source}:{linenos[-1]}"
        if column["t"] == 0 and column["valid"] is None:  # no header: maybe no CSV at all
            raise _not_a_log(where, row, str(exc)) from exc
        raise ParseError(f"{where}: bad CSV row {_shown(row)}: {str(exc)[:80]}") from exc


def _shown(row: list[str]) -> str:
    shown = repr(row)
    return shown if len(shown) <= 80 else shown[:77] + "..."


def _not_a_log(where: str, row: list[str], why: str) -> ParseError:
    return ParseError(
        f"{where}: not a log the gap tool reads (NMEA, x6wd recording, CSV with a"
        f" time,lat,lon header or rows, RTKLIB .pos): row {_shown(row)}: {why[:80]}"
    )


def _parse_time(s: str) -> float:
    try:
        return float(s)
    except ValueError:
        t_s = _utc_s(s)
        if t_s is None:
            raise ValueError(f"time {s[:40]!r} is neither seconds nor ISO 8601") from None
        return t_s


# The column legend RTKLIB writes above its solutions: "%  GPST  latitude(deg) ...", the time
# system first (RTKLIB's outsolheads: GPST, UTC or JST; BJT in some forks).
_POS_LEGEND = re.compile(r"^%\s+(GPST|UTC|JST|BJT)\s")
_POS_ZONE_S = {"UTC": 0.0, "JST": 9 * 3600.0, "BJT": 8 * 3600.0}  # ahead of UTC
_GPS_EPOCH_S = 315_964_800.0  # 1980-01-06T00:00:00Z, where GPS week 0 starts


def _read_pos(path: Path) -> Track:
    """An RTKLIB solution file: its times (date and time, or GPS week and seconds) in the
    time system of its column legend, GPST when it has none (RTKLIB's default), turned into
    UTC (:func:`gpst_to_utc_s`) like every other log's."""
    source = str(path)
    rows: list[tuple[float, ...]] = []
    systems: list[str] = []
    system: str | None = None
    open_last = _open_last_line(path)
    n_fields = _POS_MIN_FIELDS  # the line before's (RTKLIB writes one layout per file)
    cut_notes: list[str] = []
    for lineno, line in _text_lines(path):
        if line.startswith("%"):
            legend = _POS_LEGEND.match(line)
            if legend:
                system = legend.group(1)
            continue
        if not line.strip():
            continue
        fields = line.split()
        if lineno == open_last and (len(fields) < n_fields or _pos_reads_last(len(fields))):
            # a logger (rtkrcv, rnx2rtkp) stopped while writing its last line: skipped, as a
            # CSV's; a malformed line before it still stops the reading
            cut_notes.append(
                f"line {lineno}: {len(fields)} of {n_fields} fields (cut off; the last line,"
                " without a line ending): skipped"
                if len(fields) < n_fields
                else f"line {lineno}, the last, has no line ending: a logger stopped while"
                f" writing it may have cut its last field (field {len(fields)}), which is"
                " read: skipped"
            )
            continue
        n_fields = len(fields)
        try:
            if "/" in fields[0]:
                t_s = (
                    datetime.strptime(fields[0] + " " + fields[1], "%Y/%m/%d %H:%M:%S.%f")
                    .replace(tzinfo=UTC)
                    .timestamp()
                )
            else:  # GPS week and seconds of the week (RTKLIB's "tow" time format)
                t_s = _GPS_EPOCH_S + int(fields[0]) * 604_800.0 + float(fields[1])
            lat_deg, lon_deg, height_m, quality, n_sats = (
                float(fields[2]),
                float(fields[3]),
                float(fields[4]),
                int(fields[5]),
                int(fields[6]),
            )
        except (ValueError, IndexError) as exc:
            if not_text(line):
                raise ParseError(
                    f"{source}:{lineno}: not an RTKLIB .pos file: this line is not text (a"
                    " binary file?)"
                ) from None
            raise ParseError(
                f"{source}:{lineno}: not an RTKLIB .pos line: {str(exc)[:80]}"
            ) from exc
        speed_mps = course_deg = math.nan
        if len(fields) >= 17:  # velocity columns vn, ve (m/s) present
            v_north_mps, v_east_mps = float(fields[15]), float(fields[16])
            speed_mps, course_deg = (
                math.hypot(v_north_mps, v_east_mps),
                math.degrees(math.atan2(v_east_mps, v_north_mps)) % 360.0,
            )
        rows.append(
            (
                t_s,
                lat_deg,
                lon_deg,
                height_m,
                1.0 if quality > 0 else 0.0,
                float(n_sats),
                speed_mps,
                course_deg,
            )
        )
        systems.append(system or "GPST")
    if not rows:
        if cut_notes:
            raise ParseError(f"{source}: no position epochs found: {cut_notes[0]}")
        return _track(rows, source)
    t_sys_s = np.array([row[0] for row in rows])
    system_of = np.array(systems)
    gpst = system_of == "GPST"
    t_utc_s = np.where(gpst, gpst_to_utc_s(t_sys_s), t_sys_s)
    for zone, ahead_s in _POS_ZONE_S.items():
        t_utc_s = np.where(system_of == zone, t_sys_s - ahead_s, t_utc_s)
    notes = []
    if np.any(gpst):
        leap_s = t_sys_s[gpst] - t_utc_s[gpst]
        spread = f"{np.min(leap_s):.0f}" + (
            f" to {np.max(leap_s):.0f}" if np.max(leap_s) != np.min(leap_s) else ""
        )
        said = "" if system else " (the header names no time system: RTKLIB's default taken)"
        notes.append(
            f"RTKLIB times in GPST{said}: taken to UTC by the GPS-UTC leap seconds then"
            f" ({spread} s), as the other logs' times are UTC"
        )
    for zone in ("JST", "BJT"):
        if np.any(system_of == zone):
            notes.append(f"RTKLIB times in {zone}: taken to UTC")
    rows = [(float(t), *row[1:]) for t, row in zip(t_utc_s, rows, strict=True)]
    return _track(rows, source, notes + cut_notes)


# An RTKLIB position line: date time (or week tow), lat lon height Q ns, six sd, age ratio
_POS_MIN_FIELDS = 15


def _pos_reads_last(n_fields: int) -> bool:
    """Whether a .pos line of ``n_fields`` fields ends in a field the reader uses (fields
    1-7, and the velocities vn ve, fields 16-17, of a line of 17 or more)."""
    return n_fields <= 7 or n_fields == 17


def gpst_to_utc_s(t_s: np.ndarray) -> np.ndarray:
    """GPST dates and times read as if they were UTC (epoch s) -> UTC epoch seconds: less
    the GPS-UTC leap seconds in force then (:func:`sim_backend.geodesy.leap_seconds`, 18 s
    since 2017-01-01; 0 before 1981-07)."""
    from sim_backend.geodesy import leap_seconds

    def leap(at_s: np.ndarray) -> np.ndarray:
        # a leap second only ever starts at 00:00 UTC: one look-up per day
        # (days clipped to 1970..9909, which datetime holds; NaN times stay NaN)
        day = np.clip(np.nan_to_num(np.floor(at_s / 86_400.0)), 0.0, 2_900_000.0)
        days, index = np.unique(day, return_inverse=True)
        counts = [leap_seconds(datetime.fromtimestamp(d * 86_400.0, UTC)) for d in days.tolist()]
        return np.asarray(counts, dtype=float)[index.reshape(-1)]

    t_s = np.asarray(t_s, dtype=float)
    return t_s - leap(t_s - leap(t_s))


TRUTH_ALT_RANGE_M = (-1000.0, 10_000.0)
"""Altitudes (m) --truth accepts: below the Dead Sea shore's -430 m (and a geoid's -106 m)
to above Everest; NaN, inf and 1e300 are refused."""


_ORDINALS = ("1st", "2nd", "3rd")


def parse_truth(text: str) -> tuple[float, float, float]:
    """``LAT,LON[,ALT]`` (degrees, metres) -> (lat, lon, alt or NaN); ConfigError if malformed."""
    parts = [p.strip() for p in text.split(",")]
    empty = [i for i, p in enumerate(parts) if not p]
    if empty and len(parts) > 1:  # "44.07,-121.31,": a stray comma, not a malformed number
        which = ", ".join(_ORDINALS[i] if i < len(_ORDINALS) else f"{i + 1}th" for i in empty)
        raise ConfigError(
            f"--truth {text!r}: {len(parts)} value{'s' if len(parts) != 1 else ''} given, the"
            f" {which} empty: an empty value is not allowed (a stray comma?); expected"
            " LAT,LON[,ALT] (degrees, degrees, metres)"
        )
    if len(parts) not in (2, 3):
        raise ConfigError(
            f"--truth {text!r}: {len(parts)} value{'s' if len(parts) != 1 else ''}, expected 2"
            " or 3: LAT,LON[,ALT] (degrees, degrees, metres)"
        )
    try:
        values = [float(p) for p in parts]
    except ValueError:
        raise ConfigError(f"--truth {text!r}: expected LAT,LON[,ALT] in degrees/metres") from None
    if not (-90 <= values[0] <= 90 and -180 <= values[1] <= 180):
        raise ConfigError(f"--truth {text!r}: expected LAT,LON[,ALT] with |LAT|<=90, |LON|<=180")
    lo_m, hi_m = TRUTH_ALT_RANGE_M
    if len(values) == 3 and not lo_m <= values[2] <= hi_m:
        raise ConfigError(
            f"--truth {text!r}: ALT {values[2]:g} m is outside {lo_m:g}..{hi_m:g} m (a height"
            " above the ellipsoid or sea level where a receiver stands; leave ALT out when"
            " unknown)"
        )
    return values[0], values[1], values[2] if len(values) == 3 else math.nan


def wrap_lon_deg(delta_deg: np.ndarray | float) -> np.ndarray:
    """A longitude difference (deg) wrapped to (-180, 180]: across the antimeridian
    179.99999 - (-179.99999) is -0.00002°, not 359.99998° (24,860 km at 51° N)."""
    delta = np.asarray(delta_deg, dtype=float)
    return 180.0 - np.mod(180.0 - delta, 360.0)


def lon_centre_deg(lon_deg: np.ndarray, how: Callable[[np.ndarray], Any] = np.mean) -> float:
    """The centre (``how``: np.mean, np.median) of longitudes (deg) that may straddle the
    antimeridian: ``how`` of their wrapped differences from the first, added back to it and
    wrapped to (-180, 180]. A log's fixes span metres, so the reference is as good as any."""
    lon_deg = np.asarray(lon_deg, dtype=float)
    ref_deg = float(lon_deg[0])
    return float(wrap_lon_deg(ref_deg + float(how(wrap_lon_deg(lon_deg - ref_deg)))))


def unwrap_lon_deg(lon_deg: np.ndarray) -> np.ndarray:
    """Longitudes (deg) of a path made continuous (no 360° step where it crosses the
    antimeridian), so that they interpolate; values may leave ±180 by the path's extent."""
    lon_deg = np.asarray(lon_deg, dtype=float)
    if lon_deg.size == 0:
        return lon_deg
    return lon_deg[0] + np.concatenate(([0.0], np.cumsum(wrap_lon_deg(np.diff(lon_deg)))))


def errors_vs_point(
    track: Track, lat_deg: float, lon_deg: float, alt_m: float = math.nan
) -> PositionSeries:
    """Errors (m) of a static log against a surveyed point; the frame origin is the point.
    Up error is NaN-free: zero when either altitude is unknown."""
    e_per_deg, n_per_deg = metres_per_degree(lat_deg)
    east_m = wrap_lon_deg(track.lon_deg - lon_deg) * e_per_deg
    north_m = (track.lat_deg - lat_deg) * n_per_deg
    up_m = track.alt_m - alt_m
    return _series(track, east_m, north_m, up_m, lat_deg, lon_deg, None, None)


RELATIVE_TIME_DECIMALS = 5
"""Decimals (s) of a log's times from its first: absolute UTC seconds (1.6e9) hold a time
only to ~2.4e-7 s, a difference of two to ~5e-7, so a 10 Hz log's steps came out as
0.0999999 s (printed so), and rounded to the microsecond some still fell 1e-6 off: the
simulator then took the axis as uneven (its slower, 2x larger path). 10 us is far above
that error and far below any receiver's step (NMEA prints 1-10 ms)."""


def relative_times_s(t_s: np.ndarray) -> np.ndarray:
    """Times (s) from the first, rounded to :data:`RELATIVE_TIME_DECIMALS`."""
    t_s = np.asarray(t_s, dtype=float)
    return np.round(t_s - t_s[0], RELATIVE_TIME_DECIMALS) if t_s.size else t_s


def _series(
    track: Track,
    east_m: np.ndarray,
    north_m: np.ndarray,
    up_m: np.ndarray,
    lat0_deg: float,
    lon0_deg: float,
    speed_mps: np.ndarray | None,
    course_deg: np.ndarray | None,
) -> PositionSeries:
    valid = track.valid & np.isfinite(east_m) & np.isfinite(north_m)
    # heights are at every fix or none (settle_heights): 0 where unknown, and an all-zero
    # up error is what "no heights" is downstream (stats.has_up)
    up_m = np.where(np.isfinite(up_m), up_m, 0.0)
    # counts at every fix or none (settle_counts); epochs without a fix do not count
    has_counts = np.any(valid) and np.all(track.nsats[valid] >= 0)
    nsats = np.maximum(track.nsats, 0.0) if has_counts else None
    sat_set = track.sat_set
    if sat_set is not None and not np.any(sat_set[track.valid] >= 0):
        sat_set = None
    t_s = relative_times_s(track.t_s)
    _check_rising(t_s, track)
    return PositionSeries(
        t_s=t_s,
        east_m=np.where(valid, east_m, 0.0),
        north_m=np.where(valid, north_m, 0.0),
        up_m=np.where(valid, up_m, 0.0),
        valid=valid,
        origin_lat_deg=lat0_deg,
        origin_lon_deg=lon0_deg,
        speed_mps=speed_mps,
        course_deg=course_deg,
        nsats=nsats,
        sat_set=sat_set,
    )


def _check_rising(t_s: np.ndarray, track: Track) -> None:
    """ParseError naming the log and the first pair of epochs where ``t_s`` (s from the
    first, as rounded by :func:`relative_times_s`) does not rise: the simulator and the
    effects refuse such an axis with a bare "t_s must be strictly increasing" that named
    neither the log nor the epochs (a 23:59:60 read 1 us before 00:00:00 did)."""
    steps_s = np.diff(t_s)
    if not steps_s.size or np.all(steps_s > 0):
        return
    k = int(np.flatnonzero(steps_s <= 0)[0])
    gap_us = (track.t_s[k + 1] - track.t_s[k]) * 1e6
    raise ParseError(
        f"{track.source}: epochs {k + 1} and {k + 2} ({_utc_text(float(track.t_s[k]))} and"
        f" {_utc_text(float(track.t_s[k + 1]))}) are {gap_us:.1f} us apart: the time axis must"
        f" rise by at least {10.0**-RELATIVE_TIME_DECIMALS * 1e6:g} us from epoch to epoch"
        " (times finer than that fall on one time); remove one of the two or give times"
        " that rise"
    )


def _truth_samples(truth: Track) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(t s, lat, lon, alt) of a truth track's valid epochs; ParseError below two."""
    ok = truth.valid
    if np.count_nonzero(ok) < 2:
        raise ParseError(f"{truth.source}: truth track has fewer than 2 valid epochs")
    return truth.t_s[ok], truth.lat_deg[ok], truth.lon_deg[ok], truth.alt_m[ok]


def _matched(track: Track, truth_t_s: np.ndarray, max_gap_s: float) -> tuple[np.ndarray, bool]:
    """Indices of ``track``'s epochs within the truth's span and within ``max_gap_s`` of a
    truth sample, and whether the log was moved onto the truth's start (spans apart)."""
    t_s = track.t_s
    apart = bool(t_s[-1] < truth_t_s[0] or t_s[0] > truth_t_s[-1])
    if apart:
        t_s = t_s - t_s[0] + truth_t_s[0]
    index = np.clip(np.searchsorted(truth_t_s, t_s), 1, truth_t_s.size - 1)
    near = (
        np.minimum(np.abs(truth_t_s[index] - t_s), np.abs(truth_t_s[index - 1] - t_s)) <= max_gap_s
    )
    inside = (t_s >= truth_t_s[0]) & (t_s <= truth_t_s[-1]) & near
    return np.flatnonzero(inside), apart


def realign_note(track: Track, truth: Track, max_gap_s: float = 1.5) -> str | None:
    """A note when ``track``'s time span does not overlap the truth track's, so that
    :func:`errors_vs_track` moved it onto the truth's start (start to start): by how much,
    and how many of its epochs then fall within the truth's span. None when they overlap."""
    truth_t_s = _truth_samples(truth)[0]
    kept, apart = _matched(track, truth_t_s, max_gap_s)
    if not apart:
        return None
    shift_s = float(truth_t_s[0] - track.t_s[0])
    return (
        f"{track.source}: its times ({_span_text(track.t_s[0], track.t_s[-1])}) do not overlap"
        f" the truth track's ({_span_text(truth_t_s[0], truth_t_s[-1])}): it was realigned"
        f" start to start, its times moved {_duration_text(shift_s)}"
        f" {'later' if shift_s >= 0 else 'earlier'}; {kept.size} of {len(track)} epochs then"
        " match the truth in time (a simulated log's clock is its own; for a real log, is the"
        " truth track this log's?)"
    )


def _span_text(t0_s: float, t1_s: float) -> str:
    """A time span as dates when it is dated, else as seconds."""
    if is_date(t0_s) and is_date(t1_s):
        return f"{_utc_text(t0_s)} to {_utc_text(t1_s)}"
    return f"{t0_s:.1f} s to {t1_s:.1f} s"


def _duration_text(seconds: float) -> str:
    """|seconds| as days, hours, minutes and seconds (e.g. 366 d 0 h 0 min 0 s)."""
    left = round(abs(seconds), 1)
    days, left = divmod(left, 86_400.0)
    hours, left = divmod(left, 3_600.0)
    minutes, left = divmod(left, 60.0)
    parts = [f"{days:.0f} d"] if days else []
    parts += [f"{hours:.0f} h"] if days or hours else []
    parts += [f"{minutes:.0f} min"] if days or hours or minutes else []
    return " ".join([*parts, f"{left:g} s"])


MAX_STEP_S = 60.0
"""Largest median step (s) between a log's epochs the tool diagnoses. Receivers log at
1-20 Hz and the sparsest trackers once a minute; the effects it fits act within seconds
(latency, filter lag, jumps, short outages) and vanish between fixes farther apart, and a
step of about 1000 is a time column in milliseconds read as seconds."""
_TIME_UNIT = re.compile(r"(^|[^a-z])(s|sec|secs|seconds?|ms|msec|millis|milliseconds?)([^a-z]|$)")


def check_step(track: Track) -> None:
    """ParseError naming the file (and a CSV's time column) when the median step between
    ``track``'s epochs exceeds :data:`MAX_STEP_S`; a hint when they look like milliseconds
    (the step / 1000 a receiver's, and the column's name gives no unit or milliseconds)."""
    if len(track) < 2:
        return
    step_s = float(np.median(np.diff(track.t_s)))
    if step_s <= MAX_STEP_S:
        return
    column = f" (time column {track.time_column!r})" if track.time_column else ""
    hint = ""
    unit = _TIME_UNIT.search(track.time_column.lower())
    in_ms = track.time_column and (unit is None or unit.group(2).startswith("m"))
    if in_ms and 0.05 <= step_s / 1000.0 <= MAX_STEP_S:
        hint = f"; are the times in milliseconds ({step_s / 1000.0:g} s apart)? give seconds"

    raise ParseError(
        f"{track.source}: its fixes are a median {step_s:g} s apart{column}: the gap tool"
        f" diagnoses logs of at most {MAX_STEP_S:g} s between fixes{hint}"
    )


def errors_vs_track(track: Track, truth: Track, max_gap_s: float = 1.5) -> PositionSeries:
    """Errors (m) of a log against a truth track matched in time (linear interpolation of the
    truth; epochs farther than ``max_gap_s`` from a valid truth sample are dropped). If the two
    time spans do not overlap, both are taken from their own start (a simulated log).
    The series carries the truth's speed/course (from its positions), the truth's positions
    themselves (``true_east_m``/``true_north_m``), and its origin is the truth at the first
    kept epoch, so effect layers see the true motion."""
    truth_t_s, truth_lat_deg, truth_lon_deg, truth_alt_m = _truth_samples(truth)
    truth_lon_deg = unwrap_lon_deg(truth_lon_deg)  # interpolated across the antimeridian too
    kept, apart = _matched(track, truth_t_s, max_gap_s)
    if not kept.size:
        moved = " (moved start to start: their spans do not overlap)" if apart else ""
        raise ParseError(
            f"{track.source}: no epoch matches the truth track {truth.source} in time{moved}:"
            f" the log spans {_span_text(track.t_s[0], track.t_s[-1])}, the truth"
            f" {_span_text(truth_t_s[0], truth_t_s[-1])}"
        )
    t_s = track.t_s - track.t_s[0] + truth_t_s[0] if apart else track.t_s
    t_s = t_s[kept]
    true_lat_deg, true_lon_deg, true_alt_m = (
        np.interp(t_s, truth_t_s, truth_lat_deg),
        np.interp(t_s, truth_t_s, truth_lon_deg),
        np.interp(t_s, truth_t_s, truth_alt_m),
    )
    lat0_deg, lon0_deg = float(true_lat_deg[0]), float(wrap_lon_deg(true_lon_deg[0]))
    e_per_deg, n_per_deg = metres_per_degree(lat0_deg)
    sub = Track(
        t_s=t_s,
        lat_deg=track.lat_deg[kept],
        lon_deg=track.lon_deg[kept],
        alt_m=track.alt_m[kept],
        valid=track.valid[kept],
        nsats=track.nsats[kept],
        speed_mps=track.speed_mps[kept],
        course_deg=track.course_deg[kept],
        source=track.source,
        sat_set=None if track.sat_set is None else track.sat_set[kept],
    )
    true_east_m, true_north_m = (
        wrap_lon_deg(true_lon_deg - lon0_deg) * e_per_deg,
        (true_lat_deg - lat0_deg) * n_per_deg,
    )
    east_m = wrap_lon_deg(sub.lon_deg - lon0_deg) * e_per_deg - true_east_m
    north_m = (sub.lat_deg - lat0_deg) * n_per_deg - true_north_m
    # truth velocity from its own positions (central differences)
    if t_s.size > 1:
        v_east_mps, v_north_mps = np.gradient(true_east_m, t_s), np.gradient(true_north_m, t_s)
    else:
        v_east_mps, v_north_mps = np.zeros(1), np.zeros(1)
    speed_mps = np.hypot(v_east_mps, v_north_mps)
    course_deg = np.degrees(np.arctan2(v_east_mps, v_north_mps)) % 360.0
    # The truth's own positions ride along: integrating the central-difference velocity
    # drifts by millimetres to decimetres, and the lattice test needs the absolute position
    # to 0.5 mm (a moving log read as off its NMEA lattice: outside audit).
    return _series(
        sub, east_m, north_m, sub.alt_m - true_alt_m, lat0_deg, lon0_deg, speed_mps, course_deg
    ).with_(true_east_m=true_east_m, true_north_m=true_north_m)


TRUTH_VELOCITY_WINDOW_S = 2.0
"""Span (s) over which a truth's velocity is taken (its positions interpolated at either
end, centred on the epoch): a truth sampled fast and rounded (50-100 Hz at 6 decimals, 0.11
m) read 0.6-1.2 m/s of speed noise differenced sample to sample, 0.07 m/s over this."""


def truth_velocity_mps(truth: Track, t_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """East and north velocity (m/s) of a truth track at the times ``t_s`` (within its span):
    its interpolated displacement over :data:`TRUTH_VELOCITY_WINDOW_S` centred on each time
    (clipped to the truth's span), so its rounding is not read as speed."""
    truth_t_s, truth_lat_deg, truth_lon_deg, _ = _truth_samples(truth)
    e_per_deg, n_per_deg = metres_per_degree(float(truth_lat_deg[0]))
    east_m = (unwrap_lon_deg(truth_lon_deg) - truth_lon_deg[0]) * e_per_deg
    north_m = (truth_lat_deg - truth_lat_deg[0]) * n_per_deg
    half_s = TRUTH_VELOCITY_WINDOW_S / 2.0
    t0_s = np.clip(t_s - half_s, truth_t_s[0], truth_t_s[-1])
    t1_s = np.clip(t_s + half_s, truth_t_s[0], truth_t_s[-1])
    span_s = np.maximum(t1_s - t0_s, 1e-9)

    def rate(x_m: np.ndarray) -> np.ndarray:
        return (np.interp(t1_s, truth_t_s, x_m) - np.interp(t0_s, truth_t_s, x_m)) / span_s

    return rate(east_m), rate(north_m)


def truth_median_speed_mps(truth: Track) -> float:
    """Median speed (m/s) of a truth track over its own samples (:func:`truth_velocity_mps`):
    near 0 for a static survey's, however its fixes are rounded or jitter."""
    east_mps, north_mps = truth_velocity_mps(truth, _truth_samples(truth)[0])
    return float(np.median(np.hypot(east_mps, north_mps)))


def velocity_mismatch_mps(track: Track, truth: Track, max_gap_s: float = 1.5) -> float:
    """Median difference (m/s) between ``track``'s reported velocity (a receiver's Doppler
    speed and course: NMEA RMC, a recording) and its truth's (:func:`truth_velocity_mps`)
    over the epochs matched in time as :func:`errors_vs_track` matches them: the vector
    difference where the epoch has a course, the speed difference where not; NaN with fewer
    than 10 such epochs (a log without speeds). Near the receiver's velocity noise (0.085-0.13
    m/s in 30 moving x6wd sim runs, urban multipath too) against the log's own truth,
    however far its positions stray; a truth of another run or time, whose robot is
    elsewhere on its route or heading elsewhere, differs by tenths of m/s to m/s."""
    truth_t_s = _truth_samples(truth)[0]
    kept, apart = _matched(track, truth_t_s, max_gap_s)
    kept = kept[track.valid[kept] & np.isfinite(track.speed_mps[kept])]
    if kept.size < 10:
        return math.nan
    t_s = track.t_s - track.t_s[0] + truth_t_s[0] if apart else track.t_s
    east_mps, north_mps = truth_velocity_mps(truth, t_s[kept])
    speed_mps, course_rad = track.speed_mps[kept], np.radians(track.course_deg[kept])
    off_mps = np.abs(speed_mps - np.hypot(east_mps, north_mps))
    has_course = np.isfinite(course_rad)
    off_mps[has_course] = np.hypot(
        speed_mps[has_course] * np.sin(course_rad[has_course]) - east_mps[has_course],
        speed_mps[has_course] * np.cos(course_rad[has_course]) - north_mps[has_course],
    )
    return float(np.median(off_mps))


TIME_OFFSET_SEARCH_S = 120
"""Constant clock offsets (s) between a log and its truth track that are looked for."""


def time_offset_note(track: Track, truth: Track, max_gap_s: float = 1.5) -> str | None:
    """A warning when ``track`` lines up with the moving ``truth`` clearly better with its
    time stamps shifted by a constant (whole seconds within ±:data:`TIME_OFFSET_SEARCH_S`):
    the median horizontal distance at the best shift of at least 1 s is under half the
    distance as stamped. None when the shift is under 1 s, the truth hardly moves (every
    shift gives the same distance), or the spans do not overlap. The errors stay as
    stamped: the note names the offset (GPS-UTC is 18 s; a time zone is hours)."""
    truth_t_s, truth_lat_deg, truth_lon_deg, _ = _truth_samples(truth)
    truth_lon_deg = unwrap_lon_deg(truth_lon_deg)
    kept, apart = _matched(track, truth_t_s, max_gap_s)
    kept = kept[track.valid[kept]]
    if apart or kept.size < 10:
        return None
    kept = kept[np.linspace(0, kept.size - 1, min(kept.size, 3000)).astype(int)]
    t_s = track.t_s[kept]
    e_per_deg, n_per_deg = metres_per_degree(float(truth_lat_deg[0]))
    east_m = wrap_lon_deg(track.lon_deg[kept] - truth_lon_deg[0]) * e_per_deg
    north_m = (track.lat_deg[kept] - truth_lat_deg[0]) * n_per_deg
    truth_east_m = (truth_lon_deg - truth_lon_deg[0]) * e_per_deg
    truth_north_m = (truth_lat_deg - truth_lat_deg[0]) * n_per_deg

    def median_distance_m(shift_s: float) -> float:
        at_s = t_s - shift_s  # the truth's time of a fix stamped t_s by a clock shift_s ahead
        index = np.clip(np.searchsorted(truth_t_s, at_s), 1, truth_t_s.size - 1)
        gap_s = np.minimum(np.abs(truth_t_s[index] - at_s), np.abs(truth_t_s[index - 1] - at_s))
        ok = (at_s >= truth_t_s[0]) & (at_s <= truth_t_s[-1]) & (gap_s <= max_gap_s)
        if np.count_nonzero(ok) < max(10, kept.size // 2):
            return math.inf
        return float(np.median(np.hypot(
            east_m[ok] - np.interp(at_s[ok], truth_t_s, truth_east_m),
            north_m[ok] - np.interp(at_s[ok], truth_t_s, truth_north_m),
        )))  # fmt: skip

    shifts = range(-TIME_OFFSET_SEARCH_S, TIME_OFFSET_SEARCH_S + 1)
    distance_m = {shift: median_distance_m(float(shift)) for shift in shifts}
    best = min(distance_m, key=lambda shift: (distance_m[shift], abs(shift)))
    stamped_m, best_m = distance_m[0], distance_m[best]
    if best == 0 or not math.isfinite(best_m) or not best_m < 0.5 * stamped_m:
        return None
    head = (
        f"{track.source} lines up with the truth track {truth.source} best with its time"
        f" stamps {abs(best)} s {'earlier' if best > 0 else 'later'} (median distance"
        f" {best_m:.1f} m, against {stamped_m:.1f} m as stamped)"
    )
    if abs(best) == 1:  # as much a receiver's output latency (an effect fitted) as a clock
        return (
            f"{head}: a receiver latency of about a second (the latency effect measures it)"
            " or clocks 1 s apart; the errors are taken as stamped"
        )
    return (
        f"{head}: the two clocks differ by a constant (a time system: GPS-UTC is 18 s since"
        " 2017; a time zone; a logger's clock). The errors are taken as stamped: correct the"
        " log's or the truth's times"
    )


def mean_alt_m(track: Track) -> float:
    """Mean altitude (m) of a log's valid fixes; NaN when it has none."""
    alt_m = track.alt_m[track.valid & np.isfinite(track.alt_m)]
    return float(np.mean(alt_m)) if alt_m.size else math.nan


def is_date(t_s: float) -> bool:
    """Whether a log time (s) is a UTC date the sky can be simulated at: from the GPS epoch
    (1980-01-06) to 2100, not a receive clock or seconds from a log's start."""
    return _GPS_EPOCH_S <= t_s < 4_102_444_800.0


def log_start_s(track: Track, truth: Track | None = None, max_gap_s: float = 1.5) -> float:
    """Time (s, the log's own clock) of the first epoch of ``track``'s error series: its first
    epoch, or against ``truth`` the first one matched in time (:func:`errors_vs_track`)."""
    if truth is None:
        return float(track.t_s[0])
    kept, _ = _matched(track, _truth_samples(truth)[0], max_gap_s)
    return float(track.t_s[kept[0]]) if kept.size else float(track.t_s[0])


def moving_text(track: Track) -> str | None:
    """The text "the log moves (median speed ..., fixes a median ... from their centre)" when its
    median reported speed exceeds :data:`STATIC_MAX_SPEED_MPS` or its fixes lie a median of
    more than :data:`STATIC_MAX_SPREAD_M` from their centre; None for a static log (or one
    without a valid fix)."""
    valid = track.valid
    if not np.any(valid):
        return None
    speed_mps = track.speed_mps[valid]
    speed_mps = speed_mps[np.isfinite(speed_mps)]
    median_speed_mps = float(np.median(speed_mps)) if speed_mps.size else 0.0
    e_per_deg, n_per_deg = metres_per_degree(float(np.median(track.lat_deg[valid])))
    lon_deg = track.lon_deg[valid]
    spread_m = float(np.median(np.hypot(
        wrap_lon_deg(lon_deg - lon_centre_deg(lon_deg, np.median)) * e_per_deg,
        (track.lat_deg[valid] - np.median(track.lat_deg[valid])) * n_per_deg,
    )))  # fmt: skip
    if median_speed_mps > STATIC_MAX_SPEED_MPS or spread_m > STATIC_MAX_SPREAD_M:
        return (
            f"the log moves (median speed {median_speed_mps:.1f} m/s, fixes a median"
            f" {spread_m:.0f} m from their centre)"
        )
    # within both limits a robot may still drive (0.94 m/s, its route 14.5 m about its
    # centre: an audit saw it read as a static receiver's error): its steps point the same
    # way, which no error of a receiver standing still makes them do
    lat_deg, lon_deg = track.lat_deg[valid], track.lon_deg[valid]
    x_m = wrap_lon_deg(lon_deg - lon_centre_deg(lon_deg, np.median)) * e_per_deg
    y_m = (lat_deg - np.median(lat_deg)) * n_per_deg
    steady = steady_speed_mps(track.t_s[valid], x_m, y_m)
    if steady is None or steady[0] <= MAX_STATIC_SPEED_MPS or steady[1] < MOVE_SIGNIFICANCE:
        return None
    return (
        f"the log moves (a steady speed of {steady[0]:.2f} m/s: successive steps point the"
        f" same way, {steady[1]:.0f} standard errors above a still receiver's noise; median"
        f" reported speed {median_speed_mps:.1f} m/s)"
    )


def errors_vs_mean(track: Track) -> PositionSeries:
    """Errors of a static log against its own mean position (no truth: a bias is invisible).
    Raises ConfigError for a log that moves (:func:`moving_text`): its route is no error, it
    needs a truth track."""
    valid = track.valid
    if not np.any(valid):
        raise ParseError(f"{track.source}: no valid fix: 0 of {len(track)} epochs have a fix")
    moves = moving_text(track)
    if moves is not None:
        raise ConfigError(
            f"{track.source}: {moves}: without a truth its route would count as error; give"
            " --truth-track (the true path)"
        )
    lon_deg = track.lon_deg[valid]
    alt_m = track.alt_m[valid]
    alt0_m = float(np.nanmean(alt_m)) if np.any(np.isfinite(alt_m)) else math.nan
    return errors_vs_point(
        track, float(np.mean(track.lat_deg[valid])), lon_centre_deg(lon_deg), alt0_m
    )


def check_near_truth(
    series: PositionSeries, source: str, log: str | None = None, own_truth: str | None = None
) -> PositionSeries:
    """``series`` (errors against a truth, m) unless its median horizontal error exceeds
    :data:`MAX_ERROR_FROM_TRUTH_M`: then ConfigError naming ``source`` and the distance (a
    simulation of another place, or a wrong truth, would otherwise read as a bias of
    thousands of kilometres). ``log`` says which log it is, ``"real"`` or ``"sim"``: the
    hint is that log's (None: both hints, each saying whose it is). ``own_truth``: the file
    of a --sim log's own truth (truth.csv beside it) it was scored against: named as the
    truth, and the hint asks about it, not --truth/--truth-track."""
    valid = np.asarray(series.valid, dtype=bool)
    if np.any(valid):
        error_m = np.hypot(np.asarray(series.east_m)[valid], np.asarray(series.north_m)[valid])
        median_m = float(np.median(error_m))
        if median_m > MAX_ERROR_FROM_TRUTH_M:
            hint = {
                "real": "is --truth or --truth-track the real log's place, and --real the log"
                " meant?",
                "sim": "a --sim log must simulate the real log's place and path; is --truth or"
                " --truth-track right?",
            }.get(
                log or "",
                "is --truth or --truth-track right? if this is a --sim log, it must simulate"
                " the real log's place and path",
            )
            which = {"real": "the real log (--real)", "sim": "a --sim log"}.get(log or "")
            head = f"{source} ({which})" if which else source
            truth = "the truth"
            if own_truth is not None:
                truth = f"its own truth {own_truth}"
                hint = (
                    f"is {own_truth} the true path of this run (the truth.csv x6wd sim wrote"
                    " beside it), and does the run simulate the real log's place?"
                )
            raise ConfigError(
                f"{head}: its fixes lie a median {median_m / 1000:.1f} km from {truth}:"
                f" not a log of that place ({hint})"
            )
    return series


def against_own_mean(series: PositionSeries) -> PositionSeries:
    """An error series (m) taken against its own mean instead of its truth, as
    :func:`errors_vs_mean` takes a log without a truth: each axis less its mean over the
    valid epochs, the origin moved by the horizontal means so that the positions themselves
    (and the NMEA lattice they lie on) stay where they were."""
    valid = np.asarray(series.valid, dtype=bool)
    if not np.any(valid):
        return series
    means = [float(np.mean(np.asarray(a, dtype=float)[valid])) for a in
             (series.east_m, series.north_m, series.up_m)]  # fmt: skip
    e_per_deg, n_per_deg = metres_per_degree(series.origin_lat_deg)
    return series.with_(
        east_m=np.where(valid, np.asarray(series.east_m, dtype=float) - means[0], 0.0),
        north_m=np.where(valid, np.asarray(series.north_m, dtype=float) - means[1], 0.0),
        up_m=np.where(valid, np.asarray(series.up_m, dtype=float) - means[2], 0.0),
        origin_lat_deg=series.origin_lat_deg + means[1] / n_per_deg,
        origin_lon_deg=float(wrap_lon_deg(series.origin_lon_deg + means[0] / e_per_deg)),
    )


def write_csv(path: str | Path, track: Track) -> None:
    """Write a Track as CSV ``time,lat,lon,alt,valid,nsats`` (readable by :func:`read_track`)."""
    with open(path, "w", newline="") as file:
        writer = csv.writer(file)
        writer.writerow(["time", "lat", "lon", "alt", "valid", "nsats"])
        for i in range(len(track)):
            writer.writerow(
                [
                    f"{track.t_s[i]:.3f}",
                    f"{track.lat_deg[i]:.10f}",
                    f"{track.lon_deg[i]:.10f}",
                    "" if not math.isfinite(track.alt_m[i]) else f"{track.alt_m[i]:.4f}",
                    int(bool(track.valid[i])),
                    int(track.nsats[i]),
                ]
            )


def series_to_track(series: PositionSeries, alt0_m: float = 0.0) -> Track:
    """Absolute positions of an error series (origin + implied truth + error) as a Track."""
    from sim_backend.effects import truth_track_m

    e_per_deg, n_per_deg = metres_per_degree(series.origin_lat_deg)
    true_east_m, true_north_m = truth_track_m(series)
    n_epochs = len(series)
    return Track(
        t_s=np.asarray(series.t_s, dtype=float),
        lat_deg=series.origin_lat_deg + (true_north_m + series.north_m) / n_per_deg,
        lon_deg=wrap_lon_deg(series.origin_lon_deg + (true_east_m + series.east_m) / e_per_deg),
        alt_m=alt0_m + np.asarray(series.up_m, dtype=float),
        valid=np.asarray(series.valid, dtype=bool),
        nsats=np.full(n_epochs, -1.0)
        if series.nsats is None
        else np.asarray(series.nsats, dtype=float),
        speed_mps=np.full(n_epochs, math.nan),
        course_deg=np.full(n_epochs, math.nan),
    )
