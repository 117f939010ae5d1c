"""What a mission file holds but x6wd will not drive reaches the user on every route the file
takes (the control port's ``mission.load``, the console's ``mission.parse``, ``x6wd client
load``), not only ``x6wd mission show``: nothing in a file is dropped silently."""

from __future__ import annotations

import asyncio
from pathlib import Path

import pytest

from tests.test_console import console_config, daemon_with, ws_to
from tests.test_server import RecordingBackend, loop_thread, start_server  # noqa: F401
from x6wd.app.cli import main
from x6wd.app.client import RemoteClient

# a route and a waypoint beside it: the route is driven, the waypoint is named in a note
GPX = (
    '<?xml version="1.0"?><gpx version="1.1" xmlns="http://www.topografix.com/GPX/1/1">'
    '<wpt lat="51.7525" lon="-1.2570"><name>cafe</name></wpt>'
    '<rte><rtept lat="51.7520" lon="-1.2577"/><rtept lat="51.7522" lon="-1.2577"/></rte></gpx>'
)


def test_the_control_ports_mission_load_replies_with_the_files_notes(loop_thread) -> None:  # noqa: F811
    srv = start_server(loop_thread, RecordingBackend())
    try:
        with RemoteClient("127.0.0.1", srv.port) as c:
            reply = c.request("mission.load", gpx=GPX)
            assert reply["count"] == 2 and len(reply["notes"]) == 1, reply
            assert "waypoint" in reply["notes"][0]
            plain = c.request("mission.load", waypoints=[[51.0, -1.0]])
            assert "notes" not in plain  # nothing to say: no key
    finally:
        loop_thread.run(srv.close())


def test_x6wd_client_load_prints_the_files_notes(loop_thread, tmp_path: Path, capsys) -> None:  # noqa: F811
    srv = start_server(loop_thread, RecordingBackend())
    path = tmp_path / "m.gpx"
    path.write_text(GPX)
    try:
        assert main(["client", "--port", str(srv.port), "load", str(path)]) == 0
    finally:
        loop_thread.run(srv.close())
    err = capsys.readouterr().err
    assert "x6wd client: note:" in err and "waypoint" in err, err


@pytest.mark.integration
def test_the_consoles_mission_parse_replies_with_the_files_notes(tmp_path: Path) -> None:
    async def program(r) -> None:  # type: ignore[no-untyped-def]
        async with ws_to(r) as w:
            reply = await w.request("mission.parse", content=GPX, format="gpx", name="m.gpx")
            assert reply["ok"] and len(reply["waypoints"]) == 2 and len(reply["notes"]) == 1

    with daemon_with(console_config(tmp_path)) as r:
        asyncio.run(program(r))
