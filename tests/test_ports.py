"""Simulated UARTs: the in-memory pipe and a real pseudo-terminal opened with pyserial."""

from __future__ import annotations

import time
from datetime import UTC, datetime
from pathlib import Path

import pytest
import serial

from drivers.gps_nmea import GpsDecoder
from sim_backend.epoch import GnssEpoch, SimSat
from sim_backend.nmea_out import NmeaFormatter, wire_time_s
from sim_backend.ports import MemoryUart, PtyUart
from x6wd.core.errors import ConfigError, DeviceIOError
from x6wd.core.records import GpsFix


def _burst(t_s: float = 0.0) -> bytes:
    ep = GnssEpoch(
        t_s, datetime(2020, 1, 1, 12, 0, int(t_s), tzinfo=UTC), True, 51.7, 19.5, 100.0, 30.0,
        0.0, None, 1, 3, 1.0, 1.8, 1.4,
        tuple(SimSat(p, 40.0, 30.0 * p, 40.0, True) for p in range(1, 9)),
    )  # fmt: skip
    return NmeaFormatter().format_epoch(ep)


def _read_until(port: serial.Serial, n: int, timeout_s: float = 5.0) -> bytes:
    out = b""
    deadline = time.monotonic() + timeout_s
    while len(out) < n and time.monotonic() < deadline:
        out += port.read(n - len(out))
    return out


def test_memory_uart_is_a_byte_pipe_with_pyserial_reads() -> None:
    u = MemoryUart()
    assert u.in_waiting == 0 and u.read(10) == b""
    assert u.write(b"$A*00\r\n$B") == 9
    assert u.in_waiting == 9
    assert u.readline() == b"$A*00\r\n"
    assert u.read(1) == b"$" and u.read(100) == b"B"
    u.write(b"xyz")
    u.reset_input_buffer()
    assert u.in_waiting == 0
    with u:
        pass
    with pytest.raises(DeviceIOError):
        u.read(1)


def test_memory_uart_overrun_drops_and_counts() -> None:
    u = MemoryUart(max_buffer=10)
    assert u.write(b"0123456789abc") == 10
    assert u.dropped == 3 and u.read_all() == b"0123456789"


def test_memory_uart_carries_bursts_to_the_real_decoder_in_any_chunking() -> None:
    u = MemoryUart()
    dec = GpsDecoder(emit_sentences=False)
    fixes = []
    for k in range(20):
        u.write(_burst(float(k)))
        while u.in_waiting:
            fixes += [r for r in dec.feed(u.read(7 + k), float(k)) if isinstance(r, GpsFix)]
    assert len(fixes) == 20 and all(f.valid for f in fixes)


def test_bad_baud_is_rejected() -> None:
    with pytest.raises(ConfigError, match="baudrate"):
        MemoryUart(baudrate=0)
    with pytest.raises(ConfigError, match="baudrate"):
        PtyUart(baudrate=-5)


@pytest.mark.integration
def test_pyserial_opens_the_pty_and_reads_exact_bytes() -> None:
    burst = _burst()
    with (
        PtyUart(realtime=False) as pty,
        serial.Serial(pty.port_name, 9600, timeout=0.5) as port,
    ):
        pty.write(burst)
        assert _read_until(port, len(burst)) == burst
        # The other direction: what the host sends the receiver (e.g. UBX config).
        port.write(b"\xb5\x62\x06\x08")
        port.flush()
        assert pty.read(16, timeout_s=2.0) == b"\xb5\x62\x06\x08"


@pytest.mark.integration
def test_realtime_pacing_spreads_a_burst_over_its_wire_time() -> None:
    # Pacing is checked on an injected clock (no timed assertion on the real one).
    now = [0.0]
    sleeps: list[float] = []

    def sleep(dt: float) -> None:
        sleeps.append(dt)
        now[0] += dt

    burst = _burst()
    with (
        PtyUart(9600, realtime=True, sleep=sleep, clock=lambda: now[0]) as pty,
        serial.Serial(pty.port_name, 9600, timeout=0.5) as port,
    ):
        pty.write(burst)
        assert now[0] == pytest.approx(wire_time_s(burst, 9600))
        assert len(sleeps) >= len(burst) // 96  # 10 ms chunks at 960 bytes/s
        assert _read_until(port, len(burst)) == burst


@pytest.mark.integration
def test_unplug_is_seen_by_the_reader_and_replug_keeps_the_link(tmp_path: Path) -> None:
    link = tmp_path / "ttyGPS"
    pty = PtyUart(realtime=False, link=link)
    try:
        assert Path(pty.port_name) == link and link.resolve() == Path(pty.slave_name)
        port = serial.Serial(pty.port_name, 9600, timeout=0.5)
        pty.write(b"hello")
        assert _read_until(port, 5) == b"hello"
        first = pty.slave_name
        pty.close()
        assert not pty.is_open
        with pytest.raises(serial.SerialException):
            for _ in range(20):
                port.read(1)
        port.close()
        with pytest.raises(DeviceIOError):
            pty.write(b"x")
        pty.reopen()
        assert link.resolve() == Path(pty.slave_name) and pty.slave_name != "" and first
        with serial.Serial(pty.port_name, 9600, timeout=0.5) as port2:
            pty.write(b"again")
            assert _read_until(port2, 5) == b"again"
    finally:
        pty.__exit__(None, None, None)
    assert not link.exists()


@pytest.mark.integration
def test_bytes_nobody_reads_are_dropped_not_blocking() -> None:
    with PtyUart(realtime=False) as pty:
        for _ in range(100):
            pty.write(b"x" * 1024)  # nobody has the port open
        assert pty.dropped > 0 and pty.written + pty.dropped == 100 * 1024
