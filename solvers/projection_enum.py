"""C3's per-step projection solved exactly by enumerating the contact modes.

For one step row ``v = (v_x, v_lam, v_u)`` of the ADMM (Aydinoglu and Posa 2022, the
projection step of C3) and a diagonal weight ``U >= 0`` the projection is

    minimise    (d - v)^T diag(U) (d - v)              over d = (x, lam, u)
    subject to  0 <= lam  perp  eta = E x + F lam + H u + c >= 0.

Write the ``2m`` candidate equality rows as ``R d = r`` with ``R = [[0, I, 0], [E, F, H]]``
and ``r = (0, -c)`` (row ``i``: ``lam_i = 0``; row ``m + i``: ``eta_i = 0``). A *system*
chooses, for every pair ``i``, one of three equality sets: ``{lam_i = 0}``, ``{eta_i = 0}``
or ``{lam_i = 0, eta_i = 0}``; there are ``3^m`` systems ``S``. For each, the equality QP
``min (d - v)^T U (d - v) s.t. R_S d = r_S`` is solved (any minimiser), and the minimiser
is kept when it also satisfies ``lam >= 0`` and ``eta >= 0``. The answer is the cheapest
kept candidate.

**Why this is exact.** Every kept candidate is feasible (each pair has a zero member and
both members are non-negative), so its cost is at least the optimum ``f*``. Conversely,
the feasible set is a finite union of polyhedra (the ``2^m`` modes ``lam_Z = 0, eta_Z >= 0,
eta_{not Z} = 0, lam_{not Z} >= 0``) and the cost is a convex quadratic bounded below by 0,
so the minimum is attained (Frank and Wolfe 1956) at a point ``d*`` of some mode polyhedron
``P``. ``d*`` minimises the convex cost over ``P``, so by the KKT conditions it also
minimises it over the affine hull of the constraints active at ``d*``; let ``M`` be the set
of minimisers over that affine set ``S_0`` (an affine set: ``d* + (ker R_S0 cap ker U)``).
``M cap P`` is a polyhedron; take a minimal face ``F`` of it. A minimal face is an affine
set lying entirely in ``P``, cut out of ``M`` by making some of ``P``'s inequalities
(``lam_i >= 0`` or ``eta_i >= 0``) equalities. Adding those equalities to ``S_0`` gives a
system ``S`` of the three-way form above (a pair whose other member becomes tight turns into
"both"), whose minimisers are exactly ``S cap M = F`` (the optimum over ``S`` is still
``f*``, attained on ``F``). Hence **every** minimiser of that system is feasible and costs
``f*``: whichever minimiser the linear algebra returns (a pseudo-inverse one where ``U`` has
zeros or rows are dependent), it is kept. Dropping the sign constraints and enumerating only
``2^m`` equality systems would not be exact (a pair may need both members at zero, and a
minimiser of a two-way system may have the wrong sign), nor would choosing a minimiser
without the feasibility check.

**The equality QP of one system.** With ``p = d - v``, ``h = R v - r`` (the values of
``(lam, eta)`` at ``v``), the weighted variables ``w`` (``U > 0``) and the free ones ``f``
(``U = 0``), ``K = R_w U_w^-1 R_w^T`` (``2m x 2m``, one per call) and the scaled multiplier
``mu``, the KKT conditions are

    [[K_SS,      R_f,S], [R_f,S^T, 0]] [mu; p_f] = [-h_S; 0],    p_w = U_w^-1 R_w,S^T mu,

of size ``|S| + n_f`` (``m <= |S| <= 2m``). The matrices do not depend on ``v``: each
system is factorised once for all rows (batched ``numpy.linalg.solve``; systems whose
answer does not satisfy their own equalities, singular or inconsistent ones, are re-solved
with an eigenvalue pseudo-inverse, and kept only if then consistent). The candidate's
``(lam, eta) = h + R p`` and cost ``p^T U p`` follow for every row at once.

Cost: ``3^m`` systems of size at most ``2m + n_f``; :data:`MAX_PAIRS` pairs at most (the
MIQP backends remain for larger ``m``). Zero weights never make the problem unbounded (the
cost is non-negative and the minimum is attained, see above); they only make the minimiser
non-unique, and one minimiser is returned. A step whose LCS admits no complementary point
at all raises :class:`~c3bench.problems.errors.InputError`.

References
----------
A. Aydinoglu and M. Posa, "Real-time multi-contact model predictive control via ADMM", IEEE
ICRA 2022 (the projection step of C3).

M. Frank and P. Wolfe, "An algorithm for quadratic programming", Naval Research Logistics
Quarterly 3, 95-110, 1956 (a convex quadratic bounded below on a polyhedron attains its
minimum).

J. Nocedal and S. J. Wright, *Numerical Optimization*, 2nd ed., Springer, 2006, section 16.1
(the KKT system of an equality-constrained QP).
"""

from __future__ import annotations

import functools
import itertools
from dataclasses import dataclass

import numpy as np

from c3bench.problems.errors import InputError
from c3bench.problems.lcs import LCS

MAX_PAIRS = 10
"""Most complementarity pairs per step: ``3^10 = 59049`` equality systems."""

FEASIBILITY_TOLERANCE = 1e-9
"""A candidate is kept when ``lam, eta >= -tol`` and its equalities hold to ``tol``, with
``tol = FEASIBILITY_TOLERANCE (1 + ||h||_inf)`` per row (``h``: ``(lam, eta)`` at ``v``)."""

PSEUDO_INVERSE_CUTOFF = 1e-12
"""Eigenvalues below this fraction of the largest are treated as zero by the fallback."""

CHUNK_ENTRIES = 400_000
"""Systems x rows x variables per batch (bounds the memory of one batch to a few MB)."""


@dataclass(frozen=True)
class SystemGroup:
    """The three-way systems with the same number ``k`` of equality rows.

    Attributes
    ----------
    rows
        (systems, k) indices into the ``2m`` candidate rows (``i``: ``lam_i = 0``,
        ``m + i``: ``eta_i = 0``), sorted.
    """

    rows: np.ndarray


@dataclass
class EnumeratedProjection:
    """Outcome of :func:`enumerated_projection`.

    Attributes
    ----------
    point
        The projections, shaped like ``v``.
    cost
        ``(d - v)^T U (d - v)`` per row (shape ``v.shape[:-1]``).
    lam_zero, eta_zero
        Per row, the pairs whose ``lam`` / ``eta`` the winning system set to zero (boolean,
        shape ``v.shape[:-1] + (m,)``).
    systems
        Number of equality systems enumerated per row (``3^m``).
    """

    point: np.ndarray
    cost: np.ndarray
    lam_zero: np.ndarray
    eta_zero: np.ndarray
    systems: int


@functools.lru_cache(maxsize=MAX_PAIRS + 1)
def system_groups(m: int) -> tuple[SystemGroup, ...]:
    """All ``3^m`` systems for ``m`` pairs, grouped by their number of rows ``k``."""
    by_size: dict[int, list[list[int]]] = {}
    for choice in itertools.product((0, 1, 2), repeat=m):
        rows = [i for i, c in enumerate(choice) if c in (0, 2)]
        rows += [m + i for i, c in enumerate(choice) if c in (1, 2)]
        by_size.setdefault(len(rows), []).append(sorted(rows))
    return tuple(SystemGroup(np.array(by_size[k], dtype=np.int64).reshape(-1, k))
                 for k in sorted(by_size))


def _check(v: np.ndarray, lcs: LCS, U: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    n = lcs.nx + lcs.nlam + lcs.nu
    v = np.asarray(v, dtype=float)
    U = np.asarray(U, dtype=float)
    if v.ndim < 1 or v.shape[-1] != n:
        raise InputError(f"v must have shape (..., {n}) (x, lam, u), got {v.shape}")
    if U.shape != (n,):
        raise InputError(f"U must have shape ({n},), got {U.shape}")
    if not np.all(np.isfinite(v)):
        raise InputError("v has non-finite entries")
    if not np.all(np.isfinite(U)) or np.any(U < 0):
        raise InputError("U must be finite and >= 0")
    if lcs.nlam > MAX_PAIRS:
        raise InputError(f"{lcs.nlam} complementarity pairs per step exceed the enumeration "
                         f"limit MAX_PAIRS={MAX_PAIRS} (3^{lcs.nlam} systems); use an MIQP "
                         "backend")
    return v, U


def _candidate_rows(lcs: LCS) -> tuple[np.ndarray, np.ndarray]:
    """``R = [[0, I, 0], [E, F, H]]`` and ``r = (0, -c)``."""
    m = lcs.nlam
    lam_rows = np.zeros((m, lcs.nx + m + lcs.nu))
    lam_rows[:, lcs.nx:lcs.nx + m] = np.eye(m)
    R = np.vstack([lam_rows, np.hstack([lcs.E, lcs.F, lcs.H])])
    r = np.concatenate([np.zeros(m), -lcs.c])
    return R, r


def _pinv_solve(M: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """``M^+ rhs`` for stacked symmetric ``M`` (eigenvalues below the cutoff dropped)."""
    eigenvalues, vectors = np.linalg.eigh(M)
    largest = np.max(np.abs(eigenvalues), axis=-1, keepdims=True)
    keep = np.abs(eigenvalues) > PSEUDO_INVERSE_CUTOFF * np.maximum(largest, 1e-300)
    inverse = np.where(keep, 1.0 / np.where(keep, eigenvalues, 1.0), 0.0)
    solution: np.ndarray = vectors @ (inverse[..., :, None]
                                      * (np.swapaxes(vectors, -1, -2) @ rhs))
    return solution


class _Projector:
    """The per-call data (``R``, ``K``, the weighted / free split) and the batched solves."""

    def __init__(self, lcs: LCS, U: np.ndarray) -> None:
        self.R, self.r = _candidate_rows(lcs)
        self.U = U
        self.weighted = np.flatnonzero(U > 0)
        self.free = np.flatnonzero(U == 0)
        R_w = self.R[:, self.weighted]
        self.R_w_scaled = R_w / U[self.weighted]
        self.K = R_w @ self.R_w_scaled.T
        self.R_f = self.R[:, self.free]

    def solve_group(self, rows: np.ndarray, h: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Steps ``p`` (systems, N, n) and their ``(lam, eta)`` (systems, N, 2m) for systems
        ``rows`` (systems, k) and rows' ``h`` (N, 2m)."""
        k, nf = rows.shape[1], self.free.size
        M = np.zeros((rows.shape[0], k + nf, k + nf))
        M[:, :k, :k] = self.K[rows[:, :, None], rows[:, None, :]]
        R_f = self.R_f[rows]
        M[:, :k, k:] = R_f
        M[:, k:, :k] = np.swapaxes(R_f, 1, 2)
        rhs = np.zeros((rows.shape[0], k + nf, h.shape[0]))
        rhs[:, :k, :] = -h.T[rows]
        try:
            solution = np.linalg.solve(M, rhs)
        except np.linalg.LinAlgError:
            solution = _pinv_solve(M, rhs)
        p, values = self._steps(rows, solution, h)
        bad = ~self._consistent(rows, values, h)
        if np.any(bad):
            fixed = _pinv_solve(M[bad], rhs[bad])
            p[bad], values[bad] = self._steps(rows[bad], fixed, h)
        return p, values

    def _steps(self, rows: np.ndarray, solution: np.ndarray, h: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray]:
        k = rows.shape[1]
        mu = solution[:, :k, :]  # (systems, k, N)
        p = np.zeros((rows.shape[0], h.shape[0], self.U.size))
        p[:, :, self.weighted] = np.einsum("skn,skw->snw", mu, self.R_w_scaled[rows])
        p[:, :, self.free] = np.swapaxes(solution[:, k:, :], 1, 2)
        values = h[None] + p @ self.R.T
        return p, values

    @staticmethod
    def _consistent(rows: np.ndarray, values: np.ndarray, h: np.ndarray) -> np.ndarray:
        """Per system: finite and its equalities hold (to the tolerance) on every row."""
        tolerance = FEASIBILITY_TOLERANCE * (1.0 + np.max(np.abs(h), axis=1))
        on_rows = np.take_along_axis(values, rows[:, None, :], axis=2)
        ok = np.all(np.abs(on_rows) <= tolerance[None, :, None], axis=2)
        result: np.ndarray = np.all(ok & np.all(np.isfinite(values), axis=2), axis=1)
        return result


def enumerated_projection(v: np.ndarray, lcs: LCS, U: np.ndarray) -> EnumeratedProjection:
    """C3's projection of every step row of ``v`` by enumeration (module docstring).

    Parameters
    ----------
    v
        (..., nx + nlam + nu) points in the layout ``(x, lam, u)``.
    lcs
        The step's LCS (``E, F, H, c`` are used).
    U
        (nx + nlam + nu,) diagonal weights, ``>= 0``.

    Raises
    ------
    InputError
        Bad shapes, non-finite values, negative weights, ``nlam > MAX_PAIRS``, or a row
        with no complementary point.
    """
    v, U = _check(v, lcs, U)
    m, n = lcs.nlam, v.shape[-1]
    rows_v = v.reshape(-1, n)
    N = rows_v.shape[0]
    if m == 0:
        return EnumeratedProjection(v.copy(), np.zeros(v.shape[:-1]),
                                    np.zeros((*v.shape[:-1], 0), dtype=bool),
                                    np.zeros((*v.shape[:-1], 0), dtype=bool), 1)
    projector = _Projector(lcs, U)
    h = rows_v @ projector.R.T - projector.r
    tolerance = FEASIBILITY_TOLERANCE * (1.0 + np.max(np.abs(h), axis=1))
    best_cost = np.full(N, np.inf)
    best_p = np.zeros((N, n))
    best_zero = np.zeros((N, 2 * m), dtype=bool)
    for group in system_groups(m):
        chunk = max(1, CHUNK_ENTRIES // max(1, N * (n + 2 * m)))
        for start in range(0, group.rows.shape[0], chunk):
            rows = group.rows[start:start + chunk]
            p, values = projector.solve_group(rows, h)
            on_rows = np.take_along_axis(values, rows[:, None, :], axis=2)
            feasible = (np.all(values >= -tolerance[None, :, None], axis=2)
                        & np.all(np.abs(on_rows) <= tolerance[None, :, None], axis=2))
            cost = np.where(feasible, np.einsum("snj,j,snj->sn", p, U, p), np.inf)
            winner = np.argmin(cost, axis=0)
            winner_cost = cost[winner, np.arange(N)]
            better = winner_cost < best_cost
            if np.any(better):
                best_cost[better] = winner_cost[better]
                best_p[better] = p[winner[better], np.flatnonzero(better)]
                zero = np.zeros((int(np.sum(better)), 2 * m), dtype=bool)
                zero[np.arange(zero.shape[0])[:, None], rows[winner[better]]] = True
                best_zero[better] = zero
    if not np.all(np.isfinite(best_cost)):
        raise InputError("the LCS admits no complementary point for "
                         f"{int(np.sum(~np.isfinite(best_cost)))} of {N} rows")
    point = rows_v + best_p
    lam_zero = best_zero[:, :m]
    lam_part = point[:, lcs.nx:lcs.nx + m]
    lam_part[lam_zero] = 0.0  # exact zeros where the system fixed lam_i = 0
    shape = v.shape[:-1]
    return EnumeratedProjection(point.reshape(v.shape), best_cost.reshape(shape),
                                lam_zero.reshape((*shape, m)),
                                best_zero[:, m:].reshape((*shape, m)), 3 ** m)


def project_c3_enumerated(v: np.ndarray, lcs: LCS, U: np.ndarray) -> np.ndarray:
    """The exact minimiser of ``(d - v)^T diag(U) (d - v)`` s.t. ``0 <= lam perp E x + F lam +
    H u + c >= 0`` for every step row of ``v`` (..., nx + nlam + nu), layout ``(x, lam, u)``.

    See :func:`enumerated_projection` (which also returns the costs and modes) and the module
    docstring for the method and the proof that it is exact.
    """
    return enumerated_projection(v, lcs, U).point
