"""The one residual module: every accuracy figure in c3bench is computed here.

Definitions follow qpsolvers' ``Solution`` (infinity norms), for
``min 1/2 x^T P x + q^T x`` s.t. ``A x = b``, ``G x <= h``, ``lb <= x <= ub``:

* primal residual ``max(||A x - b||, ||[G x - h]_+||, ||[lb - x]_+||, ||[x - ub]_+||)``;
* dual residual ``max(||P x + q + A^T y + G^T z + z_box||, ||[-z]_+||, ||sign violation of
  z_box||)``: stationarity and dual feasibility together. ``z`` (of ``G x <= h``) must be
  ``>= 0``; ``z_box_i < 0`` is allowed only where ``lb_i`` is finite and ``z_box_i > 0`` only
  where ``ub_i`` is finite, so the box part is ``[-z_box_i]_+`` where ``lb_i`` is missing or
  infinite and ``[z_box_i]_+`` where ``ub_i`` is (a wrong-signed dual never passes on
  stationarity alone);
* duality gap ``|x^T P x + q^T x + b^T y + h^T z + lb^T [z_box]_- + ub^T [z_box]_+|``
  (infinite bounds skipped);
* complementarity violation ``max_pairs |min(x_i, x_j)|`` (the natural-map residual of
  ``0 <= x_i perp x_j >= 0``); for the LCP families (:data:`LCP_FAMILIES`), whose
  complementarity is ``0 <= lam perp w = F lam + q >= 0`` (no pairs; ``(F, q) = (P, q)`` for
  ``lcp``, ``(data["F"], h)`` for ``lcp_general``), it is the natural residual relative to the
  data, ``||min(lam, w)||_inf / max(1, ||q||_inf)`` (:func:`lcp_residual`; Siconos' LCP
  error is normalised by ``1 + ||q||`` the same way), which also bounds ``[-lam]_+`` and
  ``[-w]_+`` (``|min(a, b)| >= max(-a, -b)``);
* cost error ``|f(x) - f*| / max(1, |f*|)`` against a reference optimum ``f*``.

Our instances are badly scaled (gradients up to 4e5, objectives up to 3e6), so an absolute
1e-6 dual residual would demand 1e-12 relative accuracy. Success is therefore judged on
*relative* figures, each residual divided by ``max(1, scale)`` (OSQP's mixed test
``r <= eps_abs + eps_rel * scale`` with ``eps_abs = eps_rel``):

* primal scale ``max(||b||, ||h||, ||finite lb||, ||finite ub||)``: the data only;
* dual scale ``max(||P x||, ||q||, ||A^T y||, ||G^T z||, ||z_box||)``;
* gap scale ``max(|x^T P x|, |q^T x|, |b^T y|, |h^T z|, |lb^T [z_box]_-|, |ub^T [z_box]_+|)``.

**The answer's size never scales its own feasibility.** A primal scale with ``||A x||`` and
``||G x||`` in it (OSQP's), or an LCP scale with ``||F lam||``, lets an answer shrink its own
residuals by growing: ``x = (-5e8, 5e8)`` violates ``x_1 + x_2 >= 1`` of an infeasible LP by
1, which is 1e-9 of ``||G x||``; ``lam = (0, 1e9)`` has ``lam_2 w_2 = 1e9`` but a natural
residual of 1e-9 of ``||F lam||``. No relative perturbation argument rescues such an answer
either (a componentwise backward error still accepts an infeasible problem's huge answer:
infeasibility is within a 1e-9 relative change of ``G`` once ``x`` may be 1e9). So the
primal residual and the LCP natural residual are relative to the problem's data alone; the
dual scale keeps its answer terms, because a huge ``x`` or multiplier cannot make
stationarity hold on a dual-infeasible problem (the sign checks stay absolute). The solvers'
own acceptance tests (Lemke's, the LCP MIQP's) keep the answer-relative
:func:`relative_natural_residual`: a solver's check, not a verdict.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from c3bench.problems.instance import Problem, lcp_data
from c3bench.problems.names import Family

LCP_FAMILIES: tuple[Family, ...] = (Family.LCP, Family.LCP_GENERAL)
"""Families whose complementarity is ``0 <= lam perp F lam + q >= 0`` (no pairs)."""


def _inf_norm(vector: np.ndarray) -> float:
    return float(np.max(np.abs(vector), initial=0.0))


def primal_residual(problem: Problem, x: np.ndarray) -> float:
    """Largest violation of the equalities, inequalities and bounds."""
    x = np.asarray(x, dtype=float)
    parts = [0.0]
    if problem.A is not None:
        parts.append(_inf_norm(problem.A @ x - problem.b))
    if problem.G is not None:
        parts.append(_inf_norm(np.maximum(problem.G @ x - problem.h, 0.0)))
    if problem.lb is not None:
        finite = np.isfinite(problem.lb)
        parts.append(_inf_norm(np.maximum(problem.lb[finite] - x[finite], 0.0)))
    if problem.ub is not None:
        finite = np.isfinite(problem.ub)
        parts.append(_inf_norm(np.maximum(x[finite] - problem.ub[finite], 0.0)))
    return max(parts)


def _zeros_if_none(value: np.ndarray | None, size: int) -> np.ndarray:
    return np.zeros(size) if value is None else np.asarray(value, dtype=float)


def dual_sign_violation(problem: Problem, z: np.ndarray | None,
                        z_box: np.ndarray | None) -> float:
    """Largest wrong-signed multiplier (qpsolvers' convention, see :mod:`solvers.base`).

    ``max(||[-z]_+||, ||[-z_box]_+ where lb is not finite||, ||[z_box]_+ where ub is not
    finite||)``: ``z >= 0``, ``z_box_i < 0`` only on a finite lower bound, ``> 0`` only on a
    finite upper bound.
    """
    parts = [0.0]
    if problem.G is not None and z is not None:
        parts.append(_inf_norm(np.maximum(-np.asarray(z, dtype=float), 0.0)))
    if (problem.lb is not None or problem.ub is not None) and z_box is not None:
        box = np.asarray(z_box, dtype=float)
        lower = np.zeros(problem.n, dtype=bool) if problem.lb is None else np.isfinite(problem.lb)
        upper = np.zeros(problem.n, dtype=bool) if problem.ub is None else np.isfinite(problem.ub)
        parts.append(_inf_norm(np.maximum(-box[~lower], 0.0)))
        parts.append(_inf_norm(np.maximum(box[~upper], 0.0)))
    return max(parts)


def dual_residual(problem: Problem, x: np.ndarray, y: np.ndarray | None,
                  z: np.ndarray | None, z_box: np.ndarray | None) -> float:
    """``max(||P x + q + A^T y + G^T z + z_box||_inf, dual_sign_violation(z, z_box))``."""
    x = np.asarray(x, dtype=float)
    gradient = problem.P @ x + problem.q
    if problem.A is not None:
        gradient = gradient + problem.A.T @ _zeros_if_none(y, problem.n_eq)
    if problem.G is not None:
        gradient = gradient + problem.G.T @ _zeros_if_none(z, problem.n_ineq)
    if problem.lb is not None or problem.ub is not None:
        gradient = gradient + _zeros_if_none(z_box, problem.n)
    return max(_inf_norm(gradient), dual_sign_violation(problem, z, z_box))


def duality_gap(problem: Problem, x: np.ndarray, y: np.ndarray | None,
                z: np.ndarray | None, z_box: np.ndarray | None) -> float:
    """``|x^T P x + q^T x + b^T y + h^T z + lb^T [z_box]_- + ub^T [z_box]_+|``."""
    x = np.asarray(x, dtype=float)
    gap = float(x @ problem.P @ x + problem.q @ x)
    if problem.A is not None:
        gap += float(problem.b @ _zeros_if_none(y, problem.n_eq))
    if problem.G is not None:
        gap += float(problem.h @ _zeros_if_none(z, problem.n_ineq))
    box = _zeros_if_none(z_box, problem.n)
    if problem.lb is not None:
        finite = np.isfinite(problem.lb)
        gap += float(problem.lb[finite] @ np.minimum(box[finite], 0.0))
    if problem.ub is not None:
        finite = np.isfinite(problem.ub)
        gap += float(problem.ub[finite] @ np.maximum(box[finite], 0.0))
    return abs(gap)


def complementarity_violation(problem: Problem, x: np.ndarray) -> float:
    """``max |min(x_i, x_j)|`` over the complementarity pairs (0 without pairs)."""
    if problem.complementarity is None or problem.n_pairs == 0:
        return 0.0
    x = np.asarray(x, dtype=float)
    pairs = problem.complementarity
    return _inf_norm(np.minimum(x[pairs[:, 0]], x[pairs[:, 1]]))


def natural_residual(M: np.ndarray, q: np.ndarray, z: np.ndarray) -> float:
    """``||min(z, M z + q)||_inf``: zero exactly at a solution of ``LCP(M, q)``."""
    z = np.asarray(z, dtype=float)
    return _inf_norm(np.minimum(z, M @ z + q))


def relative_natural_residual(M: np.ndarray, q: np.ndarray, z: np.ndarray) -> float:
    """``||min(z, w)||_inf / max(1, ||M z||_inf, ||q||_inf)`` with ``w = M z + q``: the
    acceptance test of the LCP solvers (Lemke, the LCP MIQP), relative to the answer's own
    terms; the benchmark's verdict uses :func:`lcp_residual` (the data alone, module doc).

    Bounds ``[-z]_+`` and ``[-w]_+`` as well (``|min(a, b)| >= max(-a, -b)``), so a value at
    most ``tol`` implies ``z >= -tol`` and ``w >= -tol`` relative to the same scale.
    """
    z = np.asarray(z, dtype=float)
    scale = max(1.0, _inf_norm(M @ z), _inf_norm(q))
    return natural_residual(M, q, z) / scale


def lcp_residual(problem: Problem, x: np.ndarray) -> float:
    """Natural residual of the ``lcp`` / ``lcp_general`` instance ``LCP(F, q)`` relative to
    its data, ``||min(lam, F lam + q)||_inf / max(1, ||q||_inf)`` (``F`` and ``q`` from
    :func:`c3bench.problems.instance.lcp_data`; module doc: the answer's size never enters)."""
    F, q = lcp_data(problem)
    return natural_residual(F, q, x) / max(1.0, _inf_norm(q))


def cost_error(objective: float, reference: float) -> float:
    """``|f - f*| / max(1, |f*|)``."""
    return abs(objective - reference) / max(1.0, abs(reference))


def _scales(problem: Problem, x: np.ndarray, y: np.ndarray | None, z: np.ndarray | None,
            z_box: np.ndarray | None) -> tuple[float, float, float]:
    """Scales of the primal residual (the data alone), dual residual and duality gap (the
    sizes of their terms); module doc."""
    primal = [0.0]
    dual = [_inf_norm(problem.P @ x), _inf_norm(problem.q)]
    gap = [abs(float(x @ problem.P @ x)), abs(float(problem.q @ x))]
    if problem.A is not None and problem.b is not None:
        y = _zeros_if_none(y, problem.n_eq)
        primal.append(_inf_norm(problem.b))
        dual.append(_inf_norm(problem.A.T @ y))
        gap.append(abs(float(problem.b @ y)))
    if problem.G is not None and problem.h is not None:
        z = _zeros_if_none(z, problem.n_ineq)
        primal.append(_inf_norm(problem.h))
        dual.append(_inf_norm(problem.G.T @ z))
        gap.append(abs(float(problem.h @ z)))
    box = _zeros_if_none(z_box, problem.n)
    for bound, part in ((problem.lb, np.minimum(box, 0.0)), (problem.ub, np.maximum(box, 0.0))):
        if bound is None:
            continue
        finite = np.isfinite(bound)
        primal.append(_inf_norm(bound[finite]))
        gap.append(abs(float(bound[finite] @ part[finite])))
    if problem.lb is not None or problem.ub is not None:
        dual.append(_inf_norm(box))
    return max(primal), max(dual), max(gap)


@dataclass
class Residuals:
    """All accuracy figures of one solution: absolute, and relative to ``max(1, scale)``."""

    primal: float
    dual: float
    gap: float
    complementarity: float
    primal_relative: float = float("nan")
    dual_relative: float = float("nan")
    gap_relative: float = float("nan")

    def worst(self, include_dual: bool = True) -> float:
        values = [self.primal, self.complementarity]
        if include_dual:
            values += [self.dual, self.gap]
        return max(values)


def residuals(problem: Problem, x: np.ndarray, y: np.ndarray | None = None,
              z: np.ndarray | None = None, z_box: np.ndarray | None = None) -> Residuals:
    """Primal and dual residuals, duality gap and complementarity violation at once.

    The complementarity figure of an ``lcp`` or ``lcp_general`` instance is
    :func:`lcp_residual` (``lam perp w``).

    Dual residual and gap are ``nan`` when the solver returned no duals for a problem that has
    constraints (they cannot be computed, and are never counted as zero).
    """
    has_constraints = problem.n_eq + problem.n_ineq > 0 or problem.lb is not None \
        or problem.ub is not None
    missing_duals = has_constraints and y is None and z is None and z_box is None
    x = np.asarray(x, dtype=float)
    primal = primal_residual(problem, x)
    dual = float("nan") if missing_duals else dual_residual(problem, x, y, z, z_box)
    gap = float("nan") if missing_duals else duality_gap(problem, x, y, z, z_box)
    primal_scale, dual_scale, gap_scale = _scales(problem, x, y, z, z_box)
    return Residuals(
        primal=primal, dual=dual, gap=gap,
        complementarity=lcp_residual(problem, x) if problem.family in LCP_FAMILIES
        else complementarity_violation(problem, x),
        primal_relative=primal / max(1.0, primal_scale),
        dual_relative=dual / max(1.0, dual_scale),
        gap_relative=gap / max(1.0, gap_scale),
    )
