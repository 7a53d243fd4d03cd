"""Report sections on accuracy and budgets: the cells whose solver claimed a wrong solution,
and the share of QP cells solved within one ADMM iteration's control budget.

Definitions and citations: :mod:`bench.accuracy` and :mod:`bench.budgets`.
"""

from __future__ import annotations

import math

import pandas as pd

from c3bench.bench.accuracy import claimed_but_wrong
from c3bench.bench.budgets import BUDGET_FAMILIES, DEFAULT_BUDGET_S, BudgetCount, budget_table
from c3bench.bench.metrics import family_label, ranked_time_label, unverified_cells
from c3bench.bench.tables import NOT_RUN, fmt, fraction, markdown_table
from c3bench.problems.config import MPCConfig
from c3bench.problems.names import REFERENCE_ADMM_ITERATIONS


def claimed_wrong_section(frame: pd.DataFrame) -> str:
    """The "claimed success but wrong" table: per family and solver, the cells whose solver
    returned ``found=True`` and whose verdict failed, with the worst example; found=True cells
    that are *unverified* (:func:`bench.metrics.unverified_cells`; found=True by
    :func:`bench.metrics.judge`) are neither successes nor wrong and are counted apart."""
    groups = claimed_but_wrong(frame)
    apart = unverified_note(frame[unverified_cells(frame)], "wrong")
    if not groups:
        return ("No solver claimed a solution that the residual check rejected (every "
                + ("found=True cell succeeded or is unverified). " + apart if apart
                   else "found=True cell succeeded).\n"))
    rows = [[family_label(g.family, g.variant), g.solver, str(g.cells), str(g.claimed),
             fraction(g.wrong, g.claimed),
             fmt(f"{g.instance} ({g.settings}, {g.precision}, {g.start})", "text"),
             g.figure or "-", "unavailable" if math.isnan(g.value) else fmt(g.value, "res"),
             fmt(g.threshold, "sci")] for g in groups]
    return (markdown_table(["family", "solver", "cells", "claimed (found)",
                            "wrong / claimed", "worst example (settings, precision, start)",
                            "worst figure", "value", "threshold"], rows, "llrrrllrr")
            + "\nA cell is *claimed but wrong* when the solver reported a solution "
              "(`found` = True) and the residual check failed (`success` = False). The "
              "example is the wrong cell whose figure is furthest above its threshold "
              "(value / threshold largest; an unavailable figure first): the tolerance, or "
              "max(tolerance, reference spread) for the cost error.\n"
            + (f"\n{apart}" if apart else ""))


def unverified_note(unverified: pd.DataFrame, counted: str) -> str:
    """The sentence counting the *unverified* cells (the rows of ``unverified``) apart, as
    neither successes nor ``counted`` ("failures", "wrong"), per family and solver ('' when
    there are none)."""
    if unverified.empty:
        return ""
    count = len(unverified)
    groups = unverified.groupby(["family", "solver"], sort=True).size()
    where = ", ".join(f"{family} / {solver} ({cells})"
                      for (family, solver), cells in groups.items())
    return (f"{count} found=True cells passed every residual check without a verified "
            f"reference optimum: these {count} *unverified* cells (feasible, optimality not "
            f"verified) are neither successes nor {counted}, and are counted apart: "
            f"{fmt(where, 'text')}.\n")


def _budget_origin(budget_s: float, explicit: bool) -> str:
    if explicit:
        return f"b = {fmt(budget_s, 'ms')} ms (set for this report)"
    dt = MPCConfig().dt
    return (f"b = dt / N = {fmt(dt, 'ms')} ms / {REFERENCE_ADMM_ITERATIONS} = "
            f"{fmt(DEFAULT_BUDGET_S, 'ms')} ms (the reference study's control period and "
            "ADMM iterations; `budget_ms` changes it)")


def _budget_columns(counts: list[BudgetCount]) -> list[tuple[str, str, str, str]]:
    return sorted({(c.variant, c.settings, c.precision, c.start) for c in counts})


def _budget_family_table(counts: list[BudgetCount]) -> str:
    columns = _budget_columns(counts)
    by_key = {(c.solver, c.variant, c.settings, c.precision, c.start): c for c in counts}
    rows = []
    for solver in sorted({c.solver for c in counts}):
        row = [solver]
        for key in columns:
            hit = by_key.get((solver, *key))
            row.append(fraction(hit.within, hit.cells) if hit else NOT_RUN)
        rows.append(row)
    headers = ["solver", *(" / ".join(part for part in key if part) for key in columns)]
    return markdown_table(headers, rows)


def budget_section(frame: pd.DataFrame, budget_s: float, explicit: bool = False) -> str:
    """Per QP family, the cells that succeeded within the control budget ``budget_s``."""
    counts = budget_table(frame, budget_s)
    if not counts:
        return ("No cell of a QP family (" + ", ".join(BUDGET_FAMILIES) + ").\n")
    limit = float(frame["time_limit"].max())
    parts = [f"Inside C3 / C3+ each ADMM iteration solves one QP, so a QP backend has about "
             f"one control period over the ADMM iterations per solve: "
             f"{_budget_origin(budget_s, explicit)}. Each cell: succeeded with "
             f"{ranked_time_label()} <= b, as a share of the cells of the solver (count in "
             f"brackets); a failed cell never counts, whatever its time; *{NOT_RUN}*: the "
             "solver took no instance of that group. The time columns of the tables above "
             f"still charge a failed cell at the time limit ({limit:g} s here), as qpbenchmark "
             "does.\n"]
    for family in BUDGET_FAMILIES:
        mine = [c for c in counts if c.family == family]
        if mine:
            family_limit = float(frame.loc[frame["family"] == family, "time_limit"].max())
            parts.append(f"**{family}** (within b = {fmt(budget_s, 'ms')} ms; time limit "
                         f"{family_limit:g} s)\n\n" + _budget_family_table(mine))
    return "\n".join(parts)
