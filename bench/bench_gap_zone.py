"""How well the gap tool fits a withheld multipath zone (x6wd.gap.zone).

"Real" logs are a moving surrogate run (the NEO-5 baseline driving its 140 m loop, one lap
per 600 s) with a MultipathZone added: a 60 m wall just outside the top of the loop, the
zone reaching 20 m from it (about 10 % of the track, partly beside the wall, partly round
its ends, where the bias turns), Gauss-Markov sigma weak / moderate / strong (0.5 / 1.5 /
3 m, tau 10 s) with a bias of 0 / 1 / 2 m; 1 hour at 1 Hz, 12 baseline runs. Per setting:
the share of truly in-zone epochs the fitted zone covers, the share of the others it takes
in, sigma and tau against the truth, the bias error and how often it is within two of the
fit's standard errors, the time per fit. Null logs (no zone) must give no zone. Also a
slower zone (tau 60 s) and a bias-only zone, which the place map sees less well.

Run: ``python -m bench.bench_gap_zone [--quick]`` (one process: about 3 s per fit).
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from bench._common import Row, cli, print_table
from sim_backend.effects import MultipathZone, Quantization, truth_track_m
from x6wd.gap.stats import layout_for
from x6wd.gap.surrogate import BASELINE_EFFECTS, surrogate_run
from x6wd.gap.zone import fit_zone

DURATION_S = 3600.0
RUNS = 12
WALL = (113.0, 170.0, 173.0, 170.0)
DISTANCE_M = 20.0
SETTINGS = [(s, b, 10.0) for s in (0.5, 1.5, 3.0) for b in (0.0, 1.0, 2.0)]
EXTRA = [(0.5, 0.0, 60.0), (0.0, 2.0, 10.0)]  # a slow zone; a bias-only zone
SHARE_NULL = 0.02  # a "zone" on a null log smaller than this share of the track is noise


def _real(zone: MultipathZone | None, seed: int) -> Any:
    effects = [*BASELINE_EFFECTS[:-1], *([zone] if zone else []), Quantization(5)]
    return surrogate_run(DURATION_S, 1.0, np.random.default_rng(seed), moving=True, effects=effects)


def _case(base: list[Any], sigma: float, bias: float, tau: float, seed: int) -> dict[str, Any]:
    zone = MultipathZone(*WALL, distance_m=DISTANCE_M, sigma_m=sigma, bias_m=bias, tau_s=tau)
    real = _real(zone, seed)
    te, tn = truth_track_m(real)
    inside = zone.distance_to_wall_m(te, tn)[0] <= DISTANCE_M
    t0 = time.perf_counter()
    fit = fit_zone(real, base, layout_for(real))
    out: dict[str, Any] = {"time": time.perf_counter() - t0, "found": fit is not None}
    if fit is not None:
        p = fit.effect
        out |= {
            "cover": float(np.mean(fit.in_zone[inside])),
            "outside": float(np.mean(fit.in_zone[~inside])),
            "sigma": p.sigma_m, "tau": p.tau_s, "bias": p.bias_m,
            "bias_in_2se": abs(p.bias_m - bias) <= 2 * fit.se["bias_m"],
        }  # fmt: skip
    return out


def run(quick: bool = False) -> list[Row]:
    """Fit every setting ``reps`` times and ``nulls`` null logs."""
    reps, nulls = (1, 6) if quick else (5, 24)
    base = [
        surrogate_run(DURATION_S, 1.0, np.random.default_rng(70_000 + i), moving=True)
        for i in range(RUNS)
    ]
    rows: list[Row] = []
    b = "gap_zone"
    times: list[float] = []
    for sigma, bias, tau in SETTINGS + EXTRA:
        rs = [
            _case(base, sigma, bias, tau, 9_000 + 97 * k + int(10 * sigma + bias))
            for k in range(reps)
        ]
        times += [r["time"] for r in rs]
        ok = [r for r in rs if r["found"]]
        label = f"zone sigma {sigma:g} m tau {tau:g} s bias {bias:g} m"
        rows.append(Row(b, f"{label}: found", len(ok) / len(rs), "fraction", 1.0, "all"))
        if not ok:
            continue
        get = {k: np.array([r[k] for r in ok], dtype=float) for k in ok[0] if k != "found"}
        rows += [
            Row(b, f"{label}: in-zone epochs covered", float(np.median(get["cover"])), "median",
                0.8, "target", f"min {get['cover'].min():.3f}"),
            Row(b, f"{label}: other epochs taken in", float(np.median(get["outside"])), "median",
                0.1, "limit", f"max {get['outside'].max():.4f}"),
        ]  # fmt: skip
        for name, truth in (("sigma", sigma), ("tau", tau)):
            if sigma > 0:  # without noise its sigma and tau mean nothing
                ratio = get[name] / truth
                rows.append(
                    Row(b, f"{label}: {name} / truth", float(np.median(ratio)), "median", 1.0,
                        "truth", f"mean |error| {np.mean(np.abs(ratio - 1)):.0%}")
                )  # fmt: skip
        err = get["bias"] - bias
        rows.append(
            Row(b, f"{label}: bias error", float(np.median(err)), "m (median)",
                note=f"rms {np.sqrt(np.mean(err**2)):.2f} m, within 2 se: "
                f"{np.mean(get['bias_in_2se']):.2f}")
        )  # fmt: skip
    false, null_times = 0, []
    for k in range(nulls):
        real = _real(None, 20_000 + k)
        t0 = time.perf_counter()
        fit = fit_zone(real, base, layout_for(real))
        null_times.append(time.perf_counter() - t0)
        false += fit is not None and float(np.mean(fit.in_zone)) >= SHARE_NULL
    rows += [
        Row(b, f"null logs with a zone (n={nulls})", false / nulls, "fraction", 0.05, "alpha"),
        Row(b, "time per fit, zone", float(np.median(times)), "s (median)",
            note=f"max {max(times):.1f} s"),
        Row(b, "time per fit, null log", float(np.median(null_times)), "s (median)",
            note=f"max {max(null_times):.1f} s"),
    ]  # fmt: skip
    return rows


if __name__ == "__main__":
    print_table(run(quick=cli(__doc__).parse_args().quick))
