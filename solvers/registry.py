"""Registry of solver backends and the guarded, in-process ``solve``.

Backends are found, not listed: every module of :mod:`c3bench.solvers.backends` is imported
once, on first use (:func:`backend_modules`; modules whose name starts with ``_`` are helpers
and skipped), and registers its backends on import with :func:`register`. A module that fails
to import is recorded (:func:`module_errors`), never raised. Plugins outside the package
register the same way (:func:`import_plugins`; :func:`loaded_plugins` lists them so that an
isolated child can load them again).

:func:`solve` is where a solve is guarded, once for all backends: :func:`admit` checks that
the backend is known, installed, takes the family (an ``accepts()`` that raises is a recorded
error, not a silent refusal) and the precision, and validates the instance (finite data,
symmetric positive semi-definite ``P``); :func:`guarded` turns any exception into a recorded
failure (:class:`~c3bench.problems.errors.BackendUnavailable` raised while solving is a
``Failure.UNAVAILABLE`` row); :func:`finish` rejects non-finite answers and fills the
objective. It runs in the calling process, with no time limit: the controllers and the tests
use it. Warm-up, repeats, BLAS pinning and the child process killed on overrun are
:mod:`c3bench.solvers.isolation`'s job, which reuses these three steps.
"""

from __future__ import annotations

import importlib
import pkgutil
import traceback
from collections.abc import Callable, Iterable
from dataclasses import dataclass

import numpy as np

from c3bench.problems.errors import BackendUnavailable
from c3bench.problems.instance import Problem
from c3bench.problems.names import Failure, Family, Precision
from c3bench.solvers.base import Backend, Result, Settings, WarmStart

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
        try:
            ok, reason = backend.availability()
        except Exception as error:  # noqa: BLE001 - a broken check makes it unavailable
            ok, reason = False, f"availability check raised {type(error).__name__}: {error}"
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


def admit(name: str, problem: Problem, settings: Settings,
          check: bool = True) -> Backend | Result:
    """The backend called ``name`` when it may solve ``problem``, else the failure ``Result``.

    In order: known name, availability, ``accepts(problem)`` (one that raises is an explicit
    ``Failure.ERROR``, never a silent refusal), precision, and (with ``check``) a well-posed
    instance (:func:`check_problem`).
    """
    try:
        backend = get(name)
    except KeyError as error:
        return Result.failed(name, problem.name, Failure.UNAVAILABLE, str(error.args[0]))
    try:
        ok, reason = backend.availability()
    except Exception as error:  # noqa: BLE001 - a broken check is a recorded failure
        return Result.failed(name, problem.name, Failure.ERROR,
                             f"availability check raised {type(error).__name__}: {error}")
    if not ok:
        return Result.failed(name, problem.name, Failure.UNAVAILABLE, reason)
    try:
        accepted, reason = backend.accepts(problem)
    except Exception as error:  # noqa: BLE001 - a broken accepts() is a recorded failure
        return Result.failed(name, problem.name, Failure.ERROR,
                             f"accepts() raised {type(error).__name__}: {error}")
    if not accepted:
        return Result.failed(name, problem.name, Failure.UNSUPPORTED, reason)
    if settings.precision not in backend.precisions:
        return Result.failed(name, problem.name, Failure.UNSUPPORTED,
                             f"{name} does not run in {settings.precision}")
    reason = check_problem(problem) if check else ""
    if reason:
        return Result.failed(name, problem.name, Failure.INVALID_INPUT, reason)
    return backend


def guarded(name: str, problem: Problem, call: Callable[[], Result]) -> Result:
    """``call()``, with an exception turned into a failure ``Result``: a
    :class:`~c3bench.problems.errors.BackendUnavailable` (found out only while solving, e.g. a
    licence limit) is ``Failure.UNAVAILABLE``, any other ``Failure.ERROR`` with the message and
    the innermost frames of the traceback. A call that returns no ``Result`` is an error too.
    """
    try:
        result = call()
    except BackendUnavailable as error:
        return Result.failed(name, problem.name, Failure.UNAVAILABLE, str(error))
    except Exception as error:  # noqa: BLE001 - recorded, never raised
        frames = traceback.format_exc(limit=-4)
        return Result.failed(name, problem.name, Failure.ERROR,
                             f"{type(error).__name__}: {error}\n{frames}".strip())
    if not isinstance(result, Result):
        return Result.failed(name, problem.name, Failure.ERROR,
                             f"solver returned {type(result).__name__}, not a Result")
    return result


def finish(result: Result, problem: Problem) -> Result:
    """Reject a claimed solution that is missing or non-finite; fill the objective."""
    if result.found:
        if result.x is None or np.shape(result.x) != (problem.n,):
            return Result.failed(result.solver, problem.name, Failure.NON_FINITE,
                                 f"solver reported success but returned no solution of "
                                 f"size {problem.n}", iterations=result.iterations,
                                 setup_time=result.setup_time, solve_time=result.solve_time)
        if not np.all(np.isfinite(result.x)):
            return Result.failed(result.solver, problem.name, Failure.NON_FINITE,
                                 "solver returned a non-finite solution",
                                 iterations=result.iterations, setup_time=result.setup_time,
                                 solve_time=result.solve_time, x=np.asarray(result.x))
    if result.x is not None and result.objective is None and np.all(np.isfinite(result.x)):
        result.objective = problem.objective(result.x)
    return result


def solve(name: str, problem: Problem, settings: Settings | None = None,
          warm_start: WarmStart | None = None, check: bool = True) -> Result:
    """Solve ``problem`` with backend ``name`` in this process; never raises for a solver's
    misbehaviour.

    No child process, no thread and no time limit: a solver that hangs hangs the caller. The
    benchmark solves through :func:`c3bench.solvers.isolation.solve_isolated` (warm-up,
    repeats, a killed child on overrun); controllers and tests call this directly.

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
    check
        Validate the instance first (finiteness, symmetric PSD ``P``: an eigen-decomposition).
        Callers that built the instance themselves in a hot loop may skip it.

    Returns
    -------
    Result
        The backend's result, or a failure: ``unavailable`` (unknown name, missing package,
        or :class:`~c3bench.problems.errors.BackendUnavailable` raised while solving),
        ``unsupported`` (family or precision), ``invalid_input``, ``error`` (an exception,
        including one from ``accepts()``), ``non_finite`` (a claimed solution that is not
        finite).
    """
    settings = settings or Settings()
    admitted = admit(name, problem, settings, check)
    if isinstance(admitted, Result):
        return admitted
    backend = admitted
    return finish(guarded(name, problem, lambda: backend.solve(problem, settings, warm_start)),
                  problem)


_PLUGINS_LOADED: dict[str, None] = {}
"""Plugin entries loaded in this process, in loading order (a dict as an ordered set)."""


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
        _PLUGINS_LOADED[entry] = None


def loaded_plugins() -> tuple[str, ...]:
    """The plugin entries loaded in this process, in order (an isolated child replays
    them before it solves)."""
    return tuple(_PLUGINS_LOADED)
