"""Convex QP backends: thin adapters around OSQP, Clarabel, ProxQP, the qpsolvers family and
CasADi's conic interfaces.

Every backend takes the problems without complementarity pairs (:data:`QP_FAMILIES`)

    minimise 1/2 z^T P z + q^T z   s.t.   A z = b,  G z <= h,  lb <= z <= ub

in float64 and returns qpsolvers' dual conventions: ``y`` (equalities), ``z >= 0``
(inequalities) and ``z_box`` (negative at an active lower bound, positive at an active upper
bound), so that ``P z + q + A^T y + G^T z + z_box = 0`` at a KKT point. ``y``, ``z`` and
``z_box`` are always arrays of sizes ``n_eq``, ``n_ineq`` and ``n`` (zeros where a block or a
bound does not exist).

Two conversions serve all backends, each with its dual splitting:

* :class:`TwoSidedForm` ``l <= M z <= u`` with ``M = [A; G; I_S]`` (``S`` the variables with a
  finite bound; without bound rows when the solver takes bounds itself). OSQP, ProxQP and
  CasADi's conic interfaces return a multiplier of ``M`` that is positive at an active upper
  and negative at an active lower side, i.e. exactly qpsolvers' signs, row block by row block.
* :class:`ConeForm` ``M z + s = r``, ``s`` in ``{0}^{n_eq} x R_+^{m}`` with
  ``M = [A; G; I_U; -I_L]`` (Clarabel): the cone dual ``d`` gives ``y = d_eq``, ``z = d_G`` and
  ``z_box = d_U - d_L`` scattered on their variables.

Registered names and the tolerance each profile sets (``tol`` = ``settings.tolerance``; the
``default`` profile keeps every solver's own tolerances; ``max_iterations``, the time limit
and ``settings.options`` are always passed on, ``options`` last so they win):

=================  ==========================================================================
``osqp``           osqp 1.x: ``eps_abs = eps_rel = tol``, ``polishing`` off, ``max_iter``,
                   ``time_limit``; warm start of ``x`` and the stacked duals.
``clarabel``       ``tol_feas = tol_gap_abs = tol_gap_rel = tol``, ``tol_ktratio = 100 tol``
                   (Clarabel's default ratio 1e-6 / 1e-8), ``max_iter``, ``time_limit``.
``proxqp_dense``   proxsuite ``proxqp.dense``: ``eps_abs = tol``, ``eps_rel = 0``, duality gap
``proxqp_sparse``  checked with ``eps_duality_gap_abs = tol`` (``_rel = 0``); bounds as rows
                   of ``C``; warm start of ``x, y, z``.
``daqp``           via qpsolvers: ``primal_tol = dual_tol = tol``, ``iter_limit``.
``piqp``           via qpsolvers (dense backend): ``eps_abs = eps_rel = tol``,
                   ``eps_duality_gap_abs = eps_duality_gap_rel = tol``, ``max_iter``.
``highs``          via qpsolvers: ``primal_ / dual_feasibility_tolerance = tol``,
                   ``time_limit``, ``qp_iteration_limit``.
``quadprog``       via qpsolvers: no tolerance option; needs ``P`` positive definite and
                   reports the ``ValueError`` it raises otherwise as a failure.
``scs``            via qpsolvers: ``eps_abs = eps_rel = tol``, ``max_iters``,
                   ``time_limit_secs``.
``qpalm``          via qpsolvers: ``eps_abs = eps_rel = tol``, ``max_iter``, ``time_limit``.
``casadi_qpoases`` ``casadi.conic(..., "qpoases")``: ``terminationTolerance = tol``,
                   ``nWSR = max_iterations``, ``CPUtime`` = time limit, ``printLevel none``,
                   ``enableEqualities`` on in every profile (equalities start in the working
                   set: 62 instead of 364 iterations on a ``c3plus_qp`` instance).
``casadi_hpipm``   ``casadi.conic(..., "hpipm")``: rows put in HPIPM's optimal-control layout
                   (stages of ``meta["layout"]``; one stage for problems without one), ``mode
                   robust``, ``res_g_max = res_b_max = res_d_max = res_m_max = tol``,
                   ``iter_max``.
=================  ==========================================================================

ProxQP, DAQP, PIQP and quadprog take no time limit here; the registry enforces it for them.
``found`` is the solver's own verdict (fully solved only: OSQP's and SCS's "solved
inaccurate" and Clarabel's ``AlmostSolved`` count as not found); when it is False the
``failure`` category is ``infeasible`` or ``timeout`` where the status says so, else ``error``.
"""

from __future__ import annotations

import contextlib
import functools
import importlib
import os
import sys
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np
import scipy.sparse as sp

from c3bench.problems.instance import Problem
from c3bench.solvers.base import QP_FAMILIES, Backend, Result, Settings, WarmStart
from c3bench.solvers.registry import register
from c3bench.solvers.timing import Stopwatch

# ----------------------------------------------------------------------------------------
# Shared conversions
# ----------------------------------------------------------------------------------------


def _bounds(problem: Problem) -> tuple[np.ndarray, np.ndarray]:
    """``lb`` and ``ub`` as full vectors (``-inf`` / ``+inf`` where absent)."""
    n = problem.n
    lb = np.full(n, -np.inf) if problem.lb is None else np.asarray(problem.lb, dtype=float)
    ub = np.full(n, np.inf) if problem.ub is None else np.asarray(problem.ub, dtype=float)
    return lb, ub


def _block(matrix: np.ndarray | None, n: int) -> sp.csc_matrix:
    return sp.csc_matrix((0, n)) if matrix is None else sp.csc_matrix(matrix)


@dataclass
class TwoSidedForm:
    """``lower <= matrix z <= upper`` with ``matrix = [A; G; I_S]``.

    Rows ``[0, n_eq)`` are the equalities (``lower = upper = b``), the next ``n_ineq`` rows the
    inequalities (``lower = -inf``, ``upper = h``) and the last ``len(bounded)`` rows the
    identity rows of the variables ``bounded`` with a finite bound (``lower = lb``,
    ``upper = ub``); with ``bounds_as_rows=False`` there are no bound rows and ``lb, ub`` are
    kept apart for solvers that take them natively.

    Attributes
    ----------
    matrix
        Stacked constraint matrix (CSC).
    lower, upper
        Row bounds (``+-inf`` where one-sided).
    n, n_eq, n_ineq
        Variables, equality rows, inequality rows.
    bounded
        Variables given an identity row.
    lb, ub
        The full bound vectors (``+-inf`` where absent).
    """

    matrix: sp.csc_matrix
    lower: np.ndarray
    upper: np.ndarray
    n: int
    n_eq: int
    n_ineq: int
    bounded: np.ndarray
    lb: np.ndarray
    ub: np.ndarray

    @classmethod
    def from_problem(cls, problem: Problem, bounds_as_rows: bool = True) -> TwoSidedForm:
        """Stack ``problem``'s constraints (see the class docstring)."""
        n = problem.n
        lb, ub = _bounds(problem)
        bounded = (np.flatnonzero(np.isfinite(lb) | np.isfinite(ub)) if bounds_as_rows
                   else np.zeros(0, dtype=np.int64))
        identity = sp.csc_matrix((np.ones(bounded.size), (np.arange(bounded.size), bounded)),
                                 shape=(bounded.size, n))
        b = np.zeros(0) if problem.b is None else problem.b
        h = np.zeros(0) if problem.h is None else problem.h
        matrix = sp.vstack([_block(problem.A, n), _block(problem.G, n), identity], format="csc")
        lower = np.concatenate([b, np.full(h.size, -np.inf), lb[bounded]])
        upper = np.concatenate([b, h, ub[bounded]])
        return cls(matrix, lower, upper, n, problem.n_eq, problem.n_ineq, bounded, lb, ub)

    @property
    def n_rows(self) -> int:
        return int(self.matrix.shape[0])

    def rows(self, part: str) -> slice:
        """Row slice of ``part``: ``eq``, ``ineq`` (``G`` and bound rows) or ``G``."""
        if part == "eq":
            return slice(0, self.n_eq)
        if part == "ineq":
            return slice(self.n_eq, self.n_rows)
        if part == "G":
            return slice(self.n_eq, self.n_eq + self.n_ineq)
        raise KeyError(part)

    def split_duals(self, duals: np.ndarray, box_duals: np.ndarray | None = None
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """qpsolvers' ``(y, z, z_box)`` from the multiplier of ``matrix``.

        ``duals`` must have the sign convention ``P z + q + matrix^T duals (+ box_duals) = 0``
        (positive at an active upper side); ``box_duals`` is the multiplier of native bounds
        (``bounds_as_rows=False``) with the same sign convention.
        """
        duals = np.asarray(duals, dtype=float).ravel()
        y = duals[: self.n_eq].copy()
        z = duals[self.n_eq: self.n_eq + self.n_ineq].copy()
        z_box = np.zeros(self.n)
        z_box[self.bounded] = duals[self.n_eq + self.n_ineq:]
        if box_duals is not None:
            z_box += np.asarray(box_duals, dtype=float).ravel()
        return y, z, z_box

    def stack_duals(self, y: np.ndarray | None, z: np.ndarray | None,
                    z_box: np.ndarray | None) -> np.ndarray:
        """Inverse of :meth:`split_duals` for the row multiplier (warm starts)."""
        y = np.zeros(self.n_eq) if y is None else np.asarray(y, dtype=float)
        z = np.zeros(self.n_ineq) if z is None else np.asarray(z, dtype=float)
        box = np.zeros(self.n) if z_box is None else np.asarray(z_box, dtype=float)
        return np.concatenate([y, z, box[self.bounded]])


@dataclass
class ConeForm:
    """``matrix z + s = rhs`` with ``s`` in ``{0}^{n_eq} x R_+^{n_ineq + |U| + |L|}``.

    ``matrix = [A; G; I_U; -I_L]`` and ``rhs = [b; h; ub_U; -lb_L]`` where ``U`` (``L``) are the
    variables with a finite upper (lower) bound.
    """

    matrix: sp.csc_matrix
    rhs: np.ndarray
    n: int
    n_eq: int
    n_ineq: int
    upper_index: np.ndarray
    lower_index: np.ndarray

    @classmethod
    def from_problem(cls, problem: Problem) -> ConeForm:
        n = problem.n
        lb, ub = _bounds(problem)
        upper_index = np.flatnonzero(np.isfinite(ub))
        lower_index = np.flatnonzero(np.isfinite(lb))

        def selector(index: np.ndarray, sign: float) -> sp.csc_matrix:
            return sp.csc_matrix((np.full(index.size, sign), (np.arange(index.size), index)),
                                 shape=(index.size, n))

        matrix = sp.vstack([_block(problem.A, n), _block(problem.G, n),
                            selector(upper_index, 1.0), selector(lower_index, -1.0)],
                           format="csc")
        rhs = np.concatenate([np.zeros(0) if problem.b is None else problem.b,
                              np.zeros(0) if problem.h is None else problem.h,
                              ub[upper_index], -lb[lower_index]])
        return cls(matrix, rhs, n, problem.n_eq, problem.n_ineq, upper_index, lower_index)

    @property
    def n_nonnegative(self) -> int:
        return self.n_ineq + self.upper_index.size + self.lower_index.size

    def split_duals(self, duals: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``y = d_eq``, ``z = d_G``, ``z_box = d_U - d_L`` (scattered) from the cone dual."""
        duals = np.asarray(duals, dtype=float).ravel()
        start = self.n_eq + self.n_ineq
        middle = start + self.upper_index.size
        z_box = np.zeros(self.n)
        z_box[self.upper_index] += duals[start:middle]
        z_box[self.lower_index] -= duals[middle:]
        return duals[: self.n_eq].copy(), duals[self.n_eq:start].copy(), z_box


def _finite_or_none(vector: Any) -> np.ndarray | None:
    if vector is None:
        return None
    array = np.asarray(vector, dtype=float).ravel()
    return array if np.all(np.isfinite(array)) else None


def _result(name: str, problem: Problem, watch: Stopwatch, *, found: bool, status: str,
            failure: str, x: Any, duals: tuple[np.ndarray, np.ndarray, np.ndarray] | None,
            iterations: int | None, diagnostics: dict[str, float] | None = None,
            build_time: float | None = None, solve_time: float | None = None) -> Result:
    """The :class:`Result` of one solve; ``failure`` is used only when ``found`` is False."""
    x_array = None if x is None else np.asarray(x, dtype=float).ravel()
    y = z = z_box = None
    if duals is not None:
        y, z, z_box = (_finite_or_none(part) for part in duals)
    objective = None
    if x_array is not None and x_array.shape == (problem.n,) and np.all(np.isfinite(x_array)):
        objective = problem.objective(x_array)
    return Result(
        solver=name, problem=problem.name, found=bool(found), status=status or "unknown",
        x=x_array, y=y, z=z, z_box=z_box,
        iterations=None if iterations is None else int(iterations),
        build_time=watch.get("build") if build_time is None else build_time,
        solve_time=watch.get("solve") if solve_time is None else solve_time,
        objective=objective, diagnostics=dict(diagnostics or {}),
        failure="" if found else (failure or "error"))


def _failure_category(status: str) -> str:
    """``infeasible``, ``timeout`` or ``error`` from a solver's status text."""
    text = status.lower()
    if "infeasib" in text:
        return "infeasible"
    if "time" in text and "limit" in text:
        return "timeout"
    return "error"


@contextlib.contextmanager
def _quiet_stdout() -> Iterator[None]:
    """Silence C-level writes to stdout (qpOASES prints a banner whenever a solver is
    constructed); used around construction only, never around a solve that could hang."""
    try:
        sys.stdout.flush()
        saved = os.dup(1)
    except (OSError, ValueError):
        yield
        return
    try:
        with open(os.devnull, "w") as sink:
            os.dup2(sink.fileno(), 1)
            try:
                yield
            finally:
                sys.stdout.flush()
                os.dup2(saved, 1)
    finally:
        os.close(saved)


class _QPBackend(Backend):
    """Common attributes of the convex QP adapters."""

    families = QP_FAMILIES
    precisions = ("float64",)


# ----------------------------------------------------------------------------------------
# OSQP
# ----------------------------------------------------------------------------------------


class OSQPBackend(_QPBackend):
    """OSQP 1.x (ADMM) on ``l <= [A; G; I_S] z <= u`` with sparse CSC data."""

    name = "osqp"
    package = "osqp"
    description = "OSQP operator-splitting ADMM (osqp 1.x, sparse)"

    def options(self, settings: Settings) -> dict[str, Any]:
        """OSQP settings for the profile."""
        options: dict[str, Any] = {"verbose": False, "time_limit": settings.time_limit}
        if settings.sets_tolerance:
            options.update(eps_abs=settings.tolerance, eps_rel=settings.tolerance,
                           polishing=False)
        if settings.max_iterations is not None:
            options["max_iter"] = int(settings.max_iterations)
        options.update(settings.options)
        return options

    def solve(self, problem: Problem, settings: Settings,
              warm_start: WarmStart | None = None) -> Result:
        import osqp

        watch = Stopwatch()
        with watch.lap("build"):
            form = TwoSidedForm.from_problem(problem)
            solver = osqp.OSQP()
            solver.setup(sp.triu(sp.csc_matrix(problem.P), format="csc"), problem.q,
                         form.matrix, form.lower, form.upper, **self.options(settings))
            if warm_start is not None and warm_start.x is not None:
                solver.warm_start(x=np.asarray(warm_start.x, dtype=float),
                                  y=form.stack_duals(warm_start.y, warm_start.z, None))
        with watch.lap("solve"):
            output = solver.solve(raise_error=False)
        info = output.info
        status = str(info.status)
        found = info.status_val == osqp.SolverStatus.OSQP_SOLVED
        duals = form.split_duals(output.y) if output.y is not None else None
        return _result(self.name, problem, watch, found=found, status=status,
                       failure=_failure_category(status), x=output.x, duals=duals,
                       iterations=info.iter,
                       diagnostics={"solver_primal_residual": float(info.prim_res),
                                    "solver_dual_residual": float(info.dual_res)})


# ----------------------------------------------------------------------------------------
# Clarabel
# ----------------------------------------------------------------------------------------


class ClarabelBackend(_QPBackend):
    """Clarabel interior point on the cone form ``[A; G; I_U; -I_L] z + s = r``."""

    name = "clarabel"
    package = "clarabel"
    description = "Clarabel interior point (direct API, zero and nonnegative cones)"

    def settings_object(self, settings: Settings) -> Any:
        """Clarabel ``DefaultSettings`` for the profile."""
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

    def solve(self, problem: Problem, settings: Settings,
              warm_start: WarmStart | None = None) -> Result:
        import clarabel

        watch = Stopwatch()
        with watch.lap("build"):
            form = ConeForm.from_problem(problem)
            cones = []
            if form.n_eq:
                cones.append(clarabel.ZeroConeT(form.n_eq))
            if form.n_nonnegative:
                cones.append(clarabel.NonnegativeConeT(form.n_nonnegative))
            solver = clarabel.DefaultSolver(sp.triu(sp.csc_matrix(problem.P), format="csc"),
                                            problem.q, form.matrix, form.rhs, cones,
                                            self.settings_object(settings))
        with watch.lap("solve"):
            solution = solver.solve()
        status = str(solution.status)
        found = solution.status == clarabel.SolverStatus.Solved
        return _result(self.name, problem, watch, found=found, status=status,
                       failure=_failure_category(status), x=solution.x,
                       duals=form.split_duals(np.asarray(solution.z)),
                       iterations=solution.iterations,
                       diagnostics={"solver_primal_residual": float(solution.r_prim),
                                    "solver_dual_residual": float(solution.r_dual)})


# ----------------------------------------------------------------------------------------
# ProxQP
# ----------------------------------------------------------------------------------------


class ProxQPBackend(_QPBackend):
    """ProxQP (proximal augmented Lagrangian) with ``l <= [G; I_S] z <= u`` as ``C`` rows."""

    package = "proxsuite"

    def __init__(self, sparse: bool) -> None:
        self.sparse = sparse
        self.name = "proxqp_sparse" if sparse else "proxqp_dense"
        self.description = (f"ProxQP proximal augmented Lagrangian (proxsuite, "
                            f"{'sparse' if sparse else 'dense'} backend)")

    def configure(self, qp: Any, settings: Settings) -> None:
        """Set ProxQP's options for the profile on ``qp.settings``."""
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

    def solve(self, problem: Problem, settings: Settings,
              warm_start: WarmStart | None = None) -> Result:
        from proxsuite import proxqp

        watch = Stopwatch()
        with watch.lap("build"):
            form = TwoSidedForm.from_problem(problem)
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
                H, A_eq, C = problem.P, form.matrix[eq].toarray(), form.matrix[ineq].toarray()
            warm = warm_start is not None and warm_start.x is not None
            if warm:
                qp.settings.initial_guess = proxqp.InitialGuess.WARM_START
            qp.init(H, problem.q, A_eq if form.n_eq else None,
                    form.lower[eq] if form.n_eq else None, C if n_in else None,
                    form.lower[ineq] if n_in else None, form.upper[ineq] if n_in else None)
        with watch.lap("solve"):
            if warm:
                assert warm_start is not None
                stacked = form.stack_duals(warm_start.y, warm_start.z, None)
                qp.solve(np.asarray(warm_start.x, dtype=float), stacked[eq], stacked[ineq])
            else:
                qp.solve()
        results = qp.results
        info = results.info
        status = str(info.status).split(".")[-1]
        found = info.status == proxqp.QPSolverOutput.PROXQP_SOLVED
        duals = form.split_duals(np.concatenate([np.asarray(results.y).ravel(),
                                                 np.asarray(results.z).ravel()]))
        return _result(self.name, problem, watch, found=found, status=status,
                       failure=_failure_category(status.replace("_", " ")), x=results.x,
                       duals=duals, iterations=info.iter,
                       diagnostics={"solver_primal_residual": float(info.pri_res),
                                    "solver_dual_residual": float(info.dua_res)})


# ----------------------------------------------------------------------------------------
# Further solvers through qpsolvers
# ----------------------------------------------------------------------------------------


@dataclass(frozen=True)
class _QpsolversSpec:
    """How one qpsolvers solver is driven.

    Attributes
    ----------
    solver
        qpsolvers' name.
    module
        Import name of the solver's package (for availability and version).
    tolerance_options
        Option names set to ``settings.tolerance`` in non-default profiles.
    iteration_option, time_option
        Option names of the iteration cap and the time limit (``""``: none).
    fixed
        Options always passed.
    description
        One line for the registry table.
    """

    solver: str
    module: str
    tolerance_options: tuple[str, ...]
    iteration_option: str
    time_option: str
    fixed: tuple[tuple[str, Any], ...]
    description: str


QPSOLVERS_SPECS: tuple[_QpsolversSpec, ...] = (
    _QpsolversSpec("daqp", "daqp", ("primal_tol", "dual_tol"), "iter_limit", "", (),
                   "DAQP dual active set (via qpsolvers)"),
    _QpsolversSpec("piqp", "piqp", ("eps_abs", "eps_rel", "eps_duality_gap_abs",
                                    "eps_duality_gap_rel"), "max_iter", "",
                   (("backend", "dense"),), "PIQP proximal interior point (via qpsolvers, dense)"),
    _QpsolversSpec("highs", "highspy", ("primal_feasibility_tolerance",
                                        "dual_feasibility_tolerance"),
                   "qp_iteration_limit", "time_limit", (),
                   "HiGHS active-set QP (via qpsolvers)"),
    _QpsolversSpec("quadprog", "quadprog", (), "", "", (),
                   "quadprog Goldfarb-Idnani dual active set (via qpsolvers; P must be PD)"),
    _QpsolversSpec("scs", "scs", ("eps_abs", "eps_rel"), "max_iters", "time_limit_secs", (),
                   "SCS conic ADMM (via qpsolvers)"),
    _QpsolversSpec("qpalm", "qpalm", ("eps_abs", "eps_rel"), "max_iter", "time_limit", (),
                   "QPALM proximal augmented Lagrangian (via qpsolvers)"),
)


def _qpsolvers_iterations(solver: str, extras: dict[str, Any]) -> int | None:
    """Iteration count from a qpsolvers ``Solution.extras`` (``None`` where not kept)."""
    try:
        if solver in ("piqp", "qpalm"):
            return int(extras["info"].iter)
        if solver == "scs":
            return int(extras["iter"])
        if solver == "quadprog":
            return int(np.ravel(extras["iterations"])[0])
    except (KeyError, AttributeError, TypeError, IndexError):
        return None
    return None


def _qpsolvers_status(solver: str, found: bool, extras: dict[str, Any]) -> str:
    """The solver's own status text where qpsolvers keeps it."""
    try:
        if solver in ("piqp", "qpalm"):
            return str(extras["info"].status).split(".")[-1]
        if solver == "scs":
            return str(extras["status"])
    except (KeyError, AttributeError, TypeError):
        pass
    return "solved" if found else "not solved (no status kept by qpsolvers)"


class QpsolversBackend(_QPBackend):
    """One solver driven through ``qpsolvers.solve_problem`` (see :data:`QPSOLVERS_SPECS`)."""

    def __init__(self, spec: _QpsolversSpec) -> None:
        self.spec = spec
        self.name = spec.solver
        self.package = spec.module
        self.description = spec.description

    def availability(self) -> tuple[bool, str]:
        ok, reason = super().availability()
        if not ok:
            return ok, reason
        try:
            qpsolvers = importlib.import_module("qpsolvers")
        except Exception as error:  # noqa: BLE001 - any import failure means unavailable
            return False, f"cannot import qpsolvers: {error}"
        if self.spec.solver not in qpsolvers.available_solvers:
            return False, f"qpsolvers does not list {self.spec.solver!r} as available"
        return True, ""

    def options(self, settings: Settings) -> dict[str, Any]:
        """Keyword options for ``qpsolvers.solve_problem``."""
        options: dict[str, Any] = dict(self.spec.fixed)
        if settings.sets_tolerance:
            options.update({key: settings.tolerance for key in self.spec.tolerance_options})
        if self.spec.time_option:
            options[self.spec.time_option] = float(settings.time_limit)
        if self.spec.iteration_option and settings.max_iterations is not None:
            options[self.spec.iteration_option] = int(settings.max_iterations)
        options.update(settings.options)
        return options

    def solve(self, problem: Problem, settings: Settings,
              warm_start: WarmStart | None = None) -> Result:
        import warnings

        import qpsolvers

        if self.spec.solver == "highs":
            _absorb_highs_banner()
        watch = Stopwatch()
        with watch.lap("build"):
            qp = qpsolvers.Problem(problem.P, problem.q, problem.G, problem.h, problem.A,
                                   problem.b, problem.lb, problem.ub)
            initvals = None
            if warm_start is not None and warm_start.x is not None:
                initvals = np.asarray(warm_start.x, dtype=float)
            options = self.options(settings)
        try:
            with watch.lap("call"), warnings.catch_warnings():
                warnings.simplefilter("ignore")
                solution = qpsolvers.solve_problem(qp, solver=self.spec.solver,
                                                   initvals=initvals, **options)
        except (qpsolvers.QPError, ValueError) as error:
            return _result(self.name, problem, watch, found=False,
                           status=f"{type(error).__name__}: {error}", failure="error",
                           x=None, duals=None, iterations=None,
                           build_time=watch.get("build") + watch.get("call"), solve_time=0.0)
        inner_solve = float(getattr(solution, "solve_time", float("nan")))
        if not np.isfinite(inner_solve) or inner_solve > watch.get("call"):
            inner_solve = watch.get("call")
        extras = solution.extras if isinstance(solution.extras, dict) else {}
        found = bool(solution.found)
        status = _qpsolvers_status(self.spec.solver, found, extras)
        duals = None
        if solution.x is not None:
            duals = (_sized(solution.y, problem.n_eq), _sized(solution.z, problem.n_ineq),
                     _sized(solution.z_box, problem.n))
        return _result(self.name, problem, watch, found=found, status=status,
                       failure=_failure_category(status), x=solution.x, duals=duals,
                       iterations=_qpsolvers_iterations(self.spec.solver, extras),
                       build_time=watch.get("build") + watch.get("call") - inner_solve,
                       solve_time=inner_solve)


@functools.cache
def _absorb_highs_banner() -> None:
    """HiGHS prints a banner on its first construction in a process: take it here, quietly."""
    with _quiet_stdout():
        importlib.import_module("highspy").Highs()


def _sized(vector: Any, size: int) -> np.ndarray:
    """qpsolvers' dual block, or zeros when it left it empty/``None`` for an absent block."""
    if vector is None:
        return np.zeros(size)
    array = np.asarray(vector, dtype=float).ravel()
    return array if array.size == size else np.zeros(size) if array.size == 0 else array


# ----------------------------------------------------------------------------------------
# CasADi conic interfaces
# ----------------------------------------------------------------------------------------


# HPIPM (through CasADi) replaces infinite bounds by a finite number (CasADi's default 1e8).
# Its slack ``1e8 - x`` then carries a rounding error of about 1e8 * 2.2e-16 = 2e-8, so a
# tolerance of 1e-9 can never be met; 1e6 keeps the floor at 2e-10. A solution reaching half
# of it is reported as a failure (the stand-in bound could be active).
HPIPM_INFINITY = 1e6
# hpipm_common.h: enum hpipm_status
HPIPM_STATUS: dict[str, str] = {"0": "success", "1": "maximum iterations reached",
                                "2": "minimum step length reached", "3": "NaN in solution",
                                "4": "inconsistent equality constraints"}


@dataclass
class _OCPRows:
    """Row order and signs that put ``[A; G]`` into HPIPM's optimal-control layout.

    HPIPM (through CasADi) wants the variables ordered ``[x_0 u_0 x_1 u_1 ... x_N]`` and the
    rows ordered ``[gap_0 lincon_0 gap_1 lincon_1 ... lincon_N]`` where a gap row of stage
    ``k`` reads ``A_k x_k + B_k u_k - x_{k+1} = -b`` (coefficient exactly ``-1`` on one
    component of ``x_{k+1}``, each component once) and a lincon row touches stage ``k`` only.
    Row ``i`` of the permuted matrix is ``signs[i]`` times row ``order[i]`` of ``[A; G]``.
    """

    order: np.ndarray
    signs: np.ndarray
    nx: list[int]
    nu: list[int]
    ng: list[int]

    def apply(self, form: TwoSidedForm) -> tuple[sp.csc_matrix, np.ndarray, np.ndarray]:
        """Permuted and scaled ``(matrix, lower, upper)``."""
        matrix = sp.csc_matrix(sp.diags(self.signs) @ form.matrix[self.order])
        lower, upper = form.lower[self.order], form.upper[self.order]
        flip = self.signs < 0
        lower, upper = (np.where(flip, -upper, lower) * np.abs(self.signs),
                        np.where(flip, -lower, upper) * np.abs(self.signs))
        return matrix, lower, upper

    def restore(self, duals: np.ndarray) -> np.ndarray:
        """Multiplier of the original rows from that of the permuted rows."""
        original = np.zeros(self.order.size)
        original[self.order] = self.signs * np.asarray(duals, dtype=float).ravel()
        return original

    def permute(self, duals: np.ndarray) -> np.ndarray:
        """Inverse of :meth:`restore` (warm starts)."""
        return np.asarray(duals, dtype=float)[self.order] / self.signs

    @classmethod
    def one_stage(cls, form: TwoSidedForm) -> _OCPRows:
        """No structure: every variable a state of stage 0, every row a lincon row."""
        rows = form.n_rows
        return cls(np.arange(rows), np.ones(rows), [form.n], [0], [rows])

    @classmethod
    def detect(cls, problem: Problem, form: TwoSidedForm) -> _OCPRows | None:
        """The layout of a horizon problem (``meta["layout"]``), or ``None`` when the rows
        do not fit it (a row spanning non-adjacent stages, a gap that is no identity...)."""
        from c3bench.problems.mpc import HorizonLayout

        table = problem.meta.get("layout") if isinstance(problem.meta, dict) else None
        if not table:
            return None
        try:
            layout = HorizonLayout.from_json(table)
            if layout.offset("x") != 0 or layout.size != problem.n:
                return None
        except (KeyError, TypeError, ValueError):
            return None
        T, nx, step = layout.horizon, layout.nx, layout.step_size
        matrix = sp.csr_matrix(form.matrix)
        gaps: list[list[tuple[int, int, float]]] = [[] for _ in range(T + 1)]
        lincon: list[list[int]] = [[] for _ in range(T + 1)]
        for row in range(matrix.shape[0]):
            columns = matrix.indices[matrix.indptr[row]:matrix.indptr[row + 1]]
            values = matrix.data[matrix.indptr[row]:matrix.indptr[row + 1]]
            nonzero = values != 0
            columns, values = columns[nonzero], values[nonzero]
            stages = np.minimum(columns // step, T)
            first = int(stages.min()) if stages.size else 0
            if np.all(stages == first):
                lincon[first].append(row)
                continue
            later = stages == first + 1
            is_equality = form.lower[row] == form.upper[row]
            if (not is_equality or not np.all(stages[~later] == first)
                    or int(later.sum()) != 1):
                return None
            column = int(columns[later][0])
            if column - (first + 1) * step >= nx:
                return None  # the next stage enters through something other than its x
            gaps[first].append((column, row, -1.0 / float(values[later][0])))
        order: list[int] = []
        signs: list[float] = []
        for k in range(T + 1):
            if k < T:
                columns_k = sorted(item[0] for item in gaps[k])
                if columns_k != list(range((k + 1) * step, (k + 1) * step + nx)):
                    return None
            for _, row, sign in sorted(gaps[k]):
                order.append(row)
                signs.append(sign)
            order.extend(lincon[k])
            signs.extend([1.0] * len(lincon[k]))
        return cls(np.asarray(order, dtype=np.int64), np.asarray(signs), [nx] * (T + 1),
                   [step - nx] * T + [0], [len(rows) for rows in lincon])


class CasadiConicBackend(_QPBackend):
    """``casadi.conic`` with ``lba <= [A; G] z <= uba`` and native bounds ``lbx <= z <= ubx``.

    CasADi's multipliers satisfy ``H z + g + A^T lam_a + lam_x = 0`` with ``lam > 0`` at an
    active upper side, i.e. qpsolvers' signs. For HPIPM the rows are reordered into the
    optimal-control layout of :class:`_OCPRows` when the problem carries a horizon layout
    (the ``c3plus_qp`` / ``c3_qp`` families), and given as one stage otherwise; the
    ``diagnostics`` entry ``ocp_stages`` says which (``N + 1``).
    """

    package = "casadi"

    def __init__(self, plugin: str, description: str) -> None:
        self.plugin = plugin
        self.name = f"casadi_{plugin}"
        self.description = description

    def availability(self) -> tuple[bool, str]:
        ok, reason = super().availability()
        if not ok:
            return ok, reason
        import casadi

        try:
            if not casadi.has_conic(self.plugin):
                return False, f"CasADi has no conic plugin {self.plugin!r}"
        except Exception as error:  # noqa: BLE001 - plugin loading may raise anything
            return False, f"CasADi cannot load plugin {self.plugin!r}: {error}"
        return True, ""

    def options(self, settings: Settings, rows: _OCPRows | None,
                warm: bool = False) -> dict[str, Any]:
        """Options of ``casadi.conic`` for the profile (``rows``: HPIPM's stage layout;
        ``warm``: a warm start is given)."""
        options: dict[str, Any] = {"error_on_fail": False, "verbose": False}
        if self.plugin == "qpoases":
            options.update(printLevel="none", CPUtime=float(settings.time_limit),
                           enableEqualities=True)
            if settings.sets_tolerance:
                options["terminationTolerance"] = settings.tolerance
            if settings.max_iterations is not None:
                options["nWSR"] = int(settings.max_iterations)
        elif self.plugin == "hpipm" and rows is not None:
            options["inf"] = HPIPM_INFINITY
            hpipm: dict[str, Any] = {"mode": "robust"}
            if settings.sets_tolerance:
                hpipm.update({key: settings.tolerance for key in
                              ("res_g_max", "res_b_max", "res_d_max", "res_m_max")})
            if settings.max_iterations is not None:
                hpipm["iter_max"] = int(settings.max_iterations)
            if warm:
                hpipm["warm_start"] = 1
            options.update(N=len(rows.nx) - 1, nx=rows.nx, nu=rows.nu, ng=rows.ng,
                           hpipm=hpipm)
        options.update(settings.options)
        return options

    def solve(self, problem: Problem, settings: Settings,
              warm_start: WarmStart | None = None) -> Result:
        import casadi

        watch = Stopwatch()
        with watch.lap("build"):
            form = TwoSidedForm.from_problem(problem, bounds_as_rows=False)
            rows = None
            if self.plugin == "hpipm":
                rows = _OCPRows.detect(problem, form) or _OCPRows.one_stage(form)
                matrix, lower, upper = rows.apply(form)
            else:
                matrix, lower, upper = form.matrix, form.lower, form.upper
            H = casadi.DM(sp.csc_matrix(problem.P))
            M = casadi.DM(matrix)
            arguments: dict[str, Any] = {
                "h": H, "g": problem.q, "a": M, "lba": lower, "uba": upper,
                "lbx": form.lb, "ubx": form.ub}
            warm = warm_start is not None and warm_start.x is not None
            if warm:
                assert warm_start is not None
                lam_a0 = form.stack_duals(warm_start.y, warm_start.z, None)
                arguments["x0"] = np.asarray(warm_start.x, dtype=float)
                arguments["lam_a0"] = lam_a0 if rows is None else rows.permute(lam_a0)
            with _quiet_stdout():
                solver = casadi.conic("qp", self.plugin, {"h": H.sparsity(),
                                                          "a": M.sparsity()},
                                      self.options(settings, rows, warm))
        with watch.lap("solve"):
            output = solver(**arguments)
        stats = solver.stats()
        found = bool(stats.get("success", False))
        status = str(stats.get("return_status", stats.get("unified_return_status", "")))
        if self.plugin == "hpipm":
            status = f"{status} ({HPIPM_STATUS.get(status, 'unknown code')})"
        elif not found and "unified_return_status" in stats:
            status = f"{status} ({stats['unified_return_status']})"
        lam_a = np.asarray(output["lam_a"]).ravel()
        duals = form.split_duals(lam_a if rows is None else rows.restore(lam_a),
                                 np.asarray(output["lam_x"]).ravel())
        iterations = stats.get("iter_count")
        diagnostics = {} if rows is None else {"ocp_stages": float(len(rows.nx))}
        x = np.asarray(output["x"]).ravel()
        if found and rows is not None:
            infinity = float(self.options(settings, rows, warm).get("inf", HPIPM_INFINITY))
            values = np.concatenate([x, matrix @ x])
            open_side = np.concatenate([~(np.isfinite(form.lb) & np.isfinite(form.ub)),
                                        ~(np.isfinite(lower) & np.isfinite(upper))])
            reach = float(np.max(np.abs(values[open_side]), initial=0.0))
            if reach >= 0.5 * infinity:
                found = False
                status = (f"{status}; solution reaches {reach:.3g}, near the finite stand-in "
                          f"{infinity:.3g} for infinite bounds")
        return _result(self.name, problem, watch, found=found, status=status,
                       failure=_failure_category(status), x=x, duals=duals,
                       iterations=None if iterations is None else int(iterations),
                       diagnostics=diagnostics)


# ----------------------------------------------------------------------------------------
# Registration
# ----------------------------------------------------------------------------------------

BACKENDS: tuple[Backend, ...] = (
    OSQPBackend(),
    ClarabelBackend(),
    ProxQPBackend(sparse=False),
    ProxQPBackend(sparse=True),
    *(QpsolversBackend(spec) for spec in QPSOLVERS_SPECS),
    CasadiConicBackend("qpoases", "qpOASES online active set (CasADi conic interface)"),
    CasadiConicBackend("hpipm", "HPIPM interior point (CasADi conic interface, OCP stages)"),
)

for _backend in BACKENDS:
    register(_backend)
