"""IPOPT on the complementarity families: Scholtes relaxation and penalty, against enumeration."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import enumerated_optimum, pick

from c3bench.problems.instance import Problem
from c3bench.solvers import registry
from c3bench.solvers.base import settings_for
from c3bench.solvers.isolation import solve_isolated
from c3bench.solvers.residuals import complementarity_violation, primal_residual

MID = settings_for("mid_accuracy", time_limit=60.0)




def _check_local_solution(name: str, problem: Problem) -> float:
    """Found, complementary, feasible, and not below the global optimum; returns the
    relative excess over the optimum."""
    result = solve_isolated(name, problem, MID)
    assert result.found, result.status
    assert complementarity_violation(problem, result.x) <= 1e-6
    scale = 1.0 if problem.b is None else max(1.0, float(np.abs(problem.b).max()))
    assert primal_residual(problem, result.x) <= 1e-6 * scale
    assert result.objective == pytest.approx(problem.objective(result.x))
    best = enumerated_optimum(problem)
    excess = (result.objective - best) / max(1.0, abs(best))
    assert excess >= -1e-6, (result.objective, best)
    return excess


@pytest.mark.parametrize("name", ["ipopt_scholtes", "ipopt_penalty"])
@pytest.mark.parametrize("instance", [("projection-c3-s", 0), ("projection-c3-s", 7),
                                      ("projection-c3plus-s", 2)])
def test_ipopt_projection_is_feasible_and_not_below_optimum(quick: dict[str, Problem],
                                                            name: str,
                                                            instance: tuple[str, int]) -> None:
    _check_local_solution(name, pick(quick, *instance))


@pytest.mark.parametrize("name", ["ipopt_scholtes", "ipopt_penalty"])
@pytest.mark.parametrize("instance", ["h1-0", "h1-1", "h2-1"])
def test_ipopt_small_mpcc_is_feasible_and_not_below_optimum(small_mpccs: dict[str, Problem],
                                                            name: str, instance: str) -> None:
    _check_local_solution(name, small_mpccs[instance])


def test_ipopt_finds_the_global_optimum_of_the_c3plus_projection(quick: dict[str, Problem]
                                                                 ) -> None:
    # separable pairs: every local minimum of a pair is a branch minimum; starting from 0
    # IPOPT reaches the better one on this instance (checked against enumeration)
    assert _check_local_solution("ipopt_scholtes", pick(quick, "projection-c3plus-s", 5)
                                 ) < 1e-8


def test_scholtes_trace_drives_eps_down(small_mpccs: dict[str, Problem]) -> None:
    problem = small_mpccs["h1-0"]
    result = solve_isolated("ipopt_scholtes", problem, MID)
    eps = result.trace["eps"]
    np.testing.assert_allclose(eps, 0.1 * 0.1 ** np.arange(len(eps)), rtol=1e-12)
    assert eps[-1] == pytest.approx(1e-8)
    # the relaxation bounds products by eps, so min(z_i, z_j) <= sqrt(eps) (+ IPOPT's tol)
    for value, violation in zip(eps, result.trace["complementarity"], strict=True):
        assert violation <= np.sqrt(value) * 1.01 + 1e-6
    assert len(result.trace["objective"]) == len(eps)
    assert result.diagnostics["polished"] == 1.0
    assert result.diagnostics["final_complementarity"] <= 1e-8


def test_penalty_trace_raises_rho_until_complementary(small_mpccs: dict[str, Problem]
                                                      ) -> None:
    problem = small_mpccs["h2-1"]
    result = solve_isolated("ipopt_penalty", problem,
                            MID.with_(options={"rho0": 1e-2, "polish": False}))
    rho = result.trace["rho"]
    np.testing.assert_allclose(rho, 1e-2 * 10.0 ** np.arange(len(rho)))
    assert len(rho) >= 2  # rho = 1e-2 is too weak to enforce complementarity here
    assert result.trace["complementarity"][0] > 1e-6
    assert result.trace["complementarity"][-1] <= 1e-6
    assert result.found


def test_unfinished_relaxation_is_not_reported_found(small_mpccs: dict[str, Problem]) -> None:
    problem = small_mpccs["h1-0"]
    settings = MID.with_(options={"eps0": 1.0, "eps_min": 1.0, "polish": False})
    result = solve_isolated("ipopt_scholtes", problem, settings)
    assert result.trace["eps"] == [1.0]
    violation = complementarity_violation(problem, result.x)
    assert violation > 1e-6
    assert not result.found
    assert "complementarity" in result.status


def test_nlp_backends_are_registered() -> None:
    rows = {row.name: row for row in registry.available()}
    for name in ("ipopt_scholtes", "ipopt_penalty"):
        assert rows[name].available, (rows[name].reason, registry.module_errors())
        assert set(rows[name].families) == {"projection", "mpcc"}
