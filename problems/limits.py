"""Box limits of the MPC: input bounds and state bounds as a controller keeps them.

``u_lower <= u_k <= u_upper`` for every input of the horizon and ``x_lower <= x_k <= x_upper``
for every predicted state (``k >= 1``; ``x_0`` is the measurement). The reference C3
implementation keeps input and state limits inside its QP step (A. Aydinoglu, A. Wei,
W.-C. Huang, M. Posa, "Consensus Complementarity Control for Multi-Contact MPC", IEEE T-RO 2024,
arXiv:2304.11259, Sec. IV); :func:`c3bench.problems.families.consensus_qp` writes them as
qpsolvers' bounds ``lb <= z <= ub``.

The cube task's limits (:func:`cube_limits`): ``|u_i| <= force_limit`` per component, the ball
centre above the table (``z_ball >= table_height + ball_radius``) and the ball workspace box of
the ``[limits]`` table of ``cube_tipping.toml``.

Part of the plant-free core: numpy only (the scene is typed for the type checker only).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from c3bench.problems.errors import InputError

if TYPE_CHECKING:  # type only: importing the scene at run time would load MuJoCo
    from c3bench.problems.scene import Scene

_FIELDS = ("u_lower", "u_upper", "x_lower", "x_upper")


def _as_bound(name: str, value: Any) -> np.ndarray:
    """A read-only float copy of a 1-D bound vector; ``InputError`` when it is not one."""
    array = np.array(value, dtype=float)
    if array.ndim != 1:
        raise InputError(f"{name} must be a 1-D vector, got shape {array.shape}")
    if np.any(np.isnan(array)):
        raise InputError(f"{name} has NaN entries")
    array.setflags(write=False)
    return array


def _check_pair(kind: str, lower: np.ndarray, upper: np.ndarray) -> None:
    if lower.shape != upper.shape:
        raise InputError(f"{kind}_lower {lower.shape} and {kind}_upper {upper.shape} differ")
    if np.any(lower == np.inf) or np.any(upper == -np.inf):
        raise InputError(f"{kind}_lower may not be +inf nor {kind}_upper -inf")
    wrong = np.flatnonzero(lower > upper)
    if wrong.size:
        i = int(wrong[0])
        raise InputError(f"{kind}_lower[{i}] = {lower[i]} > {kind}_upper[{i}] = {upper[i]}")


@dataclass(frozen=True, eq=False)
class Limits:
    """Box bounds on the inputs and states of the MPC (``+-inf`` where unbounded).

    Attributes
    ----------
    u_lower, u_upper
        ``(nu,)``: ``u_lower <= u_k <= u_upper`` for ``k < T``.
    x_lower, x_upper
        ``(nx,)``: ``x_lower <= x_k <= x_upper`` for ``1 <= k <= T``.
    """

    u_lower: np.ndarray
    u_upper: np.ndarray
    x_lower: np.ndarray
    x_upper: np.ndarray

    def __post_init__(self) -> None:
        for name in _FIELDS:
            object.__setattr__(self, name, _as_bound(name, getattr(self, name)))
        _check_pair("u", self.u_lower, self.u_upper)
        _check_pair("x", self.x_lower, self.x_upper)

    @property
    def nu(self) -> int:
        """Input dimension."""
        return int(self.u_lower.size)

    @property
    def nx(self) -> int:
        """State dimension."""
        return int(self.x_lower.size)

    @property
    def n_finite(self) -> int:
        """Number of finite bounds (lower and upper counted apart) on one ``(u, x)`` pair."""
        return int(sum(np.isfinite(getattr(self, name)).sum() for name in _FIELDS))

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Limits):
            return NotImplemented
        return all(np.array_equal(getattr(self, n), getattr(other, n)) for n in _FIELDS)

    __hash__ = None  # type: ignore[assignment]  # arrays: equal by value, not hashable

    @classmethod
    def unbounded(cls, nx: int, nu: int) -> Limits:
        """No limit at all."""
        return cls(np.full(nu, -np.inf), np.full(nu, np.inf), np.full(nx, -np.inf),
                   np.full(nx, np.inf))

    @classmethod
    def force_only(cls, nx: int, nu: int, force_limit: float) -> Limits:
        """``|u_i| <= force_limit``, states free (the former ``input_bounds`` option)."""
        if not (np.isfinite(force_limit) and force_limit > 0):
            raise InputError(f"force_limit must be finite and > 0, got {force_limit!r}")
        return cls(np.full(nu, -force_limit), np.full(nu, force_limit),
                   np.full(nx, -np.inf), np.full(nx, np.inf))

    def intersect(self, other: Limits) -> Limits:
        """The tighter of two limits, bound by bound."""
        if (self.nx, self.nu) != (other.nx, other.nu):
            raise InputError(f"limits of (nx, nu) = {(self.nx, self.nu)} and "
                             f"{(other.nx, other.nu)} cannot be intersected")
        return Limits(np.maximum(self.u_lower, other.u_lower),
                      np.minimum(self.u_upper, other.u_upper),
                      np.maximum(self.x_lower, other.x_lower),
                      np.minimum(self.x_upper, other.x_upper))

    def to_json(self) -> dict[str, list[float | None]]:
        """The bounds as JSON lists, ``None`` for an infinite bound."""
        return {name: [None if not np.isfinite(v) else float(v) for v in getattr(self, name)]
                for name in _FIELDS}

    @classmethod
    def from_json(cls, table: dict[str, Any]) -> Limits:
        """The limits written by :meth:`to_json` (``None`` is ``-inf`` in a lower bound and
        ``+inf`` in an upper bound); ``InputError`` naming a missing or unknown key."""
        if not isinstance(table, dict):
            raise InputError(f"limits must be a JSON object, got {type(table).__name__}")
        missing = [n for n in _FIELDS if n not in table]
        unknown = sorted(set(table) - set(_FIELDS))
        if missing or unknown:
            raise InputError(f"limits: missing {missing}, unknown {unknown}")
        values = {}
        for name in _FIELDS:
            infinity = -np.inf if name.endswith("lower") else np.inf
            values[name] = np.array([infinity if v is None else float(v) for v in table[name]])
        return cls(**values)


def cube_limits(scene: Scene) -> Limits:
    """The cube task's limits for ``scene``'s state layout.

    * ``-force_limit <= u_i <= force_limit`` on every ball force component;
    * ball x (and y, spatial) inside ``[limits] ball_x`` (``ball_y``);
    * ball z in ``[max(ball_z[0], table_height + ball_radius), ball_z[1]]``: the ball centre
      stays above the table (a ball resting on the table has ``z = table_height + r``).

    Cube pose and every velocity are free. ``scene`` is a
    :class:`c3bench.problems.scene.Scene` (only its sizes, ball indices and config are read).
    """
    config = scene.config
    limit = config.scene.force_limit
    bounds = Limits.force_only(scene.nx, scene.nu, limit)
    x_lower, x_upper = bounds.x_lower.copy(), bounds.x_upper.copy()
    ball = np.asarray(scene.ball_position_indices)
    ranges = [config.limits.ball_x, config.limits.ball_y][: ball.size - 1]
    for index, (low, high) in zip(ball[:-1], ranges, strict=True):
        x_lower[index], x_upper[index] = low, high
    floor = config.scene.table_height + config.scene.ball_radius
    x_lower[ball[-1]] = max(config.limits.ball_z[0], floor)
    x_upper[ball[-1]] = config.limits.ball_z[1]
    return Limits(bounds.u_lower, bounds.u_upper, x_lower, x_upper)
