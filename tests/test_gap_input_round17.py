"""The gap tool's input, round 17: a FIFO without a writer is named while the tool waits,
and a log dated a GPS week rollover early gets a note saying so."""

from __future__ import annotations

import os
import threading
import time
from datetime import UTC, datetime
from pathlib import Path

import numpy as np
import pytest

from sim_backend.effects import PositionSeries
from sim_backend.world import load_world
from x6wd.gap.cli import read_input
from x6wd.gap.io import read_track
from x6wd.gap.scenario import place_at_log, week_rollover_hint

LOG = Path(__file__).parent / "data" / "nmea" / "quectel-l76k-dual.log"
SCENARIO = Path(__file__).resolve().parents[1] / "config" / "scenarios" / "open_field.toml"


@pytest.mark.parametrize("linked", [False, True])
def test_a_fifo_without_a_writer_is_named_while_the_tool_waits(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], linked: bool
) -> None:
    """Opening a FIFO blocks until its writer comes: `x6wd gap --real FIFO` sat silent; so
    did a symlink to one (an outside review), which not_regular calls "a pipe"."""
    path = tmp_path / "log.fifo"
    os.mkfifo(path)
    if linked:
        (tmp_path / "link").symlink_to(path)
        path = tmp_path / "link"
    said = threading.Event()

    def write() -> None:
        deadline = time.monotonic() + 10.0
        while "waiting for its writer" not in capsys.readouterr().err:
            assert time.monotonic() < deadline, "nothing said while waiting"
            time.sleep(0.05)
        said.set()
        with open(path, "wb") as f:
            f.write(LOG.read_bytes())

    writer = threading.Thread(target=write, daemon=True)
    writer.start()
    track = read_input(path)
    writer.join(10)
    assert said.is_set()  # said before the writer came (the writer waited for the words)
    assert len(track.t_s) == len(read_track(LOG).t_s) > 0
    assert read_input(LOG).source == str(LOG)
    assert capsys.readouterr().err == ""  # a regular file: nothing to say


def _series(start: datetime) -> PositionSeries:
    t = np.arange(600.0)
    z = np.zeros_like(t)
    return PositionSeries(
        t_s=t, east_m=z, north_m=z, up_m=z, valid=np.ones(t.shape, bool),
        origin_lat_deg=51.7, origin_lon_deg=19.5,
    )  # fmt: skip


NOW = datetime(2026, 12, 1, tzinfo=UTC)  # the hint's clock, fixed: no test expires


@pytest.mark.parametrize(
    ("printed", "rolled"),
    [
        (datetime(2001, 9, 16, 10, 0, tzinfo=UTC), "1024 weeks later, on 2021-05-02, and"),
        (datetime(2000, 2, 20, 8, 0, tzinfo=UTC), "1024 weeks later, on 2019-10-06, and"),
        (datetime(2020, 6, 1, 12, 0, tzinfo=UTC), None),  # after the last rollover
        (datetime(2010, 1, 1, 12, 0, tzinfo=UTC), None),  # 2029: the future
        # firmware from before 1999 today: 2048 weeks early
        (
            datetime(1987, 3, 1, 12, 0, tzinfo=UTC),
            "on 2006-10-15 or 2048 weeks later, on 2026-05-31",
        ),
    ],
)
def test_a_log_dated_a_week_rollover_early_gets_a_note(
    printed: datetime, rolled: str | None
) -> None:
    hint = week_rollover_hint(printed.timestamp(), NOW)
    if rolled is None:
        assert hint == ""
    else:
        assert f"dated {printed:%Y-%m-%d}" in hint and rolled in hint, hint


def test_the_rollover_note_reaches_the_reports_notes() -> None:
    printed = datetime(2001, 9, 16, 10, 0, tzinfo=UTC)
    world = load_world(SCENARIO)
    _, notes = place_at_log(world, _series(printed), start_utc_s=printed.timestamp())
    (note,) = [n for n in notes if "week rollover" in n]
    assert "on 2021-05-02" in note and notes.index(note) > 0, notes  # said on stderr too
