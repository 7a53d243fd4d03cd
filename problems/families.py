"""Builders of the subproblem families (docs/families.md).

All return a :class:`problems.instance.Problem` in the form
``min 1/2 z^T P z + q^T z + offset s.t. A z = b, G z <= h, lb <= z <= ub``, complementarity
pairs ``0 <= z_i perp z_j >= 0``.

* ``c3plus_qp``: C3+'s QP step over ``z_k = (x_k, lam_k, u_k, eta_k)``:
  ``min J(x, u) + sum_k ||z_k - (delta_k - w_k)||^2_{G_k}`` s.t. ``x_0 = x0``, dynamics,
  ``eta_k = E x_k + F lam_k + H u_k + c``.
* ``c3_qp``: C3's QP step over ``z_k = (x_k, lam_k, u_k)``, dynamics only.
* Both QP steps come in two variants (:class:`c3bench.problems.names.QPVariant`, in
  ``meta["variant"]``): ``bounded`` adds the MPC's limits
  (:class:`c3bench.problems.limits.Limits`) as bounds ``u_lower <= u_k <= u_upper`` (``k < T``)
  and ``x_lower <= x_k <= x_upper`` (``k >= 1``; ``x_0`` is fixed by the dynamics rows), as the
  reference C3 implementation keeps them in its QP step; ``equality`` has no bounds.
* ``projection``: one step's projection ``min ||delta - v||^2_U`` onto the complementarity set;
  variant ``c3`` couples ``eta = E x + F lam + H u + c`` (``U`` is zero on ``eta``), variant
  ``c3plus`` projects each pair ``(lam_i, eta_i)`` on its own.
* ``mpcc``: ``min J(x, u)`` s.t. dynamics, ``eta_k = E x_k + F lam_k + H u_k + c``,
  ``0 <= lam_k perp eta_k >= 0`` and ``|u| <= force_limit``, or, given limits, the same
  bounds as the bounded QP step.
* ``lcp``: ``min 1/2 lam^T F lam + q^T lam`` s.t. ``lam >= 0`` with ``q = E x + H u + c``
  (its KKT conditions are the LCP because ``F`` is symmetric PSD for Anitescu).
* ``lcp_general``: ``0 <= lam perp w = F lam + q >= 0`` for any square ``F`` (not symmetric
  for Stewart-Trinkle), ``F`` stored as is in ``data["F"]`` and ``q`` in ``h``; the QP
  fields state the LCP's feasible set ``-F lam <= q``, ``lam >= 0`` with a zero objective
  (:func:`lcp_general`): an LCP has no objective, and no QP backend takes the family.

Weights: ``G_k = diag(rho_x I, rho_lam I, rho_u I, rho_eta I)``, keyed by
:class:`c3bench.problems.names.Block` (the blocks of :data:`c3bench.problems.names.BLOCKS`).

Part of the plant-free core: pure numpy, imports neither MuJoCo nor CasADi.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import numpy as np

from c3bench.problems.errors import InputError
from c3bench.problems.instance import Problem
from c3bench.problems.lcs import LCS
from c3bench.problems.limits import Limits
from c3bench.problems.mpc import MPC, HorizonLayout
from c3bench.problems.names import Block, Family, QPVariant, Variant

ZERO_WEIGHT_BLOCKS = (Block.X, Block.U)
"""Blocks whose consensus weight may be 0: the QP step stays strictly convex through the
cost's ``Q`` and ``R`` and the dynamics (the C3 paper's zero ``G`` block on ``u``); ``lam``
and ``eta`` carry no cost of their own, so their weights must be positive."""


def check_rho(rho: Mapping[str, float], blocks: tuple[str, ...], name: str = "rho",
              positive: tuple[str, ...] | None = None) -> dict[str, float]:
    """Validate weights by block (the consensus weights ``rho``, a controller's ``rho0`` or
    projection weights): finite, ``> 0`` for the blocks in ``positive`` (default: those not
    in :data:`ZERO_WEIGHT_BLOCKS`) and ``>= 0`` for the others; ``ValueError`` names ``name``
    and the block."""
    if positive is None:
        positive = tuple(block for block in blocks if block not in ZERO_WEIGHT_BLOCKS)
    out: dict[str, float] = {}
    for block in blocks:
        label = str(block)
        if block not in rho:
            raise ValueError(f"{name} is missing the weight for block {label!r}")
        value = float(rho[block])
        strict = block in positive
        if not (math.isfinite(value) and (value > 0 if strict else value >= 0)):
            raise ValueError(f"{name}[{label!r}] must be finite and {'> 0' if strict else '>= 0'}"
                             f", got {rho[block]!r}")
        out[label] = value
    return out


def weight_vector(layout: HorizonLayout, rho: Mapping[str, float]) -> np.ndarray:
    """Diagonal of ``G_k`` for one step of the layout."""
    return np.concatenate([np.full(size, rho[name])
                           for name, size in layout.block_sizes().items()])


def _cost_terms(layout: HorizonLayout, mpc: MPC) -> tuple[np.ndarray, np.ndarray, float]:
    """Hessian, gradient and constant of ``J`` in ``z`` (``J = 1/2 z P z + q z + r``)."""
    n = layout.size
    P = np.zeros((n, n))
    q = np.zeros(n)
    offset = 0.0
    for k in range(layout.horizon + 1):
        weight = mpc.Q if k < layout.horizon else mpc.Q_f
        sx = layout.index(k, Block.X)
        P[sx, sx] += 2 * weight
        q[sx] += -2 * weight @ mpc.x_target
        offset += float(mpc.x_target @ weight @ mpc.x_target)
        if k < layout.horizon:
            su = layout.index(k, Block.U)
            P[su, su] += 2 * mpc.R
    return P, q, offset


def dynamics_rows(layout: HorizonLayout, lcs: LCS, x0: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray]:
    """``x_0 = x0``, ``x_{k+1} - A x_k - B u_k - D lam_k = d`` and, with eta,
    ``eta_k - E x_k - F lam_k - H u_k = c``."""
    T, nx, nlam = layout.horizon, layout.nx, layout.nlam
    rows = nx + T * nx + (T * nlam if layout.n_eta else 0)
    A = np.zeros((rows, layout.size))
    b = np.zeros(rows)
    sx0 = layout.index(0, Block.X)
    A[:nx, sx0] = np.eye(nx)
    b[:nx] = x0
    row = nx
    for k in range(T):
        block = slice(row, row + nx)
        A[block, layout.index(k + 1, Block.X)] = np.eye(nx)
        A[block, layout.index(k, Block.X)] = -lcs.A
        A[block, layout.index(k, Block.U)] = -lcs.B
        A[block, layout.index(k, Block.LAM)] = -lcs.D
        b[block] = lcs.d
        row += nx
    if layout.n_eta:
        for k in range(T):
            block = slice(row, row + nlam)
            A[block, layout.index(k, Block.ETA)] = np.eye(nlam)
            A[block, layout.index(k, Block.X)] = -lcs.E
            A[block, layout.index(k, Block.LAM)] = -lcs.F
            A[block, layout.index(k, Block.U)] = -lcs.H
            b[block] = lcs.c
            row += nlam
    return A, b


def limit_bounds(layout: HorizonLayout, limits: Limits) -> tuple[np.ndarray, np.ndarray]:
    """``lb``, ``ub`` over ``z``: ``limits``' input box on ``u_k`` (``k < T``), its state box
    on ``x_k`` (``1 <= k <= T``); ``x_0``, ``lam`` and ``eta`` free."""
    if (limits.nx, limits.nu) != (layout.nx, layout.nu):
        raise ValueError(f"limits are for (nx, nu) = {(limits.nx, limits.nu)}, the layout has "
                         f"{(layout.nx, layout.nu)}")
    lb = np.full(layout.size, -np.inf)
    ub = np.full(layout.size, np.inf)
    for k in range(layout.horizon):
        su = layout.index(k, Block.U)
        lb[su], ub[su] = limits.u_lower, limits.u_upper
    for k in range(1, layout.horizon + 1):
        sx = layout.index(k, Block.X)
        lb[sx], ub[sx] = limits.x_lower, limits.x_upper
    return lb, ub


def _input_bounds(layout: HorizonLayout, limit: float) -> tuple[np.ndarray, np.ndarray]:
    return limit_bounds(layout, Limits.force_only(layout.nx, layout.nu, limit))


def _qp_limits(layout: HorizonLayout, mpc: MPC, limits: Limits | None,
               input_bounds: bool) -> Limits | None:
    """The limits of a QP step: ``limits``, tightened by ``|u| <= force_limit`` when
    ``input_bounds``; ``None`` for the equality variant."""
    if not input_bounds:
        return limits
    forces = Limits.force_only(layout.nx, layout.nu, mpc.force_limit)
    return forces if limits is None else limits.intersect(forces)


def _check_horizon_arrays(name: str, value: np.ndarray | None, layout: HorizonLayout
                          ) -> np.ndarray:
    shape = (layout.horizon, layout.step_size)
    if value is None:
        return np.zeros(shape)
    array = np.asarray(value, dtype=float)
    if array.shape != shape:
        raise ValueError(f"{name} must have shape {shape} (T x step size), got {array.shape}")
    if not np.all(np.isfinite(array)):
        raise ValueError(f"{name} has non-finite entries")
    return array


def _check_x0(x0: np.ndarray, lcs: LCS) -> np.ndarray:
    x0 = np.asarray(x0, dtype=float)
    if x0.shape != (lcs.nx,):
        raise ValueError(f"x0 must have shape ({lcs.nx},), got {x0.shape}")
    if not np.all(np.isfinite(x0)):
        raise ValueError("x0 has non-finite entries")
    return x0


def _check_models(lcs: LCS, mpc: MPC) -> None:
    if not isinstance(mpc.horizon, int) or mpc.horizon < 1:
        raise ValueError(f"T (horizon) must be an integer >= 1, got {mpc.horizon!r}")
    if lcs.nx != mpc.nx or lcs.nu != mpc.nu:
        raise ValueError(f"LCS (nx={lcs.nx}, nu={lcs.nu}) and MPC (nx={mpc.nx}, nu={mpc.nu}) "
                         "disagree")


def consensus_qp(
    family: str,
    name: str,
    lcs: LCS,
    mpc: MPC,
    x0: np.ndarray,
    rho: Mapping[str, float],
    delta: np.ndarray | None = None,
    w: np.ndarray | None = None,
    input_bounds: bool = False,
    meta: dict[str, Any] | None = None,
    limits: Limits | None = None,
) -> Problem:
    """The ADMM QP step of C3+ (``family="c3plus_qp"``) or C3 (``"c3_qp"``).

    ``min J(x, u) + sum_k (z_k - (delta_k - w_k))^T G_k (z_k - (delta_k - w_k))``.

    Parameters
    ----------
    lcs, mpc
        Model and cost.
    x0
        Measured state.
    rho
        Weights by block (``x``, ``lam``, ``u`` and, for C3+, ``eta``).
    delta, w
        Projection iterate and scaled dual (T x step size); zero when ``None``.
    input_bounds
        Add ``|u_k| <= force_limit`` (on top of ``limits`` when both are given).
    limits
        The ``bounded`` variant's limits (``lb <= z <= ub`` on ``u_k``, ``k < T``, and on
        ``x_k``, ``k >= 1``; :func:`limit_bounds`); ``None`` (and no ``input_bounds``): the
        ``equality`` variant, whose arrays do not depend on this option. ``mpc.limits`` is
        not read: the caller chooses the variant.

    ``meta`` gains ``layout``, ``rho``, ``input_bounds``, ``variant`` and, when bounded,
    ``limits`` (:meth:`Limits.to_json`).
    """
    if family not in (Family.C3PLUS_QP, Family.C3_QP):
        raise ValueError(f"family must be 'c3plus_qp' or 'c3_qp', got {family!r}")
    _check_models(lcs, mpc)
    x0 = _check_x0(x0, lcs)
    n_eta = lcs.nlam if family == Family.C3PLUS_QP else 0
    layout = HorizonLayout(lcs.nx, lcs.nlam, lcs.nu, n_eta, mpc.horizon)
    weights = check_rho(rho, tuple(layout.block_sizes()))
    delta = _check_horizon_arrays("delta", delta, layout)
    w = _check_horizon_arrays("w", w, layout)
    P, q, offset = _cost_terms(layout, mpc)
    g = weight_vector(layout, weights)
    anchor = delta - w
    steps = layout.horizon * layout.step_size
    P[np.arange(steps), np.arange(steps)] += 2 * np.tile(g, layout.horizon)
    q[:steps] += -2 * (g * anchor).ravel()
    offset += float(np.sum(g * anchor * anchor))
    A, b = dynamics_rows(layout, lcs, x0)
    lb = ub = None
    bounds = _qp_limits(layout, mpc, limits, input_bounds)
    info = dict(meta or {})
    info.update({"layout": layout.to_json(), "rho": weights, "input_bounds": input_bounds,
                 "variant": QPVariant.EQUALITY if bounds is None else QPVariant.BOUNDED})
    if bounds is not None:
        lb, ub = limit_bounds(layout, bounds)
        info["limits"] = bounds.to_json()
    return Problem(
        name=name, family=family, P=P, q=q, A=A, b=b, lb=lb, ub=ub,
        objective_offset=offset, lcs=lcs,
        data={"x0": x0, "delta": delta, "w": w, "G_diag": g},
        meta=info,
    )


def mpcc(name: str, lcs: LCS, mpc: MPC, x0: np.ndarray,
         meta: dict[str, Any] | None = None, limits: Limits | None = None) -> Problem:
    """The whole-horizon MPC with complementarity (the problem C3 approximates).

    Bounds: ``|u_k| <= force_limit`` or, given ``limits``, the bounded QP step's bounds
    (:func:`limit_bounds`; ``meta`` then gains ``variant = "bounded"`` and ``limits``), plus
    ``lam_k, eta_k >= 0``.
    """
    _check_models(lcs, mpc)
    x0 = _check_x0(x0, lcs)
    layout = HorizonLayout(lcs.nx, lcs.nlam, lcs.nu, lcs.nlam, mpc.horizon)
    P, q, offset = _cost_terms(layout, mpc)
    A, b = dynamics_rows(layout, lcs, x0)
    if limits is None:
        lb, ub = _input_bounds(layout, mpc.force_limit)
    else:
        lb, ub = limit_bounds(layout, limits)
    pairs: list[tuple[int, int]] = []
    for k in range(layout.horizon):
        lam, eta = layout.index(k, Block.LAM), layout.index(k, Block.ETA)
        lb[lam] = 0.0
        lb[eta] = 0.0
        pairs.extend(zip(range(lam.start, lam.stop), range(eta.start, eta.stop), strict=True))
    info = dict(meta or {})
    info["layout"] = layout.to_json()
    if limits is not None:
        info.update({"variant": QPVariant.BOUNDED, "limits": limits.to_json()})
    return Problem(
        name=name, family=Family.MPCC, P=P, q=q, A=A, b=b, lb=lb, ub=ub,
        complementarity=np.array(pairs, dtype=np.int64), objective_offset=offset, lcs=lcs,
        data={"x0": x0}, meta=info,
    )


def projection(name: str, lcs: LCS, v: np.ndarray, U_diag: np.ndarray,
               variant: str = Variant.C3, meta: dict[str, Any] | None = None) -> Problem:
    """One step's projection ``min (delta - v)^T U (delta - v)`` onto complementarity.

    ``delta = (x, lam, u, eta)``. Variant ``c3``: ``eta = E x + F lam + H u + c`` is an
    equality and ``U`` must be zero on ``eta`` (C3's projection on ``(x, lam, u)``); variant
    ``c3plus``: no equality, so each pair ``(lam_i, eta_i)`` is projected on its own.
    """
    if variant not in (Variant.C3, Variant.C3PLUS):
        raise ValueError(f"variant must be 'c3' or 'c3plus', got {variant!r}")
    nx, nlam, nu = lcs.nx, lcs.nlam, lcs.nu
    size = nx + 2 * nlam + nu
    v = np.asarray(v, dtype=float)
    U = np.asarray(U_diag, dtype=float)
    for label, value in (("v", v), ("U_diag", U)):
        if value.shape != (size,):
            raise ValueError(f"{label} must have shape ({size},), got {value.shape}")
        if not np.all(np.isfinite(value)):
            raise ValueError(f"{label} has non-finite entries")
    if np.any(U < 0):
        raise ValueError("U_diag must be >= 0")
    x_s, lam_s = slice(0, nx), slice(nx, nx + nlam)
    u_s, eta_s = slice(nx + nlam, nx + nlam + nu), slice(nx + nlam + nu, size)
    A = b = None
    if variant == Variant.C3:
        if np.any(U[eta_s] != 0):
            raise ValueError("U_diag must be zero on eta for the c3 variant")
        A = np.zeros((nlam, size))
        A[:, eta_s] = np.eye(nlam)
        A[:, x_s] = -lcs.E
        A[:, lam_s] = -lcs.F
        A[:, u_s] = -lcs.H
        b = lcs.c.copy()
    P = 2 * np.diag(U)
    q = -2 * U * v
    offset = float(np.sum(U * v * v))
    lb = np.full(size, -np.inf)
    lb[lam_s] = 0.0
    lb[eta_s] = 0.0
    pairs = np.column_stack([np.arange(lam_s.start, lam_s.stop),
                             np.arange(eta_s.start, eta_s.stop)]).astype(np.int64)
    info = dict(meta or {})
    info.update({"variant": variant,
                 "layout": HorizonLayout(nx, nlam, nu, nlam, 1).to_json()})
    return Problem(name=name, family=Family.PROJECTION, P=P, q=q, A=A, b=b, lb=lb,
                   complementarity=pairs, objective_offset=offset, lcs=lcs,
                   data={"v": v, "U_diag": U}, meta=info)


def lcp(name: str, lcs: LCS, x: np.ndarray, u: np.ndarray,
        meta: dict[str, Any] | None = None) -> Problem:
    """The forward-simulation LCP of one step as ``min 1/2 lam^T F lam + q^T lam, lam >= 0``."""
    if lcs.contact_model != "anitescu":
        raise ValueError("the lcp family needs a symmetric F (contact_model 'anitescu')")
    x = _check_x0(x, lcs)
    u = np.asarray(u, dtype=float)
    if u.shape != (lcs.nu,) or not np.all(np.isfinite(u)):
        raise ValueError(f"u must be a finite vector of shape ({lcs.nu},)")
    offset_q = lcs.lcp_offset(x, u)
    return Problem(name=name, family=Family.LCP, P=lcs.F.copy(), q=offset_q,
                   lb=np.zeros(lcs.nlam), lcs=lcs, data={"x": x, "u": u},
                   meta=dict(meta or {}))


def _check_lcp_data(F: np.ndarray, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``F`` (n x n) and ``q`` (n) as finite float arrays; :class:`InputError` naming the fault."""
    try:
        F = np.array(F, dtype=np.float64)
        q = np.array(q, dtype=np.float64)
    except (TypeError, ValueError) as error:
        raise InputError(f"F and q must be numeric: {error}") from error
    if q.ndim != 1 or q.size == 0:
        raise InputError(f"q must be a non-empty vector, got shape {q.shape}")
    if F.shape != (q.size, q.size):
        raise InputError(f"F must be square with the size of q, ({q.size}, {q.size}); got "
                         f"{F.shape}")
    for label, value in (("F", F), ("q", q)):
        if not np.all(np.isfinite(value)):
            raise InputError(f"{label} has non-finite entries")
    return F, q


def lcp_general(name: str, F: np.ndarray, q: np.ndarray, *, lcs: LCS | None = None,
                data: Mapping[str, np.ndarray] | None = None,
                meta: dict[str, Any] | None = None) -> Problem:
    """An LCP ``0 <= lam perp w = F lam + q >= 0`` with any square ``F``, stored as is.

    Storage (:func:`c3bench.problems.instance.lcp_data` reads ``F`` and ``q`` back):
    ``data["F"] = F`` unchanged, and the QP fields state the LCP's feasible set with a zero
    objective::

        min  0   s.t.   -F lam <= q   (w >= 0),   lam >= 0,

    i.e. ``P = 0``, ``q = 0`` (the instance's ``q`` field; the LCP's ``q`` is ``h``),
    ``G = -F``, ``h = q``, ``lb = 0``. An LCP has no objective: any solution is as good as
    another (the solution need not be unique), so the family's objective is 0 and its
    certificate is the natural residual ``||min(lam, F lam + q)||`` (Cottle, Pang and Stone
    1992); the primal residual of the QP fields measures ``[-lam]_+`` and ``[-w]_+``. ``P = 0``
    keeps the instance contract (``P`` symmetric positive semi-definite); the family is still
    no convex QP (complementarity is not in the QP fields) and no QP backend takes it.

    Parameters
    ----------
    name
        Instance name.
    F, q
        The LCP's matrix (n x n) and vector (n); finite.
    lcs
        The LCS the LCP comes from (``None`` for an LCP brought on its own).
    data
        Further arrays to store (``"F"`` is reserved).
    meta
        Metadata (none is required without an LCS: ``lcp_general`` is a generic family).

    Raises
    ------
    InputError
        ``F`` not square of ``q``'s size, non-finite entries, or ``data`` holding ``"F"``.

    References
    ----------
    R. W. Cottle, J.-S. Pang and R. E. Stone, *The Linear Complementarity Problem*, Academic
    Press, 1992.
    """
    F, q = _check_lcp_data(F, q)
    extra = {key: np.asarray(value) for key, value in (data or {}).items()}
    if "F" in extra:
        raise InputError("data['F'] is reserved for the LCP matrix (pass it as F)")
    n = q.size
    return Problem(name=name, family=Family.LCP_GENERAL, P=np.zeros((n, n)), q=np.zeros(n),
                   G=-F, h=q.copy(), lb=np.zeros(n), lcs=lcs, data={"F": F, **extra},
                   meta=dict(meta or {}))


def lcp_general_from_lcs(name: str, lcs: LCS, x: np.ndarray, u: np.ndarray,
                         meta: dict[str, Any] | None = None) -> Problem:
    """The forward-simulation LCP of one LCS step, ``F = lcs.F``, ``q = E x + H u + c``
    (:meth:`LCS.lcp_offset`), for any contact model (Stewart-Trinkle's ``F`` is not
    symmetric: Stewart and Trinkle 1996). ``data`` gains ``x`` and ``u``; ``meta`` the
    ``contact_model``.

    References
    ----------
    D. E. Stewart and J. C. Trinkle, "An implicit time-stepping scheme for rigid body dynamics
    with inelastic collisions and Coulomb friction", International Journal for Numerical
    Methods in Engineering 39(15), 2673-2691, 1996.
    """
    try:
        x = _check_x0(x, lcs)
    except ValueError as error:
        raise InputError(str(error)) from error
    u = np.asarray(u, dtype=float)
    if u.shape != (lcs.nu,) or not np.all(np.isfinite(u)):
        raise InputError(f"u must be a finite vector of shape ({lcs.nu},)")
    info = dict(meta or {})
    info.setdefault("contact_model", lcs.contact_model)
    return lcp_general(name, lcs.F, lcs.lcp_offset(x, u), lcs=lcs, data={"x": x, "u": u},
                       meta=info)

