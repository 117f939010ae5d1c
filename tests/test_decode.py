"""`x6wd decode`: NMEA logs and recordings -> gpsd-style TPV/SKY JSON lines."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from x6wd.app import cli

NMEA_DIR = Path(__file__).resolve().parent / "data" / "nmea"
ROOT = Path(__file__).resolve().parent.parent
LEA5H = NMEA_DIR / "ublox-lea-5h.log"


def _run(capsys: pytest.CaptureFixture[str], *argv: str) -> tuple[int, list[str], str]:
    code = cli.main(["decode", *argv])
    captured = capsys.readouterr()
    return code, captured.out.splitlines(), captured.err


def _gpsd(name: str, cls: str) -> list[dict]:
    text = (NMEA_DIR / "chk" / f"{name}.chk").read_text(errors="replace")
    return [json.loads(x) for x in text.splitlines() if x.startswith(f'{{"class":"{cls}"')]


def test_log_to_compact_tpv_and_sky_matching_gpsd(capsys: pytest.CaptureFixture[str]) -> None:
    code, lines, err = _run(capsys, str(LEA5H))
    assert code == 0 and lines
    log = LEA5H.read_bytes()
    for line in lines:
        assert ": " not in line and ", " not in line and "null" not in line
    objs = [json.loads(x) for x in lines]
    assert {o["class"] for o in objs} == {"TPV", "SKY"}
    gpsd_last = {o["time"]: o for o in _gpsd(LEA5H.name, "TPV") if o.get("mode", 0) >= 2}
    tpvs = [o for o in objs if o["class"] == "TPV" and "lat" in o]
    assert len(tpvs) >= len(gpsd_last)
    matched = 0
    for o in tpvs:
        g = gpsd_last.get(o["time"])
        if g is None:
            continue
        matched += 1
        assert o["mode"] == g["mode"]
        assert o["lat"] == pytest.approx(g["lat"], abs=1e-9)
        assert o["lon"] == pytest.approx(g["lon"], abs=1e-9)
        hhmmss = o["time"][11:19].replace(":", "")
        if "altMSL" in o:
            assert o["altMSL"] == pytest.approx(g["altMSL"], abs=1e-4)
            assert o["altHAE"] == pytest.approx(g["altHAE"], abs=1e-4)
        else:  # an RMC-only epoch: gpsd repeats an older GGA's altitude, this omits it
            assert f"$GPGGA,{hhmmss}".encode() not in log
        if "speed" in o:  # gpsd carries an older RMC's speed over a GGA without RMC
            assert o["speed"] == pytest.approx(g["speed"], abs=1e-3)
        else:
            assert f"$GPRMC,{hhmmss}".encode() not in log
        assert ("track" in o) == ("track" in g)  # empty course at rest: omitted, not null
    assert matched == len(gpsd_last)
    # Sky reports: same satellites and used flags as gpsd's full SKY of the same cycle.
    ours = [o for o in objs if o["class"] == "SKY"]
    theirs = [o for o in _gpsd(LEA5H.name, "SKY") if "satellites" in o]
    assert len(ours) == len(theirs)
    for a, b in zip(ours, theirs, strict=True):
        assert (a["nSat"], a["uSat"], a["hdop"], a["pdop"], a["vdop"]) == (
            b["nSat"],
            b["uSat"],
            b["hdop"],
            b["pdop"],
            b["vdop"],
        )
        strip = [
            {k: s[k] for k in ("PRN", "el", "az", "ss", "used") if k in s} for s in b["satellites"]
        ]
        assert a["satellites"] == strip
    assert f"{LEA5H}: sentences=164 " in err


def test_recording_decodes_like_the_raw_log(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from x6wd.core import recorder
    from x6wd.core.records import Attitude

    rec_path = tmp_path / "run.jsonl"
    with recorder.Recorder(rec_path) as rec:
        for k, line in enumerate(LEA5H.read_bytes().splitlines()):
            if line.startswith(b"$"):
                rec.record_nmea(line, t_mono=float(k))
            if k % 10 == 0:
                rec.record_attitude(Attitude(float(k), 90.0, 0.0, 0.0))
    code, from_rec, err_rec = _run(capsys, str(rec_path))
    code_raw, from_raw, _ = _run(capsys, str(LEA5H))
    assert code == code_raw == 0
    assert from_rec == from_raw
    assert "sentences=164 " in err_rec


def test_stdin_dash_and_binary_tolerated(tmp_path: Path) -> None:
    data = (NMEA_DIR / "quectel-l76k-dual.log").read_bytes()
    proc = subprocess.run(
        [sys.executable, "-m", "x6wd", "decode", "-"],
        input=data,
        capture_output=True,
        cwd=ROOT,
        timeout=60,
        check=False,
    )
    assert proc.returncode == 0, proc.stderr
    objs = [json.loads(x) for x in proc.stdout.decode().splitlines()]
    assert sum(o["class"] == "TPV" for o in objs) >= 100
    assert b"-: sentences=2080 " in proc.stderr
    assert b"framing_errors=" in proc.stderr


def test_missing_file_reported_and_others_decoded(capsys: pytest.CaptureFixture[str]) -> None:
    code, lines, err = _run(capsys, "/nonexistent/x.log", str(LEA5H), "--no-sky")
    assert code == 1
    assert "cannot open /nonexistent/x.log" in err
    assert lines and all(json.loads(x)["class"] == "TPV" for x in lines)
