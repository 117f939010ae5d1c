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
    res = _run("ruff", "check", *PACKAGES, "bench", "tests", "tools")
    assert res.returncode == 0, res.stdout + res.stderr


@pytest.mark.slow
def test_mypy_is_clean(tmp_path: object) -> None:
    res = _run("mypy", "--cache-dir", str(tmp_path), *PACKAGES)
    assert res.returncode == 0, res.stdout + res.stderr


def test_the_mutation_table_lists_the_tests_tools_mutate_runs() -> None:
    """docs/testing.md's table of mutation areas names, per area, the tests `tools/mutate`
    runs against it (`--list`), in its order."""
    res = subprocess.run(
        [sys.executable, "tools/mutate", "--list"], cwd=ROOT, capture_output=True, text=True
    )
    assert res.returncode == 0, res.stderr
    tool: dict[str, list[str]] = {}
    for line in res.stdout.splitlines():
        if not line.startswith(" "):
            area = line.split(":")[0]
        elif line.strip().startswith("tests:"):
            tool[area] = [p.rsplit("/", 1)[-1] for p in line.split(":", 1)[1].split()]
    doc: dict[str, list[str]] = {}
    for line in (ROOT / "docs" / "testing.md").read_text().splitlines():
        cells = [c.strip() for c in line.strip("|").split("|")]
        if line.startswith("| ") and cells[0] in tool and len(cells) == 3:
            doc[cells[0]] = [c.strip().strip("`") for c in cells[2].split(",")]
    assert tool and doc == tool
