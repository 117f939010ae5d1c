"""``x6wd client``: the operator's command line for the remote-control protocol.

``x6wd client [--host H] [--port P] [--token-file F] [--tls [--cafile F]] COMMAND``
with COMMAND one of ``status``, ``load FILE | load --wp LAT,LON ...`` (FILE: ``.waypoints``,
``.plan``, ``.gpx``, ``.csv`` or ``.kml``), ``start``, ``pause``, ``resume``, ``return``, ``stop``,
``drive LEFT RIGHT SECONDS``, ``watch``, ``log [N]``.

``status`` prints a summary for a person, ``--json`` (before or after the action) the reply
as JSON, for programs; ``watch --json`` one JSON object per line. ``stop`` is sent before any
``auth`` and ``status`` falls back to asking without the token: for these two, which the robot
obeys unauthenticated, a wrong or unusable token is a warning on stderr, not a failure.
A ``stop`` whose TLS verification fails (the robot's certificate expired, say) is sent once
more over TLS without verification, with a loud warning: never the token, nor any other
command.
Every heading shown is true, in degrees, 0 <= h < 360 (docs/protocol.md, "Headings").

Exit codes: 0 success, 1 the robot refused (error reply), 2 bad input, 3 connection failed
(also when the robot closed the connection: pool full, auth deadline, too many failed tokens,
its daemon shutting down), 4 a ``stop`` sent without verification and acknowledged: the
acknowledgement may not be the robot's.
A reader of the output that goes away (``x6wd client watch | head``) ends it quietly, 0.
"""

from __future__ import annotations

import argparse
import contextlib
import itertools
import json
import math
import os
import re
import socket
import ssl
import sys
import time
from collections import deque
from collections.abc import Callable
from typing import Any, NoReturn, TextIO

from x6wd.app.server import load_token
from x6wd.core.errors import ConfigError, ParseError, ProtocolError, X6wdError
from x6wd.core.mission_files import PARSERS, Waypoint, load_file, parse_args

EXIT_OK = 0
EXIT_REFUSED = 1
EXIT_USAGE = 2
EXIT_CONNECTION = 3
EXIT_UNVERIFIED = 4  # a stop sent unverified was acknowledged, by whoever answered
EXIT_INTERRUPTED = 130  # Ctrl-C during a drive: the robot was told to stop
DEFAULT_PORT = 7601
MAX_REPLY_BYTES = 16 * 1024 * 1024
DEFAULT_MAX_LINE_BYTES = 65536
"""The daemon's default ``[server] max_line_bytes``: the longest request line it reads."""
CLEAR = "\x1b[H\x1b[2J"
MISSION_EXTENSIONS = ", ".join(f".{k}" for k in PARSERS)


class ConnectionFailed(X6wdError):
    """The server could not be reached, or the connection broke."""


class HandshakeFailed(ConnectionFailed):
    """The TLS handshake failed for another reason than the certificate (the port does not
    speak TLS: OpenSSL's WRONG_VERSION_NUMBER, a reset)."""


class ClosedWithoutReply(ConnectionFailed):
    """The robot closed the connection without a word: what its TLS port does to plain
    text."""


class CertificateNotVerified(ConnectionFailed):
    """The TLS handshake failed because the robot's certificate could not be verified
    (expired, not yet valid, another name, not trusted); ``why`` is OpenSSL's reason."""

    def __init__(self, message: str, why: str, code: int = 0) -> None:
        super().__init__(message)
        self.why = why
        self.code = code  # OpenSSL's verify code (0: not known)


# OpenSSL's X509_V_ERR_* codes (x509_vfy.h) of the causes an operator fixes differently
_CERT_NOT_YET_VALID, _CERT_HAS_EXPIRED = 9, 10
_HOSTNAME_MISMATCH, _IP_ADDRESS_MISMATCH = 62, 64


def certificate_hint(exc: CertificateNotVerified, host: str) -> str:
    """What fixes a failed verification, by its cause: the name the client connected to
    missing from the certificate, its dates, or a certificate ``--cafile`` does not trust
    (docs/install.md, section 2)."""
    if exc.code in (_HOSTNAME_MISMATCH, _IP_ADDRESS_MISMATCH) or "mismatch" in exc.why:
        return (
            f"the certificate must name this --host ({host}) in its subjectAltName: connect "
            "with a name or address it lists, or make the robot's certificate with it "
            "(docs/install.md, section 2)"
        )
    if exc.code == _CERT_HAS_EXPIRED or "expired" in exc.why:
        return "renew the robot's certificate (docs/install.md, section 2)"
    if exc.code == _CERT_NOT_YET_VALID or "not yet valid" in exc.why:
        return (
            "check the clock of this computer and the one the certificate was made with "
            "(docs/install.md, section 2)"
        )
    return (
        "give the robot's own certificate with --cafile (copy its cert.pem: docs/install.md, "
        "section 4); one made again on the robot must be copied again"
    )


class RequestFailed(X6wdError):
    """The server answered a request with an error reply; ``reason`` refines ``code`` when
    the server gave one (e.g. ``bad_request`` / ``bad_json``), else ``""``."""

    def __init__(self, code: str, message: str, reason: str = "") -> None:
        super().__init__(f"{code}: {message}")
        self.code = code
        self.message = message
        self.reason = reason


CLOSED = "closed"
"""Error code of the server's last line before it closes a connection (id null)."""
SHUTDOWN = "shutdown"
"""That line's reason when the daemon itself shuts down (it stops the motors first)."""


class RemoteClient:
    """A blocking protocol client (one request at a time; events kept while waiting).

    ``timeout_s`` bounds connecting and waiting for each reply. With a ``token`` it
    authenticates first thing after connecting: the server closes connections that have not
    authenticated within its ``auth_timeout_s``, and admits them to a session only then.
    """

    def __init__(
        self,
        host: str = "127.0.0.1",
        port: int = DEFAULT_PORT,
        *,
        token: str | None = None,
        ssl_context: ssl.SSLContext | None = None,
        timeout_s: float = 5.0,
    ) -> None:
        self.host, self.port = host, port
        self.timeout_s = timeout_s
        self.events: deque[dict[str, Any]] = deque(maxlen=10_000)
        self._ids = itertools.count(1)
        self._buf = b""
        try:
            sock = socket.create_connection((host, port), timeout=timeout_s)
        except OSError as exc:
            raise ConnectionFailed(f"cannot connect to {host}:{port}: {_why(exc)}") from None
        try:
            if ssl_context is not None:
                sock = ssl_context.wrap_socket(sock, server_hostname=host)
        except ssl.SSLCertVerificationError as exc:
            sock.close()
            why = exc.verify_message or str(exc)
            raise CertificateNotVerified(
                f"TLS handshake with {host}:{port} failed: {exc}", why, exc.verify_code or 0
            ) from None
        except TimeoutError:
            sock.close()  # a port that stalls the handshake: no sign it does not speak TLS
            raise ConnectionFailed(
                f"TLS handshake with {host}:{port} timed out after {timeout_s:g} s"
            ) from None
        except (OSError, ssl.SSLError) as exc:
            sock.close()
            raise HandshakeFailed(f"TLS handshake with {host}:{port} failed: {exc}") from None
        self._sock: socket.socket | None = sock
        self._tls = ssl_context is not None
        self.unverified_fallback = False  # a stop sent without verification (_connect)
        self.unverified_why = ""  # why the certificate was not verified (OpenSSL's reason)
        self.fallback_from: ConnectionFailed | None = None  # what a fallback stop follows
        if token is not None:
            try:
                self.authenticate(token)
            except BaseException:
                self.close()
                raise

    def authenticate(self, token: str) -> None:
        """Send ``auth``; RequestFailed when the robot refuses the token."""
        self.request("auth", token=token)

    def close(self) -> None:
        """Close the connection (idempotent)."""
        if self._sock is not None:
            self._sock.close()
            self._sock = None

    def __enter__(self) -> RemoteClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _readline(self, timeout_s: float | None) -> bytes:
        if self._sock is None:
            raise ConnectionFailed("connection closed")
        # one deadline for the whole line: a peer dripping bytes without a newline must not
        # restart the wait with each of them
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        while b"\n" not in self._buf:
            if deadline is not None:
                timeout_s = deadline - time.monotonic()
                if timeout_s <= 0:
                    raise TimeoutError
            self._sock.settimeout(timeout_s)
            try:
                chunk = self._sock.recv(65536)
            except TimeoutError:
                raise
            except OSError as exc:
                raise ConnectionFailed(
                    f"connection to {self.host}:{self.port}: {_why(exc)}"
                ) from None
            if not chunk:
                # the daemon's TLS server closes a plain-text connection without a word
                hint = "" if self._tls else " (if the daemon uses TLS, add --tls)"
                raise ClosedWithoutReply(f"{self.host}:{self.port} closed the connection{hint}")
            self._buf += chunk
            if len(self._buf) > MAX_REPLY_BYTES:
                raise ProtocolError("server line longer than 16 MiB")
        line, _, self._buf = self._buf.partition(b"\n")
        return line

    def read_message(self, timeout_s: float | None = None) -> dict[str, Any]:
        """The next line from the server as a dict (raises TimeoutError after ``timeout_s``)."""
        line = self._readline(timeout_s)
        try:
            msg = json.loads(line)
        except (ValueError, RecursionError) as exc:  # bad UTF-8 and digit limits are too
            shown = line[:40].decode("utf-8", "replace")
            raise ProtocolError(
                f"{self.host}:{self.port} does not answer in the x6wd control protocol (it"
                f" sent {shown!r}: {exc}); the control port is [server] port, 7601"
            ) from None
        if not isinstance(msg, dict):
            raise ProtocolError("server sent a non-object line")
        return msg

    def request(self, cmd: str, **args: Any) -> dict[str, Any]:
        """Send one request and return its reply (events arriving meanwhile are kept).

        Raises RequestFailed for an error reply, ConnectionFailed for a broken connection.
        """
        if self._sock is None:
            raise ConnectionFailed("connection closed")
        req_id = next(self._ids)
        data = request_line(req_id, cmd, **args)
        try:
            self._sock.sendall(data)
        except OSError as exc:
            raise ConnectionFailed(f"sending to {self.host}:{self.port}: {_why(exc)}") from None
        deadline = time.monotonic() + self.timeout_s
        while True:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise ConnectionFailed(f"no reply to {cmd!r} within {self.timeout_s:g} s")
            try:
                msg = self.read_message(remaining)
            except TimeoutError:
                raise ConnectionFailed(f"no reply to {cmd!r} within {self.timeout_s:g} s") from None
            if "event" in msg:
                self.events.append(msg)
                continue
            if "class" in msg and "ok" not in msg:
                # gpsd's JSON ({"class":"VERSION",...}): the telemetry port, not this one
                raise ProtocolError(
                    f"{self.host}:{self.port} answered as gpsd does (class"
                    f" {str(msg['class'])[:20]!r}): that is the gpsd-compatible port; the"
                    f" control port is [server] port (default {DEFAULT_PORT})"
                )
            if msg.get("id") != req_id:
                if msg.get("ok") is False and msg.get("id") is None:
                    self._raise(msg)  # an unparsable line of ours, or the server closing
                continue
            if msg.get("ok") is True:
                return msg
            self._raise(msg)

    def _raise(self, msg: dict[str, Any]) -> NoReturn:
        err = msg.get("error")
        if not isinstance(err, dict):
            err = {}
        code = str(err.get("code", "error"))
        message = str(err.get("message", ""))
        reason = str(err.get("reason") or "")
        if code == CLOSED and msg.get("id") is None:
            self.close()
            if reason == SHUTDOWN:
                raise ConnectionFailed(
                    f"the robot's daemon shut down ({self.host}:{self.port}: {message})"
                )
            raise ConnectionFailed(
                f"{self.host}:{self.port} closed the connection ({reason or 'closed'}): {message}"
            )
        raise RequestFailed(code, message, reason)

    def next_event(self, timeout_s: float | None = None) -> dict[str, Any]:
        """The next ``{"event": ..}`` message (kept ones first); ``timeout_s`` in seconds.
        Raises ConnectionFailed (with the server's reason) if the server closes."""
        if self.events:
            return self.events.popleft()
        while True:
            msg = self.read_message(timeout_s)
            if "event" in msg:
                return msg
            if msg.get("ok") is False and msg.get("id") is None:
                self._raise(msg)  # e.g. the server closing the connection, and why


def request_line(req_id: int, cmd: str, **args: Any) -> bytes:
    """One request as it goes on the wire: compact JSON, ASCII, LF-terminated."""
    return (json.dumps({"id": req_id, "cmd": cmd, **args}, separators=(",", ":")) + "\n").encode()


def mission_request(waypoints: list[Waypoint], max_line_bytes: int) -> list[list[float]]:
    """The ``mission.load`` pairs of ``waypoints``; ParseError, before anything is sent, when
    the request would be longer than the robot reads (``max_line_bytes``, its ``[server]
    max_line_bytes``): it would refuse it as ``line_too_long``, naming no waypoint count."""
    pairs = [[w.lat_deg, w.lon_deg] for w in waypoints]
    # the id is the connection's first or second request: 99 is a digit to spare
    size = len(request_line(99, "mission.load", waypoints=pairs)) - 1  # the LF is no part
    if size <= max_line_bytes:
        return pairs
    raise ParseError(too_long_text(len(pairs), size, max_line_bytes))


def too_long_text(count: int, size: int, max_line_bytes: int) -> str:
    """Why a mission of ``count`` waypoints (a request of ``size`` bytes) cannot be loaded
    in one request of at most ``max_line_bytes``, and what to do."""
    fit = max(1, int(count * (max_line_bytes - 64) / size))  # about, for points like these
    every = -(-count // fit)
    return (
        f"the mission has {count} waypoints: loading it is a request of {size} bytes, and"
        f" the robot reads requests of at most {max_line_bytes} bytes ([server]"
        f" max_line_bytes), about {fit} waypoints like these. Load fewer: thin the track"
        f" (e.g. keep one point in {every}) or split it into missions of up to {fit}"
        f" waypoints; or raise the robot's [server] max_line_bytes (up to 16 MiB) and give"
        f" the same value here with --max-line-bytes"
    )


def _why(exc: OSError) -> str:
    return exc.strerror or str(exc) or type(exc).__name__


def _fmt(v: Any, spec: str, unit: str = "") -> str:
    if v is None:
        return "-"
    try:
        return f"{v:{spec}}{unit}"
    except (TypeError, ValueError):
        return str(v)


def fmt_heading(v: Any, north: str = "true") -> str:
    """A heading or bearing as every view shows it: true (from geographic north), degrees
    clockwise, 0 <= h < 360, one decimal ("-" when unknown). ``north="magnetic"``: the
    compass heading while no declination is known (see :func:`heading_north`)."""
    if not isinstance(v, (int, float)) or not math.isfinite(v):
        return "-"
    return f"{round(float(v), 1) % 360.0:.1f} deg {north}"


def heading_north(decl: Any) -> str:
    """Which north the robot's heading is from, by ``status``'s ``declination``: "magnetic"
    while the World Magnetic Model's value is pending (no dated fix yet) or failed (0 is
    used), else "true" (also when the reply has no ``declination``)."""
    if isinstance(decl, dict) and ("pending" in decl or "error" in decl):
        return "magnetic"
    return "true"


def _returning_text(why: str) -> str:
    """Why the robot returns to launch, for a person: telemetry ``extra.returning`` is
    ``return`` (the operator's command) or ``failsafe: CONDITION``."""
    return "the operator's command" if why == "return" else why


def _telemetry_lines(tel: dict[str, Any], north: str = "true") -> list[str]:
    """The lines of a telemetry snapshot that the watch and status views share. A return to
    launch (``extra.returning``) is said, with its cause, and its target is the launch point,
    not the mission's waypoint 1/1; the last failsafe that acted (``extra.failsafe``) too.
    ``north``: the heading's (:func:`heading_north`); bearings are always true."""
    extra = tel.get("extra")
    if not isinstance(extra, dict):
        extra = {}
    returning = str(extra.get("returning") or "")
    failsafe = str(extra.get("failsafe") or "")
    wp_i, wp_n = tel.get("waypoint_index"), tel.get("waypoint_count", 0)
    wp = f"{wp_i + 1}/{wp_n}" if isinstance(wp_i, int) else "-"
    if returning:
        wp = "launch point"  # the return's one target, not the mission's waypoint 1/1
    hold = tel.get("hold_reason") or ""
    head = f"state      {tel.get('mode', '?')} / {tel.get('state', '?')}"
    if returning:
        head += f"  RETURN TO LAUNCH ({_returning_text(returning)})"
    if hold:
        head += f"  HOLD: {hold}"
    paused_by = str(extra.get("paused_by") or "")
    if paused_by:
        head += f"  (paused by {'the operator' if paused_by == 'operator' else paused_by})"
    lines = [head]
    if failsafe and f"failsafe: {failsafe}" != returning:
        lines.append(f"failsafe   {failsafe} (the last one that acted)")
    return [
        *lines,
        f"position   {_fmt(tel.get('lat_deg'), '.7f')} {_fmt(tel.get('lon_deg'), '.7f')}",
        f"filtered   {_fmt(tel.get('filt_lat_deg'), '.7f')} {_fmt(tel.get('filt_lon_deg'), '.7f')}",
        f"heading    {fmt_heading(tel.get('heading_deg'), north)}",
        f"pitch/roll {_fmt(tel.get('pitch_deg'), '.0f', ' deg')} / "
        f"{_fmt(tel.get('roll_deg'), '.0f', ' deg')}",
        f"waypoint   {wp}  distance {_fmt(tel.get('distance_m'), '.1f', ' m')}  "
        f"bearing {fmt_heading(tel.get('target_bearing_deg'))}  "
        f"deviation {_fmt(tel.get('theta_deg'), '.1f', ' deg')}",
        f"fix        quality {tel.get('fix_quality', 0)}  sats {_fmt(tel.get('sats_used'), 'd')}"
        f"  hdop {_fmt(tel.get('hdop'), '.2f')}  age {_fmt(tel.get('fix_age_s'), '.1f', ' s')}",
        f"compass    age {_fmt(tel.get('attitude_age_s'), '.2f', ' s')}",
        f"motors     L {_fmt(tel.get('left_pct'), '+.0f', '%')}  "
        f"R {_fmt(tel.get('right_pct'), '+.0f', '%')}",
    ]


def _links_line(links: dict[str, Any]) -> str:
    return "links      " + (
        "  ".join(f"{k} {v}" for k, v in links.items() if "_" not in k) if links else "-"
    )


def render_watch(tel: dict[str, Any], info: dict[str, Any] | None = None) -> str:
    """One screen of the live view from a telemetry dict (``Telemetry.to_dict()`` shape)."""
    info = info or {}
    lines = [
        "x6wd watch  (Ctrl-C to quit)",
        "",
        *_telemetry_lines(tel, heading_north(info.get("declination"))),
        _links_line(info.get("links", {})),
    ]
    if info.get("dropped"):
        lines.append(f"dropped    {info['dropped']} telemetry events (slow link)")
    return "\n".join(lines) + "\n"


def _duration(s: Any) -> str:
    if not isinstance(s, (int, float)) or not math.isfinite(s):
        return "-"
    m, sec = divmod(int(s), 60)
    h, m = divmod(m, 60)
    return f"{h}h{m:02d}m{sec:02d}s" if h else f"{m}m{sec:02d}s" if m else f"{s:.1f} s"


SETUP_OK_STATES = ("acked", "waiting", "not sent")
"""``gps_receiver.setup.state`` values that are no problem of the receiver's (status prints
the others with their reason; "not sent": no port yet, which the gps device's line says)."""


def gps_receiver_lines(g: Any) -> list[str]:
    """``status``'s ``gps_receiver`` for a person (docs/gps.md, "Status"): one brief line
    (the fix rate against the expected one, the line's baud and load, the setup's state),
    then each problem on its own line: ``slow``, ``line_full``, ``setup.line_short``, and a
    setup that is not acked (its ``problem``, ``lost``, ``not_kept``). No lines for a
    ``gps_receiver`` that is not a dict (null before the GPS reader exists)."""
    if not isinstance(g, dict):
        return []
    brief = (
        f"gps rx     fixes {_fmt(g.get('measured_rate_hz'), 'g', ' Hz')} "
        f"(expected {_fmt(g.get('expected_rate_hz'), 'g', ' Hz')})"
    )
    line = g.get("line")
    if isinstance(line, dict):
        brief += f"  line {line.get('baud', '?')} baud {_fmt(line.get('bytes_per_s'), 'd', ' B/s')}"
        if line.get("paced") is False:
            brief += " (not paced by its baud)"
        elif isinstance(line.get("load"), (int, float)):
            brief += f" {line['load']:.0%} full"
    setup = g.get("setup")
    if isinstance(setup, dict):
        brief += f"  setup {setup.get('state', '?')}"
    lines = [brief]
    for label, text in (("SLOW", g.get("slow")), ("LINE FULL", g.get("line_full"))):
        if text:
            lines.append(f"  gps rx   {label}: {text}")
    if isinstance(setup, dict):
        if setup.get("line_short"):
            lines.append(f"  gps rx   LINE SHORT: {setup['line_short']}")
        state = setup.get("state")
        if state not in SETUP_OK_STATES:
            why = setup.get("not_kept") or setup.get("problem") or setup.get("lost") or ""
            lines.append(f"  gps rx   setup {state}" + (f": {why}" if why else ""))
    return lines


def render_status(st: dict[str, Any]) -> str:
    """The ``status`` reply for a person (``--json`` prints the reply itself)."""
    head = f"x6wd {st.get('version', '?')}  up {_duration(st.get('uptime_s'))}"
    lines = [head]
    tel = st.get("telemetry")
    if isinstance(tel, dict):
        lines += _telemetry_lines(tel, heading_north(st.get("declination")))
    else:
        lines.append(
            f"state      {st.get('mode', '?')} / {st.get('state', '?')}  (no telemetry yet)"
        )
    decl = st.get("declination")
    if isinstance(decl, dict) and decl:
        if "pending" in decl:  # the WMM's value waits for a dated fix: 0 meanwhile
            text = (
                f"{_fmt(decl.get('deg', 0.0), '+.2f', ' deg')} ({decl.get('source', '?')}: "
                f"{decl['pending']})"
            )
        elif "deg" in decl:
            text = f"{_fmt(decl['deg'], '+.2f', ' deg')} ({decl.get('source', '?')})"
        elif "error" in decl:
            text = f"unknown ({decl.get('source', '?')}: {decl['error']}), heading is magnetic"
        else:
            text = str(decl.get("source", "-"))
        lines.append(f"declination {text}")
    roll = st.get("gps_week_rollover")
    if isinstance(roll, dict) and roll.get("corrected"):
        lines.append(
            f"gps date   receiver week rollover: {roll.get('receiver_utc')} read as "
            f"{roll.get('corrected_utc')} (+{roll.get('weeks_added')} weeks; "
            f"{roll.get('corrected')} records; receiver firmware older than the rollover)"
        )
    lines += gps_receiver_lines(st.get("gps_receiver"))
    drive = st.get("manual_drive")
    if isinstance(drive, dict):  # who steers: another client's drive is refused meanwhile
        whose = "this connection" if drive.get("yours") else drive.get("owner", "?")
        lines.append(f"driving    by {whose}, {_fmt(drive.get('holds_s'), '.1f', ' s')} more")
    lines.append(_links_line(st.get("links", {})))
    devices = st.get("devices")
    if isinstance(devices, dict):
        for name, dev in devices.items():
            if not isinstance(dev, dict):
                continue
            problem = dev.get("reason") or dev.get("last_error") or ""
            state = dev.get("state", "?")
            if problem and state not in ("connected", "polling"):
                lines.append(f"  {name:<9}{state}: {problem}")
            corrupt = dev.get("corrupt")
            if isinstance(corrupt, dict) and any(corrupt.values()):  # counted and skipped
                counts = ", ".join(f"{n} {k.replace('_', ' ')}" for k, n in corrupt.items() if n)
                lines.append(f"  {name:<9}corrupt input since start: {counts}")
    rec = st.get("recorder")
    if isinstance(rec, dict) and rec.get("state") not in (None, "ok"):
        # recording is how a run is looked at afterwards: say what is lost and why
        why = rec.get("last_error") or "?"
        if rec.get("state") == "stalled":  # a write that has not returned: no error yet
            why = (
                f"a write has taken {rec.get('busy_s', 0):.0f} s;"
                f" {rec.get('queued', 0)} records waiting"
            )
        dropped = rec.get("records_dropped", 0)
        lines.append(f"  recorder {rec.get('state')}: {why} ({dropped} records not recorded)")
    server = st.get("server")
    if isinstance(server, dict):
        lines.append(
            f"server     {server.get('clients', 0)} clients, {server.get('pending', 0)} pending,"
            f" {server.get('dropped', 0)} events dropped"
        )
        tls = server.get("tls")
        if isinstance(tls, dict) and tls.get("warning"):  # renew before clients refuse it
            lines.append(f"tls cert   WARNING {tls['warning']}")
    return "\n".join(lines) + "\n"


def _client_ssl(args: argparse.Namespace) -> ssl.SSLContext | None:
    """The TLS context (``--cafile`` and ``--insecure`` imply ``--tls``: an --insecure alone
    sent the token in plain text). Raises ConfigError for a CA file that cannot be used."""
    if args.cafile == "":  # not "no --cafile": that would send the token in clear text
        raise ConfigError("--cafile: empty path (give the robot's certificate file)")
    if not args.tls and not args.cafile and not args.insecure:
        return None
    try:
        ctx = ssl.create_default_context(cafile=args.cafile or None)
    except (OSError, ssl.SSLError) as exc:
        raise ConfigError(
            f"--cafile {args.cafile}: {getattr(exc, 'strerror', None) or exc}"
        ) from None
    if args.insecure:
        ctx.check_hostname = False
        ctx.verify_mode = ssl.CERT_NONE
    return ctx


def _unverified_ssl() -> ssl.SSLContext:
    """TLS without certificate verification: only for a ``stop`` whose verification failed."""
    ctx = ssl.create_default_context()
    ctx.check_hostname = False
    ctx.verify_mode = ssl.CERT_NONE
    return ctx


def _token(path: str) -> str:
    """The token of ``--token-file`` (the daemon's rules: mode 600, 8 bytes or more), as
    text: it travels in a JSON string."""
    try:
        raw = load_token(path)
    except ConfigError as exc:
        raise ConfigError(str(exc).replace("server.token_file", "--token-file", 1)) from None
    try:
        return raw.decode()
    except UnicodeDecodeError:
        raise ConfigError(
            f"--token-file: {path} is not UTF-8 text (make a token with e.g. "
            "`openssl rand -base64 32`)"
        ) from None


def _int_in(lo: int, hi: int | None = None) -> Callable[[str], int]:
    """An argparse type: an integer from ``lo`` to ``hi`` (no upper limit when None)."""

    def parse(text: str) -> int:
        try:
            v = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"not an integer: {text!r}") from None
        if v < lo or (hi is not None and v > hi):
            want = f"{lo}..{hi}" if hi is not None else f">= {lo}"
            raise argparse.ArgumentTypeError(f"must be {want}, got {v}")
        return v

    return parse


def _finite(text: str) -> float:
    """An argparse type: a finite number (NaN, inf and 1e309 are bad input, found here and
    never sent: the robot would refuse them, and exit 1 means "the robot refused")."""
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not math.isfinite(v):
        raise argparse.ArgumentTypeError(f"must be a finite number, got {text}")
    return v


DRIVE_PCT_MAX = 100.0  # the protocol's bound on a side's command (%), either way
DRIVE_S_MAX = 3600.0  # the protocol's longest drive (s)
LOG_TAIL_MAX = 1000  # the most log lines the daemon sends (server.LOG_TAIL_MAX)


def _drive_pct(text: str) -> float:
    """An argparse type: a side's command, -100..100 % (outside it is bad input, found here
    and never sent, as for NaN: exit 2, not the robot's refusal, exit 1)."""
    v = _finite(text)
    if abs(v) > DRIVE_PCT_MAX:
        raise argparse.ArgumentTypeError(f"must be within -100..100 %, got {text}")
    return v


def _timeout_s(text: str) -> float:
    """An argparse type: a reply timeout, seconds > 0 (no upper bound: not a drive)."""
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not (math.isfinite(v) and v > 0):
        raise argparse.ArgumentTypeError(f"must be a finite number of seconds > 0, got {text}")
    return v


def _positive_s(text: str) -> float:
    """An argparse type: a drive's duration, seconds > 0 and at most the protocol's."""
    v = _timeout_s(text)
    if v > DRIVE_S_MAX:
        raise argparse.ArgumentTypeError(
            f"must be a finite number of seconds, > 0 and at most {DRIVE_S_MAX:g}, got {text}"
        )
    return v


def _waypoints(args: argparse.Namespace) -> list[Waypoint]:
    if args.file and args.wp:
        raise ParseError("give a FILE or --wp, not both")
    if args.file:
        return load_file(args.file, args.format)
    if args.wp:
        return parse_args(args.wp)
    raise ParseError(f"load needs a FILE ({MISSION_EXTENSIONS}) or --wp LAT,LON ...")


def _limit_in(message: str) -> int | None:
    """The byte limit in the robot's ``line_too_long`` message ("request line longer than
    65536 bytes"), or None."""
    m = re.search(r"longer than (\d+) bytes", message)
    return int(m.group(1)) if m else None


def _body(reply: dict[str, Any]) -> dict[str, Any]:
    """A reply without its ``id`` and ``ok``."""
    return {k: v for k, v in reply.items() if k not in ("id", "ok")}


def _print_reply(reply: dict[str, Any], out: TextIO) -> None:
    print(json.dumps(_body(reply), indent=2, sort_keys=True), file=out)


def _json_line(obj: dict[str, Any], out: TextIO) -> None:
    """One compact JSON object on one line (``watch --json``)."""
    out.write(json.dumps(obj, separators=(",", ":")) + "\n")
    out.flush()


HOLD_POLL_S = 0.5
"""While a drive runs, ``x6wd client drive`` asks ``status`` this often (s): a robot that
stopped early (another operator's stop, a fault) or a server gone is reported, not taken
for a drive that ran its course."""
HOLD_END_GRACE_S = 0.3
"""The last part of a drive (s) in which a robot no longer in MANUAL is its normal end."""


def _hold_drive(client: RemoteClient, reply: dict[str, Any], err: TextIO) -> int | None:
    """Keep the connection open while the drive the robot granted runs: the robot stops a
    drive whose client went away, so leaving early would cut it short. Returns None when
    the drive ran its course; :data:`EXIT_REFUSED` when the robot left manual drive early
    (said on ``err``); :data:`EXIT_INTERRUPTED` on Ctrl-C, after a ``stop`` the robot
    acknowledged (the connection's close alone would stop it too); a stop the robot refused
    or did not answer is said as such, never "stop sent", and is :data:`EXIT_REFUSED` or
    :data:`EXIT_CONNECTION`. A connection lost meanwhile raises :class:`ConnectionFailed`."""
    try:
        duration_s = reply.get("duration_s")
        if not isinstance(duration_s, (int, float)) or not 0.0 < duration_s <= 3600.0:
            raise ProtocolError(f"'drive' reply without a usable duration_s: {duration_s!r:.60}")
        end = time.monotonic() + float(duration_s)
        while (left_s := end - time.monotonic()) > 0.0:
            time.sleep(min(HOLD_POLL_S, left_s))
            st = client.request("status")
            mode = st.get("mode")
            # (a robot too old to say who drives says no manual_drive: MANUAL is then ours)
            drive = st.get("manual_drive", {"yours": True})
            ours = isinstance(drive, dict) and drive.get("yours") is True
            if (mode != "MANUAL" or not ours) and end - time.monotonic() > HOLD_END_GRACE_S:
                _closing_notice(client, SHUTDOWN_NOTICE_WAIT_S)  # raises if the daemon went
                if mode == "MANUAL" and isinstance(drive, dict) and drive.get("owner"):
                    # stopped, then driven by another client: its drive, not this one
                    now = f"driven by another client ({drive['owner']})"
                else:
                    now = str(mode)
                print(f"x6wd client: the drive ended early: the robot is {now}", file=err)
                return EXIT_REFUSED
    except KeyboardInterrupt:
        return _interrupted_stop(client, err)
    return None


SHUTDOWN_NOTICE_WAIT_S = 0.5
"""How long a drive that ended early waits for the daemon's closing notice (s): a daemon
shutting down stops the motors and shows IDLE to a ``status`` a moment before it says
goodbye, and that is "the daemon shut down" (exit 3), not "the drive ended early"."""


def _closing_notice(client: RemoteClient, wait_s: float) -> None:
    """Raise :class:`ConnectionFailed` (with the server's reason) when the connection closes
    within ``wait_s`` (s); an event that arrives meanwhile is kept, nothing else is waited
    for."""
    deadline = time.monotonic() + wait_s
    while (left_s := deadline - time.monotonic()) > 0.0:
        try:
            msg = client.read_message(left_s)
        except TimeoutError:
            return
        if "event" in msg:
            client.events.append(msg)
        elif msg.get("ok") is False and msg.get("id") is None:
            client._raise(msg)  # the server closing the connection, and why


def _interrupted_stop(client: RemoteClient, err: TextIO) -> int:
    """Ctrl-C during a drive: ``stop``, and say truthfully whether the robot confirmed it."""
    try:
        client.request("stop")
    except (X6wdError, OSError) as exc:
        refused = isinstance(exc, RequestFailed)
        print(
            f"x6wd client: drive interrupted: the robot did not confirm the stop ({exc});"
            " closing the connection, which stops a drive the robot still runs; check with"
            " `x6wd client status`",
            file=err,
        )
        return EXIT_REFUSED if refused else EXIT_CONNECTION
    print("x6wd client: drive interrupted: stop sent (the robot confirmed it)", file=err)
    return EXIT_INTERRUPTED


def _watch(
    client: RemoteClient, args: argparse.Namespace, out: TextIO, ansi: bool, err: TextIO
) -> None:
    """The live view: one screen per telemetry event (at most ~10 per second); with
    ``--json`` one JSON object per line instead, no screen codes: every event as the robot
    sent it (``{"event": ..}``) and each status the view asks for (at the start, then every
    2 s) as ``{"status": REPLY}``; ``--count`` counts telemetry events then."""
    as_json = bool(args.json)
    info = client.request("status")
    if as_json:
        _json_line({"status": _body(info)}, out)
    client.request("watch", on=True)
    shown = 0
    t_last_status = time.monotonic()
    t_last_draw = 0.0
    while args.count is None or shown < args.count:
        try:
            ev = client.next_event(timeout_s=5.0)
        except TimeoutError:
            if as_json:  # not an object of the stream: for the person, on stderr
                print("x6wd client: no telemetry for 5 s", file=err)
            else:
                out.write((CLEAR if ansi else "") + "no telemetry for 5 s\n")
                out.flush()
            continue
        if ev.get("event") != "telemetry":
            if as_json:
                _json_line(ev, out)
            continue
        now = time.monotonic()
        if now - t_last_status > 2.0:
            client.request("watch", on=True)  # keep-alive; also refreshes link state below
            info = client.request("status")
            t_last_status = now
            if as_json:
                _json_line({"status": _body(info)}, out)
        if as_json:
            _json_line(ev, out)
            shown += 1
            continue
        if args.count is None and now - t_last_draw < 0.1:
            continue  # at most ~10 redraws per second
        t_last_draw = now
        screen = render_watch(
            ev.get("data", {}), {**info, "dropped": info.get("client", {}).get("dropped")}
        )
        out.write((CLEAR if ansi else "") + screen)
        out.flush()
        shown += 1


NEGATIVE_VALUE = re.compile(r"^-\.?\d")
"""An argument that starts like a negative number ("-33.8,151.2", "-1e1", "-.5"): a value,
never an option (argparse's own rule takes only "-12" and "-1.5" so)."""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of ``x6wd client``."""
    parser.add_argument("--host", default="127.0.0.1", help="robot address (default 127.0.0.1)")
    parser.add_argument(
        "--port", type=_int_in(1, 65535), default=DEFAULT_PORT, help="control port (7601)"
    )
    parser.add_argument("--token-file", help="file holding the shared token (mode 600)")
    parser.add_argument("--tls", action="store_true", help="connect with TLS")
    parser.add_argument("--cafile", help="CA/certificate to trust for TLS (implies --tls)")
    parser.add_argument(
        "--insecure", action="store_true", help="TLS without certificate verification"
    )
    parser.add_argument("--timeout", type=_timeout_s, default=5.0, help="reply timeout in s (5)")
    parser.add_argument("--json", action="store_true", help="print replies as JSON (for programs)")
    sub = parser.add_subparsers(dest="action", metavar="ACTION", required=True)
    sub.add_parser("status", help="show the robot's state")
    p = sub.add_parser(
        "load", help=f"load a mission from a file ({MISSION_EXTENSIONS}) or --wp points"
    )
    p.add_argument("file", nargs="?", help=f"mission file ({MISSION_EXTENSIONS})")
    p.add_argument(
        "--wp", action="append", metavar="LAT,LON", help="a waypoint (repeat): --wp -33.86,151.21"
    )
    p.add_argument(
        "--max-line-bytes",
        type=_int_in(256, 16 * 1024 * 1024),
        default=DEFAULT_MAX_LINE_BYTES,
        metavar="N",
        help=f"the robot's [server] max_line_bytes, the longest request it reads (default "
        f"{DEFAULT_MAX_LINE_BYTES}, the daemon's): a longer mission is refused here, unsent",
    )
    p.add_argument(
        "--format", choices=sorted(PARSERS), help="the file's format (default: its extension)"
    )
    for name, text in (
        ("start", "start the loaded mission"),
        ("pause", "pause the mission (motors stop)"),
        ("resume", "resume a paused mission"),
        ("return", "drive back to the launch point (where the mission started) and end there"),
        ("stop", "stop everything (always allowed)"),
    ):
        sub.add_parser(name, help=text)
    p = sub.add_parser(
        "drive",
        help="manual drive for a limited time; the robot stops when this program ends "
        "(dead-man: Ctrl-C stops it at once)",
    )
    p.add_argument("left", type=_drive_pct, help="left side, -100..100 %%")
    p.add_argument("right", type=_drive_pct, help="right side, -100..100 %%")
    p.add_argument(
        "seconds",
        type=_positive_s,
        help="duration in s (> 0; the robot refuses more than its own limit, [safety] "
        "manual_max_s: 5 s as shipped; at most 3600 here, the protocol's)",
    )
    p = sub.add_parser(
        "watch", help="live one-screen view (--json: one JSON object per line, for programs)"
    )
    p.add_argument(
        "--count",
        type=_int_in(1),
        help="exit after N screens (--json: N telemetry events); default: until Ctrl-C",
    )
    p.add_argument("--no-ansi", action="store_true", help="do not clear the screen")
    p = sub.add_parser("log", help="recent daemon log lines")
    p.add_argument(
        "n",
        type=_int_in(0, LOG_TAIL_MAX),
        nargs="?",
        default=50,
        help=f"how many of the newest lines, 0..{LOG_TAIL_MAX} (default %(default)s)",
    )
    for p in sub.choices.values():  # also after the action: `x6wd client status --json`
        p.add_argument(
            "--json",
            action="store_true",
            default=argparse.SUPPRESS,
            help="print the reply as JSON (for programs)",
        )
    for each in (parser, *sub.choices.values()):
        # argparse takes "-33.8,151.2" (southern latitude) or "-1e1" for an option and says
        # "--wp: expected one argument": every value that starts like a negative number is
        # a value here (no option of the client's starts with a digit)
        each._negative_number_matcher = NEGATIVE_VALUE


def main(args: argparse.Namespace, out: TextIO | None = None) -> int:
    """Run one client action; messages go to stderr, results to ``out`` (stdout).

    When the reader of ``out`` goes away (``x6wd client watch | head``) it stops quietly, as
    Unix filters do, with exit code 0: no traceback, no message."""
    out = out or sys.stdout
    try:
        code = _run(args, out)
        out.flush()
        return code
    except BrokenPipeError:
        _drop_output(out)
        return EXIT_OK


def _drop_output(out: TextIO) -> None:
    """After a broken pipe on ``out``: point its file descriptor at /dev/null, so what is
    still buffered (flushed again at exit) goes nowhere instead of raising once more."""
    try:
        fd = out.fileno()
    except (OSError, ValueError, AttributeError):
        return
    null = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(null, fd)
    finally:
        os.close(null)


TOKEN_OPTIONAL = frozenset({"stop", "status"})
"""Actions the robot obeys without a token (docs/protocol.md): for them a token that is
wrong or cannot be read is a warning, not a failure. ``stop`` must reach the robot."""


def _warn(text: str, err: TextIO) -> None:
    print(f"x6wd client: warning: {text}", file=err)


def _connect(
    args: argparse.Namespace,
    token: str | None,
    ssl_context: ssl.SSLContext | None,
    err: TextIO,
) -> RemoteClient:
    """The connection for ``args.action``. ``stop`` connects without authenticating: it
    goes out first thing, so nothing about the token can delay or prevent it (its token is
    checked after, :func:`_check_token`). ``status`` authenticates (an operator's status
    keeps the operator-link failsafe quiet); if the robot refuses the token it asks on a new
    connection without one (a wrong token's back-off holds up the old one, and the robot
    may close it: ``[server] max_auth_failures``), with a warning. Any other action fails
    as the robot refuses it. A ``stop`` whose TLS verification fails (the robot's
    certificate expired, say) is sent once more without verification, with a warning: it
    carries no token and the robot obeys a stop from anyone, so nothing leaks; nothing else
    is ever sent so (the connection is marked ``unverified_fallback``). So is a ``stop``
    with ``--tls`` to a port that does not speak TLS: sent once more in plain text
    (:func:`_stop_over_tls` is the other way round)."""

    def connect(tok: str | None, ctx: ssl.SSLContext | None = ssl_context) -> RemoteClient:
        return RemoteClient(
            args.host, args.port, token=tok, ssl_context=ctx, timeout_s=args.timeout
        )

    if args.action == "stop":
        try:
            return connect(None)
        except CertificateNotVerified as exc:
            _warn(
                f"THE ROBOT'S TLS CERTIFICATE COULD NOT BE VERIFIED ({exc.why}); retrying the "
                "stop over TLS WITHOUT verification (a stop carries no token; nothing "
                "else is sent so, and the reply cannot be proven to come from the robot). "
                f"To fix it: {certificate_hint(exc, args.host)}",
                err,
            )
            client = connect(None, _unverified_ssl())
            client.unverified_fallback = True
            client.unverified_why = exc.why
            return client
        except HandshakeFailed as exc:
            _warn(
                f"{exc}: the robot's port may not speak TLS; retrying the stop in PLAIN TEXT "
                "(a stop carries no token; nothing else is sent so, and the reply cannot be "
                "proven to come from the robot). Check --tls against the daemon's [server] tls",
                err,
            )
            try:
                client = connect(None, None)
            except ConnectionFailed:
                raise exc from None  # the first failure is the one to tell
            client.unverified_fallback = True
            client.unverified_why = "sent in plain text: the TLS handshake failed"
            client.fallback_from = exc  # told if the plain port closes too
            return client
    if args.action != "status" or token is None:
        return connect(token)
    try:
        return connect(token)
    except RequestFailed as exc:
        why = f"{exc.code}: {exc.message}"
    _warn(f"the robot refused the token of --token-file ({why}); asking without it", err)
    return connect(None)


def _stop_over_tls(
    args: argparse.Namespace, first: ClosedWithoutReply, err: TextIO
) -> RemoteClient:
    """A ``stop`` without ``--tls`` that the robot met by closing the connection without a
    word (its port speaks TLS): a connection over TLS without verification for it alone,
    marked ``unverified_fallback`` (a stop carries no token, so nothing leaks; the reply
    cannot be proven to be the robot's). ``first`` is raised if that fails too."""
    _warn(
        f"{first}; retrying the stop over TLS WITHOUT verification (a stop carries no token;"
        " nothing else is sent so, and the reply cannot be proven to come from the robot)."
        " Give --tls and --cafile to verify the robot",
        err,
    )
    try:
        client = RemoteClient(
            args.host, args.port, ssl_context=_unverified_ssl(), timeout_s=args.timeout
        )
    except ConnectionFailed:
        raise first from None
    client.unverified_fallback = True
    client.unverified_why = "sent over TLS without verification: no --tls given"
    return client


def _check_token(client: RemoteClient, token: str | None, err: TextIO) -> None:
    """After an unauthenticated ``stop``: tell whether the robot accepts the token, so a
    wrong one is found now and not at the next command (only a warning: the stop is done)."""
    if token is None:
        return
    try:
        client.authenticate(token)
    except RequestFailed as exc:
        _warn(
            f"the robot refused the token of --token-file ({exc.code}: {exc.message}); the"
            " stop was sent without it, other commands will be refused",
            err,
        )
    except (ConnectionFailed, ProtocolError) as exc:
        _warn(f"the token of --token-file could not be checked: {exc}", err)


def _run(args: argparse.Namespace, out: TextIO) -> int:
    err = sys.stderr
    action: str = args.action
    try:
        if args.token_file == "":  # an error even for stop/status: a path was meant, not none
            raise ConfigError("--token-file: empty path (give the file holding the token)")
        try:
            token = _token(args.token_file) if args.token_file is not None else None
        except ConfigError as exc:
            if action not in TOKEN_OPTIONAL:
                raise
            token = None  # the robot obeys these without a token: say so, and go on
            _warn(f"{exc}; sending {action} without a token", err)
        waypoints = _waypoints(args) if action == "load" else None
        for note in getattr(waypoints, "notes", ()):  # what the file held but x6wd won't use
            print(f"x6wd client: note: {note}", file=err)
        pairs = mission_request(waypoints, args.max_line_bytes) if waypoints is not None else []
        ssl_context = _client_ssl(args)
    except X6wdError as exc:
        print(f"x6wd client: {exc}", file=err)
        return EXIT_USAGE
    try:
        with contextlib.ExitStack() as stack:
            client = stack.enter_context(_connect(args, token, ssl_context, err))
            if action == "stop":
                try:
                    reply = client.request(action)
                except ClosedWithoutReply as exc:
                    if ssl_context is not None:
                        # the plain retry of a failed handshake closed too: the handshake's
                        # failure is the one to tell (this one would say "add --tls")
                        raise (client.fallback_from or exc) from None
                    client = stack.enter_context(_stop_over_tls(args, exc, err))
                    reply = client.request(action)
                if not client.unverified_fallback:  # the token only to a verified robot
                    _check_token(client, token, err)
            elif action in ("status", "start", "pause", "resume", "return"):
                reply = client.request(action)
            elif action == "load":
                try:
                    reply = client.request("mission.load", waypoints=pairs)
                except RequestFailed as exc:
                    if exc.reason != "line_too_long":
                        raise
                    # the robot reads less than --max-line-bytes: said as a count to load
                    size = len(request_line(99, "mission.load", waypoints=pairs)) - 1
                    limit = _limit_in(exc.message) or args.max_line_bytes
                    why = too_long_text(len(pairs), size, limit)
                    raise RequestFailed(exc.code, f"{exc.message}: {why}", exc.reason) from None
                robot_notes = reply.get("notes")  # the robot's own (a waypoint by the fence)
                for note in robot_notes if isinstance(robot_notes, list) else ():
                    print(f"x6wd client: note: {str(note)[:500]}", file=err)
            elif action == "drive":
                try:  # a Ctrl-C while the robot takes the drive stops it too, said so
                    reply = client.request(
                        "drive", left=args.left, right=args.right, duration_s=args.seconds
                    )
                except KeyboardInterrupt:
                    return _interrupted_stop(client, err)
                held = _hold_drive(client, reply, err)
                if held is not None:
                    return held
            elif action == "log":
                reply = client.request("log", n=args.n)
                if not args.json:
                    lines = reply.get("lines", [])
                    if not isinstance(lines, list):
                        raise ProtocolError(f"'log' reply without a list of lines: {lines!r:.60}")
                    for line in lines:
                        print(line, file=out)
                    return EXIT_OK
            elif action == "watch":
                ansi = not args.no_ansi
                try:
                    _watch(client, args, out, ansi, err)
                except KeyboardInterrupt:
                    return EXIT_OK
                return EXIT_OK
            else:  # pragma: no cover - argparse restricts the choices
                raise ParseError(f"unknown action {action}")
            if client.unverified_fallback:
                # an acknowledgement nobody can prove is the robot's (an impostor on the path
                # answers too): never the exit code, nor the words, of a confirmed stop
                if args.json:
                    _print_reply({**reply, "verified": False}, out)
                else:
                    print(f"stop: sent, reply NOT verified ({client.unverified_why})", file=out)
                return EXIT_UNVERIFIED
            if args.json:
                _print_reply(reply, out)
            elif action == "status":
                out.write(render_status(reply))
            elif action == "stop" and reply.get("motors") == "lost":
                print(
                    "stop: the robot's controller stopped, but its motor link is lost"
                    f" ({str(reply.get('motors_reason') or 'no reason given')[:300]}): the stop"
                    " may not reach the wheels; the board's own watchdog stops them if it runs",
                    file=out,
                )
            else:
                print(f"{action}: ok", file=out)
            if action == "stop" and reply.get("motors") == "lost":
                return EXIT_REFUSED
            return EXIT_OK
    except RequestFailed as exc:
        code = f"{exc.code} ({exc.reason})" if exc.reason else exc.code
        hint = (
            "; give the robot's token with --token-file FILE (docs/install.md, section 4)"
            if exc.code == "unauthorized" and token is None
            else ""
        )
        print(f"x6wd client: {args.action} refused: {code}: {exc.message}{hint}", file=err)
        return EXIT_REFUSED  # whatever the reason: the robot said no (2: found here)
    except CertificateNotVerified as exc:
        print(f"x6wd client: {exc}: {certificate_hint(exc, args.host)}", file=err)
        return EXIT_CONNECTION
    except (ConnectionFailed, ProtocolError) as exc:
        print(f"x6wd client: {exc}", file=err)
        return EXIT_CONNECTION
