"""What every C3 / C3+ kernel accepts, alike: zero consensus weights on ``x`` and ``u`` (the C3
paper's zero ``G`` block on ``u``) give the same control step in the reference kernel as in the
batched ones; an LCS without a contact pair or an input, or an ``x0`` of the wrong size, is one
:class:`InputError` from every kernel."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import random_lcs_problem

from c3bench.problems.errors import InputError
from c3bench.problems.lcs import LCSBatch
from c3bench.solvers.admm import C3Options, solve_c3
from c3bench.solvers.admm.compiled_solver import CompiledC3Plus
from c3bench.solvers.fast import FastC3Plus


@pytest.mark.parametrize("block", ["x", "u"])
def test_a_zero_consensus_weight_gives_one_answer_in_every_kernel(block: str) -> None:
    mpc, batch, x0 = random_lcs_problem(1, seed=11)
    rho0 = {"x": 1.0, "lam": 50.0, "u": 1.0, "eta": 50.0, block: 0.0}
    reference = solve_c3(batch.sample(0), mpc, x0,
                         C3Options(keep_iterates=False, rho0=rho0, qp_backend="clarabel",
                                   qp_settings="high_accuracy"))
    options = C3Options(keep_iterates=False, rho0=rho0)
    assert reference.ok, reference.status
    for solver in (FastC3Plus(mpc, options), CompiledC3Plus(mpc, options)):
        step = solver.solve(batch, x0)
        assert step.ok, step.status
        np.testing.assert_allclose(step.u, reference.u, rtol=1e-7, atol=1e-9)


def _without(batch: LCSBatch, what: str) -> LCSBatch:
    arrays = {name: getattr(batch, name) for name in "ABDdEFHc"}
    if what == "lam":
        n, nx, nu = batch.B.shape
        arrays.update(D=np.zeros((n, nx, 0)), E=np.zeros((n, 0, nx)), F=np.zeros((n, 0, 0)),
                      H=np.zeros((n, 0, nu)), c=np.zeros((n, 0)))
    else:
        n, nx, _ = batch.B.shape
        arrays.update(B=np.zeros((n, nx, 0)), H=np.zeros((n, batch.F.shape[1], 0)))
    return LCSBatch(dt=batch.dt, **arrays)


@pytest.mark.parametrize(("what", "message"), [("lam", "no complementarity pair"),
                                               ("u", "no input")])
def test_an_lcs_without_contacts_or_inputs_is_one_input_error(what: str, message: str) -> None:
    mpc, batch, x0 = random_lcs_problem(1, seed=12)
    lcs = _without(batch, what)
    with pytest.raises(InputError, match=message):
        solve_c3(lcs.sample(0), mpc, x0, C3Options(keep_iterates=False))
    for solver in (FastC3Plus(mpc, C3Options(keep_iterates=False)),
                   CompiledC3Plus(mpc, C3Options(keep_iterates=False))):
        with pytest.raises(InputError, match=message):
            solver.solve(lcs, x0)


def test_x0_of_the_wrong_size_is_one_input_error_from_the_reference_kernel() -> None:
    mpc, batch, x0 = random_lcs_problem(1, seed=13)
    with pytest.raises(InputError, match=r"x0 must have shape \(4,\)"):
        solve_c3(batch.sample(0), mpc, x0[:2], C3Options(keep_iterates=False))


def test_qp_settings_take_a_profile_name_and_refuse_anything_else() -> None:
    assert C3Options(qp_settings="high_accuracy").qp_settings.tolerance == 1e-9
    with pytest.raises(ValueError, match="qp_settings: profile must be one of"):
        C3Options(qp_settings="bogus")
    with pytest.raises(ValueError, match="projection_settings must be a Settings"):
        C3Options(projection_settings=3)  # type: ignore[arg-type]


# --- sample weights and warm starts ------------------------------------------------------------
def test_weights_are_floored_relative_to_the_largest_and_sum_to_one() -> None:
    """``p_j = max(a_j, f max a) / sum_i max(a_i, f max a)``, checked in exact rational
    arithmetic; scaling every weight changes nothing; ``None`` is uniform."""
    from fractions import Fraction

    from c3bench.solvers.admm.loop import normalise_weights

    rng = np.random.default_rng(4)
    for trial in range(20):
        raw = rng.random(int(rng.integers(1, 40))) ** 8  # many far below the largest
        raw[rng.random(raw.size) < 0.2] = 0.0
        raw[int(rng.integers(raw.size))] = 1.0 + trial
        floor = 1e-3
        p = normalise_weights(raw.tolist(), raw.size, floor)
        bound = Fraction(floor) * Fraction(float(raw.max()))
        floored = [max(Fraction(float(a)), bound) for a in raw]  # max(a, f max a), exact
        exact = [float(value / sum(floored)) for value in floored]
        np.testing.assert_allclose(p, exact, rtol=1e-14, atol=0)  # the sum: n roundings
        assert abs(p.sum() - 1) < 1e-14 and p.min() >= floor * p.max() * (1 - 1e-15)
        np.testing.assert_allclose(normalise_weights(raw * 1e-7, raw.size, floor), p,
                                   rtol=1e-14)
    np.testing.assert_array_equal(normalise_weights(None, 4), np.full(4, 0.25))
    # extremes: the floor of a tiny largest weight does not underflow, huge weights do not
    # overflow the sum
    np.testing.assert_allclose(normalise_weights([1e-320, 0.0], 2, 1e-6),
                               np.array([1.0, 1e-6]) / (1 + 1e-6), rtol=1e-15)
    np.testing.assert_allclose(normalise_weights([1e308] * 3, 3), np.full(3, 1 / 3),
                               rtol=1e-15)


@pytest.mark.parametrize("weights", [[1.0, -0.5], [1.0, np.nan], [1.0, np.inf], [0.0, 0.0],
                                     [1.0, 2.0, 3.0], ["a", "b"]])
def test_bad_weights_are_one_input_error(weights: list[object]) -> None:
    from c3bench.solvers.admm.loop import normalise_weights

    with pytest.raises(InputError, match="weights"):
        normalise_weights(weights, 2)


def test_a_controllers_own_warm_start_is_used_as_it_is_and_gives_the_checked_answer() -> None:
    """The controller hands its shifted iterates over unchecked (``trusted_iterates``); the
    same arrays handed over by a caller are checked, and the step is the same."""
    from c3bench.solvers.admm.loop import initial_iterates
    from c3bench.solvers.fast import FastC3PlusController

    mpc, batch, x0 = random_lcs_problem(3, seed=5)
    options = C3Options(keep_iterates=False)
    for solver in (FastC3Plus(mpc, options), CompiledC3Plus(mpc, options),
                   CompiledC3Plus(mpc, options, precision="float32")):
        controller = FastC3PlusController(solver)
        controller.step(batch, x0)
        delta, w = controller.warm(controller.delta.shape)
        assert delta is not None and w is not None
        layout = solver.layout
        given = initial_iterates(layout, x0, 3, delta, w, solver.dtype, trusted=True)
        assert given[0] is delta and given[1] is w
        checked = solver.solve(batch, x0, None, delta, w)
        warm = controller.step(batch, x0)
        assert warm.ok and checked.ok
        np.testing.assert_array_equal(warm.u, checked.u)
        np.testing.assert_array_equal(warm.delta, checked.delta)
        bad = delta.copy()
        bad[0, 0, 0] = np.nan
        with pytest.raises(InputError, match="delta has non-finite entries"):
            solver.solve(batch, x0, None, bad, w)
        # trusted or not, iterates of another shape or precision are checked (and converted)
        short = delta[:, :-1]
        with pytest.raises(InputError, match="delta must have shape"):
            solver.solve(batch, x0, None, short, w[:, :-1], trusted_iterates=True)
        other = delta.astype(np.float32 if delta.dtype == np.float64 else np.float64)
        assert initial_iterates(layout, x0, 3, other, w, solver.dtype,
                                trusted=True)[0].dtype == solver.dtype
