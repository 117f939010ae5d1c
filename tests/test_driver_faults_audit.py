"""Device faults an outside audit found the drivers and the daemon mishandled, each on the
real part: pseudo-terminals for the serial devices, the real `x6wd run` process where the
behaviour is the daemon's.

- A motor board silent from power-up is reported to the controller: drives are refused and
  a mission is held until it answers.
- A motor port that keeps failing with a transient errno (EIO from a pty whose far end went
  away) counts as broken after a few errors in a row, and is reopened.
- A GPS that sends only checksum-valid sentences with invalid fields goes stale.
- A serial device another process holds (locked) is a reconnect error on a reopen (at
  start-up too: tests/test_driver_faults_round2.py).
- A character device that is not a serial port is refused at start-up naming the key.
"""

from __future__ import annotations

import os
import select
import threading
import time
import tty
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import serial

from drivers import registry
from drivers.gps_io import GpsReader
from drivers.motors import MotorBoard, SerialMotorLink, serve_board_fd
from tests.conftest import ROOT
from tests.test_daemon import wait_for
from tests.test_shutdown import DaemonProcess
from tests.test_startup import assert_config_error, run_x6wd, write_config
from x6wd.app.client import RemoteClient, RequestFailed

pytestmark = pytest.mark.integration

MISSION = ROOT / "missions" / "default.gpx"


class PtyPeer:
    """A device on a raw pseudo-terminal (:attr:`path` is its serial port), served by
    :meth:`_run` on a thread until :meth:`close`."""

    def __init__(self) -> None:
        self.master, self.slave = os.openpty()
        tty.setraw(self.master)
        tty.setraw(self.slave)
        self.path = os.ttyname(self.slave)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        raise NotImplementedError

    def close(self) -> None:
        self._stop.set()
        self._thread.join(5)
        os.close(self.master)
        os.close(self.slave)


class PtyMotorBoard(PtyPeer):
    """A motor board on a pseudo-terminal that reads every byte the host sends and answers
    only while :attr:`answering` (a board powered up later, or never)."""

    def __init__(self) -> None:
        super().__init__()
        self.board = MotorBoard()
        self.answering = False
        self.lines = 0
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            ready, _, _ = select.select([self.master], [], [], 0.005)
            data = b""
            if ready:
                try:
                    data = os.read(self.master, 4096)
                except OSError:
                    return
            self.lines += data.count(b"\n")
            if not self.answering:
                continue
            reply = self.board.feed(data, time.monotonic())
            if reply:
                os.write(self.master, reply)


@pytest.fixture
def silent_board() -> Iterator[PtyMotorBoard]:
    b = PtyMotorBoard()
    yield b
    b.close()


def load_mission(c: RemoteClient) -> bool:
    try:
        c.request("mission.load", gpx=MISSION.read_text())
    except RequestFailed as exc:
        if "no fix yet" in exc.message:
            return False
        raise
    return True


def status(c: RemoteClient) -> dict[str, Any]:
    st: dict[str, Any] = c.request("status")
    return st


def test_a_board_silent_from_power_up_holds_the_robot_until_it_answers(
    tmp_path: Path, silent_board: PtyMotorBoard
) -> None:
    config = write_config(tmp_path, motors={"url": f"serial://{silent_board.path}?baud=115200"})
    p = DaemonProcess(config)
    try:
        assert p.port is not None
        with RemoteClient("127.0.0.1", p.port) as c:
            st = status(c)
            assert st["links"]["motors"] == "lost"
            assert st["devices"]["motors"]["state"] in ("disconnected", "reconnecting")
            with pytest.raises(RequestFailed) as ei:
                c.request("drive", left=30, right=30, duration_s=2)
            assert ei.value.code == "rejected" and "motor link lost" in ei.value.message
            st = status(c)
            assert st["mode"] == "IDLE"
            assert silent_board.board.running is False
            wait_for(lambda: load_mission(c), 15, "a fix to load the mission against")
            c.request("start")  # accepted, but held while the motors are lost
            time.sleep(0.5)
            st = status(c)
            tel = st["telemetry"]
            assert st["mode"] == "RUNNING" and st["state"] == "HOLD", st
            assert tel["hold_reason"] == "motor link lost"
            assert (tel["left_pct"], tel["right_pct"]) == (0.0, 0.0)
            c.request("stop")
            assert silent_board.lines > 0  # the daemon kept trying (W, S ...)

            silent_board.answering = True  # the board powers up
            wait_for(lambda: status(c)["links"]["motors"] == "ok", 10, "motors ok")
            assert status(c)["devices"]["motors"]["state"] == "connected"
            c.request("drive", left=30, right=30, duration_s=2)
            wait_for(lambda: silent_board.board.running, 5, "board driven")
            assert silent_board.board.watchdog_ms == 500  # W was sent once it answered
            c.request("stop")
            wait_for(lambda: not silent_board.board.running, 5, "board stopped")
    finally:
        p.stop()


class PluggedBoard:
    """A MotorBoard on a fresh pty reached through the symlink ``link`` (a USB adapter's
    by-id name): :meth:`unplug` closes both ends, :meth:`plug` makes a new pty there."""

    def __init__(self, link: Path) -> None:
        self.link = link
        self.board = MotorBoard()
        self.fds: tuple[int, int] | None = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def new_port(self) -> int:
        """A fresh raw pty behind :attr:`link` (a USB adapter plugged in again); its master."""
        master, slave = os.openpty()
        tty.setraw(master)
        tty.setraw(slave)
        tmp = self.link.with_suffix(".tmp")
        tmp.unlink(missing_ok=True)
        tmp.symlink_to(os.ttyname(slave))
        tmp.replace(self.link)
        self.fds = (master, slave)
        self._stop = threading.Event()
        return master

    def plug(self) -> None:
        master = self.new_port()
        self.board = MotorBoard()
        self._thread = threading.Thread(
            target=serve_board_fd, args=(master, self.board, self._stop), daemon=True
        )
        self._thread.start()

    def unplug(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(5)
        if self.fds is not None:
            for fd in self.fds:
                os.close(fd)
            self.fds = None
        # as udev does: the adapter's name goes with it (else the freed /dev/pts/N, reused
        # by any other process's pty, would be "the board" again)
        self.link.unlink(missing_ok=True)


@pytest.fixture
def plugged(tmp_path: Path) -> Iterator[PluggedBoard]:
    b = PluggedBoard(tmp_path / "ttyUSB-board")
    b.plug()
    yield b
    b.unplug()


def test_a_motor_port_failing_with_eio_for_ever_is_reopened(plugged: PluggedBoard) -> None:
    link = registry.open_motors(f"serial://{plugged.link}?baud=115200&watchdog_ms=700")
    try:
        assert link.drive(10, 10) and plugged.board.left_pct == 10
        link.take_health_events()
        plugged.unplug()  # the adapter is gone: the link's port answers EIO from now on
        for _ in range(5):
            assert not link.stop()
            time.sleep(0.3)
        h = link.health
        assert h.state == "reconnecting", h
        assert "reopening the port failed" in h.reason, h.reason  # not the old write error
        plugged.plug()  # back at the same path
        wait_for(lambda: link.stop(), 8, "the board reached again")
        assert isinstance(link, SerialMotorLink)
        assert link.counters.reopens == 1
        assert link.health.state == "connected" and link.health.reconnects >= 1
        assert link.drive(20, 20) and plugged.board.left_pct == 20
        assert plugged.board.watchdog_ms == 700  # the new board was set up again
        states = [(e.old, e.new) for e in link.take_health_events() if e.kind == "transition"]
        assert [new for _old, new in states].count("disconnected") == 1  # closed once
        assert states[-1] == ("reconnecting", "connected")
    finally:
        link.close()


def nmea(body: str) -> bytes:
    c = 0
    for ch in body.encode("ascii"):
        c ^= ch
    return f"${body}*{c:02X}\r\n".encode("ascii")


ABSURD = nmea("GPGGA,120000.00,9959.0000,N,00015.4620,W,1,08,0.9,60.0,M,47.0,M,,") + nmea(
    "GPRMC,120000.00,A,9959.0000,N,00015.4620,W,0.5,10.0,010125,,,A"
)  # latitude 99 degrees 59': checksum-valid, fields invalid
NO_FIX = nmea("GPGGA,,,,,,0,00,99.9,,,,,,") + nmea("GPRMC,,V,,,,,,,,,,N")
# a receiver still searching: valid data, no fix


@pytest.fixture
def gps_pty() -> Iterator[tuple[int, str]]:
    master, slave = os.openpty()
    tty.setraw(master)
    tty.setraw(slave)
    yield master, os.ttyname(slave)
    os.close(master)
    os.close(slave)


def feed_for(reader: GpsReader, master: int, sentences: bytes, seconds: float) -> None:
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        os.write(master, sentences)
        t_next = time.monotonic() + 0.1
        while time.monotonic() < t_next:
            reader.poll(0.02)


@pytest.mark.parametrize(
    ("sentences", "state"), [(ABSURD, "stale"), (NO_FIX, "connected")], ids=["absurd", "no_fix"]
)
def test_a_gps_sending_only_invalid_fields_goes_stale(
    gps_pty: tuple[int, str], sentences: bytes, state: str
) -> None:
    master, path = gps_pty
    reader = GpsReader(lambda: registry.open_gps_port(f"serial://{path}?baud=9600"), stale_s=0.5)
    try:
        feed_for(reader, master, sentences, 1.5)
        h = reader.health
        assert h.state == state, h
        if state == "stale":
            assert "sentences with invalid fields" in h.reason, h.reason
            assert h.corrupt["invalid_fields"] > 10
        else:
            assert h.reason == "" and h.corrupt["invalid_fields"] == 0
    finally:
        reader.close()


@pytest.mark.parametrize("key", ["gps", "motors"])
def test_a_character_device_that_is_not_a_serial_port_is_refused_at_start_up(
    tmp_path: Path, key: str
) -> None:
    proc = run_x6wd(write_config(tmp_path, **{key: {"url": "serial:///dev/null"}}), 30)
    assert_config_error(proc, f"{key}.url", "/dev/null is not a serial port")


def test_a_port_locked_when_reopened_is_a_reconnect_error_until_released(
    plugged: PluggedBoard,
) -> None:
    link = registry.open_motors(f"serial://{plugged.link}?baud=115200")
    holder: serial.Serial | None = None
    try:
        assert link.drive(10, 10)
        plugged.unplug()
        plugged.plug()  # back, but another process took it first
        holder = serial.Serial(str(plugged.link), exclusive=True)
        for _ in range(6):
            assert not link.stop()
            time.sleep(0.3)
        h = link.health
        assert h.state == "reconnecting", h
        assert "is in use: another process holds it" in h.reason, h.reason
        holder.close()
        wait_for(lambda: link.stop(), 8, "the board reached once released")
        assert link.health.state == "connected"
        assert link.drive(20, 20) and plugged.board.left_pct == 20
    finally:
        if holder is not None:
            holder.close()
        link.close()
