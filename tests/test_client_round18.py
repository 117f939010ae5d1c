"""`x6wd client stop` reaches the robot whichever way `--tls` is set (an outside audit,
round 18): plain text to the daemon's TLS port was closed without a word, and `--tls` to a
plain port failed its handshake; both ended in exit 3 with the robot driving on. The stop
now goes once more over the other transport, said as unverified (exit 4, no token sent)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from tests.test_client import client, tls_server_context
from tests.test_server import TOKEN, LoopThread, RecordingBackend, start_server
from x6wd.app.client import EXIT_UNVERIFIED


@pytest.mark.parametrize("daemon_tls", [True, False], ids=["tls-daemon", "plain-daemon"])
def test_a_stop_with_the_wrong_tls_setting_still_reaches_the_robot(
    tmp_path: Path, daemon_tls: bool
) -> None:
    token = tmp_path / "token"
    token.write_text(TOKEN + "\n")
    token.chmod(0o600)
    lt = LoopThread()
    backend = RecordingBackend()
    ctx = tls_server_context(tmp_path)[0] if daemon_tls else None
    srv = start_server(lt, backend, token=TOKEN.encode(), ssl_context=ctx)
    try:
        flags = [] if daemon_tls else ["--tls"]  # the wrong one of each
        r = client(srv.port, *flags, "stop", token=token)
        assert r.returncode == EXIT_UNVERIFIED, (r.returncode, r.stderr)
        assert "reply NOT verified" in r.stdout, r.stdout
        assert ("WITHOUT verification" if daemon_tls else "PLAIN TEXT") in r.stderr, r.stderr
        assert [name for name, _ in backend.calls] == ["stop"]
        assert srv.auth_failed_total == 0  # the token never went over the fallback
        # nothing but a stop is sent so: any other action fails as before
        r = client(srv.port, *flags, "status", token=token)
        assert r.returncode == 3, (r.returncode, r.stderr)
        assert [name for name, _ in backend.calls] == ["stop"]
    finally:
        lt.run(srv.close())
        lt.close()


def test_the_client_aimed_at_the_gpsd_port_says_so_at_once() -> None:
    # an audit (round 18): it waited its whole --timeout, then "no reply to 'stop'", though
    # the gpsd port had answered at once (its VERSION line has no id)
    import time

    from tests.test_gpsd_port import Published

    p = Published()
    try:
        t0 = time.monotonic()
        r = client(p.srv.port, "--timeout", "20", "stop")
        took_s = time.monotonic() - t0
    finally:
        p.close()
    assert r.returncode != 0 and "gpsd-compatible port" in r.stderr, r.stderr
    assert "7601" in r.stderr and took_s < 10.0, (took_s, r.stderr)


def test_the_robot_s_notes_on_a_load_are_printed(tmp_path: Path) -> None:
    # a waypoint by the geofence's edge is loaded with the robot's note (round 18); the
    # client printed only its own file's notes
    class Noting(RecordingBackend):
        def load_mission(self, waypoints: list[Any]) -> dict[str, Any]:
            return {**super().load_mission(waypoints), "notes": ["waypoint 1 (0.5 m) within"]}

    csv = tmp_path / "m.csv"
    csv.write_text("lat,lon\n51.7520,-1.2577\n")
    lt = LoopThread()
    srv = start_server(lt, Noting())
    try:
        r = client(srv.port, "load", str(csv))
    finally:
        lt.run(srv.close())
        lt.close()
    assert r.returncode == 0, r.stderr
    assert "x6wd client: note: waypoint 1 (0.5 m) within" in r.stderr, r.stderr


def test_a_stalled_tls_handshake_is_no_reason_to_fall_back_to_plain_text() -> None:
    # a review (round 18): a port that stalls the handshake (overloaded, or someone in the
    # middle) counted as "does not speak TLS"; the stop went again in plain text, and the
    # port's close then said "add --tls" although --tls was given
    import contextlib
    import socket
    import threading

    server = socket.create_server(("127.0.0.1", 0))
    seen: list[bytes] = []
    stop = threading.Event()

    def stall() -> None:
        server.settimeout(0.2)
        conns = []
        while not stop.is_set():
            try:
                conn, _ = server.accept()
            except TimeoutError:
                continue
            conns.append(conn)  # never answers the ClientHello
            conn.settimeout(0.5)
            with contextlib.suppress(TimeoutError):
                seen.append(conn.recv(4096))
        for conn in conns:
            conn.close()

    t = threading.Thread(target=stall, daemon=True)
    t.start()
    try:
        r = client(server.getsockname()[1], "--tls", "--timeout", "1", "stop")
    finally:
        stop.set()
        t.join(5)
        server.close()
    assert r.returncode == 3, (r.returncode, r.stderr)
    assert "timed out" in r.stderr and "add --tls" not in r.stderr, r.stderr
    assert not any(b'"cmd"' in s for s in seen), seen  # nothing sent in plain text
