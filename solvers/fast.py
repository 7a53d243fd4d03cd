"""Structure-exploiting, batched C3+: a Riccati solver of the C3+ QP step and the ADMM around it.

**The QP step** (family ``c3plus_qp``; :func:`problems.families.consensus_qp`) of one sample,
with ``z_k = (x_k, lam_k, u_k, eta_k)`` for ``k < T`` and the terminal ``x_T``:

    minimise   sum_{k<T} 1/2 z_k^T P_k z_k + q_k^T z_k  +  1/2 x_T^T P_T x_T + q_T^T x_T
    subject to x_0 = x0,  x_{k+1} = A x_k + B u_k + D lam_k + d,
               eta_k = E x_k + F lam_k + H u_k + c,

where for C3+ ``P_k = blockdiag(2 Q, 0, 2 R, 0) + 2 G``, ``G = diag(rho_x, rho_lam, rho_u,
rho_eta)``, ``q_k = (-2 Q x*, 0, 0, 0) - 2 G (delta_k - w_k)``, ``P_T = 2 Q_f``,
``q_T = -2 Q_f x*``. ``P`` is block diagonal in time, so the problem is an LQ problem:

1. **Eliminate eta.** With ``y_k = (x_k, v_k)``, ``v_k = (lam_k, u_k)`` (the first ``nx + nlam
   + nu`` entries of ``z_k``, in that order) and ``M = [E F H]``, ``eta_k = M y_k + c``, i.e.
   ``z_k = T_M y_k + t`` with ``T_M = [I; M]``, ``t = (0, c)``. The stage cost becomes
   ``1/2 y^T H_y y + g_y^T y + const`` with

       H_y = T_M^T P_k T_M = P_yy + P_ye M + M^T P_ey + M^T P_ee M,
       g_y = T_M^T (q_k + P_k t) = q_y + P_ye c + M^T (q_eta + P_ee c),

   for C3+ ``H_y = blockdiag(2Q + 2 rho_x I, 2 rho_lam I, 2R + 2 rho_u I) + 2 rho_eta M^T M``
   (``rho_eta`` couples ``x``, ``lam`` and ``u`` through ``M^T M``) and
   ``g_y = q_y + 2 rho_eta M^T (c - (delta - w)_eta)``.
2. **Riccati recursion** on ``x_{k+1} = A x_k + B_v v_k + d`` with ``B_v = [D B]``. Backward,
   from ``S_T = P_T``: with ``[A B_v]`` stacked as ``AB``,

       Q_yy = H_y + AB^T S_{k+1} AB,   K_k = -Q_vv^-1 Q_vx,
       S_k = Q_xx + Q_xv K_k  (symmetrised),   A_cl = A + B_v K_k,

   and for the linear terms, ``e_k = S_{k+1} d + s_{k+1}`` (``s_T = q_T``):

       kk_k = -Q_vv^-1 (g_v + B_v^T e_k),   s_k = g_x + K_k^T g_v + A_cl^T e_k.

   Forward (a **rollout**, so the dynamics hold to rounding): ``v_k = K_k x_k + kk_k``,
   ``x_{k+1} = A_cl x_k + B_v kk_k + d``; then ``eta_k = M y_k + c`` (exact by construction).

**Split.** :func:`factorize` does everything that depends on the LCS, the cost and ``rho``
(``Q_vv^-1``, ``K_k``, ``A_cl``, ``S_{k+1} d``, arranged as per-step operators
``W_e = [G_e; A_cl^T]``, ``W_g = [G_v; K^T]`` with ``G_v = -Q_vv^-1``, ``G_e = G_v B_v^T``,
so that ``[kk_k; s_k - g_x] = W_g g_v + W_e e_k``, and ``KA = [K; A_cl]``); it forms
``Q_xx = H_xx + A^T S A + Q_xv K`` and ``[Q_vx Q_vv] = H_v + B_v^T S [A B_v]`` without the
redundant ``Q_xv`` block (about 7.2k multiply-adds per sample and step plus one 8 x 8
inverse). :func:`solve_lq` does the linear passes for any ``(x0, g_y, q_T)`` in two batched
products per time step and direction. :class:`FactorCache` keeps recent factorisations keyed
by the ``rho`` values, the LCS batch identity (``LCSBatch.uid``) and the options, so a
repeated ``rho`` on an unchanged LCS costs no factorisation. With the geometric schedule the
rho of all iterations is known before the first one, so :class:`FastC3Plus` factorises the
whole schedule in one batched call over (iterations x samples) (``prefactorize``): the same
arithmetic with a tenth of the numpy calls.

**Conditioning safeguards** (the reference study's equilibrated method, section 3.2, in spirit):

* *diagonal (Jacobi) scaling* of the variables (``jacobi``, default on): ``y = D y~`` with
  ``D = diag(H_y)^-1/2`` (``x`` scaled the same at every step, so ``A~ = D_x^-1 A D_x``,
  ``B_v~ = D_x^-1 B_v D_v``, ``d~ = D_x^-1 d``, ``P_T~ = D_x P_T D_x``): every per-step Hessian
  has a unit diagonal before the recursion (the reference study's Ruiz step on ``Q``);
* *symmetrisation* of ``S_k`` (seed step 5), default on;
* *ridge* (``ridge``, default 0): ``+ ridge I`` on the ``v`` block of the scaled per-step
  Hessians, i.e. relative to their unit diagonal (a proximal term: the answer changes by
  ``O(ridge)``, so it is off by default);
* *rollout* restores ``A z = b`` (the reference study's projection step, by construction): the
  forward pass is a rollout of the (scaled) dynamics and ``eta`` is computed from the LCS row, so
  the equality residual is rounding only (float32: at most ``1.6e-6`` on the quick suite's
  ``c3plus_qp`` instances, against the reference study's ``1e-4`` after projection);
  ``rollout=True`` rolls the states out once more in the original, unscaled coordinates (measured:
  no difference, so off by default).

**Batching.** Every array has a leading sample axis; all products are numpy ``matmul``
broadcasts, with no Python loop over samples (the only loops run over the ``T`` time steps).

**ADMM** (:class:`FastC3Plus`): the semantics of :mod:`solvers.c3`'s C3+ (``variant
"c3plus"``): QP step, closed-form projection of ``z + w`` (``x`` and ``u`` copied, each pair
``(lam_i, eta_i)`` keeps the larger of ``sqrt(rho_lam) [v_lam]_+`` and ``sqrt(rho_eta)
[v_eta]_+``, ties keep ``lam``), dual update ``w <- w + z - delta``, the rho schedule
(``geometric``, ``adaptive`` or ``residual_balancing`` via :func:`solvers.c3.rho_multiplier`)
with the scaled dual rescaled by ``rho_old / rho_new``, fixed iterations (or the residual
stopping rule), output ``u_0`` of ``delta`` clipped to the force limit, warm start by
:func:`solvers.c3.shift_warm_start` (:class:`FastC3PlusController`).

**Robust variant with shared inputs: a different splitting.** :func:`solvers.c3.solve_robust`
solves one stacked QP in which the samples share ``u_k``. Here the samples' QPs stay
decoupled and the consensus on ``u`` moves into the projection, which is still separable:

    delta = argmin sum_j p_j ||delta_j - (z_j + w_j)||^2_G  s.t.  delta_j in C_j,
            delta_{j,u} = u_bar  for every j,

gives the per-sample closed form for ``(lam, eta)``, ``delta_{j,x} = z_{j,x} + w_{j,x}`` and
``u_bar_k = sum_j p_j (z_{j,u_k} + w_{j,u_k})`` (a weighted mean; ``rho_u`` cancels); the
dual ``w_j <- w_j + z_j - delta_j`` then carries each sample's disagreement with ``u_bar``.
Both are consensus ADMM for the same robust problem; the iterates differ, but with ``n``
identical samples both reduce to the nominal controller (tested), and with ``n = 1`` this is
exactly :func:`solvers.c3.solve_c3`'s C3+ (tested against a high-accuracy QP backend).
With ``shared_inputs=False`` the samples are ``n`` independent C3+ problems (shared ``rho``).

**Registry backend** ``c3plus_riccati``
(:class:`c3bench.solvers.backends.c3plus_riccati.RiccatiBackend`, family ``c3plus_qp``,
float64 and float32; :func:`solve_c3plus_qp` here): reads the per-step blocks of ``P`` and
``q`` (rejects a ``P`` that is not block diagonal in time), the LCS and ``x0``, checks that
``A z = b`` is the LCS's structure, solves, and returns the equality duals from the
stationarity conditions of the ``x``, ``eta`` columns, by a backward recursion in float64
(``y_eta_k = -(P z + q)_{eta_k}``, ``y_{T-1} = -(P z + q)_{x_T}``,
``y_{k-1} = -(P z + q)_{x_k} + A^T y_k + E^T y_eta_k``,
``y_x0 = -(P z + q)_{x_0} + A^T y_0 + E^T y_eta_0``), so the dual residual measures the
``lam``, ``u`` rows, where the solve's own error shows.
"""

from __future__ import annotations

import math
import time
from collections import OrderedDict
from collections.abc import Hashable, Mapping, Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from c3bench.problems.families import dynamics_rows
from c3bench.problems.instance import Problem
from c3bench.problems.lcs import LCSBatch
from c3bench.problems.mpc import MPC, HorizonLayout
from c3bench.problems.names import BLOCKS, Block, Precision
from c3bench.solvers.admm.controller import FastC3PlusController, solve_batched
from c3bench.solvers.admm.kernel import KernelFailure, StepInputs
from c3bench.solvers.admm.options import C3Options
from c3bench.solvers.admm.projection import make_step_projection
from c3bench.solvers.admm.schedules import schedule_for
from c3bench.solvers.admm.solution import FastSolution, FastTimings
from c3bench.solvers.admm.stacked import box_of_step, projection_weight_vector

__all__ = [
    "FactorCache",
    "FastC3Plus",
    "FastC3PlusController",
    "FastSolution",
    "FastTimings",
    "RiccatiFactor",
    "RiccatiOptions",
    "factorize",
    "fast_options",
    "solve_c3plus_qp",
    "solve_lq",
]



# --- options, factor, cache -------------------------------------------------------------------
@dataclass(frozen=True)
class RiccatiOptions:
    """Numerical options of the Riccati solve (module docstring, "conditioning safeguards").

    Attributes
    ----------
    precision
        ``float64`` or ``float32``: every array of the factorisation and the solve.
    jacobi
        Scale the variables by ``diag(H_y)^-1/2`` before the recursion.
    ridge
        ``+ ridge I`` on the ``v`` block of the (scaled) per-step Hessians; 0 = exact.
    symmetrize
        ``S_k <- (S_k + S_k^T) / 2``.
    rollout
        Roll the states out again in the original coordinates after the solve (default off:
        the forward pass already is a rollout).
    """

    precision: str = Precision.FLOAT64
    jacobi: bool = True
    ridge: float = 0.0
    symmetrize: bool = True
    rollout: bool = False

    def __post_init__(self) -> None:
        if self.precision not in tuple(Precision):
            raise ValueError(f"precision must be one of {tuple(map(str, Precision))}, got "
                             f"{self.precision!r}")
        if not (math.isfinite(self.ridge) and self.ridge >= 0):
            raise ValueError(f"ridge must be a finite number >= 0, got {self.ridge!r}")

    @property
    def dtype(self) -> type[np.floating[Any]]:
        """The scalar type of ``precision``."""
        return Precision(self.precision).dtype.type

    def key(self) -> tuple[Hashable, ...]:
        return (self.precision, self.jacobi, self.ridge, self.symmetrize)


@dataclass
class RiccatiFactor:
    """A factorised batched LQ problem (everything that depends on LCS, cost and rho).

    Arrays carry the batch shape ``b`` (e.g. ``(n,)`` samples, or ``(m, n)`` for ``m`` rho
    values at once) in front. Per step ``k`` (lists): ``KA[k] = [K_k; A_cl,k]`` (b, nv+nx,
    nx) and ``We[k] = [G_e,k; A_cl,k^T]`` (b, nv+nx, nx); stacked over steps:
    ``Wg = [G_v,k; K_k^T]`` (b, T, nv+nx, nv) and ``Sd`` (b, T, nx) with ``Sd[..., k, :] =
    S_{k+1} d``. ``D`` (b, ny) is the variable scaling (``None`` without Jacobi); ``A``,
    ``Bv``, ``d`` are the original dynamics and ``Bv_s``, ``d_s`` the scaled ones.
    """

    nx: int
    nv: int
    horizon: int
    KA: list[np.ndarray]
    We: list[np.ndarray]
    Wg: np.ndarray
    Sd: np.ndarray
    D: np.ndarray | None
    A: np.ndarray
    Bv: np.ndarray
    d: np.ndarray
    Bv_s: np.ndarray
    d_s: np.ndarray
    options: RiccatiOptions

    @property
    def batch_shape(self) -> tuple[int, ...]:
        return tuple(self.Wg.shape[:-3])

    @property
    def nbytes(self) -> int:
        arrays = [*self.KA, *self.We, self.Wg, self.Sd]
        return int(sum(a.nbytes for a in arrays))

    def take(self, index: int) -> RiccatiFactor:
        """The factor of entry ``index`` of the first batch axis (views, no copies)."""
        def pick(array: np.ndarray, core: int) -> np.ndarray:
            return array[index] if array.ndim > core else array

        return RiccatiFactor(
            nx=self.nx, nv=self.nv, horizon=self.horizon,
            KA=[a[index] for a in self.KA], We=[a[index] for a in self.We],
            Wg=self.Wg[index], Sd=self.Sd[index],
            D=None if self.D is None else self.D[index],
            A=pick(self.A, len(self.batch_shape) + 1), Bv=pick(self.Bv, len(self.batch_shape) + 1),
            d=pick(self.d, len(self.batch_shape)), Bv_s=pick(self.Bv_s, len(self.batch_shape) + 1),
            d_s=pick(self.d_s, len(self.batch_shape)), options=self.options)


class FactorCache:
    """A small LRU cache of :class:`RiccatiFactor` objects.

    Keys are built by the caller from the rho values, the LCS identity and the options
    (:meth:`FastC3Plus.factor_key`). Bounded by ``max_entries`` and ``max_bytes`` (the bytes
    of the factors' own arrays; a factor taken from a batched call keeps its whole batch
    alive until every entry of that call is evicted).
    """

    def __init__(self, max_entries: int = 16, max_bytes: int = 512 * 2**20) -> None:
        if max_entries < 0 or max_bytes < 0:
            raise ValueError("cache limits must be >= 0")
        self.max_entries = int(max_entries)
        self.max_bytes = int(max_bytes)
        self._entries: OrderedDict[Hashable, tuple[RiccatiFactor, int]] = OrderedDict()
        self._bytes = 0
        self.hits = 0
        self.misses = 0

    def __len__(self) -> int:
        return len(self._entries)

    @property
    def nbytes(self) -> int:
        return self._bytes

    def get(self, key: Hashable) -> RiccatiFactor | None:
        entry = self._entries.get(key)
        if entry is None:
            self.misses += 1
            return None
        self.hits += 1
        self._entries.move_to_end(key)
        return entry[0]

    def put(self, key: Hashable, factor: RiccatiFactor) -> None:
        size = factor.nbytes
        if self.max_entries == 0 or size > self.max_bytes:
            return
        previous = self._entries.pop(key, None)
        if previous is not None:
            self._bytes -= previous[1]
        self._entries[key] = (factor, size)
        self._bytes += size
        while self._entries and (len(self._entries) > self.max_entries
                                 or self._bytes > self.max_bytes):
            _, (_, dropped) = self._entries.popitem(last=False)
            self._bytes -= dropped

    def clear(self) -> None:
        self._entries.clear()
        self._bytes = 0
        self.hits = self.misses = 0


# --- the LQ core ------------------------------------------------------------------------------
def _swap(array: np.ndarray) -> np.ndarray:
    return np.swapaxes(array, -1, -2)


def factorize(A: np.ndarray, Bv: np.ndarray, d: np.ndarray, Hy: np.ndarray, PT: np.ndarray,
              horizon: int, options: RiccatiOptions | None = None, per_step: bool = False
              ) -> RiccatiFactor:
    """Backward Riccati recursion of the batched LQ problem (module docstring, step 2).

    Parameters
    ----------
    A, Bv, d
        (..., nx, nx), (..., nx, nv), (..., nx): ``x_{k+1} = A x_k + Bv v_k + d``.
    Hy
        Stage Hessians over ``y = (x, v)``: (..., ny, ny) for every step, or with
        ``per_step`` (..., T, ny, ny).
    PT
        (..., nx, nx) terminal Hessian.
    horizon
        ``T``.
    options
        Precision and safeguards.
    per_step
        Whether ``Hy`` has a time-step axis.

    The leading (batch) dimensions broadcast against each other, so one call can factorise
    ``n`` samples for ``m`` values of rho (``Hy`` of shape (m, n, ny, ny), ``A`` (n, nx, nx)).

    Raises
    ------
    numpy.linalg.LinAlgError
        When a ``Q_vv`` is singular.
    """
    options = options or RiccatiOptions()
    dtype = options.dtype
    A = np.asarray(A, dtype=dtype)
    Bv = np.asarray(Bv, dtype=dtype)
    d = np.asarray(d, dtype=dtype)
    Hy = np.asarray(Hy, dtype=dtype)
    PT = np.asarray(PT, dtype=dtype)
    nx, nv = A.shape[-1], Bv.shape[-1]
    ny = nx + nv
    T = int(horizon)
    A0, Bv0, d0 = A, Bv, d
    D: np.ndarray | None = None
    if options.jacobi:
        diagonal = np.diagonal(Hy[..., 0, :, :] if per_step else Hy, axis1=-2, axis2=-1)
        D = 1.0 / np.sqrt(np.where(diagonal > 0, diagonal, dtype(1)))
        Dx, Dv = D[..., :nx], D[..., nx:]
        inv_x = 1.0 / Dx
        if per_step:
            Hy = Hy * D[..., None, :, None] * D[..., None, None, :]
        else:
            Hy = Hy * D[..., :, None] * D[..., None, :]
        A = A * inv_x[..., :, None] * Dx[..., None, :]
        Bv = Bv * inv_x[..., :, None] * Dv[..., None, :]
        d = d * inv_x
        PT = PT * Dx[..., :, None] * Dx[..., None, :]
    if options.ridge > 0:
        ridge = np.zeros((ny, ny), dtype=dtype)
        ridge[nx:, nx:] = options.ridge * np.eye(nv, dtype=dtype)
        Hy = Hy + ridge
    batch = np.broadcast_shapes(A.shape[:-2], Bv.shape[:-2], d.shape[:-1], PT.shape[:-2],
                                Hy.shape[:-3] if per_step else Hy.shape[:-2])
    A = np.broadcast_to(A, (*batch, nx, nx))
    Bv = np.broadcast_to(Bv, (*batch, nx, nv))
    d = np.broadcast_to(d, (*batch, nx))
    ABd = np.concatenate([A, Bv, d[..., None]], axis=-1)  # (b, nx, ny + 1)
    AT = np.ascontiguousarray(_swap(A))
    BvT = np.ascontiguousarray(_swap(Bv))
    Hxx, Hv = Hy[..., :nx, :nx], Hy[..., nx:, :]
    KA: list[np.ndarray] = [np.empty(0)] * T
    We: list[np.ndarray] = [np.empty(0)] * T
    Wg: list[np.ndarray] = [np.empty(0)] * T
    Sd: list[np.ndarray] = [np.empty(0)] * T  # Sd[k] = S_{k+1} d
    S = PT
    for k in range(T - 1, -1, -1):
        SABd = S @ ABd  # [S A | S B_v | S d]
        Qv = BvT @ SABd[..., :ny]  # [Q_vx | Q_vv] (Q_xv = Q_vx^T is not formed)
        Qv += Hv[..., k, :, :] if per_step else Hv
        Gv = np.linalg.inv(Qv[..., nx:])
        np.negative(Gv, out=Gv)
        Qvx = Qv[..., :nx]
        Z = Gv @ np.concatenate([Qvx, BvT], axis=-1)  # [K | G_e]
        K = Z[..., :nx]
        Acl = Bv @ K
        Acl += A
        KA[k] = np.concatenate([K, Acl], axis=-2)
        We[k] = np.concatenate([Z[..., nx:], _swap(Acl)], axis=-2)
        Wg[k] = np.concatenate([Gv, _swap(K)], axis=-2)
        Sd[k] = SABd[..., ny]
        S = AT @ SABd[..., :nx]  # Q_xx = H_xx + A^T S A + Q_xv K
        S += Hxx[..., k, :, :] if per_step else Hxx
        S += _swap(Qvx) @ K
        if options.symmetrize:
            S = 0.5 * (S + _swap(S))
    return RiccatiFactor(nx=nx, nv=nv, horizon=T, KA=KA, We=We, Wg=np.stack(Wg, axis=-3),
                         Sd=np.stack(Sd, axis=-2), D=D, A=A0, Bv=Bv0, d=d0, Bv_s=Bv, d_s=d,
                         options=options)


def solve_lq(factor: RiccatiFactor, x0: np.ndarray, gy: np.ndarray, gT: np.ndarray
             ) -> tuple[np.ndarray, np.ndarray]:
    """Linear passes of the factorised LQ problem.

    Parameters
    ----------
    factor
        From :func:`factorize`, batch shape ``b``.
    x0
        (b, nx) initial states (broadcastable, e.g. (nx,) for all samples).
    gy
        (b, T, ny) stage gradients over ``y = (x, v)``.
    gT
        (b, nx) terminal gradient (broadcastable).

    Returns
    -------
    xs, vs
        (b, T+1, nx) states and (b, T, nv) inputs ``v = (lam, u)``, in the factor's dtype.

    Backward: ``[kk_k; s_k - g_x,k] = W_g,k g_v,k + W_e,k e_k`` with ``e_k = S_{k+1} d + s_{k+1}``
    (``s_T = g_T``); forward: ``[v_k; x_{k+1}] = KA_k x_k + [kk_k; B_v kk_k + d]``.
    """
    dtype = factor.options.dtype
    nx, nv, T = factor.nx, factor.nv, factor.horizon
    batch = factor.batch_shape
    gy = np.asarray(gy, dtype=dtype)
    x0 = np.broadcast_to(np.asarray(x0, dtype=dtype), (*batch, nx))
    gT = np.asarray(gT, dtype=dtype)
    D = factor.D
    if D is not None:
        gy = gy * D[..., None, :]
        gT = gT * D[..., :nx]
        x_start = x0 / D[..., :nx]
    else:
        x_start = x0
    pre = factor.Wg @ gy[..., nx:, None]  # (b, T, nv + nx, 1)
    shift = gy[..., :nx].copy()
    shift[..., 1:, :] += factor.Sd[..., :-1, :]
    pre[..., nv:, 0] += shift
    e = (factor.Sd[..., T - 1, :] + gT)[..., None]
    outs: list[np.ndarray] = [np.empty(0)] * T
    for k in range(T - 1, -1, -1):
        out = factor.We[k] @ e
        out += pre[..., k, :, :]
        outs[k] = out
        e = out[..., nv:, :]
    kk = np.stack(outs, axis=-3)[..., :nv, :]  # (b, T, nv, 1)
    Bkk = factor.Bv_s[..., None, :, :] @ kk
    Bkk += factor.d_s[..., None, :, None]
    addend = np.concatenate([kk, Bkk], axis=-2)
    x = x_start[..., None]
    ys = []
    for k in range(T):
        y = factor.KA[k] @ x
        y += addend[..., k, :, :]
        ys.append(y)
        x = y[..., nv:, :]
    Y = np.stack(ys, axis=-3)[..., 0]  # (b, T, nv + nx) = (v_k, x_{k+1})
    vs = Y[..., :nv]
    if D is not None:
        vs = vs * D[..., None, nx:]
    if factor.options.rollout:
        xs = np.empty((*batch, T + 1, nx), dtype=dtype)
        xs[..., 0, :] = x0
        drift = (factor.Bv[..., None, :, :] @ vs[..., None])[..., 0]
        drift += factor.d[..., None, :]
        A = factor.A
        for k in range(T):
            xs[..., k + 1, :] = (A @ xs[..., k, :, None])[..., 0] + drift[..., k, :]
    else:
        states = Y[..., nv:]
        if D is not None:
            states = states * D[..., None, :nx]
        xs = np.concatenate([x0[..., None, :], states], axis=-2)
    return xs, vs


# --- problem-level helpers --------------------------------------------------------------------
def reduce_stage(P_stage: np.ndarray, q_stage: np.ndarray, M: np.ndarray, c: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Eliminate ``eta = M y + c`` from stage costs ``1/2 z^T P z + q^T z`` (module step 1).

    ``P_stage`` (..., T, ns, ns), ``q_stage`` (..., T, ns), ``M`` (..., nlam, ny) and ``c``
    (..., nlam) with ``ns = ny + nlam``; returns ``H_y = T_M^T P T_M`` (..., T, ny, ny) and
    ``g_y = T_M^T (q + P t)`` (..., T, ny) with ``T_M = [I; M]``, ``t = (0, c)``.
    """
    ny = M.shape[-1]
    eye = np.broadcast_to(np.eye(ny, dtype=M.dtype), (*M.shape[:-2], ny, ny))
    TM = np.concatenate([eye, M], axis=-2)[..., None, :, :]  # (..., 1, ns, ny)
    Hy = _swap(TM) @ P_stage @ TM
    Hy = 0.5 * (Hy + _swap(Hy))
    t = np.concatenate([np.zeros((*c.shape[:-1], ny), dtype=c.dtype), c], axis=-1)
    shifted = q_stage + (P_stage @ t[..., None, :, None])[..., 0]
    gy = (_swap(TM) @ shifted[..., None])[..., 0]
    return Hy, gy


def equality_duals(problem: Problem, z: np.ndarray) -> np.ndarray:
    """Equality duals of a ``c3plus_qp`` instance from stationarity (module docstring).

    Rows in :func:`problems.families.consensus_qp`'s order: ``x_0 = x0`` (nx), dynamics
    (T x nx), then ``eta`` rows (T x nlam); sign convention ``P z + q + A^T y = 0``.
    """
    layout = HorizonLayout.from_json(problem.meta["layout"])
    lcs = problem.lcs
    assert lcs is not None
    T, nx, nlam = layout.horizon, layout.nx, layout.nlam
    gradient = problem.P @ z + problem.q
    y0 = np.zeros(nx)
    y_dyn = np.zeros((T, nx))
    y_eta = np.zeros((T, nlam))
    for k in range(T):
        y_eta[k] = -gradient[layout.index(k, "eta")]
    y_dyn[T - 1] = -gradient[layout.index(T, "x")]
    for k in range(T - 1, 0, -1):
        y_dyn[k - 1] = -gradient[layout.index(k, "x")] + lcs.A.T @ y_dyn[k] \
            + lcs.E.T @ y_eta[k]
    y0[:] = -gradient[layout.index(0, "x")] + lcs.A.T @ y_dyn[0] + lcs.E.T @ y_eta[0]
    return np.concatenate([y0, y_dyn.ravel(), y_eta.ravel()])


def _structure_error(problem: Problem, layout: HorizonLayout) -> str:
    """``""`` when ``A``, ``b`` are exactly the C3+ rows of ``problem.lcs``, else why not."""
    lcs = problem.lcs
    if lcs is None:
        return "no LCS attached"
    if problem.A is None or problem.b is None:
        return "no equality rows"
    expected, b = dynamics_rows(layout, lcs, problem.b[: layout.nx])
    if problem.A.shape != expected.shape:
        return f"A has shape {problem.A.shape}, expected {expected.shape}"
    if not np.array_equal(expected, problem.A):
        return "A is not the C3+ structure of the attached LCS"
    if not np.array_equal(b, problem.b):
        return "b is not (x0, d, ..., d, c, ..., c)"
    return ""


def _stage_blocks(problem: Problem, layout: HorizonLayout
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, str]:
    """Per-step ``P_k``, ``q_k``, terminal ``P_T``, ``q_T``; a reason when ``P`` couples steps."""
    T, ns = layout.horizon, layout.step_size
    steps = T * ns
    P, q = problem.P, problem.q
    mask = np.zeros_like(P, dtype=bool)
    for k in range(T):
        mask[k * ns:(k + 1) * ns, k * ns:(k + 1) * ns] = True
    mask[steps:, steps:] = True
    if np.any(P[~mask] != 0):
        return (np.zeros(0), np.zeros(0), np.zeros(0), np.zeros(0),
                "P couples different time steps (not block diagonal in time)")
    P_stage = np.stack([P[k * ns:(k + 1) * ns, k * ns:(k + 1) * ns] for k in range(T)])
    q_stage = q[:steps].reshape(T, ns)
    return P_stage, q_stage, P[steps:, steps:], q[steps:], ""


@dataclass
class StructuredQP:
    """A ``c3plus_qp`` instance split into its structure: per-step Hessian blocks
    ``P_stage`` (T, ns, ns) and gradients ``q_stage`` (T, ns), terminal ``P_T``, ``q_T`` (``PT``,
    ``q_terminal``), the LCS blocks ``M = [E F H]``, ``B_v = [D B]`` and ``x0`` (all float64)."""

    layout: HorizonLayout
    P_stage: np.ndarray
    q_stage: np.ndarray
    PT: np.ndarray
    q_terminal: np.ndarray
    A: np.ndarray
    Bv: np.ndarray
    d: np.ndarray
    M: np.ndarray
    c: np.ndarray
    x0: np.ndarray


def structure_of(problem: Problem) -> StructuredQP:
    """Read the C3+ structure of a ``c3plus_qp`` instance; ``ValueError`` when it has none
    (``P`` not block diagonal in time, or ``A z = b`` not the attached LCS's rows)."""
    layout = HorizonLayout.from_json(problem.meta["layout"])
    reason = _structure_error(problem, layout)
    P_stage, q_stage, PT, qT, why = _stage_blocks(problem, layout)
    reason = reason or why
    if reason:
        raise ValueError(reason)
    lcs = problem.lcs
    assert lcs is not None and problem.b is not None
    return StructuredQP(layout=layout, P_stage=P_stage, q_stage=q_stage, PT=PT, q_terminal=qT,
                        A=lcs.A, Bv=np.hstack([lcs.D, lcs.B]), d=lcs.d,
                        M=np.hstack([lcs.E, lcs.F, lcs.H]), c=lcs.c,
                        x0=problem.b[:layout.nx].copy())


def solve_structured(qp: StructuredQP, options: RiccatiOptions | None = None) -> np.ndarray:
    """The primal ``z`` (float64 copy of the working precision's answer) of a
    :class:`StructuredQP`: eliminate ``eta``, factorise, solve, recover ``eta``."""
    options = options or RiccatiOptions()
    dtype = options.dtype
    Hy, gy = reduce_stage(qp.P_stage, qp.q_stage, qp.M, qp.c)
    factor = factorize(qp.A[None], qp.Bv[None], qp.d[None], Hy[None].astype(dtype),
                       qp.PT[None], qp.layout.horizon, options, per_step=True)
    xs, vs = solve_lq(factor, qp.x0[None], gy[None], qp.q_terminal[None])
    ys = np.concatenate([xs[0, :-1], vs[0]], axis=1)  # (T, ny)
    eta = ys @ qp.M.astype(dtype).T + qp.c.astype(dtype)
    steps = np.concatenate([ys, eta], axis=1)
    return np.concatenate([steps.ravel(), xs[0, -1]]).astype(np.float64)


def solve_c3plus_qp(problem: Problem, options: RiccatiOptions | None = None
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Solve a ``c3plus_qp`` :class:`problems.instance.Problem` by the Riccati recursion.

    Returns ``(z, y)``: the primal vector (float64 copy of the working precision's answer)
    and the equality duals (:func:`equality_duals`). Raises ``ValueError`` when the instance
    does not have the C3+ structure.
    """
    z = solve_structured(structure_of(problem), options)
    return z, equality_duals(problem, z)


# --- batched C3+ ADMM -------------------------------------------------------------------------
def project_c3plus_batch(v: np.ndarray, nx: int, nlam: int, nu: int, rho_lam: float,
                         rho_eta: float) -> np.ndarray:
    """C3+'s projection of steps ``v`` (..., ns) with scalar weights (no validation; any dtype).

    :func:`c3bench.solvers.admm.projection.make_step_projection` without limits or shared inputs.
    """
    project = make_step_projection(np, nx, nlam, nu)
    inf = np.full(nx + nu, np.inf, dtype=v.dtype)
    out: np.ndarray = project(v, np.sqrt(v.dtype.type(rho_lam)), np.sqrt(v.dtype.type(rho_eta)),
                              -inf, inf, None, False)
    return out


@dataclass
class _Prepared:
    """Per-LCS data in the working precision (independent of rho, x0, delta, w)."""

    uid: int
    A: np.ndarray
    Bv: np.ndarray
    d: np.ndarray
    M: np.ndarray  # (n, nlam, ny)
    MT: np.ndarray  # (n, 1, ny, nlam)
    c: np.ndarray  # (n, nlam)
    MtM: np.ndarray  # (n, ny, ny)


class FastC3Plus:
    """Batched C3+ ADMM for ``n`` LCS samples with a Riccati QP step (module docstring).

    Parameters
    ----------
    mpc
        Cost, goal, horizon and force limit (shared by all samples).
    options
        The controller options of :class:`solvers.c3.C3Options` (variant must be
        ``c3plus``; ``qp_backend`` and ``projection_backend`` are ignored; no input bounds).
    riccati
        Precision and safeguards of the QP step.
    shared_inputs
        Robust variant (samples share ``u``; consensus in the projection) or independent
        problems.
    cache
        Factorisation cache (a new one with 16 entries when ``None``).
    record_residuals
        Compute the consensus and dual residuals every iteration (always done when the
        schedule or the stopping rule needs them).
    prefactorize
        With the geometric schedule the rho of every iteration is known before the first
        one, so all iterations' factorisations are computed up front in one batched call
        over (iterations x samples) (:meth:`factors`): the same arithmetic, a tenth of the
        numpy calls. Other schedules factorise (or hit the cache) iteration by iteration.
    chunk_bytes
        Largest size of the factors computed by one batched call.
    """

    def __init__(self, mpc: MPC, options: C3Options | None = None,
                 riccati: RiccatiOptions | None = None, shared_inputs: bool = True,
                 cache: FactorCache | None = None, record_residuals: bool = False,
                 prefactorize: bool = True, chunk_bytes: int = 64 * 2**20) -> None:
        options = options or C3Options(keep_iterates=False)
        options.check_batched_c3plus("FastC3Plus")
        self.mpc = mpc
        self.options = options
        self.riccati = riccati or RiccatiOptions()
        self.shared_inputs = shared_inputs
        self.cache = cache if cache is not None else FactorCache()
        self.record_residuals = record_residuals
        self.prefactorize = prefactorize
        self.chunk_bytes = int(chunk_bytes)
        nx, nu = mpc.nx, mpc.nu
        self.nx, self.nu = nx, nu
        self._prepared: _Prepared | None = None
        self._vectors: dict[tuple[Any, ...], np.ndarray] = {}
        dtype = self.riccati.dtype
        Q, R, Qf = (np.asarray(m, dtype=np.float64) for m in (mpc.Q, mpc.R, mpc.Q_f))
        self._Q2 = 2 * Q
        self._R2 = 2 * R
        self._PT = (2 * Qf).astype(dtype)
        self._gx = (-2 * Q @ mpc.x_target).astype(dtype)
        self._gT = (-2 * Qf @ mpc.x_target).astype(dtype)
        self.timings = FastTimings()
        self.info: dict[str, Any] = {}
        self._hits0 = self._misses0 = 0

    # -- per LCS / per rho ---------------------------------------------------------------------
    def prepare(self, lcs: LCSBatch) -> _Prepared:
        """Working-precision LCS data, kept until another batch is given."""
        if self._prepared is not None and self._prepared.uid == lcs.uid:
            return self._prepared
        if lcs.nx != self.nx or lcs.nu != self.nu:
            raise ValueError(f"LCS (nx={lcs.nx}, nu={lcs.nu}) and MPC (nx={self.nx}, "
                             f"nu={self.nu}) disagree")
        dtype = self.riccati.dtype
        M = np.concatenate([lcs.E, lcs.F, lcs.H], axis=2).astype(dtype)
        prepared = _Prepared(
            uid=lcs.uid, A=lcs.A.astype(dtype),
            Bv=np.concatenate([lcs.D, lcs.B], axis=2).astype(dtype),
            d=lcs.d.astype(dtype), M=M, MT=np.ascontiguousarray(_swap(M))[:, None],
            c=lcs.c.astype(dtype), MtM=_swap(M) @ M)
        self._prepared = prepared
        return prepared

    def factor_key(self, lcs: LCSBatch, rho: Mapping[str, float]) -> tuple[Hashable, ...]:
        """Cache key: LCS identity, the four rho values, the horizon and the options."""
        return (lcs.uid, *(float(rho[key]) for key in BLOCKS), self.mpc.horizon,
                id(self.mpc), *self.riccati.key())

    def stage_hessian(self, prepared: _Prepared, rho: Mapping[str, float]) -> np.ndarray:
        """``H_y(rho)`` (n, ny, ny) of the C3+ stage cost (module docstring, step 1)."""
        nx, nlam, nu = self.nx, prepared.M.shape[1], self.nu
        ny = nx + nlam + nu
        base = np.zeros((ny, ny))
        base[:nx, :nx] = self._Q2 + 2 * rho[Block.X] * np.eye(nx)
        base[nx:nx + nlam, nx:nx + nlam] = 2 * rho[Block.LAM] * np.eye(nlam)
        base[nx + nlam:, nx + nlam:] = self._R2 + 2 * rho[Block.U] * np.eye(nu)
        Hy = prepared.MtM * (2 * rho[Block.ETA])
        Hy += base.astype(self.riccati.dtype)
        return Hy

    def factor(self, lcs: LCSBatch, rho: Mapping[str, float]) -> tuple[RiccatiFactor, bool]:
        """The factorisation for ``(lcs, rho)`` from the cache or new; ``(factor, hit)``."""
        return self.factors(lcs, [rho])[0]

    def factors(self, lcs: LCSBatch, rhos: Sequence[Mapping[str, float]]
                ) -> list[tuple[RiccatiFactor, bool]]:
        """Factorisations for several rho values: cached ones reused, the others computed in
        batched calls over (rho values x samples), at most ``chunk_bytes`` of factors per
        call; each new one is put into the cache. Returns ``(factor, hit)`` per rho."""
        keys = [self.factor_key(lcs, rho) for rho in rhos]
        out: list[tuple[RiccatiFactor, bool] | None] = []
        missing: list[int] = []
        for index, key in enumerate(keys):
            cached = self.cache.get(key)
            out.append(None if cached is None else (cached, True))
            if cached is None:
                missing.append(index)
        if missing:
            prepared = self.prepare(lcs)
            n = prepared.A.shape[0]
            itemsize = np.dtype(self.riccati.dtype).itemsize
            nv = prepared.Bv.shape[-1]
            per_rho = n * self.mpc.horizon * itemsize * (
                (nv + self.nx) * (2 * self.nx + nv) + self.nx)
            chunk = max(1, int(self.chunk_bytes // max(per_rho, 1)))
            for start in range(0, len(missing), chunk):
                part = missing[start:start + chunk]
                Hy = np.stack([self.stage_hessian(prepared, rhos[i]) for i in part])
                batched = factorize(prepared.A, prepared.Bv, prepared.d, Hy, self._PT,
                                    self.mpc.horizon, self.riccati)
                for j, index in enumerate(part):
                    factor = batched.take(j)
                    self.cache.put(keys[index], factor)
                    out[index] = (factor, False)
        return [entry for entry in out if entry is not None]

    def planned_rhos(self) -> list[dict[str, float]] | None:
        """Every iteration's rho when the schedule does not depend on the data (geometric)."""
        return schedule_for(self.options).plan(self.options.rho0, self.options.admm_iterations)

    def layout_of(self, lcs: LCSBatch) -> HorizonLayout:
        """The C3+ step layout ``(x, lam, u, eta)`` of ``lcs``."""
        return HorizonLayout(lcs.nx, lcs.nlam, lcs.nu, lcs.nlam, self.mpc.horizon)

    def qp_step(self, lcs: LCSBatch, rho: Mapping[str, float], x0: np.ndarray,
                delta: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The QP step for every sample: ``(z_steps (n, T, ns), z_terminal (n, nx))``."""
        factor, _ = self.factor(lcs, rho)
        return self._qp_solve(self.prepare(lcs), factor, rho, x0, delta, w)

    def _qp_solve(self, prepared: _Prepared, factor: RiccatiFactor, rho: Mapping[str, float],
                  x0: np.ndarray, delta: np.ndarray, w: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray]:
        nx = self.nx
        nlam = prepared.M.shape[1]
        ny = nx + nlam + self.nu
        anchor = delta - w
        g2 = self._g2(rho, ny, nlam)
        gy = anchor[:, :, :ny] * g2
        gy[:, :, :nx] += self._gx
        eta_term = prepared.c[:, None, :] - anchor[:, :, ny:]
        gy += (prepared.MT @ eta_term[..., None])[..., 0] * (2 * rho[Block.ETA])
        xs, vs = solve_lq(factor, x0, gy, np.broadcast_to(self._gT, (gy.shape[0], nx)))
        ys = np.concatenate([xs[:, :-1], vs], axis=2)  # (n, T, ny)
        eta = (prepared.M[:, None] @ ys[..., None])[..., 0]
        eta += prepared.c[:, None, :]
        return np.concatenate([ys, eta], axis=2), xs[:, -1]

    def _g2(self, rho: Mapping[str, float], ny: int, nlam: int) -> np.ndarray:
        """``-2 G_y`` as a (ny,) vector in the working precision (memoised)."""
        key = ("g2", ny, nlam, rho[Block.X], rho[Block.LAM], rho[Block.U])
        out = self._vectors.get(key)
        if out is None:
            nx = self.nx
            out = np.empty(ny, dtype=self.riccati.dtype)
            out[:nx] = -2 * rho[Block.X]
            out[nx:nx + nlam] = -2 * rho[Block.LAM]
            out[nx + nlam:] = -2 * rho[Block.U]
            self._vectors[key] = out
        return out

    # -- the kernel of the one ADMM (solvers/admm/loop.py) -----------------------------------
    name = "riccati"

    @property
    def dtype(self) -> Any:
        return self.riccati.dtype

    def bind(self, lcs: LCSBatch) -> None:
        """Use ``lcs`` for the next control step (:func:`solvers.admm.solve_batched`)."""
        self.lcs = lcs
        self.layout = self.layout_of(lcs)
        self._project = make_step_projection(np, lcs.nx, lcs.nlam, lcs.nu)

    def start(self, inputs: StepInputs) -> None:
        """Per step: working-precision data, the box, and the planned factorisations."""
        lcs = self.lcs
        self.info = {}
        self._hits0, self._misses0 = self.cache.hits, self.cache.misses
        self._prepared_step = self.prepare(lcs)
        x0 = np.asarray(inputs.x0, dtype=np.float64)
        if not np.all(np.isfinite(x0)):
            raise KernelFailure("invalid input", "x0 has non-finite entries", True)
        self._x0 = x0.astype(self.dtype)
        self._p = np.asarray(inputs.weights).astype(self.dtype)
        self._shared = bool(inputs.shared_inputs and lcs.n_samples > 1)
        lower, upper = box_of_step(self.mpc, self.layout, self.options.use_limits)
        self._lower, self._upper = lower.astype(self.dtype), upper.astype(self.dtype)
        self._planned: dict[tuple[float, ...], RiccatiFactor] = {}
        plan = inputs.plan if self.prefactorize else None
        if plan:
            t0 = time.perf_counter()
            try:
                factors = self.factors(lcs, plan)
            except np.linalg.LinAlgError:
                factors = []  # factorise one by one to find the failing iteration
            for rho, (factor, _) in zip(plan, factors, strict=False):
                self._planned[tuple(float(rho[k]) for k in BLOCKS)] = factor
            self.timings.factor += time.perf_counter() - t0

    @property
    def step_cache_hits(self) -> int:
        return self.cache.hits - self._hits0

    @property
    def step_cache_misses(self) -> int:
        return self.cache.misses - self._misses0

    def iterate(self, rho: Mapping[str, float], delta: np.ndarray, w: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """QP step by the Riccati recursion, then the projection (box, pairs, shared mean)."""
        t0 = time.perf_counter()
        key = tuple(float(rho[k]) for k in BLOCKS)
        factor = self._planned.get(key)
        if factor is None:
            try:
                factor, _ = self.factor(self.lcs, rho)
            except np.linalg.LinAlgError as error:
                raise KernelFailure("QP factorisation failed", str(error)) from None
        t1 = time.perf_counter()
        steps, terminal = self._qp_solve(self._prepared_step, factor, rho, self._x0, delta, w)
        t2 = time.perf_counter()
        self.timings.factor += t1 - t0
        self.timings.qp_solve += t2 - t1
        if not (math.isfinite(float(steps.sum())) and math.isfinite(float(terminal.sum()))):
            raise KernelFailure("non-finite QP solution", "", True)
        U = projection_weight_vector(self.options, self.layout, rho).astype(self.dtype)
        lam_s, eta_s = self.layout.index(0, Block.LAM), self.layout.index(0, Block.ETA)
        new_delta = self._project(steps + w, np.sqrt(U[lam_s]), np.sqrt(U[eta_s]), self._lower,
                                  self._upper, self._p, self._shared)
        self.timings.projection += time.perf_counter() - t2
        return steps, terminal, new_delta

    def solve(self, lcs: LCSBatch, x0: np.ndarray, weights: Sequence[float] | None = None,
              delta: np.ndarray | None = None, w: np.ndarray | None = None,
              fallback_input: np.ndarray | None = None) -> FastSolution:
        """One control step of the one ADMM (:func:`c3bench.solvers.admm.solve_batched`).

        Parameters
        ----------
        lcs
            The samples' LCS, linearised at ``x0``.
        x0
            Measured state (nx,).
        weights
            Sample weights (normalised and floored); uniform when ``None``.
        delta, w
            Initial iterates (n, T, ns) or (T, ns); cold start when ``None``.
        fallback_input
            Returned with ``ok=False`` when the step fails (zero when ``None``).
        """
        return solve_batched(self, lcs, self.mpc, x0, self.options, weights, delta, w,
                             fallback_input, self.shared_inputs, self.record_residuals)


def fast_options(**changes: Any) -> C3Options:
    """The reference study's C3+ options for :class:`FastC3Plus` (no iterate keeping)."""
    return replace(C3Options(keep_iterates=False), **changes)
