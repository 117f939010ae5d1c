"""``recording.list`` on a hung recordings folder does not freeze the network loop.

A code review found the console listing the recorder's folder (os.scandir + stat) on the
network event loop, the loop that also reads every control-port client: on a hung SD card or
network mount one ``recording.list`` froze it, so no client's stop could be read and the
console's dead-man could not fire. The listing now runs in the console's file thread with a
timeout and an error reply; a folder that cannot be read is an error reply too, not a
closed page.

Real sockets on 127.0.0.1 (ports 8200-8299): the control server and the console on one
loop, a page on the WebSocket, the operator on the control port.
"""

from __future__ import annotations

import asyncio
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import aiohttp
import pytest

from tests.test_server import LoopThread, RecordingBackend
from x6wd.app.client import RemoteClient
from x6wd.app.console import server as console_server
from x6wd.app.console.server import ConsoleServer
from x6wd.app.server import ControlServer
from x6wd.core.config import ConsoleConfig, ServerConfig

pytestmark = pytest.mark.integration

PORTS = iter(range(8260, 8280))


@pytest.fixture
def served(tmp_path: Path) -> Iterator[tuple[LoopThread, ControlServer, ConsoleServer]]:
    lt = LoopThread()
    srv = ControlServer(ServerConfig(port=next(PORTS)), RecordingBackend())
    lt.run(srv.start())
    console = ConsoleServer(
        ConsoleConfig(enabled=True, port=next(PORTS)), srv, lambda: {}, recordings_dir=tmp_path
    )
    lt.run(console.start())
    try:
        yield lt, srv, console
    finally:
        lt.run(console.close())
        lt.run(srv.close())
        lt.close()


async def ask(ws: aiohttp.ClientWebSocketResponse, rid: int, cmd: str, **args: Any) -> Any:
    await ws.send_json({"id": rid, "cmd": cmd, **args})
    while (msg := await asyncio.wait_for(ws.receive_json(), 10)).get("id") != rid:
        pass
    return msg


def test_a_hung_recordings_folder_leaves_the_control_port_answering(
    served: tuple[LoopThread, ControlServer, ConsoleServer], monkeypatch: pytest.MonkeyPatch
) -> None:
    _lt, srv, console = served
    release = threading.Event()
    calls: list[float] = []

    def hung(directory: Any, prefix: str = "x6wd") -> list[Any]:
        calls.append(time.monotonic())
        release.wait(20)  # an NFS mount that does not answer
        return []

    monkeypatch.setattr(console_server, "list_recordings", hung)
    # 1 s (the default is 5 s): the error reply comes within 4 s after it, where a listing
    # with no timeout never answers (ask() gives up after 10 s)
    monkeypatch.setattr(console_server, "RECORDINGS_TIMEOUT_S", 1.0, raising=False)
    url = console.url.replace("http", "ws", 1) + "ws"
    answered: dict[str, Any] = {}
    operator_done = threading.Event()

    def operator() -> None:  # the control port, while the page's listing hangs
        try:
            deadline = time.monotonic() + 10.0
            while not calls and time.monotonic() < deadline:  # the listing has begun
                time.sleep(0.01)
            t0 = time.monotonic()
            with RemoteClient("127.0.0.1", srv.port, timeout_s=5) as c:
                answered["stop"] = c.request("stop")
            answered["stop_s"] = time.monotonic() - t0
            # the order is the test: a listing on the network loop holds every reply until
            # the folder answers, and it is released only after this (below)
            answered["while_hung"] = bool(calls) and not release.is_set()
        finally:
            operator_done.set()

    async def page() -> list[Any]:
        async with aiohttp.ClientSession() as session, session.ws_connect(url) as ws:
            await asyncio.wait_for(ws.receive_json(), 5)  # the welcome
            t0 = time.monotonic()
            first = await ask(ws, 1, "recording.list")
            first_s = time.monotonic() - t0
            second = await ask(ws, 2, "recording.list")  # still hung: joins the same listing
            view = await ask(ws, 3, "recording.view", name="x6wd-x.jsonl")
            status = await ask(ws, 4, "status")
            hung_calls = len(calls)
            for _ in range(1500):  # the operator's stop, up to 15 s, before the folder answers
                if operator_done.is_set():
                    break
                await asyncio.sleep(0.01)
            release.set()
            await asyncio.sleep(0.2)
            third = await ask(ws, 5, "recording.list")
            return [first, first_s, second, view, status, third, hung_calls]

    op = threading.Thread(target=operator)
    op.start()
    try:
        first, first_s, second, view, status, third, hung_calls = asyncio.run(page())
    finally:
        release.set()
        op.join(10)
    assert answered.get("stop", {}).get("ok"), answered
    assert answered["while_hung"], answered
    assert answered["stop_s"] < 3.0, answered  # ~0.01 s here; a frozen loop: ~10 s or more
    for reply in (first, second, view):
        assert reply["ok"] is False, reply
        assert reply["error"]["reason"] == "recordings_unavailable", reply
        assert "did not answer within 1 s" in reply["error"]["message"], reply
    assert first_s < 1.0 + 3.0
    assert status["ok"], status
    assert hung_calls == 1  # one hung listing at a time, not a thread per request
    assert third == {"id": 5, "ok": True, "recordings": []}


def test_an_unreadable_recordings_folder_is_an_error_reply(
    served: tuple[LoopThread, ControlServer, ConsoleServer], monkeypatch: pytest.MonkeyPatch
) -> None:
    _lt, _srv, console = served

    def refused(directory: Any, prefix: str = "x6wd") -> list[Any]:
        raise PermissionError(13, "Permission denied")

    monkeypatch.setattr(console_server, "list_recordings", refused)
    url = console.url.replace("http", "ws", 1) + "ws"

    async def page() -> list[Any]:
        async with aiohttp.ClientSession() as session, session.ws_connect(url) as ws:
            await asyncio.wait_for(ws.receive_json(), 5)
            return [await ask(ws, 1, "recording.list"), await ask(ws, 2, "status")]

    listed, status = asyncio.run(page())
    assert listed["ok"] is False and listed["error"]["reason"] == "recordings_unavailable"
    assert "Permission denied" in listed["error"]["message"]
    assert status["ok"]  # the page's link is still there
