"""systemd/x6wd.service: `systemd-analyze verify` must print nothing; the required settings,
the hardening among them, each line by itself (an outside audit deleted UMask=,
SystemCallFilter=~@privileged, CapabilityBoundingSet=, ProtectHome=, PrivateTmp=,
RestrictAddressFamilies=, MemoryDenyWriteExecute= and StateDirectoryMode= one at a time and
no test failed); and `systemd-analyze security --offline=yes`'s verdicts on them."""

from __future__ import annotations

import json
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


def analyze_unit(tmp_path: Path, text: str, *args: str) -> subprocess.CompletedProcess[str]:
    """``systemd-analyze ARGS UNIT`` on the unit ``text`` written to tmp_path, its ExecStart
    an existing binary (verify needs one; the unit's own path is an install path)."""
    analyze = require_program("systemd-analyze")
    true_bin = shutil.which("true") or "/bin/true"
    unit = tmp_path / "x6wd.service"
    unit.write_text(re.sub(r"(?m)^ExecStart=\S+", f"ExecStart={true_bin}", text))
    return subprocess.run(
        [analyze, *args, str(unit)], capture_output=True, text=True, timeout=60, cwd=tmp_path
    )


def verify(tmp_path: Path, text: str) -> str:
    proc = analyze_unit(tmp_path, text, "verify")
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
        # files the daemon creates (recordings) are not world-readable; its state dir neither
        ("UMask", "0027"),
        ("StateDirectoryMode", "0750"),
        ("ProtectHome", "yes"),
        ("PrivateTmp", "yes"),
        ("ProtectKernelTunables", "yes"),
        ("ProtectKernelModules", "yes"),
        ("ProtectKernelLogs", "yes"),
        ("ProtectControlGroups", "yes"),
        ("ProtectClock", "yes"),
        ("ProtectHostname", "yes"),
        ("ProtectProc", "invisible"),
        ("ProcSubset", "pid"),
        ("RestrictAddressFamilies", "AF_UNIX AF_INET AF_INET6"),
        ("RestrictNamespaces", "yes"),
        ("RestrictRealtime", "yes"),
        ("RestrictSUIDSGID", "yes"),
        ("LockPersonality", "yes"),
        ("MemoryDenyWriteExecute", "yes"),
        ("SystemCallArchitectures", "native"),
        ("CapabilityBoundingSet", ""),  # empty: no capability at all
        ("AmbientCapabilities", ""),
        ("RemoveIPC", "yes"),
    ],
)
def test_required_setting(key: str, value: str) -> None:
    assert settings()[key] == [value]


def test_the_system_call_filter_allows_the_service_set_without_privileged_calls() -> None:
    assert settings()["SystemCallFilter"] == ["@system-service", "~@privileged"]


# The checks of `systemd-analyze security` the unit passes (a hand list: a hardening line
# deleted fails its check here, whatever the overall score does).
SECURITY_PASSED = (
    "SystemCallFilter=~@privileged",
    "SystemCallFilter=~@mount",
    "SystemCallFilter=~@raw-io",
    "SystemCallFilter=~@module",
    "SystemCallFilter=~@clock",
    "SystemCallFilter=~@reboot",
    "SystemCallFilter=~@swap",
    "SystemCallFilter=~@debug",
    "SystemCallFilter=~@obsolete",
    "SystemCallFilter=~@cpu-emulation",
    "SystemCallArchitectures=",
    "User=/DynamicUser=",
    "NoNewPrivileges=",
    "AmbientCapabilities=",
    "CapabilityBoundingSet=~CAP_SYS_ADMIN",
    "CapabilityBoundingSet=~CAP_SYS_RAWIO",
    "CapabilityBoundingSet=~CAP_SYS_PTRACE",
    "CapabilityBoundingSet=~CAP_NET_ADMIN",
    "CapabilityBoundingSet=~CAP_SYS_MODULE",
    "CapabilityBoundingSet=~CAP_SET(UID|GID|PCAP)",
    "CapabilityBoundingSet=~CAP_(DAC_*|FOWNER|IPC_OWNER)",
    "ProtectSystem=",
    "ProtectHome=",
    "PrivateTmp=",
    "ProtectProc=",
    "ProcSubset=",
    "ProtectKernelTunables=",
    "ProtectKernelModules=",
    "ProtectKernelLogs=",
    "ProtectControlGroups=",
    "ProtectClock=",
    "ProtectHostname=",
    "RestrictAddressFamilies=~AF_PACKET",
    "RestrictAddressFamilies=~AF_NETLINK",
    "RestrictAddressFamilies=~…",
    "RestrictNamespaces=~user",
    "RestrictNamespaces=~net",
    "RestrictRealtime=",
    "RestrictSUIDSGID=",
    "LockPersonality=",
    "MemoryDenyWriteExecute=",
    "RemoveIPC=",
    "NotifyAccess=",
)


def security(tmp_path: Path, text: str) -> dict[str, dict[str, object]]:
    """``systemd-analyze security --offline=yes --json=short`` of the unit ``text``: each
    check by name ({"set": passed, "exposure": ..., "description": ...})."""
    proc = analyze_unit(tmp_path, text, "security", "--offline=yes", "--json=short")
    assert proc.returncode == 0, proc.stderr
    return {c["name"]: c for c in json.loads(proc.stdout)}


def test_systemd_analyze_security_passes_every_hardening_check(tmp_path: Path) -> None:
    checks = security(tmp_path, UNIT.read_text())
    failed = [name for name in SECURITY_PASSED if checks[name]["set"] is not True]
    assert not failed, [(n, checks[n]["description"]) for n in failed]
    # UMask=0027: group-readable at most (0022 is world-readable, exposure 0.1 more)
    assert "world" not in str(checks["UMask="]["description"]), checks["UMask="]


def test_the_security_check_does_catch_a_dropped_line(tmp_path: Path) -> None:
    for line in ("ProtectHome=yes", "SystemCallFilter=~@privileged", "CapabilityBoundingSet="):
        text = UNIT.read_text().replace(f"\n{line}\n", "\n", 1)
        assert text != UNIT.read_text(), line
        checks = security(tmp_path, text)
        assert any(checks[n]["set"] is not True for n in SECURITY_PASSED), line
    checks = security(tmp_path, UNIT.read_text().replace("\nUMask=0027\n", "\n", 1))
    assert "world-readable" in str(checks["UMask="]["description"])


def test_devices_groups_and_watchdog() -> None:
    s = settings()
    assert set(s["SupplementaryGroups"][0].split()) >= {"dialout", "i2c"}
    allowed = " ".join(s["DeviceAllow"])
    assert "char-i2c rw" in allowed and "/dev/ttyS0 rw" in allowed
    assert "PrivateDevices" not in s  # it would hide the UART and /dev/i2c-*
    assert re.fullmatch(r"\d+s", s["WatchdogSec"][0])
    assert s["ExecStart"][0].split()[1:] == ["run", "--config", "/etc/x6wd/x6wd.toml"]
