"""x6wd plot, round 13 audit: a log of sky reports only, the start of a log whose first fix
has no date, lines across holes, a true track's out-of-range rows, a run whose first part
retention deleted, and a recording's time jumps on its own axis."""

from __future__ import annotations

import itertools
import json
import re
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from x6wd.app import logview
from x6wd.app.cli import main as cli_main
from x6wd.core.recorder import Recorder
from x6wd.core.records import Mode, NavState, Telemetry

ROOT = Path(__file__).resolve().parents[1]
NMEA = ROOT / "tests" / "data" / "nmea"


def _nmea(body: str) -> str:
    cs = 0
    for ch in body.encode():
        cs ^= ch
    return f"${body}*{cs:02X}\r\n"


def _data(page: str) -> Any:
    m = re.search(r'id="x6wd-logview-data">(.*?)</script>', page, re.S)
    assert m is not None
    return json.loads(m.group(1))


def _svg(page: str, pid: str) -> str:
    m = re.search(rf'<svg id="svg-{pid}".*?</svg>', page, re.S)
    assert m is not None, pid
    return m.group(0)


def test_a_log_of_sky_reports_only_is_plotted(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # GSA and GSV only (no sentence times): timed by epochs at --rate, HDOP from GSA and the
    # satellites in view from GSV, as docs/logview.md says; it was refused "nothing to plot".
    log = tmp_path / "sky.log"
    lines = (NMEA / "ublox-lea-5h.log").read_bytes().splitlines(keepends=True)
    log.write_bytes(b"".join(ln for ln in lines if b"GSA," in ln or b"GSV," in ln))
    argv = ["plot", str(log), "--rate", "5", "--out", str(tmp_path), "--format", "html"]
    assert cli_main(argv) == 0, capsys.readouterr().err
    data = _data((tmp_path / "sky.html").read_text())
    (hdop,) = data["hdop"]
    (in_view,) = data["satellites"]
    assert hdop["label"] == "HDOP (sky)" and in_view["label"] == "in view"
    assert all(0.5 < v < 5 for v in hdop["v"] if v is not None) and len(hdop["v"]) > 5
    assert all(5 <= v <= 16 for v in in_view["v"] if v is not None)
    assert 0 < data["duration_s"] < 60  # epochs 0.2 s apart
    assert "hdop" not in data["missing"] and "satellites" not in data["missing"]
    # nothing at all is still refused, naming the file
    (tmp_path / "none.log").write_bytes(b"$GPTXT,01,01,02,hello*00\r\n")
    assert cli_main(["plot", str(tmp_path / "none.log"), "--out", str(tmp_path)]) == 2
    assert "none.log: no GPS fixes, sky reports or telemetry" in capsys.readouterr().err


def test_the_start_is_dated_from_the_first_dated_fix(tmp_path: Path) -> None:
    # A GGA before the first RMC has no date: the start is the first dated fix's UTC less
    # its time on the axis (as the real logs bundg_zeus_9 and bt451, which said "unknown").
    log = tmp_path / "gga_first.nmea"
    body = [_nmea("GPGGA,094736.00,5251.000,N,00518.000,E,1,08,1.1,0.0,M,0.0,M,,")]
    for s in range(37, 41):
        hms = f"0947{s:02d}.00"
        body.append(_nmea(f"GPRMC,{hms},A,5251.000,N,00518.000,E,0.1,,200818,,,A"))
        body.append(_nmea(f"GPGGA,{hms},5251.000,N,00518.000,E,1,08,1.1,0.0,M,0.0,M,,"))
    log.write_text("".join(body))
    view = logview.load(log)
    assert view.start_utc == "2018-08-20T09:47:36+00:00"
    assert logview.load(NMEA / "bundg_zeus_9.log").start_utc == "2018-08-20T09:47:36+00:00"
    # bt451: untimed epochs, then times from 15:25:04.5 (its first time: the axis's 0)
    assert logview.load(NMEA / "bt451.log").start_utc.startswith("2009-12-09T15:25:04.5")


def _outage_log(path: Path) -> None:
    """A 1 Hz receiver heading north, then west after a 40 s outage (no sentences at all),
    its HDOP and satellites used different either side."""
    start = datetime(2020, 1, 1, 12, 0, 0, tzinfo=UTC)
    out = []
    for k in [*range(15), *range(55, 70)]:
        t = start + timedelta(seconds=k)
        hms, dmy = t.strftime("%H%M%S.00"), t.strftime("%d%m%y")
        course, hdop, sats = ("355.0", "1.3", "07") if k < 15 else ("270.0", "0.9", "09")
        out.append(_nmea(f"GPRMC,{hms},A,5145.000,N,00115.000,W,1.0,{course},{dmy},,,A"))
        out.append(_nmea(f"GPGGA,{hms},5145.000,N,00115.000,W,1,{sats},{hdop},60.0,M,0.0,M,,"))
    path.write_text("".join(out))


def test_lines_break_across_an_outage(tmp_path: Path) -> None:
    # HDOP, satellites and the GPS course were one line across a 40 s hole (HDOP seemed to
    # fall steadily, a left turn from 355 to 270 degrees that was never made).
    log = tmp_path / "outage.nmea"
    _outage_log(log)
    view = logview.load(log)
    page = logview.html_page(view)
    for pid in ("hdop", "satellites", "heading"):
        svg = _svg(page, pid)
        xs = [
            [float(p.split(",")[0]) for p in pts.split()]
            for pts in re.findall(r'<polyline[^>]*points="([^"]*)"', svg)
        ]
        x0, x1 = float(re.findall(r'data-x0="([^"]+)"', svg)[0]), 69.0
        left, right = 56 + 14.5 / x1 * (900 - 56 - 16), 56 + 54.5 / x1 * (900 - 56 - 16)
        assert x0 == 0 and xs, pid
        # no segment of any line spans the hole
        for line in xs:
            assert not any(a < left and b > right for a, b in itertools.pairwise(line)), pid
    # the PNG's lines: broken too (NaN between the two sides), on real matplotlib axes
    pytest.importorskip("matplotlib")
    from matplotlib.figure import Figure

    from x6wd.app.plot import plot_series

    ax = Figure().add_subplot()
    assert plot_series(ax, view.hdop, view.jumps, dots=False)
    t = np.asarray(ax.lines[0].get_xdata(), dtype=float)
    v = np.asarray(ax.lines[0].get_ydata(), dtype=float)
    hole = np.flatnonzero(np.isnan(v))
    assert len(hole) == 1 and t[hole[0] - 1] == 14 and t[hole[0] + 1] == 55


def test_the_gap_rule() -> None:
    # a hole: a step over 3 times the median step and over 2 s; jitter and slow series not
    t = np.array([0.0, 1.0, 2.0, 3.0, 6.5, 7.5])  # 3.5 s: 3.5 median steps
    assert logview.gap_cuts(t) == [4.75]
    assert logview.gap_cuts(np.array([0.0, 1.0, 2.0, 4.9, 5.9])) == []  # 2.9 s: under 3 steps
    fast = np.arange(0.0, 10.0, 0.05)
    assert logview.gap_cuts(np.concatenate([fast, fast[-1] + 1.9 + fast])) == []  # < 2 s
    assert logview.gap_cuts(np.arange(0.0, 100.0, 10.0)) == []  # a slow series, evenly spaced
    assert logview.gap_cuts(np.array([5.0])) == [] and logview.gap_cuts(np.array([])) == []


def _short_run(rec: Recorder, t0: float, n: int) -> None:
    for k in range(n):
        t = t0 + k * 0.5
        rec.record_telemetry(
            Telemetry(t, Mode.RUNNING, NavState.STRAIGHT, "", filt_lat_deg=51.0 + k * 1e-6,
                      filt_lon_deg=-1.0, heading_deg=10.0)
        )  # fmt: skip


def _plot_with_truth_row(tmp_path: Path, row: str) -> tuple[Path, list[str]]:
    """A short recording and a true track whose fourth line is ``row``: the truth file and
    the plot's argv (without its format)."""
    rec_path = tmp_path / "r.jsonl"
    with Recorder(rec_path) as rec:
        _short_run(rec, 0.0, 10)
    truth = tmp_path / "mine.csv"
    truth.write_text(f"t_s,lat,lon\n0,51.0,-1.0\n1,51.0,-1.0\n{row}\n3,51.0,-1.0\n")
    return truth, ["plot", str(rec_path), "--truth", str(truth), "--out", str(tmp_path)]


@pytest.mark.parametrize(
    ("row", "said"),
    [
        ("2,51.75,200", "line 4: a true track's lon must be within [-180, 180] deg, got 200"),
        ("2,-91,-1.2", "line 4: a true track's lat must be within [-90, 90] deg, got -91"),
        ("2,nan,-1.2", "line 4: a true track needs finite numbers, got lat nan"),
        ("inf,51.75,-1.2", "line 4: a true track needs finite numbers, got t_s inf"),
    ],
)
def test_a_true_track_row_out_of_range_is_refused_naming_its_line(
    row: str, said: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    truth, argv = _plot_with_truth_row(tmp_path, row)
    assert cli_main([*argv, "--format", "html"]) == 2
    err = capsys.readouterr().err
    assert f"mine.csv {said}" in err and "Traceback" not in err
    # cut while written (no newline), the last line is skipped and counted, as before
    truth.write_text(f"t_s,lat,lon\n0,51.0,-1.0\n1,51.0,-1.0\n{row}")
    view = logview.load(tmp_path / "r.jsonl", truth=truth)
    assert view.counts["truncated_truth_lines"] == 1


def test_a_run_whose_first_part_retention_deleted_says_so(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # The daemon's run in parts; retention deletes the oldest part first. The plot drew the
    # rest as if it were the whole run: its start and duration with no word of what is gone.
    start = datetime(2026, 12, 6, 10, 11, 4, 250_000, tzinfo=UTC)
    now = [0.0]
    rec = Recorder.in_dir(
        tmp_path, max_bytes=20_000, utc_clock=lambda: start + timedelta(seconds=now[0])
    )
    with rec:
        for k in range(400):
            now[0] = 0.25 * k
            _short_run(rec, 5000.0 + now[0], 1)
        rec.record_event("shutdown", 5000.0 + now[0])
    parts = list(rec.paths)
    assert len(parts) > 3 and parts[0].name == "x6wd-20261206T101104Z.jsonl"
    parts[0].unlink()
    first_utc = json.loads(parts[1].read_text().splitlines()[0])["t_utc"]
    lost_s = (datetime.fromisoformat(first_utc) - start.replace(microsecond=0)).total_seconds()
    assert lost_s > 5
    argv = ["plot", str(tmp_path), "--out", str(tmp_path / "out"), "--format", "html"]
    assert cli_main(argv) == 0
    err = capsys.readouterr().err
    assert "part x6wd-20261206T101104Z.jsonl gone" in err and "time jumps" not in err
    assert "the run began at 2026-12-06T10:11:04+00:00 (its name)" in err
    page = (tmp_path / "out" / f"{parts[1].stem}.html").read_text()
    data = _data(page)
    assert data["missing_parts"] == ["x6wd-20261206T101104Z.jsonl"]
    assert data["missing_start_s"] == pytest.approx(lost_s, abs=1e-3)
    assert "missing parts" in page and f"about {lost_s:.1f} s before" in page
    # a middle part gone too: named; a whole run: nothing said
    parts[2].unlink()
    view = logview.load(parts[1])
    assert view.missing_parts == ["x6wd-20261206T101104Z.jsonl", parts[2].name]
    whole = tmp_path / "whole"
    whole.mkdir()
    with Recorder.in_dir(whole, max_bytes=20_000) as rec2:
        _short_run(rec2, 0.0, 300)
    assert len(rec2.paths) > 1
    view = logview.load(rec2.paths[0])
    assert view.missing_parts == [] and view.run_start_utc == "" and view.missing_start_s is None


def test_a_recordings_time_jump_is_on_its_own_axis(tmp_path: Path) -> None:
    # The daemon's t_mono is the system's monotonic clock (46069 s into a boot, say); a
    # recording holding two sessions had its jump placed at its t_mono, 46000 s off the axis
    # that starts at the first record: no mark on the panels, no break in the lines.
    path = tmp_path / "two.jsonl"
    with Recorder(path) as rec:
        _short_run(rec, 46_000.0, 40)  # 20 s
        _short_run(rec, 100.0, 40)  # the daemon started again: its clock too
    view = logview.load(path)
    (jump,) = view.jumps
    assert 19.5 < jump.t_s < 20.5 and view.duration_s == pytest.approx(40.0, abs=0.6)
    lo, hi = view.time_range()
    assert (lo, hi) == (0.0, pytest.approx(view.duration_s))
    page = logview.html_page(view)
    marks = re.findall(r'class="time-jump" x1="([\d.]+)"', _svg(page, "heading"))
    assert len(marks) == 1 and 56 < float(marks[0]) < 900 - 16
    assert len(re.findall(r"<polyline", _svg(page, "heading"))) == 2


@pytest.mark.parametrize(
    ("row", "said"),
    [
        ("2,51.75,180.00001", "lon must be within [-180, 180] deg, got 180.00001"),
        ("2,-90.0000003,-1.2", "lat must be within [-90, 90] deg, got -90.0000003"),
    ],
)
def test_a_true_track_value_just_out_of_range_is_said_as_written(
    row: str, said: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Printed with {:g}, 180.00001 read "got 180": a value in range, refused."""
    _truth, argv = _plot_with_truth_row(tmp_path, row)
    assert cli_main([*argv, "--format", "html"]) == 2
    err = capsys.readouterr().err
    assert f"mine.csv line 4: a true track's {said}\n" in err, err


def test_a_plot_of_a_cr_cr_lf_log_names_the_files_line(tmp_path: Path) -> None:
    """A Windows text-mode logger writes CR CR LF: each CR was a line end, so bt451's step
    back on line 112 was said at line 223 (of a 156-line file)."""
    log = tmp_path / "bt451_crcrlf.log"
    data = (NMEA / "bt451.log").read_bytes().replace(b"\r\n", b"\n")
    log.write_bytes(data.replace(b"\n", b"\r\r\n"))
    (jump,) = logview.load(log).jumps
    assert jump.line == 112 == logview.load(NMEA / "bt451.log").jumps[0].line
