"""problems/recover.py: the MPC read back from a horizon instance's cost, and the check that a
rebuilt instance equals the stored one (used by the c3_admm backends and the sequence cells)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from c3bench.problems import families
from c3bench.problems.mpc import HorizonLayout
from c3bench.problems.names import Family
from c3bench.problems.recover import mismatches, mpc_from_cost
from c3bench.problems.toy_lcs import point_mass_lcs, point_mass_mpc

RHO = {"x": 0.5, "lam": 3.0, "u": 0.25, "eta": 2.0}


def _same_mpc(recovered, mpc) -> None:  # type: ignore[no-untyped-def]
    for name in ("Q", "R", "Q_f"):
        np.testing.assert_allclose(getattr(recovered, name), getattr(mpc, name), rtol=1e-12,
                                   atol=1e-12)
    np.testing.assert_allclose(recovered.x_target, mpc.x_target, rtol=1e-12, atol=1e-12)
    assert recovered.horizon == mpc.horizon and recovered.dt == mpc.dt


def test_mpcc_cost_gives_back_its_mpc() -> None:
    lcs, mpc = point_mass_lcs(), point_mass_mpc(target_position=0.63, q_velocity=2.0)
    x0 = np.array([0.1, -0.4])
    problem = families.mpcc("toy", lcs, mpc, x0)
    layout = HorizonLayout.from_json(problem.meta["layout"])
    recovered = mpc_from_cost(problem, layout, mpc.force_limit, None)
    _same_mpc(recovered, mpc)
    assert mismatches(families.mpcc("toy", lcs, recovered, x0), problem) == []


def test_qp_step_cost_gives_back_its_mpc_without_the_consensus_weights() -> None:
    lcs, mpc = point_mass_lcs(), point_mass_mpc(r_input=0.3)
    x0 = np.array([0.45, 0.5])
    problem = families.consensus_qp(Family.C3PLUS_QP, "toy-qp", lcs, mpc, x0, RHO, None, None)
    layout = HorizonLayout.from_json(problem.meta["layout"])
    _same_mpc(mpc_from_cost(problem, layout, mpc.force_limit, None, RHO), mpc)
    wrong = mpc_from_cost(problem, layout, mpc.force_limit, None)  # rho left in Q and R
    assert not np.allclose(wrong.Q, mpc.Q)


@pytest.mark.parametrize("part", ["P", "q", "b", "ub", "offset"])
def test_mismatches_name_the_part_that_differs(part: str) -> None:
    lcs, mpc = point_mass_lcs(), point_mass_mpc()
    problem = families.mpcc("toy", lcs, mpc, np.array([0.0, 1.0]))
    changed = dataclasses.replace(problem)
    if part == "offset":
        changed.objective_offset = problem.objective_offset + 1e-3
    else:
        array = np.array(getattr(problem, part), dtype=float)
        first = int(np.flatnonzero(np.isfinite(array))[0])  # bounds: a finite one
        array.flat[first] += 1e-6 * max(1.0, float(np.max(np.abs(problem.P))))
        setattr(changed, part, array)
    assert mismatches(changed, problem) == [part]
    assert mismatches(problem, problem) == []
