"""The console page and the limit before auth (a review of 4506776): until its ``auth``
succeeds the console closes a page that sends a message over 4096 bytes (1009), but the page
sent any request at once. After a reconnection the token box stays hidden while the page's
automatic ``auth`` is in flight, so "Send mission" clicked then (a mission is easily over
4 KB) got the page closed, and the page said only "disconnected". Now such a request is held
and sent once the auth succeeds (refused, saying why, if it fails or a stop comes first), and
a close's reason is shown. The real daemon (``sim://`` devices) with a token, its console on
127.0.0.1, Debian's headless chromium (helpers from tests/test_console.py). The seam that
slows the page's auth is the daemon's own: an address that failed too often has every
``auth`` evaluated only after ``auth_fail_delay_s`` (here held instead until the test lets it
go: :class:`HeldAuth`). A review of c998465: the held Send's reply then comes seconds after the
click, and it marked the draft "sent", dropping an edit made meanwhile; now only a draft still
as sent is taken as on the robot."""

from __future__ import annotations

import asyncio
import dataclasses
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from selenium import webdriver
from selenium.webdriver.common.by import By

from tests import test_console
from tests.test_console import (
    TOKEN,
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
from x6wd.app.client import RemoteClient, RequestFailed

pytestmark = pytest.mark.integration

browser = test_console.browser  # the same module-scoped fixture: one chromium per module

AUTH_DELAY_S = 3.0  # auth_fail_delay_s: how long the page's auth waits once the budget is out
BIG = 150  # waypoints: about 6 KB as the page's JSON (the limit before auth: 4096 bytes)
# every text #msg and #conn showed (a later message replaces the one a test looks for)
WATCH = """
window.seen = { msg: [], conn: [] };
for (const id of ["msg", "conn"]) {
  const el = document.getElementById(id);
  // each text set, also two set in one task (one callback, a record each)
  new MutationObserver((records) => {
    for (const r of records) for (const n of r.addedNodes) window.seen[id].push(n.textContent);
  }).observe(el, { childList: true });
}
"""


@pytest.fixture(scope="module")
def robot(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Running]:
    cfg = console_config(tmp_path_factory.mktemp("preauth"), token=True)
    cfg = dataclasses.replace(
        cfg, server=dataclasses.replace(cfg.server, auth_fail_delay_s=AUTH_DELAY_S)
    )
    with daemon_with(cfg) as r:
        wait_for(lambda: has_fix(r), 30, "a fix")
        yield r


class HeldAuth:
    """The page's ``auth`` held until the test releases it: the seam is the daemon's own, the
    control server's nap before it evaluates an ``auth`` from an address whose budget is out
    (``auth_fail_delay_s``). Once armed, a console page's nap there waits for release()
    instead of the 3 s (other clients' naps are as before). A fixed 3 s raced the clicks and
    edits made meanwhile, each several WebDriver round trips (a loaded host: seconds)."""

    def __init__(self, r: Running, monkeypatch: pytest.MonkeyPatch) -> None:
        server = r.daemon.server
        assert server is not None
        self.armed = False
        self.released = threading.Event()
        nap = server._nap

        async def held_nap(c: Any, seconds: float) -> None:
            if not (self.armed and c.kind):  # not armed, or not a console page
                return await nap(c, seconds)
            c.napping = True  # as the server's own nap: an eviction still ends it
            try:
                end = time.monotonic() + 60.0  # a test that never releases: as a late auth
                while not self.released.is_set() and time.monotonic() < end:
                    await asyncio.sleep(0.01)
            finally:
                c.napping = False

        monkeypatch.setattr(server, "_nap", held_nap)

    def arm(self) -> None:
        self.released.clear()
        self.armed = True

    def release(self) -> None:
        self.armed = False
        self.released.set()


@pytest.fixture
def held_auth(robot: Running, monkeypatch: pytest.MonkeyPatch) -> Iterator[HeldAuth]:
    gate = HeldAuth(robot, monkeypatch)
    try:
        yield gate
    finally:
        gate.release()


def big_draft() -> list[list[float]]:
    """``BIG`` waypoints near the start, inside the geofence."""
    return [north(0.2 * i, float(i % 10)) for i in range(BIG)]


def put_draft(d: webdriver.Chrome, points: list[list[float]]) -> None:
    """The editor holds ``points``, not sent (as after editing it)."""
    js(d, "x6wd.draft = arguments[0]; x6wd.dirty = true; x6wd.redraw()", points)
    size = js(d, "return JSON.stringify({waypoints: x6wd.draft}).length")
    assert size > 4096, size


def slow_auth_from_here(r: Running) -> None:
    """Wrong tokens from 127.0.0.1 until the address's budget is out: from then on every
    ``auth`` from it (the page's too) is evaluated ``AUTH_DELAY_S`` late (the budget comes
    back at 0.1 per second: this holds ~10 s after the last failure)."""
    for _ in range(30):
        t0 = time.monotonic()
        with pytest.raises(RequestFailed, match="wrong token"):
            RemoteClient("127.0.0.1", r.port, token="not-the-token", timeout_s=30)
        if time.monotonic() - t0 >= AUTH_DELAY_S * 0.9:
            return
    raise AssertionError("the failed-auth budget never ran out")


def login_shown(d: webdriver.Chrome, r: Running) -> None:
    """A fresh page without the token: it asks for it (not authenticated)."""
    open_page(d, r)
    js(d, "sessionStorage.clear()")
    open_page(d, r)
    wait_for(lambda: d.find_element(By.ID, "login").is_displayed(), 10, "the token box")
    assert not js(d, "return x6wd.authed")
    js(d, WATCH)


def test_a_mission_sent_while_a_reconnected_pages_auth_is_in_flight_waits_for_it(
    robot: Running, browser: webdriver.Chrome, held_auth: HeldAuth
) -> None:
    assert robot.daemon.controller is not None
    open_page(browser, robot, f"#token={TOKEN}")
    page_ready(browser)
    draft = big_draft()
    put_draft(browser, draft)
    slow_auth_from_here(robot)
    held_auth.arm()  # the page's next auth waits until released below
    # the link drops (as a wifi hiccup would): the page reconnects and sends its auth itself
    js(browser, "window.oldWs = x6wd.ws; window.oldInfo = x6wd.info; x6wd.ws.close()")
    wait_for(
        lambda: js(
            browser,
            "return x6wd.ws !== window.oldWs && x6wd.info !== window.oldInfo"
            " && x6wd.pending.size > 0 && !x6wd.authed",
        ),
        15, "the reconnected page's auth in flight",
    )  # fmt: skip
    js(
        browser,
        "window.newWs = x6wd.ws; window.closes = [];"
        "x6wd.ws.addEventListener('close', (ev) => window.closes.push([ev.code, ev.reason]));"
        "document.getElementById('btn-send').addEventListener('click',"
        " () => { window.authedAtClick = x6wd.authed; }, { capture: true })",
    )
    js(browser, WATCH)
    assert not browser.find_element(By.ID, "login").is_displayed()  # nothing says wait
    browser.find_element(By.ID, "btn-send").click()  # a real click
    held_auth.release()  # the auth goes on now
    wait_for(
        lambda: len(robot.daemon._mission) == BIG or js(browser, "return window.closes.length"),
        20, "the mission on the robot, or the page closed",
    )  # fmt: skip
    assert js(browser, "return window.authedAtClick") is False, "clicked after the auth"
    assert js(browser, "return window.closes") == [], "the page was closed"
    assert len(robot.daemon._mission) == BIG
    for got, want in zip(robot.daemon._mission, draft, strict=True):
        assert got == pytest.approx(tuple(want), abs=1e-9)
    wait_for(lambda: "mission.load: ok" in text(browser, "msg"), 10, "the reply shown")
    assert any("waiting for the token" in m for m in js(browser, "return window.seen.msg"))
    assert js(browser, "return x6wd.ws === window.newWs && x6wd.authed")
    wait_for(lambda: "on the robot" in text(browser, "mission-state"), 10, "its map event")


def test_held_requests_are_refused_on_a_wrong_token_and_a_stop_is_never_held(
    robot: Running, browser: webdriver.Chrome
) -> None:
    login_shown(browser, robot)
    js(browser, "window.firstWs = x6wd.ws")

    def held(cmd: str) -> bool:
        seen = js(browser, "return window.seen.msg")
        return any(m.startswith(cmd + ": waiting for the token") for m in seen)

    def closed() -> bool:
        return bool(js(browser, "return x6wd.ws !== window.firstWs"))

    put_draft(browser, big_draft())
    before = len(robot.daemon._mission)
    # Send mission (under the token box: clicked from the script), then start behind it
    js(browser, "document.getElementById('btn-send').click()")
    js(browser, "document.getElementById('btn-start').click()")
    wait_for(lambda: held("start") or closed(), 10, "both held, or the page closed")
    assert not closed(), js(browser, "return window.seen")
    assert held("mission.load")
    # STOP goes at once, and what was held is not sent after it
    browser.find_element(By.ID, "btn-stop").click()  # a real click (above the token box)
    wait_for(lambda: "stop: ok" in js(browser, "return window.seen.msg.join('|')"), 10, "stopped")
    seen = js(browser, "return window.seen.msg")
    assert any("mission.load: not sent: a stop came before" in m for m in seen), seen
    assert any("start: not sent: a stop came before" in m for m in seen), seen
    assert not closed()
    # held again, then a wrong token: refused, saying so
    js(browser, "window.seen.msg = []; document.getElementById('btn-send').click()")
    wait_for(lambda: held("mission.load"), 10, "held")
    field = browser.find_element(By.ID, "token-input")
    field.send_keys("not-the-token")
    browser.find_element(By.CSS_SELECTOR, "#token-form button").click()
    wait_for(
        lambda: "mission.load: not sent: the token was refused" in text(browser, "msg"),
        20, "the refusal",
    )  # fmt: skip
    assert "wrong token" in text(browser, "msg")
    assert not closed(), "the page was closed"
    assert len(robot.daemon._mission) == before


def test_a_close_for_a_message_too_big_before_auth_says_why(
    robot: Running, browser: webdriver.Chrome
) -> None:
    # a page (or a script in it) that sends 5 KB before its auth: the console closes it
    login_shown(browser, robot)
    js(browser, "x6wd.ws.send(JSON.stringify({id: 0, cmd: 'hello', pad: 'x'.repeat(5000)}))")
    why = "message too big before auth: at most 4096 bytes until then"
    wait_for(lambda: why in text(browser, "msg"), 10, "the reason in the message line")
    assert "1009" in text(browser, "msg")
    wait_for(
        lambda: any(why in c for c in js(browser, "return window.seen.conn")), 10, "in the status"
    )
    assert "disconnected: " + why in js(browser, "return window.seen.conn")
    # and it connects again, asking for the token
    wait_for(lambda: text(browser, "conn") == "token needed", 10, "reconnected")


def reconnect_with_slow_auth(d: webdriver.Chrome, r: Running, held_auth: HeldAuth) -> None:
    """The link drops; the page reconnects and its own ``auth`` is in flight, held until
    ``held_auth`` is released; every text the message line shows is kept from here on."""
    slow_auth_from_here(r)
    held_auth.arm()
    js(d, "window.oldWs = x6wd.ws; window.oldInfo = x6wd.info; x6wd.ws.close()")
    wait_for(
        lambda: js(
            d,
            "return x6wd.ws !== window.oldWs && x6wd.info !== window.oldInfo"
            " && x6wd.pending.size > 0 && !x6wd.authed",
        ),
        15, "the reconnected page's auth in flight",
    )  # fmt: skip
    js(d, WATCH)


def test_an_edit_made_while_send_is_held_is_kept_and_the_page_says_it_is_not_sent(
    robot: Running, browser: webdriver.Chrome, held_auth: HeldAuth
) -> None:
    # review of c998465: the held Send's reply came 3 s after the click and set the page to
    # "not edited", so an edit made meanwhile was dropped and the old mission shown as sent
    n = 170
    draft = [north(0.2 * i, float(i % 10)) for i in range(n)]
    open_page(browser, robot, f"#token={TOKEN}")
    page_ready(browser)
    js(browser, "x6wd.draft = arguments[0]; x6wd.dirty = true;", draft)
    # the list drawn for it (as after an edit), so its rows' delete buttons are there
    js(browser, "document.getElementById('wp-list').dispatchEvent(new Event('scroll'))")
    reconnect_with_slow_auth(browser, robot, held_auth)
    js(
        browser,
        "document.getElementById('wp-list').addEventListener('click',"
        " () => { window.authedAtEdit = x6wd.authed; }, { capture: true })",
    )
    browser.find_element(By.ID, "btn-send").click()  # a real click: held
    # the operator deletes waypoint 1 while it waits (the row's x button, a real click)
    browser.find_element(By.CSS_SELECTOR, "#wp-rows button[data-i='0']").click()
    assert js(browser, "return window.authedAtEdit") is False, "edited after the auth"
    seen = js(browser, "return window.seen.msg")
    assert any(m.startswith("mission.load: waiting for the token") for m in seen), seen
    held_auth.release()  # the auth goes on now
    # the robot gets the mission as clicked (held requests are sent as they were asked for)
    wait_for(lambda: len(robot.daemon._mission) == n, 20, "the mission on the robot")
    for got, want in zip(robot.daemon._mission, draft, strict=True):
        assert got == pytest.approx(tuple(want), abs=1e-9)
    # once the reply and the robot's map event are in, the edit is still there, not sent
    wait_for(
        lambda: js(
            browser,
            "return x6wd.map.waypoints.length === arguments[0]"
            " && window.seen.msg.some((m) => m.startsWith('mission.load: ok'))",
            n,
        ),
        15, "the reply and the map event",
    )  # fmt: skip
    assert js(browser, "return x6wd.dirty") is True
    kept = js(browser, "return x6wd.draft")
    assert len(kept) == n - 1
    for got, want in zip(kept, draft[1:], strict=True):
        assert got == pytest.approx(want, abs=1e-12)
    assert text(browser, "mission-state") == f"{n - 1} waypoints, edited: not sent"
    said = [m for m in js(browser, "return window.seen.msg") if m.startswith("mission.load: ok")]
    assert len(said) == 2, said  # "ok", then at once what the robot has
    assert said[-1].startswith("mission.load: ok, but the robot has the mission as sent at "), said
    assert f"({n} waypoints): your edits since are not sent" in said[-1], said
    # and Send sends the edit
    browser.find_element(By.ID, "btn-send").click()
    wait_for(lambda: len(robot.daemon._mission) == n - 1, 10, "the edit on the robot")
    wait_for(
        lambda: text(browser, "mission-state") == f"{n - 1} waypoints on the robot", 10, "shown"
    )
    assert js(browser, "return x6wd.dirty") is False


def test_a_file_read_while_held_says_it_replaced_the_edits_made_meanwhile(
    robot: Running, browser: webdriver.Chrome, tmp_path: Path, held_auth: HeldAuth
) -> None:
    # the same wait for a mission file (mission.parse over 4 KB): it still replaces the draft
    # (the operator asked for it), but an edit made while it waited is named, not lost unseen
    n = 200
    f = tmp_path / "long.csv"
    points = [north(0.2 * i, float(i % 10)) for i in range(n)]
    f.write_text("lat,lon\n" + "".join(f"{p[0]:.9f},{p[1]:.9f}\n" for p in points))
    assert f.stat().st_size > 4096
    open_page(browser, robot, f"#token={TOKEN}")
    page_ready(browser)
    js(browser, "x6wd.draft = arguments[0]; x6wd.dirty = true;", [north(1), north(2), north(3)])
    js(browser, "document.getElementById('wp-list').dispatchEvent(new Event('scroll'))")
    reconnect_with_slow_auth(browser, robot, held_auth)
    browser.find_element(By.ID, "mission-file").send_keys(str(f))
    wait_for(
        lambda: any(
            m.startswith("mission.parse: waiting for the token")
            for m in js(browser, "return window.seen.msg")
        ),
        10, "the file's request held",
    )  # fmt: skip
    browser.find_element(By.CSS_SELECTOR, "#wp-rows button[data-i='0']").click()  # an edit
    assert js(browser, "return x6wd.draft.length === 2 && !x6wd.authed"), "edited after the auth"
    held_auth.release()  # the auth goes on now
    wait_for(lambda: js(browser, "return x6wd.draft.length") == n, 20, "the file read")
    said = f"long.csv: {n} waypoints (not sent yet); it replaced the edits made while it was read"
    assert said in js(browser, "return window.seen.msg")
