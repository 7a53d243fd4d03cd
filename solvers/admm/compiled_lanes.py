"""The lanes of the compiled factorisation (:func:`c3bench.solvers.admm.compiled_kernels.
factorize_batch`): which rho value and sample each lane holds, its scaled inputs, and the copy
of a block's results into the outputs.

A *lane* is one (rho value, sample) pair, lane ``i n + j`` for rho ``i`` and sample ``j``, the
last axis of every array (module docstring of :mod:`.compiled_kernels`). :func:`scale_lanes`
builds a block's Jacobi-scaled ``H_y``, ``D``, ``[A B_v d]`` and ``S_T``; the backward steps
(:func:`~c3bench.solvers.admm.compiled_kernels._riccati_lanes` or the generated code of
:mod:`.compiled_codegen`) then work the block; :func:`store_step` and :func:`store_block` copy
a block worked in local arrays into its lanes of the outputs.

References: Jacobi (diagonal) scaling of a symmetric positive definite system (Golub & Van Loan,
*Matrix Computations*, 4th ed., section 11.5.3) as :mod:`c3bench.solvers.fast` applies it.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from c3bench.problems.jit import jit

__all__ = ["lane_indices", "lane_runs", "scale_lanes", "scaled_hessian", "scaled_hessian_one_run",
           "scaled_row_gathered", "scaled_row_run", "store_block", "store_step", "used_columns"]


@jit
def lane_indices(l0: int, nl: int, lanes: int, n: int, li: np.ndarray, lj: np.ndarray
                  ) -> None:
    """The rho ``li[l]`` and sample ``lj[l]`` of lanes ``l0 .. l0 + nl`` (lane ``i n + j``);
    a padding lane (from ``lanes`` on) repeats lane ``l0``."""
    for l in range(nl):
        g = l0 + l if l0 + l < lanes else l0
        li[l], lj[l] = g // n, g % n


@jit
def store_step(k: int, l0: int, nl: int, Yb: np.ndarray, Lb: np.ndarray, Sdb: np.ndarray,
                Y: np.ndarray, L: np.ndarray, Sd: np.ndarray) -> None:
    """Copy step ``k`` of a block (``Y``, the lower triangle of ``L``, ``S_{k+1} d``) into
    lanes ``l0 .. l0 + nl`` of the outputs."""
    nv, nx = Yb.shape[0], Yb.shape[1]
    for a in range(nv):
        for b in range(nx):
            for q in range(nl):
                Y[k, a, b, l0 + q] = Yb[a, b, q]
        for b in range(a + 1):  # lower triangle (the rest stays 0)
            for q in range(nl):
                L[k, a, b, l0 + q] = Lb[a, b, q]
    for a in range(nx):
        for q in range(nl):
            Sd[k, a, l0 + q] = Sdb[a, q]


@jit
def store_block(l0: int, nl: int, fb: np.ndarray, Db: np.ndarray, ABb: np.ndarray,
                 failed: np.ndarray, D: np.ndarray, ABd: np.ndarray) -> None:
    """Copy a block's failures, scaling and scaled ``[A B_v d]`` into lanes ``l0 .. l0 +
    nl`` of the outputs."""
    ny, nx = Db.shape[0], ABb.shape[0]
    for q in range(nl):
        failed[l0 + q] = fb[q]
    for a in range(ny):
        for q in range(nl):
            D[a, l0 + q] = Db[a, q]
    for a in range(nx):
        for b in range(ny + 1):
            for q in range(nl):
                ABd[a, b, l0 + q] = ABb[a, b, q]


@jit
def used_columns(a: int, nx: int, ny: int) -> tuple[int, int]:
    """The columns ``first .. stop`` of row ``a`` of ``H_y`` that the backward step
    (:func:`~c3bench.solvers.admm.compiled_kernels._riccati_lanes`) reads: the upper triangle
    of the ``x`` block (``S_k``'s ``H_xx``) and, in the rows of ``v``, everything up to the
    diagonal (``[Q_vx Q_vv]``'s lower part); the rest of ``H_y`` is left unwritten."""
    return (a, nx) if a < nx else (0, a + 1)


@jit
def lane_runs(li: np.ndarray, lj: np.ndarray, nl: int, runs: np.ndarray) -> int:
    """The ``nl`` lanes as runs of consecutive lanes with one rho and consecutive samples:
    ``runs[r] = (first lane, rho, first sample, length)``; returns the number of runs (a
    group of ``m`` rho values for ``n`` samples has ``m`` runs of ``n``, padding lanes one
    run each)."""
    count = 0
    l = 0
    while l < nl:
        length = 1
        while l + length < nl and li[l + length] == li[l] and lj[l + length] == lj[l] + length:
            length += 1
        runs[count, 0], runs[count, 1], runs[count, 2], runs[count, 3] = l, li[l], lj[l], length
        count += 1
        l += length
    return count


@jit
def scale_lanes(A: np.ndarray, Bv: np.ndarray, d: np.ndarray, MtM: np.ndarray,
                 base: np.ndarray, two_rho_eta: np.ndarray, PT: np.ndarray, ridge: Any,
                 jacobi: bool, zero: Any, one: Any, li: np.ndarray, lj: np.ndarray, nl: int,
                 Hy: np.ndarray, S: np.ndarray, Db: np.ndarray, ABb: np.ndarray,
                 scratch: np.ndarray) -> None:
    """``H_y`` scaled to a unit diagonal (plus ridge; the entries of :func:`used_columns`),
    ``D``, the scaled ``[A B_v d]`` and ``S_T = D_x P_T D_x`` of the ``nl`` lanes (rho
    ``li[l]``, sample ``lj[l]``); lane index innermost in every loop. The per-sample inputs
    are read by runs of lanes whose samples are contiguous (:func:`lane_runs`) when the runs
    average four lanes or more (a group of 32 lanes for 16 samples: 15 -> 8 us), else gathered
    lane by lane (one sample's 10 rho values: runs of one lane, 8 against 20 us); the same
    products either way. The scaling comes first, from ``H_y``'s diagonal, so that ``H_y`` is
    written once, already scaled (the same operations in the same order as forming it and
    scaling it in a second pass: 9.1 -> 8.5 us for 32 lanes at 16 samples)."""
    nx, nv = A.shape[0], Bv.shape[1]
    ny = nx + nv
    runs = np.empty((nl, 4), np.int64)
    count = lane_runs(li, lj, nl, runs)
    if count == 1:  # one rho value, consecutive samples: the common case, in simpler loops
        scaled_hessian_one_run(MtM, base, two_rho_eta, jacobi, zero, one, nx, runs[0, 1],
                               np.uint64(runs[0, 2]), np.uint64(nl), Hy, Db)
    else:
        if 4 * count > nl:
            count = 0  # gathered
        scaled_hessian(MtM, base, two_rho_eta, jacobi, zero, one, nx, li, lj, nl, runs,
                       count, Hy, Db, scratch)
    for a in range(nx, ny):
        for l in range(nl):
            Hy[a, a, l] += ridge
    for a in range(nx):
        for l in range(nl):
            scratch[l] = one / Db[a, l]
        if count == 0:
            scaled_row_gathered(a, A, Bv, d, lj, nl, scratch, Db, ABb)
        for r in range(count):
            scaled_row_run(a, A, Bv, d, np.uint64(runs[r, 0]), np.uint64(runs[r, 2]),
                            np.uint64(runs[r, 3]), scratch, Db, ABb)
        for b in range(nx):
            for l in range(nl):
                S[a, b, l] = PT[a, b] * Db[a, l] * Db[b, l]


@jit
def scaled_hessian(MtM: np.ndarray, base: np.ndarray, two_rho_eta: np.ndarray, jacobi: bool,
                   zero: Any, one: Any, nx: int, li: np.ndarray, lj: np.ndarray, nl: int,
                   runs: np.ndarray, count: int, Hy: np.ndarray, Db: np.ndarray,
                   scratch: np.ndarray) -> None:
    """``D`` and the scaled ``H_y`` of :func:`scale_lanes` (before the ridge) for lanes read
    by ``count`` runs (:func:`lane_runs`), or gathered lane by lane when ``count`` is 0."""
    ny = MtM.shape[0]
    for a in range(ny):  # the scaling first, from the diagonal of H_y alone
        if count == 0:
            for l in range(nl):
                scratch[l] = MtM[a, a, lj[l]] * two_rho_eta[li[l]] + base[li[l], a, a]
        for r in range(count):
            factor, offset = two_rho_eta[runs[r, 1]], base[runs[r, 1], a, a]
            l0, j0 = np.uint64(runs[r, 0]), np.uint64(runs[r, 2])  # unsigned: no
            for q in range(np.uint64(runs[r, 3])):  # negative-index wraparound
                scratch[l0 + q] = MtM[a, a, j0 + q] * factor + offset
        for l in range(nl):
            h = scratch[l]
            Db[a, l] = one / np.sqrt(h) if (jacobi and h > zero) else one
    for a in range(ny):  # then H_y scaled in one pass: the entries of used_columns
        first, stop = used_columns(a, nx, ny)
        for b in range(first, stop):
            if count == 0:
                for l in range(nl):
                    Hy[a, b, l] = (MtM[a, b, lj[l]] * two_rho_eta[li[l]]
                                   + base[li[l], a, b]) * Db[a, l] * Db[b, l]
            for r in range(count):
                factor, offset = two_rho_eta[runs[r, 1]], base[runs[r, 1], a, b]
                l0, j0 = np.uint64(runs[r, 0]), np.uint64(runs[r, 2])
                for q in range(np.uint64(runs[r, 3])):
                    Hy[a, b, l0 + q] = (MtM[a, b, j0 + q] * factor + offset) \
                        * Db[a, l0 + q] * Db[b, l0 + q]


@jit
def scaled_hessian_one_run(MtM: np.ndarray, base: np.ndarray, two_rho_eta: np.ndarray,
                           jacobi: bool, zero: Any, one: Any, nx: int, rho: int, j0: Any,
                           nl: Any, Hy: np.ndarray, Db: np.ndarray) -> None:
    """:func:`scaled_hessian` when the ``nl`` lanes are one run: rho ``rho`` for the samples
    ``j0 .. j0 + nl`` (a plan group of one rho value, a block of a large batch). The same
    operations in the same order, in loops whose lane index is the work arrays' own (the
    setup of 16 lanes: 5.2 -> 4.2-4.5 us). ``j0`` and ``nl`` are unsigned, so that no index needs
    a negative-index wraparound check."""
    ny = MtM.shape[0]
    factor = two_rho_eta[rho]
    for a in range(ny):
        offset = base[rho, a, a]
        for l in range(nl):
            h = MtM[a, a, j0 + l] * factor + offset
            Db[a, l] = one / np.sqrt(h) if (jacobi and h > zero) else one
    for a in range(ny):
        first, stop = used_columns(a, nx, ny)
        for b in range(first, stop):
            offset = base[rho, a, b]
            for l in range(nl):
                Hy[a, b, l] = (MtM[a, b, j0 + l] * factor + offset) * Db[a, l] * Db[b, l]


@jit
def scaled_row_gathered(a: int, A: np.ndarray, Bv: np.ndarray, d: np.ndarray,
                         lj: np.ndarray, nl: int, scratch: np.ndarray, Db: np.ndarray,
                         ABb: np.ndarray) -> None:
    """Row ``a`` of the scaled ``[A B_v d]``, ``[A B_v d][a, b] / D[a] * D[b]`` (``scratch =
    1 / D[a]``), the samples gathered lane by lane."""
    nx, nv = A.shape[0], Bv.shape[1]
    for b in range(nx):
        for l in range(nl):
            ABb[a, b, l] = A[a, b, lj[l]] * scratch[l] * Db[b, l]
    for b in range(nv):
        for l in range(nl):
            ABb[a, nx + b, l] = Bv[a, b, lj[l]] * scratch[l] * Db[nx + b, l]
    for l in range(nl):
        ABb[a, nx + nv, l] = d[a, lj[l]] * scratch[l]


@jit
def scaled_row_run(a: int, A: np.ndarray, Bv: np.ndarray, d: np.ndarray, l0: Any, j0: Any,
                    length: Any, scratch: np.ndarray, Db: np.ndarray, ABb: np.ndarray) -> None:
    """:func:`scaled_row_gathered` for the run of lanes ``l0 .. l0 + length`` (samples
    ``j0 ..``; unsigned offsets)."""
    nx, nv = A.shape[0], Bv.shape[1]
    for b in range(nx):
        for q in range(length):
            ABb[a, b, l0 + q] = A[a, b, j0 + q] * scratch[l0 + q] * Db[b, l0 + q]
    for b in range(nv):
        for q in range(length):
            ABb[a, nx + b, l0 + q] = Bv[a, b, j0 + q] * scratch[l0 + q] * Db[nx + b, l0 + q]
    for q in range(length):
        ABb[a, nx + nv, l0 + q] = d[a, j0 + q] * scratch[l0 + q]
