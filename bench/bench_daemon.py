"""Daemon benchmarks in hardware-in-the-loop (real time, real pty, real sockets).

1. Control latency: last byte of a GGA written to the pseudo-terminal -> the first motor
   command computed from that fix reaches the (simulated) motor board; median and p99 with
   0 and with 20 watching clients (12 on the control port, 8 on the gpsd port: the default
   limits allow 16 control sessions). Target p99 < 5 ms.
2. Daemon CPU at 1 Hz GPS, 20 Hz compass, 10 watching clients, in % of one core (the
   simulated world's own threads are subtracted, per-thread times from /proc).
3. Hostile swarm with the DEFAULT connection limits (16 sessions, 32 pending, 5 s auth
   deadline...) and a token file: 100 clients on both ports (never-authenticating idle
   sockets, garbage senders, 1 MB lines, never-reading watchers, slowloris, connect churn),
   each reconnecting when the daemon closes it, while a real operator authenticates, asks
   ``status`` every second and reconnects every 5 s. Reported against targets: operator
   success 100 %, reconnects 100 %, status latency, worst gap between motor commands at the
   motor board < 250 ms, GGA-to-motor-command p99 < 5 ms.

Clients run in a separate process so they do not compete with the daemon for the GIL (the
operator, one request a second, runs in this one).
Run: ``python -m bench.bench_daemon [--quick] [--only-hostile [--gc-freeze]]`` (``--help``).
"""

from __future__ import annotations

import argparse
import asyncio
import dataclasses
import gc
import json
import os
import secrets
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from bench._common import Row, print_table
from x6wd.app.client import ConnectionFailed, RemoteClient, RequestFailed
from x6wd.app.daemon import Daemon
from x6wd.core.config import Config, GpsdConfig, RecorderConfig, ServerConfig, SimConfig
from x6wd.core.errors import ProtocolError
from x6wd.core.records import GpsFix, MotorCommand

TARGET_P99_MS = 5.0
TARGET_MOTOR_GAP_MS = 250.0
TARGET_SUCCESS_PCT = 100.0
TARGET_STATUS_P99_MS = 100.0  # an operator's "immediate" answer
RECONNECT_EVERY_S = 5.0

# The hostile swarm: 100 connections, each slot reconnecting when the daemon closes it.
HOSTILE = {
    "idle": 25,  # control port: connect, never authenticate, never send
    "gpsd_idle": 10,
    "garbage": 10,  # random-byte lines as fast as the daemon reads them
    "big": 10,  # 1 MB lines
    "stuck": 5,  # control-port watchers (with the token) that never read
    "gpsd_stuck": 5,
    "slowloris": 8,  # a byte a second, never a newline
    "gpsd_slowloris": 7,
    "churn": 15,  # connect, close, connect...
    "gpsd_churn": 5,
}

# A self-contained client swarm (run with ``python -c``): argv[1] is a JSON spec with the
# ports, the token (or null), seconds to run, and how many connections of each role. A slot
# whose connection the daemon closes reconnects at once; at the end it prints per-role
# counts of connects, closes by the daemon, bytes sent and received.
SWARM = r"""
import collections, json, os, select, socket, sys, time
spec = json.loads(sys.argv[1])
ports = {"ctl": spec["port"], "gpsd": spec["gpsd_port"]}
t_end = time.monotonic() + spec["seconds"]
auth = b""
if spec.get("token"):
    auth = json.dumps({"id": 0, "cmd": "auth", "token": spec["token"]}).encode() + b"\n"
# payloads are built once and sent round-robin from an offset: the swarm shares the 2 cores
# with the daemon, and rebuilding them per try would measure the swarm, not the daemon
garbage = b"".join(os.urandom(200).replace(b"\n", b"x") + b"\n" for _ in range(64))
big = b'{"id":1,"cmd":"hello","pad":"' + b"z" * (1 << 20) + b'"}\n'
watch = b'{"id":1,"cmd":"watch","on":true}\n'
gwatch = b'?WATCH={"enable":true,"json":true};\n'
ROLES = {  # role: (port, first bytes, reads its socket, what it keeps doing)
    "watch": ("ctl", auth + watch, True, None),
    "stuck": ("ctl", auth + watch, False, None),
    "idle": ("ctl", b"", False, None),
    "garbage": ("ctl", b"", True, garbage),
    "big": ("ctl", b"", True, big),
    "slowloris": ("ctl", b"", False, "drip"),
    "churn": ("ctl", b"", False, "churn"),
    "gpsd_watch": ("gpsd", gwatch, True, None),
    "gpsd_stuck": ("gpsd", gwatch, False, None),
    "gpsd_idle": ("gpsd", b"", False, None),
    "gpsd_slowloris": ("gpsd", b"", False, "drip"),
    "gpsd_churn": ("gpsd", b"", False, "churn"),
}
stats = {k: collections.Counter() for k in ("connects", "connect_failed", "closed_by_daemon",
                                            "sent", "received")}
poller = select.poll()
by_fd = {}
class Slot:
    def __init__(self, role):
        self.role, self.sock, self.off, self.t_drip = role, None, 0, 0.0
slots = [Slot(r) for r, n in spec["roles"].items() for _ in range(n)]
def connect(sl):
    port, first, reads, _ = ROLES[sl.role]
    s = socket.socket()
    if not reads:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    s.settimeout(2.0)
    try:
        s.connect(("127.0.0.1", ports[port]))
        if first:
            s.sendall(first)
    except OSError:
        stats["connect_failed"][sl.role] += 1
        s.close()
        return
    s.setblocking(False)
    sl.sock, sl.off, sl.t_drip = s, 0, time.monotonic()
    by_fd[s.fileno()] = sl
    poller.register(s, (select.POLLIN if reads else 0) | select.POLLRDHUP)
    stats["connects"][sl.role] += 1
def close(sl, by_daemon=True):
    if sl.sock is None:
        return
    by_fd.pop(sl.sock.fileno(), None)
    poller.unregister(sl.sock)
    sl.sock.close()
    sl.sock = None
    if by_daemon:
        stats["closed_by_daemon"][sl.role] += 1
for sl in slots:
    connect(sl)
print("ready", flush=True)
while time.monotonic() < t_end:
    now = time.monotonic()
    for sl in slots:
        if sl.sock is None:
            connect(sl)
            continue
        what = ROLES[sl.role][3]
        try:
            if what == "churn":
                close(sl, by_daemon=False)
                connect(sl)
            elif what == "drip" and now - sl.t_drip >= 1.0:
                sl.sock.send(b"x")
                sl.t_drip = now
                stats["sent"][sl.role] += 1
            elif isinstance(what, bytes):
                n = sl.sock.send(memoryview(what)[sl.off : sl.off + 65536])
                sl.off = (sl.off + n) % len(what)
                stats["sent"][sl.role] += n
        except BlockingIOError:
            pass
        except OSError:
            close(sl)
    for fd, ev in poller.poll(10):
        sl = by_fd.get(fd)
        if sl is None:
            continue
        if ev & select.POLLIN:
            try:
                data = sl.sock.recv(65536)
            except BlockingIOError:
                continue
            except OSError:
                data = b""
            if data:
                stats["received"][sl.role] += len(data)
                continue
        close(sl)
print(json.dumps(stats), flush=True)
"""


def _config(tmp: str, gps_rate_hz: float, baud: int, token_file: str = "") -> Config:
    """The defaults, except what hardware in the loop needs: free ports, the simulated
    devices and world, a recording folder, and (optionally) a token file."""
    base = Config(
        server=ServerConfig(port=0, token_file=token_file),
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
        self.daemon = _Probe(cfg)
        self.daemon.fix_out = []
        self.gga_t: list[float] = []
        self.motor: list[tuple[float, MotorCommand]] = []
        self.ready = threading.Event()
        self.thread = threading.Thread(target=self._main, daemon=True)
        self.thread.start()
        if not self.ready.wait(20):
            raise RuntimeError("daemon did not start")
        w = self.daemon.devices.backend("sim")  # the world the daemon's sim:// devices share
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

    @property
    def gpsd_port(self) -> int:
        assert self.daemon.gpsd is not None
        return self.daemon.gpsd.port

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
        self.thread.join(20)  # the daemon closes its devices, the world with them


class _Swarm:
    """The client swarm in its own process (see :data:`SWARM`)."""

    def __init__(
        self, run: _Run, roles: dict[str, int], seconds: float, token: str | None = None
    ) -> None:
        spec = {
            "port": run.port,
            "gpsd_port": run.gpsd_port,
            "token": token,
            "seconds": seconds,
            "roles": roles,
        }
        self.proc = subprocess.Popen(
            [sys.executable, "-c", SWARM, json.dumps(spec)], stdout=subprocess.PIPE, text=True
        )
        assert self.proc.stdout is not None
        if self.proc.stdout.readline().strip() != "ready":
            raise RuntimeError("client swarm failed to start")

    def wait(self) -> dict[str, dict[str, int]]:
        """Wait for the end; per-role counters the swarm printed."""
        out, _ = self.proc.communicate(timeout=60)
        return json.loads(out.strip().splitlines()[-1])


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
    over = float(np.mean(lat > TARGET_P99_MS)) * 100.0  # steadier than a p99 of a few hundred
    rows.append(Row("daemon", f"latency p99 {label}", float(np.percentile(lat, 99)), "ms",
                    TARGET_P99_MS, "target p99",
                    f"max {lat.max():.2f} ms; {over:.1f} % over {TARGET_P99_MS:g} ms"))  # fmt: skip


def bench_latency(seconds: float, rows: list[Row]) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        for watchers in (0, 20):
            run = _Run(_config(tmp, 4.0, 115200))
            roles = {"watch": 12, "gpsd_watch": 8}
            swarm = _Swarm(run, roles, seconds + 2) if watchers else None
            time.sleep(1.0)
            n0 = len(run.gga_t)
            time.sleep(seconds)
            lat = run.latencies_ms()[n0:]
            if swarm is not None:
                swarm.wait()
            run.stop()
            label = "20 watchers (12 control, 8 gpsd)" if watchers else "0 watchers"
            _latency_rows(label, lat, rows)


def bench_cpu(seconds: float, rows: list[Row]) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        run = _Run(_config(tmp, 1.0, 9600))
        swarm = _Swarm(run, {"watch": 10}, seconds + 3)
        time.sleep(1.5)
        world_tids = {t.native_id for t in run.world._threads if t.native_id}
        all_tids = {int(t) for t in os.listdir("/proc/self/task")}
        c0, w0, t0 = _thread_cpu_s(all_tids), _thread_cpu_s(world_tids), time.monotonic()
        time.sleep(seconds)
        all_tids = {int(t) for t in os.listdir("/proc/self/task")}
        c1, w1, t1 = _thread_cpu_s(all_tids), _thread_cpu_s(world_tids), time.monotonic()
        swarm.wait()
        run.stop()
    pct = ((c1 - c0) - (w1 - w0)) / (t1 - t0) * 100.0
    world_pct = 100 * (w1 - w0) / (t1 - t0)
    note = f"world threads {world_pct:.1f} % excluded"
    rows.append(Row("daemon", "CPU 1 Hz GPS, 20 Hz compass, 10 watchers", pct, "% of a core",
                    None, "", note))  # fmt: skip


@dataclasses.dataclass
class _Operator:
    """What the operator saw: status round trips (ms) and failures, reconnects (connect,
    auth, status; ms) and failures, and the daemon's last server counters."""

    status_ms: list[float] = dataclasses.field(default_factory=list)
    status_failed: list[str] = dataclasses.field(default_factory=list)
    reconnect_ms: list[float] = dataclasses.field(default_factory=list)
    reconnect_failed: list[str] = dataclasses.field(default_factory=list)
    server: dict[str, Any] = dataclasses.field(default_factory=dict)


def _operate(port: int, token: str, seconds: float) -> _Operator:
    """A real operator for ``seconds``: authenticates on connecting, asks ``status`` every
    second, and drops its connection for a new one every RECONNECT_EVERY_S."""
    op = _Operator()
    errors = (ConnectionFailed, RequestFailed, ProtocolError, OSError)

    def connect() -> RemoteClient | None:
        t0 = time.monotonic()
        try:
            c = RemoteClient("127.0.0.1", port, token=token, timeout_s=5.0)
            c.request("status")
        except errors as exc:
            op.reconnect_failed.append(f"{type(exc).__name__}: {exc}")
            return None
        op.reconnect_ms.append((time.monotonic() - t0) * 1000.0)
        return c

    t_start = time.monotonic()
    t_end = t_start + seconds
    client = connect()
    op.reconnect_ms.clear()  # the first connection is not a reconnect
    op.reconnect_failed.clear()
    next_status, next_reconnect = t_start + 1.0, t_start + RECONNECT_EVERY_S
    while True:
        now = time.monotonic()
        if now >= t_end:
            break
        if now >= next_reconnect:
            if client is not None:
                client.close()
            client = connect()
            next_reconnect += RECONNECT_EVERY_S
        elif now >= next_status:
            next_status += 1.0
            t0 = time.monotonic()
            try:
                if client is None:
                    raise ConnectionFailed("not connected")
                reply = client.request("status")
                op.status_ms.append((time.monotonic() - t0) * 1000.0)
                op.server = reply.get("server", {})
            except errors as exc:
                op.status_failed.append(f"{type(exc).__name__}: {exc}")
                if client is not None:
                    client.close()
                client = connect()
        time.sleep(max(0.0, min(next_status, next_reconnect, t_end) - time.monotonic()))
    if client is not None:
        client.close()
    return op


def _pct(ok: int, failed: int) -> float:
    return 100.0 * ok / (ok + failed) if ok + failed else float("nan")


def bench_hostile(seconds: float, rows: list[Row], gc_freeze: bool = False) -> None:
    """The operator against 100 hostile clients, with the default connection limits.

    ``gc_freeze``: move everything alive once the daemon is up out of the collector's
    reach (``gc.freeze()``), as a daemon could do after start-up; connect churn allocates
    fast, and full collections of a large heap pause every thread (rows are labelled).
    """
    with tempfile.TemporaryDirectory() as tmp:
        token = secrets.token_urlsafe(24)
        token_file = Path(tmp) / "token"
        token_file.write_text(token + "\n")
        token_file.chmod(0o600)
        run = _Run(_config(tmp, 4.0, 115200, token_file=str(token_file)))
        if gc_freeze:
            gc.collect()
            gc.freeze()
        swarm = _Swarm(run, HOSTILE, seconds + 4, token=token)
        time.sleep(1.5)  # the swarm at full strength: pools full, evictions going on
        n0 = len(run.gga_t)
        t0 = time.monotonic()
        op = _operate(run.port, token, seconds)
        t1 = time.monotonic()
        lat = run.latencies_ms()[n0:]
        motor_t = [t for t, _ in list(run.motor) if t0 <= t <= t1]
        gpsd = run.daemon.gpsd
        gpsd_closed = dict(gpsd.closed_counts) if gpsd is not None else {}
        swarm_stats = swarm.wait()
        run.stop()
        if gc_freeze:
            gc.unfreeze()
    tag = "swarm (gc.freeze)" if gc_freeze else "swarm"
    gap_ms = float(np.diff([t0, *motor_t, t1]).max()) * 1000.0
    n_status, n_rec = len(op.status_ms), len(op.reconnect_ms)
    status = np.array(op.status_ms) if op.status_ms else np.array([float("nan")])
    rec = np.array(op.reconnect_ms) if op.reconnect_ms else np.array([float("nan")])
    failures = op.status_failed[:2]
    ok_pct = _pct(n_status, len(op.status_failed))
    rows.append(Row("daemon", f"{tag}: operator status answered", ok_pct, "%",
                    TARGET_SUCCESS_PCT, "target",
                    f"{n_status}/{n_status + len(op.status_failed)}"
                    + (f"; {failures}" if failures else "")))  # fmt: skip
    rows.append(Row("daemon", f"{tag}: operator reconnects admitted",
                    _pct(n_rec, len(op.reconnect_failed)), "%", TARGET_SUCCESS_PCT, "target",
                    f"{n_rec}/{n_rec + len(op.reconnect_failed)} (connect+auth+status); "
                    f"p50 {np.median(rec):.1f} ms, max {rec.max():.1f} ms"
                    + (f"; {op.reconnect_failed[:2]}" if op.reconnect_failed else "")))  # fmt: skip
    rows.append(Row("daemon", f"{tag}: status latency p50", float(np.median(status)), "ms",
                    TARGET_STATUS_P99_MS, "target p99", f"n={n_status}"))  # fmt: skip
    rows.append(Row("daemon", f"{tag}: status latency p99", float(np.percentile(status, 99)),
                    "ms", TARGET_STATUS_P99_MS, "target p99",
                    f"max {status.max():.1f} ms"))  # fmt: skip
    rows.append(Row("daemon", f"{tag}: worst gap between motor commands", gap_ms, "ms",
                    TARGET_MOTOR_GAP_MS, "target", f"{len(motor_t)} commands at the board "
                    f"in {t1 - t0:.0f} s"))  # fmt: skip
    _latency_rows(f"GGA->motor, {tag} of 100 hostile clients", lat, rows)
    conn = swarm_stats["connects"]
    closed = swarm_stats["closed_by_daemon"]
    ctl_closed = op.server.get("closed", {})
    note = (
        f"control: {op.server.get('clients')} sessions, {op.server.get('pending')} pending, "
        f"closed {ctl_closed}, auth_failed {op.server.get('auth_failed')}; gpsd closed "
        f"{gpsd_closed}"
    )
    rows.append(Row("daemon", f"{tag}: connections the daemon closed", sum(closed.values()),
                    "count", None, "", note))  # fmt: skip
    churn = conn.get("churn", 0) + conn.get("gpsd_churn", 0)
    note = f"{churn / (seconds + 4):.0f}/s of them churn; per role {conn}"
    rows.append(Row("daemon", f"{tag}: connects by the swarm", sum(conn.values()), "count",
                    None, "", note))  # fmt: skip


def run(quick: bool = False) -> list[Row]:
    """All three benchmarks; ``quick`` shortens every measurement window."""
    rows: list[Row] = []
    bench_latency(8.0 if quick else 30.0, rows)
    bench_cpu(5.0 if quick else 30.0, rows)
    bench_hostile(12.0 if quick else 60.0, rows)
    return rows


def main(argv: Sequence[str] | None = None) -> int:
    """Command line: run the benchmarks and print their table."""
    parser = argparse.ArgumentParser(
        prog="python -m bench.bench_daemon",
        description=__doc__.splitlines()[0],
        allow_abbrev=False,
    )
    parser.add_argument(
        "--quick",
        action="store_true",
        help="short measurement windows: latency 8 s, CPU 5 s, swarm 12 s (default 30, 30, 60 s)",
    )
    parser.add_argument(
        "--only-hostile",
        action="store_true",
        help="the hostile swarm alone (benchmark 3), not the latency and CPU ones",
    )
    parser.add_argument(
        "--gc-freeze",
        action="store_true",
        help="with --only-hostile: gc.freeze() once the daemon is up (rows labelled so)",
    )
    args = parser.parse_args(argv)
    if args.gc_freeze and not args.only_hostile:
        parser.error("--gc-freeze needs --only-hostile")
    if args.only_hostile:  # re-run the section issue 12 is about
        table: list[Row] = []
        bench_hostile(12.0 if args.quick else 60.0, table, args.gc_freeze)
        print_table(table)
    else:
        print_table(run(quick=args.quick))
    return 0


if __name__ == "__main__":
    sys.exit(main())
