"""Recording retention: rotation at max_file_mb, oldest recordings deleted past max_total_mb or
below min_free_mb, never a foreign file or the part being written; the daemon runs it in the
recorder's thread."""

from __future__ import annotations

import asyncio
import dataclasses
import logging
import re
import threading
from datetime import UTC, datetime, timedelta
from pathlib import Path

import pytest

from tests.test_daemon import hil_config, run_daemon, wait_for
from x6wd.app.daemon import Daemon
from x6wd.core import recorder as recorder_mod
from x6wd.core.config import RecorderConfig
from x6wd.core.recorder import (
    MB,
    ReadStats,
    Recorder,
    ReplayPort,
    Retention,
    enforce_retention,
    list_recordings,
    read_recording_parts,
    recording_parts,
)

KB = 1024
__all__ = ["run_daemon"]  # the fixture, shared with test_daemon


def make(path: Path, size: int) -> Path:
    path.write_bytes(b"x" * (size - 1) + b"\n")
    return path


def sizes(directory: Path) -> int:
    return sum(f.size for f in list_recordings(directory))


@pytest.fixture
def foreign(tmp_path: Path) -> dict[Path, bytes]:
    """Files that only look a little like recordings: retention must never touch them."""
    files = {
        tmp_path / "notes.txt": b"keep me\n",
        tmp_path / "x6wd-latest.jsonl": b"{}\n",
        tmp_path / "other-20200101T000000Z.jsonl": b"{}\n",
        tmp_path / "x6wd-20200101T000000Z.jsonl.bak": b"{}\n",
        tmp_path / "x6wd-20200101T000000Z.01.jsonl": b"{}\n",
    }
    for path, blob in files.items():
        path.write_bytes(blob * 2000)
    (tmp_path / "x6wd-20200101T000001Z.jsonl").mkdir()  # a directory with a recording's name
    return files


def assert_untouched(foreign: dict[Path, bytes]) -> None:
    for path, blob in foreign.items():
        assert path.read_bytes() == blob * 2000, path


def test_names_and_order(tmp_path: Path, foreign: dict[Path, bytes]) -> None:
    for name in (
        "x6wd-20260102T030405Z.2.jsonl",
        "x6wd-20260102T030405Z.jsonl",
        "x6wd-20260102T030405Z-1.jsonl",
        "x6wd-20251231T235959Z.10.jsonl",
        "x6wd-20251231T235959Z.9.jsonl",
    ):
        make(tmp_path / name, 10)
    got = [(f.path.name, f.run, f.part) for f in list_recordings(tmp_path)]
    assert got == [
        ("x6wd-20251231T235959Z.9.jsonl", ("20251231T235959Z", 0), 9),
        ("x6wd-20251231T235959Z.10.jsonl", ("20251231T235959Z", 0), 10),
        ("x6wd-20260102T030405Z.jsonl", ("20260102T030405Z", 0), 0),
        ("x6wd-20260102T030405Z.2.jsonl", ("20260102T030405Z", 0), 2),
        ("x6wd-20260102T030405Z-1.jsonl", ("20260102T030405Z", 1), 0),
    ]


def test_older_runs_go_first_then_our_oldest_parts_never_the_current(
    tmp_path: Path, foreign: dict[Path, bytes], caplog: pytest.LogCaptureFixture
) -> None:
    old_a = [make(tmp_path / f"x6wd-20250101T000000Z{s}.jsonl", 10 * KB) for s in ("", ".1")]
    old_b = make(tmp_path / "x6wd-20250601T000000Z.jsonl", 10 * KB)
    # a run stamped LATER than ours (the clock was set back since): still not ours, goes first
    later = make(tmp_path / "x6wd-20991231T000000Z.jsonl", 10 * KB)
    ours = [make(tmp_path / f"x6wd-20260101T000000Z{s}.jsonl", 10 * KB) for s in ("", ".1")]
    current = make(tmp_path / "x6wd-20260101T000000Z.2.jsonl", 10 * KB)
    cap = Retention(max_total_bytes=25 * KB)
    with caplog.at_level(logging.INFO, logger="x6wd.core.recorder"):
        gone = enforce_retention(tmp_path, cap, current=current)
    assert gone == [*old_a, old_b, later, ours[0]]
    assert [f.path for f in list_recordings(tmp_path)] == [ours[1], current]
    assert sizes(tmp_path) == 20 * KB
    assert_untouched(foreign)
    logged = [r.getMessage() for r in caplog.records]
    assert all(any(str(p) in m for m in logged) for p in gone)
    # nothing left but the part being written: it stays, even over the cap
    with caplog.at_level(logging.WARNING, logger="x6wd.core.recorder"):
        assert enforce_retention(tmp_path, Retention(max_total_bytes=1), current=current) == [
            ours[1]
        ]
    assert current.exists() and "only the recording being written" in caplog.text
    assert_untouched(foreign)


def test_free_space_floor(tmp_path: Path, foreign: dict[Path, bytes]) -> None:
    runs = [make(tmp_path / f"x6wd-2025010{i}T000000Z.jsonl", 10 * KB) for i in range(1, 6)]
    current = runs[-1]
    asked: list[Path] = []

    def free(d: Path) -> int:
        asked.append(d)
        return 5 * KB  # the card is nearly full

    # 5 KB free, 22 KB wanted: two deletions of 10 KB make 25 KB
    gone = enforce_retention(
        tmp_path, Retention(min_free_bytes=22 * KB), current=current, free=free
    )
    assert gone == runs[:2] and asked == [tmp_path]
    # the current part's growth counts: with 15 KB more to come, 27 KB free is 12 KB
    more = enforce_retention(
        tmp_path,
        Retention(min_free_bytes=22 * KB),
        current=current,
        reserve_bytes=25 * KB,
        free=lambda d: 27 * KB,
    )
    assert more == [runs[2]]
    assert_untouched(foreign)


def test_real_free_space_is_asked_of_the_file_system(tmp_path: Path) -> None:
    assert 0 < recorder_mod.free_bytes(tmp_path) < 1 << 60
    make(tmp_path / "x6wd-20250101T000000Z.jsonl", KB)
    current = make(tmp_path / "x6wd-20250102T000000Z.jsonl", KB)
    # no file system has an exabyte free: everything but the current part goes
    assert len(enforce_retention(tmp_path, Retention(min_free_bytes=1 << 60), current=current))
    assert [f.path for f in list_recordings(tmp_path)] == [current]


def test_recorder_rotates_and_the_cap_holds_at_every_record(
    tmp_path: Path, foreign: dict[Path, bytes]
) -> None:
    old = [make(tmp_path / f"x6wd-2025010{i}T000000Z.jsonl", 3 * KB) for i in range(1, 4)]
    cap = 8 * KB
    rec = Recorder.in_dir(tmp_path, max_bytes=2 * KB, retention=Retention(max_total_bytes=cap))
    # the start-of-run pass: 9 KB of other runs + room for a 2 KB part > 8 KB
    assert rec.enforce_retention() == old[:1]
    with rec:
        for i in range(300):
            rec.record_event("tick", float(i), n=i, pad="p" * 40)
            assert rec.path.exists()  # the part being written is never deleted
            assert sizes(tmp_path) <= cap, i
    assert len(rec.paths) > 10  # it rotated
    assert rec.deleted[:3] == old  # other runs first, then our own oldest parts
    remaining = recording_parts(rec.paths[0])
    assert remaining and remaining[-1] == rec.path and not rec.paths[0].exists()
    # the reader reads what is left, in order, ending with the last record
    stats = ReadStats()
    got = [r.data["n"] for r in read_recording_parts(rec.paths[0], stats=stats)]
    assert got == list(range(got[0], 300)) and got[0] > 0
    assert stats.bad_lines == stats.truncated == 0
    assert_untouched(foreign)


def test_replay_plays_the_remaining_parts_in_order(tmp_path: Path) -> None:
    with Recorder(tmp_path / "x6wd-20260101T000000Z.jsonl", max_bytes=400) as rec:
        for i in range(30):
            rec.record_nmea(f"$GPTXT,01,01,02,n{i:02d}*00", float(i))
    first = rec.paths[0]
    for p in rec.paths[:3]:  # retention took the first three parts
        p.unlink()
    assert recording_parts(first) == rec.paths[3:]
    port = ReplayPort(first, speed=0, timeout=1.0)
    blob = b""
    while not port.eof:
        blob += port.read(1 << 20)
    text = blob.decode()
    numbers = [int(line.split(",n")[1][:2]) for line in text.splitlines()]
    assert numbers == list(range(numbers[0], 30)) and numbers[0] > 0


def test_daemon_rotates_and_deletes_in_the_recorder_thread(
    tmp_path: Path, run_daemon, monkeypatch: pytest.MonkeyPatch
) -> None:
    rec_dir = tmp_path / "rec"
    rec_dir.mkdir()
    t0 = datetime.now(UTC) - timedelta(days=3)
    old = []
    for day in range(3):
        stamp = (t0 + timedelta(days=day)).strftime("%Y%m%dT%H%M%SZ")
        old.append(make(rec_dir / f"x6wd-{stamp}.jsonl", 40 * KB))
    notes = rec_dir / "notes.txt"
    notes.write_text("mine\n")
    threads: list[str] = []
    real = recorder_mod.enforce_retention

    def spy(*args, **kwargs):  # type: ignore[no-untyped-def]
        threads.append(threading.current_thread().name)
        return real(*args, **kwargs)

    monkeypatch.setattr(recorder_mod, "enforce_retention", spy)
    rc = RecorderConfig(dir=str(rec_dir), max_file_mb=8 / 1024, max_total_mb=100 / 1024)
    cfg = dataclasses.replace(hil_config(tmp_path), recorder=rc)
    r = run_daemon(Daemon(cfg))
    rec = r.daemon.recorder.recorder
    # the start-of-run pass: 120 KB of old runs + room for an 8 KB part > 100 KB
    wait_for(lambda: not old[0].exists(), 5, "start-of-run retention")
    wait_for(lambda: len(rec.paths) >= 3, 15, "two rotations")
    assert r.stop() == 0
    # oldest first, and no part of ours before every other run is gone
    olds = [p for p in rec.deleted if p in old]
    assert olds == old[: len(olds)] and rec.deleted[: len(olds)] == olds
    assert sizes(rec_dir) <= 100 * KB
    assert notes.read_text() == "mine\n"
    assert threads and set(threads) == {"x6wd-recorder"}  # never the event loop
    parts = recording_parts(rec.paths[0])
    assert parts[-1] == rec.paths[-1] and max(p.stat().st_size for p in parts) <= 8 * KB
    stats = ReadStats()
    assert {r.type for r in read_recording_parts(rec.paths[0], stats=stats)} >= {"nmea", "fix"}
    assert stats.bad_lines == stats.truncated == 0


def test_daemon_refuses_a_part_larger_than_the_total(tmp_path: Path) -> None:
    rc = RecorderConfig(dir=str(tmp_path / "rec"), max_file_mb=10.0, max_total_mb=5.0)
    cfg = dataclasses.replace(hil_config(tmp_path), recorder=rc)
    assert asyncio.run(Daemon(cfg).run()) == 2
    assert not (tmp_path / "rec").exists()


def test_mb_is_a_mebibyte() -> None:
    assert MB == 1 << 20


def test_a_full_card_is_one_readable_retention_line_a_minute(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """The pass runs at every retry to open a part on a full card: its warning came on each
    (10 in 80 s) and read '... (667648 B short) < 268435456 B'."""
    rec = Recorder(
        tmp_path / "x6wd-20250101T000000Z.jsonl",
        max_bytes=KB,
        retention=Retention(min_free_bytes=1 << 62),  # more than any card has
    )
    with caplog.at_level(logging.WARNING, logger="x6wd.core.recorder"):
        for _ in range(10):
            rec.enforce_retention()
    (line,) = [r.getMessage() for r in caplog.records]
    assert re.fullmatch(
        r"retention: once the current part is full, \d+ B free, under the "
        rf"{1 << 62} B to keep, and only the recording being written is left",
        line,
    ), line
    got: list[str] = []
    enforce_retention(
        tmp_path,
        Retention(min_free_bytes=10 * KB),
        current=rec.path,
        reserve_bytes=KB,
        free=lambda d: 6 * KB,
        warn=got.append,
    )
    assert got == [
        "retention: once the current part is full, 5120 B free, under the 10240 B to keep, "
        "and only the recording being written is left"
    ]
    got.clear()  # a card too full for the part itself: no negative byte count
    enforce_retention(
        tmp_path,
        Retention(min_free_bytes=10 * KB),
        current=rec.path,
        reserve_bytes=8 * KB,
        free=lambda d: 6 * KB,
        warn=got.append,
    )
    assert got == [
        "retention: the file system lacks 2048 B for the current part to fill up, and must "
        "keep 10240 B free, and only the recording being written is left"
    ]
