"""The vectors of a QP in the forms the update APIs take (a helper module: the registry skips
modules whose name starts with ``_``).

A warm cell (:mod:`c3bench.solvers.timing`) gives a solver object that was set up on the
instance's matrices only the instance's vectors: these functions rebuild exactly the vectors
of :class:`~c3bench.solvers.backends._qp_forms.TwoSidedForm` and
:class:`~c3bench.solvers.backends._qp_forms.ConeForm` from a problem, reusing the row layout
(which variables carry bound rows) of the form the object was set up with, without stacking
any matrix again.
"""

from __future__ import annotations

import numpy as np

from c3bench.problems.instance import Problem
from c3bench.solvers.backends._qp_forms import ConeForm, TwoSidedForm


def full_bounds(problem: Problem) -> tuple[np.ndarray, np.ndarray]:
    """``lb`` and ``ub`` as full vectors (``-inf`` / ``+inf`` where absent)."""
    n = problem.n
    lb = np.full(n, -np.inf) if problem.lb is None else np.asarray(problem.lb, dtype=float)
    ub = np.full(n, np.inf) if problem.ub is None else np.asarray(problem.ub, dtype=float)
    return lb, ub


def _b_h(problem: Problem) -> tuple[np.ndarray, np.ndarray]:
    b = np.zeros(0) if problem.b is None else np.asarray(problem.b, dtype=float)
    h = np.zeros(0) if problem.h is None else np.asarray(problem.h, dtype=float)
    return b, h


def two_sided_vectors(form: TwoSidedForm, problem: Problem) -> tuple[np.ndarray, np.ndarray]:
    """``(lower, upper)`` of ``l <= [A; G; I_S] z <= u`` for ``problem``'s vectors, on the
    rows of ``form`` (same ``S``)."""
    lb, ub = full_bounds(problem)
    b, h = _b_h(problem)
    lower = np.concatenate([b, np.full(h.size, -np.inf), lb[form.bounded]])
    upper = np.concatenate([b, h, ub[form.bounded]])
    return lower, upper


def cone_rhs(form: ConeForm, problem: Problem) -> np.ndarray:
    """``rhs = [b; h; ub_U; -lb_L]`` of ``form``'s rows for ``problem``'s vectors."""
    lb, ub = full_bounds(problem)
    b, h = _b_h(problem)
    return np.concatenate([b, h, ub[form.upper_index], -lb[form.lower_index]])
