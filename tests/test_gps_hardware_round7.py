"""Review round 7, the GPS-Bee (u-blox NEO-5) on its UART.

M2: a false UBX sync in line noise (``B5 62`` and a "length" of up to 1024) made the framer
hold every byte behind it until that many had arrived: 6 noise bytes held three fixes back
for 3 s at 9600 baud, then delivered them at once with the same fresh receive time. Now a
whole checksum-valid NMEA sentence inside the claimed span makes the sync a false one: no
sentence waits for more than its own bytes. Tested on the decoder (bytes at line rate) and on
the real reader over a pty written at 9600 baud's pace.

M1: ``[gps] configure_receiver`` and ``rate_hz`` did nothing (below).
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import os
import select
import struct
import threading
import time
import tty
from collections.abc import Callable, Iterator
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import pytest
import serial

from drivers.gps_io import GpsReader
from drivers.gps_nmea import (
    GpsDecoder,
    NmeaFrame,
    NmeaFramer,
    UbxFrame,
    cfg_msg,
    cfg_rate,
    ubx_frame,
)
from drivers.nmea import checksum
from tests.conftest import ROOT
from tests.test_daemon import hil_config, run_daemon, wait_for
from x6wd.app.client import RemoteClient
from x6wd.app.daemon import Daemon
from x6wd.core.config import Config, GpsConfig, load, loads
from x6wd.core.errors import ConfigError
from x6wd.core.records import GpsFix

__all__ = ["run_daemon"]  # the fixture, shared with test_daemon

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


# --------------------------------------------------------------------------------------------
# M1: [gps] configure_receiver and rate_hz did nothing: nothing read configure_receiver, the
# daemon built its reader without init_bytes and nothing sent CFG-RATE, so with rate_hz = 4
# the config check accepted staleness limits of 0.75 s while the NEO-5 stayed at 1 Hz. The
# real daemon against a NEO-5 emulation on a pty that reads what the daemon writes.

ACK_HEAD = b"\xb5\x62\x05"


class Neo5Pty:
    """A NEO-5 on a pty reached through a symlink (``path``): RMC + GGA each epoch at
    ``hz``; UBX CFG frames from the host are answered per ``answer`` ("ack": ACK-ACK, and a
    CFG-RATE changes ``hz``; "nak": ACK-NAK; "silent": nothing). :meth:`replug` moves the
    link to a new pty, as a USB adapter unplugged and plugged in again."""

    def __init__(self, link: Path, hz: float = 1.0, answer: str = "ack") -> None:
        self.link, self.hz, self.answer = link, hz, answer
        self.received: list[bytes] = []  # what the host wrote, per pty (one entry each)
        self.lock = threading.Lock()
        self.stop = threading.Event()
        self._plug()
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _plug(self) -> None:
        master, slave = os.openpty()
        tty.setraw(master)
        tty.setraw(slave)
        tmp = self.link.with_name(self.link.name + ".tmp")
        tmp.unlink(missing_ok=True)
        tmp.symlink_to(os.ttyname(slave))
        tmp.replace(self.link)
        with self.lock:
            self.master, self.slave = master, slave
            self.framer = NmeaFramer()
            self.received.append(b"")

    def replug(self) -> None:
        with self.lock:
            old = (self.master, self.slave)
        self._plug()
        for fd in old:
            os.close(fd)

    def _run(self) -> None:
        next_t = time.monotonic()
        while not self.stop.is_set():
            with self.lock:
                master = self.master
                ready, _, _ = select.select([master], [], [], 0)
                data = b""
                if ready:
                    with contextlib.suppress(OSError):
                        data = os.read(master, 4096)
                if data:
                    self.received[-1] += data
                    for f in self.framer.feed(data):
                        if isinstance(f, UbxFrame) and f.msg_class == 0x06:
                            self._answer(master, f)
                if time.monotonic() >= next_t:
                    now = datetime.now(UTC)
                    with contextlib.suppress(OSError):
                        os.write(master, _burst(now))
                    next_t += 1.0 / self.hz
            self.stop.wait(0.005)

    def _answer(self, master: int, f: UbxFrame) -> None:
        if self.answer == "silent":
            return
        ok = self.answer == "ack"
        if ok and f.msg_id == 0x08:  # CFG-RATE
            self.hz = 1000.0 / struct.unpack("<H", f.payload[:2])[0]
        os.write(master, ubx_frame(0x05, 1 if ok else 0, bytes((0x06, f.msg_id))))

    def close(self) -> None:
        self.stop.set()
        self.thread.join(2)
        os.close(self.master)
        os.close(self.slave)


def _burst(now: datetime) -> bytes:
    hms = now.strftime("%H%M%S.") + f"{now.microsecond // 10000:02d}"
    dmy = now.strftime("%d%m%y")
    return _s(f"GPRMC,{hms},A,5145.12000,N,00115.46200,W,0.0,,{dmy},,,A") + _s(
        f"GPGGA,{hms},5145.12000,N,00115.46200,W,1,08,0.9,60.0,M,47.0,M,,"
    )


@pytest.fixture
def neo5(tmp_path: Path) -> Iterator[Callable[..., Neo5Pty]]:
    made: list[Neo5Pty] = []

    def make(hz: float = 1.0, answer: str = "ack") -> Neo5Pty:
        g = Neo5Pty(tmp_path / f"ttyGPS{len(made)}", hz, answer)
        made.append(g)
        return g

    yield make
    for g in made:
        g.close()


def _daemon_config(tmp_path: Path, url: str, configure: bool, rate_hz: float = 4.0) -> Config:
    cfg = hil_config(tmp_path)
    return dataclasses.replace(
        cfg,
        gps=GpsConfig(url=url, rate_hz=rate_hz, stale_s=2.0, configure_receiver=configure),
        safety=dataclasses.replace(cfg.safety, fix_stale_s=0.75),
        motors=dataclasses.replace(cfg.motors, url="log://"),
    )


def _gps_receiver(c: RemoteClient) -> dict[str, Any]:
    return c.request("status")["gps_receiver"]


def test_configure_receiver_sets_the_rate_on_start_and_after_a_reopen(
    tmp_path: Path, run_daemon: Any, neo5: Callable[..., Neo5Pty]
) -> None:
    gps = neo5(hz=1.0)
    r = run_daemon(Daemon(_daemon_config(tmp_path, f"serial://{gps.link}?baud=9600", True)))
    # CFG-RATE 250 ms; GGA, RMC each epoch, GSA, GSV each 4th (1 s), VTG, GLL off: ~850 B/s
    want = cfg_rate(250) + b"".join(
        cfg_msg(m, n) for m, n in (("GGA", 1), ("RMC", 1), ("GSA", 4), ("GSV", 4), ("VTG", 0),
                                   ("GLL", 0))
    )  # fmt: skip
    assert want.startswith(bytes.fromhex("b562 0608 0600 fa00 0100 0100"))  # 250 ms, GPS time
    with RemoteClient("127.0.0.1", r.port) as c:
        st = wait_for(
            lambda: (s := _gps_receiver(c))["setup"]["state"] == "acked" and s, 10, "ACKs"
        )
        assert st["configure_receiver"] is True
        assert set(st["setup"]["answers"].values()) == {"ack"}, st
        assert st["setup"]["rounds"] == 1 and "problem" not in st["setup"]
        assert gps.received == [want]  # CFG-RATE 250 ms and the CFG-MSGs, once
        st = wait_for(
            lambda: (s := _gps_receiver(c))["measured_rate_hz"] is not None and s, 10, "rate"
        )
        assert 3.5 < st["measured_rate_hz"] < 4.5 and "slow" not in st, st
        # unplugged and plugged in again: the receiver may have lost power, so again
        gps.replug()
        wait_for(lambda: _gps_receiver(c)["setup"]["rounds"] == 2, 15, "a second round")
        wait_for(lambda: _gps_receiver(c)["setup"]["state"] == "acked", 10, "ACKs again")
        assert gps.received == [want, want]
    assert r.stop() == 0


def test_a_nak_and_the_slow_rate_show_in_status_and_one_warning(
    tmp_path: Path, run_daemon: Any, neo5: Callable[..., Neo5Pty], caplog: Any
) -> None:
    caplog.set_level(logging.INFO)
    gps = neo5(hz=1.0, answer="nak")
    r = run_daemon(Daemon(_daemon_config(tmp_path, f"serial://{gps.link}?baud=9600", True)))
    with RemoteClient("127.0.0.1", r.port) as c:
        st = wait_for(lambda: (s := _gps_receiver(c))["setup"]["state"] == "refused" and s, 10)
        assert st["setup"]["answers"]["CFG-RATE 250 ms"] == "NAK"
        assert "ACK-NAK" in st["setup"]["problem"] and "CFG-RATE" in st["setup"]["problem"]
        st = wait_for(lambda: (s := _gps_receiver(c)).get("slow") and s, 15, "slow")
        assert 0.8 < st["measured_rate_hz"] < 1.2
        assert "gps.rate_hz = 4 Hz" in st["slow"] and "stale" in st["slow"]
        wait_for(lambda: r.daemon.first_fix, 5, "fixes used all the same")
    assert r.stop() == 0
    warnings = [m.getMessage() for m in caplog.records if m.levelno == logging.WARNING]
    assert len([w for w in warnings if "ACK-NAK" in w]) == 1, warnings
    assert len([w for w in warnings if "under gps.rate_hz" in w]) == 1, warnings


def test_a_silent_receiver_is_no_answer_and_configure_false_sends_nothing(
    tmp_path: Path, run_daemon: Any, neo5: Callable[..., Neo5Pty], caplog: Any
) -> None:
    caplog.set_level(logging.INFO)
    silent, quiet = neo5(hz=1.0, answer="silent"), neo5(hz=1.0)
    r = run_daemon(Daemon(_daemon_config(tmp_path, f"serial://{silent.link}?baud=9600", True)))
    with RemoteClient("127.0.0.1", r.port) as c:
        st = wait_for(lambda: (s := _gps_receiver(c))["setup"]["state"] == "no answer" and s, 10)
        assert set(st["setup"]["answers"].values()) == {"no answer"}
        assert "no UBX ACK" in st["setup"]["problem"]
    assert r.stop() == 0
    assert len([m for m in caplog.records if "no UBX ACK" in m.getMessage()]) == 1
    # configure_receiver = false: not a byte to the receiver (set up in u-center); the rate
    # it runs at is still measured against rate_hz
    r = run_daemon(
        Daemon(_daemon_config(tmp_path / "b", f"serial://{quiet.link}?baud=9600", False))
    )
    with RemoteClient("127.0.0.1", r.port) as c:
        st = wait_for(lambda: (s := _gps_receiver(c)).get("slow") and s, 15, "slow")
        assert st["configure_receiver"] is False and st["setup"] is None
        assert "gps.rate_hz = 4 Hz" in st["slow"]
    assert r.stop() == 0
    assert quiet.received == [b""]


def test_the_simulated_receiver_takes_cfg_rate_in_hil(tmp_path: Path, run_daemon: Any) -> None:
    cfg = hil_config(tmp_path)
    cfg = dataclasses.replace(
        cfg,
        gps=dataclasses.replace(cfg.gps, configure_receiver=True, rate_hz=4.0, stale_s=2.0),
        sim=dataclasses.replace(cfg.sim, gps_rate_hz=1.0),
        safety=dataclasses.replace(cfg.safety, fix_stale_s=0.75),
    )
    r = run_daemon(Daemon(cfg))
    world = r.daemon.devices.backend("sim")
    with RemoteClient("127.0.0.1", r.port) as c:
        st = wait_for(lambda: (s := _gps_receiver(c))["setup"]["state"] == "acked" and s, 10)
        assert set(st["setup"]["answers"].values()) == {"ack"}, st
        assert world.receiver.rate_hz == 4.0
        assert world.ubx.msg_rates == {"GGA": 1, "RMC": 1, "GSA": 4, "GSV": 4, "VTG": 0, "GLL": 0}
        st = wait_for(
            lambda: (s := _gps_receiver(c))["measured_rate_hz"] is not None and s, 10, "rate"
        )
        assert 3.5 < st["measured_rate_hz"] < 4.5 and "slow" not in st, st
        assert r.daemon.gpsd is not None and r.daemon.gpsd.cycle_s == 0.25  # gpsd's DEVICE
    assert r.stop() == 0
    lines = [line for _, line in list(world.gps_wire)[-40:]]
    assert not [ln for ln in lines if ln[3:6] in (b"VTG", b"GLL")]


def test_configure_receiver_refuses_a_rate_the_neo5_cannot_run() -> None:
    with pytest.raises(ConfigError, match=r"gps\.rate_hz: 5 Hz .*NEO-5"):
        loads("[gps]\nconfigure_receiver = true\nrate_hz = 5.0\n[safety]\nfix_stale_s = 1.0")
    loads("[gps]\nconfigure_receiver = false\nrate_hz = 5.0\n[safety]\nfix_stale_s = 1.0")


@pytest.mark.parametrize("name", ["x6wd.toml", "hil.toml"])
def test_the_shipped_configs_still_load(name: str) -> None:
    cfg = load(ROOT / "config" / name)
    assert cfg.gps.configure_receiver is False
