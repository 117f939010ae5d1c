"""A log without any position sentence says what it holds (round 20).

A receiver configured to send satellites only (GSA and GSV) gave "no NMEA position sentence
... (1200 NMEA sentences, ...)": the user could not tell which sentences the log had. The
error now names the most frequent types, the talker dropped.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from x6wd.core.errors import ParseError
from x6wd.gap.io import read_track


def sentence(body: str) -> str:
    check = 0
    for ch in body:
        check ^= ord(ch)
    return f"${body}*{check:02X}\r\n"


def test_a_satellites_only_log_names_its_sentence_types(tmp_path: Path) -> None:
    lines = []
    for _ in range(50):
        lines.append(sentence("GPGSA,A,3,01,02,03,04,,,,,,,,,2.0,1.0,1.7"))
        lines.append(sentence("GPGSV,1,1,04,01,40,083,46,02,17,308,41,03,07,344,39,04,22,228,45"))
        lines.append(sentence("GLGSV,1,1,01,65,40,083,46"))
    path = tmp_path / "sky.nmea"
    path.write_text("".join(lines))
    with pytest.raises(ParseError, match=r"150 NMEA sentences \(GSV 100, GSA 50\), 0 UBX"):
        read_track(path)


def test_more_than_six_types_are_summed_up(tmp_path: Path) -> None:
    kinds = ["GSA", "GSV", "VTG", "TXT", "ZDA", "GST", "GBS", "DTM"]
    lines = [sentence(f"GP{k},1,2") for i, k in enumerate(kinds) for _ in range(8 - i)]
    lines.append(sentence("PUBX,00,1"))
    path = tmp_path / "many.nmea"
    path.write_text("".join(lines))
    shown = r"\(GSA 8, GSV 7, VTG 6, TXT 5, ZDA 4, GST 3, 3 more types\)"
    with pytest.raises(ParseError, match=shown):
        read_track(path)
