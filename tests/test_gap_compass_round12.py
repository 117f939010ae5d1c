"""The compass half of ``x6wd gap`` after an outside audit (round 12, /tmp/s12/a3): the
report when only the GPS half is explained, the heading reference of the baseline logs,
readings that are not numbers, a stuck compass, and fits beyond physical bounds.

Data: the project's CMPS10 emulation along a short weaving drive (:func:`drive_track`), as
tests/test_gap_compass.py builds it; the GPS half from :func:`surrogate_run`."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from sim_backend.effects import Bias, HeadingSeries, Quantization
from x6wd.gap.compass import (
    CompassOptions,
    diagnose_compass,
    drive_track,
    simulate_compass,
)
from x6wd.gap.diagnose import Options, diagnose
from x6wd.gap.report import merged_report, write_report
from x6wd.gap.surrogate import BASELINE_EFFECTS, surrogate_run

OPT = CompassOptions(ci_resamples=20, replicates=10)


@pytest.fixture(scope="module")
def drive() -> HeadingSeries:
    return drive_track(300.0, 0.1, np.random.default_rng(21))


def compass_null(drive: HeadingSeries):
    """A compass half with no effect: another seed of the emulation against three."""
    real = simulate_compass(drive, np.random.default_rng(1))
    base = [simulate_compass(drive, np.random.default_rng(10 + i)) for i in range(3)]
    return diagnose_compass(real, base, np.random.default_rng(0), OPT)


# --- 1. the report when the GPS half is explained and the compass half selects nothing ------


def test_report_with_an_explained_gps_half_and_no_compass_selection(
    drive: HeadingSeries, tmp_path: Path
) -> None:
    pre = BASELINE_EFFECTS[:-1]
    runs = [surrogate_run(600.0, 1.0, np.random.default_rng(100 + i)) for i in range(8)]
    real = surrogate_run(
        600.0, 1.0, np.random.default_rng(7), effects=[*pre, Bias(4.0, -3.0, 0.0), Quantization(5)]
    )
    gps = diagnose(real, runs, np.random.default_rng(2), Options(ci_resamples=40))
    assert gps.explained and gps.selected[0].name == "bias"
    compass = compass_null(drive)
    assert not compass.selected
    report = merged_report(gps, compass)  # IndexError before round 12
    verdict = report["verdict"]
    assert verdict["effect"] == "bias" and verdict["explained"]
    assert verdict["effects"] == ["bias"]  # the headline is the GPS half's
    assert verdict["halves"]["heading"]["status"] == "no_gap"
    write_report(gps, tmp_path, figures=False, compass=compass)
    assert json.loads((tmp_path / "report.json").read_text())["verdict"]["effect"] == "bias"
    assert "**compass: no significant gap.**" in (tmp_path / "report.md").read_text()

