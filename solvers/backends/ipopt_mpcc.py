"""IPOPT (through CasADi) on the complementarity families: two classic MPCC reformulations.

The problem is ``min f(z) = 1/2 z^T P z + q^T z + offset`` s.t. ``A z = b``, ``G z <= h``,
``lb <= z <= ub`` and ``0 <= z_i perp z_j >= 0`` per pair (both members have ``lb = 0``).
IPOPT is a local interior-point method, so both backends return a *local* solution that
may cost more than the MIQP optimum.

``ipopt_scholtes``
    Scholtes' relaxation: the pairs become ``z_i z_j <= eps``; ``eps`` is driven down
    geometrically, ``eps_k = eps_0 * factor^k`` (default ``1e-1 * 0.1^k`` down to ``1e-8``),
    each NLP warm-started from the previous primal point and (IPOPT's
    ``warm_start_init_point``, ``mu_init = 1e-6``) its multipliers.
``ipopt_penalty``
    Penalty: ``min f(z) + rho * sum_pairs z_i z_j`` with the bounds ``z >= 0`` kept;
    ``rho_k = rho_0 * factor^k`` (default ``1 * 10^k``, at most 14 values) until the
    complementarity violation ``max |min(z_i, z_j)|`` is within tolerance; each NLP starts
    from the previous primal point (multipliers off by default, see ``warm_default``).

Both record a trace per outer iteration: ``eps`` or ``rho``, ``objective`` (``f``, without the
penalty), ``complementarity`` (from :mod:`solvers.residuals`), ``primal_residual``, IPOPT's
iteration count (``ipopt_iterations``) and whether IPOPT converged (``ipopt_success``).

Final step, *mode polish* (default on; ``settings.options["polish"] = False`` disables it):
the member of each pair with the smaller value is fixed at 0 (upper bound 0) and the
remaining convex QP is solved by IPOPT at tolerance 1e-10, with linearly dependent equality
rows dropped (:func:`independent_rows`; the final check still uses every row). This removes
the ``sqrt(eps)`` residue of the relaxation. It is kept whenever IPOPT solves it (feasible,
complementarity no worse), even when it costs more: ``[E F H]`` can be nearly rank deficient
(two table contacts; smallest singular value 8.5e-7 against 40 at one quick-suite state),
and there a point violating complementarity by 2e-6 cost 36 % less than any exactly
complementary one; such a point is not a fair answer. ``diagnostics`` keep
``objective_relaxed``, ``complementarity_relaxed`` (before polishing) and
``polish_cost_change`` (relative).

``found`` is reported only when the final point's primal residual and complementarity
violation, both measured by :mod:`solvers.residuals`, are within
``tolerance * max(1, ||b||_inf, ||h||_inf)``.

Options (``settings.options``): ``eps0``, ``eps_factor``, ``eps_min`` (Scholtes), ``rho0``,
``rho_factor``, ``max_outer`` (penalty), ``warm_multipliers``, ``polish``, and any
``ipopt.<name>`` (passed to IPOPT).

Timing (the contract of :mod:`c3bench.solvers.timing`; rankings use setup + solve): setup is
building the NLP and the CasADi ``nlpsol`` functions; solve is the IPOPT runs (every relaxation
or penalty round and the polish).

References
----------
A. Wächter and L. T. Biegler, "On the implementation of an interior-point filter line-search
algorithm for large-scale nonlinear programming", Mathematical Programming 106(1), 25-57,
2006 (IPOPT).

S. Scholtes, "Convergence properties of a regularization scheme for mathematical programs
with complementarity constraints", SIAM Journal on Optimization 11(4), 918-936, 2001.

X. M. Hu and D. Ralph, "Convergence of a penalty method for mathematical programming with
complementarity constraints", Journal of Optimization Theory and Applications 123(2),
365-390, 2004.

J. A. E. Andersson, J. Gillis, G. Horn, J. B. Rawlings and M. Diehl, "CasADi: a software
framework for nonlinear optimization and optimal control", Mathematical Programming
Computation 11(1), 1-36, 2019.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import scipy.sparse as sparse

from c3bench.problems.errors import BackendUnavailable
from c3bench.problems.instance import Problem
from c3bench.problems.names import COMPLEMENTARITY_FAMILIES, Failure, Family
from c3bench.solvers.base import Backend, Result, Settings, WarmStart, require_module
from c3bench.solvers.output import quiet_stdout
from c3bench.solvers.registry import register
from c3bench.solvers.residuals import complementarity_violation, primal_residual
from c3bench.solvers.timing import Stopwatch

DEFAULT_EPS0 = 1e-1
DEFAULT_EPS_FACTOR = 0.1
DEFAULT_EPS_MIN = 1e-8
DEFAULT_RHO0 = 1.0
DEFAULT_RHO_FACTOR = 10.0
DEFAULT_MAX_OUTER = 14
WARM_MU_INIT = 1e-6
POLISH_TOLERANCE = 1e-10


@dataclass
class _Point:
    """Primal and dual state carried between IPOPT solves."""

    x: np.ndarray
    lam_x: np.ndarray | None = None
    lam_g: np.ndarray | None = None
    iterations: int = 0
    success: bool = False
    status: str = ""


@dataclass
class _Outcome:
    """Everything a backend run produces before it becomes a Result."""

    point: _Point
    converged: bool
    status: str
    iterations: int = 0
    trace: dict[str, list[float]] = field(default_factory=dict)
    diagnostics: dict[str, float] = field(default_factory=dict)


def _feasibility_limit(problem: Problem, tolerance: float) -> float:
    """``tolerance * max(1, ||b||_inf, ||h||_inf)``: the success threshold."""
    scale = 1.0
    for vector in (problem.b, problem.h):
        if vector is not None and vector.size:
            scale = max(scale, float(np.max(np.abs(vector))))
    return tolerance * scale


def _warm_multipliers(settings: Settings, default: bool) -> bool:
    """Whether later outer iterations start IPOPT from the previous multipliers too."""
    return bool(settings.options.get("warm_multipliers", default))


def independent_rows(matrix: np.ndarray, tolerance: float = 1e-10) -> np.ndarray:
    """Indices (sorted) of a maximal set of linearly independent rows of ``matrix``.

    Rank-revealing QR with column pivoting of ``matrix^T``: rows whose pivot
    ``|R_kk| <= tolerance * |R_00|`` are dependent. Redundant equalities (the two table
    contacts' friction rows can be exactly dependent once the ``eta`` of a mode are fixed)
    make IPOPT's multipliers blow up and its scaled stopping test accept poor points.
    """
    import scipy.linalg

    if matrix.shape[0] == 0:
        return np.zeros(0, dtype=np.int64)
    _, r, pivots = scipy.linalg.qr(matrix.T, mode="economic", pivoting=True)
    diagonal = np.abs(np.diag(r))
    if diagonal.size == 0 or diagonal[0] == 0:
        return np.zeros(0, dtype=np.int64)
    rank = int(np.sum(diagonal > tolerance * diagonal[0]))
    return np.sort(pivots[:rank]).astype(np.int64)


def _pairs(problem: Problem) -> np.ndarray:
    """The complementarity pairs (``accepts`` made sure there are some)."""
    assert problem.complementarity is not None
    return problem.complementarity


class _IpoptMPCC(Backend):
    """Shared machinery: CasADi model with one scalar parameter, warm-started IPOPT."""

    families: tuple[Family, ...] = COMPLEMENTARITY_FAMILIES
    package = "casadi"
    warm_default = True

    def require(self) -> None:
        """CasADi imports and has the ``ipopt`` nlpsol plugin."""
        casadi = require_module("casadi")
        if not casadi.has_nlpsol("ipopt"):
            raise BackendUnavailable("CasADi was built without the ipopt plugin")

    def accepts(self, problem: Problem) -> tuple[bool, str]:
        """Complementarity pairs whose members all have the lower bound 0."""
        ok, reason = super().accepts(problem)
        if not ok:
            return ok, reason
        if problem.complementarity is None or problem.n_pairs == 0:
            return False, "no complementarity pairs"
        lb = problem.lb if problem.lb is not None else np.full(problem.n, -np.inf)
        members = problem.complementarity.ravel()
        if np.any(lb[members] != 0):
            return False, "every pair member needs the lower bound 0"
        return True, ""

    # --- model ------------------------------------------------------------------------------
    def _ipopt_options(self, settings: Settings, deadline: float,
                       polish: bool = False, warm: bool = False) -> dict[str, Any]:
        """IPOPT options from the settings; the polish QP runs at 1e-10 whatever the profile
        (it is convex, and nearly dependent rows of ``[E F H]`` turn a 1e-7 constraint
        violation into a visible cost gain)."""
        tolerance = POLISH_TOLERANCE if polish else settings.tolerance
        options: dict[str, Any] = {
            "print_time": False,
            "ipopt.print_level": 0,
            "ipopt.sb": "yes",
            "ipopt.tol": float(max(min(tolerance, 1e-8), 1e-12)),
            "ipopt.constr_viol_tol": float(max(min(tolerance, 1e-6), 1e-12)),
            "ipopt.bound_relax_factor": float(min(1e-8, tolerance)),
            "ipopt.max_iter": int(settings.max_iterations or 3000),
            "ipopt.max_wall_time": float(max(deadline - time.perf_counter(), 1e-3)),
        }
        if warm:
            # start from the previous primal-dual point, close to the central path
            options.update({"ipopt.warm_start_init_point": "yes",
                            "ipopt.mu_init": WARM_MU_INIT,
                            "ipopt.warm_start_bound_push": 1e-9,
                            "ipopt.warm_start_mult_bound_push": 1e-9,
                            "ipopt.warm_start_slack_bound_push": 1e-9})
        for key, value in settings.options.items():
            if key.startswith("ipopt."):
                options[key] = value
        return options

    def _build(self, problem: Problem, settings: Settings, deadline: float,
               relaxation: str, fixed_zero: np.ndarray | None = None,
               equality_rows: np.ndarray | None = None, warm: bool = False
               ) -> tuple[Any, dict[str, Any]]:
        """CasADi solver and its bound arguments.

        ``relaxation``: ``"scholtes"`` (rows ``z_i z_j - p <= 0``), ``"penalty"``
        (``+ p sum z_i z_j`` in the objective) or ``"none"`` (the QP of a fixed mode, with
        ``ub = 0`` on ``fixed_zero``). ``equality_rows`` keeps only those rows of ``A``;
        ``warm`` makes IPOPT start from the given multipliers.
        """
        import casadi

        z = casadi.SX.sym("z", problem.n)
        parameter = casadi.SX.sym("p")
        P = casadi.DM(sparse.csc_matrix(problem.P))
        objective = 0.5 * casadi.dot(z, casadi.mtimes(P, z)) + casadi.dot(
            casadi.DM(problem.q), z) + problem.objective_offset
        pairs = _pairs(problem)
        products = z[pairs[:, 0].tolist()] * z[pairs[:, 1].tolist()]
        rows, lower, upper = [], [], []
        if problem.A is not None and problem.b is not None:
            keep = (np.arange(problem.n_eq) if equality_rows is None
                    else np.asarray(equality_rows, dtype=np.int64))
            if keep.size:
                rows.append(casadi.mtimes(casadi.DM(sparse.csc_matrix(problem.A[keep])), z))
                lower.append(problem.b[keep])
                upper.append(problem.b[keep])
        if problem.G is not None and problem.h is not None:
            rows.append(casadi.mtimes(casadi.DM(sparse.csc_matrix(problem.G)), z))
            lower.append(np.full(problem.n_ineq, -np.inf))
            upper.append(problem.h)
        if relaxation == "scholtes":
            rows.append(products - parameter)
            lower.append(np.full(problem.n_pairs, -np.inf))
            upper.append(np.zeros(problem.n_pairs))
        elif relaxation == "penalty":
            objective = objective + parameter * casadi.sum1(products)
        g = casadi.vertcat(*rows) if rows else casadi.SX(0, 1)
        nlp = {"x": z, "p": parameter, "f": objective, "g": g}
        solver = casadi.nlpsol(f"{self.name}_{relaxation}", "ipopt", nlp,
                               self._ipopt_options(settings, deadline,
                                                   polish=relaxation == "none", warm=warm))
        lb = problem.lb.copy() if problem.lb is not None else np.full(problem.n, -np.inf)
        ub = problem.ub.copy() if problem.ub is not None else np.full(problem.n, np.inf)
        if fixed_zero is not None:
            ub[fixed_zero] = 0.0
        arguments: dict[str, Any] = {"lbx": lb, "ubx": ub}
        if rows:
            arguments["lbg"] = np.concatenate(lower)
            arguments["ubg"] = np.concatenate(upper)
        return solver, arguments

    @staticmethod
    def _run(solver: Any, arguments: dict[str, Any], value: float, start: _Point,
             warm: bool) -> _Point:
        """One IPOPT solve at parameter ``value`` from ``start`` (quietly)."""
        call = dict(arguments, x0=start.x, p=value)
        if warm and start.lam_x is not None:
            call["lam_x0"] = start.lam_x
            if start.lam_g is not None and start.lam_g.size:
                call["lam_g0"] = start.lam_g
        with quiet_stdout():
            solution = solver(**call)
        stats = solver.stats()
        return _Point(
            x=np.asarray(solution["x"], dtype=float).ravel(),
            lam_x=np.asarray(solution["lam_x"], dtype=float).ravel(),
            lam_g=np.asarray(solution["lam_g"], dtype=float).ravel(),
            iterations=int(stats.get("iter_count", 0)),
            success=bool(stats.get("success", False)),
            status=str(stats.get("return_status", "unknown")),
        )

    @staticmethod
    def _initial(problem: Problem, warm_start: WarmStart | None) -> np.ndarray:
        if warm_start is not None and warm_start.x is not None:
            x = np.asarray(warm_start.x, dtype=float).copy()
        else:
            x = np.zeros(problem.n)
        lb = problem.lb if problem.lb is not None else np.full(problem.n, -np.inf)
        ub = problem.ub if problem.ub is not None else np.full(problem.n, np.inf)
        clipped: np.ndarray = np.clip(x, lb, ub)
        return clipped

    # --- outer loops ------------------------------------------------------------------------
    def _outer(self, problem: Problem, settings: Settings, deadline: float,
               start: np.ndarray, watch: Stopwatch) -> _Outcome:
        """The backend's outer loop, from ``start`` until convergence or ``deadline``."""
        raise NotImplementedError

    def _polish(self, problem: Problem, settings: Settings, deadline: float,
                outcome: _Outcome, watch: Stopwatch) -> None:
        """Fix the smaller member of each pair at 0 and re-solve the convex QP with IPOPT."""
        point = outcome.point
        pairs = _pairs(problem)
        x = point.x
        zero = np.where(x[pairs[:, 0]] <= x[pairs[:, 1]], pairs[:, 0], pairs[:, 1])
        before_objective = problem.objective(x)
        before_violation = complementarity_violation(problem, x)
        outcome.diagnostics["objective_relaxed"] = before_objective
        outcome.diagnostics["complementarity_relaxed"] = before_violation
        if time.perf_counter() >= deadline:
            outcome.diagnostics["polished"] = 0.0
            return
        with watch.lap("setup"):
            rows = None
            if problem.A is not None:
                free = np.setdiff1d(np.arange(problem.n), zero)
                rows = independent_rows(problem.A[:, free])
                outcome.diagnostics["polish_dropped_rows"] = float(problem.n_eq - rows.size)
            solver, arguments = self._build(problem, settings, deadline, "none", zero, rows)
        start = _Point(np.clip(x, arguments["lbx"], arguments["ubx"]))
        with watch.lap("solve"):
            polished = self._run(solver, arguments, 0.0, start, warm=False)
        outcome.iterations += polished.iterations
        after_violation = complementarity_violation(problem, polished.x)
        after_objective = problem.objective(polished.x)
        limit = _feasibility_limit(problem, settings.tolerance)
        usable = (polished.success and bool(np.all(np.isfinite(polished.x)))
                  and primal_residual(problem, polished.x) <= limit
                  and after_violation <= max(before_violation, limit))
        outcome.diagnostics["polished"] = 1.0 if usable else 0.0
        outcome.diagnostics["polish_iterations"] = float(polished.iterations)
        outcome.diagnostics["polish_cost_change"] = (
            (after_objective - before_objective) / max(1.0, abs(before_objective)))
        if usable:
            outcome.point = polished
        else:
            outcome.status += f"; polish not used ({polished.status})"

    def solve(self, problem: Problem, settings: Settings,
              warm_start: WarmStart | None = None) -> Result:
        """Outer loop, then the mode polish; ``found`` by the final residuals (module
        docstring)."""
        watch = Stopwatch()
        deadline = time.perf_counter() + 0.9 * settings.time_limit
        start = self._initial(problem, warm_start)
        outcome = self._outer(problem, settings, deadline, start, watch)
        if bool(settings.options.get("polish", True)):
            self._polish(problem, settings, deadline, outcome, watch)
        x = outcome.point.x
        limit = _feasibility_limit(problem, settings.tolerance)
        primal = primal_residual(problem, x)
        violation = complementarity_violation(problem, x)
        outcome.diagnostics.update({"final_primal_residual": primal,
                                    "final_complementarity": violation,
                                    "success_threshold": limit})
        finite = bool(np.all(np.isfinite(x)))
        found = finite and primal <= limit and violation <= limit
        status = outcome.status
        failure = Failure.NONE
        if not found:
            timed_out = time.perf_counter() >= deadline
            failure = Failure.TIMEOUT if timed_out else Failure.ERROR
            status += (f"; final point: primal residual {primal:.3g}, complementarity "
                       f"{violation:.3g}, threshold {limit:.3g}")
        return Result(solver=self.name, problem=problem.name, found=found, status=status,
                      x=x if finite else None, iterations=outcome.iterations,
                      setup_time=watch.get("setup"), solve_time=watch.get("solve"),
                      objective=problem.objective(x) if finite else None,
                      trace=outcome.trace, diagnostics=outcome.diagnostics, failure=failure)

    def _record(self, outcome: _Outcome, problem: Problem, key: str, value: float) -> float:
        point = outcome.point
        violation = complementarity_violation(problem, point.x)
        trace = outcome.trace
        for name, entry in ((key, value), ("objective", problem.objective(point.x)),
                            ("complementarity", violation),
                            ("primal_residual", primal_residual(problem, point.x)),
                            ("ipopt_iterations", float(point.iterations)),
                            ("ipopt_success", 1.0 if point.success else 0.0)):
            trace.setdefault(name, []).append(float(entry))
        return violation


class IpoptScholtes(_IpoptMPCC):
    """IPOPT on Scholtes' relaxation ``z_i z_j <= eps``, ``eps -> eps_min`` geometrically."""

    name = "ipopt_scholtes"
    # measured: warm multipliers cut IPOPT iterations 3x (4185 -> 1320) with identical points
    warm_default = True
    description = "IPOPT (CasADi), Scholtes relaxation z_i z_j <= eps, eps 1e-1 -> 1e-8"

    def _outer(self, problem: Problem, settings: Settings, deadline: float,
               start: np.ndarray, watch: Stopwatch) -> _Outcome:
        eps = float(settings.options.get("eps0", DEFAULT_EPS0))
        factor = float(settings.options.get("eps_factor", DEFAULT_EPS_FACTOR))
        eps_min = float(settings.options.get("eps_min", DEFAULT_EPS_MIN))
        if not (eps > 0 and 0 < factor < 1 and eps_min > 0):
            raise ValueError("need eps0 > 0, 0 < eps_factor < 1, eps_min > 0")
        with watch.lap("setup"):
            solver, arguments = self._build(problem, settings, deadline, "scholtes")
            warm_solver = (self._build(problem, settings, deadline, "scholtes", warm=True)[0]
                           if _warm_multipliers(settings, self.warm_default) else None)
        outcome = _Outcome(_Point(start), converged=False, status="")
        limit = _feasibility_limit(problem, settings.tolerance)
        steps = 0
        while True:
            if time.perf_counter() >= deadline:
                outcome.status = f"time limit reached at eps = {eps:.3g}"
                break
            with watch.lap("solve"):
                warm = steps > 0 and warm_solver is not None
                point = self._run(warm_solver if warm else solver, arguments, eps,
                                  outcome.point, warm=warm)
            steps += 1
            outcome.iterations += point.iterations
            if not np.all(np.isfinite(point.x)):
                outcome.status = f"IPOPT returned a non-finite point at eps = {eps:.3g}"
                break
            outcome.point = point
            violation = self._record(outcome, problem, "eps", eps)
            if not point.success:
                outcome.status = f"IPOPT: {point.status} at eps = {eps:.3g}"
                if eps <= eps_min:
                    break
            if eps <= eps_min * (1 + 1e-12):
                outcome.converged = point.success and violation <= limit
                outcome.status = outcome.status or (
                    f"eps = {eps:.3g} reached; complementarity {violation:.3g}")
                break
            eps = max(eps * factor, eps_min)
        outcome.diagnostics["outer_iterations"] = float(steps)
        outcome.diagnostics["final_eps"] = eps
        return outcome


class IpoptPenalty(_IpoptMPCC):
    """IPOPT on ``f + rho sum z_i z_j`` with ``rho`` raised until complementarity holds."""

    name = "ipopt_penalty"
    # measured on the quick suite + horizon-1/2 MPCCs: warm multipliers cut iterations by
    # 10 % but twice landed in much worse local minima (cost +44 %, +120 %), so off
    warm_default = False
    description = "IPOPT (CasADi), complementarity penalty rho * sum z_i z_j, rho x10"

    def _outer(self, problem: Problem, settings: Settings, deadline: float,
               start: np.ndarray, watch: Stopwatch) -> _Outcome:
        rho = float(settings.options.get("rho0", DEFAULT_RHO0))
        factor = float(settings.options.get("rho_factor", DEFAULT_RHO_FACTOR))
        max_outer = int(settings.options.get("max_outer", DEFAULT_MAX_OUTER))
        if not (rho > 0 and factor > 1 and max_outer >= 1):
            raise ValueError("need rho0 > 0, rho_factor > 1, max_outer >= 1")
        with watch.lap("setup"):
            solver, arguments = self._build(problem, settings, deadline, "penalty")
            warm_solver = (self._build(problem, settings, deadline, "penalty", warm=True)[0]
                           if _warm_multipliers(settings, self.warm_default) else None)
        outcome = _Outcome(_Point(start), converged=False, status="")
        limit = _feasibility_limit(problem, settings.tolerance)
        steps = 0
        for _ in range(max_outer):
            if time.perf_counter() >= deadline:
                outcome.status = f"time limit reached at rho = {rho:.3g}"
                break
            with watch.lap("solve"):
                warm = steps > 0 and warm_solver is not None
                point = self._run(warm_solver if warm else solver, arguments, rho,
                                  outcome.point, warm=warm)
            steps += 1
            outcome.iterations += point.iterations
            if not np.all(np.isfinite(point.x)):
                outcome.status = f"IPOPT returned a non-finite point at rho = {rho:.3g}"
                break
            outcome.point = point
            violation = self._record(outcome, problem, "rho", rho)
            if point.success and violation <= limit:
                outcome.converged = True
                outcome.status = f"complementarity {violation:.3g} at rho = {rho:.3g}"
                break
            outcome.status = (f"IPOPT: {point.status}; complementarity {violation:.3g} at "
                              f"rho = {rho:.3g}")
            rho *= factor
        else:
            outcome.status += f" (max_outer = {max_outer} reached)"
        outcome.diagnostics["outer_iterations"] = float(steps)
        outcome.diagnostics["final_rho"] = rho
        return outcome


register(IpoptScholtes())
register(IpoptPenalty())
