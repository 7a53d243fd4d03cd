"""The dual's warm start across control steps (``C3Options.warm_dual``).

Rho restarts from ``rho0`` at every control step. Keeping the previous step's *scaled* dual then
changes the multiplier ``2 G w`` by ``rho0 / rho_final``; under residual balancing, where rho can
end below ``rho0``, that factor compounds from step to step and the plans diverge (measured: the
plan's predicted next state 1e51 away from the LCS rollout of its own input within a second).
Restarting ``w`` from zero, as the C3 reference implementation does, keeps the plan consistent
and the geometric schedule's behaviour (whose final rho is 512 ``rho0``, so the kept scaled dual
was already nearly zero).
"""

from __future__ import annotations

import numpy as np
import pytest

from c3bench.bench.closed_loop import ControllerSpec, run_closed_loop
from c3bench.problems.config import load_config
from c3bench.solvers.admm import C3Options, DualWarmStart

PLAN_CONSISTENCY_BOUND = 50.0
"""Largest plan-vs-LCS state error (mixed SI norm) a sane plan shows on the cube; the
diverging runs reach 1e25-1e51, the sane ones about 3-6."""


def _plan_error(schedule: str, warm_dual: str) -> float:
    spec = ControllerSpec(controller="c3plus-fast", rho_schedule=schedule, warm_dual=warm_dual)
    _, _, outcome = run_closed_loop(spec, load_config(), 1.0)
    assert outcome.metrics is not None
    return float(outcome.metrics.plan_lcs_error_max)


def test_default_restarts_the_dual_from_zero() -> None:
    assert C3Options().warm_dual == DualWarmStart.ZERO
    with pytest.raises(ValueError, match="warm_dual"):
        C3Options(warm_dual="unscaled")


@pytest.mark.parametrize("schedule", ["geometric", "residual_balancing"])
def test_zero_dual_keeps_plans_consistent(schedule: str) -> None:
    assert _plan_error(schedule, "zero") < PLAN_CONSISTENCY_BOUND


def test_scaled_dual_diverges_under_residual_balancing() -> None:
    error = _plan_error("residual_balancing", "scaled")
    assert not np.isfinite(error) or error > 1e6
