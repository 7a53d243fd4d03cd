"""A whole planned schedule in one compiled call (solvers/admm/compiled_plan.py) is the one ADMM
loop run iteration by iteration: same iterates bit for bit (the same compiled iteration, the same
rescaling), same status, iterations, rho and trace, on the push's contact states and random
batches, for group sizes that split the plan evenly and not, in both precisions; a failed
factorisation in a later group and a non-finite iterate end both runs at the same iteration with
the same message. No timing."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
from conftest import push_batches, random_lcs_problem

from c3bench.problems.lcs import LCSBatch
from c3bench.problems.mpc import MPC
from c3bench.problems.names import Precision
from c3bench.solvers.admm.compiled_factors import plan_group
from c3bench.solvers.admm.compiled_solver import CompiledC3Plus
from c3bench.solvers.admm.loop import plan_ratios, rescale_dual
from c3bench.solvers.admm.options import C3Options
from c3bench.solvers.admm.solution import C3Solution

pytestmark = pytest.mark.usefixtures("compiled_kernels")


@pytest.fixture(scope="module")
def push() -> SimpleNamespace:
    return push_batches(2, (1, 5, 16))


def _solve(mpc: MPC, lcs: LCSBatch, x0: np.ndarray, options: C3Options, precision: Precision,
           planned: bool, shared: bool, seed: int, w_scale: float = 0.1) -> C3Solution:
    """One control step with warm iterates and uneven weights, through ``run_plan`` or (with
    ``planned=False``) one kernel call per iteration."""
    solver = CompiledC3Plus(mpc, options, precision=precision, shared_inputs=shared)
    if not planned:
        solver.run_plan = None  # type: ignore[assignment, method-assign]
    rng = np.random.default_rng(seed)
    n = lcs.n_samples
    ns = lcs.nx + 2 * lcs.nlam + lcs.nu
    delta = rng.normal(size=(n, mpc.horizon, ns))
    delta[:, :, :lcs.nx] += x0
    w = w_scale * rng.normal(size=delta.shape)
    return solver.solve(lcs, x0, list(rng.uniform(0.5, 1.5, n)), delta, w)


def _assert_same(planned: C3Solution, looped: C3Solution) -> None:
    assert planned.status == looped.status
    assert planned.ok == looped.ok and planned.iterations == looped.iterations
    assert planned.rho == looped.rho
    for name in ("delta", "w", "z_steps", "z_terminal", "u"):
        ours, theirs = getattr(planned, name), getattr(looped, name)
        if theirs is None:
            assert ours is None, name
            continue
        assert ours.dtype == theirs.dtype, name
        np.testing.assert_array_equal(ours, theirs, err_msg=name)
    assert len(planned.trace.iteration) == len(looped.trace.iteration)
    assert planned.trace.failed == looped.trace.failed
    assert planned.trace.message == looped.trace.message


@pytest.mark.parametrize("precision", list(Precision))
@pytest.mark.parametrize("shared", [True, False])
@pytest.mark.parametrize("n", [1, 5, 16])
def test_planned_run_is_the_loop(push: SimpleNamespace, n: int, shared: bool,
                                 precision: Precision) -> None:
    options = C3Options(keep_iterates=False)
    group = plan_group(n, options.admm_iterations)
    assert group == options.admm_iterations if n == 1 else group < options.admm_iterations
    planned = _solve(push.mpc, push.batches[n], push.x0, options, precision, True, shared, n)
    looped = _solve(push.mpc, push.batches[n], push.x0, options, precision, False, shared, n)
    assert planned.ok and planned.iterations == options.admm_iterations
    _assert_same(planned, looped)


@pytest.mark.parametrize(("rescale", "iterations", "U"), [
    (True, 7, None), (False, 7, None), (True, 1, None),
    (True, 5, {"x": 1000.0, "lam": 1.0, "u": 0.0, "eta": 1.0})])
def test_planned_run_on_a_random_batch(rescale: bool, iterations: int,
                                       U: dict[str, float] | None) -> None:
    """All blocks scheduled, with and without rescaling, a one-iteration plan (no rescaling
    at all) and a separate projection weight ``U``."""
    mpc, lcs, x0 = random_lcs_problem(7, seed=7)
    options = C3Options(keep_iterates=False, admm_iterations=iterations, rescale_dual=rescale,
                        rho_blocks=("x", "lam", "u", "eta"), rho_factor=1.7,
                        projection_weights=U)
    planned = _solve(mpc, lcs, x0, options, Precision.FLOAT64, True, True, 1)
    looped = _solve(mpc, lcs, x0, options, Precision.FLOAT64, False, True, 1)
    assert planned.ok and planned.iterations == iterations
    _assert_same(planned, looped)


def test_a_failed_factorisation_in_a_later_group_stops_both_alike(push: SimpleNamespace
                                                                    ) -> None:
    """A falling ``rho_u`` with a negative ``R``: ``Q_vv`` loses positive definiteness part way
    through the plan, in a group after the first."""
    mpc = push.mpc
    negative = MPC(Q=mpc.Q, R=-200.0 * np.eye(mpc.nu), Q_f=mpc.Q_f, x_target=mpc.x_target,
                   horizon=mpc.horizon, dt=mpc.dt, force_limit=mpc.force_limit)
    options = C3Options(keep_iterates=False, rho0={"x": 1.0, "lam": 50.0, "u": 1600.0,
                                                   "eta": 50.0},
                        rho_blocks=("u",), rho_factor=0.5)
    lcs = push.batches[16]
    runs = [_solve(negative, lcs, push.x0, options, Precision.FLOAT64, planned, True, 3)
            for planned in (True, False)]
    planned, looped = runs
    assert not planned.ok and "QP factorisation failed at iteration" in planned.status
    assert "Cholesky" in planned.status
    assert planned.iterations >= plan_group(16, options.admm_iterations)  # a later group
    _assert_same(planned, looped)
    assert planned.trace.failed[-1]


def test_a_non_finite_iterate_stops_both_alike(push: SimpleNamespace) -> None:
    options = C3Options(keep_iterates=False)
    runs = [_solve(push.mpc, push.batches[5], push.x0, options, Precision.FLOAT64, planned,
                   True, 4, w_scale=1e306) for planned in (True, False)]
    planned, looped = runs
    assert not planned.ok and planned.iterations == 0
    assert planned.status.startswith("non-finite QP solution at iteration 0")
    _assert_same(planned, looped)


def test_plan_ratios_are_the_loops_rescaling(push: SimpleNamespace) -> None:
    """Row ``i`` of :func:`plan_ratios` times ``w`` is the loop's :func:`rescale_dual` from
    ``plan[i]`` to ``plan[i + 1]``; rows are ones without rescaling or a change of rho."""
    solver = CompiledC3Plus(push.mpc, C3Options(keep_iterates=False))
    solver.bind(push.batches[1])
    layout = solver.layout
    options = C3Options()
    plan = [dict(options.rho0)] * 2 + [{**options.rho0, "lam": 100.0}]
    ratios = plan_ratios(layout, plan, True, np.float64)
    w = np.random.default_rng(0).normal(size=(2, layout.horizon, layout.step_size))
    np.testing.assert_array_equal(ratios[0], 1.0)
    np.testing.assert_array_equal(w * ratios[1], rescale_dual(w, layout, plan[1], plan[2]))
    assert not np.all(ratios[1] == 1.0)
    np.testing.assert_array_equal(plan_ratios(layout, plan, False, np.float32), 1.0)
    assert plan_ratios(layout, plan, False, np.float32).dtype == np.float32


def test_a_frozen_plan_is_remembered_and_a_list_is_not(push: SimpleNamespace) -> None:
    """The geometric schedule gives the same read-only :class:`Plan` for the same arguments,
    so its ratios and the kernel's rho keys are remembered by identity; a plain list that is
    changed in place between control steps gets fresh ratios and keys every time."""
    from c3bench.solvers.admm.schedules import Geometric, Plan, is_frozen

    options = C3Options()
    schedule = Geometric(tuple(options.rho_blocks), 2.0)
    plan = schedule.plan(options.rho0, 4)
    assert isinstance(plan, Plan) and is_frozen(plan)
    assert schedule.plan(dict(options.rho0), 4) is plan
    with pytest.raises(TypeError):
        plan[0]["lam"] = 1.0  # type: ignore[index]
    solver = CompiledC3Plus(push.mpc, C3Options(keep_iterates=False))
    solver.bind(push.batches[1])
    layout = solver.layout
    assert plan_ratios(layout, plan, True, np.float64) is plan_ratios(layout, plan, True,
                                                                      np.float64)
    listed = [dict(rho) for rho in plan]
    assert not is_frozen(listed)
    np.testing.assert_array_equal(plan_ratios(layout, listed, True, np.float64),
                                  plan_ratios(layout, plan, True, np.float64))
    assert not np.all(plan_ratios(layout, listed, True, np.float64)[0] == 1.0)
    listed[1].update(listed[0])  # changed in place: no longer a change of rho
    np.testing.assert_array_equal(plan_ratios(layout, listed, True, np.float64)[0], 1.0)
    kernel, x0 = solver.kernel, push.x0
    kernel.start(push.batches[1], x0, np.ones(1), True, listed)
    keys = list(kernel._plan_keys)
    listed[2]["eta"] = 7.0
    kernel.start(push.batches[1], x0, np.ones(1), True, listed)
    assert kernel._plan_keys != keys and kernel._plan_keys[2][3] == 7.0


def test_new_limits_reach_the_projection(push: SimpleNamespace) -> None:
    """The solver sets its projection's box again when ``mpc.limits`` is replaced (it skips
    the work while the sizes, ``use_limits`` and the limits object stay the same)."""
    from c3bench.problems.limits import Limits

    mpc, lcs = push.mpc, push.batches[5]
    original = mpc.limits
    solver = CompiledC3Plus(mpc, C3Options(keep_iterates=False))
    free = solver.solve(lcs, push.x0)
    bound = 0.25 * float(np.max(np.abs(free.u_raw)))
    assert bound > 0
    inf = np.full(mpc.nx, np.inf)
    mpc.limits = Limits(np.full(mpc.nu, -bound), np.full(mpc.nu, bound), -inf, inf)
    try:
        tight = solver.solve(lcs, push.x0)
        assert np.max(np.abs(tight.u_raw)) <= bound + 1e-12
        assert np.max(np.abs(tight.delta[:, :, solver.layout.index(0, "u")])) <= bound + 1e-12
        mpc.limits = original
        np.testing.assert_array_equal(solver.solve(lcs, push.x0).u_raw, free.u_raw)
    finally:
        mpc.limits = original
