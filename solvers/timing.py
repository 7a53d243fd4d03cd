"""The one timing helper: monotonic wall-clock stopwatch and one-thread BLAS pinning.

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
