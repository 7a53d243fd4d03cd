"""``osqp``: OSQP, the operator-splitting (ADMM) QP solver, on the two-sided form.

The problem goes to OSQP as ``l <= [A; G; I_S] z <= u`` (:class:`TwoSidedForm`) with the upper
triangle of ``P`` in CSC; OSQP's row multiplier has qpsolvers' signs, so it is split row block
by row block into ``y``, ``z`` and ``z_box``.

Options: ``verbose`` off and ``time_limit`` always; in non-default profiles
``eps_abs = eps_rel = tolerance`` with ``polishing`` off; ``max_iter`` from
``settings.max_iterations``; ``settings.options`` last, so they win. A warm start sets ``x``
and the stacked row multiplier. ``found`` only for status "solved" ("solved inaccurate" is
not found); ``diagnostics`` carry OSQP's own primal and dual residuals.

Timing (the contract of :mod:`c3bench.solvers.timing`; rankings use setup + solve): setup is
the two-sided form, ``OSQP.setup`` (scaling and the KKT factorisation of the default direct
linear-system solver) and the warm start; solve is ``solve()``: the ADMM iterations (and a
polish where enabled). A fresh solver per call: a cold cell is cold.

Warm cells (:class:`~c3bench.solvers.timing.UpdatableBackend`): the object is set up untimed
on the instance; the setup lap is ``update(q=, l=, u=)`` with the instance's vectors and
``warm_start(x=, y=)`` from the initial guess, the solve lap ``solve()``.

References
----------
B. Stellato, G. Banjac, P. Goulart, A. Bemporad and S. Boyd, "OSQP: an operator splitting
solver for quadratic programs", Mathematical Programming Computation 12(4), 637-672, 2020.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import scipy.sparse as sp

from c3bench.problems.instance import Problem
from c3bench.solvers.backends._qp_forms import (
    QPBackend,
    TwoSidedForm,
    failure_category,
    qp_result,
)
from c3bench.solvers.backends._warm_vectors import two_sided_vectors
from c3bench.solvers.base import Result, Settings, WarmStart
from c3bench.solvers.registry import register
from c3bench.solvers.timing import SETUP, SOLVE, Stopwatch


class OSQPBackend(QPBackend):
    """OSQP 1.x (ADMM; Stellato et al. 2020) on ``l <= [A; G; I_S] z <= u``, sparse CSC."""

    name = "osqp"
    package = "osqp"
    description = "OSQP operator-splitting ADMM (osqp 1.x, sparse)"
    warm_support = ("OSQP update(q=, l=, u=) of the object set up on the same matrices, "
                    "then warm_start(x=, y=) from the initial guess")

    def options(self, settings: Settings) -> dict[str, Any]:
        """OSQP settings for the profile (module docstring)."""
        options: dict[str, Any] = {"verbose": False, "time_limit": settings.time_limit}
        if settings.sets_tolerance:
            options.update(eps_abs=settings.tolerance, eps_rel=settings.tolerance,
                           polishing=False)
        if settings.max_iterations is not None:
            options["max_iter"] = int(settings.max_iterations)
        options.update(settings.options)
        return options

    def _setup(self, problem: Problem, settings: Settings) -> tuple[Any, TwoSidedForm]:
        """A fresh OSQP object set up on ``problem`` (the form, scaling, KKT factorisation)."""
        import osqp

        form = TwoSidedForm.from_problem(problem)
        solver = osqp.OSQP()
        solver.setup(sp.triu(sp.csc_matrix(problem.P), format="csc"), problem.q,
                     form.matrix, form.lower, form.upper, **self.options(settings))
        return solver, form

    @staticmethod
    def _warm(solver: Any, form: TwoSidedForm, warm_start: WarmStart | None) -> None:
        """Set OSQP's iterate from the initial guess (``x`` and the stacked multiplier)."""
        if warm_start is not None and warm_start.x is not None:
            solver.warm_start(x=np.asarray(warm_start.x, dtype=float),
                              y=form.stack_duals(warm_start.y, warm_start.z, warm_start.z_box))

    def solve(self, problem: Problem, settings: Settings,
              warm_start: WarmStart | None = None) -> Result:
        """Set up and solve one OSQP problem; the solver's status decides ``found``."""
        watch = Stopwatch()
        with watch.lap(SETUP):
            solver, form = self._setup(problem, settings)
            self._warm(solver, form, warm_start)
        with watch.lap(SOLVE):
            output = solver.solve(raise_error=False)
        return self._result(problem, watch, form, output)

    def prepare(self, problem: Problem, settings: Settings) -> tuple[Any, TwoSidedForm]:
        """The OSQP object set up on ``problem`` (untimed in a warm cell)."""
        return self._setup(problem, settings)

    def resolve(self, prepared: tuple[Any, TwoSidedForm], problem: Problem,
                settings: Settings, warm_start: WarmStart | None) -> Result:
        """``update(q=, l=, u=)`` + ``warm_start`` (setup lap), ``solve()`` (solve lap)."""
        solver, form = prepared
        watch = Stopwatch()
        with watch.lap(SETUP):
            lower, upper = two_sided_vectors(form, problem)
            solver.update(q=np.asarray(problem.q, dtype=float), l=lower, u=upper)
            self._warm(solver, form, warm_start)
        with watch.lap(SOLVE):
            output = solver.solve(raise_error=False)
        return self._result(problem, watch, form, output)

    def _result(self, problem: Problem, watch: Stopwatch, form: TwoSidedForm,
                output: Any) -> Result:
        """The :class:`Result` of one OSQP solve."""
        import osqp

        info = output.info
        status = str(info.status)
        found = info.status_val == osqp.SolverStatus.OSQP_SOLVED
        duals = form.split_duals(output.y) if output.y is not None else None
        return qp_result(self.name, problem, watch, found=found, status=status,
                         failure=failure_category(status), x=output.x, duals=duals,
                         iterations=info.iter,
                         diagnostics={"solver_primal_residual": float(info.prim_res),
                                      "solver_dual_residual": float(info.dual_res)})

register(OSQPBackend())
