"""The daemon under faults an outside audit found: signals other than SIGTERM, a dying motor
thread, a recorder stuck in the file system (a FIFO in place of its next part, as a hung SD
card or NFS mount), failing or removed recordings, and a bind address that is no address.

Real processes, a real motor protocol board on TCP, real files and a real FIFO."""

from __future__ import annotations

import contextlib
import logging
import os
import re
import signal
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any, cast

import pytest

from tests.test_daemon import run_daemon, wait_for
from tests.test_shutdown import (
    DaemonProcess,
    StampedLink,
    TcpMotorBoard,
    board,
    daemon_process,
    drive_and_wait,
    log_motors_config,
    stamped,
)
from tests.test_startup import assert_config_error, run_x6wd, write_config
from x6wd.app.client import RemoteClient
from x6wd.app.daemon import Daemon, _RecorderWorker
from x6wd.core.recorder import ReadStats, Record, Recorder, read_recording_parts

__all__ = ["board", "daemon_process", "run_daemon", "stamped"]  # the fixtures

# -- signals: every one that would kill the process stops the motors first -----------------


@pytest.mark.integration
@pytest.mark.parametrize(
    ("sig", "code"),
    [(signal.SIGHUP, 0), (signal.SIGUSR1, 1), (signal.SIGQUIT, 1)],
    ids=["HUP", "USR1", "QUIT"],
)
def test_a_signal_while_driving_stops_the_motors_and_exits_cleanly(
    tmp_path: Path,
    daemon_process: DaemonProcess,
    board: TcpMotorBoard,
    sig: signal.Signals,
    code: int,
) -> None:
    p = daemon_process
    with drive_and_wait(p, board, 40, 40):
        time.sleep(0.2)  # keep-alives flowing: the stop must be the daemon's exit
        t_sig = time.monotonic()
        p.proc.send_signal(sig)
        assert p.proc.wait(15) == code, "\n".join(p.lines[-5:])
    assert board.first_after(t_sig, r"S #\d+$") is not None, f"no S: {board.lines[-3:]}"
    assert (board.board.left_pct, board.board.right_pct) == (0, 0)
    p.reader.join(5)
    assert any(f"{sig.name} received" in line for line in p.lines), p.lines[-5:]
    assert any("x6wd stopped" in line for line in p.lines)
    # write_config's [recorder] dir
    assert_recording_ends_with_the_stop(
        tmp_path / "rec", f"shutdown ({sig.name})", code, said="\n".join(p.lines)
    )


# -- the recording ends with the stop: a clean exit is not a crash or a power cut ----------


def assert_recording_ends_with_the_stop(
    rec_dir: Path, reason: str, code: int, cause: str = "", said: str | None = None
) -> list[Record]:
    """The recording in ``rec_dir`` says how the daemon ended: after its last drive, a motor
    record 0/0 and the controller's change to IDLE, both with ``reason``; last of all a
    ``shutdown`` event with the exit ``code`` and a cause containing ``cause``.

    ``said``: what the daemon logged. A control lock held past SHUTDOWN_LOCK_S (0.2 s) at
    exit, which a loaded host gave a deciding thread once beside busy loops, records the
    stop alone, without the controller's IDLE (by design: test_a_control_lock_held_at_exit
    _does_not_keep_the_stop_out_of_the_recording); the daemon then says so, and only then
    is the IDLE record not required."""
    (first,) = sorted(rec_dir.glob("x6wd-*Z.jsonl"))
    stats = ReadStats()
    records = list(read_recording_parts(first, stats=stats))
    assert stats.bad_lines == 0 and stats.truncated == 0
    tail = [(r.type, r.data) for r in records[-8:]]
    end = records[-1]
    assert (end.type, end.data.get("event")) == ("event", "shutdown"), tail
    assert end.data["exit_code"] == code and end.data["reason"] == reason, end.data
    assert cause in end.data["cause"], end.data
    motors = [i for i, r in enumerate(records) if r.type == "motor"]
    drives = [i for i in motors if records[i].data["left_pct"] or records[i].data["right_pct"]]
    assert drives, "the robot never drove: the test proves nothing"
    stop = records[motors[-1]]
    assert motors[-1] > drives[-1], tail
    assert (stop.data["left_pct"], stop.data["right_pct"], stop.data["reason"]) == (0, 0, reason)
    idle = [
        r
        for r in records[drives[-1] :]
        if r.type == "state" and r.data["new"] == "IDLE" and reason in r.data["reason"]
    ]
    alone = said is not None and "at exit: stopping without the controller" in said
    assert idle or alone, tail
    return records


def test_a_stop_signal_ends_the_recording_with_the_stop_and_the_exit(
    tmp_path: Path, run_daemon, stamped: StampedLink, caplog: pytest.LogCaptureFixture
) -> None:
    r = run_daemon(Daemon(log_motors_config(tmp_path)))
    with RemoteClient("127.0.0.1", r.port) as c:
        c.request("drive", left=65, right=55, duration_s=5)
        wait_for(lambda: stamped.driving(65.0, 55.0), 3, "motors driven")
        time.sleep(0.3)  # fixes, samples and ticks recorded while driving
        r.loop.call_soon_threadsafe(r.daemon.stop_on_signal, signal.SIGINT, 0)  # the handler
        r.thread.join(10)
    assert r.code == 0
    assert stamped.stamped[-1][1].is_stop
    assert_recording_ends_with_the_stop(
        tmp_path / "rec", "shutdown (SIGINT)", 0, "SIGINT", said=caplog.text
    )


class DyingCompassDaemon(Daemon):
    """Fault injection: once armed, the compass thread dies of a bug."""

    armed = False

    def _compass_thread(self) -> None:
        wait_for(lambda: self.armed, 30, "armed")
        raise RuntimeError("injected bug in the compass thread")


def test_a_dying_device_thread_ends_the_recording_with_the_stop_and_the_exit(
    tmp_path: Path, run_daemon, stamped: StampedLink, caplog: pytest.LogCaptureFixture
) -> None:
    d = DyingCompassDaemon(log_motors_config(tmp_path))
    r = run_daemon(d)
    with RemoteClient("127.0.0.1", r.port) as c:
        c.request("drive", left=40, right=40, duration_s=5)
        wait_for(lambda: stamped.driving(40.0, 40.0), 3, "motors driven")
        d.armed = True
        r.thread.join(10)
    assert r.code == 1
    assert_recording_ends_with_the_stop(
        tmp_path / "rec",
        "shutdown (error)",
        1,
        "thread x6wd-compass: RuntimeError: injected bug",
        said=caplog.text,
    )


def test_a_control_lock_held_at_exit_does_not_keep_the_stop_out_of_the_recording(
    tmp_path: Path,
) -> None:
    calls: list[tuple[str, Any]] = []

    class Sink:  # the recorder worker's and the runner's part in the exit
        def put(self, method: str, arg: Any) -> None:
            calls.append((method, arg))

        def shutdown(self, reason: str) -> None:
            calls.append(("runner", reason))

    d = Daemon(log_motors_config(tmp_path))
    d.recorder = d.runner = cast(Any, Sink())
    held, release = threading.Event(), threading.Event()

    def hold() -> None:  # a thread stuck in a decision (30 s: a stop waiting for it, too)
        with d._control_lock:
            held.set()
            release.wait(30)

    threading.Thread(target=hold, daemon=True).start()
    assert held.wait(5)
    t0 = time.monotonic()
    d._stop_controller("shutdown (SIGTERM)")
    # SHUTDOWN_LOCK_S (0.2 s), not the 30 s the stuck thread holds the lock; 3 s is a
    # loaded host's slack
    assert time.monotonic() - t0 < 3.0
    release.set()
    ((method, cmd),) = calls
    assert method == "record_motor"
    assert (cmd.left_pct, cmd.right_pct, cmd.reason) == (0, 0, "shutdown (SIGTERM)")
    wait_for(lambda: d._control_lock.acquire(blocking=False), 5, "lock released")
    d._control_lock.release()
    d._stop_controller("shutdown (SIGTERM)")  # the lock free: the runner stops the controller
    assert calls[-1] == ("runner", "shutdown (SIGTERM)")


# -- the motor thread is guarded like the others ------------------------------------------


class BuggyLink(StampedLink):
    """A motor link whose health-event call hits a bug once armed, in the motor thread's
    ``_after_io`` (not in a GPS thread's direct send, which calls it too)."""

    armed = False
    t_boom: float | None = None

    def take_health_events(self) -> list:  # type: ignore[type-arg]
        in_motor_thread = threading.current_thread().name == "x6wd-motors"
        if self.armed and self.t_boom is None and in_motor_thread:
            self.t_boom = time.monotonic()
            raise RuntimeError("injected bug in the motor thread")
        return super().take_health_events()


@pytest.fixture
def buggy(monkeypatch: pytest.MonkeyPatch) -> BuggyLink:
    from drivers import registry

    link = BuggyLink()
    monkeypatch.setattr(registry, "open_motors", lambda url, devices=None, **_kw: link)
    return link


def test_a_bug_in_the_motor_thread_stops_the_motors_and_exits_1(
    tmp_path: Path, run_daemon, buggy: BuggyLink, caplog: pytest.LogCaptureFixture
) -> None:
    r = run_daemon(Daemon(log_motors_config(tmp_path)))
    with RemoteClient("127.0.0.1", r.port) as c:
        c.request("drive", left=40, right=40, duration_s=5)
        wait_for(lambda: buggy.driving(40.0, 40.0), 3, "motors driven")
        buggy.armed = True
        r.thread.join(5)
    assert r.code == 1, "the daemon went on without its motor thread"
    assert buggy.t_boom is not None
    t_stop = buggy.first_stop_after(buggy.t_boom)
    # the dying thread's own stop, at once (the daemon's exit brings one too, later); 2 s
    # is a loaded host's slack: no stop at all is the failure this guards
    assert t_stop is not None and t_stop - buggy.t_boom < 2.0
    assert "thread x6wd-motors died" in caplog.text
    # the recorder outlives the motor thread: the recording says how it ended
    assert_recording_ends_with_the_stop(
        tmp_path / "rec",
        "shutdown (error)",
        1,
        "thread x6wd-motors: RuntimeError: injected bug",
        said=caplog.text,
    )


# -- the recorder thread: bounded queue, bounded exit, status --------------------------


@pytest.fixture
def fifo_dir(tmp_path: Path) -> Iterator[Path]:
    """A directory whose FIFOs are opened for reading at teardown, so that a writer blocked
    opening one is let go."""
    d = tmp_path / "rec"
    d.mkdir()
    yield d
    for f in d.iterdir():
        if f.is_fifo():
            with contextlib.suppress(OSError):
                os.close(os.open(f, os.O_RDONLY | os.O_NONBLOCK))


def test_a_stuck_recorder_drops_records_and_lets_go_at_close(fifo_dir: Path) -> None:
    rec = Recorder(fifo_dir / "r.jsonl", max_bytes=2000)
    os.mkfifo(fifo_dir / "r.1.jsonl")  # the next part: its open blocks
    w = _RecorderWorker(rec, max_queued=50, stall_s=0.2, log_every_s=60.0)
    for i in range(40):  # ~100 B each: the 21st needs the next part
        w.put("record_nmea", f"$GPTXT,{i:04d}*00")
    wait_for(lambda: w.status().get("busy_s", 0) > 0.2, 3, "writer stuck in the open")
    assert w.state == "stalled"
    for i in range(200):
        w.put("record_nmea", f"$GPTXT,late{i}*00")
    st = w.status()
    assert st["queued"] <= 50 and st["queue_dropped"] >= 150
    assert st["records_dropped"] >= 150 and st["state"] == "stalled"
    t0 = time.monotonic()
    assert w.close(timeout_s=0.5) is False
    # its 0.5 s, not until the open returns (never: the FIFO has no reader until the
    # teardown); 3 s is a loaded host's slack
    assert time.monotonic() - t0 < 3.0


@pytest.mark.slow  # ~10 s: the first part must fill, then the writer stall for 5 s
@pytest.mark.integration
def test_sigterm_with_the_recorder_stuck_exits_in_bounded_time(
    tmp_path: Path, board: TcpMotorBoard
) -> None:
    rec_dir = tmp_path / "rec"
    config = write_config(
        tmp_path,
        motors={"url": f"tcp://127.0.0.1:{board.port}?watchdog_ms=500"},
        recorder={"dir": str(rec_dir), "max_file_mb": 0.02, "min_free_mb": 0},
    )
    p = DaemonProcess(config)
    try:
        first = next(
            Path(m[1]) for line in p.lines if (m := re.search(r"recording to (\S+)", line))
        )
        nxt = first.with_name(f"{first.stem}.1.jsonl")
        if not nxt.exists():
            os.mkfifo(nxt)  # the next part's open blocks, as on a hung mount
        assert p.port is not None
        with RemoteClient("127.0.0.1", p.port) as c:

            def recorder() -> dict:  # type: ignore[type-arg]
                st: dict = c.request("status")  # type: ignore[type-arg]
                return st["recorder"]

            wait_for(lambda: recorder()["state"] == "stalled", 20, "recorder stalled")
            st = c.request("status")
            assert st["links"]["recorder"] == "stalled"
            assert st["recorder"]["file"] == str(first)
        t_sig = time.monotonic()
        p.proc.send_signal(signal.SIGTERM)
        # RECORDER_CLOSE_S (3 s) after the motors, not when the open returns (never): within
        # 9 s, before systemd's TimeoutStopSec (10 s) would kill it, however loaded the host
        assert p.proc.wait(10) == 0
        assert time.monotonic() - t_sig < 9.0
        assert board.first_after(t_sig, r"S #\d+$") is not None
        p.reader.join(5)
        assert any("recorder stuck" in line for line in p.lines), p.lines[-5:]
    finally:
        if nxt.is_fifo():
            with contextlib.suppress(OSError):
                os.close(os.open(nxt, os.O_RDONLY | os.O_NONBLOCK))
        p.stop()


def test_a_failing_recorder_is_logged_at_a_bounded_rate_and_shown_in_status(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    rec = Recorder(tmp_path / "r.jsonl", max_bytes=500, reopen_backoff_s=(0.02, 0.05))
    (tmp_path / "r.1.jsonl").mkdir()  # the next part cannot be opened (EISDIR), ever
    # a fixed count of records, in 5 batches 0.25 s apart (more than log_every_s): each
    # batch after the first brings at least one summary, however late the writer runs
    t_start = time.monotonic()
    w = _RecorderWorker(rec, log_every_s=0.2)
    with caplog.at_level(logging.WARNING, logger="x6wd.app.daemon"):
        for batch in range(5):
            for j in range(80):
                w.put("record_nmea", f"$GPTXT,{batch * 80 + j:05d}*00")
                time.sleep(0.002)
            wait_for(lambda: w.status()["queued"] == 0, 10, "queue drained")
            time.sleep(0.25)
        st = w.status()
        assert st["state"] == "failing"
        assert st["records_dropped"] > 100 and "r.1.jsonl" in st["last_error"]
        assert st["file"] == str(tmp_path / "r.jsonl")
        assert w.close() is True
    elapsed_s = time.monotonic() - t_start
    # only this recorder's lines: the stuck-recorder test's worker, let go at its close, may
    # still log its own FIFO's failure while this test runs
    mine = [r for r in caplog.records if str(tmp_path) in r.getMessage()]
    summaries = [r for r in mine if "records lost in the last" in r.getMessage()]
    # at most one every 0.2 s of the worker's life (a line per failure: ~400), at least
    # one per later batch
    most = int(elapsed_s / 0.2) + 1
    assert 3 <= len(summaries) <= most, (most, [r.getMessage() for r in summaries])
    # the file system's fault, expected: one line saying what, no traceback
    (first,) = [r for r in mine if r.getMessage().startswith("recorder write failed")]
    assert first.exc_info is None and "Is a directory" in first.getMessage(), first.getMessage()
    assert len(mine) <= len(summaries) + 2  # no line per failure


# -- a bind address that is not one ----------------------------------------------------


@pytest.mark.integration
def test_an_invalid_bind_address_is_named_as_such(tmp_path: Path) -> None:
    proc = run_x6wd(write_config(tmp_path, server={"bind": "127.0.0.999"}))
    line = assert_config_error(proc, "server.bind", "127.0.0.999", "not an IP address")
    assert "token_file" not in line
