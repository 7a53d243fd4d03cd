"""``bonmin``: Bonmin's branch-and-bound (B-BB) through CasADi on the complementarity families.

Bonmin runs branch-and-bound on convex NLP relaxations solved by IPOPT, with the pairs passed
as ``sos1_groups`` (no big-M); ``bonmin.time_limit`` 90 % of the registry's limit, every log
level 0 (its node log is silenced anyway: it ignores them). In non-default profiles
``allowable_fraction_gap = tolerance`` (``allowable_gap = 0``), ``integer_tolerance`` and
``tol`` follow it; ``node_limit = max_iterations``; ``settings.options`` keys starting with
``bonmin.`` are passed on. The answer is polished and checked as every MIQP answer
(:mod:`c3bench.solvers.backends._miqp`). CasADi's Bonmin status is one of ``SUCCESS``,
``INFEASIBLE``, ``CONTINUOUS_UNBOUNDED``, ``LIMIT_EXCEEDED``, ``USER_INTERRUPT`` and
``MINLP_ERROR``; ``LIMIT_EXCEEDED`` (a time or node limit, not told apart) maps to
``Failure.ERROR``.

Timing (the contract of :mod:`c3bench.solvers.timing`; rankings use setup + solve): setup is
building the CasADi expressions and the ``nlpsol`` function; solve is its call (Bonmin's
branch-and-bound).

References
----------
P. Bonami, L. T. Biegler, A. R. Conn, G. Cornuéjols, I. E. Grossmann, C. D. Laird, J. Lee,
A. Lodi, F. Margot, N. Sawaya and A. Wächter, "An algorithmic framework for convex mixed
integer nonlinear programs", Discrete Optimization 5(2), 186-204, 2008.

J. A. E. Andersson, J. Gillis, G. Horn, J. B. Rawlings and M. Diehl, "CasADi: a software
framework for nonlinear optimization and optimal control", Mathematical Programming
Computation 11(1), 1-36, 2019.
"""

from __future__ import annotations

from typing import Any

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
from c3bench.solvers.output import quiet_stdout
from c3bench.solvers.registry import register
from c3bench.solvers.timing import Stopwatch


class BonminMIQP(MIQPBackend):
    """Bonmin's B-BB (Bonami et al. 2008) through CasADi with the pairs as SOS1 groups."""

    name = "bonmin"
    package = "casadi"
    description = "MIQP reference: Bonmin B-BB via CasADi nlpsol, SOS1 groups"

    def require(self) -> None:
        """CasADi imports and has the ``bonmin`` nlpsol plugin."""
        casadi = require_module("casadi")
        if not casadi.has_nlpsol("bonmin"):
            raise BackendUnavailable("CasADi was built without the bonmin plugin")

    def solve(self, problem: Problem, settings: Settings,
              warm_start: WarmStart | None = None) -> Result:
        """Build the CasADi NLP with SOS1 groups, run Bonmin quietly, polish the answer."""
        import casadi

        watch = Stopwatch()
        with watch.lap("setup"):
            z = casadi.SX.sym("z", problem.n)
            P = casadi.DM(sparse.csc_matrix(problem.P))
            objective = 0.5 * casadi.dot(z, casadi.mtimes(P, z)) + casadi.dot(
                casadi.DM(problem.q), z) + problem.objective_offset
            rows: list[casadi.SX] = []
            lower: list[np.ndarray] = []
            upper: list[np.ndarray] = []
            if problem.A is not None and problem.b is not None:
                rows.append(casadi.mtimes(casadi.DM(sparse.csc_matrix(problem.A)), z))
                lower.append(problem.b)
                upper.append(problem.b)
            if problem.G is not None and problem.h is not None:
                rows.append(casadi.mtimes(casadi.DM(sparse.csc_matrix(problem.G)), z))
                lower.append(np.full(problem.n_ineq, -np.inf))
                upper.append(problem.h)
            g = casadi.vertcat(*rows) if rows else casadi.SX(0, 1)
            limit = solver_time_limit(settings, 0.0)
            options: dict[str, Any] = {
                "sos1_groups": [[int(i), int(j)] for i, j in pairs_of(problem)],
                "print_time": False,
                "bonmin.print_level": 0,
                "bonmin.bb_log_level": 0,
                "bonmin.nlp_log_level": 0,
                "bonmin.lp_log_level": 0,
                "bonmin.milp_log_level": 0,
                "bonmin.oa_log_level": 0,
                "bonmin.fp_log_level": 0,
                "bonmin.time_limit": limit,
                "bonmin.algorithm": "B-BB",
            }
            if settings.sets_tolerance:
                options["bonmin.allowable_fraction_gap"] = float(settings.tolerance)
                options["bonmin.allowable_gap"] = 0.0
                options["bonmin.integer_tolerance"] = float(max(settings.tolerance, 1e-9))
                options["bonmin.tol"] = float(max(settings.tolerance, 1e-10))
            if settings.max_iterations is not None:
                options["bonmin.node_limit"] = int(settings.max_iterations)
            for key, value in settings.options.items():
                if key.startswith("bonmin."):
                    options[key] = value
            solver = casadi.nlpsol("bonmin_miqp", "bonmin", {"x": z, "f": objective, "g": g},
                                   options)
            lb, ub = bounds(problem)
            arguments: dict[str, Any] = {"lbx": lb, "ubx": ub}
            if rows:
                arguments["lbg"] = np.concatenate(lower)
                arguments["ubg"] = np.concatenate(upper)
            if warm_start is not None and warm_start.x is not None:
                arguments["x0"] = np.asarray(warm_start.x, dtype=float)
        with watch.lap("solve"), quiet_stdout():  # Bonmin's node log ignores its log levels
            solution = solver(**arguments)
        stats = solver.stats()
        status = str(stats.get("return_status", "unknown"))
        point = np.asarray(solution["x"], dtype=float).ravel()
        x = point if np.all(np.isfinite(point)) else None
        success = bool(stats.get("success", False)) and status == "SUCCESS"
        failure = Failure.NONE if success else failure_category(status)
        return finish_point(self.name, problem, settings, x, success and x is not None,
                            f"bonmin: {status}", watch, {}, None, failure)


register(BonminMIQP())
