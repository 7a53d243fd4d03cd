"""Tests of the convex QP backends (the ``QPBackend`` adapters of solvers/backends/).

* A tiny QP whose primal and dual solution is known in closed form (an active equality, an
  active and an inactive inequality, an active upper and an active lower bound): every
  available backend must return it, duals included, so that a sign slip in any dual
  conversion fails.
* The quick suite's QP-form instances: Clarabel and ProxQP at ``high_accuracy`` agree; every
  backend at ``mid_accuracy`` either passes the success check or records a failure, and the
  check rejects every claimed solution whose cost is wrong.
"""

from __future__ import annotations

import dataclasses
import warnings
from pathlib import Path

import numpy as np
import pytest

from c3bench.problems.instance import Problem, load_instances
from c3bench.problems.names import QP_FAMILIES, Failure, Precision
from c3bench.problems.suites import generate_suite
from c3bench.solvers import registry
from c3bench.solvers.backends._qp_forms import ConeForm, QPBackend, TwoSidedForm
from c3bench.solvers.backends.casadi_conic import OCPRows
from c3bench.solvers.base import Result, WarmStart, settings_for
from c3bench.solvers.isolation import solve_isolated
from c3bench.solvers.residuals import cost_error, dual_residual, duality_gap, primal_residual

QP_BACKENDS: list[QPBackend] = [backend for backend in registry.backends().values()
                                 if isinstance(backend, QPBackend)]
BACKEND_NAMES: list[str] = [backend.name for backend in QP_BACKENDS]

# --- the closed-form QP --------------------------------------------------------------------
# min 1/2 |z|^2 - z1 - 2 z2 + z4  s.t.  z1 + z2 = 1,  z3 <= -0.5,  z1 + z4 <= 5,
#     -10 <= z1,  z2 <= 0.2,  z4 >= 0.
# KKT: z = (0.8, 0.2, -0.5, 0); stationarity z + q + A^T y + G^T z_G + z_box = 0 gives
# y = 1 - z1 = 0.2, z_box2 = 2 - z2 - y = 1.6 (upper bound, positive), z_G1 = -z3 = 0.5,
# z_box4 = -(z4 + 1) = -1 (lower bound, negative); z1 + z4 = 0.8 < 5 and z1 > -10 inactive.
TINY_X = np.array([0.8, 0.2, -0.5, 0.0])
TINY_Y = np.array([0.2])
TINY_Z = np.array([0.5, 0.0])
TINY_Z_BOX = np.array([0.0, 1.6, 0.0, -1.0])


def tiny_problem(family: str = "c3_qp") -> Problem:
    return Problem(
        name="tiny", family=family, P=np.eye(4), q=np.array([-1.0, -2.0, 0.0, 1.0]),
        A=np.array([[1.0, 1.0, 0.0, 0.0]]), b=np.array([1.0]),
        G=np.array([[0.0, 0.0, 1.0, 0.0], [1.0, 0.0, 0.0, 1.0]]), h=np.array([-0.5, 5.0]),
        lb=np.array([-10.0, -np.inf, -np.inf, 0.0]), ub=np.array([np.inf, 0.2, np.inf, np.inf]))


def _skip_unless_available(name: str) -> None:
    ok, reason = registry.get(name).availability()
    if not ok:
        pytest.skip(f"{name} unavailable: {reason}")


def _quiet_solve(name: str, problem: Problem, profile: str, **kwargs: object) -> Result:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return registry.solve(name, problem, settings_for(profile), **kwargs)


@pytest.mark.parametrize("name", BACKEND_NAMES)
def test_closed_form_solution_and_duals(name: str) -> None:
    _skip_unless_available(name)
    result = _quiet_solve(name, tiny_problem(), "high_accuracy")
    assert result.found, result.status
    assert result.failure == ""
    np.testing.assert_allclose(result.x, TINY_X, atol=1e-6)
    np.testing.assert_allclose(result.y, TINY_Y, atol=1e-6)
    np.testing.assert_allclose(result.z, TINY_Z, atol=1e-6)
    np.testing.assert_allclose(result.z_box, TINY_Z_BOX, atol=1e-6)
    assert result.objective == pytest.approx(tiny_problem().objective(TINY_X), abs=1e-6)
    assert result.setup_time >= 0.0 and result.solve_time >= 0.0


def test_closed_form_in_isolated_child() -> None:
    result = solve_isolated("osqp", tiny_problem(), settings_for("high_accuracy"))
    assert result.found, result.status
    np.testing.assert_allclose(result.z_box, TINY_Z_BOX, atol=1e-6)
    np.testing.assert_allclose(result.y, TINY_Y, atol=1e-6)


@pytest.mark.parametrize("name", BACKEND_NAMES)
def test_infeasible_problem_is_a_recorded_failure(name: str) -> None:
    _skip_unless_available(name)
    problem = Problem(name="infeasible", family="c3_qp", P=np.eye(2), q=np.zeros(2),
                      A=np.array([[1.0, 1.0]]), b=np.array([1.0]),
                      G=np.array([[1.0, 1.0]]), h=np.array([0.0]))
    result = registry.solve(name, problem, settings_for("mid_accuracy", time_limit=5.0))
    assert not result.found
    assert result.status and result.failure


def test_quadprog_singular_hessian_fails_with_reason() -> None:
    _skip_unless_available("quadprog")
    problem = Problem(name="singular", family="lcp", P=np.diag([1.0, 0.0]),
                      q=np.array([-1.0, 1.0]), lb=np.zeros(2))
    result = _quiet_solve("quadprog", problem, "mid_accuracy")
    assert not result.found
    assert "positive definite" in result.status


def test_families_and_precision() -> None:
    assert len(QP_BACKENDS) == 12
    for backend in QP_BACKENDS:
        assert backend.families == QP_FAMILIES
        assert backend.precisions == (Precision.FLOAT64,)
    result = registry.solve("osqp", tiny_problem(), settings_for("mid_accuracy",
                                                                 precision="float32"))
    assert result.failure == Failure.UNSUPPORTED


# --- the conversions ----------------------------------------------------------------------


def _random_problem(seed: int = 0) -> Problem:
    rng = np.random.default_rng(seed)
    n = 7
    root = rng.standard_normal((n, n))
    lb = np.where(rng.random(n) < 0.5, -rng.random(n), -np.inf)
    ub = np.where(rng.random(n) < 0.5, rng.random(n), np.inf)
    ub[0], lb[1] = 1.0, -np.inf  # at least one one-sided bound of each kind
    return Problem(name="random", family="c3_qp", P=root @ root.T, q=rng.standard_normal(n),
                   A=rng.standard_normal((2, n)), b=rng.standard_normal(2),
                   G=rng.standard_normal((3, n)), h=rng.standard_normal(3), lb=lb, ub=ub)


def _expected_gradient(problem: Problem, y: np.ndarray, z: np.ndarray,
                       z_box: np.ndarray) -> np.ndarray:
    assert problem.A is not None and problem.G is not None
    return problem.A.T @ y + problem.G.T @ z + z_box


def test_two_sided_form_dual_round_trip() -> None:
    problem = _random_problem()
    form = TwoSidedForm.from_problem(problem)
    rng = np.random.default_rng(1)
    y, z = rng.standard_normal(problem.n_eq), rng.random(problem.n_ineq)
    z_box = np.zeros(problem.n)
    z_box[form.bounded] = rng.standard_normal(form.bounded.size)
    stacked = form.stack_duals(y, z, z_box)
    np.testing.assert_allclose(form.matrix.T @ stacked,
                               _expected_gradient(problem, y, z, z_box), atol=1e-12)
    for got, want in zip(form.split_duals(stacked), (y, z, z_box), strict=True):
        np.testing.assert_allclose(got, want)
    assert np.all(form.lower[: problem.n_eq] == form.upper[: problem.n_eq])
    assert np.all(np.isneginf(form.lower[form.rows("G")]))


def test_cone_form_dual_split() -> None:
    problem = _random_problem()
    form = ConeForm.from_problem(problem)
    rng = np.random.default_rng(2)
    y, z = rng.standard_normal(problem.n_eq), rng.random(problem.n_ineq)
    upper_part, lower_part = rng.random(form.upper_index.size), rng.random(form.lower_index.size)
    cone_dual = np.concatenate([y, z, upper_part, lower_part])
    z_box = np.zeros(problem.n)
    z_box[form.upper_index] += upper_part
    z_box[form.lower_index] -= lower_part
    np.testing.assert_allclose(form.matrix.T @ cone_dual,
                               _expected_gradient(problem, y, z, z_box), atol=1e-12)
    for got, want in zip(form.split_duals(cone_dual), (y, z, z_box), strict=True):
        np.testing.assert_allclose(got, want)
    # a feasible point has nonnegative slacks in every nonnegative row
    x = np.clip(np.zeros(problem.n), problem.lb, problem.ub)
    slack = form.rhs - form.matrix @ x
    assert np.all(slack[problem.n_eq + problem.n_ineq:] >= 0)


# --- the quick suite -----------------------------------------------------------------------


@pytest.fixture(scope="module")
def quick_qps(tmp_path_factory: pytest.TempPathFactory) -> list[Problem]:
    directory = Path(tmp_path_factory.mktemp("quick"))
    generate_suite("quick", directory, progress=False)
    problems = [p for p in load_instances(directory) if p.family in QP_FAMILIES]
    assert {p.family for p in problems} == set(QP_FAMILIES) - {"qp"}  # qp: imported only
    return problems


@pytest.fixture(scope="module")
def references(quick_qps: list[Problem]) -> dict[str, Result]:
    """Clarabel at high accuracy, the reference optimum of every QP instance."""
    out = {}
    for problem in quick_qps:
        result = _quiet_solve("clarabel", problem, "high_accuracy")
        assert result.found, (problem.name, result.status)
        out[problem.name] = result
    return out


def test_ocp_rows_of_horizon_instances(quick_qps: list[Problem]) -> None:
    for problem in quick_qps:
        form = TwoSidedForm.from_problem(problem, bounds_as_rows=False)
        rows = OCPRows.detect(problem, form)
        if "layout" not in problem.meta:
            assert rows is None
            continue
        assert rows is not None, problem.name
        assert sorted(rows.order.tolist()) == list(range(form.n_rows))
        assert sum(rows.nx) + sum(rows.nu) == problem.n
        matrix, lower, upper = rows.apply(form)
        vector = np.random.default_rng(0).standard_normal(form.n_rows)
        np.testing.assert_allclose(rows.restore(rows.permute(vector)), vector)
        # rows.restore maps the multiplier of the permuted rows back:
        # matrix^T lam' == form.matrix^T restore(lam')
        np.testing.assert_allclose(matrix.T @ vector, form.matrix.T @ rows.restore(vector),
                                   atol=1e-9)
        # gap rows carry -I on the next state, stage by stage
        dense, row, column = matrix.toarray(), 0, 0
        for k in range(len(rows.nx) - 1):
            step = rows.nx[k] + rows.nu[k]
            block = dense[row:row + rows.nx[k + 1],
                          column + step:column + step + rows.nx[k + 1]]
            np.testing.assert_allclose(block, -np.eye(rows.nx[k + 1]))
            np.testing.assert_allclose(lower[row:row + rows.nx[k + 1]],
                                       upper[row:row + rows.nx[k + 1]])
            row += rows.nx[k + 1] + rows.ng[k]
            column += step


def test_high_accuracy_references_agree(quick_qps: list[Problem],
                                        references: dict[str, Result]) -> None:
    # Measured on the quick suite (objectives 1e0 .. 3e6, |q| up to 4e5, cond(P) ~ 4e6):
    # cost error Clarabel vs ProxQP <= 9e-14 on the c3 families and 1.5e-10 on lcp (there
    # both stop on an absolute duality gap near 1e-9 and the Hessian is singular, so x is not
    # unique: |x - x'| = 3e-9); primal residuals <= 1.5e-10; |x - x'| <= 6e-11 on c3.
    for problem in quick_qps:
        reference = references[problem.name]
        other = _quiet_solve("proxqp_dense", problem, "high_accuracy")
        assert other.found, (problem.name, other.status)
        assert reference.objective is not None and other.objective is not None
        assert cost_error(other.objective, reference.objective) < 1e-9, problem.name
        assert primal_residual(problem, reference.x) < 1e-8, problem.name
        assert primal_residual(problem, other.x) < 1e-8, problem.name
        if problem.family != "lcp":
            scale = max(1.0, float(np.max(np.abs(reference.x))))
            assert np.max(np.abs(other.x - reference.x)) < 1e-7 * scale, problem.name


# --- the success check ---------------------------------------------------------------------
# The residuals of solvers.residuals are absolute. These instances have gradients of 4e5 and
# objectives up to 3e6, and every solver stops on criteria relative to such scales, so the
# check divides each residual by the scale of its terms (as OSQP's relative criteria do):
#   primal / max(1, |x|, |A x|, |b|, |G x|, |h|),
#   dual   / max(1, |P x|, |q|, |A^T y|, |G^T z|, |z_box|),
#   gap    / max(1, |x'P x|, |q'x|, |b'y|, |h'z|)            (infinity norms),
# and accepts up to KKT_FACTOR times the tolerance: the solvers' own criteria use other norms
# and scalings. Measured at mid_accuracy (1e-6) on the quick suite, the largest relative
# figures of a solution its solver calls solved are 1.2e-6 (primal, QPALM), 2.9e-7 (dual,
# PIQP on lcp), 3.6e-6 (gap, QPALM); the largest cost error 1.6e-5 (QPALM), hence COST_TOL.
# The one garbage answer met (quadprog on an lcp instance, whose Hessian is singular) has a
# relative dual residual of 0.55 and a cost error of 1.8.
KKT_FACTOR = 10.0
COST_TOL = 1e-4
GARBAGE_COST = 1e-2
# (backend, family) where a claimed solution may be rejected by the check: quadprog needs a
# positive definite Hessian and the lcp family's is only semi-definite (smallest eigenvalue
# ~1e-17); its Cholesky can pass on rounding and return a wrong point. QPALM on the bounded
# QP steps (c3_qp- and c3plus_qp-bounded-s012t0-i09) calls solved points whose relative
# duality gap is 1.4e-5 and 1.7e-5 at a 1e-6 tolerance (cost errors 2.6e-5, 3.2e-5): the
# residual check rejects them.
MAY_CLAIM_WRONGLY = {("quadprog", "lcp"), ("qpalm", "c3_qp"), ("qpalm", "c3plus_qp")}


def _norm(vector: np.ndarray) -> float:
    return float(np.max(np.abs(vector), initial=0.0))


def relative_kkt(problem: Problem, result: Result) -> tuple[float, float, float]:
    """Relative primal residual, dual residual and duality gap (see the comment above)."""
    x = np.asarray(result.x, dtype=float)
    y = np.zeros(problem.n_eq) if result.y is None else result.y
    z = np.zeros(problem.n_ineq) if result.z is None else result.z
    z_box = np.zeros(problem.n) if result.z_box is None else result.z_box
    primal_scale, dual_scale = [1.0, _norm(x)], [1.0, _norm(problem.P @ x), _norm(problem.q),
                                                  _norm(z_box)]
    gap_scale = [1.0, abs(float(x @ problem.P @ x)), abs(float(problem.q @ x))]
    if problem.A is not None:
        primal_scale += [_norm(problem.A @ x), _norm(problem.b)]
        dual_scale.append(_norm(problem.A.T @ y))
        gap_scale.append(abs(float(problem.b @ y)))
    if problem.G is not None:
        primal_scale += [_norm(problem.G @ x), _norm(problem.h)]
        dual_scale.append(_norm(problem.G.T @ z))
        gap_scale.append(abs(float(problem.h @ z)))
    return (primal_residual(problem, x) / max(primal_scale),
            dual_residual(problem, x, y, z, z_box) / max(dual_scale),
            duality_gap(problem, x, y, z, z_box) / max(gap_scale))


def residuals_accept(problem: Problem, result: Result, tolerance: float) -> bool:
    """The residual part of the success check."""
    if not result.found or result.x is None or not np.all(np.isfinite(result.x)):
        return False
    if result.y is None and result.z is None and result.z_box is None:
        return False
    relative = relative_kkt(problem, result)
    return all(np.isfinite(value) and value <= KKT_FACTOR * tolerance for value in relative)


def succeeds(problem: Problem, result: Result, reference: float, tolerance: float) -> bool:
    """Success: found, residuals accepted and cost within COST_TOL of the reference."""
    return (residuals_accept(problem, result, tolerance) and result.objective is not None
            and cost_error(result.objective, reference) <= COST_TOL)


def test_success_check_rejects_garbage(quick_qps: list[Problem],
                                       references: dict[str, Result]) -> None:
    tolerance = settings_for("mid_accuracy").tolerance
    problem = next(p for p in quick_qps if p.family == "c3plus_qp")
    reference = references[problem.name]
    assert reference.objective is not None and problem.A is not None
    assert succeeds(problem, reference, reference.objective, tolerance)
    # a feasible but suboptimal point (moved in the null space of A), reference duals kept
    _, _, vt = np.linalg.svd(problem.A)
    direction = vt[-1]
    step = 1.0
    while cost_error(problem.objective(reference.x + step * direction),
                     reference.objective) < GARBAGE_COST:
        step *= 2.0
    moved = dataclasses.replace(reference, x=reference.x + step * direction,
                                objective=problem.objective(reference.x + step * direction))
    assert primal_residual(problem, moved.x) < 1e-8
    assert not residuals_accept(problem, moved, tolerance)
    # the right point with the equality duals' sign flipped
    flipped = dataclasses.replace(reference, y=-np.asarray(reference.y))
    assert not residuals_accept(problem, flipped, tolerance)
    # no duals at all cannot pass
    assert not residuals_accept(problem, dataclasses.replace(reference, y=None, z=None,
                                                             z_box=None), tolerance)


def test_every_backend_succeeds_or_records_failure(quick_qps: list[Problem],
                                                   references: dict[str, Result]) -> None:
    tolerance = settings_for("mid_accuracy").tolerance
    problems = list(quick_qps)
    outcomes: list[str] = []
    for name in BACKEND_NAMES:
        if not registry.get(name).availability()[0]:
            continue
        for problem in problems:
            reference = references[problem.name].objective
            assert reference is not None
            result = _quiet_solve(name, problem, "mid_accuracy")
            error = (cost_error(result.objective, reference) if result.objective is not None
                     else float("inf"))
            if result.found and error > GARBAGE_COST:
                # garbage must never get past the residuals
                assert not residuals_accept(problem, result, tolerance), (
                    name, problem.name, error, relative_kkt(problem, result))
            if succeeds(problem, result, reference, tolerance):
                outcomes.append(f"{name}/{problem.name}: success")
                continue
            if not result.found:
                assert result.status and result.failure, (name, problem.name)
                outcomes.append(f"{name}/{problem.name}: failure ({result.status})")
                continue
            assert (name, problem.family) in MAY_CLAIM_WRONGLY, (
                name, problem.name, result.status, error, relative_kkt(problem, result))
            assert not residuals_accept(problem, result, tolerance), (name, problem.name)
            outcomes.append(f"{name}/{problem.name}: claimed, rejected by the residuals")
    assert outcomes


@pytest.mark.parametrize("name", ["osqp", "proxqp_dense", "proxqp_sparse", "casadi_hpipm"])
def test_warm_start_from_the_solution(name: str, quick_qps: list[Problem],
                                      references: dict[str, Result]) -> None:
    _skip_unless_available(name)
    problem = next(p for p in quick_qps if p.family == "c3plus_qp")
    reference = references[problem.name]
    assert reference.objective is not None
    # from the solver's own answer, box duals included (the adapter passes x, y, z, z_box):
    # it should stop at once. (From Clarabel's high-accuracy answer ProxQP needs 14-33
    # iterations on the bounded quick instances, more than cold: the points differ by ~3e-7
    # in x on a QP whose duals reach 3e5, and its proximal scheme restarts from its defaults.)
    cold = _quiet_solve(name, problem, "mid_accuracy")
    warm = _quiet_solve(name, problem, "mid_accuracy",
                        warm_start=WarmStart(cold.x, cold.y, cold.z, cold.z_box))
    assert cold.found and warm.found, (cold.status, warm.status)
    assert warm.iterations is not None and cold.iterations is not None
    if name == "casadi_hpipm":  # an interior-point method gains nothing from a warm start
        assert warm.iterations <= cold.iterations
    else:
        assert warm.iterations <= max(2, cold.iterations // 2), (warm.iterations,
                                                                 cold.iterations)
    assert warm.objective is not None
    assert cost_error(warm.objective, reference.objective) <= COST_TOL


def test_hpipm_uses_the_horizon_stages(quick_qps: list[Problem]) -> None:
    _skip_unless_available("casadi_hpipm")
    problem = next(p for p in quick_qps if p.family == "c3_qp")
    result = _quiet_solve("casadi_hpipm", problem, "mid_accuracy")
    assert result.found, result.status
    horizon = int(problem.meta["layout"]["horizon"])
    assert result.diagnostics["ocp_stages"] == horizon + 1
