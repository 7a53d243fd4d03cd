"""Numba kernels of the compiled C3+ QP step (:mod:`solvers.admm.compiled`): the factorisation.

The arithmetic is that of :mod:`solvers.fast` (module docstring there: elimination of ``eta``,
Jacobi scaling, the Riccati recursion split into a factorisation and linear passes), written
as loops over samples and small dense blocks so that one compiled call does the work of a whole
batch. Three rearrangements save work without changing the exact answer:

* the factorisation keeps the Cholesky factor ``L`` of ``Q_vv = L L^T`` (hand-written, for
  ``nv = nlam + nu`` of about 10) and ``Y = L^-1 Q_vx`` instead of ``Q_vv^-1`` and the gain;
  with ``K = -L^-T Y``,

      S_k = H_xx + A^T S_{k+1} A - Y^T Y,

  so ``S_k`` is symmetric by construction (only its upper triangle is computed) and the
  ``Q_xv K`` product becomes the symmetric rank-``nv`` update ``Y^T Y``. ``K`` itself is
  never formed: each factorisation serves one ADMM iteration, whose passes apply it as
  ``K^T r = -Y^T (L^-1 r)`` (the backward pass solves ``L t = r`` anyway) and ``K x + kk =
  -L^-T (Y x + t)`` (one triangular solve in place of the backward pass's), which saves the
  ``nv^2 nx / 2`` multiply-adds of ``K`` per step and costs the passes nothing;
* ``A_cl = A + B_v K`` is never formed: the backward pass uses ``A_cl^T e + K^T g_v = A^T e
  + K^T r`` with ``r = g_v + B_v^T e``, and the forward pass is the rollout ``x_{k+1} = A x_k
  + B_v v_k + d`` of the scaled dynamics;
* every product with ``[A B_v d]`` runs over its **structural nonzeros** only
  (:class:`Structure`: the entries that are not exactly zero in some sample of the batch,
  found once per control step; the Jacobi scaling keeps zeros zero). A multibody LCS has
  many: the planar cube's ``A`` is ``[[I, dt I], [0, I]]`` (15 of 100 entries) and 77 of the
  210 entries of ``[A B_v d]`` are nonzero, which removes 40 % of the factorisation's
  multiply-adds. Left-out terms are exact zeros and each sum keeps its order, so the result
  is the dense one (bit for bit on the cube); a dense LCS just gets no saving.

The factorisation divides by the diagonal of ``L`` through its reciprocals (one division
per pivot instead of one per entry of ``L`` and ``Y``; vector division is many times
slower than multiplication), which changes results by rounding only, and stores those
reciprocals on ``L``'s diagonal, so that the triangular solves of the passes multiply too (a
division's latency sat on their critical path: the one-sample iteration 8.3 -> 7.8 us).

**Layout.** :func:`factorize_batch` works every (rho value, sample) pair as a *lane*,
lane ``i n + j`` for rho ``i`` and sample ``j``, with the lane index last in every array, so
every innermost loop runs over lanes and vectorises (no sum is reassociated: ``fastmath``
stays off). A group of up to :data:`LANE_BLOCK` lanes (a plan group,
:func:`c3bench.solvers.admm.compiled_factors.plan_group`) is worked in place: the output
arrays are the work arrays, nothing is copied. Larger batches are worked in blocks of
:data:`LANE_BLOCK` lanes in local arrays, each copied into its lanes of the outputs (writing
a block at an offset into the outputs directly measured 1.5-2.3 times slower: LLVM's
vectoriser gives up on most of those loops). The linear passes of
:func:`c3bench.solvers.admm.compiled_passes.solve_project` read rho ``i``'s samples as the
contiguous lanes from ``i n``, as vector lanes from its
:data:`~c3bench.solvers.admm.compiled_passes.LANE_SOLVE` samples on (below, one sample at a
time). Small dense algebra (products, Cholesky, triangular solves) is written out by hand;
nothing calls ``numpy.linalg``.

**Generated code.** The backward step, most of the work, is also generated as straight-line
code for the batch's structure (:mod:`c3bench.solvers.admm.compiled_codegen`, bit for bit
:func:`_riccati_lanes`'s results); :func:`factorize_batch` runs it wherever its ``steps``
table has one, and these lane loops elsewhere.

Measured (planar cube, ``nx = nlam + nu = 10``, ``T = 7``, one core, load average below 1,
2-core EPYC VM): one group of 2 rho values for 16 samples (32 lanes) 0.15 ms with the lane
loops, 0.053-0.063 ms with the generated step (and the lane setup by runs,
:func:`.compiled_lanes.scale_lanes`); 10 rho values for one sample 0.087 and 0.032 ms.
:func:`factor_flops` counts what either executes.

Every kernel takes its scalars in the arrays' dtype (``zero``, ``one`` and the rho-derived
constants), so that float32 arrays are worked in float32 arithmetic throughout.

References: the Riccati recursion of the LQ problem (e.g. Rawlings, Mayne & Diehl, *Model
Predictive Control*, 2nd ed., section 1.3.3); Cholesky factorisation and triangular solves
(Golub & Van Loan, *Matrix Computations*, 4th ed., algorithms 4.2.1 and 3.1.1-3.1.2); skipping
structural zeros of the dynamics as sparse linear algebra does (Davis, *Direct Methods for
Sparse Linear Systems*, SIAM 2006, chapter 2).
"""

from __future__ import annotations

from typing import Any, NamedTuple

import numpy as np

from c3bench.problems.jit import jit
from c3bench.solvers.admm.compiled_codegen import call_step
from c3bench.solvers.admm.compiled_lanes import (
    lane_indices,
    scale_lanes,
    store_block,
    store_step,
)

__all__ = ["LANE_BLOCK", "LANE_PAD", "Structure", "assemble", "assemble_flops", "factor_flops",
           "factorize_batch",
           "jit", "no_steps", "padded_lanes", "setup_flops", "structure", "work_lanes"]

def factor_flops(nx: int, nv: int, pattern: Structure | None = None) -> int:
    """Floating-point operations (2 per multiply-add) of one factorisation step of one
    sample as :func:`factorize_batch` executes it (module docstring), over the structural
    nonzeros ``pattern`` of ``[A B_v d]`` (``None``: dense)."""
    ny = nx + nv
    pattern = pattern or Structure.dense(nx, ny)
    counts = np.diff(pattern.column_start)
    mads = nx * int(counts.sum())  # S [A B_v d]
    mads += sum(int(counts[nx + a]) * (nx + a + 1) for a in range(nv))  # B_v^T S [A B_v]
    mads += sum(b for a in range(nv) for b in range(a + 1))  # Cholesky
    mads += nv * (nv - 1) // 2 * nx  # Y = L^-1 Q_vx
    mads += sum(int(counts[a]) * (nx - a) for a in range(nx))  # A^T S A
    mads += nv * nx * (nx + 1) // 2  # Y^T Y
    return 2 * mads + nv * nx + 2 * nv  # Y's scaling, the pivots' square roots and inverses


def assemble_flops(nx: int, nlam: int, nu: int) -> int:
    """Floating-point operations of one sample in :func:`assemble`: ``M^T M`` over the upper
    triangle, a multiply-add per row of ``M`` (the rest are copies)."""
    ny = nx + nlam + nu
    return 2 * nlam * ny * (ny + 1) // 2


def setup_flops(nx: int, nv: int) -> int:
    """Floating-point operations of one lane's setup in :func:`factorize_batch`: the entries
    of ``H_y`` the backward steps read (:func:`.compiled_lanes.used_columns`: a multiply-add
    each, then two products for the scaling), the scaled ``[A B_v d]`` and ``S_T``."""
    ny = nx + nv
    used = nx * (nx + 1) // 2 + nv * nx + nv * (nv + 1) // 2
    return 4 * used + 2 * nx * (ny + 1) + 2 * nx * nx + 2 * ny


LANE_BLOCK = 32
"""Lanes (rho value x sample pairs) factorised together: the innermost loop of every
operation runs over a block of lanes, so it vectorises without reassociating any sum."""
LANE_PAD = 4
"""The lanes of a block are worked in a multiple of this many (one 256-bit vector of
float64): the padding lanes repeat the block's first lane and are never read, so that no
innermost loop ends in a scalar remainder (measured for one sample's 10 rho values: 91 us for
10 lanes, 78 us for 12; the loops' fixed cost dominates at so few lanes). Their work is not
counted in the executed flops."""


@jit
def padded_lanes(lanes: int) -> int:
    """``lanes`` rounded up to a multiple of :data:`LANE_PAD` (the lanes a block works)."""
    return -(-lanes // LANE_PAD) * LANE_PAD


@jit
def work_lanes(lanes: int) -> int:
    """The lane axis of :func:`factorize_batch`'s work arrays for ``lanes`` (rho value,
    sample) pairs: the padded lanes of one in-place block, else :data:`LANE_BLOCK`."""
    return min(LANE_BLOCK, padded_lanes(lanes))


def no_steps() -> np.ndarray:
    """A :func:`factorize_batch` ``steps`` table without generated code (the lane loops run
    every step)."""
    return np.zeros((LANE_BLOCK + 1, 2), np.int64)


def structure(ABd_mask: np.ndarray) -> Structure:
    """The structural nonzeros of ``[A B_v d]`` (``ABd_mask`` (nx, ny + 1) bool: nonzero in any
    sample of the batch), by column and by row (:class:`Structure`)."""
    mask = np.asarray(ABd_mask, dtype=bool)
    nx, columns = mask.shape
    column_rows = [np.flatnonzero(mask[:, b]) for b in range(columns)]
    row_columns = [np.flatnonzero(mask[a, :columns - 1]) for a in range(nx)]
    return Structure(
        np.concatenate([[0], np.cumsum([len(r) for r in column_rows])]).astype(np.int64),
        np.concatenate([np.zeros(0, np.int64), *column_rows]).astype(np.int64),
        np.concatenate([[0], np.cumsum([len(c) for c in row_columns])]).astype(np.int64),
        np.concatenate([np.zeros(0, np.int64), *row_columns]).astype(np.int64))


class Structure(NamedTuple):
    """Where ``[A B_v d]`` (nx, ny + 1) has entries that are not exactly zero in some sample
    (module docstring), in compressed form: column ``b``'s rows are ``column_rows[column_start[b]
    : column_start[b + 1]]`` and row ``a``'s columns of ``[A B_v]`` are ``row_columns[row_start[a]
    : row_start[a + 1]]``, both in increasing order (so every sum keeps its order)."""

    column_start: np.ndarray
    column_rows: np.ndarray
    row_start: np.ndarray
    row_columns: np.ndarray

    @classmethod
    def dense(cls, nx: int, ny: int) -> Structure:
        """Every entry of an (nx, ny + 1) ``[A B_v d]``."""
        return structure(np.ones((nx, ny + 1), dtype=bool))

    @property
    def nonzeros(self) -> int:
        """Structural nonzeros of ``[A B_v d]``."""
        return int(self.column_start[-1])


@jit
def factorize_batch(A: np.ndarray, Bv: np.ndarray, d: np.ndarray, MtM: np.ndarray,
                    base: np.ndarray, two_rho_eta: np.ndarray, PT: np.ndarray,
                    ridge: Any, jacobi: bool, zero: Any, one: Any, column_start: np.ndarray,
                    column_rows: np.ndarray, Y: np.ndarray, L: np.ndarray, Sd: np.ndarray,
                    D: np.ndarray, ABd: np.ndarray, failed: np.ndarray, steps: np.ndarray
                    ) -> None:
    """Factorise ``m`` rho values for ``n`` samples (module docstring).

    Inputs (samples last): ``A`` (nx, nx, n), ``Bv`` (nx, nv, n), ``d`` (nx, n), ``MtM``
    (ny, ny, n);
    ``base`` (m, ny, ny) = ``blockdiag(2Q + 2 rho_x I, 2 rho_lam I, 2R + 2 rho_u I)``,
    ``two_rho_eta`` (m,), so ``H_y = base + 2 rho_eta M^T M``; ``PT`` (nx, nx);
    ``column_start``, ``column_rows``: the columns of :class:`Structure`.
    Outputs (preallocated, lane ``l = i n + j`` of rho ``i`` and sample ``j`` last, at least
    ``m n`` lanes): ``Y`` (T, nv, nx, lanes) = ``L^-1 Q_vx``, ``L`` (T, nv, nv, lanes) lower
    Cholesky factors of ``Q_vv`` with ``1 / L[a, a]`` on the diagonal (the upper triangle is
    not written), ``Sd`` (T, nx, lanes) =
    ``S_{k+1} d``, ``D`` (ny, lanes) scaling, ``ABd`` (nx, ny + 1, lanes) = scaled ``[A B_v
    d]``; ``failed`` (lanes,): -1, or the (first, backward) step whose ``Q_vv`` is not positive
    definite.

    Up to :data:`LANE_BLOCK` lanes are worked in place: the outputs are the work arrays, so
    every innermost loop runs over contiguous lanes and vectorises, and nothing is copied
    (their number rounded up to a multiple of :data:`LANE_PAD` when the outputs have room).
    More lanes are worked in blocks of :data:`LANE_BLOCK` in local arrays, each block copied
    into its lanes of the outputs (writing a block at an offset into the outputs directly
    measured 1.5-2.3 times slower: LLVM's vectoriser gives up on most of those loops).

    ``steps`` (LANE_BLOCK + 1, 2) int64: row ``w`` the ``(address, width)`` of the backward
    step generated for this structure and work arrays of ``w`` lanes
    (:func:`c3bench.solvers.admm.compiled_codegen.step_table`; :func:`no_steps`: none), which
    replaces :func:`_riccati_lanes` (bit for bit the same results) wherever the arrays it
    writes have that many lanes and the lanes worked are a multiple of ``width``.
    """
    m, n = base.shape[0], A.shape[2]
    nx, nv = A.shape[0], Bv.shape[1]
    ny = nx + nv
    T = Y.shape[0]
    lanes = m * n
    padded = padded_lanes(lanes)
    LB = work_lanes(lanes)
    address, width = steps[LB, 0], max(steps[LB, 1], 1)
    dt = A.dtype
    Hy, S = np.empty((ny, ny, LB), dt), np.empty((nx, nx, LB), dt)
    SAB, Qv = np.empty((nx, ny, LB), dt), np.empty((nv, ny, LB), dt)
    Li, sv, fb = np.empty((nv, LB), dt), np.empty(LB, dt), np.empty(LB, np.int64)
    li, lj = np.empty(LB, np.int64), np.empty(LB, np.int64)
    if padded <= LANE_BLOCK:
        nl = padded if Y.shape[3] >= padded else lanes  # the padding lanes, where there is room
        lane_indices(0, nl, lanes, n, li, lj)
        scale_lanes(A, Bv, d, MtM, base, two_rho_eta, PT, ridge, jacobi, zero, one, li, lj,
                     nl, Hy, S, D, ABd, sv)
        fb[:] = -1
        generated = address != 0 and nl == LB and nl % width == 0 and \
            Y.shape[3] == LB and L.shape[3] == LB and Sd.shape[2] == LB and ABd.shape[2] == LB
        for k in range(T - 1, -1, -1):
            if generated:
                call_step(address, S, ABd, Hy, Y[k], L[k], Sd[k], fb, k, nl)
            else:
                _riccati_lanes(k, nl, nx, nv, zero, one, S, ABd, Hy, SAB, Qv, sv, Li, fb,
                               column_start, column_rows, Y[k], L[k], Sd[k])
        failed[:lanes] = fb[:lanes]
        return
    Db, ABb = np.empty((ny, LB), dt), np.empty((nx, ny + 1, LB), dt)
    Yb, Lb, Sdb = np.empty((nv, nx, LB), dt), np.zeros((nv, nv, LB), dt), np.empty((nx, LB), dt)
    for l0 in range(0, lanes, LB):
        nl = min(LB, lanes - l0)
        worked = padded_lanes(nl)  # <= LB: LANE_BLOCK is a multiple of LANE_PAD
        lane_indices(l0, worked, lanes, n, li, lj)
        scale_lanes(A, Bv, d, MtM, base, two_rho_eta, PT, ridge, jacobi, zero, one, li, lj,
                     worked, Hy, S, Db, ABb, sv)
        fb[:] = -1
        generated = address != 0 and worked % width == 0
        for k in range(T - 1, -1, -1):
            if generated:
                call_step(address, S, ABb, Hy, Yb, Lb, Sdb, fb, k, worked)
            else:
                _riccati_lanes(k, worked, nx, nv, zero, one, S, ABb, Hy, SAB, Qv, sv, Li, fb,
                               column_start, column_rows, Yb, Lb, Sdb)
            store_step(k, l0, nl, Yb, Lb, Sdb, Y, L, Sd)
        store_block(l0, nl, fb, Db, ABb, failed, D, ABd)


@jit
def _riccati_lanes(k: int, nl: int, nx: int, nv: int, zero: Any, one: Any,
                   S: np.ndarray, ABb: np.ndarray, Hy: np.ndarray, SAB: np.ndarray,
                   Qv: np.ndarray, sv: np.ndarray, Li: np.ndarray, fb: np.ndarray,
                   column_start: np.ndarray, column_rows: np.ndarray, Y: np.ndarray,
                   L: np.ndarray, Sd: np.ndarray) -> None:
    """One backward step for a block of ``nl`` lanes: ``S`` (``S_{k+1}`` in, ``S_k`` out),
    ``Y``, ``L`` and ``Sd = S_{k+1} d`` of step ``k``. Every product with the scaled ``[A B_v
    d]`` (``ABb``) runs over its structural nonzeros only (:class:`Structure`, rows in
    increasing order, so each sum keeps its order and only exact zeros are left out). A lane whose
    ``Q_vv`` is not positive definite gets ``k`` in ``fb`` (first failure only) and
    continues on a unit pivot."""
    ny = nx + nv
    for b in range(ny):  # SAB = S [A B_v]: column b = sum over its rows c of S[:, c] ABd[c, b]
        for a in range(nx):
            for l in range(nl):
                SAB[a, b, l] = zero
        for q in range(column_start[b], column_start[b + 1]):
            c = column_rows[q]
            for a in range(nx):  # S[a, c] = S[c, a]; outputs a independent (no chain)
                for l in range(nl):
                    SAB[a, b, l] += S[a, c, l] * ABb[c, b, l]
    for a in range(nx):  # Sd = S d, the same way
        for l in range(nl):
            Sd[a, l] = zero
    for q in range(column_start[ny], column_start[ny + 1]):
        c = column_rows[q]
        for a in range(nx):
            for l in range(nl):
                Sd[a, l] += S[a, c, l] * ABb[c, ny, l]
    for a in range(nv):  # [Q_vx Q_vv] = H_v + B_v^T S [A B_v] (lower triangle of Q_vv)
        width = nx + a + 1
        for b in range(width):
            for l in range(nl):
                Qv[a, b, l] = Hy[nx + a, b, l]
        for q in range(column_start[nx + a], column_start[nx + a + 1]):
            c = column_rows[q]
            for b in range(width):
                for l in range(nl):
                    Qv[a, b, l] += ABb[c, nx + a, l] * SAB[c, b, l]
    for a in range(nv):  # Q_vv = L L^T; Li = 1 / diag(L) (multiplications, not divisions)
        for b in range(a + 1):
            for l in range(nl):
                sv[l] = Qv[a, nx + b, l]
            for c in range(b):
                for l in range(nl):
                    sv[l] -= L[a, c, l] * L[b, c, l]
            if a == b:
                for l in range(nl):  # branch-free (vectorises): a failed pivot becomes 1
                    positive = sv[l] > zero
                    fb[l] = k if (not positive and fb[l] < 0) else fb[l]
                    sv[l] = sv[l] if positive else one
                for l in range(nl):  # the diagonal holds 1 / L[a, a] (never read back
                    Li[a, l] = one / np.sqrt(sv[l])  # here; the passes multiply by it)
                    L[a, a, l] = Li[a, l]
            else:
                for l in range(nl):
                    L[a, b, l] = sv[l] * Li[b, l]
    for a in range(nv):  # Y = L^-1 Q_vx
        for b in range(nx):
            for l in range(nl):
                Y[a, b, l] = Qv[a, b, l]
        for c in range(a):
            for b in range(nx):
                for l in range(nl):
                    Y[a, b, l] -= L[a, c, l] * Y[c, b, l]
        for b in range(nx):
            for l in range(nl):
                Y[a, b, l] = Y[a, b, l] * Li[a, l]
    for a in range(nx):  # S_k = H_xx + A^T S A - Y^T Y (upper triangle, mirrored)
        for b in range(a, nx):
            for l in range(nl):
                S[a, b, l] = Hy[a, b, l]
        for q in range(column_start[a], column_start[a + 1]):
            c = column_rows[q]
            for b in range(a, nx):
                for l in range(nl):
                    S[a, b, l] += ABb[c, a, l] * SAB[c, b, l]
        for c in range(nv):
            for b in range(a, nx):
                for l in range(nl):
                    S[a, b, l] -= Y[c, a, l] * Y[c, b, l]
        for b in range(a + 1, nx):
            for l in range(nl):
                S[b, a, l] = S[a, b, l]


@jit
def assemble(A: np.ndarray, B: np.ndarray, D: np.ndarray, d: np.ndarray, E: np.ndarray,
             F: np.ndarray, H: np.ndarray, c: np.ndarray, zero: Any, A_out: np.ndarray,
             Bv: np.ndarray, d_out: np.ndarray, Mc: np.ndarray, Mt: np.ndarray,
             MtM: np.ndarray, mask: np.ndarray) -> None:
    """The kernel's per-step data from an LCS batch ``x+ = A x + B u + D lam + d``, ``eta = E x
    + F lam + H u + c``, in the output arrays' precision: ``A_out`` (nx, nx, n), ``B_v = [D B]``
    (nx, nv, n), ``d_out`` (nx, n), ``[M c] = [E F H c]`` (n, nlam, ny + 1) and the same with
    the samples last (nlam, ny + 1, n), ``M^T M`` (ny, ny, n; each entry's sum over the rows
    of ``M`` in order, the upper triangle mirrored), samples last so that a factorisation's
    lanes read consecutive samples from one or two cache lines, and ``mask`` (nx, ny + 1):
    the entries of ``[A B_v d]`` that are not zero in some sample (:func:`structure`)."""
    n, nx, nu = B.shape
    nlam = D.shape[2]  # the LCS's D (n, nx, nlam)
    ny = nx + nlam + nu
    M, acc = np.empty((nlam, ny, n)), np.empty(n)
    for a in range(nx):  # samples last; every innermost loop writes consecutive samples
        for b in range(nx):
            for j in range(n):
                A_out[a, b, j] = A[j, a, b]
        for b in range(nlam):
            for j in range(n):
                Bv[a, b, j] = D[j, a, b]
        for b in range(nu):
            for j in range(n):
                Bv[a, nlam + b, j] = B[j, a, b]
        for j in range(n):
            d_out[a, j] = d[j, a]
    for a in range(nx):  # the structure: an entry nonzero in some sample
        for b in range(nx):
            nonzero = False
            for j in range(n):
                nonzero |= A_out[a, b, j] != zero
            mask[a, b] = nonzero
        for b in range(nlam + nu):
            nonzero = False
            for j in range(n):
                nonzero |= Bv[a, b, j] != zero
            mask[a, nx + b] = nonzero
        nonzero = False
        for j in range(n):
            nonzero |= d_out[a, j] != zero
        mask[a, ny] = nonzero
    for j in range(n):
        for r in range(nlam):
            for b in range(nx):
                Mc[j, r, b] = E[j, r, b]
            for b in range(nlam):
                Mc[j, r, nx + b] = F[j, r, b]
            for b in range(nu):
                Mc[j, r, nx + nlam + b] = H[j, r, b]
            Mc[j, r, ny] = c[j, r]
    for r in range(nlam):
        for b in range(ny + 1):
            for j in range(n):
                Mt[r, b, j] = Mc[j, r, b]
        for b in range(nx):  # M as given (float64), samples last
            for j in range(n):
                M[r, b, j] = E[j, r, b]
        for b in range(nlam):
            for j in range(n):
                M[r, nx + b, j] = F[j, r, b]
        for b in range(nu):
            for j in range(n):
                M[r, nx + nlam + b, j] = H[j, r, b]
    lanes = np.uint64(n)  # unsigned lane indices: numba adds no negative-index wraparound
    for a in range(ny):  # M^T M, every sample at once: each entry's sum in r order from +0.0,
        for b in range(a, ny):  # in a row of n accumulators that stays in the L1 cache
            for j in range(lanes):
                acc[j] = 0.0
            for r in range(nlam):
                for j in range(lanes):
                    acc[j] += M[r, a, j] * M[r, b, j]
            for j in range(lanes):
                MtM[a, b, j] = acc[j]
                MtM[b, a, j] = acc[j]
