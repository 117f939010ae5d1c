"""The control loop's own lateness (x6wd.loop.runner): ticks that start late are measured,
counted and logged, and a stale-sensor hold that began while the loop stood still says so.

An outside audit (3 CPU hogs at nice -10 on the daemon's core) saw 21 holds on "attitude
stale" whose compass samples were read on time but reached the controller only after the
hold: the event loop had stalled ~0.6 s, and nothing said so. Here the clock is simulated:
``every()`` drives the runner's ticks at 20 Hz with ``asyncio.sleep`` moving the clock, and a
stall is a sleep that oversleeps (no real sleeps).
"""

from __future__ import annotations

import asyncio
import logging
import threading
from typing import Any

import pytest

from tests.test_loop import Loop, _VirtualTimeLoop, north
from x6wd.app.daemon import _LockedTicks
from x6wd.core.records import Attitude, Mode, NavState, StateChange
from x6wd.loop.runner import LOOP_LATE_LOG_S, LoopLateness, every, run_realtime

TICK_S = 0.05  # the daemon's 20 Hz
COMPASS_S = 0.05  # a sample read every 0.05 s, offset half a period from the ticks
NOTE = "(the control loop itself was"


class _Done(Exception):
    pass


class Stalling:
    """A mission on ``Loop``'s runner, ticked by ``every()`` on simulated time. The compass
    reads a sample every ``COMPASS_S`` (stamped when read) and it reaches the runner in the
    next wait of the loop; GPS fixes at 1 Hz likewise. ``stalls``: {time (s): length (s)},
    times off the ticks' grid: the wait that crosses that time oversleeps by the length (the
    process got no CPU), and what was read meanwhile reaches the runner only after the tick
    that ends the stall, as in the audit's recording. ``compass_dead_s``: no sample read from
    then on."""

    def __init__(
        self,
        stalls: dict[float, float],
        until_s: float,
        compass_dead_s: float = float("inf"),
    ) -> None:
        self.lp = Loop()
        self.lp.start_mission(north(80))
        self.stalls = dict(stalls)
        self.until_s = until_s
        self.compass_dead_s = compass_dead_s
        self.t_compass = COMPASS_S / 2
        self.t_fix = 1.0
        self.queued: list[tuple[float, str]] = []  # read during a stall, not yet delivered

    def _read_until(self, t_s: float) -> list[tuple[float, str]]:
        got = []
        while self.t_compass <= t_s:
            if self.t_compass < self.compass_dead_s:
                got.append((self.t_compass, "compass"))
            self.t_compass += COMPASS_S
        while self.t_fix <= t_s:
            got.append((self.t_fix, "fix"))
            self.t_fix += 1.0
        return sorted(got)

    def _deliver(self, items: list[tuple[float, str]]) -> None:
        lp, now = self.lp, self.lp.now
        for t_s, kind in items:
            if kind == "compass":
                lp.runner.attitude(Attitude(t_s, 0.0, 0.0, 0.0))
            else:  # a fix stamped when it was read
                lp.now = t_s
                lp.fix(0.0)
        lp.now = now

    async def _sleep(self, delay_s: float) -> None:
        self._deliver(self.queued)  # the stall is over: the loop runs what waited
        self.queued = []
        target = self.lp.now + delay_s
        self._deliver(self._read_until(target))  # read and run while the loop waited
        self.lp.now = target
        for at_s in sorted(self.stalls):
            if at_s <= target:
                self.lp.now = target + self.stalls.pop(at_s)
                self.queued = self._read_until(self.lp.now)  # stuck behind the late tick
                break

    def _step(self, now_s: float) -> None:
        if now_s > self.until_s:
            raise _Done
        self.lp.runner.tick(now_s)

    def run(self, monkeypatch: pytest.MonkeyPatch) -> Loop:
        monkeypatch.setattr(asyncio, "sleep", self._sleep)
        coro = every(TICK_S, self.lp.runner.clock, self._step)
        with pytest.raises(_Done):
            coro.send(None)
        return self.lp


def _holds(lp: Loop) -> list[StateChange]:
    return [s for s in lp.states if s.new == "HOLD"]


def _late_lines(caplog: pytest.LogCaptureFixture) -> list[logging.LogRecord]:
    return [r for r in caplog.records if r.getMessage().startswith("control loop late by ")]


def test_a_hold_on_a_compass_sample_stuck_behind_a_stalled_loop_names_the_loop(
    monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.WARNING, logger="x6wd.loop.runner")
    # the audit's case: the loop stalls 0.6 s at 1 s; the compass reads on time throughout
    lp = Stalling({0.99: 0.6}, until_s=3.0).run(monkeypatch)
    (hold,) = _holds(lp)
    # the tick due at 1.0 s started at 1.6 s; the newest sample it had was read at 0.975 s
    assert hold.t_s == pytest.approx(1.6)
    assert hold.reason == (
        "state: attitude stale (the control loop itself was 0.60 s late: CPU starved?)"
    )
    held = [e["data"] for e in lp.events if e["event"] == "telemetry"]
    held = [d for d in held if d["state"] == "HOLD"]
    assert held and all(
        d["hold_reason"] == "attitude stale (the control loop itself was 0.60 s late: CPU starved?)"
        for d in held
    )
    # the queued samples end the hold at once, and the mission drives on
    assert lp.runner.controller.mode == Mode.RUNNING
    assert lp.runner.controller.state != NavState.HOLD
    st = lp.runner.loop_status()
    assert st["overruns"] == 1 and st["stale_holds_while_late"] == 1
    assert st["late_max_s"] == pytest.approx(0.6, abs=1e-3)
    assert st["tick_period_s"] == TICK_S and st["late_window_s"] == 60.0
    assert st["late_last_s"] < TICK_S  # every() started afresh after the stall
    (line,) = _late_lines(caplog)
    assert line.levelno == logging.WARNING
    assert line.getMessage().startswith("control loop late by 0.60 s (CPU starved?)")


def test_a_compass_already_stale_when_the_tick_was_due_keeps_its_own_reason(
    monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.WARNING, logger="x6wd.loop.runner")
    # no sample after 0.3 s, the loop on time: the plain hold at ~0.85 s (0.5 s limit)
    lp = Stalling({}, until_s=1.5, compass_dead_s=0.3).run(monkeypatch)
    assert [h.reason for h in _holds(lp)] == ["state: attitude stale"]
    assert lp.runner.loop_status()["overruns"] == 0 and not _late_lines(caplog)
    assert lp.runner.loop_status()["late_max_s"] < TICK_S

    # a compass dead from 0.3 s (last sample 0.275 s) and a stall over the moment it went
    # stale (0.775 s): the tick due at 0.75 s starts 0.2 s late; the sample was 0.475 s old
    # when it was due, so the hold became due while the loop stood still
    lp = Stalling({0.74: 0.2}, until_s=1.5, compass_dead_s=0.3).run(monkeypatch)
    assert [h.reason for h in _holds(lp)] == [
        "state: attitude stale (the control loop itself was 0.20 s late: CPU starved?)"
    ]
    # the same, the stall starting one tick later: the sample was already 0.525 s old when
    # the late tick was due (0.8 s), so the hold is the compass's own
    lp = Stalling({0.79: 0.3}, until_s=1.5, compass_dead_s=0.3).run(monkeypatch)
    assert [h.reason for h in _holds(lp)] == ["state: attitude stale"]
    assert lp.runner.loop_status()["overruns"] == 1
    # and a stall after the hold began (0.8 s): the loop is counted late, the hold unchanged
    lp = Stalling({0.99: 0.3}, until_s=2.0, compass_dead_s=0.3).run(monkeypatch)
    assert [h.reason for h in _holds(lp)] == ["state: attitude stale"]
    assert lp.runner.controller.state == NavState.HOLD
    assert lp.runner.last_telemetry is not None
    assert lp.runner.last_telemetry.hold_reason == "attitude stale"
    st = lp.runner.loop_status()
    assert st["overruns"] == 1 and st["stale_holds_while_late"] == 0


def test_overruns_are_counted_and_the_warning_is_rate_limited(
    monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.WARNING, logger="x6wd.loop.runner")
    # short stalls (0.2 s) hold nothing; three within LOOP_LATE_LOG_S, one after it
    stalls = {0.99: 0.2, 1.99: 0.3, 2.99: 0.2, 1.49 + LOOP_LATE_LOG_S: 0.25}
    lp = Stalling(stalls, until_s=2.0 + LOOP_LATE_LOG_S).run(monkeypatch)
    st = lp.runner.loop_status()
    assert st["overruns"] == 4 and st["stale_holds_while_late"] == 0 and not _holds(lp)
    lines = [r.getMessage() for r in _late_lines(caplog)]
    assert len(lines) == 2, lines
    assert lines[0].startswith("control loop late by 0.20 s (CPU starved?)")
    assert lines[1].startswith("control loop late by 0.25 s (CPU starved?)")
    assert "(and 2 more in the last" in lines[1]
    # the most over the last minute: the 0.3 s stall, about 10 s ago
    assert st["late_max_s"] == pytest.approx(0.3, abs=1e-3)


def test_the_window_forgets_old_lateness() -> None:
    lat = LoopLateness(window_s=10.0)
    assert lat.status(0.0)["late_max_s"] == 0.0 and lat.overdue_s(5.0) == 0.0
    lat.tick(1.0, 0.5, 0.05)  # 0.5 s late: an overrun
    lat.tick(2.0, 1.98, 0.05)  # 0.02 s late: jitter
    assert lat.overruns == 1 and lat.ticks == 2
    assert lat.max_s(10.9) == pytest.approx(0.5)
    assert lat.max_s(11.5) == pytest.approx(0.02)  # the 0.5 s is over 10 s old
    assert lat.max_s(12.5) == 0.0
    # between ticks: how late the next one (due 2.03 s) already is
    assert lat.overdue_s(2.33) == pytest.approx(0.3)


def test_a_stall_is_measured_through_the_daemons_locked_ticks() -> None:
    """The daemon hands run_realtime its ticks wrapped under the control lock: the lateness
    still reaches the runner, and the stall shows in loop_status."""
    lp = Loop()
    loop = _VirtualTimeLoop()
    try:
        lp.runner.clock = loop.time
        stop = asyncio.Event()

        def stall() -> None:  # the process got no CPU for 0.4 s
            loop.now += 0.4

        loop.call_at(0.52, stall)
        loop.call_at(1.0, stop.set)
        ticks: Any = _LockedTicks(lp.runner, threading.Lock())
        loop.run_until_complete(run_realtime(ticks, stop, tick_hz=20.0))
    finally:
        loop.close()
    st = lp.runner.loop_status()
    assert st["overruns"] == 1 and st["tick_period_s"] == TICK_S
    assert 0.35 <= st["late_max_s"] <= 0.45
    assert st["ticks"] >= 12
