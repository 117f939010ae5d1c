"""Round 14 audit (F3, F4, F6, F7): bad inputs to sweep, calibrate and client end in one line
naming the file or option and exit 2; gap says the runs' spread is not defined for one log."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from x6wd.app import cli

ROOT = Path(__file__).resolve().parent.parent
SWEEP = ROOT / "config" / "sweeps" / "position_source.toml"


def _one_error_line(capsys: pytest.CaptureFixture[str], *names: str) -> str:
    err = capsys.readouterr().err
    assert "Traceback" not in err
    line = err.strip().splitlines()[-1]
    for name in names:
        assert name in line, line
    return line


@pytest.mark.parametrize("head", [b"# r\xe9sum\xe9 of the sweep\n", bytes(range(128, 256))])
def test_a_sweep_file_not_in_utf8_is_named_in_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], head: bytes
) -> None:
    bad = tmp_path / "latin1.toml"
    bad.write_bytes(head + SWEEP.read_bytes())
    rc = cli.main(["sweep", str(bad), "--out", str(tmp_path / "o"), "--quiet", "--workers", "1"])
    assert rc == 2
    _one_error_line(capsys, str(bad), "UTF-8")
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("address", ["notanaddr", "nosuchhost.invalid:8787", "127.0.0.1:99999"])
def test_a_bad_dashboard_address_is_refused_before_any_work(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], address: str
) -> None:
    out = tmp_path / "o"
    argv = ["sweep", str(SWEEP), "--out", str(out), "--quiet", "--workers", "1", "--seeds", "1"]
    assert cli.main([*argv, "--dashboard", address]) == 2
    _one_error_line(capsys, "--dashboard", address)
    assert not out.exists()


def test_gap_with_one_sim_log_says_the_spread_is_not_defined(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    sim = tmp_path / "sim"
    scenario = ROOT / "config" / "scenarios" / "open_field.toml"
    assert cli.main(["sim", str(scenario), "--out", str(sim), "--quiet"]) == 0
    out = tmp_path / "gap"
    real = ROOT / "tests" / "data" / "nmea" / "ublox-8.log"
    argv = ["gap", "--real", str(real), "--sim", str(sim / "gps.nmea"), "--out", str(out)]
    cli.main([*argv, "--quiet", "--no-figures"])
    printed = capsys.readouterr().out
    report = (out / "report.md").read_text(encoding="utf-8")
    for text in (printed, report):
        assert "nan%" not in text
    assert "own spread (sd over runs / average): not defined for one log" in report
    assert "own spread: not defined for one log" in printed


URBAN = ROOT / "tests" / "data" / "urban"
DRIVE = [
    "calibrate", "gnss", "--drive", str(URBAN / "rover_1Hz_spp.pos"),
    "--reference", str(URBAN / "reference_1Hz.pos"), "--re-m", "0.1", "--ase-m", "0.1",
]  # fmt: skip


@pytest.mark.parametrize(
    ("option", "name", "said"),
    [
        ("--plot", "lce.toml", "cannot write a .toml image"),
        ("--plot", "missing/lce.png", "cannot write there"),
        ("--map-csv", "missing/map.csv", "cannot write there"),
        ("--map-csv", ".", "cannot write there"),
    ],
)
def test_calibrate_gnss_checks_its_outputs_before_writing_any(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], option: str, name: str, said: str
) -> None:
    out, bad = tmp_path / "g.toml", str(tmp_path / name)
    assert cli.main([*DRIVE, "--out", str(out), option, bad]) == 2
    _one_error_line(capsys, option, bad, said)
    assert not out.exists()  # --out is not written when another output cannot be


def test_calibrate_odometry_names_a_fifo_and_an_unreadable_recording(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    circle = tmp_path / "circle.jsonl"
    circle.write_text("", encoding="utf-8")
    fifo = tmp_path / "straight.nmea"
    os.mkfifo(fifo)
    argv = ["calibrate", "odometry", "--circle", str(circle), "--straight"]
    assert cli.main([*argv, str(fifo)]) == 2
    _one_error_line(capsys, "--straight", str(fifo), "FIFO")
    if Path("/proc/self/mem").is_file():  # a regular file whose read fails (EIO)
        assert cli.main([*argv, "/proc/self/mem"]) == 2
        _one_error_line(capsys, "--straight", "/proc/self/mem", "Input/output error")


def _free_port() -> int:
    """A 127.0.0.1 port nothing listens on (bound, then closed)."""
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@pytest.mark.parametrize("n", ["-1", "1001"])
def test_client_log_checks_n_before_connecting(capsys: pytest.CaptureFixture[str], n: str) -> None:
    from x6wd.app import server

    # a port nothing listens on: the check must come first (it was exit 1 from the daemon)
    with pytest.raises(SystemExit) as e:
        cli.main(["client", "--port", str(_free_port()), "log", n])
    assert e.value.code == 2
    _one_error_line(capsys, "argument n", f"0..{server.LOG_TAIL_MAX}", n)


@pytest.mark.parametrize(
    ("action", "said"),
    [
        ("log", "0..1000 (default 50)"),
        ("drive", "[safety] manual_max_s: 5 s as shipped"),
        ("watch", "default: until Ctrl-C"),
    ],
)
def test_client_help_states_defaults_and_the_robots_limit(
    capsys: pytest.CaptureFixture[str], action: str, said: str
) -> None:
    with pytest.raises(SystemExit) as e:
        cli.main(["client", action, "--help"])
    assert e.value.code == 0
    assert said in " ".join(capsys.readouterr().out.split())
