"""`x6wd client` findings of the outside audit of the live daemon (after the TLS stop,
tests/test_tls_stop.py): bad numbers for `drive` were sent and refused by the robot (exit 1)
instead of being found as bad input (exit 2); a clean shutdown of the daemon was reported as
"closed the connection (if the daemon uses TLS, add --tls)"; `status` said "declination
config" without the value. The client as a subprocess against a real server, and the whole
daemon (``sim://`` devices)."""

from __future__ import annotations

import dataclasses
import json
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.conftest import self_signed_cert
from tests.test_daemon import Running, hil_config, wait_for
from tests.test_lockout import lt
from tests.test_server import LoopThread, Raw, RecordingBackend, start_server
from x6wd.app.daemon import Daemon
from x6wd.app.server import ControlServer, server_ssl_context

__all__ = ["lt"]  # the fixture, shared with test_lockout

pytestmark = pytest.mark.integration


def x6wd_client(port: int, *args: str) -> list[str]:
    return [sys.executable, "-m", "x6wd", "client", "--port", str(port), *args]


# -- 2: bad numbers are bad input, found before anything is sent --------------------------------
@pytest.mark.parametrize(
    ("left", "right", "seconds", "named"),
    [
        ("nan", "nan", "1", "argument left"),
        ("10", "10", "0", "argument seconds"),
        ("inf", "0", "1", "argument left"),
        ("1e309", "0", "1", "argument left"),  # a float past the largest: inf
        ("0", "inf", "1", "argument right"),
        ("10", "10", "-1", "argument seconds"),
        ("10", "10", "nan", "argument seconds"),
        ("10", "10", "inf", "argument seconds"),
    ],
)
def test_a_drive_with_a_non_finite_number_or_no_duration_is_bad_input(
    lt: LoopThread, left: str, right: str, seconds: str, named: str
) -> None:
    backend = RecordingBackend()
    srv = start_server(lt, backend)
    try:
        r = subprocess.run(
            x6wd_client(srv.port, "drive", left, right, seconds),
            capture_output=True, text=True, timeout=30,
        )  # fmt: skip
        assert r.returncode == 2, r.stderr
        assert named in r.stderr and "refused" not in r.stderr, r.stderr
        # never sent: the robot saw no request at all
        assert backend.calls == [] and lt.call(lambda: srv.requests_total) == 0
    finally:
        lt.run(srv.close())


def test_a_drive_with_finite_numbers_still_goes_to_the_robot(lt: LoopThread) -> None:
    backend = RecordingBackend()
    srv = start_server(lt, backend)
    try:
        r = subprocess.run(
            x6wd_client(srv.port, "drive", "-20", "20", "0.3"),
            capture_output=True, text=True, timeout=30,
        )  # fmt: skip
        assert r.returncode == 0 and "drive: ok" in r.stdout, r.stderr
        assert backend.calls == [("drive", (-20.0, 20.0, 0.3))]
    finally:
        lt.run(srv.close())


# -- 3: the daemon's shutdown is said as such ----------------------------------------------------
def test_the_server_tells_every_connection_it_shuts_down(lt: LoopThread, tmp_path: Path) -> None:
    """The notice (id null, code closed, reason shutdown) after the replies still queued;
    plain TCP and TLS; `watch` and `drive` say "the robot's daemon shut down", exit 3, and
    no TLS hint."""
    cert, key = self_signed_cert(tmp_path)
    for tls in (False, True):
        backend = RecordingBackend()
        ctx = server_ssl_context(str(cert), str(key)) if tls else None
        srv = start_server(lt, backend, ssl_context=ctx)
        tls_args = ["--cafile", str(cert)] if tls else []
        raw = None if tls else Raw(srv.port)
        watch = subprocess.Popen(
            x6wd_client(srv.port, *tls_args, "watch", "--json"),
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        )  # fmt: skip
        drive = subprocess.Popen(
            x6wd_client(srv.port, *tls_args, "drive", "30", "30", "10"),
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        )  # fmt: skip
        try:
            assert watch.stdout is not None
            assert "status" in json.loads(watch.stdout.readline())  # it watches
            wait_for(lambda b=backend: bool(b.calls), 20, "the drive")
            if raw is not None:
                assert raw.ask({"id": 1, "cmd": "hello"})["ok"]
            lt.run(srv.close())
            if raw is not None:  # the notice, exactly
                assert raw.line() == {
                    "id": None, "ok": False,
                    "error": {"code": "closed", "message": "x6wd is shutting down",
                              "reason": "shutdown"},
                }  # fmt: skip
                assert raw.f.readline() == b""  # then the end of the stream
            for proc in (watch, drive):
                _, err = proc.communicate(timeout=10)
                assert proc.returncode == 3, (tls, err)
                assert "the robot's daemon shut down" in err and "--tls" not in err, (tls, err)
        finally:
            for proc in (watch, drive):
                proc.kill()
            if raw is not None:
                raw.close()


# -- 3 and 4 on the daemon: the shutdown notice, and the configured declination ------------------
@pytest.fixture
def robot(tmp_path: Path) -> Iterator[Running]:
    cfg = hil_config(tmp_path)
    cfg = dataclasses.replace(cfg, compass=dataclasses.replace(cfg.compass, declination_deg=-0.5))
    r = Running(Daemon(cfg))
    try:
        yield r
    finally:
        r.stop()
        if r.daemon.devices is not None:
            r.daemon.devices.close()


def test_status_shows_the_configured_declination_in_degrees(robot: Running) -> None:
    r = subprocess.run(
        x6wd_client(robot.port, "status", "--json"), capture_output=True, text=True, timeout=30
    )
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout)["declination"] == {"source": "config", "deg": -0.5}
    r = subprocess.run(
        x6wd_client(robot.port, "status"), capture_output=True, text=True, timeout=30
    )
    assert r.returncode == 0, r.stderr
    assert "declination -0.50 deg (config)" in r.stdout, r.stdout


def test_watch_and_drive_say_the_daemon_shut_down(robot: Running) -> None:
    watch = subprocess.Popen(
        x6wd_client(robot.port, "watch", "--json"),
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    drive = subprocess.Popen(
        x6wd_client(robot.port, "drive", "30", "30", "5"),
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )  # fmt: skip
    try:
        assert watch.stdout is not None
        assert "status" in json.loads(watch.stdout.readline())
        wait_for(
            lambda: (t := robot.daemon.last_telemetry) is not None and str(t.mode) == "MANUAL",
            20, "the drive",
        )  # fmt: skip
        time.sleep(0.2)
        assert robot.stop() == 0  # a clean shutdown (as on SIGTERM)
        for proc in (watch, drive):
            _, err = proc.communicate(timeout=10)
            assert proc.returncode == 3, err
            assert "the robot's daemon shut down" in err, err
            assert "the motors are stopped" in err and "--tls" not in err, err
    finally:
        for proc in (watch, drive):
            proc.kill()


def test_the_tls_hint_is_kept_for_a_plain_client_on_a_tls_port(tmp_path: Path) -> None:
    """The hint is for what it was meant for: a connection closed before any reply."""
    cert, key = self_signed_cert(tmp_path)
    lt = LoopThread()
    try:
        srv = start_server(
            lt, RecordingBackend(), ssl_context=server_ssl_context(str(cert), str(key))
        )
        assert isinstance(srv, ControlServer)
        r = subprocess.run(
            x6wd_client(srv.port, "status"), capture_output=True, text=True, timeout=30
        )
        assert r.returncode == 3 and "add --tls" in r.stderr, r.stderr
        lt.run(srv.close())
    finally:
        lt.close()
