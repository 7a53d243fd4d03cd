"""Core names as types: families, variants, precisions, profiles, failure categories, blocks.

Every name the benchmark stores or compares is defined here once, as a :class:`enum.StrEnum`
(so a member equals its string and is written to tables and JSON as that string), together with
the reference study's defaults. The reference study is the C3+ cube-tipping lab note whose
figures c3bench reproduces (``docs/reference_study.md``).

This module is part of the plant-free core: it imports neither MuJoCo nor CasADi.
"""

from __future__ import annotations

from enum import StrEnum
from types import MappingProxyType
from typing import Final

import numpy as np


class Family(StrEnum):
    """Subproblem families (``docs/families.md``)."""

    C3PLUS_QP = "c3plus_qp"
    """C3+ QP step: MPC cost plus the consensus term, dynamics and ``eta`` rows."""
    C3_QP = "c3_qp"
    """C3 QP step (no ``eta`` variables)."""
    PROJECTION = "projection"
    """One step's projection onto the complementarity set."""
    MPCC = "mpcc"
    """The whole-horizon MPC with complementarity constraints."""
    LCP = "lcp"
    """Forward-simulation LCP ``0 <= lam perp F lam + q >= 0`` with symmetric PSD ``F``."""
    LCP_GENERAL = "lcp_general"
    """An LCP ``0 <= lam perp F lam + q >= 0`` with ``F`` stored as is (not symmetric, e.g. the
    Stewart-Trinkle contact model): not a QP, solved by pivoting, splitting or an MIQP."""
    QP = "qp"
    """A generic convex QP in qpsolvers' form (``P q G h A b lb ub``), brought by the user
    (``c3bench problems import``); no cube metadata."""


SUITE_FAMILIES: Final = (Family.C3PLUS_QP, Family.C3_QP, Family.PROJECTION, Family.MPCC,
                         Family.LCP)
"""Families the cube-tipping suites generate (``problems generate``)."""
GENERIC_FAMILIES: Final = (Family.QP, Family.MPCC, Family.LCP, Family.LCP_GENERAL)
"""Families whose instances need no cube metadata (an imported problem may belong to them)."""
QP_FAMILIES: Final = (Family.C3PLUS_QP, Family.C3_QP, Family.LCP, Family.QP)
"""Families a convex QP solver can take (every convex QP backend handles equality and
inequality rows and bounds, so each takes the generic ``qp`` family too)."""
EQUALITY_QP_FAMILIES: Final = (Family.C3PLUS_QP, Family.C3_QP)
"""Families whose instances are equality-constrained QPs (the KKT-family backends)."""
COMPLEMENTARITY_FAMILIES: Final = (Family.PROJECTION, Family.MPCC)
"""Families with complementarity pairs (MIQP, NLP and ADMM backends)."""


class Variant(StrEnum):
    """ADMM method: C3 (Aydinoglu and Posa 2022) or C3+ (Bui et al. 2025).

    C3+ adds the slack ``eta = E x + F lam + H u + c`` to the QP step, which makes the
    projection separable per complementarity pair and solvable in closed form.
    """

    C3 = "c3"
    C3PLUS = "c3plus"


class QPVariant(StrEnum):
    """Form of a QP-step instance (``c3plus_qp``, ``c3_qp``): with or without the limits.

    ``bounded`` (the default) carries the MPC's input and state limits as bounds
    ``lb <= z <= ub``, as the reference C3 implementation keeps them in its QP step;
    ``equality`` has the dynamics (and ``eta``) rows only, for the KKT-family backends and the
    reference study's method, which take no inequalities.
    """

    BOUNDED = "bounded"
    EQUALITY = "equality"


QP_VARIANTS: Final = (QPVariant.BOUNDED, QPVariant.EQUALITY)
"""The QP-step variants a suite generates, the default first."""


class Precision(StrEnum):
    """Floating-point precision a backend runs in."""

    FLOAT64 = "float64"
    FLOAT32 = "float32"

    @property
    def dtype(self) -> np.dtype[np.floating]:
        """The numpy dtype of this precision."""
        return np.dtype(self.value)


class Profile(StrEnum):
    """Settings profiles; each has one tolerance (:data:`PROFILE_TOLERANCE`)."""

    DEFAULT = "default"
    LOW_ACCURACY = "low_accuracy"
    MID_ACCURACY = "mid_accuracy"
    HIGH_ACCURACY = "high_accuracy"


PROFILE_TOLERANCE: Final = MappingProxyType({
    Profile.DEFAULT: 1e-3,
    Profile.LOW_ACCURACY: 1e-3,
    Profile.MID_ACCURACY: 1e-6,
    Profile.HIGH_ACCURACY: 1e-9,
})
"""Tolerance of each profile: the solver's target and the success threshold."""


class Start(StrEnum):
    """How a solve starts: cold, or warm from the previous ADMM iterate's reference."""

    COLD = "cold"
    WARM = "warm"
    SEQUENCE = "sequence"
    """The whole ADMM run of the instance's state with this QP backend as its QP step, timed
    end to end (the QP steps a controller solves at one control step)."""


class Failure(StrEnum):
    """Failure categories of a solve (``Result.failure``; empty when the solver found x)."""

    NONE = ""
    """No failure reported (success is still judged by residuals)."""
    ERROR = "error"
    """The solver raised or returned an error status."""
    TIMEOUT = "timeout"
    """The wall-clock limit ran out (the isolated child was killed)."""
    INVALID_INPUT = "invalid_input"
    """The problem failed validation before the solver ran."""
    NON_FINITE = "non_finite"
    """The solver returned NaN or infinite values."""
    UNSUPPORTED = "unsupported"
    """The backend does not take this family, precision or form."""
    UNAVAILABLE = "unavailable"
    """The backend's package is missing or cannot load."""
    INFEASIBLE = "infeasible"
    """The solver reports the problem (primal) infeasible, or infeasible or unbounded when it
    cannot tell which."""
    UNBOUNDED = "unbounded"
    """The solver reports the problem dual infeasible: the objective unbounded below."""


class Block(StrEnum):
    """Blocks of one horizon step ``z_k = (x_k, lam_k, u_k, eta_k)``; keys of the rho weights."""

    X = "x"
    LAM = "lam"
    U = "u"
    ETA = "eta"


class LcsKernel(StrEnum):
    """How the batched LCS build (:class:`c3bench.problems.linearize_batch.BatchLinearizer`)
    works out each model sample's LCS."""

    NUMPY = "numpy"
    """numpy over a leading sample axis."""
    COMPILED = "compiled"
    """One numba call (:func:`c3bench.problems.linearize_compiled.sample_lcs`), Anitescu only."""


BLOCKS: Final = (Block.X, Block.LAM, Block.U, Block.ETA)
"""The blocks of one step in their order inside ``z_k``."""

REFERENCE_RHO0: Final = MappingProxyType({
    Block.X: 1.0, Block.LAM: 50.0, Block.U: 0.1, Block.ETA: 50.0})
"""The reference study's initial ADMM weights ``G = diag(rho_x, rho_lam, rho_u, rho_eta)``."""
REFERENCE_RHO_BLOCKS: Final = (Block.LAM, Block.ETA)
"""Blocks whose weight the reference study's schedule grows (``rho = 50 * 2^i``)."""
REFERENCE_RHO_FACTOR: Final = 2.0
"""Growth factor of the reference study's geometric schedule."""
REFERENCE_ADMM_ITERATIONS: Final = 10
"""ADMM iterations per control step in the reference study."""
