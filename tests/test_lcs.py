"""The LCS against MuJoCo: these tests fail when the physics or a matrix block is wrong."""

from __future__ import annotations

import numpy as np
import pytest

from c3bench.problems.config import load_config
from c3bench.problems.lcs import LCS
from c3bench.problems.linearize import linearize
from c3bench.problems.scene import Plant, build_scene, home_state
from c3bench.problems.suites import scripted_push
from c3bench.solvers.lcp import lemke

CONFIG = load_config()
DT = CONFIG.mpc.dt


def lcs_step(lcs: LCS, x: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """One LCS step: solve the LCP for lam, then ``A x + B u + D lam + d``."""
    solution = lemke(lcs.F, lcs.lcp_offset(x, u))
    assert solution.found, solution.status
    return lcs.next_state(x, u, solution.z), solution.z


def free_flight_state(variant: str) -> np.ndarray:
    scene = build_scene(variant=variant)
    x = home_state(scene)
    if variant == "planar":
        x[1] += 0.3  # cube in the air, ball 0.1 m from it
        x[scene.nq:] = [0.3, -0.2, 0.5, 0.1, 0.2]
    else:
        x[2] += 0.3
        # translational velocities only: the LCS's q' = q + dt N v is exact for them
        x[scene.nq:] = [0.3, 0.1, -0.2, 0.0, 0.0, 0.0, 0.1, -0.1, 0.2]
    return x


@pytest.mark.parametrize("variant", ["planar", "spatial"])
def test_no_contact_step_equals_mujoco_euler_step(variant: str) -> None:
    """Without contact the LCS is MuJoCo's semi-implicit Euler step of the same dt."""
    scene = build_scene(variant=variant, timestep=DT)
    x = free_flight_state(variant)
    u = np.array([3.0, -2.0]) if variant == "planar" else np.array([3.0, 1.0, -2.0])
    lcs = linearize(scene, x, u, DT)
    predicted, lam = lcs_step(lcs, x, u)
    assert np.all(lam == 0.0)
    plant = Plant(scene)
    plant.reset(x)
    simulated = plant.step(u, DT)
    assert np.max(np.abs(predicted - simulated)) < 1e-9


def rest_against_face(height: float) -> tuple[np.ndarray, Plant]:
    """Plant settled on the table, ball touching the near face at ``height * l``."""
    plant_scene = build_scene(config=CONFIG)
    l, r = plant_scene.l, CONFIG.scene.ball_radius
    x = home_state(plant_scene)
    x[3], x[4] = -l / 2 - r, height * l
    plant = Plant(plant_scene)
    plant.reset(x)
    plant.step(np.zeros(2), 0.2)  # let the soft contact settle
    settled = plant.state()
    settled[plant_scene.nq:] = 0.0
    settled[3] = settled[0] - l / 2 - r
    return settled, plant


# Measured on this machine (MuJoCo 4.0, plant step 1 ms, dt 0.05): static push 4 N:
# |dq| 2.2e-5, |dv| 3.0e-4; tipping push at 3/4 height, 8 N: |dq| 2.6e-3, |dv| 1.0e-2;
# 12 N: |dq| 1.1e-2, |dv| 1.6e-2 (semi-implicit Euler at dt = 0.05 vs a 1 ms soft-contact
# rollout). Tolerances below are about twice the measured figures.
@pytest.mark.parametrize(
    ("force", "q_tolerance", "v_tolerance"),
    [(4.0, 1e-4, 1e-3), (8.0, 6e-3, 2e-2), (12.0, 2e-2, 3e-2)],
)
def test_push_prediction_matches_mujoco_rollout(force: float, q_tolerance: float,
                                               v_tolerance: float) -> None:
    x, plant = rest_against_face(0.75)
    model = build_scene(l=0.30, config=CONFIG)
    u = np.array([force, 0.0])
    lcs = linearize(model, x, u, DT)
    predicted, lam = lcs_step(lcs, x, u)
    plant.reset(x)
    simulated = plant.step(u, DT)
    error = np.abs(predicted - simulated)
    assert error[:5].max() < q_tolerance
    assert error[5:].max() < v_tolerance
    if force >= 8.0:
        assert predicted[2] > 1e-3 and simulated[2] > 1e-3  # both start to tip
        assert lam[:2].sum() < 1e-9  # the near corner has lifted: no table force on it


def test_delassus_operator_is_symmetric_psd_along_the_push() -> None:
    record = scripted_push(CONFIG)
    model = build_scene(l=0.29, config=CONFIG)
    for k in range(0, len(record.inputs), 5):
        lcs = linearize(model, record.states[k], record.inputs[k], DT)
        assert np.allclose(lcs.F, lcs.F.T, atol=1e-12)
        assert np.linalg.eigvalsh(lcs.F).min() > -1e-10


@pytest.mark.parametrize("variant", ["planar", "spatial"])
def test_resting_cube_stays_at_rest_under_lcs_simulation(variant: str) -> None:
    scene = build_scene(config=CONFIG, variant=variant)
    x0 = home_state(scene)
    u = np.zeros(scene.nu)
    lcs = linearize(scene, x0, u, DT)
    x = x0.copy()
    for _ in range(40):
        previous = x
        x, lam = lcs_step(lcs, previous, u)
        gap = lcs.gap(previous, u, lam)
        assert np.all(lam >= 0)
        assert np.all(gap >= -1e-9)
        assert abs(lam @ gap) < 1e-9
    assert np.max(np.abs(x - x0)) < 1e-9
    # the table carries the cube's weight through the corners (each lam is a force along
    # n + mu t, so the normal components sum to the weight)
    corners = len(scene.corner_sites) * scene.friction_directions
    assert lam[:corners].sum() == pytest.approx(CONFIG.scene.cube_mass * 9.81, rel=1e-9)


def test_anitescu_and_stewart_trinkle_agree_without_friction() -> None:
    frictionless = CONFIG.with_scene(mu_table=0.0, mu_ball=0.0)
    x, _ = rest_against_face(0.75)
    scene = build_scene(l=0.30, config=frictionless)
    for u in (np.array([8.0, 0.0]), np.array([12.0, 3.0])):
        anitescu = linearize(scene, x, u, DT, "anitescu")
        stewart = linearize(scene, x, u, DT, "stewart_trinkle")
        next_a, _ = lcs_step(anitescu, x, u)
        next_s, _ = lcs_step(stewart, x, u)
        assert np.max(np.abs(next_a - next_s)) < 1e-9
        assert np.max(np.abs(next_a - x)) > 1e-3  # something moved


def test_model_side_changes_the_contact_geometry() -> None:
    """The controller's l (0.29) differs from the plant's (0.30): the corners move."""
    x = home_state(build_scene(config=CONFIG))
    small = linearize(build_scene(l=0.29), x, np.zeros(2), DT)
    true = linearize(build_scene(l=0.30), x, np.zeros(2), DT)
    assert small.phi[0] == pytest.approx(0.005, abs=1e-12)  # corners 5 mm above the table
    assert true.phi[0] == pytest.approx(0.0, abs=1e-12)


@pytest.mark.parametrize(
    ("call", "name"),
    [
        (lambda s, x, u: linearize(s, x, u, 0.0), "dt"),
        (lambda s, x, u: linearize(s, x, u, -0.1), "dt"),
        (lambda s, x, u: linearize(s, x[:-1], u, DT), "x"),
        (lambda s, x, u: linearize(s, x, np.array([np.nan, 0.0]), DT), "u"),
        (lambda s, x, u: linearize(s, np.full_like(x, np.inf), u, DT), "x"),
        (lambda s, x, u: linearize(s, x, u, DT, "coulomb"), "contact_model"),
    ],
)
def test_linearize_rejects_bad_input(call, name: str) -> None:
    scene = build_scene()
    with pytest.raises(ValueError, match=name):
        call(scene, home_state(scene), np.zeros(2))


def test_lcs_rejects_wrong_shapes() -> None:
    lcs = linearize(build_scene(), home_state(build_scene()), np.zeros(2), DT)
    arrays = {k: getattr(lcs, k) for k in ("A", "B", "D", "d", "E", "F", "H", "c")}
    arrays["F"] = arrays["F"][:-1]
    with pytest.raises(ValueError, match=r"LCS\.F"):
        LCS(**arrays, dt=DT)
