"""A verdict cannot be bought by a huge answer, nor by impossible timings (bench/rows.py
``fill_row`` and solvers/residuals.py, the path every cell goes through)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from c3bench.bench import store
from c3bench.bench.rows import fill_row, invalid_times
from c3bench.problems.families import lcp_general
from c3bench.problems.instance import Problem
from c3bench.problems.names import Failure
from c3bench.solvers.base import Result
from c3bench.solvers.residuals import lcp_residual, residuals

TOLERANCE = 1e-3


def judged(problem: Problem, result: Result) -> dict:
    row = store.empty_row()
    row.update({"family": problem.family, "tolerance": TOLERANCE, "reference_solver": ""})
    return fill_row(row, problem, result)


def answer(problem: Problem, x: list[float], **duals: np.ndarray) -> dict:
    return judged(problem, Result("liar", problem.name, True, "ok",
                                  x=np.asarray(x, dtype=float), setup_time=0.0,
                                  solve_time=1e-3, **duals))


def infeasible_lp() -> Problem:
    """``x_1 + x_2 <= 0`` and ``x_1 + x_2 >= 1``: no feasible point."""
    return Problem(name="infeasible", family="qp", P=np.zeros((2, 2)), q=np.zeros(2),
                   G=np.array([[1.0, 1.0], [-1.0, -1.0], [1.0, -1.0]]),
                   h=np.array([0.0, -1.0, 0.0]))


def test_huge_answer_to_an_infeasible_qp_is_not_a_success() -> None:
    """``x = (-5e8, 5e8)`` violates ``x_1 + x_2 >= 1`` by 1, which was 1e-9 of ``||G x||``."""
    row = answer(infeasible_lp(), [-5e8, 5e8], z=np.zeros(3))
    assert not row["success"]
    assert row["primal_residual"] == pytest.approx(1.0)
    assert row["primal_residual_relative"] == pytest.approx(1.0)
    assert "primal_residual_relative" in row["verdict"]


def test_huge_wrong_lcp_answers_are_not_successes() -> None:
    """A solvable LCP (solution ``(0.5, 0)``) answered with ``lam = (0, 1e9)``
    (``lam_2 w_2 = 1e9``), and an LCP without a solution answered the same way."""
    solvable = lcp_general("solvable", np.array([[2.0, 1.0], [-1.0, 0.0]]),
                           np.array([-1.0, 1.0]))
    row = answer(solvable, [0.0, 1e9], z_box=np.zeros(2), z=np.zeros(2))
    assert not row["success"] and row["complementarity_violation"] == pytest.approx(1.0)
    assert answer(solvable, [0.5, 0.0], z_box=np.zeros(2), z=np.zeros(2))[
        "complementarity_violation"] == 0.0
    no_solution = lcp_general("none", np.array([[0.0, 1.0], [-1.0, 0.0]]),
                              np.array([-1.0, -1.0]))
    for lam in ([0.0, 1e9], [1e9, 1.0], [1e9, 1e9 + 1.5]):
        assert not answer(no_solution, lam, z_box=np.zeros(2), z=np.zeros(2))["success"]


def test_componentwise_scales_would_not_do() -> None:
    """The infeasible PSD LCP ``F = [[1, -1], [-1, 1]]``, ``q = (1, -2)`` (``w_1 + w_2 = -1``)
    has the answer ``(1e9, 1e9 + 1.5)`` with residual 0.5 in each row, 2.5e-10 of each row's
    ``sum_j |F_ij| lam_j``; relative to the data it is 0.25."""
    problem = lcp_general("psd", np.array([[1.0, -1.0], [-1.0, 1.0]]), np.array([1.0, -2.0]))
    lam = np.array([1e9, 1e9 + 1.5])
    assert lcp_residual(problem, lam) == pytest.approx(0.25)


def test_legitimate_large_solution_keeps_a_small_residual() -> None:
    """A feasible LP whose data are large: the scale is the data, so rounding stays tiny."""
    problem = Problem(name="big", family="qp", P=np.eye(2), q=np.array([-1e6, -1e6]),
                      G=np.array([[1.0, 1.0]]), h=np.array([1e6]))
    x, z = np.array([5e5, 5e5]), np.array([5e5])
    figures = residuals(problem, x, z=z)
    assert figures.primal_relative == 0.0 and figures.dual_relative == 0.0
    row = answer(problem, list(x), z=z)
    assert row["success"], row["verdict"]


@pytest.mark.parametrize("setup,solve", [(-1.0, -1.0), (math.nan, 1e-3), (0.0, math.inf),
                                         (0.0, -1e-9)])
def test_impossible_times_make_a_failed_row(setup: float, solve: float) -> None:
    problem = infeasible_lp()
    feasible = Problem(name="ok", family="qp", P=np.eye(2), q=np.zeros(2))
    row = judged(feasible, Result("liar", problem.name, True, "ok", x=np.zeros(2),
                                  setup_time=setup, solve_time=solve))
    assert not row["found"] and not row["success"]
    assert row["failure"] == Failure.ERROR
    assert "invalid time" in row["status"] and "invalid time" in row["verdict"]


def test_valid_times_are_accepted() -> None:
    assert invalid_times(0.0, 0.0) == ""
    assert invalid_times(1e-6, 2.0) == ""
    assert "setup_time=nan" in invalid_times(math.nan, 0.0)
