"""Tests of the JAX-compiled batched C3+ (solvers/fast_jax.py) against the numpy path.

Skipped when JAX is not installed (it is an optional extra: ``pip install c3bench[jax]``).
"""

from __future__ import annotations

import importlib.util
from types import SimpleNamespace

import numpy as np
import pytest

from c3bench.problems.config import load_config
from c3bench.problems.linearize_batch import BatchLinearizer
from c3bench.problems.scene import build_mpc, build_scene
from c3bench.problems.suites import sample_states, scripted_push
from c3bench.solvers.c3 import C3Options
from c3bench.solvers.fast import FastC3Plus, RiccatiOptions
from c3bench.solvers.fast_jax import (
    JaxC3Plus,
    JaxUnavailable,
    back_substitution,
    cholesky_factor,
    cholesky_solve,
    forward_substitution,
    gpu_available,
    jax_modules,
)

# JAX is imported only when these tests run (not at collection), and conftest.py runs them
# last: JAX starts threads, and the registry forks solver processes afterwards otherwise.
pytestmark = [pytest.mark.jax,
              pytest.mark.skipif(importlib.util.find_spec("jax") is None,
                                 reason="JAX is not installed (pip install c3bench[jax])")]

SIDES = (0.27, 0.29, 0.30, 0.33)


def _relative(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.max(np.abs(np.asarray(a, dtype=float) - np.asarray(b, dtype=float)))
                 / max(1.0, float(np.max(np.abs(np.asarray(b, dtype=float))))))


@pytest.fixture(scope="module")
def setup() -> SimpleNamespace:
    config = load_config()
    record = scripted_push(config)
    mpc = build_mpc(build_scene(l=0.29, config=config), config.mpc)
    index = sample_states(record, 3, 0.02)[1]
    x0, u_prev = record.states[index], record.inputs[index - 1]
    linearizer = BatchLinearizer(SIDES, config)
    batch = linearizer.linearize(x0, u_prev, config.mpc.dt)
    single = BatchLinearizer([0.29], config).linearize(x0, u_prev, config.mpc.dt)
    return SimpleNamespace(mpc=mpc, x0=x0, batch=batch, single=single)


def test_cholesky_solve_matches_numpy() -> None:
    _, jnp, _ = jax_modules()
    rng = np.random.default_rng(0)
    Q = rng.normal(size=(5, 8, 8))
    Q = Q @ np.swapaxes(Q, -1, -2) + 0.1 * np.eye(8)
    R = rng.normal(size=(5, 8, 3))
    got = np.asarray(cholesky_solve(jnp, jnp.asarray(Q), jnp.asarray(R)))
    np.testing.assert_allclose(got, np.linalg.solve(Q, R), rtol=1e-9, atol=1e-9)


def test_factor_and_substitutions_match_numpy() -> None:
    _, jnp, _ = jax_modules()
    rng = np.random.default_rng(1)
    Q = rng.normal(size=(5, 8, 8))
    Q = Q @ np.swapaxes(Q, -1, -2) + 0.1 * np.eye(8)
    R = rng.normal(size=(5, 8, 11))
    y = rng.normal(size=(5, 8))
    L = np.asarray(cholesky_factor(jnp, jnp.asarray(Q)))
    np.testing.assert_allclose(L, np.linalg.cholesky(Q), rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(np.asarray(forward_substitution(jnp, jnp.asarray(L),
                                                               jnp.asarray(R))),
                               np.linalg.solve(L, R), rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(np.asarray(back_substitution(jnp, jnp.asarray(L),
                                                            jnp.asarray(y))),
                               np.linalg.solve(np.swapaxes(L, -1, -2), y[..., None])[..., 0],
                               rtol=1e-9, atol=1e-9)
    not_spd = -np.eye(8)[None]
    assert np.all(np.isnan(np.asarray(cholesky_factor(jnp, jnp.asarray(not_spd)))[0, :, 0]))


def test_single_sample_float64_matches_numpy(setup: SimpleNamespace) -> None:
    numpy_path = FastC3Plus(setup.mpc).solve(setup.single, setup.x0)
    jax_path = JaxC3Plus(setup.mpc).solve(setup.single, setup.x0)
    assert numpy_path.ok and jax_path.ok
    assert _relative(jax_path.u_raw, numpy_path.u_raw) <= 1e-9
    assert _relative(jax_path.delta, numpy_path.delta) <= 1e-9
    assert _relative(jax_path.w, numpy_path.w) <= 1e-9
    assert _relative(jax_path.z_steps, numpy_path.z_steps) <= 1e-9
    assert jax_path.rho == pytest.approx(numpy_path.rho)


def test_shared_input_samples_match_numpy(setup: SimpleNamespace) -> None:
    weights = [0.4, 0.3, 0.2, 0.1]
    numpy_path = FastC3Plus(setup.mpc).solve(setup.batch, setup.x0, weights=weights)
    jax_path = JaxC3Plus(setup.mpc).solve(setup.batch, setup.x0, weights=weights)
    assert jax_path.ok
    assert _relative(jax_path.u, numpy_path.u) <= 1e-9
    assert _relative(jax_path.delta, numpy_path.delta) <= 1e-9
    assert _relative(jax_path.w, numpy_path.w) <= 1e-9


def test_float32_matches_numpy_float32(setup: SimpleNamespace) -> None:
    numpy32 = FastC3Plus(setup.mpc, riccati=RiccatiOptions(precision="float32")).solve(
        setup.batch, setup.x0)
    numpy64 = FastC3Plus(setup.mpc).solve(setup.batch, setup.x0)
    jax32 = JaxC3Plus(setup.mpc, precision="float32").solve(setup.batch, setup.x0)
    assert jax32.ok and jax32.delta.dtype == np.float32
    assert _relative(jax32.u, numpy32.u) <= 1e-3
    assert _relative(jax32.u, numpy64.u) <= 1e-3


def test_adaptive_schedule_matches_numpy(setup: SimpleNamespace) -> None:
    options = C3Options(rho_schedule="adaptive", keep_iterates=False)
    numpy_path = FastC3Plus(setup.mpc, options, record_residuals=True).solve(setup.single,
                                                                            setup.x0)
    jax_path = JaxC3Plus(setup.mpc, options).solve(setup.single, setup.x0)
    assert jax_path.rho == pytest.approx(numpy_path.rho)
    assert _relative(jax_path.delta, numpy_path.delta) <= 1e-9
    np.testing.assert_allclose(jax_path.consensus_residual, numpy_path.consensus_residual,
                               rtol=1e-8)


def test_residual_stopping_matches_numpy(setup: SimpleNamespace) -> None:
    """The one loop stops both kernels at the same iteration (the rule lives in the loop)."""
    options = C3Options(stopping="residual", admm_iterations=30, eps_abs=1e-2, eps_rel=1e-2,
                        rho_schedule="residual_balancing", keep_iterates=False)
    numpy_path = FastC3Plus(setup.mpc, options).solve(setup.single, setup.x0)
    jax_path = JaxC3Plus(setup.mpc, options).solve(setup.single, setup.x0)
    assert jax_path.iterations == numpy_path.iterations
    assert jax_path.status == numpy_path.status
    assert _relative(jax_path.delta, numpy_path.delta) <= 1e-9


def test_options_and_devices_are_checked(setup: SimpleNamespace) -> None:
    with pytest.raises(ValueError, match="precision"):
        JaxC3Plus(setup.mpc, precision="float16")
    if not gpu_available():
        with pytest.raises(JaxUnavailable, match="no GPU visible"):
            JaxC3Plus(setup.mpc, device="gpu")


@pytest.mark.parametrize("precision", ["float64", "float32"])
def test_planned_run_is_the_iteration_by_iteration_loop(setup: SimpleNamespace,
                                                        precision: str) -> None:
    """A geometric plan as one ``lax.scan`` device call (``run_plan``) gives the control step
    of one device call per iteration: same iterations, rho and status, iterates to rounding
    (XLA may fuse the scan's body differently)."""
    weights = [0.4, 0.3, 0.2, 0.1]
    planned = JaxC3Plus(setup.mpc, precision=precision)
    looped = JaxC3Plus(setup.mpc, precision=precision)
    looped.run_plan = None  # type: ignore[assignment, method-assign]
    a = planned.solve(setup.batch, setup.x0, weights=weights)
    b = looped.solve(setup.batch, setup.x0, weights=weights)
    assert a.ok and b.ok and a.status == b.status and a.iterations == b.iterations
    assert a.rho == b.rho
    tolerance = 1e-12 if precision == "float64" else 1e-5
    for ours, theirs in ((a.delta, b.delta), (a.w, b.w), (a.z_steps, b.z_steps),
                         (a.z_terminal, b.z_terminal), (a.u, b.u)):
        assert ours.dtype == theirs.dtype
        assert _relative(ours, theirs) <= tolerance
