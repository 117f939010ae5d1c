"""Round 15 outside audit of `x6wd gap` on malformed input (/tmp/s15/b_gapinput/REPORT.md;
its logs were made from `x6wd sim` output by gen.py/make*.py there; the logs here are built
in code, smaller, with the same feature):

- H1: a rerun into a used --out that fails (a full disk) left the earlier run's report.md and
  figures beside its own files, and a text output cut part-way;
- M1: a GLL- or GNS-only log with a leap second (23:59:60) or a bad time field crashed;
- M2: a hole with no sentence at all inside an NMEA log (the logger off) was filled with
  no-fix epochs and read as outages, unsaid; a 1 Hz log whose GGA is stamped 50 ms after its
  RMC read as 20 Hz, 19 of every 20 epochs "outages";
- M3: undated GGA epochs more than 12 h before the first date were put on the next day;
- M4: a static --truth 500 m from the fixes was reported as a 500 m bias; with --sim logs
  their own truth.csv was never compared with it;
- L1: a log of one repeated time stamp said "1 epoch" without what reading dropped;
- L2: a pipe's temporary copy into a full $TMPDIR was reported as the pipe unreadable;
- L5: a log without any fix was "no valid fix" without --truth, counted with it.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
from datetime import UTC, datetime, timedelta
from pathlib import Path

import numpy as np
import pytest

from drivers.nmea import sentence
from x6wd.app.cli import main
from x6wd.core.errors import ConfigError
from x6wd.core.outdir import write_output_file
from x6wd.gap.io import read_track

ROOT = Path(__file__).resolve().parents[1]
REAL_LOG = ROOT / "tests" / "data" / "nmea" / "ublox-8.log"
OPEN_FIELD = ROOT / "config" / "scenarios" / "open_field.toml"
LAT0_DEG, LON0_DEG = 51.752, -1.2577  # open_field.toml's origin (its runs' truth.csv)
T0 = datetime(2020, 6, 15, 10, 0, 0, tzinfo=UTC)


# ------------------------------------------------------------------------- log builders


def _hms(t: datetime) -> str:
    return t.strftime("%H%M%S.") + f"{t.microsecond // 10_000:02d}"


def _lat_lon(k: int, north_m: float = 0.0) -> tuple[str, str]:
    """NMEA latitude and longitude fields near open_field's origin (+ ``north_m``), a few
    metres of made-up white noise, the same for the same ``k`` (it was a smooth wander of
    sines, which read as a steady 0.55 m/s, a robot driving, once round 18 judged the steps'
    direction as x6wd.core.motion does)."""
    noise = np.random.default_rng(k).standard_normal(2)
    lat = LAT0_DEG + (north_m + 2.0 * noise[0]) / 111_200.0
    lon = -LON0_DEG + 2.0 * noise[1] / 69_000.0
    lat_m, lon_m = (lat - int(lat)) * 60.0, (lon - int(lon)) * 60.0
    return f"{int(lat):02d}{lat_m:08.5f},N", f"{int(lon):03d}{lon_m:08.5f},W"


def _rmc(t: datetime, k: int, north_m: float = 0.0) -> bytes:
    lat, lon = _lat_lon(k, north_m)
    return sentence(f"GPRMC,{_hms(t)},A,{lat},{lon},0.1,,{t.strftime('%d%m%y')},,,A")


def _gga(t: datetime, k: int, north_m: float = 0.0) -> bytes:
    lat, lon = _lat_lon(k, north_m)
    # a satellite count that changes (a constant one is noted as no counts)
    return sentence(f"GPGGA,{_hms(t)},{lat},{lon},1,{7 + k // 50 % 3:02d},1.0,60.0,M,47.0,M,,")


def _log(path: Path, times: list[datetime], north_m: float = 0.0) -> Path:
    """An RMC+GGA log at ``times``."""
    path.write_bytes(
        b"".join(_rmc(t, k, north_m) + _gga(t, k, north_m) for k, t in enumerate(times))
    )
    return path


def _seconds(start: datetime, n: int, step_s: float = 1.0) -> list[datetime]:
    return [start + timedelta(seconds=k * step_s) for k in range(n)]


def _gap(argv: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str]:
    """``x6wd gap argv --quiet --no-figures``: (exit code, stderr's last line)."""
    capsys.readouterr()
    code = main(["gap", *argv, "--quiet", "--no-figures"])
    err = capsys.readouterr().err.strip().splitlines()
    assert "Traceback" not in "\n".join(err)
    return code, err[-1] if err else ""


@pytest.fixture(scope="module")
def sim_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A 900 s open-field run (gps.nmea and truth.csv at the scenario's origin)."""
    out = tmp_path_factory.mktemp("sim")
    argv = ["sim", str(OPEN_FIELD), "--out", str(out), "--duration", "900", "--quiet"]
    assert main(argv) == 0
    return out


# ------------------------------------------------------------------------------------ H1


def test_a_rerun_cut_short_leaves_no_earlier_output_beside_its_own(
    tmp_path: Path, sim_dir: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "g"
    out.mkdir()
    # an earlier run's outputs (the tool's own headers), and the user's files
    earlier = {
        "report.md": "# x6wd gap report\n\nVerdict: no significant gap\n",
        "effects.toml": "# x6wd gap: effects\n",
        "validation.json": "{}\n",
        "calibrated.toml": "# x6wd gap: calibrated\n",
    }
    for name, text in earlier.items():
        (out / name).write_text(text)
    (out / "scatter.png").write_bytes(b"\x89PNG\r\n\x1a\n" + b"Matplotlib version3.8" + b"\0" * 64)
    (out / "map.png").write_bytes(b"\x89PNG\r\n\x1a\n my own map")  # not matplotlib's: kept
    (out / "notes.txt").write_text("mine\n")
    (out / "report.json").symlink_to("/dev/full")  # this run's first output fails
    code, last = _gap(
        ["--real", str(REAL_LOG), "--sim", str(sim_dir / "gps.nmea"), "--out", str(out)], capsys
    )
    assert code == 2 and "report.json" in last and "No space left on device" in last, last
    left = sorted(p.name for p in out.iterdir())
    assert left == ["map.png", "notes.txt", "report.json"], left  # report.json: the link
    assert (out / "report.json").is_symlink()


_LIMITED_WRITE = """
import resource, signal, sys
signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # a write past the limit fails (EFBIG)
resource.setrlimit(resource.RLIMIT_FSIZE, (4096, resource.getrlimit(resource.RLIMIT_FSIZE)[1]))
from x6wd.core.errors import ConfigError
from x6wd.core.outdir import write_output_file
try:
    write_output_file(sys.argv[1], "x" * 10000)
except ConfigError as exc:
    print(exc)
"""


@pytest.mark.parametrize("earlier", [None, "an earlier run's report\n"])
def test_a_text_output_cut_part_way_is_removed(tmp_path: Path, earlier: str | None) -> None:
    # a real part-way write: 4096 of 10000 bytes fit under the file size limit
    path = tmp_path / "validation.json"
    if earlier is not None:
        path.write_text(earlier)
    done = subprocess.run(
        [sys.executable, "-c", _LIMITED_WRITE, str(path)],
        capture_output=True, text=True, timeout=60, cwd=ROOT, check=True,
    )  # fmt: skip
    assert "validation.json" in done.stdout and "File too large" in done.stdout, done
    assert "the partly written file was removed" in done.stdout
    assert not path.exists()


def test_a_link_to_dev_full_is_never_removed(tmp_path: Path) -> None:
    link = tmp_path / "report.md"
    link.symlink_to("/dev/full")
    with pytest.raises(ConfigError, match=r"report\.md.*No space left on device"):
        write_output_file(link, "text\n")
    assert link.is_symlink() and os.readlink(link) == "/dev/full"
    with pytest.raises(ConfigError, match="No space left on device"):
        write_output_file("/dev/full", "text\n")
    assert Path("/dev/full").exists()


# ------------------------------------------------------------------------------------ M1


def _gll(t_text: str, k: int) -> bytes:
    lat, lon = _lat_lon(k)
    return sentence(f"GPGLL,{lat},{lon},{t_text},A,A")


def _gns(t_text: str, k: int) -> bytes:
    lat, lon = _lat_lon(k)
    return sentence(f"GNGNS,{t_text},{lat},{lon},AN,08,1.0,60.0,47.0,,")


def _zda(t_text: str, t: datetime) -> bytes:
    return sentence(f"GPZDA,{t_text},{t.strftime('%d,%m,%Y')},00,00")


def _leap_log(path: Path, position: object, bad_time: str | None = None) -> Path:
    """120 GLL or GNS positions (``position(time text, k)``) with ZDA dates around the leap
    second at the end of 2016: 23:59:00 ... 23:59:59, 23:59:60 (or ``bad_time`` instead),
    00:00:00 ... 00:00:58."""
    start = datetime(2016, 12, 31, 23, 59, 0, tzinfo=UTC)
    parts = []
    for k in range(120):
        t = start + timedelta(seconds=k if k < 60 else k - 1)
        text = (bad_time or "235960.00") if k == 60 else _hms(t)
        parts.append(position(text, k) + _zda(text, t))  # type: ignore[operator]
    path.write_bytes(b"".join(parts))
    return path


@pytest.mark.parametrize("kind", ["GLL", "GNS"])
def test_a_gll_or_gns_leap_second_is_left_out_not_a_crash(tmp_path: Path, kind: str) -> None:
    track = read_track(_leap_log(tmp_path / "leap.nmea", _gll if kind == "GLL" else _gns))
    assert len(track) == 119 and bool(np.all(np.diff(track.t_s) == 1.0))
    assert any("1 leap-second epoch (23:59:60 UTC) left out" in n for n in track.notes)


def test_a_gll_with_a_bad_time_field_is_an_epoch_without_a_time(tmp_path: Path) -> None:
    track = read_track(_leap_log(tmp_path / "bad.nmea", _gll, bad_time="006100.00"))
    assert any("1 epochs without a (valid) time dropped" in n for n in track.notes)
    assert int(np.count_nonzero(track.valid)) == 119


# ------------------------------------------------------------------------------------ M2


def test_a_logger_switched_off_for_an_hour_is_cut_not_an_outage(tmp_path: Path) -> None:
    times = _seconds(T0, 300) + _seconds(T0 + timedelta(seconds=300 + 3600), 200)
    track = read_track(_log(tmp_path / "gap1h.nmea", times))
    assert len(track) == 300 and bool(np.all(track.valid))  # the longer part, no no-fix
    (note,) = track.notes
    assert "no NMEA sentence at all" in note and "not an outage" in note, note
    assert "300 of 500 epochs kept" in note and "1 h 0 min 1 s" in note, note


def test_a_hole_the_receiver_filled_with_timeless_no_fix_sentences_stays_an_outage(
    tmp_path: Path,
) -> None:
    # a receiver that lost its time sends GGA with empty fields: it was sending
    times = _seconds(T0, 300) + _seconds(T0 + timedelta(seconds=400), 200)
    parts = [_rmc(t, k) + _gga(t, k) for k, t in enumerate(times)]
    parts[300:300] = [sentence("GPGGA,,,,,,0,00,99.99,,,,,,")] * 99
    path = tmp_path / "outage.nmea"
    path.write_bytes(b"".join(parts))
    track = read_track(path)
    assert len(track) == 600 and int(np.count_nonzero(track.valid)) == 500
    assert any("100 epochs missing from the log's regular 1 s steps" in n for n in track.notes)
    assert not any("cut" in n for n in track.notes), track.notes


def test_a_short_hole_is_filled_and_said(tmp_path: Path) -> None:
    times = [t for k, t in enumerate(_seconds(T0, 300)) if not 100 <= k < 103]
    track = read_track(_log(tmp_path / "short_hole.nmea", times))
    assert len(track) == 300 and int(np.count_nonzero(track.valid)) == 297
    (note,) = track.notes
    assert "3 epochs missing" in note and "the longest hole 3 epochs, 3 s" in note, note


def test_a_gga_stamped_50_ms_after_its_rmc_is_the_same_epoch(tmp_path: Path) -> None:
    parts = []
    for k, t in enumerate(_seconds(T0, 300)):
        parts += [_rmc(t, k), _gga(t + timedelta(milliseconds=50), k)]
    path = tmp_path / "splitstamp.nmea"
    path.write_bytes(b"".join(parts))
    track = read_track(path)
    assert len(track) == 300 and bool(np.all(track.valid))  # 1 Hz, not 20 Hz
    assert bool(np.all(np.diff(track.t_s) == 1.0))
    assert bool(np.all(np.isfinite(track.alt_m))) and bool(np.all(np.isfinite(track.speed_mps)))
    assert any("300 fixes whose RMC and GGA are stamped" in n for n in track.notes)


# ------------------------------------------------------------------------------------ M3


def test_undated_epochs_over_12_h_before_the_first_date_keep_their_day(tmp_path: Path) -> None:
    # GGA only from 10:00 to 22:59 (every minute), then RMC dated 150620 from 23:00
    times = _seconds(T0, 13 * 60 + 11, 60.0)
    parts = [(_rmc(t, k) if t.hour == 23 else b"") + _gga(t, k) for k, t in enumerate(times)]
    path = tmp_path / "undated13h.nmea"
    path.write_bytes(b"".join(parts))
    track = read_track(path)
    assert len(track) == len(times) and track.notes == (), track.notes
    assert track.t_s[0] == T0.timestamp() and track.t_s[-1] == times[-1].timestamp()


def test_undated_epochs_across_midnight_before_the_first_date(tmp_path: Path) -> None:
    # GGA only from 22:00 to 00:59, the first date at 01:00 on the 16th: the 15th's hours
    start = datetime(2020, 6, 15, 22, 0, tzinfo=UTC)
    times = _seconds(start, 3 * 60 + 10, 60.0)
    parts = [(_rmc(t, k) if t.hour == 1 else b"") + _gga(t, k) for k, t in enumerate(times)]
    path = tmp_path / "midnight.nmea"
    path.write_bytes(b"".join(parts))
    track = read_track(path)
    assert track.t_s[0] == start.timestamp() and track.t_s[-1] == times[-1].timestamp()


# ------------------------------------------------------------------------------------ M4


def test_a_point_truth_500_m_from_a_static_log_is_refused(
    tmp_path: Path, sim_dir: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    real = _log(tmp_path / "real.nmea", _seconds(T0, 300))
    truth = f"{LAT0_DEG + 500.0 / 111_200.0:.6f},{LON0_DEG}"
    argv = ["--real", str(real), "--sim", str(sim_dir / "gps.nmea"), "--truth", truth]
    code, last = _gap([*argv, "--out", str(tmp_path / "o")], capsys)
    assert code == 2 and f"--truth {truth}" in last and "real.nmea" in last, last
    assert re.search(r"a median (49\d|50\d) m from", last), last  # 500 m, in metres


def test_a_point_truth_far_from_the_sim_logs_own_truth_is_refused(
    tmp_path: Path, sim_dir: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # the real log and --truth 300 m north of the place the --sim run simulated
    real = _log(tmp_path / "real.nmea", _seconds(T0, 300), north_m=300.0)
    truth = f"{LAT0_DEG + 300.0 / 111_200.0:.6f},{LON0_DEG}"
    argv = ["--real", str(real), "--sim", str(sim_dir / "gps.nmea"), "--truth", truth]
    code, last = _gap([*argv, "--out", str(tmp_path / "o")], capsys)
    assert code == 2 and str(sim_dir / "truth.csv") in last, last
    assert re.search(r"lies (299|300|301) m from the point --truth", last), last
    assert f"--truth {truth}" in last


# ---------------------------------------------------------------------------- L1, L2, L5


def test_a_log_of_one_time_stamp_says_what_reading_dropped(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    real = _log(tmp_path / "allsame.nmea", [T0] * 300)
    code, last = _gap(["--real", str(real), "--out", str(tmp_path / "o")], capsys)
    assert code == 2 and "too short for a gap diagnosis: 1 epoch" in last, last
    assert "299 epochs repeating a time stamp" in last, last


_FULL_TMPDIR = """
import resource, signal
signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # a write past the limit fails (EFBIG)
resource.setrlimit(resource.RLIMIT_FSIZE, (4096, resource.getrlimit(resource.RLIMIT_FSIZE)[1]))
from x6wd.core.errors import DeviceUnavailable
from x6wd.gap.io import read_track
try:
    read_track("/dev/stdin")
except DeviceUnavailable as exc:
    print(exc)
"""


def test_a_pipes_copy_into_a_full_tmpdir_names_the_temporary_directory(tmp_path: Path) -> None:
    log = _log(tmp_path / "real.nmea", _seconds(T0, 300)).read_bytes()  # over 4096 bytes
    tmp = tmp_path / "tmpdir"
    tmp.mkdir()
    done = subprocess.run(
        [sys.executable, "-c", _FULL_TMPDIR], input=log, capture_output=True, timeout=60,
        cwd=ROOT, check=True, env={**os.environ, "TMPDIR": str(tmp)},
    )  # fmt: skip
    said = done.stdout.decode()
    assert "copied to a temporary file" in said and f"written in {tmp}:" in said, said
    assert "cannot read /dev/stdin" not in said


@pytest.mark.parametrize("truth", [None, f"{LAT0_DEG},{LON0_DEG}"])
def test_a_log_without_a_fix_is_counted_with_or_without_truth(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], truth: str | None
) -> None:
    parts = []
    for t in _seconds(T0, 300):
        parts.append(sentence(f"GPRMC,{_hms(t)},V,,,,,,,{t.strftime('%d%m%y')},,,N"))
        parts.append(sentence(f"GPGGA,{_hms(t)},,,,,0,00,99.99,,,,,,"))
    real = tmp_path / "nofix.nmea"
    real.write_bytes(b"".join(parts))
    argv = ["--real", str(real), "--out", str(tmp_path / "o")]
    code, last = _gap(argv + (["--truth", truth] if truth else []), capsys)
    assert code == 2 and "0 of 300 epochs have a fix" in last, last
