"""Listening beyond loopback needs TLS (an outside security audit): with a token but no TLS the
control port and the console bound 0.0.0.0 or a LAN address without a word, so the ``auth``
line with the token and every drive travelled in clear text. Now the real ``x6wd run`` stops
with exit 2 naming ``server.tls_cert`` (or ``console.bind``) and the opt-out
``[server] allow_plaintext``; with the opt-out it starts, warns once and says so in
``status``. Loopback binds are unchanged."""

from __future__ import annotations

import errno
import json
import queue
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import pytest

from tests.conftest import ROOT
from tests.test_startup import assert_config_error, run_x6wd, write_config
from x6wd.app.server import is_loopback
from x6wd.core.config import (
    ConsoleConfig,
    ServerConfig,
    check_plaintext,
    is_loopback_bind,
    loads,
    plaintext_binds,
)
from x6wd.core.errors import ConfigError


def token_file(tmp_path: Path) -> Path:
    p = tmp_path / "token"
    p.write_text("0123456789abcdef\n")
    p.chmod(0o600)
    return p


def free_port(host: str) -> int:
    """A port in 19500-19599 nobody listens on at ``host``."""
    for port in range(19500, 19600):
        with socket.socket() as s:
            try:
                s.bind((host, port))
            except OSError as exc:
                if exc.errno == errno.EADDRINUSE:
                    continue
                raise
            return port
    pytest.skip("no free port in 19500-19599")


# -- the real start-up path: refused ----------------------------------------------------------
@pytest.mark.integration
@pytest.mark.parametrize("bind", ["0.0.0.0", "192.168.1.50"])
def test_a_control_port_beyond_loopback_without_tls_is_exit_2_naming_tls_cert(
    tmp_path: Path, bind: str
) -> None:
    config = write_config(tmp_path, server={"bind": bind, "token_file": str(token_file(tmp_path))})
    line = assert_config_error(
        run_x6wd(config),
        "server.tls_cert",
        f"server.bind = {bind!r}",
        "is not loopback",
        "clear text",
        "server.allow_plaintext = true",
    )
    assert "token_file" not in line  # the token is there: only TLS is missing
    assert not (tmp_path / "rec").exists()


@pytest.mark.integration
def test_without_a_token_either_the_message_names_both(tmp_path: Path) -> None:
    config = write_config(tmp_path, server={"bind": "0.0.0.0"})
    assert_config_error(run_x6wd(config), "server.tls_cert", "server.allow_plaintext", "token_file")


@pytest.mark.integration
def test_a_console_beyond_loopback_without_tls_is_exit_2_naming_console_bind(
    tmp_path: Path,
) -> None:
    config = write_config(
        tmp_path,
        server={"token_file": str(token_file(tmp_path))},
        console={"enabled": True, "bind": "0.0.0.0", "port": 0},
    )
    assert_config_error(
        run_x6wd(config),
        "console.bind",
        "console.bind: '0.0.0.0' (all interfaces) is not loopback",
        "server's TLS",
        "server.allow_plaintext = true",
    )


@pytest.mark.integration
@pytest.mark.parametrize("value", ["true", 1])
def test_allow_plaintext_must_be_a_bool(tmp_path: Path, value: Any) -> None:
    config = write_config(tmp_path, server={"allow_plaintext": value})
    assert_config_error(
        run_x6wd(config), f"{config}: server.allow_plaintext", "expected true or false"
    )


# -- the real start-up path: starts -----------------------------------------------------------
def start_and_status(config: Path, port: int) -> tuple[Running, dict[str, Any]]:
    """Start ``x6wd run`` on ``config``, read ``status`` from its control ``port``, stop it
    (SIGTERM, exit 0 asserted); the finished run (its stderr lines) and the status."""
    run = Running(config)
    try:
        run.wait_ready()
        st = status(port)
        code = run.stop()
    finally:
        run.kill()
    assert code == 0, run.lines
    return run, st


class Running:
    """``x6wd run --config`` in a subprocess; its stderr lines are collected as they come."""

    def __init__(self, config: Path) -> None:
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "x6wd", "run", "--config", str(config)],
            stderr=subprocess.PIPE,
            text=True,
            cwd=ROOT,
        )
        self.lines: list[str] = []
        self._q: queue.Queue[str | None] = queue.Queue()
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        assert self.proc.stderr is not None
        for line in self.proc.stderr:
            self._q.put(line.rstrip("\n"))
        self._q.put(None)

    def wait_ready(self, timeout_s: float = 60.0) -> None:
        deadline = time.monotonic() + timeout_s
        while True:
            line = self._q.get(timeout=max(0.01, deadline - time.monotonic()))
            assert line is not None, "exited before ready:\n" + "\n".join(self.lines)
            self.lines.append(line)
            if line.endswith(" ready"):
                return

    def stop(self) -> int:
        """SIGTERM; the exit code. The rest of stderr joins ``lines``."""
        self.proc.send_signal(signal.SIGTERM)
        code = self.proc.wait(30)
        while (line := self._q.get(timeout=10)) is not None:
            self.lines.append(line)
        return code

    def kill(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait()


def status(port: int) -> dict[str, Any]:
    """``status`` on the control port, asked over loopback (open without ``auth``)."""
    with socket.create_connection(("127.0.0.1", port), timeout=10) as s:
        s.sendall(b'{"id":1,"cmd":"status"}\n')
        buf = b""
        while not buf.endswith(b"\n"):
            chunk = s.recv(65536)
            assert chunk, buf
            buf += chunk
    reply = json.loads(buf)
    assert reply["ok"], reply
    return dict(reply)


@pytest.mark.integration
def test_allow_plaintext_starts_beyond_loopback_warns_once_and_status_says_so(
    tmp_path: Path,
) -> None:
    port = free_port("0.0.0.0")
    config = write_config(
        tmp_path,
        server={
            "bind": "0.0.0.0",
            "port": port,
            "token_file": str(token_file(tmp_path)),
            "allow_plaintext": True,
        },
    )
    run, st = start_and_status(config, port)
    assert st["plaintext_beyond_loopback"] == ["server.bind"]
    warnings = [line for line in run.lines if line.startswith("WARNING") and "TLS" in line]
    assert len(warnings) == 1, run.lines
    assert "server.bind = '0.0.0.0'" in warnings[0] and "clear text" in warnings[0]


@pytest.mark.integration
def test_a_loopback_bind_without_tls_or_token_starts_as_before(tmp_path: Path) -> None:
    port = free_port("127.0.0.1")
    config = write_config(
        tmp_path,
        server={"bind": "127.0.0.1", "port": port},
        console={"enabled": True, "bind": "127.0.0.1", "port": 0},
    )
    run, st = start_and_status(config, port)
    assert st["plaintext_beyond_loopback"] == []
    assert not [line for line in run.lines if line.startswith("WARNING") and "TLS" in line]


# -- the rule itself --------------------------------------------------------------------------
HOSTS = [
    "127.0.0.1", "127.5.6.7", "::1", "localhost", "0.0.0.0", "::", "192.168.1.50",
    "robot.local", "LOCALHOST", "", "10.0.0.1",
]  # fmt: skip


@pytest.mark.parametrize("host", HOSTS)
def test_loopback_is_what_the_control_server_calls_loopback(host: str) -> None:
    # the TLS rule and the token rule (x6wd.app.server) agree on what loopback is
    assert is_loopback_bind(host) == is_loopback(host)


@pytest.mark.parametrize(
    ("bind", "said"),
    [
        ("", "server.bind = '' (all interfaces) is not loopback"),
        ("0.0.0.0", "server.bind = '0.0.0.0' (all interfaces) is not loopback"),
        ("::", "server.bind = '::' (all interfaces) is not loopback"),
        ("10.0.0.1", "server.bind = '10.0.0.1' is not loopback"),
        ("127.1", "server.bind = '127.1' is not a literal loopback address"),
        ("vm", "server.bind = 'vm' is not a literal loopback address"),
    ],
)
def test_the_message_names_the_bind_as_it_is(bind: str, said: str) -> None:
    # an outside audit: bind = "" was "server.bind () is not loopback", and names that are
    # loopback (127.1, a name /etc/hosts maps to 127.0.0.1) were called not loopback
    with pytest.raises(ConfigError) as err:
        check_plaintext(config_with({"bind": bind, "token_file": "/t"}))
    msg = str(err.value)
    assert msg.startswith("server.tls_cert: required when " + said), msg
    literal = "x6wd checks only literal loopback addresses and 'localhost'; use 127.0.0.1"
    assert (literal in msg) == (bind in ("127.1", "vm")), msg
    with pytest.raises(ConfigError) as err:
        check_plaintext(config_with({"token_file": "/t"}, {"enabled": True, "bind": bind}))
    assert str(err.value).startswith("console.bind: " + said.removeprefix("server.bind = "))


def test_localhost_in_any_case_is_loopback() -> None:
    for bind in ("localhost", "LOCALHOST", "LocalHost"):
        cfg = config_with({"bind": bind}, {"enabled": True, "bind": bind})
        assert plaintext_binds(cfg) == ()
        check_plaintext(cfg)


def config_with(server: dict[str, Any], console: dict[str, Any] | None = None) -> Any:
    text = "[server]\n" + "".join(f"{k} = {json.dumps(v)}\n" for k, v in server.items())
    if console is not None:
        text += "[console]\n" + "".join(f"{k} = {json.dumps(v)}\n" for k, v in console.items())
    return loads(text)


def test_who_must_have_tls() -> None:
    tls = {"tls_cert": "/c.pem", "tls_key": "/k.pem", "token_file": "/t"}
    # loopback: unchanged, with or without TLS, console included
    for bind in ("127.0.0.1", "::1", "localhost"):
        cfg = config_with({"bind": bind}, {"enabled": True, "bind": bind})
        assert plaintext_binds(cfg) == ()
        check_plaintext(cfg)
    # with TLS: both may listen anywhere
    cfg = config_with({"bind": "0.0.0.0", **tls}, {"enabled": True, "bind": "0.0.0.0"})
    assert plaintext_binds(cfg) == ()
    check_plaintext(cfg)
    # a disabled server or console listens nowhere
    assert plaintext_binds(config_with({"bind": "0.0.0.0", "enabled": False})) == ()
    assert plaintext_binds(config_with({}, {"enabled": False, "bind": "0.0.0.0"})) == ()
    # one of the two TLS files is not TLS: the missing one is named
    cfg = config_with({"bind": "0.0.0.0", "tls_cert": "/c.pem", "token_file": "/t"})
    with pytest.raises(ConfigError, match=r"^server\.tls_key: required"):
        check_plaintext(cfg)
    # both beyond loopback: the server is named first; with the opt-out both are listed
    both = ({"bind": "0.0.0.0", "token_file": "/t"}, {"enabled": True, "bind": "10.0.0.1"})
    with pytest.raises(ConfigError, match=r"^server\.tls_cert: required"):
        check_plaintext(config_with(*both))
    cfg = config_with({**both[0], "allow_plaintext": True}, both[1])
    check_plaintext(cfg)
    assert plaintext_binds(cfg) == ("server.bind", "console.bind")


def test_the_defaults_are_loopback_and_no_plaintext() -> None:
    assert ServerConfig().allow_plaintext is False
    assert is_loopback_bind(ServerConfig().bind) and is_loopback_bind(ConsoleConfig().bind)
    cfg = loads((ROOT / "config" / "x6wd.toml").read_text())
    assert cfg.server.allow_plaintext is False and plaintext_binds(cfg) == ()
