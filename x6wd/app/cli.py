"""`x6wd` command line: one subcommand per tool, each module imported only when chosen.

A subcommand module provides ``add_arguments(parser)`` and ``main(args) -> int``.
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys
from collections.abc import Callable, Sequence
from types import ModuleType

from x6wd import __version__
from x6wd.core.errors import X6wdError

# name -> (module, one-line help)
COMMANDS: dict[str, tuple[str, str]] = {
    "run": ("x6wd.app.daemon", "run the control daemon (robot, or hardware-in-the-loop)"),
    "sim": ("sim_backend.mission", "run a whole simulated mission in fast time"),
    "client": ("x6wd.app.client", "operator client: status, load, start, stop, drive, watch"),
    "sweep": ("x6wd.app.sweep", "run a grid of scenarios x parameters x seeds on Dask"),
    "gap": ("x6wd.gap.cli", "diagnose the gap between a real log and the simulator"),
    "calibrate": ("x6wd.calibrate.cli", "estimate configuration sections from calibration runs"),
    "decode": ("x6wd.app.decode", "decode NMEA logs or recordings to gpsd-style JSON lines"),
    "replay": ("x6wd.app.replay", "replay a recording or NMEA log through the decoders"),
    "mission": ("x6wd.app.mission", "show or convert mission files (.waypoints, .gpx, .csv, .kml)"),
}


def _load(name: str) -> ModuleType | None:
    module_name = COMMANDS[name][0]
    try:
        return importlib.import_module(module_name)
    except ModuleNotFoundError as exc:
        if exc.name and module_name.startswith(exc.name):
            return None
        raise


def build_parser(argv: Sequence[str]) -> argparse.ArgumentParser:
    """The parser; only the chosen subcommand's module is imported (fast start-up)."""
    parser = argparse.ArgumentParser(prog="x6wd", description=__doc__.splitlines()[0])
    parser.add_argument("--version", action="version", version=f"x6wd {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    chosen = next((a for a in argv if not a.startswith("-")), None)
    for name, (_module, help_text) in COMMANDS.items():
        p = sub.add_parser(name, help=help_text, description=help_text)
        if name != chosen:
            continue
        module = _load(name)
        if module is None:
            p.set_defaults(_main=_unavailable(name))
            p.add_argument("rest", nargs=argparse.REMAINDER, help=argparse.SUPPRESS)
        else:
            module.add_arguments(p)
            p.set_defaults(_main=module.main)
    return parser


def _unavailable(name: str) -> Callable[[argparse.Namespace], int]:
    def run(_args: argparse.Namespace) -> int:
        print(f"x6wd {name}: not available in this build yet", file=sys.stderr)
        return 2

    return run


BLAS_THREAD_VARS = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")


def single_thread_blas() -> None:
    """One BLAS thread unless the user chose otherwise. Every array in x6wd is small, so BLAS
    threads never pay; on a busy 2-core board they spin against each other (a 43k-element
    dot product measured 16 ms instead of 0.1 ms). Effective only before numpy is imported,
    which is why the subcommand modules are loaded after this."""
    for var in BLAS_THREAD_VARS:
        os.environ.setdefault(var, "1")


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``x6wd`` console script; returns the process exit code."""
    single_thread_blas()
    args_list = list(sys.argv[1:] if argv is None else argv)
    parser = build_parser(args_list)
    args = parser.parse_args(args_list)
    try:
        return int(args._main(args) or 0)
    except X6wdError as exc:
        print(f"x6wd {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130
