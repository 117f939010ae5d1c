"""Input files the tools read: regular files only, and a whole-file read of bounded size, so
a device (``/dev/zero``), a FIFO without a writer or a huge file is a clear error naming it
instead of a hang or the kernel's out-of-memory kill (an outside audit: ``--config
/dev/zero`` took 8 GB in 15 s)."""

from __future__ import annotations

import errno
import io
import os
import stat

MAX_TEXT_FILE_BYTES = 64 << 20
"""Most bytes a file read whole may hold (a TOML configuration, scenario or sweep, a CSV):
64 MiB, a hundred times the largest scenario with buildings."""


class InputFileError(OSError):
    """An input that is not a regular file, or too large to read whole: an :class:`OSError`
    (callers already say "cannot read PATH: ...") whose ``strerror`` says which."""


def not_regular(path: str | os.PathLike[str]) -> str | None:
    """What ``path`` is when it is neither a regular file nor a directory (``"a pipe"`` for
    ``<(cmd)``'s /dev/fd/N, ``"a FIFO"``, ``"a character device"`` ...), else None (also
    when it does not exist). Such an input can be read only once and may never end; it is
    not opened here (a FIFO without a writer would block)."""
    try:
        mode = os.stat(path).st_mode
    except OSError:
        return None
    if stat.S_ISREG(mode) or stat.S_ISDIR(mode):
        return None
    if stat.S_ISFIFO(mode):
        try:
            named = stat.S_ISFIFO(os.lstat(path).st_mode)
        except OSError:
            named = False
        return "a FIFO" if named else "a pipe"
    if stat.S_ISCHR(mode):
        return "a character device"
    if stat.S_ISBLK(mode):
        return "a block device"
    return "a socket" if stat.S_ISSOCK(mode) else "not a file"


def require_regular(path: str | os.PathLike[str]) -> None:
    """Raise :class:`InputFileError` when ``path`` is neither a regular file nor a
    directory (a missing one is left to the open that follows, which names it)."""
    kind = not_regular(path)
    if kind is not None:
        raise InputFileError(errno.EINVAL, f"not a regular file ({kind}): save it to a file first")


def read_bytes_bounded(
    path: str | os.PathLike[str], limit_bytes: int = MAX_TEXT_FILE_BYTES
) -> bytes:
    """The whole of a regular file of at most ``limit_bytes`` bytes; else
    :class:`InputFileError` (other :class:`OSError` as ``open`` raises them)."""
    require_regular(path)
    with open(path, "rb") as f:
        blob = f.read(limit_bytes + 1)
    if len(blob) > limit_bytes:
        raise InputFileError(
            errno.EFBIG, f"larger than {limit_bytes >> 20} MiB: not a file of this kind"
        )
    return blob


def read_text_bounded(
    path: str | os.PathLike[str], limit_bytes: int = MAX_TEXT_FILE_BYTES, encoding: str = "utf-8"
) -> str:
    """:func:`read_bytes_bounded` decoded as ``Path.read_text`` would (universal newlines);
    bytes that do not decode raise :class:`UnicodeDecodeError`."""
    blob = read_bytes_bounded(path, limit_bytes)
    return io.TextIOWrapper(io.BytesIO(blob), encoding=encoding).read()


def not_text(line: str) -> bool:
    """A line decoded with ``errors="replace"`` that held bytes no text file has: one that
    was not UTF-8 (U+FFFD) or a control character other than tab and line ends (a binary
    file given where a text log belongs; its bytes are not echoed to a terminal)."""
    return "\ufffd" in line or any(ord(c) < 32 and c not in "\t\r\n" for c in line)
