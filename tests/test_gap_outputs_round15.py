"""`x6wd gap`'s text outputs on a full disk (outside review of 08178ff): report.json,
effects.toml, validation.json and report.md were written unguarded, so a full disk gave a
21-line traceback (the round-14 test passed only because its disk filled in the figures
first). Each output here is a link to /dev/full (ENOSPC on every write, no root needed):
one line naming that file, exit 2."""

from __future__ import annotations

from pathlib import Path

import pytest

from x6wd.app.cli import main

ROOT = Path(__file__).resolve().parents[1]
REAL_LOG = ROOT / "tests" / "data" / "nmea" / "ublox-8.log"


@pytest.fixture(scope="module")
def sim_log(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("sim")
    argv = ["sim", str(ROOT / "config" / "scenarios" / "open_field.toml"), "--out", str(out)]
    assert main([*argv, "--duration", "900", "--quiet"]) == 0
    return out / "gps.nmea"


@pytest.mark.parametrize("name", ["report.json", "effects.toml", "validation.json", "report.md"])
def test_each_gap_text_output_on_a_full_disk_is_one_line_naming_it(
    tmp_path: Path, sim_log: Path, capsys: pytest.CaptureFixture[str], name: str
) -> None:
    out = tmp_path / "g"
    out.mkdir()
    (out / name).symlink_to("/dev/full")
    capsys.readouterr()
    argv = ["gap", "--real", str(REAL_LOG), "--sim", str(sim_log), "--out", str(out)]
    assert main([*argv, "--quiet", "--no-figures"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert "Traceback" not in "\n".join(err)
    assert name in err[-1] and "No space left on device" in err[-1], err[-1]
