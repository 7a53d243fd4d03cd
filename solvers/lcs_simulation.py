"""Closed loop on an LCS itself: the plant is the LCS (tests of controllers on any LCS).

Each step the controller maps the state to an input and the contact forces solve the step's LCP
by Lemke's method (Lemke, "Bimatrix equilibrium points and mathematical programming",
Management Science 11(7), 1965; :func:`c3bench.solvers.lcp.lemke`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from c3bench.problems.errors import C3BenchError, InputError
from c3bench.problems.lcs import LCS
from c3bench.solvers.lcp import lemke

Controller = Callable[[np.ndarray], np.ndarray]
"""A state-feedback controller ``u = controller(x)``."""


class SimulationFailed(C3BenchError, RuntimeError):
    """An LCP of the rollout had no solution found (cannot happen for a P-matrix ``F``)."""


@dataclass
class Simulation:
    """A closed-loop rollout of an LCS.

    Attributes
    ----------
    states
        (steps + 1, nx) states, ``x_0`` first.
    inputs
        (steps, nu) inputs the controller returned (applied as given).
    forces
        (steps, nlam) contact forces from the LCP of each step.
    """

    states: np.ndarray
    inputs: np.ndarray
    forces: np.ndarray


def simulate(lcs: LCS, x0: np.ndarray, controller: Controller, steps: int) -> Simulation:
    """Roll the LCS itself under ``controller`` (the plant is the LCS).

    Each step: ``u = controller(x)``, ``lam`` solves ``0 <= lam perp F lam + E x + H u + c >= 0``
    (Lemke's method, :func:`c3bench.solvers.lcp.lemke`), ``x <- A x + B u + D lam + d``.

    Raises
    ------
    InputError
        Bad ``x0``, ``steps`` or a controller output of the wrong shape / non-finite.
    SimulationFailed
        Lemke's method found no solution of a step's LCP.
    """
    x = np.asarray(x0, dtype=float)
    if x.shape != (lcs.nx,) or not np.all(np.isfinite(x)):
        raise InputError(f"x0 must be a finite vector of shape ({lcs.nx},)")
    if not isinstance(steps, int) or steps < 0:
        raise InputError(f"steps must be an integer >= 0, got {steps!r}")
    states, inputs, forces = [x], [], []
    for step in range(steps):
        u = np.asarray(controller(x), dtype=float).reshape(-1)
        if u.shape != (lcs.nu,) or not np.all(np.isfinite(u)):
            raise InputError(f"the controller returned {u!r} at step {step}; expected a finite "
                             f"vector of shape ({lcs.nu},)")
        solution = lemke(lcs.F, lcs.lcp_offset(x, u))
        if not solution.found or solution.z is None:
            raise SimulationFailed(f"Lemke found no contact force at step {step}: "
                                   f"{solution.status}")
        x = lcs.next_state(x, u, solution.z)
        states.append(x)
        inputs.append(u)
        forces.append(solution.z)
    return Simulation(states=np.array(states),
                      inputs=np.array(inputs).reshape(steps, lcs.nu),
                      forces=np.array(forces).reshape(steps, lcs.nlam))
