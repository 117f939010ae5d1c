"""What the two TCP line servers share (the remote-control server and the gpsd port).

Each client has two outboxes: ``replies`` (answers to its own requests, never dropped) and
``events`` (unsolicited reports, bounded: the oldest is dropped and counted when full), and
one sender task that writes them. So a slow or stuck reader only ever fills its own bounded
queue; nothing the control loop does waits for a socket.
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import ssl
from dataclasses import dataclass, field
from typing import Any, Generic, TypeVar


@dataclass(eq=False, kw_only=True)
class LineClient:
    """One connection's outboxes and state (subclassed per protocol)."""

    writer: asyncio.StreamWriter
    events: collections.deque[bytes] = field(default_factory=collections.deque)
    replies: collections.deque[bytes] = field(default_factory=collections.deque)
    wake: asyncio.Event = field(default_factory=asyncio.Event)
    drained: asyncio.Event = field(default_factory=asyncio.Event)  # outboxes written out
    dropped: int = 0
    closed: bool = False

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


class LineServer(Generic[C]):
    """Listening socket, client set and task bookkeeping, shutdown and the sender loop."""

    def __init__(self, configured_port: int) -> None:
        self._configured_port = configured_port
        self._server: asyncio.Server | None = None
        self._clients: set[C] = set()
        self._tasks: set[asyncio.Task[None]] = set()
        self.dropped_total = 0

    @property
    def port(self) -> int:
        """The bound TCP port (the real one when configured as 0)."""
        if self._server is not None and self._server.sockets:
            return int(self._server.sockets[0].getsockname()[1])
        return self._configured_port

    @property
    def client_count(self) -> int:
        """Connected clients."""
        return len(self._clients)

    async def close(self) -> None:
        """Stop listening and disconnect every client (idempotent)."""
        if self._server is not None:
            self._server.close()
            self._server = None
        for c in list(self._clients):
            c.closed = True
            c.wake.set()
            c.drained.set()
            c.writer.close()
        for t in list(self._tasks):
            t.cancel()
        if self._tasks:
            await asyncio.gather(*self._tasks, return_exceptions=True)

    async def _hang_up(
        self, c: C, sender: asyncio.Task[None] | None, task: asyncio.Task[Any] | None
    ) -> None:
        """End a connection: let its sender flush (at most 1 s), close, forget it."""
        self._clients.discard(c)
        c.closed = True
        c.wake.set()
        if sender is not None:
            with contextlib.suppress(asyncio.TimeoutError, asyncio.CancelledError):
                await asyncio.wait_for(sender, 1.0)
        c.writer.close()
        if task is not None:
            self._tasks.discard(task)

    async def _sender(self, c: C) -> None:
        try:
            while True:
                while c.replies or c.events:
                    # replies (never dropped) go before queued events
                    batch = b"".join(c.replies) + b"".join(c.events)
                    c.replies.clear()
                    c.events.clear()
                    c.writer.write(batch)
                    await c.writer.drain()
                c.drained.set()
                if c.closed:
                    return
                c.wake.clear()
                await c.wake.wait()
        except (ConnectionError, OSError, ssl.SSLError):
            c.closed = True
            c.drained.set()
