"""?DEVICE on the gpsd-compatible port (an audit, round 18: it was "Unrecognized request", so
`gpsctl` could not even show the receiver; gpsctl itself only talks to port 2947).
Read-only: the daemon's [gps] configuration rules the line, so a change is refused with
words that say so, as gpsd refuses what it cannot do."""

from __future__ import annotations

import json
import socket
from typing import Any

from tests.test_gpsd_port import Published


def ask(port: int, request: bytes, n: int) -> list[dict[str, Any]]:
    """The ``n`` replies after the greeting (VERSION) to ``request``."""
    with socket.create_connection(("127.0.0.1", port), timeout=5) as s, s.makefile("rb") as f:
        assert json.loads(f.readline())["class"] == "VERSION"
        s.sendall(request)
        return [json.loads(f.readline()) for _ in range(n)]


def test_device_is_the_receiver_and_changes_are_refused() -> None:
    p = Published()
    try:
        port = p.srv.port
        (dev,) = ask(port, b"?DEVICE;\n", 1)
        assert dev["class"] == "DEVICE" and dev["path"] == "/dev/ttyS0", dev
        (named,) = ask(port, b'?DEVICE={"path":"/dev/ttyS0"};\n', 1)
        assert named["class"] == "DEVICE", named
        (other,) = ask(port, b'?DEVICE={"path":"/dev/ttyUSB9"};\n', 1)
        assert other == {"class": "ERROR", "message": "Can't open /dev/ttyUSB9."}
        (change,) = ask(port, b'?DEVICE={"bps":115200};\n', 1)
        assert change["class"] == "ERROR" and "bps: not changed" in change["message"], change
    finally:
        p.close()
