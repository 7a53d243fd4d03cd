"""Success criterion and aggregates of the results table.

Success (never the solver's own word alone)
--------------------------------------------
A cell succeeds when the solver found a solution **and** every residual its family requires is
finite and at most the settings' tolerance ``eps``. Primal and dual residuals and the duality
gap are taken *relative* to the size of their terms, ``r / max(1, scale)`` as defined in
:mod:`solvers.residuals` (our instances have gradients up to 4e5, so an absolute test would
demand 1e-12 relative accuracy; this is OSQP's mixed test with ``eps_abs = eps_rel``):

* every family: relative primal residual ``<= eps`` and complementarity violation
  ``max |min(x_i, x_j)| <= eps`` (0 for families without pairs); for ``lcp`` the
  complementarity violation is the natural residual relative to the data,
  ``||min(lam, w)|| / max(1, ||q||)`` of ``0 <= lam perp w = P lam + q >= 0``, so success also needs
  ``lam >= -eps`` and ``w >= -eps`` (relatively); ``lcp_general`` is judged by the same
  natural residual of ``0 <= lam perp F lam + q >= 0`` (``F`` stored as is) and its primal
  residual (``[-lam]_+``, ``[-w]_+``) only: an LCP has no objective (the family stores 0)
  and the natural residual is its certificate on its own (a point where it is small solves
  the LCP), so neither duals nor a verified reference are needed;
* families whose solution has meaningful duals (:data:`DUAL_FAMILIES`: ``c3plus_qp``,
  ``c3_qp``, ``lcp``): also relative dual residual (stationarity *and* dual signs, see
  :func:`solvers.residuals.dual_residual`) and relative duality gap ``<= eps``; for
  ``projection`` and ``mpcc`` the problem is a mixed-integer (non-convex) program without a
  dual certificate, so duals are neither required nor checked;
* where a verified reference optimum ``f*`` exists (reference and cross-check agree, see
  :mod:`bench.reference`): ``|f - f*| / max(1, |f*|) <= max(eps, s)`` with ``s`` the
  disagreement between the reference and its cross-check (the reference's own uncertainty);
* ``projection`` and ``mpcc`` (:data:`REFERENCE_FAMILIES`, non-convex: residuals say nothing
  about optimality) need that verified ``f*``: a row that passes every residual check but has
  none is **not** a success; its verdict is :data:`UNVERIFIED_VERDICT` and it is counted
  apart (``unverified`` in the aggregates and every table).

The ``verified`` column of a row says whether it was judged against a verified ``f*``
(:func:`has_reference`); for the convex families a row without one is still judged on its
residuals, duals and gap (a certificate of optimality on its own), so only its cost error is
missing.

Ranked time
-----------
Every ranking (time columns, performance profiles, ``compare``, Pareto plots, budgets) reads
the time of a cell through :func:`ranked_time`, i.e. the column :data:`RANKED_TIME_COLUMN`;
changing what the benchmark ranks by is a change of that one constant. It is
``total_time = setup_time + solve_time`` (the timing contract of :mod:`solvers.timing`), and
the column means what a caller pays for the cell's **start mode** (:data:`RANKED_TIME_MEANING`):

* ``cold``: setup + solve of a fresh solver object, what a C3 / C3+ controller pays, since
  its QP matrices change with ``rho`` at every ADMM iteration;
* ``warm``: what a solver pays when only the vectors change: a solver object set up on the
  same matrices (untimed) takes the instance's ``q``, ``b``, ``h`` and bounds through its own
  update API (``setup_time`` = the update) and solves from the previous iterate's answer
  (``solve_time``), so ``total_time`` = update + solve. A backend without an update API pays
  its full setup + solve in warm cells too (``warm_support`` of the backend,
  :func:`c3bench.solvers.timing.warm_support`; ``warm_update`` = 0 in the cell's trace).

Cells of different starts are never ranked against each other (``start`` is a peer column).

Aggregates (per family, variant, settings, precision, start, solver)
--------------------------------------------------------------------
Shifted geometric mean of values ``v_1..v_n`` with shift ``s`` (qpbenchmark's aggregate):

    sgm(v) = exp( (1/n) sum_i log(v_i + s) ) - s.

* time: ``s = TIME_SHIFT = 1e-4`` s (0.1 ms: the solves are sub-millisecond) over the ranked
  times, a failed cell counted at its time limit (as qpbenchmark does), normalised by the best
  solver of the same (family, variant, settings, precision, start) so the best has 1.0;
* relative residuals, complementarity and cost error: plain geometric means of the actual
  values, ``gm(v) = exp(mean(log(max(v, LOG_FLOOR))))`` over the cells where they are finite,
  **not** floored at the tolerance (a solver at 1e-16 and one at 1e-4 differ in the table);
  ``LOG_FLOOR = 1e-300`` only keeps ``log`` finite on exact zeros; normalised by the best
  solver likewise; ``worst_gm`` is the same mean of each cell's worst required figure
  (:func:`worst_residual`);
* iterations, time per iteration (``solve_time / iterations``): medians over successful cells;
* condition numbers (raw and equilibrated Schur complement, KKT): medians.

The *variant* of a cell is the ADMM variant its instance was captured for (``c3`` or
``c3plus``, the second ``-`` field of the instance name, e.g. ``projection-c3-s005-i00-k0``;
empty for families without variants): a backend that takes one variant only (C3+'s
closed-form projection) is compared on that variant's instances only.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import numpy as np
import pandas as pd

from c3bench.problems.names import (
    COMPLEMENTARITY_FAMILIES,
    QP_FAMILIES,
    Family,
    QPVariant,
    Variant,
)

TIME_SHIFT = 1e-4
LOG_FLOOR = 1e-300
"""The only floor of the accuracy means: keeps ``log`` finite on exact zeros."""
RANKED_TIME_COLUMN = "total_time"
"""The results column every ranking reads (:func:`ranked_time`)."""
RANKED_TIME_MEANING: dict[str, str] = {
    "cold": "setup + solve of a fresh solver object",
    "warm": "update + solve: the solver's update API with the new vectors, then the solve "
            "from the previous answer (setup + solve where a solver has no update API)",
}
"""What :data:`RANKED_TIME_COLUMN` measures in each start mode (module docstring)."""
DUAL_FAMILIES: tuple[Family, ...] = QP_FAMILIES
"""Families whose solutions carry meaningful duals (convex QPs and the LCP)."""
NO_DUAL_FAMILIES: tuple[Family, ...] = (*COMPLEMENTARITY_FAMILIES, Family.LCP_GENERAL)
"""Families without a dual certificate (the mixed-integer families, and ``lcp_general``, whose
certificate is the natural residual): duals neither required nor checked."""
REFERENCE_FAMILIES: tuple[Family, ...] = COMPLEMENTARITY_FAMILIES
"""Families whose success needs a verified reference optimum (no certificate otherwise)."""
UNVERIFIED_VERDICT = "feasible, optimality not verified (no verified reference optimum)"
"""Verdict of a row of :data:`REFERENCE_FAMILIES` that passes every residual check but has no
verified ``f*``: not a success, counted apart as *unverified*."""
VARIANT_COLUMN = "variant"
GROUP_COLUMNS: tuple[str, ...] = (
    "family", VARIANT_COLUMN, "settings", "precision", "start", "solver")
PEER_COLUMNS: tuple[str, ...] = GROUP_COLUMNS[:-1]


def ranked_time(frame: pd.DataFrame) -> np.ndarray:
    """The time each row is ranked by (seconds): column :data:`RANKED_TIME_COLUMN`."""
    return frame[RANKED_TIME_COLUMN].to_numpy(dtype=float)


def ranked_time_label(start: str | None = None) -> str:
    """The ranked time's name for labels and captions (``total time``; with a ``start``
    mode, what it measures there, e.g. ``total time (update + solve: ...)``)."""
    label = RANKED_TIME_COLUMN.replace("_", " ")
    if start is None or str(start) not in RANKED_TIME_MEANING:
        return label
    return f"{label} ({RANKED_TIME_MEANING[str(start)]})"


def instance_variant(instance: str) -> str:
    """The instance name's second ``-`` field when it is a variant (``c3`` / ``c3plus`` of a
    projection, ``bounded`` / ``equality`` of a QP step), else ``""``."""
    parts = str(instance).split("-")
    return parts[1] if len(parts) > 2 and parts[1] in (*Variant, *QPVariant) else ""


def with_variants(frame: pd.DataFrame) -> pd.DataFrame:
    """``frame`` with a :data:`VARIANT_COLUMN` (computed from ``instance`` when missing)."""
    if VARIANT_COLUMN in frame.columns:
        return frame
    return frame.assign(**{VARIANT_COLUMN: [instance_variant(i) for i in frame["instance"]]})


def family_label(family: str, variant: str) -> str:
    """``family`` or ``family (variant variant)`` for headings and panels."""
    return f"{family} ({variant} variant)" if variant else str(family)


def required_residuals(family: str) -> tuple[str, ...]:
    """Residual columns that must be below tolerance for ``family`` (see the module doc)."""
    base = ("primal_residual_relative", "complementarity_violation")
    if family in NO_DUAL_FAMILIES:
        return base
    return (*base, "dual_residual_relative", "duality_gap_relative")


def _number(value: Any) -> float:
    try:
        return float(value)
    except (TypeError, ValueError):
        return float("nan")


def has_reference(row: Mapping[str, Any]) -> bool:
    """Whether the row's instance has a reference optimum ``f*`` (cost error is judged)."""
    return bool(row.get("reference_solver")) and math.isfinite(
        _number(row.get("reference_objective")))


def accuracy_columns(row: Mapping[str, Any]) -> tuple[str, ...]:
    """The figures success checks for this row: required residuals, plus ``cost_error``
    where a reference exists."""
    columns = required_residuals(str(row["family"]))
    return (*columns, "cost_error") if has_reference(row) else columns


def unverified_cells(frame: pd.DataFrame) -> np.ndarray:
    """Per row, whether it is *unverified*: its verdict is :data:`UNVERIFIED_VERDICT`
    (feasible, it passed every residual check, but no verified reference optimum exists;
    all False without a ``verdict`` column). Such a row is neither a success nor a failure:
    every table counts it apart."""
    if "verdict" not in frame.columns:
        return np.zeros(len(frame), dtype=bool)
    return (frame["verdict"].astype(str) == UNVERIFIED_VERDICT).to_numpy(dtype=bool)


def judge(row: Mapping[str, Any]) -> tuple[bool, str]:
    """``(success, verdict)`` of one row; ``verdict`` says why it failed (``""`` on success,
    :data:`UNVERIFIED_VERDICT` when only the verified reference is missing)."""
    if not bool(row["found"]):
        why = row.get("failure") or "not found"
        status = str(row.get("status", "")).strip().splitlines()
        return False, f"{why}: {status[0] if status else ''}".strip().rstrip(":")
    tolerance = _number(row["tolerance"])
    reasons = []
    paid, limit = _number(row.get(RANKED_TIME_COLUMN)), _number(row.get("time_limit"))
    if paid > limit:  # a failure is charged the limit: a success never costs more
        reasons.append(f"total_time {paid:.2e} s > time_limit {limit:.1e} s")
    for column in required_residuals(str(row["family"])):
        value = _number(row.get(column))
        if math.isnan(value):
            reasons.append(f"{column} unavailable")
        elif not value <= tolerance:
            reasons.append(f"{column} {value:.2e} > {tolerance:.0e}")
    if has_reference(row):
        error = _number(row.get("cost_error"))
        spread = _number(row.get("reference_spread"))
        threshold = max(tolerance, spread) if math.isfinite(spread) else tolerance
        if math.isnan(error):
            reasons.append("cost_error unavailable")
        elif not error <= threshold:
            reasons.append(f"cost_error {error:.2e} > {threshold:.1e}")
    elif str(row["family"]) in REFERENCE_FAMILIES:
        reasons.append(UNVERIFIED_VERDICT if not reasons else "no verified reference optimum")
    return not reasons, "; ".join(reasons)


def success_series(frame: pd.DataFrame) -> pd.Series:
    """:func:`judge` recomputed for every row of a results table."""
    if frame.empty:
        return pd.Series([], dtype=bool)
    return frame.apply(lambda row: judge(row)[0], axis=1).astype(bool)


def worst_residual(frame: pd.DataFrame) -> np.ndarray:
    """Per row, ``max`` of :func:`accuracy_columns` (actual values, no floor); NaN when one
    of them is not finite."""
    out = np.full(len(frame), np.nan)
    for i, row in enumerate(frame.to_dict("records")):
        values = [_number(row.get(column)) for column in accuracy_columns(row)]
        if all(math.isfinite(v) for v in values):
            out[i] = max(values)
    return out


def shifted_geometric_mean(values: Any, shift: float = 0.0) -> float:
    """``exp(mean(log(v + shift))) - shift`` (NaN for no values)."""
    array = np.asarray(values, dtype=float)
    if array.size == 0:
        return float("nan")
    return float(np.exp(np.mean(np.log(array + shift))) - shift)


def geometric_mean(values: Any) -> float:
    """``exp(mean(log(max(v, LOG_FLOOR))))`` over the finite ``v`` (NaN when none is finite).

    No floor at the tolerance: the accuracy columns show what the solvers returned.
    """
    array = np.asarray(values, dtype=float)
    array = array[np.isfinite(array)]
    if array.size == 0:
        return float("nan")
    return shifted_geometric_mean(np.maximum(array, LOG_FLOOR))


def charged_times(frame: pd.DataFrame) -> np.ndarray:
    """Ranked times with failures charged at their time limit (as qpbenchmark does)."""
    times = ranked_time(frame)
    limits = frame["time_limit"].to_numpy(dtype=float)
    ok = frame["success"].to_numpy(dtype=bool) & np.isfinite(times)
    return np.where(ok, times, limits)


def _median(values: Any) -> float:
    array = np.asarray(values, dtype=float)
    array = array[np.isfinite(array)]
    return float(np.median(array)) if array.size else float("nan")


ACCURACY_MEANS: tuple[tuple[str, str], ...] = (
    ("primal", "primal_residual_relative"), ("dual", "dual_residual_relative"),
    ("gap", "duality_gap_relative"), ("complementarity", "complementarity_violation"),
    ("cost_error", "cost_error"))
"""(prefix, results column) of the geometric-mean accuracy aggregates."""
RELATIVE_TO_BEST: tuple[str, ...] = ("time", "primal", "dual", "gap", "cost_error", "worst")
AGGREGATE_COLUMNS: tuple[str, ...] = (
    *GROUP_COLUMNS, "cells", "successes", "success_rate", "unverified", "tolerance",
    "time_limit",
    "time_sgm", "time_rel", "setup_sgm", "primal_sgm", "primal_rel", "dual_sgm", "dual_rel",
    "gap_sgm", "gap_rel", "complementarity_sgm", "cost_error_sgm", "cost_error_rel",
    "worst_sgm", "worst_rel", "iterations_median", "time_per_iteration", "cond_kkt_median",
    "cond_schur_raw_median", "cond_schur_equilibrated_median",
)


def _group_record(group: pd.DataFrame) -> dict[str, Any]:
    """The aggregates of one group (see the module doc), without the ``*_rel`` columns."""
    success = group["success"].to_numpy(dtype=bool)
    winners = group[success]
    iterations = winners["iterations"].astype("float64").to_numpy()
    per_iteration = winners["solve_time"].to_numpy(dtype=float) / np.where(
        iterations > 0, iterations, np.nan)
    record: dict[str, Any] = {
        "cells": len(group),
        "successes": int(success.sum()),
        "success_rate": float(success.mean()),
        "unverified": int(unverified_cells(group).sum()),
        "tolerance": float(group["tolerance"].max()),
        "time_limit": float(group["time_limit"].max()),
        "time_sgm": shifted_geometric_mean(charged_times(group), TIME_SHIFT),
        "setup_sgm": shifted_geometric_mean(
            np.nan_to_num(group["setup_time"].to_numpy(dtype=float)), TIME_SHIFT),
        "worst_sgm": geometric_mean(worst_residual(group)),
        "iterations_median": _median(iterations),
        "time_per_iteration": _median(per_iteration),
        "cond_kkt_median": _median(group["cond_kkt"]),
        "cond_schur_raw_median": _median(group["cond_schur_raw"]),
        "cond_schur_equilibrated_median": _median(group["cond_schur_equilibrated"]),
    }
    for prefix, column in ACCURACY_MEANS:
        record[f"{prefix}_sgm"] = geometric_mean(group[column])
    return record


def aggregate(frame: pd.DataFrame) -> pd.DataFrame:
    """One row per (family, variant, settings, precision, start, solver) with the aggregates
    above.

    Rows sorted by the group columns; ``*_rel`` columns divide by the smallest value among
    the solvers of the same (family, variant, settings, precision, start).
    """
    frame = with_variants(frame)
    records = [{**dict(zip(GROUP_COLUMNS, key, strict=True)), **_group_record(group)}
               for key, group in frame.groupby(list(GROUP_COLUMNS), sort=True)]
    table = pd.DataFrame(records, columns=[c for c in AGGREGATE_COLUMNS if not c.endswith(
        "_rel")])
    for name in RELATIVE_TO_BEST:
        best = table.groupby(list(PEER_COLUMNS))[f"{name}_sgm"].transform("min") \
            if len(table) else table[f"{name}_sgm"]
        table[f"{name}_rel"] = table[f"{name}_sgm"] / best
    return table[list(AGGREGATE_COLUMNS)].reset_index(drop=True)


def performance_ratios(frame: pd.DataFrame) -> pd.DataFrame:
    """Dolan-More ratios ``r_{p,s} = t_{p,s} / min_s t_{p,s}`` (one peer group).

    ``frame`` holds the rows of one (family, variant, settings, precision, start); ``t`` is
    the ranked time (:func:`ranked_time`) of a successful cell and ``inf`` otherwise. Returns
    instances x solvers; a problem no solver solved gets ``inf`` for all. (E. D. Dolan and
    J. J. Moré, Mathematical Programming 91(2):201-213, 2002.)
    """
    times = frame.assign(t=np.where(frame["success"].to_numpy(dtype=bool),
                                    ranked_time(frame), np.inf))
    table = times.pivot_table(index="instance", columns="solver", values="t", aggfunc="min")
    table = table.fillna(np.inf)
    best = table.min(axis=1).replace(0.0, np.finfo(float).tiny)
    return table.div(best, axis=0)


def performance_profile(ratios: pd.DataFrame, taus: np.ndarray) -> dict[str, np.ndarray]:
    """``rho_s(tau) = |{p : r_{p,s} <= tau}| / |P|`` for each solver (column)."""
    count = max(len(ratios), 1)
    return {solver: np.array([(ratios[solver] <= tau).sum() / count for tau in taus])
            for solver in ratios.columns}
