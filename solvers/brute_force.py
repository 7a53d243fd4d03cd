"""The global optimum of one control step's MPCC by enumerating the contact modes of every step.

The MPCC (:func:`c3bench.problems.families.mpcc`) is

    minimise    J(x, u) = sum_{k<T} (x_k - x*)^T Q (x_k - x*) + u_k^T R u_k
                          + (x_T - x*)^T Q_f (x_T - x*)
    subject to  x_0 = x0,  x_{k+1} = A x_k + B u_k + D lam_k + d,  |u_k| <= force_limit,
                eta_k = E x_k + F lam_k + H u_k + c,   0 <= lam_k  perp  eta_k >= 0.

A *mode* chooses, for each of the ``m T`` pairs, the member fixed at zero; the other member
keeps its sign constraint (``lam_i >= 0`` or ``eta_i >= 0``). The feasible set is the union
of the ``2^(m T)`` mode polyhedra and the cost is convex on each, so the global optimum is the
best mode optimum (a pair with both members at zero lies in both of its modes, so two-way
modes suffice *because* the sign constraint of the free member is kept). Each mode's convex
QP is solved by :func:`c3bench.solvers.modes.solve_mode`: Clarabel at gap and feasibility
tolerances ``1e-10``, then an exact null-space solve on the face Clarabel's point identifies.

The count of modes is limited (:data:`MAX_MODE_PAIRS` pairs: ``2^12 = 4096`` QPs, a few
seconds); beyond it :class:`~c3bench.problems.errors.InputError` is raised (an MIQP backend
is the tool there).

References
----------
P. J. Goulart and Y. Chen, "Clarabel: An interior-point solver for conic programs with
quadratic objectives", arXiv:2405.12762, 2024 (the QP of one mode).

Z.-Q. Luo, J.-S. Pang and D. Ralph, *Mathematical Programs with Equilibrium Constraints*,
Cambridge University Press, 1996 (the MPCC as a union of the pieces of its modes).
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import numpy as np

from c3bench.problems import families
from c3bench.problems.errors import InputError
from c3bench.problems.lcs import LCS
from c3bench.problems.mpc import MPC, HorizonLayout
from c3bench.solvers.modes import solve_mode
from c3bench.solvers.timing import single_thread_blas

MAX_MODE_PAIRS = 12
"""Most complementarity pairs over the horizon (``m T``) that are enumerated."""


@dataclass
class Trajectory:
    """A horizon of the MPCC.

    Attributes
    ----------
    x
        (T + 1, nx) states.
    lam, u, eta
        (T, nlam), (T, nu), (T, nlam) contact forces, inputs and LCS gaps.
    lam_zero
        (T, nlam) booleans: the mode (True where ``lam`` was fixed at zero, else ``eta``).
    modes, feasible
        Modes solved and modes found feasible.
    """

    x: np.ndarray
    lam: np.ndarray
    u: np.ndarray
    eta: np.ndarray
    lam_zero: np.ndarray
    modes: int
    feasible: int


def global_mpc_optimum(lcs: LCS, mpc: MPC, x0: np.ndarray,
                       max_pairs: int = MAX_MODE_PAIRS) -> tuple[float, Trajectory]:
    """Global optimum ``J*`` of the MPCC from ``x0`` and its trajectory (module docstring).

    Parameters
    ----------
    lcs, mpc
        Model and cost (``mpc.force_limit`` bounds every input).
    x0
        Initial state.
    max_pairs
        Largest ``m T`` enumerated (``2^(m T)`` convex QPs).

    Returns
    -------
    cost, trajectory
        ``J*`` (the MPC cost, constant included) and the optimal horizon.

    Raises
    ------
    InputError
        ``m T > max_pairs``, bad shapes, or no mode feasible.
    """
    pairs = lcs.nlam * mpc.horizon
    if pairs > max_pairs:
        raise InputError(f"{pairs} complementarity pairs (m T = {lcs.nlam} x {mpc.horizon}) "
                         f"exceed max_pairs={max_pairs} (2^{pairs} convex QPs); use an MIQP "
                         "backend")
    try:
        problem = families.mpcc("brute-force", lcs, mpc, np.asarray(x0, dtype=float))
    except ValueError as error:
        raise InputError(str(error)) from error
    layout = HorizonLayout(lcs.nx, lcs.nlam, lcs.nu, lcs.nlam, mpc.horizon)
    members = np.asarray(problem.complementarity, dtype=np.int64).reshape(-1, 2)
    best_cost, best_x, best_choice = math.inf, None, None
    modes = feasible = 0
    with single_thread_blas():  # thousands of tiny factorisations: threads only cost
        for choice in itertools.product((0, 1), repeat=pairs):
            zero = members[np.arange(pairs), np.array(choice, dtype=np.int64)] if pairs \
                else np.zeros(0, dtype=np.int64)
            solution = solve_mode(problem, zero)
            modes += 1
            if solution.x is None:
                continue
            feasible += 1
            if solution.objective < best_cost:
                best_cost, best_x, best_choice = solution.objective, solution.x, choice
    if best_x is None or best_choice is None:
        raise InputError(f"no contact mode of the MPCC is feasible ({modes} tried)")
    parts = layout.split(best_x)
    lam_zero = np.array(best_choice).reshape(mpc.horizon, lcs.nlam) == 0
    trajectory = Trajectory(x=parts["x"], lam=parts["lam"], u=parts["u"], eta=parts["eta"],
                            lam_zero=lam_zero, modes=modes, feasible=feasible)
    return float(best_cost), trajectory
