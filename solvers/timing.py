"""The one timing contract, its stopwatch, and one-thread BLAS pinning.

Timing contract (every backend follows it; each adapter's docstring states its split)
----------------------------------------------------------------------------------------
A backend's :meth:`~c3bench.solvers.base.Backend.solve` reports two wall-clock laps of one
call, measured with :class:`Stopwatch` under the lap names :data:`SETUP` and :data:`SOLVE`:

* **setup** (``Result.setup_time``): everything that depends on the matrices and must be
  redone when they change: converting the data (dtype casts, sparse formats, stacking the
  constraints, a modelling layer's canonicalisation), structure analysis (symbolic
  factorisation, sparsity patterns), numeric factorisation of the KKT or Schur matrix, and
  constructing the solver object (including its own setup call, e.g. ``osqp.setup``);
* **solve** (``Result.solve_time``): the rest of the call: the iterations (or the
  back-substitution of a direct method), the solver's own solve call, reading the solution
  and duals out (and an in-solver polish).

The ``objective`` and residuals computed afterwards by the benchmark are in neither. Within
one C3 / C3+ step the QP matrices change with ``rho`` at every ADMM iteration, so a controller
pays both: the benchmark ranks by :func:`total_time` (``setup + solve``), which makes the
split a description, never an advantage. Where a solver's own call does setup and solve
together and reports no split, the whole call is solve and the docstring says so.

Warm cells: what a solver pays when only the vectors change
-------------------------------------------------------------
A ``cold`` cell times :meth:`~c3bench.solvers.base.Backend.solve` as above: a fresh solver
object per call, so ``total_time`` is everything. A ``warm`` cell (a warm start is given: the
reference solution of the previous iterate of the instance's ADMM sequence,
:mod:`c3bench.bench.planning`) answers "what does this solver cost when only ``q``, ``b``,
``h`` and the bounds change, the matrices staying": a controller that keeps its solver object
between solves pays that. A backend that has an update API implements
:class:`UpdatableBackend`; :func:`warm_solve` then

1. calls ``prepare(problem, settings)`` **untimed**: the solver object set up on the
   instance's matrices (conversion, scaling, factorisation, construction), as it was left
   by a controller's previous solve with the same matrices;
2. times ``resolve(prepared, problem, settings, warm_start)``, whose **setup** lap is the
   solver's own update call with the instance's vectors (``q``, ``b``, ``h``, bounds) and
   the initial guess, and whose **solve** lap is the solve from that guess.

So a warm row's ``setup_time`` is the update time, never the construction, and its
``total_time`` (update + solve) is what the benchmark ranks warm cells by. Each backend's
``warm_support`` says what its update covers. A backend without an update API (or whose
binding hides it) pays a full ``solve`` with the initial guess in warm cells too ("warm
emulated": its ``total_time`` includes construction, as in a cold cell); the diagnostics key
:data:`WARM_UPDATE` of a result says which happened (1 update API, 0 emulated).

Small dense linear algebra on a 2-core machine runs fastest on one BLAS thread (a 136x80
Schur solve was 30x slower with multi-threaded OpenBLAS), so every timed solve runs inside
:func:`single_thread_blas`.
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import Iterator
from typing import TYPE_CHECKING, Any, Protocol, runtime_checkable

import numpy  # noqa: F401 - load numpy's BLAS before limiting thread pools
import scipy.linalg  # noqa: F401 - and SciPy's (its own OpenBLAS), see single_thread_blas
from threadpoolctl import threadpool_limits

if TYPE_CHECKING:
    from c3bench.problems.instance import Problem
    from c3bench.solvers.base import Backend, Result, Settings, WarmStart

SETUP = "setup"
"""Lap name of the setup phase (:class:`Stopwatch`)."""
SOLVE = "solve"
"""Lap name of the solve phase."""


WARM_UPDATE = "warm_update"
"""Diagnostics key of a warm solve: 1.0 when it went through the solver's update API
(:class:`UpdatableBackend`), 0.0 when it was emulated by a full solve with the initial guess."""
WARM_EMULATED = ("emulated: c3bench drives this solver without an update API, so a warm cell "
                 "pays setup + solve with the initial guess, as a cold one does")
"""``warm_support`` of a backend that is not an :class:`UpdatableBackend`."""


def total_time(setup_time: float, solve_time: float) -> float:
    """What a caller pays for one solve under the contract: ``setup_time + solve_time``."""
    return float(setup_time) + float(solve_time)


@runtime_checkable
class UpdatableBackend(Protocol):
    """A backend whose solver object takes new vectors through its own update API (the
    warm-cell contract of this module's docstring)."""

    warm_support: str
    """One line: the update call and what the initial guess sets."""

    def prepare(self, problem: Problem, settings: Settings) -> Any:
        """The solver object set up on ``problem``'s matrices (untimed in a warm cell)."""

    def resolve(self, prepared: Any, problem: Problem, settings: Settings,
                warm_start: WarmStart | None) -> Result:
        """Update ``prepared`` with ``problem``'s vectors and the initial guess (lap
        :data:`SETUP`), then solve (lap :data:`SOLVE`)."""


def warm_support(backend: Backend) -> str:
    """What a warm cell of ``backend`` measures: its ``warm_support`` line (a backend without
    an update API may still say why it has none), or :data:`WARM_EMULATED`."""
    note = getattr(backend, "warm_support", None)
    return note if isinstance(note, str) and note else WARM_EMULATED


def warm_solve(backend: Backend, problem: Problem, settings: Settings,
               warm_start: WarmStart | None) -> Result:
    """One warm solve under the contract: ``prepare`` untimed, then ``resolve`` timed
    (update = setup lap, solve = solve lap); a full ``solve`` with the initial guess for a
    backend without an update API. ``diagnostics[WARM_UPDATE]`` says which."""
    if isinstance(backend, UpdatableBackend):
        result = backend.resolve(backend.prepare(problem, settings), problem, settings,
                                 warm_start)
        result.diagnostics[WARM_UPDATE] = 1.0
    else:
        result = backend.solve(problem, settings, warm_start)
        result.diagnostics[WARM_UPDATE] = 0.0
    return result


class Stopwatch:
    """Accumulates named laps: ``with watch.lap("solve"): ...``; ``watch.laps["solve"]``."""

    def __init__(self) -> None:
        self.laps: dict[str, float] = {}

    @contextlib.contextmanager
    def lap(self, name: str) -> Iterator[None]:
        start = time.perf_counter()
        try:
            yield
        finally:
            self.laps[name] = self.laps.get(name, 0.0) + time.perf_counter() - start

    def get(self, name: str) -> float:
        return self.laps.get(name, 0.0)


@contextlib.contextmanager
def single_thread_blas() -> Iterator[None]:
    """Pin BLAS/OpenMP thread pools to one thread inside the block.

    threadpoolctl limits only the libraries already loaded when the block is entered; SciPy
    ships its own OpenBLAS, loaded with ``scipy.linalg``, so this module imports it first (a
    late import left SciPy's Cholesky multi-threaded and 30x slower under load).
    """
    with threadpool_limits(limits=1):
        yield


def blas_threads() -> int:
    """Threads the BLAS library currently uses (for reports)."""
    from threadpoolctl import threadpool_info

    counts = [pool.get("num_threads", 1) for pool in threadpool_info()
              if pool.get("user_api") == "blas"]
    return max(counts) if counts else 1
