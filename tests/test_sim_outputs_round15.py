"""Two full-disk guards that no test watched (outside review of 08178ff; each removed, the
round-14 tests still passed): `x6wd plot --format png` and a mission's summary.json."""

from __future__ import annotations

import errno
from pathlib import Path

import pytest

from sim_backend.world import load_world
from x6wd.app.cli import main

ROOT = Path(__file__).resolve().parents[1]
SCENARIOS = ROOT / "config" / "scenarios"


def _last_line_names(capsys: pytest.CaptureFixture[str], name: str) -> None:
    err = capsys.readouterr().err.strip().splitlines()
    assert "Traceback" not in "\n".join(err)
    assert name in err[-1] and "No space left on device" in err[-1], err[-1]


def test_plot_png_into_a_full_disk_is_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    argv = ["sim", str(SCENARIOS / "default.toml"), "--out", str(tmp_path / "s"), "--quiet"]
    assert main([*argv, "--duration", "20"]) == 1  # 20 s: the mission is not completed
    (tmp_path / "p").mkdir()
    (tmp_path / "p" / "recording.png").symlink_to("/dev/full")  # ENOSPC on every write
    capsys.readouterr()
    plot = ["plot", str(tmp_path / "s" / "recording.jsonl"), "--out", str(tmp_path / "p")]
    assert main([*plot, "--format", "png"]) == 2
    _last_line_names(capsys, "recording.png")


def test_a_missions_summary_json_on_a_full_disk_is_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    # the sim removes a link named summary.json at its start (its own output), so the disk
    # is made full for that one file's write
    write_text = Path.write_text

    def full(self: Path, *args: object, **kwargs: object) -> int:
        if self.name == "summary.json":
            raise OSError(errno.ENOSPC, "No space left on device")
        return write_text(self, *args, **kwargs)  # type: ignore[arg-type]

    monkeypatch.setattr(Path, "write_text", full)
    load_world(SCENARIOS / "default.toml")  # the scenario reads before the patch matters
    argv = ["sim", str(SCENARIOS / "default.toml"), "--out", str(tmp_path / "s"), "--quiet"]
    assert main([*argv, "--duration", "5"]) == 2
    _last_line_names(capsys, "summary.json")
