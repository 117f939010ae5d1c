"""The packages stay lint- and type-clean: issue 2's bar, enforced where CI sees it."""

from __future__ import annotations

import subprocess
import sys

import pytest

from tests.conftest import ROOT

PACKAGES = ["x6wd", "drivers", "sim_backend"]


def _run(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", *args], cwd=ROOT, capture_output=True, text=True, timeout=600
    )


def test_ruff_is_clean() -> None:
    res = _run("ruff", "check", *PACKAGES, "bench")
    assert res.returncode == 0, res.stdout + res.stderr


@pytest.mark.slow
def test_mypy_is_clean(tmp_path: object) -> None:
    res = _run("mypy", "--cache-dir", str(tmp_path), *PACKAGES)
    assert res.returncode == 0, res.stdout + res.stderr
