"""Round 13 (review of 60e902d, finding 4): ``x6wd client status`` printed nothing of
``gps_receiver`` (the line, a full line, slow fixes, the setup): only ``--json`` had them,
though docs/gps.md said status shows it. Now a brief ``gps rx`` line, and each problem on
its own line."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path
from typing import Any

from tests.conftest import ROOT
from tests.test_daemon import hil_config, run_daemon, wait_for
from x6wd.app.client import RemoteClient, gps_receiver_lines, render_status
from x6wd.app.daemon import Daemon
from x6wd.core.config import SimConfig

__all__ = ["run_daemon"]


def test_client_status_prints_slow_fixes_and_a_full_line_of_a_real_daemon(
    tmp_path: Path, run_daemon: Any
) -> None:
    # hardware in the loop: [sim] gps_rate_hz = 4 at 9600 baud, the receiver's own sentences
    # (not configured): the simulator's pty runs full and the fixes come at ~2.5 Hz
    cfg = hil_config(tmp_path, sim=SimConfig(gps_rate_hz=4.0, gps_baud=9600))
    r = run_daemon(Daemon(cfg))
    with RemoteClient("127.0.0.1", r.port) as c:
        wait_for(
            lambda: (g := c.request("status")["gps_receiver"]).get("slow") and g.get("line_full"),
            20,
            "slow fixes and a full line",
        )
    res = subprocess.run(
        [sys.executable, "-m", "x6wd", "client", "--port", str(r.port), "status"],
        capture_output=True,
        text=True,
        timeout=60,
        cwd=ROOT,
    )
    assert r.stop() == 0
    assert res.returncode == 0, res.stderr
    text = res.stdout
    brief = next(ln for ln in text.splitlines() if ln.startswith("gps rx     fixes "))
    assert "(expected 4 Hz)  line 9600 baud " in brief and "% full" in brief, brief
    assert "\n  gps rx   SLOW: fixes arrive at " in text and "under sim.gps_rate_hz" in text
    assert "\n  gps rx   LINE FULL: the line is full (" in text, text


# a real status's gps_receiver (hardware in the loop: configure_receiver = true, 4 Hz, the
# scenario's [gnss] baud = 4800), and a healthy one
SHORT = {
    "configure_receiver": True,
    "expected_rate_hz": 4.0,
    "line": {"baud": 4800, "bytes_per_s": 480, "load": 1.0, "paced": True},
    "line_full": "the line is full (480 of the 480 bytes/s that 4800 baud carries, ...",
    "measured_rate_hz": 4.16,
    "setup": {
        "answers": {"CFG-RATE 250 ms": "ack"},
        "baud": 4800,
        "line_short": "4800 baud at 4 Hz carries 120 bytes an epoch, under the 152 ...",
        "losses": 0,
        "rate_hz": 4.0,
        "rounds": 1,
        "state": "acked",
    },
}


def test_the_gps_receiver_lines_say_each_problem_and_briefly_a_healthy_one() -> None:
    text = render_status({"gps_receiver": SHORT})
    assert "gps rx     fixes 4.16 Hz (expected 4 Hz)  line 9600" not in text
    assert "gps rx     fixes 4.16 Hz (expected 4 Hz)  line 4800 baud 480 B/s 100% full  " in text
    assert "\n  gps rx   LINE FULL: the line is full (480 of" in text
    assert "\n  gps rx   LINE SHORT: 4800 baud at 4 Hz carries 120 bytes" in text
    assert "SLOW" not in text and "setup acked" in text
    healthy = {
        "configure_receiver": False,
        "expected_rate_hz": 1.0,
        "measured_rate_hz": 1.0,
        "line": {"baud": 9600, "bytes_per_s": 470, "load": 0.49, "paced": True},
        "setup": None,
    }
    assert gps_receiver_lines(healthy) == [
        "gps rx     fixes 1 Hz (expected 1 Hz)  line 9600 baud 470 B/s 49% full"
    ]
    usb = {**healthy, "line": {"baud": 9600, "bytes_per_s": 2905, "paced": False}}
    assert gps_receiver_lines(usb)[0].endswith("2905 B/s (not paced by its baud)")
    refused = {
        **SHORT,
        "setup": {"state": "refused", "problem": "the receiver refused (ACK-NAK) CFG-RATE"},
    }
    assert "  gps rx   setup refused: the receiver refused (ACK-NAK) CFG-RATE" in (
        gps_receiver_lines(refused)
    )
    assert gps_receiver_lines(None) == []  # before the GPS reader exists
