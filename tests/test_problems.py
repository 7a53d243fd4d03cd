"""Scene, configuration, family builders, storage and suite generation."""

from __future__ import annotations

import hashlib
import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from c3bench.bench.cli import main
from c3bench.problems import families
from c3bench.problems.capture import SUITES, SuiteSpec, reference_rho
from c3bench.problems.config import MPCConfig, SceneConfig, load_config
from c3bench.problems.instance import (
    InstanceFormatError,
    Problem,
    load_instances,
    load_problem,
    problem_arrays,
    save_problem,
)
from c3bench.problems.linearize import linearize
from c3bench.problems.mpc import HorizonLayout
from c3bench.problems.names import SUITE_FAMILIES
from c3bench.problems.scene import (
    Plant,
    RenderUnavailable,
    build_mpc,
    build_scene,
    home_state,
    make_mjcf,
    render_frame,
    target_state,
)
from c3bench.problems.suites import generate_suite

CONFIG = load_config()
TINY = SuiteSpec("tiny", n_states=1, admm_iterations=(0, 5), projection_iterations=(5,),
                 projection_steps=(0,))


@pytest.fixture(scope="module")
def quick_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("quick")
    generate_suite("quick", out, progress=False)
    return out


@pytest.fixture(scope="module")
def setting() -> tuple:
    scene = build_scene(l=0.29)
    x0 = home_state(build_scene())
    x0[3] = -0.2  # ball touching the near face of the true cube
    u = np.array([5.0, 0.0])
    lcs = linearize(scene, x0, u, CONFIG.mpc.dt)
    mpc = build_mpc(scene, CONFIG.mpc)
    return scene, lcs, mpc, x0, u


# --- scene and configuration ------------------------------------------------------------
@pytest.mark.parametrize("side", [0.27, 0.30, 0.33])
def test_mjcf_for_any_side(side: float) -> None:
    for variant in ("planar", "spatial"):
        scene = build_scene(l=side, variant=variant)
        size = scene.model.geom_size[scene.geom("cube")]
        assert np.allclose(size, side / 2)
        assert scene.nu == (2 if variant == "planar" else 3)
        assert scene.nx == (10 if variant == "planar" else 19)


@pytest.mark.parametrize("side", [0.0, -0.3, float("nan"), float("inf")])
def test_bad_side_is_rejected(side: float) -> None:
    with pytest.raises(ValueError, match="l"):
        build_scene(l=side)
    with pytest.raises(ValueError, match="l"):
        make_mjcf(side, CONFIG.scene)


def test_config_errors_name_the_field(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="dt"):
        MPCConfig(dt=0.0)
    with pytest.raises(ValueError, match="T"):
        MPCConfig(horizon=0)
    with pytest.raises(ValueError, match="cube_mass"):
        SceneConfig(cube_mass=-1.0)
    bad = tmp_path / "bad.toml"
    bad.write_text("[mpc]\nhorizon_length = 3\n")
    with pytest.raises(ValueError, match="horizon_length"):
        load_config(bad)
    custom = tmp_path / "custom.toml"
    custom.write_text("[mpc]\nhorizon = 3\n[scene]\nmu_table = 0.5\n")
    loaded = load_config(custom)
    assert loaded.mpc.horizon == 3 and loaded.scene.mu_table == 0.5
    assert loaded.scene.cube_mass == CONFIG.scene.cube_mass


def test_target_state_pivots_about_the_far_edge() -> None:
    scene = build_scene()
    for angle in (0.0, 0.3, 0.5, np.pi / 4):
        x = target_state(scene, angle)
        plant = Plant(scene)
        plant.reset(x)
        corners = plant.data.site_xpos[scene.corner_sites]
        far = corners[np.argmax(corners[:, 0])]
        assert far[0] == pytest.approx(scene.l / 2, abs=1e-12)  # pivot edge did not move
        assert far[2] == pytest.approx(0.0, abs=1e-12)
        assert scene.cube_angle(x) == pytest.approx(angle)


def test_plant_step_validates_input() -> None:
    scene = build_scene()
    plant = Plant(scene)
    plant.reset(home_state(scene))
    with pytest.raises(ValueError, match="u"):
        plant.step(np.array([np.nan, 0.0]), 0.05)
    with pytest.raises(ValueError, match="u"):
        plant.step(np.zeros(3), 0.05)
    with pytest.raises(ValueError, match="duration"):
        plant.step(np.zeros(2), 0.0005)
    with pytest.raises(ValueError, match="x"):
        plant.reset(np.zeros(4))


def test_render_frame_or_clear_skip(tmp_path: Path) -> None:
    scene = build_scene()
    try:
        path = render_frame(scene, home_state(scene), tmp_path / "frame.png", 160, 120)
    except RenderUnavailable as error:
        assert "OpenGL" in str(error)
        pytest.skip(f"rendering unavailable here: {error}")
    assert path.stat().st_size > 0


# --- family builders ----------------------------------------------------------------------
def test_consensus_qp_objective_is_mpc_cost_plus_consensus(setting: tuple) -> None:
    _, lcs, mpc, x0, _ = setting
    layout = HorizonLayout(lcs.nx, lcs.nlam, lcs.nu, lcs.nlam, mpc.horizon)
    rng = np.random.default_rng(1)
    delta = rng.normal(size=(mpc.horizon, layout.step_size))
    w = rng.normal(size=(mpc.horizon, layout.step_size))
    problem = families.consensus_qp("c3plus_qp", "t", lcs, mpc, x0, reference_rho(3), delta, w)
    z = rng.normal(size=layout.size)
    parts = layout.split(z)
    g = families.weight_vector(layout, reference_rho(3))
    steps = z[: mpc.horizon * layout.step_size].reshape(mpc.horizon, -1)
    expected = mpc.cost(parts["x"], parts["u"]) + np.sum(g * (steps - (delta - w)) ** 2)
    assert problem.objective(z) == pytest.approx(expected, rel=1e-12)


def test_consensus_qp_constraints_are_the_lcs(setting: tuple) -> None:
    """A trajectory rolled out through the LCS satisfies A z = b exactly."""
    _, lcs, mpc, x0, _ = setting
    problem = families.consensus_qp("c3plus_qp", "t", lcs, mpc, x0, reference_rho(0))
    layout = HorizonLayout.from_json(problem.meta["layout"])
    rng = np.random.default_rng(2)
    z = np.zeros(layout.size)
    x = x0
    for k in range(mpc.horizon):
        lam, u = np.abs(rng.normal(size=lcs.nlam)), rng.normal(size=lcs.nu)
        z[layout.index(k, "x")], z[layout.index(k, "lam")], z[layout.index(k, "u")] = x, lam, u
        z[layout.index(k, "eta")] = lcs.gap(x, u, lam)
        x = lcs.next_state(x, u, lam)
    z[layout.index(mpc.horizon, "x")] = x
    assert np.max(np.abs(problem.A @ z - problem.b)) < 1e-9
    c3 = families.consensus_qp("c3_qp", "t", lcs, mpc, x0,
                               {k: v for k, v in reference_rho(0).items() if k != "eta"})
    assert c3.n == problem.n - mpc.horizon * lcs.nlam
    assert c3.n_eq == problem.n_eq - mpc.horizon * lcs.nlam


def test_mpcc_and_projection_pairs(setting: tuple) -> None:
    _, lcs, mpc, x0, u = setting
    problem = families.mpcc("m", lcs, mpc, x0)
    assert problem.n_pairs == mpc.horizon * lcs.nlam
    assert np.all(problem.lb[problem.complementarity] == 0.0)
    size = lcs.nx + 2 * lcs.nlam + lcs.nu
    U = np.ones(size)
    with pytest.raises(ValueError, match="eta"):
        families.projection("p", lcs, np.zeros(size), U, "c3")
    U[lcs.nx + lcs.nlam + lcs.nu:] = 0.0
    projection = families.projection("p", lcs, np.zeros(size), U, "c3")
    assert projection.n_eq == lcs.nlam and projection.n_pairs == lcs.nlam
    lcp = families.lcp("l", lcs, x0, u)
    assert np.allclose(lcp.P, lcs.F) and np.allclose(lcp.q, lcs.lcp_offset(x0, u))


@pytest.mark.parametrize(
    ("change", "name"),
    [
        (lambda lcs, mpc, x0: (lcs, replace(mpc, horizon=0), x0), "T"),
        (lambda lcs, mpc, x0: (lcs, mpc, x0[:-1]), "x0"),
        (lambda lcs, mpc, x0: (lcs, mpc, np.full_like(x0, np.nan)), "x0"),
    ],
)
def test_builders_reject_bad_input(setting: tuple, change, name: str) -> None:
    _, lcs, mpc, x0, _ = setting
    lcs, mpc, x0 = change(lcs, mpc, x0)
    with pytest.raises(ValueError, match=name):
        families.mpcc("m", lcs, mpc, x0)
    with pytest.raises(ValueError, match=name):
        families.consensus_qp("c3plus_qp", "t", lcs, mpc, x0, reference_rho(0))


def test_rho_must_be_positive(setting: tuple) -> None:
    _, lcs, mpc, x0, _ = setting
    bad = dict(reference_rho(0), lam=-1.0)
    with pytest.raises(ValueError, match="lam"):
        families.consensus_qp("c3plus_qp", "t", lcs, mpc, x0, bad)
    with pytest.raises(ValueError, match="delta"):
        families.consensus_qp("c3plus_qp", "t", lcs, mpc, x0, reference_rho(0),
                              delta=np.zeros((2, 3)))


def test_problem_validation_names_the_field() -> None:
    with pytest.raises(ValueError, match="P"):
        Problem("p", "lcp", P=np.array([[1.0, np.nan], [0.0, 1.0]]), q=np.zeros(2))
    with pytest.raises(ValueError, match="P must have shape"):
        Problem("p", "lcp", P=np.eye(3), q=np.zeros(2))
    with pytest.raises(ValueError, match="symmetric"):
        Problem("p", "lcp", P=np.array([[1.0, 1.0], [0.0, 1.0]]), q=np.zeros(2))
    with pytest.raises(ValueError, match="b"):
        Problem("p", "lcp", P=np.eye(2), q=np.zeros(2), A=np.ones((1, 2)), b=np.ones(2))
    with pytest.raises(ValueError, match="family"):
        Problem("p", "nope", P=np.eye(2), q=np.zeros(2))


# --- storage and suites -------------------------------------------------------------------
def test_every_family_round_trips(quick_dir: Path, tmp_path: Path) -> None:
    problems = load_instances(quick_dir)
    assert {p.family for p in problems} == set(SUITE_FAMILIES)
    for problem in problems:
        path = save_problem(problem, tmp_path)
        again = load_problem(path)
        assert again.family == problem.family and again.meta == problem.meta
        assert again.objective_offset == problem.objective_offset
        original, restored = problem_arrays(problem), problem_arrays(again)
        assert original.keys() == restored.keys()
        for key in original:
            assert np.array_equal(original[key], restored[key]), key
        assert again.lcs is not None and again.lcs.contact_model == "anitescu"


def _digest(directory: Path) -> dict[str, str]:
    return {str(p.relative_to(directory)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(directory.rglob("*")) if p.is_file()}


def test_generation_is_byte_identical(quick_dir: Path, tmp_path: Path) -> None:
    generate_suite("quick", tmp_path, progress=False)
    assert _digest(tmp_path) == _digest(quick_dir)


def test_quick_suite_contents(quick_dir: Path) -> None:
    manifest = json.loads((quick_dir / "manifest.json").read_text())
    spec = SUITES["quick"]
    states = len(manifest["states"])
    per = spec.iterations_per_state or len(spec.admm_iterations)
    proj = spec.projection_iterations_per_state or len(spec.projection_iterations)
    qps = states * per * len(spec.qp_variants)
    assert manifest["counts"] == {
        "c3_qp": qps, "c3plus_qp": qps, "lcp": states,
        "mpcc": spec.mpcc_per_trajectory * (spec.mpcc_trajectories or len(spec.trajectories)),
        "projection": states * proj * len(spec.projection_steps) * 2,
    }
    problems = load_instances(quick_dir, families=("c3plus_qp",))
    for problem in problems:
        i = problem.meta["admm_iteration"]
        assert problem.meta["rho"]["lam"] == 50.0 * 2**i
        assert problem.meta["l"] == 0.29 and problem.meta["l_plant"] == 0.30
        assert problem.meta["capture"] in ("provisional",) or \
            problem.meta["capture"].startswith("controller")


def test_bad_files_name_file_and_key(quick_dir: Path, tmp_path: Path) -> None:
    problem = load_instances(quick_dir, families=("lcp",))[0]
    path = save_problem(problem, tmp_path)
    header = json.loads(path.read_text())
    header["schema_version"] = 99
    path.write_text(json.dumps(header))
    with pytest.raises(InstanceFormatError, match=r"lcp-.*schema_version"):
        load_problem(path)
    header["schema_version"] = 1
    del header["meta"]["dt"]
    path.write_text(json.dumps(header))
    with pytest.raises(InstanceFormatError, match=r"meta\.dt"):
        load_problem(path)
    header["meta"]["dt"] = 0.05
    header["arrays"].append("data.missing")
    path.write_text(json.dumps(header))
    with pytest.raises(InstanceFormatError, match=r"\.npz: missing key 'data\.missing'"):
        load_problem(path)
    with pytest.raises(InstanceFormatError, match="no such instance"):
        load_problem(tmp_path / "absent.json")


def test_cli_generate_and_list(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "suite"
    assert main(["problems", "generate", "--suite", "quick", "--out", str(out),
                 "--quiet"]) == 0
    assert main(["problems", "list", str(out)]) == 0
    text = capsys.readouterr().out
    for family in SUITE_FAMILIES:
        assert family in text
    assert "complementarity_pairs" in text
    assert main(["problems", "generate", "--suite", "nope", "--out", str(out)]) == 2


def test_tiny_custom_suite(tmp_path: Path) -> None:
    paths = generate_suite(TINY, tmp_path, progress=False)
    families_written = sorted({json.loads(p.read_text())["family"] for p in paths})
    assert families_written == sorted(SUITE_FAMILIES)
