"""The daemon's exit when the motor board no longer answers (an outside audit, round 19).

A board that stopped acknowledging (hung, or its line cut) cannot confirm the stop at exit.
The daemon said "the motors are stopped" to its clients and exited 0 all the same, and the
recording ended as a clean stop. It now says the stop was NOT acknowledged (log, clients,
recording) and exits 1. Real process, a real protocol board on TCP."""

from __future__ import annotations

import signal
import threading
import time
from pathlib import Path
from typing import Any, cast

import pytest

from tests.test_daemon import hil_config, run_daemon, status, wait_for
from tests.test_daemon_faults import assert_recording_ends_with_the_stop
from tests.test_shutdown import DaemonProcess, TcpMotorBoard, board, daemon_process, drive_and_wait
from x6wd.app.client import ClosedWithoutReply, RemoteClient
from x6wd.app.daemon import Daemon
from x6wd.core.errors import X6wdError

__all__ = ["board", "daemon_process", "run_daemon"]  # the fixtures


def last_messages(c: RemoteClient, timeout_s: float = 10.0) -> list[dict[str, Any]]:
    out = []
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        try:
            out.append(c.read_message(timeout_s=1.0))
        except (ClosedWithoutReply, X6wdError, OSError):
            break
    return out


@pytest.mark.integration
@pytest.mark.parametrize("deaf", [False, True], ids=["answering", "deaf"])
def test_the_stop_at_exit_is_said_as_confirmed_only_when_the_board_confirmed_it(
    tmp_path: Path, daemon_process: DaemonProcess, board: TcpMotorBoard, deaf: bool
) -> None:
    p = daemon_process
    c = drive_and_wait(p, board, 40, 40)
    try:
        board.deaf = deaf
        time.sleep(0.3)
        p.proc.send_signal(signal.SIGTERM)
        code = p.proc.wait(30)
        said = last_messages(c)
    finally:
        c.close()
    p.reader.join(5)
    log = "\n".join(p.lines)
    assert code == (1 if deaf else 0), log[-2000:]
    assert f"x6wd stopped (exit {code})" in log, log[-2000:]  # (the signal's line says 0)
    notices = [m["error"]["message"] for m in said if m.get("error", {}).get("code") == "closed"]
    assert notices, said
    if deaf:
        assert "NOT acknowledged" in log, log[-2000:]
        assert "stop was NOT acknowledged" in notices[-1], notices
    else:
        assert "NOT acknowledged" not in log
        assert notices[-1].endswith("the motors are stopped"), notices
    records = assert_recording_ends_with_the_stop(
        tmp_path / "rec", "shutdown (SIGTERM)", 1 if deaf else 0, said=log
    )
    assert records[-1].data["motors_stopped"] is (not deaf)


# -- a compass read that never returns ------------------------------------------------------


class HungBus:
    """The compass's I2C bus, hung once ``hang`` is set: a read blocks until released (a
    CMPS10 holding SCL low, a wedged controller)."""

    def __init__(self, bus: Any) -> None:
        self.bus = bus
        self.hang = threading.Event()
        self.release = threading.Event()

    def read_i2c_block_data(self, addr: int, reg: int, length: int) -> list[int]:
        if self.hang.is_set():
            self.release.wait(30.0)
        return cast(list[int], self.bus.read_i2c_block_data(addr, reg, length))

    def __getattr__(self, name: str) -> Any:
        return getattr(self.bus, name)


def test_a_compass_whose_read_never_returns_is_stale_in_status(
    tmp_path: Path,
    run_daemon: Any,
) -> None:
    # an outside audit (round 19): its own stale check runs in its read, so status showed
    # it "connected" at 34 s old while the robot held
    r = run_daemon(Daemon(hil_config(tmp_path)))
    compass = wait_for(lambda: r.daemon._compass_driver, 5, "the compass thread")
    hung = HungBus(compass.bus)
    compass.bus = hung
    with RemoteClient("127.0.0.1", r.port) as c:
        assert status(c)["devices"]["compass"]["state"] == "connected"
        hung.hang.set()
        try:
            limit_s = r.daemon.config.compass.stale_s

            def stale() -> Any:
                comp = status(c)["devices"]["compass"]
                return comp if comp["state"] == "stale" else None

            comp = wait_for(stale, limit_s + 5.0, "the compass stale in status")
            assert "its read has not returned" in comp["reason"], comp
        finally:
            hung.release.set()
            hung.hang.clear()
        wait_for(lambda: status(c)["devices"]["compass"]["state"] != "stale", 5, "fresh again")
