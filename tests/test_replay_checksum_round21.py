"""A sentence that fails its checksum never sets a replayed log's clock (an outside audit,
round 21): line noise in one ZDA's time field (00:10:34 read as 00:10:54) made `x6wd replay`
wait 20 s and step back 19 s, `x6wd plot` draw a 71 s log as 372 s, and `replay://` go
silent 20 s, though `x6wd decode` counted and skipped that sentence. Real u-blox 8 log."""

from __future__ import annotations

from itertools import pairwise
from pathlib import Path

import pytest

from x6wd.core.recorder import nmea_file_chunks

LOG = Path(__file__).parent / "data" / "nmea" / "ublox-8.log"
ZDA = b"$GNZDA,001034.00,10,01,2017,00,00*7A"


def times(path: Path) -> list[float]:
    return [t for t, _line in nmea_file_chunks(path)]


@pytest.mark.parametrize(
    "damaged",
    [
        b"$GNZDA,001054.00,10,01,2017,00,00*7A",  # one digit changed: the checksum fails
        b"$GNZDA,001054.00,10,01,2017,00,00*7",  # a checksum cut short
        b"$GNZDA,001054.00,10,01,2017,00,00*Z1",  # not hexadecimal
    ],
)
def test_a_sentence_failing_its_checksum_leaves_the_clock_alone(
    tmp_path: Path, damaged: bytes
) -> None:
    clean = LOG.read_bytes()
    assert clean.count(ZDA) == 1
    bad = tmp_path / "bad.log"
    bad.write_bytes(clean.replace(ZDA, damaged))
    got, want = times(bad), times(LOG)
    assert got == want
    assert all(b >= a for a, b in pairwise(got))


def test_a_sentence_without_a_checksum_still_sets_the_clock(tmp_path: Path) -> None:
    log = tmp_path / "plain.log"
    log.write_bytes(b"$GPGGA,120000.00,,,,,0,00,,,M,,M,,\r\n$GPGGA,120001.00,,,,,0,00,,,M,,M,,\r\n")
    assert times(log) == [0.0, 1.0]
