"""A stop from another client ends the drive a console page holds, as an outside audit found
it did not (the page's next resend, sent after the stop, drove the robot again 94 ms later);
and the console's Host check takes only a well-formed host[:port]. The real daemon
(``sim://`` devices), its console on 127.0.0.1, Debian's headless chromium (helpers from
tests/test_console.py)."""

from __future__ import annotations

import asyncio
import time
from collections.abc import Iterator

import aiohttp
import pytest
from selenium import webdriver
from selenium.webdriver.common.action_chains import ActionChains
from selenium.webdriver.common.by import By

from tests import test_console
from tests.test_console import (
    console_config,
    daemon_with,
    has_fix,
    js,
    open_page,
    page_ready,
    vehicle_pct,
    ws_to,
)
from tests.test_daemon import Running, wait_for
from x6wd.app.client import RemoteClient
from x6wd.app.console.server import allowed_host
from x6wd.core.records import Mode

pytestmark = pytest.mark.integration

browser = test_console.browser  # the same module-scoped fixture: one chromium per module


# deadman_s here, 4 times the default 0.5 s (and every wait below scaled with it): a drive
# arriving more than deadman_s late is refused, so with 0.5 s a stall of 0.35-0.5 s of a
# loaded host (the browser's timer, the daemon's loop) stopped a held drive and the "still
# driving" checks failed; the times the tests prove (a press, a pause, a stop) keep their
# ratios to it.
DEADMAN_S = 2.0


@pytest.fixture(scope="module")
def robot(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Running]:
    """One HIL daemon with the console (no token: loopback), deadman_s DEADMAN_S."""
    cfg = console_config(tmp_path_factory.mktemp("override"), deadman_s=DEADMAN_S)
    with daemon_with(cfg) as r:
        wait_for(lambda: has_fix(r), 30, "a fix")
        yield r


def stop_from_elsewhere(r: Running) -> None:
    """The operator's `x6wd client stop` on the control port."""
    with RemoteClient("127.0.0.1", r.port) as c:
        assert c.request("stop")["ok"]


def stays_stopped(r: Running, seconds: float) -> None:
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        assert vehicle_pct(r) == (0.0, 0.0), "driven again after the stop"
        assert r.daemon.controller.mode != Mode.MANUAL, "back in MANUAL after the stop"
        time.sleep(0.01)


def test_a_stop_from_another_client_ends_the_drive_the_page_holds(
    robot: Running, browser: webdriver.Chrome
) -> None:
    # The audit: the page held forward, `x6wd client stop` went MANUAL -> IDLE, and 94 ms
    # later the page's resend drove at 40/40 % until the button was released.
    open_page(browser, robot)
    page_ready(browser)
    button = browser.find_element(By.ID, "drive-fwd")
    ActionChains(browser).click_and_hold(button).perform()
    wait_for(lambda: vehicle_pct(robot)[0] > 0.0, 5, "the robot driving")
    time.sleep(1.2 * DEADMAN_S)  # held: a few resends (every deadman_s / 3)
    assert vehicle_pct(robot)[0] > 0.0
    # every text the status line shows: the state event of the stop (MANUAL -> IDLE) may
    # reach the page after the refused resend and replace its message there
    js(
        browser,
        "const m = document.getElementById('msg'); window.shown = [];"
        "new MutationObserver(() => window.shown.push(m.textContent))"
        ".observe(m, {childList: true, characterData: true, subtree: true});",
    )
    stop_from_elsewhere(robot)
    wait_for(lambda: vehicle_pct(robot) == (0.0, 0.0), 5.0, "the stop obeyed")
    stays_stopped(robot, 3.0 * DEADMAN_S)  # nine resend periods with the button still held
    wait_for(lambda: js(browser, "return x6wd.drive") is None, 5.0, "the page's drive ended")
    note = browser.find_element(By.ID, "drive-stopped")  # near the drive buttons
    assert note.is_displayed() and "stopped by another client" in note.text, note.text
    shown = js(browser, "return window.shown")
    assert any("stopped by another client" in text for text in shown), shown
    assert "active" not in (button.get_attribute("class") or "")
    ActionChains(browser).release(button).perform()
    stays_stopped(robot, 0.3)  # the release sends nothing more
    # a new press after the stop drives as usual, and its release stops
    ActionChains(browser).click_and_hold(button).perform()
    wait_for(lambda: vehicle_pct(robot)[0] > 0.0, 5, "a new press driving")
    assert not note.is_displayed()
    time.sleep(1.2 * DEADMAN_S)  # held past its first drive's deadman_s: resent
    assert vehicle_pct(robot)[0] > 0.0
    ActionChains(browser).release(button).perform()
    wait_for(lambda: vehicle_pct(robot) == (0.0, 0.0), 5.0, "stopped on release")


DRIVE = {"left": 20, "right": 20, "duration_s": 0.5}
RESEND_S = 0.3 * DEADMAN_S  # a held key's resends: every deadman_s / 3 (here a little less)


def page_ms() -> float:
    """A page's clock: any monotonic clock of its own."""
    return time.monotonic() * 1000.0 + 7_000_000.0


def test_a_page_without_press_ms_is_held_stopped_until_it_pauses_or_stops(robot: Running) -> None:
    # An open page whose console.js is older than the daemon (it sends no press_ms): the
    # console takes drives less than deadman_s apart (by their sent_ms) as one press.
    async def program() -> None:
        async with ws_to(robot) as w:
            for _ in range(4):  # held: a resend every deadman_s / 3
                assert (await w.request("drive", sent_ms=page_ms(), **DRIVE))["ok"]
                await asyncio.sleep(RESEND_S)
            stop_from_elsewhere(robot)
            wait_for(lambda: vehicle_pct(robot) == (0.0, 0.0), 5.0, "the stop obeyed")
            for _ in range(4):  # the same press, every resend sent after the stop
                reply = await w.request("drive", sent_ms=page_ms(), **DRIVE)
                assert reply["error"]["reason"] == "stopped", reply
                assert vehicle_pct(robot) == (0.0, 0.0)
                await asyncio.sleep(RESEND_S)
            await asyncio.sleep(1.2 * DEADMAN_S)  # nothing for longer than deadman_s: released
            assert (await w.request("drive", sent_ms=page_ms(), **DRIVE))["ok"]  # a new press
            stop_from_elsewhere(robot)
            assert (await w.request("drive", sent_ms=page_ms(), **DRIVE))["error"]["reason"] == (
                "stopped"
            )
            # its own stop (the old page's release) ends the press at once; a press within
            # deadman_s of another client's stop is still refused (must be made again later)
            assert (await w.request("stop", sent_ms=page_ms()))["ok"]
            await asyncio.sleep(1.2 * DEADMAN_S)
            assert (await w.request("drive", sent_ms=page_ms(), **DRIVE))["ok"]
            assert (await w.request("stop", sent_ms=page_ms()))["ok"]

    asyncio.run(program())


def test_a_press_that_began_before_another_clients_stop_drives_no_more(robot: Running) -> None:
    async def program() -> None:
        async with ws_to(robot) as w:
            press = page_ms()
            assert (await w.request("drive", sent_ms=page_ms(), press_ms=press, **DRIVE))["ok"]
            await asyncio.sleep(RESEND_S)
            stop_from_elsewhere(robot)
            # a pause (longer than deadman_s) does not end a press that says when it began
            await asyncio.sleep(1.4 * DEADMAN_S)
            reply = await w.request("drive", sent_ms=page_ms(), press_ms=press, **DRIVE)
            assert reply["error"]["code"] == "rejected" and reply["error"]["reason"] == "stopped"
            assert "another client" in reply["error"]["message"], reply
            assert vehicle_pct(robot) == (0.0, 0.0)
            # a new press drives (one less than deadman_s after the stop would not: the
            # guard for a press placed late by the link's delay, tests/test_console_stop_round2)
            new = page_ms()
            assert (await w.request("drive", sent_ms=page_ms(), press_ms=new, **DRIVE))["ok"]
            for bad in ({"press_ms": page_ms() + 1000.0, "sent_ms": page_ms()},  # after sending
                        {"press_ms": True, "sent_ms": page_ms()},
                        {"press_ms": "1", "sent_ms": page_ms()},
                        {"press_ms": page_ms()}):  # fmt: skip  # no sent_ms to judge it by
                reply = await w.request("drive", **bad, **DRIVE)
                assert reply["error"]["reason"] == "bad_argument", (bad, reply)
            assert (await w.request("stop", sent_ms=page_ms()))["ok"]

    asyncio.run(program())


@pytest.mark.parametrize(
    "host",
    ["127.0.0.1", "127.0.0.1:18602", "localhost", "LOCALHOST:80", "robot.lan:8080", "[::1]",
     "[::1]:18602", "[::ffff:127.0.0.1]:18602", "10.1.2.3:1"],
)  # fmt: skip
def test_a_well_formed_host_naming_the_console_is_accepted(host: str) -> None:
    assert allowed_host(host, frozenset({"localhost", "robot.lan"}))


@pytest.mark.parametrize(
    "host",
    ["foo@127.0.0.1", "127.0.0.1:18602; script-src *", "attacker.com:80@127.0.0.1",
     "127.0.0.1:18602 wss://evil.example", "127.0.0.1:", "127.0.0.1:x", "127.0.0.1:99999",
     "::1", "[::1", "[::1]x", "[fe80::1%eth0]:80", "[127.0.0.1]", "evil.example:18602",
     "0x7f.0.0.1", "2130706433", "127.0.0.1\t", " 127.0.0.1", "", "robot.lan:80:80",
     "a b.lan", "-robot.lan", "robot..lan", "127.0.0.1/x", "127.0.0.1?", "robot.lan.",
     "ro\u0301bot.lan"],
)  # fmt: skip
def test_a_host_that_is_not_a_plain_host_and_port_is_refused(host: str) -> None:
    assert not allowed_host(host, frozenset({"localhost", "robot.lan", "a b.lan", "robot.lan."}))


def test_a_refused_host_is_never_copied_into_a_header(robot: Running) -> None:
    console = robot.daemon.console
    assert console is not None
    port = console.port

    async def program() -> None:
        async with aiohttp.ClientSession() as s:
            for host in (f"127.0.0.1:{port}; script-src *", "foo@127.0.0.1",
                         f"attacker.com:80@127.0.0.1:{port}"):  # fmt: skip
                async with s.get(console.url, headers={"Host": host}) as resp:
                    assert resp.status == 421, host
                    csp = resp.headers["Content-Security-Policy"]
                    assert "script-src 'self';" in csp and "script-src *" not in csp, csp
                    assert "@" not in csp and "attacker" not in csp, csp
            async with s.get(console.url, headers={"Host": f"127.0.0.1:{port}"}) as resp:
                assert resp.status == 200
                csp = resp.headers["Content-Security-Policy"]
                assert f"connect-src 'self' ws://127.0.0.1:{port} wss://127.0.0.1:{port};" in csp

    asyncio.run(program())
