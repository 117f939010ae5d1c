"""x6wd decode judges an empty input alike however it is empty (an outside audit, round 23):
a 0-byte file was exit 0 with zero counters, a byte-order mark and blank lines exit 2 "no
NMEA sentence"."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from tests.conftest import ROOT


@pytest.mark.parametrize(
    "body",
    [
        b"",
        b"\n\n",
        b"\xef\xbb\xbf",
        b"\xef\xbb\xbf\r\n\r\n",
        b"\xef\xbb\xbf  \n",
        b"\n\xef\xbb\xbf\n",  # the review: a BOM after a blank line, two BOMs (files joined)
        b"\xef\xbb\xbf\xef\xbb\xbf\n",
    ],
)
def test_an_empty_or_blank_input_is_no_error(tmp_path: Path, body: bytes) -> None:
    f = tmp_path / "empty.nmea"
    f.write_bytes(body)
    r = subprocess.run(
        [sys.executable, "-m", "x6wd", "decode", str(f)],
        capture_output=True, text=True, timeout=120, cwd=ROOT,
    )  # fmt: skip
    assert r.returncode == 0, r.stderr
    assert r.stdout == "" and "no NMEA sentence" not in r.stderr


def test_a_byte_order_mark_before_junk_is_still_junk(tmp_path: Path) -> None:
    f = tmp_path / "junk.nmea"
    f.write_bytes(b"\xef\xbb\xbfhello\n")
    r = subprocess.run(
        [sys.executable, "-m", "x6wd", "decode", str(f)],
        capture_output=True, text=True, timeout=120, cwd=ROOT,
    )  # fmt: skip
    assert r.returncode == 2 and "no NMEA sentence" in r.stderr, r.stderr
