"""A motor board that refuses the watchdog setting (``W``), and one that refuses commands
over and over (an outside audit, round 21): before, a firmware answering ``W 500`` with
``ERR range`` was sent every drive all the same, the acknowledged stop between them made
the link healthy again, and the mission flapped between HOLD and driving at the tick rate
with ``status`` saying ``motors ok``; each refusal was one WARNING line (700 a second).

Real pty, the host's real :class:`SerialMotorLink`, a scripted board (the real
:class:`MotorBoard` behind it for the lines it takes)."""

from __future__ import annotations

import logging
import time
from collections.abc import Callable

import pytest
import serial

from drivers.motors import W_RETRY_S, SerialMotorLink
from tests.test_safety_motors import Pty, ScriptedBoard, pty
from x6wd.core.records import MotorCommand

__all__ = ["pty"]  # the fixture


def refusing(board: ScriptedBoard, kinds: set[str]) -> Callable[[bytes], bytes]:
    """Firmware that answers the command kinds ``kinds`` with ``ERR #N range`` while the
    set holds them, the rest as the real board does."""

    def answer(line: bytes) -> bytes:
        tokens = line.decode().split()
        if tokens and tokens[0] in kinds:
            return f"ERR {tokens[-1]} range\n".encode()
        return board.board.feed(line + b"\n", time.monotonic())

    return answer


class Clock:
    """The link's clock (s), moved by hand: the retry's wait without sleeping."""

    def __init__(self) -> None:
        self.t_s = 1000.0

    def __call__(self) -> float:
        return self.t_s


def sent(board: ScriptedBoard, kind: bytes) -> int:
    return sum(1 for ln in board.lines if ln.split()[:1] == [kind])


def test_a_refused_watchdog_setting_keeps_the_link_lost_and_no_drive_goes_out(
    pty: Pty, caplog: pytest.LogCaptureFixture
) -> None:
    board = ScriptedBoard(pty)
    kinds = {"W"}
    board.answer = refusing(board, kinds)
    port = serial.Serial(pty.name, baudrate=115200, timeout=0.02)
    clock = Clock()
    caplog.set_level(logging.WARNING, logger="drivers.motors")
    link = SerialMotorLink(port, ack_timeout_s=2.0, retries=1, clock=clock)
    try:
        assert not link.configured and not link.healthy
        h = link.health
        assert not h.connected and "W 500: board refused: range" in h.reason
        for k in range(30):  # 1.5 s of the controller's drives and the keep-alive's stops
            clock.t_s += 0.05
            assert not link.send(MotorCommand(clock.t_s, 50.0, 60.0, "drive"))
            assert link.stop("keepalive")  # the board takes S: it answers
            assert not link.ping()
            assert not link.healthy, k
        assert sent(board, b"M") == sent(board, b"P") == 0
        assert board.board.left_pct == board.board.right_pct == 0
        assert not link.health.connected and "board refused" in link.health.reason
        # asked again after its wait (1 s, then 2 s), not at every command
        assert sent(board, b"W") == 2
        errors = [r for r in caplog.records if r.levelno >= logging.ERROR]
        assert len(errors) == 1 and "watchdog_ms" in errors[0].getMessage()
        # the firmware takes it now: the next confirmed stop after the wait asks again
        kinds.clear()
        clock.t_s += 2.0 * W_RETRY_S + 0.1
        assert link.stop("keepalive")
        assert link.configured and link.healthy and link.health.connected
        assert board.board.watchdog_ms == 500
        assert link.send(MotorCommand(clock.t_s, 50.0, 60.0, "drive"))
        assert (board.board.left_pct, board.board.right_pct) == (50, 60)
    finally:
        board.halt()
        port.close()


def test_refusals_repeated_at_the_command_rate_are_logged_a_few_times_and_all_counted(
    pty: Pty, caplog: pytest.LogCaptureFixture
) -> None:
    board = ScriptedBoard(pty)
    board.answer = refusing(board, {"S"})
    port = serial.Serial(pty.name, baudrate=115200, timeout=0.02)
    caplog.set_level(logging.WARNING, logger="drivers.motors")
    link = SerialMotorLink(port, ack_timeout_s=2.0, retries=1)
    try:
        for _ in range(120):
            assert not link.stop("keepalive")
        assert link.counters.rejected == 120
        assert link.health.last_error == "S: board refused: range"
        refused = [r.getMessage() for r in caplog.records if "rejected 'S'" in r.getMessage()]
        assert len(refused) == 3  # the 1st, 10th and 100th
        assert refused[-1].endswith("(100 of its kind so far)")
    finally:
        board.halt()
        port.close()
