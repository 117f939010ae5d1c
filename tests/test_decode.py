"""`x6wd decode`: NMEA logs and recordings -> gpsd-style TPV/SKY JSON lines."""

from __future__ import annotations

import io
import json
import subprocess
import sys
from datetime import UTC, timedelta, timezone
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from drivers.gps_nmea import GpsDecoder
from x6wd.app import cli, decode
from x6wd.app.decode import ReportEncoder, report_lines
from x6wd.app.gpsd import sky_obj, tpv_obj
from x6wd.core.records import GpsFix, GpsSky, SatInfo

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
            {k: s[k] for k in ("PRN", "gnssid", "svid", "el", "az", "ss", "used") if k in s}
            for s in b["satellites"]
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
    assert "sentences=164 " in err_rec and err_rec.endswith(" bad_recording_lines=0\n")
    # torn lines (a copy cut short, an editor's damage): skipped and counted, never silent
    lines = rec_path.read_bytes().splitlines(keepends=True)
    torn = [ln[: len(ln) // 2] + b"\n" if i % 7 == 3 else ln for i, ln in enumerate(lines)]
    n_torn = sum(i % 7 == 3 for i in range(len(lines)))
    rec_path.write_bytes(b"".join(torn) + b'{"bad json\n')
    code, _out, err = _run(capsys, str(rec_path))
    assert code == 0 and err.endswith(f" bad_recording_lines={n_torn + 1}\n"), err
    proc = decode_stdin(rec_path.read_bytes())
    assert proc.returncode == 0 and f" bad_recording_lines={n_torn + 1}\n" in proc.stderr.decode()


def test_a_split_recording_is_decoded_whole(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # The daemon splits a recording in parts ([recorder] max_file_mb): decode reads every
    # remaining part, as replay and plot do, also once retention deleted the first part.
    from x6wd.core import recorder

    whole, split = tmp_path / "whole.jsonl", tmp_path / "x6wd-20260101T000000Z.jsonl"
    for path, max_bytes in ((whole, None), (split, 4000)):
        with recorder.Recorder(path, max_bytes=max_bytes) as rec:
            for k, line in enumerate(LEA5H.read_bytes().splitlines()):
                rec.record_nmea(line, t_mono=float(k))
    assert len(rec.paths) > 3
    _, ref, _ = _run(capsys, str(whole))
    code, got, err = _run(capsys, str(split))
    assert code == 0 and got == ref and "sentences=164 " in err
    split.unlink()
    code, got, _ = _run(capsys, str(rec.paths[1]))
    # the same reports to the end (the first epochs lack the deleted part's GSA context)
    assert code == 0 and len(ref) > len(got) > len(ref) // 2 and got[-10:] == ref[-10:]


@pytest.mark.parametrize("damage", [b"\x93\xfe garbage\xff\n", b"\0" * 4096 + b"\n"])
def test_a_recording_with_a_damaged_first_line_is_still_one(
    damage: bytes, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # A card's garbage or a block of NULs on the first line: the format is told by the next
    # intact lines, the damaged line skipped and counted like any other, not the whole file
    # refused as "no NMEA sentence or x6wd record" (decode, replay) or "nothing to plot".
    from x6wd.app.logview import load
    from x6wd.app.replay import replay_file
    from x6wd.core import recorder

    good = tmp_path / "good.jsonl"
    with recorder.Recorder(good) as rec:
        for k, line in enumerate(LEA5H.read_bytes().splitlines()):
            rec.record_nmea(line, t_mono=float(k))
    path = tmp_path / "damaged.jsonl"
    path.write_bytes(damage + good.read_bytes())
    _, ref, _ = _run(capsys, str(good))
    code, got, err = _run(capsys, str(path))
    assert code == 0 and got == ref and err.endswith(" bad_recording_lines=1\n"), err
    proc = decode_stdin(path.read_bytes())
    assert proc.returncode == 0 and proc.stdout.decode().splitlines() == ref
    counts = replay_file(str(path), speed=0, out=io.StringIO(), err=io.StringIO())
    assert counts["bad_lines"] == 1 and counts["fixes_printed"] > 0
    view = load(path)
    assert view.counts["bad_lines"] == 1 and view.counts["fixes"] == counts["fixes_printed"]


def decode_stdin(data: bytes) -> subprocess.CompletedProcess[bytes]:
    """``x6wd decode -`` as a process, ``data`` on its standard input."""
    return subprocess.run(
        [sys.executable, "-m", "x6wd", "decode", "-"],
        input=data,
        capture_output=True,
        cwd=ROOT,
        timeout=60,
        check=False,
    )


def test_stdin_dash_and_binary_tolerated(tmp_path: Path) -> None:
    proc = decode_stdin((NMEA_DIR / "quectel-l76k-dual.log").read_bytes())
    assert proc.returncode == 0, proc.stderr
    objs = [json.loads(x) for x in proc.stdout.decode().splitlines()]
    assert sum(o["class"] == "TPV" for o in objs) >= 100
    assert b"-: sentences=2080 " in proc.stderr
    assert b"framing_errors=" in proc.stderr


GPSPIPE_R = Path(__file__).resolve().parent / "data" / "gpspipe" / "lea-5h-gpspipe-r.log"


def test_gpspipe_r_capture_is_nmea_not_a_recording(
    capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    """``gpspipe -r`` writes gpsd's VERSION/DEVICES/WATCH JSON before the NMEA: such a
    file (and such stdin) is NMEA with noise, decoded like the NMEA alone."""
    data = GPSPIPE_R.read_bytes()
    assert data.startswith(b'{"class":"VERSION"')
    nmea_only = tmp_path / "nmea-only.log"
    nmea_only.write_bytes(b"".join(ln for ln in data.splitlines(True) if ln[:1] != b"{"))
    code, lines, err = _run(capsys, str(GPSPIPE_R))
    code_ref, ref, _ = _run(capsys, str(nmea_only))
    assert code == code_ref == 0 and "bad_recording_lines" not in err
    assert lines == ref and sum('"class":"TPV"' in x for x in lines) >= 8
    proc = decode_stdin(data)
    assert proc.returncode == 0 and proc.stdout.decode().splitlines() == ref


def test_missing_file_reported_and_others_decoded(capsys: pytest.CaptureFixture[str]) -> None:
    code, lines, err = _run(capsys, "/nonexistent/x.log", str(LEA5H), "--no-sky")
    assert code == 2
    assert "cannot open /nonexistent/x.log" in err
    assert lines and all(json.loads(x)["class"] == "TPV" for x in lines)


def _x6wd(*argv: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "x6wd", *argv], capture_output=True, text=True, timeout=60
    )


@pytest.mark.parametrize("command", ["decode", "replay"])
def test_an_input_in_which_nothing_decodes_is_exit_2_naming_the_file(
    command: str, tmp_path: Path
) -> None:
    noise = tmp_path / "noise.bin"
    noise.write_bytes(bytes(range(256)) * 8)
    junk = tmp_path / "junk.jsonl"  # looks like a recording: read as one
    junk.write_text('{"t_mono": 1,\nnot json\n')
    cases = {
        noise: "2048 bytes",
        junk: "2 lines",
        ROOT / "missions/default.gpx": "bytes",  # a mission file is not a log
    }
    more = ["--speed", "0"] if command == "replay" else []
    for path, what in cases.items():
        r = _x6wd(command, str(path), *more)
        assert r.returncode == 2, r.stderr
        assert f"{path}: no NMEA sentence or x6wd record in " in r.stderr, r.stderr
        assert what in r.stderr.splitlines()[-1], r.stderr
    # empty in, empty out; a log with some junk lines is decoded as usual
    empty = tmp_path / "empty.log"
    empty.write_bytes(b"")
    mixed = tmp_path / "mixed.log"
    mixed.write_bytes(b"junk\n" + LEA5H.read_bytes()[:4000] + b"\x00\xff junk\n")
    for path in (empty, mixed):
        r = _x6wd(command, str(path), *more)
        assert r.returncode == 0 and "no NMEA sentence" not in r.stderr, r.stderr
    if command == "decode":  # the other files are still decoded
        r = _x6wd("decode", str(noise), str(LEA5H), "--quiet")
        assert r.returncode == 2 and len(r.stdout.splitlines()) > 10, r.stderr


# --------------------------------------------------------------- the direct encoder
# `x6wd decode` writes its lines with ReportEncoder instead of json.dumps(tpv_obj/sky_obj);
# the text must be the same, character for character, as the plain path computed here.


def _plain(r: GpsFix | GpsSky) -> str:
    # the decoder writes the receiver's DOPs; the port adds the geometry's (test_gpsd_sky)
    obj = tpv_obj(r) if isinstance(r, GpsFix) else sky_obj(r, fill_dops=False)
    return json.dumps(obj, separators=(",", ":"))


@pytest.mark.parametrize("name", sorted(p.name for p in NMEA_DIR.glob("*.log")))
def test_encoder_writes_what_tpv_obj_and_sky_obj_give(name: str) -> None:
    dec = GpsDecoder(emit_sentences=False)
    data = (NMEA_DIR / name).read_bytes()
    records = [r for r in dec.feed(data, 0.0) + dec.flush() if isinstance(r, GpsFix | GpsSky)]
    records += records  # the second time every memo is warm
    assert list(report_lines(records)) == [_plain(r) for r in records]


_floats = st.one_of(
    st.none(),
    st.floats(allow_nan=True, allow_infinity=True),
    st.sampled_from([0.0, -0.0, 0.5, 1.25, 2.675, 1e-12, 99.99, 35.2, -1e300]),
)
_utcs = st.one_of(
    st.none(),
    st.datetimes(timezones=st.sampled_from([None, UTC, timezone(timedelta(hours=-5))])),
)
_fixes = st.builds(
    GpsFix,
    t_s=st.just(0.0),
    utc=_utcs,
    lat_deg=_floats,
    lon_deg=_floats,
    alt_m=_floats,
    quality=st.integers(0, 8),
    sats_used=st.none() | st.integers(0, 99),
    hdop=_floats,
    speed_mps=_floats,
    course_deg=_floats,
    valid=st.booleans(),
    mode=st.integers(0, 3),
    pdop=_floats,
    vdop=_floats,
    geoid_sep_m=_floats,
)
_sats = st.builds(
    SatInfo,
    prn=st.integers(0, 999),
    el_deg=_floats,
    az_deg=_floats,
    snr_dbhz=_floats,
    used=st.booleans(),
    gnssid=st.none() | st.integers(0, 7),
    svid=st.none() | st.integers(0, 999),
)
_skies = st.builds(
    GpsSky,
    t_s=st.just(0.0),
    satellites=st.lists(_sats, max_size=14).map(tuple),
    pdop=_floats,
    hdop=_floats,
    vdop=_floats,
    utc=_utcs,
)
_SHARED = ReportEncoder()  # memos carried from example to example: 0.0 after -0.0 etc.


@settings(max_examples=400, deadline=None)
@given(st.lists(st.one_of(_fixes, _skies), min_size=1, max_size=6))
def test_encoder_matches_the_plain_path_on_any_record(records: list[GpsFix | GpsSky]) -> None:
    records += records
    for r in records:
        line = _SHARED.tpv(r) if isinstance(r, GpsFix) else _SHARED.sky(r)
        assert line == _plain(r)


def test_encoder_memos_stay_bounded() -> None:
    enc = ReportEncoder()
    for k in range(3 * decode.MEMO_MAX):
        sat = SatInfo(k % 200, float(k % 90), float(k % 360), 30.0 + k % 20, k % 2 == 0)
        sky = GpsSky(0.0, (sat,), 1.0 + k, 2.0, 3.0)
        assert enc.sky(sky) == _plain(sky)
        fix = GpsFix(0.0, None, 1.0, 2.0, 10.0 + k, 1, 8, 1.0 + k, 0.1 * k, 1.0, True, 3, 2.0, 3.0)
        assert enc.tpv(fix) == _plain(fix)
        assert enc.largest_memo <= decode.MEMO_MAX
    assert enc.largest_memo > decode.MEMO_MAX // 2


def test_decode_starts_without_the_gpsd_server_module() -> None:
    # Start-up time: x6wd.app.gpsd brings asyncio and the configuration; the encoder has
    # its UERE from there, checked here.
    from x6wd.app import gpsd

    assert decode.UERE_M == gpsd.UERE_M
    code = (
        "import sys; from x6wd.app import cli;"
        f"cli.main(['decode', '--quiet', {str(LEA5H)!r}]);"
        "loaded = [m for m in ('asyncio', 'x6wd.app.gpsd') if m in sys.modules];"
        "print(loaded, file=sys.stderr)"
    )
    got = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert got.stdout.count('"class":"TPV"') > 10
    assert got.stderr.strip() == "[]"


def test_equal_values_in_different_groups_keep_their_own_text() -> None:
    """Altitudes, error estimates and DOPs share one memo: its key must tell them apart (an
    altitude of 99.99 once came back as the error estimates of an HDOP of 99.99)."""
    enc = ReportEncoder()
    first = GpsFix(0.0, None, 0.0, 0.0, 99.99, 1, 8, None, None, None, True, 3, None, None)
    second = GpsFix(0.0, None, 0.0, 0.0, None, 1, 8, 99.99, None, None, True, 3, None, None)
    for fix in (first, second, first, second):
        assert enc.tpv(fix) == _plain(fix)


_EDGES = [0.0, -0.0, 5e-10, -5e-10, 1e-3, -1e-3, 9.999e-4, 0.0005, 0.00049999, 2.675, 0.125]
_EDGES += [10.0 ** (15 - n) * s for n in (1, 2, 3, 4, 9) for s in (1.0, 0.9999999999, -1.0)]


@settings(max_examples=1500, deadline=None)
@given(
    st.one_of(
        st.floats(allow_nan=False, allow_infinity=False),
        st.floats(-200.0, 200.0),
        st.integers(-(10**9), 10**9).map(lambda k: (k + 0.5) / 10**4),  # ties at 4 digits
        st.sampled_from(_EDGES),
    ),
    st.sampled_from([1, 2, 3, 4, 9]),
)
def test_number_text_is_repr_of_round(v: float, ndigits: int) -> None:
    # _num_text writes most numbers with "%.{n}f" instead of repr(round(v, n)): same text.
    assert decode._num_text(v, ndigits) == repr(round(v, ndigits))


class _NoSlurp(io.BytesIO):
    """A pipe that fails a read of everything at once (what held a whole recording)."""

    def read(self, size: int | None = -1) -> bytes:
        assert size is not None and size > 0, "the whole input was read at once"
        return super().read(size)


def test_a_recording_from_a_pipe_is_read_a_chunk_at_a_time(tmp_path: Path) -> None:
    # An outside check: `x6wd decode -` of a 112 MB recording held 264 MB (by path: 23 MB).
    run = tmp_path / "run"
    assert cli.main(["sim", str(ROOT / "config/scenarios/open_field.toml"), "--duration", "60",
                     "--out", str(run), "--quiet"]) == 0  # fmt: skip
    data = (run / "recording.jsonl").read_bytes()
    want, got = io.StringIO(), io.StringIO()
    decode.decode_stream(io.BytesIO(data), want)
    decode.decode_stream(_NoSlurp(data), got)
    assert got.getvalue() == want.getvalue() and got.getvalue().count('"TPV"') >= 60


@pytest.mark.parametrize("repeat", [1, 40])  # 40: enough sentences for the bulk path
def test_a_gll_only_log_decodes_to_the_fixes_gpsdecode_reports(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], repeat: int
) -> None:
    """Round 21's audit: the LEA-5H's GLL sentences alone decoded to no fix at all (`decode`,
    `plot` and `calibrate gnss` lost the epochs), while gpsd reports each one (mode 2)."""
    from tests.conftest import require_program

    gpsdecode = require_program("gpsdecode")
    glls = [x for x in LEA5H.read_bytes().splitlines(keepends=True) if x.startswith(b"$GPGLL")]
    log = tmp_path / "gll.log"
    log.write_bytes(b"".join(glls) * repeat)
    code, lines, _err = _run(capsys, str(log))
    assert code == 0
    ours = [(d["mode"], d["lat"], d["lon"]) for d in map(json.loads, lines) if "lat" in d]
    done = subprocess.run([gpsdecode], input=log.read_bytes(), capture_output=True, check=True)
    gpsd = [
        (d["mode"], d["lat"], d["lon"])
        for d in map(json.loads, done.stdout.decode().splitlines())
        if d.get("class") == "TPV" and "lat" in d
    ]
    assert len(ours) == len(glls) * repeat  # one fix per GLL (the times repeat: epochs)
    assert {m for m, _, _ in ours} == {2}
    # gpsdecode reports every one but the stream's first (before it knows the device)
    assert ours[1:] == gpsd, (ours[:3], gpsd[:3])


def test_a_last_sentence_without_its_line_end_is_counted_as_skipped(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Round 21's audit: the LEA-5H log without its last LF decoded 163 of 164 sentences and
    said nothing (gpsd drops that sentence too); now its bytes are counted as skipped."""
    whole = LEA5H.read_bytes()
    assert whole.endswith(b"\n") and not whole.endswith(b"\r\n")
    cut = tmp_path / "cut.log"
    cut.write_bytes(whole[:-1])
    last = whole[:-1].rsplit(b"\n", 1)[1]
    _code, _lines, said_whole = _run(capsys, str(LEA5H))
    _code, _lines, said_cut = _run(capsys, str(cut))

    def skipped(err: str) -> int:
        return int(err.rsplit("skipped_bytes=", 1)[1].split()[0])

    assert "sentences=163 " in said_cut and "sentences=164 " in said_whole
    assert skipped(said_cut) == skipped(said_whole) + len(last)
