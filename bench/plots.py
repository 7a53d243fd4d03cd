"""Figures of the report (matplotlib, Agg backend), each returned with its caption.

Every function takes the results table (and the suite paths where it reads traces) and
returns :class:`Figure` records; a figure without data is not drawn: its record has
``path=None`` and ``note`` says why, and the report prints that note instead.
Figures use cold-start float64 rows unless they are about precision or warm starts, and the
settings profile :func:`preferred_settings` picks when one profile is shown.

Every figure follows the same conventions (:mod:`bench.palette`, :mod:`bench.figure_base`):
one fixed colour and marker per solver, legends beside the panels (never on the data),
``n = ...`` in every panel's title, one panel per ADMM variant where a family has variants
(solvers that take no instance of a panel named "not run" there). The figures live in
:mod:`bench.plots_time` (performance profiles, time distributions),
:mod:`bench.plots_accuracy` (accuracy profiles, time-vs-accuracy Pareto plots) and
:mod:`bench.plots_solver` (convergence traces, cond(S), precision, MIQP gap); this module
orders them; the perf figure is :mod:`bench.plots_perf`'s (re-exported here).
"""

from __future__ import annotations

import matplotlib

matplotlib.use("Agg")
import pandas as pd

from c3bench.bench import store
from c3bench.bench.figure_base import (
    DPI,
    SETTINGS_ORDER,
    Figure,
    keep_figures,
    ordered_settings,
    preferred_settings,
)
from c3bench.bench.plots_accuracy import accuracy_profiles, pareto_plots
from c3bench.bench.plots_perf import plot_perf
from c3bench.bench.plots_solver import (
    MIQP_FAMILIES,
    PRECISION_ORDER,
    conditioning,
    convergence_traces,
    miqp_gap,
    precision_accuracy,
)
from c3bench.bench.plots_time import performance_profiles, time_distributions

__all__ = [
    "DPI", "MIQP_FAMILIES", "PRECISION_ORDER", "SETTINGS_ORDER", "Figure", "accuracy_profiles",
    "all_figures", "conditioning", "convergence_traces", "keep_figures", "miqp_gap",
    "ordered_settings", "pareto_plots", "performance_profiles", "plot_perf",
    "precision_accuracy", "preferred_settings", "time_distributions",
]


def all_figures(frame: pd.DataFrame, paths: store.SuitePaths) -> list[Figure]:
    """Every figure of the report, in report order."""
    figures: list[Figure] = []
    for make in (performance_profiles, time_distributions, accuracy_profiles, pareto_plots,
                 convergence_traces, conditioning, precision_accuracy, miqp_gap):
        figures += make(frame, paths)
    return figures
