"""What the two TCP line servers share (the remote-control server and the gpsd port).

Each client has two outboxes: ``replies`` (answers to its own requests, never dropped) and
``events`` (unsolicited reports, bounded: the oldest is dropped and counted when full), and
one sender task that writes them. So a slow or stuck reader only ever fills its own bounded
queue; nothing the control loop does waits for a socket.

Lock-out protection. A new connection is *pending* until the protocol admits it as a
*session* (the control port: a correct ``auth``, or without a token one valid request; the
gpsd port: one valid command). The two live in separate pools:

- pending pool (``max_pending``): full means a new connection closes a pending one: of the
  address holding the most pending connections, one that has already sent something
  malformed, else the oldest that has sent nothing at all (not even a TLS ClientHello), else
  the oldest with no input waiting to be read, else the oldest. A connection
  is never refused, and pending peers never hold a session slot, so silent sockets cannot
  lock an operator out; and an operator whose ``auth`` has arrived but not been read yet
  (a burst of connections accepted after a pause) is not the one closed.
- session pool (``max_clients``): full means, first, that sessions whose peer has already
  closed or reset its connection (the kernel's TCP state; their handlers have not read the
  end of the stream yet) leave the pool, uncounted: in a connect/close storm the kernel
  hands over up to ``LISTEN_BACKLOG`` connections at once, each admitted before its close
  is seen, and those must not crowd out live sessions. If it is still full the peer being
  admitted closes a session, never a protected one (:meth:`LineServer._protected`: on the
  control port the one whose manual drive runs, whose close would stop the robot), unless
  every session is. If no address holds more sessions than the admitted peer's (it
  counted), one of that address's own goes (a storm from one address closes its own);
  otherwise, or if it has none to close, a session of any address: a session not watching
  before a watcher that is behind (not reading for a while) before one that keeps up,
  within the same kind one of the address holding the most sessions. Within that, the
  least valuable goes: the one idle longest among those not watching, the watcher most
  behind (blocked in ``drain()`` or its data unacknowledged longest, then most events
  queued), the newest watcher that keeps up (an established reader outlives one just
  admitted).

One sweeper task per server enforces the deadlines: pending longer than
``pending_timeout_s``, a session neither watching nor sending a line for ``idle_timeout_s``,
and a peer that does not read: a sender blocked in ``drain()`` for ``slow_client_s``, or
(Linux) data in the kernel's send queue that the peer has not acknowledged any of for
``slow_client_s`` (its receive window stays shut). The second catches a never-reading
watcher as soon as its own receive buffer is full, long before a low-rate stream fills the
server's send buffer. Every such close is counted in :attr:`LineServer.closed_counts` and
logged at most once per second per reason (then "N more").

A closed connection frees its memory at once, by reference counting: a TLS close does not
wait for the peer's close_notify (:func:`close_promptly`), and the stream reader's buffer
and what closes over the client are dropped when its handler ends (:func:`release_input`),
so a flood of connections the server closes does not wait for the garbage collector.
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import fcntl
import logging
import socket
import ssl
import struct
import termios
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Generic, TypeVar

from x6wd.core.ratelog import RateLimitedLog

_log = logging.getLogger(__name__)

LISTEN_BACKLOG = 100
"""Connections the kernel holds before they are accepted (asyncio's default, made explicit).
Measured with a connect-churning swarm (bench_daemon): 1024 let the churner push ~4x more
connections per second into the loop, which then queued the operator's connection behind
hundreds of others (reconnect 275 ms, status 160 ms); with 100 the full queue pushes back on
the churner instead (reconnect 2 ms median, status 0.2 ms)."""

# reasons a server closes a connection (keys of ``closed_counts``, and the notice's reason)
PENDING_FULL = "pending_full"
SESSIONS_FULL = "sessions_full"
IDLE_TIMEOUT = "idle_timeout"
SLOW_READER = "slow_reader"


@dataclass(eq=False, kw_only=True)
class LineClient:
    """One connection's outboxes and state (subclassed per protocol)."""

    writer: asyncio.StreamWriter
    peer: str = ""  # "host:port", for logs
    host: str = ""  # the peer's address alone: pending connections are counted per address
    events: collections.deque[bytes] = field(default_factory=collections.deque)
    replies: collections.deque[bytes] = field(default_factory=collections.deque)
    wake: asyncio.Event = field(default_factory=asyncio.Event)
    drained: asyncio.Event = field(default_factory=asyncio.Event)  # outboxes written out
    dropped: int = 0
    closed: bool = False
    evicted: str = ""  # why the server closed it ("" while open): nothing more is written
    session: bool = False  # admitted to the session pool (else pending)
    suspect: bool = False  # sent something malformed while pending: evicted first
    t_connect_s: float = 0.0  # server clock (s)
    t_active_s: float = 0.0  # last complete line received (s, server clock)
    drain_since_s: float | None = None  # the sender is waiting in drain() since (s)
    bytes_out: int = 0  # bytes handed to the transport
    acked_out: int = -1  # of those, acknowledged by the peer at the last sweep
    stalled_since_s: float | None = None  # unacknowledged data without progress since (s)
    task: asyncio.Task[Any] | None = None  # the connection's handler task
    reader: asyncio.StreamReader | None = None
    sender: asyncio.Task[None] | None = None
    napping: bool = False  # the handler sleeps out a back-off (eviction must wake it)
    handshaking: bool = False  # in its TLS handshake: the raw socket is not ours to write

    def put(self, line: bytes, maxlen: int) -> bool:
        """Queue an event line, dropping the oldest when ``maxlen`` are waiting; True if one
        was dropped."""
        dropped = len(self.events) >= maxlen
        if dropped:
            self.events.popleft()
            self.dropped += 1
        self.events.append(line)
        self.wake.set()
        return dropped

    def reply(self, line: bytes) -> None:
        """Queue a reply line (never dropped)."""
        self.replies.append(line)
        self.wake.set()


C = TypeVar("C", bound=LineClient)


def unread_bytes(c: LineClient) -> int:
    """Input that has arrived for a connection but that its handler has not consumed yet:
    the kernel's receive queue (FIONREAD) plus the stream reader's buffer (bytes)."""
    n = 0
    reader = c.reader
    if reader is not None:
        n += len(getattr(reader, "_buffer", b""))  # CPython's StreamReader keeps it here
    n += socket_queue_bytes(transport_socket(c.writer.transport), termios.FIONREAD) or 0
    return n


def request_waiting(c: LineClient) -> bool:
    """A whole request has arrived and waits to be read: a line end in the stream reader's
    buffer, or in the kernel's receive queue a line end or a whole TLS record (a ClientHello
    the loop has not read yet). A byte or a partial line that stalls is not one."""
    reader = c.reader
    if reader is not None and b"\n" in getattr(reader, "_buffer", b""):
        return True
    return whole_request_queued(c.writer.transport)


def whole_request_queued(transport: asyncio.BaseTransport | None) -> bool:
    """The kernel's receive queue of a TCP transport holds a line end or a whole TLS record
    (peeked, not consumed; False where it cannot be read). Never raises."""
    sock = None if transport is None else transport_socket(transport)
    if sock is None:
        return False
    try:
        # asyncio hands out a wrapper without recv(): peek through a socket object on the
        # same descriptor, detached after (never closed; no duplicate descriptor, which a
        # flood at the descriptor limit would deny just when this matters)
        view = socket.socket(fileno=sock.fileno())
    except Exception:  # a closed socket, no socket
        return False
    try:
        head = view.recv(4096, socket.MSG_PEEK | socket.MSG_DONTWAIT)
    except Exception:  # nothing queued (BlockingIOError), a closed socket
        return False
    finally:
        view.detach()
    if b"\n" in head:
        return True
    return len(head) >= 5 and head[0] == 0x16 and len(head) >= 5 + int.from_bytes(head[3:5])


def transport_socket(transport: asyncio.BaseTransport) -> Any:
    """The socket under a transport, or None. Never raises: a closed or closing transport of
    any kind may have no socket any more, and asyncio's SSL transport, once closed twice
    (the peer's hang-up, then ours), raises AttributeError from ``get_extra_info`` itself:
    no bookkeeping about one connection may fail a stop or a deadline of the others."""
    try:
        return transport.get_extra_info("socket")
    except Exception:
        return None


def write_buffer_size(transport: asyncio.BaseTransport) -> int:
    """Bytes a transport holds that it has not handed to the kernel yet; 0 for a closed
    transport (asyncio's SSL transport raises AttributeError then). Never raises."""
    try:
        return int(transport.get_write_buffer_size())  # type: ignore[attr-defined]
    except Exception:
        return 0


def socket_queue_bytes(sock: Any, request: int) -> int | None:
    """One of a socket's kernel queues (``termios.FIONREAD``: received, not read yet;
    ``termios.TIOCOUTQ`` = SIOCOUTQ: sent, not acknowledged by the peer), bytes; None where
    it cannot be read (no socket, a closed one). Never raises."""
    if sock is None:
        return None
    try:
        raw = fcntl.ioctl(sock.fileno(), request, b"\0\0\0\0")
        return int(struct.unpack("i", raw)[0])
    except Exception:  # OSError, ValueError (fd -1), or a socket object gone odd
        return None


_TCPI_BYTES_ACKED = 120
"""Offset of ``tcpi_bytes_acked`` (u64, Linux 4.1+) in the kernel's ``struct tcp_info``: 8
one-byte fields, 24 u32, then pacing_rate and max_pacing_rate (u64), on every Linux ABI."""

_TCPI_BYTES_RECEIVED = 128
"""Offset of ``tcpi_bytes_received`` (u64, Linux 4.1+) in the kernel's ``struct tcp_info``."""


_TCP_ESTABLISHED = 1
"""``tcpi_state`` (the first byte of ``struct tcp_info``) of an open connection; any other
state of an accepted socket means one side has closed or reset it (CLOSE_WAIT: the peer
sent its FIN; CLOSE: reset)."""


def _tcp_info(transport: asyncio.BaseTransport) -> bytes | None:
    """The kernel's ``struct tcp_info`` of a TCP transport (Linux); None where it cannot be
    read (no socket, a closed one, no TCP_INFO here). Never raises."""
    sock = transport_socket(transport)
    if sock is None:
        return None
    try:
        raw = sock.getsockopt(socket.IPPROTO_TCP, socket.TCP_INFO, 256)
    except Exception:  # OSError, AttributeError (no TCP_INFO here), a closed socket
        return None
    return raw if isinstance(raw, bytes) and raw else None


def _tcp_info_u64(transport: asyncio.BaseTransport, offset: int) -> int | None:
    """The u64 at ``offset`` of a TCP transport's ``struct tcp_info``; None where it cannot
    be read. Never raises."""
    raw = _tcp_info(transport)
    if raw is None or len(raw) < offset + 8:
        return None
    return int(struct.unpack_from("Q", raw, offset)[0])


def bytes_received(transport: asyncio.BaseTransport) -> int | None:
    """Bytes the peer of a TCP transport has sent since it connected, read or not (Linux
    TCP_INFO; the TLS handshake's included); None where that cannot be read. Never raises."""
    return _tcp_info_u64(transport, _TCPI_BYTES_RECEIVED)


def bytes_acked(transport: asyncio.BaseTransport) -> int | None:
    """Bytes this side has sent on a TCP transport that the peer acknowledged (Linux
    TCP_INFO; a TLS server's handshake reply included); None where that cannot be read.
    Never raises."""
    return _tcp_info_u64(transport, _TCPI_BYTES_ACKED)


def silent(transport: asyncio.BaseTransport | None) -> bool:
    """The peer has sent nothing since it connected (False when that cannot be told)."""
    return transport is not None and bytes_received(transport) == 0


def unanswered(transport: asyncio.BaseTransport | None) -> bool:
    """The server has sent this connection nothing it took (no reply, no TLS handshake
    flight): a peer that sent nothing, or a byte or a partial request and stalled. An
    operator's client has an answer within a round trip of speaking (its ClientHello's
    reply, its auth's), so under a flood these go first. False when it cannot be told."""
    return transport is not None and bytes_acked(transport) == 0


def peer_gone(c: LineClient) -> bool:
    """Whether a connection's peer has already ended it: it sent its FIN (it may still have
    requests waiting to be read, but the servers end a connection at the end of its input)
    or reset it, or the connection is closed or closing on this side. Read from the kernel
    (Linux TCP_INFO state), so it is known before the handler has seen the end of the
    stream; False where it cannot be told. Never raises."""
    if c.closed:
        return True
    transport = c.writer.transport
    try:
        if transport.is_closing():
            return True
    except Exception:
        return False
    raw = _tcp_info(transport)
    return raw is not None and raw[0] != _TCP_ESTABLISHED


def unacknowledged_bytes(transport: asyncio.BaseTransport) -> int | None:
    """Bytes in the kernel's send queue of a TCP transport that the peer has not
    acknowledged (Linux SIOCOUTQ); None where that cannot be read (also a closed transport,
    plain or TLS). Never raises."""
    return socket_queue_bytes(transport_socket(transport), termios.TIOCOUTQ)


def reset(transport: asyncio.WriteTransport) -> None:
    """Close at once with a TCP reset: data still queued for a peer that does not read is
    dropped now, instead of the kernel holding it (and the connection) while it retries."""
    sock = transport_socket(transport)
    if sock is not None:
        with contextlib.suppress(Exception):  # OSError; a closed socket object of any kind
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
    transport.abort()


def close_promptly(transport: asyncio.WriteTransport) -> None:
    """Close a transport once what it was given is written: plain TCP as ``close()``; TLS
    sends its close_notify and, as soon as that is in the kernel, is aborted. asyncio would
    otherwise wait up to its ``ssl_shutdown_timeout`` (30 s) for the peer's close_notify,
    which a peer that floods or stalls never sends (nor is it read while its handler has
    paused reading), and hold the connection meanwhile: its stream and TLS buffers, its
    handler's last read, the client (outside audit 10b: 40 TLS connections streaming a line
    without an end took the daemon from 68 to 423 MB). At the socket this is what a plain
    close does (a FIN, or a reset when the peer's input is left unread). Never raises."""
    with contextlib.suppress(Exception):  # a closed transport of any kind
        transport.close()
        raw = _tls_raw_transport(transport)
        if raw is not None and write_buffer_size(raw) == 0:
            transport.abort()


def _tls_raw_transport(transport: asyncio.BaseTransport) -> asyncio.BaseTransport | None:
    """The TCP transport under asyncio's TLS transport (CPython's ``_SSLProtocolTransport``
    keeps it on its protocol); None for any other transport or where it is not found."""
    protocol = getattr(transport, "_ssl_protocol", None)
    raw = getattr(protocol, "_transport", None)
    return raw if isinstance(raw, asyncio.BaseTransport) else None


def release_input(reader: asyncio.StreamReader) -> None:
    """Drop what a finished connection's stream reader holds at once (its buffer, up to the
    reader's limit and more), and a wrapper set on the instance (the control server counts
    what arrives by replacing ``feed_data``): it closes over the reader and the client, a
    cycle that only the garbage collector's full pass would free. Never raises."""
    with contextlib.suppress(Exception):  # a reader of another implementation
        buffer = getattr(reader, "_buffer", None)  # CPython's StreamReader keeps it here
        if isinstance(buffer, bytearray):
            buffer.clear()
        vars(reader).pop("feed_data", None)


def peer_names(writer: asyncio.StreamWriter) -> tuple[str, str]:
    """``("host:port", "host")`` of a connection's peer (``"?"`` when unknown)."""
    peer = writer.get_extra_info("peername")
    if isinstance(peer, tuple) and len(peer) >= 2:
        return f"{peer[0]}:{peer[1]}", str(peer[0])
    return str(peer or "?"), str(peer or "?")


class LineServer(Generic[C]):
    """Listening socket, the pending and session pools, deadlines, shutdown and the sender."""

    #: the closing reason when a pending connection's deadline passes (protocol-specific name)
    pending_timeout_reason = "pending_timeout"
    #: how logs name this server
    label = "line server"

    def __init__(
        self,
        configured_port: int,
        *,
        max_clients: int,
        max_pending: int,
        pending_timeout_s: float,
        idle_timeout_s: float,
        slow_client_s: float,
        clock: Callable[[], float] = time.monotonic,
        logger: logging.Logger = _log,
    ) -> None:
        """Pool sizes are connection counts; deadlines are seconds of ``clock`` (monotonic)."""
        self._configured_port = configured_port
        self.max_clients = max_clients
        self.max_pending = max_pending
        self.pending_timeout_s = pending_timeout_s
        self.idle_timeout_s = idle_timeout_s
        self.slow_client_s = slow_client_s
        self._clock = clock
        self._server: asyncio.Server | None = None
        self._clients: set[C] = set()  # every open connection
        self._pending: dict[C, None] = {}  # insertion order: oldest first
        self._sessions: set[C] = set()
        self._tasks: set[asyncio.Task[Any]] = set()
        self._sweeper: asyncio.Task[None] | None = None
        self.dropped_total = 0
        self.closed_counts: collections.Counter[str] = collections.Counter()
        self._rlog = RateLimitedLog(logger, 1.0, clock)

    @property
    def connections(self) -> tuple[C, ...]:
        """Every open connection, pending or session (a snapshot; for status and tests)."""
        return tuple(self._clients)

    @property
    def port(self) -> int:
        """The bound TCP port (the real one when configured as 0)."""
        if self._server is not None and self._server.sockets:
            return int(self._server.sockets[0].getsockname()[1])
        return self._configured_port

    @property
    def client_count(self) -> int:
        """Sessions (admitted connections)."""
        return len(self._sessions)

    @property
    def pending_count(self) -> int:
        """Connections not admitted yet."""
        return len(self._pending)

    def pool_stats(self) -> dict[str, Any]:
        """Pool sizes and counters, JSON-ready: ``clients`` (sessions), ``pending``,
        ``dropped`` (events dropped for slow readers), ``closed`` (connections the server
        closed, by reason)."""
        return {
            "clients": len(self._sessions),
            "pending": len(self._pending),
            "dropped": self.dropped_total,
            "closed": dict(self.closed_counts),
        }

    def _listening(self, server: asyncio.Server) -> None:
        """Subclasses call this once bound: starts the deadline sweeper."""
        self._server = server
        self._sweeper = asyncio.create_task(self._sweep_loop())

    async def close(self) -> None:
        """Stop listening and disconnect every client (idempotent)."""
        if self._server is not None:
            self._server.close()
            self._server = None
        if self._sweeper is not None:
            self._sweeper.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._sweeper
            self._sweeper = None
        for c in list(self._clients):
            c.closed = True
            c.wake.set()
            c.drained.set()
            with contextlib.suppress(Exception):  # one odd connection must not keep the rest
                c.writer.close()
        for t in list(self._tasks):
            t.cancel()
        if self._tasks:
            await asyncio.gather(*self._tasks, return_exceptions=True)

    # -- pools ----------------------------------------------------------------------------
    def _is_watching(self, c: C) -> bool:
        """True if the client asked for a stream of events (not idle while it does)."""
        return False

    def _notice(self, reason: str, message: str) -> bytes:
        """The protocol's last line to a connection the server closes (each protocol words
        its own; this plain line is the fallback)."""
        return f"closing: {reason}: {message}\r\n".encode("utf-8", "replace")

    def _connected(self, c: C) -> None:
        """Register a new connection as pending; make room in the pending pool if full."""
        c.t_connect_s = c.t_active_s = self._clock()
        self._clients.add(c)
        self._pending[c] = None
        if len(self._pending) > self.max_pending:
            victim = self._pending_victim(exclude=c)
            self._evict(
                victim,
                PENDING_FULL,
                f"{self.max_pending} connections waiting to be admitted; a newer one needs room",
            )

    def _pending_victim(self, exclude: C) -> C:
        # the address holding the most pending connections pays (a remote operator is not
        # crowded out by a local swarm); within it, a peer that already sent garbage or a
        # wrong token goes first, then the oldest that has no input waiting: an operator
        # sends auth at once, and after a pause a burst of newer connections must not close
        # it before its handler has read that line (a fresh operator is also the newest)
        per_host = collections.Counter(c.host for c in self._pending if c is not exclude)
        busiest = max(per_host.values())
        candidates = [c for c in self._pending if c is not exclude and per_host[c.host] == busiest]
        suspect = next((c for c in candidates if c.suspect), None)
        if suspect is not None:
            return suspect
        # then the oldest that has sent nothing since it connected: an operator's client
        # speaks at once (its auth; over TLS first its ClientHello, then it waits for the
        # server's reply with nothing to read, where the rule below would close it when it
        # is the oldest): a flood of silent sockets goes before it. Oldest first, stopping
        # at the first silent one (one getsockopt per eviction while they are the flood)
        quiet = next((c for c in candidates if silent(c.writer.transport)), None)
        if quiet is not None:
            return quiet
        # then the oldest the server has sent nothing: a peer that sent a byte (or a partial
        # line or ClientHello) and stalled has had no answer, an operator mid-handshake has
        # (the server's reply to its ClientHello); one getsockopt each, oldest first
        # and no whole request waiting to be read (an operator whose auth has arrived but
        # not been read yet has had no answer either: a review)
        mute = next(
            (c for c in candidates if unanswered(c.writer.transport) and not request_waiting(c)),
            None,
        )
        if mute is not None:
            return mute
        # oldest first, stopping at the first idle one: usually one ioctl per eviction
        return next((c for c in candidates if unread_bytes(c) == 0), candidates[0])

    def _promote(self, c: C) -> None:
        """Admit a pending connection to the session pool, making room when the pool is full:
        sessions whose peer has already hung up leave it first (they hold no slot: in a
        connect/close storm the kernel hands over many connections at once, each admitted
        before its end of stream is read), else the least valuable session is closed. An
        admitted peer always gets in."""
        if c.session or c.evicted:
            return
        self._pending.pop(c, None)
        if len(self._sessions) >= self.max_clients:
            self._reap_gone()
        if len(self._sessions) >= self.max_clients:
            victim = self._session_victim(c)
            self._evict(
                victim,
                SESSIONS_FULL,
                f"{self.max_clients} sessions open; made room for {c.peer}",
            )
        self._sessions.add(c)
        c.session = True

    def _session_victim(self, admitted: C) -> C:
        """The session to close for ``admitted``: never a :meth:`_protected` one (unless all
        are: ``max_clients`` 1). If no address holds more sessions than ``admitted``'s (it
        counted with its own), one of that address's own by :meth:`_victim_key`: a storm
        from one address closes its own (fdb4cad), also where the cheapest session is
        another address's idle one (cd61371 put kind first everywhere, so each connection of
        a watcher storm closed a non-watching client elsewhere: review 10c). Otherwise, or
        if it has none to close, the least valuable kind first, then the address holding
        the most sessions, then the rest of the key: an idle session anywhere goes before a
        live watcher, and a peer from a fresh address (none of its own) closes another's
        (cd61371: the address first closed a driving operator's session, its own watcher
        making the address the busiest, before an idle one elsewhere)."""
        per_host = collections.Counter(s.host for s in self._sessions)
        per_host[admitted.host] += 1
        candidates = [s for s in self._sessions if not self._protected(s)] or list(self._sessions)
        now = self._clock()
        if per_host[admitted.host] == max(per_host.values()):
            own = [s for s in candidates if s.host == admitted.host]
            if own:
                return min(own, key=lambda s: self._victim_key(s, now))

        def key(s: C) -> tuple[int, int, float, float]:
            kind, first, second = self._victim_key(s, now)
            return (kind, -per_host[s.host], first, second)

        return min(candidates, key=key)

    def _protected(self, c: C) -> bool:
        """A session a full pool must not close to make room (the control port: the one
        whose manual drive runs). None here."""
        return False

    def _reap_gone(self) -> None:
        """Take the sessions whose peer has already closed or reset its connection out of
        the session pool (:func:`peer_gone`). They are not closed here, nor counted: each
        one's handler still answers what it had read and ends at the end of its input, as
        it would have anyway; it only stops holding a slot (and getting events)."""
        for s in [s for s in self._sessions if peer_gone(s)]:
            self._sessions.discard(s)

    def _behind_s(self) -> float:
        """A watcher not reading for this long (s) is behind; under it, it keeps up. The
        sweeper's view of a peer's acknowledgements is up to one sweep period old, so a
        healthy reader with data in flight at the last sweep looks stalled for up to that
        long: twice the period is past that noise, and well short of ``slow_client_s``."""
        return min(2.0 * self._sweep_period_s(), self.slow_client_s / 2.0)

    def _victim_key(self, c: C, now: float) -> tuple[int, float, float]:
        """Sort key of sessions, least valuable first: not watching before watching; among
        those not watching the one idle longest; then the watchers behind (not reading for
        :meth:`_behind_s` or more), the one not reading longest first, then the one with
        most events queued; then those that keep up, the newest first: one that has
        streamed for a while has shown it reads, one just admitted has not (and in a
        connect storm is likely one of the storm). Events dropped long ago do not count
        against a watcher that reads now."""
        if not self._is_watching(c):
            return (0, c.t_active_s, 0.0)
        stalled_s = max(
            0.0 if c.drain_since_s is None else now - c.drain_since_s,
            0.0 if c.stalled_since_s is None else now - c.stalled_since_s,
        )
        if stalled_s >= self._behind_s():
            return (1, -stalled_s, -float(len(c.events)))
        return (2, -c.t_connect_s, 0.0)

    def _forget(self, c: C) -> None:
        self._clients.discard(c)
        self._pending.pop(c, None)
        self._sessions.discard(c)

    def _count_close(self, c: C, reason: str, message: str) -> None:
        """Count and (rate-limited) log a close the server decided."""
        self.closed_counts[reason] += 1
        self._rlog.log(
            f"{self.label}: {reason} closes",
            logging.WARNING,
            "%s: closing %s (%s): %s",
            self.label,
            c.peer,
            reason,
            message,
        )

    def _evict(self, c: C, reason: str, message: str) -> None:
        """Close a connection now: a last notice if its socket takes it at once (never for a
        peer that does not read), drop what is queued, end its handler. Never waits."""
        if c.evicted:
            return  # (one whose socket failed is still evicted: it leaves the pools now)
        self._count_close(c, reason, message)
        self._forget(c)
        c.evicted = reason
        c.closed = True
        c.events.clear()
        c.replies.clear()
        c.wake.set()
        c.drained.set()
        transport = c.writer.transport
        # one still in its TLS handshake gets no notice (no plain text into TLS) and is reset:
        # its handshake ends at once, and with it the handler
        polite = reason != SLOW_READER and not c.handshaking
        with contextlib.suppress(Exception):
            if polite and write_buffer_size(transport) == 0:
                transport.write(self._notice(reason, message))
            if polite and write_buffer_size(transport) == 0:
                close_promptly(transport)
            else:  # it does not read: do not keep the socket open for its buffer
                reset(transport)
        # The aborted socket ends the handler's read and the sender's drain by itself; only a
        # handler sleeping out a back-off is cancelled (cancelling costs reference cycles the
        # garbage collector must find: a connect-churn storm would make it pause the process)
        task = c.task
        if c.napping and task is not None and task is not asyncio.current_task():
            task.cancel()

    # -- deadlines ------------------------------------------------------------------------
    def sweep(self) -> int:
        """Close every connection past a deadline (pending, idle, slow reader) at the
        server clock's now; return how many. The sweeper calls this periodically; tests with
        an injected clock may call it directly."""
        now = self._clock()
        closed = 0
        for c in list(self._clients):
            if c.closed:
                continue
            try:  # one connection in a state nobody foresaw must not exempt the others
                closed += self._sweep_one(c, now)
            except Exception as exc:
                self._sweep_failed(c, "deadline check", exc)
        self._rlog.flush()
        return closed

    def _sweep_one(self, c: C, now: float) -> int:
        """Close ``c`` if it is past a deadline; 1 if it was closed."""
        try:
            stalled_s = self._stalled_s(c, now)
        except Exception as exc:  # its pending and idle deadlines still hold
            self._sweep_failed(c, "send-queue check", exc)
            stalled_s = 0.0
        if c.drain_since_s is not None:  # the sender waits in drain(): no room at all
            stalled_s = max(stalled_s, now - c.drain_since_s)
        if stalled_s >= self.slow_client_s:
            self._evict(c, SLOW_READER, f"has not read for {stalled_s:.1f} s")
        elif not c.session and now - c.t_connect_s >= self.pending_timeout_s:
            self._evict(
                c,
                self.pending_timeout_reason,
                f"not admitted within {self.pending_timeout_s:g} s",
            )
        elif c.session and not self._is_watching(c) and now - c.t_active_s >= self.idle_timeout_s:
            self._evict(c, IDLE_TIMEOUT, f"idle for {now - c.t_active_s:.1f} s")
        else:
            return 0
        return 1

    def _sweep_failed(self, c: C, what: str, exc: Exception) -> None:
        """Log (at most once per second) a sweep step that failed for one connection; the
        sweep goes on with the others."""
        self._rlog.log(
            f"{self.label}: sweep errors",
            logging.ERROR,
            "%s: %s of %s failed (the sweep goes on): %s: %s",
            self.label,
            what,
            c.peer,
            type(exc).__name__,
            exc,
        )

    @staticmethod
    def _stalled_s(c: C, now: float) -> float:
        """Seconds the peer has acknowledged none of the data waiting for it (0 when nothing
        waits, or when the kernel cannot tell)."""
        transport = c.writer.transport
        outq = unacknowledged_bytes(transport)
        if outq is None:
            return 0.0
        waiting = outq + write_buffer_size(transport)
        acked = c.bytes_out - waiting
        if waiting == 0:
            c.stalled_since_s = None
        elif acked != c.acked_out or c.stalled_since_s is None:
            c.stalled_since_s = now  # progress (or the first look): the stall starts now
        c.acked_out = acked
        return 0.0 if c.stalled_since_s is None else now - c.stalled_since_s

    def _sweep_period_s(self) -> float:
        # a quarter of the shortest deadline: closes happen at most 25 % late; one timer for
        # the whole server, not one per connection
        shortest = min(self.pending_timeout_s, self.idle_timeout_s, self.slow_client_s)
        return min(1.0, max(0.02, shortest / 4.0))

    async def _sweep_loop(self) -> None:
        period = self._sweep_period_s()
        while True:
            await asyncio.sleep(period)
            try:
                self.sweep()
            except Exception:  # a bug here must not end deadline enforcement
                _log.exception("%s: deadline sweep failed", self.label)

    # -- per connection -------------------------------------------------------------------
    async def _nap(self, c: C, seconds: float) -> None:
        """Sleep out a back-off; an eviction meanwhile ends it (the handler is cancelled)."""
        c.napping = True
        try:
            await asyncio.sleep(seconds)
        finally:
            c.napping = False

    async def _hang_up(self, c: C, reader: asyncio.StreamReader | None = None) -> None:
        """End a connection: let its sender flush (at most 1 s; an evicted one stops at
        once), close, forget it."""
        if reader is not None and reader.exception() is not None:
            # a socket error kept by the reader holds the frames it was raised in, which
            # lead back to the reader: replace it by one without a traceback so reference
            # counting frees the connection (a churn storm must not feed the collector)
            reader.set_exception(ConnectionResetError("connection closed"))
        self._forget(c)
        c.closed = True
        c.wake.set()
        sender = c.sender
        if sender is not None:
            with contextlib.suppress(asyncio.TimeoutError, asyncio.CancelledError):
                await asyncio.wait_for(sender, 1.0)
        transport = c.writer.transport
        with contextlib.suppress(Exception):
            if write_buffer_size(transport) > 0:
                reset(transport)  # a peer that does not read: do not wait for it
            else:
                close_promptly(transport)
        if c.task is not None:
            self._tasks.discard(c.task)
        if reader is not None:
            release_input(reader)
        c.task = c.sender = c.reader = None  # no cycle through the client: refcounting frees it

    async def _sender(self, c: C) -> None:
        try:
            while True:
                while (c.replies or c.events) and not c.evicted:
                    # replies (never dropped) go before queued events
                    batch = b"".join(c.replies) + b"".join(c.events)
                    c.replies.clear()
                    c.events.clear()
                    c.writer.write(batch)
                    c.bytes_out += len(batch)
                    # the sweeper closes a sender stuck here for slow_client_s
                    c.drain_since_s = self._clock()
                    await c.writer.drain()
                    c.drain_since_s = None
                c.drained.set()
                if c.closed:
                    return
                c.wake.clear()
                await c.wake.wait()
        except (ConnectionError, OSError, ssl.SSLError):
            c.closed = True
            c.drained.set()
