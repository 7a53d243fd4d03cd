"""What a suite captures: suite specifications, the rho schedule and the ADMM iterate types.

A suite (:func:`c3bench.problems.suites.generate_suite`) builds, at each sampled state, the
instances of every family. The ADMM iterates ``(delta, w)`` behind ``c3plus_qp``/``c3_qp``/
``projection`` come from a *capture* function (:data:`Capture`): it receives a
:class:`CaptureContext` and returns one :class:`CapturedIterate` per ADMM iteration. The
controller's capture is :func:`c3bench.solvers.c3.controller_capture`; without one the
deterministic :func:`provisional_capture` is used (metadata ``"capture": "provisional"``).

The rho schedule is always the reference study's (:func:`reference_rho`): ``rho_x = 1``,
``rho_u = 0.1``, ``rho_lam = rho_eta = 50 * 2^i`` at ADMM iteration ``i``.

Part of the plant-free core: imports neither MuJoCo nor CasADi (the scene a context carries is
typed only for the type checker).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import asdict, dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from c3bench.problems.lcs import CONTACT_MODELS, LCS
from c3bench.problems.mpc import MPC, HorizonLayout
from c3bench.problems.names import (
    QP_VARIANTS,
    REFERENCE_RHO0,
    REFERENCE_RHO_BLOCKS,
    REFERENCE_RHO_FACTOR,
    Block,
    QPVariant,
)

SCENE_VARIANTS: tuple[str, ...] = ("planar", "spatial")
"""Scene variants a suite may use: :data:`c3bench.problems.scene.VARIANTS`, repeated here
because this module must not import the scene (MuJoCo)."""

if TYPE_CHECKING:  # type only: importing the scene at run time would load MuJoCo
    from c3bench.problems.scene import Scene


@dataclass(frozen=True)
class Trajectory:
    """One scripted push a suite samples states from
    (:func:`c3bench.problems.suites.scripted_push`).

    Attributes
    ----------
    ball_start
        Initial ball centre ``(x, z)`` (m); ``None``: the config's ``ball_start``.
    push_height
        Height of the approach point on the near face, as a fraction of the cube side.
    """

    ball_start: tuple[float, float] | None = None
    push_height: float = 0.75

    def __post_init__(self) -> None:
        if not 0.0 < self.push_height < 1.0:
            raise ValueError(f"push_height must be in (0, 1), got {self.push_height!r}")


@dataclass(frozen=True)
class SuiteSpec:
    """What a suite contains.

    Attributes
    ----------
    name
        ``quick``, ``default`` or ``full``.
    n_states
        States sampled along each trajectory.
    admm_iterations
        ADMM iterations at which QP steps are captured.
    projection_iterations, projection_steps
        ADMM iterations and horizon steps at which projections are captured.
    model_l
        Cube side of the controller's model.
    variant
        Scene variant.
    seed
        Seed of every random choice.
    duration
        Length of the scripted push (s).
    contact_band
        Ball-cube distance (m) below which a recorded step may be sampled.
    trajectories
        The scripted pushes (different ball starts and push heights) states are sampled from.
    contact_change_states
        Of the ``n_states`` of a trajectory, how many are taken at steps where the set of
        touching contacts changes (the rest evenly in the contact band).
    iterations_per_state, projection_iterations_per_state
        ``0``: every iteration of ``admm_iterations`` (``projection_iterations``) at every
        state; ``m > 0``: ``m`` of them per state, rotating through the list from state to
        state (state ``j`` takes entries ``j m, ..., j m + m - 1`` modulo its length), so a
        small suite still covers early and late ADMM iterates.
    mpcc_per_trajectory
        ``0``: an ``mpcc`` instance at every state; ``m > 0``: at the first ``m`` states of
        each trajectory.
    mpcc_trajectories
        ``0``: ``mpcc`` instances on every trajectory; ``k > 0``: on the first ``k`` only (its
        reference, a global MINLP solve, is the costliest part of a small suite).
    qp_variants
        Variants of the QP-step families (:class:`~c3bench.problems.names.QPVariant`),
        ``bounded`` first.
    extra_scenes
        Scene variants (``spatial``) whose pushes, states and instances are generated too, in
        addition to ``variant``'s, by the same rules; their tags end ``_<scene>``
        (``s012t0_spatial``) and their metadata says the scene.
    extra_scene_trajectories
        ``0``: the extra scenes run every push of ``trajectories``; ``k > 0``: the first ``k``
        only (a spatial QP step is about six times the bytes of a planar one).
    lcp_general_models
        Contact models (:data:`c3bench.problems.lcs.CONTACT_MODELS`) whose LCS, linearised at
        every state, gives an ``lcp_general`` instance of the step's LCP
        (:func:`c3bench.problems.families.lcp_general_from_lcs`); ``()``: none.
    """

    name: str
    n_states: int
    admm_iterations: tuple[int, ...]
    projection_iterations: tuple[int, ...]
    projection_steps: tuple[int, ...] = (0, -1)
    model_l: float = 0.29
    variant: str = "planar"
    seed: int = 0
    duration: float = 1.5
    contact_band: float = 0.02
    trajectories: tuple[Trajectory, ...] = (Trajectory(),)
    contact_change_states: int = 0
    iterations_per_state: int = 0
    projection_iterations_per_state: int = 0
    mpcc_per_trajectory: int = 0
    mpcc_trajectories: int = 0
    qp_variants: tuple[QPVariant, ...] = QP_VARIANTS
    lcp_general_models: tuple[str, ...] = ()
    extra_scenes: tuple[str, ...] = ()
    extra_scene_trajectories: int = 0

    def __post_init__(self) -> None:
        if self.n_states < 1 or not self.trajectories:
            raise ValueError("a suite needs n_states >= 1 and at least one trajectory")
        for label in ("contact_change_states", "iterations_per_state",
                      "projection_iterations_per_state", "mpcc_per_trajectory",
                      "mpcc_trajectories", "extra_scene_trajectories"):
            if getattr(self, label) < 0:
                raise ValueError(f"{label} must be >= 0, got {getattr(self, label)}")
        unknown = [v for v in self.qp_variants if v not in tuple(QPVariant)]
        if unknown or not self.qp_variants:
            raise ValueError(f"qp_variants must be a non-empty subset of "
                             f"{[str(v) for v in QPVariant]}, got {list(self.qp_variants)}")
        bad = [m for m in self.lcp_general_models if m not in CONTACT_MODELS]
        if bad:
            raise ValueError(f"lcp_general_models must be among {CONTACT_MODELS}, got {bad}")
        if self.variant in self.extra_scenes or len(set(self.extra_scenes)) < len(
                self.extra_scenes) or not set(self.extra_scenes) <= set(SCENE_VARIANTS):
            raise ValueError(f"extra_scenes must be distinct scenes of {SCENE_VARIANTS} other "
                             f"than variant {self.variant!r}, got {list(self.extra_scenes)}")

    def to_json(self) -> dict[str, Any]:
        """The spec as the manifest stores it: ``dataclasses.asdict``, less the fields added
        after generator version 2 (:data:`ADDED_FIELDS`) while they keep their defaults, so
        that a suite which does not use them keeps its manifest byte for byte."""
        out = asdict(self)
        for name, default in ADDED_FIELDS.items():
            if out[name] == default:
                del out[name]
        return out

    def iterations_at(self, position: int, projection: bool = False) -> tuple[int, ...]:
        """ADMM iterations captured at the ``position``-th state of the suite (counted over
        every trajectory in order), for the QP steps or (``projection``) the projections."""
        pool = self.projection_iterations if projection else self.admm_iterations
        per_state = (self.projection_iterations_per_state if projection
                     else self.iterations_per_state)
        if per_state == 0 or not pool:
            return tuple(pool)
        return tuple(sorted({pool[(position * per_state + r) % len(pool)]
                             for r in range(per_state)}))


ADDED_FIELDS: dict[str, Any] = {"lcp_general_models": (), "extra_scenes": (),
                                "extra_scene_trajectories": 0}
"""Fields of :class:`SuiteSpec` added after generator version 2, with their defaults
(:meth:`SuiteSpec.to_json` leaves them out of the manifest while they are at them)."""

_PUSHES: tuple[Trajectory, ...] = (
    Trajectory(None, 0.75),
    Trajectory((-0.40, 0.12), 0.60),
    Trajectory((-0.35, 0.30), 0.85),
    Trajectory((-0.25, 0.10), 0.70),
    Trajectory((-0.45, 0.20), 0.80),
    Trajectory((-0.30, 0.35), 0.65),
    Trajectory((-0.38, 0.25), 0.90),
    Trajectory((-0.28, 0.16), 0.55),
)
"""Scripted pushes of the packaged suites: the config's ball start first, then other starts
and contact heights on the near face."""

SUITES: dict[str, SuiteSpec] = {
    "quick": SuiteSpec("quick", n_states=3, admm_iterations=(0, 3, 6, 9),
                       projection_iterations=(0, 3), trajectories=_PUSHES[:2],
                       contact_change_states=1, iterations_per_state=2,
                       projection_iterations_per_state=1, mpcc_per_trajectory=1,
                       mpcc_trajectories=1),
    "default": SuiteSpec("default", n_states=7, admm_iterations=(0, 3, 6, 8, 9),
                         projection_iterations=(0, 3, 6, 9), trajectories=_PUSHES[:6],
                         contact_change_states=3),
    "full": SuiteSpec("full", n_states=8, admm_iterations=tuple(range(10)),
                      projection_iterations=tuple(range(10)), projection_steps=(0, 3, -1),
                      trajectories=_PUSHES, contact_change_states=3,
                      lcp_general_models=("stewart_trinkle",), extra_scenes=("spatial",),
                      extra_scene_trajectories=2),
}
"""The packaged suites by name: ``quick`` 6 states from 2 pushes (two QP-step iterations per
state, (0, 3) or (6, 9) in turn, so a warm cell has its predecessor; projections at iteration 0
or 3; one ``mpcc``, on the first push: the late projections,
``rho_lam`` of 12800 and more, make the MINLP reference check run into its time limit and
belong to ``default``), ``default`` 42 states from 6 pushes (QP steps at iterations 0, 3, 6, 8,
9 and projections at 0, 3, 6, 9 at each state, 3 states per push at contact changes),
``full`` 64 states from 8 pushes of the planar scene and 16 from the first 2 pushes run in the
spatial scene, with an ``lcp_general`` instance of the Stewart-Trinkle LCS at each state."""


def reference_rho(iteration: int) -> dict[str, float]:
    """The reference schedule at ADMM iteration ``iteration``.

    :data:`c3bench.problems.names.REFERENCE_RHO0` with the blocks of
    :data:`~c3bench.problems.names.REFERENCE_RHO_BLOCKS` grown by
    ``REFERENCE_RHO_FACTOR ** iteration``: ``rho_x = 1``, ``rho_u = 0.1``,
    ``rho_lam = rho_eta = 50 * 2^i``. Keys are :class:`~c3bench.problems.names.Block` members.
    """
    if iteration < 0:
        raise ValueError(f"ADMM iteration must be >= 0, got {iteration}")
    grow = REFERENCE_RHO_FACTOR**iteration
    return {block: value * grow if block in REFERENCE_RHO_BLOCKS else value
            for block, value in REFERENCE_RHO0.items()}


@dataclass
class CaptureContext:
    """Everything a capture function needs at one sampled state.

    Attributes
    ----------
    spec
        The suite being generated.
    state_index
        Step index of the state along its scripted push.
    x0, u_prev
        The sampled state and the input applied before it.
    lcs, mpc
        The controller's LCS at ``(x0, u_prev)`` and its MPC.
    scene
        The controller's scene (:class:`c3bench.problems.scene.Scene`).
    rng
        Generator seeded by the suite's seed and ``state_index``.
    base_meta
        Metadata every instance of this state carries.
    position
        Position of the state in the suite (over every trajectory; picks its ADMM iterations,
        :meth:`SuiteSpec.iterations_at`).
    trajectory
        Index of its scripted push in ``spec.trajectories``.
    with_mpcc
        Whether an ``mpcc`` instance is built at this state.
    """

    spec: SuiteSpec
    state_index: int
    x0: np.ndarray
    u_prev: np.ndarray
    lcs: LCS
    mpc: MPC
    scene: Scene
    rng: np.random.Generator
    base_meta: dict[str, Any] = field(default_factory=dict)
    position: int = 0
    trajectory: int = 0
    with_mpcc: bool = True


@dataclass
class CapturedIterate:
    """One ADMM iteration's data: the QP's ``delta``/``w`` and rho, and the projection input.

    ``delta``, ``w`` are (T x step size) in the C3+ layout ``(x, lam, u, eta)``; C3's QP
    drops the ``eta`` columns. ``projection_v`` (T x step size) is the point each step's
    projection receives (``z + w``).
    """

    iteration: int
    rho: dict[str, float]
    delta: np.ndarray
    w: np.ndarray
    projection_v: np.ndarray
    source: str


Capture = Callable[[CaptureContext], Iterable[CapturedIterate]]
"""A capture function: the ADMM iterates at one sampled state."""


def provisional_capture(context: CaptureContext) -> list[CapturedIterate]:
    """Deterministic stand-in for controller iterates.

    ``delta_k = (x0, 0, u_prev, 0)``, ``w = 0``, and for projections a seeded random point
    (``lam >= 0`` and ``eta`` on the LCS gap); rho from :func:`reference_rho`.
    """
    lcs, spec = context.lcs, context.spec
    layout = HorizonLayout(lcs.nx, lcs.nlam, lcs.nu, lcs.nlam, context.mpc.horizon)
    base = np.zeros(layout.step_size)
    base[layout.index(0, Block.X)] = context.x0
    base[layout.index(0, Block.U)] = context.u_prev
    delta = np.tile(base, (layout.horizon, 1))
    iterations = sorted(set(spec.admm_iterations) | set(spec.projection_iterations))
    out = []
    for i in iterations:
        v = delta.copy()
        lam_s, eta_s = layout.index(0, Block.LAM), layout.index(0, Block.ETA)
        x_s, u_s = layout.index(0, Block.X), layout.index(0, Block.U)
        for k in range(layout.horizon):
            lam = np.abs(context.rng.normal(0.0, 2.0, lcs.nlam))
            v[k, x_s] += context.rng.normal(0.0, 0.01, lcs.nx)
            v[k, u_s] += context.rng.normal(0.0, 1.0, lcs.nu)
            v[k, lam_s] = lam
            v[k, eta_s] = lcs.gap(v[k, x_s], v[k, u_s], lam)
        out.append(CapturedIterate(i, reference_rho(i), delta, np.zeros_like(delta), v,
                                   "provisional"))
    return out
