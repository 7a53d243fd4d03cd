"""Closed-loop plumbing and the failure-mode labels on synthetic trajectories."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from c3bench.bench.closed_loop import (
    ControllerSpec,
    Trajectory,
    cube_geometry,
    label_failure_mode,
    simulate,
    summarise,
)
from c3bench.problems.config import load_config
from c3bench.problems.scene import build_scene, home_state, target_state

CONFIG = load_config()
SCENE = build_scene(config=CONFIG)
TARGET = CONFIG.mpc.target_angle
TOL = CONFIG.mpc.success_tolerance
TIMES = np.arange(41) * CONFIG.mpc.dt


def pivoted(angle: float, ball: tuple[float, float] | None = None,
            ball_velocity: tuple[float, float] = (0.0, 0.0)) -> np.ndarray:
    """Cube pivoted about its far edge by ``angle``; ball on the face unless given."""
    x = target_state(SCENE, angle)
    if ball is not None:
        x[3:5] = ball
    x[8:10] = ball_velocity
    return x


def trajectory(states: list[np.ndarray]) -> Trajectory:
    stacked = np.array(states)
    gaps = np.array([cube_geometry(SCENE, x)["ball_gap"] for x in stacked])
    return Trajectory(TIMES[: len(states)], stacked, np.zeros((len(states) - 1, 2)), gaps)


def label(states: list[np.ndarray]) -> int:
    return label_failure_mode(trajectory(states), SCENE, TARGET, TOL)[0]


def test_success() -> None:
    angles = np.minimum(np.linspace(0, 0.7, 41), TARGET)
    assert label([pivoted(a) for a in angles]) == 0


def test_no_motion() -> None:
    assert label([home_state(SCENE)] * 41) == 4


def test_backing_off_first() -> None:
    states = []
    for k in range(41):
        x = pivoted(0.0) if k < 20 else pivoted(0.01 * (k - 20))
        if k < 20:
            x[3] -= 0.003 * k  # the ball retreats 6 cm before anything tips
        states.append(x)
    assert label(states) == 2


def test_fast_sliding_past_the_edge() -> None:
    states = [pivoted(0.004 * k) for k in range(30)]
    top = SCENE.l + 0.1
    states += [pivoted(0.12, ball=(0.0, top), ball_velocity=(1.5, 0.2)) for _ in range(11)]
    assert label(states) == 1


def test_whack_then_contact_lost() -> None:
    up = [pivoted(a) for a in np.linspace(0, 0.4, 10)]
    away = (-0.6, 0.2)
    down = [pivoted(a, ball=away) for a in np.linspace(0.4, 0.05, 31)]
    assert label(up + down) == 3


def test_policy_returning_nan_falls_back_to_last_safe_input() -> None:
    calls = {"n": 0}

    def policy(x: np.ndarray, t: float) -> tuple[np.ndarray, dict]:
        calls["n"] += 1
        if calls["n"] % 2 == 0:
            return np.array([np.nan, 1.0]), {}
        if calls["n"] == 5:
            raise RuntimeError("controller crashed")
        return np.array([1.0, 0.0]), {"lcs_time": 1e-3, "solve_time": 2e-3}

    traj, records = simulate(policy, CONFIG, duration=0.5)
    outcome = summarise(traj, records, SCENE, CONFIG)
    assert outcome.steps == 10
    assert outcome.fallback_count == 6  # 5 NaN steps and one crash
    assert outcome.nan_count == 6
    assert all(np.array_equal(r.input, [1.0, 0.0]) for r in records)
    assert np.all(np.isfinite(traj.states))


def test_duration_must_be_a_multiple_of_dt() -> None:
    with pytest.raises(ValueError, match="duration"):
        simulate(lambda x, t: (np.zeros(2), {}), CONFIG, duration=0.07)


def test_short_closed_loop_is_deterministic() -> None:
    from c3bench.bench.closed_loop import ControllerSpec, run_closed_loop

    spec = ControllerSpec(qp_backend="clarabel")
    first, records, outcome = run_closed_loop(spec, CONFIG, duration=0.5)
    second, _, _ = run_closed_loop(spec, CONFIG, duration=0.5)
    assert np.array_equal(first.states, second.states)
    assert outcome.steps == 10 and outcome.fallback_count == 0
    assert all(r.lcs_time > 0 and r.solve_time > 0 for r in records)


def test_robust_sides_are_seeded() -> None:
    from c3bench.bench.closed_loop import ControllerSpec

    spec = ControllerSpec(controller="c3plus-robust", samples=16, seed=3)
    sides = spec.sample_sides()
    assert np.array_equal(sides, ControllerSpec(controller="c3plus-robust", samples=16,
                                                seed=3).sample_sides())
    assert sides.min() >= 0.27 and sides.max() <= 0.33 and len(sides) == 16


def test_closed_loop_command_writes_records(tmp_path, capsys) -> None:
    from c3bench.bench.cli import main

    assert main(["closed-loop", "--duration", "0.25", "--quiet", "--results",
                 str(tmp_path)]) == 0
    text = capsys.readouterr().out
    assert "success" in text and "control step" in text
    assert "gentle success    no" in text and "plan vs LCS       angle median" in text
    out = tmp_path / "closed_loop" / "runs" / ControllerSpec().label()
    assert f"records           {out}" in text
    assert (out / "steps.csv").exists() and (out / "summary.json").exists()
    import json

    summary = json.loads((out / "summary.json").read_text())
    assert summary["outcome"]["success"] is False  # 0.25 s cannot hold for 1 s
    # the force limit is inside the controller: the simulator never has to clip
    assert summary["metrics"]["clipped_inputs"] == 0
    steps = pd.read_csv(out / "steps.csv")
    assert {"commanded0", "commanded1", "plan_lcs_error", "plan_plant_error"} <= set(steps)
    assert steps[["commanded0", "commanded1"]].abs().max().max() <= 30 + 1e-6


def test_fast_robust_controller_runs_in_the_loop() -> None:
    from c3bench.bench.closed_loop import ControllerSpec, run_closed_loop

    spec = ControllerSpec(controller="c3plus-fast-robust", samples=4)
    trajectory, _, outcome = run_closed_loop(spec, CONFIG, duration=0.3)
    assert outcome.steps == 6 and outcome.fallback_count == 0
    assert np.all(np.isfinite(trajectory.states))
    assert spec.label() == "c3plus-fast-robust-compiled-geometric-n4"


def test_fast_and_reference_controllers_apply_the_same_first_input() -> None:
    """n = 1: the compiled C3+ kernel and the reference C3+ with Clarabel agree without the
    limits (equal kernels); with them (bounds in the reference's QP, a box in the compiled
    kernel's projection: two splittings) both keep the force limit."""
    from dataclasses import replace

    from c3bench.bench.closed_loop import ControllerSpec, make_policy
    from c3bench.problems.lcs import LCSBatch
    from c3bench.problems.linearize import linearize
    from c3bench.problems.scene import build_mpc
    from c3bench.solvers.admm.compiled_solver import CompiledC3Plus
    from c3bench.solvers.c3 import C3Options, solve_c3

    x0 = home_state(SCENE)
    model = build_scene(l=0.29, config=CONFIG)
    mpc = build_mpc(model, CONFIG.mpc)
    lcs = linearize(model, x0, np.zeros(2), CONFIG.mpc.dt)
    free = C3Options(qp_backend="clarabel", use_limits=False, keep_iterates=False)
    reference = solve_c3(lcs, mpc, x0, replace(free, qp_settings=None))
    compiled = CompiledC3Plus(mpc, free).solve(LCSBatch.from_lcs([lcs]), x0)
    assert reference.u_raw is not None and compiled.u_raw is not None
    np.testing.assert_allclose(compiled.u_raw, reference.u_raw, rtol=1e-5, atol=1e-5)
    fast, _ = make_policy(ControllerSpec(controller="c3plus-fast"), CONFIG)(x0, 0.0)
    bounded, info = make_policy(ControllerSpec(qp_backend="clarabel"), CONFIG)(x0, 0.0)
    for u in (fast, bounded, info["commanded"]):
        assert np.abs(u).max() <= 30 + 1e-6


def test_pd_tracking_law_interpolates_the_plan() -> None:
    from c3bench.bench.closed_loop import ControllerSpec, pd_tracking_law

    spec = ControllerSpec(feedback=True, feedback_kp=100.0, feedback_kd=20.0)
    x = home_state(SCENE)
    end, velocity = x[3:5] + np.array([0.01, 0.002]), np.array([0.2, 0.04])
    law = pd_tracking_law(spec, SCENE, x, (end, velocity), 0.05)
    u0 = np.array([1.0, -1.0])
    # at s = 0 the reference is the measured position: only the velocity term acts
    assert np.allclose(law(x, 0.0, u0), u0 + 20.0 * velocity)
    # half way the position reference is half way to the plan's x_1
    assert np.allclose(law(x, 0.025, u0), u0 + 100.0 * 0.5 * (end - x[3:5]) + 20.0 * velocity)
    moved = x.copy()
    moved[3:5], moved[8:10] = end, velocity
    assert np.allclose(law(moved, 0.05, u0), u0)  # on the plan: no correction


def test_feedback_changes_the_applied_forces() -> None:
    from c3bench.bench.closed_loop import ControllerSpec, run_closed_loop

    plain, _, _ = run_closed_loop(ControllerSpec(controller="c3plus-fast"), CONFIG, 0.25)
    tracked, _, outcome = run_closed_loop(ControllerSpec(controller="c3plus-fast",
                                                         feedback=True), CONFIG, 0.25)
    assert outcome.fallback_count == 0
    assert np.max(np.abs(plain.states[-1] - tracked.states[-1])) > 1e-6
