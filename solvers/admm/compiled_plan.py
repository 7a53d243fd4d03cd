"""Numba driver of a planned schedule: every iteration of one control step in one compiled call.

With a data-independent rho schedule (geometric: its ``plan`` is known before the first
iteration), ``fixed`` stopping and nothing recorded per iteration, the one ADMM loop
(:func:`c3bench.solvers.admm.loop.run_admm`) has nothing to decide between iterations; it
hands the whole plan to the kernel (``run_plan``), and :func:`run_plan` here runs, for
``i = 0 .. len(plan) - 1``:

1. at the first iteration of each group of the plan (the group buffer's ``m`` rho values),
   :func:`c3bench.solvers.admm.compiled_kernels.factorize_batch` of the group;
2. the iteration itself, :func:`c3bench.solvers.admm.compiled_passes.iterate_in_lanes` (QP step,
   projection and the loop's dual update, compiled) with ``plan[i]``'s factors;
3. before the next iteration, the loop's rescaling of the scaled dual,
   :func:`c3bench.solvers.admm.loop.scale_dual` by ``ratios[i]``
   (:func:`c3bench.solvers.admm.loop.plan_ratios`), compiled.

Nothing here is a second copy of the algorithm: every step is the loop's or the kernel's one
definition, called in the loop's order. What the call saves is the Python between
iterations (about 25 us per iteration: argument checks, dispatch of a 24-argument compiled
call, the loop's bookkeeping, the rescaling in numpy), which was half of a one-sample
control step. Between the first and the last iteration the iterates are kept with the
samples last, the layout of the passes
(:func:`c3bench.solvers.admm.compiled_passes.iterate_in_lanes`), in two sets that alternate,
so that a failed iteration leaves the last completed one intact, as the iteration-by-iteration
loop does; they are transposed only on the way in and out.
"""

from __future__ import annotations

from typing import Any

import numba
import numpy as np

from c3bench.solvers.admm.compiled_kernels import factorize_batch
from c3bench.solvers.admm.compiled_kernels import jit as _jit
from c3bench.solvers.admm.compiled_passes import (
    from_lanes,
    iterate_in_lanes,
    to_lanes,
    z_from_lanes,
)
from c3bench.solvers.admm.loop import scale_dual

__all__ = ["FACTORISATION_FAILED", "NON_FINITE", "run_plan"]

FACTORISATION_FAILED = 1
""":func:`run_plan`'s code: the factorisation of the failing iteration's rho failed."""
NON_FINITE = 2
""":func:`run_plan`'s code: the failing iteration's QP solution is not finite."""

_scale_dual = numba.njit(fastmath=False)(scale_dual)
"""The loop's one dual rescaling (:func:`c3bench.solvers.admm.loop.scale_dual`), compiled
(called entry by entry)."""


@_jit
def run_plan(A: np.ndarray, Bv: np.ndarray, d: np.ndarray, MtM: np.ndarray,
             bases: np.ndarray, two_rho_eta: np.ndarray, PT: np.ndarray, ridge: Any,
             jacobi: bool, zero: Any, one: Any, column_start: np.ndarray,
             column_rows: np.ndarray, row_start: np.ndarray, row_columns: np.ndarray,
             Y: np.ndarray, L: np.ndarray, Sd: np.ndarray, D: np.ndarray, ABd: np.ndarray,
             failed: np.ndarray, vectors: np.ndarray, Mc: np.ndarray, Mt: np.ndarray,
             consts: np.ndarray, p: np.ndarray, shared: bool, box: np.ndarray,
             ratios: np.ndarray, delta: np.ndarray, w: np.ndarray, iterates: np.ndarray,
             terminal: np.ndarray, steps: np.ndarray, generated: np.ndarray
             ) -> tuple[int, int]:
    """Every iteration of the plan (module docstring).

    ``bases`` (N, ny, ny), ``two_rho_eta`` (N,) and ``consts`` (N, ny + 3) are the plan's
    constants of :func:`~c3bench.solvers.admm.compiled_kernels.factorize_batch` and
    :func:`~c3bench.solvers.admm.compiled_passes.iterate_in_lanes`; ``Y`` ... ``failed`` the
    group buffer (:class:`~c3bench.solvers.admm.compiled_factors.CompiledFactors`, ``m n``
    lanes: ``m`` is the group size); ``ratios`` (N - 1, ns);
    ``delta`` and ``w`` (n, T, ns) the initial iterates (read only); ``iterates`` (3, n, T,
    ns) receives ``(delta, w, z_steps)`` after the last completed iteration (the initial
    ``delta`` and ``w`` when none completed; ``z_steps`` then unset), ``terminal`` (n, nx) its
    ``z_terminal``; ``steps``
    the generated backward steps of :func:`~c3bench.solvers.admm.compiled_kernels.
    factorize_batch`, ``generated`` the generated passes of :func:`~c3bench.solvers.admm.
    compiled_passes.iterate_in_lanes`.

    Returns ``(completed, code)``: the iterations completed and 0,
    :data:`FACTORISATION_FAILED` or :data:`NON_FINITE` for iteration ``completed``.
    """
    N = bases.shape[0]
    n, T, ns = delta.shape
    group = failed.shape[0] // n
    lanes = np.empty((2, 2, T, ns, n), delta.dtype)  # (delta, w) sets, samples last
    zts = np.empty((2, T + 1, ns, n), delta.dtype)  # the sets' z (row T: terminal x)
    to_lanes(delta, lanes[0, 0])
    to_lanes(w, lanes[0, 1])
    current, completed, code = 0, N, 0
    for i in range(N):
        slot = i % group
        if slot == 0:
            m = min(group, N - i)
            factorize_batch(A, Bv, d, MtM, bases[i:i + m], two_rho_eta[i:i + m], PT, ridge,
                            jacobi, zero, one, column_start, column_rows, Y, L, Sd, D, ABd,
                            failed, steps)
        if failed[slot * n:(slot + 1) * n].max() >= 0:
            completed, code = i, FACTORISATION_FAILED
            break
        target = 1 - current
        if not iterate_in_lanes(vectors, lanes[current, 0], lanes[current, 1], Mc, Mt,
                                consts[i], Y, L, Sd, D, ABd, slot, column_start, column_rows,
                                row_start, row_columns, p, shared, box, zero, zts[target],
                                lanes[target, 0], lanes[target, 1], generated):
            completed, code = i, NON_FINITE
            break
        current = target
        if i + 1 < N:
            dual = lanes[current, 1]
            for k in range(T):
                for a in range(ns):
                    ratio = ratios[i, a]
                    for j in range(n):
                        dual[k, a, j] = _scale_dual(dual[k, a, j], ratio)
    from_lanes(lanes[current, 0], iterates[0])
    from_lanes(lanes[current, 1], iterates[1])
    z_from_lanes(zts[current], iterates[2], terminal)
    return completed, code
