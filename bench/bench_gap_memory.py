"""Peak memory and time of ``x6wd gap`` on the default path (``--real LOG --truth`` and no
``--sim``: the packaged open-field scenario's 20 seeds placed at the log) for one hour of a
static receiver at 10 Hz (36,000 epochs) and, for comparison, at 1 Hz (issue 15 item 4: at
most 500 MB peak for a 1 h log).

The logs are ``x6wd sim`` runs of the open-field scenario (its ``[gnss] rate_hz`` set to 10
for the 10 Hz one). Each ``x6wd gap`` runs in a child process that reports its own peak
resident set (VmHWM); the CPU and wall seconds are printed without a target.
Measured 2026-12-04 (a shared 2-core machine) on the audit's 1 h 10 Hz log: 1.23 GB before
the Kalman likelihood was blocked in time and the time axis kept even, 551 MB after; what is
left is the simulator's receiver run over all 36,000 epochs in one call (docs/gap.md,
"Memory of a long or high-rate log").

    python -m bench.bench_gap_memory [--quick]   (--quick: 15 min logs)
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from bench._common import PEAK_CHILD, Row, print_table

ROOT = Path(__file__).resolve().parent.parent
SCENARIOS = ROOT / "config" / "scenarios"
MB = 1e6
LIMIT_MB = 500.0
TRUTH = "51.752,-1.2577,60.0"  # open_field.toml's origin


def _child(args: list[str], hwm: Path) -> dict[str, float]:
    """One ``x6wd`` process: its CPU s, wall s and peak resident set (bytes)."""
    a = time.perf_counter()
    proc = subprocess.Popen([sys.executable, "-c", PEAK_CHILD, str(hwm), *args], cwd=ROOT,
                            stdout=subprocess.DEVNULL)  # fmt: skip
    _pid, status, ru = os.wait4(proc.pid, 0)
    wall_s = time.perf_counter() - a
    code = os.waitstatus_to_exitcode(status)
    if code != 0:
        raise RuntimeError(f"x6wd {' '.join(args)} exited {code}")
    return {"cpu_s": ru.ru_utime + ru.ru_stime, "wall_s": wall_s, "rss_b": float(hwm.read_text())}


def _log(tmp: Path, rate_hz: float, duration_s: float) -> Path:
    """A static open-field log of ``duration_s`` at ``rate_hz`` (x6wd sim, seed 11)."""
    scenario = tmp / f"open_field_{rate_hz:g}hz.toml"
    scenario.write_text(
        f'include = ["{SCENARIOS / "open_field.toml"}"]\n[gnss]\nrate_hz = {rate_hz}\n'
    )
    out = tmp / f"sim_{rate_hz:g}hz"
    _child(["sim", str(scenario), "--duration", str(duration_s), "--seed", "11", "--quiet",
            "--out", str(out)], tmp / "sim.hwm")  # fmt: skip
    return out / "gps.nmea"


def run(quick: bool = False) -> list[Row]:
    duration_s = 900.0 if quick else 3600.0
    label = f"{duration_s / 60:g} min" if quick else "1 h"
    rows: list[Row] = []
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        for rate_hz in (10.0, 1.0):
            log = _log(tmp, rate_hz, duration_s)
            res = _child(["gap", "--real", str(log), "--truth", TRUTH, "--no-figures", "--quiet",
                          "--out", str(tmp / f"gap_{rate_hz:g}hz")], tmp / "gap.hwm")  # fmt: skip
            case = f"x6wd gap default path, {label} at {rate_hz:g} Hz"
            rows.append(Row("gap_memory", f"peak memory: {case}", res["rss_b"] / MB, "MB",
                            LIMIT_MB, "MB limit", "the process's peak resident set"))  # fmt: skip
            rows.append(Row("gap_memory", f"time: {case}", res["cpu_s"], "s CPU", None, "",
                            f"{res['wall_s']:.0f} s wall"))  # fmt: skip
    return rows


if __name__ == "__main__":
    print_table(run(quick="--quick" in sys.argv))
