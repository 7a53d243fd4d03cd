"""Shared conversions and result assembly of the convex QP adapters (a helper module: the
registry skips modules whose name starts with ``_``).

Every convex QP backend takes the problems without complementarity pairs
(:data:`~c3bench.problems.names.QP_FAMILIES`)

    minimise 1/2 z^T P z + q^T z   s.t.   A z = b,  G z <= h,  lb <= z <= ub

in float64 and returns qpsolvers' dual conventions (Caron et al. 2024): ``y`` (equalities),
``z >= 0`` (inequalities) and ``z_box`` (negative at an active lower bound, positive at an
active upper bound), so that ``P z + q + A^T y + G^T z + z_box = 0`` at a KKT point. ``y``,
``z`` and ``z_box`` are always arrays of sizes ``n_eq``, ``n_ineq`` and ``n`` (zeros where a
block or a bound does not exist).

Two conversions serve all backends, each with its dual splitting:

* :class:`TwoSidedForm` ``l <= M z <= u`` with ``M = [A; G; I_S]`` (``S`` the variables with a
  finite bound; without bound rows when the solver takes bounds itself). OSQP, ProxQP and
  CasADi's conic interfaces return a multiplier of ``M`` that is positive at an active upper
  and negative at an active lower side, i.e. exactly qpsolvers' signs, row block by row block.
* :class:`ConeForm` ``M z + s = r``, ``s`` in ``{0}^{n_eq} x R_+^{m}`` with
  ``M = [A; G; I_U; -I_L]`` (Clarabel): the cone dual ``d`` gives ``y = d_eq``, ``z = d_G`` and
  ``z_box = d_U - d_L`` scattered on their variables.

``found`` is the solver's own verdict (fully solved only: OSQP's and SCS's "solved
inaccurate" and Clarabel's ``AlmostSolved`` count as not found); when it is False the
``failure`` category is ``Failure.INFEASIBLE``, ``Failure.UNBOUNDED`` or ``Failure.TIMEOUT``
where the status says so, in any backend's wording, else ``Failure.ERROR``
(:func:`failure_category`).

References
----------
S. Caron et al., "qpsolvers: Quadratic Programming Solvers in Python", software, version 4,
2024.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import scipy.sparse as sp

from c3bench.problems.instance import Problem
from c3bench.problems.names import QP_FAMILIES, Failure, Family, Precision
from c3bench.solvers.backends._qpsolvers_status import QUADPROG_INCONSISTENT
from c3bench.solvers.base import Backend, Result
from c3bench.solvers.timing import Stopwatch


class QPBackend(Backend):
    """Common attributes of the convex QP adapters: the QP families, float64 only."""

    families: tuple[Family, ...] = QP_FAMILIES
    precisions: tuple[Precision, ...] = (Precision.FLOAT64,)


def _bounds(problem: Problem) -> tuple[np.ndarray, np.ndarray]:
    """``lb`` and ``ub`` as full vectors (``-inf`` / ``+inf`` where absent)."""
    n = problem.n
    lb = np.full(n, -np.inf) if problem.lb is None else np.asarray(problem.lb, dtype=float)
    ub = np.full(n, np.inf) if problem.ub is None else np.asarray(problem.ub, dtype=float)
    return lb, ub


def _block(matrix: np.ndarray | None, n: int) -> sp.csc_matrix:
    return sp.csc_matrix((0, n)) if matrix is None else sp.csc_matrix(matrix)


def _dense_block(matrix: Any, n: int) -> np.ndarray:
    if matrix is None:
        return np.zeros((0, n))
    array = matrix.toarray() if sp.issparse(matrix) else matrix
    return np.asarray(array, dtype=float).reshape(-1, n)


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
        Stacked constraint matrix (CSC; a dense array when built with ``dense=True``).
    lower, upper
        Row bounds (``+-inf`` where one-sided).
    n, n_eq, n_ineq
        Variables, equality rows, inequality rows.
    bounded
        Variables given an identity row.
    lb, ub
        The full bound vectors (``+-inf`` where absent).
    """

    matrix: Any
    lower: np.ndarray
    upper: np.ndarray
    n: int
    n_eq: int
    n_ineq: int
    bounded: np.ndarray
    lb: np.ndarray
    ub: np.ndarray

    @classmethod
    def from_problem(cls, problem: Problem, bounds_as_rows: bool = True,
                     dense: bool = False) -> TwoSidedForm:
        """Stack ``problem``'s constraints (see the class docstring); ``dense``: as a dense
        array, for a dense solver (no detour through a sparse format)."""
        n = problem.n
        lb, ub = _bounds(problem)
        bounded = (np.flatnonzero(np.isfinite(lb) | np.isfinite(ub)) if bounds_as_rows
                   else np.zeros(0, dtype=np.int64))
        b = np.zeros(0) if problem.b is None else problem.b
        h = np.zeros(0) if problem.h is None else problem.h
        if dense:
            matrix: Any = np.vstack([_dense_block(problem.A, n), _dense_block(problem.G, n),
                                     np.eye(n)[bounded]])
        else:
            identity = sp.csc_matrix((np.ones(bounded.size), (np.arange(bounded.size),
                                                               bounded)),
                                     shape=(bounded.size, n))
            matrix = sp.vstack([_block(problem.A, n), _block(problem.G, n), identity],
                               format="csc")
        lower = np.concatenate([b, np.full(h.size, -np.inf), lb[bounded]])
        upper = np.concatenate([b, h, ub[bounded]])
        return cls(matrix, lower, upper, n, problem.n_eq, problem.n_ineq, bounded, lb, ub)

    @property
    def n_rows(self) -> int:
        """Rows of ``matrix``."""
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

    matrix: Any
    rhs: np.ndarray
    n: int
    n_eq: int
    n_ineq: int
    upper_index: np.ndarray
    lower_index: np.ndarray

    @classmethod
    def from_problem(cls, problem: Problem, dense: bool = False) -> ConeForm:
        """Stack ``problem``'s constraints (see the class docstring); ``dense``: as a dense
        array, for a dense solver (no detour through a sparse format)."""
        n = problem.n
        lb, ub = _bounds(problem)
        upper_index = np.flatnonzero(np.isfinite(ub))
        lower_index = np.flatnonzero(np.isfinite(lb))
        if dense:
            identity = np.eye(n)
            matrix: Any = np.vstack([_dense_block(problem.A, n), _dense_block(problem.G, n),
                                     identity[upper_index], -identity[lower_index]])
        else:
            def selector(index: np.ndarray, sign: float) -> sp.csc_matrix:
                return sp.csc_matrix((np.full(index.size, sign),
                                      (np.arange(index.size), index)), shape=(index.size, n))

            matrix = sp.vstack([_block(problem.A, n), _block(problem.G, n),
                                selector(upper_index, 1.0), selector(lower_index, -1.0)],
                               format="csc")
        rhs = np.concatenate([np.zeros(0) if problem.b is None else problem.b,
                              np.zeros(0) if problem.h is None else problem.h,
                              ub[upper_index], -lb[lower_index]])
        return cls(matrix, rhs, n, problem.n_eq, problem.n_ineq, upper_index, lower_index)

    @property
    def n_nonnegative(self) -> int:
        """Rows in the nonnegative cone: ``G`` rows and the finite upper and lower bounds."""
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


def finite_or_none(vector: Any) -> np.ndarray | None:
    """``vector`` as a flat float array when it is given and finite, else ``None``."""
    if vector is None:
        return None
    array = np.asarray(vector, dtype=float).ravel()
    return array if np.all(np.isfinite(array)) else None


def qp_result(name: str, problem: Problem, watch: Stopwatch, *, found: bool, status: str,
            failure: Failure, x: Any, duals: tuple[np.ndarray, np.ndarray, np.ndarray] | None,
            iterations: int | None, diagnostics: dict[str, float] | None = None,
            setup_time: float | None = None, solve_time: float | None = None) -> Result:
    """The :class:`Result` of one solve; ``failure`` is used only when ``found`` is False."""
    x_array = None if x is None else np.asarray(x, dtype=float).ravel()
    y = z = z_box = None
    if duals is not None:
        y, z, z_box = (finite_or_none(part) for part in duals)
    objective = None
    if x_array is not None and x_array.shape == (problem.n,) and np.all(np.isfinite(x_array)):
        objective = problem.objective(x_array)
    return Result(
        solver=name, problem=problem.name, found=bool(found), status=status or "unknown",
        x=x_array, y=y, z=z, z_box=z_box,
        iterations=None if iterations is None else int(iterations),
        setup_time=watch.get("setup") if setup_time is None else setup_time,
        solve_time=watch.get("solve") if solve_time is None else solve_time,
        objective=objective, diagnostics=dict(diagnostics or {}),
        failure=Failure.NONE if found else (failure or Failure.ERROR))


TIME_LIMIT_WORDS = ("maxtime", "max time", "time exceeded")
"""Status wording of a reached time limit besides "time" with "limit" (OSQP's "run time limit
reached", HiGHS's "Time limit reached", QPALM's "time limit exceeded", SCS's "reached
time_limit_secs", Gurobi's ``time_limit``, SCIP's ``timelimit``): Clarabel's ``MaxTime`` and
Ipopt's ``Maximum_CpuTime_Exceeded`` / ``Maximum_WallTime_Exceeded``."""


def failure_category(status: str) -> Failure:
    """The failure category of a solver's status text, the same for every backend's wording
    (``_`` read as a space, case ignored): ``Failure.INFEASIBLE`` for "infeasible or
    unbounded" (``inforunbd``), ``Failure.UNBOUNDED`` for "unbounded" or "dual infeasible"
    (OSQP, PIQP, ProxQP, QPALM, Clarabel's ``DualInfeasible``, CVXPY, SCS, qpOASES),
    ``Failure.INFEASIBLE`` for any other "infeasib..." and for quadprog's
    :data:`QUADPROG_INCONSISTENT`, ``Failure.TIMEOUT`` for "time" and "limit" or any of
    :data:`TIME_LIMIT_WORDS`, else ``Failure.ERROR``."""
    text = status.lower().replace("_", " ")
    if "infeasible or unbounded" in text or "inforunbd" in text:
        return Failure.INFEASIBLE
    if "unbounded" in text or "dual infeasib" in text or "dualinfeasib" in text:
        return Failure.UNBOUNDED
    if "infeasib" in text or QUADPROG_INCONSISTENT in text:
        return Failure.INFEASIBLE
    if ("time" in text and "limit" in text) or any(word in text for word in TIME_LIMIT_WORDS):
        return Failure.TIMEOUT
    return Failure.ERROR
