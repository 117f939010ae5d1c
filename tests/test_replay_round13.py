"""Round 13: epochs of an NMEA log without times (a multi-part GSV is one epoch), on gpsd's
real logs."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from tests.test_recorder import ROOT, VirtualClock
from x6wd.core.recorder import ReplayPort, _file_lines, _sentence_utc_s, nmea_file_chunks

NMEA = ROOT / "tests" / "data" / "nmea"


def _untimed(log: Path, out: Path) -> Path:
    """``log`` without its sentences that carry a UTC time (GGA, RMC, GLL, ZDA, GST...)."""
    with open(log, "rb") as f:
        out.write_bytes(b"".join(x for x in _file_lines(f) if _sentence_utc_s(x) is None))
    return out


def _epochs(path: Path, rate_hz: float = 1.0) -> int:
    return len({t for t, _ in nmea_file_chunks(path, rate_hz)})


def _x6wd(*args: str) -> subprocess.CompletedProcess[str]:
    exe = Path(sys.executable).parent / "x6wd"
    cmd = [str(exe)] if exe.exists() else [sys.executable, "-m", "x6wd"]
    return subprocess.run(
        [*cmd, *args],
        capture_output=True,
        text=True,
        timeout=60,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
    )


def test_a_multi_part_gsv_is_one_epoch_in_replay_and_a_replay_port(tmp_path: Path) -> None:
    """The docs' untimed log (GSA and a 3-part GSV each second): 18 epochs at 5 Hz end at
    3.4 s (each GSV part was an epoch: 11.6 s), in `x6wd replay` and the daemon's replay://."""
    log = tmp_path / "notime.log"
    log.write_bytes(
        b"".join(
            x
            for x in (NMEA / "ublox-lea-5h.log").read_bytes().splitlines(keepends=True)
            if b"GSA" in x or b"GSV" in x
        )
    )
    assert _epochs(log) == 18 == log.read_bytes().count(b"GSA")
    proc = _x6wd("replay", str(log), "--sky", "--rate", "5", "--speed", "0")
    assert proc.returncode == 0, proc.stderr
    times = [float(x.split()[0][2:]) for x in proc.stdout.splitlines()]
    assert len(times) == 18 and times[-1] == pytest.approx(3.4)
    clock = VirtualClock()
    port = ReplayPort(log, speed=1, rate_hz=5, clock=clock, sleep=clock.sleep)
    got = b""
    while chunk := port.read(4096):
        got += chunk
    assert got == log.read_bytes() and clock() - 1000.0 == pytest.approx(3.4)


@pytest.mark.parametrize(
    "name",
    [
        "quectel-l76k-dual.log",  # 3 GNGSA by system id, GSV in groups per signal id
        "ublox-8.log",  # 2 GNGSA back to back (NMEA 4.0: no system id)
        "skytraq-dgps.log",  # GPGSA and BDGSA
        "isync.log",
        "nl402u.log",  # a banner of 7 TXT at start-up
        "nl551e.log",
    ],
)
def test_untimed_epochs_of_real_logs_are_their_rmc_epochs(name: str, tmp_path: Path) -> None:
    log = NMEA / name
    rmc = sum(1 for x in log.read_bytes().splitlines() if x[3:6] == b"RMC")
    assert _epochs(_untimed(log, tmp_path / name)) == rmc
