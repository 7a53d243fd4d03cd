"""Recover the MPC a stored horizon instance was built from, and check the rebuilt instance.

Backends that run the controller on a stored instance (``c3_admm`` / ``c3plus_admm`` on an
``mpcc``; the controller-sequence cell on a ``c3plus_qp`` / ``c3_qp`` step) need the MPC
behind it. Both read it from the cost the same way (:func:`mpc_from_cost`), then rebuild the
instance with the family's own constructor in :mod:`c3bench.problems.families` and accept the
MPC only when the rebuilt instance equals the stored one (:func:`mismatches`).
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import numpy as np

from c3bench.problems.instance import Problem
from c3bench.problems.limits import Limits
from c3bench.problems.mpc import MPC, HorizonLayout
from c3bench.problems.names import Block

__all__ = ["REBUILD_TOLERANCE", "mismatches", "mpc_from_cost"]

REBUILD_TOLERANCE = 1e-9
"""Relative tolerance (and of ``max(1, max |P|)`` absolute) of :func:`mismatches`."""


def mpc_from_cost(problem: Problem, layout: HorizonLayout, force_limit: float,
                  limits: Limits | None, rho: Mapping[str, float] | None = None) -> MPC:
    """The MPC whose stage cost the horizon instance ``problem`` carries.

    With ``rho`` the consensus weights folded into the cost (``None``: none, as in an
    ``mpcc``): ``Q = P_{x_0 x_0} / 2 - rho_x I``, ``R = P_{u_0 u_0} / 2 - rho_u I``,
    ``Q_f = P_{x_T x_T} / 2`` and ``x*`` the least-squares solution of
    ``2 Q_f x* = -q_{x_T}`` (a component of ``x*`` with zero weight is irrelevant to the
    cost). ``problem.lcs`` gives ``dt``.
    """
    if problem.lcs is None:
        raise ValueError("the instance has no LCS")
    rho = rho or {}
    T = layout.horizon
    sx, su = layout.index(0, Block.X), layout.index(0, Block.U)
    sT = layout.index(T, Block.X)
    Q = problem.P[sx, sx] / 2.0 - float(rho.get(Block.X, 0.0)) * np.eye(layout.nx)
    R = problem.P[su, su] / 2.0 - float(rho.get(Block.U, 0.0)) * np.eye(layout.nu)
    Q_f = problem.P[sT, sT] / 2.0
    x_target = np.linalg.lstsq(2.0 * Q_f, -problem.q[sT], rcond=None)[0]
    return MPC(Q=Q, R=R, Q_f=Q_f, x_target=x_target, horizon=T, dt=problem.lcs.dt,
               force_limit=force_limit, limits=limits)


def mismatches(rebuilt: Problem, stored: Problem,
               tolerance: float = REBUILD_TOLERANCE) -> list[str]:
    """Names of the parts where ``rebuilt`` and ``stored`` differ: ``P``, ``q``, ``A``,
    ``b``, ``lb``, ``ub``, ``complementarity`` (equal to ``tolerance`` relative and
    ``tolerance * max(1, max |P|)`` absolute; both absent counts as equal; infinite bounds
    must match exactly) and the objective offset."""
    scale = max(1.0, float(np.max(np.abs(stored.P))))
    wrong = [name for name in ("P", "q", "A", "b", "lb", "ub", "complementarity")
             if not _same(getattr(rebuilt, name), getattr(stored, name), tolerance, scale)]
    if not math.isclose(rebuilt.objective_offset, stored.objective_offset,
                        rel_tol=tolerance, abs_tol=tolerance * scale):
        wrong.append("offset")
    return wrong


def _same(a: np.ndarray | None, b: np.ndarray | None, tolerance: float, scale: float
          ) -> bool:
    if a is None or b is None:
        return a is None and b is None
    a, b = np.asarray(a), np.asarray(b)
    return a.shape == b.shape and bool(np.allclose(a, b, rtol=tolerance,
                                                   atol=tolerance * scale, equal_nan=False))
