"""``x6wd plot``: a recording or NMEA log drawn over time, as the log viewer's HTML page
(:mod:`x6wd.app.logview`, core install only: the web console serves it on the robot) and a
PNG (matplotlib, the ``plot`` extra). Kept apart from the viewer so the daemon, which imports
the viewer, never imports matplotlib."""

from __future__ import annotations

import argparse
import math
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from x6wd.app.logview import (
    COLORS,
    CUT_SHORT_NOTE,
    JUMP_COLOR,
    LOST_COUNTS,
    STATE_COLORS,
    TITLES,
    LogView,
    Series,
    TimeJump,
    broken_at,
    fault_lanes,
    gaps_note,
    html_page,
    in_progress_note,
    jumps_note,
    line_cuts,
    load,
    missing_parts_note,
    newest_recording,
)
from x6wd.core.errors import ConfigError
from x6wd.core.outdir import output_dir, output_file, write_output_file

# ---------------------------------------------------------------------------- PNG


def render_png(view: LogView, out_png: Path) -> None:
    """The panels as one PNG with matplotlib (the ``plot`` extra)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = ["error", "hdop", "satellites", "heading", "timeline"]
    fig = plt.figure(figsize=(11, 16), dpi=100)
    gs = fig.add_gridspec(len(rows) + 1, 1, height_ratios=[3.2] + [1] * (len(rows) - 1) + [1.4])
    ax_map = fig.add_subplot(gs[0])
    styles = {
        "true track": ("#2ca02c", "-"),
        "GPS fixes": ("#d62728", "."),
        "position estimate": ("#1f77b4", "-"),
    }
    for label, (e, n) in view.track.items():
        color, ls = styles.get(label, ("#555", "-"))
        if ls == ".":
            ax_map.plot(e, n, ".", ms=3, color=color, label=label)
        else:
            ax_map.plot(e, n, ls, lw=1.2, color=color, label=label)
    ax_map.set_aspect("equal", adjustable="datalim")
    ax_map.set_xlabel("east (m)")
    ax_map.set_ylabel("north (m)")
    ax_map.set_title(f"{view.path.name}: {TITLES['track']}", fontsize=10)
    if view.track:
        ax_map.legend(fontsize=8, loc="best")
    else:
        _missing(ax_map, view.missing.get("track", ""))
    ax_map.grid(alpha=0.3)
    t_min, t_max = view.time_range()
    t_len = t_max - t_min
    cuts = [j.t_s for j in view.jumps]
    first = None
    for k, (pid, series, ylabel) in enumerate(
        (
            ("error", view.error, "error (m)"),
            ("hdop", view.hdop, "HDOP"),
            ("satellites", view.satellites, "satellites"),
            ("heading", view.heading, "degrees"),
        )
    ):
        ax = fig.add_subplot(gs[k + 1], sharex=first)
        first = first or ax
        ax.set_title(TITLES[pid], fontsize=10, loc="left")
        ax.set_ylabel(ylabel)
        ax.grid(alpha=0.3)
        if plot_series(ax, series, view.jumps, dots=pid == "heading"):
            ax.legend(fontsize=8, loc="upper right")
            if pid == "heading":
                ax.set_ylim(0, 360)
                ax.set_yticks([0, 90, 180, 270, 360])
        else:
            _missing(ax, view.missing.get(pid, "nothing in the log"))
        _jump_lines(ax, view, label=k == 0)
        ax.set_xlim(t_min, t_max)
    ax = fig.add_subplot(gs[len(rows)], sharex=first)
    lanes = [("mode", view.states), ("navigation", view.states), ("hold", view.holds)] + [
        (d, view.faults) for d in fault_lanes(view)
    ]
    palette: dict[str, str] = {}
    for k, (lane, ivs) in enumerate(lanes):
        y = len(lanes) - 1 - k
        for iv in (i for i in ivs if i.lane == lane):
            color = palette.setdefault(
                iv.label,
                STATE_COLORS.get(iv.label)
                or COLORS[sum(1 for p in palette if p not in STATE_COLORS) % len(COLORS)],
            )
            ax.broken_barh(
                [(iv.t0_s, max(iv.t1_s - iv.t0_s, t_len / 800))], (y + 0.1, 0.8), color=color
            )
            if (iv.t1_s - iv.t0_s) > t_len * len(iv.label) / 150:
                ax.text(iv.t0_s, y + 0.5, " " + iv.label, va="center", fontsize=7, clip_on=True)
    ax.set_yticks([len(lanes) - 1 - k + 0.5 for k in range(len(lanes))])
    ax.set_yticklabels(
        [lane if lane in ("mode", "navigation", "hold") else f"{lane} fault" for lane, _ in lanes],
        fontsize=8,
    )
    ax.set_ylim(0, len(lanes))
    _jump_lines(ax, view, label=False)
    ax.set_xlim(t_min, t_max)
    ax.set_xlabel(
        "time since the start of the log (s)"
        + (", its segments in file order (dashed: the log's time jumped)" if cuts else "")
    )
    ax.set_title("Mode, navigation state, holds and device faults", fontsize=10, loc="left")
    if not (view.states or view.holds or view.faults):
        _missing(ax, view.missing.get("states", "nothing in the log"))
    else:  # a key: a short interval has no room for its own label
        from matplotlib.patches import Patch

        ax.legend(
            handles=[Patch(color=c, label=label) for label, c in palette.items()],
            loc="upper left", bbox_to_anchor=(0.0, -0.32), ncol=min(6, len(palette)),
            fontsize=7, frameon=False,
        )  # fmt: skip
    fig.tight_layout()
    fig.savefig(out_png)
    plt.close(fig)


def plot_series(ax: Any, series: Sequence[Series], jumps: Sequence[TimeJump], dots: bool) -> bool:
    """``series`` drawn on matplotlib axes ``ax`` (``dots``: as points), each line broken at
    the log's time ``jumps`` and at its own holes (:func:`x6wd.app.logview.line_cuts`); False
    when none has a value to draw."""
    drew = False
    for i, s in enumerate(series):
        if np.any(np.isfinite(s.v)):
            t, v = broken_at(s.t_s, s.v, line_cuts(s.t_s, jumps))
            color = COLORS[i % len(COLORS)]
            ax.plot(t, v, "." if dots else "-", ms=2, lw=1.1, color=color, label=s.label)
            drew = True
    return drew


def _jump_lines(ax: Any, view: LogView, *, label: bool) -> None:
    """A dashed line at each of the log's time jumps; ``label``: with its line number and
    step (not the ones too close to the last labelled to be read)."""
    lo, hi = view.time_range()
    labelled = -math.inf
    for j in view.jumps:
        ax.axvline(j.t_s, color=JUMP_COLOR, ls="--", lw=1.0)
        if label and j.t_s - labelled > (hi - lo) / 8:
            labelled = j.t_s
            way = "back" if j.step_s < 0 else "on"
            ax.text(
                j.t_s, 1.0, f" line {j.line}: time {way} {abs(j.step_s):.0f} s",
                transform=ax.get_xaxis_transform(), va="top", fontsize=7, color=JUMP_COLOR,
                clip_on=True,
            )  # fmt: skip


def _missing(ax: Any, why: str) -> None:
    ax.text(
        0.5,
        0.5,
        f"not shown: {why}",
        transform=ax.transAxes,
        ha="center",
        va="center",
        color="#888",
        fontsize=9,
        style="italic",
    )


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``x6wd plot``."""
    parser.add_argument(
        "file",
        metavar="RECORDING",
        help="a flight recording (.jsonl, with its parts) or NMEA log; a folder: its newest"
        " recording (the daemon's [recorder] dir)",
    )
    parser.add_argument(
        "--out",
        default=".",
        help="directory for <name>.png and <name>.html (default: the current directory)",
    )
    parser.add_argument(
        "--format",
        choices=("both", "png", "html"),
        default="both",
        help="what to write (html needs no plot extra; default both)",
    )
    parser.add_argument(
        "--truth", help="a true track CSV t_s,lat,lon (default: truth.csv next to the recording)"
    )
    parser.add_argument(
        "--rate",
        type=float,
        default=1.0,
        help="epochs per second for NMEA logs without sentence times (default 1)",
    )


def main(args: argparse.Namespace) -> int:
    """Entry point of ``x6wd plot``; 0 on success (errors raise X6wdError -> exit 2)."""
    if args.format != "html":
        import matplotlib  # noqa: F401  (missing: the plot extra's message, exit 2)
    if not (math.isfinite(args.rate) and args.rate > 0):
        raise ConfigError(f"--rate must be > 0, got {args.rate}")
    src = newest_recording(Path(args.file)) if Path(args.file).is_dir() else Path(args.file)
    view = load(src, truth=Path(args.truth) if args.truth else None, rate_hz=args.rate)
    out = output_dir(args.out)
    stem = src.stem
    written = []
    if args.format in ("both", "html"):
        # a page cut short by a full disk is removed, not left as the result
        written.append(write_output_file(out / f"{stem}.html", html_page(view)))
    if args.format in ("both", "png"):
        p = out / f"{stem}.png"
        with output_file(p):
            render_png(view, p)
        written.append(p)
    for p in written:
        print(p)
    for pid, why in view.missing.items():
        print(f"x6wd plot: the {pid} panel is empty: {why}", file=sys.stderr)
    if view.jumps:
        print(f"x6wd plot: {src}: the log's time jumps: {jumps_note(view)}", file=sys.stderr)
    if view.gaps:  # the recorder lost records there: nothing of that time is in the file
        print(f"x6wd plot: {src}: recording gaps: {gaps_note(view)}", file=sys.stderr)
    if view.missing_parts:  # retention deleted them: the run's start may not be drawn
        print(f"x6wd plot: {src}: {missing_parts_note(view)}", file=sys.stderr)
    if view.cut_short:
        print(f"x6wd plot: {src}: {CUT_SHORT_NOTE}", file=sys.stderr)
    elif view.writer is not None:
        print(f"x6wd plot: {src}: {in_progress_note(view)}", file=sys.stderr)
    if n := view.counts.get("records_with_unknown_fields"):
        print(
            f"x6wd plot: {src}: {n} records with fields this version does not know"
            " (a newer recorder's?): drawn without those fields",
            file=sys.stderr,
        )
    lost = {k: v for k, v in view.counts.items() if k in LOST_COUNTS and v}
    if lost:  # what was skipped is on the page too; say it where the command ran
        text = ", ".join(f"{v} {k.replace('_', ' ')}" for k, v in lost.items())
        print(f"x6wd plot: {src}: skipped {text}", file=sys.stderr)
    return 0
