"""Shared test fixtures: where the real data lives, and tools that CI must have."""

from __future__ import annotations

import os
import shutil
import signal
import socket
import subprocess
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

ROOT = Path(__file__).resolve().parent.parent
DATA = ROOT / "tests" / "data"
SHARED = ROOT.parent / "shared" / "data"


def require_program(name: str) -> str:
    """Path of a real peer program; skipped on a developer machine without it, fatal in CI."""
    path = shutil.which(name)
    if path is None:
        if os.environ.get("CI"):
            pytest.fail(f"{name} is required in CI (.ci/run installs it)")
        pytest.skip(f"{name} not installed")
    return path


def self_signed_cert(directory: Path) -> tuple[Path, Path]:
    """A throwaway self-signed certificate for localhost and 127.0.0.1 and its key (mode 600,
    as the daemon requires) in ``directory``, made by the real openssl."""
    cert, key = directory / "cert.pem", directory / "key.pem"
    subprocess.run(
        [require_program("openssl"), "req", "-x509", "-newkey", "rsa:2048", "-nodes",
         "-days", "2", "-subj", "/CN=localhost",
         "-addext", "subjectAltName=DNS:localhost,IP:127.0.0.1",
         "-keyout", str(key), "-out", str(cert)],
        check=True, capture_output=True,
    )  # fmt: skip
    key.chmod(0o600)
    return cert, key


def option_help(argv: list[str], option: str, capsys: pytest.CaptureFixture[str]) -> str:
    """The text ``x6wd ARGV --help`` prints for ``option``, on one line."""
    from x6wd.app import cli

    with pytest.raises(SystemExit) as exit_:
        cli.main([*argv, "--help"])
    assert exit_.value.code == 0
    text, lines = "", capsys.readouterr().out.splitlines()
    for i, line in enumerate(lines):
        if line.startswith(f"  {option} "):
            text = line
            for more in lines[i + 1 :]:
                if more.startswith("  -") or not more.startswith("   "):
                    break
                text += " " + more.strip()
    assert text, f"{option} not in the help"
    return " ".join(text.split())


@pytest.fixture
def data_dir() -> Path:
    return DATA


def filter_case(seed: int = 0, n: int = 40, moving: bool = False) -> tuple[Any, Any]:
    """A small irregular log (steps 0.5-2 s, a 4-epoch outage) and a two-component baseline
    noise model: the case on which the Kalman filters are checked against dense algebra."""
    import numpy as np

    from sim_backend.effects import PositionSeries
    from x6wd.gap.fit import NoiseModel

    rng = np.random.default_rng(seed)
    t = np.cumsum(rng.uniform(0.5, 2.0, n))
    v = np.ones(n, dtype=bool)
    v[10:14] = False
    y = rng.normal(size=(2, n))
    s = PositionSeries(
        t_s=t, east_m=y[0], north_m=y[1], up_m=0 * t, valid=v, origin_lat_deg=50.0,
        origin_lon_deg=10.0, speed_mps=1.0 + rng.uniform(0, 2, n) if moving else None,
        course_deg=np.linspace(0, 300, n) if moving else None,
    )  # fmt: skip
    model = NoiseModel(
        np.array([[0.5, 1.0], [0.7, 0.3]]),
        np.array([[3.0, 20.0], [5.0, 50.0]]),
        np.array([0.2, 0.3]),
        np.array([0.1, -0.1]),
    )
    return s, model


def dense_baseline_cov(model: Any, t_s: Any, axis: int) -> Any:
    """Dense covariance of the baseline noise model on one axis at times ``t_s``."""
    import numpy as np

    lag = np.abs(t_s[:, None] - t_s[None, :])
    k = model.sigma_m.shape[1]
    cov = sum(model.sigma_m[axis, i] ** 2 * np.exp(-lag / model.tau_s[axis, i]) for i in range(k))
    return cov + model.white_m[axis] ** 2 * np.eye(t_s.size)


# Under nohup (SIGHUP ignored, as some CI agents start jobs) every x6wd the tests spawn would
# inherit SIG_IGN and log "SIGHUP ignored (nohup)" to stderr, breaking the one-line error
# checks. A do-nothing handler keeps this process alive on a hangup and, unlike SIG_IGN, is
# reset to the default in every child at exec.
if signal.getsignal(signal.SIGHUP) == signal.SIG_IGN:
    signal.signal(signal.SIGHUP, lambda _signum, _frame: None)


@pytest.fixture
def listening() -> Iterator[int]:
    """A port some other program already listens on (127.0.0.1)."""
    sock = socket.socket()
    sock.bind(("127.0.0.1", 0))
    sock.listen()
    try:
        yield sock.getsockname()[1]
    finally:
        sock.close()


SLOW_TIMEOUT_S = 900
"""pytest-timeout's limit for a ``slow`` case without its own: the global 300 s is for hangs,
and a CPU-bound statistical case of ~100 s alone passed 300 s on a loaded 2-core host (the
few-logs gap test, 318-326 s beside a CI run, 2026-12-06)."""


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Give each ``slow`` case :data:`SLOW_TIMEOUT_S` unless it sets a timeout itself."""
    for item in items:
        if item.get_closest_marker("slow") and not item.get_closest_marker("timeout"):
            item.add_marker(pytest.mark.timeout(SLOW_TIMEOUT_S))


@pytest.fixture
def tiny_disk(tmp_path: Path) -> Iterator[Path]:
    """A 512 KiB tmpfs, unmounted after the test (root only, as CI runs); fill it with
    :func:`fill_disk` to make writes fail for room."""
    if os.geteuid() != 0:
        pytest.skip("mounting a tmpfs needs root")
    disk = tmp_path / "tiny"
    disk.mkdir()
    subprocess.run(["mount", "-t", "tmpfs", "-o", "size=512k", "tmpfs", str(disk)], check=True)
    try:
        yield disk
    finally:
        subprocess.run(["umount", "--lazy", str(disk)], check=True)  # even with a file open


def fill_disk(disk: Path, free_kib: int) -> None:
    """Fill ``disk`` but for ``free_kib`` KiB."""
    fill = disk / "fill"
    with open(fill, "wb") as f, pytest.raises(OSError):
        f.write(b"\0" * (1 << 20))
        f.flush()
    os.truncate(fill, os.path.getsize(fill) - free_kib * 1024)
