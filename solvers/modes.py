"""Complementarity modes: the convex QP of one mode, its exact refinement, brute-force search.

The complementarity families (``projection``, ``mpcc``) are mixed-integer QPs:

    minimise    1/2 z^T P z + q^T z + offset
    subject to  A z = b,  G z <= h,  lb <= z <= ub,
                0 <= z_i  perp  z_j >= 0   for every pair (i, j),

with ``P`` positive semi-definite. Fixing, for each pair, which member is zero (a *mode*)
leaves a convex QP, so the global optimum is the best mode optimum.

* :func:`solve_mode`: the QP of one mode, solved by Clarabel at :data:`MODE_QP_TOLERANCE` and
  then re-solved exactly on the face Clarabel's point identifies (:func:`refine_on_face`, a
  null-space solve). The refinement matters: where ``[E F H]`` is nearly rank deficient,
  Clarabel's answer was measured 7.7e-6 (relative) above the exact mode optimum while
  feasible to 3e-12.
* :func:`polish`: the mode of a point (:func:`mode_of`: the smaller member of each pair set
  to zero) re-solved; the MIQP backends polish their answers with it.
* :func:`enumerate_modes` / :func:`search_modes`: the brute-force reference, all
  ``2^pairs`` modes, best feasible kept.

References
----------
P. J. Goulart and Y. Chen, "Clarabel: An interior-point solver for conic programs with
quadratic objectives", arXiv:2405.12762, 2024 (the QP of one mode).

J. Nocedal and S. J. Wright, *Numerical Optimization*, 2nd ed., Springer, 2006, section 16.2
(the null-space method of :func:`refine_on_face`).
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sparse

from c3bench.problems.instance import Problem
from c3bench.solvers.residuals import primal_residual
from c3bench.solvers.timing import single_thread_blas

MODE_QP_TOLERANCE = 1e-10
"""Clarabel's gap and feasibility tolerances for the QP of one mode."""

REFINE_SLACK = 1e-7
"""Relative cost increase up to which the exact face solution replaces Clarabel's point."""

MODE_FEASIBILITY = 1e-7
"""Largest primal residual at which a mode's QP solution counts as feasible."""


# --- one mode: a convex QP ------------------------------------------------------------------
@dataclass
class ModeSolution:
    """Optimum of the convex QP of one complementarity mode.

    Attributes
    ----------
    x
        Full-size solution (``None`` when the mode is infeasible or the solve failed).
    objective
        ``1/2 x^T P x + q^T x + offset`` (``inf`` without a solution).
    status
        Clarabel's status text.
    """

    x: np.ndarray | None
    objective: float
    status: str


def _bounds(problem: Problem) -> tuple[np.ndarray, np.ndarray]:
    lb = problem.lb if problem.lb is not None else np.full(problem.n, -np.inf)
    ub = problem.ub if problem.ub is not None else np.full(problem.n, np.inf)
    return lb, ub


def solve_mode(problem: Problem, zero: np.ndarray,
               tolerance: float = MODE_QP_TOLERANCE) -> ModeSolution:
    """Solve the convex QP with the variables ``zero`` fixed at 0 (the pairs dropped).

    The fixed variables are eliminated; the rest keep their bounds, so
    ``min 1/2 y^T P_kk y + q_k^T y  s.t.  A_k y = b, G_k y <= h, lb_k <= y <= ub_k`` over the
    kept indices ``k``, solved by Clarabel with gap and feasibility tolerances ``tolerance``,
    then refined by :func:`refine_on_face` (kept unless it costs more than
    :data:`REFINE_SLACK` relative). The answer counts as feasible when its primal residual
    is at most :data:`MODE_FEASIBILITY`.
    """
    import clarabel

    n = problem.n
    zero = np.unique(np.asarray(zero, dtype=np.int64))
    lb, ub = _bounds(problem)
    if np.any(lb[zero] > 0) or np.any(ub[zero] < 0):
        return ModeSolution(None, math.inf, "infeasible: a fixed variable excludes 0")
    keep = np.setdiff1d(np.arange(n), zero)
    m = keep.size
    P = sparse.csc_matrix(np.triu(problem.P[np.ix_(keep, keep)]))
    blocks: list[np.ndarray] = []
    rhs: list[np.ndarray] = []
    cones: list[object] = []
    if problem.A is not None and problem.b is not None:
        blocks.append(problem.A[:, keep])
        rhs.append(problem.b)
        cones.append(clarabel.ZeroConeT(problem.n_eq))
    inequalities = 0
    if problem.G is not None and problem.h is not None:
        blocks.append(problem.G[:, keep])
        rhs.append(problem.h)
        inequalities += problem.n_ineq
    lower = np.flatnonzero(np.isfinite(lb[keep]))
    upper = np.flatnonzero(np.isfinite(ub[keep]))
    identity = np.eye(m)
    if lower.size:
        blocks.append(-identity[lower])
        rhs.append(-lb[keep][lower])
        inequalities += lower.size
    if upper.size:
        blocks.append(identity[upper])
        rhs.append(ub[keep][upper])
        inequalities += upper.size
    if inequalities:
        cones.append(clarabel.NonnegativeConeT(inequalities))
    A_all = sparse.csc_matrix(np.vstack(blocks)) if blocks else sparse.csc_matrix((0, m))
    b_all = np.concatenate(rhs) if rhs else np.zeros(0)
    settings = clarabel.DefaultSettings()
    settings.verbose = False
    settings.tol_gap_abs = tolerance
    settings.tol_gap_rel = tolerance
    settings.tol_feas = tolerance
    settings.max_iter = 400
    solution = clarabel.DefaultSolver(P, problem.q[keep], A_all, b_all, cones,
                                      settings).solve()
    status = str(solution.status)
    if status not in ("Solved", "AlmostSolved"):
        return ModeSolution(None, math.inf, status)
    x = np.zeros(n)
    x[keep] = np.asarray(solution.x)
    if not np.all(np.isfinite(x)) or primal_residual(problem, x) > MODE_FEASIBILITY:
        return ModeSolution(None, math.inf, f"{status} (primal residual too large)")
    objective = problem.objective(x)
    refined = refine_on_face(problem, x, zero)
    # the exact face solution wins unless it is clearly worse (a wrongly guessed active set);
    # a slightly cheaper interior-point answer may just be slightly infeasible
    if refined is not None and problem.objective(refined) <= objective + REFINE_SLACK * max(
            1.0, abs(objective)):
        return ModeSolution(refined, problem.objective(refined), f"{status}, refined")
    return ModeSolution(x, objective, status)


def refine_on_face(problem: Problem, x: np.ndarray, zero: np.ndarray,
                   activity: float = 1e-8) -> np.ndarray | None:
    """Exact minimiser on the face of ``x``'s active constraints, or ``None``.

    The bounds that ``x`` meets within ``activity * (1 + |bound|)`` (and the variables
    ``zero``) are fixed, the inequality rows it meets become equalities, and

        min 1/2 y^T P y + q^T y   s.t.   C y = d

    is solved by the null-space method with an SVD (rank cut at ``1e-13 sigma_max``), so
    exactly redundant rows are harmless and nearly dependent ones (``[E F H]`` with
    ``sigma_min / sigma_max ~ 1e-8`` near two table contacts) are honoured exactly; an
    interior-point solution there can be off by 1e-5 in cost while feasible to 1e-12.
    Returned only when it is feasible (primal residual at most 1e-9) and finite.
    """
    n = problem.n
    lb, ub = _bounds(problem)
    fixed_value = np.full(n, np.nan)
    at_lower = np.isfinite(lb) & (x - lb <= activity * (1 + np.abs(lb)))
    at_upper = np.isfinite(ub) & (ub - x <= activity * (1 + np.abs(ub)))
    fixed_value[at_lower] = lb[at_lower]
    fixed_value[at_upper] = ub[at_upper]
    fixed_value[np.asarray(zero, dtype=np.int64)] = 0.0
    fixed = np.isfinite(fixed_value)
    free = np.flatnonzero(~fixed)
    rows: list[np.ndarray] = []
    rhs: list[np.ndarray] = []
    if problem.A is not None and problem.b is not None:
        rows.append(problem.A)
        rhs.append(problem.b)
    if problem.G is not None and problem.h is not None:
        tight = problem.h - problem.G @ x <= activity * (1 + np.abs(problem.h))
        rows.append(problem.G[tight])
        rhs.append(problem.h[tight])
    base = np.where(fixed, fixed_value, 0.0)
    if free.size == 0:
        candidate = base
    else:
        C = np.vstack(rows)[:, free] if rows else np.zeros((0, free.size))
        d = (np.concatenate(rhs) - np.vstack(rows) @ base) if rows else np.zeros(0)
        P_ff = problem.P[np.ix_(free, free)]
        g = problem.q[free] + problem.P[np.ix_(free, np.flatnonzero(fixed))] @ base[fixed]
        if C.shape[0]:
            _, sigma, vt = np.linalg.svd(C, full_matrices=True)
            rank = int(np.sum(sigma > 1e-13 * sigma[0])) if sigma.size and sigma[0] > 0 else 0
            particular = np.linalg.lstsq(C, d, rcond=1e-13)[0]
            null = vt[rank:].T
        else:
            particular = np.zeros(free.size)
            null = np.eye(free.size)
        if null.shape[1]:
            reduced = null.T @ P_ff @ null
            step = np.linalg.lstsq(reduced, -null.T @ (P_ff @ particular + g), rcond=1e-13)[0]
            y = particular + null @ step
        else:
            y = particular
        candidate = base.copy()
        candidate[free] = y
    if not np.all(np.isfinite(candidate)) or primal_residual(problem, candidate) > 1e-9:
        return None
    return candidate


def mode_of(problem: Problem, x: np.ndarray) -> np.ndarray:
    """The variables a point sets to zero: per pair, the member with the smaller value
    (ties: the first member)."""
    pairs = problem.complementarity
    if pairs is None or pairs.size == 0:
        return np.zeros(0, dtype=np.int64)
    x = np.asarray(x, dtype=float)
    first_smaller = x[pairs[:, 0]] <= x[pairs[:, 1]]
    return np.where(first_smaller, pairs[:, 0], pairs[:, 1])


def polish(problem: Problem, x: np.ndarray) -> ModeSolution:
    """Re-solve the mode of ``x`` (see :func:`mode_of`) as a convex QP."""
    return solve_mode(problem, mode_of(problem, x))


@dataclass
class ModeSearch:
    """Outcome of the brute-force search.

    Attributes
    ----------
    x, objective
        Best feasible point and its objective (``None`` and ``inf`` when no mode is feasible).
    zero
        Variables fixed at 0 in the best mode.
    modes, feasible
        Modes solved and modes found feasible.
    """

    x: np.ndarray | None
    objective: float
    zero: np.ndarray
    modes: int
    feasible: int


def search_modes(problem: Problem, max_pairs: int = 12) -> ModeSearch:
    """Solve every complementarity mode (see :func:`enumerate_modes`) and keep the best."""
    pairs = problem.complementarity
    count = 0 if pairs is None else int(pairs.shape[0])
    if count > max_pairs:
        raise ValueError(f"{problem.name}: {count} complementarity pairs exceed "
                         f"max_pairs={max_pairs} (2^{count} convex QPs)")
    best = ModeSearch(None, math.inf, np.zeros(0, dtype=np.int64), 0, 0)
    choices = itertools.product((0, 1), repeat=count)
    with single_thread_blas():  # thousands of tiny factorisations: threads only cost
        for choice in choices:
            _visit_mode(problem, pairs, count, choice, best)
    return best


def _visit_mode(problem: Problem, pairs: np.ndarray | None, count: int,
                choice: tuple[int, ...], best: ModeSearch) -> None:
    """Solve one mode and keep it in ``best`` when it is feasible and cheaper."""
    zero = (np.array([pairs[i, c] for i, c in enumerate(choice)], dtype=np.int64)
            if count and pairs is not None else np.zeros(0, dtype=np.int64))
    solution = solve_mode(problem, zero)
    best.modes += 1
    if solution.x is None:
        return
    best.feasible += 1
    if solution.objective < best.objective:
        best.x, best.objective, best.zero = solution.x, solution.objective, zero


def enumerate_modes(problem: Problem, max_pairs: int = 12) -> tuple[np.ndarray | None, float]:
    """Brute-force global optimum over all ``2^pairs`` complementarity modes.

    For every choice of one member per pair fixed at 0 (the other keeps its bounds,
    ``lb = 0``), the convex QP is solved by :func:`solve_mode` (Clarabel, tolerances 1e-10);
    the best feasible mode wins (ties: the first in lexicographic order, first members
    zeroed first).

    Returns
    -------
    x, objective
        The optimum and ``1/2 x^T P x + q^T x + offset``; ``(None, inf)`` when every mode is
        infeasible.

    Raises
    ------
    ValueError
        When the problem has more than ``max_pairs`` pairs.
    """
    search = search_modes(problem, max_pairs)
    return search.x, search.objective
