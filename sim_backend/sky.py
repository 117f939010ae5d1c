"""The GPS sky: almanac and broadcast-ephemeris readers, satellite positions, az/el, DOP.

Readers (pure functions over text files):

- :func:`read_yuma` / :func:`read_sem`: almanacs. Their week numbers are 10-bit (mod 1024) and
  are unwrapped against a ``reference`` date (any date within ~9 years of the real one).
- :func:`read_rinex_nav`: RINEX 2.x GPS and RINEX 3.x (GPS or mixed) navigation files. Numbers
  are found by regular expression (``D`` or ``E`` exponents, any field width), because real
  files such as sugl0010.20n use 20-character fields instead of the standard 19.

:class:`SatelliteSet` propagates either kind with the IS-GPS-200 user algorithm (Table 20-IV),
vectorised over (epochs, satellites): ``positions_ecef(gps_s) -> (E, S, 3)``. For broadcast
ephemeris it picks, per epoch and satellite, the record with the nearest toe and marks the
satellite unavailable beyond ``validity_s`` (default 2 h: a 4-hour fit interval). Almanacs
are used as the ephemeris with no harmonic corrections and no mean-motion correction.

Times are continuous GPS seconds (see :mod:`sim_backend.geodesy`); angles at the public
boundary are degrees.
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from dataclasses import dataclass, fields
from datetime import UTC, datetime
from pathlib import Path
from typing import NamedTuple

import numpy as np

from sim_backend.geodesy import (
    GM_M3PS2,
    GPS_EPOCH,
    OMEGA_E_RPS,
    SECONDS_PER_WEEK,
    ecef_to_lla,
    enu_rotation,
    resolve_week,
    utc_to_gps_seconds,
    week_tow_to_gps_seconds,
)
from x6wd.core.errors import ConfigError, ParseError
from x6wd.core.geodesy import wrap360

DEFAULT_MASK_DEG = 5.0
DEFAULT_VALIDITY_S = 7200.0  # +-2 h around toe (the seed paper's validity, a 4 h fit interval)
_F_REL = -4.442807633e-10  # relativistic clock term constant, s / sqrt(m)
_SEMICIRCLE = np.pi
_NODE_STEP_S = 30.0  # orbit interpolation grid
_CACHE_NODES = 64  # minimum grid length (32 min) so closed-loop steps share one grid
_SEM_I_REF_SEMICIRCLES = 0.30  # SEM gives inclination as an offset from 0.30 semicircles

_NUMBER = re.compile(r"[+-]?(?:\d+\.\d*|\.\d+|\d+)(?:[EeDd][+-]?\d+)?")


def _numbers(text: str) -> list[float]:
    return [float(tok.replace("D", "E").replace("d", "e")) for tok in _NUMBER.findall(text)]


# ---------------------------------------------------------------- records


@dataclass(frozen=True, slots=True)
class Almanac:
    """One satellite's almanac (YUMA or SEM), SI units, full GPS week."""

    prn: int
    health: int  # 0 = healthy
    e: float
    toa_s: float  # time of applicability, seconds of week
    week: int  # full (unwrapped) GPS week of toa
    i0_rad: float
    omega_dot_rps: float
    sqrt_a_sqrtm: float
    omega0_rad: float  # longitude of ascending node at the weekly epoch
    w_rad: float  # argument of perigee
    m0_rad: float
    af0_s: float
    af1_sps: float

    @property
    def toa_gps_s(self) -> float:
        """Reference time as continuous GPS seconds."""
        return float(week_tow_to_gps_seconds(self.week, self.toa_s))


@dataclass(frozen=True, slots=True)
class Ephemeris:
    """One broadcast ephemeris record (RINEX nav), SI units, full GPS week."""

    prn: int
    toc_gps_s: float  # clock reference time, continuous GPS seconds
    af0_s: float
    af1_sps: float
    af2_sps2: float
    iode: float
    crs_m: float
    delta_n_rps: float
    m0_rad: float
    cuc_rad: float
    e: float
    cus_rad: float
    sqrt_a_sqrtm: float
    toe_s: float  # seconds of week
    cic_rad: float
    omega0_rad: float
    cis_rad: float
    i0_rad: float
    crc_m: float
    w_rad: float
    omega_dot_rps: float
    idot_rps: float
    week: int  # full GPS week of toe
    sv_accuracy_m: float
    health: int
    tgd_s: float

    @property
    def toe_gps_s(self) -> float:
        """Ephemeris reference time as continuous GPS seconds."""
        return float(week_tow_to_gps_seconds(self.week, self.toe_s))


# ---------------------------------------------------------------- readers


def _read_text(path: str | Path) -> str:
    try:
        return Path(path).read_text(encoding="ascii", errors="replace")
    except OSError as exc:
        raise ConfigError(f"cannot read {path}: {exc}") from exc


def _full_week(week: int, reference: datetime | None, path: str | Path) -> int:
    if week >= 1024:  # already a full week number (some tools write it)
        return week
    if reference is None:
        raise ConfigError(
            f"{path}: week {week} is modulo 1024; pass reference= (a date near the almanac)"
        )
    return resolve_week(week, reference)


_YUMA_KEYS = {
    "id": "prn",
    "health": "health",
    "eccentricity": "e",
    "time of applicability": "toa_s",
    "orbital inclination": "i0_rad",
    "rate of right ascen": "omega_dot_rps",
    "sqrt(a)": "sqrt_a_sqrtm",
    "right ascen at week": "omega0_rad",
    "argument of perigee": "w_rad",
    "mean anom": "m0_rad",
    "af0": "af0_s",
    "af1": "af1_sps",
    "week": "week",
}


def read_yuma(path: str | Path, reference: datetime | None = None) -> list[Almanac]:
    """Read a YUMA almanac (angles in radians). ``reference``: a UTC date near the almanac,
    used to unwrap the 10-bit week. Raises ParseError naming the line on bad content."""
    text = _read_text(path)
    out: list[Almanac] = []
    cur: dict[str, float] = {}
    needed = set(_YUMA_KEYS.values())

    def flush(lineno: int) -> None:
        if not cur:
            return
        missing = needed - set(cur)
        if missing:
            raise ParseError(f"{path}:{lineno}: almanac block lacks {sorted(missing)}")
        vals = dict(cur)
        out.append(
            Almanac(
                prn=int(vals.pop("prn")),
                health=int(vals.pop("health")),
                week=_full_week(int(vals.pop("week")), reference, path),
                **vals,
            )
        )
        cur.clear()

    for lineno, line in enumerate(text.splitlines(), 1):
        if line.lstrip().startswith("*"):
            flush(lineno)
            continue
        if ":" not in line:
            continue
        key, _, value = line.partition(":")
        key = key.strip().lower()
        name = next((v for k, v in _YUMA_KEYS.items() if key.startswith(k)), None)
        if name is None:
            continue
        nums = _numbers(value)
        if len(nums) != 1:
            raise ParseError(f"{path}:{lineno}: expected one number for {key!r}, got {value!r}")
        cur[name] = nums[0]
    flush(len(text.splitlines()))
    if not out:
        raise ParseError(f"{path}: no YUMA almanac blocks found")
    return out


def read_sem(path: str | Path, reference: datetime | None = None) -> list[Almanac]:
    """Read a SEM almanac (angles in semicircles, inclination as an offset from 0.30
    semicircles). ``reference`` unwraps the 10-bit week as for :func:`read_yuma`."""
    lines = [ln for ln in _read_text(path).splitlines() if ln.strip()]
    if len(lines) < 2:
        raise ParseError(f"{path}: too short for a SEM almanac")
    head1, head2 = _numbers(lines[0]), _numbers(lines[1])
    if not head1 or len(head2) < 2:
        raise ParseError(f"{path}: SEM header must give the record count, week and toa")
    n_records = int(head1[0])
    week = _full_week(int(head2[0]), reference, path)
    toa_s = head2[1]
    # Per record: PRN, SVN, URA, 9 orbit/clock values, health, configuration = 14 numbers.
    body = _numbers("\n".join(lines[2:]))
    if len(body) < 14 * n_records:
        raise ParseError(
            f"{path}: header announces {n_records} records but only {len(body)} numbers follow"
        )
    out = []
    for k in range(n_records):
        r = body[14 * k : 14 * (k + 1)]
        out.append(
            Almanac(
                prn=int(r[0]),
                health=int(r[12]),
                e=r[3],
                toa_s=toa_s,
                week=week,
                i0_rad=(_SEM_I_REF_SEMICIRCLES + r[4]) * _SEMICIRCLE,
                omega_dot_rps=r[5] * _SEMICIRCLE,
                sqrt_a_sqrtm=r[6],
                omega0_rad=r[7] * _SEMICIRCLE,
                w_rad=r[8] * _SEMICIRCLE,
                m0_rad=r[9] * _SEMICIRCLE,
                af0_s=r[10],
                af1_sps=r[11],
            )
        )
    return out


def _rinex_epoch_gps_s(fields: Sequence[float]) -> float:
    """RINEX epoch (year, month, day, hour, minute, second), GPS time -> GPS seconds."""
    year, month, day, hour, minute = (int(x) for x in fields[:5])
    if year < 100:  # RINEX 2: two-digit year, 80..99 -> 19xx
        year += 1900 if year >= 80 else 2000
    # GPS time has no leap seconds: count from the GPS epoch as on a plain calendar.
    base = datetime(year, month, day, hour, minute, tzinfo=UTC)
    return (base - GPS_EPOCH).total_seconds() + float(fields[5])


_RINEX_GPS_FIELDS = [
    "af0_s",
    "af1_sps",
    "af2_sps2",
    "iode",
    "crs_m",
    "delta_n_rps",
    "m0_rad",
    "cuc_rad",
    "e",
    "cus_rad",
    "sqrt_a_sqrtm",
    "toe_s",
    "cic_rad",
    "omega0_rad",
    "cis_rad",
    "i0_rad",
    "crc_m",
    "w_rad",
    "omega_dot_rps",
    "idot_rps",
    "l2_codes",
    "week",
    "l2p_flag",
    "sv_accuracy_m",
    "health",
    "tgd_s",
]
_OPTIONAL_FIELDS = {"l2_codes", "l2p_flag", "sv_accuracy_m", "tgd_s", "af2_sps2"}


def _ephemeris_from_numbers(prn: int, toc_gps_s: float, v: list[float], where: str) -> Ephemeris:
    # v: af0 af1 af2 then the broadcast-orbit lines in standard RINEX order.
    if len(v) < len(_RINEX_GPS_FIELDS):
        raise ParseError(f"{where}: GPS record has {len(v)} numbers, need at least 26")
    f = dict(zip(_RINEX_GPS_FIELDS, v, strict=False))
    for name, value in f.items():
        if not np.isfinite(value):
            if name not in _OPTIONAL_FIELDS:
                raise ParseError(f"{where}: PRN {prn} field {name} is blank or not finite")
            f[name] = 0.0
    full_week = int(f.pop("week"))
    toe_gps = full_week * SECONDS_PER_WEEK + f["toe_s"]
    # The week belongs to the transmission time; toe may sit across a week boundary.
    if toe_gps - toc_gps_s > SECONDS_PER_WEEK / 2:
        full_week -= 1
    elif toc_gps_s - toe_gps > SECONDS_PER_WEEK / 2:
        full_week += 1
    del f["l2_codes"], f["l2p_flag"]
    health = int(f.pop("health"))
    return Ephemeris(prn=prn, toc_gps_s=toc_gps_s, week=full_week, health=health, **f)


def _orbit_numbers(orbit: list[str], prefix: int, where: str) -> list[float]:
    """Numbers of a record's broadcast-orbit lines, four per line (the last line may be
    short). Numbers are found by regular expression; a line with a BLANK field (allowed by
    RINEX for spares and flags) is split into fields whose width is taken from the record's
    longest line -- 19 characters in standard files, 20 in some."""
    out: list[float] = []
    longest = max((len(ln.rstrip()) for ln in orbit[:-1]), default=0)
    width = (longest - prefix) / 4
    for k, line in enumerate(orbit):
        nums = _numbers(line)
        if len(nums) < 4 and k < len(orbit) - 1 and width.is_integer() and width >= 10:
            w = int(width)
            nums = []
            for j in range(4):
                cell = _numbers(line[prefix + j * w : prefix + (j + 1) * w])
                if len(cell) > 1:
                    raise ParseError(f"{where}: orbit line {k + 1} field {j + 1} is malformed")
                nums.append(cell[0] if cell else float("nan"))
        out.extend(nums[:4])
    return out


_RINEX3_LINES = {"G": 8, "E": 8, "C": 8, "J": 8, "I": 8, "R": 4, "S": 4}


def read_rinex_nav(path: str | Path) -> list[Ephemeris]:
    """Read GPS broadcast ephemeris from a RINEX 2.x (``N``) or 3.x (``N``, GPS or mixed)
    navigation file; other systems in a mixed file are skipped. Records are returned in
    file order. Raises ParseError naming the line on malformed content."""
    lines = _read_text(path).splitlines()
    if not lines or "RINEX VERSION" not in lines[0]:
        raise ParseError(f"{path}: first line is not a RINEX VERSION / TYPE header")
    try:
        version = float(lines[0][:9])
    except ValueError as exc:
        raise ParseError(f"{path}:1: unreadable RINEX version {lines[0][:9]!r}") from exc
    if lines[0][20:21] not in ("N", "n"):
        raise ParseError(f"{path}:1: not a navigation file (type {lines[0][20:21]!r})")
    if version >= 3 and lines[0][40:41] not in ("G", "M", " "):
        raise ParseError(f"{path}:1: RINEX 3 nav for system {lines[0][40:41]!r}, not GPS")
    try:
        start = next(i for i, ln in enumerate(lines) if "END OF HEADER" in ln) + 1
    except StopIteration as exc:
        raise ParseError(f"{path}: no END OF HEADER") from exc

    out: list[Ephemeris] = []
    i = start
    while i < len(lines):
        line = lines[i]
        if not line.strip():
            i += 1
            continue
        where = f"{path}:{i + 1}"
        if version >= 3:
            system = line[0]
            n_lines = _RINEX3_LINES.get(system)
            if n_lines is None:
                raise ParseError(f"{where}: unknown satellite system {system!r}")
            if system != "G":
                i += n_lines
                continue
            try:
                prn = int(line[1:3])
            except ValueError as exc:
                raise ParseError(f"{where}: bad satellite id {line[:3]!r}") from exc
            head = _numbers(line[3:])
        else:
            if not line[:3].strip():
                raise ParseError(f"{where}: expected a record start (PRN), got a continuation")
            head = _numbers(line)
            prn, head = int(head[0]), head[1:]
            n_lines = 8
        if len(head) < 9:
            raise ParseError(f"{where}: record header has {len(head)} numbers, need 9")
        try:
            toc = _rinex_epoch_gps_s(head[:6])
        except ValueError as exc:
            raise ParseError(f"{where}: bad epoch {head[:6]}: {exc}") from exc
        orbit = lines[i + 1 : i + n_lines]
        body = head[6:] + _orbit_numbers(orbit, 4 if version >= 3 else 3, where)
        out.append(_ephemeris_from_numbers(prn, toc, body, where))
        i += n_lines
    if not out:
        raise ParseError(f"{path}: no GPS navigation records")
    return out


# ---------------------------------------------------------------- propagation


_ELEMENTS = (
    "e",
    "sqrt_a_sqrtm",
    "m0_rad",
    "delta_n_rps",
    "w_rad",
    "omega0_rad",
    "omega_dot_rps",
    "i0_rad",
    "idot_rps",
    "cuc_rad",
    "cus_rad",
    "crc_m",
    "crs_m",
    "cic_rad",
    "cis_rad",
    "toe_s",
    "toe_gps_s",
    "toc_gps_s",
    "af0_s",
    "af1_sps",
    "af2_sps2",
    "tgd_s",
    "healthy",
)


def _element_table(records: Sequence[Almanac] | Sequence[Ephemeris]) -> dict[str, np.ndarray]:
    cols: dict[str, list[float]] = {k: [] for k in _ELEMENTS}
    for r in records:
        if isinstance(r, Almanac):
            vals = {
                "e": r.e,
                "sqrt_a_sqrtm": r.sqrt_a_sqrtm,
                "m0_rad": r.m0_rad,
                "delta_n_rps": 0.0,
                "w_rad": r.w_rad,
                "omega0_rad": r.omega0_rad,
                "omega_dot_rps": r.omega_dot_rps,
                "i0_rad": r.i0_rad,
                "idot_rps": 0.0,
                "cuc_rad": 0.0,
                "cus_rad": 0.0,
                "crc_m": 0.0,
                "crs_m": 0.0,
                "cic_rad": 0.0,
                "cis_rad": 0.0,
                "toe_s": r.toa_s,
                "toe_gps_s": r.toa_gps_s,
                "toc_gps_s": r.toa_gps_s,
                "af0_s": r.af0_s,
                "af1_sps": r.af1_sps,
                "af2_sps2": 0.0,
                "tgd_s": 0.0,
                "healthy": float(r.health == 0),
            }
        else:
            vals = {f.name: getattr(r, f.name) for f in fields(r) if f.name in cols}
            vals.update(toe_gps_s=r.toe_gps_s, healthy=float(r.health == 0))
        for k in _ELEMENTS:
            cols[k].append(float(vals[k]))
    return {k: np.asarray(v, dtype=float) for k, v in cols.items()}


def kepler_eccentric_anomaly(m_rad: np.ndarray, e: np.ndarray, iterations: int = 3) -> np.ndarray:
    """Solve Kepler's equation ``M = E - e sin E`` (rad) by Newton's method, elementwise.
    Started at ``M + e sin M`` (error ~e^2/2), three iterations reach machine precision
    for GPS eccentricities (< 0.03)."""
    ecc = np.asarray(e, dtype=float)
    m_rad = np.asarray(m_rad, dtype=float)
    ea = m_rad + ecc * np.sin(m_rad)
    for _ in range(iterations):
        ea -= (ea - ecc * np.sin(ea) - m_rad) / (1.0 - ecc * np.cos(ea))
    return ea


class _Nodes(NamedTuple):
    """Exact satellite states on a regular time grid (for interpolation)."""

    t0_s: float
    rec: np.ndarray  # (N, S) record index per node
    pos: np.ndarray  # (N, S, 3)
    clock: np.ndarray  # (N, S)


class SatState(NamedTuple):
    """Satellite state at each (epoch, satellite)."""

    ecef_m: np.ndarray  # (E, S, 3) Earth-fixed position at the given GPS time
    clock_s: np.ndarray  # (E, S) broadcast satellite clock offset incl. relativity and TGD
    available: np.ndarray  # (E, S) bool: healthy and within the record's validity


class SatelliteSet:
    """A set of GPS satellites propagated from almanacs or broadcast ephemerides.

    Build with :meth:`from_almanac` or :meth:`from_ephemeris`; ``prns`` gives the column
    order of every (epochs, satellites) array this class returns.
    """

    def __init__(
        self,
        prns: np.ndarray,
        table: dict[str, np.ndarray],
        rec_prn_index: np.ndarray,
        validity_s: float | None,
        kind: str,
    ) -> None:
        """Low-level constructor; prefer the ``from_*`` class methods."""
        self.prns = np.asarray(prns, dtype=int)
        self.kind = kind
        self.validity_s = validity_s
        self._table = table
        # Records sorted by (satellite column, toe): a flat key for one vectorised search.
        order = np.lexsort((table["toe_gps_s"], rec_prn_index))
        self._order = order
        self._rec_sat = rec_prn_index[order]
        self._toe_sorted = table["toe_gps_s"][order]
        self._t_ref = float(self._toe_sorted.min())
        span = float(self._toe_sorted.max()) - self._t_ref
        self._stride = span + 4.0 * SECONDS_PER_WEEK * 52 * 100  # >> any query range
        self._keys = (self._toe_sorted - self._t_ref) + self._rec_sat * self._stride
        counts = np.bincount(self._rec_sat, minlength=len(self.prns))
        self._first = np.concatenate(([0], np.cumsum(counts)[:-1]))
        self._count = counts
        self._cache: _Nodes | None = None

    @property
    def n_sats(self) -> int:
        """Number of satellites (columns)."""
        return int(self.prns.shape[0])

    @classmethod
    def from_almanac(
        cls,
        almanacs: Sequence[Almanac],
        validity_s: float | None = None,
        include_unhealthy: bool = False,
    ) -> SatelliteSet:
        """One column per PRN (the latest almanac if a PRN repeats). ``validity_s`` None:
        no time limit (almanacs degrade slowly, ~km after days)."""
        recs = [a for a in almanacs if include_unhealthy or a.health == 0]
        if not recs:
            raise ConfigError("almanac has no (healthy) satellites")
        latest: dict[int, Almanac] = {}
        for a in recs:
            if a.prn not in latest or a.toa_gps_s >= latest[a.prn].toa_gps_s:
                latest[a.prn] = a
        prns = np.array(sorted(latest))
        chosen = [latest[int(p)] for p in prns]
        return cls(prns, _element_table(chosen), np.arange(len(prns)), validity_s, "almanac")

    @classmethod
    def from_ephemeris(
        cls,
        ephemerides: Sequence[Ephemeris],
        validity_s: float = DEFAULT_VALIDITY_S,
        include_unhealthy: bool = False,
    ) -> SatelliteSet:
        """One column per PRN; each epoch uses that PRN's record with the nearest toe, and
        the satellite is unavailable where that toe is more than ``validity_s`` away."""
        recs = [r for r in ephemerides if include_unhealthy or r.health == 0]
        if not recs:
            raise ConfigError("navigation data has no (healthy) GPS records")
        prns = np.array(sorted({r.prn for r in recs}))
        col = {int(p): k for k, p in enumerate(prns)}
        idx = np.array([col[r.prn] for r in recs])
        return cls(prns, _element_table(recs), idx, validity_s, "ephemeris")

    def _select(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Record index (E, S) with the nearest toe, and |t - toe| (E, S)."""
        n_s = self.n_sats
        q = (t[:, None] - self._t_ref) + np.arange(n_s)[None, :] * self._stride
        pos = np.searchsorted(self._keys, q)
        lo = np.clip(pos - 1, self._first, self._first + self._count - 1)
        hi = np.clip(pos, self._first, self._first + self._count - 1)
        d_lo = np.abs(t[:, None] - self._toe_sorted[lo])
        d_hi = np.abs(t[:, None] - self._toe_sorted[hi])
        pick = np.where(d_hi < d_lo, hi, lo)
        return self._order[pick], np.minimum(d_lo, d_hi)

    def _propagate(self, t: np.ndarray, rec: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Exact IS-GPS-200 position (..., 3) and clock (...) for times and record indices
        of the same shape."""
        g = {k: v[rec] for k, v in self._table.items()}
        tk = t - g["toe_gps_s"]
        a = g["sqrt_a_sqrtm"] ** 2
        n = np.sqrt(GM_M3PS2 / a**3) + g["delta_n_rps"]
        e = g["e"]
        ea = kepler_eccentric_anomaly(g["m0_rad"] + n * tk, e)
        sin_e, cos_e = np.sin(ea), np.cos(ea)
        nu = np.arctan2(np.sqrt(1.0 - e * e) * sin_e, cos_e - e)
        phi = nu + g["w_rad"]
        s2, c2 = np.sin(2.0 * phi), np.cos(2.0 * phi)
        u = phi + g["cus_rad"] * s2 + g["cuc_rad"] * c2
        r = a * (1.0 - e * cos_e) + g["crs_m"] * s2 + g["crc_m"] * c2
        inc = g["i0_rad"] + g["cis_rad"] * s2 + g["cic_rad"] * c2 + g["idot_rps"] * tk
        xp, yp = r * np.cos(u), r * np.sin(u)
        om = g["omega0_rad"] + (g["omega_dot_rps"] - OMEGA_E_RPS) * tk - OMEGA_E_RPS * g["toe_s"]
        so, co, ci = np.sin(om), np.cos(om), np.cos(inc)
        pos = np.stack((xp * co - yp * ci * so, xp * so + yp * ci * co, yp * np.sin(inc)), -1)
        dtc = t - g["toc_gps_s"]
        clock = (
            g["af0_s"]
            + g["af1_sps"] * dtc
            + g["af2_sps2"] * dtc**2
            + _F_REL * e * g["sqrt_a_sqrtm"] * sin_e
            - g["tgd_s"]
        )
        return pos, clock

    def _nodes(self, t_lo: float, t_hi: float, n_epochs: int) -> _Nodes | None:
        """Exact states on the 30 s grid covering [t_lo, t_hi] for interpolation, from the
        cache when it covers them; None when the grid would cost more than exact states
        (few epochs spread over a long time)."""
        h = _NODE_STEP_S
        c = self._cache
        if c is not None and t_lo >= c.t0_s + h and t_hi < c.t0_s + (len(c.rec) - 2) * h:
            return c
        t0 = float(np.floor(t_lo / h) * h - h)
        need = int(np.floor((t_hi - t0) / h)) + 3
        if need > max(_CACHE_NODES, n_epochs // 4):
            return None
        # At least _CACHE_NODES nodes, so that closed-loop stepping reuses them for a while.
        t_nodes = t0 + h * np.arange(max(need, _CACHE_NODES))
        rec, _ = self._select(t_nodes)
        pos, clock = self._propagate(t_nodes[:, None], rec)
        self._cache = _Nodes(t0, rec, pos, clock)
        return self._cache

    def state(self, gps_s: np.ndarray | float, exact: bool = False) -> SatState:
        """Positions (E, S, 3) m ECEF, clock offsets (E, S) s and availability at GPS times
        ``gps_s`` (E,) continuous seconds, by the IS-GPS-200 user algorithm.

        The orbits are evaluated exactly on a 30 s grid (cached between calls) and
        interpolated by 4-point Lagrange polynomials (error below 1 mm, verified in the
        tests); satellites whose ephemeris record changes within the four grid points are
        evaluated exactly. ``exact=True`` evaluates every epoch exactly.
        """
        t = np.atleast_1d(np.asarray(gps_s, dtype=float))
        if t.ndim != 1:
            raise ConfigError(f"gps_s must be a scalar or 1-D array, got shape {t.shape}")
        if not np.all(np.isfinite(t)):
            raise ConfigError("gps_s contains non-finite times")
        nodes = None if exact else self._nodes(float(t.min()), float(t.max()), t.shape[0])
        if nodes is None:
            rec, _ = self._select(t)
            pos, clock = self._propagate(t[:, None], rec)
            return SatState(pos, clock, self._available(t, rec))
        x = (t - nodes.t0_s) / _NODE_STEP_S
        k = np.floor(x).astype(np.int64)
        u = x - k  # in [0, 1): nodes k-1, k, k+1, k+2 around it
        w = np.stack(
            (
                -u * (u - 1) * (u - 2) / 6,
                (u + 1) * (u - 1) * (u - 2) / 2,
                -(u + 1) * u * (u - 2) / 2,
                (u + 1) * u * (u - 1) / 6,
            ),
            axis=1,
        )
        idx = k[:, None] + np.arange(-1, 3)[None, :]  # (E, 4)
        rec4 = nodes.rec[idx]  # (E, 4, S)
        # The nearest-toe record is piecewise constant in time: if the grid points around
        # t agree, t uses the same record; otherwise look it up and evaluate exactly.
        rec = rec4[:, 1, :].copy()
        same = np.all(rec4 == rec4[:, :1, :], axis=1)
        if len(w) == 1:  # closed-loop stepping: avoid einsum's set-up cost
            pos = w[0] @ nodes.pos[idx[0]].reshape(4, -1)
            pos = pos.reshape(1, -1, 3)
            clock = (w[0] @ nodes.clock[idx[0]])[None, :]
        else:
            pos = np.einsum("ej,ejsc->esc", w, nodes.pos[idx])
            clock = np.einsum("ej,ejs->es", w, nodes.clock[idx])
        if not same.all():
            rows = np.nonzero(~same.all(axis=1))[0]
            rec[rows], _ = self._select(t[rows])
            ee, ss = np.nonzero(~same)
            pos[ee, ss], clock[ee, ss] = self._propagate(t[ee], rec[ee, ss])
        return SatState(pos, clock, self._available(t, rec))

    def _available(self, t: np.ndarray, rec: np.ndarray) -> np.ndarray:
        avail = self._table["healthy"][rec] > 0.5
        if self.validity_s is not None:
            avail &= np.abs(t[:, None] - self._table["toe_gps_s"][rec]) <= self.validity_s
        return avail

    def positions_ecef(self, gps_s: np.ndarray | float) -> np.ndarray:
        """Satellite ECEF positions (E, S, 3) m at continuous GPS seconds ``gps_s`` (E,)."""
        return self.state(gps_s).ecef_m

    def available(self, gps_s: np.ndarray | float) -> np.ndarray:
        """(E, S) bool: healthy and within the validity interval of the chosen record."""
        return self.state(gps_s).available

    @classmethod
    def from_file(cls, path: str | Path, reference: datetime | None = None) -> SatelliteSet:
        """Build from a YUMA, SEM or RINEX navigation file, recognised by its content."""
        text = _read_text(path)
        head = text[:200]
        if "RINEX VERSION" in head:
            return cls.from_ephemeris(read_rinex_nav(path))
        if "almanac for PRN" in head or "ID:" in head:
            return cls.from_almanac(read_yuma(path, reference))
        return cls.from_almanac(read_sem(path, reference))


# ---------------------------------------------------------------- geometry


def look_angles(
    rx_ecef_m: np.ndarray, sat_ecef_m: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Azimuth (deg, 0..360 from north, clockwise), elevation (deg) and range (m).

    ``rx_ecef_m``: (3,) or (E, 3); ``sat_ecef_m``: (E, S, 3). Returns (E, S) arrays. The
    local frame is the receiver's own geodetic east/north/up.
    """
    sat = np.asarray(sat_ecef_m, dtype=float)
    rx = np.broadcast_to(np.asarray(rx_ecef_m, dtype=float), (sat.shape[0], 3))
    lat, lon, _ = ecef_to_lla(rx)
    rot = enu_rotation(lat, lon)  # (E, 3, 3)
    d = sat - rx[:, None, :]
    enu = np.matmul(d, np.swapaxes(rot, -1, -2))
    horiz = np.hypot(enu[..., 0], enu[..., 1])
    az = wrap360(np.degrees(np.arctan2(enu[..., 0], enu[..., 1])))
    el = np.degrees(np.arctan2(enu[..., 2], horiz))
    return az, el, np.sqrt(horiz**2 + enu[..., 2] ** 2)


def azel(rx_ecef_m: np.ndarray, sat_ecef_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Azimuth and elevation (deg), each (E, S); see :func:`look_angles`."""
    az, el, _ = look_angles(rx_ecef_m, sat_ecef_m)
    return az, el


def above_mask(el_deg: np.ndarray, mask_deg: float = DEFAULT_MASK_DEG) -> np.ndarray:
    """Boolean mask of satellites at or above the elevation mask (deg)."""
    return np.asarray(el_deg) >= mask_deg


class Dops(NamedTuple):
    """Dilutions of precision per epoch (E,); NaN where fewer than 4 satellites are used or
    the geometry is degenerate."""

    gdop: np.ndarray
    pdop: np.ndarray
    hdop: np.ndarray
    vdop: np.ndarray
    tdop: np.ndarray
    n_used: np.ndarray  # (E,) int


def design_matrix(az_deg: np.ndarray, el_deg: np.ndarray) -> np.ndarray:
    """Rows ``[-e_E, -e_N, -e_U, 1]`` (E, S, 4) of the linearised pseudorange equations in
    the local frame (unit line-of-sight e from receiver to satellite)."""
    az, el = np.radians(az_deg), np.radians(el_deg)
    ce = np.cos(el)
    ones = np.ones_like(az)
    return np.stack((-ce * np.sin(az), -ce * np.cos(az), -np.sin(el), ones), axis=-1)


def batched_inverse(a: np.ndarray, ok: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Inverse of (E, 4, 4) normal matrices where ``ok``; returns (inverse, ok) with ok
    cleared for singular or ill-conditioned matrices (their inverse is NaN)."""
    n = a.shape[-1]
    safe = np.where(ok[:, None, None], a, np.eye(n))
    try:
        inv = np.linalg.inv(safe)
    except np.linalg.LinAlgError:  # an exactly singular one: find it the slow way
        cond = np.linalg.cond(safe)
        ok = ok & np.isfinite(cond) & (cond < 1e12)
        safe = np.where(ok[:, None, None], safe, np.eye(n))
        inv = np.linalg.inv(safe)
    # Ill-conditioned (nearly coplanar) geometry shows as huge variances.
    tr = np.trace(inv, axis1=1, axis2=2)
    ok = ok & np.isfinite(tr) & (tr > 0) & (tr < 1e8)
    inv[~ok] = np.nan
    return inv, ok


def dops(
    az_deg: np.ndarray,
    el_deg: np.ndarray,
    used: np.ndarray | None = None,
    mask_deg: float = DEFAULT_MASK_DEG,
) -> Dops:
    """GDOP/PDOP/HDOP/VDOP/TDOP per epoch from (E, S) azimuths/elevations (deg).

    ``used``: (E, S) bool of satellites in the solution; default: all at or above
    ``mask_deg``. NaN entries of az/el count as not used.
    """
    az = np.atleast_2d(np.asarray(az_deg, dtype=float))
    el = np.atleast_2d(np.asarray(el_deg, dtype=float))
    if az.shape != el.shape:
        raise ConfigError(f"az {az.shape} and el {el.shape} shapes differ")
    use = above_mask(np.nan_to_num(el, nan=-90.0), mask_deg) if used is None else np.asarray(used)
    use = np.atleast_2d(use) & np.isfinite(az) & np.isfinite(el)
    g = design_matrix(np.nan_to_num(az), np.nan_to_num(el))
    gw = g * use[..., None]
    normal = np.matmul(np.swapaxes(gw, 1, 2), g)
    n_used = use.sum(axis=1)
    q, _ = batched_inverse(normal, n_used >= 4)
    qd = np.diagonal(q, axis1=1, axis2=2)
    return Dops(
        gdop=np.sqrt(qd.sum(axis=1)),
        pdop=np.sqrt(qd[:, :3].sum(axis=1)),
        hdop=np.sqrt(qd[:, :2].sum(axis=1)),
        vdop=np.sqrt(qd[:, 2]),
        tdop=np.sqrt(qd[:, 3]),
        n_used=n_used,
    )


def gps_seconds(utc: datetime) -> float:
    """Convenience re-export: aware UTC datetime -> continuous GPS seconds."""
    return utc_to_gps_seconds(utc)
