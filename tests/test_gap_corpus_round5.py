"""Fifth outside audit (2026-12-05): ``x6wd gap`` on every NMEA log of gpsd's regression
corpus, the way a user runs it with only a log.

Two reading faults, both in which reader a file is handed to:

- ``gpspipe -r`` writes gpsd's VERSION, DEVICES and WATCH JSON before the NMEA it relays.
  Such a capture went to the recording reader (the file starts with "{") and was refused as
  "gpsd JSON ... recorded with gpspipe -r": what the user had done. ``x6wd decode`` reads
  the same file as NMEA.
- NMEA without checksums after comment lines (gpsd's HP 58534A log, "# Name: ..." then
  "$GPGGA,222449,...,M,,") went to the CSV reader: "time '$GPGGA' is neither seconds nor
  ISO 8601". Such a log is NMEA; the gap reader now reads its sentences as gpsd does
  (tests/test_decode_unchecksummed.py), and says the two epochs are too few.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from x6wd.gap.io import read_track

DATA = Path(__file__).resolve().parent / "data"
GPSPIPE_R = DATA / "gpspipe" / "lea-5h-gpspipe-r.log"
TELIT = DATA / "gap_logs" / "telit-he910.log"  # 149 fixes: long enough for a diagnosis
HP58534A = DATA / "gap_logs" / "hp58534a.log"  # gpsd's log: NMEA without checksums


def test_a_gpspipe_r_capture_is_read_as_the_nmea_it_relays(tmp_path: Path) -> None:
    preamble = [ln for ln in GPSPIPE_R.read_bytes().splitlines(True) if ln.startswith(b"{")]
    assert len(preamble) == 3  # VERSION, DEVICES, WATCH
    capture = tmp_path / "gpspipe-r.log"
    capture.write_bytes(b"".join(preamble) + TELIT.read_bytes())
    got, ref = read_track(capture), read_track(TELIT)
    assert int(np.sum(got.valid)) >= 60
    np.testing.assert_array_equal(got.t_s, ref.t_s)
    np.testing.assert_array_equal(got.lat_deg, ref.lat_deg)
    np.testing.assert_array_equal(got.lon_deg, ref.lon_deg)


def test_nmea_without_checksums_after_comments_is_read_as_nmea(tmp_path: Path) -> None:
    track = read_track(HP58534A)  # not the CSV reader's "neither seconds nor ISO 8601"
    assert len(track) == 2
    assert any("13 NMEA sentences without a checksum" in note for note in track.notes)
    # the same sentences without the comment lines: the same track
    bare = tmp_path / "bare.log"
    bare.write_bytes(
        b"".join(ln for ln in HP58534A.read_bytes().splitlines(True) if not ln.startswith(b"#"))
    )
    np.testing.assert_array_equal(read_track(bare).lat_deg, track.lat_deg)


def test_a_csv_or_a_checksummed_log_after_comments_reads_as_before(tmp_path: Path) -> None:
    csv = tmp_path / "fixes.csv"
    csv.write_text(
        "# logger v1\ntime,lat,lon\n"
        + "".join(f"{1.6e9 + k},44.0689,-121.3143\n" for k in range(80))
    )
    assert len(read_track(csv)) == 80
    assert int(np.sum(read_track(TELIT).valid)) >= 60  # gpsd's comment header, then NMEA
