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

Small dense linear algebra on a 2-core machine runs fastest on one BLAS thread (a 136x80
Schur solve was 30x slower with multi-threaded OpenBLAS), so every timed solve runs inside
:func:`single_thread_blas`.
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import Iterator

import numpy  # noqa: F401 - load numpy's BLAS before limiting thread pools
import scipy.linalg  # noqa: F401 - and SciPy's (its own OpenBLAS), see single_thread_blas
from threadpoolctl import threadpool_limits

SETUP = "setup"
"""Lap name of the setup phase (:class:`Stopwatch`)."""
SOLVE = "solve"
"""Lap name of the solve phase."""


def total_time(setup_time: float, solve_time: float) -> float:
    """What a caller pays for one solve under the contract: ``setup_time + solve_time``."""
    return float(setup_time) + float(solve_time)


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
