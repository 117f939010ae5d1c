"""Hardware in the loop's wheel encoders: the motor board's counters follow the simulated
vehicle with the scenario's ``[encoders]`` truth, as fast-time simulation's do."""

from __future__ import annotations

import math
import time
from pathlib import Path

import pytest
import serial

from sim_backend import hil
from tests.conftest import ROOT

DEFAULT_SCENARIO = ROOT / "config" / "scenarios" / "default.toml"
LEFT_D_M, RIGHT_D_M, CPR = 0.10, 0.15, 1000  # far from the defaults (0.1212, 0.1188, 1632)


def test_hil_encoders_count_with_the_scenarios_wheel_diameters(tmp_path: Path) -> None:
    # an outside audit: HIL built its EncoderSim with the default parameters, so a
    # scenario's [encoders] (used by x6wd sim) was silently ignored on the motor board
    scenario = tmp_path / "encoders.toml"
    scenario.write_text(
        DEFAULT_SCENARIO.read_text()
        + f"\n[encoders]\ncounts_per_rev = {CPR}\nleft_diameter_m = {LEFT_D_M}\n"
        + f"right_diameter_m = {RIGHT_D_M}\nk_left_m = 0.0\nk_right_m = 0.0\n"
    )
    world = hil.HilWorld(
        hil.HilParams(str(scenario), motor_tau_s=0.0, motor_watchdog_ms=300, gps_baud=115200)
    )
    try:
        start = world.vehicle.state
        with serial.Serial(world.plug_motor_board(), 115200, timeout=1.0) as port:

            def ask(line: bytes) -> list[str]:
                port.write(line)
                reply = port.readline().decode()
                assert reply.startswith("OK"), reply
                return reply.split()

            ask(b"M 60 60\n")
            t_end = time.monotonic() + 1.0  # straight ahead; E keeps the watchdog fed
            while time.monotonic() < t_end:
                ask(b"E\n")
                time.sleep(0.05)
            ask(b"M 0 0\n")
            time.sleep(0.2)  # the physics thread applies the stop
            _, _seq, left, right = ask(b"E\n")
        end = world.vehicle.state
    finally:
        world.close()
    travel_m = math.hypot(end.east_m - start.east_m, end.north_m - start.north_m)
    assert travel_m > 0.3
    # both sides rolled the body's travel: counts = travel * CPR / (pi * D) per side
    for counts, diameter_m in ((int(left), LEFT_D_M), (int(right), RIGHT_D_M)):
        rolled_m = counts * math.pi * diameter_m / CPR
        assert rolled_m == pytest.approx(travel_m, rel=0.02), (counts, travel_m)
