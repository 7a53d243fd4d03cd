"""Tests of the controller-sequence cells (bench/sequence.py, bench/rows.py, the planner, the
report's "Controller sequence" section and ``compare`` on sequence cells).

References: the suite's own MPC and the reference controller (:func:`solvers.c3.solve_c3`)
run independently of the cell; fake backends that spoil one QP step (a wrong ``x``; a KKT
point whose bound multiplier has the wrong sign) or hang. Fakes are registered for this module
only (the isolated child unpickles them from this module).
"""

from __future__ import annotations

import dataclasses
import math
import re
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from c3bench.bench import runner, store
from c3bench.bench import sequence as seq
from c3bench.bench.compare import compare_frame
from c3bench.bench.metrics import judge
from c3bench.bench.planning import (
    SEQUENCE_SCOPE,
    Cell,
    RunOptions,
    plan_cells,
    predecessors,
    sequence_heads,
)
from c3bench.bench.report import write_report
from c3bench.bench.rows import run_sequence_cell
from c3bench.problems.capture import SuiteSpec
from c3bench.problems.config import load_config
from c3bench.problems.instance import Problem, load_instances
from c3bench.problems.limits import cube_limits
from c3bench.problems.mpc import HorizonLayout, with_limits
from c3bench.problems.names import Block, Family, QPVariant, Variant
from c3bench.problems.scene import build_mpc, build_scene
from c3bench.problems.suites import generate_suite
from c3bench.solvers import registry
from c3bench.solvers.admm.options import ENUMERATION, C3Options
from c3bench.solvers.base import Backend, Result, Settings, WarmStart, settings_for
from c3bench.solvers.c3 import solve_c3

clarabel_missing = not registry.get("clarabel").availability()[0]
pytestmark = pytest.mark.skipif(clarabel_missing, reason="clarabel not installed")

# one state, both QP variants; QP steps at iterations 1 and 2 (the head is iteration 1)
SPEC = SuiteSpec("seqtiny", n_states=1, admm_iterations=(1, 2), projection_iterations=(0,),
                 projection_steps=(0,))
SPOILED = "i03"
"""The QP step the fakes spoil (the kernel names iteration i's QP ``c3-qp-i<ii>``)."""


# --- fakes --------------------------------------------------------------------------------------
class WrongX(Backend):
    """Clarabel, except that step 3 returns its x shifted by 0.05 (duals kept)."""

    name = "seq_wrong_x"
    families = (Family.C3PLUS_QP,)

    def solve(self, problem: Problem, settings: Settings,
              warm_start: WarmStart | None = None) -> Result:
        result = registry.get("clarabel").solve(problem, settings)
        if problem.name.endswith(SPOILED) and result.x is not None:
            result.x = result.x + 0.05
        return result


class WrongSign(Backend):
    """Clarabel, except that step 3 returns the KKT point of the QP with ``u_0[0]`` fixed at
    its upper bound: feasible and stationary, but the bound's multiplier has the wrong sign
    (the wrong active set), which only the multiplier signs and the gap reveal."""

    name = "seq_wrong_sign"
    families = (Family.C3PLUS_QP,)

    def solve(self, problem: Problem, settings: Settings,
              warm_start: WarmStart | None = None) -> Result:
        clarabel = registry.get("clarabel")
        if not problem.name.endswith(SPOILED) or problem.ub is None or problem.lb is None:
            return clarabel.solve(problem, settings)
        index = HorizonLayout.from_json(problem.meta["layout"]).index(0, Block.U).start
        lb, ub = problem.lb.copy(), problem.ub.copy()
        lb[index] = ub[index]
        result = clarabel.solve(dataclasses.replace(problem, lb=lb, ub=ub), settings)
        assert result.z_box is not None and result.z_box[index] < 0  # pushes x_i down
        return result


class Hang(Backend):
    """Hangs at step 2."""

    name = "seq_hang"
    families = (Family.C3PLUS_QP,)

    def solve(self, problem: Problem, settings: Settings,
              warm_start: WarmStart | None = None) -> Result:
        if problem.name.endswith("i02"):
            time.sleep(60)
        return registry.get("clarabel").solve(problem, settings)


FAKES: tuple[Backend, ...] = (WrongX(), WrongSign(), Hang())


@pytest.fixture(scope="module", autouse=True)
def fakes() -> Any:
    registry.backends()
    with pytest.MonkeyPatch.context() as patch:
        for backend in FAKES:
            patch.setitem(registry._BACKENDS, backend.name, backend)
        yield


@pytest.fixture(scope="module")
def instances(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("seqtiny_instances")
    generate_suite(SPEC, out, progress=False)
    return out


@pytest.fixture(scope="module")
def problems(instances: Path) -> list[Problem]:
    return load_instances(instances)


def _head(problems: list[Problem], family: str, variant: str) -> Problem:
    heads = sequence_heads(problems)
    (head,) = [p for p in problems if p.name in heads and p.family == family
               and p.meta["variant"] == variant]
    return head


def _cell(head: Problem, solver: str) -> Cell:
    return Cell(head.name, str(head.family), solver, "default", "float64", "sequence")


# --- planning -----------------------------------------------------------------------------------
def test_heads_are_the_lowest_iteration_of_each_sequence(problems: list[Problem]) -> None:
    heads = sequence_heads(problems)
    qp = [p for p in problems if p.family in (Family.C3PLUS_QP, Family.C3_QP)]
    assert len(qp) == 8  # 2 families x 2 variants x iterations 1, 2
    assert len(heads) == 4
    assert all(p.meta["admm_iteration"] == 1 for p in problems if p.name in heads)
    assert heads.isdisjoint(predecessors(problems))  # a head has no predecessor
    scoped = sequence_heads(problems, SEQUENCE_SCOPE)
    assert {(p.family, p.meta["variant"]) for p in problems if p.name in scoped} == \
        {(Family.C3PLUS_QP, QPVariant.BOUNDED)}


def test_planner_makes_one_sequence_cell_per_head_and_backend(problems: list[Problem]) -> None:
    solvers = ["clarabel", "daqp", "equilibrated_kkt", "seq_wrong_x"]
    solvers = [s for s in solvers if registry.get(s).availability()[0]]
    heads = sequence_heads(problems, None)
    plan = plan_cells(problems, solvers, ["default"], ["float64", "float32"], ["sequence"],
                      predecessors(problems), heads)
    expected = set()
    for problem in problems:
        if problem.name not in heads:
            continue
        for name in solvers:
            backend = registry.get(name)
            if backend.accepts(problem)[0]:
                expected |= {(problem.name, name, p) for p in backend.precisions}
    got = [(c.instance, c.solver, c.precision) for c in plan.cells]
    assert len(got) == len(set(got)) == len(expected) > 4
    assert set(got) == expected
    assert all(c.start == "sequence" for c in plan.cells)
    default = plan_cells(problems, solvers, ["default"], ["float64"], ["sequence"],
                         predecessors(problems))
    assert {c.instance for c in default.cells} == sequence_heads(problems, SEQUENCE_SCOPE)


# --- the controller's data ------------------------------------------------------------------------
def test_controller_data_recovers_the_suites_mpc(problems: list[Problem]) -> None:
    cfg = load_config()
    scene = build_scene(l=SPEC.model_l, config=cfg)
    mpc = with_limits(build_mpc(scene, cfg.mpc), cube_limits(scene))
    for family, variant in ((Family.C3PLUS_QP, QPVariant.BOUNDED),
                            (Family.C3_QP, QPVariant.EQUALITY)):
        head = _head(problems, family, variant)
        data = seq.controller_data(head)
        for name in ("Q", "R", "Q_f"):
            np.testing.assert_allclose(getattr(data.mpc, name), getattr(mpc, name),
                                       rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(data.mpc.x_target, mpc.x_target, atol=1e-9)
        assert data.mpc.horizon == mpc.horizon and data.mpc.dt == mpc.dt
        assert (data.mpc.limits == mpc.limits) == (variant == QPVariant.BOUNDED)
        assert data.variant == (Variant.C3PLUS if family == Family.C3PLUS_QP else Variant.C3)


def test_a_tampered_instance_is_declined(problems: list[Problem]) -> None:
    head = _head(problems, Family.C3PLUS_QP, QPVariant.BOUNDED)
    q = head.q.copy()
    q[0] += 1.0  # no longer the QP step of any MPC at this delta, w
    with pytest.raises(seq.SequenceUnsupported, match="mismatch in q"):
        seq.controller_data(dataclasses.replace(head, q=q))
    row = run_sequence_cell(_cell(head, "clarabel"), dataclasses.replace(head, q=q),
                            RunOptions(repeats=1)).row
    assert row["failure"] == "unsupported" and not row["success"]


# --- one cell -----------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def clarabel_cell(problems: list[Problem], tmp_path_factory: pytest.TempPathFactory
                  ) -> dict[str, Any]:
    head = _head(problems, Family.C3PLUS_QP, QPVariant.BOUNDED)
    outcome = run_sequence_cell(_cell(head, "clarabel"), head, RunOptions(repeats=2))
    return {"head": head, "row": outcome.row, "trace": outcome.trace}


def test_total_time_is_the_sum_of_the_steps(clarabel_cell: dict[str, Any]) -> None:
    row, trace = clarabel_cell["row"], clarabel_cell["trace"]
    steps = trace["trace"]
    assert len(steps["total_time"]) == seq.SEQUENCE_STEPS
    assert row["success"] and row["found"] and row["verdict"] == ""
    assert row["total_time"] == pytest.approx(sum(steps["total_time"]), rel=1e-12)
    assert row["setup_time"] == pytest.approx(sum(steps["setup_time"]), rel=1e-12)
    assert row["solve_time"] == pytest.approx(sum(steps["solve_time"]), rel=1e-12)
    assert row["total_time"] == pytest.approx(row["setup_time"] + row["solve_time"],
                                              rel=1e-12)
    for setup, solve, total in zip(steps["setup_time"], steps["solve_time"],
                                   steps["total_time"], strict=True):
        assert setup > 0 and solve > 0 and total == pytest.approx(setup + solve, rel=1e-12)
    # the rho schedule of the capture: 50 * 2^i on lambda, one QP per iteration
    assert steps["rho_lam"] == [50.0 * 2.0**i for i in range(seq.SEQUENCE_STEPS)]
    assert trace["diagnostics"]["admm_time"] > 0
    assert row["time_limit"] == seq.SEQUENCE_STEPS * RunOptions().time_limit
    assert row["repeats"] == 2 and row["start"] == "sequence"
    assert judge(row) == (True, "")
    for column in seq.STEP_COLUMNS:  # the worst step's figure
        assert row[column] == max(steps[column])


def test_plan_equals_the_reference_controllers(clarabel_cell: dict[str, Any]) -> None:
    head, row, trace = clarabel_cell["head"], clarabel_cell["row"], clarabel_cell["trace"]
    cfg = load_config()
    scene = build_scene(l=SPEC.model_l, config=cfg)
    mpc = with_limits(build_mpc(scene, cfg.mpc), cube_limits(scene))  # not the recovered one
    options = C3Options(variant=Variant.C3PLUS, qp_backend="clarabel",
                        qp_settings=settings_for("default"), projection_backend=ENUMERATION,
                        admm_iterations=10)
    solution = solve_c3(head.lcs, mpc, head.data["x0"], options)
    assert solution.ok and solution.u_raw is not None
    np.testing.assert_allclose(trace["plan_first_input"], solution.u_raw, rtol=0, atol=1e-6)
    # the cell's own reference (clarabel at high accuracy) agrees closely
    assert row["verified"] and row["reference_solver"] == "clarabel"
    assert trace["diagnostics"]["plan_error"] < 1e-4
    assert trace["diagnostics"]["input_error"] < 1e-3


@pytest.mark.parametrize(("solver", "figure"), [("seq_wrong_x", "primal_residual_relative"),
                                                ("seq_wrong_sign", "duality_gap_relative")])
def test_one_spoiled_step_fails_the_cell(problems: list[Problem], solver: str,
                                         figure: str) -> None:
    head = _head(problems, Family.C3PLUS_QP, QPVariant.BOUNDED)
    outcome = run_sequence_cell(_cell(head, solver), head, RunOptions(repeats=1))
    row, steps = outcome.row, outcome.trace["trace"]
    assert row["found"] and not row["success"]
    assert figure in row["verdict"] and "steps 3)" in row["status"]
    assert steps["success"] == [float(i != 3) for i in range(seq.SEQUENCE_STEPS)]
    assert steps[figure][3] > row["tolerance"]
    assert max(v for i, v in enumerate(steps[figure]) if i != 3) <= row["tolerance"]


def test_a_hanging_step_times_out_the_run(problems: list[Problem]) -> None:
    head = _head(problems, Family.C3PLUS_QP, QPVariant.BOUNDED)
    start = time.perf_counter()
    row = run_sequence_cell(_cell(head, "seq_hang"), head,
                            RunOptions(repeats=1, time_limit=0.2)).row
    assert time.perf_counter() - start < 30
    assert row["failure"] == "timeout" and not row["success"]
    assert row["time_limit"] == pytest.approx(2.0) and "2 s" in row["status"]


# --- a run, the report and compare ----------------------------------------------------------------
@pytest.fixture(scope="module")
def run(instances: Path, tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    results = tmp_path_factory.mktemp("seq_results")
    target = store.SuitePaths.of(results, "seqtiny").instances
    target.parent.mkdir(parents=True)
    target.symlink_to(instances)
    solvers = [s for s in ("clarabel", "daqp") if registry.get(s).availability()[0]]
    summary = runner.run_suite("seqtiny", results, solvers=solvers, families=("c3plus_qp",),
                               starts=("cold", "sequence"), precisions=("float64",),
                               repeats=1, progress=False)
    return {"results": results, "summary": summary, "solvers": solvers,
            "frame": store.read_results(store.SuitePaths.of(results, "seqtiny").root)}


def test_run_stores_sequence_cells(run: dict[str, Any]) -> None:
    frame, solvers = run["frame"], run["solvers"]
    cells = frame[frame["start"] == "sequence"]
    assert sorted(cells["solver"]) == sorted(solvers)  # one head in scope, one cell each
    assert cells["instance"].str.startswith("c3plus_qp-bounded").all()
    assert cells["success"].all() and cells["verified"].all()
    assert run["summary"].missing == 0


def test_report_has_the_controller_sequence_table(run: dict[str, Any]) -> None:
    frame = run["frame"]
    text = write_report("seqtiny", run["results"], figures=False).read_text()
    section = text[text.index("## Controller sequence"):text.index("## Why slow")]
    heading = "### c3plus_qp (bounded variant) / default / float64 / sequence"
    assert heading in section and text.count(heading) == 1  # not among the per-QP tables
    lines = [line for line in section.splitlines() if line.startswith("| ")]
    header = [c.strip() for c in lines[0].strip("|").split("|")]
    table = {c[0]: dict(zip(header, c, strict=True)) for c in
             ([x.strip() for x in line.strip("|").split("|")] for line in lines[1:])}
    assert set(table) == set(run["solvers"])
    fastest = None
    for solver, shown in table.items():
        row = frame[(frame["start"] == "sequence") & (frame["solver"] == solver)].iloc[0]
        assert shown["total median (ms)"] == f"{1e3 * row['total_time']:.3g}"
        assert shown["success"] == "100.0%"
        if shown["rel."] == "1.00":
            fastest = solver
    assert fastest == next(iter(table))  # fastest first
    assert re.search(r"\| \d\.\de-\d\d \|", section)  # a plan error is shown


def test_compare_works_on_sequence_cells(run: dict[str, Any]) -> None:
    if len(run["solvers"]) < 2:
        pytest.skip("needs two backends")
    rows = compare_frame(run["frame"], *run["solvers"])
    (sequence,) = [r for r in rows if r.start == "sequence"]
    assert sequence.cells == 1 and sequence.success_a == sequence.success_b == 1.0
    assert math.isfinite(sequence.time_ratio_solved)
