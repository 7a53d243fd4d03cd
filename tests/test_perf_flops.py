"""The flop model of one C3+ control step's ADMM (bench/perf_flops.py) against hand counts."""

from __future__ import annotations

import math

import numpy as np
import pytest

from c3bench.bench.perf_flops import (
    MachineRates,
    MatmulProbe,
    admm_flops,
    factorisation_flops,
    matmul_rate,
    qp_pass_flops,
    riccati_step_flops,
)
from c3bench.problems.errors import InputError

# Hand count for nx = nlam = nu = 1 (nv = 2, ny = 3, ns = 4), operation by operation of
# solvers/fast.py (factorize's loop body, its setup, _qp_solve, solve_lq, the projection).
RICCATI_STEP_TINY = (
    8       # S [A Bv d]: (1x1)(1x4)
    + 12 + 6  # Bv^T (S [A Bv]): (2x1)(1x3), + H_v (2x3)
    + 16    # inverse of Q_vv (2x2): 2 * 2^3
    + 16    # G_v [Q_vx Bv^T]: (2x2)(2x2)
    + 8 + 2 + 8 + 2  # refine K: Q_vv K (2x2)(2x1), + Q_vx, G_v (residual), K +=
    + 4 + 1   # Bv K: (1x2)(2x1), + A
    + 2 + 1 + 4 + 1  # A^T (S A): (1x1)(1x1), + H_xx, Q_vx^T K: (1x2)(2x1), +
    + 2     # symmetrise: add and halve
)
SETUP_TINY = 18 + 6 + 18 + 4 + 4 + 1  # H_y(rho) 2*9, D 2*3, scale H_y 2*9, A+P_T 4, Bv 4, d 1
MTM_TINY = 18                          # M^T M: (3x1)(1x3)
GRADIENT_TINY = 4 + 3 + 1 + 1 + 6 + 3 + 3  # anchor, *g2, +gx, eta term, M^T e, *2rho, +=
PASSES_TINY = (3 + 1 + 1     # scale g_y, g_T, x0
               + 12          # W_g g_v: (3x2)(2x1)
               + 0 + 1       # shift (T-1 = 0 additions of S d) + pre add
               + 1           # e_T = S d + g_T
               + 6 + 3       # backward: W_e e (3x1)(1x1), + pre
               + 4 + 1       # Bv kk + d
               + 6 + 3       # forward: KA x, + addend
               + 2 + 1)      # unscale v, x
ETA_TINY = 6 + 1               # M y + c
PROJECTION_TINY = 4 + 5        # v = z + w (4), per pair 2 clamps, 2 scalings, 1 comparison
DUAL_TINY = 4 + 4              # z - delta, w + (z - delta)


def test_tiny_case_matches_the_hand_count() -> None:
    assert riccati_step_flops(1, 2) == RICCATI_STEP_TINY == 93
    assert factorisation_flops(1, 2, 1) == RICCATI_STEP_TINY + SETUP_TINY == 144
    assert qp_pass_flops(1, 1, 1, 1) == GRADIENT_TINY + PASSES_TINY + ETA_TINY == 73
    flops = admm_flops(1, 1, 1, horizon=1, iterations=1, samples=1, rho_values=1)
    assert flops.factorisation == MTM_TINY + 144
    assert flops.qp_passes == 73 and flops.projection == PROJECTION_TINY
    assert flops.dual == DUAL_TINY and flops.total == 252


def test_two_steps_hand_count() -> None:
    # T = 2 (nx = nlam = nu = 1): the passes' shift adds S_{k+1} d once, every per-step term
    # doubles: 8 + 24 + 3 + 1 + 18 + 10 + 18 + 6 = 88 for solve_lq, 42 gradient, 14 eta.
    assert qp_pass_flops(1, 1, 1, 2) == 42 + 88 + 14
    assert factorisation_flops(1, 2, 2) == 2 * 93 + SETUP_TINY


def test_samples_iterations_and_rho_values_scale_their_parts() -> None:
    flops = admm_flops(1, 1, 1, horizon=1, iterations=3, samples=2, rho_values=2)
    assert flops.factorisation == 2 * (MTM_TINY + 2 * 144)
    assert flops.qp_passes == 2 * 3 * 73
    assert flops.projection == 2 * 3 * (PROJECTION_TINY + 2)  # shared-input mean: 2 T nu
    assert flops.dual == 2 * 3 * DUAL_TINY
    independent = admm_flops(1, 1, 1, 1, 3, 2, 2, shared_inputs=False)
    assert independent.projection == 2 * 3 * PROJECTION_TINY


def test_cube_dimensions_give_the_issue_figure() -> None:
    # Issue 12: about 1.3 MFLOP per sample, 89 % of it in the 10 factorisations (nx 10,
    # nlam 6, nu 2, T 7, 10 iterations), found by an independent count.
    # The issue counted the numpy code before the gain's refinement (solvers/riccati.py,
    # "accuracy of the gain": 4 nv^2 nx + 2 nv nx per step, nv = 8), which adds 13 %.
    flops = admm_flops(10, 6, 2, horizon=7, iterations=10, samples=1)
    refinement = 10 * 7 * (4 * 8 * 8 * 10 + 2 * 8 * 10)
    assert flops.total - refinement == pytest.approx(1.3e6, rel=0.05)
    assert (flops.factorisation - refinement) / (flops.total - refinement) == pytest.approx(
        0.89, abs=0.01)
    assert flops.factorisation_share == pytest.approx(0.90, abs=0.01)
    assert admm_flops(10, 6, 2, 7, 10, 16).total == pytest.approx(
        16 * flops.total + 16 * 7 * 10 * 2 * 2, rel=1e-12)


@pytest.mark.parametrize("arguments", [(0, 1, 1, 1, 1, 1), (1, -1, 1, 1, 1, 1),
                                       (1, 1, 1, 1, 1, 0), (1, 1, 1, 0, 1, 1)])
def test_bad_dimensions_are_rejected(arguments: tuple[int, int, int, int, int, int]) -> None:
    nx, nlam, nu, horizon, iterations, samples = arguments
    with pytest.raises(InputError):
        admm_flops(nx, nlam, nu, horizon, iterations, samples)


def test_matmul_rate_is_a_finite_positive_rate_per_precision() -> None:
    rate = matmul_rate(np.float32, size=32, repeats=2)
    assert math.isfinite(rate) and rate > 0
    rates = MachineRates(float64=1.0, float32=2.0)
    assert rates.of("float32") == 2.0 and rates.of("float64") == 1.0
    with pytest.raises(InputError):
        matmul_rate(np.float64, size=0)


def test_matmul_probe_keeps_the_median_of_its_samples() -> None:
    probe = MatmulProbe(size=32, repeats=3)
    assert all(math.isnan(rate) for rate in (probe.rates().float64, probe.rates().float32))
    for _ in range(3):
        probe.sample()
    for precision in ("float64", "float32"):
        samples = probe.samples[precision]
        assert len(samples) == 3 and all(math.isfinite(v) and v > 0 for v in samples)
        assert probe.rates().of(precision) == sorted(samples)[1]
    with pytest.raises(InputError):
        MatmulProbe(repeats=0)
