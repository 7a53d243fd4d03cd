"""``proxqp_dense``, ``proxqp_sparse``: ProxQP (proxsuite), a proximal augmented Lagrangian.

The problem goes to ProxQP as equalities ``A z = b`` and two-sided rows
``l <= [G; I_S] z <= u`` (the ``C`` matrix; bounds as rows, :class:`TwoSidedForm`), dense
(``proxqp.dense``) or sparse (``proxqp.sparse``). The multipliers ``y`` of ``A`` and ``z`` of
``C`` have qpsolvers' signs and split into ``y``, ``z`` and ``z_box``.

Options: ``verbose`` off; in non-default profiles ``eps_abs = tolerance``, ``eps_rel = 0`` and
the duality gap checked with ``eps_duality_gap_abs = tolerance`` (``_rel = 0``); ``max_iter``
from ``settings.max_iterations``; ``settings.options`` last (attributes of ``qp.settings``).
ProxQP takes no time limit here: the registry enforces it. A warm start sets ``x``, ``y`` and
``z`` (``InitialGuess.WARM_START``).

Timing (the contract of :mod:`c3bench.solvers.timing`; rankings use setup + solve): setup is
the two-sided form, the model construction and ``qp.init`` (storing and equilibrating the
matrices); solve is ``qp.solve`` (the proximal iterations with their factorisations, which
ProxQP performs inside ``solve``). A fresh model per call: a cold cell is cold.

Warm cells (:class:`~c3bench.solvers.timing.UpdatableBackend`): the model is initialised
untimed on the instance; the setup lap is ``qp.update(g=, b=, l=, u=)`` with the instance's
vectors (matrices and preconditioner kept), the solve lap ``qp.solve(x, y, z)`` from the
initial guess (``InitialGuess.WARM_START``).

References
----------
A. Bambade, S. El-Kazdadi, A. Taylor and J. Carpentier, "PROX-QP: Yet another Quadratic
Programming Solver for Robotics and beyond", Robotics: Science and Systems (RSS), 2022.
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


class ProxQPBackend(QPBackend):
    """ProxQP (Bambade et al. 2022) with ``l <= [G; I_S] z <= u`` as ``C`` rows."""

    package = "proxsuite"
    warm_support = ("ProxQP update(g=, b=, l=, u=) of the model initialised on the same "
                    "matrices, then solve(x, y, z) from the initial guess (WARM_START)")

    def __init__(self, sparse: bool) -> None:
        self.sparse = sparse
        self.name = "proxqp_sparse" if sparse else "proxqp_dense"
        self.description = (f"ProxQP proximal augmented Lagrangian (proxsuite, "
                            f"{'sparse' if sparse else 'dense'} backend)")

    def configure(self, qp: Any, settings: Settings) -> None:
        """Set ProxQP's options for the profile on ``qp.settings`` (module docstring)."""
        qp.settings.verbose = False
        if settings.sets_tolerance:
            qp.settings.eps_abs = settings.tolerance
            qp.settings.eps_rel = 0.0
            qp.settings.check_duality_gap = True
            qp.settings.eps_duality_gap_abs = settings.tolerance
            qp.settings.eps_duality_gap_rel = 0.0
        if settings.max_iterations is not None:
            qp.settings.max_iter = int(settings.max_iterations)
        for key, value in settings.options.items():
            setattr(qp.settings, key, value)

    def _init(self, problem: Problem, settings: Settings, warm: bool) -> tuple[Any, TwoSidedForm]:
        """A ProxQP model initialised on ``problem`` (``warm``: it will be given a guess)."""
        from proxsuite import proxqp

        form = TwoSidedForm.from_problem(problem, dense=not self.sparse)
        eq, ineq = form.rows("eq"), form.rows("ineq")
        n_in = form.n_rows - form.n_eq
        module = proxqp.sparse if self.sparse else proxqp.dense
        qp = module.QP(form.n, form.n_eq, n_in)
        self.configure(qp, settings)
        if self.sparse:
            H: Any = sp.csc_matrix(problem.P)
            A_eq: Any = form.matrix[eq]
            C: Any = form.matrix[ineq]
        else:
            H, A_eq, C = problem.P, form.matrix[eq], form.matrix[ineq]
        if warm:
            qp.settings.initial_guess = proxqp.InitialGuess.WARM_START
        qp.init(H, problem.q, A_eq if form.n_eq else None,
                form.lower[eq] if form.n_eq else None, C if n_in else None,
                form.lower[ineq] if n_in else None, form.upper[ineq] if n_in else None)
        return qp, form

    @staticmethod
    def _solve(qp: Any, form: TwoSidedForm, warm_start: WarmStart | None) -> None:
        """``qp.solve``, from the initial guess when one is given."""
        if warm_start is not None and warm_start.x is not None:
            stacked = form.stack_duals(warm_start.y, warm_start.z, warm_start.z_box)
            qp.solve(np.asarray(warm_start.x, dtype=float), stacked[form.rows("eq")],
                     stacked[form.rows("ineq")])
        else:
            qp.solve()

    def solve(self, problem: Problem, settings: Settings,
              warm_start: WarmStart | None = None) -> Result:
        """Initialise a dense or sparse ProxQP model and solve it once."""
        watch = Stopwatch()
        with watch.lap(SETUP):
            qp, form = self._init(problem, settings,
                                  warm_start is not None and warm_start.x is not None)
        with watch.lap(SOLVE):
            self._solve(qp, form, warm_start)
        return self._result(problem, watch, qp, form)

    def prepare(self, problem: Problem, settings: Settings) -> tuple[Any, TwoSidedForm]:
        """The model initialised on ``problem``, set to start from a guess (untimed in a
        warm cell)."""
        return self._init(problem, settings, warm=True)

    def resolve(self, prepared: tuple[Any, TwoSidedForm], problem: Problem,
                settings: Settings, warm_start: WarmStart | None) -> Result:
        """``qp.update`` with the vectors (setup lap), ``qp.solve`` from the guess (solve
        lap)."""
        qp, form = prepared
        eq, ineq = form.rows("eq"), form.rows("ineq")
        watch = Stopwatch()
        with watch.lap(SETUP):
            lower, upper = two_sided_vectors(form, problem)
            vectors: dict[str, Any] = {"g": np.asarray(problem.q, dtype=float)}
            if form.n_eq:
                vectors["b"] = lower[eq]
            if form.n_rows > form.n_eq:
                vectors.update(l=lower[ineq], u=upper[ineq])
            qp.update(**vectors)
        with watch.lap(SOLVE):
            self._solve(qp, form, warm_start)
        return self._result(problem, watch, qp, form)

    def _result(self, problem: Problem, watch: Stopwatch, qp: Any,
                form: TwoSidedForm) -> Result:
        """The :class:`Result` of one ProxQP solve."""
        from proxsuite import proxqp

        results = qp.results
        info = results.info
        status = str(info.status).split(".")[-1]
        found = info.status == proxqp.QPSolverOutput.PROXQP_SOLVED
        duals = form.split_duals(np.concatenate([np.asarray(results.y).ravel(),
                                                 np.asarray(results.z).ravel()]))
        return qp_result(self.name, problem, watch, found=found, status=status,
                         failure=failure_category(status), x=results.x,
                         duals=duals, iterations=info.iter,
                         diagnostics={"solver_primal_residual": float(info.pri_res),
                                      "solver_dual_residual": float(info.dua_res)})

register(ProxQPBackend(sparse=False))
register(ProxQPBackend(sparse=True))
