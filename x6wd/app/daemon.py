"""``x6wd run --config FILE``: the asyncio daemon that wires devices, controller and servers.

Threads do the blocking device I/O (GPS port reads, I2C reads, motor writes, recorder
writes). The sans-IO controller is touched by one thread at a time, under one lock (the
control lock): the GPS thread decides on a fix itself, right after decoding it, and writes
the resulting motor command to the link itself when the link is idle (no hop to the event
loop, none to the motor thread: GGA-to-motor latency); everything else that touches the
controller (compass samples, ticks, health changes, operator requests) runs on the event
loop. The motor thread, which owns the link, also polls the wheel encoders (20 Hz) between
commands. Data flow::

    gps thread ──fix──> Controller (control lock) ──> motor link (or the motor thread if busy)
    compass thread ─att───┐                 ┌─> motor thread ─> motor link
    motor thread ─odometry┤                 │
    control tick (20 Hz) ─┼─> loop: Controller ─> telemetry ─> server / gpsd port / recorder
    health, operator ─────┘                 └─> sd_notify (WATCHDOG / STATUS)

Safety: the controller holds (motors stopped) on stale input, lost motor link and dead-man
expiry; the daemon additionally stops the motors on any exit path. Every signal whose default
action would kill the process (but the faults' own: SIGABRT, below, SIGSEGV ...) stops the
motors and shuts down cleanly (:func:`stop_signals`; never lost, however long the loop was
stalled: :class:`_SignalLoop`):
SIGTERM, SIGINT and SIGHUP (a closed terminal) exit 0; the others (SIGQUIT, SIGUSR1 ...,
which nothing should send x6wd) exit 1, so systemd restarts us. An unexpected exception in
any thread, the motor thread's included, stops the motors and exits 1. The recording ends
with the stop (a motor record 0/0, the change to IDLE) and a ``shutdown`` event naming the
cause and the exit code, so a clean exit is told apart from a crash or a power cut. The
recorder never holds up the motors' stop or the shutdown: its thread gets
:data:`RECORDER_CLOSE_S` to drain, then is left behind; a thread stuck inside the kernel on a
hung disk (a frozen file system, a dead SD card: uninterruptible sleep) keeps the process
from ending until the disk returns (its other threads are gone, the motors long stopped).
SIGABRT is not handled: it is systemd's watchdog signal, sent when the control loop has not
fed the watchdog, i.e. when it is hung and could not run a shutdown; the default action
(a core dump) stays, and the motor board's watchdog stops the wheels.
"""

from __future__ import annotations

import argparse
import asyncio
import collections
import contextlib
import errno
import functools
import gc
import ipaddress
import logging
import math
import os
import queue
import re
import signal
import socket
import stat
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, cast

from drivers.gps_nmea import NmeaSentence
from x6wd import __version__
from x6wd.app.console import ConsoleServer
from x6wd.app.gpsd import GpsdServer
from x6wd.app.notify import Notifier
from x6wd.app.server import ControlServer, server_ssl_context
from x6wd.core.config import Config, check_gps_line, check_plaintext, plaintext_binds
from x6wd.core.config import load as load_config
from x6wd.core.errors import CommandError, ConfigError, DeviceUnavailable, X6wdError
from x6wd.core.geodesy import great_circle_m
from x6wd.core.health import HealthLog, HealthTracker
from x6wd.core.mission_files import Waypoint
from x6wd.core.records import (
    Attitude,
    DeviceHealth,
    GpsFix,
    GpsSky,
    HealthEvent,
    MotorCommand,
    StateChange,
    Telemetry,
    WheelOdometry,
)
from x6wd.loop.runner import Runner, every, run_realtime

log = logging.getLogger("x6wd.app.daemon")

TICK_HZ = 20.0
"""Controller tick rate: bounds the dead-man and staleness reaction time (s = 1/TICK_HZ)."""
GIL_SWITCH_S = 0.001
NET_NICE = 10
"""How much nicer (lower scheduling priority) the network thread runs than the daemon."""
MOTOR_REPEAT_S = 1.0 / TICK_HZ
"""The same motor command from the event loop (compass samples, ticks) is sent at most this
often (s); the keep-alive repeats it in between when needed, a fix's command always goes."""
ODOMETRY_HZ = 20.0
"""Wheel-encoder poll rate (docs/motors.md, "Wheel encoders"): the motor thread sends ``E``."""
ODOMETRY_GIVE_UP_AFTER = 5
"""Encoder requests refused (ERR) or unanswered in a row (before any reading, for the
unanswered) before the encoders count as unavailable: one ERR from a board still booting
or a line glitch must not turn the odometry off."""
ODOMETRY_RETRY_S = 10.0
"""While unavailable, the encoders are asked again this often (s): a board that comes back
with its encoders (rebooted, firmware updated, its ERR a transient) is polled again."""
OPERATOR_SEEN_S = 0.25
"""An operator's requests reach the controller's operator-link failsafe at most this often
(s): a client polling ``status`` in a loop must not load the control loop."""
REOPEN_BACKOFF_S = (0.1, 5.0)
"""First and longest wait between attempts to reopen a lost compass bus (s)."""
EXIT_OK = 0
EXIT_FAILURE = 1
EXIT_CONFIG = 2
"""A configuration error: restarting cannot help (the unit has RestartPreventExitStatus=2)."""
MOTORS_UNCONFIRMED = (
    "the motors' stop was NOT acknowledged by the board: only its own watchdog stops them"
)
"""Said at exit (log, the control port's clients) when the link could not confirm the stop;
the exit is then 1, not 0."""
DEVICE_POLL_S = 0.1
"""While start-up waits for a missing device node ([startup] device_wait_s), it looks again
this often (s): a stat each, cheap; a stop signal ends the wait at once."""
START_MARGIN_S = 60.0
"""Start-up time (s) asked of systemd beyond the device wait (EXTEND_TIMEOUT_USEC): opening
the devices after it, so that a long device_wait_s never meets the unit's start timeout."""
GC_FULL_S = 10.0
"""Most seconds between two full collections of the paced garbage collector (:class:`_GcPacer`)."""
GC_OVERDUE_S = 2.5
"""Without a GPS fix for this long (s), the event loop collects instead of the GPS thread."""
RECORDER_FSYNC_S = 5.0
"""fsync period of the recording (s): what a power cut can lose. A crash or ``kill -9`` loses
no written record either way (each is one ``write()``), only what is queued for the writer."""
RECORDER_QUEUE_MAX = 10_000
"""Records queued for the recorder thread at most (about a minute of the daemon's ~150
records/s, a few MB); more are dropped and counted: a stuck disk must not grow the memory."""
RECORDER_STALL_S = 5.0
"""A recorder call taking this long (s) makes the recorder "stalled" in ``status``."""
RECORDER_LOG_S = 60.0
"""While the recorder fails or drops records, one summary log line per this many seconds."""
SHUTDOWN_LOCK_S = 0.2
"""At exit, how long (s) the shutdown waits for the control lock to stop the controller (a
decision holds it for about a millisecond); a thread stuck holding it does not hold up the
motors' stop, whose record is then written without the controller."""
RECORDER_CLOSE_S = 3.0
"""At exit, how long (s) the recorder thread may take to drain its queue and close the file;
a thread stuck in the file system is left behind: the shutdown goes on (the motors stopped
before), but a thread asleep in the kernel on a hung disk keeps the process from ending until
the disk returns (docs/install.md, "Signals")."""
NET_QUEUE_MAX = 2000
"""Calls queued for the network thread's loop at most before publications are dropped
(about half a minute of the daemon's ~60 a second): a stalled network thread (blocked on a
full stderr pipe: a journald that stopped reading) must not grow the memory with telemetry
nobody receives. State changes for the network side (the gpsd port's device, the GPS
state, the declination) are always queued; the drops are counted and logged by the network
thread once it runs again."""


distance_m = great_circle_m  # the geofence's distance (m), kept under its old name


class LogTail(logging.Handler):
    """Keeps the last ``n`` formatted log lines for the protocol's ``log`` command."""

    def __init__(self, n: int = 1000) -> None:
        super().__init__(logging.INFO)
        self.lines: collections.deque[str] = collections.deque(maxlen=n)
        self.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))

    def emit(self, record: logging.LogRecord) -> None:
        try:
            self.lines.append(self.format(record))
        except Exception:  # logging must never raise into the caller
            self.handleError(record)

    def tail(self, n: int) -> list[str]:
        """The last ``n`` lines, oldest first."""
        if n <= 0:
            return []
        return list(self.lines)[-n:]


class _MotorWorker:
    """Owns the motor link in its own thread: the newest command wins, resent as keep-alive.

    An operator stop is the exception: it holds (:meth:`hold_stop`) until the controller has
    applied it (:meth:`stop_applied`); meanwhile a drive (non-zero) command, submitted or
    sent directly, is dropped, so none decided before the controller had the stop can
    replace it or follow it out. A zero command always goes through.

    ``on_health(ok, t_s)`` is called (from this thread) when the link's health changes;
    ``on_events(events)`` with the link's health events (transitions, failures while lost).
    ``on_odometry(rec)``: the thread also polls the board's wheel encoders
    (``link.read_odometry``) every ``odometry_s`` while the link is healthy and nothing is
    queued, and hands each reading over. A backend without encoders turns the polling off
    for good; a board that refuses ``E``, or does not answer it before any reading,
    :data:`ODOMETRY_GIVE_UP_AFTER` times in a row makes the odometry "unavailable" (logged
    once), asked again every :data:`ODOMETRY_RETRY_S` and polled again once it answers.
    """

    def __init__(
        self,
        link: Any,
        keepalive_s: float,
        on_health: Callable[[bool, float], None],
        on_events: Callable[[list[HealthEvent]], None] | None = None,
        on_odometry: Callable[[WheelOdometry], None] | None = None,
        odometry_s: float = 1.0 / ODOMETRY_HZ,
        on_death: Callable[[BaseException], None] | None = None,
    ) -> None:
        """``on_death(exc)``: the thread died of ``exc`` (a bug); the motors were stopped
        (best effort) first. The daemon passes its :meth:`Daemon.fail_from_thread`."""
        self.link = link
        self.keepalive_s = keepalive_s
        self._on_health = on_health
        self._on_events = on_events
        # A backend without its own health record gets one here, from ``healthy``.
        self._own: HealthTracker | None = None
        if not hasattr(link, "take_health_events"):
            self._own = HealthTracker("motors", t_s=time.monotonic())
            self._own.opened(time.monotonic())
        self.link_errors = 0
        self._cond = threading.Condition()
        self._pending: MotorCommand | None = None
        self._last: MotorCommand | None = None
        self._t_submit = time.monotonic()
        self._t_sent = self._t_submit  # end of the latest send (s): the keep-alive counts from it
        self._busy = False  # a send is in progress (this thread or a send_now caller)
        self._polling = False  # the send in progress is an encoder poll (this thread)
        self._acked = True  # the latest send went through (send_now may then send directly)
        self._stop = False
        # The operator stop that holds (its number, 0: none) and the last number given out.
        self._latched = 0
        self._latch_seq = 0
        self.dropped_while_stopping = 0  # drive commands dropped while an operator stop held
        self._verdict = threading.local()  # per caller: whether its latest command was held
        # What the controller was told: it starts with the link up, so a link that is not
        # (a board silent from power-up) is a change that start() reports at once.
        self._healthy = True
        self.direct_sent = 0  # commands sent by send_now in its caller's thread
        self.repeats_skipped = 0  # commands submit() did not send again (repeat_after_s)
        self.sent = 0
        self._on_odometry = on_odometry
        self.odometry_s = odometry_s
        self.odometry_readings = 0
        self.odometry_failures = 0
        self.odometry_state = "off"  # "polling", "unavailable" or "off" (nobody takes them)
        self.odometry_reason = ""
        # a backend with encoders and a taker: asked while polling, and while unavailable
        # every ODOMETRY_RETRY_S
        self._has_encoders = False
        self._odo_fail_run = 0  # requests refused or unanswered in a row
        if on_odometry is not None:
            if callable(getattr(link, "read_odometry", None)):
                self.odometry_state = "polling"
                self._has_encoders = True
            else:
                self._odometry_unavailable("the motor backend has no wheel encoders")
        self._t_odo = time.monotonic()  # when the next encoder poll is due
        self._on_death = on_death
        self.thread = guarded_thread(self._run, "x6wd-motors", self._died)

    def start(self) -> None:
        """Report the link's health as it is now (a link that never reached its board is
        lost before any command is accepted), then start the thread."""
        self._after_io()
        self.thread.start()

    @property
    def idle(self) -> bool:
        """No command being sent, nothing queued (an encoder poll in progress is idle: no
        command waits for it, and it is not urgent)."""
        with self._cond:
            return not (self._busy and not self._polling) and self._pending is None

    def submit(self, cmd: MotorCommand, repeat_after_s: float = 0.0) -> None:
        """Queue ``cmd`` (replacing an unsent one); never blocks on I/O.

        ``repeat_after_s`` (s): a command equal to the last one sent (same drive, same
        reason), which went through less than this long ago with nothing queued or being
        sent, is not sent again (it still counts as a submission for the keep-alive's
        silence rule, and the keep-alive repeats it). The controller answers every compass
        sample and tick with a command, mostly the same one: sending each would keep the
        link busy when a fix's command comes (it then waits for the send in progress).

        A drive while an operator stop holds (:meth:`hold_stop`) is dropped."""
        with self._cond:
            if self._held(cmd):
                return
            now = time.monotonic()
            self._t_submit = now
            last = self._last
            if (
                repeat_after_s > 0.0
                and last is not None
                and self._pending is None
                and not self._busy
                and self._acked
                and now - self._t_sent < repeat_after_s
                and (last.left_pct, last.right_pct, last.reason)
                == (cmd.left_pct, cmd.right_pct, cmd.reason)
            ):
                self.repeats_skipped += 1
                return
            self._pending = cmd
            self._cond.notify_all()

    def send_now(self, cmd: MotorCommand) -> bool:
        """Send ``cmd`` from the calling thread when the link is idle (no send in progress,
        nothing queued) and its latest send went through; otherwise queue it as
        :meth:`submit` does. True when it was sent here.

        Saves the motor thread's wake-up (a GIL hand-over behind whatever thread holds it)
        on the path from a GPS fix to the wheels. Blocks for the link's acknowledgement; a
        link that failed its latest send is only used from the motor thread, so a dead
        board never stalls the caller for more than one send. A drive while an operator
        stop holds (:meth:`hold_stop`) is dropped (False)."""
        with self._cond:
            self._verdict.held = False
            if self._stop:  # after shutdown() nothing may reach the motors
                return False
            if self._held(cmd):
                return False
            self._t_submit = time.monotonic()
            if self._busy or self._pending is not None or not (self._acked and self._healthy):
                self._pending = cmd
                self._cond.notify_all()
                return False
            self._busy = True
        try:
            self._send(cmd)
            self.direct_sent += 1
        finally:
            with self._cond:
                self._busy = False
                self._cond.notify_all()
        return True

    def hold_stop(self) -> int:
        """An operator stop comes: from now until :meth:`stop_applied` is called with the
        number returned (or a later stop's), :meth:`submit` and :meth:`send_now` drop every
        drive command, so the stop the caller submits next replaces any unsent command, goes
        out, and nothing the controller decided before it had the stop follows it. Zero
        commands go through. Never blocks on I/O."""
        with self._cond:
            self._latch_seq += 1
            self._latched = self._latch_seq
            return self._latch_seq

    def clear_restart_fault(self) -> None:
        """The operator stopped or paused: a motor board's latched restart fault (repeated
        brown-outs) may end at the next confirmed stop. Links without one ignore it."""
        clear = getattr(self.link, "clear_restart_fault", None)
        if clear is not None:
            clear()

    def stop_applied(self, seq: int) -> None:
        """The controller has applied the operator stop numbered ``seq`` (the daemon calls
        this under the control lock, once the controller has stopped): drive commands go
        through again, unless a later operator stop holds."""
        with self._cond:
            if self._latched and seq >= self._latched:
                self._latched = 0

    def last_held(self) -> bool:
        """Whether the latest command this thread gave :meth:`submit` or :meth:`send_now`
        was dropped by an operator stop's hold (decided under the worker's lock, so a hold
        that begins meanwhile cannot make a dropped command read as sent)."""
        return bool(getattr(self._verdict, "held", False))

    @property
    def stop_holding(self) -> bool:
        """An operator stop holds: drive commands are dropped until the controller has it."""
        with self._cond:
            return self._latched != 0

    def _held(self, cmd: MotorCommand) -> bool:
        """``cmd`` is a drive while an operator stop holds: count it (it is dropped). Called
        with ``_cond`` held."""
        held = bool(self._latched) and not cmd.is_stop
        self._verdict.held = held
        if not held:
            return False
        self.dropped_while_stopping += 1
        if self.dropped_while_stopping in (1, 10, 100) or self.dropped_while_stopping % 1000 == 0:
            log.info(
                "operator stop: a drive command dropped until the controller has the stop "
                "(%d so far)",
                self.dropped_while_stopping,
            )
        return True

    def _run(self) -> None:
        while True:
            poll = False
            with self._cond:
                while not self._stop:
                    if self._busy:  # a send_now in another thread: wait for its end
                        self._cond.wait()
                        continue
                    if self._pending is not None:
                        break
                    now = time.monotonic()
                    left_s = self._t_sent + self.keepalive_s - now
                    if left_s <= 0:
                        break
                    if self._has_encoders and self._healthy:
                        odo_s = self._t_odo - now
                        if odo_s <= 0:
                            poll = True
                            break
                        left_s = min(left_s, odo_s)
                    self._cond.wait(left_s)
                if self._stop:
                    return
                if poll:
                    cmd = None
                else:
                    cmd, self._pending = self._pending, None
                self._busy = True
                self._polling = poll
            if poll:  # the link is ours: one E and its reply, like any send
                try:
                    self._poll_odometry()
                finally:
                    with self._cond:
                        self._busy = self._polling = False
                        self._cond.notify_all()
                continue
            try:
                if cmd is None:
                    now = time.monotonic()
                    if (
                        self._last is None
                        or self._last.is_stop
                        or now - self._t_submit > 3.0 * self.keepalive_s
                    ):
                        # The controller submits at >= 20 Hz; silence means the control loop
                        # is stuck, so the keep-alive must not keep the robot driving: stop.
                        cmd = MotorCommand(now, 0.0, 0.0, "keepalive")
                    else:
                        cmd = self._last
                self._send(cmd)
            finally:
                with self._cond:
                    self._busy = False
                    self._cond.notify_all()

    @property
    def health(self) -> DeviceHealth:
        """The motor link's health (the link's own record, else one kept from ``healthy``)."""
        if self._own is not None:
            return self._own.health
        health: DeviceHealth = self.link.health
        return health

    def _odometry_unavailable(self, reason: str) -> None:
        self.odometry_state = "unavailable"
        self.odometry_reason = reason
        if self._has_encoders:
            log.warning(
                "wheel odometry unavailable: %s; asking again every %g s",
                reason, ODOMETRY_RETRY_S,
            )  # fmt: skip
        else:
            log.warning("wheel odometry unavailable: %s; not polling the encoders", reason)

    def _poll_odometry(self) -> None:
        """Read the encoders once (this thread owns the link: ``_busy`` is set)."""
        period_s = self.odometry_s if self.odometry_state == "polling" else ODOMETRY_RETRY_S
        rec: WheelOdometry | None = None
        try:
            rec = self.link.read_odometry()
        except Exception as exc:  # a broken backend: no odometry, the motors carry on
            log.debug("reading the wheel encoders failed: %s", exc)
            rec = None
        # A fixed schedule, but counted from AFTER the read, and at least half a period on:
        # after a slow reply (a host held up) the next poll went out at once, and its
        # reading, latched a fraction of a ms after the late one, made a near-zero span
        now = time.monotonic()
        self._t_odo = max(self._t_odo + period_s, now + 0.5 * period_s)
        if rec is not None:
            self._odo_fail_run = 0
            if self.odometry_state == "unavailable":
                self.odometry_state, self.odometry_reason = "polling", ""
                self._t_odo = now + self.odometry_s
                log.warning("wheel odometry back: the motor board answers the encoder request")
            self.odometry_readings += 1
            assert self._on_odometry is not None
            self._on_odometry(rec)
        else:
            self.odometry_failures += 1
            self._odo_fail_run += 1
            refused = getattr(self.link, "odometry_supported", None) is False
            if (
                self.odometry_state == "polling"
                and self._odo_fail_run >= ODOMETRY_GIVE_UP_AFTER
                and (refused or self.odometry_readings == 0)
            ):
                self._t_odo = now + ODOMETRY_RETRY_S
                self._odometry_unavailable(
                    "the motor board refuses the encoder request (E)"
                    if refused
                    else "the motor board did not answer the encoder request"
                )
        self._after_io()

    def _send(self, cmd: MotorCommand) -> None:
        """One send, with its health bookkeeping; only ever one at a time (``_busy``)."""
        acked = False
        try:
            acked = self.link.send(cmd) is not False
        except ValueError:
            log.exception("motor command refused: %r", cmd)
            self.link.stop("invalid command")
        except Exception as exc:
            self.link_errors += 1
            if self.link_errors in (1, 10, 100) or self.link_errors % 1000 == 0:
                # not per command: a broken backend would raise at the command rate
                log.exception("motor link failed (%d so far); stopping", self.link_errors)
            if self._own is not None:
                self._own.error(f"send failed: {exc}", time.monotonic())
            with contextlib.suppress(Exception):
                self.link.stop("link error")
        self._last = cmd
        self.sent += 1
        self._acked = acked
        self._t_sent = time.monotonic()
        self._after_io()

    def _after_io(self) -> None:
        """The link's health after a send or an encoder poll: changes and events reported."""
        ok = bool(self.link.healthy)
        if ok != self._healthy:
            self._healthy = ok
            t_s = time.monotonic()
            if self._own is not None:
                if ok:
                    self._own.opened(t_s)
                else:
                    self._own.lost(self._own.health.last_error or "link unhealthy", t_s)
            self._on_health(ok, t_s)
        take = self._own.take_events if self._own is not None else self.link.take_health_events
        events = take()
        if events and self._on_events is not None:
            self._on_events(events)

    def _died(self, exc: BaseException) -> None:
        """The motor thread's death (a bug): nothing keeps the board fed any more, so stop
        the motors now (best effort; none may start after), then report it."""
        with self._cond:
            self._stop = True  # send_now refuses from here on
            self._cond.notify_all()
        with contextlib.suppress(Exception):
            self.link.stop("motor thread died")
        if self._on_death is not None:
            self._on_death(exc)

    def shutdown(self, reason: str) -> bool:
        """Stop the thread, then stop the motors and close the link (idempotent). True if the
        link confirmed the stop (a board's acknowledgement)."""
        with self._cond:
            self._stop = True
            self._cond.notify_all()
            # a send_now in progress finishes before the stop below (none starts after it)
            t_end = time.monotonic() + 5.0
            while self._busy and self.thread is not threading.current_thread():
                left_s = t_end - time.monotonic()
                if left_s <= 0:
                    break
                self._cond.wait(left_s)
        if self.thread.is_alive() and self.thread is not threading.current_thread():
            self.thread.join(5.0)
        stopped = False
        with contextlib.suppress(Exception):
            stopped = bool(self.link.stop(reason))
        with contextlib.suppress(Exception):
            self.link.close()
        return stopped


class _GcPacer:
    """Runs the cyclic garbage collector when the daemon chooses, not when allocations cross
    a threshold in whichever thread allocates.

    Connection churn on the network thread makes garbage fast (reference cycles of closed
    connections: about 10 000 objects per full collection under the hostile benchmark), and
    an automatic collection holds the GIL for 1-30 ms at a random moment: if a GGA arrives
    then, its fix waits. Once running, the daemon turns the automatic collector off and
    collects the young generations right after each fix's motor command has gone out (the
    quiet time until the next GGA), everything every ``full_s`` seconds; with no fix for
    ``overdue_s`` the event loop collects instead, so garbage never piles up."""

    def __init__(self, full_s: float = GC_FULL_S, overdue_s: float = GC_OVERDUE_S) -> None:
        self.full_s = full_s
        self.overdue_s = overdue_s
        self._lock = threading.Lock()
        self.t_last = self.t_full = time.monotonic()
        self._was_enabled: bool | None = None
        self.collections = 0
        self.full_collections = 0
        self.longest_s = 0.0  # the longest paced collection (s)

    def start(self) -> None:
        """Turn the automatic collector off (``stop`` restores it)."""
        if self._was_enabled is None:
            self._was_enabled = gc.isenabled()
            gc.disable()
            self.t_last = self.t_full = time.monotonic()

    def stop(self) -> None:
        """Give the collector back its automatic runs (idempotent)."""
        if self._was_enabled:
            gc.enable()
        self._was_enabled = None

    def collect(self) -> None:
        """Collect now: the young generations, or everything once ``full_s`` has passed.
        A collection already running in another thread makes this one a no-op."""
        if self._was_enabled is None or not self._lock.acquire(blocking=False):
            return
        try:
            t0 = time.monotonic()
            full = t0 - self.t_full >= self.full_s
            gc.collect(2 if full else 1)
            t1 = time.monotonic()
            self.t_last = t1
            self.collections += 1
            if full:
                self.t_full = t1
                self.full_collections += 1
            self.longest_s = max(self.longest_s, t1 - t0)
        finally:
            self._lock.release()

    def collect_if_overdue(self, now_s: float) -> None:
        """Collect when nothing has for ``overdue_s`` (no fixes: the GPS is gone)."""
        if now_s - self.t_last >= self.overdue_s:
            self.collect()


class _RecorderWorker:
    """Writes recorder calls from a thread so disk stalls never reach the event loop.

    The queue is bounded (``max_queued`` records): a writer stuck in the file system (a hung
    SD card or NFS mount) makes the callers drop records, counted and logged, instead of
    growing the memory. While the recorder fails or drops records, one summary line is
    logged every ``log_every_s`` seconds; :meth:`status` says how it goes."""

    def __init__(
        self,
        recorder: Any,
        *,
        max_queued: int = RECORDER_QUEUE_MAX,
        stall_s: float = RECORDER_STALL_S,
        log_every_s: float = RECORDER_LOG_S,
        start_error: str = "",
    ) -> None:
        """``start_error``: the recorder could not open its first part (a read-only or full
        disk at start-up, already logged): it starts failing, and its first failure is not
        logged again."""
        self.recorder = recorder
        # (recorder method, its arguments), or None: drain and close
        self._q: queue.SimpleQueue[tuple[str, tuple[Any, ...]] | None] = queue.SimpleQueue()
        self.max_queued = max_queued
        self.stall_s = stall_s
        self.log_every_s = log_every_s
        self.errors = 0  # recorder calls that raised
        self.queue_dropped = 0  # records dropped because the queue was full
        self.last_error = one_line(start_error)
        self._failed_last = bool(start_error)  # the latest call raised
        self._first_logged = bool(start_error)  # the first failure's line is out
        # records dropped at a full queue and not yet told: (t_mono of the first dropped,
        # queue_dropped before it); the gap event is queued in front of the next record
        # queued, so it lands in order (_put)
        self._drop_gap: tuple[float, int] | None = None
        self._put_lock = threading.Lock()  # the drop count, the gap event before its record
        self._call = ""  # the recorder method in progress
        self._t_call: float | None = None  # time.monotonic() it started (None: idle)
        now = time.monotonic()
        self._t_summary = now  # the writer's latest summary line (s, monotonic)
        self._summarised = (0, 0)  # (errors, records lost) at that line
        self._t_drop_log = -math.inf  # the callers' latest line about dropped records
        self._drops_logged = 0
        self.thread = threading.Thread(target=self._run, name="x6wd-recorder", daemon=True)
        self.thread.start()

    def put(self, method: str, arg: Any) -> None:
        """Queue one recorder call; never blocks (a full queue drops it, counted)."""
        self._put(method, (arg,))

    def put_event(self, name: str, t_mono: float, **fields: Any) -> None:
        """Queue ``Recorder.record_event(name, t_mono, **fields)``, as :meth:`put` does."""
        self._put("record", ("event", {"event": name, **fields}, t_mono))

    @staticmethod
    def _t_of(method: str, args: tuple[Any, ...]) -> float:
        """The ``t_mono`` the recorder will give this call's record: the event's own, the
        record's ``t_s``, else its clock's (the moment it is written, so now at the least)."""
        t = args[2] if method == "record" and len(args) > 2 else getattr(args[0], "t_s", None)
        if isinstance(t, (int, float)) and not isinstance(t, bool) and math.isfinite(t):
            return float(t)
        return time.monotonic()

    def _put(self, method: str, args: tuple[Any, ...]) -> None:
        with self._put_lock:
            full = self._q.qsize() >= self.max_queued
            if full:
                if self._drop_gap is None:
                    self._drop_gap = (self._t_of(method, args), self.queue_dropped)
                self.queue_dropped += 1
            else:
                if self._drop_gap is not None:  # in order: after all queued before the drops
                    self._q.put(self._gap_item(self._t_of(method, args)))
                self._q.put((method, args))
        if full:  # logged outside the lock: a blocked log write holds up only this thread
            now = time.monotonic()
            if now - self._t_drop_log >= self.log_every_s:  # at most once a minute
                t = self._t_call
                stuck = f" for {now - t:.0f} s in {self._call}" if t is not None else ""
                log.error(
                    "recorder queue full (%d records): the writer is stuck%s; %d records "
                    "dropped so far",
                    self.max_queued,
                    stuck,
                    self.queue_dropped,
                )
                self._t_drop_log = now

    def _run(self) -> None:
        # The start-of-run retention pass deletes files: here, never on the event loop.
        enforce = getattr(self.recorder, "enforce_retention", None)
        if enforce is not None:
            try:
                enforce()
            except Exception:
                log.exception("recording retention pass failed")
        while True:
            item = self._q.get()
            if item is None:
                break
            method, args = item
            self._call, self._t_call = method, time.monotonic()
            try:
                getattr(self.recorder, method)(*args)
            except Exception as exc:
                self._failed(exc)
            else:
                self._failed_last = False
            finally:
                self._t_call = None
            self._summary()
        # closed here, in this thread: a file system that hangs holds up only this thread
        self._call, self._t_call = "close", time.monotonic()
        try:
            self.recorder.close()
        except Exception:
            log.exception("closing the recording failed")
        self._t_call = None

    def _gap_item(self, t: float) -> tuple[str, tuple[Any, ...]]:
        """The queue's gap event for the records dropped at the full queue (``_drop_gap``,
        then cleared), ending with the record at ``t`` that follows it: stamped ``t``, so
        t_mono never steps back (the records queued before the drops precede it). Call with
        ``_put_lock`` held."""
        from x6wd.core.recorder import GAP_EVENT

        gap, self._drop_gap = self._drop_gap, None
        assert gap is not None
        t0, lost0 = gap
        fields = {
            "event": GAP_EVENT,
            "from_t_mono": t0,  # the first record dropped
            "to_t_mono": t,  # the first queued again
            "duration_s": round(max(0.0, t - t0), 3),
            "records_lost": self.queue_dropped - lost0,
            "error": f"recorder queue full ({self.max_queued} records): the writer was stuck",
        }
        return "record", ("event", fields, t)

    def _failed(self, exc: Exception) -> None:
        self.errors += 1
        self.last_error = one_line(str(exc))
        self._failed_last = True
        if not self._first_logged:  # then summaries (_summary), never one line per record
            self._first_logged = True
            if isinstance(exc, (OSError, DeviceUnavailable)):  # a full, read-only, gone disk
                log.error("recorder write failed: %s", self.last_error)
            else:  # a bug: its traceback
                log.exception("recorder write failed")

    def _summary(self) -> None:
        """Once every ``log_every_s``: what failed and what was lost since the last line."""
        now = time.monotonic()
        if now - self._t_summary < self.log_every_s:
            return
        lost = int(getattr(self.recorder, "records_lost", 0))
        errors0, lost0 = self._summarised
        if self.errors > errors0 or lost > lost0:
            log.warning(
                "recorder: %d errors, %d records lost in the last %.0f s (%d errors, %d lost "
                "in all), recorder %s; last error: %s",
                self.errors - errors0,
                lost - lost0,
                now - self._t_summary,
                self.errors,
                lost,
                getattr(self.recorder, "state", "ok"),
                self.last_error or "-",
            )
        self._t_summary = now
        self._summarised = (self.errors, lost)

    @property
    def state(self) -> str:
        """ "stalled" (a call has taken ``stall_s`` or more), "failing" (the latest call
        failed, or the recorder waits to open a part again) or "ok"."""
        t = self._t_call
        if t is not None and time.monotonic() - t >= self.stall_s:
            return "stalled"
        if self._failed_last or getattr(self.recorder, "state", "ok") == "failing":
            return "failing"
        return "ok"

    def status(self) -> dict[str, Any]:
        """The recorder for ``status``: state, file, records written and dropped, errors."""
        rec = self.recorder
        lost = int(getattr(rec, "records_lost", 0))
        out: dict[str, Any] = {
            "state": self.state,
            "file": str(getattr(rec, "path", "")),
            "records_written": int(getattr(rec, "records_written", 0)),
            # queue full (the writer stuck) + not written (the file system failing)
            "records_dropped": self.queue_dropped + lost,
            "queue_dropped": self.queue_dropped,
            "queued": self._q.qsize(),
            "errors": self.errors,
            "last_error": self.last_error or getattr(rec, "last_error", ""),
        }
        t = self._t_call
        if t is not None:
            out["busy_s"] = round(time.monotonic() - t, 1)  # in the current call
        return out

    def close(self, timeout_s: float = RECORDER_CLOSE_S) -> bool:
        """Drain, flush to disk and close, waiting ``timeout_s`` (s) at most; False (logged)
        when the writer is stuck: its queue is then lost, the shutdown goes on
        (idempotent)."""
        if self.thread.is_alive():
            with self._put_lock:
                if self._drop_gap is not None:  # dropped up to the end: the gap says so
                    self._q.put(self._gap_item(max(time.monotonic(), self._drop_gap[0])))
                self._q.put(None)
            self.thread.join(timeout_s)
        if self.thread.is_alive():
            t = self._t_call
            log.error(
                "recorder stuck%s: exiting without closing the recording (%d queued records lost)",
                f" for {time.monotonic() - t:.0f} s in {self._call}" if t is not None else "",
                self._q.qsize(),
            )
            return False
        return True


class _NetThread:
    """The network side (control server, gpsd port) on its own event loop and thread, so a
    flood of clients never queues in front of the control loop's callbacks.

    On Linux the thread also runs ``NET_NICE`` steps nicer than the rest of the daemon (the
    nice value is per thread there): under a flood it is the one thread always ready to
    run, and on a loaded machine the kernel then gives the GPS, control and motor threads
    the processor first when they wake."""

    def __init__(self, max_queued: int = NET_QUEUE_MAX) -> None:
        self.loop = asyncio.new_event_loop()
        self.max_queued = max_queued
        self._lock = threading.Lock()
        self.queued = 0  # calls handed to the loop and not yet run
        self.dropped = 0  # publications dropped at the full queue
        self._dropped_logged = 0
        self.thread = threading.Thread(target=self._run, name="x6wd-net", daemon=True)
        self.thread.start()

    def _run(self) -> None:
        if sys.platform == "linux" and NET_NICE > 0:
            tid = threading.get_native_id()
            try:
                nice = os.getpriority(os.PRIO_PROCESS, tid)
                os.setpriority(os.PRIO_PROCESS, tid, min(19, nice + NET_NICE))
            except OSError as exc:  # a seccomp filter, an odd kernel: run as is
                log.debug("network thread keeps its priority: %s", exc)
        self.loop.run_forever()

    async def run(self, coro: Any) -> Any:
        """Run ``coro`` on the network loop and wait for it from the caller's loop."""
        return await asyncio.wrap_future(asyncio.run_coroutine_threadsafe(coro, self.loop))

    def call(self, fn: Callable[..., Any], *args: Any, publication: bool = False) -> None:
        """Queue ``fn(*args)`` on the network loop (never waits). A ``publication`` (an
        event, a fix, a sentence for the watchers: the next one supersedes it) is dropped,
        counted, while :data:`NET_QUEUE_MAX` calls wait for a stalled loop."""
        with self._lock:
            if publication and self.queued >= self.max_queued:
                self.dropped += 1
                return
            self.queued += 1
        try:
            self.loop.call_soon_threadsafe(self._run_one, fn, args)
        except RuntimeError:  # closed during shutdown
            with self._lock:
                self.queued -= 1

    def _run_one(self, fn: Callable[..., Any], args: tuple[Any, ...]) -> None:
        with self._lock:
            self.queued -= 1
            dropped = self.dropped
        if dropped != self._dropped_logged:  # here the loop runs again: say what it missed
            log.warning(
                "network thread stalled: %d publications dropped (%d in all) while %d calls "
                "waited for it",
                dropped - self._dropped_logged,
                dropped,
                self.max_queued,
            )
            self._dropped_logged = dropped
        fn(*args)

    def stop(self) -> None:
        """Cancel what is left, stop the loop and the thread (idempotent)."""
        if not self.thread.is_alive():
            return

        async def cancel_rest() -> None:
            me = asyncio.current_task()
            rest = [t for t in asyncio.all_tasks() if t is not me]
            for t in rest:
                t.cancel()
            await asyncio.gather(*rest, return_exceptions=True)

        with contextlib.suppress(Exception):
            asyncio.run_coroutine_threadsafe(cancel_rest(), self.loop).result(5.0)
        self.loop.call_soon_threadsafe(self.loop.stop)
        self.thread.join(5.0)
        self.loop.close()


class Daemon:
    """The running robot: devices, controller, servers. Also the server's command backend."""

    def __init__(
        self,
        config: Config,
        *,
        notifier: Notifier | None = None,
        log_tail: LogTail | None = None,
        devices: Any = None,
    ) -> None:
        """``devices``: the :class:`drivers.registry.Devices` to open the device URLs
        through (default: one built from ``config``, whose ``[sim]`` world it owns)."""
        self.config = config
        # the device set: the registry's plug-in backends (the simulated world) live here
        self.devices: Any = devices
        self.notifier = notifier or Notifier(None)
        self.log_buffer = log_tail or LogTail()
        self._loop: asyncio.AbstractEventLoop | None = None
        self._stop_event: asyncio.Event | None = None
        self._fatal: BaseException | None = None
        self._fatal_cause = ""  # the first fatal error, for the recording's shutdown event
        self._accepting = False  # operator commands that move the robot wait for "ready"
        self._threads_stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self.controller: Any = None
        self.runner: Runner | None = None
        self.motors: _MotorWorker | None = None
        self.motors_unconfirmed = False  # the stop at exit was not confirmed (MOTORS_UNCONFIRMED)
        self.recorder: _RecorderWorker | None = None
        self.server: ControlServer | None = None
        self.gpsd: GpsdServer | None = None
        self.console: ConsoleServer | None = None
        # the bind keys listening beyond loopback in clear text ([server] allow_plaintext)
        self._plaintext: tuple[str, ...] = ()
        # the loaded mission as the console's map shows it: ((lat_deg, lon_deg), ...)
        self._mission: tuple[tuple[float, float], ...] = ()
        self._mission_rev = 0
        self._gps_reader: Any = None
        self._net: _NetThread | None = None
        self._loop_thread_id: int | None = None
        # The controller (through the runner) is touched by one thread at a time: under this
        # lock. The GPS thread decides on its fixes itself (see _decide_here); the event loop
        # runs everything else. Reentrant: a request made from within a decision must not
        # deadlock.
        self._control_lock = threading.RLock()
        # While a device thread decides (control lock held): its thread id, and the recorder
        # and network calls its decision makes, sent after the motor command (_decide_here).
        self._deciding: int | None = None
        self._held_records: list[tuple[str, Any]] = []
        self._held_net: list[tuple[Callable[..., Any], tuple[Any, ...]]] = []
        self._held_state = False  # a held network call is a state change, not a publication
        self.gc_pacer: _GcPacer | None = _GcPacer()  # None: the automatic collector runs
        self._compass: Any = None
        self.compass_errors = 0  # read errors of a compass backend without its own health
        self._compass_driver: Any = None  # the Cmps10 the compass thread reads
        self._health_log = HealthLog(logging.getLogger("x6wd.core.health"))
        self._dev_dicts: dict[str, tuple[DeviceHealth, dict[str, Any]]] = {}
        self._gpsd_wmm = False  # the gpsd port still waits for the WMM declination
        self._t_operator = -math.inf  # latest operator request handed to the controller (s)
        self.t_start = time.monotonic()
        self._stop_signal: tuple[str, int] | None = None  # (name, exit code) of the first
        # why the recorder dir cannot take a file now, though it is right (read-only, full):
        # the start-up goes on with the recorder failing ("" when it can)
        self._recorder_fault = ""
        # device nodes missing or not yet accessible at the preflight, waited for after every
        # other check: config key -> (url, kind, the registry's NodeMissing or NodeNotReady)
        self._missing: dict[str, tuple[str, str, Any]] = {}

    @property
    def last_telemetry(self) -> Telemetry | None:
        """The controller's latest telemetry snapshot (None before the first input)."""
        return self.runner.last_telemetry if self.runner is not None else None

    @property
    def first_fix(self) -> tuple[float, float] | None:
        """(lat_deg, lon_deg) of the first valid fix (the geofence centre unless configured)."""
        return self.runner.first_fix if self.runner is not None else None

    @property
    def stats(self) -> dict[str, int]:
        """Inputs seen by the control loop: ``fixes``, ``attitudes``, ``odometry``."""
        return self.runner.stats if self.runner is not None else {}

    # -- lifecycle ------------------------------------------------------------------------
    def request_stop(self) -> None:
        """Ask the daemon to shut down cleanly (signal handlers call this)."""
        if self._stop_event is not None:
            self._stop_event.set()

    def stop_on_signal(self, signum: int, code: int) -> None:
        """A signal (``main`` installs this for :func:`stop_signals`): log it, then shut down
        as on SIGTERM (motors first); the first signal's ``code`` is the exit code."""
        name = signal.Signals(signum).name
        if self._stop_signal is None:
            self._stop_signal = (name, code)
            level = logging.INFO if code == EXIT_OK else logging.WARNING
            # no exit code here: an unacknowledged stop makes it 1 (said by "x6wd stopped")
            log.log(level, "%s received: stopping the motors and shutting down", name)
        self.request_stop()

    def _fail(self, exc: BaseException, cause: str = "") -> None:
        """Stop the daemon on ``exc`` (exit 1); ``cause``: where it came from, for the
        recording (default: the control loop)."""
        if self._fatal is None:
            self._fatal = exc
            self._fatal_cause = cause or f"error on the control loop: {_exc_text(exc)}"
        self.request_stop()

    def fail_from_thread(self, exc: BaseException) -> None:
        """Report an unexpected exception from a worker thread (exits non-zero)."""
        cause = f"error in thread {threading.current_thread().name}: {_exc_text(exc)}"
        loop = self._loop
        if loop is not None and not loop.is_closed():
            with contextlib.suppress(RuntimeError):
                loop.call_soon_threadsafe(self._fail, exc, cause)

    async def run(self, ready: Callable[[Daemon], Any] | None = None) -> int:
        """Open everything, serve until stopped; return the process exit code.

        ``ready`` (optional) is called once devices and servers are up (tests, benchmarks).
        """
        self._loop = asyncio.get_running_loop()
        self._loop_thread_id = threading.get_ident()
        self._stop_event = asyncio.Event()
        # Several threads share the GIL; a shorter switch interval bounds how long the
        # device and control threads wait for it behind network work.
        sys.setswitchinterval(min(sys.getswitchinterval(), GIL_SWITCH_S))
        try:
            # nothing opened, nothing created yet: a bad setting is one line and exit 2
            self._preflight()
            await self._bind_servers()
            # last: every problem that waiting cannot end is reported at once, not after it
            appeared = await self._wait_for_devices()
        except ConfigError as exc:
            await self._unbind()
            config_error(exc)
            self.notifier.stopping(f"configuration error: {one_line(str(exc))}")
            return EXIT_CONFIG
        if not appeared or self._stop_signal is not None:
            # a stop signal during the preflight, the binding or the wait: open nothing more
            # (opening a motor port can reset its board on the way out)
            await self._unbind()
            self.notifier.stopping("stopping")
            code = self._stop_signal[1] if self._stop_signal is not None else EXIT_OK
            if appeared:
                log.info("x6wd stopped during start-up, before opening the devices (exit %d)", code)
            else:
                waited = ", ".join(self._missing)
                log.info("x6wd stopped while waiting for %s (exit %d)", waited, code)
            return code
        if self._plaintext:
            binds = {
                "server.bind": self.config.server.bind,
                "console.bind": self.config.console.bind,
            }
            where = ", ".join(f"{key} = {binds[key]!r}" for key in self._plaintext)
            log.warning(
                "listening beyond loopback without TLS (%s; server.allow_plaintext = true): "
                "the token and every command travel in clear text, anyone on that network "
                "can take the token and drive the robot",
                where,
            )
        code = EXIT_FAILURE
        # how the run ended, for the recording: the stop's reason "shutdown (<why>)", the
        # shutdown event's cause and exit code (None: cancelled, no exit code of ours)
        why = cause = "cancelled"
        exit_code: int | None = None
        try:
            await self._open_devices()
            if self._stop_signal is None:  # else a signal came while they opened: no more
                await self._open_recorder()  # last: a failed start leaves no empty recording
                self._start_readers()
                self._accepting = True
                self.notifier.ready(self._status_text())
                log.info("x6wd %s ready", __version__)
                # Everything built at start-up is long-lived: move it out of the collector's
                # generations, so a full collection (set off by client churn) walks only what
                # came later instead of stalling the control loop for tens of milliseconds.
                gc.collect()
                gc.freeze()
                if self.gc_pacer is not None:
                    self.gc_pacer.start()
                if ready is not None:
                    ready(self)
                await self._control_loop()
            if self._fatal is not None:
                raise self._fatal
            code, why, cause = EXIT_OK, "stop requested", "stop requested"
            if self._stop_signal is not None:
                why, code = self._stop_signal
                cause = f"signal {why}"
            exit_code = code
        except (ConfigError, DeviceUnavailable) as exc:
            log.error("startup failed: %s", exc)
            exit_code = code = EXIT_CONFIG if isinstance(exc, ConfigError) else EXIT_FAILURE
            why, cause = "startup failed", f"startup failed: {one_line(str(exc))}"
            if exc is self._fatal:
                why, cause = "error", self._fatal_cause
        except Exception as exc:
            log.exception("fatal error, stopping the motors: %s", exc)
            exit_code = code = EXIT_FAILURE
            why = "error"
            cause = self._fatal_cause if exc is self._fatal else f"error: {_exc_text(exc)}"
        finally:
            self.notifier.stopping("stopping")
            try:
                await self._close(f"shutdown ({why})", cause, exit_code)
            finally:
                if self.gc_pacer is not None:
                    self.gc_pacer.stop()
        if self.motors_unconfirmed and code == EXIT_OK:
            code = EXIT_FAILURE  # (systemd: a failed stop is no clean exit)
        return code

    def _preflight(self) -> None:
        """Check every setting that can be checked without opening a device or creating a
        file: device URLs and the local devices they name, the simulator's world, the server
        token and TLS files, the recorder directory. Raises ConfigError naming the key."""
        cfg = self.config  # (safety.geofence_center: SafetyConfig checks it)
        from drivers import registry

        devices = (
            ("gps.url", cfg.gps.url, "gps"),
            ("compass.url", cfg.compass.url, "compass"),
            ("motors.url", cfg.motors.url, "motors"),
        )
        if self.devices is None:
            self.devices = registry.Devices(cfg)
        self._missing = {}
        with contextlib.suppress(registry.UrlError):  # (a bad URL: named below)
            if registry.parse_url(cfg.gps.url, "gps").scheme == "serial":  # the rate fits it
                from drivers.gps_io import native_usb_path

                path, baud = registry.device_path(cfg.gps.url)
                if not native_usb_path(path):  # USB (CDC-ACM) is not paced by its baud
                    check_gps_line(cfg, baud)
        for key, url, kind in devices:
            try:
                self.devices.check(url, kind)  # a sim:// URL: also the [sim] world's settings
            except (registry.NodeMissing, registry.NodeNotReady) as exc:
                if self._device_wait_s() <= 0.0:
                    raise ConfigError(f"{key}: {url!r}: {exc.reason}") from None
                self._missing[key] = (url, kind, exc)  # waited for: _wait_for_devices
            except registry.UrlError as exc:
                raise ConfigError(f"{key}: {url!r}: {exc.reason}") from None
        # before any port is bound, as every other setting (it was found at the motors' open)
        registry.check_motor_watchdog(cfg.motors.url, cfg.motors.watchdog_ms)
        from x6wd.nav.controller import Controller  # imported late: heavy, and optional in tests

        decl = cfg.compass.declination_deg
        self.controller = Controller(
            cfg.navigation,
            cfg.safety,
            0.0 if decl is None else decl,
            odometry=cfg.odometry,
            gnss_noise=cfg.gnss_noise,
            failsafe=cfg.failsafe,
        )
        self.runner = Runner(
            self.controller,
            cfg.safety,
            time.monotonic,
            motors=self._submit,
            record=self._record,
            publish=self._publish,
            devices=self._devices,
            on_state=self._on_state,
            observe=self._observe,
            health_log=self._health_log,
            wmm_declination=decl is None,
        )
        # a replay:// log played to its end is named so, not as a line's wiring fault
        self.runner.gps_at_end = lambda: self._gps_reader is not None and self._gps_reader.at_end
        self.runner.gps_log_silent = lambda: (
            self._gps_reader is not None and self._gps_reader.log_silent
        )
        for key, enabled, host in (
            ("server.bind", cfg.server.enabled, cfg.server.bind),
            ("console.bind", cfg.console.enabled, cfg.console.bind),
            ("gpsd.bind", cfg.gpsd.enabled, cfg.gpsd.bind),
        ):
            # before the server's own checks, which would blame the token for a typo
            problem = _bind_problem(host) if enabled else ""
            if problem:
                raise ConfigError(f"{key}: {problem}")
        # beyond loopback only with TLS, or [server] allow_plaintext (then warned at start-up)
        check_plaintext(cfg)
        self._plaintext = plaintext_binds(cfg)
        self.server = ControlServer.from_config(cfg.server, self) if cfg.server.enabled else None
        self.console = self._make_console()
        if cfg.gpsd.enabled:
            path, bps, cycle_s = _gps_device(cfg.gps.url, cfg.gps.rate_hz)
            # without a configured declination the ATT heading is the magnetic one until the
            # runner has the World Magnetic Model's value (_on_gps_records passes it on)
            self.gpsd = GpsdServer.from_config(
                cfg.gpsd,
                path,
                bps=bps,
                declination_deg=0.0 if decl is None else decl,
                cycle_s=cycle_s,
                fix_stale_s=cfg.safety.fix_stale_s,
            )
            self._gpsd_wmm = decl is None
        if cfg.recorder.enabled:
            # a disk that is right but read-only or full now is no configuration error: the
            # daemon starts with the recorder failing (_open_recorder), as it runs on
            problem, self._recorder_fault = _dir_check(Path(cfg.recorder.dir))
            if problem:
                raise ConfigError(f"recorder.dir: {cfg.recorder.dir!r}: {problem}")
            if cfg.recorder.max_file_mb > cfg.recorder.max_total_mb:
                raise ConfigError(
                    f"recorder.max_file_mb: {cfg.recorder.max_file_mb:g} is more than "
                    f"recorder.max_total_mb ({cfg.recorder.max_total_mb:g}): one part must fit"
                )

    def _device_wait_s(self) -> float:
        """How long (s) start-up waits for a missing device node, or one this user may not
        read and write yet: ``[startup] device_wait_s`` when started by systemd (a
        notification socket), where exit 2 leaves the unit failed (RestartPreventExitStatus=2)
        and so the robot down, though the node (a USB device enumerating at boot or after a
        board's reset, then given its group by udev) comes by itself; 0 when started by
        hand, where the operator wants the error at once and can start again."""
        return self.config.startup.device_wait_s if self.notifier.enabled else 0.0

    async def _wait_for_devices(self) -> bool:
        """Wait up to :meth:`_device_wait_s` for the device nodes the preflight found missing
        or not yet accessible (all in one wait), looking again every :data:`DEVICE_POLL_S`;
        nothing is opened. True once every one passes the preflight's check, False on a stop
        request (a signal). Still missing or not accessible at the end: :class:`ConfigError`,
        the preflight's line plus ``(waited N s)``. A node keeps its wait while it is missing
        or not accessible, either way round (udev gives a node its group a moment after
        creating it); any other problem (it appeared as a regular file, a link to
        ``/dev/null``) ends the wait at once, its line plus how long it waited."""
        if not self._missing:
            return True
        assert self._stop_event is not None
        from drivers import registry

        wait_s = self._device_wait_s()
        t0_s = time.monotonic()
        what = []
        for key, (_url, _kind, exc) in self._missing.items():
            if isinstance(exc, registry.NodeMissing):
                what.append(f"{exc.path} to appear")
                log.warning(
                    "%s: %s does not exist yet: waiting up to %g s for it to appear (a USB "
                    "device enumerating?; startup.device_wait_s)",
                    key,
                    exc.path,
                    wait_s,
                )
            else:
                what.append(f"{exc.path} to be accessible")
                log.warning(
                    "%s: %s is not accessible yet (this user may not read and write it): "
                    "waiting up to %g s (udev setting its group?; startup.device_wait_s)",
                    key,
                    exc.path,
                    wait_s,
                )
        self.notifier.notify(
            {
                "STATUS": f"waiting up to {wait_s:g} s for {', '.join(what)} "
                "(startup.device_wait_s)",
                "EXTEND_TIMEOUT_USEC": int((wait_s + START_MARGIN_S) * 1e6),
            }
        )
        pending = dict(self._missing)  # key -> (url, kind, its latest problem)
        while True:
            for key, (url, kind, _exc) in list(pending.items()):
                try:
                    self.devices.check(url, kind)
                except (registry.NodeMissing, registry.NodeNotReady) as problem:
                    pending[key] = (url, kind, problem)
                except ConfigError as problem:  # not one that waiting can end: at once
                    reason = getattr(problem, "reason", str(problem))
                    waited_s = time.monotonic() - t0_s
                    raise ConfigError(
                        f"{key}: {url!r}: {reason} (waited {waited_s:.1f} s)"
                    ) from None
                else:
                    del pending[key]
                    log.info("%s: %s is there after %.1f s", key, url, time.monotonic() - t0_s)
            if not pending:
                return True
            left_s = t0_s + wait_s - time.monotonic()
            if left_s <= 0.0:
                key, (url, _kind, last) = next(iter(pending.items()))
                reason = getattr(last, "reason", str(last))
                raise ConfigError(f"{key}: {url!r}: {reason} (waited {wait_s:g} s)")
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(self._stop_event.wait(), min(DEVICE_POLL_S, left_s))
            if self._stop_event.is_set():
                return False

    async def _bind_servers(self) -> None:
        """Listen on both ports before any device opens: a busy port is a ConfigError
        naming the key. Commands that move the robot are refused until ready."""
        cfg = self.config
        self._net = _NetThread()
        listeners = (
            ("server", self.server, cfg.server.bind, cfg.server.port),
            ("gpsd", self.gpsd, cfg.gpsd.bind, cfg.gpsd.port),
            ("console", self.console, cfg.console.bind, cfg.console.port),
        )
        # Their "listening on" lines wait until both ports are ours, so that a busy second
        # port leaves the error as the only line on stderr.
        held: list[logging.LogRecord] = []

        def hold(record: logging.LogRecord) -> bool:
            held.append(record)
            return False

        loggers = {logging.getLogger(type(s).__module__) for _k, s, _b, _p in listeners if s}
        for lg in loggers:
            lg.addFilter(hold)
        try:
            for section, server, bind, port in listeners:
                if server is None:
                    continue
                try:
                    await self._net.run(server.start())
                except OSError as exc:
                    raise ConfigError(_listen_problem(section, bind, port, exc)) from None
        finally:
            for lg in loggers:
                lg.removeFilter(hold)
        for record in held:
            logging.getLogger(record.name).handle(record)

    async def _unbind(self) -> None:
        """Undo :meth:`_bind_servers` after a start-up configuration error (idempotent)."""
        if self._net is None:
            return
        for server in (self.console, self.server, self.gpsd):
            if server is not None:
                with contextlib.suppress(Exception):
                    await self._net.run(server.close())
        await asyncio.to_thread(self._net.stop)
        self._net = None

    async def _open_recorder(self) -> None:
        """Create the recording file (rotating at ``max_file_mb``, with retention)."""
        rc = self.config.recorder
        if not rc.enabled:
            return
        from x6wd.core.recorder import MB, REOPEN_BACKOFF_S, Recorder, Retention

        retention = Retention(
            max_total_bytes=int(rc.max_total_mb * MB), min_free_bytes=int(rc.min_free_mb * MB)
        )
        rec = await asyncio.to_thread(
            Recorder.in_dir,
            rc.dir,
            fsync_interval_s=RECORDER_FSYNC_S,
            max_bytes=max(1, int(rc.max_file_mb * MB)),
            retention=retention,
            start_failing=True,  # a read-only or full disk: a runtime fault, not a stop
            gap_events=True,  # the recording says where it lost records
        )
        if rec.state == "failing":
            why = self._recorder_fault or rec.last_error
            # one line naming the dir and the errno; the recorder's summaries follow
            log.error(
                "recorder.dir: %r: %s: starting without recording, the recorder retries "
                "(%g s, then at most every %g s) and the recording begins when the disk "
                "takes it (status: recorder failing)",
                rc.dir,
                why,
                *REOPEN_BACKOFF_S,
            )
            self.recorder = _RecorderWorker(rec, start_error=why)
            return
        self.recorder = _RecorderWorker(rec)
        log.info("recording to %s", rec.path)

    async def _open_devices(self) -> None:
        from drivers import registry
        from drivers.gps_io import GpsReader, ReceiverSetup, WeekRolloverCorrection

        cfg = self.config
        from drivers.motors import encoder_rate_bound

        odo = cfg.odometry
        link = await asyncio.to_thread(
            functools.partial(
                registry.open_motors,
                cfg.motors.url,
                self.devices,
                watchdog_ms=cfg.motors.watchdog_ms,
                # a reading further than this robot's wheels can go is a board restart
                max_counts_per_s=encoder_rate_bound(
                    odo.counts_per_rev,
                    min(odo.left_diameter_m, odo.right_diameter_m),
                    cfg.navigation.full_speed_mps,
                ),
            )
        )
        # three keep-alives per watchdog period: the board's (the URL may set its own)
        keepalive_s = max(0.02, getattr(link, "watchdog_ms", cfg.motors.watchdog_ms) / 3000.0)
        self.motors = _MotorWorker(
            link,
            keepalive_s,
            self._health_from_thread,
            self._health_events_from_thread,
            on_odometry=self._odometry_from_thread,
            odometry_s=1.0 / ODOMETRY_HZ,
            on_death=self.fail_from_thread,  # a bug there stops the daemon, as in the others
        )
        self.motors.start()
        compass = await asyncio.to_thread(registry.open_compass, cfg.compass.url, self.devices)
        self._compass = compass
        # a live receiver's dates before this release are a GPS week rollover (drivers.gps_io)
        scheme = registry.parse_url(cfg.gps.url, "gps").scheme
        live = scheme != "replay"
        # [gps] configure_receiver: UBX CFG-RATE/CFG-MSG after every open, answers in status;
        # the fix rate is measured against the one the staleness limits were checked at (not
        # for a replay, which plays at its own times)
        configure = cfg.gps.configure_receiver and live
        sim_rate = not configure and scheme == "sim"  # the simulated receiver's own rate
        expected_hz = cfg.sim.gps_rate_hz if sim_rate else cfg.gps.rate_hz
        self._gps_reader = GpsReader(
            self._open_gps_port,
            stale_s=cfg.gps.stale_s,
            week_rollover=WeekRolloverCorrection() if live else None,
            setup=ReceiverSetup(cfg.gps.rate_hz) if configure else None,
            expected_rate_hz=expected_hz if live else None,
            expected_rate_key="sim.gps_rate_hz" if sim_rate else "gps.rate_hz",
            baud_key=(
                "the receiver's, in u-center, and gps.url's baud"
                if scheme != "sim"
                else "sim.gps_baud"
                if cfg.sim.gps_baud
                else "the scenario's [gnss] baud, or sim.gps_baud"
            ),
        )

    def _open_gps_port(self) -> Any:
        """Open the GPS (the reader's opener, also on reopen) and tell the gpsd port's DEVICE
        what was opened: a simulated receiver's pty, baud rate and cycle are the world's."""
        from drivers import registry

        cfg = self.config.gps
        port = registry.open_gps_port(cfg.url, self.devices)
        if self.gpsd is not None:
            world = None
            if registry.parse_url(cfg.url, "gps").scheme == "sim":
                world = self.devices.backend("sim")
            path, bps, cycle_s = _gps_device(cfg.url, cfg.rate_hz, world)
            if cfg.configure_receiver and world is not None:
                cycle_s = 1.0 / cfg.rate_hz  # what the simulated receiver is set to (CFG-RATE)
            self._net_call(self.gpsd.set_device, path, bps, cycle_s)
        return port

    def _start_readers(self) -> None:
        """Start the device threads once the recorder exists, so it sees their first data."""
        self._spawn(self._gps_thread, "x6wd-gps")
        self._spawn(self._compass_thread, "x6wd-compass")

    def _spawn(self, target: Callable[[], None], name: str) -> None:
        t = guarded_thread(target, name, self.fail_from_thread)
        self._threads.append(t)
        t.start()

    async def _close(
        self,
        reason: str = "shutdown",
        cause: str = "stop requested",
        exit_code: int | None = EXIT_OK,
    ) -> None:
        """Stop the motors, then close everything. The recording ends with the stop (a motor
        record 0/0 and the controller's change to IDLE, both with ``reason``) and a
        ``shutdown`` event with ``cause`` and ``exit_code``: a clean exit, told apart from
        a crash or a power cut."""
        self._accepting = False  # nothing may set the robot moving again
        # Motors first: whatever else fails below, the robot must be stopped.
        motors_said = "the motors are stopped"
        try:
            self._stop_controller(reason)
        finally:
            motors = self.motors
            if motors is not None and not await asyncio.to_thread(motors.shutdown, "daemon exit"):
                # said, never assumed: a board that stopped answering may still drive (an
                # outside audit: "the motors are stopped" and exit 0 while it did)
                self.motors_unconfirmed = True
                motors_said = MOTORS_UNCONFIRMED
                last = ""
                with contextlib.suppress(Exception):  # a link in any state
                    last = f" (last error: {motors.link.health.last_error})"
                log.error("%s%s", MOTORS_UNCONFIRMED, last)
                if exit_code == EXIT_OK:
                    exit_code = EXIT_FAILURE
        self._threads_stop.set()
        for t in self._threads:
            await asyncio.to_thread(t.join, 3.0)
        if self._net is not None:
            for server in (self.console, self.server, self.gpsd):
                if server is not None:
                    # the control port's clients are told why (the motors stopped above)
                    if isinstance(server, ControlServer):
                        closing = server.close(f"x6wd is shutting down: {motors_said}")
                    elif server is self.console and self.motors_unconfirmed:
                        closing = server.close("x6wd stopping: the motors' stop NOT acknowledged")
                    else:
                        closing = server.close()
                    with contextlib.suppress(Exception):
                        await self._net.run(closing)
            await asyncio.to_thread(self._net.stop)
        for dev in (self._gps_reader, self._compass):
            if dev is not None and hasattr(dev, "close"):
                with contextlib.suppress(Exception):
                    await asyncio.to_thread(dev.close)
        if self.recorder is not None:
            await asyncio.sleep(0)  # what the threads queued before they stopped, first
            self.recorder.put_event(
                "shutdown",
                time.monotonic(),
                cause=cause,
                exit_code=exit_code,
                reason=reason,
                motors_stopped=not self.motors_unconfirmed,
            )
            # bounded: a stuck file system does not hold up the shutdown
            await asyncio.to_thread(self.recorder.close)
        if self.devices is not None:  # last: the simulated world outlives every device
            await asyncio.to_thread(self.devices.close)
        # the exit code as it is now: a signal's line said the one it asked for
        log.info("x6wd stopped" + ("" if exit_code is None else f" (exit {exit_code})"))

    def _stop_controller(self, reason: str) -> None:
        """At exit, before the motor thread stops: the controller stops (IDLE), its stop goes
        to the motors and into the recording (:meth:`Runner.shutdown`), under the control
        lock, so no device thread's decision comes after it. A thread stuck holding the
        lock for :data:`SHUTDOWN_LOCK_S` is not waited for: the stop is then recorded alone."""
        runner = self.runner
        if runner is None:
            return
        if not self._control_lock.acquire(timeout=SHUTDOWN_LOCK_S):
            log.error(
                "control lock held for %g s at exit: stopping without the controller",
                SHUTDOWN_LOCK_S,
            )
            self._record("record_motor", MotorCommand(time.monotonic(), 0.0, 0.0, reason))
            return
        try:
            runner.shutdown(reason)
        except Exception:  # the motors stop all the same (_close)
            log.exception("stopping the controller at exit failed")
        finally:
            self._control_lock.release()

    # -- device threads (never touch the controller directly) ------------------------------
    def _post(self, fn: Callable[..., Any], *args: Any) -> None:
        loop = self._loop
        if loop is None or loop.is_closed():
            return
        with contextlib.suppress(RuntimeError):  # loop closing during shutdown
            loop.call_soon_threadsafe(self._guarded, fn, *args)

    def _guarded(self, fn: Callable[..., Any], *args: Any) -> None:
        # asyncio would only log an exception escaping a callback; a bug must stop the robot
        try:
            with self._control_lock:
                fn(*args)
        except Exception as exc:
            log.exception("unexpected error in %s", getattr(fn, "__name__", fn))
            self._fail(exc)

    def _decide_here(self, fn: Callable[..., Any], *args: Any) -> None:
        """Run ``fn(*args)`` (a control-loop input) in this device thread, under the control
        lock: no hop to the event loop. Its motor command goes straight to the link
        (:meth:`_MotorWorker.send_now`); the recorder and network calls it makes are held
        and sent after it, so no other thread is woken before the motors have their
        command. A bug stops the daemon (exit 1), as on the event loop."""
        with self._control_lock:
            self._deciding = threading.get_ident()
            try:
                fn(*args)
            except Exception as exc:
                log.exception("unexpected error in %s", getattr(fn, "__name__", fn))
                self.fail_from_thread(exc)
            finally:
                self._deciding = None
                records, self._held_records = self._held_records, []
                calls, self._held_net = self._held_net, []
                state, self._held_state = self._held_state, False
                if records and self.recorder is not None:
                    for method, arg in records:
                        self.recorder.put(method, arg)
                if calls and self._net is not None:
                    # one wake-up of the network loop
                    self._net.call(_run_calls, calls, publication=not state)

    def _gps_thread(self) -> None:
        reader = self._gps_reader
        take_events = getattr(reader, "take_health_events", None)
        while not self._threads_stop.is_set():
            records = reader.poll(0.2)
            # Health first: an unplugged GPS must reach the controller now, not after records
            # or the fix timeout.
            events = take_events() if take_events is not None else None
            if events:
                self._decide_here(self._on_device_events, events)
            if records:
                self._decide_here(self._on_gps_records, records)
                pacer, motors = self.gc_pacer, self.motors
                if (
                    pacer is not None
                    and (motors is None or motors.idle)
                    and any(isinstance(r, GpsFix) for r in records)
                ):
                    # the fix's command is out: until the next GGA nothing is urgent
                    pacer.collect()

    def _compass_thread(self) -> None:
        from drivers.cmps10 import Cmps10

        dev = self._compass
        compass = dev if hasattr(dev, "read") and not hasattr(dev, "read_byte_data") else None
        if compass is None:
            compass = Cmps10(dev)
        cfg = self.config.compass
        if hasattr(compass, "stale_s"):
            compass.stale_s = cfg.stale_s  # stale by time, not only by failed-sample count
        self._compass_driver = compass
        take_events = getattr(compass, "take_health_events", None)
        backoff_s, t_reopen = REOPEN_BACKOFF_S[0], -math.inf
        period_s = 1.0 / cfg.rate_hz
        t_next = time.monotonic()
        while not self._threads_stop.is_set():
            t_s = time.monotonic()
            att = None
            health = getattr(compass, "health", None)
            if getattr(compass, "needs_reopen", False):
                # Lost on a non-transient error: reopen the bus, with capped backoff.
                if t_s >= t_reopen:
                    if self._reopen_compass(compass, t_s, t_s + backoff_s):
                        backoff_s = REOPEN_BACKOFF_S[0]
                    else:
                        t_reopen = t_s + backoff_s
                        backoff_s = min(2.0 * backoff_s, REOPEN_BACKOFF_S[1])
            else:
                try:
                    att = compass.read(t_s)
                except X6wdError as exc:  # non-transient: a driver with health says so
                    self.compass_errors += 1
                    if health is None and (
                        self.compass_errors in (1, 10, 100) or self.compass_errors % 1000 == 0
                    ):
                        log.warning("compass read failed (%d): %s", self.compass_errors, exc)
            events = take_events() if take_events is not None else None
            if events:
                self._post(self._on_device_events, events)
            if att is not None:
                self._post(self._on_attitude, att)
            t_next += period_s
            delay = t_next - time.monotonic()
            if delay < -period_s:  # fell behind (suspend, slow bus): do not burst
                t_next = time.monotonic()
                delay = 0.0
            self._threads_stop.wait(max(0.0, delay))

    def _reopen_compass(self, compass: Any, t_s: float, next_attempt_t_s: float) -> bool:
        """Open the compass URL again and move its bus into ``compass`` (counters and health
        carry on); False, recorded as a failed reopen, when nothing answers."""
        from drivers import registry

        fresh = None
        try:
            fresh = registry.open_compass(self.config.compass.url, self.devices)
            fresh.check_version()  # the sim:// path does not check on open
        except (OSError, X6wdError) as exc:
            if fresh is not None:
                with contextlib.suppress(Exception):
                    fresh.close()
            compass.health_tracker.open_failed(f"reopen failed: {exc}", t_s, next_attempt_t_s)
            return False
        compass.attach_bus(fresh.bus, t_s)
        return True

    def _health_from_thread(self, ok: bool, t_s: float) -> None:
        self._post(self._on_motor_health, ok, t_s)

    def _health_events_from_thread(self, events: list[HealthEvent]) -> None:
        self._post(self._on_device_events, events)

    def _odometry_from_thread(self, rec: WheelOdometry) -> None:
        self._post(self._on_odometry, rec)

    # -- event-loop side: the edge of the one loop (x6wd.loop.runner) ---------------------
    def _on_gps_records(self, records: list[Any]) -> None:
        assert self.runner is not None
        self.runner.gps(records)  # the control decision first: GGA-to-motor latency
        if self._gpsd_wmm:
            self._gpsd_declination()
        if self.console is not None:
            for rec in records:
                if isinstance(rec, GpsSky):  # the satellites' C/N0 for the page's sky table
                    self._net_call(self.console.publish_sky, rec, publication=True)
        if self.gpsd is not None:
            for rec in records:
                if isinstance(rec, GpsFix):
                    self._net_call(self.gpsd.publish_fix, rec, publication=True)
                elif isinstance(rec, GpsSky):
                    self._net_call(self.gpsd.publish_sky, rec, publication=True)
                elif isinstance(rec, NmeaSentence):
                    self._net_call(self.gpsd.publish_nmea, rec.text, publication=True)

    def _gpsd_declination(self) -> None:
        """Hand the World Magnetic Model's declination to the gpsd port once the runner has
        it (its ATT heading is then true, as the controller's)."""
        assert self.runner is not None and self.gpsd is not None
        found = self.runner.declination
        if "deg" in found:
            self._gpsd_wmm = False
            self._net_call(self.gpsd.set_declination, float(found["deg"]))
        elif "error" in found:
            self._gpsd_wmm = False  # no model value: ATT stays magnetic (status says why)

    def _on_attitude(self, att: Attitude) -> None:
        assert self.runner is not None
        self.runner.attitude(att)
        if self.gpsd is not None:
            self._net_call(self.gpsd.publish_attitude, att, publication=True)

    def _on_odometry(self, rec: WheelOdometry) -> None:
        assert self.runner is not None
        self.runner.odometry(rec)

    def _operator_seen(self) -> None:
        if self.runner is not None:
            self.runner.operator_seen()

    def _on_motor_health(self, ok: bool, t_s: float) -> None:
        assert self.runner is not None
        self.runner.motor_link(ok, t_s)

    def _on_device_events(self, events: list[HealthEvent]) -> None:
        assert self.runner is not None
        self.runner.device_events(events)
        if self.gpsd is not None:
            for ev in events:
                if ev.device == "gps" and ev.kind == "transition":  # gpsd clients see it too
                    self._net_call(self.gpsd.set_gps_state, ev.new)

    def _net_call(self, fn: Callable[..., Any], *args: Any, publication: bool = False) -> None:
        """``fn(*args)`` on the network loop; a ``publication`` may be dropped while that
        loop is stalled (:meth:`_NetThread.call`), a state change never."""
        if self._net is not None:
            if self._deciding == threading.get_ident():
                self._held_net.append((fn, args))  # sent after the motor command
                self._held_state = self._held_state or not publication
            else:
                self._net.call(fn, *args, publication=publication)

    def _record(self, method: str, arg: Any) -> None:
        if self.recorder is not None:
            if self._deciding == threading.get_ident():
                self._held_records.append((method, arg))  # queued after the motor command
            else:
                self.recorder.put(method, arg)

    def _submit(self, cmd: MotorCommand) -> bool:
        """Hand ``cmd`` to the motor worker; False when an operator stop holds the motors
        and drops it (the runner then does not record it as sent)."""
        if self.motors is None:
            return True
        if self._deciding == threading.get_ident():
            # a device thread's decision: write it to the link from this thread when idle
            self.motors.send_now(cmd)
            return not self.motors.last_held()
        self.motors.submit(cmd, repeat_after_s=MOTOR_REPEAT_S)
        held = self.motors.last_held()
        # Hand the GIL to the motor thread now rather than after the telemetry work
        # that follows (up to a switch interval later).
        time.sleep(0)
        return not held

    def _publish(self, event: dict[str, Any]) -> None:
        if self.console is not None:
            # one wake-up of the network loop
            self._net_call(self._publish_net, event, publication=True)
        elif self.server is not None:
            self._net_call(self.server.publish, event, publication=True)

    def _publish_net(self, event: dict[str, Any]) -> None:
        """On the network loop: an event for the control port's watchers and the console."""
        if self.server is not None:
            self.server.publish(event)
        if self.console is not None:
            self.console.publish(event)

    def _on_state(self, change: StateChange) -> None:
        self.notifier.status(self._status_text())

    def _observe(self, outputs: list[Any], important: bool) -> None:
        """Every controller output list, after routing (a hook for tests and benchmarks)."""

    async def _control_loop(self) -> None:
        """The one loop's real-time edge: controller ticks and the systemd watchdog as tasks
        of one group, until a stop is asked for; a failure in either stops the daemon."""
        assert self.runner is not None and self._stop_event is not None
        tasks = []
        wd_s = self.notifier.watchdog_interval_s
        if wd_s is not None:
            tasks.append(lambda: every(wd_s, time.monotonic, self._feed_watchdog))
        pacer = self.gc_pacer
        if pacer is not None:  # collects only while the GPS thread does not (no fixes)
            tasks.append(lambda: every(1.0, time.monotonic, pacer.collect_if_overdue))
        # the ticks take the control lock (the GPS thread decides on fixes under it)
        ticks = cast(Runner, _LockedTicks(self.runner, self._control_lock))
        try:
            await run_realtime(ticks, self._stop_event, tick_hz=TICK_HZ, tasks=tasks)
        except Exception as exc:  # an ExceptionGroup from the task group: a bug, so fail
            log.exception("control loop failed")
            self._fail(exc)

    def _feed_watchdog(self, _now_s: float) -> None:
        # only a loop that is really turning (and whose readers live) feeds systemd
        if self._threads_alive():
            self.notifier.watchdog()

    def _threads_alive(self) -> bool:
        ok = all(t.is_alive() for t in self._threads)
        ok = ok and (self._net is None or self._net.thread.is_alive())
        return ok and (self.motors is None or self.motors.thread.is_alive())

    def _status_text(self) -> str:
        tel = self.last_telemetry
        if tel is None:
            return "ready, waiting for inputs"
        text = f"{tel.mode} {tel.state}"
        if tel.hold_reason:
            text += f" ({tel.hold_reason})"
        if tel.waypoint_index is not None:
            text += f" wp {tel.waypoint_index + 1}/{tel.waypoint_count}"
        return text

    # -- Backend (the control server calls these on the network loop) ------------------------
    def _on_control(self, fn: Callable[..., Any], *args: Any) -> Any:
        """Run ``fn`` on the control loop: directly when already there, else as an awaitable
        for the server (the controller is only ever touched from the control loop)."""
        harmless = (
            fn == self._status
            or fn == self._operator_stop
            or (fn == self._command and args[0] in ("stop", "pause"))
        )
        if not self._accepting and not harmless:
            # the ports listen before the devices open: nothing may queue a move meanwhile
            raise CommandError("rejected", "x6wd is starting: devices are not open yet")
        loop = self._loop
        lock = self._control_lock
        if loop is None or threading.get_ident() == self._loop_thread_id:
            with lock:
                return fn(*args)

        async def call() -> Any:
            with lock:
                return fn(*args)

        return asyncio.wrap_future(asyncio.run_coroutine_threadsafe(call(), loop))

    def status(self) -> Any:
        """State, last telemetry and device health as a JSON-ready dict."""
        return self._on_control(self._status)

    def load_mission(self, waypoints: list[Waypoint]) -> Any:
        """Check the geofence, then hand the waypoints to the controller."""
        return self._on_control(self._load_mission, waypoints)

    def start(self) -> Any:
        """Start the loaded mission."""
        return self._on_control(self._command, "start")

    def pause(self) -> Any:
        """Pause (motors stop, mission kept)."""
        if self.motors is not None:
            self.motors.clear_restart_fault()  # the operator's act: see docs/motors.md
        return self._on_control(self._command, "pause")

    def resume(self) -> Any:
        """Resume a paused mission."""
        return self._on_control(self._command, "resume")

    def return_home(self) -> Any:
        """Drive back to the launch point (where the mission started) and end there."""
        return self._on_control(self._command, "return")

    def operator_seen(self) -> None:
        """An operator's request came in (the operator-link failsafe); never waits. Handed to
        the control loop at most every ``OPERATOR_SEEN_S``, in order with the requests."""
        now = time.monotonic()
        if now - self._t_operator < OPERATOR_SEEN_S:
            return
        self._t_operator = now
        self._post(self._operator_seen)

    def stop(self) -> Any:
        """Stop everything; always allowed. The stop also goes to the motors at once, and
        holds there until the controller has applied it: no drive decided before that (a
        fix's, a tick's) replaces it before it is sent, or follows it out."""
        if self.motors is None:
            return self._on_control(self._command, "stop")
        # thread-safe, and neither waits for the control loop: drives are dropped from here
        # until the controller has the stop, and the stop replaces any unsent command
        seq = self.motors.hold_stop()
        self.motors.clear_restart_fault()  # repeated board restarts: the operator's act
        self.motors.submit(MotorCommand(time.monotonic(), 0.0, 0.0, "operator stop"))
        return self._on_control(self._operator_stop, seq)

    def _operator_stop(self, seq: int) -> dict[str, Any]:
        """On the control loop, under the control lock: the controller stops, then the
        motors take drive commands again (the stop ``seq`` held them until now)."""
        try:
            reply = self._command("stop")
        except BaseException:
            # the controller's state is unknown: the hold stays (drives stay dropped, the
            # robot stands) until a later stop succeeds; said here, and in status
            log.error(
                "the controller failed to apply an operator stop: drive commands stay held"
                " at the motors until a stop succeeds",
                exc_info=True,
            )
            raise
        motors = self.motors
        if motors is not None:
            motors.stop_applied(seq)
            if not motors.link.healthy:
                # the controller stopped, but the stop may never reach the wheels: said in
                # the reply (an outside audit: "stop: ok", exit 0, with the board gone)
                reply = {**reply, "motors": "lost", "motors_reason": motors.health.reason}
        return reply

    def drive(self, left_pct: float, right_pct: float, duration_s: float) -> Any:
        """Manual drive (percent) for ``duration_s`` seconds; the controller stops after it."""
        return self._on_control(self._drive, left_pct, right_pct, duration_s)

    def log_tail(self, n: int) -> list[str]:
        """The last ``n`` log lines."""
        return self.log_buffer.tail(n)

    def _devices(self) -> dict[str, Any]:
        """Each device's health as a JSON-ready dict (None before it exists)."""
        out: dict[str, Any] = {}
        compass = self._compass_driver or self._compass
        for name, dev in (("gps", self._gps_reader), ("compass", compass), ("motors", self.motors)):
            health = getattr(dev, "health", None)
            if not isinstance(health, DeviceHealth):
                out[name] = None
                continue
            cached = self._dev_dicts.get(name)
            if cached is None or cached[0] is not health:  # snapshots are immutable: reuse
                cached = (health, health.to_dict())
                self._dev_dicts[name] = cached
            out[name] = cached[1]
        tel = self.last_telemetry
        untrusted = tel.extra.get("compass_untrusted") if tel is not None else None
        comp = out["compass"]
        if untrusted and comp is not None and comp["state"] == "connected":
            # its reader sees good registers; the EKF refuses what they say
            out["compass"] = {**comp, "state": "degraded", "reason": f"untrusted: {untrusted}"}
        c_health = getattr(compass, "health", None)
        comp = out["compass"]
        if (
            comp is not None
            and comp["state"] in ("connected", "degraded")
            and isinstance(c_health, DeviceHealth)
            and c_health.last_data_t_s is not None
        ):
            # its own stale check runs in its read, and a read that blocks (a hung I2C bus)
            # never returns to run it: "connected" at 34 s old (an outside audit)
            data_age_s = time.monotonic() - c_health.last_data_t_s
            limit_s = self.config.compass.stale_s
            if data_age_s > limit_s:
                why = f"no reading for {data_age_s:.1f} s (limit {limit_s:g} s)"
                out["compass"] = {
                    **comp,
                    "state": "stale",
                    "reason": f"{why}: its read has not returned (a hung I2C bus?)",
                }
        gps = out["gps"]
        stale_s = self.config.safety.fix_stale_s
        health = getattr(self._gps_reader, "health", None)
        if (
            gps is not None
            and gps["state"] == "connected"
            and tel is not None
            and isinstance(health, DeviceHealth)
            and time.monotonic() - health.since_t_s > stale_s  # a new link gets its chance
        ):
            # the line is healthy, but what it says is "no position": the robot cannot use it
            age_s = tel.fix_age_s
            if age_s is None or age_s > stale_s:
                since = "since start-up" if age_s is None else f"for {age_s:.0f} s"
                runner = self.runner
                hdop = runner.fix_refused_hdop if runner is not None else None
                # a line delivering nothing is named before the reader's gps.stale_s runs out
                quiet = runner.gps_line_quiet(runner.clock()) if runner is not None else ""
                what = quiet or (
                    "the receiver reports no position"
                    if hdop is None
                    else f"the receiver's fixes have HDOP {hdop:.1f} (20 or more: no position)"
                )
                out["gps"] = {**gps, "state": "degraded", "reason": f"no valid fix {since}: {what}"}
        out["odometry"] = self._odometry_status()
        return out

    def _odometry_status(self) -> dict[str, Any] | None:
        """The wheel encoders' polling: state, readings, failures (None before the motors)."""
        m = self.motors
        if m is None:
            return None
        out: dict[str, Any] = {
            "state": m.odometry_state,
            "readings": m.odometry_readings,
            "failures": m.odometry_failures,
        }
        if m.odometry_reason:
            out["reason"] = m.odometry_reason
        return out

    def _status(self) -> dict[str, Any]:
        now = time.monotonic()
        tel = self.last_telemetry
        devices = self._devices()
        gps, compass = devices["gps"] or {}, devices["compass"] or {}
        link_ok = self.motors is not None and bool(self.motors.link.healthy)
        odo = devices["odometry"]
        odometry: int | str = "unknown"
        if odo is not None:
            odometry = odo["readings"] if odo["state"] == "polling" else odo["state"]
        recorder = self.recorder.status() if self.recorder is not None else None
        return {
            "version": __version__,
            "uptime_s": round(now - self.t_start, 3),
            "mode": str(tel.mode) if tel else "IDLE",
            "state": str(tel.state) if tel else "IDLE",
            "telemetry": tel.to_dict() if tel else None,
            "devices": devices,
            # the short summary `x6wd client watch` shows (keys without "_")
            "links": {
                "gps": gps.get("state", "unknown"),
                "gps_reconnects": gps.get("reconnects", 0),
                "compass": compass.get("state", "unknown"),
                "compass_errors": compass.get("errors", self.compass_errors),
                "motors": "ok" if link_ok else "lost",
                "odometry": odometry,  # readings so far, or "unavailable"
                "recorder": (
                    recorder["state"]
                    if recorder is not None
                    else "unknown"
                    if self.config.recorder.enabled
                    else "off"  # not open yet
                ),
            },
            "recorder": recorder,
            # an operator stop the controller has not applied yet holds the motors' drive
            # commands (dropped, counted): true for milliseconds, or until a stop succeeds
            "motor_hold": (
                {
                    "holding": self.motors.stop_holding,
                    "dropped_while_stopping": self.motors.dropped_while_stopping,
                }
                if self.motors is not None
                else None
            ),
            # where the compass declination comes from, and its value: config, or the WMM
            "declination": self._declination_status(),
            # dates of a receiver past a GPS week rollover, corrected (null: not corrected)
            "gps_week_rollover": self._week_rollover_status(),
            # [gps] configure_receiver's UBX answers, and the fix rate measured against rate_hz
            "gps_receiver": self._gps_receiver_status(),
            # the control loop's own lateness (a CPU-starved core) and the stale-sensor holds
            # that began while it stood still (docs/navigation.md)
            "loop": self.runner.loop_status() if self.runner is not None else None,
            # bind keys listening beyond loopback in clear text (server.allow_plaintext)
            "plaintext_beyond_loopback": list(self._plaintext),
            # the web console's counts (dead-man stops, drives refused late or after another
            # client's stop, refused Hosts ...); absent without the console
            **({"console": self.console.stats()} if self.console is not None else {}),
        }

    def _declination_status(self) -> dict[str, Any]:
        """``status``'s ``declination``: the runner's (``source``; with the WMM ``deg`` or
        ``error``), with the configured value as ``deg`` when it comes from the config."""
        if self.runner is None:
            return {}
        decl = dict(self.runner.declination)
        configured = self.config.compass.declination_deg
        if decl.get("source") == "config" and "deg" not in decl and configured is not None:
            decl["deg"] = round(float(configured), 3)
        elif decl.get("source") == "wmm" and "deg" not in decl and "error" not in decl:
            decl["deg"] = 0.0  # in use until the first dated fix
            decl["pending"] = "no dated fix yet: heading is magnetic"
        return decl

    def _gps_receiver_status(self) -> dict[str, Any] | None:
        """``status``'s ``gps_receiver`` (None before the reader): ``configure_receiver``, its
        setup's state and answers (``setup``, None when nothing is sent), and the fix rate
        measured (``measured_rate_hz``) against the expected one; ``slow`` when fixes come
        too slowly for the staleness limits (drivers.gps_io.FixRate)."""
        reader = self._gps_reader
        rate = getattr(reader, "fix_rate", None)
        if rate is None:
            return None
        setup = getattr(reader, "setup", None)
        return {
            "configure_receiver": self.config.gps.configure_receiver,
            "setup": None if setup is None else setup.status(),
            **rate.status(),
        }

    def _week_rollover_status(self) -> dict[str, Any] | None:
        """``status``'s ``gps_week_rollover``: the GPS reader's corrections (None when its
        dates are not corrected: a ``replay://`` log, or no reader yet)."""
        fix = getattr(self._gps_reader, "week_rollover", None)
        return None if fix is None else fix.status()

    # the runner's operator requests, run on the control loop by _on_control
    def _load_mission(self, waypoints: list[Waypoint]) -> dict[str, Any]:
        assert self.runner is not None
        result = self.runner.load_mission(waypoints)
        self._mission = tuple((w.lat_deg, w.lon_deg) for w in waypoints)
        self._mission_rev += 1
        # the console's map revision this load made: a page tells its own load from another's
        return {**result, "revision": self._mission_rev}

    # -- the web console ----------------------------------------------------------------------
    def _make_console(self) -> ConsoleServer | None:
        """The console of ``[console]`` (None when off), sharing the control server's token,
        TLS and commands. Raises ConfigError naming the key."""
        cfg = self.config
        if not cfg.console.enabled:
            return None
        if self.server is None:
            raise ConfigError(
                "console.enabled: the console needs the control server (server.enabled = "
                "true): it uses its token, TLS and commands"
            )
        if cfg.console.deadman_s > cfg.safety.manual_max_s:
            raise ConfigError(
                f"console.deadman_s: {cfg.console.deadman_s:g} s is longer than "
                f"safety.manual_max_s ({cfg.safety.manual_max_s:g} s)"
            )
        ctx = None
        if cfg.server.tls_cert and cfg.server.tls_key:
            ctx = server_ssl_context(cfg.server.tls_cert, cfg.server.tls_key)
        recordings = Path(cfg.recorder.dir) if cfg.recorder.enabled else None
        return ConsoleServer(
            cfg.console, self.server, self._map_view, ssl_context=ctx, recordings_dir=recordings
        )

    def _map_view(self) -> dict[str, Any]:
        """What the console's map draws besides the robot: the loaded mission, the launch
        point (home: where the mission started, where ``return`` drives) and the geofence.
        Called on the network thread: reads only immutable snapshots."""
        runner, ctl = self.runner, self.controller
        centre = runner.geofence_centre() if runner is not None else None
        launch = getattr(ctl, "launch_point", None)
        return {
            "revision": self._mission_rev,
            "waypoints": [list(p) for p in self._mission],
            "launch": list(launch) if launch is not None else None,
            "geofence": {
                "center": list(centre) if centre is not None else None,
                "radius_m": self.config.safety.geofence_radius_m,
            },
        }

    def _command(self, name: str) -> dict[str, Any]:
        assert self.runner is not None
        return self.runner.command(name)

    def _drive(self, left_pct: float, right_pct: float, duration_s: float) -> dict[str, Any]:
        assert self.runner is not None
        return self.runner.drive(left_pct, right_pct, duration_s)


class _LockedTicks:
    """What :func:`x6wd.loop.runner.run_realtime` uses of a runner (``clock``, ``tick``),
    with each tick under the daemon's control lock."""

    def __init__(self, runner: Runner, lock: Any) -> None:
        self.clock = runner.clock
        self._tick = runner.tick
        self._lock = lock

    def tick(self, t_s: float | None = None) -> None:
        with self._lock:
            self._tick(t_s)


def _run_calls(calls: list[tuple[Callable[..., Any], tuple[Any, ...]]]) -> None:
    """Run held network calls in order, on the network loop (one failing does not stop the
    others: asyncio would only have logged it)."""
    for fn, args in calls:
        try:
            fn(*args)
        except Exception:
            log.exception("network call %s failed", getattr(fn, "__name__", fn))


def one_line(text: str) -> str:
    """``text`` with every run of whitespace (newlines too) as one space."""
    return " ".join(text.split())


def _exc_text(exc: BaseException) -> str:
    """``Type: message`` of an exception, on one line."""
    text = one_line(str(exc))
    return f"{type(exc).__name__}: {text}" if text else type(exc).__name__


CONFIG_ERROR_ATTR = "x6wd_config_error"


def config_error(exc: BaseException) -> None:
    """Log a configuration error as ONE line; on stderr it reads ``x6wd: <key>: <reason>``
    (see :class:`_StderrFormatter`), in every other log handler as an ERROR record."""
    log.error("%s", one_line(str(exc)), extra={CONFIG_ERROR_ATTR: True})


class _StderrFormatter(logging.Formatter):
    """``LEVEL name: message``; a configuration error as just ``x6wd: message``."""

    def __init__(self) -> None:
        super().__init__("%(levelname)s %(name)s: %(message)s")

    def format(self, record: logging.LogRecord) -> str:
        if getattr(record, CONFIG_ERROR_ATTR, False):
            return f"x6wd: {record.getMessage()}"
        return super().format(record)


def guarded_thread(
    target: Callable[[], None], name: str, on_death: Callable[[BaseException], None]
) -> threading.Thread:
    """A daemon thread running ``target``; whatever escapes it is a bug: logged, then handed
    to ``on_death`` (which stops the daemon: exit 1, motors stopped). Not started."""

    def guarded() -> None:
        try:
            target()
        except BaseException as exc:  # any escape is a bug: fail loudly, motors stop
            log.exception("thread %s died", name)
            on_death(exc)

    return threading.Thread(target=guarded, name=name, daemon=True)


def _bind_problem(host: str) -> str:
    """Why a server cannot bind to ``host`` ("" when it can be tried): it must be an IP
    address or a host name that resolves ("" and "localhost" are fine)."""
    if host in ("", "localhost"):
        return ""
    try:
        ipaddress.ip_address(host)
        return ""
    except ValueError:
        pass
    try:
        socket.getaddrinfo(host, None, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)
    except (OSError, UnicodeError) as exc:
        reason = exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc)
        return f"{host!r} is not an IP address or a host name that resolves ({reason})"
    return ""


def stop_signals() -> dict[signal.Signals, int]:
    """The signals that stop the daemon cleanly, each with its exit code: every signal whose
    default action would kill the process without stopping the motors. SIGTERM (systemd),
    SIGINT (Ctrl-C) and SIGHUP (the terminal closed) are requests to stop: exit 0. The
    others are nothing x6wd expects (SIGQUIT, SIGUSR1/2, timers, SIGPWR ...): exit 1, so
    systemd's Restart=on-failure brings the daemon back (motors stopped, IDLE)."""
    out = {signal.SIGTERM: EXIT_OK, signal.SIGINT: EXIT_OK, signal.SIGHUP: EXIT_OK}
    for name in (
        "SIGQUIT", "SIGUSR1", "SIGUSR2", "SIGALRM", "SIGVTALRM", "SIGPROF", "SIGPWR", "SIGIO",
        "SIGSTKFLT", "SIGXCPU",
    ):  # fmt: skip
        sig = getattr(signal, name, None)
        if sig is not None:
            out[sig] = EXIT_FAILURE
    return out


def _dir_problem(directory: Path) -> str:
    """Why recordings cannot be created in ``directory`` as configured ("" when they can, or
    when only the disk's state keeps them out now): see :func:`_dir_check`."""
    return _dir_check(directory)[0]


def _errno_text(exc: OSError) -> str:
    """``Read-only file system (EROFS)``: the error's text and its errno's name."""
    name = errno.errorcode.get(exc.errno or 0, "")
    text = exc.strerror or str(exc)
    return f"{text} ({name})" if name else text


def _dir_check(directory: Path) -> tuple[str, str]:
    """(problem, fault) of a recorder directory, checked without leaving anything behind:
    it is (or its nearest existing ancestor is) a directory where this user can create a
    file (an unnamed temporary one: the permission bits say yes to root everywhere, also in
    /proc, and a network or FUSE file system may refuse what they allow).

    ``problem`` (a configuration error, exit 2): a dangling link, not a directory, no
    permission (EACCES, EPERM), a file system that takes no files, anything unexpected.
    ``fault`` (the daemon starts, the recorder failing until the disk takes files): the
    directory exists and is right, but its file system is read-only (an SD card's error
    remounted it) or full (no space, no inodes, over quota): :data:`RUNTIME_ERRNOS`. Both
    name the errno. A directory still to be created on such a disk is a problem (it is not
    there to be right). The kernel says EROFS before EACCES, so on a runtime errno the
    permission bits are checked too (:func:`_no_write_permission`: no permission is a
    problem), and a mount read-only by configuration, not by its file system (a read-only
    bind mount, systemd's ProtectSystem: :func:`_read_only_mount`), is a problem: it stays
    so."""
    from x6wd.core.recorder import RUNTIME_ERRNOS

    d = directory if directory.is_absolute() else Path.cwd() / directory
    probe = d
    try:
        while not probe.exists():
            if probe.is_symlink():
                return f"{probe} is a dangling symbolic link", ""
            probe = probe.parent
        if not probe.is_dir():
            return f"{probe} is not a directory", ""
    except OSError as exc:
        return f"{probe}: {_errno_text(exc)}", ""
    try:
        with tempfile.TemporaryFile(dir=probe, prefix=".x6wd-probe-"):
            pass
    except OSError as exc:
        why = _errno_text(exc)
        if exc.errno in (errno.EACCES, errno.EPERM):
            verb = "write in" if probe == d else f"create {d} in"
            return f"this user may not {verb} {probe} ({why})", ""
        if exc.errno == errno.ENOENT:  # procfs: it would read as "no such directory"
            return f"cannot create a file in {probe}: its file system takes no files", ""
        if probe == d and exc.errno in RUNTIME_ERRNOS:
            # The kernel says EROFS before EACCES: a read-only disk hides a missing
            # permission, which the bits tell (it would fail for good once writable). Only
            # then: ENOSPC and EDQUOT come after the permission check, which passed; and
            # an ACL grants what the bits do not show (a review: a full card with an ACL'd
            # directory read as "may not write", exit 2)
            denied = (
                _no_write_permission(probe)
                if exc.errno == errno.EROFS and not _has_acl(probe)
                else ""
            )
            if denied:
                return f"this user may not write in {probe} ({denied}; {why} too)", ""
            if exc.errno == errno.EROFS:
                mount = _read_only_mount(probe)
                if mount:  # made read-only by configuration: it stays so
                    return (
                        f"cannot create a file in {probe}: {why}: {probe} is on a read-only "
                        f"mount ({mount}: read-only per mount, its file system is writable; "
                        "a bind mount or remount made read-only by configuration)"
                        + _protect_system_hint(probe),
                        "",
                    )
            return "", f"cannot create a file in {probe}: {why}"
        what = "a file in" if probe == d else f"{d} in"
        return f"cannot create {what} {probe}: {why}", ""
    return "", ""


def _has_acl(directory: Path) -> bool:
    """``directory`` carries a POSIX access ACL (its permission is not the mode bits')."""
    try:
        os.getxattr(directory, "system.posix_acl_access")
    except OSError:  # ENODATA: none; ENOTSUP: the file system has no ACLs
        return False
    return True


def _no_write_permission(directory: Path) -> str:
    """Why the permission bits of ``directory`` keep this process (its effective uid, gid
    and groups) from creating a file there ("" when they do not: root may, others need w
    and x in the class that applies to them, as the kernel checks), for when the file
    system said EROFS or ENOSPC before it checked them. ACLs are not read."""
    try:
        st = os.stat(directory)
    except OSError:
        return ""
    euid = os.geteuid()
    if euid == 0:
        return ""
    if st.st_uid == euid:
        need = stat.S_IWUSR | stat.S_IXUSR
    elif st.st_gid == os.getegid() or st.st_gid in os.getgroups():
        need = stat.S_IWGRP | stat.S_IXGRP
    else:
        need = stat.S_IWOTH | stat.S_IXOTH
    if st.st_mode & need == need:
        return ""
    return (
        f"Permission denied (EACCES): {stat.filemode(st.st_mode)} uid {st.st_uid} gid "
        f"{st.st_gid}, this user uid {euid} gid {os.getegid()}"
    )


def _mountinfo_unescape(field: str) -> str:
    """A path of /proc/self/mountinfo as it is (``\\040`` a space, ``\\011`` a tab ...)."""
    return re.sub(r"\\([0-7]{3})", lambda m: chr(int(m[1], 8)), field)


def _read_only_mount(directory: Path, mountinfo: str = "/proc/self/mountinfo") -> str:
    """The mount point of ``directory``'s mount when it is read-only per mount only (its
    mount options say ro, its file system's super options rw: a bind mount or a remount
    made read-only by configuration, e.g. systemd's ProtectSystem), else "" (a file system
    read-only itself, e.g. an SD card remounted after errors; or mountinfo unreadable). The
    mount is the one with the longest mount point prefix of the real path (the last listed
    of those mounted on the same point: the one on top)."""
    path = os.path.realpath(directory)
    try:
        with open(mountinfo, encoding="utf-8", errors="replace") as f:
            lines = f.read().splitlines()
    except OSError:
        return ""
    best: tuple[int, str, bool] | None = None  # (prefix length, mount point, per-mount ro)
    for line in lines:
        head, sep, tail = line.partition(" - ")
        fields, sup = head.split(), tail.split()
        if not sep or len(fields) < 6 or len(sup) < 3:
            continue
        point = _mountinfo_unescape(fields[4])
        if not (point == "/" or path == point or path.startswith(point.rstrip("/") + "/")):
            continue
        per_mount_ro = "ro" in fields[5].split(",") and "rw" in sup[2].split(",")
        if best is None or len(point) >= best[0]:
            best = (len(point), point, per_mount_ro)
    return best[1] if best is not None and best[2] else ""


def _protect_system_hint(directory: Path) -> str:
    """``; under systemd's ProtectSystem=strict ...`` for a directory outside
    /var/lib/x6wd (the x6wd unit's only writable place), else ""."""
    path = os.path.realpath(directory)
    if path == "/var/lib/x6wd" or path.startswith("/var/lib/x6wd/"):
        return ""
    return (
        "; under systemd's ProtectSystem=strict (the x6wd unit) only /var/lib/x6wd is "
        "writable: keep recordings there or add the dir to ReadWritePaths="
    )


def _gps_device(url: str, rate_hz: float, world: Any = None) -> tuple[str, int | None, float]:
    """What the gpsd port's DEVICE says about the GPS: its path, the line's baud rate (None:
    not a serial line) and its cycle (s between fixes). A ``serial://`` URL: its device and
    ``baud``, and ``[gps] rate_hz``; ``sim://`` with its ``world``: the simulated receiver's
    pty, baud rate and rate (``[sim] gps_baud``, ``gps_rate_hz``); ``replay://``: the file
    at ``[gps] rate_hz`` (a log plays at its own times, those of the receiver it was recorded
    from; the URL's ``rate``, where it is not the default 1, paces a log without times);
    anything else (``tcp://``): the URL, no baud rate."""
    from drivers import registry

    try:
        dev = registry.parse_url(url, "gps")
    except ConfigError:
        return url, None, 1.0 / rate_hz
    if dev.scheme == "serial":
        path, bps = registry.device_path(url)
        return path, bps, 1.0 / rate_hz
    if dev.scheme == "sim" and world is not None:
        rx = world.receiver
        return str(world.uart.port_name), int(rx.baud), 1.0 / float(rx.rate_hz)
    if dev.scheme == "replay":  # the URL's rate, where it is not the default, paces it
        url_hz = float(dev.options["rate"])
        given = url_hz != registry.DEFAULTS["gps"]["replay"]["rate"]
        return dev.target, None, 1.0 / (url_hz if given else rate_hz)
    return url, None, 1.0 / rate_hz


def _listen_problem(section: str, bind: str, port: int, exc: OSError) -> str:
    """The one-line error for a server that cannot listen, naming the key to change."""
    bad_address = isinstance(exc, socket.gaierror) or exc.errno in (errno.EADDRNOTAVAIL, None)
    key = f"{section}.bind" if bad_address else f"{section}.port"
    if exc.errno == errno.EADDRINUSE and section == "gpsd":
        # 2947 is gpsd's own port, which a system gpsd (gpsd.socket) may hold
        reason = (
            "address already in use (another x6wd, or a system gpsd: stop it with "
            "'systemctl stop gpsd.socket gpsd', or set gpsd.port to a free port)"
        )
    elif exc.errno == errno.EADDRINUSE:
        reason = "address already in use (another x6wd or gpsd running?)"
    elif exc.errno == errno.EACCES:
        reason = "permission denied (ports below 1024 need privileges)"
    else:
        reason = one_line(exc.strerror or str(exc))
    return f"{key}: cannot listen on {bind}:{port}: {reason}"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of ``x6wd run``."""
    parser.add_argument("--config", required=True, help="TOML configuration file")
    parser.add_argument(
        "--log-level",
        default="INFO",
        choices=("DEBUG", "INFO", "WARNING", "ERROR"),
        help="logging threshold (default INFO)",
    )


def main(args: argparse.Namespace) -> int:
    """Run the daemon until a signal (:func:`stop_signals`: exit 0 for SIGTERM, SIGINT and
    SIGHUP, 1 for the others) or a failure (1; a configuration error 2)."""
    tail = LogTail()
    root = logging.getLogger()
    root.setLevel(args.log_level)
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(_StderrFormatter())
    root.addHandler(handler)
    root.addHandler(tail)
    notifier = Notifier.from_env()
    try:
        config = load_config(args.config)
    except ConfigError as exc:
        config_error(exc)
        notifier.stopping(f"configuration error: {one_line(str(exc))}")
        return EXIT_CONFIG
    daemon = Daemon(config, notifier=notifier, log_tail=tail)

    async def amain() -> int:
        # asyncio's add_signal_handler, but one that no stalled loop can make lose a signal
        with _SignalLoop(asyncio.get_running_loop()) as loop:
            for sig, code in stop_signals().items():
                if sig == signal.SIGHUP and signal.getsignal(sig) == signal.SIG_IGN:
                    # started under nohup: the user asked it to outlive the terminal, and it
                    # does (still in control); every other inherited SIG_IGN is overridden
                    log.info("SIGHUP ignored (nohup): x6wd keeps running when its terminal closes")
                    continue
                loop.add_signal_handler(sig, daemon.stop_on_signal, sig, code)
            return await daemon.run()

    return asyncio.run(amain())


class _SignalLoop:
    """``loop.add_signal_handler`` for the daemon's stop signals, as asyncio's (``callback(
    *args)`` runs on ``loop``), but never losing a signal (a context manager: the previous
    handlers are back on exit).

    asyncio's handler only writes the signal's number to the loop's self-pipe, which the
    device threads' ``call_soon_threadsafe`` calls fill while the loop is stalled (a full
    stderr pipe, a stuck logging handler): the number was then dropped, and the SIGTERM
    lost. This one is a Python-level handler (``signal.signal``): it runs in the main
    thread (the loop's) as soon as that runs Python code again (a blocking write the signal
    interrupts is retried after it), and appends the callback to the loop's ready queue,
    which no full pipe can refuse: the loop runs it as soon as it turns again. A wake-up fd
    of its own (written by nothing else, so never full of anything but signals) wakes a loop
    waiting in select when the signal went to another thread."""

    def __init__(self, loop: asyncio.AbstractEventLoop) -> None:
        self.loop = loop
        self._callbacks: dict[int, tuple[Callable[..., Any], tuple[Any, ...]]] = {}
        self._old: dict[int, Any] = {}
        self._wake: tuple[socket.socket, socket.socket] | None = None
        self._old_fd = -1

    def __enter__(self) -> _SignalLoop:
        rsock, wsock = socket.socketpair()
        rsock.setblocking(False)
        wsock.setblocking(False)
        self._wake = (rsock, wsock)
        self._old_fd = signal.set_wakeup_fd(wsock.fileno(), warn_on_full_buffer=False)
        self.loop.add_reader(rsock.fileno(), self._drain)
        return self

    def add_signal_handler(self, sig: int, callback: Callable[..., Any], *args: Any) -> None:
        """On signal ``sig``, ``callback(*args)`` runs on the loop."""
        self._callbacks[int(sig)] = (callback, args)
        old = signal.signal(sig, self._handle)
        self._old.setdefault(int(sig), old)

    def _handle(self, signum: int, _frame: Any) -> None:
        # In the main thread, between any two bytecodes: nothing here may take a lock (the
        # loop, a logging handler may hold it); the stop and its log line run on the loop.
        entry = self._callbacks.get(signum)
        if entry is None:  # being restored (__exit__)
            return
        with contextlib.suppress(RuntimeError):  # the loop closed: the daemon is stopping
            self.loop.call_soon_threadsafe(entry[0], *entry[1])

    def _drain(self) -> None:
        assert self._wake is not None
        with contextlib.suppress(OSError):
            while self._wake[0].recv(4096):
                pass

    def __exit__(self, *exc: object) -> None:
        for sig, old in self._old.items():
            if old is not None:  # None: a handler not set from Python, nothing to restore
                signal.signal(sig, old)
        self._old.clear()
        self._callbacks.clear()
        if self._wake is not None:
            signal.set_wakeup_fd(self._old_fd)
            with contextlib.suppress(Exception):
                self.loop.remove_reader(self._wake[0].fileno())
            for sock in self._wake:
                sock.close()
            self._wake = None
