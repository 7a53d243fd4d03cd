"""Benchmark runner: plan the cells, compute references, run the cells, store the rows.

The parts live in modules of one job each: :mod:`bench.planning` (cells, ADMM sequences, run
options), :mod:`bench.rows` (one cell's solve and row), :mod:`bench.executors` (local pool,
Dask), :mod:`bench.machine` (``run_info.json``) and :mod:`bench.store` (files). This module is
the loop that ties them together.

Each finished cell is written at once (``store.write_cell``: temporary file + rename), so an
interrupt or crash loses nothing finished; a rerun skips finished cells unless ``rerun=True``
and reruns the cells of instances whose content changed. ``results.parquet``/``.csv`` are
consolidated at the end (also after an interrupt).
"""

from __future__ import annotations

import sys
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from c3bench.bench import store
from c3bench.bench.executors import DaskPool, Executor, LocalPool, Task
from c3bench.bench.machine import machine_info, utc_now
from c3bench.bench.planning import (
    DEFAULT_PRECISIONS,
    DEFAULT_SETTINGS,
    STARTS,
    Cell,
    Plan,
    RunOptions,
    plan_cells,
    predecessors,
)
from c3bench.bench.reference import (
    Reference,
    instance_hash,
    load_references,
    plan_for,
    reusable,
    save_references,
)
from c3bench.bench.rows import CellOutcome, failure_row, reference_task, run_cell
from c3bench.problems.capture import SUITES
from c3bench.problems.errors import InputError
from c3bench.problems.instance import Problem, list_instances, load_problem
from c3bench.problems.names import Start
from c3bench.solvers import registry


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


def _suite_name(suite: Any) -> str:
    """The name of a suite given by name or as a ``SuiteSpec``."""
    return suite if isinstance(suite, str) else str(suite.name)


def _bar(enabled: bool, total: int, description: str, unit: str) -> Any:
    """A tqdm progress bar (disabled when ``enabled`` is false)."""
    from tqdm import tqdm

    tqdm.monitor_interval = 0  # no monitor thread: pool workers are forked from this process
    return tqdm(total=total, desc=description, unit=unit, disable=not enabled,
                dynamic_ncols=True)


def _write_run_info(paths: store.SuitePaths, plan: Plan, name: str, jobs: int,
                    scheduler: str | None, options: RunOptions, settings: Sequence[str],
                    precisions: Sequence[str], starts: Sequence[str]) -> None:
    """``run_info.json``: the machine, the options and the solver table of this run."""
    info = machine_info()
    info.update({"suite": name, "jobs": jobs, "scheduler": scheduler or "",
                 "repeats": options.repeats, "time_limit": options.time_limit,
                 "settings": [str(s) for s in settings],
                 "precisions": [str(p) for p in precisions],
                 "starts": [str(s) for s in starts],
                 "solvers": plan.solvers, "skipped_solvers": plan.skipped_solvers,
                 "solver_table": [{"name": r.name, "available": r.available,
                                   "reason": r.reason, "version": r.version,
                                   "families": [str(f) for f in r.families],
                                   "precisions": [str(p) for p in r.precisions]}
                                  for r in registry.available()]})
    store.write_json(paths.run_info, info)


def _references(pool: Executor, paths: store.SuitePaths, names: set[str],
                problems: dict[str, Problem], hashes: dict[str, str], options: RunOptions,
                progress: bool) -> tuple[dict[str, Reference], int]:
    """The references of ``names``: cached ones reused, the others computed and cached."""
    references = load_references(paths.references)
    missing = sorted(n for n in names if not reusable(references.get(n), hashes[n],
                                                      plan_for(problems[n].family)))
    if not missing:
        return references, 0
    shared = {n: pool.share(problems[n]) for n in missing}
    tasks: list[Task] = [
        (n, reference_task, (shared[n], hashes[n], plan_for(problems[n].family),
                             options.reference_time_limit, options.preload),
         options.reference_budget()) for n in missing]
    bar = _bar(progress, len(tasks), f"references {options.suite}", "instance")
    computed = 0
    try:
        for outcome in pool.run(tasks):
            if outcome.ok:
                references[outcome.key] = outcome.value
            else:
                ref = Reference(outcome.key, str(problems[outcome.key].family),
                                hashes[outcome.key], "", "", "")
                ref.reason, ref.failure = outcome.reason, str(outcome.failure)
                references[outcome.key] = ref
            computed += 1
            bar.update(1)
    finally:
        bar.close()
        save_references(paths.references, references)
    return references, computed


def run_suite(
    suite: Any,
    results_dir: str | Path = "results",
    solvers: Sequence[str] | None = None,
    settings: Sequence[str] = DEFAULT_SETTINGS,
    precisions: Sequence[str] = DEFAULT_PRECISIONS,
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
        Suite name (``problems.capture.SUITES``, or one whose instances are already under
        ``results_dir/<suite>/instances``) or a ``SuiteSpec``.
    results_dir
        The results root; the suite's files go to ``results_dir/<suite>/``.
    solvers, settings, precisions, starts, families
        Selection (``None`` solvers: every available backend; ``None`` families: all).
    jobs, scheduler
        Local pool size, or a Dask scheduler address (then ``jobs`` is ignored).
    rerun
        Run cells even when already stored (overwrites them).
    repeats, time_limit, reference_time_limit
        Timing (see :class:`bench.planning.RunOptions`).
    capture
        Capture function passed to ``generate_suite`` when instances are generated.
    progress
        Show progress bars.
    max_cells
        Stop after this many cells (the rest stay for a later run).
    on_cell
        Called with each stored :class:`bench.rows.CellOutcome` (raising
        ``KeyboardInterrupt`` from it stops the run like Ctrl-C: finished cells are kept).
    preload
        Plugins (``module`` or ``module:function``) loaded here and in each worker, to
        register extra backends.

    Returns
    -------
    RunSummary
        Counts of what was planned, found stored, run and failed.
    """
    name = _suite_name(suite)
    paths = store.SuitePaths.of(results_dir, name)
    if isinstance(suite, str) and suite not in SUITES \
            and not (paths.instances / "manifest.json").exists():
        raise InputError(f"unknown suite {suite!r}: no instances under {paths.instances} and "
                         f"not one of {', '.join(SUITES)}")
    paths.root.mkdir(parents=True, exist_ok=True)
    registry.import_plugins(preload)
    problems: dict[str, Problem] = {}
    hashes: dict[str, str] = {}
    for path in ensure_instances(suite, paths, capture, progress):
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
    _write_run_info(paths, plan, name, jobs, scheduler, options, settings, precisions, starts)

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

    with open(paths.solver_log, "a") as log:
        log.write(f"=== run started {utc_now()} ===\n")
    pool: Executor = DaskPool(scheduler) if scheduler else LocalPool(jobs, paths.solver_log)
    interrupted = False
    ran = failed = refs_computed = warm_missing = 0
    try:
        # references: for the instances of the cells to run and their predecessors
        needed = {c.instance for c in todo}
        needed |= {previous[c.instance] for c in todo if c.start == Start.WARM}
        references, refs_computed = _references(pool, paths, needed, problems, hashes,
                                                options, progress)
        # warm cells need the predecessor's reference solution
        runnable: list[Cell] = []
        for cell in todo:
            if cell.start == Start.WARM:
                before = references.get(previous[cell.instance])
                if before is None or before.warm_start() is None:
                    warm_missing += 1
                    continue
            runnable.append(cell)
        shared = {n: pool.share(problems[n]) for n in {c.instance for c in runnable}}
        by_key = {cell.key: cell for cell in runnable}
        tasks: list[Task] = []
        for cell in runnable:
            ref = references.get(cell.instance)
            warm = references[previous[cell.instance]].warm_start() \
                if cell.start == Start.WARM else None
            tasks.append((cell.key, run_cell,
                          (cell, shared[cell.instance], options, plan.solvers[cell.solver],
                           ref.value() if ref is not None else None, warm,
                           hashes[cell.instance]), options.cell_budget()))
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
