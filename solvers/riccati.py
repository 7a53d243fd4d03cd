"""A Riccati solver of the C3+ QP step, batched over LCS samples.

The QP-step kernel of :mod:`solvers.fast`; :mod:`solvers.riccati_qp` applies it to a stored
``c3plus_qp`` instance.

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

       Q_yy = H_y + AB^T S_{k+1} AB,   K_k = -Q_vv^-1 Q_vx  (refined once, below),
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
inverse, and ``2 nv^2 nx`` to refine ``K``). :func:`solve_lq` does the linear passes for any
``(x0, g_y, q_T)`` in two batched products per time step and direction. :class:`FactorCache`
keeps recent factorisations keyed by the ``rho`` values, the LCS batch identity
(``LCSBatch.uid``) and the options, so a repeated ``rho`` on an unchanged LCS costs no
factorisation. With the geometric schedule the
rho of all iterations is known before the first one, so the controller
(:meth:`c3bench.solvers.fast.FastC3Plus.factors`, with ``prefactorize`` on; not this module)
factorises the whole schedule in one :func:`factorize` call over (iterations x samples): the
same arithmetic with a tenth of the numpy calls.

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

**Accuracy of the gain.** ``K = -Q_vv^-1 Q_vx`` is refined once, ``K <- K + G_v (Q_vv K +
Q_vx)`` (two ``nv x nv`` by ``nv x nx`` products). A product with an explicit inverse is
not backward stable: its residual ``Q_vv K + Q_vx`` is about ``eps cond(Q_vv) |Q_vv| |K|``
instead of ``eps |Q_vv| |K|``, and ``S_k = Q_xx + Q_xv K`` inherits exactly ``K^T`` times
that residual. Late in a geometric schedule that update cancels: on a random LCS (nx 4,
nlam 1, nu 3, T 4, rho_lam 25 600) the scaled ``|Q_xx| ~ 1`` against ``|S_k| ~ 4e-4`` with
``cond(Q_vv) ~ 3e4``, the unrefined residual was ``4e-13`` relative (``2e-16`` refined),
``S_k`` was off by ``1e-9`` relative, that QP step by ``2e-9`` (the compiled kernel's
``2e-12``: its and the JAX kernel's Cholesky form ``S_k = Q_xx - Y^T Y`` avoids it) and the
control step by ``2e-9`` against the compiled kernel's ``2e-11`` (against a dense C3+).
One refinement step brings the residual, ``S_k`` and the control step to theirs (the
refined ``K`` also enters ``A_cl`` and the passes; the control step within 7e-12 of the
compiled kernel's on 40 random LCSs, ``tests/test_numpy_kernel_accuracy.py``). Measured on the
cube (10 rho values x 16 samples, T 7, one thread, loaded machine): ``factorize`` 6-7 %
slower, ``FastC3Plus.solve`` 3-5 %; the Cholesky form was as accurate but ``factorize`` 15-25 %
slower in numpy (``cholesky`` plus a triangular ``inv``), ``numpy.linalg.solve`` for ``[K | G_e
| G_v]`` 50 % slower.

**Batching.** Every array has a leading sample axis; all products are numpy ``matmul``
broadcasts, with no Python loop over samples (the only loops run over the ``T`` time steps).
"""

from __future__ import annotations

import math
from collections import OrderedDict
from collections.abc import Hashable
from dataclasses import dataclass
from typing import Any

import numpy as np

from c3bench.problems.names import Precision

__all__ = [
    "FactorCache",
    "RiccatiFactor",
    "RiccatiOptions",
    "factorize",
    "solve_lq",
    "swap_last",
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
def swap_last(array: np.ndarray) -> np.ndarray:
    """The batched transpose: ``array`` with its last two axes swapped (a view)."""
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
    AT = np.ascontiguousarray(swap_last(A))
    BvT = np.ascontiguousarray(swap_last(Bv))
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
        residual = Qv[..., nx:] @ K  # one refinement step of K (module docstring,
        residual += Qvx  # "accuracy of the gain"): K <- K - Q_vv^-1 (Q_vv K + Q_vx)
        K += Gv @ residual  # (in place: K is a view of Z)
        Acl = Bv @ K
        Acl += A
        KA[k] = np.concatenate([K, Acl], axis=-2)
        We[k] = np.concatenate([Z[..., nx:], swap_last(Acl)], axis=-2)
        Wg[k] = np.concatenate([Gv, swap_last(K)], axis=-2)
        Sd[k] = SABd[..., ny]
        S = AT @ SABd[..., :nx]  # Q_xx = H_xx + A^T S A + Q_xv K
        S += Hxx[..., k, :, :] if per_step else Hxx
        S += swap_last(Qvx) @ K
        if options.symmetrize:
            S = 0.5 * (S + swap_last(S))
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
