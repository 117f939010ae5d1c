"""Files a tool reads whole or line by line are regular files (an outside audit, round 18):
``--config /dev/zero`` took 8 GB in 15 s and a FIFO as a scenario blocked for ever; each
is now exit 2 naming the file and what it is, before any byte is read."""

from __future__ import annotations

import os
import resource
import subprocess
import sys
from pathlib import Path

import pytest

from x6wd.core.files import InputFileError, read_bytes_bounded, read_text_bounded

ROOT = Path(__file__).resolve().parents[1]
SCENARIO = ROOT / "config" / "scenarios" / "default.toml"
NMEA = ROOT / "tests" / "data" / "nmea" / "ublox-lea-5h.log"
LONG_NMEA = ROOT / "tests" / "data" / "nmea" / "quectel-l76k-dual.log"  # enough for a diagnosis
MEMORY_CAP_B = 3 << 30  # an unbounded read fails fast under it, instead of swapping


def _capped() -> None:
    resource.setrlimit(resource.RLIMIT_AS, (MEMORY_CAP_B, MEMORY_CAP_B))


# (what, x6wd arguments with {bad} for the file that is no regular file)
CASES = [
    ("robot config (run)", ["run", "--config", "{bad}"]),
    ("robot config (sim)", ["sim", str(SCENARIO), "--config", "{bad}", "--out", "{out}"]),
    ("scenario", ["sim", "{bad}", "--out", "{out}"]),
    ("sweep file", ["sweep", "{bad}", "--out", "{out}"]),
    ("gap scenario", ["gap", "--real", str(LONG_NMEA), "--scenario", "{bad}", "--out", "{out}"]),
    ("true track", ["plot", str(NMEA), "--truth", "{bad}", "--out", "{out}"]),
    ("calibrate static", ["calibrate", "gnss", "--static", "{bad}", "--ref-lat", "1",
                          "--ref-lon", "1"]),
    ("calibrate drive", ["calibrate", "gnss", "--drive", "{bad}", "--reference", str(NMEA),
                         "--re-m", "0.1", "--ase-m", "0.1"]),
]  # fmt: skip


@pytest.mark.parametrize("kind", ["/dev/zero", "fifo", "pipe"])
@pytest.mark.parametrize(("what", "args"), CASES, ids=[c[0] for c in CASES])
def test_a_device_or_fifo_is_exit_2_naming_it(
    tmp_path: Path, what: str, args: list[str], kind: str
) -> None:
    bad, fds = "/dev/zero", ()
    if kind == "fifo":
        bad = str(tmp_path / "input.fifo")
        os.mkfifo(bad)  # no writer: an open would block for ever
    elif kind == "pipe":  # as `<(cmd)` gives it: a scenario's resolved to /proc/PID/fd/pipe:[N]
        r, w = os.pipe()
        os.close(w)
        bad, fds = f"/dev/fd/{r}", (r,)
    argv = [a.format(bad=bad, out=tmp_path / "out") for a in args]
    try:
        proc = subprocess.run(
            [sys.executable, "-m", "x6wd", *argv],
            capture_output=True,
            text=True,
            timeout=120,
            preexec_fn=_capped,
            cwd=tmp_path,
            pass_fds=fds,
        )
    finally:
        for fd in fds:
            os.close(fd)
    said = {"/dev/zero": "a character device", "fifo": "a FIFO", "pipe": "a pipe"}[kind]
    assert proc.returncode == 2, (what, proc.returncode, proc.stderr[-2000:])
    assert f"not a regular file ({said})" in proc.stderr and bad in proc.stderr, proc.stderr
    assert "Traceback" not in proc.stderr, proc.stderr


def test_a_whole_file_read_is_bounded(tmp_path: Path) -> None:
    path = tmp_path / "big.toml"
    path.write_bytes(b"a = 1\r\n" * 100)
    assert read_text_bounded(path) == "a = 1\n" * 100  # universal newlines, as read_text
    with pytest.raises(InputFileError, match="larger than 0 MiB"):
        read_bytes_bounded(path, limit_bytes=699)
    assert len(read_bytes_bounded(path, limit_bytes=700)) == 700
