"""Numba kernels of the compiled C3+ QP step (:mod:`solvers.admm.compiled`).

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

**Layout.** :func:`factorize_batch` works every (rho value, sample) pair as a *lane*:
blocks of up to :data:`LANE_BLOCK` lanes sit in local arrays with the lane index last, so
every innermost loop runs over lanes and vectorises (no sum is reassociated: ``fastmath``
stays off); the results are copied out per sample, so :func:`solve_project` (one sample at a
time, in the order of :mod:`solvers.fast`) reads contiguous blocks. Small dense algebra
(products, Cholesky, triangular solves) is written out by hand; nothing calls
``numpy.linalg``.

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

from c3bench.solvers.admm.projection import make_c3plus_pairs

F = TypeVar("F", bound=Callable[..., Any])


def _jit(function: F) -> F:
    """``numba.njit(cache=True, fastmath=False)`` with the function's own type for mypy."""
    return cast(F, numba.njit(cache=True, fastmath=False)(function))


_c3plus_pairs = numba.njit(fastmath=False)(make_c3plus_pairs(np))
"""The one C3+ pair projection (:mod:`c3bench.solvers.admm.projection`) compiled by numba."""


def factor_flops(nx: int, nv: int) -> int:
    """Floating-point operations (2 per multiply-add) of one factorisation step of one
    sample (module docstring)."""
    ny = nx + nv
    mads = nx * nx * (ny + 1) + nv * nx * nx + nv * (nv + 1) // 2 * nx + nv ** 3 // 6 \
        + nv * nv * nx + nx * (nx + 1) * (nx + nv) // 2
    return 2 * mads


def solve_flops(nx: int, nv: int, nlam: int) -> int:
    """Floating-point operations of the gradient, the two passes, ``eta`` and the projection
    for one sample and step (2 per multiply-add)."""
    ny = nx + nv
    mads = 2 * nlam * ny + nv * nx + nv * nv + nx * nx + nx * nv + nv * nx + nx * nx + nx * nv
    return 2 * mads + 4 * ny


LANE_BLOCK = 64
"""Lanes (rho value x sample pairs) factorised together: the innermost loop of every
operation runs over a block of lanes, so it vectorises without reassociating any sum."""


@_jit
def factorize_batch(A: np.ndarray, Bv: np.ndarray, d: np.ndarray, MtM: np.ndarray,
                    base: np.ndarray, two_rho_eta: np.ndarray, PT: np.ndarray,
                    ridge: Any, jacobi: bool, zero: Any, one: Any,
                    K: np.ndarray, L: np.ndarray, Sd: np.ndarray, D: np.ndarray,
                    ABd: np.ndarray, failed: np.ndarray) -> None:
    """Factorise ``m`` rho values for ``n`` samples (module docstring).

    Inputs: ``A`` (n, nx, nx), ``Bv`` (n, nx, nv), ``d`` (n, nx), ``MtM`` (n, ny, ny);
    ``base`` (m, ny, ny) = ``blockdiag(2Q + 2 rho_x I, 2 rho_lam I, 2R + 2 rho_u I)``,
    ``two_rho_eta`` (m,), so ``H_y = base + 2 rho_eta M^T M``; ``PT`` (nx, nx).
    Outputs (preallocated): ``K`` (m, n, T, nv, nx), ``L`` (m, n, T, nv, nv) lower
    Cholesky factors of ``Q_vv``, ``Sd`` (m, n, T, nx) = ``S_{k+1} d``, ``D`` (m, n, ny)
    scaling, ``ABd`` (m, n, nx, ny + 1) = scaled ``[A B_v d]``; ``failed``
    (m, n): -1, or the (first, backward) step whose ``Q_vv`` is not positive definite.

    Lanes (lane ``i n + j``: rho ``i``, sample ``j``) are worked in blocks of at most
    :data:`LANE_BLOCK` in contiguous local arrays with the lane index last (so the innermost
    loops vectorise across lanes); the results are copied out per sample (so the linear
    passes of :func:`solve_project` read contiguous blocks).
    """
    m, n = base.shape[0], A.shape[0]
    nx, nv = A.shape[1], Bv.shape[2]
    ny = nx + nv
    T = K.shape[2]
    lanes = m * n
    Kl = K.reshape((lanes, T, nv, nx))
    Ll = L.reshape((lanes, T, nv, nv))
    Sdl = Sd.reshape((lanes, T, nx))
    Dl = D.reshape((lanes, ny))
    ABl = ABd.reshape((lanes, nx, ny + 1))
    fl = failed.reshape(lanes)
    LB = LANE_BLOCK
    dt = A.dtype
    Hy, S, Db = np.empty((ny, ny, LB), dt), np.empty((nx, nx, LB), dt), np.empty((ny, LB), dt)
    ABb, SAB = np.empty((nx, ny + 1, LB), dt), np.empty((nx, ny + 1, LB), dt)
    Qv, Y = np.empty((nv, ny, LB), dt), np.empty((nv, nx, LB), dt)
    Kb, Lb = np.empty((nv, nx, LB), dt), np.zeros((nv, nv, LB), dt)
    sv, fb = np.empty(LB, dt), np.empty(LB, np.int64)
    for l0 in range(0, lanes, LB):
        nl = min(LB, lanes - l0)
        _scale_lanes(A, Bv, d, MtM, base, two_rho_eta, PT, ridge, jacobi, zero, one, n,
                     l0, nl, Hy, S, Db, ABb)
        fb[:] = -1
        for k in range(T - 1, -1, -1):
            _riccati_lanes(k, nl, nx, nv, zero, one, S, ABb, Hy, SAB, Qv, Y, sv, Kb, Lb, fb)
            for l in range(nl):
                for a in range(nv):
                    for b in range(nx):
                        Kl[l0 + l, k, a, b] = Kb[a, b, l]
                    for b in range(nv):
                        Ll[l0 + l, k, a, b] = Lb[a, b, l]
                for a in range(nx):
                    Sdl[l0 + l, k, a] = SAB[a, ny, l]
        for l in range(nl):
            fl[l0 + l] = fb[l]
            for a in range(ny):
                Dl[l0 + l, a] = Db[a, l]
            for a in range(nx):
                for b in range(ny + 1):
                    ABl[l0 + l, a, b] = ABb[a, b, l]


@_jit
def _scale_lanes(A: np.ndarray, Bv: np.ndarray, d: np.ndarray, MtM: np.ndarray,
                 base: np.ndarray, two_rho_eta: np.ndarray, PT: np.ndarray, ridge: Any,
                 jacobi: bool, zero: Any, one: Any, n: int, l0: int, nl: int, Hy: np.ndarray,
                 S: np.ndarray, Db: np.ndarray, ABb: np.ndarray) -> None:
    """``H_y`` scaled to a unit diagonal (plus ridge), ``D``, the scaled ``[A B_v d]`` and
    ``S_T = D_x P_T D_x`` of the lanes ``l0 .. l0 + nl``."""
    nx, nv = A.shape[1], Bv.shape[2]
    ny = nx + nv
    for l in range(nl):
        lane = l0 + l
        i, j = lane // n, lane % n
        for a in range(ny):
            for b in range(ny):
                Hy[a, b, l] = MtM[j, a, b] * two_rho_eta[i] + base[i, a, b]
        for a in range(ny):
            h = Hy[a, a, l]
            Db[a, l] = one / np.sqrt(h) if (jacobi and h > zero) else one
        for a in range(ny):
            for b in range(ny):
                Hy[a, b, l] = Hy[a, b, l] * Db[a, l] * Db[b, l]
        for a in range(nx, ny):
            Hy[a, a, l] += ridge
        for a in range(nx):
            inv = one / Db[a, l]
            for b in range(nx):
                ABb[a, b, l] = A[j, a, b] * inv * Db[b, l]
                S[a, b, l] = PT[a, b] * Db[a, l] * Db[b, l]
            for b in range(nv):
                ABb[a, nx + b, l] = Bv[j, a, b] * inv * Db[nx + b, l]
            ABb[a, ny, l] = d[j, a] * inv


@_jit
def _riccati_lanes(k: int, nl: int, nx: int, nv: int, zero: Any, one: Any, S: np.ndarray,
                   ABb: np.ndarray, Hy: np.ndarray, SAB: np.ndarray, Qv: np.ndarray,
                   Y: np.ndarray, sv: np.ndarray, Kb: np.ndarray, Lb: np.ndarray,
                   fb: np.ndarray) -> None:
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
    for a in range(nv):  # Q_vv = L L^T
        for b in range(a + 1):
            for l in range(nl):
                sv[l] = Qv[a, nx + b, l]
            for c in range(b):
                for l in range(nl):
                    sv[l] -= Lb[a, c, l] * Lb[b, c, l]
            if a == b:
                for l in range(nl):
                    if not sv[l] > zero:
                        if fb[l] < 0:
                            fb[l] = k
                        sv[l] = one
                for l in range(nl):
                    Lb[a, a, l] = np.sqrt(sv[l])
            else:
                for l in range(nl):
                    Lb[a, b, l] = sv[l] / Lb[b, b, l]
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
                Y[a, b, l] = Y[a, b, l] / Lb[a, a, l]
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
                Kb[a, b, l] = Kb[a, b, l] / Lb[a, a, l]
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


@_jit
def solve_project(vectors: np.ndarray, delta: np.ndarray, w: np.ndarray, Mc: np.ndarray,
                  consts: np.ndarray, K: np.ndarray, L: np.ndarray, Sd: np.ndarray, D: np.ndarray,
                  ABd: np.ndarray, index: int, p: np.ndarray, shared: bool, box: np.ndarray,
                  zero: Any, z_steps: np.ndarray, z_terminal: np.ndarray, new_delta: np.ndarray
                  ) -> bool:
    """QP step (linear passes of factorisation ``index`` of ``K`` (m, n, T, nv, nx) etc.,
    :func:`factorize_batch`) and projection for every sample; ``False`` when the QP solution
    is not finite. ``vectors`` = ``(x0, g_x, g_T)`` (3, nx), ``Mc`` = ``[M c]`` (n, nlam,
    ny + 1), ``consts`` = ``(-2 G_y (ny,), 2 rho_eta, sqrt(rho_lam), sqrt(rho_eta))``.

    Gradient ``g_y = -2 G_y (delta - w)_y + (g_x, 0) + 2 rho_eta M^T (c - (delta - w)_eta)``,
    scaled by ``D``; backward ``r = g_v + B_v^T e``, ``kk = -L^-T L^-1 r``, ``e <- S_k d +
    g_x + A^T e + K^T r``; forward ``v = K x + kk``, ``x <- A x + B_v v + d``; ``eta = M y +
    c``; then the C3+ projection of ``z + w``: pairs in closed form, ``x`` clipped to the box
    ``box`` (2, nx + nu) = (lower, upper) of one step's ``(x, u)`` (``+-inf`` where
    unbounded), ``u`` replaced, when ``shared``, by the weighted mean ``sum_j p_j (z +
    w)_{j,u}`` and clipped to the box.
    """
    n, T, ns = delta.shape
    nx, nv = K.shape[4], K.shape[3]
    nlam = Mc.shape[1]
    ny = nx + nv
    x0, gx, gT = vectors[0], vectors[1], vectors[2]
    g2 = consts[:ny]
    two_rho_eta, sqrt_lam, sqrt_eta = consts[ny], consts[ny + 1], consts[ny + 2]
    gy = np.empty((T, ny), dtype=delta.dtype)
    kk = np.empty((T, nv), dtype=delta.dtype)
    eta = np.empty(nlam, dtype=delta.dtype)
    e = np.empty(nx, dtype=delta.dtype)
    r = np.empty(nv, dtype=delta.dtype)
    t = np.empty(nv, dtype=delta.dtype)
    x = np.empty(nx, dtype=delta.dtype)
    xn = np.empty(nx, dtype=delta.dtype)
    total = zero
    for j in range(n):
        Dj = D[index, j]
        ABdj = ABd[index, j]
        for k in range(T):
            for b in range(nlam):
                eta[b] = Mc[j, b, ny] - (delta[j, k, ny + b] - w[j, k, ny + b])
            for a in range(ny):
                g = (delta[j, k, a] - w[j, k, a]) * g2[a]
                if a < nx:
                    g += gx[a]
                s = zero
                for b in range(nlam):
                    s += Mc[j, b, a] * eta[b]
                gy[k, a] = (g + s * two_rho_eta) * Dj[a]
        for a in range(nx):
            e[a] = Sd[index, j, T - 1, a] + gT[a] * Dj[a]
        for k in range(T - 1, -1, -1):
            for a in range(nv):  # r = g_v + B_v^T e
                r[a] = gy[k, nx + a]
            for b in range(nx):
                h = e[b]
                for a in range(nv):
                    r[a] += h * ABdj[b, nx + a]
            Lk = L[index, j, k]
            for a in range(nv):  # L t = r
                s = r[a]
                for b in range(a):
                    s -= Lk[a, b] * t[b]
                t[a] = s / Lk[a, a]
            for a in range(nv - 1, -1, -1):  # L^T kk = -t
                s = -t[a]
                for b in range(a + 1, nv):
                    s -= Lk[b, a] * kk[k, b]
                kk[k, a] = s / Lk[a, a]
            if k > 0:
                Kk = K[index, j, k]
                for a in range(nx):  # e <- S_k d + g_x + A^T e + K^T r
                    xn[a] = gy[k, a] + Sd[index, j, k - 1, a]
                for b in range(nx):
                    h = e[b]
                    for a in range(nx):
                        xn[a] += h * ABdj[b, a]
                for b in range(nv):
                    h = r[b]
                    for a in range(nx):
                        xn[a] += h * Kk[b, a]
                for a in range(nx):
                    e[a] = xn[a]
        for a in range(nx):
            x[a] = x0[a] / Dj[a]
            z_steps[j, 0, a] = x0[a]
        for k in range(T):
            Kk = K[index, j, k]
            for a in range(nv):
                s = kk[k, a]
                for b in range(nx):
                    s += Kk[a, b] * x[b]
                t[a] = s
                z_steps[j, k, nx + a] = s * Dj[nx + a]
            for a in range(nx):
                s = ABdj[a, ny]
                for b in range(nx):
                    s += ABdj[a, b] * x[b]
                for b in range(nv):
                    s += ABdj[a, nx + b] * t[b]
                xn[a] = s
            for a in range(nx):
                x[a] = xn[a]
                if k + 1 < T:
                    z_steps[j, k + 1, a] = xn[a] * Dj[a]
                else:
                    z_terminal[j, a] = xn[a] * Dj[a]
        for k in range(T):
            for b in range(nlam):
                s = Mc[j, b, ny]
                for a in range(ny):
                    s += Mc[j, b, a] * z_steps[j, k, a]
                z_steps[j, k, ny + b] = s
            for a in range(ns):
                total += z_steps[j, k, a]
            _project_step(z_steps[j, k], w[j, k], new_delta[j, k], nx, nlam, sqrt_lam,
                          sqrt_eta, box, zero)
        for a in range(nx):
            total += z_terminal[j, a]
    nu = nv - nlam
    for k in range(T):
        for a in range(nx + nlam, nx + nlam + nu):
            lower, upper = box[0, a - nlam], box[1, a - nlam]
            if shared and n > 1:
                s = zero
                for j in range(n):
                    s += p[j] * (z_steps[j, k, a] + w[j, k, a])
                s = min(max(s, lower), upper)
                for j in range(n):
                    new_delta[j, k, a] = s
            else:
                for j in range(n):
                    new_delta[j, k, a] = min(max(new_delta[j, k, a], lower), upper)
    return bool(np.isfinite(total))


@_jit
def _project_step(z: np.ndarray, w: np.ndarray, out: np.ndarray, nx: int, nlam: int,
                  sqrt_lam: Any, sqrt_eta: Any, box: np.ndarray, zero: Any) -> None:
    """C3+ projection of ``v = z + w`` of one step into ``out``: ``x`` clipped to the box,
    ``u`` copied (the caller clips or averages it); the pairs by the one closed form
    (:func:`c3bench.solvers.admm.projection.make_c3plus_pairs`, compiled)."""
    ns = z.shape[0]
    for a in range(ns):
        out[a] = z[a] + w[a]
    for a in range(nx):
        out[a] = min(max(out[a], box[0, a]), box[1, a])
    lam, eta = _c3plus_pairs(out[nx:nx + nlam], out[ns - nlam:], sqrt_lam, sqrt_eta)
    out[nx:nx + nlam] = lam
    out[ns - nlam:] = eta
