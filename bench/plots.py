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
orders them and draws the perf figure.
"""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
import pandas as pd

from c3bench.bench import perf_store, store
from c3bench.bench.figure_base import (
    DPI,
    SETTINGS_ORDER,
    Figure,
    keep_figures,
    ordered_settings,
    preferred_settings,
)
from c3bench.bench.perf import REFERENCE_STEP_MS, TARGET_STEP_MS, summarize
from c3bench.bench.plots_accuracy import accuracy_profiles, pareto_plots
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


# --- perf: control-step time ------------------------------------------------------------------
def plot_perf(frame: pd.DataFrame, path: Path) -> Path | None:
    """Log-log median control-step time vs samples (p95 as error bars); ``None`` when empty.

    ``frame`` holds the rows of ``c3bench perf`` (:data:`bench.perf_store.PERF_SCHEMA`), of one
    or more runs: the latest run of each machine is drawn (the machine named in the legend
    when there are several). The reference study's step time and the target are drawn as
    horizontal lines.
    """
    frame = perf_store.latest_perf_runs(frame)
    hosts = list(dict.fromkeys(frame["host"].astype(str)))
    summaries = []
    for host in hosts:
        summary = summarize(frame[frame["host"].astype(str) == host])
        summaries.append(summary[summary["repeats"] > 0].assign(host=host))
    summary = pd.concat(summaries, ignore_index=True) if summaries else pd.DataFrame()
    if summary.empty:
        return None
    figure, axes = plt.subplots(figsize=(7.0, 4.6))
    for (host, backend, precision, device), group in summary.groupby(
            ["host", "backend", "precision", "device"], sort=False):
        group = group.sort_values("samples")
        medians = group["median_ms"].to_numpy(dtype=float)
        upper = group["p95_ms"].to_numpy(dtype=float) - medians
        machine = f", {str(host).split(' (')[0]}" if len(hosts) > 1 else ""
        axes.errorbar(group["samples"], medians, yerr=[np.zeros_like(upper), upper],
                      marker="o", capsize=3, label=f"{backend} ({precision}, {device}{machine})")
    axes.axhline(REFERENCE_STEP_MS, color="grey", linestyle="--", linewidth=1,
                 label=f"seed: {REFERENCE_STEP_MS:g} ms (16 samples)")
    axes.axhline(TARGET_STEP_MS, color="grey", linestyle=":", linewidth=1,
                 label=f"target: {TARGET_STEP_MS:g} ms (16 samples)")
    axes.set_xscale("log", base=2)
    axes.set_yscale("log")
    ticks = sorted(int(n) for n in summary["samples"].unique())
    axes.set_xticks(ticks, [str(n) for n in ticks])
    axes.minorticks_off()
    axes.set_xlabel("model samples n (cube sides l ~ U[0.27, 0.33])")
    axes.set_ylabel("control-step time [ms] (median; bar to p95)")
    horizon = int(frame["horizon"].iloc[0]) if len(frame) else 0
    iterations = int(frame["iterations"].iloc[0]) if len(frame) else 0
    axes.set_title(f"C3+ control step: LCS build + {iterations} ADMM iterations, T = {horizon},"
                   " one core", fontsize=10)
    axes.grid(True, which="both", alpha=0.3)
    axes.legend(fontsize=7, loc="upper left")
    figure.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(path, dpi=120)
    plt.close(figure)
    return path
