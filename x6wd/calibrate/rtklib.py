"""A small reader for RTKLIB solution files (``.pos``, the default "lat/lon/height" format).

``%`` lines are the header (program, options, the column legend); every other non-blank line
is one epoch::

    2023/07/11 06:04:30.000   35.165393934  136.881442407    39.6452   5  20   3.4239 ...

columns GPST date and time, latitude and longitude (deg, WGS-84), ellipsoidal height (m),
solution quality Q (1 fix, 2 float, 3 SBAS, 4 DGPS, 5 single, 6 PPP), number of satellites,
then the standard deviations sdn, sde, sdu (m) and more that are read when present. RTKLIB
leaves unsolved epochs out. Only this format is read: solutions written in x/y/z or e/n/u, or
with times in GPS week/seconds, are refused with the line that does not fit, and a legend
naming another time system than GPST (UTC, JST) with its line.

The time is GPST as printed, turned into seconds by reading the date as if it were UTC
(``t_gpst_s``): a clock that only has to agree with other GPST stamps, not a real UTC epoch.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path

import numpy as np
import numpy.typing as npt

from x6wd.core.errors import DeviceUnavailable, ParseError
from x6wd.core.files import not_text, require_regular

Array = npt.NDArray[np.float64]


@dataclass(frozen=True)
class PosSolution:
    """An RTKLIB solution file's epochs, in file order: GPST (s, see the module docstring),
    latitude and longitude (deg), ellipsoidal height (m), quality Q, satellites, and the
    north/east standard deviations (m; NaN when the file has no such columns)."""

    t_gpst_s: Array
    lat_deg: Array
    lon_deg: Array
    height_m: Array
    quality: npt.NDArray[np.int64]
    n_sats: npt.NDArray[np.int64]
    sdn_m: Array
    sde_m: Array

    def __len__(self) -> int:
        return int(self.t_gpst_s.shape[0])


# The column legend above the solutions, its first word the time system (GPST, UTC, JST, ...):
# a UTC file read as GPST would be off by the leap seconds (18 s since 2017), silently.
_LEGEND = re.compile(r"^%\s+(GPST|UTC|JST|BJT)\s")


def parse_pos(text: str, source: str = "<string>") -> PosSolution:
    """Parse the text of a ``.pos`` file; :class:`ParseError` names the line that does not fit."""
    rows: list[tuple[float, float, float, float, int, int, float, float]] = []
    for lineno, line in enumerate(text.splitlines(), 1):
        if not line.strip():
            continue
        if line.lstrip().startswith("%"):
            legend = _LEGEND.match(line)
            if legend is not None and legend[1] != "GPST":
                raise ParseError(
                    f"{source}:{lineno}: times in {legend[1]}; this reader takes GPST, RTKLIB's "
                    "default (rtkpost/rnx2rtkp: time format 'ww ssss GPST' off, 'hh:mm:ss GPST')"
                )
            continue
        f = line.split()
        try:
            t = datetime.strptime(f"{f[0]} {f[1]}", "%Y/%m/%d %H:%M:%S.%f").replace(tzinfo=UTC)
            lat, lon, h = float(f[2]), float(f[3]), float(f[4])
            q, ns = int(f[5]), int(f[6])
            sdn = float(f[7]) if len(f) > 8 else math.nan
            sde = float(f[8]) if len(f) > 8 else math.nan
        except (ValueError, IndexError) as exc:
            if not_text(line):
                raise ParseError(
                    f"{source}:{lineno}: not an RTKLIB .pos file: this line is not text (a"
                    " binary file?)"
                ) from None
            raise ParseError(
                f"{source}:{lineno}: not an RTKLIB .pos line (GPST date time lat lon height Q "
                f"ns ...): {exc}"
            ) from exc
        if not (-90.0 <= lat <= 90.0 and -180.0 <= lon <= 180.0):
            raise ParseError(f"{source}:{lineno}: latitude/longitude out of range: {lat}, {lon}")
        rows.append((t.timestamp(), lat, lon, h, q, ns, sdn, sde))
    if not rows:
        raise ParseError(f"{source}: no solution lines (only a header, or empty)")
    t_s, lat_d, lon_d, h_m, q_i, ns_i, sdn_m, sde_m = zip(*rows, strict=True)
    return PosSolution(
        t_gpst_s=np.array(t_s, float),
        lat_deg=np.array(lat_d, float),
        lon_deg=np.array(lon_d, float),
        height_m=np.array(h_m, float),
        quality=np.array(q_i, np.int64),
        n_sats=np.array(ns_i, np.int64),
        sdn_m=np.array(sdn_m, float),
        sde_m=np.array(sde_m, float),
    )


def read_pos(path: str | Path) -> PosSolution:
    """Read a ``.pos`` file (:func:`parse_pos`); a missing file is :class:`DeviceUnavailable`."""
    p = Path(path)
    try:
        require_regular(p)
        text = p.read_text(encoding="utf-8", errors="replace")
    except OSError as exc:
        raise DeviceUnavailable(f"cannot read {p}: {exc.strerror or exc}") from exc
    return parse_pos(text, str(p))


def looks_like_pos(path: str | Path) -> bool:
    """True for a ``.pos`` suffix, or a file whose first non-blank line is a ``%`` header."""
    p = Path(path)
    if p.suffix.lower() == ".pos":
        return True
    try:
        with open(p, encoding="utf-8", errors="replace") as f:
            for line in f:
                if line.strip():
                    return line.lstrip().startswith("%")
    except OSError:
        return False
    return False
