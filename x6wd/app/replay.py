"""`x6wd replay FILE [--speed S]`: play a recording or an NMEA log through the real decoder.

Prints one summary line per fix (``--json``: one compact JSON object per fix, and per sky
report with ``--sky``); the decoder's counters and the reader's counts go to stderr. The
bytes reach :class:`drivers.gps_nmea.GpsDecoder` at the recorded pace divided by ``--speed``
(0: as fast as possible), stamped with the recorded time (s): ``t_mono`` for recordings,
seconds since the first sentence time for plain NMEA logs (in a log without any, epochs
``1/--rate`` s apart, see ``x6wd.core.recorder.nmea_file_chunks``). Where that time goes
back (a second session in the file, a restarted clock) the replay plays on without a pause
and t goes back with it; stderr says so with the line (of a plain log) and t, the first
:data:`MAX_BACKS_SAID` one by one and then how many in all. A forward jump of more than 60 s
is replayed as 1 s and said likewise, at any speed (``--speed 0`` included). A plain log's
line is as ``grep -n`` counts it (a CR CR LF ends one line), or a CR alone's.

A run recorded in parts whose first (or other) parts retention deleted is said before it is
played, as ``x6wd plot`` says it: the parts gone and, the first being gone, the run's start by
its name and how long before the first record read it was (that start is not replayed). A
directory is replayed as ``x6wd plot`` draws it: the first remaining part of its newest run.

The input is read more than once (its head tells recording from log, a log's first sentence
time is found first), so it must be a regular file: a pipe (``<(zcat log.gz)``), a FIFO or a
device is refused before it is opened, as is a compressed file (exit 2, saying so; ``x6wd
decode`` reads those as a stream). See ``x6wd.core.recorder.is_recording``.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import sys
from datetime import datetime
from pathlib import Path
from typing import Any, TextIO

from x6wd.app.logview import (
    LogView,
    _duration,
    _missing_parts,
    missing_parts_note,
    newest_recording,
)
from x6wd.core.errors import ConfigError, ParseError
from x6wd.core.recorder import (
    GAP_REPLAY_S,
    InputSize,
    ReadStats,
    is_recording,
    nmea_chunks,
    nothing_decoded,
    paced,
    read_recording,
    recording_parts,
    recording_writer,
    to_jsonable,
)
from x6wd.core.records import GpsFix, GpsSky


def _number(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not math.isfinite(v):
        raise argparse.ArgumentTypeError(f"must be a finite number: {text!r}")
    return v


def _speed(text: str) -> float:
    v = _number(text)
    if v < 0:
        raise argparse.ArgumentTypeError(f"must be >= 0 (0 = as fast as possible): {text!r}")
    return v


def _rate(text: str) -> float:
    v = _number(text)
    if v <= 0:
        raise argparse.ArgumentTypeError(f"must be > 0: {text!r}")
    return v


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``x6wd replay``."""
    parser.add_argument(
        "file",
        metavar="FILE",
        help="a flight recording (.jsonl) or NMEA log (a regular file); a directory: its"
        " newest recording",
    )
    parser.add_argument(
        "--speed",
        type=_speed,
        default=1.0,
        help="pace: 1 = as recorded (default), 10 = ten times faster, 0 = as fast as possible",
    )
    parser.add_argument(
        "--rate",
        type=_rate,
        default=1.0,
        help="epochs per second for NMEA logs without sentence times (default 1)",
    )
    parser.add_argument("--json", action="store_true", help="one JSON object per line")
    parser.add_argument("--sky", action="store_true", help="also report sky (satellite) views")


MAX_BACKS_SAID = 10
"""Steps back of the recorded time said one by one on stderr, and as many forward jumps;
more are counted (a log of epochs out of order steps back every other epoch)."""


def fix_line(fix: GpsFix) -> str:
    """Human summary of one fix: time, position (deg), altitude (m), quality, speed (m/s)."""

    def num(v: float | None, fmt: str) -> str:
        return "-" if v is None else format(v, fmt)

    utc = fix.utc.isoformat() if fix.utc is not None else "-"
    return (
        f"t={fix.t_s:.3f} utc={utc} valid={int(fix.valid)} mode={fix.mode} q={fix.quality} "
        f"lat={num(fix.lat_deg, '.7f')} lon={num(fix.lon_deg, '.7f')} "
        f"alt_m={num(fix.alt_m, '.1f')} sats={fix.sats_used if fix.sats_used is not None else '-'}"
        f" hdop={num(fix.hdop, '.2f')} speed_mps={num(fix.speed_mps, '.2f')} "
        f"course_deg={num(fix.course_deg, '.1f')}"
    )


def sky_line(sky: GpsSky) -> str:
    """Human summary of one sky report: satellites seen/used and DOPs."""
    used = sum(1 for s in sky.satellites if s.used)
    dops = " ".join(
        f"{name}={'-' if v is None else format(v, '.2f')}"
        for name, v in (("pdop", sky.pdop), ("hdop", sky.hdop), ("vdop", sky.vdop))
    )
    return f"t={sky.t_s:.3f} sky nSat={len(sky.satellites)} uSat={used} {dops}"


def missing_parts_line(path: str) -> str:
    """What ``x6wd replay`` says of a recording ``path`` whose run's parts retention deleted,
    worded as ``x6wd plot`` says it (:func:`x6wd.app.logview.missing_parts_note`); "" when
    none is gone. With the first part gone: the run's start by its name and the time from it
    to the first record read (by the recorder's clock, as the plot measures it)."""
    gone, run_start = _missing_parts(Path(path))
    if not gone:
        return ""
    text = missing_parts_note(LogView(Path(path), "recording", missing_parts=gone))
    if run_start is not None:
        first = next(read_recording(recording_parts(path)[0]), None)  # dropped: file closed
        utc = None
        with contextlib.suppress(ValueError, TypeError):  # no t_utc: a time unknown
            utc = datetime.fromisoformat(first.t_utc) if first is not None else None
        lost_s = (utc - run_start).total_seconds() if utc and utc.tzinfo else -1.0
        how_long = f"about {_duration(lost_s)}" if lost_s >= 0 else "a time unknown"
        text += (
            f": the run began at {run_start.isoformat()} (its name), {how_long} before the first"
            " record read, and that start is not replayed"
        )
    return text


def _emit(obj: GpsFix | GpsSky, as_json: bool, out: TextIO) -> None:
    if as_json:
        d: dict[str, Any] = {"class": "fix" if isinstance(obj, GpsFix) else "sky"}
        d.update(to_jsonable(obj))
        out.write(json.dumps(d, separators=(",", ":")) + "\n")
    else:
        out.write((fix_line(obj) if isinstance(obj, GpsFix) else sky_line(obj)) + "\n")


def replay_file(
    path: str,
    *,
    speed: float = 1.0,
    rate_hz: float = 1.0,
    as_json: bool = False,
    sky: bool = False,
    out: TextIO | None = None,
    err: TextIO | None = None,
) -> dict[str, int]:
    """Decode ``path`` (a directory: its newest run) through :class:`GpsDecoder`, write the
    reports to ``out`` (default stdout) and the counts to ``err`` (default stderr); return
    the counts. Raises :class:`ParseError` for a file that is not empty but holds nothing to
    decode."""
    from drivers.gps_nmea import GpsDecoder

    out = sys.stdout if out is None else out
    err = sys.stderr if err is None else err
    if Path(path).is_dir():  # as x6wd plot: the newest run in it
        path = str(newest_recording(Path(path)))

    stats = ReadStats()
    recording = is_recording(path)
    if recording and (gone := missing_parts_line(path)):
        err.write(f"x6wd replay: {path}: {gone}\n")
    # a recorder's lock, tested before reading (after it, a run finishing in between would
    # read as cut short)
    writer_before = recording_writer(path) if recording else None
    decoder = GpsDecoder(emit_sentences=False)
    fixes = skies = 0
    t_last = 0.0
    size = InputSize()

    played = 0  # chunks played (a plain log's are its lines)
    jumps = {"goes back": 0, "jumps forward": 0}  # the recorded time's steps back, jumps

    def say(how: str, text: str) -> None:
        jumps[how] += 1
        if jumps[how] <= MAX_BACKS_SAID:
            err.write(f"x6wd replay: the recorded time {text}\n")

    def where(t_s: float) -> str:  # told before chunk ``played + 1`` is played
        return f"at {'' if recording else f'line {played + 1}, '}t={t_s:.3f}"

    def on_gap(t_s: float, jump_s: float) -> None:  # said at any speed, as a step back is
        paced_how = f": not waited out (replayed as {GAP_REPLAY_S:g} s)" if speed else ""
        say("jumps forward", f"jumps {jump_s:.0f} s forward {where(t_s)}{paced_how}")

    def on_back(t_s: float, step_s: float) -> None:
        say(
            "goes back",
            f"goes back {-step_s:.1f} s {where(t_s)} (another session or a restarted clock):"
            " played on without a pause; t goes back with it",
        )

    chunks = nmea_chunks(path, rate_hz=rate_hz, stats=stats)
    for t_s, data in paced(chunks, speed, on_gap=on_gap, on_back=on_back):
        played += 1
        t_last = t_s
        size.add(data)
        for rec in decoder.feed(data, t_s):
            if isinstance(rec, GpsFix):
                fixes += 1
                _emit(rec, as_json, out)
            elif isinstance(rec, GpsSky) and sky:
                skies += 1
                _emit(rec, as_json, out)
        out.flush()
    for rec in decoder.flush(t_last):
        if isinstance(rec, GpsFix):
            fixes += 1
            _emit(rec, as_json, out)
    for how, n in jumps.items():
        if n > MAX_BACKS_SAID:
            err.write(
                f"x6wd replay: the recorded time {how} {n} times in all"
                f" ({n - MAX_BACKS_SAID} more than said)\n"
            )
    counts = dict(decoder.counters.as_dict())
    counts["fixes_printed"] = fixes
    counts["skies_printed"] = skies
    if recording:
        counts["records"] = stats.records
        counts["truncated_lines"] = stats.truncated
        counts["bad_lines"] = stats.bad_lines
    err.write(" ".join(f"{k}={v}" for k, v in counts.items()) + "\n")
    if recording and stats.gaps:
        err.write(
            f"x6wd replay: {path}: {stats.gaps} recording gap{'s' if stats.gaps > 1 else ''}:"
            f" {stats.gap_records_lost} records lost (the recorder's disk failed or stalled)\n"
        )
    # no end record: a recorder still writing it (its lock held before reading) says it is
    # not finished
    writer = writer_before if recording and stats.cut_short else None
    if writer is not None:
        err.write(f"x6wd replay: {path}: {writer.describe()}: replayed as far as it is written\n")
    elif recording and stats.cut_short:
        err.write(
            f"x6wd replay: {path}: cut short: its last record is not the daemon's shutdown"
            " event (a crash, kill -9 or a power cut; or a recording older than that event)\n"
        )
    # not a log at all (random bytes, a mission file, junk lines): an error, not an empty
    # replay; an empty file is no error (empty in, empty out)
    what = nothing_decoded(counts["sentences"], counts["ubx_frames"], stats, size)
    if what:
        raise ParseError(f"{path}: no NMEA sentence or x6wd record in {what}")
    return counts


def main(args: argparse.Namespace) -> int:
    """Entry point of ``x6wd replay``; 0 on success (errors raise X6wdError -> exit 2)."""
    if args.file == "-" and not Path("-").exists():
        raise ConfigError(
            "x6wd replay reads a file, not standard input ('-'): it paces the log by its own"
            " times, so save it to a file first (x6wd decode reads '-')"
        )
    try:
        replay_file(args.file, speed=args.speed, rate_hz=args.rate, as_json=args.json, sky=args.sky)
    except BrokenPipeError:  # `x6wd replay f | head`
        return 0
    return 0
