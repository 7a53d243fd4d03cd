"""Where the compiled C3+ kernel keeps its factorisations (:mod:`.compiled`).

:class:`CompiledFactors` holds the factors of a group of rho values for every sample in
preallocated arrays, (rho, sample) lanes on the last axis; :func:`plan_group` says how many
planned rho values are factorised together; :func:`rho_key` keys plans and caches by the rho values.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from c3bench.problems.names import Block
from c3bench.solvers.admm import compiled_kernels as kernels

__all__ = ["ALIGNMENT", "CompiledFactors", "aligned_empty", "factor_failure", "plan_group",
           "rho_key"]

ALIGNMENT = 64
"""Bytes: the arrays the generated code reads start on a cache line (:func:`aligned_empty`)."""


def aligned_empty(shape: tuple[int, ...], dtype: Any, fill: float | None = None) -> np.ndarray:
    """An array of ``shape`` whose data starts on a :data:`ALIGNMENT`-byte boundary (filled
    with ``fill`` when given), for the arrays that numpy allocates and the generated code
    (:mod:`.compiled_ir`, :mod:`.compiled_passes_codegen`) reads: numpy aligns to 16 bytes,
    so with 16 lanes per entry every other four-lane (32-byte) load of such an array crosses
    a cache line (numba's own arrays start on 32 bytes). Measured on the generated backward
    step (znver3, 16 lanes): ``ABd`` on 16 bytes, as numpy had allocated it, 1.21 against
    1.19 us per four lanes; all six of its arrays on 16 bytes 1.51."""
    dtype = np.dtype(dtype)
    count = math.prod(shape)
    raw = np.empty(count * dtype.itemsize + ALIGNMENT, np.uint8)
    start = -int(raw.ctypes.data) % ALIGNMENT
    array: np.ndarray = raw[start:start + count * dtype.itemsize].view(dtype).reshape(shape)
    if fill is not None:
        array.fill(fill)
    return array


@dataclass
class CompiledFactors:
    """Factorisations of ``m`` rho values (*slots*) for ``n`` samples
    (:func:`kernels.factorize_batch`), every array with the *lane* ``l = i n + j`` (slot ``i``,
    sample ``j``) on its last axis: a group of at most
    :data:`~c3bench.solvers.admm.compiled_kernels.LANE_BLOCK` lanes is factorised in place,
    the factorisation's work arrays are these arrays (no copy), and the linear passes read
    slot ``i``'s samples as the contiguous run of lanes from ``i n`` (from
    :data:`~c3bench.solvers.admm.compiled_passes.LANE_SOLVE` samples on as vector lanes).

    ``Y`` (T, nv, nx, m n) = ``L^-1 Q_vx``, ``L`` (T, nv, nv, m n) lower Cholesky factors of
    ``Q_vv`` with the reciprocals of their diagonals on the diagonal (upper triangle 0),
    ``Sd`` (T, nx, m n), ``D`` (ny, m n), ``ABd`` (nx, ny + 1, m n) the scaled ``[A B_v
    d]``; ``failed`` (m n,): -1 or the time step whose Cholesky
    factorisation failed. A group of at most one block has its lane axis rounded up to a
    multiple of :data:`~c3bench.solvers.admm.compiled_kernels.LANE_PAD` (padding lanes,
    worked but never read).
    """

    Y: np.ndarray
    L: np.ndarray
    Sd: np.ndarray
    D: np.ndarray
    ABd: np.ndarray
    failed: np.ndarray
    slots: int
    samples: int

    @classmethod
    def empty(cls, m: int, n: int, T: int, nx: int, nv: int, dtype: np.dtype[Any]
              ) -> CompiledFactors:
        lanes = m * n
        if lanes <= kernels.LANE_BLOCK:  # room for the padding lanes of an in-place block
            lanes = kernels.padded_lanes(lanes)
        return cls(Y=aligned_empty((T, nv, nx, lanes), dtype),
                   L=aligned_empty((T, nv, nv, lanes), dtype, 0.0),
                   Sd=aligned_empty((T, nx, lanes), dtype),
                   D=aligned_empty((nx + nv, lanes), dtype),
                   ABd=aligned_empty((nx, nx + nv + 1, lanes), dtype),
                   failed=np.full(m * n, -1, np.int64), slots=m, samples=n)

    @property
    def shape(self) -> tuple[int, ...]:
        """``(m, n, T)``."""
        return (self.slots, self.samples, self.Y.shape[0])


def plan_group(samples: int, planned: int) -> int:
    """How many planned rho values are factorised together: as many as fill
    :data:`GROUP_LANES` lanes (rho x sample pairs), at least one, so that a group is
    factorised in place in one block and its factors stay in the core's cache until the
    iterations that use them (measured at 16 samples: factorising 2 rho values before their two
    iterations is 10 % faster than factorising all 10 up front; at 64 samples one at a time is
    17 % faster; at 1 sample all 10 together is 2-3 times faster than fewer)."""
    return min(planned, max(1, GROUP_LANES // samples))


GROUP_LANES = 16
"""Lanes of one plan group (:func:`plan_group`). 16, not a whole block of
:data:`~c3bench.solvers.admm.compiled_kernels.LANE_BLOCK`: at 16 samples one rho value per
group instead of two halves what a factorisation touches (factors and work arrays, about
0.43 -> 0.22 MB), so that the step's working set stays inside the core's 1 MB L2 cache
beside the LCS build's. Measured with ``c3bench perf --samples 16`` on the 2-core EPYC VM,
alternated with the groups of 32 lanes, eight runs each: ADMM median 0.65 against 0.70 ms,
shares of the matmul rate 25.3-28.9 % against 24.4-28.5 %."""


def rho_key(rho: Mapping[str, float]) -> tuple[float, ...]:
    """The four rho values in :data:`BLOCKS` order (plan and cache key)."""
    return (float(rho[Block.X]), float(rho[Block.LAM]), float(rho[Block.U]),
            float(rho[Block.ETA]))


def factor_failure(factors: CompiledFactors, slot: int, rho: Mapping[str, float]) -> str | None:
    """Why ``slot``'s factorisation failed (the first failed sample), or ``None``."""
    n = factors.samples
    failed = factors.failed[slot * n:(slot + 1) * n]
    if failed.max() < 0:
        return None
    j = int(np.argmax(failed >= 0))
    return (f"Q_vv not positive definite (Cholesky) for sample {j} at step {int(failed[j])}, "
            f"rho={dict(rho)}")
