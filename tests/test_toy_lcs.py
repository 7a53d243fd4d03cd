"""Tests of the point mass between two soft walls (problems/toy_lcs.py), the brute-force global
MPC optimum (solvers/brute_force.py) and the C3 / C3+ controller on that non-cube LCS.

References: the physics by hand (closed-form step of a mass against a spring wall), the MIQP
solve of :func:`c3bench.problems.families.mpcc` by ``scip``, and the brute-force optimum.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Any

import numpy as np
import pytest

from c3bench.problems import families
from c3bench.problems.errors import InputError
from c3bench.problems.toy_lcs import point_mass_lcs, point_mass_mpc, resting_position
from c3bench.solvers import registry
from c3bench.solvers.base import settings_for
from c3bench.solvers.brute_force import global_mpc_optimum
from c3bench.solvers.lcs_simulation import Controller, Simulation, simulate

DT, MASS, STIFFNESS, HALF_WIDTH = 0.05, 1.0, 50.0, 0.5
TARGET, Q_POSITION, R_INPUT = 0.7, 10.0, 0.01
STATES = ((0.0, 0.0), (0.3, 1.0), (0.45, 0.5), (0.55, 0.0), (0.65, 0.0), (-0.3, -2.0))
"""Free flight, approach, about to touch, pressing, pressing hard, flying to the left wall."""


def _scip_available() -> bool:
    try:
        return registry.get("scip").availability()[0]
    except KeyError:
        return False


def _step_by_hand(p: float, v: float, u: float) -> tuple[float, float, float, float]:
    """One step of the mass: free flight unless the next position penetrates a wall, then the
    wall's spring force ``K * penetration`` of the next position solves the linear step."""
    a = DT**2 / MASS
    free = p + DT * v + a * u
    lam1 = lam2 = 0.0
    if free > HALF_WIDTH:  # p' = free - a K (p' - L)
        p_next = (free + a * STIFFNESS * HALF_WIDTH) / (1 + a * STIFFNESS)
        lam2 = STIFFNESS * (p_next - HALF_WIDTH)
    elif free < -HALF_WIDTH:  # p' = free + a K (-L - p')
        p_next = (free - a * STIFFNESS * HALF_WIDTH) / (1 + a * STIFFNESS)
        lam1 = STIFFNESS * (-HALF_WIDTH - p_next)
    else:
        p_next = free
    v_next = v + DT / MASS * (u + lam1 - lam2)
    return p_next, v_next, lam1, lam2


def _constant(u: float) -> Controller:
    force = np.array([u])

    def law(x: np.ndarray) -> np.ndarray:
        return force

    return law


def test_lcs_steps_like_the_mass_against_spring_walls() -> None:
    lcs = point_mass_lcs(DT, MASS, STIFFNESS, HALF_WIDTH)
    assert np.all(np.linalg.eigvalsh(lcs.F) > 0)
    rng = np.random.default_rng(0)
    contacts = 0
    for _ in range(40):
        p, v, u = rng.uniform(-0.8, 0.8), rng.uniform(-3, 3), rng.uniform(-20, 20)
        sim = simulate(lcs, np.array([p, v]), _constant(u), 1)
        p_next, v_next, lam1, lam2 = _step_by_hand(p, v, u)
        np.testing.assert_allclose(sim.states[1], [p_next, v_next], atol=1e-10)
        np.testing.assert_allclose(sim.forces[0], [lam1, lam2], atol=1e-8)
        contacts += lam1 > 0 or lam2 > 0
    assert 5 <= contacts <= 35  # both regimes were exercised


def test_simulate_rejects_bad_controller_output() -> None:
    lcs = point_mass_lcs()
    with pytest.raises(InputError, match="controller"):
        simulate(lcs, np.zeros(2), lambda x: np.array([np.nan]), 2)


@pytest.mark.skipif(not _scip_available(), reason="scip is unavailable")
@pytest.mark.parametrize("x0", STATES[:4])
def test_global_optimum_equals_the_miqp_optimum(x0: tuple[float, float]) -> None:
    lcs = point_mass_lcs(DT, MASS, STIFFNESS, HALF_WIDTH)
    mpc = point_mass_mpc(TARGET, horizon=4, dt=DT, q_position=Q_POSITION, r_input=R_INPUT)
    cost, trajectory = global_mpc_optimum(lcs, mpc, np.array(x0))
    assert trajectory.modes == 2 ** 8
    problem = families.mpcc("toy-mpcc", lcs, mpc, np.array(x0))
    result = registry.get("scip").solve(problem, settings_for("high_accuracy"))
    assert result.found and result.objective is not None
    assert cost == pytest.approx(result.objective, rel=1e-6)
    # the trajectory is a point of the MPCC with that cost
    xs, us = trajectory.x, trajectory.u
    assert mpc.cost(xs, us) == pytest.approx(cost, rel=1e-9)
    for k in range(mpc.horizon):
        np.testing.assert_allclose(xs[k + 1], lcs.next_state(xs[k], us[k], trajectory.lam[k]),
                                   atol=1e-8)
        gap = lcs.gap(xs[k], us[k], trajectory.lam[k])
        assert np.max(np.abs(np.minimum(trajectory.lam[k], gap))) <= 1e-8


def test_global_optimum_rejects_too_many_modes() -> None:
    lcs = point_mass_lcs()
    with pytest.raises(InputError, match="max_pairs"):
        global_mpc_optimum(lcs, point_mass_mpc(horizon=7), np.zeros(2))


# --- the controller on this LCS (needs the lead's projection options) ----------------------
U_PEER = {"x": 1000.0, "lam": 1.0, "u": 1.0, "eta": 1.0}
"""The issue's peer tuning: ``U`` = 1000 on x, 1 on lambda (and 1 on u, eta); ``G`` = rho0."""


def _controller_api() -> tuple[Any, Any, Any]:
    """``(C3Options, C3Controller, solve_c3)`` with ``projection_weights`` and the
    ``"enumeration"`` projection, or skip."""
    for module in ("c3bench.solvers.admm", "c3bench.solvers.c3"):
        try:
            options = __import__(f"{module}.options" if module.endswith("admm") else module,
                                 fromlist=["C3Options"]).C3Options
            controller = __import__(f"{module}.controller" if module.endswith("admm")
                                    else module, fromlist=["C3Controller"])
        except (ImportError, AttributeError):
            continue
        names = {field.name for field in dataclasses.fields(options)}
        if "projection_weights" in names and hasattr(controller, "C3Controller"):
            return options, controller.C3Controller, controller.solve_c3
    pytest.skip("the controller has no projection_weights option yet (issue 12: "
                "C3Options.projection_weights and projection_backend='enumeration')")
    raise AssertionError  # unreachable


def _options(variant: str) -> Any:
    options, _, _ = _controller_api()
    extra = {"projection_backend": "enumeration"} if variant == "c3" else {}
    return options(variant=variant, projection_weights=U_PEER, qp_backend="clarabel",
                   **extra)


V_REST = 0.01
"""Speed (m/s) below which the mass counts as at rest over the last 10 steps."""
FORCE_TOLERANCE = MASS * V_REST / DT
"""0.2 N: a contact force off by ``f`` changes the next velocity by ``dt f / M``
(``v' = v + dt / M (u + lam_1 - lam_2)``), so a plan whose first-step force differs from the
LCS's by more than ``M V_REST / dt`` predicts a velocity change the resting mass does not
make. Measured: C3 0.003 N off (9.674 against 9.677 N), C3+ 0.005 N (0.183 against 0.178 N);
a model without walls, walls at +-5 m, a projection that is the identity or drops ``lam``
plan 0-0.03 N against 1.3-3.4 N."""
REST_CREEP = V_REST * 10 * DT
"""5 mm: how far a mass moving at ``V_REST`` creeps over the last 10 steps while counting as
at rest; the tolerance of a rest position."""


@dataclasses.dataclass
class Loop:
    """A closed loop on the LCS: the rollout and the controller's solution of every step."""

    sim: Simulation
    plans: list[Any]


_LOOPS: dict[str, Loop] = {}


def _closed_loop(variant: str) -> Loop:
    """60 steps (3 s) of the controller on the LCS from rest at the centre (cached)."""
    if variant not in _LOOPS:
        _, controller_class, _ = _controller_api()
        lcs = point_mass_lcs(DT, MASS, STIFFNESS, HALF_WIDTH)
        mpc = point_mass_mpc(TARGET, horizon=4, dt=DT, q_position=Q_POSITION,
                             r_input=R_INPUT)
        controller = controller_class(_options(variant))
        plans: list[Any] = []

        def law(x: np.ndarray) -> np.ndarray:
            solution = controller.step(lcs, mpc, x)
            plans.append(solution)
            return np.asarray(solution.u)

        _LOOPS[variant] = Loop(simulate(lcs, np.zeros(2), law, 60), plans)
    return _LOOPS[variant]


@functools.cache
def _exact_mpc_rest() -> float:
    """Where the exact MPC (the brute-force optimum every step, on this module's LCS and MPC)
    rests against the right wall: the ``p`` whose optimal first input holds the mass still,
    ``u_0*(p, 0) = K (p - L)`` (then ``p' = p``: the wall's force ``K (p' - L)`` balances the
    input). By fixed-point iteration ``p <- L + u_0*(p, 0) / K``: ``u_0*`` barely depends on
    ``p`` (5.98-6.00 N over 0.52-0.70 m), so it contracts by ~1e-3 per step. Cached: the same
    for every variant."""
    lcs = point_mass_lcs(DT, MASS, STIFFNESS, HALF_WIDTH)
    mpc = point_mass_mpc(TARGET, horizon=4, dt=DT, q_position=Q_POSITION, r_input=R_INPUT)
    p = TARGET
    for _ in range(6):
        _, plan = global_mpc_optimum(lcs, mpc, np.array([p, 0.0]))
        p, previous = HALF_WIDTH + float(plan.u[0][0]) / STIFFNESS, p
        if abs(p - previous) < 1e-7:
            return p
    raise AssertionError(f"the exact MPC's rest did not converge: {previous} -> {p}")


@pytest.mark.parametrize("variant", ["c3", "c3plus"])
def test_controller_comes_to_rest_against_the_wall(variant: str) -> None:
    """Closed loop on the LCS itself from rest at the centre, 60 steps (3 s), target 0.7 m
    beyond the right wall at 0.5 m: the mass must travel, touch the wall and stay there,
    pressing, with bounded forces (stabilisation, with contact); and the controller's plan
    must know the wall: over the last 10 steps its first input is the one applied and its
    first-step contact forces are the LCS's (within :data:`FORCE_TOLERANCE`; the right wall's
    nonzero, as the plant's), which a controller blind to contact (a model without walls or
    with walls elsewhere, a projection that ignores complementarity, a law that is not the
    plan's) does not satisfy."""
    loop = _closed_loop(variant)
    sim = loop.sim
    mpc = point_mass_mpc(TARGET, horizon=4, dt=DT, q_position=Q_POSITION, r_input=R_INPUT)
    last = sim.states[-10:]
    assert np.all(np.abs(sim.inputs) <= mpc.force_limit + 1e-9)
    assert np.all(sim.forces <= STIFFNESS * (TARGET - HALF_WIDTH) + 1e-6)  # no wall pierced
    assert np.all(np.abs(last[:, 1]) <= V_REST)  # at rest
    assert np.all(last[:, 0] >= HALF_WIDTH) and np.all(last[:, 0] <= TARGET + REST_CREEP)
    assert np.all(sim.forces[-10:, 1] > 0) and np.all(sim.forces[-10:, 0] == 0)
    for k in range(len(loop.plans) - 10, len(loop.plans)):
        plan = loop.plans[k]
        assert plan.ok, plan.status
        first = plan.delta0[0]
        planned_u = np.clip(first[plan.layout.index(0, "u")], -mpc.force_limit,
                            mpc.force_limit)
        np.testing.assert_allclose(sim.inputs[k], planned_u, atol=1e-9)
        planned_lam = first[plan.layout.index(0, "lam")]
        assert np.all(np.abs(planned_lam - sim.forces[k]) <= FORCE_TOLERANCE), \
            (k, planned_lam, sim.forces[k])
        assert planned_lam[1] > 0  # the plan presses the right wall, as the mass does


@pytest.mark.parametrize("variant", [
    "c3",
    pytest.param("c3plus", marks=pytest.mark.xfail(
        strict=True, reason="measured: C3+ (U peer tuning, 10 iterations) stalls on the wall "
        "surface, 0.501-0.505 m after 20-80 steps with 0.1-0.25 N of contact force, while the "
        "exact MPC rests at 0.62 m and C3 at 0.69 m; an independent C3+ from the papers "
        "(test_c3plus_independent.py) stalls the same, so it is the method's, not the code's")),
])
def test_controller_presses_the_wall_like_the_optimum(variant: str) -> None:
    """The rest position must lie between the exact MPC's (the brute-force optimum every step,
    :func:`_exact_mpc_rest`: 0.620 m, pressing with 6.0 N) and the target, within
    :data:`REST_CREEP`. Measured (60 steps): C3 rests at 0.693 m (9.7 N), C3+ at 0.504 m; a
    controller that ignores the walls rests at 0.567 m (3.4 N) and the PD law
    ``u = 40 (0.7 - p) - 10 v`` at 0.589 m (4.5 N), pressing less than the optimum."""
    sim = _closed_loop(variant).sim
    exact = _exact_mpc_rest()
    assert exact == pytest.approx(0.620, abs=1e-3)  # the audit's exact-MPC closed loop
    # deeper than the static optimum of the stage cost (0.557 m): the terminal weight
    # (10 Q) pulls the plan toward the target
    assert exact > resting_position(TARGET, Q_POSITION, R_INPUT, STIFFNESS, HALF_WIDTH)
    assert exact - REST_CREEP <= sim.states[-1, 0] <= TARGET + REST_CREEP


C3_GAP = 0.10
"""Relative gap allowed between the cost of C3's planned inputs (rolled out on the LCS) and
the global optimum. Measured with the peer U at the six :data:`STATES`: 0.8 %, 0.3 %, 1.0 %,
0.4 %, 6.6 %, 5.4 %; projecting in G instead: up to 364 % (at 0.65 m, pressing)."""


@pytest.mark.parametrize("x0", STATES)
def test_c3_first_plan_is_near_the_global_optimum(x0: tuple[float, float]) -> None:
    """The inputs of C3's first plan (``u`` of ``delta``, clipped), rolled out on the LCS,
    form a feasible MPCC point, so their cost ``J_C3 >= J*``; C3 must be within
    :data:`C3_GAP` of ``J*``."""
    _, _, solve_c3 = _controller_api()
    from c3bench.solvers.c3 import rollout

    lcs = point_mass_lcs(DT, MASS, STIFFNESS, HALF_WIDTH)
    mpc = point_mass_mpc(TARGET, horizon=4, dt=DT, q_position=Q_POSITION, r_input=R_INPUT)
    optimum, _ = global_mpc_optimum(lcs, mpc, np.array(x0))
    solution = solve_c3(lcs, mpc, np.array(x0), _options("c3"))
    assert solution.ok
    inputs = np.clip(solution.delta[0][:, solution.layout.index(0, "u")], -mpc.force_limit,
                     mpc.force_limit)
    rolled = rollout(lcs, np.array(x0), inputs)
    assert rolled is not None
    cost = mpc.cost(rolled[0], inputs)
    assert cost >= optimum * (1 - 1e-9)
    assert cost <= optimum * (1 + C3_GAP)
