"""The log viewer: a flight recording (or a plain NMEA log) as pictures (`x6wd plot`).

Eight panels over one time axis (seconds since the recording's first record): the track on a
local east/north map in metres, the position error when a true track is known, HDOP,
satellites, heading, navigation states, holds and device faults. Two outputs:

- :func:`render_html` — one self-contained HTML page: inline SVG drawn here, the data
  embedded as JSON, no script or style from anywhere else and no matplotlib, so the daemon's
  web console can serve it on the robot's core install;
- ``x6wd.app.plot.render_png`` — the same panels with matplotlib (the ``plot`` extra), in
  a module of its own so that the daemon, which imports this one, never imports matplotlib.

What a recording holds decides what can be drawn; every panel that cannot be says why in
its place (an NMEA log has no navigation states; only ``x6wd sim`` writes a true track, a
HIL or real run none). The true track is the simulator's ``truth.csv`` next to the
recording (``--truth`` for another). Device faults are the recorder's ``device`` events
(health transitions) and, in older recordings without them, the holds that name a device.

A log's own clock can go backwards or jump: a plain NMEA log's is the receiver's time of day
(a file of two sessions, a cold start's unset clock), a recording's the daemon's monotonic
clock (two sessions appended to one file, each restarting it). The time axis is then the
file's order: where the log's time goes back, or forward by more than :data:`TIME_JUMP_S`,
the next segment is drawn one epoch after the previous one, the place marked on every time
panel and said in the page's facts (:class:`TimeJump`). Crossing midnight is not a jump.

A log of any length is read in bounded memory (the daemon serves this page): each series is
kept whole up to :data:`SAMPLE_ROWS` rows and thinned as it is read beyond that, keeping its
first and last rows and its extremes (:class:`_Sample`), so the axes are those of the whole.
"""

from __future__ import annotations

import csv
import html
import json
import math
import statistics
from array import array
from collections import deque
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass, field, replace
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any

import numpy as np

from x6wd import __version__
from x6wd.core.errors import DeviceUnavailable, ParseError, X6wdError
from x6wd.core.files import require_regular
from x6wd.core.geodesy import wrap360, wrap_deg
from x6wd.core.recorder import (
    END_EVENTS,
    GAP_EVENT,
    ReadStats,
    Record,
    Writer,
    decode_record,
    is_recording,
    list_recordings,
    nmea_file_chunks,
    recording_parts,
    recording_writer,
    unknown_fields,
)
from x6wd.core.records import GpsFix, GpsSky, Mode, NavState
from x6wd.core.thinning import thinned_indices
from x6wd.nav.geo import LocalTangentPlane

PANELS = ("track", "error", "hdop", "satellites", "heading", "states", "holds", "faults")
"""Panel ids, in page order (the HTML sections are ``panel-<id>``)."""

MAX_POINTS = 2000
"""Points per drawn series in the HTML page: longer series are thinned by a stride (a day's
20 Hz compass would otherwise make a page of tens of megabytes). Intervals are never thinned."""

DEVICES = ("gps", "compass", "motors")
"""Lanes of the device-fault panel."""

TIME_JUMP_S = 3600.0
"""A plain NMEA log's time running forward by more than this between two lines is a jump
(another session, a receiver's clock set at last), drawn as one like a step back: an axis of
hours would squeeze the log's minutes out of sight. Shorter gaps (an outage, a pause between
runs in one file) are drawn as the time they were."""

RECORDING_JITTER_S = 10.0
"""A recording's time stepping back by less than this is not a jump: the recorder stamps a
record with its data's own time (a fix with its arrival, a device event with when it
happened) and several threads write, so neighbours can be out of order by a loop's latency
or a batch of device events (a reconnect's several seconds). Another session (the daemon
started again, its monotonic clock with it) steps back by about the previous one's length."""

CLOCK_AGREE_S = 120.0
"""A recording's clock (its ``t_utc``) and its first dated valid fix's UTC less the time the
fix arrived may differ by this much (the fix's latency, a clock slightly off, and a receiver
after a cold start that gives GPS time until it has the leap seconds: 18 s today); more, and the
recording's time 0 is dated by the fix: the recorder's clock was wrong (a robot without a
real-time clock boots at 1970), and fixes placed by it would miss the true track's time."""

_MODES = frozenset(str(m) for m in Mode)
_NAV_STATES = frozenset(str(s) for s in NavState)


@dataclass
class Series:
    """One time series: times (s since the log's start) and values (NaN = no value)."""

    label: str
    t_s: np.ndarray
    v: np.ndarray

    def to_json(self) -> dict[str, Any]:
        """Plain lists for the page's embedded data (NaN as null): the points drawn."""
        t, v = _thin(self.t_s, self.v)
        return {"label": self.label, "t_s": _floats(t, 3), "v": _floats(v, 4)}


@dataclass
class Interval:
    """A span of time (s since the log's start) in one lane with a label."""

    lane: str
    t0_s: float
    t1_s: float
    label: str
    detail: str = ""  # shown on hover (a device fault's first message)

    def to_json(self) -> dict[str, Any]:
        """Plain dict for the page's embedded data."""
        return {
            "lane": self.lane,
            "t0_s": round(self.t0_s, 3),
            "t1_s": round(self.t1_s, 3),
            "label": self.label,
            "detail": self.detail,
        }


@dataclass
class RecordingGap:
    """A hole in a recording: the recorder lost ``records_lost`` records (a full or
    read-only disk, a stuck writer) from ``t0_s`` to ``t1_s`` (s since the log's start) and
    went on; its gap event says so (:data:`x6wd.core.recorder.GAP_EVENT`)."""

    t0_s: float
    t1_s: float
    records_lost: int
    error: str = ""

    def describe(self) -> str:
        """In words, as the page's facts and ``x6wd plot`` say it."""
        text = (
            f"t={self.t0_s:.1f} s to t={self.t1_s:.1f} s ({self.t1_s - self.t0_s:.1f} s, "
            f"{self.records_lost} records lost"
        )
        return text + (f": {self.error})" if self.error else ")")

    def to_json(self) -> dict[str, Any]:
        """Plain dict for the page's embedded data."""
        return {
            "t0_s": round(self.t0_s, 3),
            "t1_s": round(self.t1_s, 3),
            "records_lost": self.records_lost,
            "error": self.error,
        }


@dataclass
class TimeJump:
    """A place where a log's own time goes back (or far forward): the segments either side
    are drawn in file order, one epoch apart, and the place marked."""

    t_s: float  # on the time axis: between the two segments
    line: int  # the file's line (1-based) where the later segment starts
    step_s: float  # the log's own time step there (negative: it went back)
    before_utc: str = ""  # UTC either side: an NMEA log's fixes, a recording's t_utc
    after_utc: str = ""
    file: str = ""  # a recording's part holding ``line``, when not the file plotted
    # on the time axis: the last segment's last time, the next one's first (the step's ends)
    t_before_s: float = math.nan
    t_after_s: float = math.nan

    def describe(self) -> str:
        """In words, as the page's facts and ``x6wd plot`` say it."""
        way = "back" if self.step_s < 0 else "forward"
        where = f"line {self.line}" + (f" of {self.file}" if self.file else "")
        text = f"{where}: time went {way} {_duration(abs(self.step_s))}"
        if self.before_utc or self.after_utc:
            text += f", {self.before_utc or 'unknown'} -> {self.after_utc or 'unknown'} UTC"
        return text

    def to_json(self) -> dict[str, Any]:
        """Plain dict for the page's embedded data."""
        return {
            "t_s": round(self.t_s, 3),
            "line": self.line,
            "step_s": round(self.step_s, 3),
            "before_utc": self.before_utc,
            "after_utc": self.after_utc,
            "file": self.file,
        }


MAX_JUMPS = 100
"""Time jumps kept of a log (listed in the page's data, marked on its panels and the PNG's):
a log with more (epochs written out of order, thousands of logs concatenated) has them
thinned as they are read, as its series are: the first, then one in every 2, 4, 8... by
file order, so that what is kept stays spread over the whole log. Its count is kept."""

LARGEST_JUMPS = 10
"""The largest time jumps (by their step) kept as well, wherever they are: a session's step
of an hour is not lost among thousands of one-second steps."""


class JumpList(list[TimeJump]):
    """A log's time jumps as read, in file order, bounded: :data:`MAX_JUMPS` thinned by a
    stride and the :data:`LARGEST_JUMPS` largest; :attr:`total` counts every one."""

    def __init__(self, jumps: Iterable[TimeJump] = ()) -> None:
        super().__init__()
        self.total = 0
        self.version = 0  # changes whenever the jumps kept do
        self._stride = 1
        self._strided: list[TimeJump] = []
        self._largest: list[TimeJump] = []  # by |step|, largest first
        for j in jumps:
            self.append(j)

    def append(self, jump: TimeJump) -> None:
        """One more jump, later in the file than any before it."""
        index, self.total = self.total, self.total + 1
        kept = False
        if index % self._stride == 0:
            self._strided.append(jump)
            kept = True
        size = abs(jump.step_s)
        if len(self._largest) < LARGEST_JUMPS or size > abs(self._largest[-1].step_s):
            self._largest.append(jump)
            self._largest.sort(key=lambda j: -abs(j.step_s))
            del self._largest[LARGEST_JUMPS:]
            kept = True
        if not kept:
            return
        self.version += 1
        if len(self._strided) > MAX_JUMPS:
            self._strided = self._strided[::2]  # those at a multiple of the doubled stride
            self._stride *= 2
        ids = {id(j) for j in (*self._strided, *self._largest)}
        if len(ids) == len(self) + 1 and id(jump) in ids:
            super().append(jump)  # nothing dropped: the newest is the last in file order
        else:
            self[:] = [j for j in (*self, jump) if id(j) in ids]


def n_jumps(view: LogView) -> int:
    """Every time jump of a log, those not kept (:class:`JumpList`) too."""
    return getattr(view.jumps, "total", len(view.jumps))


def _duration(s: float) -> str:
    """``s`` seconds as "12.5 s", or with its hours and minutes when long ("3122.5 s (52
    min)")."""
    text = f"{s:.1f} s"
    if s >= 120:
        h, m = divmod(round(s / 60), 60)
        text += f" ({h} h {m} min)" if h else f" ({m} min)"
    return text


@dataclass
class LogView:
    """Everything the panels draw, taken from one recording or NMEA log."""

    path: Path
    kind: str  # "recording" or "NMEA log"
    duration_s: float = 0.0
    start_utc: str = ""
    # a recording whose recorder's clock disagreed with the GPS at the first dated fix:
    # what it read there, and by how much it was off (s, + ahead); start_utc is the GPS's
    recorder_clock: str = ""
    recorder_clock_off_s: float | None = None
    origin_deg: tuple[float, float] | None = None  # (lat, lon) of the map's (0, 0)
    # track: label -> (east m, north m)
    track: dict[str, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)
    error: list[Series] = field(default_factory=list)  # horizontal error, m
    hdop: list[Series] = field(default_factory=list)
    satellites: list[Series] = field(default_factory=list)
    heading: list[Series] = field(default_factory=list)  # degrees 0-360
    states: list[Interval] = field(default_factory=list)  # lanes "mode", "navigation"
    holds: list[Interval] = field(default_factory=list)  # lane "hold", label = reason
    faults: list[Interval] = field(default_factory=list)  # lanes: DEVICES
    missing: dict[str, str] = field(default_factory=dict)  # panel id -> why it is empty
    counts: dict[str, int] = field(default_factory=dict)
    # the log's time jumps: those kept (a JumpList: at most MAX_JUMPS + LARGEST_JUMPS)
    jumps: list[TimeJump] = field(default_factory=lambda: JumpList())
    # the recording's gaps (the recorder lost records: a full or read-only disk, a stuck
    # writer); drawn in ``faults``, lane "recorder"
    gaps: list[RecordingGap] = field(default_factory=list)
    # a recording whose last record is not the daemon's shutdown event (or the simulator's
    # end), and that no recorder writes any more: a crash, kill -9 or a power cut; None for
    # an NMEA log
    cut_short: bool | None = None
    # a recording a recorder still writes (its lock held, tested before the records): drawn
    # as far as it was written, neither finished nor cut short; None when it is not
    writer: Writer | None = None
    # a run recorded in parts whose first (or other) parts are gone (retention deletes the
    # oldest first): their names, and the time from the run's name to the first record read
    # (s, by the recorder's clock; None when unknown)
    missing_parts: list[str] = field(default_factory=list)
    run_start_utc: str = ""  # the run's start by its name, when its first part is gone
    missing_start_s: float | None = None

    def time_range(self) -> tuple[float, float]:
        """The time axis: 0 to the duration, widened to any time drawn outside it (so that
        nothing is ever off the panels), at least 1 ms long."""
        lo, hi = 0.0, self.duration_s
        for s in (*self.error, *self.hdop, *self.satellites, *self.heading):
            t = s.t_s[np.isfinite(s.t_s)]
            if t.size:
                lo, hi = min(lo, float(t.min())), max(hi, float(t.max()))
        for iv in (*self.states, *self.holds, *self.faults):
            lo, hi = min(lo, iv.t0_s, iv.t1_s), max(hi, iv.t0_s, iv.t1_s)
        return lo, max(hi, lo + 1e-3)

    def to_json(self) -> dict[str, Any]:
        """The data behind every panel, as embedded in the HTML page: the points drawn
        (series and tracks thinned to :data:`MAX_POINTS`)."""
        return {
            "file": self.path.name,
            "kind": self.kind,
            "duration_s": round(self.duration_s, 3),
            "start_utc": self.start_utc,
            "recorder_clock_off_s": self.recorder_clock_off_s,
            "origin_deg": list(self.origin_deg) if self.origin_deg else None,
            "track": {
                k: {"east_m": _floats(e, 3), "north_m": _floats(n, 3)}
                for k, (e, n) in ((k, _thin(*en)) for k, en in self.track.items())
            },
            "error": [s.to_json() for s in self.error],
            "hdop": [s.to_json() for s in self.hdop],
            "satellites": [s.to_json() for s in self.satellites],
            "heading": [s.to_json() for s in self.heading],
            "states": [i.to_json() for i in self.states],
            "holds": [i.to_json() for i in self.holds],
            "faults": [i.to_json() for i in self.faults],
            "missing": self.missing,
            "counts": self.counts,
            "time_jumps": [j.to_json() for j in self.jumps],
            "time_jumps_total": n_jumps(self),
            "recording_gaps": [g.to_json() for g in self.gaps],
            "cut_short": self.cut_short,
            "in_progress": self.writer is not None,
            "writer_pid": self.writer.pid if self.writer is not None else None,
            "missing_parts": self.missing_parts,
            "run_start_utc": self.run_start_utc,
            "missing_start_s": (
                None if self.missing_start_s is None else round(self.missing_start_s, 3)
            ),
        }


def broken_at(t: np.ndarray, v: np.ndarray, cuts: Sequence[float]) -> tuple[np.ndarray, ...]:
    """``t``, ``v`` with a NaN point at each of ``cuts`` that falls between two points (times
    in order): a line drawn through them breaks there."""
    if not cuts or t.size < 2:
        return t, v
    at = np.searchsorted(t, np.asarray(cuts, dtype=float))
    at = at[(at > 0) & (at < t.size)]
    return np.insert(t, at, np.nan), np.insert(v, at, np.nan)


GAP_STEPS = 3.0
GAP_MIN_S = 2.0
"""A series' line breaks where its time steps by more than :data:`GAP_STEPS` times its median
step and more than :data:`GAP_MIN_S` s (an outage, the recorder's gap, a pause): a line across
the hole would show a steady change that was never measured."""


def gap_cuts(t_s: np.ndarray) -> list[float]:
    """The middle of each hole in a series with times ``t_s`` (in order): a step longer than
    :data:`GAP_STEPS` times the median of its steps forward and than :data:`GAP_MIN_S`."""
    t = t_s[np.isfinite(t_s)]
    step = np.diff(t)
    forward = step[step > 0]
    if not forward.size:
        return []
    limit = max(GAP_STEPS * float(np.median(forward)), GAP_MIN_S)
    at = np.flatnonzero(step > limit)
    return ((t[at] + t[at + 1]) / 2).tolist()


def line_cuts(t_s: np.ndarray, jumps: Sequence[TimeJump]) -> list[float]:
    """Where a line through a series with times ``t_s`` breaks: at the log's time jumps and
    at the series' own holes (:func:`gap_cuts`)."""
    return [j.t_s for j in jumps] + gap_cuts(t_s)


def _floats(a: np.ndarray, ndigits: int) -> list[float | None]:
    return [round(float(x), ndigits) if math.isfinite(x) else None for x in a.tolist()]


def _arr(values: Iterable[float | None]) -> np.ndarray:
    return np.array([math.nan if v is None else float(v) for v in values], dtype=float)


# ---------------------------------------------------------------------------- reading


SAMPLE_ROWS = 16384
"""Rows the reader keeps of each series (:class:`_Sample`): a series of up to this many is
kept whole (the page is as if every record were kept); a longer one is thinned as it is read,
so that reading a recording of any length takes bounded memory."""

HOLD_WINDOW_S = 60.0
"""Hold marks older than this (s) before the newest are run-length compacted
(:class:`_HoldMarks`): the recorder's threads write out of order by far less."""


def _key_float(v: Any) -> float | None:
    """``v`` as a float for a sample's extremes, or None (not a finite number)."""
    if isinstance(v, (int, float)) and math.isfinite(v):
        return float(v)
    return None


class _Sample:
    """A bounded sample of a series' rows in file order: every ``stride``-th row from the
    first (the stride doubling whenever more than :data:`SAMPLE_ROWS` would be kept), the
    last row, and the rows holding the least and greatest finite value of each of ``keys``
    (the page's axes span the whole series). A series of up to :data:`SAMPLE_ROWS` rows is
    kept whole; at most ``SAMPLE_ROWS + 1 + 2 * len(keys)`` rows are ever held."""

    def __init__(self, *keys: Any) -> None:
        self.n = 0  # rows offered
        self.stride = 1
        self._limit = SAMPLE_ROWS
        self._kept: list[tuple[int, Any]] = []  # (row number, row)
        self._last: tuple[int, Any] | None = None
        self._keys = keys
        self._ends: list[list[tuple[float, int, Any] | None]] = [[None, None] for _ in keys]

    def add(self, row: Any) -> None:
        """Offer the next row."""
        i, self.n = self.n, self.n + 1
        self._last = (i, row)
        if i % self.stride == 0:
            self._kept.append(self._last)
            if len(self._kept) > self._limit:
                self.stride *= 2
                self._kept = [k for k in self._kept if k[0] % self.stride == 0]
        for key, ends in zip(self._keys, self._ends, strict=True):
            v = _key_float(key(row))
            if v is not None:
                if ends[0] is None or v < ends[0][0]:
                    ends[0] = (v, i, row)
                if ends[1] is None or v > ends[1][0]:
                    ends[1] = (v, i, row)

    def held(self) -> int:
        """Rows held now (at most ``SAMPLE_ROWS + 1 + 2 * len(keys)``)."""
        return len(self._kept) + 1 + 2 * len(self._keys) if self.n else 0

    def rows(self) -> list[Any]:
        """The kept rows, in file order."""
        kept = dict(self._kept)
        if self._last is not None:
            kept[self._last[0]] = self._last[1]
        kept.update((e[1], e[2]) for ends in self._ends for e in ends if e is not None)
        return [kept[i] for i in sorted(kept)]


class _HoldMarks:
    """Hold marks (t s, reason; "" = not holding), drawn as holds in time order (file order
    within a time, :func:`_timelines`). A mark after one of the same reason in that order
    changes nothing, so those older than :data:`HOLD_WINDOW_S` before the newest are dropped
    as the marks come: what is held is the reason changes and the last window."""

    def __init__(self) -> None:
        self.marks: list[tuple[float, str]] = []
        self._compacted = 0  # marks held after the last compaction

    def add(self, t_s: float, reason: str) -> None:
        """A mark: from ``t_s`` on, holding for ``reason`` ("": not holding)."""
        self.marks.append((t_s, reason))
        if len(self.marks) > self._compacted + 1024:
            self.marks.sort(key=lambda m: m[0])  # stable: file order within a time
            old_s = self.marks[-1][0] - HOLD_WINDOW_S
            out: list[tuple[float, str]] = []
            for m in self.marks:
                if not (m[0] < old_s and out and out[-1][1] == m[1]):
                    out.append(m)
            self.marks, self._compacted = out, len(out)


def _fix_error_key(raw: _Raw) -> Any:
    """A valid fix's distance from the true track in degrees (roughly: only to keep the
    sample's largest error), None without a true track."""

    def key(f: GpsFix) -> float | None:
        assert f.lat_deg is not None and f.lon_deg is not None  # a good fix's
        return raw.off_truth_deg(_fix_epoch(raw, f), f.lat_deg, f.lon_deg)

    return key


def _fix_epoch(raw: _Raw, f: GpsFix) -> float:
    """A fix's epoch (its UTC) on the log's time axis, the true track's clock: its UTC less
    the UTC of the log's time 0 (``raw.utc0``), else the time it arrived."""
    if f.utc is None or raw.utc0 is None:
        return f.t_s
    return (f.utc - raw.utc0).total_seconds()


def _continuous_lon(lon_deg: np.ndarray) -> np.ndarray:
    """A track's longitudes made continuous across the 180th meridian (values may leave
    +-180 by the track's extent), so that they interpolate; a track that does not cross it
    comes back as it is."""
    step = np.diff(lon_deg)
    if not np.any(np.abs(step) > 180.0):
        return lon_deg
    return lon_deg[0] + np.concatenate(([0.0], np.cumsum(wrap_deg(step))))


@dataclass
class _Raw:
    """What the panels draw of a log, gathered as it is read (times in the log's own s):
    bounded samples of each series (:class:`_Sample`), counts of the rest."""

    truth: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None  # t s, lat deg, lon deg
    fixes: _Sample = field(default_factory=lambda: _Sample(_t, _hdop, _sats))  # GpsFix
    good: _Sample = field(init=False)  # valid fixes with a finite position
    moving: _Sample = field(default_factory=lambda: _Sample(_t))  # valid fixes with a course
    # (t, satellites in view or None, HDOP)
    skies: _Sample = field(default_factory=lambda: _Sample(_c(0), _c(1), _c(2)))
    # telemetry's position estimate: (t, the run's own t s, lat deg, lon deg)
    est: _Sample = field(init=False)
    heading: _Sample = field(default_factory=lambda: _Sample(_c(0)))  # (t, heading deg)
    att: _Sample = field(default_factory=lambda: _Sample(_c(0)))  # (t, magnetic bearing deg)
    n_fixes: int = 0
    n_valid: int = 0  # valid fixes with a latitude
    first_dated: GpsFix | None = None  # the first fix with a UTC date (valid or not)
    n_skies: int = 0
    n_tel: int = 0
    nonfinite: int = 0  # positions that are NaN or infinite: skipped
    states: list[tuple[float, str, str, str]] = field(default_factory=list)  # t, old, new, why
    device_events: list[tuple[float, str, str, str]] = field(default_factory=list)
    # the recorder's gap events: (from t, to t, records lost, why), on the time axis
    gaps: list[tuple[float, float, int, str]] = field(default_factory=list)
    last_event: str = ""  # the event name of the last record read ("" for any other record)
    hold_marks: _HoldMarks = field(default_factory=_HoldMarks)
    t_first: float | None = None
    t_last: float = 0.0
    utc0: datetime | None = None  # wall-clock time of the log's time 0
    recorder_utc0: datetime | None = None  # a recording's time 0 by its recorder's clock
    # a recording's: check utc0 (the recorder's t_utc) against the first dated valid fix
    clock_check: bool = False
    clock_checked: bool = False
    wall_utc0: datetime | None = None  # the recorder's utc0 where the GPS's replaced it
    _truth_lon: tuple[np.ndarray, np.ndarray] | None = None  # truth's lon, and unwrapped

    def __post_init__(self) -> None:
        self.good = _Sample(_t, _lat, _lon, _fix_error_key(self))
        self.est = _Sample(_c(0), _c(2), _c(3), lambda r: self.off_truth_deg(r[1], r[2], r[3]))

    def off_truth_deg(self, t_s: Any, lat_deg: float, lon_deg: float) -> float | None:
        """Roughly how far a position at the run's time ``t_s`` is from the true track
        (degrees of latitude): which of a series is furthest. None without a true track."""
        if self.truth is None or not isinstance(t_s, (int, float)):
            return None
        tt, la, lo = self.truth
        if self._truth_lon is None or self._truth_lon[0] is not lo:
            self._truth_lon = (lo, _continuous_lon(lo))
        d_lat = lat_deg - float(np.interp(t_s, tt, la))
        d_lon = lon_deg - float(np.interp(t_s, tt, self._truth_lon[1]))
        if abs(d_lon) > 180.0:  # the short way round (a fix across the 180th meridian)
            d_lon = wrap_deg(d_lon)
        return math.hypot(d_lat, d_lon * math.cos(math.radians(lat_deg)))

    def add_fix(self, f: GpsFix) -> None:
        """A fix, into the series that draw it."""
        self.n_fixes += 1
        if self.first_dated is None and f.utc is not None:
            self.first_dated = f
        if self.clock_check and not self.clock_checked and f.valid and f.utc is not None:
            self.check_clock(f)
        self.fixes.add(f)
        if f.valid and f.lat_deg is not None:
            self.n_valid += 1
            if f.lon_deg is not None:
                if _finite(f.lat_deg, f.lon_deg):
                    self.good.add(f)
                else:
                    self.nonfinite += 1
        if f.valid and f.course_deg is not None:
            self.moving.add(f)

    def check_clock(self, f: GpsFix) -> None:
        """A recording's first dated valid fix ``f``: where the recorder's clock (its
        ``t_utc``, ``utc0``) disagrees with ``f``'s UTC by more than
        :data:`CLOCK_AGREE_S` (a robot without a real-time clock booted at 1970, a clock
        set while recording), the log's time 0 is dated by the fix instead (its UTC less
        the time it arrived), so that fixes are placed at their epochs on the log's own
        clock, and the start is the GPS's."""
        assert f.utc is not None
        self.clock_checked = True
        gps0 = f.utc - timedelta(seconds=f.t_s)
        if self.utc0 is None or abs((self.utc0 - gps0).total_seconds()) > CLOCK_AGREE_S:
            self.wall_utc0, self.utc0 = self.utc0, gps0

    def add_sky(self, s: GpsSky) -> None:
        """A sky report: its count of satellites in view and its HDOP."""
        self.n_skies += 1
        self.skies.add((s.t_s, len(s.satellites) if s.satellites else None, s.hdop))

    def add_tel(self, t_s: float, t_own_s: Any, d: dict[str, Any]) -> None:
        """A telemetry record's data ``d`` at ``t_s`` (``t_own_s``: on the true track's
        clock, the run's own): its position estimate and heading."""
        self.n_tel += 1
        lat, lon = d.get("filt_lat_deg"), d.get("filt_lon_deg")
        if isinstance(lat, (int, float)) and isinstance(lon, (int, float)):
            if _finite(lat, lon):
                self.est.add((t_s, t_own_s, float(lat), float(lon)))
            else:
                self.nonfinite += 1
        h = d.get("heading_deg")
        if isinstance(h, (int, float)):
            self.heading.add((t_s, h))

    def take_gps(self, other: _Raw) -> None:
        """``other``'s fixes (and its skies, if this has none) in place of this one's."""
        self.fixes, self.good, self.moving = other.fixes, other.good, other.moving
        if other.clock_checked:  # its fixes were placed by its utc0
            self.clock_checked, self.utc0, self.wall_utc0 = True, other.utc0, other.wall_utc0
        self.n_fixes, self.n_valid = other.n_fixes, other.n_valid
        self.nonfinite += other.nonfinite
        if not self.n_skies:
            self.skies, self.n_skies = other.skies, other.n_skies

    def held(self) -> int:
        """Rows and marks held now: bounded, however long the log (state changes and
        device events aside: the page draws every one)."""
        samples = (self.fixes, self.good, self.moving, self.skies, self.est, self.heading)
        return sum(s.held() for s in (*samples, self.att)) + len(self.hold_marks.marks)


def _t(f: GpsFix | GpsSky) -> float:
    return f.t_s


def _hdop(f: GpsFix) -> float | None:
    return f.hdop


def _sats(f: GpsFix) -> int | None:
    return f.sats_used


def _lat(f: GpsFix) -> float | None:
    return f.lat_deg


def _lon(f: GpsFix) -> float | None:
    return f.lon_deg


def _c(k: int) -> Any:
    """The ``k``-th column of a row."""
    return lambda row: row[k]


def _parse_utc(text: Any) -> datetime | None:
    if not isinstance(text, str) or not text:
        return None
    try:
        return datetime.fromisoformat(text)
    except ValueError:
        return None


LOST_COUNTS = frozenset(
    {
        "bad_lines",
        "truncated_lines",
        "checksum_failures",
        "framing_errors",
        "invalid_sentences",
        "nonfinite_positions",
        "bad_records",
        "truncated_truth_lines",
    }
)
"""The counts of :attr:`LogView.counts` that say input was skipped (``x6wd plot`` says so)."""


class _Decoding:
    """NMEA decoded into a :class:`_Raw`'s fixes and skies as it comes. ``order``: a plain
    log's lines (one a chunk), their times put in file order by it and its jumps dated by
    the receiver's UTC (:class:`_JumpDates`)."""

    def __init__(self, raw: _Raw, order: _FileOrder | None = None) -> None:
        from drivers.gps_nmea import GpsDecoder

        self.raw, self.order = raw, order
        self.decoder = GpsDecoder(emit_sentences=False)
        self.dates = _JumpDates(order.jumps) if order is not None else None
        self.line = 0
        self.t_last_s = 0.0

    def _keep(self, records: Iterable[Any]) -> None:
        for rec in records:
            if isinstance(rec, GpsFix):
                self.raw.add_fix(rec)
                if self.dates is not None:
                    self.dates.see(rec)
            elif isinstance(rec, GpsSky):
                self.raw.add_sky(rec)

    def feed(self, t_s: float, data: bytes) -> None:
        """The next chunk, received at ``t_s`` (the log's own s)."""
        self.line += 1
        if self.order is not None and self.dates is not None:
            t_s = self.order.place(t_s, self.line)
            if self.order.jumped is not None:
                # The epoch in progress is the last segment's: closed before the next one's
                # first sentence, whose date the decoder would otherwise give it (a cold
                # start's 23:59:50 on 2006-12-16 came out as 2010-09-30, the next RMC's day).
                self._keep(self.decoder.flush(self.t_last_s))
        self.t_last_s = t_s
        self.raw.t_first = t_s if self.raw.t_first is None else self.raw.t_first
        self._keep(self.decoder.feed(data, t_s))

    def close(self) -> dict[str, int]:
        """The last epoch decoded, the jumps dated; the decoder's error counts."""
        self._keep(self.decoder.flush(self.t_last_s))
        self.raw.t_last = max(self.raw.t_last, self.t_last_s)
        if self.order is not None and self.dates is not None:
            self.dates.date(self.order.jumps)
        c = self.decoder.counters
        return {
            "checksum_failures": c.checksum_failures,
            "framing_errors": c.framing_errors,
            "invalid_sentences": c.invalid_fields,
        }


class _FileOrder:
    """A log's own time made to run forward in file order (an NMEA log's time of day, a
    recording's t_mono): where it goes back by more than ``jitter_s``, or forward by more
    than :data:`TIME_JUMP_S`, the next line is placed one epoch (the median of the recent
    steps) after the previous one and a :class:`TimeJump` appended to :attr:`jumps`. A log
    without jumps keeps its times."""

    def __init__(self, jumps: list[TimeJump], jitter_s: float = 0.0) -> None:
        self.jumps = jumps
        self.offset_s = 0.0  # axis time - the log's own time, in the current segment
        self._jitter_s = jitter_s
        self._prev = self._last = math.nan
        self._steps: deque[float] = deque(maxlen=64)
        self.jumped: TimeJump | None = None  # the jump the last line placed made, if any

    def place(self, t: float, line: int, file: str = "") -> float:
        """The time axis's time of the log's own time ``t`` at ``line`` (of ``file``)."""
        step = t - self._prev
        self.jumped = None
        if step < -self._jitter_s or step > TIME_JUMP_S:
            gap = statistics.median(self._steps) if self._steps else 1.0
            self.offset_s = self._last + gap - t
            self.jumped = TimeJump(self._last + gap / 2, line, step, file=file,
                                   t_before_s=self._last, t_after_s=t + self.offset_s)  # fmt: skip
            self.jumps.append(self.jumped)  # kept or not (a JumpList keeps a bounded few)
        elif step > 0:
            self._steps.append(step)
        self._prev, self._last = t, t + self.offset_s
        return self._last


class _JumpDates:
    """A plain log's time jumps dated as its fixes come: each jump's receiver UTC either
    side, of the last dated fix at the time before it (``t_before_s``) and of the first at
    the time after it (``t_after_s``). A side whose time came from a sentence that made no
    fix (a damaged one) is left unsaid, not taken from a later fix the step was not measured
    to. Held: the fixes of the last few times and of the kept jumps' times (``jumps``: those
    of a :class:`JumpList`, a bounded few; a jump it drops is not dated)."""

    _RECENT = 64  # times: a jump's time before is the newest line's when it is found

    def __init__(self, jumps: list[TimeJump]) -> None:
        self.at: dict[float, list[GpsFix]] = {}  # t -> [first, last] dated fix at t
        self._jumps = jumps
        self._version = -1
        self._wanted: set[float] = set()

    def _update_wanted(self) -> None:
        """The kept jumps' times wanted; the fixes of times no longer wanted forgotten."""
        version = getattr(self._jumps, "version", len(self._jumps))
        if version == self._version:
            return
        self._version = version
        self._wanted = {t for j in self._jumps for t in (j.t_before_s, j.t_after_s)}
        recent = set(list(self.at)[-self._RECENT :])
        for t in [t for t in self.at if t not in self._wanted and t not in recent]:
            del self.at[t]

    def see(self, fix: GpsFix) -> None:
        """The next fix the decoder made."""
        if fix.utc is None:
            return
        ends = self.at.get(fix.t_s)
        if ends is not None:
            ends[1] = fix
            return
        self._update_wanted()
        self.at[fix.t_s] = [fix, fix]
        if len(self.at) > self._RECENT + len(self._wanted):
            old = next((t for t in self.at if t not in self._wanted), None)
            if old is not None:
                del self.at[old]

    def date(self, jumps: Sequence[TimeJump]) -> None:
        """Each of ``jumps``' before_utc and after_utc."""
        for j in jumps:
            before, after = self.at.get(j.t_before_s), self.at.get(j.t_after_s)
            j.before_utc = _utc_text(before[1]) if before is not None else ""
            j.after_utc = _utc_text(after[0]) if after is not None else ""


def _utc_text(fix: GpsFix) -> str:
    assert fix.utc is not None
    return _utc_str(fix.utc)


def _utc_str(utc: datetime) -> str:
    return utc.strftime("%Y-%m-%d %H:%M:%S.%f").rstrip("0").rstrip(".")


def _record_utc(line: bytes) -> str:
    """A recorder line's t_utc as a jump states it ("" when it has none)."""
    try:
        utc = _parse_utc(json.loads(line).get("t_utc"))
    except (ValueError, UnicodeDecodeError, AttributeError):
        return ""
    return _utc_str(utc) if utc is not None else ""


_SKIP_TYPES = frozenset({b"motor", b"odometry"})
"""Record types no panel needs (half of a recording's lines): skipped before JSON decoding.
A hold's reason is in the state changes and telemetry; a motor command is recorded only
when it changes, so it adds nothing within a hold."""
_TYPE_KEY = b'"type":"'
_T_KEY = b'{"t_mono":'


def _lines(path: Path, stats: ReadStats) -> Iterator[tuple[str, int, bytes, bytes]]:
    """(part, line number, type, raw line) of every line of a recording's remaining parts
    (part: its name, "" for ``path`` itself); the type read from the recorder's key order
    without decoding the line (b"" when it is not where the recorder writes it: the line is
    then decoded to find out)."""
    parts = recording_parts(path)
    if not parts:
        raise DeviceUnavailable(f"cannot open recording {path}: no such file")
    for part in parts:
        try:
            f = open(part, "rb")  # noqa: SIM115
        except OSError as exc:
            raise DeviceUnavailable(f"cannot open recording {part}: {exc}") from exc
        name = "" if part == path else part.name
        with f:
            for number, line in enumerate(f, start=1):
                if not line.strip():
                    stats.blank_lines += 1
                    continue
                k = line.find(_TYPE_KEY, 0, 120)
                kind = line[k + 8 : line.find(b'"', k + 8)] if k >= 0 else b""
                yield name, number, kind, line


def _decode_line(line: bytes, stats: ReadStats) -> dict[str, Any] | None:
    """One recorder line as its dict (t_mono, t_utc, type, data), or None, counted as the
    recorder's reader counts: a cut last line (no newline) as truncated, else as bad."""
    try:
        obj = json.loads(line)
        ok = (
            isinstance(obj, dict)
            and isinstance(obj.get("t_mono"), (int, float))
            and not isinstance(obj.get("t_mono"), bool)
            and isinstance(obj.get("data"), dict)
            and isinstance(obj.get("type"), str)
        )
    except (ValueError, UnicodeDecodeError):
        ok = False
    if not ok:
        if line.endswith(b"\n"):
            stats.bad_lines += 1
        else:
            stats.truncated += 1
        return None
    stats.records += 1
    return obj


def _read_recording(path: Path, raw: _Raw, jumps: list[TimeJump]) -> tuple[ReadStats, int, int]:
    """Read a recording's records into ``raw``, its times in file order (its time jumps
    appended to ``jumps``); the reader's counts, the fix and sky records skipped as not
    fitting their type, and those drawn without an unknown field. A recording of the
    sentences only (no fix records) has them decoded as the daemon would have: as they
    come, until a fix record shows they are not needed."""
    stats = ReadStats()
    bad_records = unknown = 0
    side: _Decoding | None = None  # the sentences decoded while no fix record was seen
    order = _FileOrder(jumps, RECORDING_JITTER_S)
    prev_line = b""

    def at(t: float, part: str, number: int, line: bytes) -> float:
        """``t`` placed on the time axis; a jump there dated by the recorder's t_utc."""
        nonlocal prev_line
        t = order.place(t, number, part)
        if order.jumped is not None:
            order.jumped.before_utc = _record_utc(prev_line)
            order.jumped.after_utc = _record_utc(line)
        prev_line = line
        raw.t_first = t if raw.t_first is None else raw.t_first
        raw.t_last = max(raw.t_last, t)
        return t

    for part, number, kind_b, line in _lines(path, stats):
        skip = kind_b in _SKIP_TYPES or (
            kind_b == b"nmea" and raw.n_fixes > 0 and line.endswith(b"}\n")  # not needed
        )
        if skip and line.startswith(_T_KEY) and raw.t_first is not None:
            try:
                t_own = float(line[len(_T_KEY) : line.index(b",")])
            except ValueError:
                stats.bad_lines += 1
                continue
            stats.records += 1
            raw.last_event = ""
            at(t_own, part, number, line)
            continue
        obj = _decode_line(line, stats)
        raw.last_event = ""
        if obj is None:
            continue
        t_own, kind, d = float(obj["t_mono"]), obj["type"], obj["data"]
        if kind == "event" and isinstance(d.get("event"), str):
            raw.last_event = d["event"]
        if raw.t_first is None:
            utc = _parse_utc(obj.get("t_utc"))
            if utc is not None:
                raw.utc0 = raw.recorder_utc0 = utc - timedelta(seconds=t_own)
        # A record's data are drawn at the record's time: the recorder stamps it with the
        # data's own time (t_s), so the two differ only where the axis moved a segment.
        t = at(t_own, part, number, line)
        if kind == "attitude":
            b = d.get("bearing_deg")
            if isinstance(b, (int, float)) and d.get("valid", True):
                raw.att.add((t, float(b)))
        elif kind == "telemetry":
            # the run's own time: on the true track's clock, for the error
            raw.add_tel(t, d.get("t_s", t_own), d)
            raw.hold_marks.add(t, str(d.get("hold_reason") or ""))
        elif kind == "state":
            old, new, why = str(d.get("old", "")), str(d.get("new", "")), str(d.get("reason", ""))
            raw.states.append((t, old, new, why))
            if new == NavState.HOLD:
                raw.hold_marks.add(t, why.removeprefix("state: ") or "hold")
            elif new in _NAV_STATES and not why.startswith("mode:"):
                raw.hold_marks.add(t, "")
        elif kind in ("fix", "sky"):
            rec = Record(t, "", kind, d)
            try:
                typed = decode_record(rec)
            except ParseError:  # a field missing or of the wrong type: skipped, counted
                bad_records += 1
                continue
            # a newer recorder's extra field: the record is drawn, the field counted
            unknown += bool(unknown_fields(rec))
            assert isinstance(typed, (GpsFix, GpsSky))
            if typed.t_s != t:
                typed = replace(typed, t_s=t)
            if isinstance(typed, GpsFix):
                raw.add_fix(typed)
                side = None  # the sentences are not needed
            else:
                raw.add_sky(typed)
        elif kind == "nmea" and not raw.n_fixes:
            text = d.get("text")
            if isinstance(text, str):
                side = side or _Decoding(
                    _Raw(truth=raw.truth, utc0=raw.utc0, clock_check=raw.clock_check)
                )
                side.feed(t, text.encode("utf-8", "replace") + b"\r\n")
        elif kind == "event" and d.get("event") == "device":
            raw.device_events.append(
                (t, str(d.get("device", "")), str(d.get("new", "")), str(d.get("message", "")))
            )
        elif kind == "event" and d.get("event") == GAP_EVENT:
            # written when the recording goes on: it ends here, and began its length before
            t0, t1, lost = d.get("from_t_mono"), d.get("to_t_mono", t_own), d.get("records_lost")
            length = t1 - t0 if _number(t0) and _number(t1) and t1 >= t0 else 0.0
            n = lost if _number(lost) else 0
            raw.gaps.append((t - length, t, int(n), str(d.get("error", ""))))
    if side is not None:
        side.close()
        raw.take_gps(side.raw)
    return stats, bad_records, unknown


def _number(v: Any) -> bool:
    """A finite JSON number (not a flag)."""
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def _read_truth(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """(t s, lat deg, lon deg, torn last lines: 0 or 1) of a true track CSV with columns
    t_s, lat, lon, read a line at a time (24 bytes a row held). A last line without its
    newline that does not read (a run that lost power while writing) is skipped and counted,
    as a recording's is; any other bad row is a :class:`ParseError` naming its line."""
    cut = False  # the line read last has no newline: the file's last, cut

    def lines(f: Iterable[str]) -> Iterator[str]:
        nonlocal cut
        for line in f:
            cut = not line.endswith("\n")
            yield line

    rows = array("d")  # t_s, lat, lon of each row
    torn = 0
    try:
        require_regular(path)  # /dev/zero has no line end: one endless line
        with open(path, newline="", encoding="utf-8") as f:
            reader = csv.DictReader(lines(f))
            if not {"t_s", "lat", "lon"} <= set(reader.fieldnames or ()):
                raise ParseError(
                    f"{path} line 1: a true track needs columns t_s, lat, lon, "
                    f"got {', '.join(reader.fieldnames or ()) or 'nothing'}"
                )
            for r in reader:
                try:
                    if None in r.values() and cut:
                        raise ValueError("columns missing")  # cut: its numbers may be cut too
                    text = (r["t_s"], r["lat"], r["lon"])
                    row = (float(text[0]), float(text[1]), float(text[2]))
                    if out_of_range := _truth_row_problem(row, text):
                        if cut:
                            torn += 1  # the last line, cut while written
                            continue
                        raise ParseError(f"{path} line {reader.line_num}: {out_of_range}")
                    rows.extend(row)
                except (TypeError, ValueError) as exc:  # TypeError: a short row's missing value
                    if cut:
                        torn += 1  # the last line, cut while written
                        continue
                    raise ParseError(
                        f"{path} line {reader.line_num}: a true track needs numbers in t_s, "
                        f"lat, lon ({exc})"
                    ) from exc
    except (OSError, UnicodeDecodeError) as exc:
        raise DeviceUnavailable(f"cannot open true track {path}: {exc}") from exc
    a = np.frombuffer(rows, dtype=float).reshape(-1, 3)
    if len(a) < 2 or np.any(np.diff(a[:, 0]) < 0):
        raise ParseError(f"{path}: a true track needs at least two rows in time order")
    t, lat, lon = (np.ascontiguousarray(a[:, k]) for k in range(3))
    return t, lat, lon, torn


_TRUTH_LIMITS = (("t_s", math.inf), ("lat", 90.0), ("lon", 180.0))
"""A true track's columns and the largest magnitude each may have (degrees for lat, lon)."""


def _truth_row_problem(row: tuple[float, float, float], text: tuple[str, str, str]) -> str:
    """What is wrong with a true track row's numbers ("" when nothing): each must be finite,
    lat within [-90, 90] and lon within [-180, 180] degrees. ``text``: the row's numbers as
    written, as said (180.00001 is not "180")."""
    for (name, limit), v, written in zip(_TRUTH_LIMITS, row, text, strict=True):
        if not math.isfinite(v):
            return f"a true track needs finite numbers, got {name} {written.strip()}"
        if abs(v) > limit:
            return (
                f"a true track's {name} must be within [-{limit:g}, {limit:g}] deg,"
                f" got {written.strip()}"
            )
    return ""


def _missing_parts(path: Path) -> tuple[list[str], datetime | None]:
    """The names of a recorder's run's parts that are gone (``path``: any remaining part of a
    run named ``x6wd-<UTC>...jsonl``; retention deletes the oldest part first), and, when its
    first part is gone, the run's start as its name gives it (UTC, to the second)."""
    parts = set(recording_parts(path))
    files = [f for f in list_recordings(path.parent) if f.path in parts]
    have = {f.part for f in files}
    gone = [n for n in range(files[-1].part) if n not in have] if files else []
    if not gone:
        return [], None
    stem = files[0].path.name.removesuffix(".jsonl").removesuffix(f".{files[0].part}")
    names = [f"{stem}.{n}.jsonl" if n else f"{stem}.jsonl" for n in gone]
    start = None
    if gone[0] == 0:
        start = datetime.strptime(files[0].run[0], "%Y%m%dT%H%M%SZ").replace(tzinfo=UTC)
    return names, start


def missing_parts_note(view: LogView) -> str:
    """What the page and ``x6wd plot`` say of a run whose parts are gone ("" when none is)."""
    if not view.missing_parts:
        return ""
    n = len(view.missing_parts)
    text = f"part{'s' if n > 1 else ''} {', '.join(view.missing_parts)} gone (retention?)"
    if view.run_start_utc:  # the first part: the run's start is not drawn
        lost = view.missing_start_s
        how_long = f"about {_duration(lost)}" if lost is not None else "a time unknown"
        text += (
            f": the run began at {view.run_start_utc} (its name), {how_long} before the first "
            "record read, and that start is not drawn; duration and start (UTC) are those of "
            "the parts read"
        )
    return text


SIM_NMEA_NAME = "gps.nmea"
"""The NMEA log ``x6wd sim`` writes beside its recording and ``truth.csv``."""


def default_truth(recording: Path) -> Path | None:
    """The simulator's true track next to a recording or its ``gps.nmea`` (``truth.csv``),
    or None."""
    p = recording.with_name("truth.csv")
    return p if p.is_file() else None


def load(path: Path, *, truth: Path | None = None, rate_hz: float = 1.0) -> LogView:
    """Read a recording (.jsonl, all its rotated parts) or a plain NMEA log into the panels'
    data. ``truth``: a true track CSV (t_s, lat, lon; default: ``truth.csv`` next to a
    recording or to ``x6wd sim``'s ``gps.nmea``). ``rate_hz``: epochs per second for NMEA
    logs without sentence times."""
    path = Path(path)
    raw = _Raw()
    view = LogView(path=path, kind="recording" if is_recording(path) else "NMEA log")
    if truth is None and (view.kind == "recording" or path.name == SIM_NMEA_NAME):
        truth = default_truth(path)  # (a gps.nmea's too: x6wd gap reads it, an outside audit)
    # read first (the reader keeps each series' furthest from it), said after the log's own
    # errors as before
    torn, truth_error, run_start = 0, None, None
    if truth is not None:
        try:
            *tt, torn = _read_truth(truth)
            raw.truth = (tt[0], tt[1], tt[2])
        except X6wdError as exc:
            truth_error = exc
    if view.kind == "recording":
        raw.clock_check = True
        # the lock is tested before reading: held then and no end record read -> still being
        # written (a writer that finishes meanwhile wrote its end record, read here); free
        # then -> the file was final when read (tested after reading, a run finishing in
        # between read as cut short)
        writer = recording_writer(path)
        stats, bad_records, unknown = _read_recording(path, raw, view.jumps)
        view.counts = {
            "records": stats.records,
            "bad_lines": stats.bad_lines,
            "truncated_lines": stats.truncated,
            "bad_records": bad_records,
            "records_with_unknown_fields": unknown,
        }
        if raw.last_event not in END_EVENTS:
            # no end record: still being written (a recorder held it), else cut short
            view.writer = writer
        view.cut_short = raw.last_event not in END_EVENTS and view.writer is None
        view.missing_parts, run_start = _missing_parts(path)
    else:
        decoding = _Decoding(raw, _FileOrder(view.jumps))
        for t_s, data in nmea_file_chunks(path, rate_hz):
            decoding.feed(t_s, data)
        view.counts = decoding.close()
        # time 0 dated by the first dated fix of the first segment, back along the log's
        # time: a GGA before the first RMC (no date yet), or untimed epochs, start undated
        first_jump = view.jumps[0].t_s if view.jumps else math.inf
        dated = raw.first_dated
        if dated is not None and dated.utc is not None and dated.t_s < first_jump:
            raw.utc0 = dated.utc - timedelta(seconds=dated.t_s)
    if not raw.n_fixes and not raw.n_tel and not raw.n_skies:
        raise ParseError(
            f"{path}: no GPS fixes, sky reports or telemetry: nothing to plot (x6wd plot reads"
            " x6wd recordings and NMEA logs)"
        )
    if truth_error is not None:
        raise truth_error
    t0 = raw.t_first or 0.0
    view.duration_s = raw.t_last - t0
    if run_start is not None:
        view.run_start_utc = run_start.isoformat()
    if run_start is not None and raw.recorder_utc0 is not None:
        # the run's name is its start by the recorder's clock, to the second (rounded down)
        missing = (raw.recorder_utc0 + timedelta(seconds=t0) - run_start).total_seconds()
        view.missing_start_s = missing if missing >= 0 else None
    for j in view.jumps:  # read on the log's own clock (a recording's t_mono): onto the axis
        j.t_s, j.t_before_s, j.t_after_s = j.t_s - t0, j.t_before_s - t0, j.t_after_s - t0
    if raw.utc0 is not None:
        view.start_utc = (raw.utc0 + timedelta(seconds=t0)).isoformat()
    if raw.wall_utc0 is not None and raw.utc0 is not None:
        view.recorder_clock = (raw.wall_utc0 + timedelta(seconds=t0)).isoformat()
        view.recorder_clock_off_s = round((raw.wall_utc0 - raw.utc0).total_seconds(), 3)
    view.counts.update(
        fixes=raw.n_fixes,
        valid_fixes=raw.n_valid,
        sky_reports=raw.n_skies,
        telemetry=raw.n_tel,
        state_changes=len(raw.states),
    )
    _track_and_error(view, raw, t0, torn if truth is not None else None)
    _gps_quality(view, raw, t0)
    _headings(view, raw, t0)
    _timelines(view, raw, t0)
    return view


def _finite(*values: Any) -> bool:
    return all(math.isfinite(v) for v in values)


def _track_and_error(view: LogView, raw: _Raw, t0: float, torn: int | None) -> None:
    """The map's tracks and the error panel; ``torn``: the true track's cut last lines
    (None: no true track)."""
    good: list[GpsFix] = raw.good.rows()
    est: list[tuple[float, Any, float, float]] = raw.est.rows()
    # A NaN or infinite position (a foreign or hand-edited file: the recorder writes none)
    # is skipped and counted, not allowed to refuse the whole file in the plane's to_xy.
    view.counts["nonfinite_positions"] = raw.nonfinite
    tt = raw.truth
    if torn is not None:
        view.counts["truncated_truth_lines"] = torn
    if good:
        origin = (good[0].lat_deg, good[0].lon_deg)
    elif tt is not None:
        origin = (float(tt[1][0]), float(tt[2][0]))
    elif est:
        origin = (est[0][2], est[0][3])
    else:
        view.missing["track"] = "no valid fix and no position estimate in the log"
        view.missing["error"] = view.missing["track"]
        return
    assert origin[0] is not None and origin[1] is not None
    view.origin_deg = (float(origin[0]), float(origin[1]))
    plane = LocalTangentPlane(*view.origin_deg)

    def xy(lat: np.ndarray, lon: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        x, y = plane.to_xy(lat, lon)
        return np.asarray(x, dtype=float), np.asarray(y, dtype=float)

    if tt is not None:
        # drawn: up to SAMPLE_ROWS rows whole, a longer track by a stride and its extremes
        lat, lon = tt[1], tt[2]
        ends = [a.argmin() for a in (lat, lon)] + [a.argmax() for a in (lat, lon)]
        drawn = np.union1d(thinned_indices(len(lat), SAMPLE_ROWS), ends)
        view.track["true track"] = xy(lat[drawn], lon[drawn])
    fx_e = fx_n = np.zeros(0)
    if good:
        fx_e, fx_n = xy(_arr(f.lat_deg for f in good), _arr(f.lon_deg for f in good))
        view.track["GPS fixes"] = (fx_e, fx_n)
    if est:
        es_e, es_n = xy(_arr(r[2] for r in est), _arr(r[3] for r in est))
        # no line across a time jump or a hole on the map either (it would join two sessions)
        t_est = _arr(r[0] for r in est) - t0
        cuts = line_cuts(t_est, view.jumps)
        view.track["position estimate"] = (
            broken_at(t_est, es_e, cuts)[1],
            broken_at(t_est, es_n, cuts)[1],
        )
    if tt is None:
        view.missing["error"] = (
            "no true track: only `x6wd sim` writes one (truth.csv next to its recording and "
            "its gps.nmea); a HIL or real run has none (--truth FILE for a true track of your "
            "own)"
        )
        return
    tr_t, (tr_e, tr_n) = tt[0], xy(tt[1], tt[2])
    if good:
        # a fix is the receiver's position at its epoch (its UTC), not at its arrival
        ep = _arr(_fix_epoch(raw, f) for f in good)
        err = np.hypot(fx_e - np.interp(ep, tr_t, tr_e), fx_n - np.interp(ep, tr_t, tr_n))
        view.error.append(Series("GPS fix", _arr(f.t_s for f in good) - t0, err))
    if est:
        te = _arr(r[1] for r in est)
        err = np.hypot(es_e - np.interp(te, tr_t, tr_e), es_n - np.interp(te, tr_t, tr_n))
        view.error.append(Series("position estimate", t_est, err))


def _gps_quality(view: LogView, raw: _Raw, t0: float) -> None:
    fixes: list[GpsFix] = raw.fixes.rows()
    if fixes:
        t = _arr(f.t_s for f in fixes) - t0
        view.hdop.append(Series("HDOP (fix)", t, _arr(f.hdop for f in fixes)))
        view.satellites.append(Series("used (fix)", t, _arr(f.sats_used for f in fixes)))
    skies: list[tuple[float, int | None, float | None]] = raw.skies.rows()
    if skies:
        t = _arr(s[0] for s in skies) - t0
        view.satellites.append(Series("in view", t, _arr(s[1] for s in skies)))
        if not fixes:
            view.hdop.append(Series("HDOP (sky)", t, _arr(s[2] for s in skies)))
    if not view.hdop or all(np.all(np.isnan(s.v)) for s in view.hdop):
        view.missing["hdop"] = "the receiver reported no HDOP (no GGA or GSA sentences)"
    if not view.satellites or all(np.all(np.isnan(s.v)) for s in view.satellites):
        view.missing["satellites"] = "the receiver reported no satellite counts (no GGA or GSV)"


def _headings(view: LogView, raw: _Raw, t0: float) -> None:
    if tel := raw.heading.rows():
        h = np.array(tel, dtype=float).reshape(-1, 2)
        view.heading.append(
            Series("heading (true, navigation)", h[:, 0] - t0, np.asarray(wrap360(h[:, 1])))
        )
    if att := raw.att.rows():
        a = np.array(att)
        view.heading.append(Series("compass (magnetic)", a[:, 0] - t0, a[:, 1]))
    if moving := raw.moving.rows():
        view.heading.append(
            Series(
                "GPS course (true)",
                _arr(f.t_s for f in moving) - t0,
                _arr(f.course_deg for f in moving),
            )
        )
    if not view.heading:
        view.missing["heading"] = "no heading: no telemetry, compass samples or GPS course"


def _lane_intervals(
    changes: Sequence[tuple[float, str, str]], lane: str, t_end: float
) -> list[Interval]:
    """Intervals of a lane from its changes (t, old, new): the first ``old`` from time 0."""
    out: list[Interval] = []
    if not changes:
        return out
    cur_t, cur = 0.0, changes[0][1]
    for t, _old, new in changes:
        if new == cur:
            continue
        # a state of no duration stays (ARRIVED lasts one step): drawn as a thin mark
        if t > cur_t or cur_t > 0.0:
            out.append(Interval(lane, cur_t, t, cur))
        cur_t, cur = t, new
    out.append(Interval(lane, cur_t, t_end, cur))
    return out


_HOLD_DEVICES = (
    ("motor link", "motors"),
    ("gps ", "gps"),
    ("no valid fix", "gps"),
    ("fix stale", "gps"),
    ("compass ", "compass"),
    ("attitude invalid", "compass"),
    ("attitude stale", "compass"),
)
"""Hold reasons (the controller's words) that name a device: a reader's report ("gps
stale", "compass disconnected", "motor link lost", "gps back, waiting ...") or what the
controller saw of the data itself (no valid fix, a stale fix, an out-of-range attitude)."""


def _device_of(reason: str) -> str | None:
    """The device a hold reason names (:data:`_HOLD_DEVICES`), or None; None too for a
    stale-sensor hold the runner marks as the control loop's own lateness ("the control loop
    itself was X s late: CPU starved?"): the device's samples were on time."""
    if "the control loop itself was" in reason:
        return None
    for prefix, dev in _HOLD_DEVICES:
        if reason.startswith(prefix):
            return dev
    return None


def _timelines(view: LogView, raw: _Raw, t0: float) -> None:
    t_end = raw.t_last - t0
    if view.kind != "recording":
        why = "an NMEA log holds only the receiver's output"
        for p in ("states", "holds", "faults"):
            view.missing[p] = why
        return
    mode_ch, nav_ch = [], []
    for t, old, new, why in raw.states:
        if why.startswith("mode:") or (
            not why.startswith("state:") and new in _MODES - _NAV_STATES
        ):
            mode_ch.append((t - t0, old, new))
        elif new in _NAV_STATES or why.startswith("state:"):
            nav_ch.append((t - t0, old, new))
    view.states = _lane_intervals(mode_ch, "mode", t_end) + _lane_intervals(
        nav_ch, "navigation", t_end
    )
    if not view.states:
        view.missing["states"] = "no state changes recorded"

    # Holds: a change into HOLD names its reason ("state: <why>"); the reason may change
    # during a hold, which telemetry (hold_reason, about 1 Hz) shows. In time order (file
    # order within a time: the controller's), each mark says "holding for <why>" or not.
    marks = sorted(raw.hold_marks.marks, key=lambda m: m[0])  # stable: file order within a time
    cur: tuple[float, str] | None = None
    for t, reason in [(t - t0, r) for t, r in marks] + [(t_end, "")]:
        if cur is not None and reason != cur[1]:
            if t > cur[0]:
                view.holds.append(Interval("hold", cur[0], t, cur[1]))
            cur = None
        if cur is None and reason:
            cur = (t, reason)
    if not view.holds:
        view.missing["holds"] = "no holds"

    if raw.device_events:
        # a device is at fault from a change to any state but "connected" until the next
        # change (degraded, stale, disconnected, reconnecting: each its own interval)
        down: dict[str, tuple[float, str, str]] = {}  # device -> (since s, state, message)
        for t, dev, new, msg in raw.device_events:
            if dev in down and down[dev][1] != new:
                since, state, first = down.pop(dev)
                view.faults.append(Interval(dev, since, t - t0, state, first))
            if new != "connected" and dev not in down:
                down[dev] = (t - t0, new, msg)
        for dev, (since, state, first) in down.items():
            view.faults.append(Interval(dev, since, t_end, state, first))
    # a device no reader reported on (an older recording, a simulator's GPS outage, data
    # the controller refused itself): the holds that name it
    reported = {dev for _t, dev, _new, _msg in raw.device_events}
    for h in view.holds:
        named = _device_of(h.label)
        if named is not None and named not in reported:
            view.faults.append(Interval(named, h.t0_s, h.t1_s, h.label))
    # the recording's own holes: what happened then is not in it
    for t0_s, t1_s, lost, why in raw.gaps:
        gap = RecordingGap(t0_s - t0, t1_s - t0, lost, why)
        view.gaps.append(gap)
        detail = f"{lost} records lost" + (f": {why}" if why else "")
        view.faults.append(Interval("recorder", gap.t0_s, gap.t1_s, "gap", detail))
    if not view.faults:
        view.missing["faults"] = "no device faults"


# ---------------------------------------------------------------------------- SVG / HTML

_W, _H, _ML, _MR, _MT, _MB = 900, 190, 56, 16, 24, 28
COLORS = ("#1f77b4", "#d62728", "#2ca02c", "#ff7f0e", "#9467bd", "#8c564b", "#e377c2")
STATE_COLORS = {
    "IDLE": "#c7c7c7",
    "RUNNING": "#98df8a",
    "PAUSED": "#ffbb78",
    "MANUAL": "#aec7e8",
    "DONE": "#dbdb8d",
    "STRAIGHT": "#98df8a",
    "TURN_LEFT": "#aec7e8",
    "TURN_RIGHT": "#c5b0d5",
    "ARRIVED": "#17becf",
    "MISSION_DONE": "#dbdb8d",
    "HOLD": "#ff9896",
}


def nice_ticks(lo: float, hi: float, n: int = 6) -> list[float]:
    """About ``n`` round tick values (1, 2, 5 x 10^k steps) covering [lo, hi]."""
    if not (math.isfinite(lo) and math.isfinite(hi)) or hi <= lo:
        return [lo] if math.isfinite(lo) else []
    raw_step = (hi - lo) / max(n - 1, 1)
    mag = 10 ** math.floor(math.log10(raw_step))
    step = next(m * mag for m in (1, 2, 5, 10) if m * mag >= raw_step)
    first = math.ceil(lo / step - 1e-9) * step
    out = []
    x = first
    while x <= hi + step * 1e-9:
        out.append(round(x, 10))
        x += step
    return out


def _fmt(v: float) -> str:
    return f"{v:g}" if abs(v) < 1e6 else f"{v:.3g}"


def _esc(s: str) -> str:
    return html.escape(s, quote=True)


def _thin(t: np.ndarray, v: np.ndarray, limit: int = MAX_POINTS) -> tuple[np.ndarray, np.ndarray]:
    idx = thinned_indices(len(t), limit)
    return t[idx], v[idx]


def _polylines(xs: np.ndarray, ys: np.ndarray, color: str, extra: str = "") -> str:
    """Polylines through the finite points (a NaN breaks the line)."""
    out, pts = [], []
    for x, y in zip(xs.tolist(), ys.tolist(), strict=True):
        if math.isfinite(x) and math.isfinite(y):
            pts.append(f"{x:.1f},{y:.1f}")
        elif pts:
            out.append(pts)
            pts = []
    if pts:
        out.append(pts)
    return "".join(
        f'<polyline fill="none" stroke="{color}" stroke-width="1.4" {extra}points="{" ".join(p)}"/>'
        if len(p) > 1
        else f'<circle cx="{p[0].split(",")[0]}" cy="{p[0].split(",")[1]}" r="2" fill="{color}"/>'
        for p in out
    )


def _legend(items: Sequence[tuple[str, str]], x: float, y: float) -> str:
    """One row of legend entries from ``x`` along the top margin at ``y``."""
    parts = []
    for label, color in items:
        parts.append(
            f'<rect x="{x:.0f}" y="{y - 5}" width="14" height="3" fill="{color}"/>'
            f'<text x="{x + 18:.0f}" y="{y}" font-size="11">{_esc(label)}</text>'
        )
        x += 30 + 6.2 * len(label)
    return "".join(parts)


def _legend_rows(items: Sequence[tuple[str, str]], x0: float, x1: float) -> tuple[str, int]:
    """Legend entries in rows from ``x0`` wrapping before ``x1``, the first row in the top
    margin; (svg, rows)."""
    parts, x, row = [], x0, 0
    for label, color in items:
        width = 30 + 6.2 * len(label)
        if x > x0 and x + width > x1:
            x, row = x0, row + 1
        y = _MT - 8 + 14 * row
        parts.append(
            f'<rect x="{x:.0f}" y="{y - 8}" width="10" height="10" fill="{color}"/>'
            f'<text x="{x + 14:.0f}" y="{y}" font-size="11">{_esc(label)}</text>'
        )
        x += width
    return "".join(parts), row + 1


def _svg_open(pid: str, w: int, h: int, axes: dict[str, float], top: int = _MT) -> str:
    data = "".join(f' data-{k}="{v:.6g}"' for k, v in axes.items())
    return (
        f'<svg id="svg-{pid}" width="{w}" height="{h}" '
        f'viewBox="0 0 {w} {h}" font-family="sans-serif"{data} '
        f'data-plot-left="{_ML}" data-plot-right="{w - _MR}" data-plot-top="{top}" '
        f'data-plot-bottom="{h - _MB}">'
    )


def _x_grid(x0: float, x1: float, pw: float, top: float, h: int) -> list[str]:
    """Vertical grid lines from ``top`` (px) down to the axis, with their tick labels, for an
    x range [x0, x1] drawn ``pw`` px wide."""
    parts = []
    for tx in nice_ticks(x0, x1, 10):
        px = _ML + (tx - x0) / (x1 - x0) * pw
        parts.append(
            f'<line x1="{px:.1f}" y1="{top}" x2="{px:.1f}" y2="{h - _MB}" stroke="#eee"/>'
            f'<text x="{px:.1f}" y="{h - _MB + 13}" font-size="10" text-anchor="middle">'
            f"{_fmt(tx)}</text>"
        )
    return parts


JUMP_COLOR = "#9467bd"
"""The marks of a log's time jumps on the time panels."""


def _jump_marks(
    jumps: Sequence[TimeJump], x0: float, x1: float, pw: float, top: float, h: int
) -> str:
    """A dashed vertical line at each of a log's time jumps, saying what it is on hover."""
    return "".join(
        f'<line class="time-jump" x1="{px:.1f}" y1="{top}" x2="{px:.1f}" y2="{h - _MB}" '
        f'stroke="{JUMP_COLOR}" stroke-width="1.2" stroke-dasharray="4,3">'
        f"<title>{_esc(j.describe())}</title></line>"
        for j in jumps
        for px in [_ML + (j.t_s - x0) / (x1 - x0) * pw]
    )


def _axes(
    w: int, h: int, x0: float, x1: float, y0: float, y1: float, xlabel: str, ylabel: str
) -> str:
    """Frame, grid, ticks and labels of a plot area mapping [x0, x1] x [y0, y1]."""
    pw, ph = w - _ML - _MR, h - _MT - _MB
    parts = [f'<rect x="{_ML}" y="{_MT}" width="{pw}" height="{ph}" fill="#fff" stroke="#888"/>']
    parts += _x_grid(x0, x1, pw, _MT, h)
    for ty in nice_ticks(y0, y1, 5):
        py = h - _MB - (ty - y0) / (y1 - y0) * ph
        parts.append(
            f'<line x1="{_ML}" y1="{py:.1f}" x2="{w - _MR}" y2="{py:.1f}" stroke="#eee"/>'
            f'<text x="{_ML - 4}" y="{py + 3:.1f}" font-size="10" text-anchor="end">'
            f"{_fmt(ty)}</text>"
        )
    parts.append(
        f'<text x="{_ML + pw / 2}" y="{h - 2}" font-size="11" text-anchor="middle">'
        f"{_esc(xlabel)}</text>"
        f'<text x="12" y="{_MT + ph / 2}" font-size="11" text-anchor="middle" '
        f'transform="rotate(-90 12 {_MT + ph / 2})">{_esc(ylabel)}</text>'
    )
    return "".join(parts)


def _range(
    values: Iterable[np.ndarray], pad: float = 0.05, floor: float | None = None
) -> tuple[float, float]:
    finite = [a[np.isfinite(a)] for a in values]
    finite = [a for a in finite if a.size]
    if not finite:
        return 0.0, 1.0
    lo = float(min(a.min() for a in finite))
    hi = float(max(a.max() for a in finite))
    if floor is not None:
        lo = min(lo, floor)
    span = hi - lo or max(abs(hi), 1.0)
    lo2 = lo - pad * span if floor is None or lo - pad * span >= floor or lo > floor else floor
    return lo2, hi + pad * span


def _svg_series(
    pid: str,
    series: Sequence[Series],
    t_range: tuple[float, float],
    ylabel: str,
    y_range: tuple[float, float] | None = None,
    floor: float | None = None,
    wrap: bool = False,
    jumps: Sequence[TimeJump] = (),
) -> str:
    x0, x1 = t_range
    y0, y1 = y_range or _range((s.v for s in series), floor=floor)
    w, h = _W, _H
    pw, ph = w - _ML - _MR, h - _MT - _MB
    parts = [_svg_open(pid, w, h, {"x0": x0, "x1": x1, "y0": y0, "y1": y1})]
    parts.append(_axes(w, h, x0, x1, y0, y1, "time (s)", ylabel))
    parts.append(_jump_marks(jumps, x0, x1, pw, _MT, h))
    legend = []
    for i, s in enumerate(series):
        color = COLORS[i % len(COLORS)]
        t, v = broken_at(*_thin(s.t_s, s.v), line_cuts(s.t_s, jumps))
        if wrap:  # 359 -> 1 degree is a small turn, not a line across the panel
            cut = np.flatnonzero(np.abs(np.diff(v)) > 180.0) + 1
            t, v = np.insert(t, cut, np.nan), np.insert(v, cut, np.nan)
        px = _ML + (t - x0) / (x1 - x0) * pw
        py = h - _MB - (v - y0) / (y1 - y0) * ph
        parts.append(f'<g class="series" data-label="{_esc(s.label)}">')
        parts.append(_polylines(px, py, color))
        parts.append("</g>")
        legend.append((s.label, color))
    parts.append(_legend(legend, _ML + 150, _MT - 8))
    parts.append("</svg>")
    return "".join(parts)


def _svg_track(view: LogView) -> str:
    vals_e = [e for e, _ in view.track.values()]
    vals_n = [n for _, n in view.track.values()]
    e0, e1 = _range(vals_e)
    n0, n1 = _range(vals_n)
    # equal scale on both axes: metres look like metres
    w = _W
    pw = w - _ML - _MR
    span = max(e1 - e0, (n1 - n0) * pw / 420.0)
    ce, cn = (e0 + e1) / 2, (n0 + n1) / 2
    e0, e1 = ce - span / 2, ce + span / 2
    ph = max(120.0, min(600.0, pw * (n1 - n0) / span))
    n0, n1 = cn - ph / pw * span / 2, cn + ph / pw * span / 2
    h = int(ph + _MT + _MB)
    parts = [_svg_open("track", w, h, {"x0": e0, "x1": e1, "y0": n0, "y1": n1})]
    parts.append(_axes(w, h, e0, e1, n0, n1, "east (m)", "north (m)"))
    styles = {"true track": "#2ca02c", "GPS fixes": "#d62728", "position estimate": "#1f77b4"}
    legend = []
    for label, (e, n) in view.track.items():
        color = styles.get(label, "#555")
        te, tn = _thin(e, n)
        px = _ML + (te - e0) / (e1 - e0) * pw
        py = h - _MB - (tn - n0) / (n1 - n0) * ph
        parts.append(f'<g class="series" data-label="{_esc(label)}">')
        if label == "GPS fixes":
            parts.append(
                "".join(
                    f'<circle cx="{x:.1f}" cy="{y:.1f}" r="1.8" fill="{color}"/>'
                    for x, y in zip(px.tolist(), py.tolist(), strict=True)
                    if math.isfinite(x) and math.isfinite(y)
                )
            )
        else:
            parts.append(_polylines(px, py, color))
        parts.append("</g>")
        legend.append((label, color))
    parts.append(_legend(legend, _ML + 150, _MT - 8))
    parts.append("</svg>")
    return "".join(parts)


def _svg_lanes(
    pid: str,
    intervals: Sequence[Interval],
    lanes: Sequence[str],
    t_range: tuple[float, float],
    jumps: Sequence[TimeJump] = (),
) -> str:
    x0, x1 = t_range
    lane_h = 22
    palette: dict[str, str] = {}
    for iv in intervals:
        if iv.lane in lanes and iv.label not in palette:
            palette[iv.label] = (
                STATE_COLORS.get(iv.label)
                or COLORS[sum(1 for k in palette if k not in STATE_COLORS) % len(COLORS)]
            )
    # a key of every label above the lanes (a short interval has no room for its own)
    key, rows = _legend_rows(list(palette.items()), _ML, _W - _MR)
    top = _MT + 14 * (rows - 1)
    h = top + _MB + lane_h * len(lanes)
    w = _W
    pw = w - _ML - _MR
    parts = [_svg_open(pid, w, h, {"x0": x0, "x1": x1}, top=top)]
    parts.append(key)
    parts.append(
        f'<rect x="{_ML}" y="{top}" width="{pw}" height="{h - top - _MB}" '
        'fill="#fff" stroke="#888"/>'
    )
    parts += _x_grid(x0, x1, pw, top, h)
    parts.append(_jump_marks(jumps, x0, x1, pw, top, h))
    parts.append(
        f'<text x="{_ML + pw / 2}" y="{h - 2}" font-size="11" text-anchor="middle">time (s)</text>'
    )
    for k, lane in enumerate(lanes):
        y = top + k * lane_h
        parts.append(
            f'<text x="{_ML - 4}" y="{y + lane_h / 2 + 4}" font-size="10" text-anchor="end">'
            f"{_esc(lane)}</text>"
        )
        for iv in (i for i in intervals if i.lane == lane):
            color = palette[iv.label]
            a = _ML + (iv.t0_s - x0) / (x1 - x0) * pw
            b = _ML + (iv.t1_s - x0) / (x1 - x0) * pw
            width = max(b - a, 1.5)
            tip = f"{iv.label}: {iv.t0_s:.2f}-{iv.t1_s:.2f} s" + (
                f" ({iv.detail})" if iv.detail else ""
            )
            parts.append(
                f'<rect class="interval" x="{a:.1f}" y="{y + 2}" width="{width:.1f}" '
                f'height="{lane_h - 4}" fill="{color}" fill-opacity="0.85" '
                f'data-label="{_esc(iv.label)}"><title>{_esc(tip)}</title></rect>'
            )
            if width > 7 * len(iv.label):
                parts.append(
                    f'<text x="{a + 3:.1f}" y="{y + lane_h / 2 + 4}" font-size="10">'
                    f"{_esc(iv.label)}</text>"
                )
    parts.append("</svg>")
    return "".join(parts)


TITLES = {
    "track": "Track (local east/north from the first fix)",
    "error": "Horizontal position error against the true track (m)",
    "hdop": "HDOP",
    "satellites": "Satellites",
    "heading": "Heading (degrees, 0-360)",
    "states": "Mode and navigation state",
    "holds": "Holds (the controller's reason)",
    "faults": "Device faults (and the recording's gaps)",
}

_CSS = (
    "body{font-family:sans-serif;margin:16px;color:#222;max-width:940px}"
    "h1{font-size:20px}h2{font-size:15px;margin:18px 0 4px}"
    "p.missing{color:#888;font-style:italic;margin:4px 0}"
    "table{border-collapse:collapse;font-size:13px}td{padding:1px 10px 1px 0}"
    "svg{display:block;max-width:100%;height:auto}"
)


def fault_lanes(view: LogView) -> list[str]:
    """The device-fault panel's lanes: :data:`DEVICES`, then any other device named."""
    return list(dict.fromkeys([*DEVICES, *(i.lane for i in view.faults)]))


def panel_svgs(view: LogView) -> dict[str, str]:
    """Each panel's SVG (or "" when the log has nothing for it; ``view.missing`` says why)."""
    t_range = view.time_range()
    j = view.jumps
    out: dict[str, str] = {}
    out["track"] = _svg_track(view) if view.track else ""
    out["error"] = (
        _svg_series("error", view.error, t_range, "error (m)", floor=0.0, jumps=j)
        if view.error
        else ""
    )
    out["hdop"] = (
        ""
        if "hdop" in view.missing
        else _svg_series("hdop", view.hdop, t_range, "HDOP", floor=0.0, jumps=j)
    )
    out["satellites"] = (
        ""
        if "satellites" in view.missing
        else _svg_series("satellites", view.satellites, t_range, "satellites", floor=0.0, jumps=j)
    )
    out["heading"] = (
        _svg_series(
            "heading", view.heading, t_range, "degrees", y_range=(0.0, 360.0), wrap=True, jumps=j
        )
        if view.heading
        else ""
    )
    out["states"] = (
        _svg_lanes("states", view.states, ("mode", "navigation"), t_range, j) if view.states else ""
    )
    out["holds"] = _svg_lanes("holds", view.holds, ("hold",), t_range, j) if view.holds else ""
    out["faults"] = (
        _svg_lanes("faults", view.faults, fault_lanes(view), t_range, j) if view.faults else ""
    )
    return out


def gaps_note(view: LogView, most: int = 3) -> str:
    """What the page and ``x6wd plot`` say of a recording's gaps ("" when it has none)."""
    if not view.gaps:
        return ""
    n, lost = len(view.gaps), sum(g.records_lost for g in view.gaps)
    said = "; ".join(g.describe() for g in view.gaps[:most])
    more = f"; and {n - most} more" if n > most else ""
    return f"{n} gap{'s' if n > 1 else ''}, {lost} records lost: {said}{more}"


CUT_SHORT_NOTE = (
    "cut short: its last record is not the daemon's shutdown event (a crash, kill -9 or a "
    "power cut; or a recording older than that event)"
)
"""What the page, ``x6wd plot`` and ``x6wd replay`` say of a recording that was cut short."""


def in_progress_note(view: LogView) -> str:
    """What the page and ``x6wd plot`` say of a recording still being written ("" when it is
    not): not a crash, the recording so far."""
    if view.writer is None:
        return ""
    return f"{view.writer.describe()}: what is shown is the recording so far"


def jumps_note(view: LogView, most: int = 3) -> str:
    """What the page and ``x6wd plot`` say of a log's time jumps ("" when it has none)."""
    if not view.jumps:
        return ""
    total, listed = n_jumps(view), list(view.jumps[:most])
    said = "; ".join(j.describe() for j in listed)
    more = f"; and {total - len(listed)} more" if total > len(listed) else ""
    largest = max(view.jumps, key=lambda j: abs(j.step_s))
    if total > len(listed) and largest not in listed:
        more += f" (the largest: {largest.describe()})"
    marked = ""
    if total > len(view.jumps):
        marked = (
            f" ({len(view.jumps)} of the {total} marked: the first, the {LARGEST_JUMPS} "
            "largest and the rest thinned evenly through the log)"
        )
    return (
        f"{f'{total} time jumps: ' if total > 1 else ''}{said}{more}. Drawn in file order, "
        f"each jump one epoch wide and marked with a dashed line{marked}; the time axis is "
        "the log's time within each segment"
    )


def _clock_off(s: float) -> str:
    return f"{s / 86400:.0f} days" if s >= 2 * 86400 else _duration(s)


def recorder_clock_note(view: LogView) -> str:
    """What the recorder's clock read at the start, where it disagreed with the GPS."""
    off = view.recorder_clock_off_s or 0.0
    return (
        f"{view.recorder_clock} at the start, {_clock_off(abs(off))} "
        f"{'ahead of' if off > 0 else 'behind'} the GPS (no real-time clock, or set while "
        "recording): the start is the GPS's, the fixes placed by their UTC from the first "
        "dated fix"
    )


def html_page(view: LogView) -> str:
    """The self-contained page of a loaded log (see :func:`render_html`)."""
    svgs = panel_svgs(view)
    facts = [
        ("file", str(view.path)),
        ("kind", view.kind),
        ("duration", f"{view.duration_s:.1f} s"),
        ("start (UTC)", view.start_utc or "unknown"),
    ]
    if view.recorder_clock:
        facts.append(("recorder clock", recorder_clock_note(view)))
    if view.jumps:
        facts.append((f"time jumps ({n_jumps(view)})", jumps_note(view)))
    if view.gaps:
        facts.append((f"recording gaps ({len(view.gaps)})", gaps_note(view)))
    if view.missing_parts:
        facts.append(("missing parts", missing_parts_note(view)))
    if view.cut_short:
        facts.append(("end", CUT_SHORT_NOTE))
    elif view.writer is not None:
        facts.append(("end", in_progress_note(view)))
    facts += [(k.replace("_", " "), str(v)) for k, v in view.counts.items()]
    rows = "".join(f"<tr><td>{_esc(k)}</td><td>{_esc(v)}</td></tr>" for k, v in facts)
    sections = []
    for pid in PANELS:
        why = view.missing.get(pid, "nothing in the log")
        body = svgs[pid] or f'<p class="missing">Not shown: {_esc(why)}.</p>'

        sections.append(f'<section id="panel-{pid}"><h2>{_esc(TITLES[pid])}</h2>{body}</section>')
    # </script> inside the data must not end the element: escape every "<"
    data = json.dumps(view.to_json(), separators=(",", ":"), allow_nan=False).replace(
        "<", "\\u003c"
    )
    return (
        '<!DOCTYPE html>\n<html lang="en"><head><meta charset="utf-8">'
        f"<title>x6wd log: {_esc(view.path.name)}</title><style>{_CSS}</style></head><body>"
        f"<h1>x6wd log: {_esc(view.path.name)}</h1><table>{rows}</table>"
        + "".join(sections)
        + f'<script type="application/json" id="x6wd-logview-data">{data}</script>'
        f'<p style="color:#888;font-size:11px">x6wd {__version__} logview</p>'
        "</body></html>\n"
    )


def render_html(recording_path: Path, truth: Path | None = None) -> str:
    """One self-contained HTML page (inline SVG, data embedded as JSON, nothing fetched)
    of a recording or NMEA log: what the web console serves. ``truth``: a true track CSV
    (default: ``truth.csv`` next to the recording). Raises :class:`DeviceUnavailable` for a
    file that cannot be read and :class:`ParseError` for one with nothing to plot."""
    return html_page(load(Path(recording_path), truth=truth))


SIM_RECORDING = "recording.jsonl"
"""The recording's name in a folder ``x6wd sim`` wrote (its ``--out``)."""


def newest_recording(directory: Path) -> Path:
    """The first remaining part of the newest run the daemon recorded in ``directory``
    (named ``x6wd-<UTC>.jsonl`` by the recorder), else the :data:`SIM_RECORDING` of a
    folder ``x6wd sim`` wrote; :class:`DeviceUnavailable` if neither."""
    files = list_recordings(directory)
    if not files:
        sim = directory / SIM_RECORDING
        if sim.is_file():
            return sim
        raise DeviceUnavailable(
            f"{directory}: no recordings in it (the daemon's x6wd-<UTC time>.jsonl, or"
            f" x6wd sim's {SIM_RECORDING})"
        )
    newest = files[-1].run
    return next(f.path for f in files if f.run == newest)
