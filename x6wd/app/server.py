"""Remote-control protocol server: JSON lines over TCP (optionally TLS). See docs/protocol.md.

One request per line ``{"id": .., "cmd": "..", ...}``, exactly one reply per request
(``{"id": .., "ok": true, ...}`` or ``{"id": .., "ok": false, "error": {"code", "message"}}``),
and ``{"event": ...}`` lines for clients that asked to watch. The server owns the protocol
(framing, limits, authentication, watch fan-out); what the commands DO is delegated to a
:class:`Backend` (the daemon), called on the event loop.

Isolation: every client has its own reader and writer task; telemetry goes into a bounded
per-client queue (oldest dropped and counted), so a slow or stuck client never delays the
publisher, which is the control loop.

Lock-out protection (shared mechanics in :mod:`x6wd.app.lineserver`): a connection is pending
until it authenticates (without a token: until one valid request), in a pool of its own;
pending connections past ``auth_timeout_s``, sessions idle for ``idle_timeout_s`` and
clients that never read are closed; a full pool makes room instead of refusing. ``stop`` is
always obeyed: never rate-limited, allowed before ``auth``, executed ahead of a client's own
back-off, and a storm of stops is coalesced into one backend call in flight at a time.
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import functools
import hashlib
import hmac
import inspect
import json
import logging
import math
import re
import ssl
import stat
import sys
import termios
import time
import weakref
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

from x6wd import __version__
from x6wd.app.lineserver import (
    LISTEN_BACKLOG,
    LineClient,
    LineServer,
    peer_names,
    socket_queue_bytes,
    transport_socket,
    write_buffer_size,
)
from x6wd.core.config import ServerConfig, is_loopback_bind
from x6wd.core.errors import CommandError, ConfigError, ParseError, X6wdError
from x6wd.core.mission_files import (
    Waypoint,
    from_pairs,
    parse_csv,
    parse_gpx,
    parse_kml,
    parse_plan,
    parse_wpl,
)

log = logging.getLogger(__name__)

PROTOCOL_VERSION = 1
UNAUTHENTICATED_COMMANDS = frozenset({"hello", "auth", "status", "stop"})
COMMANDS = (
    "hello",
    "auth",
    "status",
    "mission.load",
    "start",
    "pause",
    "resume",
    "return",
    "stop",
    "drive",
    "watch",
    "log",
)
# commands that change what the robot does: a stop issued before one of these cannot stand
# in for a stop requested after it
MOTION_COMMANDS = frozenset({"mission.load", "start", "pause", "resume", "return", "drive"})
ACTING_COMMANDS = MOTION_COMMANDS | {"stop"}
SUPERSEDED_COMMANDS = frozenset({"start", "resume", "return", "drive"})
"""What a later ``stop`` cancels: one of these received before it (a backlog held behind the
request throttle, on any connection) is refused, never carried out after the stop."""
"""What a watch-only client (the web console with ``console.watch_only``) is refused."""
DETACHED_OPEN_COMMANDS = frozenset({"hello", "auth", "stop"})
"""What a detached client (the web console) may send before ``auth``: the brake, no status."""
MISSION_KEYS = ("waypoints", "gpx", "csv", "wpl", "kml", "plan")
"""``mission.load``'s arguments: a list of pairs, or a file's content in one of four formats."""
MAX_PENDING_REPLIES = 64
LOG_TAIL_MAX = 1000
MAX_JSON_DEPTH = 16
"""Deepest nesting of arrays/objects a request may have (a mission is 3 deep)."""
AUTH_FAIL_BUDGET = 10
"""Failed authentications an address may make before its attempts are slowed down."""
AUTH_FAIL_REFILL_PER_S = 0.1
"""How fast that budget comes back (failures per second)."""
MAX_TRACKED_ADDRESSES = 1024
MAX_AUTH_BACKOFF_S = 60.0
"""Longest per-connection wait after failed authentications (s)."""
STATUS_REUSE_S = 0.05
"""A status computed this recently (s), with no command since, answers other requesters: a
crowd polling ``status`` costs the control loop at most ~20 calls per second."""
OWNER_CHECK_S = 0.1
"""Most a drive from another client waits for the robot's mode before it is refused ``busy``
(s): the robot's own end of the owner's drive releases it (``_release_ended_drive``). The
connection's next line (a stop, say) waits behind that question: without the bound a busy
control loop held a non-owner's stop for as long as it stayed busy (2 s in a review)."""
CLOSED = "closed"
"""Error code of the notice sent (id null) before the server closes a connection."""
SHUTDOWN = "shutdown"
"""The notice's reason when the server itself closes (the daemon shuts down)."""
SHUTDOWN_MESSAGE = "x6wd is shutting down"
# error codes of requests that do not count as "one valid request" (admission without token)
_INVALID_CODES = frozenset(
    {"bad_request", "unknown_command", "rate_limited", "unauthorized", "auth_failed"}
)


class Backend(Protocol):
    """What the server needs from the daemon. Methods are called on the server's loop and must
    not block; each returns its result (a JSON-ready dict merged into the reply; a list of
    lines for ``log_tail``) or an awaitable of it (the daemon runs commands on its control
    loop). Raise :class:`CommandError` (or any X6wdError, reported as ``rejected``) to refuse.
    ``return_home`` answers the ``return`` command. ``operator_seen`` is called (and must
    not wait) for every request of a client allowed to command: the operator-link failsafe.
    """

    def status(self) -> Any: ...
    def load_mission(self, waypoints: list[Waypoint]) -> Any: ...
    def start(self) -> Any: ...
    def pause(self) -> Any: ...
    def resume(self) -> Any: ...
    def return_home(self) -> Any: ...
    def stop(self) -> Any: ...
    def drive(self, left_pct: float, right_pct: float, duration_s: float) -> Any: ...
    def log_tail(self, n: int) -> Any: ...
    def operator_seen(self) -> None: ...


def load_token(path: str | Path) -> bytes:
    """Read the shared secret; refuse a file that the group or others can read or write.

    Raises ConfigError naming the file and the problem.
    """
    p = Path(path)
    try:
        st = p.stat()
    except OSError as exc:
        raise ConfigError(f"server.token_file: cannot read {p}: {exc.strerror or exc}") from None
    if not stat.S_ISREG(st.st_mode):
        raise ConfigError(f"server.token_file: {p} is not a regular file")
    if st.st_mode & 0o077:
        raise ConfigError(
            f"server.token_file: {p} has mode {stat.S_IMODE(st.st_mode):04o}; it must not be "
            f"accessible to group or others (chmod 600 {p})"
        )
    try:
        token = p.read_bytes().strip()
    except OSError as exc:  # another user's file: exit 2, not a restart loop of tracebacks
        raise ConfigError(f"server.token_file: cannot read {p}: {exc.strerror or exc}") from None
    if len(token) < 8:
        raise ConfigError(f"server.token_file: {p}: token shorter than 8 bytes")
    return token


CERT_WARN_DAYS = 30.0
"""A certificate with fewer days left than this is a WARNING in the log and in ``status``:
time to renew it before every verified client refuses the robot (docs/install.md)."""
CERT_CHECK_S = 3600.0
"""How often (s) a running server looks at its certificate's dates again, for the log (a
certificate may expire while the daemon runs; ``status`` judges them at each request)."""
CLOCK_STEP_S = 60.0
"""A wall clock that moves this much (s) against the monotonic clock between two sweeps has
been set (NTP stepping a Pi's 1970 clock after boot): the certificate is judged again at once,
not up to :data:`CERT_CHECK_S` later."""
DAY_S = 86400.0


@dataclass(frozen=True)
class CertDates:
    """A certificate's validity, Unix time (s)."""

    not_before_s: float
    not_after_s: float


def cert_dates(path: str) -> CertDates | None:
    """The validity of the PEM certificate at ``path`` (its first), read with CPython's
    private ``ssl._ssl._test_decode_cert``: no new dependency for two dates. None (and a
    debug line) when that function is absent or cannot read the file: the check is skipped,
    start-up never fails because of it."""
    decode = getattr(getattr(ssl, "_ssl", None), "_test_decode_cert", None)
    if decode is None:
        log.debug("ssl._ssl._test_decode_cert absent: the dates of %s are not checked", path)
        return None
    try:
        info = decode(path)
        return CertDates(
            float(ssl.cert_time_to_seconds(info["notBefore"])),
            float(ssl.cert_time_to_seconds(info["notAfter"])),
        )
    except Exception as exc:  # a private API: any change of its shape skips the check
        log.debug("the dates of %s are not checked: %s: %s", path, type(exc).__name__, exc)
        return None


def utc_text(t_s: float) -> str:
    """Unix time ``t_s`` (s) as ISO 8601 UTC, seconds: ``2026-01-01T00:00:00Z``."""
    return time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime(t_s))


def _clock_floor_s() -> float:
    """This release's date (Unix time, s): a system clock before it has not been set (a
    Raspberry Pi boots at 1970 until it reaches a time server)."""
    from drivers.gps_io import WEEK_ROLLOVER_FLOOR_UTC

    return WEEK_ROLLOVER_FLOOR_UTC.timestamp()


def cert_verdict(
    dates: CertDates, now_s: float, path: str, key: str = "server.tls_cert"
) -> tuple[str, str]:
    """Judge ``dates`` at ``now_s`` (Unix time, s): ``(state, message)`` with state ``ok``
    (message ""), ``expiring`` (fewer than :data:`CERT_WARN_DAYS` days left), ``expired``,
    ``not_yet_valid`` (both: every verified client refuses the robot) or ``clock_unset``
    (not yet valid, but the system clock is before this release: the clock is wrong; the
    message says whether the certificate was valid on this release's date, else that its
    dates cannot be judged until the clock is set). A certificate that expired before this
    release is ``expired`` whatever the clock says. The message names ``key`` and ``path``
    and gives the dates."""
    span = f"valid {utc_text(dates.not_before_s)} to {utc_text(dates.not_after_s)}"
    floor_s = _clock_floor_s()
    if now_s > dates.not_after_s:
        return "expired", (
            f"{key}: {path} expired on {utc_text(dates.not_after_s)} ({span}, now "
            f"{utc_text(now_s)}): every verified client refuses it; renew it (docs/install.md)"
        )
    if now_s < floor_s and dates.not_after_s < floor_s:  # expired whatever the true date
        return "expired", (
            f"{key}: {path} expired on {utc_text(dates.not_after_s)} ({span}), before this "
            f"release ({utc_text(floor_s)}; the system clock says {utc_text(now_s)}, not set "
            "yet): every verified client refuses it; renew it (docs/install.md)"
        )
    if now_s < dates.not_before_s:
        if now_s < floor_s:
            unset = (
                f"{key}: {path} is not valid before {utc_text(dates.not_before_s)} ({span}) "
                f"and the system clock says {utc_text(now_s)}, before this release "
                f"({utc_text(floor_s)}): set the clock"
            )
            if dates.not_before_s <= floor_s:  # valid then: the clock alone is wrong
                return "clock_unset", (
                    f"{unset} (the certificate was valid on this release's date: clients "
                    f"whose clock is right accept it until {utc_text(dates.not_after_s)})"
                )
            return "clock_unset", (
                f"{unset}; its dates cannot be judged until then (it starts after this "
                "release's date: clients whose clock is right may refuse it too)"
            )
        return "not_yet_valid", (
            f"{key}: {path} is not valid before {utc_text(dates.not_before_s)} ({span}, now "
            f"{utc_text(now_s)}): every verified client refuses it; make it with the clock "
            "right (docs/install.md)"
        )
    left_d = (dates.not_after_s - now_s) / DAY_S
    if left_d < CERT_WARN_DAYS:
        return "expiring", (
            f"{key}: {path} expires on {utc_text(dates.not_after_s)}, in {left_d:.1f} days; "
            "renew it before then (docs/install.md)"
        )
    return "ok", ""


def check_key_file(path: str) -> None:
    """Refuse a TLS private key that the group or others can read or write, as the token
    file (:func:`load_token`). A missing or unreadable file is left to the loader, which
    names it. Raises ConfigError naming ``server.tls_key``."""
    try:
        st = Path(path).stat()
    except OSError:
        return
    if stat.S_ISREG(st.st_mode) and st.st_mode & 0o077:
        raise ConfigError(
            f"server.tls_key: {path} has mode {stat.S_IMODE(st.st_mode):04o}; it must not be "
            f"accessible to group or others (chmod 600 {path})"
        )


def server_ssl_context(cert: str, key: str, *, now_s: float | None = None) -> ssl.SSLContext:
    """TLS context for the server from PEM certificate and key paths (TLS 1.2+). Raises
    ConfigError naming the key for a key file others may read, files that cannot be loaded,
    and a certificate expired or not yet valid at ``now_s`` (Unix time, s; default now):
    started so, the daemon would be refused by every verified client, ``stop`` too."""
    check_key_file(key)
    ctx = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
    ctx.minimum_version = ssl.TLSVersion.TLSv1_2
    try:
        ctx.load_cert_chain(cert, key)
    except (OSError, ssl.SSLError) as exc:
        raise ConfigError(f"server.tls_cert/tls_key: cannot load {cert}, {key}: {exc}") from None
    dates = cert_dates(cert)
    if dates is not None:
        state, message = cert_verdict(dates, time.time() if now_s is None else now_s, cert)
        if state in ("expired", "not_yet_valid"):
            raise ConfigError(message)
    return ctx


def is_loopback(host: str) -> bool:
    """True for localhost (any case) / 127.0.0.0/8 / ::1 binds: the token rule and the TLS
    rule (:func:`x6wd.core.config.is_loopback_bind`) are one rule."""
    return is_loopback_bind(host)


def encode(obj: dict[str, Any]) -> bytes:
    """One protocol line (compact JSON + LF)."""
    return json.dumps(obj, separators=(",", ":"), allow_nan=False).encode() + b"\n"


def error_reply(req_id: Any, code: str, message: str, reason: str | None = None) -> dict[str, Any]:
    """The error reply object; ``reason`` (optional) refines ``code`` (e.g. bad_request's
    ``bad_json``, ``line_too_long``)."""
    err: dict[str, Any] = {"code": code, "message": message}
    if reason is not None:
        err["reason"] = reason
    return {"id": req_id, "ok": False, "error": err}


class _Reject(Exception):
    def __init__(self, code: str, message: str, reason: str | None = None, **extra: Any) -> None:
        super().__init__(message)
        self.code = code
        self.reason = reason
        self.extra = extra  # more fields of the error object (a ``busy`` drive's ``driver``)


def _bad(reason: str, message: str) -> _Reject:
    return _Reject("bad_request", message, reason)


@dataclass
class _Bucket:
    """A token bucket: ``level`` tokens refilled at ``rate`` per second up to ``burst``."""

    rate: float
    burst: float
    level: float
    t: float

    def refill(self, now: float) -> float:
        """Bring the level up to ``now`` (s, the server's clock) and return it."""
        self.level = min(self.burst, self.level + (now - self.t) * self.rate)
        self.t = now
        return self.level


@dataclass(eq=False, kw_only=True)
class _Client(LineClient):
    authenticated: bool
    tokens: _Bucket  # requests
    faults: _Bucket  # error replies (same rate and burst)
    watching: bool = False
    auth_failures: int = 0
    backoff_s: float = 0.0  # after a failed auth: wait this long before the next line
    close_reason: str = ""  # close once this reply is sent (too many failed auths)
    watch_only: bool = False  # refused every command in ACTING_COMMANDS
    open_commands: frozenset[str] = UNAUTHENTICATED_COMMANDS  # allowed before ``auth``
    drive_limit_s: float | None = None  # a drive's duration_s is cut to this (the dead-man)
    kind: str = ""  # what it is beside its peer, in status and refusals ("web console page")
    # the input as a stream (TCP: bytes, counted as the transport feeds the stream reader; a
    # detached client: messages): how much was received, where the line being handled ends,
    # and the stop fence: lines ending at or before it were received before a stop
    received: int = 0
    taken: int = 0
    fence: int = 0
    early_stop_end: int = 0  # where the latest stop sent ahead of its turn ends
    other_stop_s: float = -math.inf  # time.monotonic() of the latest stop from elsewhere


class _Shared:
    """One backend call shared by concurrent requesters (``stop``, ``status``)."""

    def __init__(self) -> None:
        self.future: asyncio.Future[Any] | None = None
        self.seq = -1  # the server's command sequence number when it was issued
        self.stops_sent = -1  # the server's count of stops sent when it was issued
        self.t_done_s = -float("inf")  # time.monotonic() when it completed


def _retrieve(f: asyncio.Future[Any]) -> None:
    # a shared call nobody awaits any more must not warn "exception never retrieved"
    if not f.cancelled():
        f.exception()


def _report_failed_stop(peer: str, f: asyncio.Future[Any]) -> None:
    """The dead-man's stop (nobody awaits its reply) failed: say so, the log said it was
    stopping the motors."""
    if not f.cancelled() and f.exception() is not None:
        log.error(
            "the stop for %s, which went away while driving, failed: %s: %s",
            peer,
            type(f.exception()).__name__,
            f.exception(),
        )


TLS_RECORD_B = 16_384 + 256
"""The most text one TLS record holds (its plaintext limit, with room): OpenSSL may keep one
read from the socket but not yet decrypted, which no buffer size shows."""


def _rebind_protocol(
    protocol: asyncio.BaseProtocol, writer: asyncio.StreamWriter, tls: asyncio.BaseTransport
) -> None:
    """Point a stream's protocol at its new TLS transport, as ``StreamWriter.start_tls``
    does: through ``_replace_transport(transport)`` where the interpreter has it (newer
    CPython renamed the method), else ``_replace_writer(writer)`` (3.11). Without either,
    every TLS connection would end in an AttributeError after its handshake."""
    replace = getattr(protocol, "_replace_transport", None)
    if replace is not None:
        replace(tls)
    else:
        protocol._replace_writer(writer)  # type: ignore[attr-defined]


def _arrived_b(c: _Client) -> int:
    """Bytes of a client's input that have reached this host (its position in the input):
    a detached client's messages received; a TCP client's bytes handed to its stream reader
    (counted as they are fed, so none is missed while a read is under way) plus, not read
    yet, on TLS asyncio's SSL layer (encrypted bytes it holds while the reader is paused,
    decrypted ones not handed on, and while any is held one record OpenSSL may keep) and
    the kernel's receive queue (FIONREAD). Encrypted counts and that record are a little
    more than their text: behind a backlog, a line sent just after a stop may be refused
    with the ones before it. asyncio has no public size for its SSL buffers (its own
    attributes, read defensively; tests/test_safety_server.py checks both transports).
    Never raises: a closed transport (asyncio's SSL one raises AttributeError from
    ``get_extra_info`` once closed twice) has nothing more to give than what was received
    (tests/test_tls_stop.py)."""
    writer = c.writer
    n = c.received
    if writer is None:
        return n
    transport = writer.transport
    proto = getattr(transport, "_ssl_protocol", None)  # None once that transport is closed
    held = 0
    if proto is not None:
        with contextlib.suppress(Exception):
            held = int(getattr(getattr(proto, "_incoming", None), "pending", 0))
        n += held
        with contextlib.suppress(Exception):  # ssl.SSLError, ValueError, AttributeError
            sslobj = getattr(proto, "_sslobj", None)
            n += int(sslobj.pending()) if sslobj is not None else 0
    queued = socket_queue_bytes(transport_socket(transport), termios.FIONREAD) or 0
    if proto is not None and queued + held > 0:
        # a held-back TLS stream: OpenSSL may hold a record it read but did not decrypt
        n += TLS_RECORD_B
    return n + queued


async def _result(value: Any) -> Any:
    """A backend result, awaited when the backend runs it on another loop (the daemon)."""
    if inspect.isawaitable(value):
        return await value
    return value


def _no_constant(name: str) -> Any:
    raise _bad("bad_number", f"{name} is not allowed (numbers must be finite)")


def _bounded_int(text: str) -> int:
    """An integer of a request (``parse_int``): one longer than the interpreter converts
    (``sys.get_int_max_str_digits()``, 4300 digits by default) is a number out of range,
    not a JSON error (its message would be Python's, naming a Python setting)."""
    try:
        return int(text)
    except ValueError:
        digits, most = len(text.lstrip("-")), sys.get_int_max_str_digits()
        raise _bad(
            "bad_number", f"number out of range: an integer of {digits} digits (at most {most})"
        ) from None


def _finite_float(text: str) -> float:
    v = float(text)
    if v in (float("inf"), float("-inf")):
        raise _bad("bad_number", f"number out of range: {text[:40]}")
    return v


def _check_tree(obj: Any, depth_check: bool, unicode_check: bool) -> None:
    """Reject nesting deeper than MAX_JSON_DEPTH and strings that are not valid Unicode
    (lone surrogates from ``\\ud800`` escapes: they cannot be encoded)."""
    stack: list[tuple[Any, int]] = [(obj, 1)]
    while stack:
        o, depth = stack.pop()
        if isinstance(o, (dict, list)):
            if depth_check and depth > MAX_JSON_DEPTH:
                raise _bad("too_deep", f"nested deeper than {MAX_JSON_DEPTH} levels")
            items = o.items() if isinstance(o, dict) else enumerate(o)
            for k, v in items:
                if unicode_check and isinstance(k, str):
                    stack.append((k, depth + 1))
                stack.append((v, depth + 1))
        elif unicode_check and isinstance(o, str) and not o.isascii():
            try:
                o.encode("utf-8")
            except UnicodeEncodeError:
                raise _bad(
                    "bad_unicode", "a string holds a lone surrogate (invalid Unicode)"
                ) from None


def parse_request(line: bytes) -> dict[str, Any]:
    """Decode one request line into its object: strict UTF-8, JSON without NaN/Infinity,
    at most :data:`MAX_JSON_DEPTH` deep, no lone surrogates. Raises ``_Reject`` with code
    ``bad_request`` and a ``reason`` (bad_utf8, bad_json, bad_number, too_deep, bad_unicode,
    not_object)."""
    try:
        text = line.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise _bad("bad_utf8", f"not UTF-8: {exc.reason} at byte {exc.start}") from None
    try:
        req = json.loads(
            text, parse_constant=_no_constant, parse_float=_finite_float, parse_int=_bounded_int
        )
    except RecursionError:
        raise _bad("too_deep", f"nested deeper than {MAX_JSON_DEPTH} levels") from None
    except ValueError as exc:  # JSONDecodeError
        raise _bad("bad_json", f"not valid JSON: {exc}") from None
    if not isinstance(req, dict):
        raise _bad("not_object", "a request must be a JSON object")
    depth_check = text.count("[") + text.count("{") > MAX_JSON_DEPTH
    unicode_check = "\\u" in text  # a surrogate can only come from an escape
    if depth_check or unicode_check:
        _check_tree(req, depth_check, unicode_check)
    return req


def _command_reason(exc: CommandError) -> str | None:
    """The ``reason`` of a backend's refusal: its own when it gives one; for ``bad_request``
    (every one carries a reason, docs/protocol.md) ``bad_argument``: the backend only sees
    requests that parsed, so it refuses an argument's value (``duration_s`` over
    ``[safety] manual_max_s``)."""
    reason = getattr(exc, "reason", None)
    if isinstance(reason, str) and reason:
        return reason
    return "bad_argument" if exc.code == "bad_request" else None


_HTTP_LINE = re.compile(
    rb"\s*(?:[A-Z]{3,10} \S+ HTTP/\d|(?i:host|origin|user-agent|content-type|content-length):)"
)
"""An HTTP request line or one of the headers every browser request carries (the first
line of a cross-protocol request from a web page; a JSON request never starts so)."""


def _number(args: dict[str, Any], key: str, lo: float, hi: float) -> float:
    v = args.get(key)
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise _bad("bad_argument", f"'{key}' must be a number")
    try:
        v = float(v)
    except OverflowError:
        raise _bad("bad_argument", f"'{key}' is out of range") from None
    if not lo <= v <= hi:  # also rejects NaN
        raise _bad("bad_argument", f"'{key}' must be within {lo:g}..{hi:g}, got {v:g}")
    return v


def _may_hold_stop(data: bytes) -> bool:
    """Whether ``data`` may hold a ``stop`` request: the bytes "stop", or a JSON escape
    (``"\\u0073top"`` is the same request; parsing every line would cost the flood path)."""
    return b"stop" in data or b"\\u" in data


def _ended(buf: bytearray, discarding: bool) -> bytearray:
    """``buf`` at the input's end: its last line, unterminated, given its newline (unless it
    is the rest of an oversized line being discarded, or blank), in place."""
    tail_at = buf.rfind(b"\n") + 1
    tail = buf[tail_at:]
    if tail.strip() and not (discarding and tail_at == 0):
        buf += b"\n"
    return buf


class ControlServer(LineServer[_Client]):
    """The remote-control endpoint. :meth:`publish` is called from the loop and never waits."""

    pending_timeout_reason = "auth_timeout"
    label = "control server"

    def __init__(
        self,
        config: ServerConfig,
        backend: Backend,
        *,
        token: bytes | None = None,
        ssl_context: ssl.SSLContext | None = None,
        clock: Callable[[], float] = time.monotonic,
        wall_clock: Callable[[], float] = time.time,
    ) -> None:
        """``token`` None: no authentication (refused unless bound to loopback). ``clock``:
        monotonic seconds for rates and deadlines; ``wall_clock``: Unix time (s) that the
        certificate's dates are judged at (tests inject both)."""
        if token is None and not is_loopback(config.bind):
            raise ConfigError(
                f"server.token_file: required when server.bind ({config.bind}) is not loopback"
            )
        super().__init__(
            config.port,
            max_clients=config.max_clients,
            max_pending=config.max_pending,
            pending_timeout_s=config.auth_timeout_s,
            idle_timeout_s=config.idle_timeout_s,
            slow_client_s=config.slow_client_s,
            clock=clock,
            logger=log,
        )
        self.config = config
        self.backend = backend
        self._token = token
        # compared as digests: constant time, and the time does not depend on the length
        self._token_digest = hashlib.sha256(token).digest() if token is not None else b""
        self._ssl = ssl_context
        # the loaded certificate's dates (None: no TLS, or unreadable): ``status`` judges them
        # at each request; the sweeper logs a change at most every ``cert_check_s`` (s)
        self._cert_path = config.tls_cert if ssl_context is not None else ""
        self._cert_dates = cert_dates(self._cert_path) if self._cert_path else None
        self.cert_check_s = CERT_CHECK_S
        self._wall_clock = wall_clock
        self._cert_checked_s = -math.inf  # time.monotonic() of the latest check
        # wall_clock() - time.monotonic() then (s): a change of it is the clock being set
        self._cert_clock_offset_s = wall_clock() - time.monotonic()
        self._cert_logged = ("ok", -math.inf)  # the state logged last, and when (monotonic s)
        self.requests_total = 0
        self.errors_total = 0
        self.auth_failed_total = 0
        self.stops = collections.Counter(
            {
                "requested": 0, "sent": 0, "coalesced": 0, "early": 0, "orphaned": 0,
                "superseded": 0,
            }
        )  # fmt: skip
        self._fenced: weakref.WeakSet[_Client] = weakref.WeakSet()  # every client, any transport
        # whose manual drive runs: the dead-man (its client gone: stop) and the drive's owner
        # (another client's drive is refused until it ends: _refuse_foreign_drive)
        self._drive_owner: _Client | None = None
        self._drive_seq = 0  # drives sent to the robot (_release_ended_drive)
        self._drives_in_flight = 0  # sent, not yet answered
        self._closing = False  # close() has begun: connections end because the server does
        self._drive_until_s = 0.0  # time.monotonic() when it ends
        self._command_seq = 0  # incremented before each motion command reaches the backend
        self._stop_call = _Shared()
        self._status_call = _Shared()
        self._auth_budgets: collections.OrderedDict[str, _Bucket] = collections.OrderedDict()

    @classmethod
    def from_config(cls, config: ServerConfig, backend: Backend) -> ControlServer:
        """Build with the token file and TLS files named in ``config`` (ConfigError on problems)."""
        token = load_token(config.token_file) if config.token_file else None
        ctx = None
        if config.tls_cert or config.tls_key:
            if not (config.tls_cert and config.tls_key):
                raise ConfigError("server.tls_cert and server.tls_key must be given together")
            ctx = server_ssl_context(config.tls_cert, config.tls_key)
        return cls(config, backend, token=token, ssl_context=ctx)

    @property
    def auth_required(self) -> bool:
        """True when a token is configured."""
        return self._token is not None

    async def start(self) -> None:
        """Bind and listen."""
        # TLS is not the listener's: each connection is accepted as plain TCP, joins the
        # pending pool at once, and is upgraded there (:meth:`_upgrade`). A listener's TLS
        # handshake comes before any pool: peers that never send a ClientHello were not
        # counted, and 250 of them took every file descriptor (accept() failed EMFILE, the
        # operator's connection with it).
        server = await asyncio.start_server(
            self._handle,
            self.config.bind,
            self._configured_port,
            backlog=LISTEN_BACKLOG,
        )
        self._listening(server)
        log.info(
            "control server listening on %s:%d%s",
            self.config.bind,
            self.port,
            " (TLS)" if self._ssl else "",
        )
        self.check_cert()

    def cert_status(self, now_s: float | None = None) -> dict[str, Any] | None:
        """The ``tls`` object of ``status`` at ``now_s`` (Unix time, s; default now): the
        certificate's path, dates, ``days_left``, ``state`` (:func:`cert_verdict`, or
        ``unknown`` when the dates cannot be read) and ``warning`` (null when ``ok``). None
        without TLS."""
        if not self._cert_path:
            return None
        dates = self._cert_dates
        if dates is None:
            return {"cert": self._cert_path, "state": "unknown", "warning": None}
        now_s = self._wall_clock() if now_s is None else now_s
        state, message = cert_verdict(dates, now_s, self._cert_path)
        return {
            "cert": self._cert_path,
            "not_before": utc_text(dates.not_before_s),
            "not_after": utc_text(dates.not_after_s),
            "days_left": round((dates.not_after_s - now_s) / DAY_S, 1),
            "state": state,
            "warning": message or None,
        }

    def check_cert(self, now_s: float | None = None) -> str:
        """Judge the certificate's dates at ``now_s`` (Unix time, s; default now) and log a
        state that is not ``ok`` when it changes, and once a day while it lasts (WARNING
        when it expires soon or the clock is unset, ERROR once expired); return the state
        (``none`` without TLS or dates). The sweeper calls it every ``cert_check_s``, and
        at once when the wall clock has been set (:data:`CLOCK_STEP_S`)."""
        self._cert_checked_s = time.monotonic()
        self._cert_clock_offset_s = self._wall_clock() - self._cert_checked_s
        st = self.cert_status(now_s)
        if st is None or st["state"] == "unknown":
            return "none"
        state, message = st["state"], st["warning"]
        before, t_logged = self._cert_logged
        if state == "ok":
            if before != "ok":
                log.info("server.tls_cert: %s is valid until %s", st["cert"], st["not_after"])
                self._cert_logged = ("ok", self._cert_checked_s)
            return state
        if state == before and self._cert_checked_s - t_logged < DAY_S:
            return state
        if state in ("expired", "not_yet_valid"):
            log.error(
                "%s (the daemon runs on: `x6wd client stop` falls back to an unverified stop)",
                message,
            )
        else:
            log.warning("%s", message)
        self._cert_logged = (state, self._cert_checked_s)
        return state

    def sweep(self) -> int:
        """The deadlines (:meth:`LineServer.sweep`), and the certificate's dates
        (:meth:`check_cert`, cheap: no file is read) every ``cert_check_s`` and as soon as
        the wall clock has been set: NTP stepping a Pi's clock from 1970 a minute after boot
        would otherwise leave the verdict of 1970 (``clock_unset``) for up to an hour."""
        closed = super().sweep()
        if self._cert_dates is not None:
            mono_s = time.monotonic()
            stepped_s = abs(self._wall_clock() - mono_s - self._cert_clock_offset_s)
            if stepped_s > CLOCK_STEP_S or mono_s - self._cert_checked_s >= self.cert_check_s:
                self.check_cert()
        return closed

    def publish(self, event: dict[str, Any]) -> None:
        """Queue an ``{"event": ..}`` line for every watching client (drop-oldest when full)."""
        watchers = [c for c in self._sessions if c.watching and not c.closed]
        if not watchers:
            return
        line = encode(event)
        maxlen = self.config.queue_len
        for c in watchers:
            if c.put(line, maxlen):
                self.dropped_total += 1

    def server_stats(self) -> dict[str, Any]:
        """The ``server`` object of the ``status`` reply: pools, closes by reason, failed
        authentications, stops (requested, sent to the backend, coalesced) and, with TLS,
        the certificate's dates (``tls``, :meth:`cert_status`)."""
        stats = {
            **self.pool_stats(),
            "auth_failed": self.auth_failed_total,
            "stops": dict(self.stops),
        }
        tls = self.cert_status()
        if tls is not None:
            stats["tls"] = tls
        return stats

    # -- pools ----------------------------------------------------------------------------
    def _is_watching(self, c: _Client) -> bool:
        return c.watching

    def _protected(self, c: _Client) -> bool:
        # the driving operator: closing it for a stranger's connection fires the dead-man
        return self.drive_active(c)

    def _notice(self, reason: str, message: str) -> bytes:
        return encode(error_reply(None, CLOSED, message, reason))

    # -- per-connection -------------------------------------------------------------------
    async def _handle(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        task = asyncio.current_task()
        if task is not None:
            self._tasks.add(task)
        peer, host = peer_names(writer)
        now = self._clock()
        c = _Client(
            writer=writer,
            peer=peer,
            host=host,
            task=task,
            reader=reader,
            authenticated=self._token is None,
            tokens=self._bucket(now),
            faults=self._bucket(now),
        )
        self._fenced.add(c)
        feed = reader.feed_data

        def counted(data: bytes) -> None:  # the stop fence's count of what has arrived
            c.received += len(data)
            feed(data)

        reader.feed_data = counted  # type: ignore[method-assign,assignment]
        try:
            # pending from accept on, before any TLS handshake: the pool's bound (oldest
            # closed when full) holds whatever the peers do or do not send
            self._connected(c)
            if self._ssl is not None and not await self._upgrade(c):
                return
            c.sender = asyncio.create_task(self._sender(c))
            await self._read_loop(reader, c)
        except (ConnectionError, OSError, ssl.SSLError):
            pass
        except asyncio.CancelledError:
            pass  # close() or eviction: a finished task keeps asyncio's stream callback quiet
        finally:
            try:
                self._drive_orphaned(c)
            finally:  # whatever happened there, the connection leaves the pools
                await self._hang_up(c, reader)

    async def _upgrade(self, c: _Client) -> bool:
        """The TLS handshake of a pending connection (nothing else may be awaited between
        its accept and this: its input is not read before the handshake takes it). False
        when it did not complete: the peer failed it or went away, it took longer than
        ``auth_timeout_s``, or the connection was closed meanwhile (evicted from the full
        pending pool, or past its deadline: the sweeper resets it)."""
        raw = c.writer.transport
        if c.evicted or raw.is_closing():  # (gone already: the peer reset it)
            return False
        protocol = raw.get_protocol()
        c.handshaking = True
        try:
            tls = await asyncio.get_running_loop().start_tls(
                raw,
                protocol,
                self._ssl,  # type: ignore[arg-type]
                server_side=True,
                # a backstop: the sweeper closes it at auth_timeout_s, as any pending one
                ssl_handshake_timeout=2.0 * self.config.auth_timeout_s,
            )
        finally:
            c.handshaking = False
        if tls is None or c.evicted:  # closed during the handshake (None: by us)
            return False
        # what StreamWriter.start_tls does once the handshake is done; not that method
        # itself: a transport closed mid-handshake leaves its writer with none (an
        # AttributeError, and another in the writer's __del__)
        c.writer._transport = tls  # type: ignore[attr-defined]
        _rebind_protocol(protocol, c.writer, tls)
        return True

    async def close(self, message: str = SHUTDOWN_MESSAGE) -> None:
        """Stop listening and disconnect every client (idempotent), each told so first: the
        ``closed`` notice with reason ``shutdown`` and ``message`` (what the daemon has
        done about the motors), unless it does not read (its queue is full)."""
        if not self._closing:
            self._closing = True
            notice = self._notice(SHUTDOWN, message)
            for c in list(self._clients):
                with contextlib.suppress(Exception):  # a goodbye never holds up the close
                    self._goodbye(c, notice)
        await super().close()

    @staticmethod
    def _goodbye(c: _Client, notice: bytes) -> None:
        """The last line to an open connection, after the replies still queued for it (the
        events are dropped): written now, as the transport closes next."""
        if c.closed or c.evicted or c.handshaking:
            return
        c.evicted = SHUTDOWN  # its sender writes nothing more
        c.events.clear()
        line = b"".join(c.replies) + notice
        c.replies.clear()
        transport = c.writer.transport
        if not transport.is_closing() and write_buffer_size(transport) == 0:
            transport.write(line)

    def drive_active(self, c: _Client) -> bool:
        """True while ``c``'s manual drive runs and no later command replaced it."""
        return self._drive_owner is c and time.monotonic() < self._drive_until_s

    @staticmethod
    def _name(c: _Client) -> str:
        """How status and refusals name a client: "host:port", a page "web console page
        host:port"."""
        return f"{c.kind} {c.peer}" if c.kind else c.peer

    def _drive_status(self, c: _Client) -> dict[str, Any] | None:
        """``status``'s ``manual_drive``: who drives (null: nobody's drive holds), for how
        much longer its latest drive holds (s), and whether it is the asker."""
        owner = self._drive_owner
        if owner is None or not self.drive_active(owner):
            return None
        holds_s = self._drive_until_s - time.monotonic()
        return {"owner": self._name(owner), "holds_s": round(holds_s, 2), "yours": owner is c}

    def _refuse_foreign_drive(self, c: _Client) -> None:
        """Manual drive belongs to the client whose drive started it: while that drive holds
        (its dead-man has not expired, no stop came, the client is connected: its going away
        stops it), a drive from any other client is refused (``rejected``, ``busy``) and the
        robot keeps the owner's. Two pages holding two keys made the motors switch between
        them several times a second, and neither page was told (outside audit, round 7).
        ``stop`` is never refused, and ends the ownership: the next drive from anyone takes
        it. (Here, not deeper: the sessions, TCP and console pages, are this server's, and
        it already keeps the drive's owner and deadline for the dead-man; the controller
        knows no clients.)"""
        owner = self._drive_owner
        if owner is None or owner is c or not self.drive_active(owner):
            return
        holds_s = self._drive_until_s - time.monotonic()
        name = self._name(owner)
        self._rlog.log(
            "drives refused", logging.INFO, "drive from %s refused: %s drives", self._name(c), name
        )
        raise _Reject(
            "rejected",
            f"another client is driving ({name}): its drive holds for {holds_s:.1f} s more "
            "(each of its drives renews it); not driven. 'stop' works from here and ends that "
            "drive; once it has ended, the next drive from any client takes over",
            "busy",
            driver=name,
            holds_s=round(holds_s, 2),
        )

    async def _release_ended_drive(self, c: _Client) -> None:
        """Before another client's drive is refused: a drive the robot ended on its own (the
        motor link lost, a failsafe; the controller no longer in MANUAL) no longer holds,
        though its deadline has not come (up to ``manual_max_s``, 60 s configurable) and
        its owner is still connected, or seems to be (a half-open connection). The robot's
        mode is asked (``status``, on the control loop) only then, and only when no drive
        is on its way to the robot: one sent before is taken before the question, so a
        mode other than MANUAL is the robot's own end of the owner's drive (review of
        a1a7005). A drive sent meanwhile, or a stop, leaves the ownership to them."""
        owner = self._drive_owner
        if owner is None or owner is c or not self.drive_active(owner):
            return
        if self._drives_in_flight:
            return
        seq = self._drive_seq
        try:  # shared with the status requests (a crowd of drivers cannot load the loop),
            # and bounded: the line after this one on the connection waits meanwhile
            st = await asyncio.wait_for(self._status(), OWNER_CHECK_S)
        except Exception:  # no answer in time: the deadline decides, as before
            st = None
        if c.taken <= c.fence:  # a stop came while the robot was asked
            self.stops["superseded"] += 1
            raise _Reject("rejected", "a stop came after this drive: not done", "stopped")
        mode = st.get("mode") if isinstance(st, dict) else None
        if (
            self._drive_owner is owner
            and self._drive_seq == seq
            and not self._drives_in_flight
            and isinstance(mode, str)
            and mode != "MANUAL"
        ):
            self._drive_owner = None
            log.info(
                "the drive of %s ended on the robot (mode %s): %s may drive",
                self._name(owner),
                mode,
                self._name(c),
            )

    def _drive_orphaned(self, c: _Client) -> None:
        """The dead-man on the control port: a client that goes away (closed, reset, evicted)
        while its drive runs stops the motors now, not when ``duration_s`` ends. Not when
        the server itself closes: the daemon's shutdown stops the motors, no client left."""
        if self._closing or not self.drive_active(c):
            return
        self._drive_owner = None
        stopping = self._fire_stop()  # the motors first: nothing below may skip or delay it
        with self._bookkeeping("the dead-man's stop"):
            self.stops["requested"] += 1
            self.stops["orphaned"] += 1
            log.warning("%s went away while driving: stopping the motors", c.peer)
            stopping.add_done_callback(functools.partial(_report_failed_stop, c.peer))
            self._stop_fence(None, 0)

    @contextlib.contextmanager
    def _bookkeeping(self, what: str) -> Iterator[None]:
        """Around the counts, log lines and fences that follow a stop already sent to the
        motors: an error in them is logged (at most once per second) and goes no further,
        so it can neither undo the stop nor fail its reply."""
        try:
            yield
        except Exception as exc:
            self._rlog.log(
                "stop bookkeeping errors",
                logging.ERROR,
                "bookkeeping after %s failed (the stop was sent): %s: %s",
                what,
                type(exc).__name__,
                exc,
            )

    def _bucket(self, now: float) -> _Bucket:
        burst = max(5.0, self.config.rate_per_s)
        return _Bucket(self.config.rate_per_s, burst, burst, now)

    async def _read_loop(self, reader: asyncio.StreamReader, c: _Client) -> None:
        limit = self.config.max_line_bytes
        buf = bytearray()
        discarding = False
        scanned = 0  # bytes at the head of buf already searched for stops (see _early_stops)
        rate = float(self.config.input_bytes_per_s)
        burst = max(rate, 2.0 * limit)
        budget = _Bucket(rate, burst, burst, self._clock())
        eof = False
        while not c.closed and not eof:
            chunk = await reader.read(65536)
            if not chunk:
                # the input's end: a last request without its newline (`printf '{"cmd":
                # "stop"}' | nc`, a client that shuts its sending side) is still carried out
                # and answered, as gpsd does, never dropped in silence
                if discarding or not buf.strip():
                    return
                eof, chunk = True, b"\n"
                if buf.endswith(b"\n"):  # _ended gave it its newline during a back-off
                    chunk = b""
            buf += chunk
            budget.refill(self._clock())
            budget.level -= len(chunk)
            if budget.level < 0:
                # a flood: stop reading this client for a while (only it waits)
                nap = -budget.level / rate
                scanned = await self._nap_reading(reader, c, buf, scanned, discarding, budget, nap)
            while not c.closed:
                nl = buf.find(b"\n")
                if nl < 0:
                    if len(buf) > limit:
                        if not discarding:
                            self._reply(c, self._too_long())
                        discarding = True
                        c.taken += len(buf)
                        buf.clear()
                        scanned = 0
                    break
                line = bytes(buf[:nl])
                del buf[: nl + 1]
                c.taken += nl + 1
                scanned = max(0, scanned - (nl + 1))
                c.t_active_s = self._clock()
                if discarding:
                    discarding = False  # the rest of an oversized line
                    continue
                if _HTTP_LINE.match(line):
                    # a browser's request (a page of any site can POST here with no-cors;
                    # the body would follow as lines): no program of ours sends this
                    why = "an HTTP request on the control port"
                    self._reply(c, error_reply(None, "bad_request", why, "http"))
                    self._count_close(c, "http", why)
                    c.reply(self._notice("http", why))
                    return
                if len(line) > limit:
                    reply = self._too_long()
                elif line.strip():
                    reply = await self.dispatch(c, line)
                else:
                    continue
                self._reply(c, reply)
                if c.close_reason:
                    self._count_close(
                        c, c.close_reason, f"{c.auth_failures} failed authentications"
                    )
                    c.reply(self._notice(c.close_reason, "too many failed authentications"))
                    return  # the hang-up flushes the reply and the notice
                wait = 0.0
                if not reply["ok"]:
                    if not c.session:
                        c.suspect = True  # evicted first when the pending pool is full
                    # a client whose requests keep failing is read at the request rate:
                    # each line still gets its reply, only later (only it waits)
                    wait = self._fault_wait(c)
                wait, c.backoff_s = max(wait, c.backoff_s), 0.0
                if wait > 0.0:
                    scanned = await self._nap_reading(
                        reader, c, buf, scanned, discarding, budget, wait
                    )
            while len(c.replies) > MAX_PENDING_REPLIES and not c.closed:
                # a client that asks without reading waits here, alone
                scanned = self._early_stops(c, buf, scanned, discarding)
                c.drained.clear()
                await c.drained.wait()

    async def _nap_reading(
        self, reader: asyncio.StreamReader, c: _Client, buf: bytearray, scanned: int,
        discarding: bool, budget: _Bucket, seconds: float,
    ) -> int:  # fmt: skip
        """Sleep out a client's back-off while still reading its input into ``buf`` (charged to
        its input ``budget``; at most ``2 * max_line_bytes`` + one 64 KiB read held): a stop
        that arrives meanwhile goes to the motors at once, not when the back-off ends. Returns
        how far ``buf`` has been searched for stops."""
        scanned = self._early_stops(c, buf, scanned, discarding)
        loop = asyncio.get_running_loop()
        deadline = loop.time() + seconds
        c.napping = True  # an eviction cancels the handler, as in _nap
        try:
            # and it is looked at here too: Python 3.11's wait_for drops a cancel that comes
            # as its read completes, and the handler would sleep out the rest of its back-off
            # holding the connection it has lost (an eviction sets ``closed`` first)
            while not c.closed and (left := deadline - loop.time()) > 0.0:
                if reader.at_eof() or len(buf) >= 2 * self.config.max_line_bytes:
                    if reader.at_eof():  # a last stop without its newline goes now too
                        scanned = self._early_stops(c, _ended(buf, discarding), scanned, discarding)
                    await asyncio.sleep(left)  # held back: the rest waits in the kernel
                    break
                try:  # a read cancelled by the timeout loses nothing: its data stays queued
                    chunk = await asyncio.wait_for(reader.read(65536), left)
                except TimeoutError:
                    break
                buf += chunk
                budget.level -= len(chunk)
                scanned = self._early_stops(c, buf, scanned, discarding)
        finally:
            c.napping = False
        return scanned

    def _early_stops(self, c: _Client, buf: bytearray, scanned: int, discarding: bool) -> int:
        """Before a client waits out its own back-off, send the stops already in its input to
        the backend at once (each is still answered in order, when its turn comes: then it
        joins the stop in flight, or is sent again if a command came in between). Returns
        how far ``buf`` has been searched."""
        end = buf.rfind(b"\n") + 1
        if end <= scanned:
            return scanned
        region = bytes(buf[scanned:end])
        if _may_hold_stop(region):
            lines = region.split(b"\n")[:-1]
            at = c.taken + scanned  # where the region begins in the client's input
            for i, line in enumerate(lines):
                at += len(line) + 1
                if i == 0 and scanned == 0 and discarding:
                    continue  # the tail of an oversized line
                if len(line) <= self.config.max_line_bytes:
                    self._early_stop(c, line, at)
        return end

    def _early_stop(self, c: _Client, line: bytes, end: int) -> None:
        """Send a ``stop`` request line that ends at ``end`` in ``c``'s input to the backend
        at once (anything else: nothing)."""
        if not _may_hold_stop(line):
            return
        try:
            req = parse_request(line)
        except _Reject:
            return
        if req.get("cmd") == "stop":
            self._fire_stop()  # the motors first, then the bookkeeping
            with self._bookkeeping("an early stop"):
                self.stops["early"] += 1
                c.early_stop_end = max(c.early_stop_end, end)
                self._stop_fence(c, end)

    def receive(self, c: _Client, line: bytes, *, early: bool) -> None:
        """A detached client's request line as it arrives (each, in order, then handled in
        turn through :meth:`take` and :meth:`request`). ``early``: it came while the
        transport was still busy with an earlier one or its back-off, and a ``stop`` goes to
        the backend now, as on the TCP port."""
        c.received += 1
        if early and not c.watch_only:  # a watch-only client's stop is refused, early or not
            self._early_stop(c, line, c.received)

    @staticmethod
    def take(c: _Client) -> None:
        """A detached client's next received line is about to be handled (every line the
        transport took from its queue, whether or not it reaches :meth:`request`)."""
        c.taken += 1

    def _stop_fence(self, origin: _Client | None, end: int) -> None:
        """A stop was asked for: every motion command received before it is refused, on
        every connection, also what is still on its way in (held in the kernel behind a
        throttled client). On ``origin``'s own input (where the stop ends at ``end``) the
        lines after the stop were sent after it and stand. A detached client's messages
        still in its transport are judged there, by their send time (:meth:`stopped_since`)."""
        now_s = time.monotonic()
        for c in list(self._fenced):
            if c is origin:
                c.fence = max(c.fence, end)
                continue
            c.other_stop_s = now_s
            try:
                arrived = _arrived_b(c)
            except Exception as exc:  # (it does not raise; if it ever did: this client only)
                arrived = c.received  # at least all that reached its reader is fenced
                self._rlog.log(
                    "stop fence errors",
                    logging.ERROR,
                    "stop fence: cannot measure the input of %s (fenced at what it has "
                    "received): %s: %s",
                    c.peer,
                    type(exc).__name__,
                    exc,
                )
            c.fence = max(c.fence, arrived)

    def stopped_since(self, c: _Client, sent_s: float) -> bool:
        """A stop came from another client after ``sent_s`` (time.monotonic() s, the latest
        ``c`` can have sent a motion command): the command is refused (counted in
        ``stops.superseded``). ``c``'s own stops are judged by order (:meth:`dispatch`)."""
        if sent_s < c.other_stop_s:
            self.stops["superseded"] += 1
            return True
        return False

    def _fault_wait(self, c: _Client) -> float:
        """Charge one error reply to the client's fault bucket; seconds to wait before its
        next line (0 within the burst). Bounds what a garbage flood costs the robot to
        ``rate_per_s`` error replies per second per client. An empty bucket waits until it is
        half full again: one wake-up per half burst, not a timer per line."""
        b = c.faults
        b.refill(self._clock())
        b.level -= 1.0
        if b.level >= 0.0:
            return 0.0
        return (b.burst / 2.0 - b.level) / b.rate

    def _too_long(self) -> dict[str, Any]:
        msg = f"request line longer than {self.config.max_line_bytes} bytes"
        return error_reply(None, "bad_request", msg, "line_too_long")

    def _reply(self, c: _Client, obj: dict[str, Any]) -> None:
        if not obj.get("ok", False):
            self.errors_total += 1
        try:
            line = encode(obj)
        except (ValueError, TypeError) as exc:  # a backend result that is not JSON-ready
            self._rlog.log("internal", logging.ERROR, "unencodable reply %r: %s", obj, exc)
            self.errors_total += 1
            line = encode(error_reply(obj.get("id"), "internal", "internal error: bad reply"))
        c.reply(line)

    def _take_token(self, c: _Client) -> bool:
        if c.tokens.refill(self._clock()) >= 1.0:
            c.tokens.level -= 1.0
            return True
        return False

    async def dispatch(self, c: _Client, line: bytes) -> dict[str, Any]:
        """Handle one request line and return its reply object (never raises)."""
        self.requests_total += 1
        req_id: Any = None
        try:
            req = parse_request(line)
            req_id = req.get("id")
            if isinstance(req_id, (dict, list)):
                req_id = None
                raise _bad("bad_id", "'id' must be a string, number or null")
            cmd = req.get("cmd")
            if not isinstance(cmd, str):
                raise _bad("bad_cmd", "missing 'cmd' (a string)")
            if cmd not in COMMANDS:
                raise _Reject(
                    "unknown_command", f"unknown command {cmd!r} (valid: {', '.join(COMMANDS)})"
                )
            # stop must always get through: it is the operator's emergency brake; auth has
            # its own throttle, and a correct token is never refused for rate
            if cmd not in ("stop", "auth") and not self._take_token(c):
                raise _Reject("rate_limited", f"more than {self.config.rate_per_s:g} requests/s")
            if not c.authenticated and cmd not in c.open_commands:
                raise _Reject("unauthorized", f"authenticate first to use {cmd!r}")
            if c.watch_only and cmd in ACTING_COMMANDS:
                raise _Reject("watch_only", f"this connection only watches: {cmd!r} refused")
            if cmd in SUPERSEDED_COMMANDS and c.taken <= c.fence:
                self.stops["superseded"] += 1
                raise _Reject("rejected", f"a stop came after this {cmd}: not done", "stopped")
            if c.authenticated and not c.watch_only:  # an operator is there (the
                self.backend.operator_seen()  # operator-link failsafe; not a spectator)
            result = await self._execute(c, cmd, req)
            if cmd == "auth" and c.authenticated and not c.watch_only:
                self.backend.operator_seen()
            reply = {"id": req_id, "ok": True, **result}
        except _Reject as exc:
            reply = error_reply(req_id, exc.code, str(exc), exc.reason)
            reply["error"].update(exc.extra)
        except CommandError as exc:
            reply = error_reply(req_id, exc.code, str(exc), _command_reason(exc))
        except ParseError as exc:
            reply = error_reply(req_id, "bad_request", str(exc), "bad_mission")
        except X6wdError as exc:
            reply = error_reply(req_id, "rejected", str(exc))
        except (UnicodeError, OverflowError, RecursionError) as exc:
            # malformed values that got past the checks above: the client's fault, not ours
            reply = error_reply(req_id, "bad_request", f"bad value: {exc}"[:200], "bad_value")
        except Exception as exc:  # a bug must not take the connection (or robot) down
            log.exception("internal error handling %r", line[:200])
            reply = error_reply(req_id, "internal", f"internal error: {type(exc).__name__}")
        if self._token is None and not c.session:
            err = reply.get("error")
            if err is None or err["code"] not in _INVALID_CODES:
                self._promote(c)  # without a token: one valid request admits
        return reply

    async def _execute(self, c: _Client, cmd: str, req: dict[str, Any]) -> dict[str, Any]:
        b = self.backend
        if cmd in MOTION_COMMANDS:
            # validate first, then count: a rejected request changes nothing
            args = self._motion_args(c, cmd, req)
            if cmd == "drive":
                await self._release_ended_drive(c)  # one the robot ended holds no longer
                self._refuse_foreign_drive(c)  # before it counts: it changes nothing
            self._command_seq += 1
            if cmd == "mission.load":
                reply = await _result(b.load_mission(*args))
                # what the file held but x6wd won't use, then the robot's own (the fence)
                notes = [*getattr(args[0], "notes", ()), *reply.get("notes", ())]
                return {**reply, "notes": notes} if notes else reply
            if cmd == "drive":
                # owned from now, before the robot has it: another client's drive arriving
                # meanwhile is refused, not sent after it
                before = self._drive_owner, self._drive_until_s
                self._drive_owner, self._drive_until_s = c, time.monotonic() + args[2]
                self._drive_seq += 1
                self._drives_in_flight += 1
                try:
                    reply = await _result(b.drive(*args))
                except BaseException:
                    if self._drive_owner is c:  # refused: as it was (unless a stop came)
                        self._drive_owner, self._drive_until_s = before
                    raise
                finally:
                    self._drives_in_flight -= 1
                if self._drive_owner is c:  # (a stop that came meanwhile ended it)
                    # the robot's dead-man started when it took the drive, a little later
                    self._drive_until_s = max(self._drive_until_s, time.monotonic() + args[2])
                return reply
            if cmd == "return":  # a Python keyword: the backend's method is return_home
                reply = await _result(b.return_home())
            else:
                reply = await _result(getattr(b, cmd)())
            # start, pause, resume, return took the motors over; one the robot refused
            # raised above and left the drive (and its dead-man) as it was
            self._drive_owner = None
            return reply
        if cmd == "hello":
            return {
                "server": "x6wd",
                "version": __version__,
                "protocol": PROTOCOL_VERSION,
                "auth_required": self._token is not None,
                "authenticated": c.authenticated,
                "tls": self._ssl is not None,
            }
        if cmd == "auth":
            return await self._auth(c, req)
        if cmd == "status":
            if self._token is None:
                # a status is a valid request, which admits a connection without a token:
                # admitted before the figures are taken, the asker is not counted as pending
                self._promote(c)
            st = dict(await self._status())
            st["client"] = {"watching": c.watching, "dropped": c.dropped}
            st["manual_drive"] = self._drive_status(c)
            st["server"] = self.server_stats()
            return st
        if cmd == "stop":
            self._drive_owner = None
            # the motors first: no bookkeeping below (on any client) may skip or delay it.
            # Nothing awaits in between, so no other request runs before the fence is up.
            stopping = self._fire_stop()
            with self._bookkeeping("a stop"):
                if c.taken > c.early_stop_end:  # (one sent ahead fenced the others on arrival)
                    self._stop_fence(c, c.taken)
                self.stops["requested"] += 1
                self._rlog.log("stop requests", logging.INFO, "stop requested by %s", c.peer)
            return dict(await asyncio.shield(stopping))
        if cmd == "watch":
            on = req.get("on", req.get("enable", True))
            if not isinstance(on, bool):
                raise _bad("bad_argument", "'on' must be true or false")
            c.watching = on
            if not on:
                c.events.clear()
            return {"watching": on, "dropped": c.dropped}
        if cmd == "log":
            n = req.get("n", 50)
            if isinstance(n, bool) or not isinstance(n, int) or not 0 <= n <= LOG_TAIL_MAX:
                raise _bad("bad_argument", f"'n' must be an integer 0..{LOG_TAIL_MAX}")
            return {"lines": await _result(b.log_tail(n))}
        raise _Reject("unknown_command", f"unknown command {cmd!r}")  # pragma: no cover

    def _motion_args(self, c: _Client, cmd: str, req: dict[str, Any]) -> tuple[Any, ...]:
        if cmd == "mission.load":
            return (self._waypoints(req),)
        if cmd == "drive":
            duration_s = _number(req, "duration_s", 0.0, 3600.0)
            if duration_s <= 0.0:  # an argument out of range, not a state the robot refuses
                raise _bad("bad_argument", f"'duration_s' must be > 0 s, got {duration_s:g}")
            if c.drive_limit_s is not None:
                duration_s = min(duration_s, c.drive_limit_s)
            return (
                _number(req, "left", -100.0, 100.0),
                _number(req, "right", -100.0, 100.0),
                duration_s,
            )
        return ()

    # -- other transports (the web console's WebSocket) ---------------------------------------
    def detached_client(
        self,
        peer: str,
        host: str,
        *,
        watch_only: bool = False,
        drive_limit_s: float | None = None,
        kind: str = "web console page",
    ) -> _Client:
        """A client of another transport: the same token, throttles and commands as a TCP
        connection, outside the TCP pools (its transport keeps its own), except that before
        ``auth`` only ``hello``, ``auth`` and ``stop`` are open (no ``status``: a page shows
        nothing of the robot without the token). ``watch_only``: every command that acts is
        refused; ``drive_limit_s``: drives last at most this (s); ``kind``: how status and
        refusals name it beside ``peer`` (who drives)."""
        now = self._clock()
        c = _Client(
            writer=None,  # type: ignore[arg-type]  # never written: the transport replies
            peer=peer,
            host=host,
            authenticated=self._token is None,
            tokens=self._bucket(now),
            faults=self._bucket(now),
            session=True,  # never promoted into (nor evicted from) the TCP session pool
            watch_only=watch_only,
            open_commands=DETACHED_OPEN_COMMANDS,
            drive_limit_s=drive_limit_s,
            kind=kind,
        )
        self._fenced.add(c)
        return c

    async def request(self, c: _Client, line: bytes) -> tuple[dict[str, Any], float]:
        """One request line of a detached client: its reply, and how long (s) the transport
        must wait before it reads that client's next request (the back-off after a wrong
        token, the throttle of failing requests), as the TCP read loop does. After the reply,
        ``c.close_reason`` non-empty means: close the connection (too many wrong tokens)."""
        reply = await self.dispatch(c, line)
        wait = 0.0 if reply["ok"] else self._fault_wait(c)
        wait, c.backoff_s = max(wait, c.backoff_s), 0.0
        if c.close_reason:
            self._count_close(c, c.close_reason, f"{c.auth_failures} failed authentications")
        return reply, wait

    # -- stop and status: shared backend calls ----------------------------------------------
    def _fire_stop(self) -> asyncio.Future[Any]:
        """The stop to wait for: the one in flight when no command reached the backend since
        it was sent (its effect covers this request too), else a new one sent now. So a
        storm of stops keeps at most one in flight, and a stop is never answered by one that
        a later ``drive`` or ``start`` overtook."""
        self._drive_owner = None  # any stop ends the manual drive, and its ownership
        shared = self._stop_call
        f = shared.future
        if f is not None and not f.done() and shared.seq == self._command_seq:
            self.stops["coalesced"] += 1
            return f
        self.stops["sent"] += 1
        f = self._call_now(self.backend.stop)
        shared.future, shared.seq = f, self._command_seq
        return f

    async def _status(self) -> Any:
        """The backend's status, shared by concurrent requesters and reused for
        :data:`STATUS_REUSE_S` when no command (stop included) came in since: a crowd asking
        ``status`` cannot load the control loop, and no reply predates a command."""
        shared = self._status_call
        f = shared.future
        reusable = (
            f is not None
            and shared.seq == self._command_seq
            and shared.stops_sent == self.stops["sent"]
            # real time, not the injected clock: this sheds load, it is no protocol deadline
            and (not f.done() or time.monotonic() - shared.t_done_s < STATUS_REUSE_S)
        )
        if not reusable or f is None:
            f = self._call_now(self.backend.status)
            shared.future, shared.seq, shared.stops_sent = f, self._command_seq, self.stops["sent"]

            def done(_f: asyncio.Future[Any], shared: _Shared = shared) -> None:
                shared.t_done_s = time.monotonic()

            f.add_done_callback(done)
        return await asyncio.shield(f)

    @staticmethod
    def _call_now(fn: Callable[[], Any]) -> asyncio.Future[Any]:
        """Call the backend now (its side effects start at once) and return its result as a
        future several requesters can await."""
        try:
            value = fn()
        except Exception as exc:
            f: asyncio.Future[Any] = asyncio.get_running_loop().create_future()
            f.set_exception(exc)
        else:
            f = asyncio.ensure_future(_result(value))
        f.add_done_callback(_retrieve)
        return f

    # -- authentication --------------------------------------------------------------------
    async def _auth(self, c: _Client, req: dict[str, Any]) -> dict[str, Any]:
        token = req.get("token")
        if not isinstance(token, str):
            raise _bad("bad_argument", "'token' must be a string")
        try:
            given = token.encode("utf-8")
        except UnicodeEncodeError:
            raise _bad("bad_unicode", "'token' is not valid Unicode") from None
        if self._token is None:
            c.authenticated = True
            self._promote(c)
            return {"authenticated": True}
        budget = self._auth_budget(c.host)
        if budget.refill(self._clock()) < 1.0:
            # this address has failed too often: every attempt from it is evaluated only
            # after a delay. Each waits in its own task (no queue), so a guesser cannot make
            # an operator on the same address wait longer than this.
            await self._nap(c, self.config.auth_fail_delay_s)
        ok = hmac.compare_digest(hashlib.sha256(given).digest(), self._token_digest)
        if not ok:
            budget.refill(self._clock())
            budget.level = max(0.0, budget.level - 1.0)
            c.authenticated = False
            c.auth_failures += 1
            self.auth_failed_total += 1
            # doubling per failure: the next line from this connection is read only then
            c.backoff_s = min(
                MAX_AUTH_BACKOFF_S, self.config.auth_fail_delay_s * 2.0 ** (c.auth_failures - 1)
            )
            if c.auth_failures >= self.config.max_auth_failures:
                c.close_reason = "auth_failures"
            self._rlog.log(
                "failed authentications",
                logging.WARNING,
                "failed authentication from %s (%d on this connection)",
                c.peer,
                c.auth_failures,
            )
            raise _Reject("auth_failed", "wrong token")
        c.authenticated = True
        self._promote(c)
        return {"authenticated": True}

    def _auth_budget(self, host: str) -> _Bucket:
        budgets = self._auth_budgets
        b = budgets.get(host)
        if b is None:
            b = _Bucket(AUTH_FAIL_REFILL_PER_S, AUTH_FAIL_BUDGET, AUTH_FAIL_BUDGET, self._clock())
            budgets[host] = b
            if len(budgets) > MAX_TRACKED_ADDRESSES:
                budgets.popitem(last=False)  # bounded memory: forget the least recent address
        else:
            budgets.move_to_end(host)
        return b

    # -- arguments -------------------------------------------------------------------------
    @staticmethod
    def _waypoints(req: dict[str, Any]) -> list[Waypoint]:
        given = [k for k in MISSION_KEYS if k in req]
        if len(given) != 1:
            raise _bad(
                "bad_argument",
                "give exactly one of 'waypoints', 'gpx', 'csv', 'wpl', 'kml' or 'plan'",
            )
        key = given[0]
        if key == "waypoints":
            pairs = req[key]
            if not isinstance(pairs, list):
                raise _bad("bad_argument", "'waypoints' must be a list of [lat, lon] pairs")
            for i, item in enumerate(pairs):
                if isinstance(item, dict):
                    values = [item[k] for k in ("lat", "lon") if k in item]
                else:
                    values = item
                if not isinstance(values, list) or not all(
                    isinstance(v, (int, float)) and not isinstance(v, bool) for v in values
                ):
                    raise _bad(
                        "bad_argument",
                        f'waypoints[{i}]: expected [lat, lon] or {{"lat": .., "lon": ..}} '
                        "with numbers (degrees)",
                    )
                for v in values:  # a JSON integer past a float: OverflowError, bad_value
                    float(v)
            return from_pairs(pairs, "waypoints")
        text = req[key]
        if not isinstance(text, str):
            raise _bad("bad_argument", f"'{key}' must be the file content as a string")
        parse = {
            "gpx": parse_gpx,
            "csv": parse_csv,
            "wpl": parse_wpl,
            "kml": parse_kml,
            "plan": parse_plan,
        }[key]
        return parse(text)
