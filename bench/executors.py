"""Executors: run tasks in a local process pool or on a Dask cluster, one interface.

A task is ``(key, fn, args, watchdog_seconds)``; :meth:`run` yields a :class:`TaskResult` per
task as it finishes (completion order), never raising for a task's own failure:

* :class:`LocalPool` (default): ``jobs`` worker processes, one task each at a time; a worker
  that dies or overruns its watchdog costs only its task, recorded as a failed result, and is
  replaced;
* :class:`DaskPool`: a Dask distributed cluster (``Client(address)``).

The benchmark runner (:mod:`bench.runner`) and the closed-loop suites
(:mod:`bench.closed_loop_suite`) both run through these.
"""

from __future__ import annotations

import contextlib
import multiprocessing
import os
import signal
import time
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from multiprocessing.connection import wait as wait_connections
from pathlib import Path
from typing import Any, Protocol

from c3bench.problems.errors import InputError
from c3bench.problems.names import Failure


@dataclass
class TaskResult:
    """Outcome of one task: ``ok`` with its value, or the reason it produced none."""

    key: Any
    ok: bool
    value: Any = None
    failure: str = ""
    reason: str = ""


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


def worker_main(connection: Any, log_path: str | None = None) -> None:
    """Loop of a pool worker: receive ``(key, fn, args)``, send ``(key, ok, value)``.

    With ``log_path`` the worker's stdout and stderr (file descriptors 1 and 2, so C
    libraries' prints too) are appended to that file instead of the terminal.
    """
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the parent handles Ctrl-C
    if log_path:
        descriptor = os.open(log_path, os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o644)
        os.dup2(descriptor, 1)
        os.dup2(descriptor, 2)
        os.close(descriptor)

    def terminate(signum: int, frame: Any) -> None:
        raise SystemExit(0)  # runs the registry's finally blocks, which kill its children

    signal.signal(signal.SIGTERM, terminate)
    while True:
        try:
            message = connection.recv()
        except EOFError:
            return
        if message is None:
            return
        key, fn, args = message
        try:
            reply = (key, True, fn(*args))
        except Exception as error:  # noqa: BLE001
            reply = (key, False, f"{type(error).__name__}: {error}")
        connection.send(reply)


class LocalPool:
    """``jobs`` worker processes, one task each at a time, with crash and hang recovery.

    A task is ``(key, fn, args, watchdog_seconds)``. A worker that dies while running a task
    yields a failed :class:`TaskResult` for that task only and is replaced; one that does not
    answer within the watchdog is killed (its task fails with ``timeout``) and replaced.
    Solver output of the workers goes to ``log_path`` when given.
    """

    def __init__(self, jobs: int, log_path: str | Path | None = None) -> None:
        if jobs < 1:
            raise InputError(f"jobs must be >= 1, got {jobs}")
        self.jobs = jobs
        self.log_path = str(log_path) if log_path else None
        method = "fork" if "fork" in multiprocessing.get_all_start_methods() else "spawn"
        self.context: Any = multiprocessing.get_context(method)
        self.workers: list[dict[str, Any]] = []

    def _start(self) -> dict[str, Any]:
        """A new worker process and the parent's end of its pipe."""
        parent, child = self.context.Pipe(duplex=True)
        process = self.context.Process(target=worker_main, args=(child, self.log_path),
                                       daemon=False)
        process.start()
        child.close()
        return {"process": process, "conn": parent, "task": None, "since": 0.0}

    def _stop(self, worker: dict[str, Any], force: bool = False) -> None:
        """End a worker: ask it to stop (unless ``force``), then terminate, then kill."""
        process = worker["process"]
        if not force:
            with contextlib.suppress(OSError):
                worker["conn"].send(None)
            process.join(2)
        if process.is_alive():
            process.terminate()
            process.join(5)
        if process.is_alive():
            process.kill()
            process.join(5)
        worker["conn"].close()

    def share(self, value: Any) -> Any:
        """``value`` itself: forked workers receive it with each task."""
        return value

    def run(self, tasks: Iterable[Task]) -> Iterator[TaskResult]:
        """Run tasks, yielding results as they finish (in completion order)."""
        pending = list(tasks)
        pending.reverse()
        try:
            while len(self.workers) < min(self.jobs, len(pending)):
                self.workers.append(self._start())
            while pending or any(w["task"] is not None for w in self.workers):
                for index, worker in enumerate(self.workers):
                    if worker["task"] is None and pending:
                        if not worker["process"].is_alive():
                            self._stop(worker, force=True)
                            worker = self.workers[index] = self._start()
                        task = pending.pop()
                        key, fn, args, _ = task
                        try:
                            worker["conn"].send((key, fn, args))
                        except (OSError, ValueError) as error:
                            yield TaskResult(key, False, failure=Failure.ERROR,
                                             reason=f"cannot send the task: {error}")
                            continue
                        worker["task"], worker["since"] = task, time.monotonic()
                busy = [w for w in self.workers if w["task"] is not None]
                if not busy:
                    continue
                waitables: list[Any] = [w["conn"] for w in busy]
                waitables += [w["process"].sentinel for w in busy]
                deadline = min(w["since"] + w["task"][3] for w in busy)
                ready = wait_connections(waitables, timeout=max(0.0, deadline
                                                                - time.monotonic()) + 0.05)
                for index, worker in enumerate(self.workers):
                    task = worker["task"]
                    if task is None:
                        continue
                    key = task[0]
                    outcome: TaskResult | None = None
                    if worker["conn"] in ready or worker["process"].sentinel in ready:
                        try:
                            if worker["conn"].poll():
                                _, ok, value = worker["conn"].recv()
                                outcome = (TaskResult(key, True, value) if ok else
                                           TaskResult(key, False, failure=Failure.ERROR,
                                                      reason=f"worker raised {value}"))
                        except (EOFError, OSError):
                            outcome = None
                        if outcome is None and not worker["process"].is_alive():
                            code = worker["process"].exitcode
                            outcome = TaskResult(key, False, failure=Failure.ERROR,
                                                 reason=f"worker process died (exit code "
                                                        f"{code}) while running this cell")
                            self._stop(worker, force=True)
                            self.workers[index] = self._start()
                    elif time.monotonic() - worker["since"] > task[3]:
                        outcome = TaskResult(key, False, failure=Failure.TIMEOUT,
                                             reason=f"worker did not answer within "
                                                    f"{task[3]:g} s; worker killed")
                        self._stop(worker, force=True)
                        self.workers[index] = self._start()
                    if outcome is not None:
                        self.workers[index]["task"] = None
                        yield outcome
        finally:
            self.close()

    def close(self) -> None:
        """Stop every worker (killing those still busy)."""
        for worker in self.workers:
            self._stop(worker, force=worker["task"] is not None)
        self.workers = []


class DaskPool:
    """Tasks on a Dask distributed cluster (``Client(address)``), same interface."""

    def __init__(self, address: str) -> None:
        """Connect to the scheduler at ``address`` (for example ``tcp://host:8786``)."""
        from distributed import Client

        self.client = Client(address)

    def share(self, value: Any) -> Any:
        """Scatter ``value`` to the cluster once; tasks receive the future."""
        return self.client.scatter(value, broadcast=False, hash=False)

    def run(self, tasks: Iterable[Task]) -> Iterator[TaskResult]:
        """Submit every task, then yield results as they finish (watchdogs unused)."""
        from distributed import as_completed

        futures: dict[Any, Any] = {}
        try:
            for index, (key, fn, args, _) in enumerate(tasks):
                future = self.client.submit(fn, *args, pure=False, retries=0,
                                            key=f"c3bench-{os.getpid()}-{index}-{time.time_ns()}")
                futures[future.key] = (key, future)
            for future in as_completed([f for _, f in futures.values()]):
                key = futures[future.key][0]
                try:
                    value = future.result()
                except Exception as error:  # noqa: BLE001 - e.g. KilledWorker
                    yield TaskResult(key, False, failure=Failure.ERROR,
                                     reason=f"dask task failed: {type(error).__name__}: "
                                            f"{error}")
                else:
                    yield TaskResult(key, True, value)
                future.release()
        finally:
            pending = [f for _, f in futures.values() if not f.done()]
            if pending:
                self.client.cancel(pending)

    def close(self) -> None:
        """Disconnect from the cluster."""
        self.client.close()
