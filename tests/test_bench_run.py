"""bench/run.py, the one table of every benchmark: a benchmark whose extra is missing says
which one to install, as every x6wd tool does, and is no crash."""

from __future__ import annotations

import subprocess
import sys
import types
from collections.abc import Callable
from typing import Any

import pytest

from bench import run as bench_run
from tests.conftest import ROOT

# bench/run.py with the packages of the `sweep` extra made unimportable (an install without it)
WITHOUT_DASK = """
import sys
sys.modules["dask"] = sys.modules["distributed"] = None
sys.path.insert(0, "bench")
from run import main
sys.exit(main(sys.argv[1:]))
"""


def test_a_benchmark_without_its_extra_prints_only_the_hint_and_exits_2() -> None:
    # an outside audit: `--only sweep` without Dask ran the in-process sweeps, then printed a
    # full traceback before the x6wd[sweep] line
    res = subprocess.run(
        [sys.executable, "-c", WITHOUT_DASK, "--quick", "--only", "sweep"],
        cwd=ROOT, capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert res.returncode == 2, res.stderr
    assert res.stderr.splitlines() == [
        "benchmark sweep needs dask, which is not installed: pip install 'x6wd[sweep]' "
        "(from a checkout: pip install -e '.[sweep]')"
    ]
    assert res.stdout == ""  # no empty table


def test_an_extra_imported_on_first_use_is_the_hint_and_a_bug_keeps_its_traceback(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """A benchmark that imports an extra's package itself: its ModuleNotFoundError is the
    same one line (exit 2); any other failure keeps its traceback (exit 1)."""

    def bench_importing(exc: Exception) -> Callable[[str], Any]:
        def run(quick: bool = False) -> list[Any]:
            raise exc

        return lambda name: types.SimpleNamespace(run=run)

    missing = ModuleNotFoundError("No module named 'scipy'", name="scipy")
    monkeypatch.setattr(bench_run.importlib, "import_module", bench_importing(missing))
    assert bench_run.main(["--only", "gap"]) == 2
    out = capsys.readouterr()
    assert out.err.splitlines() == [
        "benchmark gap needs scipy, which is not installed: pip install 'x6wd[sim]' "
        "(from a checkout: pip install -e '.[sim]')"
    ]
    # numpy is the robot's own install: missing, it is a broken install, not an extra
    for exc in (ModuleNotFoundError("No module named 'numpy'", name="numpy"), RuntimeError("x")):
        monkeypatch.setattr(bench_run.importlib, "import_module", bench_importing(exc))
        assert bench_run.main(["--only", "gap"]) == 1
        err = capsys.readouterr().err
        assert "benchmark gap failed:" in err and "Traceback" in err and "failed: gap" in err


@pytest.mark.parametrize(
    "module", sorted(p.stem for p in (ROOT / "bench").glob("bench_*.py")), ids=str
)
def test_every_benchmark_answers_help_without_running(module: str) -> None:
    # an outside audit (round 19): `python -m bench.bench_gap_zone --help` (named in
    # docs/gap_zone.md) ran the whole benchmark, as did ten others
    res = subprocess.run(
        [sys.executable, "-m", f"bench.{module}", "--help"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert res.returncode == 0, res.stderr[-1000:]
    assert res.stdout.startswith("usage: "), res.stdout[:300]
