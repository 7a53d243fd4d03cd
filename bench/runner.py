"""Benchmark runner: plan the cells, compute references, run the cells, store the rows.

The parts live in modules of one job each: :mod:`bench.planning` (cells, ADMM sequences, run
options), :mod:`bench.rows` (one cell's solve and row), :mod:`bench.executors` (local pool,
Dask), :mod:`bench.lock` (one run per results directory, SIGTERM), :mod:`bench.machine`
(``run_info.json``) and :mod:`bench.store` (files). This module is the loop that ties them
together.

Each finished cell is written at once (``store.write_cell``: temporary file + rename), so an
interrupt or crash loses nothing finished; a rerun skips finished cells unless ``rerun=True``
and reruns the cells of instances whose content changed (their identity,
:mod:`c3bench.problems.identity`: provenance and arrays to ~1e-9, so a suite regenerated on
another machine is not "changed"; their stale cells are deleted and
``results.parquet``/``.csv`` rewritten before any work). The tables are consolidated again at
the end, also after Ctrl-C or SIGTERM.

Only a solve's own outcome becomes a row (a timeout, a crash of the solving child, an error,
garbage output: :mod:`bench.rows`). A cell whose worker, pool or scheduler failed outside the
solve is not stored: the executor retries it once, and if it still fails it is counted in
:attr:`RunSummary.missing` with its reason, for the next run to complete.
"""

from __future__ import annotations

import json
import os
import secrets
import shutil
import sys
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from c3bench.bench import store
from c3bench.bench.executors import DaskPool, Executor, LocalPool, Task, note_reason
from c3bench.bench.lock import exclusive_run, report_stopped
from c3bench.bench.machine import machine_info, utc_now
from c3bench.bench.planning import (
    DEFAULT_PRECISIONS,
    DEFAULT_SETTINGS,
    SEQUENCE_SCOPE,
    STARTS,
    Cell,
    Plan,
    RunOptions,
    plan_cells,
    predecessors,
    sequence_heads,
)
from c3bench.bench.progress import progress_bar
from c3bench.bench.reference import (
    Reference,
    load_references,
    plan_for,
    reusable,
    save_references,
)
from c3bench.bench.rows import CellOutcome, reference_task, run_cell, run_sequence_cell
from c3bench.problems.capture import SUITES, SuiteSpec
from c3bench.problems.errors import InputError, SchemaVersionError
from c3bench.problems.identity import (
    InstanceIdentity,
    identify,
    load_identities,
    save_identities,
)
from c3bench.problems.importers import write_manifest
from c3bench.problems.instance import MANIFEST, InstanceSet, Problem, read_instances
from c3bench.problems.names import Start
from c3bench.solvers import registry


@dataclass
class RunSummary:
    """What a run did.

    ``missing`` counts the cells planned for this run that were not stored because the
    infrastructure failed (a worker died outside the solve, the scheduler went away, a
    reference could not be computed for such a reason); ``missing_reasons`` gives their first
    distinct reasons (at most
    :data:`bench.executors.MAX_REASONS`). The next run completes them.
    """

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
    missing: int = 0
    missing_reasons: list[str] = field(default_factory=list)
    adopted: int = 0
    """Rows of a results table found without its cell files (a fresh checkout of committed
    results) that this run did not plan and kept as cells (:func:`_adopt_table`)."""


@dataclass
class _Tally:
    """Counts of a run so far (kept when it is interrupted)."""

    ran: int = 0
    failed: int = 0
    missing: int = 0
    reasons: list[str] = field(default_factory=list)
    references: int = 0
    warm_missing: int = 0

    def miss(self, reason: str) -> None:
        """One more cell not stored, for ``reason``."""
        self.missing += 1
        note_reason(self.reasons, reason)


def ensure_instances(spec: Any, paths: store.SuitePaths, capture: Any = None,
                     progress: bool = True, skip_bad: bool = False) -> InstanceSet:
    """Generate the suite's instances under ``paths.instances`` unless already there and written
    by today's generator for a packaged suite's definition (an out-of-date suite is replaced, with
    a note on stderr; its stale cells are then removed by the identity check), then read them (a
    bad file stops the run, or with ``skip_bad`` is listed and left out)."""
    from c3bench.problems.suites import generate_suite, out_of_date

    manifest_path = paths.instances / "manifest.json"
    known = SUITES.get(spec) if isinstance(spec, str) else spec
    if manifest_path.exists() and isinstance(known, SuiteSpec):
        try:
            why = out_of_date(known, store.read_json_object(manifest_path, "manifest"))
        except SchemaVersionError:
            why = "its manifest.json is damaged"
        if why:
            print(f"note: regenerating the {known.name} instances under {paths.instances}: {why}",
                  file=sys.stderr)
            generate_suite(known, paths.instances, capture=capture, progress=progress)
    if not manifest_path.exists():
        generate_suite(spec, paths.instances, capture=capture, progress=progress)
    return read_instances(paths.instances, skip_bad)


def adopt_instances(source: str | Path, paths: store.SuitePaths,
                    skip_bad: bool = False) -> InstanceSet:
    """Make ``paths.instances`` a copy of the instances below ``source`` (``run --instances``).

    The instance files (and ``source``'s ``manifest.json``; one is written for the copy when
    ``source`` has none) are copied into a hidden sibling and swapped in as a whole, so the
    results folder always holds exactly the instances its cells were run on; the run's stale
    check then drops the cells of instances that changed or left. ``source`` being that
    folder already copies nothing. A bad file stops it, or with ``skip_bad`` is left out.
    """
    source = Path(source)
    target = paths.instances
    found = read_instances(source, skip_bad)
    if target.exists() and source.resolve() == target.resolve():
        return found
    staging = target.with_name(f".instances.adopting-{os.getpid()}-{secrets.token_hex(4)}")
    old = target.with_name(f".instances.old-{os.getpid()}-{secrets.token_hex(4)}")
    try:
        for json_path in found.paths:
            relative = json_path.relative_to(source)
            (staging / relative).parent.mkdir(parents=True, exist_ok=True)
            for path in (json_path, json_path.with_suffix(".npz")):
                shutil.copyfile(path, staging / relative.with_name(path.name))
        staging.mkdir(parents=True, exist_ok=True)
        if (source / MANIFEST).is_file():
            shutil.copyfile(source / MANIFEST, staging / MANIFEST)
        else:
            write_manifest(staging, found.problems,
                           {"name": paths.root.name, "instances_from": str(source.resolve())})
        if target.exists():
            os.rename(target, old)
        os.rename(staging, target)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
        shutil.rmtree(old, ignore_errors=True)
    return read_instances(target, skip_bad)


def _suite_name(suite: Any) -> str:
    """The name of a suite given by name or as a ``SuiteSpec``."""
    return suite if isinstance(suite, str) else str(suite.name)


def _write_run_info(paths: store.SuitePaths, plan: Plan, name: str, jobs: int,
                    scheduler: str | None, options: RunOptions, settings: Sequence[str],
                    precisions: Sequence[str], starts: Sequence[str],
                    sequence_scope: Sequence[tuple[str, str]] | None = None) -> None:
    """``run_info.json``: the machine, the options and the solver table of this run."""
    info = machine_info()
    if Start.SEQUENCE in starts:
        info["sequence_scope"] = "every head" if sequence_scope is None else \
            [f"{family}/{variant}" for family, variant in sequence_scope]
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
                progress: bool, tally: _Tally) -> tuple[dict[str, Reference], dict[str, str]]:
    """The references of ``names``: cached ones reused, the others computed and cached.

    Returns the references and, for instances whose reference task failed for an
    infrastructure reason, that reason (nothing is cached for them: the next run retries).
    """
    references = load_references(paths.references)
    missing = sorted(n for n in names if not reusable(references.get(n), hashes[n],
                                                      plan_for(problems[n].family)))
    lost: dict[str, str] = {}
    if not missing:
        return references, lost
    shared = {n: pool.share(problems[n]) for n in missing}
    tasks: list[Task] = [
        (n, reference_task, (shared[n], hashes[n], plan_for(problems[n].family),
                             options.reference_time_limit, options.preload),
         options.reference_budget()) for n in missing]
    bar = progress_bar(progress, len(tasks), f"references {options.suite}", "instance")
    try:
        for outcome in pool.run(tasks):
            if outcome.ok and isinstance(outcome.value, Reference):
                references[outcome.key] = outcome.value
                tally.references += 1
            else:
                lost[outcome.key] = outcome.reason or "the reference task returned no reference"
            bar.update(1)
    finally:
        bar.close()
        if tally.references:
            save_references(paths.references, references)
    return references, lost


def _load(suite: Any, paths: store.SuitePaths, families: Sequence[str] | None, capture: Any,
          progress: bool, skip_bad: bool = False, source: str | Path | None = None
          ) -> tuple[dict[str, Problem], dict[str, str]]:
    """The suite's problems of ``families`` by name, and every instance's identity id
    (:func:`identify_instances`; the instances copied from ``source`` first when given:
    :func:`adopt_instances`)."""
    problems: dict[str, Problem] = {}
    instances = (adopt_instances(source, paths, skip_bad) if source is not None
                 else ensure_instances(suite, paths, capture, progress, skip_bad))
    for problem in instances.problems:
        if families is None or problem.family in families:
            problems[problem.name] = problem
    return problems, identify_instances(paths, instances)


def identify_instances(paths: store.SuitePaths, instances: InstanceSet) -> dict[str, str]:
    """``instance -> identity id`` (what rows store as ``instance_hash``): the recorded
    identity of each instance where it still holds (same provenance, arrays equal to the
    rounding of :mod:`c3bench.problems.identity`, so a suite regenerated on another machine
    keeps its cells), else a new one; the records are saved beside the cells."""
    known = load_identities(paths.identities)
    manifest: dict[str, Any] | None = None
    try:
        manifest = json.loads((paths.instances / MANIFEST).read_text())
    except (OSError, ValueError):
        manifest = None
    if not isinstance(manifest, dict):
        manifest = None
    current: dict[str, InstanceIdentity] = {}
    for problem, path in zip(instances.problems, instances.paths, strict=True):
        current[problem.name] = identify(path, known.get(problem.name), manifest)
    if current != {name: known.get(name) for name in current}:
        paths.root.mkdir(parents=True, exist_ok=True)
        save_identities(paths.identities, {**known, **current})
    return {name: identity.id for name, identity in current.items()}


ADOPTING = "cells.adopting"
"""Folder (beside ``cells/``) where :func:`_adopt_table` writes the adopted cells before
renaming it onto ``cells/``."""


def _has_cells(paths: store.SuitePaths) -> bool:
    """Whether ``cells/`` holds a cell file."""
    return paths.cells.is_dir() and any(paths.cells.glob("*.json"))


def _adopt_table(paths: store.SuitePaths, planned: set[tuple[str, ...]]) -> int:
    """Keep the rows of a results table that has no cell files (``cells/`` is never
    committed, so a fresh checkout of committed results has only ``results.parquet``): the
    rows of cells this run does not plan become cell files, so that the consolidated table
    keeps them; the planned cells are measured again (a fresh checkout's run measures this
    machine). Without this, running one solver on a fresh checkout replaced the committed
    table of 29 solvers by that solver's rows. Returns the rows adopted.

    All or nothing: the cell files are written into ``cells.adopting/`` (:data:`ADOPTING`)
    and that folder renamed onto ``cells/``, so an interrupt (Ctrl-C, a full disk) leaves no
    partial ``cells/`` whose consolidation would drop the rows not yet written; the next
    run adopts the whole table again.

    Raises :class:`InputError` when the table cannot be read (another schema version, damaged):
    it is never replaced silently.
    """
    if not paths.parquet.exists() or _has_cells(paths):
        return 0
    try:
        table = store.read_results(paths.parquet)
    except ValueError as error:  # SchemaVersionError (every read failure), all naming the file
        raise InputError(f"{error}; it has no cell files to rebuild it from, so this run "
                         f"would replace it: move it away first") from error
    staging = paths.root / ADOPTING
    shutil.rmtree(staging, ignore_errors=True)  # left by a run killed while adopting
    adopted = 0
    try:
        for row in table.to_dict("records"):
            if store.cell_key(row) not in planned:
                store.write_cell(paths, row, cells=staging)
                adopted += 1
        if adopted:
            if paths.cells.is_dir():  # holds no cell file (else nothing is adopted)
                shutil.rmtree(paths.cells)
            os.replace(staging, paths.cells)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    return adopted


def _sweep_stored(paths: store.SuitePaths, hashes: dict[str, str],
                  rerun: bool) -> tuple[set[tuple[str, ...]], int]:
    """Keys of the stored cells to skip, after removing stale ones (and consolidating).

    A cell is stale when its instance changed or left the suite. ``results.parquet`` is
    rewritten right away, so that no later interruption (even ``kill -9``) can leave a
    consolidated table holding rows of deleted cells.
    """
    done: set[tuple[str, ...]] = set()
    kept: list[dict[str, Any]] = []
    stale = 0
    for row in store.read_cells(paths):
        if hashes.get(row["instance"]) != row["instance_hash"]:
            store.remove_cell(paths, row)
            stale += 1
            continue
        kept.append(row)
        if not rerun:
            done.add(store.cell_key(row))
    if paths.cells.is_dir():
        store.write_frame(paths, store.rows_to_frame(kept))
    return done, stale


def _runnable(todo: list[Cell], references: dict[str, Reference], lost: dict[str, str],
              previous: dict[str, str], tally: _Tally) -> list[Cell]:
    """The cells that can run now: their reference (and a warm cell's predecessor's) is
    there or failed as a solve, never lost to an infrastructure fault."""
    runnable: list[Cell] = []
    for cell in todo:
        if cell.start == Start.SEQUENCE:  # its reference is its own reference run
            runnable.append(cell)
            continue
        before = previous.get(cell.instance) if cell.start == Start.WARM else None
        reason = lost.get(cell.instance) or (lost.get(before) if before else None)
        if reason:
            tally.miss(f"reference not computed: {reason}")
            continue
        if before is not None:
            reference = references.get(before)
            if reference is None or reference.warm_start() is None:
                tally.warm_missing += 1
                continue
        runnable.append(cell)
    return runnable


def _cell_tasks(pool: Executor, cells: list[Cell], problems: dict[str, Problem],
                hashes: dict[str, str], references: dict[str, Reference],
                previous: dict[str, str], plan: Plan, options: RunOptions) -> list[Task]:
    """One :func:`run_cell` task per cell (:func:`run_sequence_cell` for a ``sequence``
    cell; problems shared once each)."""
    shared = {n: pool.share(problems[n]) for n in {c.instance for c in cells}}
    tasks: list[Task] = []
    for cell in cells:
        if cell.start == Start.SEQUENCE:
            tasks.append((cell.key, run_sequence_cell,
                          (cell, shared[cell.instance], options, plan.solvers[cell.solver],
                           None, None, hashes[cell.instance]), options.sequence_budget()))
            continue
        ref = references.get(cell.instance)
        warm = references[previous[cell.instance]].warm_start() \
            if cell.start == Start.WARM else None
        tasks.append((cell.key, run_cell,
                      (cell, shared[cell.instance], options, plan.solvers[cell.solver],
                       ref.value() if ref is not None else None, warm,
                       hashes[cell.instance]), options.cell_budget()))
    return tasks


def _run_cells(pool: Executor, paths: store.SuitePaths, tasks: list[Task], name: str,
               progress: bool, on_cell: Callable[[CellOutcome], None] | None,
               tally: _Tally) -> None:
    """Run the cell tasks, storing each row as it arrives; infrastructure faults store
    nothing (they are counted as missing)."""
    bar = progress_bar(progress, len(tasks), f"cells {name}", "cell")
    try:
        for outcome in pool.run(tasks):
            bar.update(1)
            if not outcome.ok or not isinstance(outcome.value, CellOutcome):
                tally.miss(outcome.reason or "the cell task returned no row")
                continue
            result: CellOutcome = outcome.value
            store.write_cell(paths, result.row, result.trace)
            tally.ran += 1
            tally.failed += not result.row["success"]
            if on_cell is not None:
                on_cell(result)
    finally:
        bar.close()


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
    skip_bad: bool = False,
    instances: str | Path | None = None,
    sequence_scope: Sequence[tuple[str, str]] | None = SEQUENCE_SCOPE,
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
    skip_bad
        Leave out bad instance files (the CLI lists them first) instead of stopping.
    instances
        Run this directory of instances instead of a generated suite (``run --instances``):
        they are copied into ``results_dir/<suite>/instances`` (:func:`adopt_instances`;
        ``suite`` then only names the results folder, by default the directory's name).
    sequence_scope
        ``(family, QP variant)`` pairs whose ADMM-sequence heads get ``sequence`` cells when
        ``starts`` has ``sequence`` (:data:`bench.planning.SEQUENCE_SCOPE`; ``None``: every
        ``c3plus_qp`` / ``c3_qp`` head).

    Returns
    -------
    RunSummary
        Counts of what was planned, found stored, run, failed and left missing.

    Raises
    ------
    ResultsLocked
        Another process works in ``results_dir/<suite>/``.
    KeyboardInterrupt
        Ctrl-C, or :class:`~c3bench.problems.errors.Terminated` on SIGTERM: the workers are
        stopped and the finished cells consolidated first.
    """
    name = _suite_name(suite) if suite or instances is None else Path(instances).resolve().name
    paths = store.SuitePaths.of(results_dir, name)
    if instances is None and isinstance(suite, str) and suite not in SUITES \
            and not (paths.instances / "manifest.json").exists():
        raise InputError(f"unknown suite {suite!r}: no instances under {paths.instances} and "
                         f"not one of {', '.join(SUITES)}")
    with exclusive_run(paths.root):
        # connect first: an unreachable scheduler fails before anything is written
        pool: Executor = DaskPool(scheduler) if scheduler else LocalPool(jobs,
                                                                         paths.solver_log)
        tally = _Tally()
        table_adopted = False  # until then, only cell files are consolidated (a table
        # refused or half adopted is never replaced by an empty or partial cells/)
        try:
            registry.import_plugins(preload)
            problems, hashes = _load(suite, paths, families, capture, progress, skip_bad,
                                     instances)
            previous = predecessors(list(problems.values()))
            plan = plan_cells(list(problems.values()), solvers, settings, precisions, starts,
                              previous, sequence_heads(list(problems.values()),
                                                       sequence_scope))
            options = RunOptions(repeats=repeats, time_limit=time_limit,
                                 reference_time_limit=reference_time_limit,
                                 preload=tuple(preload), suite=name)
            adopted = _adopt_table(paths, {cell.key for cell in plan.cells})
            table_adopted = True
            _write_run_info(paths, plan, name, jobs, scheduler, options, settings, precisions,
                            starts, sequence_scope)
            done, stale = _sweep_stored(paths, hashes, rerun)
            todo = [cell for cell in plan.cells if cell.key not in done]
            already = len(plan.cells) - len(todo)
            todo = todo if max_cells is None else todo[:max_cells]
            with open(paths.solver_log, "a") as log:
                log.write(f"=== run started {utc_now()} ===\n")
            # references: for the instances of the cells to run and their predecessors
            needed = {c.instance for c in todo if c.start != Start.SEQUENCE}
            needed |= {previous[c.instance] for c in todo if c.start == Start.WARM}
            references, lost = _references(pool, paths, needed, problems, hashes, options,
                                           progress, tally)
            runnable = _runnable(todo, references, lost, previous, tally)
            tasks = _cell_tasks(pool, runnable, problems, hashes, references, previous, plan,
                                options)
            _run_cells(pool, paths, tasks, name, progress, on_cell, tally)
        except KeyboardInterrupt as stop:  # Ctrl-C, or SIGTERM (Terminated)
            report_stopped(stop, f"{tally.ran} cells", paths.cells, rerun)
            raise
        finally:
            pool.close()
            if (table_adopted and paths.cells.is_dir()) or _has_cells(paths):
                store.consolidate(paths)
    return RunSummary(name, paths.root, len(plan.cells), already, tally.ran, tally.failed,
                      False, plan.skipped_solvers, tally.warm_missing, tally.references,
                      stale, tally.missing, tally.reasons, adopted)
