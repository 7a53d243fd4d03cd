"""C3+'s closed-form projection onto complementarity, and its registry backend.

For one pair, with weights ``w_lam, w_eta >= 0`` and a point ``(a, b) = (v_lam, v_eta)``:

    minimise   w_lam (lam - a)^2 + w_eta (eta - b)^2
    subject to lam >= 0,  eta >= 0,  lam * eta = 0.

The feasible set is the union of the two half-axes ``{eta = 0, lam >= 0}`` and
``{lam = 0, eta >= 0}``. On the first the best point is ``(max(a, 0), 0)`` with cost
``w_lam min(a, 0)^2 + w_eta b^2``; on the second ``(0, max(b, 0))`` with cost
``w_lam a^2 + w_eta min(b, 0)^2``. Since ``t^2 - min(t, 0)^2 = max(t, 0)^2``,

    cost(keep eta) - cost(keep lam) = w_lam max(a, 0)^2 - w_eta max(b, 0)^2,

so the optimum keeps ``lam`` iff ``sqrt(w_lam) max(a, 0) >= sqrt(w_eta) max(b, 0)``, and then
``(lam, eta) = (max(a, 0), 0)``; otherwise ``(lam, eta) = (0, max(b, 0))``. Ties (equal
weighted positive parts, both branches optimal) deterministically keep ``lam``. When both
``a, b <= 0`` the answer is ``(0, 0)`` either way.

C3+'s projection ``min ||delta - v||^2_U`` with diagonal ``U`` and no coupling between
``eta`` and ``(x, lam, u)`` is separable: ``x = v_x``, ``u = v_u``, and every pair takes the
closed form above.
"""

from __future__ import annotations

import numpy as np

from c3bench.problems.instance import Problem
from c3bench.solvers.base import Backend, Result, Settings, WarmStart
from c3bench.solvers.registry import register
from c3bench.solvers.timing import Stopwatch


def c3plus_projection(v_lam: np.ndarray, v_eta: np.ndarray, w_lam: np.ndarray | float,
                      w_eta: np.ndarray | float) -> tuple[np.ndarray, np.ndarray]:
    """Project every pair ``(v_lam_i, v_eta_i)`` onto ``{lam, eta >= 0, lam eta = 0}``.

    The norm is ``w_lam (lam - v_lam)^2 + w_eta (eta - v_eta)^2`` per pair; the member with
    the larger ``sqrt(w) max(v, 0)`` is kept (clipped at 0), the other set to 0; ties keep
    ``lam`` (see the module docstring for the derivation).

    Parameters
    ----------
    v_lam, v_eta
        Points to project (same shape, any number of dimensions).
    w_lam, w_eta
        Non-negative weights, broadcastable to ``v_lam``.

    Returns
    -------
    lam, eta
        The projection, arrays of ``v_lam``'s shape, in the inputs' floating type
        (``float32`` stays ``float32``; integers become ``float64``).
    """
    dtype = np.result_type(np.asarray(v_lam), np.asarray(v_eta), np.float32)
    a = np.asarray(v_lam, dtype=dtype)
    b = np.asarray(v_eta, dtype=dtype)
    if a.shape != b.shape:
        raise ValueError(f"v_lam and v_eta must have the same shape, got {a.shape} and "
                         f"{b.shape}")
    wl = np.broadcast_to(np.asarray(w_lam, dtype=dtype), a.shape)
    we = np.broadcast_to(np.asarray(w_eta, dtype=dtype), a.shape)
    if np.any(wl < 0) or np.any(we < 0):
        raise ValueError("weights must be >= 0")
    if not (np.all(np.isfinite(a)) and np.all(np.isfinite(b))
            and np.all(np.isfinite(wl)) and np.all(np.isfinite(we))):
        raise ValueError("points and weights must be finite")
    zero = dtype.type(0)
    a_plus = np.maximum(a, zero)
    b_plus = np.maximum(b, zero)
    keep_lam = np.sqrt(wl) * a_plus >= np.sqrt(we) * b_plus
    lam = np.where(keep_lam, a_plus, zero)
    eta = np.where(keep_lam, zero, b_plus)
    return lam, eta


def _separable_data(problem: Problem) -> tuple[np.ndarray, np.ndarray, str]:
    """Weights ``w = diag(P)/2`` and targets ``v`` of a separable projection, or a reason.

    ``1/2 P_ii z_i^2 + q_i z_i = w_i (z_i - v_i)^2 + const`` with ``w_i = P_ii / 2`` and
    ``v_i = -q_i / P_ii``; where ``P_ii = 0`` the target is taken from ``data["v"]`` (any
    value is optimal there when also ``q_i = 0``).
    """
    n = problem.n
    diagonal = np.diag(problem.P).copy()
    if np.max(np.abs(problem.P - np.diag(diagonal)), initial=0.0) > 0:
        return np.zeros(0), np.zeros(0), "P is not diagonal"
    positive = diagonal > 0
    if np.any(~positive & (problem.q != 0)):
        return np.zeros(0), np.zeros(0), "linear term on a variable with zero weight"
    target = np.zeros(n)
    if "v" in problem.data and np.shape(problem.data["v"]) == (n,):
        target = np.asarray(problem.data["v"], dtype=float).copy()
    target[positive] = -problem.q[positive] / diagonal[positive]
    return diagonal / 2.0, target, ""


class C3PlusClosedForm(Backend):
    """C3+'s projection in closed form (no iterations): exact for the ``c3plus`` variant."""

    name = "c3plus_closed_form"
    families = ("projection",)
    package = ""
    precisions = ("float64", "float32")
    description = "C3+ closed-form projection: keep the larger of sqrt(w) [v]_+ per pair"

    def accepts(self, problem: Problem) -> tuple[bool, str]:
        ok, reason = super().accepts(problem)
        if not ok:
            return ok, reason
        variant = problem.meta.get("variant")
        if variant != "c3plus":
            return False, (f"the closed form needs the separable c3plus variant; variant "
                           f"{variant!r} couples eta = E x + F lam + H u + c (use an MIQP "
                           "backend)")
        if problem.A is not None or problem.G is not None:
            return False, "the closed form takes no equality or inequality rows"
        pairs = problem.complementarity
        if pairs is None or pairs.size == 0:
            return False, "no complementarity pairs"
        members = pairs.ravel()
        if len(set(members.tolist())) != members.size:
            return False, "a variable belongs to two pairs"
        lb = problem.lb if problem.lb is not None else np.full(problem.n, -np.inf)
        ub = problem.ub if problem.ub is not None else np.full(problem.n, np.inf)
        free = np.ones(problem.n, dtype=bool)
        free[members] = False
        if np.any(np.isfinite(lb[free])) or np.any(np.isfinite(ub[free])):
            return False, "variables outside the pairs must be unbounded"
        if np.any(lb[members] != 0) or np.any(np.isfinite(ub[members])):
            return False, "pair members must have bounds [0, inf)"
        _, _, reason = _separable_data(problem)
        if reason:
            return False, reason
        return True, ""

    def solve(self, problem: Problem, settings: Settings,
              warm_start: WarmStart | None = None) -> Result:
        watch = Stopwatch()
        with watch.lap("build"):
            weights, target, reason = _separable_data(problem)
            if reason:
                return Result.failed(self.name, problem.name, "unsupported", reason)
            pairs = problem.complementarity
            dtype = np.float32 if settings.precision == "float32" else np.float64
            weights = weights.astype(dtype)
            target = target.astype(dtype)
        with watch.lap("solve"):
            x = target.copy()
            lam, eta = c3plus_projection(target[pairs[:, 0]], target[pairs[:, 1]],
                                         weights[pairs[:, 0]], weights[pairs[:, 1]])
            x[pairs[:, 0]] = lam
            x[pairs[:, 1]] = eta
        x64 = x.astype(np.float64)
        return Result(solver=self.name, problem=problem.name, found=True,
                      status="solved (closed form)", x=x64, iterations=0,
                      build_time=watch.get("build"), solve_time=watch.get("solve"),
                      objective=problem.objective(x64))


register(C3PlusClosedForm())
