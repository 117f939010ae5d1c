"""The console page with a large mission in its editor: an outside audit found STOP took
seconds to reach the robot (3000 waypoints loaded into the editor, not sent, a mission
running: 4.2-12.1 s from the click to the daemon IDLE with motors 0/0; 0.13-1.18 s with an
empty editor). The page drew the whole map (every waypoint numbered, the whole track) at every
animation frame: its main thread was busy ~10 s of every 11 s, and the click waited behind
it. The real daemon (``sim://`` devices), its console on 127.0.0.1, Debian's headless
chromium (helpers from tests/test_console.py); the page's long tasks are Chromium's
PerformanceObserver('longtask') entries (tasks over 50 ms)."""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from selenium import webdriver
from selenium.webdriver.common.action_chains import ActionChains
from selenium.webdriver.common.by import By
from selenium.webdriver.common.keys import Keys

from tests import test_console
from tests.test_console import (
    console_config,
    daemon_with,
    has_fix,
    js,
    north,
    open_page,
    page_ready,
    vehicle_pct,
)
from tests.test_daemon import Running, wait_for
from x6wd.app.client import RemoteClient, RequestFailed
from x6wd.core.mission_files import format_csv
from x6wd.core.records import Mode

pytestmark = pytest.mark.integration

browser = test_console.browser  # the same module-scoped fixture: one chromium per module

BIG = 3000  # waypoints in the editor (the audit's file: 3000, 90 KB)
# The bounds, against what was measured on a 2-core machine under a load of 4-10 (other test
# runs), the audit's file in the editor and a mission running. The page before the fix: STOP
# 2.4-11.0 s (9 trials; this test: 4.6 s), long tasks 9.7-10.4 s of every 10 s idle (this
# test: 3.5-4.1 s of 5 s, longest 135-149 ms). After: STOP 0.06-0.16 s, idle long tasks
# none, or one or two of 50-120 ms (the load's preemption).
# Made load-independent (all three were wall times a starved host inflates directly):
# - STOP is timed from the press's own event (the pointerdown's e.timeStamp: when the input
#   event was created, in performance.now()'s timebase, mapped to this process's clock) to
#   the daemon IDLE with motors 0/0, not from before the WebDriver click: chromedriver's own
#   steps (scrolling, the element's place) took most of a loaded host's time. The time the
#   press then waits in the page's input queue behind busy main-thread tasks (the audit's
#   symptom) is counted, as it would not be from performance.now() read in the listener;
#   the busy main thread itself is the idle check's to catch too.
# - the idle page's work is its main thread's CPU time (CDP Performance.getMetrics
#   ThreadTime), not the wall time of its long tasks, which CPU starvation stretches: the
#   old page (a57442a^'s) used 3.47 s of CPU in 5.1 s here (0.68), the fixed page 0.12.
# - the longest long task is bounded by LONG_TASK_BOUND_MS of CPU: its wall time over the
#   page's slowdown in the same run (wall time over main-thread CPU time of a busy loop run
#   in the page: 1 on an idle host, 2-4 beside 3 busy loops).
STOP_BOUND_S = 1.5
IDLE_S = 5.0
IDLE_BUSY_BOUND = 0.25  # of the idle time: the main thread's CPU time
LONG_TASK_BOUND_MS = 400.0
LONG_TASKS = """
window.longTasks = [];
new PerformanceObserver((l) => {
  for (const e of l.getEntries()) window.longTasks.push(e.duration);
}).observe({ type: "longtask" });
"""
# when the press on STOP was made: its event's timeStamp (not when a listener ran: that leaves
# out the time it waited in the page's input queue)
STOP_PRESSES = """
window.stopPresses = [];
window.addEventListener("pointerdown", (e) => {
  if (e.target.closest && e.target.closest("#btn-stop")) window.stopPresses.push(e.timeStamp);
}, { capture: true });
"""


def metrics(d: webdriver.Chrome) -> dict[str, float]:
    """The page's CDP performance metrics (ThreadTime: its main thread's CPU time, s)."""
    got = d.execute_cdp_cmd("Performance.getMetrics", {})["metrics"]
    return {m["name"]: float(m["value"]) for m in got}


def slowdown(d: webdriver.Chrome) -> float:
    """How much longer the page's main thread takes in wall time than in CPU time now: a busy
    loop of 300 ms in the page, over the CPU time it got (at least 1)."""
    before = metrics(d)
    js(d, "const t = performance.now(); while (performance.now() - t < 300) {}")
    after = metrics(d)
    cpu = after["ThreadTime"] - before["ThreadTime"]
    return max(1.0, 0.3 / max(cpu, 0.01))


def page_to_monotonic(d: webdriver.Chrome) -> float:
    """The offset (s) that maps the page's performance.now() (ms / 1000) onto this process's
    time.monotonic(), at its latest: the page read its clock before the call returned (the
    least of five round trips)."""
    offsets = []
    for _ in range(5):
        page_ms = js(d, "return performance.now()")
        offsets.append(time.monotonic() - page_ms / 1000.0)
    return min(offsets)


@pytest.fixture(scope="module")
def robot(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Running]:
    with daemon_with(console_config(tmp_path_factory.mktemp("round7"))) as r:
        wait_for(lambda: has_fix(r), 30, "a fix")
        yield r


def big_mission_file(tmp_path: Path) -> Path:
    """A spiral of ``BIG`` waypoints out to 60 m (as the audit's file: about 90 KB of CSV)."""
    points = []
    for i in range(BIG):
        a = i * 0.05
        rad = 5.0 + 55.0 * i / BIG
        points.append(tuple(north(rad * math.sin(a), rad * math.cos(a))))
    path = tmp_path / "big.csv"
    path.write_text(format_csv(points))  # type: ignore[arg-type]
    return path


def laps() -> list[list[float]]:
    """A mission that keeps the robot driving: laps of a 15 m square."""
    square = [north(15, 0), north(15, 15), north(0, 15), north(0, 0)]
    return square * 10


class Watch(threading.Thread):
    """The daemon's mode and motor command every 5 ms (in-process: no request in between)."""

    def __init__(self, r: Running) -> None:
        super().__init__(daemon=True)
        self.r = r
        self.since = 0.0
        self.stopped_at: float | None = None
        self.on = True

    def arm(self) -> None:
        self.stopped_at = None
        self.since = time.monotonic()

    def run(self) -> None:
        while self.on:
            now = time.monotonic()
            if (
                self.stopped_at is None
                and self.since
                and self.r.daemon.controller.mode == Mode.IDLE
                and vehicle_pct(self.r) == (0.0, 0.0)
            ):
                self.stopped_at = now
            time.sleep(0.005)


def running(r: Running, c: RemoteClient) -> None:
    """The mission runs and the robot drives."""
    if r.daemon.controller.mode != Mode.RUNNING:
        time.sleep(0.5)  # the page's stop done with (see below)
        try:
            c.request("start")
        except RequestFailed as exc:
            # A page's stop that came while its link was busy (its status poll) is obeyed at
            # once and handled again in its turn, which refuses a start read in between as
            # "a stop came after this start" (seen once in ~10 runs): once more
            assert "a stop came after" in str(exc), exc
            time.sleep(0.5)
            c.request("start")
    wait_for(lambda: vehicle_pct(r) != (0.0, 0.0), 10, "the robot driving its mission")


def test_stop_is_quick_with_3000_waypoints_in_the_editor(
    tmp_path: Path, robot: Running, browser: webdriver.Chrome
) -> None:
    mission = big_mission_file(tmp_path)
    with RemoteClient("127.0.0.1", robot.port) as c:
        assert c.request("stop")["ok"]
        assert c.request("mission.load", waypoints=laps())["ok"]
        running(robot, c)
        open_page(browser, robot)
        page_ready(browser)
        js(browser, LONG_TASKS)
        js(browser, STOP_PRESSES)
        browser.execute_cdp_cmd("Performance.enable", {})
        browser.find_element(By.ID, "mission-file").send_keys(str(mission))  # not sent
        wait_for(lambda: js(browser, "return x6wd.draft.length") == BIG, 15, "the file read")
        assert "not sent" in browser.find_element(By.ID, "mission-state").text
        slow = slowdown(browser)  # (its own long task is reported before the settling ends)
        time.sleep(1.0)  # settled
        # idle (the mission runs, telemetry arrives, nobody touches the page)
        js(browser, "window.longTasks = []")
        before = metrics(browser)
        time.sleep(IDLE_S)
        after = metrics(browser)
        tasks = js(browser, "return window.longTasks")
        slow = max(slow, slowdown(browser))
        wall = after["Timestamp"] - before["Timestamp"]
        cpu = after["ThreadTime"] - before["ThreadTime"]
        idle = (
            f"the idle page: main thread CPU {cpu:.2f} s in {wall:.2f} s; long tasks "
            f"{len(tasks)}, {sum(tasks) / 1000.0:.2f} s in all, longest "
            f"{max(tasks, default=0.0):.0f} ms (wall) at a slowdown of {slow:.1f}"
        )
        # STOP: the page's press to the daemon IDLE with motors 0/0
        watch = Watch(robot)
        watch.start()
        took = []
        try:
            for i in range(3):
                running(robot, c)
                offset = page_to_monotonic(browser)
                watch.arm()
                browser.find_element(By.ID, "btn-stop").click()
                wait_for(lambda: watch.stopped_at is not None, STOP_BOUND_S + 10, "stopped")
                assert watch.stopped_at is not None
                presses = js(browser, "return window.stopPresses")
                assert len(presses) == i + 1, presses
                took.append(watch.stopped_at - (presses[-1] / 1000.0 + offset))
                assert took[-1] < STOP_BOUND_S, f"STOP took {took} s; {idle}"
        finally:
            watch.on = False
        assert cpu < IDLE_BUSY_BOUND * wall, idle
        assert max(tasks, default=0.0) < LONG_TASK_BOUND_MS * slow, idle
        # still the 3000 waypoints, still not sent, and the page drew them
        assert js(browser, "return x6wd.draft.length") == BIG
        assert len(robot.daemon._mission) == len(laps())
        assert js(browser, "return x6wd.layerDraws") >= 1
        print(f"STOP took {[round(t, 3) for t in took]} s; {idle}; long tasks {tasks}")


def test_stop_acts_on_the_press_once_and_from_the_keyboard(
    robot: Running, browser: webdriver.Chrome
) -> None:
    with RemoteClient("127.0.0.1", robot.port) as c:
        assert c.request("stop")["ok"]
        assert c.request("mission.load", waypoints=laps())["ok"]
        open_page(browser, robot)
        page_ready(browser)
        # count the page's stops as they leave
        js(
            browser,
            "window.stops = 0; const ws = x6wd.ws, send = ws.send.bind(ws);"
            "ws.send = (t) => { if (JSON.parse(t).cmd === 'stop') window.stops++; send(t); };",
        )
        button = browser.find_element(By.ID, "btn-stop")
        running(robot, c)
        ActionChains(browser).click_and_hold(button).perform()
        # the robot stops while the button is still held
        wait_for(lambda: vehicle_pct(robot) == (0.0, 0.0), 3, "stopped on the press")
        assert robot.daemon.controller.mode == Mode.IDLE
        ActionChains(browser).release(button).perform()
        time.sleep(0.3)
        assert js(browser, "return window.stops") == 1  # the click after it sends no second
        # Enter on the focused button (a click without a press) stops too
        running(robot, c)
        js(browser, "document.getElementById('btn-stop').focus()")
        ActionChains(browser).send_keys(Keys.ENTER).perform()
        wait_for(lambda: vehicle_pct(robot) == (0.0, 0.0), 3, "stopped by Enter on STOP")
        assert js(browser, "return window.stops") == 2
