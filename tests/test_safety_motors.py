"""The motor link and board to the letter of docs/motors.md: the board powers up stopped, its
watchdog period, line framing at its limits, replies that are found among other lines, refusals
that are not retried, a link that cannot hang on a blocking port, stop that never raises and
always says whether it worked. Written against the mutants `tools/mutate motors` found
surviving (docs/testing.md, "Mutation testing"). The host side talks to a real pty board."""

from __future__ import annotations

import contextlib
import errno
import os
import select
import threading
import time
import tty
from collections.abc import Callable, Iterator
from typing import Any

import pytest
import serial

from drivers.motors import (
    ENC_MODULO,
    EncoderUnwrap,
    LogMotorLink,
    MotorBoard,
    SerialMotorLink,
    parse_encoder_payload,
    serve_board_fd,
    wrap_count_delta,
)
from tests.test_motors import FlakyPort, PtyBoard, open_link, pty_board
from x6wd.core.records import MotorCommand

__all__ = ["pty_board"]  # the fixture, shared with test_motors


class Pty:
    """A bare pseudo-terminal: ``master`` is the board's end, ``name`` the host's port."""

    def __init__(self) -> None:
        self.master, self.slave = os.openpty()
        tty.setraw(self.master)
        tty.setraw(self.slave)
        self.name = os.ttyname(self.slave)

    def close(self) -> None:
        for fd in (self.master, self.slave):
            with contextlib.suppress(OSError):
                os.close(fd)


@pytest.fixture
def pty() -> Iterator[Pty]:
    p = Pty()
    yield p
    p.close()


def serve(p: Pty, board: MotorBoard, stop: threading.Event, **kw: Any) -> threading.Thread:
    t = threading.Thread(target=serve_board_fd, args=(p.master, board, stop), kwargs=kw,
                         daemon=True)  # fmt: skip
    t.start()
    return t


def read_host(p: Pty, timeout_s: float = 2.0) -> bytes:
    """What the board sent to the host side within ``timeout_s`` (s) (b"" if nothing)."""
    ready, _, _ = select.select([p.slave], [], [], timeout_s)
    return os.read(p.slave, 4096) if ready else b""


class ScriptedBoard:
    """A board on a pty whose answer to each complete line is ``answer(line)`` (bytes), by
    default what a real :class:`MotorBoard` replies; ``lines`` keeps what arrived."""

    def __init__(self, p: Pty, answer: Callable[[bytes], bytes] | None = None) -> None:
        self.p = p
        self.board = MotorBoard()
        self.answer = answer or (lambda line: self.board.feed(line + b"\n", time.monotonic()))
        self.lines: list[bytes] = []
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self) -> None:
        buf = b""
        while not self.stop.is_set():
            ready, _, _ = select.select([self.p.master], [], [], 0.01)
            if not ready:
                continue
            try:
                buf += os.read(self.p.master, 4096)
            except OSError:
                return
            *complete, buf = buf.split(b"\n")
            for line in complete:
                self.lines.append(line)
                reply = self.answer(line)
                if reply:
                    os.write(self.p.master, reply)

    def halt(self) -> None:
        self.stop.set()
        self.thread.join(2)


def limited_to_50(board: MotorBoard) -> Callable[[bytes], bytes]:
    """Firmware that refuses drive above 50 % with ``ERR #N range`` (docs/motors.md)."""

    def answer(line: bytes) -> bytes:
        tokens = line.decode().split()
        if tokens[0] == "M" and any(abs(int(v)) > 50 for v in tokens[1:3]):
            return f"ERR {tokens[-1]} range\n".encode()
        return board.feed(line + b"\n", time.monotonic())

    return answer


# -- the board alone (sans-IO) ---------------------------------------------------------------
def test_the_board_powers_up_stopped_with_its_default_watchdog() -> None:
    b = MotorBoard(watchdog_ms=300)
    assert (b.left_pct, b.right_pct, b.running) == (0, 0, False)
    assert b.feed(b"Q #1\n", 0.0) == b"OK #1 0 0 300\n"
    assert b.tick(100.0) == b""


@pytest.mark.parametrize(("ms", "ok"), [(50, True), (60_000, True), (49, False), (60_001, False)])
def test_the_watchdog_period_is_50_to_60000_ms(ms: int, ok: bool) -> None:
    b = MotorBoard()
    assert b.feed(f"W {ms} #7\n".encode(), 0.0) == (b"OK #7\n" if ok else b"ERR #7 range\n")
    if ok:
        assert MotorBoard(watchdog_ms=ms).watchdog_ms == ms
    else:
        with pytest.raises(ValueError, match=rf"^watchdog_ms must be 50\.\.60000, got {ms}$"):
            MotorBoard(watchdog_ms=ms)


def test_the_watchdog_stops_exactly_after_its_period_each_time() -> None:
    b = MotorBoard(watchdog_ms=200)
    b.feed(b"M 50 50\n", 1.0)
    assert b.tick(1.1999) == b"" and b.running
    assert b.tick(1.2) == b"EVT WATCHDOG\n" and not b.running
    b.feed(b"M 20 20\n", 2.0)
    assert b.tick(2.2) == b"EVT WATCHDOG\n"
    assert b.watchdog_trips == 2


def test_full_power_both_ways_is_in_range() -> None:
    b = MotorBoard()
    assert b.feed(b"M 100 -100 #1\n", 0.0) == b"OK #1\n"
    assert (b.left_pct, b.right_pct) == (100, -100)


@pytest.mark.parametrize(
    ("line", "reply"),
    [(b"P 1 #3\n", b"ERR #3 syntax\n"), (b"W #4\n", b"ERR #4 syntax\n"),
     (b"W 100 200 #5\n", b"ERR #5 syntax\n"), (b"Q 1 #6\n", b"ERR #6 syntax\n"),
     (b"P #99999\n", b"OK #99999\n"), (b"P #100000\n", b"ERR syntax\n"),
     (b"\xff\xfe\n", b"ERR unknown\n")],
)  # fmt: skip
def test_more_replies_by_the_protocol(line: bytes, reply: bytes) -> None:
    assert MotorBoard().feed(line, 0.0) == reply


def test_bad_lines_are_all_counted() -> None:
    b = MotorBoard()
    b.feed(b"X\nM 1\n", 0.0)
    assert b.errors == 2
    b.feed(b"M " + b"1" * 80 + b"\n", 0.0)
    assert b.errors == 3


def test_empty_lines_are_ignored_and_do_not_block_the_next_command() -> None:
    b = MotorBoard()
    assert b.feed(b"\nS #1\n", 0.0) == b"OK #1\n"
    assert b.feed(b"  \r\n\n", 0.0) == b""
    assert b.feed(b"P #2\n", 0.0) == b"OK #2\n"


def test_a_line_of_64_bytes_is_read_whole_or_in_pieces_and_65_is_too_long() -> None:
    line64 = b"M 10 -10" + b" " * 53 + b"#12"
    assert len(line64) == 64
    assert MotorBoard().feed(line64 + b"\n", 0.0) == b"OK #12\n"
    b = MotorBoard()
    assert b.feed(line64, 0.0) == b""
    assert b.feed(b"\n", 0.0) == b"OK #12\n"
    assert (b.left_pct, b.right_pct) == (10, -10)
    line65 = b"M 10 -10" + b" " * 54 + b"#12"
    assert MotorBoard().feed(line65 + b"\n", 0.0) == b"ERR overflow\n"


def test_an_overflow_keeps_the_replies_around_it() -> None:
    b = MotorBoard(watchdog_ms=100)
    b.feed(b"M 30 30\n", 0.0)
    out = b.feed(b"P #1\n" + b"x" * 70 + b"\nP #2\n", 1.0)
    assert out == b"EVT WATCHDOG\nOK #1\nERR overflow\nOK #2\n"


# -- wheel encoders (docs/motors.md, "Wheel encoders") ----------------------------------------
@pytest.mark.parametrize("delta", [0, 1, -1, 4300, -4300, 2**31 - 1, -(2**31)])
def test_count_differences_are_exact_integers(delta: int) -> None:
    # the counts are integers all the way: a float would round beyond 2**53 counts and
    # show as "8.0" in a record
    for start in (0, 5, ENC_MODULO - 3):
        got = wrap_count_delta((start + delta) % ENC_MODULO - start)
        assert got == delta and type(got) is int
    u = EncoderUnwrap()
    u.update(1, ENC_MODULO - 3, 10)
    left, right = u.update(2, 5, 2)
    assert (left, right) == (8, -8) and type(left) is int and type(right) is int


@pytest.mark.parametrize(
    ("payload", "parsed"),
    [("65535 4294967295 4294967295", (65535, ENC_MODULO - 1, ENC_MODULO - 1)),
     ("0 0 0", (0, 0, 0)),
     ("1 0 4294967296", None), ("1 4294967296 0", None), ("65536 0 0", None)],
)  # fmt: skip
def test_encoder_replies_at_the_limits_of_their_ranges(
    payload: str, parsed: tuple[int, int, int] | None
) -> None:
    assert parse_encoder_payload(payload) == parsed


def test_a_latch_number_up_to_1000_ahead_continues_and_beyond_restarts() -> None:
    u = EncoderUnwrap()
    u.update(10, 0, 0)
    assert u.update(1010, 100, 50) == (100, 50)  # 999 replies lost: the counts still add
    assert (u.skipped, u.restarts) == (999, 0)
    assert u.update(2011, 500, 500) == (100, 50)  # 1001 ahead: a restart, a new baseline
    assert (u.skipped, u.restarts) == (999, 1)
    # across the 16-bit wrap: 65000 -> 464 is 1000 ahead
    u = EncoderUnwrap()
    u.update(65000, 7, 7)
    assert u.update(464, 17, 2) == (10, -5) and (u.skipped, u.restarts) == (999, 0)


def test_lost_latches_and_restarts_are_counted_all_along() -> None:
    u = EncoderUnwrap()
    u.update(1, 0, 0)
    u.update(3, 10, 10)  # one lost
    u.update(6, 20, 20)  # two more
    assert u.skipped == 3 and u.update(7, 30, 30) == (30, 30) and u.skipped == 3
    u.update(7, 99, 99)  # the same latch number again: restarted
    u.update(1, 5, 5)  # and back to 1: restarted again
    u.update(0, 6, 6)  # and again (a step of 65535)
    assert u.restarts == 3 and u.update(1, 8, 9) == (32, 33)
    u.rebase()  # EVT BOOT: one more
    assert u.restarts == 4 and u.update(1, 0, 0) == (32, 33)


# -- the board on a pty (serve_board_fd) -----------------------------------------------------
def test_a_served_board_without_a_lock_or_boot_just_answers(pty: Pty) -> None:
    stop = threading.Event()
    t = serve(pty, MotorBoard(), stop)
    try:
        os.write(pty.slave, b"P #1\n")
        assert read_host(pty) == b"OK #1\n"  # and no EVT BOOT before it
    finally:
        stop.set()
        t.join(2)


def test_the_lock_is_held_while_the_board_changes(pty: Pty) -> None:
    stop, lock, board = threading.Event(), threading.Lock(), MotorBoard()
    t = serve(pty, board, stop, lock=lock)
    try:
        with lock:
            os.write(pty.slave, b"M 10 10 #1\n")
            assert read_host(pty, 0.2) == b""  # the board waits for the lock
            assert (board.left_pct, board.right_pct) == (0, 0)
        assert read_host(pty) == b"OK #1\n"
        assert (board.left_pct, board.right_pct) == (10, 10)
    finally:
        stop.set()
        t.join(2)


def test_a_served_board_reports_its_watchdog_promptly_to_a_silent_host(pty: Pty) -> None:
    stop = threading.Event()
    t = serve(pty, MotorBoard(), stop)
    try:
        t0 = time.monotonic()  # before the commands: the board's 50 ms run from after it
        os.write(pty.slave, b"W 50 #1\nM 10 10 #2\n")
        got = b""
        while got.count(b"\n") < 2:
            got += read_host(pty)
        assert read_host(pty, 3.0) == b"EVT WATCHDOG\n"
        # 50 ms period, polled every 5 ms: within 1 s however loaded the host (a board that
        # looks at its watchdog only when a line arrives never tells this silent host)
        assert time.monotonic() - t0 < 1.0
    finally:
        stop.set()
        t.join(2)


# -- the host link ---------------------------------------------------------------------------
def test_send_drives_and_stops_with_the_controllers_reason(pty_board: PtyBoard) -> None:
    with open_link(pty_board, watchdog_ms=2000) as link:
        assert link.send(MotorCommand(1.0, 30.0, -20.0, "TURN_RIGHT"))
        assert pty_board.state() == (30, -20)
        last = link.last_command
        assert last is not None and (last.left_pct, last.right_pct, last.reason) == (
            30.0, -20.0, "TURN_RIGHT"
        )  # fmt: skip
        assert link.send(MotorCommand(2.0, 0.0, 0.0, "hold: fix stale"))
        assert pty_board.state() == (0, 0)
        assert link.last_command is not None and link.last_command.reason == "hold: fix stale"


def test_last_command_says_what_was_sent_and_when(pty_board: PtyBoard) -> None:
    stamps: list[float] = []

    def clock() -> float:
        stamps.append(time.monotonic())
        return stamps[-1]

    port = serial.Serial(pty_board.name, baudrate=115200, timeout=0.02)
    link = SerialMotorLink(port, ack_timeout_s=0.5, clock=clock)
    assert link.last_command is None
    assert link.drive(10, 20)
    assert link.last_command == MotorCommand(link.last_command.t_s, 10.0, 20.0, "")
    assert link.last_command.t_s in stamps
    assert link.stop() and link.last_command.reason == "stop"
    assert link.stop("hold") and link.last_command.reason == "hold"
    link.close()
    assert link.last_command.reason == "close" and link.last_command.t_s in stamps
    h = link.health
    assert h.state == "disconnected" and h.since_t_s in stamps


def test_full_power_is_accepted_and_bad_values_name_the_side() -> None:
    link = LogMotorLink()
    assert link.drive(100, -100)
    assert link.send(MotorCommand(0.0, -100.0, 100.0, "spin"))
    for call in (link.drive, lambda a, b: link.send(MotorCommand(0.0, a, b))):
        with pytest.raises(ValueError, match=r"^left_pct must be within -100\.\.100 percent"):
            call(100.5, 0)
        with pytest.raises(ValueError, match=r"^right_pct must be within -100\.\.100 percent"):
            call(0, -101)
        with pytest.raises(ValueError, match=r"^right_pct must be a number in -100\.\.100"):
            call(0, True)


def test_a_link_to_a_pty_board_also_names_the_side(pty_board: PtyBoard) -> None:
    with open_link(pty_board) as link:
        with pytest.raises(ValueError, match=r"^left_pct must be within"):
            link.drive(101, 0)
        with pytest.raises(ValueError, match=r"^right_pct must be within"):
            link.drive(0, -101)
        assert link.drive(100, -100) and pty_board.state() == (100, -100)


def test_link_settings_are_checked() -> None:
    with pytest.raises(ValueError, match=r"^retries must be >= 0 and unhealthy_after >= 1$"):
        SerialMotorLink(None, retries=-1)
    with pytest.raises(ValueError, match=r"^retries must be >= 0 and unhealthy_after >= 1$"):
        SerialMotorLink(None, unhealthy_after=0)


def test_the_longest_watchdog_and_the_default_ack_timeout(pty_board: PtyBoard) -> None:
    port = serial.Serial(pty_board.name, baudrate=115200, timeout=0.02)
    with SerialMotorLink(port, watchdog_ms=60_000) as link:
        assert link.configured and pty_board.board.watchdog_ms == 60_000
        assert link.ack_timeout_s == 0.1  # docs/motors.md: default 0.1 s


def test_one_unconfirmed_command_is_enough_when_unhealthy_after_is_1(
    pty_board: PtyBoard,
) -> None:
    link = open_link(pty_board, ack_timeout_s=0.05, unhealthy_after=1)
    assert link.healthy
    pty_board.halt()
    assert not link.drive(10, 10)
    assert not link.healthy
    link.port.close()


def test_a_link_whose_watchdog_setting_went_unanswered_is_not_healthy(
    pty_board: PtyBoard,
) -> None:
    pty_board.halt()
    port = serial.Serial(pty_board.name, baudrate=115200, timeout=0.02)
    link = SerialMotorLink(port, ack_timeout_s=0.05, retries=0)
    assert not link.configured and not link.healthy  # at once, before any command
    pty_board.start()
    assert link.ping() and link.configured and link.healthy
    link.port.close()


def test_a_port_without_a_timeout_cannot_block_the_link(pty_board: PtyBoard) -> None:
    pty_board.halt()  # nothing will ever answer
    result: dict[str, Any] = {}

    def use() -> None:
        port = serial.Serial(pty_board.name, baudrate=115200, timeout=None)  # blocking reads
        link = SerialMotorLink(port, ack_timeout_s=0.1, retries=0)
        result["stop"] = link.stop()
        port.close()

    t = threading.Thread(target=use, daemon=True)
    t0 = time.monotonic()
    t.start()
    # a blocked read never returns: 10 s is a loaded host's slack for the port's opening
    # and one 0.1 s wait (2.1 s seen beside busy loops)
    t.join(10.0)
    assert not t.is_alive(), "the link blocked on a port without a timeout"
    assert result["stop"] is False and time.monotonic() - t0 < 10.0


def test_a_refusal_is_not_retried_and_counts_as_unconfirmed(pty: Pty) -> None:
    board = ScriptedBoard(pty)
    board.answer = limited_to_50(board.board)
    port = serial.Serial(pty.name, baudrate=115200, timeout=0.02)
    link = SerialMotorLink(port, ack_timeout_s=2.0, retries=1)
    try:
        t0 = time.monotonic()
        assert not link.drive(80, 80)
        # answered, not timed out: a refusal taken for no answer costs the 2 s ack timeout
        # (4 s with its retry); 1.5 s leaves the board thread a loaded host's slack
        assert time.monotonic() - t0 < 1.5
        assert [ln for ln in board.lines if ln.startswith(b"M")] == [b"M 80 80 #2"]  # once
        c = link.counters
        assert (c.rejected, c.timeouts, c.acked) == (1, 0, 1)  # the W was acknowledged
        h = link.health
        assert h.last_error == "M: board refused: range" and h.last_error_t_s is not None
        assert link.healthy  # one unconfirmed command (unhealthy_after 2)
        assert not link.drive(-60, 60)
        assert not link.healthy and link.counters.rejected == 2
        assert link.drive(40, 40) and link.healthy and board.board.left_pct == 40
    finally:
        board.halt()
        port.close()


def test_noise_on_the_line_is_skipped(pty_board: PtyBoard) -> None:
    with open_link(pty_board) as link:
        os.write(pty_board.master, b"\xff\xfe\x80 line noise\n\x00\x01\n")
        assert link.drive(10, 10)
        assert link.healthy and link.counters.write_errors == 0
        assert pty_board.state() == (10, 10)


@pytest.fixture
def slow_polling_board(pty: Pty) -> Iterator[MotorBoard]:
    """A board whose watchdog is looked at only when a line arrives: an expired watchdog
    and the reply to the late command go out in one write."""
    board, stop = MotorBoard(), threading.Event()
    t = serve(pty, board, stop, poll_s=60.0)
    yield board
    stop.set()
    os.write(pty.slave, b"\n")  # wake it
    t.join(2)


def test_the_reply_is_found_behind_an_event_in_the_same_read(
    pty: Pty, slow_polling_board: MotorBoard
) -> None:
    port = serial.Serial(pty.name, baudrate=115200, timeout=0.02)
    link = SerialMotorLink(port, ack_timeout_s=2.0, watchdog_ms=50)  # a late board thread
    try:
        for n, v in enumerate((30, 20, 10), start=0):
            assert link.drive(v, v), f"drive {v}"
            assert link.counters.events == n  # EVT WATCHDOG then OK, in one chunk
            time.sleep(0.1)
        assert slow_polling_board.watchdog_trips == 2
    finally:
        port.close()


class FailingClock:
    """time.monotonic until ``fail`` is set, then raises (a clock is an input like any)."""

    def __init__(self) -> None:
        self.fail = False

    def __call__(self) -> float:
        if self.fail:
            raise RuntimeError("clock broken")
        return time.monotonic()


def test_stop_never_raises_and_counts_every_failure(pty_board: PtyBoard) -> None:
    clock = FailingClock()
    port = serial.Serial(pty_board.name, baudrate=115200, timeout=0.02)
    link = SerialMotorLink(port, ack_timeout_s=0.5, clock=clock)
    assert link.drive(20, 20)
    clock.fail = True
    assert link.stop() is False
    assert link.stop("again") is False
    assert link.counters.stop_failures == 2
    clock.fail = False
    assert link.stop() is True and pty_board.state() == (0, 0)
    port.close()


def test_a_transient_error_during_stop_is_retried_and_named(pty_board: PtyBoard) -> None:
    port = FlakyPort(serial.Serial(pty_board.name, baudrate=115200, timeout=0.02))
    link = SerialMotorLink(port, ack_timeout_s=0.3, retries=1)
    try:
        assert link.drive(25, 25)
        port.code, port.fail = errno.EIO, 1
        t0 = time.monotonic()
        assert link.stop() is True and pty_board.state() == (0, 0)
        h = link.health
        assert h.last_error.startswith("S: port error: ") and t0 <= h.last_error_t_s
        port.code, port.fail = errno.EAGAIN, 1
        assert link.ping() is True
        assert link.health.last_error.startswith("P: port error: ")
    finally:
        link.close()


def test_health_of_a_dead_board_names_the_command_and_the_times(pty_board: PtyBoard) -> None:
    stamps: list[float] = []

    def clock() -> float:
        stamps.append(time.monotonic())
        return stamps[-1]

    port = serial.Serial(pty_board.name, baudrate=115200, timeout=0.02)
    link = SerialMotorLink(port, ack_timeout_s=0.1, clock=clock)
    assert link.drive(10, 10)
    link.take_health_events()
    pty_board.halt()
    assert not link.drive(20, 20)
    h = link.health
    assert h.state == "degraded" and h.since_t_s in stamps and h.last_error_t_s in stamps
    assert h.last_error == "M: no acknowledgement within 100 ms"
    assert not link.ping()
    h = link.health
    assert h.state == "disconnected" and h.since_t_s in stamps
    assert not link.stop()
    h = link.health
    assert h.state == "reconnecting" and h.since_t_s in stamps
    events = link.take_health_events()
    assert [(e.new, e.message) for e in events] == [
        ("degraded", "motors degraded: M: no acknowledgement within 100 ms"),
        ("disconnected", "motors disconnected: P: no acknowledgement within 100 ms"),
        ("reconnecting", "motors reconnecting: S: no acknowledgement within 100 ms"),
    ]
    assert all(e.t_s in stamps for e in events)
    port.close()


def test_a_link_created_without_an_answer_is_disconnected_since_its_creation(
    pty_board: PtyBoard,
) -> None:
    pty_board.halt()
    t0 = time.monotonic()
    port = serial.Serial(pty_board.name, baudrate=115200, timeout=0.02)
    link = SerialMotorLink(port, ack_timeout_s=0.05, retries=0)
    h = link.health
    assert h.state in ("disconnected", "reconnecting") and t0 <= h.since_t_s <= time.monotonic()
    port.close()


# -- the log link ----------------------------------------------------------------------------
def test_the_log_link_keeps_the_last_commands_and_records_stops_sent_as_commands() -> None:
    link = LogMotorLink(keep=3)
    for v in (10, 20, 30, 40):
        link.drive(v, v)
    assert [c.left_pct for c in link.commands] == [20.0, 30.0, 40.0]
    hold = MotorCommand(7.5, 0.0, 0.0, "hold: gps disconnected")
    assert link.send(hold) is True
    assert link.last_command == hold
    assert link.drive(5, 5, "x") and link.last_command.reason == "x"
    assert link.stop() and link.last_command.reason == "stop"
    assert link.drive(5, 5) and link.last_command.reason == ""


def test_a_log_link_stop_that_cannot_be_recorded_says_so_and_never_raises() -> None:
    def broken(_cmd: MotorCommand) -> None:
        raise OSError(errno.ENOSPC, "disk full")

    link = LogMotorLink(on_command=broken)
    assert link.stop() is False
    assert link.send(MotorCommand(1.0, 0.0, 0.0, "hold")) is False
    link.close()  # still no exception


def test_the_log_link_is_connected_until_closed_at_the_closing_stop() -> None:
    t = iter([2.0, 3.0, 4.0])
    link = LogMotorLink(clock=lambda: next(t))
    h = link.health
    assert (h.device, h.state, h.since_t_s) == ("motors", "connected", 0.0)
    link.drive(10, 10)  # 2.0
    link.drive(20, 20)  # 3.0
    link.close()  # the closing stop: 4.0
    h = link.health
    assert (h.state, h.since_t_s) == ("disconnected", 4.0)
    keeps_nothing = LogMotorLink(keep=0, clock=lambda: 9.0)
    keeps_nothing.close()  # no command kept to take the time from: its creation time, 0
    assert keeps_nothing.health.since_t_s == 0.0
