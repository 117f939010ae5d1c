"""A scenario's ``[mission] file`` is read once (review of c30d4e7/9fbd8e4/f1ffecd, finding 1).

``x6wd sim --config config/x6wd.toml`` built the world, then rebuilt it under the robot
configuration and read the mission file again: a FIFO whose writer was started first was
drained by the first read and the second said "no writer has it open (... start the writer
first)", exit 2, while the same run without ``--config`` ran. Hardware in the loop read the
scenario twice too (:meth:`HilParams.from_config` to check it, :class:`HilWorld` to run it).
Real FIFOs, a real writer process, the real CLI.
"""

from __future__ import annotations

import os
import subprocess
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest

from sim_backend import hil
from sim_backend.world import load_world, merge_fragment
from x6wd.app import cli
from x6wd.core.config import SimConfig

ROOT = Path(__file__).resolve().parents[1]
MISSION = "lat,lon\n51.7522,-1.2577\n51.7522,-1.2574\n"
WAYPOINTS = ((51.7522, -1.2577), (51.7522, -1.2574))
SCENARIO = (
    'name = "fifo"\nstart_utc = "2020-01-01T12:00:00Z"\nduration_s = 30.0\nseed = 1\n'
    "[origin]\nlat_deg = 51.752\nlon_deg = -1.2577\nalt_m = 60.0\n"
    '[mission]\nfile = "m.csv"\n'
)


@contextmanager
def fifo_scenario(folder: Path) -> Iterator[Path]:
    """A scenario whose mission file is a FIFO with a writer already waiting to write it once
    (as ``cat m.csv > fifo &`` started first)."""
    (folder / "src.csv").write_text(MISSION, encoding="utf-8")
    fifo = folder / "m.csv"
    os.mkfifo(fifo)
    scenario = folder / "s.toml"
    scenario.write_text(SCENARIO, encoding="utf-8")
    writer = subprocess.Popen(["sh", "-c", f"cat '{folder / 'src.csv'}' > '{fifo}'"])
    try:
        time.sleep(0.3)  # the writer is in open(), waiting for a reader
        yield scenario
    finally:
        try:
            writer.wait(5)
        except subprocess.TimeoutExpired:  # never read: still waiting in open()
            writer.kill()
            writer.wait(5)


def test_sim_with_a_robot_config_reads_a_fifo_mission_once(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    with fifo_scenario(tmp_path) as scenario:
        argv = ["sim", str(scenario), "--quiet", "--duration", "20", "--out", str(tmp_path / "o")]
        rc = cli.main([*argv, "--config", str(ROOT / "config" / "x6wd.toml")])
    err = capsys.readouterr().err
    assert rc in (0, 1), err  # ran (before: 2, "no writer has it open")
    assert "writer" not in err, err


def test_a_rebuilt_world_keeps_its_mission_and_a_changed_mission_is_read(tmp_path: Path) -> None:
    with fifo_scenario(tmp_path) as scenario:
        world = load_world(scenario)
    assert world.mission.waypoints == WAYPOINTS
    frag = tmp_path / "seed.toml"
    frag.write_text("seed = 2\n", encoding="utf-8")
    again = merge_fragment(world, frag)  # the FIFO is not read again
    assert again.seed == 2 and again.mission.waypoints == WAYPOINTS
    (tmp_path / "other.csv").write_text("51.7523,-1.2576\n", encoding="utf-8")
    frag.write_text('[mission]\nfile = "other.csv"\n', encoding="utf-8")
    assert merge_fragment(world, frag).mission.waypoints == ((51.7523, -1.2576),)


def test_hardware_in_the_loop_reads_a_fifo_mission_once(tmp_path: Path) -> None:
    with fifo_scenario(tmp_path) as scenario:
        params = hil.HilParams.from_config(SimConfig(scenario=str(scenario)))
        world = hil.HilWorld(params)  # before: its second read found no writer
    try:
        assert world.scenario.mission.waypoints == WAYPOINTS
        assert world.scenario is params.load_world()
    finally:
        world.close()


def test_the_daemons_device_check_and_world_read_a_fifo_mission_once(tmp_path: Path) -> None:
    """The daemon's path: :meth:`Devices.check` at start-up, then the world on first open.
    Before, each built its own parameters from ``[sim]`` and the second read found no
    writer (DeviceUnavailable / ConfigError "no writer has it open")."""
    from drivers.registry import Devices
    from x6wd.core.config import Config

    with fifo_scenario(tmp_path) as scenario:
        devices = Devices(Config(sim=SimConfig(scenario=str(scenario))))
        devices.check("sim://", "gps")
        try:
            world = devices.backend("sim")
            assert world.scenario.mission.waypoints == WAYPOINTS
        finally:
            devices.close()
