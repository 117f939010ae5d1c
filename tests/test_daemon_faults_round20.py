"""The console's pages are told when the motors' stop at exit was not acknowledged (round 20).

Round 19 made the daemon say so to the control port's clients, the log and the recording,
and closed the console's pages with that reason too, but nothing checked the pages. Real
process, a real protocol board on TCP, a real WebSocket page on the console's port."""

from __future__ import annotations

import asyncio
import re
import signal
import time
from pathlib import Path

import aiohttp
import pytest

from tests.test_shutdown import DaemonProcess, TcpMotorBoard, board, drive_and_wait
from tests.test_startup import write_config

__all__ = ["board"]  # the fixture


def console_url(p: DaemonProcess) -> str:
    for line in p.lines:
        m = re.search(r"web console on (http://[\d.]+:\d+/)", line)
        if m:
            return m[1].replace("http", "ws", 1) + "ws"
    raise AssertionError("no console line:\n" + "\n".join(p.lines))


@pytest.mark.integration
@pytest.mark.parametrize("deaf", [False, True], ids=["answering", "deaf"])
def test_a_console_page_is_told_whether_the_stop_at_exit_was_acknowledged(
    tmp_path: Path, board: TcpMotorBoard, deaf: bool
) -> None:
    url = f"tcp://127.0.0.1:{board.port}?watchdog_ms=500"
    p = DaemonProcess(
        write_config(tmp_path, motors={"url": url}, console={"enabled": True, "port": 0})
    )
    try:
        ws_url = console_url(p)
        c = drive_and_wait(p, board, 40, 40)

        async def page() -> tuple[int | None, str]:
            async with aiohttp.ClientSession() as session, session.ws_connect(ws_url) as ws:
                await asyncio.wait_for(ws.receive_json(), 5)  # the welcome
                board.deaf = deaf
                await asyncio.sleep(0.3)
                p.proc.send_signal(signal.SIGTERM)
                deadline = time.monotonic() + 30
                while time.monotonic() < deadline:
                    msg = await asyncio.wait_for(ws.receive(), 30)
                    if msg.type in (aiohttp.WSMsgType.CLOSE, aiohttp.WSMsgType.CLOSED):
                        return ws.close_code, str(msg.extra or "")
                raise AssertionError("the page was never closed")

        try:
            code, reason = asyncio.run(page())
        finally:
            c.close()
        assert p.proc.wait(30) == (1 if deaf else 0)
    finally:
        p.stop()
    assert code == 1001, (code, reason)
    if deaf:
        assert reason == "x6wd stopping: the motors' stop NOT acknowledged", reason
    else:
        assert reason == "x6wd stopping", reason
