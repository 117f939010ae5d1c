"""``x6wd gap --scenario``: the scenario's runs simulate the real log's sky, its date and
time and its height, not the scenario's own ``start_utc`` and altitude, and the report says
what the runs simulate (an outside audit: gpsd's 2016 Skytraq log was compared against a sky
of 2020-01-01 12:00, and the verdict changed with the date)."""

from __future__ import annotations

import math
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from sim_backend.effects import PositionSeries
from sim_backend.world import load_world
from x6wd.app.cli import main as x6wd_main
from x6wd.gap.scenario import place_at_log

ROOT = Path(__file__).resolve().parent.parent
SCENARIO = ROOT / "config" / "scenarios" / "open_field.toml"  # 2020-01-01 12:00, 60 m
SKYTRAQ = ROOT / "tests" / "data" / "nmea" / "skytraq-dgps.log"  # 2016-04-07, Bend OR


def worlds_built(monkeypatch: pytest.MonkeyPatch) -> list[Any]:
    """The list each scenario run's world is appended to as its receiver is built."""
    import sim_backend.receiver as receiver

    seen: list[Any] = []
    build = receiver.build_receiver

    def recording_build(world: Any, seed: int, **kwargs: Any) -> Any:
        seen.append(world)
        return build(world, seed, **kwargs)

    monkeypatch.setattr(receiver, "build_receiver", recording_build)
    return seen


def test_the_runs_simulate_the_real_logs_date_and_height(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    seen = worlds_built(monkeypatch)
    out = tmp_path / "report"
    argv = ["gap", "--real", str(SKYTRAQ), "--scenario", str(SCENARIO), "--seeds", "1"]
    assert (
        x6wd_main([*argv, "--replicates", "3", "--no-figures", "--quiet", "--out", str(out)]) == 0
    )
    assert seen, "no scenario run"
    for world in seen:
        assert world.start_utc == datetime(2016, 4, 7, 21, 31, 21, tzinfo=UTC)
        assert world.origin.alt_m == pytest.approx(1103.3, abs=0.1)  # the log's mean
        assert world.origin.lat_deg == pytest.approx(44.0688, abs=1e-3)
    md = (out / "report.md").read_text()
    assert "the scenario's runs simulate 2016-04-07 21:31:21Z, the real log's first epoch" in md
    assert "the scenario's start_utc 2020-01-01 12:00Z is not used" in md
    assert "altitude 1103 m (the real log's mean altitude)" in md
    # the packaged almanac (2020-01-03) is years from that date: said, as x6wd sim says it
    assert "simulated sky: start_utc 2016-04-07 21:31Z is 1365 days from" in md


def test_without_a_scenario_the_packaged_open_field_is_the_baseline(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A first report needs no scenario file: the open-field scenario, at the log's place
    and date, said in the report (it was an argparse error)."""
    seen = worlds_built(monkeypatch)
    out = tmp_path / "report"
    argv = ["gap", "--real", str(SKYTRAQ), "--seeds", "1", "--replicates", "3"]
    assert x6wd_main([*argv, "--no-figures", "--quiet", "--out", str(out)]) == 0
    assert seen and {w.name for w in seen} == {load_world(SCENARIO).name}
    assert all(w.start_utc == datetime(2016, 4, 7, 21, 31, 21, tzinfo=UTC) for w in seen)
    md = (out / "report.md").read_text()
    assert "no --scenario or --sim: the baseline is the packaged open-field scenario" in md


def _template(n: int = 100) -> PositionSeries:
    zeros = np.zeros(n)
    return PositionSeries(
        t_s=np.arange(n, dtype=float),
        east_m=zeros,
        north_m=zeros,
        up_m=zeros,
        valid=np.ones(n, dtype=bool),
        origin_lat_deg=51.70,
        origin_lon_deg=-1.20,
    )


def test_what_is_taken_from_the_log_and_what_is_not() -> None:
    scenario = load_world(SCENARIO)
    near = datetime(2020, 1, 2, 6, 30, tzinfo=UTC).timestamp()  # a day from the almanac
    world, notes = place_at_log(scenario, _template(), near, 123.4, "--truth's altitude")
    assert world.start_utc == datetime(2020, 1, 2, 6, 30, tzinfo=UTC)
    assert (world.origin.lat_deg, world.origin.lon_deg, world.origin.alt_m) == (51.70, -1.20, 123.4)
    assert len(notes) == 1 and "altitude 123 m (--truth's altitude)" in notes[0]  # no sky warning
    # a log without a date (a receive clock) keeps the scenario's, and says what that means;
    # an altitude no origin takes (a bad column) or none keeps the scenario's
    for alt_m, said in (
        (math.nan, "altitude 60 m (the scenario's; the log gives none)"),
        (1e6, "altitude 60 m (the scenario's: the real log's mean altitude, 1000000 m, is"
         " outside -500..9000 m)"),
    ):  # fmt: skip
        world, (note,) = place_at_log(scenario, _template(), None, alt_m)
        assert world.start_utc == scenario.start_utc and world.origin.alt_m == 60.0
        assert "2020-01-01 12:00:00Z, the scenario's start_utc: the real log has no date" in note
        assert said in note, note
