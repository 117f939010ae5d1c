"""Round 15 audit of the sweep's and the calibration's outputs: a full disk while the sweep
report or the LCE map/plot is written is one line naming the file, exit 2, never a traceback,
and no partly written file is left (F1, F2); calibrate's output check leaves a dangling link
alone, so its target gets the fragment (F3); ``--dashboard`` refuses an IPv6 host in one line
and takes a bare port as Dask does (F4)."""

from __future__ import annotations

import errno
import os
import re
import shutil
from collections.abc import Callable
from pathlib import Path

import pytest

from tests.conftest import fill_disk
from x6wd.app import cli
from x6wd.app.sweep import _check_dashboard
from x6wd.core.errors import ConfigError

ROOT = Path(__file__).resolve().parents[1]
SWEEP = ROOT / "config" / "sweeps" / "position_source.toml"
SWEEP_ARGS = ["--seeds", "1", "--workers", "1", "--quiet"]
URBAN = ROOT / "tests" / "data" / "urban"
DRIVE = [
    "calibrate", "gnss", "--drive", str(URBAN / "rover_1Hz_spp.pos"),
    "--reference", str(URBAN / "reference_1Hz.pos"), "--re-m", "0.1", "--ase-m", "0.1",
]  # fmt: skip
DASHBOARD_PORT = 21450  # this round's range: 21450-21499


@pytest.fixture(scope="module")
def done_sweep(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A finished one-seed sweep (4 runs) whose runs a later sweep finds done."""
    out = tmp_path_factory.mktemp("done") / "w"
    assert cli.main(["sweep", str(SWEEP), "--out", str(out), *SWEEP_ARGS]) == 0
    return out


def _runs_of(done: Path, out: Path) -> Path:
    """``out`` holding ``done``'s plan and finished runs, none of its report."""
    out.mkdir(parents=True)
    for name in ("runs", "cells"):
        shutil.copytree(done / name, out / name)
    shutil.copy(done / "sweep.json", out / "sweep.json")
    return out


def _one_line_exit_2(
    capsys: pytest.CaptureFixture[str], argv: list[str], file_name: str
) -> tuple[str, str]:
    """``x6wd argv`` exits 2, its last stderr line naming a file matching ``file_name`` (a
    regular expression) and ENOSPC, no traceback; returns that line and the stdout."""
    assert cli.main(argv) == 2
    out, err = capsys.readouterr()
    assert "Traceback" not in err
    line = err.strip().splitlines()[-1]
    assert re.search(f"{file_name}.*No space left on device", line), line
    return line, out


def test_the_sweep_report_on_a_full_disk_is_one_line_and_leaves_no_part(
    done_sweep: Path, tiny_disk: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = _runs_of(done_sweep, tiny_disk / "w")
    fill_disk(tiny_disk, 24)  # the tables fit, a figure does not: the report fails half-way
    line, _ = _one_line_exit_2(
        capsys, ["sweep", str(SWEEP), "--out", str(out), *SWEEP_ARGS], f"{out}/"
    )
    named = re.search(rf"{out}/([\w.]+\.png)", line)  # a figure's, after the tables
    assert named is not None, line
    assert (out / "results.csv").exists()
    assert not (out / named.group(1)).exists()  # no truncated figure left as the sweep's


@pytest.mark.parametrize("name", ["results.csv", "completion.png", "summary.md"])
def test_each_sweep_report_file_into_dev_full_is_named(
    done_sweep: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], name: str
) -> None:
    out = _runs_of(done_sweep, tmp_path / "w")
    (out / name).symlink_to("/dev/full")
    _one_line_exit_2(capsys, ["sweep", str(SWEEP), "--out", str(out), *SWEEP_ARGS], name)
    assert (out / name).is_symlink()  # the user's link is left, not removed


def test_the_lce_map_on_a_full_disk_is_one_line_and_removed(
    tiny_disk: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    fill_disk(tiny_disk, 8)  # the fragment (one 4 KiB page) fits, the map (~11 kB) does not
    out, csv = tiny_disk / "g.toml", tiny_disk / "map.csv"
    argv = [*DRIVE, "--out", str(out), "--map-csv", str(csv)]
    line, printed = _one_line_exit_2(capsys, argv, "map.csv")
    assert "partly written file was removed" in line
    assert not csv.exists()
    assert out.read_text(encoding="utf-8") == printed  # the whole fragment, written first


def test_the_lce_plot_into_dev_full_is_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    plot = tmp_path / "lce.png"
    plot.symlink_to("/dev/full")
    _one_line_exit_2(capsys, [*DRIVE, "--plot", str(plot)], "lce.png")
    assert plot.is_symlink()


def test_a_dangling_link_as_calibrates_out_is_written_through(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    (tmp_path / "target").mkdir()
    (tmp_path / "dl").mkdir()
    link = tmp_path / "dl" / "calib.toml"
    link.symlink_to(Path("..") / "target" / "calib.toml")
    target = tmp_path / "target" / "calib.toml"
    refused = [*DRIVE, "--out", str(link), "--map-csv", str(tmp_path / "missing" / "m.csv")]
    assert cli.main(refused) == 2
    assert "--map-csv" in capsys.readouterr().err
    assert link.is_symlink() and not target.exists()  # the check made and removed nothing
    assert cli.main([*DRIVE, "--out", str(link)]) == 0
    assert link.is_symlink()
    assert target.read_text(encoding="utf-8") == capsys.readouterr().out  # the fragment


@pytest.mark.parametrize("address", ["[::1]:21451", "::1:21452"])
def test_an_ipv6_dashboard_is_refused_in_one_line_before_any_work(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], address: str
) -> None:
    out = tmp_path / "o"
    assert (
        cli.main(["sweep", str(SWEEP), "--out", str(out), *SWEEP_ARGS, "--dashboard", address]) == 2
    )
    err = capsys.readouterr().err
    assert "Traceback" not in err
    assert re.search(rf"--dashboard {re.escape(address)}: an IPv6 address .*not supported", err)
    assert not out.exists()


@pytest.mark.parametrize("address", ["21453", ":21453", "127.0.0.1:21453", "localhost:21453"])
def test_the_dashboard_check_takes_what_dask_takes(address: str) -> None:
    _check_dashboard(address)  # no ConfigError


@pytest.mark.parametrize("address", ["", "host:", "99999", "[127.0.0.1]:21453"])
def test_the_dashboard_check_refuses_the_rest(address: str) -> None:
    with pytest.raises(ConfigError, match=f"--dashboard {re.escape(address)}: "):
        _check_dashboard(address)


def test_a_sweep_with_a_bare_dashboard_port_runs(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    argv = ["sweep", str(SWEEP), "--out", str(tmp_path / "o"), *SWEEP_ARGS]
    assert cli.main([*argv, "--dashboard", str(DASHBOARD_PORT)]) == 0, capsys.readouterr().err


def _refused(path: str) -> None:
    raise PermissionError(errno.EACCES, os.strerror(errno.EACCES))


def _half_written(path: str) -> None:
    Path(path).write_text("half", encoding="utf-8")
    raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))


def test_only_a_partly_written_output_is_removed(tmp_path: Path) -> None:
    """A file the write never opened (refused) is the user's and stays; one a full disk cut
    short goes, in calibrate's outputs and the sweep report's alike."""
    from sim_backend.sweep_report import _report_file
    from x6wd.calibrate.cli import _write_output

    def report_write(write: Callable[[str], None]) -> Callable[[str], None]:
        def run(path: str) -> None:  # the sweep report's wrapper around the same write
            with _report_file(Path(path)):
                write(path)

        return run

    for wrap in (lambda write: lambda p: _write_output(p, write), report_write):
        kept, cut = tmp_path / "kept.csv", tmp_path / "cut.csv"
        kept.write_text("mine", encoding="utf-8")
        with pytest.raises(ConfigError, match=r"kept\.csv.*Permission denied"):
            wrap(_refused)(str(kept))
        assert kept.read_text(encoding="utf-8") == "mine"
        with pytest.raises(ConfigError, match=r"cut\.csv.*No space.*partly written.*removed"):
            wrap(_half_written)(str(cut))
        assert not cut.exists()
