"""The controller-sequence cell: one real ADMM run with a QP backend as its QP step.

A ``sequence`` cell (:class:`c3bench.problems.names.Start`) answers "which QP backend makes my
C3 / C3+ control step fastest": its instance is the *head* of a state's ADMM sequence
(:func:`bench.planning.sequence_heads`), from which the cell recovers the controller's data at
that state (:func:`controller_data`) and runs the reference controller's consensus ADMM
(:func:`c3bench.solvers.c3.solve_c3`, the stacked kernel) from a cold start with the cell's
backend as the QP step: :data:`SEQUENCE_STEPS` iterations of the reference study's geometric
rho schedule (``rho_lam = rho_eta = 50 * 2^i``, as the suites' capture), so ``P`` changes at
every step and each QP step is a fresh solve. C3 (``c3_qp`` heads) projects by enumerating the
contact modes (``projection_backend="enumeration"``), so no MIQP solver dominates the time.

Timing (the contract of :mod:`c3bench.solvers.timing`): each QP step reports its own setup
and solve laps (the backend's ``Result``, exactly what a ``cold`` cell of that QP would
time); per step the median over the ``repeats`` timed runs (after one untimed run) is taken,
and the row's

    setup_time = sum_i setup_i,   solve_time = sum_i solve_i,
    total_time = sum_i (setup_i + solve_i)

is what the controller pays for its QP steps at one control step. The run's wall time
(building the QPs, projections, dual updates and residuals included; median over the runs)
is the trace diagnostic ``admm_time``.

Verdict: success needs every QP step found by the backend **and** each step's solution
certified against that step's QP by the residual checks of :func:`bench.metrics.judge` (relative
primal and dual residuals, multiplier signs included, and duality gap within the profile's
tolerance, via :func:`c3bench.solvers.residuals.residuals`); the row's residual columns are the
worst over the steps, so :func:`~bench.metrics.judge` of the row agrees. Accuracy: the same run
with :data:`REFERENCE_BACKEND` at ``high_accuracy`` (inside the cell, untimed) is the reference
plan; the diagnostics ``plan_error`` ``= ||delta - delta_ref||_inf / max(1, ||delta_ref||_inf)``
(the final projected trajectory) and ``input_error`` ``= ||u0 - u0_ref||_inf`` (the first input
before clipping, N). A reference run that fails or whose own steps are not certified at
:data:`REFERENCE_TOLERANCE` leaves the row ``verified = False`` and both errors NaN.

The cell runs in an isolated child process (:mod:`c3bench.solvers.child_process`, as every
solve of the benchmark) killed when a run overruns ``SEQUENCE_STEPS * time_limit`` seconds
(the untimed run), or ``repeats`` times that (the timed runs); each QP step gets the cell's
profile, precision and ``time_limit``.

References
----------
W. Aydinoglu and M. Posa, "Real-time multi-contact model predictive control via ADMM", ICRA
2022 (C3); Bui et al., 2025 (C3+); S. Boyd et al., "Distributed optimization and statistical
learning via the alternating direction method of multipliers", 2011 (consensus ADMM).
"""

from __future__ import annotations

import math
import os
import statistics
import time
from dataclasses import dataclass, field
from multiprocessing.connection import Connection
from multiprocessing.reduction import ForkingPickler
from typing import Any

import numpy as np

from c3bench.bench.metrics import judge
from c3bench.problems import families
from c3bench.problems.instance import Problem
from c3bench.problems.lcs import LCS
from c3bench.problems.limits import Limits
from c3bench.problems.mpc import MPC, HorizonLayout
from c3bench.problems.names import (
    PROFILE_TOLERANCE,
    REFERENCE_ADMM_ITERATIONS,
    Block,
    Failure,
    Family,
    Profile,
    Variant,
)
from c3bench.problems.recover import mismatches, mpc_from_cost
from c3bench.solvers.admm.options import ENUMERATION, C3Options
from c3bench.solvers.base import Backend, Result, Settings, WarmStart, settings_for
from c3bench.solvers.child_process import (
    Reply,
    detach,
    died,
    launch,
    load,
    pinned_blas,
    receive,
    send,
    stop,
)
from c3bench.solvers.isolation import SLOW_SOLVE_SECONDS
from c3bench.solvers.residuals import residuals

SEQUENCE_STEPS: int = REFERENCE_ADMM_ITERATIONS
"""QP steps (ADMM iterations) of one sequence cell: the reference study's 10."""
SEQUENCE_FAMILIES: tuple[Family, ...] = (Family.C3PLUS_QP, Family.C3_QP)
"""Families whose instances head a sequence cell (``c3plus_qp``: C3+, ``c3_qp``: C3)."""
REFERENCE_BACKEND = "clarabel"
"""QP backend of the reference plan (run at ``high_accuracy``)."""
REFERENCE_TOLERANCE = PROFILE_TOLERANCE[Profile.MID_ACCURACY]
"""Each step of the reference run must be certified at this tolerance to be a reference."""
UNBOUNDED_FORCE = 1e9
"""Force limit of a recovered MPC without limits (the ``equality`` variant): it only clips the
applied input, which the plan comparison does not read."""
STEP_COLUMNS: tuple[str, ...] = ("primal_residual_relative", "dual_residual_relative",
                                 "duality_gap_relative", "complementarity_violation")
"""Per-step residual figures (the row holds the worst over the steps)."""


class SequenceUnsupported(ValueError):
    """The head instance does not carry what a controller run needs."""


# --- the controller's data at the head's state -------------------------------------------------
@dataclass
class ControllerData:
    """What one control step needs: model, cost, state and the C3 variant."""

    lcs: LCS
    mpc: MPC
    x0: np.ndarray
    variant: Variant


def _force_limit(limits: Limits | None) -> float:
    if limits is None:
        return UNBOUNDED_FORCE
    bounds = np.abs(np.concatenate([limits.u_lower, limits.u_upper]))
    finite = bounds[np.isfinite(bounds)]
    return float(finite.max()) if finite.size else UNBOUNDED_FORCE


def controller_data(problem: Problem) -> ControllerData:
    """Recover the controller's LCS, MPC and state from a ``c3plus_qp`` / ``c3_qp`` instance.

    With ``g`` the consensus weights (``meta["rho"]``): ``Q = P_{x_0 x_0} / 2 - rho_x I``,
    ``R = P_{u_0 u_0} / 2 - rho_u I``, ``Q_f = P_{x_T x_T} / 2`` and ``x*`` the least-squares
    solution of ``2 Q_f x* = -q_{x_T}`` (:func:`c3bench.problems.recover.mpc_from_cost`); the
    limits from ``meta["limits"]`` (``bounded``). The instance is then rebuilt with
    :func:`c3bench.problems.families.consensus_qp` and must match ``P``, ``q``, ``A``, ``b``,
    the bounds and the offset (:func:`c3bench.problems.recover.mismatches`), else
    :class:`SequenceUnsupported`.
    """
    needed = ("layout", "rho")
    if problem.family not in SEQUENCE_FAMILIES or problem.lcs is None \
            or "x0" not in problem.data or any(k not in problem.meta for k in needed):
        raise SequenceUnsupported("a sequence needs a c3plus_qp / c3_qp instance with its lcs, "
                                  "data['x0'], meta['layout'] and meta['rho']")
    layout = HorizonLayout.from_json(problem.meta["layout"])
    rho = {str(k): float(v) for k, v in dict(problem.meta["rho"]).items()}
    limits = Limits.from_json(problem.meta["limits"]) if "limits" in problem.meta else None
    mpc = mpc_from_cost(problem, layout, _force_limit(limits), limits, rho)
    _check_rebuilt(problem, mpc, rho, limits)
    variant = Variant.C3PLUS if problem.family == Family.C3PLUS_QP else Variant.C3
    assert problem.lcs is not None  # checked above
    return ControllerData(problem.lcs, mpc, np.asarray(problem.data["x0"], dtype=float),
                          variant)


def _check_rebuilt(problem: Problem, mpc: MPC, rho: dict[str, float],
                   limits: Limits | None) -> None:
    assert problem.lcs is not None
    try:
        rebuilt = families.consensus_qp(
            problem.family, problem.name, problem.lcs, mpc, problem.data["x0"], rho,
            problem.data.get("delta"), problem.data.get("w"),
            input_bounds=bool(problem.meta.get("input_bounds", False)), limits=limits)
    except ValueError as error:
        raise SequenceUnsupported(f"cannot rebuild the QP step: {error}") from error
    wrong = mismatches(rebuilt, problem)
    if wrong:
        raise SequenceUnsupported(f"not a QP step of problems.families.consensus_qp's form "
                                  f"(mismatch in {', '.join(wrong)})")


# --- one run, its QP steps recorded -------------------------------------------------------------
@dataclass
class QPStep:
    """One QP step of a run: its problem and the backend's result (``None`` if none)."""

    problem: Problem
    result: Result | None


class RecordingBackend(Backend):
    """Passes every solve to ``backend`` and keeps each ``(problem, result)``."""

    def __init__(self, backend: Backend) -> None:
        self.backend = backend
        self.name = backend.name
        self.families = backend.families
        self.precisions = backend.precisions
        self.package = backend.package
        self.steps: list[QPStep] = []

    def accepts(self, problem: Problem) -> tuple[bool, str]:
        return self.backend.accepts(problem)

    def solve(self, problem: Problem, settings: Settings,
              warm_start: WarmStart | None = None) -> Result:
        step = QPStep(problem, None)
        self.steps.append(step)
        step.result = self.backend.solve(problem, settings, warm_start)
        return step.result


@dataclass
class RunRecord:
    """One ADMM run: its QP steps, the plan and the wall time."""

    steps: list[QPStep]
    ok: bool
    status: str
    delta: np.ndarray
    u_raw: np.ndarray | None
    wall_time: float
    projection_time: float


def controller_options(data: ControllerData, backend: Backend, settings: Settings) -> C3Options:
    """The reference controller's options of a sequence cell (module docstring)."""
    return C3Options(variant=data.variant, qp_backend=backend.name, qp_settings=settings,
                     projection_backend=ENUMERATION, admm_iterations=SEQUENCE_STEPS,
                     keep_iterates=False, backends={backend.name: backend})


def run_once(data: ControllerData, backend: Backend, settings: Settings) -> RunRecord:
    """One cold-started ADMM run with ``backend`` as the QP step, every step recorded."""
    from c3bench.solvers.c3 import solve_c3

    recorder = RecordingBackend(backend)
    options = controller_options(data, recorder, settings)
    start = time.perf_counter()
    solution = solve_c3(data.lcs, data.mpc, data.x0, options)
    wall = time.perf_counter() - start
    return RunRecord(recorder.steps, bool(solution.ok), solution.status,
                     np.array(solution.delta0), None if solution.u_raw is None
                     else np.array(solution.u_raw), wall, float(solution.timings.projection))


# --- certification of each step -----------------------------------------------------------------
@dataclass
class StepFigures:
    """One QP step's times and certificate."""

    setup_time: float
    solve_time: float
    found: bool
    failure: str
    status: str
    iterations: int | None
    rho_lam: float
    objective: float = math.nan
    figures: dict[str, float] = field(default_factory=dict)
    success: bool = False
    verdict: str = ""

    @property
    def total_time(self) -> float:
        """``setup_time + solve_time``."""
        return self.setup_time + self.solve_time


def certify(step: QPStep, tolerance: float) -> StepFigures:
    """Times and the :func:`bench.metrics.judge` verdict of one step against its own QP."""
    problem, result = step.problem, step.result
    rho = problem.meta.get("rho", {})
    out = StepFigures(
        setup_time=float(result.setup_time) if result else math.nan,
        solve_time=float(result.solve_time) if result else math.nan,
        found=bool(result and result.found), failure=str(result.failure) if result else
        str(Failure.ERROR), status=result.status if result else "no result",
        iterations=None if result is None or result.iterations is None
        else int(result.iterations), rho_lam=float(rho.get(Block.LAM, math.nan)))
    out.figures = {name: math.nan for name in STEP_COLUMNS}
    x = None if result is None or result.x is None else np.asarray(result.x, dtype=float)
    if x is not None and x.shape == (problem.n,) and np.all(np.isfinite(x)):
        assert result is not None
        got = residuals(problem, x, result.y, result.z, result.z_box)
        out.objective = problem.objective(x)
        out.figures = {"primal_residual_relative": got.primal_relative,
                       "dual_residual_relative": got.dual_relative,
                       "duality_gap_relative": got.gap_relative,
                       "complementarity_violation": got.complementarity}
    row = {"family": str(problem.family), "found": out.found, "failure": out.failure,
           "status": out.status, "tolerance": tolerance, **out.figures}
    out.success, out.verdict = judge(row)
    return out


# --- the child's job ----------------------------------------------------------------------------
@dataclass(frozen=True)
class SequenceJob:
    """One sequence cell, pickled into the child (backends travel as instances)."""

    backend: Backend
    problem: Problem
    settings: Settings
    repeats: int
    reference: Backend | None
    reference_time_limit: float


@dataclass
class SequenceOutcome:
    """What the child returns: per-step figures (medians of the timed runs), the run."""

    steps: list[StepFigures]
    ok: bool
    status: str
    timed_runs: int
    admm_time: float
    projection_time: float
    delta: np.ndarray
    u_raw: np.ndarray | None


@dataclass
class SequenceReference:
    """The reference run's plan (``verified`` when every step was certified)."""

    verified: bool
    status: str
    delta: np.ndarray | None = None
    u_raw: np.ndarray | None = None


def timed_runs(job: SequenceJob, data: ControllerData, repeats: int) -> SequenceOutcome:
    """``repeats`` runs; per step the median setup and solve; the last run's plan."""
    runs = [run_once(data, job.backend, job.settings) for _ in range(repeats)]
    last = runs[-1]
    tolerance = float(job.settings.tolerance)
    steps = [certify(step, tolerance) for step in last.steps]
    complete = [run for run in runs if len(run.steps) == len(last.steps)]
    for i, figures in enumerate(steps):
        results = [run.steps[i].result for run in complete]
        if all(r is not None for r in results):
            figures.setup_time = statistics.median(float(r.setup_time) for r in results if r)
            figures.solve_time = statistics.median(float(r.solve_time) for r in results if r)
    return SequenceOutcome(steps, last.ok, last.status, repeats,
                           statistics.median(r.wall_time for r in runs),
                           statistics.median(r.projection_time for r in runs),
                           last.delta, last.u_raw)


def reference_plan(job: SequenceJob, data: ControllerData) -> SequenceReference:
    """The reference run (:data:`REFERENCE_BACKEND` at ``high_accuracy``), certified."""
    if job.reference is None:
        return SequenceReference(False, f"reference backend {REFERENCE_BACKEND} not available")
    settings = settings_for(Profile.HIGH_ACCURACY, time_limit=job.reference_time_limit)
    try:
        run = run_once(data, job.reference, settings)
    except Exception as error:  # noqa: BLE001 - a failed reference leaves the row unverified
        return SequenceReference(False, f"reference run raised {type(error).__name__}: {error}")
    failed = [i for i, step in enumerate(run.steps)
              if not certify(step, REFERENCE_TOLERANCE).success]
    if not run.ok or len(run.steps) != SEQUENCE_STEPS or failed:
        why = run.status if not run.ok else f"steps {failed} not certified at " \
                                             f"{REFERENCE_TOLERANCE:g}"
        return SequenceReference(False, f"reference run with {REFERENCE_BACKEND}: {why}")
    return SequenceReference(True, "", run.delta, run.u_raw)


def _sequence_child(connection: Connection, plugins: tuple[str, ...], payload: bytes) -> None:
    """Child of :func:`run_isolated`: untimed run, ``WARM``, timed runs, ``DONE``, reference,
    ``DONE``."""
    detach()
    connection.send((Reply.STARTED, os.getpid()))
    job = load(connection, plugins, payload)
    if not isinstance(job, SequenceJob):
        return
    connection.send((Reply.READY, None))
    try:
        data = controller_data(job.problem)
        with pinned_blas():
            start = time.perf_counter()
            run_once(data, job.backend, job.settings)
            repeats = 1 if time.perf_counter() - start > SLOW_SOLVE_SECONDS else job.repeats
            connection.send((Reply.WARM, repeats))
            send(connection, (Reply.DONE, timed_runs(job, data, repeats)))
            send(connection, (Reply.DONE, reference_plan(job, data)))
    except Exception as error:  # noqa: BLE001 - reported to the parent as the cell's error
        send(connection, (Reply.ERROR, f"{type(error).__name__}: {error}"))


@dataclass
class IsolatedSequence:
    """The parent's view of a sequence cell: the outcome, or the failure that ended it."""

    outcome: SequenceOutcome | None
    reference: SequenceReference
    failure: str = ""
    status: str = ""


def run_isolated(job: SequenceJob) -> IsolatedSequence:
    """Run ``job`` in a child killed when the untimed run overruns ``SEQUENCE_STEPS *
    time_limit`` s, the timed runs ``repeats`` times that, or the reference run
    ``SEQUENCE_STEPS * reference_time_limit`` s.

    Raises :class:`~c3bench.solvers.child_process.IsolationFailed` when the child does not
    start (no row: an infrastructure fault).
    """
    limit = SEQUENCE_STEPS * float(job.settings.time_limit)
    missing = SequenceReference(False, "reference run not reached")
    try:
        payload = bytes(ForkingPickler.dumps(job))
    except Exception as error:  # noqa: BLE001 - an unpicklable backend is the cell's error
        return IsolatedSequence(None, missing, Failure.ERROR,
                                f"the sequence could not be sent to the solver process: "
                                f"{type(error).__name__}: {error}")
    process, connection, message = launch(_sequence_child, payload, duplex=False)
    try:
        if message[0] == Reply.READY:
            message = receive(connection, limit)
        if message[0] == Reply.WARM:
            message = receive(connection, limit * int(message[1]))
        if message[0] != Reply.DONE or not isinstance(message[1], SequenceOutcome):
            return _ended(message, process, limit, missing)
        outcome = message[1]
        answer = receive(connection, SEQUENCE_STEPS * job.reference_time_limit)
        reference = answer[1] if answer[0] == Reply.DONE and isinstance(
            answer[1], SequenceReference) else SequenceReference(
                False, f"reference run: {answer[0]}")
        return IsolatedSequence(outcome, reference)
    finally:
        connection.close()
        stop(process)


def _ended(message: tuple[Reply, Any], process: Any, limit: float,
           reference: SequenceReference) -> IsolatedSequence:
    """The failure of a child that did not return its timed runs."""
    kind, payload = message
    if kind == Reply.TIMEOUT:
        return IsolatedSequence(None, reference, Failure.TIMEOUT,
                                f"time limit of {limit:g} s per run exceeded; process killed")
    if kind == Reply.DIED:
        return IsolatedSequence(None, reference, Failure.ERROR, died(process))
    return IsolatedSequence(None, reference, Failure.ERROR,
                            str(payload or f"unexpected message {kind!r}").strip())

