"""The C3+ QP step of a stored ``c3plus_qp`` instance, solved by :mod:`solvers.riccati`.

**Registry backend** ``c3plus_riccati``
(:class:`c3bench.solvers.backends.c3plus_riccati.RiccatiBackend`, family ``c3plus_qp``,
float64 and float32; :func:`solve_c3plus_qp` here): reads the per-step blocks of ``P`` and
``q`` (rejects a ``P`` that is not block diagonal in time), the LCS and ``x0``, checks that
``A z = b`` is the LCS's structure, solves, and returns the equality duals from the
stationarity conditions of the ``x``, ``eta`` columns, by a backward recursion in float64
(``y_eta_k = -(P z + q)_{eta_k}``, ``y_{T-1} = -(P z + q)_{x_T}``,
``y_{k-1} = -(P z + q)_{x_k} + A^T y_k + E^T y_eta_k``,
``y_x0 = -(P z + q)_{x_0} + A^T y_0 + E^T y_eta_0``), so the dual residual measures the
``lam``, ``u`` rows, where the solve's own error shows.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from c3bench.problems.families import dynamics_rows
from c3bench.problems.instance import Problem
from c3bench.problems.mpc import HorizonLayout
from c3bench.solvers.riccati import RiccatiOptions, factorize, solve_lq, swap_last

__all__ = [
    "StructuredQP",
    "equality_duals",
    "reduce_stage",
    "solve_c3plus_qp",
    "solve_structured",
    "structure_of",
]


# --- problem-level helpers --------------------------------------------------------------------
def reduce_stage(P_stage: np.ndarray, q_stage: np.ndarray, M: np.ndarray, c: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Eliminate ``eta = M y + c`` from stage costs ``1/2 z^T P z + q^T z`` (module step 1).

    ``P_stage`` (..., T, ns, ns), ``q_stage`` (..., T, ns), ``M`` (..., nlam, ny) and ``c``
    (..., nlam) with ``ns = ny + nlam``; returns ``H_y = T_M^T P T_M`` (..., T, ny, ny) and
    ``g_y = T_M^T (q + P t)`` (..., T, ny) with ``T_M = [I; M]``, ``t = (0, c)``.
    """
    ny = M.shape[-1]
    eye = np.broadcast_to(np.eye(ny, dtype=M.dtype), (*M.shape[:-2], ny, ny))
    TM = np.concatenate([eye, M], axis=-2)[..., None, :, :]  # (..., 1, ns, ny)
    Hy = swap_last(TM) @ P_stage @ TM
    Hy = 0.5 * (Hy + swap_last(Hy))
    t = np.concatenate([np.zeros((*c.shape[:-1], ny), dtype=c.dtype), c], axis=-1)
    shifted = q_stage + (P_stage @ t[..., None, :, None])[..., 0]
    gy = (swap_last(TM) @ shifted[..., None])[..., 0]
    return Hy, gy


def equality_duals(problem: Problem, z: np.ndarray) -> np.ndarray:
    """Equality duals of a ``c3plus_qp`` instance from stationarity (module docstring).

    Rows in :func:`problems.families.consensus_qp`'s order: ``x_0 = x0`` (nx), dynamics
    (T x nx), then ``eta`` rows (T x nlam); sign convention ``P z + q + A^T y = 0``.
    """
    layout = HorizonLayout.from_json(problem.meta["layout"])
    lcs = problem.lcs
    assert lcs is not None
    T, nx, nlam = layout.horizon, layout.nx, layout.nlam
    gradient = problem.P @ z + problem.q
    y0 = np.zeros(nx)
    y_dyn = np.zeros((T, nx))
    y_eta = np.zeros((T, nlam))
    for k in range(T):
        y_eta[k] = -gradient[layout.index(k, "eta")]
    y_dyn[T - 1] = -gradient[layout.index(T, "x")]
    for k in range(T - 1, 0, -1):
        y_dyn[k - 1] = -gradient[layout.index(k, "x")] + lcs.A.T @ y_dyn[k] \
            + lcs.E.T @ y_eta[k]
    y0[:] = -gradient[layout.index(0, "x")] + lcs.A.T @ y_dyn[0] + lcs.E.T @ y_eta[0]
    return np.concatenate([y0, y_dyn.ravel(), y_eta.ravel()])


def _structure_error(problem: Problem, layout: HorizonLayout) -> str:
    """``""`` when ``A``, ``b`` are exactly the C3+ rows of ``problem.lcs``, else why not."""
    lcs = problem.lcs
    if lcs is None:
        return "no LCS attached"
    if problem.A is None or problem.b is None:
        return "no equality rows"
    expected, b = dynamics_rows(layout, lcs, problem.b[: layout.nx])
    if problem.A.shape != expected.shape:
        return f"A has shape {problem.A.shape}, expected {expected.shape}"
    if not np.array_equal(expected, problem.A):
        return "A is not the C3+ structure of the attached LCS"
    if not np.array_equal(b, problem.b):
        return "b is not (x0, d, ..., d, c, ..., c)"
    return ""


def _stage_blocks(problem: Problem, layout: HorizonLayout
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, str]:
    """Per-step ``P_k``, ``q_k``, terminal ``P_T``, ``q_T``; a reason when ``P`` couples steps."""
    T, ns = layout.horizon, layout.step_size
    steps = T * ns
    P, q = problem.P, problem.q
    mask = np.zeros_like(P, dtype=bool)
    for k in range(T):
        mask[k * ns:(k + 1) * ns, k * ns:(k + 1) * ns] = True
    mask[steps:, steps:] = True
    if np.any(P[~mask] != 0):
        return (np.zeros(0), np.zeros(0), np.zeros(0), np.zeros(0),
                "P couples different time steps (not block diagonal in time)")
    P_stage = np.stack([P[k * ns:(k + 1) * ns, k * ns:(k + 1) * ns] for k in range(T)])
    q_stage = q[:steps].reshape(T, ns)
    return P_stage, q_stage, P[steps:, steps:], q[steps:], ""


@dataclass
class StructuredQP:
    """A ``c3plus_qp`` instance split into its structure: per-step Hessian blocks
    ``P_stage`` (T, ns, ns) and gradients ``q_stage`` (T, ns), terminal ``P_T``, ``q_T`` (``PT``,
    ``q_terminal``), the LCS blocks ``M = [E F H]``, ``B_v = [D B]`` and ``x0`` (all float64)."""

    layout: HorizonLayout
    P_stage: np.ndarray
    q_stage: np.ndarray
    PT: np.ndarray
    q_terminal: np.ndarray
    A: np.ndarray
    Bv: np.ndarray
    d: np.ndarray
    M: np.ndarray
    c: np.ndarray
    x0: np.ndarray


def structure_of(problem: Problem) -> StructuredQP:
    """Read the C3+ structure of a ``c3plus_qp`` instance; ``ValueError`` when it has none
    (``P`` not block diagonal in time, or ``A z = b`` not the attached LCS's rows)."""
    layout = HorizonLayout.from_json(problem.meta["layout"])
    reason = _structure_error(problem, layout)
    P_stage, q_stage, PT, qT, why = _stage_blocks(problem, layout)
    reason = reason or why
    if reason:
        raise ValueError(reason)
    lcs = problem.lcs
    assert lcs is not None and problem.b is not None
    return StructuredQP(layout=layout, P_stage=P_stage, q_stage=q_stage, PT=PT, q_terminal=qT,
                        A=lcs.A, Bv=np.hstack([lcs.D, lcs.B]), d=lcs.d,
                        M=np.hstack([lcs.E, lcs.F, lcs.H]), c=lcs.c,
                        x0=problem.b[:layout.nx].copy())


def solve_structured(qp: StructuredQP, options: RiccatiOptions | None = None) -> np.ndarray:
    """The primal ``z`` (float64 copy of the working precision's answer) of a
    :class:`StructuredQP`: eliminate ``eta``, factorise, solve, recover ``eta``."""
    options = options or RiccatiOptions()
    dtype = options.dtype
    Hy, gy = reduce_stage(qp.P_stage, qp.q_stage, qp.M, qp.c)
    factor = factorize(qp.A[None], qp.Bv[None], qp.d[None], Hy[None].astype(dtype),
                       qp.PT[None], qp.layout.horizon, options, per_step=True)
    xs, vs = solve_lq(factor, qp.x0[None], gy[None], qp.q_terminal[None])
    ys = np.concatenate([xs[0, :-1], vs[0]], axis=1)  # (T, ny)
    eta = ys @ qp.M.astype(dtype).T + qp.c.astype(dtype)
    steps = np.concatenate([ys, eta], axis=1)
    return np.concatenate([steps.ravel(), xs[0, -1]]).astype(np.float64)


def solve_c3plus_qp(problem: Problem, options: RiccatiOptions | None = None
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Solve a ``c3plus_qp`` :class:`problems.instance.Problem` by the Riccati recursion.

    Returns ``(z, y)``: the primal vector (float64 copy of the working precision's answer)
    and the equality duals (:func:`equality_duals`). Raises ``ValueError`` when the instance
    does not have the C3+ structure.
    """
    z = solve_structured(structure_of(problem), options)
    return z, equality_duals(problem, z)
