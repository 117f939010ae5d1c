"""Run every benchmark (bench/bench_*.py) and print one table.

Usage: ``python bench/run.py [--quick] [--only NAME ...]`` from the repository root (also
``python -m bench.run``). NAME is a benchmark's file name without ``bench_`` and ``.py``.
A benchmark that fails is reported on stderr with its traceback; the others still run; the
exit code is 1. A benchmark whose extra is not installed (Dask for ``sweep``) says which one to
install in one line, no traceback; the others still run; the exit code is 2 (1 if another
failed).
"""

from __future__ import annotations

import argparse
import importlib
import sys
import traceback
from collections.abc import Sequence
from pathlib import Path

BENCH_DIR = Path(__file__).resolve().parent
ROOT = BENCH_DIR.parent
if str(ROOT) not in sys.path:  # run as a script: make ``bench._common`` importable
    sys.path.insert(0, str(ROOT))

from bench._common import MissingExtra, Row, extra_hint, print_table  # noqa: E402


def available() -> list[str]:
    """Names of the benchmarks found in bench/ (``bench_filter.py`` -> ``filter``)."""
    return sorted(p.stem[len("bench_") :] for p in BENCH_DIR.glob("bench_*.py"))


def main(argv: Sequence[str] | None = None) -> int:
    """Run the chosen benchmarks; return the process exit code."""
    parser = argparse.ArgumentParser(
        prog="bench/run.py", description=__doc__.splitlines()[0], allow_abbrev=False
    )
    parser.add_argument("--quick", action="store_true", help="smaller inputs, quicker figures")
    parser.add_argument(
        "--only", action="append", metavar="NAME", help="run only this benchmark (repeatable)"
    )
    args = parser.parse_args(argv)
    names = available()
    chosen = names
    if args.only:
        wanted = [n.removeprefix("bench_").removesuffix(".py") for n in args.only]
        unknown = [n for n in wanted if n not in names]
        if unknown:
            parser.error(f"unknown benchmark {unknown[0]!r} (available: {', '.join(names)})")
        chosen = [n for n in names if n in wanted]
    rows: list[Row] = []
    failed = []
    lacking = []  # benchmarks whose extra is not installed: a setup matter, not a bug
    for name in chosen:
        try:
            module = importlib.import_module(f"bench.bench_{name}")
            rows.extend(module.run(quick=args.quick))
        except MissingExtra as exc:
            lacking.append(name)
            print(exc, file=sys.stderr)
        except Exception as exc:
            hint = None
            if isinstance(exc, ModuleNotFoundError):  # a package of an extra, on first use
                hint = extra_hint(name, (exc.name or "").split(".")[0])
            if hint is not None:
                lacking.append(name)
                print(hint, file=sys.stderr)
                continue
            failed.append(name)
            print(f"benchmark {name} failed:", file=sys.stderr)
            traceback.print_exc()
    if rows:
        print_table(rows)
    if failed:
        print(f"failed: {', '.join(failed)}", file=sys.stderr)
        return 1
    return 2 if lacking else 0


if __name__ == "__main__":
    sys.exit(main())
