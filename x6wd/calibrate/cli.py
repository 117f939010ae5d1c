"""``x6wd calibrate odometry --straight REC --circle REC [--out FRAGMENT.toml]``."""

from __future__ import annotations

import argparse
import sys
from datetime import UTC, datetime
from pathlib import Path

from x6wd.calibrate.odometry import calibrate, load_track
from x6wd.core import config as config_mod
from x6wd.core.errors import ConfigError


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``x6wd calibrate``: one subcommand per calibration."""
    sub = parser.add_subparsers(dest="what", metavar="WHAT", required=True)
    odo = sub.add_parser(
        "odometry",
        help="wheel diameters, effective track and odometry noise from two recordings",
        description="Estimate the [odometry] section from a straight-track and a circle-track "
        "recording whose fix records are the reference (RTK or simulator truth).",
    )
    odo.add_argument("--straight", required=True, help="recording of the straight-track passes")
    odo.add_argument("--circle", required=True, help="recording of the circle-track passes")
    odo.add_argument("--out", help="write the TOML fragment here (default: only print it)")
    odo.add_argument(
        "--config", help="robot configuration: its [odometry] counts_per_rev (default 1632)"
    )
    odo.add_argument("--counts-per-rev", type=int, help="encoder counts per wheel turn")
    odo.add_argument(
        "--ref-sigma-m",
        type=float,
        default=0.02,
        help="standard deviation of one reference fix per axis, m (default 0.02: RTK)",
    )
    odo.add_argument(
        "--stop-s", type=float, default=1.0, help="a stop between passes lasts at least this, s"
    )
    odo.add_argument(
        "--min-pass-m", type=float, default=2.0, help="shorter straight passes are ignored, m"
    )


def main(args: argparse.Namespace) -> int:
    """Run the chosen calibration; 0 on success (errors are X6wdError, exit code 2)."""
    cpr = args.counts_per_rev
    if cpr is None:
        cfg = config_mod.load(args.config) if args.config else config_mod.Config()
        cpr = cfg.odometry.counts_per_rev
    if cpr < 1:
        raise ConfigError(f"--counts-per-rev must be >= 1, got {cpr}")
    result = calibrate(
        load_track(args.straight),
        load_track(args.circle),
        counts_per_rev=cpr,
        ref_sigma_m=args.ref_sigma_m,
        stop_s=args.stop_s,
        min_pass_m=args.min_pass_m,
    )
    stamp = datetime.now(UTC).strftime("%Y-%m-%dT%H:%M:%SZ")
    text = result.toml(
        f"x6wd calibrate odometry, {stamp}\nstraight: {args.straight}\ncircle: {args.circle}"
    )
    if result.dropped_passes:
        print(
            f"x6wd calibrate: {result.dropped_passes} passes without reference fixes in the "
            "stops around them were left out",
            file=sys.stderr,
        )
    sys.stdout.write(text)
    if args.out:
        Path(args.out).write_text(text, encoding="utf-8")
    return 0
