"""Round 15 review of x6wd's entry: an empty option of a parent parser (``x6wd client --cafile ''
status``) sent the token in clear text (1); an empty item of a list option (``--sim ''``,
``decode ''``) was read as the current folder (2); a write to stdout on a full disk was a
traceback (3)."""

from __future__ import annotations

import errno
import os
import socket
import subprocess
import sys
import threading
from collections.abc import Iterator
from pathlib import Path

import pytest

from x6wd.app import cli, client

ROOT = Path(__file__).resolve().parents[1]
LOG = ROOT / "tests" / "data" / "nmea" / "ublox-8.log"
MISSION = ROOT / "missions" / "default.waypoints"
SCENARIO = ROOT / "config" / "scenarios" / "default.toml"
TOKEN = "round15-secret-token-0123456789"
PORTS = range(21400, 21450)  # this test file's TCP ports


class Listener:
    """A plain TCP listener on 127.0.0.1 that keeps every byte a client sends (and never
    answers): whatever reaches it went out in clear text."""

    def __init__(self) -> None:
        self.sock = socket.socket()
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        for port in PORTS:
            try:
                self.sock.bind(("127.0.0.1", port))
                break
            except OSError:
                continue
        else:
            pytest.skip("no free port in 21400-21449")
        self.port = port
        self.sock.listen(4)
        self.sock.settimeout(0.2)
        self.received = b""
        self.connections = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._serve, daemon=True)
        self._thread.start()

    def _serve(self) -> None:
        while not self._stop.is_set():
            try:
                conn, _ = self.sock.accept()
            except TimeoutError:
                continue
            except OSError:
                return
            self.connections += 1
            conn.settimeout(0.2)
            with conn:
                while not self._stop.is_set():
                    try:
                        data = conn.recv(4096)
                    except TimeoutError:
                        continue
                    except OSError:
                        break
                    if not data:
                        break
                    self.received += data

    def close(self) -> None:
        self._stop.set()
        self._thread.join(5)
        self.sock.close()


@pytest.fixture
def listener() -> Iterator[Listener]:
    server = Listener()
    yield server
    server.close()


@pytest.fixture
def token_file(tmp_path: Path) -> Path:
    path = tmp_path / "tok"
    path.write_text(TOKEN)
    path.chmod(0o600)
    return path


def x6wd(*argv: str, **kwargs) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "x6wd", *argv],
        cwd=ROOT,
        text=True,
        timeout=120,
        stderr=subprocess.PIPE,
        **kwargs,
    )


# --- 1: an empty option of a parent parser ------------------------------------------------


@pytest.mark.parametrize("action", ["status", "stop", "start"])
def test_an_empty_cafile_never_sends_the_token_in_clear_text(
    listener: Listener, token_file: Path, action: str
) -> None:
    run = x6wd(
        "client", "--port", str(listener.port), "--token-file", str(token_file),
        "--cafile", "", "--timeout", "1", action,
        stdout=subprocess.PIPE,
    )  # fmt: skip
    listener.close()
    assert TOKEN.encode() not in listener.received
    assert listener.received == b"" and listener.connections == 0
    assert run.returncode == 2, run.stderr
    assert "--cafile: empty value" in run.stderr
    assert "Traceback" not in run.stderr


def test_an_empty_token_file_is_exit_2_naming_it(listener: Listener) -> None:
    run = x6wd(
        "client", "--port", str(listener.port), "--token-file", "", "--timeout", "1", "status",
        stdout=subprocess.PIPE,
    )  # fmt: skip
    listener.close()
    assert listener.connections == 0
    assert run.returncode == 2, run.stderr
    assert "--token-file: empty value" in run.stderr


@pytest.mark.parametrize(
    "argv",
    [["--host", "", "status"], ["--host", "", "drive", "10", "10", "1"], ["--cafile", "", "log"]],
    ids=["host-status", "host-drive", "cafile-log"],
)
def test_every_parser_on_the_chosen_path_is_checked(argv: list[str], capsys) -> None:
    """`x6wd client`'s own options, below which the action's parser is chosen."""
    assert cli.main(["client", "--port", "21449", *argv]) == 2
    assert f"{argv[0]}: empty value" in capsys.readouterr().err


def _client_args(port: int, *options: str) -> object:
    argv = ["client", "--port", str(port), "--timeout", "1", *options]
    return cli.build_parser(argv).parse_args(argv)


@pytest.mark.parametrize("action", ["status", "stop"])
def test_client_itself_refuses_an_empty_cafile(
    listener: Listener, token_file: Path, action: str, capsys
) -> None:
    """Not only x6wd's entry: client.main given ``cafile=''`` (another caller) does not fall
    back to clear text."""
    args = _client_args(listener.port, "--token-file", str(token_file), "--cafile", "", action)
    assert client.main(args) == client.EXIT_USAGE
    listener.close()
    assert TOKEN.encode() not in listener.received
    assert listener.connections == 0
    assert "--cafile: empty path" in capsys.readouterr().err


def test_client_itself_refuses_an_empty_token_file(listener: Listener, capsys) -> None:
    args = _client_args(listener.port, "--token-file", "", "status")
    assert client.main(args) == client.EXIT_USAGE
    listener.close()
    assert listener.connections == 0
    assert "--token-file: empty path" in capsys.readouterr().err


# --- 2: an empty item of a list option ----------------------------------------------------


@pytest.mark.parametrize(
    ("argv", "name"),
    [
        (["gap", "--real", str(LOG), "--sim", "", "--quiet"], "--sim"),
        (["gap", "--real", str(LOG), "--sim", str(LOG), "", "--quiet"], "--sim"),
        (["calibrate", "gnss", "--drive", "", "--reference", ""], "--drive"),
        (["calibrate", "gnss", "--drive", str(LOG), "--reference", ""], "--reference"),
        (["decode", ""], "FILE"),
        (["decode", str(LOG), ""], "FILE"),
    ],
    ids=[
        "gap-sim",
        "gap-sim-2nd",
        "calibrate-drive",
        "calibrate-reference",
        "decode",
        "decode-2nd",
    ],
)
def test_an_empty_item_of_a_list_is_exit_2_naming_it(
    tmp_path: Path, monkeypatch, capsys, argv: list[str], name: str
) -> None:
    monkeypatch.chdir(tmp_path)
    assert cli.main(argv) == 2
    captured = capsys.readouterr()
    assert f"{name}: empty value" in captured.err
    assert captured.out == ""  # decode wrote nothing of the first file either
    assert list(tmp_path.iterdir()) == []


# --- 3: stdout on a full disk ------------------------------------------------------------


@pytest.mark.parametrize(
    "argv",
    [
        ["decode", str(LOG)],
        ["mission", "show", str(MISSION)],
        ["replay", "--speed", "0", str(LOG)],
        ["sim", str(SCENARIO), "--out", "OUT"],
    ],
    ids=["decode", "mission-show", "replay", "sim"],
)
def test_stdout_on_a_full_disk_is_one_line_and_exit_2(tmp_path: Path, argv: list[str]) -> None:
    argv = [a if a != "OUT" else str(tmp_path / "sim") for a in argv]
    with open("/dev/full", "w") as full:
        run = x6wd(*argv, stdout=full)
    assert "Traceback" not in run.stderr, run.stderr
    assert "x6wd: writing output: No space left on device\n" in run.stderr
    assert "Exception ignored" not in run.stderr  # the exit flush does not fail once more
    assert run.returncode == 2


def test_a_short_output_on_a_full_disk_fails_before_the_exit_flush() -> None:
    """`x6wd --version`-size outputs stay in the buffer until exit: the entry flushes them."""
    with open("/dev/full", "w") as full:
        run = x6wd("mission", "show", str(MISSION), stdout=full)
    assert run.returncode == 2 and run.stderr.count("writing output") == 1


def test_stderr_on_a_full_disk_is_exit_2() -> None:
    with open("/dev/full", "w") as full:
        run = subprocess.run(
            [sys.executable, "-m", "x6wd", "decode", str(LOG)],
            cwd=ROOT,
            stdout=subprocess.DEVNULL,
            stderr=full,
            timeout=120,
        )
    assert run.returncode == 2


def test_a_broken_pipe_keeps_its_exit_code() -> None:
    """EPIPE is not a full disk: ``x6wd mission show ... | head`` stays quiet, as before."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "x6wd", "replay", "--speed", "0", str(LOG)],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    assert proc.stdout is not None
    proc.stdout.readline()
    proc.stdout.close()
    _, err = proc.communicate(timeout=120)
    assert "writing output" not in err and "Traceback" not in err
    assert proc.returncode in (0, 141)


class FullStream:
    """A text stream on a full disk."""

    def write(self, _text: str) -> int:
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    def flush(self) -> None:
        pass


def test_another_oserror_without_a_file_name_is_still_a_crash(monkeypatch) -> None:
    """EIO reading a serial device that was unplugged is no 'writing output' error."""
    from x6wd.app import decode

    def unplugged(_args: object) -> int:
        raise OSError(errno.EIO, os.strerror(errno.EIO))

    monkeypatch.setattr(decode, "main", unplugged)
    with pytest.raises(OSError, match="Input/output error"):
        cli.main(["decode", str(LOG)])


def test_the_daemons_failed_write_stays_a_crash_for_systemd(monkeypatch, tmp_path: Path) -> None:
    """`x6wd run`: exit 2 is RestartPreventExitStatus, so a failed write there stays a crash
    (exit 1, systemd restarts the daemon)."""
    from x6wd.app import daemon

    def writes(_args: object) -> int:
        print("starting")
        return 0

    monkeypatch.setattr(daemon, "main", writes)
    monkeypatch.setattr(sys, "stdout", FullStream())
    with pytest.raises(OSError, match="No space left"):
        cli.main(["run", "--config", str(tmp_path / "x.toml")])


def test_the_marked_streams_are_put_back(monkeypatch) -> None:
    from x6wd.app import mission

    seen = []
    monkeypatch.setattr(mission, "main", lambda _args: seen.append(sys.stdout) or 0)
    before = sys.stdout, sys.stderr
    assert cli.main(["mission", "show", str(MISSION)]) == 0
    assert (sys.stdout, sys.stderr) == before
    assert isinstance(seen[0], cli.MarkedStream)
