"""One cell's row: solve it in an isolated child and fill the results schema.

Both executors (the local pool and Dask, :mod:`bench.executors`) call exactly
:func:`run_cell`, and :func:`reference_task` for references. Timing follows docs/metrics.md
through :func:`c3bench.solvers.isolation.solve_isolated`: an untimed warm-up, then ``repeats``
timed solves (median), BLAS pinned to one thread, setup and solve apart
(:mod:`c3bench.solvers.timing`; ``total_time`` is their sum), the time limit
enforced by killing the child. A child that cannot be started
(:class:`~c3bench.solvers.isolation.IsolationFailed`) is raised, not stored. Columns are those
of :data:`bench.store.SCHEMA`.

A ``sequence`` cell runs :func:`run_sequence_cell` instead (:mod:`bench.sequence`: the ADMM
run of the instance's state with the cell's backend as the QP step); its row sums the QP
steps' times, holds the worst step's residuals and ``time_limit`` of one run
(``SEQUENCE_STEPS`` times the per-QP limit); its trace holds every step and the diagnostics
``admm_time``, ``projection_time``, ``plan_error``, ``input_error``.
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
from c3bench.bench.sequence import (
    REFERENCE_BACKEND,
    SEQUENCE_STEPS,
    STEP_COLUMNS,
    IsolatedSequence,
    SequenceJob,
    SequenceOutcome,
    SequenceReference,
    SequenceUnsupported,
    controller_data,
    run_isolated,
)
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


def invalid_times(setup_time: float, solve_time: float) -> str:
    """Why the laps a backend reported cannot be times (``""`` when they can): each must be
    a finite number ``>= 0`` (the timing contract, :mod:`c3bench.solvers.timing`). A row with
    such laps is the backend's failure, not a fast or free success."""
    laps = {"setup_time": setup_time, "solve_time": solve_time}
    bad = [f"{name}={value!r}" for name, value in laps.items()
           if not store.valid_time(value)]
    return f"the backend reported an invalid time: {', '.join(bad)}" if bad else ""


def fill_row(row: dict[str, Any], problem: Problem, result: Result) -> dict[str, Any]:
    """Put a :class:`Result` and its residuals (the one residual module) into ``row``."""
    row.update({
        "found": bool(result.found), "failure": str(result.failure or Failure.NONE),
        "status": str(result.status), "setup_time": _finite_or_nan(result.setup_time),
        "solve_time": _finite_or_nan(result.solve_time),
        "total_time": _finite_or_nan(result.total_time),
        "iterations": None if result.iterations is None else int(result.iterations),
    })
    invalid = invalid_times(row["setup_time"], row["solve_time"])
    if result.found and invalid:
        row.update({"found": False, "failure": str(Failure.ERROR),
                    "status": f"{invalid} (the answer is not judged)"})
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


def run_sequence_cell(cell: Cell, problem: Problem, options: RunOptions, version: str = "",
                      reference: ReferenceValue | None = None,
                      warm_start: WarmStart | None = None, digest: str = "") -> CellOutcome:
    """Run one ``sequence`` cell in an isolated child and build its row (same signature and
    faults as :func:`run_cell`; ``reference`` and ``warm_start`` are not used: the cell's
    reference is its own reference run, :mod:`bench.sequence`)."""
    registry.import_plugins(options.preload)
    limit = SEQUENCE_STEPS * options.time_limit
    try:
        controller_data(problem)  # declines an instance it cannot run, before any child
        settings = settings_for(cell.settings, time_limit=options.time_limit,
                                precision=cell.precision)
        backend = registry.get(cell.solver)
        checker = registry.get(REFERENCE_BACKEND) if REFERENCE_BACKEND in \
            registry.backends() else None
        if checker is not None and not checker.availability()[0]:
            checker = None
        job = SequenceJob(backend, problem, settings, options.repeats, checker,
                          options.reference_time_limit)
        isolated = run_isolated(job)
        row = base_row(cell, problem, options, version, None, digest)
        row.update({"time_limit": limit, "admm_iteration": None, "rho_lam": math.nan})
        return sequence_row(row, isolated)
    except BaseException as error:
        if isinstance(error, KeyboardInterrupt | SystemExit | IsolationFailed):
            raise
        failure = Failure.UNSUPPORTED if isinstance(error, SequenceUnsupported | KeyError) \
            else Failure.ERROR
        status = f"{type(error).__name__}: {error}\n{traceback.format_exc(limit=3)}"
        row = failure_row(cell, problem, options, version, None, failure, status.strip(),
                          digest)
        row.update({"time_limit": limit, "admm_iteration": None, "rho_lam": math.nan})
        return CellOutcome(row)


def _worst(values: list[float]) -> float:
    """The largest value, NaN when there is none or one is NaN (then it is unavailable)."""
    array = np.asarray(values, dtype=float)
    return float(np.max(array)) if array.size else math.nan


def sequence_row(row: dict[str, Any], isolated: IsolatedSequence) -> CellOutcome:
    """Fill ``row`` (from :func:`base_row`) with a sequence cell's outcome (module docstring
    of :mod:`bench.sequence`): success by :func:`bench.metrics.judge` on the worst step."""
    outcome = isolated.outcome
    if outcome is None:
        row.update({"found": False, "failure": str(isolated.failure),
                    "status": isolated.status})
        row["success"], row["verdict"] = judge(row)
        return CellOutcome(row)
    steps = outcome.steps
    complete = outcome.ok and len(steps) == SEQUENCE_STEPS
    unfound = [i for i, step in enumerate(steps) if not step.found]
    failing = [i for i, step in enumerate(steps) if not step.success]
    failure = "" if complete and not unfound else next(
        (steps[i].failure for i in unfound if steps[i].failure), str(Failure.ERROR)
        if not complete else "")
    status = f"{outcome.status}; {len(steps) - len(failing)}/{SEQUENCE_STEPS} QP steps " \
             f"certified" + (f" (not: steps {', '.join(map(str, failing))})" if failing else "")
    iterations = [step.iterations for step in steps]
    row.update({
        "found": complete and not unfound, "failure": failure, "status": status,
        "setup_time": sum(step.setup_time for step in steps),
        "solve_time": sum(step.solve_time for step in steps),
        "total_time": sum(step.total_time for step in steps),
        "repeats": outcome.timed_runs,
        "iterations": sum(i for i in iterations if i is not None)
        if steps and None not in iterations else None,
        "objective": steps[-1].objective if steps else math.nan,
        **{name: _worst([step.figures[name] for step in steps]) for name in STEP_COLUMNS},
    })
    errors = plan_errors(outcome, isolated.reference) if complete else (math.nan, math.nan)
    row["verified"] = bool(isolated.reference.verified)
    if row["verified"]:
        row["reference_solver"] = REFERENCE_BACKEND
    row["success"], row["verdict"] = judge(row)
    return CellOutcome(row, sequence_trace(outcome, isolated.reference, errors))


def plan_errors(outcome: SequenceOutcome, reference: SequenceReference) -> tuple[float, float]:
    """``(plan_error, input_error)`` against the reference run (NaN when it is not verified):
    ``||delta - delta_ref||_inf / max(1, ||delta_ref||_inf)`` and ``||u0 - u0_ref||_inf``."""
    if not reference.verified or reference.delta is None:
        return math.nan, math.nan
    scale = max(1.0, float(np.max(np.abs(reference.delta))))
    plan = float(np.max(np.abs(outcome.delta - reference.delta))) / scale
    if outcome.u_raw is None or reference.u_raw is None:
        return plan, math.nan
    return plan, float(np.max(np.abs(outcome.u_raw - reference.u_raw)))


def sequence_trace(outcome: SequenceOutcome, reference: SequenceReference,
                   errors: tuple[float, float]) -> dict[str, Any]:
    """The trace payload of a sequence cell: one entry per QP step, and the run's figures."""
    steps = outcome.steps
    series: dict[str, list[float]] = {
        "rho_lam": [step.rho_lam for step in steps],
        "setup_time": [step.setup_time for step in steps],
        "solve_time": [step.solve_time for step in steps],
        "total_time": [step.total_time for step in steps],
        "found": [float(step.found) for step in steps],
        "success": [float(step.success) for step in steps],
        "objective": [step.objective for step in steps],
        **{name: [step.figures[name] for step in steps] for name in STEP_COLUMNS},
    }
    return {"trace": {k: [_finite_or_nan(v) for v in values] for k, values in series.items()},
            "diagnostics": {"admm_time": outcome.admm_time,
                            "projection_time": outcome.projection_time,
                            "qp_steps": float(len(steps)), "plan_error": errors[0],
                            "input_error": errors[1],
                            "reference_verified": float(reference.verified)},
            "reference_status": reference.status,
            "step_verdicts": [step.verdict for step in steps],
            "plan_first_input": [] if outcome.u_raw is None
            else [float(v) for v in np.ravel(outcome.u_raw)]}


def reference_task(problem: Problem, digest: str, plan: ReferencePlan | None,
                   time_limit: float, preload: tuple[str, ...]) -> Reference:
    """Worker entry point for references (the plan travels with the task)."""
    return compute_reference(problem, digest, plan, time_limit, preload)
