"""`x6wd plot` (x6wd.app.logview): the HTML page and PNG of a simulated run and a real NMEA log.

The values drawn are checked against the recording read independently (the recorder's own
reader) and against the simulator's summary of the same run (its raw-fix error statistics).
"""

from __future__ import annotations

import json
import math
import re
import shutil
import struct
import subprocess
import sys
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from sim_backend.mission import run_mission
from sim_backend.world import load_world
from x6wd.app import logview
from x6wd.app.cli import main as cli_main
from x6wd.app.decode import decode_path
from x6wd.core.config import NavigationConfig, SafetyConfig
from x6wd.core.health import HealthTracker
from x6wd.core.recorder import Recorder, read_recording
from x6wd.core.records import Mode, NavState, StateChange, Telemetry
from x6wd.loop.runner import Runner
from x6wd.nav.controller import Controller

ROOT = Path(__file__).resolve().parent.parent
NMEA_LOG = ROOT / "tests" / "data" / "nmea" / "ublox-lea-5h.log"


@pytest.fixture(scope="module")
def sim_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The shipped default scenario, 45 s simulated: recording.jsonl, truth.csv, summary."""
    out = tmp_path_factory.mktemp("logview_sim")
    run_mission(load_world(ROOT / "config" / "scenarios" / "default.toml"), out, duration_s=45.0)
    return out


def page_data(page: str) -> dict[str, Any]:
    m = re.search(r'<script type="application/json" id="x6wd-logview-data">(.*?)</script>', page)
    assert m is not None
    data: dict[str, Any] = json.loads(m.group(1))
    return data


def drawn_points(page: str, panel: str, label: str) -> np.ndarray:
    """The (x, y) data values of a series as drawn: its SVG points mapped back through the
    panel's axes (data-x0/x1/y0/y1 and the plot area's pixel edges)."""
    svg = re.search(rf'<svg id="svg-{panel}"([^>]*)>(.*?)</svg>', page, re.S)
    assert svg is not None, panel
    attrs = dict(re.findall(r'data-([\w-]+)="([^"]*)"', svg.group(1)))
    a = {k: float(v) for k, v in attrs.items()}
    group = re.search(rf'<g class="series" data-label="{re.escape(label)}">(.*?)</g>', svg.group(2))
    assert group is not None, label
    pts = [
        tuple(map(float, p.split(",")))
        for line in re.findall(r'points="([^"]*)"', group.group(1))
        for p in line.split()
    ]
    px = np.array(pts)
    x = a["x0"] + (px[:, 0] - a["plot-left"]) / (a["plot-right"] - a["plot-left"]) * (
        a["x1"] - a["x0"]
    )
    y = a["y0"] + (a["plot-bottom"] - px[:, 1]) / (a["plot-bottom"] - a["plot-top"]) * (
        a["y1"] - a["y0"]
    )
    return np.column_stack([x, y])


def test_html_is_self_contained_with_every_panel(sim_run: Path) -> None:
    page = logview.render_html(sim_run / "recording.jsonl")
    assert page.startswith("<!DOCTYPE html>")
    # nothing fetched: no address at all, no external script, style, image or frame
    assert "http://" not in page and "https://" not in page
    assert not re.search(r"<(script|img|iframe|link)[^>]*\b(src|href)=", page)
    for pid in logview.PANELS:
        section = re.search(rf'<section id="panel-{pid}">(.*?)</section>', page, re.S)
        assert section is not None, pid
    data = page_data(page)
    # a simulated mission has everything but device faults
    assert set(data["missing"]) == {"faults"}, data["missing"]
    for pid in ("track", "error", "hdop", "satellites", "heading", "states", "holds"):
        assert f'<svg id="svg-{pid}"' in page, pid


def test_series_match_the_recording(sim_run: Path) -> None:
    rec = sim_run / "recording.jsonl"
    page = logview.render_html(rec)
    data = page_data(page)
    records = list(read_recording(rec))
    t0 = records[0].t_mono
    fixes = [r.data for r in records if r.type == "fix"]
    hdop = next(s for s in data["hdop"] if s["label"] == "HDOP (fix)")
    assert len(hdop["v"]) == len(fixes)
    assert np.allclose(hdop["v"], [f["hdop"] for f in fixes], atol=1e-4)
    assert np.allclose(hdop["t_s"], [f["t_s"] - t0 for f in fixes], atol=1e-3)
    used = next(s for s in data["satellites"] if s["label"] == "used (fix)")
    assert used["v"] == [f["sats_used"] for f in fixes]
    seen = next(s for s in data["satellites"] if s["label"] == "in view")
    skies = [r.data for r in records if r.type == "sky"]
    assert seen["v"] == [len(s["satellites"]) for s in skies]

    # the fix error against truth.csv is the simulator's own figure for the same run
    summary = json.loads((sim_run / "summary.json").read_text())
    err = np.array(next(s for s in data["error"] if s["label"] == "GPS fix")["v"])
    raw = summary["raw_error"]
    assert len(err) == raw["n"]
    assert err.mean() == pytest.approx(raw["mean_m"], abs=0.01)
    assert float(np.sqrt(np.mean(err**2))) == pytest.approx(raw["rms_m"], abs=0.01)
    assert err.max() == pytest.approx(raw["max_m"], abs=0.01)

    # holds and states: the summary's hold periods and the recording's state changes
    holds = [(h["t0_s"] + t0, h["t1_s"] + t0) for h in data["holds"]]
    startup = summary["extra"]["startup_wait_s"]  # drawn as a hold, not counted as one
    assert np.allclose(holds, [startup, *summary["extra"]["holds_s"]], atol=2e-3)
    nav = [i for i in data["states"] if i["lane"] == "navigation"]
    changes = [r.data for r in records if r.type == "state" and r.data["new"] in set(NavState)]
    changes = [c for c in changes if not c["reason"].startswith("mode:")]
    assert [i["label"] for i in nav[1:]] == [c["new"] for c in changes]
    assert np.allclose([i["t0_s"] for i in nav[1:]], [c["t_s"] - t0 for c in changes], atol=1e-3)

    # what is drawn is what is in the data: the error curve, mapped back from the SVG
    drawn = drawn_points(page, "error", "GPS fix")
    t_err = np.array(next(s for s in data["error"] if s["label"] == "GPS fix")["t_s"])
    assert len(drawn) == len(err)
    assert np.allclose(drawn[:, 0], t_err, atol=0.1)  # 0.1 px rounding of ~860 px for 45 s
    assert np.allclose(drawn[:, 1], err, atol=0.03)


def test_png_of_a_simulated_run(sim_run: Path, tmp_path: Path) -> None:
    rc = cli_main(["plot", str(sim_run / "recording.jsonl"), "--out", str(tmp_path / "plot")])
    assert rc == 0
    png = tmp_path / "plot" / "recording.png"
    blob = png.read_bytes()
    assert blob[:8] == b"\x89PNG\r\n\x1a\n"
    width, height = struct.unpack(">II", blob[16:24])
    assert (width, height) == (1100, 1600)
    assert len(blob) > 50_000  # eight panels of lines, not an empty canvas
    assert (tmp_path / "plot" / "recording.html").stat().st_size > 10_000


def test_a_real_nmea_log(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    rc = cli_main(["plot", str(NMEA_LOG), "--out", str(tmp_path)])
    assert rc == 0
    err = capsys.readouterr().err
    # what an NMEA log cannot show is said, once per panel
    assert "the states panel is empty: an NMEA log holds only the receiver's output" in err
    assert "the error panel is empty: no true track" in err
    page = (tmp_path / "ublox-lea-5h.html").read_text()
    data = page_data(page)
    assert data["kind"] == "NMEA log"
    counts = decode_path(str(NMEA_LOG), open("/dev/null", "w"))  # noqa: SIM115
    assert data["counts"]["fixes"] == counts.fixes
    assert data["track"]["GPS fixes"]["east_m"]
    for pid in ("states", "holds", "faults", "error"):
        assert f'<svg id="svg-{pid}"' not in page
        assert re.search(rf'<section id="panel-{pid}"><h2>[^<]*</h2><p class="missing">', page)
    assert (tmp_path / "ublox-lea-5h.png").read_bytes()[:4] == b"\x89PNG"
    assert "skipped" not in err
    # damaged sentences: counted on the page and said on stderr, not silently missing data
    lines = NMEA_LOG.read_bytes().splitlines(keepends=True)
    bad = [ln[:10] + b"\xff\x00junk" + ln[10:] if i % 4 == 1 else ln for i, ln in enumerate(lines)]
    (tmp_path / "bad.nmea").write_bytes(b"".join(bad))
    assert cli_main(["plot", str(tmp_path / "bad.nmea"), "--out", str(tmp_path)]) == 0
    counts = page_data((tmp_path / "bad.html").read_text())["counts"]
    assert counts["checksum_failures"] > 0
    assert f"skipped {counts['checksum_failures']} checksum failures" in capsys.readouterr().err


def _recorded(path: Path, hold_reason: str) -> None:
    """A short recording written by the real recorder: a mission that starts, holds for a
    lost GPS and resumes."""
    with Recorder(path) as rec:
        rec.record_state(StateChange(1.0, "IDLE", "RUNNING", "mode: start"))
        rec.record_state(StateChange(1.0, "IDLE", "STRAIGHT", "state: start"))
        for t in (1.0, 2.0, 3.0, 4.0, 5.0, 6.0):
            hold = hold_reason if 3.0 <= t < 5.0 else ""
            if t == 3.0:
                rec.record_state(StateChange(t, "STRAIGHT", "HOLD", f"state: {hold_reason}"))
            if t == 5.0:
                rec.record_state(StateChange(t, "HOLD", "STRAIGHT", "state: gps ok"))
            tel = Telemetry(
                t, Mode.RUNNING, NavState.HOLD if hold else NavState.STRAIGHT, hold,
                filt_lat_deg=51.0 + t * 1e-5, filt_lon_deg=-1.0, heading_deg=-90.0,
            )  # fmt: skip
            rec.record_telemetry(tel)


def test_a_recording_without_a_true_track_says_which_runs_have_one(
    sim_run: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """An outside audit: a HIL recording (a simulated receiver, but no truth.csv) was told
    "only a simulated run has one". The simulator's recording alone in its folder is what
    a HIL or a real run's folder holds."""
    rec = tmp_path / "hil" / "recording.jsonl"
    rec.parent.mkdir()
    shutil.copy(sim_run / "recording.jsonl", rec)
    assert cli_main(["plot", str(rec), "--out", str(tmp_path / "plot")]) == 0
    assert (
        "the error panel is empty: no true track: only `x6wd sim` writes one (truth.csv next "
        "to its recording and its gps.nmea); a HIL or real run has none (--truth FILE for a "
        "true track of your own)"
    ) in capsys.readouterr().err


def test_the_sims_gps_nmea_is_plotted_against_the_truth_beside_it(
    sim_run: Path, tmp_path: Path
) -> None:
    """An outside audit (round 23): `x6wd plot gps.nmea` of a simulated run left the error
    panel empty, "only x6wd sim writes one", with its truth.csv beside it (x6wd gap reads it).
    Another NMEA log's name takes no truth.csv it happens to sit beside."""
    view = logview.load(sim_run / "gps.nmea")
    assert "error" not in view.missing
    (fix,) = [s for s in view.error if s.label == "GPS fix"]
    assert fix.v.size > 30 and 0.0 < float(np.median(fix.v)) < 20.0
    other = tmp_path / "log.nmea"
    shutil.copy(sim_run / "gps.nmea", other)
    shutil.copy(sim_run / "truth.csv", tmp_path / "truth.csv")
    assert "no true track" in logview.load(other).missing["error"]


def test_holds_and_device_faults(tmp_path: Path) -> None:
    path = tmp_path / "r.jsonl"
    _recorded(path, "gps disconnected")
    data = page_data(logview.render_html(path))
    assert [(h["t0_s"], h["t1_s"], h["label"]) for h in data["holds"]] == [
        (2.0, 4.0, "gps disconnected")
    ]
    assert [(f["lane"], f["t0_s"], f["t1_s"]) for f in data["faults"]] == [("gps", 2.0, 4.0)]
    heading = next(s for s in data["heading"] if s["label"].startswith("heading"))
    assert heading["v"] == [270.0] * 6  # true degrees 0-360, as every heading shown


def test_a_recording_from_before_headings_were_recorded_0_to_360_still_shows_them(
    tmp_path: Path,
) -> None:
    """Recordings before the recorder wrapped them hold the controller's (-180, 180]."""
    path = tmp_path / "r.jsonl"
    _recorded(path, "gps disconnected")
    text = path.read_text()
    assert text.count('"heading_deg":270.0') == 6  # the recorder writes 0-360 now
    path.write_text(text.replace('"heading_deg":270.0', '"heading_deg":-90.0'))
    series = page_data(logview.render_html(path))["heading"]
    heading = next(s for s in series if s["label"].startswith("heading"))
    assert heading["v"] == [270.0] * 6


@pytest.mark.parametrize(
    ("reason", "lane"),
    [("no valid fix", "gps"), ("fix stale", "gps"), ("attitude invalid", "compass"),
     ("attitude stale", "compass"), ("motor link lost", "motors")],
)  # fmt: skip
def test_a_hold_on_data_the_controller_refused_is_a_device_fault(
    tmp_path: Path, reason: str, lane: str
) -> None:
    """No reader reported anything (a simulated outage, a compass reading 0xFF): the hold's
    own words name the device."""
    path = tmp_path / "r.jsonl"
    _recorded(path, reason)
    data = page_data(logview.render_html(path))
    assert [(f["lane"], f["t0_s"], f["t1_s"]) for f in data["faults"]] == [(lane, 2.0, 4.0)]


def test_a_hold_of_a_late_control_loop_is_no_device_fault(tmp_path: Path) -> None:
    # the runner marks a stale-sensor hold that began while the loop itself stood still (a
    # CPU-starved core, outside audit 10e): the compass was on time, so no compass fault
    path = tmp_path / "r.jsonl"
    _recorded(path, "attitude stale (the control loop itself was 0.60 s late: CPU starved?)")
    data = page_data(logview.render_html(path))
    assert data["faults"] == []


def test_device_faults_recorded_by_the_loop(tmp_path: Path) -> None:
    # The loop records every health event it is handed (x6wd.loop.runner -> Recorder); the
    # page draws a device's time away from "connected", whatever the robot was doing.
    path = tmp_path / "r.jsonl"
    safety = SafetyConfig()
    nav = NavigationConfig.paper(filter_n=3, projection="local_tangent_plane")
    gps = HealthTracker("gps", t_s=0.0)
    compass = HealthTracker("compass", t_s=0.0)
    with Recorder(path) as rec:
        runner = Runner(
            Controller(nav, safety), safety, lambda: 0.0, motors=lambda _c: None,
            record=lambda method, arg: getattr(rec, method)(arg),
        )  # fmt: skip
        rec.record_telemetry(Telemetry(0.0, Mode.IDLE, NavState.IDLE, filt_lat_deg=51.0,
                                       filt_lon_deg=-1.0))  # fmt: skip
        gps.opened(0.5)
        compass.opened(0.5)
        gps.lost("unplugged", 2.0)
        gps.open_failed("no such device", 3.0)
        gps.open_failed("no such device", 4.0)
        gps.opened(6.0)
        compass.failed("I2C NACK", 7.0)
        runner.device_events([*gps.take_events(), *compass.take_events()])
        rec.record_telemetry(Telemetry(9.0, Mode.IDLE, NavState.IDLE))
    page = logview.render_html(path)
    faults = [(f["lane"], f["t0_s"], f["t1_s"], f["label"]) for f in page_data(page)["faults"]]
    assert faults == [
        ("gps", 2.0, 3.0, "disconnected"),
        ("gps", 3.0, 6.0, "reconnecting"),
        ("compass", 7.0, 9.0, "degraded"),
    ]
    assert "gps disconnected: unplugged" in page  # the first message, on hover
    assert '<svg id="svg-faults"' in page


def test_text_from_a_recording_is_escaped(tmp_path: Path) -> None:
    # A recording is data: a reason with markup must not become markup on the console's page.
    # (Checked to fail with logview._esc returning its input unchanged.)
    path = tmp_path / "r.jsonl"
    _recorded(path, "<script>alert(1)</script>")
    page = logview.render_html(path)
    assert "<script>alert" not in page
    assert "&lt;script&gt;alert(1)&lt;/script&gt;" in page
    assert page.count("<script") == 1  # the data block only
    assert page_data(page)["holds"][0]["label"] == "<script>alert(1)</script>"


def test_bad_input_says_what_is_wrong(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert cli_main(["plot", str(tmp_path / "none.jsonl"), "--out", str(tmp_path)]) == 2
    assert "none.jsonl" in capsys.readouterr().err
    empty = tmp_path / "empty.jsonl"
    with Recorder(empty) as rec:
        rec.record_event("start", 0.0)
    assert cli_main(["plot", str(empty), "--out", str(tmp_path)]) == 2
    assert "nothing to plot" in capsys.readouterr().err
    rec_path = tmp_path / "r.jsonl"
    _recorded(rec_path, "gps stale")
    bad_truth = tmp_path / "truth.csv"
    bad_truth.write_text("time,x\n1,2\n")
    assert cli_main(["plot", str(rec_path), "--out", str(tmp_path)]) == 2
    assert "truth.csv line 1: a true track needs columns t_s, lat, lon, got time, x" in (
        capsys.readouterr().err
    )


def _rewrite_in_parts(records: list[Any], path: Path) -> list[Path]:
    """``records`` written at ``path`` by the recorder in 200 kB parts; the parts."""
    with Recorder(path, max_bytes=200_000) as rec:
        for r in records:
            rec.record(r.type, r.data, r.t_mono)
    return list(rec.paths)


def test_parts_bad_lines_and_a_cut_last_line(sim_run: Path, tmp_path: Path) -> None:
    # A daemon recording in parts (the recorder's rotation), a garbled line and a crash
    # mid-line: every part is read, the damage counted as the recorder's reader counts it.
    records = list(read_recording(sim_run / "recording.jsonl"))
    path = tmp_path / "run.jsonl"
    _rewrite_in_parts(records, path)
    parts = sorted(tmp_path.glob("run*.jsonl"))
    assert len(parts) > 3
    with open(parts[1], "ab") as f:
        f.write(b'{"t_mono": 1.0, "type": "fix", "da\n')
    with open(parts[-1], "ab") as f:
        f.write(b'{"t_mono":99.0,"t_utc":"","type":"fix","data":{"t_s":99.0,"lat')
    data = page_data(logview.render_html(path))
    assert data["counts"]["records"] == len(records)
    assert (data["counts"]["bad_lines"], data["counts"]["truncated_lines"]) == (1, 1)
    assert data["counts"]["fixes"] == sum(r.type == "fix" for r in records)
    assert data["duration_s"] == pytest.approx(records[-1].t_mono - records[0].t_mono, abs=1e-3)


def test_records_that_do_not_fit_their_type_are_counted(
    sim_run: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # A fix with a field this version lacks is drawn without it; a fix whose latitude is a
    # string and a sky whose satellite lacks fields are skipped and counted: never a
    # traceback, never a record gone without a word.
    lines = (sim_run / "recording.jsonl").read_text().splitlines(keepends=True)
    fixes = [i for i, ln in enumerate(lines) if '"type":"fix"' in ln]
    skies = [i for i, ln in enumerate(lines) if '"type":"sky"' in ln]
    obj = json.loads(lines[fixes[1]])
    obj["data"]["new_field_m"] = 1.5
    lines[fixes[1]] = json.dumps(obj) + "\n"
    obj = json.loads(lines[fixes[2]])
    obj["data"]["lat_deg"] = str(obj["data"]["lat_deg"])
    lines[fixes[2]] = json.dumps(obj) + "\n"
    obj = json.loads(lines[skies[0]])
    obj["data"]["satellites"][0] = {"prn": 3, "elevation": 10}
    lines[skies[0]] = json.dumps(obj) + "\n"
    path = tmp_path / "recording.jsonl"
    path.write_text("".join(lines))
    assert cli_main(["plot", str(path), "--out", str(tmp_path), "--format", "html"]) == 0
    err = capsys.readouterr().err
    assert "skipped 2 bad records" in err and "1 records with fields" in err, err
    counts = page_data((tmp_path / "recording.html").read_text())["counts"]
    assert (counts["fixes"], counts["sky_reports"]) == (len(fixes) - 1, len(skies) - 1)
    assert counts["records_with_unknown_fields"] == 1


def test_a_folder_means_its_newest_recording(tmp_path: Path) -> None:
    runs = tmp_path / "recordings"
    runs.mkdir()
    for stamp in ("20260102T000000Z", "20260101T235959Z"):
        _recorded(runs / f"x6wd-{stamp}.jsonl", "gps stale")
    (runs / "notes.jsonl").write_text("{}\n")  # not the recorder's name: not a run
    out = tmp_path / "plots"
    assert cli_main(["plot", str(runs), "--out", str(out), "--format", "html"]) == 0
    assert [p.name for p in out.iterdir()] == ["x6wd-20260102T000000Z.html"]
    assert cli_main(["plot", str(out), "--out", str(out)]) == 2  # no recordings there


def test_a_folder_whose_newest_run_lost_its_first_part(sim_run: Path, tmp_path: Path) -> None:
    # Retention deletes a run's first part first: the folder's newest run is then found as
    # its part .1, and every remaining part (.1, .2, ...) is still drawn, not .1 alone.
    records = list(read_recording(sim_run / "recording.jsonl"))
    path = tmp_path / "x6wd-20260102T000000Z.jsonl"
    assert len(_rewrite_in_parts(records, path)) > 3
    first = [r for r in read_recording(path) if r.type == "fix"]
    path.unlink()
    src = logview.newest_recording(tmp_path)
    assert src.name == "x6wd-20260102T000000Z.1.jsonl"
    view = logview.load(src)
    assert view.counts["fixes"] == sum(r.type == "fix" for r in records) - len(first)


@pytest.mark.integration
def test_without_the_plot_extra(tmp_path: Path) -> None:
    script = (
        "import sys\n"
        "sys.modules['matplotlib'] = None\n"
        "from x6wd.app.cli import main\n"
        "sys.exit(main(sys.argv[1:]))\n"
    )

    def run(*args: str) -> subprocess.CompletedProcess[str]:
        return subprocess.run(
            [sys.executable, "-c", script, "plot", str(NMEA_LOG), "--out", str(tmp_path), *args],
            capture_output=True,
            text=True,
            timeout=60,
        )

    proc = run()
    assert proc.returncode == 2, proc.stderr
    assert "pip install 'x6wd[plot]'" in proc.stderr and "Traceback" not in proc.stderr
    assert not list(tmp_path.iterdir())  # nothing half-written
    proc = run("--format", "html")  # the page needs no extra (the robot's console)
    assert proc.returncode == 0, proc.stderr
    assert (tmp_path / "ublox-lea-5h.html").is_file()


def _nan_positions(path: Path) -> None:
    """Four fixes and four estimates, one of each with a NaN or infinite position (as only a
    foreign or hand-edited file has: the recorder writes allow_nan=False)."""
    lines = []
    for i, t in enumerate((0.0, 1.0, 2.0, 3.0)):
        lat = math.nan if i == 1 else 51.75 + t * 1e-5
        lon = math.inf if i == 2 else -1.25
        fix = {"t_s": t, "utc": None, "lat_deg": lat, "lon_deg": -1.25, "alt_m": 50.0,
               "quality": 1, "sats_used": 7, "hdop": 1.0, "valid": True}  # fmt: skip
        tel = {"t_s": t, "mode": "IDLE", "state": "IDLE", "hold_reason": "",
               "filt_lat_deg": 51.75 + t * 1e-5, "filt_lon_deg": lon}  # fmt: skip
        for kind, data in (("fix", fix), ("telemetry", tel)):
            lines.append(json.dumps({"t_mono": t, "t_utc": "", "type": kind, "data": data}))
    path.write_text("\n".join(lines) + "\n")


def test_a_nan_position_is_skipped_and_counted_not_a_refused_file(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # Found by an outside check: one fix with "lat_deg": NaN made x6wd plot refuse the whole
    # file ("lat_deg must be finite", exit 2) and crashed the console's Recordings view.
    path = tmp_path / "r.jsonl"
    _nan_positions(path)
    assert "NaN" in path.read_text() and "Infinity" in path.read_text()
    assert cli_main(["plot", str(path), "--out", str(tmp_path), "--format", "html"]) == 0
    assert "skipped 2 nonfinite positions" in capsys.readouterr().err
    data = page_data((tmp_path / "r.html").read_text())
    assert data["counts"]["nonfinite_positions"] == 2
    fixes, est = data["track"]["GPS fixes"], data["track"]["position estimate"]
    assert len(fixes["north_m"]) == len(est["north_m"]) == 3
    assert fixes["north_m"] == pytest.approx([0.0, 2.2, 3.3], abs=0.05)
    assert None not in fixes["east_m"] + est["east_m"]


BT451 = ROOT / "tests" / "data" / "nmea" / "bt451.log"  # 15:25, then 14:33 the same day


def _nmea(body: str) -> str:
    cs = 0
    for ch in body.encode():
        cs ^= ch
    return f"${body}*{cs:02X}\r\n"


def _session(start: datetime, seconds: int, lat: str = "5147.000") -> str:
    """A receiver's RMC and GGA once a second from ``start`` (UTC)."""
    out = []
    for k in range(seconds):
        t = start + timedelta(seconds=k)
        hms, dmy = t.strftime("%H%M%S.00"), t.strftime("%d%m%y")
        out.append(_nmea(f"GPRMC,{hms},A,{lat},N,00115.000,W,0.1,,{dmy},,,A"))
        out.append(_nmea(f"GPGGA,{hms},{lat},N,00115.000,W,1,08,1.1,50.0,M,0.0,M,,"))
    return "".join(out)


def _time_panels_on_screen(page: str) -> int:
    """Asserts every point of every time panel's lines lies inside its plot area; the number
    of polylines drawn."""
    n = 0
    for pid in ("error", "hdop", "satellites", "heading"):
        svg = re.search(rf'<svg id="svg-{pid}"([^>]*)>(.*?)</svg>', page, re.S)
        if svg is None:
            continue
        a = {k: float(v) for k, v in re.findall(r'data-(plot-\w+)="([^"]*)"', svg.group(1))}
        for line in re.findall(r'points="([^"]*)"', svg.group(2)):
            n += 1
            xs = [float(p.split(",")[0]) for p in line.split()]
            assert a["plot-left"] <= min(xs) and max(xs) <= a["plot-right"], (pid, xs)
    return n


def test_a_log_whose_time_goes_back_is_drawn_in_file_order(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    # Found by an outside check: bt451.log holds two sessions, 15:25 then 14:33, and x6wd
    # plot drew nothing usable: a duration of 0.0, the PNG's time axes 0..0.001 s, the page's
    # lines at x = 414056 and -2582117944. Now: the segments in file order, one epoch apart,
    # the jump marked and said.
    import matplotlib.figure

    figures: list[Any] = []
    savefig = matplotlib.figure.Figure.savefig

    def keep(fig: Any, *args: Any, **kwargs: Any) -> None:
        figures.append(fig)
        savefig(fig, *args, **kwargs)

    monkeypatch.setattr(matplotlib.figure.Figure, "savefig", keep)
    assert cli_main(["plot", str(BT451), "--out", str(tmp_path)]) == 0
    err = capsys.readouterr().err
    assert "bt451.log: the log's time jumps: line 112: time went back 3122.5 s (52 min)" in err
    page = (tmp_path / "bt451.html").read_text()
    data = page_data(page)
    # 4 s stationary at 15:25:04.5-08.5, half a second, 2.5 s driving from 14:33:06
    assert data["duration_s"] == pytest.approx(7.0)
    assert data["time_jumps"] == [
        {"t_s": 4.25, "line": 112, "step_s": -3122.5,
         "before_utc": "2009-12-09 15:25:08.5", "after_utc": "2009-12-09 14:33:06", "file": ""}
    ]  # fmt: skip
    assert "<td>time jumps (1)</td><td>line 112: time went back 3122.5 s (52 min)" in page
    for pid in ("hdop", "satellites", "heading"):
        for s in data[pid]:
            t = np.array([x for x in s["t_s"] if x is not None])
            assert t.min() >= 0.0 and t.max() <= 7.0 and np.all(np.diff(t) >= 0), (pid, t)
        assert page.count('class="time-jump"', page.index(f'<svg id="svg-{pid}"')) >= 1
    # every line inside its panel, and broken at the jump: HDOP and both satellite counts
    # in two pieces each (heading is dots)
    assert _time_panels_on_screen(page) >= 6
    hdop = re.search(r'data-label="HDOP \(fix\)">(.*?)</g>', page)
    assert hdop is not None and hdop.group(1).count("<polyline") == 2
    # the PNG's time axes hold every point drawn on them
    (fig,) = figures
    for ax in fig.axes[1:]:
        lo, hi = ax.get_xlim()
        assert (lo, hi) == pytest.approx((0.0, 7.0)), ax.get_title()
        for line in ax.get_lines():
            x = np.asarray(line.get_xdata(), dtype=float)
            x = x[np.isfinite(x)]
            assert x.size == 0 or (lo <= x.min() and x.max() <= hi), ax.get_title()


def test_time_jumps_and_what_is_not_one(tmp_path: Path) -> None:
    day = datetime(2025, 12, 31, tzinfo=UTC)
    # across midnight (and into a new year): one segment, time running on
    path = tmp_path / "midnight.nmea"
    path.write_text(_session(day + timedelta(hours=23, minutes=59, seconds=55), 10))
    view = logview.load(path)
    assert view.jumps == [] and view.duration_s == pytest.approx(9.0)
    assert view.start_utc == "2025-12-31T23:59:55+00:00"
    assert np.array_equal(view.hdop[0].t_s, np.arange(10.0))
    assert _time_panels_on_screen(logview.html_page(view)) == 2  # HDOP, satellites: unbroken
    # two sessions four hours apart: forward by more than TIME_JUMP_S is a jump too
    path.write_text(_session(day + timedelta(hours=10), 5) + _session(day + timedelta(hours=14), 5))
    view = logview.load(path)
    assert [(j.line, j.step_s) for j in view.jumps] == [(11, 4 * 3600.0 - 4.0)]
    assert view.duration_s == pytest.approx(9.0)
    assert view.jumps[0].describe() == (
        "line 11: time went forward 14396.0 s (4 h 0 min), "
        "2025-12-31 10:00:04 -> 2025-12-31 14:00:00 UTC"
    )
    # the same, later session first
    path.write_text(_session(day + timedelta(hours=14), 5) + _session(day + timedelta(hours=10), 5))
    view = logview.load(path)
    assert [(j.line, j.step_s) for j in view.jumps] == [(11, -4 * 3600.0 - 4.0)]
    assert np.array_equal(view.hdop[0].t_s, [0, 1, 2, 3, 4, 5, 6, 7, 8, 9])
    # a gap under the limit (this log's 1059 s pause) is drawn as the time it was
    view = logview.load(NMEA_LOG)
    assert view.jumps == [] and view.duration_s == pytest.approx(1077.0)


def _series_in_order(data: dict[str, Any], duration_s: float) -> None:
    """Asserts every time series of the page's data lies within [0, duration] in order."""
    for pid in ("error", "hdop", "satellites", "heading"):
        for s in data[pid]:
            t = np.array([x for x in s["t_s"] if x is not None])
            assert t.min() >= 0.0 and t.max() <= duration_s + 1e-3, (pid, s["label"])
            assert np.all(np.diff(t) >= 0), (pid, s["label"])


def test_a_recording_whose_time_jumps_is_drawn_in_file_order(
    sim_run: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # Found by an outside audit: two daemon sessions appended to one file (t_mono restarts)
    # were drawn over each other, joined by diagonals, the duration one session's and no
    # word said; a forward jump of 100000 s left the data as slivers. Now a recording's time
    # is put in file order as an NMEA log's is, the jump marked and said.
    lines = (sim_run / "recording.jsonl").read_text().splitlines(keepends=True)
    records = list(read_recording(sim_run / "recording.jsonl"))
    one_s = records[-1].t_mono - records[0].t_mono
    assert logview.load(sim_run / "recording.jsonl").jumps == []
    path = tmp_path / "recording.jsonl"  # two sessions of the simulator, appended
    path.write_text("".join(lines + lines))
    (tmp_path / "truth.csv").write_bytes((sim_run / "truth.csv").read_bytes())
    assert cli_main(["plot", str(path), "--out", str(tmp_path), "--format", "html"]) == 0
    err = capsys.readouterr().err
    assert f"line {len(lines) + 1}: time went back {one_s:.1f} s" in err, err
    page = (tmp_path / "recording.html").read_text()
    data = page_data(page)
    (jump,) = data["time_jumps"]
    assert (jump["line"], jump["step_s"]) == (len(lines) + 1, pytest.approx(-one_s, abs=1e-3))
    assert jump["after_utc"] == "2020-01-01 12:00:00"  # the recorder's t_utc either side
    assert jump["before_utc"] == records[-1].t_utc.replace("T", " ").rstrip("Z0")
    assert data["duration_s"] == pytest.approx(2 * one_s, abs=0.2)  # two sessions, one epoch
    assert data["counts"]["fixes"] == 2 * sum(r.type == "fix" for r in records)
    _series_in_order(data, data["duration_s"])
    assert _time_panels_on_screen(page) >= 6
    for pid, label in (("hdop", "HDOP (fix)"), ("error", "position estimate"),
                       ("track", "position estimate")):  # fmt: skip
        # a line each side, none across (on the map: none from one session's end to the next)
        svg = page[page.index(f'<svg id="svg-{pid}"') :]
        g = re.search(rf'data-label="{re.escape(label)}">(.*?)</g>', svg)
        assert g is not None and g.group(1).count("<polyline") == 2, (pid, label)
    # the second session's error is against the run's own clock: the same as the first's
    est = next(s for s in data["error"] if s["label"] == "position estimate")
    v = [x for x in est["v"] if x is not None]
    assert v[: len(v) // 2] == pytest.approx(v[len(v) - len(v) // 2 :], abs=0.01)

    # forward by 100000 s half way (a daemon's clock after a suspend): the same, marked
    half = len(records) // 2
    path = tmp_path / "run.jsonl"
    with Recorder(path, max_bytes=200_000) as rec:  # in parts: the jump names its part
        for k, r in enumerate(records):
            t = r.t_mono + (100_000.0 if k >= half else 0.0)
            data_t = {**r.data, "t_s": t} if "t_s" in r.data else r.data
            rec.record(r.type, data_t, t)
    view = logview.load(path)
    (j,) = view.jumps
    assert j.step_s == pytest.approx(100_000.0, abs=1.0) and j.file.startswith("run.")
    assert f"line {j.line} of {j.file}: time went forward" in j.describe()
    assert view.duration_s == pytest.approx(one_s, abs=0.2)
    assert view.time_range() == pytest.approx((0.0, view.duration_s))
    _series_in_order(page_data(logview.html_page(view)), view.duration_s)


COLDBOOT = ROOT / "tests" / "data" / "nmea" / "gp-320fw-2019-04-07-coldboot.log"


def test_a_jumps_utc_is_the_receivers_at_the_step_s_two_ends() -> None:
    # Found by an outside audit on this real cold start: "line 45: time went back 15873.0 s,
    # 2010-09-30 23:59:50 -> ..." though the receiver said 23:59:50 on 2006-12-16 (RMC, line
    # 42): the decoder still held that epoch when line 45's RMC brought 2010-09-30, and gave
    # it that date. And line 48's step was measured to 23:59:52 (its damaged GGA, no fix)
    # while its "after" was 23:59:57, a fix five lines on. Now the epoch is closed at the
    # jump, and a side whose time made no dated fix is said to be unknown. Since round 21 a
    # sentence failing its checksum (line 48's damaged GGA) sets no time: the step is at
    # line 53's RMC, whose date is known.
    view = logview.load(COLDBOOT)
    said = {j.line: j.describe() for j in view.jumps}
    assert said[45] == (
        "line 45: time went back 15873.0 s (4 h 25 min), "
        "2006-12-16 23:59:50 -> 2010-09-30 19:35:15 UTC"
    )
    assert said[53] == (
        "line 53: time went forward 15882.0 s (4 h 25 min), "
        "2010-09-30 19:35:15 -> 2010-09-25 23:59:57 UTC"
    )
    assert said[38].endswith("unknown -> 2006-12-16 23:59:48 UTC")  # before any dated fix


def test_a_true_track_cut_mid_line_is_read_and_a_bad_row_named(
    sim_run: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # Found by an outside audit: a truth.csv cut mid-line (a run that lost power) was
    # refused whole, and the message named no line ("could not convert string to float:
    # ''"). Now the torn last line is skipped and counted, as a recording's is; a bad row
    # elsewhere is refused naming its line.
    text = (sim_run / "truth.csv").read_text()
    rows = text.count("\n") - 1
    rec = tmp_path / "recording.jsonl"
    rec.write_bytes((sim_run / "recording.jsonl").read_bytes())
    truth = tmp_path / "truth.csv"
    head, last = text[: text.rindex("\n", 0, -1) + 1], text[text.rindex("\n", 0, -1) + 1 :]
    lon_at = last.index(",-1.") + 1
    for cut in (last[:lon_at], last[: lon_at + 3]):  # lon empty, lon cut to "-1."
        truth.write_text(head + cut)
        assert cli_main(["plot", str(rec), "--out", str(tmp_path), "--format", "html"]) == 0
        assert "skipped 1 truncated truth lines" in capsys.readouterr().err
        data = page_data((tmp_path / "recording.html").read_text())
        assert data["counts"]["truncated_truth_lines"] == 1
        assert len(data["track"]["true track"]["east_m"]) == min(rows - 1, logview.MAX_POINTS)
        assert data["error"]  # drawn
    lines = text.splitlines(keepends=True)
    lines[7] = lines[7].replace(",", ",x", 1)
    truth.write_text("".join(lines))
    assert cli_main(["plot", str(rec), "--out", str(tmp_path), "--format", "html"]) == 2
    assert "truth.csv line 8: a true track needs numbers in t_s, lat, lon" in (
        capsys.readouterr().err
    )
