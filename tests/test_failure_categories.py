"""Failure categories read the same from every backend's wording (``failure_category``), and the
backends that report why they failed say infeasible / unbounded on problems known to be so.

The problems are tiny, with a known answer: ``x_1 <= -1`` and ``x_1 >= 1`` (infeasible),
``x_1 + x_2 = 0`` and ``x_1 + x_2 = 1`` (inconsistent equalities), and
``min x_1^2 / 2 - x_2`` with ``x_1 <= 1`` and ``x_2`` free (unbounded below: dual infeasible).
"""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from c3bench.problems.importers import QPSOLVERS_KEYS, qp_problem
from c3bench.problems.instance import Problem
from c3bench.problems.names import Failure
from c3bench.solvers import registry
from c3bench.solvers.backends._qp_forms import failure_category
from c3bench.solvers.base import settings_for


@pytest.mark.parametrize(("status", "category"), [
    ("primal infeasible", Failure.INFEASIBLE),  # OSQP, QPALM
    ("PrimalInfeasible", Failure.INFEASIBLE),  # Clarabel
    ("PIQP_PRIMAL_INFEASIBLE", Failure.INFEASIBLE),
    ("infeasible_inaccurate", Failure.INFEASIBLE),  # CVXPY
    ("gurobi: infeasible_or_unbounded", Failure.INFEASIBLE),
    ("scip: inforunbd", Failure.INFEASIBLE),
    ("dual infeasible", Failure.UNBOUNDED),  # OSQP, QPALM
    ("DualInfeasible", Failure.UNBOUNDED),  # Clarabel
    ("AlmostDualInfeasible", Failure.UNBOUNDED),
    ("PROXQP_DUAL_INFEASIBLE", Failure.UNBOUNDED),
    ("unbounded_inaccurate", Failure.UNBOUNDED),  # CVXPY
    ("Initial QP could not be solved due to unboundedness!", Failure.UNBOUNDED),  # qpOASES
    ("time limit reached", Failure.TIMEOUT),
    ("MaxTime", Failure.TIMEOUT),  # Clarabel
    ("run time limit reached", Failure.TIMEOUT),  # OSQP
    ("time limit exceeded", Failure.TIMEOUT),  # QPALM
    ("HiGHS: Time limit reached", Failure.TIMEOUT),
    ("solved (inaccurate - reached time_limit_secs)", Failure.TIMEOUT),  # SCS
    ("time_limit", Failure.TIMEOUT),  # Gurobi
    ("timelimit", Failure.TIMEOUT),  # SCIP
    ("Maximum_CpuTime_Exceeded", Failure.TIMEOUT),  # Ipopt
    ("max time reached", Failure.TIMEOUT),
    ("quadprog: constraints are inconsistent, no solution", Failure.INFEASIBLE),
    ("MaxIterations", Failure.ERROR),
    ("maximum iterations reached", Failure.ERROR),  # OSQP
    ("solved (inaccurate - reached max_iters)", Failure.ERROR),  # SCS
    ("PROXQP_MAX_ITER_REACHED", Failure.ERROR),
    ("node_limit", Failure.ERROR),  # Gurobi
    ("nodelimit", Failure.ERROR),  # SCIP
    ("LIMIT_EXCEEDED", Failure.ERROR),  # Bonmin: time or node limit, not told apart
    ("not solved (no status kept by qpsolvers)", Failure.ERROR),
])
def test_failure_category_reads_every_wording_alike(status: str, category: Failure) -> None:
    assert failure_category(status) == category


def test_clarabels_time_limit_status_is_a_timeout() -> None:
    clarabel = pytest.importorskip("clarabel")
    assert failure_category(str(clarabel.SolverStatus.MaxTime)) == Failure.TIMEOUT
    assert failure_category(str(clarabel.SolverStatus.MaxIterations)) == Failure.ERROR


def _qp(name: str, **arrays: np.ndarray) -> Problem:
    return qp_problem(name, {key: arrays.get(key) for key in QPSOLVERS_KEYS}, "test")


INFEASIBLE = _qp("infeasible", P=np.eye(2), q=np.zeros(2), G=np.array([[1.0, 0.0], [-1.0, 0.0]]),
                 h=np.array([-1.0, -1.0]))
INCONSISTENT = _qp("inconsistent", P=np.eye(2), q=np.zeros(2), A=np.ones((2, 2)),
                   b=np.array([0.0, 1.0]))
UNBOUNDED = _qp("unbounded", P=np.diag([1.0, 0.0]), q=np.array([0.0, -1.0]),
                G=np.array([[1.0, 0.0]]), h=np.array([1.0]))

REPORTING = ("osqp", "clarabel", "piqp", "proxqp_dense", "qpalm", "scs", "cvxpy_clarabel",
             "daqp")
"""Backends whose status says why they failed on both problems (DAQP's exit flag recorded as
qpsolvers receives it; HiGHS claims the unbounded problem optimal, and quadprog refuses a P that
is not positive definite before it could find it unbounded: both tested apart)."""


def _solve(name: str, problem: Problem) -> tuple[bool, Failure, str]:
    ok, reason = registry.get(name).availability()
    if not ok:
        pytest.skip(f"{name} unavailable: {reason}")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        result = registry.solve(name, problem, settings_for("mid_accuracy", time_limit=30.0))
    return result.found, Failure(result.failure), result.status


@pytest.mark.parametrize("name", REPORTING)
@pytest.mark.parametrize(("problem", "category"), [(INFEASIBLE, Failure.INFEASIBLE),
                                                   (UNBOUNDED, Failure.UNBOUNDED)],
                         ids=["infeasible", "unbounded"])
def test_a_backend_that_reports_why_says_infeasible_or_unbounded(
        name: str, problem: Problem, category: Failure) -> None:
    found, failure, status = _solve(name, problem)
    assert not found and failure == category, status


@pytest.mark.parametrize("problem", [INFEASIBLE, INCONSISTENT], ids=["infeasible", "equalities"])
def test_quadprog_inconsistent_constraints_are_infeasible(problem: Problem) -> None:
    found, failure, status = _solve("quadprog", problem)
    assert not found and failure == Failure.INFEASIBLE
    assert status == "quadprog: constraints are inconsistent, no solution"


def test_highs_says_infeasible_and_its_optimal_claim_on_an_unbounded_qp_is_no_success() -> None:
    found, failure, status = _solve("highs", INFEASIBLE)
    assert (found, failure, status) == (False, Failure.INFEASIBLE, "HiGHS: Infeasible")
    found, failure, status = _solve("highs", UNBOUNDED)
    assert status.startswith("HiGHS: ")  # its own claim, kept as the status


def test_the_status_probe_passes_the_call_through_and_restores_the_solver() -> None:
    daqp = pytest.importorskip("daqp")
    highspy = pytest.importorskip("highspy")
    from c3bench.solvers.backends._qpsolvers_status import StatusProbe

    solve, had_status = daqp.solve, "getModelStatus" in vars(highspy.Highs)
    H, f = np.eye(2), np.array([1.0, -1.0])
    A, upper = np.ones((1, 2)), np.array([0.5])
    expected = daqp.solve(H, f, A, upper)
    probe = StatusProbe("daqp")
    with probe.watching():
        got = daqp.solve(H, f, A, upper)
    assert np.array_equal(got[0], expected[0]) and got[2] == expected[2] == 1
    assert probe.status(True) == "daqp: optimal (exit flag 1)"
    assert daqp.solve is solve
    with StatusProbe("highs").watching():
        pass
    assert ("getModelStatus" in vars(highspy.Highs)) == had_status
