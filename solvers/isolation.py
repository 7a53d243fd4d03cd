"""Isolated solves: warm-up, repeats, and a child process killed when it overruns.

Every benchmark solve goes through :func:`solve_isolated`; the closed loop wraps its QP
backends in :class:`IsolatedBackend`. Both run the solver in a child process
(:mod:`c3bench.solvers.child_process`): started from a forkserver, never by ``fork``, so
threads of the parent (JAX, BLAS pools, Dask's) cannot make it unsafe; in its own process
group, killed with ``SIGKILL`` on overrun *and after every solve*, so a subprocess the solver
started dies with it; dying with its parent (``kill -9`` included); startable from a daemonic
process (Dask and pool workers).

What becomes a failure :class:`~c3bench.solvers.base.Result` (a row): everything the solve does
itself. An overrun is ``Failure.TIMEOUT`` ("time limit of X s exceeded; process killed"); an
exception is ``Failure.ERROR`` (``BackendUnavailable``: ``Failure.UNAVAILABLE``); a child that
dies (segfault, ``os._exit``) is ``Failure.ERROR`` "solver process died (exit code N, signal
NAME)"; a result that cannot be pickled is ``Failure.ERROR`` "the solver's result could not be
sent back: ..."; a backend class defined in ``__main__`` (which the child does not re-run) is
``Failure.ERROR`` with that reason. A child that cannot be started at all is not the solver's
doing: that raises :class:`IsolationFailed`, so that the caller stores nothing and tries again.

Time limits (docs/metrics.md): the untimed warm-up gets ``time_limit`` seconds, the ``n`` timed
solves ``n * time_limit`` together; starting the child and loading the solver are not counted
(they have their own bound,
:data:`~c3bench.solvers.child_process.STARTUP_SECONDS`).
"""

from __future__ import annotations

import copy
import functools
import math
import os
import statistics
import threading
import time
import weakref
from collections.abc import Callable
from dataclasses import dataclass
from multiprocessing.connection import Connection
from multiprocessing.process import BaseProcess
from multiprocessing.reduction import ForkingPickler
from types import TracebackType
from typing import TypeVar

import numpy as np

from c3bench.problems.errors import InputError
from c3bench.problems.instance import Problem
from c3bench.problems.names import Failure, Family, Precision
from c3bench.solvers import registry
from c3bench.solvers.base import Backend, Result, Settings, WarmStart
from c3bench.solvers.child_process import (
    IsolationFailed as IsolationFailed,  # re-exported: callers catch it from here
)
from c3bench.solvers.child_process import (
    Message,
    Reply,
    detach,
    died,
    launch,
    load,
    pinned_blas,
    receive,
    send,
    stop,
)
from c3bench.solvers.timing import warm_solve

SLOW_SOLVE_SECONDS = 1.0
"""A solve whose warm-up took longer than this is timed once: repeats add little accuracy."""


@dataclass(frozen=True)
class SolveJob:
    """One isolated solve, pickled in the parent and loaded in the child. ``backend`` is the
    instance (its class pickled by reference), so backends registered at runtime work too."""

    backend: Backend
    problem: Problem
    settings: Settings
    warm_start: WarmStart | None
    repeats: int
    warmup: bool
    update: bool = False
    """A warm cell: each solve is :func:`~c3bench.solvers.timing.warm_solve` (the solver
    object prepared untimed, then update + solve timed), not ``backend.solve``."""


def _one_solve(job: SolveJob) -> Result:
    """One solve of ``job``: cold (``backend.solve``) or warm (``warm_solve``)."""
    if job.update:
        return warm_solve(job.backend, job.problem, job.settings, job.warm_start)
    return job.backend.solve(job.problem, job.settings, job.warm_start)


def _run_repeats(job: SolveJob, notify: Callable[[int], None]) -> Result:
    """Warm-up (untimed) then ``job.repeats`` solves, BLAS on one thread; times are the
    medians. After a warm-up longer than :data:`SLOW_SOLVE_SECONDS` one timed solve is made.
    ``notify(n)`` is told, after the warm-up, how many timed solves follow. A warm job
    (``job.update``) times update + solve of a solver object prepared untimed before each
    solve (:func:`~c3bench.solvers.timing.warm_solve`), so ``setup_time`` is the update."""
    repeats = job.repeats
    with pinned_blas():
        if job.warmup:
            start = time.perf_counter()
            _one_solve(job)
            if time.perf_counter() - start > SLOW_SOLVE_SECONDS:
                repeats = 1
        notify(repeats)
        results = [_one_solve(job) for _ in range(repeats)]
    result = results[-1]
    if repeats > 1:
        result.setup_time = statistics.median(r.setup_time for r in results)
        result.solve_time = statistics.median(r.solve_time for r in results)
    result.diagnostics.setdefault("timed_repeats", float(repeats))
    return result


_Loaded = TypeVar("_Loaded")


def _handshake(connection: Connection, plugins: tuple[str, ...], payload: bytes,
               expected: type[_Loaded]) -> _Loaded | None:
    """A child's start: report ``STARTED`` with its pid, load ``payload`` (:func:`load`, which
    reports a failure itself), and report ``READY`` when it is an ``expected``; ``None``
    otherwise."""
    connection.send((Reply.STARTED, os.getpid()))
    loaded = load(connection, plugins, payload)
    if not isinstance(loaded, expected):
        return None
    connection.send((Reply.READY, None))
    return loaded


def _solve_in_child(connection: Connection, plugins: tuple[str, ...], payload: bytes) -> None:
    """Child of :func:`solve_isolated`: one job, then exit (quietly when the parent went
    away: an ``EOFError`` or ``OSError`` on the pipe)."""
    detach()
    try:
        job = _handshake(connection, plugins, payload, SolveJob)
        if job is None:
            return

        def notify(repeats: int) -> None:
            connection.send((Reply.WARM, repeats))

        result = registry.guarded(job.backend.name, job.problem,
                                  functools.partial(_run_repeats, job, notify))
        send(connection, (Reply.DONE, result))
    except (EOFError, OSError):  # the parent closed the pipe or died
        return


def _serve_in_child(connection: Connection, plugins: tuple[str, ...], payload: bytes) -> None:
    """Child of :class:`IsolatedBackend`: solve every ``(problem, settings, warm_start)``
    received until the pipe closes, BLAS on one thread.

    A parent that goes away (its pipe closes, even in the middle of a message or of the
    reply) ends the child quietly: an ``EOFError`` or ``OSError`` on the pipe is the end of
    the work, not an error to print.
    """
    detach()
    try:
        backend = _handshake(connection, plugins, payload, Backend)
        if backend is None:
            return
        with pinned_blas():
            while True:
                problem, settings, warm_start = connection.recv()
                problem = expand(problem)
                call = functools.partial(backend.solve, problem, settings, warm_start)
                send(connection, (Reply.DONE, registry.guarded(backend.name, problem, call)))
    except (EOFError, OSError):  # the parent closed the pipe or died
        return


def _failure(message: Message, process: BaseProcess, solver: str, problem: str,
             time_limit: float) -> Result:
    """The failure ``Result`` of a message other than ``DONE`` (``READY`` while loading never
    reaches here)."""
    kind, payload = message
    if kind == Reply.TIMEOUT:
        return Result.failed(solver, problem, Failure.TIMEOUT,
                             f"time limit of {time_limit:g} s exceeded; process killed",
                             solve_time=time_limit)
    if kind == Reply.DIED:
        return Result.failed(solver, problem, Failure.ERROR, died(process))
    return Result.failed(solver, problem, Failure.ERROR,
                         str(payload or f"unexpected message {kind!r}").strip())


COMPACT_BYTES = 1 << 20
"""A dense matrix of the problem larger than this (bytes) travels to the persistent child as
its nonzeros when at most :data:`COMPACT_DENSITY` of it is nonzero."""
COMPACT_DENSITY = 0.25


@dataclass
class _Nonzeros:
    """A dense matrix on the wire: its shape, dtype, flat nonzero positions and values."""

    shape: tuple[int, ...]
    dtype: str
    positions: np.ndarray
    values: np.ndarray

    def dense(self) -> np.ndarray:
        """The matrix again, bit for bit."""
        out = np.zeros(self.shape, dtype=self.dtype)
        out.ravel()[self.positions] = self.values
        return out


def compact(problem: Problem) -> Problem:
    """A shallow copy of ``problem`` whose large sparse matrices (``P``, ``A``, ``G``) are
    :class:`_Nonzeros` (a robust controller's stacked QP is 55 MB dense, 1 % nonzero);
    :func:`expand` restores them exactly."""
    out = copy.copy(problem)
    for field_name in ("P", "A", "G"):
        matrix = getattr(problem, field_name)
        if not isinstance(matrix, np.ndarray) or matrix.nbytes <= COMPACT_BYTES:
            continue
        positions = np.flatnonzero(matrix)
        if positions.size <= COMPACT_DENSITY * matrix.size:
            object.__setattr__(out, field_name, _Nonzeros(
                matrix.shape, matrix.dtype.str, positions, matrix.ravel()[positions]))
    return out


def expand(problem: Problem) -> Problem:
    """Undo :func:`compact` (in place)."""
    for field_name in ("P", "A", "G"):
        matrix = getattr(problem, field_name)
        if isinstance(matrix, _Nonzeros):
            object.__setattr__(problem, field_name, matrix.dense())
    return problem


def _pickled(item: object, backend: Backend) -> bytes | str:
    """``item`` pickled, or the reason it cannot be (also: ``backend``'s class lives in
    ``__main__``, which a child does not re-run, so it could not load it)."""
    kind = type(backend)
    if kind.__module__ == "__main__":
        return (f"backend class {kind.__qualname__} is defined in __main__, which an isolated "
                f"solver process cannot import: define it in an importable module (or solve "
                f"in this process with registry.solve)")
    try:
        return bytes(ForkingPickler.dumps(item))
    except Exception as error:  # noqa: BLE001 - any pickling error is reported
        return (f"the solve could not be sent to the solver process: "
                f"{type(error).__name__}: {error}")


def solve_isolated(name: str, problem: Problem, settings: Settings | None = None,
                   warm_start: WarmStart | None = None, repeats: int = 1, warmup: bool = False,
                   check: bool = True, update: bool | None = None) -> Result:
    """Solve ``problem`` with backend ``name`` in a child process killed on overrun; never
    raises for a solver's misbehaviour.

    Parameters
    ----------
    name, problem, settings, warm_start, check
        As for :func:`c3bench.solvers.registry.solve` (whose checks run first, here).
    repeats
        Timed solves (``>= 1``); the result's ``setup_time`` and ``solve_time`` are their
        medians (one solve when the warm-up took over :data:`SLOW_SOLVE_SECONDS`).
    warmup
        Solve once, untimed, first (first-call costs, lazy imports, JIT).
    update
        Time a warm cell by the solver's update API (:func:`~c3bench.solvers.timing.warm_solve`:
        the solver object prepared untimed, update + solve timed); ``None``: whenever a
        ``warm_start`` is given (a benchmark's warm cell), cold otherwise.

    Returns
    -------
    Result
        As :func:`~c3bench.solvers.registry.solve`, plus ``timeout`` (the warm-up overran
        ``settings.time_limit``, or the timed solves ``repeats * time_limit``; ``solve_time``
        is the limit) and ``error`` rows for a child that died or whose result could not be
        pickled.

    Raises
    ------
    IsolationFailed
        The child process could not be started (not a result of the solve).
    """
    settings = settings or Settings()
    if repeats < 1:
        raise InputError(f"repeats must be >= 1, got {repeats}")
    admitted = registry.admit(name, problem, settings, check)
    if isinstance(admitted, Result):
        return admitted
    warm = (warm_start is not None) if update is None else update
    payload = _pickled(SolveJob(admitted, problem, settings, warm_start, repeats, warmup, warm),
                       admitted)
    if isinstance(payload, str):
        return Result.failed(name, problem.name, Failure.ERROR, payload)
    limit = settings.time_limit
    process, connection, message = launch(_solve_in_child, payload, duplex=False)
    try:
        if message[0] == Reply.READY:
            message = receive(connection, limit)  # the warm-up
        if message[0] == Reply.WARM:
            message = receive(connection, limit * int(message[1]))  # the timed solves
        if message[0] == Reply.DONE and isinstance(message[1], Result):
            return registry.finish(message[1], problem)
        return _failure(message, process, name, problem.name, limit)
    finally:
        connection.close()
        stop(process)


# --- a persistent isolated backend (the closed loop) --------------------------------------
class _Child:
    """The persistent child of an :class:`IsolatedBackend` (``None`` until started)."""

    def __init__(self) -> None:
        self.process: BaseProcess | None = None
        self.connection: Connection | None = None

    def stop(self) -> None:
        """Kill the child's process group and forget it (a new one starts on demand)."""
        if self.connection is not None:
            self.connection.close()
        if self.process is not None:
            stop(self.process)
        self.process, self.connection = None, None


class IsolatedBackend(Backend):
    """A :class:`~c3bench.solvers.base.Backend` whose ``solve`` runs in one persistent child
    process, killed when a solve overruns ``time_limit`` seconds.

    The child (started on the first solve, as :func:`solve_isolated`'s: forkserver, own process
    group, dies with its parent) keeps the wrapped backend loaded and runs each solve sent over
    a pipe, BLAS on one thread. On overrun its process group is killed and ``solve`` returns a
    ``Failure.TIMEOUT`` result; a crash returns ``Failure.ERROR``; either way the next solve
    starts a fresh child. An exception in the backend is returned as a failure ``Result``
    (``BackendUnavailable``: ``Failure.UNAVAILABLE``), never raised. ``name``, ``families``,
    ``precisions``, ``accepts`` and availability are the wrapped backend's.

    Use as a context manager or call :meth:`close`; a forgotten one is closed when collected.

    Raises
    ------
    InputError
        ``time_limit`` is not a finite number > 0.
    """

    def __init__(self, backend: Backend, time_limit: float) -> None:
        if not (isinstance(time_limit, int | float) and math.isfinite(time_limit)
                and time_limit > 0):
            raise InputError(f"time limit must be a finite number > 0, got {time_limit!r}")
        self.backend = backend
        self.time_limit = float(time_limit)
        self.name = backend.name
        self.families: tuple[Family, ...] = backend.families
        self.precisions: tuple[Precision, ...] = backend.precisions
        self.package = backend.package
        self.description = backend.description
        self._lock = threading.Lock()
        self._child = _Child()
        self._finalizer = weakref.finalize(self, self._child.stop)

    def __reduce__(self) -> tuple[type[IsolatedBackend], tuple[Backend, float]]:
        """Pickled as its backend and limit (a copy starts its own child)."""
        return IsolatedBackend, (self.backend, self.time_limit)

    def require(self) -> None:
        self.backend.require()

    def availability(self) -> tuple[bool, str]:
        return self.backend.availability()

    def version(self) -> str:
        return self.backend.version()

    def accepts(self, problem: Problem) -> tuple[bool, str]:
        return self.backend.accepts(problem)

    @property
    def pid(self) -> int | None:
        """The child's process id (``None`` when none runs)."""
        return None if self._child.process is None else self._child.process.pid

    def solve(self, problem: Problem, settings: Settings,
              warm_start: WarmStart | None = None) -> Result:
        """Solve in the child; a failure ``Result`` on overrun, crash or exception.

        Raises
        ------
        IsolationFailed
            The child process could not be started.
        """
        with self._lock:
            request = _pickled((compact(problem), settings, warm_start), self.backend)
            if isinstance(request, str):
                return Result.failed(self.name, problem.name, Failure.ERROR, request)
            child = self._child
            if child.process is None or child.connection is None:
                loaded = self.start()
                if loaded is not None:
                    return self._failed(loaded, problem.name)
            assert child.process is not None and child.connection is not None
            try:
                child.connection.send_bytes(request)
            except OSError:
                return self._failed((Reply.DIED, None), problem.name)
            message = receive(child.connection, self.time_limit)
            if message[0] == Reply.DONE and isinstance(message[1], Result):
                return message[1]
            return self._failed(message, problem.name)

    def start(self) -> Message | None:
        """Start the child; ``None`` when ready, else the message that ended the loading."""
        payload = _pickled(self.backend, self.backend)
        if isinstance(payload, str):
            return Reply.ERROR, payload
        process, connection, message = launch(_serve_in_child, payload, duplex=True)
        self._child.process, self._child.connection = process, connection
        return None if message[0] == Reply.READY else message

    def _failed(self, message: Message, problem: str) -> Result:
        """The failure of ``message``; the child is killed (a new one starts next time)."""
        process = self._child.process
        result = (Result.failed(self.name, problem, Failure.ERROR, str(message[1]))
                  if process is None else
                  _failure(message, process, self.name, problem, self.time_limit))
        self._child.stop()
        return result

    def close(self) -> None:
        """Kill the child (a later ``solve`` starts a new one)."""
        with self._lock:
            self._child.stop()

    def __enter__(self) -> IsolatedBackend:
        return self

    def __exit__(self, kind: type[BaseException] | None, error: BaseException | None,
                 trace: TracebackType | None) -> None:
        self.close()
