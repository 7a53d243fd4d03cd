"""MIQP references (SCIP, Gurobi, Bonmin), brute-force mode enumeration and C3+'s closed form."""

from __future__ import annotations

import itertools
import sys

import numpy as np
import pytest
from conftest import enumerated_optimum, pick

from c3bench.problems.errors import BackendUnavailable
from c3bench.problems.instance import Problem
from c3bench.problems.names import Failure
from c3bench.solvers import registry
from c3bench.solvers.backends.gurobi_backend import GurobiMIQP
from c3bench.solvers.base import Settings, settings_for
from c3bench.solvers.isolation import solve_isolated
from c3bench.solvers.modes import enumerate_modes, refine_on_face, search_modes, solve_mode
from c3bench.solvers.projection import c3plus_projection
from c3bench.solvers.residuals import complementarity_violation, cost_error, primal_residual

MID = settings_for("mid_accuracy", time_limit=60.0)




C3 = "projection-c3-s"
C3PLUS = "projection-c3plus-s"
# (name prefix, position among the sorted names): first and last state, both variants
PROJECTIONS = ((C3, 0), (C3, 7), (C3PLUS, 2), (C3PLUS, 5))


# --- mode enumeration -----------------------------------------------------------------------
def _toy(P: np.ndarray, q: np.ndarray, pairs: list[tuple[int, int]], A: np.ndarray | None = None,
         b: np.ndarray | None = None) -> Problem:
    n = q.size
    lb = np.full(n, -np.inf)
    lb[np.array(pairs).ravel()] = 0.0
    return Problem(name="toy", family="projection", P=P, q=q, A=A, b=b, lb=lb,
                   complementarity=np.array(pairs, dtype=np.int64))


def test_enumeration_on_hand_solved_problems() -> None:
    # min (z0 - 1)^2 + (z1 - 2)^2, 0 <= z0 perp z1 >= 0: keep z1 = 2, cost 1.
    toy = _toy(2 * np.eye(2), np.array([-2.0, -4.0]), [(0, 1)])
    x, objective = enumerate_modes(toy)
    np.testing.assert_allclose(x, [0.0, 2.0], atol=1e-8)
    assert objective == pytest.approx(1.0 - 5.0, abs=1e-8)  # no offset: cost - 5
    # with z0 + z1 = 3 and a free z2 = z0 - 1 via equality, cost z2^2 + (z1 - 1)^2:
    # mode z0 = 0 -> z1 = 3, z2 = -1: cost 1 + 4 = 5; mode z1 = 0 -> z0 = 3, z2 = 2: 4 + 1 = 5;
    # make the first cheaper by weighting z1 less.
    P = np.diag([0.0, 1.0, 2.0])
    q = np.array([0.0, -1.0, 0.0])
    A = np.array([[1.0, 1.0, 0.0], [1.0, 0.0, -1.0]])
    b = np.array([3.0, 1.0])
    toy = _toy(P, q, [(0, 1)], A, b)
    x, objective = enumerate_modes(toy)
    # mode z0 = 0: z1 = 3, z2 = -1: 0.5*9 - 3 + 1 = 2.5; mode z1 = 0: z0 = 3, z2 = 2: 4
    np.testing.assert_allclose(x, [0.0, 3.0, -1.0], atol=1e-7)
    assert objective == pytest.approx(2.5, abs=1e-7)


def test_enumeration_skips_infeasible_modes_and_refuses_large(quick: dict[str, Problem]
                                                              ) -> None:
    # z0 + z1 = 1 with z0 fixed at 0 forces z1 = 1; mode z1 = 0 needs z1 = 0 and z0 = 1;
    # add z1 = 1 as well: only the first mode is feasible.
    A = np.array([[1.0, 1.0], [0.0, 1.0]])
    toy = _toy(2 * np.eye(2), np.zeros(2), [(0, 1)], A, np.array([1.0, 1.0]))
    search = search_modes(toy)
    assert (search.modes, search.feasible) == (2, 1)
    np.testing.assert_allclose(search.x, [0.0, 1.0], atol=1e-8)
    infeasible = _toy(2 * np.eye(2), np.zeros(2), [(0, 1)], np.array([[1.0, 1.0]]),
                      np.array([-1.0]))
    assert enumerate_modes(infeasible) == (None, np.inf)
    with pytest.raises(ValueError, match="56 complementarity pairs"):
        enumerate_modes(pick(quick, "mpcc-s", 0))


def test_mode_qp_is_the_exact_optimum_of_its_mode(quick: dict[str, Problem]) -> None:
    problem = pick(quick, C3, 7)
    pairs = problem.complementarity
    solution = solve_mode(problem, pairs[:, 1])
    x = solution.x
    assert x is not None
    assert primal_residual(problem, x) < 1e-8
    assert np.all(x[pairs[:, 1]] == 0)
    # KKT of the mode QP with the active lam bounds: P x + q + A^T y - mu = 0 on the free
    # variables, mu >= 0 where lam = 0; check by a least-squares multiplier fit.
    free = np.setdiff1d(np.arange(problem.n), pairs[:, 1])
    gradient = (problem.P @ x + problem.q)[free]
    active = [k for k, i in enumerate(free) if i in pairs[:, 0] and x[i] < 1e-9]
    columns = [problem.A[:, free].T, -np.eye(free.size)[:, active]]
    multipliers, *_ = np.linalg.lstsq(np.hstack(columns), -gradient, rcond=None)
    # Clarabel's x is accurate to ~1e-9 and P reaches 5e4 (rho_lam = 50 * 2^9)
    scale = float(np.abs(problem.P).max())
    assert np.linalg.norm(np.hstack(columns) @ multipliers + gradient) < 1e-7 * scale
    assert np.all(multipliers[problem.n_eq:] >= -1e-6)


def test_face_refinement_honours_nearly_dependent_rows() -> None:
    # z0 + z1 + z3 = 1 and z0 + (1 + d) z1 + z3 = 1 + d t force z1 = t with sensitivity 1/d;
    # min (z0 - 5)^2 + w (z1 + 3)^2 + (z2 - 1)^2 + z3^2 with 0 <= z1 perp z2 >= 0.
    delta, t, w = 1e-7, 0.3, 1.0
    A = np.array([[1.0, 1.0, 0.0, 1.0], [1.0, 1.0 + delta, 0.0, 1.0]])
    b = np.array([1.0, 1.0 + delta * t])
    P = 2 * np.diag([1.0, w, 1.0, 1.0])
    v = np.array([5.0, -3.0, 1.0, 0.0])
    toy = _toy(P, -P @ v, [(1, 2)], A, b)
    toy.objective_offset = float(v @ P @ v / 2)
    z3 = (1 - t - 5) / 2
    exact = np.array([1 - t - z3, t, 0.0, z3])
    x, objective = enumerate_modes(toy)
    # float64 limit: cond(A) ~ 4e7, so |dz| ~ 1e-8
    np.testing.assert_allclose(x, exact, atol=1e-7)
    assert cost_error(objective, toy.objective(exact)) < 1e-8
    refined = refine_on_face(toy, x + 1e-6 * np.array([1.0, 0.0, 0.0, -1.0]), [2])
    assert refined is not None
    np.testing.assert_allclose(refined, exact, atol=1e-7)
    assert primal_residual(toy, refined) < 1e-12


# --- SCIP, Bonmin, Gurobi against enumeration ----------------------------------------------
def _check_against_enumeration(name: str, problem: Problem, settings: Settings = MID) -> None:
    result = solve_isolated(name, problem, settings)
    assert result.found, result.status
    assert result.y is None and result.z is None
    assert result.diagnostics["big_m"] == 0.0
    assert complementarity_violation(problem, result.x) < 1e-9
    assert primal_residual(problem, result.x) < 1e-6
    assert cost_error(result.objective, enumerated_optimum(problem)) < 1e-6, (
        result.objective, enumerated_optimum(problem))


@pytest.mark.parametrize("instance", PROJECTIONS)
def test_scip_equals_enumeration_on_projections(quick: dict[str, Problem],
                                                instance: tuple[str, int]) -> None:
    _check_against_enumeration("scip", pick(quick, *instance))


@pytest.mark.parametrize("instance", ["h1-0", "h1-1", "h2-0",
                                      "h2-1"])
def test_scip_equals_enumeration_on_small_mpccs(small_mpccs: dict[str, Problem],
                                                instance: str) -> None:
    _check_against_enumeration("scip", small_mpccs[instance])


def test_scip_without_polish_is_close_and_reports_gap(small_mpccs: dict[str, Problem]
                                                      ) -> None:
    problem = small_mpccs["h1-1"]
    result = solve_isolated("scip", problem, MID.with_(options={"polish": False}))
    assert result.found, result.status
    assert "polished" not in result.diagnostics
    assert 0.0 <= result.diagnostics["mip_gap"] <= 1e-6
    assert complementarity_violation(problem, result.x) <= 1e-6
    assert cost_error(result.objective, enumerated_optimum(problem)) < 1e-4
    assert result.diagnostics["dual_bound"] <= enumerated_optimum(problem) * (1 + 1e-6)


@pytest.mark.parametrize("instance", [PROJECTIONS[0], PROJECTIONS[2]])
def test_bonmin_equals_enumeration_on_projections(quick: dict[str, Problem],
                                                  instance: tuple[str, int]) -> None:
    _check_against_enumeration("bonmin", pick(quick, *instance))


@pytest.mark.parametrize("instance", ["h1-0", "h2-1"])
def test_bonmin_equals_enumeration_on_small_mpccs(small_mpccs: dict[str, Problem],
                                                  instance: str) -> None:
    _check_against_enumeration("bonmin", small_mpccs[instance])


def _gurobi_usable() -> bool:
    return GurobiMIQP().availability()[0]


@pytest.mark.skipif(not _gurobi_usable(), reason="gurobipy or its licence is missing")
@pytest.mark.parametrize("instance", ["h1-0", "h2-0", "h2-1"])
def test_gurobi_equals_enumeration(small_mpccs: dict[str, Problem], instance: str) -> None:
    _check_against_enumeration("gurobi", small_mpccs[instance])


@pytest.mark.skipif(not _gurobi_usable(), reason="gurobipy or its licence is missing")
def test_gurobi_reports_the_licence_size_limit() -> None:
    n = 2100  # the pip wheel's licence stops at 2000 variables
    pairs = [(i, i + 1) for i in range(0, 20, 2)]
    big = _toy(np.eye(n), -np.ones(n), pairs)
    result = registry.solve("gurobi", big, MID)
    if result.found:
        pytest.skip("this Gurobi licence is not size-limited")
    assert result.failure == Failure.UNAVAILABLE
    assert result.status.startswith("licence size limit")
    with pytest.raises(BackendUnavailable, match="licence size limit"):
        GurobiMIQP().solve(big, MID)  # raised by the backend, recorded by the registry


def test_gurobi_reports_missing_package(monkeypatch: pytest.MonkeyPatch,
                                        quick: dict[str, Problem]) -> None:
    registry.backends()
    monkeypatch.setitem(sys.modules, "gurobipy", None)  # makes ``import gurobipy`` fail
    monkeypatch.setattr(GurobiMIQP, "_licence", None)
    ok, reason = GurobiMIQP().availability()
    assert not ok and reason.startswith("cannot import gurobipy")
    with pytest.raises(BackendUnavailable):
        GurobiMIQP().require()
    result = solve_isolated("gurobi", pick(quick, *PROJECTIONS[0]), MID)
    assert not result.found and result.failure == Failure.UNAVAILABLE
    assert result.status == reason


def test_registry_lists_the_complementarity_backends() -> None:
    rows = {row.name: row for row in registry.available()}
    for name in ("scip", "gurobi", "bonmin", "c3plus_closed_form"):
        assert name in rows, registry.module_errors()
    assert rows["scip"].available and rows["bonmin"].available
    assert rows["gurobi"].available or rows["gurobi"].reason


# --- the C3+ closed form ------------------------------------------------------------------------
def test_closed_form_matches_two_branch_minimum() -> None:
    rng = np.random.default_rng(3)
    a, b = rng.normal(0, 2, 500), rng.normal(0, 2, 500)
    w_lam, w_eta = rng.uniform(0, 5, 500), rng.uniform(0, 5, 500)
    lam, eta = c3plus_projection(a, b, w_lam, w_eta)
    assert np.all(lam >= 0) and np.all(eta >= 0) and np.all(lam * eta == 0)
    cost = w_lam * (lam - a) ** 2 + w_eta * (eta - b) ** 2
    keep_lam = w_lam * np.minimum(a, 0) ** 2 + w_eta * b**2
    keep_eta = w_lam * a**2 + w_eta * np.minimum(b, 0) ** 2
    np.testing.assert_allclose(cost, np.minimum(keep_lam, keep_eta), rtol=1e-12, atol=1e-12)
    # a grid over the feasible set never beats it
    grid = np.linspace(0, 8, 801)
    for i in range(20):
        on_lam = w_lam[i] * (grid - a[i]) ** 2 + w_eta[i] * b[i] ** 2
        on_eta = w_lam[i] * a[i] ** 2 + w_eta[i] * (grid - b[i]) ** 2
        assert cost[i] <= min(on_lam.min(), on_eta.min()) + 1e-12


def test_closed_form_rule_ties_and_dtype() -> None:
    # weights change the choice: sqrt(4) * 1 = 2 > sqrt(1) * 1.5
    lam, eta = c3plus_projection(np.array([1.0, 1.0]), np.array([1.5, 1.5]),
                                 np.array([4.0, 1.0]), 1.0)
    np.testing.assert_array_equal(lam, [1.0, 0.0])
    np.testing.assert_array_equal(eta, [0.0, 1.5])
    # ties keep lam; negative parts are clipped
    lam, eta = c3plus_projection(np.array([2.0, -1.0, -1.0]), np.array([1.0, -2.0, 3.0]),
                                 np.array([1.0, 1.0, 1.0]), np.array([4.0, 1.0, 1.0]))
    np.testing.assert_array_equal(lam, [2.0, 0.0, 0.0])
    np.testing.assert_array_equal(eta, [0.0, 0.0, 3.0])
    lam32, _ = c3plus_projection(np.ones(3, np.float32), np.zeros(3, np.float32), 1.0, 1.0)
    assert lam32.dtype == np.float32
    with pytest.raises(ValueError):
        c3plus_projection(np.ones(2), np.ones(2), -1.0, 1.0)


@pytest.mark.parametrize("position", [0, 3, 4, 7])
def test_closed_form_equals_scip_and_enumeration(quick: dict[str, Problem], position: int
                                                 ) -> None:
    problem = pick(quick, C3PLUS, position)
    closed = registry.solve("c3plus_closed_form", problem, MID)
    assert closed.found and closed.iterations == 0
    x_enum, f_enum = enumerate_modes(problem)
    scip = solve_isolated("scip", problem, MID)
    assert cost_error(closed.objective, f_enum) < 1e-9
    assert cost_error(scip.objective, f_enum) < 1e-6
    np.testing.assert_allclose(closed.x, x_enum, atol=1e-6)
    np.testing.assert_allclose(closed.x, scip.x, atol=1e-5)


def test_closed_form_rejects_c3_variant(quick: dict[str, Problem]) -> None:
    problem = pick(quick, C3, 0)
    result = solve_isolated("c3plus_closed_form", problem, MID)
    assert result.failure == "unsupported"
    assert "c3plus variant" in result.status and "'c3'" in result.status


def test_closed_form_is_globally_optimal_on_every_pair_mode() -> None:
    """Against all 2^3 modes of a random separable c3plus-like instance."""
    rng = np.random.default_rng(11)
    w = rng.uniform(0.1, 3.0, 8)
    v = rng.normal(0.0, 1.0, 8)
    pairs = [(2, 5), (3, 6), (4, 7)]
    problem = _toy(2 * np.diag(w), -2 * w * v, pairs)
    problem.meta["variant"] = "c3plus"
    problem.objective_offset = float(np.sum(w * v * v))
    closed = registry.solve("c3plus_closed_form", problem, MID)
    best = min(solve_mode(problem, [pair[c] for pair, c in zip(pairs, choice, strict=True)]
                          ).objective
               for choice in itertools.product((0, 1), repeat=3))
    assert closed.objective == pytest.approx(best, rel=1e-9, abs=1e-12)


# --- full horizon (42 pairs) ------------------------------------------------------------------
@pytest.mark.slow
@pytest.mark.parametrize("position", [0, 1])
def test_scip_full_horizon_matches_gurobi(quick: dict[str, Problem], position: int) -> None:
    """SCIP needs minutes here (measured: time limit at 180 s with gap ~2e-4); its polished
    incumbent is compared with Gurobi's proven optimum."""
    if not _gurobi_usable():
        pytest.skip("no Gurobi to compare with")
    problem = pick(quick, "mpcc-s", position)
    gurobi = solve_isolated("gurobi", problem, MID)
    assert gurobi.found, gurobi.status
    scip = solve_isolated("scip", problem, settings_for("default", time_limit=240.0))
    assert scip.x is not None
    assert complementarity_violation(problem, scip.x) < 1e-9
    assert cost_error(scip.objective, gurobi.objective) < 1e-3
