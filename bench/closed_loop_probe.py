"""What the plant did between two recorded states: contact and the cube's height, measured
after every plant step (1 ms) of a closed-loop run.

:class:`ContactProbe` is called by :func:`bench.closed_loop.advance` after each plant step and
keeps, per control period, the quantities of
:class:`~c3bench.bench.closed_loop_metrics.PlantContact`; :mod:`bench.closed_loop`
re-exports it.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import mujoco
import numpy as np

from c3bench.bench.closed_loop_metrics import PlantContact
from c3bench.problems.scene import Scene

GAP_RANGE = 10.0
"""``distmax`` of ``mj_geomDistance`` (m): signed distances are exact below it."""

__all__ = ["GAP_RANGE", "ContactProbe", "box_clearance"]


def box_clearance(centre_z: float, vertical: Sequence[float], half: Sequence[float],
                  table: float) -> float:
    """Height (m) of a box's lowest point above the table at height ``table``: its centre
    height ``centre_z`` less ``sum_i |R_zi| s_i``, with ``vertical`` the third row of its
    rotation matrix (``R_z*``) and ``half`` its half sizes ``s``. Plain floats, not arrays: the
    probe calls it after every plant step, and numpy's sum of three costs about three times
    as much."""
    r_x, r_y, r_z = vertical
    h_x, h_y, h_z = half
    return centre_z - abs(r_x) * h_x - abs(r_y) * h_y - abs(r_z) * h_z - table


class ContactProbe:
    """Running contact statistics of a control period, updated after every plant step.

    After each plant step :meth:`observe` puts the plant's positions into a scratch
    ``MjData``, runs ``mj_kinematics`` and takes the ball-cube signed distance with
    ``mj_geomDistance``, the same function as :func:`bench.closed_loop.cube_geometry`, and
    the height of the cube's lowest point above the table (:func:`box_clearance`, as in
    :func:`bench.closed_loop.cube_geometry`; 1-7 us per plant step with the
    bookkeeping on the 2-core VM, against about 4 us for the plant step), and keeps, per
    period, the
    quantities of :class:`~c3bench.bench.closed_loop_metrics.PlantContact`. Planar scene:
    the impact speed is the ball's velocity minus that of the cube's material point at the
    ball's centre, ``(v_x + omega r_z, v_z - omega r_x)`` with ``r`` from the cube centre to
    the ball's (theta about +y).

    Parameters
    ----------
    scene
        The plant's scene.
    contact_gap, away_gap
        Signed distances (m) at or below which the ball touches, above which it is away.
    air_gap
        Height (m) of the cube's lowest point above the table beyond which the cube is
        airborne (:func:`bench.closed_loop.simulate` passes the labels'
        :attr:`~bench.closed_loop_labels.LabelRules.air_gap`).
    """

    def __init__(self, scene: Scene, contact_gap: float, away_gap: float,
                 air_gap: float) -> None:
        self.scene = scene
        self.model = scene.model
        self.data = mujoco.MjData(scene.model)
        self.probe_qpos = self.data.qpos
        self.qpos, self.qvel = self.probe_qpos, self.data.qvel  # until :meth:`watch`
        self.ball, self.cube = scene.geom("ball"), scene.geom("cube")
        self.height_index = int(scene.ball_position_indices[-1])
        self.height_offset = scene.config.scene.ball_radius + scene.config.scene.table_height
        self.table = float(scene.config.scene.table_height)
        self.cube_centre = self.data.geom_xpos[self.cube]  # views, updated by mj_kinematics
        self.cube_vertical = self.data.geom_xmat[self.cube][6:9]
        self.cube_half: list[float] = [float(h) for h in self.model.geom_size[self.cube]]
        self.step = float(scene.model.opt.timestep)
        self.contact_gap, self.away_gap = float(contact_gap), float(away_gap)
        self.air_gap = float(air_gap)
        self.periods: list[tuple[float, ...]] = []
        self.start = 0.0
        self.begin(0.0)

    def begin(self, start: float) -> None:
        """Start a control period at time ``start`` (s)."""
        self.start = start
        self.min_gap = self.min_height = math.inf
        self.clearance = -math.inf
        self.touching = self.away = self.airborne = 0
        self.touch_time = self.touch_speed = math.nan

    def watch(self, data: mujoco.MjData) -> None:
        """Observe the plant whose ``MjData`` is ``data`` (its arrays' views are kept)."""
        self.qpos, self.qvel = data.qpos, data.qvel

    def observe(self, index: int) -> None:
        """Take the watched plant's state after the period's ``index``-th plant step (from
        1)."""
        qpos = self.qpos
        self.probe_qpos[:] = qpos
        mujoco.mj_kinematics(self.model, self.data)
        gap = mujoco.mj_geomDistance(self.model, self.data, self.ball, self.cube, GAP_RANGE,
                                     None)
        if gap < self.min_gap:
            self.min_gap = gap
        height = float(qpos[self.height_index]) - self.height_offset
        if height < self.min_height:
            self.min_height = height
        clearance = box_clearance(self.cube_centre.item(2), self.cube_vertical.tolist(),
                                  self.cube_half, self.table)
        if clearance > self.clearance:
            self.clearance = clearance
        if clearance > self.air_gap:
            self.airborne += 1
        if gap <= self.contact_gap:
            self.touching += 1
            if self.touching == 1:
                self.touch_time = self.start + index * self.step
                self.touch_speed = self._relative_speed(qpos, self.qvel)
        if gap > self.away_gap:
            self.away += 1

    @staticmethod
    def _relative_speed(qpos: np.ndarray, qvel: np.ndarray) -> float:
        r_x, r_z = qpos[3] - qpos[0], qpos[4] - qpos[1]
        omega = qvel[2]
        return math.hypot(qvel[3] - qvel[0] - omega * r_z, qvel[4] - qvel[1] + omega * r_x)

    def end(self) -> None:
        """Close the period."""
        self.periods.append((self.min_gap, self.min_height, self.touching, self.away,
                             self.touch_time, self.touch_speed, self.clearance,
                             self.airborne))

    def record(self) -> PlantContact:
        """The closed periods as a :class:`PlantContact`."""
        table = np.array(self.periods, dtype=float).reshape(len(self.periods), 8)
        return PlantContact(
            plant_step=self.step, contact_gap=self.contact_gap, away_gap=self.away_gap,
            min_gap=table[:, 0], min_height=table[:, 1], contact_time=table[:, 2] * self.step,
            away_time=table[:, 3] * self.step, touch_time=table[:, 4],
            touch_speed=table[:, 5], air_gap=self.air_gap, cube_clearance=table[:, 6],
            cube_air_time=table[:, 7] * self.step)
