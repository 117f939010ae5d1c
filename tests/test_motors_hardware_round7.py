"""Round 7 review of the motor link on real hardware (/tmp/review5): saturated arcs one ulp
over 100 %, odometry after an unannounced board restart, a brown-out that resumed the last
drive, a USB node that vanished. The host side talks to the real MotorBoard emulator on a
real pty (serve_board_fd), as the review's scripts did; the daemon's own motor worker where
the effect reaches it."""

from __future__ import annotations

import contextlib
import math
import os
import random
import threading
import time
import tty
from collections.abc import Callable, Iterator

import pytest
import serial

from drivers.motors import MotorBoard, SerialMotorLink, _check_pct, serve_board_fd
from x6wd.nav.steering import skid_mix


def wait_for(cond: Callable[[], bool], limit_s: float = 5.0) -> bool:
    end = time.monotonic() + limit_s
    while time.monotonic() < end:
        if cond():
            return True
        time.sleep(0.005)
    return cond()


class Pty:
    """A MotorBoard served on a pty master (serve_board_fd); ``name`` is the slave."""

    def __init__(self, board: MotorBoard | None = None, *, boot: bool = False) -> None:
        self.board = board or MotorBoard()
        self.master, self.slave = os.openpty()
        tty.setraw(self.master)
        tty.setraw(self.slave)
        self.name = os.ttyname(self.slave)
        self.lock = threading.Lock()
        self.stop = threading.Event()
        self.thread = threading.Thread(
            target=serve_board_fd,
            args=(self.master, self.board, self.stop),
            kwargs={"lock": self.lock, "boot": boot},
            daemon=True,
        )
        self.thread.start()

    def state(self) -> tuple[int, int]:
        with self.lock:
            return self.board.left_pct, self.board.right_pct

    def halt(self) -> None:
        self.stop.set()
        self.thread.join(5)

    def close(self) -> None:
        self.halt()
        for fd in (self.master, self.slave):
            with contextlib.suppress(OSError):
                os.close(fd)


@pytest.fixture
def pty_board() -> Iterator[Pty]:
    pb = Pty()
    yield pb
    pb.close()


def open_port(name: str) -> serial.Serial:
    return serial.Serial(name, 115200, timeout=0.02)


# --- H2: a saturated arc is 1 ulp over 100 % -----------------------------------------------


def test_skid_mix_never_exceeds_100_percent() -> None:
    rng = random.Random(0)  # the review's sample (/tmp/review5/mix.py)
    saturated = 0
    for _ in range(20_000):
        kappa = rng.uniform(-0.6, 0.6)
        left, right = skid_mix(kappa, 60.0, 4.95)
        assert abs(left) <= 100.0 and abs(right) <= 100.0, (kappa, left, right)
        if abs(kappa) * 4.95 / 2 > 100.0 / 60.0 - 1:  # a side over 100 % before scaling
            saturated += 1
            assert max(abs(left), abs(right)) == 100.0, (kappa, left, right)  # exactly
            assert abs(_check_pct("left", left)) <= 100 and abs(_check_pct("right", right)) <= 100
    assert saturated > 1000


def test_check_pct_takes_a_float_ulp_over_the_limit_and_refuses_real_overs() -> None:
    over = math.nextafter(100.0, math.inf)
    assert _check_pct("l", over) == 100
    assert _check_pct("l", -over) == -100
    for bad in (100.5, -100.5, 101, math.nan, math.inf, -math.inf):
        with pytest.raises(ValueError, match=r"within -100\.\.100 percent"):
            _check_pct("l", bad)


@pytest.mark.integration
def test_a_saturated_arc_drives_the_board_through_the_daemons_worker(pty_board: Pty) -> None:
    from x6wd.app.daemon import _MotorWorker
    from x6wd.core.records import MotorCommand

    left, right = skid_mix(-0.3727, 60.0, 4.95)  # the controller's own numbers
    over = math.nextafter(100.0, math.inf)  # what the old skid_mix gave
    link = SerialMotorLink(open_port(pty_board.name), ack_timeout_s=0.5)
    w = _MotorWorker(link, 0.5 / 3, lambda ok, t: None)
    w.start()
    try:
        w.submit(MotorCommand(time.monotonic(), left, right, "STRAIGHT"))
        assert wait_for(lambda: pty_board.state() == (round(left), 100))
        w.submit(MotorCommand(time.monotonic(), 4.0, over, "STRAIGHT"))
        assert wait_for(lambda: pty_board.state() == (4, 100))
        time.sleep(0.2)  # the keep-alive repeats it: still driving, never "invalid command"
        assert pty_board.state() == (4, 100)
        assert link.last_command is not None and link.last_command.reason == "STRAIGHT"
    finally:
        w.shutdown("end")
