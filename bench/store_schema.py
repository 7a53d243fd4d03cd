"""The results table's schema: its columns (name, dtype, meaning), the identity and sort keys,
and the one schema version of every stored table.

:mod:`bench.store` reads and writes the tables and re-exports these names; the version rules
are in its docstring.
"""

from __future__ import annotations

from dataclasses import dataclass

__all__ = [
    "COLUMNS", "DIAGNOSTIC_COLUMNS", "DTYPES", "KEY_COLUMNS", "PARQUET_METADATA_KEY", "SCHEMA",
    "SCHEMA_VERSION", "SORT_COLUMNS", "Column", "schema_markdown",
]

SCHEMA_VERSION = 2
"""Version 2: ``build_time`` renamed ``setup_time``; ``total_time`` and ``verified`` added."""
PARQUET_METADATA_KEY = b"c3bench_schema"


@dataclass(frozen=True)
class Column:
    """One column of the results table: name, pandas dtype and meaning (README copies it)."""

    name: str
    dtype: str
    meaning: str


# The results schema. dtypes: ``str``; ``int64``; ``Int64`` (nullable integer, empty when
# unknown); ``float64`` (NaN when unknown or not applicable); ``bool``.
SCHEMA: tuple[Column, ...] = (
    Column("schema_version", "int64", "Version of this schema (rows of another are rejected)."),
    Column("cell_id", "str", "File-safe id of the cell: instance--solver--settings--precision"
           "--start."),
    Column("suite", "str", "Suite name (quick, default, full or a custom spec)."),
    Column("instance", "str", "Instance name (unique within the suite)."),
    Column("instance_hash", "str", "Identity of the instance (problems.identity: its "
           "provenance and its arrays rounded to ~1e-9 of each array's largest entry); a "
           "cell of a changed instance is stale and rerun, one regenerated elsewhere with "
           "last-bit noise is not."),
    Column("family", "str", "Subproblem family: c3plus_qp, c3_qp, projection, mpcc, lcp, "
           "lcp_general, qp (imported)."),
    Column("solver", "str", "Registry name of the backend."),
    Column("solver_version", "str", "Version of the backend's package ('-' for our own code)."),
    Column("settings", "str", "Settings profile: default, low_accuracy, mid_accuracy, "
           "high_accuracy."),
    Column("tolerance", "float64", "Tolerance of the profile: solver target and success "
           "threshold."),
    Column("time_limit", "float64", "Wall-clock limit per solve (s; a sequence cell: per "
           "ADMM run, 10 x the per-QP limit); failures count as this in time aggregates."),
    Column("precision", "str", "Floating-point precision the backend ran in: float64 or "
           "float32."),
    Column("start", "str", "cold (fresh solver object), or warm (solver object kept: update "
           "API with the new vectors, started from the reference solution of the previous "
           "ADMM iterate; solvers.timing), or sequence (the 10 QP steps of one ADMM run at "
           "the instance's state, the backend as its QP step; times summed over the steps, "
           "residuals of the worst step; bench.sequence)."),
    Column("repeats", "int64", "Timed repeats after one untimed warm-up; times are medians."),
    Column("state_index", "Int64", "Step of the scripted push the instance was linearised at."),
    Column("admm_iteration", "Int64", "ADMM iteration the instance was captured at (empty for "
           "mpcc, lcp)."),
    Column("rho_lam", "float64", "ADMM weight on lambda at that iteration (NaN when none)."),
    Column("n_variables", "int64", "Number of variables."),
    Column("n_constraints", "int64", "Equality + inequality rows + variables with a finite "
           "bound."),
    Column("found", "bool", "The solver claims a solution (never success on its own)."),
    Column("failure", "str", "Failure category from the registry: '', error, timeout, "
           "invalid_input, non_finite, unsupported, unavailable, infeasible, unbounded."),
    Column("status", "str", "Solver's own status text, or the failure reason."),
    Column("success", "bool", "found, total_time within time_limit, every residual of the "
           "family below tolerance and cost_error below tolerance where a verified reference "
           "exists; projection / mpcc also need that reference (bench.metrics)."),
    Column("verdict", "str", "Why success is False ('' when it is True); 'feasible, "
           "optimality not verified ...' for a projection / mpcc row without a verified "
           "reference optimum (counted apart as unverified)."),
    Column("verified", "bool", "Judged against a verified reference optimum f* (reference "
           "and cross-check passed and agree, bench.reference); projection / mpcc rows "
           "without one are never a success."),
    Column("iterations", "Int64", "Solver iterations (empty when not reported)."),
    Column("setup_time", "float64", "Median seconds of setup: conversion, structure analysis, "
           "factorisation, solver object construction (solvers.timing); in a warm cell the "
           "update call where the solver has an update API."),
    Column("solve_time", "float64", "Median seconds of the solve proper (iterations, back "
           "substitution, reading the solution out)."),
    Column("total_time", "float64", "setup_time + solve_time: what a caller pays per solve; "
           "every ranking reads it (bench.metrics.RANKED_TIME_COLUMN)."),
    Column("objective", "float64", "1/2 x^T P x + q^T x + offset at the returned x."),
    Column("primal_residual", "float64", "max(||Ax-b||, ||[Gx-h]+||, bound violation), inf-norm."),
    Column("dual_residual", "float64", "max(||Px + q + A^T y + G^T z + z_box||_inf, largest "
           "wrong-signed z or z_box) (NaN without duals)."),
    Column("duality_gap", "float64", "|x^T P x + q^T x + b^T y + h^T z + bound terms|."),
    Column("primal_residual_relative", "float64", "primal_residual / max(1, size of the data: "
           "||b||, ||h||, finite bounds; never the answer's) (solvers.residuals); judged for "
           "success."),
    Column("dual_residual_relative", "float64", "dual_residual / max(1, ||Px||, ||q||, "
           "||A^T y||, ||G^T z||, ||z_box||); judged for success."),
    Column("duality_gap_relative", "float64", "duality_gap / max(1, largest term of the gap); "
           "judged for success."),
    Column("complementarity_violation", "float64", "max over pairs |min(x_i, x_j)| (0 without "
           "pairs); lcp: ||min(lam, P lam + q)||_inf / max(1, ||P lam||, ||q||)."),
    Column("cost_error", "float64", "|f - f*| / max(1, |f*|) against the reference optimum "
           "(NaN without one)."),
    Column("reference_solver", "str", "Backend that gave f* ('' when no reference)."),
    Column("reference_objective", "float64", "The reference optimum f* (NaN when none)."),
    Column("reference_spread", "float64", "Disagreement of f* with its cross-check, "
           "|f*_ref - f*_check| / max(1, |f*|); cost threshold is max(tolerance, this)."),
    Column("cond_kkt", "float64", "Condition number of the KKT matrix, where the backend "
           "reports it."),
    Column("cond_schur_raw", "float64", "cond(S = A Q^-1 A^T) before equilibration."),
    Column("cond_schur_equilibrated", "float64", "cond(S) after equilibration."),
    Column("violation_before_projection", "float64", "||Ax - b||_inf before the final "
           "projection step."),
    Column("violation_after_projection", "float64", "||Ax - b||_inf after it."),
    Column("trace_file", "str", "Path of the trace JSON relative to the suite directory ('' "
           "when none)."),
    Column("host", "str", "Host name of the worker that ran the cell."),
    Column("finished_at", "str", "UTC time the cell finished (ISO 8601)."),
)

COLUMNS: tuple[str, ...] = tuple(column.name for column in SCHEMA)
DTYPES: dict[str, str] = {column.name: column.dtype for column in SCHEMA}
KEY_COLUMNS: tuple[str, ...] = ("instance", "solver", "settings", "precision", "start")
SORT_COLUMNS: tuple[str, ...] = ("family", "instance", "solver", "settings", "precision",
                                 "start")
DIAGNOSTIC_COLUMNS: tuple[str, ...] = ("cond_kkt", "cond_schur_raw", "cond_schur_equilibrated",
                                       "violation_before_projection",
                                       "violation_after_projection")


def schema_markdown() -> str:
    """The schema as a Markdown table (for the README and the report)."""
    lines = ["| column | type | meaning |", "|---|---|---|"]
    lines += [f"| `{c.name}` | {c.dtype} | {c.meaning} |" for c in SCHEMA]
    return "\n".join(lines) + "\n"
