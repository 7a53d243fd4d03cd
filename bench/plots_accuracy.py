"""Accuracy figures: accuracy profiles and the time-vs-accuracy Pareto plot per family
(definitions and citations in :mod:`bench.accuracy`)."""

from __future__ import annotations

import numpy as np
import pandas as pd
from matplotlib.axes import Axes
from matplotlib.lines import Line2D
from matplotlib.typing import LineStyleType

from c3bench.bench import figure_base as base
from c3bench.bench import store
from c3bench.bench.accuracy import (
    ParetoPoint,
    accuracy_profile,
    pareto_points,
    profile_thresholds,
)
from c3bench.bench.palette import (
    SolverStyle,
    legend_outside,
    palette,
    panel_title,
    solver_handles,
)

TOLERANCE_COLOR = "black"
TOLERANCE_LINE: LineStyleType = ":"
"""How the profile's tolerance is marked in the accuracy figures."""


def _tolerance_handle() -> Line2D:
    return Line2D([], [], color=TOLERANCE_COLOR, linestyle=TOLERANCE_LINE, linewidth=1.0,
                  label="tolerance of the settings profile")


def _accuracy_panel(ax: Axes, panel: base.Panel, styles: dict[str, SolverStyle],
                    family_rows: pd.DataFrame) -> None:
    thresholds = profile_thresholds(panel.rows)
    curves = accuracy_profile(panel.rows, thresholds, instances=panel.instances)
    for index, (solver, curve) in enumerate(sorted(curves.items())):
        style = styles[solver]
        ax.step(thresholds, curve, where="post", color=style.color, linestyle=style.linestyle,
                marker=style.marker, markevery=((7 * index) % 40, 40), markersize=4,
                label=solver)
    ax.axvline(float(panel.rows["tolerance"].max()), color=TOLERANCE_COLOR,
               linestyle=TOLERANCE_LINE, linewidth=1.0)
    ax.set_xscale("log")
    ax.set_ylim(-0.02, 1.02)
    ax.set_xlabel("eps: worst residual / cost error (-)")
    ax.set_ylabel("fraction solved to eps (-)")
    ax.grid(True, alpha=0.3)
    panel_title(ax, panel.label, panel.instances, not_run=base.not_run(panel, family_rows))


def accuracy_profiles(frame: pd.DataFrame, paths: store.SuitePaths) -> list[base.Figure]:
    """One figure, one panel per (family, variant, settings profile): for each solver the
    fraction of the panel's instances it solved to each accuracy level; cold, float64."""
    figure = base.Figure(
        "accuracy_profiles", "Accuracy profiles",
        "For each solver, the fraction of the panel's n instances it returned a solution for "
        "(found) whose worst required relative residual (and cost error, where a reference "
        "optimum exists) is at most eps (x: eps, log scale, dimensionless; y: fraction); the "
        "dotted line is the settings profile's tolerance, where the curve is the success "
        "rate; cold start, float64, one panel per family, variant and settings profile.")
    rows = base.baseline(frame)
    if rows.empty or not rows["found"].any():
        figure.note = "no cold-start float64 cell returned a solution"
        return [figure]
    groups = [panel for family in sorted(set(rows["family"]))
              for panel in base.panels(rows[rows["family"] == family])]
    styles = palette(set(rows["solver"]))
    fig, axes = base.new_figure(len(groups), 4.4, 3.9, max_columns=3)
    for ax, panel in zip(axes, groups, strict=True):
        _accuracy_panel(ax, panel, styles, rows[rows["family"] == panel.family])
    legend_outside(fig, [*solver_handles(styles), _tolerance_handle()])
    figure.path = base.save(fig, paths, figure.key)
    return [figure]


def _pareto_panel(ax: Axes, panel: base.Panel, styles: dict[str, SolverStyle],
                  family_rows: pd.DataFrame) -> None:
    points = pareto_points(panel.rows)
    drawn = [p for p in points if np.isfinite(p.residual) and np.isfinite(p.time)]
    for point in drawn:
        style = styles[point.solver]
        ax.scatter(1e3 * point.time, max(point.residual, base.DRAW_FLOOR), color=style.color,
                   marker=style.marker, s=70 if point.on_front else 35,
                   edgecolors="black" if point.on_front else "none", linewidths=1.2,
                   zorder=3)
    front = sorted((p for p in drawn if p.on_front), key=lambda p: p.time)
    if front:
        ax.step([1e3 * p.time for p in front],
                [max(p.residual, base.DRAW_FLOOR) for p in front],
                where="post", color="black", linewidth=0.8, zorder=2)
    ax.axhline(float(panel.rows["tolerance"].max()), color=TOLERANCE_COLOR,
               linestyle=TOLERANCE_LINE, linewidth=1.0)
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel(f"median {base.time_label()} (ms), failures at the time limit")
    ax.set_ylabel("geometric mean of the worst residual (-)")
    ax.grid(True, which="both", alpha=0.3)
    panel_title(ax, panel.label, panel.instances,
                f"instances, {len(drawn)} solvers drawn" + _undrawn(points, drawn),
                not_run=base.not_run(panel, family_rows))


def _undrawn(points: list[ParetoPoint], drawn: list[ParetoPoint]) -> str:
    missing = sorted(p.solver for p in points if p not in drawn)
    return f" (no finite residual: {', '.join(missing)})" if missing else ""


def pareto_plots(frame: pd.DataFrame, paths: store.SuitePaths) -> list[base.Figure]:
    """Per family: each solver one point (median ranked time, geometric-mean worst residual),
    the Pareto front ringed and joined; one panel per (variant, settings profile)."""
    front = Line2D([], [], color="black", marker="o", markerfacecolor="none",
                   linewidth=0.8, label="Pareto front")
    return base.family_figures(frame, paths, base.FamilyFigure(
        "pareto", "Time vs accuracy",
        lambda family: (
            f"{family}: each solver is one point, x = median {base.time_label()} over the "
            "panel's cells with failures charged at the time limit (ms, log scale), y = "
            "geometric mean over its cells of the worst required relative residual (and cost "
            "error where a reference exists; dimensionless, log scale, not floored); ringed "
            "points joined by the black line are the Pareto front (no solver both faster and "
            "more accurate); the dotted line is the tolerance; residuals below "
            f"{base.DRAW_FLOOR:g} drawn at {base.DRAW_FLOOR:g}; cold start, float64."),
        "no cold-start float64 cell of this family has a finite residual",
        lambda rows: bool(np.isfinite(rows["primal_residual_relative"].to_numpy(float)).any()),
        _pareto_panel, lambda rows: (4.6, 4.0),
        lambda styles: [*solver_handles(styles, lines=False), front, _tolerance_handle()]))
