"""Global references for the complementarity families (``projection``, ``mpcc``).

Both families are mixed-integer QPs:

    minimise    1/2 z^T P z + q^T z + offset
    subject to  A z = b,  G z <= h,  lb <= z <= ub,
                0 <= z_i  perp  z_j >= 0   for every pair (i, j),

with ``P`` positive semi-definite. Fixing, for each pair, which member is zero (a *mode*)
leaves a convex QP, so the global optimum is the best mode optimum.

Backends
--------
``scip``
    PySCIPOpt. Objective as an epigraph ``t >= 1/2 z^T P z + q^T z`` (SCIP's objective is
    linear), complementarity as SOS1 constraints ``{z_i, z_j}`` (at most one non-zero), so
    no big-M constant and no variable bound is needed. Relative gap ``limits/gap`` and
    feasibility tolerance from the settings; SCIP's time limit set below the registry's.
``gurobi``
    gurobipy (the pip wheel's size-limited licence is enough for these instances), native
    convex quadratic objective and SOS1 constraints.
``bonmin``
    Bonmin through CasADi's ``nlpsol`` (branch-and-bound on convex NLP relaxations, solved by
    IPOPT) with the pairs passed as ``sos1_groups``.

No backend uses big-M: every result carries ``diagnostics["big_m"] = 0``.

Polishing (default on; ``settings.options["polish"] = False`` turns it off): the mode of the
solver's point (the smaller member of each pair set to zero) is re-solved as a convex QP with
Clarabel at 1e-10, so the reported point is the exact optimum of the mode the MIQP solver
chose; ``diagnostics["objective_solver"]`` keeps the solver's own objective and
``polish_cost_change`` the relative change. The polished point is used even when it costs
more: the solvers' points satisfy complementarity only to their feasibility tolerance
(1e-6), and where ``[E F H]`` is nearly rank deficient such a point can be much cheaper than
any exactly complementary one. MIQP duals are
not meaningful: ``y``, ``z`` and ``z_box`` stay ``None``.

:func:`enumerate_modes` is the brute-force reference: all ``2^pairs`` modes, each a convex QP
solved by Clarabel and then re-solved exactly on the face Clarabel's point identifies
(:func:`refine_on_face`, a null-space solve), best feasible kept. The refinement matters:
where ``[E F H]`` is nearly rank deficient, Clarabel's answer was measured 7.7e-6 (relative)
above the exact mode optimum while feasible to 3e-12.
"""

from __future__ import annotations

import importlib
import itertools
import math
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sparse

import c3bench.solvers.projection  # noqa: F401 - registers ``c3plus_closed_form``
from c3bench.problems.instance import Problem
from c3bench.solvers.backends.nlp import quiet_stdout
from c3bench.solvers.base import COMPLEMENTARITY_FAMILIES, Backend, Result, Settings, WarmStart
from c3bench.solvers.registry import register
from c3bench.solvers.residuals import complementarity_violation, primal_residual
from c3bench.solvers.timing import Stopwatch, single_thread_blas

MODE_QP_TOLERANCE = 1e-10
"""Clarabel's gap and feasibility tolerances for the QP of one mode."""

SCIP_MIN_FEASTOL = 1e-8
"""Smallest feasibility tolerance given to SCIP (below it SoPlex asks for GMP)."""

REFINE_SLACK = 1e-7
"""Relative cost increase up to which the exact face solution replaces Clarabel's point."""

MODE_FEASIBILITY = 1e-7
"""Largest primal residual at which a mode's QP solution counts as feasible."""


# --- one mode: a convex QP ------------------------------------------------------------------
@dataclass
class ModeSolution:
    """Optimum of the convex QP of one complementarity mode.

    Attributes
    ----------
    x
        Full-size solution (``None`` when the mode is infeasible or the solve failed).
    objective
        ``1/2 x^T P x + q^T x + offset`` (``inf`` without a solution).
    status
        Clarabel's status text.
    """

    x: np.ndarray | None
    objective: float
    status: str


def _bounds(problem: Problem) -> tuple[np.ndarray, np.ndarray]:
    lb = problem.lb if problem.lb is not None else np.full(problem.n, -np.inf)
    ub = problem.ub if problem.ub is not None else np.full(problem.n, np.inf)
    return lb, ub


def solve_mode(problem: Problem, zero: np.ndarray,
               tolerance: float = MODE_QP_TOLERANCE) -> ModeSolution:
    """Solve the convex QP with the variables ``zero`` fixed at 0 (the pairs dropped).

    The fixed variables are eliminated; the rest keep their bounds, so
    ``min 1/2 y^T P_kk y + q_k^T y  s.t.  A_k y = b, G_k y <= h, lb_k <= y <= ub_k`` over the
    kept indices ``k``, solved by Clarabel with gap and feasibility tolerances ``tolerance``,
    then refined by :func:`refine_on_face` (kept unless it costs more than
    :data:`REFINE_SLACK` relative). The answer counts as feasible when its primal residual
    is at most :data:`MODE_FEASIBILITY`.
    """
    import clarabel

    n = problem.n
    zero = np.unique(np.asarray(zero, dtype=np.int64))
    lb, ub = _bounds(problem)
    if np.any(lb[zero] > 0) or np.any(ub[zero] < 0):
        return ModeSolution(None, math.inf, "infeasible: a fixed variable excludes 0")
    keep = np.setdiff1d(np.arange(n), zero)
    m = keep.size
    P = sparse.csc_matrix(np.triu(problem.P[np.ix_(keep, keep)]))
    blocks: list[np.ndarray] = []
    rhs: list[np.ndarray] = []
    cones: list[object] = []
    if problem.A is not None:
        blocks.append(problem.A[:, keep])
        rhs.append(problem.b)
        cones.append(clarabel.ZeroConeT(problem.n_eq))
    inequalities = 0
    if problem.G is not None:
        blocks.append(problem.G[:, keep])
        rhs.append(problem.h)
        inequalities += problem.n_ineq
    lower = np.flatnonzero(np.isfinite(lb[keep]))
    upper = np.flatnonzero(np.isfinite(ub[keep]))
    identity = np.eye(m)
    if lower.size:
        blocks.append(-identity[lower])
        rhs.append(-lb[keep][lower])
        inequalities += lower.size
    if upper.size:
        blocks.append(identity[upper])
        rhs.append(ub[keep][upper])
        inequalities += upper.size
    if inequalities:
        cones.append(clarabel.NonnegativeConeT(inequalities))
    A_all = sparse.csc_matrix(np.vstack(blocks)) if blocks else sparse.csc_matrix((0, m))
    b_all = np.concatenate(rhs) if rhs else np.zeros(0)
    settings = clarabel.DefaultSettings()
    settings.verbose = False
    settings.tol_gap_abs = tolerance
    settings.tol_gap_rel = tolerance
    settings.tol_feas = tolerance
    settings.max_iter = 400
    solution = clarabel.DefaultSolver(P, problem.q[keep], A_all, b_all, cones,
                                      settings).solve()
    status = str(solution.status)
    if status not in ("Solved", "AlmostSolved"):
        return ModeSolution(None, math.inf, status)
    x = np.zeros(n)
    x[keep] = np.asarray(solution.x)
    if not np.all(np.isfinite(x)) or primal_residual(problem, x) > MODE_FEASIBILITY:
        return ModeSolution(None, math.inf, f"{status} (primal residual too large)")
    objective = problem.objective(x)
    refined = refine_on_face(problem, x, zero)
    # the exact face solution wins unless it is clearly worse (a wrongly guessed active set);
    # a slightly cheaper interior-point answer may just be slightly infeasible
    if refined is not None and problem.objective(refined) <= objective + REFINE_SLACK * max(
            1.0, abs(objective)):
        return ModeSolution(refined, problem.objective(refined), f"{status}, refined")
    return ModeSolution(x, objective, status)


def refine_on_face(problem: Problem, x: np.ndarray, zero: np.ndarray,
                   activity: float = 1e-8) -> np.ndarray | None:
    """Exact minimiser on the face of ``x``'s active constraints, or ``None``.

    The bounds that ``x`` meets within ``activity * (1 + |bound|)`` (and the variables
    ``zero``) are fixed, the inequality rows it meets become equalities, and

        min 1/2 y^T P y + q^T y   s.t.   C y = d

    is solved by the null-space method with an SVD (rank cut at ``1e-13 sigma_max``), so
    exactly redundant rows are harmless and nearly dependent ones (``[E F H]`` with
    ``sigma_min / sigma_max ~ 1e-8`` near two table contacts) are honoured exactly; an
    interior-point solution there can be off by 1e-5 in cost while feasible to 1e-12.
    Returned only when it is feasible (primal residual at most 1e-9) and finite.
    """
    n = problem.n
    lb, ub = _bounds(problem)
    fixed_value = np.full(n, np.nan)
    at_lower = np.isfinite(lb) & (x - lb <= activity * (1 + np.abs(lb)))
    at_upper = np.isfinite(ub) & (ub - x <= activity * (1 + np.abs(ub)))
    fixed_value[at_lower] = lb[at_lower]
    fixed_value[at_upper] = ub[at_upper]
    fixed_value[np.asarray(zero, dtype=np.int64)] = 0.0
    fixed = np.isfinite(fixed_value)
    free = np.flatnonzero(~fixed)
    rows: list[np.ndarray] = []
    rhs: list[np.ndarray] = []
    if problem.A is not None:
        rows.append(problem.A)
        rhs.append(problem.b)
    if problem.G is not None:
        tight = problem.h - problem.G @ x <= activity * (1 + np.abs(problem.h))
        rows.append(problem.G[tight])
        rhs.append(problem.h[tight])
    base = np.where(fixed, fixed_value, 0.0)
    if free.size == 0:
        candidate = base
    else:
        C = np.vstack(rows)[:, free] if rows else np.zeros((0, free.size))
        d = (np.concatenate(rhs) - np.vstack(rows) @ base) if rows else np.zeros(0)
        P_ff = problem.P[np.ix_(free, free)]
        g = problem.q[free] + problem.P[np.ix_(free, np.flatnonzero(fixed))] @ base[fixed]
        if C.shape[0]:
            _, sigma, vt = np.linalg.svd(C, full_matrices=True)
            rank = int(np.sum(sigma > 1e-13 * sigma[0])) if sigma.size and sigma[0] > 0 else 0
            particular = np.linalg.lstsq(C, d, rcond=1e-13)[0]
            null = vt[rank:].T
        else:
            particular = np.zeros(free.size)
            null = np.eye(free.size)
        if null.shape[1]:
            reduced = null.T @ P_ff @ null
            step = np.linalg.lstsq(reduced, -null.T @ (P_ff @ particular + g), rcond=1e-13)[0]
            y = particular + null @ step
        else:
            y = particular
        candidate = base.copy()
        candidate[free] = y
    if not np.all(np.isfinite(candidate)) or primal_residual(problem, candidate) > 1e-9:
        return None
    return candidate


def mode_of(problem: Problem, x: np.ndarray) -> np.ndarray:
    """The variables a point sets to zero: per pair, the member with the smaller value
    (ties: the first member)."""
    pairs = problem.complementarity
    if pairs is None or pairs.size == 0:
        return np.zeros(0, dtype=np.int64)
    x = np.asarray(x, dtype=float)
    first_smaller = x[pairs[:, 0]] <= x[pairs[:, 1]]
    return np.where(first_smaller, pairs[:, 0], pairs[:, 1])


def polish(problem: Problem, x: np.ndarray) -> ModeSolution:
    """Re-solve the mode of ``x`` (see :func:`mode_of`) as a convex QP."""
    return solve_mode(problem, mode_of(problem, x))


@dataclass
class ModeSearch:
    """Outcome of the brute-force search.

    Attributes
    ----------
    x, objective
        Best feasible point and its objective (``None`` and ``inf`` when no mode is feasible).
    zero
        Variables fixed at 0 in the best mode.
    modes, feasible
        Modes solved and modes found feasible.
    """

    x: np.ndarray | None
    objective: float
    zero: np.ndarray
    modes: int
    feasible: int


def search_modes(problem: Problem, max_pairs: int = 12) -> ModeSearch:
    """Solve every complementarity mode (see :func:`enumerate_modes`) and keep the best."""
    pairs = problem.complementarity
    count = 0 if pairs is None else int(pairs.shape[0])
    if count > max_pairs:
        raise ValueError(f"{problem.name}: {count} complementarity pairs exceed "
                         f"max_pairs={max_pairs} (2^{count} convex QPs)")
    best = ModeSearch(None, math.inf, np.zeros(0, dtype=np.int64), 0, 0)
    choices = itertools.product((0, 1), repeat=count)
    with single_thread_blas():  # thousands of tiny factorisations: threads only cost
        for choice in choices:
            _visit_mode(problem, pairs, count, choice, best)
    return best


def _visit_mode(problem: Problem, pairs: np.ndarray | None, count: int,
                choice: tuple[int, ...], best: ModeSearch) -> None:
    """Solve one mode and keep it in ``best`` when it is feasible and cheaper."""
    zero = (np.array([pairs[i, c] for i, c in enumerate(choice)], dtype=np.int64)
            if count and pairs is not None else np.zeros(0, dtype=np.int64))
    solution = solve_mode(problem, zero)
    best.modes += 1
    if solution.x is None:
        return
    best.feasible += 1
    if solution.objective < best.objective:
        best.x, best.objective, best.zero = solution.x, solution.objective, zero


def enumerate_modes(problem: Problem, max_pairs: int = 12) -> tuple[np.ndarray | None, float]:
    """Brute-force global optimum over all ``2^pairs`` complementarity modes.

    For every choice of one member per pair fixed at 0 (the other keeps its bounds,
    ``lb = 0``), the convex QP is solved by :func:`solve_mode` (Clarabel, tolerances 1e-10);
    the best feasible mode wins (ties: the first in lexicographic order, first members
    zeroed first).

    Returns
    -------
    x, objective
        The optimum and ``1/2 x^T P x + q^T x + offset``; ``(None, inf)`` when every mode is
        infeasible.

    Raises
    ------
    ValueError
        When the problem has more than ``max_pairs`` pairs.
    """
    search = search_modes(problem, max_pairs)
    return search.x, search.objective


# --- helpers shared by the backends ---------------------------------------------------------
def _finite_or_none(value: float) -> float | None:
    return float(value) if math.isfinite(value) else None


def _polish_enabled(settings: Settings) -> bool:
    return bool(settings.options.get("polish", True))


def _finish_point(name: str, problem: Problem, settings: Settings, x: np.ndarray | None,
                  found: bool, status: str, watch: Stopwatch, diagnostics: dict[str, float],
                  iterations: int | None, failure: str = "") -> Result:
    """Polish (when asked), measure the point with ``solvers.residuals`` and build a Result.

    ``found`` stays true only if the final point is feasible and complementary within
    ``max(settings.tolerance, 1e-6)`` (the MIQP solvers' own feasibility tolerance).
    """
    diagnostics["big_m"] = 0.0
    if x is not None:
        x = np.asarray(x, dtype=float)
        diagnostics["objective_solver"] = problem.objective(x)
        diagnostics["complementarity_solver"] = complementarity_violation(problem, x)
        if _polish_enabled(settings):
            with watch.lap("polish"):
                polished = polish(problem, x)
            diagnostics["polish_time"] = watch.get("polish")
            if polished.x is not None:
                diagnostics["polish_cost_change"] = (
                    (polished.objective - problem.objective(x))
                    / max(1.0, abs(problem.objective(x))))
                x = polished.x
                diagnostics["polished"] = 1.0
            else:
                diagnostics["polished"] = 0.0
                status += f"; polish not used ({polished.status})"
        limit = max(settings.tolerance, 1e-6)
        violation = max(primal_residual(problem, x), complementarity_violation(problem, x))
        diagnostics["final_violation"] = violation
        if found and violation > limit:
            found = False
            failure = failure or "error"
            status += f"; final point violates constraints by {violation:.3g} > {limit:.3g}"
    return Result(solver=name, problem=problem.name, found=found, status=status, x=x,
                  iterations=iterations, build_time=watch.get("build"),
                  solve_time=watch.get("solve") + watch.get("polish"),
                  objective=None if x is None else problem.objective(x),
                  diagnostics=diagnostics, failure="" if found else failure)


def _objective_scale(problem: Problem) -> float:
    """``max(1, max |P_ij|, max |q_i|)``: the epigraph is ``t >= f(z) / scale`` so that the
    cut coefficients SCIP's LP sees are O(1) (the MPC weights reach 2e5)."""
    return max(1.0, float(np.max(np.abs(problem.P), initial=0.0)),
               float(np.max(np.abs(problem.q), initial=0.0)))


def _solver_time_limit(settings: Settings, elapsed: float) -> float:
    """Time left for the solver itself: 90 % of the registry's limit minus set-up time."""
    return max(0.05, 0.9 * settings.time_limit - elapsed)


# --- SCIP -------------------------------------------------------------------------------------
class ScipMIQP(Backend):
    """SCIP branch-and-bound with SOS1 complementarity and an epigraph objective."""

    name = "scip"
    families = COMPLEMENTARITY_FAMILIES
    package = "pyscipopt"
    description = "MIQP reference: SCIP (PySCIPOpt), SOS1 complementarity, no big-M"

    def solve(self, problem: Problem, settings: Settings,
              warm_start: WarmStart | None = None) -> Result:
        from pyscipopt import Model, quicksum

        watch = Stopwatch()
        with watch.lap("build"):
            model = Model()
            model.hideOutput()
            lb, ub = _bounds(problem)
            z = [model.addVar(name=f"z{i}", vtype="C",
                              lb=None if math.isinf(lb[i]) else float(lb[i]),
                              ub=None if math.isinf(ub[i]) else float(ub[i]))
                 for i in range(problem.n)]
            for matrix, vector, sense in ((problem.A, problem.b, "=="),
                                          (problem.G, problem.h, "<=")):
                if matrix is None:
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
            scale = _objective_scale(problem)
            # offset inside the epigraph: SCIP's relative gap is then relative to the true cost
            model.addCons((quadratic + linear + problem.objective_offset) * (1.0 / scale) <= t)
            model.setObjective(t, "minimize")
            for i, j in problem.complementarity:
                model.addConsSOS1([z[int(i)], z[int(j)]])
            # SCIP's own default gap (0) makes the epigraph outer approximation branch
            # until the LP fails numerically, so the gap always comes from the settings.
            model.setParam("limits/gap", float(settings.tolerance))
            if settings.sets_tolerance:
                model.setParam("numerics/feastol", float(min(1e-6, max(settings.tolerance,
                                                                       SCIP_MIN_FEASTOL))))
            model.setParam("limits/time", _solver_time_limit(settings, watch.get("build")))
            model.setParam("parallel/maxnthreads", 1)
            if settings.max_iterations is not None:
                model.setParam("limits/nodes", int(settings.max_iterations))
            for key, value in settings.options.items():
                if "/" in key:
                    model.setParam(key, value)
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
                return Result.failed(self.name, problem.name, "error",
                                     f"scip: {error}", build_time=watch.get("build"),
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
        failure = {"timelimit": "timeout", "infeasible": "infeasible",
                   "inforunbd": "infeasible"}.get(status, "" if found else "error")
        return _finish_point(self.name, problem, settings, x, found, f"scip: {status}", watch,
                             diagnostics, int(model.getNNodes()), failure)


# --- Gurobi -----------------------------------------------------------------------------------
class GurobiMIQP(Backend):
    """Gurobi MIQP with SOS1 complementarity (when gurobipy and a licence are present)."""

    name = "gurobi"
    families = COMPLEMENTARITY_FAMILIES
    package = "gurobipy"
    description = "MIQP reference: Gurobi, SOS1 complementarity (licence permitting)"
    _licence: tuple[bool, str] | None = None

    def availability(self) -> tuple[bool, str]:
        try:
            gp = importlib.import_module("gurobipy")
        except ImportError:
            return False, "gurobipy not installed"
        except Exception as error:  # noqa: BLE001
            return False, f"gurobipy does not import: {error}"
        if GurobiMIQP._licence is None:
            try:
                env = gp.Env(empty=True)
                env.setParam("OutputFlag", 0)
                env.start()
                env.dispose()
                GurobiMIQP._licence = (True, "")
            except gp.GurobiError as error:
                GurobiMIQP._licence = (False, f"no usable Gurobi licence: {error}")
        return GurobiMIQP._licence

    def solve(self, problem: Problem, settings: Settings,
              warm_start: WarmStart | None = None) -> Result:
        import gurobipy as gp
        from gurobipy import GRB

        watch = Stopwatch()
        try:
            with watch.lap("build"):
                env = gp.Env(empty=True)
                env.setParam("OutputFlag", 0)
                env.start()
                model = gp.Model(env=env)
                lb, ub = _bounds(problem)
                z = model.addMVar(problem.n, lb=np.where(np.isinf(lb), -GRB.INFINITY, lb),
                                  ub=np.where(np.isinf(ub), GRB.INFINITY, ub))
                if problem.A is not None:
                    model.addConstr(sparse.csr_matrix(problem.A) @ z == problem.b)
                if problem.G is not None:
                    model.addConstr(sparse.csr_matrix(problem.G) @ z <= problem.h)
                model.setObjective(0.5 * (z @ sparse.csr_matrix(problem.P) @ z)
                                   + problem.q @ z + problem.objective_offset, GRB.MINIMIZE)
                variables = z.tolist()
                for i, j in problem.complementarity:
                    model.addSOS(GRB.SOS_TYPE1, [variables[int(i)], variables[int(j)]],
                                 [1.0, 2.0])
                model.Params.Threads = 1
                model.Params.TimeLimit = _solver_time_limit(settings, watch.get("build"))
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
            reason = ("licence size limit" if getattr(error, "errno", None) == 10010
                      else "gurobi error")
            return Result.failed(self.name, problem.name,
                                 "unavailable" if reason == "licence size limit" else "error",
                                 f"{reason}: {error}", build_time=watch.get("build"),
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
        failure = {"time_limit": "timeout", "infeasible": "infeasible"}.get(
            status, "" if found else "error")
        iterations = int(model.NodeCount)
        model.dispose()
        env.dispose()
        return _finish_point(self.name, problem, settings, x, found, f"gurobi: {status}",
                             watch, diagnostics, iterations, failure)


# --- Bonmin -----------------------------------------------------------------------------------
class BonminMIQP(Backend):
    """Bonmin (B-BB) through CasADi with the pairs as SOS1 groups."""

    name = "bonmin"
    families = COMPLEMENTARITY_FAMILIES
    package = "casadi"
    description = "MIQP reference: Bonmin B-BB via CasADi nlpsol, SOS1 groups"

    def availability(self) -> tuple[bool, str]:
        try:
            casadi = importlib.import_module("casadi")
        except ImportError as error:
            return False, f"cannot import casadi: {error}"
        if not casadi.has_nlpsol("bonmin"):
            return False, "CasADi was built without the bonmin plugin"
        return True, ""

    def solve(self, problem: Problem, settings: Settings,
              warm_start: WarmStart | None = None) -> Result:
        import casadi

        watch = Stopwatch()
        with watch.lap("build"):
            z = casadi.SX.sym("z", problem.n)
            P = casadi.DM(sparse.csc_matrix(problem.P))
            objective = 0.5 * casadi.dot(z, casadi.mtimes(P, z)) + casadi.dot(
                casadi.DM(problem.q), z) + problem.objective_offset
            rows, lower, upper = [], [], []
            if problem.A is not None:
                rows.append(casadi.mtimes(casadi.DM(sparse.csc_matrix(problem.A)), z))
                lower.append(problem.b)
                upper.append(problem.b)
            if problem.G is not None:
                rows.append(casadi.mtimes(casadi.DM(sparse.csc_matrix(problem.G)), z))
                lower.append(np.full(problem.n_ineq, -np.inf))
                upper.append(problem.h)
            g = casadi.vertcat(*rows) if rows else casadi.SX(0, 1)
            limit = _solver_time_limit(settings, 0.0)
            options: dict[str, object] = {
                "sos1_groups": [[int(i), int(j)] for i, j in problem.complementarity],
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
            lb, ub = _bounds(problem)
            arguments: dict[str, object] = {"lbx": lb, "ubx": ub}
            if rows:
                arguments["lbg"] = np.concatenate(lower)
                arguments["ubg"] = np.concatenate(upper)
            if warm_start is not None and warm_start.x is not None:
                arguments["x0"] = np.asarray(warm_start.x, dtype=float)
        with watch.lap("solve"), quiet_stdout():  # Bonmin's node log ignores its log levels
            solution = solver(**arguments)
        stats = solver.stats()
        status = str(stats.get("return_status", "unknown"))
        x = np.asarray(solution["x"], dtype=float).ravel()
        success = bool(stats.get("success", False)) and status == "SUCCESS"
        if not np.all(np.isfinite(x)):
            x = None
        failure = "" if success else ("infeasible" if "INFEASIBLE" in status.upper()
                                      else "timeout" if "TIME" in status.upper() else "error")
        return _finish_point(self.name, problem, settings, x, success and x is not None,
                             f"bonmin: {status}", watch, {}, None, failure)


register(ScipMIQP())
register(GurobiMIQP())
register(BonminMIQP())
