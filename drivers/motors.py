"""Motor controller link: the line protocol of docs/motors.md, both ends of it.

- :class:`SerialMotorLink` drives a real board over any pyserial-like port and waits for the
  board's acknowledgement of every command.
- :class:`LogMotorLink` only records commands (bench runs, dry runs, tests).
- :class:`MotorBoard` is the board's side as a sans-IO parser: bytes and the time in, reply
  bytes out, with the watchdog and the wheel-encoder counters. The simulator runs it behind a
  pseudo-terminal (:func:`serve_board_fd`) so the daemon talks to it exactly as to the real
  board.

Stopping never raises: :meth:`SerialMotorLink.stop` tries, counts and returns whether the
board confirmed. If the link is dead, the board's watchdog stops the motors by itself.

Health: both links keep a :class:`~x6wd.core.records.DeviceHealth` (:attr:`health`) and queue its
transitions for :meth:`take_health_events`. A port error with a transient errno
(:data:`x6wd.core.errors.TRANSIENT_ERRNOS`) or a missing acknowledgement is retried within the
command; any other port error is not (the port is broken): the link is lost at once. So are
``transient_limit`` transient errors in a row (:data:`drivers.gps_io.TRANSIENT_LIMIT`, as for
the GPS), across commands, once they have gone on for :data:`TRANSIENT_MIN_S` with no
command through in between: a pty or USB adapter that went away answers EIO for ever. A
port that reopens but still fails is reopened with the backoff still growing: it is reset
only by a command that succeeds on the new port. A link where over half of the last
:data:`RETRY_WINDOW` commands needed a retry is degraded.
"""

from __future__ import annotations

import logging
import math
import os
import select
import socket
import struct
import threading
import time
from collections import Counter, deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol, runtime_checkable

from drivers.gps_io import TRANSIENT_LIMIT
from x6wd.core.errors import is_transient
from x6wd.core.health import HealthTracker, root_oserror
from x6wd.core.records import DeviceHealth, DeviceState, HealthEvent, MotorCommand, WheelOdometry

log = logging.getLogger(__name__)

MAX_PCT = 100
PCT_SLACK = 1e-9
"""How far (percent) beyond ±MAX_PCT a drive value may be and still count as ±MAX_PCT: float
rounding of a command scaled to exactly 100 % (a few ulps), never a real overshoot."""
WATCHDOG_MIN_MS = 50
WATCHDOG_MAX_MS = 60_000
DEFAULT_WATCHDOG_MS = 500
MAX_LINE_BYTES = 64
SEQ_MODULO = 10_000
# Encoders (docs/motors.md, "Wheel encoders"): the board's counters are unsigned 32-bit and
# its latch number 16-bit; a latch number more than ENC_MAX_SEQ_STEP ahead (or not ahead)
# of the last one means the board restarted and its counters began again at 0.
ENC_MODULO = 1 << 32
ENC_SEQ_MODULO = 1 << 16
ENC_MAX_SEQ_STEP = 1000
ENC_MAX_COUNTS_PER_S = 200_000.0
"""The most counts per second a side's encoder can move while the wheels turn, by default: a
reading that moved further than this over the longest the board can have counted since the
last one (:class:`EncoderUnwrap`) is no motion. The X6WD's default wheels
give 1632 counts per turn of a 120 mm wheel, 4,329 counts/m, and its top speed is 3.888 m/s
(14 km/h, ``[navigation] full_speed_mps``): 16,800 counts/s; 200,000 leaves a factor of 12
for finer encoders, bigger wheels or a faster robot. A board restart that went unannounced
(its ``EVT BOOT`` lost) with a latch number that happens to step 1..ENC_MAX_SEQ_STEP showed
as a jump back by the board's whole lifetime count (-4,299,957 counts, 1 km, in one 50 ms
poll). :func:`encoder_rate_bound` gives the bound for a configured robot."""
ENC_JUMP_SLACK_S = 0.05
"""Time (s) added to the longest interval between two latches (this reply's arrival minus
the last request's send) before the distance bound is applied: the host's clock readings
around a write and a read are a few ms off the bytes' real times."""
TRANSIENT_MIN_S = 0.5
"""How long (s) transient port errors must go on, with no command through in between, before
the port counts as broken (besides ``transient_limit`` of them): the board's default watchdog
period, after which the board has stopped the motors by itself, so closing and reopening
costs no more; a USB or EMI hiccup of tens of ms (or one command's back-to-back retries,
which have no delay between them) is ridden out on the same port."""
RETRY_WINDOW = 20
"""Commands kept to judge how often they needed a retry: when over half of the last
``RETRY_WINDOW`` did, the link is degraded (a board answering every other command)."""
RESTART_LATCH_COUNT = 3
RESTART_WINDOW_S = 60.0
"""Board restarts under a running link (``EVT BOOT`` once up, or one the encoder readings
show) that latch a fault: this many within this many seconds (s). A brown-out under motor
current restarts the board each time the robot drives off again; after one restart the link
comes back at the controller's first stop and a mission drives on, but the third within a
minute keeps the link lost until the operator stops or pauses
(:meth:`SerialMotorLink.clear_restart_fault`, which the daemon calls for them) and a stop the
board confirms follows. Never the controller's own stops: after a lost link cancelled a
manual drive it stops with ``idle``, and a held mission with ``hold: motor link lost``; if
those cleared it, the next drive would brown the board out again."""
W_RETRY_S = 1.0
W_RETRY_MAX_S = 30.0
"""A board that refuses ``W <watchdog_ms>`` (``ERR``: a firmware with a narrower range, or
none) is asked again after this many seconds (s), the wait doubling up to the maximum (s):
until it accepts, the link is lost and no ``M`` or ``P`` goes out (a drive on a watchdog
the host never set). Asked only after a stop the board confirmed, or before a drive or
ping."""
REFUSAL_LOGGED = (1, 10, 100)
"""Which of a command kind's refusals (``ERR``) are logged: these, then every 1000th (each
one is counted in ``counters.rejected`` and is the link's last error): a board that refuses
the keep-alive's stop did so 40 times a second, each a warning."""
REOPEN_LOG_S = 30.0
"""At most one "motor port reopened" log line per this many seconds (s); status counts
every reopen."""


class PortLike(Protocol):
    """What the link needs from a serial port (pyserial ``Serial`` fits)."""

    def read(self, size: int = 1) -> bytes: ...

    def write(self, data: bytes) -> int | None: ...

    def close(self) -> None: ...


@runtime_checkable
class MotorLink(Protocol):
    """Common interface of the motor backends (what the daemon uses)."""

    @property
    def healthy(self) -> bool: ...

    @property
    def last_command(self) -> MotorCommand | None: ...

    @property
    def health(self) -> DeviceHealth: ...

    def take_health_events(self) -> list[HealthEvent]: ...

    def drive(self, left_pct: float, right_pct: float, reason: str = "") -> bool: ...

    def stop(self, reason: str = "") -> bool: ...

    def send(self, cmd: MotorCommand) -> bool: ...

    def close(self) -> None: ...

    def __enter__(self) -> MotorLink: ...

    def __exit__(self, *exc: object) -> None: ...


def _check_pct(name: str, value: float) -> int:
    """Validate a drive percentage and round it to the protocol's integer percent.

    A value up to :data:`PCT_SLACK` beyond ±100 is float rounding of a saturated command
    (``x * 100 / peak`` gives 100.00000000000001) and is clamped to ±100; anything further
    out (100.5, a NaN, an infinity) is a ValueError."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ValueError(f"{name} must be a number in -100..100 percent, got {value!r}")
    if not math.isfinite(value) or abs(value) > MAX_PCT + PCT_SLACK:
        raise ValueError(f"{name} must be within -100..100 percent, got {value!r}")
    return max(-MAX_PCT, min(MAX_PCT, round(value)))


@dataclass
class LinkCounters:
    """Traffic and failures of a :class:`SerialMotorLink`."""

    sent: int = 0  # command lines written
    acked: int = 0  # OK received for a command
    rejected: int = 0  # ERR received for a command
    timeouts: int = 0  # no answer within ack_timeout_s
    write_errors: int = 0  # the port raised on write/read
    stop_failures: int = 0  # stop() calls that got no OK
    events: int = 0  # unsolicited EVT lines from the board (e.g. watchdog trips)
    watchdog_stops: int = 0  # EVT WATCHDOG: the board stopped the motors on its own
    board_restarts: int = 0  # restarts under a running link: EVT BOOT, or seen in E readings
    reopens: int = 0  # the port reopened after it broke
    held_drives: int = 0  # send() drives refused (a stop sent) while a board restart held
    restart_faults: int = 0  # RESTART_LATCH_COUNT restarts within RESTART_WINDOW_S: latched


def encoder_rate_bound(
    counts_per_rev: float, diameter_m: float, full_speed_mps: float, margin: float = 4.0
) -> float:
    """The counts per second a side can move (counts/s): ``full_speed_mps`` (m/s, the speed
    at +100 %) on a wheel of ``diameter_m`` (m, the smallest of the sides) with
    ``counts_per_rev`` counts per turn, times ``margin`` (wheel spin on loose ground, a
    downhill run). For :class:`SerialMotorLink`'s ``max_counts_per_s``."""
    if not (counts_per_rev > 0 and diameter_m > 0 and full_speed_mps > 0 and margin >= 1):
        raise ValueError(
            "encoder_rate_bound needs counts_per_rev, diameter_m, full_speed_mps > 0 and "
            f"margin >= 1, got {counts_per_rev!r}, {diameter_m!r}, {full_speed_mps!r}, "
            f"{margin!r}"
        )
    return counts_per_rev / (math.pi * diameter_m) * full_speed_mps * margin


def wrap_count_delta(delta: int) -> int:
    """The signed difference of two 32-bit counter readings (counts): the shortest way
    round the ring, valid while the true change is under 2**31 counts between readings."""
    return (delta + ENC_MODULO // 2) % ENC_MODULO - ENC_MODULO // 2


def parse_encoder_payload(payload: str) -> tuple[int, int, int] | None:
    """``"<seq> <left> <right>"`` of an ``E`` reply -> (seq, left, right), None if malformed
    or out of range (seq 0..65535, counts 0..2**32-1)."""
    tokens = payload.split()
    if len(tokens) != 3 or not all(t.isdigit() for t in tokens):
        return None
    seq, left, right = (int(t) for t in tokens)
    if seq >= ENC_SEQ_MODULO or left >= ENC_MODULO or right >= ENC_MODULO:
        return None
    return seq, left, right


class EncoderUnwrap:
    """Board counter readings (modulo 2**32) to continuous counts since the first reading.

    A reading after :meth:`rebase` (the board announced a reboot) is a new baseline: it adds
    no counts (the motion between the last reading and the restart is lost).

    Without times, a reading whose latch number is 1..ENC_MAX_SEQ_STEP ahead of the last
    continues and any other is a restart (a new baseline). With the reading's times (``t_s``
    when its reply arrived, ``sent_s`` when its request went out) and ``requests`` (latch
    requests written since the last reading, this one's included), it is judged by what each
    case looks like. The board latched the last reading no earlier than that request was
    sent and this one no later than this reply arrived, so its counters ran at most
    ``reach`` = ``max_counts_per_s`` x (``t_s`` - the last ``sent_s`` +
    :data:`ENC_JUMP_SLACK_S`) counts between the two (a host thread held up after a reply
    widens this, where the time between replies did not).

    - Continuing: the latch number 1..``requests`` ahead (only our requests latch) and each
      side within ``reach`` of the last reading: the counts add.
    - A restart nobody announced: the latch number 1..``requests`` itself and each side's
      count within ``reach`` of zero (a restarted board counts from 0 and latch 1): a new
      baseline. This catches the restart whose latch number happened to step 1..1000 (65001
      -> 1), with a big lifetime count or a small one (a robot that stood ~54 min: the
      counts near zero, which a distance bound alone took as motion backwards).
    - Neither, but the latch number 1..ENC_MAX_SEQ_STEP ahead and the counts within reach
      (another host polling ``E`` too): the counts add.
    - Anything else fits no motion: a new baseline (``implausible`` counts it).

    :meth:`reopened` (the port was opened again) makes the next reading continue only when
    the latch number continues (1..``requests`` ahead) and the counts fit ``reach`` over the
    outage; else it is a new baseline (a restart as above, or "reopened"). ``verdict`` is
    the last reading's: "first", "continued", "restart" (detected), "implausible" or
    "reopened". ``skipped``
    counts latches whose replies never arrived (nothing is lost: counts are cumulative);
    ``restarts`` the new baselines after the first; ``detected`` the restarts seen in the
    readings (no ``EVT BOOT``); ``jumps`` the readings that moved further than the wheels
    can (a restart or implausible).
    """

    def __init__(self, max_counts_per_s: float = ENC_MAX_COUNTS_PER_S) -> None:
        if not (max_counts_per_s > 0 and math.isfinite(max_counts_per_s)):
            raise ValueError(f"max_counts_per_s must be > 0, got {max_counts_per_s!r}")
        self.max_counts_per_s = float(max_counts_per_s)
        self.left = 0
        self.right = 0
        self.skipped = 0
        self.restarts = 0
        self.detected = 0  # restarts seen in the readings (latch and counts from zero)
        self.implausible = 0  # readings that fit neither motion nor a restart
        self.jumps = 0  # readings that moved further than the wheels can in the time
        self.verdict = ""
        self._last: tuple[int, int, int] | None = None  # (seq, left, right) as read
        self._last_t: float | None = None  # when its request went out (else its reply), s
        self._reopened = False  # the port reopened since the last reading

    def rebase(self) -> None:
        """The next reading starts a new baseline (the board's counters began again)."""
        if self._last is not None:
            self.restarts += 1
        self._last = None
        self._last_t = None
        self._reopened = False

    def reopened(self) -> None:
        """The port was opened again: the next reading continues only if it plainly does
        (its latch number continues and its counts fit the time since the last one)."""
        self._reopened = self._last is not None

    def update(
        self,
        seq: int,
        left: int,
        right: int,
        t_s: float | None = None,
        *,
        sent_s: float | None = None,
        requests: int | None = None,
    ) -> tuple[int, int]:
        """Take one reading (its reply at ``t_s``, its request sent at ``sent_s``, s, and
        ``requests`` latch requests sent since the last reading, if known); the continuous
        (left, right) counts."""
        last = self._last
        reopened, self._reopened = self._reopened, False
        if last is None:
            self.verdict = "first"
        else:
            step = (seq - last[0]) % ENC_SEQ_MODULO
            d_left = wrap_count_delta(left - last[1])
            d_right = wrap_count_delta(right - last[2])
            reach = self._reach(t_s)
            own = ENC_MAX_SEQ_STEP if requests is None else max(1, requests)
            ahead = 1 <= step <= ENC_MAX_SEQ_STEP
            moved = max(abs(d_left), abs(d_right))
            fits = reach is None or moved <= reach
            if 1 <= step <= own and fits:
                verdict = "continued"
            elif reach is None:  # no times: the latch number alone
                verdict = "continued" if ahead else "restart"
            elif (
                1 <= seq <= own
                and max(abs(wrap_count_delta(left)), abs(wrap_count_delta(right))) <= reach
            ):
                verdict = "restart"
            elif ahead and fits and not reopened:
                verdict = "continued"
            else:
                verdict = "implausible"
            if verdict == "continued":
                self.skipped += step - 1
                self.left += d_left
                self.right += d_right
            else:
                self.restarts += 1
                if reopened and verdict == "implausible":
                    verdict = "reopened"  # a new baseline, as every reopen was before
                elif verdict == "restart":
                    self.detected += 1
                else:
                    self.implausible += 1
                if not fits:
                    self.jumps += 1
            self.verdict = verdict
        self._last = (seq, left, right)
        self._last_t = sent_s if sent_s is not None else t_s
        return self.left, self.right

    def _reach(self, t_s: float | None) -> float | None:
        """The most counts a side can have moved since the last reading's request went out
        (None without the times)."""
        if t_s is None or self._last_t is None:
            return None
        return self.max_counts_per_s * (max(0.0, t_s - self._last_t) + ENC_JUMP_SLACK_S)


# --- host side ------------------------------------------------------------------------------


class SerialMotorLink:
    """Drive a motor board over a serial port with the docs/motors.md protocol.

    Every command carries a sequence number and waits up to ``ack_timeout_s`` (s) for its
    ``OK``; it is retried ``retries`` times. At start the board's watchdog is set to
    ``watchdog_ms``; the board stops by itself when no command arrives for that long, so
    the caller must send commands (or :meth:`ping`) more often than that. I/O failures never
    raise out of :meth:`drive`, :meth:`stop` or :meth:`close`: they are counted and make
    :attr:`healthy` False (``unhealthy_after`` failed commands in a row, or at once for a
    non-transient port error); :attr:`health` says connected / degraded / disconnected /
    reconnecting (commands failing while lost), with error and reconnect counts.

    ``reopen`` (optional) opens the port again: after a non-transient port error (a TCP
    board that closed its socket, a USB adapter that re-enumerated) the link closes the dead
    port and, on the commands that follow, calls it with capped exponential backoff
    (``reopen_initial_s`` doubling to ``reopen_max_s``); until then commands fail at once.
    Without it a broken port stays broken (the owner replaces the link).

    ``max_counts_per_s`` (counts/s, default :data:`ENC_MAX_COUNTS_PER_S`;
    :func:`encoder_rate_bound` for a configured robot): encoder readings that moved further
    than this allows are no motion (:class:`EncoderUnwrap`). After a reopen of the port
    the odometry goes on only if the next reading plainly continues the last (its latch
    number 1..n ahead, its counts within reach over the outage: a TCP link that dropped),
    else a new baseline (a board on native USB restarts with its port, and its
    ``EVT BOOT`` went out before the port was open again).
    """

    def __init__(
        self,
        port: Any,
        *,
        ack_timeout_s: float = 0.1,
        watchdog_ms: int = DEFAULT_WATCHDOG_MS,
        retries: int = 1,
        unhealthy_after: int = 2,
        clock: Callable[[], float] = time.monotonic,
        reopen: Callable[[], Any] | None = None,
        reopen_initial_s: float = 0.2,
        reopen_max_s: float = 5.0,
        transient_limit: int = TRANSIENT_LIMIT,
        max_counts_per_s: float = ENC_MAX_COUNTS_PER_S,
    ) -> None:
        if not (ack_timeout_s > 0 and math.isfinite(ack_timeout_s)):
            raise ValueError(f"ack_timeout_s must be > 0 s, got {ack_timeout_s!r}")
        if not WATCHDOG_MIN_MS <= watchdog_ms <= WATCHDOG_MAX_MS:
            raise ValueError(
                f"watchdog_ms must be {WATCHDOG_MIN_MS}..{WATCHDOG_MAX_MS}, got {watchdog_ms!r}"
            )
        if retries < 0 or unhealthy_after < 1:
            raise ValueError("retries must be >= 0 and unhealthy_after >= 1")
        if transient_limit < 1:
            raise ValueError(f"transient_limit must be >= 1, got {transient_limit!r}")
        if not 0 < reopen_initial_s <= reopen_max_s < math.inf:
            raise ValueError(
                "reopen backoff must satisfy 0 < reopen_initial_s <= reopen_max_s, got "
                f"{reopen_initial_s!r} and {reopen_max_s!r}"
            )
        self._reopen = reopen
        self.reopen_initial_s = float(reopen_initial_s)
        self.reopen_max_s = float(reopen_max_s)
        self._reopen_backoff_s = self.reopen_initial_s
        self._next_reopen_t = -math.inf
        self._port_dead = False  # closed after a non-transient error, reopen pending
        self.transient_limit = transient_limit
        self._transient_run = 0  # transient port errors in a row, across commands
        self._transient_t0: float | None = None  # when that run began
        self._reopens_since_break = 0  # reopens since the port last carried a command
        self._reopen_log_t = -math.inf
        self._retried: deque[bool] = deque(maxlen=RETRY_WINDOW)  # per answered command
        self.ack_timeout_s = float(ack_timeout_s)
        self.watchdog_ms = int(watchdog_ms)
        self.retries = retries
        self.unhealthy_after = unhealthy_after
        self.counters = LinkCounters()
        self._clock = clock
        self._seq = 0
        self._rx = bytearray()
        self._failures = 0
        self._closed = False
        self._last: MotorCommand | None = None
        self._lock = threading.Lock()
        self._tracker = HealthTracker("motors", t_s=clock())
        self._set_port(port)
        self.encoders = EncoderUnwrap(max_counts_per_s)
        self._latch_requests = 0  # E lines written since the last valid encoder reading
        self._write_s = clock()  # when the last command line was written (s, ``clock``)
        self.odometry_supported: bool | None = None
        self._refusal: str | None = None  # the payload of the latest ERR
        # Why the board restarted under a running link (EVT BOOT once up, or seen in an
        # encoder reading), until a stop() the board confirmed: the link is lost meanwhile
        # and send() refuses drives.
        self._restart_hold: str | None = None
        # Board restarts (times, s) within RESTART_WINDOW_S; the latched fault they make
        # (its reason) until an operator's stop: the hold stays meanwhile
        self._restarts: deque[float] = deque()
        self._restart_fault: str | None = None
        # the fault the operator cleared (clear_restart_fault), ended by the next confirmed
        # stop; a fault latched after that is another object and stays
        self._fault_cleared: str | None = None
        # The board's refusal of our W (why, for status) while it lasts, when to ask again
        # and the wait after that (s): W_RETRY_S
        self._w_refusal: str | None = None
        self._w_retry_t = -math.inf
        self._w_wait_s = W_RETRY_S
        self._refusals: Counter[str] = Counter()  # ERR replies per command kind
        self.configured = False
        self._configure()

    def _set_port(self, port: Any) -> None:
        self.port = port
        self._rx = bytearray()
        # Poll the port in short slices so a deadline is honoured whatever the port's timeout.
        if hasattr(port, "timeout"):
            try:
                port.timeout = min(self.ack_timeout_s, 0.02)
            except Exception:  # a port that refuses: we still bound waits by our deadline
                log.debug("motor port does not accept a timeout", exc_info=True)

    def _configure(self) -> None:
        """Set the board's watchdog; until that succeeds the link counts as unhealthy. A
        refusal (``ERR``) keeps it lost, with no drive or ping sent, until the board accepts
        a later ``W`` (:data:`W_RETRY_S`)."""
        self._refusal = None
        self.configured = self._transact(f"W {self.watchdog_ms}")
        t_s = self._clock()
        if self.configured:
            self._w_wait_s = W_RETRY_S
            if self._w_refusal is not None:
                self._w_refusal = None
                log.warning("motors: the board accepts W %d now; drives go again", self.watchdog_ms)
            return
        self._failures = max(self._failures, self.unhealthy_after)
        if self._refusal is None:
            return  # unanswered: a link failure, counted as any other
        if self._w_refusal is None:
            log.error(
                "motors: the board refuses W %d (%s): no drive goes out until it accepts"
                " ([motors] watchdog_ms, or the URL's watchdog_ms, within the firmware's range)",
                self.watchdog_ms, self._refusal,
            )  # fmt: skip
        self._w_refusal = f"W {self.watchdog_ms}: board refused: {self._refusal}"
        self._w_retry_t = t_s + self._w_wait_s
        self._w_wait_s = min(2.0 * self._w_wait_s, W_RETRY_MAX_S)
        tracker = self._tracker
        if tracker.health.connected:
            tracker.lost(self._w_refusal, t_s, self._w_retry_t, count_error=False)
        else:
            tracker.open_failed(self._w_refusal, t_s, self._w_retry_t, count_error=False)

    def _configure_if_due(self) -> None:
        """Send ``W`` when the board lacks it: at once, or after a refusal once its wait has
        passed."""
        if not self.configured and (self._w_refusal is None or self._clock() >= self._w_retry_t):
            self._configure()

    # --- state ------------------------------------------------------------------------------

    @property
    def healthy(self) -> bool:
        """True while the board acknowledges commands (fewer than ``unhealthy_after``
        consecutive failed commands), the link is open and no board restart holds it
        (:meth:`send`)."""
        return (
            not self._closed
            and self._failures < self.unhealthy_after
            and self._restart_hold is None
            and self._w_refusal is None
        )

    @property
    def last_command(self) -> MotorCommand | None:
        """The last drive/stop command sent (acknowledged or not)."""
        return self._last

    @property
    def health(self) -> DeviceHealth:
        """The link's health (immutable snapshot; any thread may read it)."""
        return self._tracker.health

    def take_health_events(self) -> list[HealthEvent]:
        """Health transitions (and repeated failures while lost) since the last call."""
        return self._tracker.take_events()

    # --- commands ---------------------------------------------------------------------------

    def drive(self, left_pct: float, right_pct: float, reason: str = "") -> bool:
        """Set left/right drive in percent (-100..100, rounded to whole percent).

        Returns True when the board acknowledged. Bad values raise ValueError; I/O never
        raises. The caller's own new command: it goes out even while a board restart holds
        the link (:meth:`send` is the controller's path, which does not).
        """
        return self._drive(left_pct, right_pct, reason, held=False)

    def _drive(self, left_pct: float, right_pct: float, reason: str, *, held: bool) -> bool:
        left, right = _check_pct("left_pct", left_pct), _check_pct("right_pct", right_pct)
        if self._closed:
            return False
        if held and self._restart_hold is not None:
            return self._restart_stop()
        self._last = MotorCommand(self._clock(), float(left), float(right), reason)
        ok = self._configured_transact(f"M {left} {right}", held=held)
        if held and self._restart_hold is not None:
            # EVT BOOT came before this drive's reply: the board, restarted, took it; the S
            # goes out next (before the lost watchdog setting) and the drive is unconfirmed
            return self._restart_stop()
        return ok

    def stop(self, reason: str = "") -> bool:
        """Stop both sides. Never raises; tries ``retries + 1`` times; True if confirmed.
        A confirmed stop ends a board restart's hold (:meth:`send`)."""
        return self._stop(reason or "stop", ends_hold=True)

    def _stop(self, reason: str, *, ends_hold: bool) -> bool:
        try:
            self._last = MotorCommand(self._clock(), 0.0, 0.0, reason)
            ok = self._transact_reply("S", ends_hold=ends_hold) is not None
            if ok and self._w_refusal is not None:
                self._configure_if_due()  # asked again with the motors stopped
        except Exception:  # stop must not raise, whatever the port does
            log.exception("motor stop failed")
            ok = False
        if not ok:
            self.counters.stop_failures += 1
        return ok

    def clear_restart_fault(self) -> None:
        """The operator stops or pauses (the daemon calls this; thread-safe): a latched
        restart fault (:data:`RESTART_LATCH_COUNT`) ends at the next stop the board confirms.
        Nothing else ends it. No effect without one; a fault latched later stays."""
        self._fault_cleared = self._restart_fault

    def _operator_cleared(self) -> bool:
        """No latched restart fault, or the operator cleared it (under ``_lock``)."""
        return self._restart_fault is None or self._restart_fault is self._fault_cleared

    def _restart_stop(self) -> bool:
        """A drive refused because the board restarted under the link: stop instead (the
        board restarts stopped, but it may have taken the drive just after) and say False.
        The hold stays until the caller's own stop."""
        self.counters.held_drives += 1
        self._stop("board restarted: drive held until the controller stops", ends_hold=False)
        return False

    def send(self, cmd: MotorCommand) -> bool:
        """Send a controller :class:`MotorCommand` (a stop command uses ``S``).

        After the board restarted under a running link (``EVT BOOT`` once a command was
        acknowledged: a brown-out; or a restart seen in an encoder reading, its
        ``EVT BOOT`` lost) the link is lost (:attr:`healthy` False, :attr:`health`
        disconnected, the restart its error) and every drive given here is refused
        (False; an ``S`` goes out instead, counted in ``counters.held_drives``) until a
        :meth:`stop` the board confirms: a keep-alive repeating the drive from before the
        restart, or one the controller decided before it was told, must not start the
        motors again. Input waiting on the port is read before a drive is written, so an
        ``EVT BOOT`` already received holds it back; one that arrives before the drive's
        reply (the board took the drive after restarting) stops the board at once. The
        :data:`RESTART_LATCH_COUNT`-th restart within :data:`RESTART_WINDOW_S` latches the
        hold: only a confirmed stop after :meth:`clear_restart_fault` ends it."""
        if cmd.is_stop:
            return self.stop(cmd.reason)
        return self._drive(cmd.left_pct, cmd.right_pct, cmd.reason, held=True)

    def ping(self) -> bool:
        """Keep-alive: feeds the board's watchdog without changing the drive."""
        return self._configured_transact("P")

    def query(self) -> tuple[int, int, int] | None:
        """The board's (left_pct, right_pct, watchdog_ms), or None without an answer."""
        reply = self._transact_reply("Q")
        if reply is None:
            return None
        try:
            left, right, wd = (int(x) for x in reply.split()[:3])
        except ValueError:
            return None
        return left, right, wd

    def read_odometry(self) -> WheelOdometry | None:
        """Latch and read the wheel-encoder counts (``E``), unwrapped (:class:`EncoderUnwrap`)
        and stamped (``t_s``) with the host time its answered request was written: the board
        latches on receipt, a fraction of a millisecond later, while the reply may be read
        tens of ms late (a host thread held up); stamped at the read, a late reply and the
        next one read at once gave the EKF 20-180 ms of counts over a 0.5 ms span (43-540
        m/s). None without a valid answer. Like every command it feeds the board's
        watchdog, so polling it is also a keep-alive.

        A board that refuses ``E`` (``ERR``: a firmware without encoders) answered, so the
        refusal does not count against the link's health; :attr:`odometry_supported` is
        then False (True after a valid reading, None before either)."""
        self._refusal = None
        reply = self._transact_reply("E", refusal_ok=True)
        if reply is None:
            if self._refusal is not None:
                self.odometry_supported = False
            return None
        # the board latched after the answered E was written (sent_s, the reading's stamp)
        # and at the latest when its reply was read (t_s): a host thread held up between
        # the reply and this line widens the interval EncoderUnwrap bounds, never shrinks it
        sent_s = self._write_s
        t_s = self._clock()
        parsed = parse_encoder_payload(reply)
        if parsed is None:
            log.warning("motor board sent a malformed encoder reply: %r", reply)
            return None
        self.odometry_supported = True
        seq = parsed[0]
        enc = self.encoders
        requests, self._latch_requests = self._latch_requests, 0
        left, right = enc.update(*parsed, t_s=t_s, sent_s=sent_s, requests=requests)
        what = f"latch {parsed[0]}, counts {parsed[1]} {parsed[2]}"
        if enc.verdict == "restart":
            # its EVT BOOT was lost, but the board forgot our settings all the same: handled
            # as an announced restart, except that this reading is already the new baseline
            self._board_lost_settings(
                "seen in the encoder reading",
                f"board restarted without EVT BOOT, seen in the encoder reading ({what}: the "
                f"latch number and counts began again from zero; {enc.detected} so far): its "
                f"settings were lost, odometry goes on from a new baseline; drives held until "
                f"the controller stops",
                t_s,
            )
        elif enc.verdict == "implausible":
            self._encoder_implausible(what, t_s)
        return WheelOdometry(sent_s, left, right, seq)

    def _encoder_implausible(self, what: str, t_s: float) -> None:
        """A reading that fits neither motion nor a restart (:class:`EncoderUnwrap`), ``what``
        its latch number and counts, at ``t_s`` (s): a new baseline, logged (the first,
        10th, 100th, every 1000th) and shown in :attr:`health` (degraded, this as the last
        error)."""
        enc = self.encoders
        n = enc.implausible
        why = (
            f"encoder reading fits neither motion (at most "
            f"{enc.max_counts_per_s:.0f} counts/s) nor a board restart ({what}): "
            f"taken as a new baseline ({n} so far)"
        )
        if n in (1, 10, 100) or n % 1000 == 0:
            log.warning("motors: %s", why)
        self._tracker.failed(why, t_s)

    def close(self) -> None:
        """Stop the motors, then close the port (idempotent, never raises)."""
        if self._closed:
            return
        self.stop("close")
        self._closed = True
        try:
            self.port.close()
        except Exception:
            log.debug("closing the motor port failed", exc_info=True)
        self._tracker.closed(self._clock())

    def __enter__(self) -> SerialMotorLink:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # --- transport --------------------------------------------------------------------------

    def _configured_transact(self, body: str, *, held: bool = False) -> bool:
        """``body`` after (re)sending the watchdog setting if the board lacks it: never
        confirmed, or the board restarted (then also right after ``body``). ``held``:
        not sent (False) once a board restart holds the link (:meth:`send`), and False with
        no ``W`` after it when the hold began during it (the caller's stop goes first)."""
        self._configure_if_due()
        if self._w_refusal is not None:
            return False  # never a drive on a watchdog the board refused to take
        if held and self._restart_hold is not None:
            return False
        ok = self._transact_reply(body, held=held) is not None
        if held and self._restart_hold is not None:
            # EVT BOOT before this drive's reply: the restarted board may drive it. The
            # caller's S must be the next line, not a W round trip first (a browning-out
            # board ran on and sagged again); W goes before the next drive
            return False
        if ok and not self.configured:
            self._configure()
        return ok

    def _transact(self, body: str) -> bool:
        return self._transact_reply(body) is not None

    def _transact_reply(
        self, body: str, refusal_ok: bool = False, *, held: bool = False, ends_hold: bool = False
    ) -> str | None:
        """Send ``body`` with a fresh sequence number; the OK payload, or None on failure.
        ``refusal_ok``: an ``ERR`` reply is an answer (kept in ``_refusal``), not a failure
        of the link. ``held``: read what waits on the port first, and send nothing (None)
        if a board restart holds the link. ``ends_hold``: its confirmation ends the hold."""
        if self._closed:
            return None
        tracker = self._tracker
        with self._lock:
            if self._port_dead and not self._reopen_port():
                self._failures = max(self._failures + 1, self.unhealthy_after)
                return None
            if held:
                self._read_waiting()
                if self._restart_hold is not None:
                    return None
            broken = False
            for attempt in range(self.retries + 1):
                self._seq = self._seq % (SEQ_MODULO - 1) + 1
                seq = self._seq
                if body == "E":  # each one the board takes latches (its latch number + 1)
                    self._latch_requests += 1
                try:
                    self._write_s = self._clock()  # an E's latch time (read_odometry)
                    self.port.write(f"{body} #{seq}\n".encode("ascii"))
                    self.counters.sent += 1
                    reply = self._await(seq)
                except Exception as exc:  # SerialException is an OSError; closed ports differ
                    self.counters.write_errors += 1
                    log.debug("motor link I/O error: %s", exc)
                    text = f"{body.split()[0]}: port error: {exc}"
                    t_err = self._clock()
                    gone = self._node_gone() if is_transient(root_oserror(exc)) else None
                    if gone is not None:
                        # unplugged: no retry, and the dead fd must not hold the tty minor
                        text += f" ({gone})"
                    elif is_transient(root_oserror(exc)):
                        self._transient_run += 1
                        if self._transient_t0 is None:
                            self._transient_t0 = t_err
                        lasted = t_err - self._transient_t0
                        if self._transient_run < self.transient_limit or lasted < TRANSIENT_MIN_S:
                            tracker.error(text, t_err)
                            continue
                        # EIO for ever: the device went away (a pty's far end, a USB adapter)
                        text += (
                            f" ({self._transient_run} transient errors in a row over "
                            f"{lasted:.2f} s)"
                        )
                    if self._reopens_since_break:
                        text += (
                            f"; the port reopened {self._reopens_since_break} times and still fails"
                        )
                    tracker.error(text, t_err)
                    broken = True  # EBADF, a closed port ...: repeating will not help
                    break
                self._transient_run = 0  # the port worked, whether or not the board answered
                self._transient_t0 = None
                if reply is None:
                    self.counters.timeouts += 1
                    tracker.error(
                        f"{body.split()[0]}: no acknowledgement within "
                        f"{self.ack_timeout_s * 1000:.0f} ms",
                        self._clock(),
                    )
                    continue
                ok, payload = reply
                if ok or refusal_ok:
                    if ok:
                        self.counters.acked += 1
                    else:  # refused, but the board answered: the link is good
                        self.counters.rejected += 1
                        self._refusal = payload
                    self._failures = 0
                    # the new port carried a command: the next break starts the backoff anew
                    self._reopen_backoff_s = self.reopen_initial_s
                    self._reopens_since_break = 0
                    t_s = self._clock()
                    # a latched restart fault ends only once the operator has cleared it;
                    # judged here, under the lock: a fault latched while this stop waited
                    # for the port (another thread's transaction) is not this stop's to end
                    if (
                        ends_hold
                        and ok
                        and self._restart_hold is not None
                        and self._operator_cleared()
                    ):
                        self._restart_hold = None
                        if self._restart_fault is not None:
                            self._restart_fault = self._fault_cleared = None
                            log.warning(
                                "motors: the restart fault cleared by a stop (%s); drives go again",
                                self._last.reason if self._last is not None else "stop",
                            )
                        else:
                            log.warning("motors: stopped after the board restart; drives go again")
                    if self._w_refusal is not None and not body.startswith("W "):
                        pass  # lost, with the refusal as the reason, until W is taken
                    elif self._restart_hold is None:  # held: lost until the caller's stop
                        if not tracker.health.connected:
                            tracker.opened(t_s)  # the board answers again: a reconnect
                        self._note_retries(attempt > 0, t_s)
                        tracker.good(t_s)
                    elif (
                        self._restart_fault is not None
                        and tracker.health.reason != self._restart_fault
                    ):
                        # the board answers, but the latched fault keeps the link lost: it is
                        # the reason status shows (not an older one's, a timeout's)
                        tracker.opened(t_s)
                        tracker.lost(self._restart_fault, t_s, count_error=False)
                    return payload if ok else None
                self.counters.rejected += 1
                self._refusal = payload
                kind = body.split()[0]
                self._refusals[kind] += 1
                n = self._refusals[kind]
                if n in REFUSAL_LOGGED or n % 1000 == 0:
                    log.warning(
                        "motor board rejected %r: %s (%d of its kind so far)", body, payload, n
                    )
                tracker.error(f"{kind}: board refused: {payload}", self._clock())
                break  # the board understood and refused: repeating will not help
            self._failures += 1
            if broken:
                self._failures = max(self._failures, self.unhealthy_after)
                if self._reopen is not None:
                    self._drop_port()
            self._track_failure()
            return None

    def _node_gone(self) -> str | None:
        """After a transient error (EIO): why the port's device node is no longer the one
        open (gone: a USB adapter unplugged, a pty closed; replaced: the path names another
        device now, a re-enumerated adapter under a ``/dev/serial/by-id`` name), or None
        while it is, or when the port has no path and descriptor to compare."""
        path = getattr(self.port, "port", None)
        fileno = getattr(self.port, "fileno", None)
        if not isinstance(path, str) or not path.startswith("/") or not callable(fileno):
            return None  # socket://, a port object without a node: EIO stays transient
        try:
            rdev = os.fstat(fileno()).st_rdev
        except Exception:
            return None
        try:
            now = os.stat(path).st_rdev
        except FileNotFoundError:
            return f"its device node {path} is gone: unplugged"
        except OSError:
            return None
        if now != rdev:
            return f"its device node {path} now names another device: replaced"
        return None

    def _drop_port(self) -> None:
        """Close the broken port; the next command after the backoff reopens it. What it has
        not sent yet is discarded first: those commands are stale (the board would act on
        them whenever a stalled line flowed again), and a USB serial port closes only once
        its output has drained, or after its closing_wait (30 s by default) under this lock."""
        self._port_dead = True
        self._next_reopen_t = self._clock() + self._reopen_backoff_s
        # doubled here too: a port that reopens fine but breaks again is not reopened at
        # the first step for ever (a command through on it resets the backoff)
        self._reopen_backoff_s = min(2.0 * self._reopen_backoff_s, self.reopen_max_s)
        discard = getattr(self.port, "reset_output_buffer", None)
        if callable(discard):
            try:
                discard()
            except Exception:  # a port that went away: nothing left to send anyway
                log.debug("discarding the broken motor port's output failed", exc_info=True)
        sock = getattr(self.port, "_socket", None)  # pyserial's socket:// port
        if isinstance(sock, socket.socket):
            # its reset_output_buffer does nothing and its close sends what is queued: a
            # zero linger resets the connection instead, and the queued drives die with it
            try:
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
            except OSError:
                log.debug("setting the motor socket's zero linger failed", exc_info=True)
        try:
            self.port.close()
        except Exception:
            log.debug("closing the broken motor port failed", exc_info=True)

    def _reopen_port(self) -> bool:
        """Try to open the port again if the backoff allows; True once it is open. The
        board may have restarted meanwhile: the watchdog setting is sent again."""
        t_s = self._clock()
        if t_s < self._next_reopen_t:
            return False
        assert self._reopen is not None
        try:
            port = self._reopen()
        except Exception as exc:
            self._next_reopen_t = t_s + self._reopen_backoff_s
            self._reopen_backoff_s = min(2.0 * self._reopen_backoff_s, self.reopen_max_s)
            self._tracker.open_failed(f"reopening the port failed: {exc}", t_s, self._next_reopen_t)
            return False
        self._set_port(port)
        self._port_dead = False
        # Not reset here: the transient run (a port that reopens but whose writes still fail
        # is broken again at its first error) and the backoff (it keeps growing until a
        # command succeeds on the new port).
        self.configured = False
        # a board on native USB restarts with its port: its counters began again at 0 and
        # its EVT BOOT went out before the port was open; a TCP link that dropped did not
        # restart the board: the next reading tells which (EncoderUnwrap.reopened)
        self.encoders.reopened()
        self.counters.reopens += 1
        self._reopens_since_break += 1
        if t_s - self._reopen_log_t >= REOPEN_LOG_S:
            self._reopen_log_t = t_s
            log.info(
                "motor port reopened (%d reopens since the break, %d in all)",
                self._reopens_since_break,
                self.counters.reopens,
            )
        return True

    def _note_retries(self, retried: bool, t_s: float) -> None:
        """An answered command that did (not) need a retry: over half of the last
        :data:`RETRY_WINDOW` needing one degrades the link, naming the rate; it recovers
        once they stop (no error for the tracker's recover time)."""
        self._retried.append(retried)
        n = sum(self._retried)
        if retried and n * 2 > RETRY_WINDOW and self._tracker.state == DeviceState.CONNECTED:
            self._tracker.failed(
                f"{n} of the last {len(self._retried)} commands needed a retry "
                f"(the board misses commands; each retry costs up to "
                f"{self.ack_timeout_s * 1000:.0f} ms)",
                t_s,
            )

    def _track_failure(self) -> None:
        """A command failed: degraded, lost once unhealthy, reconnecting while lost."""
        tracker, t_s = self._tracker, self._clock()
        state = tracker.health
        if self._failures < self.unhealthy_after:
            tracker.degrade(t_s)
        elif state.connected:
            next_t = self._next_reopen_t if self._port_dead else None
            tracker.lost(state.last_error, t_s, next_t, count_error=False)  # counted per attempt
        else:  # already lost: this command was another attempt to reach the board
            next_t = self._next_reopen_t if self._port_dead else None
            tracker.open_failed(state.last_error, t_s, next_t, count_error=False)

    def _board_restarted(self, how: str, t_s: float) -> None:
        """The board restarted under a running link at ``t_s`` (s), as ``how`` tells:
        counted within :data:`RESTART_WINDOW_S`; the :data:`RESTART_LATCH_COUNT`-th there
        latches a fault. The link is lost (``healthy`` False, send() refuses drives) until
        the operator clears it (:meth:`clear_restart_fault`: a stop or pause) and a stop the
        board confirms follows; said as an ERROR."""
        times = self._restarts
        times.append(t_s)
        while times and t_s - times[0] > RESTART_WINDOW_S:
            times.popleft()
        if len(times) < RESTART_LATCH_COUNT or self._restart_fault is not None:
            return
        why = (
            f"board restarted {len(times)} times in {t_s - times[0]:.1f} s (the last "
            f"{how}; a brown-out each time the motors draw current?): latched, the link "
            f"stays lost and drives are refused until the operator stops or pauses (x6wd "
            f"client stop / pause, the console)"
        )
        self.counters.restart_faults += 1
        log.error("motors: %s", why)
        self._restart_fault = why
        self._restart_hold = why
        self._failures = max(self._failures, self.unhealthy_after)
        if self._tracker.health.connected:
            self._tracker.lost(why, t_s)
        else:  # lost already (a timeout): the reason follows once the board answers
            self._tracker.error(why, t_s)

    def _board_lost_settings(self, how: str, why: str, t_s: float) -> None:
        """The board restarted under a running link at ``t_s`` (s), learnt as ``how`` (its
        ``EVT BOOT``, or the encoder reading when that was lost; ``why`` says so): it forgot
        our watchdog setting (``W`` goes out again before the next drive or ping), counted
        (``counters.board_restarts``, and once in the latch: :meth:`_board_restarted`),
        logged as a warning, and a lost link: :attr:`healthy` False and :meth:`send` refusing
        drives until a stop the board confirms. The encoder baseline is the caller's."""
        self.configured = False
        self.counters.board_restarts += 1
        self._board_restarted(how, t_s)
        log.warning("motors: %s", why)
        # a lost link, as a dropped one: the controller holds and stops; the drive from
        # before the restart is not sent again (send)
        self._restart_hold = why
        self._failures = max(self._failures, self.unhealthy_after)
        self._tracker.lost(why, t_s)

    def _board_event(self, payload: str) -> None:
        """An unsolicited ``EVT``. A watchdog stop, or a restart once the link was up, is
        a fault of the drive (the robot stopped, or lost its settings, without being told
        to): counted, logged as a warning and shown in :attr:`health` (degraded). The
        power-up ``BOOT`` before the first acknowledged command is the normal start."""
        self.counters.events += 1
        what = payload.split()[:1]
        t_s = self._clock()
        if what == ["BOOT"]:
            self.configured = False  # it forgot our watchdog setting
            self.encoders.rebase()  # and its counters start again at 0
            if self.counters.acked == 0:
                log.info("motor board powered up")
                return
            self._board_lost_settings(
                "EVT BOOT",
                "board restarted (EVT BOOT; a brown-out?): its settings and counters were "
                "lost; drives held until the controller stops",
                t_s,
            )
            return
        elif what == ["WATCHDOG"]:
            self.counters.watchdog_stops += 1
            why = "board watchdog stopped the motors (EVT WATCHDOG): commands came too late"
        else:
            log.info("motor board event: %s", payload)
            return
        log.warning("motors: %s", why)
        self._tracker.failed(why, t_s)

    def _await(self, seq: int) -> tuple[bool, str] | None:
        """Read lines until the reply for ``seq`` or the ack deadline."""
        deadline = self._clock() + self.ack_timeout_s
        while True:
            found = self._take_lines(seq)
            if found is not None:
                return found
            if self._clock() >= deadline:
                # the host may have been held up past the deadline with the reply already
                # in the kernel buffer: take what waits, without blocking, before giving up
                self._take_waiting()
                return self._take_lines(seq)
            waiting = getattr(self.port, "in_waiting", 0) or 0
            self._take_chunk(self.port.read(max(1, min(int(waiting), 256))))
            # a read that blocked for its first byte: the rest of the line came meanwhile
            self._take_waiting()

    def _take_waiting(self) -> None:
        """Read (without blocking) everything the port holds now (``in_waiting`` bytes)."""
        waiting = int(getattr(self.port, "in_waiting", 0) or 0)
        if waiting > 0:
            self._take_chunk(self.port.read(min(waiting, 4096)))

    def _take_lines(self, seq: int | None) -> tuple[bool, str] | None:
        """Handle the complete lines received: events acted on, the reply to ``seq``
        returned; replies to older, timed-out commands are dropped."""
        while b"\n" in self._rx:
            raw, _, rest = bytes(self._rx).partition(b"\n")
            self._rx = bytearray(rest)
            parsed = _parse_reply(raw.decode("ascii", "replace").strip())
            if parsed is None:
                continue
            kind, rseq, payload = parsed
            if kind == "EVT":
                self._board_event(payload)
            elif seq is not None and rseq == seq:
                return kind == "OK", payload
        return None

    def _take_chunk(self, chunk: bytes) -> None:
        if chunk:
            self._rx += chunk
            if len(self._rx) > 4096:  # a babbling line: keep only the tail
                del self._rx[:-MAX_LINE_BYTES]

    def _read_waiting(self) -> None:
        """Before a drive: read what the port holds already, without waiting, and act on its
        events (an ``EVT BOOT`` that came while the link was idle holds the drive back).
        A port that fails here fails the write that follows, where it is handled."""
        try:
            waiting = int(getattr(self.port, "in_waiting", 0) or 0)
            if waiting > 0:
                self._take_chunk(self.port.read(min(waiting, 4096)))
        except Exception:
            log.debug("reading the motor port's waiting input failed", exc_info=True)
        self._take_lines(None)


def _parse_reply(line: str) -> tuple[str, int | None, str] | None:
    """``OK #7 payload`` -> ("OK", 7, "payload"); EVT lines have no sequence."""
    if not line:
        return None
    kind, _, rest = line.partition(" ")
    if kind not in ("OK", "ERR", "EVT"):
        return None
    seq: int | None = None
    rest = rest.strip()
    if rest.startswith("#"):
        token, _, rest = rest.partition(" ")
        try:
            seq = int(token[1:])
        except ValueError:
            return None
    return kind, seq, rest.strip()


class LogMotorLink:
    """A motor backend that only logs and keeps the commands (``log://``).

    ``commands`` holds the last ``keep`` commands; ``on_command`` (e.g. a recorder's
    ``record_motor``) is called for each one.
    """

    def __init__(
        self,
        *,
        keep: int = 10_000,
        on_command: Callable[[MotorCommand], Any] | None = None,
        clock: Callable[[], float] = time.monotonic,
        logger: logging.Logger | None = None,
    ) -> None:
        self.commands: deque[MotorCommand] = deque(maxlen=keep)
        self.on_command = on_command
        self._clock = clock
        self._log = logger or log
        self._closed = False
        self._tracker = HealthTracker("motors", t_s=0.0)
        self._tracker.opened(0.0)  # nothing to lose but closing; no clock call (tests count)

    @property
    def healthy(self) -> bool:
        """True until closed."""
        return not self._closed

    @property
    def health(self) -> DeviceHealth:
        """Connected until closed."""
        return self._tracker.health

    def take_health_events(self) -> list[HealthEvent]:
        """Health transitions since the last call (only the initial connect)."""
        return self._tracker.take_events()

    @property
    def last_command(self) -> MotorCommand | None:
        """The last command given, or None."""
        return self.commands[-1] if self.commands else None

    def _keep(self, cmd: MotorCommand) -> bool:
        prev = self.commands[-1] if self.commands else None
        self.commands.append(cmd)
        # The controller repeats its command at the sample rate (20 Hz): a change is INFO, a
        # repeat DEBUG, or a robot left on log:// fills the journal with ~1.3 M lines a day.
        same = prev is not None and (prev.left_pct, prev.right_pct, prev.reason) == (
            cmd.left_pct, cmd.right_pct, cmd.reason
        )  # fmt: skip
        level = logging.DEBUG if same else logging.INFO
        self._log.log(level, "motors L%+.0f R%+.0f %s", cmd.left_pct, cmd.right_pct, cmd.reason)
        if self.on_command is not None:
            self.on_command(cmd)
        return not self._closed

    def drive(self, left_pct: float, right_pct: float, reason: str = "") -> bool:
        """Record a drive command (validated like the serial link); True unless closed."""
        left, right = _check_pct("left_pct", left_pct), _check_pct("right_pct", right_pct)
        return self._keep(MotorCommand(self._clock(), float(left), float(right), reason))

    def stop(self, reason: str = "") -> bool:
        """Record a stop; never raises."""
        try:
            return self._keep(MotorCommand(self._clock(), 0.0, 0.0, reason or "stop"))
        except Exception:
            self._log.exception("recording a stop failed")
            return False

    def send(self, cmd: MotorCommand) -> bool:
        """Record a controller command (its own ``t_s`` is kept)."""
        if cmd.is_stop:
            try:
                return self._keep(cmd)
            except Exception:
                self._log.exception("recording a stop failed")
                return False
        _check_pct("left_pct", cmd.left_pct)
        _check_pct("right_pct", cmd.right_pct)
        return self._keep(cmd)

    def close(self) -> None:
        """Stop, then refuse further commands (idempotent)."""
        if not self._closed:
            self.stop("close")
            self._closed = True
            # the time of the closing stop: no extra clock call (tests script the clock)
            self._tracker.closed(self.commands[-1].t_s if self.commands else 0.0)

    def __enter__(self) -> LogMotorLink:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


# --- board side -----------------------------------------------------------------------------


class MotorBoard:
    """The motor board's protocol engine, sans-IO (docs/motors.md).

    ``feed(data, t_s)`` takes received bytes at time ``t_s`` (s, any monotonic clock) and
    returns the reply bytes. ``tick(t_s)`` only advances time (watchdog). ``left_pct`` /
    ``right_pct`` are the drive the board applies now. ``left_counts`` / ``right_counts``
    are the wheel-encoder counters as the hardware keeps them (modulo 2**32), moved by
    :meth:`add_counts`; ``E`` latches and reports them.
    """

    def __init__(self, *, watchdog_ms: int = DEFAULT_WATCHDOG_MS) -> None:
        if not WATCHDOG_MIN_MS <= watchdog_ms <= WATCHDOG_MAX_MS:
            raise ValueError(
                f"watchdog_ms must be {WATCHDOG_MIN_MS}..{WATCHDOG_MAX_MS}, got {watchdog_ms!r}"
            )
        self.watchdog_ms = int(watchdog_ms)
        self.default_watchdog_ms = int(watchdog_ms)  # what the firmware starts with
        self.left_pct = 0
        self.right_pct = 0
        self.watchdog_trips = 0
        self.commands = 0  # valid commands executed
        self.errors = 0  # ERR replies sent
        self.left_counts = 0
        self.right_counts = 0
        self.enc_seq = 0  # number of the last latch (E), modulo 2**16
        self._buf = bytearray()
        self._overflow = False
        self._last_cmd_t_s: float | None = None

    def boot(self) -> bytes:
        """Power-up: stopped, default watchdog, input cleared, encoder counters and latch
        number at 0; returns ``EVT BOOT``."""
        self.left_pct = self.right_pct = 0
        self.left_counts = self.right_counts = self.enc_seq = 0
        self.watchdog_ms = self.default_watchdog_ms
        self._buf.clear()
        self._overflow = False
        self._last_cmd_t_s = None
        return b"EVT BOOT\n"

    def add_counts(self, left: int, right: int) -> None:
        """The wheels turned: add signed encoder counts per side (the hardware's quadrature
        counters; they wrap modulo 2**32 as a 32-bit timer register does)."""
        self.left_counts = (self.left_counts + int(left)) % ENC_MODULO
        self.right_counts = (self.right_counts + int(right)) % ENC_MODULO

    @property
    def running(self) -> bool:
        """True while either side is driven."""
        return self.left_pct != 0 or self.right_pct != 0

    def tick(self, t_s: float) -> bytes:
        """Advance time to ``t_s``; stop and report ``EVT WATCHDOG`` if it expired."""
        if (
            self.running
            and self._last_cmd_t_s is not None
            and t_s - self._last_cmd_t_s >= self.watchdog_ms / 1000.0 - 1e-9  # float slack
        ):
            self.left_pct = self.right_pct = 0
            self.watchdog_trips += 1
            return b"EVT WATCHDOG\n"
        return b""

    def feed(self, data: bytes, t_s: float) -> bytes:
        """Process received bytes at ``t_s``; return the replies (possibly empty)."""
        out = bytearray(self.tick(t_s))
        self._buf += data
        while True:
            i = self._buf.find(b"\n")
            if i < 0:
                break
            line = bytes(self._buf[:i])
            del self._buf[: i + 1]
            if self._overflow or len(line) > MAX_LINE_BYTES:
                # too long, whether it arrived in one read or was cut short across several
                self._overflow = False
                self.errors += 1
                out += b"ERR overflow\n"
                continue
            out += self._line(line.decode("ascii", "replace").strip(), t_s)
        if len(self._buf) > MAX_LINE_BYTES:
            # discard the rest of this line; answer ERR at its end
            self._buf.clear()
            self._overflow = True
        return bytes(out)

    def _err(self, seq: str, reason: str) -> bytes:
        self.errors += 1
        return f"ERR{seq} {reason}\n".encode("ascii")

    def _line(self, line: str, t_s: float) -> bytes:
        if not line:
            return b""
        tokens = line.split()
        seq = ""
        if tokens[-1].startswith("#"):
            digits = tokens.pop()[1:]
            if not digits.isdigit() or len(digits) > 5:
                return self._err("", "syntax")
            seq = f" #{int(digits)}"
            if not tokens:
                return self._err(seq, "syntax")
        cmd, args = tokens[0].upper(), tokens[1:]
        try:
            values = [int(a, 10) for a in args]
        except ValueError:
            return self._err(seq, "syntax")
        payload = ""
        if cmd == "M":
            if len(values) != 2:
                return self._err(seq, "syntax")
            if any(abs(v) > MAX_PCT for v in values):
                return self._err(seq, "range")
            self.left_pct, self.right_pct = values
        elif cmd == "S":
            if values:
                return self._err(seq, "syntax")
            self.left_pct = self.right_pct = 0
        elif cmd == "P":
            if values:
                return self._err(seq, "syntax")
        elif cmd == "W":
            if len(values) != 1:
                return self._err(seq, "syntax")
            if not WATCHDOG_MIN_MS <= values[0] <= WATCHDOG_MAX_MS:
                return self._err(seq, "range")
            self.watchdog_ms = values[0]
        elif cmd == "Q":
            if values:
                return self._err(seq, "syntax")
            payload = f" {self.left_pct} {self.right_pct} {self.watchdog_ms}"
        elif cmd == "E":
            if values:
                return self._err(seq, "syntax")
            self.enc_seq = (self.enc_seq + 1) % ENC_SEQ_MODULO
            payload = f" {self.enc_seq} {self.left_counts} {self.right_counts}"
        else:
            return self._err(seq, "unknown")
        self.commands += 1
        self._last_cmd_t_s = t_s
        return f"OK{seq}{payload}\n".encode("ascii")


def serve_board_fd(
    fd: int,
    board: MotorBoard,
    stop: threading.Event,
    *,
    clock: Callable[[], float] = time.monotonic,
    poll_s: float = 0.005,
    lock: threading.Lock | None = None,
    boot: bool = False,
) -> None:
    """Run ``board`` on a file descriptor (e.g. a pty master) until ``stop`` is set.

    Reads what arrives, feeds it with the time from ``clock``, writes the replies back, and
    ticks the watchdog every ``poll_s`` seconds. ``lock`` (if given) is held while the board
    changes so another thread can read its state consistently. Returns on EOF or when the
    far end goes away (EIO on a pty master whose slave was closed). With ``boot`` the board
    first powers up (:meth:`MotorBoard.boot`) and announces it, as real firmware does.
    """
    guard = lock or threading.Lock()
    if boot:
        with guard:
            hello = board.boot()
        try:
            os.write(fd, hello)
        except OSError:
            return
    while not stop.is_set():
        ready, _, _ = select.select([fd], [], [], poll_s)
        data = b""
        if ready:
            try:
                data = os.read(fd, 4096)
            except OSError:
                return
            if not data:
                return
        with guard:
            reply = board.feed(data, clock()) if data else board.tick(clock())
        if reply:
            try:
                os.write(fd, reply)
            except OSError:
                return
