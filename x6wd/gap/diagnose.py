"""The gap pipeline: where the gap lies, which effect explains it, how far it closes.

1. Null: the baseline ensemble (M sim runs, or a block bootstrap of fewer) calibrates every
   cell of the battery; cells of the real log beyond the family-wise threshold are "where".
2. Candidates are ranked by their fingerprint on the battery, fitted on the first part of the
   log, added to every baseline run, and scored on the held-out last part (after a guard gap)
   by G = mean clipped z^2; closure = (G_baseline - G_effect) / (G_baseline - G_floor).
3. Greedy add-one-in (up to three effects), then leave-one-out drops any that no longer help.
   Within the drift family (bias, Gauss-Markov, random walk) only the member(s) the exact
   whole-log likelihood names by BIC may be selected (see :func:`x6wd.gap.drift.drift_fit`).
4. The reported parameters (with standard errors) are refitted on the WHOLE log; the closures
   stay those of the fit-part fits scored on the held-out part.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from sim_backend.effects import PositionSeries, Quantization
from x6wd.core.errors import ConfigError
from x6wd.gap.drift import (
    COMPANIONS,
    DRIFT_FAMILY,
    DRIFTS,
    drift_fit,
    joint_drift_fits,
    random_walk_lr,
)
from x6wd.gap.fit import FITTABLE, FITTERS, fingerprint_score
from x6wd.gap.fitted import Fit
from x6wd.gap.noise import noise_model
from x6wd.gap.null import NullModel, block_bootstrap, closure_ci, closure_of, null_model
from x6wd.gap.stats import (
    QUANT_DECIMALS,
    Cell,
    Layout,
    battery,
    lattice_fraction,
    layout_for,
    window,
)

Progress = Callable[[str, float], None]

EXPLAINED_CLOSURE = 0.5  # a selection closing at least half the held-out gap explains it
ADD_MIN_GAIN = 0.1  # a first effect must close at least 10 % of the gap
ADD_MIN_LEFT = 0.5  # G above the floor still worth explaining (null G - floor spread ~0.2)
ADD_MIN_SHARE = 0.3  # a further effect must remove 30 % of the gap left
FINAL_DRAWS = 4  # fresh draws of an effect ensemble, pooled, for decisions and the closure
# Whole-log cell: signed root likelihood ratio of a random walk on top of the baseline noise
# model (see :func:`x6wd.gap.drift.random_walk_lr`).
RW_LR_CELL = Cell("random_walk_lr", "horizontal")


@dataclass(frozen=True)
class Options:
    """Pipeline settings: ``replicates`` the size of a bootstrap ensemble (when fewer than
    ``min_runs`` baseline runs are given), ``fit_fraction`` and ``guard_fraction`` of the log,
    ``alpha`` the family-wise error rate, ``candidates`` the effects considered,
    ``ci_resamples`` for closure intervals."""

    replicates: int = 20
    min_runs: int = 8
    fit_fraction: float = 0.6
    guard_fraction: float = 0.05
    alpha: float = 0.05
    candidates: tuple[str, ...] = FITTABLE
    ci_resamples: int = 200
    max_effects: int = 3

    def __post_init__(self) -> None:
        if not 0.2 <= self.fit_fraction <= 0.8:
            raise ConfigError(f"fit_fraction={self.fit_fraction}: must be in [0.2, 0.8]")
        if not 0.0 <= self.guard_fraction <= 0.2:
            raise ConfigError(f"guard_fraction={self.guard_fraction}: must be in [0, 0.2]")
        unknown = sorted(set(self.candidates) - set(FITTABLE))
        if unknown:
            raise ConfigError(f"candidates {unknown} cannot be fitted; fittable: {list(FITTABLE)}")


@dataclass
class Candidate:
    """A fitted effect and how it scored on the held-out part."""

    fit: Fit
    score: float  # fingerprint evidence on the fit part
    closure: float
    closure_ci: tuple[float, float]
    g_effect: float


@dataclass(kw_only=True)
class Outcome:
    """What both halves (GPS and compass) report: null-calibrated cells, where the gap is,
    the candidates and the selected effects with their held-out closure."""

    bootstrap: bool
    cells: tuple[Cell, ...]
    z: np.ndarray
    threshold: float
    where: list[dict[str, Any]]
    g_baseline: float
    g_floor: float
    g_with: float
    candidates: list[Candidate]
    selected: list[Fit]
    closure: float
    split_s: tuple[float, float, float]
    # 5-95 % interval of the selection's held-out closure over resamples of the ensembles
    closure_ci: tuple[float, float] = (0.0, 0.0)
    notes: list[str] = field(default_factory=list)

    @property
    def significant(self) -> bool:
        return bool(self.where)

    @property
    def explained(self) -> bool:
        return self.significant and bool(self.selected) and self.closure >= EXPLAINED_CLOSURE


@dataclass(kw_only=True)
class Diagnosis(Outcome):
    """Everything the report needs (GPS half)."""

    layout: Layout
    real: PositionSeries
    baseline: list[PositionSeries]
    null: NullModel


def _lattice_decimals(series: Sequence[PositionSeries]) -> int | None:
    """The NMEA minute lattice every series lies on (None if not quantised)."""
    for dec in QUANT_DECIMALS:
        if all(lattice_fraction(s, dec) >= 0.99 for s in series[:3]):
            return dec
    return None


def apply_fits(
    fits: Sequence[Fit],
    runs: Sequence[PositionSeries],
    rng: np.random.Generator,
    lattice: int | None,
) -> list[PositionSeries]:
    """Each run with the effects added, then printed on the baseline's NMEA lattice again
    (a receiver prints its final position; an added error does not leave the lattice)."""
    out = []
    eff_lattice = next((f.effect.decimals for f in fits if f.name == "quantization"), lattice)
    for s in runs:
        for f in fits:
            if f.name != "quantization":
                s = f.effect.apply(s, rng)
        if eff_lattice is not None:
            s = Quantization(decimals=int(eff_lattice)).apply(s, rng)
        out.append(s)
    return out


def _batteries(
    runs: Sequence[PositionSeries], layout: Layout, t0: float, t1: float
) -> list[dict[Cell, float]]:
    return [battery(window(s, t0, t1), layout) for s in runs]


# Effects whose parameters are refined by simulation when a coarse NMEA lattice is in the
# model: their positive parameters, searched in log space.
SIM_REFIT: dict[str, tuple[str, ...]] = {
    "gauss_markov": ("sigma_m", "tau_s"),
    "random_walk": ("q_m_per_sqrt_s",),
    "jumps": ("sigma_m", "rate_per_s"),
    "multipath_zone": ("sigma_m", "tau_s"),
}
SIM_REFIT_EVALS = 30


def simulation_refit(
    fit: Fit,
    others: Sequence[Fit],
    real_b: dict[Cell, float],
    runs: Sequence[PositionSeries],
    layout: Layout,
    lattice: int | None,
    ref_sd: np.ndarray | None = None,
    alt_start: Fit | None = None,
) -> Fit:
    """``fit`` with its :data:`SIM_REFIT` parameters moved to minimise G of ``real_b`` against
    ``runs`` plus ``others`` plus the effect, printed on the lattice (Nelder-Mead in log
    parameters from the analytical fit, or from ``alt_start`` when that scores better; common
    random numbers so that G is smooth in them). Rounding to a coarse lattice is not
    additive: an effect that moves the position makes it cross lattice lines faster, which a
    likelihood on top of the quantised baseline's own noise credits to the effect (a 0.8 m /
    60 s drift under a 1.85 m lattice fitted as 0.74 m / 19 s, or on another log as 0.16 m /
    2.3 s, too far for a short local search). A parameter moved by simulation has no standard
    error (NaN): the analytical one belongs to another point."""
    from scipy.optimize import minimize

    keys = SIM_REFIT.get(fit.name, ())
    p0 = fit.effect.to_params()
    if not keys or any(float(p0[k]) <= 0 for k in keys):
        return fit
    x0 = np.log([float(p0[k]) for k in keys])
    cls = type(fit.effect)

    def make(x: np.ndarray) -> Fit:
        params = {k: v for k, v in p0.items() if k != "name"}
        params.update({k: round(float(math.exp(v)), 6) for k, v in zip(keys, x, strict=True)})
        # a likelihood's curvature says nothing about a point it did not choose
        return Fit(cls(**params), {**fit.se, **{k: math.nan for k in keys}})

    def g_of(x: np.ndarray) -> float:
        rng = np.random.default_rng(20_241)  # common random numbers across evaluations
        with_runs = apply_fits([*others, make(x)], runs, rng, lattice)
        return null_model([battery(s, layout) for s in with_runs]).gap(real_b, ref_sd)

    g0 = g_of(x0)
    moved = False
    if alt_start is not None and alt_start.name == fit.name:
        pa = alt_start.effect.to_params()
        if all(float(pa[k]) > 0 for k in keys):
            xa = np.log([float(pa[k]) for k in keys])
            ga = g_of(xa)
            if ga < g0:
                x0, g0, moved = xa, ga, True
    res = minimize(
        g_of,
        x0,
        method="Nelder-Mead",
        options={
            "maxfev": SIM_REFIT_EVALS,
            "xatol": 0.02,
            "fatol": 1e-3,
            "initial_simplex": np.vstack([x0, x0 + 0.3 * np.eye(len(keys))]),
        },
    )
    if res.fun < g0:
        return make(res.x)
    return make(x0) if moved else fit


def _refit_whole(
    selected: Sequence[Fit],
    real: PositionSeries,
    runs: Sequence[PositionSeries],
    layout: Layout,
    rng: np.random.Generator,
    lattice: int | None,
) -> list[Fit]:
    """Each selected effect refitted on the whole log on top of the baseline runs plus the
    other selected effects (its fit-part version kept when the refit fails)."""
    names = [f.name for f in selected]
    drift = next((n for n in names if n in DRIFTS), None)
    joint: dict[str, Fit] = {}
    if drift is not None:
        # the drift and the bias / latency beside it: one joint likelihood, on top of the
        # baseline plus the selected effects outside that family
        rest = [g for g in selected if g.name != drift and g.name not in COMPANIONS]
        base = apply_fits(rest, runs, rng, lattice) if rest else list(runs)
        flags = ("bias" in names, "latency" in names)
        joint = {f.name: f for f in joint_drift_fits(real, base, layout, drift, flags)}
    coarse = "quantization" in names
    real_b = battery(real, layout) if coarse else {}
    out = []
    for f in selected:
        others = [g for g in selected if g is not f]
        if f.name in joint:
            whole: Fit | None = joint[f.name]
        else:
            base = apply_fits(others, runs, rng, lattice) if others else list(runs)
            whole = FITTERS[f.name](real, base, layout)
        if whole is not None and coarse and f.name in SIM_REFIT:
            # the fit-part fit was already refined by simulation: a second start
            whole = simulation_refit(whole, others, real_b, runs, layout, lattice, alt_start=f)
        out.append(whole if whole is not None else f)
    return out


def diagnose(
    real: PositionSeries,
    baseline: Sequence[PositionSeries],
    rng: np.random.Generator,
    options: Options | None = None,
    progress: Progress | None = None,
) -> Diagnosis:
    """Run the whole pipeline on an error series and its baseline runs (errors, metres)."""
    opt = options or Options()
    say = progress or (lambda _msg, _frac: None)
    if len(real) < 60:
        raise ConfigError(
            f"real log too short for a gap diagnosis: {len(real)} epochs (need >= 60)"
        )
    if not baseline:
        raise ConfigError("no baseline: give --sim logs or --scenario")
    layout = layout_for(real)
    notes: list[str] = []
    runs = list(baseline)
    boot = len(runs) < opt.min_runs
    if boot:
        block_s = max(layout.duration_s / 4.0, 10 * layout.dt_s)
        runs = block_bootstrap(runs, opt.replicates, rng, block_s, template=real)
        notes.append(
            f"baseline: {len(baseline)} sim log(s), null from a circular block bootstrap "
            f"({opt.replicates} replicates, blocks of {block_s:.0f} s): slower drifts than a block "
            "are under-represented, so treat long-scale cells with care"
        )
    lattice = _lattice_decimals(runs)
    T = layout.duration_s

    # 1. where: the whole log against the baseline null
    say("calibrating the sim-vs-sim null", 0.05)
    full_b = _batteries(runs, layout, 0.0, T + layout.dt_s)
    real_full = battery(real, layout)
    # The random-walk likelihood ratio is a whole-log cell only: it needs the noise model of
    # the baseline, and the split parts are too short for a walk to show. The baseline runs
    # are scored against a model fitted on all of them (in-sample, so their ratios are if
    # anything smaller); its SD_FLOOR keeps the cell honest when most of them are exactly 0.
    nm = noise_model(runs, layout)
    for b, s in zip(full_b, runs, strict=True):
        b[RW_LR_CELL] = random_walk_lr(s, nm)
    real_full[RW_LR_CELL] = random_walk_lr(real, nm)
    null = null_model(full_b, opt.alpha)
    z = null.z(real_full)
    where = [
        {
            "statistic": c.statistic,
            "axis": c.axis,
            "scale": c.scale,
            "period": c.period,
            "place": c.place,
            "z": round(float(zc), 2),
        }
        for c, zc in sorted(zip(null.cells, z, strict=True), key=lambda p: -abs(p[1]))
        if abs(zc) > null.threshold
    ]

    # 2. split: fit part, guard gap, held-out test part
    t_fit = opt.fit_fraction * T
    t_test = t_fit + opt.guard_fraction * T
    fit_lay = Layout(
        layout.dt_s, t_fit, layout.moving, layout.place_e_m, layout.place_n_m, layout.has_up
    )
    test_lay = Layout(
        layout.dt_s, T - t_test, layout.moving, layout.place_e_m, layout.place_n_m, layout.has_up
    )
    real_fit = window(real, 0.0, t_fit)
    real_test_b = battery(window(real, t_test, T + layout.dt_s), test_lay)
    base_test = null_model(_batteries(runs, test_lay, t_test, T + layout.dt_s), opt.alpha)
    ref_sd = base_test.sd
    g_b = base_test.gap(real_test_b, ref_sd)
    g_f = base_test.floor(ref_sd)
    diag = Diagnosis(
        layout=layout,
        real=real,
        baseline=runs,
        null=null,
        bootstrap=boot,
        cells=null.cells,
        z=z,
        threshold=null.threshold,
        where=where,
        g_baseline=g_b,
        g_floor=g_f,
        g_with=g_b,
        candidates=[],
        selected=[],
        closure=0.0,
        split_s=(t_fit, t_test, T),
        notes=notes,
    )
    if not where:
        say("no significant gap", 1.0)
        return diag

    # 3. candidates: fingerprint, fit, held-out closure; greedy add-one-in
    selected: list[Fit] = []
    current = runs
    g_cur = g_b
    scored: dict[str, Candidate] = {}
    real_fit_b = battery(real_fit, fit_lay)
    # the drift-family member and the bias or latency the whole-log likelihood names: the
    # short held-out part cannot tell them from look-alikes (a walk over 20 minutes is a bias;
    # a drift widens the spread of means or soaks up a speed-correlated error), so
    # leave-one-out keeps them and drops only what the likelihood did not ask for
    named_by_likelihood: set[str] = set()
    runs_fit = [window(s, 0.0, t_fit) for s in runs]
    ref_fit_sd = null_model([battery(s, fit_lay) for s in runs_fit], opt.alpha).sd

    def evaluate(fits: list[Fit]) -> tuple[float, float, NullModel, list[PositionSeries]]:
        """(selection key, held-out G, held-out null, runs) of the baseline plus ``fits``."""
        with_runs = apply_fits(fits, runs, rng, lattice)
        eff_null = null_model(_batteries(with_runs, test_lay, t_test, T + layout.dt_s), opt.alpha)
        g_e = eff_null.gap(real_test_b, ref_sd)
        fit_part = null_model(_batteries(with_runs, fit_lay, 0.0, t_fit), opt.alpha)
        return g_e + fit_part.gap(real_fit_b, ref_fit_sd), g_e, eff_null, with_runs

    def pooled_gap(fits: list[Fit]) -> tuple[float, NullModel]:
        """Held-out G of the baseline plus ``fits`` on FINAL_DRAWS fresh draws, pooled."""
        pooled: list[PositionSeries] = []
        for _ in range(FINAL_DRAWS):
            pooled += apply_fits(fits, runs, rng, lattice)
        nm = null_model(_batteries(pooled, test_lay, t_test, T + layout.dt_s), opt.alpha)
        return nm.gap(real_test_b, ref_sd), nm

    for round_ in range(opt.max_effects):
        # a lattice coarser than the baseline's is in the model: fits through it by simulation
        lattice_now = next(
            (int(f.effect.decimals) for f in selected if f.name == "quantization"), lattice
        )
        coarse = lattice_now != lattice
        cur_fit = [window(s, 0.0, t_fit) for s in current]
        fit_null = null_model([battery(s, fit_lay) for s in cur_fit], opt.alpha)
        zf = fit_null.z(battery(real_fit, fit_lay))
        names = [n for n in opt.candidates if n not in {f.name for f in selected}]
        ranked = sorted(names, key=lambda n: -fingerprint_score(n, fit_null.cells, zf))
        # Choice among candidates: held-out G plus the fit part's G. The fit part sees the
        # longer time scales a short held-out part cannot, so a look-alike (random walk for a
        # slow Gauss-Markov drift) that only matches the short scales loses.
        best: tuple[float, float, list[Fit], list[str]] | None = None
        mean_cells = np.array([c.statistic == "mean" for c in fit_null.cells])
        bias_flagged = bool(np.any(np.abs(zf[mean_cells]) > 3.0))
        # A lattice is a fact, not an estimate: every real fix lies on a coarser NMEA lattice
        # than the baseline's. It enters the model first and the rest is fitted through it
        # (a look-alike, such as white noise of the rounding error's size, must not take
        # its place and then double-count the rounding).
        lattice_fact = (
            round_ == 0
            and "quantization" in names
            and (FITTERS["quantization"](real_fit, cur_fit, fit_lay) is not None)
        )
        g_pair = math.inf
        # The drift family (bias, Gauss-Markov, random walk) is told apart by exact likelihood
        # on the whole log (BIC: none / bias / GM / GM + bias / RW / RW + bias on top of the
        # current baseline's noise model): only the member(s) it names may be selected this
        # round. The battery G alone cannot separate them: over one log a random walk looks
        # like a bias plus a slow drift, or a Gauss-Markov drift longer than the log.
        family = [n for n in names if n in DRIFT_FAMILY]
        fam_best: list[str] = []
        if family:
            say(
                f"round {round_ + 1}: drift family by likelihood",
                0.1 + 0.8 * round_ / opt.max_effects,
            )
            fam = drift_fit(real, current, layout)
            # In the first round "none" is not an answer: whether a gap exists is the
            # battery's question (sim-vs-sim calibrated). Once an effect is in, "none" means
            # the likelihood sees no drift left, and no drift is added.
            best_model = fam.best_effect if round_ == 0 else fam.best
            fam_best = [] if best_model == "none" else best_model.split("+")
            ranks = sorted(fam.models, key=fam.bic)
            notes.append(
                f"round {round_ + 1}: drift family by exact likelihood on the whole log: "
                f"{best_model} (BIC, lower is better, relative to it: "
                + ", ".join(
                    f"{m} {fam.bic(m) - fam.bic(best_model):+.1f}" for m in ranks if m != best_model
                )
                + ")"
            )
        for i, name in enumerate(ranked):
            say(
                f"round {round_ + 1}: fitting {name}",
                0.1 + 0.8 * (round_ + i / len(ranked)) / opt.max_effects,
            )
            fit = FITTERS[name](real_fit, cur_fit, fit_lay)
            if fit is None:
                continue
            in_family = name in DRIFT_FAMILY
            eligible = not in_family or bool(fam_best and fam_best[0] == name)
            if coarse and eligible and name in SIM_REFIT:
                fit = simulation_refit(
                    fit, selected, real_fit_b, runs_fit, fit_lay, lattice_now, ref_fit_sd
                )
            key, g_e, eff_null, with_runs = evaluate([*selected, fit])
            option = [fit]
            forced: list[str] = []  # companions named beside it by the likelihood
            comps = [c for c in fam_best[1:] if c in COMPANIONS and c in names and c != name]
            if in_family and eligible and comps and name in DRIFTS:
                # the likelihood names this drift WITH companions: all from one joint fit
                flags = ("bias" in comps, "latency" in comps)
                joint = joint_drift_fits(real_fit, cur_fit, fit_lay, name, flags)
                if len(joint) > 1:
                    option = joint
                    forced = [f.name for f in joint[1:]]
                    key, g_pair, _n2, with_runs = evaluate([*selected, *option])
            elif in_family and eligible and comps:  # bias named with a latency
                for comp_name in comps:
                    comp = FITTERS[comp_name](
                        real_fit, [window(s, 0.0, t_fit) for s in with_runs], fit_lay
                    )
                    if comp is not None:
                        option.append(comp)
                        forced.append(comp_name)
                        key, g_pair, _n2, with_runs = evaluate([*selected, *option])
            # A bias hides under any effect that widens the spread of means: when the
            # likelihood names one, try each candidate with a bias refitted on top and keep
            # the pair if it scores better (not otherwise: a walk's wandering mean is no bias).
            elif (
                eligible and name != "bias" and bias_flagged and "bias" in fam_best
                and "bias" in names
            ):  # fmt: skip
                comp = FITTERS["bias"](
                    real_fit, [window(s, 0.0, t_fit) for s in with_runs], fit_lay
                )
                if comp is not None:
                    key2, g_e2, _n2, _r2 = evaluate([*selected, fit, comp])
                    if key2 < key:
                        key, option = key2, [fit, comp]
                        g_pair = g_e2
            if round_ == 0:
                ci = closure_ci(real_test_b, base_test, eff_null, rng, opt.ci_resamples)
                scored[name] = Candidate(
                    fit,
                    fingerprint_score(name, fit_null.cells, zf),
                    closure_of(g_b, g_e, g_f),
                    ci,
                    g_e,
                )
            if lattice_fact and name != "quantization":
                eligible = False
            if eligible and (best is None or key < best[0]):
                named = [*forced, *([name] if in_family else [])]  # what the likelihood named
                best = (key, g_e if len(option) == 1 else g_pair, option, named)
        if best is None:
            break
        # A further effect must remove a real part of what is LEFT of the gap (a first effect
        # with a huge signature, e.g. a coarse lattice, leaves a second one a small share
        # of the total but most of the remainder).
        # The choice above is the best of several one-draw scores; whether it enters is
        # decided on fresh pooled draws (no winner's curse, less Monte Carlo noise).
        g_new = pooled_gap([*selected, *best[2]])[0]
        left = g_cur - g_f
        if round_ > 0 and (left < ADD_MIN_LEFT or g_cur - g_new < ADD_MIN_SHARE * left):
            break
        if round_ == 0 and closure_of(g_b, g_new, g_f) < ADD_MIN_GAIN:
            break
        selected.extend(best[2])
        named_by_likelihood.update(best[3])
        g_cur = g_new
        current = apply_fits(selected, runs, rng, lattice)

    # 4. leave-one-out: drop effects the others make redundant
    if len(selected) > 1:
        say("leave-one-out", 0.95)
        for f in list(selected):
            if f.name in named_by_likelihood:
                continue
            rest = [s for s in selected if s is not f]
            g_rest = pooled_gap(rest)[0]
            if closure_of(g_b, g_rest, g_f) >= closure_of(g_b, g_cur, g_f) - ADD_MIN_GAIN / 2:
                selected = rest
                g_cur = g_rest
    # 5. parameters: every reported effect is refitted on the WHOLE log (more data; exact
    # likelihood for gauss_markov and random_walk), a selected one on top of the baseline plus
    # the other selected effects. The closures stay those of the fit-part fits on the held-out
    # part, so they remain honest out-of-sample figures.
    say("refitting parameters on the whole log", 0.97)
    closure_fits = list(selected)
    selected = _refit_whole(selected, real, runs, layout, rng, lattice)
    for name, c in scored.items():
        if name not in {f.name for f in selected}:
            whole = FITTERS[name](real, runs, layout)
            if whole is not None:
                c.fit = whole
    if scored:
        notes.append(
            "parameters (+- standard errors) are fitted on the whole log (exact Kalman "
            "likelihood for gauss_markov / random_walk on top of a noise model of the "
            "baseline runs); each closure is that of the fit on the first "
            f"{opt.fit_fraction:.0%} of the log, scored on the held-out last "
            f"{1 - opt.fit_fraction - opt.guard_fraction:.0%} after a guard gap"
        )
    if closure_fits != selected:
        diag.notes.append(
            "fit-part parameters used for the closure: "
            + "; ".join(f"{f.name} {f.params}" for f in closure_fits)
        )
    sel_names = [f.name for f in selected]
    total = closure_of(g_b, g_cur, g_f)
    for f in selected:  # selected later without a first-round fit: report the set's closure
        if f.name not in scored:
            scored[f.name] = Candidate(f, 0.0, total, (total, total), g_cur)
    order = sorted(scored.values(), key=lambda c: (c.fit.name not in sel_names, -c.closure))
    for c in order:  # the selected fits replace the first-round ones (refitted on the residual)
        if c.fit.name in sel_names:
            c.fit = selected[sel_names.index(c.fit.name)]
    diag.candidates = sorted(
        order,
        key=lambda c: (
            c.fit.name not in sel_names,
            sel_names.index(c.fit.name) if c.fit.name in sel_names else 0,
            -c.closure,
        ),
    )
    diag.selected = selected
    diag.g_with = g_cur
    if closure_fits:
        # The selection's closure is scored again on FINAL_DRAWS fresh draws of its effect
        # ensemble, pooled: the G it was chosen on is the best of several noisy options (a
        # winner's curse of a few hundredths of closure on a marginal log), and one draw of
        # the effects' randomness is itself noisy.
        say("scoring the selection on fresh draws", 0.98)
        diag.g_with, final_null = pooled_gap(closure_fits)
        diag.closure_ci = closure_ci(real_test_b, base_test, final_null, rng, opt.ci_resamples)
    diag.closure = closure_of(g_b, diag.g_with, g_f)
    if not math.isfinite(diag.closure):
        diag.closure = 0.0
    say("done", 1.0)
    return diag


def report_dict(d: Diagnosis) -> dict[str, Any]:
    """The report.json content (keys fixed by the issue)."""
    top = d.selected[0].name if d.explained else None
    return {
        "gap": {
            "baseline": round(d.g_baseline, 4),
            "floor": round(d.g_floor, 4),
            "with_effects": round(d.g_with, 4),
        },
        "where": d.where,
        "effects": [
            {
                "name": c.fit.name,
                "params": c.fit.params,
                "closure": round(c.closure, 3),
                "closure_ci": [round(c.closure_ci[0], 3), round(c.closure_ci[1], 3)],
            }
            for c in d.candidates
        ],
        "verdict": {"effect": top, "explained": bool(d.explained) if d.significant else True},
    }


def verdict_text(d: Diagnosis) -> str:
    """One line for people."""
    if not d.significant:
        return "no significant gap"
    ci = f", 90 % interval {d.closure_ci[0]:.2f}-{d.closure_ci[1]:.2f}"
    if d.explained:
        names = " + ".join(f.name for f in d.selected)
        return f"gap explained by {names} (held-out closure {d.closure:.2f}{ci})"
    if d.selected:
        names = " + ".join(f.name for f in d.selected)
        return (
            f"gap not explained by any known effect (best: {names}, held-out closure "
            f"{d.closure:.2f}{ci}; {EXPLAINED_CLOSURE:g} needed)"
        )
    return "gap not explained by any known effect"
