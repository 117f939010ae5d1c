"""systemd/x6wd.service: `systemd-analyze verify` must print nothing; the required settings."""

from __future__ import annotations

import re
import shutil
import subprocess
from pathlib import Path

import pytest

from tests.conftest import ROOT, require_program

UNIT = ROOT / "systemd" / "x6wd.service"


def settings() -> dict[str, list[str]]:
    out: dict[str, list[str]] = {}
    for line in UNIT.read_text().splitlines():
        line = line.strip()
        if not line or line.startswith(("#", ";", "[")):
            continue
        key, _, value = line.partition("=")
        out.setdefault(key.strip(), []).append(value.strip())
    return out


def verify(tmp_path: Path, text: str) -> str:
    analyze = require_program("systemd-analyze")
    # ExecStart must name an existing binary for verify; the unit's own path is an install path
    true_bin = shutil.which("true") or "/bin/true"
    text = re.sub(r"(?m)^ExecStart=\S+", f"ExecStart={true_bin}", text)
    unit = tmp_path / "x6wd.service"
    unit.write_text(text)
    proc = subprocess.run(
        [analyze, "verify", str(unit)], capture_output=True, text=True, timeout=60, cwd=tmp_path
    )
    return (proc.stdout + proc.stderr).strip() + (
        "" if proc.returncode == 0 else f" rc={proc.returncode}"
    )


def test_systemd_analyze_verify_prints_no_warning(tmp_path: Path) -> None:
    assert verify(tmp_path, UNIT.read_text()) == ""


def test_the_check_does_catch_a_broken_unit(tmp_path: Path) -> None:
    broken = UNIT.read_text().replace("[Service]", "[Service]\nWatchdogSecs=5s", 1)
    assert "WatchdogSecs" in verify(tmp_path, broken)


@pytest.mark.parametrize(
    ("key", "value"),
    [
        ("Type", "notify"),
        ("Restart", "on-failure"),
        ("User", "x6wd"),
        ("DevicePolicy", "closed"),
        ("StateDirectory", "x6wd"),
        ("ProtectSystem", "strict"),
        ("NoNewPrivileges", "yes"),
    ],
)
def test_required_setting(key: str, value: str) -> None:
    assert settings()[key] == [value]


def test_devices_groups_and_watchdog() -> None:
    s = settings()
    assert set(s["SupplementaryGroups"][0].split()) >= {"dialout", "i2c"}
    allowed = " ".join(s["DeviceAllow"])
    assert "char-i2c rw" in allowed and "/dev/ttyS0 rw" in allowed
    assert "PrivateDevices" not in s  # it would hide the UART and /dev/i2c-*
    assert re.fullmatch(r"\d+s", s["WatchdogSec"][0])
    assert s["ExecStart"][0].split()[1:] == ["run", "--config", "/etc/x6wd/x6wd.toml"]
