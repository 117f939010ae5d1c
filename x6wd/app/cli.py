"""`x6wd` command line: one subcommand per tool, each module imported only when chosen.

A subcommand module provides ``add_arguments(parser)`` and ``main(args) -> int``.
"""

from __future__ import annotations

import argparse
import contextlib
import errno
import importlib
import importlib.util
import os
import sys
from collections.abc import Callable, Iterable, Iterator, Sequence
from types import ModuleType
from typing import Any, TextIO

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


def chosen_parsers(
    parser: argparse.ArgumentParser, args: argparse.Namespace
) -> Iterator[argparse.ArgumentParser]:
    """The parsers on the path of the (nested) subcommand chosen in ``args``, outermost first:
    ``x6wd``'s, ``x6wd client``'s, ``x6wd client status``'s."""
    yield parser
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            sub = action.choices.get(getattr(args, action.dest, ""))
            if sub is not None:
                yield from chosen_parsers(sub, args)
                return


def chosen_parser(
    parser: argparse.ArgumentParser, args: argparse.Namespace
) -> argparse.ArgumentParser:
    """The parser of the (nested) subcommand chosen in ``args``, e.g. ``x6wd client status``'s."""
    *_, last = chosen_parsers(parser, args)
    return last


def empty_option(parser: argparse.ArgumentParser, args: argparse.Namespace) -> str | None:
    """The first option or argument of ``args`` given as an empty string (``--out ''``, which
    would be the current folder; ``--config ''``, no file: every one is a path or a name), as
    its error message; None when there is none. Every parser on the chosen path is looked at,
    not only the innermost: ``x6wd client --cafile '' status`` holds ``--cafile`` in ``x6wd
    client``'s (an empty one meant no TLS, the token in clear text); and so is every item of a
    list value (``--sim a ''``, ``decode ''``: '' was read as the current folder)."""
    for each in chosen_parsers(parser, args):
        for action in each._actions:
            value = getattr(args, action.dest, None)
            items = value if isinstance(value, list | tuple) else [value]
            if not any(isinstance(item, str) and item == "" for item in items):
                continue
            if action.option_strings:
                name = action.option_strings[-1]
                return f"{name}: empty value ({name} '' gives no path, name or number)"
            name = action.metavar if isinstance(action.metavar, str) else action.dest
            return f"{name}: empty value ('' gives no path, name or number)"
    return None


def _fail(message: str) -> Callable[[argparse.Namespace], int]:
    def run(_args: argparse.Namespace) -> int:
        print(message, file=sys.stderr)
        return 2

    return run


# errno values of a write to stdout/stderr that cannot succeed (a full disk or quota under a
# redirection, a terminal or disk gone): one line and exit 2, not a traceback
OUTPUT_WRITE_ERRNOS = frozenset({errno.ENOSPC, errno.EDQUOT, errno.EIO})


class MarkedStream:
    """``sys.stdout`` or ``sys.stderr`` while a command runs: every call goes to ``stream``;
    an OSError from ``write``, ``writelines`` or ``flush`` gets ``x6wd_output = name``. That
    is how :func:`main` tells a failed write of the command's output (``x6wd decode LOG >
    /dev/full``) from any other OSError without a file name, e.g. EIO reading a serial
    device that was unplugged, which is a crash to report in full."""

    def __init__(self, stream: TextIO, name: str) -> None:
        self._stream = stream
        self._name = name

    def _mark(self, exc: OSError) -> None:
        exc.x6wd_output = self._name  # type: ignore[attr-defined]

    def write(self, text: str) -> int:
        """Write ``text`` to the stream; its OSError marked."""
        try:
            return self._stream.write(text)
        except OSError as exc:
            self._mark(exc)
            raise

    def writelines(self, lines: Iterable[str]) -> None:
        """Write ``lines`` to the stream; its OSError marked."""
        try:
            self._stream.writelines(lines)
        except OSError as exc:
            self._mark(exc)
            raise

    def flush(self) -> None:
        """Flush the stream; its OSError marked."""
        try:
            self._stream.flush()
        except OSError as exc:
            self._mark(exc)
            raise

    def __getattr__(self, attr: str) -> Any:
        return getattr(self._stream, attr)


@contextlib.contextmanager
def marked_output() -> Iterator[None]:
    """``sys.stdout`` and ``sys.stderr`` as :class:`MarkedStream` for the block; put back after
    (unless the command replaced one meanwhile, e.g. with /dev/null after a broken pipe)."""
    saved = sys.stdout, sys.stderr
    marked = MarkedStream(sys.stdout, "stdout"), MarkedStream(sys.stderr, "stderr")
    sys.stdout, sys.stderr = marked
    try:
        yield
    finally:
        if sys.stdout is marked[0]:
            sys.stdout = saved[0]
        if sys.stderr is marked[1]:
            sys.stderr = saved[1]


def _silence(stream: TextIO) -> None:
    """Point ``stream``'s file descriptor at /dev/null: what is still buffered in it (flushed
    again at the interpreter's exit) goes nowhere instead of failing once more."""
    with contextlib.suppress(OSError, ValueError):
        devnull = os.open(os.devnull, os.O_WRONLY)
        try:
            os.dup2(devnull, stream.fileno())
        finally:
            os.close(devnull)


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
    # not for the daemon: under systemd a failed write there is a crash that systemd should
    # restart from (exit 1), while exit 2 is RestartPreventExitStatus (systemd/x6wd.service)
    marking = marked_output() if args.command != "run" else contextlib.nullcontext()
    try:
        with marking:
            code = int(args._main(args) or 0)
            if args.command != "run":
                # a short output still buffered on a full disk fails here, not in the
                # interpreter's exit flush (a Python message and exit 120). A broken pipe is
                # left to that exit flush, as before (its data stays in the buffer).
                with contextlib.suppress(BrokenPipeError, ValueError):
                    sys.stdout.flush()
            return code
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
        stream = getattr(exc, "x6wd_output", None)
        if exc.filename is None and stream is not None and exc.errno in OUTPUT_WRITE_ERRNOS:
            # stdout or stderr: full disk (``> file``), /dev/full, a terminal gone (EIO)
            _silence(sys.stdout if stream == "stdout" else sys.stderr)
            with contextlib.suppress(OSError):
                print(f"x6wd: writing output: {exc.strerror or exc}", file=sys.stderr)
            return 2
        if exc.filename is None:  # the sites that write outputs name theirs (output_file)
            raise
        print(
            f"x6wd {args.command}: error: {exc.filename!r}: {exc.strerror or exc}", file=sys.stderr
        )
        return 2
