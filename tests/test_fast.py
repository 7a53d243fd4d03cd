"""Tests of the structure-exploiting batched C3+ (solvers/fast.py) and the batched LCS
(``LCSBatch`` in problems/lcs.py, built by problems/linearize_batch.py): correctness against
references only, never timing."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from c3bench.problems.config import load_config
from c3bench.problems.errors import InputError
from c3bench.problems.instance import Problem, load_instances
from c3bench.problems.lcs import LCS_MATRICES, LCSBatch
from c3bench.problems.linearize import linearize
from c3bench.problems.linearize_batch import BatchLinearizer
from c3bench.problems.names import PROFILE_TOLERANCE, Profile
from c3bench.problems.scene import build_mpc, build_scene
from c3bench.problems.suites import generate_suite, sample_states, scripted_push
from c3bench.solvers import registry
from c3bench.solvers.base import Settings, settings_for
from c3bench.solvers.c3 import C3Controller, C3Options, controller_capture, solve_c3
from c3bench.solvers.fast import (
    FactorCache,
    FastC3Plus,
    FastC3PlusController,
    RiccatiOptions,
    project_c3plus_batch,
)
from c3bench.solvers.projection import c3plus_projection
from c3bench.solvers.residuals import primal_residual, residuals
from c3bench.solvers.riccati_qp import solve_c3plus_qp

MID = PROFILE_TOLERANCE[Profile.MID_ACCURACY]
SIDES = (0.27, 0.29, 0.30, 0.33)


def _available(name: str) -> bool:
    try:
        return registry.get(name).availability()[0]
    except KeyError:
        return False


def _reference_backend() -> str:
    for name in ("clarabel", "kkt_ldl", "proxqp_dense"):
        if _available(name):
            return name
    pytest.skip("no high-accuracy QP backend available")
    raise AssertionError


def _relative(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.max(np.abs(np.asarray(a) - np.asarray(b)))
                 / max(1.0, float(np.max(np.abs(b)))))


@pytest.fixture(scope="module")
def quick_qps(tmp_path_factory: pytest.TempPathFactory) -> list[Problem]:
    """The quick suite's c3plus_qp instances, with the provisional iterates and with iterates
    captured from real C3+ runs (clarabel inside: nonzero duals, the reference study's rho
    schedule)."""
    problems: list[Problem] = []
    for capture in (None, controller_capture(_exact_options(keep_iterates=True))):
        out: Path = tmp_path_factory.mktemp("quick")
        generate_suite("quick", out, capture=capture, progress=False)
        problems += [p for p in load_instances(out) if p.family == "c3plus_qp"
                     and p.lb is None and p.ub is None and p.n_ineq == 0]
    assert len(problems) >= 8  # the equality variant (the Riccati kernel's form)
    assert any(np.any(p.data["w"] != 0) for p in problems)
    return problems


@pytest.fixture(scope="module")
def push() -> SimpleNamespace:
    """Contact-rich states of the scripted push, the controller model (l = 0.29) and MPC."""
    config = load_config()
    record = scripted_push(config)
    scene = build_scene(l=0.29, config=config)
    mpc = build_mpc(scene, config.mpc)
    indices = sample_states(record, 3, 0.02)
    cases = []
    for index in indices:
        x0, u_prev = record.states[index], record.inputs[max(index - 1, 0)]
        cases.append(SimpleNamespace(index=index, x0=x0, u_prev=u_prev,
                                     lcs=linearize(scene, x0, u_prev, config.mpc.dt)))
    return SimpleNamespace(config=config, record=record, scene=scene, mpc=mpc, cases=cases)


def _exact_options(**changes: object) -> C3Options:
    values: dict[str, object] = {"keep_iterates": False, **changes}
    return C3Options(qp_backend=_reference_backend(), qp_settings=settings_for("high_accuracy"),
                     **values)  # type: ignore[arg-type]


# --- the registry backend against clarabel ------------------------------------------------------
def test_riccati_backend_matches_reference_float64(quick_qps: list[Problem]) -> None:
    reference = _reference_backend()
    for problem in quick_qps:
        ours = registry.solve("c3plus_riccati", problem, Settings())
        ref = registry.solve(reference, problem, settings_for("high_accuracy"))
        assert ours.found and ref.found, (ours.status, ref.status)
        figures = residuals(problem, ours.x, ours.y)
        assert figures.primal_relative <= MID, problem.name
        assert figures.dual_relative <= MID, problem.name
        assert figures.gap_relative <= MID, problem.name
        assert _relative(ours.x, ref.x) <= MID, problem.name
        assert abs(ours.objective - ref.objective) <= MID * max(1.0, abs(ref.objective))


def test_riccati_backend_float32_restores_equalities(quick_qps: list[Problem]) -> None:
    for problem in quick_qps:
        result = registry.solve("c3plus_riccati", problem, Settings(precision="float32"))
        assert result.found
        assert primal_residual(problem, result.x) <= 1e-4, problem.name
        exact, _ = solve_c3plus_qp(problem)
        assert _relative(result.x, exact) <= 1e-3, problem.name


@pytest.mark.parametrize("options", [
    {"jacobi": False}, {"symmetrize": False, "rollout": False}, {"ridge": 1e-12},
])
def test_riccati_safeguard_switches_keep_accuracy(quick_qps: list[Problem],
                                                  options: dict[str, object]) -> None:
    problem = quick_qps[-1]
    exact, _ = solve_c3plus_qp(problem)
    z, y = solve_c3plus_qp(problem, RiccatiOptions(**options))  # type: ignore[arg-type]
    assert _relative(z, exact) <= 1e-8
    assert residuals(problem, z, y).dual_relative <= MID


def test_riccati_backend_rejects_other_structures(quick_qps: list[Problem]) -> None:
    problem = quick_qps[0]
    coupled = replace(problem, P=problem.P.copy())
    lcs = problem.lcs
    assert lcs is not None
    ns = lcs.nx + 2 * lcs.nlam + lcs.nu
    coupled.P[0, ns] = coupled.P[ns, 0] = 1e-3
    result = registry.solve("c3plus_riccati", coupled, Settings(), check=False)
    assert not result.found and "time steps" in result.status
    moved = replace(problem, b=problem.b.copy())
    moved.b[12] += 1.0  # a dynamics row no longer equal to the LCS's d
    result = registry.solve("c3plus_riccati", moved, Settings())
    assert not result.found and result.failure == "unsupported"
    bounded = replace(problem, lb=np.full(problem.n, -1e3), ub=np.full(problem.n, 1e3))
    accepted, reason = registry.get("c3plus_riccati").accepts(bounded)
    assert not accepted and "bounds" in reason


# --- the batched ADMM against solvers.c3 --------------------------------------------------------
@pytest.mark.parametrize("schedule", ["geometric", "adaptive", "residual_balancing"])
def test_fast_c3plus_matches_solve_c3(push: SimpleNamespace, schedule: str) -> None:
    cases = push.cases if schedule == "geometric" else push.cases[:1]
    for case in cases:
        options = _exact_options(rho_schedule=schedule)
        reference = solve_c3(case.lcs, push.mpc, case.x0, options)
        assert reference.ok
        fast = FastC3Plus(push.mpc, replace(options, qp_backend="c3plus_riccati"))
        solution = fast.solve(LCSBatch.from_lcs([case.lcs]), case.x0)
        assert solution.ok
        assert solution.u_raw is not None and reference.u_raw is not None
        assert _relative(solution.u_raw, reference.u_raw) <= 1e-6
        assert _relative(solution.delta, reference.delta) <= 1e-6
        assert _relative(solution.w, reference.w) <= 1e-6
        assert _relative(solution.z_steps, reference.z_steps) <= 1e-6
        assert solution.rho == pytest.approx(reference.rho)
        np.testing.assert_allclose(solution.u, reference.u, rtol=1e-6, atol=1e-6)


def test_fast_controller_warm_start_matches_c3_controller(push: SimpleNamespace) -> None:
    options = _exact_options()
    reference = C3Controller(options)
    fast = FastC3PlusController(FastC3Plus(push.mpc, options))
    for case in push.cases[:2]:
        expected = reference.step(case.lcs, push.mpc, case.x0)
        got = fast.step(LCSBatch.from_lcs([case.lcs]), case.x0)
        assert expected.ok and got.ok
        assert _relative(got.u, expected.u) <= 1e-6
        assert _relative(got.delta, expected.delta) <= 1e-6


def test_identical_samples_equal_the_single_sample(push: SimpleNamespace) -> None:
    case = push.cases[0]
    single = LCSBatch.from_lcs([case.lcs])
    fast = FastC3Plus(push.mpc)
    one = fast.solve(single, case.x0)
    many = fast.solve(single.repeat(5), case.x0, weights=[1, 2, 3, 4, 5])
    assert one.ok and many.ok
    assert one.u_raw is not None and many.u_raw is not None
    np.testing.assert_allclose(many.u_raw, one.u_raw, rtol=1e-9, atol=1e-9)
    for j in range(5):
        np.testing.assert_allclose(many.delta[j], one.delta[0], rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(many.w[j], one.w[0], rtol=1e-9, atol=1e-9)


def test_shared_inputs_are_a_consensus(push: SimpleNamespace) -> None:
    case = push.cases[0]
    batch = BatchLinearizer(SIDES).linearize(case.x0, case.u_prev, push.config.mpc.dt)
    weights = np.array([0.1, 0.2, 0.3, 0.4])
    solution = FastC3Plus(push.mpc).solve(batch, case.x0, weights=weights)
    assert solution.ok and solution.u_raw is not None
    u_s = slice(batch.nx + batch.nlam, batch.nx + batch.nlam + batch.nu)
    assert np.ptp(solution.delta[:, :, u_s], axis=0).max() == 0.0  # one u for all samples
    np.testing.assert_allclose(solution.u_raw, solution.delta[0, 0, u_s])
    independent = FastC3Plus(push.mpc, shared_inputs=False).solve(batch, case.x0)
    assert independent.u.shape == (4, 2)
    for j, side in enumerate(SIDES):
        lcs = linearize(build_scene(l=side), case.x0, case.u_prev, push.config.mpc.dt)
        alone = FastC3Plus(push.mpc).solve(LCSBatch.from_lcs([lcs]), case.x0)
        np.testing.assert_allclose(independent.u[j], alone.u, rtol=1e-7, atol=1e-7)


def test_float32_controller_close_to_float64(push: SimpleNamespace) -> None:
    case = push.cases[1]
    batch = LCSBatch.from_lcs([case.lcs])
    f64 = FastC3Plus(push.mpc).solve(batch, case.x0)
    f32 = FastC3Plus(push.mpc, riccati=RiccatiOptions(precision="float32")).solve(batch,
                                                                                 case.x0)
    assert f32.ok and f32.delta.dtype == np.float32
    assert _relative(f32.u, f64.u) <= 1e-3


def test_invalid_inputs_raise(push: SimpleNamespace) -> None:
    case = push.cases[0]
    batch = LCSBatch.from_lcs([case.lcs])
    fast = FastC3Plus(push.mpc)
    with pytest.raises(InputError, match="weights"):  # the project's one-line input error
        fast.solve(batch, case.x0, weights=[1.0, 2.0])
    for bad in ([-1.0], [np.nan], [0.0]):
        with pytest.raises(InputError, match="weights must be finite, >= 0"):
            fast.solve(batch, case.x0, weights=bad)
    with pytest.raises(InputError, match="weights must be numbers"):  # not numpy's message
        fast.solve(batch, case.x0, weights=["heavy"])
    with pytest.raises(InputError, match="non-finite"):
        ns = batch.nx + 2 * batch.nlam + batch.nu
        fast.solve(batch, case.x0, delta=np.full((push.mpc.horizon, ns), np.nan))
    with pytest.raises(ValueError, match="c3plus"):
        FastC3Plus(push.mpc, C3Options(variant="c3"))
    with pytest.raises(ValueError, match="precision"):
        RiccatiOptions(precision="float16")
    with pytest.raises(ValueError, match="non-finite"):
        LCSBatch(**{name: getattr(batch, name) * np.nan if name == "A" else
                    getattr(batch, name) for name in LCS_MATRICES}, dt=0.05)


# --- factorisation cache ------------------------------------------------------------------------
def test_factor_cache_hits_and_misses(push: SimpleNamespace) -> None:
    case = push.cases[0]
    batch = LCSBatch.from_lcs([case.lcs, case.lcs])
    fast = FastC3Plus(push.mpc, cache=FactorCache(max_entries=32))
    rho = {"x": 1.0, "lam": 50.0, "u": 0.1, "eta": 50.0}
    first, hit = fast.factor(batch, rho)
    assert not hit
    again, hit = fast.factor(batch, dict(rho))
    assert hit and again is first
    _, hit = fast.factor(batch, {**rho, "lam": 100.0, "eta": 100.0})
    assert not hit  # rho changed
    same_data = LCSBatch.from_lcs([case.lcs, case.lcs])
    _, hit = fast.factor(same_data, rho)
    assert not hit  # another LCS batch (another identity)
    assert (fast.cache.hits, fast.cache.misses) == (1, 3)
    # a control step on an unchanged LCS reuses every factorisation of the schedule
    step1 = fast.solve(batch, case.x0)
    step2 = fast.solve(batch, case.x0, delta=step1.delta, w=step1.w)
    assert step1.cache_misses == 8 and step1.cache_hits == 2  # rho0 and 2 rho0 were cached
    assert step2.cache_misses == 0 and step2.cache_hits == 10
    # without prefactorisation the loop asks the cache once per iteration
    loop = FastC3Plus(push.mpc, prefactorize=False)
    fresh = loop.solve(batch, case.x0)
    assert (fresh.cache_hits, fresh.cache_misses) == (0, 10)
    np.testing.assert_allclose(fresh.delta, step1.delta, rtol=1e-12, atol=1e-12)
    small = FactorCache(max_entries=2)
    FastC3Plus(push.mpc, cache=small).solve(batch, case.x0)
    assert len(small) == 2


# --- projection ---------------------------------------------------------------------------------
def test_batched_projection_equals_closed_form() -> None:
    rng = np.random.default_rng(3)
    v = rng.normal(size=(4, 7, 24))
    v[0, 0, 10] = v[0, 0, 18] = 0.5  # a tie keeps lam
    out = project_c3plus_batch(v, 10, 6, 2, 50.0, 80.0)
    lam, eta = c3plus_projection(v[..., 10:16], v[..., 18:24], 50.0, 80.0)
    np.testing.assert_array_equal(out[..., 10:16], lam)
    np.testing.assert_array_equal(out[..., 18:24], eta)
    np.testing.assert_array_equal(out[..., :10], v[..., :10])
    np.testing.assert_array_equal(out[..., 16:18], v[..., 16:18])


# --- batched LCS --------------------------------------------------------------------------------
@pytest.mark.parametrize("contact_model", ["anitescu", "stewart_trinkle"])
def test_batched_lcs_equals_linearize(push: SimpleNamespace, contact_model: str) -> None:
    config, record = push.config, push.record
    linearizer = BatchLinearizer(SIDES, config, contact_model=contact_model)
    scenes = [build_scene(l=side, config=config) for side in SIDES]
    steps = np.linspace(0, record.inputs.shape[0] - 1, 6).round().astype(int)
    for index in steps:
        x, u = record.states[index], record.inputs[index]
        batch = linearizer.linearize(x, u, config.mpc.dt)
        assert batch.n_samples == len(SIDES)
        for j, scene in enumerate(scenes):
            reference = linearize(scene, x, u, config.mpc.dt, contact_model=contact_model)
            for name in (*LCS_MATRICES, "phi"):
                ours, theirs = getattr(batch, name)[j], getattr(reference, name)
                scale = max(1.0, float(np.max(np.abs(theirs), initial=0.0)))
                assert np.max(np.abs(ours - theirs)) <= 1e-9 * scale, (index, SIDES[j], name)
        sample = batch.sample(1)
        np.testing.assert_array_equal(sample.F, batch.F[1])


def test_batched_lcs_inertia_matches_mujoco() -> None:
    linearizer = BatchLinearizer(SIDES)
    for side, inertia in zip(SIDES, linearizer.inertia, strict=True):
        scene = build_scene(l=side)
        expected = scene.model.body_inertia[scene.body("cube")]
        np.testing.assert_allclose(expected, inertia, rtol=1e-14)


def test_batched_lcs_rejects_spatial_and_bad_sides() -> None:
    with pytest.raises(NotImplementedError, match="planar"):
        BatchLinearizer(SIDES, variant="spatial")
    with pytest.raises(ValueError, match="sides"):
        BatchLinearizer([0.3, -1.0])
    with pytest.raises(ValueError, match="contact_model"):
        BatchLinearizer(SIDES, contact_model="soft")


def test_lcs_batch_is_read_only_with_identity(push: SimpleNamespace) -> None:
    lcs = push.cases[0].lcs
    a, b = LCSBatch.from_lcs([lcs]), LCSBatch.from_lcs([lcs])
    assert a.uid != b.uid
    with pytest.raises(ValueError):
        a.A[0, 0, 0] = 1.0
    assert a.repeat(3).n_samples == 3
