"""An operator stop holds at the motors until the controller has applied it.

``Daemon.stop`` puts the stop in the motor worker at once, before the control loop has run
it. Until the controller has it, a drive decided meanwhile (a GPS fix's, sent directly from
the GPS thread; a tick's) must neither replace the stop before it is sent nor follow it out:
the robot would drive on after the operator stopped it, exactly when the control loop is
behind. Once the controller has the stop, drive commands go through again (a later manual
drive works), and zero commands always do.
"""

from __future__ import annotations

import threading
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

from tests.test_daemon import ORIGIN, run_daemon, wait_for
from tests.test_safety_daemon import SlowLink, worker
from tests.test_shutdown import StampedLink, log_motors_config, stamped
from x6wd.app.client import RemoteClient
from x6wd.app.daemon import Daemon, _MotorWorker
from x6wd.core.config import SafetyConfig
from x6wd.core.records import MotorCommand

__all__ = ["run_daemon", "stamped"]  # fixtures


def cmd(left: float, reason: str) -> MotorCommand:
    return MotorCommand(time.monotonic(), left, left, reason)


def operator_stop(w: _MotorWorker) -> int:
    """What Daemon.stop does with the motors: hold, then submit the stop."""
    seq = w.hold_stop()
    w.submit(cmd(0.0, "operator stop"))
    return seq


# -- the motor worker ------------------------------------------------------------------------
def test_a_drive_after_an_operator_stop_neither_replaces_it_nor_follows_it() -> None:
    """The review's case: the motor thread is mid-send when the stop comes; a fix's drive
    (send_now) and a tick's (submit) come before the controller has the stop."""
    link = SlowLink()
    w = worker(link, 2.0)
    try:
        w.submit(cmd(30.0, "drive"))
        assert link.sending.wait(2)  # the motor thread is in the middle of a send
        seq = operator_stop(w)
        assert w.send_now(cmd(30.0, "fix")) is False  # a GPS fix's decision
        w.submit(cmd(30.0, "tick"))  # a 20 Hz tick's
        link.release.set()
        wait_for(lambda: any(c.is_stop for _t, c in link.arrived), 3, "the operator's stop")
        time.sleep(0.3)  # a drive queued behind the stop would be out by now
        w.send_now(cmd(35.0, "fix"))  # the link idle, the stop sent: still held
        time.sleep(0.2)
        assert [c.reason for _t, c in link.arrived] == ["drive", "operator stop"]
        assert w.dropped_while_stopping == 3 and w.stop_holding
        w.submit(cmd(0.0, "hold"))  # a zero command always goes
        wait_for(lambda: link.arrived[-1][1].reason == "hold", 3, "a zero command")
        # the controller has applied the stop: drives go through again
        w.stop_applied(seq)
        assert not w.stop_holding
        assert w.send_now(cmd(20.0, "manual")) is True
        assert link.arrived[-1][1].reason == "manual"
    finally:
        link.release.set()
        w.shutdown("test end")


def test_only_the_newest_operator_stop_applied_lets_drives_through() -> None:
    link = SlowLink()
    link.release.set()  # no send blocks here
    w = worker(link, 2.0)
    try:
        first = operator_stop(w)
        second = operator_stop(w)
        w.stop_applied(first)  # the controller has the first stop, not the second yet
        assert w.stop_holding and w.send_now(cmd(30.0, "fix")) is False
        w.stop_applied(second)
        assert not w.stop_holding
        w.submit(cmd(30.0, "tick"))
        wait_for(lambda: link.arrived and link.arrived[-1][1].reason == "tick", 3, "the drive")
    finally:
        w.shutdown("test end")


def test_an_operator_stop_held_keeps_the_keepalive_stopped_and_shuts_down() -> None:
    link = SlowLink()
    link.release.set()
    w = worker(link, 0.05)
    try:
        w.submit(cmd(30.0, "drive"))
        wait_for(lambda: link.arrived and link.arrived[-1][1].reason == "drive", 3, "drive")
        operator_stop(w)
        for _ in range(10):  # the controller, behind, keeps deciding drives meanwhile
            w.submit(cmd(30.0, "tick"))
            time.sleep(0.02)
        n = len(link.arrived)
        wait_for(lambda: len(link.arrived) >= n + 3, 3, "keep-alives")
        reasons = [c.reason for _t, c in link.arrived]
        after = [c for _t, c in link.arrived[reasons.index("operator stop") :]]
        assert set(reasons[: reasons.index("operator stop")]) == {"drive"}  # (keep-alives)
        assert all(c.is_stop for c in after) and after[-1].reason == "keepalive"
        assert w.thread.is_alive()
    finally:
        w.shutdown("test end")
    assert link.commands[-1].is_stop and not w.thread.is_alive()


# -- the running daemon ----------------------------------------------------------------------
def test_an_operator_stop_holds_while_the_loop_is_behind_and_fixes_keep_deciding(
    tmp_path: Path, run_daemon: Any, stamped: StampedLink
) -> None:
    """A mission drives on every fix, decided and sent on the GPS thread. The event loop
    stalls (without the control lock: a slow callback), an operator stops: the stop goes
    out at once, and the fixes that come before the controller has it send no drive. Once
    the loop runs the stop, the controller is IDLE and a manual drive moves the motors."""
    cfg = log_motors_config(tmp_path)
    # the compass's samples go through the stalled event loop: a stale attitude would hold
    # the mission by itself within 0.5 s, stop or no stop
    d = Daemon(replace(cfg, safety=replace(cfg.safety, attitude_stale_s=5.0)))
    r = run_daemon(d)
    wait_for(lambda: d.first_fix, 20, "first fix")
    assert d.motors is not None
    with RemoteClient("127.0.0.1", r.port) as c:
        c.request("mission.load", waypoints=[[ORIGIN[0] + 30.0 / 111_200.0, ORIGIN[1]]])
        c.request("start")
    sent = d.motors.direct_sent
    wait_for(lambda: d.motors.direct_sent >= sent + 2, 10, "fixes' drives sent directly")
    wait_for(lambda: not stamped.stamped[-1][1].is_stop, 5, "the mission driving")

    stall, stalled = threading.Event(), threading.Event()

    def slow_callback() -> None:  # the event loop is behind: no tick, no request runs
        stalled.set()
        stall.wait(10)

    reply: dict[str, Any] = {}

    def ask_stop() -> None:
        with RemoteClient("127.0.0.1", r.port) as c2:
            reply.update(c2.request("stop"))

    r.loop.call_soon_threadsafe(slow_callback)
    asker = threading.Thread(target=ask_stop, daemon=True)
    try:
        assert stalled.wait(5)
        t0 = time.monotonic()
        asker.start()
        wait_for(lambda: stamped.first_stop_after(t0), 2, "the operator's stop at the motors")
        t_stop = stamped.first_stop_after(t0)
        assert t_stop is not None
        # fixes come at 4 Hz: the controller, still on its mission, decides on each
        time.sleep(1.5)
        assert not reply  # the loop is still behind: the controller has not had the stop
        after = [c for t, c in stamped.stamped if t >= t_stop]
        assert after and all(c.is_stop for c in after), [
            (c.reason, c.left_pct) for c in after if not c.is_stop
        ]
        assert d.motors.dropped_while_stopping >= 3  # fixes did decide drives: none went out
    finally:
        stall.set()
    asker.join(10)
    assert reply.get("mode") == "IDLE"
    assert not d.motors.stop_holding
    with RemoteClient("127.0.0.1", r.port) as c:
        hold = c.request("status")["motor_hold"]  # what the operator can see of it
    assert hold["holding"] is False and hold["dropped_while_stopping"] >= 3
    # a manual drive after the stop moves the motors again
    with RemoteClient("127.0.0.1", r.port) as c:  # open: closed, its drive would stop
        c.request("drive", left=25, right=25, duration_s=2)
        wait_for(lambda: stamped.driving(25.0, 25.0), 3, "a manual drive after the stop")


def test_a_drive_the_motors_refused_is_not_recorded_as_sent() -> None:
    """While an operator stop holds, the daemon's motor sink drops the controller's drives
    and says so (False): the recording shows what reached the motors (a review: it showed
    drives after the stop that never went out, the very pattern the stop race was read
    from)."""
    from tests.test_loop import Loop

    lp = Loop(SafetyConfig(manual_max_s=5.0))
    refused: list[MotorCommand] = []

    def sink(cmd: MotorCommand) -> bool:
        if cmd.is_stop:
            lp.motors.append(cmd)
            return True
        refused.append(cmd)
        return False

    lp.runner._motors = sink
    lp.runner.drive(20.0, 20.0, 5.0)
    assert refused and refused[-1].left_pct == 20.0
    assert not [a for m, a in lp.records if m == "record_motor" and not a.is_stop]


def test_whether_a_command_was_held_is_decided_with_it_per_thread() -> None:
    """The daemon asks the worker whether the command it just gave was dropped (so the
    recording skips it); the answer is the one decided under the worker's lock for that
    thread's command, not the hold's state read before or after (a hold beginning between
    the two made a dropped drive read as sent: a review)."""
    link = SlowLink()
    link.release.set()  # sends go straight through
    w = worker(link, 0.1)
    try:
        w.submit(MotorCommand(time.monotonic(), 20.0, 20.0, "drive"))
        assert not w.last_held()
        seq = w.hold_stop()
        w.submit(MotorCommand(time.monotonic(), 30.0, 30.0, "drive"))
        assert w.last_held()
        seen: list[bool] = []

        def other() -> None:  # another thread's verdict is its own
            w.submit(MotorCommand(time.monotonic(), 0.0, 0.0, "operator stop"))
            seen.append(w.last_held())

        t = threading.Thread(target=other)
        t.start()
        t.join()
        assert seen == [False] and w.last_held()
        w.stop_applied(seq)
        w.send_now(MotorCommand(time.monotonic(), 25.0, 25.0, "drive"))
        assert not w.last_held()
    finally:
        w.shutdown("test end")
