"""Where ``c3bench perf`` runs a configuration's steps: its own process, or this one.

Every configuration (backend, precision, device, samples) of a run is prepared and stepped in
a process of its own by default (:class:`WorkerBackend`), forked from the run's process once
the shared inputs exist (:class:`~c3bench.bench.perf_backends.PerfContext`; nothing is
pickled) and driven block by block, so that the interleaving of :mod:`bench.perf` is kept
(one process computes at a time, the others wait on their pipes) while no backend runs in an
interpreter that another backend's runtime has changed. Measured on the 2-core EPYC VM
(znver3, load average below 1, 16 samples, warm steps, three alternated runs each): the
compiled ADMM took 832 us alone, 910 us when the JAX backend's steps ran in the same process
between its blocks (its Python glue 50 % slower, its compiled calls 10 %), and 840 us when
they ran in another process on the same machine; a controller runs one solver in its
process, so that is the like-for-like measurement. ``perf --same-process`` measures
everything in the run's process (:class:`InProcessBackend`) to show the difference.

A backend's own failure (its factory says it cannot run or raises, a step raises, what it
returns cannot be sent back) comes back as a message and becomes a skipped row, in either
mode. A worker that dies is an infrastructure failure (:class:`WorkerLost`): the
configuration gets no row. There is no time limit on a block (the reference controller's
blocks take tens of seconds); a worker ends with the run's process (parent-death signal, end
of file on its pipe, SIGTERM handled as an exit) and is joined, or killed, when its sample
count is done. Without ``--cpu`` the workers may run on either core, so a ``cold`` step may
find its core's private caches as its own last step left them; ``--cpu N`` puts every worker
on one core. Where ``fork`` is not available (Windows), every configuration runs in the run's
process, as with ``--same-process``.
"""

from __future__ import annotations

import contextlib
import gc
import multiprocessing
import os
import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from c3bench.bench.executors import become_worker, pickled, serve
from c3bench.bench.perf_backends import (
    BackendSpec,
    BackendUnavailable,
    Configuration,
    PerfContext,
    PreparedBackend,
    StepParts,
)
from c3bench.bench.perf_store import ProcessMode
from c3bench.problems.errors import C3BenchError

__all__ = ["BackendFailure", "InProcessBackend", "StepRecord", "WorkerBackend", "WorkerLost",
           "process_mode", "start_backend"]

JOIN_SECONDS = 5.0
"""How long a finished worker may take to exit before it is killed."""


class WorkerLost(C3BenchError, RuntimeError):
    """A configuration's worker process died or its pipe closed (no row is stored)."""


class BackendFailure(C3BenchError, RuntimeError):
    """A configuration's step raised (``unavailable``: it raised
    :class:`~c3bench.bench.perf_backends.BackendUnavailable`); the steps it completed before
    are in ``records``."""

    def __init__(self, message: str, records: list[StepRecord], unavailable: bool) -> None:
        super().__init__(message)
        self.records = records
        self.unavailable = unavailable


@dataclass
class StepRecord:
    """One timed control step: wall and CPU seconds around the backend's ``step`` call, its
    parts and the MFLOP its arithmetic executed (``None``: the backend does not count them)."""

    wall: float
    cpu: float
    parts: StepParts
    executed_mflop: float | None


@dataclass(frozen=True)
class BackendTraits:
    """What the run needs to know of a prepared backend (:class:`PreparedBackend`)."""

    repeats: int | None
    note: str
    flop_model: bool


def _traits(prepared: PreparedBackend) -> BackendTraits:
    return BackendTraits(prepared.repeats, prepared.note, prepared.flop_model)


def _prepare(spec: BackendSpec, context: PerfContext, config: Configuration
             ) -> PreparedBackend:
    """The configuration prepared by its factory; :class:`BackendUnavailable` when the
    factory says it cannot run or raises (the skipped row's note says which)."""
    try:
        return spec.make(context, config)
    except BackendUnavailable:
        raise
    except Exception as error:  # a factory that raises: a skipped row, not a crashed run
        raise BackendUnavailable(f"preparation failed: {type(error).__name__}: {error}"
                                 ) from error


def _run_block(prepared: PreparedBackend, context: PerfContext, first: int, count: int,
               failure_prefix: str) -> list[StepRecord]:
    """Steps ``first .. first + count - 1`` of the state sequence, timed (BLAS as the caller
    pinned it); a step that raises ends the block with :class:`BackendFailure`."""
    records: list[StepRecord] = []
    for step in range(first, first + count):
        index, x, u_prev = context.states[step % len(context.states)]
        try:
            wall, cpu = time.perf_counter(), time.process_time()
            parts = prepared.step(index, x, u_prev)
            cpu = time.process_time() - cpu
            wall = time.perf_counter() - wall
            executed = None if prepared.executed_flops is None else \
                prepared.executed_flops() / 1e6
        except BackendUnavailable as error:
            raise BackendFailure(str(error), records, True) from error
        except Exception as error:  # a backend that raises: a skipped row
            raise BackendFailure(f"{failure_prefix}: {type(error).__name__}: {error}",
                                 records, False) from error
        records.append(StepRecord(wall, cpu, parts, executed))
    return records


class InProcessBackend:
    """A configuration prepared and stepped in the run's own process (``--same-process``)."""

    process = ProcessMode.SHARED

    def __init__(self, spec: BackendSpec, context: PerfContext, config: Configuration) -> None:
        self._prepared = _prepare(spec, context, config)  # BackendUnavailable: nothing to close
        self._context = context
        self._failure_prefix = spec.failure
        self.traits = _traits(self._prepared)

    def run_block(self, first: int, count: int) -> list[StepRecord]:
        """Timed steps ``first .. first + count - 1`` (:class:`BackendFailure`)."""
        return _run_block(self._prepared, self._context, first, count, self._failure_prefix)

    def compile_seconds(self) -> float:
        """JIT seconds in this process (:class:`BackendFailure` when that raises)."""
        try:
            return float(self._prepared.compile_seconds())
        except Exception as error:  # the backend's failure: a skipped row
            raise BackendFailure(f"{self._failure_prefix}: {type(error).__name__}: {error}",
                                 [], False) from error

    def close(self) -> None:
        """Nothing to release."""


def _worker(connection: Any, spec: BackendSpec, context: PerfContext, config: Configuration,
            parent_pid: int, inherited: Sequence[Any]) -> None:
    """The worker's loop: prepare, then answer ``("block", first, count)``, ``("compile",)``
    and ``None`` (stop)."""
    from c3bench.solvers.timing import single_thread_blas

    become_worker(parent_pid, inherited)
    try:
        prepared = _prepare(spec, context, config)
    except BackendUnavailable as error:
        connection.send(("unavailable", str(error)))
        return
    connection.send(("ready", _traits(prepared)))
    gc.collect()
    with single_thread_blas():
        serve(connection, lambda message: _answer(prepared, context, spec, message))


def _answer(prepared: PreparedBackend, context: PerfContext, spec: BackendSpec,
            message: tuple[Any, ...]) -> bytes:
    """The pickled reply to ``("block", first, count)`` or ``("compile",)``: ``("ok",
    value)`` or ``("failed", note, records, unavailable)`` (the backend's own failure)."""
    reply: tuple[Any, ...]
    try:
        if message[0] == "compile":
            reply = ("ok", float(prepared.compile_seconds()))
        else:
            reply = ("ok", _run_block(prepared, context, message[1], message[2],
                                      spec.failure))
    except BackendFailure as failure:
        reply = ("failed", str(failure), failure.records, failure.unavailable)
    except Exception as error:  # noqa: BLE001 (its compile_seconds raised: its failure)
        reply = ("failed", f"{spec.failure}: {type(error).__name__}: {error}", [], False)
    return pickled(reply, lambda why: ("failed", f"{spec.failure}: its result cannot be "
                                                 f"sent back ({why})", [], False))


class WorkerBackend:
    """A configuration prepared and stepped in a forked worker process (module docstring);
    :class:`BackendUnavailable` from the constructor when its factory says it cannot run."""

    process = ProcessMode.WORKER

    def __init__(self, spec: BackendSpec, context: PerfContext, config: Configuration,
                 others: Sequence[WorkerBackend] = ()) -> None:
        fork = multiprocessing.get_context("fork")
        self._connection, child = fork.Pipe()
        inherited = [self._connection, *(other._connection for other in others)]
        self._process = fork.Process(
            target=_worker, args=(child, spec, context, config, os.getpid(), inherited),
            name=f"c3bench-perf-{config.backend}-{config.precision}-{config.samples}", daemon=True)
        self._process.start()
        child.close()
        try:
            answer = self._receive()
        except BaseException:  # lost, or Ctrl-C while it prepares: never leave it running
            self.close()
            raise
        if answer[0] == "unavailable":
            self.close()
            raise BackendUnavailable(answer[1])
        self.traits: BackendTraits = answer[1]

    def _receive(self) -> Any:
        try:
            return self._connection.recv()
        except (EOFError, OSError) as error:
            code = self._process.exitcode
            self._process.join(JOIN_SECONDS)
            code = self._process.exitcode if code is None else code
            raise WorkerLost(f"its worker process ended (exit code {code})") from error

    def run_block(self, first: int, count: int) -> list[StepRecord]:
        """Timed steps ``first .. first + count - 1`` in the worker (:class:`BackendFailure`,
        :class:`WorkerLost`)."""
        records: list[StepRecord] = self._request(("block", first, count))
        return records

    def compile_seconds(self) -> float:
        """JIT seconds in the worker (:class:`BackendFailure`, :class:`WorkerLost`)."""
        return float(self._request(("compile",)))

    def _request(self, message: tuple[Any, ...]) -> Any:
        """Send ``message``; the value of the ``("ok", value)`` reply
        (:class:`BackendFailure` for a ``("failed", ...)`` one, :class:`WorkerLost`)."""
        try:
            self._connection.send(message)
        except OSError as error:
            raise WorkerLost(f"its worker process cannot be reached ({error})") from error
        reply = self._receive()
        if reply[0] == "failed":
            raise BackendFailure(reply[1], reply[2], reply[3])
        return reply[1]

    def close(self) -> None:
        """Stop the worker: ask it, then kill it if it has not exited in
        :data:`JOIN_SECONDS`."""
        with contextlib.suppress(OSError):
            self._connection.send(None)
        self._process.join(JOIN_SECONDS)
        if self._process.is_alive():
            self._process.kill()
            self._process.join()
        self._connection.close()


def process_mode(worker_processes: bool) -> ProcessMode:
    """Where :func:`start_backend` runs configurations: in workers when asked and ``fork``
    is available, else in the run's process."""
    if worker_processes and "fork" in multiprocessing.get_all_start_methods():
        return ProcessMode.WORKER
    return ProcessMode.SHARED


def start_backend(spec: BackendSpec, context: PerfContext, config: Configuration,
                  worker_process: bool, others: Sequence[Any] = ()
                  ) -> WorkerBackend | InProcessBackend:
    """The configuration prepared in a worker process (``worker_process``, where
    :func:`process_mode` allows it) or in this one; ``others`` are the workers already running
    (their pipes are closed in the new one)."""
    if process_mode(worker_process) == ProcessMode.SHARED:
        return InProcessBackend(spec, context, config)
    return WorkerBackend(spec, context, config,
                         [other for other in others if isinstance(other, WorkerBackend)])
