"""CasADi ``conic`` problems and LCPs brought through ``problems import``.

A QP built and solved by CasADi itself (qpOASES, an exact active-set method) is saved with
:func:`save_conic`, imported and run through the whole CLI with Clarabel: the same optimum.
An LCP file becomes an ``lcp_general`` instance whose solution by our runner matches the one
found by enumerating every complementary basis.
"""

from __future__ import annotations

import itertools
from pathlib import Path

import casadi
import numpy as np
import pytest

from c3bench.bench import store
from c3bench.bench.cli import main
from c3bench.problems.conic import CONIC_KEYS, conic_to_qpsolvers, save_conic
from c3bench.problems.errors import InputError
from c3bench.problems.instance import lcp_data, load_instances
from c3bench.problems.names import Family
from c3bench.solvers import registry
from c3bench.solvers.base import settings_for

INF = np.inf


def conic_qp() -> dict[str, np.ndarray]:
    """A strictly convex QP in CasADi's form with an equality row, a two-sided row, a one-sided
    row, an unconstrained row and bounds infinite on some sides; several are active."""
    rng = np.random.default_rng(7)
    M = rng.standard_normal((4, 4))
    return {"H": M @ M.T + 0.5 * np.eye(4), "g": np.array([3.0, -2.0, 1.0, 4.0]),
            "A": np.array([[1.0, 1.0, 1.0, 1.0], [1.0, -1.0, 0.0, 0.0],
                           [0.0, 0.0, 1.0, 2.0], [0.0, 1.0, 0.0, 1.0]]),
            "lba": np.array([1.0, -0.2, -INF, -INF]), "uba": np.array([1.0, 0.2, 0.3, INF]),
            "lbx": np.array([-INF, 0.0, -1.0, 0.0]), "ubx": np.array([0.5, INF, 1.0, INF])}


def casadi_optimum(qp: dict[str, np.ndarray]) -> tuple[float, np.ndarray]:
    """``(f*, x*)`` from ``casadi.conic`` with qpOASES."""
    solver = casadi.conic("c3bench_test", "qpoases",
                          {"h": casadi.DM(qp["H"]).sparsity(), "a": casadi.DM(qp["A"]).sparsity()},
                          {"printLevel": "none", "error_on_fail": True})
    out = solver(h=qp["H"], g=qp["g"], a=qp["A"], lba=qp["lba"], uba=qp["uba"], lbx=qp["lbx"],
                 ubx=qp["ubx"])
    return float(out["cost"]), np.asarray(out["x"]).reshape(-1)


def _cli(capsys: pytest.CaptureFixture[str], *argv: str) -> tuple[int, str, str]:
    code = main(list(argv))
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def test_conversion_rows_by_hand() -> None:
    qp = conic_qp()
    arrays = conic_to_qpsolvers({k.lower(): v for k, v in qp.items()})
    A, G = qp["A"], qp["A"]
    np.testing.assert_array_equal(arrays["A"], A[[0]])
    np.testing.assert_array_equal(arrays["b"], [1.0])
    # upper sides of rows 1 and 2, then the lower side of row 1; row 3 (free) dropped
    np.testing.assert_array_equal(arrays["G"], np.vstack([G[1], G[2], -G[1]]))
    np.testing.assert_array_equal(arrays["h"], [0.2, 0.3, 0.2])
    np.testing.assert_array_equal(arrays["lb"], qp["lbx"])
    np.testing.assert_array_equal(arrays["ub"], qp["ubx"])
    np.testing.assert_array_equal(arrays["P"], qp["H"])
    bare = conic_to_qpsolvers({"g": np.ones(2), "lbx": np.full(2, -INF)})
    assert bare["G"] is None and bare["A"] is None and bare["lb"] is None
    np.testing.assert_array_equal(bare["P"], np.zeros((2, 2)))


def test_save_conic_takes_casadi_and_sparse_values(tmp_path: Path) -> None:
    import scipy.sparse as sp

    qp = conic_qp()
    path = save_conic(tmp_path / "qp", H=casadi.DM(qp["H"]), g=casadi.DM(qp["g"]),
                      A=sp.csc_matrix(qp["A"]), lba=qp["lba"], uba=casadi.DM(qp["uba"]),
                      lbx=qp["lbx"], ubx=qp["ubx"])
    assert path.name == "qp.npz"
    with np.load(path) as stored:
        assert set(stored.files) == set(CONIC_KEYS)
        assert set(stored.files) <= set(casadi.conic_in())  # CasADi's own input names
        np.testing.assert_array_equal(stored["a"], qp["A"])
        np.testing.assert_array_equal(stored["uba"], qp["uba"])
    with pytest.raises(InputError, match="lba > uba"):
        save_conic(tmp_path / "bad", H=np.eye(1), g=[0.0], A=[[1.0]], lba=[1.0], uba=[0.0])
    with pytest.raises(InputError, match="without A"):
        save_conic(tmp_path / "bad", H=np.eye(1), g=[0.0], lba=[1.0])


@pytest.mark.timeout(240)
def test_casadi_conic_runs_to_casadi_optimum(tmp_path: Path,
                                             capsys: pytest.CaptureFixture[str]) -> None:
    qp = conic_qp()
    optimum, x = casadi_optimum(qp)
    active = np.isclose(qp["A"] @ x, qp["uba"]) | np.isclose(qp["A"] @ x, qp["lba"])
    assert active[1:3].any()  # an inequality row binds, not only the equality
    source = tmp_path / "mine"
    source.mkdir()
    save_conic(source / "casadi_qp.npz", H=casadi.DM(qp["H"]), g=qp["g"], A=qp["A"],
               lba=qp["lba"], uba=qp["uba"], lbx=qp["lbx"], ubx=qp["ubx"])
    np.savez(source / "plain.npz", P=np.eye(2), q=-np.ones(2))  # a qpsolvers file beside it
    instances, results = tmp_path / "instances", tmp_path / "results"
    code, out, err = _cli(capsys, "problems", "import", str(source), "--out", str(instances))
    assert code == 0, err
    assert "imported 2 instances" in out
    problems = {p.name: p for p in load_instances(instances)}
    assert problems["casadi_qp"].family == Family.QP
    assert (problems["casadi_qp"].n_eq, problems["casadi_qp"].n_ineq) == (1, 3)
    code, _, err = _cli(capsys, "run", "--instances", str(instances), "--results",
                          str(results), "--solvers", "clarabel", "--start", "cold",
                          "--repeats", "1", "--quiet", "--no-report")
    assert code == 0, err
    rows = store.read_results(results / "instances").set_index("instance")
    assert bool(rows.loc["casadi_qp", "success"])
    assert rows.loc["casadi_qp", "objective"] == pytest.approx(optimum, rel=1e-6, abs=1e-6)
    assert rows.loc["casadi_qp", "reference_objective"] == pytest.approx(optimum, rel=1e-6,
                                                                          abs=1e-6)
    assert rows.loc["plain", "objective"] == pytest.approx(-1.0, rel=1e-6)


def test_bad_conic_file_exits_2_naming_it(tmp_path: Path,
                                          capsys: pytest.CaptureFixture[str]) -> None:
    source = tmp_path / "src"
    source.mkdir()
    bad = source / "bad.npz"
    np.savez(bad, h=np.eye(2), g=np.ones(2), a=np.ones((1, 2)), lba=[2.0], uba=[1.0])
    code, _, err = _cli(capsys, "problems", "import", str(source), "--out", str(tmp_path / "o"))
    assert code == 2 and str(bad) in err and "lba > uba" in err and err.count("\n") == 1


def brute_force_lcp(F: np.ndarray, q: np.ndarray) -> list[np.ndarray]:
    """Every solution of ``0 <= lam perp F lam + q >= 0`` found by trying each basis (the
    set of indices where ``w = 0``) and keeping the sign-feasible ones."""
    n, solutions = q.size, []
    for basis in itertools.product((False, True), repeat=n):
        free = np.flatnonzero(basis)
        lam = np.zeros(n)
        if free.size:
            lam[free] = np.linalg.solve(F[np.ix_(free, free)], -q[free])
        w = F @ lam + q
        if np.all(lam >= -1e-12) and np.all(w >= -1e-12):
            solutions.append(lam)
    return solutions


@pytest.mark.timeout(240)
def test_lcp_file_imports_as_lcp_general(tmp_path: Path,
                                         capsys: pytest.CaptureFixture[str]) -> None:
    F = np.array([[2.0, 1.5, 0.0], [-1.0, 3.0, 0.5], [0.5, -2.0, 4.0]])  # P-matrix, not symmetric
    q = np.array([-1.0, 0.5, -2.0])
    [expected] = brute_force_lcp(F, q)  # a P-matrix: exactly one solution
    source = tmp_path / "src"
    source.mkdir()
    np.savez(source / "my_lcp.npz", F=F, q=q)
    instances = tmp_path / "instances"
    code, out, err = _cli(capsys, "problems", "import", str(source), "--out", str(instances))
    assert code == 0, err
    assert out.splitlines()[2].split()[:3] == ["lcp_general", "-", "1"]  # the table's row
    [problem] = load_instances(instances)
    assert problem.family == Family.LCP_GENERAL and problem.meta["imported"] is True
    stored_F, stored_q = lcp_data(problem)
    np.testing.assert_array_equal(stored_F, F)
    np.testing.assert_array_equal(stored_q, q)
    results = tmp_path / "results"
    code, _, err = _cli(capsys, "run", "--instances", str(instances), "--results",
                          str(results), "--solvers", "lemke", "--start", "cold", "--repeats",
                          "1", "--quiet", "--no-report")
    assert code == 0, err
    [row] = store.read_results(results / "instances").to_dict("records")
    assert row["success"], row
    lemke = registry.get("lemke").solve(problem, settings_for("high_accuracy"))
    assert lemke.found and lemke.x is not None
    np.testing.assert_allclose(lemke.x, expected, atol=1e-9)
    np.savez(source / "extra.npz", F=F, q=q, G=np.eye(3))
    code, _, err = _cli(capsys, "problems", "import", str(source), "--out", str(tmp_path / "x"))
    assert code == 2 and "exactly the keys F and q" in err
    assert expected[0] > 0 and expected[2] > 0  # not the trivial lam = 0
