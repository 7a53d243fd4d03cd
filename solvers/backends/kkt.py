"""Direct KKT solvers of the equality-constrained QP families (``c3plus_qp``, ``c3_qp``).

For ``min 1/2 x^T P x + q^T x`` s.t. ``A x = b`` (no inequalities, no finite bounds):

* ``equilibrated_kkt``: the reference study's 11-step equilibrated Schur-complement method
  (:mod:`c3bench.solvers.equilibrated`, with ``Q = P / 2`` and ``c = q``), float64 or
  float32. ``settings.options`` may name a preset, ``{"ablation": "no_ruiz_schur"}`` (see
  :data:`c3bench.solvers.equilibrated.ABLATIONS`), and/or switch single steps,
  ``{"ridge": 0.0, "projection": False}`` (field names of
  :class:`c3bench.solvers.equilibrated.EquilibrationSteps`); unknown names are an error.
  ``{"diagnostics": False}`` skips the condition numbers (two SVDs, slower than the solve
  itself), e.g. inside a controller loop; the violations are still reported.
* ``kkt_ldl``: baseline, the full KKT system ``[[P, A^T], [A, 0]] [x; y] = [-q; b]`` solved
  by LAPACK's symmetric-indefinite ``?sysv`` (Bunch-Kaufman ``L D L^T``), no scaling.
* ``schur_plain``: baseline, the un-equilibrated Schur complement ``A P^-1 A^T`` with
  Cholesky: every step of the method switched off (no scaling, no ridge, no projection, no
  fallback); a failed Cholesky is a recorded failure.

These are direct methods: ``iterations`` is ``None`` (not an iterative solver; a count of 1
would make per-iteration aggregates meaningless next to ADMM and interior-point solvers).
Timing (the contract of :mod:`c3bench.solvers.timing`; ranked by ``setup + solve``, since an
ADMM controller refactorises each time ``rho`` changes): for the equilibrated methods
(``equilibrated_kkt*``, ``schur_plain``) ``setup_time`` is the conversion of the data
(``Q = P / 2``, the dtype cast) plus :meth:`EquilibratedKKT.factorize` (scaling, Schur
complement, Cholesky with its ridge retries) and ``solve_time`` the substitutions and the
projection (``diagnostics`` keep ``factorize_time`` and ``substitute_time`` apart); for
``kkt_ldl`` ``setup_time`` is assembling the KKT matrix and ``solve_time`` the one LAPACK
``?sysv`` call, which factorises and substitutes together (no split is exposed). Condition
numbers and violations are measured after the timed part, in float64 on the original data.
``y`` follows qpsolvers' sign: ``P x + q + A^T y = 0``.

References
----------
D. Ruiz, "A scaling algorithm to equilibrate both rows and columns norms in matrices",
Technical Report RAL-TR-2001-034, Rutherford Appleton Laboratory, 2001 (the equilibration).

J. R. Bunch and L. Kaufman, "Some stable methods for calculating inertia and solving
symmetric linear systems", Mathematics of Computation 31(137), 163-179, 1977 (``kkt_ldl``).

G. H. Golub and C. F. Van Loan, *Matrix Computations*, 4th ed., Johns Hopkins University
Press, 2013 (Cholesky and the Schur complement, ``schur_plain``).
"""

from __future__ import annotations

import time
import warnings
from typing import Any

import numpy as np
import scipy.linalg

from c3bench.problems.instance import Problem
from c3bench.problems.names import EQUALITY_QP_FAMILIES, Failure, Family, Precision
from c3bench.solvers.base import Backend, Result, Settings, WarmStart
from c3bench.solvers.equilibrated import (
    ABLATIONS,
    EquilibratedKKT,
    EquilibrationSteps,
    condition_number,
    diagnose,
    raw_schur,
)
from c3bench.solvers.registry import register
from c3bench.solvers.timing import Stopwatch


def steps_from_options(options: dict[str, Any]) -> EquilibrationSteps:
    """The ablation switches named in ``settings.options`` (default: the full method).

    ``options["ablation"]`` picks a preset of :data:`ABLATIONS`; other keys are field names of
    :class:`EquilibrationSteps` and override it.
    """
    options = dict(options)
    options.pop("diagnostics", None)
    preset = options.pop("ablation", "full")
    if preset not in ABLATIONS:
        raise ValueError(f"unknown ablation {preset!r}; known: {', '.join(ABLATIONS)}")
    return ABLATIONS[preset].with_options(options)


def equality_only(problem: Problem) -> tuple[bool, str]:
    """Whether ``problem`` has equalities only (no ``G``, no finite bound), with the reason."""
    if problem.A is None or problem.n_eq == 0:
        return False, "needs equality constraints A x = b"
    if problem.G is not None and problem.n_ineq > 0:
        return False, f"takes equality constraints only; problem has {problem.n_ineq} " \
                      "inequality rows (G x <= h)"
    if problem.n_bounded > 0:
        return False, f"takes equality constraints only; problem has {problem.n_bounded} " \
                      "variables with finite bounds"
    return True, ""


class _EqualityQPBackend(Backend):
    """Shared family and structure checks."""

    families: tuple[Family, ...] = EQUALITY_QP_FAMILIES
    package = ""  # numpy / scipy only
    precisions: tuple[Precision, ...] = (Precision.FLOAT64, Precision.FLOAT32)

    def accepts(self, problem: Problem) -> tuple[bool, str]:
        """The equality-QP families with equalities only (:func:`equality_only`)."""
        ok, reason = super().accepts(problem)
        if not ok:
            return ok, reason
        ok, reason = equality_only(problem)
        return ok, (f"{self.name} {reason}" if reason else "")


class EquilibratedKKTBackend(_EqualityQPBackend):
    """The reference study's equilibrated Schur-complement method, with ablation switches."""

    name = "equilibrated_kkt"
    description = ("the reference study's equilibrated Schur-complement KKT solve (row "
                   "scaling, Ruiz on Q and S, ridge, projection); float32/float64; ablations "
                   "via options")
    steps_override: EquilibrationSteps | None = None

    def steps(self, settings: Settings) -> EquilibrationSteps:
        """The ablation switches of this backend for ``settings.options``."""
        if self.steps_override is not None:
            options = {k: v for k, v in settings.options.items() if k != "diagnostics"}
            return self.steps_override.with_options(options) if options \
                else self.steps_override
        return steps_from_options(settings.options)

    def solve(self, problem: Problem, settings: Settings,
              warm_start: WarmStart | None = None) -> Result:
        """Factorise and solve in ``settings.precision``; diagnostics in float64 after."""
        try:
            steps = self.steps(settings)
        except ValueError as error:
            return Result.failed(self.name, problem.name, Failure.INVALID_INPUT,
                                 f"bad options: {error}")
        watch = Stopwatch()
        dtype = settings.dtype
        assert problem.A is not None and problem.b is not None
        with watch.lap("setup"):
            Q = (problem.P * 0.5).astype(dtype)
            c = problem.q.astype(dtype)
            A = problem.A.astype(dtype)
            b = problem.b.astype(dtype)
        try:
            with watch.lap("factorize"):
                kkt = EquilibratedKKT.factorize(Q, A, steps, settings.precision)
            with watch.lap("substitute"):
                x, y, x_unprojected = kkt.solve(c, b)
        except (ValueError, np.linalg.LinAlgError) as error:
            return Result.failed(self.name, problem.name, Failure.ERROR, str(error),
                                 setup_time=watch.get("setup") + watch.get("factorize"),
                                 solve_time=watch.get("substitute"))
        x64 = x.astype(np.float64)
        found = diagnose(kkt, problem.P * 0.5, problem.A, problem.b, x64,
                         x_unprojected.astype(np.float64),
                         conditioning=bool(settings.options.get("diagnostics", True)))
        diagnostics = found.as_dict()
        diagnostics["factorize_time"] = watch.get("factorize")
        diagnostics["substitute_time"] = watch.get("substitute")
        status = "solved" if kkt.fallbacks == 0 else \
            f"solved (Cholesky of S needed {kkt.fallbacks} ridge increase(s))"
        return Result(solver=self.name, problem=problem.name, found=True, status=status,
                      x=x64, y=y.astype(np.float64), iterations=None,
                      setup_time=watch.get("setup") + watch.get("factorize"),
                      solve_time=watch.get("substitute"),
                      diagnostics=diagnostics)


class EquilibratedNoRidgeBackend(EquilibratedKKTBackend):
    """The reference study's method without the ridge (step 7): exact on well-posed instances.

    With the reference study's relative ridge of 1e-4 the answer is feasible (thanks to the
    projection) but not optimal, because after Ruiz the smallest eigenvalues of ``S`` are 1e-5 to
    1e-6; this variant shows what the ridge costs in accuracy and buys in robustness.
    """

    name = "equilibrated_kkt_noridge"
    description = "the reference study's equilibrated method with the ridge (step 7) switched off"
    steps_override = ABLATIONS["no_ridge"]


class SchurPlainBackend(EquilibratedKKTBackend):
    """Baseline: ``A P^-1 A^T`` with Cholesky, nothing else (every step switched off)."""

    name = "schur_plain"
    description = "un-equilibrated Schur complement with Cholesky (no scaling, ridge, projection)"
    steps_override = EquilibrationSteps.none()

    def solve(self, problem: Problem, settings: Settings,
              warm_start: WarmStart | None = None) -> Result:
        """The plain Schur solve; only the raw condition number is reported."""
        result = super().solve(problem, settings, warm_start)
        # only the raw condition number is meaningful without equilibration
        keep = ("cond_schur_raw", "violation_before_projection",
                "mean_violation_before_projection", "factorize_time", "substitute_time")
        result.diagnostics = {key: value for key, value in result.diagnostics.items()
                              if key in keep}
        if result.found:
            result.status = "solved"
        return result


class KKTLDLBackend(_EqualityQPBackend):
    """Baseline: the full KKT matrix, symmetric-indefinite LAPACK solve, no scaling."""

    name = "kkt_ldl"
    description = "full KKT [[P, A^T], [A, 0]] by symmetric-indefinite LDL^T (LAPACK sysv)"

    def solve(self, problem: Problem, settings: Settings,
              warm_start: WarmStart | None = None) -> Result:
        """Assemble ``[[P, A^T], [A, 0]]`` and solve it by LAPACK's ``?sysv``."""
        watch = Stopwatch()
        dtype = settings.dtype
        assert problem.A is not None and problem.b is not None
        n, m = problem.n, problem.n_eq
        with watch.lap("setup"):
            K = np.zeros((n + m, n + m), dtype=dtype)
            K[:n, :n] = problem.P
            K[:n, n:] = problem.A.T
            K[n:, :n] = problem.A
            rhs = np.concatenate([-problem.q, problem.b]).astype(dtype)
        start = time.perf_counter()
        ill_conditioned = False
        try:
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always", scipy.linalg.LinAlgWarning)
                solution = scipy.linalg.solve(K, rhs, assume_a="sym", check_finite=False)
            ill_conditioned = any(issubclass(w.category, scipy.linalg.LinAlgWarning)
                                  for w in caught)
        except (np.linalg.LinAlgError, ValueError) as error:
            return Result.failed(self.name, problem.name, Failure.ERROR,
                                 f"KKT matrix is singular: {error}",
                                 setup_time=watch.get("setup"),
                                 solve_time=time.perf_counter() - start)
        solve_time = time.perf_counter() - start
        x = solution[:n].astype(np.float64)
        y = solution[n:].astype(np.float64)
        residual = np.abs(problem.A @ x - problem.b)
        conditioning = bool(settings.options.get("diagnostics", True))
        diagnostics = {
            "cond_kkt": condition_number(K) if conditioning else float("nan"),
            "cond_schur_raw": (condition_number(raw_schur(problem.P * 0.5, problem.A))
                               if conditioning else float("nan")),
            "kkt_ill_conditioned": float(ill_conditioned),
            "violation_before_projection": float(residual.max(initial=0.0)),
            "mean_violation_before_projection": float(residual.mean()) if m else 0.0,
        }
        status = "solved" if not ill_conditioned else \
            "solved (LAPACK warns: KKT matrix ill-conditioned)"
        return Result(solver=self.name, problem=problem.name, found=True, status=status,
                      x=x, y=y, iterations=None, setup_time=watch.get("setup"),
                      solve_time=solve_time, diagnostics=diagnostics)


register(EquilibratedKKTBackend())
register(EquilibratedNoRidgeBackend())
register(KKTLDLBackend())
register(SchurPlainBackend())
