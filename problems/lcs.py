"""Linear complementarity system (LCS) linearisation of the cube-tipping scene.

The LCS (docs/lcs.md) is

    x_{k+1} = A x_k + B u_k + D lam_k + d,
    0 <= lam_k  perp  E x_k + F lam_k + H u_k + c >= 0,

derived from MuJoCo's mass matrix ``M``, smooth acceleration (bias, gravity compensation and
actuator forces), contact frames, signed distances ``phi`` (``mj_geomDistance`` for the
ball-cube pair, touching or not) and point Jacobians, never from MuJoCo's soft contact.

With the smooth dynamics ``v' = M^-1 (tau - C v + B_u u)`` linearised as
``J_q q + J_v v + J_u u + d_v``, ``q' = N v`` (``N^+`` its pseudo-inverse) and semi-implicit
Euler of step ``dt``:

* Anitescu (default): one force per contact ``i`` and friction direction ``j`` along
  ``n_i + mu_i t_ij``; ``J_c = E_t^T J_n + mu J_t``;
  ``A = [[I + dt^2 N J_q, dt N + dt^2 N J_v], [dt J_q, I + dt J_v]]``,
  ``B = [dt^2 N J_u; dt J_u]``, ``d = [dt^2 N d_v; dt d_v]``,
  ``D = [dt^2 N M^-1 J_c^T; dt M^-1 J_c^T]``,
  ``E = [dt J_c J_q + E_t^T J_n N^+ / dt, J_c + dt J_c J_v]``, ``F = dt J_c M^-1 J_c^T``,
  ``H = dt J_c J_u``, ``c = E_t^T phi / dt + dt J_c d_v - E_t^T J_n N^+ q_0 / dt``.
* Stewart-Trinkle: ``lam = [gamma; lam_n; lam_t]`` with the slack ``gamma`` per contact;
  rows: friction cone ``mu lam_n - E_t lam_t``, position-level gap
  ``phi + dt J_n v_{k+1}``, and maximum dissipation ``E_t^T gamma + J_t v_{k+1}``.

``E_t`` (contacts x directions) sums a contact's friction directions.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Literal

import mujoco
import numpy as np

from c3bench.problems.scene import Scene

ContactModel = Literal["anitescu", "stewart_trinkle"]
CONTACT_MODELS: tuple[str, ...] = ("anitescu", "stewart_trinkle")
LCS_MATRICES: tuple[str, ...] = ("A", "B", "D", "d", "E", "F", "H", "c")


@dataclass
class LCS:
    """A discrete-time LCS: ``x' = A x + B u + D lam + d``, ``0 <= lam perp E x + F lam + H u + c``.

    Attributes
    ----------
    A, B, D, d, E, F, H, c
        The LCS matrices (docs/lcs.md).
    dt
        Time step (s).
    contact_model
        ``"anitescu"`` or ``"stewart_trinkle"``.
    n_contacts, friction_directions
        Contacts and friction directions per contact.
    phi
        Signed distances of the contacts at the linearisation point (m).
    """

    A: np.ndarray
    B: np.ndarray
    D: np.ndarray
    d: np.ndarray
    E: np.ndarray
    F: np.ndarray
    H: np.ndarray
    c: np.ndarray
    dt: float
    contact_model: str = "anitescu"
    n_contacts: int = 0
    friction_directions: int = 0
    phi: np.ndarray = field(default_factory=lambda: np.zeros(0))

    def __post_init__(self) -> None:
        self.validate()

    @property
    def nx(self) -> int:
        return int(self.A.shape[0])

    @property
    def nu(self) -> int:
        return int(self.B.shape[1])

    @property
    def nlam(self) -> int:
        return int(self.D.shape[1])

    def validate(self) -> None:
        """Check shapes and finiteness; raise ``ValueError`` naming the offending matrix."""
        nx, nu, nlam = self.A.shape[0], self.B.shape[1], self.D.shape[1]
        expected = {
            "A": (nx, nx), "B": (nx, nu), "D": (nx, nlam), "d": (nx,),
            "E": (nlam, nx), "F": (nlam, nlam), "H": (nlam, nu), "c": (nlam,),
        }
        for name, shape in expected.items():
            value = getattr(self, name)
            if not isinstance(value, np.ndarray):
                value = np.asarray(value, dtype=float)
                setattr(self, name, value)
            if value.shape != shape:
                raise ValueError(f"LCS.{name} must have shape {shape}, got {value.shape}")
            if not np.all(np.isfinite(value)):
                raise ValueError(f"LCS.{name} has non-finite entries")
        if not (math.isfinite(self.dt) and self.dt > 0):
            raise ValueError(f"LCS.dt must be a finite number > 0, got {self.dt!r}")

    def next_state(self, x: np.ndarray, u: np.ndarray, lam: np.ndarray) -> np.ndarray:
        """``A x + B u + D lam + d``."""
        return self.A @ x + self.B @ u + self.D @ lam + self.d

    def lcp_offset(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        """``E x + H u + c``: the ``q`` of the step's LCP ``0 <= lam perp F lam + q >= 0``."""
        return self.E @ x + self.H @ u + self.c

    def gap(self, x: np.ndarray, u: np.ndarray, lam: np.ndarray) -> np.ndarray:
        """``E x + F lam + H u + c``."""
        return self.lcp_offset(x, u) + self.F @ lam

    def arrays(self) -> dict[str, np.ndarray]:
        """The matrices by name, plus ``phi``."""
        out = {name: getattr(self, name) for name in LCS_MATRICES}
        out["phi"] = self.phi
        return out


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

    Contacts: each bottom corner of the cube with the table (normal +z, ``phi`` = corner
    height above the table), then the ball with the cube (``mj_geomDistance``; normal from
    the cube to the ball centre; ``phi`` negative when they overlap).
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
    for site in scene.corner_sites:
        point = data.site_xpos[site].copy()
        mujoco.mj_jac(model, data, jac_a, None, point, cube_body)
        phi.append(float(point[2] - table_z))
        normal_rows.append(up @ jac_a)
        tangent_rows.extend(t @ jac_a for t in _tangent_directions(up, planar))
        mu.append(scene.config.scene.mu_table)
    ball_geom, cube_geom = scene.geom("ball"), scene.geom("cube")
    fromto = np.zeros(6)
    distance = mujoco.mj_geomDistance(model, data, ball_geom, cube_geom, 10.0, fromto)
    centre = data.geom_xpos[ball_geom]
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
    E_t = np.kron(np.eye(n_contacts), np.ones((1, per)))
    return ContactFrames(
        phi=np.array(phi), J_n=np.array(normal_rows), J_t=np.array(tangent_rows),
        mu=np.array(mu), E_t=E_t,
    )


@dataclass
class SmoothDynamics:
    """Linearised smooth dynamics ``v' = J_q q + J_v v + J_u u + d_v``, kinematics ``q' = N v``."""

    J_q: np.ndarray
    J_v: np.ndarray
    J_u: np.ndarray
    d_v: np.ndarray
    N: np.ndarray
    N_pinv: np.ndarray
    M_inv: np.ndarray


def _smooth_acceleration(scene: Scene, q: np.ndarray, v: np.ndarray,
                         u: np.ndarray) -> np.ndarray:
    data = scene.data
    data.qpos[:] = q
    data.qvel[:] = v
    data.ctrl[:] = u
    mujoco.mj_forward(scene.model, data)
    return data.qacc_smooth.copy()


def smooth_dynamics(scene: Scene, x: np.ndarray, u: np.ndarray,
                    eps: float = 1e-6) -> SmoothDynamics:
    """Linearise MuJoCo's unconstrained acceleration by central differences.

    ``J_q`` is taken in the tangent space (``mj_integratePos``) and mapped to ``q`` by ``N^+``.
    Control clamping is disabled while differencing so that ``J_u`` is the actuator map.
    Leaves ``scene.data`` at ``(x, u)`` with kinematics current.
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
    return SmoothDynamics(J_q=J_q, J_v=J_v, J_u=J_u, d_v=d_v, N=N, N_pinv=N_pinv, M_inv=M_inv)


def check_dt(dt: float) -> float:
    if not (isinstance(dt, int | float) and math.isfinite(dt) and dt > 0):
        raise ValueError(f"dt must be a finite number > 0, got {dt!r}")
    return float(dt)


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
    x = scene.check_state(x)
    u = scene.check_input(u)
    dt = check_dt(dt)
    if contact_model not in CONTACT_MODELS:
        raise ValueError(f"contact_model must be one of {CONTACT_MODELS}, got {contact_model!r}")
    dyn = smooth_dynamics(scene, x, u)
    frames = contact_frames(scene)
    arrays = assemble_lcs(
        dt, x[: scene.nq], dyn.N, dyn.N_pinv, dyn.J_q[None], dyn.J_v[None], dyn.J_u[None],
        dyn.d_v[None], dyn.M_inv[None], frames.phi[None], frames.J_n[None], frames.J_t[None],
        frames.E_t, frames.mu, contact_model)
    return LCS(**{name: value[0] for name, value in arrays.items()}, dt=dt,
               contact_model=contact_model, n_contacts=len(frames.phi),
               friction_directions=scene.friction_directions, phi=frames.phi)


def assemble_lcs(dt: float, q0: np.ndarray, N: np.ndarray, N_pinv: np.ndarray,
                 J_q: np.ndarray, J_v: np.ndarray, J_u: np.ndarray, d_v: np.ndarray,
                 M_inv: np.ndarray, phi: np.ndarray, J_n: np.ndarray, J_t: np.ndarray,
                 E_t: np.ndarray, mu: np.ndarray, contact_model: str
                 ) -> dict[str, np.ndarray]:
    """The LCS matrices (module docstring) for ``n`` models at once (leading axis ``n``).

    Shared: ``q0`` (nq), ``N`` (nq x nv), ``N_pinv`` (nv x nq), ``E_t`` (contacts x
    directions), ``mu`` (contacts). Per model: ``J_q`` (n, nv, nq), ``J_v`` (n, nv, nv),
    ``J_u`` (n, nv, nu), ``d_v`` (n, nv), ``M_inv`` (n, nv, nv), ``phi`` (n, contacts),
    ``J_n`` (n, contacts, nv), ``J_t`` (n, directions, nv). Returns ``A, B, D, d, E, F, H, c``
    stacked along the leading axis; :func:`linearize` calls it with ``n = 1`` and
    :mod:`problems.lcs_batch` with one model per sampled cube side.
    """
    n, nv, nq = J_q.shape
    nu = J_u.shape[-1]
    Et = E_t
    eye_q = np.broadcast_to(np.eye(nq), (n, nq, nq))
    eye_v = np.broadcast_to(np.eye(nv), (n, nv, nv))
    A = np.concatenate([
        np.concatenate([eye_q + dt**2 * N @ J_q, dt * N + dt**2 * N @ J_v], axis=2),
        np.concatenate([dt * J_q, eye_v + dt * J_v], axis=2),
    ], axis=1)
    B = np.concatenate([dt**2 * N @ J_u, dt * J_u], axis=1)
    d = np.concatenate([dt**2 * d_v @ N.T, dt * d_v], axis=1)
    mu_rows = Et.T @ mu
    if contact_model == "anitescu":
        J = Et.T @ J_n + mu_rows[:, None] * J_t  # (n, nlam, nv)
        JnNp = Et.T @ J_n @ N_pinv
        E = np.concatenate([dt * J @ J_q + JnNp / dt, J + dt * J @ J_v], axis=2)
        F = dt * J @ M_inv @ np.swapaxes(J, -1, -2)
        F = 0.5 * (F + np.swapaxes(F, -1, -2))
        H = dt * J @ J_u
        c = (phi @ Et) / dt + dt * (J @ d_v[..., None])[..., 0] - (JnNp @ q0) / dt
    elif contact_model == "stewart_trinkle":
        nc, nd = Et.shape
        Jn, Jt = J_n, J_t
        J = np.concatenate([np.zeros((n, nc, nv)), Jn, Jt], axis=1)
        JnT, JtT = np.swapaxes(Jn, -1, -2), np.swapaxes(Jt, -1, -2)
        E = np.concatenate([
            np.zeros((n, nc, nq + nv)),
            np.concatenate([Jn @ N_pinv + dt**2 * Jn @ J_q, dt * Jn + dt**2 * Jn @ J_v], axis=2),
            np.concatenate([dt * Jt @ J_q, Jt + dt * Jt @ J_v], axis=2),
        ], axis=1)
        zeros_c = np.zeros((n, nc, nc))
        F = np.concatenate([
            np.concatenate([zeros_c, np.broadcast_to(np.diag(mu), (n, nc, nc)),
                            np.broadcast_to(-Et, (n, nc, nd))], axis=2),
            np.concatenate([zeros_c, dt**2 * Jn @ M_inv @ JnT, dt**2 * Jn @ M_inv @ JtT],
                           axis=2),
            np.concatenate([np.broadcast_to(Et.T, (n, nd, nc)), dt * Jt @ M_inv @ JnT,
                            dt * Jt @ M_inv @ JtT], axis=2),
        ], axis=1)
        H = np.concatenate([np.zeros((n, nc, nu)), dt**2 * Jn @ J_u, dt * Jt @ J_u], axis=1)
        c = np.concatenate([
            np.zeros((n, nc)),
            phi - (Jn @ N_pinv @ q0) + dt**2 * (Jn @ d_v[..., None])[..., 0],
            dt * (Jt @ d_v[..., None])[..., 0],
        ], axis=1)
    else:
        raise ValueError(f"contact_model must be one of {CONTACT_MODELS}, got "
                         f"{contact_model!r}")
    D = np.concatenate([dt**2 * N @ M_inv @ np.swapaxes(J, -1, -2),
                        dt * M_inv @ np.swapaxes(J, -1, -2)], axis=1)
    return {"A": A, "B": B, "D": D, "d": d, "E": E, "F": F, "H": H, "c": c}
