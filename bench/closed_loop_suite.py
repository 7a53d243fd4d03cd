"""Closed-loop suites and the hyperparameter sweep, run through the benchmark's executors.

A *case* is one closed-loop run: a controller (:class:`bench.closed_loop.ControllerSpec`), task
constants changed from the defaults (``dt``, ``q_cube_pose``), a seed that jitters the ball's
start (seed 0 is the nominal start) and a duration. Cases run in the runner's local process
pool or on a Dask cluster (the same executors as ``c3bench run``); each finished case is
written atomically to ``<results>/closed_loop/<suite>/cells/<case>/`` (``summary.json``,
``steps.parquet``), so an interrupted suite resumes, and the rows are consolidated into
``results.parquet`` / ``results.csv``.

Suites (:data:`CLOSED_LOOP_SUITES`, :class:`ClosedLoopSuite`, defined in
:mod:`bench.closed_loop_configs`): *configurations* x N randomized trials
(:mod:`bench.trials`); ``quick`` (20 trials each) and ``full`` (100).

The sweep (:func:`sweep_cases`) crosses ``dt`` x rho schedule x ``Q_box`` x model ``l`` for C3+
and reports the outcome of every combination (success, or the run's label) as a grid.

Schema of ``results.parquet`` (one row per case): ``case``, ``group``, ``controller``,
``qp_backend``, ``projection``, ``rho_schedule``, ``model_l``, ``samples``, ``weighting``,
``feedback``, ``qp_time_limit`` (s per QP solve, NaN when the QP runs in-process), ``dt``,
``q_cube_pose``, ``seed``, ``duration``, for a suite's trials ``config`` (the configuration's
name) and ``trial`` (its index), ``success``, ``angle_error`` (rad, at the end),
``final_angle`` (rad), ``failure_mode`` (0-5), ``failure_label``, ``failure_reason``,
``median_step_time``, ``p95_step_time``, ``median_lcs_time``, ``median_solve_time`` (s),
``nan_count``, ``fallback_count``, ``steps``, ``qp_failure_steps``, ``qp_failure`` (steps with
a failed QP solve or projection, and the first reason), the physical metrics of
:class:`bench.closed_loop_metrics.PhysicalMetrics` (``success`` is theirs, with
``gentle_success``), for randomized trials (:mod:`bench.trials`) the draw (``ball_dx``,
``ball_dz``, ``cube_side``, ``cube_mass``, ``mu_table``, ``mu_ball``), ``load_average`` (the
1-minute load average when the case ended) and ``error`` (why a case produced no run, else
''); docs/results.md has units. The reports are written by :mod:`bench.closed_loop_report`
(:func:`write_trials_report` for the suites, :func:`write_report` for the sweep).
"""

from __future__ import annotations

import itertools
import json
import math
import os
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from c3bench.bench.closed_loop import (
    ControllerSpec,
    SuccessRules,
    run_closed_loop,
    write_run,
)
from c3bench.bench.closed_loop_configs import (  # the suites, re-exported for the commands
    CLOSED_LOOP_SUITES,
    COMPARISONS,
    ClosedLoopSuite,
    Comparison,
    Configuration,
    SeedClaim,
    SuiteGroup,
    _c3plus,
    l_curve_points,
    reference_ablation,
    suite_configurations,
)
from c3bench.bench.closed_loop_report import (  # the report, re-exported for the commands
    cell_states,
    plot_angles,
    plot_error_bars,
    plot_step_times,
    sweep_grid,
    write_report,
    write_trials_report,
)
from c3bench.bench.progress import progress_bar
from c3bench.problems.config import Config, load_config
from c3bench.problems.instance import atomic_write_bytes
from c3bench.problems.scene import build_scene, home_state
from c3bench.solvers.isolation import IsolationFailed

JUDGED_COLUMNS: tuple[str, ...] = ("contact_step", "pivot_slip")
"""Columns a stored row must have to be reused: each marks a change of how runs are judged.
``contact_step``: contact metrics at the plant's rate; ``pivot_slip``: the success rule that
needs the pivot to stay put, and the labels that came with it (``thrown / tumbled``,
``cube slid``, over-the-top only after a touch), with the cube's height measured at every
plant step (:class:`bench.closed_loop_metrics.PlantContact`)."""

SWEEP_DTS: tuple[float, ...] = (0.05, 0.1)
"""Control periods of the sweep (s) unless chosen otherwise."""
SWEEP_SCHEDULES: tuple[str, ...] = ("geometric", "adaptive")
"""Rho schedules of the sweep unless chosen otherwise."""
SWEEP_Q_BOXES: tuple[float, ...] = (2e4, 2e5)
"""Cube-pose weights ``Q_box`` of the sweep unless chosen otherwise."""
SWEEP_MODEL_LS: tuple[float, ...] = (0.29, 0.30)
"""Model cube sides of the sweep (m) unless chosen otherwise."""


@dataclass(frozen=True)
class Case:
    """One closed-loop run of a suite.

    Attributes
    ----------
    name
        File-safe unique name.
    group
        What the case belongs to in the report (``backends``, ``ablation``, ``robust``,
        ``sweep``).
    spec
        The controller.
    dt, q_cube_pose
        Task constants replacing the defaults (``None``: keep).
    seed
        Jitter of the ball's start: seed 0 is the nominal start, others add ``U[-1, 1] cm``.
    duration
        Seconds simulated (success needs at least 3 s: :mod:`bench.closed_loop_metrics`).
    scene_changes
        The plant's physical constants replacing the defaults (``(name, value)`` pairs of
        :class:`~c3bench.problems.config.SceneConfig`: a randomized trial's cube side, mass,
        friction); the controller keeps the defaults.
    ball_offset
        Added to the ball's start ``(x, z)`` (m).
    hold_time
        Seconds the angle must stay in the band at the end for success.
    configuration, trial
        For a suite's randomized trials: the :class:`Configuration`'s name and the trial
        index (``""`` and -1 otherwise).
    """

    name: str
    group: str
    spec: ControllerSpec
    dt: float | None = None
    q_cube_pose: float | None = None
    seed: int = 0
    duration: float = 3.0
    scene_changes: tuple[tuple[str, float], ...] = ()
    ball_offset: tuple[float, float] = (0.0, 0.0)
    hold_time: float = 1.0
    configuration: str = ""
    trial: int = -1

    def config(self, base: Config) -> Config:
        changes: dict[str, float] = {}
        if self.dt is not None:
            changes["dt"] = self.dt
        if self.q_cube_pose is not None:
            changes["q_cube_pose"] = self.q_cube_pose
        return base.with_mpc(**changes) if changes else base

    def plant_config(self, config: Config) -> Config:
        """The plant's constants: ``config`` with :attr:`scene_changes`."""
        return config.with_scene(**dict(self.scene_changes)) if self.scene_changes else config

    def initial_state(self, config: Config) -> np.ndarray:
        """The plant's start for the plant constants ``config``."""
        x0 = home_state(build_scene(config=config))
        if self.seed:
            rng = np.random.default_rng(self.seed)
            x0[3] += rng.uniform(-0.01, 0.01)
            x0[4] += rng.uniform(-0.01, 0.01)
        x0[3] += self.ball_offset[0]
        x0[4] += self.ball_offset[1]
        return x0


def sweep_cases(dts: Sequence[float] = SWEEP_DTS,
                schedules: Sequence[str] = SWEEP_SCHEDULES,
                q_boxes: Sequence[float] = SWEEP_Q_BOXES,
                model_ls: Sequence[float] = SWEEP_MODEL_LS,
                backend: str = "clarabel") -> list[Case]:
    """C3+ over the grid ``dt x rho schedule x Q_box x model l`` (the reference study's
    hand-drawn map)."""
    cases = []
    for dt, schedule, q_box, side in itertools.product(dts, schedules, q_boxes, model_ls):
        spec = _c3plus(backend, rho_schedule=schedule, model_l=side)
        name = f"sweep-dt{dt:g}-{schedule}-q{q_box:g}-l{side:g}"
        if backend != "clarabel":  # the default keeps its names (and stored runs)
            name += f"-{backend}"
        cases.append(Case(name, "sweep", spec, dt=dt, q_cube_pose=q_box))
    return cases


def case_row(case: Case) -> dict[str, Any]:
    """The identifying columns of a case."""
    spec = case.spec
    fast = spec.controller.startswith("c3plus-fast")
    return {"case": case.name, "group": case.group, "controller": spec.controller,
            "qp_backend": "compiled" if fast else spec.qp_backend,
            "projection": spec.projection if spec.controller == "c3" else "closed_form",
            "rho_schedule": spec.rho_schedule,
            "model_l": float("nan") if spec.robust else spec.model_l,
            "samples": spec.samples if spec.robust else 1,
            "weighting": spec.weighting if spec.robust else False,
            "feedback": spec.feedback,
            "contact_model": spec.contact_model,
            "qp_time_limit": float("nan") if fast or spec.qp_time_limit is None
            else spec.qp_time_limit,
            "dt": case.dt, "q_cube_pose": case.q_cube_pose, "seed": case.seed,
            "duration": case.duration,
            **({"config": case.configuration, "trial": case.trial}
               if case.configuration else {}),
            **({"ball_dx": case.ball_offset[0], "ball_dz": case.ball_offset[1],
                **dict(case.scene_changes)} if case.scene_changes else {})}


def run_case(case: Case, cell_dir: str) -> dict[str, Any]:
    """Run one case and write its cell (:func:`bench.closed_loop.write_run`, summary = the row).

    A case whose controller cannot be built (e.g. its QP backend is unknown or not installed
    here) or crashes outside the control loop becomes a row with ``error`` set and no stored
    cell; it never stops the suite. :class:`~c3bench.solvers.isolation.IsolationFailed` (no
    solver process could start) is raised: the case is missing, not a row.
    """
    base = load_config()
    row = case_row(case)
    config = case.config(base)
    plant = case.plant_config(config)
    row["dt"] = config.mpc.dt
    row["q_cube_pose"] = config.mpc.q_cube_pose
    try:
        trajectory, records, outcome = run_closed_loop(
            case.spec, config, case.duration, x0=case.initial_state(plant),
            plant_config=plant, rules=SuccessRules(hold_time=case.hold_time))
    except IsolationFailed:  # infrastructure, not the case's result: the case is missing
        raise
    except Exception as error:  # noqa: BLE001 - recorded as the case's row
        row.update({"success": False, "error": f"{type(error).__name__}: {error}",
                    "failure_mode": -1, "failure_label": "error", "label": "error"})
        return row
    row.update(outcome.row())
    row["failure_label"] = outcome.failure_label
    row["error"] = ""
    row["load_average"] = os.getloadavg()[0]
    write_run(Path(cell_dir) / case.name, trajectory, records, build_scene(config=plant), row)
    return row


@dataclass
class SuiteRun:
    """Where a closed-loop suite lives and what it did.

    ``missing`` counts the cases of this run that stored nothing because the infrastructure
    failed (a pool worker died outside the run, the Dask scheduler went away);
    ``missing_reasons`` are their first distinct reasons. The next run completes them.
    """

    directory: Path
    rows: list[dict[str, Any]] = field(default_factory=list)
    skipped: int = 0
    missing: int = 0
    missing_reasons: list[str] = field(default_factory=list)


def _same(stored: Any, expected: Any) -> bool:
    """Whether a stored identifying value (read back from JSON) is ``expected``."""
    if isinstance(expected, bool) or isinstance(stored, bool):
        return stored is expected
    if isinstance(expected, int | float) and isinstance(stored, int | float):
        if math.isnan(expected) or math.isnan(stored):
            return math.isnan(expected) and math.isnan(stored)
        return math.isclose(stored, expected, rel_tol=1e-12, abs_tol=0.0)
    return bool(stored == expected)


def _stored(cell_dir: Path, case: Case) -> dict[str, Any] | None:
    """The stored row of ``case``; ``None`` when there is none or it is stale, so that the
    case runs again: a row whose identifying columns (:func:`case_row`: controller, QP
    backend, schedule, model, duration, seed, ...) differ from the case's was run for another
    case under the same name (e.g. ``sweep --qp-backend`` over a folder of another backend's
    runs); a row without one of :data:`JUDGED_COLUMNS` was judged by older rules (e.g. no
    ``contact_step``: before the contact metrics were taken at the plant's rate; no
    ``pivot_slip``: before success required the pivot to stay put)."""
    path = cell_dir / case.name / "summary.json"
    if not path.exists():
        return None
    try:
        row = json.loads(path.read_text())
    except json.JSONDecodeError:
        return None
    if not isinstance(row, dict) or any(column not in row for column in JUDGED_COLUMNS):
        return None
    for key, expected in case_row(case).items():
        if expected is not None and not _same(row.get(key), expected):
            return None
    return row


def _write_table(directory: Path, rows: list[dict[str, Any]], names: Sequence[str]) -> None:
    """``results.parquet`` / ``results.csv``: the rows in case order."""
    order = {name: i for i, name in enumerate(names)}
    rows.sort(key=lambda row: order.get(row["case"], len(order)))
    frame = pd.DataFrame(rows)
    atomic_write_bytes(directory / "results.parquet", frame.to_parquet(index=False))
    atomic_write_bytes(directory / "results.csv", frame.to_csv(index=False).encode())


def run_cases(cases: Iterable[Case], directory: str | Path, jobs: int = 2,
              scheduler: str | None = None, rerun: bool = False,
              progress: bool = True) -> SuiteRun:
    """Run cases (skipping stored ones unless ``rerun``) and consolidate ``results.parquet``.

    The directory is locked for the run (:class:`bench.lock.DirectoryLock`); SIGTERM stops it
    like Ctrl-C (:class:`~c3bench.problems.errors.Terminated`), and the finished cases are
    consolidated either way. A case whose worker failed outside the run is not a row: it is
    retried once, then counted in :attr:`SuiteRun.missing`.
    """
    from c3bench.bench.executors import DaskPool, Executor, LocalPool, note_reason
    from c3bench.bench.lock import exclusive_run, report_stopped

    directory = Path(directory)
    cases = list(cases)
    names = [case.name for case in cases]
    if len(set(names)) != len(names):
        raise ValueError("case names must be unique")
    with exclusive_run(directory):
        cell_dir = directory / "cells"
        cell_dir.mkdir(parents=True, exist_ok=True)
        run = SuiteRun(directory)
        todo = []
        for case in cases:
            stored = None if rerun else _stored(cell_dir, case)
            if stored is not None:
                run.rows.append(stored)
                run.skipped += 1
            else:
                todo.append(case)
        pool: Executor = DaskPool(scheduler) if scheduler else LocalPool(
            jobs, log_path=directory / "solver_output.log")
        watchdog = 1800.0
        tasks = [(case.name, run_case, (case, str(cell_dir)), watchdog) for case in todo]
        bar = progress_bar(progress and bool(tasks), len(tasks),
                           f"closed loop {directory.name}", "run")
        try:
            for result in pool.run(tasks):
                if result.ok and isinstance(result.value, dict):
                    run.rows.append(result.value)
                else:
                    run.missing += 1
                    note_reason(run.missing_reasons, result.reason or "no row returned")
                bar.update(1)
        except KeyboardInterrupt as stop:  # Ctrl-C, or SIGTERM (Terminated)
            report_stopped(stop, f"{len(run.rows)} runs", cell_dir, rerun)
            raise
        finally:
            bar.close()
            pool.close()
            if run.rows:
                _write_table(directory, run.rows, names)
    return run


__all__ = [
    "CLOSED_LOOP_SUITES", "COMPARISONS", "JUDGED_COLUMNS", "Case", "ClosedLoopSuite",
    "Comparison", "Configuration", "SeedClaim", "SuiteGroup", "SuiteRun", "case_row", "cell_states",
    "l_curve_points", "plot_angles", "plot_error_bars", "plot_step_times",
    "reference_ablation", "run_case", "run_cases", "suite_configurations", "sweep_cases",
    "sweep_grid", "write_report", "write_trials_report",
]
