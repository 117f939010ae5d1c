"""Peak memory and time of ``x6wd gap`` on the default path (``--real LOG --truth`` and no
``--sim``: the packaged open-field scenario's 20 seeds placed at the log) for one hour of a
static receiver at 20 Hz (72,000 epochs) and 10 Hz (36,000) and, for comparison, at 1 Hz
(issue 15 item 4: at most 500 MB peak for a 1 h log).

The 1 Hz log is an ``x6wd sim`` run of the open-field scenario. The simulated NEO-5 prints
at most 4 Hz (``[gnss] rate_hz`` 1..4), so the 20 and 10 Hz logs (a ZED-F9P's or M8's
rates) are written here: RMC and GGA at the open field's origin with a 2 m, 300 s
Gauss-Markov error and 0.3 m of white noise, at 5 decimals. Each ``x6wd gap`` runs in a
child process that reports its own peak resident set (VmHWM); the CPU and wall seconds are
printed without a target; the table's note says at which rate the log was read.
Measured 2026-12-04 (a shared 2-core machine): the audit's 1 h 10 Hz log peaked at 1.23 GB
before the Kalman likelihood was blocked in time and the time axis kept even, 551 MB after.
On this file's 10 Hz log, the same run: 534 MB with the simulator's receiver over all
36,000 epochs in one call, **298 MB** with it in chunks of at most 7,200 epochs (351 s wall,
193 s CPU); 1 h at 1 Hz 162 MB (docs/gap.md, "Memory of a long or high-rate log").
One hour at 20 Hz (72,000 epochs; the audit's generator, 2 seeds) then passed 1.1 GB and ran
past 9 minutes; since 2026-12-05 a log faster than 2 Hz is read at 2 Hz
(``x6wd.gap.rate``, the report's notes say so) and its runs simulated at that rate. Measured
then on this file's logs: **1 h at 20 Hz 211 MB** (0.42 of the limit, 36 s), 10 Hz 210 MB
(36 s), 1 Hz 156 MB (9 s).

    python -m bench.bench_gap_memory [--quick] [--rates 20,10,1]   (--quick: 15 min logs)
"""

from __future__ import annotations

import math
import os
import subprocess
import sys
import tempfile
import time
from datetime import UTC, datetime, timedelta
from pathlib import Path

import numpy as np

from bench._common import PEAK_CHILD, Row, cli, print_table

ROOT = Path(__file__).resolve().parent.parent
SCENARIOS = ROOT / "config" / "scenarios"
MB = 1e6
LIMIT_MB = 500.0
TRUTH = "51.752,-1.2577,60.0"  # open_field.toml's origin
RATES_HZ = (20.0, 10.0, 1.0)


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


def _nmea_deg(value_deg: float, hemi: str, width: int) -> str:
    a = abs(value_deg)
    d = int(a)
    return f"{d:0{width}d}{(a - d) * 60.0:08.5f},{hemi[int(value_deg < 0)]}"


def _synthetic_log(tmp: Path, rate_hz: float, duration_s: float) -> Path:
    """A static receiver's RMC + GGA at ``rate_hz`` (see the module docstring), seed 11."""
    from drivers.nmea import sentence
    from sim_backend.effects import metres_per_degree

    lat0, lon0 = (float(v) for v in TRUTH.split(",")[:2])
    n = round(duration_s * rate_hz)
    rng = np.random.default_rng(11)
    phi = math.exp(-1.0 / (rate_hz * 300.0))
    drive = rng.standard_normal((n, 2)) * 2.0 * math.sqrt(1.0 - phi * phi)
    gm = np.empty((n, 2))
    gm[0] = rng.standard_normal(2) * 2.0
    for k in range(1, n):  # 36,000 steps: the first-order recursion in plain Python is fine
        gm[k] = phi * gm[k - 1] + drive[k]
    err = gm + rng.standard_normal((n, 2)) * 0.3
    e_per, n_per = metres_per_degree(lat0)
    lines = []
    for k in range(n):
        t = datetime(2020, 1, 1, 12, tzinfo=UTC) + timedelta(seconds=k / rate_hz)
        hms = f"{t:%H%M%S}.{t.microsecond // 10000:02d}"
        lat = _nmea_deg(float(lat0 + err[k, 1] / n_per), "NS", 2)
        lon = _nmea_deg(float(lon0 + err[k, 0] / e_per), "EW", 3)
        lines.append(sentence(f"GPRMC,{hms},A,{lat},{lon},0.0,,010120,,,A"))
        lines.append(sentence(f"GPGGA,{hms},{lat},{lon},1,08,1.0,60.0,M,47.0,M,,"))
    path = tmp / f"synthetic_{rate_hz:g}hz.nmea"
    path.write_bytes(b"".join(lines))
    return path


def _log(tmp: Path, rate_hz: float, duration_s: float) -> Path:
    """A static open-field log of ``duration_s`` at ``rate_hz`` (x6wd sim, seed 11)."""
    if rate_hz > 4.0:
        return _synthetic_log(tmp, rate_hz, duration_s)
    scenario = tmp / f"open_field_{rate_hz:g}hz.toml"
    scenario.write_text(
        f'include = ["{SCENARIOS / "open_field.toml"}"]\n[gnss]\nrate_hz = {rate_hz}\n'
    )
    out = tmp / f"sim_{rate_hz:g}hz"
    _child(["sim", str(scenario), "--duration", str(duration_s), "--seed", "11", "--quiet",
            "--out", str(out)], tmp / "sim.hwm")  # fmt: skip
    return out / "gps.nmea"


def run(quick: bool = False, rates_hz: tuple[float, ...] = RATES_HZ) -> list[Row]:
    duration_s = 900.0 if quick else 3600.0
    label = f"{duration_s / 60:g} min" if quick else "1 h"
    rows: list[Row] = []
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        for rate_hz in rates_hz:
            log = _log(tmp, rate_hz, duration_s)
            out = tmp / f"gap_{rate_hz:g}hz"
            res = _child(["gap", "--real", str(log), "--truth", TRUTH, "--no-figures", "--quiet",
                          "--out", str(out)], tmp / "gap.hwm")  # fmt: skip
            case = f"x6wd gap default path, {label} at {rate_hz:g} Hz"
            read_at = next((ln for ln in (out / "report.md").read_text().splitlines()
                            if ln.startswith("- note: the log was read at")), None)  # fmt: skip
            how = "read as it is" if read_at is None else read_at[len("- note: ") :].split(" (")[0]
            rows.append(Row("gap_memory", f"peak memory: {case}", res["rss_b"] / MB, "MB",
                            LIMIT_MB, "MB limit",
                            f"the process's peak resident set; {how}"))  # fmt: skip
            rows.append(Row("gap_memory", f"time: {case}", res["cpu_s"], "s CPU", None, "",
                            f"{res['wall_s']:.0f} s wall"))  # fmt: skip
    return rows


if __name__ == "__main__":
    parser = cli(__doc__)
    parser.add_argument(
        "--rates",
        type=lambda text: tuple(float(r) for r in text.split(",")),
        default=RATES_HZ,
        help="log rates to measure, Hz, comma-separated (default: %(default)s)",
    )
    args = parser.parse_args()
    print_table(run(quick=args.quick, rates_hz=args.rates))
