"""Flight recorder: JSON lines on disk, their reader, and replay at the recorded pace.

One record per line::

    {"t_mono":12.5,"t_utc":"2026-11-22T04:43:12.123456Z","type":"nmea","data":{"text":"$GPGGA,..."}}

``t_mono`` is the monotonic time (s) the input had when it entered the host (the ``t_s`` of
the records in :mod:`x6wd.core.records`), ``t_utc`` the wall-clock time it was written. ``type`` is
one of :data:`RECORD_TYPES`; ``data`` holds the payload (a typed record as a dict, datetimes
as ISO-8601 strings).

Durability: each record is ONE ``write()`` system call of a complete line on an unbuffered
file, so a crash (even ``kill -9``) loses at most the line being written; optional periodic
``os.fsync`` bounds what a power cut can lose. The reader tolerates a truncated last line
and counts it. Reopening a file whose last line was cut off starts a fresh line first.
(``kill -9`` needs no fsync: what ``write()`` handed to the kernel survives the process; only
a power cut or a kernel crash loses what was not yet fsync'ed.)

Retention (an SD card fills up): :meth:`Recorder.in_dir` names a run
``<prefix>-YYYYmmddTHHMMSSZ[-N].jsonl`` and, with ``max_bytes``, continues it in parts
``<stem>.1.jsonl``, ``.2`` ... . The name is the run's order (retention, ``x6wd plot DIR``,
the console's list): a run is never named before one already in the directory, so a robot
without a real-time clock, started at 1970, names its run one second after the newest
instead (:func:`run_name_stamp`). With a :class:`Retention`, the recorder deletes the oldest
files of that naming pattern in its directory (older runs first, then the oldest parts of its
own run, never the part being written) while they add up to more than ``max_total_bytes`` or
the file system has less than ``min_free_bytes`` free. It does so when asked
(:meth:`Recorder.enforce_retention`, the daemon's recorder thread at start) and after every
rotation, in the thread that writes. Files of any other name are never touched.

Faults (a full or read-only file system, an unwritable or removed directory): a part that
cannot be opened, or a write that fails, does not end the recording. The recorder counts
the records it cannot write (``records_lost``), tries again after a back-off
(:data:`REOPEN_BACKOFF_S`) and carries on once it can: a failed write is retried by
reopening the same part (a record cut off by the failure then ends on its own line, so
readers lose only that record), a failed rotation by opening the next part again. Every
``check_interval_s`` it also checks that the part it writes is still in its directory
(removed with its directory, replaced by another file) and continues in a new part if not.
With ``gap_events`` (the daemon's recorder) the records lost are not only counted: the
first record written again is preceded by a :data:`GAP_EVENT` record naming the gap. With
``start_failing`` a disk that is read-only or full at start (:data:`RUNTIME_ERRNOS`) is
waited out the same way instead of raising.

A recording still being written: the recorder holds an advisory lock (``flock``, exclusive)
on the part it writes, from when it opens it until :meth:`Recorder.close` (a new part is
locked before the last one is let go; while a part waits to be opened again after a disk
failure its lock is let go, so that the card can be unmounted), and notes that part in this
process (:func:`recording_writer` sees it even where the file system has no ``flock``).
Readers test the lock (:func:`recording_writer`: the run's two newest parts, the older
first, so that a rotation under the test is seen) before reading: held, and no end record
read, the recording is in progress, not cut short. A crash, ``kill -9`` or a power cut ends
the process and the kernel lets the lock go, so such a recording still reads as cut short.
A file system without ``flock`` (an error) records as before, unmarked.
"""

from __future__ import annotations

import contextlib
import dataclasses
import enum
import errno
import fcntl
import functools
import json
import logging
import math
import operator
import os
import re
import stat
import threading
import time
import types
import typing
import weakref
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from datetime import UTC, datetime, timedelta
from itertools import chain, islice
from operator import attrgetter
from pathlib import Path
from typing import IO, Any, BinaryIO

from x6wd.core.errors import DeviceUnavailable, ParseError
from x6wd.core.files import not_regular
from x6wd.core.ratelog import RateLimitedLog
from x6wd.core.records import (
    Attitude,
    GpsFix,
    GpsSky,
    HealthEvent,
    MotorCommand,
    SatInfo,
    StateChange,
    Telemetry,
    WheelOdometry,
)

log = logging.getLogger(__name__)

RETENTION_WARN_S = 60.0
"""At most one "only the recording being written is left" warning per recorder this often
(s): the pass repeats at every retry of a part that cannot be opened (docs/install.md)."""

MB = 1 << 20
"""Bytes in the recorder's megabyte ([recorder] *_mb keys): MiB, as ``du -m``/``df -m`` count."""

REOPEN_BACKOFF_S = (1.0, 15.0)
"""First and longest wait (s, monotonic) between attempts to open a part after a failure."""
CHECK_INTERVAL_S = 5.0
"""How often (s) the recorder checks that its part is still in the directory (one stat)."""

RECORD_TYPES = frozenset(
    {"nmea", "attitude", "motor", "state", "telemetry", "sky", "fix", "event", "odometry"}
)

RUNTIME_ERRNOS = frozenset({errno.EROFS, errno.ENOSPC, errno.EDQUOT})
"""Errors of a file system that is right but cannot take the recording now (remounted
read-only after a card error, out of space or inodes, over quota): the recorder waits them
out, also at start-up (``Recorder(start_failing=True)``), and the daemon is not stopped."""

GAP_EVENT = "recording_gap"
"""The ``event`` record written when records were lost and the recording continues:
``from_t_mono``/``to_t_mono`` (the first record lost, the first written again),
``from_utc``/``to_utc``, ``duration_s``, ``records_lost`` and the ``error``."""

END_EVENTS = frozenset({"shutdown", "sim_end"})
"""The ``event`` records a complete recording ends with: the daemon's ``shutdown`` (written
on every exit under its own control), the simulator's ``sim_end``. A recording whose last
record is anything else was cut short (a crash, ``kill -9``, a power cut)."""


@dataclass(frozen=True, slots=True)
class Record:
    """One recorded line: monotonic time (s), UTC wall time (ISO-8601 Z), type and payload."""

    t_mono: float
    t_utc: str
    type: str
    data: dict[str, Any]


@dataclass
class ReadStats:
    """What :func:`read_recording` met besides good records."""

    records: int = 0
    truncated: int = 0  # an unterminated, undecodable last line (crash while writing)
    bad_lines: int = 0  # undecodable or malformed complete lines (skipped)
    blank_lines: int = 0
    # the event name of the last record read ("" when it is not an event, or when a cut-off
    # line came last): one of END_EVENTS when the recording was not cut short
    last_event: str = ""
    gaps: int = 0  # GAP_EVENT records: the recorder lost records and carried on
    gap_records_lost: int = 0  # the records those say were lost

    @property
    def cut_short(self) -> bool:
        """A recording read to its end (records in it) whose last record is not one of
        :data:`END_EVENTS`: it ended in a crash, ``kill -9`` or a power cut."""
        return self.records > 0 and self.last_event not in END_EVENTS


class InputSize:
    """The bytes of a plain (not recording) input, and whether any of them was not blank."""

    def __init__(self) -> None:
        self.bytes = 0
        self.blank = True

    def add(self, chunk: bytes) -> None:
        """Count ``chunk``, the input's next bytes; a byte-order mark (a Windows editor's,
        or several where such files were joined) is blank too (a BOM and blank lines were
        refused where an empty file was not: an outside audit). A BOM split across two
        chunks is not seen as one (the chunks are large: a first-line matter)."""
        self.bytes += len(chunk)
        if self.blank and chunk.replace(b"\xef\xbb\xbf", b"").strip():
            self.blank = False


def nothing_decoded(sentences: int, ubx_frames: int, stats: ReadStats, size: InputSize) -> str:
    """``"N bytes"`` or ``"N lines"`` when an input that is not empty held no NMEA sentence,
    UBX frame or x6wd record at all (not a log: random bytes, a mission file, junk JSON
    lines), else "". An empty or blank input is no error: empty in, empty out (decode and
    replay judge their inputs alike)."""
    lines = stats.records + stats.bad_lines + stats.truncated + stats.blank_lines
    if lines:  # a recording
        return f"{lines} lines" if not stats.records and lines > stats.blank_lines else ""
    if sentences or ubx_frames or size.blank:
        return ""
    return f"{size.bytes} bytes"


def _utc_now() -> datetime:
    return datetime.now(UTC)


def _iso_z(dt: datetime) -> str:
    if dt.tzinfo is not None:
        dt = dt.astimezone(UTC).replace(tzinfo=None)
    return dt.isoformat(timespec="microseconds") + "Z"


# One encoder for every line: json.dumps() with options builds a new encoder per call.
_ENCODE = json.JSONEncoder(separators=(",", ":"), ensure_ascii=False, allow_nan=False).encode


def to_jsonable(value: Any) -> Any:
    """Typed records to plain JSON values: dataclasses to dicts, enums to values, datetimes
    to ISO-8601 strings (aware ones in UTC with Z), non-finite floats to None."""
    # Exact-type checks first: the recorder converts every field of every record (tens of
    # thousands a simulated hour), and most are plain floats, ints, strings or None.
    t = type(value)
    if t is float:
        return value if math.isfinite(value) else None
    if t is str or t is int or t is bool or value is None:
        return value
    if t is dict:
        return {str(k): to_jsonable(v) for k, v in value.items()}
    names = _dataclass_names(t)
    if names is not None:
        return {name: to_jsonable(getattr(value, name)) for name in names}
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, enum.Enum):
        return value.value
    if isinstance(value, (str, int, bool)):
        return value
    if isinstance(value, datetime):
        return _iso_z(value) if value.tzinfo is not None else value.isoformat()
    if isinstance(value, dict):
        return {str(k): to_jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [to_jsonable(v) for v in value]
    return str(value)


_NAMES: dict[type, tuple[str, ...] | None] = {}


def _dataclass_names(cls: type) -> tuple[str, ...] | None:
    """Field names of a dataclass type, None for any other type (cached: ``fields()``
    rebuilds its tuple on every call, a hot spot at 20 Hz x records)."""
    try:
        return _NAMES[cls]
    except KeyError:
        pass
    names = None
    if dataclasses.is_dataclass(cls):
        names = tuple(f.name for f in dataclasses.fields(cls))
    _NAMES[cls] = names
    return names


def _float_json(v: float) -> str:
    # v - v is 0.0 exactly for every finite float, NaN for NaN and the infinities
    return float.__repr__(v) if v - v == 0.0 else "null"


# What the encoder above writes for each plain scalar type (floats by repr, non-finite ones
# as null, strings escaped by the same function): a record of such fields only is formatted
# directly, several times faster than converting it and encoding the result.
_SCALAR_JSON: dict[type, Callable[[Any], str]] = {
    float: _float_json,
    int: int.__repr__,
    bool: lambda v: "true" if v else "false",
    str: json.encoder.encode_basestring,
    type(None): lambda _v: "null",
}


@functools.cache
def _json_keys(names: tuple[str, ...]) -> tuple[str, ...]:
    return tuple(json.encoder.encode_basestring(n) + ":" for n in names)


# dataclass type -> (its field values as a tuple, their '"name":' keys), or None for a type
# that is not a dataclass (cached: one C call fetches all the fields of a record)
_FLAT_SPEC: dict[type, tuple[Callable[[Any], tuple[Any, ...]], tuple[str, ...]] | None] = {}


def _flat_spec(cls: type) -> tuple[Callable[[Any], tuple[Any, ...]], tuple[str, ...]] | None:
    try:
        return _FLAT_SPEC[cls]
    except KeyError:
        pass
    names = _dataclass_names(cls)
    spec = None
    if names is not None:
        get: Callable[[Any], tuple[Any, ...]]
        if len(names) > 1:
            get = attrgetter(*names)  # a tuple of the values
        else:  # attrgetter of one name gives the value itself, of none cannot be made
            get = lambda v: tuple(getattr(v, n) for n in names)  # noqa: E731
        spec = (get, _json_keys(names))
    _FLAT_SPEC[cls] = spec
    return spec


class _NotDirect(Exception):
    """A value :func:`_value_json` leaves to ``to_jsonable`` and the encoder."""


def _value_json(value: Any) -> str:
    """The encoder's text for ``to_jsonable(value)``, written directly, for the values the
    records hold: plain scalars, dicts with string keys, dataclasses, enums of plain values,
    datetimes, lists and tuples of these. Anything else raises :class:`_NotDirect`."""
    t = type(value)
    fmt = _SCALAR_JSON.get(t)
    if fmt is not None:
        return fmt(value)
    members = _members(value)
    if members is not None:
        keys, values = members
        return "{" + ",".join([k + _value_json(v) for k, v in zip(keys, values, strict=True)]) + "}"
    if t is dict:
        raise _NotDirect  # a key that is not a string: to_jsonable converts it
    if isinstance(value, enum.Enum):  # to_jsonable keeps its value as it is
        v = value.value
        if type(v) is float and v - v != 0.0:
            raise _NotDirect  # the encoder refuses a non-finite float
        fmt = _SCALAR_JSON.get(type(v))
        if fmt is None:
            raise _NotDirect
        return fmt(v)
    if isinstance(value, datetime):
        text = _iso_z(value) if value.tzinfo is not None else value.isoformat()
        return json.encoder.encode_basestring(text)
    if t is list or t is tuple:
        return "[" + ",".join([_value_json(v) for v in value]) + "]"
    raise _NotDirect


def _members(value: Any) -> tuple[tuple[str, ...], Any] | None:
    """The ``'"name":'`` keys and the values of a dict with string keys or of a dataclass
    (the two kinds of JSON object the records hold); None for anything else."""
    if type(value) is dict:
        if not all(type(k) is str for k in value):
            return None
        return _json_keys(tuple(value)), value.values()
    spec = _flat_spec(type(value))
    if spec is None:
        return None
    get, keys = spec
    return keys, get(value)


def _flat_json(value: Any) -> str | None:
    """``value`` (a dataclass or a dict with string keys) as the encoder's JSON object text
    of ``to_jsonable(value)``, written directly; None for what only the conversion and the
    encoder handle (the caller then takes that path)."""
    scalar = _SCALAR_JSON
    members = _members(value)
    if members is None:
        return None
    keys, values = members
    try:
        parts = [k + scalar[type(v)](v) for k, v in zip(keys, values, strict=True)]
    except KeyError:  # a field that is not a plain scalar: the general writer
        try:
            parts = [k + _value_json(v) for k, v in zip(keys, values, strict=True)]
        except (_NotDirect, RecursionError):
            return None
    return "{" + ",".join(parts) + "}"


def _ends_with_newline(path: Path) -> bool:
    with open(path, "rb") as f:
        f.seek(-1, os.SEEK_END)
        return f.read(1) == b"\n"


@dataclass(frozen=True)
class Retention:
    """How much the recordings of one naming ``prefix`` in a directory may take.

    ``max_total_bytes``: the recordings together (None: no cap). ``min_free_bytes``: free
    space (for unprivileged users, ``f_bavail``) the file system must keep (None: no floor).
    """

    max_total_bytes: int | None = None
    min_free_bytes: int | None = None
    prefix: str = "x6wd"


@dataclass(frozen=True, order=True)
class RecordingFile:
    """One file of the recorder's naming pattern; sorts oldest first (run, then part)."""

    run: tuple[str, int]  # (UTC stamp YYYYmmddTHHMMSSZ, same-second counter N or 0)
    part: int  # 0 for the run's first file, n for ``<stem>.n.jsonl``
    path: Path = field(compare=False)
    size: int = field(compare=False)  # bytes


# --- a recording still being written ---------------------------------------------------------

_LOCK_TRIES = 20
"""Attempts (5 ms apart) at a part's exclusive lock: a reader's test holds a shared one for
a moment; a part still refused after them is written unmarked (logged)."""

_HOLDER_TRIES = 3
"""Tests (1 ms apart) of a part's lock found held whose holder ``/proc/locks`` does not
show: the lock was let go just then (a rotation), or the holder cannot be told (not Linux)."""

_ROTATION_TRIES = 5
"""Rounds of :func:`recording_writer`'s tests while newer parts keep appearing."""

# (st_dev, st_ino) of the parts this process's recorders write now -> how many hold each
_WRITING: dict[tuple[int, int], int] = {}
_WRITING_LOCK = threading.Lock()


def _file_key(st: os.stat_result) -> tuple[int, int]:
    return st.st_dev, st.st_ino


class _WritingMark:
    """What says a part is being written: an exclusive ``flock`` on a descriptor of its own
    (so closing or reopening the file written does not let it go) and the part's entry in
    this process's :data:`_WRITING`. :meth:`move_to` marks a newly opened part, then lets
    the previous one go; :meth:`release` lets go at the close. Lock errors (a file system
    without ``flock``) are ignored: the part is written, only not marked for other
    processes."""

    def __init__(self) -> None:
        self._fd: int | None = None
        self._key: tuple[int, int] | None = None
        self.locked = False  # the part's flock is held (False: none, or not supported)
        self._unlocked = False  # the lock was let go on a disk failure (unlock()), noted still

    def move_to(self, f: Any, path: Path) -> None:
        try:
            key = _file_key(os.fstat(f.fileno()))
        except (OSError, AttributeError, ValueError):
            return  # cannot tell which file: the previous mark stays
        if key == self._key and not self._unlocked:
            return  # the same part opened again: already marked
        fd: int | None = None
        locked = False
        try:
            fd = os.open(path, os.O_RDONLY | os.O_CLOEXEC)
            if _file_key(os.fstat(fd)) != key:  # replaced meanwhile: not the part written
                raise FileNotFoundError(errno.ENOENT, "replaced", str(path))
            for attempt in range(_LOCK_TRIES):
                try:
                    fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                except BlockingIOError:  # a reader testing it: a moment
                    if attempt + 1 < _LOCK_TRIES:
                        time.sleep(0.005)
                    continue
                locked = True
                break
            else:
                log.info("recorder: %s stays locked by another process: not marked", path)
        except OSError as exc:  # no flock here (or the part is gone): written unmarked
            log.debug("recorder: cannot lock %s: %s", path, exc)
        if not locked and fd is not None:
            os.close(fd)
            fd = None
        with _WRITING_LOCK:
            _WRITING[key] = _WRITING.get(key, 0) + 1
        self._let_go()
        self._fd, self._key, self.locked = fd, key, locked

    def unlock(self) -> None:
        """The part was dropped on a disk failure: close the lock's descriptor (an open
        descriptor keeps a failed card from being unmounted), keep the in-process note (this
        process's console still says "this run"). Other processes read the part as cut short
        until :meth:`move_to` marks the part reopened."""
        fd, self._fd, self.locked = self._fd, None, False
        self._unlocked = True
        if fd is not None:
            with contextlib.suppress(OSError):
                os.close(fd)

    def _let_go(self) -> None:
        fd, key, self._fd, self._key, self.locked = self._fd, self._key, None, None, False
        self._unlocked = False
        if key is not None:
            with _WRITING_LOCK:
                n = _WRITING.get(key, 0) - 1
                if n > 0:
                    _WRITING[key] = n
                else:
                    _WRITING.pop(key, None)
        if fd is not None:
            with contextlib.suppress(OSError):
                os.close(fd)  # the lock goes with the last descriptor of its open file

    def release(self) -> None:
        self._let_go()


@dataclass(frozen=True)
class Writer:
    """Who writes a recording still being written (:func:`recording_writer`)."""

    pid: int | None  # the writing process, None when it cannot be told
    this_process: bool  # this process's own recorder (the daemon's console, its own run)

    def describe(self) -> str:
        """What readers say of it (``x6wd plot``, ``x6wd replay``, the page's "end")."""
        if self.this_process:
            return "still being recorded (this run)"
        pid = f" (pid {self.pid})" if self.pid else ""
        return f"not finished: still being written by a running x6wd{pid}"


def _lock_holder(st: os.stat_result) -> int | None:
    """The pid holding an exclusive ``flock`` on the file of ``st``, from ``/proc/locks``
    (Linux); None when it cannot be told."""
    maj, mnr, ino = os.major(st.st_dev), os.minor(st.st_dev), st.st_ino
    try:
        with open("/proc/locks", encoding="ascii", errors="replace") as f:
            text = f.read()
    except OSError:
        return None
    for line in text.splitlines():
        fields = line.split()
        if len(fields) < 6 or fields[1] != "FLOCK" or fields[3] != "WRITE":
            continue  # ("->" lines are waiters)
        try:
            d_maj, d_min, d_ino = fields[5].split(":")
            if (int(d_maj, 16), int(d_min, 16), int(d_ino)) == (maj, mnr, ino):
                return int(fields[4]) or None
        except ValueError:
            continue
    return None


def part_writer(path: str | os.PathLike[str]) -> Writer | None:
    """The :class:`Writer` of one file being written by a recorder now (its lock held, or
    written by this process), or None (finished, cut short, not a recording, no ``flock``
    there, cannot be opened)."""
    try:
        fd = os.open(path, os.O_RDONLY | os.O_CLOEXEC | os.O_NONBLOCK)
    except OSError:
        return None
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            return None
        with _WRITING_LOCK:
            here = _file_key(st) in _WRITING
        if here:
            return Writer(os.getpid(), True)
        for attempt in range(_HOLDER_TRIES):
            try:
                fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
            except BlockingIOError:
                pid = _lock_holder(st)
                if pid is not None or attempt + 1 == _HOLDER_TRIES:
                    return Writer(pid, False)
                time.sleep(0.001)  # let go after the test (a rotation)? tested again
                continue
            except OSError:  # no flock on this file system: cannot tell
                return None
            fcntl.flock(fd, fcntl.LOCK_UN)
            return None
        return None
    finally:
        os.close(fd)


def recording_writer(path: str | os.PathLike[str]) -> Writer | None:
    """The :class:`Writer` of the recording whose part is ``path`` (any part: its run's
    parts are looked at as they are now) while a recorder still writes it, else None.

    The lock is on the run's last part, or, for the moment a rotation takes, the one before:
    a rotation creates the new part, locks it, then lets the previous one go. So the two
    newest parts are tested oldest first (the older found free, the newer was locked by
    then), and tested again while a newer part appeared meanwhile (a rotation between the
    listing and the tests)."""
    parts = recording_parts(path)[-2:]
    for _ in range(_ROTATION_TRIES):
        for part in parts:
            if (w := part_writer(part)) is not None:
                return w
        newest = recording_parts(path)[-2:]
        if not newest or newest[-1] == parts[-1]:
            return None  # no part newer than those found free: not being written
        parts = newest
    return None


@functools.cache
def _name_pattern(prefix: str) -> re.Pattern[str]:
    return re.compile(
        rf"^{re.escape(prefix)}-(\d{{8}}T\d{{6}}Z)(?:-([1-9]\d*))?(?:\.([1-9]\d*))?\.jsonl$"
    )


def _parse_name(name: str, prefix: str) -> tuple[tuple[str, int], int] | None:
    m = _name_pattern(prefix).match(name)
    if m is None:
        return None
    return (m[1], int(m[2] or 0)), int(m[3] or 0)


_STAMP_FORMAT = "%Y%m%dT%H%M%SZ"


def _previous_stamp(stamp: str) -> str:
    t = datetime.strptime(stamp, _STAMP_FORMAT).replace(tzinfo=UTC)
    return (t - timedelta(seconds=1)).strftime(_STAMP_FORMAT)


def run_name_stamp(
    directory: str | os.PathLike[str], prefix: str, now: datetime
) -> tuple[str, int]:
    """(stamp, N) naming a new run in ``directory`` at UTC ``now`` so that it sorts after
    every run already there (:func:`list_recordings`' order): ``now``'s stamp with N 0 when
    it is later than the newest run's; the newest stamp with its N + 1 in the same second;
    one second after the newest stamp when ``now`` is earlier (a clock at 1970, set back).
    A folder that cannot be read (missing, no permission) gives ``now``'s stamp."""
    stamp = now.astimezone(UTC).strftime(_STAMP_FORMAT)
    try:
        files = list_recordings(directory, prefix)
    except OSError:
        files = []
    if not files:
        return stamp, 0
    newest, newest_n = max(f.run for f in files)
    if stamp > newest:
        return stamp, 0
    if stamp == newest:
        return stamp, newest_n + 1
    t = datetime.strptime(newest, _STAMP_FORMAT).replace(tzinfo=UTC)
    if t.year == 9999 and t.strftime("%m%d%H%M%S") == "1231235959":
        return newest, newest_n + 1  # no second after it to name
    return (t + timedelta(seconds=1)).strftime(_STAMP_FORMAT), 0


def _claim(path: Path) -> bool:
    """Create ``path`` empty if no file has the name (atomic, ``O_EXCL``): False when one
    has. Two processes naming a run in the same second both see the same newest run; only
    one of them can create the name, so they never append to one file. A folder that cannot
    be written gives True: opening the recording then names that error."""
    try:
        os.close(os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666))
    except FileExistsError:
        return False
    except OSError:
        return not os.path.lexists(path)
    return True


def list_recordings(directory: str | os.PathLike[str], prefix: str = "x6wd") -> list[RecordingFile]:
    """The regular files in ``directory`` named as :meth:`Recorder.in_dir` names runs and
    their parts, oldest first. A missing directory has none."""
    out: list[RecordingFile] = []
    try:
        entries = list(os.scandir(directory))
    except FileNotFoundError:
        return out
    for entry in entries:
        key = _parse_name(entry.name, prefix)
        if key is None:
            continue
        try:
            if not entry.is_file(follow_symlinks=False):
                continue
            size = entry.stat(follow_symlinks=False).st_size
        except FileNotFoundError:  # deleted meanwhile
            continue
        out.append(RecordingFile(key[0], key[1], Path(entry.path), size))
    out.sort()
    return out


def free_bytes(directory: str | os.PathLike[str]) -> int:
    """Bytes an unprivileged user may still write on the file system of ``directory``."""
    st = os.statvfs(directory)
    return st.f_bavail * st.f_frsize


def enforce_retention(
    directory: str | os.PathLike[str],
    retention: Retention,
    *,
    current: str | os.PathLike[str] | None = None,
    reserve_bytes: int = 0,
    free: Callable[[Path], int] = free_bytes,
    warn: Callable[[str], object] | None = None,
) -> list[Path]:
    """Delete the oldest recordings in ``directory`` until they take at most
    ``retention.max_total_bytes`` and the file system has ``retention.min_free_bytes`` free,
    counting ``current`` (the part being written) at the ``reserve_bytes`` it may grow to,
    so that both limits still hold when it is full.

    Order: every run other than ``current``'s (oldest first, each run's parts in order), then
    the parts of ``current``'s run oldest first; ``current`` itself is never deleted, nor any
    file outside the naming pattern. ``free(dir)`` gives the free bytes (asked once; each
    deletion then counts as freed). Returns the deleted paths, each one logged; a limit
    still broken with nothing left to delete goes to ``warn(text)`` (default: a WARNING).
    """
    d = Path(directory)
    cur = Path(current) if current is not None else None
    files = list_recordings(d, retention.prefix)
    if not files:
        return []
    cur_size = next((f.size for f in files if cur is not None and f.path == cur), 0)
    headroom = max(0, reserve_bytes - cur_size)  # what the current part may still grow
    total = sum(f.size for f in files) + headroom
    free_now = free(d) - headroom if retention.min_free_bytes is not None else 0
    cur_key = _parse_name(cur.name, retention.prefix) if cur is not None else None
    cur_run = cur_key[0] if cur_key is not None else None
    # other runs first (a clock set back must not make the live run look oldest), then ours
    victims = [f for f in files if f.run != cur_run] + [
        f for f in files if f.run == cur_run and (cur is None or f.path != cur)
    ]

    def over() -> str:
        cap, floor = retention.max_total_bytes, retention.min_free_bytes
        if cap is not None and total > cap:
            return f"recordings take {total} B (the current part full) > {cap} B"
        if floor is not None and free_now < floor:  # no negative byte counts in the log
            if free_now < 0:
                return (
                    f"the file system lacks {-free_now} B for the current part to fill up, "
                    f"and must keep {floor} B free"
                )
            return f"once the current part is full, {free_now} B free, under the {floor} B to keep"
        return ""

    deleted: list[Path] = []
    for f in victims:
        why = over()
        if not why:
            break
        try:
            f.path.unlink()
        except FileNotFoundError:
            pass  # someone else removed it: it takes no space either way
        except OSError as exc:
            log.warning("retention: cannot delete %s: %s", f.path, exc.strerror or exc)
            continue
        else:
            deleted.append(f.path)
            log.info("retention: deleted %s (%d B): %s", f.path, f.size, why)
        total -= f.size
        free_now += f.size
    why = over()
    if why:
        text = f"retention: {why}, and only the recording being written is left"
        if warn is None:
            log.warning("%s", text)
        else:
            warn(text)
    return deleted


class Recorder:
    """Append-only JSON-lines flight recorder (a context manager; thread-safe).

    ``fsync_interval_s``: call ``os.fsync`` when at least this many seconds (wall) passed
    since the last one (None: never; the OS still gets every line at once). ``max_bytes``:
    rotate to a new part ``<stem>.1<suffix>``, ``.2`` ... before a record would make the
    current part larger (``paths`` lists them; :func:`recording_parts` finds them again).
    ``clock`` gives ``t_mono`` when a call omits it; ``utc_clock`` gives ``t_utc``.
    ``retention``: applied to the recording's directory after every rotation (in the
    writing thread) and by :meth:`enforce_retention`; see the module docstring.
    ``buffer_bytes``: 0 (default) writes each record at once; more collects records in a
    buffer of that size first (the simulator's fast time, which needs no crash durability:
    a crash then loses up to that much).
    ``reopen_backoff_s``: (first, longest) wait in seconds between attempts to open a part
    after a failure (see the module docstring); ``check_interval_s``: how often (s) to check
    that the part is still in its directory (None: never).
    ``start_failing``: a first part that cannot be opened for one of :data:`RUNTIME_ERRNOS`
    (a read-only or full file system) does not raise: the recorder starts ``failing`` and
    opens it later, as after a failed write (the daemon starts on such a disk); any other
    error raises :class:`DeviceUnavailable` as without it.

    ``gap_events``: records lost (a part that cannot be written or opened) make a gap: the
    first record written after it is preceded by a :data:`GAP_EVENT` event naming the gap's
    ends and the records lost, so the recording shows its holes (``x6wd plot`` and ``x6wd
    replay`` report them; the daemon's recorder does this). Without it, as before: the gap
    is only counted (``records_lost``) and logged.
    """

    def __init__(
        self,
        path: str | os.PathLike[str],
        *,
        fsync_interval_s: float | None = None,
        max_bytes: int | None = None,
        retention: Retention | None = None,
        clock: Callable[[], float] = time.monotonic,
        utc_clock: Callable[[], datetime] = _utc_now,
        buffer_bytes: int = 0,
        reopen_backoff_s: tuple[float, float] = REOPEN_BACKOFF_S,
        check_interval_s: float | None = CHECK_INTERVAL_S,
        start_failing: bool = False,
        gap_events: bool = False,
    ) -> None:
        if fsync_interval_s is not None and not fsync_interval_s >= 0:
            raise ValueError(f"fsync_interval_s must be >= 0 or None, got {fsync_interval_s}")
        if max_bytes is not None and max_bytes < 1:
            raise ValueError(f"max_bytes must be >= 1 or None, got {max_bytes}")
        if buffer_bytes < 0:
            raise ValueError(f"buffer_bytes must be >= 0, got {buffer_bytes}")
        self.buffer_bytes = buffer_bytes
        self.path = Path(path)
        self.paths = [self.path]
        self.fsync_interval_s = fsync_interval_s
        self.max_bytes = max_bytes
        self.retention = retention
        self.deleted: list[Path] = []  # files retention removed, oldest first
        # a pass runs at each part opened, also each retry of a full card: one line a minute
        self._retention_log = RateLimitedLog(log, RETENTION_WARN_S)
        self._clock = clock
        self._utc_clock = utc_clock
        # (the latest datetime utc_clock gave, its text): a clock that hands back the same
        # object (the simulator, for the records of one step) is formatted once
        self._utc_memo: tuple[datetime | None, str] = (None, "")
        self._lock = threading.Lock()
        self.records_written = 0
        self.bytes_written = 0
        self.write_errors = 0  # failed writes and failed attempts to open a part
        self.records_lost = 0  # records not written while a part could not be written
        self.reopens = 0  # parts opened again after a failure or a removed file
        self.last_error = ""
        self.dropped_after_close = 0
        self.reopen_backoff_s = reopen_backoff_s
        self.check_interval_s = check_interval_s
        self._closed = False
        self._recovering = False  # a part failed: say so when one opens again
        # the gap in progress: (t_mono, t_utc text of its first lost record, records_lost
        # before it), None when nothing was lost since the last record written
        self._gap: tuple[float, str, int] | None = None
        self.gap_events = gap_events
        self._reopen_path: Path | None = None  # the part to open then
        self._backoff_s = reopen_backoff_s[0]
        self._t_retry = 0.0  # time.monotonic() of the next attempt to open it
        self._file: Any = None  # None while a part waits to be (re)opened
        # the part being written, marked (locked) for readers until close()
        self._mark = _WritingMark()
        weakref.finalize(self, self._mark.release)  # a recorder never closed, collected
        try:
            self._file = self._open(self.path)
            self._mark.move_to(self._file, self.path)
        except DeviceUnavailable as exc:
            cause = exc.__cause__
            if not (start_failing and isinstance(cause, OSError) and cause.errno in RUNTIME_ERRNOS):
                raise
            self._reopen_path = self.path
            self._failed(str(exc), time.monotonic())
        now = time.monotonic()
        self._last_fsync = now
        self._t_check = now + (check_interval_s or 0.0)

    def _open(self, path: Path) -> Any:
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            # Unbuffered binary (by default): each record reaches the kernel in one write().
            size = self.buffer_bytes and max(2, self.buffer_bytes)  # 1 would mean lines
            f = open(path, "ab", buffering=size)  # noqa: SIM115
            if f.tell() > 0 and not _ends_with_newline(path):
                f.write(b"\n")  # a previous run died mid-line: do not glue onto it
        except OSError as exc:
            raise DeviceUnavailable(f"cannot open recording {path}: {exc}") from exc
        return f

    def _sync(self) -> None:
        """Hand any buffered records to the kernel, then ``os.fsync``."""
        self._file.flush()
        os.fsync(self._file.fileno())

    def _next_part(self) -> Path:
        first = self.paths[0]
        return first.with_name(f"{first.stem}.{len(self.paths)}{first.suffix}")

    def _rotate(self, now: float) -> None:
        """Continue in the next part, ``<stem>.<n><suffix>`` (see :func:`recording_parts`).
        Raises DeviceUnavailable when it cannot be opened (it is tried again later)."""
        self._drop_file()
        self._reopen_path = self._next_part()
        self._t_retry = now
        self._reopen(now)

    def _drop_file(self) -> None:
        """Close the part (best effort: its file system may be failing)."""
        f, self._file = self._file, None
        if f is None:
            return
        with contextlib.suppress(OSError):
            f.flush()
            os.fsync(f.fileno())
        with contextlib.suppress(OSError):
            f.close()

    def _reopen(self, now: float) -> bool:
        """Open the waiting part when the back-off allows: True when one is open now, False
        while waiting; raises DeviceUnavailable when the attempt fails (next one later)."""
        if self._file is not None:
            return True
        if now < self._t_retry:
            return False
        path = self._reopen_path or self.path
        if self.retention is not None and self._recovering:
            # a full file system: retention's min_free_bytes may make room first
            with contextlib.suppress(OSError):
                self.enforce_retention()
        try:
            f = self._open(path)
        except DeviceUnavailable as exc:
            self._failed(str(exc), now)
            raise
        self._file = f
        self._mark.move_to(f, path)  # the new part marked, then the previous one let go
        self._reopen_path = None
        self._backoff_s = self.reopen_backoff_s[0]
        if path != self.path or path not in self.paths:
            self.path = path
            self.paths.append(path)
        if self._recovering:
            self._recovering = False
            self.reopens += 1
            log.warning(
                "recording continues in %s (%d records lost so far)", path, self.records_lost
            )
        return True

    def _write_failed(self, exc: OSError, now: float) -> None:
        """A write failed: the part is closed and reopened after the back-off (appending
        after a newline when the failed write left part of its line)."""
        self._failed(f"{self.path}: write failed: {exc}", now)
        self._drop_file()
        self._reopen_path = self.path

    def _failed(self, error: str, now: float) -> None:
        """Count a failed open or write and try again after the back-off (doubling, capped).
        The last part's lock goes too (no descriptor left on a failing card: it can be
        unmounted); the in-process note stays."""
        self._mark.unlock()
        self.write_errors += 1
        self.last_error = error
        self._recovering = True
        self._t_retry = now + self._backoff_s
        self._backoff_s = min(2.0 * self._backoff_s, self.reopen_backoff_s[1])

    def _check_still_there(self, now: float) -> None:
        """Continue in a new part when the one being written left its directory (removed, or
        the directory with it, or replaced): writing on would fill a deleted file."""
        self._t_check = now + (self.check_interval_s or 0.0)
        try:
            st = os.stat(self.path)
            fst = os.fstat(self._file.fileno())
        except FileNotFoundError:
            same = False
        except OSError:
            return  # cannot tell (a failing file system): the writes will say
        else:
            same = (st.st_dev, st.st_ino) == (fst.st_dev, fst.st_ino)
        if not same:
            log.warning("recording %s was removed: continuing in a new part", self.path)
            self.last_error = f"{self.path} was removed"
            self._rotate(now)

    @property
    def state(self) -> str:
        """ "ok" (a part is open), "failing" (waiting to open one) or "closed"."""
        if self._closed:
            return "closed"
        return "ok" if self._file is not None else "failing"

    def enforce_retention(self) -> list[Path]:
        """Run the retention pass now (no-op without ``retention``); the deleted paths.

        Blocks on file-system calls: call it from the writing thread, never an event loop.
        """
        if self.retention is None:
            return []
        gone = enforce_retention(
            self.path.parent,
            self.retention,
            current=self.path,
            reserve_bytes=self.max_bytes or 0,
            warn=lambda text: self._retention_log.log("retention", logging.WARNING, "%s", text),
        )
        self.deleted.extend(gone)
        return gone

    @classmethod
    def in_dir(
        cls, directory: str | os.PathLike[str], prefix: str = "x6wd", **kwargs: Any
    ) -> Recorder:
        """A new recording ``<prefix>-YYYYmmddTHHMMSSZ[-N].jsonl`` in ``directory``.

        The name is the UTC time of ``utc_clock`` but also the order of the runs (retention,
        ``x6wd plot DIR``, the console's list all go by it), so a new run never sorts before
        one already in the directory: when the clock reads earlier than the newest run's
        name (a robot without a real-time clock boots at 1970, a clock set back), the run is
        named one second after that newest name instead, and this is logged (its records
        keep the clock's ``t_utc``). In the newest run's own second, ``-N`` follows its
        highest ``N``. See :func:`run_name_stamp`.
        """
        utc_clock = kwargs.get("utc_clock", _utc_now)
        now = utc_clock().astimezone(UTC)
        stamp, n = run_name_stamp(directory, prefix, now)
        if stamp != now.strftime(_STAMP_FORMAT):
            log.warning(
                "recorder: the clock reads %s UTC, earlier than the newest recording in %s "
                "(%s-%s...): the new run is named %s-%s so that it sorts after it (its "
                "records keep the clock's t_utc)",
                now.strftime("%Y-%m-%d %H:%M:%S"),
                directory,
                prefix,
                _previous_stamp(stamp),
                prefix,
                stamp,
            )
        base = Path(directory) / f"{prefix}-{stamp}"
        path = Path(f"{base}-{n}.jsonl") if n else base.with_suffix(".jsonl")
        while not _claim(path):  # taken (another daemon in the same second, a file of
            n += 1  # another kind): never shared, never overwritten
            path = Path(f"{base}-{n}.jsonl")
        try:
            return cls(path, **kwargs)
        except BaseException:  # a run that never started leaves no empty file in the lists
            with contextlib.suppress(OSError):
                if path.stat().st_size == 0:
                    path.unlink()
            raise

    @property
    def closed(self) -> bool:
        """True once :meth:`close` ran."""
        return self._closed

    def record(self, type: str, payload: Any, t_mono: float | None = None) -> None:
        """Write one record of ``type`` (one of :data:`RECORD_TYPES`) with ``payload``.

        ``payload`` is a dict or a dataclass (converted); ``t_mono`` (s) defaults to the
        clock. Raises ValueError for an unknown type or a non-finite time; an I/O error on
        write, or on opening a part, is re-raised as :class:`DeviceUnavailable` after being
        counted (``write_errors``; the record in ``records_lost``). While a part waits to be
        opened again (the back-off), records are counted in ``records_lost`` without an
        exception. After :meth:`close`, records are dropped and counted in
        ``dropped_after_close``.
        """
        if type not in RECORD_TYPES:
            raise ValueError(
                f"unknown record type {type!r} (valid: {', '.join(sorted(RECORD_TYPES))})"
            )
        t = self._clock() if t_mono is None else float(t_mono)
        if not math.isfinite(t):
            raise ValueError(f"t_mono must be finite, got {t_mono!r}")
        body = _flat_json(payload)
        if body is None:
            data = to_jsonable(payload)
            if not isinstance(data, dict):
                raise ValueError(f"payload must be a dict or a dataclass, got {payload!r}")
            body = _ENCODE(data)
        utc = self._utc_clock()
        memo = self._utc_memo
        if memo[0] is utc:
            utc_text = memo[1]
        else:
            utc_text = _iso_z(utc)
            self._utc_memo = (utc, utc_text)  # one assignment: safe between threads
        # The encoder's own text for {"t_mono", "t_utc", "type", "data"} (t is finite).
        line = (
            f'{{"t_mono":{float.__repr__(t)},"t_utc":"{utc_text}","type":"{type}","data":{body}}}\n'
        )
        blob = line.encode("utf-8")
        rotated = False
        with self._lock:
            if self._closed:  # a late record during shutdown: counted, not fatal
                self.dropped_after_close += 1
                return
            now = time.monotonic()
            try:
                if self._file is None and not self._reopen(now):
                    self._lose(t, utc_text)  # waiting out the back-off
                    return
                if self.check_interval_s is not None and now >= self._t_check:
                    self._check_still_there(now)
                if (
                    self.max_bytes is not None
                    and self._file.tell() > 0
                    and self._file.tell() + len(blob) > self.max_bytes
                ):
                    self._rotate(now)
                    rotated = True
            except DeviceUnavailable:
                self._lose(t, utc_text)
                raise
            try:
                if self._gap is not None:  # records were lost: the recording says so first
                    self._write_gap(t, utc_text)
                self._write_all(blob)
            except OSError as exc:
                self._lose(t, utc_text)
                self._write_failed(exc, now)
                raise DeviceUnavailable(f"recording {self.path}: write failed: {exc}") from exc
            self.records_written += 1
            self.bytes_written += len(blob)
            if self.fsync_interval_s is not None:
                now = time.monotonic()
                if now - self._last_fsync >= self.fsync_interval_s:
                    self._sync()
                    self._last_fsync = now
        if rotated:  # outside the lock: deleting files must not hold up other writers
            try:
                self.enforce_retention()
            except OSError as exc:  # retention is housekeeping: recording goes on
                log.warning("retention pass failed: %s", exc)

    def _lose(self, t: float, utc_text: str) -> None:
        """A record at ``t`` could not be written: counted, and the gap starts (if it has
        not yet)."""
        if self._gap is None and self.gap_events:
            self._gap = (t, utc_text, self.records_lost)
        self.records_lost += 1

    def _write_gap(self, t: float, utc_text: str) -> None:
        """Write the :data:`GAP_EVENT` record of the gap that ends with the record at ``t``
        (raises OSError as a write does; the gap then goes on)."""
        assert self._gap is not None
        t0, utc0, lost0 = self._gap
        body = _ENCODE(
            {
                "event": GAP_EVENT,
                "from_t_mono": t0,
                "to_t_mono": t,
                "from_utc": utc0,
                "to_utc": utc_text,
                "duration_s": round(max(0.0, t - t0), 3),
                "records_lost": self.records_lost - lost0,
                "error": self.last_error,
            }
        )
        line = f'{{"t_mono":{float.__repr__(t)},"t_utc":"{utc_text}","type":"event","data":'
        line += body + "}\n"
        blob = line.encode("utf-8")
        self._write_all(blob)
        self._gap = None
        self.records_written += 1
        self.bytes_written += len(blob)

    def _write_all(self, blob: bytes) -> None:
        """Write ``blob`` whole: an unbuffered file may take part of it (a file system that
        just filled up), the rest then goes in further writes, whose error is raised."""
        view = memoryview(blob)
        while view:
            n = self._file.write(view)
            if n is None or n >= len(view):  # buffered: all or an exception
                return
            if n == 0:
                raise OSError(errno.EIO, "the write took nothing")
            view = view[n:]

    def record_nmea(self, text: str | bytes, t_mono: float | None = None) -> None:
        """One raw NMEA sentence as received (line ending stripped)."""
        if isinstance(text, bytes):
            text = text.decode("ascii", "replace")
        self.record("nmea", {"text": text.rstrip("\r\n")}, t_mono)

    def record_attitude(self, att: Attitude) -> None:
        """A compass sample; ``t_mono`` is its ``t_s``."""
        self.record("attitude", att, att.t_s)

    def record_motor(self, cmd: MotorCommand) -> None:
        """A motor command; ``t_mono`` is its ``t_s``."""
        self.record("motor", cmd, cmd.t_s)

    def record_state(self, change: StateChange) -> None:
        """A controller mode/state change; ``t_mono`` is its ``t_s``."""
        self.record("state", change, change.t_s)

    def record_telemetry(self, tel: Telemetry) -> None:
        """A controller telemetry snapshot; ``t_mono`` is its ``t_s``. Its heading and
        target bearing as status and watch show them, 0 <= h < 360 (recordings before
        this held the controller's (-180, 180]: their readers wrap)."""
        # The dataclass itself, not ``tel.to_dict()``: same JSON (enums by value), without
        # ``asdict``'s deep copy.
        self.record("telemetry", tel.shown(), tel.t_s)

    def record_fix(self, fix: GpsFix) -> None:
        """A decoded fix; ``t_mono`` is its ``t_s``."""
        self.record("fix", fix, fix.t_s)

    def record_sky(self, sky: GpsSky) -> None:
        """A decoded sky report; ``t_mono`` is its ``t_s``."""
        self.record("sky", sky, sky.t_s)

    def record_odometry(self, odo: WheelOdometry) -> None:
        """Wheel-encoder counts (unwrapped, cumulative); ``t_mono`` is their ``t_s``."""
        self.record("odometry", odo, odo.t_s)

    def record_event(self, name: str, t_mono: float | None = None, **fields: Any) -> None:
        """A free-form event (start, stop, device lost ...) with extra fields."""
        self.record("event", {"event": name, **fields}, t_mono)

    def record_health(self, ev: HealthEvent) -> None:
        """A device's health event as a ``device`` event (device, kind, old and new state,
        message): the device faults of ``x6wd plot``. ``t_mono`` is its ``t_s``."""
        self.record_event(
            "device", ev.t_s, device=ev.device, kind=ev.kind, old=str(ev.old), new=str(ev.new),
            message=ev.message,
        )  # fmt: skip

    def flush(self) -> None:
        """Force the data to stable storage (``os.fsync``)."""
        with self._lock:
            if not self._closed and self._file is not None:
                self._sync()

    def close(self) -> None:
        """fsync and close (idempotent)."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
            self._drop_file()
            self._mark.release()  # finished: no longer being written

    def __enter__(self) -> Recorder:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


# --- reading --------------------------------------------------------------------------------


def _parse_line(raw: bytes) -> Record:
    obj = json.loads(raw)
    if not isinstance(obj, dict):
        raise ValueError("not a JSON object")
    t_mono, rtype, data = obj.get("t_mono"), obj.get("type"), obj.get("data")
    if isinstance(t_mono, bool) or not isinstance(t_mono, (int, float)):
        raise ValueError("t_mono missing or not a number")
    if rtype not in RECORD_TYPES:
        raise ValueError(f"unknown type {rtype!r}")
    if not isinstance(data, dict):
        raise ValueError("data missing or not an object")
    t_utc = obj.get("t_utc")
    return Record(float(t_mono), t_utc if isinstance(t_utc, str) else "", rtype, data)


MAX_RECORD_LINE_BYTES = 1 << 20
"""A recording line longer than this (bytes) is no record (the longest, a sky of 32
satellites, is about 3 kB): a card's garbage tail, skipped a piece at a time."""


def _bounded_lines(f: BinaryIO) -> Iterator[bytes | None]:
    """The lines of ``f``; None for each line longer than :data:`MAX_RECORD_LINE_BYTES`,
    whose bytes are read and dropped a piece at a time. A read error raises
    :class:`DeviceUnavailable` naming the file."""
    limit = MAX_RECORD_LINE_BYTES
    try:
        while raw := f.readline(limit + 1):
            if len(raw) <= limit or raw.endswith(b"\n"):
                yield raw
                continue
            while raw and not raw.endswith(b"\n"):
                raw = f.readline(limit)
            yield None
    except OSError as exc:  # an I/O error (a failing card, /proc/self/mem): named, no traceback
        name = getattr(f, "name", "recording")
        raise DeviceUnavailable(f"cannot read recording {name}: {exc.strerror or exc}") from exc


def read_recording(
    path: str | os.PathLike[str], *, stats: ReadStats | None = None, strict: bool = False
) -> Iterator[Record]:
    """Yield the records of a recording in file order.

    A last line without its newline that does not decode is the mark of a crash while
    writing: it is skipped and counted in ``stats.truncated``. Other undecodable lines are
    skipped and counted in ``stats.bad_lines``, or raise :class:`ParseError` (naming the
    line) when ``strict``. A missing file raises :class:`DeviceUnavailable`.
    """
    st = stats if stats is not None else ReadStats()
    try:
        f = open(path, "rb")  # noqa: SIM115
    except OSError as exc:
        raise DeviceUnavailable(f"cannot open recording {path}: {exc}") from exc
    with f:
        for lineno, raw in enumerate(_bounded_lines(f), 1):
            if raw is None:  # longer than any record: skipped without holding it whole
                if strict:
                    raise ParseError(
                        f"{path}:{lineno}: line longer than {MAX_RECORD_LINE_BYTES} bytes"
                    )
                st.bad_lines += 1
                continue
            if not raw.strip():
                st.blank_lines += 1
                continue
            try:
                rec = _parse_line(raw)
            except (ValueError, UnicodeDecodeError) as exc:
                if not raw.endswith(b"\n"):
                    st.truncated += 1
                    st.last_event = ""  # cut off while written: not the end of a clean exit
                    continue
                if strict:
                    raise ParseError(f"{path}:{lineno}: not a recording line: {exc}") from exc
                st.bad_lines += 1
                continue
            st.records += 1
            if rec.type == "event":
                name = rec.data.get("event")
                st.last_event = name if isinstance(name, str) else ""
                if name == GAP_EVENT:
                    st.gaps += 1
                    lost = rec.data.get("records_lost")
                    if isinstance(lost, int) and not isinstance(lost, bool):
                        st.gap_records_lost += lost
            else:
                st.last_event = ""
            yield rec


def _utc_field(value: Any) -> datetime | None:
    if not isinstance(value, str):
        return None
    try:
        return datetime.fromisoformat(value)
    except ValueError:
        return None


_KINDS: dict[Any, tuple[type, ...]] = {float: (int, float), int: (int,), bool: (bool,)}


@functools.cache
def _fields_of(cls: type) -> tuple[frozenset[str], dict[str, tuple[tuple[type, ...], bool]]]:
    """A record class's field names, and for its number and flag fields (``float``, ``int``,
    ``bool``, each maybe ``| None``) the JSON types they take and whether None is one."""
    checks = {}
    for name, hint in typing.get_type_hints(cls).items():
        args = typing.get_args(hint) if isinstance(hint, types.UnionType) else (hint,)
        rest = [a for a in args if a is not type(None)]
        if len(rest) == 1 and rest[0] in _KINDS:
            checks[name] = (_KINDS[rest[0]], len(rest) < len(args))
    return frozenset(f.name for f in dataclasses.fields(cls)), checks


def _typed(cls: type, d: Any) -> Any:
    """``cls(**d)`` without ``d``'s unknown keys (a newer recorder may add fields: the
    record is kept, see :func:`unknown_fields`); TypeError when a field is missing or a
    number or flag holds anything else (``"51.75"``, ``true`` for a number)."""
    if not isinstance(d, dict):
        raise TypeError(f"{cls.__name__} is {type(d).__name__}, not an object")
    names, checks = _fields_of(cls)
    kw = {k: v for k, v in d.items() if k in names}
    for k, (kinds, optional) in checks.items():
        v = kw.get(k)
        if k not in kw or (v is None and optional):
            continue
        if not isinstance(v, kinds) or (isinstance(v, bool) and bool not in kinds):
            raise TypeError(f"{cls.__name__}.{k} is {v!r}")
    return cls(**kw)


def decode_record(
    rec: Record,
) -> Attitude | MotorCommand | StateChange | GpsFix | GpsSky | WheelOdometry | Record:
    """The typed record behind an attitude, motor, state, fix, sky or odometry record; other types
    (nmea, telemetry, event) are returned unchanged. A fix's or sky's fields that the type
    does not have are ignored (:func:`unknown_fields` names them), its numbers and flags
    checked. Raises :class:`ParseError` when the payload does not fit its type (a field
    missing or unknown, a fix's or sky's number that is not one)."""
    d = rec.data
    try:
        if rec.type == "fix":
            return _typed(GpsFix, {**d, "utc": _utc_field(d.get("utc"))})
        if rec.type == "sky":
            sats = tuple(_typed(SatInfo, s) for s in d.get("satellites", ()))
            return _typed(GpsSky, {**d, "satellites": sats, "utc": _utc_field(d.get("utc"))})
        cls = _RECORD_CLASSES.get(rec.type)
        if cls is not None:  # as strict as ever: their readers judge the values themselves
            return cls(**d)
    except TypeError as exc:
        raise ParseError(f"{rec.type} record at t_mono={rec.t_mono}: {exc}") from exc
    return rec


_RECORD_CLASSES: dict[str, type] = {
    "attitude": Attitude,
    "motor": MotorCommand,
    "state": StateChange,
    "odometry": WheelOdometry,
}


def unknown_fields(rec: Record) -> list[str]:
    """The fields of a fix or sky record (see :func:`decode_record`) that its type does not
    have and decoding ignores, satellites' included; [] for other types."""
    cls = {"fix": GpsFix, "sky": GpsSky}.get(rec.type)
    if cls is None:
        return []
    out = sorted(rec.data.keys() - _fields_of(cls)[0])
    if rec.type == "sky" and isinstance(sats := rec.data.get("satellites"), list):
        names = _fields_of(SatInfo)[0]
        out += sorted(
            {f"satellites.{k}" for s in sats if isinstance(s, dict) for k in s.keys() - names}
        )
    return out


_PART_NAME = re.compile(r"^(.+)\.[1-9]\d*(\.[^.]+)$")


def recording_parts(path: str | os.PathLike[str]) -> list[Path]:
    """The existing files of the recording whose first part is ``path``: ``path`` itself and
    its rotated parts ``<stem>.1<suffix>``, ``.2`` ..., in part order. Parts that retention
    deleted are skipped (the first ones go first), so the list may not start at ``path``.

    ``path`` may also name any part ``<stem>.N<suffix>`` (the first remaining one, once
    retention deleted the first part, is what a folder's newest run is found as): the list
    is then every remaining part of its run ``<stem><suffix>``, not ``path``'s own
    sub-parts ``<stem>.N.1<suffix>``, which the recorder never writes."""
    first = Path(path)
    if m := _PART_NAME.match(first.name):
        first = first.with_name(m[1] + m[2])
    found: list[tuple[int, Path]] = [(0, first)] if first.is_file() else []
    head, tail = f"{first.stem}.", first.suffix
    try:
        names = os.listdir(first.parent)
    except FileNotFoundError:
        names = []
    for name in names:
        if name.startswith(head) and name.endswith(tail):
            n = name[len(head) : len(name) - len(tail)]
            if n.isdigit() and n[0] != "0":
                found.append((int(n), first.with_name(name)))
    return [p for _, p in sorted(found)]


def read_recording_parts(
    path: str | os.PathLike[str], *, stats: ReadStats | None = None, strict: bool = False
) -> Iterator[Record]:
    """Yield the records of every remaining part of a recording (see :func:`recording_parts`)
    in order, as :func:`read_recording` reads one file. Raises :class:`DeviceUnavailable`
    when no part exists."""
    parts = recording_parts(path)
    if not parts:
        what = (
            "a directory, not a recording"
            if Path(path).is_dir()
            else "no such file, nor parts of it"
        )
        raise DeviceUnavailable(f"cannot open recording {path}: {what}")
    for part in parts:
        _refuse_compressed(part)
        yield from read_recording(part, stats=stats, strict=strict)


def _refuse_compressed(path: str | os.PathLike[str]) -> None:
    """:class:`ParseError` for a compressed regular file (read as a recording it held no
    record: ``calibrate odometry`` said "fewer than 2 odometry records" of a .jsonl.gz)."""
    if not_regular(path) is not None:
        return
    try:
        with open(path, "rb") as f:
            kind = compression_of(f.read(8))
    except OSError:
        return  # the reader says what is wrong with it
    if kind is not None:
        raise compressed_error(path, kind)


def compressed_error(path: str | os.PathLike[str], kind: str) -> ParseError:
    """The error for a recording or log compressed with ``kind`` (gzip, bzip2 ...)."""
    hint = " (x6wd decode reads gzip)" if kind == "gzip" else ""
    return ParseError(f"{path}: compressed ({kind}): decompress it first{hint}")


HEAD_LINES = 8
"""Non-blank lines :func:`looks_like_recording` looks at past damaged ones (garbage, a block
of NULs from a card) for the first intact line that tells the format."""


def looks_like_recording(head: bytes) -> bool:
    """True when ``head`` (a file's first bytes) begins like a recording: its first non-blank
    line is a JSON object, or, when that line and the next few are damaged (neither JSON nor
    NMEA), the first intact one is a recorder record. A complete line of gpsd's own JSON (an
    object with a ``class`` and no ``t_mono``, as ``gpspipe -r`` writes before the NMEA it
    captures) decides nothing: such a file is NMEA with a few lines of noise. A torn first
    line still counts, so the recording reader can name the fault."""
    # line by line up to HEAD_LINES: the head is up to 1 MiB (~15,000 NMEA lines), and
    # splitting and stripping all of it was ~4 % of `x6wd decode` on gpsd's corpus
    lines: list[tuple[bytes, bool]] = []
    start = 0
    while len(lines) < HEAD_LINES:
        end = head.find(b"\n", start)
        if end < 0:
            t = head[start:].strip()
            if t:
                lines.append((t, False))
            break
        t = head[start:end].strip()
        if t:
            lines.append((t, True))
        start = end + 1
    for k, (text, complete) in enumerate(lines):
        if text[:1] in (b"$", b"!"):
            return False  # NMEA
        if text[:1] != b"{":
            continue  # damaged: the reader skips and counts it
        if not complete:
            return True  # torn (or longer than the head)
        try:
            obj = json.loads(text)
        except ValueError:
            if k == 0:
                return True
            continue
        if isinstance(obj, dict) and "class" in obj and "t_mono" not in obj:
            continue  # gpsd's own JSON
        if k == 0 or (isinstance(obj, dict) and ("t_mono" in obj or "type" in obj)):
            return True
    return False


_HEAD_BYTES = 1 << 16  # enough for HEAD_LINES records; a first line longer is judged by its start


COMPRESSED_MAGIC = (
    (b"\x1f\x8b", "gzip"),
    (b"BZh", "bzip2"),
    (b"\xfd7zXZ\x00", "xz"),
    (b"\x28\xb5\x2f\xfd", "zstd"),
    (b"PK\x03\x04", "zip"),
)
"""The first bytes of compressed files (no log begins so)."""


def compression_of(head: bytes) -> str | None:
    """The compression (``"gzip"``, ``"bzip2"``, ...) a file's first bytes show, or None."""
    for magic, kind in COMPRESSED_MAGIC:
        if head.startswith(magic):
            return kind
    return None


def is_recording(path: str | os.PathLike[str]) -> bool:
    """True when the file begins like a recording (:func:`looks_like_recording`), False for
    plain NMEA or other text. A first part that retention deleted is judged by its first
    remaining part.

    Raises :class:`DeviceUnavailable` for an input that is not a regular file (a pipe such
    as ``<(zcat log.gz)``, a FIFO, a device: its readers open the path again, which loses a
    pipe's first bytes or waits forever on a FIFO; ``x6wd decode`` reads such inputs as a
    stream) and :class:`ParseError` for a compressed file."""
    parts = [] if Path(path).exists() else recording_parts(path)
    if parts:
        path = parts[0]
    kind = not_regular(path)
    if kind is not None:
        raise DeviceUnavailable(
            f"cannot read {path}: not a regular file ({kind}), and it is read more than"
            " once: save it to a file first (x6wd decode reads it, or '-', as a stream)"
        )
    try:
        with open(path, "rb") as f:
            head = f.read(_HEAD_BYTES)
    except OSError as exc:
        raise DeviceUnavailable(f"cannot open {path}: {exc}") from exc
    compressed = compression_of(head)
    if compressed is not None:
        raise compressed_error(path, compressed)
    return looks_like_recording(head)


_GPSD_CLASSES = frozenset({"VERSION", "DEVICES", "DEVICE", "WATCH", "TPV", "SKY", "GST", "ATT"})


def is_gpsd_json(path: str | os.PathLike[str], max_lines: int = 20) -> bool:
    """Whether one of the first ``max_lines`` lines is a gpsd report (a JSON object with a
    gpsd ``class``): asked of a file read as no recording and no log, to say what it is."""
    with open(path, "rb") as f:
        for _, raw in zip(range(max_lines), f, strict=False):
            try:
                obj = json.loads(raw)
            except ValueError:
                continue
            if isinstance(obj, dict) and obj.get("class") in _GPSD_CLASSES:
                return True
    return False


def gpsd_json_error(path: str | os.PathLike[str], tool: str) -> str:
    """What to say of gpsd JSON given to ``tool`` ("the gap tool"), which reads NMEA."""
    return (
        f"{path}: gpsd JSON (TPV/SKY reports, as gpspipe -w or x6wd decode write them),"
        f" which {tool} does not read: give it the receiver's NMEA, recorded with"
        " gpspipe -r > log.nmea (or the NMEA log the JSON was decoded from)"
    )


def _check_speed(speed: float) -> float:
    if isinstance(speed, bool) or not isinstance(speed, (int, float)):
        raise ValueError(f"speed must be a number >= 0, got {speed!r}")
    if not (math.isfinite(speed) and speed >= 0):
        raise ValueError(f"speed must be finite and >= 0 (0 = as fast as possible), got {speed}")
    return float(speed)


MAX_SLEEP_S = 60.0  # the longest single sleep of a paced replay (s)
MAX_GAP_S = 60.0  # a longer forward jump of recorded time is not waited out (s)
GAP_REPLAY_S = 1.0  # ... but replayed as this much recorded time (s)


class _Pacer:
    """Releases items at ``start + (t - t0) / speed`` on the wall clock (speed 0: at once).

    A backward jump of the recorded time (a restarted clock, a second session) goes on
    without a pause and is passed to ``on_back(t, step_s)`` (``step_s`` < 0); a forward jump
    of more than :data:`MAX_GAP_S` (a receiver switched off, logs joined, a clock reset to a
    default) is replayed as :data:`GAP_REPLAY_S`, counted in :attr:`gaps` and passed to
    ``on_gap(t, jump_s)``: a real-time replay must not go silent for hours."""

    def __init__(
        self,
        speed: float,
        clock: Callable[[], float],
        sleep: Callable[[float], Any],
        on_gap: Callable[[float, float], Any] | None = None,
        on_back: Callable[[float, float], Any] | None = None,
    ) -> None:
        self.speed = speed
        self.clock = clock
        self.sleep = sleep
        self.on_gap = on_gap
        self.on_back = on_back
        self.gaps = 0
        self._t0: float | None = None  # recorded time of the pace origin
        self._wall0 = 0.0
        self._last_t: float | None = None
        self._offset = 0.0  # added to recorded times so jumps do not stall

    def due(self, t: float) -> float:
        """Wall time at which recorded time ``t`` is due."""
        if self._last_t is not None:
            step = t + self._offset - self._last_t
            if step < 0:
                self._offset -= step  # clock restarted in the recording: continue
                if self.on_back is not None:
                    self.on_back(t, step)
            elif step > MAX_GAP_S:
                self._offset -= step - GAP_REPLAY_S
                self.gaps += 1
                if self.on_gap is not None:
                    self.on_gap(t, step)
        t += self._offset
        self._last_t = t
        if self._t0 is None:
            self._t0, self._wall0 = t, self.clock()
        if self.speed == 0:
            return self._wall0
        return self._wall0 + (t - self._t0) / self.speed

    def wait(self, t: float) -> None:
        due = self.due(t)
        while True:
            remaining = due - self.clock()
            if remaining <= 0:
                return
            # in pieces: a speed of 1e-300 makes remaining too large for the OS to sleep
            self.sleep(min(remaining, MAX_SLEEP_S))


def replay_records(
    path: str | os.PathLike[str],
    speed: float = 1.0,
    *,
    stats: ReadStats | None = None,
    clock: Callable[[], float] = time.monotonic,
    sleep: Callable[[float], Any] = time.sleep,
) -> Iterator[Record]:
    """Yield a recording's records at the recorded pace divided by ``speed``.

    ``speed`` 1 is real time, 2 twice as fast, 0 as fast as possible. Pacing follows
    ``t_mono``; a backward jump (a restarted clock) is replayed without a pause.
    """
    pacer = _Pacer(_check_speed(speed), clock, sleep)
    for rec in read_recording(path, stats=stats):
        pacer.wait(rec.t_mono)
        yield rec


# --- byte-stream replay (a pyserial-like port) ------------------------------------------------

_TIME_FIELD = {"GGA": 1, "RMC": 1, "GLL": 5, "ZDA": 1, "GNS": 1, "GBS": 1, "GST": 1, "GRS": 1}
_HHMMSS = re.compile(rb"^(\d{2})(\d{2})(\d{2}(?:\.\d+)?)$")


def _sentence_utc_s(line: bytes) -> float | None:
    """Seconds of day from a sentence's UTC time field, or None (also for a sentence whose
    checksum fails: line noise in its time field made a replay wait 20 s, an outside audit;
    one without a checksum is taken as it is)."""
    start = line.find(b"$")
    if start < 0 or len(line) < start + 7:
        return None
    body, star, tail = line[start + 1 :].partition(b"*")
    if star:
        try:
            given = int(tail[:2], 16)
        except ValueError:
            return None
        # (drivers.nmea.checksum is a layer above: the XOR is written here again)
        if len(tail.rstrip()) < 2 or functools.reduce(operator.xor, body, 0) != given:
            return None
    fields = body.split(b",")
    kind = fields[0][-3:].decode("ascii", "replace")
    idx = _TIME_FIELD.get(kind)
    if idx is None or idx >= len(fields):
        return None
    m = _HHMMSS.match(fields[idx].strip())
    if m is None:
        return None
    h, mi, s = int(m[1]), int(m[2]), float(m[3])
    if h > 23 or mi > 59 or s >= 61:
        return None
    return h * 3600 + mi * 60 + s


def nmea_file_chunks(
    path: str | os.PathLike[str], rate_hz: float = 1.0
) -> Iterator[tuple[float, bytes]]:
    """(time s, line bytes) of a plain NMEA log, the bytes exactly as in the file, streamed
    (memory does not grow with the file).

    A line's time is the UTC time of the latest sentence carrying one (and passing its
    checksum, when it has one), in seconds after the first such time (earlier lines get 0).
    Successive times are taken to be within 12 h of each other, so the day wraps at midnight
    both ways: a receiver whose clock restarts from a default just before midnight steps back
    minutes, not on a day. In a file without any
    UTC time, an epoch ends where a sentence type comes again (the parts of a multi-part GSV
    are one; see :func:`_untimed_epochs`) and epochs are ``1/rate_hz`` s apart. Raises
    :class:`DeviceUnavailable` if the file cannot be opened.
    """
    if not (rate_hz > 0 and math.isfinite(rate_hz)):
        raise ValueError(f"rate_hz must be > 0, got {rate_hz!r}")
    try:
        f = open(path, "rb")  # noqa: SIM115 - closed by the generator
    except OSError as exc:
        raise DeviceUnavailable(f"cannot open {path}: {exc}") from exc
    return _nmea_lines_timed(f, rate_hz)


_BLOCK_BYTES = 1 << 16
_MAX_LINE_BYTES = 1 << 20  # a longer run without a line end (binary) is passed on in pieces


_LINE = re.compile(rb"[^\r\n]*(?:\r*\n|\r)")  # CR+ LF is one line end (a Windows logger's CR CR LF)


def _file_lines(f: BinaryIO) -> Iterator[bytes]:
    """The lines of ``f`` from where it is, ends kept, read by blocks: split at LF, at CRs
    then LF (CRLF; CR CR LF, a Windows text-mode logger's: one line, as ``wc -l`` counts)
    and at a CR alone (some receivers end sentences with CR alone)."""
    carry = b""
    while block := f.read(_BLOCK_BYTES):
        buf = carry + block
        # the block's last CRs may yet be followed by an LF: kept with their line
        limit = len(buf.rstrip(b"\r"))
        # matched only up to the last line end: past it the pattern was tried at every
        # offset, each try scanning to the end (quadratic: 256 KiB of an SD card's zeros
        # after a power cut took ~20 min)
        last = max(buf.rfind(b"\n", 0, limit), buf.rfind(b"\r", 0, limit))
        lines = _LINE.findall(buf, 0, last + 1) if last >= 0 else []
        carry = buf[sum(map(len, lines)) :]
        if len(carry) > _MAX_LINE_BYTES:
            lines.append(carry)
            carry = b""
        yield from lines
    if carry:
        yield carry


MAX_UNTIMED_HEAD_BYTES = 16 << 20
"""A stream that cannot be read twice (a pipe) is held this far (bytes) while looking for
its first sentence time; without a sentence by then, it is no NMEA log (``/dev/zero``)."""


def regular_stream(f: IO[bytes]) -> bool:
    """True for a regular file (which ends, and can be read again); a file object without a
    descriptor counts as one when it can seek (``io.BytesIO``)."""
    try:
        return stat.S_ISREG(os.fstat(f.fileno()).st_mode)
    except (OSError, ValueError, AttributeError):  # io.UnsupportedOperation is an OSError
        return f.seekable()


def _first_time(f: BinaryIO) -> tuple[float | None, Iterator[bytes]]:
    """The first sentence time of ``f`` and its lines from the start. A seekable file is
    read twice; a stream once, its lines up to the first time held: at most
    :data:`MAX_UNTIMED_HEAD_BYTES`, then it is taken as untimed (its epochs counted by
    sentence type), or, without any sentence so far, refused (:class:`ParseError`)."""
    if regular_stream(f):
        first = next((t for t in map(_sentence_utc_s, _file_lines(f)) if t is not None), None)
        f.seek(0)
        return first, _file_lines(f)
    held: list[bytes] = []
    n, sentences = 0, False
    lines = _file_lines(f)
    for line in lines:
        held.append(line)
        t = _sentence_utc_s(line)
        if t is not None:
            return t, chain(held, lines)
        n += len(line)
        sentences = sentences or b"$" in line
        if n > MAX_UNTIMED_HEAD_BYTES:
            if not sentences:
                raise ParseError(
                    f"no NMEA sentence in its first {MAX_UNTIMED_HEAD_BYTES >> 20} MiB: not"
                    " an NMEA log (given up)"
                )
            return None, chain(held, lines)  # sentences without times: epochs by type
    return None, iter(held)


def _nmea_lines_timed(f: BinaryIO, rate_hz: float) -> Iterator[tuple[float, bytes]]:
    with f:
        first, lines = _first_time(f)
        if first is not None:
            current = first
            for line in lines:
                t = _sentence_utc_s(line)
                if t is not None:
                    day = current - current % 86_400
                    t += day
                    if t < current - 43_200:  # midnight, forwards
                        t += 86_400
                    elif t > current + 43_200:  # midnight, backwards
                        t -= 86_400
                    current = t
                yield current - first, line
            return
        yield from _untimed_epochs(lines, rate_hz)


_TYPES_HEAD_LINES = 1000  # an untimed log's head that tells one sentence type from several


def _untimed_epochs(lines: Iterator[bytes], rate_hz: float) -> Iterator[tuple[float, bytes]]:
    """Times of a log without any: an epoch ends where a sentence's :func:`_epoch_key` comes
    again after a sentence of another type, or right after itself; not in a run of one type
    in between (a ST Teseo's GSAs: twice per system, 1,3,4,1,3,4) nor a GNGSA after a GNGSA
    (a u-blox 8's: one per system without its id). A log of one type alone (its first
    lines tell) has no other type between: there any repeat ends the epoch (a GNGSA's
    right after itself still not)."""
    head = list(islice(lines, _TYPES_HEAD_LINES))
    by_run = len({k[2:5] for k in map(_epoch_key, head) if k}) > 1
    seen: dict[bytes, int] = {}  # key -> the run (of one type) it came first in this epoch
    epoch = run = 0
    last = b""
    for line in chain(head, lines):
        key = _epoch_key(line)
        if key:
            if key[2:5] != last[2:5]:
                run += 1
            # back to back: a new epoch but for a GNGSA (one per system, NMEA 4.0: no id)
            if key in seen and (key != b"GNGSA" if key == last else not by_run or seen[key] != run):
                epoch += 1
                seen.clear()
            seen.setdefault(key, run)
            last = key
        yield epoch / rate_hz, line


_MULTIPART = (b"GSV", b"RTE")  # fields 1 and 2: the group's parts, this part's number
_ADDRESS = re.compile(rb"[A-Z0-9]{5}[,*]")  # a sentence's talker and type, then its fields


def _epoch_key(line: bytes) -> bytes | None:
    """What a sentence repeats as from one epoch to the next in a log without times: its type
    (b"" for no sentence); a GSA's with its system id and a GSV's with its signal id (NMEA
    4.10 sends one of each per system or signal and epoch). None for what does not: part 2
    on of a multi-part group (GSV, RTE: in the epoch of its part 1), TXT (a notice sent
    any time, a start-up banner several at once, a long one in parts) and a proprietary
    ``$P...`` (a ST Teseo's ``$PSTMVER`` banner, anything at any time); b"" also for a
    ``$`` not followed by a talker and type (binary, a comment). A doubled ``$`` (a ST
    Teseo's ``$$GNGSA``) is one, as the decoder reads it."""
    start = line.find(b"$")
    body = line[start:].lstrip(b"$") if start >= 0 else b""
    if body[:1] == b"P":
        return None
    if not _ADDRESS.match(body):
        return b""  # a "$" in binary (UBX) or a comment
    kind = body[:5]
    tail = kind[2:]
    if tail == b"TXT":
        return None
    if tail not in _MULTIPART and tail != b"GSA":
        return kind
    fields = body.split(b"*", 1)[0].split(b",")
    if tail == b"GSA":
        return kind + b"," + fields[18].strip() if len(fields) > 18 else kind
    part = fields[2].strip() if len(fields) > 2 else b""
    if part.isdigit() and int(part) > 1:
        return None
    if tail == b"GSV" and len(fields) % 4 == 1:  # 4 + 4 per satellite + the signal id
        return kind + b"," + fields[-1].strip()
    return kind


def recording_nmea_chunks(
    path: str | os.PathLike[str], stats: ReadStats | None = None
) -> Iterator[tuple[float, bytes]]:
    """(t_mono s, sentence bytes + CRLF) for every nmea record of a recording (all of its
    remaining parts, in order)."""
    for rec in read_recording_parts(path, stats=stats):
        if rec.type == "nmea":
            text = rec.data.get("text")
            if isinstance(text, str):
                yield rec.t_mono, text.encode("utf-8", "replace") + b"\r\n"


def nmea_chunks(
    path: str | os.PathLike[str], *, rate_hz: float = 1.0, stats: ReadStats | None = None
) -> Iterator[tuple[float, bytes]]:
    """(time s, bytes) of the NMEA in a recording or a plain log, whichever ``path`` is."""
    if is_recording(path):
        return recording_nmea_chunks(path, stats)
    return nmea_file_chunks(path, rate_hz)


def paced(
    chunks: Iterator[tuple[float, bytes]],
    speed: float = 1.0,
    *,
    clock: Callable[[], float] = time.monotonic,
    sleep: Callable[[float], Any] = time.sleep,
    on_gap: Callable[[float, float], Any] | None = None,
    on_back: Callable[[float, float], Any] | None = None,
) -> Iterator[tuple[float, bytes]]:
    """Yield ``chunks`` no earlier than their recorded time divided by ``speed`` (0: at once),
    counted from the first chunk; forward jumps of more than :data:`MAX_GAP_S` are shortened
    (``on_gap(t, jump_s)`` is told), backward ones played on at once (``on_back(t, step_s)``
    is told, before the chunk at ``t`` is yielded)."""
    pacer = _Pacer(_check_speed(speed), clock, sleep, on_gap, on_back)
    for t, data in chunks:
        pacer.wait(t)
        yield t, data


@dataclass
class _ReplayState:
    buffer: bytearray = field(default_factory=bytearray)
    pending: tuple[float, bytes] | None = None
    eof: bool = False


class ReplayPort:
    """A pyserial-like, read-only port that plays a recording or a plain NMEA log.

    ``read(n)`` returns what has been "received" by now: chunks become available at their
    recorded time divided by ``speed`` (0 = everything at once). ``timeout`` works as in
    pyserial: None blocks until at least one byte (or the end), 0 never waits, t > 0 waits
    at most t seconds. At the end of the data ``read`` returns b"" and :attr:`eof` is True.
    Recordings are detected from their content; of them only the nmea records are played.
    """

    def __init__(
        self,
        path: str | os.PathLike[str],
        speed: float = 1.0,
        *,
        rate_hz: float = 1.0,
        timeout: float | None = None,
        clock: Callable[[], float] = time.monotonic,
        sleep: Callable[[float], Any] = time.sleep,
    ) -> None:
        self.path = Path(path)
        self.speed = _check_speed(speed)
        self.timeout = timeout
        self.stats = ReadStats()
        self._clock = clock
        self._sleep = sleep
        self._pacer = _Pacer(self.speed, clock, sleep)
        self.is_recording = is_recording(self.path)
        self._chunks = nmea_chunks(self.path, rate_hz=rate_hz, stats=self.stats)
        self._st = _ReplayState()
        self.is_open = True
        self.bytes_read = 0

    @property
    def eof(self) -> bool:
        """True when every byte was read."""
        return self._st.eof and not self._st.buffer

    @property
    def log_silent(self) -> bool:
        """True while the log itself has nothing due now but more to come later: a stretch
        in which its receiver sent nothing (or a slow replay between epochs). Any thread may
        read it."""
        st = self._st
        pending = st.pending
        return pending is not None and not st.buffer and pending[0] > self._clock()

    def _pull(self, now: float) -> float | None:
        """Move due chunks into the buffer; the wall time of the next one, or None at end."""
        st = self._st
        while not st.eof:
            if st.pending is None:
                try:
                    t, data = next(self._chunks)
                except StopIteration:
                    st.eof = True
                    return None
                st.pending = (self._pacer.due(t), data)
            due, data = st.pending
            if due > now:
                return due
            st.buffer += data
            st.pending = None
        return None

    @property
    def in_waiting(self) -> int:
        """Bytes available now without waiting."""
        self._pull(self._clock())
        return len(self._st.buffer)

    def read(self, size: int = 1) -> bytes:
        """Up to ``size`` bytes, waiting as the timeout allows (see the class doc)."""
        if not self.is_open:
            raise DeviceUnavailable(f"replay port {self.path} is closed")
        if size <= 0:
            return b""
        start = self._clock()
        while True:
            now = self._clock()
            next_due = self._pull(now)
            buf = self._st.buffer
            if buf or next_due is None:
                out = bytes(buf[:size])
                del buf[:size]
                self.bytes_read += len(out)
                return out
            if self.timeout is not None:
                limit = start + self.timeout
                if now >= limit:
                    return b""
                next_due = min(next_due, limit)
            self._sleep(max(next_due - now, 0.0))

    def readline(self) -> bytes:
        """Bytes up to and including the next b"\\n" (or what the timeout/end leaves)."""
        out = bytearray()
        while True:
            buf = self._st.buffer
            i = buf.find(b"\n")
            if i >= 0:
                out += buf[: i + 1]
                del buf[: i + 1]
                self.bytes_read += i + 1
                return bytes(out)
            if buf:
                out += buf
                self.bytes_read += len(buf)
                buf.clear()
            chunk = self.read(1)
            if not chunk:
                return bytes(out)
            out += chunk
            if chunk == b"\n":
                return bytes(out)

    def write(self, data: bytes) -> int:
        """Accepted and dropped (a receiver being configured over a replay ignores it)."""
        return len(data)

    def reset_input_buffer(self) -> None:
        """Drop what is buffered now."""
        self._st.buffer.clear()

    def close(self) -> None:
        """Close (idempotent)."""
        self.is_open = False

    def __enter__(self) -> ReplayPort:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
