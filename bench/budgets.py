"""Budgets that fit the application: the share of cells solved within one ADMM iteration.

A C3 / C3+ controller runs ``N`` ADMM iterations per control period ``dt``, and each iteration
solves one QP, so a QP backend has about

    budget = dt / N        (default 0.05 s / 10 = 5 ms, the reference study's controller)

per solve. For each QP family (:data:`BUDGET_FAMILIES`) and each (variant, settings,
precision, start, solver), :func:`budget_table` counts the cells that *succeeded* with a
ranked time (:func:`bench.metrics.ranked_time`) at most the budget. A failed cell is never
within the budget, whatever its time; the time columns of the report keep charging failures
at the time limit, as qpbenchmark does (S. Caron et al., qpbenchmark,
https://github.com/qpsolvers/qpbenchmark).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd

from c3bench.bench.metrics import PEER_COLUMNS, ranked_time, with_variants
from c3bench.problems.config import MPCConfig
from c3bench.problems.errors import InputError
from c3bench.problems.names import QP_FAMILIES, REFERENCE_ADMM_ITERATIONS, Family

BUDGET_FAMILIES: tuple[str, ...] = tuple(dict.fromkeys(
    (Family.C3PLUS_QP, Family.C3_QP, *QP_FAMILIES)))
"""The QP families whose cells are held to the control budget."""
DEFAULT_BUDGET_S = MPCConfig().dt / REFERENCE_ADMM_ITERATIONS
"""Control period over ADMM iterations of the reference study: 0.05 s / 10 = 5 ms."""


def budget_seconds(budget_ms: float | None) -> float:
    """The budget in seconds: ``budget_ms / 1000``, or :data:`DEFAULT_BUDGET_S` for ``None``.

    Raises :class:`~c3bench.problems.errors.InputError` (a ``ValueError``) for a budget that
    is not a positive finite number.
    """
    if budget_ms is None:
        return DEFAULT_BUDGET_S
    value = float(budget_ms)
    if not np.isfinite(value) or value <= 0:
        raise InputError(f"the budget must be a positive number of ms, got {budget_ms!r}")
    return value / 1e3


@dataclass(frozen=True)
class BudgetCount:
    """Cells of one (family, variant, settings, precision, start, solver) and how many
    succeeded within the budget."""

    family: str
    variant: str
    settings: str
    precision: str
    start: str
    solver: str
    cells: int
    within: int

    @property
    def fraction(self) -> float:
        """``within / cells`` (NaN for no cells)."""
        return self.within / self.cells if self.cells else float("nan")


def within_budget(frame: pd.DataFrame, budget_s: float) -> np.ndarray:
    """Per row: succeeded and ranked time ``<= budget_s``."""
    times = ranked_time(frame)
    return frame["success"].to_numpy(dtype=bool) & np.isfinite(times) & (times <= budget_s)


def budget_table(frame: pd.DataFrame, budget_s: float) -> list[BudgetCount]:
    """One :class:`BudgetCount` per group of the :data:`BUDGET_FAMILIES` rows, sorted."""
    rows = with_variants(frame[frame["family"].isin(BUDGET_FAMILIES)])
    rows = rows.assign(_within=within_budget(rows, budget_s))
    out = []
    for key, group in rows.groupby([*PEER_COLUMNS, "solver"], sort=True):
        family, variant, settings, precision, start, solver = (str(k) for k in key)
        out.append(BudgetCount(family, variant, settings, precision, start, solver,
                               len(group), int(group["_within"].sum())))
    return out
