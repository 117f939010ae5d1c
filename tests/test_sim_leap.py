"""The simulated receiver's NMEA UTC labels come from GPS time through the leap-second table:
the leap second at the end of 2016 prints as 23:59:60, and the seconds after it as UTC."""

from __future__ import annotations

from datetime import UTC, datetime, timedelta
from pathlib import Path

import numpy as np

from drivers.nmea import parse_time
from sim_backend.geodesy import gps_seconds_to_utc, utc_to_gps_seconds
from sim_backend.receiver import build_receiver
from sim_backend.world import load_world

SCENARIO = """
name = "leap"
start_utc = "{start}"
duration_s = 30

[origin]
lat_deg = 40.0
lon_deg = -105.0
alt_m = 1600

[gnss]
fidelity = "pseudorange"
rate_hz = 4
"""


def _gga_times(tmp_path: Path, start: str, t_s: np.ndarray) -> list[tuple[str, str]]:
    """(GGA time, RMC date) of each epoch at ``t_s``, by the batch path; the per-epoch path
    must print the same bytes."""
    path = tmp_path / "leap.toml"
    path.write_text(SCENARIO.format(start=start), encoding="utf-8")
    receiver = build_receiver(load_world(path), 11)
    zeros = np.zeros((t_s.shape[0], 3))
    batch = receiver.batch(t_s, zeros, zeros)
    bursts = receiver.formatter.format_batch(batch)
    assert bursts == build_receiver(load_world(path), 11).formatter.format_epochs(batch.epochs())
    out = []
    for burst in bursts:
        lines = burst.decode("ascii").split("\r\n")
        rmc = next(x for x in lines if x.startswith("$GPRMC")).split(",")
        gga = next(x for x in lines if x.startswith("$GPGGA")).split(",")
        assert gga[6] == "1"  # a fix: the labels are the fix's
        out.append((gga[1], rmc[9]))
    return out


def test_the_leap_second_prints_as_23_59_60_and_utc_after_it_is_gps_minus_18(
    tmp_path: Path,
) -> None:
    start = datetime(2016, 12, 31, 23, 59, 55, tzinfo=UTC)
    # 0.25 s steps, and 10.996 s: 23:59:60.996 rounds to the next day's 000000.00
    grid_s = np.arange(0.0, 12.0, 0.25)
    t_s = np.sort(np.concatenate((grid_s, [10.996])))
    labels = _gga_times(tmp_path, "2016-12-31T23:59:55Z", t_s)
    by_t = dict(zip(t_s.tolist(), labels, strict=True))
    assert by_t[4.75] == ("235959.75", "311216")
    assert by_t[5.0] == ("235960.00", "311216")
    assert by_t[5.75] == ("235960.75", "311216")
    assert by_t[6.0] == ("000000.00", "010117")
    assert by_t[10.996] == ("000005.00", "010117")
    gps0_s = utc_to_gps_seconds(start)
    for t, (hms, dmy) in by_t.items():
        tod_us = parse_time(hms)
        assert tod_us is not None
        if hms.startswith("2359"):
            assert dmy == "311216"
        else:  # after the leap: UTC is GPS - 18 s, as geodesy maps it
            utc = gps_seconds_to_utc(gps0_s + round(t, 2))
            assert (utc.strftime("%H%M%S.") + f"{utc.microsecond // 10_000:02d}", dmy) == (
                hms,
                utc.strftime("%d%m%y"),
            )
    # one label per GPS second: never the same twice, never a step back
    keys = [
        ((d := by_t[t][1])[4:] + d[2:4] + d[:2], parse_time(by_t[t][0])) for t in grid_s.tolist()
    ]
    assert keys == sorted(keys) and len(set(keys)) == len(keys)


def test_a_run_that_spans_no_leap_second_is_labelled_start_plus_t(tmp_path: Path) -> None:
    # the hour before the 2016 leap second, and one in 2020 (no leap second since 2017)
    for start in (datetime(2016, 12, 31, 22, 59, 55, tzinfo=UTC),
                  datetime(2020, 1, 1, 23, 59, 55, tzinfo=UTC)):  # fmt: skip
        t_s = np.arange(0.0, 12.0, 0.25)
        labels = _gga_times(tmp_path, start.isoformat(), t_s)
        want = [start + timedelta(seconds=t) for t in t_s.tolist()]
        assert labels == [
            (u.strftime("%H%M%S.") + f"{u.microsecond // 10_000:02d}", u.strftime("%d%m%y"))
            for u in want
        ]
