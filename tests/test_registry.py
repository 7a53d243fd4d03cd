"""The guarded solve: every failure path becomes a recorded failure, never an exception."""

from __future__ import annotations

import time

import numpy as np
import pytest

from c3bench.problems.instance import Problem
from c3bench.solvers import registry
from c3bench.solvers.base import Backend, Result, Settings, WarmStart
from c3bench.solvers.residuals import residuals


class DenseKKT(Backend):
    """Test-only equality-QP solver: the KKT system by numpy."""

    name = "test_dense_kkt"
    families = ("c3plus_qp", "c3_qp", "lcp")

    def solve(self, problem: Problem, settings: Settings,
              warm_start: WarmStart | None = None) -> Result:
        n, m = problem.n, problem.n_eq
        kkt = np.block([[problem.P, problem.A.T], [problem.A, np.zeros((m, m))]])
        solution = np.linalg.solve(kkt, np.concatenate([-problem.q, problem.b]))
        return Result(self.name, problem.name, True, "solved", x=solution[:n],
                      y=solution[n:])


class Raises(Backend):
    name = "test_raises"
    families = ("c3plus_qp", "c3_qp", "lcp")

    def solve(self, problem: Problem, settings: Settings,
              warm_start: WarmStart | None = None) -> Result:
        raise RuntimeError("solver exploded")


class Hangs(Backend):
    name = "test_hangs"
    families = ("c3plus_qp", "c3_qp", "lcp")

    def solve(self, problem: Problem, settings: Settings,
              warm_start: WarmStart | None = None) -> Result:
        time.sleep(60)
        raise AssertionError("unreachable")


class ReturnsNaN(Backend):
    name = "test_nan"
    families = ("c3plus_qp", "c3_qp", "lcp")

    def solve(self, problem: Problem, settings: Settings,
              warm_start: WarmStart | None = None) -> Result:
        return Result(self.name, problem.name, True, "solved", x=np.full(problem.n, np.nan))


class Missing(Backend):
    name = "test_missing"
    families = ("c3plus_qp",)
    package = "a_package_that_is_not_installed"


@pytest.fixture(autouse=True)
def fakes(monkeypatch: pytest.MonkeyPatch) -> None:
    registry.backends()  # load the real ones first
    for backend in (DenseKKT(), Raises(), Hangs(), ReturnsNaN(), Missing()):
        monkeypatch.setitem(registry._BACKENDS, backend.name, backend)


def equality_qp(P: np.ndarray | None = None, A: np.ndarray | None = None,
                b: np.ndarray | None = None) -> Problem:
    P = np.diag([2.0, 4.0, 6.0]) if P is None else P
    A = np.array([[1.0, 1.0, 1.0]]) if A is None else A
    b = np.array([1.0]) if b is None else b
    return Problem("eq", "c3_qp", P=P, q=np.array([1.0, 0.0, -1.0]), A=A, b=b)


def test_correct_backend_passes_through() -> None:
    problem = equality_qp()
    for isolate in (True, False):
        result = registry.solve("test_dense_kkt", problem, isolate=isolate)
        assert result.found and result.failure == ""
        figures = residuals(problem, result.x, result.y)
        assert figures.primal < 1e-12 and figures.dual < 1e-12
        assert result.objective == pytest.approx(problem.objective(result.x))


def test_backend_that_raises_is_a_recorded_failure() -> None:
    result = registry.solve("test_raises", equality_qp())
    assert not result.found and result.failure == "error"
    assert "solver exploded" in result.status


def test_backend_that_hangs_is_killed_at_the_time_limit() -> None:
    start = time.perf_counter()
    result = registry.solve("test_hangs", equality_qp(), Settings(time_limit=0.5))
    assert time.perf_counter() - start < 10
    assert not result.found and result.failure == "timeout"
    assert "time limit" in result.status


def test_non_finite_answer_is_rejected() -> None:
    result = registry.solve("test_nan", equality_qp())
    assert not result.found and result.failure == "non_finite"


def test_non_psd_objective_is_invalid_input() -> None:
    result = registry.solve("test_dense_kkt", equality_qp(P=np.diag([1.0, -1.0, 1.0])))
    assert result.failure == "invalid_input" and "positive semi-definite" in result.status


def test_non_finite_data_is_invalid_input() -> None:
    problem = equality_qp()
    problem.P[0, 0] = np.inf  # corrupted after construction
    result = registry.solve("test_dense_kkt", problem)
    assert result.failure == "invalid_input" and "P" in result.status


def test_missing_package_unknown_solver_and_wrong_family() -> None:
    problem = equality_qp()
    result = registry.solve("test_missing", problem)
    assert result.failure == "unavailable" and "a_package_that_is_not_installed" in result.status
    assert registry.solve("no_such_solver", problem).failure == "unavailable"
    mpcc_like = Problem("m", "mpcc", P=np.eye(2), q=np.zeros(2))
    assert registry.solve("test_dense_kkt", mpcc_like).failure == "unsupported"
    assert registry.solve("test_dense_kkt", problem,
                          Settings(precision="float32")).failure == "unsupported"


def test_infeasible_equalities_fail_in_a_real_backend() -> None:
    """Two contradicting rows: a real solver must not claim a solution."""
    problem = equality_qp(A=np.array([[1.0, 1.0, 1.0], [1.0, 1.0, 1.0]]),
                          b=np.array([1.0, 2.0]))
    ran = 0
    for name in ("clarabel", "osqp", "equilibrated_kkt"):
        backend = registry.backends().get(name)
        if backend is None or not backend.availability()[0]:
            continue
        ran += 1
        result = registry.solve(name, problem, Settings(profile="high_accuracy",
                                                        tolerance=1e-9))
        if result.found:
            # a claimed solution must at least be visibly infeasible by residuals
            assert residuals(problem, result.x).primal > 0.1
    if ran == 0:
        pytest.skip("no real equality-QP backend installed in this checkout")


def test_registry_table_lists_real_backends() -> None:
    rows = {row.name: row for row in registry.available()}
    assert rows["test_missing"].available is False
    assert "a_package_that_is_not_installed" in rows["test_missing"].reason
    assert registry.module_errors() == {}


def test_unbounded_problem_is_never_a_success() -> None:
    """min -z_0 with z_0 free (P = 0 on it): every real QP solver must fail or be caught."""
    problem = Problem("unbounded", "lcp", P=np.diag([0.0, 1.0]), q=np.array([-1.0, 0.0]),
                      lb=np.array([-np.inf, 0.0]))
    ran = 0
    for name in ("clarabel", "osqp", "proxqp_dense", "piqp"):
        backend = registry.backends().get(name)
        if backend is None or not backend.availability()[0]:
            continue
        ran += 1
        result = registry.solve(name, problem, Settings(time_limit=5.0))
        if result.found:
            figures = residuals(problem, result.x, result.y, result.z, result.z_box)
            assert figures.dual_relative > 1e-3, name  # the success check rejects it
    if ran == 0:
        pytest.skip("no real QP backend installed in this checkout")
