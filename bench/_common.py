"""Benchmark convention: each bench_*.py has run(quick=False) -> list[Row] and a __main__.

A row is one measured figure with its anchor (the reference it is judged against: a target,
or the baseline it is compared with) and the ratio value / anchor.
"""

from __future__ import annotations

import argparse
import importlib.util
from dataclasses import dataclass


@dataclass
class Row:
    bench: str
    metric: str
    value: float
    unit: str
    anchor: float | None = None
    anchor_label: str = ""
    note: str = ""

    @property
    def ratio(self) -> float | None:
        if self.anchor in (None, 0):
            return None
        return self.value / self.anchor  # type: ignore[operator]


class MissingExtra(Exception):
    """A benchmark needs a package of an extra that is not installed; the message is the one
    line that says which extra to install (bench/run.py prints it with no traceback)."""


def extra_hint(bench: str, module: str) -> str | None:
    """The line for ``module`` (a top-level package) missing from benchmark ``bench``, or None
    when no extra of x6wd installs it (then it is a bug, not a missing extra)."""
    from x6wd.app.cli import OPTIONAL_MODULES

    extra = OPTIONAL_MODULES.get(module)
    if extra is None:
        return None
    return (
        f"benchmark {bench} needs {module}, which is not installed: pip install "
        f"'x6wd[{extra}]' (from a checkout: pip install -e '.[{extra}]')"
    )


def require_modules(bench: str, *modules: str) -> None:
    """Raise :class:`MissingExtra` for the first of ``modules`` that is not installed, before
    a benchmark spends minutes on the figures that do not need it; nothing is imported."""
    for name in modules:
        if importlib.util.find_spec(name) is None:
            raise MissingExtra(extra_hint(bench, name) or f"benchmark {bench} needs {name}")


def upper95(k: int, n: int) -> float:
    """One-sided 95 % Clopper-Pearson upper bound of a rate seen k times in n trials (for a
    false-alarm rate measured on a finite number of null cases)."""
    from scipy.stats import beta

    return 1.0 if k >= n else float(beta.ppf(0.95, k + 1, n - k))


def print_table(rows: list[Row]) -> None:
    """Print rows as an aligned text table."""
    head = ("bench", "metric", "value", "unit", "anchor", "ratio", "note")
    body = [
        (
            r.bench,
            r.metric,
            f"{r.value:.4g}",
            r.unit,
            "" if r.anchor is None else f"{r.anchor:.4g} {r.anchor_label}".strip(),
            "" if r.ratio is None else f"{r.ratio:.3g}",
            r.note,
        )
        for r in rows
    ]
    widths = [max(len(str(x)) for x in col) for col in zip(head, *body, strict=True)]
    for line in (head, *body):
        print("  ".join(str(x).ljust(w) for x, w in zip(line, widths, strict=True)).rstrip())


# ``python -c PEAK_CHILD HWM_FILE ARGS...`` runs ``x6wd ARGS`` and writes its own peak
# resident set (VmHWM of the exec'd process, bytes) to HWM_FILE. ``ru_maxrss`` from wait4
# would not do: Linux carries the forking parent's high-water mark across exec.
PEAK_CHILD = """
import atexit, sys
path = sys.argv[1]
def _hwm():
    with open("/proc/self/status") as f:
        kb = next(int(ln.split()[1]) for ln in f if ln.startswith("VmHWM:"))
    with open(path, "w") as out:
        out.write(str(kb * 1024))
atexit.register(_hwm)
from x6wd.app.cli import main
sys.exit(main(sys.argv[2:]))
"""


def cli(doc: str | None, *, quick: bool = True) -> argparse.ArgumentParser:
    """A benchmark's command line: ``--help`` prints its docstring (what it measures, its
    targets, how long it takes) instead of starting a full run, ``--quick`` where it has a
    short run; anything else is an error (exit 2). Add options, then ``parse_args()``."""
    parser = argparse.ArgumentParser(
        description=doc, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    if quick:
        parser.add_argument("--quick", action="store_true", help="the short run")
    return parser
