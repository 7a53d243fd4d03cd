"""``compare(suite, A, B)``: who wins, per family and settings, on success, time and accuracy.

Only the cells both solvers ran are compared (same instance, settings, precision, start; the
instance fixes the variant). Per (family, variant, settings, precision, start):

* success: the higher success rate wins;
* time: ``sgm_A / sgm_B`` of the ranked times (:func:`bench.metrics.ranked_time`; shifted
  geometric mean, shift :data:`bench.metrics.TIME_SHIFT`), over all common cells with
  failures charged at the time limit (as qpbenchmark does), and over the cells both solved;
  the winner is decided on the cells both solved (on all cells when there are none): below
  ``1 - TIE`` A wins, above ``1 / (1 - TIE)`` B wins, otherwise a tie;
* accuracy: on the cells **both solved**, ``w`` is each cell's worst required figure
  (:func:`bench.metrics.worst_residual`, the actual value, never floored at the tolerance);
  the ratio ``gm(w_A) / gm(w_B)`` of the geometric means (:func:`bench.metrics.geometric_mean`)
  decides with the same tie rule (below 1: A is more accurate), and the cells are counted:
  A wins a cell when ``w_A < w_B / CELL_FACTOR``, B when ``w_B < w_A / CELL_FACTOR``,
  otherwise the cell is a tie. When no cell was solved by both, the cells where both ``w``
  are finite are used instead and the basis column says so.
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
    family_label,
    geometric_mean,
    ranked_time,
    ranked_time_label,
    shifted_geometric_mean,
    unverified_cells,
    with_variants,
    worst_residual,
)
from c3bench.bench.tables import fmt, markdown_table
from c3bench.problems.errors import InputError

TIE = 0.05
CELL_FACTOR = 2.0
"""A cell's accuracy is decided only when the worst figures differ by more than this factor."""
PEERS: tuple[str, ...] = ("family", "variant", "settings", "precision", "start")
BOTH_SOLVED = "both solved"
BOTH_FINITE = "both finite"


@dataclass
class Comparison:
    """One line of a comparison."""

    family: str
    variant: str
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
    accuracy_basis: str = ""
    accuracy_cells: int = 0
    accuracy_wins_a: int = 0
    accuracy_wins_b: int = 0
    unverified_a: int = 0
    unverified_b: int = 0


@dataclass(frozen=True)
class AccuracyDuel:
    """Accuracy of A against B on a set of cells (see the module doc)."""

    basis: str
    cells: int
    ratio: float
    wins_a: int
    wins_b: int


def _winner(ratio: float, a: str, b: str) -> str:
    if not math.isfinite(ratio):
        return "-"
    if ratio < 1 - TIE:
        return a
    if ratio > 1 / (1 - TIE):
        return b
    return "tie"


def accuracy_duel(group_a: pd.DataFrame, group_b: pd.DataFrame) -> AccuracyDuel:
    """:class:`AccuracyDuel` of two row-aligned groups (same cells, same order)."""
    res_a, res_b = worst_residual(group_a), worst_residual(group_b)
    finite = np.isfinite(res_a) & np.isfinite(res_b)
    solved = finite & group_a["success"].to_numpy(bool) & group_b["success"].to_numpy(bool)
    basis, mask = (BOTH_SOLVED, solved) if solved.any() else (BOTH_FINITE, finite)
    if not mask.any():
        return AccuracyDuel("", 0, float("nan"), 0, 0)
    a, b = res_a[mask], res_b[mask]
    return AccuracyDuel(basis, int(mask.sum()), geometric_mean(a) / geometric_mean(b),
                        int((a < b / CELL_FACTOR).sum()), int((b < a / CELL_FACTOR).sum()))


def _time_ratios(group_a: pd.DataFrame, group_b: pd.DataFrame) -> tuple[float, float, bool]:
    """(all cells, cells both solved, whether any cell was solved by both)."""
    everything = (shifted_geometric_mean(charged_times(group_a), TIME_SHIFT)
                  / shifted_geometric_mean(charged_times(group_b), TIME_SHIFT))
    solved = group_a["success"].to_numpy(bool) & group_b["success"].to_numpy(bool)
    if not solved.any():
        return everything, float("nan"), False
    both = (shifted_geometric_mean(ranked_time(group_a)[solved], TIME_SHIFT)
            / shifted_geometric_mean(ranked_time(group_b)[solved], TIME_SHIFT))
    return everything, both, True


def _compare_group(peers: tuple[str, ...], group_a: pd.DataFrame, group_b: pd.DataFrame,
                   a: str, b: str) -> Comparison:
    rate_a, rate_b = float(group_a["success"].mean()), float(group_b["success"].mean())
    time_ratio, time_ratio_solved, any_solved = _time_ratios(group_a, group_b)
    duel = accuracy_duel(group_a, group_b)
    family, variant, settings, precision, start = (str(p) for p in peers)
    return Comparison(
        family, variant, settings, precision, start, len(group_a), rate_a, rate_b,
        time_ratio, time_ratio_solved, duel.ratio,
        a if rate_a > rate_b else b if rate_b > rate_a else "tie",
        _winner(time_ratio_solved if any_solved else time_ratio, a, b),
        _winner(duel.ratio, a, b), duel.basis, duel.cells, duel.wins_a, duel.wins_b,
        _unverified(group_a), _unverified(group_b))


def _unverified(group: pd.DataFrame) -> int:
    """Cells of ``group`` that are feasible but without a verified optimum
    (:func:`bench.metrics.unverified_cells`)."""
    return int(unverified_cells(group).sum())


def compare_frame(frame: pd.DataFrame, a: str, b: str) -> list[Comparison]:
    """The comparisons of solvers ``a`` and ``b`` on a results table."""
    for name in (a, b):
        if name not in set(frame["solver"]):
            raise InputError(f"solver {name!r} has no results; stored: "
                             f"{', '.join(sorted(set(frame['solver'])))}")
    frame = with_variants(frame)
    key = ["instance", "settings", "precision", "start"]
    left = frame[frame["solver"] == a].set_index(key)
    right = frame[frame["solver"] == b].set_index(key)
    common = left.index.intersection(right.index).sort_values()
    left, right = left.loc[common].reset_index(), right.loc[common].reset_index()
    out: list[Comparison] = []
    for peers, group_a in left.groupby(list(PEERS), sort=True):
        group_b = right.loc[group_a.index]  # same cells, same order (aligned on common)
        out.append(_compare_group(tuple(str(p) for p in peers), group_a, group_b, a, b))
    return out


def format_comparison(rows: list[Comparison], a: str, b: str) -> str:
    """Markdown table of :func:`compare_frame`'s output."""
    if not rows:
        return f"{a} and {b} share no cell (no instance both accept with the same settings).\n"
    table = markdown_table(
        ["family", "settings", "precision", "start", "cells", f"success {a}",
         f"success {b}", f"unverified {a} / {b}", "winner", f"time {a}/{b}",
         f"time {a}/{b} (both solved)", "winner",
         f"accuracy {a}/{b}", "basis (cells)", f"cells {a} / {b} more accurate", "winner"],
        [[family_label(r.family, r.variant), r.settings, r.precision, r.start, str(r.cells),
          fmt(r.success_a, "percent"), fmt(r.success_b, "percent"),
          f"{r.unverified_a} / {r.unverified_b}", r.success_winner,
          fmt(r.time_ratio, "rel"), fmt(r.time_ratio_solved, "rel"), r.time_winner,
          fmt(r.accuracy_ratio, "sci"),
          f"{r.accuracy_basis} ({r.accuracy_cells})" if r.accuracy_basis else "-",
          f"{r.accuracy_wins_a} / {r.accuracy_wins_b}", r.accuracy_winner] for r in rows],
        "llllrrrrlrrlrlrl")
    return (f"Comparison of {a} (A) and {b} (B) on the cells both ran. Time: ratio of shifted "
            f"geometric means of the {ranked_time_label()} (shift {TIME_SHIFT:g} s) over all "
            "cells with failures at the time limit, and over the cells both solved (which "
            "decides the winner when there are any). Accuracy: ratio of the geometric means "
            "of each cell's worst required residual (and cost error where a reference "
            "exists), actual values without a floor, on the cells both solved (else on the "
            "cells where both are finite, as the basis says); below 1 A is more accurate; "
            "*unverified*: feasible projection / mpcc cells without a verified reference "
            "optimum (not successes); "
            f"a cell counts for the solver whose figure is smaller by more than a factor "
            f"{CELL_FACTOR:g}. Ratios within {TIE:.0%} of 1 are ties.\n\n" + table)


def compare(suite: str, a: str, b: str, results_dir: str | Path = "results") -> str:
    """Compare solvers ``a`` and ``b`` on a stored suite; returns the Markdown text."""
    frame = store.read_results(store.SuitePaths.of(results_dir, suite).root)
    return format_comparison(compare_frame(frame, a, b), a, b)
