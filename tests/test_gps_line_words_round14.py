"""A GPS line that delivers nothing decodable is named as the line, not the sky.

An outside audit (round 14): a silent UART, or one sending garbage, was first reported as
"gps: no valid fix for 2.5 s (the receiver reports no position: searching, or the sky
blocked)", and status showed gps degraded "the receiver reports no position" for 0.25-0.5 s
before the reader's own "gps stale: no good data ..." came: both timed from the last valid
fix ([safety] fix_stale_s), which ran out before the line's staleness ([gps] stale_s), and
neither asked whether the line delivered anything. Here the real daemon reads a real pty
whose far end this test writes: valid 4 Hz epochs, then silence, garbage, or a receiver's
valid no-fix sentences (which must still say searching / the sky)."""

from __future__ import annotations

import dataclasses
import logging
import os
import random
import threading
import time
import tty
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from drivers.nmea import checksum
from tests.test_daemon import hil_config, run_daemon, wait_for
from x6wd.app.client import RemoteClient
from x6wd.app.daemon import Daemon
from x6wd.core.config import GpsConfig

__all__ = ["run_daemon"]  # a fixture

SKY_WORDS = "the receiver reports no position"
LINE_WORDS = "from the receiver"  # "no (good) data from the receiver ...: check the line's"


def _s(body: str) -> bytes:
    return f"${body}*{checksum(body.encode()):02X}\r\n".encode()


def _epoch(fix: bool) -> bytes:
    t = datetime.now(UTC)
    hms = t.strftime("%H%M%S.") + f"{t.microsecond // 10000:02d}"
    if not fix:  # a receiver searching: it talks, and says there is no position
        return _s(f"GPRMC,{hms},V,,,,,,,{t:%d%m%y},,,N") + _s(f"GPGGA,{hms},,,,,0,00,99.99,,,,,,")
    return _s(f"GPRMC,{hms},A,5140.00000,N,03945.00000,E,0.0,,{t:%d%m%y},,,A") + _s(
        f"GPGGA,{hms},5140.00000,N,03945.00000,E,1,08,1.0,100.0,M,10.0,M,,"
    )


class Receiver:
    """A pty whose far end writes a 4 Hz receiver's epochs as ``mode`` says: "fix",
    "nofix" (valid sentences without a position), "silent" or "garbage" (random bytes)."""

    def __init__(self) -> None:
        self.master, self.slave = os.openpty()
        tty.setraw(self.master)
        tty.setraw(self.slave)
        self.path = os.ttyname(self.slave)
        self.mode = "fix"
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self) -> None:
        rnd = random.Random(14)
        while not self.stop.wait(0.25):
            mode = self.mode
            if mode == "silent":
                continue
            data = _epoch(mode == "fix")
            if mode == "garbage":
                data = bytes(rnd.getrandbits(8) for _ in data)
            os.write(self.master, data)

    def close(self) -> None:
        self.stop.set()
        self.thread.join(5)
        os.close(self.master)
        os.close(self.slave)


def spell(c: RemoteClient, rx: Receiver, mode: str, caplog: Any) -> tuple[str, list[str]]:
    """Switch the receiver to ``mode`` for 4 s: the first "no valid fix" WARNING logged and
    the gps status reasons seen meanwhile (polled every 50 ms); then valid epochs again
    until the status is connected."""
    caplog.clear()
    rx.mode = mode
    reasons: list[str] = []
    end = time.monotonic() + 4.0
    while time.monotonic() < end:
        g = c.request("status")["devices"]["gps"]
        reasons.append(f"{g['state']}: {g['reason']}")
        time.sleep(0.05)
    warnings = [
        r.getMessage()
        for r in caplog.records
        if r.levelno == logging.WARNING and r.getMessage().startswith("gps: no valid fix")
    ]
    rx.mode = "fix"
    wait_for(lambda: c.request("status")["devices"]["gps"]["state"] == "connected", 10,
             "gps connected again")  # fmt: skip
    time.sleep(0.5)
    assert warnings, f"no 'no valid fix' warning for {mode}"
    return warnings[0], reasons


def test_a_silent_or_garbled_line_is_named_a_searching_receiver_the_sky(
    tmp_path: Path, run_daemon: Any, caplog: Any
) -> None:
    caplog.set_level(logging.WARNING)
    rx = Receiver()
    try:
        cfg = hil_config(tmp_path)
        cfg = dataclasses.replace(
            cfg, gps=GpsConfig(url=f"serial://{rx.path}?baud=115200", rate_hz=4.0)
        )
        r = run_daemon(Daemon(cfg))
        with RemoteClient("127.0.0.1", r.port) as c:
            wait_for(lambda: r.daemon.first_fix, 15, "first fix")
            wait_for(lambda: c.request("status")["devices"]["gps"]["state"] == "connected", 10,
                     "gps connected")  # fmt: skip
            for mode in ("silent", "garbage"):
                first, reasons = spell(c, rx, mode, caplog)
                assert LINE_WORDS in first and "check the line's wiring, baud and power" in first
                assert "sky" not in first, (mode, first)
                assert not [x for x in reasons if SKY_WORDS in x], (mode, reasons)
                assert any("no good data" in x for x in reasons), (mode, reasons)
            first, reasons = spell(c, rx, "nofix", caplog)
            assert "searching, or the sky blocked" in first and LINE_WORDS not in first, first
            assert any(x.startswith("degraded: no valid fix for ") and SKY_WORDS in x
                       for x in reasons), reasons  # fmt: skip
            assert not [x for x in reasons if LINE_WORDS in x or "no good data" in x], reasons
    finally:
        rx.close()
