"""Pivoting and iterative solvers of the linear complementarity problem.

``LCP(M, q)``: find ``z >= 0`` with ``w = M z + q >= 0`` and ``z^T w = 0``. The registry
backends ``lemke`` and ``pgs`` are :mod:`c3bench.solvers.backends.lcp`.

References
----------
C. E. Lemke, "Bimatrix equilibrium points and mathematical programming", Management Science
11(7), 681-689, 1965 (:func:`lemke`).

R. W. Cottle, J.-S. Pang and R. E. Stone, *The Linear Complementarity Problem*, Academic
Press, 1992 (:func:`lemke`: sections 4.4 and 4.9, the lexicographic ratio test;
:func:`projected_gauss_seidel`: chapter 5).

K. G. Murty, *Linear Complementarity, Linear and Nonlinear Programming*, Heldermann, 1988
(chapter 2, Lemke's method and its lexicographic degeneracy resolution).

P. M. J. Harris, "Pivot selection methods of the Devex LP code", Mathematical Programming
5, 1-28, 1973 (the tolerance of the ratio-test ties, :func:`_ties`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from c3bench.solvers.residuals import natural_residual, relative_natural_residual

__all__ = ["LCPSolution", "lemke", "natural_residual", "projected_gauss_seidel"]


@dataclass
class LCPSolution:
    """Outcome of an LCP solve.

    Attributes
    ----------
    z
        The solution (``None`` when not found).
    found
        Whether the method terminated at a solution.
    status
        Why it stopped.
    iterations
        Pivots (Lemke) or sweeps (PGS).
    residuals
        Per-iteration natural-map residual ``||min(z, M z + q)||_inf`` (PGS only).
    """

    z: np.ndarray | None
    found: bool
    status: str
    iterations: int
    residuals: list[float]


def lemke(M: np.ndarray, q: np.ndarray, max_pivots: int | None = None,
          tol: float = 1e-12, check_tol: float = 1e-9) -> LCPSolution:
    """Lemke's complementary pivoting method with covering vector ``e = 1`` and the
    lexicographic minimum ratio test.

    Solves the tableau ``w - M z - e z0 = q``: ``z0`` enters at the row of the most negative
    ``q_i`` (the lowest such row), then complementary pivots follow until ``z0`` leaves.
    Degenerate ties in the ratio test are resolved by the lexicographic rule (Cottle, Pang and
    Stone 1992, sections 4.4 and 4.9; Murty 1988, chapter 2), i.e. Lemke's method on the
    perturbed ``q + (eps^m, eps^(m-1), ..., eps)`` for an infinitesimal ``eps > 0``: that
    problem is nondegenerate, and with this rule the method terminates at a solution for
    P-matrices and, for copositive-plus ``M`` (symmetric PSD included), whenever the LCP is
    feasible; a secondary ray means no solution was found (for copositive-plus ``M``, in exact
    arithmetic: the LCP is infeasible). See :func:`_leaving_row` for the ratio test in
    floating point (``tol``).

    A terminal basis is a solution only if it checks: the natural residual
    ``||min(z, M z + q)||_inf`` (which bounds ``[-z]_+`` and ``[-w]_+``) must be at most
    ``check_tol * max(1, ||M z||_inf, ||q||_inf)``; otherwise ``found`` is False and the status
    starts ``"check failed"`` (round-off in the tableau, non-finite entries, or no solution).
    """
    M = np.asarray(M, dtype=float)
    q = np.asarray(q, dtype=float)
    n = q.size
    if M.shape != (n, n):
        raise ValueError(f"M must have shape ({n}, {n}), got {M.shape}")
    if n == 0 or np.all(q >= 0):
        return LCPSolution(np.zeros(n), True, "trivial: q >= 0", 0, [])
    limit = max_pivots if max_pivots is not None else 50 * (n + 1)
    artificial = 2 * n
    tableau = np.hstack([np.eye(n), -M, -np.ones((n, 1)), q[:, None]])
    basis = list(range(n))

    def pivot(row: int, column: int) -> None:
        tableau[row] /= tableau[row, column]
        others = np.arange(n) != row
        tableau[others] -= np.outer(tableau[others, column], tableau[row])

    row = int(np.argmin(q))
    pivot(row, artificial)
    leaving = basis[row]
    basis[row] = artificial
    for count in range(1, limit + 1):
        entering = leaving + n if leaving < n else leaving - n
        row = _leaving_row(tableau, entering, basis, artificial, tol)
        if row == -1:
            return LCPSolution(None, False, "secondary ray: no solution found", count, [])
        if row == -2:
            return LCPSolution(None, False, "check failed: non-finite tableau entries in the "
                               "ratio test", count, [])
        pivot(row, entering)
        leaving = basis[row]
        basis[row] = entering
        if leaving == artificial:
            z = np.zeros(n)
            for i, var in enumerate(basis):
                if n <= var < 2 * n:
                    z[var - n] = tableau[i, -1]
            return _checked(M, q, z, count, check_tol)
    return LCPSolution(None, False, f"pivot limit {limit} reached", limit, [])


def _ties(tableau: np.ndarray, source: int, entering: int, rows: np.ndarray,
          tol: float) -> np.ndarray | None:
    """The rows of ``rows`` that tie for the minimum of ``b_i / d_i`` (``b`` column ``source``,
    ``d`` column ``entering`` of the tableau, ``d_i > tol``), ``None`` on a NaN.

    Row ``i`` ties when ``b_i / d_i <= min_k (b_k + tol max(1, |b_k|)) / d_k`` (Harris's
    tolerance): pivoting on it would take no ``b_k`` below ``-tol max(1, |b_k|)``. A tie
    window in the ratios themselves would miss degenerate ties whose ratios differ by
    round-off amplified by a small ``d_k``.
    """
    b = tableau[rows, source]
    d = tableau[rows, entering]
    threshold = ((b + tol * np.maximum(1.0, np.abs(b))) / d).min()
    if np.isnan(threshold):  # a NaN b_i / d_i (d_i > tol) makes its bound NaN too
        return None
    tied: np.ndarray = rows[b / d <= threshold]
    return tied


def _leaving_row(tableau: np.ndarray, entering: int, basis: list[int], artificial: int,
                 tol: float) -> int:
    """Leaving row of the lexicographic minimum ratio test for the column ``entering``.

    Returns -1 on a secondary ray (no entry of the column above ``tol``) and -2 when NaN
    tableau entries leave no comparison. Otherwise, among the rows with ``d_i > tol``
    (``d`` the entering column): the rows that tie for the minimum ratio ``q_i / d_i`` (``q``
    the current right-hand side, ties as in :func:`_ties`); the artificial variable ``z0``'s
    row if it is among them (it leaves, and the next basis is a solution); otherwise the
    lexicographic minimum of the rows of ``B^-1 / d_i`` (``B^-1`` the basis inverse: the
    tableau's first ``m`` columns, which started as the identity), compared from column
    ``m - 1`` down to column 0, each comparison narrowing the ties as in :func:`_ties`
    (columns in this order: the perturbation ``q + (eps^m, ..., eps)``, under which the
    first pivot's lowest row among equal minima of ``q`` is the lexicographic one). In exact
    arithmetic the rows of ``B^-1`` are independent and a single row remains; if round-off
    leaves several, the lowest.
    """
    m = tableau.shape[0]
    rows = np.flatnonzero(tableau[:, entering] > tol)
    if rows.size == 0:
        return -1
    tied = _ties(tableau, -1, entering, rows, tol)
    if tied is None:
        return -2
    for row in tied:
        if basis[row] == artificial:
            return int(row)
    for source in range(m - 1, -1, -1):
        if tied.size == 1:
            break
        tied = _ties(tableau, source, entering, tied, tol)
        if tied is None:
            return -2
    return int(tied[0])


def _checked(M: np.ndarray, q: np.ndarray, z: np.ndarray, count: int,
             check_tol: float) -> LCPSolution:
    """Lemke's terminal point, ``found`` only when it solves ``LCP(M, q)`` (see :func:`lemke`)."""
    if not np.all(np.isfinite(z)):
        return LCPSolution(z, False, "check failed: non-finite z", count, [])
    residual = relative_natural_residual(M, q, z)
    if not residual <= check_tol:
        w = M @ z + q
        return LCPSolution(z, False, "check failed: ||min(z, Mz + q)||_inf / max(1, ||Mz||, "
                           f"||q||) = {residual:.3g} > {check_tol:g} (min z = "
                           f"{float(np.min(z, initial=0.0)):.3g}, min w = "
                           f"{float(np.min(w, initial=0.0)):.3g})", count, [])
    return LCPSolution(np.maximum(z, 0.0), True, "solved", count, [])


def projected_gauss_seidel(M: np.ndarray, q: np.ndarray, tol: float = 1e-8,
                           max_iterations: int = 10_000,
                           z0: np.ndarray | None = None) -> LCPSolution:
    """Projected Gauss-Seidel: ``z_i <- max(0, z_i - (q_i + M_i z) / M_ii)``, sweep by sweep.

    Converges for symmetric PSD ``M`` with a positive diagonal; stops when the natural
    residual ``||min(z, M z + q)||_inf`` falls below ``tol``.
    """
    M = np.asarray(M, dtype=float)
    q = np.asarray(q, dtype=float)
    n = q.size
    diagonal = np.diag(M).copy()
    if np.any(diagonal <= 0):
        bad = int(np.flatnonzero(diagonal <= 0)[0])
        return LCPSolution(None, False, f"PGS needs M_ii > 0 (M[{bad},{bad}] = "
                           f"{diagonal[bad]:.3g})", 0, [])
    z = np.zeros(n) if z0 is None else np.maximum(np.asarray(z0, dtype=float), 0.0)
    residuals: list[float] = []
    for sweep in range(1, max_iterations + 1):
        for i in range(n):
            z[i] = max(0.0, z[i] - (q[i] + M[i] @ z) / diagonal[i])
        residual = natural_residual(M, q, z)
        residuals.append(residual)
        if not np.isfinite(residual):
            return LCPSolution(None, False, "diverged (non-finite)", sweep, residuals)
        if residual <= tol:
            return LCPSolution(z, True, "solved", sweep, residuals)
    return LCPSolution(z, False, f"iteration limit {max_iterations} reached",
                       max_iterations, residuals)
