"""A receiver restarted without its clock in the middle of a log (round 19).

A cold restart without a backup battery dates the receiver's no-fix sentences 1980-01-06
(or its firmware's date, or counts the time of day from 00:00) until it has decoded the
time. Sorted by time those epochs went to the log's far end and the hole they left was
read as the logger's: half of a 1 h log was dropped, with a note that no sentence came at
all. They are now dropped as a clock excursion and the hole read as the receiver's outage.
"""

from __future__ import annotations

from datetime import datetime, timedelta
from pathlib import Path

import pytest

from x6wd.gap.io import read_track

T0 = datetime(2026, 12, 7, 10, 0, 0)


def sentence(body: str) -> str:
    check = 0
    for ch in body:
        check ^= ord(ch)
    return f"${body}*{check:02X}\r\n"


def fix(t: datetime) -> list[str]:
    tod, date = t.strftime("%H%M%S.00"), t.strftime("%d%m%y")
    return [
        sentence(f"GPGGA,{tod},5230.0000,N,01320.0000,E,1,08,1.0,50.0,M,40.0,M,,"),
        sentence(f"GPRMC,{tod},A,5230.0000,N,01320.0000,E,0.0,0.0,{date},,,A"),
    ]


def no_fix(t: datetime, dated: bool = True) -> list[str]:
    tod, date = t.strftime("%H%M%S.00"), t.strftime("%d%m%y") if dated else ""
    return [
        sentence(f"GPGGA,{tod},,,,,0,00,99.99,,,,,,"),
        sentence(f"GPRMC,{tod},V,,,,,,,{date},,,N"),
    ]


def write(tmp_path: Path, lines: list[str]) -> Path:
    path = tmp_path / "log.nmea"
    path.write_text("".join(lines))
    return path


def test_a_mid_log_restart_dated_1980_keeps_the_whole_log(tmp_path: Path) -> None:
    lines: list[str] = []
    for k in range(3600):
        if 1800 <= k < 1920:  # two minutes of a clock counting from the GPS epoch
            lines += no_fix(datetime(1980, 1, 6) + timedelta(seconds=k - 1800))
        else:
            lines += fix(T0 + timedelta(seconds=k))
    track = read_track(write(tmp_path, lines))
    assert track.t_s[-1] - track.t_s[0] == 3599.0
    assert int(track.valid.sum()) == 3480  # the restart is an outage of 120 s
    notes = " ".join(track.notes)
    assert "120 epochs dated away from the log's own time" in notes, track.notes
    assert "no NMEA sentence at all" not in notes


def test_a_time_of_day_from_midnight_after_a_silent_reboot(tmp_path: Path) -> None:
    lines: list[str] = []
    for k in range(3600):
        if 1800 <= k < 1810:
            continue  # the reboot: nothing sent
        if 1810 <= k < 1900:  # no date yet, the time of day from 00:00
            lines += no_fix(datetime(2000, 1, 1) + timedelta(seconds=k - 1810), dated=False)
        else:
            lines += fix(T0 + timedelta(seconds=k))
    track = read_track(write(tmp_path, lines))
    assert track.t_s[-1] - track.t_s[0] == 3599.0
    assert int(track.valid.sum()) == 3500


@pytest.mark.parametrize("off_s", [5, 90, 600])
def test_a_restart_after_the_receiver_was_off_keeps_the_whole_log(
    tmp_path: Path, off_s: int
) -> None:
    # a review (round 19): a receiver loses its clock by being off (no backup battery); off
    # over 60 s, the first version read the hole as the logger's and dropped 10 minutes
    lines = [s for k in range(600) for s in fix(T0 + timedelta(seconds=k))]
    lines += [s for k in range(45) for s in no_fix(datetime(1980, 1, 6) + timedelta(0, k))]
    back = 600 + off_s + 45
    lines += [s for k in range(1800) for s in fix(T0 + timedelta(seconds=back + k))]
    track = read_track(write(tmp_path, lines))
    assert int(track.valid.sum()) == 2400, track.notes
    assert track.t_s[-1] - track.t_s[0] == back + 1799, track.notes
    assert "no NMEA sentence at all" not in " ".join(track.notes)


def test_sessions_of_fixes_out_of_order_are_still_the_log_s(tmp_path: Path) -> None:
    # fixes are never a clock not yet set (a receiver with a fix knows the time), even when
    # the hole they leave is just as long as they are
    lines: list[str] = []
    for start_s in (0, 4 * 3600, 3600):
        lines += [s for k in range(1800) for s in fix(T0 + timedelta(seconds=start_s + k))]
    track = read_track(write(tmp_path, lines))
    notes = " ".join(track.notes)
    assert "dated away from the log's own time" not in notes
    assert "went back in time" in notes


def test_sessions_joined_hours_apart_are_not_an_excursion(tmp_path: Path) -> None:
    lines = [s for k in range(1800) for s in fix(T0 + timedelta(seconds=k))]
    lines += [s for k in range(2400) for s in fix(T0 + timedelta(seconds=7200 + k))]
    track = read_track(write(tmp_path, lines))
    assert track.t_s.size == 2400  # the longer session, as before
    assert "no NMEA sentence at all" in " ".join(track.notes)


def test_csv_times_without_a_zone_are_said_to_be_read_as_utc(tmp_path: Path) -> None:
    rows = [f"2026-12-07T10:00:0{k}{{}},52.5,13.3\n" for k in range(4)]
    naive, zoned = tmp_path / "naive.csv", tmp_path / "zoned.csv"
    naive.write_text("time,lat,lon\n" + "".join(r.format("") for r in rows))
    zoned.write_text("time,lat,lon\n" + "".join(r.format("Z") for r in rows))
    said = [n for n in read_track(naive).notes if "without a time zone" in n]
    assert said and "4 times" in said[0] and "read as UTC" in said[0], said
    assert not [n for n in read_track(zoned).notes if "time zone" in n]


def test_a_restart_in_a_gll_log_dated_by_zda(tmp_path: Path) -> None:
    lines: list[str] = []
    for k in range(1200):
        restart = 600 <= k < 660
        t = datetime(1980, 1, 6) + timedelta(seconds=k - 600) if restart else T0 + timedelta(0, k)
        tod = t.strftime("%H%M%S.00")
        if k % 60 == 0 or k == 600 or k == 660:
            lines.append(sentence(f"GPZDA,{tod},{t.day:02d},{t.month:02d},{t.year},00,00"))
        fixed = "5230.0000,N,01320.0000,E" if not restart else ",,,"
        lines.append(
            sentence(f"GPGLL,{fixed},{tod},{'V' if restart else 'A'},{'N' if restart else 'A'}")
        )
    track = read_track(write(tmp_path, lines))
    assert track.t_s[-1] - track.t_s[0] == 1199.0, track.notes
    assert "60 epochs dated away from the log's own time" in " ".join(track.notes), track.notes
