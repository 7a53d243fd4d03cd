"""The qpsolvers-driven adapters pay what the solver pays, no more: quadprog gets only the
finite bounds as rows (with duals mapped back in qpsolvers' signs), DAQP's and SCS's own setup
is booked as setup, a dropped initial guess is said, and ProxQP's dense form is built dense."""

from __future__ import annotations

import warnings
from types import SimpleNamespace

import numpy as np
import pytest

from c3bench.problems.importers import QPSOLVERS_KEYS, qp_problem
from c3bench.problems.instance import Problem
from c3bench.solvers import registry
from c3bench.solvers.backends._qp_forms import ConeForm, TwoSidedForm
from c3bench.solvers.backends._qpsolvers_status import StatusProbe
from c3bench.solvers.backends.qpsolvers_backends import _inner_solve_time
from c3bench.solvers.base import settings_for
from c3bench.solvers.timing import warm_support


def _qp(**arrays: np.ndarray) -> Problem:
    return qp_problem("adapter", {key: arrays.get(key) for key in QPSOLVERS_KEYS}, "test")


# min ||x - c||^2 / 2 with 0 <= x_0, x_1 <= 1, x_2 free, x_0 + x_2 <= 1: the answer sits on
# the lower bound of x_0, the upper bound of x_1 and the inequality.
BOUNDED = _qp(P=np.eye(3), q=-np.array([-1.0, 2.0, 3.0]), G=np.array([[1.0, 0.0, 1.0]]),
              h=np.array([1.0]), lb=np.array([0.0, -np.inf, -np.inf]),
              ub=np.array([np.inf, 1.0, np.inf]))


def test_bound_rows_are_the_finite_bounds_only() -> None:
    rows = ConeForm.from_problem(BOUNDED, dense=True)  # what quadprog is given
    G, h = rows.matrix[rows.n_eq:], rows.rhs[rows.n_eq:]
    assert G.shape == (3, 3) and rows.upper_index.tolist() == [1]
    assert rows.lower_index.tolist() == [0]
    np.testing.assert_array_equal(h, [1.0, 1.0, -0.0])
    np.testing.assert_array_equal(G, ConeForm.from_problem(BOUNDED).matrix.toarray())
    _, z, z_box = rows.split_duals(np.array([0.5, 2.0, 3.0]))
    np.testing.assert_array_equal(z, [0.5])
    np.testing.assert_array_equal(z_box, [-3.0, 2.0, 0.0])  # lower: negative, upper: positive


def test_quadprog_answer_and_duals_match_a_solver_taking_bounds_natively() -> None:
    for name in ("quadprog", "clarabel"):
        ok, reason = registry.get(name).availability()
        if not ok:
            pytest.skip(f"{name} unavailable: {reason}")
    settings = settings_for("high_accuracy", time_limit=30.0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ours = registry.solve("quadprog", BOUNDED, settings)
        native = registry.solve("clarabel", BOUNDED, settings)
    assert ours.found and native.found
    np.testing.assert_allclose(ours.x, native.x, atol=1e-7)
    np.testing.assert_allclose(ours.z, native.z, atol=1e-6)
    np.testing.assert_allclose(ours.z_box, native.z_box, atol=1e-6)
    assert ours.z_box[0] < -0.5 and ours.z_box[1] > 0.5  # active lower and upper bounds


def test_the_solvers_own_setup_is_setup() -> None:
    probe = StatusProbe("daqp")
    probe.last = ((), (None, 0.0, 1, {"setup_time": 9e-4, "solve_time": 1e-4,
                                      "iterations": 3}))
    call = SimpleNamespace(solve_time=1e-3)  # qpsolvers' time of the whole daqp.solve
    assert _inner_solve_time("daqp", call, {}, probe) == pytest.approx(1e-4)
    assert _inner_solve_time("scs", call, {"solve_time": 0.4, "setup_time": 1.6},
                             StatusProbe("scs")) == pytest.approx(4e-4)  # SCS: milliseconds
    assert _inner_solve_time("qpalm", call, {}, StatusProbe("qpalm")) == 1e-3


@pytest.mark.parametrize("name", ["quadprog", "highs", "qpalm", "casadi_qpoases"])
def test_a_warm_cell_whose_guess_is_dropped_says_it_is_a_cold_solve(name: str) -> None:
    assert "cold solve" in warm_support(registry.get(name))


def test_the_dense_two_sided_form_is_the_sparse_one() -> None:
    sparse = TwoSidedForm.from_problem(BOUNDED)
    dense = TwoSidedForm.from_problem(BOUNDED, dense=True)
    assert isinstance(dense.matrix, np.ndarray)
    np.testing.assert_array_equal(dense.matrix, sparse.matrix.toarray())
    np.testing.assert_array_equal(dense.lower, sparse.lower)
    np.testing.assert_array_equal(dense.upper, sparse.upper)
