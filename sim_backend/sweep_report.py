"""The results of a sweep (:mod:`sim_backend.sweep`): a table, figures and a markdown summary.

Written into the sweep's output directory from the run records (``runs/*.json``):

- ``results.csv`` — one row per run: its cell, scenario, parameters (one column per grid or
  [set] key), replicate, seed, status and error, and the mission's summary figures
  (completed, waypoints, path and straight lengths (m), their ratio, simulated and wall
  seconds, the number of arrivals and their median true and GPS slow errors (m));
  ``results.parquet`` the same when pyarrow is installed (it is not a dependency);
- ``arrivals.csv`` — one row per waypoint arrival: the true horizontal error from the antenna to
  the waypoint when the arrival was decided (m) and the GPS's slow error at that moment (m);
- ``completion.png`` (completed missions per cell, % of the missions that ran: a run whose
  mission raised or that the cluster lost is no mission the robot failed, and is shown apart; a
  cell where none ran is a hatched bar, not a 0 % one), ``arrival_cdf.png`` (the empirical
  CDF of the true arrival error per cell, the GPS slow error dashed), ``path_ratio.png`` (true
  path / straight polyline per completed run, per cell), ``gps_cep50.png`` (each run's raw-fix
  CEP50, per cell: a survey sweep's figure); each only when a cell has something to show in
  it, the per-cell ones for up to :data:`MAX_ROW_CELLS` cells (the summary says which were
  left out and why);
- ``summary.md`` — the sweep, the executor and its throughput, a table per cell, the failed
  runs with their errors and the runs the cluster lost; the folder's finished runs that this
  sweep does not plan (a quick look with ``--seeds 1`` at a finished sweep) are counted there,
  not tabled. It names the x6wd version(s) the runs come from, and each median over only some
  of a cell's runs says so ("1.61 m (1 of 2 runs)").
"""

from __future__ import annotations

import csv
import io
import json
import math
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass, field
from datetime import date, time
from pathlib import Path
from typing import Any

import numpy as np

from x6wd.core.outdir import whole_output_file

RUN_COLUMNS = (
    "run_id",
    "cell_id",
    "scenario",
    "replicate",
    "seed",
    "status",
    "error",
    "completed",
    "waypoints_reached",
    "waypoint_count",
    "path_length_m",
    "straight_length_m",
    "path_ratio",
    "sim_time_s",
    "wall_time_s",
    "arrivals",
    "arrival_true_median_m",
    "arrival_gps_slow_median_m",
    "gps_cep50_m",
    "gps_r95_m",
    "gps_rms_m",
    "filtered_rms_m",
    "fix_fraction",
    "hold_time_s",
    "position_source",
    "engine",
    "worker",
    "x6wd_version",
    "schema",
)
ARRIVAL_COLUMNS = ("index", "t_s", "true_error_m", "gps_error_m", "gps_slow_error_m")
RESULT_FIELDS = (
    "completed",
    "waypoints_reached",
    "waypoint_count",
    "path_length_m",
    "straight_length_m",
    "sim_time_s",
    "wall_time_s",
    "arrivals",
    "position_source",
    "gps_cep50_m",
    "gps_r95_m",
    "gps_rms_m",
    "filtered_rms_m",
    "fix_fraction",
    "hold_time_s",
)
"""The figures a successful run's record of :data:`sim_backend.sweep.RESULTS_SCHEMA` has (a
value may be null: no fix, no figure; the key is there)."""
OLDER_RUNS_DIR = "older-runs"
"""In a sweep's folder: the run records of another results schema that a rerun replaced
(:func:`sim_backend.sweep.stale_reason`), kept for a comparison and in no table."""
WORKER_MISMATCH = "worker_mismatch"
"""In a run record: the figures its worker's x6wd returned were not this x6wd's (another
results schema, or some missing: "schema 1, without gps_* figures"). Such a run is stored as
failed without them and run again by the next call (:func:`sim_backend.sweep.stale_reason`);
the summary's version line leaves it out."""
FIXED_COLUMNS = frozenset(RUN_COLUMNS) | frozenset(ARRIVAL_COLUMNS)
"""The tables' own columns: no parameter ([set] or [grid] key) may have one of these names
(:func:`sim_backend.sweep.load_sweep` refuses it; :func:`param_keys` raises)."""


def _num(v: Any) -> float:
    if isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v):
        return float(v)
    return math.nan


def record_schema(record: dict[str, Any]) -> int | None:
    """A record's results schema: its ``"schema"``. A record without one (written before
    2026-12-06) is of schema 2 when it is a success with every :data:`RESULT_FIELDS` (the
    figures came on 2026-12-04), of schema 1 when it is a success without them; a run that
    raised or was lost has no figures to tell its schema by: None (unknown, and no reason to
    run it again: the ``retry_failed`` rules apply to it as to any error)."""
    schema = record.get("schema")
    if isinstance(schema, int) and not isinstance(schema, bool):
        return schema
    if record.get("status") != "ok":
        return None
    return 2 if all(k in record for k in RESULT_FIELDS) else 1


def path_ratio(rec: dict[str, Any]) -> float:
    """True path length / straight polyline of a run (NaN without lengths)."""
    path, straight = _num(rec.get("path_length_m")), _num(rec.get("straight_length_m"))
    return path / straight if straight > 0 else math.nan


def _median(values: Sequence[float]) -> float:
    v = [x for x in values if math.isfinite(x)]
    return float(np.median(v)) if v else math.nan


def _pct(values: Sequence[float], q: float) -> float:
    v = [x for x in values if math.isfinite(x)]
    return float(np.percentile(v, q)) if v else math.nan


def json_value(value: Any) -> Any:
    """A TOML date, time or datetime (a sweep value) as its ISO text, as JSON cannot hold
    it (``2020-01-01T12:00:00+00:00``); any other value as it is."""
    if isinstance(value, (date, time)):
        return value.isoformat()
    return value


def _json_default(value: Any) -> Any:
    out = json_value(value)
    if out is value:
        raise TypeError(f"Object of type {type(value).__name__} is not JSON serializable")
    return out


def _cell_text(value: Any) -> str:
    if value is None:
        return ""
    if isinstance(value, float) and not math.isfinite(value):
        return ""
    if isinstance(value, (list, dict)):
        return json.dumps(value, default=_json_default)
    return str(json_value(value))


def short_keys(keys: Sequence[str]) -> dict[str, str]:
    """Each dotted key's shortest suffix (whole parts) that no other of ``keys`` ends with:
    ``gnss.rate_hz`` and ``compass.rate_hz`` stay whole, ``navigation.position_source`` alone
    is ``position_source``; a key that is another's suffix (``rate_hz``, ``gnss.rate_hz``) is
    itself whole, the other longer."""
    split = {k: k.split(".") for k in keys}
    out: dict[str, str] = {}
    for k, parts in split.items():
        n = 1
        while n < len(parts) and any(o != k and op[-n:] == parts[-n:] for o, op in split.items()):
            n += 1
        out[k] = ".".join(parts[-n:])
    return out


def param_keys(records: Sequence[dict[str, Any]]) -> list[str]:
    """Every override key of the records, in first-seen order; one named as a fixed column
    (:data:`FIXED_COLUMNS`) raises ValueError: its column would overwrite that one."""
    keys: dict[str, None] = {}
    for r in records:
        for k in r.get("overrides") or {}:
            keys.setdefault(k, None)
    clash = [k for k in keys if k in FIXED_COLUMNS]
    if clash:
        raise ValueError(f"parameter {clash[0]!r} has the name of a column of the results")
    return list(keys)


def run_rows(records: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    """The rows of ``results.csv`` (values as Python scalars; NaN where unknown)."""
    keys = param_keys(records)
    rows = []
    for r in records:
        arr = r.get("arrivals") or []
        row: dict[str, Any] = {c: r.get(c) for c in RUN_COLUMNS}
        if row["engine"] is None and r.get("status") == "ok":
            row["engine"] = "robot"  # a run kept from before the column: every run was
        for k in keys:
            row[k] = (r.get("overrides") or {}).get(k)
        row["path_ratio"] = path_ratio(r)
        row["arrivals"] = len(arr)
        row["arrival_true_median_m"] = _median([_num(a.get("true_error_m")) for a in arr])
        row["arrival_gps_slow_median_m"] = _median([_num(a.get("gps_slow_error_m")) for a in arr])
        rows.append(row)
    return rows


_report_file = whole_output_file
"""Around the writing of one report file: a full disk is one line naming it, and no
truncated table or figure is left to be read as the sweep's."""


def _write_csv(path: Path, rows: Sequence[dict[str, Any]], columns: Sequence[str]) -> None:
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(columns)
    for row in rows:
        w.writerow([_cell_text(row.get(c)) for c in columns])
    with _report_file(path):
        path.write_text(buf.getvalue(), encoding="utf-8")


def _write_parquet(path: Path, rows: Sequence[dict[str, Any]], columns: Sequence[str]) -> bool:
    try:
        import pyarrow as pa
        import pyarrow.parquet as pq
    except ImportError:
        return False

    def value(v: Any) -> Any:
        return json.dumps(v, default=_json_default) if isinstance(v, (list, dict)) else v

    table = pa.table({c: [value(r.get(c)) for r in rows] for c in columns})
    with _report_file(path):
        pq.write_table(table, path)
    return True


# ---------------------------------------------------------------------------- per cell


@dataclass
class CellStats:
    """The figures of one cell over its runs (m, s; ratios dimensionless). ``ok``: the
    mission ran (to its end, completed or not); ``failed``: the mission raised (an unreadable
    almanac: the robot never drove); ``lost``: the cluster could not finish the run (no
    result). Neither failed nor lost runs are successes or failures of the robot: the
    completion rate is of the ``ok`` ones that drove a mission (``surveys``: ok runs of a
    scenario without waypoints, which have no completion to count)."""

    cell_id: str
    scenario: str
    params: dict[str, Any]
    names: dict[str, str] = field(default_factory=dict)
    runs: int = 0
    ok: int = 0
    failed: int = 0
    lost: int = 0
    completed: int = 0
    surveys: int = 0  # ok runs without waypoints (a static survey): no completion
    arrival_runs: int = 0  # runs with an arrival error
    arrival_true_m: list[float] = field(default_factory=list)
    arrival_gps_m: list[float] = field(default_factory=list)
    path_ratios: list[float] = field(default_factory=list)
    gps_cep50_m: list[float] = field(default_factory=list)  # per run, raw fixes
    sim_times_s: list[float] = field(default_factory=list)
    wall_times_s: list[float] = field(default_factory=list)

    @property
    def label(self) -> str:
        """ "scenario key=value ...", each dotted key by its name in ``names`` (the shortest
        suffix that tells the sweep's keys apart, :func:`short_keys`), else its own."""
        names = self.names or short_keys(list(self.params))
        parts = [f"{names.get(k, k)}={_cell_text(v)}" for k, v in self.params.items()]
        return " ".join([self.scenario, *parts])

    @property
    def completion_pct(self) -> float:
        """Completed missions, % of the missions that ran (``ok`` less ``surveys``; NaN when
        none ran)."""
        missions = self.ok - self.surveys
        return 100.0 * self.completed / missions if missions else math.nan

    @property
    def apart(self) -> str:
        """The runs left out of the completion rate, in words ("6 errored, 1 lost"; "" for
        none)."""
        parts = [f"{self.surveys} survey{'' if self.surveys == 1 else 's'}" if self.surveys else ""]
        parts.append(f"{self.failed} errored" if self.failed else "")
        parts.append(f"{self.lost} lost" if self.lost else "")
        return ", ".join(p for p in parts if p)

    @property
    def completion_text(self) -> str:
        """ "3/4 (75 %)" of the missions that ran; "n/a (6 errored)" when none ran: six runs
        that raised are not six missions that did not complete."""
        missions = self.ok - self.surveys
        if not missions:
            return f"n/a ({self.apart or 'no run'})"
        return f"{self.completed}/{missions} ({_f(self.completion_pct, '.0f')} %)"


def cell_stats(records: Sequence[dict[str, Any]]) -> list[CellStats]:
    """Group the runs by cell (first-seen order) and collect the figures."""
    cells: dict[str, CellStats] = {}
    for r in records:
        cid = r["cell_id"]
        c = cells.get(cid)
        if c is None:
            c = cells[cid] = CellStats(cid, r.get("scenario", ""), dict(r.get("params") or {}))
        c.runs += 1
        if r.get("status") == "lost":
            c.lost += 1
            continue
        if r.get("status") != "ok":
            c.failed += 1
            continue
        c.ok += 1
        c.surveys += r.get("waypoint_count") == 0
        c.wall_times_s.append(_num(r.get("wall_time_s")))
        c.gps_cep50_m.append(_num(r.get("gps_cep50_m")))
        before = len(c.arrival_true_m)
        for a in r.get("arrivals") or []:
            t, g = _num(a.get("true_error_m")), _num(a.get("gps_slow_error_m"))
            if math.isfinite(t):
                c.arrival_true_m.append(t)
            if math.isfinite(g):
                c.arrival_gps_m.append(g)
        c.arrival_runs += len(c.arrival_true_m) > before
        if r.get("completed"):
            c.completed += 1
            c.path_ratios.append(path_ratio(r))
            c.sim_times_s.append(_num(r.get("sim_time_s")))
    names = short_keys(list({k: None for c in cells.values() for k in c.params}))
    for c in cells.values():  # one naming over the whole sweep: a label means one key
        c.names = {k: names[k] for k in c.params}
    return list(cells.values())


# ---------------------------------------------------------------------------- figures


MAX_ROW_CELLS = 100
"""A per-cell row figure (completion, path ratio, GPS CEP50) is drawn for up to this many
cells: at a row each, 1000 cells made 35,000-pixel images that took most of the report's
time (an outside audit); the summary's table has every cell."""
CDF_PANEL_CELLS = 10
"""Cells per panel of ``arrival_cdf.png``: one colour each of tab10, so no two curves of a
panel share one (past 10 cells one panel repeated its colours: an outside audit)."""
MAX_CDF_PANELS = 6


def cdf_panels(cells: Sequence[CellStats]) -> list[list[CellStats]]:
    """The cells with arrivals, in order, in panels of :data:`CDF_PANEL_CELLS` (none when
    more than :data:`MAX_CDF_PANELS` panels would be needed: see :func:`figure_plan`)."""
    with_arrivals = [c for c in cells if c.arrival_true_m]
    if len(with_arrivals) > CDF_PANEL_CELLS * MAX_CDF_PANELS:
        return []
    k = CDF_PANEL_CELLS
    return [with_arrivals[i : i + k] for i in range(0, len(with_arrivals), k)]


def figure_plan(cells: Sequence[CellStats]) -> tuple[list[str], list[str]]:
    """The figures the cells have something to show in (file names, :data:`FIGURES`' order)
    and, for the summary, a line for each kind left out and why."""
    # a run that raised or was lost may have been a mission: its completion bar says "n/a"
    missions = any(c.ok > c.surveys or c.failed or c.lost for c in cells)
    has_ratio = any(math.isfinite(x) for c in cells for x in c.path_ratios)
    has_cep = any(math.isfinite(x) for c in cells for x in c.gps_cep50_m)
    n_arrival = sum(bool(c.arrival_true_m) for c in cells)
    few = len(cells) <= MAX_ROW_CELLS
    plan, notes = [], []
    if missions and few:
        plan.append("completion.png")
    if n_arrival and cdf_panels(cells):
        plan.append("arrival_cdf.png")
    if has_ratio and few:
        plan.append("path_ratio.png")
    if has_cep and few:
        plan.append("gps_cep50.png")
    if not missions:
        notes.append(
            "no mission ran (every run a survey): no completion, arrival error or path ratio figure"
        )
    if not few and (missions or has_cep):
        notes.append(
            f"{len(cells)} cells: the per-cell figures (completion, path ratio, GPS"
            f" CEP50) are drawn for up to {MAX_ROW_CELLS}; the table has every cell"
        )
    if n_arrival > CDF_PANEL_CELLS * MAX_CDF_PANELS:
        notes.append(
            f"{n_arrival} cells with arrivals: the arrival error CDF is drawn for up to"
            f" {CDF_PANEL_CELLS * MAX_CDF_PANELS}; the table has each cell's median"
            " and p95"
        )
    return plan, notes


def _ecdf(values: Sequence[float]) -> tuple[np.ndarray, np.ndarray]:
    """The empirical CDF as step points, from 0 at the smallest value (so that one value
    draws its step, not a lone point)."""
    v = np.sort(np.asarray(values, dtype=float))
    return np.r_[v[:1], v], np.r_[0.0, np.arange(1, v.size + 1) / v.size]


def _plots(cells: Sequence[CellStats], out: Path) -> list[str]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    plan, _notes = figure_plan(cells)
    names = []
    labels = [c.label for c in cells]
    height = max(2.5, 0.35 * len(cells) + 1.2)
    y = np.arange(len(cells))

    def save(fig: Any, name: str) -> None:
        fig.tight_layout()
        with _report_file(out / name):
            fig.savefig(out / name, dpi=100, bbox_inches="tight")
        plt.close(fig)
        names.append(name)

    if "completion.png" in plan:
        fig, ax = plt.subplots(figsize=(8, height))
        pct = [c.completion_pct if math.isfinite(c.completion_pct) else 0.0 for c in cells]
        ax.barh(y, pct, color="tab:green")
        none_ran = [float(yi) for yi, c in zip(y, cells, strict=True) if c.ok == c.surveys]
        if none_ran:  # no mission ran: a hatched "n/a" bar, not an empty 0 % one
            ax.barh(none_ran, 100.0, color="none", edgecolor="tab:grey", hatch="//", lw=0.5)
        ax.set_yticks(y, labels, fontsize=8)
        ax.invert_yaxis()
        ax.set_xlim(0, 115)
        errored, lost = sum(c.failed for c in cells), sum(c.lost for c in cells)
        apart = [f"{errored} errored" if errored else "", f"{lost} lost" if lost else ""]
        apart_text = " and ".join(p for p in apart if p)
        ax.set_xlabel(
            "missions completed (% of the missions that ran"
            + (f"; {apart_text} runs not counted)" if apart_text else ")")
        )
        ax.set_title("Completion rate per cell")
        for yi, c, x in zip(y, cells, pct, strict=True):
            text = f"{c.completed}/{c.ok - c.surveys}" + (f", {c.apart}" if c.apart else "")
            if c.ok == c.surveys:
                text, x = f"n/a: no mission ran ({c.apart or 'no run'})", 0.0
            ax.text(x + 1, float(yi), text, va="center", fontsize=7)
        save(fig, "completion.png")

    if "arrival_cdf.png" in plan:
        panels = cdf_panels(cells)
        fig, axes = plt.subplots(len(panels), 1, figsize=(10, 1.0 + 3.6 * len(panels)),
                                 squeeze=False, sharex=True)  # fmt: skip
        colours = plt.get_cmap("tab10")
        for ax, panel in zip(axes[:, 0], panels, strict=True):
            for i, c in enumerate(panel):  # a colour per cell of the panel; GPS dashed
                col = colours(i)
                ax.step(*_ecdf(c.arrival_true_m), where="post", color=col, label=c.label)
                if c.arrival_gps_m:
                    ax.step(*_ecdf(c.arrival_gps_m), where="post", color=col, ls="--", lw=0.8)
            ax.set_ylabel("fraction of arrivals")
            ax.set_ylim(0, 1.01)
            ax.grid(alpha=0.3)
            ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))
        axes[-1, 0].set_xlabel("true arrival error (m); dashed: GPS slow error at the same moments")
        split = f" ({len(panels)} panels of up to {CDF_PANEL_CELLS} cells)"
        axes[0, 0].set_title("Arrival error CDF per cell" + (split if len(panels) > 1 else ""))
        save(fig, "arrival_cdf.png")

    def dots(name: str, per_cell: list[list[float]], xlabel: str, title: str) -> None:
        fig, ax = plt.subplots(figsize=(8, height))
        for yi, d in zip(y, per_cell, strict=True):
            if d:  # the runs, their interquartile range and median
                q1, q2, q3 = np.percentile(d, [25, 50, 75])
                ax.hlines(yi, q1, q3, color="tab:blue", lw=6, alpha=0.3)
                ax.plot([q2], [yi], "|", ms=14, mew=2, color="tab:blue")
                ax.plot(d, np.full(len(d), yi), "o", ms=3, alpha=0.6, color="tab:blue")
        ax.set_yticks(y, labels, fontsize=8)
        ax.invert_yaxis()
        ax.set_xlabel(xlabel)
        ax.set_title(title)
        if name == "path_ratio.png":
            ax.axvline(1.0, color="grey", lw=0.8)
        save(fig, name)

    per_run = (  # file, each cell's per-run figures, x label, title
        ("path_ratio.png", [c.path_ratios for c in cells],
         "true path length / straight polyline (completed runs)", "Path ratio per cell"),
        ("gps_cep50.png", [c.gps_cep50_m for c in cells],
         "GPS CEP50 of each run's raw fixes against the truth (m)", "GPS CEP50 per cell"),
    )  # fmt: skip
    for name, values, xlabel, title in per_run:
        if name in plan:
            dots(name, [[x for x in v if math.isfinite(x)] for v in values], xlabel, title)
    return names


# ---------------------------------------------------------------------------- markdown


def _f(v: float, fmt: str = ".2f") -> str:
    return format(v, fmt) if math.isfinite(v) else "-"


def _of(n: int, c: CellStats) -> str:
    """ " (n of m runs)" after a median over ``n`` of a cell's ``m`` runs, when that is some but
    not all of them ("" otherwise: over all, or "-" for none)."""
    return f" ({n} of {c.runs} runs)" if 0 < n < c.runs else ""


def _finite(values: Sequence[float]) -> int:
    return sum(math.isfinite(v) for v in values)


def _version_lines(records: Sequence[dict[str, Any]]) -> list[str]:
    """The summary's line about the x6wd (version, results schema) the runs come from: a
    resumed folder may hold runs of several versions of one schema (a schema's figures are
    the same ones; another schema's records are run again, never tabled here)."""
    done = [  # a run whose task raised has no worker's word (no "worker"); nor is one of
        # another x6wd's figures (WORKER_MISMATCH) in any table
        r
        for r in records
        if r.get("status") in ("ok", "error") and "worker" in r and WORKER_MISMATCH not in r
    ]
    if not done:
        return []
    unknown = "an x6wd that did not record its version (before 2026-12-06)"
    versions = Counter(str(r.get("x6wd_version") or unknown) for r in done)
    known = sorted({s for s in map(record_schema, done) if s is not None})
    schema = f"results schema {', '.join(map(str, known)) or 'not recorded'}"
    if len(versions) == 1:
        return [f"- x6wd: every run by {next(iter(versions))} ({schema})"]
    listed = ", ".join(f"{v} ({n} run{'' if n == 1 else 's'})" for v, n in versions.items())
    return [
        f"- **runs from {len(versions)} x6wd versions** ({schema}): {listed}; a cell's figures"
        " may mix them (a new --out runs every run with one)"
    ]


def _older_lines(n: int) -> list[str]:
    """The summary's line about the records in ``older-runs/`` (none without any)."""
    if not n:
        return []
    return [
        f"- `{OLDER_RUNS_DIR}/`: {n} record{'' if n == 1 else 's'} of another results schema"
        f" that {'its rerun' if n == 1 else 'their reruns'} replaced, in no table"
    ]


FIGURES = {  # file -> its caption in the summary
    "completion.png": "completion",
    "arrival_cdf.png": "arrival error CDF",
    "path_ratio.png": "path ratio",
    "gps_cep50.png": "GPS CEP50",
}


def _outside_lines(outside: dict[str, int]) -> list[str]:
    """The summary's line about the finished runs of the folder that this sweep does not plan
    (``outside``: count, more_seeds, seeds, as :func:`x6wd.app.sweep.outside_runs` counts
    them): none without any."""
    n, more = int(outside.get("count", 0)), int(outside.get("more_seeds", 0))
    stale = int(outside.get("stale_seeds", 0))
    if not n:
        return []
    why = []
    if more:
        why.append(
            f"{more} further seeds of these cells (a sweep of {outside.get('seeds')} seeds"
            " tables them)"
        )
    if stale:
        why.append(
            f"{stale} further seeds of these cells made with another scenario, file or x6wd"
            " (the sweep that plans them runs them again)"
        )
    if n - more - stale:
        why.append(f"{n - more - stale} of cells not in this grid")
    return [
        f"- **not in this summary**: {n} finished run{'' if n == 1 else 's'} in `runs/`"
        f" outside this sweep's grid ({'; '.join(why)}); their files are kept, and the sweep"
        " that plans them tables the current ones without running them again"
    ]


def markdown(
    result_info: dict[str, Any],
    cells: Sequence[CellStats],
    records: Sequence[dict[str, Any]],
    figures: Sequence[str] = tuple(FIGURES),
    figure_notes: Sequence[str] = (),
) -> str:
    """The summary: the sweep, a row per cell, the figures (the ``figures`` files; a line
    each of ``figure_notes``: those left out and why), the failed runs."""
    i = result_info
    lost = [r for r in records if r.get("status") == "lost"]
    lost_text = (
        f"; {len(lost)} lost by the cluster (no result, not counted anywhere below: the same"
        " command runs them again)"
        if lost
        else ""
    )
    raised = int(i.get("raised") or 0)
    raised_text = (
        f" ({raised} run{'' if raised == 1 else 's'} that raised not counted)" if raised else ""
    )
    lines = [f"# Sweep {i['name']!r}", ""]
    lines += [
        f"- sweep file: `{i.get('source') or '-'}`; sweep seed {i['seed']}, {i['seeds']}"
        f" seed{'' if i['seeds'] == 1 else 's'} per cell",
        f"- scenarios: {', '.join(f'`{s}`' for s in i['scenarios'])}",
        f"- [set]: `{json.dumps(i['set'], default=_json_default)}`;"
        f" [grid]: `{json.dumps(i['grid'], default=_json_default)}`",
        f"- {len(records)} runs in {len(cells)} cells: {i['ran']} run now, {i['skipped']}"
        f" found done; {sum(c.failed for c in cells)} failed" + lost_text,
        (
            f"- executor: {i['executor']}; {_f(i['wall_s'], '.1f')} s wall,"
            f" {_f(i['missions_per_min'], '.1f')} missions/min{raised_text}"
            if i["ran"]
            else "- executor: none this time (every run was found done: no throughput)"
        ),
        *_version_lines(records),
        *_outside_lines(i.get("outside") or {}),
        *_older_lines(int(i.get("older_files") or 0)),
        "",
        "Arrival errors are true horizontal distances (m) from the antenna to the waypoint when"
        " the arrival was decided; *GPS slow* is the GPS's own slow error at those moments"
        " (what no navigation can see); *GPS CEP50* is the median over a cell's runs of each"
        " run's raw-fix horizontal CEP50 against the truth (also results.csv's gps_* columns,"
        " the figures of a survey's sweep); the path ratio is the true path over the straight"
        " polyline, over completed runs. A median over only some of a cell's runs says over how"
        " many: *(1 of 2 runs)*.",
        "",
        "*Completed* is a share of the missions that ran (*failed* runs, whose mission raised,"
        " and *lost* runs, which the cluster could not finish, are no missions of the robot:"
        " counted apart, n/a where no mission ran).",
        "",
        "| cell | runs | completed | failed | lost | arrival error median / p95"
        " | GPS slow median | GPS CEP50 median | path ratio median (max) | sim time median"
        " | wall per run |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for c in cells:
        ratios = [x for x in c.path_ratios if math.isfinite(x)]
        lines.append(
            f"| `{c.cell_id}` {c.label} | {c.runs} | {c.completion_text} | {c.failed} | {c.lost}"
            f" | {_f(_median(c.arrival_true_m))} /"
            f" {_f(_pct(c.arrival_true_m, 95))} m{_of(c.arrival_runs, c)}"
            f" | {_f(_median(c.arrival_gps_m))} m{_of(c.arrival_runs, c)}"
            f" | {_f(_median(c.gps_cep50_m))} m{_of(_finite(c.gps_cep50_m), c)}"
            f" | {_f(_median(ratios), '.3f')} ({_f(max(ratios) if ratios else math.nan, '.3f')})"
            f"{_of(len(ratios), c)}"
            f" | {_f(_median(c.sim_times_s), '.1f')} s{_of(_finite(c.sim_times_s), c)}"
            f" | {_f(_median(c.wall_times_s))} s{_of(_finite(c.wall_times_s), c)} |"
        )
    lines.append("")
    for name in figures:
        lines += [f"![{FIGURES.get(name, name)}]({name})", ""]
    if figure_notes:
        lines += [*(f"- figures: {n}" for n in figure_notes), ""]
    failed = [r for r in records if r.get("status") not in ("ok", "lost")]
    if failed:
        lines += [f"## Failed runs ({len(failed)})", ""]
        for r in failed[:50]:
            lines.append(
                f"- `{r['run_id']}` seed {r.get('seed')} ({r.get('status')}): {r.get('error')}"
            )
        if len(failed) > 50:
            lines.append(f"- ... and {len(failed) - 50} more (results.csv)")
        lines.append("")
    if lost:
        lines += [
            f"## Lost runs ({len(lost)})",
            "",
            "The cluster could not finish them (a worker died too often, or the scheduler went"
            " away): run the same command again to finish them.",
            "",
        ]
        for r in lost[:10]:
            lines.append(f"- `{r['run_id']}` seed {r.get('seed')}: {r.get('error')}")
        if len(lost) > 10:
            lines.append(f"- ... and {len(lost) - 10} more (results.csv)")
        lines.append("")
    engine = i.get("engine") or "auto"
    flag = "" if engine == "auto" else f" --engine {engine}"
    lines += [
        f"Replay a run: `x6wd sim cells/CELL_ID.toml --seed SEED{flag}` (the cell's resolved"
        " scenario; seeds in results.csv).",
        "",
    ]
    return "\n".join(lines)


def write_report(
    result_info: dict[str, Any],
    records: Sequence[dict[str, Any]],
    out_dir: str | Path,
    figures: bool = True,
) -> list[str]:
    """Write the table(s), figures and ``summary.md``; returns the file names written.
    ``result_info``: name, source, seed, seeds, scenarios, set, grid, ran, skipped, executor,
    wall_s, missions_per_min, (optional) raised: this call's runs that raised, not in
    missions_per_min, (optional) older_files: the records in ``older-runs/`` (counted here
    when not given), and (optional) outside: the folder's finished runs this sweep
    does not plan (count, more_seeds, seeds), said in the summary."""
    out = Path(out_dir)
    rows = run_rows(records)
    keys = param_keys(records)
    columns = [*RUN_COLUMNS[:3], *keys, *RUN_COLUMNS[3:]]
    _write_csv(out / "results.csv", rows, columns)
    written = ["results.csv"]
    if _write_parquet(out / "results.parquet", rows, columns):
        written.append("results.parquet")
    arows = []
    for r in records:
        for a in r.get("arrivals") or []:
            row = {
                "run_id": r["run_id"],
                "cell_id": r["cell_id"],
                "scenario": r.get("scenario"),
                "seed": r.get("seed"),
                **(r.get("overrides") or {}),
            }
            row.update({k: a.get(k) for k in ARRIVAL_COLUMNS})
            arows.append(row)
    _write_csv(
        out / "arrivals.csv",
        arows,
        ["run_id", "cell_id", "scenario", *keys, "seed", *ARRIVAL_COLUMNS],
    )
    written.append("arrivals.csv")
    cells = cell_stats(records)
    drawn = _plots(cells, out) if figures else []
    for stale in set(FIGURES) - set(drawn):  # an earlier call's, of other runs
        with _report_file(out / stale):
            (out / stale).unlink(missing_ok=True)
    written += drawn
    if "older_files" not in result_info:
        older = out / OLDER_RUNS_DIR
        n_older = len(list(older.glob("*.json"))) if older.is_dir() else 0
        result_info = {**result_info, "older_files": n_older}
    notes = figure_plan(cells)[1] if figures else []
    text = markdown(result_info, cells, records, drawn, notes)
    with _report_file(out / "summary.md"):
        (out / "summary.md").write_text(text, encoding="utf-8")
    written.append("summary.md")
    return written
