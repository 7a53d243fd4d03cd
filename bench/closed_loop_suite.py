"""Closed-loop suites and the hyperparameter sweep, run through the benchmark's executors.

A *case* is one closed-loop run: a controller (:class:`bench.closed_loop.ControllerSpec`), task
constants changed from the defaults (``dt``, ``q_cube_pose``), a seed that jitters the ball's
start (seed 0 is the nominal start) and a duration. Cases run in the runner's local process
pool or on a Dask cluster (the same executors as ``c3bench run``); each finished case is
written atomically to ``<results>/closed_loop/<suite>/cells/<case>/`` (``summary.json``,
``steps.parquet``), so an interrupted suite resumes, and the rows are consolidated into
``results.parquet`` / ``results.csv``.

Suites (:data:`CLOSED_LOOP_SUITES`, :class:`ClosedLoopSuite`): *configurations* (a
controller, a group, a display name) x N randomized trials (:mod:`bench.trials`: ball start
+-3 cm, cube mass +-20 %, friction +-25 %, plant side U[0.28, 0.32] m; seed
:data:`SUITE_SEED`, so trial ``i`` is the same episode in both suites and whatever N, and a
run resumes or extends the stored one):

* ``quick``, 20 trials each: stacked C3+ (shrunk model ``l = 0.29``, geometric rho, 10 ADMM
  iterations) with Clarabel and OSQP and with the true-size model (``l = 0.30``, Clarabel);
  the seed's method (fast robust C3+, 16 samples, LCP weighting, feedback); the fast robust
  variants without feedback, weighted and uniform; the reference study's ablation
  (:func:`reference_ablation`, fast path); the success-vs-``l`` curve (:data:`L_CURVE`: the
  ablation's ``no-samples`` with its side varied). A controller asked for twice runs once
  (:attr:`Configuration.also`): 15 configurations, 300 episodes;
* ``full``, 100 trials each: the same with the QP backends of :data:`FULL_BACKENDS` and C3
  with its MIQP projection (Gurobi, SCIP): 23 configurations.

``--trials N`` (``c3bench closed-loop-suite``) overrides the count. Measured on the 2-core VM
(load average 1-2, this suite the only heavy job): 2 trials of ``quick`` (30 episodes) took
35 s with two workers, the stacked C3+ episodes 3-5 s each (50-100 ms per step), the fast
robust ones 0.6-1.2 s, the fast single-model ones 0.2-0.4 s; under a load average of 4-5
from other jobs, the next 30 episodes took 61 s. The 300 episodes of ``quick`` take about 6
minutes on a quiet machine, 10 on a busy one; ``full`` takes hours (C3's MIQP projection
takes seconds per step).

The sweep (:func:`sweep_cases`) crosses ``dt`` x rho schedule x ``Q_box`` x model ``l`` for C3+
and reports the failure-mode label of every combination as a grid.

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
import os
import sys
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field, replace
from enum import StrEnum
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
from c3bench.bench.closed_loop_report import (  # the report, re-exported for the commands
    cell_states,
    plot_angles,
    plot_error_bars,
    plot_step_times,
    sweep_grid,
    write_report,
    write_trials_report,
)
from c3bench.bench.trials import trial_case
from c3bench.problems.config import Config, load_config
from c3bench.problems.errors import InputError
from c3bench.problems.instance import atomic_write_bytes
from c3bench.problems.scene import build_scene, home_state
from c3bench.solvers.isolation import IsolationFailed

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


def _c3plus(backend: str, **changes: Any) -> ControllerSpec:
    return ControllerSpec(controller="c3plus", qp_backend=backend, **changes)


QUICK_BACKENDS: tuple[str, ...] = ("clarabel", "osqp")
"""QP backends of the stacked C3+ in the quick suite."""
FULL_BACKENDS: tuple[str, ...] = (*QUICK_BACKENDS, "equilibrated_kkt",
                                  "equilibrated_kkt_noridge", "proxqp_sparse", "daqp",
                                  "kkt_ldl", "casadi_hpipm")
"""QP backends of the stacked C3+ in the full suite."""
L_CURVE: tuple[float, ...] = (0.27, 0.28, 0.29, 0.295, 0.30, 0.31)
"""Model cube sides (m) of the success-vs-``l`` curve: fast C3+ with one model and feedback
(the ablation's ``no-samples`` with its side varied; 0.29 and 0.30 are the ablation's
``no-samples`` and ``no-shrunk-model``)."""
QUICK_TRIALS = 20
FULL_TRIALS = 100
SUITE_SEED = 0
"""Seed of the trial draws of both suites (trial ``i`` is the same episode in both)."""


class SuiteGroup(StrEnum):
    """What a configuration of a closed-loop suite stands for (one colour per group in the
    report's figures)."""

    BACKENDS = "backends"
    SEED_METHOD = "seed method"
    ROBUST = "robust"
    ABLATION = "ablation"
    L_CURVE = "l-curve"
    C3 = "c3"


def reference_ablation() -> list[tuple[str, ControllerSpec]]:
    """The reference study's ablation (its bar plot): the full method, one part removed each.

    Full: robust C3+ (16 samples ``l ~ U[0.27, 0.33]``, LCP-error weighting) with low-level
    feedback, on the fast path. Removed in turn: feedback, the samples (one model, the shrunk
    ``l = 0.29``), the samples and the shrunk model (one model of the true ``l = 0.30``), the
    weighting; and the two other rho schedules.
    """
    full = ControllerSpec(controller="c3plus-fast-robust", feedback=True)
    return [
        ("full", full),
        ("no-feedback", replace(full, feedback=False)),
        ("no-samples", replace(full, controller="c3plus-fast", model_l=0.29)),
        ("no-shrunk-model", replace(full, controller="c3plus-fast", model_l=0.30)),
        ("no-weighting", replace(full, weighting=False)),
        ("rho-adaptive", replace(full, rho_schedule="adaptive")),
        ("rho-residual-balancing", replace(full, rho_schedule="residual_balancing")),
    ]


@dataclass(frozen=True)
class Configuration:
    """One controller of a closed-loop suite, run for every trial of the suite.

    Attributes
    ----------
    name
        File-safe unique name: the prefix of its cases and the ``config`` column.
    group
        A :class:`SuiteGroup` value.
    spec
        The controller (the robust ones get a fresh model seed per trial:
        :func:`bench.trials.trial_case`).
    title
        Display name in the report.
    also
        Other roles the same controller plays in the suite (a controller that two parts of
        the suite ask for runs once, e.g. the ablation's ``no-samples`` is the ``l = 0.29``
        point of the success-vs-``l`` curve).
    """

    name: str
    group: str
    spec: ControllerSpec
    title: str
    also: tuple[str, ...] = ()


def _with_role(configurations: list[Configuration], name: str, group: str,
               spec: ControllerSpec, title: str) -> None:
    """Append a configuration, or add ``title`` as another role of an equal controller."""
    for index, known in enumerate(configurations):
        if known.spec == spec:
            configurations[index] = replace(known, also=(*known.also, title))
            return
    configurations.append(Configuration(name, group, spec, title))


def suite_configurations(backends: Sequence[str], with_c3: bool) -> tuple[Configuration, ...]:
    """The configurations of a suite: stacked C3+ per QP backend (shrunk model ``l = 0.29``)
    and with the true-size model; the seed's method; the robust variants; the ablation; the
    success-vs-``l`` curve (:data:`L_CURVE`); with ``with_c3``, C3 with each MIQP projection.
    Controllers asked for twice run once (:attr:`Configuration.also`)."""
    out: list[Configuration] = []
    add = out.append
    for backend in backends:
        add(Configuration(f"c3plus-{backend}-l0.29", SuiteGroup.BACKENDS, _c3plus(backend),
                          f"C3+ {backend}, l 0.29"))
    add(Configuration("c3plus-clarabel-l0.3", SuiteGroup.BACKENDS,
                      _c3plus("clarabel", model_l=0.30), "C3+ clarabel, true l 0.30"))
    ablation = dict(reference_ablation())
    add(Configuration("seed-method", SuiteGroup.SEED_METHOD, ablation["full"],
                      "seed method (fast robust, weighted, feedback)", ("ablation full",)))
    robust = replace(ablation["full"], feedback=False)
    _with_role(out, "robust-weighted", SuiteGroup.ROBUST, robust, "fast robust, weighted")
    _with_role(out, "robust-uniform", SuiteGroup.ROBUST, replace(robust, weighting=False),
               "fast robust, uniform")
    for label, spec in reference_ablation()[1:]:
        _with_role(out, f"ablation-{label}", SuiteGroup.ABLATION, spec, f"ablation {label}")
    for side in L_CURVE:  # the ablation's no-samples with the model side varied
        _with_role(out, f"fast-l{side:g}", SuiteGroup.L_CURVE,
                   replace(ablation["full"], controller="c3plus-fast", model_l=side),
                   f"l-curve {side:g}")
    if with_c3:
        for projection in ("gurobi", "scip"):
            spec = ControllerSpec(controller="c3", qp_backend="clarabel", projection=projection)
            add(Configuration(f"c3-clarabel-{projection}", SuiteGroup.C3, spec,
                              f"C3 clarabel + {projection}"))
    return tuple(out)


def l_curve_points(configurations: Sequence[Configuration]) -> tuple[tuple[float, str], ...]:
    """``(model side, configuration name)`` of the success-vs-``l`` curve: for each side of
    :data:`L_CURVE`, the configuration that runs the ablation's ``no-samples`` controller with
    that side (skipped when the suite has none)."""
    no_samples = dict(reference_ablation())["no-samples"]
    points = []
    for side in L_CURVE:
        spec = replace(no_samples, model_l=side)
        names = [c.name for c in configurations if c.spec == spec]
        if names:
            points.append((side, names[0]))
    return tuple(points)


class SeedClaim(StrEnum):
    """The seed's design choices that the randomized trials test."""

    SHRUNK_MODEL = "shrunk model"
    WEIGHTING = "LCP weighting"
    FEEDBACK = "low-level feedback"


@dataclass(frozen=True)
class Comparison:
    """One test of a :class:`SeedClaim`: configuration ``with_choice`` (the seed's choice)
    against ``without`` (the choice removed), everything else equal; ``setting`` says what
    the two share."""

    claim: SeedClaim
    with_choice: str
    without: str
    setting: str


COMPARISONS: tuple[Comparison, ...] = (
    Comparison(SeedClaim.SHRUNK_MODEL, "c3plus-clarabel-l0.29", "c3plus-clarabel-l0.3",
               "stacked C3+ (clarabel), one model, no feedback: l 0.29 vs 0.30"),
    Comparison(SeedClaim.SHRUNK_MODEL, "ablation-no-samples", "ablation-no-shrunk-model",
               "fast C3+, one model, feedback: l 0.29 vs 0.30"),
    Comparison(SeedClaim.WEIGHTING, "seed-method", "ablation-no-weighting",
               "fast robust C3+, 16 samples, feedback: weighted vs uniform"),
    Comparison(SeedClaim.WEIGHTING, "robust-weighted", "robust-uniform",
               "fast robust C3+, 16 samples, no feedback: weighted vs uniform"),
    Comparison(SeedClaim.FEEDBACK, "seed-method", "robust-weighted",
               "fast robust C3+, 16 samples, weighted: feedback vs none"),
)
"""The pairs the report compares (Newcombe's interval for the difference of the success
rates: :func:`bench.trials.newcombe_interval`)."""


@dataclass(frozen=True)
class ClosedLoopSuite:
    """Configurations x randomized trials (:mod:`bench.trials`).

    Attributes
    ----------
    name
        ``quick`` or ``full``: the directory ``ROOT/closed_loop/<name>/``.
    configurations
        The controllers.
    trials
        Episodes per configuration (``--trials`` overrides it).
    seed
        Seed of the draws: trial ``i`` is the same episode for every configuration and
        whatever the number of trials, so a run with more trials reuses the stored ones.
    duration, hold_time
        Seconds per episode and seconds the angle must stay in the band at the end.
    comparisons
        The claims the report tests (:data:`COMPARISONS`; one naming a configuration the
        suite lacks is skipped).
    """

    name: str
    configurations: tuple[Configuration, ...]
    trials: int
    seed: int = SUITE_SEED
    duration: float = 3.0
    hold_time: float = 1.0
    comparisons: tuple[Comparison, ...] = COMPARISONS

    @property
    def l_curve(self) -> tuple[tuple[float, str], ...]:
        """:func:`l_curve_points` of the configurations."""
        return l_curve_points(self.configurations)

    def cases(self, trials: int | None = None) -> list[Case]:
        """Every episode: ``trials`` (default :attr:`trials`) per configuration, named
        ``<configuration>-<trial, 4 digits>``, trials outermost (an interrupted run has
        the first trials of every configuration rather than all trials of the first)."""
        count = self.trials if trials is None else trials
        if count < 1:
            raise InputError(f"--trials must be an integer >= 1, got {count!r}")
        base = load_config()
        cases = []
        for index in range(count):
            for configuration in self.configurations:
                case = trial_case(configuration.spec, index, self.seed, self.duration,
                                  self.hold_time, base=base)
                cases.append(replace(case, name=f"{configuration.name}-{index:04d}",
                                     group=str(configuration.group),
                                     configuration=configuration.name, trial=index))
        return cases


CLOSED_LOOP_SUITES: dict[str, ClosedLoopSuite] = {
    "quick": ClosedLoopSuite("quick", suite_configurations(QUICK_BACKENDS, with_c3=False),
                             QUICK_TRIALS),
    "full": ClosedLoopSuite("full", suite_configurations(FULL_BACKENDS, with_c3=True),
                            FULL_TRIALS),
}


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


def _stored(cell_dir: Path, case: Case) -> dict[str, Any] | None:
    path = cell_dir / case.name / "summary.json"
    if not path.exists():
        return None
    try:
        return json.loads(path.read_text())
    except json.JSONDecodeError:
        return None


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
    from c3bench.bench.lock import exclusive_run, stopped_message

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
        bar = None
        if progress and tasks:
            from tqdm import tqdm

            bar = tqdm(total=len(tasks), desc=f"closed loop {directory.name}", unit="run")
        try:
            for result in pool.run(tasks):
                if result.ok and isinstance(result.value, dict):
                    run.rows.append(result.value)
                else:
                    run.missing += 1
                    note_reason(run.missing_reasons, result.reason or "no row returned")
                if bar is not None:
                    bar.update(1)
        except KeyboardInterrupt as stop:  # Ctrl-C, or SIGTERM (Terminated)
            print("\n" + stopped_message(stop, f"{len(run.rows)} runs", cell_dir),
                  file=sys.stderr)
            raise
        finally:
            if bar is not None:
                bar.close()
            pool.close()
            if run.rows:
                _write_table(directory, run.rows, names)
    return run


__all__ = [
    "CLOSED_LOOP_SUITES", "COMPARISONS", "Case", "ClosedLoopSuite", "Comparison",
    "Configuration", "SeedClaim", "SuiteGroup", "SuiteRun", "case_row", "cell_states",
    "l_curve_points", "plot_angles", "plot_error_bars", "plot_step_times",
    "reference_ablation", "run_case", "run_cases", "suite_configurations", "sweep_cases",
    "sweep_grid", "write_report", "write_trials_report",
]
