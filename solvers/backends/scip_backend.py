"""``scip``: SCIP's branch-and-bound (through PySCIPOpt) on the complementarity families.

The objective becomes an epigraph ``t >= (1/2 z^T P z + q^T z + offset) / scale`` (SCIP's
objective is linear; ``scale = max(1, max |P_ij|, max |q_i|)`` keeps the cut coefficients of
SCIP's LP O(1)), the pairs SOS1 constraints ``{z_i, z_j}`` (at most one non-zero; no big-M).
Parameters: ``limits/gap = tolerance`` always (SCIP's own default gap 0 makes the epigraph's
outer approximation branch until the LP fails numerically); ``numerics/feastol =
min(1e-6, max(tolerance, 1e-8))`` in non-default profiles (below 1e-8 SoPlex asks for GMP);
``limits/time`` 90 % of the registry's limit minus set-up; one thread; ``limits/nodes =
max_iterations``; any ``settings.options`` key containing ``/`` is passed as a SCIP
parameter. The answer is polished and checked as every MIQP answer
(:mod:`c3bench.solvers.backends._miqp`).

Timing (the contract of :mod:`c3bench.solvers.timing`; rankings use setup + solve): setup is
building the SCIP model (variables, SOS1 constraints, objective, parameters); solve is
``model.optimize()`` (presolve and branch-and-bound).

References
----------
S. Maher, M. Miltenberger, J. P. Pedroso, D. Rehfeldt, R. Schwarz and F. Serrano,
"PySCIPOpt: Mathematical programming in Python with the SCIP Optimization Suite",
Mathematical Software - ICMS 2016, Lecture Notes in Computer Science 9725, 301-307, 2016.

S. Bolusani et al., "The SCIP Optimization Suite 9.0", arXiv:2402.17702, 2024.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

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
from c3bench.solvers.base import Result, Settings, WarmStart
from c3bench.solvers.output import quiet_stdout
from c3bench.solvers.registry import register
from c3bench.solvers.timing import Stopwatch

SCIP_MIN_FEASTOL = 1e-8
"""Smallest feasibility tolerance given to SCIP (below it SoPlex asks for GMP)."""


def apply_settings(model: Any, settings: Settings, time_limit: float) -> None:
    """The benchmark's settings on a SCIP ``model``: feasibility tolerance (from the
    profile, within ``[SCIP_MIN_FEASTOL, 1e-6]``), wall-clock limit, one thread, node limit
    (``max_iterations``) and any SCIP parameter of ``settings.options`` (keys with a ``/``)."""
    if settings.sets_tolerance:
        model.setParam("numerics/feastol", float(min(1e-6, max(settings.tolerance,
                                                               SCIP_MIN_FEASTOL))))
    model.setParam("limits/time", time_limit)
    model.setParam("parallel/maxnthreads", 1)
    if settings.max_iterations is not None:
        model.setParam("limits/nodes", int(settings.max_iterations))
    for key, value in settings.options.items():
        if "/" in key:
            model.setParam(key, value)


def objective_scale(problem: Problem) -> float:
    """``max(1, max |P_ij|, max |q_i|)``: the epigraph is ``t >= f(z) / scale`` so that the
    cut coefficients SCIP's LP sees are O(1) (the MPC weights reach 2e5)."""
    return max(1.0, float(np.max(np.abs(problem.P), initial=0.0)),
               float(np.max(np.abs(problem.q), initial=0.0)))



class ScipMIQP(MIQPBackend):
    """SCIP branch-and-bound (Maher et al. 2016's PySCIPOpt) with SOS1 complementarity and an
    epigraph objective."""

    name = "scip"
    package = "pyscipopt"
    description = "MIQP reference: SCIP (PySCIPOpt), SOS1 complementarity, no big-M"

    def solve(self, problem: Problem, settings: Settings,
              warm_start: WarmStart | None = None) -> Result:
        """Build the SCIP model (module docstring), optimise quietly, polish the answer."""
        from pyscipopt import Model, quicksum

        watch = Stopwatch()
        with watch.lap("setup"):
            model = Model()
            model.hideOutput()
            lb, ub = bounds(problem)
            z = [model.addVar(name=f"z{i}", vtype="C",
                              lb=None if math.isinf(lb[i]) else float(lb[i]),
                              ub=None if math.isinf(ub[i]) else float(ub[i]))
                 for i in range(problem.n)]
            for matrix, vector, sense in ((problem.A, problem.b, "=="),
                                          (problem.G, problem.h, "<=")):
                if matrix is None or vector is None:
                    continue
                for row, value in zip(matrix, vector, strict=True):
                    columns = np.flatnonzero(row)
                    expression = quicksum(float(row[j]) * z[j] for j in columns)
                    if sense == "==":
                        model.addCons(expression == float(value))
                    else:
                        model.addCons(expression <= float(value))
            t = model.addVar(name="epigraph", vtype="C", lb=None, ub=None)
            upper = np.triu(problem.P)
            rows, columns = np.nonzero(upper)
            quadratic = quicksum(
                (0.5 if r == c else 1.0) * float(upper[r, c]) * z[r] * z[c]
                for r, c in zip(rows, columns, strict=True))
            linear = quicksum(float(problem.q[i]) * z[i] for i in np.flatnonzero(problem.q))
            scale = objective_scale(problem)
            # offset inside the epigraph: SCIP's relative gap is then relative to the true cost
            model.addCons((quadratic + linear + problem.objective_offset) * (1.0 / scale) <= t)
            model.setObjective(t, "minimize")
            for i, j in pairs_of(problem):
                model.addConsSOS1([z[int(i)], z[int(j)]])
            # SCIP's own default gap (0) makes the epigraph outer approximation branch
            # until the LP fails numerically, so the gap always comes from the settings.
            model.setParam("limits/gap", float(settings.tolerance))
            apply_settings(model, settings, solver_time_limit(settings, watch.get("setup")))
            if warm_start is not None and warm_start.x is not None:
                start = model.createSol()
                for i, value in enumerate(np.asarray(warm_start.x, dtype=float)):
                    model.setSolVal(start, z[i], float(value))
                model.setSolVal(start, t, float(problem.objective(warm_start.x)) / scale)
                model.addSol(start, free=True)
        with watch.lap("solve"), quiet_stdout():  # SoPlex prints tolerance warnings
            try:
                model.optimize()
            except Exception as error:  # noqa: BLE001 - SCIP raises plain Exception
                return Result.failed(self.name, problem.name, Failure.ERROR,
                                     f"scip: {error}", setup_time=watch.get("setup"),
                                     solve_time=watch.get("solve"),
                                     iterations=int(model.getNNodes()))
        status = str(model.getStatus())
        diagnostics: dict[str, float] = {
            "mip_gap": float(model.getGap()),
            "nodes": float(model.getNNodes()),
            "primal_bound": float(model.getPrimalbound()) * scale,
            "dual_bound": float(model.getDualbound()) * scale,
            "objective_scale": scale,
            "scip_solving_time": float(model.getSolvingTime()),
        }
        x = None
        if model.getNSols() > 0:
            best = model.getBestSol()
            x = np.array([model.getSolVal(best, var) for var in z])
        found = status in ("optimal", "gaplimit") and x is not None
        failure = Failure.NONE if found else failure_category(status)
        return finish_point(self.name, problem, settings, x, found, f"scip: {status}", watch,
                            diagnostics, int(model.getNNodes()), failure)


register(ScipMIQP())
