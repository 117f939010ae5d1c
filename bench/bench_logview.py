"""The log viewer's memory (found by an outside audit): ``x6wd plot`` and ``render_html``
(the web console's page of a recording, in the daemon) on a long recording.

A 10 h static robot-engine run (``x6wd sim open_field.toml --engine robot``: a 190 MB
recording of 760,000 records and a 180,000-row truth.csv) is drawn by one child process per
case, its peak resident memory its own ``VmHWM``, its time its CPU s (from ``wait4``):

- ``x6wd plot REC --format html``: the page alone, what ``render_html`` does (load, then
  the page); <= 150 MB;
- ``x6wd plot REC``: the page and the PNG (matplotlib); <= 150 MB;
- both on a 1 h run of the same scenario: the reader keeps a bounded sample of each series
  (``logview.SAMPLE_ROWS`` rows), so ten times the recording must not be ten times the
  memory: the ratio of the 10 h peak to the 1 h peak is reported (anchor 1.5).

``--quick``: 1 h and 2 h runs. Run: ``python -m bench.bench_logview [--quick]``.

Measured 2026-12-04 on the fix (10 h): html 70 MB, html + PNG 113 MB (before it, as each
record was kept until the end: 409 MB and 427 MB).
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
from pathlib import Path

from bench._common import PEAK_CHILD, Row, cli, print_table

ROOT = Path(__file__).resolve().parent.parent
SCENARIO = ROOT / "config" / "scenarios" / "open_field.toml"
MB = 1e6


def _x6wd(out: Path, *args: str) -> tuple[float, float]:
    """One ``x6wd ARGS`` child process: its peak resident memory (bytes) and CPU s."""
    hwm = out.with_suffix(".hwm")
    proc = subprocess.Popen(
        [sys.executable, "-c", PEAK_CHILD, str(hwm), *args],
        cwd=ROOT,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    _pid, status, ru = os.wait4(proc.pid, 0)
    if os.waitstatus_to_exitcode(status) != 0:
        raise RuntimeError(f"x6wd {' '.join(args)} failed")
    return float(hwm.read_text()), ru.ru_utime + ru.ru_stime


def _recording(tmp: Path, duration_s: float) -> Path:
    """A static robot-engine run of ``duration_s`` s; its recording.jsonl."""
    out = tmp / f"run{duration_s:g}"
    args = ["sim", str(SCENARIO), "--engine", "robot", "--duration", f"{duration_s:g}"]
    _x6wd(out, *args, "--out", str(out), "--quiet")
    return out / "recording.jsonl"


def run(quick: bool = False) -> list[Row]:
    """Peaks of the page and the page + PNG on a short and a long run."""
    short_s, long_s = (3600.0, 7200.0) if quick else (3600.0, 36000.0)
    rows: list[Row] = []
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        peaks: dict[tuple[str, float], float] = {}
        for duration_s in (short_s, long_s):
            rec = _recording(tmp, duration_s)
            size_mb = rec.stat().st_size / MB
            for case, extra in (("page (render_html)", ["--format", "html"]), ("page + PNG", [])):
                out = tmp / f"plot{duration_s:g}{len(extra)}"
                rss_b, cpu_s = _x6wd(out, "plot", str(rec), "--out", str(out), *extra)
                peaks[case, duration_s] = rss_b / MB
                rows.append(Row("logview", f"peak memory: x6wd plot, {case}, "
                                f"{duration_s / 3600:g} h", rss_b / MB, "MB", 150.0, "MB limit",
                                f"{size_mb:.0f} MB recording; {cpu_s:.1f} s CPU"))  # fmt: skip
        for case in ("page (render_html)", "page + PNG"):
            growth = peaks[case, long_s] / peaks[case, short_s]
            rows.append(Row("logview", f"peak growth {long_s / short_s:g}x the recording: "
                            f"{case}", growth, "x", 1.5, "x limit",
                            "bounded: a sample of each series is kept"))  # fmt: skip
    return rows


if __name__ == "__main__":
    print_table(run(quick=cli(__doc__).parse_args().quick))
