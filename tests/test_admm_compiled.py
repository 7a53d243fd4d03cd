"""Tests of the compiled (numba) C3+ kernel (solvers/admm/compiled.py): one iteration equals the
numpy Riccati QP step of :class:`FastC3Plus` followed by the closed-form C3+ projection and the
shared-input mean (an independent implementation of the same maths), on contact-rich states of
the scripted push and on random LCS batches; failures raise :class:`KernelFailure`. No timing."""

from __future__ import annotations

from collections.abc import Mapping
from types import SimpleNamespace

import numba
import numpy as np
import pytest
from conftest import push_batches, random_lcs_problem

from c3bench.problems.errors import InputError
from c3bench.problems.lcs import LCSBatch
from c3bench.problems.mpc import MPC, HorizonLayout
from c3bench.problems.names import Precision
from c3bench.solvers.admm import compiled_kernels as kernels
from c3bench.solvers.admm import compiled_passes as passes
from c3bench.solvers.admm.compiled import CompiledC3PlusKernel, KernelFailure
from c3bench.solvers.admm.projection import make_c3plus_pairs
from c3bench.solvers.fast import FastC3Plus, RiccatiOptions, project_c3plus_batch

TOLERANCE = {Precision.FLOAT64: 1e-9, Precision.FLOAT32: 2e-3}
"""Relative agreement with the float64 reference (float32: a few hundred float32 ulps of the
conditioning-scaled solution, measured at most 1.2e-4)."""


def _relative(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.max(np.abs(np.asarray(a, dtype=float) - b)) / max(1.0, np.max(np.abs(b))))


pytestmark = pytest.mark.usefixtures("compiled_kernels")


@pytest.fixture(scope="module")
def push() -> SimpleNamespace:
    """Contact-rich states of the scripted push, batches of 1, 3 and 16 cube sides."""
    return push_batches(1, (1, 3, 16))


def _reference(mpc: MPC, lcs: LCSBatch, x0: np.ndarray, rho: Mapping[str, float],
               delta: np.ndarray, w: np.ndarray, p: np.ndarray, shared: bool
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """float64 FastC3Plus QP step + closed-form projection + shared-input mean."""
    fast = FastC3Plus(mpc, riccati=RiccatiOptions())
    steps, terminal = fast.qp_step(lcs, rho, x0, delta, w)
    v = steps + w
    nx, nlam, nu = lcs.nx, lcs.nlam, lcs.nu
    projected = project_c3plus_batch(v, nx, nlam, nu, rho["lam"], rho["eta"])
    if shared and lcs.n_samples > 1:
        u_s = slice(nx + nlam, nx + nlam + nu)
        projected[:, :, u_s] = np.tensordot(p, v[:, :, u_s], axes=(0, 0))
    return steps, terminal, projected


def _warm_iterates(lcs: LCSBatch, T: int, x0: np.ndarray, seed: int
                   ) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    ns = lcs.nx + 2 * lcs.nlam + lcs.nu
    delta = rng.normal(size=(lcs.n_samples, T, ns))
    delta[:, :, :lcs.nx] += x0
    return delta, 0.1 * rng.normal(size=delta.shape)


def _check(mpc: MPC, lcs: LCSBatch, x0: np.ndarray, precision: Precision, shared: bool,
           seed: int) -> None:
    n = lcs.n_samples
    plan = FastC3Plus(mpc).planned_rhos()
    assert plan is not None and len(plan) >= 3
    off_plan = {**plan[0], "lam": 7.0, "u": 0.3}
    p = np.random.default_rng(seed).uniform(0.5, 1.5, n)
    p /= p.sum()
    delta, w = _warm_iterates(lcs, mpc.horizon, x0, seed)
    kernel = CompiledC3PlusKernel(mpc, precision)
    kernel.start(lcs, x0, p, shared, plan)
    dtype = precision.dtype
    for rho in (plan[0], plan[len(plan) // 2], plan[-1], off_plan, off_plan):
        expected = _reference(mpc, lcs, x0, rho, delta, w, p, shared)
        got = kernel.iterate(rho, delta.astype(dtype), w.astype(dtype))
        for name, ours, theirs in zip(("z_steps", "z_terminal", "new_delta"), got, expected,
                                      strict=True):
            assert ours.dtype == dtype and ours.shape == theirs.shape, name
            assert _relative(ours, theirs) <= TOLERANCE[precision], (name, rho, n, shared)
    assert len(kernel._off_plan) == 1  # the repeated off-plan rho came from the cache
    if shared and n > 1:
        u_s = slice(lcs.nx + lcs.nlam, lcs.nx + lcs.nlam + lcs.nu)
        assert np.ptp(got[2][:, :, u_s], axis=0).max() == 0.0  # one input for every sample


@pytest.mark.parametrize("precision", list(Precision))
@pytest.mark.parametrize("shared", [True, False])
@pytest.mark.parametrize("n", [1, 3, 16])
def test_iterate_equals_riccati_step_and_projection(push: SimpleNamespace, n: int,
                                                    shared: bool, precision: Precision) -> None:
    _check(push.mpc, push.batches[n], push.x0, precision, shared, seed=n)


@pytest.mark.parametrize("precision", list(Precision))
@pytest.mark.parametrize("n", [1, 3, 16, 40])
def test_iterate_on_random_lcs_batches(n: int, precision: Precision) -> None:
    mpc, lcs, x0 = random_lcs_problem(n, seed=10 + n)
    _check(mpc, lcs, x0, precision, shared=True, seed=n)


def _sparse_problem(n: int, seed: int) -> tuple[MPC, LCSBatch, np.ndarray]:
    """:func:`_random_problem` with exact zeros in ``A``, ``B``, ``D`` and ``d``: some shared by
    every sample (a zero column of ``B``, a zero row of ``D``), some in one sample only (so the
    kernel's structure must be the union over the batch)."""
    mpc, lcs, x0 = random_lcs_problem(n, seed)
    rng = np.random.default_rng(seed + 1)
    A, B, D, d = (np.array(a) for a in (lcs.A, lcs.B, lcs.D, lcs.d))
    A[:, 0, 1:] = 0.0
    A[:, 2, :2] = 0.0
    B[:, :, 1] = 0.0
    D[:, 3, :] = 0.0
    d[:, 1] = 0.0
    for j in range(n):
        A[j][rng.uniform(size=A[j].shape) < 0.4] = 0.0
        D[j][rng.uniform(size=D[j].shape) < 0.4] = 0.0
    A[0, 3, 3] = 0.0  # zero in sample 0 only
    lcs = LCSBatch(A=A, B=B, D=D, d=d, E=lcs.E, F=lcs.F, H=lcs.H, c=lcs.c, dt=lcs.dt)
    return mpc, lcs, x0


@pytest.mark.parametrize("precision", list(Precision))
@pytest.mark.parametrize("n", [1, 3, 16, 40])
def test_iterate_on_lcs_batches_with_exact_zeros(n: int, precision: Precision) -> None:
    mpc, lcs, x0 = _sparse_problem(n, seed=30 + n)
    _check(mpc, lcs, x0, precision, shared=True, seed=n)


def test_structure_is_the_union_over_samples_and_follows_the_batch() -> None:
    """The skipped entries are the zeros of every sample; a later batch with more nonzeros
    (same shapes) is not solved with the earlier, sparser structure."""
    mpc, sparse, x0 = _sparse_problem(3, seed=40)
    dense = random_lcs_problem(3, seed=40)[1]
    kernel = CompiledC3PlusKernel(mpc)
    plan = FastC3Plus(mpc).planned_rhos()
    assert plan is not None
    p = np.full(3, 1 / 3)
    for lcs in (sparse, dense, sparse):
        kernel.start(lcs, x0, p, True, plan)
        mask = np.concatenate([np.any(lcs.A != 0, axis=0), np.any(lcs.D != 0, axis=0),
                               np.any(lcs.B != 0, axis=0), np.any(lcs.d != 0, axis=0)[:, None]],
                              axis=1)
        structure = kernel.structure
        assert structure.nonzeros == mask.sum()
        for b in range(mask.shape[1]):
            rows = structure.column_rows[structure.column_start[b]:structure.column_start[b + 1]]
            assert rows.tolist() == np.flatnonzero(mask[:, b]).tolist()
        delta, w = _warm_iterates(lcs, mpc.horizon, x0, 1)
        expected = _reference(mpc, lcs, x0, plan[1], delta, w, p, True)
        got = kernel.iterate(plan[1], delta, w)
        assert all(_relative(a, b) <= 1e-9 for a, b in zip(got, expected, strict=True))


@pytest.mark.parametrize(("nx", "nv"), [(10, 10), (4, 5), (1, 1)])
def test_flop_counts_of_a_dense_block(nx: int, nv: int) -> None:
    """The executed-flop counts over every entry equal the closed forms of the loops."""
    ny = nx + nv
    mads = (nx * nx * (ny + 1) + nx * (nv * nx + nv * (nv + 1) // 2)
            + sum(a * (a + 1) // 2 for a in range(nv)) + nv * (nv - 1) // 2 * nx
            + (nx + nv) * nx * (nx + 1) // 2)
    assert kernels.factor_flops(nx, nv) == 2 * mads + nv * nx + 2 * nv
    pattern = kernels.structure(np.eye(nx, ny + 1, dtype=bool))
    assert pattern.nonzeros == nx
    assert kernels.factor_flops(nx, nv, pattern) < kernels.factor_flops(nx, nv)
    assert passes.solve_flops(nx, nv, 2, pattern) < passes.solve_flops(nx, nv, 2)


def test_executed_flops_of_a_planned_step_count_every_part(push: SimpleNamespace) -> None:
    """A whole planned step counts the batch's M^T M, every group's factorisations, every
    iteration with the shared-input mean, and the dual rescalings between iterations."""
    from c3bench.solvers.admm.loop import plan_ratios

    mpc, x0, lcs = push.mpc, push.x0, push.batches[3]
    plan = FastC3Plus(mpc).planned_rhos()
    assert plan is not None
    kernel = CompiledC3PlusKernel(mpc)
    kernel.start(lcs, x0, np.full(3, 1 / 3), True, plan)
    delta, w = _warm_iterates(lcs, mpc.horizon, x0, 7)
    layout = HorizonLayout(lcs.nx, lcs.nlam, lcs.nu, lcs.nlam, mpc.horizon)
    run = kernel.run_plan(plan, plan_ratios(layout, plan, True, np.float64), delta, w)
    assert run.failure is None and run.completed == len(plan)
    n, T, ns = delta.shape
    nx, nlam, nu = lcs.nx, lcs.nlam, lcs.nu
    nv, N = nlam + nu, len(plan)
    pattern = kernel.structure
    lane = T * kernels.factor_flops(nx, nv, pattern) + kernels.setup_flops(nx, nv)
    iteration = T * passes.solve_flops(nx, nv, nlam, pattern) + 2 * nu * T
    expected = n * (kernels.assemble_flops(nx, nlam, nu) + N * lane + N * iteration
                    + (N - 1) * T * ns)
    assert kernel.flops == expected
    assert kernels.assemble_flops(nx, nlam, nu) == nlam * (nx + nv) * (nx + nv + 1)


def test_ridge_and_no_jacobi_match_the_reference(push: SimpleNamespace) -> None:
    lcs, x0, mpc = push.batches[3], push.x0, push.mpc
    plan = FastC3Plus(mpc).planned_rhos()
    assert plan is not None
    delta, w = _warm_iterates(lcs, mpc.horizon, x0, 5)
    for options in (RiccatiOptions(jacobi=False), RiccatiOptions(ridge=1e-6)):
        kernel = CompiledC3PlusKernel(mpc, riccati=options)
        kernel.start(lcs, x0, np.full(3, 1 / 3), False, plan)
        fast = FastC3Plus(mpc, riccati=options)
        steps, terminal = fast.qp_step(lcs, plan[1], x0, delta, w)
        z_steps, z_terminal, _ = kernel.iterate(plan[1], delta, w)
        assert _relative(z_steps, steps) <= 1e-9
        assert _relative(z_terminal, terminal) <= 1e-9


@pytest.mark.parametrize("shared", [True, False])
def test_box_clips_states_and_inputs(push: SimpleNamespace, shared: bool) -> None:
    mpc, lcs, x0 = push.mpc, push.batches[3], push.x0
    plan = FastC3Plus(mpc).planned_rhos()
    assert plan is not None
    delta, w = _warm_iterates(lcs, mpc.horizon, x0, 11)
    p = np.array([0.2, 0.3, 0.5])
    _, _, free = _reference(mpc, lcs, x0, plan[2], delta, w, p, shared)
    nx, nlam, nu = lcs.nx, lcs.nlam, lcs.nu
    x_s, u_s = slice(0, nx), slice(nx + nlam, nx + nlam + nu)
    lower = np.concatenate([np.quantile(free[..., x_s], 0.3, axis=(0, 1)),
                            np.quantile(free[..., u_s], 0.3, axis=(0, 1))])
    upper = np.concatenate([np.quantile(free[..., x_s], 0.7, axis=(0, 1)), [np.inf] * nu])
    lower[1] = -np.inf  # an unbounded side
    kernel = CompiledC3PlusKernel(mpc, box=(lower, upper))
    kernel.start(lcs, x0, p, shared, plan)
    _, _, got = kernel.iterate(plan[2], delta, w)
    expected = free.copy()
    expected[..., x_s] = np.clip(free[..., x_s], lower[:nx], upper[:nx])
    expected[..., u_s] = np.clip(free[..., u_s], lower[nx:], upper[nx:])
    assert np.any(expected != free)  # the box is active
    assert _relative(got, expected) <= 1e-9
    with pytest.raises(InputError, match="box"):
        CompiledC3PlusKernel(mpc, box=(upper, lower))


def test_start_reuses_buffers_and_refactorises(push: SimpleNamespace) -> None:
    mpc, x0 = push.mpc, push.x0
    plan = FastC3Plus(mpc).planned_rhos()
    assert plan is not None
    kernel = CompiledC3PlusKernel(mpc)
    lcs3 = push.batches[3]
    kernel.start(lcs3, x0, np.full(3, 1 / 3), True, plan)
    delta, w = _warm_iterates(lcs3, mpc.horizon, x0, 7)
    first = kernel.iterate(plan[0], delta, w)
    kernel.start(push.batches[16], x0, np.full(16, 1 / 16), True, plan)  # other shapes
    kernel.start(lcs3, x0, np.full(3, 1 / 3), True, plan)
    kernel.start(lcs3, x0, np.full(3, 1 / 3), True, plan)
    again = kernel.iterate(plan[0], delta, w)
    for a, b in zip(first, again, strict=True):
        np.testing.assert_array_equal(a, b)
    reused = kernel._planned
    kernel.start(lcs3, x0, np.full(3, 1 / 3), True, plan)
    assert kernel._planned is reused  # same shapes: the same preallocated arrays


@pytest.mark.parametrize(("m", "n"), [(10, 1), (3, 3), (3, 13)])
def test_padding_lanes_change_no_factor(m: int, n: int) -> None:
    """Factorising ``m`` rho values for ``n`` samples with padding lanes (a group of one
    block: its lanes rounded up to a multiple of LANE_PAD; more lanes: a last block that is
    not a multiple) gives every real lane bit for bit what factorising one rho value at a
    time into unpadded arrays gives, and the padding lanes leave ``failed`` alone."""
    mpc, lcs, x0 = random_lcs_problem(n, seed=50 + n)
    plan = FastC3Plus(mpc).planned_rhos()
    assert plan is not None
    kernel = CompiledC3PlusKernel(mpc)
    kernel.start(lcs, x0, np.full(n, 1 / n), True, plan)
    padded = kernel._allocate(m)
    assert padded.Y.shape[-1] == (-(-m * n // kernels.LANE_PAD) * kernels.LANE_PAD
                                  if m * n <= kernels.LANE_BLOCK else m * n)
    assert padded.failed.shape == (m * n,)
    kernel._factorize(plan[:m], padded)
    for i in range(m):
        single = kernel._allocate(1)
        exact = type(single)(Y=single.Y[..., :n].copy(), L=single.L[..., :n].copy(),
                             Sd=single.Sd[..., :n].copy(), D=single.D[..., :n].copy(),
                             ABd=single.ABd[..., :n].copy(), failed=single.failed,
                             slots=1, samples=n)
        kernel._factorize(plan[i:i + 1], exact)
        lanes = slice(i * n, (i + 1) * n)
        for name in ("Y", "Sd", "D", "ABd"):
            np.testing.assert_array_equal(getattr(padded, name)[..., lanes],
                                          getattr(exact, name))
        lower = np.tril(np.ones(padded.L.shape[1:3], dtype=bool))
        np.testing.assert_array_equal(padded.L[:, lower][..., lanes], exact.L[:, lower])
        np.testing.assert_array_equal(padded.failed[lanes], exact.failed)
    assert np.all(padded.failed == -1)


def test_indefinite_stage_hessian_raises(push: SimpleNamespace) -> None:
    mpc = push.mpc
    negative = MPC(Q=mpc.Q, R=-1e4 * np.eye(mpc.nu), Q_f=mpc.Q_f, x_target=mpc.x_target,
                   horizon=mpc.horizon, dt=mpc.dt, force_limit=mpc.force_limit)
    lcs = push.batches[3]
    plan = FastC3Plus(mpc).planned_rhos()
    assert plan is not None
    delta, w = _warm_iterates(lcs, mpc.horizon, push.x0, 3)
    for precision in Precision:
        kernel = CompiledC3PlusKernel(negative, precision)
        kernel.start(lcs, push.x0, np.full(3, 1 / 3), True, plan)  # failure surfaces per rho
        with pytest.raises(KernelFailure, match="Cholesky"):
            kernel.iterate(plan[0], delta, w)
        with pytest.raises(KernelFailure, match="Cholesky"):
            kernel.iterate({**plan[0], "lam": 3.0}, delta, w)  # off the plan


def test_non_finite_inputs_raise(push: SimpleNamespace) -> None:
    mpc, lcs = push.mpc, push.batches[1]
    plan = FastC3Plus(mpc).planned_rhos()
    assert plan is not None
    kernel = CompiledC3PlusKernel(mpc)
    x0 = push.x0.copy()
    x0[2] = np.nan
    with pytest.raises(KernelFailure, match="x0"):
        kernel.start(lcs, x0, np.ones(1), True, plan)
    kernel.start(lcs, push.x0, np.ones(1), True, plan)
    delta, w = _warm_iterates(lcs, mpc.horizon, push.x0, 1)
    w[0, 3, 0] = np.inf
    with pytest.raises(KernelFailure, match="non-finite"):
        kernel.iterate(plan[0], delta, w)


@pytest.mark.parametrize("precision", list(Precision))
def test_fused_step_is_the_iteration_and_its_dual_update(push: SimpleNamespace,
                                                         precision: Precision) -> None:
    """``CompiledC3Plus.fused`` (one compiled call) returns what the loop's own
    ``admm_iteration`` (kernel step, then the numpy ``dual_update``) returns, and a whole control
    step through it equals the numpy Riccati kernel's step."""
    from c3bench.solvers.admm.compiled_solver import CompiledC3Plus
    from c3bench.solvers.admm.kernel import StepInputs
    from c3bench.solvers.admm.loop import admm_iteration, initial_iterates
    from c3bench.solvers.admm.options import C3Options

    lcs, n = push.batches[16], 16
    options = C3Options(keep_iterates=False)
    solver = CompiledC3Plus(push.mpc, options, precision=precision)
    solver.bind(lcs)
    rng = np.random.default_rng(3)
    p = rng.uniform(0.5, 1.5, n)
    solver.start(StepInputs(push.x0, p / p.sum(), True, None))
    delta, w = initial_iterates(solver.layout, push.x0, n, None, None, solver.dtype)
    w = (w + 0.1 * rng.normal(size=w.shape)).astype(solver.dtype)
    rho = dict(options.rho0)
    fused = solver.fused(solver, rho, delta, w)
    looped = admm_iteration(solver, rho, delta, w)
    for name, ours, theirs in zip(("z", "terminal", "delta", "w"), fused, looped, strict=True):
        assert ours.dtype == solver.dtype, name
        np.testing.assert_array_equal(ours, theirs, err_msg=name)
    assert _relative(fused[3], w + fused[0] - fused[2]) == 0.0
    if precision == Precision.FLOAT64:
        got = CompiledC3Plus(push.mpc, options).solve(lcs, push.x0)
        expected = FastC3Plus(push.mpc, options).solve(lcs, push.x0)
        for ours, theirs in ((got.delta, expected.delta), (got.w, expected.w),
                             (got.u, expected.u)):
            assert _relative(ours, theirs) <= TOLERANCE[precision]


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_pair_projection_for_scalars_is_the_array_one_bit_for_bit(dtype: type) -> None:
    """The closed form compiled for one pair (the projection's loop) against the same closed
    form compiled for arrays, on near-ties, NaN, infinities and signed zeros."""
    array_pairs = numba.njit(make_c3plus_pairs(np))
    rng = np.random.default_rng(3)
    a = rng.normal(size=4000).astype(dtype)
    b = (a * dtype(1.0000001) + rng.normal(size=4000).astype(dtype) * dtype(1e-7)).astype(dtype)
    a[:10] = [np.nan, -np.inf, np.inf, 0.0, -0.0, 0.0, -0.0, np.nan, 1.0, -1.0]
    b[:10] = [1.0, 2.0, 3.0, -0.0, 0.0, 0.0, -0.0, np.nan, np.nan, np.inf]
    unsigned = np.uint64 if dtype == np.float64 else np.uint32
    for sqrt_lam, sqrt_eta in ((1.3, 1.3), (31.6, 1.0), (0.0, 2.0)):
        weights = (dtype(sqrt_lam), dtype(sqrt_eta))
        lam, eta = (np.asarray(x).astype(dtype) for x in array_pairs(a, b, *weights))
        pairs = [passes._c3plus_pair(x, y, *weights) for x, y in zip(a, b, strict=True)]
        got_lam = np.array([p[0] for p in pairs]).astype(dtype)
        got_eta = np.array([p[1] for p in pairs]).astype(dtype)
        np.testing.assert_array_equal(got_lam.view(unsigned), lam.view(unsigned))
        np.testing.assert_array_equal(got_eta.view(unsigned), eta.view(unsigned))
