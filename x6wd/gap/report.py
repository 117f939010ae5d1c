"""Report writers: report.md (people), report.json (programs), effects.toml (a simulator
config fragment of ``[[effects]]`` tables), and PNG figures."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from sim_backend.effects import metres_per_degree, truth_track_m
from x6wd.gap.compass import (
    CompassDiagnosis,
    compass_report_dict,
    compass_verdict_text,
    heading_error_deg,
    regression,
)
from x6wd.gap.diagnose import Diagnosis, report_dict, verdict_text
from x6wd.gap.stats import acf, allan_var, octave_taus, regular

FIGURES = ("scatter.png", "cdf.png", "allan.png", "acf.png", "time.png", "map.png")


def _toml_value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        return repr(v) if math.isfinite(v) else "0.0"
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    return json.dumps(str(v))


ZONE_POINTS = ("x1_m", "y1_m", "x2_m", "y2_m")


def effects_toml(
    d: Diagnosis,
    compass: CompassDiagnosis | None = None,
    origin_deg: tuple[float, float] | None = None,
) -> str:
    """The selected effects (GPS, then compass layers) as ``[[effects]]`` tables (comment-only
    text when none). A multipath zone's wall is fitted in metres from the log's first true
    position; with ``origin_deg`` (the scenario's origin, lat/lon deg) it is moved into that
    scenario's local frame, where the simulator evaluates zones."""
    lines = [
        f"# x6wd gap: fitted effects ({verdict_text(d)})",
        '# merge into a scenario: include = ["effects.toml"]',
    ]
    if compass is not None:
        lines.insert(1, f"# {compass_verdict_text(compass)}")
    lat0, lon0 = d.real.origin_lat_deg, d.real.origin_lon_deg
    shift = (0.0, 0.0)
    if origin_deg is not None:
        e_per, n_per = metres_per_degree(origin_deg[0])
        shift = ((lon0 - origin_deg[1]) * e_per, (lat0 - origin_deg[0]) * n_per)
    for f in [*d.selected, *(compass.selected if compass is not None else [])]:
        params = f.effect.to_params()
        lines.append("")
        if f.name == "multipath_zone":
            ref = origin_deg if origin_deg is not None else (lat0, lon0)
            lines.append(
                f"# wall in metres east/north of {ref[0]:.7f}, {ref[1]:.7f}"
                + (" (the scenario's origin)" if origin_deg else " (the log's first true position)")
            )
            for k in ZONE_POINTS:
                params[k] = round(params[k] + shift[0 if k[0] == "x" else 1], 3)
        lines.append("[[effects]]")
        for k, v in params.items():
            lines.append(f"{k} = {_toml_value(v)}")
    return "\n".join(lines) + "\n"


def merged_report(d: Diagnosis, compass: CompassDiagnosis | None) -> dict[str, Any]:
    """report.json: the GPS half, with the compass half merged in when it ran.

    ``where``: both lists, by decreasing |z|. ``effects``: the selected effects of both halves
    first, then the others, each group by decreasing held-out closure. ``gap`` keeps the GPS
    figures and gains ``heading`` {baseline, floor, with_effects}. ``verdict.effect``: the
    explained selection's first effect with the larger closure of the two halves;
    ``verdict.explained``: no significant gap is left unexplained in either half."""
    rep = report_dict(d)
    if compass is None:
        return rep
    crep = compass_report_dict(compass)
    rep["where"] = sorted([*rep["where"], *crep["where"]], key=lambda w: -abs(w["z"]))
    chosen = {f.name for f in d.selected} | {f.name for f in compass.selected}
    rep["effects"] = sorted(
        [*rep["effects"], *crep["effects"]],
        key=lambda e: (e["name"] not in chosen, -e["closure"]),
    )
    rep["gap"]["heading"] = crep["gap"]
    found = [(h.closure, h.selected[0].name) for h in (d, compass) if h.explained]
    rep["verdict"] = {
        "effect": max(found)[1] if found else None,
        "explained": all(h.explained or not h.significant for h in (d, compass)),
    }
    return rep


def write_report(
    d: Diagnosis,
    out_dir: str | Path,
    real_name: str = "real",
    figures: bool = True,
    compass: CompassDiagnosis | None = None,
    origin_deg: tuple[float, float] | None = None,
) -> dict[str, Any]:
    """Write every output into ``out_dir`` (created); returns the report.json content.
    ``compass``: the compass half (merged into report.json, a section of report.md, its
    layers in effects.toml and the figure compass.png); ``origin_deg``: the scenario's origin
    (lat, lon deg), the frame of effects.toml's walls (see :func:`effects_toml`)."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    rep = merged_report(d, compass)
    (out / "report.json").write_text(json.dumps(rep, indent=2) + "\n")
    (out / "effects.toml").write_text(effects_toml(d, compass, origin_deg))
    if figures:
        write_figures(d, out)
        if compass is not None:
            compass_figure(compass, out)
    text = markdown(d, report_dict(d), real_name, figures)
    if compass is not None:
        text += compass_markdown(compass, figures)
    (out / "report.md").write_text(text)
    return rep


def compass_markdown(c: CompassDiagnosis, figures: bool) -> str:
    """The compass section of report.md."""
    L = c.layout
    s = [
        "",
        "## Compass (heading)",
        "",
        f"**{compass_verdict_text(c)}.**",
        "",
        f"- {len(c.real)} samples over {L.duration_s:.0f} s ({L.dt_s:g} s steps); baseline "
        f"{len(c.baseline)} runs{' (block bootstrap)' if c.bootstrap else ''}; {len(c.cells)} "
        f"statistics; threshold |z| > {c.threshold:.2f}; field magnitude "
        f"{'used' if L.has_field else 'not available'}",
        f"- gap G on the held-out part (t >= {c.split_s[1]:.0f} s): baseline {c.g_baseline:.2f}, "
        f"floor {c.g_floor:.2f}, with the selected layers {c.g_with:.2f}; closure {c.closure:.2f}",
    ]
    s += [f"- note: {n}" for n in c.notes]
    s += ["", "| statistic | scale | z |", "|---|---|---|"]
    s += [f"| {w['statistic']} | {w['scale']} | {w['z']:+.1f} |" for w in c.where]
    if not c.where:
        s = [*s[:-2], "No heading statistic differs beyond the sim-vs-sim spread."]
    if c.candidates:
        s += ["", "| effect | parameters | held-out closure | 90 % interval |", "|---|---|---|---|"]
        for k in c.candidates:
            params = ", ".join(
                f"{p}={v}" + (f" ± {k.fit.se[p]:.2g}" if math.isfinite(k.fit.se.get(p, math.nan))
                              else "")
                for p, v in k.fit.params.items()
            )  # fmt: skip
            s.append(
                f"| {k.fit.name} | {params} | {k.closure:.2f} | "
                f"[{k.closure_ci[0]:.2f}, {k.closure_ci[1]:.2f}] |"
            )
    if figures:
        s += ["", "![compass.png](compass.png)"]
    s += [
        "",
        "Once-per-turn harmonics: hard iron (or tilt, told apart by the tilt gain and the field",
        "magnitude); twice per turn: soft iron; mean: declination; lag: error against turn rate.",
    ]
    return "\n".join(s) + "\n"


def compass_figure(c: CompassDiagnosis, out: Path) -> None:
    """compass.png: heading error vs true heading, real vs a sim run, with each one's fitted
    mean + harmonics curve (the part of the error that depends on heading alone)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 4.5))
    grid = np.linspace(0.0, 360.0, 361)
    g = np.radians(grid)
    basis = np.column_stack([np.ones_like(g), np.cos(g), np.sin(g), np.cos(2 * g), np.sin(2 * g)])
    rng = np.random.default_rng(0)
    for s, colour, label in ((c.baseline[0], "0.6", "sim"), (c.real, "C3", "real")):
        assert s.true_heading_deg is not None
        err = heading_error_deg(s)
        pick = rng.choice(err.size, size=min(err.size, 3000), replace=False)
        ax.plot(np.asarray(s.true_heading_deg)[pick], err[pick], ".", ms=1.5, color=colour,
                alpha=0.4)  # fmt: skip
        coef, _ = regression(s, c.layout)
        ax.plot(grid, basis @ coef[:5], color=colour, lw=2, label=f"{label}: fitted harmonics")
    ax.set(
        xlabel="true heading (deg)",
        ylabel="heading error (deg)",
        title="compass: heading error vs heading",
        xlim=(0, 360),
    )
    ax.legend()
    fig.savefig(out / "compass.png", dpi=90)
    plt.close(fig)


def markdown(d: Diagnosis, rep: dict[str, Any], real_name: str, figures: bool) -> str:
    """report.md text."""
    L = d.layout
    s = [
        f"# Sim-to-real gap: {real_name}",
        "",
        f"**Verdict: {verdict_text(d)}.**",
        "",
        f"- log: {L.duration_s:.0f} s at {L.dt_s:g} s steps, {'moving' if L.moving else 'static'}, "
        f"fix availability {np.mean(d.real.valid):.1%}",
        f"- baseline: {len(d.baseline)} runs{' (block bootstrap)' if d.bootstrap else ''}; "
        f"{len(d.cells)} statistics; family-wise threshold |z| > {d.threshold:.2f} (alpha 5 %)",
        f"- fit on t < {d.split_s[0]:.0f} s, guard gap, held-out test on t >= {d.split_s[1]:.0f} s",
        f"- gap G (mean clipped z^2 on the held-out part): baseline {d.g_baseline:.2f}, floor "
        f"{d.g_floor:.2f} (sim vs sim), with the selected effects {d.g_with:.2f}; "
        f"closure {d.closure:.2f}"
        + (
            f" (90 % interval {d.closure_ci[0]:.2f} to {d.closure_ci[1]:.2f})"
            if d.selected
            else " (no effect selected)"
        ),
    ]
    s += [f"- note: {n}" for n in d.notes]
    s += ["", "## Where", ""]
    if d.where:
        s += ["| statistic | axis | scale | period | place | z |", "|---|---|---|---|---|---|"]
        for w in d.where[:40]:
            s.append(
                f"| {w['statistic']} | {w['axis']} | {w['scale']} | {w['period']} "
                f"| {w['place']} | {w['z']:+.1f} |"
            )
        if len(d.where) > 40:
            s.append(f"\n({len(d.where) - 40} more cells in report.json)")
    else:
        s.append(
            "No statistic differs from the simulator beyond what seed-to-seed variation explains."
        )
    s += ["", "## Which effect", ""]
    if rep["effects"]:
        s += [
            "| rank | effect | parameters | held-out closure | 90 % interval | selected |",
            "|---|---|---|---|---|---|",
        ]
        sel = {f.name for f in d.selected}
        for i, c in enumerate(d.candidates, 1):
            se = c.fit.se
            params = ", ".join(
                f"{k}={v}" + (f" ± {se[k]:.2g}" if se.get(k) and math.isfinite(se[k]) else "")
                for k, v in c.fit.params.items()
            )
            s.append(
                f"| {i} | {c.fit.name} | {params} | {c.closure:.2f} | "
                f"[{c.closure_ci[0]:.2f}, {c.closure_ci[1]:.2f}] | "
                f"{'yes' if c.fit.name in sel else ''} |"
            )
        s += ["", "The selected effects are in `effects.toml` (a scenario fragment)."]
    else:
        s.append(
            "No candidate was fitted (no significant gap)."
            if not d.where
            else "No candidate fitted."
        )
    if figures:
        s += ["", "## Figures", ""]
        s += [f"![{f}]({f})" for f in FIGURES if (f != "map.png" or L.moving)]
    s += [
        "",
        "## How to read this",
        "",
        "z scores are against the simulator's own seed-to-seed spread (never iid tests);",
        "closure 1 means the held-out gap fell to the sim-vs-sim floor, 0 means no change.",
        "See docs/gap.md.",
    ]
    return "\n".join(s) + "\n"


def write_figures(d: Diagnosis, out: Path) -> None:
    """PNG figures: scatter, CDF, Allan deviation with the null band, ACF, time, map."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    real = d.real
    sims = d.baseline[: min(5, len(d.baseline))]
    v = np.asarray(real.valid, dtype=bool)

    fig, ax = plt.subplots(figsize=(5, 5))
    for s in sims[:1]:
        sv = np.asarray(s.valid, dtype=bool)
        ax.plot(s.east_m[sv], s.north_m[sv], ".", ms=2, alpha=0.4, label="sim")
    ax.plot(real.east_m[v], real.north_m[v], ".", ms=2, alpha=0.6, label="real")
    ax.set(
        xlabel="east error (m)", ylabel="north error (m)", title="horizontal error", aspect="equal"
    )
    ax.legend()
    fig.savefig(out / "scatter.png", dpi=90)
    plt.close(fig)

    fig, ax = plt.subplots(figsize=(6, 4))
    for i, s in enumerate(d.baseline):
        sv = np.asarray(s.valid, dtype=bool)
        h = np.sort(np.hypot(s.east_m[sv], s.north_m[sv]))
        ax.plot(
            h, np.linspace(0, 1, h.size), color="0.7", lw=0.8, label="sim runs" if i == 0 else None
        )
    h = np.sort(np.hypot(real.east_m[v], real.north_m[v]))
    ax.plot(h, np.linspace(0, 1, h.size), color="C3", lw=2, label="real")
    ax.set(xlabel="horizontal error (m)", ylabel="CDF", title="error CDF, real vs sim runs")
    ax.legend()
    fig.savefig(out / "cdf.png", dpi=90)
    plt.close(fig)

    ms = octave_taus(d.layout)
    taus = np.array(ms) * d.layout.dt_s
    fig, axs = plt.subplots(1, 2, figsize=(10, 4))
    for k, ax in enumerate(axs):
        sims_ad = np.array(
            [np.sqrt(allan_var(regular(s, d.layout.dt_s)[k], ms)) for s in d.baseline]
        )
        lo, hi = np.nanquantile(sims_ad, [0.025, 0.975], axis=0)
        ax.fill_between(taus, lo, hi, color="0.8", label="sim null 95 %")
        ax.loglog(
            taus, np.sqrt(allan_var(regular(real, d.layout.dt_s)[k], ms)), "C3o-", label="real"
        )
        ax.set(
            xlabel="averaging time (s)", ylabel="Allan deviation (m)", title=["east", "north"][k]
        )
        ax.legend()
    fig.tight_layout()
    fig.savefig(out / "allan.png", dpi=90)
    plt.close(fig)

    lags = list(range(1, max(2, min(600, int(d.layout.duration_s / d.layout.dt_s / 5)))))
    fig, ax = plt.subplots(figsize=(6, 4))
    sims_acf = np.array([acf(regular(s, d.layout.dt_s)[0], lags) for s in d.baseline])
    lo, hi = np.quantile(sims_acf, [0.025, 0.975], axis=0)
    lag_s = np.array(lags) * d.layout.dt_s
    ax.fill_between(lag_s, lo, hi, color="0.8", label="sim null 95 %")
    ax.plot(lag_s, acf(regular(real, d.layout.dt_s)[0], lags), "C3", label="real")
    ax.set(xlabel="lag (s)", ylabel="autocorrelation (east)", title="autocorrelation")
    ax.legend()
    fig.savefig(out / "acf.png", dpi=90)
    plt.close(fig)

    fig, ax = plt.subplots(figsize=(10, 4))
    t = np.asarray(real.t_s) - real.t_s[0]
    ax.plot(t[v], np.hypot(real.east_m, real.north_m)[v], "C3.", ms=2, label="real")
    for s in sims[:2]:
        sv = np.asarray(s.valid, dtype=bool)
        ts = np.asarray(s.t_s) - s.t_s[0]
        ax.plot(ts[sv], np.hypot(s.east_m, s.north_m)[sv], ".", ms=1, color="0.6")
    for w in d.where:
        if w["period"] != "all":
            a, b = (float(x) for x in w["period"][2:-1].split("-"))
            ax.axvspan(a, b, color="C1", alpha=0.15)
    ax.axvline(d.split_s[0], color="k", ls="--", lw=0.8)
    ax.axvline(d.split_s[1], color="k", ls="--", lw=0.8)
    ax.set(
        xlabel="time (s)",
        ylabel="horizontal error (m)",
        title="error over time (shaded: flagged periods; dashed: fit | guard | test)",
    )
    ax.legend()
    fig.savefig(out / "time.png", dpi=90)
    plt.close(fig)

    if d.layout.moving:
        te, tn = truth_track_m(real)
        fig, ax = plt.subplots(figsize=(6, 6))
        herr = np.hypot(real.east_m, real.north_m)
        sc = ax.scatter(te[v], tn[v], c=herr[v], s=4, cmap="viridis")
        fig.colorbar(sc, label="horizontal error (m)")
        flagged = {w["place"] for w in d.where if w["place"] != "all"}
        ax.axvline(d.layout.place_e_m, color="0.5", lw=0.5)
        ax.axhline(d.layout.place_n_m, color="0.5", lw=0.5)
        for f in d.selected:
            if f.name == "multipath_zone":
                z = f.effect
                dist, _ux, _uy = z.distance_to_wall_m(te, tn)
                inside = v & (dist <= z.distance_m)
                ax.plot(te[inside], tn[inside], "o", mfc="none", mec="C3", ms=5, alpha=0.4,
                        label="fitted multipath zone")  # fmt: skip
                ax.plot([z.x1_m, z.x2_m], [z.y1_m, z.y2_m], "C3-", lw=3, label="fitted wall")
                ax.legend(loc="best")
        ax.set(
            xlabel="east (m)",
            ylabel="north (m)",
            aspect="equal",
            title=f"error over the map ({len(flagged)} of 4 quadrants flagged)",
        )
        fig.savefig(out / "map.png", dpi=90)
        plt.close(fig)
