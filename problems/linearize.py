"""MuJoCo linearisation of the cube-tipping scene into an LCS.

:func:`linearize` derives the LCS (:mod:`c3bench.problems.lcs`) from MuJoCo's mass matrix
``M``, smooth acceleration (bias, gravity compensation and actuator forces), contact frames,
signed distances ``phi`` (``mj_geomDistance`` for the ball-cube pair, touching or not) and
point Jacobians, never from MuJoCo's soft contact: :func:`smooth_dynamics` linearises the
smooth dynamics by central differences, :func:`contact_frames` measures the contact geometry
(cube corners-table, ball-table, ball-cube), and :func:`c3bench.problems.lcs.assemble_lcs`
turns both into the LCS matrices.

:func:`smooth_dynamics` computes exactly (bit for bit) what the readable
:func:`smooth_dynamics_reference` does with cheaper MuJoCo calls (constraints off, later
pipeline stages only where a velocity or an input is perturbed); :func:`linearize_reference`
is :func:`linearize` on the reference. Central differences are kept: MuJoCo has no analytic
derivative with respect to positions, and a one-sided difference would change the result by
far more than 1e-10.

This is the plant side: it imports MuJoCo. The LCS types and formulas live in the plant-free
core (:mod:`c3bench.problems.lcs`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import mujoco
import numpy as np

from c3bench.problems.lcs import CONTACT_MODELS, LCS, ContactModel, assemble_lcs, check_dt
from c3bench.problems.scene import Scene


@dataclass
class ContactFrames:
    """Contact geometry at one configuration.

    Attributes
    ----------
    phi
        Signed distances, one per contact (m).
    J_n
        Normal Jacobians (contacts x nv): relative normal velocity ``J_n v``.
    J_t
        Tangential Jacobians (directions x nv), one row per friction direction.
    mu
        Friction coefficient per contact.
    E_t
        Contacts x directions, 1 where a direction belongs to a contact.
    """

    phi: np.ndarray
    J_n: np.ndarray
    J_t: np.ndarray
    mu: np.ndarray
    E_t: np.ndarray


def _tangent_directions(normal: np.ndarray, planar: bool) -> list[np.ndarray]:
    if planar:
        tangent = np.array([normal[2], 0.0, -normal[0]])
        tangent /= np.linalg.norm(tangent)
        return [tangent, -tangent]
    helper = np.array([0.0, 1.0, 0.0]) if abs(normal[1]) < 0.9 else np.array([1.0, 0.0, 0.0])
    t1 = np.cross(helper, normal)
    t1 /= np.linalg.norm(t1)
    t2 = np.cross(normal, t1)
    return [t1, -t1, t2, -t2]


def contact_frames(scene: Scene) -> ContactFrames:
    """Contact geometry of ``scene.data`` (kinematics must be current).

    Contacts, in this order: each bottom corner of the cube with the table (normal +z,
    ``phi`` = corner height above the table, friction ``mu_table``); the ball with the table
    when the scene declares it (``scene.ball_table``; normal +z at the ball's lowest point,
    ``phi = z_ball - r - z_table``, friction ``mu_table``); the ball with the cube
    (``mj_geomDistance``; normal from the cube to the ball centre; ``phi`` negative when they
    overlap; friction ``mu_ball``). The ball-cube contact is always the last one.
    """
    model, data = scene.model, scene.data
    planar = scene.variant == "planar"
    cube_body, ball_body = scene.body("cube"), scene.body("ball")
    table_z = scene.config.scene.table_height
    normal_rows: list[np.ndarray] = []
    tangent_rows: list[np.ndarray] = []
    phi: list[float] = []
    mu: list[float] = []
    jac_a = np.zeros((3, scene.nv))
    jac_b = np.zeros((3, scene.nv))
    up = np.array([0.0, 0.0, 1.0])
    table_points = [(data.site_xpos[site].copy(), cube_body) for site in scene.corner_sites]
    ball_geom, cube_geom = scene.geom("ball"), scene.geom("cube")
    centre = data.geom_xpos[ball_geom]
    if scene.ball_table:
        radius = float(model.geom_size[ball_geom][0])
        table_points.append((centre - radius * up, ball_body))
    for point, body in table_points:
        mujoco.mj_jac(model, data, jac_a, None, point, body)
        phi.append(float(point[2] - table_z))
        normal_rows.append(up @ jac_a)
        tangent_rows.extend(t @ jac_a for t in _tangent_directions(up, planar))
        mu.append(scene.config.scene.mu_table)
    fromto = np.zeros(6)
    distance = mujoco.mj_geomDistance(model, data, ball_geom, cube_geom, 10.0, fromto)
    normal = centre - fromto[:3]
    normal /= np.linalg.norm(normal)
    mujoco.mj_jac(model, data, jac_a, None, fromto[:3].copy(), ball_body)
    mujoco.mj_jac(model, data, jac_b, None, fromto[3:].copy(), cube_body)
    relative = jac_a - jac_b
    phi.append(float(distance))
    normal_rows.append(normal @ relative)
    tangent_rows.extend(t @ relative for t in _tangent_directions(normal, planar))
    mu.append(scene.config.scene.mu_ball)
    n_contacts = len(phi)
    per = scene.friction_directions
    E_t = np.repeat(np.eye(n_contacts), per, axis=1)  # = kron(I, ones((1, per)))
    return ContactFrames(
        phi=np.array(phi), J_n=np.array(normal_rows), J_t=np.array(tangent_rows),
        mu=np.array(mu), E_t=E_t,
    )


@dataclass
class SmoothDynamics:
    """Linearised smooth dynamics ``v' = J_q q + J_v v + J_u u + d_v``, kinematics ``q' = N v``.

    ``acceleration`` is MuJoCo's ``qacc_smooth`` at the linearisation point.
    """

    J_q: np.ndarray
    J_v: np.ndarray
    J_u: np.ndarray
    d_v: np.ndarray
    N: np.ndarray
    N_pinv: np.ndarray
    M_inv: np.ndarray
    acceleration: np.ndarray


def _smooth_acceleration(scene: Scene, q: np.ndarray, v: np.ndarray,
                         u: np.ndarray) -> np.ndarray:
    """MuJoCo's unconstrained acceleration ``qacc_smooth`` at ``(q, v, u)`` (leaves
    ``scene.data`` there)."""
    data = scene.data
    data.qpos[:] = q
    data.qvel[:] = v
    data.ctrl[:] = u
    mujoco.mj_forward(scene.model, data)
    acceleration: np.ndarray = data.qacc_smooth.copy()
    return acceleration


def smooth_dynamics_reference(scene: Scene, x: np.ndarray, u: np.ndarray,
                              eps: float = 1e-6) -> SmoothDynamics:
    """Linearise MuJoCo's unconstrained acceleration by central differences (readable
    reference of :func:`smooth_dynamics`, which returns the same numbers faster).

    ``J_q`` is taken in the tangent space (``mj_integratePos``) and mapped to ``q`` by ``N^+``.
    Control clamping is disabled while differencing so that ``J_u`` is the actuator map.
    ``2 (2 nv + nu) + 1`` full ``mj_forward`` calls. Leaves ``scene.data`` at ``(x, u)`` with
    kinematics current.
    """
    model = scene.model
    nq, nv, nu = scene.nq, scene.nv, scene.nu
    q0, v0 = x[:nq].copy(), x[nq:].copy()
    flags = model.opt.disableflags
    model.opt.disableflags = flags | int(mujoco.mjtDisableBit.mjDSBL_CLAMPCTRL)
    try:
        J_tangent = np.zeros((nv, nv))
        N = np.zeros((nq, nv))
        for i in range(nv):
            step = np.zeros(nv)
            step[i] = eps
            q_plus, q_minus = q0.copy(), q0.copy()
            mujoco.mj_integratePos(model, q_plus, step, 1.0)
            mujoco.mj_integratePos(model, q_minus, step, -1.0)
            N[:, i] = (q_plus - q_minus) / (2 * eps)
            J_tangent[:, i] = (
                _smooth_acceleration(scene, q_plus, v0, u)
                - _smooth_acceleration(scene, q_minus, v0, u)
            ) / (2 * eps)
        J_v = np.zeros((nv, nv))
        for i in range(nv):
            dv = np.zeros(nv)
            dv[i] = eps
            J_v[:, i] = (
                _smooth_acceleration(scene, q0, v0 + dv, u)
                - _smooth_acceleration(scene, q0, v0 - dv, u)
            ) / (2 * eps)
        J_u = np.zeros((nv, nu))
        for i in range(nu):
            du = np.zeros(nu)
            du[i] = eps
            J_u[:, i] = (
                _smooth_acceleration(scene, q0, v0, u + du)
                - _smooth_acceleration(scene, q0, v0, u - du)
            ) / (2 * eps)
        acceleration = _smooth_acceleration(scene, q0, v0, u)
    finally:
        model.opt.disableflags = flags
    N_pinv = np.linalg.pinv(N)
    J_q = J_tangent @ N_pinv
    M = np.zeros((nv, nv))
    mujoco.mj_fullM(model, scene.data, M)
    M_inv = np.linalg.inv(M)
    M_inv = 0.5 * (M_inv + M_inv.T)
    d_v = acceleration - J_q @ q0 - J_v @ v0 - J_u @ u
    return SmoothDynamics(J_q=J_q, J_v=J_v, J_u=J_u, d_v=d_v, N=N, N_pinv=N_pinv, M_inv=M_inv,
                          acceleration=acceleration)


def smooth_dynamics(scene: Scene, x: np.ndarray, u: np.ndarray,
                    eps: float = 1e-6) -> SmoothDynamics:
    """:func:`smooth_dynamics_reference`'s central differences with cheaper MuJoCo calls.

    The same perturbations, the same differences in the same floating-point order, so the
    result is bit for bit the reference's (tested). What is saved:

    * constraints are disabled while differencing (``mjDSBL_CONSTRAINT``): MuJoCo then skips
      collision detection and the constraint solver, neither of which ``qacc_smooth`` (the
      acceleration before constraint forces) depends on;
    * a velocity perturbation reruns only the velocity, actuation and acceleration stages
      (``mj_forwardSkip(..., mjSTAGE_POS)``), an input perturbation only actuation and
      acceleration (``mjSTAGE_VEL``): only ``2 nv + 1`` calls run the position stage
      (kinematics, mass matrix and its factorisation);
    * the perturbed configurations are built once as arrays, and the accelerations are
      written into preallocated rows.

    Leaves ``scene.data`` at ``(x, u)`` with kinematics and ``qacc_smooth`` current (no
    contacts detected).
    """
    model, data = scene.model, scene.data
    nq, nv, nu = scene.nq, scene.nv, scene.nu
    q0, v0 = x[:nq].copy(), x[nq:].copy()
    u = np.array(u, dtype=float)
    twice = 2 * eps
    flags = model.opt.disableflags
    model.opt.disableflags = flags | int(mujoco.mjtDisableBit.mjDSBL_CLAMPCTRL) \
        | int(mujoco.mjtDisableBit.mjDSBL_CONSTRAINT)
    try:
        steps = np.zeros((nv, nv))
        np.fill_diagonal(steps, eps)
        q_plus, q_minus = np.tile(q0, (nv, 1)), np.tile(q0, (nv, 1))
        for i in range(nv):
            mujoco.mj_integratePos(model, q_plus[i], steps[i], 1.0)
            mujoco.mj_integratePos(model, q_minus[i], steps[i], -1.0)
        plus = np.empty((2 * nv + nu, nv))
        minus = np.empty((2 * nv + nu, nv))
        data.qvel[:] = v0
        data.ctrl[:] = u
        for i in range(nv):
            for rows, q in ((plus, q_plus[i]), (minus, q_minus[i])):
                data.qpos[:] = q
                mujoco.mj_forward(model, data)
                rows[i] = data.qacc_smooth
        data.qpos[:] = q0
        mujoco.mj_forward(model, data)  # position stage at q0 for the v and u columns
        skip_position, skip_velocity = mujoco.mjtStage.mjSTAGE_POS, mujoco.mjtStage.mjSTAGE_VEL
        for i in range(nv):
            for rows, sign in ((plus, 1.0), (minus, -1.0)):
                data.qvel[i] = v0[i] + sign * eps
                mujoco.mj_forwardSkip(model, data, skip_position, 1)
                rows[nv + i] = data.qacc_smooth
            data.qvel[i] = v0[i]
        mujoco.mj_forwardSkip(model, data, skip_position, 1)  # velocity stage at v0
        for i in range(nu):
            for rows, sign in ((plus, 1.0), (minus, -1.0)):
                data.ctrl[i] = u[i] + sign * eps
                mujoco.mj_forwardSkip(model, data, skip_velocity, 1)
                rows[2 * nv + i] = data.qacc_smooth
            data.ctrl[i] = u[i]
        mujoco.mj_forwardSkip(model, data, skip_velocity, 1)
        acceleration = data.qacc_smooth.copy()
    finally:
        model.opt.disableflags = flags
    derivatives = ((plus - minus) / twice).T  # nv x (2 nv + nu), one column per variable
    N = ((q_plus - q_minus) / twice).T
    N_pinv = np.linalg.pinv(N)
    J_q = derivatives[:, :nv] @ N_pinv
    J_v = np.ascontiguousarray(derivatives[:, nv:2 * nv])
    J_u = np.ascontiguousarray(derivatives[:, 2 * nv:])
    M = np.zeros((nv, nv))
    mujoco.mj_fullM(model, data, M)
    M_inv = np.linalg.inv(M)
    M_inv = 0.5 * (M_inv + M_inv.T)
    d_v = acceleration - J_q @ q0 - J_v @ v0 - J_u @ u
    return SmoothDynamics(J_q=J_q, J_v=J_v, J_u=J_u, d_v=d_v, N=N, N_pinv=N_pinv, M_inv=M_inv,
                          acceleration=acceleration)


def linearize(
    scene: Scene,
    x: np.ndarray,
    u: np.ndarray,
    dt: float,
    contact_model: ContactModel = "anitescu",
) -> LCS:
    """Linearise the scene into an LCS at state ``x`` and input ``u``.

    Parameters
    ----------
    scene
        The controller's model (its ``l`` may differ from the plant's).
    x, u
        Linearisation point: state ``(q, v)`` and ball force.
    dt
        Time step (s).
    contact_model
        ``"anitescu"`` (default) or ``"stewart_trinkle"``.
    """
    return _linearize_with(smooth_dynamics, scene, x, u, dt, contact_model)


def linearize_reference(
    scene: Scene,
    x: np.ndarray,
    u: np.ndarray,
    dt: float,
    contact_model: ContactModel = "anitescu",
) -> LCS:
    """:func:`linearize` with :func:`smooth_dynamics_reference` (the readable central
    differences, full ``mj_forward`` per evaluation); the same LCS bit for bit (tested)."""
    return _linearize_with(smooth_dynamics_reference, scene, x, u, dt, contact_model)


def _linearize_with(
    dynamics: Callable[[Scene, np.ndarray, np.ndarray], SmoothDynamics],
    scene: Scene,
    x: np.ndarray,
    u: np.ndarray,
    dt: float,
    contact_model: ContactModel,
) -> LCS:
    """The LCS of :func:`linearize`, its smooth dynamics from ``dynamics``."""
    x = scene.check_state(x)
    u = scene.check_input(u)
    dt = check_dt(dt)
    if contact_model not in CONTACT_MODELS:
        raise ValueError(f"contact_model must be one of {CONTACT_MODELS}, got {contact_model!r}")
    dyn = dynamics(scene, x, u)
    frames = contact_frames(scene)
    arrays = assemble_lcs(
        dt, x[: scene.nq], dyn.N, dyn.N_pinv, dyn.J_q[None], dyn.J_v[None], dyn.J_u[None],
        dyn.d_v[None], dyn.M_inv[None], frames.phi[None], frames.J_n[None], frames.J_t[None],
        frames.E_t, frames.mu, contact_model)
    return LCS(**{name: value[0] for name, value in arrays.items()}, dt=dt,
               contact_model=contact_model, n_contacts=len(frames.phi),
               friction_directions=scene.friction_directions, phi=frames.phi)
