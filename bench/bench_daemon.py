"""Daemon benchmarks in hardware-in-the-loop (real time, real pty, real sockets).

1. Control latency: last byte of a GGA written to the pseudo-terminal -> the first motor
   command computed from that fix reaches the (simulated) motor board; median and p99 with
   0 and with 20 watching clients. Target p99 < 5 ms.
2. Daemon CPU at 1 Hz GPS, 20 Hz compass, 10 watching clients, in % of one core (the
   simulated world's own threads are subtracted, per-thread times from /proc).
3. Robustness: 100 concurrent clients (watchers, never-reading watchers, garbage senders,
   oversized-line senders) while one operator sends commands: latency stays in target and
   every command gets its reply.

Clients run in a separate process so they do not compete with the daemon for the GIL.
Run: ``python -m bench.bench_daemon [--quick]``.
"""

from __future__ import annotations

import asyncio
import dataclasses
import json
import os
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

from bench._common import Row, print_table
from sim_backend import hil
from x6wd.config import Config, GpsdConfig, RecorderConfig, ServerConfig, SimConfig
from x6wd.daemon import Daemon
from x6wd.records import GpsFix, MotorCommand

TARGET_P99_MS = 5.0

# A self-contained client swarm (run with ``python -c``): argv = port, then counts of
# watchers, stuck watchers, garbage senders, oversized senders, and seconds to run.
SWARM = r"""
import json, os, selectors, socket, sys, time
port = int(sys.argv[1]); n_watch, n_stuck, n_garbage, n_big = map(int, sys.argv[2:6])
t_end = time.monotonic() + float(sys.argv[6])
sel = selectors.DefaultSelector()
socks = []
def conn():
    s = socket.create_connection(("127.0.0.1", port)); socks.append(s); return s
for _ in range(n_watch):
    s = conn(); s.sendall(b'{"id":1,"cmd":"watch","on":true}\n'); s.setblocking(False)
    sel.register(s, selectors.EVENT_READ)
for _ in range(n_stuck):
    s = conn(); s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    s.sendall(b'{"id":1,"cmd":"watch","on":true}\n')
senders = []
# payloads are built once and sent round-robin from an offset: the swarm shares the 2 cores
# with the daemon, and rebuilding 300 kB per try would measure the swarm, not the daemon
garbage = b"".join(os.urandom(200).replace(b"\n", b"x") + b"\n" for _ in range(64))
big = b'{"id":1,"cmd":"hello","pad":"' + b"z" * 300000 + b'"}\n'
for i in range(n_garbage):
    senders.append([conn(), garbage, 0])
for i in range(n_big):
    senders.append([conn(), big, 0])
for s, _, _ in senders:
    s.setblocking(False)
print("ready", flush=True)
received = 0
while time.monotonic() < t_end:
    for key, _ in sel.select(0.05):
        try:
            received += len(key.fileobj.recv(65536))
        except BlockingIOError:
            pass
    for snd in senders:
        s, data, off = snd
        try:
            snd[2] = (off + s.send(memoryview(data)[off:])) % len(data)
        except (BlockingIOError, OSError):
            pass
        try:
            s.recv(65536)  # garbage senders read their error replies
        except (BlockingIOError, OSError):
            pass
    time.sleep(0.01)
print(json.dumps({"received": received}), flush=True)
"""


def _config(tmp: str, gps_rate_hz: float, baud: int, max_clients: int = 64) -> Config:
    base = Config(
        server=ServerConfig(port=0, max_clients=max_clients),
        gpsd=GpsdConfig(port=0),
        recorder=RecorderConfig(dir=tmp),
        sim=SimConfig(gps_rate_hz=gps_rate_hz, gps_baud=baud),
    )
    return dataclasses.replace(
        base,
        gps=dataclasses.replace(base.gps, url="sim://"),
        compass=dataclasses.replace(base.compass, url="sim://", rate_hz=20.0),
        motors=dataclasses.replace(base.motors, url="sim://"),
    )


class _Probe(Daemon):
    """Notes, for each fix, when the controller returned and the motor command it produced."""

    fix_out: list[tuple[float, MotorCommand]]

    def _on_gps_records(self, records: list[Any]) -> None:
        on_fix = self.controller.on_fix

        def timed(fix: GpsFix) -> list[Any]:
            outs = on_fix(fix)
            cmd = next(o for o in outs if isinstance(o, MotorCommand))
            self.fix_out.append((time.monotonic(), cmd))
            return outs

        self.controller.on_fix = timed
        try:
            super()._on_gps_records(records)
        finally:
            del self.controller.on_fix


class _Run:
    """The daemon in a thread with latency hooks on the world."""

    def __init__(self, cfg: Config) -> None:
        hil.shutdown()
        hil.configure(cfg.sim)
        self.daemon = _Probe(cfg)
        self.daemon.fix_out = []
        self.gga_t: list[float] = []
        self.motor: list[tuple[float, MotorCommand]] = []
        self.ready = threading.Event()
        self.thread = threading.Thread(target=self._main, daemon=True)
        self.thread.start()
        if not self.ready.wait(20):
            raise RuntimeError("daemon did not start")
        w = hil.world()
        w.on_gga = self.gga_t.append
        w.on_motor = self._motor
        self.world = w

    def _motor(self, cmd: MotorCommand, t: float) -> None:
        self.motor.append((t, cmd))

    def _main(self) -> None:
        async def go() -> int:
            self.loop = asyncio.get_running_loop()
            return await self.daemon.run(ready=lambda _d: self.ready.set())

        self.code = asyncio.run(go())

    @property
    def port(self) -> int:
        assert self.daemon.server is not None
        return self.daemon.server.port

    def latencies_ms(self) -> np.ndarray:
        """Per GGA: when the motor command computed from its fix reached the board (or, if
        a newer command replaced it before it was sent, that newer one), minus the GGA's
        write time."""
        gga = np.array(self.gga_t)
        fix_out = list(self.daemon.fix_out)
        done = np.array([t for t, _ in fix_out])
        motor = list(self.motor)
        sent_at = {id(cmd): t for t, cmd in motor}
        motor_t = np.array([t for t, _ in motor])
        out = []
        for t_g in gga:
            i = int(np.searchsorted(done, t_g))
            if i >= len(done) or done[i] - t_g > 0.5:
                continue  # that GGA's fix was not seen (should not happen)
            t_ret, cmd = fix_out[i]
            t_m = sent_at.get(id(cmd))
            if t_m is None:  # coalesced: the next command sent after it carries the fix
                j = int(np.searchsorted(motor_t, t_ret))
                if j >= len(motor_t):
                    continue
                t_m = float(motor_t[j])
            out.append((t_m - t_g) * 1000.0)
        return np.array(out)

    def stop(self) -> None:
        self.loop.call_soon_threadsafe(self.daemon.request_stop)
        self.thread.join(20)
        hil.shutdown()


def _swarm(port: int, counts: tuple[int, int, int, int], seconds: float) -> subprocess.Popen[str]:
    p = subprocess.Popen(
        [sys.executable, "-c", SWARM, str(port), *map(str, counts), str(seconds)],
        stdout=subprocess.PIPE,
        text=True,
    )
    assert p.stdout is not None
    if p.stdout.readline().strip() != "ready":
        raise RuntimeError("client swarm failed to start")
    return p


def _thread_cpu_s(tids: set[int]) -> float:
    tick = os.sysconf("SC_CLK_TCK")
    total = 0.0
    for tid in tids:
        try:
            fields = Path(f"/proc/self/task/{tid}/stat").read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        total += (int(fields[11]) + int(fields[12])) / tick  # utime, stime
    return total


def _latency_rows(label: str, lat: np.ndarray, rows: list[Row]) -> None:
    rows.append(Row("daemon", f"latency median {label}", float(np.median(lat)), "ms",
                    TARGET_P99_MS, "target p99", f"n={len(lat)}"))  # fmt: skip
    rows.append(Row("daemon", f"latency p99 {label}", float(np.percentile(lat, 99)), "ms",
                    TARGET_P99_MS, "target p99", f"max {lat.max():.2f} ms"))  # fmt: skip


def bench_latency(seconds: float, rows: list[Row]) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        for watchers in (0, 20):
            run = _Run(_config(tmp, 4.0, 115200))
            swarm = _swarm(run.port, (watchers, 0, 0, 0), seconds + 2) if watchers else None
            time.sleep(1.0)
            n0 = len(run.gga_t)
            time.sleep(seconds)
            lat = run.latencies_ms()[n0:]
            if swarm is not None:
                swarm.wait(30)
            run.stop()
            _latency_rows(f"{watchers} watchers", lat, rows)


def bench_cpu(seconds: float, rows: list[Row]) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        run = _Run(_config(tmp, 1.0, 9600))
        swarm = _swarm(run.port, (10, 0, 0, 0), seconds + 3)
        time.sleep(1.5)
        world_tids = {t.native_id for t in run.world._threads if t.native_id}
        all_tids = {int(t) for t in os.listdir("/proc/self/task")}
        c0, w0, t0 = _thread_cpu_s(all_tids), _thread_cpu_s(world_tids), time.monotonic()
        time.sleep(seconds)
        all_tids = {int(t) for t in os.listdir("/proc/self/task")}
        c1, w1, t1 = _thread_cpu_s(all_tids), _thread_cpu_s(world_tids), time.monotonic()
        swarm.wait(30)
        run.stop()
    pct = ((c1 - c0) - (w1 - w0)) / (t1 - t0) * 100.0
    world_pct = 100 * (w1 - w0) / (t1 - t0)
    note = f"world threads {world_pct:.1f} % excluded"
    rows.append(Row("daemon", "CPU 1 Hz GPS, 20 Hz compass, 10 watchers", pct, "% of a core",
                    None, "", note))  # fmt: skip


def bench_robustness(seconds: float, rows: list[Row]) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        run = _Run(_config(tmp, 4.0, 115200, max_clients=200))
        swarm = _swarm(run.port, (40, 20, 20, 20), seconds + 3)
        time.sleep(1.0)
        n0 = len(run.gga_t)
        sent = answered = 0
        with socket.create_connection(("127.0.0.1", run.port), timeout=10) as s:
            f = s.makefile("rb")
            t_end = time.monotonic() + seconds
            cmds: list[dict[str, Any]] = [
                {"cmd": "status"},
                {"cmd": "drive", "left": 10, "right": 10, "duration_s": 0.5},
                {"cmd": "stop"},
            ]
            while time.monotonic() < t_end:
                req = {"id": sent, **cmds[sent % len(cmds)]}
                s.sendall(json.dumps(req).encode() + b"\n")
                sent += 1
                while True:
                    msg = json.loads(f.readline())
                    if "event" not in msg:
                        break
                if msg.get("id") == req["id"] and msg.get("ok"):
                    answered += 1
                time.sleep(0.05)  # 20 commands/s, within the default rate limit
        lat = run.latencies_ms()[n0:]
        srv = run.daemon.server
        assert srv is not None
        clients, dropped, errors = srv.client_count, srv.dropped_total, srv.errors_total
        swarm.wait(30)
        run.stop()
    _latency_rows("100 hostile clients", lat, rows)
    note = (
        f"lost {sent - answered}; {clients} clients, {errors / seconds:.0f} error replies/s "
        f"to the hostile ones, {dropped} events dropped"
    )
    rows.append(Row("daemon", "commands answered ok", answered, "count", sent, "sent", note))


def run(quick: bool = False) -> list[Row]:
    """All three benchmarks; ``quick`` shortens every measurement window."""
    rows: list[Row] = []
    bench_latency(8.0 if quick else 30.0, rows)
    bench_cpu(5.0 if quick else 30.0, rows)
    bench_robustness(6.0 if quick else 40.0, rows)
    return rows


if __name__ == "__main__":
    print_table(run(quick="--quick" in sys.argv))
