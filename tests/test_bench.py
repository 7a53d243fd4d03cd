"""Tests of the benchmark runner, results store, metrics, report and compare (bench/).

Fake backends are registered for this module only (a module fixture; forked pool workers
inherit them, Dask workers load them through ``preload=("test_bench:register_fakes",)``):
a correct dense KKT solver, a second correct one (the reference's cross-check), one returning
a wrong point with ``found=True``, one that raises, one that sleeps past the time limit, one
returning NaN and one whose cells kill their pool worker. References are pointed at the
fakes, so nothing here depends on the real backends.
"""

from __future__ import annotations

import math
import os
import re
import shutil
import time
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pyarrow.parquet as pq
import pytest

from c3bench.bench import perf_store, runner, store
from c3bench.bench import reference as reference_module
from c3bench.bench.cli import main
from c3bench.bench.compare import compare, compare_frame
from c3bench.bench.executors import LocalPool, TaskOutcome
from c3bench.bench.metrics import TIME_SHIFT, aggregate, judge, success_series
from c3bench.bench.planning import Cell, predecessors
from c3bench.bench.reference import ReferencePlan, load_references
from c3bench.bench.report import write_report
from c3bench.bench.rows import CellOutcome, run_cell
from c3bench.problems.capture import SuiteSpec
from c3bench.problems.errors import InputError, SchemaVersionError
from c3bench.problems.instance import Problem
from c3bench.problems.names import QPVariant
from c3bench.problems.suites import generate_suite
from c3bench.solvers import registry
from c3bench.solvers.base import Backend, Result, Settings, WarmStart
from c3bench.solvers.timing import Stopwatch

QP = ("c3plus_qp", "c3_qp")
# one state, the equality variant (the fake KKT backends take equality constraints only)
TINY = SuiteSpec("tiny", n_states=1, admm_iterations=(0, 1, 2), projection_iterations=(0,),
                 projection_steps=(0,), qp_variants=(QPVariant.EQUALITY,))


# --- fake backends ------------------------------------------------------------------------------
def _kkt_solve(problem: Problem, dtype: type) -> tuple[np.ndarray, np.ndarray]:
    """x, y of min 1/2 x'Px + q'x s.t. Ax = b from the KKT system (dual sign: P x + q + A'y)."""
    n, m = problem.n, problem.n_eq
    K = np.block([[problem.P, problem.A.T], [problem.A, np.zeros((m, m))]]).astype(dtype)
    rhs = np.concatenate([-problem.q, problem.b]).astype(dtype)
    sol = np.linalg.solve(K, rhs).astype(float)
    return sol[:n], sol[n:]


class FakeKKT(Backend):
    name = "fake_kkt"
    families = QP
    precisions = ("float64", "float32")

    def solve(self, problem: Problem, settings: Settings,
              warm_start: WarmStart | None = None) -> Result:
        watch = Stopwatch()
        dtype = np.float32 if settings.precision == "float32" else np.float64
        with watch.lap("solve"):
            x, y = _kkt_solve(problem, dtype)
        warm = math.nan if warm_start is None or warm_start.x is None else float(
            np.linalg.norm(warm_start.x))
        return Result(self.name, problem.name, True, "solved", x=x, y=y, iterations=1,
                      solve_time=watch.get("solve"),
                      trace={"primal_residual": [1.0, 1e-3, 1e-9]},
                      diagnostics={"cond_kkt": 1e6, "warm_norm": warm,
                                   "cond_schur_raw": 1e12 * (1 + problem.meta[
                                       "admm_iteration"]), "cond_schur_equilibrated": 1e4})


class FakeLU(Backend):
    name = "fake_lu"
    families = QP

    def solve(self, problem: Problem, settings: Settings,
              warm_start: WarmStart | None = None) -> Result:
        K = np.block([[problem.P, problem.A.T], [problem.A, np.zeros((problem.n_eq,) * 2)]])
        rhs = np.concatenate([-problem.q, problem.b])
        sol = np.linalg.solve(K, rhs)  # LU, then two steps of iterative refinement
        for _ in range(2):
            sol += np.linalg.solve(K, rhs - K @ sol)
        return Result(self.name, problem.name, True, "solved", x=sol[:problem.n],
                      y=sol[problem.n:], iterations=1)


class FakeWrong(Backend):
    """Claims success but returns the correct point shifted: residuals must catch it."""

    name = "fake_wrong"
    families = ("c3_qp",)

    def solve(self, problem: Problem, settings: Settings,
              warm_start: WarmStart | None = None) -> Result:
        x, y = _kkt_solve(problem, np.float64)
        return Result(self.name, problem.name, True, "solved", x=x + 0.05, y=y, iterations=3)


class FakeCrash(Backend):
    name = "fake_crash"
    families = ("c3_qp",)

    def solve(self, problem: Problem, settings: Settings,
              warm_start: WarmStart | None = None) -> Result:
        raise RuntimeError("fake solver crashed")


class FakeHang(Backend):
    name = "fake_hang"
    families = ("c3_qp",)

    def solve(self, problem: Problem, settings: Settings,
              warm_start: WarmStart | None = None) -> Result:
        time.sleep(30)
        raise AssertionError("should have been killed")


class FakeNaN(Backend):
    name = "fake_nan"
    families = ("c3_qp",)

    def solve(self, problem: Problem, settings: Settings,
              warm_start: WarmStart | None = None) -> Result:
        return Result(self.name, problem.name, True, "solved", x=np.full(problem.n, np.nan))


class FakeDie(Backend):
    """Its cells kill the pool worker itself (see ``dying_run_cell``)."""

    name = "fake_die"
    families = ("c3_qp",)

    def solve(self, problem: Problem, settings: Settings,
              warm_start: WarmStart | None = None) -> Result:
        return Result(self.name, problem.name, False, "never reached")


FAKES: tuple[Backend, ...] = (FakeKKT(), FakeLU(), FakeWrong(), FakeCrash(), FakeHang(),
                              FakeNaN(), FakeDie())


def register_fakes() -> None:
    """Plugin entry for Dask workers (``preload=("test_bench:register_fakes",)``)."""
    for backend in FAKES:
        registry.register(backend)

FAKE_PLANS = {family: ReferencePlan("fake_kkt", "fake_lu") for family in QP}


def dying_run_cell(cell: Cell, *args: Any) -> CellOutcome:
    """``run_cell`` that kills its own worker process for ``fake_die`` cells."""
    if cell.solver == "fake_die":
        os._exit(7)
    return REAL_RUN_CELL(cell, *args)


REAL_RUN_CELL = run_cell


def exit_task(code: int) -> int:
    os._exit(code)


def square_task(value: int) -> int:
    return value * value


def sleep_task(seconds: float) -> float:
    time.sleep(seconds)
    return seconds


# --- fixtures -----------------------------------------------------------------------------------
@pytest.fixture(scope="module", autouse=True)
def fakes() -> Any:
    """Fake backends and reference plans for this module only (removed afterwards, so other
    test modules never see them; forked pool workers inherit them)."""
    registry.backends()  # load the real ones first
    with pytest.MonkeyPatch.context() as patch:
        for backend in FAKES:
            patch.setitem(registry._BACKENDS, backend.name, backend)
        patch.setattr(reference_module, "REFERENCE_PLANS", FAKE_PLANS)
        yield


@pytest.fixture(scope="module")
def instances(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("tiny_instances")
    generate_suite(TINY, out, progress=False)
    return out


def _seed(results: Path, instances: Path) -> None:
    """Place the pre-generated tiny suite where the runner looks for it."""
    target = store.SuitePaths.of(results, "tiny").instances
    target.parent.mkdir(parents=True, exist_ok=True)
    os.symlink(instances, target)


RUN = dict(solvers=["fake_kkt", "fake_wrong"], families=QP, repeats=1, time_limit=5.0,
           reference_time_limit=10.0, progress=False)


@pytest.fixture(scope="module")
def resumed(tmp_path_factory: pytest.TempPathFactory, instances: Path) -> dict[str, Any]:
    """Run, interrupt after 5 cells, resume, run once more: what each step saw."""
    results = tmp_path_factory.mktemp("results")
    _seed(results, instances)
    paths = store.SuitePaths.of(results, "tiny")
    seen: list[str] = []

    def stop_after_five(outcome: CellOutcome) -> None:
        seen.append(outcome.row["cell_id"])
        if len(seen) == 5:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        runner.run_suite("tiny", results, on_cell=stop_after_five, **RUN)
    after_interrupt = store.read_results(paths.parquet)
    cell_files = sorted(p.name for p in paths.cells.glob("*.json"))
    second = runner.run_suite("tiny", results, **RUN)
    third = runner.run_suite("tiny", results, **RUN)
    return {"results": results, "paths": paths, "interrupted": after_interrupt,
            "cell_files": cell_files, "seen": seen, "second": second, "third": third,
            "frame": store.read_results(paths.root)}


# --- runner: interrupt, resume, cells -------------------------------------------------------------
def test_interrupt_then_resume_stores_every_cell_once(resumed: dict[str, Any]) -> None:
    interrupted = resumed["interrupted"]
    assert len(interrupted) == 5 == len(resumed["cell_files"])
    assert sorted(interrupted["cell_id"]) == sorted(resumed["seen"])
    second, third = resumed["second"], resumed["third"]
    # 3 c3plus + 3 c3 instances; fake_kkt: 6 x 2 precisions cold + 4 x 2 warm = 20;
    # fake_wrong (c3_qp, float64 only): 3 cold + 2 warm = 5.
    assert second.planned == 25
    assert second.already_done == 5 and second.ran == 20
    assert third.already_done == 25 and third.ran == 0
    frame = resumed["frame"]
    assert len(frame) == 25
    assert not frame.duplicated(list(store.KEY_COLUMNS)).any()
    assert set(frame["cell_id"]) >= set(interrupted["cell_id"])
    csv = store.read_results(resumed["paths"].csv)
    pd.testing.assert_frame_equal(csv, frame, check_dtype=False)


def test_cells_follow_backend_families_precisions_and_sequences(
        resumed: dict[str, Any]) -> None:
    frame = resumed["frame"]
    assert set(frame.loc[frame["solver"] == "fake_wrong", "family"]) == {"c3_qp"}
    assert set(frame.loc[frame["solver"] == "fake_wrong", "precision"]) == {"float64"}
    assert set(frame.loc[frame["solver"] == "fake_kkt", "precision"]) == {"float64", "float32"}
    warm = frame[frame["start"] == "warm"]
    assert set(warm["admm_iteration"]) == {1, 2}  # iteration 0 has no predecessor
    assert (frame["repeats"] == 1).all()
    assert (frame["rho_lam"] == 50.0 * 2.0 ** frame["admm_iteration"].astype(float)).all()


def test_warm_start_is_the_predecessors_reference(resumed: dict[str, Any]) -> None:
    paths, frame = resumed["paths"], resumed["frame"]
    references = load_references(paths.references)
    warm = frame[(frame["start"] == "warm") & (frame["solver"] == "fake_kkt")]
    assert len(warm) == 8
    for row in warm.to_dict("records"):
        before = row["instance"].replace(f"i{row['admm_iteration']:02d}",
                                         f"i{row['admm_iteration'] - 1:02d}")
        expected = np.linalg.norm(references[before].x)
        got = store.read_trace(paths, row["trace_file"])["diagnostics"]["warm_norm"]
        assert got == pytest.approx(expected, rel=1e-12)
    cold = frame[(frame["start"] == "cold") & (frame["solver"] == "fake_kkt")]
    for row in cold.to_dict("records"):
        assert math.isnan(store.read_trace(paths, row["trace_file"])["diagnostics"][
            "warm_norm"] or math.nan)


def test_references_are_cross_checked(resumed: dict[str, Any]) -> None:
    references = load_references(resumed["paths"].references)
    assert len(references) == 6
    for ref in references.values():
        assert ref.available and ref.solver == "fake_kkt" and ref.check_solver == "fake_lu"
        # ill-conditioned: two direct methods differ; an inaccurate check gives no spread
        if math.isnan(ref.spread):
            assert "residual" in ref.check_status
        else:
            assert 0 <= ref.spread < 1e-5
        assert ref.x is not None and ref.y is not None
    assert sum(math.isfinite(r.spread) for r in references.values()) >= 4


def test_success_needs_residuals_not_found(resumed: dict[str, Any]) -> None:
    frame = resumed["frame"]
    wrong = frame[frame["solver"] == "fake_wrong"]
    assert wrong["found"].all()
    assert not wrong["success"].any()
    assert wrong["verdict"].str.contains("primal_residual_relative").all()
    good = frame[(frame["solver"] == "fake_kkt") & (frame["precision"] == "float64")]
    assert good["success"].all()
    assert (good["cost_error"] < 1e-9).all()
    assert (success_series(frame) == frame["success"]).all()


def test_judge_rules_per_family() -> None:
    row = store.empty_row()
    row.update({"family": "c3_qp", "found": True, "tolerance": 1e-3,
                "primal_residual_relative": 1e-5, "dual_residual_relative": 1e-5,
                "duality_gap_relative": 1e-5, "complementarity_violation": 0.0,
                "primal_residual": 5.0, "dual_residual": 5.0, "duality_gap": 5.0})
    assert judge(row) == (True, "")
    assert not judge({**row, "found": False})[0]
    assert judge(row)[0]  # absolute residuals are not judged: relative ones are
    assert not judge({**row, "primal_residual_relative": 2e-3})[0]
    assert not judge({**row, "duality_gap_relative": 2e-3})[0]
    assert not judge({**row, "dual_residual_relative": math.nan})[0]  # duals required
    # projection / mpcc have no dual certificate: duals not required ...
    mpcc = {**row, "family": "mpcc", "dual_residual_relative": math.nan,
            "duality_gap_relative": math.nan, "reference_solver": "r",
            "reference_objective": 1.0, "reference_spread": 0.0, "cost_error": 0.0}
    assert judge(mpcc)[0]
    # ... but complementarity is
    assert not judge({**mpcc, "complementarity_violation": 0.1})[0]
    # cost error counts where a reference exists, against max(tolerance, spread)
    referenced = {**row, "reference_solver": "r", "reference_objective": 10.0,
                  "reference_spread": math.nan, "cost_error": 5e-3}
    assert not judge(referenced)[0]
    assert judge({**referenced, "reference_spread": 1e-2})[0]
    assert not judge({**referenced, "cost_error": math.nan})[0]
    assert judge({**row, "cost_error": 5.0})[0]  # no reference: not judged on cost


def test_unavailable_reference_gives_nan_cost_error_and_a_reason(
        tmp_path: Path, instances: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    _seed(tmp_path, instances)
    monkeypatch.setattr(reference_module, "REFERENCE_PLANS",
                        {"c3_qp": ReferencePlan("no_such_backend", None)})
    runner.run_suite("tiny", tmp_path, solvers=["fake_kkt", "fake_wrong"], families=("c3_qp",),
                     starts=("cold", "warm"), precisions=("float64",), repeats=1,
                     time_limit=5.0, progress=False)
    frame = store.read_results(tmp_path / "tiny")
    assert len(frame) == 3 * 2  # no reference solution: no warm starts
    assert frame["cost_error"].isna().all() and (frame["reference_solver"] == "").all()
    assert frame.loc[frame["solver"] == "fake_kkt", "success"].all()  # residuals alone
    assert not frame.loc[frame["solver"] == "fake_wrong", "success"].any()
    references = load_references(tmp_path / "tiny" / "references.parquet")
    assert all("unknown solver 'no_such_backend'" in r.reason for r in references.values())
    text = write_report("tiny", tmp_path, figures=False).read_text()
    assert "unknown solver 'no_such_backend'" in _table(text, "## Reference optima")[
        "c3_qp"]["why not"]


def test_cells_of_a_changed_instance_are_rerun(tmp_path: Path, instances: Path) -> None:
    import shutil

    copy = tmp_path / "instances"
    shutil.copytree(instances, copy)
    _seed(tmp_path, copy)
    options = dict(solvers=["fake_wrong"], families=("c3_qp",), starts=("cold",),
                   precisions=("float64",), repeats=1, time_limit=5.0, progress=False)
    assert runner.run_suite("tiny", tmp_path, max_cells=2, **options).ran == 2
    assert runner.run_suite("tiny", tmp_path, **options).ran == 1
    changed = sorted((copy / "c3_qp").glob("*.json"))[0]
    changed.write_text(changed.read_text().replace('"seed": 0', '"seed": 1'))
    summary = runner.run_suite("tiny", tmp_path, **options)
    assert (summary.stale_removed, summary.already_done, summary.ran) == (1, 2, 1)
    frame = store.read_results(tmp_path / "tiny")
    assert len(frame) == 3 and frame["instance_hash"].nunique() == 3


ADOPT = dict(families=("c3_qp",), starts=("cold",), precisions=("float64",), repeats=1,
             time_limit=5.0, progress=False)


def test_an_interrupted_adoption_keeps_every_row_of_the_table(
        tmp_path: Path, instances: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A fresh checkout (table, no cells/) whose adoption of the table's rows is interrupted
    after two cell files: the table is untouched and the next run adopts every row."""
    _seed(tmp_path, instances)
    paths = store.SuitePaths.of(tmp_path, "tiny")
    runner.run_suite("tiny", tmp_path, solvers=["fake_kkt", "fake_wrong"], **ADOPT)
    table = store.read_results(paths.parquet)
    assert len(table) == 6
    shutil.rmtree(paths.cells)
    paths.cells.mkdir()  # an empty cells/ is no cell files either
    stored = paths.parquet.read_bytes()
    written = []
    real_write_cell = store.write_cell

    def interrupted(*args: Any, **kwargs: Any) -> Path:
        if len(written) == 2:
            raise KeyboardInterrupt
        written.append(real_write_cell(*args, **kwargs))
        return written[-1]

    monkeypatch.setattr(store, "write_cell", interrupted)
    with pytest.raises(KeyboardInterrupt):
        runner.run_suite("tiny", tmp_path, solvers=["fake_wrong"], **ADOPT)
    assert paths.parquet.read_bytes() == stored
    assert not (paths.root / runner.ADOPTING).exists()
    monkeypatch.undo()
    summary = runner.run_suite("tiny", tmp_path, solvers=["fake_wrong"], **ADOPT)
    assert (summary.adopted, summary.ran) == (3, 3)
    after = store.read_results(paths.parquet)
    kept = ["cell_id", "objective", "solve_time"]
    pd.testing.assert_frame_equal(after[kept], table[kept])


def test_an_unreadable_table_with_an_empty_cells_folder_is_kept_and_nothing_written(
        tmp_path: Path, instances: Path) -> None:
    _seed(tmp_path, instances)
    paths = store.SuitePaths.of(tmp_path, "tiny")
    paths.cells.mkdir(parents=True)
    paths.parquet.write_bytes(b"not parquet")
    with pytest.raises(InputError, match="move it away") as caught:
        runner.run_suite("tiny", tmp_path, solvers=["fake_wrong"], **ADOPT)
    assert paths.parquet.read_bytes() == b"not parquet"
    assert not paths.csv.exists() and not paths.run_info.exists()
    message = str(caught.value)  # one line, the file named first and once there
    assert message.startswith(f"{paths.parquet}: not a readable") and "\n" not in message


# --- crashes, hangs, NaN, dead workers ------------------------------------------------------------
def test_crash_hang_nan_cost_only_their_rows_and_a_dead_worker_no_row(
        tmp_path: Path, instances: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    _seed(tmp_path, instances)
    monkeypatch.setattr(runner, "run_cell", dying_run_cell)
    summary = runner.run_suite(
        "tiny", tmp_path, solvers=["fake_kkt", "fake_crash", "fake_hang", "fake_nan",
                                   "fake_die"],
        families=("c3_qp",), starts=("cold",), precisions=("float64",), repeats=1,
        time_limit=1.0, reference_time_limit=10.0, progress=False)
    frame = store.read_results(tmp_path / "tiny")
    assert summary.ran == len(frame) == 12
    by_solver = {s: g for s, g in frame.groupby("solver")}
    assert by_solver["fake_kkt"]["success"].all()
    assert (by_solver["fake_crash"]["failure"] == "error").all()
    assert by_solver["fake_crash"]["status"].str.contains("fake solver crashed").all()
    assert (by_solver["fake_hang"]["failure"] == "timeout").all()
    assert (by_solver["fake_nan"]["failure"] == "non_finite").all()
    # a worker that dies outside the solve is the infrastructure's fault: no row, retried
    # once, then missing for the next run
    assert "fake_die" not in by_solver
    assert summary.missing == 3
    assert summary.missing_reasons == ["pool worker died (exit code 7) outside the isolated "
                                       "solve"]
    assert not frame.loc[frame["solver"] != "fake_kkt", "success"].any()


def test_local_pool_survives_dead_and_stuck_workers() -> None:
    pool = LocalPool(2)
    tasks = [("a", square_task, (3,), 30.0), ("dead", exit_task, (5,), 30.0),
             ("b", square_task, (4,), 30.0), ("stuck", sleep_task, (60.0,), 1.0),
             ("c", square_task, (5,), 30.0)]
    results = {r.key: r for r in pool.run(tasks)}
    assert {k: r.value for k, r in results.items() if r.ok} == {"a": 9, "b": 16, "c": 25}
    assert results["dead"].outcome == TaskOutcome.WORKER_DIED
    assert "exit code 5" in results["dead"].reason and results["dead"].attempts == 2
    assert results["stuck"].outcome == TaskOutcome.WATCHDOG
    assert results["stuck"].attempts == 2
    assert pool.workers == []


# --- Dask ---------------------------------------------------------------------------------------
@pytest.mark.slow  # 35-40 s; the Dask path stays in the default run through test_faults'
# lost-scheduler and daemonic-worker tests
def test_dask_cluster_gives_the_same_rows(tmp_path: Path, instances: Path) -> None:
    distributed = pytest.importorskip("distributed")
    options = dict(solvers=["fake_kkt", "fake_wrong"], families=("c3_qp",),
                   starts=("cold", "warm"), precisions=("float64",), repeats=1,
                   time_limit=5.0, reference_time_limit=10.0, progress=False)
    local, remote = tmp_path / "local", tmp_path / "dask"
    for folder in (local, remote):
        _seed(folder, instances)
    runner.run_suite("tiny", local, jobs=2, **options)
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                  dashboard_address=None) as cluster:
        runner.run_suite("tiny", remote, scheduler=cluster.scheduler_address,
                         preload=(f"{__name__}:register_fakes",), **options)
    ignore = ["setup_time", "solve_time", "total_time", "finished_at", "host"]
    a = store.read_results(local / "tiny").drop(columns=ignore)
    b = store.read_results(remote / "tiny").drop(columns=ignore)
    assert len(a) == 10
    pd.testing.assert_frame_equal(a, b)


# --- store: schema versions ---------------------------------------------------------------------
def test_other_schema_versions_are_rejected(resumed: dict[str, Any], tmp_path: Path) -> None:
    paths = resumed["paths"]
    table = pq.read_table(paths.parquet)
    metadata = dict(table.schema.metadata)
    metadata[store.PARQUET_METADATA_KEY] = b"999"
    pq.write_table(table.replace_schema_metadata(metadata), tmp_path / "old.parquet")
    with pytest.raises(SchemaVersionError, match="schema version 999"):
        store.read_results(tmp_path / "old.parquet")
    csv = pd.read_csv(paths.csv)
    csv["schema_version"] = 0
    csv.to_csv(tmp_path / "old.csv", index=False)
    with pytest.raises(SchemaVersionError, match="version 0"):
        store.read_results(tmp_path / "old.csv")
    old = store.SuitePaths(tmp_path / "suite")
    row = store.read_cell(next(paths.cells.glob("*.json")))
    store.write_json(old.cells / "x.json", {**row, "schema_version": 0})
    with pytest.raises(SchemaVersionError, match=f"delete or move {old.root}"):
        store.read_cells(old)


def test_perf_files_carry_the_one_schema_version(tmp_path: Path) -> None:
    frame = pd.DataFrame([{name: 1 for name in perf_store.PERF_COLUMNS}])
    frame["schema_version"] = store.SCHEMA_VERSION
    parquet, csv = perf_store.write_perf(frame, tmp_path)
    assert parquet.parent == store.perf_dir(tmp_path)
    pd.testing.assert_frame_equal(perf_store.read_perf(tmp_path), frame)
    table = pq.read_table(parquet)
    assert table.schema.metadata[store.PARQUET_METADATA_KEY] == str(
        store.SCHEMA_VERSION).encode()
    metadata = {**table.schema.metadata, store.PARQUET_METADATA_KEY: b"999"}
    pq.write_table(table.replace_schema_metadata(metadata), parquet)
    with pytest.raises(SchemaVersionError, match="schema version 999"):
        perf_store.read_perf(tmp_path)
    parquet.unlink()
    frame.assign(schema_version=0).to_csv(csv, index=False)
    with pytest.raises(SchemaVersionError, match="version 0"):
        perf_store.read_perf(tmp_path)


def test_rows_round_trip_with_missing_values(tmp_path: Path) -> None:
    paths = store.SuitePaths(tmp_path)
    row = store.empty_row()
    row.update({"cell_id": "a", "instance": "i", "solver": "s", "settings": "default",
                "precision": "float64", "start": "cold", "family": "lcp",
                "primal_residual": math.inf})
    store.write_cell(paths, row, {"trace": {"primal_residual": [1.0, 0.5]}})
    frame = store.consolidate(paths)
    assert list(frame.columns) == list(store.COLUMNS)
    assert frame["primal_residual"].iloc[0] == math.inf
    assert pd.isna(frame["iterations"].iloc[0]) and pd.isna(frame["admm_iteration"].iloc[0])
    assert store.read_trace(paths, frame["trace_file"].iloc[0])["trace"] == {
        "primal_residual": [1.0, 0.5]}


# --- metrics, report, compare -------------------------------------------------------------------
def _table(text: str, heading: str) -> dict[str, dict[str, str]]:
    """Rows of the Markdown table under ``heading``, keyed by their first cell."""
    block = text.split(heading, 1)[1].split("\n### ", 1)[0].split("\n## ", 1)[0]
    lines = [line for line in block.splitlines() if line.startswith("|")]
    headers = [cell.strip() for cell in lines[0].strip("|").split("|")]
    rows = {}
    for line in lines[2:]:
        cells = [cell.strip() for cell in line.strip("|").split("|")]
        rows[cells[0]] = dict(zip(headers, cells, strict=True))
    return rows


def test_report_tables_equal_metrics_recomputed_from_rows(resumed: dict[str, Any]) -> None:
    results, paths = resumed["results"], resumed["paths"]
    path = write_report("tiny", results)
    text = path.read_text()
    frame = store.read_results(paths.root)
    table = _table(text, "### c3_qp (equality variant) / default / float64 / cold")
    assert set(table) == {"fake_kkt", "fake_wrong"}
    for solver, shown in table.items():
        rows = frame[(frame["family"] == "c3_qp") & (frame["settings"] == "default")
                     & (frame["precision"] == "float64") & (frame["start"] == "cold")
                     & (frame["solver"] == solver)]
        rate = rows["success"].mean()
        times = np.where(rows["success"], rows["total_time"], rows["time_limit"])
        sgm = np.exp(np.mean(np.log(times + TIME_SHIFT))) - TIME_SHIFT
        # actual values, not floored at the tolerance (1e-300 only keeps log finite)
        primal = np.exp(np.mean(np.log(np.maximum(rows["primal_residual_relative"], 1e-300))))
        assert shown["cells"] == str(len(rows))
        assert shown["success"] == f"{100 * rate:.1f}%"
        assert shown["time sgm (ms)"] == f"{1e3 * sgm:.3g}"
        bold = "**" if primal > 1e-3 else ""
        assert shown["primal (rel.)"] == f"{bold}{primal:.1e}{bold}"
    assert table["fake_kkt"]["success"] == "100.0%"
    assert table["fake_wrong"]["success"] == "0.0%"
    assert table["fake_kkt"]["time rel."] == "1.00"
    # figures: drawn where there is data, a note where there is none
    assert (paths.root / "figures" / "profile_c3_qp.png").exists()
    assert (paths.root / "figures" / "traces_c3_qp.png").exists()
    assert (paths.root / "figures" / "conditioning_admm.png").exists()
    assert (paths.root / "figures" / "precision_accuracy.png").exists()
    assert re.search(r"MIQP vs heuristic cost gap\n\n\*No figure: no projection/mpcc", text)
    assert "shift s = 0.0001 s (0.1 ms)" in text
    assert text.count("![") == len(list((paths.root / "figures").glob("*.png")))
    again = write_report("tiny", results).read_text()
    assert again == text  # deterministic
    summary = pd.read_csv(paths.summary)
    assert len(summary) == len(aggregate(frame))


def test_report_without_trace_files_says_they_are_missing(resumed: dict[str, Any],
                                                          tmp_path: Path) -> None:
    """A checkout has the results table but not ``traces/`` (not committed): the trace
    figure says the files are missing instead of claiming no solver reported a trace."""
    copy = tmp_path / "results"
    shutil.copytree(resumed["results"], copy)
    shutil.rmtree(copy / "tiny" / "traces")
    text = write_report("tiny", copy).read_text()
    assert re.search(r"Convergence traces: c3_qp\n\n\*No figure: the trace files of its "
                     r"cells are not here \(\d+ missing", text)
    assert not (copy / "tiny" / "figures" / "traces_c3_qp.png").exists()


def test_compare_names_the_winners(resumed: dict[str, Any]) -> None:
    frame = resumed["frame"]
    rows = compare_frame(frame, "fake_kkt", "fake_wrong")
    assert {(r.family, r.start) for r in rows} == {("c3_qp", "cold"), ("c3_qp", "warm")}
    for r in rows:
        assert r.success_a == 1.0 and r.success_b == 0.0
        assert r.success_winner == "fake_kkt" and r.accuracy_winner == "fake_kkt"
        assert r.time_winner == "fake_kkt"  # nothing solved by both: failures charged
        assert r.time_ratio < 1 and math.isnan(r.time_ratio_solved)
    text = compare("tiny", "fake_kkt", "fake_wrong", resumed["results"])
    assert ("| c3_qp (equality variant) | default | float64 | cold | 3 | 100.0% | 0.0% | 0 / 0 "
            "| fake_kkt |" in text)  # unverified counts of A / B (none: c3_qp has a certificate)
    with pytest.raises(ValueError, match="no results"):
        compare_frame(frame, "fake_kkt", "nobody")


def test_commands(resumed: dict[str, Any], tmp_path: Path,
                  capsys: pytest.CaptureFixture[str]) -> None:
    results = str(resumed["results"])
    assert main(["compare", "fake_kkt", "fake_wrong", "--suite", "tiny",
                 "--results", results]) == 0
    assert "fake_kkt" in capsys.readouterr().out
    assert main(["report", "--suite", "tiny", "--results", results, "--no-figures"]) == 0
    assert main(["report", "--suite", "nothing", "--results", str(tmp_path)]) == 1
    assert capsys.readouterr().err.startswith("error: ")
    assert main(["compare", "fake_kkt", "nobody", "--suite", "tiny", "--results",
                 results]) == 2
    assert capsys.readouterr().err.startswith("error: solver 'nobody' has no results")
    assert main(["run", "--suite", "tiny", "--results", results, "--solvers",
                 "fake_kkt,fake_wrong", "--families", "c3plus_qp", "c3_qp",
                 "--repeats", "1", "--quiet", "--no-report"]) == 0
    assert "25 already stored, 0 run" in capsys.readouterr().out
    assert main(["run", "--suite", "tiny", "--results", results, "--solvers",
                 "no_such_solver", "--quiet"]) == 2
    error = capsys.readouterr().err
    assert error.startswith("error: unknown solver 'no_such_solver'")
    assert "Traceback" not in error and error.count("\n") == 1


def test_predecessors_follow_admm_sequences(instances: Path) -> None:
    from c3bench.problems.instance import load_instances

    problems = load_instances(instances)
    previous = predecessors(problems)
    by_name = {p.name: p for p in problems}
    # iterations 1 and 2 of both QP families; the projection has only iteration 0
    assert len(previous) == 4
    for after, before in previous.items():
        a, b = by_name[after], by_name[before]
        assert a.family == b.family and a.meta["state_index"] == b.meta["state_index"]
        assert a.meta["admm_iteration"] == b.meta["admm_iteration"] + 1
    assert not any(by_name[n].family in ("mpcc", "lcp", "projection") for n in previous)
