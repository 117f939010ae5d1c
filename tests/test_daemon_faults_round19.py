"""The daemon's exit when the motor board no longer answers (an outside audit, round 19).

A board that stopped acknowledging (hung, or its line cut) cannot confirm the stop at exit.
The daemon said "the motors are stopped" to its clients and exited 0 all the same, and the
recording ended as a clean stop. It now says the stop was NOT acknowledged (log, clients,
recording) and exits 1. Real process, a real protocol board on TCP."""

from __future__ import annotations

import signal
import time
from pathlib import Path
from typing import Any

import pytest

from tests.test_daemon_faults import assert_recording_ends_with_the_stop
from tests.test_shutdown import DaemonProcess, TcpMotorBoard, board, daemon_process, drive_and_wait
from x6wd.app.client import ClosedWithoutReply, RemoteClient
from x6wd.core.errors import X6wdError

__all__ = ["board", "daemon_process"]  # the fixtures


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
