"""Round 14 audit of the commands' outputs: an interrupted ``x6wd sim`` leaves no earlier run's
truth/summary/track beside its own cut recording (F1); a full disk is one line naming the
file and exit 2 in sim (both engines), gap, plot and sweep, never a traceback (F2); an empty
path option is exit 2 naming it, not the current folder or "no file" (F5)."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from sim_backend.mission import run_mission
from sim_backend.survey import SIM_OUTPUTS, run_survey
from sim_backend.sweep import write_atomic
from sim_backend.world import load_world
from tests.conftest import fill_disk
from x6wd.app.cli import main
from x6wd.core.errors import ConfigError

ROOT = Path(__file__).resolve().parents[1]
SCENARIOS = ROOT / "config" / "scenarios"
REAL_LOG = ROOT / "tests" / "data" / "nmea" / "ublox-8.log"
EARLIER = ("truth.csv", "summary.json", "track.png")


def _interrupt(t_s: float, _total_s: float) -> None:
    if t_s > 2.0:
        raise KeyboardInterrupt


@pytest.mark.parametrize(
    ("scenario", "run"),
    [("default", run_mission), ("open_field", run_survey)],
    ids=["robot", "receiver"],
)
def test_an_interrupted_sim_leaves_no_earlier_runs_outputs(
    tmp_path: Path, scenario: str, run
) -> None:
    world = load_world(SCENARIOS / f"{scenario}.toml")
    run(world, tmp_path, 1, 5.0, None)
    assert all((tmp_path / name).exists() for name in SIM_OUTPUTS)
    (tmp_path / "notes.txt").write_text("mine")
    with pytest.raises(KeyboardInterrupt):
        run(world, tmp_path, 2, 600.0, _interrupt)
    assert [n for n in EARLIER if (tmp_path / n).exists()] == []
    assert (tmp_path / "recording.jsonl").exists()
    assert (tmp_path / "notes.txt").read_text() == "mine"  # only the sim's own names go


@pytest.fixture
def full_disk(tiny_disk: Path) -> Path:
    """A 512 KiB tmpfs filled but for 24 KiB (root only, as CI runs)."""
    fill_disk(tiny_disk, 24)
    return tiny_disk


def _one_line_exit_2(capsys, argv: list[str], file_name: str) -> None:
    """``x6wd argv`` exits 2, its last stderr line naming a file matching ``file_name`` (a
    regular expression) and the error; no traceback."""
    assert main(argv) == 2
    err_lines = capsys.readouterr().err.strip().splitlines()
    assert "Traceback" not in "\n".join(err_lines)
    assert re.search(f"{file_name}.*No space left on device", err_lines[-1]), err_lines[-1]


@pytest.mark.parametrize(
    ("scenario", "file_name"),
    [("default", "recording.jsonl"), ("open_field", "/s/(gps.nmea|recording.jsonl)")],
    ids=["robot", "receiver"],
)
def test_sim_on_a_full_disk_is_one_line_naming_the_file(
    full_disk: Path, capsys, scenario: str, file_name: str
) -> None:
    argv = ["sim", str(SCENARIOS / f"{scenario}.toml"), "--out", str(full_disk / "s")]
    _one_line_exit_2(capsys, [*argv, "--duration", "3600", "--quiet"], file_name)


def test_a_close_error_does_not_hide_the_missions_own(full_disk: Path) -> None:
    world = load_world(SCENARIOS / "default.toml")
    with pytest.raises(Exception, match="recording") as caught:  # the recorder's, not close's
        run_mission(world, full_disk / "s", 1, 3600.0, None)
    assert "recording.jsonl" in str(caught.value)


def _survey(out: Path, capsys: pytest.CaptureFixture[str]) -> Path:
    """A 900 s open-field survey written to ``out`` (its output cleared from capsys)."""
    argv = ["sim", str(SCENARIOS / "open_field.toml"), "--out", str(out), "--quiet"]
    assert main([*argv, "--duration", "900"]) == 0
    capsys.readouterr()
    return out


def test_gap_plot_and_sweep_on_a_full_disk_are_one_line(
    full_disk: Path, tmp_path: Path, capsys
) -> None:
    sim = _survey(tmp_path / "sim", capsys)
    _one_line_exit_2(
        capsys,
        [
            "gap",
            "--real",
            str(REAL_LOG),
            "--sim",
            str(sim / "gps.nmea"),
            "--out",
            str(full_disk / "g"),
            "--quiet",
        ],
        f"{full_disk}/g/",
    )
    _one_line_exit_2(
        capsys, ["plot", str(sim / "recording.jsonl"), "--out", str(full_disk / "p")], "/p/"
    )
    # the page cut short is removed, not left as the result (audit round 21)
    assert not (full_disk / "p" / "recording.html").exists()
    _one_line_exit_2(
        capsys,
        [
            "sweep",
            str(ROOT / "config" / "sweeps" / "position_source.toml"),
            "--out",
            str(full_disk / "w"),
            "--seeds",
            "1",
            "--workers",
            "1",
            "--quiet",
        ],
        f"{full_disk}/w/",
    )


def test_sweeps_atomic_write_on_a_full_disk_names_the_file(full_disk: Path) -> None:
    with pytest.raises(ConfigError, match=r"runs\.json.*No space left on device"):
        write_atomic(full_disk / "runs.json", "x" * (64 * 1024))
    assert sorted(p.name for p in full_disk.iterdir()) == ["fill"]  # no temporary left


def test_plot_and_gap_into_dev_full_name_the_file(tmp_path: Path, capsys) -> None:
    """Without root: an output that is a link to /dev/full (ENOSPC on every write)."""
    sim = _survey(tmp_path / "sim", capsys)
    (tmp_path / "p").mkdir()
    (tmp_path / "p" / "recording.html").symlink_to("/dev/full")
    _one_line_exit_2(
        capsys,
        ["plot", str(sim / "recording.jsonl"), "--out", str(tmp_path / "p"), "--format", "html"],
        "recording.html",
    )
    (tmp_path / "g").mkdir()
    (tmp_path / "g" / "scatter.png").symlink_to("/dev/full")
    _one_line_exit_2(
        capsys,
        [
            "gap",
            "--real",
            str(REAL_LOG),
            "--sim",
            str(sim / "gps.nmea"),
            "--out",
            str(tmp_path / "g"),
            "--quiet",
        ],
        "scatter.png",
    )


@pytest.mark.parametrize(
    ("argv", "option"),
    [
        (["sim", str(SCENARIOS / "default.toml"), "--out", ""], "--out"),
        (["sim", str(SCENARIOS / "default.toml"), "--config", "", "--out", "o"], "--config"),
        (["gap", "--real", str(REAL_LOG), "--sim", "x.nmea", "--out", ""], "--out"),
        (["gap", "--real", ""], "--real"),
        (["plot", "x.jsonl", "--out", ""], "--out"),
    ],
    ids=["sim-out", "sim-config", "gap-out", "gap-real", "plot-out"],
)
def test_an_empty_path_option_is_exit_2_naming_it(
    tmp_path: Path, monkeypatch, capsys, argv: list[str], option: str
) -> None:
    monkeypatch.chdir(tmp_path)
    assert main([*argv, "--quiet"] if argv[0] != "plot" else argv) == 2
    assert f"{option}: empty" in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []  # nothing written into the current folder


def test_output_dir_refuses_an_empty_path() -> None:
    from x6wd.core.outdir import output_dir

    with pytest.raises(ConfigError, match="empty path"):
        output_dir("")


def test_a_ctrl_c_in_x6wd_sim_says_what_it_left(tmp_path: Path) -> None:
    # an outside audit (round 22): exit 130 and nothing said, the progress bar's "0%" last
    from tests.test_sweep import ctrl_c_when

    out = tmp_path / "o"
    args = ["sim", str(ROOT / "config" / "scenarios" / "zigzag.toml"), "--out", str(out)]
    nmea = out / "gps.nmea"
    returncode, err = ctrl_c_when(
        args, lambda _pid: nmea.exists() and nmea.stat().st_size > 0, 120.0, group=True
    )
    assert returncode == 130, err
    assert f"x6wd sim: interrupted: {out.resolve()} holds the run so far" in err, err
    assert "Traceback" not in err
    assert not (out / "summary.json").exists()
