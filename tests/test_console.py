"""The web console end to end: the real daemon with ``sim://`` devices (as in
tests/test_daemon.py), its console over real HTTP/WebSocket on 127.0.0.1, Debian's headless
chromium driven through Debian's chromedriver (Selenium), and programs speaking the
WebSocket directly (aiohttp's client) where a browser would hide what the server does.

Screenshots: every browser test saves its PNGs in its tmp_path; with
``X6WD_CONSOLE_SHOTS=docs/console`` they are also copied there (docs/console.md shows them).
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import json
import math
import os
import shutil
import signal
import socket
import ssl
import struct
import threading
import time
import zlib
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import aiohttp
import pytest
from aiohttp import web
from selenium import webdriver
from selenium.webdriver.chrome.service import Service
from selenium.webdriver.common.action_chains import ActionChains
from selenium.webdriver.common.by import By
from selenium.webdriver.common.keys import Keys

from tests.conftest import ROOT, require_program, self_signed_cert
from tests.test_daemon import Running, hil_config, wait_for
from tests.test_startup import assert_config_error, run_x6wd, write_config
from x6wd.app.client import RemoteClient, RequestFailed
from x6wd.app.console import server as console_server
from x6wd.app.console.server import CONNECTION_SLACK
from x6wd.app.daemon import Daemon
from x6wd.core.config import Config, ConsoleConfig, FailsafeConfig, SafetyConfig, SimConfig
from x6wd.core.geodesy import great_circle_m
from x6wd.core.mission_files import format_csv, format_gpx, format_wpl, parse_gpx
from x6wd.core.records import Mode, NavState, Telemetry

pytestmark = pytest.mark.integration

TOKEN = "console-token-7b1e2f"
ORIGIN = (51.7520, -1.2577)  # the default scenario's origin (the robot starts there)
M_PER_DEG_LAT = 111_250.0
SHOTS = os.environ.get("X6WD_CONSOLE_SHOTS", "")
CHROMIUM_FLAGS = (
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--ignore-certificate-errors",  # the TLS test's certificate is self-signed
)


def north(metres: float, east_m: float = 0.0) -> list[float]:
    """[lat, lon] ``metres`` north (and ``east_m`` east) of the scenario's origin."""
    return [
        ORIGIN[0] + metres / M_PER_DEG_LAT,
        ORIGIN[1] + east_m / (M_PER_DEG_LAT * math.cos(math.radians(ORIGIN[0]))),
    ]


def console_config(
    tmp_path: Path, *, token: bool = False, tls: bool = False, **console: Any
) -> Config:
    """The HIL daemon's configuration with the console on a free port."""
    cfg = hil_config(
        tmp_path,
        console=ConsoleConfig(enabled=True, port=0, **console),
        # the robot starts facing 350 deg true: the raw telemetry's heading is -10
        sim=SimConfig(gps_rate_hz=4.0, gps_baud=115200, start_heading_deg=350.0),
    )
    server = cfg.server
    if token:
        path = tmp_path / "token"
        path.write_text(TOKEN)
        path.chmod(0o600)
        server = dataclasses.replace(server, token_file=str(path))
    if tls:
        cert, key = self_signed_cert(tmp_path)
        server = dataclasses.replace(server, tls_cert=str(cert), tls_key=str(key))
    return dataclasses.replace(cfg, server=server)


@contextlib.contextmanager
def daemon_with(cfg: Config) -> Iterator[Running]:
    r = Running(Daemon(cfg))
    try:
        yield r
    finally:
        r.stop()
        if r.daemon.devices is not None:
            r.daemon.devices.close()


def has_fix(r: Running) -> bool:
    tel = r.daemon.last_telemetry
    return r.daemon.first_fix is not None and tel is not None and tel.fix_quality > 0


def _first_recording(r: Running) -> str:
    """The name of a recording the running daemon wrote (one recording.view accepts)."""
    names = sorted(p.name for p in Path(r.daemon.config.recorder.dir).glob("x6wd-*.jsonl"))
    assert names, "no recording yet"
    return names[0]


def vehicle_pct(r: Running) -> tuple[float, float]:
    return r.daemon.devices.backend("sim").vehicle.command_pct


# -- a program on the WebSocket --------------------------------------------------------------------
class Ws:
    """One WebSocket to the console: requests by id, events kept in arrival order."""

    def __init__(self, ws: aiohttp.ClientWebSocketResponse) -> None:
        self.ws = ws
        self.events: list[dict[str, Any]] = []
        self.n = 0

    async def request(self, cmd: str, **args: Any) -> dict[str, Any]:
        self.n += 1
        await self.ws.send_json({"id": self.n, "cmd": cmd, **args})
        while True:
            msg = await asyncio.wait_for(self.ws.receive_json(), 15)
            if msg.get("id") == self.n:
                return msg
            self.events.append(msg)

    async def collect(self, seconds: float) -> list[dict[str, Any]]:
        """Events that arrive within ``seconds``."""
        end = time.monotonic() + seconds
        with contextlib.suppress(TimeoutError):
            while (left := end - time.monotonic()) > 0:
                self.events.append(await asyncio.wait_for(self.ws.receive_json(), left))
        return self.events


@contextlib.asynccontextmanager
async def ws_to(r: Running, ssl_ctx: ssl.SSLContext | None = None, **headers: str):
    console = r.daemon.console
    assert console is not None
    url = console.url.replace("http", "ws", 1) + "ws"
    async with (
        aiohttp.ClientSession() as session,
        session.ws_connect(url, headers=headers, ssl=ssl_ctx or False) as ws,
    ):
        w = Ws(ws)
        w.events.append(await asyncio.wait_for(ws.receive_json(), 10))  # the welcome
        yield w


# -- the browser -----------------------------------------------------------------------------------
def chromium(tmp_path: Path, width: int = 1400, height: int = 1150) -> webdriver.Chrome:
    """Debian's chromium through Debian's chromedriver (fails in CI when missing)."""
    binary, driver = require_program("chromium"), require_program("chromedriver")
    options = webdriver.ChromeOptions()
    options.binary_location = binary
    for flag in CHROMIUM_FLAGS:
        options.add_argument(flag)
    options.add_argument(f"--window-size={width},{height}")
    profile = tmp_path / f"chromium-{time.monotonic_ns()}"
    options.add_argument(f"--user-data-dir={profile}")
    return webdriver.Chrome(service=Service(driver), options=options)


@pytest.fixture(scope="module")
def browser(tmp_path_factory: pytest.TempPathFactory) -> Iterator[webdriver.Chrome]:
    d = chromium(tmp_path_factory.mktemp("browser"))
    try:
        yield d
    finally:
        d.quit()


def js(d: webdriver.Chrome, script: str, *args: Any) -> Any:
    return d.execute_script(script, *args)


def text(d: webdriver.Chrome, element_id: str) -> str:
    return d.find_element(By.ID, element_id).text


def shot(d: webdriver.Chrome, tmp_path: Path, name: str) -> Path:
    path = tmp_path / name
    assert d.save_screenshot(str(path))
    data = path.read_bytes()
    assert data.startswith(b"\x89PNG\r\n\x1a\n") and len(data) > 20_000, len(data)
    if SHOTS:
        dest = ROOT / SHOTS if not Path(SHOTS).is_absolute() else Path(SHOTS)
        dest.mkdir(parents=True, exist_ok=True)
        shutil.copy(path, dest / name)
    return path


def open_page(d: webdriver.Chrome, r: Running, suffix: str = "") -> None:
    console = r.daemon.console
    assert console is not None
    d.get("about:blank")  # a new document even when only the #fragment differs
    d.get(console.url + suffix)


def page_ready(d: webdriver.Chrome) -> None:
    """Until the page is authenticated, has telemetry and the map's frame."""
    wait_for(
        # typeof first: under load the wait may start before the page's script ran (a CI run:
        # "x6wd is not defined" ended the wait instead of continuing it)
        lambda: js(
            d,
            "return typeof x6wd !== 'undefined' && x6wd.authed && x6wd.tel !== null"
            " && x6wd.originFromFence === true",
        ),
        20,
        "the page connected, with telemetry and the geofence",
    )


def canvas_click(d: webdriver.Chrome, x: float, y: float, button: str = "left") -> None:
    """A real click at canvas pixel (x, y)."""
    canvas = d.find_element(By.ID, "map")
    w, h = js(d, "const c = x6wd.canvas; return [c.clientWidth, c.clientHeight]")
    chain = ActionChains(d).move_to_element_with_offset(canvas, int(x - w / 2), int(y - h / 2))
    (chain.context_click() if button == "right" else chain.click()).perform()


# -- configuration ---------------------------------------------------------------------------------
def test_an_unknown_console_key_is_exit_2_naming_it(tmp_path: Path) -> None:
    config = write_config(tmp_path, console={"enabled": True, "bogus": 1})
    assert_config_error(run_x6wd(config), str(config), "console.bogus: unknown key")


@pytest.mark.parametrize(
    ("changes", "key", "reason"),
    [
        ({"deadman_s": 9.0}, "console.deadman_s", "longer than safety.manual_max_s (5 s)"),
        ({"server_enabled": False}, "console.enabled", "needs the control server"),
        ({"bind": "0.0.0.0"}, "console.bind", "server.token_file"),
    ],
)
def test_a_console_setting_at_odds_with_the_rest_is_exit_2_naming_the_key(
    tmp_path: Path, caplog: pytest.LogCaptureFixture, changes: dict[str, Any], key: str, reason: str
) -> None:
    server_enabled = changes.pop("server_enabled", True)
    cfg = console_config(tmp_path, **changes)
    cfg = dataclasses.replace(cfg, server=dataclasses.replace(cfg.server, enabled=server_enabled))
    d = Daemon(cfg)
    try:
        # bounded: a daemon that took the setting would run on, not exit
        assert asyncio.run(asyncio.wait_for(d.run(), 30.0)) == 2
    finally:
        if d.devices is not None:
            d.devices.close()
    errors = [r.getMessage() for r in caplog.records if r.levelname == "ERROR"]
    assert len(errors) == 1 and errors[0].startswith(key) and reason in errors[0], errors
    assert not (tmp_path / "rec").exists()


def test_busy_console_port_is_exit_2(tmp_path: Path, listening: int) -> None:
    proc = run_x6wd(write_config(tmp_path, console={"enabled": True, "port": listening}))
    assert_config_error(proc, "console.port", f"127.0.0.1:{listening}", "address already in use")


# -- the token, TLS and origin ---------------------------------------------------------------------
def test_without_the_token_the_console_accepts_no_command_and_shows_nothing(
    tmp_path: Path, browser: webdriver.Chrome
) -> None:
    with daemon_with(console_config(tmp_path, token=True, tls=True, max_clients=2)) as r:
        assert r.daemon.console is not None and r.daemon.console.url.startswith("https://")
        wait_for(lambda: has_fix(r), 30, "a fix")
        ca = ssl.create_default_context(cafile=str(tmp_path / "cert.pem"))

        async def program() -> None:
            async with ws_to(r, ca) as w:
                welcome = w.events.pop()
                assert welcome["auth_required"] is True and welcome["tls"] is True
                for cmd, args in (
                    ("start", {}),
                    ("drive", {"left": 50, "right": 50, "duration_s": 0.5}),
                    ("mission.load", {"waypoints": [north(5)]}),
                    ("mission.parse", {"content": "51.7,-1.2\n"}),
                    # the robot's recordings are its track: no list, no viewer
                    ("recording.list", {}),
                    ("recording.view", {"name": _first_recording(r)}),
                    ("log", {}),
                    ("status", {}),  # open on the control port, not here: it has telemetry
                ):
                    reply = await w.request(cmd, **args)
                    assert reply["error"]["code"] == "unauthorized", (cmd, reply)
                # no telemetry, sky or map for a page that has not authenticated
                assert await w.collect(1.0) == []
                reply = await w.request("auth", token="wrong-token-123")
                assert reply["error"]["code"] == "auth_failed"
                await asyncio.sleep(1.1)  # the back-off after a wrong token
                assert (await w.request("auth", token=TOKEN))["ok"]
                kinds = {e.get("event") for e in await w.collect(1.5)}
                assert {"telemetry", "sky", "map"} <= kinds, kinds

        asyncio.run(program())
        assert vehicle_pct(r) == (0.0, 0.0)
        # a plain (not TLS) connection gets nothing
        with pytest.raises((aiohttp.ClientError, ConnectionError)):
            asyncio.run(
                _plain_get(r.daemon.console.url.replace("https://", "http://"))  # type: ignore[union-attr]
            )
        # the page: it asks for the token, refuses a wrong one, connects with the right one
        open_page(browser, r)
        wait_for(lambda: browser.find_element(By.ID, "login").is_displayed(), 10, "login form")
        assert js(browser, "return x6wd.tel") is None  # nothing shown before the token
        browser.find_element(By.ID, "token-input").send_keys("not-the-token")
        browser.find_element(By.CSS_SELECTOR, "#token-form button").click()
        wait_for(lambda: "wrong token" in text(browser, "login-error"), 10, "refusal shown")
        shot(browser, tmp_path, "login.png")
        time.sleep(1.1)
        field = browser.find_element(By.ID, "token-input")
        field.clear()
        field.send_keys(TOKEN)
        browser.find_element(By.CSS_SELECTOR, "#token-form button").click()
        page_ready(browser)
        assert text(browser, "conn") == "connected (TLS)"
        # the token in the address is taken out of it (and works)
        js(browser, "sessionStorage.clear()")
        open_page(browser, r, f"#token={TOKEN}")
        page_ready(browser)
        assert "token" not in browser.current_url
        assert r.daemon.server is not None and r.daemon.server.auth_failed_total == 2

        # pages without the token cannot lock the operator out: a full console (2 here)
        # closes the oldest of them, never the operator's page
        async def squatters() -> None:
            async with ws_to(r, ca) as a, ws_to(r, ca) as b:
                await asyncio.wait_for(a.ws.receive(), 5)  # closed to make room
                assert a.ws.closed
                assert (await b.request("hello"))["ok"]

        console = r.daemon.console
        wait_for(lambda: len(console._pages) == 1, 5, "the earlier pages closed")
        asyncio.run(squatters())
        assert js(browser, "return x6wd.authed") and text(browser, "conn") == "connected (TLS)"


async def _plain_get(url: str) -> None:
    async with aiohttp.ClientSession() as s, s.get(url) as resp:
        await resp.read()


def test_a_websocket_from_another_site_is_refused(tmp_path: Path) -> None:
    with daemon_with(console_config(tmp_path)) as r:
        console = r.daemon.console
        assert console is not None
        host = f"127.0.0.1:{console.port}"

        async def program() -> None:
            # a page of another site open in the operator's browser: refused (no token here)
            with pytest.raises(aiohttp.WSServerHandshakeError) as ei:
                async with ws_to(r, Origin="http://attacker.example"):
                    pass
            assert ei.value.status == 403
            with pytest.raises(aiohttp.WSServerHandshakeError):
                async with ws_to(r, Origin=f"http://127.0.0.1:{console.port + 1}"):
                    pass
            async with ws_to(r, Origin=f"http://{host}") as w:  # the console's own page
                assert (await w.request("hello"))["ok"]

        asyncio.run(program())


def test_a_rebound_host_name_is_refused_and_idle_connections_cannot_starve_the_stop(
    tmp_path: Path,
) -> None:
    # Found by an outside check. DNS rebinding: a site whose name the attacker points at
    # 127.0.0.1 sent its own Host and a matching Origin, and drove the robot (no token).
    # 1100 idle HTTP connections took the daemon's file descriptors, and with them `stop`.
    with daemon_with(console_config(tmp_path, hostnames=("robot.lan",))) as r:
        console = r.daemon.console
        assert console is not None
        port = console.port
        evil = f"evil.example:{port}"

        async def program() -> None:
            with pytest.raises(aiohttp.WSServerHandshakeError) as ei:
                async with ws_to(r, Host=evil, Origin=f"http://{evil}"):
                    pass
            assert ei.value.status == 421
            async with aiohttp.ClientSession() as s:
                for host, status in ((evil, 421), (f"localhost:{port}", 200),
                                     (f"ROBOT.lan:{port}", 200), (f"[::1]:{port}", 200),
                                     (f"127.0.0.1:{port}", 200), ("[::1", 421)):  # fmt: skip
                    async with s.get(console.url, headers={"Host": host}) as resp:
                        assert resp.status == status, host

        asyncio.run(program())
        assert console.refused_hosts == 3
        cap = console.config.max_clients + CONNECTION_SLACK
        idle = []
        for _ in range(cap + 40):  # each sends half a request and waits
            s = socket.create_connection(("127.0.0.1", port), timeout=5)
            s.sendall(b"GET / HTTP/1.1\r\n")
            idle.append(s)
        try:
            wait_for(lambda: console.connections_closed >= 40, 10, "the oldest idle closed")
            server = console._runner.server  # type: ignore[union-attr]
            wait_for(lambda: len(server.connections) <= cap, 10, "the connections capped")

            async def page() -> None:  # a page still opens, and the brake still works
                async with ws_to(r) as w:
                    assert (await w.request("hello"))["ok"]

            asyncio.run(page())
            with RemoteClient("127.0.0.1", r.port) as c:
                assert c.request("stop")["ok"]
        finally:
            for s in idle:
                s.close()


# -- watch-only and the map's tiles ----------------------------------------------------------------
def _png(width: int, height: int, rgb: tuple[int, int, int], grid: int = 32) -> bytes:
    """A small PNG (a coloured tile with a grid), written by hand: nothing to install."""
    rows = []
    for y in range(height):
        row = bytearray([0])
        for x in range(width):
            edge = x % grid == 0 or y % grid == 0
            row += bytes((90, 90, 90) if edge else rgb)
        rows.append(bytes(row))
    raw = zlib.compress(b"".join(rows))

    def chunk(kind: bytes, data: bytes) -> bytes:
        return (
            struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))
        )

    header = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + chunk(b"IDAT", raw) + chunk(b"IEND", b"")


class TileServer:
    """XYZ tiles on 127.0.0.1 (the test's stand-in for a tile service); counts requests."""

    def __init__(self) -> None:
        self.requests: list[tuple[int, int, int]] = []
        # a checkerboard of tiles, each with a frame: the tiles' places show in a screenshot
        self.tiles = (_png(256, 256, (214, 232, 206), 256), _png(256, 256, (232, 226, 206), 256))
        self.ready = threading.Event()
        self.loop = asyncio.new_event_loop()
        self.thread = threading.Thread(target=self.loop.run_forever, daemon=True)
        self.thread.start()
        self.port = asyncio.run_coroutine_threadsafe(self._start(), self.loop).result(10)

    async def _start(self) -> int:
        app = web.Application()
        app.router.add_get("/{z}/{x}/{y}.png", self._get)
        self.runner = web.AppRunner(app, access_log=None)
        await self.runner.setup()
        site = web.TCPSite(self.runner, "127.0.0.1", 0)
        await site.start()
        return int(self.runner.addresses[0][1])

    async def _get(self, request: web.Request) -> web.Response:
        m = request.match_info
        z, x, y = int(m["z"]), int(m["x"]), int(m["y"])
        self.requests.append((z, x, y))
        return web.Response(body=self.tiles[(x + y) % 2], content_type="image/png")

    def close(self) -> None:
        asyncio.run_coroutine_threadsafe(self.runner.cleanup(), self.loop).result(10)
        self.loop.call_soon_threadsafe(self.loop.stop)
        self.thread.join(5)


def test_watch_only_refuses_every_command_in_the_daemon_and_tiles_come_when_configured(
    tmp_path: Path, browser: webdriver.Chrome
) -> None:
    tiles = TileServer()
    url = f"http://127.0.0.1:{tiles.port}/{{z}}/{{x}}/{{y}}.png"
    try:
        with daemon_with(console_config(tmp_path, watch_only=True, tile_url=url)) as r:
            wait_for(lambda: has_fix(r), 30, "a fix")

            async def program() -> None:
                async with ws_to(r) as w:
                    assert w.events.pop()["watch_only"] is True
                    for cmd, args in (
                        ("mission.load", {"waypoints": [north(5)]}),
                        ("start", {}),
                        ("pause", {}),
                        ("resume", {}),
                        ("return", {}),
                        ("drive", {"left": 60, "right": 60, "duration_s": 0.5}),
                        ("stop", {}),
                    ):
                        reply = await w.request(cmd, **args)
                        assert reply["error"]["code"] == "watch_only", (cmd, reply)
                    assert (await w.request("status"))["ok"]  # watching is allowed
                    kinds = {e.get("event") for e in await w.collect(1.0)}
                    assert "telemetry" in kinds

            asyncio.run(program())
            assert vehicle_pct(r) == (0.0, 0.0)
            assert r.daemon.server is not None
            assert r.daemon.server.stops["requested"] == 0  # the stop never reached the robot
            with RemoteClient("127.0.0.1", r.port) as c:  # the control port is not watch-only
                assert c.request("status")["mode"] == "IDLE"
            open_page(browser, r)
            page_ready(browser)
            for element_id in ("btn-start", "btn-stop", "drive-fwd", "btn-send", "btn-add"):
                assert not browser.find_element(By.ID, element_id).is_displayed(), element_id
            assert browser.find_element(By.ID, "watch-only").is_displayed()
            wait_for(lambda: len(tiles.requests) >= 4, 10, "tiles requested")
            zooms = {z for z, _x, _y in tiles.requests}
            # ~4 px per metre at 52 deg north: zoom 18 or 19 (0.4 m / 0.2 m per pixel)
            assert zooms <= {18, 19}, zooms
            time.sleep(1.0)  # the tiles drawn
            shot(browser, tmp_path, "watch-only-tiles.png")
            # a view across the 180th meridian draws the tiles of both sides (review of
            # 92568a8: with the east edge wrapped to -179.99 the columns ran backwards, none)
            browser.find_element(By.ID, "follow").click()  # the view stays where it is put
            js(browser, "x6wd.origin = [-16.5, 179.9999]; x6wd.view.e = 0; x6wd.view.n = 0")
            seen = len(tiles.requests)

            def both_sides() -> bool:
                new = tiles.requests[seen:]
                return any(x <= 1 for _z, x, _y in new) and any(x >= 2**z - 2 for z, x, _y in new)

            wait_for(both_sides, 10, "tiles either side of the 180th meridian")
    finally:
        tiles.close()


def test_a_watch_only_page_does_not_keep_the_operator_link_failsafe_quiet(tmp_path: Path) -> None:
    # the operator starts a mission over the control port and goes away; a spectator's
    # watch-only page keeps authenticating and asking for status: it is no operator, so
    # the operator-link failsafe still holds the robot (a watcher must not keep it driving)
    cfg = console_config(tmp_path, token=True, watch_only=True)
    cfg = dataclasses.replace(
        cfg, failsafe=FailsafeConfig(operator_timeout_s=2.0, operator_action="hold")
    )
    with daemon_with(cfg) as r:
        wait_for(lambda: has_fix(r), 30, "a fix")
        wait_for(lambda: "ekf_sigma_m" in r.daemon.last_telemetry.extra, 30, "an EKF position")  # type: ignore[union-attr]
        with RemoteClient("127.0.0.1", r.port, token=TOKEN) as c:
            c.request("mission.load", waypoints=[north(40)])
            assert c.request("start")["mode"] == "RUNNING"
        t_quiet = time.monotonic()

        async def spectator() -> float:
            async with ws_to(r) as w:
                while time.monotonic() - t_quiet < 10.0:
                    assert (await w.request("auth", token=TOKEN))["ok"]
                    assert (await w.request("status"))["ok"]
                    tel = r.daemon.last_telemetry
                    if tel is not None and tel.extra.get("failsafe") == "operator link lost":
                        return time.monotonic() - t_quiet
                    await asyncio.sleep(0.2)
            raise AssertionError("the failsafe never fired while a watch-only page talked")

        quiet_s = asyncio.run(spectator())
        assert 1.5 < quiet_s < 6.0, quiet_s
        assert r.daemon.controller.mode == Mode.PAUSED
        wait_for(lambda: vehicle_pct(r) == (0.0, 0.0), 3, "motors stopped")


# -- the running robot on the page -----------------------------------------------------------------
@pytest.fixture(scope="module")
def robot(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Running]:
    """One HIL daemon with the console (no token: loopback) for the page's tests below."""
    with daemon_with(console_config(tmp_path_factory.mktemp("robot"))) as r:
        wait_for(lambda: has_fix(r), 30, "a fix")
        wait_for(lambda: "ekf_sigma_m" in r.daemon.last_telemetry.extra, 30, "an EKF position")  # type: ignore[union-attr]
        yield r


@pytest.mark.parametrize(
    ("controller_deg", "shown_deg"),
    [(-2.4, 357.6), (-1e-17, 0.0), (0.0, 0.0), (180.0, 180.0), (-179.9, 180.1), (359.99, 359.99)],
)
def test_telemetry_json_has_one_heading_convention(controller_deg: float, shown_deg: float) -> None:
    tel = Telemetry(0.0, Mode.IDLE, NavState.IDLE, heading_deg=controller_deg,
                    target_bearing_deg=controller_deg, theta_deg=-5.0)  # fmt: skip
    d = tel.to_dict()
    for key in ("heading_deg", "target_bearing_deg"):
        assert 0.0 <= d[key] < 360.0 and d[key] == pytest.approx(shown_deg), key
    assert d["theta_deg"] == -5.0  # a deviation keeps its sign
    assert Telemetry(0.0, Mode.IDLE, NavState.IDLE).to_dict()["heading_deg"] is None


def test_the_page_shows_live_telemetry_sky_and_devices(
    tmp_path: Path, robot: Running, browser: webdriver.Chrome
) -> None:
    open_page(browser, robot)
    page_ready(browser)
    wait_for(lambda: len(browser.find_elements(By.CSS_SELECTOR, "#sky tbody tr")) >= 4, 10, "sky")
    rows = js(  # in one go: the table is redrawn at every sky event
        browser,
        "return [...document.querySelectorAll('#sky tbody tr')]"
        ".map((tr) => [...tr.cells].map((td) => td.textContent))",
    )
    cn0 = [float(row[3]) for row in rows if row[3] != "—"]
    # GSV's C/N0 (0-99 dB-Hz), strongest first; the fix uses at least four of them
    assert len(cn0) >= 4 and all(0.0 < v < 99.0 for v in cn0) and cn0 == sorted(cn0)[::-1], rows
    assert sum(row[4] == "yes" and row[3] != "—" for row in rows) >= 4
    wait_for(lambda: "connected" in text(browser, "devices"), 10, "device health")
    devices = text(browser, "devices")
    for name in ("gps", "compass", "motors", "odometry", "motor link"):
        assert name in devices, devices
    # one heading convention: true, 0..360 (the controller's own value is -10 here)
    ctl = robot.daemon.last_telemetry
    assert ctl is not None and ctl.heading_deg is not None and -20.0 < ctl.heading_deg < 0.0
    with RemoteClient("127.0.0.1", robot.port) as c:
        sent = c.request("status")["telemetry"]["heading_deg"]
    assert 340.0 < sent < 360.0, sent
    shown = float(text(browser, "tel-heading").split("°")[0])
    assert 340.0 < shown < 360.0, shown
    # the page's value is one telemetry event older or newer than ours: same to ~1 deg
    assert abs(shown - sent) < 1.0, (shown, sent)
    lat, lon = (float(v) for v in text(browser, "tel-pos").split(" (")[0].split(","))
    assert great_circle_m(lat, lon, *ORIGIN) < 15.0
    assert text(browser, "mode") in ("IDLE", "DONE")
    shot(browser, tmp_path, "telemetry.png")


def test_mission_editing_on_the_map_and_from_files(
    tmp_path: Path, robot: Running, browser: webdriver.Chrome
) -> None:
    open_page(browser, robot)
    page_ready(browser)
    browser.find_element(By.ID, "follow").click()  # the view stays where it is
    browser.find_element(By.ID, "btn-clear").click()
    browser.find_element(By.ID, "btn-add").click()
    w, h = js(
        browser, "const c = document.getElementById('map'); return [c.clientWidth, c.clientHeight]"
    )
    px_per_m = js(browser, "return x6wd.view.pxPerM")
    cx, cy = w / 2, h / 2
    clicks = [(cx, cy - 40), (cx + 60, cy - 100), (cx + 120, cy - 40)]
    for x, y in clicks:
        canvas_click(browser, x, y)
    draft = js(browser, "return x6wd.draft")
    assert len(draft) == 3, draft
    # the map's metres are the earth's: 60 px east and 60 px north at the page's scale
    leg_m = great_circle_m(*draft[0], *draft[1])
    assert abs(leg_m - math.hypot(60, 60) / px_per_m) < 0.02 * leg_m + 0.1, leg_m
    north_m = great_circle_m(draft[0][0], draft[0][1], draft[1][0], draft[0][1])
    assert abs(north_m - 60 / px_per_m) < 0.3, north_m
    # drag waypoint 2 by 40 px to the east
    browser.find_element(By.ID, "btn-add").click()  # adding off: a click would add
    canvas = browser.find_element(By.ID, "map")
    x, y = clicks[1]
    (
        ActionChains(browser)
        .move_to_element_with_offset(canvas, int(x - w / 2), int(y - h / 2))
        .click_and_hold()
        .move_by_offset(20, 0)
        .move_by_offset(20, 0)
        .release()
        .perform()
    )
    moved = js(browser, "return x6wd.draft")
    assert len(moved) == 3
    assert abs(great_circle_m(*draft[1], *moved[1]) - 40 / px_per_m) < 0.3
    assert moved[0] == draft[0] and moved[2] == draft[2]
    # right-click deletes waypoint 3
    canvas_click(browser, *clicks[2], button="right")
    edited = js(browser, "return x6wd.draft")
    assert edited == moved[:2]
    assert "not sent" in text(browser, "mission-state")
    shot(browser, tmp_path, "mission-edit.png")
    browser.find_element(By.ID, "btn-send").click()
    wait_for(lambda: len(robot.daemon._mission) == 2, 10, "the mission on the robot")
    for got, want in zip(robot.daemon._mission, edited, strict=True):
        assert got == pytest.approx(tuple(want), abs=1e-9)
    wait_for(lambda: "on the robot" in text(browser, "mission-state"), 10, "sent")
    # files: GPX, CSV, QGC WPL and KML, read by the daemon's own readers
    wps = parse_gpx(format_gpx([tuple(north(4)), tuple(north(8, 3)), tuple(north(12))]))  # type: ignore[list-item]
    kml = (
        '<?xml version="1.0"?><kml xmlns="http://www.opengis.net/kml/2.2"><Document><Placemark>'
        "<LineString><coordinates>"
        + " ".join(f"{w.lon_deg},{w.lat_deg},0" for w in wps)
        + "</coordinates></LineString></Placemark></Document></kml>"
    )
    files = {
        "m.gpx": format_gpx(wps),
        "m.csv": format_csv(wps),
        "m.waypoints": format_wpl(wps),
        "m.kml": kml,
    }
    for name, content in files.items():
        path = tmp_path / name
        path.write_text(content)
        browser.find_element(By.ID, "btn-clear").click()
        browser.find_element(By.ID, "mission-file").send_keys(str(path))
        wait_for(lambda: len(js(browser, "return x6wd.draft")) == 3, 10, f"{name} loaded")
        got = js(browser, "return x6wd.draft")
        for g, want in zip(got, wps, strict=True):
            assert g == pytest.approx([want.lat_deg, want.lon_deg], abs=1e-7), name
    # a file that is no mission: the daemon's reader says why, the draft stays
    bad = tmp_path / "bad.gpx"
    bad.write_text("<gpx><rte><rtept lat='95' lon='0'/></rte></gpx>")
    browser.find_element(By.ID, "mission-file").send_keys(str(bad))
    wait_for(lambda: "bad.gpx:" in text(browser, "msg"), 10, "the error shown")
    assert len(js(browser, "return x6wd.draft")) == 3
    browser.find_element(By.ID, "btn-revert").click()
    assert js(browser, "return x6wd.draft") == [list(p) for p in robot.daemon._mission]


def test_the_maps_frame_is_metres_across_the_180th_meridian(
    robot: Running, browser: webdriver.Chrome
) -> None:
    """A robot across the 180th meridian from the map's origin is metres away, and a point
    drafted across it is a longitude within +-180 (outside audit, places round 5: the
    plain difference drew it 40,000 km off and drafted 180.0001)."""
    open_page(browser, robot)
    page_ready(browser)
    east_m, north_m, lat, lon = js(
        browser,
        "const o = x6wd.origin; x6wd.origin = [-16.5, 179.9999];"
        "const a = x6wd.geo.toLocal(-16.5, -179.9999); const b = x6wd.geo.toLatLon(30, 0);"
        "x6wd.origin = o; return [a[0], a[1], b[0], b[1]]",
    )
    assert abs(east_m - great_circle_m(-16.5, 179.9999, -16.5, -179.9999)) < 0.01
    assert abs(north_m) < 1e-6
    assert -180.0 < lon <= 180.0 and abs(lat + 16.5) < 1e-9
    assert abs(great_circle_m(-16.5, 179.9999, lat, lon) - 30.0) < 0.01


def test_mission_load_takes_qgc_wpl_and_kml_on_the_control_port(robot: Running) -> None:
    wps = parse_gpx(format_gpx([tuple(north(3)), tuple(north(6, 2))]))  # type: ignore[list-item]
    kml = (
        '<kml xmlns="http://www.opengis.net/kml/2.2"><Placemark><LineString><coordinates>'
        + " ".join(f"{w.lon_deg},{w.lat_deg}" for w in wps)
        + "</coordinates></LineString></Placemark></kml>"
    )
    with RemoteClient("127.0.0.1", robot.port) as c:
        assert c.request("mission.load", wpl=format_wpl(wps))["count"] == 2
        assert robot.daemon._mission == tuple((w.lat_deg, w.lon_deg) for w in wps)
        assert c.request("mission.load", kml=kml)["count"] == 2
        items = [
            {"type": "SimpleItem", "command": 16, "frame": 3, "autoContinue": True,
             "doJumpId": i + 1, "params": [0, 0, 0, None, w.lat_deg, w.lon_deg, 0]}
            for i, w in enumerate(wps)
        ]  # fmt: skip
        plan = json.dumps(
            {"fileType": "Plan", "version": 1,
             "mission": {"version": 2, "items": items, "plannedHomePosition": [*ORIGIN, 0]}}
        )  # fmt: skip
        assert c.request("mission.load", plan=plan)["count"] == 2  # QGroundControl's .plan
        assert robot.daemon._mission == tuple((w.lat_deg, w.lon_deg) for w in wps)
        with pytest.raises(RequestFailed) as ei:
            c.request("mission.load", wpl="QGC WPL 110\n0\t1\t0\t16\t0\t0\t0\t0\t95\t0\t0\t1\n")
        assert ei.value.code == "bad_request"
        with pytest.raises(RequestFailed) as ei:
            c.request("mission.load", wpl=format_wpl(wps), kml=kml)
        assert "exactly one of" in str(ei.value)


def test_every_response_forbids_framing_other_sources_and_sniffing(robot: Running) -> None:
    # another site must not frame the console (clickjacking its drive buttons), pull in
    # scripts or send the page's data elsewhere
    console = robot.daemon.console
    assert console is not None
    host = f"127.0.0.1:{console.port}"

    async def headers(path: str) -> Any:
        async with aiohttp.ClientSession() as s, s.get(console.url + path) as resp:
            await resp.read()
            assert resp.status == 200, (path, resp.status)
            return resp.headers

    for path in ("", "static/console.js", "static/console.css"):
        h = asyncio.run(headers(path))
        csp = {d.split()[0]: d.split()[1:] for d in h["Content-Security-Policy"].split("; ")}
        assert csp["frame-ancestors"] == ["'none'"], (path, csp)
        assert csp["default-src"] == csp["script-src"] == ["'self'"], (path, csp)
        assert csp["connect-src"] == ["'self'", f"ws://{host}", f"wss://{host}"], (path, csp)
        assert csp["form-action"] == csp["base-uri"] == ["'none'"], (path, csp)
        assert h["X-Content-Type-Options"] == "nosniff", path
        assert h["Referrer-Policy"] == "no-referrer", path
        assert h["Cache-Control"] == "no-store", path


def test_a_drive_from_the_console_lasts_at_most_deadman_s(robot: Running) -> None:
    async def program() -> None:
        async with ws_to(robot) as w:
            reply = await w.request("drive", left=10, right=10, duration_s=4.0)
            assert reply["ok"] and reply["duration_s"] == 0.5, reply
            assert (await w.request("stop"))["ok"]

    asyncio.run(program())
    wait_for(lambda: vehicle_pct(robot) == (0.0, 0.0), 3, "stopped")


@pytest.mark.slow
def test_a_whole_hil_mission_driven_from_the_page(
    tmp_path: Path, robot: Running, browser: webdriver.Chrome
) -> None:
    open_page(browser, robot)
    page_ready(browser)
    gpx = tmp_path / "two.gpx"
    # the mission: 8 m and 16 m north of where the robot's navigation has it (its EKF)
    tel = robot.daemon.last_telemetry
    assert tel is not None and tel.filt_lat_deg is not None
    here_n = (tel.filt_lat_deg - ORIGIN[0]) * M_PER_DEG_LAT
    world = robot.daemon.devices.backend("sim")
    _e0, n0, _h, _v = world.truth()
    gpx.write_text(format_gpx([tuple(north(here_n + 8, 2)), tuple(north(here_n + 16))]))  # type: ignore[list-item]
    browser.find_element(By.ID, "mission-file").send_keys(str(gpx))
    wait_for(lambda: len(js(browser, "return x6wd.draft")) == 2, 10, "file read")
    browser.find_element(By.ID, "btn-send").click()
    wait_for(lambda: "2 waypoints on the robot" in text(browser, "mission-state"), 10, "sent")
    browser.find_element(By.ID, "btn-start").click()
    wait_for(lambda: text(browser, "mode") == "RUNNING", 10, "running")
    wait_for(lambda: js(browser, "return x6wd.track.length") > 20, 20, "a track")
    shot(browser, tmp_path, "mission-running.png")
    browser.find_element(By.ID, "btn-pause").click()
    wait_for(lambda: text(browser, "mode") == "PAUSED", 10, "paused")
    wait_for(lambda: vehicle_pct(robot) == (0.0, 0.0), 3, "motors stopped while paused")
    browser.find_element(By.ID, "btn-resume").click()
    wait_for(lambda: text(browser, "mode") == "RUNNING", 10, "resumed")
    wait_for(lambda: text(browser, "state") == "MISSION_DONE", 60, "the mission done")
    assert text(browser, "mode") == "DONE"
    with RemoteClient("127.0.0.1", robot.port) as c:
        st = c.request("status")
    assert st["mode"] == "DONE" and st["state"] == "MISSION_DONE"
    # 16 m north in truth too, within what the GPS's slow error drifts in half a minute
    e, n, _h, _v = world.truth()
    assert abs((n - n0) - 16.0) < 4.0, (here_n, n0, e, n)
    browser.find_element(By.ID, "btn-fit").click()
    time.sleep(0.3)
    shot(browser, tmp_path, "mission-done.png")
    # a page opened now draws the track so far (the console kept it)
    open_page(browser, robot)
    page_ready(browser)
    assert js(browser, "return x6wd.track.length") > 20
    assert robot.daemon.console is not None and len(robot.daemon.console.track) > 20
    # Return drives back to the launch point; STOP ends it there and then
    browser.find_element(By.ID, "btn-return").click()
    wait_for(lambda: js(browser, "return x6wd.tel.extra.returning") == "return", 10, "returning")
    assert text(browser, "mode") == "RUNNING"
    browser.find_element(By.ID, "btn-stop").click()
    wait_for(lambda: text(browser, "mode") == "IDLE", 10, "stopped")
    wait_for(lambda: vehicle_pct(robot) == (0.0, 0.0), 3, "motors stopped")


def test_the_robots_recordings_open_in_the_log_viewer_from_the_page(
    tmp_path: Path, robot: Running, browser: webdriver.Chrome
) -> None:
    # a program: only names the recorder wrote are read, never a path
    async def program() -> None:
        async with ws_to(robot) as w:
            listed = await w.request("recording.list")
            assert listed["ok"] and listed["recordings"], listed
            name = listed["recordings"][0]["name"]
            assert name.startswith("x6wd-") and name.endswith(".jsonl")
            # a log the viewer could draw, named by path: refused all the same
            log = Path(__file__).parent / "data" / "nmea" / "ublox-lea-5h.log"
            for bad in (str(log), os.path.relpath(log, robot.daemon.config.recorder.dir),
                        "x6wd-none.jsonl", None):  # fmt: skip
                reply = await w.request("recording.view", name=bad)
                assert reply["error"]["code"] == "bad_request", (bad, reply)
            page = await w.request("recording.view", name=name)
            assert page["ok"] and page["html"].startswith("<!DOCTYPE html>")

    asyncio.run(program())
    # the page: list, open, the viewer's panels inside the console, close
    open_page(browser, robot)
    page_ready(browser)
    browser.find_element(By.ID, "rec-list").click()
    # generous waits: the robot's recording grows through the module, and a loaded 2-core
    # machine takes a while to list and draw it (a 10 s wait timed out in a CI run)
    wait_for(lambda: browser.find_elements(By.CSS_SELECTOR, "#recordings button"), 30, "the list")
    # the daemon's own run, newest, says it is still being written; older ones do not
    items = [li.text for li in browser.find_elements(By.CSS_SELECTOR, "#recordings li")]
    assert "still being recorded (this run)" in items[0], items
    assert not any("being recorded" in t for t in items[1:]), items
    browser.find_element(By.CSS_SELECTOR, "#recordings button").click()
    wait_for(lambda: browser.find_element(By.ID, "rec-view").is_displayed(), 60, "the viewer")
    browser.switch_to.frame(browser.find_element(By.ID, "rec-frame"))
    try:
        wait_for(lambda: browser.find_elements(By.TAG_NAME, "svg"), 30, "the viewer's panels")
        assert "Track" in browser.find_element(By.TAG_NAME, "body").text
        # the viewer's own inline style applies under the console's policy (found by an
        # outside check: style-src 'self' blocked it in the srcdoc frame)
        styled = js(
            browser,
            "const css = (el) => getComputedStyle(el);"
            "return [css(document.body).fontFamily, css(document.body).maxWidth,"
            " css(document.querySelector('h1')).fontSize,"
            " css(document.body.lastElementChild).fontSize]",
        )
        assert styled == ["sans-serif", "940px", "20px", "11px"], styled
    finally:
        browser.switch_to.default_content()
    shot(browser, tmp_path, "recording.png")
    browser.find_element(By.ID, "rec-close").click()
    assert not browser.find_element(By.ID, "rec-view").is_displayed()


def test_a_recording_that_cannot_be_drawn_is_an_error_reply_not_a_lost_link(
    robot: Running, monkeypatch: pytest.MonkeyPatch
) -> None:
    # Found by an outside check: a fix with "lat_deg": NaN (a hand-edited file) raised
    # GeoError in the viewer, which crashed the page's WebSocket handler: "connection lost",
    # and the reconnection would have stopped a running drive.
    rec_dir = Path(robot.daemon.config.recorder.dir)
    nan_rec = rec_dir / "x6wd-20200101T000000Z.jsonl"  # the oldest: listed last
    fix = {"t_s": 0.0, "lat_deg": 51.75, "lon_deg": -1.25, "quality": 1, "valid": True}
    lines = [
        {"t_mono": t, "t_utc": "", "type": "fix", "data": {**fix, "t_s": t}} for t in (0, 1, 2)
    ]
    lines[1]["data"]["lat_deg"] = math.nan
    nan_rec.write_text("".join(json.dumps(line) + "\n" for line in lines))

    async def program() -> None:
        async with ws_to(robot) as w:
            page = await w.request("recording.view", name=nan_rec.name)
            assert page["ok"] and "nonfinite positions" in page["html"], page.get("error")

            # whatever else the viewer may choke on: a reply, the link stays
            def broken(_path: Path) -> str:
                raise ValueError("lat_deg must be finite")

            monkeypatch.setattr(console_server, "render_html", broken)
            reply = await w.request("recording.view", name=nan_rec.name)
            assert reply["error"]["reason"] == "bad_recording", reply
            assert "lat_deg must be finite" in reply["error"]["message"]
            assert (await w.request("hello"))["ok"]

    try:
        asyncio.run(program())
    finally:
        nan_rec.unlink()


def _focus_map(d: webdriver.Chrome) -> None:
    js(d, "document.getElementById('map').focus()")


def test_releasing_a_drive_key_stops_whatever_shift_did_to_it(
    robot: Running, browser: webdriver.Chrome
) -> None:
    # Found by an outside check: W down, Shift down, W up (the key reads "W" now), Shift up:
    # the page matched the release by ev.key and drove on at 40 % for as long as it was open.
    open_page(browser, robot)
    page_ready(browser)
    _focus_map(browser)
    ActionChains(browser).key_down("w").perform()
    wait_for(lambda: vehicle_pct(robot)[0] > 0.0, 5, "the robot driving on W")
    ActionChains(browser).key_down(Keys.SHIFT).key_up("w").perform()
    wait_for(lambda: vehicle_pct(robot) == (0.0, 0.0), 2, "a stop on W released with Shift down")
    assert js(browser, "return x6wd.drive") is None
    time.sleep(1.0)  # the page does not drive again
    assert vehicle_pct(robot) == (0.0, 0.0)
    ActionChains(browser).key_up(Keys.SHIFT).perform()
    # Cmd down while a key is held: macOS sends no keyup for a key released meanwhile
    ActionChains(browser).key_down("d").perform()
    wait_for(lambda: vehicle_pct(robot)[0] > 0.0, 5, "the robot turning on D")
    ActionChains(browser).key_down(Keys.META).perform()
    wait_for(lambda: vehicle_pct(robot) == (0.0, 0.0), 2, "a stop on Cmd")
    assert js(browser, "return x6wd.drive") is None
    ActionChains(browser).key_up(Keys.META).key_up("d").perform()


def test_the_space_bar_stops_with_the_speed_slider_focused(
    robot: Running, browser: webdriver.Chrome
) -> None:
    # Found by an outside check: the keydown handler left INPUTs alone before it looked at
    # the space bar, so with the slider just moved the operator's stop was ignored.
    open_page(browser, robot)
    page_ready(browser)
    tel = robot.daemon.last_telemetry
    assert tel is not None and tel.filt_lat_deg is not None
    here_n = (tel.filt_lat_deg - ORIGIN[0]) * M_PER_DEG_LAT
    with RemoteClient("127.0.0.1", robot.port) as c:
        c.request("mission.load", waypoints=[north(here_n + 15)])
        assert c.request("start")["mode"] == "RUNNING"
    try:
        browser.find_element(By.ID, "speed").click()
        assert js(browser, "return document.activeElement.id") == "speed"
        ActionChains(browser).send_keys(Keys.SPACE).perform()
        wait_for(lambda: robot.daemon.controller.mode == Mode.IDLE, 3, "stopped by the space bar")
    finally:
        with RemoteClient("127.0.0.1", robot.port) as c:
            c.request("stop")
    # the token field is a text field: a space typed there is text, not a stop
    assert js(
        browser,
        "const ev = new KeyboardEvent('keydown', {key: ' ', code: 'Space', bubbles: true,"
        " cancelable: true}); return document.getElementById('token-input').dispatchEvent(ev)",
    ), "a space in the token field was taken for a stop"


def test_a_reconnected_page_does_not_duplicate_the_track(
    robot: Running, browser: webdriver.Chrome
) -> None:
    # Found by an outside check: each reconnection prepended the daemon's whole track to the
    # page's (14 -> 26 -> 63 points over four reconnections).
    console = robot.daemon.console
    assert console is not None
    saved = list(console.track)
    console.track.clear()
    console.track.extend(tuple(north(float(i), 30.0)) for i in range(60))  # type: ignore[misc]
    try:
        open_page(browser, robot)
        page_ready(browser)
        wait_for(lambda: js(browser, "return x6wd.track.length") >= 60, 10, "the kept track")
        for _ in range(3):
            js(browser, "window.oldWs = x6wd.ws; x6wd.ws.close()")
            wait_for(
                lambda: js(browser, "return x6wd.ws !== window.oldWs && x6wd.authed"),
                10, "reconnected",
            )  # fmt: skip
            time.sleep(0.5)  # the track event, after the map
        n = js(browser, "return x6wd.track.length")
        assert 60 <= n <= len(console.track) + 10, (n, len(console.track))
    finally:
        console.track.clear()
        console.track.extend(saved)


class FreezingProxy:
    """A TCP relay in front of the console that can go silent (as a frozen daemon or a dead
    network path does: no FIN, bytes held) or hang up (as a daemon that stops does)."""

    def __init__(self, target_port: int) -> None:
        self.target = target_port
        self.flowing = threading.Event()
        self.flowing.set()
        self.accepting = True
        self.writers: list[asyncio.StreamWriter] = []
        self.loop = asyncio.new_event_loop()
        self.thread = threading.Thread(target=self.loop.run_forever, daemon=True)
        self.thread.start()
        self.port = asyncio.run_coroutine_threadsafe(self._start(), self.loop).result(10)

    async def _start(self) -> int:
        self.server = await asyncio.start_server(self._handle, "127.0.0.1", 0)
        return int(self.server.sockets[0].getsockname()[1])

    async def _handle(self, cr: asyncio.StreamReader, cw: asyncio.StreamWriter) -> None:
        if not self.accepting:
            cw.close()
            return
        sr, sw = await asyncio.open_connection("127.0.0.1", self.target)
        self.writers += [cw, sw]
        await asyncio.gather(self._pipe(cr, sw), self._pipe(sr, cw), return_exceptions=True)

    async def _pipe(self, r: asyncio.StreamReader, w: asyncio.StreamWriter) -> None:
        try:
            while data := await r.read(65536):
                while not self.flowing.is_set():  # held: the rest waits in the kernel
                    await asyncio.sleep(0.01)
                w.write(data)
                await w.drain()
        finally:
            w.close()

    def hang_up(self) -> None:
        """Close every connection (a FIN each way) and refuse new ones until resume()."""

        def close() -> None:
            self.accepting = False
            for w in self.writers:
                w.close()
            self.writers.clear()

        self.loop.call_soon_threadsafe(close)

    def resume(self) -> None:
        self.accepting = True

    def close(self) -> None:
        self.flowing.set()
        self.hang_up()

        async def shut() -> None:
            self.server.close()
            tasks = [t for t in asyncio.all_tasks() if t is not asyncio.current_task()]
            for t in tasks:
                t.cancel()
            await asyncio.gather(*tasks, return_exceptions=True)

        asyncio.run_coroutine_threadsafe(shut(), self.loop).result(10)
        self.loop.call_soon_threadsafe(self.loop.stop)
        self.thread.join(5)


def _stale(d: webdriver.Chrome) -> bool:
    return bool(js(d, "return document.body.classList.contains('stale')"))


def test_a_silent_link_is_shown_stale_and_drives_it_held_back_never_run(
    robot: Running, browser: webdriver.Chrome
) -> None:
    # Found by an outside check: with the link silent (the daemon stopped with SIGSTOP, or a
    # relay that stops forwarding) the page showed "connected", MANUAL and L 40 % R 40 % as
    # live for 30 s and more; and a key released during a short freeze had its queued
    # drives run when the link thawed (20-60 ms of 40 % after the release).
    console = robot.daemon.console
    assert console is not None
    proxy = FreezingProxy(console.port)
    try:
        browser.get("about:blank")
        browser.get(f"http://127.0.0.1:{proxy.port}/")
        page_ready(browser)
        _focus_map(browser)
        ActionChains(browser).key_down(Keys.ARROW_UP).perform()
        wait_for(lambda: vehicle_pct(robot)[0] > 0.0, 5, "the robot driving")
        late0 = console.late_drives
        proxy.flowing.clear()
        t0 = time.monotonic()
        wait_for(lambda: vehicle_pct(robot) == (0.0, 0.0), 2, "the drive run out")
        time.sleep(max(0.0, 1.0 - (time.monotonic() - t0)))
        ActionChains(browser).key_up(Keys.ARROW_UP).perform()  # released during the freeze
        time.sleep(max(0.0, 2.0 - (time.monotonic() - t0)))
        assert not _stale(browser)  # 2 s: within the page's patience
        proxy.flowing.set()  # the queued drives arrive, then the stop
        moved, end = [], time.monotonic() + 1.5
        while time.monotonic() < end:
            pct = vehicle_pct(robot)
            if pct != (0.0, 0.0):
                moved.append(pct)
            time.sleep(0.002)
        assert not moved, f"queued drives ran after the key was up: {moved[:5]}"
        assert console.late_drives > late0
        assert js(browser, "return x6wd.authed")  # the link itself lived on
        # a longer silence: the page says so within SILENCE_MS (3 s), greys what it shows.
        # Timed on the page's own clock, from the last message it heard to the moment its
        # body turned stale (the test's wall clock counted its own delays after the freeze
        # and the WebDriver polls: a loaded host pushed it under 2.5 s or over 5 s)
        js(
            browser,
            "window.heard = x6wd.heardAt; window.staleAt = null;"
            "x6wd.ws.addEventListener('message', () => { window.heard = x6wd.heardAt; });"
            "new MutationObserver(() => {"
            "  if (window.staleAt === null && document.body.classList.contains('stale'))"
            "    window.staleAt = performance.now() - window.heard;"
            "}).observe(document.body, {attributes: true, attributeFilter: ['class']});",
        )
        proxy.flowing.clear()
        wait_for(lambda: _stale(browser), 15, "the page marked stale")
        silent_ms = js(browser, "return window.staleAt")
        assert 3000.0 <= silent_ms < 5000.0, silent_ms  # its check runs every 250 ms
        assert text(browser, "conn").startswith("no data for 3 s")
        opacity = js(
            browser,
            "return getComputedStyle(document.getElementById('tel-motors').closest('.live'))"
            ".opacity",
        )
        assert float(opacity) < 0.6, opacity
        proxy.flowing.set()
        wait_for(lambda: not _stale(browser), 10, "fresh values after reconnecting")
        assert text(browser, "conn") == "connected"
        # the daemon hanging up (it stopped): "disconnected", and the values stale too
        proxy.hang_up()
        wait_for(lambda: _stale(browser), 3, "stale on a closed link")
        assert text(browser, "conn") == "disconnected"
        assert "(stale)" in js(
            browser, "return getComputedStyle(document.getElementById('mode'), '::after').content"
        )
        proxy.resume()
        wait_for(lambda: not _stale(browser), 10, "reconnected")
    finally:
        proxy.close()
        with RemoteClient("127.0.0.1", robot.port) as c:
            c.request("stop")


# -- the dead-man ----------------------------------------------------------------------------------
def _chromium_pid(d: webdriver.Chrome) -> int:
    """The browser process chromedriver started (a child of it)."""
    driver_pid = d.service.process.pid
    children = [  # each thread's own children: chromedriver starts it from another thread
        pid
        for task in Path(f"/proc/{driver_pid}/task").iterdir()
        for pid in (task / "children").read_text().split()
    ]
    for pid in children:
        if "chrom" in Path(f"/proc/{pid}/cmdline").read_bytes().decode(errors="replace"):
            return int(pid)
    raise AssertionError(f"no browser among chromedriver's children {children}")


def _hold_forward(d: webdriver.Chrome, r: Running) -> None:
    open_page(d, r)
    page_ready(d)
    ActionChains(d).click_and_hold(d.find_element(By.ID, "drive-fwd")).perform()
    wait_for(lambda: vehicle_pct(r)[0] > 0.0, 5, "the robot driving")


DEADMAN_DRIVE_S = 30.0  # the page's drives last this long here (sent again every 10 s)
DEADMAN_BOUND_S = 10.0  # many times a loaded host's stop; the drive running out: >= 20 s


def test_dead_man_a_page_hidden_or_a_browser_gone_stops_the_motors(tmp_path: Path) -> None:
    # each drive lasts DEADMAN_DRIVE_S here: a stop within DEADMAN_BOUND_S is the dead-man's
    # doing, not the drive running out (>= 20 s after the page's last word). (With 5 s drives
    # and a 2.5 s bound, a loaded host's WebDriver and stop latency ate the 0.8 s margin.)
    cfg = console_config(tmp_path, deadman_s=DEADMAN_DRIVE_S)
    cfg = dataclasses.replace(
        cfg, safety=SafetyConfig(geofence_radius_m=100.0, manual_max_s=DEADMAN_DRIVE_S)
    )
    with daemon_with(cfg) as r:
        wait_for(lambda: has_fix(r), 30, "a fix")
        d = chromium(tmp_path)
        try:
            _hold_forward(d, r)
            time.sleep(2.0)  # held: the robot keeps going
            assert vehicle_pct(r)[0] > 0.0
            # the page is hidden (another tab, the screen locked): motors stop at once
            t0 = time.monotonic()
            js(
                d,
                "Object.defineProperty(document, 'hidden', {value: true, configurable: true});"
                "document.dispatchEvent(new Event('visibilitychange'))",
            )
            wait_for(lambda: vehicle_pct(r) == (0.0, 0.0), DEADMAN_BOUND_S, "stop on a hidden page")
            assert time.monotonic() - t0 < DEADMAN_BOUND_S
            ActionChains(d).release().perform()
            # driving again, then the browser dies (no page code runs): the daemon stops
            js(d, "delete document.hidden")
            _hold_forward(d, r)
            pid = _chromium_pid(d)
            t0 = time.monotonic()
            os.kill(pid, signal.SIGKILL)
            wait_for(
                lambda: vehicle_pct(r) == (0.0, 0.0), DEADMAN_BOUND_S, "stop on a browser gone"
            )
            assert time.monotonic() - t0 < DEADMAN_BOUND_S
            console = r.daemon.console
            assert console is not None
            # counted once the stop's reply is back, after the motors stopped: waited for
            wait_for(lambda: console.deadman_stops > 0, 5.0, "the dead-man stop counted")
            assert console.deadman_stops == 1
        finally:
            with contextlib.suppress(Exception):
                d.quit()
