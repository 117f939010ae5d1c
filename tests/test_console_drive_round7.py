"""The console page and manual drive owned by one client (a1a7005: while one client's drive
holds, another's ``drive`` is refused ``rejected``/``busy`` naming the ``driver``; ``status``
says who drives in ``manual_drive``). Found in review: a tap of a drive key on a second page
(pressed and released before its ``busy`` reply came) sent ``stop`` on the release and ended
the other client's drive. The page now sends its release's stop only when a drive of that
press was obeyed, says who is driving (from the refusal and from its status poll), and reads
QGroundControl ``.plan`` files in its editor. The real daemon (``sim://`` devices), its
console on 127.0.0.1, Debian's headless chromium (helpers from tests/test_console.py); the
other driver is a RemoteClient on the control port, resending its drive."""

from __future__ import annotations

import json
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
    text,
    vehicle_pct,
)
from tests.test_daemon import Running, wait_for
from x6wd.app.client import RemoteClient
from x6wd.core.records import Mode

pytestmark = pytest.mark.integration

browser = test_console.browser  # the same module-scoped fixture: one chromium per module

SPEED = 30.0  # the other client's drive (%)
# the page's stops, counted as they leave its WebSocket
COUNT_STOPS = (
    "window.stops = 0; const ws = x6wd.ws, send = ws.send.bind(ws);"
    "ws.send = (t) => { if (JSON.parse(t).cmd === 'stop') window.stops++; send(t); };"
)
# a tap: the key pressed and released in one task, before any reply can arrive
TAP = (
    "for (const type of ['keydown', 'keyup'])"
    " document.dispatchEvent("
    "new KeyboardEvent(type, { code: 'ArrowUp', key: 'ArrowUp', bubbles: true }));"
)


@pytest.fixture(scope="module")
def robot(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Running]:
    with daemon_with(console_config(tmp_path_factory.mktemp("drive7"))) as r:
        wait_for(lambda: has_fix(r), 30, "a fix")
        yield r


class Driver(threading.Thread):
    """A control-port client holding a drive: ``SPEED`` % both sides, 1 s drives resent every
    0.2 s; meanwhile the motors are read every 5 ms, any other command counted."""

    def __init__(self, r: Running) -> None:
        super().__init__(daemon=True)
        self.r = r
        self.client = RemoteClient("127.0.0.1", r.port)
        sock = self.client._sock
        assert sock is not None
        self.name_ = f"127.0.0.1:{sock.getsockname()[1]}"  # how the daemon names it
        self.on = True
        self.watching = False
        self.off_readings: list[tuple[float, float]] = []
        self.drives = 0

    def run(self) -> None:
        next_drive = 0.0
        while self.on:
            now = time.monotonic()
            if now >= next_drive:
                assert self.client.request("drive", left=SPEED, right=SPEED, duration_s=1.0)["ok"]
                self.drives += 1
                next_drive = now + 0.2
            if self.watching:
                pct = vehicle_pct(self.r)
                if pct != (SPEED, SPEED) or self.r.daemon.controller.mode != Mode.MANUAL:
                    self.off_readings.append(pct)
            time.sleep(0.005)
        self.client.request("stop")


@pytest.fixture
def driver(robot: Running) -> Iterator[Driver]:
    with RemoteClient("127.0.0.1", robot.port) as c:
        assert c.request("stop")["ok"]
    d = Driver(robot)
    with d.client:
        d.start()
        wait_for(lambda: vehicle_pct(robot) == (SPEED, SPEED), 5, "the other client driving")
        try:
            yield d
        finally:
            d.on = False
            d.join(5)


def test_a_tap_on_the_page_while_another_client_drives_stops_nothing(
    robot: Running, browser: webdriver.Chrome, driver: Driver
) -> None:
    open_page(browser, robot)
    page_ready(browser)
    js(browser, COUNT_STOPS)
    driver.watching = True
    # taps, released before their busy reply: the old page sent a stop on each release
    for _ in range(3):
        js(browser, TAP)
        time.sleep(0.3)
    assert js(browser, "return window.stops") == 0, "a tap on the page sent stop"
    assert driver.off_readings == [], f"a tap disturbed the other drive: {driver.off_readings[:5]}"
    wait_for(lambda: "another client is driving" in text(browser, "msg"), 3, "the busy message")
    assert driver.name_ in text(browser, "msg")
    # a key held: refused busy, shown, not shown as driving; its release sends nothing
    body = browser.find_element(By.TAG_NAME, "body")
    ActionChains(browser).key_down(Keys.ARROW_UP, body).perform()
    wait_for(lambda: browser.find_element(By.ID, "drive-busy").is_displayed(), 3, "busy shown")
    busy = text(browser, "drive-busy")
    assert f"Another client is driving ({driver.name_})" in busy and "Stop still works" in busy
    wait_for(lambda: js(browser, "return x6wd.drive") is None, 3, "the refused press ended")
    assert "active" not in (browser.find_element(By.ID, "drive-fwd").get_attribute("class") or "")
    ActionChains(browser).key_up(Keys.ARROW_UP, body).perform()
    time.sleep(0.5)
    driver.watching = False
    assert js(browser, "return window.stops") == 0
    assert driver.off_readings == [], f"the other drive was disturbed: {driver.off_readings[:5]}"
    assert vehicle_pct(robot) == (SPEED, SPEED)
    # STOP still works from the page
    browser.find_element(By.ID, "btn-stop").click()
    driver.on = False  # (its next drive would take over again: a stop ends the ownership)
    wait_for(lambda: vehicle_pct(robot) == (0.0, 0.0), 3, "stopped by the page's STOP")
    assert js(browser, "return window.stops") == 1


def test_the_page_shows_who_drives_from_status(
    robot: Running, browser: webdriver.Chrome, driver: Driver
) -> None:
    open_page(browser, robot)
    page_ready(browser)
    # nothing pressed on the page: its status poll names the driver
    wait_for(
        lambda: browser.find_element(By.ID, "drive-busy").is_displayed(), 3, "who drives shown"
    )
    assert driver.name_ in text(browser, "drive-busy")
    driver.on = False
    driver.join(5)  # it sent stop: nobody drives
    wait_for(lambda: not browser.find_element(By.ID, "drive-busy").is_displayed(), 3, "cleared")
    # the page's own drive: nothing shown, and a tap (released before its reply) still stops
    # the robot once its drive is obeyed
    js(browser, COUNT_STOPS)
    js(browser, TAP)
    wait_for(lambda: js(browser, "return window.stops") == 1, 3, "the tap's stop after its ok")
    wait_for(lambda: vehicle_pct(robot) == (0.0, 0.0), 3, "stopped after the tap")
    assert robot.daemon.controller.mode != Mode.MANUAL
    assert not browser.find_element(By.ID, "drive-busy").is_displayed()


def test_a_qgroundcontrol_plan_loads_into_the_editor(
    tmp_path: Path, robot: Running, browser: webdriver.Chrome
) -> None:
    open_page(browser, robot)
    page_ready(browser)
    assert ".plan" in (browser.find_element(By.ID, "mission-file").get_attribute("accept") or "")
    points = [north(10), north(10, 10), north(0, 10)]
    items = [
        {"AMSLAltAboveTerrain": None, "Altitude": 50, "AltitudeMode": 1, "autoContinue": True,
         "command": 16, "doJumpId": i + 1, "frame": 3, "params": [0, 0, 0, None, lat, lon, 50],
         "type": "SimpleItem"}
        for i, (lat, lon) in enumerate(points)
    ]  # fmt: skip
    plan = {
        "fileType": "Plan", "groundStation": "QGroundControl", "version": 1,
        "geoFence": {"circles": [], "polygons": [], "version": 2},
        "rallyPoints": {"points": [], "version": 2},
        "mission": {"cruiseSpeed": 15, "firmwareType": 3, "hoverSpeed": 5, "version": 2,
                    "plannedHomePosition": [*north(0), 60], "items": items},
    }  # fmt: skip
    f = tmp_path / "square.plan"
    f.write_text(json.dumps(plan, indent=4))
    browser.find_element(By.ID, "mission-file").send_keys(str(f))
    wait_for(lambda: js(browser, "return x6wd.draft.length") == 3, 10, "the plan read")
    got = js(browser, "return x6wd.draft")
    assert all(
        abs(a - b) < 1e-9
        for p, q in zip(got, points, strict=True)
        for a, b in zip(p, q, strict=True)
    )
    assert "square.plan: 3 waypoints" in text(browser, "msg")
    assert "not sent" in text(browser, "mission-state")
