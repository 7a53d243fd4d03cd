"""Tests of the CVXPY backends (solvers/backends/cvxpy_backend.py).

* ``cvxpy_clarabel`` and ``cvxpy_osqp`` return the closed-form primal and dual solution of a
  tiny QP (an active equality, inequality, upper and lower bound: a sign slip in any dual
  fails), and the quick suite's QP instances to Clarabel's high-accuracy optimum with duals
  that pass the residual module's checks (signs included).
* The parametrized model is compiled once per shape: a second instance of the same shape is a
  cache hit whose answer is the *new* instance's optimum (a stale parameter would fail), an
  instance of another shape compiles again, and an isolated cell's timed repeats reuse the
  model its warm-up compiled.
* ``cvxpy_scip`` (binary big-M) finds the enumerated global optimum of projection and small
  MPCC instances; a big-M constant that cuts the optimum off is never a success.
* A solver CVXPY does not list makes the backend unavailable, with the reason.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from conftest import enumerated_optimum, pick

from c3bench.problems.instance import Problem, load_instances
from c3bench.problems.names import QP_FAMILIES
from c3bench.problems.suites import generate_suite
from c3bench.solvers import registry
from c3bench.solvers.backends import cvxpy_backend
from c3bench.solvers.backends.cvxpy_backend import (
    CvxpyOSQP,
    build_model,
    compilations,
    hessian_factor,
)
from c3bench.solvers.base import Result, settings_for
from c3bench.solvers.isolation import solve_isolated
from c3bench.solvers.residuals import cost_error, dual_sign_violation, residuals

QP_NAMES = ["cvxpy_clarabel", "cvxpy_osqp"]
TOLERANCE = settings_for("mid_accuracy").tolerance
KKT_FACTOR = 10.0
"""Accepted relative residual, in tolerances (the solvers' own criteria use other norms)."""
COST_TOL = 1e-4


def _skip_unless_available(name: str) -> None:
    ok, reason = registry.get(name).availability()
    if not ok:
        pytest.skip(f"{name} unavailable: {reason}")


def tiny_problem() -> Problem:
    """``min 1/2 |z|^2 - z1 - 2 z2 + z4`` s.t. ``z1 + z2 = 1``, ``z3 <= -0.5``,
    ``z1 + z4 <= 5``, ``-10 <= z1``, ``z2 <= 0.2``, ``z4 >= 0``: solution ``(0.8, 0.2, -0.5,
    0)``, ``y = 0.2``, ``z = (0.5, 0)``, ``z_box = (0, 1.6, 0, -1)`` (test_qp_backends.py)."""
    return Problem(
        name="tiny", family="c3_qp", P=np.eye(4), q=np.array([-1.0, -2.0, 0.0, 1.0]),
        A=np.array([[1.0, 1.0, 0.0, 0.0]]), b=np.array([1.0]),
        G=np.array([[0.0, 0.0, 1.0, 0.0], [1.0, 0.0, 0.0, 1.0]]), h=np.array([-0.5, 5.0]),
        lb=np.array([-10.0, -np.inf, -np.inf, 0.0]), ub=np.array([np.inf, 0.2, np.inf, np.inf]))


@pytest.fixture(scope="module")
def quick_qps(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Problem]:
    directory = Path(tmp_path_factory.mktemp("cvxpy_quick"))
    generate_suite("quick", directory, progress=False)
    return {p.name: p for p in load_instances(directory) if p.family in QP_FAMILIES}


@pytest.fixture(scope="module")
def reference_optima(quick_qps: dict[str, Problem]) -> dict[str, float]:
    out = {}
    for name, problem in quick_qps.items():
        result = registry.solve("clarabel", problem, settings_for("high_accuracy"))
        assert result.found and result.objective is not None, (name, result.status)
        out[name] = result.objective
    return out


def _selection(quick_qps: dict[str, Problem]) -> list[Problem]:
    """Two c3plus_qp instances of one shape, one c3_qp and both lcp instances."""
    return [pick(quick_qps, "c3plus_qp-equality-", 0), pick(quick_qps, "c3plus_qp-equality-", 1),
            pick(quick_qps, "c3_qp-equality-", 0), pick(quick_qps, "lcp-", 0),
            pick(quick_qps, "lcp-", 1)]


def _assert_kkt(problem: Problem, result: Result) -> None:
    assert result.x is not None
    figures = residuals(problem, result.x, result.y, result.z, result.z_box)
    for value in (figures.primal_relative, figures.dual_relative, figures.gap_relative):
        assert value <= KKT_FACTOR * TOLERANCE, (result.solver, problem.name, figures)
    assert dual_sign_violation(problem, result.z, result.z_box) <= TOLERANCE


@pytest.mark.parametrize("name", QP_NAMES)
def test_closed_form_solution_and_duals(name: str) -> None:
    _skip_unless_available(name)
    result = registry.solve(name, tiny_problem(), settings_for("high_accuracy"))
    assert result.found and result.failure == "", result.status
    np.testing.assert_allclose(result.x, [0.8, 0.2, -0.5, 0.0], atol=1e-6)
    np.testing.assert_allclose(result.y, [0.2], atol=1e-6)
    np.testing.assert_allclose(result.z, [0.5, 0.0], atol=1e-6)
    np.testing.assert_allclose(result.z_box, [0.0, 1.6, 0.0, -1.0], atol=1e-6)
    assert result.setup_time > 0.0 and result.solve_time > 0.0


@pytest.mark.parametrize("name", QP_NAMES)
def test_quick_instances_match_the_reference(name: str, quick_qps: dict[str, Problem],
                                             reference_optima: dict[str, float]) -> None:
    _skip_unless_available(name)
    for problem in _selection(quick_qps):
        result = registry.solve(name, problem, settings_for("mid_accuracy"))
        assert result.found, (problem.name, result.status)
        assert result.objective is not None
        assert cost_error(result.objective, reference_optima[problem.name]) <= COST_TOL
        _assert_kkt(problem, result)


@pytest.mark.parametrize("name", QP_NAMES)
def test_infeasible_problem_is_a_recorded_failure(name: str) -> None:
    _skip_unless_available(name)
    problem = Problem(name="infeasible", family="c3_qp", P=np.eye(2), q=np.zeros(2),
                      A=np.array([[1.0, 1.0]]), b=np.array([1.0]),
                      G=np.array([[1.0, 1.0]]), h=np.array([0.0]))
    result = registry.solve(name, problem, settings_for("mid_accuracy", time_limit=5.0))
    assert not result.found
    assert result.status and result.failure


def test_model_is_dpp_with_the_factor_of_p(quick_qps: dict[str, Problem]) -> None:
    for problem in (pick(quick_qps, "c3plus_qp-equality-", 0), pick(quick_qps, "lcp-", 0)):
        factor = hessian_factor(problem.P)
        dense = factor.value()
        matrix = dense if isinstance(dense, np.ndarray) else dense.toarray()
        np.testing.assert_allclose(matrix.T @ matrix, problem.P, atol=1e-9 * np.abs(
            problem.P).max())
        # C3 QPs have a diagonal P, the lcp family a dense 6 x 6 one
        assert factor.kind == ("dense" if problem.family == "lcp" else "diagonal")
        assert build_model(problem, factor, integer=False).problem.is_dpp()


def test_second_instance_of_a_shape_reuses_the_compiled_problem(
        quick_qps: dict[str, Problem], reference_optima: dict[str, float]) -> None:
    _skip_unless_available("cvxpy_osqp")
    cvxpy_backend.clear_cache()
    first = pick(quick_qps, "c3plus_qp-equality-", 0)
    second = pick(quick_qps, "c3plus_qp-equality-", 1)
    assert cvxpy_backend.shape_key(first, hessian_factor(first.P), False) == \
        cvxpy_backend.shape_key(second, hessian_factor(second.P), False)
    assert reference_optima[first.name] != pytest.approx(reference_optima[second.name])
    before = compilations("cvxpy_osqp")
    results = [registry.solve("cvxpy_osqp", problem, settings_for("mid_accuracy"))
               for problem in (first, second)]
    assert compilations("cvxpy_osqp") == before + 1
    assert [r.diagnostics["cvxpy_compiled"] for r in results] == [1.0, 0.0]
    for problem, result in zip((first, second), results, strict=True):
        assert result.found and result.objective is not None, result.status
        # the re-solve answers the new parameter values, not the compiled instance's
        assert cost_error(result.objective, reference_optima[problem.name]) <= COST_TOL
        _assert_kkt(problem, result)
    other = registry.solve("cvxpy_osqp", pick(quick_qps, "c3_qp-equality-", 0),
                           settings_for("mid_accuracy"))
    assert other.diagnostics["cvxpy_compiled"] == 1.0
    assert compilations("cvxpy_osqp") == before + 2


def test_large_non_diagonal_p_is_a_constant_of_the_model(
        monkeypatch: pytest.MonkeyPatch, quick_qps: dict[str, Problem],
        reference_optima: dict[str, float]) -> None:
    """Above DENSE_FACTOR_MAX (lowered here to reach the path with the lcp instances) ``P``
    is a constant: each new ``P`` compiles, and the answers stay right."""
    _skip_unless_available("cvxpy_clarabel")
    monkeypatch.setattr(cvxpy_backend, "DENSE_FACTOR_MAX", 2)
    cvxpy_backend.clear_cache()
    first, second = pick(quick_qps, "lcp-", 0), pick(quick_qps, "lcp-", 1)
    assert hessian_factor(first.P).kind == "constant"
    before = compilations("cvxpy_clarabel")
    for problem in (first, second, first):
        result = registry.solve("cvxpy_clarabel", problem, settings_for("mid_accuracy"))
        assert result.found and result.objective is not None, result.status
        assert cost_error(result.objective, reference_optima[problem.name]) <= COST_TOL
        _assert_kkt(problem, result)
    assert compilations("cvxpy_clarabel") == before + 2  # the third solve is a cache hit
    cvxpy_backend.clear_cache()


@pytest.mark.timeout(120)
def test_isolated_repeats_reuse_the_warm_up_compile(quick_qps: dict[str, Problem]) -> None:
    _skip_unless_available("cvxpy_clarabel")
    problem = pick(quick_qps, "c3plus_qp-equality-", 0)
    cold = solve_isolated("cvxpy_clarabel", problem, settings_for("mid_accuracy"))
    warm = solve_isolated("cvxpy_clarabel", problem, settings_for("mid_accuracy"),
                          repeats=3, warmup=True)
    assert cold.found and warm.found, (cold.status, warm.status)
    assert cold.diagnostics["cvxpy_compiled"] == 1.0  # a fresh child compiles
    assert warm.diagnostics["cvxpy_compiled"] == 0.0  # the warm-up compiled, repeats reuse
    assert warm.diagnostics["timed_repeats"] == 3.0


def test_missing_solver_makes_the_backend_unavailable() -> None:
    class Missing(CvxpyOSQP):
        name = "cvxpy_missing"
        solver = "NO_SUCH_SOLVER"

    ok, reason = Missing().availability()
    assert not ok
    assert "NO_SUCH_SOLVER" in reason


# --- cvxpy_scip: binary big-M complementarity ----------------------------------------------


@pytest.mark.timeout(120)
def test_scip_finds_the_enumerated_optimum(quick: dict[str, Problem],
                                           small_mpccs: dict[str, Problem]) -> None:
    _skip_unless_available("cvxpy_scip")
    problems = [pick(quick, "projection-c3plus-", 0), pick(quick, "projection-c3-", 0),
                small_mpccs["h1-0"]]
    for problem in problems:
        result = registry.solve("cvxpy_scip", problem,
                                settings_for("mid_accuracy", time_limit=30.0))
        assert result.found, (problem.name, result.status)
        assert result.objective is not None
        assert cost_error(result.objective, enumerated_optimum(problem)) <= COST_TOL, (
            problem.name, result.objective, enumerated_optimum(problem))
        assert result.diagnostics["big_m"] == cvxpy_backend.BIG_M
        assert result.diagnostics["big_m_ratio"] < cvxpy_backend.BIG_M_ACTIVE


@pytest.mark.timeout(60)
def test_scip_big_m_that_cuts_the_optimum_is_not_a_success(
        quick: dict[str, Problem]) -> None:
    _skip_unless_available("cvxpy_scip")
    problem = pick(quick, "projection-c3plus-", 0)
    result = registry.solve("cvxpy_scip", problem,
                            settings_for("mid_accuracy", time_limit=30.0,
                                         options={"big_m": 0.1}))
    # the optimum has pair members up to ~5: with M = 0.1 the model cannot reach it, and
    # SCIP's answer sits on the big-M bound (polishing may still land on the right mode,
    # but the solve is not a success: it could as well have cut the optimum's mode off)
    assert not result.found, result.status
    assert result.failure
    assert "big-M bound active" in result.status
    assert result.diagnostics["big_m_ratio"] >= cvxpy_backend.BIG_M_ACTIVE
