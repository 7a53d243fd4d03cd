"""What the MIQP adapters share: mode polishing of the answer, its check, the time budget.

A helper module (the registry skips modules whose name starts with ``_``). Every MIQP
backend (``scip``, ``gurobi``, ``bonmin``) takes the complementarity families (``projection``,
``mpcc``) with the pairs as SOS1 constraints (Beale and Tomlin 1970), so no big-M constant and
no variable bound is needed: their results carry ``diagnostics["big_m"] = 0`` (a big-M
formulation, ``cvxpy_scip``, records its smallest constant there instead).

Polishing (default on; ``settings.options["polish"] = False`` turns it off): the mode of the
solver's point (the smaller member of each pair set to zero) is re-solved as a convex QP
(:func:`c3bench.solvers.modes.polish`, Clarabel at 1e-10 plus an exact face solve), so the
reported point is the exact optimum of the mode the MIQP solver chose;
``diagnostics["objective_solver"]`` keeps the solver's own objective and
``polish_cost_change`` the relative change. The polished point is used even when it costs
more: the solvers' points satisfy complementarity only to their feasibility tolerance
(1e-6), and where ``[E F H]`` is nearly rank deficient such a point can be much cheaper than
any exactly complementary one. MIQP duals are not meaningful: ``y``, ``z`` and ``z_box`` stay
``None``.

References
----------
E. M. L. Beale and J. A. Tomlin, "Special facilities in a general mathematical programming
system for non-convex problems using ordered sets of variables", Proceedings of the Fifth
International Conference on Operational Research (OR 69), 447-454, 1970.
"""

from __future__ import annotations

import numpy as np

from c3bench.problems.instance import Problem
from c3bench.problems.names import COMPLEMENTARITY_FAMILIES, Failure, Family
from c3bench.solvers.base import Backend, Result, Settings
from c3bench.solvers.modes import polish
from c3bench.solvers.residuals import complementarity_violation, primal_residual
from c3bench.solvers.timing import Stopwatch


class MIQPBackend(Backend):
    """Common attribute of the MIQP adapters: the complementarity families."""

    families: tuple[Family, ...] = COMPLEMENTARITY_FAMILIES


def bounds(problem: Problem) -> tuple[np.ndarray, np.ndarray]:
    """``lb`` and ``ub`` as full vectors (``-inf`` / ``+inf`` where absent)."""
    lb = problem.lb if problem.lb is not None else np.full(problem.n, -np.inf)
    ub = problem.ub if problem.ub is not None else np.full(problem.n, np.inf)
    return lb, ub


def polish_enabled(settings: Settings) -> bool:
    """``settings.options["polish"]`` (default on)."""
    return bool(settings.options.get("polish", True))


def pairs_of(problem: Problem) -> np.ndarray:
    """The complementarity pairs, ``(pairs, 2)`` integers (none: an empty array)."""
    if problem.complementarity is None:
        return np.zeros((0, 2), dtype=np.int64)
    return np.asarray(problem.complementarity, dtype=np.int64).reshape(-1, 2)


def finish_point(name: str, problem: Problem, settings: Settings, x: np.ndarray | None,
                 found: bool, status: str, watch: Stopwatch, diagnostics: dict[str, float],
                 iterations: int | None, failure: Failure = Failure.NONE) -> Result:
    """Polish (when asked), measure the point with :mod:`c3bench.solvers.residuals` and build
    the :class:`Result`.

    ``found`` stays true only if the final point is feasible and complementary within
    ``max(settings.tolerance, 1e-6)`` (the MIQP solvers' own feasibility tolerance).
    """
    diagnostics.setdefault("big_m", 0.0)
    if x is not None:
        x = np.asarray(x, dtype=float)
        diagnostics["objective_solver"] = problem.objective(x)
        diagnostics["complementarity_solver"] = complementarity_violation(problem, x)
        if polish_enabled(settings):
            with watch.lap("polish"):
                polished = polish(problem, x)
            diagnostics["polish_time"] = watch.get("polish")
            if polished.x is not None:
                diagnostics["polish_cost_change"] = (
                    (polished.objective - problem.objective(x))
                    / max(1.0, abs(problem.objective(x))))
                x = polished.x
                diagnostics["polished"] = 1.0
            else:
                diagnostics["polished"] = 0.0
                status += f"; polish not used ({polished.status})"
        limit = max(settings.tolerance, 1e-6)
        violation = max(primal_residual(problem, x), complementarity_violation(problem, x))
        diagnostics["final_violation"] = violation
        if found and violation > limit:
            found = False
            failure = failure or Failure.ERROR
            status += f"; final point violates constraints by {violation:.3g} > {limit:.3g}"
    return Result(solver=name, problem=problem.name, found=found, status=status, x=x,
                  iterations=iterations, setup_time=watch.get("setup"),
                  solve_time=watch.get("solve") + watch.get("polish"),
                  objective=None if x is None else problem.objective(x),
                  diagnostics=diagnostics,
                  failure=Failure.NONE if found else (failure or Failure.ERROR))


def solver_time_limit(settings: Settings, elapsed: float) -> float:
    """Time left for the solver itself: 90 % of the registry's limit minus set-up time."""
    return max(0.05, 0.9 * settings.time_limit - elapsed)
