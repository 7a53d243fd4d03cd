"""Lemke and projected Gauss-Seidel backends for the ``lcp`` and ``lcp_general`` families.

An ``lcp`` instance is the QP ``min 1/2 lam^T F lam + q^T lam`` s.t. ``lam >= 0`` (``P = F``
symmetric PSD, ``lb = 0``, no ``ub``, no ``A``, no ``G``); its KKT conditions are
``LCP(M = P, q)``: ``lam >= 0``, ``w = P lam + q >= 0``, ``lam^T w = 0``. An ``lcp_general``
instance is ``LCP(M = data["F"], q = h)`` for any square ``F`` (stored as is,
:func:`c3bench.problems.families.lcp_general`); both methods read ``M`` and ``q`` through
:func:`c3bench.problems.instance.lcp_data`.

Result conventions (qpsolvers): ``x = lam`` and the box dual ``z_box = min(-(M x + q), 0)``.
The lower-bound dual must be ``<= 0``; at an exact solution ``w >= 0`` and the clip changes
nothing. Clipping keeps the multiplier sign-feasible, so a violation ``w_i < 0`` shows up in the
dual residual ``||P x + q + z_box|| = ||min(w, 0)||`` instead of being hidden by a wrong-signed
dual; ``lam^T w`` shows up in the duality gap. An ``lcp_general`` result carries no duals
(its stored objective is 0; the natural residual is the LCP's certificate).
``diagnostics["natural_residual"]`` is ``||min(lam, w)||_inf``.

* ``lemke``: complementary pivoting (:func:`c3bench.solvers.lcp.lemke`; Lemke 1965);
  ``iterations`` = pivots. A terminal basis is checked before it is claimed: unless
  ``||min(lam, w)||_inf <= 1e-9 max(1, ||P lam||, ||q||)`` (so ``lam >= 0`` and ``w >= 0``
  up to that tolerance) the result is ``found=False``, ``Failure.ERROR``, status
  ``"check failed: ..."`` with the point as ``x``. An LCP without a solution is never
  reported solved (its status is then a secondary ray or a failed check).
* ``pgs``: projected Gauss-Seidel (:func:`c3bench.solvers.lcp.projected_gauss_seidel`; Cottle,
  Pang and Stone 1992); stops when the
  natural residual ``||min(lam, w)||_inf`` *and* the gap ``|lam^T w|`` are both below
  ``settings.tolerance`` (or ``options["tol"]``): the natural residual alone let the gap stay
  ten times above the tolerance on the default suite, so when it is not met the sweeps go on
  from the same iterate with a tighter natural-residual target. At most
  ``settings.max_iterations`` sweeps in all (default 10 000); ``iterations`` = sweeps; the
  natural residual after every sweep is in ``trace["natural_residual"]``. A warm start's
  ``x`` is the initial iterate. PGS converges for symmetric PSD ``M`` with a positive
  diagonal; on a non-symmetric ``F`` (``lcp_general``) it may diverge or cycle, and that is
  reported as a failure (a non-finite iterate or the sweep limit), never as a solution; a zero
  diagonal entry (Stewart-Trinkle's slack rows) fails at once.

Timing (the contract of :mod:`c3bench.solvers.timing`; rankings use setup + solve): setup is
copying ``M`` and ``q`` to float64 arrays; solve is the pivoting (Lemke) or the sweeps (PGS),
which factorise nothing ahead.

References
----------
C. E. Lemke, "Bimatrix equilibrium points and mathematical programming", Management Science
11(7), 681-689, 1965.

R. W. Cottle, J.-S. Pang and R. E. Stone, *The Linear Complementarity Problem*, Academic
Press, 1992 (projected Gauss-Seidel / SOR, chapter 5).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from c3bench.problems.instance import Problem, lcp_data
from c3bench.problems.names import Failure, Family, Precision
from c3bench.solvers.base import Backend, Result, Settings, WarmStart
from c3bench.solvers.lcp import LCPSolution, lemke, projected_gauss_seidel
from c3bench.solvers.registry import register
from c3bench.solvers.residuals import natural_residual
from c3bench.solvers.timing import Stopwatch

PGS_DEFAULT_MAX_SWEEPS = 10_000


def lcp_form(problem: Problem) -> tuple[bool, str]:
    """Whether ``problem`` is ``min 1/2 x P x + q x s.t. x >= 0`` exactly, with the reason.

    An ``lcp_general`` instance always is an LCP: its form is checked when it is built
    (:class:`~c3bench.problems.instance.Problem` validates it)."""
    if problem.family == Family.LCP_GENERAL:
        return True, ""
    if problem.A is not None and problem.n_eq > 0:
        return False, "an LCP backend takes no equality constraints"
    if problem.G is not None and problem.n_ineq > 0:
        return False, "an LCP backend takes no inequality constraints"
    if problem.lb is None or not np.all(problem.lb == 0.0):
        return False, "an LCP backend needs the lower bound lb = 0 on every variable"
    if problem.ub is not None and np.any(np.isfinite(problem.ub)):
        return False, "an LCP backend takes no finite upper bounds"
    return True, ""


class _LCPBackend(Backend):
    """Shared conversion: ``LCP(P, q)`` from the instance, the result's box duals."""

    families = (Family.LCP, Family.LCP_GENERAL)
    package = ""  # our own code (numpy)
    precisions = (Precision.FLOAT64,)

    def accepts(self, problem: Problem) -> tuple[bool, str]:
        """The ``lcp`` family in the exact form ``x >= 0`` (:func:`lcp_form`), and
        ``lcp_general``."""
        ok, reason = super().accepts(problem)
        if not ok:
            return ok, reason
        return lcp_form(problem)

    def _run(self, M: np.ndarray, q: np.ndarray, settings: Settings,
             warm_start: WarmStart | None) -> LCPSolution:
        """The method itself on ``LCP(M, q)``."""
        raise NotImplementedError

    def solve(self, problem: Problem, settings: Settings,
              warm_start: WarmStart | None = None) -> Result:
        """Run the method; an unsolved LCP is ``Failure.ERROR`` with the last iterate."""
        watch = Stopwatch()
        with watch.lap("setup"):
            M, q = lcp_data(problem, copy=True)
        with watch.lap("solve"):
            outcome = self._run(M, q, settings, warm_start)
        trace: dict[str, list[float]] = {}
        if outcome.residuals:
            trace["natural_residual"] = [float(r) for r in outcome.residuals]
        common: dict[str, Any] = {"iterations": outcome.iterations,
                                  "setup_time": watch.get("setup"),
                                  "solve_time": watch.get("solve"), "trace": trace}
        if not outcome.found or outcome.z is None:
            last = None if outcome.z is None else np.asarray(outcome.z, dtype=np.float64)
            return Result.failed(self.name, problem.name, Failure.ERROR, outcome.status, x=last,
                                 **common)
        x = np.asarray(outcome.z, dtype=np.float64)
        w = M @ x + q
        duals = None if problem.family == Family.LCP_GENERAL else np.minimum(-w, 0.0)
        return Result(solver=self.name, problem=problem.name, found=True,
                      status=outcome.status, x=x, z_box=duals,
                      diagnostics={"natural_residual": natural_residual(M, q, x)}, **common)


class LemkeBackend(_LCPBackend):
    """Lemke's complementary pivoting method (Lemke 1965)."""

    name = "lemke"
    description = "Lemke's complementary pivoting (covering vector e = 1) on LCP(F, q)"

    def _run(self, M: np.ndarray, q: np.ndarray, settings: Settings,
             warm_start: WarmStart | None) -> LCPSolution:
        max_pivots = settings.max_iterations
        return lemke(M, q, max_pivots=max_pivots)


class PGSBackend(_LCPBackend):
    """Projected Gauss-Seidel sweeps (Cottle, Pang and Stone 1992)."""

    name = "pgs"
    description = "projected Gauss-Seidel on LCP(F, q); stops on the natural residual and lam^T w"

    def _run(self, M: np.ndarray, q: np.ndarray, settings: Settings,
             warm_start: WarmStart | None) -> LCPSolution:
        tol = float(settings.options.get("tol", settings.tolerance))
        sweeps = settings.max_iterations or PGS_DEFAULT_MAX_SWEEPS
        z = None if warm_start is None or warm_start.x is None else warm_start.x
        target = tol
        done = 0
        residuals: list[float] = []
        while True:
            outcome = projected_gauss_seidel(M, q, tol=target, max_iterations=sweeps - done,
                                             z0=z)
            done += outcome.iterations
            residuals += outcome.residuals
            if not outcome.found or outcome.z is None:
                return LCPSolution(outcome.z, False, outcome.status, done, residuals)
            z = outcome.z
            gap = abs(float(z @ (M @ z + q)))
            if gap <= tol:
                return LCPSolution(z, True, outcome.status, done, residuals)
            if done >= sweeps:
                return LCPSolution(z, False, f"iteration limit {sweeps} reached with "
                                   f"lam^T w = {gap:.3g} > {tol:g}", done, residuals)
            # natural residual small but lam^T w (the duality gap) not yet: tighten
            target = max(target * min(0.1, 0.5 * tol / gap), 1e-300)


register(LemkeBackend())
register(PGSBackend())
