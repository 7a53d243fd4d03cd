"""``scip_lcp``: an ``lcp_general`` instance as a mixed-integer program, solved by SCIP.

``LCP(F, q)``: find ``lam >= 0`` with ``w = F lam + q >= 0`` and ``lam^T w = 0``. With one
binary ``b_i`` per pair (Hu, Mitchell, Pang, Bennett and Kunapuli 2008)::

    w = F lam + q,   0 <= lam_i <= M_lam b_i,   0 <= w_i <= M_w (1 - b_i),   b_i in {0, 1},

a point of which solves the LCP exactly when ``M_lam`` and ``M_w`` bound some solution. The
program has no objective (a feasibility problem; SCIP stops at its first solution,
``limits/solutions = 1``), so any solution of the LCP is an answer: the LCP's solution need not
be unique, and the family has no objective (it stores 0).

The constants (:func:`big_m`) are derived, never guessed silently:

* when the symmetric part of ``F`` is positive definite, ``sigma = lambda_min((F + F^T)/2) >
  0``, the solution is unique and ``lam^T F lam = -q^T lam`` gives ``||lam||_2 <= ||q||_2 /
  sigma``; then ``M_lam = ||q||_2 / sigma`` and ``M_w = ||F||_inf M_lam + ||q||_inf`` bound it
  (``diagnostics["big_m_proved"] = 1``);
* otherwise no a-priori bound holds for every ``F`` (Stewart-Trinkle's ``F`` is not positive
  definite): the constants start at ``M_lam = M_w = BIG_M_START * max(1, ||q||_inf) /
  min(1, ||F||_inf)`` and grow by ``BIG_M_GROWTH`` after an infeasible solve, at most
  ``BIG_M_TRIES`` times. An infeasible last try is reported as
  ``Failure.INFEASIBLE`` with the bound ("no solution with ``lam, w <= M``"), never as a proof
  that the LCP has none (``big_m_proved = 0``); with a proved bound an infeasible solve can
  only be numerical trouble and is ``Failure.ERROR``.

Whatever M is, the answer is verified: SCIP's point satisfies ``lam_i <= M b_i`` only to its
feasibility tolerance (1e-6 of ``M``), so the binaries' basis ``B = {i : b_i = 1}`` is solved
exactly, ``F_BB lam_B = -q_B``, ``lam_N = 0``, keeping ``w_i = 0`` on the degenerate pairs too
(:func:`basis_point`: SCIP's point moved by the least-norm correction onto that set), and the
point claimed (the basis point, or SCIP's own
when that is closer) must have a relative natural residual
``||min(lam, w)||_inf / max(1, ||F lam||_inf, ||q||_inf)`` at most ``settings.tolerance``
(:func:`c3bench.solvers.residuals.relative_natural_residual`); otherwise the result is
``Failure.ERROR`` with the point. ``diagnostics["big_m"]`` holds ``max(M_lam, M_w) > 0``, so a
reference never takes this model for an exact global certificate
(:func:`c3bench.bench.reference.optimality_certificate`).

Parameters: one thread, ``limits/time`` 90 % of the registry's limit minus set-up,
``limits/nodes = max_iterations``; ``numerics/feastol = min(1e-6, max(tolerance, 1e-8))`` in
non-default profiles; any ``settings.options`` key containing ``/`` is a SCIP parameter.
Duals are not meaningful: ``y``, ``z``, ``z_box`` stay ``None``.

Timing (the contract of :mod:`c3bench.solvers.timing`; rankings use setup + solve): setup is
copying ``F`` and ``q`` and computing the constants; solve is, for every try, building the
SCIP model (a try's constants change its coefficients) and ``model.optimize()``, then the
basis solve.

References
----------
J. Hu, J. E. Mitchell, J.-S. Pang, K. P. Bennett and G. Kunapuli, "On the global solution of
linear programs with linear complementarity constraints", SIAM Journal on Optimization 19(1),
445-471, 2008 (the big-M mixed-integer form of complementarity).

S. Bolusani et al., "The SCIP Optimization Suite 9.0", arXiv:2402.17702, 2024.

R. W. Cottle, J.-S. Pang and R. E. Stone, *The Linear Complementarity Problem*, Academic
Press, 1992 (existence and uniqueness for positive definite ``F``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from c3bench.problems.instance import Problem, lcp_data
from c3bench.problems.names import Failure, Family
from c3bench.solvers.backends._miqp import solver_time_limit
from c3bench.solvers.backends.scip_backend import apply_settings
from c3bench.solvers.base import Backend, Result, Settings, WarmStart
from c3bench.solvers.output import quiet_stdout
from c3bench.solvers.registry import register
from c3bench.solvers.residuals import relative_natural_residual
from c3bench.solvers.timing import Stopwatch

BIG_M_START = 1e3
"""First constant when no bound is proved: ``BIG_M_START * max(1, ||q||) / min(1, ||F||)``."""
BIG_M_GROWTH = 100.0
"""Factor the unproved constant grows by after an infeasible solve."""
BIG_M_TRIES = 3
"""Solves with an unproved constant before reporting "no solution within M"."""
DEGENERATE_W = 1e-7
"""Relative size of ``w_i`` under which the basis solve keeps ``w_i = 0`` (:func:`basis_point`)."""
PROVED_MARGIN = 1.0 + 1e-6
"""Relative margin added to a proved bound (round-off of the eigenvalue)."""


@dataclass(frozen=True)
class BigM:
    """Big-M constants of the mixed-integer form.

    Attributes
    ----------
    lam, w
        Bounds on ``lam_i`` and on ``w_i``.
    proved
        Whether they provably bound the LCP's solution (positive definite symmetric part).
    """

    lam: float
    w: float
    proved: bool

    def grown(self, factor: float) -> BigM:
        """Both constants times ``factor`` (no longer proved)."""
        return BigM(self.lam * factor, self.w * factor, False)


def big_m(F: np.ndarray, q: np.ndarray) -> BigM:
    """The constants of the module docstring for ``LCP(F, q)``."""
    norm_f = float(np.max(np.sum(np.abs(F), axis=1), initial=0.0))
    norm_q = float(np.max(np.abs(q), initial=0.0))
    sigma = float(np.linalg.eigvalsh(0.5 * (F + F.T))[0]) if q.size else 0.0
    if sigma > 1e-9 * max(1.0, norm_f):
        lam = PROVED_MARGIN * float(np.linalg.norm(q)) / sigma
        return BigM(max(lam, 1e-12), PROVED_MARGIN * (norm_f * lam + norm_q) + 1e-12, True)
    start = BIG_M_START * max(1.0, norm_q) / min(1.0, max(norm_f, 1e-12))
    return BigM(start, start, False)


def basis_point(F: np.ndarray, q: np.ndarray, basic: np.ndarray,
                start: np.ndarray) -> np.ndarray:
    """The point of the basis ``B`` nearest ``start``: ``lam_N = 0`` and ``w_R = 0`` on the
    rows ``R = B`` plus those where ``start`` already has ``|w_i| <= DEGENERATE_W * max(1,
    ||q||_inf)`` (degenerate pairs, ``lam_i = w_i = 0``, which a correction on ``B`` alone
    would push negative), by the least-norm correction
    ``lam_B = start_B + F_RB^+ (-q_R - F_RB start_B)`` (the exact solution when ``F_BB`` is
    invertible; the nearest point of the solution set when it is singular, as
    Stewart-Trinkle's blocks often are)."""
    lam = np.zeros(q.size)
    columns = np.flatnonzero(basic)
    if columns.size:
        w = F @ start + q
        degenerate = np.abs(w) <= DEGENERATE_W * max(1.0, float(np.max(np.abs(q))))
        rows = np.flatnonzero(basic | degenerate)
        block = F[np.ix_(rows, columns)]
        base = start[columns]
        lam[columns] = base + np.linalg.lstsq(block, -q[rows] - block @ base, rcond=None)[0]
    return lam


@dataclass
class _Attempt:
    """One SCIP solve: status, SCIP's point and binaries (when it found one), nodes."""

    status: str
    lam: np.ndarray | None
    basic: np.ndarray | None
    nodes: int


def _solve_once(F: np.ndarray, q: np.ndarray, bound: BigM, settings: Settings,
                time_limit: float, warm_start: WarmStart | None) -> _Attempt:
    """Build and optimise the mixed-integer form with the constants ``bound``."""
    from pyscipopt import Model, quicksum

    n = q.size
    model = Model()
    model.hideOutput()
    lam = [model.addVar(name=f"lam{i}", vtype="C", lb=0.0, ub=bound.lam) for i in range(n)]
    w = [model.addVar(name=f"w{i}", vtype="C", lb=0.0, ub=bound.w) for i in range(n)]
    basic = [model.addVar(name=f"b{i}", vtype="B") for i in range(n)]
    for i in range(n):
        columns = np.flatnonzero(F[i])
        model.addCons(w[i] - quicksum(float(F[i, j]) * lam[j] for j in columns) == float(q[i]))
        model.addCons(lam[i] <= bound.lam * basic[i])
        model.addCons(w[i] <= bound.w * (1 - basic[i]))
    model.setParam("limits/solutions", 1)
    apply_settings(model, settings, time_limit)
    if warm_start is not None and warm_start.x is not None:
        _add_start(model, F, q, np.asarray(warm_start.x, dtype=float), lam, w, basic)
    with quiet_stdout():
        model.optimize()
    status = str(model.getStatus())
    nodes = int(model.getNNodes())
    if model.getNSols() == 0:
        return _Attempt(status, None, None, nodes)
    best = model.getBestSol()
    point = np.array([model.getSolVal(best, var) for var in lam])
    chosen = np.array([model.getSolVal(best, var) > 0.5 for var in basic])
    return _Attempt(status, point, chosen, nodes)


def _add_start(model: Any, F: np.ndarray, q: np.ndarray, x: np.ndarray, lam: list[Any],
               w: list[Any], basic: list[Any]) -> None:
    """Offer a warm start's ``x`` to SCIP (it checks the point and drops it when infeasible)."""
    start = model.createSol()
    slack = F @ x + q
    for i, value in enumerate(x):
        model.setSolVal(start, lam[i], float(max(value, 0.0)))
        model.setSolVal(start, w[i], float(max(slack[i], 0.0)))
        model.setSolVal(start, basic[i], 1.0 if value > slack[i] else 0.0)
    model.addSol(start, free=True)


def _verified_point(F: np.ndarray, q: np.ndarray, attempt: _Attempt
                    ) -> tuple[np.ndarray, float, bool]:
    """The better of the exact basis point and SCIP's own (clipped at 0), its relative
    natural residual, and whether the basis point was taken."""
    assert attempt.lam is not None and attempt.basic is not None
    raw = np.maximum(attempt.lam, 0.0)
    exact = basis_point(F, q, attempt.basic, raw)
    raw_residual = relative_natural_residual(F, q, raw)
    exact_residual = relative_natural_residual(F, q, exact) if np.all(np.isfinite(exact)) \
        else math.inf
    if exact_residual <= raw_residual:
        return exact, exact_residual, True
    return raw, raw_residual, False


class ScipLCP(Backend):
    """SCIP on the big-M mixed-integer form of ``LCP(F, q)`` (module docstring)."""

    name = "scip_lcp"
    families = (Family.LCP_GENERAL,)
    package = "pyscipopt"
    description = ("LCP as a mixed-integer feasibility program (binary per pair, big-M derived "
                   "from F and q), SCIP; the basis point is verified by the natural residual")

    def solve(self, problem: Problem, settings: Settings,
              warm_start: WarmStart | None = None) -> Result:
        """Solve with growing constants until SCIP finds a point (module docstring)."""
        watch = Stopwatch()
        with watch.lap("setup"):
            F, q = lcp_data(problem, copy=True)
            bound = big_m(F, q)
        nodes = 0
        tries = 1 if bound.proved else BIG_M_TRIES
        attempt = _Attempt("not run", None, None, 0)
        with watch.lap("solve"):
            for attempt_index in range(tries):
                left = solver_time_limit(settings, watch.get("setup") + watch.get("solve"))
                try:
                    attempt = _solve_once(F, q, bound, settings, left, warm_start)
                except Exception as error:  # noqa: BLE001 - SCIP raises plain Exception
                    return Result.failed(self.name, problem.name, Failure.ERROR,
                                         f"scip: {error}", setup_time=watch.get("setup"),
                                         solve_time=watch.get("solve"), iterations=nodes)
                nodes += attempt.nodes
                if attempt.lam is not None or attempt.status not in ("infeasible",
                                                                      "inforunbd"):
                    break
                if attempt_index < tries - 1:
                    bound = bound.grown(BIG_M_GROWTH)
            diagnostics: dict[str, float] = {"big_m": max(bound.lam, bound.w),
                                             "big_m_proved": float(bound.proved),
                                             "nodes": float(nodes)}
            if attempt.lam is None:
                return self._no_point(problem, attempt, bound, watch, diagnostics, nodes)
            x, residual, polished = _verified_point(F, q, attempt)
        diagnostics.update({"natural_residual_relative": residual, "polished": float(polished)})
        common: dict[str, Any] = {"x": x, "iterations": nodes, "setup_time": watch.get("setup"),
                                  "solve_time": watch.get("solve"),
                                  "objective": problem.objective(x), "diagnostics": diagnostics}
        if not residual <= settings.tolerance:
            return Result.failed(self.name, problem.name, Failure.ERROR,
                                 f"scip: {attempt.status}; check failed: relative natural "
                                 f"residual {residual:.3g} > {settings.tolerance:g}", **common)
        return Result(solver=self.name, problem=problem.name, found=True,
                      status=f"scip: {attempt.status}; verified", **common)

    def _no_point(self, problem: Problem, attempt: _Attempt, bound: BigM, watch: Stopwatch,
                  diagnostics: dict[str, float], nodes: int) -> Result:
        """The failure when SCIP found no point: infeasible within the bound, or a limit."""
        if attempt.status in ("infeasible", "inforunbd") and bound.proved:
            # a positive definite symmetric part guarantees a solution inside the bound
            what, failure = ("reported infeasible although F's symmetric part is positive "
                             "definite (a solution exists within the bound): numerical "
                             "failure"), Failure.ERROR
        elif attempt.status in ("infeasible", "inforunbd"):
            what = (f"no solution with lam <= {bound.lam:.3g}, w <= {bound.w:.3g} "
                    "(not a proof that none exists)")
            failure = Failure.INFEASIBLE
        else:
            what, failure = "no point found", (Failure.TIMEOUT if attempt.status == "timelimit"
                                              else Failure.ERROR)
        return Result.failed(self.name, problem.name, failure, f"scip: {attempt.status}; {what}",
                             setup_time=watch.get("setup"), solve_time=watch.get("solve"),
                             iterations=nodes, diagnostics=diagnostics)


register(ScipLCP())
