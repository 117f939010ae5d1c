"""Motor link protocol: the sans-IO board, and the host link talking to it over a REAL pty."""

from __future__ import annotations

import errno
import itertools
import logging
import math
import os
import socket
import threading
import time
import tty
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any

import pytest
import serial
from hypothesis import given, settings
from hypothesis import strategies as st

from drivers import registry
from drivers.motors import (
    ENC_MODULO,
    EncoderUnwrap,
    LogMotorLink,
    MotorBoard,
    MotorLink,
    SerialMotorLink,
    parse_encoder_payload,
    serve_board_fd,
    wrap_count_delta,
)
from x6wd.core.records import MotorCommand

# --- the board alone (sans-IO) ----------------------------------------------------------------


def test_board_drive_stop_query_with_sequence_numbers() -> None:
    b = MotorBoard()
    assert b.feed(b"M 60 -40 #7\n", 0.0) == b"OK #7\n"
    assert (b.left_pct, b.right_pct) == (60, -40)
    assert b.feed(b"q #8\r\n", 0.1) == b"OK #8 60 -40 500\n"
    assert b.feed(b"S\n", 0.2) == b"OK\n"
    assert (b.left_pct, b.right_pct) == (0, 0)
    assert b.feed(b"W 250 #9\nP #10\n", 0.3) == b"OK #9\nOK #10\n"
    assert b.watchdog_ms == 250
    assert b.commands == 5


@pytest.mark.parametrize(
    ("line", "reply"),
    [
        (b"M 101 0 #1\n", b"ERR #1 range\n"),
        (b"M -101 0\n", b"ERR range\n"),
        (b"M 10 #2\n", b"ERR #2 syntax\n"),
        (b"M 1.5 2 #3\n", b"ERR #3 syntax\n"),
        (b"W 10 #4\n", b"ERR #4 range\n"),
        (b"X #5\n", b"ERR #5 unknown\n"),
        (b"S 3 #6\n", b"ERR #6 syntax\n"),
        (b"M 1 1 #x\n", b"ERR syntax\n"),
        (b"#5\n", b"ERR #5 syntax\n"),
    ],
)
def test_board_rejects_bad_commands_and_keeps_drive(line: bytes, reply: bytes) -> None:
    b = MotorBoard()
    b.feed(b"M 30 30\n", 0.0)
    assert b.feed(line, 0.1) == reply
    assert (b.left_pct, b.right_pct) == (30, 30)
    assert b.errors == 1


def test_board_overflow_line_is_discarded() -> None:
    b = MotorBoard()
    out = b.feed(b"M " + b"1" * 200, 0.0)
    assert out == b""
    assert b.feed(b" 5\nM 20 20 #3\n", 0.0) == b"ERR overflow\nOK #3\n"
    assert (b.left_pct, b.right_pct) == (20, 20)


def test_board_watchdog_stops_after_period_without_commands() -> None:
    b = MotorBoard(watchdog_ms=200)
    b.feed(b"M 50 50\n", 10.0)
    assert b.tick(10.199) == b""
    assert b.running
    b.feed(b"P\n", 10.15)  # a ping feeds it
    assert b.tick(10.349) == b"" and b.running
    assert b.tick(10.35) == b"EVT WATCHDOG\n"
    assert not b.running and b.watchdog_trips == 1
    assert b.tick(20.0) == b""  # reported once
    # a late command: the watchdog fires first, then the command runs
    b.feed(b"M 10 10\n", 20.0)
    assert b.feed(b"M 40 40 #2\n", 21.0) == b"EVT WATCHDOG\nOK #2\n"
    assert (b.left_pct, b.right_pct) == (40, 40)


def test_board_boot_forgets_settings() -> None:
    b = MotorBoard(watchdog_ms=400)
    b.feed(b"W 2000\nM 50 50\nM 1", 0.0)
    assert b.boot() == b"EVT BOOT\n"
    assert (b.left_pct, b.right_pct, b.watchdog_ms) == (0, 0, 400)
    assert b.feed(b"0 10\n", 0.1) == b"ERR unknown\n"  # the half line died with the boot


def test_board_invalid_lines_do_not_feed_watchdog() -> None:
    b = MotorBoard(watchdog_ms=100)
    b.feed(b"M 50 50\n", 0.0)
    b.feed(b"garbage\n", 0.09)
    assert b.tick(0.1) == b"EVT WATCHDOG\n"


STREAM = b"W 300 #1\nM 10 -10 #2\nbogus\nM 100 100\r\nQ #3\nS #4\nM 5 5 #5\n"


@settings(max_examples=60, deadline=None)
@given(cuts=st.lists(st.integers(0, len(STREAM)), max_size=12))
def test_board_replies_do_not_depend_on_chunking(cuts: list[int]) -> None:
    whole = MotorBoard()
    expected = whole.feed(STREAM, 0.0)
    b = MotorBoard()
    bounds = [0, *sorted(cuts), len(STREAM)]
    got = b"".join(b.feed(STREAM[a:c], 0.0) for a, c in itertools.pairwise(bounds))
    assert got == expected
    assert (b.left_pct, b.right_pct, b.watchdog_ms) == (5, 5, 300)


# --- the host link over a real pseudo-terminal ------------------------------------------------


@dataclass
class PtyBoard:
    """A MotorBoard served on a pty master; the link opens the slave with pyserial."""

    master: int
    slave: int
    name: str
    board: MotorBoard
    stop: threading.Event
    thread: threading.Thread | None = None
    lock: threading.Lock = threading.Lock()  # noqa: RUF009

    def start(self, boot: bool = False) -> None:
        self.stop = threading.Event()
        self.thread = threading.Thread(
            target=serve_board_fd,
            args=(self.master, self.board, self.stop),
            kwargs={"lock": self.lock, "boot": boot},
            daemon=True,
        )
        self.thread.start()

    def halt(self) -> None:
        self.stop.set()
        if self.thread is not None:
            self.thread.join(5)

    def state(self) -> tuple[int, int]:
        with self.lock:
            return self.board.left_pct, self.board.right_pct


@pytest.fixture
def pty_board() -> Iterator[PtyBoard]:
    master, slave = os.openpty()
    tty.setraw(slave)
    pb = PtyBoard(master, slave, os.ttyname(slave), MotorBoard(), threading.Event())
    pb.start()
    yield pb
    pb.halt()
    os.close(master)
    os.close(slave)


def open_link(pb: PtyBoard, **kw: float) -> SerialMotorLink:
    port = serial.Serial(pb.name, baudrate=115200, timeout=0.02)
    kw.setdefault("ack_timeout_s", 0.5)
    return SerialMotorLink(port, **kw)  # type: ignore[arg-type]


def wait_for(cond: Callable[[], bool], limit_s: float = 5.0) -> bool:
    end = time.monotonic() + limit_s
    while time.monotonic() < end:
        if cond():
            return True
        time.sleep(0.005)
    return cond()


@pytest.mark.integration
def test_link_drives_the_board_through_a_pty(pty_board: PtyBoard) -> None:
    with open_link(pty_board, watchdog_ms=2000) as link:
        assert isinstance(link, MotorLink)
        assert link.configured and pty_board.board.watchdog_ms == 2000
        assert link.drive(60, -40.4, reason="turn")
        assert pty_board.state() == (60, -40)
        assert link.last_command is not None
        assert (link.last_command.left_pct, link.last_command.right_pct) == (60.0, -40.0)
        assert link.query() == (60, -40, 2000)
        assert link.ping()
        assert link.send(MotorCommand(0.0, 0.0, 0.0, "hold"))
        assert pty_board.state() == (0, 0)
        assert link.healthy
        assert link.counters.acked == link.counters.sent == 5  # W M Q P S


@pytest.mark.integration
def test_close_stops_the_motors_first(pty_board: PtyBoard) -> None:
    link = open_link(pty_board, watchdog_ms=5000)
    assert link.drive(80, 80)
    link.close()
    assert pty_board.state() == (0, 0)
    assert link.last_command is not None and link.last_command.is_stop
    assert not link.healthy
    link.close()  # idempotent
    assert not link.drive(10, 10)


@pytest.mark.integration
def test_board_watchdog_stops_a_silent_host(pty_board: PtyBoard) -> None:
    with open_link(pty_board, watchdog_ms=50) as link:
        assert link.drive(30, 30)
        assert wait_for(lambda: pty_board.state() == (0, 0))
        assert pty_board.board.watchdog_trips == 1
        assert link.drive(20, 20)  # the EVT line in between is counted, not mistaken for OK
        assert link.counters.events == 1


@pytest.mark.integration
def test_dead_board_makes_link_unhealthy_and_stop_never_raises(pty_board: PtyBoard) -> None:
    link = open_link(pty_board, ack_timeout_s=0.2)
    assert link.drive(10, 10) and link.healthy
    pty_board.halt()  # the board stops answering
    timeouts = link.counters.timeouts
    assert not link.drive(20, 20)
    assert not link.stop()
    assert not link.healthy
    assert link.counters.timeouts - timeouts == 4  # 2 commands x (1 try + 1 retry)
    assert link.counters.stop_failures == 1
    pty_board.start()  # it comes back
    assert link.drive(5, 5)
    assert link.healthy and pty_board.state() == (5, 5)
    link.close()


@pytest.mark.integration
def test_stop_on_a_broken_port_returns_false(pty_board: PtyBoard) -> None:
    link = open_link(pty_board)
    link.port.close()  # the port vanishes under the link
    assert link.stop() is False
    assert not link.drive(10, 10)
    assert link.counters.write_errors >= 2
    link.close()  # still no exception


@pytest.mark.integration
def test_late_reply_to_a_timed_out_command_is_not_taken_as_ack(pty_board: PtyBoard) -> None:
    pty_board.halt()
    link_port = serial.Serial(pty_board.name, baudrate=115200, timeout=0.02)
    link = SerialMotorLink(link_port, ack_timeout_s=0.05, retries=0)  # W goes unanswered
    assert not link.configured
    # the board answers the W late (its old sequence number) and never the ping
    os.write(pty_board.master, b"OK #1\n")
    assert not link.ping()  # OK #1 is stale: W #2 and P #3 get no answer
    assert link.counters.timeouts == 3 and link.counters.acked == 0
    assert not link.healthy
    pty_board.start()  # the board appears: the link sets the watchdog it never confirmed
    assert link.ping() and link.configured and link.healthy
    assert pty_board.board.watchdog_ms == 500
    link.port.close()


@pytest.mark.integration
def test_link_resets_the_watchdog_after_a_board_reboot(pty_board: PtyBoard) -> None:
    with open_link(pty_board, watchdog_ms=3000) as link:
        assert link.drive(40, 40) and pty_board.board.watchdog_ms == 3000
        pty_board.halt()
        pty_board.start(boot=True)  # brown-out: the board restarts with its defaults
        assert wait_for(lambda: pty_board.board.watchdog_ms == 500)
        assert link.drive(30, 30)
        assert pty_board.board.watchdog_ms == 3000 and pty_board.state() == (30, 30)
        assert link.configured and link.counters.events == 1


@pytest.mark.integration
def test_a_watchdog_stop_or_a_board_restart_shows_in_health_and_the_log(
    pty_board: PtyBoard, caplog: pytest.LogCaptureFixture
) -> None:
    with open_link(pty_board, watchdog_ms=50) as link, caplog.at_level(logging.INFO):
        assert link.drive(30, 30)
        assert wait_for(lambda: pty_board.state() == (0, 0))  # the host fell silent
        assert link.stop()  # EVT WATCHDOG arrives before this OK
        h = link.health
        assert link.counters.watchdog_stops == 1 and h.state == "degraded" and h.errors == 1
        assert "EVT WATCHDOG" in h.last_error
        assert link.healthy  # the board answers: a fault to show, not a lost link
        pty_board.halt()
        pty_board.start(boot=True)  # a brown-out
        assert link.drive(10, 10)
        assert link.counters.board_restarts == 1 and "EVT BOOT" in link.health.last_error
        assert link.stop()
    warned = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert sum("EVT WATCHDOG" in m for m in warned) == 1
    assert sum("EVT BOOT" in m for m in warned) == 1


@pytest.mark.integration
def test_a_broken_port_is_reopened_with_backoff_and_the_board_set_up_again(
    pty_board: PtyBoard,
) -> None:
    opens: list[float] = []
    refuse = [True]

    def reopen() -> serial.Serial:
        opens.append(time.monotonic())
        if refuse[0]:
            raise OSError(errno.ENODEV, "no such device")
        return serial.Serial(pty_board.name, baudrate=115200, timeout=0.02)

    port = serial.Serial(pty_board.name, baudrate=115200, timeout=0.02)
    link = SerialMotorLink(
        port, ack_timeout_s=0.5, watchdog_ms=2000, reopen=reopen, reopen_initial_s=0.5,
        reopen_max_s=1.0,
    )  # fmt: skip
    assert link.drive(10, 10)
    link.port.close()  # the adapter vanishes under the link
    t_break = time.monotonic()
    assert not link.drive(10, 10) and not link.healthy
    assert link.health.state == "disconnected" and link.port is port
    assert not link.drive(10, 10)  # within the backoff: no attempt, no write
    assert opens == [] or opens[0] - t_break >= 0.5
    pty_board.board.feed(b"W 500\n", time.monotonic())  # the board lost the setting
    time.sleep(0.55)
    assert not link.drive(10, 10) and len(opens) == 1
    h = link.health
    assert h.state == "reconnecting" and "reopening the port failed" in h.last_error
    refuse[0] = False
    time.sleep(1.05)  # the backoff doubled to its 1 s cap
    assert link.drive(20, 20) and len(opens) == 2 and link.port is not port
    h = link.health
    assert link.healthy and h.state == "connected" and h.reconnects == 1
    assert link.counters.reopens == 1 and pty_board.state() == (20, 20)
    assert pty_board.board.watchdog_ms == 2000  # sent again after the reopen
    link.close()
    assert pty_board.state() == (0, 0)


@pytest.mark.integration
def test_a_tcp_board_that_drops_the_connection_is_reached_again() -> None:
    board = MotorBoard()
    server = socket.create_server(("127.0.0.1", 0))
    conns: list[socket.socket] = []

    def serve() -> None:
        while True:
            try:
                conn, _ = server.accept()
            except OSError:
                return
            conns.append(conn)
            with conn:
                while data := _recv(conn):
                    reply = board.feed(data, time.monotonic())
                    if reply:
                        conn.sendall(reply)

    threading.Thread(target=serve, daemon=True).start()
    url = f"tcp://127.0.0.1:{server.getsockname()[1]}?watchdog_ms=3000"
    link = registry.open_motors(url)
    try:
        assert isinstance(link, SerialMotorLink) and link.drive(30, 30)
        conns[-1].shutdown(socket.SHUT_RDWR)  # ser2net restarted, a Wi-Fi bridge dropped
        board.feed(b"W 500\n", time.monotonic())
        end = time.monotonic() + 10
        while not link.drive(25, 25):
            assert time.monotonic() < end, link.health
            time.sleep(0.05)
        assert len(conns) == 2 and link.health.reconnects == 1
        assert (board.left_pct, board.right_pct, board.watchdog_ms) == (25, 25, 3000)
    finally:
        link.close()
        server.close()
    assert (board.left_pct, board.right_pct) == (0, 0)


def _recv(conn: socket.socket) -> bytes:
    try:
        return conn.recv(4096)
    except OSError:
        return b""


def test_drive_rejects_bad_values() -> None:
    link = LogMotorLink()
    for bad in (101, -100.6, math.nan, math.inf):
        with pytest.raises(ValueError, match="left_pct"):
            link.drive(bad, 0)
    with pytest.raises(ValueError, match="right_pct"):
        link.drive(0, "50")  # type: ignore[arg-type]
    assert link.last_command is None


def test_log_link_keeps_commands_and_stops_on_close() -> None:
    seen: list[MotorCommand] = []
    t = iter([1.0, 2.0, 3.0, 4.0])
    with LogMotorLink(on_command=seen.append, clock=lambda: next(t)) as link:
        assert isinstance(link, MotorLink)
        assert link.drive(50, 49.6, "cruise")
        assert link.send(MotorCommand(1.5, -20.0, 20.0, "turn"))
        assert link.stop("hold")
        assert link.healthy
    assert [(c.t_s, c.left_pct, c.right_pct) for c in seen] == [
        (1.0, 50.0, 50.0),
        (1.5, -20.0, 20.0),
        (2.0, 0.0, 0.0),
        (3.0, 0.0, 0.0),
    ]
    assert seen[-1].reason == "close" and not link.healthy
    assert not link.drive(1, 1)
    assert list(link.commands)[-1] == link.last_command


def test_link_constructor_validates() -> None:
    with pytest.raises(ValueError, match="watchdog_ms"):
        SerialMotorLink(None, watchdog_ms=10)
    with pytest.raises(ValueError, match="ack_timeout_s"):
        SerialMotorLink(None, ack_timeout_s=0)


def test_board_overflow_line_arriving_whole_is_an_overflow() -> None:
    b = MotorBoard(watchdog_ms=500)
    b.feed(b"W 500\n", 0.0)
    long_line = b"M 10 10 " + b"#" * 80 + b"\n"
    assert b.feed(long_line + b"M 20 20 #4\n", 0.0) == b"ERR overflow\nOK #4\n"
    assert (b.left_pct, b.right_pct) == (20, 20)


# --- health and transient errors ----------------------------------------------------------

TRANSIENT = [errno.EIO, errno.ENXIO, errno.EAGAIN, errno.EBUSY, errno.EINTR, errno.EPROTO,
             errno.ETIMEDOUT, errno.EREMOTEIO]  # fmt: skip
NOT_TRANSIENT = [errno.ENOENT, errno.EACCES, errno.EBADF]


class PortProxy:
    """A real pyserial port, passed through as a driver uses it (``timeout``, ``in_waiting``,
    ``read``, ``close``): the base of a test's port that breaks some of it."""

    def __init__(self, port: serial.Serial) -> None:
        self.port = port

    @property
    def timeout(self) -> Any:
        return self.port.timeout

    @timeout.setter
    def timeout(self, value: Any) -> None:
        self.port.timeout = value

    @property
    def in_waiting(self) -> int:
        return int(self.port.in_waiting)

    def read(self, size: int = 1) -> bytes:
        return bytes(self.port.read(size))

    def close(self) -> None:
        self.port.close()


class FlakyPort(PortProxy):
    """The real pyserial port to the pty board whose next ``fail`` writes raise
    ``OSError(code)``; ``writes`` counts the attempts."""

    def __init__(self, port: serial.Serial) -> None:
        super().__init__(port)
        self.code = errno.EIO
        self.fail = 0
        self.writes = 0

    def write(self, data: bytes) -> int | None:
        self.writes += 1
        if self.fail > 0:
            self.fail -= 1
            raise OSError(self.code, os.strerror(self.code))
        return self.port.write(data)


def flaky_link(pb: PtyBoard) -> tuple[SerialMotorLink, FlakyPort]:
    port = FlakyPort(serial.Serial(pb.name, baudrate=115200, timeout=0.02))
    return SerialMotorLink(port, ack_timeout_s=0.3, retries=1), port


@pytest.mark.integration
@pytest.mark.parametrize("code", TRANSIENT, ids=lambda c: errno.errorcode[c])
def test_transient_port_errors_are_retried_within_the_command(
    pty_board: PtyBoard, code: int
) -> None:
    link, port = flaky_link(pty_board)
    try:
        assert link.health.state == "connected"  # the watchdog setting was acknowledged
        port.code, port.fail, port.writes = code, 1, 0
        assert link.drive(25, 25)  # the retry got through
        assert port.writes == 2 and pty_board.state() == (25, 25)
        h = link.health
        assert link.healthy and h.state == "connected" and h.errors == 1
        assert os.strerror(code) in h.last_error
        assert link.counters.write_errors == 1
    finally:
        link.close()


@pytest.mark.integration
@pytest.mark.parametrize("code", NOT_TRANSIENT, ids=lambda c: errno.errorcode[c])
def test_a_non_transient_port_error_loses_the_link_at_once(pty_board: PtyBoard, code: int) -> None:
    link, port = flaky_link(pty_board)
    try:
        link.take_health_events()
        port.code, port.fail, port.writes = code, 1, 0
        assert not link.drive(25, 25)
        assert port.writes == 1  # not retried: the port is broken
        assert not link.healthy  # one command was enough (unhealthy_after is 2)
        h = link.health
        assert h.state == "disconnected" and os.strerror(code) in h.last_error
        assert link.drive(10, 10)  # the port works again: the board answers
        h = link.health
        assert link.healthy and h.state == "connected" and h.reconnects == 1
        assert [(e.old, e.new) for e in link.take_health_events()] == [
            ("connected", "disconnected"),
            ("disconnected", "connected"),
        ]
    finally:
        link.close()


@pytest.mark.integration
def test_dead_board_health_goes_degraded_lost_reconnecting_and_back(pty_board: PtyBoard) -> None:
    link = open_link(pty_board, ack_timeout_s=0.1)
    assert link.drive(10, 10)
    pty_board.halt()
    assert not link.drive(20, 20)
    assert link.healthy and link.health.state == "degraded"  # one failed command
    assert not link.drive(20, 20)
    assert not link.healthy and link.health.state == "disconnected"
    assert not link.ping()
    h = link.health
    assert h.state == "reconnecting" and h.errors == 6  # 3 commands x (1 try + 1 retry)
    assert "no acknowledgement within 100 ms" in h.last_error
    pty_board.start()
    assert link.drive(5, 5)
    h = link.health
    assert h.state == "connected" and h.reconnects == 1 and h.consecutive_errors == 0
    events = link.take_health_events()
    assert [e.new for e in events] == [
        "connected", "degraded", "disconnected", "reconnecting", "connected"
    ]  # fmt: skip
    assert events[-1].message.startswith("motors reconnected (reconnect 1, ")
    link.close()
    assert link.health.state == "disconnected" and link.take_health_events() == []


# --- wheel encoders (docs/motors.md, "Wheel encoders") ------------------------------------------


def test_board_latches_encoder_counts_with_a_latch_number_and_32_bit_rollover() -> None:
    b = MotorBoard()
    assert b.feed(b"E #4\n", 0.0) == b"OK #4 1 0 0\n"
    b.add_counts(-6, 1532)  # backwards from 0 wraps to the top of the 32-bit ring
    assert b.feed(b"e\n", 0.1) == b"OK 2 4294967290 1532\n"
    b.add_counts(10, ENC_MODULO)  # a whole turn of the ring is no change
    assert b.feed(b"E #5\n", 0.2) == b"OK #5 3 4 1532\n"
    assert b.feed(b"E 1 #6\n", 0.3) == b"ERR #6 syntax\n"
    b.enc_seq = 65535
    assert b.feed(b"E\n", 0.4) == b"OK 0 4 1532\n"  # the latch number wraps too
    b.boot()
    assert (b.left_counts, b.right_counts, b.enc_seq) == (0, 0, 0)


def test_e_feeds_the_watchdog() -> None:
    b = MotorBoard(watchdog_ms=100)
    b.feed(b"M 20 20\n", 0.0)
    b.feed(b"E\n", 0.08)
    assert b.tick(0.15) == b"" and b.running
    assert b.tick(0.19) == b"EVT WATCHDOG\n"


@pytest.mark.parametrize(
    ("payload", "parsed"),
    [
        ("7 0 4294967295", (7, 0, 4294967295)),
        ("65536 0 0", None),
        ("1 4294967296 0", None),
        ("1 -1 0", None),
        ("1 2", None),
        ("1 2 3 4", None),
        ("1 2 3OK", None),
    ],
)
def test_encoder_payload_is_checked(payload: str, parsed: tuple[int, int, int] | None) -> None:
    assert parse_encoder_payload(payload) == parsed


@given(st.integers(-(2**31) + 1, 2**31 - 1), st.integers(0, ENC_MODULO - 1))
def test_wrap_count_delta_inverts_the_ring(delta: int, start: int) -> None:
    assert wrap_count_delta((start + delta) % ENC_MODULO - start) == delta


def test_unwrap_across_rollover_skips_and_restarts() -> None:
    u = EncoderUnwrap()
    assert u.update(1, ENC_MODULO - 3, 10) == (0, 0)  # the first reading is the baseline
    assert u.update(2, 5, 2) == (8, -8)  # left rolled over forwards
    assert u.update(5, 5, ENC_MODULO - 2) == (8, -12)  # two replies lost: counts still whole
    assert u.skipped == 2 and u.restarts == 0
    assert u.update(1, 100, 100) == (8, -12)  # latch number went back: restarted, new baseline
    assert u.update(2, 130, 90) == (38, -22)
    u.rebase()  # EVT BOOT
    assert u.update(1, 7, 7) == (38, -22)
    assert u.restarts == 2


@pytest.mark.integration
def test_link_reads_unwrapped_odometry_through_a_pty(pty_board: PtyBoard) -> None:
    with open_link(pty_board, watchdog_ms=2000) as link:
        with pty_board.lock:
            pty_board.board.add_counts(ENC_MODULO - 100, 50)
        first = link.read_odometry()
        assert first is not None and (first.left_counts, first.right_counts) == (0, 0)
        assert first.seq == 1
        with pty_board.lock:
            pty_board.board.add_counts(4300, -70)  # left passes the top of the ring
        odo = link.read_odometry()
        assert odo is not None
        assert (odo.left_counts, odo.right_counts, odo.seq) == (4300, -70, 2)
        assert odo.t_s >= first.t_s
        # a reboot loses the board's counters; the host's continue from where they were
        pty_board.halt()
        pty_board.start(boot=True)
        assert wait_for(lambda: pty_board.board.watchdog_ms == 500)
        with pty_board.lock:
            pty_board.board.add_counts(10, 10)
        assert link.ping()  # reads EVT BOOT
        after = link.read_odometry()
        assert after is not None and (after.left_counts, after.right_counts) == (4300, -70)
        with pty_board.lock:
            pty_board.board.add_counts(5, 6)
        again = link.read_odometry()
        assert again is not None and (again.left_counts, again.right_counts) == (4305, -64)
        assert link.encoders.restarts == 1


@pytest.mark.integration
def test_read_odometry_without_a_board_is_none(pty_board: PtyBoard) -> None:
    link = open_link(pty_board, ack_timeout_s=0.05)
    pty_board.halt()
    assert link.read_odometry() is None
    assert link.odometry_supported is None  # no answer is no refusal: support still unknown
    link.port.close()


class NoEncoderBoard(MotorBoard):
    """An older firmware: no ``E`` command (``ERR unknown``), everything else as documented."""

    def _line(self, line: str, t_s: float) -> bytes:
        tokens = line.split()
        if tokens and tokens[0].upper() == "E":
            seq = f" {tokens[-1]}" if tokens[-1].startswith("#") else ""
            return self._err(seq, "unknown")
        return super()._line(line, t_s)


@pytest.mark.integration
def test_a_board_that_refuses_e_answered_so_the_link_stays_healthy(pty_board: PtyBoard) -> None:
    pty_board.halt()
    pty_board.board = NoEncoderBoard()
    pty_board.start()
    with open_link(pty_board, watchdog_ms=2000) as link:
        assert link.odometry_supported is None
        link.take_health_events()  # the start's
        for _ in range(3):  # more than unhealthy_after (2) refusals in a row
            assert link.read_odometry() is None
        assert link.odometry_supported is False
        assert link.healthy and link.health.state == "connected"
        assert link.health.errors == 0 and link.take_health_events() == []
        assert link.counters.rejected == 3 and link.counters.timeouts == 0
        assert link.drive(20, 20) and pty_board.state() == (20, 20)
    # a board with encoders says so
    pty_board.halt()
    pty_board.board = MotorBoard()
    pty_board.start()
    with open_link(pty_board, watchdog_ms=2000) as link:
        assert link.read_odometry() is not None and link.odometry_supported is True
