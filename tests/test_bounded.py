"""Bounded QP steps: the limits type, the cube's limits, the bounded variant against an
independent active-set KKT solve, bound activity at captured states, and the equality variant
left unchanged."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from c3bench.problems import families
from c3bench.problems.capture import SuiteSpec, Trajectory, reference_rho
from c3bench.problems.config import load_config
from c3bench.problems.errors import InputError
from c3bench.problems.instance import Problem, load_instances
from c3bench.problems.limits import Limits, cube_limits
from c3bench.problems.linearize import linearize
from c3bench.problems.mpc import HorizonLayout, with_limits
from c3bench.problems.names import Block, Family, QPVariant
from c3bench.problems.scene import build_mpc, build_scene
from c3bench.problems.suites import generate_suite, qp_limits, sample_states, scripted_push
from c3bench.solvers import registry
from c3bench.solvers.base import settings_for

CONFIG = load_config()
HIGH = settings_for("high_accuracy")


@pytest.fixture(scope="module")
def state() -> tuple:
    """A contact state of the scripted push, its LCS and the cube's bounded MPC."""
    scene = build_scene(l=0.29, config=CONFIG)
    record = scripted_push(CONFIG, 1.5)
    index = sample_states(record, 3, 0.02)[1]
    x0, u_prev = record.states[index], record.inputs[index - 1]
    lcs = linearize(scene, x0, u_prev, CONFIG.mpc.dt)
    mpc = with_limits(build_mpc(scene, CONFIG.mpc), cube_limits(scene))
    return scene, lcs, mpc, x0, u_prev


# --- the limits type ----------------------------------------------------------------------------
def test_limits_validate_and_round_trip() -> None:
    a = np.array
    limits = Limits(a([-1.0, -2.0]), a([1.0, 2.0]), a([-np.inf, 0.0, 0.1]), a([np.inf, 1.0, 0.2]))
    again = Limits.from_json(limits.to_json())
    assert again == limits and (again.nx, again.nu) == (3, 2) and again.n_finite == 8
    assert limits.to_json()["x_lower"][0] is None
    with pytest.raises(InputError, match=r"u_lower\[1\] = 3.0 > u_upper\[1\]"):
        Limits(a([0.0, 3.0]), a([1.0, 2.0]), a([0.0]), a([1.0]))
    with pytest.raises(InputError, match="differ"):
        Limits(a([0.0]), a([1.0, 2.0]), a([0.0]), a([1.0]))
    with pytest.raises(InputError, match="NaN"):
        Limits(a([np.nan]), a([1.0]), a([0.0]), a([1.0]))
    with pytest.raises(InputError, match=r"x_lower may not be \+inf"):
        Limits(a([0.0]), a([1.0]), a([np.inf]), a([np.inf]))
    with pytest.raises(InputError, match="unknown"):
        Limits.from_json({**limits.to_json(), "extra": []})
    tight = limits.intersect(Limits.force_only(3, 2, 1.5))
    np.testing.assert_array_equal(tight.u_lower, [-1.0, -1.5])
    np.testing.assert_array_equal(tight.u_upper, [1.0, 1.5])


def test_cube_limits_follow_the_config(tmp_path: Path) -> None:
    scene = build_scene(l=0.29, config=CONFIG)
    limits = cube_limits(scene)
    np.testing.assert_array_equal(limits.u_upper, np.full(scene.nu, CONFIG.scene.force_limit))
    np.testing.assert_array_equal(limits.u_lower, -limits.u_upper)
    bx, bz = scene.ball_position_indices
    assert limits.x_lower[bz] == CONFIG.scene.table_height + CONFIG.scene.ball_radius
    assert (limits.x_lower[bx], limits.x_upper[bx]) == CONFIG.limits.ball_x
    assert limits.x_upper[bz] == CONFIG.limits.ball_z[1]
    free = np.setdiff1d(np.arange(scene.nx), [bx, bz])
    assert np.all(np.isinf(limits.x_lower[free])) and np.all(np.isinf(limits.x_upper[free]))
    spatial = cube_limits(build_scene(l=0.29, variant="spatial", config=CONFIG))
    by = build_scene(l=0.29, variant="spatial", config=CONFIG).ball_position_indices[1]
    assert (spatial.x_lower[by], spatial.x_upper[by]) == CONFIG.limits.ball_y
    path = tmp_path / "cfg.toml"
    path.write_text("[limits]\nball_x = [-0.5, 0.5]\nball_z = [0.1, 0.6]\n")
    custom = load_config(path)
    limits = cube_limits(build_scene(l=0.29, config=custom))
    assert (limits.x_lower[bx], limits.x_upper[bx]) == (-0.5, 0.5)
    assert (limits.x_lower[bz], limits.x_upper[bz]) == (0.1, 0.6)
    path.write_text("[limits]\nball_w = [0, 1]\n")
    with pytest.raises(InputError, match=r"unknown key\(s\) \['ball_w'\] in \[limits\]"):
        load_config(path)
    path.write_text("[limits]\nball_x = [0.5, -0.5]\n")
    with pytest.raises(InputError, match=r"\[limits\] ball_x must have low < high"):
        load_config(path)


# --- the bounded QP step ----------------------------------------------------------------------
def _bounded_pair(state: tuple, family: str, iteration: int,
                  limits: Limits | None = None) -> tuple[Problem, Problem]:
    """The bounded and equality QP steps at ``state`` with a nonzero consensus anchor."""
    _, lcs, mpc, x0, u_prev = state
    n_eta = lcs.nlam if family == Family.C3PLUS_QP else 0
    layout = HorizonLayout(lcs.nx, lcs.nlam, lcs.nu, n_eta, mpc.horizon)
    rho = {k: v for k, v in reference_rho(iteration).items() if k in layout.block_sizes()}
    delta = np.zeros((mpc.horizon, layout.step_size))
    delta[:, layout.index(0, Block.X)] = x0
    delta[:, layout.index(0, Block.U)] = 2.0 * u_prev
    bounded = families.consensus_qp(family, "b", lcs, mpc, x0, rho, delta,
                                    limits=limits or mpc.limits)
    equality = families.consensus_qp(family, "e", lcs, mpc, x0, rho, delta)
    return bounded, equality


def active_set_certificate(problem: Problem, z: np.ndarray, tol: float = 1e-5
                           ) -> tuple[np.ndarray, float]:
    """Optimum of ``problem`` by an independent active-set KKT solve, with the bounds that are
    active at ``z`` (within ``tol``, relative: an interior-point ``z`` stops short of its
    bounds) held as equalities, and the worst sign violation of the multipliers.

    ``P z + q + A^T y + mu = 0``, ``A z = b``, ``z_i = bound_i`` on the active set; for a convex
    QP the point is optimal iff it is feasible and ``mu_i >= 0`` on active upper bounds and
    ``mu_i <= 0`` on active lower bounds (Nocedal and Wright, Numerical Optimization, 2nd ed.,
    Thm 12.1 and 16.4).
    """
    assert problem.A is not None and problem.b is not None
    assert problem.lb is not None and problem.ub is not None
    scale = np.maximum(1.0, np.abs(z))
    upper = np.flatnonzero(np.isfinite(problem.ub) & (problem.ub - z <= tol * scale))
    lower = np.flatnonzero(np.isfinite(problem.lb) & (z - problem.lb <= tol * scale))
    active = np.concatenate([upper, lower])
    n, m, k = problem.n, problem.A.shape[0], active.size
    S = np.zeros((k, n))
    S[np.arange(k), active] = 1.0
    kkt = np.block([[problem.P, problem.A.T, S.T],
                    [problem.A, np.zeros((m, m)), np.zeros((m, k))],
                    [S, np.zeros((k, m)), np.zeros((k, k))]])
    rhs = np.concatenate([-problem.q, problem.b,
                          np.concatenate([problem.ub[upper], problem.lb[lower]])])
    solution = np.linalg.solve(kkt, rhs)
    z_star, mu = solution[:n], solution[n + m:]
    sign_violation = max(0.0, float(-np.min(mu[: upper.size], initial=0.0)),
                         float(np.max(mu[upper.size:], initial=0.0)))
    return z_star, sign_violation


@pytest.mark.parametrize("family", [Family.C3PLUS_QP, Family.C3_QP])
def test_bounded_optimum_matches_an_active_set_kkt_solve(state: tuple, family: str) -> None:
    """Clarabel at high accuracy and the independent KKT solve agree, with the cube's limits
    and with a tighter force box (so that the input bounds are certainly active)."""
    mpc = state[2]
    assert mpc.limits is not None
    for limits in (mpc.limits, mpc.limits.intersect(Limits.force_only(mpc.nx, mpc.nu, 2.0))):
        bounded, _ = _bounded_pair(state, family, 9, limits)
        result = registry.solve("clarabel", bounded, HIGH)
        assert result.x is not None, result.status
        z_star, sign_violation = active_set_certificate(bounded, result.x)
        assert bounded.lb is not None and bounded.ub is not None
        gradient = float(np.max(np.abs(bounded.P @ z_star + bounded.q)))
        assert sign_violation <= 1e-6 * gradient
        assert np.all(z_star >= bounded.lb - 1e-9) and np.all(z_star <= bounded.ub + 1e-9)
        np.testing.assert_allclose(result.x, z_star, atol=1e-6 * max(1.0, np.abs(z_star).max()))
        assert result.objective == pytest.approx(bounded.objective(z_star), rel=1e-8, abs=1e-8)
    # with the force box of 2 N the bounds are active and change the optimum
    equality_z = registry.solve("clarabel", _bounded_pair(state, family, 9)[1], HIGH).x
    assert equality_z is not None and np.max(np.abs(equality_z - z_star)) > 1e-3


def test_bounds_sit_on_u_and_predicted_x_only(state: tuple) -> None:
    mpc = state[2]
    bounded, equality = _bounded_pair(state, Family.C3PLUS_QP, 0)
    layout = HorizonLayout.from_json(bounded.meta["layout"])
    assert bounded.meta["variant"] == QPVariant.BOUNDED
    assert Limits.from_json(bounded.meta["limits"]) == mpc.limits
    assert equality.meta["variant"] == QPVariant.EQUALITY and "limits" not in equality.meta
    assert equality.lb is None and equality.ub is None
    assert bounded.lb is not None and bounded.ub is not None
    for k in range(layout.horizon):
        np.testing.assert_array_equal(bounded.ub[layout.index(k, Block.U)], mpc.limits.u_upper)
        for block in (Block.LAM, Block.ETA):
            assert np.all(np.isinf(bounded.lb[layout.index(k, block)]))
    assert np.all(np.isinf(bounded.lb[layout.index(0, Block.X)]))
    for k in range(1, layout.horizon + 1):
        np.testing.assert_array_equal(bounded.lb[layout.index(k, Block.X)], mpc.limits.x_lower)
    assert bounded.n_bounded == layout.horizon * (mpc.nu + 2)  # inputs; ball x and z
    # the same arrays otherwise
    for name in ("P", "q", "A", "b"):
        np.testing.assert_array_equal(getattr(bounded, name), getattr(equality, name))


def test_input_bounds_keyword_still_means_the_force_box(state: tuple) -> None:
    _, lcs, mpc, x0, _ = state
    rho = {k: v for k, v in reference_rho(0).items() if k != Block.ETA}
    legacy = families.consensus_qp(Family.C3_QP, "l", lcs, mpc, x0, rho, input_bounds=True)
    layout = HorizonLayout.from_json(legacy.meta["layout"])
    assert legacy.meta["variant"] == QPVariant.BOUNDED and legacy.meta["input_bounds"]
    assert legacy.ub is not None and legacy.n_bounded == layout.horizon * mpc.nu
    assert np.all(legacy.ub[layout.index(0, Block.U)] == mpc.force_limit)


def test_mpcc_carries_the_same_limits(state: tuple) -> None:
    _, lcs, mpc, x0, _ = state
    problem = families.mpcc("m", lcs, mpc, x0, limits=mpc.limits)
    plain = families.mpcc("m", lcs, mpc, x0)
    qp, _ = _bounded_pair(state, Family.C3PLUS_QP, 0)
    assert problem.lb is not None and qp.lb is not None and plain.lb is not None
    layout = HorizonLayout.from_json(problem.meta["layout"])
    x_and_u = np.zeros(layout.size, dtype=bool)
    for k in range(layout.horizon + 1):
        x_and_u[layout.index(k, Block.X)] = True
        if k < layout.horizon:
            x_and_u[layout.index(k, Block.U)] = True
    np.testing.assert_array_equal(problem.lb[x_and_u], qp.lb[x_and_u])
    np.testing.assert_array_equal(problem.lb[~x_and_u], plain.lb[~x_and_u])
    assert problem.meta["variant"] == QPVariant.BOUNDED and "variant" not in plain.meta


# --- suites: equality variant unchanged, bounds active at captured states ----------------------
TWO_PUSHES = SuiteSpec("bounded_test", n_states=2, admm_iterations=(0, 9),
                       projection_iterations=(), trajectories=(Trajectory(), Trajectory(
                           (-0.40, 0.12), 0.60)), contact_change_states=1)


@pytest.fixture(scope="module")
def captured(tmp_path_factory: pytest.TempPathFactory) -> list[Problem]:
    """QP steps at 4 states of 2 pushes, iterates from real C3+ runs (clarabel)."""
    from c3bench.bench.cli_problems import capture_for

    out = tmp_path_factory.mktemp("bounded_suite")
    generate_suite(TWO_PUSHES, out, capture=capture_for("controller"), progress=False)
    return load_instances(out, families=(Family.C3PLUS_QP, Family.C3_QP))


def test_equality_variant_equals_the_instance_built_without_limits(
        captured: list[Problem]) -> None:
    scene = build_scene(l=0.29, config=CONFIG)
    mpc = build_mpc(scene, CONFIG.mpc)
    by_name = {p.name: p for p in captured}
    checked = 0
    for problem in captured:
        if problem.meta["variant"] != QPVariant.EQUALITY:
            continue
        twin = by_name[problem.name.replace("-equality-", "-bounded-")]
        assert problem.lcs is not None
        rebuilt = families.consensus_qp(problem.family, problem.name, problem.lcs, mpc,
                                        problem.data["x0"], problem.meta["rho"],
                                        problem.data["delta"], problem.data["w"])
        for name in ("P", "q", "A", "b"):
            assert np.array_equal(getattr(rebuilt, name), getattr(problem, name)), name
            assert np.array_equal(getattr(twin, name), getattr(problem, name)), name
        assert twin.objective_offset == problem.objective_offset
        # the suite passes C3's delta as a column slice; numpy's pairwise sum then rounds the
        # offset differently in the last bit than from the contiguous copy loaded here
        assert rebuilt.objective_offset == pytest.approx(problem.objective_offset, rel=1e-15)
        assert problem.lb is None and problem.ub is None and twin.n_bounded > 0
        checked += 1
    assert checked == len(captured) // 2 == 16


def test_a_share_of_captured_bounded_steps_has_an_active_bound(
        captured: list[Problem]) -> None:
    """At states of real C3+ runs the cube's limits bind in some QP steps (the force limit,
    and the ball's table bound when the plan presses the ball down)."""
    bounded = [p for p in captured if p.meta["variant"] == QPVariant.BOUNDED]
    active = 0
    for problem in bounded:
        result = registry.solve("clarabel", problem, HIGH)
        assert result.x is not None, result.status
        z_star, sign_violation = active_set_certificate(problem, result.x)
        np.testing.assert_allclose(result.x, z_star, atol=1e-6 * max(1.0, np.abs(z_star).max()))
        assert sign_violation <= 1e-6 * float(np.max(np.abs(problem.P @ z_star + problem.q)))
        assert problem.lb is not None and problem.ub is not None
        gap = np.minimum(problem.ub - z_star, z_star - problem.lb)
        active += int(np.any(gap <= 1e-9 * np.maximum(1.0, np.abs(z_star))))
    assert len(bounded) == 16
    assert active >= 2, f"{active} of {len(bounded)} bounded QP steps have an active bound"


def test_qp_limits_fall_back_to_the_force_box() -> None:
    scene = build_scene(l=0.29, config=CONFIG)
    mpc = with_limits(build_mpc(scene, CONFIG.mpc), None)
    assert qp_limits(mpc) == Limits.force_only(mpc.nx, mpc.nu, mpc.force_limit)
    assert qp_limits(with_limits(mpc, cube_limits(scene))) == cube_limits(scene)
    assert build_mpc(scene, CONFIG.mpc).limits == cube_limits(scene)  # the cube's MPC has them
