"""NMEA sentences without a ``*hh`` checksum, as older receivers and some loggers write them.

gpsd's packet lexer verifies a checksum only where a ``*`` is present, so it decodes gpsd's
HP 58534A regression log (comment lines, then ``$GPGGA,...`` without checksums);
``x6wd decode`` said "no NMEA sentence" and exited 2, and the gap tool could not read it.
Now ``NmeaFramer(accept_unchecksummed=True)`` (``x6wd decode`` unless ``--strict``, the gap
tool's NMEA reader) takes such a complete, well-formed line, in a stream that carried no
checksum before it; the robot's daemon stays strict. tests/data/gap_logs/README.md says
where the log and gpsd's .chk come from.
"""

from __future__ import annotations

import json
import subprocess
import sys
from datetime import datetime, timedelta
from pathlib import Path

import pytest

from drivers.gps_io import GpsReader
from drivers.gps_nmea import GpsDecoder, NmeaFramer
from drivers.nmea import checksum
from x6wd.app import cli
from x6wd.gap.io import read_track

DATA = Path(__file__).resolve().parent / "data"
HP58534A = DATA / "gap_logs" / "hp58534a.log"
GPSD_CHK = DATA / "gap_logs" / "hp58534a.log.chk"
GGA = b"$GPGGA,222449,3349.0337,S,01843.9282,E,1,07,02.31,000115.4,M,0033.3,M,,"
GPS_WEEKS_1024 = timedelta(weeks=1024)


def _with_sum(line: bytes) -> str:
    return f"{line.decode()}*{checksum(line[1:]):02X}"


def _decode(capsys: pytest.CaptureFixture[str], *argv: str) -> tuple[int, list[str], str]:
    code = cli.main(["decode", *argv])
    captured = capsys.readouterr()
    return code, captured.out.splitlines(), captured.err


def _iso(text: str) -> datetime:
    return datetime.fromisoformat(text.replace("Z", "+00:00"))


def test_the_hp58534a_log_decodes_as_gpsd_decodes_it(capsys: pytest.CaptureFixture[str]) -> None:
    code, lines, err = _decode(capsys, str(HP58534A))
    assert code == 0, err
    assert "no NMEA sentence" not in err
    assert "sentences=13 decoded=13 " in err and "unchecksummed=13 " in err
    assert "framing_errors=0 " in err
    objs = [json.loads(x) for x in lines]
    ours = [o for o in objs if o["class"] == "TPV"]
    gpsd = [
        json.loads(x) for x in GPSD_CHK.read_text().splitlines() if x.startswith('{"class":"TPV"')
    ]
    assert len(gpsd) == 2 and len(ours) == len(gpsd)
    # The tolerances of tests/test_decode.py: gpsd prints 9 decimals (1e-9 deg), 4 for
    # heights. Its first TPV has no time (the GGA comes before the epoch's ZDA; this
    # decoder holds the GGA for the epoch's date); its second's time is the ZDA's date
    # 2010-10-25 plus 1024 GPS weeks (gpsd 3.20's rollover guess for a date before its
    # build), the same second of the day.
    for o, g in zip(ours, gpsd, strict=True):
        assert o["mode"] == g["mode"] == 3
        assert o["lat"] == pytest.approx(g["lat"], abs=1e-9)
        assert o["lon"] == pytest.approx(g["lon"], abs=1e-9)
        assert o["altMSL"] == pytest.approx(g["altMSL"], abs=1e-4)
        assert o["altHAE"] == pytest.approx(g["altHAE"], abs=1e-4)
        assert o["geoidSep"] == pytest.approx(g["geoidSep"], abs=1e-3)
    assert "time" not in gpsd[0]
    assert [o["time"] for o in ours] == ["2010-10-25T22:24:49.000Z", "2010-10-25T22:24:50.000Z"]
    assert _iso(ours[1]["time"]) + GPS_WEEKS_1024 == _iso(gpsd[1]["time"])
    # gpsd's .chk holds no SKY for this log; ours lists each complete GSV group's 9 satellites
    skies = [o for o in objs if o["class"] == "SKY"]
    assert [s["nSat"] for s in skies] == [9, 9]


def test_decode_strict_refuses_them(capsys: pytest.CaptureFixture[str]) -> None:
    code, lines, err = _decode(capsys, "--strict", str(HP58534A))
    assert code == 2 and lines == []
    assert "framing_errors=13 unchecksummed=0 " in err
    assert "no NMEA sentence or x6wd record in" in err


def test_the_daemon_refuses_them() -> None:
    """The robot's decoder (the daemon's GpsReader, as x6wd/app/daemon.py builds it, with
    its default decoder) stays strict."""

    def no_port() -> None:
        raise OSError("not opened in this test")

    reader = GpsReader(no_port, stale_s=2.0)  # type: ignore[arg-type]
    for decoder in (GpsDecoder(), reader.decoder):
        records = decoder.feed(HP58534A.read_bytes(), 0.0) + decoder.flush()
        counters = decoder.counters
        assert records == []
        assert counters.sentences == 0 and counters.unchecksummed == 0
        assert counters.framing_errors == 13
    assert NmeaFramer().feed(GGA + b"\r\n") == []


@pytest.mark.parametrize("ending", [b"\r\n", b"\n", b"\r", b"  \r\n"])
def test_a_complete_line_takes_its_computed_checksum(ending: bytes) -> None:
    framer = NmeaFramer(accept_unchecksummed=True)
    frames = framer.feed(GGA + ending)
    assert [f.text for f in frames] == [_with_sum(GGA)]  # type: ignore[union-attr]
    c = framer.counters
    assert (c.sentences, c.unchecksummed, c.framing_errors) == (1, 1, 0)


def test_cut_long_and_bad_lines_stay_errors() -> None:
    framer = NmeaFramer(accept_unchecksummed=True)
    cases = [
        GGA[:40] + b"$GPZDA,222449,25,10,2010,+00,00\r\n",  # cut off by a new '$'
        b"$GPTXT," + b"A" * 121 + b"\r\n",  # 128 characters: 131 with its checksum
        GGA + b"*G1\r\n",  # a '*' without two hex digits
        GGA + b"*1\r\n",
        b"$GP,GGA,1\r\n",  # no address
        b"$gpgga,1\r\n",
        GGA[:30] + b"\xe9" + GGA[31:] + b"\r\n",  # not ASCII
    ]
    for data in cases:
        framer = NmeaFramer(accept_unchecksummed=True)
        frames = framer.feed(data)
        texts = [f.text for f in frames]  # type: ignore[union-attr]
        assert texts in ([], [_with_sum(b"$GPZDA,222449,25,10,2010,+00,00")]), data
        assert framer.counters.framing_errors == 1, data
        assert framer.counters.unchecksummed == len(texts), data
    # 127 characters: 130 with its checksum, the cap
    longest = b"$GPTXT," + b"A" * 120
    assert [f.text for f in NmeaFramer(accept_unchecksummed=True).feed(longest + b"\n")] == [  # type: ignore[union-attr]
        _with_sum(longest)
    ]
    # a wrong checksum stays a checksum failure
    framer = NmeaFramer(accept_unchecksummed=True)
    assert framer.feed(_with_sum(GGA)[:-2].encode() + b"00\r\n") == []
    assert framer.counters.checksum_failures == 1 and framer.counters.unchecksummed == 0
    # a line not yet ended is held, not taken
    framer = NmeaFramer(accept_unchecksummed=True)
    assert framer.feed(GGA) == [] and framer.pending_bytes == len(GGA)
    assert [f.text for f in framer.feed(b"\r\n")] == [_with_sum(GGA)]  # type: ignore[union-attr]


def test_in_a_stream_with_checksums_a_line_without_one_is_a_cut_line() -> None:
    """gpsd's ublox-8 log ends in ``$GNRMC,001053.00,A,...,W,0.``: the rest of a checksummed
    stream's line was lost. Taken, it made a fix gpsd's output does not have."""
    checked = _with_sum(b"$GPZDA,222449,25,10,2010,+00,00").encode() + b"\r\n"
    for data in (checked + GGA + b"\r\n", checked * 40 + GGA + b"\r\n"):
        for size in (len(data), 7):
            framer = NmeaFramer(accept_unchecksummed=True)
            frames = []
            for i in range(0, len(data), size):
                frames += framer.feed(data[i : i + size])
            assert len(frames) == data.count(b"*")
            assert framer.counters.framing_errors == 1 and framer.counters.unchecksummed == 0
    # a stream that starts without checksums: taken until a checksummed line comes
    framer = NmeaFramer(accept_unchecksummed=True)
    frames = framer.feed(GGA + b"\r\n" + checked + GGA + b"\r\n")
    assert [f.text for f in frames] == [_with_sum(GGA), checked.decode().strip()]  # type: ignore[union-attr]
    assert framer.counters.unchecksummed == 1 and framer.counters.framing_errors == 1


def test_the_gap_reader_reads_the_log() -> None:
    track = read_track(HP58534A)
    assert len(track) == 2
    assert track.lat_deg[0] == pytest.approx(-(33 + 49.0337 / 60), abs=1e-9)
    assert any("13 NMEA sentences without a checksum" in note for note in track.notes)


def test_the_gap_tool_names_the_log_too_short(tmp_path: Path) -> None:
    done = subprocess.run(
        [sys.executable, "-m", "x6wd", "gap", "--real", str(HP58534A), "--out",
         str(tmp_path / "out"), "--no-figures"],
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert done.returncode == 2
    assert "too short for a gap diagnosis: 2 epochs" in done.stderr, done.stderr
