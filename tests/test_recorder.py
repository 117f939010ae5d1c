"""Flight recorder, its reader, paced replay, ReplayPort and `x6wd replay`, on real logs."""

from __future__ import annotations

import functools
import json
import operator
import os
import re
import signal
import subprocess
import sys
from datetime import UTC, datetime
from pathlib import Path

import numpy as np
import pytest

from drivers.gps_nmea import GpsDecoder
from x6wd.app.cli import main as cli_main
from x6wd.core.errors import DeviceUnavailable, ParseError
from x6wd.core.recorder import (
    _ENCODE,
    RECORD_TYPES,
    ReadStats,
    Record,
    Recorder,
    ReplayPort,
    decode_record,
    is_recording,
    looks_like_recording,
    nmea_file_chunks,
    paced,
    read_recording,
    read_recording_parts,
    recording_parts,
    replay_records,
    to_jsonable,
    unknown_fields,
)
from x6wd.core.recorder import _flat_json as direct_json
from x6wd.core.records import (
    Attitude,
    GpsFix,
    GpsSky,
    Mode,
    MotorCommand,
    NavState,
    SatInfo,
    StateChange,
    Telemetry,
    WheelOdometry,
)

ROOT = Path(__file__).resolve().parent.parent
DATA = ROOT / "tests" / "data" / "recorder"
LEA5H = DATA / "ublox-lea-5h.log"
NL402U = DATA / "nl402u.log"


class VirtualClock:
    """Wall time that only moves when replay sleeps."""

    def __init__(self) -> None:
        self.now_s = 1000.0

    def __call__(self) -> float:
        return self.now_s

    def sleep(self, dt_s: float) -> None:
        assert dt_s >= 0
        self.now_s += dt_s


def fixes_of(data: bytes) -> list[GpsFix]:
    dec = GpsDecoder(emit_sentences=False)
    out = [r for r in dec.feed(data, 0.0) if isinstance(r, GpsFix)]
    return out + [r for r in dec.flush() if isinstance(r, GpsFix)]


def key(fixes: list[GpsFix]) -> list[tuple[object, ...]]:
    return [(f.utc, f.lat_deg, f.lon_deg, f.valid, f.mode) for f in fixes]


def record_log(path: Path, log: Path) -> int:
    """Record every line of an NMEA log as nmea records, 0.1 s apart; return the count."""
    n = 0
    with Recorder(path) as rec:
        for line in log.read_bytes().splitlines():
            if line.startswith(b"$"):
                rec.record_nmea(line, 50.0 + 0.1 * n)
                n += 1
    return n


# --- writing and reading ----------------------------------------------------------------------


def test_every_record_type_round_trips(tmp_path: Path) -> None:
    utc = datetime(2026, 11, 22, 4, 43, 12, 250000, tzinfo=UTC)
    path = tmp_path / "r.jsonl"
    fix = GpsFix(3.0, utc=utc, lat_deg=51.9, lon_deg=4.57, valid=True, mode=3, hdop=1.2)
    sky = GpsSky(3.5, (SatInfo(5, 40.0, 120.0, 38.0, True),), pdop=1.9)
    tel = Telemetry(4.0, Mode.RUNNING, NavState.TURN_LEFT, theta_deg=float("nan"))
    with Recorder(path, fsync_interval_s=0.0, utc_clock=lambda: utc) as rec:
        rec.record_nmea("$GPGGA,1*00\r\n", 1.0)
        rec.record_attitude(Attitude(2.0, 359.9, -3.0, 4.0))
        rec.record_motor(MotorCommand(2.5, 60.0, -40.0, "turn"))
        rec.record_state(StateChange(2.75, "STRAIGHT", "TURN_LEFT", "theta"))
        rec.record_fix(fix)
        rec.record_sky(sky)
        rec.record_telemetry(tel)
        rec.record_event("start", 5.0, version="0.1.0")
        rec.record_odometry(WheelOdometry(5.5, 4300, -12, 7))
        assert rec.records_written == 9
    stats = ReadStats()
    recs = list(read_recording(path, stats=stats))
    assert [r.type for r in recs] == [
        "nmea", "attitude", "motor", "state", "fix", "sky", "telemetry", "event", "odometry",
    ]  # fmt: skip
    assert {r.type for r in recs} == RECORD_TYPES
    assert [r.t_mono for r in recs] == [1.0, 2.0, 2.5, 2.75, 3.0, 3.5, 4.0, 5.0, 5.5]
    assert all(r.t_utc == "2026-11-22T04:43:12.250000Z" for r in recs)
    assert recs[0].data == {"text": "$GPGGA,1*00"}
    assert Attitude(**recs[1].data) == Attitude(2.0, 359.9, -3.0, 4.0)
    assert MotorCommand(**recs[2].data) == MotorCommand(2.5, 60.0, -40.0, "turn")
    assert recs[4].data["utc"] == "2026-11-22T04:43:12.250000Z"
    assert recs[4].data["lat_deg"] == 51.9
    assert recs[5].data["satellites"][0]["prn"] == 5
    assert recs[6].data["state"] == "TURN_LEFT" and recs[6].data["theta_deg"] is None
    assert recs[7].data == {"event": "start", "version": "0.1.0"}
    assert stats.records == 9 and stats.truncated == stats.bad_lines == 0
    typed = [decode_record(r) for r in recs]
    assert typed[1:6] == [
        Attitude(2.0, 359.9, -3.0, 4.0),
        MotorCommand(2.5, 60.0, -40.0, "turn"),
        StateChange(2.75, "STRAIGHT", "TURN_LEFT", "theta"),
        fix,
        sky,
    ]
    assert typed[0] is recs[0] and typed[7] is recs[7]
    assert typed[8] == WheelOdometry(5.5, 4300, -12, 7)
    for line in path.read_text().splitlines():  # strict JSON: no NaN, one object per line
        json.loads(line, parse_constant=lambda c: pytest.fail(f"non-standard JSON {c}"))


def test_direct_json_is_what_conversion_and_encoder_give() -> None:
    # The recorder writes a record's JSON itself (many records per simulated second); the
    # reference is the conversion (to_jsonable) and the encoder, computed here. Nested
    # telemetry extras, enums, datetimes, lists and non-finite floats are written directly;
    # values only the conversion knows (numpy scalars, dates, non-string keys) fall back.
    utc = datetime(2026, 11, 22, 4, 43, 12, 250000, tzinfo=UTC)
    extra = {"ekf_sigma_m": 1.5, "sensors_down": {"gps": "stale"}, "odd": float("inf")}
    direct = [
        GpsFix(3.0, utc=utc, lat_deg=51.9, lon_deg=4.57, valid=True, mode=3, hdop=1.2),
        GpsFix(3.0, utc=utc.replace(tzinfo=None), lat_deg=float("nan")),
        GpsSky(3.5, (SatInfo(5, 40.0, 120.0, 38.0, True),), pdop=1.9),
        Telemetry(4.0, Mode.RUNNING, NavState.TURN_LEFT, theta_deg=float("nan"), extra=extra),
        {"event": "x", "when": utc, "mode": Mode.IDLE, "nested": {"a": [{"b": -0.0}, None]}},
        {"list": [1, 2.5, True, "é\n", ()], "empty": {}},
    ]
    for payload in direct:
        assert direct_json(payload) == _ENCODE(to_jsonable(payload))
    for payload in ({"np": np.float64(1.5)}, {"day": utc.date()}, {"k": {1: "int key"}}):
        assert direct_json(payload) is None
        assert json.loads(_ENCODE(to_jsonable(payload)))  # the conversion's path handles it


def test_bad_calls_are_rejected(tmp_path: Path) -> None:
    with Recorder(tmp_path / "r.jsonl") as rec:
        with pytest.raises(ValueError, match=r"unknown record type 'gps'.*attitude"):
            rec.record("gps", {})
        with pytest.raises(ValueError, match="t_mono"):
            rec.record("event", {}, float("inf"))
        with pytest.raises(ValueError, match="payload"):
            rec.record("event", [1, 2])
        assert rec.records_written == 0
    rec.record_event("late", 1.0)  # after close: dropped and counted, no exception
    assert rec.dropped_after_close == 1
    assert list(read_recording(rec.path)) == []
    bad = Record(1.0, "", "attitude", {"t_s": 1.0, "heading": 3})
    with pytest.raises(ParseError, match="attitude record"):
        decode_record(bad)


def test_decode_record_ignores_unknown_fields_and_refuses_wrong_types() -> None:
    fix = {"t_s": 1.0, "lat_deg": 51.75, "lon_deg": -1.25, "valid": True, "new_m": 2}
    rec = Record(1.0, "", "fix", fix)
    assert decode_record(rec) == GpsFix(1.0, lat_deg=51.75, lon_deg=-1.25, valid=True)
    assert unknown_fields(rec) == ["new_m"]
    for field, value in (("lat_deg", "51.75"), ("valid", 1), ("sats_used", True)):
        with pytest.raises(ParseError, match=f"GpsFix.{field} is"):
            decode_record(Record(1.0, "", "fix", {**fix, field: value}))
    sky = Record(1.0, "", "sky", {"t_s": 1.0, "satellites": [{"prn": 3, "elevation": 1}]})
    with pytest.raises(ParseError, match="sky record"):
        decode_record(sky)


def test_missing_recording_is_device_unavailable(tmp_path: Path) -> None:
    with pytest.raises(DeviceUnavailable, match="nope"):
        list(read_recording(tmp_path / "nope.jsonl"))


_CHILD = """
import os, sys
from x6wd.core.recorder import Recorder
rec = Recorder(sys.argv[1])
for i in range(int(sys.argv[2])):
    rec.record_nmea(f"$GPTXT,{i}*00", float(i))
print("written", flush=True)
sys.stdin.read()  # wait to be killed, with the recorder still open
"""


@pytest.mark.integration
def test_kill_9_loses_nothing_that_was_recorded(tmp_path: Path) -> None:
    path = tmp_path / "crash.jsonl"
    proc = subprocess.Popen(
        [sys.executable, "-c", _CHILD, str(path), "500"],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        cwd=ROOT,
    )
    assert proc.stdout is not None
    assert proc.stdout.readline() == b"written\n"
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    recs = list(read_recording(path))
    assert [r.data["text"] for r in recs] == [f"$GPTXT,{i}*00" for i in range(500)]


def test_truncated_last_line_is_counted_and_reopening_continues(tmp_path: Path) -> None:
    path = tmp_path / "cut.jsonl"
    with Recorder(path) as rec:
        for i in range(10):
            rec.record_event("tick", float(i), n=i)
    size = path.stat().st_size
    with open(path, "r+b") as f:  # a crash in the middle of the last write
        f.truncate(size - 7)
    stats = ReadStats()
    assert [r.data["n"] for r in read_recording(path, stats=stats)] == list(range(9))
    assert stats.truncated == 1 and stats.bad_lines == 0
    with Recorder(path) as rec:  # the next run appends after the broken line
        rec.record_event("tick", 10.0, n=10)
    stats = ReadStats()
    assert [r.data["n"] for r in read_recording(path, stats=stats)] == [*range(9), 10]
    assert stats.truncated == 0 and stats.bad_lines == 1
    with pytest.raises(ParseError, match=r"cut\.jsonl:10"):
        list(read_recording(path, strict=True))


def _write_each_type(rec: Recorder, utc: datetime) -> None:
    extra = {"ekf": {"sigma_m": float("inf"), "pair": (1, 2.5)}, "mode": Mode.MANUAL}
    for k in range(3):
        t = float(k)
        rec.record_nmea(b"$GPGGA,1*00\r\n", t)
        rec.record_attitude(Attitude(t, 359.9, -3.0, 4.0, valid=bool(k)))
        rec.record_motor(MotorCommand(t, 60.0, -40.0, "turn"))
        rec.record_state(StateChange(t, "STRAIGHT", "TURN_LEFT", 'theta "q"'))
        rec.record_fix(GpsFix(t, utc=utc, lat_deg=51.9, hdop=float("nan"), valid=True))
        rec.record_sky(GpsSky(t, (SatInfo(5, 40.0, None, 38.0, True),), utc=utc))
        rec.record_telemetry(Telemetry(t, Mode.RUNNING, NavState.HOLD, extra=dict(extra)))
        rec.record_odometry(WheelOdometry(t, 4300, -12, k))
        rec.record_event("e", t, n=k, when=utc)


def test_buffered_recorder_writes_the_same_bytes(tmp_path: Path) -> None:
    """The simulator's buffered recorder (``buffer_bytes``) writes exactly the unbuffered
    one's lines, also across rotation and fsync, and has them all on disk once closed; the
    telemetry line is the one its ``to_dict()`` gives."""
    utc = datetime(2026, 11, 22, 4, 43, 12, 250000, tzinfo=UTC)
    with Recorder(tmp_path / "plain.jsonl", utc_clock=lambda: utc, max_bytes=2000) as rec:
        _write_each_type(rec, utc)
        plain = list(rec.paths)
    with Recorder(
        tmp_path / "buf.jsonl", utc_clock=lambda: utc, max_bytes=2000, buffer_bytes=1 << 16,
        fsync_interval_s=0.0,
    ) as rec:  # fmt: skip
        _write_each_type(rec, utc)
        buffered = list(rec.paths)
    assert len(plain) == len(buffered) > 2
    assert [p.read_bytes() for p in plain] == [p.read_bytes() for p in buffered]
    tel = Telemetry(1.0, Mode.RUNNING, NavState.HOLD, extra={"x": (1, float("nan"))})
    with Recorder(tmp_path / "t.jsonl", utc_clock=lambda: utc) as rec:
        rec.record_telemetry(tel)
        rec.record("telemetry", tel.to_dict(), 1.0)
    a, b = (tmp_path / "t.jsonl").read_text().splitlines()
    assert a == b
    with pytest.raises(ValueError, match="buffer_bytes"):
        Recorder(tmp_path / "bad.jsonl", buffer_bytes=-1)


def test_rotation_by_size_keeps_every_record_in_order(tmp_path: Path) -> None:
    with Recorder(tmp_path / "rot.jsonl", max_bytes=600) as rec:
        for i in range(40):
            rec.record_event("tick", float(i), n=i)
        paths = list(rec.paths)
    assert len(paths) > 3 and paths[1].name == "rot.1.jsonl"
    assert all(0 < p.stat().st_size <= 600 for p in paths)
    assert recording_parts(tmp_path / "rot.jsonl") == paths
    got = [r.data["n"] for p in paths for r in read_recording(p)]
    assert got == list(range(40))


def test_parts_are_found_past_gaps_and_a_missing_first_part(tmp_path: Path) -> None:
    with Recorder(tmp_path / "rot.jsonl", max_bytes=300) as rec:
        for i in range(40):
            rec.record_event("tick", float(i), n=i)
    paths = rec.paths
    assert len(paths) > 5
    (tmp_path / "rot.01.jsonl").write_text("not a part: a leading zero\n")
    (tmp_path / "rot.x.jsonl").write_text("not a part\n")
    for gone in (paths[0], paths[1], paths[3]):  # retention, or a hand, removed some
        gone.unlink()
    remaining = [p for p in paths if p.exists()]
    assert recording_parts(tmp_path / "rot.jsonl") == remaining
    assert recording_parts(paths[4]) == remaining  # a part names its whole run
    got = [r.data["n"] for r in read_recording_parts(tmp_path / "rot.jsonl")]
    assert got == sorted(got) and got[-1] == 39
    assert recording_parts(tmp_path / "nothing.jsonl") == []
    with pytest.raises(DeviceUnavailable, match="nor parts of it"):
        list(read_recording_parts(tmp_path / "nothing.jsonl"))


def test_in_dir_names_files_by_utc_time(tmp_path: Path) -> None:
    t = datetime(2026, 1, 2, 3, 4, 5, tzinfo=UTC)
    with Recorder.in_dir(tmp_path / "rec", utc_clock=lambda: t) as a:
        a.record_event("x", 0.0)
    with Recorder.in_dir(tmp_path / "rec", utc_clock=lambda: t) as b:
        pass
    assert a.path.name == "x6wd-20260102T030405Z.jsonl"
    assert b.path.name == "x6wd-20260102T030405Z-1.jsonl"
    assert is_recording(a.path) and not is_recording(LEA5H)


def test_two_runs_named_in_the_same_second_never_share_a_file(tmp_path: Path) -> None:
    """Two daemons (or sims) starting in one second both list the folder before either has
    opened its file: the name is claimed atomically, so the second takes ``-1`` instead of
    appending its records into the first one's recording."""
    import threading

    t = datetime(2026, 1, 2, 3, 4, 5, tzinfo=UTC)
    both_named = threading.Barrier(2, timeout=10)

    class Late(Recorder):
        def __init__(self, path: Path, **kw: object) -> None:
            both_named.wait()  # both have chosen a name; neither has opened it
            super().__init__(path, **kw)  # type: ignore[arg-type]

    got: list[Recorder] = []
    threads = [
        threading.Thread(target=lambda: got.append(Late.in_dir(tmp_path, utc_clock=lambda: t)))
        for _ in range(2)
    ]
    for th in threads:
        th.start()
    for th in threads:
        th.join(15)
    assert len(got) == 2
    for rec in got:
        rec.close()
    names = sorted(r.path.name for r in got)
    assert names == ["x6wd-20260102T030405Z-1.jsonl", "x6wd-20260102T030405Z.jsonl"]


def test_a_run_that_fails_to_start_leaves_no_empty_file(tmp_path: Path) -> None:
    t = datetime(2026, 1, 2, 3, 4, 5, tzinfo=UTC)
    with pytest.raises(ValueError, match="max_bytes"):
        Recorder.in_dir(tmp_path, utc_clock=lambda: t, max_bytes=0)
    assert list(tmp_path.iterdir()) == []


def test_a_recording_is_told_from_gpsd_json_and_nmea(tmp_path: Path) -> None:
    """A file beginning with gpsd's own JSON (``gpspipe -r``) is NMEA, not a recording; a
    recording whose first line is torn still is one (its reader names the fault)."""
    gpspipe = ROOT / "tests" / "data" / "gpspipe" / "lea-5h-gpspipe-r.log"
    assert not is_recording(gpspipe)
    assert [t for t, _ in nmea_file_chunks(gpspipe)][-1] > 0  # its NMEA's times
    assert looks_like_recording(b'\n  {"t_mono":0.0,"type":"event","data":{}}\n')
    assert looks_like_recording(b'{"t_mono":0.0,"ty')  # torn, or longer than the head
    assert looks_like_recording(b'{"bad json\n$GPGGA,...\n')
    assert not looks_like_recording(b'{"class":"TPV","mode":1}\n$GPGGA,...\n')
    assert not looks_like_recording(b"$GPGGA,...\n") and not looks_like_recording(b"")
    # a damaged first line (garbage, NULs): the next intact line tells
    assert looks_like_recording(b"\0" * 64 + b'\n{"t_mono":0.0,"type":"event","data":{}}\n')
    assert not looks_like_recording(b"\xff junk\n$GPGGA,...\n{}\n")
    binary = tmp_path / "binary.bin"
    binary.write_bytes(b"\xb5\x62" + bytes(range(11, 256)) * 4000)  # no newline at all
    assert not is_recording(binary)


# --- paced replay -----------------------------------------------------------------------------


def test_replay_records_keeps_the_recorded_pace(tmp_path: Path) -> None:
    path = tmp_path / "r.jsonl"
    with Recorder(path) as rec:
        for t in (100.0, 100.5, 102.0, 3.0, 3.5):  # the last two after a clock restart
            rec.record_event("e", t)
    for speed, expected in ((1.0, [0, 0.5, 2.0, 2.0, 2.5]), (2.0, [0, 0.25, 1.0, 1.0, 1.25])):
        clock = VirtualClock()
        seen = [
            clock() - 1000.0 for _ in replay_records(path, speed, clock=clock, sleep=clock.sleep)
        ]
        assert seen == pytest.approx(expected)
    clock = VirtualClock()
    assert len(list(replay_records(path, 0, clock=clock, sleep=clock.sleep))) == 5
    assert clock() == 1000.0
    with pytest.raises(ValueError, match="speed"):
        next(replay_records(path, -1))


def test_replay_port_plays_a_plain_log_byte_for_byte() -> None:
    port = ReplayPort(LEA5H, speed=0)
    got = bytearray()
    while chunk := port.read(97):
        got += chunk
    assert bytes(got) == LEA5H.read_bytes()
    assert port.eof and port.in_waiting == 0
    assert key(fixes_of(bytes(got))) == key(fixes_of(LEA5H.read_bytes()))


def test_replay_port_paces_by_sentence_time() -> None:
    clock = VirtualClock()
    port = ReplayPort(NL402U, speed=4, timeout=None, clock=clock, sleep=clock.sleep)
    first = port.read(4096)
    assert b"$GPRMC,104706.000" in first and b"104707.000" not in first
    second = port.read(4096)
    assert second.startswith(b"$GPRMC,104707.000") or b"104707.000" in second[:80]
    assert clock() - 1000.0 == pytest.approx(0.25)  # 1 s of log at 4x
    rest = b""
    while chunk := port.read(4096):
        rest += chunk
    assert first + second + rest == NL402U.read_bytes()
    times = [t for t, _ in nmea_file_chunks(NL402U)]
    assert clock() - 1000.0 == pytest.approx(times[-1] / 4)


def test_replay_port_timeout_zero_never_waits() -> None:
    clock = VirtualClock()
    port = ReplayPort(NL402U, speed=1, timeout=0, clock=clock, sleep=clock.sleep)
    first = port.read(100_000)
    assert first and port.read(10) == b"" and port.in_waiting == 0
    assert clock() == 1000.0
    clock.now_s += 1.0
    assert port.in_waiting > 0 and b"104707.000" in port.read(100_000)
    port.close()
    with pytest.raises(DeviceUnavailable, match="closed"):
        port.read(1)


def test_replay_port_plays_the_nmea_of_a_recording(tmp_path: Path) -> None:
    path = tmp_path / "r.jsonl"
    n = record_log(path, LEA5H)
    with Recorder(path) as rec:  # other record types are not part of the byte stream
        rec.record_attitude(Attitude(9999.0, 1.0, 0.0, 0.0))
    clock = VirtualClock()
    port = ReplayPort(path, speed=1, clock=clock, sleep=clock.sleep)
    assert port.is_recording
    lines = []
    while line := port.readline():
        lines.append(line)
    assert len(lines) == n and all(x.endswith(b"\r\n") for x in lines)
    assert clock() - 1000.0 == pytest.approx(0.1 * (n - 1))
    expected = [x for x in LEA5H.read_bytes().splitlines() if x.startswith(b"$")]
    assert [x.rstrip(b"\r\n") for x in lines] == expected


def summed(log: bytes) -> bytes:
    """``log`` with each ``*00`` replaced by its sentence's checksum (a sentence failing it
    sets no time)."""
    return re.sub(
        rb"\$([^*$\r\n]*)\*00",
        lambda m: b"$%s*%02X" % (m[1], functools.reduce(operator.xor, m[1], 0)),
        log,
    )


def test_plain_log_time_wraps_at_midnight_and_falls_back_to_rate(tmp_path: Path) -> None:
    wrap = tmp_path / "wrap.nmea"
    wrap.write_bytes(
        summed(
            b"$GPGGA,235959.00,,,,,0,00,99.99,,,,,,*00\r\n$GPGSA,A,1*00\r\n"
            b"$GPGGA,000001.00,,,,,0,00,99.99,,,,,,*00\r\n"
        )
    )
    assert [t for t, _ in nmea_file_chunks(wrap)] == [0.0, 0.0, 2.0]
    untimed = tmp_path / "untimed.nmea"
    untimed.write_bytes(b"$GPGSA,1*00\n$GPGSV,1*00\n$GPGSA,2*00\n$GPGSV,2*00\n$GPGSA,3*00\n")
    assert [t for t, _ in nmea_file_chunks(untimed, rate_hz=4)] == [0, 0, 0.25, 0.25, 0.5]
    with pytest.raises(ValueError, match="rate_hz"):
        nmea_file_chunks(untimed, rate_hz=0)


def test_plain_log_time_steps_back_across_midnight_and_lines_end_with_cr(tmp_path: Path) -> None:
    """A receiver restarting at 00:03:46 with a default clock of 23:59:48 steps back 238 s
    (not forward a day); CR-only line ends split lines like LF."""
    log = tmp_path / "coldboot.nmea"
    log.write_bytes(
        summed(
            b"$GPGGA,000346.00,,,,,0,00,99.99,,,,,,*00\r"
            b"$GPGGA,235948.00,,,,,0,00,99.99,,,,,,*00\r"
            b"$GPGGA,235949.00,,,,,0,00,99.99,,,,,,*00\r"
            b"$GPGGA,000001.00,,,,,0,00,99.99,,,,,,*00"
        )
    )
    assert [t for t, _ in nmea_file_chunks(log)] == [0.0, -238.0, -237.0, -225.0]


def test_plain_log_is_streamed_not_read_whole(tmp_path: Path) -> None:
    import tracemalloc

    one = LEA5H.read_bytes()
    big = tmp_path / "big.nmea"
    with open(big, "wb") as f:
        for _ in range(8_000_000 // len(one)):
            f.write(one)
    n = 0
    tracemalloc.start()
    try:
        for _t, _line in nmea_file_chunks(big):
            n += 1
        _now, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert n > 50_000 and peak < 1_500_000, peak


def test_paced_replay_does_not_wait_out_a_long_gap() -> None:
    """Four hours without data in a log (a receiver off, logs joined) are replayed as a
    second at speed 1, and said; short gaps and the pace itself are kept."""
    clock = VirtualClock()
    chunks = [(0.0, b"a"), (1.0, b"b"), (31.0, b"c"), (14_431.0, b"d"), (14_432.0, b"e")]
    gaps: list[tuple[float, float]] = []
    out = list(
        paced(
            iter(chunks),
            1.0,
            clock=clock,
            sleep=clock.sleep,
            on_gap=lambda t, jump: gaps.append((t, jump)),
        )
    )
    assert out == chunks
    assert clock.now_s - 1000.0 == pytest.approx(1.0 + 30.0 + 1.0 + 1.0)
    assert gaps == [(14_431.0, 14_400.0)]


# --- x6wd replay ------------------------------------------------------------------------------


def test_cli_replay_of_a_log_and_of_its_recording_agree(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    expected = [f for f in fixes_of(LEA5H.read_bytes())]
    assert cli_main(["replay", str(LEA5H), "--speed", "0", "--json"]) == 0
    out, err = capsys.readouterr()
    plain = [json.loads(x) for x in out.splitlines()]
    assert len(plain) == len(expected) > 10
    assert [(d["lat_deg"], d["lon_deg"], d["mode"]) for d in plain] == [
        (f.lat_deg, f.lon_deg, f.mode) for f in expected
    ]
    assert "sentences=164" in err and "checksum_failures=0" in err
    rec = tmp_path / "r.jsonl"
    record_log(rec, LEA5H)
    assert cli_main(["replay", str(rec), "--speed", "0", "--json", "--sky"]) == 0
    out, err = capsys.readouterr()
    objs = [json.loads(x) for x in out.splitlines()]
    fixes = [d for d in objs if d["class"] == "fix"]
    assert [(d["utc"], d["lat_deg"]) for d in fixes] == [(d["utc"], d["lat_deg"]) for d in plain]
    assert any(d["class"] == "sky" for d in objs)
    assert fixes[0]["t_s"] >= 50.0  # stamped with the recorded t_mono
    assert "records=" in err and "truncated_lines=0" in err


def test_cli_replay_summary_lines(capsys: pytest.CaptureFixture[str]) -> None:
    assert cli_main(["replay", str(NL402U), "--speed", "0"]) == 0
    out, _ = capsys.readouterr()
    lines = out.splitlines()
    assert lines and all(x.startswith("t=") and " lat=" in x for x in lines)
    assert "lat=54.0934683" in lines[0] or "lat=54.0934683" in lines[1]


def test_cli_replay_errors(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert cli_main(["replay", str(tmp_path / "missing.nmea"), "--speed", "0"]) == 2
    assert "missing.nmea" in capsys.readouterr().err
    for option, value, says in [
        ("--speed", "-1", "must be >= 0"),
        ("--speed", "inf", "must be a finite number"),
        ("--rate", "-1", "--rate: must be > 0"),
        ("--rate", "0", "--rate: must be > 0"),
        ("--rate", "nan", "must be a finite number"),
    ]:
        with pytest.raises(SystemExit) as exc:
            cli_main(["replay", str(LEA5H), option, value])
        assert exc.value.code == 2 and says in capsys.readouterr().err, (option, value)


@pytest.mark.integration
def test_cli_replay_as_a_process() -> None:
    exe = Path(sys.executable).parent / "x6wd"
    cmd = [str(exe)] if exe.exists() else [sys.executable, "-m", "x6wd"]
    proc = subprocess.run(
        [*cmd, "replay", str(NL402U), "--speed", "0", "--json"],
        capture_output=True,
        text=True,
        timeout=60,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
    )
    assert proc.returncode == 0, proc.stderr
    assert len(proc.stdout.splitlines()) == len(fixes_of(NL402U.read_bytes()))
    assert "sentences=" in proc.stderr


def test_an_over_long_line_is_skipped_without_being_held_whole(tmp_path: Path) -> None:
    # a card's garbage tail (NULs, no newline for hundreds of MB) or one huge line: the
    # reader held each whole (613 MB for a 300 MB tail); now 1 MiB pieces at a time
    import tracemalloc

    from x6wd.core.recorder import MAX_RECORD_LINE_BYTES, ReadStats, read_recording

    good = json.dumps({"t_mono": 1.0, "type": "event", "data": {"what": "x"}}) + "\n"
    path = tmp_path / "r.jsonl"
    with open(path, "wb") as f:
        f.write(good.encode() + b"y" * (16 * MAX_RECORD_LINE_BYTES) + b"\n" + good.encode())
        f.write(b"\0" * (16 * MAX_RECORD_LINE_BYTES))  # the tail, unterminated
    stats = ReadStats()
    tracemalloc.start()
    try:
        records = list(read_recording(path, stats=stats))
        peak_b = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert len(records) == 2 and stats.bad_lines == 2
    assert peak_b < 4 * MAX_RECORD_LINE_BYTES, peak_b  # not the 16 MiB of either


def test_a_very_slow_replay_sleeps_in_pieces_the_os_accepts(tmp_path: Path) -> None:
    # --speed 1e-300 asked time.sleep for 1e300 s: OverflowError, a traceback
    from x6wd.core.recorder import MAX_SLEEP_S, replay_records

    path = tmp_path / "r.jsonl"
    lines = [json.dumps({"t_mono": float(t), "type": "event", "data": {}}) for t in (0, 1)]
    path.write_text("\n".join(lines) + "\n")
    asked: list[float] = []

    def sleep(s: float) -> None:
        asked.append(s)
        raise KeyboardInterrupt  # the operator gives up

    records = replay_records(path, speed=1e-300, sleep=sleep)
    assert next(records).t_mono == 0.0
    with pytest.raises(KeyboardInterrupt):
        next(records)
    assert asked == [MAX_SLEEP_S]


def test_telemetry_headings_are_recorded_as_shown_0_to_360(tmp_path: Path) -> None:
    """docs/protocol.md, "Headings": the recording carries what status and watch show
    (Telemetry.to_dict), not the controller's (-180, 180]."""
    path = tmp_path / "r.jsonl"
    run, straight = Mode.RUNNING, NavState.STRAIGHT
    tels = [
        Telemetry(1.0, run, straight, heading_deg=-90.0, target_bearing_deg=-0.0),
        Telemetry(2.0, run, straight, heading_deg=-1e-17, target_bearing_deg=180.0),
        Telemetry(3.0, Mode.IDLE, NavState.IDLE, heading_deg=45.0),
    ]
    with Recorder(path, fsync_interval_s=0.0) as rec:
        for tel in tels:
            rec.record_telemetry(tel)
    assert "-0.0" not in path.read_text()
    got = [r.data for r in read_recording(path)]
    assert [(d["heading_deg"], d["target_bearing_deg"]) for d in got] == [
        (270.0, 0.0), (0.0, 180.0), (45.0, None)
    ]  # fmt: skip
    assert got == [json.loads(json.dumps(tel.to_dict())) for tel in tels]
