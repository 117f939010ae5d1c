"""`x6wd decode`'s own path (``decode_stream``: ``ReportDecoder`` + ``ReportEncoder``, built for
speed) against the reference, in the same run: the daemon's ``GpsDecoder`` records written
through gpsd's ``tpv_obj``/``sky_obj`` and ``json.dumps``. Same lines, byte for byte, and
same counters (a corrupt line is counted and skipped alike), on the gpsd corpus, the
synthetic NEO-5 hour of bench/bench_decode.py and fuzzed streams; read whole and in small
reads."""

from __future__ import annotations

import io
import json
import re
from dataclasses import asdict
from pathlib import Path
from typing import IO, cast

import numpy as np
import pytest

from bench.bench_nmea import synthetic_neo5
from drivers import gps_nmea
from drivers.gps_nmea import GpsDecoder, NmeaFramer
from x6wd.app import decode
from x6wd.app.gpsd import sky_obj, tpv_obj
from x6wd.core.records import GpsFix, GpsSky

NMEA_DIR = Path(__file__).resolve().parent / "data" / "nmea"
CORPUS = sorted(NMEA_DIR.glob("*.log"))


class _Reads(io.RawIOBase):
    """A byte stream whose reads return at most ``size`` bytes (a pipe, a serial log)."""

    def __init__(self, data: bytes, size: int) -> None:
        self._data = memoryview(data)
        self._size = size

    def readable(self) -> bool:
        return True

    def readinto(self, b: bytearray) -> int:  # type: ignore[override]
        n = min(len(b), self._size, len(self._data))
        b[:n] = self._data[:n]
        self._data = self._data[n:]
        return n


def _reference(data: bytes, with_sky: bool) -> tuple[list[str], dict[str, int]]:
    dec = GpsDecoder(emit_sentences=False)
    # The reference takes the data whole: records and counters must not depend on the reads.
    records = dec.feed(data, 0.0)
    records += dec.flush()
    lines = [
        json.dumps(
            tpv_obj(r) if isinstance(r, GpsFix) else sky_obj(r, fill_dops=False),
            separators=(",", ":"),
        )
        for r in records
        if isinstance(r, GpsFix) or (with_sky and isinstance(r, GpsSky))
    ]
    return lines, dec.counters.as_dict()


def _decode(data: bytes, read_size: int, with_sky: bool) -> tuple[list[str], dict[str, int]]:
    out = io.StringIO()
    stream = cast("IO[bytes]", _Reads(data, read_size))  # what decode_stream reads: read(n)
    counters = decode.decode_stream(stream, out, with_sky=with_sky)
    return out.getvalue().splitlines(), counters.as_dict()


def _check(data: bytes, read_sizes: tuple[int, ...] = (1 << 20, 4093)) -> None:
    assert data.lstrip()[:1] != b"{"  # a raw stream, not a recording
    for with_sky in (True, False):
        expected = _reference(data, with_sky)
        for size in read_sizes:
            assert _decode(data, size, with_sky) == expected, size


@pytest.mark.parametrize("path", CORPUS, ids=lambda p: p.name)
def test_corpus_log_decodes_like_the_reference(path: Path) -> None:
    _check(path.read_bytes())


def test_whole_corpus_and_the_neo5_hour_decode_like_the_reference() -> None:
    _check(b"".join(p.read_bytes() for p in CORPUS), (1 << 20,))
    _check(synthetic_neo5(3600, np.random.default_rng(5)), (1 << 20,))


_JUNK = (b"", b"1e5", b"-1", b"abc", b"\xe9", b"99.9.9", b"7", b"999", b"1_0", b" 2", b"nan")


def _resummed(line: bytes, rng: np.random.Generator) -> bytes:
    """``line`` with one field (or its type) replaced, under a checksum that matches."""
    body = line[1 : line.index(b"*")]
    fields = body.split(b",")
    k = int(rng.integers(0, len(fields)))
    if k == 0:
        heads = (b"GPXYZ", b"PUBX", b"GP", b"GNGSV", b"GLGSA", b"GPZDA", b"PGRME")
        fields[0] = heads[int(rng.integers(0, len(heads)))]
    else:
        fields[k] = _JUNK[int(rng.integers(0, len(_JUNK)))]
    body = b",".join(fields)
    xor = 0
    for c in body:
        xor ^= c
    return b"$%s*%02X\r\n" % (body, xor)


def _fuzzed(rng: np.random.Generator) -> bytes:
    """Receiver output broken the ways real links and logs break it."""
    base = synthetic_neo5(120, rng) + (NMEA_DIR / "ublox-lea-5h.log").read_bytes()
    lines = base.splitlines(keepends=True)
    out: list[bytes] = []
    for line in lines:
        r = rng.random()
        if r < 0.03:  # a flipped byte (bad checksum, or a bad field when it still sums)
            k = int(rng.integers(0, len(line)))
            line = line[:k] + bytes([int(rng.integers(0, 256))]) + line[k + 1 :]
        elif r < 0.05:  # cut short
            line = line[: int(rng.integers(0, len(line)))]
        elif r < 0.07:  # line ending lost or changed
            line = (
                line.rstrip(b"\r\n")
                + [b"", b"\r", b"\n", b"\n\r", b"\r\r\n"][int(rng.integers(0, 5))]
            )
        elif r < 0.08:  # binary noise, with UBX syncs among it
            noise = rng.integers(0, 256, size=int(rng.integers(1, 300)), dtype=np.uint8)
            line = noise.tobytes().replace(b"\n", b"\xb5b") + line
        elif r < 0.09:  # a very long line
            line = line.rstrip(b"\r\n") + b"," * int(rng.integers(60, 400)) + b"*00\r\n"
        elif r < 0.10:  # the date of an RMC gone: undated epochs
            line = line.replace(b",010526,", b",,")
        elif r < 0.11:  # lower-case checksum digits, a doubled '$', non-ASCII text
            line = [line.lower(), b"$" + line, line.replace(b",", b",\xe9", 1)][
                int(rng.integers(0, 3))
            ]
        elif r < 0.12:  # a sentence dropped (a lost GSV part, an RMC without its GGA)
            continue
        elif r < 0.16 and line.startswith(b"$") and b"*" in line:  # bad content, good sum
            line = _resummed(line, rng)
        out.append(line)
    data = b"".join(out)
    return b"x" + data if data.lstrip()[:1] == b"{" else data


@pytest.mark.parametrize("seed", range(12))
def test_fuzzed_streams_decode_like_the_reference(seed: int) -> None:
    data = _fuzzed(np.random.default_rng(seed))
    _check(data, (1 << 20, 4093, 61))


def _sentence(body: str) -> bytes:
    xor = 0
    for c in body.encode():
        xor ^= c
    return f"${body}*{xor:02X}\r\n".encode()


def test_midnight_leap_second_and_zda_dates_decode_like_the_reference() -> None:
    # The time of a report is the date's day, the day after or the day before (a time of
    # day 12 h away from the date's own) or 23:59:59.999 for a leap second.
    pos = "5142.12345,N,00430.12345,W"
    bodies = [
        f"GPGGA,235958.00,{pos},1,08,1.1,35.2,M,49.0,M,,",  # undated: no time member
        f"GPRMC,235959.50,A,{pos},0.3,,311226,,,A",
        f"GPGGA,235959.50,{pos},1,08,1.1,35.2,M,49.0,M,,",
        f"GPGGA,235960.00,{pos},1,08,1.1,35.2,M,49.0,M,,",  # leap second
        f"GPGGA,000000.25,{pos},1,08,1.1,35.2,M,49.0,M,,",  # past midnight, old date
        "GPGSV,1,1,02,02,45,123,33,05,12,045,41",
        f"GPRMC,000001.00,A,{pos},0.3,,010127,,,A",
        f"GPGGA,000001.00,{pos},1,08,1.1,35.2,M,49.0,M,,",
        "GPZDA,115959.00,28,02,2100,00,00",
        f"GPGGA,120000.00,{pos},1,08,1.1,35.2,M,49.0,M,,",
        f"GPGGA,000000.00,{pos},1,08,1.1,35.2,M,49.0,M,,",  # 12 h before: the day before
        "GPZDA,000000.00,01,01,2200,00,00",
        f"GPGGA,235959.99,{pos},1,08,1.1,35.2,M,49.0,M,,",  # the day before the date
    ]
    _check(b"".join(map(_sentence, bodies)), (1 << 20, 7))


def test_reads_cut_anywhere_decode_like_the_reference() -> None:
    # Reads of a few hundred to a few thousand sentences, cut at odd places (inside a
    # sentence, between CR and LF, inside a UBX frame): each read is decoded in bulk.
    data = (
        _fuzzed(np.random.default_rng(99)) + (NMEA_DIR / "ublox-zed-f9p_hpg1.11.log").read_bytes()
    )
    _check(data, (9_973, 65_537, 200_003))


def _framed(data: bytes, size: int) -> tuple[list[object], dict[str, int]]:
    framer = NmeaFramer()
    frames: list[object] = []
    for i in range(0, len(data), size):
        frames += framer.feed(data[i : i + size])
    return frames, asdict(framer.counters)


def test_framer_runs_frame_like_the_general_scan(monkeypatch: pytest.MonkeyPatch) -> None:
    # The framer finds runs of well-formed lines with _RUN_B (on a copy whose body bytes
    # are all "b") and checksums them together; with no runs every byte goes through
    # _SCAN. Lines whose checksum "digits" are body bytes but not hex send a read through
    # _RUN instead. Same frames and counters.
    bad_digits = b"$GPGLL,,,,,,V,N*G4\r\n$GPGLL,,,,,,V,N*4g\n"
    data = _fuzzed(np.random.default_rng(5)) + bad_digits * 3
    data += (NMEA_DIR / "ublox-lea-5h.log").read_bytes()
    fast = [_framed(data, size) for size in (1 << 20, 4093, 61)]
    assert fast[0][1]["sentences"] > 1000 and fast[0][1]["framing_errors"] > 0
    monkeypatch.setattr(gps_nmea, "_RUN_B", re.compile(rb"()((?!))?"))
    assert [_framed(data, size) for size in (1 << 20, 4093, 61)] == fast


def test_positions_times_and_satellites_at_their_edges_decode_like_the_reference() -> None:
    # Read in bulk (by columns): positions at zero, near zero, on whole degrees, at the
    # poles and the antimeridian, minutes that round to 60, odd forms; times in each form;
    # GSV groups of every length, with empty fields and a signal id; ZDA dates that are
    # none, bad or partial, with and without a time.
    lats = ["0000.0000,N", "0000.0001,S", "4500.0000,N", "8959.9999999,S", "9000.0000,N",
            "5159.99999999999999999,N", "512.5,N", "05142.1,N", "5142,N", "5142.,S", ",",
            "5142.1,n", "-5142.1,N", "5142.1,"]  # fmt: skip
    lons = ["00000.0000,E", "00000.0001,W", "17959.9999,W", "18000.0000,E", "00430.5,W",
            "0430.5,W", "00430.12345678901,E", ","]  # fmt: skip
    times = ["120000", "120000.5", "120000.25", "120000.125", "120000.1234", "235960.00",
             "1200", "", "12000x.00", "246000.00"]  # fmt: skip
    gsvs = ["3,1,11,02,08,259,44,05,26,058,28,08,16,338,27,12,22,125,39",
            "3,2,11,15,10,112,22,18,51,005,40,21,39,105,21,24,56,267,30",
            "3,3,11,26,39,061,33,27,21,221,46,29,11,063",
            "3,3,11,26,39,061,33,27,21,221,46,29,11,063,22",
            "1,1,02,05,,,,07,12,300,",
            "1,1,01,05,45,123,33,1",
            "1,1,05,01,02,003,04,05,06,007,08,09,10,011,12,13,14,015,16,17,18,019,20,7",
            "1,1,00", "1,1,00,", "2,1,05,99,45,123,99,,,,"]  # fmt: skip
    zdas = ["{t},01,05,2026,00,00", "{t},31,02,2026,00,00", ",31,02,2026,00,00", "{t},,05,2026",
            ",02,05,2026,00,00",
            "{t},00,05,2026,00,00", "{t},01,13,2026,00,00", "{t},01,05,1979,00,00", "{t},1,5,2026",
            "{t},01,05", "{t},01,05,2026,00,00,7", "{t},0x,05,2026,00,00"]  # fmt: skip
    bodies = []
    for k in range(400):
        lat, lon, hms = lats[k % len(lats)], lons[k % len(lons)], times[k % len(times)]
        if k % 3 == 0:
            bodies.append("GPZDA," + zdas[k // 3 % len(zdas)].format(t=hms))
        bodies += [
            f"GPRMC,{hms},A,{lat},{lon},0.3,,010526,,,A",
            "GPVTG,,T,,M,0.3,N,0.6,K,A",
            f"GPGGA,{hms},{lat},{lon},1,08,1.10,35.2,M,49.0,M,,",
            "GPGSA,A,3,02,05,08,12,15,18,21,24,,,,,2.10,1.10,1.80",
            "GPGSV," + gsvs[k % len(gsvs)],
            f"GPGLL,{lat},{lon},{hms},A,A",
        ]
    _check(b"".join(map(_sentence, bodies)), (1 << 20, 4093, 61))


def test_back_to_back_ubx_frames_frame_alike_in_any_reads() -> None:
    # UBX frames one after the other (taken without rescanning, see NmeaFramer._pass),
    # among them a bad checksum, a false sync, a frame cut by the end of a read, a length
    # over the cap, and NMEA between: the same frames and counters whatever the reads.
    rng = np.random.default_rng(3)
    parts: list[bytes] = []
    for k in range(300):
        frame = gps_nmea.ubx_frame(1, k % 256, rng.integers(0, 256, k % 90, np.uint8).tobytes())
        r = k % 7
        if r == 1:  # bad checksum
            frame = frame[:-1] + bytes([frame[-1] ^ 0x5A])
        elif r == 2:  # a false sync inside noise
            frame = b"\xb5b\x01" + frame
        elif r == 3:  # length over MAX_UBX_PAYLOAD
            frame = b"\xb5b\x01\x02\xff\x7f" + frame
        elif r == 4:
            frame += _sentence("GPGLL,5142.1,N,00430.5,W,120000.00,A,A")
        parts.append(frame)
    data = b"".join(parts)
    whole = _framed(data, 1 << 20)
    # As the framer counted them before frames were taken back to back (5b7edd0's; a "$"
    # in the payload of a frame with a bad checksum starts a sentence that cuts another).
    # Since the false-sync bound (a whole NMEA sentence inside a claimed frame makes its
    # sync a false one, drivers.gps_nmea._nmea_inside) the last 195 bytes are no longer held
    # behind a false sync in a bad frame's payload: 4 frames, a GLL and 9 noise bytes more.
    counted = ("ubx_frames", "sentences", "framing_errors", "skipped_bytes")
    assert tuple(whole[1][k] for k in counted) == (257, 43, 5, 2388)
    for size in (4093, 517, 61, 7):
        assert _framed(data, size) == whole, size


def test_a_read_of_ubx_frames_only_decodes_like_the_reference() -> None:
    # an outside audit: 16 or more UBX frames and no NMEA in one read (a u-blox set to
    # binary output) crashed the bulk path with an IndexError
    frames = [gps_nmea.ubx_frame(1, 7, bytes(92)) for _ in range(100)]
    _check(b"".join(frames), (1 << 20, 4093))


def test_memos_cleared_while_reading_decode_like_the_reference(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # Every memo of the bulk path full many times over within one read (times, positions,
    # satellites, heads, ...: a memo is cleared when a read's new keys would take it
    # above MEMO_MAX, and then holds all of that read's keys). The NEO-5 hour's 3,600 times
    # and positions do not fill MEMO_MAX (4096): only a longer log does, here a small one.
    monkeypatch.setattr(decode, "MEMO_MAX", 40)
    data = synthetic_neo5(900, np.random.default_rng(8))
    _check(data + _fuzzed(np.random.default_rng(4)), (1 << 20, 65_537))
    _check(b"".join(p.read_bytes() for p in CORPUS), (1 << 20,))


def test_more_heads_than_the_route_memo_holds_decode_like_the_reference() -> None:
    # A read with more distinct sentence heads than the decoder keeps routes for (line
    # noise makes new heads): the memo is cleared while the read's heads are looked up.
    bodies = [f"Q{k:04d},1,2" for k in range(1500)]
    bodies[::50] = [f"GPGGA,1200{k % 60:02d}.00,5142.1,N,00430.5,W,1,08,1.1,35.2,M,49.0,M,,"
                    for k in range(len(bodies[::50]))]  # fmt: skip
    _check(b"".join(map(_sentence, bodies)), (1 << 20, 4093))
