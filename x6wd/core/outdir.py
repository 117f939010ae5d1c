"""The output directory a command writes into (``--out``): made, or refused with a clear error.

A mistaken ``--out`` (an existing file, a path under a file, a read-only place) is a user's
error like a bad config key: the commands report it as a :class:`ConfigError` (exit 2, the
path named) before any work is done, not as a traceback minutes into a run.
"""

from __future__ import annotations

import errno
import io
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from x6wd.core.errors import ConfigError


def output_dir(
    path: str | Path, probe: str = ".x6wd-write-test", clear: Sequence[str] = ()
) -> Path:
    """``path`` as a directory that exists and takes files (made with its parents if need
    be); :class:`ConfigError` naming it otherwise. A probe file ``probe`` is written and
    removed to find a read-only place now. The files named in ``clear`` (the outputs this
    run writes, nothing else) are removed, so that a run cut short never leaves an earlier
    run's outputs beside its own."""
    out = Path(path)
    if not str(path).strip():
        raise ConfigError("output directory: empty path")
    try:
        out.mkdir(parents=True, exist_ok=True)
        test = out / probe
        test.write_bytes(b"")
        test.unlink()
    except OSError as e:
        blocker = next((p for p in (out, *out.parents) if p.exists()), None)
        if blocker is not None and not blocker.is_dir():
            why = f"{str(blocker)!r} is not a directory"
        else:
            why = e.strerror or str(e)
        raise ConfigError(f"output directory {str(out)!r}: {why}") from e
    for name in clear:
        with output_file(out / name):
            (out / name).unlink(missing_ok=True)
    return out


@contextmanager
def output_file(path: str | Path) -> Iterator[Path]:
    """Around the writing of the output file ``path``: an ``OSError`` there (a full disk, a
    read-only place) becomes a :class:`ConfigError` naming the file (exit 2, one line)."""
    try:
        yield Path(path)
    except OSError as e:
        raise ConfigError(f"output file {str(path)!r}: {e.strerror or e}") from e


_OUT_OF_SPACE = (errno.ENOSPC, errno.EDQUOT, errno.EFBIG)
"""The write errors of a file already opened (truncated): a full disk, a quota, a size limit."""


@contextmanager
def whole_output_file(path: str | Path) -> Iterator[Path]:
    """:func:`output_file` around the writing of ``path``, and a regular file that the block
    left cut short for room (a full disk, a quota, a size limit) is removed and said so, so
    that no truncated table, map or report reads as a result. A link (its target is the
    user's: /dev/full, another folder) or a device there is never removed, nor a file whose
    open was refused (a read-only file: it was not truncated)."""
    out = Path(path)
    # decided before writing: the write itself makes a missing path a regular file
    ours = not out.is_symlink() and (out.is_file() or not out.exists())
    try:
        with output_file(out):
            yield out
    except ConfigError as exc:
        cause = exc.__cause__
        # only these come after the file was opened (and so truncated)
        filled = isinstance(cause, OSError) and cause.errno in _OUT_OF_SPACE
        if not (ours and filled) or out.is_symlink() or not out.is_file():
            raise
        try:
            out.unlink()
        except OSError:
            raise exc from cause
        raise ConfigError(f"{exc} (the partly written file was removed)") from cause


def write_output_file(path: str | Path, text: str) -> Path:
    """Write ``text`` (UTF-8) to the file ``path`` a user named; :class:`ConfigError` naming
    it when that cannot be done (a directory there, a missing parent, a read-only place, a
    full disk: then the part written is removed, :func:`whole_output_file`)."""
    with whole_output_file(path) as out:
        out.write_text(text, encoding="utf-8")
    return out


class _NamedFileIO(io.FileIO):
    """A file whose write errors (a full disk) carry its name, as its open's errors do."""

    def write(self, data: Any, /) -> Any:  # int | None, as FileIO.write
        try:
            return super().write(data)
        except OSError as e:
            if e.filename is not None:
                raise
            raise OSError(e.errno, e.strerror, self.name) from e


def open_output(path: str | Path) -> io.BufferedWriter:
    """``path`` opened to write bytes (buffered) whose every ``OSError``, a write's or the
    closing flush's too, names the file (``x6wd``'s entry reports it in one line, exit 2)."""
    return io.BufferedWriter(_NamedFileIO(str(path), "wb"))
