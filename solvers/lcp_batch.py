"""Lemke's method compiled and batched, and the robust controller's LCP sample weighting on it.

:func:`lemke_batch` solves ``k`` problems ``LCP(M_i, q_i)`` (find ``z >= 0`` with
``w = M z + q >= 0``, ``z^T w = 0``) in one compiled call. It is the scalar
:func:`c3bench.solvers.lcp.lemke`, operation for operation: the tableau ``w - M z - e z0 = q``
with covering vector ``e = 1``, the same pivots, the same lexicographic ratio test (ties of
the minimum ratio within Harris's tolerance; the artificial variable ``z0`` if it ties, else
the lexicographic minimum of the tied rows of the basis inverse over the entering column;
Cottle, Pang and Stone 1992, sections 4.4 and 4.9) and the same acceptance check of a terminal basis
(relative natural residual ``||min(z, M z + q)||_inf / max(1, ||M z||_inf, ||q||_inf) <=
check_tol``, which bounds ``[-z]_+`` and ``[-w]_+``; issue 9: a terminal basis that fails it
is reported as not a solution, never as solved). On the same data it returns the same ``z``.

:func:`lcp_prediction_errors_batch` is :func:`c3bench.solvers.c3.lcp_prediction_errors` for
every sample ``j`` and observed transition ``(x_t, u_t, x_{t+1})`` in one compiled call:
``lam`` from ``LCP(F_j, E_j x_t + H_j u_t + c_j)``, ``x_hat = A_j x_t + B_j u_t + D_j lam + d_j``
and ``e_j = sum_t ||x_{t+1} - x_hat||_2^2``, with ``e_j = inf`` when Lemke finds no solution
for one of sample ``j``'s LCPs. :func:`prediction_weights` turns errors into the weights
``p_j ~ exp(-(e_j - min_i e_i) / temperature)``.

Compiled with numba (``@njit(cache=True)``, float64): the first call in a process loads the
machine code from numba's cache (or compiles it, about a second, once per installation).

References
----------
C. E. Lemke, "Bimatrix equilibrium points and mathematical programming", Management Science
11(7), 681-689, 1965.

R. W. Cottle, J.-S. Pang and R. E. Stone, *The Linear Complementarity Problem*, Academic
Press, 1992 (sections 4.4 and 4.9, Lemke's method and the lexicographic ratio test).

K. G. Murty, *Linear Complementarity, Linear and Nonlinear Programming*, Heldermann, 1988
(chapter 2).

P. M. J. Harris, "Pivot selection methods of the Devex LP code", Mathematical Programming
5, 1-28, 1973 (the tolerance of the ratio-test ties).
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass
from enum import IntEnum

import numpy as np
from numba import njit

from c3bench.problems.errors import InputError
from c3bench.problems.lcs import LCS, LCSBatch

__all__ = [
    "LemkeBatchResult",
    "LemkeStatus",
    "lcp_prediction_errors_batch",
    "lcp_prediction_weights_batch",
    "lemke_batch",
    "observation_arrays",
    "prediction_weights",
    "warm_up",
]

Observation = tuple[np.ndarray, np.ndarray, np.ndarray]


class LemkeStatus(IntEnum):
    """Why Lemke stopped on one problem (the scalar :func:`~c3bench.solvers.lcp.lemke`'s
    status strings, as integer codes a compiled loop can return)."""

    SOLVED = 0
    """A terminal basis that passed the check (``"solved"``)."""
    TRIVIAL = 1
    """``q >= 0`` (or ``m = 0``): ``z = 0`` without a pivot (``"trivial: q >= 0"``)."""
    SECONDARY_RAY = 2
    """No positive entry in the entering column (``"secondary ray: no solution found"``)."""
    PIVOT_LIMIT = 3
    """``max_pivots`` pivots without termination (``"pivot limit ... reached"``)."""
    NOT_A_SOLUTION = 4
    """A terminal basis that fails the check, a non-finite ``z``, or a ratio test left
    without a candidate by non-finite tableau entries (``"check failed: ..."``)."""


FOUND = (LemkeStatus.SOLVED, LemkeStatus.TRIVIAL)


@dataclass
class LemkeBatchResult:
    """Outcome of :func:`lemke_batch` on ``k`` problems of size ``m``.

    Attributes
    ----------
    z
        (k, m) solutions, ``max(z, 0)`` where found; the unchecked terminal point where the
        check failed; ``nan`` on a secondary ray or the pivot limit (as the scalar's ``None``).
    w
        (k, m) ``M z + q`` of those ``z``.
    status
        (k,) :class:`LemkeStatus` codes (int64).
    pivots
        (k,) the scalar's ``iterations``: pivots after the first (artificial) one.
    """

    z: np.ndarray
    w: np.ndarray
    status: np.ndarray
    pivots: np.ndarray

    @property
    def found(self) -> np.ndarray:
        """(k,) bool: whether each problem was solved (``SOLVED`` or ``TRIVIAL``)."""
        found: np.ndarray = np.isin(self.status, [int(code) for code in FOUND])
        return found


# --- compiled kernels ---------------------------------------------------------------------------
@njit(cache=True)
def _pivot(tableau: np.ndarray, row: int, column: int) -> None:  # pragma: no cover - compiled
    """Gauss-Jordan pivot on ``tableau[row, column]`` (the scalar's ``pivot``, in its order)."""
    rows, width = tableau.shape
    value = tableau[row, column]
    for k in range(width):
        tableau[row, k] = tableau[row, k] / value
    for i in range(rows):
        if i == row:
            continue
        factor = tableau[i, column]
        for k in range(width):
            tableau[i, k] = tableau[i, k] - factor * tableau[row, k]


@njit(cache=True)
def _ties(tableau: np.ndarray, source: int, entering: int, tied: np.ndarray,
          tol: float) -> int:  # pragma: no cover - compiled
    """Narrow ``tied`` (a row mask) to the rows that tie for the minimum of ``b_i / d_i``
    (``b`` column ``source``, ``d`` column ``entering``): ``b_i / d_i <= min_k (b_k + tol
    max(1, |b_k|)) / d_k`` over the tied rows (the scalar's ``_ties``); returns how many
    remain, -1 on a NaN."""
    m = tableau.shape[0]
    threshold = math.inf
    for i in range(m):
        if tied[i]:
            b = tableau[i, source]
            d = tableau[i, entering]
            bound = (b + tol * max(1.0, abs(b))) / d
            if math.isnan(bound):
                return -1
            threshold = min(threshold, bound)
    count = 0
    for i in range(m):
        if tied[i]:
            if tableau[i, source] / tableau[i, entering] <= threshold:
                count += 1
            else:
                tied[i] = False
    return count


@njit(cache=True)
def _ratio_row(tableau: np.ndarray, entering: int, basis: np.ndarray, artificial: int,
               tol: float, tied: np.ndarray) -> int:  # pragma: no cover - compiled
    """Leaving row of the lexicographic minimum ratio test (the scalar's ``_leaving_row``):
    -1 on a secondary ray, -2 on NaN entries; the ties of the minimum ratio, the artificial
    variable's row if among them, else the ties narrowed by the columns ``m - 1, ..., 0`` of
    the basis inverse, the lowest row left."""
    m = tableau.shape[0]
    last = tableau.shape[1] - 1
    positive = False
    for i in range(m):
        tied[i] = tableau[i, entering] > tol
        if tied[i]:
            positive = True
    if not positive:
        return -1
    count = _ties(tableau, last, entering, tied, tol)
    if count < 0:
        return -2
    for i in range(m):
        if tied[i] and basis[i] == artificial:
            return i
    for source in range(m - 1, -1, -1):
        if count == 1:
            break
        count = _ties(tableau, source, entering, tied, tol)
        if count < 0:
            return -2
    for i in range(m):
        if tied[i]:
            return i
    return -2


@njit(cache=True)
def _check(M: np.ndarray, q: np.ndarray, z: np.ndarray, w: np.ndarray,
           check_tol: float) -> bool:  # pragma: no cover - compiled
    """``w = M z + q``; whether ``||min(z, w)||_inf / max(1, ||M z||_inf, ||q||_inf) <=
    check_tol`` with a finite ``z`` (the scalar's ``_checked``)."""
    m = q.shape[0]
    for i in range(m):
        if not math.isfinite(z[i]):
            return False
    residual = 0.0
    scale = 1.0
    for i in range(m):
        product = 0.0
        for k in range(m):
            product += M[i, k] * z[k]
        w[i] = product + q[i]
        scale = max(scale, abs(product), abs(q[i]))
        residual = max(residual, abs(min(z[i], w[i])))
    return residual / scale <= check_tol


@njit(cache=True)
def _lemke_one(M: np.ndarray, q: np.ndarray, limit: int, tol: float, check_tol: float,
               z: np.ndarray, w: np.ndarray) -> tuple[int, int]:  # pragma: no cover - compiled
    """One ``LCP(M, q)`` into ``z`` and ``w``; returns ``(status code, pivots)``."""
    m = q.shape[0]
    trivial = True
    for i in range(m):
        if not q[i] >= 0.0:
            trivial = False
    if trivial:
        for i in range(m):
            z[i] = 0.0
            w[i] = q[i]
        return 1, 0
    artificial = 2 * m
    tableau = np.zeros((m, 2 * m + 2))
    basis = np.empty(m, dtype=np.int64)
    tied = np.empty(m, dtype=np.bool_)
    for i in range(m):
        tableau[i, i] = 1.0
        for k in range(m):
            tableau[i, m + k] = -M[i, k]
        tableau[i, artificial] = -1.0
        tableau[i, artificial + 1] = q[i]
        basis[i] = i
    row = int(np.argmin(q))
    _pivot(tableau, row, artificial)
    leaving = basis[row]
    basis[row] = artificial
    for count in range(1, limit + 1):
        entering = leaving + m if leaving < m else leaving - m
        row = _ratio_row(tableau, entering, basis, artificial, tol, tied)
        if row == -1:
            z[:] = np.nan
            w[:] = np.nan
            return 2, count
        if row == -2:
            z[:] = np.nan
            w[:] = np.nan
            return 4, count
        _pivot(tableau, row, entering)
        leaving = basis[row]
        basis[row] = entering
        if leaving == artificial:
            z[:] = 0.0
            for i in range(m):
                if m <= basis[i] < 2 * m:
                    z[basis[i] - m] = tableau[i, artificial + 1]
            if not _check(M, q, z, w, check_tol):
                return 4, count
            for i in range(m):
                z[i] = max(z[i], 0.0)
            _check(M, q, z, w, check_tol)
            return 0, count
    z[:] = np.nan
    w[:] = np.nan
    return 3, limit


@njit(cache=True)
def _lemke_many(M: np.ndarray, q: np.ndarray, limit: int, tol: float, check_tol: float,
                z: np.ndarray, w: np.ndarray, status: np.ndarray,
                pivots: np.ndarray) -> None:  # pragma: no cover - compiled
    for i in range(q.shape[0]):
        status[i], pivots[i] = _lemke_one(M[i], q[i], limit, tol, check_tol, z[i], w[i])


@njit(cache=True)
def _prediction_errors(A: np.ndarray, B: np.ndarray, D: np.ndarray, d: np.ndarray,
                       E: np.ndarray, F: np.ndarray, H: np.ndarray, c: np.ndarray,
                       xs: np.ndarray, us: np.ndarray, x_next: np.ndarray, limit: int,
                       tol: float, check_tol: float,
                       errors: np.ndarray) -> None:  # pragma: no cover - compiled
    n, nx, nu = B.shape
    m = F.shape[1]
    q = np.empty(m)
    lam = np.empty(m)
    w = np.empty(m)
    for j in range(n):
        error = 0.0
        for t in range(xs.shape[0]):
            for i in range(m):
                offset = 0.0
                for k in range(nx):
                    offset += E[j, i, k] * xs[t, k]
                for k in range(nu):
                    offset += H[j, i, k] * us[t, k]
                q[i] = offset + c[j, i]
            code, _ = _lemke_one(F[j], q, limit, tol, check_tol, lam, w)
            if code > 1:
                error = math.inf
                break
            for i in range(nx):
                predicted = d[j, i]
                for k in range(nx):
                    predicted += A[j, i, k] * xs[t, k]
                for k in range(nu):
                    predicted += B[j, i, k] * us[t, k]
                for k in range(m):
                    predicted += D[j, i, k] * lam[k]
                error += (x_next[t, i] - predicted) ** 2
        errors[j] = error


# --- public functions ---------------------------------------------------------------------------
def _pivot_limit(m: int, max_pivots: int | None) -> int:
    return max_pivots if max_pivots is not None else 50 * (m + 1)


def lemke_batch(M: np.ndarray, q: np.ndarray, max_pivots: int | None = None,
                tol: float = 1e-12, check_tol: float = 1e-9) -> LemkeBatchResult:
    """Lemke's method on ``k`` problems ``LCP(M_i, q_i)`` in one compiled call.

    Parameters
    ----------
    M
        (k, m, m) matrices.
    q
        (k, m) vectors.
    max_pivots
        Pivot limit per problem (default ``50 (m + 1)``, as the scalar).
    tol, check_tol
        Ratio-test tolerance and acceptance tolerance, as :func:`c3bench.solvers.lcp.lemke`.

    Returns
    -------
    LemkeBatchResult
        Per problem the scalar's ``z`` (``nan`` where it returns ``None``), ``M z + q``, the
        status code and its ``iterations``.

    Raises
    ------
    InputError
        When the shapes disagree.
    """
    M = np.ascontiguousarray(M, dtype=np.float64)
    q = np.ascontiguousarray(q, dtype=np.float64)
    if q.ndim != 2 or M.shape != (q.shape[0], q.shape[1], q.shape[1]):
        raise InputError(f"lemke_batch needs M (k, m, m) and q (k, m), got {M.shape} and "
                         f"{q.shape}")
    k, m = q.shape
    z = np.zeros((k, m))
    w = np.zeros((k, m))
    status = np.zeros(k, dtype=np.int64)
    pivots = np.zeros(k, dtype=np.int64)
    if k:
        _lemke_many(M, q, _pivot_limit(m, max_pivots), float(tol), float(check_tol), z, w,
                    status, pivots)
    return LemkeBatchResult(z=z, w=w, status=status, pivots=pivots)


def observation_arrays(observations: Sequence[Observation], nx: int, nu: int
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Observed transitions ``(x_t, u_t, x_{t+1})`` as float64 arrays (t, nx), (t, nu), (t, nx)."""
    t = len(observations)
    xs = np.empty((t, nx))
    us = np.empty((t, nu))
    x_next = np.empty((t, nx))
    for i, (x, u, after) in enumerate(observations):
        xs[i], us[i], x_next[i] = x, u, after
    return xs, us, x_next


def _stacked(lcs: LCSBatch | Sequence[LCS]) -> list[np.ndarray]:
    """``A, B, D, d, E, F, H, c`` stacked along the sample axis, float64 and contiguous."""
    names = ("A", "B", "D", "d", "E", "F", "H", "c")
    if isinstance(lcs, LCSBatch):
        return [np.ascontiguousarray(getattr(lcs, name), dtype=np.float64) for name in names]
    if len(lcs) == 0:
        raise InputError("need at least one LCS sample")
    return [np.ascontiguousarray(np.stack([getattr(s, name) for s in lcs]), dtype=np.float64)
            for name in names]


def lcp_prediction_errors_batch(lcs: LCSBatch | Sequence[LCS], xs: np.ndarray,
                                us: np.ndarray, x_next: np.ndarray,
                                max_pivots: int | None = None) -> np.ndarray:
    """One-step LCP prediction errors of every sample on every observed transition.

    ``e_j = sum_t ||x_{t+1} - (A_j x_t + B_j u_t + D_j lam_jt + d_j)||_2^2`` with ``lam_jt``
    from Lemke on ``LCP(F_j, E_j x_t + H_j u_t + c_j)``; ``e_j = inf`` when Lemke finds no
    solution of one of them (as :func:`c3bench.solvers.c3.lcp_prediction_errors`).

    Parameters
    ----------
    lcs
        The ``n`` samples, an :class:`LCSBatch` or a sequence of :class:`LCS`.
    xs, us, x_next
        (t, nx), (t, nu), (t, nx) observed transitions.
    max_pivots
        Lemke's pivot limit per LCP (default ``50 (nlam + 1)``).

    Returns
    -------
    numpy.ndarray
        (n,) errors.
    """
    A, B, D, d, E, F, H, c = _stacked(lcs)
    n, nx, nu = B.shape
    xs = np.ascontiguousarray(xs, dtype=np.float64).reshape(-1, nx)
    t = xs.shape[0]
    us = np.ascontiguousarray(us, dtype=np.float64).reshape(t, nu)
    x_next = np.ascontiguousarray(x_next, dtype=np.float64).reshape(t, nx)
    errors = np.zeros(n)
    _prediction_errors(A, B, D, d, E, F, H, c, xs, us, x_next,
                       _pivot_limit(F.shape[1], max_pivots), 1e-12, 1e-9, errors)
    return errors


def prediction_weights(errors: np.ndarray, temperature: float | None = None) -> np.ndarray:
    """Normalised weights ``p_j = exp(-(e_j - min_i e_i) / temperature) / sum`` of errors.

    ``temperature=None`` takes the median finite error (floored at 1e-12); an infinite error
    gets weight 0; when no error is finite the weights are uniform (seed 000, section 3.3; the
    rule of :func:`c3bench.solvers.c3.lcp_prediction_weights`).
    """
    errors = np.asarray(errors, dtype=float)
    S = errors.size
    finite = np.isfinite(errors)
    if not np.any(finite):
        return np.full(S, 1.0 / S)
    if temperature is None:
        temperature = max(float(np.median(errors[finite])), 1e-12)
    if not (math.isfinite(temperature) and temperature > 0):
        raise InputError(f"temperature must be a finite number > 0, got {temperature!r}")
    logits = np.where(finite, -(errors - errors[finite].min()) / temperature, -np.inf)
    weights = np.exp(logits)
    normalised: np.ndarray = weights / weights.sum()
    return normalised


def lcp_prediction_weights_batch(lcs: LCSBatch | Sequence[LCS],
                                 observations: Sequence[Observation],
                                 temperature: float | None = None) -> np.ndarray:
    """:func:`c3bench.solvers.c3.lcp_prediction_weights` on the compiled errors.

    Uniform weights without observations; otherwise :func:`prediction_weights` of
    :func:`lcp_prediction_errors_batch`.
    """
    S = lcs.n_samples if isinstance(lcs, LCSBatch) else len(lcs)
    if S == 0:
        raise InputError("need at least one sample")
    if len(observations) == 0:
        return np.full(S, 1.0 / S)
    A, B = (lcs.A, lcs.B) if isinstance(lcs, LCSBatch) else (lcs[0].A, lcs[0].B)
    nx, nu = int(A.shape[-1]), int(B.shape[-1])
    xs, us, x_next = observation_arrays(observations, nx, nu)
    return prediction_weights(lcp_prediction_errors_batch(lcs, xs, us, x_next), temperature)


def warm_up() -> float:
    """Load (or compile) the kernels on tiny problems; returns the seconds it took.

    Call once per process before timing a control step: the first call of each kernel loads
    its machine code from numba's cache (about 0.3 s) or compiles it (seconds).
    """
    start = time.perf_counter()
    lemke_batch(np.eye(1)[None], -np.ones((1, 1)))
    one = LCSBatch(A=np.eye(1)[None], B=np.zeros((1, 1, 1)), D=np.ones((1, 1, 1)),
                   d=np.zeros((1, 1)), E=np.zeros((1, 1, 1)), F=np.eye(1)[None],
                   H=np.zeros((1, 1, 1)), c=-np.ones((1, 1)), dt=1.0)
    lcp_prediction_errors_batch(one, np.zeros((1, 1)), np.zeros((1, 1)), np.zeros((1, 1)))
    return time.perf_counter() - start
