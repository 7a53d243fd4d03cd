"""Our exported instances run in qpbenchmark's own machinery and reach our stored references.

Three instances (two imported QPs and one with a constant ``objective_offset``) are run by
``c3bench run`` (which stores a high-accuracy Clarabel reference cross-checked by ProxQP),
exported, then run by qpbenchmark: its ``run`` on Clarabel (results with residuals under its
``high_accuracy`` tolerances), its solve call with its own settings (objective plus offset equal
to our reference), and its command line on the exported ``c3bench_test_set.py``.
"""

from __future__ import annotations

import importlib
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from c3bench.bench import store
from c3bench.bench.cli import main
from c3bench.bench.qpbenchmark_set import QpbenchmarkMissing, qpbenchmark_class
from c3bench.problems.instance import Problem, save_problem
from c3bench.problems.names import Family

try:
    qpbenchmark: Any = importlib.import_module("qpbenchmark")
except ImportError:  # optional: in the test extra
    qpbenchmark = None
needs_qpbenchmark = pytest.mark.skipif(qpbenchmark is None, reason="qpbenchmark is not "
                                       "installed (pip install qpbenchmark; in the test extra)")
SOLVER = "clarabel"
SETTINGS = "high_accuracy"


def _qp(seed: int, offset: float = 0.0) -> Problem:
    """A strictly convex QP with an equality row, inequality rows and bounds."""
    rng = np.random.default_rng(seed)
    M = rng.standard_normal((4, 4))
    return Problem(f"qp_{seed}", Family.QP, P=M @ M.T + 0.2 * np.eye(4),
                   q=3.0 * rng.standard_normal(4), A=np.ones((1, 4)), b=np.array([0.3]),
                   G=rng.standard_normal((2, 4)), h=np.array([0.1, -0.1]),
                   lb=np.full(4, -0.5), ub=np.full(4, 0.5), objective_offset=offset)


@pytest.fixture(scope="module")
def exported(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict[str, float]]:
    """``(export directory, our stored reference objective per instance)``."""
    root = tmp_path_factory.mktemp("qpb")
    instances = root / "instances"
    for problem in (_qp(1), _qp(2), _qp(3, offset=2.5)):
        save_problem(problem, instances)
    assert main(["run", "--instances", str(instances), "--results", str(root / "results"),
                 "--solvers", SOLVER, "--start", "cold", "--repeats", "1", "--quiet",
                 "--no-report"]) == 0
    frame = store.read_results(root / "results" / "instances")
    references = frame.groupby("instance")["reference_objective"].first().to_dict()
    assert main(["problems", "export", str(instances), "--out", str(root / "export"),
                 "--format", "qpsolvers"]) == 0
    return root / "export", {str(k): float(v) for k, v in references.items()}


@needs_qpbenchmark
def test_test_set_is_a_qpbenchmark_test_set(exported: tuple[Path, dict[str, float]]) -> None:
    directory, references = exported
    test_set = qpbenchmark_class()(directory)
    assert isinstance(test_set, qpbenchmark.TestSet)
    assert test_set.count_problems() == 3 and not test_set.sparse_only
    assert {p.name for p in test_set} == set(references)
    assert test_set.objective_offsets == {"qp_1": 0.0, "qp_2": 0.0, "qp_3": 2.5}
    assert SOLVER in test_set.solvers and set(test_set.tolerances) == set(
        test_set.solver_settings)
    assert isinstance(test_set.get_problem("qp_2"), qpbenchmark.Problem)


@needs_qpbenchmark
def test_qpbenchmark_run_reaches_our_references(exported: tuple[Path, dict[str, float]],
                                                tmp_path: Path) -> None:
    time_solve_problem = importlib.import_module("qpbenchmark.utils").time_solve_problem
    directory, references = exported
    test_set = qpbenchmark_class()(directory)
    results = qpbenchmark.Results(str(tmp_path / "results.csv"), test_set)
    qpbenchmark.run(test_set, results, only_solver=SOLVER, only_settings=SETTINGS)
    frame = results.df.set_index("problem")
    tolerance = test_set.tolerances[SETTINGS]
    assert set(frame.index) == set(references) and frame["found"].all()
    assert (frame["primal_residual"] < tolerance.primal).all()
    assert (frame["dual_residual"] < 1e-6).all() and (frame["duality_gap"] < 1e-6).all()
    for problem in test_set:
        solution, _ = time_solve_problem(problem, SOLVER,
                                         **test_set.solver_settings[SETTINGS][SOLVER])
        assert solution.found, problem.name
        ours = solution.obj + test_set.objective_offsets[problem.name]
        assert ours == pytest.approx(references[problem.name], rel=1e-7, abs=1e-8)


@needs_qpbenchmark
@pytest.mark.timeout(120)
def test_qpbenchmark_command_line_runs_the_export(exported: tuple[Path, dict[str, float]],
                                                  tmp_path: Path) -> None:
    directory, references = exported
    results = tmp_path / "results.csv"
    done = subprocess.run(
        [sys.executable, "-c", "from qpbenchmark.benchmark import main; main()",
         "--results-path", str(results), str(directory / "c3bench_test_set.py"), "run",
         "--solver", SOLVER, "--author", "c3bench"],
        capture_output=True, text=True, timeout=110, cwd=tmp_path)
    assert done.returncode == 0, done.stderr[-2000:]
    frame = qpbenchmark.Results.read_from_file(results)
    assert set(frame["problem"]) == set(references) and frame["found"].all()
    assert (tmp_path / "c3bench_test_set.md").exists()  # qpbenchmark's report


def test_missing_qpbenchmark_is_named(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "qpbenchmark", None)  # import qpbenchmark -> ImportError
    qpbenchmark_class.cache_clear()
    try:
        with pytest.raises(QpbenchmarkMissing, match="pip install qpbenchmark"):
            qpbenchmark_class()
    finally:
        qpbenchmark_class.cache_clear()
