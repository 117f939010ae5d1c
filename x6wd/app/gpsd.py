"""A read-only gpsd-compatible telemetry port (gpsd client protocol 3.14, JSON over TCP).

Encoders are pure functions from x6wd records to gpsd objects; :class:`GpsdServer` is the
asyncio endpoint. What real clients rely on (REFERENCE §5): VERSION on connect, DEVICES
listing one device before the WATCH echo, COMPACT JSON (libgps 3.22 finds ``"class":"TPV"``
by text match), CRLF line ends, and no ``null`` (unknown fields are omitted).
A slow client never blocks the publisher: each client has a bounded queue and the oldest
report is dropped (and counted) when it is full.

The port follows the GPS link (:meth:`GpsdServer.set_gps_state`): while it is lost, DEVICES
lists no device, POLL is inactive and watchers were sent ``DEVICE`` ``"activated":0``, as
gpsd does. A fix older than the robot's own staleness limit (``[safety] fix_stale_s``) is
never handed out again, neither by POLL nor to a new watcher: a client must not show a
lost position as current.

Lock-out protection (shared mechanics in :mod:`x6wd.app.lineserver`): there is no
authentication, so a connection is pending until it sends one valid command (``?WATCH``,
``?POLL``, ``?VERSION``, ``?DEVICES``); pending connections have their own pool and deadline,
a client neither watching nor sending a command for ``idle_timeout_s`` is closed, and so is a
watcher that never reads (``slow_client_s``). A full pool makes room instead of refusing.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import math
import re
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from datetime import UTC, datetime
from typing import Any

import numpy as np

from drivers.gps_nmea import STATUS_DGPS, fix_status
from x6wd import __version__
from x6wd.app.lineserver import (
    LISTEN_BACKLOG,
    LineClient,
    LineServer,
    peer_names,
    write_buffer_size,
)
from x6wd.core.config import GpsdConfig, SafetyConfig
from x6wd.core.errors import ProtocolError
from x6wd.core.geodesy import wrap360
from x6wd.core.records import Attitude, DeviceState, GpsFix, GpsSky, SatInfo

log = logging.getLogger(__name__)

GPSD_RELEASE = "3.22"
PROTO_MAJOR = 3
PROTO_MINOR = 14
UERE_M = 5.0
"""User-equivalent range error used to turn DOP into the eph/epv estimates (metres, 1 sigma)."""
MAX_COMMAND_BYTES = 4096  # one read of a client's bytes
MAX_REQUEST_BYTES = 2 * MAX_COMMAND_BYTES  # the longest request taken, with or without "\n"
MAX_PENDING_REPLIES = 256
"""With more replies than this waiting, the port reads no more of that client's requests
until they are written: a client asking faster than it reads is held back, not closed (one
that does not read at all is closed as a slow reader)."""
MAX_ECHO_CHARS = 40
"""An error echoes at most this much of the request it refuses (gpsd echoes the whole of
its 8 KB input buffer): a client learns what was refused without getting it back whole."""
MAX_NAME_CHARS = 16
"""A bare command name longer than this (gpsd's are 4 to 7 letters) that arrived without a
newline is not taken as complete: it is a long request cut by a read, and waits for its end."""
REFUSED_LINGER_S = 1.0
"""After refusing a request too long, the port reads and discards what the client still sends
for this long (s) at most before closing, so the close is a FIN after the error, not a reset
that may throw the error away unread."""
REFUSED_DISCARD_BYTES = 1 << 20
"""The most bytes read and dropped after refusing a request too long (1 MiB; see
:data:`REFUSED_LINGER_S`)."""
COMMANDS = frozenset({"WATCH", "POLL", "VERSION", "DEVICES", "DEVICE"})

DEVICE_SETTINGS = ("bps", "parity", "stopbits", "native", "cycle", "mincycle", "hexdata")
"""?DEVICE={...} keys that would change the receiver: gpsd applies them; here the daemon's own
[gps] configuration rules the line, so they are refused (`gpsctl` then says why)."""
WATCH_FLAGS = ("scaled", "timing", "split24", "pps")
"""?WATCH options that change nothing this port sends (no scaling, PPS or timing objects):
echoed as asked, as gpsd echoes them."""
GPS_DOWN_STATES = frozenset({DeviceState.DISCONNECTED, DeviceState.RECONNECTING})
"""GPS link states in which the port lists no device (the link is closed; a stale but open
link stays listed, as gpsd keeps a silent receiver's device)."""
DEFAULT_MAX_PENDING = 32
"""Connections that have not sent a valid command yet (there is no GpsdConfig key)."""
DEFAULT_PENDING_TIMEOUT_S = 5.0
"""Seconds a new connection has to send its first valid command (gpsd clients send
``?WATCH`` at once; there is no GpsdConfig key)."""


def dumps(obj: dict[str, Any]) -> bytes:
    """One gpsd line: compact JSON, CRLF, with ``None`` values removed at the top level."""
    clean = {k: v for k, v in obj.items() if v is not None}
    return json.dumps(clean, separators=(",", ":"), allow_nan=False).encode() + b"\r\n"


def iso_time(utc: datetime | None) -> str | None:
    """ISO-8601 UTC with milliseconds and a ``Z``, as gpsd prints it; None if unknown."""
    if utc is None:
        return None
    if utc.tzinfo is not None:
        utc = utc.astimezone(UTC).replace(tzinfo=None)
    return utc.strftime("%Y-%m-%dT%H:%M:%S.") + f"{utc.microsecond // 1000:03d}Z"


def _num(v: float | None, ndigits: int) -> float | None:
    if v is None or not math.isfinite(v):
        return None
    return round(float(v), ndigits)


def version_obj() -> dict[str, Any]:
    """The VERSION object sent on connect and answering ``?VERSION``."""
    return {
        "class": "VERSION",
        "release": GPSD_RELEASE,
        "rev": f"x6wd-{__version__}",
        "proto_major": PROTO_MAJOR,
        "proto_minor": PROTO_MINOR,
    }


def devices_obj(
    path: str, bps: int | None = 9600, cycle_s: float = 1.0, activated: datetime | None = None
) -> dict[str, Any]:
    """DEVICES with exactly one device (an empty list leaves cgps blank)."""
    return {"class": "DEVICES", "devices": [device_obj(path, bps, cycle_s, activated)]}


def device_obj(
    path: str, bps: int | None = 9600, cycle_s: float = 1.0, activated: datetime | None = None
) -> dict[str, Any]:
    """One DEVICE object describing the GPS receiver: its serial settings (``bps`` None: not
    a serial line, e.g. a TCP or replay source, so no bps/parity/stopbits, as gpsd omits
    them), its cycle (s between fixes) and when it was opened (``activated``; None: now)."""
    obj: dict[str, Any] = {
        "class": "DEVICE",
        "path": path,
        "driver": "NMEA0183",
        "activated": iso_time(activated or datetime.now(UTC)),
        "flags": 1,
        "native": 0,
    }
    if bps is not None:
        obj.update(bps=int(bps), parity="N", stopbits=1)
    obj["cycle"] = _num(cycle_s, 3)
    return {k: v for k, v in obj.items() if v is not None}


def tpv_obj(fix: GpsFix, device: str | None = None) -> dict[str, Any]:
    """TPV report for one fix; fields the fix does not have are omitted, never null.

    ``status`` is gpsd's fix status of the GGA quality (2 DGPS, 3 RTK fixed, 4 RTK float,
    5 dead reckoning, 7 surveyed, 8 simulated; ``drivers.gps_nmea.fix_status``), shown from
    2 on as gpsd shows it. eph/epx/epy/epv (metres) are DOP x :data:`UERE_M` estimates.
    """
    mode = fix.mode if fix.valid else 1
    # gpsd's fix status (DGPS, RTK, ...) from the GGA quality; gpsd leaves out 0 (no fix)
    # and 1 (a plain fix), so does this, and an invalid fix has none.
    status = fix_status(fix.quality) if fix.valid else 0
    obj: dict[str, Any] = {
        "class": "TPV",
        "device": device,
        "status": status if status >= STATUS_DGPS else None,
        "mode": mode,
    }
    t = iso_time(fix.utc)
    if t is not None:
        obj["time"] = t
    if fix.valid and mode >= 2 and fix.lat_deg is not None and fix.lon_deg is not None:
        obj["lat"] = _num(fix.lat_deg, 9)
        obj["lon"] = _num(fix.lon_deg, 9)
        if mode >= 3 and fix.alt_m is not None:
            obj["altMSL"] = _num(fix.alt_m, 3)
            obj["alt"] = obj["altMSL"]
            if fix.geoid_sep_m is not None:
                obj["altHAE"] = _num(fix.alt_m + fix.geoid_sep_m, 3)
                obj["geoidSep"] = _num(fix.geoid_sep_m, 3)
        if fix.speed_mps is not None:
            obj["speed"] = _num(fix.speed_mps, 3)
        if fix.course_deg is not None:
            obj["track"] = _num(fix.course_deg, 4)
        if fix.hdop is not None:
            eph = fix.hdop * UERE_M
            obj["eph"] = _num(eph, 3)
            obj["epx"] = obj["epy"] = _num(eph / math.sqrt(2.0), 3)
        if fix.vdop is not None and mode >= 3:
            obj["epv"] = _num(fix.vdop * UERE_M, 3)
    return {k: v for k, v in obj.items() if v is not None}


MIN_DET = 1e-4
"""The least determinant of the line-of-sight product a geometry's DOPs are taken from
(gpsd's limit: below it the matrix is treated as singular, no DOPs)."""


def geometry_dops(satellites: Iterable[SatInfo]) -> dict[str, float] | None:
    """The dilutions of precision of the used satellites' geometry, as gpsd fills in those a
    receiver does not report: ``xdop`` (east), ``ydop`` (north), ``hdop``, ``vdop``,
    ``pdop``, ``tdop`` (clock) and ``gdop``, dimensionless, from each satellite's unit
    line of sight (azimuth, elevation in degrees) and a clock column, unweighted. A
    satellite without a number >= 1 or with its azimuth outside 0-359 deg or elevation
    outside +-90 deg is left out; None with fewer than 4 or a singular geometry."""
    rows = []
    for s in satellites:
        az, el = s.az_deg, s.el_deg
        if not s.used or s.prn < 1 or az is None or el is None:
            continue
        if not (0.0 <= az <= 359.0 and abs(el) <= 90.0):  # NaN fails both
            continue
        az_rad, el_rad = math.radians(az), math.radians(el)
        rows.append((math.sin(az_rad) * math.cos(el_rad), math.cos(az_rad) * math.cos(el_rad),
                     math.sin(el_rad), 1.0))  # fmt: skip
    if len(rows) < 4:
        return None
    g = np.array(rows)
    product = g.T @ g
    if abs(float(np.linalg.det(product))) < MIN_DET:
        return None
    q = np.diag(np.linalg.inv(product))
    if not (np.all(np.isfinite(q)) and np.all(q > 0.0)):
        return None
    e, n, u, t = (float(v) for v in q)
    return {
        "xdop": math.sqrt(e), "ydop": math.sqrt(n), "hdop": math.sqrt(e + n),
        "vdop": math.sqrt(u), "pdop": math.sqrt(e + n + u), "tdop": math.sqrt(t),
        "gdop": math.sqrt(e + n + u + t),
    }  # fmt: skip


def sky_obj(
    sky: GpsSky, device: str | None = None, fill_dops: bool = True, zero_ss: bool = False
) -> dict[str, Any]:
    """SKY report: DOPs, satellite counts and the satellite list (PRN, gnssid, svid, used,
    el, az, ss; gnssid and svid omitted for a number in no known range; a satellite without
    a signal has no ss, or with ``zero_ss`` ss 0.0 as gpsd sends it: the port's, since
    python3-gps and gpscsv show -999 for a missing one; ``x6wd decode`` omits it). The
    receiver's hdop, vdop and pdop as it reported them; with ``fill_dops`` the others (xdop,
    ydop, tdop, gdop), and any it left out, from the used satellites' geometry
    (:func:`geometry_dops`), as gpsd does (``x6wd decode`` writes the receiver's alone)."""
    sats: list[dict[str, Any]] = []
    for s in sky.satellites:
        d: dict[str, Any] = {"PRN": s.prn, "gnssid": s.gnssid, "svid": s.svid, "used": bool(s.used)}
        if s.el_deg is not None:
            d["el"] = _num(s.el_deg, 1)
        if s.az_deg is not None:
            d["az"] = _num(s.az_deg, 1)
        if s.snr_dbhz is not None:
            d["ss"] = _num(s.snr_dbhz, 1)
        elif zero_ss:  # no signal, as gpsd sends it (with no "ss" libgps clients show -999)
            d["ss"] = 0.0
        sats.append({k: v for k, v in d.items() if v is not None})
    obj: dict[str, Any] = {
        "class": "SKY",
        "device": device,
        "time": iso_time(sky.utc),
        "hdop": _num(sky.hdop, 2),
        "vdop": _num(sky.vdop, 2),
        "pdop": _num(sky.pdop, 2),
    }
    for k, v in ((fill_dops and geometry_dops(sky.satellites)) or {}).items():
        if obj.get(k) is None:
            obj[k] = _num(v, 2)
    obj |= {
        "nSat": len(sats),
        "uSat": sum(1 for s in sky.satellites if s.used),
        "satellites": sats,
    }
    return {k: v for k, v in obj.items() if v is not None}


def att_obj(att: Attitude, device: str, declination_deg: float = 0.0) -> dict[str, Any]:
    """ATT report from the compass: ``heading`` true (declination applied), ``mheading``
    magnetic as read, ``pitch``/``roll`` in degrees."""
    obj: dict[str, Any] = {"class": "ATT", "device": device}
    if att.valid:
        obj["heading"] = _num(wrap360(att.bearing_deg + declination_deg), 1)
        obj["mheading"] = _num(att.bearing_deg, 1)
        obj["pitch"] = _num(att.pitch_deg, 1)
        obj["roll"] = _num(att.roll_deg, 1)
    return {k: v for k, v in obj.items() if v is not None}


_NOT_UTF8 = re.compile("[\udc80-\udcff]")
"""Bytes that were not UTF-8, as ``surrogateescape`` decoding keeps them."""
# one way only to match each text: "\s*;?\s*" between commands split a run of blanks in
# as many ways as it is long, and a text that then failed ("?A  ?A  ...?") backtracked
# through all of them (20 commands: minutes on the event loop)
_BARE_COMMANDS = re.compile(rf"\s*(?:\?[A-Za-z]{{1,{MAX_NAME_CHARS}}}\s*(?:;\s*)?)+")
_BARE_PREFIX = re.compile(rf"\s*(?:\?[A-Za-z]{{1,{MAX_NAME_CHARS}}}\s*(?:;\s*)?)*")


def shown(text: str) -> str:
    """``text`` as an error echoes it: at most :data:`MAX_ECHO_CHARS`, then ``...``; a
    byte that was not UTF-8 is shown as U+FFFD."""
    text = _NOT_UTF8.sub("\ufffd", text)
    if len(text) <= MAX_ECHO_CHARS:
        return text
    return text[:MAX_ECHO_CHARS] + "..."


def _complete_without_newline(data: bytes | bytearray) -> bool:
    """Whether requests that arrived without a newline are whole. gpsd answers what each
    read brought, and many clients send ``?WATCH={...}`` or ``?POLL;`` with no newline: a
    text ending in ``;``, bare commands (of at most :data:`MAX_NAME_CHARS` letters), or a
    JSON argument that parses is taken as it is; a ``}`` whose JSON does not parse yet waits
    for the rest of the object. Commands followed by junk no continuation can make valid
    (``?VERSION;junk``: a request does not start with ``?``) are whole too: the commands are
    answered, then the junk refused, as gpsd does. A NUL (a C client's string terminator)
    ends the request (:func:`parse_request` ignores what follows it, as gpsd)."""
    return _judge(data)[0]


def _judge(data: bytes | bytearray, start: int = 0, bare: bool = True) -> tuple[bool, int, bool]:
    """:func:`_complete_without_newline` for ``data``, whose commands before byte ``start``
    are known good and finished (``start`` is the ``?`` of a command, or 0; ``bare``: they
    are bare commands), and where to start the next time more bytes are appended to
    ``data`` (with ``bare`` for that start). Only the last command can change as bytes are
    appended (a name ends at a byte that is no letter, an object at its ``}``), so the
    commands before it are not looked at again: a client sending an unfinished request a
    byte at a time costs the bytes it sends, not the whole buffer on each read."""
    if data.find(b"\0", start) >= 0:  # one before start would have ended it already
        return True, start, bare
    # data[start] is "?", so this is the end of data.decode() and text the end of its
    # rstrip() (a blank text when start is 0 only)
    tail = data[start:].decode("utf-8", "replace")
    text = tail.rstrip()
    if not text or text.endswith(";") or (bare and _BARE_COMMANDS.fullmatch(text)):
        return bool(text), start, bare
    starts: list[int] = []
    try:
        _parse_into(text, [], starts)
        error: ProtocolError | None = None
    except ProtocolError as exc:
        error = exc
    if isinstance(error, _Junk):
        return True, start, bare
    complete = error is None and text.endswith("}")
    if starts and starts[-1] > 0:  # the last command's "?" is the next start
        bare = bare and _BARE_PREFIX.fullmatch(text, 0, starts[-1]) is not None
        # "?" is one byte, and a byte that is not UTF-8 never takes one into its U+FFFD:
        # the "?"s of text and data[start:] pair up
        if "\ufffd" not in text[: starts[-1]]:
            start += len(text[: starts[-1]].encode("utf-8"))
        else:
            at = start - 1
            for _ in range(text.count("?", 0, starts[-1]) + 1):
                at = data.index(b"?", at + 1)
            start = at
    return complete, start, bare


async def next_request(reader: asyncio.StreamReader, pending: bytearray) -> bytes | None:
    """The next request from ``reader``: a line, or what arrived without a newline once it
    is complete (:func:`_complete_without_newline`) and nothing more is buffered behind it
    (a burst longer than one read is cut by the read, not by the client); None at the end of
    the stream.
    ``pending`` keeps the bytes read past it. A request longer than
    :data:`MAX_REQUEST_BYTES` comes back as it is, longer than the limit, for the caller
    to refuse."""
    start, bare = 0, True  # pending's commands before start are whole and good (_judge)
    while True:
        end = pending.find(b"\n")
        if end >= 0 or len(pending) > MAX_REQUEST_BYTES:
            cut = end + 1 if end >= 0 else len(pending)
            raw = bytes(pending[:cut])
            del pending[:cut]
            return raw
        # bytes already buffered behind them mean a read cut them: not a request on its own
        more = bool(getattr(reader, "_buffer", b""))  # CPython's StreamReader keeps it here
        if pending and not more:
            complete, start, bare = _judge(pending, start, bare)
            if complete:
                raw = bytes(pending)
                pending.clear()
                return raw
        chunk = await reader.read(MAX_COMMAND_BYTES)
        if not chunk:  # the end of the stream: what is left is the last request
            raw = bytes(pending)
            pending.clear()
            return raw or None
        pending += chunk


def parse_commands(text: str) -> list[tuple[str, dict[str, Any] | None]]:
    """Split client input into ``(COMMAND, argument-or-None)``; ``?WATCH={...};`` style.

    The trailing ``;`` is optional. Raises ProtocolError naming the first bad command.
    """
    cmds, error = parse_request(text)
    if error is not None:
        raise error
    return cmds


def parse_request(
    text: str,
) -> tuple[list[tuple[str, dict[str, Any] | None]], ProtocolError | None]:
    """The commands of one request up to the first bad one, and that one's error (None if
    all are good): a client gets answers to the good commands before the error, as gpsd
    answers ``?VERSION;junk``. The request ends at a NUL: gpsd reads it as a C string, so
    a C client's terminator (and whatever it sent after it) is no command and no error."""
    text = text.partition("\0")[0]
    out: list[tuple[str, dict[str, Any] | None]] = []
    try:
        _parse_into(text, out)
    except ProtocolError as exc:
        return out, exc
    return out, None


class _Junk(ProtocolError):
    """A request that no bytes sent after it can make valid (it does not start with ``?``,
    or a ``?`` is followed by neither a name nor the end of the text)."""


def _parse_into(
    text: str, out: list[tuple[str, dict[str, Any] | None]], starts: list[int] | None = None
) -> None:
    """Parse ``text`` into ``out``; ``starts`` (if given) gets each command's index."""
    decoder = json.JSONDecoder()
    i, n = 0, len(text)
    while i < n:
        c = text[i]
        if c in " \t\r\n;":
            i += 1
            continue
        if c != "?":
            raise _Junk(f"Unrecognized request '{shown(text[i : i + 200].strip())}'")
        if starts is not None:
            starts.append(i)
        j = i + 1
        while j < n and text[j].isalpha():
            j += 1
        name = text[i + 1 : j].upper()
        if not name:
            if j < n:  # "?" then neither a name nor the end: no continuation makes it one
                raise _Junk("Unrecognized request '?'")
            raise ProtocolError("Unrecognized request '?'")
        arg: dict[str, Any] | None = None
        if j < n and text[j] == "=":
            try:
                value, end = decoder.raw_decode(text, j + 1)
            except json.JSONDecodeError as exc:
                raise ProtocolError(f"Invalid JSON argument to ?{shown(name)}: {exc.msg}") from None
            except RecursionError:
                raise ProtocolError(
                    f"Invalid JSON argument to ?{shown(name)}: nested too deeply"
                ) from None
            except ValueError as exc:  # e.g. an integer past the digit limit
                raise ProtocolError(f"Invalid JSON argument to ?{shown(name)}: {exc}") from None
            if not isinstance(value, dict):
                raise ProtocolError(f"?{shown(name)} argument must be a JSON object")
            if _NOT_UTF8.search(text, j + 1, end):  # JSON takes the escaped bytes as text
                raise ProtocolError(f"Invalid JSON argument to ?{shown(name)}: not UTF-8")
            arg, j = value, end
        out.append((name, arg))
        i = j


@dataclass(eq=False, kw_only=True)
class _Client(LineClient):
    # the session's ?WATCH policy, as gpsd keeps it (gps_policy_t)
    watch_enable: bool = False
    watch_json: bool = False
    watch_nmea: bool = False
    watch_raw: int = 0  # 1 and 2 both stream the sentences as received (they are NMEA)
    watch_flags: dict[str, bool] = field(default_factory=dict)  # scaled, timing, ... echoed
    watch_device: str = ""  # the one device asked for ("" all); another path gets nothing
    watch_path: str = ""  # the GPS's path when it asked (the port's one device)
    att_due_s: float = -math.inf  # when its next ATT may go (clock, s; attitude_rate_hz)

    @property
    def streams_json(self) -> bool:
        """Whether JSON reports go to it."""
        return self.watch_enable and self.watch_json and self._device_ok

    @property
    def streams_nmea(self) -> bool:
        """Whether the received sentences go to it."""
        return self.watch_enable and (self.watch_nmea or self.watch_raw > 0) and self._device_ok

    @property
    def _device_ok(self) -> bool:
        return self.watch_device in ("", self.watch_path)


class GpsdServer(LineServer[_Client]):
    """gpsd-compatible read-only endpoint. Call the ``publish_*`` methods from the event loop."""

    pending_timeout_reason = "pending_timeout"
    label = "gpsd port"

    def __init__(
        self,
        bind: str,
        port: int,
        device_path: str,
        *,
        bps: int | None = 9600,
        cycle_s: float = 1.0,
        declination_deg: float = 0.0,
        max_clients: int = 32,
        queue_len: int = 64,
        idle_timeout_s: float = 60.0,
        slow_client_s: float = 10.0,
        attitude_rate_hz: float = 2.0,
        max_pending: int = DEFAULT_MAX_PENDING,
        pending_timeout_s: float = DEFAULT_PENDING_TIMEOUT_S,
        fix_stale_s: float = SafetyConfig.fix_stale_s,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        """``port`` 0 picks a free port (see :attr:`port`); ``device_path``, ``bps`` (the GPS
        line's baud rate; None: not a serial line) and ``cycle_s`` (s between fixes) go into
        DEVICE until :meth:`set_device` says what was opened. Defaults are GpsdConfig's.
        ``max_clients``: sessions (clients that sent a valid command); ``max_pending``:
        connections that have not yet; deadlines in seconds of ``clock`` (monotonic; tests
        inject one). ``fix_stale_s``: a TPV/SKY older than this (s) is not handed to POLL or
        a new watcher (the daemon passes ``[safety] fix_stale_s``). ``attitude_rate_hz``: ATT
        to each JSON watcher at most this often, the newest reading (0: none)."""
        super().__init__(
            port,
            max_clients=max_clients,
            max_pending=max_pending,
            pending_timeout_s=pending_timeout_s,
            idle_timeout_s=idle_timeout_s,
            slow_client_s=slow_client_s,
            clock=clock,
            logger=log,
        )
        self.bind = bind
        self.device_path = device_path
        self.bps = bps
        self.cycle_s = cycle_s
        self.activated: datetime | None = None
        self.declination_deg = declination_deg
        self.queue_len = queue_len
        self.attitude_rate_hz = float(attitude_rate_hz)
        self.fix_stale_s = fix_stale_s
        self.gps_up = True  # the GPS link is open (set_gps_state)
        self._last_tpv: dict[str, Any] | None = None
        self._last_sky: dict[str, Any] | None = None
        self._tpv_t_s = self._sky_t_s = -math.inf  # when they were published (clock, s)

    @classmethod
    def from_config(
        cls,
        cfg: GpsdConfig,
        device_path: str,
        bps: int | None = 9600,
        declination_deg: float = 0.0,
        cycle_s: float = 1.0,
        fix_stale_s: float = SafetyConfig.fix_stale_s,
    ) -> GpsdServer:
        """Build from the ``[gpsd]`` section; ``bps`` (GPS baud rate) and ``cycle_s`` (s
        between fixes) are shown in DEVICE, ``declination_deg`` turns the compass's magnetic
        heading into ATT's true one, ``fix_stale_s`` ([safety]) bounds the age of a fix
        POLL or a new watcher gets."""
        return cls(
            cfg.bind,
            cfg.port,
            device_path,
            bps=bps,
            cycle_s=cycle_s,
            declination_deg=declination_deg,
            max_clients=cfg.max_clients,
            queue_len=cfg.queue_len,
            idle_timeout_s=cfg.idle_timeout_s,
            slow_client_s=cfg.slow_client_s,
            attitude_rate_hz=cfg.attitude_rate_hz,
            fix_stale_s=fix_stale_s,
        )

    async def start(self) -> None:
        """Bind and listen."""
        server = await asyncio.start_server(
            self._handle,
            self.bind,
            self._configured_port,
            limit=MAX_REQUEST_BYTES,
            backlog=LISTEN_BACKLOG,
        )
        self._listening(server)
        log.info("gpsd port listening on %s:%d", self.bind, self.port)

    # -- publishing (sync, never blocks) ----------------------------------------------
    def _fanout(self, line: bytes, nmea: bool) -> None:
        for c in self._sessions:
            wanted = (c.streams_nmea if nmea else c.streams_json) and not c.closed
            if wanted and c.put(line, self.queue_len):
                self.dropped_total += 1

    def publish_fix(self, fix: GpsFix) -> None:
        """Send a TPV to JSON watchers and keep it for ?POLL."""
        obj = tpv_obj(fix, self.device_path)
        self._last_tpv, self._tpv_t_s = obj, self._clock()
        if obj["mode"] < 2:
            # no fix: the kept SKY's DOPs and used satellites are no longer true; an epoch
            # with a GSV/GSA sends its own SKY after this TPV, which replaces this one
            nofix = GpsSky(t_s=fix.t_s, hdop=fix.hdop, vdop=fix.vdop, pdop=fix.pdop, utc=fix.utc)
            nofix_obj = sky_obj(nofix, self.device_path, zero_ss=True)
            self._last_sky, self._sky_t_s = nofix_obj, self._tpv_t_s
        self._fanout(dumps(obj), nmea=False)

    def publish_sky(self, sky: GpsSky) -> None:
        """Send a SKY to JSON watchers and keep it for ?POLL."""
        obj = sky_obj(sky, self.device_path, zero_ss=True)
        self._last_sky, self._sky_t_s = obj, self._clock()
        self._fanout(dumps(obj), nmea=False)

    def set_device(self, path: str, bps: int | None, cycle_s: float) -> None:
        """The GPS as opened: its path, baud rate (None: not a serial line) and cycle (s
        between fixes); DEVICE shows them, activated now, from the next report on."""
        self.device_path, self.bps, self.cycle_s = path, bps, float(cycle_s)
        self.activated = datetime.now(UTC)

    def set_gps_state(self, state: DeviceState) -> None:
        """Follow the GPS link's health state: when it is lost (:data:`GPS_DOWN_STATES`)
        JSON watchers get ``DEVICE`` ``"activated":0`` and the kept fix is forgotten; when it
        is back they get the whole DEVICE again (gpsd's notices)."""
        up = state not in GPS_DOWN_STATES
        if up == self.gps_up:
            return
        self.gps_up = up
        if up:
            line = dumps(device_obj(self.device_path, self.bps, self.cycle_s, self.activated))
        else:
            line = dumps({"class": "DEVICE", "path": self.device_path, "activated": 0})
            self._last_tpv = self._last_sky = None
        self._fanout(line, nmea=False)

    def _device_answer(self, arg: dict[str, Any] | None) -> list[bytes]:
        """?DEVICE; is the DEVICE object of the receiver (nothing while no device is open, as
        gpsd); ?DEVICE={...} names it by ``path`` (another path: gpsd's "Can't open") and may
        not change it: the daemon's [gps] configuration rules the line."""
        if arg is not None:
            path = arg.get("path")
            if isinstance(path, str) and path not in ("", self.device_path):
                return [dumps({"class": "ERROR", "message": f"Can't open {shown(path)}."})]
            if not self.gps_up:
                message = "Can't perform DEVICE configuration, no devices attached."
                return [dumps({"class": "ERROR", "message": message})]
            asked = [k for k in DEVICE_SETTINGS if k in arg]
            if asked:
                message = (
                    f"{', '.join(asked)}: not changed over this port; the robot's receiver"
                    " is configured by its daemon ([gps] in its configuration)"
                )
                return [dumps({"class": "ERROR", "message": message})]
        if not self.gps_up:
            return []
        return [dumps(device_obj(self.device_path, self.bps, self.cycle_s, self.activated))]

    def _devices(self) -> bytes:
        if not self.gps_up:
            return dumps({"class": "DEVICES", "devices": []})  # as gpsd, with no device open
        return dumps(devices_obj(self.device_path, self.bps, self.cycle_s, self.activated))

    def _fresh(self) -> tuple[dict[str, Any] | None, dict[str, Any] | None]:
        """The kept TPV and SKY, each None unless published within ``fix_stale_s``."""
        now = self._clock()
        tpv = self._last_tpv if now - self._tpv_t_s <= self.fix_stale_s else None
        sky = self._last_sky if now - self._sky_t_s <= self.fix_stale_s else None
        return tpv, sky

    def set_declination(self, declination_deg: float) -> None:
        """Use ``declination_deg`` (deg, east positive) for ATT's true heading from now on
        (the daemon passes the World Magnetic Model's value once the first dated fix came)."""
        self.declination_deg = float(declination_deg)

    def publish_attitude(self, att: Attitude) -> None:
        """Send an ATT (compass) to each JSON watcher whose next ATT is due: at most
        ``attitude_rate_hz`` a second (0: never), always this reading, the newest. Every
        reading of a 20 Hz compass would be ~90 % of the stream, and gpsd clients cannot
        turn ATT off: one handling ~10 reports a second would fall ever further behind."""
        if self.attitude_rate_hz <= 0.0:
            return
        period_s = 1.0 / self.attitude_rate_hz
        now = self._clock()
        line: bytes | None = None
        for c in self._sessions:
            if c.closed or not c.streams_json or now < c.att_due_s:
                continue
            # on the period's grid while readings come often enough; after a gap (a new
            # watcher, a silent compass) one period from now: never a burst to catch up
            late = now - c.att_due_s >= period_s
            c.att_due_s = now + period_s if late else c.att_due_s + period_s
            if line is None:
                line = dumps(att_obj(att, self.device_path, self.declination_deg))
            if c.put(line, self.queue_len):
                self.dropped_total += 1

    def publish_nmea(self, sentence: str) -> None:
        """Pass one raw NMEA sentence (without line end) to NMEA watchers."""
        if any(c.streams_nmea for c in self._sessions):
            self._fanout(sentence.rstrip("\r\n").encode("ascii", "replace") + b"\r\n", nmea=True)

    # -- connection handling ----------------------------------------------------------
    def _poll_obj(self) -> dict[str, Any]:
        # active: the link is open and has sent a report (gpsd: a device that was seen); a
        # stale fix reads as no fix (mode 1) rather than the old position (see the module)
        active = self.gps_up and self._last_tpv is not None
        tpv, sky = self._fresh()
        if active and tpv is None:
            tpv = {"class": "TPV", "device": self.device_path, "mode": 1}
        return {
            "class": "POLL",
            "time": iso_time(datetime.now(UTC)),
            "active": 1 if active else 0,
            "tpv": [tpv] if active else [],
            "sky": [sky] if active and sky is not None else [],
        }

    def _watch_obj(self, c: _Client) -> dict[str, Any]:
        obj: dict[str, Any] = {
            "class": "WATCH",
            "enable": c.watch_enable,
            "json": c.watch_json,
            "nmea": c.watch_nmea,
            "raw": c.watch_raw,
        }
        obj.update((k, c.watch_flags.get(k, False)) for k in WATCH_FLAGS)
        if c.watch_device:
            obj["device"] = c.watch_device
        return obj

    @staticmethod
    def _set_watch(c: _Client, arg: dict[str, Any]) -> None:
        """Apply a ?WATCH argument as gpsd does: ``enable`` is true unless it says false;
        ``json``, ``nmea`` and ``raw`` keep the session's values unless named; the flags gpsd
        only echoes (scaled, timing, split24, pps) are what this request says (else false)."""
        c.watch_enable = arg.get("enable", True) is not False
        if "json" in arg:
            c.watch_json = bool(arg["json"])
        if "nmea" in arg:
            c.watch_nmea = bool(arg["nmea"])
        if "raw" in arg:
            raw = arg["raw"]
            c.watch_raw = min(2, max(0, int(raw))) if isinstance(raw, int) else int(bool(raw))
        c.watch_flags = {k: bool(arg.get(k, False)) for k in WATCH_FLAGS}
        device = arg.get("device", "")  # per request, as gpsd
        c.watch_device = device if isinstance(device, str) else str(device)

    def _answer(self, c: _Client, name: str, arg: dict[str, Any] | None) -> list[bytes]:
        if name == "VERSION":
            return [dumps(version_obj())]
        if name == "DEVICES":
            return [self._devices()]
        if name == "DEVICE":
            return self._device_answer(arg)
        if name == "POLL":
            return [dumps(self._poll_obj())]
        if name == "WATCH":
            if arg is not None:  # a bare ?WATCH shows the session's policy, as gpsd
                self._set_watch(c, arg)
            c.watch_path = self.device_path
            if c.watch_enable and c.watch_device not in ("", self.device_path):
                # gpsd: this error alone, and the session streams nothing (no such device)
                message = f"No such device as {shown(c.watch_device)}"
                return [dumps({"class": "ERROR", "message": message})]
            out = [self._devices(), dumps(self._watch_obj(c))]
            if c.streams_json and self.gps_up:
                # an immediate report so a fresh watcher does not wait a whole epoch, but
                # never one older than fix_stale_s: that would show a lost fix as current
                out.extend(dumps(o) for o in self._fresh() if o is not None)
            return out
        return [dumps({"class": "ERROR", "message": f"Unrecognized request '{shown(name)}'"})]

    def _is_watching(self, c: _Client) -> bool:
        # a session watching for ?POLL only (enable, nothing streamed) can still idle out
        return c.streams_json or c.streams_nmea

    def _notice(self, reason: str, message: str) -> bytes:
        return dumps({"class": "ERROR", "message": f"closing: {reason}: {message}"})

    async def _handle(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        task = asyncio.current_task()
        if task is not None:
            self._tasks.add(task)
        peer, host = peer_names(writer)
        c = _Client(writer=writer, peer=peer, host=host, task=task, reader=reader)
        try:
            self._connected(c)
            c.reply(dumps(version_obj()))
            c.sender = asyncio.create_task(self._sender(c))
            pending = bytearray()
            while not c.closed:
                raw = await next_request(reader, pending)
                if raw is None:
                    break
                if len(raw) > MAX_REQUEST_BYTES:
                    await self._refuse(c, reader, raw)
                    break
                c.t_active_s = self._clock()
                # bytes that are not UTF-8 are kept apart from U+FFFD sent as such
                text = raw.decode("utf-8", "surrogateescape")
                cmds, error = parse_request(text)
                if any(name in COMMANDS for name, _ in cmds):
                    self._promote(c)  # one valid command admits (before ?WATCH counts)
                elif cmds or error is not None:
                    c.suspect = not c.session
                for name, arg in cmds:
                    for line in self._answer(c, name, arg):
                        c.reply(line)
                if error is not None:  # after the answers to what came before it
                    c.reply(dumps({"class": "ERROR", "message": str(error)}))
                if len(c.replies) > MAX_PENDING_REPLIES:
                    # read on once the sender has written them out (an eviction or a
                    # failed write also sets drained): memory stays bounded, and a reading
                    # client gets every answer
                    c.drained.clear()
                    c.wake.set()
                    await c.drained.wait()
        except (ConnectionError, OSError):
            pass
        except asyncio.CancelledError:
            pass  # close() or eviction: a finished task keeps asyncio's stream callback quiet
        finally:
            await self._hang_up(c, reader)

    async def _refuse(self, c: _Client, reader: asyncio.StreamReader, raw: bytes) -> None:
        """Refuse a request too long: one short error (its start echoed), sent before the
        end of the stream; what the client still sends is read and dropped (at most
        :data:`REFUSED_LINGER_S`, :data:`REFUSED_DISCARD_BYTES`), so that the close that
        follows is not a reset, which could throw the error away before the client reads
        it. A client that does not read gets no such wait."""
        echo = shown(raw.decode("utf-8", "replace").strip())
        message = f"request too long (over {MAX_REQUEST_BYTES} bytes): '{echo}'"
        c.watch_enable = False  # nothing more goes out after the error
        c.events.clear()
        c.reply(dumps({"class": "ERROR", "message": message}))
        c.closed = True  # the sender ends once the error is out
        c.wake.set()
        sender = c.sender
        if sender is None:
            return
        done, _ = await asyncio.wait({sender}, timeout=REFUSED_LINGER_S)
        if not done or write_buffer_size(c.writer.transport) > 0:
            return  # it does not read: the hang-up resets it
        with contextlib.suppress(Exception):
            c.writer.write_eof()
        deadline = self._clock() + REFUSED_LINGER_S
        dropped = 0
        while dropped < REFUSED_DISCARD_BYTES:
            left_s = deadline - self._clock()
            if left_s <= 0:
                break
            try:
                chunk = await asyncio.wait_for(reader.read(65536), left_s)
            except (TimeoutError, ConnectionError, OSError):
                break
            if not chunk:
                break
            dropped += len(chunk)


def read_objects(lines: Iterable[bytes]) -> list[dict[str, Any]]:
    """Decode gpsd JSON lines (for clients and tests); non-JSON lines (NMEA) are skipped."""
    out: list[dict[str, Any]] = []
    for line in lines:
        s = line.strip()
        if s.startswith(b"{"):
            out.append(json.loads(s))
    return out
