"""Deterministic problem suites along a scripted push of the cube.

A suite is generated in three steps:

1. **Scripted pushes** of the true plant (``l = 0.30``), one per trajectory of the suite
   (:class:`~c3bench.problems.capture.Trajectory`: ball start, contact height): a closed-loop
   PD law on the ball position drives it to the near face of the cube, then pushes forward
   and up, for ``duration`` seconds; state, input, ball-cube distance and the set of touching
   contacts are recorded every ``dt``.
2. **States** of each push (:func:`choose_states`): ``contact_change_states`` of them where the
   set of touching contacts changes (ball reaches the cube, a corner lifts off), the rest
   evenly (``numpy.linspace`` over step indices) among the steps where the ball is within
   ``contact_band`` of the cube, so the subproblems are contact-rich. The manifest records each
   state's trajectory, ball start, step, time and reason.
3. **Instances** of every family are built at each sampled state from the controller's model
   (``model_l``, the reference study's shrunk 0.29 cube) linearised at that state; the QP steps
   in both variants (``bounded`` with the cube's limits,
   :func:`c3bench.problems.limits.cube_limits`, and ``equality``), the ``mpcc`` with the same
   limits; where the suite asks for it (``lcp_general_models``: the ``full`` suite), the
   step's LCP of the model linearised with the Stewart-Trinkle contact model, an
   ``lcp_general`` instance (its ``F`` is not symmetric).
4. **Extra scenes** (``extra_scenes``: the ``full`` suite's spatial scene): steps 1 to 3 again
   in that scene, for the first ``extra_scene_trajectories`` pushes, tags ending
   ``_<scene>``; the manifest's states then say their scene.

A suite is written into a hidden sibling folder and swapped in whole when complete, so a
directory never mixes instances of two generations and an interrupted generation leaves the
previous suite as it was (:mod:`problems.suite_files`).

The ADMM iterates ``(delta, w)`` behind ``c3plus_qp``/``c3_qp``/``projection`` come from a
*capture* function (:mod:`c3bench.problems.capture`, which also holds the suite specifications
:data:`~c3bench.problems.capture.SUITES`). Without one (the default of this module) the
provisional, deterministic :func:`~c3bench.problems.capture.provisional_capture` is used; its
metadata says ``"capture": "provisional"``. The rho schedule is always the reference study's:
``rho_x = 1``, ``rho_u = 0.1``, ``rho_lam = rho_eta = 50 * 2^i`` at ADMM iteration ``i``.

This module runs the plant (MuJoCo); the instance builders it calls
(:mod:`c3bench.problems.families`) are in the plant-free core.
"""

from __future__ import annotations

import json
import shutil
from collections.abc import Iterable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, cast

import mujoco
import numpy as np

from c3bench.problems import families
from c3bench.problems.capture import (
    SUITES,
    Capture,
    CaptureContext,
    SuiteSpec,
    Trajectory,
    provisional_capture,
)
from c3bench.problems.config import Config, load_config
from c3bench.problems.errors import InputError
from c3bench.problems.instance import (
    MANIFEST,
    Problem,
    atomic_write_bytes,
    save_problem,
)
from c3bench.problems.lcs import ContactModel
from c3bench.problems.limits import Limits, cube_limits
from c3bench.problems.linearize import contact_frames, linearize
from c3bench.problems.mpc import MPC, HorizonLayout, with_limits
from c3bench.problems.names import Block, Family, Precision, QPVariant, Variant
from c3bench.problems.scene import (
    Plant,
    Scene,
    build_mpc,
    build_scene,
    check_variant,
    home_state,
)
from c3bench.problems.suite_files import (  # re-exported: the suite's directory
    GENERATOR_VERSION,
    check_target,
    out_of_date,
    staging_dir,
    swap_in,
)

__all__ = [
    "CONTACT_BAND", "CONTACT_CHANGE", "CONTACT_THRESHOLD", "GENERATOR_VERSION", "PushRecord",
    "build_state_instances", "check_target", "choose_states", "contact_changes", "general_lcps",
    "generate_suite", "out_of_date", "qp_limits", "sample_states", "scripted_push",
    "staging_dir", "state_tag", "swap_in",
]

CONTACT_THRESHOLD = 1e-3
"""Gap (m) below which a contact counts as touching when finding contact changes."""


@dataclass
class PushRecord:
    """States (steps+1 x nx) and inputs (steps x nu) of the scripted push, every ``dt``;
    the ball-cube distance and the touching contacts (steps x contacts, ``phi <=``
    :data:`CONTACT_THRESHOLD`) at each recorded state before its input."""

    states: np.ndarray
    inputs: np.ndarray
    ball_distance: np.ndarray
    dt: float
    touching: np.ndarray | None = None


def scripted_push(config: Config | None = None, duration: float = 1.5,
                  variant: str = "planar", ball_start: tuple[float, float] | None = None,
                  push_height: float = 0.75) -> PushRecord:
    """Push the true cube with a PD law on the ball and record every ``dt``.

    Waypoints (relative to the cube's initial centre): approach
    ``(-l/2 - r + 0.005, push_height l)`` (just inside the near face) for 0.4 s, then move the
    ball target forward at 0.2 m/s and up at 0.1 m/s. Force ``u = 100 (p_target - p) - 20 v``,
    clipped to the force limit. ``ball_start`` replaces the config's initial ball centre.
    """
    cfg = config or load_config()
    if ball_start is not None:
        cfg = cfg.with_scene(ball_start=tuple(ball_start))
    plant_scene = build_scene(variant=check_variant(variant), config=cfg)
    plant = Plant(plant_scene)
    x = home_state(plant_scene)
    plant.reset(x)
    dt = cfg.mpc.dt
    steps = round(duration / dt)
    l, r = plant_scene.l, cfg.scene.ball_radius
    ball = plant_scene.ball_position_indices
    approach = np.zeros(len(ball))
    approach[0] = -l / 2 - r + 0.005
    approach[-1] = push_height * l
    states, inputs, distances, touching = [x], [], [], []
    limit = cfg.scene.force_limit
    for k in range(steps):
        t = k * dt
        target = approach.copy()
        if t > 0.4:
            target[0] += 0.2 * (t - 0.4)
            target[-1] += 0.1 * (t - 0.4)
        position = x[ball]
        velocity = x[plant_scene.nq + ball - (plant_scene.nq - plant_scene.nv)]
        u = np.clip(100.0 * (target - position) - 20.0 * velocity, -limit, limit)
        phi = _contact_gaps(plant_scene, x)
        distances.append(float(phi[-1]))
        touching.append(phi <= CONTACT_THRESHOLD)
        x = plant.step(u, dt)
        states.append(x)
        inputs.append(u)
    return PushRecord(np.array(states), np.array(inputs), np.array(distances), dt,
                      np.array(touching))


def _contact_gaps(scene: Scene, x: np.ndarray) -> np.ndarray:
    """Gaps ``phi`` of every contact at state ``x`` (the ball-cube distance last)."""
    scene.data.qpos[:] = x[: scene.nq]
    mujoco.mj_kinematics(scene.model, scene.data)
    mujoco.mj_comPos(scene.model, scene.data)
    return np.array(contact_frames(scene).phi, dtype=float)


def sample_states(record: PushRecord, n_states: int, band: float) -> list[int]:
    """Evenly spaced step indices among the steps with the ball within ``band`` of the cube."""
    if n_states < 1:
        raise ValueError(f"n_states must be >= 1, got {n_states}")
    candidates = np.flatnonzero(record.ball_distance <= band)
    if candidates.size == 0:
        candidates = np.arange(record.inputs.shape[0])
    picks = np.linspace(0, candidates.size - 1, n_states).round().astype(int)
    return sorted({int(candidates[i]) for i in picks})


CONTACT_CHANGE = "contact_change"
"""Reason of a state taken where the set of touching contacts changes."""
CONTACT_BAND = "contact_band"
"""Reason of a state taken evenly among the steps with the ball near the cube."""


def contact_changes(record: PushRecord) -> np.ndarray:
    """Step indices ``k >= 1`` whose touching contacts differ from step ``k - 1``'s."""
    if record.touching is None or len(record.touching) < 2:
        return np.zeros(0, dtype=int)
    differ = np.any(record.touching[1:] != record.touching[:-1], axis=1)
    return np.flatnonzero(differ) + 1


def _even(pool: np.ndarray, count: int) -> list[int]:
    """``count`` distinct entries of ``pool`` spread evenly (all of it when shorter)."""
    if count <= 0 or pool.size == 0:
        return []
    if pool.size <= count:
        return [int(i) for i in pool]
    picks = np.linspace(0, pool.size - 1, count).round().astype(int)
    return [int(pool[i]) for i in picks]


def choose_states(record: PushRecord, n_states: int, band: float,
                  n_changes: int = 0) -> list[tuple[int, str]]:
    """``(step index, reason)`` of the states sampled from one push, by step.

    Up to ``n_changes`` steps evenly among the contact changes (:func:`contact_changes`,
    reason :data:`CONTACT_CHANGE`), the rest evenly among the other steps with the ball within
    ``band`` of the cube (:data:`CONTACT_BAND`; every step when none is).
    """
    if n_states < 1:
        raise ValueError(f"n_states must be >= 1, got {n_states}")
    chosen = {k: CONTACT_CHANGE for k in _even(contact_changes(record), min(n_changes,
                                                                          n_states))}
    near = np.flatnonzero(record.ball_distance <= band)
    if near.size == 0:
        near = np.arange(record.inputs.shape[0])
    rest = np.array([k for k in near if k not in chosen], dtype=int)
    for k in _even(rest, n_states - len(chosen)):
        chosen[k] = CONTACT_BAND
    return sorted(chosen.items())


def _c3_columns(layout: HorizonLayout) -> np.ndarray:
    """Columns of a C3+ step vector that C3's QP keeps (everything but eta)."""
    keep = np.ones(layout.step_size, dtype=bool)
    keep[layout.index(0, Block.ETA)] = False
    return keep


def qp_limits(mpc: MPC) -> Limits:
    """The bounded QP step's limits: ``mpc.limits``, or ``|u| <= force_limit`` without them."""
    return mpc.limits if mpc.limits is not None else Limits.force_only(mpc.nx, mpc.nu,
                                                                        mpc.force_limit)


def _qp_steps(context: CaptureContext, iteration: int, rho: dict[str, float],
              delta: np.ndarray, w: np.ndarray, meta: dict[str, Any], tag: str) -> list[Problem]:
    """The QP steps of one ADMM iterate, every family at every variant of the suite."""
    lcs, mpc = context.lcs, context.mpc
    keep = _c3_columns(HorizonLayout(lcs.nx, lcs.nlam, lcs.nu, lcs.nlam, mpc.horizon))
    c3_rho = {k: v for k, v in rho.items() if k != Block.ETA}
    problems = []
    for variant in context.spec.qp_variants:
        limits = qp_limits(mpc) if variant == QPVariant.BOUNDED else None
        for family, weights, d, ww in ((Family.C3PLUS_QP, rho, delta, w),
                                       (Family.C3_QP, c3_rho, delta[:, keep], w[:, keep])):
            problems.append(families.consensus_qp(
                family, f"{family}-{variant}-{tag}-i{iteration:02d}", lcs, mpc, context.x0,
                weights, d, ww, meta=meta, limits=limits))
    return problems


def build_state_instances(context: CaptureContext, capture: Capture) -> list[Problem]:
    """Every family's instances at one sampled state.

    QP steps at the state's ADMM iterations (:meth:`SuiteSpec.iterations_at`) in every variant
    of ``spec.qp_variants``; projections at its projection iterations and
    ``spec.projection_steps``; the ``mpcc`` (bounded by :func:`qp_limits`) when
    ``context.with_mpcc``; the ``lcp``; the ``lcp_general`` instances of
    ``spec.lcp_general_models`` (:func:`general_lcps`).
    """
    spec, lcs, mpc = context.spec, context.lcs, context.mpc
    layout = HorizonLayout(lcs.nx, lcs.nlam, lcs.nu, lcs.nlam, mpc.horizon)
    tag = state_tag(spec, context.scene.variant, context.state_index, context.trajectory)
    qp_iterations = spec.iterations_at(context.position)
    projection_iterations = spec.iterations_at(context.position, projection=True)
    problems: list[Problem] = []
    for iterate in capture(context):
        meta = dict(context.base_meta)
        meta.update({"admm_iteration": iterate.iteration, "rho": iterate.rho,
                     "capture": iterate.source})
        if iterate.iteration in qp_iterations:
            problems.extend(_qp_steps(context, iterate.iteration, iterate.rho, iterate.delta,
                                      iterate.w, meta, tag))
        if iterate.iteration in projection_iterations:
            weights = families.weight_vector(HorizonLayout(lcs.nx, lcs.nlam, lcs.nu,
                                                           lcs.nlam, 1), iterate.rho)
            for step in spec.projection_steps:
                k = step % mpc.horizon
                for variant in (Variant.C3, Variant.C3PLUS):
                    U = weights.copy()
                    if variant == Variant.C3:
                        U[layout.index(0, Block.ETA)] = 0.0
                    step_meta = dict(meta, horizon_step=k)
                    problems.append(families.projection(
                        f"{Family.PROJECTION}-{variant}-{tag}-i{iterate.iteration:02d}-k{k}", lcs,
                        iterate.projection_v[k], U, variant, meta=step_meta))
    meta = dict(context.base_meta)
    if context.with_mpcc:
        problems.append(families.mpcc(f"{Family.MPCC}-{tag}", lcs, mpc, context.x0, meta=meta,
                                      limits=qp_limits(mpc)))
    problems.append(families.lcp(f"{Family.LCP}-{tag}", lcs, context.x0, context.u_prev, meta=meta))
    problems.extend(general_lcps(context, tag))
    return problems


def general_lcps(context: CaptureContext, tag: str) -> list[Problem]:
    """The ``lcp_general`` instances of one state: for each contact model of
    ``spec.lcp_general_models``, the step's LCP of the controller's model linearised with it at
    ``(x0, u_prev)`` (:func:`c3bench.problems.families.lcp_general_from_lcs`), named
    ``lcp_general-<model>-<tag>`` (``-`` for ``_`` in the model)."""
    out = []
    for model in context.spec.lcp_general_models:
        lcs = linearize(context.scene, context.x0, context.u_prev, context.lcs.dt,
                        cast(ContactModel, model))
        meta = dict(context.base_meta, contact_model=model)
        label = model.replace("_", "-")
        out.append(families.lcp_general_from_lcs(f"{Family.LCP_GENERAL}-{label}-{tag}", lcs,
                                                 context.x0, context.u_prev, meta=meta))
    return out


def generate_suite(
    suite: str | SuiteSpec,
    out_dir: str | Path,
    config: Config | None = None,
    capture: Capture | None = None,
    progress: bool = True,
) -> list[Path]:
    """Generate and save a suite's instances under ``out_dir/<family>/``.

    Returns the written JSON paths. A ``manifest.json`` records the suite, its arguments,
    the sampled states and the instance counts. Regenerating with the same arguments writes
    byte-identical files.

    The suite is written into a hidden sibling folder and swapped in only when complete
    (:func:`swap_in`): a directory that already holds a suite is replaced as a whole (never
    a mix of two generations), and an interrupted or failed generation leaves it as it was.
    An unknown suite name, ``out_dir`` being a file, or ``out_dir`` holding anything but a
    suite's instances is an :class:`InputError` raised before anything is written.
    """
    if isinstance(suite, str) and suite not in SUITES:
        raise InputError(f"unknown suite {suite!r}; known: {', '.join(SUITES)}")
    spec = SUITES[suite] if isinstance(suite, str) else suite
    out = Path(out_dir)
    check_target(out)
    cfg = config or load_config()
    staging = staging_dir(out)
    try:
        written = _write_suite(spec, staging, cfg, capture or provisional_capture, progress)
        swap_in(staging, out)
    except BaseException as error:
        shutil.rmtree(staging, ignore_errors=True)
        if isinstance(error, OSError) and error.strerror and error.filename \
                and Path(error.filename).is_relative_to(staging):
            raise type(error)(error.errno, error.strerror,
                              str(out / Path(error.filename).relative_to(staging))) from error
        raise
    return [out / path.relative_to(staging) for path in written]


def _trajectory_json(index: int, trajectory: Trajectory, cfg: Config) -> dict[str, Any]:
    """How a push was run, for the manifest and the instances' metadata."""
    start = trajectory.ball_start or cfg.scene.ball_start
    return {"trajectory": index, "kind": "scripted_pd_push",
            "ball_start": [float(v) for v in start], "push_height": trajectory.push_height}


def state_tag(spec: SuiteSpec, scene: str, state_index: int, trajectory: int) -> str:
    """The tag of a state in instance names: ``s<step>t<push>``, plus ``_<scene>`` for a
    state of one of ``spec.extra_scenes``."""
    tag = f"s{state_index:03d}t{trajectory}"
    return tag if scene == spec.variant else f"{tag}_{scene}"


@dataclass
class _State:
    """One sampled state: its scene, push and step, and why it was chosen."""

    scene: str
    trajectory: int
    push: Trajectory
    record: PushRecord
    index: int
    reason: str


@dataclass
class _Tally:
    """What a generation wrote: paths, counts by family and by family/variant, the states."""

    written: list[Path]
    counts: dict[str, int]
    variant_counts: dict[str, int]
    chosen: list[dict[str, Any]]

    def add(self, problem: Problem, path: Path) -> None:
        """Count one written instance."""
        self.written.append(path)
        self.counts[problem.family] = self.counts.get(problem.family, 0) + 1
        key = f"{problem.family}/{problem.meta.get('variant', '')}".rstrip("/")
        self.variant_counts[key] = self.variant_counts.get(key, 0) + 1


def _sample_states(spec: SuiteSpec, cfg: Config, scene: str) -> list[_State]:
    """The states of the pushes of ``spec`` run in ``scene`` (:func:`choose_states`): every
    push in ``spec.variant``'s scene, the first ``spec.extra_scene_trajectories`` (``0``:
    all) in an extra scene."""
    pushes = spec.trajectories
    if scene != spec.variant and spec.extra_scene_trajectories:
        pushes = pushes[:spec.extra_scene_trajectories]
    states: list[_State] = []
    for t, push in enumerate(pushes):
        record = scripted_push(cfg, spec.duration, scene, push.ball_start, push.push_height)
        picks = choose_states(record, spec.n_states, spec.contact_band,
                              spec.contact_change_states)
        states.extend(_State(scene, t, push, record, index, reason) for index, reason in picks)
    return states


def _write_suite(spec: SuiteSpec, out: Path, cfg: Config, capture: Capture,
                 progress: bool) -> list[Path]:
    """Write every instance and the manifest of ``spec`` into ``out``: the states of
    ``spec.variant``'s scene, then those of each of ``spec.extra_scenes``."""
    scenes = (spec.variant, *spec.extra_scenes)
    models = {scene: build_scene(l=spec.model_l, variant=check_variant(scene), config=cfg)
              for scene in scenes}
    mpcs = {scene: with_limits(build_mpc(model, cfg.mpc), cube_limits(model))
            for scene, model in models.items()}
    states = [state for scene in scenes for state in _sample_states(spec, cfg, scene)]
    tally = _Tally([], {}, {}, [])
    mpccs: dict[tuple[str, int], int] = {}
    iterator: Iterable[int] = range(len(states))
    if progress:
        from tqdm import tqdm

        iterator = tqdm(iterator, desc=f"generating {spec.name}", unit="state")
    for position in iterator:
        state = states[position]
        key = (state.scene, state.trajectory)
        with_mpcc = (spec.mpcc_per_trajectory == 0
                     or mpccs.get(key, 0) < spec.mpcc_per_trajectory) \
            and (spec.mpcc_trajectories == 0 or state.trajectory < spec.mpcc_trajectories)
        mpccs[key] = mpccs.get(key, 0) + int(with_mpcc)
        context = _context(spec, cfg, state, models[state.scene], mpcs[state.scene], position,
                           with_mpcc, tally)
        for problem in build_state_instances(context, capture):
            tally.add(problem, save_problem(problem, out / problem.family))
    _write_manifest(spec, cfg, out, tally, mpcs)
    return tally.written


def _context(spec: SuiteSpec, cfg: Config, state: _State, model: Scene, mpc: MPC,
             position: int, with_mpcc: bool, tally: _Tally) -> CaptureContext:
    """The capture context of one state (its LCS linearised here); the state's manifest entry
    is appended to ``tally.chosen``."""
    index, t = state.index, state.trajectory
    x0, u_prev = state.record.states[index], state.record.inputs[max(index - 1, 0)]
    lcs = linearize(model, x0, u_prev, cfg.mpc.dt)
    how = dict(_trajectory_json(t, state.push, cfg), state_index=index,
               time=round(index * cfg.mpc.dt, 10), reason=state.reason,
               tag=state_tag(spec, state.scene, index, t))
    if spec.extra_scenes:
        how["scene"] = state.scene
    tally.chosen.append(how)
    base_meta: dict[str, Any] = {
        "suite": spec.name, "scene": state.scene, "l": spec.model_l,
        "l_plant": cfg.scene.cube_side, "dt": cfg.mpc.dt, "T": cfg.mpc.horizon,
        "state_index": index, "time": how["time"], "trajectory": t,
        "ball_start": how["ball_start"], "state_reason": state.reason,
        "seed": spec.seed, "precision": Precision.FLOAT64, "contact_model": lcs.contact_model,
        "target_angle": cfg.mpc.target_angle,
    }
    seed = [spec.seed, t, index] if state.scene == spec.variant else \
        [spec.seed, t, index, 1 + spec.extra_scenes.index(state.scene)]
    return CaptureContext(spec, index, x0, u_prev, lcs, mpc, model,
                          np.random.default_rng(seed), base_meta, position=position,
                          trajectory=t, with_mpcc=with_mpcc)


def _write_manifest(spec: SuiteSpec, cfg: Config, out: Path, tally: _Tally,
                    mpcs: dict[str, MPC]) -> None:
    """``manifest.json``: the suite, states, counts, pushes, limits and constants (with
    ``extra_scenes``, the limits of every scene under ``limits_by_scene`` too)."""
    limits = {scene: mpc.limits.to_json() for scene, mpc in mpcs.items()
              if mpc.limits is not None}
    manifest = {"generator_version": GENERATOR_VERSION, "suite": spec.to_json(),
                "states": tally.chosen, "counts": dict(sorted(tally.counts.items())),
                "counts_by_variant": dict(sorted(tally.variant_counts.items())),
                "trajectories": [_trajectory_json(t, trajectory, cfg)
                                 for t, trajectory in enumerate(spec.trajectories)],
                "limits": limits[spec.variant],
                "config": {"scene": asdict(cfg.scene), "mpc": asdict(cfg.mpc),
                           "limits": asdict(cfg.limits)}}
    if spec.extra_scenes:
        manifest["limits_by_scene"] = limits
    atomic_write_bytes(out / MANIFEST,
                       (json.dumps(manifest, indent=2, sort_keys=True) + "\n").encode())
