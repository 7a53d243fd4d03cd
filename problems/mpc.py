"""The MPC cost and the horizon variable layout shared by every family and solver.

Cost (docs/mpc.md):

    J = sum_{k<T} (x_k - x*)^T Q (x_k - x*) + u_k^T R u_k  +  (x_T - x*)^T Q_f (x_T - x*),

with ``Q`` diagonal (cube pose ``q_cube_pose``, ball position ``q_ball_position``, every velocity
``q_velocity``), ``R = r_input I`` and ``Q_f = terminal_factor Q``; the weights for a scene are
built by :func:`c3bench.problems.scene.build_mpc`.

:class:`HorizonLayout` is the variable order of a horizon QP, ``z = (z_0, ..., z_{T-1}, x_T)``
with ``z_k = (x_k, lam_k, u_k, eta_k)`` (:data:`c3bench.problems.names.BLOCKS`).

Part of the plant-free core: imports neither MuJoCo nor CasADi.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from functools import lru_cache
from typing import Any

import numpy as np

from c3bench.problems.limits import Limits
from c3bench.problems.names import BLOCKS, Block


@dataclass
class MPC:
    """Weights, goal and limits of the MPC.

    Attributes
    ----------
    Q, R, Q_f
        Stage state weight, input weight and terminal weight.
    x_target
        Goal state ``x*``.
    horizon
        ``T``.
    dt
        Step (s).
    force_limit
        Bound on every input component (N).
    limits
        Box limits on inputs and predicted states (:class:`c3bench.problems.limits.Limits`)
        that a controller keeps in its QP step; ``None``: only ``force_limit`` (applied by
        clipping). The cube's are :func:`c3bench.problems.limits.cube_limits`.
    """

    Q: np.ndarray
    R: np.ndarray
    Q_f: np.ndarray
    x_target: np.ndarray
    horizon: int
    dt: float
    force_limit: float
    limits: Limits | None = None

    def __post_init__(self) -> None:
        if self.limits is not None and (self.limits.nx, self.limits.nu) != (self.nx, self.nu):
            raise ValueError(f"limits are for (nx, nu) = {(self.limits.nx, self.limits.nu)}, "
                             f"the MPC has {(self.nx, self.nu)}")

    @property
    def nx(self) -> int:
        """State dimension."""
        return int(self.Q.shape[0])

    @property
    def nu(self) -> int:
        """Input dimension."""
        return int(self.R.shape[0])

    def cost(self, xs: np.ndarray, us: np.ndarray) -> float:
        """``J`` for states ``xs`` (T+1 x nx) and inputs ``us`` (T x nu)."""
        errors = xs - self.x_target
        stage = np.einsum("ki,ij,kj->", errors[:-1], self.Q, errors[:-1])
        inputs = np.einsum("ki,ij,kj->", us, self.R, us)
        return float(stage + inputs + errors[-1] @ self.Q_f @ errors[-1])


def with_limits(mpc: MPC, limits: Limits | None) -> MPC:
    """A copy of ``mpc`` carrying ``limits``."""
    return replace(mpc, limits=limits)


@dataclass(frozen=True)
class HorizonLayout:
    """Variable order of a horizon QP: ``z = (z_0, ..., z_{T-1}, x_T)``.

    Each ``z_k = (x_k, lam_k, u_k, eta_k)`` (``eta`` absent when ``n_eta = 0``, as in C3's
    QP); the terminal state ``x_T`` closes the vector.
    """

    nx: int
    nlam: int
    nu: int
    n_eta: int
    horizon: int

    @property
    def step_size(self) -> int:
        """Length of one ``z_k``."""
        return self.nx + self.nlam + self.nu + self.n_eta

    @property
    def size(self) -> int:
        """Length of ``z``."""
        return self.horizon * self.step_size + self.nx

    def block_sizes(self) -> dict[str, int]:
        """Sizes of the blocks present in one ``z_k`` (keys :class:`Block`), in :data:`BLOCKS`
        order."""
        sizes: dict[str, int] = {Block.X: self.nx, Block.LAM: self.nlam, Block.U: self.nu,
                                 Block.ETA: self.n_eta}
        return {name: sizes[name] for name in BLOCKS if sizes[name] > 0}

    def offset(self, block: str) -> int:
        """Offset of ``block`` inside one ``z_k``."""
        position = 0
        for name, size in self.block_sizes().items():
            if name == block:
                return position
            position += size
        raise KeyError(f"no block {str(block)!r} in this layout")

    def index(self, k: int, block: str) -> slice:
        """Slice of ``block`` of step ``k`` in ``z`` (``k = T`` with block ``x`` is ``x_T``;
        memoised: a controller asks for the same slices every control step)."""
        return _layout_index(self, k, block)

    def _index(self, k: int, block: str) -> slice:
        """:meth:`index`, computed."""
        if k == self.horizon:
            if block != Block.X:
                raise KeyError("only x exists at k = T")
            start = self.horizon * self.step_size
            return slice(start, start + self.nx)
        if not 0 <= k < self.horizon:
            raise IndexError(f"step {k} outside 0..{self.horizon}")
        start = k * self.step_size + self.offset(block)
        return slice(start, start + self.block_sizes()[block])

    def split(self, z: np.ndarray) -> dict[str, np.ndarray]:
        """Per-block trajectories: ``x`` (T+1 x nx), ``lam``, ``u``, ``eta`` (T x n)."""
        z = np.asarray(z)
        steps = z[: self.horizon * self.step_size].reshape(self.horizon, self.step_size)
        out: dict[str, np.ndarray] = {}
        for name, size in self.block_sizes().items():
            start = self.offset(name)
            out[name] = steps[:, start:start + size]
        out[Block.X] = np.vstack([out[Block.X], z[self.horizon * self.step_size:][None, :]])
        return out

    def to_json(self) -> dict[str, Any]:
        """The layout as JSON (sizes and the block order)."""
        return {"nx": self.nx, "nlam": self.nlam, "nu": self.nu, "n_eta": self.n_eta,
                "horizon": self.horizon, "order": list(self.block_sizes())}

    @classmethod
    def from_json(cls, table: dict[str, Any]) -> HorizonLayout:
        """The layout written by :meth:`to_json`."""
        return cls(nx=int(table["nx"]), nlam=int(table["nlam"]), nu=int(table["nu"]),
                   n_eta=int(table["n_eta"]), horizon=int(table["horizon"]))


@lru_cache(maxsize=1024)
def _layout_index(layout: HorizonLayout, k: int, block: str) -> slice:
    """:meth:`HorizonLayout.index`, memoised (layouts are frozen, so hashable)."""
    return layout._index(k, block)
