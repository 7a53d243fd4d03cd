"""Lemke and PGS backends (solvers/backends/lcp.py) on the ``lcp`` family."""

from __future__ import annotations

import itertools
import math
from pathlib import Path

import numpy as np
import pytest

from c3bench.problems.instance import Problem, load_instances
from c3bench.problems.suites import generate_suite
from c3bench.solvers import registry
from c3bench.solvers.base import Settings, WarmStart, settings_for
from c3bench.solvers.lcp import natural_residual
from c3bench.solvers.residuals import residuals

NAMES = ("lemke", "pgs")


@pytest.fixture(scope="module")
def quick_lcps(tmp_path_factory: pytest.TempPathFactory) -> list[Problem]:
    out: Path = tmp_path_factory.mktemp("quick")
    generate_suite("quick", out, progress=False)
    problems = load_instances(out, families=("lcp",))
    assert problems
    return problems


def lcp_problem(name: str, M: np.ndarray, q: np.ndarray) -> Problem:
    return Problem(name=name, family="lcp", P=M, q=q, lb=np.zeros(q.size))


def random_psd_lcp(seed: int, n: int = 8, rank: int | None = None) -> Problem:
    """``M = B B^T`` (singular when ``rank < n``) and ``q = w* - M z*`` for a complementary
    pair ``z*, w* >= 0`` (half the indices active), so that the LCP is solvable."""
    rng = np.random.default_rng(seed)
    B = rng.standard_normal((n, rank or n))
    M = B @ B.T / n
    active = rng.permutation(n) < n // 2
    z_star = np.where(active, rng.uniform(0.5, 2.0, n), 0.0)
    w_star = np.where(active, 0.0, rng.uniform(0.5, 2.0, n))
    return lcp_problem(f"psd-{seed}", M, w_star - M @ z_star)


def enumerate_lcp(M: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Exact reference by enumerating the active sets: the KKT system of
    ``min 1/2 z M z + q z, z >= 0`` on each support ``S`` is ``M_SS z_S = -q_S`` (least squares
    for singular ``M``), accepted when ``z_S >= 0`` and ``w = M z + q >= 0``."""
    n = q.size
    for size in range(n + 1):
        for support in itertools.combinations(range(n), size):
            z = np.zeros(n)
            if support:
                index = list(support)
                z[index] = np.linalg.lstsq(M[np.ix_(index, index)], -q[index], rcond=None)[0]
            w = M @ z + q
            if z.min() >= -1e-10 and w.min() >= -1e-10 and abs(z @ w) < 1e-9:
                return np.maximum(z, 0.0)
    raise AssertionError("no solution found by enumeration")


def check_solution(problem: Problem, x: np.ndarray, reference: np.ndarray, tol: float) -> None:
    """For PSD ``M`` the solution set may be a face, but ``w = M z + q`` and the objective
    are unique; compare those (and ``z`` itself where ``M`` is definite)."""
    M, q = problem.P, problem.q
    np.testing.assert_allclose(M @ x + q, M @ reference + q, atol=tol)
    assert problem.objective(x) == pytest.approx(problem.objective(reference), abs=tol)
    if np.linalg.eigvalsh(M)[0] > 1e-6:
        np.testing.assert_allclose(x, reference, atol=tol * 10)


def cases(quick: list[Problem]) -> list[Problem]:
    return [*quick, random_psd_lcp(0), random_psd_lcp(1, rank=4), random_psd_lcp(2, n=12)]


@pytest.mark.parametrize("name", NAMES)
def test_agrees_with_enumeration(quick_lcps: list[Problem], name: str) -> None:
    settings = settings_for("high_accuracy")
    for problem in cases(quick_lcps):
        reference = enumerate_lcp(problem.P, problem.q)
        result = registry.solve(name, problem, settings)
        assert result.found, (problem.name, result.status)
        assert result.failure == ""
        check_solution(problem, result.x, reference, 1e-7)
        found = residuals(problem, result.x, result.y, result.z, result.z_box)
        assert found.primal <= 1e-9 and found.dual <= 1e-9 and found.gap <= 1e-9
        assert result.diagnostics["natural_residual"] == pytest.approx(
            natural_residual(problem.P, problem.q, result.x))
        assert result.diagnostics["natural_residual"] <= 1e-9
        # qpsolvers' box dual: P x + q + z_box = 0 with z_box <= 0 on the lower bound
        assert np.all(result.z_box <= 0.0)
        np.testing.assert_allclose(problem.P @ result.x + problem.q + result.z_box, 0.0,
                                   atol=1e-9)
        assert result.iterations is not None and result.iterations >= 0


def test_lemke_and_pgs_agree_at_every_profile(quick_lcps: list[Problem]) -> None:
    for problem in cases(quick_lcps):
        for profile in ("default", "mid_accuracy"):
            settings = settings_for(profile)
            lemke = registry.solve("lemke", problem, settings)
            pgs = registry.solve("pgs", problem, settings)
            assert lemke.found and pgs.found
            found = residuals(problem, pgs.x, pgs.y, pgs.z, pgs.z_box)
            # PGS stops on the natural residual and the gap lam^T w, both below tolerance
            assert found.worst() <= settings.tolerance, (problem.name, profile, found)
            scale = max(1.0, np.abs(lemke.x).max())
            assert np.abs(problem.P @ (pgs.x - lemke.x)).max() <= 100 * settings.tolerance * scale


def test_pgs_trace(quick_lcps: list[Problem]) -> None:
    problem = quick_lcps[0]
    settings = settings_for("high_accuracy")
    result = registry.solve("pgs", problem, settings)
    trace = result.trace["natural_residual"]
    assert len(trace) == result.iterations > 1
    assert trace[-1] <= settings.tolerance < trace[0]
    assert trace[-1] == pytest.approx(result.diagnostics["natural_residual"])
    # warm-started from its own answer it stops after one sweep
    again = registry.solve("pgs", problem, settings, warm_start=WarmStart(x=result.x))
    assert again.found and again.iterations == 1


def test_pgs_fails_cleanly_on_a_zero_diagonal() -> None:
    M = np.diag([1.0, 0.0, 2.0])  # PSD with M_11 = 0: PGS cannot divide by it
    problem = lcp_problem("zero-diagonal", M, np.array([-1.0, 1.0, -1.0]))
    result = registry.solve("pgs", problem)
    assert not result.found and result.failure == "error"
    assert "M_ii > 0" in result.status
    # Lemke solves it (q_1 >= 0 there)
    lemke = registry.solve("lemke", problem)
    assert lemke.found
    np.testing.assert_allclose(lemke.x, [1.0, 0.0, 0.5], atol=1e-12)


def test_unbounded_lcp_is_a_failure() -> None:
    # M_11 = 0 and q_1 < 0: the QP is unbounded below, the LCP has no solution
    problem = lcp_problem("unbounded", np.diag([1.0, 0.0]), np.array([-1.0, -1.0]))
    lemke = registry.solve("lemke", problem)
    assert not lemke.found and lemke.failure == "error" and "ray" in lemke.status


def test_pgs_iteration_limit_is_a_failure(quick_lcps: list[Problem]) -> None:
    problem = quick_lcps[0]
    result = registry.solve("pgs", problem, settings_for("high_accuracy", max_iterations=2))
    assert not result.found and "limit" in result.status
    assert result.iterations == 2 and len(result.trace["natural_residual"]) == 2


def test_accepts_only_the_lcp_form(quick_lcps: list[Problem]) -> None:
    problem = quick_lcps[0]
    n = problem.n
    shifted = lcp_problem("shifted", problem.P, problem.q)
    shifted.lb = np.full(n, -1.0)
    capped = Problem(name="capped", family="lcp", P=problem.P, q=problem.q, lb=np.zeros(n),
                     ub=np.ones(n))
    open_top = Problem(name="open", family="lcp", P=problem.P, q=problem.q, lb=np.zeros(n),
                       ub=np.full(n, np.inf))
    for name in NAMES:
        backend = registry.get(name)
        assert backend.accepts(problem) == (True, "")
        assert backend.accepts(open_top) == (True, "")
        ok, reason = backend.accepts(shifted)
        assert not ok and "lb = 0" in reason
        ok, reason = backend.accepts(capped)
        assert not ok and "upper" in reason
        result = registry.solve(name, capped)
        assert result.failure == "unsupported"
        float32 = registry.solve(name, problem, Settings(precision="float32"))
        assert float32.failure == "unsupported"


# --- LCPs without a solution: never solved, never a reference, never a success -------------------
def unsolvable_lcps() -> list[Problem]:
    """``F = [[0]], q = [-1]``: ``w = -1`` for every ``lam``; ``F = [[2, -2], [-2, 2]]``,
    ``q = [-3, 0]``: ``w_2 >= 0`` needs ``lam_2 >= lam_1``, then ``w_1 = -3 - 2 (lam_2 - lam_1)
    < 0``."""
    return [lcp_problem("none-1", np.array([[0.0]]), np.array([-1.0])),
            lcp_problem("none-2", np.array([[2.0, -2.0], [-2.0, 2.0]]), np.array([-3.0, 0.0]))]


def test_lemke_never_claims_an_unsolvable_lcp() -> None:
    settings = settings_for("high_accuracy")
    for problem in unsolvable_lcps():
        result = registry.solve("lemke", problem, settings)
        assert not result.found and result.failure == "error", result.status


def test_lemke_checks_its_terminal_basis() -> None:
    """A loose tie tolerance makes the ratio test pick a wrong row on ``none-2``: the terminal
    basis has ``w_2 = -3``; the check refuses it instead of reporting "solved"."""
    from c3bench.solvers.lcp import lemke

    problem = unsolvable_lcps()[1]
    outcome = lemke(problem.P, problem.q, tol=1.5)
    assert not outcome.found and outcome.status.startswith("check failed"), outcome.status
    assert outcome.z is not None and np.min(problem.P @ outcome.z + problem.q) < -1.0


def test_claimed_non_solution_is_not_judged_a_success() -> None:
    """A fake backend claiming ``lam = 0`` (with a sign-feasible or a wrong-signed box dual
    that zeroes stationarity) is not a success, and is not accepted as a reference."""
    from c3bench.bench import store
    from c3bench.bench.reference import _accept
    from c3bench.bench.rows import fill_row
    from c3bench.solvers.base import Result

    problem = unsolvable_lcps()[0]
    x = np.zeros(1)
    w = problem.P @ x + problem.q
    for z_box in (np.minimum(-w, 0.0), -w):  # clipped (dual residual 1), wrong sign (+1)
        fake = Result("fake", problem.name, True, "solved", x=x, z_box=z_box)
        row = store.empty_row()
        row.update({"family": "lcp", "tolerance": 1e-6})
        row = fill_row(row, problem, fake)
        assert row["complementarity_violation"] == pytest.approx(1.0)
        assert row["dual_residual"] == pytest.approx(1.0)
        assert not row["success"] and "complementarity_violation" in row["verdict"]
        assert not _accept(problem, fake)[0]


def test_unsolvable_lcp_gets_no_reference() -> None:
    from c3bench.bench.reference import compute_reference, plan_for

    for problem in unsolvable_lcps():
        ref = compute_reference(problem, "digest", plan_for("lcp"), time_limit=30.0)
        assert not ref.available and math.isnan(ref.objective), ref


def test_solvable_lcp_still_passes() -> None:
    from c3bench.bench import store
    from c3bench.bench.reference import _accept, compute_reference, plan_for
    from c3bench.bench.rows import fill_row

    problem = random_psd_lcp(3)
    ref = compute_reference(problem, "digest", plan_for("lcp"), time_limit=30.0)
    assert ref.available and ref.solver == "lemke"
    result = registry.solve("lemke", problem, settings_for("default"))
    assert result.found and _accept(problem, result)[0]
    row = store.empty_row()
    row.update({"family": "lcp", "tolerance": 1e-6, "reference_solver": ref.solver,
                "reference_objective": ref.objective, "reference_spread": ref.spread})
    row = fill_row(row, problem, result)
    assert row["success"], row["verdict"]
    assert row["complementarity_violation"] <= 1e-9
