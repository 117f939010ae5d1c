"""NMEA decode throughput: drivers.gps_nmea.GpsDecoder beside raw pynmea2.parse.

Two inputs: the whole gpsd corpus in tests/data/nmea (real receivers, noise, binary) and a
synthetic hour of NEO-5 output at 1 Hz (RMC, VTG, GGA, GSA, GSV x3, GLL; correct checksums).
The decoder gets the raw bytes in 256-byte reads (a UART poll) and does everything: framing,
checksum, pynmea2 field split, validation, epoch assembly, records. The anchor is
``pynmea2.parse`` alone on the same checksum-valid sentences (it verifies the checksum
too). Target: decoder time / pynmea2 time <= 1.30.
"""

from __future__ import annotations

import contextlib
import functools
import operator
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pynmea2

from bench._common import Row, print_table
from drivers.gps_nmea import GpsDecoder, NmeaFramer

CORPUS = Path(__file__).resolve().parent.parent / "tests" / "data" / "nmea"
READ_BYTES = 256
TARGET_RATIO = 1.30


def _line(body: str) -> str:
    return f"${body}*{functools.reduce(operator.xor, body.encode(), 0):02X}\r\n"


def synthetic_neo5(seconds: int, rng: np.random.Generator) -> bytes:
    """``seconds`` epochs of NEO-5 output from a slow random walk (deterministic via rng)."""
    lat0, lon0 = 51.7, -4.5
    steps = rng.normal(0.0, 2e-6, size=(seconds, 2)).cumsum(axis=0)
    prns = [2, 5, 8, 12, 15, 18, 21, 24, 26, 27, 29]
    els = rng.integers(5, 85, size=len(prns))
    azs = rng.integers(0, 359, size=len(prns))
    out: list[str] = []
    for k in range(seconds):
        hh, rem = divmod(10 * 3600 + k, 3600)
        mm, ss = divmod(rem, 60)
        hms = f"{hh % 24:02d}{mm:02d}{ss:02d}.00"
        lat = lat0 + steps[k, 0]
        lon = lon0 + steps[k, 1]
        lat_s = f"{int(lat):02d}{(lat - int(lat)) * 60:08.5f}"
        lon_a = abs(lon)
        lon_s = f"{int(lon_a):03d}{(lon_a - int(lon_a)) * 60:08.5f}"
        kn = f"{abs(rng.normal(0.3, 0.1)):.3f}"
        snr = rng.integers(20, 48, size=len(prns))
        gsv = []
        for part in range(3):
            group = ",".join(
                f"{prns[i]:02d},{els[i]:02d},{azs[i]:03d},{snr[i]:02d}"
                for i in range(part * 4, min(part * 4 + 4, len(prns)))
            )
            gsv.append(f"GPGSV,3,{part + 1},{len(prns)},{group}")
        bodies = [
            f"GPRMC,{hms},A,{lat_s},N,{lon_s},W,{kn},,010526,,,A",
            f"GPVTG,,T,,M,{kn},N,{float(kn) * 1.852:.3f},K,A",
            f"GPGGA,{hms},{lat_s},N,{lon_s},W,1,08,1.10,35.2,M,49.0,M,,",
            "GPGSA,A,3,02,05,08,12,15,18,21,24,,,,,2.10,1.10,1.80",
            *gsv,
            f"GPGLL,{lat_s},N,{lon_s},W,{hms},A,A",
        ]
        out.extend(_line(b) for b in bodies)
    return "".join(out).encode("ascii")


def _best_interleaved(fns: list[Callable[[], object]], repeat: int) -> list[float]:
    """Best time of each function, run in turns so load changes hit all of them alike."""
    best = [float("inf")] * len(fns)
    for _ in range(repeat):
        for i, fn in enumerate(fns):
            t0 = time.perf_counter()
            fn()
            best[i] = min(best[i], time.perf_counter() - t0)
    return best


def _decode(data: bytes) -> int:
    dec = GpsDecoder()
    feed = dec.feed
    for i in range(0, len(data), READ_BYTES):
        feed(data[i : i + READ_BYTES], 0.0)
    dec.flush()
    return dec.counters.sentences


def _pynmea2_all(sentences: list[str]) -> None:
    parse = pynmea2.parse
    for s in sentences:
        with contextlib.suppress(pynmea2.ParseError):
            parse(s)


def _pynmea2_no_checksum(sentences: list[str]) -> None:
    # What the decoder itself asks of pynmea2 (it verified the checksum already).
    parse = pynmea2.parse
    for s in sentences:
        with contextlib.suppress(pynmea2.ParseError):
            parse(s[:-3])


def _measure(label: str, data: bytes, repeat: int) -> list[Row]:
    sentences = [f.text for f in NmeaFramer().feed(data) if hasattr(f, "text")]
    n = len(sentences)
    t_dec, t_ref, t_inner = _best_interleaved(
        [
            lambda: _decode(data),
            lambda: _pynmea2_all(sentences),
            lambda: _pynmea2_no_checksum(sentences),
        ],
        repeat,
    )
    ratio_note = "PASS" if t_dec / t_ref <= TARGET_RATIO else "over target"
    return [
        Row("nmea", f"{label}: decoder", n / t_dec, "sent/s", n / t_ref, "pynmea2.parse", ""),
        Row(
            "nmea",
            f"{label}: decoder time / pynmea2 time",
            t_dec / t_ref,
            "ratio",
            TARGET_RATIO,
            "target",
            ratio_note,
        ),
        Row(
            "nmea",
            f"{label}: pynmea2 share of decode",
            t_inner / t_dec,
            "fraction",
            None,
            "",
            f"{n} sentences, {len(data)} bytes",
        ),
    ]


def run(quick: bool = False) -> list[Row]:
    """Throughput rows for the corpus and a synthetic NEO-5 hour (quick: 10 minutes)."""
    corpus = b"".join(p.read_bytes() for p in sorted(CORPUS.glob("*.log")))
    seconds = 600 if quick else 3600
    synth = synthetic_neo5(seconds, np.random.default_rng(5))
    repeat = 2 if quick else 7
    rows = _measure("gpsd corpus", corpus, repeat)
    rows += _measure(f"NEO-5 synthetic {seconds} s", synth, repeat)
    return rows


if __name__ == "__main__":
    print_table(run())
