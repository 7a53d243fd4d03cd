"""The projection step of the consensus ADMM, defined once for every kernel.

**C3+ closed form** (Bui et al. 2025, C3+; the pair problem of Aydinoglu and Posa 2022, C3): for
one complementarity pair with weights ``w_lam, w_eta >= 0`` and a point ``(a, b)``,

    min  w_lam (lam - a)^2 + w_eta (eta - b)^2   s.t.  lam, eta >= 0,  lam eta = 0,

the feasible set is the union of the half-axes ``{eta = 0, lam >= 0}`` (cost
``w_eta b^2 + w_lam [a]_-^2``) and ``{lam = 0, eta >= 0}`` (cost ``w_lam a^2 + w_eta [b]_-^2``);
the first is no worse exactly when ``w_lam [a]_+^2 >= w_eta [b]_+^2``, i.e. the member with
the larger ``sqrt(w) [v]_+`` is kept (clipped at 0) and the other set to 0; ties keep ``lam``.
``x`` and ``u`` are copied (C3+'s projection has no other constraint on them).

**Box limits** (:class:`c3bench.problems.limits.Limits`): with a diagonal weight the projection
onto ``lower <= y <= upper`` is the clip, whatever the weights; the fast kernels put the
controller's input and state limits here (a splitting: the QP step keeps the dynamics, the
projection the limits and the complementarity, which act on disjoint coordinates).

**Shared inputs** (the robust controller's fast splitting): ``delta_{j,u} = u_bar`` for every
sample ``j`` gives ``u_bar = sum_j p_j v_{j,u}`` (a weighted mean; the weight cancels).

:func:`make_c3plus_pairs` and :func:`make_step_projection` take the array namespace (numpy,
``jax.numpy``) so numpy, JAX and numba (which compiles the numpy closure) share the maths.
"""

from __future__ import annotations

from collections.abc import Callable
from types import ModuleType
from typing import Any

import numpy as np

PairProjection = Callable[[Any, Any, Any, Any], tuple[Any, Any]]


def make_c3plus_pairs(xp: ModuleType) -> PairProjection:
    """The pair projection ``(a, b, sqrt_w_lam, sqrt_w_eta) -> (lam, eta)`` in namespace ``xp``.

    ``sqrt_w_*`` are the square roots of the weights (scalars or broadcastable arrays).
    """

    def pairs(a: Any, b: Any, sqrt_w_lam: Any, sqrt_w_eta: Any) -> tuple[Any, Any]:
        a_plus = xp.maximum(a, 0.0)
        b_plus = xp.maximum(b, 0.0)
        keep_lam = sqrt_w_lam * a_plus >= sqrt_w_eta * b_plus
        return xp.where(keep_lam, a_plus, 0.0), xp.where(keep_lam, 0.0, b_plus)

    return pairs


c3plus_pairs_numpy = make_c3plus_pairs(np)


def c3plus_projection(v_lam: np.ndarray, v_eta: np.ndarray, w_lam: np.ndarray | float,
                      w_eta: np.ndarray | float) -> tuple[np.ndarray, np.ndarray]:
    """Project every pair ``(v_lam_i, v_eta_i)`` onto ``{lam, eta >= 0, lam eta = 0}`` (checked).

    The norm is ``w_lam (lam - v_lam)^2 + w_eta (eta - v_eta)^2`` per pair (module docstring).

    Parameters
    ----------
    v_lam, v_eta
        Points to project (same shape, any number of dimensions).
    w_lam, w_eta
        Non-negative weights, broadcastable to ``v_lam``.

    Returns
    -------
    lam, eta
        The projection in the inputs' floating type (``float32`` stays ``float32``).
    """
    dtype = np.result_type(np.asarray(v_lam), np.asarray(v_eta), np.float32)
    a = np.asarray(v_lam, dtype=dtype)
    b = np.asarray(v_eta, dtype=dtype)
    if a.shape != b.shape:
        raise ValueError(f"v_lam and v_eta must have the same shape, got {a.shape} and "
                         f"{b.shape}")
    wl = np.broadcast_to(np.asarray(w_lam, dtype=dtype), a.shape)
    we = np.broadcast_to(np.asarray(w_eta, dtype=dtype), a.shape)
    if np.any(wl < 0) or np.any(we < 0):
        raise ValueError("weights must be >= 0")
    if not (np.all(np.isfinite(a)) and np.all(np.isfinite(b))
            and np.all(np.isfinite(wl)) and np.all(np.isfinite(we))):
        raise ValueError("points and weights must be finite")
    lam, eta = c3plus_pairs_numpy(a, b, np.sqrt(wl), np.sqrt(we))
    return np.asarray(lam, dtype=dtype), np.asarray(eta, dtype=dtype)


StepProjection = Callable[..., Any]


def make_step_projection(xp: ModuleType, nx: int, nlam: int, nu: int) -> StepProjection:
    """C3+'s projection of steps ``v`` (..., S, T, ns) with ``ns = nx + 2 nlam + nu``.

    Returns ``project(v, sqrt_w_lam, sqrt_w_eta, lower, upper, p, shared)``: pairs in closed
    form (weights per entry or scalars), ``x`` and ``u`` clipped to ``[lower, upper]`` (the
    box limits of one step's ``(x, u)``, length ``nx + nu``; ``+-inf`` where unbounded) and,
    when ``shared``, ``u`` replaced by the weighted mean over the sample axis (``p`` the sample
    weights). The box and the mean commute: the mean of points in a box lies in the box.
    """
    pairs = make_c3plus_pairs(xp)
    lam_s = slice(nx, nx + nlam)
    u_s = slice(nx + nlam, nx + nlam + nu)
    eta_s = slice(nx + nlam + nu, nx + 2 * nlam + nu)

    def project(v: Any, sqrt_w_lam: Any, sqrt_w_eta: Any, lower: Any, upper: Any, p: Any,
                shared: bool) -> Any:
        lam, eta = pairs(v[..., lam_s], v[..., eta_s], sqrt_w_lam, sqrt_w_eta)
        x = xp.clip(v[..., :nx], lower[:nx], upper[:nx])
        u = v[..., u_s]
        if shared:
            u = xp.broadcast_to(xp.einsum("j,jtu->tu", p, u), u.shape)
        u = xp.clip(u, lower[nx:], upper[nx:])
        return xp.concatenate([x, lam, u, eta], axis=-1)

    return project
