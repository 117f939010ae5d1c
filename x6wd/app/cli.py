"""`x6wd` command line: one subcommand per tool, each module imported only when chosen.

A subcommand module provides ``add_arguments(parser)`` and ``main(args) -> int``.
"""

from __future__ import annotations

import argparse
import importlib
import importlib.util
import os
import sys
from collections.abc import Callable, Iterator, Sequence
from types import ModuleType

from x6wd import __version__
from x6wd.core.errors import X6wdError

# name -> (module, one-line help)
COMMANDS: dict[str, tuple[str, str]] = {
    "run": ("x6wd.app.daemon", "run the control daemon (robot, or hardware-in-the-loop)"),
    "sim": ("sim_backend.cli", "run a scenario in fast time: a mission, or a static survey"),
    "client": ("x6wd.app.client", "operator client: status, load, start, stop, drive, watch"),
    "sweep": ("x6wd.app.sweep", "run a grid of scenarios x parameters x seeds on Dask"),
    "gap": ("x6wd.gap.cli", "diagnose the gap between a real log and the simulator"),
    "calibrate": ("x6wd.calibrate.cli", "estimate configuration sections from calibration runs"),
    "decode": ("x6wd.app.decode", "decode NMEA logs or recordings to gpsd-style JSON lines"),
    "replay": ("x6wd.app.replay", "replay a recording or NMEA log through the decoders"),
    "mission": (
        "x6wd.app.mission",
        "show or convert mission files (.waypoints, .plan, .gpx, .csv, .kml)",
    ),
    "plot": ("x6wd.app.plot", "draw a recording or NMEA log over time (PNG, HTML page)"),
}

# The robot's install has only what the daemon imports (pyproject.toml's dependencies); the
# other tools' packages come with extras. A tool that misses one says which extra to install.
# command -> the extra that has its packages (`x6wd run`: only a configuration with sim://
# devices, hardware in the loop, needs the simulator's)
COMMAND_EXTRAS = {
    "run": "sim",
    "sim": "sim",
    "sweep": "sweep",
    "gap": "gap",
    "calibrate": "plot",
    "plot": "plot",
}
# top-level modules of packages that only extras install -> the extra that has them all
OPTIONAL_MODULES = {
    "scipy": "sim",
    "matplotlib": "plot",
    "dask": "sweep",
    "distributed": "sweep",
}


# what a command needs from its extra before it starts: a simulation or an analysis should not
# run for minutes and then stop at its first use of scipy or at the plot (those are imported
# lazily, for start-up time)
REQUIRED_MODULES = {
    "sim": ("scipy", "matplotlib"),
    "gap": ("scipy", "matplotlib"),
}


def require_modules(modules: Sequence[str]) -> None:
    """Raise ``ModuleNotFoundError`` (with its ``name``) for the first of ``modules`` that is
    not installed; nothing is imported."""
    for name in modules:
        if importlib.util.find_spec(name) is None:
            raise ModuleNotFoundError(f"No module named {name!r}", name=name)


def missing_extra(command: str, exc: ModuleNotFoundError) -> str | None:
    """The message for a package of an extra that is not installed, or None when ``exc`` is
    about something else."""
    top = (exc.name or "").split(".")[0]
    if top not in OPTIONAL_MODULES:
        return None
    extra = COMMAND_EXTRAS.get(command, OPTIONAL_MODULES[top])
    what = " hardware in the loop (sim:// devices)" if command == "run" else ""
    return (
        f"x6wd {command}:{what} needs {top}, which is not installed (the robot's install "
        f"leaves it out): pip install 'x6wd[{extra}]' (from a checkout: "
        f"pip install -e '.[{extra}]')"
    )


def _load(name: str) -> ModuleType | str:
    """The subcommand's module, or why it cannot run (a message for stderr)."""
    module_name = COMMANDS[name][0]
    try:
        require_modules(REQUIRED_MODULES.get(name, ()))
        return importlib.import_module(module_name)
    except ModuleNotFoundError as exc:
        message = missing_extra(name, exc)
        if message is not None:
            return message
        if exc.name and module_name.startswith(exc.name):
            return f"x6wd {name}: not available in this build yet"
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
        if isinstance(module, str):
            p.description = f"{help_text} (not installed here: {module.split(': ', 1)[1]})"
            p.set_defaults(_main=_fail(module), _any_arguments=True)
        else:
            module.add_arguments(p)
            p.set_defaults(_main=module.main)
    for each in parsers(parser):
        # a misspelt option (`sweep --seed 42`) is an error, not a silent prefix match
        # (`--seeds 42`: 8x the planned runs). Set here on the whole tree, so that the nested
        # parsers the subcommand modules build (client status, ...) are covered too.
        each.allow_abbrev = False
    return parser


def parsers(parser: argparse.ArgumentParser) -> Iterator[argparse.ArgumentParser]:
    """``parser`` and all its subcommands' parsers, nested ones too."""
    yield parser
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub in action.choices.values():
                yield from parsers(sub)


def chosen_parser(
    parser: argparse.ArgumentParser, args: argparse.Namespace
) -> argparse.ArgumentParser:
    """The parser of the (nested) subcommand chosen in ``args``, e.g. ``x6wd client status``'s."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            sub = action.choices.get(getattr(args, action.dest, ""))
            if sub is not None:
                return chosen_parser(sub, args)
    return parser


def empty_option(parser: argparse.ArgumentParser, args: argparse.Namespace) -> str | None:
    """The first option or argument of ``args`` given as an empty string (``--out ''``, which
    would be the current folder; ``--config ''``, no file: every one is a path or a name), as
    its error message; None when there is none."""
    for action in chosen_parser(parser, args)._actions:
        if getattr(args, action.dest, None) == "":
            name = action.option_strings[-1] if action.option_strings else action.dest
            return f"{name}: empty value ({name} '' gives no path, name or number)"
    return None


def _fail(message: str) -> Callable[[argparse.Namespace], int]:
    def run(_args: argparse.Namespace) -> int:
        print(message, file=sys.stderr)
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
    try:  # building the parser imports the subcommand (numpy, ...): a Ctrl-C may land here
        parser = build_parser(args_list)
        args, unknown = parser.parse_known_args(args_list)
    except KeyboardInterrupt:
        return 130
    if unknown and not getattr(args, "_any_arguments", False):
        # the chosen subcommand's usage and name (`x6wd sim: error: ...`), not the top level's
        chosen_parser(parser, args).error(f"unrecognized arguments: {' '.join(unknown)}")
    empty = empty_option(parser, args)
    if empty is not None:
        print(f"x6wd {args.command}: error: {empty}", file=sys.stderr)
        return 2
    try:
        return int(args._main(args) or 0)
    except X6wdError as exc:
        print(f"x6wd {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except ModuleNotFoundError as exc:  # a package of an extra, imported on first use
        message = missing_extra(args.command, exc)
        if message is None:
            raise
        print(message, file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130
    except BrokenPipeError:
        # the reader went away (``x6wd sim ... | head``): the work is done and its files are
        # written; point stdout at /dev/null so the interpreter's exit flush cannot fail too
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        return 141  # 128 + SIGPIPE, what a shell reports for a command killed by it
    except OSError as exc:  # a file the command named (an output on a full disk, ...)
        if exc.filename is None:  # the sites that write outputs name theirs (output_file)
            raise
        print(
            f"x6wd {args.command}: error: {exc.filename!r}: {exc.strerror or exc}", file=sys.stderr
        )
        return 2
