"""Fast-time missions: world -> real GNSS model -> NEO-5 bytes -> real decoder -> controller."""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import numpy as np
import pytest

from drivers.gps_nmea import GpsDecoder
from sim_backend.geodesy import lla_to_enu
from sim_backend.mission import ErrorStats, Summary, run_mission
from sim_backend.world import load_world
from x6wd import cli
from x6wd.errors import ConfigError
from x6wd.recorder import read_recording
from x6wd.records import GpsFix

ROOT = Path(__file__).resolve().parent.parent
SCENARIOS = ROOT / "config" / "scenarios"


@pytest.fixture(scope="module")
def default_run(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Summary]:
    out = tmp_path_factory.mktemp("default")
    world = load_world(SCENARIOS / "default.toml")
    return out, run_mission(world, out)


def test_default_mission_reaches_every_waypoint_in_fast_time(
    default_run: tuple[Path, Summary],
) -> None:
    _out, s = default_run
    assert s.completed and s.waypoint_count == 4 and s.waypoints_reached == 4
    assert s.sim_time_s < load_world(SCENARIOS / "default.toml").duration_s
    # The robot drove roughly the polygon: not much shorter, not wildly longer.
    assert 0.9 * s.straight_length_m < s.path_length_m < 1.6 * s.straight_length_m
    assert s.fixes_valid == s.fixes > 0
    assert 0 < s.raw_error.cep50_m < 5 and s.raw_error.r95_m >= s.raw_error.cep50_m


def test_every_emitted_sentence_decodes_in_the_real_driver(
    default_run: tuple[Path, Summary],
) -> None:
    out, s = default_run
    data = (out / "gps.nmea").read_bytes()
    assert data.startswith(b"$GPTXT,01,01,02,u-blox ag - www.u-blox.com*50\r\n")
    dec = GpsDecoder(emit_sentences=False)
    recs = dec.feed(data, 0.0) + dec.flush()
    c = dec.counters
    assert c.sentences == data.count(b"\r\n")
    assert c.decoded == c.sentences and c.checksum_failures == 0 and c.invalid_fields == 0
    assert sum(isinstance(r, GpsFix) for r in recs) == s.fixes


def test_output_files_are_consistent(default_run: tuple[Path, Summary]) -> None:
    out, s = default_run
    records = list(read_recording(out / "recording.jsonl", strict=True))
    kinds = {r.type for r in records}
    assert {"nmea", "fix", "sky", "attitude", "telemetry", "state", "motor", "event"} <= kinds
    times = [r.t_mono for r in records if r.type != "event"]
    assert times == sorted(times)  # the controller saw its inputs in time order
    nmea_lines = [r.data["text"] for r in records if r.type == "nmea"]
    file_lines = (out / "gps.nmea").read_bytes().decode().split("\r\n")[:-1]
    assert nmea_lines == [ln for ln in file_lines if not ln.startswith("$GPTXT")]
    with open(out / "truth.csv") as f:
        rows = list(csv.DictReader(f))
    assert list(rows[0]) == ["t_s", "lat", "lon", "alt", "heading_deg"]
    assert float(rows[-1]["t_s"]) == pytest.approx(s.sim_time_s)
    saved = json.loads((out / "summary.json").read_text())
    assert saved["waypoints_reached"] == s.waypoints_reached == 4
    assert saved["raw_error"]["cep50_m"] == pytest.approx(s.raw_error.cep50_m)
    assert (out / "track.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_error_statistics_agree_with_the_files(default_run: tuple[Path, Summary]) -> None:
    # Recompute the raw error from gps.nmea and truth.csv independently of the mission code.
    out, s = default_run
    world = load_world(SCENARIOS / "default.toml")
    dec = GpsDecoder(emit_sentences=False)
    fixes = [r for r in dec.feed((out / "gps.nmea").read_bytes(), 0.0) if isinstance(r, GpsFix)]
    with open(out / "truth.csv") as f:
        truth = {round(float(r["t_s"]), 3): r for r in csv.DictReader(f)}
    o = world.origin
    err = []
    for fx in fixes:
        assert fx.utc is not None and fx.lat_deg is not None and fx.lon_deg is not None
        t = round((fx.utc - world.start_utc).total_seconds(), 3)
        tr = truth[t]
        e = lla_to_enu(
            np.array([fx.lat_deg, float(tr["lat"])]),
            np.array([fx.lon_deg, float(tr["lon"])]),
            np.array([o.alt_m, o.alt_m]),
            o.lat_deg,
            o.lon_deg,
            o.alt_m,
        )
        err.append(math.hypot(e[0][0] - e[1][0], e[0][1] - e[1][1]))
    assert s.raw_error.n == len(err)
    assert s.raw_error.cep50_m == pytest.approx(float(np.median(err)), abs=0.01)
    assert s.raw_error.rms_m == pytest.approx(float(np.sqrt(np.mean(np.square(err)))), abs=0.01)


def test_same_seed_same_bytes_other_seed_other_bytes(tmp_path: Path) -> None:
    world = load_world(SCENARIOS / "default.toml")
    runs = {}
    for name, seed in (("a", 5), ("b", 5), ("c", 6)):
        run_mission(world, tmp_path / name, seed=seed, duration_s=20.0)
        runs[name] = (tmp_path / name / "gps.nmea").read_bytes()
    assert runs["a"] == runs["b"] != runs["c"]
    rec_a = (tmp_path / "a" / "recording.jsonl").read_bytes()
    assert rec_a == (tmp_path / "b" / "recording.jsonl").read_bytes()


def test_static_survey_reports_the_papers_dispersion(tmp_path: Path) -> None:
    world = load_world(SCENARIOS / "open_field.toml")
    s = run_mission(world, tmp_path, duration_s=60.0)
    assert s.waypoint_count == 0 and s.path_length_m == 0.0
    assert s.fixes_valid > 50
    # Open ground: the paper's rows 2/4 are +-1..10 m; a healthy open-sky receiver is metres.
    assert 0.05 < s.dispersion_lat_m < 10 and 0.05 < s.dispersion_lon_m < 10
    assert s.mean_hdop < 2.5 and s.mean_sats_used >= 5


def test_error_stats_definitions() -> None:
    e = np.array([3.0, 1.0, 4.0, 1.0, 5.0, 9.0, 2.0, 6.0])
    st = ErrorStats.of(np.append(e, math.nan))
    assert st.n == 8 and st.mean_m == pytest.approx(e.mean())
    assert st.rms_m == pytest.approx(math.sqrt(float(np.mean(e**2))))
    assert st.cep50_m == pytest.approx(float(np.median(e))) and st.max_m == 9.0
    assert math.isnan(ErrorStats.of(np.array([])).mean_m)


def test_cli_runs_a_scenario_and_reports(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    rc = cli.main(
        ["sim", str(SCENARIOS / "default.toml"), "--out", str(tmp_path), "--duration", "15",
         "--seed", "3", "--quiet"]
    )  # fmt: skip
    out = capsys.readouterr().out
    assert rc == 1  # 15 s is too short to finish the mission: not completed
    assert "waypoints reached" in out and "CEP50" in out and "HOLD periods" in out
    assert json.loads((tmp_path / "summary.json").read_text())["seed"] == 3


def test_bad_inputs_are_named(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bad = tmp_path / "bad.toml"
    text = (SCENARIOS / "default.toml").read_text().replace("noise_ut = 0.05", "noise_uT = 1")
    bad.write_text(text)
    with pytest.raises(ConfigError, match=r"compass\.noise_uT"):
        run_mission(load_world(bad), tmp_path / "o")
    odd = tmp_path / "odd.toml"
    odd.write_text(
        (SCENARIOS / "default.toml").read_text().replace("rate_hz = 1.0", "rate_hz = 3.0")
    )
    with pytest.raises(ConfigError, match="whole multiple"):
        run_mission(load_world(odd), tmp_path / "o")
    with pytest.raises(ConfigError, match="duration"):
        run_mission(load_world(SCENARIOS / "default.toml"), tmp_path / "o", duration_s=-1)
    assert cli.main(["sim", str(tmp_path / "missing.toml"), "--out", str(tmp_path)]) == 2
    assert "missing.toml" in capsys.readouterr().err


@pytest.mark.slow
def test_paper_situations_order_of_magnitude(tmp_path: Path) -> None:
    figures = {}
    for name in ("open_field", "broken_roof"):
        world = load_world(SCENARIOS / f"{name}.toml")
        figures[name] = run_mission(world, tmp_path / name, duration_s=300.0)
    open_s, roof = figures["open_field"], figures["broken_roof"]
    # Under the broken roof fewer satellites are seen direct and reflections add metres.
    assert roof.mean_sats_used < open_s.mean_sats_used
    assert roof.raw_error.r95_m > 2 * open_s.raw_error.r95_m
    assert 2 < max(roof.dispersion_lat_m, roof.dispersion_lon_m) < 40


def test_effect_layers_from_a_fragment_act_on_the_receiver(tmp_path: Path) -> None:
    base = (SCENARIOS / "open_field.toml").read_text()
    frag = tmp_path / "effects.toml"
    frag.write_text(
        '[[effects]]\nname = "bias"\neast_m = 30.0\n\n'
        '[[effects]]\nname = "latency"\ndelay_s = 0.5\n'
    )
    scen = tmp_path / "scen.toml"
    scen.write_text(f"include = [{str(frag)!r}]\n" + base)
    plain = run_mission(load_world(SCENARIOS / "open_field.toml"), tmp_path / "a", 2, 40.0)
    biased = run_mission(load_world(scen), tmp_path / "b", 2, 40.0)
    # A 30 m east bias moves every fix by 30 m (the model's own error is a few metres).
    assert biased.raw_error.mean_m > plain.raw_error.mean_m + 25
    assert biased.extra["effects_applied"] == ["bias"]
    assert biased.extra["effects_skipped"] == ["latency"]


def test_outage_layer_removes_fixes_and_the_robot_holds(tmp_path: Path) -> None:
    base = (SCENARIOS / "default.toml").read_text()
    scen = tmp_path / "scen.toml"
    scen.write_text(base + '\n[[effects]]\nname = "outages"\nmean_up_s = 15.0\nmean_down_s = 8.0\n')
    s = run_mission(load_world(scen), tmp_path / "o", duration_s=60.0)
    assert s.fixes_valid < s.fixes
    assert s.hold_periods >= 1 and s.hold_time_s > 0
    dec = GpsDecoder(emit_sentences=False)
    recs = dec.feed((tmp_path / "o" / "gps.nmea").read_bytes(), 0.0)
    assert any(isinstance(r, GpsFix) and not r.valid for r in recs)
    assert dec.counters.invalid_fields == 0
