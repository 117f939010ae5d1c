"""Review round 7, the GPS-Bee (u-blox NEO-5) on its UART.

M2: a false UBX sync in line noise (``B5 62`` and a "length" of up to 1024) made the framer
hold every byte behind it until that many had arrived: 6 noise bytes held three fixes back
for 3 s at 9600 baud, then delivered them at once with the same fresh receive time. Now a
whole checksum-valid NMEA sentence inside the claimed span makes the sync a false one: no
sentence waits for more than its own bytes. Tested on the decoder (bytes at line rate) and on
the real reader over a pty written at 9600 baud's pace.

M1: ``[gps] configure_receiver`` and ``rate_hz`` did nothing (below).

Review 6: a receiver that resets while the port stays open is configured again; the fix rate
falls while the GPS is silent and "slow" is warned at each fall (at the end).
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
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any

import pytest
import serial

from drivers.gps_io import GpsReader, ReceiverSetup, neo5_setup
from drivers.gps_nmea import (
    NMEA_MSG_IDS,
    GpsDecoder,
    NmeaFrame,
    NmeaFramer,
    UbxFrame,
    cfg_msg,
    cfg_rate,
    ubx_frame,
)
from drivers.nmea import checksum
from sim_backend.nmea_out import NEO5_BANNER
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
    is when the k-th GGA's CR left (monotonic), the byte that completes it for the framer
    (CR or LF ends a sentence): taken just before the write, so no fix of it can be older."""

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
            gga_ends.add(data.index(b"\r", at))
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
    # The fix's receive time against when its GGA's CR was written: never before it
    # (causal), and within 0.6 s. Each fix leaves at its GGA (a millisecond after it here);
    # a loaded host only delays the reader thread (0.25 s was the bound). The bug, bytes
    # held until the false sync's claimed 1008-byte frame is complete, holds fix 1 at least
    # 0.87 s after its GGA (832 bytes at 960/s), and here for ever (this data ends first).
    for k, (sec, t_s, _) in enumerate(got):
        lag = t_s - paced_pty.sent[k]
        assert 0.0 <= lag < 0.6, f"fix {sec}: {lag:.3f} s after its GGA was written"


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

    def __init__(
        self, link: Path, hz: float = 1.0, answer: str = "ack", full: bool = False
    ) -> None:
        self.link, self.hz, self.answer = link, hz, answer
        # full: VTG and GLL too (a NEO-5's defaults, until CFG-MSG turns them off)
        self.extra = ["VTG", "GLL"] if full else []
        self.banner = False  # print the start-up banner before the next burst
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
                    out = _burst(now, self.extra)
                    if self.banner:
                        self.banner = False
                        out = b"".join(_s(b) for b in NEO5_BANNER) + out
                    with contextlib.suppress(OSError):
                        os.write(master, out)
                    next_t += 1.0 / self.hz
            self.stop.wait(0.005)

    def _answer(self, master: int, f: UbxFrame) -> None:
        if self.answer == "silent":
            return
        ok = self.answer == "ack"
        if ok and f.msg_id == 0x08:  # CFG-RATE
            self.hz = 1000.0 / struct.unpack("<H", f.payload[:2])[0]
        if ok and f.msg_id == 0x01 and f.payload[0] == 0xF0 and f.payload[2] == 0:  # CFG-MSG off
            self.extra = [m for m in self.extra if NMEA_MSG_IDS[m] != f.payload[1]]
        os.write(master, ubx_frame(0x05, 1 if ok else 0, bytes((0x06, f.msg_id))))

    def reset(self, banner: bool = True) -> None:
        """The receiver restarts (a brown-out) while the host's port stays open: its
        defaults again (1 Hz, VTG and GLL), its start-up banner first if ``banner``."""
        with self.lock:
            self.hz = 1.0
            self.extra = ["VTG", "GLL"]
            self.banner = banner

    def close(self) -> None:
        self.stop.set()
        self.thread.join(2)
        os.close(self.master)
        os.close(self.slave)


def _burst(now: datetime, extra: list[str] | tuple[str, ...] = ()) -> bytes:
    hms = now.strftime("%H%M%S.") + f"{now.microsecond // 10000:02d}"
    dmy = now.strftime("%d%m%y")
    out = _s(f"GPRMC,{hms},A,5145.12000,N,00115.46200,W,0.0,,{dmy},,,A")
    if "VTG" in extra:
        out += _s("GPVTG,,T,,M,0.0,N,0.0,K,A")
    out += _s(f"GPGGA,{hms},5145.12000,N,00115.46200,W,1,08,0.9,60.0,M,47.0,M,,")
    if "GLL" in extra:
        out += _s(f"GPGLL,5145.12000,N,00115.46200,W,{hms},A,A")
    return out


@pytest.fixture
def neo5(tmp_path: Path) -> Iterator[Callable[..., Neo5Pty]]:
    made: list[Neo5Pty] = []

    def make(hz: float = 1.0, answer: str = "ack", full: bool = False) -> Neo5Pty:
        g = Neo5Pty(tmp_path / f"ttyGPS{len(made)}", hz, answer, full)
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


def wait_4_hz(c: RemoteClient) -> dict[str, Any]:
    """Until status measures the fixes at 4 Hz (3.5..4.5) and not slow. The rate is taken
    from the fixes' receive times over a second or two, so one status could be 0.1 Hz off
    on a loaded host (4.39, 4.01 measured beside 3 busy loops): it is asked again. A
    receiver left at 1 Hz is never in the band (1.0 measured in the NAK case)."""
    return wait_for(
        lambda: (
            (s := _gps_receiver(c))["measured_rate_hz"] is not None
            and 3.5 < s["measured_rate_hz"] < 4.5
            and "slow" not in s
            and s
        ),
        15,
        "a measured rate of 4 Hz, not slow",
    )


def test_configure_receiver_sets_the_rate_on_start_and_after_a_reopen(
    tmp_path: Path, run_daemon: Any, neo5: Callable[..., Neo5Pty]
) -> None:
    gps = neo5(hz=1.0)
    r = run_daemon(Daemon(_daemon_config(tmp_path, f"serial://{gps.link}?baud=9600", True)))
    # CFG-RATE 250 ms; GGA, RMC each epoch, GSA each 4th (1 s), VTG, GLL off, and at 9600
    # baud GSV off (its epoch would not leave the line before the next one: review 6 item 5)
    want = cfg_rate(250) + b"".join(
        cfg_msg(m, n) for m, n in (("GGA", 1), ("RMC", 1), ("GSA", 4), ("GSV", 0), ("VTG", 0),
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
        assert gps.hz == 4.0  # the receiver took it
        wait_4_hz(c)
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
        wait_4_hz(c)
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


# --------------------------------------------------------------------------------------------
# Review 6, item 2: a NEO-5 that resets on its own (a brown-out of its supply) while the Pi's
# UART stays open comes back at 1 Hz with its default sentences; the setup was written only
# at an open, so it was never written again and status still said "acked". Now the start-up
# banner, a sentence the setup turned off coming back, or the ACKed rate lost for 5 s mark
# the setup lost (status, one WARNING) and it is written again (at most once per 10 s).
# And the fix rate falls while the GPS is silent, and "slow" is warned at each fall.


def _setup_frames(rate_hz: float = 4.0) -> bytes:
    return ReceiverSetup(rate_hz).init_bytes


def test_a_receiver_that_resets_on_an_open_port_is_configured_again(
    tmp_path: Path, run_daemon: Any, neo5: Callable[..., Neo5Pty], caplog: Any
) -> None:
    caplog.set_level(logging.INFO)
    gps = neo5(hz=1.0, full=True)
    r = run_daemon(Daemon(_daemon_config(tmp_path, f"serial://{gps.link}?baud=9600", True)))
    with RemoteClient("127.0.0.1", r.port) as c:
        wait_for(lambda: _gps_receiver(c)["setup"]["state"] == "acked", 10, "ACKs")
        wait_for(lambda: 3.5 < (_gps_receiver(c)["measured_rate_hz"] or 0) < 4.5, 10, "4 Hz first")
        gps.reset(banner=True)  # 1 Hz, VTG and GLL again; the port stays open
        st = wait_for(
            lambda: (
                (s := _gps_receiver(c))["setup"]["rounds"] == 2
                and s["setup"]["state"] == "acked"
                and s
            ),
            20,
            "the setup written again and ACKed",
        )
        assert gps.received == [_setup_frames() * 2]  # the same port: written twice
        assert st["setup"]["losses"] == 1, st
        assert "start-up banner" in st["setup"]["lost"], st
        st = wait_for(
            lambda: (
                (s := _gps_receiver(c))["measured_rate_hz"] is not None
                and 3.5 < s["measured_rate_hz"] < 4.5
                and s
            ),
            15,
            "4 Hz again",
        )
        assert "slow" not in st and gps.hz == 4.0
    assert r.stop() == 0
    lost = [m.getMessage() for m in caplog.records if "lost its configuration" in m.getMessage()]
    assert len(lost) == 1 and m_level(caplog, lost[0]) == logging.WARNING, lost


def m_level(caplog: Any, message: str) -> int:
    return next(m.levelno for m in caplog.records if m.getMessage() == message)


class ClockedNeo5:
    """A NEO-5 behind an in-memory port on a test clock: RMC and GGA (VTG and GLL too while
    not turned off) every 1/``hz`` s of the clock when :meth:`step` is called; UBX CFG
    answered with ACK-ACK (CFG-RATE and CFG-MSG taken); :meth:`reset` as
    :meth:`Neo5Pty.reset`. ``writes``: (clock, bytes) the host wrote."""

    def __init__(self, clock: list[float], hz: float = 1.0, full: bool = True) -> None:
        self.clock, self.hz = clock, hz
        self.extra = ["VTG", "GLL"] if full else []
        self.out = bytearray()
        self.writes: list[tuple[float, bytes]] = []
        self.mute = False
        self.keeps_msg = True  # False: CFG-MSG is ACKed and ignored
        self.timeout: float | None = None
        self._framer = NmeaFramer()
        self._next_t = clock[0]

    def write(self, data: bytes) -> int:
        self.writes.append((self.clock[0], bytes(data)))
        for f in self._framer.feed(data):
            if isinstance(f, UbxFrame) and f.msg_class == 0x06:
                if f.msg_id == 0x08:
                    self.hz = 1000.0 / struct.unpack("<H", f.payload[:2])[0]
                off = f.msg_id == 0x01 and f.payload[0] == 0xF0 and f.payload[2] == 0
                if off and self.keeps_msg:
                    self.extra = [m for m in self.extra if NMEA_MSG_IDS[m] != f.payload[1]]
                self.out += ubx_frame(0x05, 0x01, bytes((0x06, f.msg_id)))
        return len(data)

    @property
    def in_waiting(self) -> int:
        return len(self.out)

    def read(self, n: int = 1) -> bytes:
        d = bytes(self.out[:n])
        del self.out[:n]
        return d

    def close(self) -> None:
        pass

    def reset(self, banner: bool = True, extra: tuple[str, ...] = ("VTG", "GLL")) -> None:
        self.hz, self.extra = 1.0, list(extra)
        if banner:
            self.out += b"".join(_s(b) for b in NEO5_BANNER)

    def step(self) -> None:
        t = self.clock[0]
        if t >= self._next_t:
            self._next_t = t + 1.0 / self.hz
            if not self.mute:
                utc = datetime(2026, 12, 5, 12, tzinfo=UTC) + timedelta(seconds=t)
                self.out += _burst(utc, self.extra)


def _clocked(
    setup: bool = True, hz: float = 1.0, full: bool = True
) -> tuple[GpsReader, ClockedNeo5, Callable[[float], None]]:
    clock = [1000.0]
    rx = ClockedNeo5(clock, hz, full)
    reader = GpsReader(
        lambda: rx,
        clock=lambda: clock[0],
        sleep=lambda s: None,
        stale_s=5.0,
        setup=ReceiverSetup(4.0) if setup else None,
        expected_rate_hz=4.0,
    )

    def run(seconds: float) -> None:
        until = clock[0] + seconds
        while clock[0] < until - 1e-9:
            clock[0] = round(clock[0] + 0.05, 3)
            rx.step()
            reader.poll(0.0)

    return reader, rx, run


def test_a_reset_without_a_banner_shows_in_the_sentences_the_setup_turned_off(
    caplog: Any,
) -> None:
    caplog.set_level(logging.INFO)
    reader, rx, run = _clocked()
    setup = reader.setup
    assert setup is not None
    run(10.0)
    assert (setup.state, rx.hz, rx.extra) == ("acked", 4.0, [])
    rx.reset(banner=False)  # the banner lost in the brown-out: VTG and GLL tell
    run(1.0)
    assert setup.rounds == 2  # written again; the last write was 10 s ago: at once
    assert setup.losses == 1
    assert setup.lost_reason == "VTG sentences came back, which the setup turned off"
    run(10.0)
    assert (setup.state, rx.hz, rx.extra) == ("acked", 4.0, [])
    st = reader.fix_rate.status()
    assert 3.5 < st["measured_rate_hz"] < 4.5 and "slow" not in st, st
    assert setup.status()["losses"] == 1 and "VTG" in setup.status()["lost"]
    assert len([m for m in caplog.records if "lost its configuration" in m.getMessage()]) == 1


def test_a_reset_seen_only_in_the_rate_is_configured_again() -> None:
    reader, rx, run = _clocked()
    setup = reader.setup
    assert setup is not None
    run(10.0)
    assert setup.state == "acked" and rx.hz == 4.0
    rx.reset(banner=False, extra=())  # no banner, no default sentence: only the rate tells
    run(4.0)
    assert setup.rounds == 1  # slow for less than 5 s so far
    run(8.0)
    assert setup.rounds == 2, setup.status()
    assert setup.losses == 1
    assert setup.lost_reason is not None and "fixes arrive at" in setup.lost_reason
    assert "CFG-RATE for 4 Hz" in setup.lost_reason
    run(6.0)
    assert setup.state == "acked" and rx.hz == 4.0
    assert 3.5 < (reader.fix_rate.measured_hz or 0) < 4.5


def test_the_setup_is_written_again_at_most_every_10_s_and_warned_once_a_minute(
    caplog: Any,
) -> None:
    caplog.set_level(logging.INFO)
    reader, rx, run = _clocked()
    setup = reader.setup
    assert setup is not None
    run(10.0)
    rx.reset()
    run(2.0)
    rx.reset()  # again, 2 s later: lost again, written 10 s after the last write
    run(12.0)
    sent = [t - 1000.0 for t, data in rx.writes if data == setup.init_bytes]
    assert len(sent) == 3 and sent[0] == pytest.approx(0.05), sent
    assert 10.0 <= sent[1] < 10.2 and sent[2] - sent[1] >= 10.0, sent
    assert setup.losses == 2 and setup.state == "acked" and rx.hz == 4.0
    lost = [m.getMessage() for m in caplog.records if "lost its configuration" in m.getMessage()]
    assert len(lost) == 1, lost  # the second within a minute: counted, not logged


def test_a_receiver_that_does_not_keep_its_setup_is_written_again_less_and_less_often(
    caplog: Any,
) -> None:
    # review of ff03700: GLL/VTG coming back after every ACK (a receiver that ACKs CFG-MSG
    # and ignores it, or something else re-enabling them) had the setup written every 10 s
    # for ever; now the wait doubles with each such loss, up to RESEND_MAX_S, and says why
    caplog.set_level(logging.INFO)
    reader, rx, run = _clocked()
    rx.keeps_msg = False
    setup = reader.setup
    assert setup is not None
    run(1000.0)
    sent = [round(t - 1000.0, 2) for t, data in rx.writes if data == setup.init_bytes]
    assert sent == [0.05, 10.05, 30.05, 70.05, 150.05, 310.05, 610.05, 910.05], sent
    assert setup.resend_s == 300.0  # RESEND_MAX_S
    st = setup.status()
    assert "does not keep its setup" in st["not_kept"] and st["resend_s"] == 300.0, st
    assert "GLL" in st["not_kept"] or "VTG" in st["not_kept"], st
    said = [m.getMessage() for m in caplog.records if m.name == "drivers.gps_io"]
    assert len([m for m in said if "does not keep its setup" in m]) == 1, said
    assert len([m for m in said if "lost its configuration" in m]) == 1, said
    # it keeps it from now on: taken at the next write (910 + 300), and held
    rx.keeps_msg = True
    run(400.0)
    assert (setup.state, rx.extra, len(rx.writes) - len(sent)) == ("acked", [], 1)
    assert "not_kept" in setup.status()  # (the last loss's verdict, until the next loss)
    rx.reset()  # a restart: the setup again after 10 s, as ever, and no longer 'not kept'
    run(12.0)
    sent = [t - 1000.0 for t, data in rx.writes if data == setup.init_bytes]
    assert len(sent) == 10 and 1400.0 < sent[-1] < 1412.0, sent
    assert (setup.state, setup.resend_s, rx.hz) == ("acked", 10.0, 4.0)
    assert "not_kept" not in setup.status()


def test_a_banner_before_the_first_answers_is_no_loss() -> None:
    # the simulated receiver's banner waits in the pty when the daemon opens it (HIL): it
    # comes before the ACKs, which tell that the receiver took the setup after it
    reader, rx, run = _clocked()
    rx.out += b"".join(_s(b) for b in NEO5_BANNER)
    setup = reader.setup
    assert setup is not None
    run(5.0)
    assert (setup.state, setup.losses, setup.rounds, rx.hz) == ("acked", 0, 1, 4.0)


def test_the_measured_rate_falls_while_the_gps_is_silent() -> None:
    reader, rx, run = _clocked(setup=False, hz=4.0, full=False)
    run(5.0)
    rate = reader.fix_rate
    assert rate.measured_hz == pytest.approx(4.0, abs=0.2) and rate.slow is None
    rx.mute = True  # the port stays open, nothing comes
    run(3.0)
    assert rate.measured_hz is not None and rate.measured_hz < 2.0
    # silence is no slow receiver (an outside audit, round 19: "set its rate" for a cut
    # line): the GPS's health says it is stale, the rate blames nothing
    assert rate.slow is None
    run(10.0)
    assert rate.measured_hz == 0.0
    assert rate.status()["measured_rate_hz"] == 0.0 and rate.slow is None
    assert reader.health.state.value == "stale", reader.health
    rx.mute = False
    run(5.0)
    assert rate.measured_hz == pytest.approx(4.0, abs=0.2) and rate.slow is None


def test_the_slow_warning_comes_again_each_time_the_rate_falls(caplog: Any) -> None:
    caplog.set_level(logging.INFO)
    reader, rx, run = _clocked(setup=False, hz=1.0, full=False)

    def slow_warnings() -> int:
        return len([m for m in caplog.records if "under gps.rate_hz" in m.getMessage()])

    run(12.0)
    assert slow_warnings() == 1
    rx.hz = 4.0  # set in u-center, say
    run(5.0)
    assert reader.fix_rate.slow is None
    run(5.0)
    assert slow_warnings() == 1  # fine: nothing new
    rx.hz = 1.0  # fell back (a reset the host does not configure: configure_receiver false)
    run(12.0)
    assert reader.fix_rate.slow is not None and slow_warnings() == 2
    run(12.0)
    assert slow_warnings() == 2  # still slow: not again


# --------------------------------------------------------------------------------------------
# Review 6, item 5: at 4 Hz on 9600 baud the line carries 240 bytes an epoch. With GSA and GSV
# once a second, the simulated NEO-5's GSV epoch was 400 bytes (RMC 73, GGA 74, GSA 57, GSV
# 190): 160 bytes still on the line when the next epoch began, whose fix then arrived 0.32 s
# after its epoch instead of 0.15 s (stamped at arrival). A slower GSV rate would make that
# rarer, not smaller (a GSV group goes out whole in one epoch): at 4 Hz on 9600 baud GSV is
# off, and every epoch leaves the line before the next.


def _gga_lateness(baud: int, rate_hz: float, epochs: int = 200) -> tuple[list[float], list[int]]:
    """The simulated receiver (default scenario) configured by neo5_setup(rate_hz, baud)
    through its own UBX input, its epochs through its UART model: each GGA's arrival after
    its epoch (s), and each epoch's bytes."""
    from sim_backend.hil import HilParams
    from sim_backend.receiver import UartTx, build_receiver
    from sim_backend.ubx_config import UbxConfigPort

    w = HilParams(gps_rate_hz=1.0, gps_baud=baud).load_world()
    rx = build_receiver(w, w.seed)
    ubx = UbxConfigPort(1.0)
    for answer in ubx.feed(b"".join(f for _, f in neo5_setup(rate_hz, baud))):
        assert answer.reply[3] == 0x01  # ACK-ACK
    assert ubx.rate_hz == rate_hz
    uart = UartTx(baud)
    late, sizes = [], []
    for k in range(1, epochs):
        t = k / rate_hz
        ep = rx.epoch(t, (0.5 * t, 0.0, 0.0), (0.5, 0.0, 0.0))
        lines = [ln for ln in rx.sentences(ep) if ubx.keeps(ln[3:6].decode(), k)]
        sizes.append(sum(len(ln) for ln in lines))
        late += [t_end - t for t_end, ln in uart.send(lines, t) if ln[3:6] == b"GGA"]
    assert uart.dropped == 0 and len(late) == epochs - 1
    return late, sizes


@pytest.mark.parametrize(("baud", "rate_hz"), [(9600, 4.0), (9600, 2.0), (9600, 1.0), (38400, 4.0)])
def test_every_epoch_leaves_the_line_before_the_next(baud: int, rate_hz: float) -> None:
    late, sizes = _gga_lateness(baud, rate_hz)
    room = baud / 10 / rate_hz
    assert max(sizes) <= room, (max(sizes), room)
    # each fix as soon as its own RMC and GGA are out (142-148 bytes here, 152 at most),
    # never behind an earlier epoch's bytes
    assert max(late) <= 152 * 10 / baud, (min(late), max(late))


def test_the_9600_baud_setup_at_4_hz_and_its_budget() -> None:
    names = [n for n, _ in neo5_setup(4.0, 9600)]
    assert names[3:5] == ["CFG-MSG GSA 4", "CFG-MSG GSV 0"]
    assert [n for n, _ in neo5_setup(4.0, 115200)][3:5] == ["CFG-MSG GSA 4", "CFG-MSG GSV 4"]
    assert [n for n, _ in neo5_setup(1.0, 9600)][3:5] == ["CFG-MSG GSA 1", "CFG-MSG GSV 1"]
    _, sizes = _gga_lateness(9600, 4.0, 41)
    assert sum(sizes[:40]) / 10.0 < 0.85 * 960  # 10 s: RMC + GGA each epoch, GSA each 4th


def test_hil_at_9600_baud_and_4_hz_each_fix_leaves_the_line_before_the_next_epoch(
    tmp_path: Path, run_daemon: Any
) -> None:
    cfg = hil_config(tmp_path)
    cfg = dataclasses.replace(
        cfg,
        gps=dataclasses.replace(cfg.gps, configure_receiver=True, rate_hz=4.0, stale_s=2.0),
        sim=dataclasses.replace(cfg.sim, gps_rate_hz=1.0, gps_baud=9600),
        safety=dataclasses.replace(cfg.safety, fix_stale_s=0.75),
    )
    r = run_daemon(Daemon(cfg))
    world = r.daemon.devices.backend("sim")
    with RemoteClient("127.0.0.1", r.port) as c:
        wait_for(lambda: _gps_receiver(c)["setup"]["state"] == "acked", 10, "ACKs")
        assert world.receiver.rate_hz == 4.0
        st = _gps_receiver(c)["setup"]
        t_cfg = time.monotonic() - world.t0

        def ggas() -> int:  # the GGAs the receiver model put on the line from t_cfg + 1.5 s
            ends = [t for t, line in list(world.gps_wire) if line[3:6] == b"GGA"]
            return len([t for t in ends if t >= t_cfg + 1.5])

        # 12 epochs (3 s at 4 Hz), counted rather than timed: a receiver thread held up on
        # a loaded host skips epochs
        wait_for(lambda: ggas() >= 12, 20, "12 epochs at 4 Hz")
    assert r.stop() == 0
    day = world.utc0.date()
    late = []
    for t_end, line in list(world.gps_wire):
        if line[3:6] != b"GGA" or t_end < t_cfg + 1.5:
            continue
        hms = line.split(b",")[1].decode()
        utc = datetime.combine(day, datetime.strptime(hms, "%H%M%S.%f").time(), UTC)
        if (utc - world.utc0).total_seconds() < -43200:
            utc += timedelta(days=1)
        late.append(t_end - world.scenario_t_s(utc))
    assert len(late) >= 10, late
    # RMC + GGA (~147 bytes) take 0.153 s at 9600 baud; with the GSV epoch the next one's
    # GGA came 0.32 s after its epoch
    assert max(late) < 0.2, sorted(late)[-5:]
    assert world.ubx.msg_rates["GSV"] == 0
    assert st["baud"] == 9600 and st["answers"]["CFG-MSG GSV 0"] == "ack", st


def test_a_very_slow_receiver_is_slow_steadily_not_silent_between_its_fixes() -> None:
    # a review (round 19): at 0.09 Hz against rate_hz 1 a 10 s window holds no fix most of
    # the time, and "silent" there made the complaint come and go 48 times in 300 s
    from drivers.gps_io import FixRate

    rate = FixRate(1.0)
    flips, was = 0, None
    for k in range(3000):
        t = 0.1 * k
        if k % 111 == 0:
            rate.add(t)
        else:
            rate.tick(t)
        now = rate.slow is not None
        flips += was is not None and now != was and rate.measured_hz is not None
        was = now
    assert rate.slow is not None and flips <= 1, flips
