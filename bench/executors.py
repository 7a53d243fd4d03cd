"""Executors: run tasks in a local process pool or on a Dask cluster, one interface.

A task is ``(key, fn, args, watchdog_seconds)``; :meth:`run` yields one :class:`TaskResult`
per task as it finishes (completion order), never raising for a task's own trouble. A result
either carries the task's value (:attr:`TaskOutcome.VALUE`) or says why the *infrastructure*
produced none: the worker died while running it, overran the watchdog, the task function
raised, the Dask scheduler went away, the future was cancelled, Dask gave up on it
(``KilledWorker``) or a connection closed. Every solve runs in its own isolated child
(:mod:`c3bench.solvers.isolation`), so none of these is ever the solver's fault: the callers
store no row for them. A failed task is retried on a fresh worker up to ``retries`` times
(default once), except when the scheduler itself is gone: then nothing more is submitted
and every unfinished task is reported as :attr:`TaskOutcome.SCHEDULER_LOST`.

* :class:`LocalPool` (default): ``jobs`` forked worker processes, one task each at a time. A
  worker dies with its parent: a parent-death signal (Linux ``PR_SET_PDEATHSIG``) and the
  end-of-file on its pipe (the worker holds no other copy of the parent's end) both end it,
  and its SIGTERM handler exits through ``SystemExit`` so that the isolated solve's cleanup
  (killing its process group) runs.
* :class:`DaskPool`: a Dask distributed cluster (``Client(address)``, connected within
  :data:`CONNECT_TIMEOUT` seconds or :class:`SchedulerUnreachable`).

The benchmark runner (:mod:`bench.runner`) and the closed-loop suites
(:mod:`bench.closed_loop_suite`) both run through these.
"""

from __future__ import annotations

import contextlib
import ctypes
import logging
import multiprocessing
import os
import signal
import sys
import time
from collections import deque
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass
from enum import StrEnum
from multiprocessing.connection import wait as wait_connections
from multiprocessing.reduction import ForkingPickler
from pathlib import Path
from types import FrameType
from typing import Any, Protocol

from c3bench.bench.lock import close_inherited_locks
from c3bench.problems.errors import C3BenchError, InputError

CONNECT_TIMEOUT = 10.0
"""Seconds :class:`DaskPool` waits for the scheduler (also its reconnection window)."""
RETRIES = 1
"""How many times a task whose infrastructure failed is run again (on a fresh worker)."""


class SchedulerUnreachable(C3BenchError, ConnectionError):
    """The Dask scheduler cannot be reached (the message names its address)."""


class TaskOutcome(StrEnum):
    """How a task ended: with its value, or why the infrastructure produced none."""

    VALUE = "value"
    """The task function returned; :attr:`TaskResult.value` holds what it returned."""
    WORKER_DIED = "worker_died"
    """The worker process died while running the task (or before taking it)."""
    WATCHDOG = "watchdog"
    """The worker did not answer within the task's watchdog and was killed."""
    TASK_RAISED = "task_raised"
    """The task function raised, or its value could not be sent back."""
    SCHEDULER_LOST = "scheduler_lost"
    """The connection to the Dask scheduler is gone; the task did not finish."""
    CANCELLED = "cancelled"
    """The Dask future was cancelled (the scheduler still answers)."""
    KILLED_WORKER = "killed_worker"
    """Dask gave up on the task after it was running on several workers that died."""
    COMM_CLOSED = "comm_closed"
    """A connection closed while fetching the task's value."""


RETRIED: frozenset[TaskOutcome] = frozenset({
    TaskOutcome.WORKER_DIED, TaskOutcome.WATCHDOG, TaskOutcome.TASK_RAISED,
    TaskOutcome.CANCELLED, TaskOutcome.COMM_CLOSED})
"""Outcomes run again (``KILLED_WORKER``: the scheduler already retried it; a lost scheduler
runs nothing more)."""


@dataclass
class TaskResult:
    """Outcome of one task: its value, or the infrastructure reason it produced none."""

    key: Any
    outcome: TaskOutcome
    value: Any = None
    reason: str = ""
    attempts: int = 1

    @property
    def ok(self) -> bool:
        """Whether the task returned a value."""
        return self.outcome is TaskOutcome.VALUE


Task = tuple[Any, Callable[..., Any], tuple[Any, ...], float]
"""``(key, fn, args, watchdog_seconds)``."""


class Executor(Protocol):
    """What the runner needs of an executor."""

    def share(self, value: Any) -> Any:
        """A handle of ``value`` to pass in many tasks' arguments."""

    def run(self, tasks: Iterable[Task]) -> Iterator[TaskResult]:
        """Run tasks, yielding results as they finish."""

    def close(self) -> None:
        """Release the workers."""


MAX_REASONS = 5
"""Distinct reasons of missing tasks a caller keeps (:func:`note_reason`)."""


def note_reason(reasons: list[str], reason: str, limit: int = MAX_REASONS) -> None:
    """Append ``reason`` to ``reasons`` unless it is there or ``limit`` are kept already."""
    if reason not in reasons and len(reasons) < limit:
        reasons.append(reason)


# --- the local pool's worker ----------------------------------------------------------------------
PR_SET_PDEATHSIG = 1


def die_with_parent(parent_pid: int) -> None:
    """Make this process receive SIGTERM when its parent dies (Linux), and exit now if the
    parent is already gone (the race between the fork and ``prctl``)."""
    if sys.platform.startswith("linux"):
        with contextlib.suppress(OSError, AttributeError):
            ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, int(signal.SIGTERM),
                                                    0, 0, 0)
    if os.getppid() != parent_pid:
        raise SystemExit(0)


def exit_on_sigterm(signum: int, frame: FrameType | None) -> None:
    raise SystemExit(0)  # unwinds through the isolated solve's finally, which kills its child


def pickled(reply: Any, unsendable: Callable[[str], Any]) -> bytes:
    """``reply`` pickled for a pipe, or, when it cannot be pickled, ``unsendable(why)``."""
    try:
        return bytes(ForkingPickler.dumps(reply))
    except Exception as error:  # noqa: BLE001 - e.g. an unpicklable value
        return bytes(ForkingPickler.dumps(unsendable(f"{type(error).__name__}: {error}")))


def _reply(key: Any, fn: Callable[..., Any], args: tuple[Any, ...]) -> bytes:
    """The pickled ``(key, ok, value)`` answer of one task (``ok`` false: a message)."""
    try:
        reply: tuple[Any, bool, Any] = (key, True, fn(*args))
    except Exception as error:  # noqa: BLE001 - the task raised: reported, never fatal
        reply = (key, False, f"the task raised {type(error).__name__}: {error}")
    return pickled(reply, lambda why: (key, False, f"the task's value cannot be sent back "
                                                   f"({why})"))


def become_worker(parent_pid: int, inherited: Sequence[Any] = ()) -> None:
    """Set up a forked worker process: SIGTERM exits (:func:`exit_on_sigterm`, not a handler
    copied from the parent), Ctrl-C is left to the parent, the worker dies with
    ``parent_pid`` (:func:`die_with_parent`), and the parent's pipe ends copied by the fork
    (``inherited``: closed so that the worker sees end-of-file when the parent dies) and its
    results-directory locks are closed."""
    signal.signal(signal.SIGTERM, exit_on_sigterm)
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the parent handles Ctrl-C
    die_with_parent(parent_pid)
    for other in inherited:
        other.close()
    close_inherited_locks()


def serve(connection: Any, answer: Callable[[Any], bytes]) -> None:
    """Send ``answer(message)`` for each message received, until ``None``, end-of-file or a
    broken pipe."""
    while True:
        try:
            message = connection.recv()
        except (EOFError, OSError):
            return
        if message is None:
            return
        try:
            connection.send_bytes(answer(message))
        except OSError:
            return


def worker_main(connection: Any, log_path: str | None = None,
                inherited: Sequence[Any] = (), parent_pid: int | None = None) -> None:
    """Loop of a pool worker: receive ``(key, fn, args)``, send ``(key, ok, value)``.

    ``inherited`` are the parent's ends of every worker's pipe, copied by the fork
    (:func:`become_worker`). With ``log_path`` the worker's stdout and stderr (file
    descriptors 1 and 2, so C libraries' prints too) are appended to that file instead of the
    terminal.
    """
    become_worker(os.getppid() if parent_pid is None else parent_pid, inherited)
    if log_path:
        descriptor = os.open(log_path, os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o644)
        os.dup2(descriptor, 1)
        os.dup2(descriptor, 2)
        os.close(descriptor)
    serve(connection, lambda message: _reply(*message))


# --- the local pool ---------------------------------------------------------------------------
@dataclass
class _Worker:
    """A worker process, the parent's end of its pipe and the task it runs."""

    process: Any
    conn: Any
    task: Task | None = None
    attempt: int = 0
    since: float = 0.0


class LocalPool:
    """``jobs`` worker processes, one task each at a time, with crash and hang recovery.

    A worker that dies while running a task, or does not answer within the task's watchdog
    (then it is killed), is replaced; its task is run again up to ``retries`` times and
    otherwise yields :attr:`TaskOutcome.WORKER_DIED` / :attr:`TaskOutcome.WATCHDOG`. Solver
    output of the workers goes to ``log_path`` when given.
    """

    def __init__(self, jobs: int, log_path: str | Path | None = None,
                 retries: int = RETRIES) -> None:
        if jobs < 1:
            raise InputError(f"jobs must be >= 1, got {jobs}")
        self.jobs = jobs
        self.retries = retries
        self.log_path = str(log_path) if log_path else None
        method = "fork" if "fork" in multiprocessing.get_all_start_methods() else "spawn"
        self.context: Any = multiprocessing.get_context(method)
        self.workers: list[_Worker] = []

    def _start(self) -> _Worker:
        """A new worker process and the parent's end of its pipe."""
        parent, child = self.context.Pipe(duplex=True)
        inherited = [parent, *(worker.conn for worker in self.workers)]
        process = self.context.Process(
            target=worker_main, daemon=False,
            args=(child, self.log_path, inherited if self.context.get_start_method() == "fork"
                  else (), os.getpid()))
        process.start()
        child.close()
        return _Worker(process, parent)

    def _stop(self, worker: _Worker, force: bool = False) -> None:
        """End a worker: ask it to stop (unless ``force``), then terminate, then kill."""
        process = worker.process
        if not force:
            with contextlib.suppress(OSError, ValueError):
                worker.conn.send(None)
            process.join(2)
        if process.is_alive():
            process.terminate()  # SIGTERM: the worker exits through SystemExit
            process.join(5)
        if process.is_alive():
            process.kill()
            process.join(5)
        worker.conn.close()

    def _replace(self, worker: _Worker) -> _Worker:
        """Stop ``worker`` (killing it) and put a fresh one in its place."""
        index = self.workers.index(worker)
        self._stop(worker, force=True)
        self.workers[index] = fresh = self._start()
        return fresh

    def share(self, value: Any) -> Any:
        """``value`` itself: forked workers receive it with each task."""
        return value

    def _dispatch(self, queue: deque[tuple[Task, int]]) -> Iterator[TaskResult]:
        """Hand queued tasks to idle workers; yield those that cannot be sent."""
        for index in range(len(self.workers)):
            worker = self.workers[index]
            if worker.task is not None or not queue:
                continue
            if not worker.process.is_alive():
                worker = self._replace(worker)
            task, attempt = queue.popleft()
            key, fn, args, _ = task
            try:
                payload = bytes(ForkingPickler.dumps((key, fn, args)))
            except Exception as error:  # noqa: BLE001 - an argument that cannot be pickled
                yield TaskResult(key, TaskOutcome.TASK_RAISED, attempts=attempt,
                                 reason=f"the task cannot be sent ({type(error).__name__}: "
                                        f"{error})")
                continue
            try:
                worker.conn.send_bytes(payload)
            except OSError:  # the worker died idle: a fresh one takes the task, if allowed
                self._replace(worker)
                if attempt <= self.retries:
                    queue.appendleft((task, attempt + 1))
                else:
                    yield TaskResult(key, TaskOutcome.WORKER_DIED, attempts=attempt,
                                     reason="pool worker died before taking the task")
                continue
            worker.task, worker.attempt, worker.since = task, attempt, time.monotonic()

    def _collect(self, worker: _Worker, ready: list[Any]) -> TaskResult | None:
        """The result of ``worker``'s task if it has one now (answer, death or overrun)."""
        task = worker.task
        assert task is not None
        key, watchdog = task[0], task[3]
        if worker.conn in ready or worker.process.sentinel in ready:
            with contextlib.suppress(EOFError, OSError):
                if worker.conn.poll():
                    _, ok, value = worker.conn.recv()
                    if ok:
                        return TaskResult(key, TaskOutcome.VALUE, value, attempts=worker.attempt)
                    return TaskResult(key, TaskOutcome.TASK_RAISED, reason=str(value),
                                      attempts=worker.attempt)
            if not worker.process.is_alive():
                code = worker.process.exitcode
                self._replace(worker)
                return TaskResult(key, TaskOutcome.WORKER_DIED, attempts=worker.attempt,
                                  reason=f"pool worker died (exit code {code}) outside the "
                                         f"isolated solve")
        if time.monotonic() - worker.since > watchdog:
            self._replace(worker)
            return TaskResult(key, TaskOutcome.WATCHDOG, attempts=worker.attempt,
                              reason=f"pool worker did not answer within its {watchdog:g} s "
                                     f"watchdog; worker killed")
        return None

    def _wait(self) -> list[Any]:
        """Wait until a busy worker answers, dies, or reaches its watchdog."""
        busy = [w for w in self.workers if w.task is not None]
        waitables: list[Any] = [w.conn for w in busy] + [w.process.sentinel for w in busy]
        deadline = min(w.since + w.task[3] for w in busy if w.task is not None)
        return list(wait_connections(waitables, timeout=max(0.0, deadline - time.monotonic())
                                     + 0.05))

    def run(self, tasks: Iterable[Task]) -> Iterator[TaskResult]:
        """Run tasks, yielding results as they finish (in completion order)."""
        queue: deque[tuple[Task, int]] = deque((task, 1) for task in tasks)
        try:
            while len(self.workers) < min(self.jobs, len(queue)):
                self.workers.append(self._start())
            while queue or any(w.task is not None for w in self.workers):
                yield from self._dispatch(queue)
                if not any(w.task is not None for w in self.workers):
                    continue
                ready = self._wait()
                for worker in list(self.workers):
                    if worker.task is None or worker not in self.workers:
                        continue
                    task, attempt = worker.task, worker.attempt
                    result = self._collect(worker, ready)
                    if result is None:
                        continue
                    worker.task = None
                    if result.outcome in RETRIED and attempt <= self.retries:
                        queue.append((task, attempt + 1))
                    else:
                        yield result
        finally:
            self.close()

    def close(self) -> None:
        """Stop every worker (killing those still busy)."""
        for worker in self.workers:
            self._stop(worker, force=worker.task is not None)
        self.workers = []


# --- Dask -------------------------------------------------------------------------------------
def _scheduler_lost(error: BaseException, client: Any) -> bool:
    """Whether ``error`` means the scheduler connection is gone."""
    return ("scheduler-connection-lost" in str(error)
            or getattr(client, "status", "running") not in ("running", "newly-created"))


def check_scheduler_address(address: str, option: str = "--scheduler") -> None:
    """``address`` is a Dask scheduler address (``tcp://host:port``, ``host:port``, ...).

    Checked before a ``Client`` is made: one given a malformed address fails half-built and
    its finaliser then waits 20 s for a connection that never existed.

    Raises
    ------
    InputError
        The address cannot be parsed (no port, unknown scheme, port out of range).
    """
    from distributed.comm.addressing import get_address_host_port

    try:
        _, port = get_address_host_port(address)
    except ValueError as error:
        if "don't know how to extract" in str(error):
            return  # a scheme without host:port (ucx, inproc): the client checks it
        raise InputError(f"{option} {address!r}: {error}") from None
    if not 0 < port < 65536:
        raise InputError(f"{option} {address!r}: port {port} is not in 1-65535")


class DaskPool:
    """Tasks on a Dask distributed cluster (``Client(address)``), same interface.

    Raises :class:`SchedulerUnreachable` when the scheduler does not answer within
    ``connect_timeout`` seconds and :class:`~c3bench.problems.errors.InputError` for an
    address it cannot parse. Watchdogs are not used: every solve enforces its own time limit
    by killing its isolated child. Once the scheduler is lost (:attr:`lost` says why),
    nothing more is submitted and every unfinished task yields
    :attr:`TaskOutcome.SCHEDULER_LOST`.
    """

    def __init__(self, address: str, retries: int = RETRIES,
                 connect_timeout: float = CONNECT_TIMEOUT) -> None:
        """Connect to the scheduler at ``address`` (for example ``tcp://host:8786``)."""
        from distributed import Client

        self.address = address
        self.retries = retries
        self.lost = ""
        check_scheduler_address(address)
        try:
            self.client = Client(address, timeout=connect_timeout, set_as_default=False)
        except ValueError as error:
            raise InputError(f"--scheduler {address!r}: {error}") from None
        except OSError as error:  # TimeoutError and CommClosedError among them
            raise SchedulerUnreachable(
                f"--scheduler {address}: cannot reach the Dask scheduler within "
                f"{connect_timeout:g} s ({error}); is it running?") from None

    def _lose(self, error: BaseException | str) -> str:
        """Record that the scheduler is gone (silencing the client's reconnection noise)."""
        if not self.lost:
            self.lost = f"lost the connection to the Dask scheduler at {self.address}"
            for name in ("distributed", "distributed.client", "distributed.comm"):
                logging.getLogger(name).setLevel(logging.CRITICAL)
        return self.lost

    def share(self, value: Any) -> Any:
        """Scatter ``value`` to the cluster once; tasks receive the future."""
        if self.lost:
            return value
        try:
            return self.client.scatter(value, broadcast=False, hash=False)
        except Exception as error:  # CancelledError, OSError, TimeoutError: re-raised unless lost
            if not _scheduler_lost(error, self.client):
                raise
            self._lose(error)
            return value

    def _submit(self, task: Task, attempt: int) -> Any:
        _, fn, args, _ = task
        return self.client.submit(fn, *args, pure=False, retries=0,
                                  key=f"c3bench-{os.getpid()}-{attempt}-{time.time_ns()}")

    def _result(self, future: Any, key: Any, attempt: int) -> TaskResult:
        """The :class:`TaskResult` of a finished future."""
        from distributed import KilledWorker

        def failed(outcome: TaskOutcome, reason: str) -> TaskResult:
            return TaskResult(key, outcome, reason=reason, attempts=attempt)

        status = future.status
        if status == "error":
            error = future.exception()
            if isinstance(error, KilledWorker):
                return failed(TaskOutcome.KILLED_WORKER, f"Dask gave up on the task: workers "
                                                         f"died while running it ({error})")
            return failed(TaskOutcome.TASK_RAISED,
                          f"the task raised {type(error).__name__}: {error}")
        try:
            if status == "cancelled":
                future.result()  # raises with the cancellation's reason
            return TaskResult(key, TaskOutcome.VALUE, future.result(), attempts=attempt)
        except Exception as error:  # noqa: BLE001 - classified below
            if _scheduler_lost(error, self.client):
                return failed(TaskOutcome.SCHEDULER_LOST, self._lose(error))
            if status == "cancelled" or "cancel" in type(error).__name__.lower():
                return failed(TaskOutcome.CANCELLED, f"the Dask future was cancelled "
                                                     f"({str(error).splitlines()[0]})")
            return failed(TaskOutcome.COMM_CLOSED,
                          f"fetching the result failed: {type(error).__name__}: {error}")

    def run(self, tasks: Iterable[Task]) -> Iterator[TaskResult]:
        """Submit every task, then yield results as they finish (watchdogs unused)."""
        from distributed import as_completed

        tasks = list(tasks)
        if self.lost:
            for task in tasks:
                yield TaskResult(task[0], TaskOutcome.SCHEDULER_LOST, reason=self.lost)
            return
        running: dict[str, tuple[Task, int, Any]] = {}
        try:
            stream = as_completed(loop=self.client.loop)
            for task in tasks:
                future = self._submit(task, 1)
                running[future.key] = (task, 1, future)
                stream.add(future)
            for future in stream:
                task, attempt, _ = running.pop(future.key)
                result = self._result(future, task[0], attempt)
                with contextlib.suppress(Exception):
                    future.release()
                if result.outcome is TaskOutcome.SCHEDULER_LOST:
                    yield result
                    for other, other_attempt, _ in running.values():
                        yield TaskResult(other[0], TaskOutcome.SCHEDULER_LOST,
                                         reason=self.lost, attempts=other_attempt)
                    running.clear()
                    return
                if result.outcome in RETRIED and attempt <= self.retries:
                    again = self._submit(task, attempt + 1)
                    running[again.key] = (task, attempt + 1, again)
                    stream.add(again)
                    continue
                yield result
        finally:
            pending = [future for _, _, future in running.values() if not future.done()]
            if pending and not self.lost:
                with contextlib.suppress(Exception):
                    self.client.cancel(pending)

    def close(self) -> None:
        """Disconnect from the cluster (within a few seconds when the scheduler is gone)."""
        with contextlib.suppress(Exception):
            self.client.close(timeout=2 if self.lost else CONNECT_TIMEOUT)
