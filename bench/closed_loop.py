"""Closed loop: a controller replans every ``dt`` from the measured MuJoCo state and drives the
true plant (``l = 0.30``) with its first input held for ``dt`` (zero-order hold).

The plant runs at its own step (1 ms); after every plant step a :class:`ContactProbe`
measures the ball-cube signed distance, the ball's height and the height of the cube's lowest
point above the table, so that contact and a cube in the air between two recorded states (one
per control step) are seen (:class:`PlantContact`).

Outcome metrics (docs/closed_loop.md): cube angle error at the end, control-step wall
time (median, p95; LCS build and solve apart), NaN / fallback counts, the physical metrics and
the success rule built on them (:mod:`bench.closed_loop_metrics`: peak angle, contact times,
impact speed, hold time, penetration, clipped inputs, plan consistency), and an automatic
failure-mode label computed from the trajectory by :func:`label_failure_mode`.

Failure-mode rules (thresholds in :class:`FailureRules`), checked in this order:

0. **success** (the older end-time rule, kept as a label; ``success`` itself is the physical
   metrics' rule): ``|theta(T_end) - theta*| <= success_tolerance`` and the pivot (far
   bottom corner) moved less than ``pivot_slip`` in x.
4. **no motion**: ``max |theta| < still_angle`` and the cube centre moved less than
   ``still_shift``.
2. **backing off**: before the cube first tips past ``tip_start``, the ball retreats by more than
   ``back_off`` in -x from its starting x.
1. **fast sliding past the edge**: the ball rises above the cube's top face (in the cube frame)
   while its speed exceeds ``fast_speed``, or the pivot slips by more than ``pivot_slip``.
3. **whack and lose contact**: the angle peaked above ``whack_fraction * theta*``, the ball was
   farther than ``contact_gap`` from the cube for at least ``lost_time`` in all after the peak
   (counted at every plant step when ``simulate`` measured it: :class:`ContactProbe`), and the
   final angle is at least ``fall_back`` below the peak.
5. **unlabelled**: none of the above (reported as such, never forced into a mode).

The controllers (:class:`ControllerSpec`, :func:`make_policy`, the per-solve time limit of
their QP backends) live in :mod:`bench.closed_loop_policy` and are re-exported here.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import mujoco
import numpy as np

from c3bench.bench.closed_loop_checks import check_backends, control_steps
from c3bench.bench.closed_loop_labels import LabelRules, physical_label
from c3bench.bench.closed_loop_metrics import (
    PhysicalMetrics,
    PlantContact,
    RunSignals,
    SuccessRules,
    physical_metrics,
    pivot_slip,
)
from c3bench.bench.closed_loop_policy import (
    CONTROLLERS,
    FAST_CONTROLLERS,
    ROBUST_CONTROLLERS,
    ContactModelOption,
    ControllerSpec,
    Policy,
    make_policy,
    pd_tracking_law,
    planned_ball_state,
    step_backends,
    step_failures,
)
from c3bench.bench.closed_loop_probe import (  # ContactProbe re-exported
    GAP_RANGE,
    ContactProbe,
    box_clearance,
)
from c3bench.bench.closed_loop_records import (  # re-exported
    records_frame,
    render_run,
    run_summary,
    write_run,
)
from c3bench.bench.progress import progress_bar
from c3bench.problems.config import Config, load_config
from c3bench.problems.scene import Plant, Scene, build_scene, home_state
from c3bench.solvers.isolation import IsolationFailed
from c3bench.solvers.timing import single_thread_blas

__all__ = [
    "CONTROLLERS", "FAILURE_MODES", "FAST_CONTROLLERS", "ROBUST_CONTROLLERS",
    "ClosedLoopOutcome", "ContactModelOption", "ContactProbe", "ControllerSpec", "FailureRules",
    "PhysicalMetrics", "PlantContact", "Policy", "StepRecord", "SuccessRules", "Trajectory",
    "advance", "cube_geometry", "label_failure_mode", "make_policy", "pd_tracking_law",
    "planned_ball_state", "records_frame", "render_run", "run_closed_loop", "run_signals",
    "run_summary", "simulate", "step_backends", "step_failures", "summarise", "write_run",
]

FAILURE_MODES: dict[int, str] = {
    0: "success",
    1: "fast sliding past the edge",
    2: "backing off first",
    3: "whack, then contact lost",
    4: "no motion",
    5: "unlabelled failure",
}


@dataclass(frozen=True)
class FailureRules:
    """Thresholds of the failure-mode labels (see the module docstring)."""

    pivot_slip: float = SuccessRules.pivot_slip  # the success rule's; summarise passes its own
    still_angle: float = 0.05
    still_shift: float = 0.01
    tip_start: float = 0.05
    back_off: float = 0.03
    fast_speed: float = 0.5
    whack_fraction: float = 0.5
    contact_gap: float = 0.02
    lost_time: float = 0.2
    fall_back: float = 0.1


@dataclass
class Trajectory:
    """What the plant did: times (N), states (N x nx), inputs (N-1 x nu) and ball-cube gaps (N)
    at the recorded states (one per control step), and ``plant``: the contact measured at
    every plant step, per control period (``None`` when not measured)."""

    times: np.ndarray
    states: np.ndarray
    inputs: np.ndarray
    ball_gap: np.ndarray
    plant: PlantContact | None = None


def cube_geometry(scene: Scene, x: np.ndarray, data: mujoco.MjData | None = None
                  ) -> dict[str, Any]:
    """Far bottom corner, ball position in the cube frame, ball-cube distance and the height
    of the cube's lowest point above the table (``clearance``, m) at ``x``.

    ``data``: a scratch ``MjData`` of ``scene.model`` to work in (its positions are
    overwritten); a new one is made per call without it (about 0.4 ms, most of the cost).
    """
    data = mujoco.MjData(scene.model) if data is None else data
    data.qpos[:] = x[: scene.nq]
    mujoco.mj_kinematics(scene.model, data)
    corners = data.site_xpos[scene.corner_sites]
    far = corners[np.argmax(corners[:, 0])].copy()
    cube = scene.body("cube")
    rotation = data.xmat[cube].reshape(3, 3)
    ball_world = data.xpos[scene.body("ball")]
    ball_local = rotation.T @ (ball_world - data.xpos[cube])
    box = scene.geom("cube")
    gap = mujoco.mj_geomDistance(scene.model, data, scene.geom("ball"), box, GAP_RANGE, None)
    clearance = box_clearance(data.geom_xpos[box].item(2), data.geom_xmat[box][6:9].tolist(),
                              scene.model.geom_size[box].tolist(),
                              float(scene.config.scene.table_height))
    return {"far_corner": far, "ball_local": ball_local, "ball_gap": float(gap),
            "clearance": clearance}


def _state_geometry(scene: Scene, states: np.ndarray) -> list[dict[str, Any]]:
    """:func:`cube_geometry` at every state (one scratch ``MjData`` for all)."""
    scratch = mujoco.MjData(scene.model)
    return [cube_geometry(scene, x, scratch) for x in states]


def advance(plant: Plant, u: np.ndarray, duration: float, probe: ContactProbe,
            law: Callable[[np.ndarray, float, np.ndarray], np.ndarray] | None = None
            ) -> np.ndarray:
    """Step ``plant`` for ``duration`` s with :meth:`Plant.step` (``u`` held) or, with ``law``,
    :meth:`Plant.step_with` (``law(x, s, u)`` every plant step), ``probe`` observing every
    plant step; return the state."""
    probe.watch(plant.data)
    if law is None:
        return plant.step(u, duration, probe.observe)
    return plant.step_with(lambda x, s: law(x, s, u), duration, probe.observe)


def label_failure_mode(trajectory: Trajectory, scene: Scene, target_angle: float,
                       success_tolerance: float, rules: FailureRules | None = None,
                       geometry: Sequence[dict[str, Any]] | None = None) -> tuple[int, str]:
    """The failure mode (0 = success) of a closed-loop trajectory, with the rule that fired.

    ``geometry``: :func:`cube_geometry` at every recorded state (computed here without it).
    """
    rules = rules or FailureRules()
    states = trajectory.states
    angles = np.array([scene.cube_angle(x) for x in states])
    if geometry is None:
        geometry = _state_geometry(scene, states)
    slip = pivot_slip(np.array([g["far_corner"][0] for g in geometry]))
    error = abs(angles[-1] - target_angle)
    if error <= success_tolerance and slip < rules.pivot_slip:
        return 0, f"|theta - theta*| = {error:.3f} rad at the end, pivot slip {slip:.3f} m"
    centre = states[:, scene.cube_pose_indices[0]]
    if np.max(np.abs(angles)) < rules.still_angle and \
            np.max(np.abs(centre - centre[0])) < rules.still_shift:
        return 4, f"max |theta| {np.max(np.abs(angles)):.3f} rad, cube barely moved"
    ball_x = states[:, scene.ball_position_indices[0]]
    tipped = np.flatnonzero(angles > rules.tip_start)
    before = slice(0, int(tipped[0]) if tipped.size else len(states))
    retreat = float(ball_x[0] - np.min(ball_x[before]))
    if retreat > rules.back_off:
        return 2, f"ball backed off {retreat:.3f} m before the cube tipped"
    half = scene.l / 2
    nq = scene.nq
    ball_velocity = states[:, nq + scene.ball_position_indices - (scene.nq - scene.nv)]
    speed = np.linalg.norm(ball_velocity, axis=1)
    above = np.array([g["ball_local"][2] > half for g in geometry])
    if np.any(above & (speed > rules.fast_speed)) or slip >= rules.pivot_slip:
        return 1, (f"ball over the top edge at up to {speed[above].max(initial=0):.2f} m/s"
                   if np.any(above) else f"pivot slipped {slip:.3f} m")
    peak = int(np.argmax(angles))
    if angles[peak] > rules.whack_fraction * target_angle and \
            angles[-1] < angles[peak] - rules.fall_back:
        away = _time_away(trajectory, peak, rules.contact_gap)
        if away >= rules.lost_time:
            return 3, (f"peak {angles[peak]:.2f} rad, contact lost {away:.2f} s, "
                       f"fell back to {angles[-1]:.2f} rad")
    return 5, f"final error {error:.3f} rad; no rule matched"


def _time_away(trajectory: Trajectory, start: int, gap: float) -> float:
    """Time the ball spent farther than ``gap`` from the cube after recorded state ``start``:
    at the plant's rate when ``simulate`` measured it for that threshold, else from the
    recorded states (each standing for one control period)."""
    plant = trajectory.plant
    if plant is not None and math.isclose(plant.away_gap, gap, rel_tol=1e-12):
        return plant.count(float(np.sum(plant.away_time[start:]))) * plant.plant_step
    gaps = trajectory.ball_gap[start:]
    dt = float(np.median(np.diff(trajectory.times))) if len(trajectory.times) > 1 else 0.0
    return float(np.sum(gaps > gap) * dt)


@dataclass
class StepRecord:
    """One control step of a closed-loop run.

    ``qp_failures`` counts the controller's failed sub-solves in the step (a QP step or a
    projection whose backend raised, rejected the instance, overran the per-step time limit or
    returned no or a non-finite answer; the ADMM stops at the first, so 0 or 1), with
    ``qp_failure`` the first one's reason; ``fallback_reason`` says why the last safe input
    was held (``""`` when ``ok``). ``commanded`` is the controller's input before any clip
    (its unclipped ``u_0``); ``plan_next``, ``lcs_next`` and ``plan_input`` are the plan's
    ``x_1``, the LCS rollout of its ``u_0`` and that ``u_0`` (``None`` without a plan;
    :mod:`bench.closed_loop_metrics`).
    """

    time: float
    state: np.ndarray
    input: np.ndarray
    lcs_time: float
    solve_time: float
    ok: bool
    nan_count: int
    info: dict[str, float] = field(default_factory=dict)
    qp_failures: int = 0
    qp_failure: str = ""
    fallback_reason: str = ""
    commanded: np.ndarray | None = None
    plan_next: np.ndarray | None = None
    lcs_next: np.ndarray | None = None
    plan_input: np.ndarray | None = None


@dataclass
class ClosedLoopOutcome:
    """The summary of a run."""

    success: bool
    angle_error: float
    final_angle: float
    failure_mode: int
    failure_reason: str
    median_step_time: float
    p95_step_time: float
    median_lcs_time: float
    median_solve_time: float
    nan_count: int
    fallback_count: int
    steps: int
    qp_failure_steps: int = 0
    qp_failure: str = ""
    metrics: PhysicalMetrics | None = None
    label: str = ""
    label_reason: str = ""

    @property
    def failure_label(self) -> str:
        return FAILURE_MODES[self.failure_mode]

    def row(self) -> dict[str, Any]:
        """The outcome as one flat row: its fields and the physical metrics'."""
        from dataclasses import asdict, fields

        row = {f.name: getattr(self, f.name) for f in fields(self) if f.name != "metrics"}
        if self.metrics is not None:
            row.update(asdict(self.metrics))
        return row


def _plan_fields(info: dict[str, Any], ok: bool) -> dict[str, np.ndarray | None]:
    """The plan arrays of a policy's ``info`` (``None`` when missing or the step failed)."""
    out: dict[str, np.ndarray | None] = {}
    for key in ("plan_next", "lcs_next", "plan_input"):
        value = info.get(key)
        out[key] = np.array(value, dtype=float) if ok and value is not None else None
    return out


def simulate(policy: Policy, config: Config | None = None, duration: float = 2.0,
             x0: np.ndarray | None = None, plant_scene: Scene | None = None,
             progress: Callable[[int, int], None] | None = None,
             contact_gap: float | None = None, away_gap: float | None = None,
             air_gap: float | None = None) -> tuple[Trajectory, list[StepRecord]]:
    """Run ``policy`` on the MuJoCo plant for ``duration`` seconds, replanning every ``dt``.

    After every plant step a :class:`ContactProbe` updates the period's contact statistics
    (``Trajectory.plant``): touching at signed distance ``<= contact_gap`` (default
    :attr:`SuccessRules.contact_gap`), away at ``> away_gap`` (default
    :attr:`FailureRules.contact_gap`), and the cube airborne when its lowest point is more
    than ``air_gap`` above the table (default
    :attr:`~bench.closed_loop_labels.LabelRules.air_gap`).

    A policy that returns a non-finite input, or raises, is a failed step: the last safe input
    is held instead and the step is counted (``ok = False``, with its ``fallback_reason``).
    :class:`~c3bench.solvers.isolation.IsolationFailed` (no solver process could be started)
    is an infrastructure fault, not a step: it stops the run.
    ``duration`` must be a positive multiple of ``dt`` (:class:`InputError` otherwise).
    """
    cfg = config or load_config()
    scene = plant_scene or build_scene(config=cfg)
    plant = Plant(scene)
    state = home_state(scene) if x0 is None else np.asarray(x0, dtype=float)
    plant.reset(state)
    dt = cfg.mpc.dt
    steps = control_steps(duration, dt)
    last_safe = np.zeros(scene.nu)
    records: list[StepRecord] = []
    scratch = mujoco.MjData(scene.model)
    probe = ContactProbe(scene, SuccessRules().contact_gap if contact_gap is None
                         else contact_gap,
                         FailureRules().contact_gap if away_gap is None else away_gap,
                         LabelRules().air_gap if air_gap is None else air_gap)
    states, inputs, times = [state], [], [0.0]
    gaps = [cube_geometry(scene, state, scratch)["ball_gap"]]
    for k in range(steps):
        t = k * dt
        start = time.perf_counter()
        try:
            u, info = policy(state, t)
            u = np.asarray(u, dtype=float)
        except IsolationFailed:  # no solver process could start: not the controller's doing
            raise
        except Exception as error:  # noqa: BLE001 - a crashing controller is a counted step
            u, info = np.full(scene.nu, np.nan), {
                "ok": False, "fallback_reason": f"controller raised "
                                                f"{type(error).__name__}: {error}"}
        wall = time.perf_counter() - start
        nan_count = int(info.get("nan_count", 0))
        ok = bool(info.get("ok", True))
        reason = str(info.get("fallback_reason", "")) if not ok else ""
        commanded = np.asarray(info.get("commanded", u), dtype=float)
        if u.shape != (scene.nu,) or not np.all(np.isfinite(u)):
            nan_count += 1
            ok = False
            reason = reason or f"non-finite or mis-shaped input {u.tolist()}"
            u = last_safe
        else:
            u = np.clip(u, -cfg.scene.force_limit, cfg.scene.force_limit)
            if ok:
                last_safe = u
        lcs_time = float(info.get("lcs_time", 0.0))
        solve_time = float(info.get("solve_time", wall - lcs_time))
        scalars = {key: float(value) for key, value in info.items()
                   if isinstance(value, int | float) and key not in
                   ("lcs_time", "solve_time", "ok", "nan_count", "qp_failures")}
        scalars["wall_time"] = wall
        records.append(StepRecord(t, state.copy(), u.copy(), lcs_time, solve_time, ok,
                                  nan_count, scalars,
                                  qp_failures=int(info.get("qp_failures", 0)),
                                  qp_failure=str(info.get("qp_failure", "")),
                                  fallback_reason=reason,
                                  commanded=commanded.copy()
                                  if ok and commanded.shape == u.shape else None,
                                  **_plan_fields(info, ok)))
        law = info.get("control_law") if ok else None
        probe.begin(t)
        state = advance(plant, u, dt, probe, law or None)
        probe.end()
        states.append(state)
        inputs.append(u)
        gaps.append(cube_geometry(scene, state, scratch)["ball_gap"])
        times.append((k + 1) * dt)
        if progress is not None:
            progress(k + 1, steps)
    trajectory = Trajectory(np.array(times), np.array(states), np.array(inputs),
                            np.array(gaps), probe.record())
    return trajectory, records


def run_signals(trajectory: Trajectory, records: list[StepRecord], scene: Scene,
                geometry: Sequence[dict[str, Any]] | None = None) -> RunSignals:
    """The per-state signals of a run that :func:`physical_metrics` needs (``geometry``: as
    in :func:`label_failure_mode`)."""
    states = trajectory.states
    ball = scene.ball_position_indices
    velocity = states[:, scene.nq + ball - (scene.nq - scene.nv)]
    nx = scene.nx

    def stacked(name: str, width: int) -> np.ndarray:
        rows = [getattr(r, name) for r in records]
        return np.array([np.full(width, np.nan) if v is None else v for v in rows]
                        ).reshape(len(records), width)

    commanded = np.array([r.input if r.commanded is None else r.commanded for r in records]
                         ).reshape(len(records), scene.nu)
    if geometry is None:
        geometry = _state_geometry(scene, states)
    half = scene.l / 2
    over_top = [bool(g["ball_local"][2] > half and np.all(np.abs(g["ball_local"][:2]) <= half))
                for g in geometry]  # above the top face's plane, within its extent
    return RunSignals(
        times=trajectory.times,
        angles=np.array([scene.cube_angle(x) for x in states]),
        ball_gap=trajectory.ball_gap,
        ball_height=states[:, ball[-1]] - scene.config.scene.ball_radius
        - scene.config.scene.table_height,
        ball_speed=np.linalg.norm(velocity, axis=1),
        commanded=commanded, force_limit=scene.config.scene.force_limit,
        cube_side=scene.l, plan_next=stacked("plan_next", nx),
        lcs_next=stacked("lcs_next", nx), states=states,
        angle_index=2,  # planar: theta is x[2]
        ball_above_top=np.array(over_top, dtype=bool),
        pivot_x=np.array([g["far_corner"][0] for g in geometry]),
        cube_clearance=np.array([g["clearance"] for g in geometry]), plant=trajectory.plant)


def summarise(trajectory: Trajectory, records: list[StepRecord], scene: Scene,
              config: Config, rules: SuccessRules | None = None) -> ClosedLoopOutcome:
    """Outcome metrics of a run (see the module docstring): ``success`` is the physical
    metrics' (:mod:`bench.closed_loop_metrics`, under ``rules``), whose pivot slip threshold
    the failure modes take too."""
    target = config.mpc.target_angle
    geometry = _state_geometry(scene, trajectory.states)  # once, for the modes and the metrics
    mode, reason = label_failure_mode(
        trajectory, scene, target, config.mpc.success_tolerance,
        FailureRules(pivot_slip=(rules or SuccessRules()).pivot_slip), geometry)
    signals = run_signals(trajectory, records, scene, geometry)
    metrics = physical_metrics(signals, target, config.mpc.success_tolerance, rules)
    label, label_reason = physical_label(metrics, signals, target, success_rules=rules)
    final = scene.cube_angle(trajectory.states[-1])
    walls = np.array([r.info.get("wall_time", r.lcs_time + r.solve_time) for r in records])
    failed = [r for r in records if r.qp_failures]
    return ClosedLoopOutcome(
        success=metrics.success,
        angle_error=abs(final - target),
        final_angle=final,
        failure_mode=mode,
        failure_reason=reason,
        median_step_time=float(np.median(walls)),
        p95_step_time=float(np.percentile(walls, 95)),
        median_lcs_time=float(np.median([r.lcs_time for r in records])),
        median_solve_time=float(np.median([r.solve_time for r in records])),
        nan_count=int(sum(r.nan_count for r in records)),
        fallback_count=int(sum(not r.ok for r in records)),
        steps=len(records),
        qp_failure_steps=len(failed),
        qp_failure=failed[0].qp_failure if failed else "",
        metrics=metrics,
        label=label,
        label_reason=label_reason,
    )


def run_closed_loop(spec: ControllerSpec, config: Config | None = None,
                    duration: float = 2.0, progress: bool = False,
                    x0: np.ndarray | None = None, plant_config: Config | None = None,
                    rules: SuccessRules | None = None
                    ) -> tuple[Trajectory, list[StepRecord], ClosedLoopOutcome]:
    """Drive the true plant with the controller of ``spec`` for ``duration`` seconds.

    ``x0`` is the plant's initial state (default: :func:`problems.scene.home_state`). The
    backends and the duration are checked first (:class:`InputError`), and each QP solve
    runs under ``spec.qp_time_limit`` (:func:`step_backends`). ``config`` is the controller's
    (its model, MPC and control period); ``plant_config`` the plant's (default: the same),
    e.g. a randomized trial's cube side, mass and friction. ``rules``: the success rule.
    """
    cfg = config or load_config()
    steps = control_steps(duration, cfg.mpc.dt)
    check_backends(spec)
    plant_cfg = plant_config or cfg
    if plant_cfg.mpc != cfg.mpc:
        plant_cfg = replace(plant_cfg, mpc=cfg.mpc)
    plant_scene = build_scene(config=plant_cfg)
    with step_backends(spec) as backends:
        policy = make_policy(spec, cfg, backends)
        trajectory, records = _simulate_with_progress(
            spec, policy, cfg, duration, steps, plant_scene, progress, x0,
            (rules or SuccessRules()).contact_gap)
    return trajectory, records, summarise(trajectory, records, plant_scene, cfg, rules)


def _simulate_with_progress(spec: ControllerSpec, policy: Policy, cfg: Config,
                            duration: float, steps: int, plant_scene: Scene, progress: bool,
                            x0: np.ndarray | None, contact_gap: float
                            ) -> tuple[Trajectory, list[StepRecord]]:
    """:func:`simulate` with one BLAS thread and, when ``progress``, a progress bar."""
    bar = progress_bar(progress, steps, spec.label(), "step")

    def callback(done: int, total: int) -> None:
        bar.update(1)

    try:
        with single_thread_blas():  # small dense solves: one BLAS thread is fastest
            trajectory, records = simulate(policy, cfg, duration, x0=x0,
                                           plant_scene=plant_scene,
                                           progress=callback if progress else None,
                                           contact_gap=contact_gap)
    finally:
        bar.close()
    return trajectory, records
