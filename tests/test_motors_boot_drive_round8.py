"""A drive that crosses the motor board's restart: the restarted board says ``EVT BOOT``,
then obeys and acknowledges the drive (the host wrote it before it could know). The link
must stop it with the very next line it writes, not after re-sending the watchdog setting:
under load that extra round trip let a browning-out board run long enough to sag again
(audit 10d: test_motors_hardware_round7's SaggingBoard restarted a 4th time).

A real pty served by :func:`drivers.motors.serve_board_fd` with the repo's MotorBoard."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator

import pytest
import serial

from drivers.motors import MotorBoard, SerialMotorLink
from tests.test_motors_hardware_round7 import Pty
from x6wd.core.records import MotorCommand


class RestartOnDriveBoard(MotorBoard):
    """Restarts as the next ``M`` arrives once armed (``EVT BOOT`` first, then it takes the
    ``M``), and records what it is told afterwards: (command word, driving when it came)."""

    armed = False
    after_restart: list[tuple[str, bool]] | None = None

    def feed(self, data: bytes, t_s: float) -> bytes:
        if self.armed and b"M " in data:
            self.armed = False
            self.after_restart = []
            return self.boot() + super().feed(data, t_s)
        return super().feed(data, t_s)

    def _line(self, line: str, t_s: float) -> bytes:
        if self.after_restart is not None and line.strip():
            self.after_restart.append((line.split()[0], self.running))
        return super()._line(line, t_s)


@pytest.fixture
def served() -> Iterator[tuple[RestartOnDriveBoard, threading.Lock, str]]:
    board = RestartOnDriveBoard()
    pb = Pty(board, boot=True)
    yield board, pb.lock, pb.name
    pb.close()


@pytest.mark.integration
def test_a_drive_acknowledged_by_the_restarted_board_is_stopped_by_the_next_line(
    served: tuple[RestartOnDriveBoard, threading.Lock, str],
) -> None:
    board, lock, name = served
    link = SerialMotorLink(serial.Serial(name, 115200, timeout=0.02), ack_timeout_s=0.5)
    try:
        assert link.send(MotorCommand(time.monotonic(), 60.0, 60.0, "mission"))
        board.armed = True  # the keep-alive's resend meets a board that has just restarted
        assert not link.send(MotorCommand(time.monotonic(), 60.0, 60.0, "mission"))
        with lock:
            told = list(board.after_restart or [])
            state = (board.left_pct, board.right_pct)
        # the restarted board obeyed the M (it was driving when the next line came) and
        # that next line is the stop: nothing else while it drives
        assert told[:2] == [("M", False), ("S", True)], told
        assert state == (0, 0)
        assert not link.healthy and link.counters.board_restarts == 1
        assert link.counters.held_drives == 1
        # held: the next drive is refused (an S instead) until the caller's own stop
        assert not link.send(MotorCommand(time.monotonic(), 60.0, 60.0, "mission"))
        assert link.stop("hold") and link.healthy
        # the watchdog setting the restart lost goes out before the next drive
        assert link.send(MotorCommand(time.monotonic(), 30.0, 30.0, "mission"))
        with lock:
            words = [w for w, _ in board.after_restart or []]
            state = (board.left_pct, board.right_pct)
        assert words[-2:] == ["W", "M"] and state == (30, 30), words
        assert link.configured
    finally:
        link.close()
