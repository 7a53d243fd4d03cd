"""Registry of solver backends and the guarded ``solve`` every caller goes through.

Backends are found, not listed: every module of :mod:`c3bench.solvers.backends` is imported
once, on first use (:func:`backend_modules`; modules whose name starts with ``_`` are helpers
and skipped), and registers its backends on import with :func:`register`. A module that fails
to import is recorded (:func:`module_errors`), never raised. Plugins outside the package
register the same way (:func:`import_plugins`).

``solve`` is where robustness lives, once for all backends: it validates the instance (finite
data, symmetric positive semi-definite ``P``), checks that the backend is installed and takes
the family and precision, runs the backend in a forked child process under a wall-clock limit
(killed when it overruns), turns any exception or crash into a recorded failure, and rejects
non-finite answers. A backend that raises
:class:`~c3bench.problems.errors.BackendUnavailable` (from ``require`` or while solving) is a
``Failure.UNAVAILABLE`` row. Warm-up and repeats happen inside the same child, with BLAS
pinned to one thread, so timings exclude process start and first-call costs.
"""

from __future__ import annotations

import importlib
import multiprocessing
import pkgutil
import statistics
import threading
import time
import traceback
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import Any

import numpy as np

from c3bench.problems.errors import BackendUnavailable
from c3bench.problems.instance import Problem
from c3bench.problems.names import Failure, Family, Precision
from c3bench.solvers.base import Backend, Result, Settings, WarmStart
from c3bench.solvers.timing import single_thread_blas

BACKEND_PACKAGE = "c3bench.solvers.backends"
"""The package whose modules define the backends (each registers its own on import)."""

_BACKENDS: dict[str, Backend] = {}
_MODULE_ERRORS: dict[str, str] = {}
_LOADED = False


def register(backend: Backend) -> Backend:
    """Add a backend instance to the registry (its ``name`` must be new)."""
    if not backend.name:
        raise ValueError("a backend needs a name")
    if backend.name in _BACKENDS and type(_BACKENDS[backend.name]) is not type(backend):
        raise ValueError(f"backend {backend.name!r} is registered twice")
    _BACKENDS[backend.name] = backend
    return backend


def backend_modules() -> tuple[str, ...]:
    """Every module of :data:`BACKEND_PACKAGE` (sorted; names starting with ``_`` skipped)."""
    package = importlib.import_module(BACKEND_PACKAGE)
    return tuple(f"{BACKEND_PACKAGE}.{info.name}"
                 for info in sorted(pkgutil.iter_modules(package.__path__),
                                    key=lambda info: info.name)
                 if not info.name.startswith("_"))


def _load() -> None:
    global _LOADED
    if _LOADED:
        return
    _LOADED = True
    for module in backend_modules():
        try:
            importlib.import_module(module)
        except Exception as error:  # noqa: BLE001 - recorded, never raised
            _MODULE_ERRORS[module] = f"{type(error).__name__}: {error}"


def backends() -> dict[str, Backend]:
    """All registered backends by name."""
    _load()
    return dict(sorted(_BACKENDS.items()))


def get(name: str) -> Backend:
    """The backend called ``name``; ``KeyError`` lists the known names."""
    known = backends()
    if name not in known:
        raise KeyError(f"unknown solver {name!r}; known: {', '.join(known)}")
    return known[name]


@dataclass
class BackendInfo:
    """One row of the registry table."""

    name: str
    available: bool
    reason: str
    version: str
    families: tuple[Family, ...]
    precisions: tuple[Precision, ...]
    description: str


def available() -> list[BackendInfo]:
    """Every backend with availability (the reason of a
    :class:`~c3bench.problems.errors.BackendUnavailable` when not), version and accepted
    families."""
    rows = []
    for name, backend in backends().items():
        ok, reason = backend.availability()
        try:
            version = backend.version() if ok else "-"
        except Exception as error:  # noqa: BLE001 - recorded, never raised
            version = f"unknown ({error})"
        rows.append(BackendInfo(name, ok, reason, version, backend.families,
                                backend.precisions, backend.description))
    return rows


def module_errors() -> dict[str, str]:
    """Backend modules that failed to import, with the error."""
    _load()
    return dict(_MODULE_ERRORS)


def check_problem(problem: Problem) -> str:
    """``""`` when ``problem`` is well posed for a convex solver, else the reason.

    Checks finiteness and shapes (``Problem.validate``) and that ``P`` is positive
    semi-definite: ``lambda_min(P) >= -1e-8 max(1, ||P||)``.
    """
    try:
        problem.validate()
    except ValueError as error:
        return str(error)
    if problem.n == 0:
        return "problem has no variables"
    eigenvalues = np.linalg.eigvalsh(problem.P)
    scale = max(1.0, float(np.max(np.abs(eigenvalues), initial=0.0)))
    if eigenvalues[0] < -1e-8 * scale:
        return (f"P is not positive semi-definite (smallest eigenvalue "
                f"{eigenvalues[0]:.3g})")
    return ""


def _finish(result: Result, problem: Problem) -> Result:
    """Reject non-finite answers and fill the objective."""
    if result.found:
        if result.x is None or np.shape(result.x) != (problem.n,):
            return Result.failed(result.solver, problem.name, Failure.NON_FINITE,
                                 f"solver reported success but returned no solution of "
                                 f"size {problem.n}", iterations=result.iterations,
                                 build_time=result.build_time, solve_time=result.solve_time)
        if not np.all(np.isfinite(result.x)):
            return Result.failed(result.solver, problem.name, Failure.NON_FINITE,
                                 "solver returned a non-finite solution",
                                 iterations=result.iterations, build_time=result.build_time,
                                 solve_time=result.solve_time, x=np.asarray(result.x))
    if result.x is not None and result.objective is None and np.all(np.isfinite(result.x)):
        result.objective = problem.objective(result.x)
    return result


SLOW_SOLVE_SECONDS = 1.0
"""A solve slower than this is timed once after the warm-up: repeats add little accuracy."""

Notify = Callable[[int], None]


def _run_repeats(backend: Backend, problem: Problem, settings: Settings,
                 warm_start: WarmStart | None, repeats: int, warmup: bool,
                 notify: Notify | None = None) -> Result:
    """Warm-up (untimed) then ``repeats`` solves; times are the medians.

    When the warm-up took longer than :data:`SLOW_SOLVE_SECONDS` one timed solve is made.
    ``notify(n)`` is told, after the warm-up, how many timed solves follow (so a watcher can
    give each its own time limit).
    """
    with single_thread_blas():
        if warmup:
            start = time.perf_counter()
            backend.solve(problem, settings, warm_start)
            if time.perf_counter() - start > SLOW_SOLVE_SECONDS:
                repeats = 1
        if notify is not None:
            notify(repeats)
        results = [backend.solve(problem, settings, warm_start) for _ in range(repeats)]
    result = results[-1]
    if repeats > 1:
        result.build_time = statistics.median(r.build_time for r in results)
        result.solve_time = statistics.median(r.solve_time for r in results)
    result.diagnostics.setdefault("timed_repeats", float(repeats))
    return result


Call = Callable[[Notify | None], Result]


def _child(connection: Any, call: Call) -> None:
    def notify(repeats: int) -> None:
        connection.send(("warm", repeats))

    try:
        outcome: tuple[str, Any] = ("ok", call(notify))
    except BaseException as error:  # noqa: BLE001 - recorded, never raised
        outcome = ("error", f"{type(error).__name__}: {error}\n{traceback.format_exc(limit=4)}")
    try:
        connection.send(outcome)
    finally:
        connection.close()


def _isolated(call: Call, time_limit: float, solver: str, problem: str) -> Result:
    """Run ``call`` in a forked child; kill it when a solve overruns ``time_limit`` seconds.

    The first solve (the warm-up) gets ``time_limit``; once the child reports it done, the
    ``n`` timed solves get ``n * time_limit`` together.
    """
    context = multiprocessing.get_context("fork")
    receiver, sender = context.Pipe(duplex=False)
    try:
        process = context.Process(target=_child, args=(sender, call), daemon=True)
        process.start()
    except AssertionError:
        # daemonic workers may not fork children: fall back to a watched thread
        return _threaded(call, time_limit * 4, solver, problem)
    sender.close()
    deadline = time.monotonic() + time_limit
    kind, payload = "timeout", None
    try:
        while True:
            remaining = deadline - time.monotonic()
            if remaining <= 0 or not receiver.poll(remaining):
                kind, payload = "timeout", None
                break
            try:
                kind, payload = receiver.recv()
            except EOFError:
                kind, payload = "crash", None
                break
            if kind != "warm":
                break
            deadline = time.monotonic() + time_limit * int(payload)
    finally:
        receiver.close()
        if process.is_alive():
            process.kill()
        process.join(5)
    if kind == "ok" and isinstance(payload, Result):
        return payload
    if kind == "timeout":
        return Result.failed(solver, problem, Failure.TIMEOUT,
                             f"time limit of {time_limit:g} s exceeded; process killed",
                             solve_time=time_limit)
    if kind == "crash":
        return Result.failed(solver, problem, Failure.ERROR,
                             f"solver process died (exit code {process.exitcode})")
    return Result.failed(solver, problem, Failure.ERROR, str(payload).strip())


def _threaded(call: Call, time_limit: float, solver: str, problem: str) -> Result:
    """Run ``call`` in a watched thread; abandon it after ``time_limit`` seconds in all."""
    box: dict[str, Any] = {}

    def target() -> None:
        try:
            box["result"] = call(None)
        except BaseException as error:  # noqa: BLE001 - recorded, never raised
            box["error"] = f"{type(error).__name__}: {error}"

    thread = threading.Thread(target=target, daemon=True)
    thread.start()
    thread.join(time_limit)
    if thread.is_alive():
        return Result.failed(solver, problem, Failure.TIMEOUT,
                             f"time limit of {time_limit:g} s exceeded (thread abandoned)",
                             solve_time=time_limit)
    result = box.get("result")
    if not isinstance(result, Result):
        return Result.failed(solver, problem, Failure.ERROR,
                             str(box.get("error", "solver returned no Result")))
    return result


def solve(name: str, problem: Problem, settings: Settings | None = None,
          warm_start: WarmStart | None = None, repeats: int = 1, warmup: bool = False,
          isolate: bool = True, check: bool = True) -> Result:
    """Solve ``problem`` with backend ``name``; never raises for a solver's misbehaviour.

    Parameters
    ----------
    name
        Registry name.
    problem
        The instance.
    settings
        Profile, tolerance, time limit, precision (default profile when ``None``).
    warm_start
        Initial guess passed to the backend.
    repeats, warmup
        Timed repeats (median reported) after an optional untimed warm-up solve.
    isolate
        Run in a child process with the time limit enforced by killing it (default). With
        ``False`` the solve runs in this process and the limit is enforced by abandoning a
        watcher thread.
    check
        Validate the instance first (finiteness, symmetric PSD ``P``: an eigen-decomposition).
        Callers that built the instance themselves in a hot loop may skip it.
    """
    settings = settings or Settings()
    if repeats < 1:
        raise ValueError(f"repeats must be >= 1, got {repeats}")
    try:
        backend = get(name)
    except KeyError as error:
        return Result.failed(name, problem.name, Failure.UNAVAILABLE, str(error.args[0]))
    ok, reason = backend.availability()
    if not ok:
        return Result.failed(name, problem.name, Failure.UNAVAILABLE, reason)
    accepted, reason = backend.accepts(problem)
    if not accepted:
        return Result.failed(name, problem.name, Failure.UNSUPPORTED, reason)
    if settings.precision not in backend.precisions:
        return Result.failed(name, problem.name, Failure.UNSUPPORTED,
                             f"{name} does not run in {settings.precision}")
    reason = check_problem(problem) if check else ""
    if reason:
        return Result.failed(name, problem.name, Failure.INVALID_INPUT, reason)

    def call(notify: Notify | None) -> Result:
        try:
            return _run_repeats(backend, problem, settings, warm_start, repeats, warmup,
                                notify)
        except BackendUnavailable as error:  # found out only while solving (e.g. a licence)
            return Result.failed(name, problem.name, Failure.UNAVAILABLE, str(error))

    if isolate:
        result = _isolated(call, settings.time_limit, name, problem.name)
    else:
        budget = settings.time_limit * (repeats + (1 if warmup else 0))
        result = _threaded(call, budget, name, problem.name)
    return _finish(result, problem)


_PLUGINS_LOADED: set[str] = set()


def import_plugins(entries: Iterable[str]) -> None:
    """Load plugins in this process, once each: ``module`` (imported; registering backends
    at import) or ``module:function`` (imported, then ``function()`` called)."""
    for entry in entries:
        if entry in _PLUGINS_LOADED:
            continue
        module, _, function = entry.partition(":")
        loaded = importlib.import_module(module)
        if function:
            getattr(loaded, function)()
        _PLUGINS_LOADED.add(entry)
