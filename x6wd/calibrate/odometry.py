"""Odometry calibration from a straight-track and a circular-track recording (seed 003, 2.3).

Inputs are flight recordings (:mod:`x6wd.core.recorder`) holding ``odometry`` records (the
motor board's unwrapped encoder counts) and ``fix`` records that are the REFERENCE: a
receiver good to centimetres (RTK) or the simulator's truth written as fixes (GGA quality 4).
Their error is taken as independent between fixes with standard deviation ``ref_sigma_m``
per axis, by default from the fixes' GGA quality (:func:`choose_reference`): RTK fixed and
float are a reference, anything else (a NEO-5's GPS fixes, metres and correlated in time)
is refused unless ``ref_sigma_m`` is given.

Both recordings are cut into PASSES: motion between stops of at least ``stop_s`` (no count
changes). A pass's start and end points are the mean of the reference fixes during the stops
around it (the robot stands still, so averaging is free), its counts the exact difference
over the pass. The protocol the operator drives (docs in :func:`calibrate`):

- straight track: several passes along a straight line (forwards, or forwards and back);
  passes shorter than ``min_pass_m`` (pivots to turn round, nudges) are ignored;
- circle: constant drive for one or more whole laps per pass, several passes.

Estimation, with metres per count ``α = π·D / counts_per_rev``:

1. Diameters (straight). The sides roll the pass length L_i (along the reference path,
   :func:`path_geometry`) ± ``B·Δψ_i/2`` for the path's heading change Δψ_i (a pass that
   bows), so ``α̂_l = Σ (L_i + B·Δψ_i/2) / Σ c_l,i`` (the paper's ``D = L·CPR / (π·c)``
   pooled over passes; the ratio estimator is best when the variance grows with L).
   Likewise right, with − B·Δψ_i/2. B comes from step 2; the two are iterated.
2. Effective track (circle). With the calibrated α̂: ``s_l − s_r = B·Δψ`` (clockwise), the
   true heading change Δψ from the reference: a circle fitted to the pass's fixes and the
   unwrapped angle swept about its centre. ``B̂ = Σ (s_l − s_r) / Σ Δψ`` — the paper's
   ``B_new = B_old · Δψ_odometry / Δψ_true``, pooled.
3. Non-systematic k_l, k_r (seed 003: Var(side travel) = k·|travel|), from the pass-to-pass
   scatter of the residuals of each track. Both sides are compared with the same reference,
   so its error cancels in ``E[r_l² − r_l·r_r] = k_l·|s_l|`` (and symmetrically for the
   right); the sums are corrected for the degrees of freedom the fits used. As the paper
   does, the larger of the straight and circle values is kept per side.

Standard errors: α̂ from the residual scatter (it includes the reference error); B̂ from the
residual scatter of ``s_l − s_r − B̂·Δψ`` (or, with fewer than 3 circle passes, from the
straight's k and the reference angle error) plus the diameters' errors carried through; k
from the spread of the per-pass terms (with n passes it is roughly k·sqrt(2/n): many passes
are needed for a k good to 20 %).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import numpy.typing as npt

from x6wd.core.config import OdometryConfig, build
from x6wd.core.errors import ConfigError, ParseError
from x6wd.core.recorder import ReadStats, decode_record, read_recording_parts
from x6wd.core.records import GpsFix, WheelOdometry
from x6wd.nav.controller import has_usable_position
from x6wd.nav.geo import LocalTangentPlane

Array = npt.NDArray[np.float64]
MIN_PASSES = 3  # repetitions needed for the scatter-based k and standard errors
ODOMETRY_MAX_COUNTS = 1e15  # ~1e9 km of 120 mm wheels: beyond it a count is a writer's fault


@dataclass(frozen=True)
class Track:
    """One recording reduced to what calibration uses: encoder counts (cumulative) at their
    times (s) and reference positions (m, east/north of ``origin``) at theirs."""

    t_odo_s: Array
    left_counts: npt.NDArray[np.int64]
    right_counts: npt.NDArray[np.int64]
    t_ref_s: Array
    east_m: Array
    north_m: Array
    ref_quality: npt.NDArray[np.int64]  # each fix's GGA quality (4 RTK fixed, 1 GPS, ...)
    origin: tuple[float, float] = (0.0, 0.0)  # (lat_deg, lon_deg) of the plane
    skipped: int = 0  # recording lines or records that could not be read

    @classmethod
    def from_records(
        cls, odometry: list[WheelOdometry], fixes: list[GpsFix], origin: tuple[float, float] | None
    ) -> Track:
        """From decoded records; fixes the robot could not use are dropped (not valid, no
        position, HDOP 20 or more: :func:`x6wd.nav.controller.has_usable_position`); the
        plane's origin is ``origin`` or the first usable fix."""
        good = [f for f in fixes if has_usable_position(f)]
        if len(odometry) < 2:
            raise ParseError("no odometry: the recording holds fewer than 2 odometry records")
        if len(good) < 2:
            raise ParseError("no reference: the recording holds fewer than 2 valid fixes")
        odometry = sorted(odometry, key=lambda o: o.t_s)
        good = sorted(good, key=lambda f: f.t_s)
        lat0, lon0 = origin or (float(good[0].lat_deg), float(good[0].lon_deg))  # type: ignore[arg-type]
        plane = LocalTangentPlane(lat0, lon0)
        x, y = plane.to_xy(
            np.array([f.lat_deg for f in good], float), np.array([f.lon_deg for f in good], float)
        )
        return cls(
            t_odo_s=np.array([o.t_s for o in odometry], float),
            left_counts=np.array([o.left_counts for o in odometry], np.int64),
            right_counts=np.array([o.right_counts for o in odometry], np.int64),
            t_ref_s=np.array([f.t_s for f in good], float),
            east_m=np.asarray(x, float),
            north_m=np.asarray(y, float),
            ref_quality=np.array([f.quality for f in good], np.int64),
            origin=(lat0, lon0),
        )

    def fixes_of(self, qualities: tuple[int, ...]) -> Track:
        """The track with only the reference fixes of these GGA qualities."""
        keep = np.isin(self.ref_quality, qualities)
        return dataclasses.replace(
            self,
            t_ref_s=self.t_ref_s[keep],
            east_m=self.east_m[keep],
            north_m=self.north_m[keep],
            ref_quality=self.ref_quality[keep],
        )


def _numbers(*values: object, none: bool = False) -> bool:
    """Every value a real number (not a bool), or None where ``none``."""
    return all(
        (none and v is None) or (isinstance(v, (int, float)) and not isinstance(v, bool))
        for v in values
    )


def _bad_value(rec: WheelOdometry | GpsFix) -> str | None:
    """What is wrong with a record's numbers that the arrays would hide, or None: a count
    that is not a whole number (np.int64 truncates 1234.5 and fails on NaN), a time or a
    used position that is not finite (it would poison every mean it enters)."""
    values: dict[str, float | None] = {"t_s": rec.t_s}
    if isinstance(rec, WheelOdometry):
        for side in ("left_counts", "right_counts"):
            v = getattr(rec, side)
            if not (math.isfinite(v) and float(v).is_integer()):
                return f"{side} must be a whole number of counts, got {v!r}"
            if not -ODOMETRY_MAX_COUNTS <= v <= ODOMETRY_MAX_COUNTS:  # would overflow int64
                return f"{side} must be within +-{ODOMETRY_MAX_COUNTS:.0e} counts, got {v!r}"
    elif rec.valid:  # an invalid fix's position is dropped unused
        values |= {"lat_deg": rec.lat_deg, "lon_deg": rec.lon_deg}
    for name, value in values.items():
        if value is not None and not math.isfinite(value):
            return f"{name} must be finite, got {value!r}"
    return None


def load_track(path: str | Path, origin: tuple[float, float] | None = None) -> Track:
    """The odometry and fix records of a recording (all its parts). Lines that are not
    records, and odometry or fix records with fields of the wrong type, are skipped and
    counted in the track's ``skipped`` (the CLI says how many). A number of the right type
    but unusable (NaN, a fractional count) raises ParseError naming the file and record: it
    is no torn line but a writer's fault, and skipping it would shift a pass's counts."""
    odo: list[WheelOdometry] = []
    fixes: list[GpsFix] = []
    stats = ReadStats()
    malformed = 0
    seen = {"odometry": 0, "fix": 0}
    for rec in read_recording_parts(path, stats=stats):
        if rec.type in seen:
            seen[rec.type] += 1
            typed = decode_record(rec)
            # the values go into numeric arrays: a count of "abc" makes a bad record; a fix
            # without a position (None) is a no-fix epoch, dropped later, not a bad record
            if isinstance(typed, WheelOdometry):
                if not _numbers(typed.t_s, typed.left_counts, typed.right_counts):
                    malformed += 1
                    continue
                odo.append(typed)
            elif isinstance(typed, GpsFix):
                if (
                    not _numbers(typed.t_s)
                    or not _numbers(typed.lat_deg, typed.lon_deg, none=True)
                    or not isinstance(typed.quality, int)
                    or isinstance(typed.quality, bool)
                ):
                    malformed += 1
                    continue
                fixes.append(typed)
            else:
                continue
            why = _bad_value(typed)
            if why is not None:
                raise ParseError(
                    f"{path}: {rec.type} record {seen[rec.type]} (t_mono {rec.t_mono:.3f} s): {why}"
                )
    try:
        track = Track.from_records(odo, fixes, origin)
    except ParseError as exc:
        raise ParseError(f"{path}: {exc}") from exc
    return dataclasses.replace(track, skipped=malformed + stats.bad_lines + stats.truncated)


QUALITY_NAMES = {
    0: "invalid or not recorded", 1: "GPS", 2: "DGPS", 3: "PPS", 4: "RTK fixed", 5: "RTK float",
    6: "dead reckoning", 7: "manual input", 8: "simulation",
}  # fmt: skip
"""GGA fix quality (NMEA 0183) by number."""

RTK_FIXED = 4  # GGA quality of an RTK fixed solution
RTK_SIGMA_M = {RTK_FIXED: 0.02, 5: 0.3}
"""The reference's error per fix and axis (m) by GGA quality, for the qualities that are a
reference. RTK fixed: centimetres (the simulator's truth is written as quality 4, with 2 cm
of noise). RTK float: the carrier's ambiguities are not fixed, so decimetres (0.1-0.5 m once
converged, more before): 0.3 m, the upper middle, so as not to flatter the standard errors.
Anything else (GPS, DGPS: metres, correlated over minutes) is no reference for wheels
measured to 0.1 mm: refused unless the user gives ``ref_sigma_m``."""


def _quality_text(counts: Mapping[int, int]) -> str:
    """'600 fixes of quality 1 (GPS), 3 of quality 2 (DGPS)'."""
    parts = [
        f"{n} {'fixes ' if i == 0 else ''}of quality {q} ({QUALITY_NAMES.get(q, 'unknown')})"
        for i, (q, n) in enumerate(sorted(counts.items()))
    ]
    return ", ".join(parts)


def _counts(quality: npt.NDArray[np.int64]) -> dict[int, int]:
    values, n = np.unique(quality, return_counts=True)
    return {int(q): int(c) for q, c in zip(values, n, strict=True)}


@dataclass(frozen=True)
class Reference:
    """What the reference fixes are: the sigma per fix and axis (m) the standard errors
    assume, whether the user gave it, the fixes used by GGA quality (both tracks), and per
    track the fixes left out by quality (not RTK, with RTK ones to use instead)."""

    sigma_m: float
    given: bool
    used: Mapping[int, int]
    left_out: Mapping[str, Mapping[int, int]]

    @property
    def rtk(self) -> bool:
        """Every fix used is RTK fixed or float."""
        return all(q in RTK_SIGMA_M for q in self.used)

    def summary(self) -> str:
        """'sigma 0.02 m per fix (1488 fixes of quality 4 (RTK fixed))' and where the sigma
        came from when given."""
        how = " as given with --ref-sigma-m" if self.given else ""
        return f"sigma {self.sigma_m:g} m per fix{how} ({_quality_text(self.used)})"

    def notes(self) -> list[str]:
        """What the user must know about the reference, one line each (stderr and the
        fragment's comments): fixes left out, a float reference, a reference not RTK."""
        lines = [
            f"{name} recording: {_quality_text(n)} left out of the reference: not RTK "
            "(only RTK fixed (4) and float (5) fixes are used unless --ref-sigma-m is given)"
            for name, n in self.left_out.items()
            if n
        ]
        if not self.rtk:
            lines.append(
                f"NOT A CALIBRATION: the reference is not RTK ({_quality_text(self.used)}), "
                f"taken at the {self.sigma_m:g} m per fix given: such fixes are metres off, "
                "the error correlated over minutes, so every estimate carries it and its "
                "standard error need not show it (docs/odometry.md, 'Calibrating')"
            )
        elif 5 in self.used and not self.given:
            lines.append(
                f"{self.used[5]} reference fixes are RTK float (quality 5): sigma "
                f"{self.sigma_m:g} m per fix, not RTK fixed's {RTK_SIGMA_M[4]:g}; wait for a "
                "fixed solution for better estimates"
            )
        return lines


def choose_reference(
    straight: Track, circle: Track, ref_sigma_m: float | None = None
) -> tuple[Track, Track, Reference]:
    """The tracks with the fixes to use as the reference, and what that reference is.

    ``ref_sigma_m`` None: the fixes' GGA quality decides. Only RTK fixed (4) and float (5)
    fixes are used, the others left out and counted; the sigma is :data:`RTK_SIGMA_M` of
    the worst quality used. A track with no RTK fix is refused (ConfigError naming the
    qualities and counts): a NEO-5's metre-level, time-correlated error made diameters 4 %
    high at 2 SEs (an outside audit, a HIL session) while the fragment claimed 2 cm.
    ``ref_sigma_m`` given: the user says what the reference is; every valid fix is used.
    """
    tracks = {"straight": straight, "circle": circle}
    if ref_sigma_m is not None:
        if not (ref_sigma_m > 0 and math.isfinite(ref_sigma_m)):
            raise ConfigError(f"ref_sigma_m must be > 0, got {ref_sigma_m!r}")
        used = _counts(np.concatenate([t.ref_quality for t in tracks.values()]))
        return straight, circle, Reference(ref_sigma_m, True, used, {})
    rtk = tuple(RTK_SIGMA_M)
    if all(np.any(t.ref_quality == RTK_FIXED) for t in tracks.values()):
        # fixed fixes in both recordings: a float one among them (a brief loss of the
        # ambiguities) is left out, not let set the sigma of all (15x the standard errors)
        rtk = (RTK_FIXED,)
    kept = {name: t.fixes_of(rtk) for name, t in tracks.items()}
    none = [name for name, t in kept.items() if t.t_ref_s.size == 0]
    if none:
        which = "; ".join(f"{n}: {_quality_text(_counts(tracks[n].ref_quality))}" for n in none)
        raise ConfigError(
            f"the reference is not RTK ({which}; no fix of quality 4 (RTK fixed) or 5 (RTK "
            "float)): such fixes are metres off, the error correlated over minutes, far too "
            "coarse to measure the wheels (a HIL session's GPS fixes gave diameters 4 % high "
            "under a header claiming a 2 cm reference). Record with an RTK receiver as the GPS "
            "(in simulation: tools/calibration-runs writes the truth as RTK fixes), or give "
            "--ref-sigma-m SIGMA to take these fixes at SIGMA m per fix anyway"
        )
    used = _counts(np.concatenate([t.ref_quality for t in kept.values()]))
    left_out = {
        name: _counts(t.ref_quality[~np.isin(t.ref_quality, rtk)]) for name, t in tracks.items()
    }
    sigma = max(RTK_SIGMA_M[q] for q in used)
    return kept["straight"], kept["circle"], Reference(sigma, False, used, left_out)


@dataclass(frozen=True)
class Pass:
    """Motion between two stops: count differences, the start and end points (mean of the
    reference fixes during the stops, and how many), and the fixes while moving."""

    t0_s: float
    t1_s: float
    d_left_counts: int
    d_right_counts: int
    start_m: tuple[float, float]
    end_m: tuple[float, float]
    n_start: int
    n_end: int
    path_m: Array  # (n, 2) reference positions while moving, in time order
    path_t_s: Array  # (n,) their times, s
    back_counts: int = 0  # the larger side's counts against its net direction (a reversal)
    back_left_counts: int = 0  # the left side's counts against its own net direction
    back_right_counts: int = 0  # the right side's


def find_passes(track: Track, *, stop_s: float = 1.0) -> tuple[list[Pass], int]:
    """The passes of a track and how many were dropped for want of reference fixes in the
    stops around them. A stop is ``stop_s`` or more without count changes; fixes within
    ``stop_s / 2`` of the motion are not used as stationary (GPS latency)."""
    t, lc, rc = track.t_odo_s, track.left_counts, track.right_counts
    moving = np.flatnonzero(np.abs(np.diff(lc)) + np.abs(np.diff(rc)) > 1) + 1
    if moving.size == 0:
        return [], 0
    groups: list[tuple[int, int]] = []  # (index of the last still sample, last moving one)
    first = prev = int(moving[0])
    for i in moving[1:]:
        if t[i] - t[prev] >= stop_s:
            groups.append((first - 1, prev))
            first = int(i)
        prev = int(i)
    groups.append((first - 1, prev))
    guard_s = 0.5 * stop_s
    tr = track.t_ref_s
    xy = np.column_stack([track.east_m, track.north_m])
    passes, dropped = [], 0
    for k, (i0, i1) in enumerate(groups):
        back_l, back_r = _back_counts(lc[i0 : i1 + 1]), _back_counts(rc[i0 : i1 + 1])
        t0, t1 = float(t[i0]), float(t[i1])
        before = t[groups[k - 1][1]] + guard_s if k else -math.inf
        after = t[groups[k + 1][0]] if k + 1 < len(groups) else math.inf
        start = (tr > before) & (tr <= t0)
        end = (tr >= t1 + guard_s) & (tr <= after)
        if not start.any() or not end.any():
            dropped += 1
            continue
        inside = (tr > t0) & (tr < t1)
        passes.append(
            Pass(
                t0, t1,
                int(lc[i1] - lc[i0]), int(rc[i1] - rc[i0]),
                _point(xy[start]), _point(xy[end]),
                int(start.sum()), int(end.sum()),
                xy[inside], tr[inside],
                max(back_l, back_r), back_l, back_r,
            )
        )  # fmt: skip
    return passes, dropped


def _back_counts(counts: npt.NDArray[np.int64]) -> int:
    """Counts rolled against the net direction over a stretch of cumulative counts."""
    steps = np.diff(counts)
    return int((np.abs(steps).sum() - abs(int(steps.sum()))) // 2)


def _point(xy: Array) -> tuple[float, float]:
    m = xy.mean(axis=0)
    return float(m[0]), float(m[1])


@dataclass(frozen=True)
class Estimate:
    """A value and its standard error (same unit); ``resolved`` False for a k whose
    estimate is not significantly above 0 (under :data:`K_RESOLVED_SES` SEs; below 0 it is
    clamped: the passes' scatter did not show the wheel's noise), or for the bound written
    in place of such a k."""

    value: float
    se: float
    resolved: bool = True


def fit_circle(xy: Array) -> tuple[float, float, float]:
    """Least-squares (algebraic, Kåsa) circle through points: (east_m, north_m, radius_m)."""
    x, y = xy[:, 0], xy[:, 1]
    a = np.column_stack([x, y, np.ones_like(x)])
    (p, q, r), *_ = np.linalg.lstsq(a, -(x * x + y * y), rcond=None)
    xc, yc = -p / 2, -q / 2
    return float(xc), float(yc), float(math.sqrt(max(xc * xc + yc * yc - r, 0.0)))


K_RESOLVED_SES = 2.0
"""A k counts as resolved only this many SEs above 0. A k just above 0 with an SE larger
than itself (a second outside audit: k_right_m = 7.865e-06 ± 8.6e-06, true 2e-4) says no
more than a clamped 0 does, and written as a value it would tell the estimator the wheel
hardly slips."""


def _k_terms(u: Array, scale: float) -> Estimate:
    """k from per-pass terms u (sum / scale), SE from their spread; clamped at 0, and not
    resolved unless :data:`K_RESOLVED_SES` SEs above 0."""
    n = u.size
    se = math.sqrt(n * float(np.var(u, ddof=1))) / scale if n > 1 else math.inf
    k = float(u.sum()) / scale
    return Estimate(max(k, 0.0), se, k > K_RESOLVED_SES * se)


def _pick_k(straight: Estimate, circle: Estimate) -> Estimate:
    """The larger resolved k of the two tracks (as the paper keeps the larger). When neither
    is resolved (0, or under 2 SEs above it), a 0 or a tiny k would tell the estimator the
    wheels never slip: an upper bound is written instead, the larger of k + SE over the
    tracks with a finite SE (0 + SE for a clamped k), marked not resolved."""
    resolved = [e for e in (straight, circle) if e.resolved]
    if resolved:
        return max(resolved, key=lambda e: e.value)
    bound = max((e.value + e.se for e in (straight, circle) if math.isfinite(e.se)), default=0.0)
    return Estimate(bound, bound, resolved=False)


MIN_DOF = 5
"""Degrees of freedom (passes − 1 per track) below which the fragment and the command warn
that the standard errors are rough: an SE from ν degrees of freedom is itself uncertain by
about 1/sqrt(2ν) (50 % at 2, 32 % at 5), and a k near 0 can come out as 0."""


@dataclass(frozen=True)
class StraightResult:
    """Metres per count per side (α) with their covariance, the pass count and length, and
    the straight track's k's."""

    alpha_left: float
    alpha_right: float
    cov_alpha: Array  # 2x2, (m/count)²
    passes: int
    mean_length_m: float
    k_left_m: Estimate
    k_right_m: Estimate
    found: int = 0  # passes between stops, used or not
    returned: int = 0  # of the unused: a side turned both ways (runs merged, or a pivot)
    pivoted: int = 0  # of the returned: one side only counted backwards (a pivot merged in)
    left_out: tuple[str, ...] = ()  # why each pass was left out, naming it by its times
    turned: int = 0  # of the unused: the reference path turned too far (not straight)
    turn_deg: float = 0.0  # the largest heading change of a pass used, deg


BACK_NOISE_COUNTS = 10
BACK_FRACTION = 0.002
"""A side of a straight pass may count against its own net direction by at most
``BACK_NOISE_COUNTS + BACK_FRACTION * |its net counts|`` (a straight pass's counts creep back
by a count or two of noise; the simulator's by none). More is a turn in place or a reversal
merged into the pass: a 180-degree pivot flowing into a 19 m drive with no stop between
rolls one side back ~3 % of the pass (an outside audit: diameters 10 SEs off, track 0.163 m
for 0.370 m, exit 0, under the 10 % the merged-runs test allowed)."""


def _pass_name(p: Pass) -> str:
    return f"pass {p.t0_s:.1f}-{p.t1_s:.1f} s"


MERGED_NOTE = (
    "a side counting backwards within a pass is a reversal or a pivot with no stop of "
    "--stop-s between it and the drive, so the pass's ends are not one straight run apart: "
    "stand still 4 s or more between runs, and between a pivot and the drive"
)


def _not_straight(p: Pass) -> str | None:
    """Why a straight pass's counts are not those of one straight run (naming the pass by
    its times), or None."""
    net = {"left": abs(p.d_left_counts), "right": abs(p.d_right_counts)}
    back = {"left": p.back_left_counts, "right": p.back_right_counts}
    if p.back_counts > 0.1 * max(net.values()) + 10:
        # Runs out and back with no stop of stop_s between (the motors' lag eats a short
        # commanded stop) merge into one "pass" whose wheels turned both ways: its net
        # length is not what they rolled (and the k terms need the rolled travel).
        what = "runs out and back merged"
    else:
        sides = [s for s in back if back[s] > BACK_NOISE_COUNTS + BACK_FRACTION * net[s]]
        if not sides:
            return None
        what = "a pivot merged into the drive" if len(sides) == 1 else "a turn merged in"
    counted = ", ".join(f"{s} {back[s]} of {net[s]} net" for s in back if back[s])
    return f"{_pass_name(p)}: counts back ({counted}): {what}"


MAX_STRAIGHT_TURN_DEG = 30.0
"""A straight pass whose reference path turns more than this between its ends (deg) is left
out: the bow is taken into account (:func:`path_geometry`, the effective track), but a
larger turn is no straight drive, and its sides' travel rests on the track's error."""

BOW_NOTE_DEG = 5.0
"""From this heading change between a straight pass's ends (deg) the fragment says the passes
bow (and were taken as such); the documented runs' straight passes: at most 1.8 deg (noise,
30 seeds)."""

BEND_SIGMAS = 3.0
"""A straight pass whose reference fixes scatter about the smooth path fitted to them
(:func:`path_geometry`) by more than this many times the reference's sigma (rms) is left
out: its path bends sharply, a turn merged into the drive (the simulator's robot turning at
50/0 % for 2 s into a 50/50 % drive: 4x; 444 good passes: 0.67-1.29x). Such a kink is smoothed
by the fit, its heading change underestimated and the diameters biased (2.3 SEs)."""

TURN_NOTE = (
    f"a pass whose reference path turns more than {MAX_STRAIGHT_TURN_DEG:g} deg between its "
    "ends, or bends sharply (a turn merged into the drive with no stop of --stop-s between), "
    "is no straight drive"
)


def path_geometry(p: Pass) -> tuple[float, float, float]:
    """The pass's length along its reference path (m), the path's heading change between
    its ends (rad, clockwise) and the rms of the moving fixes about the path (m), from a
    polynomial (degree <= 4) fitted to the lateral offset of the reference points from the
    chord between the pass's averaged ends (those weighted by their fix counts): a bowed
    "straight" pass rolled the arc, not the chord (an outside audit: 0.9 m of bow over
    17.7 m made the left diameter 14 SEs low), and its sides rolled ``± B·Δψ/2`` apart.
    Fitting smooths the reference's noise, which summed step by step would lengthen every
    path (2 cm fixes 0.4 m apart: +0.3 %)."""
    a, b = np.asarray(p.start_m, float), np.asarray(p.end_m, float)
    chord = float(np.hypot(*(b - a)))
    if chord == 0.0 or len(p.path_m) < 2:
        return chord, 0.0, 0.0
    along = (b - a) / chord
    left = np.array([-along[1], along[0]])
    pts = np.vstack([a, np.asarray(p.path_m, float).reshape(-1, 2), b]) - a
    u, v = pts @ along, pts @ left
    w = np.ones(len(u))
    w[0], w[-1] = math.sqrt(p.n_start), math.sqrt(p.n_end)
    deg = min(4, len(u) - 2)
    coef = np.polynomial.polynomial.polyfit(u, v, deg, w=w)
    off = (v - np.polynomial.polynomial.polyval(u, coef))[1:-1]
    rms = float(np.sqrt(off @ off / max(off.size - deg, 1)))
    slope = np.polynomial.polynomial.polyval(
        np.linspace(0.0, chord, 401), np.polynomial.polynomial.polyder(coef)
    )
    speed = np.sqrt(1.0 + slope * slope)  # d(path)/du; trapezoid rule (numpy 1.26 has no
    length = float((speed[1:] + speed[:-1]).sum()) * chord / 800  # np.trapezoid)
    return length, -float(math.atan(slope[-1]) - math.atan(slope[0])), rms


def straight_fit(
    passes: list[Pass],
    *,
    min_pass_m: float = 2.0,
    track_m: Estimate | None = None,
    ref_sigma_m: float | None = None,
) -> StraightResult:
    """Wheel scale factors from straight passes (see the module docstring, step 1 and 3).
    A pass a side of which counted backwards within it (:data:`BACK_NOISE_COUNTS`,
    :data:`BACK_FRACTION`: merged runs, a merged pivot), or whose reference path turned more
    than :data:`MAX_STRAIGHT_TURN_DEG` or bent sharply (:data:`BEND_SIGMAS` times
    ``ref_sigma_m``, when given), is left out, the reason in ``left_out``. Each side
    rolled the path's length ± ``track_m``·Δψ/2 (:func:`path_geometry`; 0 without a track:
    :func:`calibrate` refits with the circle's)."""
    rows = []
    returned = pivoted = turned = 0
    left_out: list[str] = []
    b_m, b_se = (track_m.value, track_m.se) if track_m is not None else (0.0, 0.0)
    for p in passes:
        why = _not_straight(p)
        if why is not None:
            returned += 1
            pivoted += "pivot" in why
            left_out.append(why)
            continue
        if math.dist(p.start_m, p.end_m) < min_pass_m:
            continue
        length, turn, rms = path_geometry(p)
        if abs(turn) > math.radians(MAX_STRAIGHT_TURN_DEG):
            turned += 1
            left_out.append(
                f"{_pass_name(p)}: its reference path turned {math.degrees(turn):+.0f} deg "
                "(clockwise) between its ends"
            )
            continue
        if ref_sigma_m is not None and rms > BEND_SIGMAS * ref_sigma_m:
            turned += 1
            left_out.append(
                f"{_pass_name(p)}: its reference path bends sharply (fixes {rms:.3f} m rms "
                f"off a smooth bow, {rms / ref_sigma_m:.1f}x the reference's {ref_sigma_m:g} m)"
            )
            continue
        sign = 1.0 if p.d_left_counts + p.d_right_counts >= 0 else -1.0
        rows.append((sign * length, turn, p.d_left_counts, p.d_right_counts))
    if len(rows) < MIN_PASSES:
        shown = "; ".join(left_out[:4]) + (
            f"; {len(left_out) - 4} more" if len(left_out) > 4 else ""
        )
        notes = [MERGED_NOTE] * bool(returned) + [TURN_NOTE] * bool(turned)
        raise ConfigError(
            f"straight track: {len(rows)} usable passes (>= {min_pass_m} m between stops); "
            f"need at least {MIN_PASSES}"
            + (f"; {len(left_out)} left out: {shown} ({'; '.join(notes)})" if left_out else "")
        )
    lengths, psi, cl, cr = (np.array(c, float) for c in zip(*rows, strict=True))
    sg = np.sign(lengths)
    den_l, den_r = float((sg * cl).sum()), float((sg * cr).sum())
    half_turn = 0.5 * float((sg * psi).sum())  # Σ sg·Δψ/2: the sides' travel apart per B
    alpha_l = float((sg * lengths).sum() + b_m * half_turn) / den_l
    alpha_r = float((sg * lengths).sum() - b_m * half_turn) / den_r
    r_l = alpha_l * cl - lengths - 0.5 * b_m * psi
    r_r = alpha_r * cr - lengths + 0.5 * b_m * psi
    total = float(np.abs(lengths).sum())
    dof = total - float((lengths * lengths).sum()) / total  # E Σr² = k·dof for the ratio fit
    # Σ Var_i from the residuals (reference error included), per side and shared
    s_ll, s_rr, s_lr = (float(v) * total / dof for v in (r_l @ r_l, r_r @ r_r, r_l @ r_r))
    cov = np.array(
        [[s_ll / den_l**2, s_lr / (den_l * den_r)], [s_lr / (den_l * den_r), s_rr / den_r**2]]
    )
    g = np.array([half_turn / den_l, -half_turn / den_r])  # d alpha / d B
    cov = cov + np.outer(g, g) * b_se**2  # the track's error, the same in every pass
    return StraightResult(
        alpha_l,
        alpha_r,
        cov,
        len(rows),
        total / len(rows),
        _k_terms(r_l * r_l - r_l * r_r, dof),
        _k_terms(r_r * r_r - r_l * r_r, dof),
        found=len(passes),
        returned=returned,
        pivoted=pivoted,
        left_out=tuple(left_out),
        turned=turned,
        turn_deg=math.degrees(float(np.abs(psi).max())),
    )


@dataclass(frozen=True)
class CircleResult:
    """Effective track, the circle's k's, and what the passes were."""

    track_m: Estimate
    k_left_m: Estimate
    k_right_m: Estimate
    passes: int
    turn_deg: float  # total |heading change|
    radius_m: float  # mean fitted radius
    gap_passes: int = 0  # left out: reference fixes too far apart to count the laps
    noisy_passes: int = 0  # left out: fixes at the usual spacing a quarter lap apart (noise)


MAX_STEP_RAD = math.pi / 2
"""Largest angle about the circle's centre between two reference points of a pass (rad, a
quarter lap) for the swept angle to be unwrapped safely. Past half a lap a gap's angle
aliases (a 0.6-lap gap reads as 0.4 lap backwards), so a whole lap could go uncounted."""


def _swept_rad(p: Pass, xc: float, yc: float, pts: Array) -> float | str:
    """The angle (rad, counter-clockwise) swept about (xc, yc) over the pass's points, or why
    the laps cannot be counted: "gap" when two points are more than :data:`MAX_STEP_RAD`
    apart in time at the pass's typical turn rate (the angle of a long gap aliases, so the
    angle alone cannot show it) or in angle across a pause in the fixes; "noise" when two
    fixes at the usual spacing are that far apart in angle (the reference's scatter is a
    large part of the radius)."""
    theta = np.arctan2(pts[:, 1] - yc, pts[:, 0] - xc)
    step = np.angle(np.exp(1j * np.diff(theta)))  # wrapped to (-pi, pi]
    times = np.concatenate(([p.t0_s], p.path_t_s, [p.t1_s]))
    dt = np.diff(times)
    ok = dt > 0
    big = np.abs(step) > MAX_STEP_RAD
    if big.any():
        # the stop's averaged ends are a fix's spacing from the path: judge the path's
        usual = float(np.median(dt[ok])) if ok.any() else 0.0
        return "gap" if float(dt[big].max()) > 1.5 * usual else "noise"
    if ok.any():
        rate = float(np.median(np.abs(step[ok]) / dt[ok]))  # rad/s, robust to one gap
        if float(dt.max()) * rate > MAX_STEP_RAD:
            return "gap"
    return float(step.sum())


NOISY_PASS = (
    "consecutive reference fixes at the usual spacing more than a quarter lap apart about the "
    "circle's centre (not a gap: the reference's scatter, or a jump, is a large part of the "
    "radius; a better reference, a higher fix rate or a larger circle)"
)


def circle_fit(passes: list[Pass], straight: StraightResult, *, ref_sigma_m: float) -> CircleResult:
    """Effective track from circle passes and the calibrated wheels (steps 2 and 3). A pass
    whose reference fixes are more than a quarter lap apart is left out and counted in
    ``gap_passes`` (a GPS gap) or ``noisy_passes`` (at the usual fix spacing: the reference's
    noise): its lap count would be a guess."""
    rows = []
    gaps = noisy = 0
    for p in passes:
        if len(p.path_m) < 3:
            continue
        pts = np.vstack([p.start_m, p.path_m, p.end_m])
        xc, yc, radius = fit_circle(pts)
        swept = _swept_rad(p, xc, yc, pts)  # counter-clockwise about the centre
        if isinstance(swept, str):
            gaps += swept == "gap"
            noisy += swept == "noise"
            continue
        if abs(swept) < math.pi:
            continue  # not even half a lap: no circle to speak of
        direction = 1.0 if p.d_left_counts + p.d_right_counts >= 0 else -1.0
        v_theta = ref_sigma_m**2 * (1 / p.n_start + 1 / p.n_end) / radius**2
        rows.append((-swept, direction * radius * abs(swept), p.d_left_counts, p.d_right_counts,
                     v_theta, radius))  # fmt: skip
    if not rows:
        raise ConfigError(
            "circle track: no pass of at least half a lap between stops"
            + (
                f"; {gaps} passes left out: reference fixes more than a quarter lap apart"
                if gaps
                else ""
            )
            + (f"; {noisy} passes left out: {NOISY_PASS}" if noisy else "")
        )
    dpsi, s_true, cl, cr, var_theta, radii = (np.array(c, float) for c in zip(*rows, strict=True))
    n = len(rows)
    s_l, s_r = straight.alpha_left * cl, straight.alpha_right * cr
    sg = np.sign(dpsi)
    turned = float(np.abs(dpsi).sum())
    b = float((sg * (s_l - s_r)).sum()) / turned
    d = (s_l - s_r) - b * dpsi  # the difference's residual, m
    a = 0.5 * (s_l + s_r) - s_true  # the common residual, m
    if n >= MIN_PASSES:
        var_diff = float(d @ d) * n / (n - 1)
    else:  # too few passes for a scatter: the straight's noise model and the reference
        var_diff = float(
            (straight.k_left_m.value * np.abs(s_l) + straight.k_right_m.value * np.abs(s_r)).sum()
            + b * b * var_theta.sum()
        )
    # the wheels' own error, the same in every pass
    g = np.array([(sg * cl).sum(), -(sg * cr).sum()])
    var_wheels = float(g @ straight.cov_alpha @ g)
    track = Estimate(b, math.sqrt(var_diff + var_wheels) / turned)
    f = n / (n - 1) if n > 1 else 1.0  # B̂ used one degree of freedom of d
    k_l = _k_terms(a * d + 0.5 * f * d * d, float(np.abs(s_l).sum()))
    k_r = _k_terms(-a * d + 0.5 * f * d * d, float(np.abs(s_r).sum()))
    return CircleResult(track, k_l, k_r, n, math.degrees(turned), float(radii.mean()), gaps, noisy)


@dataclass(frozen=True)
class OdometryCalibration:
    """The estimates with their standard errors, and the tracks they came from."""

    counts_per_rev: int
    left_diameter_m: Estimate
    right_diameter_m: Estimate
    track_m: Estimate
    k_left_m: Estimate
    k_right_m: Estimate
    straight: StraightResult
    circle: CircleResult
    reference: Reference
    dropped_passes: int  # without reference fixes in the stops around them (both tracks)

    @property
    def ref_sigma_m(self) -> float:
        """The reference's error per fix and axis the standard errors assume, m."""
        return self.reference.sigma_m

    @property
    def gap_passes(self) -> int:
        """Circle passes left out for a reference gap of more than a quarter lap."""
        return self.circle.gap_passes

    def config(self) -> OdometryConfig:
        """The ``[odometry]`` section (range-checked: ConfigError if an estimate is absurd)."""
        return build(OdometryConfig, self.table(), "odometry.")

    @property
    def few_passes(self) -> str | None:
        """A warning when either track has fewer than :data:`MIN_DOF` degrees of freedom
        for its scatter (every SE here comes from that scatter), else None."""
        dof_s, dof_c = self.straight.passes - 1, self.circle.passes - 1
        low = min(dof_s, dof_c)
        if low >= MIN_DOF:
            return None
        rough = (
            f"each ± is itself uncertain by {100 / math.sqrt(2 * low):.0f} % or more"
            if low > 0
            else "a track without a scatter has no SE of its own"
        )
        return (
            f"the standard errors rest on {dof_s} (straight, {self.straight.passes} passes) and "
            f"{dof_c} (circle, {self.circle.passes} passes) degrees of freedom: {rough}, and "
            f"a k near 0 can come out as 0; drive {MIN_DOF + 1} or more passes of each track"
        )

    def table(self) -> dict[str, float | int]:
        """The section's keys and values."""
        return {
            "counts_per_rev": self.counts_per_rev,
            "left_diameter_m": self.left_diameter_m.value,
            "right_diameter_m": self.right_diameter_m.value,
            "track_m": self.track_m.value,
            "k_left_m": self.k_left_m.value,
            "k_right_m": self.k_right_m.value,
        }

    def toml(self, header: str = "") -> str:
        """A TOML fragment with the ``[odometry]`` section, each estimate's standard error
        as a comment."""
        self.config()  # refuse to write what the daemon would refuse to load
        st, ci = self.straight, self.circle
        lines = [f"# {line}" for line in header.splitlines()]
        lines += [
            f"# straight: {st.passes} passes of {st.mean_length_m:.2f} m"
            + (f" (of {st.found} between stops)" if st.found > st.passes else "")
            + f"; circle: {ci.passes} "
            f"passes, {ci.turn_deg:.0f} deg in all, radius {ci.radius_m:.2f} m",
            *(
                [
                    f"# the straight passes bow: up to {st.turn_deg:.0f} deg between a pass's "
                    "ends, taken into account with the circle's track (docs/odometry.md)"
                ]
                if st.turn_deg >= BOW_NOTE_DEG
                else []
            ),
            *(f"# left out: {why}" for why in st.left_out),
            *([f"# ({MERGED_NOTE})"] if st.returned else []),
            *([f"# ({TURN_NOTE})"] if st.turned else []),
            f"# reference {self.reference.summary()}",
            *(f"# {note}" for note in self.reference.notes()),
            *([f"# rough: {self.few_passes}"] if self.few_passes else []),
            "# value  # ± standard error",
            "[odometry]",
            f"counts_per_rev = {self.counts_per_rev}",
        ]
        for key in ("left_diameter_m", "right_diameter_m", "track_m"):
            e: Estimate = getattr(self, key)
            lines.append(f"{key} = {e.value:.6f}  # ± {e.se:.6f}")
        for key, s, c in (
            ("k_left_m", st.k_left_m, ci.k_left_m),
            ("k_right_m", st.k_right_m, ci.k_right_m),
        ):
            e = getattr(self, key)
            both = f"straight {s.value:.2e} ± {s.se:.1e}, circle {c.value:.2e} ± {c.se:.1e}"
            lines.append(
                f"{key} = {e.value:.3e}  # ± {e.se:.1e}; {both} (the larger is kept)"
                if e.resolved
                else f"{key} = {e.value:.3e}  # not resolved: k not 2 SE above 0 on either "
                f"track ({both}: the passes' scatter did not show this wheel's noise); "
                "written: its upper bound, the larger k + SE"
            )
        return "\n".join(lines) + "\n"


def calibrate(
    straight: Track,
    circle: Track,
    *,
    counts_per_rev: int,
    ref_sigma_m: float | None = None,
    stop_s: float = 1.0,
    min_pass_m: float = 2.0,
) -> OdometryCalibration:
    """Wheel diameters, effective track and k_l, k_r from the two tracks. The reference is
    the fixes' GGA quality's, or every fix at ``ref_sigma_m`` (:func:`choose_reference`).

    Driving protocol: stand still for 2 s or more (several reference fixes) before and after
    every pass. Straight: at least 3 passes of 10 m or more (longer and more passes shrink
    every standard error). Circle: constant drive (e.g. ``drive 60 10``) for whole laps, at
    least 3 passes; the fix rate must give well under half a lap between fixes.
    """
    straight, circle, reference = choose_reference(straight, circle, ref_sigma_m)
    _check_overlap(straight, "straight")
    _check_overlap(circle, "circle")
    s_passes, s_dropped = find_passes(straight, stop_s=stop_s)
    c_passes, c_dropped = find_passes(circle, stop_s=stop_s)
    _check_sides_count_alike(s_passes, straight, circle, stop_s, min_pass_m, reference.sigma_m)
    try:
        st = straight_fit(s_passes, min_pass_m=min_pass_m, ref_sigma_m=reference.sigma_m)
    except ConfigError as exc:
        raise ConfigError(f"{exc}{_left_out(s_dropped)}") from None
    try:
        ci = circle_fit(c_passes, st, ref_sigma_m=reference.sigma_m)
    except ConfigError as exc:
        raise ConfigError(f"{exc}{_left_out(c_dropped)}") from None
    if ci.track_m.value < 0:
        raise ConfigError(
            f"left and right swapped: the circle gives a negative effective track "
            f"({ci.track_m.value:.3f} m): the side whose counts say it rolled further on the "
            "circle is the inner one. The left encoder's counts are read as the right's and "
            "the right's as the left's (or both encoders count backwards): swap the two "
            "encoders' connections on the motor board (x6wd has no setting to swap or reverse "
            "them) and record both tracks again"
        )
    for _ in range(3):  # the straight's bows need the track, the track the wheels: iterate
        st = straight_fit(
            s_passes, min_pass_m=min_pass_m, track_m=ci.track_m, ref_sigma_m=reference.sigma_m
        )
        ci = circle_fit(c_passes, st, ref_sigma_m=reference.sigma_m)
    to_d = counts_per_rev / math.pi  # diameter per (metres per count)
    pick_l = _pick_k(st.k_left_m, ci.k_left_m)
    pick_r = _pick_k(st.k_right_m, ci.k_right_m)
    return OdometryCalibration(
        counts_per_rev=counts_per_rev,
        left_diameter_m=Estimate(st.alpha_left * to_d, math.sqrt(st.cov_alpha[0, 0]) * to_d),
        right_diameter_m=Estimate(st.alpha_right * to_d, math.sqrt(st.cov_alpha[1, 1]) * to_d),
        track_m=ci.track_m,
        k_left_m=pick_l,
        k_right_m=pick_r,
        straight=st,
        circle=ci,
        reference=reference,
        dropped_passes=s_dropped + c_dropped,
    )


def _negated(track: Track, side: str) -> Track:
    """The track with one side's counts negated."""
    counts = -getattr(track, f"{side}_counts")
    return dataclasses.replace(track, **{f"{side}_counts": counts})


def _check_sides_count_alike(
    passes: list[Pass],
    straight: Track,
    circle: Track,
    stop_s: float,
    min_pass_m: float,
    ref_sigma_m: float,
) -> None:
    """ConfigError naming the encoder that counts backwards when on most straight passes the
    two sides counted in opposite directions (an outside audit: the right encoder reversed
    gave "odometry.left_diameter_m: must be >= 0.01, got -0.1213", naming the wrong wheel).
    Which side it is shows on the circle: with the reversed side's counts negated the track
    comes out positive, with the other side's negated negative (the sides then read swapped)."""
    used = [p for p in passes if math.dist(p.start_m, p.end_m) >= min_pass_m]
    opposite = [
        p
        for p in used
        if p.d_left_counts * p.d_right_counts < 0
        and min(abs(p.d_left_counts), abs(p.d_right_counts))
        > 0.5 * max(abs(p.d_left_counts), abs(p.d_right_counts))
    ]
    if not opposite or 2 * len(opposite) <= len(used):
        return
    tracks = {}
    for side in ("right", "left"):
        try:
            s_p, _ = find_passes(_negated(straight, side), stop_s=stop_s)
            c_p, _ = find_passes(_negated(circle, side), stop_s=stop_s)
            st = straight_fit(s_p, min_pass_m=min_pass_m, ref_sigma_m=ref_sigma_m)
            tracks[side] = circle_fit(c_p, st, ref_sigma_m=ref_sigma_m).track_m.value
        except ConfigError:
            continue
    p = opposite[0]
    seen = (
        f"on {len(opposite)} of {len(used)} straight passes the left and right counts have "
        f"opposite signs ({_pass_name(p)}: left {p.d_left_counts:+d}, right "
        f"{p.d_right_counts:+d})"
    )
    fix = (
        "swap its A and B channel wires (x6wd has no setting to reverse an encoder's count "
        "direction) and record both tracks again"
    )
    reversed_side = next((s for s, b in tracks.items() if b > 0), None)
    if reversed_side is None:
        raise ConfigError(f"one encoder counts backwards: {seen}; {fix}")
    other = "left" if reversed_side == "right" else "right"
    why = f"with its counts negated the circle gives a track of {tracks[reversed_side]:.3f} m"
    if other in tracks:
        why += f", with the {other} side's negated {tracks[other]:.3f} m (no track)"
    raise ConfigError(f"the {reversed_side} encoder counts backwards: {seen}; {why}; {fix}")


def _left_out(dropped: int) -> str:
    """The note a too-few-passes error gets when passes were dropped for want of fixes."""
    if not dropped:
        return ""
    return f"; {dropped} passes left out: no reference fixes in the stops around them"


def _check_overlap(track: Track, name: str) -> None:
    """ConfigError naming both time ranges (s) when no reference fix falls within the
    odometry's: every pass would be dropped, and a count of usable passes hides why (two
    clocks, or the wrong pair of files)."""
    a, b = float(track.t_odo_s[0]), float(track.t_odo_s[-1])  # sorted by from_records
    c, d = float(track.t_ref_s[0]), float(track.t_ref_s[-1])
    if d < a or c > b:
        raise ConfigError(
            f"{name} track: no reference fix during the odometry: odometry {a:.1f} to "
            f"{b:.1f} s, fixes {c:.1f} to {d:.1f} s (not the same clock, or not the same run?)"
        )
