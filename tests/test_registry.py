"""The guarded solve: every failure path becomes a recorded failure, never an exception, in
this process (``registry.solve``) and in an isolated child (``isolation.solve_isolated``)."""

from __future__ import annotations

import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from c3bench.problems.errors import BackendUnavailable
from c3bench.problems.instance import Problem
from c3bench.problems.names import Failure
from c3bench.solvers import registry
from c3bench.solvers.base import Backend, Result, Settings, WarmStart
from c3bench.solvers.isolation import solve_isolated
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


class BrokenAccepts(DenseKKT):
    """Its ``accepts`` raises: an explicit failure, never a silently missing cell."""

    name = "test_broken_accepts"

    def accepts(self, problem: Problem) -> tuple[bool, str]:
        raise KeyError("meta has no 'variant'")


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


class NoLicence(Backend):
    """Installed, but finds out only while solving that it cannot run (a licence limit)."""

    name = "test_no_licence"
    families = ("c3plus_qp", "c3_qp", "lcp")

    def solve(self, problem: Problem, settings: Settings,
              warm_start: WarmStart | None = None) -> Result:
        raise BackendUnavailable("licence size limit: model too large")


class NoPlugin(Backend):
    """Its package imports, its plugin does not: ``require`` says so."""

    name = "test_no_plugin"
    families = ("c3plus_qp",)
    package = "numpy"

    def require(self) -> None:
        super().require()
        raise BackendUnavailable("numpy was built without the frobnicate plugin")


@pytest.fixture(autouse=True)
def fakes(monkeypatch: pytest.MonkeyPatch) -> None:
    registry.backends()  # load the real ones first
    for backend in (DenseKKT(), Raises(), Hangs(), ReturnsNaN(), Missing(), NoLicence(),
                    NoPlugin(), BrokenAccepts()):
        monkeypatch.setitem(registry._BACKENDS, backend.name, backend)


def equality_qp(P: np.ndarray | None = None, A: np.ndarray | None = None,
                b: np.ndarray | None = None) -> Problem:
    P = np.diag([2.0, 4.0, 6.0]) if P is None else P
    A = np.array([[1.0, 1.0, 1.0]]) if A is None else A
    b = np.array([1.0]) if b is None else b
    return Problem("eq", "c3_qp", P=P, q=np.array([1.0, 0.0, -1.0]), A=A, b=b)


SOLVES = (registry.solve, solve_isolated)
"""In this process, and in an isolated child: the same guard, the same answers."""


@pytest.mark.parametrize("solve", SOLVES)
def test_correct_backend_passes_through(solve: Callable[..., Result]) -> None:
    problem = equality_qp()
    result = solve("test_dense_kkt", problem)
    assert result.found and result.failure == ""
    figures = residuals(problem, result.x, result.y)
    assert figures.primal < 1e-12 and figures.dual < 1e-12
    assert result.objective == pytest.approx(problem.objective(result.x))


@pytest.mark.parametrize("solve", SOLVES)
def test_backend_that_raises_is_a_recorded_failure(solve: Callable[..., Result]) -> None:
    result = solve("test_raises", equality_qp())
    assert not result.found and result.failure == "error"
    assert result.status.startswith("RuntimeError: solver exploded")
    assert "test_registry.py" in result.status  # where it was raised


@pytest.mark.timeout(60)
def test_backend_that_hangs_is_killed_at_the_time_limit() -> None:
    start = time.perf_counter()
    result = solve_isolated("test_hangs", equality_qp(), Settings(time_limit=0.5))
    assert time.perf_counter() - start < 10
    assert not result.found and result.failure == "timeout"
    assert "time limit" in result.status


@pytest.mark.parametrize("solve", SOLVES)
def test_non_finite_answer_is_rejected(solve: Callable[..., Result]) -> None:
    result = solve("test_nan", equality_qp())
    assert not result.found and result.failure == "non_finite"


@pytest.mark.parametrize("solve", SOLVES)
def test_an_accepts_that_raises_is_an_error_row(solve: Callable[..., Result]) -> None:
    result = solve("test_broken_accepts", equality_qp())
    assert result.failure == Failure.ERROR
    assert result.status == "accepts() raised KeyError: \"meta has no 'variant'\""


def test_an_accepts_that_raises_still_plans_its_cells() -> None:
    """Planning keeps the cell, so the run stores the error instead of dropping it."""
    from c3bench.bench.planning import plan_cells  # here: isolated children import this file

    plan = plan_cells([equality_qp()], ["test_broken_accepts", "test_dense_kkt"],
                      ["default"], ["float64"], ["cold"], {})
    assert sorted(cell.solver for cell in plan.cells) == ["test_broken_accepts",
                                                          "test_dense_kkt"]


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
        result = solve_isolated(name, problem, Settings(profile="high_accuracy",
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
        result = solve_isolated(name, problem, Settings(time_limit=5.0))
        if result.found:
            figures = residuals(problem, result.x, result.y, result.z, result.z_box)
            assert figures.dual_relative > 1e-3, name  # the success check rejects it
    if ran == 0:
        pytest.skip("no real QP backend installed in this checkout")


def test_backend_unavailable_is_an_unavailable_row() -> None:
    problem = equality_qp()
    for solve in SOLVES:
        result = solve("test_no_licence", problem)
        assert not result.found and result.failure == Failure.UNAVAILABLE
        assert result.status == "licence size limit: model too large"
    result = registry.solve("test_no_plugin", problem)
    assert result.failure == Failure.UNAVAILABLE and "frobnicate" in result.status
    rows = {row.name: row for row in registry.available()}
    assert not rows["test_no_plugin"].available and "frobnicate" in rows["test_no_plugin"].reason
    assert rows["test_no_licence"].available


def test_backend_modules_are_discovered() -> None:
    """Every non-helper module of the backends package is imported; helpers (``_name``) are
    not listed, and every real backend comes from a listed module."""
    modules = registry.backend_modules()
    short = {name.rsplit(".", 1)[1] for name in modules}
    assert {"osqp_backend", "kkt", "lcp", "c3_admm", "c3plus_riccati"} <= short
    assert not any(name.startswith("_") for name in short)
    fakes = {"test_dense_kkt", "test_raises", "test_hangs", "test_nan", "test_missing",
             "test_no_licence", "test_no_plugin", "test_broken_accepts"}
    for name, backend in registry.backends().items():
        if name not in fakes:
            assert type(backend).__module__ in modules, (name, type(backend).__module__)


def test_a_module_that_fails_to_import_is_recorded(tmp_path: Path,
                                                   monkeypatch: pytest.MonkeyPatch) -> None:
    package = tmp_path / "fake_backends"
    package.mkdir()
    (package / "__init__.py").write_text("")
    (package / "_helper.py").write_text("raise RuntimeError('helpers are never imported')\n")
    (package / "broken.py").write_text("import a_package_that_is_not_installed\n")
    (package / "good.py").write_text(
        "from c3bench.solvers.base import Backend\n"
        "from c3bench.solvers.registry import register\n"
        "class Good(Backend):\n"
        "    name = 'test_discovered'\n"
        "register(Good())\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setattr(registry, "BACKEND_PACKAGE", "fake_backends")
    monkeypatch.setattr(registry, "_LOADED", False)
    monkeypatch.setattr(registry, "_MODULE_ERRORS", {})
    monkeypatch.setattr(registry, "_BACKENDS", {})
    for name in ("fake_backends", "fake_backends.good", "fake_backends.broken"):
        monkeypatch.delitem(sys.modules, name, raising=False)
    assert registry.backend_modules() == ("fake_backends.broken", "fake_backends.good")
    assert list(registry.backends()) == ["test_discovered"]
    errors = registry.module_errors()
    assert list(errors) == ["fake_backends.broken"]
    assert "a_package_that_is_not_installed" in errors["fake_backends.broken"]
