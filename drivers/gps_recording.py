"""The GPS records of an x6wd recording, whichever way it holds them.

The daemon records both the sentences it received (``nmea``) and what it decoded from them
(``fix``, ``sky``); the simulator's receiver engine, which runs no daemon, records the
sentences only. A reader that wants fixes takes the decoded records when the recording has
any, else decodes the sentences with the daemon's own decoder at their receive times
(``t_mono``), so both kinds of recording give the same fixes.
"""

from __future__ import annotations

import os
from collections.abc import Iterator

from drivers.gps_nmea import GpsDecoder
from x6wd.core.recorder import decode_record, read_recording_parts
from x6wd.core.records import GpsFix, GpsSky


def recorded_gps(path: str | os.PathLike[str]) -> Iterator[GpsFix | GpsSky]:
    """The fixes and sky views of the recording at ``path`` (all its parts), in file order:
    its ``fix``/``sky`` records, or, when it has none, its ``nmea`` records decoded."""
    decoded = False
    has_nmea = False
    for rec in read_recording_parts(path):
        if rec.type in ("fix", "sky"):
            typed = decode_record(rec)
            if isinstance(typed, (GpsFix, GpsSky)):
                decoded = True
                yield typed
        elif rec.type == "nmea":
            has_nmea = True
    if decoded or not has_nmea:
        return
    decoder = GpsDecoder(emit_sentences=False)
    t_last = 0.0
    for rec in read_recording_parts(path):
        if rec.type != "nmea":
            continue
        text = rec.data.get("text")
        if not isinstance(text, str):
            continue
        t_last = rec.t_mono
        for out in decoder.feed(text.encode("ascii", "replace") + b"\r\n", t_last):
            if isinstance(out, (GpsFix, GpsSky)):
                yield out
    for out in decoder.flush(t_last):
        if isinstance(out, (GpsFix, GpsSky)):
            yield out
