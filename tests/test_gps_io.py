"""drivers.gps_io: the reader over a real pseudo-terminal and a real TCP socket."""

from __future__ import annotations

import errno
import os
import socket
import threading
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
import serial

from drivers.gps_io import GpsReader
from drivers.gps_nmea import GpsDecoder, cfg_rate, ubx_frame
from tests.test_motors import PortProxy
from x6wd.core.errors import ConfigError
from x6wd.core.records import GpsFix

NMEA_DIR = Path(__file__).resolve().parent / "data" / "nmea"
LOG = (NMEA_DIR / "ublox-lea-5h.log").read_bytes()


class Pty:
    """A pseudo-terminal whose slave is reachable through a symlink that can be repointed."""

    def __init__(self, link: Path) -> None:
        self.link = link
        self.master = -1
        self.slave = -1
        self.open()

    def open(self) -> None:
        self.master, self.slave = os.openpty()
        tmp = self.link.with_suffix(".new")
        tmp.unlink(missing_ok=True)
        tmp.symlink_to(os.ttyname(self.slave))
        os.replace(tmp, self.link)

    def hang_up(self) -> None:
        os.close(self.master)
        os.close(self.slave)
        self.master = self.slave = -1

    def close(self) -> None:
        if self.master >= 0:
            self.hang_up()


def _open(link: Path) -> Callable[[], serial.Serial]:
    return lambda: serial.Serial(str(link), 9600, timeout=0)


def _drain(reader: GpsReader, polls: int = 5) -> list:
    out: list = []
    for _ in range(polls):
        out += reader.poll(0.05)
    return out


def test_pty_stale_unplug_reconnect_resume(tmp_path: Path) -> None:
    link = tmp_path / "ttyGPS"
    pty = Pty(link)
    reader = GpsReader(_open(link), stale_s=0.3, backoff_initial_s=0.05, backoff_max_s=0.2)
    rng = np.random.default_rng(7)
    try:
        assert reader.poll(0.05) == []
        # open, and within stale_s of the open: connected (the controller still waits for a fix)
        assert reader.health.connected and reader.health.state == "connected"
        half = len(LOG) // 2
        records: list = []
        i = 0
        while i < half:
            n = int(rng.integers(1, 300))
            os.write(pty.master, LOG[i : i + n])
            i += n
            records += reader.poll(0.05)
        assert reader.health.state == "connected"  # as the last bytes are decoded (below)
        records += _drain(reader)
        fixes_before = [r for r in records if isinstance(r, GpsFix)]
        assert len(fixes_before) >= 5

        # Silence: the port stays open but nothing valid arrives -> stale.
        for _ in range(100):
            reader.poll(0.05)
            if reader.health.state == "stale":
                break
        assert reader.health.state == "stale" and reader.health.connected
        events = reader.take_health_events()
        assert [(e.old, e.new) for e in events] == [
            ("disconnected", "connected"),
            ("connected", "stale"),
        ]
        assert events[-1].message.startswith("gps stale: no good data for ")

        # Unplug: the far end goes away -> disconnected, not an exception.
        pty.hang_up()
        for _ in range(20):
            reader.poll(0.05)
            if reader.health.state == "disconnected":
                break
        health = reader.health
        assert health.state == "disconnected" and not health.connected
        assert "read failed" in health.last_error and health.errors >= 1
        # known at once: the transition is queued by the poll that saw the failure
        (lost,) = [e for e in reader.take_health_events() if e.new == "disconnected"]
        assert "Input/output error" in lost.message and lost.health.next_attempt_t_s

        # Plug back in (a new pty behind the same path): reopen, resume decoding.
        pty.open()
        records = []
        for _ in range(100):
            records += reader.poll(0.05)
            if reader.health.connected:
                break
        assert reader.health.reconnects == 1
        events = reader.take_health_events()
        assert events[-1].new == "connected"
        assert events[-1].message.startswith("gps reconnected (reconnect 1, ")
        while i < len(LOG):
            n = int(rng.integers(1, 300))
            os.write(pty.master, LOG[i : i + n])
            i += n
            records += reader.poll(0.05)
        # judged as the last bytes are decoded: the drain below polls for longer than stale_s
        # after them, so a loaded machine sees the (correct) stale state by its end
        assert reader.health.state == "connected"
        records += _drain(reader)
        fixes_after = [r for r in records if isinstance(r, GpsFix)]
        assert len(fixes_after) >= 5 and all(f.valid for f in fixes_after[1:])
        seen = {f.utc for f in fixes_before + fixes_after}
        assert len(seen) >= len(fixes_before) + len(fixes_after) - 2  # a new epoch each
    finally:
        reader.close()
        pty.close()


def test_open_failure_backs_off_exponentially_with_cap(tmp_path: Path) -> None:
    now = [100.0]
    slept: list[float] = []

    def sleep(dt: float) -> None:
        slept.append(dt)
        now[0] += dt

    reader = GpsReader(
        _open(tmp_path / "missing"),
        backoff_initial_s=0.1,
        backoff_max_s=0.5,
        clock=lambda: now[0],
        sleep=sleep,
    )
    gaps = []
    for _ in range(6):
        assert reader.poll(10.0) == []  # opening fails: still returns
        attempt_t = now[0]  # the poll slept until the scheduled attempt, then tried once
        gaps.append(round(reader.health.next_attempt_t_s - attempt_t, 6))  # type: ignore[operator]
        assert reader.health.state == "reconnecting"
    assert gaps == [0.1, 0.2, 0.4, 0.5, 0.5, 0.5]
    assert "open failed" in reader.health.last_error
    assert reader.health.reconnects == 0
    # A poll never waits longer than its timeout, even when the next attempt is later.
    slept.clear()
    reader.poll(0.01)
    assert slept and max(slept) <= 0.01


def test_ubx_config_sent_on_connect_and_ack_collected(tmp_path: Path) -> None:
    link = tmp_path / "ttyGPS"
    pty = Pty(link)
    init = cfg_rate(1000)
    reader = GpsReader(_open(link), init_bytes=init)
    try:
        reader.poll(0.05)
        assert reader.health.connected
        got = b""
        for _ in range(50):
            got += os.read(pty.master, 64)
            if len(got) >= len(init):
                break
        assert got == init
        ack = ubx_frame(0x05, 0x01, bytes((0x06, 0x08)))
        os.write(pty.master, LOG[300:700] + ack + LOG[700:1200])
        _drain(reader)
        acks = reader.take_acks()
        assert [(a.acked, a.msg_class, a.msg_id) for a in acks] == [(True, 0x06, 0x08)]
        assert reader.take_acks() == []
    finally:
        reader.close()
        pty.close()


def test_tcp_socket_url_reconnects_after_peer_closes() -> None:
    server = socket.create_server(("127.0.0.1", 0))
    port = server.getsockname()[1]
    stop = threading.Event()
    conns: list[socket.socket] = []

    def stream(c: socket.socket, chunks: int | None) -> None:
        # Like a receiver: bytes keep coming (pyserial drops what arrived before open()).
        i = 0
        while not stop.is_set() and (chunks is None or i < chunks):
            c.sendall(LOG[(i * 200) % 9000 : (i * 200) % 9000 + 200])
            i += 1
            stop.wait(0.01)

    def serve() -> None:
        c, _ = server.accept()
        conns.append(c)
        stream(c, 30)
        c.close()  # the first peer leaves
        c, _ = server.accept()
        conns.append(c)
        stream(c, None)

    t = threading.Thread(target=serve, daemon=True)
    t.start()
    reader = GpsReader(
        lambda: serial.serial_for_url(f"socket://127.0.0.1:{port}", timeout=0),
        backoff_initial_s=0.05,
    )
    try:
        after: list = []
        states = set()
        for _ in range(400):
            records = reader.poll(0.05)
            states.add(reader.health.state)
            if reader.health.reconnects == 1:
                after += records
                if sum(isinstance(r, GpsFix) for r in after) >= 3:
                    break
        assert "disconnected" in states
        assert reader.health.reconnects == 1
        assert sum(isinstance(r, GpsFix) for r in after) >= 3
        assert reader.health.state == "connected"
    finally:
        stop.set()
        reader.close()
        t.join(2.0)
        for c in conns:
            c.close()
        server.close()


def test_close_is_idempotent_and_bad_settings_rejected(tmp_path: Path) -> None:
    reader = GpsReader(_open(tmp_path / "none"), decoder=GpsDecoder())
    reader.close()
    reader.close()
    assert reader.poll(0.01) == [] and reader.health.state == "disconnected"
    with pytest.raises(ConfigError, match="stale_s"):
        GpsReader(_open(tmp_path / "none"), stale_s=0)
    with pytest.raises(ConfigError, match="backoff"):
        GpsReader(_open(tmp_path / "none"), backoff_initial_s=2.0, backoff_max_s=1.0)


TRANSIENT = [errno.EIO, errno.ENXIO, errno.EAGAIN, errno.EBUSY, errno.EINTR, errno.EPROTO,
             errno.ETIMEDOUT, errno.EREMOTEIO]  # fmt: skip
NOT_TRANSIENT = [errno.ENOENT, errno.EACCES, errno.EBADF]


class FlakyPort(PortProxy):
    """A real pyserial port on a pty whose next ``fail`` reads raise ``OSError(code)``."""

    def __init__(self, port: serial.Serial, code: int, fail: int) -> None:
        super().__init__(port)
        self.code = code
        self.fail = fail

    def fileno(self) -> int:
        return int(self.port.fileno())

    def read(self, size: int = 1) -> bytes:
        if self.fail > 0:
            self.fail -= 1
            raise OSError(self.code, os.strerror(self.code))
        return super().read(size)


def flaky_reader(link: Path, code: int, fails: list[int]) -> tuple[GpsReader, list[FlakyPort]]:
    """A reader whose n-th open gives a port failing ``fails[n]`` reads (0 after the list)."""
    opened: list[FlakyPort] = []

    def open_port() -> FlakyPort:
        n = fails[len(opened)] if len(opened) < len(fails) else 0
        opened.append(FlakyPort(serial.Serial(str(link), 9600, timeout=0), code, n))
        return opened[-1]

    return GpsReader(open_port, backoff_initial_s=0.01, transient_limit=3), opened


def _fixes(reader: GpsReader, pty: Pty, want: int = 5, polls: int = 60) -> int:
    """Feed the log until the reader decoded ``want`` fixes (or ``polls`` polls)."""
    n = 0
    for k in range(polls):
        os.write(pty.master, LOG[k * 300 : (k + 1) * 300])
        n += sum(isinstance(r, GpsFix) for r in reader.poll(0.05))
        if n >= want:
            break
    return n


@pytest.mark.parametrize("code", TRANSIENT, ids=lambda c: errno.errorcode[c])
def test_transient_read_errors_are_retried_on_the_same_port(tmp_path: Path, code: int) -> None:
    link = tmp_path / "ttyGPS"
    pty = Pty(link)
    reader, opened = flaky_reader(link, code, [2])  # 2 < transient_limit
    try:
        reader.poll(0.01)  # open
        os.write(pty.master, LOG[:3000])
        records = reader.poll(0.5)  # both failures and the good read happen in this poll
        assert records, "a transient error must not cost the poll its data"
        h = reader.health
        assert len(opened) == 1 and h.reconnects == 0 and h.connected
        assert h.state == "degraded" and h.errors == 2 and h.consecutive_errors == 0
        assert os.strerror(code) in h.last_error
        assert [e.new for e in reader.take_health_events()] == ["connected", "degraded"]
        assert _fixes(reader, pty) >= 5
    finally:
        reader.close()
        pty.close()


@pytest.mark.parametrize("code", [errno.EIO, errno.EBUSY])
def test_transient_errors_in_a_row_drop_the_port(tmp_path: Path, code: int) -> None:
    link = tmp_path / "ttyGPS"
    pty = Pty(link)
    reader, opened = flaky_reader(link, code, [3])  # = transient_limit
    try:
        reader.poll(0.01)
        os.write(pty.master, LOG[:3000])
        assert reader.poll(0.5) == []
        h = reader.health
        assert h.state == "disconnected" and h.errors == 3
        assert "3 transient errors in a row" in h.last_error
        assert _fixes(reader, pty) >= 5
        assert len(opened) == 2 and reader.health.reconnects == 1
        assert reader.health.state == "connected"
    finally:
        reader.close()
        pty.close()


@pytest.mark.parametrize("code", NOT_TRANSIENT, ids=lambda c: errno.errorcode[c])
def test_a_non_transient_read_error_drops_and_reopens_at_once(tmp_path: Path, code: int) -> None:
    link = tmp_path / "ttyGPS"
    pty = Pty(link)
    reader, opened = flaky_reader(link, code, [1])
    try:
        reader.poll(0.01)
        os.write(pty.master, LOG[:3000])
        assert reader.poll(0.5) == []
        h = reader.health
        assert h.state == "disconnected" and h.errors == 1 and os.strerror(code) in h.last_error
        assert [e.new for e in reader.take_health_events()] == ["connected", "disconnected"]
        assert _fixes(reader, pty) >= 5
        assert len(opened) == 2 and reader.health.reconnects == 1
        events = reader.take_health_events()
        assert [e.new for e in events] == ["connected"]
        assert events[0].message.startswith("gps reconnected (reconnect 1")
    finally:
        reader.close()
        pty.close()


def test_a_port_opened_inside_a_sentence_is_no_line_noise(tmp_path: Path) -> None:
    """An outside HIL audit: every clean start reported "gps corrupt input since start: 7
    skipped bytes", the tail of the sentence the receiver was sending as the port opened.
    Bytes before the first sentence after an open are that tail, not noise; noise after it,
    or far too much of it before any sentence, still counts."""
    link = tmp_path / "ttyGPS"
    pty = Pty(link)
    reader = GpsReader(_open(link), stale_s=5.0)
    try:
        assert reader.poll(0.05) == []  # open
        start = LOG.index(b"$", 40)  # inside the log's first sentence
        tail = LOG[17:start]
        os.write(pty.master, tail)
        records = _drain(reader, 3)
        os.write(pty.master, LOG[start : start + 1500])
        records += _drain(reader)
        assert [r for r in records if isinstance(r, GpsFix)]
        assert reader.health.corrupt.get("skipped_bytes", 0) == 0, reader.health.corrupt
        assert reader.joined_mid_sentence_bytes == len(tail)
        os.write(pty.master, b"noise!!" + LOG[start : start + 300])  # after it: counted
        _drain(reader)
        assert sum(reader.health.corrupt.values()) >= 1  # (after a cut line: framing)
    finally:
        reader.close()
        pty.close()
    reader = GpsReader(_open(link := tmp_path / "ttyGPS2"), stale_s=5.0)
    pty = Pty(link)
    try:
        reader.poll(0.05)
        os.write(pty.master, b"\x00" * 600 + LOG[:400])  # no sentence in 512 bytes: noise
        _drain(reader)
        assert reader.health.corrupt.get("skipped_bytes", 0) >= 600 - 512
    finally:
        reader.close()
        pty.close()
