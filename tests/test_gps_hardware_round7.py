"""Review round 7, the GPS-Bee (u-blox NEO-5) on its UART.

M2: a false UBX sync in line noise (``B5 62`` and a "length" of up to 1024) made the framer
hold every byte behind it until that many had arrived: 6 noise bytes held three fixes back
for 3 s at 9600 baud, then delivered them at once with the same fresh receive time. Now a
whole checksum-valid NMEA sentence inside the claimed span makes the sync a false one: no
sentence waits for more than its own bytes. Tested on the decoder (bytes at line rate) and on
the real reader over a pty written at 9600 baud's pace.
"""

from __future__ import annotations

import os
import threading
import time
import tty
from collections.abc import Iterator

import pytest
import serial

from drivers.gps_io import GpsReader
from drivers.gps_nmea import GpsDecoder, NmeaFrame, NmeaFramer, UbxFrame, ubx_frame
from drivers.nmea import checksum
from x6wd.core.records import GpsFix

BYTES_PER_S = 960  # 9600 baud 8N1
FALSE_SYNC = b"\xb5\x62\x0a\x0b\xe8\x03"  # class 0A id 0B, "length" 1000


def _s(body: str) -> bytes:
    return f"${body}*{checksum(body.encode()):02X}\r\n".encode()


def _epoch(sec: int) -> bytes:
    """A NEO-5 burst (RMC, VTG, GGA, GSA, GLL) at 12:00:sec."""
    hh = f"1200{sec:02d}.00"
    return (
        _s(f"GPRMC,{hh},A,5140.00000,N,03945.00000,E,0.0,,051226,,,A")
        + _s("GPVTG,,T,,M,0.0,N,0.0,K,A")
        + _s(f"GPGGA,{hh},5140.00000,N,03945.00000,E,1,08,1.0,100.0,M,10.0,M,,")
        + _s("GPGSA,A,3,01,02,03,04,05,06,07,08,,,,,2.0,1.0,1.7")
        + _s(f"GPGLL,5140.00000,N,03945.00000,E,{hh},A,A")
    )


def _fixes_at_line_rate(noise: bytes) -> list[tuple[int, float, float]]:
    """(second, fix t_s, when its GGA's last byte arrived) for 6 epochs a second apart fed in
    32-byte reads at 9600 baud, ``noise`` before epoch 1."""
    d = GpsDecoder()
    out = []
    for sec in range(6):
        e = (noise if sec == 1 else b"") + _epoch(sec)
        gga_end = e.index(b"GPGGA")
        gga_end = e.index(b"\n", gga_end) + 1
        for i in range(0, len(e), 32):
            t = sec + min(i + 32, len(e)) / BYTES_PER_S
            for r in d.feed(e[i : i + 32], t):
                if isinstance(r, GpsFix):
                    assert r.utc is not None
                    out.append((r.utc.second, r.t_s, sec + gga_end / BYTES_PER_S))
    return out


def test_a_false_ubx_sync_delays_no_fix() -> None:
    clean = _fixes_at_line_rate(b"")
    noisy = _fixes_at_line_rate(FALSE_SYNC)
    assert [s for s, _, _ in noisy] == [0, 1, 2, 3, 4, 5]
    # each fix out within the 32-byte read that completes its GGA, as without the noise
    for (sec, t_s, t_gga), (_, t_clean, _) in zip(noisy, clean, strict=True):
        assert t_s - t_gga < 32 / BYTES_PER_S + 0.01, (sec, t_s, t_gga)
        assert abs(t_s - t_clean) < 0.01 + len(FALSE_SYNC) / BYTES_PER_S, sec


@pytest.mark.parametrize("size", [1, 7, 32, 4096])
def test_a_false_sync_before_sentences_frames_alike_in_any_reads(size: int) -> None:
    data = _epoch(0) + FALSE_SYNC + _epoch(1) + ubx_frame(5, 1, b"\x06\x08") + _epoch(2)
    framer = NmeaFramer()
    frames = []
    for i in range(0, len(data), size):
        frames += framer.feed(data[i : i + size])
    assert framer.pending_bytes == 0
    nmea = [f for f in frames if isinstance(f, NmeaFrame)]
    assert len(nmea) == 15
    assert [f for f in frames if isinstance(f, UbxFrame)] == [UbxFrame(5, 1, b"\x06\x08")]
    c = framer.counters
    assert (c.sentences, c.ubx_frames, c.checksum_failures, c.framing_errors) == (15, 1, 0, 0)
    assert c.skipped_bytes == 5  # B5 62 0A 0B E8 03 less its LF (0x0A is not counted)


def test_a_sentence_is_held_only_until_its_own_line_end() -> None:
    framer = NmeaFramer()
    gga = _s("GPGGA,120001.00,5140.00000,N,03945.00000,E,1,08,1.0,100.0,M,10.0,M,,")
    assert framer.feed(FALSE_SYNC + gga[:-1]) == []  # the sentence is not complete yet
    assert framer.feed(gga[-1:]) == [NmeaFrame(gga[:-2].decode())]
    assert framer.pending_bytes == 0


def test_ubx_frames_with_binary_payloads_still_frame() -> None:
    # a true frame whose payload holds '$' and '*' (no whole sentence) is a frame
    payload = b"$GPX*" + bytes(range(256)) + b"$ab*00\r\n"  # '*00' is not ab's checksum
    framer = NmeaFramer()
    frame = ubx_frame(1, 7, payload)
    got = []
    for i in range(0, len(frame), 5):
        got += framer.feed(frame[i : i + 5])
    assert got == [UbxFrame(1, 7, payload)]


class PacedPty:
    """A pty whose far end writes ``data`` at 9600 baud's pace from ``start``; ``sent[k]``
    is when the line end of the k-th GGA left (monotonic)."""

    def __init__(self) -> None:
        self.master, self.slave = os.openpty()
        tty.setraw(self.master)
        tty.setraw(self.slave)
        self.path = os.ttyname(self.slave)
        self.sent: list[float] = []
        self.thread: threading.Thread | None = None

    def play(self, data: bytes) -> None:
        gga_ends = set()
        at = data.find(b"GGA,")
        while at >= 0:
            gga_ends.add(data.index(b"\n", at))
            at = data.find(b"GGA,", at + 1)

        def run() -> None:
            t0 = time.monotonic()
            chunk = 10  # ~10 ms of line
            for i in range(0, len(data), chunk):
                due = t0 + i / BYTES_PER_S
                time.sleep(max(0.0, due - time.monotonic()))
                t = time.monotonic()
                if gga_ends.intersection(range(i, i + chunk)):
                    self.sent.append(t)
                os.write(self.master, data[i : i + chunk])

        self.thread = threading.Thread(target=run, daemon=True)
        self.thread.start()

    def close(self) -> None:
        if self.thread is not None:
            self.thread.join(10)
        os.close(self.master)
        os.close(self.slave)


@pytest.fixture
def paced_pty() -> Iterator[PacedPty]:
    p = PacedPty()
    yield p
    p.close()


def test_the_reader_on_a_9600_baud_pty_gets_each_fix_as_its_gga_arrives(
    paced_pty: PacedPty,
) -> None:
    # three epochs back to back (the burst is ~350 bytes, 0.37 s of line), the false sync
    # before the second: each fix must leave poll() as its GGA arrives, not 1000 bytes on
    data = _epoch(0) + FALSE_SYNC + _epoch(1) + _epoch(2) + _epoch(3)
    reader = GpsReader(lambda: serial.Serial(paced_pty.path, 9600, timeout=0), stale_s=5.0)
    try:
        reader.poll(0.05)  # opens the port
        paced_pty.play(data)
        got: list[tuple[int, float, float]] = []
        deadline = time.monotonic() + len(data) / BYTES_PER_S + 3.0
        while len(got) < 4 and time.monotonic() < deadline:
            for r in reader.poll(0.05):
                if isinstance(r, GpsFix) and r.utc is not None:
                    got.append((r.utc.second, r.t_s, time.monotonic()))
    finally:
        reader.close()
    assert paced_pty.thread is not None
    paced_pty.thread.join(5)
    assert [s for s, _, _ in got] == [0, 1, 2, 3]
    assert len(paced_pty.sent) == 4
    for k, (sec, t_s, _) in enumerate(got):
        lag = t_s - paced_pty.sent[k]
        assert -0.05 < lag < 0.25, f"fix {sec}: {lag:.3f} s after its GGA was written"
