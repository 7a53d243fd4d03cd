"""A non-cube LCS: a point mass on a line between two soft walls (docs/toy_lcs.md).

A mass ``M`` at position ``p`` with velocity ``v`` is pushed by the input force ``u``; a wall
at ``-L`` pushes it right with the contact force ``lam_1 >= 0`` and a wall at ``+L`` pushes it
left with ``lam_2 >= 0``. Semi-implicit Euler with step ``dt``:

    v_{k+1} = v_k + dt / M (u_k + lam_1 - lam_2),
    p_{k+1} = p_k + dt v_{k+1} = p_k + dt v_k + dt^2 / M (u_k + lam_1 - lam_2).

The walls are springs of stiffness ``K``: a wall's force is ``K`` times the penetration of the
*next* position, ``lam_1 = K max(0, -(p_{k+1} + L))`` and ``lam_2 = K max(0, p_{k+1} - L)``.
With the gaps ``p_{k+1} + L`` and ``L - p_{k+1}`` this is the complementarity

    0 <= lam_1  perp  p_{k+1} + L + lam_1 / K >= 0,
    0 <= lam_2  perp  L - p_{k+1} + lam_2 / K >= 0,

so with ``x = (p, v)`` and ``a = dt^2 / M``, ``b = dt / M`` the LCS
``x' = A x + B u + D lam + d``, ``0 <= lam perp E x + F lam + H u + c >= 0`` has

    A = [[1, dt], [0, 1]],   B = [[a], [b]],   D = [[a, -a], [b, -b]],   d = 0,
    E = [[1, dt], [-1, -dt]],   F = [[a + 1/K, -a], [-a, a + 1/K]],
    H = [[a], [-a]],   c = [L, L].

``F = a [[1, -1], [-1, 1]] + I / K`` is symmetric positive definite (eigenvalues ``1/K`` and
``2 a + 1/K``), a P-matrix, so every step's LCP has exactly one solution (Cottle, Pang and
Stone 1992, theorem 3.3.7) and :func:`c3bench.solvers.lcs_simulation.simulate` is well defined.

:func:`point_mass_mpc` sets a target position, by default beyond the right wall, so the
optimal plan presses against the wall: the static optimum of the stage cost
``q_p (p - p*)^2 + r u^2`` over the resting states ``u = lam_2 = K (p - L)`` is
``p_rest = (q_p p* + r K^2 L) / (q_p + r K^2)`` (:func:`resting_position`).

Part of the plant-free core: numpy only (the simulator imports Lemke's method on call).

References
----------
R. W. Cottle, J.-S. Pang and R. E. Stone, *The Linear Complementarity Problem*, Academic
Press, 1992.

D. E. Stewart, "Rigid-body dynamics with friction and impact", SIAM Review 42(1), 3-39, 2000
(time-stepping contact with the position gap at the end of the step).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from c3bench.problems.errors import InputError
from c3bench.problems.lcs import LCS, check_dt
from c3bench.problems.mpc import MPC

"""A state-feedback law: state ``x`` (nx,) -> input ``u`` (nu,)."""


@dataclass(frozen=True)
class PointMassParameters:
    """Physical parameters of the point mass between two soft walls.

    Attributes
    ----------
    dt
        Time step (s).
    mass
        ``M`` (kg).
    stiffness
        ``K`` (N/m) of both walls.
    half_width
        ``L`` (m): the walls are at ``-L`` and ``+L``.
    """

    dt: float = 0.05
    mass: float = 1.0
    stiffness: float = 50.0
    half_width: float = 0.5

    def __post_init__(self) -> None:
        check_dt(self.dt)
        for name in ("mass", "stiffness", "half_width"):
            value = getattr(self, name)
            if not (isinstance(value, int | float) and np.isfinite(value) and value > 0):
                raise InputError(f"{name} must be a finite number > 0, got {value!r}")


def point_mass_lcs(dt: float = 0.05, mass: float = 1.0, stiffness: float = 50.0,
                   half_width: float = 0.5) -> LCS:
    """The LCS of the point mass between two soft walls (module docstring for the matrices)."""
    params = PointMassParameters(dt, mass, stiffness, half_width)
    a = params.dt**2 / params.mass
    b = params.dt / params.mass
    compliance = 1.0 / params.stiffness
    return LCS(
        A=np.array([[1.0, params.dt], [0.0, 1.0]]),
        B=np.array([[a], [b]]),
        D=np.array([[a, -a], [b, -b]]),
        d=np.zeros(2),
        E=np.array([[1.0, params.dt], [-1.0, -params.dt]]),
        F=np.array([[a + compliance, -a], [-a, a + compliance]]),
        H=np.array([[a], [-a]]),
        c=np.full(2, params.half_width),
        dt=params.dt,
        contact_model="anitescu",
        n_contacts=2,
        friction_directions=0,
        phi=np.full(2, params.half_width),
    )


def point_mass_mpc(target_position: float = 0.7, horizon: int = 4, dt: float = 0.05,
                   q_position: float = 10.0, q_velocity: float = 1.0, r_input: float = 0.01,
                   terminal_factor: float = 10.0, force_limit: float = 20.0) -> MPC:
    """The MPC of the point mass: ``Q = diag(q_position, q_velocity)``, ``R = r_input``,
    ``Q_f = terminal_factor Q``, goal ``(target_position, 0)``, ``|u| <= force_limit``.

    The default target (0.7 m) lies beyond the right wall at ``L = 0.5``: the optimum presses
    against the wall.
    """
    if not isinstance(horizon, int) or horizon < 1:
        raise InputError(f"horizon must be an integer >= 1, got {horizon!r}")
    Q = np.diag([float(q_position), float(q_velocity)])
    return MPC(Q=Q, R=np.array([[float(r_input)]]), Q_f=float(terminal_factor) * Q,
               x_target=np.array([float(target_position), 0.0]), horizon=horizon,
               dt=check_dt(dt), force_limit=float(force_limit))


def resting_position(target_position: float, q_position: float, r_input: float,
                     stiffness: float, half_width: float) -> float:
    """``p_rest = (q_p p* + r K^2 L) / (q_p + r K^2)``: the static optimum of the stage cost
    at rest against the right wall (valid for ``p* > L``; module docstring)."""
    weight = r_input * stiffness**2
    return float((q_position * target_position + weight * half_width) / (q_position + weight))
