"""Time figures: Dolan-Moré performance profiles and time distributions per family.

Both read the ranked time (:func:`bench.metrics.ranked_time`) of cold-start float64 cells,
one panel per (variant, settings profile) of a family (:func:`bench.figure_base.panels`).
"""

from __future__ import annotations

import math

import numpy as np
import pandas as pd
from matplotlib.axes import Axes

from c3bench.bench import figure_base as base
from c3bench.bench import store
from c3bench.bench.metrics import performance_profile, performance_ratios, ranked_time
from c3bench.bench.palette import (
    SolverStyle,
    panel_title,
    solver_handles,
)


def _profile_panel(ax: Axes, panel: base.Panel, styles: dict[str, SolverStyle],
                   family_rows: pd.DataFrame) -> None:
    ratios = performance_ratios(panel.rows)
    finite = ratios.to_numpy()[np.isfinite(ratios.to_numpy())]
    top = max(2.0, float(finite.max()) * 1.5) if finite.size else 2.0
    taus = np.logspace(0, math.log10(top), 200)
    for solver, curve in sorted(performance_profile(ratios, taus).items()):
        style = styles[solver]
        ax.step(taus, curve, where="post", color=style.color, linestyle=style.linestyle,
                marker=style.marker, markevery=(styles_offset(solver, styles), 40),
                markersize=4, label=solver)
    ax.set_xscale("log", base=2)
    ax.set_ylim(-0.02, 1.02)
    ax.set_xlabel(f"tau = {base.time_label()} / best (-)")
    ax.set_ylabel("fraction of instances (-)")
    ax.grid(True, alpha=0.3)
    panel_title(ax, panel.label, len(ratios), not_run=base.not_run(panel, family_rows))


def styles_offset(solver: str, styles: dict[str, SolverStyle]) -> int:
    """Marker offset along a curve so that overlapping curves show different markers."""
    return (sorted(styles).index(solver) * 7) % 40


def performance_profiles(frame: pd.DataFrame, paths: store.SuitePaths) -> list[base.Figure]:
    """Dolan-More profiles per family, one panel per (variant, settings profile); cold,
    float64 (E. D. Dolan, J. J. Moré, Math. Programming 91(2):201-213, 2002)."""
    return base.family_figures(frame, paths, base.FamilyFigure(
        "profile", "Performance profile",
        lambda family: (
            f"{family}: fraction of instances a solver solves (success as defined above) "
            f"within a factor tau of the fastest solver's {base.time_label()} (x: tau, log2 "
            "scale, dimensionless; y: fraction of the panel's n instances); cold start, "
            "float64, one panel per variant and settings profile; solvers that take no "
            "instance of a panel are named 'not run' in its title."),
        "no cold-start float64 cell of this family succeeded",
        lambda rows: bool(rows["success"].any()), _profile_panel, lambda rows: (4.6, 3.9),
        solver_handles))


def _box_panel(ax: Axes, panel: base.Panel, styles: dict[str, SolverStyle],
               family_rows: pd.DataFrame) -> None:
    solvers = sorted(set(panel.rows["solver"]))
    positions, data, colors = [], [], []
    labels = []
    for i, solver in enumerate(solvers):
        mine = panel.rows[(panel.rows["solver"] == solver) & panel.rows["success"]]
        times = 1e3 * ranked_time(mine)
        times = times[np.isfinite(times)]
        labels.append(f"{solver} (n={times.size})")
        if times.size:
            positions.append(i)
            data.append(times)
            colors.append(styles[solver].color)
    if data:
        boxes = ax.boxplot(data, positions=positions, patch_artist=True, widths=0.6)
        for patch, color in zip(boxes["boxes"], colors, strict=True):
            patch.set_facecolor(color)
            patch.set_alpha(0.6)
    ax.set_xticks(range(len(solvers)), labels, rotation=60, ha="right", fontsize=7)
    ax.set_yscale("log")
    ax.set_ylabel(f"{base.time_label()} of successful cells (ms)")
    ax.grid(True, axis="y", alpha=0.3)
    panel_title(ax, panel.label, panel.instances, not_run=base.not_run(panel, family_rows))


def time_distributions(frame: pd.DataFrame, paths: store.SuitePaths) -> list[base.Figure]:
    """Box plots of the ranked time of successful cells per solver, one figure per family,
    one panel per (variant, settings profile)."""
    return base.family_figures(frame, paths, base.FamilyFigure(
        "times", "Time distribution",
        lambda family: (
            f"{family}: {base.time_label()} of the successful cold-start float64 cells per "
            f"solver (y: {base.time_label()} in ms, log scale; box: quartiles, whiskers: 1.5 "
            "IQR; n per solver in its label: successful cells of the panel's n instances), "
            "one panel per variant and settings profile."),
        "no successful cold-start float64 cell in this family",
        lambda rows: bool(rows["success"].any()), _box_panel,
        lambda rows: (max(4.5, 0.45 * rows["solver"].nunique() + 1.5), 4.2), None))
