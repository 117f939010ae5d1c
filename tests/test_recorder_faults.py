"""The recorder through file-system faults: a part that cannot be opened, a write cut short
by a full file system, a directory removed under it. Real files and real OS errors: a
directory in a part's place (EISDIR), RLIMIT_FSIZE (a short write, then EFBIG, as a file
system filling up mid-record), rmtree."""

from __future__ import annotations

import json
import logging
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tests.conftest import ROOT
from x6wd.core.errors import DeviceUnavailable
from x6wd.core.recorder import ReadStats, Recorder, read_recording, read_recording_parts


def _nmea(rec: Recorder, i: int) -> None:
    rec.record_nmea(f"$GPTXT,{i:05d}*00", float(i))


def test_a_failed_rotation_is_retried_and_recording_goes_on(tmp_path: Path) -> None:
    rec = Recorder(tmp_path / "r.jsonl", max_bytes=1000, reopen_backoff_s=(0.05, 0.1))
    blocker = tmp_path / "r.1.jsonl"
    blocker.mkdir()  # the next part cannot be opened (as a full or read-only file system)
    i = 0
    with pytest.raises(DeviceUnavailable, match=r"r\.1\.jsonl"):
        while True:
            _nmea(rec, i)
            i += 1
    assert rec.state == "failing"
    for j in range(5):  # within the back-off: counted, no exception per record
        _nmea(rec, 1000 + j)
    assert rec.records_lost == 6
    blocker.rmdir()  # space back
    time.sleep(0.06)
    for j in range(5):
        _nmea(rec, 2000 + j)
    rec.close()
    assert rec.state == "closed" and rec.paths[-1] == blocker
    texts = [r.data["text"] for r in read_recording_parts(tmp_path / "r.jsonl")]
    assert texts[-5:] == [f"$GPTXT,{2000 + j:05d}*00" for j in range(5)]
    assert len(texts) == i + 5 and rec.dropped_after_close == 0


_TORN = """
import resource, sys, time
from x6wd.core.errors import DeviceUnavailable
from x6wd.core.recorder import Recorder
path = sys.argv[1]
rec = Recorder(path, reopen_backoff_s=(0.05, 0.1))
for i in range(3):
    rec.record_nmea(f"$GPTXT,before{i}*00", float(i))
soft, hard = resource.getrlimit(resource.RLIMIT_FSIZE)
size = rec.bytes_written
resource.setrlimit(resource.RLIMIT_FSIZE, (size + 40, hard))  # the next line is cut at 40 B
try:
    rec.record_nmea("$GPTXT,torn*00", 3.0)
except DeviceUnavailable as exc:
    print("failed:", exc, flush=True)
rec.record_nmea("$GPTXT,lost*00", 4.0)  # within the back-off
resource.setrlimit(resource.RLIMIT_FSIZE, (soft, hard))  # space back
time.sleep(0.06)
for i in range(3):
    rec.record_nmea(f"$GPTXT,after{i}*00", 5.0 + i)
rec.close()
print("lost", rec.records_lost, "errors", rec.write_errors, flush=True)
"""


@pytest.mark.integration
def test_a_record_cut_by_a_full_file_system_loses_only_itself(tmp_path: Path) -> None:
    path = tmp_path / "r.jsonl"
    proc = subprocess.run(
        [sys.executable, "-c", _TORN, str(path)],
        capture_output=True,
        text=True,
        timeout=30,
        cwd=ROOT,
    )
    assert proc.returncode == 0, proc.stderr
    assert "failed:" in proc.stdout and "lost 2 errors 1" in proc.stdout, proc.stdout
    raw = path.read_bytes().split(b"\n")
    assert len(raw[3]) == 40  # the torn record, alone on its line
    stats = ReadStats()
    texts = [r.data["text"] for r in read_recording(path, stats=stats)]
    assert texts == [f"$GPTXT,before{i}*00" for i in range(3)] + [
        f"$GPTXT,after{i}*00" for i in range(3)
    ]
    assert stats.bad_lines == 1 and stats.truncated == 0
    assert all(json.loads(line) for line in raw[4:] if line)


def test_a_removed_directory_gets_a_new_part(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    d = tmp_path / "rec"
    rec = Recorder(d / "r.jsonl", check_interval_s=0.05)
    _nmea(rec, 0)
    shutil.rmtree(d)  # an operator cleaning up during a run
    time.sleep(0.06)
    with caplog.at_level(logging.WARNING, logger="x6wd.core.recorder"):
        for i in range(1, 4):
            _nmea(rec, i)
    rec.close()
    assert "r.jsonl was removed: continuing in a new part" in caplog.text
    assert rec.path == d / "r.1.jsonl" and rec.path.exists()
    assert [r.data["text"] for r in read_recording(rec.path)] == [
        f"$GPTXT,{i:05d}*00" for i in range(1, 4)
    ]
