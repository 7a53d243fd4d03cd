"""Tests of C3's projection by contact-mode enumeration (solvers/projection_enum.py).

References: the MIQP :func:`c3bench.problems.families.projection` (variant ``c3``) solved by the
``scip`` registry backend at high accuracy (and ``gurobi`` where installed), and the independent
brute force :func:`c3bench.solvers.modes.enumerate_modes` (``2^m`` mode QPs with their sign
constraints, Clarabel plus an exact face solve).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from c3bench.problems import families
from c3bench.problems.config import load_config
from c3bench.problems.errors import InputError
from c3bench.problems.instance import Problem
from c3bench.problems.lcs import LCS
from c3bench.problems.linearize import linearize
from c3bench.problems.scene import build_scene
from c3bench.problems.suites import sample_states, scripted_push
from c3bench.solvers import registry
from c3bench.solvers.base import settings_for
from c3bench.solvers.modes import enumerate_modes
from c3bench.solvers.projection_enum import (
    MAX_PAIRS,
    enumerated_projection,
    project_c3_enumerated,
)
from c3bench.solvers.residuals import complementarity_violation

OBJECTIVE_RTOL = 1e-8
POINT_ATOL = 1e-6


def _available(name: str) -> bool:
    try:
        return registry.get(name).availability()[0]
    except KeyError:
        return False


MIQP_BACKENDS = [name for name in ("scip", "gurobi") if _available(name)]


def _random_lcs(rng: np.random.Generator, nx: int, m: int, nu: int) -> LCS:
    root = rng.normal(size=(m, m))
    return LCS(A=np.eye(nx), B=rng.normal(size=(nx, nu)), D=rng.normal(size=(nx, m)),
               d=np.zeros(nx), E=rng.normal(size=(m, nx)),
               F=root @ root.T / m + 0.1 * np.eye(m), H=rng.normal(size=(m, nu)),
               c=rng.normal(size=m), dt=0.1)


def _problem(lcs: LCS, v: np.ndarray, U: np.ndarray) -> Problem:
    """The MIQP instance of one row: ``v`` extended by its gap, ``U`` by zeros on ``eta``."""
    nx, m = lcs.nx, lcs.nlam
    gap = lcs.gap(v[:nx], v[nx + m:], v[nx:nx + m])
    return families.projection("proj-enum", lcs, np.concatenate([v, gap]),
                               np.concatenate([U, np.zeros(m)]), "c3")


def _full(lcs: LCS, d: np.ndarray) -> np.ndarray:
    nx, m = lcs.nx, lcs.nlam
    return np.concatenate([d, lcs.gap(d[:nx], d[nx + m:], d[nx:nx + m])])


def _check_row(lcs: LCS, v: np.ndarray, U: np.ndarray, point: np.ndarray, cost: float,
               reference: np.ndarray, reference_cost: float, unique: bool) -> None:
    problem = _problem(lcs, v, U)
    full = _full(lcs, point)
    assert complementarity_violation(problem, full) <= 1e-9
    assert np.min(full[lcs.nx:lcs.nx + lcs.nlam]) >= -1e-9
    assert problem.objective(full) == pytest.approx(cost, rel=1e-10, abs=1e-12)
    assert cost == pytest.approx(reference_cost, rel=OBJECTIVE_RTOL, abs=1e-10)
    if unique:
        np.testing.assert_allclose(point, reference[:point.size], atol=POINT_ATOL)


@pytest.mark.parametrize("backend", MIQP_BACKENDS)
@pytest.mark.parametrize("zero_u", [False, True])
def test_equals_the_miqp_projection_on_random_lcs(backend: str, zero_u: bool) -> None:
    rng = np.random.default_rng(11)
    for _ in range(3):
        lcs = _random_lcs(rng, nx=3, m=3, nu=2)
        n = lcs.nx + lcs.nlam + lcs.nu
        U = rng.uniform(0.5, 3.0, n)
        if zero_u:  # u free in the projection: the minimiser is not unique, the cost is
            U[lcs.nx + lcs.nlam:] = 0.0
        v = rng.normal(size=(3, n))
        out = enumerated_projection(v, lcs, U)
        for i in range(v.shape[0]):
            result = registry.get(backend).solve(_problem(lcs, v[i], U),
                                                 settings_for("high_accuracy"))
            assert result.found and result.x is not None and result.objective is not None
            _check_row(lcs, v[i], U, out.point[i], float(out.cost[i]), result.x,
                       result.objective, unique=not zero_u)


@pytest.fixture(scope="module")
def cube() -> tuple[LCS, np.ndarray]:
    """The cube LCS at a contact-rich state of the quick suite's push (model l = 0.29)."""
    config = load_config()
    config = replace(config, mpc=replace(config.mpc, horizon=2))
    record = scripted_push(config, 1.5)
    index = sample_states(record, 2, 0.02)[0]
    scene = build_scene(l=0.29, config=config)
    x0, u_prev = record.states[index], record.inputs[max(index - 1, 0)]
    return linearize(scene, x0, u_prev, config.mpc.dt), x0


@pytest.mark.parametrize("backend", MIQP_BACKENDS)
def test_equals_the_miqp_projection_on_cube_rows(backend: str, cube: tuple[LCS, np.ndarray]
                                                 ) -> None:
    lcs, x0 = cube
    assert 4 <= lcs.nlam <= MAX_PAIRS
    nx, m, nu = lcs.nx, lcs.nlam, lcs.nu
    rng = np.random.default_rng(5)
    v = rng.normal(0.0, 1.0, (3, nx + m + nu))
    v[:, :nx] = x0 + 0.01 * v[:, :nx]
    v[:, nx:nx + m] *= 5.0
    for U in (np.concatenate([np.full(nx, 1.0), np.full(m, 50.0), np.full(nu, 0.1)]),
              np.concatenate([np.full(nx, 1000.0), np.full(m, 1.0), np.full(nu, 1.0)])):
        out = enumerated_projection(v, lcs, U)
        for i in range(v.shape[0]):
            result = registry.get(backend).solve(_problem(lcs, v[i], U),
                                                 settings_for("high_accuracy"))
            assert result.found and result.x is not None and result.objective is not None
            # cost only: near two table contacts [E F H] is nearly rank deficient
            # (sigma_min / sigma_max ~ 1e-8), the minimiser is ill-determined along a nearly
            # flat direction (points measured 1e-4 apart, costs equal to 6e-10 relative)
            _check_row(lcs, v[i], U, out.point[i], float(out.cost[i]), result.x,
                       result.objective, unique=False)


def test_equals_brute_force_enumeration_on_tiny_cases() -> None:
    rng = np.random.default_rng(7)
    for m in (1, 2, 3):
        lcs = _random_lcs(rng, nx=2, m=m, nu=1)
        n = lcs.nx + m + lcs.nu
        U = rng.uniform(0.1, 10.0, n)
        v = rng.normal(0.0, 2.0, (4, n))
        out = enumerated_projection(v, lcs, U)
        for i in range(v.shape[0]):
            x, optimum = enumerate_modes(_problem(lcs, v[i], U))
            assert x is not None
            _check_row(lcs, v[i], U, out.point[i], float(out.cost[i]), x, optimum, True)


def test_a_pair_with_both_members_zero_is_found() -> None:
    """``eta = x - lam``, ``v = (-1, -1)``: ``{lam = 0}`` alone gives ``x = -1, eta = -1`` and
    ``{eta = 0}`` alone gives ``lam = -1``; only ``lam = eta = 0`` is feasible: ``d = (0, 0)``,
    cost 2 (a projection that enumerated two-way systems without the sign check would fail)."""
    lcs = LCS(A=np.eye(1), B=np.zeros((1, 0)), D=np.zeros((1, 1)), d=np.zeros(1),
              E=np.eye(1), F=-np.eye(1), H=np.zeros((1, 0)), c=np.zeros(1), dt=0.1)
    out = enumerated_projection(np.array([-1.0, -1.0]), lcs, np.ones(2))
    np.testing.assert_allclose(out.point, [0.0, 0.0], atol=1e-12)
    assert float(out.cost) == pytest.approx(2.0, rel=1e-12)
    assert bool(out.lam_zero[0]) and bool(out.eta_zero[0])
    _, optimum = enumerate_modes(_problem(lcs, np.array([-1.0, -1.0]), np.ones(2)))
    assert optimum == pytest.approx(2.0, rel=1e-9)


def test_rows_of_any_leading_shape_are_projected_one_by_one() -> None:
    rng = np.random.default_rng(2)
    lcs = _random_lcs(rng, nx=2, m=2, nu=1)
    U = rng.uniform(0.5, 2.0, 5)
    v = rng.normal(size=(2, 3, 5))
    batch = project_c3_enumerated(v, lcs, U)
    assert batch.shape == v.shape
    for index in np.ndindex(2, 3):
        np.testing.assert_allclose(batch[index], project_c3_enumerated(v[index], lcs, U),
                                   atol=1e-12)


def test_a_row_already_complementary_is_its_own_projection() -> None:
    rng = np.random.default_rng(4)
    lcs = _random_lcs(rng, nx=2, m=3, nu=1)
    x, u = rng.normal(size=2), rng.normal(size=1)
    from c3bench.solvers.lcp import lemke

    lam = lemke(lcs.F, lcs.lcp_offset(x, u)).z
    assert lam is not None
    v = np.concatenate([x, lam, u])
    out = enumerated_projection(v, lcs, np.ones(6))
    np.testing.assert_allclose(out.point, v, atol=1e-10)
    assert float(out.cost) <= 1e-18


def test_bad_inputs_are_rejected() -> None:
    rng = np.random.default_rng(0)
    lcs = _random_lcs(rng, nx=2, m=2, nu=1)
    with pytest.raises(InputError, match="shape"):
        project_c3_enumerated(np.zeros(4), lcs, np.ones(5))
    with pytest.raises(InputError, match=">= 0"):
        project_c3_enumerated(np.zeros(5), lcs, -np.ones(5))
    with pytest.raises(InputError, match="non-finite"):
        project_c3_enumerated(np.full(5, np.nan), lcs, np.ones(5))
    big = _random_lcs(rng, nx=1, m=MAX_PAIRS + 1, nu=1)
    with pytest.raises(InputError, match="MAX_PAIRS"):
        project_c3_enumerated(np.zeros(MAX_PAIRS + 3), big, np.ones(MAX_PAIRS + 3))
    # eta = -1 whatever (x, lam, u): no complementary point exists
    empty = LCS(A=np.eye(1), B=np.zeros((1, 1)), D=np.zeros((1, 1)), d=np.zeros(1),
                E=np.zeros((1, 1)), F=np.zeros((1, 1)), H=np.zeros((1, 1)), c=-np.ones(1),
                dt=0.1)
    with pytest.raises(InputError, match="no complementary point"):
        project_c3_enumerated(np.zeros(3), empty, np.ones(3))
