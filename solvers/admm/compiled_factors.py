"""Where the compiled C3+ kernel keeps its factorisations (:mod:`.compiled`).

:class:`CompiledFactors` holds the factors of a group of rho values for every sample in
preallocated arrays, samples on the last axis; :func:`plan_group` says how many planned rho
values are factorised together; :func:`rho_key` keys plans and caches by the rho values.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from c3bench.problems.names import Block
from c3bench.solvers.admm import compiled_kernels as kernels

__all__ = ["CompiledFactors", "factor_failure", "plan_group", "rho_key"]


@dataclass
class CompiledFactors:
    """Factorisations of ``m`` rho values for ``n`` samples (:func:`kernels.factorize_batch`).

    ``Y`` (m, T, nv, nx, n) = ``L^-1 Q_vx``, ``L`` (m, T, nv, nv, n) lower Cholesky factors of
    ``Q_vv``, ``Sd`` (m, T, nx, n), ``D`` (m, ny, n), ``ABd`` (m, nx, ny + 1, n) the scaled
    ``[A B_v d]`` (samples last: from :data:`~c3bench.solvers.admm.compiled_passes.LANE_SOLVE`
    samples on, the linear passes work the samples as vector lanes);
    ``failed`` (m, n): -1 or the time step whose Cholesky factorisation failed.
    """

    Y: np.ndarray
    L: np.ndarray
    Sd: np.ndarray
    D: np.ndarray
    ABd: np.ndarray
    failed: np.ndarray

    @classmethod
    def empty(cls, m: int, n: int, T: int, nx: int, nv: int, dtype: np.dtype[Any]
              ) -> CompiledFactors:
        return cls(Y=np.empty((m, T, nv, nx, n), dtype), L=np.zeros((m, T, nv, nv, n), dtype),
                   Sd=np.empty((m, T, nx, n), dtype), D=np.empty((m, nx + nv, n), dtype),
                   ABd=np.empty((m, nx, nx + nv + 1, n), dtype),
                   failed=np.full((m, n), -1, np.int64))

    @property
    def shape(self) -> tuple[int, ...]:
        """``(m, n, T)``."""
        return (self.Y.shape[0], self.Y.shape[4], self.Y.shape[1])


def plan_group(samples: int, planned: int) -> int:
    """How many planned rho values are factorised together: enough for a full block of
    :data:`~c3bench.solvers.admm.compiled_kernels.LANE_BLOCK` lanes (rho x sample pairs),
    no more, so that one group's factors stay in the core's cache until the iterations
    that use them (measured at 16 samples: factorising 2 rho values before their two
    iterations is 10 % faster than factorising all 10 up front; at 64 samples one at a
    time is 17 % faster; at 1 sample all 10 together is 2-3 times faster than fewer)."""
    return min(planned, max(1, -(-kernels.LANE_BLOCK // samples)))


def rho_key(rho: Mapping[str, float]) -> tuple[float, ...]:
    """The four rho values in :data:`BLOCKS` order (plan and cache key)."""
    return (float(rho[Block.X]), float(rho[Block.LAM]), float(rho[Block.U]),
            float(rho[Block.ETA]))


def factor_failure(factors: CompiledFactors, slot: int, rho: Mapping[str, float]) -> str | None:
    """Why ``slot``'s factorisation failed (the first failed sample), or ``None``."""
    failed = factors.failed[slot]
    if failed.max() < 0:
        return None
    j = int(np.argmax(failed >= 0))
    return (f"Q_vv not positive definite (Cholesky) for sample {j} at step {int(failed[j])}, "
            f"rho={dict(rho)}")
