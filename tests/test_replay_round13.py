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


def _count(log: Path, sentence: bytes) -> int:
    return sum(1 for x in log.read_bytes().splitlines() if x.lstrip(b"$")[2:5] == sentence)


@pytest.mark.parametrize(
    ("name", "per_epoch", "before_first"),
    [
        # $$-doubled sentences, GNGSA twice per system (1,3,4,1,3,4), $PSTM... banners; it
        # starts with the sky of an epoch before the first RMC's (a restart between): +1
        ("st-teseo-liv4f.log", b"RMC", 1),
        ("ublox-zed-f9p_hpg1.11.log", b"GGA", 0),  # RMC on late; UBX binary holding "$"
        ("ublox-lea-4h.log", b"RMC", 0),
        ("ublox-lea-5q.log", b"RMC", 0),
        ("triton400.log", b"RMC", 0),
    ],
)
def test_untimed_epochs_of_more_real_logs(
    name: str, per_epoch: bytes, before_first: int, tmp_path: Path
) -> None:
    """Times removed, the ST Teseo's 12 epochs were 175 ($$GNGSA read as "$GNGS": no system
    id, each part of a GSV an epoch; the second GNGSA,1 and each $PSTMVER a new epoch)."""
    log = NMEA / name
    assert _epochs(_untimed(log, tmp_path / name)) == _count(log, per_epoch) + before_first


def test_teseo_sky_only_replays_over_its_epochs(tmp_path: Path) -> None:
    """docs/logview.md's example (GSA and GSV only) of the ST Teseo log: replay --sky
    stamped t up to 159 s for its 12 s."""
    log = tmp_path / "teseo_sky.log"
    lines = (NMEA / "st-teseo-liv4f.log").read_bytes().splitlines(keepends=True)
    log.write_bytes(b"".join(x for x in lines if x[:1] == b"$" and (b"GSA" in x or b"GSV" in x)))
    out = io.StringIO()
    replay_file(str(log), speed=0, sky=True, out=out, err=io.StringIO())
    times = [float(x.split()[0][2:]) for x in out.getvalue().splitlines()]
    assert times[-1] == 12.0 and len(set(times)) == 13


def test_untimed_epochs_by_kind_of_receiver(tmp_path: Path) -> None:
    """An epoch ends where a sentence comes again after another type: not in a run of one
    type (GSA per system twice), not at a proprietary sentence; a log of one type alone
    (GSV only) still ends an epoch at each repeat, and a GPGSA right after itself does."""

    def epochs(*bodies: str) -> list[float]:
        log = tmp_path / "u.nmea"
        lines = (x.encode() for x in bodies)
        log.write_bytes(b"".join(b"$%s*%02X\r\n" % (x, reduce(xor, x)) for x in lines))
        return [t for t, _ in nmea_file_chunks(log)]

    gsa = [f"GNGSA,A,3,01,,,,,,,,,,,,2.5,1.7,1.8,{s}" for s in (1, 3, 4, 1, 3, 4)]
    epoch = [*gsa, "GPGSV,1,1,01,16,71,196,27,1", "PSTMVER,1", "PUBX,00", "GNVTG,1,T,,M,0,N,0,K,A"]
    assert epochs(*epoch, *epoch, *epoch) == [0.0] * 10 + [1.0] * 10 + [2.0] * 10
    assert epochs(*("$" + x for x in epoch), *("$" + x for x in epoch)) == [0.0] * 10 + [1.0] * 10
    gsv = ["GPGSV,1,1,01,16,71,196,27", "GLGSV,1,1,01,70,71,196,27"]
    assert epochs(*gsv, *gsv, *gsv) == [0, 0, 1, 1, 2, 2]
    assert epochs("GPGSA,A,1", "GPGSV,1,1,00", "GPGSA,A,1", "GPGSA,A,1") == [0, 0, 1, 2]


def test_replay_of_a_cr_cr_lf_log_names_the_files_line(tmp_path: Path) -> None:
    """Each CR was a line end: bt451's step back on line 112 was said at line 223."""
    log = tmp_path / "bt451_crcrlf.log"
    log.write_bytes(
        (NMEA / "bt451.log").read_bytes().replace(b"\r\n", b"\n").replace(b"\n", b"\r\r\n")
    )
    assert log.read_bytes().count(b"\n") == 156
    err = io.StringIO()
    replay_file(str(log), speed=0, out=io.StringIO(), err=err)
    assert "goes back 3122.5 s at line 112, t=-3118.500" in err.getvalue(), err.getvalue()
    with open(log, "rb") as f:
        assert [x[-3:] for x in _file_lines(f)] == [b"\r\r\n"] * 156  # one line each


def test_file_lines_across_blocks(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """CR CR LF cut anywhere by the blocks read is one line end; a CR alone still ends one."""
    import x6wd.core.recorder as recorder

    lines = [b"a\r\r\n", b"b\r", b"c\r\n", b"d\n", b"\r\r\n", b"e\r"]
    for block in range(1, 6):
        monkeypatch.setattr(recorder, "_BLOCK_BYTES", block)
        assert list(_file_lines(io.BytesIO(b"".join(lines)))) == lines


def test_replay_at_speed_0_says_forward_jumps_too() -> None:
    """gp-320fw's cold boot log jumps 4 h 25 min forward at line 53 (x6wd plot says so): at
    --speed 0 replay said its steps back only. (Line 48's garbled GGA said it first until
    round 21: a sentence failing its checksum no longer sets the clock.)"""
    err = io.StringIO()
    replay_file(str(NMEA / "gp-320fw-2019-04-07-coldboot.log"), speed=0, out=io.StringIO(), err=err)
    said = [x for x in err.getvalue().splitlines() if "forward" in x]
    assert said == [
        "x6wd replay: the recorded time jumps 15882 s forward at line 53, t=-226.030",
        "x6wd replay: the recorded time jumps 268 s forward at line 86, t=43.970",
    ]


def test_replay_of_many_forward_jumps_says_the_first_and_counts_all(tmp_path: Path) -> None:
    """A fix every 2 min: each a jump of over 60 s, said at most MAX_BACKS_SAID times."""
    log = tmp_path / "slow.nmea"
    bodies = [b"GPGGA,12%02d00.00,,,,,0,00,99.99,,,,,," % m for m in range(0, 60, 2)]
    log.write_bytes(b"".join(b"$%s*%02X\r\n" % (x, reduce(xor, x)) for x in bodies))
    err = io.StringIO()
    replay_file(str(log), speed=0, out=io.StringIO(), err=err)
    said = [x for x in err.getvalue().splitlines() if "forward" in x]
    assert len(said) == MAX_BACKS_SAID + 1 and "jumps 120 s forward at line 2, t=120.000" in said[0]
    assert said[-1].endswith("jumps forward 29 times in all (19 more than said)")


def test_replay_of_standard_input_says_it_reads_files(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # round 21's audit: "cannot open -: [Errno 2] No such file or directory: '-'"
    from x6wd.app.cli import main

    monkeypatch.chdir(tmp_path)
    assert main(["replay", "-"]) == 2
    assert "x6wd replay reads a file, not standard input ('-')" in capsys.readouterr().err


def test_a_long_stretch_without_a_line_end_is_read_in_linear_time(tmp_path: Path) -> None:
    """An outside audit (round 22): 256 KiB of zero bytes after a log (an SD card's tail after
    a power cut) hung ``plot`` and ``replay`` for ~20 min: the line regex was tried at every
    offset of the carried text, each try scanning to its end (16 kB took 0.35 s, 64 kB 43 s).
    Through the real CLI on 1 MiB of it; the bound is the subprocess's timeout (60 s), which
    the quadratic reading exceeded by hours."""
    log = tmp_path / "zerotail.nmea"
    good = (NMEA / "ublox-8.log").read_bytes()
    log.write_bytes(good + b"\0" * (1 << 20) + good[:2000])
    done = _x6wd("replay", str(log), "--speed", "0")
    assert done.returncode in (0, 1), done.stderr
    assert "Traceback" not in done.stderr
    with open(log, "rb") as f:  # the zeros are one overlong line, cut at _MAX_LINE_BYTES
        lines = list(_file_lines(f))
    assert b"".join(lines) == log.read_bytes()
    assert max(map(len, lines)) <= (1 << 20) + (64 << 10) + 2000
