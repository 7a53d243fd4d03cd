"""The ``lcp_general`` family: an LCP with ``F`` stored as is (not symmetric).

References: brute-force enumeration of the ``2^n`` complementary bases (exact for a P-matrix,
whose LCP has exactly one solution for every ``q``: Cottle, Pang and Stone 1992, theorem
3.3.7), the LCS's own step (:func:`c3bench.solvers.lcs_simulation.simulate`), and the MIQP
backend ``scip_lcp`` as an independent method on the Stewart-Trinkle instances.
"""

from __future__ import annotations

import itertools
import json
import math
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from c3bench.bench import store
from c3bench.bench.metrics import judge, required_residuals
from c3bench.bench.reference import ReferencePlan, _accept, compute_reference, plan_for
from c3bench.bench.rows import fill_row
from c3bench.problems import families
from c3bench.problems.capture import SUITES, SuiteSpec
from c3bench.problems.errors import InputError, InstanceFormatError
from c3bench.problems.instance import Problem, lcp_data, load_instances, load_problem, save_problem
from c3bench.problems.names import QP_FAMILIES, Failure, Family
from c3bench.problems.suites import generate_suite, out_of_date
from c3bench.solvers import registry
from c3bench.solvers.base import Result, settings_for
from c3bench.solvers.lcs_simulation import simulate
from c3bench.solvers.residuals import relative_natural_residual, residuals

HIGH = settings_for("high_accuracy")
SCIP_OK, SCIP_WHY = registry.get("scip_lcp").availability()
needs_scip = pytest.mark.skipif(not SCIP_OK, reason=f"scip_lcp unavailable: {SCIP_WHY}")


# --- references -----------------------------------------------------------------------------------
def enumerate_solutions(F: np.ndarray, q: np.ndarray) -> list[np.ndarray]:
    """Every basic solution of ``LCP(F, q)``: on each support ``S``, ``F_SS lam_S = -q_S``
    (skipped when singular), kept when ``lam >= 0`` and ``w = F lam + q >= 0``."""
    n = q.size
    out = []
    for size in range(n + 1):
        for support in itertools.combinations(range(n), size):
            lam = np.zeros(n)
            index = list(support)
            if index:
                block = F[np.ix_(index, index)]
                if abs(np.linalg.det(block)) < 1e-12:
                    continue
                lam[index] = np.linalg.solve(block, -q[index])
            w = F @ lam + q
            if lam.min() >= -1e-10 and w.min() >= -1e-10:
                out.append(np.maximum(lam, 0.0))
    return out


def p_matrix_lcp(seed: int, n: int, kind: str) -> Problem:
    """A random non-symmetric P-matrix LCP: ``kind = "monotone"``: ``F = B B^T / n + I / 2 +
    S`` with ``S`` skew (positive definite symmetric part); ``"triangular"``: upper triangular
    with a positive diagonal and large entries above it (a P-matrix whose symmetric part is
    indefinite)."""
    rng = np.random.default_rng(seed)
    if kind == "monotone":
        B = rng.standard_normal((n, n))
        S = rng.standard_normal((n, n))
        F = B @ B.T / n + 0.5 * np.eye(n) + (S - S.T)
    else:
        F = np.triu(rng.normal(0.0, 3.0, (n, n)), 1) + np.diag(rng.uniform(0.5, 2.0, n))
    q = rng.normal(0.0, 1.0, n)
    return families.lcp_general(f"{kind}-{seed}-{n}", F, q)


def solution(result: Result) -> np.ndarray:
    """``result.x`` of a solve that must have found one."""
    assert result.found and result.x is not None, result.status
    return np.asarray(result.x, dtype=float)


def stored(problem: Problem, field: str) -> np.ndarray:
    """A QP field of an instance that has it."""
    value = getattr(problem, field)
    assert value is not None
    return np.asarray(value)


def constant_input(u: np.ndarray) -> Callable[[np.ndarray], np.ndarray]:
    """A controller that always returns ``u``."""
    return lambda _: u


P_CASES = [(seed, n, kind) for seed, n in ((0, 3), (1, 5), (2, 8))
           for kind in ("monotone", "triangular")]


# --- the family -----------------------------------------------------------------------------------
def test_storage_round_trips_and_keeps_f_as_is(tmp_path: Path) -> None:
    F = np.array([[1.0, 2.0, 0.0], [-3.0, 1.0, 0.5], [0.0, 0.25, 4.0]])
    q = np.array([-1.0, 0.5, -2.0])
    problem = families.lcp_general("round-trip", F, q, meta={"source": "test"})
    loaded = load_problem(save_problem(problem, tmp_path))
    assert loaded.family == Family.LCP_GENERAL and loaded.meta == {"source": "test"}
    stored_F, stored_q = lcp_data(loaded)
    np.testing.assert_array_equal(stored_F, F)
    np.testing.assert_array_equal(stored_q, q)
    assert not np.allclose(stored_F, stored_F.T)
    lam = np.array([0.5, 0.0, 1.0])
    assert loaded.objective(lam) == 0.0  # an LCP has no objective
    # the primal residual of the stored form is [-w]_+ (w = F lam + q)
    assert residuals(loaded, lam).primal == pytest.approx(max(0.0, -float((F @ lam + q).min())))


@pytest.mark.parametrize(("F", "q", "match"), [
    (np.ones((2, 3)), np.zeros(2), "square"),
    (np.eye(2), np.zeros(3), "square"),
    (np.array([[np.nan]]), np.zeros(1), "non-finite"),
    (np.eye(1), np.array([np.inf]), "non-finite"),
    (np.eye(1), np.zeros((1, 1)), "vector"),
])
def test_bad_data_is_a_clear_input_error(F: np.ndarray, q: np.ndarray, match: str) -> None:
    with pytest.raises(InputError, match=match):
        families.lcp_general("bad", F, q)


def test_a_tampered_stored_form_is_refused(tmp_path: Path) -> None:
    problem = families.lcp_general("tampered", np.array([[2.0, 1.0], [0.0, 1.0]]),
                                   np.array([-1.0, -1.0]))
    with pytest.raises(ValueError, match="G"):
        Problem(name="x", family="lcp_general", P=problem.P, q=problem.q, G=-stored(problem, "G"),
                h=problem.h, lb=problem.lb, data=problem.data)
    with pytest.raises(ValueError, match="data\\['F'\\]"):
        Problem(name="x", family="lcp_general", P=problem.P, q=problem.q, G=problem.G,
                h=problem.h, lb=problem.lb)
    path = save_problem(problem, tmp_path)
    header = json.loads(path.read_text())
    header["arrays"].remove("data.F")
    path.write_text(json.dumps(header))
    np.savez(path.with_suffix(".npz"), P=problem.P, q=problem.q, G=stored(problem, "G"),
             h=stored(problem, "h"), lb=stored(problem, "lb"))
    with pytest.raises(InstanceFormatError, match="data\\['F'\\]"):
        load_problem(path)


# --- backends -------------------------------------------------------------------------------------
@pytest.mark.parametrize(("seed", "n", "kind"), P_CASES)
def test_lemke_equals_enumeration_on_p_matrices(seed: int, n: int, kind: str) -> None:
    problem = p_matrix_lcp(seed, n, kind)
    F, q = lcp_data(problem)
    solutions = enumerate_solutions(F, q)
    assert len(solutions) == 1  # a P-matrix: exactly one solution
    lam = solution(registry.solve("lemke", problem, HIGH))
    np.testing.assert_allclose(lam, solutions[0], atol=1e-9)
    assert residuals(problem, lam).complementarity <= 1e-12


@needs_scip
@pytest.mark.parametrize(("seed", "n", "kind"), P_CASES)
def test_miqp_equals_enumeration_on_p_matrices(seed: int, n: int, kind: str) -> None:
    problem = p_matrix_lcp(seed, n, kind)
    F, q = lcp_data(problem)
    result = registry.solve("scip_lcp", problem, HIGH)
    np.testing.assert_allclose(solution(result), enumerate_solutions(F, q)[0], atol=1e-9)
    assert result.diagnostics["big_m_proved"] == float(kind == "monotone")
    assert result.diagnostics["big_m"] > 0  # never an exact model for the certificate


@pytest.mark.parametrize("seed", range(5))
def test_proved_big_m_bounds_the_solution(seed: int) -> None:
    """With a positive definite symmetric part the constants are a proof: the enumerated
    solution lies inside them."""
    from c3bench.solvers.backends.lcp_miqp import big_m

    problem = p_matrix_lcp(seed, 6, "monotone")
    F, q = lcp_data(problem)
    bound = big_m(F, q)
    lam = enumerate_solutions(F, q)[0]
    assert bound.proved
    assert lam.max() <= bound.lam and (F @ lam + q).max() <= bound.w


@needs_scip
def test_miqp_grows_an_unproved_big_m_until_it_finds_the_solution() -> None:
    """``F = [[1, -1e4], [0, 1]]``, ``q = [-1, -1]`` (a P-matrix with an indefinite symmetric
    part): the solution ``(10001, 1)`` lies outside the first constant (1e3), inside the
    second (1e5)."""
    problem = families.lcp_general("far", np.array([[1.0, -1e4], [0.0, 1.0]]),
                                   np.array([-1.0, -1.0]))
    result = registry.solve("scip_lcp", problem, HIGH)
    np.testing.assert_allclose(solution(result), [10001.0, 1.0], rtol=1e-12)
    assert result.diagnostics["big_m"] == pytest.approx(1e5)
    assert result.diagnostics["big_m_proved"] == 0.0


def test_pgs_solves_or_fails_never_fakes() -> None:
    """PGS converges on the diagonally dominant case; on ``F = [[1, 6], [-6, 1]]`` (a P-matrix,
    positive definite symmetric part) its sweeps cycle: a failure, not a solution."""
    dominant = families.lcp_general("dominant", np.array([[4.0, 1.0], [-2.0, 3.0]]),
                                    np.array([-1.0, -1.0]))
    result = registry.solve("pgs", dominant, HIGH)
    np.testing.assert_allclose(solution(result), enumerate_solutions(*lcp_data(dominant))[0],
                               atol=1e-8)
    cycling = families.lcp_general("cycling", np.array([[1.0, 6.0], [-6.0, 1.0]]),
                                   np.array([-2.5, 0.6]))
    result = registry.solve("pgs", cycling, settings_for("high_accuracy", max_iterations=500))
    assert not result.found and result.failure == Failure.ERROR and "limit" in result.status
    lemke = solution(registry.solve("lemke", cycling, HIGH))
    np.testing.assert_allclose(lemke, enumerate_solutions(*lcp_data(cycling))[0], atol=1e-12)


def test_qp_backends_decline_lcp_general() -> None:
    problem = p_matrix_lcp(0, 3, "monotone")
    qp_backends = [name for name, backend in registry.backends().items()
                   if set(backend.families) & set(QP_FAMILIES) - {Family.LCP}]
    assert {"clarabel", "osqp"} <= set(qp_backends)
    for name in qp_backends:
        accepted, reason = registry.get(name).accepts(problem)
        assert not accepted and "lcp_general" in reason, (name, reason)
    assert registry.solve("clarabel", problem).failure == Failure.UNSUPPORTED
    takers = {name for name, backend in registry.backends().items()
              if Family.LCP_GENERAL in backend.families}
    assert takers == {"lemke", "pgs", "scip_lcp"}


# --- an LCP without a solution --------------------------------------------------------------------
def unsolvable() -> list[Problem]:
    """``F = [[-1]], q = [-1]``: ``w = -1 - lam < 0`` for every ``lam >= 0``.
    ``F = [[1, -1], [1, -1]], q = [-1, -2]``: ``w_2 = w_1 - 1``, so ``w_2 >= 0`` needs
    ``w_1 >= 1 > 0``, hence ``lam_1 = 0`` and then ``w_1 = -1 - lam_2 < 0``."""
    return [families.lcp_general("none-1", np.array([[-1.0]]), np.array([-1.0])),
            families.lcp_general("none-2", np.array([[1.0, -1.0], [1.0, -1.0]]),
                                 np.array([-1.0, -2.0]))]


def test_an_lcp_without_solution_is_never_solved() -> None:
    for problem in unsolvable():
        assert enumerate_solutions(*lcp_data(problem)) == []
        for name in ("lemke", "pgs", *(("scip_lcp",) if SCIP_OK else ())):
            result = registry.solve(name, problem, HIGH)
            assert not result.found, (name, result.status)
        if SCIP_OK:
            result = registry.solve("scip_lcp", problem, HIGH)
            assert result.failure == Failure.INFEASIBLE and "not a proof" in result.status


def test_an_lcp_without_solution_is_never_a_reference_nor_a_success() -> None:
    for problem in unsolvable():
        ref = compute_reference(problem, "digest", plan_for(Family.LCP_GENERAL),
                                time_limit=30.0)
        assert not ref.available and ref.x is None, ref
        lam = np.zeros(problem.n)
        fake = Result("fake", problem.name, True, "solved", x=lam)
        assert not _accept(problem, fake)[0]
        row = store.empty_row()
        row.update({"family": Family.LCP_GENERAL, "tolerance": 1e-3})
        row = fill_row(row, problem, fake)
        assert not row["success"] and "complementarity_violation" in row["verdict"]


def test_verdict_needs_the_natural_residual_only() -> None:
    assert required_residuals(Family.LCP_GENERAL) == ("primal_residual_relative",
                                                      "complementarity_violation")
    problem = p_matrix_lcp(1, 5, "triangular")
    result = registry.solve("lemke", problem, HIGH)
    row = store.empty_row()
    row.update({"family": Family.LCP_GENERAL, "tolerance": 1e-9})
    row = fill_row(row, problem, result)
    assert row["success"], row["verdict"]
    assert judge(row) == (True, "")


def test_reference_is_lemke_checked_by_the_miqp_or_pgs() -> None:
    problem = families.lcp_general("dominant", np.array([[4.0, 1.0], [-2.0, 3.0]]),
                                   np.array([-1.0, -1.0]))
    plan = plan_for(Family.LCP_GENERAL)
    assert plan is not None and (plan.solver, plan.check) == ("lemke", "scip_lcp")
    ref = compute_reference(problem, "digest", plan, time_limit=30.0)
    assert ref.available and ref.solver == "lemke" and ref.objective == 0.0
    assert ref.check_solver == ("scip_lcp" if SCIP_OK else "pgs")
    missing = ReferencePlan("lemke", "no_such_backend", fallback_check="pgs")
    ref = compute_reference(problem, "digest", missing, time_limit=30.0)
    assert ref.available and ref.check_solver == "pgs"


# --- Stewart-Trinkle instances of the full suite --------------------------------------------------
SLICE = SuiteSpec("full-slice", n_states=2, admm_iterations=(0,), projection_iterations=(),
                  trajectories=SUITES["full"].trajectories[:2], contact_change_states=1,
                  mpcc_trajectories=1, mpcc_per_trajectory=1,
                  lcp_general_models=SUITES["full"].lcp_general_models,
                  extra_scenes=SUITES["full"].extra_scenes, extra_scene_trajectories=1)
"""A slice of the ``full`` suite's definition: two states of two planar pushes and of the
first push run in the spatial scene (QP steps at one iteration)."""


@pytest.fixture(scope="module")
def full_slice(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("full_slice")
    generate_suite(SLICE, out, progress=False)
    return out


def test_full_suite_asks_for_stewart_trinkle_and_spatial_and_others_do_not() -> None:
    from c3bench.problems.capture import SCENE_VARIANTS
    from c3bench.problems.scene import VARIANTS

    full = SUITES["full"]
    assert full.lcp_general_models == ("stewart_trinkle",)
    assert full.extra_scenes == ("spatial",) and full.extra_scene_trajectories == 2
    for name in ("quick", "default"):
        assert (SUITES[name].lcp_general_models, SUITES[name].extra_scenes) == ((), ())
        stored = SUITES[name].to_json()  # the manifest keeps its keys of generator version 2
        assert not {"lcp_general_models", "extra_scenes", "extra_scene_trajectories"} & set(
            stored)
    assert full.to_json()["extra_scenes"] == ("spatial",)
    assert SCENE_VARIANTS == VARIANTS
    with pytest.raises(ValueError, match="lcp_general_models"):
        SuiteSpec("x", 1, (0,), (0,), lcp_general_models=("coulomb",))
    for scenes in (("planar",), ("spatial", "spatial"), ("flat",)):
        with pytest.raises(ValueError, match="extra_scenes"):
            SuiteSpec("x", 1, (0,), (0,), extra_scenes=scenes)


def test_full_slice_has_stewart_trinkle_instances(full_slice: Path) -> None:
    manifest = json.loads((full_slice / "manifest.json").read_text())
    assert manifest["counts"]["lcp_general"] == manifest["counts"]["lcp"] == 6
    scenes = [state["scene"] for state in manifest["states"]]
    assert scenes.count("planar") == 4 and scenes.count("spatial") == 2
    assert {s["trajectory"] for s in manifest["states"] if s["scene"] == "spatial"} == {0}
    assert set(manifest["limits_by_scene"]) == {"planar", "spatial"}
    assert manifest["suite"]["lcp_general_models"] == ["stewart_trinkle"]
    assert out_of_date(SLICE, manifest) == ""
    assert "definition" in out_of_date(SuiteSpec(**{**SLICE.__dict__,
                                                    "lcp_general_models": ()}), manifest)
    tags = {state["tag"] for state in manifest["states"]}
    problems = load_instances(full_slice, families=(Family.LCP_GENERAL,))
    assert {p.name.rsplit("-", 1)[1] for p in problems} == tags
    sizes = {p.meta["scene"]: p.n for p in problems}
    assert sizes == {"planar": 16, "spatial": 36}  # contacts x (gamma, normal, directions)
    for problem in problems:
        assert problem.name.endswith("_spatial") == (problem.meta["scene"] == "spatial")
        assert problem.lcs is not None and problem.lcs.contact_model == "stewart_trinkle"
        assert problem.meta["contact_model"] == "stewart_trinkle"
        assert problem.meta["state_reason"] in ("contact_change", "contact_band")
        F, _ = lcp_data(problem)
        assert np.max(np.abs(F - F.T)) > 0.5  # the friction-cone rows: not symmetric


def test_stewart_trinkle_step_round_trips_and_lemke_reproduces_the_lcs_step(
        full_slice: Path, tmp_path: Path) -> None:
    for problem in load_instances(full_slice, families=(Family.LCP_GENERAL,)):
        loaded = load_problem(save_problem(problem, tmp_path))
        for key in ("F", "x", "u"):
            np.testing.assert_array_equal(loaded.data[key], problem.data[key])
        assert loaded.lcs is not None
        x, u = loaded.data["x"], loaded.data["u"]
        lam = solution(registry.solve("lemke", loaded, HIGH))
        step = simulate(loaded.lcs, x, constant_input(u), 1)
        np.testing.assert_allclose(loaded.lcs.next_state(x, u, lam), step.states[1], atol=1e-9)
        F, q = lcp_data(loaded)
        assert relative_natural_residual(F, q, lam) <= 1e-12
        if SCIP_OK:  # an independent method finds a solution too (not always the same one:
            # a spatial Stewart-Trinkle LCP can have several, with different next states)
            miqp = solution(registry.solve("scip_lcp", loaded, HIGH))
            assert relative_natural_residual(F, q, miqp) <= 1e-9


def test_stewart_trinkle_instances_get_a_verified_reference(full_slice: Path) -> None:
    problem = load_instances(full_slice, families=(Family.LCP_GENERAL,))[0]
    ref = compute_reference(problem, "digest", plan_for(problem.family), time_limit=60.0)
    assert ref.available, ref.reason
    assert math.isfinite(ref.spread) and ref.spread == 0.0
