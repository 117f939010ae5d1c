"""The `x6wd` command line itself: how its options are matched and its errors reported."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from x6wd.app import cli

ROOT = Path(__file__).resolve().parent.parent


def x6wd(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "x6wd", *args], capture_output=True, text=True, timeout=120, cwd=ROOT
    )


@pytest.mark.parametrize("command", sorted(cli.COMMANDS))
def test_no_parser_matches_an_abbreviated_option(command: str) -> None:
    # every parser of the chosen command's tree, the nested ones (client status, ...) too
    assert all(not p.allow_abbrev for p in cli.parsers(cli.build_parser([command])))


@pytest.mark.parametrize(
    ("argv", "unknown"),
    [
        # a refused --out stops the run at once should the abbreviation be taken
        (["sweep", "config/sweeps/position_source.toml", "--seed", "42", "--out", "f/x"],
         "--seed 42"),  # not --seeds 42
        (["sim", "config/scenarios/default.toml", "--dur", "5", "--out", "f/x"], "--dur 5"),
        # a nested parser; nothing listens on the port
        (["client", "--port", "47901", "status", "--js"], "--js"),  # not --json
    ],
    ids=["sweep", "sim", "client status"],
)  # fmt: skip
def test_an_abbreviated_option_is_an_error(argv: list[str], unknown: str, tmp_path: Path) -> None:
    (tmp_path / "f").write_text("")
    r = x6wd(*(str(tmp_path / a) if a == "f/x" else a for a in argv))
    assert r.returncode == 2, r.stderr
    assert f"unrecognized arguments: {unknown}" in r.stderr, r.stderr


@pytest.mark.parametrize(
    ("argv", "prog", "unknown"),
    [
        (["sim", "config/scenarios/default.toml", "--seeds", "3"], "x6wd sim", "--seeds 3"),
        (["replay", "X", "--sped", "0"], "x6wd replay", "--sped 0"),
        (["decode", "F", "--quite"], "x6wd decode", "--quite"),
        (["client", "--port", "47901", "status", "--foo"], "x6wd client status", "--foo"),
    ],
    ids=["sim", "replay", "decode", "client status"],
)
def test_a_misspelt_option_is_reported_with_the_subcommands_usage(
    argv: list[str], prog: str, unknown: str
) -> None:
    r = x6wd(*argv)
    assert r.returncode == 2, r.stderr
    assert r.stderr.startswith(f"usage: {prog} [-h]"), r.stderr
    assert f"\n{prog}: error: unrecognized arguments: {unknown}\n" in r.stderr, r.stderr
