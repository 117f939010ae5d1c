"""Report writers: report.md (people), report.json (programs), effects.toml (a simulator
config fragment of ``[[effects]]`` tables), calibrated.toml (the same with the level
calibration's layers after the selected effects), validation.json (seed 000's validation
both ways), and PNG figures."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from sim_backend.effects import Quantization, metres_per_degree, truth_track_m
from x6wd.core.outdir import output_file, write_output_file
from x6wd.gap.compass import (
    CompassDiagnosis,
    compass_report_dict,
    compass_verdict_text,
    heading_error_deg,
    regression,
)
from x6wd.gap.diagnose import Diagnosis, headline, report_dict, verdict_text
from x6wd.gap.fitted import Fit
from x6wd.gap.level import Calibration, closeness_text
from x6wd.gap.null import NullModel
from x6wd.gap.pipeline import EXPLAINED_CLOSURE, Outcome
from x6wd.gap.stats import acf, allan_var, octave_taus, regular
from x6wd.gap.validate import Validation, direction_text, own_mean

FIGURES = ("scatter.png", "cdf.png", "allan.png", "acf.png", "time.png", "map.png")


def is_borderline(head: dict[str, Any]) -> bool:
    """Whether the verdict rests on a closure (``head``: :func:`~x6wd.gap.diagnose.headline`)
    whose 90 % interval holds :data:`EXPLAINED_CLOSURE` with room on both sides: another
    --seed or --seeds may land the closure on the other side of it and turn "explained" into
    "not explained" (an audit's borderline log: 0.51 with one seed, 0.48 with another)."""
    ci = head["closure_ci"]
    return ci is not None and ci[0] < EXPLAINED_CLOSURE < ci[1]


def verdict_line(diagnosis: Diagnosis, other_place_km: float | None = None) -> str:
    """The GPS verdict as the report and the CLI headline it: :func:`verdict_text`, after
    what makes it weaker than it reads. ``other_place_km``: the farthest --sim log's distance
    (km) from the real log when one simulates another place (None: same place or unknown).
    Wording only: the statistics are those of :func:`verdict_text`."""
    text = verdict_text(diagnosis)
    head = headline(diagnosis)
    if is_borderline(head):
        low, high = head["closure_ci"]
        text = (
            f"borderline: the closure's 90 % interval {low:.2f}-{high:.2f} holds the"
            f" {EXPLAINED_CLOSURE:g} that 'explained' needs, so another --seed or --seeds may"
            f" turn this verdict: {text}"
        )
    if other_place_km is not None:
        text = (
            f"not meaningful: the --sim logs simulate another place (up to {other_place_km:.1f}"
            " km from the real log: another sky, other walls), so this compares different"
            f" places: {text}"
        )
    return text


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


_OUR_HEADER = "# x6wd gap:"  # the first words of every TOML file this tool writes
# the prefix of a candidate's lines in effects.toml (not "# ": a zone's own comment stays one)
TRY_PREFIX = "#~ "


def remove_earlier_calibration(out: Path) -> bool:
    """Remove an earlier run's ``calibrated.toml`` from ``out`` (a log without a significant
    gap gets none, and a left one would read as this log's); True if one was removed. A file
    of that name this tool did not write (its first line is not ours) is the user's: kept."""
    stale = out / "calibrated.toml"
    if not stale.is_file():
        return False
    with open(stale, encoding="utf-8", errors="replace") as f:
        ours = f.read(len(_OUR_HEADER)) == _OUR_HEADER
    if ours:
        stale.unlink()
    return ours


def effects_toml(
    diagnosis: Diagnosis,
    compass: CompassDiagnosis | None = None,
    origin_deg: tuple[float, float] | None = None,
    calibrated: bool = False,
    verdict: str | None = None,
) -> str:
    """The written effects (:attr:`~x6wd.gap.pipeline.Outcome.written`; GPS, then compass
    layers) as ``[[effects]]`` tables (comment-only text when none; a selection that does not
    explain its half's gap follows commented out); ``calibrated``: with the level
    calibration's layers after the GPS ones (calibrated.toml). A multipath zone's wall is
    fitted in metres from the log's first true position; with ``origin_deg`` (the scenario's
    origin, lat/lon deg) it is moved into that scenario's local frame, where the simulator
    evaluates zones. ``verdict``: the header's
    verdict (default :func:`verdict_text`)."""
    verdict = verdict_text(diagnosis) if verdict is None else verdict
    gps = diagnosis.written
    if calibrated and diagnosis.calibration is not None:
        c = diagnosis.calibration
        gps = [*gps, *c.layers]
        lines = [
            f"{_OUR_HEADER} fitted effects ({verdict}), then the level calibration",
            "# (in sample: fitted to seed 000's validation figures on this very log, see",
            '# report.md); use it INSTEAD of effects.toml: include = ["calibrated.toml"]',
        ]
        if not c.layers:
            lines.append(
                "# no level layer is kept: this file holds the selected effects only"
                if gps
                else "# no level layer is kept and no effect explains the gap: nothing to add"
            )
        lines += [f"# level layer left out: {name}: {why}" for name, why in c.left_out]
    else:
        lines = [
            f"{_OUR_HEADER} fitted effects ({verdict})",
            '# merge into a scenario: include = ["effects.toml"]',
        ]
    if compass is not None:
        lines.insert(1, f"# {compass_verdict_text(compass)}")
    origin_lat_deg, origin_lon_deg = diagnosis.real.origin_lat_deg, diagnosis.real.origin_lon_deg
    shift_m = (0.0, 0.0)
    if origin_deg is not None:
        m_per_deg_lon, m_per_deg_lat = metres_per_degree(origin_deg[0])
        shift_m = (
            ((origin_lon_deg - origin_deg[1] + 180.0) % 360.0 - 180.0) * m_per_deg_lon,  # ±180
            (origin_lat_deg - origin_deg[0]) * m_per_deg_lat,
        )
    halves: list[tuple[str, Outcome[Any, Any] | None]] = [("GPS", diagnosis), ("compass", compass)]
    candidates: list[Fit] = []
    for sensor, half in halves:
        if half is None or half.written or not half.selected:
            continue
        names = " + ".join(f.name for f in half.selected)
        lines.append(
            f"# not written: {sensor} {names}, the best candidate of a gap it does not explain"
            f" (held-out closure {half.closure:.2f}, {EXPLAINED_CLOSURE:g} needed)"
        )
        if calibrated:  # this file's level was fitted without it: no mix to try here
            lines.append("# (effects.toml holds it commented out; this file's level was fitted"
                         " without it)")  # fmt: skip
        else:
            candidates += half.selected
    if candidates:
        lines.append(f"# report.md validates it; to try it anyway, remove the '{TRY_PREFIX}' of"
                     " its lines below")  # fmt: skip
    written = [*gps, *(compass.written if compass is not None else [])]
    for fit, live in [*((f, True) for f in written), *((f, False) for f in candidates)]:
        start = len(lines)
        params = fit.effect.to_params()
        lines.append("")
        if fit.name == "multipath_zone":
            frame_deg = origin_deg if origin_deg is not None else (origin_lat_deg, origin_lon_deg)
            lines.append(
                f"# wall in metres east/north of {frame_deg[0]:.7f}, {frame_deg[1]:.7f}"
                + (" (the scenario's origin)" if origin_deg else " (the log's first true position)")
            )
            for key in ZONE_POINTS:
                params[key] = round(params[key] + shift_m[0 if key[0] == "x" else 1], 3)
        lines.append("[[effects]]")
        for key, value in params.items():
            lines.append(f"{key} = {_toml_value(value)}")
        if not live:
            lines[start + 1 :] = [line if line.startswith("#") else f"{TRY_PREFIX}{line}"
                                  for line in lines[start + 1 :]]  # fmt: skip
    return "\n".join(lines) + "\n"


def merged_report(diagnosis: Diagnosis, compass: CompassDiagnosis | None) -> dict[str, Any]:
    """report.json: the GPS half, with the compass half merged in when it ran.

    ``where``: both lists, by decreasing |z|. ``effects``: the selected effects of both halves
    first, then the others, each group by decreasing held-out closure. ``gap`` keeps the GPS
    figures and gains ``heading`` {baseline, floor, with_effects}. ``verdict.effect``: the
    explained selection's first effect with the larger closure of the two halves;
    ``verdict.explained``: no significant gap is left unexplained in either half."""
    report = report_dict(diagnosis)
    if compass is None:
        report["verdict"].update(headline(diagnosis))
        return report
    compass_report = compass_report_dict(compass)
    report["where"] = sorted(
        [*report["where"], *compass_report["where"]], key=lambda w: -abs(w["z"])
    )
    chosen = {fit.name for fit in diagnosis.selected} | {fit.name for fit in compass.selected}
    report["effects"] = sorted(
        [*report["effects"], *compass_report["effects"]],
        key=lambda e: (e["name"] not in chosen, -e["closure"]),
    )
    report["gap"]["heading"] = compass_report["gap"]
    # the explained half with the larger closure names the verdict's effect (its first
    # selected); a half that selected nothing is never read for a name (before round 12 an
    # explained GPS half beside a compass half without a selection raised IndexError)
    both: list[Outcome[Any, Any]] = [diagnosis, compass]
    found = [
        (float(half.closure), half.selected[0].name, index)
        for index, half in enumerate(both)
        if half.explained and half.selected
    ]
    best = max(found) if found else None
    report["verdict"] = {
        "effect": best[1] if best is not None else None,
        "explained": all(half.explained or not half.significant for half in (diagnosis, compass)),
    }
    halves = {"gps": headline(diagnosis), "heading": headline(compass)}
    # the headline's figures are those of the half verdict.effect names (the GPS half's when
    # neither is explained); the status sums both halves
    named = compass if best is not None and best[2] == 1 else diagnosis
    statuses = {h["status"] for h in halves.values()} - {"no_gap"}
    status = (
        "no_gap" if not statuses else statuses.pop() if len(statuses) == 1 else "partly_explained"
    )
    report["verdict"].update({**headline(named), "status": status, "halves": halves})
    return report


def _nearest_cells(diagnosis: Diagnosis, n: int = 3) -> list[str]:
    """With no cell beyond its limit, the ``n`` nearest (|z| / limit), and, when one of them
    has a limit far above the family's least (a per-log statistic's t limit with a few
    logs' degrees of freedom), what would lower it: a gap a few logs cannot decide is not
    the same as no gap (an outside audit: a 25 m bias at z 11 against 21.5 read as none)."""
    z = np.asarray(diagnosis.z, dtype=float)
    if z.size == 0 or diagnosis.null is None:
        return []
    limits = np.asarray(diagnosis.null.limits(), dtype=float)
    ratio = np.where(np.isfinite(z), np.abs(z) / limits, 0.0)
    top = [int(i) for i in np.argsort(-ratio)[:n] if ratio[i] > 0]
    if not top:
        return []
    parts = []
    for i in top:
        c = diagnosis.cells[i]
        where = ", ".join(x for x in (c.scale, c.period, c.place) if x != "all")
        parts.append(f"{c.statistic} {c.axis}{f' ({where})' if where else ''}: z {z[i]:+.1f}"
                     f" against {limits[i]:.1f}")  # fmt: skip
    out = ["", f"Nearest to their limits: {'; '.join(parts)}."]
    if any(limits[i] > 2.0 * float(np.min(limits)) and ratio[i] > 0.25 for i in top):
        out.append(
            "A limit far above the others is a per-log statistic's (a whole-log mean, spread"
            " or autocorrelation: each log holds one draw of the slow error), which a few"
            " --sim logs pin poorly; more --sim logs (or --scenario with its 20 seeds) lower it."
        )
    return out


def write_report(
    diagnosis: Diagnosis,
    out_dir: str | Path,
    real_name: str = "real",
    figures: bool = True,
    compass: CompassDiagnosis | None = None,
    origin_deg: tuple[float, float] | None = None,
    other_place_km: float | None = None,
) -> dict[str, Any]:
    """Write every output into ``out_dir`` (created); returns the report.json content (its
    keys are fixed: seed 000's validation goes to validation.json).
    ``compass``: the compass half (merged into report.json, a section of report.md, its
    layers in effects.toml and the figure compass.png); ``origin_deg``: the scenario's origin
    (lat, lon deg), the frame of effects.toml's walls (see :func:`effects_toml`);
    ``other_place_km``: the farthest --sim log's distance (km) when they simulate another
    place (:func:`verdict_line`). report.json's ``verdict.borderline`` (the GPS closure's
    interval holds the 'explained' threshold) and ``verdict.other_place_km`` (None when the
    same place) say what the verdict's wording says."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    report = merged_report(diagnosis, compass)
    report["verdict"]["borderline"] = is_borderline(headline(diagnosis))
    report["verdict"]["other_place_km"] = (
        None if other_place_km is None else round(other_place_km, 1)
    )
    verdict = verdict_line(diagnosis, other_place_km)
    # a full disk or a read-only file: one line naming the file, exit 2 (never a traceback)
    write_output_file(out / "report.json", json.dumps(report, indent=2) + "\n")
    write_output_file(
        out / "effects.toml", effects_toml(diagnosis, compass, origin_deg, verdict=verdict)
    )
    if diagnosis.calibration is not None:
        write_output_file(
            out / "calibrated.toml",
            effects_toml(diagnosis, compass, origin_deg, calibrated=True, verdict=verdict),
        )
        validation = validation_dict(diagnosis.calibration)
        # a selection that does not explain the gap: its own validation ("selected" is then
        # the baseline runs', which is what the files hold)
        candidate = diagnosis.candidate_validation
        validation["candidate"] = None if candidate is None else _validation_json(candidate)
        write_output_file(out / "validation.json", json.dumps(validation, indent=2) + "\n")
    elif diagnosis.validation is not None:
        remove_earlier_calibration(out)
        write_output_file(
            out / "validation.json",
            json.dumps(uncalibrated_dict(diagnosis.validation), indent=2) + "\n",
        )
    if figures:
        write_figures(diagnosis, out)
        if compass is not None:
            compass_figure(compass, out)
    text = markdown(diagnosis, report_dict(diagnosis), real_name, figures, verdict=verdict)
    if compass is not None:
        text += compass_markdown(compass, figures)
    write_output_file(out / "report.md", text)
    return report


def compass_markdown(compass: CompassDiagnosis, figures: bool) -> str:
    """The compass section of report.md."""
    layout = compass.layout
    lines = [
        "",
        "## Compass (heading)",
        "",
        f"**{compass_verdict_text(compass)}.**",
        "",
        f"- {len(compass.real)} samples over {layout.duration_s:.0f} s ({layout.dt_s:g} s "
        f"steps); baseline {compass.baseline_text}; {len(compass.cells)} "
        f"statistics; threshold |z| > {compass.threshold:.2f}; field magnitude "
        f"{'used' if layout.has_field else 'not available'}",
        f"- gap G on the held-out part ({split_text(compass.split_s, test_only=True)}): baseline "
        f"{compass.g_baseline:.2f}, floor {compass.g_floor:.2f}, with the selected layers "
        f"{compass.g_with:.2f}; closure {compass.closure:.2f}",
    ]
    lines += [f"- note: {note}" for note in compass.notes]
    lines += ["", "| statistic | scale | z |", "|---|---|---|"]
    lines += [
        f"| {cell['statistic']} | {cell['scale']} | {cell['z']:+.1f} |" for cell in compass.where
    ]
    if not compass.where:
        lines = [*lines[:-2], "No heading statistic differs beyond the sim-vs-sim spread."]
    if compass.candidates:
        lines += [
            "",
            "| effect | parameters | held-out closure | 90 % interval |",
            "|---|---|---|---|",
        ]
        for cand in compass.candidates:
            se = cand.fit.se
            params = ", ".join(
                f"{param}={value}"
                + (f" ± {se[param]:.2g}" if math.isfinite(se.get(param, math.nan)) else "")
                for param, value in cand.fit.params.items()
            )
            lines.append(
                f"| {cand.fit.name} | {params} | {cand.closure:.2f} | "
                f"[{cand.closure_ci[0]:.2f}, {cand.closure_ci[1]:.2f}] |"
            )
    if compass.selected and not compass.written:
        names = " + ".join(f.name for f in compass.selected)
        lines += ["", f"The selection ({names}) does not explain the gap: `effects.toml` holds"
                  " it commented out."]  # fmt: skip
    if figures:
        lines += ["", "![compass.png](compass.png)"]
    lines += [
        "",
        "Once-per-turn harmonics: hard iron (or tilt, told apart by the tilt gain and the field",
        "magnitude); twice per turn: soft iron; mean: declination; lag: error against turn rate.",
    ]
    return "\n".join(lines) + "\n"


def compass_figure(compass: CompassDiagnosis, out: Path) -> None:
    """compass.png: heading error vs true heading, real vs a sim run, with each one's fitted
    mean + harmonics curve (the part of the error that depends on heading alone)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 4.5))
    grid_deg = np.linspace(0.0, 360.0, 361)
    grid_rad = np.radians(grid_deg)
    basis = np.column_stack(
        [
            np.ones_like(grid_rad),
            np.cos(grid_rad),
            np.sin(grid_rad),
            np.cos(2 * grid_rad),
            np.sin(2 * grid_rad),
        ]
    )
    rng = np.random.default_rng(0)
    for series, colour, label in (
        (compass.baseline[0], "0.6", "sim"),
        (compass.real, "C3", "real"),
    ):
        assert series.true_heading_deg is not None
        error_deg = heading_error_deg(series)
        pick = rng.choice(error_deg.size, size=min(error_deg.size, 3000), replace=False)
        ax.plot(
            np.asarray(series.true_heading_deg)[pick], error_deg[pick], ".", ms=1.5,
            color=colour, alpha=0.4,
        )  # fmt: skip
        coef, _ = regression(series, compass.layout)
        ax.plot(grid_deg, basis @ coef[:5], color=colour, lw=2, label=f"{label}: fitted harmonics")
    ax.set(
        xlabel="true heading (deg)",
        ylabel="heading error (deg)",
        title="compass: heading error vs heading",
        xlim=(0, 360),
    )
    ax.legend()
    with output_file(out / "compass.png"):
        fig.savefig(out / "compass.png", dpi=90)
    plt.close(fig)


def _ci_text(head: dict[str, Any], sep: str, before: str, after: str) -> str:
    """The verdict's closure interval as text, or "" where none was computed."""
    ci = head["closure_ci"]
    return "" if ci is None else f"{before}{ci[0]:.2f}{sep}{ci[1]:.2f}{after}"


def markdown(
    diagnosis: Diagnosis,
    report: dict[str, Any],
    real_name: str,
    figures: bool,
    verdict: str | None = None,
) -> str:
    """report.md text; ``verdict``: its headline (default :func:`verdict_text`)."""
    layout = diagnosis.layout
    motion = "moving" if layout.moving else "static"
    head = report["verdict"] if "status" in report["verdict"] else headline(diagnosis)
    lines = [
        f"# Sim-to-real gap: {real_name}",
        "",
        f"**Verdict: {verdict_text(diagnosis) if verdict is None else verdict}.**",
        "",
        f"- log: {layout.duration_s:.0f} s at {layout.dt_s:g} s steps, {motion}, "
        f"fix availability {np.mean(diagnosis.real.valid):.1%}",
        f"- baseline: {diagnosis.baseline_text}; {len(diagnosis.cells)} statistics; "
        f"family-wise limits |z| > {_limits_text(diagnosis.null)} "
        f"(alpha {100 * diagnosis.alpha:g} %"
        + (
            f"; {diagnosis.null.apart} heavy-tailed statistic(s) at limits of their own)"
            if diagnosis.null.apart
            else ")"
        ),
        f"- {split_text(diagnosis.split_s)}",
        f"- gap G (mean of clipped z^2 plus the spread term 2 log(s/s0), docs/gap.md step 5, on"
        " the held-out part; below 0 where the effects' spread is narrower than the"
        " baseline's): baseline "
        f"{diagnosis.g_baseline:.2f}, floor {diagnosis.g_floor:.2f} (sim vs sim), with the "
        f"selected effects {diagnosis.g_with:.2f}; closure "
        + (
            f"{head['closure']:.2f} ({_ci_text(head, ' to ', '90 % interval ', '; ')}"
            "report.json's verdict.closure, verdict.closure_ci)"
            if head["closure"] is not None
            else f"{diagnosis.closure:.2f} (no effect selected)"
        ),
        f"- verdict status: {head['status']} (report.json's verdict.status; with a compass "
        "half, verdict.halves.gps.status)",
    ]
    lines += [f"- note: {note}" for note in diagnosis.notes]
    lines += [f"- note: {text}" for text in outlier_notes(diagnosis.null)]
    lines += ["", "## Where", ""]
    if diagnosis.where:
        lines += ["| statistic | axis | scale | period | place | z |", "|---|---|---|---|---|---|"]
        for cell in diagnosis.where[:40]:
            lines.append(
                f"| {cell['statistic']} | {cell['axis']} | {cell['scale']} | {cell['period']} "
                f"| {cell['place']} | {cell['z']:+.1f} |"
            )
        if len(diagnosis.where) > 40:
            lines.append(f"\n({len(diagnosis.where) - 40} more cells in report.json)")
    else:
        lines.append(
            "No statistic differs from the simulator beyond what seed-to-seed variation explains."
        )
        lines += _nearest_cells(diagnosis)
    lines += ["", "## Which way", ""]
    way = direction_text(diagnosis.direction)
    lines.append(
        f"Allan deviation by octave, real against the simulator's runs: {way}."
        if way
        else "No Allan deviation cell (the log is too short for one octave)."
    )
    lines += ["", "## Which effect", ""]
    if report["effects"]:
        lines += [
            "| rank | effect | parameters | held-out closure | 90 % interval | selected |",
            "|---|---|---|---|---|---|",
        ]
        selected = {figure.name for figure in diagnosis.selected}
        for rank, cand in enumerate(diagnosis.candidates, 1):
            se = cand.fit.se
            params = ", ".join(
                f"{key}={value}"
                + (f" ± {se[key]:.2g}" if se.get(key) and math.isfinite(se[key]) else "")
                for key, value in cand.fit.params.items()
            )
            name = cand.fit.name
            if isinstance(cand.fit.effect, Quantization) and cand.fit.effect.unit == "deg":
                name += f" ({cand.fit.effect.step_text})"  # not the NMEA minutes' rounding
            lines.append(
                f"| {rank} | {name} | {params} | {cand.closure:.2f} | "
                f"[{cand.closure_ci[0]:.2f}, {cand.closure_ci[1]:.2f}] | "
                f"{'yes' if cand.fit.name in selected else ''} |"
            )
        if diagnosis.written:
            lines += ["", "The selected effects are in `effects.toml` (a scenario fragment)."]
        elif diagnosis.selected:
            lines += [
                "",
                "The selection does not explain the gap: `effects.toml` holds it commented out"
                " and `calibrated.toml`'s level is fitted without it (the validation below"
                " says what it would do).",
            ]
        if head["closure"] is not None:
            lines += [
                "",
                f"Each row's closure is that effect's alone on the baseline, scored on the draw "
                "it was offered with in the first round (report.json's effects[].closure, "
                f"closure_ci). The verdict's, {head['closure']:.2f}"
                f"{_ci_text(head, '-', ' (', ')')}, is the selection's "
                f"({' + '.join(head['effects'])}) scored again on fresh pooled draws of its "
                "effects (report.json's verdict.closure, verdict.closure_ci).",
            ]
    else:
        lines.append(
            "No candidate was fitted (no significant gap)."
            if not diagnosis.where
            else "No candidate fitted."
        )
    if diagnosis.calibration is not None:
        lines += [
            "",
            *validation_markdown(
                diagnosis.calibration,
                [f.name for f in diagnosis.written],
                own_mean(diagnosis.real),
            ),
        ]
        if diagnosis.candidate_validation is not None:
            lines += ["", candidate_text(diagnosis)]
    elif diagnosis.validation is not None:
        lines += ["", *uncalibrated_markdown(diagnosis.validation, own_mean(diagnosis.real))]
    if figures:
        lines += ["", "## Figures", ""]
        lines += [
            f"![{figure}]({figure})" for figure in FIGURES if (figure != "map.png" or layout.moving)
        ]
    lines += [
        "",
        "## How to read this",
        "",
        "z scores are against the simulator's own seed-to-seed spread (never iid tests);",
        "closure 1 means the held-out gap fell to the sim-vs-sim floor, 0 means no change.",
        "See docs/gap.md.",
    ]
    return "\n".join(lines) + "\n"


def _params_text(fit: Any) -> str:
    return ", ".join(
        f"{key}={value:.4g}" if isinstance(value, float) else f"{key}={value}"
        for key, value in fit.params.items()
    )


def split_text(
    split_s: tuple[tuple[float, float], tuple[float, float]], test_only: bool = False
) -> str:
    """The fit and held-out parts in words (s from the log's start), e.g. "fit on t < 842 s,
    guard gap, held-out test on t >= 913 s"; reversed (the test part first) it says why."""
    (fit0_s, fit1_s), (test0_s, test1_s) = split_s
    if test0_s > fit0_s:
        fit, test, why = f"t < {fit1_s:.0f} s", f"t >= {test0_s:.0f} s", ""
    else:
        fit, test = f"t >= {fit0_s:.0f} s", f"t < {test1_s:.0f} s"
        why = " (the log's start is held out: its end showed no gap to close)"
    return test if test_only else f"fit on {fit}, guard gap, held-out test on {test}{why}"


def outlier_notes(null: NullModel) -> list[str]:
    """The report's note on each baseline replicate that is an outlier of one statistic
    (:func:`x6wd.gap.null.single_run_outliers`): which replicate, which statistic, its z."""
    out = []
    # with fewer logs than the null needs, its runs are replicates drawn from a model fitted
    # to them (null.inflation): "run 1 of 20" read as one of 20 logs the user never gave
    what = "baseline run" if null.inflation is None else "baseline replicate"
    made = "" if null.inflation is None else " (drawn from the noise model of the --sim logs)"
    for run, c, z_loo in null.outliers:
        where = ", ".join(x for x in (c.scale, c.period, c.place) if x != "all")
        out.append(
            f"{what} {run + 1} of {null.n_runs}{made} is an outlier in {c.statistic} {c.axis}"
            f"{f' ({where})' if where else ''}: z {z_loo:+.1f} against the other runs "
            "(leave-one-out); that statistic's limit alone covers it, every other limit is set "
            "without it (more seeds tell a heavy tail from a one-off)"
        )
    return out


def _limits_text(null: NullModel) -> str:
    """The "where" test's limits: the primary cells' and the others' (or the one limit)."""
    primary, other = null.limit_of(True), null.limit_of(False)
    mask = null.primary()
    if math.isnan(other) or mask is None:
        return f"{primary:.2f}"
    n_primary = int(np.sum(mask))
    return f"{primary:.2f} on the {n_primary} primary statistics, {other:.2f} on the others"


NO_CALIBRATION = (
    "no significant gap (no statistic beyond its family-wise limit), so no level calibration "
    "is fitted and no calibrated.toml written: layers fitted to this one log's figures would "
    "be fitted to how it happened to fall, not to a difference the test found; the scenario "
    "as it is stands"
)


def _validation_intro(n_runs: int, own: bool, both_ways: bool) -> str:
    return (
        "Mean and sigma of the horizontal error within 3 % (seed 000 reached 3.256 % on one "
        "hour) and the overlapping Allan deviation of east and north combined, "
        "sqrt(AVAR_e + AVAR_n), within 20 % at every octave from one step to a quarter of "
        f"the log; real against the average of the {n_runs} simulated runs, each one log "
        "like the real one"
        + (", both ways on the same draws" if both_ways else "")
        + (" (errors against each log's own mean, as the real log's: no truth)" if own else "")
        + ":"
    )


def spread_text(v: Validation) -> str:
    """The runs' own spread of mean, sigma and sigma / mean, or that it is not defined for
    one log (one --sim log, or one run: no spread over runs, not "nan%")."""
    if v.n_runs < 2:
        return "not defined for one log"
    return f"mean {v.mean_spread:.1%}, sigma {v.sd_spread:.1%}, sigma / mean {v.ratio_spread:.1%}"


def uncalibrated_markdown(v: Validation, own: bool = False) -> list[str]:
    """The validation block of report.md without a significant gap: seed 000's figures of
    the baseline runs alone, how many are within their tolerance, the runs' own spread, and
    why nothing is calibrated (no pass/fail verdict: one log within the seed-to-seed spread
    meets seed 000's tolerance only as far as the runs' own spread allows)."""
    figures = v.figures()
    within = sum(bool(Validation.within(sim, real, tol)) for _label, real, sim, tol in figures)
    lines = [
        "## Validation (seed 000's test)",
        "",
        _validation_intro(v.n_runs, own, both_ways=False),
        "",
        f"- the baseline runs alone: {within} of {len(figures)} figures within seed 000's "
        f"tolerance (furthest off: {v.worst_text()}); how far one log of this length lands "
        f"from its own model is the runs' own spread (sd over runs / average): "
        f"{spread_text(v)}",
        f"- {NO_CALIBRATION}.",
        "",
        "| figure | real | simulated | difference | within tolerance | target |",
        "|---|---|---|---|---|---|",
    ]
    labels = ["horizontal error mean (m)", "horizontal error sigma (m)"]
    labels += [f"Allan deviation, tau = {tau_s:g} s (m)" for tau_s in v.taus_s]
    for label, (_name, real, sim, tol) in zip(labels, figures, strict=True):
        lines.append(
            f"| {label} | {real:.4g} | {sim:.4g} | {Validation.rel_text(sim, real)} | "
            f"{_yes_no(Validation.within(sim, real, tol))} | ±{tol:.0%} |"
        )
    return lines


def _yes_no(within: bool | None) -> str:
    return "n/a" if within is None else ("yes" if within else "no")


def validation_markdown(c: Calibration, effects: list[str], own: bool = False) -> list[str]:
    """The validation block of report.md: seed 000's test (mean and sigma of the horizontal
    error within 3 %, the overlapping Allan deviation per octave within 20 %) of the runs
    with the selected effects only (a) and with the level calibration after them (b, the
    closing figure), each figure with pass/fail, the calibration's layers, and what (b)
    being in sample means. ``own``: the errors are against each log's own mean."""
    a, b = c.selected, c.calibrated
    with_what = (
        f"the selected effects only ({' + '.join(effects)}, with the parameters reported above)"
        if effects
        else "the baseline runs alone (no effect written)"
    )

    def verdict(v: Validation) -> str:
        return f"**{'PASS' if v.passed else 'FAIL'}** (furthest off: {v.worst_text()})"

    lines = [
        "## Validation (seed 000's test)",
        "",
        _validation_intro(a.n_runs, own, both_ways=True),
        "",
        f"- (a) {with_what}: " + verdict(a),
        "- (b) **calibrated**, the closing figure: (a) plus the level calibration below, "
        f"fitted to these figures by {c.evaluations} simulations: " + verdict(b),
    ]
    if not b.passed:
        lines.append(f"  - (b) {c.miss_text()}")
    lines += [
        "",
        "| figure | real | (a) selected | (a) difference | (a) pass "
        "| (b) calibrated | (b) difference | (b) pass | target |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    labels = ["horizontal error mean (m)", "horizontal error sigma (m)"]
    labels += [f"Allan deviation, tau = {tau_s:g} s (m)" for tau_s in a.taus_s]
    for label, fa, fb in zip(labels, a.figures(), b.figures(), strict=True):
        _name, real, sim_a, tol = fa
        sim_b = fb[2]
        cells = [label, f"{real:.4g}"]
        for sim in (sim_a, sim_b):
            cells += [
                f"{sim:.4g}",
                Validation.rel_text(sim, real),
                _yes_no(Validation.within(sim, real, tol)),
            ]
        lines.append("| " + " | ".join([*cells, f"±{tol:.0%}"]) + " |")
    lines += ["", "Level calibration (after the selected effects; `calibrated.toml`):", ""]
    lines += [f"- {fit.name}: {_params_text(fit)}" for fit in c.layers]
    if not c.layers:
        lines.append(
            "- no level layer is kept: `calibrated.toml` holds the selected effects only, and "
            "(b) is (a)"
        )
    if c.at_edge:
        lines.append(f"- at the edge of the search: {', '.join(c.at_edge)}")
    if c.held_out is not None and c.held_out_s is not None:
        before, after = c.held_out
        lines.append(
            f"- held-out check, reported not gated (the layers fitted on the fit part, "
            f"validated on t {c.held_out_s[0]:.0f}-{c.held_out_s[1]:.0f} s): without them "
            f"{closeness_text(before)}; with them {closeness_text(after)}"
        )
    lines += [f"- left out: {name}: {why}" for name, why in c.left_out]
    lines += [
        "",
        "(b) is **in sample**: its layers are fitted to these very figures on this very log, "
        "as seed 000 configured its model for the conditions of its one real hour. It shows "
        "that the simulator can be set to this receiver, not that it predicts it. How far "
        "one log of this length lands from its own model is the simulated runs' own spread "
        f"(sd over runs / average): {spread_text(a)}; a new log of this receiver is expected "
        "that far from (b)'s figures; where the first two are above 3 % even a perfect model meets "
        "(a)'s 3 % on one log only by luck, and where the third is, (b) meets mean and sigma "
        "together only when this log's sigma / mean happens to be the model's (scaling the "
        "error does not change it). "
        "`calibrated.toml` is `effects.toml` with the calibration's layers after the "
        "selected effects: a scenario fragment to use instead of it, to simulate this "
        "receiver at its level. A level layer is written only when the explanation or the "
        "test asks for it and, fitted on the whole log, it leaves the figures no further "
        "from the real log than the selected effects alone (in mean and sigma and in the "
        "Allan octaves no fewer within tolerance, and no larger summed miss).",
    ]
    return lines


def _num(x: float) -> float | None:  # JSON has no NaN
    return round(float(x), 6) if math.isfinite(x) else None


def candidate_text(diagnosis: Diagnosis) -> str:
    """What the best candidate of a gap it does not explain would do to seed 000's figures
    (its validation against the baseline's), in one line."""
    v = diagnosis.candidate_validation
    assert v is not None and diagnosis.calibration is not None
    names = " + ".join(f.name for f in diagnosis.selected)
    return (
        f"The best candidate, {names}, is not written (held-out closure "
        f"{diagnosis.closure:.2f}, {EXPLAINED_CLOSURE:g} needed). With it: "
        f"{'PASS' if v.passed else 'FAIL'} (furthest off: {v.worst_text()}); "
        f"{closeness_text(v)}, against the baseline runs' "
        f"{closeness_text(diagnosis.calibration.selected)}."
    )


def _validation_json(v: Validation) -> dict[str, Any]:
    """One validation's part of validation.json."""
    figures = []
    for label, real, sim, tol in v.figures():
        rel = Validation.rel(sim, real)
        within = Validation.within(sim, real, tol)
        figures.append(
            {
                "figure": label,
                "real": _num(real),
                "simulated": _num(sim),
                "difference": _num(rel),
                "tolerance": tol,
                # null: the simulated logs do not reach this octave (they are shorter)
                "pass": within,
            }
        )
    worst_label, worst_rel = v.worst()  # None: the simulated logs reach no figure
    return {
        "passed": v.passed,
        "runs": v.n_runs,
        "figures": figures,
        "furthest_off": {"figure": worst_label, "difference": _num(worst_rel)},
        "runs_spread": {
            "mean": _num(v.mean_spread),
            "sigma": _num(v.sd_spread),
            "sigma_over_mean": _num(v.ratio_spread),
        },
    }


def uncalibrated_dict(v: Validation) -> dict[str, Any]:
    """validation.json without a significant gap: the baseline runs' validation as
    ``selected``, ``calibrated`` and ``in_sample`` null, no calibration layers, and why
    (``not_calibrated``)."""
    return {
        "selected": _validation_json(v),
        "calibrated": None,
        "calibration": [],
        "in_sample": None,
        "evaluations": 0,
        "at_edge": [],
        "not_calibrated": NO_CALIBRATION,
        "candidate": None,
    }


def validation_dict(c: Calibration) -> dict[str, Any]:
    """validation.json: both validations (figures, differences, pass/fail, the runs' own
    spread), the calibration's layers and whether it is in sample (always)."""
    return {
        "selected": _validation_json(c.selected),
        "calibrated": _validation_json(c.calibrated),
        "calibration": [{"name": fit.name, "params": fit.params} for fit in c.layers],
        "in_sample": True,
        "evaluations": c.evaluations,
        "at_edge": list(c.at_edge),
        # the level layers not written, and why; the held-out check of those written
        "left_out": [{"name": name, "why": why} for name, why in c.left_out],
        "held_out": (
            None
            if c.held_out is None or c.held_out_s is None
            else {
                "part_s": [_num(c.held_out_s[0]), _num(c.held_out_s[1])],
                "without": _validation_json(c.held_out[0]),
                "with": _validation_json(c.held_out[1]),
            }
        ),
    }


def write_figures(diagnosis: Diagnosis, out: Path) -> None:
    """PNG figures: scatter, CDF, Allan deviation with the null band, ACF, time, map."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    def save(fig: Any, name: str) -> None:  # a full disk: exit 2 naming the file
        with output_file(out / name):
            fig.savefig(out / name, dpi=90)

    real = diagnosis.real
    sims = diagnosis.baseline[: min(5, len(diagnosis.baseline))]
    valid = np.asarray(real.valid, dtype=bool)

    fig, ax = plt.subplots(figsize=(5, 5))
    for run in sims[:1]:
        run_valid = np.asarray(run.valid, dtype=bool)
        ax.plot(run.east_m[run_valid], run.north_m[run_valid], ".", ms=2, alpha=0.4, label="sim")
    ax.plot(real.east_m[valid], real.north_m[valid], ".", ms=2, alpha=0.6, label="real")
    ax.set(
        xlabel="east error (m)", ylabel="north error (m)", title="horizontal error", aspect="equal"
    )
    ax.legend()
    save(fig, "scatter.png")
    plt.close(fig)

    fig, ax = plt.subplots(figsize=(6, 4))
    for i, run in enumerate(diagnosis.baseline):
        run_valid = np.asarray(run.valid, dtype=bool)
        radial_m = np.sort(np.hypot(run.east_m[run_valid], run.north_m[run_valid]))
        ax.plot(
            radial_m,
            np.linspace(0, 1, radial_m.size),
            color="0.7",
            lw=0.8,
            label="sim runs" if i == 0 else None,
        )
    radial_m = np.sort(np.hypot(real.east_m[valid], real.north_m[valid]))
    ax.plot(radial_m, np.linspace(0, 1, radial_m.size), color="C3", lw=2, label="real")
    ax.set(xlabel="horizontal error (m)", ylabel="CDF", title="error CDF, real vs sim runs")
    ax.legend()
    save(fig, "cdf.png")
    plt.close(fig)

    factors = octave_taus(diagnosis.layout)
    taus_s = np.array(factors) * diagnosis.layout.dt_s
    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    for axis, ax in enumerate(axes):
        sims_adev_m = np.array(
            [
                np.sqrt(allan_var(regular(run, diagnosis.layout.dt_s)[axis], factors))
                for run in diagnosis.baseline
            ]
        )
        band_lo, band_hi = np.nanquantile(sims_adev_m, [0.025, 0.975], axis=0)
        ax.fill_between(taus_s, band_lo, band_hi, color="0.8", label="sim null 95 %")
        ax.loglog(
            taus_s,
            np.sqrt(allan_var(regular(real, diagnosis.layout.dt_s)[axis], factors)),
            "C3o-",
            label="real",
        )
        ax.set(
            xlabel="averaging time (s)", ylabel="Allan deviation (m)", title=["east", "north"][axis]
        )
        ax.legend()
    fig.tight_layout()
    save(fig, "allan.png")
    plt.close(fig)

    lag_steps = list(
        range(1, max(2, min(600, int(diagnosis.layout.duration_s / diagnosis.layout.dt_s / 5))))
    )
    fig, ax = plt.subplots(figsize=(6, 4))
    sims_acf = np.array(
        [acf(regular(run, diagnosis.layout.dt_s)[0], lag_steps) for run in diagnosis.baseline]
    )
    band_lo, band_hi = np.quantile(sims_acf, [0.025, 0.975], axis=0)
    lag_s = np.array(lag_steps) * diagnosis.layout.dt_s
    ax.fill_between(lag_s, band_lo, band_hi, color="0.8", label="sim null 95 %")
    ax.plot(lag_s, acf(regular(real, diagnosis.layout.dt_s)[0], lag_steps), "C3", label="real")
    ax.set(xlabel="lag (s)", ylabel="autocorrelation (east)", title="autocorrelation")
    ax.legend()
    save(fig, "acf.png")
    plt.close(fig)

    fig, ax = plt.subplots(figsize=(10, 4))
    t_s = np.asarray(real.t_s) - real.t_s[0]
    ax.plot(t_s[valid], np.hypot(real.east_m, real.north_m)[valid], "C3.", ms=2, label="real")
    for run in sims[:2]:
        run_valid = np.asarray(run.valid, dtype=bool)
        run_t_s = np.asarray(run.t_s) - run.t_s[0]
        ax.plot(
            run_t_s[run_valid], np.hypot(run.east_m, run.north_m)[run_valid], ".", ms=1, color="0.6"
        )
    for cell in diagnosis.where:
        if cell["period"] != "all":
            start_s, end_s = (float(edge) for edge in cell["period"][2:-1].split("-"))
            ax.axvspan(start_s, end_s, color="C1", alpha=0.15)
    (fit0_s, fit1_s), (test0_s, test1_s) = diagnosis.split_s
    for edge_s in (fit1_s, test0_s) if test0_s > fit0_s else (test1_s, fit0_s):
        ax.axvline(edge_s, color="k", ls="--", lw=0.8)
    ax.set(
        xlabel="time (s)",
        ylabel="horizontal error (m)",
        title="error over time (shaded: flagged periods; dashed: fit | guard | test)",
    )
    ax.legend()
    save(fig, "time.png")
    plt.close(fig)

    if diagnosis.layout.moving:
        true_east_m, true_north_m = truth_track_m(real)
        fig, ax = plt.subplots(figsize=(6, 6))
        error_m = np.hypot(real.east_m, real.north_m)
        points = ax.scatter(
            true_east_m[valid], true_north_m[valid], c=error_m[valid], s=4, cmap="viridis"
        )
        fig.colorbar(points, label="horizontal error (m)")
        flagged = {cell["place"] for cell in diagnosis.where if cell["place"] != "all"}
        ax.axvline(diagnosis.layout.place_e_m, color="0.5", lw=0.5)
        ax.axhline(diagnosis.layout.place_n_m, color="0.5", lw=0.5)
        for fit in diagnosis.selected:
            if fit.name == "multipath_zone":
                zone = fit.effect
                dist_m, _ux, _uy = zone.distance_to_wall_m(true_east_m, true_north_m)
                inside = valid & (dist_m <= zone.distance_m)
                ax.plot(
                    true_east_m[inside], true_north_m[inside], "o", mfc="none", mec="C3", ms=5,
                    alpha=0.4, label="fitted multipath zone",
                )  # fmt: skip
                ax.plot(
                    [zone.x1_m, zone.x2_m], [zone.y1_m, zone.y2_m], "C3-", lw=3, label="fitted wall"
                )
                ax.legend(loc="best")
        ax.set(
            xlabel="east (m)",
            ylabel="north (m)",
            aspect="equal",
            title=f"error over the map ({len(flagged)} of 4 quadrants flagged)",
        )
        save(fig, "map.png")
        plt.close(fig)
