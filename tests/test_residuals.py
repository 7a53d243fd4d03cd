"""Dual signs in the dual residual (solvers/residuals.py): qpsolvers' convention."""

from __future__ import annotations

import numpy as np
import pytest

from c3bench.problems.instance import Problem
from c3bench.solvers.residuals import (
    dual_residual,
    dual_sign_violation,
    lcp_residual,
    natural_residual,
    residuals,
)


def inequality_qp() -> Problem:
    """``min 1/2 (x1^2 + x2^2) - x1 - x2`` s.t. ``x1 <= 0.5``, ``-x2 <= 5`` (inactive at
    ``x* = (0.5, 1)``); the duals are ``z* = (0.5, 0)``."""
    return Problem(name="ineq", family="c3_qp", P=np.eye(2), q=np.array([-1.0, -1.0]),
                   G=np.array([[1.0, 0.0], [0.0, -1.0]]), h=np.array([0.5, 5.0]))


def test_correct_inequality_duals_pass() -> None:
    problem = inequality_qp()
    x, z = np.array([0.5, 1.0]), np.array([0.5, 0.0])
    figures = residuals(problem, x, z=z)
    assert figures.primal == 0.0 and figures.dual == 0.0 and figures.gap == pytest.approx(0.0)


def test_wrong_signed_inequality_dual_fails_with_stationarity_intact() -> None:
    """Perturb ``x2`` so that stationarity holds with a *negative* multiplier on the
    inactive row ``-x2 <= 5``: ``x = (0.5, 0.5)`` has ``P x + q = (-0.5, -0.5)``, cancelled
    by ``G^T z`` with ``z = (0.5, -0.5)``. Only the sign is wrong, and the dual residual says
    so."""
    problem = inequality_qp()
    x, z = np.array([0.5, 0.5]), np.array([0.5, -0.5])
    gradient = problem.P @ x + problem.q + problem.G.T @ z
    assert np.max(np.abs(gradient)) == 0.0  # stationarity alone would pass
    assert dual_sign_violation(problem, z, None) == pytest.approx(0.5)
    assert dual_residual(problem, x, None, z, None) == pytest.approx(0.5)
    assert residuals(problem, x, z=z).dual_relative == pytest.approx(0.5)
    # the correct sign on the same row costs nothing
    assert dual_sign_violation(problem, np.abs(z), None) == 0.0


def test_box_dual_signs() -> None:
    """``z_box_i < 0`` only on a finite lower bound, ``> 0`` only on a finite upper bound."""
    n = 4
    lb = np.array([0.0, -np.inf, 0.0, -np.inf])
    ub = np.array([np.inf, 1.0, 1.0, np.inf])
    problem = Problem(name="box", family="c3_qp", P=np.eye(n), q=np.zeros(n), lb=lb, ub=ub)
    assert dual_sign_violation(problem, None, np.array([-1.0, 1.0, -1.0, 0.0])) == 0.0
    assert dual_sign_violation(problem, None, np.array([0.0, 1.0, 1.0, 0.0])) == 0.0
    assert dual_sign_violation(problem, None, np.array([2.0, 0.0, 0.0, 0.0])) == 2.0  # no ub
    assert dual_sign_violation(problem, None, np.array([0.0, -3.0, 0.0, 0.0])) == 3.0  # no lb
    assert dual_sign_violation(problem, None, np.array([0.0, 0.0, 0.0, 0.25])) == 0.25  # free
    # stationarity exact (x = 0 has gradient 0 only with z_box = 0), a wrong sign shows up
    x = np.array([0.0, 0.0, 0.0, 0.0])
    q_shift = np.array([-2.0, 0.0, 0.0, 0.0])  # P x + q = (-2, 0, 0, 0) needs z_box_0 = 2 > 0
    shifted = Problem(name="box2", family="c3_qp", P=np.eye(n), q=q_shift, lb=lb, ub=ub)
    assert dual_residual(shifted, x, None, None, np.array([2.0, 0.0, 0.0, 0.0])) == 2.0


def test_lcp_residual_bounds_signs() -> None:
    """Relative natural residual of the ``lcp`` family, as ``complementarity_violation``."""
    problem = Problem(name="lcp", family="lcp", P=np.array([[0.0]]), q=np.array([-1.0]),
                      lb=np.zeros(1))
    assert natural_residual(problem.P, problem.q, np.zeros(1)) == 1.0
    assert lcp_residual(problem, np.zeros(1)) == 1.0
    assert residuals(problem, np.zeros(1), z_box=np.zeros(1)).complementarity == 1.0
    solvable = Problem(name="lcp2", family="lcp", P=np.array([[2.0]]), q=np.array([-4.0]),
                       lb=np.zeros(1))
    assert residuals(solvable, np.array([2.0]), z_box=np.zeros(1)).complementarity == 0.0
    # lam < 0 with w = 0 is caught too
    assert lcp_residual(solvable, np.array([-1.0])) > 0.0
