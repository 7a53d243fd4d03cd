"""Ball-table contact (issue 11 item 1): the plant and the LCS stop a ball pushed down onto the
table. Without the contact (``ball_table=False``, the scene before) the ball goes through, so
these tests fail when the contact is missing from either side."""

from __future__ import annotations

import numpy as np
import pytest

from c3bench.problems.config import load_config
from c3bench.problems.lcs import LCS
from c3bench.problems.linearize import linearize
from c3bench.problems.scene import Plant, build_scene, home_state
from c3bench.solvers.lcp import lemke

CONFIG = load_config()
DT = CONFIG.mpc.dt
RADIUS = CONFIG.scene.ball_radius
DOWN = np.array([0.0, -20.0])  # 20 N down on the gravity-compensated 0.5 kg ball


def plant_ball_heights(ball_table: bool, steps: int = 12) -> np.ndarray:
    """Ball-centre height after each control step of the plant pushed down with ``DOWN``."""
    scene = build_scene(config=CONFIG, ball_table=ball_table)
    plant = Plant(scene)
    plant.reset(home_state(scene))
    return np.array([plant.step(DOWN, DT)[scene.ball_position_indices[-1]]
                     for _ in range(steps)])


def lcs_rollout(lcs: LCS, x0: np.ndarray, u: np.ndarray, steps: int) -> np.ndarray:
    """States of the LCS rolled out ``steps`` times from ``x0`` (Lemke at every step)."""
    states = [x0]
    for _ in range(steps):
        solution = lemke(lcs.F, lcs.lcp_offset(states[-1], u))
        assert solution.found and solution.z is not None, solution.status
        states.append(lcs.next_state(states[-1], u, solution.z))
    return np.array(states[1:])


def test_scene_declares_the_ball_table_contact() -> None:
    scene = build_scene(config=CONFIG)
    assert scene.n_contacts == 4  # two corners, ball-table, ball-cube
    assert build_scene(config=CONFIG, ball_table=False).n_contacts == 3
    lcs = linearize(scene, home_state(scene), np.zeros(2), DT)
    per = scene.friction_directions
    assert lcs.nlam == scene.n_contacts * per
    ball_z = home_state(scene)[4]
    # contact order: corners, ball-table (phi = ball height above the table minus r), ball-cube
    assert lcs.phi[2] == pytest.approx(ball_z - RADIUS - CONFIG.scene.table_height, abs=1e-15)
    spatial = build_scene(config=CONFIG, variant="spatial")
    assert linearize(spatial, home_state(spatial), np.zeros(3), DT).nlam == 6 * 4


def test_plant_ball_does_not_go_through_the_table() -> None:
    """Measured (MuJoCo 4.0, 1 ms step, solref 4 ms): 3.6 mm at the impact (2.4 m/s),
    0.04 mm at rest under 20 N; the issue's success rule allows 5 mm."""
    scene = build_scene(config=CONFIG)
    plant = Plant(scene)
    plant.reset(home_state(scene))
    heights = np.array([plant.step(DOWN, scene.model.opt.timestep)[4] for _ in range(600)])
    assert RADIUS - heights.min() < 5e-3
    assert abs(heights[-1] - RADIUS) < 1e-4  # resting on the table
    assert plant_ball_heights(False)[-1] < -0.5  # without the pair it falls through


def test_lcs_rollout_stops_the_ball_at_the_table_like_the_plant() -> None:
    """One LCS (the ball-table gap is linear in the ball height, so one linearisation is
    exact for it) rolled out 12 steps: the ball lands and rests on the table; the plant's
    ball rests at the same height to 1 mm once both have landed (t >= 0.15 s; before, the two
    differ by the LCS's 50 ms semi-implicit Euler step against the plant's 1 ms)."""
    scene = build_scene(config=CONFIG)
    x0 = home_state(scene)
    states = lcs_rollout(linearize(scene, x0, DOWN, DT), x0, DOWN, 12)
    ball_z = states[:, 4]
    assert ball_z.min() > RADIUS - 1e-9  # no penetration in the LCS
    assert abs(ball_z[-1] - RADIUS) < 1e-9 and abs(states[-1, 9]) < 1e-9  # at rest on it
    plant = plant_ball_heights(True)
    np.testing.assert_allclose(ball_z[2:], plant[2:], atol=1e-3)
    np.testing.assert_allclose(states[-1, :3], x0[:3], atol=1e-9)  # the cube did not move
    without = build_scene(config=CONFIG, ball_table=False)
    falling = lcs_rollout(linearize(without, x0, DOWN, DT), x0, DOWN, 12)
    assert falling[-1, 4] < 0.0  # without the contact the LCS ball falls through


def test_ball_table_friction_holds_a_ball_pressed_down() -> None:
    """Pressed down with 20 N and pushed sideways with 5 N (< mu_table 20 N), the LCS ball
    sticks: the table's friction carries the sideways force (Anitescu keeps a sticking
    contact closed: no separation without sliding)."""
    scene = build_scene(config=CONFIG)
    x0 = home_state(scene)
    x0[4] = RADIUS  # ball resting on the table
    u = np.array([5.0, -20.0])
    states = lcs_rollout(linearize(scene, x0, u, DT), x0, u, 5)
    np.testing.assert_allclose(states[:, [3, 4, 8, 9]],
                               np.tile(x0[[3, 4, 8, 9]], (5, 1)), atol=1e-9)
