"""``x6wd sim``: run a scenario in fast time on the robot engine or the receiver engine.

The engine is chosen before anything heavy is imported: a static survey on the receiver
engine never loads the robot's code (see :mod:`sim_backend.survey`).
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

from sim_backend.runs import (
    ENGINES,
    Summary,
    check_mission_geofence,
    engine_for,
    engine_note,
    sky_warnings,
)
from sim_backend.world import (
    MAX_DURATION_S,
    GnssSettings,
    load_world,
    robot_config_notes,
    with_robot_config,
)

MIN_GNSS_RATE_HZ: float = next(
    f.metadata["min"] for f in dataclasses.fields(GnssSettings) if f.name == "rate_hz"
)
"""The lowest ``[gnss] rate_hz`` a scenario takes (1 Hz): below it "lower rate_hz" is no advice."""


def _duration_s(text: str) -> float:
    """``--duration``: a positive, finite number of simulated seconds up to 30 days (the
    scenario's ``duration_s`` cap; a run's per-tick arrays grow with it)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number of seconds: {text!r}") from None
    if not (0.0 < value <= MAX_DURATION_S):  # also NaN and infinities
        raise argparse.ArgumentTypeError(
            f"must be more than 0 and at most {MAX_DURATION_S:.0f} s (30 days), got {text}"
        )
    return value


def _seed(text: str) -> int:
    """``--seed``: a whole number within the scenario's ``seed`` range, 0..2**63 - 1."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a whole number: {text!r}") from None
    if not 0 <= value <= 2**63 - 1:
        raise argparse.ArgumentTypeError(
            f"must be within 0..2**63 - 1 (a scenario's seed), got {text}"
        )
    return value


def _progress_bar(stream: Any) -> Callable[[float, float], None]:
    tty = bool(getattr(stream, "isatty", lambda: False)())
    state = {"last": -1}

    def show(t_s: float, total_s: float) -> None:
        frac = min(1.0, t_s / total_s) if total_s > 0 else 1.0
        pct = int(frac * 100)
        if tty:
            bar = "#" * (pct // 4) + "-" * (25 - pct // 4)
            stream.write(f"\r[{bar}] {pct:3d}% t={t_s:7.1f} s")
            if frac >= 1.0 or pct == 100:
                stream.write("\n")
            stream.flush()
        elif pct // 25 != state["last"]:
            state["last"] = pct // 25
            stream.write(f"sim: {pct}% (t={t_s:.1f} s)\n")
            stream.flush()

    return show


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """``x6wd sim SCENARIO.toml [--out DIR] [--seed N] [--duration S]``."""
    parser.add_argument("scenario", help="scenario TOML file (see config/scenarios/)")
    parser.add_argument("--out", default="sim-out", help="output directory (default: sim-out)")
    parser.add_argument("--seed", type=_seed, default=None, help="override the scenario's seed")
    parser.add_argument(
        "--duration",
        type=_duration_s,
        default=None,
        help="override the duration (simulated s, at most 30 days)",
    )
    parser.add_argument(
        "--config",
        default=None,
        help="robot configuration (e.g. config/x6wd.toml) whose [navigation], [safety], "
        "[failsafe], [odometry] and [gnss_noise] the robot uses, under the scenario's own "
        "keys; default: the built-in defaults, which are config/x6wd.toml's",
    )
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    parser.add_argument(
        "--engine",
        choices=ENGINES,
        default="auto",
        help="robot: the robot's whole loop (at 20 Hz or more on a mission); receiver: the "
        "receiver alone at a standing antenna (a static survey, ~20x faster; it ignores the "
        "robot's settings, with a warning); auto (default): receiver for a scenario without "
        "waypoints, unless it (or --config) sets what only the robot reads ([navigation], "
        "[safety], [failsafe], [odometry], [gnss_noise], [encoders], compass [[effects]]: "
        "said in one note); robot otherwise",
    )


def uart_drop_text(summary: Summary, baud: int, rate_hz: float) -> str:
    """The summary's line on the sentences the receiver's UART dropped (either engine's
    summary; ``baud`` the line's, bit/s; ``rate_hz`` the receiver's), "" when it dropped none:
    how many, of how many and of which types, and where the robot engine counted them the
    fixes' delay after their epoch and the valid fixes that lost their GGA. The advice names
    rate_hz only where it can be lowered (above :data:`MIN_GNSS_RATE_HZ`)."""
    extra = summary.extra
    dropped = extra.get("uart_dropped_sentences") or 0
    if not dropped:
        return ""
    total = extra.get("uart_sentences")
    text = f"  UART line           {baud} baud dropped {dropped:,}"
    text += (f" of {total:,}" if total else "") + " sentences"
    by_type = extra.get("uart_dropped_by_type") or {}
    if by_type:
        text += " (" + ", ".join(f"{name} {n:,}" for name, n in by_type.items()) + ")"
    delay_s = (extra.get("fix_delay_s") or {}).get("mean")
    if delay_s is not None:
        text += f"; fixes {delay_s:.2f} s after their epoch on average"
    no_gga = extra.get("fixes_without_gga") or 0
    if no_gga:
        text += (
            f"; {no_gga:,} of {summary.fixes_valid:,} fixes came without their GGA (no"
            f" satellite count: mean satellites used is of the other"
            f" {summary.fixes_valid - no_gga:,}; their HDOP is the last GSA's received)"
        )
    lower = " or lower rate_hz" if rate_hz > MIN_GNSS_RATE_HZ else ""
    return text + ": raise [gnss] baud" + lower


EXIT_REFUSED = 2
"""A scenario or mission that cannot run, refused before the run (one line on stderr, as
every X6wdError), or a mission the robot rejected in the run (which then stops there)."""


def main(args: argparse.Namespace) -> int:
    """Run the subcommand; 0 when the mission completed (or a static survey ran), 1 if it
    did not, 2 when the mission was refused: before the run (a waypoint beyond the geofence,
    as every bad input) or by the robot in it."""
    scenario = world = load_world(args.scenario, check_rates=not args.config)
    if args.config:
        world = with_robot_config(world, args.config)
        for note in robot_config_notes(world, args.config):
            print(f"x6wd sim: note: {note}", file=sys.stderr)
    engine = engine_for(world, args.engine)
    said = engine_note(world, args.engine, scenario=scenario, robot_config=args.config)
    if said is not None:  # a survey's robot-only settings: run (auto) or ignored (receiver)
        print(f"x6wd sim: {said[0]}: {said[1]}", file=sys.stderr)
    check_mission_geofence(world)  # the robot would refuse it: say so now, not after the run
    for note in world.mission_notes:  # what the mission file holds that the robot ignores
        print(f"x6wd sim: note: {note}", file=sys.stderr)
    for warning in sky_warnings(world, args.duration):
        print(f"x6wd sim: warning: {warning}", file=sys.stderr)
    progress = None if args.quiet else _progress_bar(sys.stderr)
    try:
        if engine == "receiver":
            from sim_backend.survey import run_survey

            summary = run_survey(world, args.out, args.seed, args.duration, progress)
        else:
            from sim_backend.mission import run_mission

            summary = run_mission(world, args.out, args.seed, args.duration, progress)
    except KeyboardInterrupt:  # said, then exit 130 (x6wd.app.cli)
        print(
            f"\nx6wd sim: interrupted: {Path(args.out).resolve()} holds the run so far"
            " (its NMEA and recording; no summary, truth or plot)",
            file=sys.stderr,
        )
        raise
    print(summary.text())
    uart_line = uart_drop_text(summary, world.gnss.baud, world.gnss.rate_hz)
    if uart_line:
        print(uart_line)
    print(f"  outputs in {Path(args.out).resolve()}")
    if summary.waypoint_count == 0:
        return 0
    if summary.extra.get("mission_rejected"):
        return EXIT_REFUSED
    return 0 if summary.completed else 1
