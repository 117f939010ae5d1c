"""The gap tool's input, after an outside audit: a baseline whose runs an outage leaves short
or empty is still fitted; a GGA satellite count that never changes carries no information;
corrupt sentences and missing counts or heights are said; logs whose positions come only from
GLL or GNS are read; clear messages for milliseconds, degrees-minutes, gzip and huge lines."""

from __future__ import annotations

import gzip
from pathlib import Path

import numpy as np
import pytest

from drivers.nmea import sentence
from x6wd.app.cli import build_parser
from x6wd.core.errors import ParseError
from x6wd.gap.io import errors_vs_point, read_track
from x6wd.gap.noise import fit_noise_model
from x6wd.gap.stats import layout_for
from x6wd.gap.surrogate import surrogate_run

# ------------------------------------------------- a baseline with runs lost to an outage


def test_noise_model_fits_runs_an_outage_left_short_or_empty() -> None:
    # A fitted 20-minute outage applied to the baseline runs leaves some with a few hundred
    # fixes and one with none: their regular grids differ in length (one sample for the
    # empty run), and averaging their periodograms raised "inhomogeneous shape".
    runs = [surrogate_run(1800.0, 1.0, np.random.default_rng(30 + i)) for i in range(6)]
    layout = layout_for(runs[0])
    short = np.asarray(runs[1].valid, dtype=bool).copy()
    short[600:] = False  # 600 s of fixes, then the outage to the end
    runs[1] = runs[1].with_(valid=short)
    runs[2] = runs[2].with_(valid=np.zeros(len(runs[2]), dtype=bool))  # lost whole
    model = fit_noise_model(runs, layout)
    whole = fit_noise_model([runs[0], *runs[3:]], layout)
    assert np.all(np.isfinite(model.sigma_m)) and np.all(np.isfinite(model.white_m))
    # the short and empty runs are left out: the law is that of the whole runs
    np.testing.assert_allclose(model.white_m, whole.white_m, rtol=1e-6)
    # every run lost whole: no spectrum, but no crash either
    empty = [r.with_(valid=np.zeros(len(r), dtype=bool)) for r in runs[:3]]
    assert np.all(np.isfinite(fit_noise_model(empty, layout).white_m))


# ------------------------------------------------------------------------ reading NMEA

N = 120  # two minutes at 1 Hz: enough to show each reading rule


def _hms(k: int) -> str:
    return f"12{k // 60:02d}{k % 60:02d}.00"


def _latlon(k: int) -> tuple[str, str]:
    return f"5145.{12000 + k % 7:05d},N", f"00115.{46000 + k % 5:05d},W"


def _log(tmp_path: Path, name: str, epoch: object) -> Path:
    """A log of N epochs, each the sentences ``epoch(k)`` gives."""
    path = tmp_path / name
    path.write_bytes(b"".join(b"".join(epoch(k)) for k in range(N)))  # type: ignore[operator]
    return path


def _gga(k: int, nsats: str = "08", alt: str = "60.0") -> bytes:
    lat, lon = _latlon(k)
    return sentence(f"GPGGA,{_hms(k)},{lat},{lon},1,{nsats},1.0,{alt},M,47.0,M,,")


def _rmc(k: int) -> bytes:
    lat, lon = _latlon(k)
    return sentence(f"GPRMC,{_hms(k)},A,{lat},{lon},0.1,,010120,,,A")


def test_a_count_that_never_changes_is_taken_as_no_counts(tmp_path: Path) -> None:
    track = read_track(_log(tmp_path, "cap12.nmea", lambda k: [_rmc(k), _gga(k, "12")]))
    assert np.all(track.nsats < 0)
    assert any("never changes" in note and "12" in note for note in track.notes)
    assert errors_vs_point(track, 51.752, -1.2577).nsats is None
    # a count that changes is kept
    varying = read_track(_log(tmp_path, "v.nmea", lambda k: [_rmc(k), _gga(k, f"{8 + k % 3:02d}")]))
    assert errors_vs_point(varying, 51.752, -1.2577).nsats is not None


def _corrupt(line: bytes) -> bytes:
    return line[:-4] + (b"00" if line[-4:-2] != b"00" else b"11") + line[-2:]


def test_bad_checksums_are_counted_and_a_few_missing_counts_filled(tmp_path: Path) -> None:
    # 3 of 120 GGA corrupt (2.5 %): their fixes come from RMC, without a count or height
    def epoch(k: int) -> list[bytes]:
        gga = _gga(k, f"{8 + k // 30:02d}", "61.0")
        return [_rmc(k), _corrupt(gga) if k in (10, 50, 90) else gga]

    track = read_track(_log(tmp_path, "badck.nmea", epoch))
    assert any("3 with a bad checksum" in note for note in track.notes), track.notes
    series = errors_vs_point(track, 51.752, -1.2577, 60.0)
    assert series.nsats is not None  # one epoch without a count used to drop them all
    assert np.all(np.asarray(series.nsats)[np.asarray(series.valid)] >= 8)
    assert any("no satellite count" in note for note in track.notes)
    # the missing heights are interpolated, not an up error of 0 (a perfect height)
    up = np.asarray(series.up_m)
    np.testing.assert_allclose(up[[10, 50, 90]], 1.0)


def test_many_missing_counts_or_heights_are_dropped_with_a_note(tmp_path: Path) -> None:
    def epoch(k: int) -> list[bytes]:
        gga = _gga(k, f"{8 + k // 30:02d}", "61.0")
        return [_rmc(k), _corrupt(gga) if k % 5 == 0 else gga]  # 20 % corrupt

    track = read_track(_log(tmp_path, "many.nmea", epoch))
    series = errors_vs_point(track, 51.752, -1.2577, 60.0)
    assert series.nsats is None
    assert np.all(np.asarray(series.up_m) == 0.0)  # no heights, not a mix of 1 m and 0
    assert any("24 of 120 fixes (20.0%) have no satellite count" in n for n in track.notes)
    assert any("have no height: the log's heights are not used" in n for n in track.notes)


def _zda(k: int, talker: str = "GP") -> bytes:
    return sentence(f"{talker}ZDA,{_hms(k)},01,01,2020,00,00")


@pytest.mark.parametrize("talker", ["GP", "GL"])
def test_gll_only_positions_are_read(tmp_path: Path, talker: str) -> None:
    def epoch(k: int) -> list[bytes]:
        lat, lon = _latlon(k)
        return [_zda(k, talker), sentence(f"{talker}GLL,{lat},{lon},{_hms(k)},A,A")]

    track = read_track(_log(tmp_path, "gll.nmea", epoch))
    assert len(track) == N and bool(np.all(track.valid))
    assert track.lat_deg[0] == pytest.approx(51 + 45.12 / 60, abs=1e-6)
    assert track.t_s[0] == pytest.approx(1577880000.0)
    assert any("GLL" in note for note in track.notes)


def test_gns_only_positions_are_read_with_counts_and_heights(tmp_path: Path) -> None:
    def epoch(k: int) -> list[bytes]:
        lat, lon = _latlon(k)
        gns = f"GNGNS,{_hms(k)},{lat},{lon},AA,{8 + k // 40:02d},1.1,63.2,47.7,,"
        return [_zda(k, "GN"), sentence(gns)]

    track = read_track(_log(tmp_path, "gns.nmea", epoch))
    assert len(track) == N and bool(np.all(track.valid))
    assert set(np.unique(track.nsats)) == {8.0, 9.0, 10.0}
    assert np.all(track.alt_m == 63.2)


def test_a_log_without_positions_names_what_it_holds(tmp_path: Path) -> None:
    path = tmp_path / "big.nmea"
    path.write_bytes(b"$GPGGA," + b"1" * 200_000 + b"\n")
    with pytest.raises(ParseError, match=r"GGA, RMC, GLL or GNS.*1 malformed"):
        read_track(path)


# --------------------------------------------------------------------------- messages


def test_a_gzip_log_is_named_as_such(tmp_path: Path) -> None:
    path = tmp_path / "log.nmea"  # no .gz suffix: told by its content
    path.write_bytes(gzip.compress(b"".join(_rmc(k) + _gga(k) for k in range(N))))
    with pytest.raises(ParseError, match=r"compressed \(gzip\): decompress it first"):
        read_track(path)


def test_epoch_milliseconds_in_a_csv_get_the_hint(tmp_path: Path) -> None:
    path = tmp_path / "ms.csv"
    rows = "".join(f"{1577880000000 + 1000 * k},51.752,-1.2577\n" for k in range(N))
    path.write_text("time,lat,lon\n" + rows)
    with pytest.raises(ParseError, match=r"milliseconds since 1970.*2020-01-01T12:00:00"):
        read_track(path)


def test_degrees_minutes_in_a_csv_are_named(tmp_path: Path) -> None:
    path = tmp_path / "dm.csv"
    rows = "".join(f"{1577880000 + k},5145.12,-115.4616\n" for k in range(N))
    path.write_text("time,lat,lon\n" + rows)
    with pytest.raises(ParseError, match=r"latitude beyond ±90°.*degrees and minutes"):
        read_track(path)


def test_several_sim_logs_after_one_sim_flag() -> None:
    argv = ["gap", "--real", "r.nmea", "--sim", "a.nmea", "b.nmea", "--sim", "c.nmea"]
    assert build_parser(argv).parse_args(argv).sim == ["a.nmea", "b.nmea", "c.nmea"]


def test_the_no_heights_note_says_the_height_errors_are_missing() -> None:
    # --truth without ALT on a log with GGA altitudes: stats' note said "the real log has no
    # heights" beside "altitude 64 m (the real log's mean altitude)"
    from x6wd.gap.cli import _heights_not_compared

    note = (
        "the real log has no satellite sets or heights: the baseline runs' are set aside"
        " too, so that every statistic reads the same observables"
    )
    assert _heights_not_compared(note, "--truth has no ALT") == (
        "the real log has no satellite sets or height errors (its heights are not compared:"
        " --truth has no ALT): the baseline runs' are set aside too, so that every statistic"
        " reads the same observables"
    )
    assert _heights_not_compared("another note: heights:", "x") == "another note: heights:"
