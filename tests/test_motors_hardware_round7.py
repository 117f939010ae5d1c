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
import re
import threading
import time
import tty
from collections.abc import Iterator
from pathlib import Path

import pytest
import serial

from drivers.motors import MotorBoard, SerialMotorLink, _check_pct, serve_board_fd
from tests.test_motors import wait_for
from x6wd.nav.steering import skid_mix


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


# --- H1: odometry after an unannounced board restart ---------------------------------------


@pytest.mark.integration
def test_a_restart_whose_evt_boot_was_lost_does_not_jump_the_odometry(
    pty_board: Pty, caplog: pytest.LogCaptureFixture
) -> None:
    # up ~54 min at 20 Hz: the latch number near its wrap, ~1 km driven (review5 enc_wrap.py)
    with pty_board.lock:
        pty_board.board.enc_seq = 65000
        pty_board.board.add_counts(4_300_000, 4_300_000)
    link = SerialMotorLink(open_port(pty_board.name), ack_timeout_s=0.5)
    try:
        first = link.read_odometry()
        assert first is not None and (first.left_counts, first.right_counts) == (0, 0)
        with pty_board.lock:
            pty_board.board.add_counts(43, 43)
        odo = link.read_odometry()
        assert odo is not None and odo.left_counts == 43
        with pty_board.lock:  # a brown-out whose EVT BOOT never reached the host
            pty_board.board.boot()
            pty_board.board.add_counts(43, 43)
        with caplog.at_level("WARNING", logger="drivers.motors"):
            after = link.read_odometry()
            assert after is not None
            # the latch number went 65001 -> 1, a step of 536: only the distance tells
            assert (after.left_counts, after.right_counts) == (43, 43)  # was -4299957
            assert link.encoders.restarts == 1
            with pty_board.lock:
                pty_board.board.add_counts(10, 10)
            again = link.read_odometry()
            assert again is not None and (again.left_counts, again.right_counts) == (53, 53)
        jumps = [r.getMessage() for r in caplog.records if "encoder" in r.getMessage()]
        assert len(jumps) == 1 and "restart" in jumps[0], jumps
        assert "encoder" in link.health.last_error  # status shows it
        # the restarted board lost its settings (watchdog): a lost link until a stop, as
        # after EVT BOOT (tests/test_motor_silent_restart.py)
        assert not link.healthy
    finally:
        link.close()


@pytest.mark.integration
def test_the_odometry_starts_a_new_baseline_when_the_port_reopens() -> None:
    # a native-USB board: its EVT BOOT goes out before the host has the port open again
    # (review5 enc_reopen.py); a lifetime short enough that no distance bound can see it
    board = MotorBoard()
    board.boot()
    board.enc_seq = 65000
    board.add_counts(2000, 2000)
    pb = Pty(board)
    pb2: list[Pty] = []
    link = SerialMotorLink(
        open_port(pb.name),
        ack_timeout_s=0.2,
        reopen=lambda: open_port(pb2[0].name),
        reopen_initial_s=0.01,
    )
    try:
        assert link.read_odometry() is not None
        with pb.lock:
            board.add_counts(430, 430)
        odo = link.read_odometry()
        assert odo is not None and odo.left_counts == 430
        pb.close()  # USB gone: the port dies (EIO), the board restarts and re-enumerates
        board.boot()
        board.add_counts(43, 43)
        pb2.append(Pty(board))
        assert wait_for(
            lambda: (link.ping() or True) and link.counters.reopens > 0 and link.healthy
        )
        after = link.read_odometry()
        assert after is not None
        assert (after.left_counts, after.right_counts) == (430, 430)  # not 430 + 43 - 2473
        assert link.encoders.restarts == 1
    finally:
        link.close()
        pb.close()
        for p in pb2:
            p.close()


@pytest.mark.integration
def test_a_reopen_keeps_the_odometry_when_the_board_did_not_restart() -> None:
    # review6 6: every reopen started a new baseline, so a link that dropped (ser2net's TCP
    # connection, a flaky adapter) while the board ran on lost the counts of the outage.
    # Now the reading after the reopen continues when its latch number continues and its
    # counts fit the bound over the outage; the board moved 2 m meanwhile
    board = MotorBoard()
    board.boot()
    board.enc_seq = 65000
    board.add_counts(2000, 2000)
    pb = Pty(board)
    pb2: list[Pty] = []
    link = SerialMotorLink(
        open_port(pb.name),
        ack_timeout_s=0.2,
        reopen=lambda: open_port(pb2[0].name),
        reopen_initial_s=0.01,
        max_counts_per_s=SHIPPED_BOUND,
    )
    try:
        assert link.read_odometry() is not None
        with pb.lock:
            board.add_counts(430, 430)
        odo = link.read_odometry()
        assert odo is not None and odo.left_counts == 430
        pb.close()  # the link drops; the board runs on (no restart) and the robot rolls
        board.add_counts(8658, 8650)  # 0.51 s at 3.888 m/s: the outage lasts 0.6 s
        assert not link.ping()
        time.sleep(0.6)
        pb2.append(Pty(board))
        assert wait_for(
            lambda: (link.ping() or True) and link.counters.reopens > 0 and link.healthy
        )
        after = link.read_odometry()
        assert after is not None
        assert (after.left_counts, after.right_counts) == (430 + 8658, 430 + 8650)  # was 430
        assert link.encoders.restarts == 0
        assert link.health.state == "connected"
    finally:
        link.close()
        pb.close()
        for p in pb2:
            p.close()


# --- M3: a brown-out is a lost link; the last drive is not sent again -------------------------


class BrownoutBoard(MotorBoard):
    """A board that browns out as the next ``M`` arrives (once armed): it restarts, says
    ``EVT BOOT``, then takes the ``M`` (the host wrote it before it could know)."""

    armed = False

    def feed(self, data: bytes, t_s: float) -> bytes:
        if self.armed and b"M " in data:
            self.armed = False
            return self.boot() + super().feed(data, t_s)
        return super().feed(data, t_s)


@pytest.mark.integration
def test_after_a_brown_out_the_worker_reports_a_lost_link_and_does_not_resume(
    caplog: pytest.LogCaptureFixture,
) -> None:
    # review5 boot_resume.py: the board drove 80/80 again 0.040 s after its EVT BOOT, with
    # the link healthy and no health callback: the keep-alive had re-sent the last drive
    from x6wd.app.daemon import _MotorWorker
    from x6wd.core.records import HealthEvent, MotorCommand

    pb = Pty(boot=True)
    link = SerialMotorLink(open_port(pb.name), ack_timeout_s=0.5)
    health: list[bool] = []
    events: list[HealthEvent] = []
    told_ok = [True]

    def on_health(ok: bool, t_s: float) -> None:
        health.append(ok)
        told_ok[0] = ok

    w = _MotorWorker(link, 0.5 / 3, on_health, events.extend)
    done = threading.Event()

    def controller() -> None:  # the daemon's: a command at 20 Hz; holds while told lost
        while not done.is_set():
            if told_ok[0]:
                w.submit(MotorCommand(time.monotonic(), 80.0, 80.0, "mission"))
            else:
                w.submit(MotorCommand(time.monotonic(), 0.0, 0.0, "hold: motor link lost"))
            time.sleep(0.05)

    ctl = threading.Thread(target=controller, daemon=True)
    w.start()
    ctl.start()
    try:
        assert wait_for(lambda: pb.state() == (80, 80))
        with caplog.at_level("WARNING", logger="drivers.motors"):
            with pb.lock:
                hello = pb.board.boot()  # brown-out: the board restarts stopped
            os.write(pb.master, hello)
            end = time.monotonic() + 3.0
            while time.monotonic() < end:
                board = pb.state()  # before the health: the resumed drive follows a True
                if False in health and health[health.index(False) :].count(True):
                    break  # told lost, stopped, told up again: the controller resumed
                assert board == (0, 0), f"driving again after the reboot, health {health}"
                time.sleep(0.002)
            else:
                pytest.fail(f"the controller was never told: health callbacks {health}")
        assert link.counters.board_restarts == 1 and link.counters.held_drives >= 1
        assert any("EVT BOOT" in r.getMessage() for r in caplog.records)
        lost = [e for e in events if e.new == "disconnected"]
        assert lost and "EVT BOOT" in lost[0].message
        assert link.health.reconnects == 1
        assert wait_for(lambda: pb.state() == (80, 80))  # the controller's own new drive
    finally:
        done.set()
        ctl.join(5)
        w.shutdown("end")
        pb.close()


@pytest.mark.integration
def test_a_drive_the_board_took_just_after_restarting_is_stopped_at_once() -> None:
    from x6wd.core.records import MotorCommand

    board = BrownoutBoard()
    pb = Pty(board, boot=True)
    link = SerialMotorLink(open_port(pb.name), ack_timeout_s=0.5)
    try:
        assert link.send(MotorCommand(time.monotonic(), 40.0, 40.0, "mission"))
        board.armed = True  # the next M meets a board that has just restarted
        assert not link.send(MotorCommand(time.monotonic(), 40.0, 40.0, "mission"))
        assert pb.state() == (0, 0)  # the S followed at once
        assert not link.healthy and link.counters.board_restarts == 1
        assert not link.send(MotorCommand(time.monotonic(), 40.0, 40.0, "mission"))
        assert pb.state() == (0, 0)
        assert link.stop("hold") and link.healthy
        assert link.send(MotorCommand(time.monotonic(), 30.0, 30.0, "mission"))
        assert pb.state() == (30, 30)
    finally:
        link.close()
        pb.close()


# --- M4: a USB serial node that vanished or was replaced ------------------------------------


class ClosingPort(serial.Serial):
    """pyserial's port, noting when the link closes it."""

    closed_at: float | None = None

    def close(self) -> None:
        if self.closed_at is None:
            self.closed_at = time.monotonic()
        super().close()


@pytest.mark.integration
def test_an_unplugged_adapter_is_a_broken_port_at_the_first_error() -> None:
    # review5 unplug.py: the dead fd was held 0.548 s (EIO counted as transient), keeping
    # the tty minor, so a re-plugged adapter came back under another name
    pb = Pty()
    port = ClosingPort(pb.name, 115200, timeout=0.02)
    opens: list[float] = []

    def reopen() -> serial.Serial:
        opens.append(time.monotonic())
        raise OSError(2, f"No such file or directory: {pb.name}")

    link = SerialMotorLink(port, ack_timeout_s=0.2, reopen=reopen)
    try:
        assert link.drive(50, 50)
        pb.close()  # the far end and the node are gone
        assert not os.path.exists(pb.name)
        assert not link.drive(50, 50)  # the first command after the unplug
        assert port.closed_at is not None, "the dead port is still held open"
        assert not link.healthy
        assert "gone" in link.health.last_error, link.health.last_error
    finally:
        link.close()


@pytest.mark.integration
def test_a_by_id_path_that_now_names_another_node_is_reopened_at_once(tmp_path: Path) -> None:
    by_id = tmp_path / "usb-x6wd-motor-board-if00"  # as /dev/serial/by-id/... is
    first = Pty()
    by_id.symlink_to(first.name)
    port = ClosingPort(str(by_id), 115200, timeout=0.02)
    second: list[Pty] = []
    link = SerialMotorLink(
        port,
        ack_timeout_s=0.2,
        reopen=lambda: serial.Serial(str(by_id), 115200, timeout=0.02),
        reopen_initial_s=0.01,
    )
    try:
        assert link.drive(20, 20)
        # re-enumerated: the old node hangs up, the link names the new one (another minor)
        second.append(Pty())
        by_id.unlink()
        by_id.symlink_to(second[0].name)
        first.halt()
        os.close(first.master)
        assert not link.drive(20, 20)
        assert port.closed_at is not None
        assert "replaced" in link.health.last_error or "gone" in link.health.last_error
        assert wait_for(lambda: link.drive(30, 30))
        assert second[0].state() == (30, 30) and link.counters.reopens == 1
    finally:
        link.close()
        with contextlib.suppress(OSError):
            os.close(first.slave)
        for p in second:
            p.close()


def test_the_daemon_bounds_the_encoders_by_its_own_robot(tmp_path: Path) -> None:
    """The distance bound that tells a board restart from motion comes from the robot's
    configuration ([odometry], [navigation] full_speed_mps), not the generic default: a
    small robot's restart whose counts look like a plausible step for the default (200,000
    counts/s) is one for this robot."""
    import dataclasses

    from drivers.motors import encoder_rate_bound
    from tests.test_daemon import Running, hil_config, wait_for
    from tests.test_shutdown import TcpMotorBoard
    from x6wd.app.daemon import Daemon

    board = TcpMotorBoard()
    cfg = hil_config(tmp_path)
    cfg = dataclasses.replace(
        cfg,
        motors=dataclasses.replace(cfg.motors, url=f"tcp://127.0.0.1:{board.port}?watchdog_ms=500"),
        odometry=dataclasses.replace(
            cfg.odometry, counts_per_rev=1000, left_diameter_m=0.1, right_diameter_m=0.12
        ),
        navigation=dataclasses.replace(cfg.navigation, full_speed_mps=2.0),
    )
    r = Running(Daemon(cfg))
    try:
        wait_for(lambda: r.daemon.motors is not None, 10, "the motor link")
        link = r.daemon.motors.link  # type: ignore[union-attr]
        want = encoder_rate_bound(1000, 0.1, 2.0)
        assert want == pytest.approx(1000 / (math.pi * 0.1) * 2.0 * 4.0)
        assert link.encoders.max_counts_per_s == pytest.approx(want)
    finally:
        r.stop()
        if r.daemon.devices is not None:
            r.daemon.devices.close()
        board.close()


# --- review6 4: a host pause is not a board restart; a restart with a small lifetime is -------

SHIPPED_BOUND = 67_325.0  # encoder_rate_bound(1632, 0.120, 3.888): the daemon's, shipped config
FULL_SPEED_CPS = 1632 / (math.pi * 0.120) * 3.888  # 16,831 counts/s at 3.888 m/s


class StallingPort(serial.Serial):
    """pyserial's port whose reader is held up (the motor thread descheduled, a GC pause)
    right after it took an encoder reply off the line, when ``stall_s`` is set: the board
    latched before the pause, the host stamps the reply after it."""

    stall_s = 0.0
    _seen = b""

    def read(self, size: int = 1) -> bytes:
        data = super().read(size)
        self._seen = (self._seen + data)[-64:]  # the link may read a byte at a time
        if self.stall_s and re.search(rb"OK #\d+ \d+ \d+ \d+\n$", self._seen):
            time.sleep(self.stall_s)
            self.stall_s = 0.0
        return data


class Wheels:
    """Turns the board's encoders at ``cps`` counts/s on both sides, in its own thread."""

    def __init__(self, pb: Pty, cps: float) -> None:
        self.pb, self.cps = pb, cps
        self.done = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self) -> None:
        t0, added = time.monotonic(), 0
        while not self.done.is_set():
            due = int(self.cps * (time.monotonic() - t0))
            with self.pb.lock:
                self.pb.board.add_counts(due - added, due - added)
            added = due
            time.sleep(0.002)

    def stop(self) -> None:
        self.done.set()
        self.thread.join(5)


def _board_counts(pb: Pty) -> int:
    with pb.lock:
        return pb.board.left_counts


@pytest.mark.integration
@pytest.mark.parametrize(("speed", "stall_s"), [(1.0, 0.5), (2.0 / 3.888, 0.7)])
def test_a_host_pause_after_a_reply_at_full_speed_keeps_every_count(
    speed: float, stall_s: float
) -> None:
    # review6 enc_stall.py: the bound was applied to the time between replies on the host;
    # a pause after one reply sent the next poll at once while the board had counted all
    # through it: >= 0.25 s at 3.888 m/s (0.5 s at 2 m/s) read as a board restart and
    # dropped 4,342-16,965 counts (1-4 m), health degraded, "board restart" logged
    board = MotorBoard()
    board.boot()
    board.enc_seq = 30_000
    board.add_counts(1_000_000, 1_000_000)
    pb = Pty(board)
    port = StallingPort(pb.name, 115200, timeout=0.02)
    link = SerialMotorLink(port, ack_timeout_s=0.5, max_counts_per_s=SHIPPED_BOUND)
    wheels: Wheels | None = None
    try:
        first = link.read_odometry()
        assert first is not None
        c0 = _board_counts(pb)
        wheels = Wheels(pb, FULL_SPEED_CPS * speed)
        for _ in range(3):  # the worker's 20 Hz
            time.sleep(0.05)
            assert link.read_odometry() is not None
        port.stall_s = stall_s
        assert link.read_odometry() is not None  # stamped stall_s after the board latched
        assert link.read_odometry() is not None  # the next poll at once: no wait
        time.sleep(0.05)
        assert link.read_odometry() is not None
        wheels.stop()
        last = link.read_odometry()
        assert last is not None
        assert link.encoders.restarts == 0 and link.encoders.jumps == 0
        assert last.left_counts == _board_counts(pb) - c0  # every count, none dropped
        assert "encoder" not in link.health.last_error
    finally:
        if wheels is not None:
            wheels.stop()
        link.close()
        pb.close()


@pytest.mark.integration
def test_full_speed_with_jittery_polls_is_never_a_restart() -> None:
    # the daemon's 20 Hz polls late and early (a loaded host), replies read in pieces and
    # stamped late by up to 0.3 s, the wheels at full speed: every count arrives
    rng = random.Random(6)
    pb = Pty(MotorBoard())
    port = StallingPort(pb.name, 115200, timeout=0.02)
    link = SerialMotorLink(port, ack_timeout_s=0.5, max_counts_per_s=SHIPPED_BOUND)
    wheels: Wheels | None = None
    try:
        assert link.read_odometry() is not None
        c0 = _board_counts(pb)
        wheels = Wheels(pb, FULL_SPEED_CPS)
        for _ in range(40):
            if rng.random() < 0.3:
                port.stall_s = rng.uniform(0.0, 0.3)
            assert link.read_odometry() is not None
            time.sleep(rng.choice([0.0, 0.0, rng.uniform(0.0, 0.09)]))
        wheels.stop()
        last = link.read_odometry()
        assert last is not None
        assert link.encoders.restarts == 0, link.encoders.verdict
        assert last.left_counts == last.right_counts == _board_counts(pb) - c0
    finally:
        if wheels is not None:
            wheels.stop()
        link.close()
        pb.close()


@pytest.mark.integration
def test_an_unannounced_restart_of_a_board_that_stood_still_is_a_restart(
    pty_board: Pty, caplog: pytest.LogCaptureFixture
) -> None:
    # review6: up ~54 min at 20 Hz standing (the latch number near its wrap, counts near
    # zero), then a brown-out whose EVT BOOT was lost: latch 65001 -> 1 is a step of 536
    # and 2043 -> 43 counts is within the distance bound, so odometry went 2000 back
    with pty_board.lock:
        pty_board.board.enc_seq = 65000
        pty_board.board.add_counts(2000, 2000)
    link = SerialMotorLink(
        open_port(pty_board.name), ack_timeout_s=0.5, max_counts_per_s=SHIPPED_BOUND
    )
    try:
        assert link.read_odometry() is not None
        with pty_board.lock:
            pty_board.board.add_counts(43, 43)
        odo = link.read_odometry()
        assert odo is not None and odo.left_counts == 43
        with pty_board.lock:
            pty_board.board.boot()
            pty_board.board.add_counts(43, -43)
        with caplog.at_level("WARNING", logger="drivers.motors"):
            after = link.read_odometry()
        assert after is not None
        assert (after.left_counts, after.right_counts) == (43, 43)  # was (-1957, -2043)
        assert link.encoders.restarts == 1 and link.encoders.detected == 1
        assert any("restart" in r.getMessage() for r in caplog.records)
        with pty_board.lock:
            pty_board.board.add_counts(10, 10)
        again = link.read_odometry()
        assert again is not None and (again.left_counts, again.right_counts) == (53, 53)
    finally:
        link.close()


# --- review6 3: a board that browns out each time it drives off is a latched fault -----------


def _brown_out(pb: Pty) -> None:
    """The board restarts (its EVT BOOT reaches the host)."""
    with pb.lock:
        hello = pb.board.boot()
    os.write(pb.master, hello)


@pytest.mark.integration
def test_the_third_restart_within_a_minute_latches_until_an_operators_stop(
    caplog: pytest.LogCaptureFixture,
) -> None:
    from x6wd.core.records import MotorCommand

    now = [100.0]
    pb = Pty(boot=True)
    link = SerialMotorLink(open_port(pb.name), ack_timeout_s=0.5, clock=lambda: now[0])

    def drive() -> bool:
        return link.send(MotorCommand(now[0], 60.0, 60.0, "mission"))

    def restart() -> None:
        _brown_out(pb)
        assert wait_for(lambda: (link.ping() or True) and link.counters.board_restarts == n)

    try:
        n = 0
        for gap_s in (0.0, 61.0, 5.0):  # the first two over a minute (the window) apart
            now[0] += gap_s
            assert drive() and pb.state() == (60, 60)
            n += 1
            restart()
            assert not link.healthy
            assert link.stop("hold: motor link lost") and link.healthy  # one stop: drives go
        with caplog.at_level("ERROR", logger="drivers.motors"):
            now[0] += 5.0  # the third within 60 s (the 2nd and 3rd and this one)
            assert drive() and pb.state() == (60, 60)
            n += 1
            restart()
        for _ in range(3):  # the controller's stops: the board stops, the link stays lost
            now[0] += 1.0
            assert link.stop("hold: motor link lost")
            assert not link.healthy
            assert not drive() and pb.state() == (0, 0)
        errors = [r.getMessage() for r in caplog.records if r.levelname == "ERROR"]
        assert len(errors) == 1 and "restarted 3 times" in errors[0], errors
        assert link.counters.restart_faults == 1
        health = link.health
        assert health.state == "disconnected" and "restarted 3 times" in health.reason
        assert "stops or pauses" in health.reason
        # the controller's own stops never clear it: 'idle' after a lost link cancelled a
        # manual drive (review7: the next press drove off and browned the board out again)
        for own in ("idle", "paused", "done", "operator stop"):
            assert link.stop(own) and not link.healthy, own
            assert not drive() and pb.state() == (0, 0)
        link.clear_restart_fault()  # the operator stopped or paused (the daemon calls it)
        assert link.stop("idle") and link.healthy
        assert link.health.state == "connected"
        assert drive() and pb.state() == (60, 60)
        # the history stays: one more restart within the minute latches again at once
        n += 1
        restart()
        assert link.counters.restart_faults == 2
        assert link.stop("hold: motor link lost") and not link.healthy
    finally:
        link.close()
        pb.close()


class SaggingBoard(MotorBoard):
    """A board whose supply sags under motor current: it restarts (EVT BOOT) ``sag_s``
    after its motors start."""

    sag_s = 0.5  # the host stops a drive that crossed the restart within this (loaded CI: > 0.15 s)
    sags = 0
    _since: float | None = None

    def tick(self, t_s: float) -> bytes:
        out = super().tick(t_s)
        if not self.running:
            self._since = None
        elif self._since is None:
            self._since = t_s
        elif t_s - self._since >= self.sag_s:
            self._since = None
            self.sags += 1
            return out + self.boot()
        return out


@pytest.mark.integration
@pytest.mark.parametrize("ends", ["stop", "pause"])
def test_a_mission_on_a_board_browning_out_holds_until_the_operator_acts(ends: str) -> None:
    """review6 3: the hold ended at the first stop the board confirmed, the controller saw
    'motor link up' and the mission drove again within a cycle: a board that browns out
    under motor current restarted again and again, each time only a health event. The
    daemon's motor worker, a 20 Hz controller as the real one answers (the state's name
    while running, 'hold: motor link lost' while told lost; after the operator's stop
    'idle', after a pause 'paused'), its board on a pty browning out 0.15 s after it
    drives off: after the third restart the link stays lost until the operator acts."""
    from x6wd.app.daemon import _MotorWorker
    from x6wd.core.records import MotorCommand
    from x6wd.nav.controller import Mode

    board = SaggingBoard()
    pb = Pty(board, boot=True)
    link = SerialMotorLink(open_port(pb.name), ack_timeout_s=0.5)
    health: list[bool] = []
    told_ok = [True]
    mode = ["running"]

    def on_health(ok: bool, t_s: float) -> None:
        health.append(ok)
        told_ok[0] = ok

    w = _MotorWorker(link, 0.5 / 3, on_health)
    done = threading.Event()

    def controller() -> None:
        while not done.is_set():
            now = time.monotonic()
            if mode[0] != "running":
                w.submit(MotorCommand(now, 0.0, 0.0, mode[0]), repeat_after_s=0.1)
            elif told_ok[0]:
                w.submit(MotorCommand(now, 60.0, 60.0, "STRAIGHT"), repeat_after_s=0.1)
            else:
                w.submit(MotorCommand(now, 0.0, 0.0, "hold: motor link lost"), repeat_after_s=0.1)
            time.sleep(0.05)

    ctl = threading.Thread(target=controller, daemon=True)
    w.start()
    ctl.start()
    try:
        assert wait_for(lambda: link.counters.board_restarts >= 3, 10)
        time.sleep(1.5)  # the controller holds; nothing brings the link back
        assert board.sags == 3 and link.counters.board_restarts == 3
        assert not link.healthy and told_ok[0] is False
        assert link.health.state == "disconnected"
        assert "restarted 3 times" in link.health.reason
        assert pb.state() == (0, 0)
        # the operator: the daemon's stop (the worker's hold, the stop at once, then the
        # controller idle), or a pause (the controller paused)
        # the controller going idle by itself (a manual drive cancelled by the lost link)
        # clears nothing
        mode[0] = str(Mode.IDLE).lower()
        time.sleep(0.5)
        assert not link.healthy and told_ok[0] is False and pb.state() == (0, 0)
        if ends == "stop":  # as Daemon.stop does
            seq = w.hold_stop()
            w.clear_restart_fault()
            w.submit(MotorCommand(time.monotonic(), 0.0, 0.0, "operator stop"))
            mode[0] = str(Mode.IDLE).lower()
            w.stop_applied(seq)
        else:  # as Daemon.pause does
            w.clear_restart_fault()
            mode[0] = str(Mode.PAUSED).lower()
        assert wait_for(lambda: link.healthy and told_ok[0], 5)
        assert link.health.state == "connected"
        time.sleep(0.3)
        assert pb.state() == (0, 0) and board.sags == 3  # the mission waits for its operator
    finally:
        done.set()
        ctl.join(5)
        w.shutdown("end")
        pb.close()


def test_after_a_reopen_only_a_plain_continuation_keeps_the_baseline() -> None:
    from drivers.motors import EncoderUnwrap

    def reopened_then(seq: int, left: int, requests: int = 1) -> tuple[EncoderUnwrap, int]:
        u = EncoderUnwrap(1000.0)  # counts/s
        u.update(10, 100, 100, t_s=1.0, sent_s=0.99, requests=1)
        u.reopened()
        got, _ = u.update(seq, left, left, t_s=2.0, sent_s=1.99, requests=requests)
        return u, got

    u, got = reopened_then(11, 600)  # 500 counts in 1.01 s: fits 1,060
    assert (got, u.verdict, u.restarts) == (500, "continued", 0)
    u, got = reopened_then(13, 600, requests=3)  # two E lost to the dead port
    assert (got, u.verdict, u.skipped) == (500, "continued", 2)
    u, got = reopened_then(11, 5100)  # 5,000 counts: more than the wheels can
    assert (got, u.verdict, u.restarts) == (0, "reopened", 1)
    u, got = reopened_then(15, 600)  # 5 latches for our 1: another poller, or not ours
    assert (got, u.verdict) == (0, "reopened")
    u, got = reopened_then(1, 30)  # the board restarted with its port
    assert (got, u.verdict, u.detected) == (0, "restart", 1)
    # without a reopen the other poller's latches still count as motion
    u = EncoderUnwrap(1000.0)
    u.update(10, 100, 100, t_s=1.0, sent_s=0.99, requests=1)
    assert u.update(15, 600, 600, t_s=2.0, sent_s=1.99, requests=1) == (500, 500)


@pytest.mark.integration
@pytest.mark.parametrize("act", ["stop", "pause"])
def test_the_daemon_clears_a_latched_restart_fault_on_the_operators_stop_or_pause(
    tmp_path: Path, act: str
) -> None:
    """Daemon.stop and Daemon.pause are what clear the motor link's latched restart fault
    (nothing else does): the real daemon, its board on TCP."""
    import dataclasses

    from tests.test_daemon import Running, hil_config, wait_for
    from tests.test_shutdown import TcpMotorBoard
    from x6wd.app.client import RemoteClient
    from x6wd.app.daemon import Daemon

    board = TcpMotorBoard()
    cfg = hil_config(tmp_path)
    cfg = dataclasses.replace(
        cfg,
        motors=dataclasses.replace(cfg.motors, url=f"tcp://127.0.0.1:{board.port}?watchdog_ms=500"),
    )
    r = Running(Daemon(cfg))
    try:
        wait_for(lambda: r.daemon.motors is not None and r.daemon.motors.link.healthy, 10, "link")
        link = r.daemon.motors.link  # type: ignore[union-attr]
        if act == "pause":  # a mission running when the board browns out
            from tests.test_daemon import ORIGIN

            wait_for(lambda: r.daemon.first_fix, 20, "a fix")
            with RemoteClient("127.0.0.1", r.port) as c:
                c.request("mission.load", waypoints=[[ORIGIN[0] + 0.0003, ORIGIN[1]]])
                c.request("start")
        with link._lock:  # three restarts, as the transactions see them
            link.configured = True
            for _ in range(3):
                link._board_restarted("EVT BOOT", time.monotonic())
        wait_for(lambda: not link.healthy, 5, "the latched fault")
        time.sleep(0.5)  # the controller's own stops meanwhile clear nothing
        assert not link.healthy and "restarted 3 times" in link.health.reason
        with RemoteClient("127.0.0.1", r.port) as c:
            c.request(act)  # then the controller's own stop ('idle', 'paused') is confirmed
        wait_for(lambda: link.healthy, 5, "the fault cleared")
    finally:
        r.stop()
        if r.daemon.devices is not None:
            r.daemon.devices.close()
        board.close()


@pytest.mark.integration
def test_a_stop_waiting_for_the_port_while_the_fault_latches_does_not_end_it() -> None:
    """CI stop 49: the controller's 'idle' stop judged "no latched fault" before it had the
    port, waited while the third restart latched, and its confirmation then ended the fault
    the operator had not cleared. The rule is judged under the port's lock."""
    pb = Pty(boot=True)
    link = SerialMotorLink(open_port(pb.name), ack_timeout_s=0.5)
    try:
        assert link.stop("idle") and link.healthy
        result: list[bool] = []
        with link._lock:  # another thread's transaction holds the port
            waiting = threading.Thread(target=lambda: result.append(link.stop("idle")))
            waiting.start()
            time.sleep(0.3)  # the stop is past its start, blocked on the port
            link.configured = True
            for _ in range(3):
                link._board_restarted("EVT BOOT", time.monotonic())
        waiting.join(5)
        assert result == [True]  # the board stopped ...
        assert not link.healthy and "restarted 3 times" in link.health.reason  # ... latched
        link.clear_restart_fault()
        assert link.stop("operator stop") and link.healthy
    finally:
        link.close()
        pb.close()
