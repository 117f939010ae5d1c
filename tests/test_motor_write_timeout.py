"""A motor port whose writes stall (a stuck USB adapter, a line held by flow control) is a
link fault, not a writer blocked for ever.

The board is a real :class:`drivers.motors.MotorBoard` on a pseudo-terminal, the link the one
:func:`drivers.registry.open_motors` opens for ``serial://``. Suspending the pty's output
(``tcflow(TCOOFF)``, what an XOFF does) makes every write to the port block: without a write
timeout pyserial retries it for ever, under the link's lock (and, for a fix's command sent
directly, the daemon's control lock). With it the write fails within the acknowledgement
timeout, the link is lost (health says why, the motor worker tells the controller), the board's
own watchdog stops the motors, and once the line flows again the port is reopened and the link
comes back.
"""

from __future__ import annotations

import contextlib
import socket
import termios
import threading
import time
from typing import Any

import pytest
import serial

from drivers import registry
from drivers.motors import SerialMotorLink
from drivers.registry import MOTOR_WRITE_TIMEOUT_S
from tests.test_daemon import BoardOnPty, wait_for
from tests.test_motors import PortProxy
from tests.test_safety_daemon import Calls
from x6wd.app.daemon import _MotorWorker
from x6wd.core.records import MotorCommand

ACK_S = 0.1


def send_in_thread(link: Any, cmd: MotorCommand) -> tuple[threading.Thread, dict[str, Any]]:
    out: dict[str, Any] = {}

    def go() -> None:
        t0 = time.monotonic()
        try:
            out["ok"] = link.send(cmd)
        except BaseException as exc:  # a crash is a failure of the test, reported below
            out["raised"] = exc
        out["took_s"] = time.monotonic() - t0

    t = threading.Thread(target=go, daemon=True)
    t.start()
    return t, out


def test_a_stalled_motor_port_fails_the_write_in_time_and_the_link_recovers() -> None:
    with BoardOnPty(watchdog_ms=500) as board:
        link: Any = registry.open_motors(f"{board.url}?ack_timeout={ACK_S}&retries=1")
        try:
            assert link.configured and link.healthy
            assert link.send(MotorCommand(time.monotonic(), 30.0, 30.0, "drive"))
            assert board.board.left_pct == 30
            termios.tcflow(board.slave, termios.TCOOFF)  # the line stops taking bytes
            try:
                t, out = send_in_thread(link, MotorCommand(time.monotonic(), 40.0, 40.0, "fix"))
                t.join(3.0)
                assert not t.is_alive(), "the write still blocks after 3 s"
                assert "raised" not in out, out
                assert out["ok"] is False and out["took_s"] < MOTOR_WRITE_TIMEOUT_S + 1.0
                assert not link.healthy and link.counters.write_errors >= 1
                health = link.health
                assert health.state in ("disconnected", "reconnecting")
                assert "Write timeout" in (health.last_error or "")
                # the next commands fail at once (the port is closed until its reopen)
                t0 = time.monotonic()
                assert link.stop("operator stop") is False
                assert time.monotonic() - t0 < 1.0
                # nothing reaches the board: its watchdog stops the motors by itself
                wait_for(lambda: board.board.watchdog_trips >= 1, 3, "the board's watchdog")
                assert board.board.left_pct == 0
            finally:
                termios.tcflow(board.slave, termios.TCOON)
            # the line flows again: the port is reopened, the watchdog set, commands go
            wait_for(lambda: link.send(MotorCommand(time.monotonic(), 0.0, 0.0, "hold")), 10,
                     "the link back")  # fmt: skip
            assert link.healthy and link.counters.reopens >= 1
            # a write may take as long as its ack, and never less than the floor
            assert link.port.write_timeout == max(ACK_S, MOTOR_WRITE_TIMEOUT_S)
            assert board.board.left_pct == 0 and board.board.right_pct == 0
        finally:
            link.close()


def test_the_motor_worker_reports_a_stalled_port_lost_and_keeps_running() -> None:
    """Through the daemon's motor worker: a direct send (a fix's, under the control lock)
    returns in time, the controller is told the link is lost, and the thread lives on."""
    with BoardOnPty(watchdog_ms=500) as board:
        link: Any = registry.open_motors(f"{board.url}?ack_timeout={ACK_S}&retries=1")
        calls = Calls()
        w = _MotorWorker(link, 0.1, calls.on_health, calls.on_events)
        w.start()
        try:
            assert w.send_now(MotorCommand(time.monotonic(), 30.0, 30.0, "fix"))
            termios.tcflow(board.slave, termios.TCOOFF)
            try:
                done = threading.Event()

                def fix() -> None:
                    w.send_now(MotorCommand(time.monotonic(), 40.0, 40.0, "fix"))
                    done.set()

                threading.Thread(target=fix, daemon=True).start()
                assert done.wait(3.0), "a fix's send still blocks after 3 s"
                wait_for(lambda: any(ok is False for ok, _t in calls.health), 3, "link lost")
                assert w.thread.is_alive()
            finally:
                termios.tcflow(board.slave, termios.TCOON)
            wait_for(lambda: calls.health and calls.health[-1][0] is True, 10, "link back")
            assert w.thread.is_alive()
        finally:
            w.shutdown("test end")


class StuckAdapter(PortProxy):
    """The real pyserial port to the pty board behind a USB adapter that can stall, modelled
    at the boundary a pty cannot be made to behave like (its buffering varies run to run):
    while ``stuck`` the adapter's buffer takes up to ``room`` bytes, which go out when it
    unsticks; a write that does not fit fails after the port's ``write_timeout`` as
    pyserial's does; ``reset_output_buffer`` (tcflush) empties the buffer; ``close`` with
    bytes still in it drains them first, as a USB serial port does (waiting for the line,
    here up to ``closing_wait_s``; 30 s by default on Linux)."""

    def __init__(self, port: serial.Serial, room: int = 16, closing_wait_s: float = 5.0) -> None:
        super().__init__(port)
        self.room = room
        self.closing_wait_s = closing_wait_s
        self.pending = bytearray()
        self.unstuck = threading.Event()
        self.unstuck.set()
        self.discarded = 0

    def write(self, data: bytes) -> int | None:
        if self.unstuck.is_set():
            return self.port.write(data)
        take = max(0, min(len(data), self.room - len(self.pending)))
        self.pending += data[:take]
        if take < len(data):
            time.sleep(self.port.write_timeout)
            raise serial.SerialTimeoutException("Write timeout")
        return len(data)

    def flow(self) -> None:
        """The adapter sends again: what it held goes out, in order."""
        self.unstuck.set()
        if self.pending and self.port.is_open:
            self.port.write(bytes(self.pending))
        self.pending.clear()

    def reset_output_buffer(self) -> None:
        self.discarded += len(self.pending)
        self.pending.clear()
        self.port.reset_output_buffer()

    def close(self) -> None:
        if self.pending:  # tty_port_close_start: tty_wait_until_sent(closing_wait)
            self.unstuck.wait(self.closing_wait_s)
            if self.unstuck.is_set():
                self.port.write(bytes(self.pending))
                self.port.flush()
            self.pending.clear()
        self.port.close()


def test_a_drive_a_stuck_adapter_still_holds_is_discarded_when_the_link_drops_the_port() -> None:
    """A drive went into the adapter's buffer just before it stalled; its retry does not fit
    and times out, and the link drops the port. The held drive is discarded: closing the
    port does not wait for the stalled line to drain it (under the link's lock, and the
    control lock when a fix's command was being sent), and when the line flows again the
    board does not act on a drive the link gave up long before."""
    with BoardOnPty(watchdog_ms=2000) as board:
        name = board.url.removeprefix("serial://")

        def open_port() -> StuckAdapter:
            return StuckAdapter(serial.Serial(name, 115200, timeout=0.02, write_timeout=ACK_S))

        adapter = open_port()
        link = SerialMotorLink(adapter, ack_timeout_s=ACK_S, watchdog_ms=2000, reopen=open_port)
        try:
            assert link.drive(20, 20) and board.board.left_pct == 20
            commands = board.board.commands
            adapter.unstuck.clear()
            t, out = send_in_thread(link, MotorCommand(time.monotonic(), 40.0, 40.0, "fix"))
            t.join(2.0)
            assert not t.is_alive(), "closing the broken port waits for the stalled line"
            assert "raised" not in out, out
            assert out["ok"] is False and not link.healthy
            assert "Write timeout" in (link.health.last_error or "")
            assert adapter.discarded > 0 and not adapter.pending
            adapter.flow()  # the line flows again
            time.sleep(0.3)
            assert board.board.commands == commands and board.board.left_pct == 20
        finally:
            adapter.flow()
            link.close()


def test_a_dropped_tcp_motor_port_does_not_deliver_its_queued_drives() -> None:
    """pyserial's socket:// port ignores reset_output_buffer and its close sends what is
    queued: a board (or serial bridge) that stalled and then read again acted on every stale
    drive (a review: 124,328 queued commands delivered after the drop, the last a 40/40
    drive). The drop resets the connection instead."""
    srv = socket.socket()
    srv.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    srv.bind(("127.0.0.1", 0))
    srv.listen(1)
    url = f"socket://127.0.0.1:{srv.getsockname()[1]}"
    port = serial.serial_for_url(url, timeout=0.02, write_timeout=0.1)
    conn, _ = srv.accept()
    try:
        link = SerialMotorLink(port, ack_timeout_s=ACK_S, watchdog_ms=500,
                               reopen=lambda: serial.serial_for_url(url, timeout=0.02))  # fmt: skip
        sent = 0
        with pytest.raises(serial.SerialTimeoutException):
            for sent in range(1, 10_000_000):  # noqa: B007 (read below) the queue fills
                port.write(b"D 40 40\n")
        link._drop_port()
        got = 0
        conn.settimeout(2.0)
        with contextlib.suppress(ConnectionResetError, TimeoutError):
            while data := conn.recv(65536):
                got += data.count(b"\n")
        # what sat in the board's own receive buffer may arrive; the sender's queue may not
        assert got < sent // 2, f"{got} of {sent} queued drives reached the board after the drop"
    finally:
        conn.close()
        srv.close()
