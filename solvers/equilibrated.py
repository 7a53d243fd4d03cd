"""The reference study's equilibrated Schur-complement solve of an equality-constrained QP.

For (the reference study's convention, ``Q = P / 2`` and ``c = q`` for a
:class:`problems.instance.Problem`)

    minimise  x^T Q x + c^T x   subject to   A x = b,

with ``Q`` symmetric positive definite, the KKT conditions are ``2 Q x + c + A^T y = 0`` and
``A x = b``; ``y`` is the equality dual in qpsolvers' sign convention (``P x + q + A^T y = 0``).
Eliminating ``x`` gives the Schur system with ``S = A Q^-1 A^T``:

    S y = -(2 b + A Q^-1 c),        x = -1/2 (Q^-1 c + Q^-1 A^T y).

The method (seed 000, section 3.2), each step switchable through :class:`EquilibrationSteps`:

1. ``row_scaling``: ``A <- R A``, ``b <- R b`` with ``R = diag(1 / (||A_i||_2 + eps))``.
2. ``ruiz_q``: one Ruiz iteration on ``Q``: ``D = diag(1 / (sqrt(||Q_i||_inf) + eps))``,
   ``Q <- D Q D``, ``A <- A D``, ``c <- D c`` (the variable becomes ``x = D x~``).
3. Cholesky ``Q = L L^T``; solves for ``Q^-1 A^T`` and ``Q^-1 c``.
4. ``S = A (Q^-1 A^T)``.
5. ``symmetrize``: ``S <- (S + S^T) / 2``.
6. ``ruiz_schur``: one Ruiz iteration on ``S``: ``E = diag(1 / (sqrt(||S_i||_inf) + eps))``,
   ``S <- E S E`` (the multiplier becomes ``y = E v``).
7. ``ridge``: ``S <- S + delta I`` with ``delta = ridge * max_i S_ii``. The ridge is *relative*
   to the largest diagonal entry of the matrix being factorised. After step 6 that entry is
   at most 1 (a PSD matrix's largest entry sits on its diagonal, and one Ruiz iteration maps
   every entry into [-1, 1]), so with the full method it coincides with the reference study's
   absolute ``1e-4``; in ablations without step 6 a relative ridge keeps the same meaning instead of
   vanishing against entries of ``1e5`` or swamping entries of ``1e-6``. It bounds
   ``cond(S + delta I) <= (lambda_max + delta) / delta <= m (1 + 1/ridge)`` after Ruiz.
8. Cholesky solve of ``S v = E (-(2 b + A Q^-1 c))``; when it fails and ``cholesky_fallback``
   is on, the ridge is raised tenfold (from at least ``m eps_dtype max_i S_ii``) up to
   ``MAX_FALLBACKS`` times, and the count is reported.
9. ``x~ = -1/2 (Q^-1 c + Q^-1 A^T y)``, unscaled ``x = D x~``, ``y_orig = R E v``.
10. ``projection``: least-norm correction onto ``A x = b`` in the original variables,
    ``x <- x - A^T (A A^T)^-1 (A x - b)``, computed from an economic QR of the row-scaled
    ``A^T = Q_A R_A`` as ``x <- x - Q_A R_A^-T (R (A x - b))`` (never forming ``A A^T``, whose
    condition number is the square of ``A``'s). ``y`` is not changed by the projection.
11. Return ``x`` and ``y``.

All arithmetic runs in the requested dtype (``float32`` or ``float64``); the reported
condition numbers and violations are computed afterwards in float64 against the original
data. :meth:`EquilibratedKKT.factorize` does steps 1-7 (everything that depends only on
``Q`` and ``A``) once; :meth:`EquilibratedKKT.solve` does steps 8-11 for any ``(c, b)``, so a
controller can reuse a factorisation while ``rho`` does not change. The per-instance table
of condition numbers for reports is :func:`c3bench.solvers.conditioning.conditioning_table`.

References
----------
D. Ruiz, "A scaling algorithm to equilibrate both rows and columns norms in matrices",
Technical Report RAL-TR-2001-034, Rutherford Appleton Laboratory, 2001 (steps 2 and 6).

G. H. Golub and C. F. Van Loan, *Matrix Computations*, 4th ed., Johns Hopkins University
Press, 2013 (Cholesky, Schur complement and least-norm projection by QR).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field, fields, replace
from typing import Any

import numpy as np
import scipy.linalg

from c3bench.problems.errors import NotPositiveDefiniteError
from c3bench.problems.names import Precision

MAX_FALLBACKS = 10
"""Most ridge increases of the Cholesky fallback (step 8)."""


@dataclass(frozen=True)
class EquilibrationSteps:
    """Which steps of the method run (ablation switches); defaults are the reference study's method.

    Attributes
    ----------
    row_scaling
        Step 1, rows of ``A`` and ``b`` scaled to unit 2-norm.
    ruiz_q
        Step 2, one Ruiz iteration on ``Q`` and the matching column scaling of ``A`` and ``c``.
    symmetrize
        Step 5, ``S <- (S + S^T) / 2``.
    ruiz_schur
        Step 6, one Ruiz iteration on ``S``.
    ridge
        Step 7, relative ridge ``delta = ridge * max_i S_ii`` (0 switches it off).
    projection
        Step 10, least-norm projection of ``x`` onto ``A x = b``.
    cholesky_fallback
        Step 8, raise the ridge and retry when the Cholesky factorisation of ``S`` fails
        (off: the failure is raised as :class:`NotPositiveDefiniteError`).
    eps
        Guard added to every norm before it is inverted; it only matters for an all-zero
        row, and is far below any nonzero norm of our instances.
    """

    row_scaling: bool = True
    ruiz_q: bool = True
    symmetrize: bool = True
    ruiz_schur: bool = True
    ridge: float = 1e-4
    projection: bool = True
    cholesky_fallback: bool = True
    eps: float = 1e-12

    def __post_init__(self) -> None:
        if not (math.isfinite(self.ridge) and self.ridge >= 0):
            raise ValueError(f"ridge must be finite and >= 0, got {self.ridge!r}")
        if not (math.isfinite(self.eps) and self.eps >= 0):
            raise ValueError(f"eps must be finite and >= 0, got {self.eps!r}")

    @classmethod
    def none(cls) -> EquilibrationSteps:
        """Every step off: the plain Schur-complement solve with Cholesky."""
        return cls(row_scaling=False, ruiz_q=False, symmetrize=False, ruiz_schur=False,
                   ridge=0.0, projection=False, cholesky_fallback=False)

    def with_options(self, options: Mapping[str, Any]) -> EquilibrationSteps:
        """A copy with the switches named in ``options`` changed (unknown names raise)."""
        names = {f.name: f for f in fields(self)}
        changes: dict[str, Any] = {}
        for key, value in options.items():
            if key not in names:
                raise ValueError(f"unknown equilibration step {key!r}; known: "
                                 f"{', '.join(names)}")
            if names[key].type in ("bool", bool):
                if not isinstance(value, bool | np.bool_):
                    raise ValueError(f"step {key!r} takes True or False, got {value!r}")
                changes[key] = bool(value)
            else:
                changes[key] = float(value)
        return replace(self, **changes)


#: Named ablations: the full method, each step switched off alone, and every step off.
ABLATIONS: dict[str, EquilibrationSteps] = {
    "full": EquilibrationSteps(),
    "no_row_scaling": EquilibrationSteps(row_scaling=False),
    "no_ruiz_q": EquilibrationSteps(ruiz_q=False),
    "no_symmetrize": EquilibrationSteps(symmetrize=False),
    "no_ruiz_schur": EquilibrationSteps(ruiz_schur=False),
    "no_ridge": EquilibrationSteps(ridge=0.0),
    "no_projection": EquilibrationSteps(projection=False),
    "none": EquilibrationSteps.none(),
}


def scalar_type(precision: str) -> type[np.floating[Any]]:
    """The numpy scalar type of a :class:`~c3bench.problems.names.Precision` name
    (``ValueError`` for any other name)."""
    if precision not in tuple(Precision):
        raise ValueError(f"precision must be one of {tuple(map(str, Precision))}, got "
                         f"{precision!r}")
    return Precision(precision).dtype.type


def _cholesky(matrix: np.ndarray, what: str) -> tuple[np.ndarray, bool]:
    """``scipy.linalg.cho_factor`` (lower) that raises :class:`NotPositiveDefiniteError`."""
    try:
        factor = scipy.linalg.cho_factor(matrix, lower=True, check_finite=True)
    except np.linalg.LinAlgError as error:
        raise NotPositiveDefiniteError(f"{what} is not positive definite: Cholesky failed "
                                       f"({error})") from error
    except ValueError as error:  # non-finite entries
        raise NotPositiveDefiniteError(f"{what} cannot be factorised: {error}") from error
    if not np.all(np.isfinite(factor[0])):
        raise NotPositiveDefiniteError(f"{what}: Cholesky factor is not finite")
    return np.asarray(factor[0]), bool(factor[1])


@dataclass
class EquilibratedKKT:
    """Steps 1-7 done for one ``(Q, A)``: scalings, factors, the Schur matrix.

    Build with :meth:`factorize`; solve with :meth:`solve`. Arrays are in the working dtype.

    Attributes
    ----------
    steps, precision
        The switches and the working precision.
    row_scale, col_scale, schur_scale
        Diagonals of ``R`` (step 1), ``D`` (step 2) and ``E`` (step 6); ones when off.
    A_rows
        ``R A`` (row-scaled, original columns), used by the projection.
    A_scaled
        ``R A D``.
    q_factor
        Cholesky factor of ``D Q D``.
    q_inv_at
        ``(D Q D)^-1 (R A D)^T``.
    schur_scaled
        ``E S E`` after steps 4-6 (before the ridge).
    schur_factor
        Cholesky factor of the matrix actually factorised (with the ridge).
    ridge_used
        Absolute ridge added (after any fallback).
    fallbacks
        How many times the ridge had to be raised for Cholesky to succeed.
    schur_asymmetry
        ``max |S - S^T| / max |S|`` of the matrix handed to Cholesky.
    projector
        ``(Q_A, R_A)`` of the economic QR of ``A_rows^T`` (``None`` when projection is off).
    """

    steps: EquilibrationSteps
    precision: str
    row_scale: np.ndarray
    col_scale: np.ndarray
    schur_scale: np.ndarray
    A_rows: np.ndarray
    A_scaled: np.ndarray
    q_factor: tuple[np.ndarray, bool]
    q_inv_at: np.ndarray
    schur_scaled: np.ndarray
    schur_factor: tuple[np.ndarray, bool]
    ridge_used: float
    fallbacks: int
    schur_asymmetry: float
    projector: tuple[np.ndarray, np.ndarray] | None = None

    @classmethod
    def factorize(cls, Q: np.ndarray, A: np.ndarray,
                  steps: EquilibrationSteps | None = None,
                  precision: str = Precision.FLOAT64) -> EquilibratedKKT:
        """Steps 1-7 (and the QR of step 10) for ``min x^T Q x + c^T x s.t. A x = b``.

        Raises
        ------
        NotPositiveDefiniteError
            ``Q`` after scaling, or the Schur complement (fallback off or exhausted), is not
            numerically positive definite.
        ValueError
            Wrong shapes or precision.
        """
        steps = steps or EquilibrationSteps()
        dtype = scalar_type(precision)
        Q = np.asarray(Q, dtype=dtype)
        A = np.asarray(A, dtype=dtype)
        n = Q.shape[0]
        if Q.shape != (n, n):
            raise ValueError(f"Q must be square, got shape {Q.shape}")
        if A.ndim != 2 or A.shape[1] != n:
            raise ValueError(f"A must have {n} columns, got shape {A.shape}")
        m = A.shape[0]
        eps = dtype(steps.eps)
        # step 1: rows of A (and later b) to unit 2-norm
        if steps.row_scaling:
            row_scale = (dtype(1) / (np.linalg.norm(A, axis=1) + eps)).astype(dtype)
        else:
            row_scale = np.ones(m, dtype=dtype)
        A_rows = A * row_scale[:, None]
        # step 2: one Ruiz iteration on Q, the same column scaling on A (and later c)
        if steps.ruiz_q:
            col_scale = (dtype(1) / (np.sqrt(np.max(np.abs(Q), axis=1)) + eps)).astype(dtype)
        else:
            col_scale = np.ones(n, dtype=dtype)
        Q_scaled = np.outer(col_scale, col_scale) * Q  # (d_i d_j) Q_ij: keeps symmetry exactly
        A_scaled = A_rows * col_scale[None, :]
        # step 3: Cholesky of Q, then Q^-1 A^T
        q_factor = _cholesky(Q_scaled, "Q (after scaling)")
        q_inv_at = scipy.linalg.cho_solve(q_factor, A_scaled.T, check_finite=False)
        # step 4: S = A Q^-1 A^T
        schur = A_scaled @ q_inv_at
        # step 5: symmetrise
        if steps.symmetrize:
            schur = (schur + schur.T) * dtype(0.5)
        # step 6: one Ruiz iteration on S
        if steps.ruiz_schur:
            schur_scale = (dtype(1) / (np.sqrt(np.max(np.abs(schur), axis=1)) + eps)
                           ).astype(dtype)
        else:
            schur_scale = np.ones(m, dtype=dtype)
        schur = np.outer(schur_scale, schur_scale) * schur  # exact symmetry is preserved
        top = float(np.max(np.abs(schur), initial=0.0))
        asymmetry = float(np.max(np.abs(schur - schur.T), initial=0.0)) / top if top else 0.0
        # steps 7 and 8 (factorisation part): ridge, Cholesky, fallback
        diagonal_max = float(np.max(np.diag(schur), initial=0.0))
        ridge = steps.ridge * diagonal_max
        fallbacks = 0
        while True:
            matrix = schur + dtype(ridge) * np.eye(m, dtype=dtype) if ridge > 0 else schur
            try:
                schur_factor = _cholesky(matrix, "the Schur complement A Q^-1 A^T")
                break
            except NotPositiveDefiniteError:
                if not steps.cholesky_fallback or fallbacks >= MAX_FALLBACKS:
                    raise
                floor = m * float(np.finfo(dtype).eps) * max(diagonal_max, 1e-300)
                ridge = max(10.0 * ridge, floor)
                fallbacks += 1
        projector = None
        if steps.projection:
            projector = scipy.linalg.qr(A_rows.T, mode="economic", check_finite=False)
            r_diag = np.abs(np.diag(projector[1]))
            if m and r_diag.min() <= m * float(np.finfo(dtype).eps) * r_diag.max():
                raise ValueError("A is rank deficient: the projection onto A x = b is not "
                                 "defined by (A A^T)^-1")
        return cls(steps=steps, precision=precision, row_scale=row_scale,
                   col_scale=col_scale, schur_scale=schur_scale, A_rows=A_rows,
                   A_scaled=A_scaled, q_factor=q_factor, q_inv_at=q_inv_at,
                   schur_scaled=schur, schur_factor=schur_factor, ridge_used=ridge,
                   fallbacks=fallbacks, schur_asymmetry=asymmetry, projector=projector)

    @property
    def dtype(self) -> type[np.floating[Any]]:
        """The scalar type of the working precision."""
        return scalar_type(self.precision)

    def schur_factorised(self) -> np.ndarray:
        """The matrix that was handed to Cholesky: ``E S E + delta I``."""
        m = self.schur_scaled.shape[0]
        ridge = self.dtype(self.ridge_used) * np.eye(m, dtype=self.dtype)
        factorised: np.ndarray = self.schur_scaled + ridge
        return factorised

    def solve(self, c: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Steps 8-11 for linear term ``c`` and right-hand side ``b``.

        Returns
        -------
        x, y, x_unprojected
            Primal (after projection when it is on), equality dual of the original problem
            (``2 Q x + c + A^T y = 0``) and the primal before projection, in the working dtype.
        """
        dtype = self.dtype
        c = np.asarray(c, dtype=dtype)
        b = np.asarray(b, dtype=dtype)
        if c.shape != (self.col_scale.shape[0],):
            raise ValueError(f"c must have shape ({self.col_scale.shape[0]},), got {c.shape}")
        if b.shape != (self.row_scale.shape[0],):
            raise ValueError(f"b must have shape ({self.row_scale.shape[0]},), got {b.shape}")
        b_rows = self.row_scale * b
        c_scaled = self.col_scale * c
        q_inv_c = scipy.linalg.cho_solve(self.q_factor, c_scaled, check_finite=False)
        # step 8: S y = -(2 b + A Q^-1 c), equilibrated: (E S E) v = E rhs, y = E v
        rhs = -(dtype(2) * b_rows + self.A_scaled @ q_inv_c)
        v = scipy.linalg.cho_solve(self.schur_factor, self.schur_scale * rhs,
                                   check_finite=False)
        y_scaled = self.schur_scale * v
        # step 9: x~ = -1/2 (Q^-1 c + Q^-1 A^T y), x = D x~, y = R y~
        x = self.col_scale * (dtype(-0.5) * (q_inv_c + self.q_inv_at @ y_scaled))
        y = self.row_scale * y_scaled
        x_unprojected = x
        # step 10: least-norm projection onto A x = b via the QR of (R A)^T
        if self.projector is not None:
            basis, triangle = self.projector
            residual = self.A_rows @ x - b_rows
            step = scipy.linalg.solve_triangular(triangle, residual, trans="T",
                                                 check_finite=False)
            x = x - basis @ step
        # step 11
        return x, y, x_unprojected


@dataclass
class EquilibrationDiagnostics:
    """What the method reports about one solve (float64 figures on the original data).

    Attributes
    ----------
    cond_schur_raw
        2-norm condition number of ``A Q^-1 A^T`` from the unscaled data.
    cond_schur_scaled
        Condition number of ``E S E`` after the scaling steps 1-6 (no ridge).
    cond_schur_equilibrated
        Condition number of the equilibrated matrix that is factorised: ``E S E + delta I``
        (steps 1-7; equals ``cond_schur_scaled`` when the ridge is 0).
    violation_before_projection, violation_after_projection
        ``||A x - b||_inf`` before and after step 10 (equal when the projection is off).
    mean_violation_before_projection, mean_violation_after_projection
        ``mean |A x - b|`` before and after step 10.
    cholesky_fallback
        Times the ridge was raised for the Schur Cholesky to succeed (0: no fallback).
    ridge_used
        Absolute ridge added to the equilibrated ``S``.
    schur_asymmetry
        ``max |S - S^T| / max |S|`` of the factorised matrix (0 after symmetrisation).
    """

    cond_schur_raw: float
    cond_schur_scaled: float
    cond_schur_equilibrated: float
    violation_before_projection: float
    violation_after_projection: float
    mean_violation_before_projection: float
    mean_violation_after_projection: float
    cholesky_fallback: float
    ridge_used: float
    schur_asymmetry: float

    def as_dict(self) -> dict[str, float]:
        return {f.name: float(getattr(self, f.name)) for f in fields(self)}


@dataclass
class EquilibratedSolution:
    """Result of :func:`solve_equality_qp` (``x``, ``y`` cast to float64).

    ``y`` follows qpsolvers' convention for the original problem: ``2 Q x + c + A^T y = 0``
    (``P x + q + A^T y = 0`` with ``P = 2 Q``).
    """

    x: np.ndarray
    y: np.ndarray
    x_unprojected: np.ndarray
    kkt: EquilibratedKKT
    diagnostics: EquilibrationDiagnostics | None = field(default=None)


def condition_number(matrix: np.ndarray) -> float:
    """2-norm condition number in float64 (``inf`` for a singular or non-finite matrix)."""
    matrix = np.asarray(matrix, dtype=np.float64)
    if not np.all(np.isfinite(matrix)):
        return math.inf
    singular = np.linalg.svd(matrix, compute_uv=False)
    if singular.size == 0:
        return 1.0
    return math.inf if singular[-1] == 0 else float(singular[0] / singular[-1])


def raw_schur(Q: np.ndarray, A: np.ndarray) -> np.ndarray:
    """``A Q^-1 A^T`` in float64 from the unscaled data (``inf`` entries if ``Q`` is singular)."""
    Q = np.asarray(Q, dtype=np.float64)
    A = np.asarray(A, dtype=np.float64)
    try:
        factor = scipy.linalg.cho_factor(Q, lower=True)
        schur: np.ndarray = A @ scipy.linalg.cho_solve(factor, A.T)
        return schur
    except np.linalg.LinAlgError:
        return np.full((A.shape[0], A.shape[0]), np.inf)


def _violations(A: np.ndarray, b: np.ndarray, x: np.ndarray) -> tuple[float, float]:
    residual = np.abs(A @ np.asarray(x, dtype=np.float64) - b)
    if residual.size == 0:
        return 0.0, 0.0
    return float(residual.max()), float(residual.mean())


def diagnose(kkt: EquilibratedKKT, Q: np.ndarray, A: np.ndarray, b: np.ndarray,
             x: np.ndarray, x_unprojected: np.ndarray,
             cond_raw: float | None = None,
             conditioning: bool = True) -> EquilibrationDiagnostics:
    """Condition numbers and violations of one solve, in float64 on the original data.

    ``cond_raw`` skips recomputing ``cond(A Q^-1 A^T)`` when the caller already has it;
    ``conditioning=False`` skips every condition number (reported as ``nan``).
    """
    A64 = np.asarray(A, dtype=np.float64)
    b64 = np.asarray(b, dtype=np.float64)
    before_max, before_mean = _violations(A64, b64, x_unprojected)
    after_max, after_mean = _violations(A64, b64, x)
    if not conditioning:
        raw = scaled = equilibrated = math.nan
    else:
        raw = condition_number(raw_schur(Q, A64)) if cond_raw is None else cond_raw
        scaled = condition_number(kkt.schur_scaled)
        equilibrated = condition_number(kkt.schur_factorised())
    return EquilibrationDiagnostics(
        cond_schur_raw=raw,
        cond_schur_scaled=scaled,
        cond_schur_equilibrated=equilibrated,
        violation_before_projection=before_max,
        violation_after_projection=after_max,
        mean_violation_before_projection=before_mean,
        mean_violation_after_projection=after_mean,
        cholesky_fallback=float(kkt.fallbacks),
        ridge_used=kkt.ridge_used,
        schur_asymmetry=kkt.schur_asymmetry,
    )


def solve_equality_qp(Q: np.ndarray, c: np.ndarray, A: np.ndarray, b: np.ndarray,
                      steps: EquilibrationSteps | None = None,
                      precision: str = Precision.FLOAT64,
                      diagnostics: bool = True) -> EquilibratedSolution:
    """Solve ``min x^T Q x + c^T x s.t. A x = b`` by the 11 steps (module docstring).

    Parameters
    ----------
    Q, c, A, b
        Problem data in the reference study's convention (for a ``Problem``: ``Q = P / 2``, ``c =
    q``). steps
        Ablation switches (default: the full method).
    precision
        ``"float64"`` or ``"float32"``: the dtype of all arithmetic of the method.
    diagnostics
        Also compute :class:`EquilibrationDiagnostics` (SVDs in float64; leave it off inside
        timed sections and call :func:`diagnose` afterwards).

    Raises
    ------
    NotPositiveDefiniteError
        Cholesky of the scaled ``Q``, or of the Schur complement without a working fallback,
        failed.
    """
    kkt = EquilibratedKKT.factorize(Q, A, steps, precision)
    x, y, x_unprojected = kkt.solve(c, b)
    solution = EquilibratedSolution(x=x.astype(np.float64), y=y.astype(np.float64),
                                    x_unprojected=x_unprojected.astype(np.float64), kkt=kkt)
    if diagnostics:
        solution.diagnostics = diagnose(kkt, Q, A, b, solution.x, solution.x_unprojected)
    return solution
