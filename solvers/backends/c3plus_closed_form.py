"""``c3plus_closed_form``: C3+'s projection onto complementarity in closed form.

Takes a ``projection`` instance of the separable C3+ variant (``meta["variant"] == "c3plus"``):
diagonal ``P``, no rows, pair members bounded to ``[0, inf)`` and every other variable free.
The objective ``1/2 P_ii z_i^2 + q_i z_i`` is ``w_i (z_i - v_i)^2 + const`` with
``w_i = P_ii / 2`` and ``v_i = -q_i / P_ii``, so the answer is ``v`` outside the pairs and the
closed form of :func:`c3bench.solvers.projection.c3plus_projection` on every pair (keep the
member with the larger ``sqrt(w) [v]_+``; ties keep ``lam``). No iterations; float64 or
float32.

Timing (the contract of :mod:`c3bench.solvers.timing`; rankings use setup + solve): setup is
reading the separable weights and target; solve is the per-pair closed form.

References
----------
Bui et al., 2025: C3+, whose slack ``eta`` makes this projection separable (the method of
the reference study c3bench reproduces).
"""

from __future__ import annotations

import numpy as np

from c3bench.problems.instance import Problem
from c3bench.problems.names import Failure, Family, Precision, Variant
from c3bench.solvers.base import Backend, Result, Settings, WarmStart
from c3bench.solvers.projection import c3plus_projection
from c3bench.solvers.registry import register
from c3bench.solvers.timing import Stopwatch


def separable_data(problem: Problem) -> tuple[np.ndarray, np.ndarray, str]:
    """Weights ``w = diag(P)/2`` and targets ``v`` of a separable projection, or a reason.

    ``1/2 P_ii z_i^2 + q_i z_i = w_i (z_i - v_i)^2 + const`` with ``w_i = P_ii / 2`` and
    ``v_i = -q_i / P_ii``; where ``P_ii = 0`` the target is taken from ``data["v"]`` (any
    value is optimal there when also ``q_i = 0``).
    """
    n = problem.n
    diagonal = np.diag(problem.P).copy()
    if np.max(np.abs(problem.P - np.diag(diagonal)), initial=0.0) > 0:
        return np.zeros(0), np.zeros(0), "P is not diagonal"
    positive = diagonal > 0
    if np.any(~positive & (problem.q != 0)):
        return np.zeros(0), np.zeros(0), "linear term on a variable with zero weight"
    target = np.zeros(n)
    if "v" in problem.data and np.shape(problem.data["v"]) == (n,):
        target = np.asarray(problem.data["v"], dtype=float).copy()
    target[positive] = -problem.q[positive] / diagonal[positive]
    return diagonal / 2.0, target, ""


class C3PlusClosedForm(Backend):
    """C3+'s projection in closed form (Bui et al. 2025; no iterations): exact for the
    ``c3plus`` variant."""

    name = "c3plus_closed_form"
    families = (Family.PROJECTION,)
    package = ""
    precisions = (Precision.FLOAT64, Precision.FLOAT32)
    description = "C3+ closed-form projection: keep the larger of sqrt(w) [v]_+ per pair"

    def accepts(self, problem: Problem) -> tuple[bool, str]:
        """The separable C3+ form only (module docstring)."""
        ok, reason = super().accepts(problem)
        if not ok:
            return ok, reason
        variant = problem.meta.get("variant")
        if variant != Variant.C3PLUS:
            return False, (f"the closed form needs the separable c3plus variant; variant "
                           f"{variant!r} couples eta = E x + F lam + H u + c (use an MIQP "
                           "backend)")
        if problem.A is not None or problem.G is not None:
            return False, "the closed form takes no equality or inequality rows"
        pairs = problem.complementarity
        if pairs is None or pairs.size == 0:
            return False, "no complementarity pairs"
        members = pairs.ravel()
        if len(set(members.tolist())) != members.size:
            return False, "a variable belongs to two pairs"
        lb = problem.lb if problem.lb is not None else np.full(problem.n, -np.inf)
        ub = problem.ub if problem.ub is not None else np.full(problem.n, np.inf)
        free = np.ones(problem.n, dtype=bool)
        free[members] = False
        if np.any(np.isfinite(lb[free])) or np.any(np.isfinite(ub[free])):
            return False, "variables outside the pairs must be unbounded"
        if np.any(lb[members] != 0) or np.any(np.isfinite(ub[members])):
            return False, "pair members must have bounds [0, inf)"
        _, _, reason = separable_data(problem)
        if reason:
            return False, reason
        return True, ""

    def solve(self, problem: Problem, settings: Settings,
              warm_start: WarmStart | None = None) -> Result:
        """Project every pair in ``settings.precision``; the answer is returned in float64."""
        watch = Stopwatch()
        with watch.lap("setup"):
            weights, target, reason = separable_data(problem)
            pairs = problem.complementarity
            if reason or pairs is None:
                return Result.failed(self.name, problem.name, Failure.UNSUPPORTED,
                                     reason or "no complementarity pairs")
            dtype = settings.dtype
            weights = weights.astype(dtype)
            target = target.astype(dtype)
        with watch.lap("solve"):
            x = target.copy()
            lam, eta = c3plus_projection(target[pairs[:, 0]], target[pairs[:, 1]],
                                         weights[pairs[:, 0]], weights[pairs[:, 1]])
            x[pairs[:, 0]] = lam
            x[pairs[:, 1]] = eta
        x64 = x.astype(np.float64)
        return Result(solver=self.name, problem=problem.name, found=True,
                      status="solved (closed form)", x=x64, iterations=0,
                      setup_time=watch.get("setup"), solve_time=watch.get("solve"),
                      objective=problem.objective(x64))


register(C3PlusClosedForm())
