"""README.md's "A tour" runs verbatim on a fresh checkout (issue 17, item 6).

Every line of the indented block after "## A tour" is run as written, by bash, in a copy of
the repository's tracked files (what a fresh clone has: no out/, no recordings, no files
from /work/shared), with this interpreter's venv first on PATH, in order. A line named in
:data:`BACKGROUND` (the daemon) is started in the background, waited for, and stopped after
the last line; every other line must exit 0 without a traceback. Lines that start with "#"
(a note such as "open http://... in a browser") are not run. A new tour line needs nothing
here unless it runs until stopped.
"""

from __future__ import annotations

import json
import os
import shlex
import shutil
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import pytest

from tests.conftest import require_program

ROOT = Path(__file__).resolve().parent.parent
LINE_TIMEOUT_S = 300.0  # one line on a loaded 2-core machine (the gap and sweep lines)


def _daemon_has_a_fix(env: dict[str, str], cwd: Path) -> bool:
    r = subprocess.run(
        ["x6wd", "client", "status", "--json"], env=env, cwd=cwd, capture_output=True,
        text=True, timeout=30,
    )  # fmt: skip
    if r.returncode != 0:
        return False
    tel = json.loads(r.stdout).get("telemetry") or {}
    return bool(tel.get("fix_quality"))


BACKGROUND: dict[str, tuple[Callable[[dict[str, str], Path], bool], tuple[int, ...]]] = {
    # a tour line (its command, comment stripped) that runs until stopped -> (ready when, the
    # ports it takes): the daemon serves once it has a fix (a mission load needs one)
    "x6wd run --config config/hil.toml": (_daemon_has_a_fix, (7601, 7602, 2947)),
}
READY_TIMEOUT_S = 90.0
RERUN_SKIPS = ("x6wd sim ", "x6wd gap ", "x6wd sweep ", "python bench/")
"""Tour lines before the daemon's that a second run of the tour does not repeat here (for
time: each writes only into its --out folder, which it replaces); every other one runs twice."""


def tour_lines(readme: str) -> list[str]:
    """The commands of the first indented block after "## A tour", as written (comments
    kept; lines that are only a comment left out)."""
    lines = readme.splitlines()
    block: list[str] = []
    for line in lines[lines.index("## A tour") + 1 :]:
        if line.startswith("## "):
            break
        if line.startswith("    "):
            block.append(line.strip())
        elif line.strip() and block:
            break  # the text after the block
    return [c for c in block if c and not c.startswith("#")]


def command_of(line: str) -> str:
    """The line without its comment, words normalised (the key of :data:`BACKGROUND`)."""
    return shlex.join(shlex.split(line, comments=True))


def fresh_checkout(dest: Path) -> Path:
    """The repository's tracked files (as in the working tree) copied into ``dest``."""
    git = require_program("git")
    r = subprocess.run(
        [git, "ls-files", "-z"], cwd=ROOT, capture_output=True, check=False, timeout=60
    )
    if r.returncode != 0:
        pytest.fail(f"the tour test needs a git checkout: {r.stderr.decode().strip()}")
    for name in r.stdout.decode().split("\0"):
        src = ROOT / name
        if not name or not src.is_file():  # deleted in the working tree
            continue
        target = dest / name
        target.parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(src, target)
    return dest


def _git(*args: str, stdin: str | None = None) -> str:
    """``git ARGS`` in this checkout (its .gitignore is the fresh copy's): stdout."""
    r = subprocess.run(
        [require_program("git"), *args], cwd=ROOT, input=stdin, capture_output=True,
        text=True, timeout=60,
    )  # fmt: skip
    assert r.returncode in (0, 1), r.stderr  # check-ignore: 1 when nothing is ignored
    return r.stdout


def port_free(port: int) -> bool:
    with socket.socket() as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind(("127.0.0.1", port))
        except OSError:
            return False
    return True


def test_tour_block_is_found() -> None:
    lines = tour_lines((ROOT / "README.md").read_text())
    assert len(lines) >= 10, lines
    assert any(command_of(c) in BACKGROUND for c in lines)
    for c in lines:  # a shorthand such as "status | load ... | start" is not a command
        assert "|" not in c.split("#")[0], c


@pytest.mark.slow
@pytest.mark.integration
def test_the_tour_runs_verbatim_on_a_fresh_checkout(tmp_path: Path) -> None:
    lines = tour_lines((ROOT / "README.md").read_text())
    if any(c.startswith("gpspipe") for c in lines):
        require_program("gpspipe")
    work = fresh_checkout(tmp_path / "x6wd")
    bin_dir = str(Path(sys.executable).parent)
    env = {**os.environ, "PATH": bin_dir + os.pathsep + os.environ.get("PATH", "")}
    env.pop("PYTHONPATH", None)
    env["PYTHONUNBUFFERED"] = "1"
    logs = tmp_path / "logs"
    logs.mkdir()
    background: list[tuple[str, subprocess.Popen[bytes]]] = []
    timings: list[tuple[float, str]] = []
    try:
        for k, line in enumerate(lines):
            out, err = logs / f"{k:02d}.out", logs / f"{k:02d}.err"
            t0 = time.monotonic()
            with open(out, "wb") as fo, open(err, "wb") as fe:
                spec = BACKGROUND.get(command_of(line))
                if spec is not None:
                    ready, ports = spec
                    busy = [p for p in ports if not port_free(p)]
                    assert not busy, f"ports {busy} are taken: the tour's daemon needs them"
                    proc = subprocess.Popen(
                        ["bash", "-c", line], cwd=work, env=env, stdout=fo, stderr=fe,
                        start_new_session=True,
                    )  # fmt: skip
                    background.append((line, proc))
                    deadline = time.monotonic() + READY_TIMEOUT_S
                    while not ready(env, work):
                        assert proc.poll() is None, f"{line!r} ended:\n{err.read_text()[-3000:]}"
                        assert time.monotonic() < deadline, f"{line!r} not ready in time"
                        time.sleep(0.5)
                else:
                    r = subprocess.run(
                        ["bash", "-c", line], cwd=work, env=env, stdout=fo, stderr=fe,
                        timeout=LINE_TIMEOUT_S,
                    )  # fmt: skip
                    text = err.read_text(errors="replace")
                    assert r.returncode == 0, (
                        f"tour line {k + 1} failed (exit {r.returncode}): {line}\n"
                        f"{out.read_text(errors='replace')[-2000:]}\n{text[-3000:]}"
                    )
                    assert "Traceback" not in text, f"{line}\n{text[-3000:]}"
            timings.append((time.monotonic() - t0, line))
    finally:
        for line, proc in background:
            if proc.poll() is None:
                os.killpg(proc.pid, signal.SIGTERM)
            try:
                rc = proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                os.killpg(proc.pid, signal.SIGKILL)
                rc = proc.wait()
            timings.append((0.0, f"{line} -> exit {rc}"))
        for dt, line in timings:
            print(f"{dt:6.1f} s  {line}")
    for line, proc in background:
        assert proc.returncode == 0, (line, (logs / "x").parent)
    problems = []
    # a reader runs the tour again in the same checkout: every line still works (an outside
    # audit: `mission convert ... plan.waypoints` refused the second time, "exists")
    first = next(k for k, c in enumerate(lines) if command_of(c) in BACKGROUND)
    again = [c for c in lines[:first] if not c.startswith(RERUN_SKIPS)]
    assert again, "no tour line to run twice"
    for line in again:
        r = subprocess.run(
            ["bash", "-c", line], cwd=work, env=env, capture_output=True, text=True,
            timeout=LINE_TIMEOUT_S,
        )  # fmt: skip
        if r.returncode != 0 or "Traceback" in r.stderr:
            problems.append(f"second run: exit {r.returncode}: {line}\n{r.stderr[-2000:]}")
    # what the tour wrote is ignored by git: `git status` after the tour shows nothing new
    # (the same audit: gnss.toml, lce.png, odometry.toml, plan.waypoints, report/, sweep/)
    written = sorted(
        str(p.relative_to(work)) for p in work.rglob("*") if p.is_file() or p.is_symlink()
    )
    tracked = set(_git("ls-files", "-z").split("\0"))
    new = [name for name in written if name not in tracked]
    ignored = set(
        _git("check-ignore", "--no-index", "--stdin", "-z", stdin="\0".join(new)).split("\0")
    )
    shown = sorted({name.split("/")[0] for name in new if name not in ignored})
    if shown:
        problems.append(f"the tour leaves files git does not ignore: {shown}")
    assert not problems, "\n".join(problems)
