"""The ``Problem`` contract: one subproblem instance in the shared QP-with-complementarity form.

Every family is stored in one QP-with-complementarity form, following qpsolvers' names:

    minimise    1/2 z^T P z + q^T z + objective_offset
    subject to  A z = b,   G z <= h,   lb <= z <= ub,
                0 <= z_i  perp  z_j >= 0   for every row (i, j) of ``complementarity``.

``lcs`` holds the LCS the instance came from (optional: ``None`` for an instance without one),
``data`` the family's own arrays (``x0``, ``delta``, ``w``, ``G_diag``, ``v``, ``U_diag``, ...),
``meta`` its JSON metadata. :class:`Problem` validates its fields when built; its storage
(``.npz`` + JSON) is :mod:`problems.instance`, which re-exports these names.

Part of the plant-free core: imports neither MuJoCo nor CasADi.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from c3bench.problems.lcs import LCS
from c3bench.problems.names import Family

__all__ = ["FAMILIES", "QP_FIELDS", "REQUIRED_META", "SCHEMA_VERSION", "Problem", "lcp_data"]

SCHEMA_VERSION = 1
FAMILIES: tuple[str, ...] = tuple(Family)
"""Family names in their canonical order (:class:`c3bench.problems.names.Family`)."""
QP_FIELDS: tuple[str, ...] = ("P", "q", "A", "b", "G", "h", "lb", "ub")
REQUIRED_META: tuple[str, ...] = ("scene", "l", "dt", "T", "seed", "precision")
"""Metadata describing the cube scene: required of the cube families only (the generic
families, :data:`~c3bench.problems.names.GENERIC_FAMILIES`, load without it)."""


@dataclass
class Problem:
    """One subproblem instance (see the module docstring for the form).

    Attributes
    ----------
    name
        Unique, file-safe name.
    family
        One of :data:`FAMILIES`.
    P, q
        Objective ``1/2 z^T P z + q^T z`` (P symmetric positive semi-definite, dense).
    A, b
        Equalities ``A z = b`` (``None`` when absent).
    G, h
        Inequalities ``G z <= h`` (``None`` when absent).
    lb, ub
        Bounds (``None`` when absent; entries may be infinite).
    complementarity
        Integer array (pairs x 2): ``0 <= z[i] perp z[j] >= 0``; ``None`` when absent.
    objective_offset
        Constant added to the objective, so that it equals the family's true cost.
    lcs
        The LCS the instance came from, or ``None`` (then no ``lcs.*`` arrays are stored).
    data
        Family-specific arrays.
    meta
        JSON-serialisable metadata (family, scene, l, dt, T, rho, admm_iteration,
        state_index, seed, precision, ...).
    """

    name: str
    family: str
    P: np.ndarray
    q: np.ndarray
    A: np.ndarray | None = None
    b: np.ndarray | None = None
    G: np.ndarray | None = None
    h: np.ndarray | None = None
    lb: np.ndarray | None = None
    ub: np.ndarray | None = None
    complementarity: np.ndarray | None = None
    objective_offset: float = 0.0
    lcs: LCS | None = None
    data: dict[str, np.ndarray] = field(default_factory=dict)
    meta: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.validate()

    # --- sizes ----------------------------------------------------------------------------
    @property
    def n(self) -> int:
        """Number of variables."""
        return int(self.q.shape[0])

    @property
    def n_eq(self) -> int:
        """Equality rows."""
        return 0 if self.A is None else int(self.A.shape[0])

    @property
    def n_ineq(self) -> int:
        """Inequality rows."""
        return 0 if self.G is None else int(self.G.shape[0])

    @property
    def n_pairs(self) -> int:
        """Complementarity pairs."""
        return 0 if self.complementarity is None else int(self.complementarity.shape[0])

    @property
    def n_bounded(self) -> int:
        """Variables with at least one finite bound."""
        finite = np.zeros(self.n, dtype=bool)
        for bound in (self.lb, self.ub):
            if bound is not None:
                finite |= np.isfinite(bound)
        return int(finite.sum())

    # --- checks ---------------------------------------------------------------------------
    def validate(self) -> None:
        """Check shapes and values; raise ``ValueError`` naming the field at fault."""
        if self.family not in FAMILIES:
            raise ValueError(f"family must be one of {', '.join(map(str, FAMILIES))}, got "
                             f"{self.family!r}")
        self.q = _as_float("q", self.q, ndim=1)
        n = self.q.shape[0]
        self.P = _as_float("P", self.P, ndim=2)
        rows, columns = self.P.shape
        if rows == columns != n:  # a square P of another size: q is the one at fault
            raise ValueError(f"{self.name}: q has length {n} but P is {rows} x {columns}: q "
                             f"must have length {rows} (or P must have shape ({n}, {n}))")
        if self.P.shape != (n, n):
            raise ValueError(f"P must have shape {(n, n)}, got {self.P.shape}")
        if not np.all(np.isfinite(self.P)):
            raise ValueError(f"{self.name}: P has non-finite entries")
        if not np.all(np.isfinite(self.q)):
            raise ValueError(f"{self.name}: q has non-finite entries")
        scale = max(1.0, float(np.max(np.abs(self.P), initial=0.0)))
        if np.max(np.abs(self.P - self.P.T), initial=0.0) > 1e-9 * scale:
            raise ValueError(f"{self.name}: P is not symmetric")
        for matrix, vector in (("A", "b"), ("G", "h")):
            M, v = getattr(self, matrix), getattr(self, vector)
            if (M is None) != (v is None):
                raise ValueError(f"{self.name}: {matrix} and {vector} must both be given or "
                                 "both be None")
            if M is None:
                continue
            M = _as_float(matrix, M, ndim=2)
            if M.shape[1] != n:
                raise ValueError(f"{self.name}: {matrix} must have {n} columns, got {M.shape}")
            v = _as_float(vector, v, shape=(M.shape[0],))
            for label, value in ((matrix, M), (vector, v)):
                if not np.all(np.isfinite(value)):
                    raise ValueError(f"{self.name}: {label} has non-finite entries")
            setattr(self, matrix, M)
            setattr(self, vector, v)
        for bound in ("lb", "ub"):
            value = getattr(self, bound)
            if value is None:
                continue
            value = _as_float(bound, value, shape=(n,))
            if np.any(np.isnan(value)):
                raise ValueError(f"{self.name}: {bound} has NaN entries")
            setattr(self, bound, value)
        if self.lb is not None and self.ub is not None and np.any(self.lb > self.ub):
            raise ValueError(f"{self.name}: lb > ub at index "
                             f"{int(np.flatnonzero(self.lb > self.ub)[0])}")
        if self.complementarity is not None:
            pairs = np.asarray(self.complementarity)
            if pairs.ndim != 2 or pairs.shape[1] != 2 or not np.issubdtype(pairs.dtype,
                                                                           np.integer):
                raise ValueError(f"{self.name}: complementarity must be an integer array of "
                                 f"shape (pairs, 2), got {pairs.dtype} {pairs.shape}")
            if pairs.size and (pairs.min() < 0 or pairs.max() >= n):
                raise ValueError(f"{self.name}: complementarity indices outside 0..{n - 1}")
            self.complementarity = pairs.astype(np.int64)
        if not math.isfinite(self.objective_offset):
            raise ValueError(f"{self.name}: objective_offset must be finite")
        for key, value in self.data.items():
            self.data[key] = np.asarray(value)
        if self.family == Family.LCP_GENERAL:
            _check_lcp_general(self)

    # --- evaluation -----------------------------------------------------------------------
    def objective(self, z: np.ndarray) -> float:
        """``1/2 z^T P z + q^T z + objective_offset``."""
        z = np.asarray(z, dtype=float)
        return float(0.5 * z @ self.P @ z + self.q @ z + self.objective_offset)

    def summary(self) -> dict[str, Any]:
        """Sizes for listings: variables, equality and inequality rows, pairs, bounds."""
        return {"name": self.name, "family": self.family, "variables": self.n,
                "equality_rows": self.n_eq, "inequality_rows": self.n_ineq,
                "bounded_variables": self.n_bounded, "complementarity_pairs": self.n_pairs}


def lcp_data(problem: Problem, copy: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """``(F, q)`` of the LCP ``0 <= lam perp F lam + q >= 0`` an ``lcp`` or ``lcp_general``
    instance states: ``(data["F"], h)`` for ``lcp_general`` (``F`` stored as is,
    :func:`c3bench.problems.families.lcp_general`), ``(P, q)`` for ``lcp`` (whose ``F`` is
    symmetric and is the QP's Hessian). ``copy``: float64 copies a solver may overwrite
    (the instance's own arrays otherwise)."""
    if problem.family == Family.LCP_GENERAL:
        assert problem.h is not None  # checked by Problem.validate
        F, q = problem.data["F"], problem.h
    else:
        F, q = problem.P, problem.q
    if copy:
        return np.array(F, dtype=np.float64), np.array(q, dtype=np.float64)
    return F, q


def _check_lcp_general(problem: Problem) -> None:
    """An ``lcp_general`` instance is exactly the form of
    :func:`c3bench.problems.families.lcp_general`: ``data["F"]`` square of size ``n`` and
    finite, ``P = 0``, ``q = 0``, ``G = -F``, ``h`` (the LCP's ``q``) given, ``lb = 0``,
    nothing else; ``ValueError`` naming the field at fault."""
    n, name = problem.n, problem.name
    if "F" not in problem.data:
        raise ValueError(f"{name}: an lcp_general instance stores its matrix as data['F']; "
                         "build it with c3bench.problems.families.lcp_general")
    F = _as_float("data['F']", problem.data["F"], shape=(n, n))
    if not np.all(np.isfinite(F)):
        raise ValueError(f"{name}: data['F'] has non-finite entries")
    problem.data["F"] = F
    expected = (("P", problem.P, np.zeros((n, n))), ("q", problem.q, np.zeros(n)),
                ("G", problem.G, -F), ("lb", problem.lb, np.zeros(n)))
    for label, value, form in expected:
        if value is None or value.shape != form.shape or not np.array_equal(value, form):
            raise ValueError(f"{name}: an lcp_general instance needs {label} of its stored "
                             "form (P = 0, q = 0, G = -F, h = the LCP's q, lb = 0; "
                             "c3bench.problems.families.lcp_general)")
    extra = [label for label, value in (("A", problem.A), ("complementarity",
                                                          problem.complementarity))
             if value is not None]
    if problem.ub is not None and np.any(np.isfinite(problem.ub)):
        extra.append("ub")
    if extra:
        raise ValueError(f"{name}: an lcp_general instance takes no {', '.join(extra)}")


REAL_KINDS = "biuf"
"""NumPy dtype kinds of real numbers (bool, signed and unsigned integers, floats)."""


def check_real(key: str, array: np.ndarray) -> None:
    """``ValueError`` naming ``key`` unless ``array`` holds real numbers (complex data are
    never cut to their real part)."""
    if array.dtype.kind == "c":
        raise ValueError(f"key {key!r} is complex ({array.dtype}); instance data are real "
                         "numbers (nothing is cut to its real part)")
    if array.dtype.kind not in REAL_KINDS:
        raise ValueError(f"key {key!r} holds {array.dtype} values, not real numbers")


def _as_float(name: str, value: Any, ndim: int | None = None,
              shape: tuple[int, ...] | None = None) -> np.ndarray:
    raw = np.asarray(value)
    if raw.dtype.kind == "c":
        raise ValueError(f"{name} must be real, got complex values (nothing is cut to its "
                         "real part)")
    if raw.dtype.kind not in REAL_KINDS + "O":  # text is refused, as the loaders refuse it
        raise ValueError(f"{name} holds {raw.dtype} values, not real numbers")
    try:
        array = np.asarray(raw, dtype=np.float64)
    except (TypeError, ValueError) as error:
        raise ValueError(f"{name} must be numeric: {error}") from error
    if ndim is not None and array.ndim != ndim:
        raise ValueError(f"{name} must be {ndim}-D, got shape {array.shape}")
    if shape is not None and array.shape != shape:
        raise ValueError(f"{name} must have shape {shape}, got {array.shape}")
    return array
