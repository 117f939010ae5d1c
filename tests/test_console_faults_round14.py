"""What the web console shows of a robot in trouble (an outside audit, round 14): why a
failsafe paused it (telemetry ``extra.failsafe``), each device's current ``reason`` rather than
an older ``last_error``, and the recorder's state. The real daemon with ``sim://`` devices
and its console, Debian's chromium through chromedriver (tests/test_console.py's fixtures);
faults made in the simulated world (its compass's I2C error injector), the file system (the
recording folder replaced by a file) and the operator-link failsafe (nobody asks)."""

from __future__ import annotations

import dataclasses
import errno
import math
import random
import shutil
import ssl
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
    shot,
)
from tests.test_daemon import Running, wait_for
from tests.test_health import Storm
from x6wd.app.client import RemoteClient
from x6wd.core.config import Config, FailsafeConfig
from x6wd.core.records import Mode

pytestmark = pytest.mark.integration
__all__ = ["browser", "chromium"]  # the fixture

# the ports of this file's daemons (the brief's range: 43600-43699)
PORTS = iter(range(43610, 43690, 3))


def ported(cfg: Config) -> Config:
    """``cfg`` with its control, gpsd and console ports from this file's range."""
    base = next(PORTS)
    return dataclasses.replace(
        cfg,
        server=dataclasses.replace(cfg.server, port=base),
        gpsd=dataclasses.replace(cfg.gpsd, port=base + 1),
        console=dataclasses.replace(cfg.console, port=base + 2),
    )


@pytest.fixture
def robot(tmp_path: Path) -> Iterator[Running]:
    """A HIL daemon with its console; the operator-link failsafe holds after 2 s."""
    cfg = dataclasses.replace(
        console_config(tmp_path),
        failsafe=FailsafeConfig(operator_timeout_s=2.0, operator_action="hold"),
    )
    with daemon_with(ported(cfg)) as r:
        wait_for(lambda: has_fix(r), 30, "a fix")
        wait_for(lambda: "ekf_sigma_m" in r.daemon.last_telemetry.extra, 30, "an EKF position")  # type: ignore[union-attr]
        yield r


def pill(d: webdriver.Chrome, element_id: str) -> tuple[bool, str, str]:
    """(shown, text, class) of a top-bar pill."""
    script = (
        "const e = document.getElementById(arguments[0]); if (!e) return [false, '', ''];"
        "return [!e.hidden && e.offsetParent !== null, e.textContent, e.className]"
    )
    shown, words, cls = js(d, script, element_id)
    return shown, words, cls


def device_rows(d: webdriver.Chrome) -> dict[str, dict[str, str]]:
    """The devices table: name -> state, the detail (why it is in that state now) and the
    older fault marked "last error" (its .last-error part, apart from the detail)."""
    rows = js(d, """
return [...document.querySelectorAll('#devices tbody tr')].map((tr) => {
  const td = tr.cells[3], old = td ? td.querySelector('.last-error') : null;
  const all = td ? td.textContent : '';
  return [tr.cells[0].textContent, tr.cells[1].textContent,
          old ? all.replace(old.textContent, '') : all, old ? old.textContent : ''];
});""")  # fmt: skip
    return {r[0]: {"state": r[1], "detail": r[2], "last": r[3]} for r in rows}


def test_a_failsafe_pause_is_shown_with_its_reason_while_it_holds_also_on_a_page_opened_later(
    robot: Running, browser: webdriver.Chrome, tmp_path: Path
) -> None:
    # Audit: after a failsafe pause the page said "PAUSED / IDLE" and the word "failsafe"
    # appeared nowhere (console.js never read telemetry extra; the one-off state message was
    # overwritten, and a page opened later never got it), while `x6wd client status` printed
    # "failsafe  operator link lost (the last one that acted)".
    r = robot
    with RemoteClient("127.0.0.1", r.port) as c:  # the operator starts it and goes away
        c.request("mission.load", waypoints=[north(40)])
        assert c.request("start")["mode"] == "RUNNING"
    wait_for(lambda: r.daemon.controller.mode == Mode.PAUSED, 10, "the failsafe's pause")
    assert r.daemon.last_telemetry.extra.get("failsafe") == "operator link lost"  # type: ignore[union-attr]
    open_page(browser, r)  # opened after the pause: no state event ever reaches it
    page_ready(browser)
    # shown persistently: every telemetry (4 a second) and status answer rewrites the page
    wait_for(lambda: pill(browser, "failsafe")[0], 5, "the failsafe shown")
    for _ in range(12):
        shown, words, cls = pill(browser, "failsafe")
        assert shown and words == "failsafe: operator link lost", (shown, words)
        assert "bad" in cls.split(), cls
        assert "failsafe: operator link lost" in browser.find_element(By.TAG_NAME, "body").text
        time.sleep(0.25)
    shot(browser, tmp_path, "failsafe-pause.png")
    # resumed (this page is the operator now): the pause no longer holds, the failsafe is
    # the last one that acted, as the client says, not an alarm
    browser.find_element(By.ID, "btn-resume").click()
    wait_for(lambda: r.daemon.controller.mode == Mode.RUNNING, 5, "resumed")
    wait_for(lambda: pill(browser, "failsafe")[1] == "last failsafe: operator link lost", 5,
             "the failsafe shown as the last one")  # fmt: skip
    assert "bad" not in pill(browser, "failsafe")[2].split()
    # the operator pauses from elsewhere, and a page opened now (it saw no pause) says the
    # failsafe is the last one that acted, not what holds the robot: the telemetry's
    # paused_by says who paused (it could not tell before)
    with RemoteClient("127.0.0.1", r.port) as c:
        c.request("pause")
    wait_for(lambda: r.daemon.controller.mode == Mode.PAUSED, 5, "the operator's pause")
    open_page(browser, r)
    page_ready(browser)
    wait_for(lambda: pill(browser, "failsafe")[0], 5, "the failsafe shown")
    for _ in range(4):
        shown, words, cls = pill(browser, "failsafe")
        assert words == "last failsafe: operator link lost" and "bad" not in cls.split()
        time.sleep(0.25)
    browser.find_element(By.ID, "btn-resume").click()
    wait_for(lambda: r.daemon.controller.mode == Mode.RUNNING, 5, "resumed again")
    # a new start clears it (telemetry extra.failsafe gone): nothing shown
    browser.find_element(By.ID, "btn-stop").click()
    wait_for(lambda: r.daemon.controller.mode == Mode.IDLE, 5, "stopped")
    browser.find_element(By.ID, "btn-start").click()
    wait_for(lambda: r.daemon.controller.mode == Mode.RUNNING, 5, "started again")
    wait_for(lambda: not pill(browser, "failsafe")[0], 5, "the failsafe cleared")
    assert "failsafe" not in browser.find_element(By.TAG_NAME, "header").text
    browser.find_element(By.ID, "btn-stop").click()


def test_the_devices_detail_is_the_state_s_reason_and_an_old_error_is_marked_as_such(
    robot: Running, browser: webdriver.Chrome
) -> None:
    # Audit: the detail was `last_error || reason`: a compass healthy again kept showing an
    # I2C error it had recovered from, as if it were its state now (docs/protocol.md:
    # `reason` is why the device is in its state now, `last_error` may be older).
    r = robot
    storm = Storm()
    r.daemon.devices.backend("sim").compass.injector = storm  # the simulated CMPS10's I2C
    open_page(browser, r)
    page_ready(browser)
    wait_for(lambda: device_rows(browser)["compass"]["state"] == "connected", 10, "compass up")
    # the storm lasts until the daemon has said so and the page has shown it: a storm of a
    # fixed 0.2 s could pass unseen by a compass poll late under load
    storm.code, storm.until_s = errno.EIO, math.inf
    with RemoteClient("127.0.0.1", r.port) as c:
        wait_for(
            lambda: "Input/output error" in c.request("status")["devices"]["compass"]["reason"],
            10,
            "the I2C error as the compass's reason",
        )
        wait_for(
            lambda: device_rows(browser)["compass"]["state"] != "connected", 5, "shown degraded"
        )
        storm.until_s = -math.inf
        comp = wait_for(
            lambda: (s := c.request("status")["devices"]["compass"])["state"] == "connected" and s,
            10,
            "compass recovered",
        )
    assert "Input/output error" in comp["last_error"] and comp["reason"] == "", comp
    wait_for(lambda: device_rows(browser)["compass"]["state"] == "connected", 5, "shown recovered")
    for _ in range(4):  # redrawn at each telemetry: stays so
        row = device_rows(browser)["compass"]
        assert "Input/output" not in row["detail"], row
        assert row["last"].startswith("last error: ") and "Input/output error" in row["last"], row
        time.sleep(0.25)
    # a device whose reason is its state's now shows that reason, its old error apart
    status = js(browser, "return x6wd.devices")
    for name, h in status.items():
        if h and h.get("reason"):
            assert device_rows(browser)[name]["detail"].startswith(h["reason"][:20]), (name, h)


def test_the_recorder_s_state_and_reason_are_shown(
    tmp_path: Path, browser: webdriver.Chrome
) -> None:
    # Audit: with the recording failing `x6wd client status` said "recorder failing: ..."
    # while the page showed nothing of the recorder (only the motor link of status' links).
    cfg = ported(console_config(tmp_path))
    with daemon_with(cfg) as r:
        wait_for(lambda: has_fix(r), 30, "a fix")
        open_page(browser, r)
        page_ready(browser)
        wait_for(lambda: "recorder" in device_rows(browser), 5, "the recorder's row")
        assert device_rows(browser)["recorder"]["state"] == "ok"
        rec_dir = Path(cfg.recorder.dir)
        (first,) = rec_dir.glob("x6wd-*.jsonl")  # the run's part being written
        # the folder replaced by one where the part is not a file, nor its next one (EISDIR):
        # the recorder notices within 5 s, and every open of the next part fails
        shutil.rmtree(rec_dir)
        for part in (first, first.with_name(f"{first.stem}.1{first.suffix}")):
            part.mkdir(parents=True)
        with RemoteClient("127.0.0.1", r.port) as c:
            st = wait_for(
                lambda: (s := c.request("status"))["recorder"]["state"] == "failing" and s,
                15,
                "the recorder failing",
            )
        assert st["links"]["recorder"] == "failing"
        wait_for(lambda: device_rows(browser)["recorder"]["state"] == "failing", 5, "shown failing")
        row = device_rows(browser)["recorder"]
        shot(browser, tmp_path, "recorder-failing.png")
        assert "records not recorded" in row["detail"] and "Is a directory" in row["detail"], row
        assert js(browser, "return getComputedStyle(document.querySelector("
                           "'#devices td.st-failing')).fontWeight") == "700"  # fmt: skip


def test_a_compass_the_ekf_refuses_shows_why_not_its_older_i2c_error(
    robot: Running, browser: webdriver.Chrome, tmp_path: Path
) -> None:
    # Audit: a compass degraded with reason "untrusted: the EKF refused 57 % of 200 readings"
    # was shown as the I2C error it had recovered from before
    r = robot
    world = r.daemon.devices.backend("sim")
    storm = Storm()
    world.compass.injector = storm
    storm.code, storm.until_s = errno.EIO, time.monotonic() + 0.2  # a brief glitch, recovered
    with RemoteClient("127.0.0.1", r.port) as c:
        wait_for(lambda: "Input/output" in c.request("status")["devices"]["compass"]["last_error"],
                 5, "the glitch")  # fmt: skip
        # the simulated CMPS10 reads a random bearing each time (a valid register set)
        rng = random.Random(14)
        set_state = world.compass.set_state
        world.compass.set_state = lambda t, h, *a: set_state(t, rng.uniform(0.0, 360.0), *a)
        comp = wait_for(
            lambda: (
                (s := c.request("status")["devices"]["compass"])["reason"][:9] == "untrusted" and s
            ),
            40,
            "the compass untrusted",
        )
    assert comp["state"] == "degraded" and "Input/output" in comp["last_error"], comp
    open_page(browser, r)
    page_ready(browser)
    wait_for(lambda: device_rows(browser)["compass"]["state"] == "degraded", 5, "shown degraded")
    row = device_rows(browser)["compass"]
    shot(browser, tmp_path, "compass-untrusted.png")
    assert row["detail"].startswith("untrusted: the EKF refused "), row
    assert row["last"].startswith("last error: ") and "Input/output" in row["last"], row


def test_the_status_problems_the_client_prints_are_shown_too(
    tmp_path: Path, browser: webdriver.Chrome
) -> None:
    # the same check for the rest of `status` that `x6wd client status` prints as a problem:
    # here the TLS certificate's warning (2 days left: "expiring")
    cfg = ported(console_config(tmp_path, tls=True))
    with daemon_with(cfg) as r:
        wait_for(lambda: has_fix(r), 30, "a fix")
        trust = ssl.create_default_context(cafile=cfg.server.tls_cert)
        with RemoteClient("127.0.0.1", r.port, ssl_context=trust) as c:
            tls = c.request("status")["server"]["tls"]
        assert tls["state"] == "expiring" and tls["warning"], tls
        open_page(browser, r)
        page_ready(browser)
        wait_for(lambda: "tls certificate" in device_rows(browser), 5, "the certificate's row")
        row = device_rows(browser)["tls certificate"]
        assert row["state"] == "expiring" and row["detail"] == tls["warning"], row


def test_a_long_failsafe_reason_is_read_whole_at_a_laptops_width(
    tmp_path: Path, browser: webdriver.Chrome
) -> None:
    # Review: at 701-1240 px the pill cut the gps jump's reason short ("... (GPS back ...")
    # with no way to read the rest; the advice is its end
    with daemon_with(ported(console_config(tmp_path))) as r:
        wait_for(lambda: has_fix(r), 30, "a fix")
        world = r.daemon.devices.backend("sim")
        browser.set_window_size(1024, 800)
        try:
            open_page(browser, r)
            page_ready(browser)
            with RemoteClient("127.0.0.1", r.port) as c:
                c.request("mission.load", waypoints=[north(60)])
                c.request("start")
                time.sleep(3)
                v = world.vehicle  # carried 80 m east while driving
                v._state = dataclasses.replace(v._state, east_m=v._state.east_m + 80.0)
                wait_for(lambda: c.request("status")["mode"] == "PAUSED", 60, "the jump's pause")
                why = r.daemon.last_telemetry.extra["failsafe"]  # type: ignore[union-attr]
                assert len(why) > 100, why
                wait_for(lambda: pill(browser, "failsafe")[1] == "failsafe: " + why, 5, "shown")
                shot(browser, tmp_path, "failsafe-long-1024.png")
                cut = js(browser, "const e = document.getElementById('failsafe');"
                                  "return [e.scrollWidth > e.clientWidth, e.title]")  # fmt: skip
                assert cut == [False, "failsafe: " + why], cut
                c.request("stop")
        finally:
            browser.set_window_size(1400, 1150)


def test_corrupt_compass_input_and_a_stalled_recorder_are_shown_as_the_client_says(
    tmp_path: Path, browser: webdriver.Chrome
) -> None:
    # Review: the client printed "compass  corrupt input since start: 30 bearing mismatches"
    # and the page had no row; a stalled recorder read "? (0 records not recorded)" with
    # hundreds of records waiting
    import threading

    from x6wd.app.client import render_status

    with daemon_with(ported(console_config(tmp_path))) as r:
        wait_for(lambda: has_fix(r), 30, "a fix")
        open_page(browser, r)
        page_ready(browser)
        world = r.daemon.devices.backend("sim")
        read, bad = world.compass._read, [0]

        def disagreeing(register: int, length: int) -> list[int]:  # the bearing byte off
            v = list(read(register, length))
            if register <= 1 < register + length and bad[0] < 30:
                bad[0] += 1
                v[1 - register] = (v[1 - register] + 100) % 256
            return v

        world.compass._read = disagreeing
        wait_for(lambda: bad[0] >= 30, 20, "30 disagreeing reads")
        wait_for(lambda: "compass input" in device_rows(browser), 5, "the compass's corrupt row")
        row = device_rows(browser)["compass input"]
        assert row["state"] == "corrupt" and "bearing mismatches" in row["detail"], row
        # a write that does not return: records wait in memory, no error yet
        writer, gate = r.daemon.recorder, threading.Event()
        inner = writer.recorder

        class Stuck:
            def __getattr__(self, name: str) -> object:
                f = getattr(inner, name)
                if callable(f) and name.startswith("record"):
                    return lambda *a, **kw: (gate.wait(30), f(*a, **kw))[1]
                return f

        writer.recorder = Stuck()
        try:
            with RemoteClient("127.0.0.1", r.port) as c:
                st = wait_for(
                    lambda: (s := c.request("status"))["recorder"]["state"] == "stalled" and s,
                    20,
                    "the recorder stalled",
                )
            assert "records waiting" in render_status(st), render_status(st)
            wait_for(lambda: device_rows(browser)["recorder"]["state"] == "stalled", 5, "shown")
            detail = device_rows(browser)["recorder"]["detail"]
            assert detail.startswith("a write has taken ") and "records waiting" in detail, detail
        finally:
            gate.set()
            writer.recorder = inner
