"""The fast LCS build (issue 12 item 5) against the readable reference: the same LCS to 1e-10
(in fact bit for bit: the same central differences, cheaper MuJoCo calls)."""

from __future__ import annotations

import numpy as np
import pytest

from c3bench.problems.config import load_config
from c3bench.problems.lcs import LCS_MATRICES, ContactModel
from c3bench.problems.linearize import (
    linearize,
    linearize_reference,
    smooth_dynamics,
    smooth_dynamics_reference,
)
from c3bench.problems.linearize_batch import BatchLinearizer
from c3bench.problems.scene import build_scene, check_variant, home_state
from c3bench.problems.suites import scripted_push

CONFIG = load_config()
DT = CONFIG.mpc.dt
SMOOTH_FIELDS = ("J_q", "J_v", "J_u", "d_v", "N", "N_pinv", "M_inv", "acceleration")


def random_states(variant: str, count: int, seed: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """States of the scripted push (planar) or home with a random orientation (spatial), with
    random velocities and inputs."""
    rng = np.random.default_rng(seed)
    scene = build_scene(config=CONFIG, variant=check_variant(variant))
    record = scripted_push(CONFIG, 1.0) if variant == "planar" else None
    out = []
    for k in range(count):
        x = home_state(scene) if record is None else record.states[3 * k].copy()
        x[scene.nq:] = rng.normal(0.0, 0.5, scene.nv)
        if variant == "spatial":
            quaternion = rng.normal(size=4)
            x[3:7] = quaternion / np.linalg.norm(quaternion)
        out.append((x, rng.normal(0.0, 8.0, scene.nu)))
    return out


@pytest.mark.parametrize("variant", ["planar", "spatial"])
def test_smooth_dynamics_equals_reference(variant: str) -> None:
    scene = build_scene(l=0.29, config=CONFIG, variant=check_variant(variant))
    for x, u in random_states(variant, 6, 1):
        fast, reference = smooth_dynamics(scene, x, u), smooth_dynamics_reference(scene, x, u)
        for name in SMOOTH_FIELDS:
            ours, theirs = getattr(fast, name), getattr(reference, name)
            scale = max(1.0, float(np.max(np.abs(theirs))))
            assert np.max(np.abs(ours - theirs)) <= 1e-10 * scale, name
        # the fast path leaves the data at the linearisation point like the reference
        np.testing.assert_array_equal(scene.data.qpos, x[:scene.nq])
        np.testing.assert_array_equal(scene.data.qacc_smooth, reference.acceleration)


@pytest.mark.parametrize("contact_model", ["anitescu", "stewart_trinkle"])
@pytest.mark.parametrize("variant", ["planar", "spatial"])
def test_linearize_equals_reference(variant: str, contact_model: ContactModel) -> None:
    scene = build_scene(l=0.29, config=CONFIG, variant=check_variant(variant))
    for x, u in random_states(variant, 4, 2):
        fast = linearize(scene, x, u, DT, contact_model)
        reference = linearize_reference(scene, x, u, DT, contact_model)
        for name in (*LCS_MATRICES, "phi"):
            ours, theirs = getattr(fast, name), getattr(reference, name)
            scale = max(1.0, float(np.max(np.abs(theirs))))
            assert np.max(np.abs(ours - theirs)) <= 1e-10 * scale, name


def test_batch_linearizer_equals_reference_with_and_without_ball_table() -> None:
    sides = [0.27, 0.30, 0.33]
    for ball_table in (True, False):
        linearizer = BatchLinearizer(sides, CONFIG, ball_table=ball_table)
        scenes = [build_scene(l=side, config=CONFIG, ball_table=ball_table) for side in sides]
        for x, u in random_states("planar", 3, 3):
            batch = linearizer.linearize(x, u, DT)
            assert batch.n_contacts == 3 + int(ball_table)
            for j, scene in enumerate(scenes):
                reference = linearize_reference(scene, x, u, DT)
                for name in (*LCS_MATRICES, "phi"):
                    ours, theirs = getattr(batch, name)[j], getattr(reference, name)
                    scale = max(1.0, float(np.max(np.abs(theirs))))
                    assert np.max(np.abs(ours - theirs)) <= 1e-9 * scale, name


def _assert_same_lcs(ours: object, theirs: object, tolerance: float) -> None:
    for name in (*LCS_MATRICES, "phi"):
        mine, reference = getattr(ours, name), getattr(theirs, name)
        assert mine.shape == reference.shape, name
        scale = max(1.0, float(np.max(np.abs(reference))))
        assert np.max(np.abs(mine - reference)) <= tolerance * scale, name


@pytest.mark.parametrize("ball_table", [True, False])
@pytest.mark.parametrize("samples", [1, 16])
def test_compiled_lcs_build_equals_numpy_build(samples: int, ball_table: bool) -> None:
    """The compiled per-sample part (one numba call) gives the numpy build's LCS to rounding
    along the scripted push, with random velocities and inputs."""
    sides = np.random.default_rng(samples).uniform(0.27, 0.33, samples)
    numpy_build = BatchLinearizer(sides, CONFIG, ball_table=ball_table)
    compiled = BatchLinearizer(sides, CONFIG, ball_table=ball_table, kernel="compiled")
    for x, u in random_states("planar", 5, 4):
        _assert_same_lcs(compiled.linearize(x, u, DT), numpy_build.linearize(x, u, DT), 1e-12)


def test_compiled_lcs_build_ball_inside_some_cubes() -> None:
    """A ball centre inside the larger cubes and outside the smaller ones: the nearest-face
    branch (negative gap, flipped normal) agrees with the numpy build sample by sample."""
    sides = np.array([0.27, 0.28, 0.29, 0.31, 0.33])
    scene = build_scene(config=CONFIG)
    x = home_state(scene)
    numpy_build = BatchLinearizer(sides, CONFIG)
    compiled = BatchLinearizer(sides, CONFIG, kernel="compiled")
    # ball centre 0.142 m beside the cube's axis (nearest face: a side), then 0.142 m above
    # its centre (nearest face: the top)
    for ball in ((-0.142, 0.16), (-0.02, 0.15 + 0.142)):
        x[3], x[4] = ball
        reference = numpy_build.linearize(x, np.zeros(2), DT)
        centre_gap = reference.phi[:, -1] + numpy_build.ball_radius  # < 0: centre inside
        assert np.any(centre_gap < 0) and np.any(centre_gap > 0)
        _assert_same_lcs(compiled.linearize(x, np.zeros(2), DT), reference, 1e-12)


def test_compiled_lcs_build_keeps_stewart_trinkle_on_numpy() -> None:
    sides = [0.28, 0.32]
    x, u = random_states("planar", 1, 5)[0]
    compiled = BatchLinearizer(sides, CONFIG, contact_model="stewart_trinkle",
                               kernel="compiled").linearize(x, u, DT)
    reference = BatchLinearizer(sides, CONFIG, contact_model="stewart_trinkle").linearize(
        x, u, DT)
    _assert_same_lcs(compiled, reference, 0.0)


def test_batch_linearizer_rejects_unknown_kernel() -> None:
    with pytest.raises(ValueError, match="kernel must be one of"):
        BatchLinearizer([0.3], CONFIG, kernel="fortran")
