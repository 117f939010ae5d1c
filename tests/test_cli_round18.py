"""What a new user meets first, from an outside audit (round 18): `x6wd plot`/`replay` of a
folder `x6wd sim` wrote, a sweep that fails to start leaves no folder behind, a finished
sweep run again does not report a throughput it did not measure, and clear words for a
binary .pos, an empty sweep file, a robot_config that is missing, a mission written to a
folder and a calibration whose inputs do not read."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
from pathlib import Path

import pytest

from tests.conftest import ROOT
from tests.test_sweep import sweep_file
from x6wd.app.cli import main

X6WD = [sys.executable, "-m", "x6wd"]
DEFAULT = ROOT / "config" / "scenarios" / "default.toml"


def x6wd(*args: str, cwd: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [*X6WD, *args], cwd=cwd, capture_output=True, text=True, timeout=300, check=False
    )


def test_plot_and_replay_take_a_folder_x6wd_sim_wrote(tmp_path: Path) -> None:
    run = x6wd("sim", str(DEFAULT), "--duration", "8", "--out", "window", "--quiet", cwd=tmp_path)
    assert run.returncode in (0, 1), run.stderr  # 1: a mission not completed in 8 s
    plot = x6wd("plot", "window", "--format", "html", "--out", "plot", cwd=tmp_path)
    assert plot.returncode == 0, plot.stderr
    assert (tmp_path / "plot" / "recording.html").is_file()
    replay = x6wd("replay", "window", "--speed", "0", cwd=tmp_path)
    assert replay.returncode == 0, replay.stderr
    assert replay.stdout.count(" valid=1 ") >= 5, replay.stdout
    (tmp_path / "nothing").mkdir()
    none = x6wd("plot", "nothing", cwd=tmp_path)
    assert none.returncode == 2 and "recording.jsonl" in none.stderr, none.stderr


def _closed_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])  # closed again: nothing listens there


@pytest.mark.parametrize("given_out", [True, False])
def test_a_sweep_that_cannot_start_leaves_no_folder(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch,
    given_out: bool,
) -> None:  # fmt: skip
    f = sweep_file(tmp_path, "seeds = 1\n[set]\nduration_s = 5.0\n")
    monkeypatch.chdir(tmp_path)
    scheduler = f"tcp://127.0.0.1:{_closed_port()}"
    out = tmp_path / "o" if given_out else tmp_path / "out" / "sweeps" / "sweep"
    extra = ["--out", str(out)] if given_out else []
    assert main(["sweep", str(f), "--scheduler", scheduler, *extra, "--quiet"]) == 2
    assert "connection refused" in capsys.readouterr().err
    assert not out.exists()
    # a folder that was there before stays, whatever is in it
    out.mkdir(parents=True)
    (out / "notes.txt").write_text("mine")
    assert main(["sweep", str(f), "--scheduler", scheduler, *extra, "--quiet"]) == 2
    assert (out / "notes.txt").read_text() == "mine"


def test_a_finished_sweep_run_again_claims_no_throughput(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from sim_backend.executor import Executor
    from sim_backend.sweep import load_sweep, run_sweep

    f = sweep_file(tmp_path, "seeds = 1\n[set]\nduration_s = 5.0\n")
    out = tmp_path / "out"
    with Executor(inline=True) as ex:
        run_sweep(load_sweep(f), out, ex)
    assert main(["sweep", str(f), "--out", str(out), "--quiet"]) == 0
    summary = (out / "summary.md").read_text()
    assert "- executor: none this time (every run was found done" in summary, summary
    assert "missions/min" not in summary.split("- executor:")[1].splitlines()[0]
    assert "1 seed per cell" in summary
    capsys.readouterr()


def test_clear_words_for_inputs_of_the_wrong_kind(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    binary = tmp_path / "binary.pos"
    binary.write_bytes(bytes(range(256)) * 8)
    assert main(["calibrate", "gnss", "--static", str(binary), "--ref-lat", "1",
                 "--ref-lon", "1"]) == 2  # fmt: skip
    err = capsys.readouterr().err
    assert "not an RTKLIB .pos file: this line is not text" in err, err
    assert "\x00" not in err and "\ufffd" not in err

    empty = tmp_path / "empty.toml"
    empty.write_text("")
    assert main(["sweep", str(empty), "--out", str(tmp_path / "e")]) == 2
    assert "got nothing (the key is missing)" in capsys.readouterr().err

    nope = tmp_path / "nope.toml"
    rc = tmp_path / "rc.toml"
    rc.write_text(f'name = "t"\nscenarios = ["{DEFAULT}"]\nrobot_config = "{nope}"\n')
    assert main(["sweep", str(rc), "--out", str(tmp_path / "r")]) == 2
    err = capsys.readouterr().err
    assert err.count(str(nope)) == 1, err

    folder = tmp_path / "d.waypoints"
    folder.mkdir()
    for force in ([], ["--force"]):
        src = str(ROOT / "missions" / "default.kml")
        assert main(["mission", "convert", src, str(folder), *force]) == 2
        err = capsys.readouterr().err
        assert "is a directory" in err and "--force" not in err, err

    missing = tmp_path / "missing.pos"
    assert main(["calibrate", "gnss", "--drive", str(missing), "--reference", str(binary),
                 "--re-m", "0.1", "--ase-m", "0.1"]) == 2  # fmt: skip
    err = capsys.readouterr().err
    assert "cannot read" in err and "built-in default" not in err, err
    assert os.listdir(tmp_path)  # (nothing else asserted of the folder)


def test_a_sweep_refused_by_another_s_lock_leaves_that_sweep_s_folder_alone(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    # a review (round 18): two sweeps started at once into a new folder both took it as
    # made by them; the one refused by the other's lock then removed that sweep's lock
    # file, its runs/ and the folder. Only the call that made the folder removes it, and
    # only under its own lock.
    import contextlib

    import x6wd.app.sweep as sweep_cli
    from sim_backend.sweep import LOCK_FILE, out_dir_lock

    f = sweep_file(tmp_path, "seeds = 1\n[set]\nduration_s = 5.0\n")
    out = tmp_path / "o"
    real = sweep_cli.output_dir
    other = contextlib.ExitStack()

    def and_another_sweep_takes_it(path: Path) -> Path:
        made = real(path)
        other.enter_context(out_dir_lock(made))  # sweep A, started at the same moment
        (made / "runs").mkdir()
        return made

    monkeypatch.setattr(sweep_cli, "output_dir", and_another_sweep_takes_it)
    with other:
        code = main(["sweep", str(f), "--scheduler", f"tcp://127.0.0.1:{_closed_port()}",
                     "--out", str(out), "--quiet"])  # fmt: skip
        assert code == 2 and "another sweep" in capsys.readouterr().err
        assert (out / LOCK_FILE).is_file() and (out / "runs").is_dir()
