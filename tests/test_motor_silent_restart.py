"""A motor board that restarts without its ``EVT BOOT`` reaching the host (lost on the wire):
the restart shows only in the next encoder reading (latch number and counts from zero). The
board has forgotten the watchdog setting all the same, and a drive decided before the
restart must not start it: the link handles it as it handles an announced restart
(docs/motors.md, "Host behaviour"). Before, only the restart latch counted it: the link
stayed healthy and ``configured``, the next ``M`` drove the restarted board at once, on
the board's default 500 ms watchdog instead of the configured one.

The real MotorBoard emulator served on a real pty (:func:`drivers.motors.serve_board_fd`);
its ``boot()`` without writing the ``EVT BOOT`` it returns is the silent restart."""

from __future__ import annotations

import functools
import logging
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass

import pytest
import serial

from drivers.motors import DEFAULT_WATCHDOG_MS, MotorBoard, SerialMotorLink
from tests.test_motors import wait_for as motors_wait_for
from tests.test_motors_hardware_round7 import Pty
from x6wd.core.records import HealthEvent, MotorCommand

WATCHDOG_MS = 200
"""The link's watchdog (ms): shorter than the board's default, so losing it shows."""


class RecordingBoard(MotorBoard):
    """The emulator, recording each command line with the watchdog period (ms) the board
    had when it arrived."""

    def __init__(self) -> None:
        super().__init__()
        self.lines: list[tuple[str, int]] = []

    def _line(self, line: str, t_s: float) -> bytes:
        if line:
            self.lines.append((line.split("#")[0].strip(), self.watchdog_ms))
        return super()._line(line, t_s)


@dataclass
class Served:
    board: RecordingBoard
    lock: threading.Lock
    name: str  # the pty slave the link opens

    def state(self) -> tuple[int, int]:
        with self.lock:
            return self.board.left_pct, self.board.right_pct

    def silent_restart(self) -> int:
        """The board restarts (stopped, default watchdog, counters and latch at 0) and its
        ``EVT BOOT`` is lost; the wheels roll a little after. The index of the next line."""
        with self.lock:
            self.board.boot()  # the EVT BOOT it returns never reaches the host
            self.board.add_counts(12, 12)
            return len(self.board.lines)

    def lines_since(self, mark: int) -> list[tuple[str, int]]:
        with self.lock:
            return list(self.board.lines[mark:])


@pytest.fixture
def served() -> Iterator[Served]:
    board = RecordingBoard()
    pb = Pty(board, boot=True)
    yield Served(board, pb.lock, pb.name)
    pb.close()


wait_for = functools.partial(motors_wait_for, limit_s=10.0)


def mission(left: float = 40.0, right: float = 40.0) -> MotorCommand:
    return MotorCommand(time.monotonic(), left, right, "mission")


def running_link(sv: Served) -> SerialMotorLink:
    """A link that is up, has an odometry baseline and has driven the board."""
    port = serial.Serial(sv.name, 115200, timeout=0.02)
    link = SerialMotorLink(port, ack_timeout_s=0.5, watchdog_ms=WATCHDOG_MS)
    assert link.configured and sv.board.watchdog_ms == WATCHDOG_MS
    assert link.read_odometry() is not None
    with sv.lock:
        sv.board.add_counts(500, 500)
    assert link.read_odometry() is not None and link.encoders.verdict == "continued"
    assert link.send(mission()) and sv.state() == (40, 40)
    return link


def detect_silent_restart(sv: Served, link: SerialMotorLink) -> int:
    """Restart the board silently and let the link's next encoder reading see it; the index
    of the first line after the restart (the detecting ``E``)."""
    mark = sv.silent_restart()
    assert sv.board.watchdog_ms == DEFAULT_WATCHDOG_MS and sv.state() == (0, 0)
    odo = link.read_odometry()
    assert odo is not None and link.encoders.verdict == "restart"
    return mark


@pytest.mark.integration
def test_the_watchdog_setting_goes_out_before_the_next_command(served: Served) -> None:
    link = running_link(served)
    try:
        mark = detect_silent_restart(served, link)
        assert link.ping()
        # on the wire: the detecting E, then W before the ping, which finds the board set
        assert served.lines_since(mark) == [
            ("E", DEFAULT_WATCHDOG_MS),
            (f"W {WATCHDOG_MS}", DEFAULT_WATCHDOG_MS),
            ("P", WATCHDOG_MS),
        ]
        assert served.board.watchdog_ms == WATCHDOG_MS and link.configured
    finally:
        link.close()


@pytest.mark.integration
def test_a_drive_after_the_detected_restart_is_held_until_a_confirmed_stop(
    served: Served,
) -> None:
    link = running_link(served)
    try:
        mark = detect_silent_restart(served, link)
        # the keep-alive's repeat of the drive from before: refused, an S instead
        assert not link.send(mission())
        assert not link.send(mission())
        assert served.state() == (0, 0) and link.counters.held_drives == 2
        assert [w for w, _ in served.lines_since(mark)] == ["E", "S", "S"]
        # the controller, told the link is lost, stops; drives go again, set up first
        assert link.stop("hold: motor link lost") and link.healthy
        assert link.send(mission(30.0, 30.0)) and served.state() == (30, 30)
        assert served.lines_since(mark)[-2:] == [
            (f"W {WATCHDOG_MS}", DEFAULT_WATCHDOG_MS),
            ("M 30 30", WATCHDOG_MS),
        ]
    finally:
        link.close()


@pytest.mark.integration
def test_the_detected_restart_is_a_lost_link_in_health_counters_and_log(
    served: Served, caplog: pytest.LogCaptureFixture
) -> None:
    link = running_link(served)
    try:
        link.take_health_events()
        with caplog.at_level(logging.WARNING, logger="drivers.motors"):
            detect_silent_restart(served, link)
        assert not link.healthy
        health = link.health
        assert health.state == "disconnected"
        assert "restarted" in health.reason and "encoder reading" in health.reason
        lost = [e for e in link.take_health_events() if e.new == "disconnected"]
        assert len(lost) == 1 and "encoder reading" in lost[0].message
        assert link.counters.board_restarts == 1  # counted as EVT BOOT's are
        warned = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
        assert len(warned) == 1 and "without EVT BOOT" in warned[0], warned
        assert "seen in the encoder reading" in warned[0]
        assert link.stop("hold: motor link lost") and link.healthy
        assert link.health.state == "connected" and link.health.reconnects == 1
    finally:
        link.close()


@pytest.mark.integration
def test_each_detected_restart_counts_once_and_the_third_latches(served: Served) -> None:
    link = running_link(served)
    try:
        for n in (1, 2, 3):
            detect_silent_restart(served, link)
            assert not link.healthy and link.counters.board_restarts == n
            assert link.counters.restart_faults == (1 if n == 3 else 0)
            stopped = link.stop("hold: motor link lost")
            assert stopped and link.healthy is (n < 3)
        assert "restarted 3 times" in link.health.reason
        assert not link.send(mission()) and served.state() == (0, 0)
        link.clear_restart_fault()  # the operator stops
        assert link.stop("operator stop") and link.healthy
    finally:
        link.close()


@pytest.mark.integration
def test_the_daemons_motor_worker_holds_the_mission_after_a_silent_restart(
    served: Served,
) -> None:
    """The daemon's motor thread polls the encoders at 20 Hz while a 20 Hz controller drives
    (holding while told the link is lost). Drives written before the next reading reach the
    restarted board (nothing tells the host sooner); from the reading that shows the restart
    on, the board gets only stops until the controller was told and stopped, and its next
    drive finds the watchdog set first."""
    from x6wd.app.daemon import _MotorWorker

    port = serial.Serial(served.name, 115200, timeout=0.02)
    link = SerialMotorLink(port, ack_timeout_s=0.5, watchdog_ms=WATCHDOG_MS)
    health: list[bool] = []
    events: list[HealthEvent] = []
    told_ok = [True]
    readings: list[object] = []

    def on_health(ok: bool, t_s: float) -> None:
        health.append(ok)
        told_ok[0] = ok

    w = _MotorWorker(link, WATCHDOG_MS / 1000 / 3, on_health, events.extend, readings.append)
    done = threading.Event()

    def controller() -> None:
        while not done.is_set():
            if told_ok[0]:
                w.submit(mission(60.0, 60.0))
            else:
                w.submit(MotorCommand(time.monotonic(), 0.0, 0.0, "hold: motor link lost"))
            time.sleep(0.05)

    ctl = threading.Thread(target=controller, daemon=True)
    w.start()
    ctl.start()
    try:
        assert wait_for(lambda: served.state() == (60, 60) and len(readings) >= 2)
        mark = served.silent_restart()
        # told lost, then up again after its stop, and driving again
        assert wait_for(lambda: False in health), f"never told: health callbacks {health}"
        assert wait_for(lambda: True in health[health.index(False) :])
        assert wait_for(lambda: served.state() == (60, 60))
        lines = served.lines_since(mark)
        words = [w for w, _ in lines]
        seen = words.index("E")  # the first reading after the restart shows it
        up = words.index(f"W {WATCHDOG_MS}", seen)
        between = words[seen + 1 : up]
        assert "S" in between and not any(w.startswith("M") for w in between), words
        assert words[up + 1] == "M 60 60" and lines[up + 1][1] == WATCHDOG_MS, lines
        lost = [e for e in events if e.new == "disconnected"]
        assert lost and "encoder reading" in lost[0].message
    finally:
        done.set()
        ctl.join(5)
        w.shutdown("end")
