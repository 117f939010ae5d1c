"""Injection benchmark of the gap tool (issue 6): withheld effects it must find.

"Real" logs are a baseline run with another seed plus an effect the tool is not told about,
for every fittable effect at weak / moderate / strong strength, static and moving, plus null
pairs and pairs of two effects. The main set uses the effects-only NEO-5 surrogate
(x6wd.gap.surrogate) as the simulator, which keeps a 1-hour pair within seconds; a smaller
set (static, moderate and strong, nulls) uses the project's pseudorange GNSS model
(sim_backend.gnss via x6wd.gap.scenario) for both the baseline and the "real" log. Prints
the confusion matrices (stderr) and the figures against the issue's targets.
"""

from __future__ import annotations

import sys
import time
from collections import Counter
from concurrent.futures import ProcessPoolExecutor
from typing import Any

import numpy as np

from bench._common import Row, print_table
from sim_backend.effects import (
    Bias,
    GaussMarkov,
    Jumps,
    Latency,
    Outages,
    Quantization,
    RandomWalk,
)
from x6wd.gap.diagnose import Options, diagnose
from x6wd.gap.surrogate import BASELINE_EFFECTS, surrogate_run

PRE = BASELINE_EFFECTS[:-1]
# kind, level, effect names, moving, seed, duration_s, baseline runs, source
Case = tuple[str, str, tuple[str, ...], bool, int, float, int, str]
OPEN_SKY = """name = "bench open sky"
start_utc = "2020-01-01T12:00:00Z"
duration_s = 3600.0
[origin]
lat_deg = 51.712345
lon_deg = 19.487654
alt_m = 100.0
[gnss]
fidelity = "pseudorange"
"""
STRENGTHS: dict[str, tuple[Any, Any, Any]] = {
    "gauss_markov": (GaussMarkov(0.4, 60.0), GaussMarkov(0.8, 60.0), GaussMarkov(1.5, 60.0)),
    "random_walk": (RandomWalk(0.01), RandomWalk(0.03), RandomWalk(0.08)),
    "bias": (Bias(0.6, -0.4, 0.0), Bias(1.5, -1.0, 0.0), Bias(3.0, -2.0, 0.0)),
    "quantization": (Quantization(4), Quantization(3), Quantization(2)),
    "jumps": (Jumps(0.5, 0.005), Jumps(1.0, 0.005), Jumps(2.0, 0.005)),
    "outages": (Outages(600.0, 5.0), Outages(200.0, 10.0), Outages(60.0, 20.0)),
    "latency": (Latency(0.2), Latency(0.5), Latency(1.0)),
}
LEVELS = ("weak", "moderate", "strong")
PAIRS = (
    ("gauss_markov", "bias"),
    ("quantization", "gauss_markov"),
    ("outages", "bias"),
    ("jumps", "quantization"),
)


def _real(effects: list[Any], duration_s: float, seed: int, moving: bool) -> Any:
    quant = [e for e in effects if e.name == "quantization"]
    rest = [e for e in effects if e.name != "quantization"]
    return surrogate_run(
        duration_s,
        1.0,
        np.random.default_rng(seed),
        moving=moving,
        effects=[*PRE, *rest, *(quant or [Quantization(5)])],
    )


def _case(case: Case) -> dict[str, Any]:
    kind, level, names, moving, seed, duration_s, m_runs, source = case
    li = LEVELS.index(level) if level in LEVELS else 1
    effects = [STRENGTHS[n][li] for n in names]
    if source == "gnss":
        import tempfile
        from pathlib import Path

        from x6wd.gap.scenario import scenario_baseline

        with tempfile.TemporaryDirectory() as tmp:
            path = Path(tmp) / "open.toml"
            path.write_text(OPEN_SKY)
            tpl = surrogate_run(duration_s, 1.0, np.random.default_rng(0), moving=moving)
            base = scenario_baseline(path, tpl, m_runs, base_seed=10_000 + 97 * seed)
            real = scenario_baseline(path, tpl, 1, base_seed=seed, extra_effects=effects)[0]
    else:
        base = [
            surrogate_run(
                duration_s, 1.0, np.random.default_rng(10_000 + 97 * seed + i), moving=moving
            )
            for i in range(m_runs)
        ]
        real = _real(effects, duration_s, seed, moving)
    t0 = time.perf_counter()
    d = diagnose(real, base, np.random.default_rng(seed), Options(ci_resamples=50))
    dt = time.perf_counter() - t0
    sel = [f.name for f in d.selected]
    right = next((c for c in d.candidates if names and c.fit.name == names[0]), None)
    wrong = [c.closure for c in d.candidates if c.fit.name not in names]
    top = sel[0] if d.explained and sel else ("none" if not d.significant else "unexplained")
    return {
        "source": source, "kind": kind, "level": level, "names": names, "moving": moving,
        "top": top, "selected": sel,
        "significant": d.significant, "seconds": dt,
        "closure_right": right.closure if right else None, "closure_wrong": wrong,
        "params": right.fit.params if right else None, "se": right.fit.se if right else None,
        "truth": effects[0].to_params() if effects else None,
    }  # fmt: skip


def cases(quick: bool) -> list[Case]:
    """Surrogate-baseline cases (all effects, levels, static and moving, nulls, pairs) and a
    smaller set on the project's pseudorange GNSS model (static, moderate and strong, nulls)."""
    duration_s = 900.0 if quick else 3600.0
    m_runs = 8 if quick else 12
    reps = 1 if quick else 2
    out: list[Case] = []
    seed = 1
    for moving in (False, True):
        for name in STRENGTHS:
            if name == "latency" and not moving:
                continue  # latency is invisible at rest
            for level in LEVELS if not quick else ("moderate", "strong"):
                for _ in range(reps):
                    out.append(
                        ("single", level, (name,), moving, seed, duration_s, m_runs, "surrogate")
                    )
                    seed += 1
        # 30 null pairs per motion state: 60 in all, so that a false-alarm rate of 5 % is
        # resolved (with 60 pairs, 0-3 alarms put the one-sided 95 % bound near 5-13 %)
        for _ in range(3 if quick else 30):
            out.append(("null", "", (), moving, seed, duration_s, m_runs, "surrogate"))
            seed += 1
    for pair in PAIRS if not quick else PAIRS[:1]:
        out.append(("pair", "moderate", pair, False, seed, duration_s, m_runs, "surrogate"))
        seed += 1
    if not quick:
        for name in STRENGTHS:
            if name == "latency":
                continue
            for level in ("moderate", "strong"):
                out.append(("single", level, (name,), False, seed, duration_s, m_runs, "gnss"))
                seed += 1
        for _ in range(10):
            out.append(("null", "", (), False, seed, duration_s, m_runs, "gnss"))
            seed += 1
    return out


def _param_ok(r: dict[str, Any]) -> dict[str, bool]:
    """Parameter accuracy against the issue's targets, per effect."""
    p, se, truth, n = r["params"], r["se"], r["truth"], r["names"][0]
    if p is None:
        return {}
    if n == "gauss_markov":
        return {
            "gm_tau_within_25pct": abs(p["tau_s"] / truth["tau_s"] - 1) <= 0.25,
            "gm_sigma_within_15pct": abs(p["sigma_m"] / truth["sigma_m"] - 1) <= 0.15,
        }
    if n == "quantization":
        return {"quantization_exact": p["decimals"] == truth["decimals"]}
    if n == "bias":
        return {
            "bias_within_0.1m_2se": all(
                abs(p[k] - truth[k]) <= 0.1 + 2 * se[k] for k in ("east_m", "north_m")
            )
        }
    if n == "latency":
        return {"latency_within_100ms": abs(p["delay_s"] - truth["delay_s"]) <= 0.1}
    return {}


def _upper95(k: int, n: int) -> float:
    """One-sided 95 % Clopper-Pearson upper bound of a rate seen k times in n trials."""
    from scipy.stats import beta

    return 1.0 if k >= n else float(beta.ppf(0.95, k + 1, n - k))


def run(quick: bool = False) -> list[Row]:
    """Run every case (2 worker processes) and summarise against the targets, separately for
    the surrogate and the GNSS-model baselines."""
    todo = cases(quick)
    with ProcessPoolExecutor(max_workers=2) as ex:
        results = list(ex.map(_case, todo))
    rows: list[Row] = []
    for source, prefix in (("surrogate", ""), ("gnss", "gnss model: ")):
        res = [r for r in results if r["source"] == source]
        if not res:
            continue
        print(f"[{source} baseline]", file=sys.stderr)
        part = _summary(res, quick)
        for row in part:
            row.metric = prefix + row.metric
        rows += part
    return rows


def _summary(results: list[dict[str, Any]], quick: bool) -> list[Row]:
    """Rows of one set of results; the confusion matrix goes to stderr."""
    rows: list[Row] = []
    b = "gap"
    nulls = [r for r in results if r["kind"] == "null"]
    n_fa = sum(r["significant"] for r in nulls)
    fa = n_fa / max(1, len(nulls))
    rows.append(
        Row(
            b,
            "false alarm rate, null pairs",
            fa,
            "fraction",
            0.05,
            "target <=",
            f"n={len(nulls)}, {n_fa} alarms, 95 % upper bound {_upper95(n_fa, len(nulls)):.3f}",
        )
    )
    singles = [r for r in results if r["kind"] == "single"]
    for level, target in (("weak", None), ("moderate", 0.90), ("strong", 0.97)):
        rs = [r for r in singles if r["level"] == level]
        if not rs:
            continue
        top1 = sum(r["top"] == r["names"][0] for r in rs) / len(rs)
        rows.append(
            Row(
                b,
                f"top-1 identification, {level}",
                top1,
                "fraction",
                target,
                "target >=" if target else "",
                f"n={len(rs)}",
            )
        )
    right = [
        r["closure_right"]
        for r in singles
        if r["closure_right"] is not None and r["level"] != "weak"
    ]
    wrong = [c for r in singles if r["level"] != "weak" for c in r["closure_wrong"]]
    if right:
        rows.append(
            Row(
                b,
                "held-out closure median, right effect",
                float(np.median(right)),
                "",
                0.7,
                "target >=",
                f"n={len(right)}",
            )
        )
    if wrong:
        rows.append(
            Row(
                b,
                "held-out closure median, wrong effects",
                float(np.median(wrong)),
                "",
                0.2,
                "target <=",
                f"n={len(wrong)}",
            )
        )
    pairs = [r for r in results if r["kind"] == "pair"]
    if pairs:
        both = sum(set(r["names"]) <= set(r["selected"]) for r in pairs) / len(pairs)
        rows.append(
            Row(b, "pairs: both effects selected", both, "fraction", None, "", f"n={len(pairs)}")
        )
    acc: dict[str, list[bool]] = {}
    for r in singles:
        if r["level"] == "weak":
            continue
        for k, v in _param_ok(r).items():
            acc.setdefault(k, []).append(v)
    for k, vs in sorted(acc.items()):
        rows.append(
            Row(b, f"parameters: {k}", sum(vs) / len(vs), "fraction", None, "", f"n={len(vs)}")
        )
    secs = [r["seconds"] for r in results]
    label = "900 s" if quick else "3600 s"
    rows.append(
        Row(
            b,
            f"seconds per pair ({label} at 1 Hz), median",
            float(np.median(secs)),
            "s",
            60.0,
            "target <=",
        )
    )
    rows.append(
        Row(
            b,
            f"seconds per pair ({label} at 1 Hz), max",
            float(np.max(secs)),
            "s",
            60.0,
            "target <=",
        )
    )
    # confusion matrix (true effect -> top answer) on stderr, strong + moderate singles
    conf: dict[str, Counter[str]] = {}
    for r in singles:
        if r["level"] != "weak":
            conf.setdefault(r["names"][0], Counter())[r["top"]] += 1
    for r in nulls:
        conf.setdefault("(null)", Counter())[r["top"]] += 1
    answers = sorted({a for c in conf.values() for a in c})
    print("confusion (rows: injected; columns: top answer; moderate+strong):", file=sys.stderr)
    print("  " + " ".join(f"{a[:12]:>12}" for a in ["", *answers]), file=sys.stderr)
    for k, c in conf.items():
        print(
            "  " + f"{k[:12]:>12} " + " ".join(f"{c.get(a, 0):>12}" for a in answers),
            file=sys.stderr,
        )
    return rows


if __name__ == "__main__":
    print_table(run(quick="--quick" in sys.argv))
