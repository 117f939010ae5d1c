"""``x6wd sim`` says what the receiver's UART dropped (outside audit, round 13, finding 5).

``default.toml`` at 4 Hz and 9600 baud drops about half its sentences on the line (most of
the GSV) and delivers every fix about a second late, yet the printed summary said nothing and a
mission's ``summary.json`` had no ``uart_dropped_sentences`` (a survey's has). At 4800 baud
almost every GGA is dropped: the fixes are RMC-only (no satellite count, the last GSA's HDOP)
while the summary printed mean HDOP and satellites used as if nothing were missing. Real runs,
real files, the real CLI.
"""

from __future__ import annotations

import json
import subprocess
import sys
from collections import Counter
from pathlib import Path

import pytest

from sim_backend.mission import run_mission
from sim_backend.world import loads_world

ROOT = Path(__file__).resolve().parent.parent
SCENARIOS = ROOT / "config" / "scenarios"
DEFAULT = (SCENARIOS / "default.toml").read_text(encoding="utf-8")


def _scenario(rate_hz: float, baud: int, duration_s: float = 40.0) -> str:
    for old in ("rate_hz = 1.0", "duration_s = 400.0", "\nbaud = 9600\n"):
        assert DEFAULT.count(old) == 1, old
    return (
        DEFAULT.replace("rate_hz = 1.0", f"rate_hz = {rate_hz}")
        .replace("duration_s = 400.0", f"duration_s = {duration_s}")
        .replace("\nbaud = 9600\n", f"\nbaud = {baud}\n")
    )


def _types(lines: list[str]) -> Counter[str]:
    return Counter(ln.split(",", 1)[0][3:] for ln in lines if ln.startswith("$"))


def _sim(tmp_path: Path, text: str, *extra: str) -> list[str]:
    scenario = tmp_path / "s.toml"
    scenario.write_text(text, encoding="utf-8")
    r = subprocess.run(
        [sys.executable, "-m", "x6wd", "sim", str(scenario), "--out", str(tmp_path / "out"),
         "--quiet", *extra],
        capture_output=True, text=True, timeout=300, cwd=ROOT, check=False,
    )  # fmt: skip
    assert r.returncode in (0, 1), r.stderr
    return r.stdout.splitlines()


def test_a_mission_counts_the_sentences_its_uart_dropped(tmp_path: Path) -> None:
    """4 Hz at 9600 baud: summary.json counts the dropped sentences per type, exactly the
    ones in gps.nmea (what the receiver formatted) that recording.jsonl (what crossed the line)
    lacks, and the fixes' delay after their epoch (about the full buffer's wire time)."""
    world = loads_world(_scenario(4.0, 9600), base_dir=SCENARIOS)
    summary = run_mission(world, tmp_path)
    extra = json.loads((tmp_path / "summary.json").read_text(encoding="utf-8"))["extra"]
    formatted = _types((tmp_path / "gps.nmea").read_text(encoding="ascii").splitlines())
    carried = _types(
        [
            r["data"]["text"]
            for r in map(json.loads, (tmp_path / "recording.jsonl").open(encoding="utf-8"))
            if r["type"] == "nmea"
        ]
    )
    formatted.pop("TXT")  # the start-up banner: fed to the decoder, not recorded
    lost = formatted - carried
    assert lost["GSV"] > 0.8 * formatted["GSV"]  # GSV hardly ever gets through
    assert extra["uart_dropped_by_type"] == dict(lost)
    assert extra["uart_dropped_sentences"] == lost.total()
    assert extra["uart_sentences"] == formatted.total() + 7  # + the banner's TXT, all sent
    assert extra["fixes_without_gga"] == 0  # GGA is third in a burst: it gets through
    assert 0.7 < extra["fix_delay_s"]["mean"] < 1.2
    assert extra["fix_delay_s"]["max"] >= extra["fix_delay_s"]["mean"]
    assert summary.extra["uart_dropped_sentences"] == extra["uart_dropped_sentences"]


def test_the_printed_summary_says_what_the_line_dropped(tmp_path: Path) -> None:
    """One 'UART line' row: how many of how many, by type, and the fixes' delay."""
    out = _sim(tmp_path, _scenario(4.0, 9600))
    rows = [ln for ln in out if ln.startswith("  UART line")]
    assert len(rows) == 1, out
    extra = json.loads((tmp_path / "out" / "summary.json").read_text(encoding="utf-8"))["extra"]
    by_type = ", ".join(f"{k} {v:,}" for k, v in extra["uart_dropped_by_type"].items())
    assert rows[0].startswith(
        f"  UART line           9600 baud dropped {extra['uart_dropped_sentences']:,} of"
        f" {extra['uart_sentences']:,} sentences ({by_type}); fixes "
    ), rows[0]
    assert rows[0].endswith("s after their epoch on average: raise [gnss] baud or lower rate_hz")


def test_fixes_without_their_gga_are_said(tmp_path: Path) -> None:
    """4 Hz at 4800 baud: almost every GGA is dropped, so the fixes are RMC-only; the row says
    so and where the mean HDOP and satellites used then come from."""
    out = _sim(tmp_path, _scenario(4.0, 4800))
    summary = json.loads((tmp_path / "out" / "summary.json").read_text(encoding="utf-8"))
    no_gga = summary["extra"]["fixes_without_gga"]
    valid = summary["fixes_valid"]
    assert no_gga > 0.9 * valid
    assert summary["extra"]["uart_dropped_by_type"]["GGA"] >= no_gga
    row = next(ln for ln in out if ln.startswith("  UART line"))
    assert (
        f"; {no_gga:,} of {valid:,} fixes came without their GGA (no satellite count: mean"
        f" satellites used is of the other {valid - no_gga:,}; their HDOP is the last GSA's"
        " received)"
    ) in row


@pytest.mark.parametrize("survey", [False, True])
def test_no_row_when_nothing_was_dropped_and_a_survey_says_it_too(
    tmp_path: Path, survey: bool
) -> None:
    """1 Hz at 9600 baud drops nothing: no row (a mission). A survey at 4 Hz drops: its row
    gives the count its summary.json has (the receiver engine counts no types)."""
    if not survey:
        out = _sim(tmp_path, _scenario(1.0, 9600, 20.0))
        assert not [ln for ln in out if "UART" in ln], out
        extra = json.loads((tmp_path / "out" / "summary.json").read_text(encoding="utf-8"))
        assert extra["extra"]["uart_dropped_sentences"] == 0
        return
    text = _scenario(4.0, 9600, 20.0).split("[mission]")[0]
    out = _sim(tmp_path, text)
    n = json.loads((tmp_path / "out" / "summary.json").read_text(encoding="utf-8"))["extra"][
        "uart_dropped_sentences"
    ]
    assert n > 0
    row = f"  UART line           9600 baud dropped {n:,} sentences: raise [gnss] baud"
    assert f"{row} or lower rate_hz" in out, out


def test_at_the_lowest_rate_the_advice_is_only_to_raise_the_baud(tmp_path: Path) -> None:
    """1 Hz at 4800 baud drops a few GLL; 1 Hz is the least rate_hz a scenario takes (0.5 is
    refused), so the row advises the baud alone, not "or lower rate_hz" (review round 13)."""
    out = _sim(tmp_path, _scenario(1.0, 4800, 60.0))
    row = next(ln for ln in out if ln.startswith("  UART line"))
    assert row.endswith(": raise [gnss] baud"), row
    assert "rate_hz" not in row
