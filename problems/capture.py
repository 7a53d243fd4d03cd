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
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from c3bench.problems.lcs import LCS
from c3bench.problems.mpc import MPC, HorizonLayout
from c3bench.problems.names import (
    REFERENCE_RHO0,
    REFERENCE_RHO_BLOCKS,
    REFERENCE_RHO_FACTOR,
    Block,
)

if TYPE_CHECKING:  # type only: importing the scene at run time would load MuJoCo
    from c3bench.problems.scene import Scene


@dataclass(frozen=True)
class SuiteSpec:
    """What a suite contains.

    Attributes
    ----------
    name
        ``quick``, ``default`` or ``full``.
    n_states
        States sampled along the push.
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


SUITES: dict[str, SuiteSpec] = {
    "quick": SuiteSpec("quick", n_states=2, admm_iterations=(0, 3, 6, 9),
                       projection_iterations=(0, 9)),
    "default": SuiteSpec("default", n_states=6, admm_iterations=tuple(range(10)),
                         projection_iterations=(0, 3, 6, 9)),
    "full": SuiteSpec("full", n_states=16, admm_iterations=tuple(range(10)),
                      projection_iterations=tuple(range(10)), projection_steps=(0, 3, -1)),
}
"""The packaged suites by name."""


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
        Step index of the state along the scripted push.
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
