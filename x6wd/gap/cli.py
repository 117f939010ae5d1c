"""``x6wd gap --real REAL [--sim SIM [SIM ...] | --scenario FILE [--seeds M]
[--workers N | --scheduler ADDRESS]] [--truth LAT,LON[,ALT] | --truth-track FILE] [--out DIR]``."""

from __future__ import annotations

import argparse
import dataclasses
import filecmp
import hashlib
import math
import os
import re
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from sim_backend.effects import PositionSeries, metres_per_degree
from x6wd.core.config import PACKAGED_CONFIG_DIR
from x6wd.core.errors import ConfigError, X6wdError
from x6wd.core.files import not_regular
from x6wd.core.geodesy import great_circle_m
from x6wd.core.outdir import output_dir, output_file
from x6wd.gap.compass import CompassDiagnosis, compass_verdict_text
from x6wd.gap.diagnose import Diagnosis, Options, check_real, diagnose, enough_fixes
from x6wd.gap.io import (
    MAX_ERROR_FROM_TRUTH_M,
    STATIC_MAX_SPREAD_M,
    Track,
    against_own_mean,
    check_near_truth,
    check_step,
    errors_vs_mean,
    errors_vs_point,
    errors_vs_track,
    is_date,
    log_start_s,
    lon_centre_deg,
    mean_alt_m,
    moving_text,
    parse_truth,
    read_track,
    realign_note,
    time_offset_note,
    truth_median_speed_mps,
    velocity_mismatch_mps,
    wrap_lon_deg,
)
from x6wd.gap.report import (
    FIGURES,
    candidate_text,
    remove_earlier_calibration,
    spread_text,
    verdict_line,
    write_report,
)
from x6wd.gap.stats import has_up


def _int_in(low: int, high: int) -> Callable[[str], int]:
    """An argparse type: an integer within ``low``..``high`` (argparse then exits 2 naming
    the option and the value, before anything is read)."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not an integer") from None
        if not low <= value <= high:
            bound = f"within {low}..{high}" if high < 2**62 else f">= {low}"
            raise argparse.ArgumentTypeError(f"{value}: must be {bound}")
        return value

    return parse


MAX_SEEDS = 1000
"""Most --scenario runs (each a full simulation of the log); --replicates' bound too."""
DEFAULT_SEEDS = 20


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``x6wd gap``."""
    parser.add_argument(
        "--real", required=True, help="real log: NMEA, x6wd recording, CSV or RTKLIB .pos"
    )
    baseline = parser.add_mutually_exclusive_group()
    baseline.add_argument(
        "--sim",
        nargs="+",
        action="extend",
        default=[],
        help="baseline sim log(s): several after one --sim, or --sim repeated",
    )
    baseline.add_argument(
        "--scenario",
        help="scenario TOML: the baseline is run with --seeds seeds, placed where and when the"
        " log was (default, without --sim: the packaged open-field scenario)",
    )
    parser.add_argument(
        "--seeds",
        type=_int_in(1, MAX_SEEDS),
        default=None,
        help=f"baseline runs with --scenario (default {DEFAULT_SEEDS}; not with --sim)",
    )
    parser.add_argument(
        "--workers",
        type=_int_in(1, 1024),
        default=None,
        metavar="N",
        help="run the --scenario seeds on a Dask LocalCluster of N workers (the executor of"
        " x6wd sweep; default: one after another in this process)",
    )
    parser.add_argument(
        "--scheduler",
        metavar="ADDRESS",
        default=None,
        help="run the --scenario seeds on a running Dask scheduler (tcp://host:8786)",
    )
    # "--truth -45.87,170.5": argparse takes an argument starting with "-" for an option
    # unless it is one plain negative number, so a southern or western first value stopped
    # with "expected one argument". Any "-" then a digit is a value here (the rule of newer
    # Pythons' argparse); no option of this parser starts with a digit.
    parser._negative_number_matcher = re.compile(r"-\.?\d")
    truth = parser.add_mutually_exclusive_group()
    truth.add_argument(
        "--truth",
        help="surveyed point LAT,LON[,ALT] (deg, deg, m); negative values work as they are:"
        " --truth -45.87,170.5",
    )
    truth.add_argument("--truth-track", help="truth trajectory (any log format, e.g. RTKLIB .pos)")
    parser.add_argument("--out", default="gap-report", help="output directory (default gap-report)")
    parser.add_argument(
        "--seed",
        type=_int_in(0, 2**63 - 1),
        default=0,
        help="seed of the tool's own randomness (an integer >= 0)",
    )
    parser.add_argument(
        "--replicates",
        type=_int_in(3, MAX_SEEDS),
        default=20,
        help="replicates made of the --sim logs' innovations when fewer than 8 (default 20)",
    )
    parser.add_argument("--no-figures", action="store_true", help="skip the PNG figures")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")


class ProgressBar:
    """A one-line progress bar on stderr (only drawn on a terminal unless forced)."""

    def __init__(self, enabled: bool, width: int = 30) -> None:
        self.enabled = enabled
        self.width = width
        self.t0 = time.monotonic()

    def __call__(self, msg: str, frac: float) -> None:
        if not self.enabled:
            return
        n_filled = round(max(0.0, min(1.0, frac)) * self.width)
        elapsed_s = time.monotonic() - self.t0
        filled = "#" * n_filled + " " * (self.width - n_filled)
        line = f"\r[{filled}] {frac:4.0%} {elapsed_s:5.1f}s {msg[:50]:<50}"
        sys.stderr.write(line)
        if frac >= 1.0:
            sys.stderr.write("\n")
        sys.stderr.flush()


def to_errors(
    track: Track,
    args: argparse.Namespace,
    truth_track: Track | None,
    log: str | None = None,
    own_truth: bool = False,
) -> PositionSeries:
    """A log's errors against the chosen truth (ConfigError for a log far from it, or a
    moving log without one). ``log``: ``"real"`` or ``"sim"``, so that error's hint is
    that log's; ``own_truth``: ``truth_track`` is a --sim log's own truth.csv (named then)."""
    if args.truth is not None:  # "" too: parse_truth names it
        lat, lon, alt = parse_truth(args.truth)
        series = check_near_truth(errors_vs_point(track, lat, lon, alt), track.source, log)
        return check_static_error(series, track, f"the point --truth {args.truth}", log)
    if truth_track is not None:
        own = truth_track.source if own_truth else None
        series = check_near_truth(errors_vs_track(track, truth_track), track.source, log, own)
        if np.count_nonzero(truth_track.valid) >= 1 and _truth_still(truth_track):
            which = "its own truth" if own_truth else "the static truth track"
            return check_static_error(series, track, f"{which} {truth_track.source}", log)
        return series
    return errors_vs_mean(track)


def check_static_error(
    series: PositionSeries, track: Track, truth_text: str, log: str | None = None
) -> PositionSeries:
    """``series`` (a static log's errors against a truth that stands still, m) unless their
    median horizontal error exceeds :data:`~x6wd.gap.io.STATIC_MAX_SPREAD_M`: then ConfigError
    naming the log, ``truth_text`` (what it is scored against) and the median distance. A
    static receiver lies metres, at worst tens of metres, from its place: 500 m is a wrong
    truth, and scored it would be reported as a 500 m bias ("explained by bias", written into
    calibrated.toml). A moving log is left to :func:`check_still`."""
    median_m = _median_error_m(series)
    if not median_m > STATIC_MAX_SPREAD_M or moving_text(track) is not None:
        return series
    which = {"real": " (the real log, --real)", "sim": " (a --sim log)"}.get(log or "", "")
    raise ConfigError(
        f"{track.source}{which}: its fixes lie a median {median_m:.0f} m from {truth_text}:"
        f" a static receiver's fixes lie metres, at most tens of metres, from its place (over"
        f" {STATIC_MAX_SPREAD_M:g} m is no GNSS error, and would be reported as a bias). Is the"
        " truth this log's place (a digit wrong, latitude and longitude swapped, another"
        " site's survey)?"
    )


def check_sim_truths_at_point(args: argparse.Namespace, sims: list[Track]) -> None:
    """ConfigError naming the --sim logs whose own static truth (:data:`SIM_TRUTH_NAME` beside
    them, its median position) lies more than :data:`~x6wd.gap.io.STATIC_MAX_SPREAD_M` from
    the point --truth: their runs simulate another place than the one the real log is scored
    at, and their errors against --truth would be that distance. Compared only where it is the
    run's truth (the log's fixes lie within STATIC_MAX_SPREAD_M of it); a truth.csv that
    cannot be read as positions (a compass-only one), that moves (a mission's:
    :func:`check_still` refuses a moving log against a point) or lies away from its log's
    fixes (not that run's truth) is not compared."""

    def centre(track: Track) -> tuple[float, float] | None:
        v = np.asarray(track.valid, dtype=bool)
        if not np.any(v):
            return None
        return float(np.median(track.lat_deg[v])), lon_centre_deg(track.lon_deg[v], np.median)

    lat_deg, lon_deg, _ = parse_truth(args.truth)
    for path, sim in zip(args.sim, sims, strict=True):
        own = Path(path).parent / SIM_TRUTH_NAME
        if not own.is_file():
            continue
        try:
            truth = read_track(own)
        except X6wdError:
            continue
        there, fixes = centre(truth), centre(sim)
        if there is None or fixes is None or not _truth_still(truth):
            continue
        if great_circle_m(*there, *fixes) > STATIC_MAX_SPREAD_M:
            continue  # not this run's truth (placeholder positions of a heading truth)
        d_m = great_circle_m(lat_deg, lon_deg, *there)
        if d_m > STATIC_MAX_SPREAD_M:
            raise ConfigError(
                f"{own} (the truth of the --sim log {path}) lies {d_m:.0f} m from the"
                f" point --truth {args.truth}, over {STATIC_MAX_SPREAD_M:g} m: the runs simulate"
                " another place than the one the real log is scored at, and their errors"
                " against --truth would be that distance. Give the --truth of the place the"
                " runs simulate (or runs simulated at the real log's place)"
            )


SIM_TRUTH_NAME = "truth.csv"
"""A --sim log's own truth, beside it (``x6wd sim`` writes it beside gps.nmea and
recording.jsonl): the true path of that run."""
ROUTE_RATIO = 3.0
ROUTE_MIN_M = 5.0
"""A --sim log without its own truth whose fixes lie a median of more than ROUTE_RATIO times
the real log's median error, and more than ROUTE_MIN_M, from the real log's moving truth
track did not drive the real route (:func:`check_sim_routes`). The same rule holds a --sim
log that reports no speeds to its own moving truth (nothing else can tell that truth)."""
OWN_TRUTH_RATIO = 10.0
OWN_TRUTH_MIN_M = 50.0
"""A --sim log reporting speeds whose fixes lie a median of more than OWN_TRUTH_RATIO times
the real log's median error, and more than OWN_TRUTH_MIN_M, from its own moving truth is not
that truth's run (:func:`check_own_truths`): another scenario's route (zigzag's truth
beside a laps run: 88.9 m). Nearer, position error is the receiver's: unaltered x6wd sim
runs of the shipped building_route lie a median 3.2-20.5 m from their own truth (urban
multipath), a sim receiver noisier than the real one is the gap the tool finds, and the
velocity rule (:data:`SPEED_MIN_MPS`) tells a wrong truth."""
SPEED_MIN_MPS = 0.3
"""A --sim log whose reported velocity (speed and course) differs from its own moving
truth's by a median of more than ROUTE_RATIO times the real log's difference from its
truth, and more than this (m/s), is not that truth's run (:func:`check_own_truths`).
Against their own truth x6wd sim's logs differ by 0.085-0.127 m/s (30 moving runs of 6
scenarios, building_route's 20 m multipath too), cut 20 s into it by 1.4-2.6 m/s, against
another seed's of the same laps by 0.4-1.3 m/s, where their positions (4.1 m from their
own, 4.3 m from another seed's) cannot tell."""
STATIC_TRUTH_MAX_SPEED_MPS = 0.2
"""A truth track stands still (a static survey's) when it reaches no farther than
:data:`ROUTE_MIN_M` from its centre and its median speed is under this (m/s): a robot
circling 3.5 m round a point at 1.5 m/s (a compass check) moves."""
ZERO_ERROR_M = 1e-3
"""A real log whose fixes lie a median of less than this (m) from its truth track is scored
against itself (the log, a copy or a conversion of it given as --truth-track)."""


def _same_file(a: str | Path, b: str | Path) -> bool:
    """Whether two paths are one file, or regular files of identical bytes."""
    a, b = Path(a), Path(b)
    if a.resolve() == b.resolve():
        return True
    return a.is_file() and b.is_file() and filecmp.cmp(a, b, shallow=False)


def sim_truth(path: str, truth_track_path: str) -> tuple[Track | None, str | None, str | None]:
    """The truth a --sim log carries: :data:`SIM_TRUTH_NAME` beside it, read as a track; a
    note when one is there but is not used (a copy of the --truth-track, or unreadable); and
    why it could not be read (the file and the reader's error), else None. (None, None,
    None) when there is none, or it is the --truth-track itself."""
    own = Path(path).parent / SIM_TRUTH_NAME
    if not own.is_file() or own.resolve() == Path(truth_track_path).resolve():
        return None, None, None
    if _same_file(own, truth_track_path):  # a copy: the real route's truth, checked as such
        note = (
            f"--sim log {path}: the {SIM_TRUTH_NAME} beside it is a copy of the real log's"
            f" truth track {truth_track_path}: scored against it, as a log that drove the"
            " real route"
        )
        return None, note, None
    try:
        return read_track(own), None, None
    except X6wdError as exc:  # a heading-only truth.csv (the compass half's) has no positions
        why = str(exc) if str(own) in str(exc) else f"{own}: {exc}"
        note = (
            f"--sim log {path}: the {SIM_TRUTH_NAME} beside it was not read ({why}): scored"
            " against the real log's truth track"
        )
        return None, note, why


def check_shared_truths(names: list[str], truths: list[Track | None], truth_track: Track) -> None:
    """ConfigError naming the --sim logs whose own moving truths are one file or copies of
    one (same bytes): the runs of a mission each drive their own route, so one path is the
    truth of one of them at most. Static truths (a survey's, alike in every seed) may be
    shared."""
    groups: dict[str, list[tuple[str, str]]] = {}
    for name, truth in zip(names, truths, strict=True):
        if truth is None or truth is truth_track or _truth_still(truth):
            continue
        digest = hashlib.sha256(Path(truth.source).read_bytes()).hexdigest()
        groups.setdefault(digest, []).append((name, truth.source))
    shared = [group for group in groups.values() if len(group) > 1]
    if not shared:
        return
    listed = "; ".join(
        f"{', '.join(name for name, _ in group)} share"
        f" {' and '.join(dict.fromkeys(src for _, src in group))}"
        f"{'' if len({src for _, src in group}) == 1 else ' (identical copies)'}"
        for group in shared
    )
    raise ConfigError(
        f"--sim logs with one truth: {listed}. Each run of a mission drives its own route (a"
        " closed-loop run steers on its own GPS error), so one moving truth is the true path"
        f" of one run at most: give each --sim log the {SIM_TRUTH_NAME} its own run wrote"
    )


def read_input(path: str | Path) -> Track:
    """:func:`read_track` of a log the user named; on a named FIFO it first says on stderr
    that it waits for the FIFO's writer (opening one without a writer blocks, and the run
    looked hung with no word)."""
    kind = not_regular(path)
    # a symlink to a named FIFO reads as "a pipe" (as /dev/fd/N does, whose writer exists)
    target = os.path.realpath(path)
    if kind == "a FIFO" or (kind == "a pipe" and not target.startswith(("/proc/", "/dev/fd/"))):
        print(f"x6wd gap: {path} is a FIFO: waiting for its writer", file=sys.stderr, flush=True)
    return read_track(path)


def check_real_truth(args: argparse.Namespace, real: PositionSeries | None = None) -> None:
    """ConfigError when the real log is scored against itself: --truth-track is the --real
    file or a copy of it, or (``real`` given) its fixes lie a median of under
    :data:`ZERO_ERROR_M` from the truth track (a conversion of the log). Every error would be
    zero and any simulator "a gap"."""
    if args.truth_track is None:
        return
    if real is None:
        if _same_file(args.real, args.truth_track):
            raise ConfigError(
                f"--truth-track {args.truth_track} is the real log {args.real} itself (the"
                " same file or the same bytes): its errors against itself are all zero. Give"
                " the true path from another source (a surveyed route, an RTK or"
                " post-processed solution, the truth.csv of a simulated run)"
            )
        return
    median_m = _median_error_m(real)
    if median_m < ZERO_ERROR_M:
        raise ConfigError(
            f"{args.real}: its fixes lie a median {median_m * 1000:.3f} mm from the truth track"
            f" {args.truth_track}: is --truth-track the real log itself, or made from it? Its"
            " errors against itself are all zero. Give the true path from another source (a"
            " surveyed route, an RTK or post-processed solution, the truth.csv of a simulated"
            " run)"
        )


def _static_truth_text(args: argparse.Namespace, truth: Track | None) -> str | None:
    """What a log is scored against when that truth stands still (the point --truth, a truth
    track that does not move: :func:`_truth_still`); None otherwise (and for a track of under
    2 valid epochs: io.errors_vs_track names that)."""
    if args.truth is not None:
        return f"the point --truth {args.truth}"
    if truth is None or np.count_nonzero(truth.valid) < 2 or not _truth_still(truth):
        return None
    return (
        f"the static truth track {truth.source} (reaching {_truth_extent_m(truth):.1f} m, a"
        f" median speed of {truth_median_speed_mps(truth):.2f} m/s)"
    )


def check_still(
    args: argparse.Namespace, names: list[str], tracks: list[Track], truths: list[Track | None]
) -> None:
    """ConfigError naming the logs that move (:func:`~x6wd.gap.io.moving_text`) but are
    scored against a truth that stands still (:func:`_static_truth_text`): their route would
    count as error, as it would without a truth (io.errors_vs_mean's refusal)."""
    moving = [
        f"{name}: {moves}, scored against {against}"
        for name, track, truth in zip(names, tracks, truths, strict=True)
        if (against := _static_truth_text(args, truth)) is not None
        and (moves := moving_text(track)) is not None
    ]
    if moving:
        raise ConfigError(
            f"{'; '.join(moving)}: against a truth that stands still a log's route would count"
            " as error. Give --truth-track with the real log's true path; a --sim log must"
            f" move as the real log does (a moving --sim run with the {SIM_TRUTH_NAME} x6wd"
            " sim writes beside it; a static survey's baseline is a static run)"
        )


def check_sims_still(args: argparse.Namespace, names: list[str], sims: list[Track]) -> None:
    """With a point ``--truth``, or none, the real log stands still: ConfigError naming the
    --sim logs whose own :data:`SIM_TRUTH_NAME` moves (a mission's runs): a receiver's
    error depends on its motion, and their runs' would be read as the real receiver's gap
    (an audit: a static log against two mission runs, their errors +389 %, read "no
    significant gap" once the null's spread had widened 70-fold)."""
    odd = []
    for name, sim in zip(names, sims, strict=True):
        own = Path(name).parent / SIM_TRUTH_NAME
        if not own.is_file():
            continue
        try:
            truth = read_track(own)
        except X6wdError:  # a heading-only truth.csv (the compass half's): no positions
            continue
        if np.count_nonzero(truth.valid) >= 2 and not _still_over(truth, sim):
            odd.append(name)
    if not odd:
        return
    against = f"the point --truth {args.truth}" if args.truth is not None else "its own mean"
    raise ConfigError(
        f"{', '.join(odd)}: the {SIM_TRUTH_NAME} beside"
        f" {'this --sim log' if len(odd) == 1 else 'each of these'} moves, but the real log"
        f" stands still (scored against {against}): a receiver's error depends on its motion"
        " (its navigation filter's lag, static hold), so the runs' would be read as the real"
        " receiver's gap. Give --sim runs of a receiver standing still (x6wd sim"
        " config/scenarios/open_field.toml), or --scenario"
    )


def check_same_motion(
    args: argparse.Namespace,
    real: tuple[Track, Track],
    names: list[str],
    sims: list[Track],
    truths: list[Track | None],
) -> None:
    """ConfigError naming the --sim logs whose own truth moves while the real log's stands
    still, or stands still while the real log's moves: a receiver's error depends on its
    motion (its navigation filter's lag, static hold), so the difference would be reported
    as the receiver's gap. ``real``: the real log and its truth track. Each truth is judged
    over its log's span, robustly (:func:`_still_over`)."""
    real_track, truth_track = real
    if np.count_nonzero(truth_track.valid) < 2:
        return  # io.errors_vs_track names that
    real_still = args.truth is not None or _still_over(truth_track, real_track)
    odd = [
        name
        for name, sim, truth in zip(names, sims, truths, strict=True)
        if truth is not None
        and truth is not truth_track
        and np.count_nonzero(truth.valid) >= 2
        and _still_over(truth, sim) != real_still
    ]
    if not odd:
        return
    real_way, sim_way = ("stands still", "moves") if real_still else ("moves", "stands still")
    raise ConfigError(
        f"{', '.join(odd)}: the real log's truth {truth_track.source} {real_way} but the"
        f" {SIM_TRUTH_NAME} beside {'this --sim log' if len(odd) == 1 else 'each of these'}"
        f" {sim_way}: a receiver's error depends on its motion (its navigation filter, static"
        " hold), so the difference would be reported as a gap. Give --sim runs that move as"
        " the real log does (a static scenario for a static survey, a mission for a driven"
        " log), or --scenario FILE"
    )


def _median_error_m(series: PositionSeries) -> float:
    """Median horizontal error (m) over the valid epochs; NaN without one."""
    valid = np.asarray(series.valid, dtype=bool)
    if not np.any(valid):
        return math.nan
    east_m, north_m = np.asarray(series.east_m)[valid], np.asarray(series.north_m)[valid]
    return float(np.median(np.hypot(east_m, north_m)))


def _truth_extent_m(truth: Track, quantile: float = 1.0) -> float:
    """How far (m) a truth track's valid positions reach from their median centre (the
    largest distance, or that ``quantile`` of them): near 0 for a static survey's."""
    v = np.asarray(truth.valid, dtype=bool)
    if not np.any(v):
        return 0.0
    lat_deg, lon_deg = truth.lat_deg[v], truth.lon_deg[v]
    e_per_deg, n_per_deg = metres_per_degree(float(np.median(lat_deg)))
    east_m = wrap_lon_deg(lon_deg - lon_centre_deg(lon_deg, np.median)) * e_per_deg
    north_m = (lat_deg - np.median(lat_deg)) * n_per_deg
    return float(np.quantile(np.hypot(east_m, north_m), quantile))


def _still_over(truth: Track, log: Track) -> bool:
    """Whether ``truth`` stands still while ``log`` runs: its samples within the span of the
    log's valid epochs (all of them when under 2 fall there: a simulator's truth in seconds
    from its start against a UTC log), 95 % of them within :data:`ROUTE_MIN_M` of their
    centre and their median speed under :data:`STATIC_TRUTH_MAX_SPEED_MPS`. A reference
    logged from power-on (the antenna walked to the mark before the log began) or one
    RTK float epoch 6 m off leaves a survey still (a review of 5cc3bad: both were refused)."""
    t_s = log.t_s[np.asarray(log.valid, dtype=bool)]
    if len(t_s):
        inside = (truth.t_s >= t_s[0]) & (truth.t_s <= t_s[-1])
        if np.count_nonzero(inside & np.asarray(truth.valid, dtype=bool)) >= 2:
            truth = dataclasses.replace(
                truth,
                **{
                    f.name: getattr(truth, f.name)[inside]
                    for f in dataclasses.fields(truth)
                    if isinstance(getattr(truth, f.name), np.ndarray)
                },
            )
    if _truth_extent_m(truth, 0.95) > ROUTE_MIN_M:
        return False
    if np.count_nonzero(truth.valid) < 2:
        return True
    return truth_median_speed_mps(truth) < STATIC_TRUTH_MAX_SPEED_MPS


def _truth_still(truth: Track) -> bool:
    """Whether a truth track stands still: it reaches no farther than :data:`ROUTE_MIN_M`
    from its centre and its median speed is under :data:`STATIC_TRUTH_MAX_SPEED_MPS` (a
    compact path driven round, a compass-check circle, moves)."""
    if _truth_extent_m(truth) > ROUTE_MIN_M:
        return False
    if np.count_nonzero(truth.valid) < 2:
        return True
    return truth_median_speed_mps(truth) < STATIC_TRUTH_MAX_SPEED_MPS


def check_sim_routes(
    real: PositionSeries,
    baseline: list[PositionSeries],
    truths: list[Track | None],
    truth_track: Track,
    names: list[str],
    unread: dict[str, str] | None = None,
) -> None:
    """ConfigError naming the --sim logs scored against the real log's moving truth track
    (no truth of their own) that did not drive the real route: their fixes lie a median of
    more than :data:`ROUTE_RATIO` times the real log's median error, and more than
    :data:`ROUTE_MIN_M`, from it. A closed-loop run steers on its own GPS error and laps at
    its own times: its route difference would count as GNSS error (22 of 24 unaltered
    moving logs were false alarms). A static truth (reaching no farther than ROUTE_MIN_M)
    leaves no route to miss: a noisier sim receiver there is a gap to find (:func:`check_still`
    refuses a moving log there). ``unread``: --sim log -> why the truth.csv beside it was
    not read, said with that log."""
    if _truth_still(truth_track):
        return
    real_m = _median_error_m(real)
    if not math.isfinite(real_m):
        return
    limit_m = max(ROUTE_MIN_M, ROUTE_RATIO * real_m)
    off = [
        (name, d_m)
        for name, series, truth in zip(names, baseline, truths, strict=True)
        if truth is truth_track and (d_m := _median_error_m(series)) > limit_m
    ]
    if not off:
        return
    unread = unread or {}
    listed = ", ".join(
        f"{name} (a median {d_m:.1f} m"
        + (f"; its {SIM_TRUTH_NAME} was not read: {unread[name]})" if name in unread else ")")
        for name, d_m in off
    )
    give = (
        "a readable truth (the reader's error is named above: the "
        if any(name in unread for name, _ in off)
        else "its own truth ("
    )
    raise ConfigError(
        f"{listed}: {'this --sim log' if len(off) == 1 else 'these --sim logs'} did not drive"
        f" the real route: {'its' if len(off) == 1 else 'their'} fixes lie that far from the"
        f" real log's truth track {truth_track.source}, over {ROUTE_RATIO:g} times the real"
        f" log's own median error ({real_m:.1f} m) and over {ROUTE_MIN_M:g} m. A closed-loop"
        " run steers on its own GPS error and drives its own route: against the real route"
        f" that difference would count as GNSS error. Give each such log {give}"
        f"{SIM_TRUTH_NAME} beside it, t_s in seconds, lat, lon[, alt], as x6wd sim writes"
        " it), or use --scenario FILE (runs driven along the real truth)"
    )


def check_own_truths(
    real: tuple[Track, PositionSeries],
    sims: list[Track],
    baseline: list[PositionSeries],
    truths: list[Track | None],
    truth_track: Track,
    names: list[str],
) -> None:
    """ConfigError naming the --sim logs whose own moving truth (truth.csv beside them) is
    not their run's path. A log reporting speeds: its reported velocity differs from the
    truth's by more than :data:`ROUTE_RATIO` times the real log's difference and more than
    :data:`SPEED_MIN_MPS` (another seed's truth of the same laps, a log cut or shifted
    against its truth), or its fixes lie a median of more than :data:`OWN_TRUTH_RATIO` times
    the real log's median error and more than :data:`OWN_TRUTH_MIN_M` from it (another
    route); nearer, its error is its receiver's, however much larger than the real one's. A
    log without speeds: its fixes lie more than ROUTE_RATIO times the real log's median
    error and more than :data:`ROUTE_MIN_M` from it (positions are all that can tell).
    ``real``: the real log and its errors against ``truth_track``."""
    real_track, real_series = real
    real_m = _median_error_m(real_series)
    if not math.isfinite(real_m):
        return
    route_limit_m = max(ROUTE_MIN_M, ROUTE_RATIO * real_m)
    far_limit_m = max(OWN_TRUTH_MIN_M, OWN_TRUTH_RATIO * real_m)
    real_mps = velocity_mismatch_mps(real_track, truth_track)
    # a real log without reported speeds: SPEED_MIN_MPS alone
    limit_mps = (
        max(SPEED_MIN_MPS, ROUTE_RATIO * real_mps) if math.isfinite(real_mps) else SPEED_MIN_MPS
    )
    off = []
    for name, sim, series, truth in zip(names, sims, baseline, truths, strict=True):
        if truth is None or truth is truth_track or _truth_still(truth):
            continue
        d_m, d_mps = _median_error_m(series), velocity_mismatch_mps(sim, truth)
        if not math.isfinite(d_mps) and d_m > route_limit_m:
            off.append(
                f"{name}: its fixes lie a median {d_m:.1f} m from {truth.source} (over"
                f" {ROUTE_RATIO:g} times the real log's error and {ROUTE_MIN_M:g} m; the log"
                " reports no speeds, by which an own truth is told from another run's)"
            )
        elif d_m > far_limit_m:
            off.append(
                f"{name}: its fixes lie a median {d_m:.1f} m from {truth.source} (over"
                f" {OWN_TRUTH_RATIO:g} times the real log's error and {OWN_TRUTH_MIN_M:g} m)"
            )
        elif d_mps > limit_mps:
            off.append(
                f"{name}: its reported velocity (speed and course) differs from"
                f" {truth.source}'s by a median {d_mps:.2f} m/s (over {ROUTE_RATIO:g} times the"
                f" real log's difference and {SPEED_MIN_MPS:g} m/s)"
            )
    if not off:
        return
    real_text = f"a median {real_m:.1f} m"
    if math.isfinite(real_mps):
        real_text += f" and {real_mps:.2f} m/s"
    raise ConfigError(
        f"{'; '.join(off)}. The real log lies {real_text} from {truth_track.source}: the"
        f" {SIM_TRUTH_NAME} beside such a --sim log is not its run's true path (another run's"
        " or scenario's, or the log cut or shifted against it: a log and truth that do not"
        " overlap in time are aligned start to start), and the difference would count as"
        f" GNSS error. Give each --sim log the {SIM_TRUTH_NAME} its own run wrote, whole"
    )


def sim_truths_note(
    truths: list[Track | None], truth_track: Track, args: argparse.Namespace
) -> str:
    """The note saying which truth each --sim log was scored against."""
    own = [(name, t) for name, t in zip(args.sim, truths, strict=True) if t is not truth_track]
    shared = [name for name, t in zip(args.sim, truths, strict=True) if t is truth_track]
    n = len(args.sim)
    parts = []
    if own:
        parts.append(
            f"{len(own)} of {n} --sim logs are scored against the {SIM_TRUTH_NAME} beside them"
            " (each its own route: a closed-loop run drives its own, not the real log's):"
            f" {', '.join(t.source for _, t in own if t is not None)}"
        )
    if shared:
        parts.append(
            f"{len(shared)} of {n} --sim logs are scored against the real log's truth track"
            f" {args.truth_track} (no {SIM_TRUTH_NAME} of their own; they keep to the real"
            f" route): {', '.join(shared)}"
        )
    return "; ".join(parts)


def far_sims(real: Track, sims: list[Track], names: list[str]) -> list[tuple[str, float]]:
    """(name, distance m) of the --sim logs whose median fix lies more than
    :data:`~x6wd.gap.io.MAX_ERROR_FROM_TRUTH_M` from the real log's: they simulate another
    place (its sky, its walls). Empty when every one is near (or a log has no fix)."""

    def centre(track: Track) -> tuple[float, float] | None:
        v = np.asarray(track.valid, dtype=bool)
        if not np.any(v):
            return None
        return float(np.median(track.lat_deg[v])), lon_centre_deg(track.lon_deg[v], np.median)

    here = centre(real)
    if here is None:
        return []
    far = []
    for name, sim in zip(names, sims, strict=True):
        there = centre(sim)
        if there is not None:
            d_m = great_circle_m(here[0], here[1], there[0], there[1])
            if d_m > MAX_ERROR_FROM_TRUTH_M:
                far.append((name, d_m))
    return far


def place_note(real: Track, sims: list[Track], names: list[str]) -> str | None:
    """Without a truth (errors against each log's own mean), a note naming the --sim logs
    that simulate another place (:func:`far_sims`), which the errors cannot show. None when
    every one is near."""
    far = [f"{name} {d_m / 1000:.1f} km" for name, d_m in far_sims(real, sims, names)]
    if not far:
        return None
    return (
        f"{len(far)} of {len(sims)} --sim logs lie far from the real log ({', '.join(far)}):"
        " without a truth each log's errors are against its own mean, so the place cannot"
        " show in them, but the sky, walls and satellites of another place do (simulate the"
        " real log's place, or give --truth)"
    )


FIGURE_NAMES = (*FIGURES, "compass.png")
"""The PNG figures the report writes (x6wd.gap.report)."""


def remove_earlier_figures(out: Path) -> list[str]:
    """Remove an earlier run's figures from ``out`` (with --no-figures, a left one would read
    as this log's, as a left calibrated.toml would); their names. A PNG of one of those
    names that matplotlib did not write (its header does not say so) is the user's: kept."""
    removed = []
    for name in FIGURE_NAMES:
        path = out / name
        if not path.is_file() or path.is_symlink():
            continue
        with open(path, "rb") as f:
            head = f.read(512)
        if head.startswith(b"\x89PNG") and b"Matplotlib" in head:
            path.unlink()
            removed.append(name)
    return removed


TEXT_OUTPUTS = ("report.json", "effects.toml", "validation.json", "report.md")
"""The text outputs every run writes (x6wd.gap.report; calibrated.toml only with a level
calibration: :func:`~x6wd.gap.report.remove_earlier_calibration`)."""


def remove_earlier_outputs(out: Path) -> None:
    """Remove an earlier run's outputs from ``out`` at this run's start, as ``x6wd sim`` does:
    a run cut short (a full disk) left the earlier run's report.md and figures beside its own
    report.json. Only :data:`TEXT_OUTPUTS` that are regular files (a link is the user's: its
    target is not this run's), a calibrated.toml this tool wrote and the figures matplotlib
    wrote (:func:`remove_earlier_figures`); nothing else in the folder."""
    for name in TEXT_OUTPUTS:
        path = out / name
        if path.is_file() and not path.is_symlink():
            with output_file(path):
                path.unlink()
    if not (out / "calibrated.toml").is_symlink():
        remove_earlier_calibration(out)
    remove_earlier_figures(out)


def realigned_sims_notes(
    names: list[str], sims: list[Track], truths: list[Track | None], baseline: list[PositionSeries]
) -> list[str]:
    """The notes on --sim logs realigned onto their truth start to start
    (:func:`~x6wd.gap.io.realign_note`): one for them all when several (a simulator's clock
    is its own), with each other log's epochs matching its truth (a truth covering only part
    of a log shows there)."""
    moved = [
        (name, note, f"{name} {len(series.t_s)} of {len(sim)}")
        for name, sim, truth, series in zip(names, sims, truths, baseline, strict=True)
        if truth is not None and (note := realign_note(sim, truth)) is not None
    ]
    if len(moved) <= 1:
        return [note for _, note, _ in moved]
    return [
        f"{len(moved)} of {len(sims)} --sim logs do not overlap their truth's time span and were"
        f" realigned start to start: {moved[0][1]} (the others alike; epochs then matching"
        f" their truth: {', '.join(matched for _, _, matched in moved[1:])})"
    ]


def short_sims_notes(
    real: PositionSeries,
    baseline: list[PositionSeries],
    names: list[str],
    logs: list[Track] | None = None,
    truths: list[Track | None] | None = None,
) -> list[str]:
    """A note naming the --sim logs whose error series is shorter than the real log's (by
    more than two of its steps): the real log's later part, and its time scales beyond a sim
    log's length, have no or fewer simulated values to be compared with (the held-out part,
    the validation's longest Allan octaves). With the sim ``logs`` and their ``truths``, a
    log whose truth covers only part of it says so (the truth is short, not only the log).
    Also said on stderr. Empty when every sim log is as long."""

    def span_s(t_s: np.ndarray) -> float:
        t_s = np.asarray(t_s, dtype=float)
        return float(t_s[-1] - t_s[0]) if t_s.size else 0.0

    real_s = span_s(real.t_s)
    steps = np.diff(np.asarray(real.t_s, dtype=float))
    slack_s = 2.0 * float(np.median(steps)) if steps.size else 0.0
    logs_s = [math.inf] * len(names) if logs is None else [span_s(log.t_s) for log in logs]
    truths = truths or [None] * len(names)
    short = [(name, span_s(s.t_s), log_s, truth) for name, s, log_s, truth
             in zip(names, baseline, logs_s, truths, strict=True)
             if span_s(s.t_s) < real_s - slack_s]  # fmt: skip
    if not short:
        return []
    # a log scored over less than its own length: its truth is (also) short
    cut = {name: f" (of its {log_s:.0f} s: its truth {truth.source} covers no more)"
           for name, length, log_s, truth in short
           if truth is not None and log_s - length > slack_s}  # fmt: skip
    listed = ", ".join(f"{name} {length:.0f} s{cut.get(name, '')}" for name, length, _, _ in short)
    give = (
        " Give --sim logs at least as long as the real log, each with a truth covering all of it"
        if cut
        else " Give --sim logs at least as long as the real log"
    )
    note = (
        f"{len(short)} of {len(baseline)} --sim logs are"
        f" {'scored over less time than' if cut else 'shorter than'} the real log"
        f" ({real_s:.0f} s): {listed}. Past a sim log's end the real log has no simulated"
        " counterpart: the held-out part and the longest time scales are compared with fewer"
        f" runs or none (a figure with no run is not a finding).{give}"
    )
    print(f"x6wd gap: warning: {note}", file=sys.stderr)
    return [note]


def _log_time_and_height(
    args: argparse.Namespace, track: Track, truth_track: Track | None
) -> tuple[float | None, float, str]:
    """What the scenario's runs take from the real log (:func:`place_at_log`): the UTC (s) of
    its error series' first epoch when the log is dated, else None; and the site's altitude
    (m, NaN unknown) with whose it is: --truth's, the truth track's mean, or the log's mean."""
    start_s = log_start_s(track, truth_track)
    start = start_s if is_date(start_s) else None
    if args.truth is not None and math.isfinite(alt_m := parse_truth(args.truth)[2]):
        return start, alt_m, "--truth's altitude"
    if truth_track is not None and math.isfinite(alt_m := mean_alt_m(truth_track)):
        return start, alt_m, "the truth track's mean altitude"
    return start, mean_alt_m(track), "the real log's mean altitude"


def _heights_not_compared(note: str, reason: str) -> str:
    """A note saying that the real log has no heights, when it has them but no height error
    (the truth has none), made accurate: it is the height errors that are missing."""
    if note.startswith("the real log has no ") and "heights:" in note:
        return note.replace(
            "heights:", f"height errors (its heights are not compared: {reason}):", 1
        )
    return note


# The baseline when the user names none: open sky, the default receiver, at the log's place
# and time (place_at_log), so a first report needs no scenario file.
DEFAULT_SCENARIO = PACKAGED_CONFIG_DIR / "scenarios" / "open_field.toml"


def main(args: argparse.Namespace) -> int:
    """Run the diagnosis and write the report; exit code 0 (whatever the verdict)."""
    bar = ProgressBar(enabled=not args.quiet and sys.stderr.isatty())
    if args.sim:
        # the --sim logs are the baseline: options of the scenario's runs would be ignored
        given = [f"--{name}" for name in ("seeds", "workers", "scheduler")
                 if getattr(args, name) is not None]  # fmt: skip
        if given:
            raise ConfigError(
                f"{' and '.join(given)} with --sim: {'they apply' if len(given) > 1 else 'it'}"
                f" {'' if len(given) > 1 else 'applies '}to a --scenario's runs; with --sim the"
                " baseline is the given logs (drop it, or give --scenario instead of --sim)"
            )
    if args.seeds is None:
        args.seeds = DEFAULT_SEEDS
    # a mistaken --out is named now, not after the diagnosis; an earlier run's outputs go now,
    # so that a run cut short (a full disk) never leaves them beside its own
    remove_earlier_outputs(output_dir(args.out))
    bar("reading logs", 0.0)
    check_real_truth(args)
    truth_track = read_input(args.truth_track) if args.truth_track is not None else None
    real_track = read_input(args.real)
    check_step(real_track)
    real = to_errors(real_track, args, truth_track, "real")
    check_still(args, [args.real], [real_track], [truth_track])
    check_real_truth(args, real)
    try:
        check_real(real)  # refused before the runs are placed and their almanac's age warned of
    except ConfigError as exc:  # named with its file, as the readers' refusals are
        # with what reading dropped: 300 epochs of one time stamp read as "1 epoch"
        read = f" (reading the log: {'; '.join(real_track.notes)})" if real_track.notes else ""
        raise ConfigError(f"{args.real}: {exc}{read}") from exc
    notes = [f"reading the real log: {note}" for note in real_track.notes]
    if truth_track is not None:
        notes += [f"reading the truth track: {note}" for note in truth_track.notes]
        moved = realign_note(real_track, truth_track)
        if moved is not None:
            notes.append(moved)
            print(f"x6wd gap: warning: {moved}", file=sys.stderr)
        offset = time_offset_note(real_track, truth_track)
        if offset is not None:
            notes.append(offset)
            print(f"x6wd gap: warning: {offset}", file=sys.stderr)
    if (
        args.truth
        and not math.isfinite(parse_truth(args.truth)[2])
        and np.any(np.isfinite(real_track.alt_m[real_track.valid]))
    ):
        notes.append(
            "the real log's heights are not compared: --truth has no ALT (LAT,LON,ALT, in the"
            " log's height system)"
        )
    if args.truth is None and truth_track is None:
        notes.append(
            "no truth given: errors are taken against each log's own mean, so a bias is invisible"
        )
    # the farthest --sim log (km) when they simulate another place: the verdict says so
    other_place_km: float | None = None
    if not args.sim and not args.scenario:
        args.scenario = str(DEFAULT_SCENARIO)
        notes.append(
            "no --scenario or --sim: the baseline is the packaged open-field scenario"
            " (config/scenarios/open_field.toml: open sky, no buildings), placed at the log;"
            " give a scenario of the site for buildings, walls or another receiver model"
        )
    if args.scenario:
        from sim_backend.executor import Executor
        from sim_backend.world import load_world
        from x6wd.gap.scenario import place_at_log, scenario_baseline

        world, placed = place_at_log(
            load_world(args.scenario), real, *_log_time_and_height(args, real_track, truth_track)
        )
        notes += placed
        for note in placed[1:]:  # the almanac's age at the log's date
            print(f"x6wd gap: warning: {note}", file=sys.stderr)
        cluster = args.workers is not None or args.scheduler is not None
        with Executor(args.scheduler, args.workers, inline=not cluster) as executor:
            baseline = scenario_baseline(
                world,
                real,
                args.seeds,
                progress=lambda i: bar(f"simulating seed {i}/{args.seeds}", 0.05 * i / args.seeds),
                executor=executor,
            )
        if args.truth is None and truth_track is None:
            # the real log's errors are against its own mean: the runs' must be too, or
            # every level cell (CEP50, R95, the means) reads the runs' hour offsets as a gap
            baseline = [against_own_mean(s) for s in baseline]
    else:
        sims = [read_input(p) for p in args.sim]
        for sim in sims:
            check_step(sim)
        if args.truth is not None:
            check_sim_truths_at_point(args, sims)
        # each --sim log against its own truth when it carries one (truth.csv beside it):
        # a closed-loop mission's run drove its own route, not the real log's
        sim_truths: list[Track | None] = [truth_track] * len(sims)
        unread: dict[str, str] = {}  # --sim log -> why the truth.csv beside it was not read
        if truth_track is not None:
            found = [sim_truth(p, args.truth_track) for p in args.sim]
            sim_truths = [truth_track if own is None else own for own, _, _ in found]
            notes += [note for _, note, _ in found if note is not None]
            unread = {p: why for p, (_, _, why) in zip(args.sim, found, strict=True) if why}
            for why in unread.values():
                print(f"x6wd gap: warning: {SIM_TRUTH_NAME} not read: {why}", file=sys.stderr)
            check_shared_truths(args.sim, sim_truths, truth_track)
            check_same_motion(args, (real_track, truth_track), args.sim, sims, sim_truths)
        else:
            check_sims_still(args, args.sim, sims)
        check_still(args, args.sim, sims, sim_truths)
        baseline = [
            to_errors(sim, args, truth, "sim", own_truth=truth is not truth_track)
            for sim, truth in zip(sims, sim_truths, strict=True)
        ]
        for path, series in zip(args.sim, baseline, strict=True):
            enough_fixes(series, f"--sim log {path}")  # named (the check's "log 2 of 2" is not)
        if truth_track is not None:
            check_own_truths((real_track, real), sims, baseline, sim_truths, truth_track, args.sim)
            check_sim_routes(real, baseline, sim_truths, truth_track, args.sim, unread)
            notes.append(sim_truths_note(sim_truths, truth_track, args))
            notes += realigned_sims_notes(args.sim, sims, sim_truths, baseline)
        notes += short_sims_notes(real, baseline, args.sim, sims, sim_truths)
        if args.truth is None and truth_track is None:
            # not refused (as a far log is against a --truth): without a truth the errors
            # are computed right, about another sky; the verdict's first words say so
            far = place_note(real_track, sims, args.sim)
            if far is not None:
                notes.append(far)
                print(f"x6wd gap: warning: {far}", file=sys.stderr)
                other_place_km = max(d_m for _, d_m in far_sims(real_track, sims, args.sim)) / 1e3
    rng = np.random.default_rng(args.seed)
    diagnosis = diagnose(real, baseline, rng, Options(replicates=args.replicates), progress=bar)
    diagnosis.notes.extend(notes)
    if not has_up(real) and np.any(np.isfinite(real_track.alt_m[real_track.valid])):
        reason = "--truth has no ALT" if args.truth else "the truth track has no heights"
        diagnosis.notes[:] = [_heights_not_compared(note, reason) for note in diagnosis.notes]
    compass = compass_diagnosis(args, diagnosis, rng, bar)
    bar("writing report", 1.0)
    origin = None
    if args.scenario:
        from sim_backend.world import load_world

        world = load_world(args.scenario)
        origin = (world.origin.lat_deg, world.origin.lon_deg)
    write_report(
        diagnosis,
        Path(args.out),
        real_name=Path(args.real).name,
        figures=not args.no_figures,
        compass=compass,
        origin_deg=origin,
        other_place_km=other_place_km,
    )
    extra = f"; {compass_verdict_text(compass)}" if compass is not None else ""
    verdict = verdict_line(diagnosis, other_place_km)
    print(f"{verdict}{extra}; report in {Path(args.out) / 'report.md'}")
    calibration = diagnosis.calibration
    if calibration is not None:
        if diagnosis.written:
            print(f"validation, selected effects only: {calibration.selected.summary()}")
        else:
            print(f"validation, the baseline runs alone: {calibration.selected.summary()}")
        if diagnosis.candidate_validation is not None:
            print(candidate_text(diagnosis))
        print(
            f"validation, calibrated (in sample; {Path(args.out) / 'calibrated.toml'}): "
            f"{calibration.calibrated.summary()}; the runs' own spread: "
            f"{spread_text(calibration.selected)}"
        )
        if not calibration.calibrated.passed:
            print(f"calibrated validation {calibration.miss_text()}")
    if not math.isfinite(diagnosis.closure):
        return 1
    return 0


def compass_diagnosis(
    args: argparse.Namespace, diagnosis: Diagnosis, rng: np.random.Generator, bar: ProgressBar
) -> CompassDiagnosis | None:
    """The compass half, when the real log is a recording with attitude records and a heading
    truth (``--truth-track`` with a heading column, ``truth.csv`` beside the recording, or the
    GPS course over ground while moving); None otherwise. Baseline: the scenario's CMPS10
    along the real truth (``--scenario``), or the ``--sim`` recordings that carry attitude
    records and a heading truth of their own. Problems become notes in ``diagnosis``, never errors:
    the GPS report stands on its own."""
    from x6wd.gap.compass import (
        HEADING_REFERENCES,
        CompassOptions,
        diagnose_compass,
        read_heading_log,
        scenario_compass_baseline,
    )

    try:  # a recording the GPS side read; what the compass side cannot read is a note
        real_log = read_heading_log(args.real, args.truth_track)
    except X6wdError as exc:
        diagnosis.notes.append(f"compass: not diagnosed ({exc})")
        return None
    if real_log is None:
        return None
    real, reference = real_log.series, real_log.reference
    opts = CompassOptions(replicates=args.replicates)
    # Every baseline log is read against the kind of heading truth the real log has: an
    # exact heading against a course over ground compares different noise (sideslip, the
    # course's own noise) and finds a gap that is the reference's, not the compass's.
    compass_notes = [
        f"compass: heading reference: {HEADING_REFERENCES[reference]}, for the real log and"
        " every baseline log alike",
        *(f"compass: the real log: {note}" for note in real_log.notes),
    ]
    if args.scenario and reference == "cog":
        diagnosis.notes.append(
            "compass: not diagnosed (the real log has no heading truth: its heading errors"
            " are against the GPS course over ground, which differs from the heading by the"
            " sideslip and the course's noise; the scenario's CMPS10 can only be driven along"
            " that course, so its errors would lack that noise and any difference would read"
            " as a compass gap. Give a heading truth (--truth-track with a heading column, or"
            " truth.csv beside the recording), or --sim recordings, read by their own course"
            " over ground as the real log is)"
        )
        return None
    if args.scenario:
        bar("compass: simulating the CMPS10", 0.9)
        baseline, field_model = scenario_compass_baseline(args.scenario, real, args.seeds)
        opts = CompassOptions(
            replicates=args.replicates,
            inclination_deg=field_model.inclination_deg,
            horizontal_field_ut=field_model.horizontal_ut,
        )
    else:
        logs = []
        for p in args.sim:
            try:
                logs.append(read_heading_log(p, reference=reference))
            except X6wdError as exc:
                compass_notes.append(f"compass: --sim log {p} not read ({exc})")
                logs.append(None)
        compass_notes += [
            f"compass: --sim log {p}: {note}"
            for p, log in zip(args.sim, logs, strict=True)
            if log is not None
            for note in log.notes
        ]
        baseline = [log.series for log in logs if log is not None]
        left_out = [p for p, log in zip(args.sim, logs, strict=True) if log is None]
        if left_out and baseline:
            compass_notes.append(
                f"compass: {len(left_out)} of {len(args.sim)} --sim logs have no compass samples"
                f" with {HEADING_REFERENCES[reference]} and were left out: {', '.join(left_out)}"
            )
    if not baseline:
        diagnosis.notes.append(
            "compass: the real log has heading data but no baseline log has compass samples with"
            f" {HEADING_REFERENCES[reference]} (the real log's heading reference): not diagnosed"
        )
        return None
    try:
        outcome = diagnose_compass(real, baseline, rng, opts, progress=bar)
    except ConfigError as exc:
        diagnosis.notes.append(f"compass: not diagnosed ({exc})")
        print(f"x6wd gap: warning: compass: not diagnosed ({exc})", file=sys.stderr)
        return None
    outcome.notes[:0] = compass_notes
    return outcome
