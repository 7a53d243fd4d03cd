"""Numba kernels of the compiled C3+ QP step (:mod:`solvers.admm.compiled`): the factorisation.

The arithmetic is that of :mod:`solvers.fast` (module docstring there: elimination of ``eta``,
Jacobi scaling, the Riccati recursion split into a factorisation and linear passes), written
as loops over samples and small dense blocks so that one compiled call does the work of a whole
batch. Two algebraic rearrangements save work without changing the exact answer:

* the factorisation keeps the Cholesky factor ``L`` of ``Q_vv = L L^T`` (hand-written, for
  ``nv = nlam + nu`` of about 8) instead of ``Q_vv^-1``; with ``Y = L^-1 Q_vx``,

      K = -L^-T Y,    S_k = H_xx + A^T S_{k+1} A - Y^T Y,

  so ``S_k`` is symmetric by construction (only its upper triangle is computed) and the
  ``Q_xv K`` product becomes the symmetric rank-``nv`` update ``Y^T Y``;
* ``A_cl = A + B_v K`` is never formed: the backward pass uses
  ``A_cl^T e + K^T g_v = A^T e + K^T r`` with ``r = g_v + B_v^T e`` (which it needs anyway
  for ``kk = -Q_vv^-1 r``), and the forward pass is the rollout ``x_{k+1} = A x_k + B_v v_k +
  d`` of the scaled dynamics.

The factorisation divides by the diagonal of ``L`` through its reciprocals (one division
per pivot instead of one per entry of ``L``, ``Y`` and ``K``; vector division is many times
slower than multiplication), which changes results by rounding only.

**Layout.** :func:`factorize_batch` works every (rho value, sample) pair as a *lane*:
blocks of up to :data:`LANE_BLOCK` lanes sit in local arrays with the lane index last, so
every innermost loop runs over lanes and vectorises (no sum is reassociated: ``fastmath``
stays off); the factors are stored with the samples on the last axis, so
:func:`c3bench.solvers.admm.compiled_passes.solve_project` (the linear passes, projection and
dual update of one iteration) works the samples as vector lanes too, from its
:data:`~c3bench.solvers.admm.compiled_passes.LANE_SOLVE` samples on (below, one sample at a
time). Each sample's sums keep the order of :mod:`solvers.fast`. Small dense algebra
(products, Cholesky, triangular solves) is written out by hand; nothing calls
``numpy.linalg``.

Measured (planar cube, ``nx = nlam + nu = 10``, ``T = 7``, 10 rho values, 16 samples, one
core shared with other jobs at load average 2-4): the factorisation runs at about 8.5
GFLOP/s in this module's count (:func:`factor_flops`), about 16 % of the core's dense
matmul rate; the innermost lane loops are short (``LANE_BLOCK``), so loop and address
overhead, not arithmetic, bounds it.

Per sample, rho and step the factorisation costs ``nx^2 (ny + 1) + nv ny nx`` (the products
``S [A B_v d]`` and ``B_v^T S [A B_v]``, the latter on the lower triangle of ``Q_vv`` only),
``nv^3 / 6`` (Cholesky), ``nv^2 nx`` (the two triangular solves) and ``nx (nx + 1) (nx + nv)
/ 2`` (the upper triangle of ``A^T S A - Y^T Y``) multiply-adds (:func:`factor_flops`).

Every kernel takes its scalars in the arrays' dtype (``zero``, ``one`` and the rho-derived
constants), so that float32 arrays are worked in float32 arithmetic throughout.

References: the Riccati recursion of the LQ problem (e.g. Rawlings, Mayne & Diehl, *Model
Predictive Control*, 2nd ed., section 1.3.3); Cholesky factorisation and triangular solves
(Golub & Van Loan, *Matrix Computations*, 4th ed., algorithms 4.2.1 and 3.1.1-3.1.2).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, TypeVar, cast

import numba
import numpy as np

__all__ = ["LANE_BLOCK", "factor_flops", "factorize_batch", "jit"]

F = TypeVar("F", bound=Callable[..., Any])


def jit(function: F) -> F:
    """``numba.njit(cache=True, fastmath=False, error_model="numpy")`` with the function's own
    type for mypy. The numpy error model divides by IEEE rules instead of testing every divisor
    for zero (a branch that keeps a loop from vectorising); every divisor here is a positive
    pivot or scale."""
    return cast(F, numba.njit(cache=True, fastmath=False, error_model="numpy")(function))


def factor_flops(nx: int, nv: int) -> int:
    """Floating-point operations (2 per multiply-add) of one factorisation step of one
    sample (module docstring)."""
    ny = nx + nv
    mads = nx * nx * (ny + 1) + nv * nx * nx + nv * (nv + 1) // 2 * nx + nv ** 3 // 6 \
        + nv * nv * nx + nx * (nx + 1) * (nx + nv) // 2
    return 2 * mads


LANE_BLOCK = 32
"""Lanes (rho value x sample pairs) factorised together: the innermost loop of every
operation runs over a block of lanes, so it vectorises without reassociating any sum."""


@jit
def factorize_batch(A: np.ndarray, Bv: np.ndarray, d: np.ndarray, MtM: np.ndarray,
                    base: np.ndarray, two_rho_eta: np.ndarray, PT: np.ndarray,
                    ridge: Any, jacobi: bool, zero: Any, one: Any,
                    K: np.ndarray, L: np.ndarray, Sd: np.ndarray, D: np.ndarray,
                    ABd: np.ndarray, failed: np.ndarray) -> None:
    """Factorise ``m`` rho values for ``n`` samples (module docstring).

    Inputs: ``A`` (n, nx, nx), ``Bv`` (n, nx, nv), ``d`` (n, nx), ``MtM`` (n, ny, ny);
    ``base`` (m, ny, ny) = ``blockdiag(2Q + 2 rho_x I, 2 rho_lam I, 2R + 2 rho_u I)``,
    ``two_rho_eta`` (m,), so ``H_y = base + 2 rho_eta M^T M``; ``PT`` (nx, nx).
    Outputs (preallocated, samples on the last axis): ``K`` (m, T, nv, nx, n), ``L``
    (m, T, nv, nv, n) lower Cholesky factors of ``Q_vv``, ``Sd`` (m, T, nx, n) =
    ``S_{k+1} d``, ``D`` (m, ny, n) scaling, ``ABd`` (m, nx, ny + 1, n) = scaled
    ``[A B_v d]``; ``failed`` (m, n): -1, or the (first, backward) step whose ``Q_vv`` is not
    positive definite.

    Lanes (lane ``i n + j``: rho ``i``, sample ``j``) are worked in blocks of at most
    :data:`LANE_BLOCK` in contiguous local arrays with the lane index last (so the innermost
    loops vectorise across lanes); the results are copied out, one run of consecutive
    samples of one rho at a time, with the samples last (so the linear passes of
    :func:`c3bench.solvers.admm.compiled_passes.solve_project` vectorise across samples).
    """
    m, n = base.shape[0], A.shape[0]
    nx, nv = A.shape[1], Bv.shape[2]
    ny = nx + nv
    T = K.shape[1]
    lanes = m * n
    LB = min(LANE_BLOCK, lanes)
    dt = A.dtype
    Hy, S, Db = np.empty((ny, ny, LB), dt), np.empty((nx, nx, LB), dt), np.empty((ny, LB), dt)
    ABb, SAB = np.empty((nx, ny + 1, LB), dt), np.empty((nx, ny + 1, LB), dt)
    Qv, Y = np.empty((nv, ny, LB), dt), np.empty((nv, nx, LB), dt)
    Kb, Lb = np.empty((nv, nx, LB), dt), np.zeros((nv, nv, LB), dt)
    sv, fb, Li = np.empty(LB, dt), np.empty(LB, np.int64), np.empty((nv, LB), dt)
    li, lj = np.empty(LB, np.int64), np.empty(LB, np.int64)
    for l0 in range(0, lanes, LB):
        nl = min(LB, lanes - l0)
        for l in range(nl):
            li[l], lj[l] = (l0 + l) // n, (l0 + l) % n
        _scale_lanes(A, Bv, d, MtM, base, two_rho_eta, PT, ridge, jacobi, zero, one, li, lj,
                     nl, Hy, S, Db, ABb, sv)
        fb[:] = -1
        for k in range(T - 1, -1, -1):
            _riccati_lanes(k, nl, nx, nv, zero, one, S, ABb, Hy, SAB, Qv, Y, sv, Kb, Lb, Li,
                           fb)
            _store_step(k, l0, nl, n, Kb, Lb, SAB, K, L, Sd)
        _store_block(l0, nl, n, fb, Db, ABb, failed, D, ABd)


@jit
def _store_step(k: int, l0: int, nl: int, n: int, Kb: np.ndarray, Lb: np.ndarray,
                SAB: np.ndarray, K: np.ndarray, L: np.ndarray, Sd: np.ndarray) -> None:
    """Copy step ``k`` of the block's lanes ``l0 .. l0 + nl`` (``K``, the lower triangle of
    ``L``, ``S_{k+1} d``) out, one run of consecutive samples of one rho at a time."""
    nv, nx = Kb.shape[0], Kb.shape[1]
    ny = SAB.shape[1] - 1
    l = 0
    while l < nl:
        i, j0 = (l0 + l) // n, (l0 + l) % n
        run = min(n - j0, nl - l)
        for a in range(nv):
            for b in range(nx):
                for q in range(run):
                    K[i, k, a, b, j0 + q] = Kb[a, b, l + q]
            for b in range(a + 1):  # lower triangle (the rest stays 0)
                for q in range(run):
                    L[i, k, a, b, j0 + q] = Lb[a, b, l + q]
        for a in range(nx):
            for q in range(run):
                Sd[i, k, a, j0 + q] = SAB[a, ny, l + q]
        l += run


@jit
def _store_block(l0: int, nl: int, n: int, fb: np.ndarray, Db: np.ndarray, ABb: np.ndarray,
                 failed: np.ndarray, D: np.ndarray, ABd: np.ndarray) -> None:
    """Copy the block's failures, scaling and scaled ``[A B_v d]`` out (as
    :func:`_store_step`)."""
    ny, nx = Db.shape[0], ABb.shape[0]
    l = 0
    while l < nl:
        i, j0 = (l0 + l) // n, (l0 + l) % n
        run = min(n - j0, nl - l)
        for q in range(run):
            failed[i, j0 + q] = fb[l + q]
        for a in range(ny):
            for q in range(run):
                D[i, a, j0 + q] = Db[a, l + q]
        for a in range(nx):
            for b in range(ny + 1):
                for q in range(run):
                    ABd[i, a, b, j0 + q] = ABb[a, b, l + q]
        l += run


@jit
def _scale_lanes(A: np.ndarray, Bv: np.ndarray, d: np.ndarray, MtM: np.ndarray,
                 base: np.ndarray, two_rho_eta: np.ndarray, PT: np.ndarray, ridge: Any,
                 jacobi: bool, zero: Any, one: Any, li: np.ndarray, lj: np.ndarray, nl: int,
                 Hy: np.ndarray, S: np.ndarray, Db: np.ndarray, ABb: np.ndarray,
                 scratch: np.ndarray) -> None:
    """``H_y`` scaled to a unit diagonal (plus ridge), ``D``, the scaled ``[A B_v d]`` and
    ``S_T = D_x P_T D_x`` of the ``nl`` lanes (rho ``li[l]``, sample ``lj[l]``); lane
    index innermost in every loop."""
    nx, nv = A.shape[1], Bv.shape[2]
    ny = nx + nv
    for l in range(nl):
        scratch[l] = two_rho_eta[li[l]]
    for a in range(ny):
        for b in range(ny):
            for l in range(nl):
                Hy[a, b, l] = MtM[lj[l], a, b] * scratch[l] + base[li[l], a, b]
    for a in range(ny):
        for l in range(nl):
            h = Hy[a, a, l]
            Db[a, l] = one / np.sqrt(h) if (jacobi and h > zero) else one
    for a in range(ny):
        for b in range(ny):
            for l in range(nl):
                Hy[a, b, l] = Hy[a, b, l] * Db[a, l] * Db[b, l]
    for a in range(nx, ny):
        for l in range(nl):
            Hy[a, a, l] += ridge
    for a in range(nx):
        for l in range(nl):
            scratch[l] = one / Db[a, l]
        for b in range(nx):
            for l in range(nl):
                ABb[a, b, l] = A[lj[l], a, b] * scratch[l] * Db[b, l]
                S[a, b, l] = PT[a, b] * Db[a, l] * Db[b, l]
        for b in range(nv):
            for l in range(nl):
                ABb[a, nx + b, l] = Bv[lj[l], a, b] * scratch[l] * Db[nx + b, l]
        for l in range(nl):
            ABb[a, ny, l] = d[lj[l], a] * scratch[l]


@jit
def _riccati_lanes(k: int, nl: int, nx: int, nv: int, zero: Any, one: Any, S: np.ndarray,
                   ABb: np.ndarray, Hy: np.ndarray, SAB: np.ndarray, Qv: np.ndarray,
                   Y: np.ndarray, sv: np.ndarray, Kb: np.ndarray, Lb: np.ndarray,
                   Li: np.ndarray, fb: np.ndarray) -> None:
    """One backward step for a block of ``nl`` lanes: ``S`` (``S_{k+1}`` in,
    ``S_k`` out), ``K``, ``L`` and (in ``SAB[:, ny]``) ``S_{k+1} d`` of step ``k``; a lane
    whose ``Q_vv`` is not positive definite gets ``k`` in ``fb`` (first failure only) and
    continues on a unit pivot."""
    ny = nx + nv
    for a in range(nx):  # SAB = S [A B_v d]
        for b in range(ny + 1):
            for l in range(nl):
                SAB[a, b, l] = zero
        for c in range(nx):
            for b in range(ny + 1):
                for l in range(nl):
                    SAB[a, b, l] += S[a, c, l] * ABb[c, b, l]
    for a in range(nv):  # [Q_vx Q_vv] = H_v + B_v^T S [A B_v] (lower triangle of Q_vv)
        width = nx + a + 1
        for b in range(width):
            for l in range(nl):
                Qv[a, b, l] = Hy[nx + a, b, l]
        for c in range(nx):
            for b in range(width):
                for l in range(nl):
                    Qv[a, b, l] += ABb[c, nx + a, l] * SAB[c, b, l]
    for a in range(nv):  # Q_vv = L L^T; Li = 1 / diag(L) (multiplications, not divisions)
        for b in range(a + 1):
            for l in range(nl):
                sv[l] = Qv[a, nx + b, l]
            for c in range(b):
                for l in range(nl):
                    sv[l] -= Lb[a, c, l] * Lb[b, c, l]
            if a == b:
                for l in range(nl):  # branch-free (vectorises): a failed pivot becomes 1
                    positive = sv[l] > zero
                    fb[l] = k if (not positive and fb[l] < 0) else fb[l]
                    sv[l] = sv[l] if positive else one
                for l in range(nl):
                    Lb[a, a, l] = np.sqrt(sv[l])
                    Li[a, l] = one / Lb[a, a, l]
            else:
                for l in range(nl):
                    Lb[a, b, l] = sv[l] * Li[b, l]
    for a in range(nv):  # Y = L^-1 Q_vx
        for b in range(nx):
            for l in range(nl):
                Y[a, b, l] = Qv[a, b, l]
        for c in range(a):
            for b in range(nx):
                for l in range(nl):
                    Y[a, b, l] -= Lb[a, c, l] * Y[c, b, l]
        for b in range(nx):
            for l in range(nl):
                Y[a, b, l] = Y[a, b, l] * Li[a, l]
    for a in range(nv - 1, -1, -1):  # K = -L^-T Y
        for b in range(nx):
            for l in range(nl):
                Kb[a, b, l] = -Y[a, b, l]
        for c in range(a + 1, nv):
            for b in range(nx):
                for l in range(nl):
                    Kb[a, b, l] -= Lb[c, a, l] * Kb[c, b, l]
        for b in range(nx):
            for l in range(nl):
                Kb[a, b, l] = Kb[a, b, l] * Li[a, l]
    for a in range(nx):  # S_k = H_xx + A^T S A - Y^T Y (upper triangle, mirrored)
        for b in range(a, nx):
            for l in range(nl):
                S[a, b, l] = Hy[a, b, l]
        for c in range(nx):
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

