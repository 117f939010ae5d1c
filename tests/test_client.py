"""`x6wd client` as a real subprocess against a real server; mission files; the watch view."""

from __future__ import annotations

import contextlib
import json
import os
import ssl
import subprocess
import sys
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from tests.conftest import DATA, require_program
from tests.test_server import TOKEN, LoopThread, RecordingBackend, start_server
from x6wd.app.client import CLEAR, render_status, render_watch
from x6wd.app.server import ControlServer
from x6wd.core.errors import ParseError
from x6wd.core.mission_files import Waypoint, load_file, parse_args, parse_csv, parse_gpx


@pytest.fixture
def served() -> Iterator[tuple[LoopThread, ControlServer, RecordingBackend]]:
    lt = LoopThread()
    backend = RecordingBackend()
    srv = start_server(lt, backend, token=TOKEN.encode())
    yield lt, srv, backend
    lt.run(srv.close())
    lt.close()


@pytest.fixture
def token_file(tmp_path: Path) -> Path:
    p = tmp_path / "token"
    p.write_text(TOKEN + "\n")
    p.chmod(0o600)
    return p


def client(port: int, *args: str, token: Path | None = None) -> subprocess.CompletedProcess[str]:
    cmd = [sys.executable, "-m", "x6wd", "client", "--port", str(port)]
    if token is not None:
        cmd += ["--token-file", str(token)]
    return subprocess.run(cmd + list(args), capture_output=True, text=True, timeout=30)


def test_status_start_stop_and_auth(served, token_file: Path) -> None:
    _, srv, backend = served
    r = client(srv.port, "status")  # for a person by default
    assert r.returncode == 0, r.stderr
    assert "state      IDLE / IDLE" in r.stdout and "{" not in r.stdout, r.stdout
    for args in (("--json", "status"), ("status", "--json")):  # for programs
        r = client(srv.port, *args)
        assert r.returncode == 0, r.stderr
        assert json.loads(r.stdout)["mode"] == "IDLE"
    r = client(srv.port, "start")  # no token: refused with a clear message
    assert r.returncode == 1
    assert "start refused: unauthorized" in r.stderr
    r = client(srv.port, "stop")  # always allowed
    assert r.returncode == 0 and "stop: ok" in r.stdout
    for action in ("start", "pause", "resume", "return"):
        r = client(srv.port, action, token=token_file)
        assert r.returncode == 0, r.stderr
        assert f"{action}: ok" in r.stdout
    assert [name for name, _ in backend.calls] == ["stop", "start", "pause", "resume", "return"]


def test_load_from_csv_gpx_and_arguments(served, token_file: Path, tmp_path: Path) -> None:
    _, srv, backend = served
    gpx = tmp_path / "m.gpx"
    gpx.write_text(
        '<gpx version="1.1"><wpt lat="51.75" lon="-1.25"><name>a</name></wpt>'
        '<wpt lat="51.76" lon="-1.26"/></gpx>'
    )
    assert client(srv.port, "load", str(gpx), token=token_file).returncode == 0
    r = client(srv.port, "load", "--wp", "51.7,-1.2", "--wp", "51.71,-1.21", token=token_file)
    assert r.returncode == 0, r.stderr
    assert (
        client(srv.port, "load", str(DATA / "client" / "mobile.csv"), token=token_file).returncode
        == 0
    )
    loads = [arg for name, arg in backend.calls if name == "load_mission"]
    assert loads[0] == [Waypoint(51.75, -1.25), Waypoint(51.76, -1.26)]
    assert loads[1] == [Waypoint(51.7, -1.2), Waypoint(51.71, -1.21)]
    assert len(loads[2]) == 1406 and loads[2][0] == Waypoint(39.821673201, -105.095171686)


def test_bad_input_and_refusals_give_clear_messages(
    served, token_file: Path, tmp_path: Path
) -> None:
    _, srv, _ = served
    bad = tmp_path / "bad.csv"
    bad.write_text("lat,lon\n51.0,-1.0\n91.5,-1.0\n")
    r = client(srv.port, "load", str(bad), token=token_file)
    assert r.returncode == 2 and "line 3" in r.stderr and "latitude 91.5" in r.stderr
    r = client(srv.port, "load", str(tmp_path / "missing.gpx"), token=token_file)
    assert r.returncode == 2 and "cannot read" in r.stderr
    r = client(srv.port, "load", "--wp", "51.0;-1.0", token=token_file)
    assert r.returncode == 2 and "LAT,LON" in r.stderr
    for args, said in (
        (("150", "0", "1"), "left: must be within -100..100 %, got 150"),
        (("0", "-100.5", "1"), "right: must be within -100..100 %, got -100.5"),
        (("10", "10", "3601"), "seconds: must be a finite number of seconds, > 0 and at most"),
    ):  # bad input, found by the client and never sent: exit 2, as for NaN
        r = client(srv.port, "drive", *args, token=token_file)
        assert r.returncode == 2 and said in r.stderr, r.stderr
    r = client(srv.port, "drive", "-100", "100", "0.2", token=token_file)  # the bounds themselves
    assert r.returncode == 0, r.stderr
    r = client(srv.port, "--timeout", "5000", "status")  # a reply timeout is no drive: no cap
    assert r.returncode == 0, r.stderr
    r = client(srv.port, "drive", "20", "-20", "1.5", token=token_file)
    assert r.returncode == 0, r.stderr


def test_drive_holds_its_connection_and_ctrl_c_stops_the_robot(served, token_file: Path) -> None:
    """The robot stops a drive whose client went away, so the client stays for the drive's
    duration; Ctrl-C sends ``stop`` and exits 130."""
    import signal
    import time

    _, srv, backend = served
    t0 = time.monotonic()
    r = client(srv.port, "drive", "20", "-20", "1.5", token=token_file)
    assert r.returncode == 0 and "drive: ok" in r.stdout, r.stderr
    assert time.monotonic() - t0 >= 1.5
    assert [n for n, _ in backend.calls] == ["drive"]
    cmd = [sys.executable, "-m", "x6wd", "client", "--port", str(srv.port)]
    proc = subprocess.Popen(
        [*cmd, "--token-file", str(token_file), "drive", "30", "30", "20"],
        stderr=subprocess.PIPE, text=True,
        # a background job may inherit SIGINT ignored: give the child Ctrl-C's default
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )  # fmt: skip
    deadline = time.monotonic() + 20
    while [n for n, _ in backend.calls] != ["drive", "drive"]:
        assert time.monotonic() < deadline and proc.poll() is None
        time.sleep(0.02)
    proc.send_signal(signal.SIGINT)
    _, stderr = proc.communicate(timeout=10)
    assert proc.returncode == 130 and "stop sent" in stderr, stderr
    assert [n for n, _ in backend.calls] == ["drive", "drive", "stop"]


@contextlib.contextmanager
def drive_under_way(
    backend: RecordingBackend, token_file: Path
) -> Iterator[tuple[LoopThread, ControlServer, subprocess.Popen[str]]]:
    """A real server on ``backend`` and `x6wd client drive 30 30 10` against it (Ctrl-C at
    its default), yielded once the drive reached the backend; all closed after."""
    import signal
    import time

    lt = LoopThread()
    srv = start_server(lt, backend, token=TOKEN.encode())
    cmd = [sys.executable, "-m", "x6wd", "client", "--port", str(srv.port)]
    proc = subprocess.Popen(
        [*cmd, "--token-file", str(token_file), "drive", "30", "30", "10"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )  # fmt: skip
    try:
        deadline = time.monotonic() + 20
        while not backend.calls:
            assert time.monotonic() < deadline and proc.poll() is None
            time.sleep(0.01)
        yield lt, srv, proc
    finally:
        proc.kill()
        lt.run(srv.close())
        lt.close()


class SlowDriveBackend(RecordingBackend):
    """A robot that takes its time to confirm a drive it has already started."""

    async def drive(self, left_pct: float, right_pct: float, duration_s: float) -> dict[str, Any]:
        import asyncio

        reply = super().drive(left_pct, right_pct, duration_s)
        await asyncio.sleep(1.0)
        return reply


def test_ctrl_c_before_the_drive_is_confirmed_stops_the_robot_too(token_file: Path) -> None:
    """Ctrl-C while the drive's reply is on its way (the motors already run): the client
    sends ``stop`` and says so, rather than leaving with exit 130 and no stop (CI saw this
    on a loaded machine: the daemon's dead-man stopped the motors, the client claimed it)."""
    import signal
    import time

    backend = SlowDriveBackend()
    with drive_under_way(backend, token_file) as (_, srv, proc):
        proc.send_signal(signal.SIGINT)  # the drive's reply is a second away
        _, stderr = proc.communicate(timeout=10)
        time.sleep(0.2)  # the server sees the close
        stops = srv.server_stats()["stops"]
    assert proc.returncode == 130 and "stop sent" in stderr, stderr
    assert [n for n, _ in backend.calls] == ["drive", "stop"]
    assert stops["orphaned"] == 0, stops  # the client's stop, not the dead-man's


def test_drive_reports_a_robot_stopped_early_or_a_server_gone(token_file: Path) -> None:
    """Another operator's stop mid-drive: exit 1, 'ended early'; the server going away:
    exit 3. Neither is 'drive: ok'."""

    from x6wd.app.client import RemoteClient

    for how, code, said in (("stop", 1, "ended early: the robot is IDLE"), ("close", 3, "")):
        with drive_under_way(RecordingBackend(), token_file) as (lt, srv, proc):
            if how == "stop":
                with RemoteClient("127.0.0.1", srv.port) as other:
                    other.request("stop")
            else:
                lt.run(srv.close())
            out, stderr = proc.communicate(timeout=10)
        assert proc.returncode == code and "drive: ok" not in out, (how, out, stderr)
        assert said in stderr, stderr


class CountingBackend(RecordingBackend):
    """Counts the status requests (a drive's client polls them)."""

    statuses = 0

    def status(self) -> dict[str, Any]:
        self.statuses += 1
        return super().status()


def test_a_daemon_shutting_down_mid_drive_is_said_as_such(token_file: Path) -> None:
    """An outside audit: SIGTERM to the daemon during `x6wd client drive` gave "the drive
    ended early: the robot is IDLE" (exit 1) in 5 of 9 tries: the daemon stops the motors
    and answers IDLE a moment before its closing notice. The client waits for that notice
    before calling a drive cut short: "the robot's daemon shut down", exit 3."""
    import time

    backend = CountingBackend()
    with drive_under_way(backend, token_file) as (lt, srv, proc):
        backend.manual_until = 0.0  # the daemon's shutdown: motors stopped, IDLE ...
        seen = backend.statuses
        deadline = time.monotonic() + 20
        while backend.statuses == seen:  # ... which the client has seen ...
            assert time.monotonic() < deadline
            time.sleep(0.01)
        time.sleep(0.2)
        lt.run(srv.close())  # ... then its goodbye
        out, stderr = proc.communicate(timeout=10)
    assert proc.returncode == 3 and "shut down" in stderr, (proc.returncode, stderr)
    assert "ended early" not in stderr and "drive: ok" not in out


def test_the_servers_reason_for_closing_is_reported(tmp_path: Path) -> None:
    """A connection that does not authenticate in time is closed with a notice; the client
    says why (exit 3 from the command line)."""
    import time

    from x6wd.app.client import ConnectionFailed, RemoteClient

    lt = LoopThread()
    srv = start_server(lt, RecordingBackend(), token=TOKEN.encode(), auth_timeout_s=0.2)
    try:
        c = RemoteClient("127.0.0.1", srv.port)  # no token: never authenticates
        time.sleep(0.5)
        with pytest.raises(ConnectionFailed, match=r"closed the connection \(auth_timeout\)"):
            c.request("status")
        c.close()
        # a watcher that has to make room for a newly authenticated operator learns why
        full = start_server(lt, RecordingBackend(), token=TOKEN.encode(), max_clients=1)
        with RemoteClient("127.0.0.1", full.port, token=TOKEN) as watcher:
            watcher.request("watch", on=True)
            with RemoteClient("127.0.0.1", full.port, token=TOKEN) as op:
                assert op.request("stop")["ok"]
            with pytest.raises(ConnectionFailed, match=r"\(sessions_full\)"):
                watcher.next_event(5.0)
        lt.run(full.close())
        wrong = tmp_path / "wrong"
        wrong.write_text("not-the-token\n")
        wrong.chmod(0o600)
        r = client(srv.port, "start", token=wrong)
        assert r.returncode == 1 and "start refused: auth_failed" in r.stderr
    finally:
        lt.run(srv.close())
        lt.close()


def test_connection_refused_is_exit_3(tmp_path: Path) -> None:
    import socket

    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()  # nothing listens there now
    r = client(port, "status")
    assert r.returncode == 3
    assert f"cannot connect to 127.0.0.1:{port}" in r.stderr


TEL: dict[str, Any] = {
    "mode": "RUNNING", "state": "TURN_LEFT", "hold_reason": "", "waypoint_index": 1,
    "waypoint_count": 3, "lat_deg": 51.7512345, "lon_deg": -1.2567891,
    "filt_lat_deg": 51.7512301, "filt_lon_deg": -1.2567802, "bearing_deg": 93.5,
    "heading_deg": 95.0, "pitch_deg": -4.0, "roll_deg": 2.0, "target_bearing_deg": 40.0,
    "theta_deg": -55.0, "distance_m": 12.34, "fix_quality": 1, "sats_used": 7, "hdop": 1.1,
    "fix_age_s": 0.4, "attitude_age_s": 0.05, "left_pct": -40.0, "right_pct": 40.0,
}  # fmt: skip


def test_watch_redraws_one_screen_per_event(served, token_file: Path) -> None:
    lt, srv, _ = served
    stop = threading.Event()

    def publish() -> None:
        while not stop.wait(0.05):
            lt.call(lambda: srv.publish({"event": "telemetry", "data": TEL}))

    t = threading.Thread(target=publish, daemon=True)
    t.start()
    try:
        r = client(srv.port, "watch", "--count", "3", token=token_file)
    finally:
        stop.set()
        t.join()
    assert r.returncode == 0, r.stderr
    screens = r.stdout.split(CLEAR)
    assert screens[0] == "" and len(screens) == 4
    last = screens[-1]
    for text in ("RUNNING / TURN_LEFT", "51.7512345", "51.7512301", "95.0 deg true", "-4 deg",
                 "2/3", "12.3 m", "quality 1", "sats 7", "motors ok"):  # fmt: skip
        assert text in last, (text, last)


def test_every_view_shows_one_heading_true_in_degrees_0_to_360() -> None:
    # the controller's heading can come as -2.4 (true); the compass read 358.1 magnetic
    tel = {**TEL, "bearing_deg": 358.1, "heading_deg": -2.4, "target_bearing_deg": -0.04}
    for screen in (render_watch(tel), render_status({"telemetry": tel, "mode": "RUNNING"})):
        assert "heading    357.6 deg true" in screen, screen
        assert "bearing 0.0 deg true" in screen, screen  # to the waypoint
        assert "magnetic" not in screen and "358.1" not in screen and "-2.4" not in screen


def test_status_for_a_person_names_what_is_wrong() -> None:
    st = {
        "version": "0.1.0", "uptime_s": 3725.0, "mode": "IDLE", "state": "IDLE",
        "telemetry": None, "links": {"gps": "disconnected", "gps_reconnects": 3, "motors": "ok"},
        "devices": {"gps": {"state": "disconnected", "last_error": "read failed: EIO"},
                    "motors": {"state": "connected", "last_error": ""}},
        "declination": {"source": "wmm", "deg": -0.42},
        "server": {"clients": 2, "pending": 0, "dropped": 5},
    }  # fmt: skip
    text = render_status(st)
    assert text.startswith("x6wd 0.1.0  up 1h02m05s\n")
    for part in ("IDLE / IDLE  (no telemetry yet)", "declination -0.42 deg (wmm)",
                 "links      gps disconnected  motors ok", "gps      disconnected: read failed",
                 "server     2 clients, 0 pending, 5 events dropped"):  # fmt: skip
        assert part in text, (part, text)
    assert "motors   connected" not in text  # only the devices with a problem
    assert "recorder" not in text
    st["recorder"] = {"state": "failing", "last_error": "[Errno 28] No space left on device",
                      "records_dropped": 940}  # fmt: skip
    assert (
        "  recorder failing: [Errno 28] No space left on device (940 records not recorded)"
        in render_status(st)
    )
    st["recorder"] = {"state": "ok", "last_error": "an old one", "records_dropped": 940}
    assert "recorder" not in render_status(st)


def test_a_closed_pipe_ends_the_client_quietly(served, token_file: Path) -> None:
    lt, srv, _ = served
    stop = threading.Event()

    def publish() -> None:
        while not stop.wait(0.02):
            lt.call(lambda: srv.publish({"event": "telemetry", "data": TEL}))

    t = threading.Thread(target=publish, daemon=True)
    t.start()
    cmd = [sys.executable, "-m", "x6wd", "client", "--port", str(srv.port),
           "--token-file", str(token_file), "watch", "--no-ansi"]  # fmt: skip
    try:
        # `x6wd client watch | head -2`: the reader goes away after two lines
        proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
        assert proc.stdout is not None and proc.stderr is not None
        assert proc.stdout.readline().startswith(b"x6wd watch")
        proc.stdout.readline()
        proc.stdout.close()
        assert proc.wait(20) == 0
        err = proc.stderr.read().decode()
        proc.stderr.close()
    finally:
        stop.set()
        t.join()
    assert err == "", err  # no BrokenPipeError traceback, no message


def test_render_watch_shows_hold_reason_and_unknowns() -> None:
    screen = render_watch({"mode": "RUNNING", "state": "HOLD", "hold_reason": "fix stale"})
    assert "HOLD: fix stale" in screen
    assert "position   - -" in screen
    assert "waypoint   -" in screen


def test_mission_file_parsers() -> None:
    assert parse_csv("# comment\n51.0, -1.0\n\n51.1,-1.1\n") == [(51.0, -1.0), (51.1, -1.1)]
    assert parse_csv("name,Longitude,Latitude\nA,-1.0,51.0\n") == [(51.0, -1.0)]
    with pytest.raises(ParseError, match="header needs lat and lon"):
        parse_csv("name,lat\nA,51\n")
    with pytest.raises(ParseError, match="line 2: expected at least 2 columns"):
        parse_csv("51,-1\n52\n")
    with pytest.raises(ParseError, match="no waypoints"):
        parse_csv("lat,lon\n")
    trk = (
        '<gpx xmlns="http://www.topografix.com/GPX/1/0"><trk><trkseg>'
        '<trkpt lat="1.5" lon="2.5"/><trkpt lat="1.6" lon="2.6"/></trkseg></trk></gpx>'
    )
    assert parse_gpx(trk) == [(1.5, 2.5), (1.6, 2.6)]
    with pytest.raises(ParseError, match="DTDs and entities"):
        parse_gpx('<!DOCTYPE gpx [<!ENTITY a "b">]><gpx><wpt lat="1" lon="2"/></gpx>')
    with pytest.raises(ParseError, match="not valid XML"):
        parse_gpx("<gpx><wpt")
    with pytest.raises(ParseError, match="expected <gpx>"):
        parse_gpx("<kml/>")
    with pytest.raises(ParseError, match="longitude 200"):
        parse_args(["1,200"])
    with pytest.raises(ParseError, match="must be finite"):
        parse_args(["nan,1"])


def test_real_csv_with_many_columns() -> None:
    wps = load_file(DATA / "client" / "mobile.csv")
    assert len(wps) == 1406
    assert wps[-1].lat_deg == pytest.approx(39.8216, abs=1e-3)
    assert all(-105.1 < w.lon_deg < -105.09 for w in wps)


def tls_server_context(tmp_path: Path) -> tuple[ssl.SSLContext, Path]:
    """A server TLS context of a fresh self-signed certificate for 127.0.0.1 (openssl), and
    the certificate's file (a client's --cafile)."""
    openssl = require_program("openssl")
    cert, key = tmp_path / "cert.pem", tmp_path / "key.pem"
    subprocess.run(
        [openssl, "req", "-x509", "-newkey", "rsa:2048", "-nodes", "-days", "2",
         "-subj", "/CN=localhost", "-addext", "subjectAltName=IP:127.0.0.1",
         "-keyout", str(key), "-out", str(cert)],
        check=True, capture_output=True,
    )  # fmt: skip
    os.chmod(key, 0o600)
    ctx = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
    ctx.load_cert_chain(cert, key)
    return ctx, cert


def test_tls_from_the_command_line(tmp_path: Path, token_file: Path) -> None:
    ctx, cert = tls_server_context(tmp_path)
    lt = LoopThread()
    backend = RecordingBackend()
    srv = start_server(lt, backend, token=TOKEN.encode(), ssl_context=ctx)
    try:
        r = client(srv.port, "--cafile", str(cert), "start", token=token_file)
        assert r.returncode == 0, r.stderr
        r = client(srv.port, "--tls", "start", token=token_file)  # untrusted certificate
        assert r.returncode == 3 and "TLS handshake" in r.stderr
        r = client(srv.port, "status")  # plain text to a TLS port: a hint (outside audit)
        assert r.returncode == 3 and "add --tls" in r.stderr, r.stderr
    finally:
        lt.run(srv.close())
        lt.close()
    assert [name for name, _ in backend.calls] == ["start"]


def test_bad_options_and_peers_that_are_not_the_robot_give_clear_errors(
    served, token_file: Path, tmp_path: Path
) -> None:
    # an outside check: each was a traceback, a wrap-around to another port, a hang, or the
    # token in plain text
    import socket
    import threading

    _, srv, _ = served
    for opts in (["--port", str(srv.port + 65536)], ["--port", "-1"], ["--timeout", "nan"],
                 ["--timeout", "0"]):  # fmt: skip
        r = subprocess.run([sys.executable, "-m", "x6wd", "client", *opts, "status"],
                           capture_output=True, text=True, timeout=30)  # fmt: skip
        assert r.returncode == 2 and "Traceback" not in r.stderr, (opts, r.stderr)
    r = client(srv.port, "watch", "--count", "0")
    assert r.returncode == 2 and "must be >= 1" in r.stderr
    r = client(srv.port, "--cafile", str(tmp_path / "missing.pem"), "status")
    assert r.returncode == 2 and "--cafile" in r.stderr and "Traceback" not in r.stderr
    raw = tmp_path / "raw"
    raw.write_bytes(b"abcdefgh\xff\xfe")
    raw.chmod(0o600)
    r = client(srv.port, "start", token=raw)
    assert r.returncode == 2 and "--token-file" in r.stderr and "not UTF-8" in r.stderr
    r = client(srv.port, "status", token=raw)  # answered without a token: only a warning
    assert r.returncode == 0 and "warning: --token-file" in r.stderr and "not UTF-8" in r.stderr

    # peers that are not the control port: one dripping bytes with no newline, one HTTP
    # server, one that never listens for TLS; and what --insecure sends
    got: list[bytes] = []
    server = socket.create_server(("127.0.0.1", 0))

    def answer(conn: socket.socket, k: int) -> None:
        import contextlib

        with conn, contextlib.suppress(OSError):  # the client hangs up first
            got.append(conn.recv(4096))
            if got[-1].startswith(b"\x16"):  # a TLS hello: answer nothing
                return
            conn.sendall(b"HTTP/1.0 400 Bad request\r\n\r\n" if k == 1 else b"x")
            for _ in range(40):
                conn.sendall(b"x")
                threading.Event().wait(0.1)

    def serve() -> None:
        import contextlib

        with contextlib.suppress(OSError):
            for k in range(3):
                conn, _ = server.accept()
                threading.Thread(target=answer, args=(conn, k), daemon=True).start()

    threading.Thread(target=serve, daemon=True).start()
    port = server.getsockname()[1]
    try:
        r = subprocess.run(
            [sys.executable, "-m", "x6wd", "client", "--port", str(port), "--timeout", "1",
             "status"], capture_output=True, text=True, timeout=30,
        )  # fmt: skip
        assert r.returncode == 3 and "within 1 s" in r.stderr, r.stderr  # not 4 s of drips
        r = client(port, "status")
        assert r.returncode == 3 and "does not answer in the x6wd control protocol" in r.stderr
        r = client(port, "--insecure", "status", token=token_file)
        assert r.returncode == 3
        assert got[-1].startswith(b"\x16")  # a TLS hello, never the token in the clear
    finally:
        server.close()


def test_stop_reaches_the_robot_whatever_happens_with_the_token(
    served, token_file: Path, tmp_path: Path
) -> None:
    """stop is always obeyed (docs/protocol.md): a wrong token, a token file that does not
    exist or that others may read is a warning for ``stop`` (and the read-only ``status``),
    the robot is stopped all the same, exit 0. Every other command still fails."""
    _, srv, backend = served
    wrong = tmp_path / "wrong"
    wrong.write_text("not-the-token-at-all\n")
    wrong.chmod(0o600)
    loose = tmp_path / "loose"
    loose.write_text(TOKEN + "\n")
    loose.chmod(0o644)
    missing = tmp_path / "missing"
    for bad, said in ((wrong, "refused the token"), (missing, "cannot read"),
                      (loose, "chmod 600")):  # fmt: skip
        backend.calls.clear()
        r = client(srv.port, "stop", token=bad)
        assert r.returncode == 0 and r.stdout == "stop: ok\n", (bad, r.stdout, r.stderr)
        assert backend.calls == [("stop", None)], bad  # the robot was told to stop
        assert "warning" in r.stderr and said in r.stderr, (bad, r.stderr)
        r = client(srv.port, "status", token=bad)  # read-only: answered too, with a warning
        assert r.returncode == 0 and "state      IDLE / IDLE" in r.stdout, (bad, r.stderr)
        assert "warning" in r.stderr and said in r.stderr, (bad, r.stderr)
        r = client(srv.port, "start", token=bad)  # anything else: as before
        assert r.returncode == (1 if bad is wrong else 2), (bad, r.stderr)
        assert "warning" not in r.stderr
        assert backend.calls == [("stop", None)], bad
    r = client(srv.port, "--json", "stop", token=wrong)
    assert r.returncode == 0 and json.loads(r.stdout) == {"did": "stop"}, r.stderr
    r = client(srv.port, "stop", token=token_file)  # the right token: no word about it
    assert r.returncode == 0 and r.stdout == "stop: ok\n" and r.stderr == "", r.stderr


def test_a_status_whose_token_closes_the_connection_asks_again_without_it(
    token_file: Path, tmp_path: Path
) -> None:
    """With ``max_auth_failures = 1`` the robot closes the connection at the first wrong
    token: ``status`` asks again on a new one; ``stop`` was sent before the token."""
    lt = LoopThread()
    backend = RecordingBackend()
    srv = start_server(lt, backend, token=TOKEN.encode(), max_auth_failures=1)
    wrong = tmp_path / "wrong"
    wrong.write_text("not-the-token-at-all\n")
    wrong.chmod(0o600)
    try:
        r = client(srv.port, "status", token=wrong)
        assert r.returncode == 0 and "state      IDLE / IDLE" in r.stdout, r.stderr
        assert "auth_failed" in r.stderr and "warning" in r.stderr, r.stderr
        r = client(srv.port, "stop", token=wrong)
        assert r.returncode == 0 and "stop: ok" in r.stdout, r.stderr
        assert "warning" in r.stderr, r.stderr
        assert backend.calls == [("stop", None)]
        assert client(srv.port, "pause", token=wrong).returncode == 1  # refused: as before
    finally:
        lt.run(srv.close())
        lt.close()


def test_watch_json_prints_one_object_per_line_and_no_screen(served, token_file: Path) -> None:
    lt, srv, _ = served
    stop = threading.Event()
    state = {"event": "state", "old": "STRAIGHT", "new": "TURN_LEFT", "reason": "state: fix"}

    def publish() -> None:
        while not stop.wait(0.05):
            lt.call(lambda: srv.publish({"event": "telemetry", "data": TEL}))
            lt.call(lambda: srv.publish(state))

    t = threading.Thread(target=publish, daemon=True)
    t.start()
    try:
        for args in (("watch", "--json", "--count", "3"), ("--json", "watch", "--count", "3")):
            r = client(srv.port, *args, token=token_file)
            assert r.returncode == 0, r.stderr
            assert "\x1b" not in r.stdout and "x6wd watch" not in r.stdout, r.stdout
            objs = [json.loads(line) for line in r.stdout.splitlines()]
            assert objs[0]["status"]["mode"] == "IDLE"  # the status it watches with
            assert "id" not in objs[0]["status"] and "ok" not in objs[0]["status"]
            telemetry = [o for o in objs if o.get("event") == "telemetry"]
            assert telemetry == [{"event": "telemetry", "data": TEL}] * 3
            assert objs[-1]["event"] == "telemetry"  # --count: three telemetry events
            assert state in objs  # the other events as they came
    finally:
        stop.set()
        t.join()


def test_status_and_watch_show_a_return_to_launch_and_its_cause() -> None:
    """A return is a one-point mission to the launch point: the views say it is one, and
    whether a failsafe ordered it (telemetry ``extra.returning``), not "waypoint 1/1"."""
    tel = {**TEL, "waypoint_index": 0, "waypoint_count": 1, "state": "TURN_RIGHT"}
    plain = render_status({"telemetry": tel})
    assert "waypoint   1/1" in plain and "RETURN" not in plain and "failsafe" not in plain
    home = {**tel, "extra": {"returning": "return"}}
    for screen in (render_status({"telemetry": home}), render_watch(home)):
        assert "RUNNING / TURN_RIGHT  RETURN TO LAUNCH (the operator's command)" in screen
        assert "waypoint   launch point  distance 12.3 m" in screen and "1/1" not in screen
        assert "failsafe" not in screen
    why = "operator link lost"
    fs = {**tel, "extra": {"returning": f"failsafe: {why}", "failsafe": why}}
    screen = render_status({"telemetry": fs})
    assert f"RETURN TO LAUNCH (failsafe: {why})" in screen, screen
    assert screen.count("failsafe") == 1  # said once
    paused = {**tel, "mode": "PAUSED", "extra": {"failsafe": "stuck for 5 s"}}
    screen = render_watch(paused)
    assert "failsafe   stuck for 5 s" in screen and "RETURN" not in screen, screen
