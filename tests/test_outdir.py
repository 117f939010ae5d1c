"""A mistaken --out is a user's error: exit 2 naming the path, before any work is done."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from x6wd.app import cli
from x6wd.core.errors import ConfigError
from x6wd.core.outdir import output_dir, write_output_file

ROOT = Path(__file__).resolve().parent.parent


def test_output_dir_makes_parents_and_leaves_nothing_behind(tmp_path: Path) -> None:
    out = output_dir(tmp_path / "a" / "b")
    assert out.is_dir() and list(out.iterdir()) == []
    assert output_dir(out) == out  # an existing directory is fine


def test_output_dir_names_the_file_in_the_way(tmp_path: Path) -> None:
    (tmp_path / "f").write_text("")
    for path in (tmp_path / "f", tmp_path / "f" / "x" / "y"):
        with pytest.raises(ConfigError, match=r"'.*/f' is not a directory"):
            output_dir(path)


@pytest.mark.parametrize(
    "argv",
    [
        ["sim", str(ROOT / "config/scenarios/default.toml"), "--quiet"],
        ["sweep", str(ROOT / "config/sweeps/position_source.toml"), "--quiet"],
        ["gap", "--real", str(ROOT / "tests/data/nmea/bt451.log"), "--sim", "a", "--quiet"],
    ],
    ids=lambda a: a[0],
)
def test_commands_refuse_a_file_as_out_with_exit_2(
    argv: list[str], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    (tmp_path / "f").write_text("")
    assert cli.main([*argv, "--out", str(tmp_path / "f" / "sub")]) == 2
    err = capsys.readouterr().err
    assert f"x6wd {argv[0]}: error: output directory" in err and "is not a directory" in err
    assert [p.name for p in tmp_path.iterdir()] == ["f"] and (tmp_path / "f").is_file()


def test_write_output_file_names_what_is_in_the_way(tmp_path: Path) -> None:
    assert write_output_file(tmp_path / "frag.toml", "a = 1\n").read_text() == "a = 1\n"
    for bad in (tmp_path, tmp_path / "missing" / "frag.toml"):
        with pytest.raises(ConfigError, match=f"output file '{bad}'"):
            write_output_file(bad, "a = 1\n")


def test_plot_refuses_a_file_as_out_with_exit_2(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    sim = ["sim", str(ROOT / "config/scenarios/open_field.toml"), "--duration", "5", "--quiet"]
    assert cli.main([*sim, "--out", str(tmp_path / "run")]) == 0
    (tmp_path / "f").write_text("")
    plot = ["plot", str(tmp_path / "run" / "recording.jsonl"), "--format", "html"]
    assert cli.main([*plot, "--out", str(tmp_path / "f" / "x")]) == 2
    assert "x6wd plot: error: output directory" in capsys.readouterr().err


def test_the_paths_printed_are_normalised(tmp_path: Path) -> None:
    """`--out report/` printed `report//report.md`: each command prints clean paths."""

    def x6wd(*argv: str) -> str:
        r = subprocess.run(
            [sys.executable, "-m", "x6wd", *argv, "--out", "out/"],
            capture_output=True, text=True, timeout=120, cwd=tmp_path,
        )  # fmt: skip
        assert r.returncode == 0, r.stderr
        assert "//" not in r.stdout, r.stdout
        return r.stdout

    real = str(ROOT / "tests/data/nmea/skytraq-dgps.log")
    out = x6wd("gap", "--real", real, "--seeds", "1", "--replicates", "3", "--no-figures")
    assert "report in out/report.md" in out, out
    out = x6wd("sim", str(ROOT / "config/scenarios/open_field.toml"), "--duration", "5")
    assert f"outputs in {tmp_path / 'out'}" in out, out
    out = x6wd("plot", "out/recording.jsonl", "--format", "html")
    assert out == "out/recording.html\n"
