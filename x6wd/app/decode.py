"""`x6wd decode FILE... | -`: NMEA logs or x6wd recordings -> gpsd-style JSON lines.

Like gpsd's ``gpsdecode``: one compact JSON object per line for every fix (``TPV``) and sky
report (``SKY``), with gpsd's field names and units (lat/lon deg, altMSL/altHAE m, speed
m/s, track deg true). Unknown fields are omitted, never null. A file whose first non-blank
character is ``{`` is an x6wd recording (JSON lines); its ``nmea`` records are decoded
(files through ``x6wd.core.recorder.read_recording``; standard input by a small line parser that
also takes the flat ``{"type":"nmea","text":...}`` form); its other records are ignored.
Anything else is read as a raw byte stream (binary and line noise tolerated). The decoder's
counters go to standard error, one line per input.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import sys
from collections.abc import Iterable, Iterator
from typing import IO

from drivers.gps_nmea import DecoderCounters, GpsDecoder, GpsOutput
from x6wd.app.gpsd import sky_obj, tpv_obj
from x6wd.core.errors import DeviceUnavailable
from x6wd.core.records import GpsFix, GpsSky

_CHUNK_BYTES = 1 << 20


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Register the ``decode`` options."""
    parser.add_argument(
        "files", nargs="+", metavar="FILE", help="NMEA log or recording; - is stdin"
    )
    parser.add_argument("--no-sky", action="store_true", help="print TPV reports only")
    parser.add_argument("--quiet", action="store_true", help="do not print counters on stderr")


def report_lines(records: Iterable[GpsOutput], *, with_sky: bool = True) -> Iterator[str]:
    """Compact JSON lines (no newline) for the fixes and sky reports among ``records``."""
    for r in records:
        if isinstance(r, GpsFix):
            yield json.dumps(tpv_obj(r), separators=(",", ":"))
        elif with_sky and isinstance(r, GpsSky):
            yield json.dumps(sky_obj(r), separators=(",", ":"))


def _recording_sentences(lines: Iterable[bytes]) -> Iterator[tuple[float, str]]:
    """(t_s, text) of the raw NMEA records in recording lines; other lines are skipped.

    Accepts the recorder's ``{"t_mono":..,"type":"nmea","data":{"text":..}}`` and the flat
    ``{"type":"nmea","text":..}`` form.
    """
    for raw in lines:
        try:
            obj = json.loads(raw)
        except (ValueError, UnicodeDecodeError):
            continue
        if not isinstance(obj, dict) or obj.get("type") != "nmea":
            continue
        data = obj.get("data")
        text = data.get("text") if isinstance(data, dict) else obj.get("text")
        t = obj.get("t_mono", 0.0)
        if isinstance(text, str):
            yield (float(t) if isinstance(t, (int, float)) else 0.0), text


def _decode_sentences(
    sentences: Iterable[tuple[float, str]], out: IO[str], with_sky: bool
) -> DecoderCounters:
    decoder = GpsDecoder(emit_sentences=False)
    for t_s, text in sentences:
        for line in report_lines(decoder.feed_sentence(text, t_s), with_sky=with_sky):
            out.write(line + "\n")
    for line in report_lines(decoder.flush(), with_sky=with_sky):
        out.write(line + "\n")
    return decoder.counters


def decode_stream(stream: IO[bytes], out: IO[str], *, with_sky: bool = True) -> DecoderCounters:
    """Decode one input (NMEA bytes or a recording) and write report lines to ``out``."""
    head = stream.read(_CHUNK_BYTES)
    if head.lstrip()[:1] == b"{":
        lines = (head + stream.read()).splitlines()
        return _decode_sentences(_recording_sentences(lines), out, with_sky)
    decoder = GpsDecoder(emit_sentences=False)
    chunk = head
    while chunk:
        for line in report_lines(decoder.feed(chunk, 0.0), with_sky=with_sky):
            out.write(line + "\n")
        chunk = stream.read(_CHUNK_BYTES)
    for line in report_lines(decoder.flush(), with_sky=with_sky):
        out.write(line + "\n")
    return decoder.counters


def decode_path(path: str, out: IO[str], *, with_sky: bool = True) -> DecoderCounters:
    """Decode a file; recordings go through ``x6wd.core.recorder.read_recording``."""
    try:
        f = open(path, "rb")  # noqa: SIM115
    except OSError as exc:
        raise DeviceUnavailable(f"cannot open {path}: {exc.strerror}") from exc
    with f:
        first = f.read(4096).lstrip()
        while not first:
            block = f.read(4096)
            if not block:
                break
            first = block.lstrip()
        f.seek(0)
        if first[:1] != b"{":
            return decode_stream(f, out, with_sky=with_sky)
    from x6wd.core.recorder import read_recording

    sentences = (
        (rec.t_mono, rec.data["text"])
        for rec in read_recording(path)
        if rec.type == "nmea" and isinstance(rec.data.get("text"), str)
    )
    return _decode_sentences(sentences, out, with_sky)


def main(args: argparse.Namespace) -> int:
    """Decode every FILE in order; returns 0, or 1 when a file could not be read."""
    status = 0
    for name in args.files:
        try:
            if name == "-":
                counters = decode_stream(sys.stdin.buffer, sys.stdout, with_sky=not args.no_sky)
            else:
                counters = decode_path(name, sys.stdout, with_sky=not args.no_sky)
        except BrokenPipeError:
            # The reader went away (e.g. `| head`): stop quietly like other filters.
            with contextlib.suppress(OSError):
                sys.stdout = open(os.devnull, "w")  # noqa: SIM115
            return status
        except DeviceUnavailable as exc:
            print(f"x6wd decode: {exc}", file=sys.stderr)
            status = 1
            continue
        sys.stdout.flush()
        if not args.quiet:
            figures = " ".join(f"{k}={v}" for k, v in counters.as_dict().items())
            print(f"{name}: {figures}", file=sys.stderr)
    return status
