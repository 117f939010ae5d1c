"""``x6wd calibrate odometry --straight REC --circle REC [--out FRAGMENT.toml]`` and
``x6wd calibrate gnss [--static REC --ref-lat DEG --ref-lon DEG] [--drive REC --reference REF
...] [--out FRAGMENT.toml] [--plot MAP.png] [--map-csv MAP.csv]``."""

from __future__ import annotations

import argparse
import errno
import math
import os
import stat
import sys
import tomllib
from collections.abc import Callable
from datetime import UTC, datetime
from pathlib import Path

from x6wd.calibrate import gnss
from x6wd.calibrate.odometry import NOISY_PASS, RTK_SIGMA_M, Track, calibrate, load_track
from x6wd.core import config as config_mod
from x6wd.core.errors import ConfigError, DeviceUnavailable
from x6wd.core.outdir import whole_output_file


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
        help="standard deviation of one reference fix per axis, m, and use every valid fix "
        f"whatever its quality (default: from the fixes' GGA quality: {RTK_SIGMA_M[4]:g} for "
        f"RTK fixed, {RTK_SIGMA_M[5]:g} for RTK float; other fixes are left out, and a "
        "recording without RTK fixes refused)",
    )
    odo.add_argument(
        "--stop-s",
        type=float,
        default=1.0,
        help="a stop between passes lasts at least this, s (default %(default)g)",
    )
    odo.add_argument(
        "--min-pass-m",
        type=float,
        default=2.0,
        help="shorter straight passes are ignored, m (default %(default)g)",
    )
    _add_gnss(sub)


def _add_gnss(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    g = sub.add_parser(
        "gnss",
        help="seed-003 GPS error terms RE, ASE and the LCE map from reference runs",
        description="Estimate the [gnss_noise] section (docs/gnss_calibration.md): RE and ASE "
        "from a static recording at a known position (the white and the slow part of the "
        "error), the LCE map from drives with a reference trajectory. Recordings: x6wd "
        "recordings (fix or nmea records), plain NMEA logs, RTKLIB .pos files or CSV (t_s, "
        "lat, lon[, hdop], or TIME, LATITUDE, LONGITUDE).",
    )
    g.add_argument("--static", help="static open-sky recording at a known position")
    g.add_argument("--ref-lat", type=float, help="the static position's latitude, deg")
    g.add_argument("--ref-lon", type=float, help="the static position's longitude, deg")
    g.add_argument(
        "--drive", action="append", default=[], help="a drive's recording (repeat per drive)"
    )
    g.add_argument(
        "--reference",
        action="append",
        default=[],
        help="the reference trajectory of the drive before it (.pos, truth CSV or recording)",
    )
    g.add_argument("--re-m", type=float, help="RE, m per axis at HDOP 1 (instead of --static)")
    g.add_argument("--ase-m", type=float, help="ASE, m per axis at HDOP 1 (instead of --static)")
    g.add_argument(
        "--correlation-s", type=float, help="the slow part's correlation time, s (with --re-m)"
    )
    g.add_argument("--config", help="take RE, ASE and correlation_s from this configuration")
    # their defaults are _DRIVE_ONLY's (None here: given without --drive, they are refused)
    d = _DRIVE_ONLY
    g.add_argument("--cell-m", type=float, help=f"LCE map cell size, m ({d['cell_m']:g})")
    g.add_argument("--min-fixes", type=int, help=f"fixes a mapped cell needs ({d['min_fixes']})")
    g.add_argument(
        "--min-visits", type=int, help=f"separate passes a mapped cell needs ({d['min_visits']})"
    )
    g.add_argument(
        "--visit-gap-s",
        type=float,
        help=f"a new pass after this long away, s ({d['visit_gap_s']:g})",
    )
    g.add_argument(
        "--origin", help="LAT,LON of the map's plane (default: the first reference point)"
    )
    g.add_argument(
        "--max-gap-s",
        type=float,
        help=f"longest reference gap to interpolate, s ({d['max_gap_s']:g})",
    )
    g.add_argument("--out", help="write the TOML fragment here (default: only print it)")
    g.add_argument("--plot", help="write a PNG of the LCE map and the drive track here")
    g.add_argument("--map-csv", help="write every visited cell (counts, SE, marks) here")


def _gnss_noise_keys(path: str) -> set[str]:
    """The keys a configuration file sets in its [gnss_noise] section (none without one);
    the file has passed :func:`config_mod.load`, so it reads and parses."""
    with open(path, "rb") as f:
        section = tomllib.load(f).get("gnss_noise", {})
    return set(section) if isinstance(section, dict) else set()


def _latlon(text: str) -> tuple[float, float]:
    try:
        lat, lon = (float(v) for v in text.split(","))
    except ValueError:
        raise ConfigError(f"--origin {text!r}: expected LAT,LON in degrees") from None
    if not (math.isfinite(lat) and abs(lat) <= 90 and math.isfinite(lon) and abs(lon) <= 180):
        raise ConfigError(
            f"--origin {text!r}: latitude must be finite and within ±90, longitude within ±180"
        )
    return lat, lon


_FLAG_RULES: dict[str, tuple[Callable[[float], bool], str]] = {
    "finite>=0": (lambda v: math.isfinite(v) and v >= 0, ">= 0"),
    "finite>0": (lambda v: math.isfinite(v) and v > 0, "> 0"),
    "int>=1": (lambda v: v >= 1, ">= 1"),
    "lat": (lambda v: math.isfinite(v) and abs(v) <= 90.0, "finite and within ±90 degrees"),
    "lon": (lambda v: math.isfinite(v) and abs(v) <= 180.0, "finite and within ±180 degrees"),
}


def _check_flags(args: argparse.Namespace, rules: dict[str, str]) -> None:
    """ConfigError naming the first flag (attribute: a rule of :data:`_FLAG_RULES`) out of
    range, before any work; None (not given) passes."""
    for name, rule in rules.items():
        v = getattr(args, name, None)
        ok, want = _FLAG_RULES[rule]
        if v is not None and not ok(v):
            raise ConfigError(f"--{name.replace('_', '-')} must be {want}, got {v!r}")


_DRIVE_ONLY = {
    "cell_m": 10.0,
    "min_fixes": 10,
    "min_visits": 2,
    "visit_gap_s": 30.0,
    "max_gap_s": 1.5,
    "origin": None,
    "plot": None,
    "map_csv": None,
}
"""The options that shape or write the LCE map, which only --drive makes, and their defaults
(None in the parser, so an option given without --drive is seen and refused)."""


def _check_output_file(option: str, path: str | None, *, plot: bool = False) -> None:
    """Refuse now, naming ``option``, an output file that cannot be written (a missing or
    read-only folder, a directory there) or, for a plot, a suffix matplotlib cannot write:
    before any work, and before another output is written."""
    if not path:
        return
    p = Path(path)
    if plot and p.suffix:
        from matplotlib.figure import Figure

        kinds = Figure().canvas.get_supported_filetypes()
        if p.suffix[1:].lower() not in kinds:
            raise ConfigError(
                f"{option} {path}: cannot write a {p.suffix} image (one of: {', '.join(kinds)})"
            )
    if p.exists() and not p.is_file() and not p.is_dir():
        return  # a device or pipe (/dev/null): opening it now could block
    # Probe without creating anything: a create-then-delete probe through a dangling link
    # made its target and then removed the link itself (the later write left a plain file).
    try:
        if p.is_dir():
            raise IsADirectoryError(errno.EISDIR, os.strerror(errno.EISDIR))
        if p.exists():  # written over later; opening it to append changes nothing
            with open(p, "a"):
                pass
            return
        folder = Path(os.path.realpath(p)).parent  # a dangling link's target's folder
        if not folder.is_dir():
            code = errno.ENOTDIR if folder.exists() else errno.ENOENT
            raise OSError(code, os.strerror(code))
        if not os.access(folder, os.W_OK | os.X_OK):
            read_only = os.statvfs(folder).f_flag & os.ST_RDONLY
            code = errno.EROFS if read_only else errno.EACCES
            raise OSError(code, os.strerror(code))
    except OSError as exc:
        raise ConfigError(f"{option} {path}: cannot write there: {exc.strerror or exc}") from exc


def _write_output(path: str, write: Callable[[str], object]) -> None:
    """``write(path)``: an ``OSError`` there (a full disk) is a :class:`ConfigError` naming the
    file, and a partly written regular file is removed (:func:`whole_output_file`)."""
    with whole_output_file(path):
        write(path)


def _load_track_of(option: str, path: str) -> Track:
    """:func:`load_track` of the recording given with ``option``; a path that is no regular
    file (a FIFO, a device: reading it could block) or cannot be read is a ConfigError
    naming the option and the file."""
    try:
        mode = os.stat(path).st_mode
    except OSError:
        mode = None  # missing: its rotated parts may remain (read_recording_parts says)
    if mode is not None and not stat.S_ISREG(mode) and not stat.S_ISDIR(mode):
        what = "a FIFO" if stat.S_ISFIFO(mode) else "a device or socket"
        raise ConfigError(f"{option} {path}: {what}, not a recording file")
    try:
        return load_track(path)
    except DeviceUnavailable as exc:
        raise ConfigError(f"{option}: {exc}") from exc


def main_gnss(args: argparse.Namespace) -> int:
    """``x6wd calibrate gnss``: 0 on success."""
    if not args.drive:
        unused = [f"--{k.replace('_', '-')}" for k in _DRIVE_ONLY if getattr(args, k) is not None]
        if unused:
            verb = "shapes or writes" if len(unused) == 1 else "shape or write"
            raise ConfigError(
                f"calibrate gnss: {', '.join(unused)} {verb} the LCE map, which only "
                "--drive makes: give --drive with --reference, or leave them out"
            )
    for key, value in _DRIVE_ONLY.items():
        if getattr(args, key) is None:
            setattr(args, key, value)
    if args.plot:  # now, not after the map is made and the fragment written
        import matplotlib  # noqa: F401  (missing: the CLI names the extra to install)
    _check_output_file("--out", args.out)
    _check_output_file("--map-csv", args.map_csv)
    _check_output_file("--plot", args.plot, plot=True)
    _check_flags(args, {
        "re_m": "finite>=0", "ase_m": "finite>=0", "correlation_s": "finite>=0",
        "cell_m": "finite>0", "max_gap_s": "finite>0", "visit_gap_s": "finite>=0",
        "min_fixes": "int>=1", "min_visits": "int>=1", "ref_lat": "lat", "ref_lon": "lon",
    })  # fmt: skip
    if not args.static and not args.drive:
        raise ConfigError("calibrate gnss: give --static, --drive, or both")
    if len(args.drive) != len(args.reference):
        raise ConfigError(
            f"calibrate gnss: {len(args.drive)} --drive but {len(args.reference)} --reference; "
            "give one reference per drive"
        )
    header = [f"x6wd calibrate gnss, {datetime.now(UTC).strftime('%Y-%m-%dT%H:%M:%SZ')}"]
    static = None
    given: dict[str, str] = {}  # where RE, ASE and correlation_s came from, when not measured
    default_note = ""  # said once the inputs have read: a file that does not read comes first
    if args.static:
        if args.ref_lat is None or args.ref_lon is None:
            raise ConfigError("calibrate gnss: --static needs --ref-lat and --ref-lon")
        # --static measures all three: a value given beside it would be silently unused
        extra = [f"--{k.replace('_', '-')}" for k in ("re_m", "ase_m", "correlation_s", "config")
                 if getattr(args, k) is not None]  # fmt: skip
        if extra:
            raise ConfigError(
                f"calibrate gnss: --static measures RE, ASE and correlation_s, and "
                f"{', '.join(extra)} would set them too: give one or the other"
            )
        static = gnss.static_noise(gnss.load_fixes(args.static), args.ref_lat, args.ref_lon)
        if static.duplicates:
            print(
                f"x6wd calibrate: {static.duplicates} static fixes sharing an epoch with the "
                "fix before (a repeated time stamp) left out",
                file=sys.stderr,
            )
        re_m, ase_m, tau = static.re_m, static.ase_m, static.correlation_s
        header.append(f"static: {args.static} at {args.ref_lat}, {args.ref_lon}")
    else:
        # the keys the --config file's [gnss_noise] sets: the others are built-in defaults
        base = (config_mod.load(args.config) if args.config else config_mod.Config()).gnss_noise
        in_file = _gnss_noise_keys(args.config) if args.config else set()
        if (args.re_m is None) != (args.ase_m is None):
            # the LCE map subtracts both: one given and a built-in default for the other
            # would be taken for the user's value
            have, missing = ("--re-m", "--ase-m") if args.ase_m is None else ("--ase-m", "--re-m")
            if missing.removeprefix("--").replace("-", "_") not in in_file:
                where = (
                    f" (--config {args.config} does not set {missing[2:].replace('-', '_')} "
                    "in [gnss_noise])"
                    if args.config
                    else ""
                )
                raise ConfigError(
                    f"calibrate gnss: {have} without {missing}{where}: give both (the LCE map "
                    "subtracts RE and ASE), or --config with a [gnss_noise] section setting "
                    f"{missing[2:].replace('-', '_')}, or --static"
                )
        default = "the built-in default, not measured"
        src = f"from --config {args.config}"
        re_m = gnss.Estimate(args.re_m if args.re_m is not None else base.re_m, 0.0)
        ase_m = gnss.Estimate(args.ase_m if args.ase_m is not None else base.ase_m, 0.0)
        tau = args.correlation_s if args.correlation_s is not None else base.correlation_s
        sources = {
            "re": "given with --re-m"
            if args.re_m is not None
            else (src if "re_m" in in_file else default),
            "ase": "given with --ase-m"
            if args.ase_m is not None
            else (src if "ase_m" in in_file else default),
            "tau": "given with --correlation-s"
            if args.correlation_s is not None
            else (src if "correlation_s" in in_file else default),
        }
        defaults = [
            (f"{name} {value:g} {unit}", flag)
            for name, value, unit, key, flag in (
                ("RE", re_m.value, "m", "re", "--re-m"),
                ("ASE", ase_m.value, "m", "ase", "--ase-m"),
                ("correlation_s", tau, "s", "tau", "--correlation-s"))
            if sources[key] == default
        ]  # fmt: skip
        given = {"re_from": sources["re"], "ase_from": sources["ase"], "tau_from": sources["tau"]}
        if defaults:
            what, flags = (", ".join(d) for d in zip(*defaults, strict=True))
            plural = "s" if len(defaults) > 1 else ""
            absent = (
                f"not in --config {args.config}'s [gnss_noise], no --static or {flags}"
                if args.config
                else f"no --static, --config or {flags}"
            )
            default_note = (
                f"x6wd calibrate: {what}: the built-in default{plural}, not measured "
                f"({absent}); the fragment says so"
            )
    pairs = [
        (gnss.load_fixes(d), gnss.load_fixes(r))
        for d, r in zip(args.drive, args.reference, strict=True)
    ]
    if default_note:
        print(default_note, file=sys.stderr)
    lce = None
    if args.drive:
        lce = gnss.drives_lce_map(
            pairs,
            re_m=re_m.value,
            ase_m=ase_m.value,
            origin=_latlon(args.origin) if args.origin else None,
            max_gap_s=args.max_gap_s,
            cell_m=args.cell_m,
            min_fixes=args.min_fixes,
            min_visits=args.min_visits,
            visit_gap_s=args.visit_gap_s,
        )
        header += [f"drive: {s}" for s in lce.sources]
        if not lce.mapped():
            print(
                f"x6wd calibrate: LCE map: {lce.spread_text()}; only lce_default_m applies",
                file=sys.stderr,
            )
    result = gnss.GnssCalibration(re_m, ase_m, tau, static, lce, **given)
    if result.tau_bound_note:
        print(f"x6wd calibrate: correlation_s: {result.tau_bound_note}", file=sys.stderr)
    if result.standing_warning:
        print(f"x6wd calibrate: WARNING: {result.standing_warning}", file=sys.stderr)
    text = result.toml("\n".join(header))
    sys.stdout.write(text)
    if args.out:
        _write_output(args.out, lambda p: Path(p).write_text(text, encoding="utf-8"))
    if lce is not None and args.map_csv:
        _write_output(args.map_csv, lambda p: gnss.write_map_csv(lce, p))
    if lce is not None and args.plot:
        title = ", ".join(Path(d).name for d in args.drive)
        _write_output(args.plot, lambda p: gnss.plot_lce_map(lce, p, title=title))
    return 0


def main(args: argparse.Namespace) -> int:
    """Run the chosen calibration; 0 on success (errors are X6wdError, exit code 2)."""
    if args.what == "gnss":
        return main_gnss(args)
    cpr = args.counts_per_rev
    if cpr is None:
        cfg = config_mod.load(args.config) if args.config else config_mod.Config()
        cpr = cfg.odometry.counts_per_rev
    if cpr < 1:
        raise ConfigError(f"--counts-per-rev must be >= 1, got {cpr}")
    _check_flags(args, {"stop_s": "finite>0", "min_pass_m": "finite>=0", "ref_sigma_m": "finite>0"})
    _check_output_file("--out", args.out)
    straight = _load_track_of("--straight", args.straight)
    circle = _load_track_of("--circle", args.circle)
    for name, track in (("straight", straight), ("circle", circle)):
        if track.skipped:
            print(
                f"x6wd calibrate: {track.skipped} unreadable lines or records of the {name}"
                " recording skipped",
                file=sys.stderr,
            )
    result = calibrate(
        straight,
        circle,
        counts_per_rev=cpr,
        ref_sigma_m=args.ref_sigma_m,
        stop_s=args.stop_s,
        min_pass_m=args.min_pass_m,
    )
    stamp = datetime.now(UTC).strftime("%Y-%m-%dT%H:%M:%SZ")
    text = result.toml(
        f"x6wd calibrate odometry, {stamp}\nstraight: {args.straight}\ncircle: {args.circle}"
    )
    for note in result.reference.notes():
        print(f"x6wd calibrate: {note}", file=sys.stderr)
    if result.dropped_passes:
        print(
            f"x6wd calibrate: {result.dropped_passes} passes without reference fixes in the "
            "stops around them were left out",
            file=sys.stderr,
        )
    st = result.straight
    if st.found > st.passes:
        short = st.found - st.passes - st.returned - st.turned
        print(
            f"x6wd calibrate: straight track: {st.passes} of {st.found} passes used; "
            f"{st.returned} counted backwards within the pass (runs or a pivot merged: the stop "
            f"between was shorter than --stop-s {args.stop_s:g} s once the motors' lag is "
            f"counted), {st.turned} turned or bent (no straight drive), {short} shorter than "
            f"--min-pass-m {args.min_pass_m:g} m (pivots, nudges)",
            file=sys.stderr,
        )
        for why in st.left_out:
            print(f"x6wd calibrate: left out: {why}", file=sys.stderr)
    unresolved = [k for k in ("k_left_m", "k_right_m") if not getattr(result, k).resolved]
    if unresolved:
        print(
            f"x6wd calibrate: {' and '.join(unresolved)} not resolved (not 2 standard errors "
            "above 0 on either track): written as an upper bound, the larger k + its standard "
            "error",
            file=sys.stderr,
        )
    if result.few_passes:
        print(f"x6wd calibrate: rough: {result.few_passes}", file=sys.stderr)
    if result.gap_passes:
        print(
            f"x6wd calibrate: {result.gap_passes} circle passes with reference fixes more than "
            "a quarter lap apart (a GPS gap: their laps cannot be counted) were left out",
            file=sys.stderr,
        )
    if result.circle.noisy_passes:
        print(
            f"x6wd calibrate: {result.circle.noisy_passes} circle passes with {NOISY_PASS} "
            "were left out: their laps cannot be counted",
            file=sys.stderr,
        )
    sys.stdout.write(text)
    if args.out:
        _write_output(args.out, lambda p: Path(p).write_text(text, encoding="utf-8"))
    return 0
