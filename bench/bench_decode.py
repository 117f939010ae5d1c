"""`x6wd decode` beside gpsd's C `gpsdecode`: the same NMEA file through both, in one run.

Two inputs, as in bench_nmea: the whole gpsd corpus in tests/data/nmea (real receivers,
noise, binary; the logs concatenated) and a synthetic hour of NEO-5 output at 1 Hz (RMC, VTG,
GGA, GSA, GSV x3, GLL). Each tool is run as its own process on the same file with its output
to /dev/null: ``gpsdecode -d < FILE`` (gpsd's JSON reports, one or more per sentence) and
``python -m x6wd decode --quiet FILE`` (TPV and SKY lines, see x6wd/app/decode.py).

The figure is CPU time (user + system) of the child process, the best of several runs taken
in turns so that load from other processes hits both tools alike. Each tool's start-up is
measured on an empty file and subtracted: the rate is sentences per second of decoding, which
is what a long log costs. The start-up itself (the Python interpreter and imports, about
0.1 s, against 2 ms for gpsdecode) is printed in its own rows and in a whole-process ratio.
Sentences are the checksum-valid ones as x6wd's framer counts them, the same number for both.
Target: x6wd's rate >= gpsdecode's (ratio >= 1).

The corpus row is noisy: its decoding (about 0.1 s) is no longer than x6wd's start-up, so
the spread of the two minima shows in the ratio (0.74 to 1.16 in six runs on 2026-11-27,
against 0.74 to 0.79 for the NEO-5 hour). Where x6wd's time goes on the corpus: UBX
checksums of the ZED-F9P log (``drivers.gps_nmea.ubx_checksum``, big-integer arithmetic,
about a sixth) and importing pynmea2 for the proprietary sentences; on the NEO-5 hour:
framing about an eighth, the rest spread over the per-sentence field decoding, GSV groups
and the report text (tests/test_decode_bulk.py keeps that path byte-identical to the
reference).
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

from bench._common import Row, print_table
from bench.bench_nmea import CORPUS, synthetic_neo5
from drivers.gps_nmea import NmeaFramer

ROOT = Path(__file__).resolve().parent.parent
TARGET_RATIO = 1.0


def _cpu_s(argv: list[str], stdin_path: Path) -> float:
    """CPU time (user + system, s) of one run of ``argv`` with ``stdin_path`` on stdin."""
    with open(stdin_path, "rb") as f, open(os.devnull, "wb") as sink:
        proc = subprocess.Popen(argv, stdin=f, stdout=sink, stderr=subprocess.PIPE, cwd=ROOT)
        assert proc.stderr is not None
        err = proc.stderr.read()
        _, status, usage = os.wait4(proc.pid, 0)
        proc.returncode = os.waitstatus_to_exitcode(status)
    if proc.returncode != 0:
        raise RuntimeError(f"{argv[0]} failed ({proc.returncode}): {err.decode()[-500:]}")
    return usage.ru_utime + usage.ru_stime


def _commands(gpsdecode: str, path: Path) -> dict[str, list[str]]:
    return {
        "gpsdecode": [gpsdecode, "-d"],
        "x6wd decode": [sys.executable, "-m", "x6wd", "decode", "--quiet", str(path)],
    }


def _best(gpsdecode: str, path: Path, repeat: int) -> dict[str, float]:
    """Best CPU time per tool on ``path``, the tools run in turns."""
    best = dict.fromkeys(_commands(gpsdecode, path), float("inf"))
    for _ in range(repeat):
        for name, argv in _commands(gpsdecode, path).items():
            best[name] = min(best[name], _cpu_s(argv, path))
    return best


def _measure(label: str, data: bytes, gpsdecode: str, tmp: Path, repeat: int) -> list[Row]:
    framer = NmeaFramer()
    framer.feed(data)
    n = framer.counters.sentences
    path = tmp / "input.nmea"
    path.write_bytes(data)
    empty = tmp / "empty.nmea"
    empty.write_bytes(b"")
    full = _best(gpsdecode, path, repeat)
    start = _best(gpsdecode, empty, repeat)
    rate = {k: n / max(full[k] - start[k], 1e-9) for k in full}
    ratio = rate["x6wd decode"] / rate["gpsdecode"]
    whole = {k: n / full[k] for k in full}
    note = f"{n} sentences, {len(data)} bytes; start-up subtracted"
    return [
        Row("decode", f"{label}: gpsdecode", rate["gpsdecode"], "sent/s", None, "", note),
        Row(
            "decode",
            f"{label}: x6wd decode",
            rate["x6wd decode"],
            "sent/s",
            rate["gpsdecode"],
            "gpsdecode",
            note,
        ),
        Row(
            "decode",
            f"{label}: x6wd rate / gpsdecode rate",
            ratio,
            "ratio",
            TARGET_RATIO,
            "target",
            "PASS" if ratio >= TARGET_RATIO else "under target",
        ),
        Row(
            "decode",
            f"{label}: x6wd decode, whole process",
            whole["x6wd decode"],
            "sent/s",
            whole["gpsdecode"],
            "gpsdecode, whole process",
            f"start-up included: x6wd {start['x6wd decode'] * 1e3:.0f} ms, "
            f"gpsdecode {start['gpsdecode'] * 1e3:.1f} ms",
        ),
    ]


def run(quick: bool = False) -> list[Row]:
    """Rows for the gpsd corpus and a synthetic NEO-5 hour (quick: 10 minutes)."""
    gpsdecode = shutil.which("gpsdecode")
    if gpsdecode is None:
        return [Row("decode", "gpsdecode not installed (apt-get install gpsd-clients)", 0.0, "")]
    corpus = b"".join(p.read_bytes() for p in sorted(CORPUS.glob("*.log")))
    seconds = 600 if quick else 3600
    synth = synthetic_neo5(seconds, np.random.default_rng(5))
    repeat = 3 if quick else 7
    with tempfile.TemporaryDirectory() as tmp:
        rows = _measure("gpsd corpus", corpus, gpsdecode, Path(tmp), repeat)
        rows += _measure(f"NEO-5 synthetic {seconds} s", synth, gpsdecode, Path(tmp), repeat)
    return rows


if __name__ == "__main__":
    print_table(run())
