"""The output directory a command writes into (``--out``): made, or refused with a clear error.

A mistaken ``--out`` (an existing file, a path under a file, a read-only place) is a user's
error like a bad config key: the commands report it as a :class:`ConfigError` (exit 2, the
path named) before any work is done, not as a traceback minutes into a run.
"""

from __future__ import annotations

from pathlib import Path

from x6wd.core.errors import ConfigError


def output_dir(path: str | Path, probe: str = ".x6wd-write-test") -> Path:
    """``path`` as a directory that exists and takes files (made with its parents if need
    be); :class:`ConfigError` naming it otherwise. A probe file ``probe`` is written and
    removed to find a read-only place now."""
    out = Path(path)
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
    return out


def write_output_file(path: str | Path, text: str) -> Path:
    """Write ``text`` (UTF-8) to the file ``path`` a user named; :class:`ConfigError` naming
    it when that cannot be done (a directory there, a missing parent, a read-only place)."""
    out = Path(path)
    try:
        out.write_text(text, encoding="utf-8")
    except OSError as e:
        raise ConfigError(f"output file {str(out)!r}: {e.strerror or e}") from e
    return out
