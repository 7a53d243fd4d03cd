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
