"""The simulated GPS receiver, built from a scenario in ONE place.

:func:`build_receiver` turns a :class:`~sim_backend.world.World` into a :class:`SimReceiver`:

- the GNSS model (:class:`~sim_backend.gnss.GnssModel`): the scenario's almanac sky, origin,
  start time, fidelity, elevation mask, atmosphere, walls and roofs, receiver parameters and
  the seed-003 LCE grid;
- the scenario's ``[[effects]]`` GPS layers, each running on the receiver's output the one way
  layers run (:meth:`sim_backend.effects.GpsLayer.start`: own state, own random stream
  spawned from the effects stream; a latency layer delays what the model solves for), in
  list order by stage (the minutes' rounding after the rest, as a receiver prints last);
- the NEO-5 NMEA formatter (the scenario's minute decimals and rate) and the UART at its baud
  rate (:class:`UartTx`, 8N1: each sentence arrives when its last byte has crossed the wire;
  a bounded transmit buffer queues what the line cannot carry at once and drops whole
  sentences when it is full).

Every user of the simulated receiver builds it here: ``x6wd sim``
(:mod:`sim_backend.mission`, closed loop in fast time), HIL (:mod:`sim_backend.hil`, closed
loop in real time) and the gap tool's baselines (:mod:`x6wd.gap.scenario`, a whole real log's
truth at once through :meth:`SimReceiver.errors`).

Randomness: :class:`SimRandom` splits one seed into the streams of a run (GNSS model, compass
noise, I2C faults, effects) exactly as ``x6wd sim`` always has, so a seed means the same
receiver in all three.

Conventions: times are scenario seconds; positions are metres in the origin's local ENU frame
(the antenna), velocities m/s ENU.
"""

from __future__ import annotations

import math
import threading
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass, fields, replace
from typing import Any, cast

import numpy as np

from sim_backend.effects import (
    GpsLayer,
    LayerRun,
    PositionSeries,
    Quantization,
    interp_track,
    metres_per_degree,
    satellite_set_id,
    truth_track_m,
    truth_velocity_mps,
)
from sim_backend.epoch import GnssEpoch
from sim_backend.geodesy import EnuFrame, enu_to_lla
from sim_backend.gnss import GnssBatch, GnssModel, LceGrid, ReceiverParams
from sim_backend.nmea_out import NmeaFormatter, sentence, wire_time_s
from sim_backend.sky import SatelliteSet
from sim_backend.world import World
from x6wd.core.errors import ConfigError
from x6wd.core.geodesy import wrap_deg


@dataclass(frozen=True)
class SimRandom:
    """The random streams of one simulated run, all from one seed: the GNSS model, the
    compass's magnetometer noise, its I2C faults, and the ``[[effects]]`` layers (each layer
    gets its own stream spawned from ``effects``)."""

    gnss: np.random.Generator
    compass: np.random.Generator
    i2c: np.random.Generator
    effects: np.random.Generator

    @classmethod
    def from_seed(cls, seed: int) -> SimRandom:
        """Split ``seed`` (>= 0) as ``x6wd sim`` does (SeedSequence children 0..3)."""
        ss = np.random.SeedSequence(seed)
        gnss, compass, i2c, effects = (np.random.default_rng(s) for s in ss.spawn(4))
        return cls(gnss, compass, i2c, effects)


class TruthHistory:
    """A short history of the true antenna track, for a receiver that reports late.

    ``add`` takes (time s, east/north/up m, velocity east/north/up m/s) in time order;
    ``at(t)`` interpolates linearly (the law of :func:`sim_backend.effects.interp_track`);
    before the first sample the vehicle is taken to move with its first velocity. Entries
    older than ``keep_s`` before the newest are dropped.
    """

    def __init__(self, keep_s: float) -> None:
        self.keep_s = keep_s + 1.0
        self._rows: deque[tuple[float, float, float, float, float, float, float]] = deque()
        self._first: tuple[float, float, float, float, float, float, float] | None = None

    def __len__(self) -> int:
        return len(self._rows)

    def add(self, t_s: float, pos_m: Sequence[float], vel_mps: Sequence[float]) -> None:
        """Append the truth at ``t_s`` (s): position (m) and velocity (m/s), ENU."""
        row = (t_s, float(pos_m[0]), float(pos_m[1]), float(pos_m[2]),
               float(vel_mps[0]), float(vel_mps[1]), float(vel_mps[2]))  # fmt: skip
        if self._first is None:
            self._first = row
        self._rows.append(row)
        while len(self._rows) > 2 and self._rows[1][0] < t_s - self.keep_s:
            self._rows.popleft()

    def at(self, t_s: float) -> tuple[tuple[float, float, float], tuple[float, float, float]]:
        """(position m, velocity m/s) at ``t_s`` (s)."""
        rows = self._rows
        if not rows or self._first is None:
            raise ValueError("TruthHistory is empty")
        f = self._first
        if t_s <= f[0]:
            dt = t_s - f[0]
            return (f[1] + dt * f[4], f[2] + dt * f[5], f[3] + dt * f[6]), (f[4], f[5], f[6])
        if t_s <= rows[0][0]:
            r = rows[0]  # older than kept: the oldest kept sample (keep_s covers the delay)
            return (r[1], r[2], r[3]), (r[4], r[5], r[6])
        for j in range(len(rows) - 1, 0, -1):
            a, b = rows[j - 1], rows[j]
            if a[0] <= t_s <= b[0]:
                w = 0.0 if b[0] == a[0] else (t_s - a[0]) / (b[0] - a[0])
                p = tuple(a[m] + w * (b[m] - a[m]) for m in range(1, 7))
                return (p[0], p[1], p[2]), (p[3], p[4], p[5])
        r = rows[-1]
        return (r[1], r[2], r[3]), (r[4], r[5], r[6])


UART_TX_BUFFER_BYTES = 1024  # the receiver's transmit buffer per port (assumed: not published)


class UartTx:
    """The receiver's UART transmitter: a bounded buffer drained at the line's rate.

    A u-blox receiver writes each epoch's messages into a per-port transmit buffer that
    the UART empties at ``baud`` / 10 bytes per second (8N1). When the enabled messages
    need more than the line carries (e.g. 4 Hz at 9600 baud), the backlog grows until the
    buffer is full; from then on a message that does not fit is discarded WHOLE, never
    torn, and is not sent later (u-blox: "discarded messages won't be transmitted").
    Pure arithmetic on the scenario clock, so fast time (``x6wd sim``) and HIL drop the
    same sentences for the same epochs; :attr:`dropped` counts them.
    """

    def __init__(self, baud: int, buffer_bytes: int = UART_TX_BUFFER_BYTES) -> None:
        """``baud`` (bit/s, 8N1) and the buffer's size (bytes)."""
        wire_time_s(0, baud)  # validates the baud rate
        if buffer_bytes <= 0:
            raise ConfigError(f"UART buffer_bytes must be positive, got {buffer_bytes}")
        self.baud = int(baud)
        self.buffer_bytes = int(buffer_bytes)
        self.free_at_s = -math.inf  # when the last queued byte has left the wire
        self.dropped = 0
        self.sent = 0

    def queued_bytes(self, t_s: float) -> float:
        """Bytes still waiting in the buffer at ``t_s`` (s)."""
        return max(0.0, self.free_at_s - t_s) * self.baud / 10.0

    def send(self, lines: Sequence[bytes], t_s: float) -> list[tuple[float, bytes]]:
        """Queue ``lines`` (whole sentences, in order) at ``t_s`` (s, non-decreasing between
        calls); returns those accepted with the time (s) each one's last byte arrives."""
        out = []
        for line in lines:
            if self.queued_bytes(t_s) + len(line) > self.buffer_bytes:
                self.dropped += 1
                continue
            self.free_at_s = max(self.free_at_s, t_s) + wire_time_s(len(line), self.baud)
            self.sent += 1
            out.append((self.free_at_s, line))
        return out

    def send_bursts(
        self, bursts: Sequence[bytes], t_s: Sequence[float]
    ) -> list[tuple[float, bytes]]:
        """:meth:`send` of each burst's sentences at its time (s), in one call: the same
        arithmetic, in the same order, without a method call per sentence (a 10 h survey
        sends 290,000 of them)."""
        out: list[tuple[float, bytes]] = []
        append = out.append
        baud, cap = self.baud, self.buffer_bytes
        free_at, dropped, sent = self.free_at_s, self.dropped, self.sent
        for burst, t in zip(bursts, t_s, strict=True):
            for line in burst.splitlines(keepends=True):
                n = len(line)
                # queued_bytes() and wire_time_s() written out, operations in their order
                # (a conditional picks what max() would, NaN included, without the call)
                wait = free_at - t
                if (wait if wait > 0.0 else 0.0) * baud / 10.0 + n > cap:
                    dropped += 1
                    continue
                free_at = (t if t > free_at else free_at) + n * 10 / baud
                sent += 1
                append((free_at, line))
        self.free_at_s, self.dropped, self.sent = free_at, dropped, sent
        return out

    def send_table(self, lengths: np.ndarray, t_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`send` of each epoch's sentences given by their sizes: row ``e`` of
        ``lengths`` (E, K) the bytes of epoch e's sentences in order (0: no sentence there),
        handed over at ``t_s[e]`` (s, increasing). Returns each sentence's arrival time (s, its
        last byte) and whether it was sent (False: dropped, or no sentence), both (E, K).

        The same arithmetic in the same order as :meth:`send`. Bursts that find the wire idle
        and lose nothing (every burst at 1 Hz and 9600 baud) run down the K columns for all
        epochs at once; any other burst, sentence by sentence."""
        n = np.asarray(lengths, dtype=np.int64)
        t = np.asarray(t_s, dtype=float)
        n_e, n_k = n.shape
        arrive = np.empty((n_e, n_k))
        sent = np.zeros((n_e, n_k), dtype=bool)
        if n_e == 0:
            return arrive, sent
        exists = n > 0
        # Every burst as if it found the wire idle: its sentences one after the other from t.
        wire = n * 10 / self.baud  # wire_time_s: (bytes * bits) / baud, one rounding
        prev = t
        for k in range(n_k):
            arrive[:, k] = prev + wire[:, k]  # + 0.0 where there is no sentence: unchanged
            prev = arrive[:, k]
        wait = np.zeros((n_e, n_k))  # queued ahead of each sentence (s); none at an idle start
        wait[:, 1:] = arrive[:, :-1] - t[:, None]
        queued = np.where(wait > 0.0, wait, 0.0) * self.baud / 10.0
        own: np.ndarray = np.any(exists & (queued + n > self.buffer_bytes), axis=1)
        own |= ~np.any(exists, axis=1)  # (and an epoch without sentences: one by one)
        # a burst that is fine itself is right as computed if the one before it was and
        # ended by its time
        fail = own.copy()
        fail[1:] |= ~(arrive[:-1, -1] <= t[1:])
        at = np.where(fail, np.arange(n_e), n_e)
        next_fail = np.minimum.accumulate(at[::-1])[::-1]  # first failing burst from each on
        baud, cap = self.baud, self.buffer_bytes
        free_at, dropped, n_sent = self.free_at_s, self.dropped, self.sent
        rows: list[list[int]] | None = None
        e = 0
        while e < n_e:
            t_e = float(t[e])
            if free_at <= t_e and not own[e]:
                end = int(next_fail[e + 1]) if e + 1 < n_e else n_e
                sent[e:end] = exists[e:end]
                n_sent += int(np.count_nonzero(exists[e:end]))
                free_at = float(arrive[end - 1, -1])
                e = end
                continue
            if rows is None:
                rows = n.tolist()
            for k, size in enumerate(rows[e]):  # send_bursts' arithmetic
                if size <= 0:
                    continue
                wait_s = free_at - t_e
                if (wait_s if wait_s > 0.0 else 0.0) * baud / 10.0 + size > cap:
                    dropped += 1
                    continue
                free_at = (t_e if t_e > free_at else free_at) + size * 10 / baud
                n_sent += 1
                arrive[e, k] = free_at
                sent[e, k] = True
            e += 1
        self.free_at_s, self.dropped, self.sent = free_at, dropped, n_sent
        return arrive, sent


class SimReceiver:
    """The scenario's simulated NEO-5: model, error layers, NMEA and UART timing.

    Closed loop: :meth:`observe` the true antenna track at the physics rate (only needed when
    :attr:`tracks`), :meth:`epoch` once per receiver epoch, then :meth:`nmea` /
    :meth:`sentences` for its bytes and :meth:`arrivals` / :meth:`wire_time_s` for their
    timing. Along a known truth: :meth:`batch` (all epochs at once) or :meth:`errors` (the gap
    tool's error series). ``observe`` and ``epoch`` may run in different threads.
    """

    def __init__(
        self,
        model: GnssModel,
        layers: Sequence[LayerRun],
        formatter: NmeaFormatter,
        baud: int,
    ) -> None:
        """``model`` the GNSS model (its origin is the receiver's frame), ``layers`` the
        running GPS layers in order, ``formatter`` the NMEA printer, ``baud`` (bit/s) the
        UART's rate."""
        self.model = model
        self.layers = tuple(layers)
        self.formatter = formatter
        self.baud = int(baud)
        self.uart = UartTx(self.baud)  # validates the baud rate
        # Chained receiver delays add up: one delay of their sum.
        self.delay_s = float(sum(run.delay_s for run in self.layers))
        self._history = TruthHistory(self.delay_s) if self.delay_s > 0 else None
        self._lock = threading.Lock()
        self._frame: EnuFrame | None = None  # about self.origin, for a position per epoch

    # --- properties ------------------------------------------------------------------------

    @property
    def origin(self) -> tuple[float, float, float]:
        """The local frame's origin: latitude, longitude (deg), altitude (m above MSL)."""
        return self.model.origin

    @property
    def rate_hz(self) -> float:
        """The navigation rate (Hz)."""
        return self.formatter.rate_hz

    @property
    def tracks(self) -> bool:
        """True when the receiver needs the true track between epochs (:meth:`observe`): a
        layer delays it, and the delayed truth is interpolated on the physics-rate track."""
        return self._history is not None

    # --- closed loop -----------------------------------------------------------------------

    def observe(self, t_s: float, pos_enu_m: Sequence[float], vel_enu_mps: Sequence[float]) -> None:
        """The true antenna at ``t_s`` (s, increasing): position (m) and velocity (m/s), ENU.
        Kept only when :attr:`tracks`; call it at every physics step so the delayed position
        follows the real path."""
        if self._history is None:
            return
        with self._lock:
            self._history.add(t_s, pos_enu_m, vel_enu_mps)

    def epoch(
        self,
        t_s: float,
        pos_enu_m: Sequence[float],
        vel_enu_mps: Sequence[float],
        track_t_s: float | None = None,
    ) -> GnssEpoch:
        """The receiver's report at scenario time ``t_s`` (s) for an antenna truly at
        ``pos_enu_m`` (m) moving at ``vel_enu_mps`` (m/s) now.

        With a delay the model solves for the observed track at ``track_t_s - delay_s``
        (``track_t_s``: the time of now on the :meth:`observe` clock, default ``t_s``); the
        layers then act with the truth of now."""
        pos_m: Sequence[float] = pos_enu_m
        vel_m: Sequence[float] = vel_enu_mps
        if self._history is not None:
            now = t_s if track_t_s is None else track_t_s
            with self._lock:
                if not len(self._history):
                    self._history.add(now, pos_enu_m, vel_enu_mps)
                pos_m, vel_m = self._history.at(now - self.delay_s)
        frame = self._frame
        if frame is None or frame.origin != self.origin:
            frame = self._frame = EnuFrame(*self.origin)
        lat, lon, alt = frame.to_lla(np.array(pos_m, dtype=float))
        b = self.model.batch(
            np.array([t_s], dtype=float),
            np.array([float(lat)]),
            np.array([float(lon)]),
            np.array([float(alt)]),
            np.asarray(vel_m, dtype=float).reshape(1, 3),
        )
        if self.layers:
            b = self._layered(
                b,
                np.asarray(pos_enu_m, dtype=float).reshape(1, 3),
                np.asarray(vel_enu_mps, dtype=float).reshape(1, 3),
            )
        return b.epoch(0)

    # --- along a known truth ---------------------------------------------------------------

    def batch(self, t_s: np.ndarray, pos_enu_m: np.ndarray, vel_enu_mps: np.ndarray) -> GnssBatch:
        """All epochs at once along a known truth: times (E,) s increasing, the antenna's
        positions (E, 3) m and velocities (E, 3) m/s, ENU. A delay reads the truth the model
        solves for from these same rows (:func:`sim_backend.effects.interp_track`)."""
        t = np.asarray(t_s, dtype=float)
        pos = np.asarray(pos_enu_m, dtype=float).reshape(t.shape[0], 3)
        vel = np.asarray(vel_enu_mps, dtype=float).reshape(t.shape[0], 3)
        pos_m, vel_m = pos, vel
        if self.delay_s > 0 and t.shape[0]:
            tq = t - self.delay_s
            pos_m = interp_track(t, pos, vel[0], tq)
            vel_m = interp_track(t, vel, np.zeros(3), tq)
        lat0, lon0, alt0 = self.origin
        lat, lon, alt = enu_to_lla(pos_m, lat0, lon0, alt0)
        n = t.shape[0]
        b = self.model.batch(
            t,
            np.broadcast_to(np.asarray(lat, dtype=float), (n,)),
            np.broadcast_to(np.asarray(lon, dtype=float), (n,)),
            np.broadcast_to(np.asarray(alt, dtype=float), (n,)),
            vel_m,
        )
        return self._layered(b, pos, vel) if self.layers else b

    def errors(self, template: PositionSeries) -> PositionSeries:
        """The receiver's position errors (m) shaped like ``template``: its times (from its
        first, as scenario time 0), its true motion (:func:`~sim_backend.effects.truth_track_m`,
        on the ground at the origin's altitude), the layers, and the minutes the NMEA prints
        (the formatter's decimals). Errors are against the truth in this receiver's frame:
        the template's origin should be the receiver's. ``valid`` and ``nsats`` are the
        receiver's; errors at epochs without a fix are 0."""
        t = np.asarray(template.t_s, dtype=float)
        t = t - t[0]
        te, tn = truth_track_m(template)
        ve, vn = truth_velocity_mps(template)
        zeros = np.zeros(t.shape[0])
        pos, vel = np.column_stack([te, tn, zeros]), np.column_stack([ve, vn, zeros])
        parts: list[PositionSeries] = []
        sets: list[np.ndarray] = []
        n_calls = -(-t.shape[0] // ERRORS_CHUNK_EPOCHS)  # bounded memory (see there)
        size = -(-t.shape[0] // n_calls)  # even chunks: no call of a few epochs at the end
        for a in range(0, t.shape[0], size):
            z = slice(a, a + size)
            b = self.batch(t[z], pos[z], vel[z])
            parts.append(self._series(b, te[z], tn[z], zeros[z], ve[z], vn[z]))
            sets.append(used_set_ids(b.used, b.prns))
        joined: dict[str, Any] = {
            f.name: np.concatenate([getattr(p, f.name) for p in parts])
            for f in fields(PositionSeries) if isinstance(getattr(parts[0], f.name), np.ndarray)
        }  # fmt: skip
        s = parts[0] if len(parts) == 1 else replace(parts[0], **joined)
        s = s.with_(east_m=np.nan_to_num(s.east_m), north_m=np.nan_to_num(s.north_m),
                    up_m=np.nan_to_num(s.up_m))  # fmt: skip
        s = Quantization(decimals=self.formatter.minute_decimals).start(_NO_DRAWS).step(s)
        return template.with_(
            east_m=s.east_m, north_m=s.north_m, up_m=s.up_m, valid=s.valid, nsats=s.nsats,
            sat_set=np.concatenate(sets),
        )  # fmt: skip

    # --- bytes and timing ------------------------------------------------------------------

    def banner(self) -> bytes:
        """The ``$GPTXT`` boot banner, printed once when the receiver starts."""
        return self.formatter.banner()

    def nmea(self, ep: GnssEpoch) -> bytes:
        """One epoch's burst of NEO-5 sentences (CRLF-terminated)."""
        return self.formatter.format_epoch(ep)

    def sentences(self, ep: GnssEpoch) -> list[bytes]:
        """One epoch's sentences, each complete with ``$``, checksum and CRLF, in the order
        they leave the receiver (:meth:`nmea` joined)."""
        return [sentence(body) for body in self.formatter.epoch_bodies(ep)]

    def wire_time_s(self, n_bytes: int) -> float:
        """Seconds ``n_bytes`` take on the receiver's UART (8N1 at :attr:`baud`)."""
        return wire_time_s(n_bytes, self.baud)

    def arrivals(self, burst: bytes, t_s: float) -> list[tuple[float, bytes]]:
        """The sentences of ``burst``, handed to the UART at ``t_s`` (s), that the line
        carries, each with the time (s) its last byte arrives (:meth:`UartTx.send`): they
        queue behind bytes still waiting and are dropped whole when the buffer is full."""
        return self.uart.send(burst.splitlines(keepends=True), t_s)

    # --- the layers ------------------------------------------------------------------------

    def _series(
        self,
        b: GnssBatch,
        te: np.ndarray,
        tn: np.ndarray,
        tu: np.ndarray,
        ve: np.ndarray,
        vn: np.ndarray,
    ) -> PositionSeries:
        """The batch's reports as errors (m) against the truth, through the origin's linear
        degrees-to-metres map (so the round trip back to degrees is exact). The longitude
        difference is taken the short way round: a report across the 180th meridian from the
        origin (-179.99999 against 179.99999) is metres east, not the Earth's circumference
        west; every other difference is left bit for bit as it was."""
        lat0, lon0, alt0 = self.origin
        e_per, n_per = metres_per_degree(lat0)
        speed = np.hypot(ve, vn)
        dlon = np.asarray(b.lon_deg, dtype=float) - lon0
        dlon = np.where(np.abs(dlon) > 180.0, wrap_deg(dlon), dlon)
        return PositionSeries(
            t_s=np.asarray(b.t_s, dtype=float),
            east_m=dlon * e_per - te,
            north_m=(b.lat_deg - lat0) * n_per - tn,
            up_m=b.alt_m - (alt0 + tu),
            valid=np.asarray(b.valid, dtype=bool).copy(),
            origin_lat_deg=lat0,
            origin_lon_deg=lon0,
            speed_mps=speed,
            course_deg=np.degrees(np.arctan2(ve, vn)) % 360.0,
            nsats=np.asarray(b.n_used),
            true_east_m=te,
            true_north_m=tn,
        )

    def _layered(self, b: GnssBatch, pos: np.ndarray, vel: np.ndarray) -> GnssBatch:
        """``b`` with every layer stepped over it, in order (truth: ``pos``/``vel`` now)."""
        s0 = self._series(b, pos[:, 0], pos[:, 1], pos[:, 2], vel[:, 0], vel[:, 1])
        s = s0
        for run in self.layers:
            s = run.step(s)
        _lat0, _lon0, _alt0 = self.origin
        e_per, n_per = metres_per_degree(_lat0)
        ok = np.asarray(b.valid, dtype=bool) & np.asarray(s.valid, dtype=bool)
        d = np.column_stack([s.east_m - s0.east_m, s.north_m - s0.north_m, s.up_m - s0.up_m])
        nan = np.full(ok.shape[0], math.nan)
        return replace(
            b,
            valid=ok,
            lat_deg=np.where(ok, b.lat_deg + d[:, 1] / n_per, nan),
            lon_deg=np.where(ok, b.lon_deg + d[:, 0] / e_per, nan),
            alt_m=np.where(ok, b.alt_m + d[:, 2], nan),
            speed_mps=np.where(ok, b.speed_mps, 0.0),
            course_deg=np.where(ok, b.course_deg, nan),
            hdop=np.where(ok, b.hdop, nan),
            pdop=np.where(ok, b.pdop, nan),
            vdop=np.where(ok, b.vdop, nan),
            n_used=np.where(ok, b.n_used, 0),
            used=b.used & ok[:, None],
            err_enu_m=np.where(ok[:, None], b.err_enu_m + d, nan[:, None]),
        )


ERRORS_CHUNK_EPOCHS = 7200
""":meth:`SimReceiver.errors` runs the model at most this many epochs per call, in even
chunks: one call over a 1 h 10 Hz log (36,000 epochs) took ~240 MB of per-satellite
processes and geometry, 7,200 epochs take ~50 MB. A template of at most this many epochs (an
hour at 1 Hz, with or without its closing epoch, and two hours) is one call, as it always
was; a longer one draws chunk by chunk, differing from one call by the draw order only."""

_NO_DRAWS = cast(np.random.Generator, None)  # for layers that draw nothing (the print lattice)


def build_gnss_model(world: World, rng: np.random.Generator) -> GnssModel:
    """The scenario's GNSS model (sky, atmosphere, walls, LCE grid, receiver parameters,
    fidelity, mask) driven by ``rng``."""
    g = world.gnss
    lce_arr = world.lce_array()
    lce = (
        None
        if lce_arr is None
        else LceGrid(g.lce_east0_m, g.lce_north0_m, g.lce_cell_m, lce_arr, g.lce_outside_m)
    )
    params = ReceiverParams(
        seed_uere=g.seed_uere,  # type: ignore[arg-type]
        re_sigma_m=g.re_m,
        ase_sigma_m=g.ase_m,
        lce=lce,
        max_channels=g.max_channels,
    )
    o = world.origin
    return GnssModel(
        SatelliteSet.from_file(world.almanac_path, world.start_utc),
        o.lat_deg,
        o.lon_deg,
        o.alt_m,
        world.start_utc,
        fidelity=g.fidelity,  # type: ignore[arg-type]
        mask_deg=g.mask_deg,
        atmosphere=world.atmosphere,
        walls=cast(Any, world.walls_model()),  # buildings.Walls implements gnss.Walls
        receiver=params,
        rng=rng,
    )


def used_set_ids(used: np.ndarray, prns: np.ndarray) -> np.ndarray:
    """Per epoch, the identity (:func:`~sim_backend.effects.satellite_set_id`) of the
    satellites used (``used``: epochs x satellites, bool; ``prns``: the satellites' ids), as
    the receiver's GSA lists them; computed once per distinct set."""
    used = np.asarray(used, dtype=bool)
    if used.ndim != 2 or used.shape[0] == 0:
        return np.zeros(used.shape[0] if used.ndim else 0)
    sets, inverse = np.unique(used, axis=0, return_inverse=True)
    ids = np.array([satellite_set_id(np.asarray(prns)[row]) for row in sets])
    return ids[np.ravel(inverse)]


def build_receiver(
    world: World, rand: SimRandom | int, extra_layers: Sequence[GpsLayer] = ()
) -> SimReceiver:
    """The scenario's simulated receiver (see the module docstring).

    ``rand``: the run's streams, or a seed to split (:meth:`SimRandom.from_seed`).
    ``extra_layers`` run after the scenario's own GPS layers (the gap tool's injection
    benchmark adds the effects it withholds)."""
    if not isinstance(rand, SimRandom):
        rand = SimRandom.from_seed(int(rand))
    layers: list[GpsLayer] = [e for e in world.effect_objects() if e.kind == "gps"]
    layers += list(extra_layers)
    # Each layer its own stream (in list order): what one draws never shifts another's.
    streams = rand.effects.spawn(len(layers)) if layers else []
    runs = sorted(zip(layers, streams, strict=True), key=lambda pair: pair[0].stage)
    g = world.gnss
    return SimReceiver(
        build_gnss_model(world, rand.gnss),
        [layer.start(r) for layer, r in runs],
        NmeaFormatter(minute_decimals=g.nmea_decimals, rate_hz=g.rate_hz),
        g.baud,
    )
