"""Two operators, one mission (an outside audit, round 18): page A's unsent edits were sent
over a mission page B had loaded meanwhile, and neither page was told. Now a page says when
the robot's mission was replaced from elsewhere, and a draft made on the mission before asks
for a second Send before it replaces the new one. The real daemon with ``sim://`` devices
and its console, Debian's chromium through chromedriver, the control port as the other
operator."""

from __future__ import annotations

import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from selenium import webdriver
from selenium.webdriver.common.by import By

from tests.test_console import (
    browser,
    chromium,
    console_config,
    daemon_with,
    has_fix,
    js,
    north,
    open_page,
    page_ready,
    text,
)
from tests.test_daemon import Running, wait_for
from x6wd.app.client import RemoteClient

pytestmark = pytest.mark.integration
__all__ = ["browser", "chromium"]  # the fixtures


@pytest.fixture
def robot(tmp_path: Path) -> Iterator[Running]:
    with daemon_with(console_config(tmp_path)) as r:
        wait_for(lambda: has_fix(r), 30, "a fix")
        yield r


def on_robot(r: Running) -> list[tuple[float, float]]:
    return list(r.daemon._mission)


def test_a_draft_made_on_a_mission_replaced_meanwhile_asks_before_it_replaces_it(
    robot: Running, browser: webdriver.Chrome
) -> None:
    r = robot
    open_page(browser, r)
    page_ready(browser)
    mine = [north(10), north(20, 5)]
    js(browser, "x6wd.draft = arguments[0]; x6wd.dirty = true;", mine)  # an edit, not sent
    theirs = [north(30)]
    with RemoteClient("127.0.0.1", r.port) as c:  # the other operator
        c.request("mission.load", waypoints=theirs)
    said = wait_for(
        lambda: "replaced, not from this page" in (m := text(browser, "msg")) and m,
        10,
        "the page told of the other load",
    )
    assert "1 waypoints now" in said and "your edits (not sent)" in said, said
    browser.find_element(By.ID, "btn-send").click()
    wait_for(lambda: "Send again to replace it" in text(browser, "msg"), 5, "asked first")
    time.sleep(0.5)
    assert len(on_robot(r)) == 1  # theirs stands
    browser.find_element(By.ID, "btn-send").click()
    wait_for(lambda: len(on_robot(r)) == 2, 10, "mine sent on the second Send")
    wait_for(lambda: "on the robot" in text(browser, "mission-state"), 10, "shown as sent")
    # its own load is not told as another's, however late its map comes
    for _ in range(8):
        assert "not from this page" not in text(browser, "msg"), text(browser, "msg")
        time.sleep(0.25)
    # a page without edits is told too, and follows the robot's mission
    with RemoteClient("127.0.0.1", r.port) as c:
        c.request("mission.load", waypoints=[north(40), north(50), north(60)])
    wait_for(
        lambda: (
            "it has 3 waypoints now" in text(browser, "msg")
            and len(js(browser, "return x6wd.draft")) == 3
        ),
        10,
        "the page told, its list the robot's",
    )


def test_the_estimate_standing_in_for_a_lost_fix_is_said_so(
    tmp_path: Path, browser: webdriver.Chrome
) -> None:
    # an audit (round 18): in a GPS outage the position row showed the EKF's estimate as if
    # it were a fix, and the receiver's "no HDOP" (99.99) as "HDOP 100.0"
    import dataclasses

    from x6wd.core.config import SimConfig

    scenario = tmp_path / "outage.toml"
    default = Path(__file__).resolve().parents[1] / "config" / "scenarios" / "default.toml"
    scenario.write_text(
        f'include = ["{default}"]\nname = "outage"\n'
        '[[effects]]\nname = "outage"\nstart_s = 8.0\nduration_s = 300.0\n'
    )
    cfg = console_config(tmp_path)
    cfg = dataclasses.replace(
        cfg, sim=SimConfig(scenario=str(scenario), gps_rate_hz=4.0, gps_baud=115200)
    )
    with daemon_with(cfg) as r:
        wait_for(lambda: has_fix(r), 30, "a fix")
        open_page(browser, r)
        page_ready(browser)
        assert "estimate" not in text(browser, "tel-pos")  # a fix: said plainly
        wait_for(
            lambda: (
                (t := r.daemon.last_telemetry) is not None
                and t.lat_deg is None
                and t.filt_lat_deg is not None
            ),
            30,
            "the outage, the estimate going on",
        )
        shown = wait_for(
            lambda: "(estimate: no fix)" in (s := text(browser, "tel-pos")) and s, 5, "said so"
        )
        lat, lon = (float(v) for v in shown.split(" (")[0].split(","))
        assert abs(lat - 51.752) < 0.01 and abs(lon + 1.2577) < 0.01, shown
        assert "HDOP 100" not in text(browser, "tel-fix"), text(browser, "tel-fix")
