"""The operator's web console: one page (static HTML/JS/CSS, no build, no CDN) and a
WebSocket that carries the control protocol (docs/protocol.md) plus live events.

Every request from the page goes through :meth:`ControlServer.request`, so the console has
exactly the control port's token, throttles and commands (one dispatcher); the page's own
connection is a *detached* client of that server. What the console adds:

- events pushed to authenticated pages: ``telemetry`` and ``state`` (as ``watch`` sends
  them), ``sky`` (satellites with their C/N0), ``map`` (mission, launch point, geofence);
- ``mission.parse``: a mission file's content (GPX, CSV, QGC WPL, KML) read into waypoints
  for the page's editor, without touching the robot;
- ``recording.list`` and ``recording.view``: the runs the recorder wrote on the robot and one
  of them as the log viewer's self-contained page (:func:`x6wd.app.logview.render_html`);
- the dead-man for manual drive: a page's drive lasts at most ``console.deadman_s`` (the
  page repeats it while a key is held), and a page that goes away while its drive runs gets
  its motors stopped at once; a drive that arrives more than ``deadman_s`` late (by the
  page's ``sent_ms``: held in a stalled link) is refused, not replayed; a stop from
  another client ends a held drive: a drive whose press began before it or less than
  ``deadman_s`` after it (the page's ``press_ms``, else the press the console infers from
  the page's drives) is refused, and logged once per press;
- ``console.watch_only``: every command that acts (``stop`` too) is refused by the server;
- cross-origin WebSockets are refused: another site open in the operator's browser must not
  be able to reach the robot through it.
"""

from __future__ import annotations

import asyncio
import base64
import collections
import concurrent.futures
import contextlib
import hashlib
import ipaddress
import logging
import math
import re
import socket
import ssl
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

from aiohttp import WSCloseCode, WSMsgType, web

from x6wd import __version__
from x6wd.app.lineserver import (
    close_promptly,
    reset,
    silent,
    unanswered,
    whole_request_queued,
    write_buffer_size,
)
from x6wd.app.logview import LogView, html_page, render_html
from x6wd.app.server import (
    SUPERSEDED_COMMANDS,
    ControlServer,
    encode,
    error_reply,
    is_loopback,
    parse_request,
)
from x6wd.core.config import HOSTNAME_PATTERN, ConsoleConfig
from x6wd.core.errors import ConfigError, DeviceUnavailable, ParseError
from x6wd.core.mission_files import PARSERS, parse_content
from x6wd.core.ratelog import RateLimitedLog
from x6wd.core.recorder import RecordingFile, list_recordings, recording_writer
from x6wd.core.records import GpsSky

log = logging.getLogger(__name__)

STATIC_DIR = Path(__file__).resolve().parent / "static"
HEARTBEAT_S = 5.0
"""WebSocket ping period (s): a link that died without a FIN is found within ~2 periods (the
motors have long stopped by then: a drive lasts ``deadman_s``). A page whose pong has not
come half a period after a ping is closed (aiohttp's heartbeat): a page that does not read
(or whose link is gone) is closed this way, counted in ``slow_pages`` and logged."""
SEND_TIMEOUT_S = 10.0
"""A page that takes no data for this long (s) is closed (its events are dropped before)."""
MAP_CHECK_S = 0.5
"""How often (s) the mission, launch point and geofence are compared with what pages have."""
STOP_LINE = b'{"id":null,"cmd":"stop"}'
TRACK_POINTS = 5000
"""Positions the console keeps for a page opened later (the robot's track, oldest dropped)."""
TRACK_STEP_M = 0.5
"""A position is kept when it is this far (m) from the last one kept."""
M_PER_DEG = 111_195.0  # mean metres per degree of latitude: the track's thinning only


def _viewer_style_sources() -> str:
    """CSP sources for the log viewer's own inline styles (its <style> element and style
    attributes, by their SHA-256): its page, shown in a srcdoc frame, lives under the
    console's policy, and ``'unsafe-inline'`` would open the console to any style."""
    page = html_page(LogView(path=Path("x.jsonl"), kind="recording"))
    styles = re.findall(r"<style>(.*?)</style>", page, re.S)
    attrs = re.findall(r' style="([^"]*)"', page)

    def h(text: str) -> str:
        return "'sha256-" + base64.b64encode(hashlib.sha256(text.encode()).digest()).decode() + "'"

    # 'unsafe-hashes': hashes that match style attributes too (only these exact ones)
    return " ".join([*map(h, styles), *(["'unsafe-hashes'"] if attrs else []), *map(h, attrs)])


VIEWER_STYLES = _viewer_style_sources()


@dataclass(eq=False)
class _Page:
    """One open page: its WebSocket, its control-protocol client, its outboxes."""

    ws: web.WebSocketResponse
    client: Any  # the ControlServer's detached client
    peer: str
    replies: collections.deque[str] = field(default_factory=collections.deque)
    events: collections.deque[str] = field(default_factory=collections.deque)
    wake: asyncio.Event = field(default_factory=asyncio.Event)
    dropped: int = 0
    map_sent: Any = None
    transport: Any = None  # its connection's (kept open when connections are capped)
    # the clocks' offset: min(arrival - page's sent_ms) over a recent window (see _late_s):
    # the minimum over this period and over the one before it
    clock_offset_s: float = math.inf
    offset_now_s: float = math.inf
    offset_before_s: float = math.inf
    offset_period_s: float = -math.inf  # when this period began (time.monotonic())
    busy: bool = False  # a request of it is being handled or sleeps out its back-off
    held: int = 0  # bytes charged for its messages read, not handled yet (_message_cost)
    queued: int = 0  # its messages read, not handled yet
    room: asyncio.Event = field(default_factory=asyncio.Event)  # held went down
    # its drives without press_ms, taken as one press while less than deadman_s apart (by
    # their send time, this clock; see _press_s): the send time of the first of them the
    # robot carried out or refused because of another client's stop (inf: none yet), of
    # the latest, and of the one being handled
    run_start_s: float = math.inf
    run_last_s: float = -math.inf
    drive_sent_s: float = math.inf
    last_drove_s: float = -math.inf  # the send time of its latest drive carried out
    logged_press: Any = None  # the press whose refusal (another client's stop) was logged
    slow: bool = False  # closed for not reading (counted once)


OFFSET_PERIOD_S = 5.0
"""The clocks' offset is the least (arrival - ``sent_ms``) over the current period of this
length and the one before it (a window of 5-10 s of messages; a page asks ``status`` every
second): a page clock running slow or fast is followed (1 % off: under 0.1 s of error), and
one absurd ``sent_ms`` (a far-future one: every later message late, refused) is forgotten
within 10 s. A period begins only with a message, so messages held in a stalled link, however
long the stall, are judged against the offset of the messages that came before it."""

MESSAGE_COST_B = 1024
"""What one queued page message is charged against ``max_message_bytes`` besides its bytes:
its objects take a few hundred bytes however short it is, so empty messages sent during a
back-off could otherwise queue without end (an outside check: 2 MB/s of daemon memory)."""


PRE_AUTH_MESSAGE_BYTES = 4096
"""The largest message (bytes) a page may send before its ``auth`` succeeds: then only
``hello``, ``auth`` and ``stop`` are taken, each well under this, and a larger one closes
the page (1009) before it is parsed. An outside audit: 8 unauthenticated pages sending
200 KB messages raised the control port's stop round trip from 2 ms to 83-461 ms, each
message parsed before the throttle refused it. After ``auth``: ``max_message_bytes``."""
REFUSE_CLOSE_S = 1.0
"""How long (s) a page closed for a large message before ``auth`` gets to answer the close."""


def _message_cost(line: bytes) -> int:
    return len(line) + MESSAGE_COST_B


CONNECTION_SLACK = 16
"""HTTP connections allowed beyond ``max_clients`` pages (a browser opens up to 6 per host
for a page's files). Past them one that is not a page's WebSocket is closed
(:func:`_eviction_choice`: half-sent requests first): idle connections cannot take the
process's file descriptors, and with them the control port where the operator's stop
arrives."""

HANDSHAKE_TIMEOUT_S = 10.0
"""With TLS: a connection whose handshake has not finished within this (s) is closed."""


def _http_stage(handler: Any) -> int:
    """How far an aiohttp connection has got, for the cap (:func:`_eviction_choice`): 0 no
    whole request head received yet (silent, or headers half sent), 1 between requests
    (kept alive), 2 a request being handled or answered (its response being written, or
    a whole request waiting). aiohttp keeps these in its handler's private fields: when
    one is missing (another aiohttp), every connection is 1, which is oldest first."""
    if getattr(handler, "_request_in_progress", False) or getattr(handler, "_messages", None):
        return 2
    transport = getattr(handler, "transport", None)
    if transport is not None and write_buffer_size(transport) > 0:
        return 2  # a response written, not handed to the kernel yet
    return 0 if getattr(handler, "_request_count", None) == 0 else 1


def _peer_host(transport: asyncio.BaseTransport) -> str:
    peer = transport.get_extra_info("peername")
    return str(peer[0]) if isinstance(peer, tuple) and peer else "?"


def _eviction_choice(
    handlers: list[Any], opening: Any, pages: set[Any]
) -> asyncio.Transport | None:
    """The connection the cap closes (None: none but ``opening``, the one being opened now,
    is open and not a page's WebSocket): the first by stage (:func:`_http_stage`: half-sent
    requests before idle kept-alive connections before those answering a request, so a
    churn of half-open connections never cuts a page's files mid-transfer, the audit's
    ContentLengthError), then from the peer address that holds the most connections, then
    the oldest. ``handlers``: aiohttp's, oldest first."""
    open_ = [
        (i, h, h.transport)
        for i, h in enumerate(handlers)
        if h.transport is not None and not h.transport.is_closing()
    ]
    held = collections.Counter(_peer_host(t) for _, _, t in open_)
    best: tuple[int, int, int] | None = None
    choice = None
    for i, h, t in open_:
        if h is opening or t in pages:
            continue
        key = (_http_stage(h), -held[_peer_host(t)], i)
        if best is None or key < best:
            best, choice = key, t
    return choice


RECORDINGS_TIMEOUT_S = 5.0
"""``recording.list`` (and the look-up of ``recording.view``'s name) waits at most this (s)
for the recordings folder: a hung SD card or network mount is an error reply, never a
frozen network loop."""

RENDER_TIMEOUT_S = 60.0
"""``recording.view`` waits at most this (s) for the viewer's page of a run."""


_HOST_RE = re.compile(
    rf"(?:(?P<name>{HOSTNAME_PATTERN})"
    r"|\[(?P<ipv6>[0-9a-f:.]+)\])(?::(?P<port>[0-9]{1,5}))?",
    re.ASCII | re.IGNORECASE,
)
"""A ``Host`` as a browser sends it: a hostname (or dotted IPv4; ``_`` allowed, as
``[console] hostnames`` allows it) or a bracketed IPv6, and an optional port of digits.
Nothing else (no user@, no spaces, no ``;``, no zone id)."""


def allowed_host(host_header: str, names: frozenset[str]) -> bool:
    """Whether the Host of a request is a well-formed host[:port] that names this console: an
    IP address (a rebound name never is one), or one of ``names`` (lower case, without the
    port). Only such a Host is ever copied into a response header."""
    m = _HOST_RE.fullmatch(host_header)
    if m is None or len(host_header) > 261 or int(m["port"] or 0) > 65535:
        return False
    if m["ipv6"] is not None:
        try:
            ipaddress.IPv6Address(m["ipv6"])
        except ValueError:
            return False
        return True
    host = m["name"].lower()
    if host in names:
        return True
    try:
        ipaddress.IPv4Address(host)
    except ValueError:
        return False
    return True


def _origin_ok(request: web.Request) -> bool:
    """A WebSocket from the console's own page (or from a program that sends no Origin)."""
    origin = request.headers.get("Origin")
    if origin is None:
        return True
    parts = urlsplit(origin)
    return parts.scheme in ("http", "https") and parts.netloc.lower() == request.host.lower()


def sky_event(sky: GpsSky) -> dict[str, Any]:
    """The ``sky`` event: satellites in view (PRN, elevation, azimuth, C/N0 dB-Hz, used)."""
    return {
        "event": "sky",
        "hdop": sky.hdop,
        "pdop": sky.pdop,
        "satellites": [
            {
                "prn": s.prn,
                "el_deg": s.el_deg,
                "az_deg": s.az_deg,
                "cn0_dbhz": s.snr_dbhz,
                "used": s.used,
            }
            for s in sky.satellites
        ],
    }


class _Handshake(asyncio.Protocol):
    """A console connection over TLS, counted from its accept: the handshake runs here
    (:meth:`ConsoleServer._handshake_gate`), then aiohttp's handler gets the TLS transport.
    aiohttp's own TLS listener counts a connection only once its handshake is done (the
    default handshake timeout: 60 s), so peers that never send a ClientHello were in no
    count and could take the process's file descriptors."""

    def __init__(self, console: ConsoleServer, factory: Callable[[], asyncio.Protocol]) -> None:
        self.console = console
        self.factory = factory
        self.transport: asyncio.Transport | None = None

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        assert isinstance(transport, asyncio.Transport)
        transport.pause_reading()  # the ClientHello stays for the handshake
        self.transport = transport
        self.console._handshake_started(self)
        if not transport.is_closing():
            task = asyncio.create_task(self._upgrade(transport))
            self.console._handshake_tasks.add(task)
            task.add_done_callback(self.console._handshake_tasks.discard)

    def connection_lost(self, exc: Exception | None) -> None:  # (before the handshake began)
        self.console._handshaking.pop(self, None)

    async def _upgrade(self, transport: asyncio.Transport) -> None:
        ctx = self.console._ssl
        assert ctx is not None
        try:
            if transport.is_closing():  # reset before its turn came (the cap, or closing)
                return
            handler = self.factory()
            tls = await asyncio.get_running_loop().start_tls(
                transport, handler, ctx, server_side=True,
                ssl_handshake_timeout=HANDSHAKE_TIMEOUT_S,
            )  # fmt: skip
        except (OSError, ssl.SSLError, EOFError):  # failed, timed out, reset: closed
            return
        finally:
            self.console._handshaking.pop(self, None)
        if tls is not None:  # None: closed meanwhile (evicted, or the console closing)
            handler.connection_made(tls)


class _TlsSite(web.TCPSite):
    """aiohttp's TCP site with TLS begun per connection once it is counted (_Handshake)."""

    __slots__ = ("_gate",)

    def __init__(
        self, runner: web.AppRunner, host: str, port: int, *, ssl_context: ssl.SSLContext,
        gate: Callable[[], asyncio.Protocol],
    ) -> None:  # fmt: skip
        super().__init__(runner, host, port, ssl_context=ssl_context)
        self._gate = gate

    async def start(self) -> None:
        await web.BaseSite.start(self)  # registers the site with its runner
        self._server = await asyncio.get_running_loop().create_server(
            self._gate,
            self._host,
            self._port,
            backlog=self._backlog,
            reuse_address=self._reuse_address,
            reuse_port=self._reuse_port,
        )
        sockets = self._server.sockets
        self._bound_port = sockets[0].getsockname()[1] if sockets else self._port


@dataclass(frozen=True)
class _Run:
    """One run in the recordings folder, as ``recording.list`` gives it."""

    path: Path  # its first remaining part (the name the list gives)
    size: int  # that part's bytes
    # a recorder still writes it (this daemon's current run, or another process's: its
    # last part's lock held, or the one before it while a rotation moves the lock)
    in_progress: bool


class ConsoleServer:
    """HTTP + WebSocket server on the daemon's network loop. :meth:`publish` and
    :meth:`publish_sky` are called on that loop and never wait."""

    def __init__(
        self,
        config: ConsoleConfig,
        control: ControlServer,
        map_view: Callable[[], dict[str, Any]],
        *,
        ssl_context: ssl.SSLContext | None = None,
        recordings_dir: Path | None = None,
    ) -> None:
        """``map_view()``: the mission, launch point and geofence as a JSON-ready dict (read
        from the network thread: it must only read immutable snapshots). ``recordings_dir``:
        the recorder's folder (None: no recordings to show)."""
        if not control.auth_required and not is_loopback(config.bind):
            raise ConfigError(
                f"console.bind: {config.bind} is not loopback: the console needs the control "
                "server's token (server.token_file)"
            )
        self.config = config
        self.control = control
        self._map_view = map_view
        self._ssl = ssl_context
        self._recordings_dir = recordings_dir
        self._pages: dict[_Page, None] = {}  # open pages, oldest first
        self._runner: web.AppRunner | None = None
        self._closing: set[asyncio.Task[Any]] = set()
        self._ticker: asyncio.Task[None] | None = None
        self.port = 0
        self.dropped_total = 0
        self.deadman_stops = 0
        self.refused_hosts = 0  # requests whose Host named no name of this console
        self.connections_closed = 0  # idle HTTP connections closed to stay within the cap
        self.slow_pages = 0  # pages closed for not reading (no pong, or data not taken)
        self._rlog = RateLimitedLog(log, 1.0)  # closes are logged at most once per second
        self.late_drives = 0  # drives refused for arriving later than they would have lasted
        self.held_drives_stopped = 0  # drives refused: their press began before another's stop
        me = socket.gethostname().lower()
        self._hostnames = frozenset(
            {"localhost", me, f"{me}.local", *(n.lower() for n in config.hostnames)}
        )
        self.track: collections.deque[tuple[float, float]] = collections.deque(maxlen=TRACK_POINTS)
        self._handshaking: dict[_Handshake, None] = {}  # TLS handshakes under way, oldest first
        self._handshake_tasks: set[asyncio.Task[None]] = set()
        # the recordings folder is read here, off the network loop: one thread per kind of
        # work, so a hung mount holds two threads at most (no pile of threads, and no
        # default-executor thread the daemon needs)
        self._files = concurrent.futures.ThreadPoolExecutor(
            max_workers=2, thread_name_prefix="x6wd-console-files"
        )
        self._listing: asyncio.Future[dict[str, _Run]] | None = None
        self._hung_logged: set[asyncio.Future[Any]] = set()

    @property
    def url(self) -> str:
        """Where the page is (the bind address and the bound port)."""
        scheme = "https" if self._ssl is not None else "http"
        host = self.config.bind if ":" not in self.config.bind else f"[{self.config.bind}]"
        return f"{scheme}://{host}:{self.port}/"

    # -- lifecycle ----------------------------------------------------------------------------
    async def start(self) -> None:
        """Bind and listen (OSError when the address cannot be had)."""
        app = web.Application(
            client_max_size=self.config.max_message_bytes, middlewares=[self._host_guard]
        )
        app.router.add_get("/", self._index)
        app.router.add_get("/ws", self._websocket)
        app.router.add_static("/static/", STATIC_DIR, follow_symlinks=False)
        app.on_response_prepare.append(self._headers)
        runner = web.AppRunner(app, access_log=None, handle_signals=False, shutdown_timeout=1.0)
        await runner.setup()
        self._cap_connections(runner.server)
        site: web.TCPSite
        if self._ssl is None:
            site = web.TCPSite(runner, self.config.bind, self.config.port)
        else:  # TLS once the connection is counted (_Handshake), not in aiohttp's listener
            factory = runner.server
            site = _TlsSite(
                runner, self.config.bind, self.config.port, ssl_context=self._ssl,
                gate=lambda: _Handshake(self, factory),  # type: ignore[arg-type]
            )  # fmt: skip
        try:
            await site.start()
        except BaseException:
            await runner.cleanup()
            raise
        self._runner = runner
        self.port = int(runner.addresses[0][1])
        self._ticker = asyncio.create_task(self._tick_loop())
        log.info(
            "web console on %s%s",
            self.url,
            " (watch only)" if self.config.watch_only else "",
        )

    @web.middleware
    async def _host_guard(self, request: web.Request, handler: Any) -> web.StreamResponse:
        if allowed_host(request.host, self._hostnames):
            return await handler(request)
        self.refused_hosts += 1
        if self.refused_hosts <= 3 or self.refused_hosts % 100 == 0:
            log.warning(
                "console: refused a request for host %r from %s (%d so far; an expected name"
                " goes in console.hostnames)",
                request.host, request.remote, self.refused_hosts,
            )  # fmt: skip
        return web.Response(status=421, text="unknown host name (console.hostnames)\n")

    def _handshake_started(self, h: _Handshake) -> None:
        """Count a TLS connection from its accept; past ``max_clients`` +
        :data:`CONNECTION_SLACK` handshakes under way, the oldest is reset (a browser's
        completes in milliseconds; one that sends nothing waits to be closed this way or at
        :data:`HANDSHAKE_TIMEOUT_S`)."""
        self._handshaking[h] = None
        cap = self.config.max_clients + CONNECTION_SLACK
        while len(self._handshaking) > cap:
            # the oldest that has sent nothing (not even its ClientHello), then the oldest
            # the console has answered nothing (a byte or a partial ClientHello and a stall),
            # else the oldest: a browser mid-handshake (answered) outlives a flood of either
            # from its own address
            old = next(
                (o for o in self._handshaking if o is not h and silent(o.transport)),
                next(
                    (
                        o
                        for o in self._handshaking
                        if o is not h
                        and unanswered(o.transport)
                        and not whole_request_queued(o.transport)
                    ),
                    next(iter(self._handshaking)),
                ),
            )
            self._handshaking.pop(old, None)
            self.connections_closed += 1
            self._rlog.log(
                "console: connection cap closes",
                logging.WARNING,
                "console: resetting a connection in its TLS handshake: %d handshakes under way"
                " (console.max_clients + %d; connections_closed %d)",
                cap + 1, CONNECTION_SLACK, self.connections_closed,
            )  # fmt: skip
            if old.transport is not None:
                reset(old.transport)

    def _cap_connections(self, server: Any) -> None:
        """Close one connection that is not a page's WebSocket whenever more than
        ``max_clients`` + :data:`CONNECTION_SLACK` are open (checked as each one opens),
        chosen by :func:`_eviction_choice`. The one opening now is closed only when no older
        one can be, and not at once: this runs before aiohttp has started its handler, and a
        connection closed before that fails the handler's task ("Task exception was never
        retrieved ... assert manager is not None", a traceback per close in a connect
        storm)."""
        made = server.connection_made
        cap = self.config.max_clients + CONNECTION_SLACK

        def connection_made(handler: Any, transport: asyncio.Transport) -> None:
            made(handler, transport)
            conns = server.connections  # their handlers, oldest first
            if len(conns) <= cap:
                return
            pages = {page.transport for page in self._pages}
            old = _eviction_choice(conns, handler, pages)
            if old is not None:
                self._cap_close(old, len(conns), False)
                return
            # every other one is a page or closing already: this one goes, once its handler
            # has started (its start is scheduled after this returns; the close, scheduled
            # now, then ends it as any connection the peer closes)
            asyncio.get_running_loop().call_soon(self._cap_close, transport, len(conns), True)

        server.connection_made = connection_made

    def _cap_close(self, transport: asyncio.Transport, open_now: int, opening: bool) -> None:
        """Close a connection to stay within the cap: counted (``connections_closed``) and
        logged at most once per second. An older one is reset: closed at once, whatever it
        had not been sent dropped (a page's, only when every connection is answering a
        request). The one being opened is closed promptly (:func:`close_promptly`; it has
        been sent nothing). A plain TLS close waited up to 30 s for the peer's close_notify,
        which a churn of half-open connections never sends: the console's closing
        connections, still counted, grew to ~400 (the audit's churn) and every new one,
        the page's too, was closed on its arrival."""
        if transport.is_closing():
            return
        self.connections_closed += 1
        peer = transport.get_extra_info("peername")
        self._rlog.log(
            "console: connection cap closes",
            logging.WARNING,
            "console: closing %s: %d connections open (console.max_clients + %d); one that has "
            "not sent a whole request goes first (connections_closed %d)",
            f"{peer[0]}:{peer[1]}" if isinstance(peer, tuple) else "?",
            open_now, CONNECTION_SLACK, self.connections_closed,
        )  # fmt: skip
        if opening:
            close_promptly(transport)
        else:
            reset(transport)

    def _slow_page(self, page: _Page, why: str) -> None:
        """A page closed for not reading: counted (``slow_pages``) and logged at most once
        per second."""
        if page.slow:
            return
        page.slow = True
        self.slow_pages += 1
        self._rlog.log(
            "console: slow page closes",
            logging.WARNING,
            "console: closing %s: %s (slow_pages %d, dropped %d)",
            page.peer, why, self.slow_pages, self.dropped_total,
        )  # fmt: skip

    async def close(self, message: str = "x6wd stopping") -> None:
        """Close every page, each told ``message`` (the WebSocket's close reason, at most
        123 bytes), and stop listening (idempotent)."""
        reason = message.encode("utf-8")[:123]
        if self._ticker is not None:
            self._ticker.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._ticker
            self._ticker = None
        for page in list(self._pages):
            with contextlib.suppress(Exception):
                await page.ws.close(code=1001, message=reason)
        if self._runner is not None:
            await self._runner.cleanup()
            self._runner = None
        for h in list(self._handshaking):
            if h.transport is not None:
                reset(h.transport)
        self._handshaking.clear()
        tasks = [t for t in self._handshake_tasks if not t.done()]
        for t in tasks:
            t.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
        self._files.shutdown(wait=False, cancel_futures=True)  # a hung read is not waited for

    # -- events (from the daemon, on this loop) --------------------------------------------------
    def publish(self, event: dict[str, Any]) -> None:
        """A control-server event (``telemetry``, ``state``) for every authenticated page."""
        if event.get("event") == "telemetry":
            self._keep_track(event.get("data") or {})
        self._broadcast(event)

    def _keep_track(self, tel: dict[str, Any]) -> None:
        """The navigation position every ``TRACK_STEP_M``: a page opened mid-mission draws
        the track so far."""
        lat, lon = tel.get("filt_lat_deg"), tel.get("filt_lon_deg")
        if lat is None or lon is None:
            lat, lon = tel.get("lat_deg"), tel.get("lon_deg")
        if lat is None or lon is None:
            return
        if self.track:
            lat0, lon0 = self.track[-1]
            dn = (lat - lat0) * M_PER_DEG
            de = (lon - lon0) * M_PER_DEG * math.cos(math.radians(lat0))
            if dn * dn + de * de < TRACK_STEP_M * TRACK_STEP_M:
                return
        self.track.append((float(lat), float(lon)))

    def publish_sky(self, sky: GpsSky) -> None:
        """Satellites in view, for the page's sky table."""
        self._broadcast(sky_event(sky))

    def _broadcast(self, event: dict[str, Any]) -> None:
        pages = [p for p in self._pages if p.client.authenticated]
        if not pages:
            return
        text = encode(event).decode()
        for p in pages:
            self._event(p, text)

    def _event(self, page: _Page, text: str) -> None:
        if len(page.events) >= self.config.queue_len:
            page.events.popleft()  # a page that cannot keep up sees the newest
            page.dropped += 1
            self.dropped_total += 1
        page.events.append(text)
        page.wake.set()

    def _reply(self, page: _Page, obj: dict[str, Any]) -> None:
        page.replies.append(encode(obj).decode())
        page.wake.set()

    def _send_map(self, page: _Page, view: dict[str, Any]) -> None:
        page.map_sent = view
        self._event(page, encode({"event": "map", **view}).decode())

    async def _tick_loop(self) -> None:
        """Pages get the map (mission, launch, geofence) whenever it changes."""
        while True:
            await asyncio.sleep(MAP_CHECK_S)
            self._rlog.flush()  # the "N more" of a storm of closes that has stopped
            pages = [p for p in self._pages if p.client.authenticated]
            if not pages:
                continue
            try:
                view = self._map_view()
            except Exception:
                log.exception("console: map view failed")
                continue
            for p in pages:
                if p.map_sent != view:
                    self._send_map(p, view)

    # -- HTTP ---------------------------------------------------------------------------------
    async def _headers(self, request: web.Request, response: web.StreamResponse) -> None:
        tiles = ""
        if self.config.tile_url:
            parts = urlsplit(self.config.tile_url)
            tiles = f" {parts.scheme}://{parts.netloc}"
        # the page's own WebSocket by name, for browsers whose 'self' leaves ws: out; only a
        # Host the guard accepts (a refused one gets its 421 with 'self' alone)
        host = request.headers.get("Host", "")
        sockets = f" ws://{host} wss://{host}" if allowed_host(host, self._hostnames) else ""
        response.headers["Content-Security-Policy"] = (
            f"default-src 'self'; script-src 'self'; style-src 'self' {VIEWER_STYLES}; "
            f"img-src 'self' data:{tiles}; connect-src 'self'{sockets}; "
            "frame-ancestors 'none'; base-uri 'none'; form-action 'none'"
        )
        response.headers["X-Content-Type-Options"] = "nosniff"
        response.headers["Referrer-Policy"] = "no-referrer"
        # no-store: never kept in the back/forward cache with its link open, never stale
        response.headers["Cache-Control"] = "no-store"

    async def _index(self, request: web.Request) -> web.FileResponse:
        return web.FileResponse(STATIC_DIR / "index.html")

    # -- the WebSocket ------------------------------------------------------------------------
    async def _websocket(self, request: web.Request) -> web.StreamResponse:
        if not _origin_ok(request):
            log.warning(
                "console: refused a WebSocket from origin %r", request.headers.get("Origin")
            )
            return web.Response(status=403, text="cross-origin WebSocket refused\n")
        full = len(self._pages) >= self.config.max_clients and not self._make_room()
        ws = web.WebSocketResponse(
            heartbeat=HEARTBEAT_S, max_msg_size=self.config.max_message_bytes
        )
        await ws.prepare(request)
        if full:  # closed with its reason: a browser sees no HTTP status of a refused WebSocket
            why = f"console full: {self.config.max_clients} pages open (console.max_clients)"
            await ws.close(code=1013, message=why.encode())
            return ws
        peername = request.transport.get_extra_info("peername") if request.transport else None
        host = str(peername[0]) if isinstance(peername, tuple) else "?"
        peer = f"{host}:{peername[1]}" if isinstance(peername, tuple) else "?"
        client = self.control.detached_client(
            peer,
            host,
            watch_only=self.config.watch_only,
            drive_limit_s=self.config.deadman_s,
        )
        page = _Page(ws=ws, client=client, peer=peer, transport=request.transport)
        self._pages[page] = None
        sender = asyncio.create_task(self._sender(page))
        self._reply(page, self._welcome())
        if client.authenticated:
            self._authenticated(page)
        try:
            await self._read_loop(page)
        finally:
            listed = page in self._pages  # (not: closed to make room for another page)
            self._pages.pop(page, None)
            if listed and isinstance(ws.exception(), TimeoutError):  # the heartbeat closed it
                self._slow_page(
                    page, f"no pong within {HEARTBEAT_S / 2:g} s of a ping (it does not read, "
                    "or its link is gone)",
                )  # fmt: skip
            await self._hang_up(page)
            sender.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await sender
            with contextlib.suppress(Exception):
                await ws.close()
        return ws

    def _authenticated(self, page: _Page) -> None:
        """What a page gets once it may see the robot: the map, then the track so far."""
        self._send_map(page, self._map_view())
        points = [[lat, lon] for lat, lon in self.track]
        self._event(page, encode({"event": "track", "points": points}).decode())

    def _make_room(self) -> bool:
        """A full console closes its oldest page that has not authenticated (pages that
        never send the token cannot lock the operator out); False when every page has."""
        victim = next((p for p in self._pages if not p.client.authenticated), None)
        if victim is None:
            return False
        self._pages.pop(victim, None)
        log.info("console: closing %s (not authenticated) to make room", victim.peer)
        task = asyncio.create_task(victim.ws.close(code=1013, message=b"console full"))
        self._closing.add(task)
        task.add_done_callback(self._closing.discard)
        return True

    def _welcome(self) -> dict[str, Any]:
        return {
            "event": "console",
            "version": __version__,
            "auth_required": self.control.auth_required,
            "watch_only": self.config.watch_only,
            "tile_url": self.config.tile_url,
            "deadman_s": self.config.deadman_s,
            "tls": self._ssl is not None,
            "max_message_bytes": self.config.max_message_bytes,  # larger ones close the link
            "max_message_bytes_before_auth": PRE_AUTH_MESSAGE_BYTES,  # likewise, until auth
        }

    async def _read_loop(self, page: _Page) -> None:
        """The page's requests in order, each after the back-off of the one before; its
        messages are read meanwhile (:meth:`_receive`), so a stop is obeyed on arrival."""
        inbox: asyncio.Queue[bytes | None] = asyncio.Queue()
        receiver = asyncio.create_task(self._receive(page, inbox))
        try:
            while True:
                page.busy = False
                line = await inbox.get()
                if line is None:
                    return
                page.busy = True
                self.control.take(page.client)
                page.held -= _message_cost(line)
                page.queued -= 1
                page.room.set()
                if not await self._handle(page, line):
                    return
        finally:
            receiver.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await receiver

    async def _receive(self, page: _Page, inbox: asyncio.Queue[bytes | None]) -> None:
        """Every message of the page into ``inbox`` (None: the page closed), at most
        ``max_message_bytes`` held; before ``auth`` succeeded one over
        :data:`PRE_AUTH_MESSAGE_BYTES` closes the page (:meth:`_refuse_large`). One that
        arrives while an earlier request is handled or sleeps out its back-off (seconds after
        a wrong token) is a ``stop`` sent to the motors now; its reply still comes in turn."""
        try:
            async for msg in page.ws:
                if msg.type == WSMsgType.BINARY:
                    line = bytes(msg.data)
                elif msg.type == WSMsgType.TEXT:
                    line = str(msg.data).encode("utf-8", "surrogatepass")
                else:
                    break  # an error or a close
                if len(line) > PRE_AUTH_MESSAGE_BYTES and not page.client.authenticated:
                    await self._refuse_large(page, len(line))
                    break
                self.control.receive(page.client, line, early=page.busy or not inbox.empty())
                page.held += _message_cost(line)
                page.queued += 1
                inbox.put_nowait(line)
                while page.held > self.config.max_message_bytes:
                    page.room.clear()  # held back: the rest waits in aiohttp and the kernel
                    await page.room.wait()
        finally:
            inbox.put_nowait(None)

    async def _refuse_large(self, page: _Page, size_b: int) -> None:
        """Close a page that sent a message over :data:`PRE_AUTH_MESSAGE_BYTES` before its
        ``auth`` succeeded: 1009 (message too big) and why, logged at most once per second.
        The close waits at most :data:`REFUSE_CLOSE_S` for the peer's close frame (a page
        that floods does not read), then drops the connection."""
        self._rlog.log(
            "console: large before auth",
            logging.WARNING,
            "console: closing %s: a message of %d bytes before auth (at most %d until the "
            "token is accepted)",
            page.peer, size_b, PRE_AUTH_MESSAGE_BYTES,
        )  # fmt: skip
        why = f"message too big before auth: at most {PRE_AUTH_MESSAGE_BYTES} bytes until then"
        with contextlib.suppress(Exception):
            await asyncio.wait_for(
                page.ws.close(code=WSCloseCode.MESSAGE_TOO_BIG, message=why.encode()),
                REFUSE_CLOSE_S,
            )

    async def _handle(self, page: _Page, line: bytes) -> bool:
        """One request: its reply, then its back-off; False: the page is to be closed."""
        c = page.client
        was_authenticated = c.authenticated
        reply, wait_s = await self._request(page, line)
        self._reply(page, reply)
        if c.authenticated and not was_authenticated:
            self._authenticated(page)
        if c.close_reason:
            notice = error_reply(None, "closed", "too many failed authentications")
            notice["error"]["reason"] = c.close_reason
            self._reply(page, notice)
            await asyncio.sleep(0.1)  # let the sender write the reply and the notice
            return False
        if wait_s > 0.0:
            await asyncio.sleep(wait_s)  # only this page waits (_receive reads on)
        return True

    async def _request(self, page: _Page, line: bytes) -> tuple[dict[str, Any], float]:
        """One message: ``mission.parse`` here, everything else through the control server's
        dispatcher (which tracks whose drive runs, for the dead-man)."""
        c = page.client
        cmd = None
        with contextlib.suppress(Exception):  # the dispatcher reports a bad line itself
            req = parse_request(line)
            cmd = req.get("cmd")
        late_s = self._late_s(page, req) if cmd is not None else 0.0
        press_s: float | None = None
        if cmd == "drive":
            try:
                press_s = self._press_s(page, req)
            except ValueError as exc:
                rid = req.get("id")
                return error_reply(
                    rid if isinstance(rid, (int, str)) else None, "bad_request", str(exc),
                    "bad_argument",
                ), 0.0  # fmt: skip
        elif cmd == "stop":
            page.run_last_s = -math.inf  # the page's own stop: its held drive was let go
        if cmd == "drive" and late_s > self.config.deadman_s:
            # it sat in a stalled link (a frozen network, a suspended laptop) longer than it
            # would have lasted: the key may well be up by now, and its stop is behind it
            self.late_drives += 1
            rid = req.get("id")
            return error_reply(
                rid if isinstance(rid, (int, str)) else None, "rejected",
                f"drive arrived {late_s:.1f} s late (the link stalled): not driven", "late",
            ), 0.0  # fmt: skip
        sent = req.get("sent_ms") if cmd is not None else None
        if (
            cmd in SUPERSEDED_COMMANDS
            and c.authenticated
            and not c.watch_only
            and isinstance(sent, (int, float))
            and not isinstance(sent, bool)
            and self.control.stopped_since(c, sent / 1000.0 + page.clock_offset_s)
        ):
            # sent before another client's stop, held in this page's link meanwhile (the
            # order-based fence sees only what the console has read)
            if cmd == "drive":
                self._log_stopped(page, req)
            rid = req.get("id")
            return error_reply(
                rid if isinstance(rid, (int, str)) else None, "rejected",
                f"a stop came after this {cmd}: not done", "stopped",
            ), 0.0  # fmt: skip
        if (
            press_s is not None
            and c.authenticated
            and not c.watch_only
            and self.control.stopped_since(c, press_s - self._guard_s(page, req))
        ):
            # a resend of a held drive whose press began before another client's stop: that
            # stop ended the press; the robot stays stopped until the key is pressed again.
            # A press placed less than deadman_s after the stop counts as before it: the
            # offset holds the link's least one-way delay, so a press is placed up to that
            # much late (a press within deadman_s of another's stop must be made again)
            self.held_drives_stopped += 1
            page.run_start_s = min(page.run_start_s, page.drive_sent_s)  # stays stopped
            self._log_stopped(page, req)
            rid = req.get("id")
            return error_reply(
                rid if isinstance(rid, (int, str)) else None, "rejected",
                "the robot was stopped by another client while this drive was held: not "
                "driven (release and press again to drive)", "stopped",
            ), 0.0  # fmt: skip
        if cmd == "mission.parse":
            return self._parse_mission(c, req), 0.0
        if cmd in ("recording.list", "recording.view"):
            return await self._recording(c, req), 0.0
        reply, wait_s = await self.control.request(c, line)
        if cmd == "drive" and reply.get("ok"):  # driven: its press, if inferred, began
            page.run_start_s = min(page.run_start_s, page.drive_sent_s)
            page.last_drove_s = max(page.last_drove_s, page.drive_sent_s)
        return reply, wait_s

    def _guard_s(self, page: _Page, req: dict[str, Any]) -> float:
        """How long after another client's stop a press still counts as begun before it:
        ``deadman_s`` for a press the page names (``press_ms``: the offset holds the link's
        least one-way delay, so the press is placed up to that much late), and for an
        inferred press of a page whose drive ran at the stop (its latest drive carried out
        sent less than ``deadman_s`` before it: a drive that starts a "new press" after a
        stall is still the stopped press); 0 for a page that was not driving (a program
        that sends a drive just after another's stop is obeyed, as before)."""
        if "press_ms" in req:
            return self.config.deadman_s
        other_stop_s = getattr(page.client, "other_stop_s", -math.inf)
        return (
            self.config.deadman_s
            if page.last_drove_s > other_stop_s - self.config.deadman_s
            else 0.0
        )

    def _log_stopped(self, page: _Page, req: dict[str, Any]) -> None:
        """A drive refused because of another client's stop: the first refusal of each press
        is logged."""
        press = req.get("press_ms", ("inferred", page.run_start_s))
        if press == page.logged_press:
            return
        page.logged_press = press
        log.warning(
            "console: %s: a drive refused: another client stopped the robot after its press "
            "began (the robot stays stopped until that key is pressed again; "
            "held_drives_stopped %d, late_drives %d)",
            page.peer, self.held_drives_stopped, self.late_drives,
        )  # fmt: skip

    def stats(self) -> dict[str, int]:
        """The console's counts: motors stopped by the dead-man (a page gone while driving),
        drives refused for arriving more than ``deadman_s`` late, drives refused because
        another client stopped the robot after their press began, requests refused for
        their Host, idle connections closed at the cap, events dropped for slow pages."""
        return {
            "deadman_stops": self.deadman_stops,
            "late_drives": self.late_drives,
            "held_drives_stopped": self.held_drives_stopped,
            "refused_hosts": self.refused_hosts,
            "connections_closed": self.connections_closed,
            "slow_pages": self.slow_pages,
            "dropped": self.dropped_total,
        }

    @staticmethod
    def _late_s(page: _Page, req: dict[str, Any]) -> float:
        """How much later than the page's fastest recent message this one arrives (s), from
        its ``sent_ms`` (the page's monotonic clock); 0 without one. The fastest message
        fixes the clocks' offset plus the link's least delay: the rest is the stall. Recent:
        this period of :data:`OFFSET_PERIOD_S` and the one before it (see there)."""
        sent = req.get("sent_ms")
        if not isinstance(sent, (int, float)) or isinstance(sent, bool):
            return 0.0
        now = time.monotonic()
        offset = now - sent / 1000.0
        if now - page.offset_period_s >= OFFSET_PERIOD_S:  # a new period, begun by a message
            page.offset_before_s, page.offset_now_s = page.offset_now_s, math.inf
            page.offset_period_s = now
        page.offset_now_s = min(page.offset_now_s, offset)
        page.clock_offset_s = min(page.offset_before_s, page.offset_now_s)
        return offset - page.clock_offset_s

    def _press_s(self, page: _Page, req: dict[str, Any]) -> float:
        """When the press a drive belongs to began (time.monotonic() s, at the latest): a
        stop from elsewhere after it, or shortly before it (:meth:`_guard_s`), ends the press.
        Its ``press_ms`` (the page's clock) mapped as ``sent_ms`` is. Without one (a page
        with an older console.js, another program) the press is inferred: the page's drives
        sent (by ``sent_ms``, else as they arrive) less than ``deadman_s`` apart since its
        last own ``stop`` (a held key's resends are ``deadman_s``/3 apart), begun when the
        first of them the robot carried out, or that was refused as begun before another
        client's stop, was sent; until then at this drive (one refused for another reason
        never drove: the older page ended its drive on that refusal). ValueError: a bad
        ``press_ms``."""
        raw = req.get("sent_ms")
        sent = float(raw) if isinstance(raw, (int, float)) and not isinstance(raw, bool) else None
        sent_s = time.monotonic() if sent is None else sent / 1000.0 + page.clock_offset_s
        if not sent_s - page.run_last_s <= self.config.deadman_s:  # (also a NaN: a new run)
            page.run_start_s = math.inf
        page.run_last_s = max(page.run_last_s, sent_s)
        page.drive_sent_s = sent_s
        if "press_ms" not in req:
            return min(page.run_start_s, sent_s)
        press = req["press_ms"]
        if (
            sent is None
            or isinstance(press, bool)
            or not isinstance(press, (int, float))
            or not press <= sent
        ):
            raise ValueError(
                "'press_ms' must be the page's time (ms, its sent_ms clock) when the drive's "
                "key was pressed: a number, not after 'sent_ms', which it needs"
            )
        return press / 1000.0 + page.clock_offset_s

    def _parse_mission(self, c: Any, req: dict[str, Any]) -> dict[str, Any]:
        """``{"cmd": "mission.parse", "content": TEXT, "format": "gpx"|...|null}`` ->
        ``waypoints`` ([[lat, lon], ...], degrees). Reads a file for the editor only."""
        rid = req.get("id")
        if isinstance(rid, (dict, list)):
            rid = None
        if not c.authenticated:
            return error_reply(rid, "unauthorized", "authenticate first to use 'mission.parse'")
        text, fmt = req.get("content"), req.get("format")
        if not isinstance(text, str) or not (fmt is None or isinstance(fmt, str)):
            return error_reply(
                rid,
                "bad_request",
                "'content' must be the file's text, 'format' one of "
                f"{', '.join(PARSERS)} or null (guessed from the content)",
                "bad_argument",
            )
        name = str(req.get("name") or "mission")
        try:
            wps = parse_content(text, fmt or None, name)
        except ParseError as exc:
            return error_reply(rid, "bad_request", str(exc), "bad_mission")
        except Exception as exc:  # a file the reader chokes on must not end the operator's link
            log.exception("console: mission.parse of %.80s failed", name)
            return error_reply(
                rid, "bad_request", f"{name:.80}: cannot be read: {exc!s:.200}", "bad_mission"
            )
        reply = {"id": rid, "ok": True, "waypoints": [[w.lat_deg, w.lon_deg] for w in wps]}
        notes = getattr(wps, "notes", None)  # what the file held but x6wd won't use
        return {**reply, "notes": list(notes)} if notes else reply

    @staticmethod
    def _list_runs(directory: Path) -> dict[str, _Run]:
        """The recorder's runs in ``directory`` by the name of their first remaining part,
        oldest first (reads the folder: called in a thread)."""
        runs: dict[str, list[RecordingFile]] = {}
        for f in list_recordings(directory):
            runs.setdefault(str(f.run), []).append(f)  # parts sort after their first file
        return {
            # recording_writer re-lists a run that rotates meanwhile (a listing's own two
            # newest parts can both read free for the moment a rotation takes)
            parts[0].path.name: _Run(
                parts[0].path, parts[0].size, recording_writer(parts[-1].path) is not None
            )
            for parts in runs.values()
        }

    async def _runs(self) -> dict[str, _Run]:
        """:meth:`_list_runs` of the recordings folder, read in the console's file thread,
        never on the network loop (which reads every client's stop); requests meanwhile
        share the listing under way. TimeoutError after :data:`RECORDINGS_TIMEOUT_S` (the
        listing goes on, and the next request waits for it: one hung folder holds one
        thread); OSError from the folder."""
        if self._recordings_dir is None:
            return {}
        f = self._listing
        if f is None or f.done():
            loop = asyncio.get_running_loop()
            f = loop.run_in_executor(self._files, self._list_runs, self._recordings_dir)
            f.add_done_callback(lambda f: f.cancelled() or f.exception())  # (none unheard)
            self._listing = f
        return await asyncio.wait_for(asyncio.shield(f), RECORDINGS_TIMEOUT_S)

    async def _recording(self, c: Any, req: dict[str, Any]) -> dict[str, Any]:
        """``recording.list`` -> ``recordings`` ([{name, bytes, in_progress}], newest first;
        ``in_progress``: still being written, this daemon's current run);
        ``recording.view`` with ``name`` (one of the list) -> ``html``, the log viewer's page
        (a run still being written says so under "end", not "cut short").
        Only names the recorder wrote are read: a name is never a path."""
        rid = req.get("id")
        if isinstance(rid, (dict, list)):
            rid = None
        cmd = req["cmd"]
        if not c.authenticated:
            return error_reply(rid, "unauthorized", f"authenticate first to use '{cmd}'")
        try:
            runs = await self._runs()
        except TimeoutError:
            if self._listing is not None and self._listing not in self._hung_logged:
                self._hung_logged = {self._listing}  # once per hung listing
                log.warning(
                    "console: the recordings folder %s has not answered for %g s (%s refused)",
                    self._recordings_dir, RECORDINGS_TIMEOUT_S, cmd,
                )  # fmt: skip
            return error_reply(
                rid, "rejected",
                f"the recordings folder ({self._recordings_dir}) did not answer within "
                f"{RECORDINGS_TIMEOUT_S:g} s (a hung SD card or network mount?); the robot is "
                "not affected", "recordings_unavailable",
            )  # fmt: skip
        except OSError as exc:
            return error_reply(
                rid, "rejected",
                f"cannot read the recordings folder ({self._recordings_dir}): "
                f"{exc.strerror or exc}", "recordings_unavailable",
            )  # fmt: skip
        if cmd == "recording.list":
            items = [
                {"name": n, "bytes": f.size, "in_progress": f.in_progress}
                for n, f in reversed(runs.items())
            ]
            return {"id": rid, "ok": True, "recordings": items}
        name = req.get("name")
        if not isinstance(name, str) or name not in runs:
            return error_reply(
                rid, "bad_request", f"no recording named {name!r} (see recording.list)",
                "bad_argument",
            )  # fmt: skip
        loop = asyncio.get_running_loop()
        try:  # reading a long run takes a while: off the network loop
            rendering = loop.run_in_executor(self._files, render_html, runs[name].path)
            page = await asyncio.wait_for(rendering, RENDER_TIMEOUT_S)
        except TimeoutError:
            return error_reply(
                rid, "rejected",
                f"{name}: not read within {RENDER_TIMEOUT_S:g} s (a hung SD card or network "
                "mount?); the robot is not affected", "recordings_unavailable",
            )  # fmt: skip
        except (DeviceUnavailable, ParseError) as exc:
            return error_reply(rid, "bad_request", str(exc), "bad_recording")
        except Exception as exc:  # a file the viewer chokes on must not end the operator's link
            log.exception("console: rendering recording %s failed", name)
            return error_reply(
                rid, "bad_request", f"{name}: cannot be shown: {exc}", "bad_recording"
            )
        return {"id": rid, "ok": True, "name": name, "html": page}

    async def _hang_up(self, page: _Page) -> None:
        """The dead-man: a page that goes away while its drive runs stops the motors now."""
        if self.control.drive_active(page.client):  # its drive runs, no command replaced it
            # the stop first (the control server sends it to the motors before any of its
            # bookkeeping), then the counts and the log line, which says how it went
            try:
                reply, _ = await self.control.request(page.client, STOP_LINE)
            except Exception as exc:  # (request never raises; if it did: say so)
                reply = error_reply(None, "internal", f"{type(exc).__name__}: {exc}")
            self.deadman_stops += 1
            if reply.get("ok"):
                log.warning("console: %s went away while driving: motors stopped", page.peer)
            else:
                log.error(
                    "console: %s went away while driving: its stop failed: %s",
                    page.peer, reply.get("error"),
                )  # fmt: skip

    async def _sender(self, page: _Page) -> None:
        ws = page.ws
        try:
            while not ws.closed:
                await page.wake.wait()
                page.wake.clear()
                while page.replies or page.events:
                    text = page.replies.popleft() if page.replies else page.events.popleft()
                    await asyncio.wait_for(ws.send_str(text), SEND_TIMEOUT_S)
        except TimeoutError:
            self._slow_page(page, f"it has taken no data for {SEND_TIMEOUT_S:g} s")
            with contextlib.suppress(Exception):
                await ws.close(code=1008, message=b"too slow")
        except (ConnectionError, RuntimeError):  # gone (closed, reset) while sending to it
            with contextlib.suppress(Exception):
                await ws.close(code=1008, message=b"too slow")
