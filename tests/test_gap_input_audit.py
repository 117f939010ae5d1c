"""The gap tool's input, after an outside audit: a baseline whose runs an outage leaves short
or empty is still fitted; a GGA satellite count that never changes carries no information;
corrupt sentences and missing counts or heights are said; logs whose positions come only from
GLL or GNS are read; clear messages for milliseconds, degrees-minutes, gzip and huge lines."""

from __future__ import annotations

import numpy as np

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
