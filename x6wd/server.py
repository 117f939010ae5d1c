"""Remote-control protocol server: JSON lines over TCP (optionally TLS). See docs/protocol.md.

One request per line ``{"id": .., "cmd": "..", ...}``, exactly one reply per request
(``{"id": .., "ok": true, ...}`` or ``{"id": .., "ok": false, "error": {"code", "message"}}``),
and ``{"event": ...}`` lines for clients that asked to watch. The server owns the protocol
(framing, limits, authentication, watch fan-out); what the commands DO is delegated to a
:class:`Backend` (the daemon), called on the event loop.

Isolation: every client has its own reader and writer task; telemetry goes into a bounded
per-client queue (oldest dropped and counted), so a slow or stuck client never delays the
publisher, which is the control loop.
"""

from __future__ import annotations

import asyncio
import contextlib
import hmac
import inspect
import ipaddress
import json
import logging
import ssl
import stat
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

from x6wd import __version__
from x6wd.config import ServerConfig
from x6wd.errors import ConfigError, ParseError, X6wdError
from x6wd.lineserver import LineClient, LineServer
from x6wd.mission_files import Waypoint, from_pairs, parse_csv, parse_gpx

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
    "stop",
    "drive",
    "watch",
    "log",
)
MAX_PENDING_REPLIES = 64
LOG_TAIL_MAX = 1000


class CommandError(X6wdError):
    """A request the robot refuses; ``code`` is the protocol error code."""

    def __init__(self, code: str, message: str) -> None:
        super().__init__(message)
        self.code = code


class Backend(Protocol):
    """What the server needs from the daemon. Methods are called on the server's loop and must
    not block; each returns its result (a JSON-ready dict merged into the reply; a list of
    lines for ``log_tail``) or an awaitable of it (the daemon runs commands on its control
    loop). Raise :class:`CommandError` (or any X6wdError, reported as ``rejected``) to refuse.
    """

    def status(self) -> Any: ...
    def load_mission(self, waypoints: list[Waypoint]) -> Any: ...
    def start(self) -> Any: ...
    def pause(self) -> Any: ...
    def resume(self) -> Any: ...
    def stop(self) -> Any: ...
    def drive(self, left_pct: float, right_pct: float, duration_s: float) -> Any: ...
    def log_tail(self, n: int) -> Any: ...


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
    token = p.read_bytes().strip()
    if len(token) < 8:
        raise ConfigError(f"server.token_file: {p}: token shorter than 8 bytes")
    return token


def server_ssl_context(cert: str, key: str) -> ssl.SSLContext:
    """TLS context for the server from PEM certificate and key paths (TLS 1.2+)."""
    ctx = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
    ctx.minimum_version = ssl.TLSVersion.TLSv1_2
    try:
        ctx.load_cert_chain(cert, key)
    except (OSError, ssl.SSLError) as exc:
        raise ConfigError(f"server.tls_cert/tls_key: cannot load {cert}, {key}: {exc}") from None
    return ctx


def is_loopback(host: str) -> bool:
    """True for localhost / 127.0.0.0/8 / ::1 binds."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def encode(obj: dict[str, Any]) -> bytes:
    """One protocol line (compact JSON + LF)."""
    return json.dumps(obj, separators=(",", ":"), allow_nan=False).encode() + b"\n"


def error_reply(req_id: Any, code: str, message: str) -> dict[str, Any]:
    """The error reply object."""
    return {"id": req_id, "ok": False, "error": {"code": code, "message": message}}


class _Reject(Exception):
    def __init__(self, code: str, message: str) -> None:
        super().__init__(message)
        self.code = code


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
    peer: str
    authenticated: bool
    tokens: _Bucket  # requests
    faults: _Bucket  # error replies (same rate and burst)
    watching: bool = False


async def _result(value: Any) -> Any:
    """A backend result, awaited when the backend runs it on another loop (the daemon)."""
    if inspect.isawaitable(value):
        return await value
    return value


def _number(args: dict[str, Any], key: str, lo: float, hi: float) -> float:
    v = args.get(key)
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise _Reject("bad_request", f"'{key}' must be a number")
    v = float(v)
    if not lo <= v <= hi:  # also rejects NaN
        raise _Reject("bad_request", f"'{key}' must be within {lo:g}..{hi:g}, got {v:g}")
    return v


class ControlServer(LineServer[_Client]):
    """The remote-control endpoint. :meth:`publish` is called from the loop and never waits."""

    def __init__(
        self,
        config: ServerConfig,
        backend: Backend,
        *,
        token: bytes | None = None,
        ssl_context: ssl.SSLContext | None = None,
        clock: Any = time.monotonic,
    ) -> None:
        """``token`` None: no authentication (refused unless bound to loopback)."""
        if token is None and not is_loopback(config.bind):
            raise ConfigError(
                f"server.token_file: required when server.bind ({config.bind}) is not loopback"
            )
        super().__init__(config.port)
        self.config = config
        self.backend = backend
        self._token = token
        self._ssl = ssl_context
        self._clock = clock
        self.requests_total = 0
        self.errors_total = 0
        self.rejected_connections = 0

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
        self._server = await asyncio.start_server(
            self._handle, self.config.bind, self._configured_port, ssl=self._ssl
        )
        log.info(
            "control server listening on %s:%d%s",
            self.config.bind,
            self.port,
            " (TLS)" if self._ssl else "",
        )

    def publish(self, event: dict[str, Any]) -> None:
        """Queue an ``{"event": ..}`` line for every watching client (drop-oldest when full)."""
        watchers = [c for c in self._clients if c.watching and not c.closed]
        if not watchers:
            return
        line = encode(event)
        maxlen = self.config.queue_len
        for c in watchers:
            if c.put(line, maxlen):
                self.dropped_total += 1

    # -- per-connection -------------------------------------------------------------------
    async def _handle(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        task = asyncio.current_task()
        if task is not None:
            self._tasks.add(task)
        peer = str(writer.get_extra_info("peername"))
        now = self._clock()
        c = _Client(
            writer=writer,
            peer=peer,
            authenticated=self._token is None,
            tokens=self._bucket(now),
            faults=self._bucket(now),
        )
        sender: asyncio.Task[None] | None = None
        try:
            if len(self._clients) >= self.config.max_clients:
                self.rejected_connections += 1
                msg = f"server full ({self.config.max_clients} clients)"
                writer.write(encode(error_reply(None, "too_many_clients", msg)))
                with contextlib.suppress(OSError, asyncio.TimeoutError):
                    await asyncio.wait_for(writer.drain(), 1.0)
                return
            self._clients.add(c)
            sender = asyncio.create_task(self._sender(c))
            await self._read_loop(reader, c)
        except (ConnectionError, OSError, ssl.SSLError):
            pass
        except asyncio.CancelledError:
            pass  # close(): a finished (not cancelled) task keeps asyncio's stream callback quiet
        finally:
            await self._hang_up(c, sender, task)

    def _bucket(self, now: float) -> _Bucket:
        burst = max(5.0, self.config.rate_per_s)
        return _Bucket(self.config.rate_per_s, burst, burst, now)

    async def _read_loop(self, reader: asyncio.StreamReader, c: _Client) -> None:
        limit = self.config.max_line_bytes
        buf = bytearray()
        discarding = False
        rate = float(self.config.input_bytes_per_s)
        burst = max(rate, 2.0 * limit)
        budget = _Bucket(rate, burst, burst, self._clock())
        while not c.closed:
            chunk = await reader.read(65536)
            if not chunk:
                return
            budget.refill(self._clock())
            budget.level -= len(chunk)
            if budget.level < 0:
                # a flood: stop reading this client for a while (only it waits)
                await asyncio.sleep(-budget.level / rate)
            buf += chunk
            while True:
                nl = buf.find(b"\n")
                if nl < 0:
                    if len(buf) > limit:
                        if not discarding:
                            self._reply(c, error_reply(None, "line_too_long", self._too_long()))
                        discarding = True
                        buf.clear()
                    break
                line = bytes(buf[:nl])
                del buf[: nl + 1]
                if discarding:
                    discarding = False  # the rest of an oversized line
                    continue
                if len(line) > limit:
                    reply = error_reply(None, "line_too_long", self._too_long())
                elif line.strip():
                    reply = await self.dispatch(c, line)
                else:
                    continue
                self._reply(c, reply)
                if not reply["ok"]:
                    wait = self._fault_wait(c)
                    if wait > 0.0:
                        # a client whose requests keep failing is read at the request rate:
                        # each line still gets its reply, only later (only it waits)
                        await asyncio.sleep(wait)
            while len(c.replies) > MAX_PENDING_REPLIES and not c.closed:
                # a client that asks without reading waits here, alone
                c.drained.clear()
                await c.drained.wait()

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

    def _too_long(self) -> str:
        return f"request line longer than {self.config.max_line_bytes} bytes"

    def _reply(self, c: _Client, obj: dict[str, Any]) -> None:
        if not obj.get("ok", False):
            self.errors_total += 1
        c.reply(encode(obj))

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
            try:
                req = json.loads(line)
            except (json.JSONDecodeError, UnicodeDecodeError) as exc:
                raise _Reject("bad_json", f"not valid JSON: {exc}") from None
            if not isinstance(req, dict):
                raise _Reject("bad_request", "a request must be a JSON object")
            req_id = req.get("id")
            if isinstance(req_id, (dict, list)):
                req_id = None
                raise _Reject("bad_request", "'id' must be a string, number or null")
            cmd = req.get("cmd")
            if not isinstance(cmd, str):
                raise _Reject("bad_request", "missing 'cmd' (a string)")
            if cmd not in COMMANDS:
                raise _Reject(
                    "unknown_command", f"unknown command {cmd!r} (valid: {', '.join(COMMANDS)})"
                )
            # stop must always get through: it is the operator's emergency brake
            if cmd != "stop" and not self._take_token(c):
                raise _Reject("rate_limited", f"more than {self.config.rate_per_s:g} requests/s")
            if not c.authenticated and cmd not in UNAUTHENTICATED_COMMANDS:
                raise _Reject("unauthorized", f"authenticate first to use {cmd!r}")
            result = await self._execute(c, cmd, req)
            return {"id": req_id, "ok": True, **result}
        except _Reject as exc:
            return error_reply(req_id, exc.code, str(exc))
        except CommandError as exc:
            return error_reply(req_id, exc.code, str(exc))
        except ParseError as exc:
            return error_reply(req_id, "bad_request", str(exc))
        except X6wdError as exc:
            return error_reply(req_id, "rejected", str(exc))
        except Exception as exc:  # a bug must not take the connection (or robot) down
            log.exception("internal error handling %r", line[:200])
            return error_reply(req_id, "internal", f"internal error: {type(exc).__name__}")

    async def _execute(self, c: _Client, cmd: str, req: dict[str, Any]) -> dict[str, Any]:
        b = self.backend
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
            token = req.get("token")
            if not isinstance(token, str):
                raise _Reject("bad_request", "'token' must be a string")
            if self._token is None:
                c.authenticated = True
                return {"authenticated": True}
            if not hmac.compare_digest(token.encode("utf-8"), self._token):
                c.authenticated = False
                log.warning("failed authentication from %s", c.peer)
                raise _Reject("auth_failed", "wrong token")
            c.authenticated = True
            return {"authenticated": True}
        if cmd == "status":
            st = dict(await _result(b.status()))
            st["client"] = {"watching": c.watching, "dropped": c.dropped}
            st["server"] = {"clients": len(self._clients), "dropped": self.dropped_total}
            return st
        if cmd == "mission.load":
            return await _result(b.load_mission(self._waypoints(req)))
        if cmd == "start":
            return await _result(b.start())
        if cmd == "pause":
            return await _result(b.pause())
        if cmd == "resume":
            return await _result(b.resume())
        if cmd == "stop":
            return await _result(b.stop())
        if cmd == "drive":
            left = _number(req, "left", -100.0, 100.0)
            right = _number(req, "right", -100.0, 100.0)
            duration = _number(req, "duration_s", 0.0, 3600.0)
            return await _result(b.drive(left, right, duration))
        if cmd == "watch":
            on = req.get("on", req.get("enable", True))
            if not isinstance(on, bool):
                raise _Reject("bad_request", "'on' must be true or false")
            c.watching = on
            if not on:
                c.events.clear()
            return {"watching": on, "dropped": c.dropped}
        if cmd == "log":
            n = req.get("n", 50)
            if isinstance(n, bool) or not isinstance(n, int) or not 0 <= n <= LOG_TAIL_MAX:
                raise _Reject("bad_request", f"'n' must be an integer 0..{LOG_TAIL_MAX}")
            return {"lines": await _result(b.log_tail(n))}
        raise _Reject("unknown_command", f"unknown command {cmd!r}")  # pragma: no cover

    @staticmethod
    def _waypoints(req: dict[str, Any]) -> list[Waypoint]:
        given = [k for k in ("waypoints", "gpx", "csv") if k in req]
        if len(given) != 1:
            raise _Reject("bad_request", "give exactly one of 'waypoints', 'gpx' or 'csv'")
        key = given[0]
        if key == "waypoints":
            return from_pairs(req[key], "waypoints")
        text = req[key]
        if not isinstance(text, str):
            raise _Reject("bad_request", f"'{key}' must be the file content as a string")
        return parse_gpx(text) if key == "gpx" else parse_csv(text)
