"""Batched LCS linearisation: one control step's LCS for many model samples (cube sides) at once.

The robust controller linearises ``n`` models that differ only in the cube side ``l_j`` at the
same measured state ``x`` and input ``u``. :func:`c3bench.problems.linearize.linearize` would
repeat every MuJoCo call ``n`` times; :class:`BatchLinearizer` splits the work by what depends
on ``l``:

**Once per control step** (MuJoCo, on one reference model of side ``l_ref``):

* the smooth dynamics by central differences, ``J_q^ref, J_v^ref, J_u^ref``, the smooth
  acceleration ``a^ref`` and ``N``, ``N^+`` (:func:`c3bench.problems.linearize.smooth_dynamics`,
  ``4 nv + 2 nu + 1`` MuJoCo calls of which ``2 nv + 1`` run the position stage);
* the mass matrix ``M^ref`` and the cube's rotational Jacobian ``J_r`` (3 x nv);
* the cube pose (origin ``p``, rotation ``R``), the origin Jacobians ``J_p0`` of the cube and
  of the ball, the ball centre ``b`` and its radius ``r``.

**Per sample** (numpy, a leading sample axis, no Python loop over samples):

* cube inertia ``I_j = m (h_j^2 + h_j^2) / 3`` with ``h_j = l_j / 2`` (MuJoCo's box formula;
  the cube's inertia is isotropic, so ``M_j = M^ref + (I_j - I_ref) J_r^T J_r``);
* ``M_j^-1`` (inverted, then symmetrised like
  :func:`c3bench.problems.linearize.smooth_dynamics`) and the smooth dynamics of sample
  ``j``: with ``v' = M^-1 f(q, v, u)`` and ``f`` independent of ``l`` (the cube's centre of
  mass is on its hinge and its inertia is isotropic, so neither the bias forces nor ``M``
  depend on ``q`` or on ``l`` other than through ``I_j``),
  ``J_*^j = M_j^-1 M^ref J_*^ref`` for ``* = q, v, u``, ``a^j = M_j^-1 M^ref a^ref`` and
  ``d_v^j = a^j - J_q^j q_0 - J_v^j v_0 - J_u^j u``;
* contact geometry: bottom corners ``c_i^j = p + R s_i^j`` with ``s = (+-h_j, 0, -h_j)``,
  ``phi = c_z - z_table``, normal ``+z``; the ball-table contact (when the scene has it) is
  the same for every sample (``phi = b_z - r - z_table``, Jacobian the ball's); ball-cube
  distance in closed form (what ``mj_geomDistance`` returns for a sphere and a box):
  ``o = R^T (b - p)``; outside the box the nearest box point is ``p + R clip(o, -h_j, h_j)``;
  with the centre inside it is the nearest face; ``phi = +-||b - near|| - r``, normal from
  the box point to the ball centre, the ball's point ``b - r n``;
* point Jacobians of a body point ``x``: ``J_p(x) = J_p0 + J_r x (x - p_0)`` column by column
  (rigid-body velocity ``v_x = v_0 + omega x (x - p_0)``);
* the LCS blocks with exactly the formulas of :func:`c3bench.problems.lcs.assemble_lcs`
  (Anitescu or Stewart-Trinkle), as batched matrix products.

The result equals ``linearize(build_scene(l=l_j), x, u, dt)`` for every sample to rounding
(tested to 1e-9 along the scripted push). With ``kernel="compiled"`` (:class:`LcsKernel`) the
per-sample part runs as one numba call (:mod:`c3bench.problems.linearize_compiled`, Anitescu
model), equal to the numpy part to rounding; it halves the build (0.57 -> 0.28 ms at 16
samples alone: the numpy part is some 60 small array calls whose Python overhead
dominates). Only the planar scene is supported; the spatial variant raises
``NotImplementedError``.

This is the plant side (it imports MuJoCo); the :class:`c3bench.problems.lcs.LCSBatch` type it
returns is in the plant-free core.
"""

from __future__ import annotations

from collections.abc import Sequence

import mujoco
import numpy as np

from c3bench.problems.config import Config, load_config
from c3bench.problems.lcs import CONTACT_MODELS, LCSBatch, assemble_lcs, check_dt
from c3bench.problems.linearize import SmoothDynamics, smooth_dynamics
from c3bench.problems.names import LcsKernel
from c3bench.problems.scene import Scene, build_scene, home_state


def _skew_apply(columns: np.ndarray, r: np.ndarray) -> np.ndarray:
    """``columns[..., :, i] x r`` for every column ``i``: (..., 3, nv) with ``r`` (..., 3)."""
    a0, a1, a2 = columns[..., 0, :], columns[..., 1, :], columns[..., 2, :]
    r0, r1, r2 = r[..., 0, None], r[..., 1, None], r[..., 2, None]
    return np.stack([a1 * r2 - a2 * r1, a2 * r0 - a0 * r2, a0 * r1 - a1 * r0], axis=-2)


class BatchLinearizer:
    """Linearise the planar cube-tipping scene for many cube sides at once.

    Parameters
    ----------
    sides
        Cube sides ``l_j`` of the model samples (m), each finite and > 0.
    config
        Task constants (default: the packaged ``cube_tipping.toml``).
    variant
        ``"planar"`` only; ``"spatial"`` raises ``NotImplementedError``.
    contact_model
        ``"anitescu"`` (default) or ``"stewart_trinkle"``.
    reference_side
        Side of the MuJoCo model used for the ``l``-independent quantities (default: the
        config's plant side); any value gives the same LCS up to rounding.
    ball_table
        Include the ball-table contact (default, as :func:`c3bench.problems.scene.build_scene`).
    kernel
        :attr:`LcsKernel.NUMPY` (default): the per-sample part in numpy, as above;
        :attr:`LcsKernel.COMPILED`: the same arithmetic in one numba call
        (:func:`c3bench.problems.linearize_compiled.sample_lcs`; the Anitescu model only,
        Stewart-Trinkle stays on numpy), equal to rounding.
    """

    def __init__(self, sides: Sequence[float] | np.ndarray, config: Config | None = None,
                 variant: str = "planar", contact_model: str = "anitescu",
                 reference_side: float | None = None, ball_table: bool = True,
                 kernel: LcsKernel | str = LcsKernel.NUMPY) -> None:
        if variant != "planar":
            raise NotImplementedError(
                f"BatchLinearizer supports the planar scene only (got variant {variant!r}); "
                "the spatial scene needs the four-corner, 3-D ball-box geometry: use "
                "c3bench.problems.linearize.linearize per sample")
        if contact_model not in CONTACT_MODELS:
            raise ValueError(f"contact_model must be one of {CONTACT_MODELS}, got "
                             f"{contact_model!r}")
        side_array = np.asarray(sides, dtype=float).reshape(-1)
        if side_array.size < 1 or not np.all(np.isfinite(side_array)) or np.any(side_array <= 0):
            raise ValueError(f"sides must be finite numbers > 0, got {sides!r}")
        try:
            self.kernel = LcsKernel(kernel)
        except ValueError:
            raise ValueError(f"kernel must be one of {[k.value for k in LcsKernel]}, got "
                             f"{kernel!r}") from None
        self.config = config or load_config()
        self.variant = variant
        self.contact_model = contact_model
        self.sides = side_array
        ref = self.config.scene.cube_side if reference_side is None else float(reference_side)
        self.scene: Scene = build_scene(l=ref, variant="planar", config=self.config,
                                        ball_table=ball_table)
        scene = self.scene
        self.cube_body = scene.body("cube")
        self.ball_body = scene.body("ball")
        self.cube_geom = scene.geom("cube")
        self.ball_geom = scene.geom("ball")
        self.ball_radius = float(scene.model.geom_size[self.ball_geom][0])
        mass = float(scene.model.body_mass[self.cube_body])
        self.half = self.sides / 2.0
        # MuJoCo's box inertia about a principal axis, m (h_1^2 + h_2^2) / 3 (isotropic cube)
        self.inertia = mass * (self.half * self.half + self.half * self.half) / 3.0
        self.inertia_ref = float(scene.model.body_inertia[self.cube_body][1])
        self.inertia_shift = self.inertia - self.inertia_ref  # I_j - I_ref
        h = self.half
        # bottom corners in the cube frame, in the scene's site order (-x then +x)
        self.corners_local = np.stack([
            np.stack([-h, np.zeros_like(h), -h], axis=-1),
            np.stack([h, np.zeros_like(h), -h], axis=-1),
        ], axis=1)  # (n, 2, 3)
        self.friction_directions = scene.friction_directions
        self.ball_table = ball_table
        self.n_contacts = scene.n_contacts
        self.mu = np.array([self.config.scene.mu_table] * (self.n_contacts - 1)
                           + [self.config.scene.mu_ball])
        self.E_t = np.kron(np.eye(self.n_contacts), np.ones((1, self.friction_directions)))

    def warm_up(self) -> None:
        """One build at the scene's home state (result discarded): with
        :attr:`LcsKernel.COMPILED` this compiles the kernel or loads it from numba's disk
        cache, so that the first control step does not pay it."""
        self.linearize(home_state(self.scene), np.zeros(self.scene.nu), self.config.mpc.dt)

    @property
    def n_samples(self) -> int:
        return int(self.sides.size)

    def linearize(self, x: np.ndarray, u: np.ndarray, dt: float) -> LCSBatch:
        """The LCS of every sample at ``(x, u)`` with step ``dt`` (module docstring)."""
        scene = self.scene
        model, data = scene.model, scene.data
        x = scene.check_state(x)
        u = scene.check_input(u)
        dt = check_dt(dt)
        nq, nv = scene.nq, scene.nv
        # ---- once per control step: MuJoCo at the measured state --------------------------
        dyn = smooth_dynamics(scene, x, u)
        acceleration = dyn.acceleration
        M_ref = np.zeros((nv, nv))
        mujoco.mj_fullM(model, data, M_ref)
        cube_origin = data.xpos[self.cube_body].copy()
        ball_origin = data.xpos[self.ball_body].copy()
        jacp_cube, jacr_cube = np.zeros((3, nv)), np.zeros((3, nv))
        mujoco.mj_jac(model, data, jacp_cube, jacr_cube, cube_origin, self.cube_body)
        jacp_ball, jacr_ball = np.zeros((3, nv)), np.zeros((3, nv))
        mujoco.mj_jac(model, data, jacp_ball, jacr_ball, ball_origin, self.ball_body)
        box_pos = data.geom_xpos[self.cube_geom].copy()
        box_rot = data.geom_xmat[self.cube_geom].reshape(3, 3).copy()
        centre = data.geom_xpos[self.ball_geom].copy()
        cube_rot = data.xmat[self.cube_body].reshape(3, 3).copy()
        table_z = self.config.scene.table_height
        if self.kernel == LcsKernel.COMPILED and self.contact_model == "anitescu":
            return self._compiled(dt, x, u, dyn, M_ref, cube_origin, cube_rot, jacp_cube,
                                  jacr_cube, ball_origin, jacp_ball, jacr_ball, box_pos,
                                  box_rot, centre, table_z)
        # ---- per sample: inertia, smooth dynamics ------------------------------------------
        n = self.n_samples
        M = np.broadcast_to(M_ref, (n, nv, nv)) + \
            self.inertia_shift[:, None, None] * (jacr_cube.T @ jacr_cube)
        M_inv = np.linalg.inv(M)
        M_inv = 0.5 * (M_inv + np.swapaxes(M_inv, -1, -2))
        transfer = M_inv @ M_ref  # M_j^-1 M_ref
        J_q = transfer @ dyn.J_q
        J_v = transfer @ dyn.J_v
        J_u = transfer @ dyn.J_u
        acc = transfer @ acceleration
        q0, v0 = x[:nq], x[nq:]
        d_v = acc - J_q @ q0 - J_v @ v0 - J_u @ u
        # ---- per sample: contact geometry -------------------------------------------------
        corners = cube_origin + np.einsum("ab,nkb->nka", cube_rot, self.corners_local)
        corner_phi = corners[..., 2] - table_z  # (n, 2)
        corner_jac = jacp_cube + _skew_apply(jacr_cube, corners - cube_origin)  # (n, 2, 3, nv)
        up = np.array([0.0, 0.0, 1.0])
        tangent_up = np.array([up[2], 0.0, -up[0]])
        tangent_up = tangent_up / np.linalg.norm(tangent_up)
        corner_n = np.einsum("a,nkav->nkv", up, corner_jac)
        corner_t = np.einsum("a,nkav->nkv", tangent_up, corner_jac)
        offset = box_rot.T @ (centre - box_pos)  # ball centre in the box frame
        h3 = np.repeat(self.half[:, None], 3, axis=1)  # (n, 3) half sizes
        inside = np.all(np.abs(offset) < h3, axis=1)
        near_local = np.clip(offset, -h3, h3)
        if np.any(inside):
            depth = h3[inside] - np.abs(offset)
            face = np.argmin(depth, axis=1)
            rows = np.arange(face.size)
            fixed = np.broadcast_to(offset, depth.shape).copy()
            fixed[rows, face] = np.sign(offset[face]) * h3[inside][rows, face]
            near_local[inside] = fixed
        near = box_pos + near_local @ box_rot.T  # (n, 3) box point
        gap = centre - near
        gap_norm = np.linalg.norm(gap, axis=1)
        ball_phi = np.where(inside, -gap_norm, gap_norm) - self.ball_radius
        normal = np.where(inside[:, None], -gap, gap) / gap_norm[:, None]
        ball_point = centre - self.ball_radius * normal
        jac_a = jacp_ball + _skew_apply(jacr_ball, ball_point - ball_origin)
        jac_b = jacp_cube + _skew_apply(jacr_cube, near - cube_origin)
        relative = jac_a - jac_b  # (n, 3, nv)
        tangent = np.stack([normal[:, 2], np.zeros(n), -normal[:, 0]], axis=1)
        tangent = tangent / np.linalg.norm(tangent, axis=1, keepdims=True)
        ball_n = np.einsum("na,nav->nv", normal, relative)
        ball_t = np.einsum("na,nav->nv", tangent, relative)
        phi_parts, normal_parts = [corner_phi], [corner_n]
        tangent_parts = [corner_t[:, 0], -corner_t[:, 0], corner_t[:, 1], -corner_t[:, 1]]
        if self.ball_table:  # l-independent: the ball's Jacobian at its lowest point
            lowest = centre - self.ball_radius * up
            jac_low = jacp_ball + _skew_apply(jacr_ball, lowest - ball_origin)
            phi_parts.append(np.full((n, 1), lowest[2] - table_z))
            normal_parts.append(np.broadcast_to(up @ jac_low, (n, 1, nv)))
            ball_table_t = np.broadcast_to(tangent_up @ jac_low, (n, nv))
            tangent_parts += [ball_table_t, -ball_table_t]
        phi = np.concatenate([*phi_parts, ball_phi[:, None]], axis=1)  # (n, contacts)
        J_n = np.concatenate([*normal_parts, ball_n[:, None]], axis=1)  # (n, contacts, nv)
        J_t = np.stack([*tangent_parts, ball_t, -ball_t], axis=1)  # (n, directions, nv)
        return self._assemble(dt, q0, dyn.N, dyn.N_pinv, J_q, J_v, J_u, d_v, M_inv, phi,
                              J_n, J_t)

    def _compiled(self, dt: float, x: np.ndarray, u: np.ndarray, dyn: SmoothDynamics,
                  M_ref: np.ndarray, cube_origin: np.ndarray, cube_rot: np.ndarray,
                  jacp_cube: np.ndarray, jacr_cube: np.ndarray, ball_origin: np.ndarray,
                  jacp_ball: np.ndarray, jacr_ball: np.ndarray, box_pos: np.ndarray,
                  box_rot: np.ndarray, centre: np.ndarray, table_z: float) -> LCSBatch:
        """The per-sample part in one compiled call (:class:`LcsKernel` ``COMPILED``)."""
        from c3bench.problems.linearize_compiled import sample_lcs

        scene, n = self.scene, self.n_samples
        nq, nv, nu = scene.nq, scene.nv, scene.nu
        nx, nlam = nq + nv, self.E_t.shape[1]
        A, B, D = np.empty((n, nx, nx)), np.empty((n, nx, nu)), np.empty((n, nx, nlam))
        d, E, F = np.empty((n, nx)), np.empty((n, nlam, nx)), np.empty((n, nlam, nlam))
        H, c, phi = np.empty((n, nlam, nu)), np.empty((n, nlam)), np.empty((n, self.n_contacts))
        sample_lcs(dt, x[:nq], x[nq:], u, dyn.N, dyn.N_pinv, dyn.J_q, dyn.J_v, dyn.J_u,
                   dyn.acceleration, M_ref, self.inertia_shift, self.half,
                   self.corners_local, cube_origin, cube_rot, jacp_cube, jacr_cube,
                   ball_origin, jacp_ball, jacr_ball, box_pos, box_rot, centre,
                   self.ball_radius, float(table_z), self.ball_table, self.E_t, self.mu,
                   A, B, D, d, E, F, H, c, phi)
        return LCSBatch(A=A, B=B, D=D, d=d, E=E, F=F, H=H, c=c, dt=dt,
                        contact_model=self.contact_model, n_contacts=self.n_contacts,
                        friction_directions=self.friction_directions, phi=phi,
                        sides=self.sides.copy())

    def _assemble(self, dt: float, q0: np.ndarray, N: np.ndarray, Np: np.ndarray,
                  J_q: np.ndarray, J_v: np.ndarray, J_u: np.ndarray, d_v: np.ndarray,
                  M_inv: np.ndarray, phi: np.ndarray, J_n: np.ndarray, J_t: np.ndarray
                  ) -> LCSBatch:
        """The LCS blocks of :func:`c3bench.problems.lcs.assemble_lcs`, one model per sample."""
        arrays = assemble_lcs(dt, q0, N, Np, J_q, J_v, J_u, d_v, M_inv, phi, J_n, J_t,
                              self.E_t, self.mu, self.contact_model)
        return LCSBatch(**arrays, dt=dt, contact_model=self.contact_model,
                        n_contacts=self.n_contacts,
                        friction_directions=self.friction_directions, phi=phi,
                        sides=self.sides.copy())
