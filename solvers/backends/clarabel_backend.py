"""``clarabel``: Clarabel's interior-point method on the cone form.

The problem goes to Clarabel as ``[A; G; I_U; -I_L] z + s = r`` with ``s`` in the zero cone
(equalities) times the nonnegative orthant (:class:`ConeForm`); the cone dual splits into
``y = d_eq``, ``z = d_G`` and ``z_box = d_U - d_L``.

Options: ``verbose`` off and ``time_limit`` always; in non-default profiles
``tol_feas = tol_gap_abs = tol_gap_rel = tolerance`` and ``tol_ktratio = min(100 tolerance,
0.1)`` (Clarabel's default ratio of 1e-6 to 1e-8); ``max_iter`` from
``settings.max_iterations``; ``settings.options`` last (set as attributes of Clarabel's
``DefaultSettings``). ``found`` only for ``Solved`` (``AlmostSolved`` is not found);
``diagnostics`` carry Clarabel's own primal and dual residuals.

Timing (the contract of :mod:`c3bench.solvers.timing`; rankings use setup + solve): setup is
the cone form (stacking, CSC conversion), the settings object and
``clarabel.DefaultSolver(...)`` (equilibration, KKT assembly, symbolic factorisation); solve is
``solver.solve()``: the interior-point iterations, each with its numeric KKT factorisation (the
matrix changes every iteration, so no factorisation can move ahead of them). A fresh solver per
call: no state survives between solves.

Warm cells (:class:`~c3bench.solvers.timing.UpdatableBackend`): the solver is constructed
untimed on the instance; the setup lap is ``solver.update(q=, b=)`` with the instance's
vectors (Clarabel >= 0.7 keeps the matrices, their equilibration and symbolic factorisation),
the solve lap ``solver.solve()``. Clarabel takes no initial guess: its interior point restarts
from its own central point, so the guess is unused (only the construction is saved).

References
----------
P. J. Goulart and Y. Chen, "Clarabel: An interior-point solver for conic programs with
quadratic objectives", arXiv:2405.12762, 2024.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import scipy.sparse as sp

from c3bench.problems.instance import Problem
from c3bench.solvers.backends._qp_forms import ConeForm, QPBackend, failure_category, qp_result
from c3bench.solvers.backends._warm_vectors import cone_rhs
from c3bench.solvers.base import Result, Settings, WarmStart
from c3bench.solvers.registry import register
from c3bench.solvers.timing import SETUP, SOLVE, Stopwatch


class ClarabelBackend(QPBackend):
    """Clarabel interior point (Goulart and Chen 2024) on ``[A; G; I_U; -I_L] z + s = r``."""

    name = "clarabel"
    package = "clarabel"
    description = "Clarabel interior point (direct API, zero and nonnegative cones)"
    warm_support = ("Clarabel update(q=, b=) of the solver built on the same matrices; no "
                    "initial guess (the interior point restarts from its central point)")

    def settings_object(self, settings: Settings) -> Any:
        """Clarabel ``DefaultSettings`` for the profile (module docstring)."""
        import clarabel

        options = clarabel.DefaultSettings()
        options.verbose = False
        options.time_limit = float(settings.time_limit)
        if settings.sets_tolerance:
            tolerance = settings.tolerance
            options.tol_feas = tolerance
            options.tol_gap_abs = tolerance
            options.tol_gap_rel = tolerance
            options.tol_ktratio = min(100.0 * tolerance, 1e-1)
        if settings.max_iterations is not None:
            options.max_iter = int(settings.max_iterations)
        for key, value in settings.options.items():
            setattr(options, key, value)
        return options

    def _build(self, problem: Problem, settings: Settings) -> tuple[Any, ConeForm]:
        """A Clarabel solver constructed on ``problem`` (cones, equilibration, symbolic
        factorisation)."""
        import clarabel

        form = ConeForm.from_problem(problem)
        cones = []
        if form.n_eq:
            cones.append(clarabel.ZeroConeT(form.n_eq))
        if form.n_nonnegative:
            cones.append(clarabel.NonnegativeConeT(form.n_nonnegative))
        solver = clarabel.DefaultSolver(sp.triu(sp.csc_matrix(problem.P), format="csc"),
                                        problem.q, form.matrix, form.rhs, cones,
                                        self.settings_object(settings))
        return solver, form

    def solve(self, problem: Problem, settings: Settings,
              warm_start: WarmStart | None = None) -> Result:
        """Build the cones and solve once (Clarabel takes no warm start)."""
        watch = Stopwatch()
        with watch.lap(SETUP):
            solver, form = self._build(problem, settings)
        with watch.lap(SOLVE):
            solution = solver.solve()
        return self._result(problem, watch, form, solution)

    def prepare(self, problem: Problem, settings: Settings) -> tuple[Any, ConeForm]:
        """The solver constructed on ``problem`` (untimed in a warm cell)."""
        return self._build(problem, settings)

    def resolve(self, prepared: tuple[Any, ConeForm], problem: Problem, settings: Settings,
                warm_start: WarmStart | None) -> Result:
        """``solver.update(q=, b=)`` (setup lap), ``solver.solve()`` (solve lap); the
        initial guess is unused (Clarabel takes none)."""
        solver, form = prepared
        watch = Stopwatch()
        with watch.lap(SETUP):
            solver.update(q=np.asarray(problem.q, dtype=float), b=cone_rhs(form, problem))
        with watch.lap(SOLVE):
            solution = solver.solve()
        return self._result(problem, watch, form, solution)

    def _result(self, problem: Problem, watch: Stopwatch, form: ConeForm,
                solution: Any) -> Result:
        """The :class:`Result` of one Clarabel solve."""
        import clarabel

        status = str(solution.status)
        found = solution.status == clarabel.SolverStatus.Solved
        return qp_result(self.name, problem, watch, found=found, status=status,
                         failure=failure_category(status), x=solution.x,
                         duals=form.split_duals(np.asarray(solution.z)),
                         iterations=solution.iterations,
                         diagnostics={"solver_primal_residual": float(solution.r_prim),
                                      "solver_dual_residual": float(solution.r_dual)})

register(ClarabelBackend())
