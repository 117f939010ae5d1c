"""An evicted connection whose handler is sleeping out a back-off (CI, round 19).

Eviction closes the socket and cancels a napping handler. On Python 3.11, ``wait_for`` drops
a cancel that arrives as its read completes; the handler then slept out the rest of its
back-off holding the connection it had lost (a flood test's evicted client was still in
memory after 5 s, with the garbage collector off). The nap now also ends once the
connection is closed, cancelled or not."""

from __future__ import annotations

import socket
import time

from tests.test_lineserver_flood_round8 import TrackedControlServer
from tests.test_server import TOKEN, LoopThread, RecordingBackend, loop_thread  # noqa: F401
from x6wd.core.config import ServerConfig


def test_a_closed_connection_ends_its_back_off_without_the_cancel(
    loop_thread: LoopThread,  # noqa: F811
) -> None:
    # half an error reply a second: past its burst of 5 the client waits 7 s per line
    cfg = ServerConfig(port=0, rate_per_s=0.5, auth_timeout_s=60.0)
    srv = TrackedControlServer(cfg, RecordingBackend(), token=TOKEN.encode())
    loop_thread.run(srv.start())
    try:
        with socket.create_connection(("127.0.0.1", srv.port), timeout=5) as s:
            s.sendall(b"x\n" * 20)  # garbage past the fault budget: its replies are paced
            t0 = time.monotonic()
            while not loop_thread.call(lambda: bool(srv.seen) and srv.seen[0][0]().napping):
                assert time.monotonic() - t0 < 5.0, "the garbage never began a back-off"
                time.sleep(0.01)
            c = srv.seen[0][0]()
            task = c.task

            def evicted_but_not_cancelled() -> None:
                c.closed = True
                c.evicted = "test"
                c.writer.transport.abort()

            loop_thread.call(evicted_but_not_cancelled)
            t0 = time.monotonic()
            while not task.done() and time.monotonic() - t0 < 5.0:
                time.sleep(0.01)
            took_s = time.monotonic() - t0
        assert task.done() and took_s < 1.0, f"the handler slept on {took_s:.1f} s"
    finally:
        loop_thread.run(srv.close())
