"""References are accepted only when cross-checked, and rows without one are marked.

A reference whose cross-check disagrees (or fails, or is missing) gives no ``f*``; a check
never stands in for a failed reference. An ``mpcc`` / ``projection`` row without a verified
``f*`` is never a success: it is ``verified = False``, its verdict says "feasible, optimality
not verified", and the aggregates and the report count it apart as *unverified*.

The fake backends solve ``min 1/2 |x|^2 - x_0`` s.t. ``x_0 + x_1 = 1`` (optimum ``(1, 0)``,
``f* = -0.5``) and return a point that is exactly feasible: the optimum, or another feasible
point whose cost differs; :func:`bench.reference.compute_reference` runs them through the
registry (in this process) and they are registered for the test only.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from synthetic_results import row as synthetic_row

from c3bench.bench import reference as reference_module
from c3bench.bench import store
from c3bench.bench.accuracy import claimed_but_wrong
from c3bench.bench.metrics import UNVERIFIED_VERDICT, aggregate, judge
from c3bench.bench.reference import (
    Reference,
    ReferencePlan,
    compute_reference,
    optimality_certificate,
    save_references,
)
from c3bench.bench.report import write_report
from c3bench.bench.rows import fill_row
from c3bench.problems.instance import Problem
from c3bench.problems.names import Failure, Family
from c3bench.solvers import registry
from c3bench.solvers.base import Backend, Result, Settings, WarmStart


def _qp() -> Problem:
    return Problem(name="qp-ref", family=Family.QP, P=np.eye(2), q=np.array([-1.0, 0.0]),
                   A=np.array([[1.0, 1.0]]), b=np.array([1.0]))


class Point(Backend):
    """Returns a fixed feasible point (``found``), or claims nothing (``x=None``)."""

    families = (Family.QP, Family.MPCC)

    def __init__(self, name: str, x: list[float] | None) -> None:
        self.name, self.x = name, x

    def solve(self, problem: Problem, settings: Settings,
              warm_start: WarmStart | None = None) -> Result:
        if self.x is None:
            return Result.failed(self.name, problem.name, Failure.ERROR, "planted failure")
        return Result(self.name, problem.name, True, "solved", x=np.array(self.x),
                      y=np.array([0.0]))


FAKES = (Point("ref_exact", [1.0, 0.0]), Point("ref_exact_too", [1.0, 0.0]),
         Point("ref_off", [0.5, 0.5]), Point("ref_fails", None))


@pytest.fixture(autouse=True)
def fakes(monkeypatch: pytest.MonkeyPatch) -> None:
    """The fakes registered for this test; references solve in this process (the isolated
    child is tested elsewhere and costs seconds per launch on a loaded machine)."""
    registry.backends()
    for fake in FAKES:
        monkeypatch.setitem(registry._BACKENDS, fake.name, fake)
    monkeypatch.setattr(reference_module, "solve_isolated", registry.solve)


def _reference(solver: str, check: str | None) -> Reference:
    return compute_reference(_qp(), "digest", ReferencePlan(solver, check, "default"),
                             time_limit=20.0)


@pytest.mark.timeout(120)
def test_a_reference_whose_cross_check_disagrees_is_not_accepted() -> None:
    agreed = _reference("ref_exact", "ref_exact_too")
    assert agreed.available and agreed.reason == "" and agreed.spread == 0.0
    assert agreed.value().objective == pytest.approx(-0.5)

    disagreed = _reference("ref_exact", "ref_off")  # f = -0.25 against f* = -0.5
    assert not disagreed.available
    assert "disagree" in disagreed.reason and "not verified" in disagreed.reason
    assert disagreed.spread == pytest.approx(0.25)
    assert disagreed.value().solver == "" and math.isnan(disagreed.value().objective)
    assert disagreed.warm_start() is not None  # its point still warm-starts the next iterate

    failed_check = _reference("ref_exact", "ref_fails")
    assert not failed_check.available and "cross-check ref_fails failed" in failed_check.reason

    unchecked = _reference("ref_exact", None)
    assert not unchecked.available and "no cross-check" in unchecked.reason

    no_fallback = _reference("ref_fails", "ref_exact")  # the check never stands in
    assert not no_fallback.available and math.isnan(no_fallback.objective)
    assert no_fallback.warm_start() is None


def _mpcc() -> Problem:
    """``min 1/2 |x - (1, 1)|^2`` s.t. ``0 <= x_0 perp x_1 >= 0``: optimum ``(1, 0)`` or
    ``(0, 1)``, ``f* = 0.5``."""
    return Problem(name="mpcc-s000", family=Family.MPCC, P=np.eye(2),
                   q=np.array([-1.0, -1.0]), lb=np.zeros(2), ub=np.full(2, np.inf),
                   complementarity=np.array([[0, 1]]), objective_offset=1.0)


def _mpcc_row(reference: Reference | None) -> dict[str, object]:
    problem = _mpcc()
    row = store.empty_row()
    row.update({"cell_id": "mpcc-s000--solver", "instance": problem.name, "family": "mpcc",
                "solver": "solver", "settings": "default", "tolerance": 1e-3,
                "time_limit": 10.0, "precision": "float64", "start": "cold"})
    if reference is not None and reference.available:
        value = reference.value()
        row.update({"reference_solver": value.solver, "reference_objective": value.objective,
                    "reference_spread": value.spread})
    result = Result("solver", problem.name, True, "solved", x=np.array([1.0, 0.0]))
    return fill_row(row, problem, result)


def test_an_mpcc_row_without_a_verified_reference_is_not_a_success(tmp_path: Path) -> None:
    verified = Reference("mpcc-s000", "mpcc", "digest", "scip", "bonmin", "high_accuracy",
                         available=True, solver="scip", objective=0.5, spread=0.0)
    good = _mpcc_row(verified)
    assert good["success"] and good["verified"] and good["cost_error"] == 0.0

    bare = _mpcc_row(None)  # the same feasible, optimal point: optimality not verified
    assert bare["primal_residual_relative"] == 0.0 and bare["complementarity_violation"] == 0
    assert not bare["success"] and not bare["verified"]
    assert bare["verdict"] == UNVERIFIED_VERDICT
    worse = {**bare, "complementarity_violation": 0.5}  # infeasible: a plain failure
    assert not judge(worse)[0] and judge(worse)[1] != UNVERIFIED_VERDICT

    frame = store.rows_to_frame([bare, {**good, "cell_id": "mpcc-s001--solver",
                                        "instance": "mpcc-s001"}])
    summary = aggregate(frame)
    assert (summary["successes"].tolist(), summary["unverified"].tolist()) == ([1], [1])
    assert claimed_but_wrong(frame) == []  # unverified is not wrong

    # the report counts it apart: the family table and the overview
    paths = store.SuitePaths.of(tmp_path, "synthetic")
    paths.root.mkdir(parents=True)
    store.write_frame(paths, frame)
    save_references(paths.references, {"mpcc-s001": verified})
    text = write_report("synthetic", tmp_path, figures=False).read_text()
    assert "| unverified |" in text
    assert "50.0% (+1 unverified)" in text


def test_a_convex_row_without_a_reference_is_judged_on_its_certificate() -> None:
    row = synthetic_row(family="c3_qp")  # residuals, duals and gap at 1e-12, no reference
    assert row["success"] and row["verdict"] == ""


def test_optimality_certificate_needs_optimal_exact_model_and_closed_gap() -> None:
    def result(status: str, gap: float, big_m: float) -> Result:
        return Result("scip", "p", True, status,
                      diagnostics={"mip_gap": gap, "big_m": big_m, "dual_bound": 1.0})

    assert "optimal, gap" in optimality_certificate(result("optimal", 0.0, 0.0))
    assert optimality_certificate(result("gaplimit", 1e-8, 0.0))
    assert not optimality_certificate(result("optimal", 1e-3, 0.0))  # gap not closed
    assert not optimality_certificate(result("optimal", 0.0, 1e4))  # big-M: M may cut f*
    assert not optimality_certificate(result("timelimit", 0.0, 0.0))
    assert not optimality_certificate(Result("clarabel", "p", True, "solved"))


def test_a_certified_global_solve_is_a_verified_mpcc_reference(
        small_mpccs: dict[str, Problem]) -> None:
    """SCIP's proof (SOS1 model, gap closed) verifies f* without Bonmin, and f* is the optimum
    found by enumerating every contact mode."""
    miqp = pytest.importorskip("c3bench.solvers.modes")
    ok, why = registry.get("scip").availability()
    if not ok:
        pytest.skip(why)
    problem = small_mpccs["h2-0"]
    ref = compute_reference(problem, "digest", reference_module.plan_for(problem.family))
    assert ref.available and ref.solver == "scip" and ref.reason == ""
    assert ref.check_status.startswith("certificate: scip optimal")
    _, optimum = miqp.enumerate_modes(problem)
    assert ref.objective == pytest.approx(optimum, rel=1e-6)
