"""Shutdown with the robot MOVING: a stop reaches the motors within 50 ms of SIGTERM or of an
unexpected exception, and kill -9 loses at most one record of the recording.

A check on a robot that never moved passes with the motor stop removed; every test here
first drives the motors and then looks for the stop command itself, in time.
"""

from __future__ import annotations

import dataclasses
import logging
import re
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

from drivers import registry
from drivers.motors import LogMotorLink, MotorBoard
from tests.conftest import ROOT
from tests.test_daemon import hil_config, run_daemon, wait_for
from tests.test_startup import write_config
from x6wd.app.client import RemoteClient
from x6wd.app.daemon import Daemon, stop_signals
from x6wd.core.recorder import ReadStats, read_recording_parts
from x6wd.core.records import Attitude, MotorCommand

__all__ = ["run_daemon"]  # the fixture, shared with test_daemon

STOP_DEADLINE_S = 0.050
"""The longest a stop may take to reach the motors after SIGTERM or an unexpected error."""


class StampedLink(LogMotorLink):
    """A ``log://`` motor link that keeps each command with the monotonic time (s) it
    reached the link."""

    def __init__(self) -> None:
        quiet = logging.getLogger("tests.motors")
        quiet.setLevel(logging.WARNING)  # the keep-alive would log 6 lines a second
        super().__init__(logger=quiet)
        self.stamped: list[tuple[float, MotorCommand]] = []

    def _keep(self, cmd: MotorCommand) -> bool:
        self.stamped.append((time.monotonic(), cmd))
        return super()._keep(cmd)

    def driving(self, left: float, right: float) -> bool:
        return bool(self.stamped) and (
            self.stamped[-1][1].left_pct,
            self.stamped[-1][1].right_pct,
        ) == (left, right)

    def first_stop_after(self, t0: float) -> float | None:
        return next((t for t, c in self.stamped if t >= t0 and c.is_stop), None)


@pytest.fixture
def stamped(monkeypatch: pytest.MonkeyPatch) -> StampedLink:
    """The :class:`StampedLink` every daemon of the test gets as its motor link (other test
    files import this fixture)."""
    link = StampedLink()
    monkeypatch.setattr(registry, "open_motors", lambda url, devices=None, **_kw: link)
    return link


@pytest.fixture
def fresh_stamped(monkeypatch: pytest.MonkeyPatch) -> Callable[[], StampedLink]:
    """A fresh :class:`StampedLink` for the next daemon each call (its motor link)."""

    def fresh() -> StampedLink:
        link = StampedLink()
        monkeypatch.setattr(registry, "open_motors", lambda url, devices=None, **_kw: link)
        return link

    return fresh


def log_motors_config(tmp_path: Path) -> Any:
    cfg = hil_config(tmp_path)
    return dataclasses.replace(cfg, motors=dataclasses.replace(cfg.motors, url="log://"))


def best_of_three(tmp_path: Path, stop_latency_s: Callable[[Path], float]) -> None:
    """A latency on a shared machine: a run the scheduler starves may take longer (a loaded
    2-core CI measured 77-280 ms against the usual 0.3 ms), so a slow run is repeated (up
    to three in all, each a fresh daemon in its own folder) and the best must meet the
    deadline. A stop path that is slow by design fails every run."""
    latencies_s: list[float] = []
    for i in range(3):
        run_dir = tmp_path / f"run{i}"
        run_dir.mkdir()
        latencies_s.append(stop_latency_s(run_dir))
        if min(latencies_s) < STOP_DEADLINE_S:
            break
    assert min(latencies_s) < STOP_DEADLINE_S, [
        f"stop after {1000 * t:.1f} ms" for t in latencies_s
    ]


def test_stop_request_while_driving_stops_the_motors_within_50_ms(
    tmp_path: Path, run_daemon, fresh_stamped: Callable[[], StampedLink]
) -> None:
    def stop_latency_s(run_dir: Path) -> float:
        link = fresh_stamped()
        r = run_daemon(Daemon(log_motors_config(run_dir)))
        with RemoteClient("127.0.0.1", r.port) as c:  # open: the robot stops a drive left alone
            c.request("drive", left=40, right=40, duration_s=5)
            wait_for(lambda: link.driving(40.0, 40.0), 3, "motors driven")
            time.sleep(0.2)  # keep-alives flowing: the stop must not be the controller's own
            assert link.driving(40.0, 40.0)
            t0 = time.monotonic()
            r.loop.call_soon_threadsafe(r.daemon.request_stop)  # what the SIGTERM handler does
            r.thread.join(10)
        assert r.code == 0
        t_stop = link.first_stop_after(t0)
        assert t_stop is not None, "no stop reached the motors"
        assert link.stamped[-1][1].is_stop
        return t_stop - t0

    best_of_three(tmp_path, stop_latency_s)


class ExplodingDaemon(Daemon):
    """Fault injection: once armed, the next compass sample hits a bug on the event loop."""

    t_boom: float | None = None
    armed = False

    def _on_attitude(self, att: Attitude) -> None:
        if self.armed and self.t_boom is None:
            self.t_boom = time.monotonic()
            raise RuntimeError("injected bug")
        super()._on_attitude(att)


def test_unexpected_exception_while_driving_stops_the_motors_within_50_ms(
    tmp_path: Path, run_daemon, fresh_stamped: Callable[[], StampedLink]
) -> None:
    def stop_latency_s(run_dir: Path) -> float:
        link = fresh_stamped()
        d = ExplodingDaemon(log_motors_config(run_dir))
        r = run_daemon(d)
        with RemoteClient("127.0.0.1", r.port) as c:  # open: the robot stops a drive left alone
            c.request("drive", left=-30, right=30, duration_s=5)
            wait_for(lambda: link.driving(-30.0, 30.0), 3, "motors driven")
            d.armed = True
            r.thread.join(10)
        assert r.code == 1
        assert d.t_boom is not None
        t_stop = link.first_stop_after(d.t_boom)
        assert t_stop is not None, "no stop reached the motors"
        return t_stop - d.t_boom

    best_of_three(tmp_path, stop_latency_s)


# -- the real process, the real motor protocol -------------------------------------------


class TcpMotorBoard:
    """A docs/motors.md board on a TCP socket (what ser2net would expose): answers with
    :class:`MotorBoard` and keeps every received line with its arrival time (s, monotonic,
    the same clock as the daemon's)."""

    def __init__(self) -> None:
        self.sock = socket.create_server(("127.0.0.1", 0))
        self.port = self.sock.getsockname()[1]
        self.board = MotorBoard(watchdog_ms=500)
        self.deaf = False  # True: lines are still read (and kept), none is answered or obeyed
        self.lines: list[tuple[float, str]] = []
        self.closed = threading.Event()
        self.thread = threading.Thread(target=self._serve, daemon=True)
        self.thread.start()

    def _serve(self) -> None:
        conn, _ = self.sock.accept()
        buf = b""
        with conn:
            while True:
                try:
                    data = conn.recv(4096)
                except OSError:
                    break
                t = time.monotonic()
                if not data:
                    break
                buf += data
                *complete, buf = buf.split(b"\n")
                self.lines.extend((t, line.decode("ascii", "replace")) for line in complete)
                if self.deaf:
                    continue
                reply = self.board.feed(data, t)
                if reply:
                    conn.sendall(reply)
        self.closed.set()

    def saw(self, pattern: str) -> bool:
        return any(re.match(pattern, line) for _t, line in list(self.lines))

    def first_after(self, t0: float, pattern: str) -> float | None:
        return next(
            (t for t, line in list(self.lines) if t >= t0 and re.match(pattern, line)), None
        )

    def close(self) -> None:
        self.sock.close()


def default_signals() -> None:
    """In the child before exec: the default action for every signal the tests send (a
    background shell may have left SIGINT/SIGQUIT/SIGHUP ignored, which would hide the
    daemon's own handling, or its lack)."""
    for sig in stop_signals():
        signal.signal(sig, signal.SIG_DFL)


class DaemonProcess:
    """``python -m x6wd run --config FILE`` with its stderr read line by line."""

    def __init__(self, config: Path) -> None:
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "x6wd", "run", "--config", str(config)],
            stderr=subprocess.PIPE,
            text=True,
            cwd=ROOT,
            preexec_fn=default_signals,
        )
        self.lines: list[str] = []
        self.port: int | None = None
        self.ready = threading.Event()
        self.reader = threading.Thread(target=self._read, daemon=True)
        self.reader.start()
        if not self.ready.wait(30):
            self.proc.kill()
            raise AssertionError("daemon not ready:\n" + "\n".join(self.lines))

    def _read(self) -> None:
        assert self.proc.stderr is not None
        for line in self.proc.stderr:
            self.lines.append(line.rstrip("\n"))
            m = re.search(r"control server listening on [\d.]+:(\d+)", line)
            if m:
                self.port = int(m[1])
            if re.search(r"x6wd \S+ ready", line):
                self.ready.set()
        self.ready.set()

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
        self.proc.wait(10)
        self.reader.join(5)


@pytest.fixture
def board() -> Iterator[TcpMotorBoard]:
    b = TcpMotorBoard()
    yield b
    b.close()


@pytest.fixture
def daemon_process(tmp_path: Path, board: TcpMotorBoard) -> Iterator[DaemonProcess]:
    config = write_config(tmp_path, motors={"url": f"tcp://127.0.0.1:{board.port}?watchdog_ms=500"})
    p = DaemonProcess(config)
    yield p
    p.stop()


def drive_and_wait(p: DaemonProcess, board: TcpMotorBoard, left: int, right: int) -> RemoteClient:
    """Drive; the connection that drives, to be held open (the robot stops a drive whose
    client went away)."""
    assert p.port is not None
    c = RemoteClient("127.0.0.1", p.port)
    c.request("drive", left=left, right=right, duration_s=5)
    wait_for(lambda: board.saw(rf"M {left} {right} #"), 5, f"board driven at {left} {right}")
    return c


def _sigterm_stop_s(p: DaemonProcess, board: TcpMotorBoard) -> float:
    """Drive, SIGTERM the daemon: the time (s) from the signal to the board's S line, after
    checking the daemon exited 0, the board stopped and the log says so."""
    with drive_and_wait(p, board, 40, 40):
        time.sleep(0.2)  # keep-alives flowing
        assert (board.board.left_pct, board.board.right_pct) == (40, 40)
        t_sig = time.monotonic()
        p.proc.send_signal(signal.SIGTERM)
        assert p.proc.wait(15) == 0
    t_stop = board.first_after(t_sig, r"S #\d+$")
    assert t_stop is not None, f"no S line after SIGTERM: {board.lines[-5:]}"
    assert (board.board.left_pct, board.board.right_pct) == (0, 0)
    p.reader.join(5)
    assert any("x6wd stopped" in line for line in p.lines)
    return t_stop - t_sig


@pytest.mark.integration
def test_sigterm_while_driving_sends_S_to_the_board_within_50_ms(
    tmp_path: Path, daemon_process: DaemonProcess, board: TcpMotorBoard
) -> None:
    # A latency on a shared machine: a run the scheduler starves may take longer, so a slow
    # run is repeated (up to three in all, each a fresh daemon and board) and the best must
    # meet the deadline. A stop path that is slow by design fails every run.
    latencies_s = [_sigterm_stop_s(daemon_process, board)]
    for i in range(2):
        if min(latencies_s) < STOP_DEADLINE_S:
            break
        run_dir = tmp_path / f"again{i}"
        run_dir.mkdir()
        again_board = TcpMotorBoard()
        url = f"tcp://127.0.0.1:{again_board.port}?watchdog_ms=500"
        again = DaemonProcess(write_config(run_dir, motors={"url": url}))
        try:
            latencies_s.append(_sigterm_stop_s(again, again_board))
        finally:
            again.stop()
            again_board.close()
    assert min(latencies_s) < STOP_DEADLINE_S, [f"{1000 * t:.1f} ms" for t in latencies_s]


@pytest.mark.integration
def test_kill_9_loses_at_most_one_record(
    tmp_path: Path, daemon_process: DaemonProcess, board: TcpMotorBoard
) -> None:
    def recording_has(*types: str) -> bool:
        files = sorted((tmp_path / "rec").glob("x6wd-*.jsonl"))
        text = "".join(f.read_text(errors="replace") for f in files)
        return all(f'"type":"{t}"' in text for t in types)

    # the recorder busy with every kind of input when the kill comes
    wait_for(lambda: recording_has("nmea", "fix", "attitude"), 10, "inputs recorded")
    speeds = [10, 20, 30, 40, 50]
    # one connection: manual drive belongs to the client whose drive started it (another
    # connection's drive would be refused while this one's holds)
    driver = drive_and_wait(daemon_process, board, speeds[0], speeds[0])
    for v in speeds[1:]:
        driver.request("drive", left=v, right=v, duration_s=5)
        wait_for(lambda v=v: board.saw(rf"M {v} {v} #"), 5, f"board driven at {v} {v}")
    daemon_process.proc.send_signal(signal.SIGKILL)  # the moment the board acted on 50
    assert daemon_process.proc.wait(10) == -signal.SIGKILL
    driver.close()
    (first,) = sorted((tmp_path / "rec").glob("x6wd-*Z.jsonl"))
    stats = ReadStats()
    records = list(read_recording_parts(first, stats=stats))
    assert stats.bad_lines == 0 and stats.truncated <= 1
    assert {"nmea", "fix", "attitude", "telemetry", "motor"} <= {r.type for r in records}
    recorded = [int(r.data["left_pct"]) for r in records if r.type == "motor"]
    # every drive the board acted on is in the recording, except at most the last one
    missing = [v for v in speeds if v not in recorded]
    assert missing in ([], [speeds[-1]]), f"recorded {recorded}"
    assert stats.truncated + len(missing) <= 1
