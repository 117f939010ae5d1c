"""The closing validation when the simulated logs reach no figure (outside review round 13):
six --sim logs of 70-600 s against a 1230 s real log left every figure "not reached", and
writing the report died on ``max()`` of an empty list (report.md never written)."""

from __future__ import annotations

import json
import math

from x6wd.gap import report
from x6wd.gap.validate import Validation


def _unreached() -> Validation:
    nan = math.nan
    return Validation(
        n_runs=3,
        mean_real_m=2.0,
        mean_sim_m=nan,
        sd_real_m=1.0,
        sd_sim_m=nan,
        taus_s=(1.0, 2.0, 4.0),
        adev_real_m=(0.5, 0.4, 0.3),
        adev_sim_m=(nan, nan, nan),
    )


def test_a_validation_that_reaches_no_figure_is_said_not_a_crash() -> None:
    v = _unreached()
    assert v.worst() == (None, v.worst()[1]) and math.isnan(v.worst()[1])
    assert "reach no figure" in v.worst_text()
    out = report._validation_json(v)
    assert out["furthest_off"]["figure"] is None
    json.dumps(out)  # report.json takes it as it is


def test_a_validation_that_reaches_a_figure_names_the_furthest_off() -> None:
    v = Validation(
        n_runs=3, mean_real_m=2.0, mean_sim_m=2.2, sd_real_m=1.0, sd_sim_m=1.5,
        taus_s=(1.0,), adev_real_m=(0.5,), adev_sim_m=(0.5,),
    )  # fmt: skip
    label, rel = v.worst()
    assert label == "sigma" and abs(rel - 0.5) < 1e-12
    assert "simulated 50.0% above the real" in v.worst_text()
