"""``cvxpy_clarabel``, ``cvxpy_osqp``, ``cvxpy_scip``: the subproblems as a researcher
prototypes them in CVXPY, a parametrized problem compiled once per instance shape.

What a modelling layer costs a controller. Inside C3 / C3+ the QP data change at every ADMM
iteration (rho enters ``P``) and at every control step (the LCS enters ``A`` and ``q``), but
the *shape* does not. The usual CVXPY prototype therefore writes the problem once with
:class:`cvxpy.Parameter` data (Agrawal et al. 2019's disciplined parametrized programming,
DPP) and re-solves it with new parameter values; CVXPY then skips the symbolic
canonicalisation and only maps the parameter values onto the solver's data. These backends do
exactly that:

* **Model.** ``minimise 1/2 ||L z||^2 + q^T z`` s.t. ``A z = b``, ``G z <= h``,
  ``z_L >= lb_L``, ``z_U <= ub_U`` (``L``, ``U``: the variables with a finite lower / upper
  bound), every datum a parameter: ``q``, ``b``, ``h``, the finite bounds, and ``A``, ``G``
  and ``L`` as *sparse* parameters carrying the instance's sparsity pattern. ``P`` itself
  cannot be a parameter (``cp.quad_form(z, P)`` with a parameter ``P`` is not DPP), so, as
  the usual prototype does, ``P = L^T L`` enters through a factor ``L``
  (:func:`hessian_factor`): ``diag(sqrt(p_ii))`` when ``P`` is diagonal (every C3 / C3+ QP
  and MPCC), else ``diag(sqrt(lambda)) V^T`` from ``P``'s eigen-decomposition, a dense
  parameter (the ``lcp`` family's 6 x 6 ``P``). A non-diagonal ``P`` larger than
  :data:`DENSE_FACTOR_MAX` enters as a constant ``quad_form`` instead (``n^2`` parameter
  entries would dominate every re-solve), so a new ``P`` of that size compiles anew. The
  factor is computed at every solve and counted as setup.
* **Cache.** One compiled model per backend and *shape*: sizes, the sparsity patterns of
  ``L``, ``A`` and ``G``, the bounded variables and (``cvxpy_scip``) the pairs
  (:func:`shape_key`; at most :data:`CACHE_SHAPES` shapes, least recently used dropped). It
  lives in the solver process, so a cell's warm-up compiles it and its timed repeats re-solve
  it (the controller's steady state); :func:`compilations` counts the compiles.
* **Timing contract.** ``setup_time``: the factor of ``P``, building the CVXPY problem on a
  cache miss, assigning the parameter values and :meth:`cvxpy.Problem.get_problem_data` (the
  first compile on a miss, the parameter-to-data map on a hit); ``diagnostics["cvxpy_compiled"]``
  says which. ``solve_time``: the solver's ``solve_via_data`` and CVXPY's unpacking of the
  answer. CVXPY constructs the solver object inside ``solve_via_data`` at every call (no
  solver cache is passed: every solve is cold, no hidden hot start), so the solver's own
  set-up (OSQP's and Clarabel's KKT factorisation, SCIP's model) lands in ``solve_time``;
  ``diagnostics["solver_setup_time"]`` carries it where the solver reports it (OSQP).
* **Answers.** ``x`` is ``z``'s value; the duals are the constraints' ``dual_value`` in
  qpsolvers' convention (CVXPY's equality dual already has it, inequality duals are ``>= 0``;
  ``z_box = dual(ub) - dual(lb)`` scattered). ``found`` only for CVXPY's ``optimal``
  (``optimal_inaccurate`` is not found).
* **Options.** ``cvxpy_osqp``: :meth:`OSQPBackend.options` (``verbose`` left to CVXPY); in the
  ``default`` profile CVXPY's own OSQP defaults apply (``eps_abs = eps_rel = 1e-5``,
  ``max_iter = 10000``, polishing on), which is what a CVXPY user gets. ``cvxpy_clarabel``:
  ``time_limit``, and in non-default profiles the tolerances of the ``clarabel`` backend
  (:func:`clarabel_options`). ``settings.options`` are passed on last (``cvxpy_scip``: keys
  containing ``/`` are SCIP parameters, ``big_m`` sets the big-M constant).
* **cvxpy_scip** (``projection``, ``mpcc``). CVXPY has no SOS1 constraint, so each pair
  ``0 <= z_i perp z_j >= 0`` becomes the binary big-M pair ``z_i <= M_i s``,
  ``z_j <= M_j (1 - s)``, ``z_i, z_j >= 0`` (``s`` boolean), with ``M_i = min(ub_i, M)`` and
  ``M = settings.options["big_m"]`` or :data:`BIG_M` (35 times the largest pair member of the
  quick suite's SCIP optima, 27). A solution with a pair member at 99 % of its ``M`` is not
  found ("big-M bound active": the bound may cut off the optimum). SCIP's parameters follow
  the ``scip`` backend (:func:`scip_parameters`); the objective reaches SCIP as a second-order
  cone epigraph (CVXPY's canonicalisation of ``sum_squares``). The answer is polished and
  checked as every MIQP answer (:func:`c3bench.solvers.backends._miqp.finish_point`); MIQP
  duals are not returned.

A backend is unavailable when CVXPY does not import or does not list its solver
(``cvxpy.installed_solvers()``).

References
----------
S. Diamond and S. Boyd, "CVXPY: A Python-embedded modeling language for convex optimization",
Journal of Machine Learning Research 17(83), 1-5, 2016.

A. Agrawal, B. Amos, S. Barratt, S. Boyd, S. Diamond and J. Z. Kolter, "Differentiable convex
optimization layers", Advances in Neural Information Processing Systems 32, 2019 (DPP).
"""

from __future__ import annotations

import math
import warnings
from collections import Counter, OrderedDict
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import scipy.sparse as sp

from c3bench.problems.errors import BackendUnavailable
from c3bench.problems.instance import Problem
from c3bench.problems.names import COMPLEMENTARITY_FAMILIES, QP_FAMILIES, Failure, Family
from c3bench.solvers.backends._miqp import finish_point, pairs_of, solver_time_limit
from c3bench.solvers.backends._qp_forms import failure_category, qp_result
from c3bench.solvers.backends.osqp_backend import OSQPBackend
from c3bench.solvers.backends.scip_backend import SCIP_MIN_FEASTOL
from c3bench.solvers.base import Backend, Result, Settings, WarmStart, require_module
from c3bench.solvers.output import quiet_stdout
from c3bench.solvers.registry import register
from c3bench.solvers.timing import Stopwatch

CACHE_SHAPES = 16
"""Compiled models kept per backend (least recently used dropped)."""
DENSE_FACTOR_MAX = 100
"""Largest non-diagonal ``P`` entered through a dense parameter factor (its ``n^2`` entries
weigh on every compile and re-solve); a larger one is a constant of the model."""
BIG_M = 1e3
"""Default big-M constant of ``cvxpy_scip`` (module docstring)."""
BIG_M_ACTIVE = 0.99
"""A pair member at this fraction of its big-M bound makes the answer not found."""

_CACHE: dict[str, OrderedDict[tuple[Any, ...], _Model]] = {}
_COMPILATIONS: Counter[str] = Counter()


def compilations(name: str) -> int:
    """How many CVXPY problems backend ``name`` compiled in this process (cache misses)."""
    return _COMPILATIONS[name]


def clear_cache() -> None:
    """Forget every compiled model (the next solve of each shape compiles again)."""
    _CACHE.clear()


@dataclass(frozen=True)
class Factor:
    """How ``P`` enters the model (:func:`hessian_factor`).

    ``kind`` is ``"diagonal"`` (a sparse parameter ``L`` with ``values`` at ``(rows,
    columns)``), ``"dense"`` (a dense parameter ``L``, ``values`` row-major) or
    ``"constant"`` (``P`` itself, a constant of the model, ``values`` its entries: a new ``P``
    is a new shape).
    """

    kind: str
    values: np.ndarray
    rows: np.ndarray
    columns: np.ndarray
    n: int

    def pattern(self) -> tuple[str, bytes, bytes]:
        """What the compiled model depends on (part of the shape key)."""
        if self.kind == "dense":
            return self.kind, b"", b""
        return self.kind, self.rows.tobytes(), self.columns.tobytes() + (
            self.values.tobytes() if self.kind == "constant" else b"")

    def value(self) -> np.ndarray | sp.coo_array:
        """The matrix: ``L`` (dense or sparse on the pattern), or ``P`` when constant."""
        if self.kind == "dense":
            return self.values.reshape(self.n, self.n)
        return sp.coo_array((self.values, (self.rows, self.columns)), shape=(self.n, self.n))


def hessian_factor(P: np.ndarray) -> Factor:
    """How ``P`` enters the model: ``L = diag(sqrt(p_ii))`` on the positive diagonal when
    ``P`` is diagonal; ``L = diag(sqrt(max(lambda, 0))) V^T`` from ``eigh(P)`` (a dense
    parameter) when ``n <= DENSE_FACTOR_MAX``; else ``P`` as a constant."""
    P = np.asarray(P, dtype=float)
    n = P.shape[0]
    diagonal = np.diag(P)
    if np.count_nonzero(P) == np.count_nonzero(diagonal):
        index = np.flatnonzero(diagonal > 0)
        return Factor("diagonal", np.sqrt(diagonal[index]), index, index.copy(), n)
    if n > DENSE_FACTOR_MAX:
        rows, columns = np.nonzero(P)
        return Factor("constant", P[rows, columns], rows, columns, n)
    eigenvalues, vectors = np.linalg.eigh(P)
    factor = np.sqrt(np.maximum(eigenvalues, 0.0))[:, None] * vectors.T
    empty = np.zeros(0, np.int64)
    return Factor("dense", factor.ravel(), empty, empty, n)


def _pattern(matrix: np.ndarray | None) -> tuple[bytes, bytes] | None:
    """Row and column indices of the nonzeros (as bytes), ``None`` without ``matrix``."""
    if matrix is None:
        return None
    rows, columns = np.nonzero(matrix)
    return rows.tobytes(), columns.tobytes()


def _finite_index(bound: np.ndarray | None) -> np.ndarray:
    return np.zeros(0, np.int64) if bound is None else np.flatnonzero(np.isfinite(bound))


def shape_key(problem: Problem, factor: Factor, integer: bool) -> tuple[Any, ...]:
    """What a compiled model depends on: sizes, sparsity patterns of ``L``, ``A``, ``G``,
    the variables with finite bounds and, for the MIQP model, the pairs."""
    return (problem.n, problem.n_eq, problem.n_ineq, factor.pattern(), _pattern(problem.A),
            _pattern(problem.G),
            _finite_index(problem.lb).tobytes(), _finite_index(problem.ub).tobytes(),
            pairs_of(problem).tobytes() if integer else None)


@dataclass
class _Model:
    """A compiled CVXPY problem and the handles to set its data and read its answer."""

    problem: Any
    z: Any
    parameters: dict[str, Any]
    constraints: dict[str, Any]
    lower_index: np.ndarray
    upper_index: np.ndarray
    members: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))

    def assign(self, problem: Problem, factor: Factor, big_m: float) -> None:
        """Set every parameter from ``problem`` (and the big-M bounds)."""
        values: dict[str, Any] = {"q": problem.q, "b": problem.b, "h": problem.h}
        if "L" in self.parameters:
            values["L"] = factor.value()
        for name, matrix in (("A", problem.A), ("G", problem.G)):
            if name in self.parameters and matrix is not None:
                pattern = np.nonzero(matrix)
                values[name] = sp.coo_array((matrix[pattern], pattern), shape=matrix.shape)
        if self.lower_index.size:
            values["lb"] = np.asarray(problem.lb)[self.lower_index]
        if self.upper_index.size:
            values["ub"] = np.asarray(problem.ub)[self.upper_index]
        if self.members.size:
            upper = (np.full(problem.n, np.inf) if problem.ub is None
                     else np.asarray(problem.ub, dtype=float))
            values["M"] = np.minimum(upper[self.members], big_m)
        for name, parameter in self.parameters.items():
            value = values[name]
            if sp.issparse(value):
                parameter.value_sparse = value
            else:
                parameter.value = value

    def duals(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """qpsolvers' ``(y, z, z_box)`` from the constraints' dual values."""
        n = self.z.shape[0]

        def dual(name: str, size: int) -> np.ndarray:
            constraint = self.constraints.get(name)
            if constraint is None or constraint.dual_value is None:
                return np.zeros(size)
            return np.asarray(constraint.dual_value, dtype=float).ravel()

        n_eq = 0 if "eq" not in self.constraints else self.constraints["eq"].shape[0]
        n_ineq = 0 if "ineq" not in self.constraints else self.constraints["ineq"].shape[0]
        z_box = np.zeros(n)
        z_box[self.upper_index] += dual("upper", self.upper_index.size)
        z_box[self.lower_index] -= dual("lower", self.lower_index.size)
        return dual("eq", n_eq), dual("ineq", n_ineq), z_box


def _sparse_parameter(cp: Any, matrix: np.ndarray) -> Any:
    return cp.Parameter(np.shape(matrix), sparsity=np.nonzero(matrix))


def build_model(problem: Problem, factor: Factor, integer: bool) -> _Model:
    """The parametrized CVXPY problem of ``problem``'s shape (module docstring)."""
    import cvxpy as cp

    n = problem.n
    z = cp.Variable(n, name="z")
    parameters: dict[str, Any] = {"q": cp.Parameter(n, name="q")}
    if factor.kind == "constant":
        quadratic = cp.quad_form(z, cp.psd_wrap(sp.csc_matrix(factor.value())))
    else:
        parameters["L"] = (
            cp.Parameter((n, n), name="L") if factor.kind == "dense"
            else cp.Parameter((n, n), name="L", sparsity=(factor.rows, factor.columns)))
        quadratic = cp.sum_squares(parameters["L"] @ z)
    constraints: dict[str, Any] = {}
    if problem.A is not None and problem.n_eq:
        parameters["A"] = _sparse_parameter(cp, problem.A)
        parameters["b"] = cp.Parameter(problem.n_eq, name="b")
        constraints["eq"] = parameters["A"] @ z == parameters["b"]
    if problem.G is not None and problem.n_ineq:
        parameters["G"] = _sparse_parameter(cp, problem.G)
        parameters["h"] = cp.Parameter(problem.n_ineq, name="h")
        constraints["ineq"] = parameters["G"] @ z <= parameters["h"]
    lower_index, upper_index = _finite_index(problem.lb), _finite_index(problem.ub)
    if lower_index.size:
        parameters["lb"] = cp.Parameter(lower_index.size, name="lb")
        constraints["lower"] = z[lower_index] >= parameters["lb"]
    if upper_index.size:
        parameters["ub"] = cp.Parameter(upper_index.size, name="ub")
        constraints["upper"] = z[upper_index] <= parameters["ub"]
    extra, members = [], np.zeros(0, np.int64)
    if integer:
        pairs = pairs_of(problem)
        members = pairs.ravel()
        mode = cp.Variable(pairs.shape[0], boolean=True, name="mode")
        big_m = parameters["M"] = cp.Parameter(members.size, nonneg=True, name="M")
        first, second = big_m[0::2], big_m[1::2]
        extra = [z[members] >= 0, z[pairs[:, 0]] <= cp.multiply(first, mode),
                 z[pairs[:, 1]] <= cp.multiply(second, 1 - mode)]
    objective = 0.5 * quadratic + parameters["q"] @ z
    compiled = cp.Problem(cp.Minimize(objective), [*constraints.values(), *extra])
    return _Model(compiled, z, parameters, constraints, lower_index, upper_index, members)


def clarabel_options(settings: Settings) -> dict[str, Any]:
    """Clarabel's options as the ``clarabel`` backend sets them, as a CVXPY options dict."""
    options: dict[str, Any] = {"time_limit": float(settings.time_limit)}
    if settings.sets_tolerance:
        tolerance = settings.tolerance
        options.update(tol_feas=tolerance, tol_gap_abs=tolerance, tol_gap_rel=tolerance,
                       tol_ktratio=min(100.0 * tolerance, 1e-1))
    if settings.max_iterations is not None:
        options["max_iter"] = int(settings.max_iterations)
    options.update(settings.options)
    return options


def scip_parameters(settings: Settings, elapsed: float) -> dict[str, Any]:
    """SCIP's parameters as the ``scip`` backend sets them (gap, feasibility tolerance, time
    left after ``elapsed`` seconds of set-up, one thread, node limit, ``/`` options)."""
    parameters: dict[str, Any] = {"limits/gap": float(settings.tolerance),
                                  "limits/time": solver_time_limit(settings, elapsed),
                                  "parallel/maxnthreads": 1}
    if settings.sets_tolerance:
        parameters["numerics/feastol"] = float(min(1e-6, max(settings.tolerance,
                                                             SCIP_MIN_FEASTOL)))
    if settings.max_iterations is not None:
        parameters["limits/nodes"] = int(settings.max_iterations)
    parameters.update({key: value for key, value in settings.options.items() if "/" in key})
    return parameters


@dataclass
class _Solved:
    """What one CVXPY solve left: the model, the status and the measured laps."""

    model: _Model
    status: str
    watch: Stopwatch
    diagnostics: dict[str, float]
    native_status: str
    """The solver's own status where CVXPY passes it on (SCIP), else ``status``."""


class CvxpyBackend(Backend):
    """A solver called through a parametrized CVXPY problem (module docstring)."""

    package = "cvxpy"
    solver = ""
    """CVXPY's name of the solver (``cvxpy.CLARABEL``, ...)."""
    integer = False
    """Whether the model has the binary big-M complementarity (``cvxpy_scip``)."""

    def require(self) -> None:
        """CVXPY imports and lists :attr:`solver` among its installed solvers."""
        cp = require_module("cvxpy")
        if self.solver not in cp.installed_solvers():
            raise BackendUnavailable(f"cvxpy does not find solver {self.solver} "
                                     f"(installed: {', '.join(cp.installed_solvers())})")

    def solver_options(self, settings: Settings, elapsed: float) -> dict[str, Any]:
        """CVXPY ``solver_opts`` of :attr:`solver` for ``settings``."""
        raise NotImplementedError

    def model_for(self, problem: Problem, factor: Factor) -> tuple[_Model, bool]:
        """The cached model of ``problem``'s shape, compiled on a miss; ``(model, missed)``."""
        cache = _CACHE.setdefault(self.name, OrderedDict())
        key = shape_key(problem, factor, self.integer)
        model = cache.get(key)
        if model is not None:
            cache.move_to_end(key)
            return model, False
        model = build_model(problem, factor, self.integer)
        cache[key] = model
        while len(cache) > CACHE_SHAPES:
            cache.popitem(last=False)
        _COMPILATIONS[self.name] += 1
        return model, True

    def run(self, problem: Problem, settings: Settings) -> _Solved:
        """Set up (factor, model, parameters, compile) and solve cold; see the module
        docstring for what each lap holds."""
        watch = Stopwatch()
        with warnings.catch_warnings():
            # CVXPY warns about dense access to sparse parameters inside its own chain and
            # about inaccurate answers (judged here by the status and the residuals)
            warnings.simplefilter("ignore")
            with watch.lap("setup"):
                factor = hessian_factor(problem.P)
                model, missed = self.model_for(problem, factor)
                model.assign(problem, factor, float(settings.options.get("big_m", BIG_M)))
                options = self.solver_options(settings, watch.get("setup"))
                data, chain, inverse = model.problem.get_problem_data(
                    self.solver, solver_opts=dict(options))
            with watch.lap("solve"), quiet_stdout():
                raw = chain.solver.solve_via_data(data, False, False, dict(options), None)
                model.problem.unpack_results(raw, chain, inverse)
        diagnostics = {"cvxpy_compiled": float(missed),
                       "cvxpy_cached_shapes": float(len(_CACHE[self.name]))}
        stats = model.problem.solver_stats
        setup = getattr(getattr(raw, "info", None), "setup_time", None)  # OSQP's own
        if setup is None and stats is not None:
            setup = stats.setup_time
        if setup is not None:
            diagnostics["solver_setup_time"] = float(setup)
        if stats is not None and stats.solve_time is not None:
            diagnostics["solver_solve_time"] = float(stats.solve_time)
        status = str(model.problem.status)
        native = raw.get("scip_status", status) if isinstance(raw, dict) else status
        return _Solved(model, status, watch, diagnostics, str(native))

    def solve(self, problem: Problem, settings: Settings,
              warm_start: WarmStart | None = None) -> Result:
        """Solve cold through the cached CVXPY model (a warm start is not used)."""
        import cvxpy as cp

        try:
            solved = self.run(problem, settings)
        except cp.error.SolverError as error:
            return Result.failed(self.name, problem.name, Failure.ERROR,
                                 f"cvxpy: {error}".strip())
        return self.result(problem, settings, solved)

    def result(self, problem: Problem, settings: Settings, solved: _Solved) -> Result:
        """The :class:`Result` of a solve."""
        raise NotImplementedError


def _iterations(stats: Any) -> int | None:
    value = None if stats is None else stats.num_iters
    return None if value is None else int(value)


class CvxpyQP(CvxpyBackend):
    """A convex QP solver under CVXPY, on the QP families."""

    families: tuple[Family, ...] = QP_FAMILIES

    def result(self, problem: Problem, settings: Settings, solved: _Solved) -> Result:
        """x, qpsolvers' duals and the status (``found`` only for ``optimal``)."""
        import cvxpy as cp

        model, status = solved.model, solved.status
        found = status == cp.OPTIMAL and model.z.value is not None
        x = model.z.value
        return qp_result(self.name, problem, solved.watch, found=found, status=status,
                         failure=failure_category(status), x=x,
                         duals=model.duals() if x is not None else None,
                         iterations=_iterations(model.problem.solver_stats),
                         diagnostics=solved.diagnostics)


class CvxpyClarabel(CvxpyQP):
    """Clarabel (Goulart and Chen 2024) under a parametrized CVXPY problem."""

    name = "cvxpy_clarabel"
    solver = "CLARABEL"
    description = "Clarabel through CVXPY (DPP problem compiled once per shape)"

    def solver_options(self, settings: Settings, elapsed: float) -> dict[str, Any]:
        return clarabel_options(settings)


class CvxpyOSQP(CvxpyQP):
    """OSQP (Stellato et al. 2020) under a parametrized CVXPY problem."""

    name = "cvxpy_osqp"
    solver = "OSQP"
    description = "OSQP through CVXPY (DPP problem compiled once per shape)"

    def solver_options(self, settings: Settings, elapsed: float) -> dict[str, Any]:
        options = OSQPBackend().options(settings)
        options.pop("verbose", None)  # CVXPY passes its own
        return options


class CvxpyScip(CvxpyBackend):
    """SCIP under a parametrized CVXPY problem, complementarity as binary big-M."""

    name = "cvxpy_scip"
    solver = "SCIP"
    integer = True
    families: tuple[Family, ...] = COMPLEMENTARITY_FAMILIES
    description = "SCIP through CVXPY, binary big-M complementarity (DPP, once per shape)"

    def solver_options(self, settings: Settings, elapsed: float) -> dict[str, Any]:
        return {"scip_params": scip_parameters(settings, elapsed)}

    def result(self, problem: Problem, settings: Settings, solved: _Solved) -> Result:
        """Polish and check the answer (:func:`finish_point`); big-M activity is a failure."""

        model, status = solved.model, solved.native_status
        x = None if model.z.value is None else np.asarray(model.z.value, dtype=float)
        found = status in ("optimal", "gaplimit") and x is not None
        big_m = np.asarray(model.parameters["M"].value, dtype=float)
        diagnostics = dict(solved.diagnostics, big_m=float(np.min(big_m, initial=math.inf)))
        if x is not None and model.members.size:
            ratio = float(np.max(x[model.members] / big_m))
            diagnostics["big_m_ratio"] = ratio
            if found and ratio >= BIG_M_ACTIVE:
                found = False
                status += f"; big-M bound active ({ratio:.3g} of M)"
        failure = Failure.NONE if found else failure_category(solved.native_status)
        return finish_point(self.name, problem, settings, x, found, f"cvxpy_scip: {status}",
                            solved.watch, diagnostics,
                            _iterations(model.problem.solver_stats), failure)


register(CvxpyClarabel())
register(CvxpyOSQP())
register(CvxpyScip())
