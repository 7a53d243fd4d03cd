"""One ADMM, four kernels: every kernel gives the same control step (issue: one algorithm).

The loop (dual update, residuals, schedule, stopping, output) is defined once
(``solvers/admm/loop.py``); the kernels differ only in how they compute the QP step and the
projection. Compared here on contact-rich states of the scripted push, for the three rho
schedules, cold and warm-started (a previous step's shifted iterates), limits on and off:
numpy Riccati (the readable batched kernel) against the compiled and JAX kernels to 1e-9, and
the reference kernel (stacked QP through Clarabel at high accuracy) to the QP solver's accuracy.
"""

from __future__ import annotations

import re
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from c3bench.problems.config import load_config
from c3bench.problems.lcs import LCSBatch
from c3bench.problems.linearize import linearize
from c3bench.problems.linearize_batch import BatchLinearizer
from c3bench.problems.scene import build_mpc, build_scene
from c3bench.problems.suites import sample_states, scripted_push
from c3bench.solvers.admm.compiled_solver import CompiledC3Plus
from c3bench.solvers.admm.loop import shift_warm_start as shift
from c3bench.solvers.base import settings_for
from c3bench.solvers.c3 import C3Options, solve_c3
from c3bench.solvers.fast import FastC3Plus

CONFIG = load_config()
SCHEDULES = ("geometric", "adaptive", "residual_balancing")
ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def states() -> list[tuple[np.ndarray, np.ndarray]]:
    record = scripted_push(CONFIG)
    return [(record.states[i], record.inputs[max(i - 1, 0)])
            for i in sample_states(record, 3, 0.02)]


def _relative(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.max(np.abs(a - b)) / max(1.0, float(np.max(np.abs(b)))))


@pytest.mark.parametrize("schedule", SCHEDULES)
@pytest.mark.parametrize("limits", [True, False])
def test_batched_kernels_agree(states: list[tuple[np.ndarray, np.ndarray]], schedule: str,
                               limits: bool) -> None:
    mpc = build_mpc(build_scene(l=0.29, config=CONFIG), CONFIG.mpc)
    options = C3Options(rho_schedule=schedule, keep_iterates=False, use_limits=limits)
    linearizer = BatchLinearizer((0.28, 0.29, 0.31), CONFIG)
    kernels = {"numpy": FastC3Plus(mpc, options, record_residuals=True),
               "compiled": CompiledC3Plus(mpc, options, record_residuals=True)}
    try:
        from c3bench.solvers.fast_jax import JaxC3Plus, jax_available

        if jax_available():
            kernels["jax"] = JaxC3Plus(mpc, options)
    except ImportError:
        pass
    for x, u in states:
        lcs = linearizer.linearize(x, u, CONFIG.mpc.dt)
        weights = [0.2, 0.5, 0.3]
        cold = {name: k.solve(lcs, x, weights) for name, k in kernels.items()}
        delta, w = shift(cold["numpy"].delta, cold["numpy"].w)
        given = delta.copy(), w.copy()
        warm = {name: k.solve(lcs, x, weights, delta, w) for name, k in kernels.items()}
        # the loop takes given iterates without a copy: no kernel may write into them
        assert np.array_equal(delta, given[0]) and np.array_equal(w, given[1])
        for results in (cold, warm):
            reference = results["numpy"]
            assert reference.ok
            for name, result in results.items():
                assert result.ok, name
                assert result.rho == pytest.approx(reference.rho), name
                assert _relative(result.delta, reference.delta) <= 1e-9, name
                assert _relative(result.w, reference.w) <= 1e-9, name
                np.testing.assert_allclose(result.u, reference.u, rtol=1e-9, atol=1e-9)
                if limits:  # the box is in the projection: delta keeps the force limit
                    u_slice = reference.layout.index(0, "u")
                    assert np.abs(result.delta[:, :, u_slice]).max() <= 30 + 1e-9


@pytest.mark.parametrize("schedule", SCHEDULES)
def test_reference_kernel_matches_the_batched_one(states: list[tuple[np.ndarray, np.ndarray]],
                                                  schedule: str) -> None:
    """n = 1, no limits (the reference puts limits in its QP, the batched kernels in their
    projection: two splittings): the stacked QP through Clarabel gives the Riccati kernel's
    step to Clarabel's accuracy, cold and warm."""
    model = build_scene(l=0.29, config=CONFIG)
    mpc = build_mpc(model, CONFIG.mpc)
    options = C3Options(rho_schedule=schedule, keep_iterates=False, use_limits=False,
                        qp_backend="clarabel", qp_settings=settings_for("high_accuracy"))
    for x, u in states[:2]:
        lcs = linearize(model, x, u, CONFIG.mpc.dt)
        fast = FastC3Plus(mpc, replace(options, qp_settings=None))
        batch = LCSBatch.from_lcs([lcs])
        first = fast.solve(batch, x)
        reference = solve_c3(lcs, mpc, x, options)
        assert _relative(reference.delta, first.delta) <= 1e-6
        delta, w = shift(first.delta, first.w)
        warm_fast = fast.solve(batch, x, None, delta, w)
        given = delta.copy(), w.copy()
        warm_reference = solve_c3(lcs, mpc, x, options, delta[0], w[0])
        assert np.array_equal(delta, given[0]) and np.array_equal(w, given[1])  # not written
        assert _relative(warm_reference.delta, warm_fast.delta) <= 1e-6
        assert warm_reference.rho == pytest.approx(warm_fast.rho)


def test_one_definition_of_the_iteration_schedules_and_closed_form() -> None:
    """The ADMM iteration, the dual update, the dual rescaling, each rho schedule and the C3+
    closed form are defined once in the package sources (the compiled plan run calls them)."""
    sources = {path: path.read_text() for folder in ("solvers", "bench", "problems")
               for path in (ROOT / folder).rglob("*.py")}
    patterns = {"iteration": r"\ndef admm_iteration\(", "dual update": r"\ndef dual_update\(",
                "dual rescaling": r"\ndef scale_dual\(", "plan ratios": r"\ndef plan_ratios\(",
                "geometric": r"\nclass Geometric\(", "adaptive": r"\nclass Adaptive\(",
                "balancing": r"\nclass ResidualBalancing\(",
                "closed form": r"sqrt_w_lam \* a_plus >= sqrt_w_eta \* b_plus"}
    for what, pattern in patterns.items():
        where = [path.name for path, text in sources.items() if re.search(pattern, text)]
        assert len(where) == 1, (what, where)
        assert sum(len(re.findall(pattern, text)) for text in sources.values()) == 1, what
    # no other file compares weighted positive parts of a pair (a second closed form)
    second = [path.name for path, text in sources.items()
              if re.search(r"sqrt\w*\s*\*\s*\w+\s*>=\s*\w*sqrt", text)
              and path.name != "projection.py"]
    assert not second, second
