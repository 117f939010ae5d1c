"""The GPS effects the gap pipeline can fit, registered in :data:`EFFECTS` (fitter, the
battery cells each moves: its fingerprint, and what a simulation refit may move); plus the
direct fits that need no likelihood (quantisation lattice, outage runs).

Fits are made against the baseline ensemble, never against a single sim: an effect adds to
whatever the simulator already does. The fitters live by method: the drift family and its
companions by exact likelihood (:mod:`x6wd.gap.drift`), jumps by a step-law mixture
(:mod:`x6wd.gap.jumps`), the multipath zone by a masked likelihood (:mod:`x6wd.gap.zone`), all
on top of the baseline noise model (:mod:`x6wd.gap.noise`); this module sits above them all.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from sim_backend.effects import Outages, PositionSeries, Quantization
from x6wd.gap.drift import fit_bias, fit_gauss_markov, fit_latency, fit_random_walk
from x6wd.gap.fitted import Fit
from x6wd.gap.jumps import fit_jumps
from x6wd.gap.noise import NoiseModel
from x6wd.gap.pipeline import EffectFitter
from x6wd.gap.stats import LATTICES, Layout, lattice_fraction
from x6wd.gap.zone import fit_multipath_zone

# Re-exported for callers that knew them here (tests/conftest.py builds a NoiseModel).
__all__ = [
    "EFFECTS",
    "FINGERPRINTS",
    "FITTABLE",
    "FITTERS",
    "SIM_REFIT",
    "Fit",
    "NoiseModel",
    "fit_outages",
    "fit_quantization",
]


def fit_quantization(
    real: PositionSeries, baseline: Sequence[PositionSeries], layout: Layout
) -> Fit | None:
    """The coarsest lattice all real fixes lie on (exact), of NMEA minutes or of decimal
    degrees (:data:`x6wd.gap.stats.LATTICES`, coarsest step first: a log rounded to 1e-5
    deg is also on 1e-4 min, a grid six times finer), when the baseline is not already on
    it."""
    for decimals, unit in LATTICES:
        if lattice_fraction(real, decimals, unit) >= 0.99:
            if np.mean([lattice_fraction(s, decimals, unit) for s in baseline]) >= 0.99:
                return None
            return Fit(Quantization(decimals=decimals, unit=unit), {"decimals": 0.0})
    return None


def fit_outages(
    real: PositionSeries, baseline: Sequence[PositionSeries], layout: Layout
) -> Fit | None:
    """Two-state Markov outages by maximum likelihood from the real log's valid/invalid runs
    (mean run lengths), when the real log loses its fix more often than the baseline."""
    valid = np.asarray(real.valid, dtype=bool)
    if valid.size < 3:
        return None
    baseline_availability = float(
        np.mean([np.mean(np.asarray(s.valid, dtype=bool)) for s in baseline])
    )
    if np.mean(valid) >= baseline_availability:
        return None
    edges = np.diff(np.concatenate(([1], valid.astype(int), [1])))
    n_down = int(np.count_nonzero(edges == -1))
    if n_down == 0:
        return None
    dt_s = layout.dt_s
    up_s = float(np.count_nonzero(valid)) * dt_s
    down_s = float(np.count_nonzero(~valid)) * dt_s
    mean_up_s, mean_down_s = up_s / n_down, down_s / n_down
    return Fit(
        Outages(mean_up_s=round(mean_up_s, 3), mean_down_s=round(max(mean_down_s, dt_s), 3)),
        {
            "mean_up_s": mean_up_s / math.sqrt(n_down),
            "mean_down_s": mean_down_s / math.sqrt(n_down),
        },
    )


# The GPS effects: fitter, fingerprint (the battery statistics the effect moves, which rank
# the candidates) and the positive parameters refined by simulation under a coarse NMEA
# lattice. A new effect is one row here (the order is the default candidates' order).
EFFECTS: dict[str, EffectFitter[PositionSeries, Layout]] = {
    "bias": EffectFitter(fit_bias, ("mean",)),
    "gauss_markov": EffectFitter(
        fit_gauss_markov,
        (
            "log_std",
            "log_adev",
            "log_psd",
            "acf",
            "log_cep50",
            "log_r95",
            "log_step_med",
            "log_incr_med",
        ),
        sim_refit=("sigma_m", "tau_s"),
    ),
    "random_walk": EffectFitter(
        fit_random_walk,
        ("log_adev", "log_psd", "log_std", "acf", "log_step_med", "log_incr_med"),
        sim_refit=("q_m_per_sqrt_s",),
    ),
    "quantization": EffectFitter(fit_quantization, ("lattice", "zero_step")),
    "jumps": EffectFitter(
        fit_jumps, ("step_tail", "log_step_std", "tail_ratio"), sim_refit=("sigma_m", "rate_per_s")
    ),
    "outages": EffectFitter(fit_outages, ("availability", "log_outage_s")),
    "latency": EffectFitter(fit_latency, ("latency_slope",)),
    # per-place spread and step size (moving logs): a zone makes one place noisier
    "multipath_zone": EffectFitter(
        fit_multipath_zone,
        ("log_rms_place", "log_step_std_place"),
        sim_refit=("sigma_m", "tau_s"),
    ),
}
FITTABLE = tuple(EFFECTS)
FITTERS = {name: e.fit for name, e in EFFECTS.items()}
FINGERPRINTS = {name: e.fingerprint for name, e in EFFECTS.items()}
SIM_REFIT = {name: e.sim_refit for name, e in EFFECTS.items() if e.sim_refit}
