"""Benchmark runner: plan cells, compute references, run cells in a pool or on Dask, store rows.

Unit of work: one **cell** = (instance, solver, settings profile, precision, start). A cell
exists only when the backend accepts the instance (``backend.accepts``) and runs in that
precision; ``warm`` cells exist only for instances with a predecessor in their ADMM sequence
(same family and metadata except ``admm_iteration``/``rho``, the largest earlier iteration
present in the suite) whose reference solution is known: the warm start is that solution, as
a controller reuses its last answer.

Both executors call the same :func:`run_cell`:

* the local pool (default, ``jobs`` worker processes, one cell at a time each; a worker that
  dies or overruns a watchdog costs only its cell, recorded as a failed row, and is replaced);
* a Dask distributed cluster when a scheduler address is given (``Client(address)``).

Timing follows docs/metrics.md through :func:`solvers.registry.solve`: an untimed warm-up, then
``repeats`` timed solves (median), BLAS pinned to one thread, build and solve apart, the time
limit enforced in a killed child. Each finished cell is written at once (``store.write_cell``:
temporary file + rename), so an interrupt or crash loses nothing finished; a rerun skips
finished cells unless ``rerun=True``. ``results.parquet``/``.csv`` are consolidated at the end
(also after an interrupt).
"""

from __future__ import annotations

import contextlib
import datetime as dt
import itertools
import json
import math
import multiprocessing
import os
import platform
import signal
import socket
import sys
import time
import traceback
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from multiprocessing.connection import wait as wait_connections
from pathlib import Path
from typing import Any

import numpy as np

from c3bench.bench import store
from c3bench.bench.metrics import judge
from c3bench.bench.reference import (
    Reference,
    ReferencePlan,
    ReferenceValue,
    compute_reference,
    instance_hash,
    load_references,
    plan_for,
    reusable,
    save_references,
)
from c3bench.problems.instance import Problem, list_instances, load_problem
from c3bench.solvers import registry
from c3bench.solvers.base import PRECISIONS, PROFILES, Result, WarmStart, settings_for
from c3bench.solvers.residuals import cost_error, residuals
from c3bench.solvers.timing import blas_threads

STARTS: tuple[str, ...] = ("cold", "warm")
DEFAULT_SETTINGS: tuple[str, ...] = ("default",)
ITERATION_KEYS: tuple[str, ...] = ("admm_iteration", "rho")


@dataclass(frozen=True)
class Cell:
    """One unit of work."""

    instance: str
    family: str
    solver: str
    settings: str
    precision: str
    start: str

    @property
    def id(self) -> str:
        return store.cell_id(self.instance, self.solver, self.settings, self.precision,
                             self.start)

    @property
    def key(self) -> tuple[str, ...]:
        return (self.instance, self.solver, self.settings, self.precision, self.start)


@dataclass(frozen=True)
class RunOptions:
    """How each cell is solved.

    Attributes
    ----------
    repeats
        Timed repeats (median reported) after one untimed warm-up.
    time_limit
        Seconds per solve (the registry kills the solve after it).
    reference_time_limit
        Seconds per reference solve.
    preload
        Plugins loaded in every worker before a cell runs, ``module`` or
        ``module:function`` (to register extra backends; see
        :func:`c3bench.solvers.registry.import_plugins`).
    suite
        Suite name written into each row.
    """

    repeats: int = 3
    time_limit: float = 10.0
    reference_time_limit: float = 60.0
    preload: tuple[str, ...] = ()
    suite: str = ""

    def cell_budget(self) -> float:
        """Watchdog for one cell in the pool: well beyond the registry's own limit."""
        return 2.0 * self.time_limit * (self.repeats + 1) + 60.0


@dataclass
class CellOutcome:
    """What a worker returns: the row and the trace payload (``{}`` when none)."""

    row: dict[str, Any]
    trace: dict[str, Any] = field(default_factory=dict)


# --- rows -------------------------------------------------------------------------------------
def _now() -> str:
    return dt.datetime.now(dt.UTC).isoformat(timespec="seconds")


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
        "settings": cell.settings, "tolerance": PROFILES[cell.settings],
        "time_limit": options.time_limit, "precision": cell.precision, "start": cell.start,
        "repeats": options.repeats,
        "state_index": None if state is None else int(state),
        "admm_iteration": None if iteration is None else int(iteration),
        "rho_lam": float(rho["lam"]) if isinstance(rho, dict) and "lam" in rho else math.nan,
        "n_variables": problem.n,
        "n_constraints": problem.n_eq + problem.n_ineq + problem.n_bounded,
        "host": socket.gethostname(), "finished_at": _now(),
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
    row.update({"found": False, "failure": failure, "status": status})
    row["success"], row["verdict"] = judge(row)
    return row


def _finite_or_nan(value: Any) -> float:
    try:
        number = float(value)
    except (TypeError, ValueError):
        return math.nan
    return number


def fill_row(row: dict[str, Any], problem: Problem, result: Result) -> dict[str, Any]:
    """Put a :class:`Result` and its residuals (the one residual module) into ``row``."""
    row.update({
        "found": bool(result.found), "failure": result.failure or "",
        "status": str(result.status), "build_time": _finite_or_nan(result.build_time),
        "solve_time": _finite_or_nan(result.solve_time),
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
    row["success"], row["verdict"] = judge(row)
    return row


def run_cell(cell: Cell, problem: Problem, options: RunOptions, version: str = "",
             reference: ReferenceValue | None = None,
             warm_start: WarmStart | None = None, digest: str = "") -> CellOutcome:
    """Solve one cell through the guarded registry and build its row. Never raises.

    Both executors (local pool, Dask) call exactly this function.
    """
    try:
        registry.import_plugins(options.preload)
        settings = settings_for(cell.settings, time_limit=options.time_limit,
                                precision=cell.precision)
        result = registry.solve(cell.solver, problem, settings,
                                warm_start=warm_start if cell.start == "warm" else None,
                                repeats=options.repeats, warmup=True, isolate=True)
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
        if isinstance(error, KeyboardInterrupt | SystemExit):
            raise
        status = f"{type(error).__name__}: {error}\n{traceback.format_exc(limit=3)}"
        return CellOutcome(failure_row(cell, problem, options, version, reference, "error",
                                       status.strip(), digest))


def reference_task(problem: Problem, digest: str, plan: ReferencePlan | None,
                   time_limit: float, preload: tuple[str, ...]) -> Reference:
    """Worker entry point for references (the plan travels with the task)."""
    return compute_reference(problem, digest, plan, time_limit, preload)


# --- planning ---------------------------------------------------------------------------------
def sequence_key(problem: Problem) -> str:
    """Identity of an ADMM sequence: family and all metadata but the iteration and rho."""
    meta = {k: v for k, v in problem.meta.items() if k not in ITERATION_KEYS}
    return json.dumps([problem.family, problem.n, meta], sort_keys=True, default=str)


def predecessors(problems: Sequence[Problem]) -> dict[str, str]:
    """``instance -> previous instance of its ADMM sequence`` (absent for the first)."""
    sequences: dict[str, list[tuple[int, str]]] = {}
    for problem in problems:
        iteration = problem.meta.get("admm_iteration")
        if iteration is None:
            continue
        sequences.setdefault(sequence_key(problem), []).append((int(iteration), problem.name))
    out: dict[str, str] = {}
    for members in sequences.values():
        members.sort()
        for (_, before), (_, after) in itertools.pairwise(members):
            out[after] = before
    return out


@dataclass
class Plan:
    """The cells of a run and what was left out."""

    cells: list[Cell]
    solvers: dict[str, str]
    skipped_solvers: dict[str, str]


def plan_cells(problems: Sequence[Problem], solvers: Sequence[str] | None,
               settings: Sequence[str], precisions: Sequence[str],
               starts: Sequence[str], previous: dict[str, str]) -> Plan:
    """Every cell a backend can take; warm cells only where a predecessor exists.

    ``solvers=None`` means every available backend. Unknown names raise ``ValueError``;
    unavailable backends are skipped (listed in ``skipped_solvers`` with the reason).
    """
    for profile in settings:
        if profile not in PROFILES:
            raise ValueError(f"unknown settings {profile!r}; known: {', '.join(PROFILES)}")
    for precision in precisions:
        if precision not in PRECISIONS:
            raise ValueError(f"unknown precision {precision!r}; known: {', '.join(PRECISIONS)}")
    for start in starts:
        if start not in STARTS:
            raise ValueError(f"unknown start {start!r}; known: {', '.join(STARTS)}")
    infos = {info.name: info for info in registry.available()}
    if solvers is not None:
        unknown = [name for name in solvers if name not in infos]
        if unknown:
            raise ValueError(f"unknown solver(s) {', '.join(unknown)}; known: "
                             f"{', '.join(infos)}")
    names = list(infos) if solvers is None else list(dict.fromkeys(solvers))
    chosen = {n: infos[n].version for n in names if infos[n].available}
    skipped = {n: infos[n].reason for n in names if not infos[n].available}
    cells = []
    for problem in problems:
        for name in chosen:
            backend = registry.get(name)
            try:
                accepted, _ = backend.accepts(problem)
            except Exception:  # noqa: BLE001 - a broken accepts() means it cannot take it
                accepted = False
            if not accepted:
                continue
            for precision in precisions:
                if precision not in backend.precisions:
                    continue
                for profile in settings:
                    for start in starts:
                        if start == "warm" and problem.name not in previous:
                            continue
                        cells.append(Cell(problem.name, problem.family, name, profile,
                                          precision, start))
    return Plan(cells, chosen, skipped)


# --- executors --------------------------------------------------------------------------------
@dataclass
class TaskResult:
    """Outcome of one task: ``ok`` with its value, or the reason it produced none."""

    key: Any
    ok: bool
    value: Any = None
    failure: str = ""
    reason: str = ""


Task = tuple[Any, Callable[..., Any], tuple[Any, ...], float]


def _worker_main(connection: Any, log_path: str | None = None) -> None:
    """Loop of a pool worker: receive ``(key, fn, args)``, send ``(key, ok, value)``.

    With ``log_path`` the worker's stdout and stderr (file descriptors 1 and 2, so C
    libraries' prints too) are appended to that file instead of the terminal.
    """
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the parent handles Ctrl-C
    if log_path:
        descriptor = os.open(log_path, os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o644)
        os.dup2(descriptor, 1)
        os.dup2(descriptor, 2)
        os.close(descriptor)

    def terminate(signum: int, frame: Any) -> None:
        raise SystemExit(0)  # runs the registry's finally blocks, which kill its children

    signal.signal(signal.SIGTERM, terminate)
    while True:
        try:
            message = connection.recv()
        except EOFError:
            return
        if message is None:
            return
        key, fn, args = message
        try:
            reply = (key, True, fn(*args))
        except Exception as error:  # noqa: BLE001
            reply = (key, False, f"{type(error).__name__}: {error}")
        connection.send(reply)


class LocalPool:
    """``jobs`` worker processes, one task each at a time, with crash and hang recovery.

    A task is ``(key, fn, args, watchdog_seconds)``. A worker that dies while running a task
    yields a failed :class:`TaskResult` for that task only and is replaced; one that does not
    answer within the watchdog is killed (its task fails with ``timeout``) and replaced.
    Solver output of the workers goes to ``log_path`` when given.
    """

    def __init__(self, jobs: int, log_path: str | Path | None = None) -> None:
        if jobs < 1:
            raise ValueError(f"jobs must be >= 1, got {jobs}")
        self.jobs = jobs
        self.log_path = str(log_path) if log_path else None
        method = "fork" if "fork" in multiprocessing.get_all_start_methods() else "spawn"
        self.context = multiprocessing.get_context(method)
        self.workers: list[dict[str, Any]] = []

    def _start(self) -> dict[str, Any]:
        parent, child = self.context.Pipe(duplex=True)
        process = self.context.Process(target=_worker_main, args=(child, self.log_path),
                                       daemon=False)
        process.start()
        child.close()
        return {"process": process, "conn": parent, "task": None, "since": 0.0}

    def _stop(self, worker: dict[str, Any], force: bool = False) -> None:
        process = worker["process"]
        if not force:
            with contextlib.suppress(OSError):
                worker["conn"].send(None)
            process.join(2)
        if process.is_alive():
            process.terminate()
            process.join(5)
        if process.is_alive():
            process.kill()
            process.join(5)
        worker["conn"].close()

    def share(self, value: Any) -> Any:
        return value

    def run(self, tasks: Iterable[Task]) -> Iterator[TaskResult]:
        """Run tasks, yielding results as they finish (in completion order)."""
        pending = list(tasks)
        pending.reverse()
        try:
            while len(self.workers) < min(self.jobs, len(pending)):
                self.workers.append(self._start())
            while pending or any(w["task"] is not None for w in self.workers):
                for index, worker in enumerate(self.workers):
                    if worker["task"] is None and pending:
                        if not worker["process"].is_alive():
                            self._stop(worker, force=True)
                            worker = self.workers[index] = self._start()
                        task = pending.pop()
                        key, fn, args, _ = task
                        try:
                            worker["conn"].send((key, fn, args))
                        except (OSError, ValueError) as error:
                            yield TaskResult(key, False, failure="error",
                                             reason=f"cannot send the task: {error}")
                            continue
                        worker["task"], worker["since"] = task, time.monotonic()
                busy = [w for w in self.workers if w["task"] is not None]
                if not busy:
                    continue
                waitables: list[Any] = [w["conn"] for w in busy]
                waitables += [w["process"].sentinel for w in busy]
                deadline = min(w["since"] + w["task"][3] for w in busy)
                ready = wait_connections(waitables, timeout=max(0.0, deadline
                                                                - time.monotonic()) + 0.05)
                for index, worker in enumerate(self.workers):
                    task = worker["task"]
                    if task is None:
                        continue
                    key = task[0]
                    outcome: TaskResult | None = None
                    if worker["conn"] in ready or worker["process"].sentinel in ready:
                        try:
                            if worker["conn"].poll():
                                _, ok, value = worker["conn"].recv()
                                outcome = (TaskResult(key, True, value) if ok else
                                           TaskResult(key, False, failure="error",
                                                      reason=f"worker raised {value}"))
                        except (EOFError, OSError):
                            outcome = None
                        if outcome is None and not worker["process"].is_alive():
                            code = worker["process"].exitcode
                            outcome = TaskResult(key, False, failure="error",
                                                 reason=f"worker process died (exit code "
                                                        f"{code}) while running this cell")
                            self._stop(worker, force=True)
                            self.workers[index] = self._start()
                    elif time.monotonic() - worker["since"] > task[3]:
                        outcome = TaskResult(key, False, failure="timeout",
                                             reason=f"worker did not answer within "
                                                    f"{task[3]:g} s; worker killed")
                        self._stop(worker, force=True)
                        self.workers[index] = self._start()
                    if outcome is not None:
                        self.workers[index]["task"] = None
                        yield outcome
        finally:
            self.close()

    def close(self) -> None:
        for worker in self.workers:
            self._stop(worker, force=worker["task"] is not None)
        self.workers = []


class DaskPool:
    """Tasks on a Dask distributed cluster (``Client(address)``), same interface."""

    def __init__(self, address: str) -> None:
        from distributed import Client

        self.client = Client(address)

    def share(self, value: Any) -> Any:
        return self.client.scatter(value, broadcast=False, hash=False)

    def run(self, tasks: Iterable[Task]) -> Iterator[TaskResult]:
        from distributed import as_completed

        futures: dict[Any, Any] = {}
        try:
            for index, (key, fn, args, _) in enumerate(tasks):
                future = self.client.submit(fn, *args, pure=False, retries=0,
                                            key=f"c3bench-{os.getpid()}-{index}-{time.time_ns()}")
                futures[future.key] = (key, future)
            for future in as_completed([f for _, f in futures.values()]):
                key = futures[future.key][0]
                try:
                    value = future.result()
                except Exception as error:  # noqa: BLE001 - e.g. KilledWorker
                    yield TaskResult(key, False, failure="error",
                                     reason=f"dask task failed: {type(error).__name__}: "
                                            f"{error}")
                else:
                    yield TaskResult(key, True, value)
                future.release()
        finally:
            pending = [f for _, f in futures.values() if not f.done()]
            if pending:
                self.client.cancel(pending)

    def close(self) -> None:
        self.client.close()


# --- the run ----------------------------------------------------------------------------------
@dataclass
class RunSummary:
    """What a run did."""

    suite: str
    root: Path
    planned: int
    already_done: int
    ran: int
    failed: int
    interrupted: bool
    skipped_solvers: dict[str, str]
    warm_without_reference: int
    references_computed: int
    stale_removed: int = 0


def ensure_instances(spec: Any, paths: store.SuitePaths, capture: Any = None,
                     progress: bool = True) -> list[Path]:
    """Generate the suite's instances under ``paths.instances`` unless already there."""
    if not (paths.instances / "manifest.json").exists():
        from c3bench.problems.suites import generate_suite

        generate_suite(spec, paths.instances, capture=capture, progress=progress)
    return list_instances(paths.instances)


def machine_info() -> dict[str, Any]:
    """Machine, Python and package versions for the report header."""
    import importlib.metadata as metadata

    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    packages = {}
    for name in ("c3bench", "numpy", "scipy", "pandas", "pyarrow", "matplotlib", "dask",
                 "distributed", "threadpoolctl", "mujoco"):
        try:
            packages[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            packages[name] = "not installed"
    return {"cpu": cpu, "cores": os.cpu_count(), "host": socket.gethostname(),
            "platform": platform.platform(), "python": platform.python_version(),
            "packages": packages, "blas_threads_default": blas_threads(),
            "blas_threads_timed": 1, "date": _now()}


def _suite_name(suite: Any) -> str:
    return suite if isinstance(suite, str) else suite.name


def run_suite(
    suite: Any,
    results_dir: str | Path = "results",
    solvers: Sequence[str] | None = None,
    settings: Sequence[str] = DEFAULT_SETTINGS,
    precisions: Sequence[str] = PRECISIONS,
    starts: Sequence[str] = STARTS,
    families: Sequence[str] | None = None,
    jobs: int = 2,
    scheduler: str | None = None,
    rerun: bool = False,
    repeats: int = 3,
    time_limit: float = 10.0,
    reference_time_limit: float = 60.0,
    capture: Any = None,
    progress: bool = True,
    max_cells: int | None = None,
    on_cell: Callable[[CellOutcome], None] | None = None,
    preload: Sequence[str] = (),
) -> RunSummary:
    """Run a suite into ``results_dir/<suite>/`` (see the module docstring).

    Parameters
    ----------
    suite
        Suite name (``problems.suites.SUITES``) or a ``SuiteSpec``.
    solvers, settings, precisions, starts, families
        Selection (``None`` solvers: every available backend; ``None`` families: all).
    jobs, scheduler
        Local pool size, or a Dask scheduler address (then ``jobs`` is ignored).
    rerun
        Run cells even when already stored (overwrites them).
    repeats, time_limit, reference_time_limit
        Timing (see :class:`RunOptions`).
    capture
        Capture function passed to ``generate_suite`` when instances are generated.
    max_cells
        Stop after this many cells (the rest stay for a later run).
    on_cell
        Called with each stored :class:`CellOutcome` (raising ``KeyboardInterrupt`` from it
        stops the run like Ctrl-C: finished cells are kept).
    preload
        Plugins (``module`` or ``module:function``) loaded here and in each worker, to
        register extra backends.
    """
    name = _suite_name(suite)
    paths = store.SuitePaths.of(results_dir, name)
    paths.root.mkdir(parents=True, exist_ok=True)
    registry.import_plugins(preload)
    instance_files = ensure_instances(suite, paths, capture, progress)
    problems: dict[str, Problem] = {}
    hashes: dict[str, str] = {}
    for path in instance_files:
        problem = load_problem(path)
        hashes[problem.name] = instance_hash(path)
        if families is None or problem.family in families:
            problems[problem.name] = problem
    previous = predecessors(list(problems.values()))
    plan = plan_cells(list(problems.values()), solvers, settings, precisions, starts,
                      previous)
    options = RunOptions(repeats=repeats, time_limit=time_limit,
                         reference_time_limit=reference_time_limit,
                         preload=tuple(preload), suite=name)
    info = machine_info()
    info.update({"suite": name, "jobs": jobs, "scheduler": scheduler or "",
                 "repeats": repeats, "time_limit": time_limit, "settings": list(settings),
                 "precisions": list(precisions), "starts": list(starts),
                 "solvers": plan.solvers, "skipped_solvers": plan.skipped_solvers,
                 "solver_table": [{"name": r.name, "available": r.available,
                                   "reason": r.reason, "version": r.version,
                                   "families": list(r.families),
                                   "precisions": list(r.precisions)}
                                  for r in registry.available()]})
    store.write_json(paths.run_info, info)

    done: set[tuple[str, ...]] = set()
    stale = 0
    for row in store.read_cells(paths):
        if hashes.get(row["instance"]) != row["instance_hash"]:
            store.remove_cell(paths, row)  # its instance changed or left the suite
            stale += 1
        elif not rerun:
            done.add(store.cell_key(row))
    todo = [cell for cell in plan.cells if cell.key not in done]
    already = len(plan.cells) - len(todo)
    if max_cells is not None:
        todo = todo[:max_cells]

    log_path = paths.solver_log
    with open(log_path, "a") as log:
        log.write(f"=== run started {_now()} ===\n")
    pool: LocalPool | DaskPool = DaskPool(scheduler) if scheduler else LocalPool(jobs, log_path)
    interrupted = False
    ran = failed = refs_computed = warm_missing = 0
    try:
        # references: for the instances of the cells to run and their predecessors
        needed = {c.instance for c in todo}
        needed |= {previous[c.instance] for c in todo if c.start == "warm"}
        references = load_references(paths.references)
        missing = sorted(n for n in needed if not reusable(references.get(n), hashes[n],
                                                           plan_for(problems[n].family)))
        if missing:
            shared = {n: pool.share(problems[n]) for n in missing}
            tasks = [(n, reference_task, (shared[n], hashes[n], plan_for(problems[n].family),
                                          reference_time_limit, tuple(preload)),
                      4 * reference_time_limit + 60) for n in missing]
            bar = _bar(progress, len(tasks), f"references {name}", "instance")
            try:
                for outcome in pool.run(tasks):
                    if outcome.ok:
                        references[outcome.key] = outcome.value
                    else:
                        ref = Reference(outcome.key, problems[outcome.key].family,
                                        hashes[outcome.key], "", "", "")
                        ref.reason, ref.failure = outcome.reason, outcome.failure
                        references[outcome.key] = ref
                    refs_computed += 1
                    bar.update(1)
            finally:
                bar.close()
                save_references(paths.references, references)
        # warm cells need the predecessor's reference solution
        runnable = []
        for cell in todo:
            if cell.start == "warm":
                ref = references.get(previous[cell.instance])
                if ref is None or ref.warm_start() is None:
                    warm_missing += 1
                    continue
            runnable.append(cell)
        shared = {n: pool.share(problems[n]) for n in {c.instance for c in runnable}}
        by_key = {cell.key: cell for cell in runnable}
        tasks = []
        for cell in runnable:
            ref = references.get(cell.instance)
            value = ref.value() if ref is not None else None
            warm = references[previous[cell.instance]].warm_start() \
                if cell.start == "warm" else None
            tasks.append((cell.key, run_cell,
                          (cell, shared[cell.instance], options, plan.solvers[cell.solver],
                           value, warm, hashes[cell.instance]), options.cell_budget()))
        bar = _bar(progress, len(tasks), f"cells {name}", "cell")
        try:
            for outcome in pool.run(tasks):
                cell = by_key[outcome.key]
                if outcome.ok:
                    result: CellOutcome = outcome.value
                else:
                    ref = references.get(cell.instance)
                    result = CellOutcome(failure_row(
                        cell, problems[cell.instance], options, plan.solvers[cell.solver],
                        ref.value() if ref is not None else None, outcome.failure,
                        outcome.reason, hashes[cell.instance]))
                store.write_cell(paths, result.row, result.trace)
                ran += 1
                failed += not result.row["success"]
                bar.update(1)
                if on_cell is not None:
                    on_cell(result)
        finally:
            bar.close()
    except KeyboardInterrupt:
        interrupted = True
        raise
    finally:
        pool.close()
        if paths.cells.is_dir():
            store.consolidate(paths)
        if interrupted:
            print(f"\ninterrupted: {ran} cells stored in {paths.cells}; rerun to resume",
                  file=sys.stderr)
    return RunSummary(name, paths.root, len(plan.cells), already, ran, failed, interrupted,
                      plan.skipped_solvers, warm_missing, refs_computed, stale)


def _bar(enabled: bool, total: int, description: str, unit: str) -> Any:
    from tqdm import tqdm

    tqdm.monitor_interval = 0  # no monitor thread: pool workers are forked from this process
    return tqdm(total=total, desc=description, unit=unit, disable=not enabled,
                dynamic_ncols=True)
