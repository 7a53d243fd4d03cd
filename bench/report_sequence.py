"""The report's "Controller sequence" section: which QP backend makes a C3 / C3+ step fastest.

One table per (family, variant, settings, precision) of the ``sequence`` cells
(:mod:`bench.sequence`: the 10 QP steps of one real ADMM run at a state, the backend as its QP
step), a row per backend, fastest first:

* ``cells``, ``success`` (every QP step found and certified, :func:`bench.metrics.judge`);
* ``total median (ms)``: median over the successful cells of the row's ``total_time``, the
  sum of the steps' setup + solve, what the controller pays for its QP steps at one control
  step;
* ``total sgm (ms)`` and ``rel.``: the shifted geometric mean with failures charged at the
  time limit of one run, and its ratio to the fastest backend of the table
  (:func:`bench.metrics.aggregate`, the same aggregate as every other table);
* ``ADMM median (ms)``: median wall time of the whole run (QP steps, building them,
  projections, dual updates: the trace diagnostic ``admm_time``);
* ``within dt``: successful cells whose ``total_time`` fits one control period
  (:data:`bench.budgets.DEFAULT_BUDGET_S` per QP step, times the steps);
* ``plan error (median)``, ``input error (max, N)``: against the reference run
  (:data:`bench.sequence.REFERENCE_BACKEND` at high accuracy), over the cells with a
  verified reference (``verified``); ``-`` where there is none.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pandas as pd

from c3bench.bench import store
from c3bench.bench.budgets import DEFAULT_BUDGET_S
from c3bench.bench.metrics import aggregate, family_label, with_variants
from c3bench.bench.sequence import REFERENCE_BACKEND, SEQUENCE_STEPS
from c3bench.bench.tables import fmt, fraction, markdown_table
from c3bench.problems.names import Start

HEADERS: tuple[str, ...] = ("solver", "cells", "success", "total median (ms)",
                            "total sgm (ms)", "rel.", "ADMM median (ms)", "within dt",
                            "plan error (median)", "input error (max, N)")
DIAGNOSTICS: tuple[str, ...] = ("admm_time", "plan_error", "input_error")


def sequence_rows(frame: pd.DataFrame) -> pd.DataFrame:
    """The ``sequence`` cells of a results table."""
    rows: pd.DataFrame = frame[frame["start"] == Start.SEQUENCE]
    return rows


def other_rows(frame: pd.DataFrame) -> pd.DataFrame:
    """Every cell but the ``sequence`` ones (the per-QP tables and figures)."""
    rows: pd.DataFrame = frame[frame["start"] != Start.SEQUENCE]
    return rows


def with_diagnostics(frame: pd.DataFrame, paths: store.SuitePaths) -> pd.DataFrame:
    """``frame`` with the columns :data:`DIAGNOSTICS` read from each cell's trace (NaN when
    the trace has none)."""
    values: dict[str, list[float]] = {name: [] for name in DIAGNOSTICS}
    for relative in frame["trace_file"]:
        diagnostics = store.read_trace(paths, str(relative)).get("diagnostics", {})
        for name in DIAGNOSTICS:
            value = diagnostics.get(name)
            values[name].append(math.nan if value is None else float(value))
    return frame.assign(**values)


def _median(values: Any) -> float:
    array = np.asarray(values, dtype=float)
    array = array[np.isfinite(array)]
    return float(np.median(array)) if array.size else math.nan


def _max(values: Any) -> float:
    array = np.asarray(values, dtype=float)
    array = array[np.isfinite(array)]
    return float(np.max(array)) if array.size else math.nan


def _table(cells: pd.DataFrame, summary: pd.DataFrame) -> str:
    """One table: a row per solver of ``summary`` (aggregates), fastest first."""
    budget = DEFAULT_BUDGET_S * SEQUENCE_STEPS
    rows = []
    for record in summary.sort_values(["time_sgm", "solver"]).to_dict("records"):
        mine = cells[cells["solver"] == record["solver"]]
        won = mine[mine["success"].to_numpy(dtype=bool)]
        verified = mine[mine["verified"].to_numpy(dtype=bool)]
        within = int((won["total_time"].to_numpy(dtype=float) <= budget).sum())
        rows.append([fmt(record["solver"], "text"), str(len(mine)),
                     fmt(record["success_rate"], "percent"),
                     fmt(_median(won["total_time"]), "ms"), fmt(record["time_sgm"], "ms"),
                     fmt(record["time_rel"], "rel"), fmt(_median(mine["admm_time"]), "ms"),
                     fraction(within, len(mine)),
                     fmt(_median(verified["plan_error"]), "sci"),
                     fmt(_max(verified["input_error"]), "sci")])
    return markdown_table(list(HEADERS), rows)


def sequence_section(frame: pd.DataFrame, paths: store.SuitePaths) -> str:
    """The section's Markdown (a note when the run had no ``sequence`` cells)."""
    cells = sequence_rows(frame)
    if cells.empty:
        return ("_Not run: `c3bench run --start sequence` (or the default starts of "
                "`c3bench run`) adds the controller-sequence cells._\n")
    absent = store.absent_traces(paths, cells["trace_file"])
    cells = with_diagnostics(with_variants(cells), paths)
    summary = aggregate(cells)
    out = [_method(cells)]
    if absent:
        out.append(f"_ADMM time, plan error and input error come from the cells' trace "
                   f"files, and {absent} of them are not here (traces/ is not committed): "
                   f"rerun the suite to fill those columns._\n")
    keys = ["family", "variant", "settings", "precision"]
    for key, group in summary.groupby(keys, sort=True):
        family, variant, profile, precision = (str(k) for k in key)
        mine = cells
        for column, value in zip(keys, key, strict=True):
            mine = mine[mine[column].astype(str) == str(value)]
        limit = float(mine["time_limit"].max())
        out.append(f"### {family_label(family, variant)} / {profile} / {precision} / "
                   f"sequence\n")
        states = mine["instance"].nunique()
        out.append(f"{states} state{'' if states == 1 else 's'}; time limit {limit:g} s per run "
                   "(failures count at it in the sgm). Fastest first.\n")
        out.append(_table(mine, group))
    return "\n".join(out)


def _method(cells: pd.DataFrame) -> str:
    budget_ms = 1e3 * DEFAULT_BUDGET_S * SEQUENCE_STEPS
    return (
        f"Each cell runs the reference controller's consensus ADMM at one state "
        f"({SEQUENCE_STEPS} iterations, geometric rho schedule rho_lam = rho_eta = 50 * 2^i, "
        "cold start; C3 projects by enumerating contact modes) with the backend as its QP "
        "step, in an isolated process. rho changes P at every iteration, so each QP step is "
        "a fresh solve. **total** = sum over the QP steps of setup + solve (each step's "
        "median over the timed runs): what the controller pays for its QP steps at one "
        "control step; **ADMM** is the whole run's wall time (building the QPs, projections "
        "and dual updates included). **Success**: every QP step found and certified "
        "against its own QP (relative primal, dual with multiplier signs, gap within the "
        "profile's tolerance); the row's residuals are the worst step's. *within dt*: "
        f"successful cells with total at most {budget_ms:g} ms (the control period). "
        f"**plan error** = ||delta - delta_ref||_inf / max(1, ||delta_ref||_inf) of the "
        f"final plan and **input error** = ||u0 - u0_ref||_inf (N) against the same run "
        f"with {REFERENCE_BACKEND} at high accuracy, over the cells whose reference run was "
        f"certified ({int(cells['verified'].sum())} of {len(cells)} cells).\n")
