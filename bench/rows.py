"""One cell's row: solve it in an isolated child and fill the results schema.

Both executors (the local pool and Dask, :mod:`bench.executors`) call exactly
:func:`run_cell`, and :func:`reference_task` for references. Timing follows docs/metrics.md
through :func:`c3bench.solvers.isolation.solve_isolated`: an untimed warm-up, then ``repeats``
timed solves (median), BLAS pinned to one thread, setup and solve apart
(:mod:`c3bench.solvers.timing`; ``total_time`` is their sum), the time limit
enforced by killing the child. A child that cannot be started
(:class:`~c3bench.solvers.isolation.IsolationFailed`) is raised, not stored. Columns are those
of :data:`bench.store.SCHEMA`.
"""

from __future__ import annotations

import math
import traceback
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from c3bench.bench import store
from c3bench.bench.machine import hostname, utc_now
from c3bench.bench.metrics import has_reference, judge
from c3bench.bench.planning import Cell, RunOptions
from c3bench.bench.reference import Reference, ReferencePlan, ReferenceValue, compute_reference
from c3bench.problems.instance import Problem
from c3bench.problems.names import PROFILE_TOLERANCE, Failure, Profile, Start
from c3bench.solvers import registry
from c3bench.solvers.base import Result, WarmStart, settings_for
from c3bench.solvers.isolation import IsolationFailed, solve_isolated
from c3bench.solvers.residuals import cost_error, residuals


@dataclass
class CellOutcome:
    """What a worker returns: the row and the trace payload (``{}`` when none)."""

    row: dict[str, Any]
    trace: dict[str, Any] = field(default_factory=dict)


def base_row(cell: Cell, problem: Problem, options: RunOptions, version: str,
             reference: ReferenceValue | None, digest: str = "") -> dict[str, Any]:
    """Identifier columns of a cell's row (everything else at its 'unknown' value)."""
    row = store.empty_row()
    rho = problem.meta.get("rho")
    iteration = problem.meta.get("admm_iteration")
    state = problem.meta.get("state_index")
    row.update({
        "cell_id": cell.id, "suite": options.suite, "instance": cell.instance,
        "instance_hash": digest,
        "family": cell.family, "solver": cell.solver, "solver_version": version,
        "settings": cell.settings, "tolerance": PROFILE_TOLERANCE[Profile(cell.settings)],
        "time_limit": options.time_limit, "precision": cell.precision, "start": cell.start,
        "repeats": options.repeats,
        "state_index": None if state is None else int(state),
        "admm_iteration": None if iteration is None else int(iteration),
        "rho_lam": float(rho["lam"]) if isinstance(rho, dict) and "lam" in rho else math.nan,
        "n_variables": problem.n,
        "n_constraints": problem.n_eq + problem.n_ineq + problem.n_bounded,
        "host": hostname(), "finished_at": utc_now(),
    })
    if reference is not None and reference.solver:
        row.update({"reference_solver": reference.solver,
                    "reference_objective": reference.objective,
                    "reference_spread": reference.spread})
    return row


def failure_row(cell: Cell, problem: Problem, options: RunOptions, version: str,
                reference: ReferenceValue | None, failure: str, status: str,
                digest: str = "") -> dict[str, Any]:
    """A failed row for a cell whose worker died, overran or raised."""
    row = base_row(cell, problem, options, version, reference, digest)
    row.update({"found": False, "failure": str(failure), "status": status})
    row["verified"] = has_reference(row)
    row["success"], row["verdict"] = judge(row)
    return row


def _finite_or_nan(value: Any) -> float:
    """``float(value)``, NaN when it is not a number."""
    try:
        return float(value)
    except (TypeError, ValueError):
        return math.nan


def fill_row(row: dict[str, Any], problem: Problem, result: Result) -> dict[str, Any]:
    """Put a :class:`Result` and its residuals (the one residual module) into ``row``."""
    row.update({
        "found": bool(result.found), "failure": str(result.failure or Failure.NONE),
        "status": str(result.status), "setup_time": _finite_or_nan(result.setup_time),
        "solve_time": _finite_or_nan(result.solve_time),
        "total_time": _finite_or_nan(result.total_time),
        "iterations": None if result.iterations is None else int(result.iterations),
    })
    x = None if result.x is None else np.asarray(result.x, dtype=float)
    if x is not None and x.shape == (problem.n,) and np.all(np.isfinite(x)):
        figures = residuals(problem, x, result.y, result.z, result.z_box)
        objective = problem.objective(x)
        row.update({"objective": objective, "primal_residual": figures.primal,
                    "dual_residual": figures.dual, "duality_gap": figures.gap,
                    "primal_residual_relative": figures.primal_relative,
                    "dual_residual_relative": figures.dual_relative,
                    "duality_gap_relative": figures.gap_relative,
                    "complementarity_violation": figures.complementarity})
        if row["reference_solver"] and math.isfinite(row["reference_objective"]):
            row["cost_error"] = cost_error(objective, row["reference_objective"])
    for name in store.DIAGNOSTIC_COLUMNS:
        if name in result.diagnostics:
            row[name] = _finite_or_nan(result.diagnostics[name])
    row["verified"] = has_reference(row)
    row["success"], row["verdict"] = judge(row)
    return row


def run_cell(cell: Cell, problem: Problem, options: RunOptions, version: str = "",
             reference: ReferenceValue | None = None,
             warm_start: WarmStart | None = None, digest: str = "") -> CellOutcome:
    """Solve one cell in an isolated child and build its row. Raises only on an interrupt or
    :class:`~c3bench.solvers.isolation.IsolationFailed` (no row for an infrastructure fault).

    Both executors (local pool, Dask) call exactly this function.
    """
    registry.import_plugins(options.preload)  # a plugin missing on this worker: no row
    try:
        settings = settings_for(cell.settings, time_limit=options.time_limit,
                                precision=cell.precision)
        result = solve_isolated(cell.solver, problem, settings,
                                warm_start=warm_start if cell.start == Start.WARM else None,
                                repeats=options.repeats, warmup=True)
        row = fill_row(base_row(cell, problem, options, version, reference, digest), problem,
                       result)
        trace: dict[str, Any] = {}
        if result.trace or result.diagnostics:
            trace = {"trace": {k: [float(v) for v in np.ravel(values)]
                               for k, values in result.trace.items()},
                     "diagnostics": {k: _finite_or_nan(v)
                                     for k, v in result.diagnostics.items()}}
        return CellOutcome(row, trace)
    except BaseException as error:
        if isinstance(error, KeyboardInterrupt | SystemExit | IsolationFailed):
            raise  # an interrupt, or no solver process: not a result of the solve
        status = f"{type(error).__name__}: {error}\n{traceback.format_exc(limit=3)}"
        return CellOutcome(failure_row(cell, problem, options, version, reference,
                                       Failure.ERROR, status.strip(), digest))


def reference_task(problem: Problem, digest: str, plan: ReferencePlan | None,
                   time_limit: float, preload: tuple[str, ...]) -> Reference:
    """Worker entry point for references (the plan travels with the task)."""
    return compute_reference(problem, digest, plan, time_limit, preload)
