"""An operator's stop while the motor link is lost says so (an outside audit, round 21).

Before, `x6wd client stop` printed "stop: ok" with exit 0 after the board had gone deaf:
the controller had stopped, but nothing said that the stop could not reach the wheels
(only `status` showed "motors lost"). Real daemon process, a real protocol board on TCP
that stops answering, the real client as a user runs it."""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tests.test_shutdown import ROOT, DaemonProcess, TcpMotorBoard, board
from tests.test_startup import write_config
from x6wd.app.client import RemoteClient

__all__ = ["board"]  # the fixture


def client_stop(port: int, *extra: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "x6wd", "client", "--port", str(port), "stop", *extra],
        capture_output=True,
        text=True,
        timeout=30,
        cwd=ROOT,
    )


@pytest.mark.integration
def test_a_stop_with_the_motor_link_lost_is_not_reported_as_ok(
    tmp_path: Path, board: TcpMotorBoard
) -> None:
    url = f"tcp://127.0.0.1:{board.port}?watchdog_ms=500"
    p = DaemonProcess(write_config(tmp_path, motors={"url": url}))
    try:
        assert p.port is not None
        ok = client_stop(p.port)
        assert (ok.returncode, ok.stdout) == (0, "stop: ok\n"), ok.stderr
        board.deaf = True
        with RemoteClient("127.0.0.1", p.port) as c:
            deadline = time.monotonic() + 15
            while c.request("status")["links"]["motors"] != "lost":
                assert time.monotonic() < deadline, "the motor link was never lost"
                time.sleep(0.1)
        lost = client_stop(p.port)
        assert lost.returncode == 1, (lost.stdout, lost.stderr)
        assert lost.stdout.startswith("stop: the robot's controller stopped, but its motor link")
        assert "no acknowledgement" in lost.stdout and "may not reach the wheels" in lost.stdout
        as_json = json.loads(client_stop(p.port, "--json").stdout)
        assert as_json["mode"] == "IDLE" and as_json["motors"] == "lost"
        assert p.proc.poll() is None  # the robot keeps going
    finally:
        p.stop()
