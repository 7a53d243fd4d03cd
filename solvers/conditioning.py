"""Conditioning figures of the equilibrated Schur-complement method, per instance, for reports.

:func:`conditioning_table` runs :class:`c3bench.solvers.equilibrated.EquilibratedKKT` on
equality-constrained QP instances and tabulates the 2-norm condition numbers of the Schur
complement before and after equilibration (:func:`~c3bench.solvers.equilibrated.diagnose`)
and the constraint violations before and after the projection, per precision.

References
----------
D. Ruiz, "A scaling algorithm to equilibrate both rows and columns norms in matrices",
Technical Report RAL-TR-2001-034, Rutherford Appleton Laboratory, 2001.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from typing import Any

from c3bench.problems.names import Block, Precision
from c3bench.solvers.equilibrated import (
    EquilibratedKKT,
    EquilibrationSteps,
    condition_number,
    diagnose,
    raw_schur,
)


def conditioning_table(problems: Iterable[Any],
                       precisions: tuple[str, ...] = (Precision.FLOAT64, Precision.FLOAT32),
                       ablations: Mapping[str, EquilibrationSteps] | None = None
                       ) -> list[dict[str, Any]]:
    """Per-instance conditioning and violation figures of the method, for reports.

    Parameters
    ----------
    problems
        Equality-constrained QP instances (``Problem`` with ``A``, ``b``; ``G`` and bounds are
        ignored), e.g. the ``c3plus_qp`` and ``c3_qp`` instances of a suite.
    precisions
        Precisions in which the full method is run for the violation columns.
    ablations
        Extra named step sets (e.g. :data:`ABLATIONS`) whose ``cond`` of the factorised matrix
        (float64) is added as column ``cond_schur_<name>`` (``inf`` when it cannot be built).

    Returns
    -------
    list of dict
        One row per instance: ``name``, ``family``, ``state_index``, ``admm_iteration``,
        ``rho_lam``; ``cond_schur_raw`` (``A Q^-1 A^T``), ``cond_schur_scaled`` (after steps
        1-6) and ``cond_schur_equilibrated`` (the factorised matrix, with the ridge), all of the
        float64 run; and per precision ``p``: ``violation_max_before_<p>``,
        ``violation_mean_before_<p>``, ``violation_max_after_<p>``,
        ``violation_mean_after_<p>`` (``|A x - b|`` before and after the projection) and
        ``error_<p>`` (the failure text, ``""`` when the solve ran).
    """
    rows: list[dict[str, Any]] = []
    for problem in problems:
        if problem.A is None or problem.b is None:
            raise ValueError(f"{problem.name}: conditioning_table needs equality constraints")
        Q = problem.P / 2.0
        rho = problem.meta.get("rho", {})
        cond_raw = condition_number(raw_schur(Q, problem.A))
        row: dict[str, Any] = {
            "name": problem.name, "family": problem.family,
            "state_index": problem.meta.get("state_index"),
            "admm_iteration": problem.meta.get("admm_iteration"),
            "rho_lam": (float(rho.get(Block.LAM, math.nan)) if isinstance(rho, dict)
                        else math.nan),
            "cond_schur_raw": cond_raw,
            "cond_schur_scaled": math.nan,
            "cond_schur_equilibrated": math.nan,
        }
        for precision in precisions:
            row[f"error_{precision}"] = ""
            for key in ("max_before", "mean_before", "max_after", "mean_after"):
                row[f"violation_{key}_{precision}"] = math.nan
            try:
                kkt = EquilibratedKKT.factorize(Q, problem.A, EquilibrationSteps(), precision)
                x, _, x_unprojected = kkt.solve(problem.q, problem.b)
            except ValueError as error:  # NotPositiveDefiniteError included
                row[f"error_{precision}"] = str(error)
                continue
            found = diagnose(kkt, Q, problem.A, problem.b, x, x_unprojected, cond_raw)
            row[f"violation_max_before_{precision}"] = found.violation_before_projection
            row[f"violation_mean_before_{precision}"] = found.mean_violation_before_projection
            row[f"violation_max_after_{precision}"] = found.violation_after_projection
            row[f"violation_mean_after_{precision}"] = found.mean_violation_after_projection
            if precision == Precision.FLOAT64:
                row["cond_schur_scaled"] = found.cond_schur_scaled
                row["cond_schur_equilibrated"] = found.cond_schur_equilibrated
        for label, steps in (ablations or {}).items():
            try:
                kkt = EquilibratedKKT.factorize(Q, problem.A, steps, Precision.FLOAT64)
                row[f"cond_schur_{label}"] = condition_number(kkt.schur_factorised())
            except ValueError:
                row[f"cond_schur_{label}"] = math.inf
        rows.append(row)
    return rows
