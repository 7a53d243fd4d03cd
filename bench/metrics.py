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
  complementarity violation is the relative natural residual ``||min(lam, w)|| / max(1,
  ||P lam||, ||q||)`` of ``0 <= lam perp w = P lam + q >= 0``, so success also needs
  ``lam >= -eps`` and ``w >= -eps`` (relatively);
* families whose solution has meaningful duals (:data:`DUAL_FAMILIES`: ``c3plus_qp``,
  ``c3_qp``, ``lcp``): also relative dual residual (stationarity *and* dual signs, see
  :func:`solvers.residuals.dual_residual`) and relative duality gap ``<= eps``; for
  ``projection`` and ``mpcc`` the problem is a mixed-integer (non-convex) program without a
  dual certificate, so duals are neither required nor checked;
* where a reference optimum ``f*`` exists: ``|f - f*| / max(1, |f*|) <= max(eps, s)`` with
  ``s`` the disagreement between the reference and its cross-check (the reference's own
  uncertainty; see :mod:`bench.reference`).

Aggregates (per family, settings, precision, start, solver)
-----------------------------------------------------------
Shifted geometric mean of values ``v_1..v_n`` with shift ``s``:

    sgm(v) = exp( (1/n) sum_i log(v_i + s) ) - s.

* solve time: ``s = TIME_SHIFT = 1e-4`` s (0.1 ms: the solves are sub-millisecond), a failed
  cell counted at its time limit (as qpbenchmark does), normalised by the best solver of the
  same (family, settings, precision, start) so the best has 1.0;
* relative residuals and cost error: floored at the tolerance (``max(v, eps)``: below tolerance is
  "solved", finer differences are noise), over the cells where they are finite, no shift;
  normalised by the best solver likewise;
* iterations, time per iteration (``solve_time / iterations``): medians over successful cells;
* condition numbers (raw and equilibrated Schur complement, KKT): medians.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import numpy as np
import pandas as pd

from c3bench.problems.names import COMPLEMENTARITY_FAMILIES, QP_FAMILIES, Family

TIME_SHIFT = 1e-4
DUAL_FAMILIES: tuple[Family, ...] = QP_FAMILIES
"""Families whose solutions carry meaningful duals (convex QPs and the LCP)."""
NO_DUAL_FAMILIES: tuple[Family, ...] = COMPLEMENTARITY_FAMILIES
"""Mixed-integer families: no dual certificate, duals neither required nor checked."""
GROUP_COLUMNS: tuple[str, ...] = ("family", "settings", "precision", "start", "solver")
PEER_COLUMNS: tuple[str, ...] = ("family", "settings", "precision", "start")


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


def judge(row: Mapping[str, Any]) -> tuple[bool, str]:
    """``(success, verdict)`` of one row; ``verdict`` says why it failed (``""`` on success)."""
    if not bool(row["found"]):
        why = row.get("failure") or "not found"
        status = str(row.get("status", "")).strip().splitlines()
        return False, f"{why}: {status[0] if status else ''}".strip().rstrip(":")
    tolerance = _number(row["tolerance"])
    reasons = []
    for column in required_residuals(str(row["family"])):
        value = _number(row.get(column))
        if math.isnan(value):
            reasons.append(f"{column} unavailable")
        elif not value <= tolerance:
            reasons.append(f"{column} {value:.2e} > {tolerance:.0e}")
    if row.get("reference_solver") and math.isfinite(_number(row.get("reference_objective"))):
        error = _number(row.get("cost_error"))
        spread = _number(row.get("reference_spread"))
        threshold = max(tolerance, spread) if math.isfinite(spread) else tolerance
        if math.isnan(error):
            reasons.append("cost_error unavailable")
        elif not error <= threshold:
            reasons.append(f"cost_error {error:.2e} > {threshold:.1e}")
    return not reasons, "; ".join(reasons)


def success_series(frame: pd.DataFrame) -> pd.Series:
    """:func:`judge` recomputed for every row of a results table."""
    if frame.empty:
        return pd.Series([], dtype=bool)
    return frame.apply(lambda row: judge(row)[0], axis=1).astype(bool)


def shifted_geometric_mean(values: Any, shift: float = 0.0) -> float:
    """``exp(mean(log(v + shift))) - shift`` (NaN for no values)."""
    array = np.asarray(values, dtype=float)
    if array.size == 0:
        return float("nan")
    return float(np.exp(np.mean(np.log(array + shift))) - shift)


def charged_times(frame: pd.DataFrame) -> np.ndarray:
    """Solve times with failures charged at their time limit."""
    times = frame["solve_time"].to_numpy(dtype=float)
    limits = frame["time_limit"].to_numpy(dtype=float)
    ok = frame["success"].to_numpy(dtype=bool) & np.isfinite(times)
    return np.where(ok, times, limits)


def floored_sgm(values: Any, tolerance: Any) -> float:
    """Geometric mean of ``max(v, eps)`` over finite ``v`` (NaN when none is finite)."""
    values = np.asarray(values, dtype=float)
    floor = np.broadcast_to(np.asarray(tolerance, dtype=float), values.shape)
    finite = np.isfinite(values)
    if not finite.any():
        return float("nan")
    return shifted_geometric_mean(np.maximum(values[finite], floor[finite]))


def _median(values: Any) -> float:
    array = np.asarray(values, dtype=float)
    array = array[np.isfinite(array)]
    return float(np.median(array)) if array.size else float("nan")


AGGREGATE_COLUMNS: tuple[str, ...] = (
    *GROUP_COLUMNS, "cells", "successes", "success_rate", "time_sgm", "time_rel", "build_sgm",
    "primal_sgm", "primal_rel", "dual_sgm", "dual_rel", "gap_sgm", "gap_rel",
    "complementarity_sgm", "cost_error_sgm", "cost_error_rel", "iterations_median",
    "time_per_iteration", "cond_kkt_median", "cond_schur_raw_median",
    "cond_schur_equilibrated_median",
)


def aggregate(frame: pd.DataFrame) -> pd.DataFrame:
    """One row per (family, settings, precision, start, solver) with the aggregates above.

    Rows sorted by the group columns; ``*_rel`` columns divide by the smallest value among
    the solvers of the same (family, settings, precision, start).
    """
    records = []
    for key, group in frame.groupby(list(GROUP_COLUMNS), sort=True):
        tolerance = group["tolerance"].to_numpy(dtype=float)
        success = group["success"].to_numpy(dtype=bool)
        winners = group[success]
        iterations = winners["iterations"].astype("float64").to_numpy()
        per_iteration = winners["solve_time"].to_numpy(dtype=float) / np.where(
            iterations > 0, iterations, np.nan)
        records.append({
            **dict(zip(GROUP_COLUMNS, key, strict=True)),
            "cells": len(group),
            "successes": int(success.sum()),
            "success_rate": float(success.mean()),
            "time_sgm": shifted_geometric_mean(charged_times(group), TIME_SHIFT),
            "build_sgm": shifted_geometric_mean(
                np.nan_to_num(group["build_time"].to_numpy(dtype=float)), TIME_SHIFT),
            "primal_sgm": floored_sgm(group["primal_residual_relative"], tolerance),
            "dual_sgm": floored_sgm(group["dual_residual_relative"], tolerance),
            "gap_sgm": floored_sgm(group["duality_gap_relative"], tolerance),
            "complementarity_sgm": floored_sgm(group["complementarity_violation"], tolerance),
            "cost_error_sgm": floored_sgm(group["cost_error"], tolerance),
            "iterations_median": _median(iterations),
            "time_per_iteration": _median(per_iteration),
            "cond_kkt_median": _median(group["cond_kkt"]),
            "cond_schur_raw_median": _median(group["cond_schur_raw"]),
            "cond_schur_equilibrated_median": _median(group["cond_schur_equilibrated"]),
        })
    table = pd.DataFrame(records, columns=[c for c in AGGREGATE_COLUMNS if not c.endswith(
        "_rel")])
    for name in ("time", "primal", "dual", "gap", "cost_error"):
        best = table.groupby(list(PEER_COLUMNS))[f"{name}_sgm"].transform("min") \
            if len(table) else table[f"{name}_sgm"]
        table[f"{name}_rel"] = table[f"{name}_sgm"] / best
    return table[list(AGGREGATE_COLUMNS)].reset_index(drop=True)


def performance_ratios(frame: pd.DataFrame) -> pd.DataFrame:
    """Dolan-More ratios ``r_{p,s} = t_{p,s} / min_s t_{p,s}`` (one peer group).

    ``frame`` holds the rows of one (family, settings, precision, start); ``t`` is the solve
    time of a successful cell and ``inf`` otherwise. Returns instances x solvers; a problem
    no solver solved gets ``inf`` for all.
    """
    times = frame.assign(t=np.where(frame["success"].to_numpy(dtype=bool),
                                    frame["solve_time"].to_numpy(dtype=float), np.inf))
    table = times.pivot_table(index="instance", columns="solver", values="t", aggfunc="min")
    table = table.fillna(np.inf)
    best = table.min(axis=1).replace(0.0, np.finfo(float).tiny)
    return table.div(best, axis=0)


def performance_profile(ratios: pd.DataFrame, taus: np.ndarray) -> dict[str, np.ndarray]:
    """``rho_s(tau) = |{p : r_{p,s} <= tau}| / |P|`` for each solver (column)."""
    count = max(len(ratios), 1)
    return {solver: np.array([(ratios[solver] <= tau).sum() / count for tau in taus])
            for solver in ratios.columns}
