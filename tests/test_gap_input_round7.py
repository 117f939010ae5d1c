"""x6wd gap: input findings of the outside audit, round 7. A CSV or RTKLIB .pos log whose
logger was killed while writing leaves a last line cut off: it was read as a real fix
(a CSV) or refused with exit 2 (a .pos). The logs here are the first rows of
tests/data/static/mobile.csv and tests/data/urban/rover_1Hz_spp.pos, cut as the audit cut
them. Also: the far-from-truth message names the log it checks (--real or --sim)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from x6wd.core.errors import ConfigError, ParseError
from x6wd.gap.io import check_near_truth, errors_vs_point, read_track

DATA = Path(__file__).parent / "data"
MOBILE = DATA / "static" / "mobile.csv"
POS = DATA / "urban" / "rover_1Hz_spp.pos"
# The audit's cut line: row 301 of mobile.csv killed inside LONGITUDE (6 of its 12 fields)
CUT_LON = '"vagabund", 301, 1589815253.671234567, 1589819292.000000000, 39.821672257, -105.09'


def _mobile_head(n_rows: int = 300) -> str:
    """The header and the first ``n_rows`` rows of mobile.csv, each line ending in a newline."""
    lines = MOBILE.read_text().splitlines(keepends=True)
    return "".join(lines[: n_rows + 1])


def _same_track(a, b) -> None:
    for name in ("t_s", "lat_deg", "lon_deg", "alt_m", "valid", "nsats"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)


def test_csv_last_row_cut_in_a_field_is_skipped_and_named(tmp_path: Path) -> None:
    clean = tmp_path / "clean300.csv"
    clean.write_text(_mobile_head())
    cut = tmp_path / "trunc_lon.csv"
    cut.write_text(_mobile_head() + CUT_LON)  # no newline: the logger died there
    clean_track, cut_track = read_track(clean), read_track(cut)
    _same_track(cut_track, clean_track)  # the cut row was a fix at lon -105.09, 440 m off
    note = [n for n in cut_track.notes if "line 302" in n]
    assert note and "6 of 12 fields" in note[0] and "skipped" in note[0], cut_track.notes
    assert not any("no height" in n for n in cut_track.notes), cut_track.notes


def test_csv_last_row_cut_in_the_time_field_is_not_a_time_error(tmp_path: Path) -> None:
    cut = tmp_path / "trunc_time.csv"
    cut.write_text(_mobile_head() + '"vagabund", 301, 1589815253.671234567, 15898')
    track = read_track(cut)
    clean = tmp_path / "clean.csv"
    clean.write_text(_mobile_head())
    _same_track(track, read_track(clean))
    text = " | ".join(track.notes)
    assert "went back in time" not in text and "time axis cut" not in text, text
    assert "line 302: 4 of 12 fields" in text, text


def test_csv_of_one_cut_row_is_no_epoch(tmp_path: Path) -> None:
    path = tmp_path / "one.csv"
    path.write_text("time,lat,lon\n1,2")
    with pytest.raises(ParseError, match=r"line 2: 2 of 3 fields"):
        read_track(path)


def test_csv_short_row_in_the_middle_is_skipped_and_counted(tmp_path: Path) -> None:
    rows = [f"{k},45.0,7.0000{k % 3},100.0" for k in range(20)]
    rows[7] = "7,45.0"  # a row that lost its end (a logger restarted on the same file)
    rows[12] = "12,45.0,7.0"  # no height
    path = tmp_path / "mid.csv"
    path.write_text("time,lat,lon,alt\n" + "\n".join(rows) + "\n")
    track = read_track(path)
    kept = track.t_s[track.valid].tolist()  # the skipped rows' epochs are no-fix epochs
    assert len(kept) == 18 and 7.0 not in kept and 12.0 not in kept, kept
    text = " | ".join(track.notes)
    assert "2 rows with fewer fields than the header's 4" in text, text
    assert "line 9 (2 of 4)" in text and "line 14 (3 of 4)" in text, text


def test_headerless_csv_short_row_is_skipped(tmp_path: Path) -> None:
    path = tmp_path / "bare.csv"
    path.write_text("1,45.0,7.0\n2,45.0,7.0\n3,45.0,7.0\n4,45.0\n")
    track = read_track(path)
    assert track.t_s.tolist() == [1.0, 2.0, 3.0]
    assert any("line 4: 2 of 3 fields" in n for n in track.notes), track.notes


def test_csv_open_last_line_whose_last_field_is_read_is_skipped(tmp_path: Path) -> None:
    # All fields there, no newline: the logger may have died inside the longitude (7.0123
    # written as 7.0). Field counts cannot tell; the missing line ending can.
    path = tmp_path / "open.csv"
    path.write_text("time,lat,lon\n1,45.0,7.0123\n2,45.0,7.0123\n3,45.0,7.0")
    track = read_track(path)
    assert track.t_s.tolist() == [1.0, 2.0]
    note = [n for n in track.notes if "line 4" in n]
    assert note and "no line ending" in note[0] and "'lon'" in note[0], track.notes


def test_csv_open_last_line_whose_last_field_is_not_read_is_kept(tmp_path: Path) -> None:
    # mobile.csv's last column (COURSE) is not read: a cut there leaves every read field whole
    clean = tmp_path / "clean.csv"
    clean.write_text(_mobile_head())
    open_end = tmp_path / "open.csv"
    open_end.write_text(_mobile_head().rstrip("\n"))
    _same_track(read_track(open_end), read_track(clean))


def _pos_head(n_lines: int = 60) -> str:
    return "".join(POS.read_text().splitlines(keepends=True)[:n_lines])


def test_pos_last_line_cut_is_skipped_with_a_note(tmp_path: Path) -> None:
    head = _pos_head()
    last = POS.read_text().splitlines()[60]
    clean = tmp_path / "clean.pos"
    clean.write_text(head)
    cut = tmp_path / "cut.pos"
    cut.write_text(head + last[:40])  # inside the longitude: 3 fields
    track = read_track(cut)  # was ParseError (exit 2): not an RTKLIB .pos line
    _same_track(track, read_track(clean))
    note = [n for n in track.notes if "line 61" in n]
    assert note and "cut off" in note[0] and "skipped" in note[0], track.notes


def test_pos_malformed_line_in_the_middle_still_refused(tmp_path: Path) -> None:
    lines = _pos_head().splitlines(keepends=True)
    lines[30] = lines[30][:40] + "\n"
    path = tmp_path / "mid.pos"
    path.write_text("".join(lines))
    with pytest.raises(ParseError, match=r":31: not an RTKLIB .pos line"):
        read_track(path)


def _far_csv(path: Path) -> Path:
    path.write_text("time,lat,lon\n" + "".join(f"{k},10.0,10.0\n" for k in range(30)))
    return path


def test_far_from_truth_message_names_the_log_checked(tmp_path: Path) -> None:
    track = read_track(_far_csv(tmp_path / "far.csv"))
    series = errors_vs_point(track, 39.82, -105.09, 0.0)
    with pytest.raises(ConfigError) as real:
        check_near_truth(series, track.source, log="real")
    assert "--sim" not in str(real.value) and "the real log" in str(real.value), real.value
    assert "--truth" in str(real.value)
    with pytest.raises(ConfigError) as sim:
        check_near_truth(series, track.source, log="sim")
    assert "--sim log must simulate the real log's place" in str(sim.value), sim.value


def test_far_real_log_is_not_told_about_sim_logs(tmp_path: Path, capsys) -> None:
    # The audit: --real firefly-II.log with a --truth 1471.7 km away was told "(a --sim log
    # must simulate the real log's place ...)". The CLI says which log it checks.
    from x6wd.app.cli import main as x6wd_main

    far = _far_csv(tmp_path / "far.csv")
    argv = ["gap", "--real", str(far), "--truth", "39.82,-105.09", "--out", str(tmp_path / "o")]
    assert x6wd_main([*argv, "--quiet", "--no-figures"]) == 2
    err = capsys.readouterr().err
    assert "far.csv" in err and "km from the truth" in err, err
    assert "(a --sim log must simulate" not in err and "--sim" not in err, err
    assert "(the real log (--real))" in err and "the real log's place" in err, err


@pytest.mark.parametrize("kind", ["fifo", "pipe"])
def test_a_log_on_a_pipe_or_fifo_is_read_whole(tmp_path: Path, kind: str) -> None:
    """`x6wd gap --real <(zcat log.gz)`: the reader sniffed the head, then opened the path
    again, so a pipe lost its first 64 KB ("no position epochs found" on a short log) and a
    FIFO's second open waited for ever. Now a path that is not a regular file is read once
    into a temporary copy: the same epochs as the file, messages naming the path."""
    import os
    import threading

    log = Path(__file__).parent / "data" / "nmea" / "quectel-l76k-dual.log"
    data = log.read_bytes()
    assert len(data) > 3 * 65536
    if kind == "fifo":
        path = tmp_path / "log.fifo"
        os.mkfifo(path)

        def write() -> None:
            with open(path, "wb") as f:
                f.write(data)

    else:
        r, w = os.pipe()
        path = Path(f"/dev/fd/{r}")

        def write() -> None:
            with os.fdopen(w, "wb") as f:
                f.write(data)

    writer = threading.Thread(target=write, daemon=True)
    writer.start()
    try:
        track = read_track(path)
    finally:
        writer.join(10)
        if kind == "pipe":
            os.close(r)
    whole = read_track(log)
    assert len(track.t_s) == len(whole.t_s) > 0
    assert np.array_equal(np.asarray(track.valid), np.asarray(whole.valid))
    assert track.source == str(path)
