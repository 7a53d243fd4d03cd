"""Bring your own problem: ``problems import``, ``run --instances``, ``problems export``.

The problems are written by the tests in qpsolvers' own ``.npz`` form (or yielded by a module
the test writes), solved through the whole CLI, and compared with a direct Clarabel call;
exported instances are read back by ``qpsolvers.Problem.load`` itself.
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path
from typing import Any

import clarabel
import numpy as np
import pandas as pd
import pytest
import qpsolvers
import scipy.sparse as sp

from c3bench.bench import store
from c3bench.bench.cli import main
from c3bench.bench.metrics import required_residuals
from c3bench.problems.capture import SuiteSpec
from c3bench.problems.errors import InstanceFormatError
from c3bench.problems.instance import Problem, load_instances, load_problem, save_problem
from c3bench.problems.names import QP_FAMILIES, Family
from c3bench.problems.suites import generate_suite
from c3bench.solvers import registry
from c3bench.solvers.base import settings_for

README = Path(__file__).resolve().parents[1] / "README.md"
EXAMPLE = re.compile(r"<!-- byo-example:start -->\s*```bash\n(.*?)```\s*"
                     r"<!-- byo-example:end -->", re.S)
TINY = SuiteSpec("tiny", n_states=1, admm_iterations=(0,), projection_iterations=(0,),
                 projection_steps=(0,))
SOLVERS = "clarabel,osqp,daqp,piqp"


def external_qp(seed: int, n: int = 5) -> dict[str, Any]:
    """A convex QP with equality and inequality rows and bounds, some of them active."""
    rng = np.random.default_rng(seed)
    M = rng.standard_normal((n, n))
    return {"P": M @ M.T + 0.1 * np.eye(n), "q": 5.0 * rng.standard_normal(n),
            "G": rng.standard_normal((2, n)), "h": np.array([0.1, -0.2]),
            "A": np.ones((1, n)), "b": np.array([0.5]),
            "lb": np.full(n, -0.4), "ub": np.full(n, 0.6)}


def clarabel_optimum(qp: dict[str, np.ndarray]) -> tuple[float, np.ndarray]:
    """``(f*, x*)`` from Clarabel's own API: ``A x + s = b``, ``s`` in zero x nonnegative."""
    n = qp["q"].size
    rows = sp.vstack([sp.csc_matrix(qp["A"]), sp.csc_matrix(qp["G"]), sp.eye(n), -sp.eye(n)],
                     format="csc")
    rhs = np.concatenate([qp["b"], qp["h"], qp["ub"], -qp["lb"]])
    settings = clarabel.DefaultSettings()
    settings.verbose = False
    settings.tol_gap_abs = settings.tol_gap_rel = settings.tol_feas = 1e-10
    solver = clarabel.DefaultSolver(sp.csc_matrix(np.triu(qp["P"])), qp["q"], rows, rhs,
                                    [clarabel.ZeroConeT(qp["b"].size),
                                     clarabel.NonnegativeConeT(rhs.size - qp["b"].size)],
                                    settings)
    solution = solver.solve()
    assert str(solution.status) == "Solved"
    x = np.asarray(solution.x)
    return float(0.5 * x @ qp["P"] @ x + qp["q"] @ x), x


def _cli(capsys: pytest.CaptureFixture[str], *argv: str) -> tuple[int, str, str]:
    code = main(list(argv))
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def _import_and_run(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                    problems: dict[str, dict[str, Any]]) -> tuple[Path, tuple[str, ...]]:
    """Write ``problems`` in qpsolvers' form, import them, delete the manifest (any directory
    of instances runs), run them; returns the suite folder and the run's arguments."""
    source = tmp_path / "mine"
    source.mkdir()
    for index, (name, qp) in enumerate(problems.items()):
        if index % 2 == 0:
            qpsolvers.Problem(**qp).save(str(source / f"{name}.npz"))  # qpsolvers' writer
        else:
            np.savez(source / f"{name}.npz", **qp)  # the same keys written by numpy
    instances, results = tmp_path / "instances", tmp_path / "results"
    code, out, err = _cli(capsys, "problems", "import", str(source), "--out", str(instances))
    assert code == 0, err
    assert f"imported {len(problems)} instances" in out
    assert {p.family for p in load_instances(instances)} == {Family.QP}
    (instances / "manifest.json").unlink()
    run = ("run", "--instances", str(instances), "--results", str(results), "--solvers", SOLVERS,
           "--start", "cold", "--repeats", "1", "--quiet", "--no-report")
    code, out, err = _cli(capsys, *run)
    assert code == 0, err
    assert f"{4 * len(problems)} cells planned" in out
    suite = results / "instances"
    assert (suite / "instances" / "manifest.json").exists()  # written for the copy
    return suite, run


@pytest.mark.timeout(240)
def test_imported_qp_runs_to_clarabel_optimum(tmp_path: Path,
                                              capsys: pytest.CaptureFixture[str]) -> None:
    problems = {"first": external_qp(1), "second": external_qp(2)}
    suite, _ = _import_and_run(tmp_path, capsys, problems)
    frame = store.read_results(suite)
    assert len(frame) == 8
    for name, qp in problems.items():
        optimum, x = clarabel_optimum(qp)
        assert np.any(np.isclose(x, qp["lb"]) | np.isclose(x, qp["ub"]))  # a bound is active
        rows = frame[frame["instance"] == name]
        assert rows["reference_objective"].iloc[0] == pytest.approx(optimum, rel=1e-7, abs=1e-9)
        assert rows["success"].all(), rows[["solver", "verdict"]]
        for objective in rows["objective"]:
            assert objective == pytest.approx(optimum, rel=1e-3, abs=1e-6)


@pytest.mark.slow
@pytest.mark.timeout(300)
def test_reimported_change_reruns_only_its_cells(tmp_path: Path,
                                                 capsys: pytest.CaptureFixture[str]) -> None:
    first, second = external_qp(3), external_qp(4)
    suite, run = _import_and_run(tmp_path, capsys, {"first": first, "second": second})
    code, out, _ = _cli(capsys, *run)
    assert code == 0 and "8 already stored, 0 run" in out
    changed = dict(first, q=-first["q"])
    np.savez(tmp_path / "mine" / "first.npz", **changed)
    code, _, err = _cli(capsys, "problems", "import", str(tmp_path / "mine"), "--out",
                        str(tmp_path / "instances"))
    assert code == 0, err
    code, out, err = _cli(capsys, *run)
    assert code == 0, err
    assert "4 already stored, 4 run" in out and "4 stale cells" in out
    rows = store.read_results(suite).set_index("instance")
    assert rows.loc["first", "objective"].to_numpy() == pytest.approx(
        clarabel_optimum(changed)[0], rel=1e-3, abs=1e-6)
    assert rows.loc["second", "objective"].to_numpy() == pytest.approx(
        clarabel_optimum(second)[0], rel=1e-3, abs=1e-6)


def test_a_table_without_cell_files_keeps_the_rows_a_run_does_not_plan(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A fresh checkout has results.parquet but no cells/ (never committed): running one
    solver there measures that solver again and keeps every other solver's rows."""
    import shutil

    suite, run = _import_and_run(tmp_path, capsys, {"first": external_qp(5),
                                                   "second": external_qp(6)})
    before = store.read_results(suite)
    shutil.rmtree(suite / "cells")
    one = tuple("osqp" if value == SOLVERS else value for value in run)
    code, out, err = _cli(capsys, *one)
    assert code == 0, err
    assert "2 cells planned, 0 already stored, 2 run" in out and "6 rows of the stored" in out
    after = store.read_results(suite)
    assert len(after) == len(before) == 8
    kept = ["cell_id", "solver", "objective", "setup_time", "solve_time"]
    others = before[before.solver != "osqp"][kept].reset_index(drop=True)
    pd.testing.assert_frame_equal(after[after.solver != "osqp"][kept].reset_index(drop=True),
                                  others)
    (suite / "results.parquet").write_bytes(b"not parquet")  # unreadable: never replaced
    shutil.rmtree(suite / "cells")
    code, _, err = _cli(capsys, *one)
    assert code == 2 and "results.parquet" in err and "move it away" in err
    assert (suite / "results.parquet").read_bytes() == b"not parquet"


def test_export_reads_back_in_qpsolvers(tmp_path: Path,
                                        capsys: pytest.CaptureFixture[str]) -> None:
    suite, out = tmp_path / "suite", tmp_path / "export"
    generate_suite(TINY, suite, progress=False)
    problems = {p.name: p for p in load_instances(suite)}
    code, _, err = _cli(capsys, "problems", "export", str(suite), "--out", str(out),
                        "--format", "qpsolvers")
    assert code == 0
    index = json.loads((out / "index.json").read_text())
    exported = {entry["name"]: entry for entry in index["instances"]}
    assert {problems[n].family for n in exported} == {"c3plus_qp", "c3_qp", "lcp"}
    assert set(index["skipped"]) == {n for n, p in problems.items() if p.n_pairs}
    assert "left out" in err
    clarabel_backend = registry.get("clarabel")
    for name, entry in exported.items():
        ours = problems[name]
        loaded = qpsolvers.Problem.load(str(out / entry["file"]))
        for key in ("P", "q", "A", "b", "G", "h", "lb", "ub"):
            mine, theirs = getattr(ours, key), getattr(loaded, key)
            assert (mine is None) == (theirs is None), (name, key)
            if mine is not None:
                np.testing.assert_array_equal(theirs, mine)
        solution = qpsolvers.solve_problem(loaded, solver="clarabel")
        assert solution.found, name
        reference = clarabel_backend.solve(ours, settings_for("high_accuracy"))
        assert reference.found and reference.objective is not None
        theirs_f = solution.obj + entry["objective_offset"]
        assert theirs_f == pytest.approx(reference.objective, rel=1e-6, abs=1e-8), name


def test_module_test_set_imports(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                 capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / "byo_testset.py").write_text(
        "import numpy as np\n"
        "from qpsolvers import Problem\n\n"
        "class Boxes:\n"
        "    def __iter__(self):\n"
        "        for k in range(3):\n"
        "            yield Problem(np.eye(2) * (k + 1), np.ones(2), lb=np.zeros(2))\n\n"
        "def named():\n"
        "    yield 'ridge/one', Problem(np.eye(3), -np.ones(3), A=np.ones(3), b=np.array(1.0))\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    out = tmp_path / "instances"
    code, out_text, err = _cli(capsys, "problems", "import", "--module", "byo_testset", "--out",
                           str(out))
    assert code == 0, err
    assert "imported 4 instances" in out_text
    problems = {p.name: p for p in load_instances(out)}
    assert set(problems) == {"Boxes_000", "Boxes_001", "Boxes_002", "ridge_one"}
    assert problems["ridge_one"].n_eq == 1 and problems["Boxes_002"].P[0, 0] == 3.0
    assert _cli(capsys, "problems", "import", "--module", "no_such_byo_module", "--out",
                str(tmp_path / "x"))[0] == 2


@pytest.mark.parametrize(("content", "message"), [
    (b"not a zip archive", "unreadable"),
    (None, "positive semi-definite"),
    ({"P": np.eye(2), "q": np.ones(3)}, "shape"),
    ({"P": np.eye(2), "c": np.ones(2)}, "not qpsolvers' Problem keys"),
])
def test_bad_import_file_exits_2_naming_it(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                           content: object, message: str) -> None:
    source = tmp_path / "src"
    source.mkdir()
    np.savez(source / "good.npz", P=np.eye(2), q=np.ones(2))
    bad = source / "bad.npz"
    if isinstance(content, bytes):
        bad.write_bytes(content)
    elif isinstance(content, dict):
        np.savez(bad, **content)
    else:
        np.savez(bad, P=np.array([[1.0, 0.0], [0.0, -1.0]]), q=np.ones(2))  # not convex
    out = tmp_path / "out"
    code, _, err = _cli(capsys, "problems", "import", str(source), "--out", str(out))
    assert code == 2
    assert err.count("\n") == 1 and err.startswith("error: ") and str(bad) in err
    assert message in err
    assert not out.exists()  # nothing half-written


def test_generic_families_load_without_cube_metadata(tmp_path: Path) -> None:
    bare: dict[str, Any] = {"P": np.eye(2), "q": np.ones(2), "lb": np.zeros(2),
                            "ub": np.ones(2)}
    for family in (Family.QP, Family.MPCC, Family.LCP):
        save_problem(Problem(f"bare_{family}", family, **bare), tmp_path)
        assert load_problem(tmp_path / f"bare_{family}.json").meta == {}
    save_problem(Problem("bare_c3plus", Family.C3PLUS_QP, **bare), tmp_path)
    with pytest.raises(InstanceFormatError, match=r"meta\.scene"):
        load_problem(tmp_path / "bare_c3plus.json")
    assert Family.QP in QP_FAMILIES
    assert required_residuals(Family.QP) == required_residuals(Family.C3PLUS_QP)
    assert all(Family.QP in registry.get(info.name).families for info in registry.available()
               if Family.C3PLUS_QP in info.families and Family.LCP in info.families)


@pytest.mark.slow
@pytest.mark.timeout(240)
def test_readme_example_runs_verbatim(tmp_path: Path) -> None:
    found = EXAMPLE.search(README.read_text())
    assert found, "README.md lacks the 'Benchmark your own problem' example between the " \
                  "<!-- byo-example:start --> and <!-- byo-example:end --> markers"
    done = subprocess.run(["bash", "-euo", "pipefail", "-c", found.group(1)], cwd=tmp_path,
                          capture_output=True, text=True, timeout=220,
                          env={**os.environ, "PATH": f"{Path(sys.executable).parent}:"
                                                     f"{os.environ.get('PATH', '')}"})
    assert done.returncode == 0, done.stderr[-2000:]
    frame = store.read_results(tmp_path / "my_results" / "my_instances")
    assert frame["success"].all() and len(frame) == 2
    loaded = qpsolvers.Problem.load(str(tmp_path / "my_export" / "toy.npz"))
    assert qpsolvers.solve_problem(loaded, solver="clarabel").obj == pytest.approx(
        frame["reference_objective"].iloc[0], rel=1e-6)


def test_run_instances_refuses_what_is_not_instances(tmp_path: Path,
                                                     capsys: pytest.CaptureFixture[str]) -> None:
    raw = tmp_path / "raw"
    raw.mkdir()
    np.savez(raw / "toy.npz", P=np.eye(2), q=np.ones(2))
    code, _, err = _cli(capsys, "run", "--instances", str(raw), "--results", str(tmp_path / "r"))
    assert code == 2 and "c3bench problems import" in err and err.count("\n") == 1
    code, _, err = _cli(capsys, "run", "--instances", str(tmp_path / "absent"))
    assert code == 2 and "not a directory" in err
    assert not (tmp_path / "r").exists()


def test_list_counts_bounds_as_inequalities(tmp_path: Path,
                                            capsys: pytest.CaptureFixture[str]) -> None:
    qp = external_qp(5)
    qp["ub"][0] = np.inf  # one side infinite: 5 finite lb + 4 finite ub
    source = tmp_path / "src"
    source.mkdir()
    np.savez(source / "mixed.npz", **qp)
    out = tmp_path / "instances"
    assert _cli(capsys, "problems", "import", str(source), "--out", str(out))[0] == 0
    code, text, _ = _cli(capsys, "problems", "list", str(out))
    assert code == 0
    header, row = (line.split() for line in text.splitlines()[:2])
    values = dict(zip(header, row, strict=True))
    assert values["inequality_rows"] == "2" and values["bounded_variables"] == "5"
    assert values["inequalities"] == str(2 + 5 + 4)
    main(["problems", "list", "--help"])
    help_text = " ".join(capsys.readouterr().out.split())
    assert "inequalities = inequality rows + finite bound entries" in help_text
