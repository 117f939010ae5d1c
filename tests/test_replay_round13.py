"""Round 13: epochs of an NMEA log without times (a multi-part GSV is one epoch), and
`x6wd replay` saying where the recorded time goes back; on gpsd's real logs. `x6wd replay`
of a run whose first parts retention deleted says so."""

from __future__ import annotations

import io
import json
import os
import re
import subprocess
import sys
from datetime import UTC, datetime, timedelta
from functools import reduce
from operator import xor
from pathlib import Path

import pytest

from tests.test_recorder import ROOT, VirtualClock
from x6wd.app import logview
from x6wd.app.replay import MAX_BACKS_SAID, replay_file
from x6wd.core.recorder import (
    Recorder,
    ReplayPort,
    _file_lines,
    _sentence_utc_s,
    nmea_file_chunks,
    paced,
)

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


def test_paced_tells_each_step_back_before_its_chunk() -> None:
    clock = VirtualClock()
    chunks = [(0.0, b"a"), (1.0, b"b"), (-5.0, b"c"), (-4.0, b"d")]
    backs: list[tuple[float, float]] = []
    out = list(
        paced(
            iter(chunks),
            1.0,
            clock=clock,
            sleep=clock.sleep,
            on_back=lambda t, step: backs.append((t, step)),
        )
    )
    assert out == chunks and backs == [(-5.0, -6.0)]
    assert clock() - 1000.0 == pytest.approx(2.0)  # played on without a pause


def test_replay_says_where_the_time_goes_back() -> None:
    """bt451.log holds two sessions, 15:25 then 14:33 (x6wd plot: "line 112: time went
    back 3122.5 s"): replay printed t=-3118.500 and said nothing."""
    proc = _x6wd("replay", str(NMEA / "bt451.log"), "--speed", "0")
    assert proc.returncode == 0, proc.stderr
    said = [x for x in proc.stderr.splitlines() if "goes back" in x]
    assert len(said) == 1 and "back 3122.5 s at line 112, t=-3118.500" in said[0], proc.stderr
    assert "t=-3118.500 utc=2009-12-09T14:33:06" in proc.stdout


def test_replay_of_many_steps_back_says_the_first_and_counts_all(tmp_path: Path) -> None:
    """Epochs written in swapped pairs step back every other epoch: the first few are said,
    the rest counted, not one stderr line each."""
    log = tmp_path / "swapped.nmea"
    seconds = [s for pair in range(0, 60, 2) for s in (pair + 1, pair)]
    bodies = [b"GPGGA,1200%02d.00,,,,,0,00,99.99,,,,,," % s for s in seconds]
    log.write_bytes(b"".join(b"$%s*%02X\r\n" % (x, reduce(xor, x)) for x in bodies))
    err = io.StringIO()
    replay_file(str(log), speed=0, out=io.StringIO(), err=err)
    said = [x for x in err.getvalue().splitlines() if "goes back" in x]
    assert len(said) == MAX_BACKS_SAID + 1 and "at line 2, t=-1.000" in said[0]
    assert said[-1].endswith("goes back 30 times in all (20 more than said)")


def _nmea_run(directory: Path, start: datetime, n: int) -> list[Path]:
    """A daemon's run in parts (a GGA every 0.25 s, by a recorder's clock from ``start``)."""
    now = [0.0]
    rec = Recorder.in_dir(
        directory, max_bytes=4_000, utc_clock=lambda: start + timedelta(seconds=now[0])
    )
    with rec:
        for k in range(n):
            now[0] = 0.25 * k
            utc = start + timedelta(seconds=now[0])
            body = b"GPGGA,%s,5145.1200,N,00115.4600,W,1,08,0.9,65.0,M,47.0,M,," % (
                utc.strftime("%H%M%S.%f")[:9].encode()
            )
            rec.record_nmea(b"$%s*%02X" % (body, reduce(xor, body)), 5000.0 + now[0])
        rec.record_event("shutdown", 5000.0 + now[0])
    return list(rec.paths)


def test_replay_of_a_run_whose_parts_retention_deleted_says_so(tmp_path: Path) -> None:
    """Retention deletes a run's oldest part first: x6wd plot says so, x6wd replay replayed
    from the first part left (45 s into a HIL run) as if that were the run's start, silent."""
    start = datetime(2026, 12, 6, 10, 11, 4, 250_000, tzinfo=UTC)
    parts = _nmea_run(tmp_path, start, 200)
    assert len(parts) > 3 and parts[0].name == "x6wd-20261206T101104Z.jsonl"

    def replay(path: Path) -> list[str]:
        err = io.StringIO()
        replay_file(str(path), speed=0, out=io.StringIO(), err=err)
        return [x for x in err.getvalue().splitlines() if "gone" in x]

    assert replay(tmp_path) == []  # the whole run: nothing said
    parts[2].unlink()  # a middle part
    assert replay(tmp_path) == [f"x6wd replay: {parts[0]}: part {parts[2].name} gone (retention?)"]
    parts[0].unlink()  # and the first: the directory, the first part's name, the part left
    first_utc = json.loads(parts[1].read_text().splitlines()[0])["t_utc"]
    lost_s = (datetime.fromisoformat(first_utc) - start.replace(microsecond=0)).total_seconds()
    assert lost_s > 5
    for path in (tmp_path, parts[0], parts[1]):
        (said,) = replay(path)
        assert said.startswith(
            f"x6wd replay: {parts[1] if path == tmp_path else path}: parts"
            f" {parts[0].name}, {parts[2].name} gone (retention?): the run began at"
            " 2026-12-06T10:11:04+00:00 (its name), about "
        ), said
        m = re.search(r"about ([0-9.]+) s before the first record read", said)
        assert m is not None and float(m[1]) == pytest.approx(lost_s, abs=0.051), said
    # worded as x6wd plot's line, up to what the plot draws
    note = logview.missing_parts_note(logview.load(parts[1]))
    assert said.split(": ", 2)[2].split(", and that start")[0] == note.split(", and that")[0]
