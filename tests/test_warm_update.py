"""Warm cells through each solver's update API (the warm contract of solvers/timing.py).

* For every backend with an update API (OSQP, ProxQP dense and sparse, Clarabel, PIQP):
  ``warm_solve`` (object prepared untimed, then update + solve) returns the cold solution,
  primal and duals, on the closed-form QP of test_qp_backends and on a random QP with active
  inequalities and bounds whose solution is a high-accuracy Clarabel solve cross-checked by
  ProxQP; the warm start given is the solution of a perturbed problem (a predecessor).
* The recorded ``setup_time`` of a warm solve is the update: the update call runs inside the
  setup lap, the solve call inside the solve lap, and nothing constructs or sets up a solver
  inside either (checked by recording which lap each call of the solver object runs in, not
  by timing).
* A backend without an update API pays a full solve (``warm_update`` = 0) and its
  ``warm_support`` says so.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest

from c3bench.problems.instance import Problem
from c3bench.solvers import registry
from c3bench.solvers.base import WarmStart, settings_for
from c3bench.solvers.isolation import solve_isolated
from c3bench.solvers.timing import (
    SETUP,
    SOLVE,
    WARM_EMULATED,
    WARM_UPDATE,
    Stopwatch,
    UpdatableBackend,
    warm_solve,
    warm_support,
)
from tests.test_qp_backends import TINY_X, TINY_Y, TINY_Z, TINY_Z_BOX, tiny_problem

UPDATABLE = ("osqp", "proxqp_dense", "proxqp_sparse", "clarabel", "piqp")


def _available(name: str) -> None:
    ok, reason = registry.get(name).availability()
    if not ok:
        pytest.skip(f"{name} unavailable: {reason}")


def random_qp(seed: int = 3, n: int = 20) -> Problem:
    """A strictly convex QP with 4 equalities, 12 inequalities and bounds, several active
    (the unconstrained minimiser lies far outside them)."""
    rng = np.random.default_rng(seed)
    M = rng.standard_normal((n, n))
    return Problem(name="random", family="c3_qp", P=M @ M.T + np.eye(n),
                   q=20.0 * rng.standard_normal(n), A=rng.standard_normal((4, n)),
                   b=rng.standard_normal(4), G=rng.standard_normal((12, n)),
                   h=rng.uniform(0.0, 1.0, 12), lb=np.full(n, -0.5), ub=np.full(n, 0.5))


def predecessor_start(problem: Problem, backend: str) -> WarmStart:
    """The solution of ``problem`` with ``q`` perturbed by 1 %: a previous iterate's answer."""
    moved = Problem(**{**problem.__dict__, "q": problem.q * 1.01})
    result = registry.get(backend).solve(moved, settings_for("high_accuracy"))
    assert result.found
    return WarmStart(result.x, result.y, result.z)


@pytest.mark.parametrize("name", UPDATABLE)
def test_warm_update_equals_cold_on_closed_form(name: str) -> None:
    _available(name)
    backend = registry.get(name)
    settings = settings_for("high_accuracy")
    start = WarmStart(TINY_X + 0.05, TINY_Y, TINY_Z)
    warm = warm_solve(backend, tiny_problem(), settings, start)
    assert warm.found and warm.diagnostics[WARM_UPDATE] == 1.0
    for got, want in ((warm.x, TINY_X), (warm.y, TINY_Y), (warm.z, TINY_Z),
                      (warm.z_box, TINY_Z_BOX)):
        np.testing.assert_allclose(got, want, atol=1e-6)


@pytest.mark.parametrize("name", UPDATABLE)
def test_warm_update_equals_cold_on_random_qp(name: str) -> None:
    _available(name)
    problem = random_qp()
    settings = settings_for("high_accuracy")
    reference = registry.get("clarabel").solve(problem, settings)
    check = registry.get("proxqp_dense").solve(problem, settings)
    assert reference.found and check.found
    np.testing.assert_allclose(reference.x, check.x, atol=1e-7)
    active = np.sum(problem.G @ reference.x > problem.h - 1e-7) + np.sum(
        np.abs(np.abs(reference.x) - 0.5) < 1e-7)
    assert active >= 2  # the update must carry h and the bounds, not only q and b
    backend = registry.get(name)
    cold = backend.solve(problem, settings)
    warm = warm_solve(backend, problem, settings, predecessor_start(problem, name))
    assert cold.found and warm.found
    scale = max(1.0, float(np.max(np.abs(reference.x))))
    np.testing.assert_allclose(warm.x, reference.x, atol=1e-6 * scale)
    np.testing.assert_allclose(warm.x, cold.x, atol=1e-6 * scale)
    np.testing.assert_allclose(warm.y, reference.y, rtol=1e-5, atol=1e-5)
    assert warm.objective == pytest.approx(reference.objective, rel=1e-8, abs=1e-8)


@pytest.mark.parametrize("name", UPDATABLE)
def test_warm_update_is_the_setup_time(name: str, monkeypatch: pytest.MonkeyPatch) -> None:
    """The setup lap of a warm solve holds the update call and nothing that constructs."""
    _available(name)
    backend = registry.get(name)
    assert isinstance(backend, UpdatableBackend)
    open_lap: list[str] = []
    original_lap = Stopwatch.lap

    @contextlib.contextmanager
    def tracked(self: Stopwatch, lap_name: str) -> Iterator[None]:
        open_lap.append(lap_name)
        try:
            with original_lap(self, lap_name):
                yield
        finally:
            open_lap.pop()

    monkeypatch.setattr(Stopwatch, "lap", tracked)
    calls: list[tuple[str, str]] = []

    class Recorder:
        """Forwards to the solver object, recording each method call and its lap."""

        def __init__(self, target: Any) -> None:
            self._target = target

        def __getattr__(self, attribute: str) -> Any:
            value = getattr(self._target, attribute)
            if not callable(value):
                return value

            def call(*args: Any, **kwargs: Any) -> Any:
                calls.append((attribute, open_lap[-1] if open_lap else ""))
                return value(*args, **kwargs)
            return call

    problem = random_qp()
    settings = settings_for("high_accuracy")
    prepared = backend.prepare(problem, settings)
    assert not calls
    wrapped = ((Recorder(prepared[0]), *prepared[1:]) if isinstance(prepared, tuple)
               else Recorder(prepared))
    result = backend.resolve(wrapped, problem, settings, predecessor_start(problem, name))
    assert result.found
    laps = dict(calls)
    assert laps["update"] == SETUP
    assert laps["solve"] == SOLVE
    assert not {"setup", "init"} & set(laps), calls  # nothing set up inside the timed laps
    assert all(lap in (SETUP, SOLVE) for _, lap in calls), calls


def test_emulated_backend_pays_a_full_solve() -> None:
    _available("daqp")
    backend = registry.get("daqp")
    assert not isinstance(backend, UpdatableBackend)
    assert warm_support(backend) == WARM_EMULATED
    result = warm_solve(backend, tiny_problem(), settings_for("high_accuracy"),
                        WarmStart(TINY_X))
    assert result.diagnostics[WARM_UPDATE] == 0.0
    np.testing.assert_allclose(result.x, TINY_X, atol=1e-6)


def test_isolated_warm_cell_uses_the_update_api() -> None:
    """A benchmark's warm cell (``solve_isolated`` with a warm start) goes through
    ``warm_solve``; a cold one does not."""
    _available("osqp")
    problem = random_qp()
    start = predecessor_start(problem, "osqp")
    settings = settings_for("mid_accuracy")
    warm = solve_isolated("osqp", problem, settings, warm_start=start, repeats=2, warmup=True)
    cold = solve_isolated("osqp", problem, settings, repeats=1)
    assert warm.found and warm.diagnostics[WARM_UPDATE] == 1.0, warm.status
    assert WARM_UPDATE not in cold.diagnostics
    np.testing.assert_allclose(warm.x, cold.x, atol=1e-3)
