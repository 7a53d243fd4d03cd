"""Accuracy you can see: accuracy profiles, the time-accuracy Pareto front and the cells
whose solver claimed a solution that the residual check rejected.

Accuracy of a cell
------------------
``w`` is the cell's worst accuracy figure (:func:`bench.metrics.worst_residual`: the largest
of the family's required relative residuals and, where a reference optimum exists, the cost
error), the actual value, never floored at the tolerance.

Accuracy profile
----------------
For the instances ``P`` of one panel (family, variant, settings, precision, start) and a
solver ``s``, the fraction solved to accuracy ``eps``

    a_s(eps) = |{ p in P : found_{p,s} and w_{p,s} <= eps }| / |P|,

the accuracy analogue of a Dolan-Moré performance profile (E. D. Dolan, J. J. Moré,
"Benchmarking optimization software with performance profiles", Mathematical Programming
91(2):201-213, 2002; data profiles over an accuracy level as in J. J. Moré, S. M. Wild,
"Benchmarking derivative-free optimization algorithms", SIAM J. Optim. 20(1):172-191, 2009).
A cell the solver did not claim (``found`` False) or without a finite ``w`` is solved at no
level. At ``eps`` equal to the profile's tolerance ``a_s`` is the success rate up to the
reference spread allowance of :func:`bench.metrics.judge`.

Pareto front
------------
Each solver of a panel is one point ``(t_s, r_s)``: ``t_s`` the median ranked time
(:func:`bench.metrics.ranked_time`) with failed cells charged at the time limit (as
qpbenchmark does), ``r_s`` the geometric mean of ``w`` over its cells with a finite ``w``. A
point is on the front when no other point is at least as good in both and better in one
(``t_q <= t_s``, ``r_q <= r_s``, one strictly): the non-dominated set of multi-objective
optimisation (K. Miettinen, *Nonlinear Multiobjective Optimization*, Kluwer 1999, ch. 2).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pandas as pd

from c3bench.bench.metrics import (
    accuracy_columns,
    charged_times,
    geometric_mean,
    has_reference,
    unverified_cells,
    with_variants,
    worst_residual,
)


def solved_accuracy(frame: pd.DataFrame) -> np.ndarray:
    """Per row, ``w`` where the solver claimed a solution and ``w`` is finite, else ``inf``."""
    worst = worst_residual(frame)
    found = frame["found"].to_numpy(dtype=bool)
    return np.where(found & np.isfinite(worst), worst, np.inf)


def accuracy_profile(frame: pd.DataFrame, thresholds: np.ndarray,
                     instances: int | None = None) -> dict[str, np.ndarray]:
    """``a_s(eps)`` for every solver of ``frame`` (one panel) at each threshold.

    ``instances`` is ``|P|``, default the number of distinct instances in ``frame``; a solver
    gets the fraction of ``|P|`` it solved to each level (its best cell per instance).
    """
    count = instances if instances is not None else frame["instance"].nunique()
    count = max(count, 1)
    levels = frame.assign(_w=solved_accuracy(frame))
    best = levels.groupby(["solver", "instance"])["_w"].min()
    out = {}
    for solver in sorted(set(frame["solver"])):
        values = best.loc[solver].to_numpy(dtype=float)
        out[solver] = np.array([(values <= eps).sum() / count for eps in thresholds])
    return out


def profile_thresholds(frame: pd.DataFrame, points: int = 200) -> np.ndarray:
    """Log-spaced thresholds spanning the panel's finite accuracies (and its tolerance)."""
    values = solved_accuracy(frame)
    values = values[np.isfinite(values) & (values > 0)]
    tolerance = float(frame["tolerance"].max()) if len(frame) else 1e-3
    low = min(float(values.min()), tolerance) if values.size else tolerance
    high = max(float(values.max()), tolerance) if values.size else tolerance
    low, high = max(low, 1e-300), max(high, low)
    return np.logspace(math.log10(low) - 0.5, math.log10(high) + 0.5, points)


@dataclass(frozen=True)
class ParetoPoint:
    """One solver of a Pareto panel.

    Attributes
    ----------
    solver
        Backend name.
    time
        Median ranked time in seconds, failures charged at the time limit.
    residual
        Geometric mean of the cells' worst accuracy figure (NaN when none is finite).
    cells
        Cells behind the point.
    on_front
        Whether no other point dominates it.
    """

    solver: str
    time: float
    residual: float
    cells: int
    on_front: bool = False


def dominates(a: tuple[float, float], b: tuple[float, float]) -> bool:
    """``a`` is at least as good as ``b`` in both coordinates and better in one."""
    return a[0] <= b[0] and a[1] <= b[1] and (a[0] < b[0] or a[1] < b[1])


def pareto_front(points: list[tuple[float, float]]) -> list[bool]:
    """For each (time, residual) point, whether it is non-dominated (NaN points never are)."""
    finite = [math.isfinite(p[0]) and math.isfinite(p[1]) for p in points]
    return [ok and not any(other_ok and dominates(other, point)
                           for other, other_ok in zip(points, finite, strict=True))
            for point, ok in zip(points, finite, strict=True)]


def pareto_points(frame: pd.DataFrame) -> list[ParetoPoint]:
    """One :class:`ParetoPoint` per solver of ``frame`` (one panel), sorted by name."""
    raw = []
    for solver, group in frame.groupby("solver", sort=True):
        raw.append((str(solver), float(np.median(charged_times(group))),
                    geometric_mean(worst_residual(group)), len(group)))
    front = pareto_front([(t, r) for _, t, r, _ in raw])
    return [ParetoPoint(s, t, r, n, f) for (s, t, r, n), f in zip(raw, front, strict=True)]


@dataclass(frozen=True)
class ClaimedWrong:
    """Cells of one (family, variant, solver) whose solver said found but failed the check.

    Attributes
    ----------
    family, variant, solver
        The group.
    cells
        Cells of the group.
    claimed
        Cells with ``found`` True.
    wrong
        Of those, cells whose verdict failed.
    instance, settings, precision, start
        The example: the wrong cell with the largest ``figure / threshold``.
    figure, value, threshold
        The example's worst figure, its value and the tolerance it was judged against.
    verdict
        The example's verdict text.
    """

    family: str
    variant: str
    solver: str
    cells: int
    claimed: int
    wrong: int
    instance: str
    settings: str
    precision: str
    start: str
    figure: str
    value: float
    threshold: float
    verdict: str


def worst_figure(row: dict[str, object]) -> tuple[str, float, float]:
    """``(column, value, threshold)`` of the row's figure furthest above its threshold
    (``value / threshold`` largest; an unavailable figure first, with value NaN)."""
    tolerance = float(row["tolerance"])  # type: ignore[arg-type]
    best: tuple[str, float, float] = ("", math.nan, tolerance)
    score = -math.inf
    for column in accuracy_columns(row):
        value = float(row.get(column, math.nan))  # type: ignore[arg-type]
        threshold = tolerance
        if column == "cost_error" and has_reference(row):
            spread = float(row.get("reference_spread", math.nan))  # type: ignore[arg-type]
            threshold = max(tolerance, spread) if math.isfinite(spread) else tolerance
        ratio = math.inf if math.isnan(value) else value / threshold
        if ratio > score:
            best, score = (column, value, threshold), ratio
    return best


def claimed_but_wrong(frame: pd.DataFrame) -> list[ClaimedWrong]:
    """Per (family, variant, solver) with at least one cell whose solver reported
    ``found=True`` while the verdict failed: counts and the worst example. A feasible cell
    whose optimality is only unverified (:func:`bench.metrics.unverified_cells`) is not wrong."""
    frame = with_variants(frame)
    out = []
    for (family, variant, solver), group in frame.groupby(
            ["family", "variant", "solver"], sort=True):
        found = group["found"].to_numpy(dtype=bool)
        unverified = unverified_cells(group)
        wrong = group[found & ~group["success"].to_numpy(dtype=bool) & ~unverified]
        if wrong.empty:
            continue
        examples = [(worst_figure(row), row) for row in wrong.to_dict("records")]
        (figure, value, threshold), row = max(
            examples, key=lambda item: (math.inf if math.isnan(item[0][1])
                                        else item[0][1] / item[0][2], str(item[1]["instance"])))
        out.append(ClaimedWrong(str(family), str(variant), str(solver), len(group),
                                int(found.sum()), len(wrong), str(row["instance"]),
                                str(row["settings"]), str(row["precision"]), str(row["start"]),
                                figure, value, threshold, str(row["verdict"])))
    return out
