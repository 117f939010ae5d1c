"""``x6wd mission``: mission files offline, without a robot.

``x6wd mission show FILE`` prints the waypoints x6wd reads from a file (and the legs'
lengths); ``x6wd mission convert IN OUT`` rewrites a mission in another format. The formats
are chosen by extension (``.waypoints`` QGC WPL 110, ``.gpx``, ``.csv``, ``.kml`` read only;
:mod:`x6wd.core.mission_files`), or by ``--from``/``--to``.

Exit codes: 0 success, 2 a file that cannot be read, parsed or written (one line on stderr).
"""

from __future__ import annotations

import argparse
import sys
from typing import TextIO

from x6wd.core.errors import ParseError
from x6wd.core.geodesy import great_circle_m
from x6wd.core.mission_files import (
    PARSERS,
    WRITERS,
    format_content,
    format_of,
    load_file,
    save_file,
)

EXIT_OK = 0
EXIT_USAGE = 2


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of ``x6wd mission``."""
    sub = parser.add_subparsers(dest="mission_action", metavar="ACTION", required=True)
    p = sub.add_parser("show", help="print the waypoints read from a mission file")
    p.add_argument("file", help="mission file (.waypoints, .plan, .gpx, .csv, .kml)")
    p.add_argument("--from", dest="from_fmt", choices=sorted(PARSERS), help="format of FILE")
    p = sub.add_parser(
        "convert", help="convert a mission file (e.g. .kml or .gpx to .waypoints for QGC)"
    )
    p.add_argument("input", help="mission file to read (.waypoints, .plan, .gpx, .csv, .kml)")
    p.add_argument("output", help="file to write (.waypoints, .gpx, .csv); '-' for stdout")
    p.add_argument("--from", dest="from_fmt", choices=sorted(PARSERS), help="format of INPUT")
    p.add_argument("--to", dest="to_fmt", choices=sorted(WRITERS), help="format of OUTPUT")
    p.add_argument("--force", action="store_true", help="replace OUTPUT if it exists")


def main(args: argparse.Namespace, out: TextIO | None = None) -> int:
    """Run one ``x6wd mission`` action; errors are one line on stderr and exit 2."""
    out = out or sys.stdout
    try:
        wps = load_file(args.file if args.mission_action == "show" else args.input, args.from_fmt)
        for note in wps.notes:  # what the file holds that x6wd does not use
            print(f"x6wd mission: note: {note}", file=sys.stderr)
        if args.mission_action == "show":
            total = 0.0
            print(f"{len(wps)} waypoints (lat, lon in degrees WGS-84; leg length)", file=out)
            for i, w in enumerate(wps):
                leg = great_circle_m(wps[i - 1][0], wps[i - 1][1], w[0], w[1]) if i else 0.0
                total += leg
                print(f"{i + 1:5d}  {w.lat_deg:.7f} {w.lon_deg:.7f}  {leg:8.1f} m", file=out)
            print(f"total {total:.1f} m", file=out)
            return EXIT_OK
        if args.output == "-":
            if args.to_fmt is None:
                raise ParseError("writing to stdout ('-') needs --to FORMAT")
            out.write(format_content(wps, format_of("-", args.to_fmt, writing=True)))
            return EXIT_OK
        kind = save_file(args.output, wps, args.to_fmt, force=args.force)
        print(f"{args.output}: {len(wps)} waypoints written ({kind})", file=sys.stderr)
        return EXIT_OK
    except ParseError as exc:
        print(f"x6wd mission: {exc}", file=sys.stderr)
        return EXIT_USAGE
