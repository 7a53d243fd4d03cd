"""Solvers driven through qpsolvers' ``solve_problem``: DAQP, PIQP, HiGHS, quadprog, SCS, QPALM.

qpsolvers (Caron et al. 2024) converts the problem to each solver's own form and returns
``x`` with qpsolvers' duals ``y``, ``z`` and ``z_box`` (the convention of the whole
benchmark); missing dual blocks become zeros of the right size. How each solver is driven
(:data:`QPSOLVERS_SPECS`; ``tol`` = ``settings.tolerance``, set in non-default profiles only;
``settings.options`` are passed last, so they win):

============  =============================================================================
``daqp``      ``primal_tol = dual_tol = tol``, ``iter_limit``.
``piqp``      dense backend; ``eps_abs = eps_rel = tol``,
              ``eps_duality_gap_abs = eps_duality_gap_rel = tol``, ``max_iter``.
``highs``     ``primal_ / dual_feasibility_tolerance = tol``, ``time_limit``,
              ``qp_iteration_limit``; HiGHS' banner (printed on its first construction in a
              process) is absorbed once, quietly.
``quadprog``  no tolerance option; needs ``P`` positive definite and reports the
              ``ValueError`` it raises otherwise as a failure.
``scs``       ``eps_abs = eps_rel = tol``, ``max_iters``, ``time_limit_secs``.
``qpalm``     ``eps_abs = eps_rel = tol``, ``max_iter``, ``time_limit``.
============  =============================================================================

DAQP, PIQP and quadprog take no time limit here; the registry enforces it. ``found`` is
qpsolvers' verdict; the status is the solver's own: where qpsolvers keeps it (PIQP, QPALM,
SCS) or recorded as qpsolvers receives it (DAQP's exit flag, HiGHS's model status, quadprog's
message: :mod:`._qpsolvers_status`).
``setup_time`` includes qpsolvers' conversion (the call's time minus the solver's own
``solve_time`` where qpsolvers reports it).

Timing (the contract of :mod:`c3bench.solvers.timing`; rankings use setup + solve): setup is
building the ``qpsolvers.Problem`` plus qpsolvers' conversion to the solver's form (the call's
time minus the solver's own ``solve_time``); solve is the solver's own ``solve_time``. For a
solver whose time qpsolvers does not report the whole call counts as solve.

Warm cells (:class:`~c3bench.solvers.timing.UpdatableBackend`): ``piqp`` only, natively
(qpsolvers has no update API): a ``piqp.DenseSolver`` set up untimed on the instance with
the options above; the setup lap is ``solver.update(c=, b=, h_u=, x_l=, x_u=)`` with the
instance's vectors, the solve lap ``solver.solve()``. PIQP takes no initial guess, so the
guess is unused. The other solvers here pay a full ``solve_problem`` in warm cells too
(emulated: their ``warm_support`` says so).

References
----------
S. Caron et al., "qpsolvers: Quadratic Programming Solvers in Python", software, version 4,
2024.

D. Arnström, A. Bemporad and D. Axehill, "A dual active-set solver for embedded quadratic
programming using recursive LDL^T updates", IEEE Transactions on Automatic Control 67(8),
4362-4369, 2022 (DAQP).

R. Schwan, Y. Jiang, D. Kuhn and C. N. Jones, "PIQP: A Proximal Interior-Point Quadratic
Programming Solver", IEEE Conference on Decision and Control (CDC), 2023.

Q. Huangfu and J. A. J. Hall, "Parallelizing the dual revised simplex method", Mathematical
Programming Computation 10(1), 119-142, 2018 (HiGHS).

D. Goldfarb and A. Idnani, "A numerically stable dual method for solving strictly convex
quadratic programs", Mathematical Programming 27(1), 1-33, 1983 (quadprog).

B. O'Donoghue, "Operator splitting for a homogeneous embedding of the linear complementarity
problem", SIAM Journal on Optimization 31(3), 1999-2023, 2021 (SCS 3).

B. Hermans, A. Themelis and P. Patrinos, "QPALM: a proximal augmented Lagrangian method for
nonconvex quadratic programs", Mathematical Programming Computation 14, 497-541, 2022.
"""

from __future__ import annotations

import functools
import importlib
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from c3bench.problems.errors import BackendUnavailable
from c3bench.problems.instance import Problem
from c3bench.problems.names import Failure
from c3bench.solvers.backends._qp_forms import ConeForm, QPBackend, failure_category, qp_result
from c3bench.solvers.backends._qpsolvers_status import StatusProbe
from c3bench.solvers.backends._warm_vectors import full_bounds
from c3bench.solvers.base import Result, Settings, WarmStart, require_module
from c3bench.solvers.output import quiet_stdout
from c3bench.solvers.registry import register
from c3bench.solvers.timing import SETUP, SOLVE, Stopwatch


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


def _inner_solve_time(solver: str, solution: Any, extras: dict[str, Any],
                      probe: StatusProbe) -> float:
    """The solver's own solve time (s), without its setup: DAQP's and SCS's own split
    (qpsolvers' ``solve_time`` wraps their whole call, which builds and factorises first;
    the contract books that as setup), else qpsolvers' ``solve_time``."""
    try:
        if solver == "daqp":
            return float(probe.info()["solve_time"])
        if solver == "scs":
            return float(extras["solve_time"]) / 1e3  # SCS reports milliseconds
    except (KeyError, TypeError, ValueError):
        pass
    return float(getattr(solution, "solve_time", float("nan")))


def _qpsolvers_iterations(solver: str, extras: dict[str, Any],
                          probe: StatusProbe) -> int | None:
    """Iteration count from a qpsolvers ``Solution.extras`` or, for DAQP, the recorded
    call's ``info`` (``None`` where not kept)."""
    try:
        if solver == "daqp":
            return int(probe.info()["iterations"])
        if solver in ("piqp", "qpalm"):
            return int(extras["info"].iter)
        if solver == "scs":
            return int(extras["iter"])
        if solver == "quadprog":
            return int(np.ravel(extras["iterations"])[0])
    except (KeyError, AttributeError, TypeError, IndexError):
        return None
    return None


GUESS_DROPPED = {
    "quadprog": "qpsolvers ignores initvals for it (with a warning)",
    "highs": "qpsolvers ignores initvals for it (with a warning)",
    "qpalm": "qpsolvers' hand-over sets a setting QPALM does not have and drops the error",
}
"""Solvers whose initial guess qpsolvers (4.x) drops, so that their warm cells are cold
solves (measured: the same iterations and objective with no guess, the exact answer or a
guess 1e4 away; QPALM's own ``warm_start`` with the exact answer takes 7 -> 5 iterations)."""


def _qpsolvers_status(solver: str, found: bool, extras: dict[str, Any],
                      probe: StatusProbe, warned: Sequence[str] = ()) -> str:
    """The solver's own status: where qpsolvers keeps it (PIQP, QPALM, SCS), else what the
    ``probe`` recorded (DAQP's exit flag, HiGHS's model status, quadprog's message:
    :mod:`._qpsolvers_status`)."""
    recorded = probe.status(found, warned)
    if recorded is not None:
        return recorded
    try:
        if solver in ("piqp", "qpalm"):
            return str(extras["info"].status).split(".")[-1]
        if solver == "scs":
            return str(extras["status"])
    except (KeyError, AttributeError, TypeError):
        pass
    return "solved" if found else "not solved (no status kept by qpsolvers)"


class QpsolversBackend(QPBackend):
    """One solver driven through ``qpsolvers.solve_problem`` (Caron et al. 2024; see
    :data:`QPSOLVERS_SPECS` and the module docstring for each solver's reference)."""

    def __init__(self, spec: _QpsolversSpec) -> None:
        self.spec = spec
        self.name = spec.solver
        self.package = spec.module
        self.description = spec.description
        if spec.solver in GUESS_DROPPED:
            self.warm_support = (f"emulated, and the initial guess never reaches "
                                 f"{spec.solver}: {GUESS_DROPPED[spec.solver]}; a warm cell is "
                                 f"a cold solve (setup + solve)")

    def require(self) -> None:
        """The solver's package and qpsolvers import, and qpsolvers lists the solver."""
        super().require()
        qpsolvers = require_module("qpsolvers")
        if self.spec.solver not in qpsolvers.available_solvers:
            raise BackendUnavailable(
                f"qpsolvers does not list {self.spec.solver!r} as available")

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
        """One ``qpsolvers.solve_problem`` call; its ``QPError`` / ``ValueError`` (e.g.
        quadprog on a singular ``P``) is a recorded failure."""
        import warnings

        import qpsolvers

        if self.spec.solver == "highs":
            _absorb_highs_banner()
        watch = Stopwatch()
        rows: ConeForm | None = None
        with watch.lap("setup"):
            if self.spec.solver == "quadprog" and (problem.lb is not None or
                                                   problem.ub is not None):
                # qpsolvers would make every lb/ub entry a row, infinite ones included (a
                # c3plus_qp instance with 28 finite bounds of 206: 548 rows instead of 192,
                # 22.0 against 14.1 ms, the same answer): only the finite ones become rows
                rows = ConeForm.from_problem(problem, dense=True)
                some = rows.n_nonnegative > 0
                qp = qpsolvers.Problem(problem.P, problem.q,
                                       rows.matrix[rows.n_eq:] if some else None,
                                       rows.rhs[rows.n_eq:] if some else None, problem.A,
                                       problem.b)
            else:
                qp = qpsolvers.Problem(problem.P, problem.q, problem.G, problem.h, problem.A,
                                       problem.b, problem.lb, problem.ub)
            initvals = None
            if warm_start is not None and warm_start.x is not None:
                initvals = np.asarray(warm_start.x, dtype=float)
            options = self.options(settings)
        probe = StatusProbe(self.spec.solver)
        try:
            with probe.watching(), warnings.catch_warnings(record=True) as caught:
                # quadprog's message comes as a warning (_qpsolvers_status); others: ignored
                warnings.simplefilter("always" if self.spec.solver == "quadprog" else "ignore")
                with watch.lap("call"):  # the solver call only, as in the other backends
                    solution = qpsolvers.solve_problem(qp, solver=self.spec.solver,
                                                       initvals=initvals, **options)
        except (qpsolvers.QPError, ValueError) as error:
            return qp_result(self.name, problem, watch, found=False,
                             status=f"{type(error).__name__}: {error}",
                             failure=Failure.ERROR, x=None, duals=None, iterations=None,
                             setup_time=watch.get("setup") + watch.get("call"),
                             solve_time=0.0)
        extras = solution.extras if isinstance(solution.extras, dict) else {}
        inner_solve = _inner_solve_time(self.spec.solver, solution, extras, probe)
        if not np.isfinite(inner_solve) or inner_solve > watch.get("call"):
            inner_solve = watch.get("call")
        found = bool(solution.found)
        status = _qpsolvers_status(self.spec.solver, found, extras, probe,
                                   [str(warning.message) for warning in caught])
        duals = None
        if solution.x is not None:
            duals = (_sized(solution.y, problem.n_eq), _sized(solution.z, problem.n_ineq),
                     _sized(solution.z_box, problem.n))
            if rows is not None:  # quadprog: the finite bounds were rows of G
                rows_z = _sized(solution.z, rows.n_nonnegative)
                duals = rows.split_duals(np.concatenate([duals[0], rows_z]))
        return qp_result(self.name, problem, watch, found=found, status=status,
                         failure=failure_category(status), x=solution.x, duals=duals,
                         iterations=_qpsolvers_iterations(self.spec.solver, extras, probe),
                         setup_time=watch.get("setup") + watch.get("call") - inner_solve,
                         solve_time=inner_solve)


PIQP_STATUS_SOLVED = "PIQP_SOLVED"
"""PIQP's status name of a solved problem."""


class PiqpBackend(QpsolversBackend):
    """PIQP (Schwan et al. 2023): cold cells through qpsolvers like the others, warm cells
    through PIQP's own ``DenseSolver.update`` (module docstring)."""

    warm_support = ("PIQP DenseSolver.update(c=, b=, h_u=, x_l=, x_u=) of the solver set up "
                    "on the same matrices (native, not through qpsolvers); no initial guess")

    def _native_settings(self, solver: Any, settings: Settings) -> None:
        """Set the options qpsolvers would pass (``backend`` excluded) on ``solver``."""
        for key, value in self.options(settings).items():
            if key != "backend":
                setattr(solver.settings, key, value)

    def prepare(self, problem: Problem, settings: Settings) -> Any:
        """A ``piqp.DenseSolver`` set up on ``problem`` (untimed in a warm cell)."""
        import piqp

        solver = piqp.DenseSolver()
        self._native_settings(solver, settings)
        lb, ub = full_bounds(problem)
        solver.setup(np.asarray(problem.P, dtype=float), np.asarray(problem.q, dtype=float),
                     _dense_or_none(problem.A), _vector_or_none(problem.b),
                     _dense_or_none(problem.G), None, _vector_or_none(problem.h), lb, ub)
        return solver

    def resolve(self, prepared: Any, problem: Problem, settings: Settings,
                warm_start: WarmStart | None) -> Result:
        """``update`` with the vectors (setup lap), ``solve`` (solve lap); the initial
        guess is unused (PIQP takes none)."""
        solver = prepared
        watch = Stopwatch()
        with watch.lap(SETUP):
            lb, ub = full_bounds(problem)
            vectors: dict[str, Any] = {"c": np.asarray(problem.q, dtype=float),
                                       "x_l": lb, "x_u": ub}
            if problem.b is not None and problem.n_eq:
                vectors["b"] = np.asarray(problem.b, dtype=float)
            if problem.h is not None and problem.n_ineq:
                vectors["h_u"] = np.asarray(problem.h, dtype=float)
            solver.update(**vectors)
        with watch.lap(SOLVE):
            status = solver.solve()
        name = str(status).split(".")[-1]
        result = solver.result
        found = name == PIQP_STATUS_SOLVED
        duals = (np.asarray(result.y, dtype=float),
                 np.asarray(result.z_u, dtype=float) - np.asarray(result.z_l, dtype=float)
                 if problem.n_ineq else np.zeros(0),
                 np.asarray(result.z_bu, dtype=float) - np.asarray(result.z_bl, dtype=float))
        return qp_result(self.name, problem, watch, found=found, status=name,
                         failure=failure_category(name), x=np.asarray(result.x),
                         duals=duals, iterations=int(result.info.iter))


def _dense_or_none(matrix: Any) -> np.ndarray | None:
    """A Fortran-ordered float64 copy of ``matrix`` (PIQP's dense input), or ``None``."""
    if matrix is None or np.size(matrix) == 0:
        return None
    return np.asfortranarray(matrix, dtype=float)


def _vector_or_none(vector: Any) -> np.ndarray | None:
    """``vector`` as float64, or ``None`` when absent or empty."""
    if vector is None or np.size(vector) == 0:
        return None
    return np.asarray(vector, dtype=float)


@functools.cache
def _absorb_highs_banner() -> None:
    """HiGHS prints a banner on its first construction in a process: take it here, quietly."""
    with quiet_stdout():
        importlib.import_module("highspy").Highs()


def _sized(vector: Any, size: int) -> np.ndarray:
    """qpsolvers' dual block, or zeros when it left it empty/``None`` for an absent block."""
    if vector is None:
        return np.zeros(size)
    array = np.asarray(vector, dtype=float).ravel()
    return array if array.size == size else np.zeros(size) if array.size == 0 else array


for _spec in QPSOLVERS_SPECS:
    register(PiqpBackend(_spec) if _spec.solver == "piqp" else QpsolversBackend(_spec))
