"""``compare(suite, A, B)``: who wins, per family and settings, on success, time and accuracy.

Only the cells both solvers ran are compared (same instance, settings, precision, start).
Per (family, settings, precision, start):

* success: the higher success rate wins;
* time: ``sgm_A / sgm_B`` of the solve times (shifted geometric mean, shift
  :data:`bench.metrics.TIME_SHIFT`), over all common cells with failures charged at the time
  limit (as qpbenchmark does), and over the cells both solved; the winner is decided on the
  cells both solved (on all cells when there are none): below ``1 - TIE`` A wins, above
  ``1 / (1 - TIE)`` B wins, otherwise a tie;
* accuracy: ratio of the geometric means of each cell's worst required residual (the family's
  residuals of :func:`bench.metrics.required_residuals`, and the cost error where a reference
  exists), floored at the tolerance, over the cells where both are finite; same tie rule.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from c3bench.bench import store
from c3bench.bench.metrics import (
    TIME_SHIFT,
    charged_times,
    required_residuals,
    shifted_geometric_mean,
)
from c3bench.bench.report import fmt, markdown_table
from c3bench.problems.errors import InputError

TIE = 0.05
PEERS: tuple[str, ...] = ("family", "settings", "precision", "start")


@dataclass
class Comparison:
    """One line of a comparison."""

    family: str
    settings: str
    precision: str
    start: str
    cells: int
    success_a: float
    success_b: float
    time_ratio: float
    time_ratio_solved: float
    accuracy_ratio: float
    success_winner: str
    time_winner: str
    accuracy_winner: str


def worst_residual(frame: pd.DataFrame) -> np.ndarray:
    """Per row: max of the family's required residuals (and cost error), floored at tol."""
    out = np.full(len(frame), np.nan)
    for i, row in enumerate(frame.to_dict("records")):
        columns = list(required_residuals(row["family"]))
        if row["reference_solver"] and math.isfinite(row["reference_objective"]):
            columns.append("cost_error")
        values = [float(row[c]) for c in columns]
        if all(math.isfinite(v) for v in values):
            out[i] = max(max(values), float(row["tolerance"]))
    return out


def _winner(ratio: float, a: str, b: str) -> str:
    if not math.isfinite(ratio):
        return "-"
    if ratio < 1 - TIE:
        return a
    if ratio > 1 / (1 - TIE):
        return b
    return "tie"


def compare_frame(frame: pd.DataFrame, a: str, b: str) -> list[Comparison]:
    """The comparisons of solvers ``a`` and ``b`` on a results table."""
    for name in (a, b):
        if name not in set(frame["solver"]):
            raise InputError(f"solver {name!r} has no results; stored: "
                             f"{', '.join(sorted(set(frame['solver'])))}")
    key = ["instance", "settings", "precision", "start"]
    left = frame[frame["solver"] == a].set_index(key)
    right = frame[frame["solver"] == b].set_index(key)
    common = left.index.intersection(right.index)
    left, right = left.loc[common].reset_index(), right.loc[common].reset_index()
    out: list[Comparison] = []
    if left.empty:
        return out
    for peers, group_a in left.groupby(list(PEERS), sort=True):
        mask = np.ones(len(right), dtype=bool)
        for column, value in zip(PEERS, peers, strict=True):
            mask &= (right[column] == value).to_numpy()
        group_b = right[mask].set_index("instance").loc[group_a["instance"]].reset_index()
        rate_a, rate_b = float(group_a["success"].mean()), float(group_b["success"].mean())
        time_ratio = (shifted_geometric_mean(charged_times(group_a), TIME_SHIFT)
                      / shifted_geometric_mean(charged_times(group_b), TIME_SHIFT))
        solved = group_a["success"].to_numpy(bool) & group_b["success"].to_numpy(bool)
        time_ratio_solved = (shifted_geometric_mean(group_a["solve_time"].to_numpy(float)[
            solved], TIME_SHIFT) / shifted_geometric_mean(group_b["solve_time"].to_numpy(
                float)[solved], TIME_SHIFT)) if solved.any() else float("nan")
        res_a, res_b = worst_residual(group_a), worst_residual(group_b)
        both = np.isfinite(res_a) & np.isfinite(res_b)
        accuracy_ratio = (shifted_geometric_mean(res_a[both]) / shifted_geometric_mean(
            res_b[both])) if both.any() else float("nan")
        success_winner = a if rate_a > rate_b else b if rate_b > rate_a else "tie"
        decisive = time_ratio_solved if solved.any() else time_ratio
        family, settings, precision, start = (str(p) for p in peers)
        out.append(Comparison(family, settings, precision, start, len(group_a), rate_a, rate_b,
                              time_ratio, time_ratio_solved, accuracy_ratio, success_winner,
                              _winner(decisive, a, b), _winner(accuracy_ratio, a, b)))
    return out


def format_comparison(rows: list[Comparison], a: str, b: str) -> str:
    """Markdown table of :func:`compare_frame`'s output."""
    if not rows:
        return f"{a} and {b} share no cell (no instance both accept with the same settings).\n"
    table = markdown_table(
        ["family", "settings", "precision", "start", "cells", f"success {a}",
         f"success {b}", "winner", f"time {a}/{b}", f"time {a}/{b} (both solved)", "winner",
         f"residual {a}/{b}", "winner"],
        [[r.family, r.settings, r.precision, r.start, str(r.cells),
          fmt(r.success_a, "percent"), fmt(r.success_b, "percent"), r.success_winner,
          fmt(r.time_ratio, "rel"), fmt(r.time_ratio_solved, "rel"), r.time_winner,
          fmt(r.accuracy_ratio, "rel"), r.accuracy_winner] for r in rows], "llllrrrlrrlrl")
    return (f"Comparison of {a} (A) and {b} (B) on the cells both ran. Time: ratio of shifted "
            f"geometric means (shift {TIME_SHIFT:g} s) over all cells with failures at the "
            "time limit, and over the cells both solved (which decides the winner when there "
            "are any); residual: ratio of geometric means of each cell's worst required "
            f"residual floored at the tolerance; ratios within {TIE:.0%} are ties.\n\n"
            + table)


def compare(suite: str, a: str, b: str, results_dir: str | Path = "results") -> str:
    """Compare solvers ``a`` and ``b`` on a stored suite; returns the Markdown text."""
    frame = store.read_results(store.SuitePaths.of(results_dir, suite).root)
    return format_comparison(compare_frame(frame, a, b), a, b)
