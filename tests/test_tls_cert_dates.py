"""The TLS certificate's dates and the key file's mode, checked by the daemon; a ``stop`` that
still reaches a robot whose certificate has expired.

An outside audit found a robot started with an expired (or not yet valid) ``[server]
tls_cert`` without a word, after which every verified client failed, `x6wd client --tls
--cafile cert.pem stop` too ("certificate has expired", exit 3): docs/install.md makes
825-day certificates, so a long-lived robot meets this on a schedule. It also found a
world-readable ``tls_key`` accepted where a token file so is refused.

Certificates with chosen dates are made by the real openssl (``openssl ca -selfsign
-startdate/-enddate``: Debian's OpenSSL 3.0 has no ``req -not_before``); the daemon runs as
a real process (start-up refusals) or on its thread with ``sim://`` devices, and the client
as a subprocess over real TLS sockets on 127.0.0.1.
"""

from __future__ import annotations

import calendar
import contextlib
import dataclasses
import json
import logging
import socket
import ssl
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import pytest

from tests.conftest import require_program, self_signed_cert
from tests.test_console import daemon_with, vehicle_pct
from tests.test_daemon import hil_config, wait_for
from tests.test_startup import assert_config_error, run_x6wd, write_config
from x6wd.app.client import RemoteClient
from x6wd.core.config import SafetyConfig, ServerConfig
from x6wd.core.errors import ConfigError

TOKEN = "cert-dates-token-0123456789"
CA_CONFIG = """\
[ca]
default_ca = selfsign
[selfsign]
database = index.txt
serial = serial
new_certs_dir = .
default_md = sha256
policy = anything
x509_extensions = robot
unique_subject = no
[anything]
commonName = supplied
[robot]
basicConstraints = critical,CA:TRUE
subjectAltName = DNS:localhost,IP:127.0.0.1
"""


def openssl_time(t_s: float) -> str:
    """Unix time ``t_s`` (s) as openssl ca's -startdate/-enddate (YYYYMMDDHHMMSSZ)."""
    return time.strftime("%Y%m%d%H%M%SZ", time.gmtime(t_s))


def dated_cert(directory: Path, not_before_s: float, not_after_s: float) -> tuple[Path, Path]:
    """A self-signed certificate for localhost/127.0.0.1 valid from ``not_before_s`` to
    ``not_after_s`` (Unix time, s, whole seconds), and its key (mode 600)."""
    openssl = require_program("openssl")
    work = directory / "ca"
    work.mkdir()
    (work / "ca.cnf").write_text(CA_CONFIG)
    (work / "index.txt").write_text("")
    (work / "serial").write_text("01\n")
    cert, key = directory / "cert.pem", directory / "key.pem"
    subprocess.run(
        [openssl, "req", "-new", "-newkey", "rsa:2048", "-nodes", "-subj", "/CN=localhost",
         "-keyout", str(key), "-out", "req.csr"],
        check=True, capture_output=True, cwd=work,
    )  # fmt: skip
    subprocess.run(
        [openssl, "ca", "-batch", "-config", "ca.cnf", "-selfsign", "-keyfile", str(key),
         "-in", "req.csr", "-out", str(cert), "-notext",
         "-startdate", openssl_time(not_before_s), "-enddate", openssl_time(not_after_s)],
        check=True, capture_output=True, cwd=work,
    )  # fmt: skip
    key.chmod(0o600)
    return cert, key


def utc_text(t_s: float) -> str:
    """As status and the messages give a date: ISO 8601 UTC, whole seconds."""
    return time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime(t_s))


def token_file(tmp_path: Path, name: str = "token", text: str = TOKEN) -> Path:
    path = tmp_path / name
    path.write_text(text + "\n")
    path.chmod(0o600)
    return path


# -- start-up: a certificate no verified client accepts, a key others may read ---------------
@pytest.mark.integration
@pytest.mark.parametrize(
    ("valid", "reason"),
    [
        (("2024-01-01", "2025-01-01"), "expired on 2025-01-01T00:00:00Z"),
        (("2098-01-01", "2099-01-01"), "is not valid before 2098-01-01T00:00:00Z"),
    ],
)
def test_a_certificate_out_of_its_dates_stops_start_up_naming_the_key_and_dates(
    tmp_path: Path, valid: tuple[str, str], reason: str
) -> None:
    start_s, end_s = (calendar.timegm(time.strptime(d, "%Y-%m-%d")) for d in valid)
    cert, key = dated_cert(tmp_path, start_s, end_s)
    proc = run_x6wd(write_config(tmp_path, server={"tls_cert": str(cert), "tls_key": str(key)}))
    assert_config_error(proc, "server.tls_cert", str(cert), reason, f"{valid[0]}T00:00:00Z")


@pytest.mark.integration
@pytest.mark.parametrize("mode", [0o644, 0o640], ids=["0644", "0640"])
def test_a_tls_key_readable_by_others_stops_start_up_as_a_token_file_does(
    tmp_path: Path, mode: int
) -> None:
    cert, key = self_signed_cert(tmp_path)
    key.chmod(mode)
    proc = run_x6wd(write_config(tmp_path, server={"tls_cert": str(cert), "tls_key": str(key)}))
    assert_config_error(proc, "server.tls_key", str(key), f"mode {mode:04o}", "chmod 600")


# -- running: expiring, expired; the operator's stop gets through ------------------------------
@pytest.mark.integration
def test_a_certificate_expiring_while_the_daemon_runs_is_warned_logged_and_a_stop_gets_through(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    # The steps before the expiry (the daemon's start-up, a status, a client subprocess's
    # status) took 1.5 s here, 5.9 s beside 3 busy loops (8 s of life left 2.1 s): 30 s is
    # five times that for a slower CI host; the test then waits the rest of it out.
    life_s = 30.0
    now_s = float(int(time.time()))
    cert, key = dated_cert(tmp_path, now_s - 3600.0, now_s + life_s)
    not_after_s = now_s + life_s
    not_after = utc_text(not_after_s)
    token, wrong = token_file(tmp_path), token_file(tmp_path, "wrong", "not-the-robots-token")
    cfg = hil_config(
        tmp_path,
        server=ServerConfig(port=0, token_file=str(token), tls_cert=str(cert), tls_key=str(key)),
        safety=SafetyConfig(geofence_radius_m=100.0, manual_max_s=30.0),
    )
    verified = ssl.create_default_context(cafile=str(cert))

    def client(*args: str) -> subprocess.CompletedProcess[str]:
        return subprocess.run(
            [sys.executable, "-m", "x6wd", "client", "--port", str(r.port), "--cafile",
             str(cert), *args],
            capture_output=True, text=True, timeout=30,
        )  # fmt: skip

    def logged(level: int, text: str) -> bool:
        return any(rec.levelno == level and text in rec.getMessage() for rec in caplog.records)

    def still_valid(step: str) -> None:
        """After a step that needs the certificate valid, before its assertions: a host too
        slow for ``life_s`` fails here, saying so, instead of in a confusing assertion."""
        late_s = time.time() - not_after_s
        if late_s >= 0.0:
            pytest.fail(
                f"the certificate expired {late_s:.1f} s before the end of {step} "
                f"({life_s:g} s after it was made): the host was too slow for this test's "
                "life_s, not a fault of the daemon"
            )

    with caplog.at_level(logging.INFO, logger="x6wd.app.server"), daemon_with(cfg) as r:
        still_valid("the daemon's start-up")
        srv = r.daemon.server
        assert srv is not None
        srv.cert_check_s = 0.1  # (an hour in the daemon) the sweeper looks again this often
        # fewer than 30 days left: a WARNING at start and in status, the dates in status
        assert logged(logging.WARNING, f"server.tls_cert: {cert} expires on {not_after}")
        driver = RemoteClient("127.0.0.1", r.port, token=TOKEN, ssl_context=verified)
        with driver:
            tls = driver.request("status")["server"]["tls"]
            still_valid("the first status (a verified handshake)")
            assert tls["state"] == "expiring" and tls["not_after"] == not_after, tls
            assert tls["warning"].startswith(f"server.tls_cert: {cert} expires on {not_after}")
            shown = client("--token-file", str(token), "status")
            still_valid("`x6wd client status` (a verified handshake)")
            assert shown.returncode == 0, shown.stderr
            assert f"tls cert   WARNING server.tls_cert: {cert} expires on" in shown.stdout
            # it expires while the daemon runs: an ERROR in the log, the state in status
            wait_for(
                lambda: logged(logging.ERROR, f"{cert} expired on {not_after}"),
                life_s + 10.0, "the running daemon's log says the certificate expired",
            )  # fmt: skip
            tls = driver.request("status")["server"]["tls"]
            assert tls["state"] == "expired" and "expired on" in tls["warning"], tls
            # the operator drives on the connection opened before; a new verified one fails
            assert driver.request("drive", left=40, right=40, duration_s=30)["ok"]
            wait_for(lambda: vehicle_pct(r) == (40.0, 40.0), 5.0, "the motors driven")
            refused = client("--token-file", str(token), "status")
            assert refused.returncode == 3 and "certificate has expired" in refused.stderr
            assert "WITHOUT verification" not in refused.stderr  # only a stop goes so
            sent = srv.stops["sent"]
            # `x6wd client stop` retries once without verification, loudly, without the token
            stop = client("--token-file", str(wrong), "stop")
            # acknowledged, but not by a verified robot: never "stop: ok" nor exit 0
            assert stop.returncode == 4, stop.stderr
            assert stop.stdout == "stop: sent, reply NOT verified (certificate has expired)\n"
            assert "COULD NOT BE VERIFIED (certificate has expired)" in stop.stderr
            assert "WITHOUT verification" in stop.stderr
            wait_for(lambda: vehicle_pct(r) == (0.0, 0.0), 5.0, "the motors stopped")
            assert srv.stops["sent"] == sent + 1
            assert "refused the token" not in stop.stderr  # the token never went out
            assert srv.auth_failed_total == 0


def test_dates_of_the_certificate_are_in_status_only_with_tls(tmp_path: Path) -> None:
    """A certificate with years left: state ok, no warning; no TLS: no ``tls`` entry."""
    from tests.test_server import RecordingBackend
    from x6wd.app.server import ControlServer, server_ssl_context

    now_s = float(int(time.time()))
    cert, key = dated_cert(tmp_path, now_s - 86400.0, now_s + 400 * 86400.0)
    cfg = ServerConfig(port=0, tls_cert=str(cert), tls_key=str(key))
    srv = ControlServer(
        cfg, RecordingBackend(), ssl_context=server_ssl_context(str(cert), str(key))
    )
    tls = srv.server_stats()["tls"]
    assert tls["state"] == "ok" and tls["warning"] is None and 399 < tls["days_left"] <= 400
    assert tls["not_after"] == utc_text(now_s + 400 * 86400.0)
    plain = ControlServer(dataclasses.replace(cfg, tls_cert="", tls_key=""), RecordingBackend())
    assert "tls" not in plain.server_stats()


def test_a_system_clock_before_this_release_is_blamed_instead_of_the_certificate(
    tmp_path: Path,
) -> None:
    """A Raspberry Pi without a clock boots at 1970: its certificate is "not yet valid"
    until a time server sets the clock. The daemon starts (the state is ``clock_unset``,
    a WARNING) instead of refusing a certificate that is fine."""
    from x6wd.app.server import cert_dates, cert_verdict, server_ssl_context

    now_s = float(int(time.time()))
    cert, key = dated_cert(tmp_path, now_s - 86400.0, now_s + 400 * 86400.0)
    server_ssl_context(str(cert), str(key), now_s=3600.0)  # 1970-01-01T01:00:00Z: no error
    dates = cert_dates(str(cert))
    assert dates is not None
    state, message = cert_verdict(dates, 3600.0, str(cert))
    assert state == "clock_unset" and "set the clock" in message, message
    with pytest.raises(ConfigError, match=r"^server\.tls_cert: .* is not valid before"):
        server_ssl_context(str(cert), str(key), now_s=dates.not_before_s - 86400.0)


def test_without_cpythons_private_decoder_the_dates_are_skipped_not_fatal(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    """``ssl._ssl._test_decode_cert`` is CPython's private API: where it is missing the check
    is skipped (a debug line), start-up goes on, and status says ``unknown``."""
    from tests.test_server import RecordingBackend
    from x6wd.app.server import ControlServer, server_ssl_context

    cert, key = dated_cert(tmp_path, 1704067200.0, 1735689600.0)  # 2024 only: expired
    monkeypatch.delattr(ssl._ssl, "_test_decode_cert")  # type: ignore[attr-defined]
    with caplog.at_level(logging.DEBUG, logger="x6wd.app.server"):
        ctx = server_ssl_context(str(cert), str(key))
    assert any("_test_decode_cert absent" in r.getMessage() for r in caplog.records)
    cfg = ServerConfig(port=0, tls_cert=str(cert), tls_key=str(key))
    srv = ControlServer(cfg, RecordingBackend(), ssl_context=ctx)
    assert srv.server_stats()["tls"] == {"cert": str(cert), "state": "unknown", "warning": None}
    assert srv.check_cert() == "none"


# -- an impostor acknowledges the unverified stop: never reported as a confirmed one -----------
@contextlib.contextmanager
def impostor(directory: Path) -> Any:
    """A TLS server on 127.0.0.1 with a certificate of its own that answers every line with
    ``ok`` (a forged acknowledgement); yields its port and the lines it received."""
    directory.mkdir()
    cert, key = self_signed_cert(directory)
    ctx = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
    ctx.load_cert_chain(cert, key)
    listener = socket.create_server(("127.0.0.1", 0))
    received: list[dict[str, Any]] = []

    def serve() -> None:
        while True:
            try:
                raw, _ = listener.accept()
            except OSError:  # closed: the test is over
                return
            with contextlib.suppress(OSError), ctx.wrap_socket(raw, server_side=True) as s:
                for line in s.makefile("rb"):
                    req = json.loads(line)
                    received.append(req)
                    s.sendall(json.dumps({"id": req.get("id"), "ok": True}).encode() + b"\n")

    thread = threading.Thread(target=serve, daemon=True)
    thread.start()
    try:
        yield listener.getsockname()[1], received
    finally:
        listener.close()
        thread.join(5)


@pytest.mark.integration
def test_a_stop_acknowledged_without_verification_is_not_reported_as_a_confirmed_stop(
    tmp_path: Path,
) -> None:
    """The review of b7485e0: with the robot's certificate in --cafile, an impostor on its
    address got `x6wd client stop` to print "stop: ok" and exit 0 (``--json``: ``{}``),
    what a script or an e-stop wrapper takes for a confirmed stop. Now: exit 4, "stop:
    sent, reply NOT verified (REASON)", ``"verified": false``; the stop went out once, no
    token."""
    (tmp_path / "robot").mkdir()
    trusted, _ = self_signed_cert(tmp_path / "robot")
    token = token_file(tmp_path)
    with impostor(tmp_path / "impostor") as (port, received):
        for extra, expect_json in (((), False), (("--json",), True)):
            proc = subprocess.run(
                [sys.executable, "-m", "x6wd", "client", "--port", str(port), "--cafile",
                 str(trusted), "--token-file", str(token), *extra, "stop"],
                capture_output=True, text=True, timeout=30,
            )  # fmt: skip
            assert proc.returncode == 4, (proc.stdout, proc.stderr)
            assert "WITHOUT verification" in proc.stderr
            if expect_json:
                assert json.loads(proc.stdout) == {"verified": False}, proc.stdout
            else:
                assert proc.stdout.startswith("stop: sent, reply NOT verified ("), proc.stdout
                assert "stop: ok" not in proc.stdout
        assert [r["cmd"] for r in received] == ["stop", "stop"]
        assert all("token" not in r for r in received)


# -- a clock not set yet: what the verdict may claim, and the re-check once it is set ----------
def day(text: str) -> float:
    """Unix time (s) of ``YYYY-MM-DD`` 00:00 UTC."""
    return float(calendar.timegm(time.strptime(text, "%Y-%m-%d")))


def test_a_clock_before_this_release_promises_nothing_of_a_certificate_starting_after_it() -> None:
    """The review of b7485e0: at a 1970 clock a certificate valid only from 2027-06-01 was
    ``clock_unset`` with "clients with a right clock accept the certificate", which is false
    (not valid yet by a right clock either). Only one valid on this release's date may be
    promised; one that starts after it cannot be judged until the clock is set; one that
    expired before it is expired whatever the clock says."""
    from x6wd.app.server import CertDates, _clock_floor_s, cert_verdict

    floor_s, at_1970_s = _clock_floor_s(), 3600.0
    state, message = cert_verdict(CertDates(day("2027-06-01"), day("2029-09-01")), at_1970_s, "c")
    assert state == "clock_unset" and "set the clock" in message, message
    assert "cannot be judged until then" in message and "accept" not in message, message
    valid_then = CertDates(floor_s - 30 * 86400.0, floor_s + 700 * 86400.0)
    state, message = cert_verdict(valid_then, at_1970_s, "c")
    assert state == "clock_unset" and "set the clock" in message, message
    assert f"accept it until {utc_text(valid_then.not_after_s)}" in message, message
    state, message = cert_verdict(CertDates(day("2024-01-01"), day("2025-01-01")), at_1970_s, "c")
    assert state == "expired" and "expired on 2025-01-01T00:00:00Z" in message, message


def test_the_certificate_is_judged_again_as_soon_as_the_wall_clock_is_set(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """A Pi boots at 1970 (``clock_unset``, a WARNING) and NTP sets its clock a minute
    later: the certificate, not valid for another 10 days, must be an ERROR at the next
    sweep, not up to an hour later (the re-check was keyed on the monotonic clock alone).
    The server's wall clock is injected; nothing else is."""
    from tests.test_server import RecordingBackend
    from x6wd.app.server import ControlServer, server_ssl_context

    now_s = float(int(time.time()))
    cert, key = dated_cert(tmp_path, now_s + 10 * 86400.0, now_s + 400 * 86400.0)
    wall_s = [3600.0]  # 1970-01-01T01:00:00Z
    cfg = ServerConfig(port=0, tls_cert=str(cert), tls_key=str(key))
    srv = ControlServer(
        cfg,
        RecordingBackend(),
        ssl_context=server_ssl_context(str(cert), str(key), now_s=wall_s[0]),
        wall_clock=lambda: wall_s[0],
    )

    def logged(level: int) -> list[str]:
        return [r.getMessage() for r in caplog.records if r.levelno == level]

    with caplog.at_level(logging.INFO, logger="x6wd.app.server"):
        assert srv.check_cert() == "clock_unset"
        assert len(logged(logging.WARNING)) == 1
        wall_s[0] += 30.0  # the clock runs on, unset: nothing new
        srv.sweep()
        assert logged(logging.ERROR) == [] and len(logged(logging.WARNING)) == 1
        wall_s[0] = now_s  # NTP sets it
        srv.sweep()
        errors = logged(logging.ERROR)
        assert len(errors) == 1 and f"{cert} is not valid before" in errors[0], errors
        assert srv.server_stats()["tls"]["state"] == "not_yet_valid"
