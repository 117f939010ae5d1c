"""The receiver engine of ``x6wd sim``: a static survey with no robot in the loop.

A scenario without waypoints is a survey (the papers' static experiments): nothing moves the
antenna, so what the receiver says cannot depend on what the robot does. This engine runs
only the receiver: the scenario's model and error layers in vectorised chunks of
:data:`~sim_backend.runs.STATIC_CHUNK_EPOCHS` epochs, its NMEA text, and the UART that
carries it, and writes

- ``gps.nmea``: the receiver's bytes, identical to what the robot engine writes for the same
  scenario, seed and duration (same chunks, same draws);
- ``recording.jsonl``: what the daemon's recorder would have kept of them, one ``nmea`` record
  per sentence at the time its last byte arrives (sentences the 1 KiB transmit buffer drops
  are not there), between ``sim_start`` and ``sim_end`` events. Tools that read recordings
  (``x6wd gap``, the log viewer) decode those sentences as the daemon would;
- ``truth.csv`` at the GPS epochs, ``summary.json`` and ``track.png``.

The summary's raw-GPS figures come from the positions as the NMEA text prints them (the
differential test decodes ``gps.nmea`` with the daemon's decoder and finds the same numbers);
there is no filtered row, because no robot ran its EKF. ``x6wd sim --engine robot`` runs the
robot engine on a survey too (the robot's whole loop at the compass rate, ~20x slower).
"""

from __future__ import annotations

import functools
import json
import math
import re
import time
from collections.abc import Callable
from datetime import UTC
from pathlib import Path
from typing import TextIO

import numpy as np

from sim_backend.compass import CompassSetup
from sim_backend.geodesy import EnuFrame, lla_to_enu
from sim_backend.nmea_out import NmeaCells, dop_texts
from sim_backend.receiver import SimRandom, build_receiver
from sim_backend.runs import (
    STATIC_CHUNK_EPOCHS,
    ErrorStats,
    RunPlan,
    Summary,
    dispersion_m,
    sky_warnings,
    steps_evenly,
    vehicle_from_world,
)
from sim_backend.textblocks import (
    compact,
    const_block,
    day_texts,
    fixed_block,
    joined,
    put_texts,
    text_block,
    uint_block,
)
from sim_backend.trackpng import plot_survey
from sim_backend.world import World
from x6wd.core.outdir import open_output, output_dir, output_file
from x6wd.nav.geo import R1_M, R2_M

SIM_OUTPUTS = ("gps.nmea", "recording.jsonl", "truth.csv", "summary.json", "track.png")
"""The files ``x6wd sim`` writes into its ``--out`` (either engine): removed at a run's start,
so that a run cut short (Ctrl-C) never leaves an earlier run's beside its own."""


def survey_clock_hz(world: World) -> float:
    """The receiver engine's clock (Hz): the robot engine's (it steps at the compass rate),
    so the same epochs; a rate pair that clock cannot step (compass 5 Hz, GPS 4 Hz) has no
    such run to match, and the receiver alone has no control loop: then the GPS rate."""
    clock_hz = CompassSetup.from_table(world.compass).rate_hz
    return clock_hz if steps_evenly(clock_hz, world.gnss.rate_hz) else world.gnss.rate_hz


def run_survey(
    world: World,
    out_dir: str | Path,
    seed: int | None = None,
    duration_s: float | None = None,
    progress: Callable[[float, float], None] | None = None,
) -> Summary:
    """Run ``world`` as a static survey on the receiver alone and write the output files into
    ``out_dir`` (see the module docstring). ``seed`` and ``duration_s`` (s, simulated)
    override the scenario's; ``progress(t_s, total_s)`` is called once per chunk. The antenna
    stands at the vehicle's start pose for the whole run, waypoints or not."""
    wall0 = time.perf_counter()
    plan = RunPlan.of(world, seed, duration_s, survey_clock_hz(world))
    out = output_dir(out_dir, clear=SIM_OUTPUTS)
    receiver = build_receiver(world, SimRandom.from_seed(plan.seed))
    s0 = vehicle_from_world(world).state
    antenna = np.array([s0.east_m, s0.north_m, s0.up_m + world.vehicle.antenna_height_m])
    origin = world.origin
    truth_lat, truth_lon, truth_alt = (
        float(v) for v in EnuFrame(origin.lat_deg, origin.lon_deg, origin.alt_m).to_lla(antenna)
    )
    t_ep = plan.epoch_times_s()
    decimals = receiver.formatter.minute_decimals
    utc0 = world.start_utc
    utc0_naive = utc0.astimezone(UTC).replace(tzinfo=None) if utc0.tzinfo else utc0
    start_us = np.datetime64(utc0_naive, "us")
    rec_lines = _RecordLines(start_us)

    # Kept of the whole run (a 720 h run is 2.6 million fixes): the fixes' east/north (the
    # plot) and errors (the percentiles), HDOP in hundredths and satellites used in compact
    # types; the printed positions' spread as its extremes. The figures are those of the
    # whole arrays: the same values, summed and sorted whole.
    enu_parts: list[np.ndarray] = []
    err_parts: list[np.ndarray] = []
    hdop_parts: list[np.ndarray] = []
    used_parts: list[np.ndarray] = []
    spread = _Spread()
    n_fix = n_valid = 0
    with open_output(out / "gps.nmea") as nmea, open_output(out / "recording.jsonl") as rec:
        rec.write(
            rec_lines.event(
                0.0,
                {"event": "sim_start", "scenario": world.name, "seed": plan.seed,
                 "duration_s": plan.total_s, "engine": "receiver"},
            ).encode("utf-8")
        )  # fmt: skip
        banner = receiver.banner()
        nmea.write(banner)
        # the banner goes out first and holds the UART, but the daemon's recording starts
        # with the first epoch (as the robot engine's does)
        receiver.arrivals(banner, 0.0)
        wire_bytes = len(banner)
        t_end = last_rx_s = float(t_ep[-1])
        for start in range(0, len(t_ep), STATIC_CHUNK_EPOCHS):
            t = t_ep[start : start + STATIC_CHUNK_EPOCHS]
            n = t.shape[0]
            b = receiver.batch(t, np.tile(antenna, (n, 1)), np.zeros((n, 3)))
            cells = receiver.formatter.format_cells(b)
            text = cells.text()
            nmea.write(text)
            arrive, sent = receiver.uart.send_table(cells.lengths, t)
            lines, carried = rec_lines.nmea_cells(text, cells, arrive, sent)
            rec.write(lines)
            wire_bytes += carried
            if sent.any():
                last_rx_s = float(arrive[sent][-1])
            valid = np.asarray(b.valid, dtype=bool)
            n_fix += n
            lat = _as_printed(np.asarray(b.lat_deg)[valid], decimals)
            lon = _as_printed(np.asarray(b.lon_deg)[valid], decimals)
            n_valid += lat.size
            spread.add(lat - truth_lat, lon - truth_lon)
            if lat.size:
                enu = lla_to_enu(lat, lon, np.full(lat.shape, origin.alt_m),
                                 origin.lat_deg, origin.lon_deg, origin.alt_m)  # fmt: skip
                en = np.ascontiguousarray(np.asarray(enu)[:, :2])
                enu_parts.append(en)
                err_parts.append(np.hypot(en[:, 0] - antenna[0], en[:, 1] - antenna[1]))
            # HDOP and satellites used as GGA prints them (2 decimals and capped; 2 digits):
            # HDOP kept as its hundredths (k / 100 is the printed value again)
            hundredths = np.rint(_printed_dops(np.asarray(b.hdop)[valid]) * 100.0)
            hdop_parts.append(hundredths.astype(np.uint16))
            used_parts.append(np.minimum(np.asarray(b.n_used)[valid], 99).astype(np.uint8))
            if progress is not None:
                progress(float(t[-1]), plan.total_s)
        # the run ends when the last sentence on the wire has arrived (as the robot engine's)
        end = rec_lines.event(max(t_end, last_rx_s), {"event": "sim_end", "completed": False})
        rec.write(end.encode("utf-8"))

    with output_file(out / "truth.csv"):
        _write_truth(out / "truth.csv", t_ep, truth_lat, truth_lon, truth_alt)
    del t_ep
    err = np.concatenate(err_parts) if err_parts else np.zeros(0)
    err_parts.clear()
    raw_error = ErrorStats.of(err)
    del err
    hdop = np.concatenate(hdop_parts) / 100.0
    hdop_parts.clear()
    mean_hdop = float(np.mean(hdop)) if hdop.size else math.nan
    del hdop
    used = np.concatenate(used_parts)
    disp_lat, disp_lon = spread.half_m()
    gps_effects = [e.name for e in world.effect_objects() if e.kind == "gps"]
    summary = Summary(
        scenario=world.name,
        seed=plan.seed,
        completed=False,
        waypoints_reached=0,
        waypoint_count=0,
        sim_time_s=t_end,
        wall_time_s=time.perf_counter() - wall0,
        path_length_m=0.0,
        straight_length_m=0.0,
        raw_error=raw_error,
        filtered_error=ErrorStats.of(np.zeros(0)),
        hold_periods=0,
        hold_time_s=0.0,
        fixes=n_fix,
        fixes_valid=n_valid,
        dispersion_lat_m=disp_lat,
        dispersion_lon_m=disp_lon,
        mean_hdop=mean_hdop,
        mean_sats_used=float(np.mean(used)) if used.size else math.nan,
        extra={
            "engine": "receiver",
            # not run here; what --engine robot would run (the summary names it)
            "position_source": world.navigation.position_source,
            "warnings": sky_warnings(world, plan.total_s),
            "nmea_bytes": wire_bytes,
            "uart_dropped_sentences": receiver.uart.dropped,
            "fidelity": world.gnss.fidelity,
            "effects_applied": gps_effects,
            "effects_skipped": [
                f"{e.name}: no compass in the receiver engine"
                for e in world.effect_objects()
                if e.kind != "gps"
            ],
        },
    )
    with output_file(out / "summary.json"):
        (out / "summary.json").write_text(json.dumps(summary.to_dict(), indent=2) + "\n")
    fix_enu = np.concatenate(enu_parts) if enu_parts else np.zeros((0, 2))
    enu_parts.clear()
    with output_file(out / "track.png"):
        at_m = (float(antenna[0]), float(antenna[1]))
        plot_survey(out / "track.png", world, at_m, fix_enu, summary)
    return summary


class _Spread:
    """:func:`~sim_backend.runs.dispersion_m` of readings minus truth (deg) given a chunk at a
    time: the extremes kept, the same figures as of the whole arrays."""

    def __init__(self) -> None:
        self.lat = [math.inf, -math.inf]
        self.lon = [math.inf, -math.inf]

    def add(self, dlat_deg: np.ndarray, dlon_deg: np.ndarray) -> None:
        if dlat_deg.size == 0:
            return
        dlon_deg = (np.asarray(dlon_deg, dtype=float) + 180.0) % 360.0 - 180.0  # as it does
        for ends, d in ((self.lat, dlat_deg), (self.lon, dlon_deg)):
            ends[0], ends[1] = min(ends[0], float(np.min(d))), max(ends[1], float(np.max(d)))

    def half_m(self) -> tuple[float, float]:
        if not math.isfinite(self.lat[0]):
            return dispersion_m(np.zeros(0), np.zeros(0))
        return (
            math.radians(self.lat[1] - self.lat[0]) * R2_M / 2.0,
            math.radians(self.lon[1] - self.lon[0]) * R1_M / 2.0,
        )


def _printed_dops(values: np.ndarray) -> np.ndarray:
    """DOPs as numbers read back from their GGA text (:func:`dop_texts`): the capped ones
    99.99, the others ``rint(100 v) / 100``, which is the double nearest the two-decimal
    text wherever ``100 v`` is not within 1e-6 of a rounding half (there: the text read)."""
    v = np.asarray(values, dtype=float)
    with np.errstate(invalid="ignore"):
        capped = ~(np.isfinite(v) & (v <= 99.99))
        x = np.where(capped | ~(v > 0.0), 0.0, v) * 100.0
        near = np.abs(x - np.floor(x) - 0.5) <= 1e-6
    out = np.where(capped, 99.99, np.rint(x) / 100.0)
    if near.any():
        out[near] = np.array(dop_texts(v[near]), dtype=float)
    return out


def _as_printed(value_deg: np.ndarray, minute_decimals: int) -> np.ndarray:
    """Degrees (deg) as the NMEA text prints them with ``minute_decimals`` decimals of a
    minute (the formatter's rounding: whole units of that decimal)."""
    scale = float(10**minute_decimals)
    total = np.rint(np.abs(value_deg) * 60.0 * scale)
    deg, rem = np.divmod(total, 60.0 * scale)
    return np.copysign(deg + (rem / scale) / 60.0, value_deg)


def _write_truth(path: Path, t_s: np.ndarray, lat: float, lon: float, alt: float) -> None:
    """truth.csv (the robot engine's columns) at the epochs: the antenna does not move. The
    times' ``f"{t:.3f}"`` as a text block, a chunk at a time."""
    tail = f",{lat:.9f},{lon:.9f},{alt:.3f},0.000\n"
    with open(path, "wb") as f:
        f.write(b"t_s,lat,lon,alt,heading_deg\n")
        for start in range(0, t_s.shape[0], STATIC_CHUNK_EPOCHS):
            t = t_s[start : start + STATIC_CHUNK_EPOCHS]
            f.write(compact(joined((fixed_block(t, 3), const_block(tail, t.shape[0])))))


# What JSON leaves as it is inside a string (printable ASCII but quote and backslash), plus
# the CRLFs between the sentences.
_JSON_PLAIN = re.compile(rb"[\x20\x21\x23-\x5b\x5d-\x7e\r\n]*")
_D3 = [f"{i:03d}" for i in range(1000)]


@functools.cache
def _hms_table() -> list[str]:
    """``hh:mm:ss`` of every second of a day."""
    d2 = [f"{i:02d}" for i in range(60)]
    mm_ss = [m + ":" + s for m in d2 for s in d2]
    return [h + ":" + x for h in d2[:24] for x in mm_ss]


class _RecordLines:
    """Recording lines in the recorder's own format (:class:`x6wd.core.recorder.Recorder`),
    written a chunk at a time: per-record calls cost more than the receiver itself."""

    def __init__(self, start_us: np.datetime64) -> None:
        self.start_us = start_us

    def _utc_parts(self, t_s: np.ndarray) -> tuple[list[str], ...]:
        """The ISO UTC times (without the Z) of ``t_s`` (s) after the start, in pieces (date
        and T, hh:mm:ss, milliseconds, microseconds) from tables: 3x cheaper than numpy's
        date formatting, and joined by the caller's one join."""
        total = int(self.start_us.astype(np.int64)) + np.rint(t_s * 1e6).astype(np.int64)
        day, of_day = np.divmod(total, 86_400_000_000)
        sec, micro = np.divmod(of_day, 1_000_000)
        ms, us = np.divmod(micro, 1000)
        days = {d: str(np.datetime64(d, "D")) + "T" for d in np.unique(day).tolist()}
        hms, d3 = _hms_table(), _D3
        return (
            list(map(days.__getitem__, day.tolist())),
            list(map(hms.__getitem__, sec.tolist())),
            list(map(d3.__getitem__, ms.tolist())),
            list(map(d3.__getitem__, us.tolist())),
        )

    def event(self, t_s: float, data: dict[str, object]) -> str:
        """One ``event`` record's line."""
        body = json.dumps(data, separators=(",", ":"), ensure_ascii=False)
        (day,), (hms,), (ms,), (us,) = self._utc_parts(np.array([t_s]))
        utc = f"{day}{hms}.{ms}{us}Z"
        return f'{{"t_mono":{float(t_s)!r},"t_utc":"{utc}","type":"event","data":{body}}}\n'

    def write_nmea(self, f: TextIO, arrived: list[tuple[float, bytes]]) -> int:
        """``nmea`` records for (arrival time s, sentence) pairs into ``f``; the bytes carried."""
        text, carried = self.nmea_lines(arrived)
        f.write(text)
        return carried

    def nmea_lines(self, arrived: list[tuple[float, bytes]]) -> tuple[str, int]:
        """The ``nmea`` records' lines for (arrival time s, sentence) pairs, and the bytes
        carried: any sentence text, escaped as JSON needs."""
        if not arrived:
            return "", 0
        times, lines = zip(*arrived, strict=True)
        blob = b"".join(lines)
        n = len(lines)
        if blob.count(b"\r\n") == blob.count(b"\r") == blob.count(b"\n") == n:
            # every sentence ends in one CRLF and holds no other: split the whole text once
            texts = blob.decode("ascii", "replace").split("\r\n")[:n]
        else:
            texts = [line.rstrip(b"\r\n").decode("ascii", "replace") for line in lines]
        day, hms, ms, us = self._utc_parts(np.array(times))
        # float reprs by the list's repr (one C call), the lines by one join of their pieces
        reprs = repr(list(times))[1:-1].split(", ")
        if _JSON_PLAIN.fullmatch(blob):  # nothing to escape: the text goes in as it is
            quoted, head, tail = texts, '"type":"nmea","data":{"text":"', '"}}\n'
        else:
            quoted = list(map(json.encoder.encode_basestring, texts))
            head, tail = '"type":"nmea","data":{"text":', "}}\n"
        pieces = (
            ['{"t_mono":'] * n, reprs, [',"t_utc":"'] * n, day, hms, ["."] * n, ms, us,
            ['Z",' + head] * n, quoted, [tail] * n,
        )  # fmt: skip
        parts: list[str] = [""] * (len(pieces) * n)
        for k, piece in enumerate(pieces):
            parts[k :: len(pieces)] = piece
        return "".join(parts), len(blob)

    def nmea_cells(
        self, text: bytes, cells: NmeaCells, arrive: np.ndarray, sent: np.ndarray
    ) -> tuple[bytes, int]:
        """The ``nmea`` records' lines (UTF-8) of the sentences of ``cells`` that were
        ``sent``, arriving at ``arrive`` (s; both as :meth:`UartTx.send_table` gives them),
        and the bytes carried; ``text`` is all of ``cells``' sentences. Built as blocks of
        text (:mod:`sim_backend.textblocks`) when the sentences need no JSON escaping, as the
        receiver's own do; :meth:`nmea_lines` otherwise."""
        flat = np.flatnonzero(sent.reshape(-1))
        if not flat.size:
            return b"", 0
        lengths = cells.lengths.reshape(-1)
        times = arrive.reshape(-1)[flat]
        if not (cells.plain_lines and b'"' not in text and b"\\" not in text):
            width = cells.cells.shape[2]
            rows = cells.cells.reshape(-1, width)[flat]
            pairs = [
                (t, row.tobytes().replace(b"\0", b""))
                for t, row in zip(times.tolist(), rows, strict=True)
            ]
            lines, carried = self.nmea_lines(pairs)
            return lines.encode("utf-8"), carried
        body = cells.cells.reshape(-1, cells.cells.shape[2])[flat]
        n = flat.size
        block = joined(
            (const_block('{"t_mono":', n), *_repr_pieces(times), const_block(',"t_utc":"', n),
             *self._utc_pieces(times), const_block('Z","type":"nmea","data":{"text":"', n),
             body, const_block('"}}' + chr(_EOL), n))
        )  # fmt: skip
        return compact(block, _LINE_ENDS, b"\0\r\n"), int(lengths[flat].sum())

    def _utc_pieces(self, t_s: np.ndarray) -> tuple[np.ndarray, ...]:
        """The ISO UTC times (``YYYY-MM-DDThh:mm:ss.ffffff``) of ``t_s`` (s) after the start,
        as blocks to be put side by side (:func:`joined`)."""
        total = int(self.start_us.astype(np.int64)) + np.rint(t_s * 1e6).astype(np.int64)
        day, of_day = np.divmod(total, 86_400_000_000)
        sec, micro = np.divmod(of_day, 1_000_000)
        ms, us = np.divmod(micro, 1000)
        dates = day_texts(day, lambda d: str(np.datetime64(d, "D")) + "T")
        d3 = _D3_BLOCK
        return (dates, _hms_block()[sec], const_block(".", t_s.shape[0]), d3[ms], d3[us])


@functools.cache
def _hms_block() -> np.ndarray:
    """``hh:mm:ss`` of every second of a day, as a block."""
    d2 = text_block([f"{i:02d}" for i in range(60)])
    colon = np.full((86400, 1), ord(":"), dtype=np.uint8)
    hh = np.repeat(d2[:24], 3600, axis=0)
    mm = np.tile(np.repeat(d2, 60, axis=0), (24, 1))
    ss = np.tile(d2, (1440, 1))
    return np.concatenate((hh, colon, mm, colon, ss), axis=1)


_D3_BLOCK = text_block(_D3)
# A recording line's end is written as 0x01 in the block (no sentence holds one), so that
# compacting it can drop each sentence's own CR LF and turn those into the line ends.
_EOL = 0x01
_LINE_ENDS = bytes(range(256)).replace(bytes([_EOL]), b"\n")


def _repr_pieces(values: np.ndarray) -> tuple[np.ndarray, ...]:
    """``repr`` of every float (the recorder's JSON for a float), as blocks to be put side
    by side (:func:`joined`).

    ``repr(v)`` is the shortest decimal that reads back as ``v``. For ``1 <= v < 2**52`` with
    ``v = i + f`` (``i`` whole) the decimals that read back as ``v`` are ``i`` plus those that
    read back as ``f`` on the grid of ``v``'s binade (whose spacing divides ``i``), so the
    digits after the point depend on ``f`` and the binade alone; while ``f`` is farther
    than that spacing from 0 and 1 the integer part is ``i`` itself. A chunk's arrival
    times are whole epochs plus a few hundred distinct wire offsets: ``repr`` runs once per
    (binade, ``f``), the integer parts are digits. Other values: ``repr`` each."""
    v = np.asarray(values, dtype=float)
    with np.errstate(invalid="ignore"):
        whole = np.floor(v)
        frac = v - whole  # exact
        cached = np.isfinite(v) & (v >= 1.0) & (v < 2.0**52) & (frac > 1e-6) & (frac < 1.0 - 1e-6)
    # one key per (binade, f): f's bits (below 2**62: 0 <= f < 1) and the binade above them
    binade = np.frexp(v)[1]
    low = int(binade[cached].min()) if cached.any() else 0
    cached &= binade - low <= 1
    key = frac.view(np.int64) | ((binade - low).astype(np.int64) << 62)
    keys, first, inverse = np.unique(
        np.where(cached, key, -1), return_index=True, return_inverse=True
    )
    digits = []
    for k, i in zip(keys.tolist(), first.tolist(), strict=True):
        head, _, tail = repr(float(v[i])).partition(".")
        ok = k >= 0 and head == str(int(whole[i])) and tail.isdigit()
        digits.append(tail if ok else "")  # (not ok: never seen, but repr would say)
    table = text_block(digits)
    cached &= table[inverse.reshape(-1), 0] != 0
    n = v.shape[0]
    # the integer parts: digits once per whole second of the chunk
    ints = np.where(cached, whole, 0.0).astype(np.int64)
    lo, hi = (int(ints.min()), int(ints.max())) if n else (0, n)
    few = hi - lo < n  # (a chunk's arrivals span its hour)
    int_text = uint_block(np.arange(lo, hi + 1))[ints - lo] if few else uint_block(ints)
    pieces = (int_text, const_block(".", n), table[inverse.reshape(-1)])
    rest = np.flatnonzero(~cached)
    if not rest.size:
        return pieces
    block = put_texts(joined(pieces), rest, [repr(x).encode("ascii") for x in v[rest].tolist()])
    return (block,)
