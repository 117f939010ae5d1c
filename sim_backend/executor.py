"""The one executor for many simulations: Dask's distributed scheduler, or this process.

x6wd's tools run their batches of independent simulations through :class:`Executor`:
``x6wd sweep`` (:mod:`sim_backend.sweep`), the mission benchmark (``bench/bench_mission.py``)
and the gap tool's baseline seeds (``x6wd gap --seeds M``); the gap benchmarks
(``bench/bench_gap*.py``) use a ProcessPoolExecutor of their own. It
has three backends, chosen when it is made:

- ``Executor(workers=N)``: a Dask ``LocalCluster`` of N worker processes on this machine
  (one thread each: a mission is pure Python and holds the GIL), started on ``__enter__`` and
  shut down on ``__exit__``; N defaults to ``os.cpu_count()``;
- ``Executor(scheduler="tcp://host:8786")``: an existing Dask cluster (``dask scheduler`` and
  any number of ``dask worker`` processes on any machines that have x6wd installed);
  ``workers=N`` then waits until N workers have joined;
- ``Executor(inline=True)``: in this process, one task after another, without Dask (the
  default of the gap tool, a benchmark's ``--jobs 1``, and machines without the ``sweep``
  extra).

:meth:`Executor.map_unordered` submits ``fn(*args)`` for every argument tuple and yields an
:class:`Outcome` per task as it finishes (in completion order). A task whose ``fn`` raises is
an outcome with ``error`` (kind ``"task"``); a task the cluster could not finish (its worker
died more often than Dask's ``distributed.scheduler.allowed-failures``, or the cluster went
away) is an outcome with kind ``"executor"``. A worker that dies once costs nothing but time:
the scheduler runs its tasks again on the workers that are left, and the finished results it
held that were not collected yet (Dask marks them "lost": they are waited for, not lost).

A cluster with no worker at all waits for one, but not for ever: when no worker has been
connected for ``worker_timeout_s`` (default :data:`WORKER_TIMEOUT_S`, 60 s) in a row, every
task not finished is an outcome of kind ``"executor"`` saying so (a scheduler no worker
joined, workers that closed on their first task because they cannot import x6wd, the last
worker killed). A worker that comes back within that time resets the clock: the tasks go on.
Meanwhile ``map_unordered(..., waiting=...)`` is told how long it has waited (a progress bar
says so: :meth:`TextProgress.waiting`), instead of seeming hung.
The same time bounds the wait for ``workers=N`` workers to join an existing scheduler.

A LocalCluster's workers ignore SIGINT (a Ctrl-C at the terminal reaches the whole process
group: only this process acts on it) and log nothing once they are closing
(:data:`WORKER_PRELOAD`); a Ctrl-C during a call into the client is raised when the call
returns (:func:`_sigint_deferred`).

A LocalCluster opens no dashboard (Dask's default is one on port 8787, which a second sweep
on the same machine then finds taken) unless ``dashboard="HOST:PORT"`` asks for one.

Dask is imported only here and only when a cluster backend is entered, so the daemon and
``x6wd sim`` never import it, and the package works without the optional ``sweep`` extra.
"""

from __future__ import annotations

import contextlib
import logging
import math
import os
import shutil
import signal
import socket
import sys
import threading
import time
import traceback
import uuid
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from multiprocessing import resource_tracker
from pathlib import Path
from types import TracebackType
from typing import Any, TextIO
from urllib.parse import urlsplit

from x6wd.core.errors import ConfigError

INSTALL_HINT = "pip install 'x6wd[sweep]' (dask[distributed])"

WORKER_TIMEOUT_S = 60.0
"""How long (s) :class:`Executor` waits with no worker connected before it gives up the tasks
not finished (and how long it waits for ``workers=N`` to join an existing scheduler)."""
WORKER_POLL_S = 1.0
"""How often (s) the worker count is asked for while no task result is ready."""
WAITING_EVERY_S = 5.0
"""How often (s) :meth:`TextProgress.waiting` writes a line when not on a terminal (a log)."""
CLEAR_TO_EOL = "\x1b[K"
"""The ANSI (ECMA-48) erase-to-end-of-line a progress line on a terminal ends with."""


@dataclass
class Outcome:
    """What became of one task: ``index`` into the submitted list, its ``value``, or its
    ``error`` (one line: type, message and where) with ``kind`` "task" (the function
    raised, or its workers died running it: KilledWorker) or "executor" (the cluster could
    not run it)."""

    index: int
    value: Any = None
    error: str | None = None
    kind: str = "ok"

    @property
    def ok(self) -> bool:
        return self.error is None


def describe_exception(exc: BaseException, tb: Any = None) -> str:
    """``Type: message at file.py:line`` (the innermost frame)."""
    frames = traceback.extract_tb(tb if tb is not None else exc.__traceback__)[-1:]
    where = f" at {Path(frames[0].filename).name}:{frames[0].lineno}" if frames else ""
    msg = str(exc).strip().splitlines()
    return f"{type(exc).__name__}: {msg[0] if msg else ''}{where}"


def dask_available() -> bool:
    """True when ``distributed`` can be imported (the ``sweep`` extra is installed)."""
    try:
        import distributed  # noqa: F401
    except ImportError:
        return False
    return True


WORKER_PRELOAD = """
import logging
import signal

signal.signal(signal.SIGINT, signal.SIG_IGN)


def dask_setup(worker):
    closing = ("closing", "closing_gracefully", "closed", "failed")

    def going(record):
        return getattr(worker.status, "name", "") not in closing

    for handler in logging.getLogger("distributed").handlers:
        handler.addFilter(going)
"""
"""A LocalCluster worker's preload. A Ctrl-C at the terminal reaches the whole process group,
and only this process should act on it (it stops the cluster): the worker ignores it
(otherwise every worker printed a KeyboardInterrupt traceback on its way down). And what the
worker logs once it is closing is left out: a heartbeat in flight when the cluster shuts it
down fails ("distributed.worker - ERROR - Failed to communicate with scheduler during
heartbeat", a CommClosedError traceback of 25 lines per worker), at the end of every sweep
whose scheduler answers slowly (a loaded machine) and after most Ctrl-Cs there."""


def _drop_reconnect_failure(record: logging.LogRecord) -> bool:
    return not str(record.msg).startswith("Failed to reconnect to scheduler")


def _quiet_reconnect_failure() -> None:
    """The client's "Failed to reconnect to scheduler after 30.00 seconds, closing client"
    ERROR is left out: the runs it cancels are reported as lost, naming the scheduler that
    went away (:meth:`Executor._gone`)."""
    logger = logging.getLogger("distributed.client")
    if _drop_reconnect_failure not in logger.filters:
        logger.addFilter(_drop_reconnect_failure)


@contextlib.contextmanager
def _sigint_held() -> Iterator[None]:
    """A Ctrl-C while a LocalCluster starts is held and raised once it is up, when the caller
    can shut it down (ignored, as before, it was dropped and the sweep ran on to exit 0)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    # multiprocessing's resource tracker starts with the first spawned process, and its
    # start unblocks SIGINT in the spawning thread afterwards: the workers spawned next then
    # died of a Ctrl-C in their site import. Started here, before the block, it cannot.
    resource_tracker.ensure_running()
    held: list[int] = []
    old = signal.signal(signal.SIGINT, lambda signum, _frame: held.append(signum))
    # Blocked, not only handled: the threads and worker processes started meanwhile inherit
    # the mask (across exec too), so a Ctrl-C sent to the whole group while a worker's
    # interpreter starts stays pending there until its preload ignores it; before, it killed
    # that worker in its site import ("Fatal Python error ... KeyboardInterrupt")
    signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})  # a held one lands now
        signal.signal(signal.SIGINT, old)
        if held:  # also when the start failed: the user asked to stop
            raise KeyboardInterrupt


@contextlib.contextmanager
def _sigint_deferred() -> Iterator[None]:
    """A Ctrl-C during a call into Dask's client raised when the call returns (a second one at
    once: a call that hangs can still be stopped). A client call waits for its event loop's
    thread (``distributed.utils.sync``), and a KeyboardInterrupt raised in that wait has the
    loop cancel the call: when the call had not begun there yet, the cancellation failed on
    the loop's thread with "NameError: cannot access free variable 'future'" and a traceback
    on stderr (the client polls the worker count every second, so a Ctrl-C on a loaded
    machine met one now and then). Only in the main thread, and only over Python's own
    handler (a caller's handler is left alone)."""
    if (
        threading.current_thread() is not threading.main_thread()
        or signal.getsignal(signal.SIGINT) is not signal.default_int_handler
    ):
        yield
        return
    held: list[int] = []

    def hold(signum: int, _frame: Any) -> None:
        if held:
            raise KeyboardInterrupt
        held.append(signum)

    signal.signal(signal.SIGINT, hold)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, signal.default_int_handler)
        if held:
            raise KeyboardInterrupt


def probe_scheduler(address: str, timeout_s: float) -> None:
    """Raise :class:`ConfigError` naming ``address`` unless a Dask scheduler answers there
    within ``timeout_s`` (s). ``Client`` alone raises a bare ValueError for a malformed
    address and a ``socket.gaierror`` for a host no resolver knows, waits with no limit in
    its handshake with a peer that never speaks (an HTTP server, the dashboard's port), and
    tries to allocate exabytes for one that speaks something else."""
    import asyncio

    try:
        from distributed.comm import connect
        from distributed.comm.addressing import resolve_address
    except ImportError as exc:
        raise ConfigError(f"a Dask cluster needs {INSTALL_HINT}: {exc}") from exc

    scheme, sep, rest = address.partition("://")
    if sep and scheme.lower() not in ("tcp", "tls"):  # ucx://, inproc:// ...: not a cluster's
        raise ConfigError(
            f"scheduler {address}: protocol {scheme!r} not supported (expected tcp://HOST:PORT"
            " or tls://HOST:PORT)"
        )
    try:
        port = urlsplit(f"//{rest if sep else address}").port
    except ValueError as exc:  # a port out of 0..65535, or not a number
        raise ConfigError(
            f"scheduler {address}: not an address of the form tcp://HOST:PORT ({exc})"
        ) from None
    if port == 0:
        raise ConfigError(f"scheduler {address}: port 0 (expected tcp://HOST:PORT)")
    try:
        resolved = resolve_address(address)
    except ValueError as exc:  # Dask's own words follow ours
        raise ConfigError(
            f"scheduler {address}: not an address of the form tcp://HOST:PORT ({exc})"
        ) from None
    except OSError as exc:  # socket.gaierror: an unknown host name, or 256.1.1.1
        raise ConfigError(
            f"scheduler {address}: cannot resolve its host: {exc.strerror or exc}"
        ) from None
    except Exception as exc:  # whatever else distributed's parser meets: a clear refusal
        raise ConfigError(f"scheduler {address}: {exc} (expected tcp://HOST:PORT)") from None

    handshake_s = timeout_s  # what is left of it after a TCP connect
    if resolved.startswith("tcp://"):
        # Dask's connect retries a refused connection until the timeout ends and then says
        # only "TimeoutError": a plain TCP connect says "refused" at once (tls://, ws:// ...
        # are left to Dask: their handshake is not a plain socket's)
        t0 = time.monotonic()
        _tcp_reachable(address, resolved, timeout_s)
        handshake_s = max(1.0, timeout_s - (time.monotonic() - t0))

    async def identity() -> Any:
        comm = await connect(resolved, timeout=handshake_s)
        try:
            await comm.write({"op": "identity"})
            return await comm.read()
        finally:
            comm.abort()

    try:
        reply = asyncio.run(asyncio.wait_for(identity(), handshake_s))
    except Exception as exc:  # OSError, a timeout, garbage framing (MemoryError) ...
        why = str(exc) or f"{type(exc).__name__} (no Dask reply: is it a scheduler's port?)"
        raise ConfigError(
            f"cannot reach a Dask scheduler at {address} within {timeout_s:g} s: {why}"
        ) from None
    if not (isinstance(reply, dict) and reply.get("type") == "Scheduler"):
        raise ConfigError(f"{address} answered, but not as a Dask scheduler: {reply!r:.200}")


def _tcp_reachable(address: str, resolved: str, timeout_s: float) -> None:
    """Raise :class:`ConfigError` naming ``address`` and why, unless a plain TCP connect to
    ``resolved`` (tcp://HOST:PORT) succeeds within ``timeout_s`` (s)."""
    from distributed.comm.addressing import get_address_host_port

    host, port = get_address_host_port(resolved)
    where = f"{host}:{port}" if ":" not in host else f"[{host}]:{port}"
    try:
        socket.create_connection((host, port), timeout=timeout_s).close()
    except ConnectionRefusedError:
        raise ConfigError(
            f"cannot reach a Dask scheduler at {address}: connection refused by {where}"
            " (nothing listens on that port: is the scheduler started, on that port?)"
        ) from None
    except TimeoutError:
        raise ConfigError(
            f"cannot reach a Dask scheduler at {address} within {timeout_s:g} s: {where} did"
            " not answer a TCP connect (a host that is down, or a firewall that drops it)"
        ) from None
    except OSError as exc:  # no route to host, network unreachable ...
        raise ConfigError(
            f"cannot reach a Dask scheduler at {address}: {where}: {exc.strerror or exc}"
        ) from None


class Executor:
    """Runs independent tasks on a Dask cluster (local or remote) or in this process; use it
    as a context manager. See the module docstring."""

    def __init__(
        self,
        scheduler: str | None = None,
        workers: int | None = None,
        *,
        inline: bool = False,
        connect_timeout_s: float = 30.0,
        worker_timeout_s: float | None = None,
        dashboard: str | None = None,
    ) -> None:
        if workers is not None and workers < 1:
            raise ConfigError(f"workers: must be >= 1, got {workers}")
        if worker_timeout_s is None:
            worker_timeout_s = WORKER_TIMEOUT_S
        if not (worker_timeout_s > 0 and math.isfinite(worker_timeout_s)):
            raise ConfigError(
                f"worker timeout: expected a positive number of seconds, got {worker_timeout_s!r}"
            )
        if dashboard is not None and (scheduler or inline):
            raise ConfigError(
                "dashboard: only a LocalCluster started here has one to open (an existing"
                " scheduler has its own: dask scheduler --dashboard-address)"
            )
        if scheduler is not None and not scheduler.strip():  # an unset $DASK_SCHEDULER
            raise ConfigError(
                f"scheduler: empty address {scheduler!r} (expected tcp://HOST:PORT; omit it for"
                " a LocalCluster)"
            )
        if inline and scheduler:
            raise ConfigError("an in-process executor has no scheduler")
        self.scheduler = scheduler
        self.workers = workers
        self.inline = inline
        self.connect_timeout_s = connect_timeout_s
        self.worker_timeout_s = float(worker_timeout_s)
        self.dashboard = dashboard
        self._cluster: Any = None
        self._client: Any = None
        self._peak_workers = 0  # the most seen at once: those the tasks ran on

    # -- life cycle ------------------------------------------------------------------------
    def __enter__(self) -> Executor:
        if self.inline:
            return self
        try:
            with _sigint_held():  # Python drops a KeyboardInterrupt raised in an import's lock
                from distributed import Client, LocalCluster
        except ImportError as exc:
            raise ConfigError(f"a Dask cluster needs {INSTALL_HINT}: {exc}") from exc
        if self.scheduler:
            probe_scheduler(self.scheduler, self.connect_timeout_s)
        _quiet_reconnect_failure()
        try:
            if self.scheduler:
                self._client = Client(self.scheduler, timeout=self.connect_timeout_s)
                if self.workers:
                    self._wait_for_workers(self.workers)
            else:
                n = self.workers or os.cpu_count() or 1
                with _sigint_held():
                    self._cluster = LocalCluster(
                        n_workers=n,
                        threads_per_worker=1,
                        processes=True,
                        # dashboard_address=None only leaves out the dashboard's pages: the
                        # scheduler's HTTP server still took 8787 (or warned it was taken)
                        dashboard_address=self.dashboard,
                        scheduler_kwargs=(
                            {} if self.dashboard else {"dashboard_address": "127.0.0.1:0"}
                        ),
                        silence_logs=logging.ERROR,
                        preload=[WORKER_PRELOAD],
                    )
                self._client = Client(self._cluster)
        except ConfigError:
            self.close()
            raise
        except (OSError, TimeoutError) as exc:
            self.close()
            where = self.scheduler or "a LocalCluster"
            raise ConfigError(f"cannot reach {where}: {exc}") from exc
        except BaseException:  # a Ctrl-C held while the cluster started: no 'with' to close it
            self.close()
            raise
        self._peak_workers = self.worker_count()
        return self

    def _wait_for_workers(self, n: int) -> None:
        """Wait until ``n`` workers have joined the scheduler (at most ``worker_timeout_s``);
        the scheduler was reached, so a timeout says how many came, not "cannot reach"."""
        try:
            self._client.wait_for_workers(n, timeout=self.worker_timeout_s)
        except TimeoutError:
            have = self.worker_count()
            raise ConfigError(
                f"scheduler {self.scheduler} answered, but only {have} of the {n} workers asked"
                f" for (--workers {n}) joined within {self.worker_timeout_s:g} s: start more"
                f" (dask worker {self.scheduler}), or ask for fewer"
            ) from None

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    def close(self) -> None:
        """Disconnect; a LocalCluster this executor started is shut down."""
        client, cluster = self._client, self._cluster
        self._client = self._cluster = None
        # Interrupted or not, the cluster's own shutdown messages are noise here.
        logging.getLogger("distributed").setLevel(logging.CRITICAL)
        try:
            if client is not None:
                client.close()
        finally:
            if cluster is not None:
                cluster.close()

    # -- facts -----------------------------------------------------------------------------
    @property
    def description(self) -> str:
        """What runs the tasks, for reports: "in this process", "LocalCluster, 2 workers",
        "scheduler tcp://..., 1 worker"; the most workers seen at once (those the tasks ran
        on), and "(1 at the end)" when fewer are left."""
        if self.inline:
            return "in this process"
        n = self.worker_count()
        peak = max(n, self._peak_workers)
        workers = f"{peak} worker{'' if peak == 1 else 's'}" + (
            f" ({n} at the end)" if n < peak else ""
        )
        if self.scheduler:
            return f"scheduler {self.scheduler}, {workers}"
        return f"LocalCluster, {workers}"

    def worker_count(self) -> int:
        """Workers connected now (1 in this process)."""
        if self.inline or self._client is None:
            return 1
        with _sigint_deferred():  # the count, not every worker's facts
            info = self._client.scheduler_info(n_workers=0)
        n = info.get("n_workers")
        return int(n) if isinstance(n, int) else len(info.get("workers", {}))

    def _no_worker_message(self) -> str:
        where = f"the scheduler {self.scheduler}" if self.scheduler else "the LocalCluster"
        return (
            f"no Dask worker connected to {where} for {self.worker_timeout_s:g} s: none joined,"
            " or every worker left or died (a worker that cannot import x6wd's sim_backend"
            " closes on its first task: see the workers' logs); start workers, then run the"
            " same command again"
        )

    # -- running ---------------------------------------------------------------------------
    def map_unordered(
        self,
        fn: Callable[..., Any],
        args_list: Sequence[tuple[Any, ...]],
        names: Sequence[str] | None = None,
        reraise: bool = False,
        waiting: Callable[[float, float], None] | None = None,
    ) -> Iterator[Outcome]:
        """``fn(*args)`` for each tuple of ``args_list``; yields an :class:`Outcome` per task
        as it finishes. ``names`` (one per task) label the tasks on the cluster's dashboard.
        ``reraise``: a task whose ``fn`` raised raises its exception here instead of
        yielding an error outcome. ``waiting(waited_s, timeout_s)`` is called about every
        :data:`WORKER_POLL_S` while no worker is connected (s without one, s until the tasks
        left are given up): a progress bar otherwise sits still as if hung. Stopping the
        iteration early (or an exception, Ctrl-C) cancels the tasks not yet finished."""
        if self.inline:
            yield from self._inline(fn, args_list, reraise)
            return
        if self._client is None:
            raise RuntimeError("Executor used outside its 'with' block")
        from distributed import as_completed

        tag = uuid.uuid4().hex[:8]
        label = getattr(fn, "__name__", "task")
        futures = []
        for i, args in enumerate(args_list):
            name = names[i] if names is not None else str(i)
            key = f"x6wd-{label}-{name}-{tag}"
            futures.append(self._client.submit(fn, *args, key=key, pure=False))
        index = {f.key: i for i, f in enumerate(futures)}
        pending = set(index)
        try:
            done = as_completed(futures)
            watch = _WorkerWatch(self.worker_count, self.worker_timeout_s)
            said = watch.asked  # the poll last told to ``waiting``
            while not done.is_empty():
                if not done.has_ready():
                    gone = watch.gone()
                    if waiting and watch.waited_s is not None and (gone or watch.asked != said):
                        said = watch.asked  # one call per poll of the worker count
                        waiting(self.worker_timeout_s if gone else watch.waited_s, watch.timeout_s)
                    if gone:  # no worker for the whole timeout: give the rest up
                        left = sorted(pending, key=index.__getitem__)
                        with _sigint_deferred():
                            self._client.cancel([futures[index[k]] for k in left])
                        pending.clear()
                        message = self._no_worker_message()
                        for k in left:
                            yield Outcome(index[k], error=message, kind="executor")
                        return
                    time.sleep(0.02)
                    continue
                fut = next(done)
                i = index[fut.key]
                outcome = self._outcome(i, fut, self._gone())
                if outcome.kind == "executor" and fut.status == "lost":
                    done.add(fut)  # finished, then its worker died: the scheduler runs it again
                    continue
                pending.discard(fut.key)
                self._peak_workers = max(self._peak_workers, self.worker_count())
                if reraise and outcome.kind == "task":
                    with _sigint_deferred():
                        fut.result()  # raises the task's own exception
                yield outcome
                fut.release()
        finally:
            if pending:
                with _sigint_deferred():
                    self._client.cancel([f for f in futures if f.key in pending])

    def _gone(self) -> str | None:
        """Why the tasks left were cancelled when the client lost its scheduler (it cancels
        every future at once, tries to reconnect for ``connect_timeout_s``, then closes), else
        None."""
        client = self._client
        status = getattr(client, "status", "running")
        if client is None or status not in ("connecting", "closing", "closed"):
            return None
        where = self.scheduler or "of the LocalCluster"
        return f"the connection to the scheduler {where} was lost (is it still running?)"

    @staticmethod
    def _outcome(i: int, fut: Any, gone: str | None = None) -> Outcome:
        with _sigint_deferred():  # it asks the scheduler (the result, the error)
            return Executor._outcome_of(i, fut, gone)

    @staticmethod
    def _outcome_of(i: int, fut: Any, gone: str | None = None) -> Outcome:
        if fut.status == "finished":
            try:
                return Outcome(i, value=fut.result())
            except Exception as exc:  # lost between "finished" and the transfer
                return Outcome(i, error=describe_exception(exc), kind="executor")
        if fut.status == "error":
            from distributed import KilledWorker

            err = fut.exception()
            if isinstance(err, KilledWorker):
                # the scheduler gives a task up after its workers died running it more than
                # distributed.scheduler.allowed-failures times: the task's doing (out of memory,
                # a crash in native code), so a failure with its error, not a loss that the
                # same command runs again to kill as many workers (an outside audit)
                return Outcome(
                    i,
                    error=f"KilledWorker: {err} (the worker died each time it ran this task:"
                    " out of memory, or a crash in native code?)",
                    kind="task",
                )
            return Outcome(i, error=describe_exception(err, fut.traceback()), kind="task")
        # "cancelled": the scheduler went away (the client gave up reconnecting)
        return Outcome(i, error=gone or f"task {fut.status} by the cluster", kind="executor")

    @staticmethod
    def _inline(
        fn: Callable[..., Any], args_list: Sequence[tuple[Any, ...]], reraise: bool
    ) -> Iterator[Outcome]:
        for i, args in enumerate(args_list):
            try:
                value = fn(*args)
            except Exception as exc:
                if reraise:
                    raise
                yield Outcome(i, error=describe_exception(exc), kind="task")
            else:
                yield Outcome(i, value=value)


class _WorkerWatch:
    """Whether a cluster has had no worker for ``timeout_s`` in a row; ``count()`` (a call to
    the scheduler) is asked at most every :data:`WORKER_POLL_S`."""

    def __init__(self, count: Callable[[], int], timeout_s: float) -> None:
        self.count = count
        self.timeout_s = timeout_s
        self.asked = -math.inf  # when count() was last asked (time.monotonic, s)
        self._none_since: float | None = None

    @property
    def waited_s(self) -> float | None:
        """Seconds without a worker, as of the last ask (None while one is connected)."""
        return None if self._none_since is None else self.asked - self._none_since

    def gone(self) -> bool:
        now = time.monotonic()
        if now - self.asked >= WORKER_POLL_S:
            self.asked = now
            try:
                n = self.count()
            except Exception:  # the scheduler went away: the futures say so in their time
                n = 1
            if n > 0:
                self._none_since = None
            elif self._none_since is None:
                self._none_since = now
        return self._none_since is not None and now - self._none_since >= self.timeout_s


class TextProgress:
    """A plain-text progress bar on ``stream`` (stderr): redrawn in place on a terminal,
    otherwise a line at most every ``every_s`` seconds and at the end. Call it with the count
    done so far (of ``total``), of them the failed and the lost ones (tasks the cluster could
    not finish); the first call's count is what was done before this process ran anything (a
    resumed sweep's runs found done): the rate and the ETA are of the tasks run since then,
    from that call on, lost ones not counted."""

    def __init__(
        self,
        total: int,
        label: str = "runs",
        stream: TextIO | None = None,
        every_s: float = 10.0,
        width: int = 30,
    ) -> None:
        self.total = total
        self.label = label
        self.stream = stream if stream is not None else sys.stderr
        self.tty = bool(getattr(self.stream, "isatty", lambda: False)())
        self.every_s = every_s
        self.width = width
        self.t0 = time.monotonic()
        self._last = -math.inf
        self._start: tuple[int, float] | None = None  # (done, time) of the first call
        self._done = 0  # of the last call
        self._waited_last = -math.inf  # when the last "waiting for workers" line was written

    def __call__(self, done: int, failed: int = 0, lost: int = 0) -> None:
        now = time.monotonic()
        self._done = done
        if self._start is None:
            self._start = (done, now)
        final = done >= self.total
        if not self.tty and not final and now - self._last < self.every_s:
            return
        self._last = now
        elapsed = now - self.t0
        ran, running_s = done - lost - self._start[0], now - self._start[1]
        rate = ran / running_s * 60.0 if running_s > 0 and ran > 0 else 0.0
        eta = (self.total - done) / (rate / 60.0) if rate > 0 else float("nan")
        eta_text = f", ETA {eta:.0f} s" if rate > 0 and not final else ""
        line = (
            f"{self._bar(done)} {done}/{self.total} {self.label}"
            f", {failed} failed{f', {lost} lost' if lost else ''}, {elapsed:.0f} s, {rate:.1f}/min"
            f"{eta_text}"
        )
        self._write(line, final)

    def waiting(self, waited_s: float, timeout_s: float) -> None:
        """Say that no worker is connected, for ``waited_s`` of the ``timeout_s`` (s) after
        which the tasks left are given up (and that they are, from then on): redrawn in place
        on a terminal, otherwise a line at most every :data:`WAITING_EVERY_S`."""
        now = time.monotonic()
        over = waited_s >= timeout_s
        if not self.tty and not over and now - self._waited_last < WAITING_EVERY_S:
            return
        self._waited_last = now
        done = self._done
        if over:
            said = f"no worker connected for {timeout_s:g} s: the {self.label} left are lost"
        else:
            said = (
                f"waiting for workers (0 connected) for {waited_s:.0f} s; the {self.label} left"
                f" are given up after {timeout_s:g} s without one"
            )
        self._write(f"{self._bar(done)} {done}/{self.total} {self.label}, {said}", over)

    def _bar(self, done: int) -> str:
        filled = round((done / self.total if self.total else 1.0) * self.width)
        return f"[{'#' * filled}{'.' * (self.width - filled)}]"

    def _write(self, line: str, final: bool) -> None:
        if self.tty:
            # cut to the terminal's width (a wrapped line is not redrawn by "\r": each update
            # added a row) and cleared to its end (a shorter line left a longer one's tail)
            columns = shutil.get_terminal_size().columns
            self.stream.write(f"\r{line[: max(columns - 1, 20)]}{CLEAR_TO_EOL}")
            self.stream.write("\n" if final else "")
        else:
            self.stream.write(line + "\n")
        self.stream.flush()
