"""What `x6wd plot` and the survey simulator hold does not grow with what a log or run holds
(outside audit round 7, items 3 and 5).

- A log whose time jumps thousands of times (epochs written out of order in pairs, many logs
  concatenated) made a page with every jump in its data and a dashed line per jump on every
  time panel: 6 h of swapped pairs, 10,799 jumps, 9.2 MB of HTML and 92 MB of memory. The
  jumps kept are now bounded as the series are; the count, the first and the largest are said.
- The survey's track.png expanded every fix into nine pixel offsets at once; now in chunks.
"""

from __future__ import annotations

import json
import re
import subprocess
import sys
import tracemalloc
from datetime import UTC, datetime, timedelta
from pathlib import Path

import numpy as np

import sim_backend.trackpng as trackpng
from sim_backend.world import load_world
from tests.test_trackpng import _summary
from x6wd.app import logview

REPO = Path(__file__).resolve().parents[1]


def _nmea(body: str) -> str:
    cs = 0
    for ch in body.encode():
        cs ^= ch
    return f"${body}*{cs:02X}\r\n"


def _epoch(t: datetime, k: int) -> str:
    hms, dmy = t.strftime("%H%M%S.00"), t.strftime("%d%m%y")
    lat = f"5147.{k % 1000:03d}"
    hdop = f"{1.0 + (k % 7) / 10:.1f}"
    return _nmea(f"GPRMC,{hms},A,{lat},N,00115.000,W,0.1,,{dmy},,,A") + _nmea(
        f"GPGGA,{hms},{lat},N,00115.000,W,1,08,{hdop},50.0,M,0.0,M,,"
    )


def _swapped_log(path: Path, seconds: int, *, session_step_at: int | None = None) -> None:
    """A 1 Hz receiver's log of ``seconds`` epochs written out of order in pairs (each pair's
    later epoch first: the time steps back 1 s every other epoch); ``session_step_at``: from
    that epoch on the clock is 52 min earlier (another session, one real jump among them)."""
    start = datetime(2026, 1, 1, 10, tzinfo=UTC)
    epochs = []
    for k in range(seconds):
        t = start + timedelta(seconds=k)
        if session_step_at is not None and k >= session_step_at:
            t -= timedelta(minutes=52)
        epochs.append(_epoch(t, k))
    out = []
    for i in range(0, len(epochs) - 1, 2):
        out += [epochs[i + 1], epochs[i]]
    path.write_text("".join(out))


def _plot_html(log: Path, out: Path) -> tuple[str, str]:
    """The page and stderr of the real CLI's ``x6wd plot LOG --format html``."""
    r = subprocess.run(
        [sys.executable, "-m", "x6wd", "plot", str(log), "--format", "html", "--out", str(out)],
        capture_output=True,
        text=True,
        cwd=REPO,
        timeout=300,
    )
    assert r.returncode == 0, r.stderr
    return (out / (log.stem + ".html")).read_text(), r.stderr


def _page_data(page: str) -> dict:
    m = re.search(r'id="x6wd-logview-data">(.*?)</script>', page, re.S)
    assert m is not None
    return json.loads(m.group(1))


def test_a_log_of_thousands_of_time_jumps_makes_a_page_of_bounded_size(tmp_path: Path) -> None:
    seconds = 2 * 3600  # 3600 steps back of 1 s, and one of 52 min in the middle
    log = tmp_path / "swapped.nmea"
    _swapped_log(log, seconds, session_step_at=3000)
    page, err = _plot_html(log, tmp_path / "out")
    data = _page_data(page)
    # the jumps kept are bounded as the series are (the old page: all 3601 in its data, a
    # dashed line per jump on each of its time panels)
    kept = data["time_jumps"]
    assert len(kept) <= 110, len(kept)  # MAX_JUMPS + LARGEST_JUMPS
    assert page.count('class="time-jump"') <= 4 * len(kept)
    assert data["time_jumps_total"] == 3601
    # the page of the same log in order (no jumps) and this one differ by the jumps' marks
    plain = tmp_path / "plain.nmea"
    start = datetime(2026, 1, 1, 10, tzinfo=UTC)
    plain.write_text("".join(_epoch(start + timedelta(seconds=k), k) for k in range(seconds)))
    plain_page, _ = _plot_html(plain, tmp_path / "plain")
    assert len(page) < len(plain_page) + 250_000, (len(page), len(plain_page))
    # the real session step (52 min back) is said and marked among the 1 s ones
    big = [j for j in kept if j["step_s"] < -3000]
    assert len(big) == 1 and big[0]["before_utc"] and big[0]["after_utc"]
    assert "3601 time jumps" in err and "largest" in err and "52 min" in err
    assert "time jumps (3601)" in page
    # the first jump is kept (the start's UTC is dated before it)
    assert kept[0]["line"] == 3


def test_jump_list_keeps_the_first_the_largest_and_a_stride() -> None:
    jumps = logview.JumpList()
    for k in range(100_000):
        step = -5000.0 if k == 77_777 else -1.0
        jumps.append(logview.TimeJump(float(k), k + 1, step))
    assert jumps.total == 100_000
    assert len(jumps) <= logview.MAX_JUMPS + logview.LARGEST_JUMPS
    assert jumps[0].line == 1
    assert any(j.step_s == -5000.0 for j in jumps)
    t = np.array([j.t_s for j in jumps])
    assert np.all(np.diff(t) > 0)  # in file order
    assert t[-1] > 90_000  # spread through the file, not only its start


def test_the_survey_plot_works_on_its_fixes_a_chunk_at_a_time(tmp_path: Path) -> None:
    """track.png of 400,000 fixes (a 111 h survey at 1 Hz): what the plot allocates beyond its
    input stays bounded (the old one turned every fix into nine int64 offsets and weights at
    once: about 145 MB traced here), and the picture does not depend on the chunk."""
    world = load_world(REPO / "config" / "scenarios" / "open_field.toml")
    rng = np.random.default_rng(7)
    fixes = np.column_stack((rng.normal(3.0, 2.0, 400_000), rng.normal(-1.0, 2.5, 400_000)))
    tracemalloc.start()
    try:
        trackpng.plot_survey(tmp_path / "a.png", world, (3.0, -1.0), fixes, _summary("x"))
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 60e6, f"{peak / 1e6:.0f} MB"
    # the same picture, byte for byte, from chunks of another size
    old = trackpng.DOT_CHUNK
    try:
        trackpng.DOT_CHUNK = 7_001
        trackpng.plot_survey(tmp_path / "b.png", world, (3.0, -1.0), fixes, _summary("x"))
    finally:
        trackpng.DOT_CHUNK = old
    assert (tmp_path / "a.png").read_bytes() == (tmp_path / "b.png").read_bytes()
