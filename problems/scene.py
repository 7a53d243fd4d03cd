"""The cube-tipping scene: MJCF generation, start and goal states, the scene's MPC weights
(:func:`build_mpc`), the MuJoCo plant and off-screen rendering.

A cube of side ``l`` rests on a table; a ball end effector, moved by a force command ``u``,
pushes it. Two variants:

* ``planar`` (default, the reference study's setting): cube (x, z, theta) and ball (x, z) joints,
  ``nq = nv = 5``, state ``x = (q, v)`` in R^10, input ``u`` in R^2.
  ``q = (cube_x, cube_z, cube_theta, ball_x, ball_z)``; theta is the rotation about +y, so a
  positive angle lifts the near (-x) edge and pivots the cube about its far (+x) bottom edge.
* ``spatial``: cube free joint ``(x, y, z, qw, qx, qy, qz)``, ball ``(x, y, z)``: ``nq = 10``,
  ``nv = 9``, ``u`` in R^3.

Joint coordinates are absolute: body frames sit at the world origin, so ``cube_x`` is the
cube centre's x coordinate. Collisions are declared pair by pair (cube-table with ``mu_table``,
ball-cube with ``mu_ball``); the ball does not collide with the table (it models an end
effector whose workspace stays above it). The ball is gravity compensated (``gravcomp``).
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import mujoco
import numpy as np

from c3bench.problems.config import Config, MPCConfig, SceneConfig, load_config, whole_steps
from c3bench.problems.errors import RenderUnavailable
from c3bench.problems.limits import cube_limits
from c3bench.problems.mpc import MPC

Variant = Literal["planar", "spatial"]
VARIANTS: tuple[str, ...] = ("planar", "spatial")


def check_variant(variant: str) -> Variant:
    """``variant`` as a :data:`Variant`; ``ValueError`` unless it is one of :data:`VARIANTS`."""
    if variant == "planar":
        return "planar"
    if variant == "spatial":
        return "spatial"
    raise ValueError(f"variant must be one of {VARIANTS}, got {variant!r}")


def _check_side(l: float) -> float:
    if not (isinstance(l, int | float) and math.isfinite(l) and l > 0):
        raise ValueError(f"l (cube side) must be a finite number > 0, got {l!r}")
    return float(l)


def make_mjcf(
    l: float,
    scene: SceneConfig,
    variant: Variant = "planar",
    timestep: float | None = None,
    ball_table: bool = True,
) -> str:
    """Return the MJCF text of the scene for a cube of side ``l``.

    Parameters
    ----------
    l
        Cube side (m).
    scene
        Physical constants.
    variant
        ``"planar"`` or ``"spatial"``.
    timestep
        MuJoCo integration step; defaults to ``scene.plant_timestep``. The integrator is
        semi-implicit Euler (MuJoCo's ``Euler``), the same scheme the LCS discretises.
    ball_table
        Declare the ball-table contact pair (friction ``mu_table``, the plant's ``solref``).
    """
    l = _check_side(l)
    if variant not in VARIANTS:
        raise ValueError(f"variant must be one of {VARIANTS}, got {variant!r}")
    step = scene.plant_timestep if timestep is None else timestep
    if not (math.isfinite(step) and step > 0):
        raise ValueError(f"timestep must be a finite number > 0, got {step!r}")
    half = l / 2
    r = scene.ball_radius
    fl = scene.force_limit
    tr, ts = scene.contact_solref
    inertia = scene.cube_mass * l * l / 6.0
    if variant == "planar":
        cube_joints = (
            '<joint name="cube_x" type="slide" axis="1 0 0"/>'
            '<joint name="cube_z" type="slide" axis="0 0 1"/>'
            '<joint name="cube_theta" type="hinge" axis="0 1 0"/>'
        )
        ball_axes: tuple[tuple[str, str], ...] = (("x", "1 0 0"), ("z", "0 0 1"))
        corners = [(-half, 0.0, -half), (half, 0.0, -half)]
    else:
        cube_joints = '<freejoint name="cube_free"/>'
        ball_axes = (("x", "1 0 0"), ("y", "0 1 0"), ("z", "0 0 1"))
        corners = [(sx * half, sy * half, -half) for sx in (-1, 1) for sy in (-1, 1)]
    ball_joints = "".join(
        f'<joint name="ball_{name}" type="slide" axis="{axis}"/>' for name, axis in ball_axes
    )
    motors = "".join(
        f'<motor name="force_{name}" joint="ball_{name}" ctrllimited="true" '
        f'ctrlrange="{-fl} {fl}"/>'
        for name, _ in ball_axes
    )
    sites = "".join(
        f'<site name="corner_{i}" pos="{x:.17g} {y:.17g} {z:.17g}" size="0.005"/>'
        for i, (x, y, z) in enumerate(corners)
    )
    friction_table = f"{scene.mu_table} {scene.mu_table} 0.005 0.0001 0.0001"
    friction_ball = f"{scene.mu_ball} {scene.mu_ball} 0.005 0.0001 0.0001"
    ball_table_pair = (
        f'<pair geom1="ball" geom2="table" condim="3" friction="{friction_table}" '
        f'solref="{tr:.17g} {ts:.17g}"/>' if ball_table else "")
    return f"""<mujoco model="cube_tipping_{variant}">
  <option timestep="{step:.17g}" integrator="Euler" gravity="0 0 -9.81"/>
  <visual><global offwidth="640" offheight="480"/></visual>
  <worldbody>
    <light pos="0 -1 2" dir="0 1 -2"/>
    <geom name="table" type="plane" pos="0 0 {scene.table_height:.17g}" size="2 2 0.1"
          rgba="0.8 0.8 0.8 1" contype="0" conaffinity="0"/>
    <body name="cube">
      {cube_joints}
      <geom name="cube" type="box" size="{half:.17g} {half:.17g} {half:.17g}"
            mass="{scene.cube_mass:.17g}" rgba="0.2 0.4 0.8 1" contype="0" conaffinity="0"/>
      {sites}
    </body>
    <body name="ball" gravcomp="1">
      {ball_joints}
      <geom name="ball" type="sphere" size="{r:.17g}" mass="{scene.ball_mass:.17g}"
            rgba="0.9 0.3 0.2 1" contype="0" conaffinity="0"/>
    </body>
  </worldbody>
  <contact>
    <pair geom1="cube" geom2="table" condim="3" friction="{friction_table}"
          solref="{tr:.17g} {ts:.17g}"/>
    <pair geom1="ball" geom2="cube" condim="3" friction="{friction_ball}"
          solref="{tr:.17g} {ts:.17g}"/>
    {ball_table_pair}
  </contact>
  <actuator>{motors}</actuator>
  <!-- uniform-density cube: inertia m l^2 / 6 = {inertia:.6g} kg m^2 about every axis -->
</mujoco>
"""


@dataclass
class Scene:
    """A compiled MuJoCo model of the scene with its own scratch ``MjData``.

    Attributes
    ----------
    model, data
        MuJoCo model and data.
    variant
        ``"planar"`` or ``"spatial"``.
    l
        Cube side of this model (m): the plant's true side or a controller model's side.
    config
        The task constants it was built from.
    corner_sites
        Site ids of the cube's bottom corners (the cube-table contacts).
    ball_table
        Whether the ball collides with the table (MJCF pair and LCS contact).
    """

    model: mujoco.MjModel
    data: mujoco.MjData
    variant: Variant
    l: float
    config: Config
    corner_sites: list[int] = field(default_factory=list)
    ball_table: bool = True

    @property
    def nq(self) -> int:
        return int(self.model.nq)

    @property
    def nv(self) -> int:
        return int(self.model.nv)

    @property
    def nx(self) -> int:
        """State dimension ``nq + nv``."""
        return self.nq + self.nv

    @property
    def nu(self) -> int:
        return int(self.model.nu)

    @property
    def friction_directions(self) -> int:
        """Friction directions per contact: 2 (planar, +-t) or 4 (spatial, +-t1, +-t2)."""
        return 2 if self.variant == "planar" else 4

    @property
    def n_contacts(self) -> int:
        """LCS contacts: bottom corners, the ball-table contact (when declared), ball-cube."""
        return len(self.corner_sites) + int(self.ball_table) + 1

    def geom(self, name: str) -> int:
        return int(mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_GEOM, name))

    def body(self, name: str) -> int:
        return int(mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_BODY, name))

    # --- state layout -------------------------------------------------------------------
    @property
    def ball_position_indices(self) -> np.ndarray:
        """Indices of the ball centre coordinates inside ``q`` (and ``x``)."""
        start = 3 if self.variant == "planar" else 7
        return np.arange(start, self.nq)

    @property
    def cube_pose_indices(self) -> np.ndarray:
        """Indices of the cube pose inside ``q`` (and ``x``)."""
        return np.arange(0, 3 if self.variant == "planar" else 7)

    def cube_angle(self, x: np.ndarray) -> float:
        """Pivot angle of the cube (rad): rotation about +y (planar) or its spatial equivalent."""
        x = np.asarray(x, dtype=float)
        if self.variant == "planar":
            return float(x[2])
        qw, qx, qy, qz = x[3:7]
        # rotation angle about y of the body z axis projected on the xz-plane
        zx = 2 * (qx * qz + qw * qy)
        zz = 1 - 2 * (qx * qx + qy * qy)
        return float(math.atan2(zx, zz))

    def check_state(self, x: np.ndarray, name: str = "x") -> np.ndarray:
        """Return ``x`` as a float array after checking its shape and finiteness."""
        return check_vector(x, self.nx, name)

    def check_input(self, u: np.ndarray, name: str = "u") -> np.ndarray:
        return check_vector(u, self.nu, name)


def check_vector(value: np.ndarray, size: int, name: str) -> np.ndarray:
    """Validate a 1-D float vector of a given size; raise ``ValueError`` naming it."""
    array = np.asarray(value, dtype=float)
    if array.shape != (size,):
        raise ValueError(f"{name} must have shape ({size},), got {array.shape}")
    if not np.all(np.isfinite(array)):
        raise ValueError(f"{name} has non-finite entries: {array}")
    return array


def build_scene(
    l: float | None = None,
    variant: Variant = "planar",
    config: Config | None = None,
    timestep: float | None = None,
    ball_table: bool = True,
) -> Scene:
    """Compile the scene.

    Parameters
    ----------
    l
        Cube side; defaults to the plant's ``config.scene.cube_side``.
    variant
        ``"planar"`` or ``"spatial"``.
    config
        Task constants; defaults to the packaged ``cube_tipping.toml``.
    timestep
        MuJoCo step; defaults to the plant step of the config.
    ball_table
        Ball-table contact in the plant and in the LCS (default); ``False`` restores the
        scene without it (one contact fewer in the LCS).
    """
    cfg = config if config is not None else load_config()
    side = cfg.scene.cube_side if l is None else _check_side(l)
    model = mujoco.MjModel.from_xml_string(
        make_mjcf(side, cfg.scene, variant, timestep, ball_table))
    data = mujoco.MjData(model)
    corners = [
        int(mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SITE, f"corner_{i}"))
        for i in range(2 if variant == "planar" else 4)
    ]
    return Scene(model=model, data=data, variant=variant, l=side, config=cfg,
                 corner_sites=corners, ball_table=ball_table)


def home_state(scene: Scene) -> np.ndarray:
    """The resting start: cube centre at ``(0, l/2)`` upright, ball at ``ball_start``, at rest."""
    half = scene.l / 2
    z0 = scene.config.scene.table_height + half
    bx, bz = scene.config.scene.ball_start
    if scene.variant == "planar":
        q = np.array([0.0, z0, 0.0, bx, bz])
    else:
        q = np.array([0.0, 0.0, z0, 1.0, 0.0, 0.0, 0.0, bx, 0.0, bz])
    return np.concatenate([q, np.zeros(scene.nv)])


def target_state(scene: Scene, angle: float, cube_x0: float = 0.0) -> np.ndarray:
    """The goal ``x*``: cube pivoted by ``angle`` about its far bottom edge, at rest.

    The pivot edge is the far (+x) bottom edge of the cube that started with its centre at
    ``cube_x0``: ``p = (cube_x0 + l/2, table)``; the centre is then
    ``p + (-l/2 cos a + l/2 sin a, l/2 sin a + l/2 cos a)``. The ball goal is in contact with
    the near face at three quarters of its height, the position that holds the cube.
    """
    if not math.isfinite(angle):
        raise ValueError(f"angle must be finite, got {angle!r}")
    half = scene.l / 2
    r = scene.config.scene.ball_radius
    px, pz = cube_x0 + half, scene.config.scene.table_height
    c, s = math.cos(angle), math.sin(angle)
    centre = np.array([px - half * c + half * s, pz + half * s + half * c])

    def rotate(vx: float, vz: float) -> np.ndarray:
        return np.array([vx * c + vz * s, -vx * s + vz * c])

    face_point = centre + rotate(-half, 0.5 * half)
    ball = face_point + rotate(-r, 0.0)
    if scene.variant == "planar":
        q = np.array([centre[0], centre[1], angle, ball[0], ball[1]])
    else:
        quat = np.array([math.cos(angle / 2), 0.0, math.sin(angle / 2), 0.0])
        q = np.concatenate([[centre[0], 0.0, centre[1]], quat, [ball[0], 0.0, ball[1]]])
    return np.concatenate([q, np.zeros(scene.nv)])


def build_mpc(scene: Scene, config: MPCConfig, cube_x0: float = 0.0) -> MPC:
    """The MPC of ``config`` for ``scene``'s state layout; goal from :func:`target_state`.

    Parameters
    ----------
    scene
        The controller's scene (its state layout, force limit and goal geometry).
    config
        Weights, horizon, step and target angle.
    cube_x0
        Initial x of the cube's centre (the goal pivots about that cube's far edge).
    """
    weights = np.full(scene.nx, config.q_velocity)
    weights[scene.cube_pose_indices] = config.q_cube_pose
    weights[scene.ball_position_indices] = config.q_ball_position
    Q = np.diag(weights)
    return MPC(
        Q=Q,
        R=config.r_input * np.eye(scene.nu),
        Q_f=config.terminal_factor * Q,
        x_target=target_state(scene, config.target_angle, cube_x0),
        horizon=config.horizon,
        dt=config.dt,
        force_limit=scene.config.scene.force_limit,
        limits=cube_limits(scene),
    )


class Plant:
    """The closed-loop plant: MuJoCo with its own soft contact, stepped under a force command."""

    def __init__(self, scene: Scene) -> None:
        self.scene = scene
        self.data = mujoco.MjData(scene.model)

    def reset(self, x: np.ndarray) -> None:
        """Set the state ``x = (q, v)``."""
        x = self.scene.check_state(x)
        mujoco.mj_resetData(self.scene.model, self.data)
        self.data.qpos[:] = x[: self.scene.nq]
        self.data.qvel[:] = x[self.scene.nq:]
        mujoco.mj_forward(self.scene.model, self.data)

    def state(self) -> np.ndarray:
        return np.concatenate([self.data.qpos, self.data.qvel]).copy()

    @property
    def time(self) -> float:
        return float(self.data.time)

    def _count(self, duration: float) -> int:
        """Plant steps in ``duration`` seconds (a whole number, at least one, of them:
        :func:`~c3bench.problems.config.whole_steps`)."""
        if not (math.isfinite(duration) and duration > 0):
            raise ValueError(f"duration must be a finite number > 0, got {duration!r}")
        step = float(self.scene.model.opt.timestep)
        if not whole_steps(duration, step):
            raise ValueError(f"duration {duration} is not a multiple of the plant step {step}")
        return round(duration / step)

    def step(self, u: np.ndarray, duration: float,
             observe: Callable[[int], None] | None = None) -> np.ndarray:
        """Hold the ball force ``u`` (zero-order hold) for ``duration`` seconds; return ``x``.

        ``duration`` must be a whole number of plant steps (to 1e-9 relative). ``observe(k)``,
        when given, is called after the ``k``-th plant step (from 1), e.g. to measure contact
        at the plant's rate.
        """
        u = self.scene.check_input(u)
        count = self._count(duration)
        self.data.ctrl[:] = u
        for k in range(count):
            mujoco.mj_step(self.scene.model, self.data)
            if observe is not None:
                observe(k + 1)
        return self.state()

    def step_with(self, control: Callable[[np.ndarray, float], np.ndarray],
                  duration: float, observe: Callable[[int], None] | None = None
                  ) -> np.ndarray:
        """Step ``duration`` seconds with ``u = control(x, s)`` recomputed every plant step
        (``s`` = seconds since the call), clipped to the force limit; return ``x``
        (``observe`` as in :meth:`step`)."""
        count = self._count(duration)
        step = float(self.scene.model.opt.timestep)
        limit = self.scene.config.scene.force_limit
        for k in range(count):
            u = self.scene.check_input(control(self.state(), k * step))
            self.data.ctrl[:] = np.clip(u, -limit, limit)
            mujoco.mj_step(self.scene.model, self.data)
            if observe is not None:
                observe(k + 1)
        return self.state()


def render_frames(scene: Scene, states: np.ndarray, width: int = 640,
                  height: int = 480) -> list[np.ndarray]:
    """Render every state of ``states`` (N x nx) to an RGB array, with one renderer.

    Needs an off-screen OpenGL backend (``MUJOCO_GL=egl``, chosen automatically when libEGL is
    installed, or ``osmesa``); raises :class:`RenderUnavailable` with the reason where none can
    create a context.
    """
    checked = [scene.check_state(x, f"states[{i}]") for i, x in enumerate(np.atleast_2d(states))]
    data = mujoco.MjData(scene.model)
    try:
        renderer = mujoco.Renderer(scene.model, height=height, width=width)
    except Exception as error:
        backend = os.environ.get("MUJOCO_GL", "(unset)")
        raise RenderUnavailable(
            f"no off-screen OpenGL context (MUJOCO_GL={backend}): {error}"
        ) from error
    camera = mujoco.MjvCamera()
    camera.lookat[:] = [0.05, 0.0, 0.15]
    camera.distance = 1.4
    camera.azimuth = 90.0
    camera.elevation = -10.0
    frames = []
    try:
        for x in checked:
            data.qpos[:] = x[: scene.nq]
            data.qvel[:] = x[scene.nq:]
            mujoco.mj_forward(scene.model, data)
            renderer.update_scene(data, camera=camera)
            frames.append(renderer.render().copy())
    finally:
        renderer.close()
    return frames


def render_frame(scene: Scene, x: np.ndarray, path: str | Path, width: int = 640,
                 height: int = 480) -> Path:
    """Render the scene at state ``x`` to a PNG file (see :func:`render_frames`)."""
    pixels = render_frames(scene, np.asarray(x, dtype=float)[None, :], width, height)[0]
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.image

    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    matplotlib.image.imsave(out, pixels)
    return out


def save_gif(frames: list[np.ndarray], path: str | Path, frame_time: float) -> Path:
    """Write RGB frames as an animated GIF, ``frame_time`` seconds per frame."""
    from PIL import Image

    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    images = [Image.fromarray(frame) for frame in frames]
    images[0].save(out, save_all=True, append_images=images[1:],
                   duration=max(1, round(1000 * frame_time)), loop=0)
    return out
