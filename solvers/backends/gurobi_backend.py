"""``gurobi``: Gurobi's MIQP branch-and-bound on the complementarity families.

Native convex quadratic objective, the pairs as SOS1 constraints (no big-M), one thread,
``TimeLimit`` 90 % of the registry's limit minus set-up. In non-default profiles
``MIPGap = tolerance`` (``MIPGapAbs = 0``) and ``FeasibilityTol``, ``OptimalityTol`` (at most
1e-6) and ``IntFeasTol`` (at most 1e-5) follow the tolerance (at least 1e-9). Any
``settings.options`` key other than ``polish`` is set as a Gurobi parameter. Needs gurobipy
and a licence (the pip wheel's size-limited licence is enough for these instances); without
one the backend is unavailable, and an instance over the licence's size limit is recorded as
``Failure.UNAVAILABLE``. The answer is polished and checked as every MIQP answer
(:mod:`c3bench.solvers.backends._miqp`).

Timing (the contract of :mod:`c3bench.solvers.timing`; rankings use setup + solve): setup is
the environment and the model (variables, SOS1 constraints, objective, parameters); solve is
``model.optimize()``.

References
----------
Gurobi Optimization, LLC, "Gurobi Optimizer Reference Manual", version 11, 2024.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sparse

from c3bench.problems.errors import BackendUnavailable
from c3bench.problems.instance import Problem
from c3bench.problems.names import Failure
from c3bench.solvers.backends._miqp import (
    MIQPBackend,
    bounds,
    finish_point,
    pairs_of,
    solver_time_limit,
)
from c3bench.solvers.backends._qp_forms import failure_category
from c3bench.solvers.base import Result, Settings, WarmStart, require_module
from c3bench.solvers.registry import register
from c3bench.solvers.timing import Stopwatch

GUROBI_SIZE_LIMIT = 10010
"""Gurobi's error code for a model too large for the licence."""


class GurobiMIQP(MIQPBackend):
    """Gurobi MIQP (Gurobi Optimization 2024) with SOS1 complementarity (when gurobipy and a
    licence are present)."""

    name = "gurobi"
    package = "gurobipy"
    description = "MIQP reference: Gurobi, SOS1 complementarity (licence permitting)"
    _licence: str | None = None
    """``""`` once a licence was found, the reason when none was, ``None`` before the check."""

    def require(self) -> None:
        """gurobipy imports and a Gurobi environment starts (a licence; checked once per
        process)."""
        gp = require_module("gurobipy")
        if GurobiMIQP._licence is None:
            try:
                env = gp.Env(empty=True)
                env.setParam("OutputFlag", 0)
                env.start()
                env.dispose()
                GurobiMIQP._licence = ""
            except gp.GurobiError as error:
                GurobiMIQP._licence = f"no usable Gurobi licence: {error}"
        if GurobiMIQP._licence:
            raise BackendUnavailable(GurobiMIQP._licence)

    def solve(self, problem: Problem, settings: Settings,
              warm_start: WarmStart | None = None) -> Result:
        """Build the model, optimise on one thread, polish the answer; a licence too small
        for the instance raises :class:`BackendUnavailable` (an unavailable row)."""
        import gurobipy as gp
        from gurobipy import GRB

        watch = Stopwatch()
        try:
            with watch.lap("setup"):
                env = gp.Env(empty=True)
                env.setParam("OutputFlag", 0)
                env.start()
                model = gp.Model(env=env)
                lb, ub = bounds(problem)
                z = model.addMVar(problem.n, lb=np.where(np.isinf(lb), -GRB.INFINITY, lb),
                                  ub=np.where(np.isinf(ub), GRB.INFINITY, ub))
                if problem.A is not None and problem.b is not None:
                    model.addConstr(sparse.csr_matrix(problem.A) @ z == problem.b)
                if problem.G is not None and problem.h is not None:
                    model.addConstr(sparse.csr_matrix(problem.G) @ z <= problem.h)
                model.setObjective(0.5 * (z @ sparse.csr_matrix(problem.P) @ z)
                                   + problem.q @ z + problem.objective_offset, GRB.MINIMIZE)
                variables = z.tolist()
                for i, j in pairs_of(problem):
                    model.addSOS(GRB.SOS_TYPE1, [variables[int(i)], variables[int(j)]],
                                 [1.0, 2.0])
                model.Params.Threads = 1
                model.Params.TimeLimit = solver_time_limit(settings, watch.get("setup"))
                if settings.sets_tolerance:
                    model.Params.MIPGap = settings.tolerance
                    model.Params.MIPGapAbs = 0.0
                    model.Params.FeasibilityTol = min(1e-6, max(settings.tolerance, 1e-9))
                    model.Params.OptimalityTol = min(1e-6, max(settings.tolerance, 1e-9))
                    model.Params.IntFeasTol = min(1e-5, max(settings.tolerance, 1e-9))
                if warm_start is not None and warm_start.x is not None:
                    z.Start = np.asarray(warm_start.x, dtype=float)
                for key, value in settings.options.items():
                    if key != "polish":
                        model.setParam(key, value)
            with watch.lap("solve"):
                model.optimize()
        except gp.GurobiError as error:
            if getattr(error, "errno", None) == GUROBI_SIZE_LIMIT:
                raise BackendUnavailable(f"licence size limit: {error}") from error
            return Result.failed(self.name, problem.name, Failure.ERROR,
                                 f"gurobi error: {error}", setup_time=watch.get("setup"),
                                 solve_time=watch.get("solve"))
        codes = {GRB.OPTIMAL: "optimal", GRB.TIME_LIMIT: "time_limit",
                 GRB.INFEASIBLE: "infeasible", GRB.INF_OR_UNBD: "infeasible_or_unbounded",
                 GRB.UNBOUNDED: "unbounded", GRB.NODE_LIMIT: "node_limit",
                 GRB.SUBOPTIMAL: "suboptimal", GRB.NUMERIC: "numeric"}
        status = codes.get(model.Status, f"status {model.Status}")
        diagnostics: dict[str, float] = {"nodes": float(model.NodeCount)}
        x = None
        if model.SolCount > 0:
            x = np.asarray(z.X, dtype=float)
            diagnostics["mip_gap"] = float(model.MIPGap)
            diagnostics["primal_bound"] = float(model.ObjVal)
            diagnostics["dual_bound"] = float(model.ObjBound)
        found = model.Status == GRB.OPTIMAL and x is not None
        failure = Failure.NONE if found else failure_category(status)
        iterations = int(model.NodeCount)
        model.dispose()
        env.dispose()
        return finish_point(self.name, problem, settings, x, found, f"gurobi: {status}",
                            watch, diagnostics, iterations, failure)


register(GurobiMIQP())
