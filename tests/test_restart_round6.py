"""Crash/restart audit 8c, round 6: what a restart makes of a disk the running daemon rides
out, a SIGTERM during a stalled loop, and the recording's holes.

Real parts: real `x6wd run` processes, real file systems (tmpfs mounts made read-only or
full: these tests need root and skip without it), real pipes and signals, the real
`x6wd plot` and `x6wd replay` commands on what the recorder wrote."""

from __future__ import annotations

import contextlib
import errno
import itertools
import json
import logging
import os
import re
import select
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from tests.conftest import ROOT
from tests.test_daemon import wait_for
from x6wd.app.client import RemoteClient
from x6wd.app.daemon import _NetThread, _RecorderWorker
from x6wd.app.logview import load
from x6wd.core.errors import DeviceUnavailable
from x6wd.core.recorder import Recorder

GAP_EVENT = "recording_gap"  # the recorder's gap event (x6wd.core.recorder.GAP_EVENT)

ROOT_ONLY = pytest.mark.skipif(os.geteuid() != 0, reason="mounts a tmpfs: needs root")


def config(tmp: Path, rec_dir: Path, **extra: dict[str, Any]) -> Path:
    sections: dict[str, dict[str, Any]] = {
        "gps": {"url": "sim://"},
        "compass": {"url": "sim://"},
        "motors": {"url": "sim://"},
        "server": {"port": 0},
        "gpsd": {"port": 0},
        "recorder": {"dir": str(rec_dir)},
        "sim": {"gps_rate_hz": 4.0, "gps_baud": 115200},
    }
    for name, table in extra.items():
        sections.setdefault(name, {}).update(table)
    text = "".join(
        f"[{name}]\n" + "".join(f"{k} = {json.dumps(v)}\n" for k, v in t.items())
        for name, t in sections.items()
    )
    path = tmp / "x6wd.toml"
    path.write_text(text, encoding="utf-8")
    return path


@contextlib.contextmanager
def tmpfs(where: Path, options: str) -> Iterator[Path]:
    where.mkdir(parents=True, exist_ok=True)
    subprocess.run(["mount", "-t", "tmpfs", "-o", options, "tmpfs", str(where)], check=True)
    try:
        yield where
    finally:
        subprocess.run(["umount", "-l", str(where)], check=False)


def remount(where: Path, mode: str) -> None:
    subprocess.run(["mount", "-o", f"remount,{mode}", str(where)], check=True)


class Proc:
    """`x6wd run` with its stderr in a file."""

    def __init__(self, cfg: Path, log: Path) -> None:
        self.log = log
        self._f = open(log, "w")  # noqa: SIM115
        self.p = subprocess.Popen(
            [sys.executable, "-m", "x6wd", "run", "--config", str(cfg)],
            stdout=subprocess.DEVNULL,
            stderr=self._f,
            cwd=ROOT,
        )

    def text(self) -> str:
        return self.log.read_text()

    def ready_port(self) -> int:
        def port() -> int | None:
            assert self.p.poll() is None, f"exit {self.p.returncode}: {self.text()}"
            m = re.search(r"control server listening on 127\.0\.0\.1:(\d+)", self.text())
            return int(m[1]) if m and " ready" in self.text() else None

        return wait_for(port, 20, "ready")

    def stop(self) -> int:
        if self.p.poll() is None:
            self.p.send_signal(signal.SIGTERM)
        try:
            return self.p.wait(15)
        finally:
            if self.p.poll() is None:
                self.p.kill()
                self.p.wait()
            self._f.close()


def recorder_status(port: int) -> dict[str, Any]:
    with RemoteClient("127.0.0.1", port) as c:
        st = c.request("status")
    return {"links": st["links"]["recorder"], **st["recorder"]}


def records(rec_dir: Path) -> list[dict[str, Any]]:
    (path,) = rec_dir.glob("x6wd-*.jsonl")
    return [json.loads(line) for line in path.read_text().splitlines()]


def fill_inodes(d: Path) -> list[Path]:
    """Files created in ``d`` until the file system has no inode left."""
    made = []
    for k in range(10_000):
        p = d / f"filler{k}"
        try:
            p.touch()
        except OSError as exc:
            assert exc.errno == errno.ENOSPC, exc
            return made
        made.append(p)
    raise AssertionError("no inode limit")


# -- 1. a read-only or full recording disk at start-up is a runtime fault, not exit 2 --------


@ROOT_ONLY
@pytest.mark.integration
@pytest.mark.parametrize("fault", ["read-only", "no inodes"])
def test_the_daemon_starts_on_a_read_only_or_full_recording_disk_and_records_once_it_can(
    tmp_path: Path, fault: str
) -> None:
    # after a reboot on an SD card remounted read-only, or full: the robot must have its
    # daemon (exit 2 is never restarted), the recorder failing until the disk takes files
    opts = "size=4m,nr_inodes=64" if fault == "no inodes" else "size=4m"
    with tmpfs(tmp_path / "disk", opts) as disk:
        rec = disk / "rec"
        rec.mkdir()
        fillers: list[Path] = []
        if fault == "read-only":
            remount(disk, "ro")
            said = "Read-only file system (EROFS)"
        else:
            fillers = fill_inodes(rec)
            said = "No space left on device (ENOSPC)"
        d = Proc(config(tmp_path, rec), tmp_path / "daemon.log")
        try:
            port = d.ready_port()
            lines = [ln for ln in d.text().splitlines() if "recorder.dir" in ln]
            assert len(lines) == 1, d.text()  # one line naming the dir and the errno
            assert lines[0].startswith("ERROR") and repr(str(rec)) in lines[0], lines[0]
            assert said in lines[0] and "may not" not in lines[0], lines[0]
            st = recorder_status(port)
            assert st["links"] == "failing" and st["state"] == "failing", st
            assert st["records_written"] == 0 and st["last_error"], st
            # the disk comes back: the recording begins, as after a failure at run time
            if fault == "read-only":
                remount(disk, "rw")
            else:
                for p in fillers[:8]:
                    p.unlink()
            wait_for(
                lambda: (s := recorder_status(port))["state"] == "ok" and s["records_written"],
                20,
                "the recorder to recover",
            )
            assert recorder_status(port)["links"] == "ok"
            assert d.text().count("recorder write failed") == 0, d.text()  # said once, above
        finally:
            code = d.stop()
        assert code == 0, d.text()
        recs = records(rec)
        gaps = [r for r in recs if r["type"] == "event" and r["data"]["event"] == GAP_EVENT]
        assert len(gaps) == 1 and gaps[0]["data"]["records_lost"] > 0, gaps
        assert recs[0]["data"].get("event") == GAP_EVENT  # the hole is the recording's start
        assert recs[-1]["data"].get("event") == "shutdown"
        view = load(next(rec.glob("x6wd-*.jsonl")))
        assert len(view.gaps) == 1 and view.cut_short is False


@ROOT_ONLY
@pytest.mark.integration
def test_a_recorder_dir_to_create_on_a_read_only_disk_stays_a_config_error_naming_the_errno(
    tmp_path: Path,
) -> None:
    with tmpfs(tmp_path / "disk", "size=1m,ro") as disk:
        proc = subprocess.run(
            [sys.executable, "-m", "x6wd", "run", "--config", str(config(tmp_path, disk / "rec"))],
            capture_output=True,
            text=True,
            timeout=30,
            cwd=ROOT,
        )
    assert proc.returncode == 2, proc.stderr
    (line,) = proc.stderr.splitlines()
    assert line.startswith("x6wd: recorder.dir:"), line
    # the real errno, not "this user may not" (root may; the file system is read-only)
    assert "Read-only file system (EROFS)" in line and "may not" not in line, line


@ROOT_ONLY
@pytest.mark.integration
def test_a_recorder_dir_this_user_may_not_write_stays_a_config_error_naming_the_errno() -> None:
    if shutil.which("setpriv") is None:
        pytest.skip("no setpriv to run as another user")
    tmp = Path(tempfile.mkdtemp(prefix="x6wd-r6-"))
    try:
        tmp.chmod(0o755)
        locked = tmp / "locked"
        locked.mkdir(mode=0o755)  # root's: user nobody may not write there
        cfg = config(tmp, locked)
        cfg.chmod(0o644)
        proc = subprocess.run(
            [
                *("setpriv", "--reuid=65534", "--regid=65534", "--clear-groups"),
                *(sys.executable, "-m", "x6wd", "run", "--config", str(cfg)),
            ],
            capture_output=True,
            text=True,
            timeout=30,
            cwd=ROOT,
            env={**os.environ, "PYTHONDONTWRITEBYTECODE": "1"},
        )
        assert proc.returncode == 2, proc.stderr
        (line,) = proc.stderr.splitlines()
        assert line.startswith("x6wd: recorder.dir:"), line
        assert f"this user may not write in {locked}" in line, line
        assert "Permission denied (EACCES)" in line, line
        assert list(locked.iterdir()) == []
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


# -- 2. a SIGTERM during a stalled loop is never lost -----------------------------------------


@pytest.mark.integration
def test_a_sigterm_while_the_loop_is_stalled_on_a_full_stderr_pipe_is_not_lost(
    tmp_path: Path,
) -> None:
    # the loop blocks writing a log line to a pipe nobody reads (a stalled journald) while
    # the device threads keep posting to it: asyncio's self-pipe fills (about 280 wake-ups,
    # 3 s of a 75 Hz compass and the 20 Hz encoders), where its signal handler wrote the
    # signal's number: the SIGTERM was dropped, and the daemon ran on once the pipe flowed
    cfg = config(tmp_path, tmp_path / "rec", compass={"rate_hz": 75.0})
    r, w = os.pipe()
    proc = subprocess.Popen(
        [sys.executable, "-m", "x6wd", "run", "--config", str(cfg)],
        stdout=subprocess.DEVNULL,
        stderr=w,
        cwd=ROOT,
    )
    err = bytearray()

    def read_until(pat: bytes, timeout_s: float) -> re.Match[bytes]:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            m = re.search(pat, err)
            if m:
                return m
            if select.select([r], [], [], 0.1)[0]:
                err.extend(os.read(r, 65536))
        raise AssertionError(f"no {pat!r} in: {err.decode(errors='replace')}")

    def drain() -> None:
        while chunk := os.read(r, 65536):
            err.extend(chunk)

    try:
        port = int(read_until(rb"control server listening on 127\.0\.0\.1:(\d+)", 20)[1])
        read_until(rb" ready\n", 20)
        time.sleep(1.0)  # device threads running
        # the pipe opened anew (its own file status flags: the daemon's end stays blocking)
        filler = os.open(f"/proc/self/fd/{w}", os.O_WRONLY | os.O_NONBLOCK)
        with contextlib.suppress(BlockingIOError):
            while True:  # the pipe full: the daemon's next log line blocks its writer
                os.write(filler, b"\n" * 4096)
        os.close(filler)
        with socket.create_connection(("127.0.0.1", port), timeout=2) as s:
            s.sendall(b'{"cmd": "stop"}\n')  # logged on the loop: "operator: stop"
            time.sleep(5.0)  # the loop stalled, the self-pipe filling up
            proc.send_signal(signal.SIGTERM)
            time.sleep(1.0)
            reader = threading.Thread(target=drain, daemon=True)
            reader.start()  # the pipe flows again
            code = proc.wait(15)  # the old daemon ran on: the SIGTERM was gone
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        os.close(w)
    reader.join(10)  # to the end of the daemon's stderr
    os.close(r)
    text = err.decode(errors="replace").replace("\n\n", "")
    assert code == 0, text
    assert "SIGTERM received" in text and "x6wd stopped" in text, text
    assert "signal wakeup fd" not in text, text


# -- 4. the recording shows its holes, and whether it was cut short ---------------------------


def plot_and_replay(path: Path, out: Path) -> tuple[str, str]:
    plot = subprocess.run(
        [sys.executable, "-m", "x6wd", "plot", str(path), "--out", str(out), "--format", "html"],
        capture_output=True,
        text=True,
        timeout=60,
        cwd=ROOT,
    )
    assert plot.returncode == 0, plot.stderr
    replay = subprocess.run(
        [sys.executable, "-m", "x6wd", "replay", "--speed", "0", str(path)],
        capture_output=True,
        text=True,
        timeout=60,
        cwd=ROOT,
    )
    assert replay.returncode == 0, replay.stderr
    return plot.stderr, replay.stderr


NMEA = "$GPGGA,120000.00,5145.12000,N,00115.46200,W,1,08,1.0,60.0,M,47.0,M,,*{:02X}"


def gga(k: int) -> str:
    body = NMEA.split("$")[1].split("*")[0].replace("120000.00", f"1200{k % 60:02d}.00")
    cs = 0
    for ch in body:
        cs ^= ord(ch)
    return f"${body}*{cs:02X}"


@ROOT_ONLY
@pytest.mark.integration
def test_a_recording_that_lost_records_on_a_full_disk_says_so_and_plot_and_replay_report_it(
    tmp_path: Path,
) -> None:
    with tmpfs(tmp_path / "disk", "size=256k") as disk:
        rec = Recorder(
            disk / "x6wd-20261205T000000Z.jsonl", reopen_backoff_s=(0.05, 0.1), gap_events=True
        )
        t = 100.0
        for k in range(20):
            rec.record_nmea(gga(k), t)
            t += 0.25
        filler = disk / "filler"
        fd = os.open(filler, os.O_WRONLY | os.O_CREAT)
        with contextlib.suppress(OSError):
            while True:
                os.write(fd, b"\0" * 4096)
        os.close(fd)
        lost_from = None  # the first record lost (a write may still fit its last page)
        for k in range(20, 60):  # the card is full: these are lost
            before = rec.records_lost
            with contextlib.suppress(DeviceUnavailable):
                rec.record_nmea(gga(k), t)
            if rec.records_lost > before and lost_from is None:
                lost_from = t
            t += 0.25
        lost = rec.records_lost
        assert lost_from is not None and lost >= 30, lost
        filler.unlink()
        time.sleep(0.15)  # the back-off
        back_at = t
        for k in range(60, 80):
            rec.record_nmea(gga(k), t)
            t += 0.25
        assert rec.records_lost == lost
        rec.close()
        path = rec.path
        lines = [json.loads(x) for x in path.read_text().splitlines() if x.endswith("}")]
        shutil.copy(path, tmp_path / path.name)
    path = tmp_path / path.name
    (gap,) = [x["data"] for x in lines if x["type"] == "event"]
    assert gap["event"] == GAP_EVENT and gap["records_lost"] == lost, gap
    assert gap["from_t_mono"] == lost_from and gap["to_t_mono"] == back_at, gap
    assert "No space left on device" in gap["error"], gap
    plot_err, replay_err = plot_and_replay(path, tmp_path / "plot")
    assert f"recording gaps: 1 gap, {lost} records lost" in plot_err, plot_err
    assert "no device faults" not in plot_err, plot_err
    assert f"1 recording gap: {lost} records lost" in replay_err, replay_err
    # no shutdown record at its end: cut short (a crash, kill -9, a power cut), one line each
    assert plot_err.count("cut short") == 1 and replay_err.count("cut short") == 1
    page = (tmp_path / "plot" / f"{path.stem}.html").read_text()
    assert "recording gaps (1)" in page and "cut short" in page
    data = json.loads(page.split('id="x6wd-logview-data">')[1].split("</script>")[0])
    assert data["recording_gaps"][0]["records_lost"] == lost and data["cut_short"] is True
    # the same run ended by the daemon's shutdown record: not cut short
    with open(path, "a") as f:
        shutdown = {"event": "shutdown", "cause": "signal SIGTERM", "exit_code": 0}
        f.write(json.dumps({"t_mono": t, "t_utc": "", "type": "event", "data": shutdown}) + "\n")
    plot_err, replay_err = plot_and_replay(path, tmp_path / "plot")
    assert "cut short" not in plot_err and "cut short" not in replay_err, (plot_err, replay_err)


def test_records_dropped_at_the_full_queue_of_a_stuck_writer_leave_a_gap_event(
    tmp_path: Path,
) -> None:
    # a hung disk (fsfreeze, a dead NFS mount): the writer stuck, the callers drop records at
    # the full queue; once it writes again the recording says how many it lost
    release = threading.Event()
    taken = threading.Event()

    class Stuck(Recorder):
        def record(self, *args: Any, **kw: Any) -> None:
            taken.set()
            release.wait(10)
            super().record(*args, **kw)

    rec = Stuck(tmp_path / "x6wd-20261205T000000Z.jsonl")
    worker = _RecorderWorker(rec, max_queued=10)
    try:
        worker.put_event("tick", 100.0, k=0)
        assert taken.wait(5)  # the writer stuck in its first record (else a slot frees late)
        for k in range(1, 40):
            worker.put_event("tick", 100.0 + k, k=k)
        assert worker.queue_dropped >= 29
        release.set()
        wait_for(lambda: worker._q.qsize() == 0 and worker._t_call is None, 10, "drained")
        time.sleep(0.1)
    finally:
        release.set()
        worker.close()
    events = [json.loads(x)["data"] for x in rec.path.read_text().splitlines()]
    gaps = [e for e in events if e["event"] == GAP_EVENT]
    assert len(gaps) == 1 and gaps[0]["records_lost"] == worker.queue_dropped, gaps
    assert "queue full" in gaps[0]["error"]


# -- 2b. a stalled network thread does not queue publications without bound ------------------


def test_a_stalled_network_loop_drops_publications_beyond_its_bound_but_no_state_change(
    caplog: pytest.LogCaptureFixture,
) -> None:
    # the network thread blocked (a log line to a stderr nobody reads) while the control
    # loop publishes at 60 a second: the queue grew for as long as the stall lasted
    net = _NetThread(max_queued=50)
    release = threading.Event()
    ran: list[str] = []
    try:
        net.call(release.wait, 10)  # the loop stalls
        for k in range(500):
            net.call(ran.append, f"event {k}", publication=True)
            if k % 100 == 0:
                net.call(ran.append, f"state {k}")  # a state change: always queued
        assert net.queued <= 50 + 5 and net.dropped >= 440, (net.queued, net.dropped)
        with caplog.at_level(logging.WARNING, logger="x6wd.app.daemon"):
            release.set()
            wait_for(lambda: net.queued == 0, 10, "the loop to catch up")
    finally:
        release.set()
        net.stop()
    assert [x for x in ran if x.startswith("state")] == [f"state {k}" for k in range(0, 500, 100)]
    assert len([x for x in ran if x.startswith("event")]) == 500 - net.dropped
    assert f"{net.dropped} publications dropped" in caplog.text


# -- review of 3e82ba3: a read-only disk hid what stays so; the queue's gap event in order ----


def run_once(cfg: Path, *pre: str, timeout_s: float = 25.0) -> tuple[int | None, str]:
    """`x6wd run` (after ``pre``, e.g. setpriv): its exit code, None when it was still running
    after ``timeout_s`` (it started: stopped here), and its stderr."""
    p = subprocess.Popen(
        [*pre, sys.executable, "-m", "x6wd", "run", "--config", str(cfg)],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
        cwd=ROOT,
        env={**os.environ, "PYTHONDONTWRITEBYTECODE": "1"},
    )
    try:
        _, err = p.communicate(timeout=timeout_s)
        return p.returncode, err
    except subprocess.TimeoutExpired:
        p.send_signal(signal.SIGTERM)
        try:
            _, err = p.communicate(timeout=15)
        except subprocess.TimeoutExpired:
            p.kill()
            _, err = p.communicate()
        return None, err


@ROOT_ONLY
@pytest.mark.integration
def test_a_user_without_permission_on_a_read_only_disk_stays_a_config_error() -> None:
    # the kernel says EROFS before EACCES: the daemon started without recording, and once
    # the disk was writable again the recorder failed with EACCES for good
    if shutil.which("setpriv") is None:
        pytest.skip("no setpriv to run as another user")
    tmp = Path(tempfile.mkdtemp(prefix="x6wd-r6-"))
    try:
        tmp.chmod(0o755)
        with tmpfs(tmp / "disk", "size=1m,mode=755") as disk:
            rec = disk / "rec"
            rec.mkdir(mode=0o755)  # root's: user nobody may not write there
            remount(disk, "ro")
            cfg = config(tmp, rec)
            cfg.chmod(0o644)
            pre = ("setpriv", "--reuid=65534", "--regid=65534", "--clear-groups")
            code, err = run_once(cfg, *pre)
        assert code == 2, err
        (line,) = err.splitlines()
        assert line.startswith("x6wd: recorder.dir:"), line
        assert f"this user may not write in {rec}" in line, line
        assert "Permission denied (EACCES)" in line and "(EROFS)" in line, line
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


@contextlib.contextmanager
def bind_read_only(source: Path, where: Path) -> Iterator[Path]:
    """``source`` bind-mounted on ``where``, the bind made read-only (its file system stays
    writable): what systemd's ProtectSystem=strict makes of a path."""
    where.mkdir(parents=True, exist_ok=True)
    subprocess.run(["mount", "--bind", str(source), str(where)], check=True)
    try:
        subprocess.run(["mount", "-o", "remount,bind,ro", str(where)], check=True)
        yield where
    finally:
        subprocess.run(["umount", "-l", str(where)], check=False)


@ROOT_ONLY
@pytest.mark.integration
def test_a_recorder_dir_on_a_read_only_bind_mount_is_a_config_error_naming_it(
    tmp_path: Path,
) -> None:
    # a recorder.dir outside /var/lib/x6wd under ProtectSystem=strict: read-only for good,
    # the daemon ran without recording; an SD card's file system remounted read-only stays
    # a runtime fault, also seen through a bind mount (a space in its name: \040)
    with tmpfs(tmp_path / "disk", "size=1m") as disk:
        (disk / "rec").mkdir()
        with bind_read_only(disk, tmp_path / "read only") as view:
            rec = view / "rec"
            code, err = run_once(config(tmp_path, rec))
            assert code == 2, err
            (line,) = err.splitlines()
            assert line.startswith(f"x6wd: recorder.dir: {str(rec)!r}:"), line
            assert "Read-only file system (EROFS)" in line, line
            assert f"read-only mount ({view}" in line and "may not" not in line, line
            assert "ProtectSystem=strict" in line and "/var/lib/x6wd" in line, line
            # the check itself: the file system read-only, the bind too: a runtime fault
            from x6wd.app.daemon import _dir_check

            assert _dir_check(disk / "rec") == ("", "")
            remount(disk, "ro")
            for d in (disk / "rec", rec):
                problem, fault = _dir_check(d)
                assert problem == "" and "Read-only file system (EROFS)" in fault, (d, problem)


def test_the_queue_gap_event_lands_in_order_and_names_the_lost_span(tmp_path: Path) -> None:
    # the writer stalled, records dropped at the full queue: the gap event was stamped
    # `now` and written once the queue was half drained, before the other half's older
    # records: t_mono stepped back by the stall (a time jump for x6wd plot)
    release = threading.Event()
    taken = threading.Event()

    class Stuck(Recorder):
        def record(self, *args: Any, **kw: Any) -> None:
            taken.set()
            release.wait(10)
            super().record(*args, **kw)

    rec = Stuck(tmp_path / "x6wd-20261205T000000Z.jsonl", gap_events=True)
    worker = _RecorderWorker(rec, max_queued=10)
    put: list[tuple[float, bool]] = []  # (t_mono, dropped)

    def put_one(k: int) -> None:
        t = time.monotonic()
        before = worker.queue_dropped
        worker.put_event("tick", t, k=k)
        put.append((t, worker.queue_dropped > before))

    try:
        put_one(0)
        assert taken.wait(5)  # the writer holds record 0: stuck
        for k in range(1, 41):
            put_one(k)
            time.sleep(0.002)
        time.sleep(0.3)  # the stall
        release.set()
        for k in range(41, 81):
            put_one(k)
            time.sleep(0.005)
    finally:
        release.set()
        assert worker.close(10)
    lost = [t for t, dropped in put if dropped]
    kept = [t for t, dropped in put if not dropped]
    assert len(lost) == worker.queue_dropped >= 25
    first_back = next(t for t, dropped in put if not dropped and t > lost[-1])
    recs = [json.loads(x) for x in rec.path.read_text().splitlines()]
    ts = [r["t_mono"] for r in recs]
    steps_back = [(a, b) for a, b in itertools.pairwise(ts) if b < a]
    assert not steps_back, steps_back
    (gap,) = [r for r in recs if r["data"]["event"] == GAP_EVENT]
    g = gap["data"]
    assert g["from_t_mono"] == lost[0] and g["to_t_mono"] == first_back, (g, lost, first_back)
    assert g["records_lost"] == len(lost) and "queue full" in g["error"], g
    assert gap["t_mono"] == first_back  # just before the first record queued again
    ticks = [r["t_mono"] for r in recs if r["data"]["event"] == "tick"]
    assert ticks == kept  # every record kept, in order, none of the span lost
    assert not [t for t in ticks if g["from_t_mono"] <= t < g["to_t_mono"]]


ACL_CHECK = """
import os, sys
from pathlib import Path
from x6wd.app.daemon import _dir_check
os.setegid(65534)
os.seteuid(65534)
print(repr(_dir_check(Path(sys.argv[1]))))
"""


@ROOT_ONLY
def test_a_full_disk_with_an_acl_granting_this_user_stays_a_runtime_fault(tmp_path: Path) -> None:
    """The mode bits say no (0700 root) but a POSIX ACL lets the user write: on a full disk
    (ENOSPC comes after the kernel's permission check, which passed) that is a disk fault,
    not "this user may not write" and exit 2 (a review)."""
    import shutil
    import tempfile

    top = Path(tempfile.mkdtemp(prefix="x6wd-acl-", dir="/tmp"))  # nobody may pass /tmp
    top.chmod(0o755)  # (pytest's tmp_path is root's alone)
    try:
        _acl_case(top)
    finally:
        shutil.rmtree(top, ignore_errors=True)


def _acl_case(top: Path) -> None:
    import struct

    with tmpfs(top / "disk", "size=64k,nr_inodes=3,mode=0755") as disk:
        d = disk / "rec"
        d.mkdir(mode=0o700)
        # user_obj rwx, user nobody rwx, group_obj ---, mask rwx, other ---
        entries = [(1, 7, 0xFFFFFFFF), (2, 7, 65534), (4, 0, 0xFFFFFFFF),
                   (0x10, 7, 0xFFFFFFFF), (0x20, 0, 0xFFFFFFFF)]  # fmt: skip
        blob = struct.pack("<I", 2) + b"".join(struct.pack("<HHI", *e) for e in entries)
        os.setxattr(d, "system.posix_acl_access", blob)
        with contextlib.suppress(OSError), open(disk / "ballast", "wb") as f:  # fill the disk
            while True:
                f.write(b"\0" * 4096)
                f.flush()
        out = subprocess.run(
            [sys.executable, "-c", ACL_CHECK, str(d)], capture_output=True, text=True,
            cwd=ROOT, timeout=60,
        )  # fmt: skip
        assert out.returncode == 0, out.stderr
        config_error, runtime = eval(out.stdout)
        assert config_error == "", config_error
        assert "No space left" in runtime or "ENOSPC" in runtime, runtime
