"""Solver-behaviour figures: convergence traces, cond(S) along ADMM, float32 vs float64, and
the MIQP cost gap of the mixed-integer families."""

from __future__ import annotations

import numpy as np
import pandas as pd
from matplotlib.axes import Axes
from matplotlib.lines import Line2D

from c3bench.bench import figure_base as base
from c3bench.bench import store
from c3bench.bench.metrics import family_label, with_variants
from c3bench.bench.palette import (
    SolverStyle,
    legend_outside,
    palette,
    panel_title,
    solver_handles,
)
from c3bench.problems.names import COMPLEMENTARITY_FAMILIES, Precision, Start

MIQP_FAMILIES: tuple[str, ...] = tuple(COMPLEMENTARITY_FAMILIES)
"""Families whose reference is a mixed-integer optimum."""
PRECISION_ORDER: tuple[str, ...] = (Precision.FLOAT64, Precision.FLOAT32)


# --- convergence traces -----------------------------------------------------------------------
def _trace_series(rows: pd.DataFrame, paths: store.SuitePaths, instance: str
                  ) -> dict[str, dict[str, list[float]]]:
    series: dict[str, dict[str, list[float]]] = {}
    for _, row in rows[rows["instance"] == instance].sort_values("solver").iterrows():
        trace = store.read_trace(paths, row["trace_file"]).get("trace", {})
        keep = {k: v for k, v in trace.items() if "residual" in k and len(v) > 0}
        if keep:
            series[row["solver"]] = keep
    return series


def convergence_traces(frame: pd.DataFrame, paths: store.SuitePaths) -> list[base.Figure]:
    """Residual vs iteration for every solver with a trace, on one instance per family."""
    out = []
    rows_all = base.baseline(frame)
    rows_all = rows_all[rows_all["trace_file"] != ""]
    for family in sorted(set(frame["family"])):
        rows = rows_all[rows_all["family"] == family]
        figure = base.Figure(
            f"traces_{family}", f"Convergence traces: {family}",
            f"{family}: per-iteration residuals reported by each solver on one instance "
            "(x: iteration, -; y: residual, log scale, units of the problem data); cold "
            "start, float64; one panel per residual series (n = 1 instance and the number "
            "of solvers drawn).")
        series: dict[str, dict[str, list[float]]] = {}
        if not rows.empty:
            profile = str(base.preferred_settings(rows))
            rows = rows[rows["settings"] == profile]
            counts = rows.groupby("instance")["solver"].nunique()
            instance = sorted(counts[counts == counts.max()].index)[0]
            series = _trace_series(rows, paths, instance)
        if not series:
            absent = store.absent_traces(paths, rows["trace_file"])
            figure.note = (f"the trace files of its cells are not here ({absent} missing; "
                           "traces/ is not committed): rerun the suite to draw it"
                           if absent else "no solver reported a per-iteration residual "
                           "trace for this family")
            out.append(figure)
            continue
        figure.caption = figure.caption.replace(
            "one instance", f"instance {instance} ({profile} settings)", 1)
        keys = sorted({k for trace in series.values() for k in trace})
        styles = palette(series)
        fig, axes = base.new_figure(len(keys), 4.6, 3.8)
        for ax, key in zip(axes, keys, strict=True):
            _trace_panel(ax, key, series, styles, instance)
        legend_outside(fig, solver_handles(styles))
        figure.path = base.save(fig, paths, figure.key)
        out.append(figure)
    return out


def _trace_panel(ax: Axes, key: str, series: dict[str, dict[str, list[float]]],
                 styles: dict[str, SolverStyle], instance: str) -> None:
    drawn = 0
    for solver in sorted(series):
        values = np.asarray(series[solver].get(key, []), dtype=float)
        if values.size:
            style = styles[solver]
            ax.semilogy(np.arange(values.size), np.maximum(np.abs(values), 1e-300),
                        color=style.color, linestyle=style.linestyle, marker=style.marker,
                        markevery=max(1, values.size // 8), markersize=4, label=solver)
            drawn += 1
    ax.set_xlabel("iteration (-)")
    ax.set_ylabel(key.replace("_", " "))
    ax.grid(True, alpha=0.3)
    panel_title(ax, f"{key}, {instance}", 1, f"instance, {drawn} solver(s)")


# --- cond(S) along ADMM ----------------------------------------------------------------------
def conditioning(frame: pd.DataFrame, paths: store.SuitePaths) -> list[base.Figure]:
    """cond(S) raw (dashed) and equilibrated (solid) vs ADMM iteration, median over states."""
    figure = base.Figure(
        "conditioning_admm", "cond(S) along ADMM iterations",
        "Condition number of the Schur complement S = A Q^-1 A^T before (dashed) and after "
        "(solid) equilibration vs the ADMM iteration the QP was captured at (x: ADMM "
        "iteration, -; y: cond(S), -, log scale; median over states and settings), per "
        "backend that reports it; float64; n = the cells behind each panel.")
    rows = frame[(frame["precision"] == Precision.FLOAT64) & frame["admm_iteration"].notna()]
    rows = rows[np.isfinite(rows["cond_schur_raw"].to_numpy(float))
                | np.isfinite(rows["cond_schur_equilibrated"].to_numpy(float))]
    if rows.empty:
        figure.note = ("no backend reported cond_schur_raw / cond_schur_equilibrated on an "
                       "instance with an ADMM iteration")
        return [figure]
    families = sorted(set(rows["family"]))
    styles = palette(set(rows["solver"]))
    fig, axes = base.new_figure(len(families), 4.8, 3.9)
    for ax, family in zip(axes, families, strict=True):
        subset = rows[rows["family"] == family]
        for solver in sorted(set(subset["solver"])):
            _conditioning_lines(ax, subset[subset["solver"] == solver], styles[solver])
        ax.set_xlabel("ADMM iteration (-)")
        ax.set_ylabel("cond(S) (-)")
        ax.grid(True, alpha=0.3)
        panel_title(ax, family, len(subset), "cells")
    kinds = [Line2D([], [], color="black", linestyle="--", label="raw"),
             Line2D([], [], color="black", linestyle="-", label="equilibrated")]
    legend_outside(fig, [*solver_handles(styles, lines=False), *kinds])
    figure.path = base.save(fig, paths, figure.key)
    return [figure]


def _conditioning_lines(ax: Axes, mine: pd.DataFrame, style: SolverStyle) -> None:
    medians = mine.groupby("admm_iteration")[["cond_schur_raw",
                                              "cond_schur_equilibrated"]].median()
    x = medians.index.to_numpy(dtype=float)
    for column, line in (("cond_schur_raw", "--"), ("cond_schur_equilibrated", "-")):
        y = medians[column].to_numpy(dtype=float)
        if np.isfinite(y).any():
            ax.semilogy(x, y, line, marker=style.marker, color=style.color, markersize=5)


# --- float32 vs float64 -----------------------------------------------------------------------
def _boxes(ax: Axes, groups: list[tuple[str, str, np.ndarray]],
           styles: dict[str, SolverStyle]) -> int:
    """Box per (solver, label, values) with a gap between solvers; returns the cell count."""
    positions, data, labels, colors = [], [], [], []
    index, previous = 0, None
    for solver, label, values in groups:
        if previous is not None and solver != previous:
            index += 1
        previous = solver
        positions.append(index)
        data.append(np.maximum(values, base.DRAW_FLOOR) if values.size else [np.nan])
        labels.append(f"{label} (n={values.size})")
        colors.append(styles[solver].color)
        index += 1
    boxes = ax.boxplot(data, positions=positions, tick_labels=labels, patch_artist=True)
    for patch, color, label in zip(boxes["boxes"], colors, labels, strict=True):
        patch.set_facecolor(color)
        patch.set_alpha(0.35 if Precision.FLOAT32 in label else 0.75)
    ax.set_yscale("log")
    ax.tick_params(axis="x", labelsize=7, labelrotation=60)
    for tick in ax.get_xticklabels():
        tick.set_horizontalalignment("right")
    ax.grid(True, axis="y", alpha=0.3)
    return sum(values.size for _, _, values in groups)


def _finite(values: pd.Series) -> np.ndarray:
    array = values.to_numpy(float)
    return array[np.isfinite(array)]


def precision_accuracy(frame: pd.DataFrame, paths: store.SuitePaths) -> list[base.Figure]:
    """Primal residual (and projection violations) in float32 vs float64 per backend."""
    figure = base.Figure(
        "precision_accuracy", "float32 vs float64 accuracy",
        "Left: relative primal residual ||Ax - b||_inf / max(1, ||b||) of each "
        "backend that runs in both precisions (y: dimensionless, log scale); right: "
        "constraint violation before and after the final projection step (y: "
        "||Ax - b||_inf, log scale), float32 (light) and float64 (dark); cold start, all "
        f"settings; values below {base.DRAW_FLOOR:g} drawn at {base.DRAW_FLOOR:g}; n per box "
        "in its label.")
    cold = frame[frame["start"] == Start.COLD]
    both = [s for s in sorted(set(cold["solver"]))
            if set(PRECISION_ORDER) <= set(cold.loc[cold["solver"] == s, "precision"])]
    if not both:
        figure.note = "no backend ran in both float32 and float64"
        return [figure]
    rows = cold[cold["solver"].isin(both)]
    styles = palette(both)
    primal = [(s, f"{s} {p}", _finite(rows.loc[(rows["solver"] == s) & (rows["precision"] == p),
                                               "primal_residual_relative"]))
              for s in both for p in PRECISION_ORDER]
    projection = [(s, f"{s} {p} {tag}", _finite(rows.loc[(rows["solver"] == s)
                                                         & (rows["precision"] == p), column]))
                  for s in both for p in PRECISION_ORDER
                  for column, tag in (("violation_before_projection", "before"),
                                      ("violation_after_projection", "after"))]
    projection = [group for group in projection if group[2].size]
    fig, axes = base.new_figure(2 if projection else 1, max(5.0, 1.3 * len(both) + 2), 5.0,
                                legend=False)
    n = _boxes(axes[0], primal, styles)
    axes[0].set_ylabel("relative primal residual (-)")
    panel_title(axes[0], "primal residual", n, "cells")
    if projection:
        n = _boxes(axes[1], projection, styles)
        axes[1].set_ylabel("constraint violation ||Ax - b||_inf (-)")
        panel_title(axes[1], "before / after the final projection", n, "cells")
    figure.path = base.save(fig, paths, figure.key)
    return [figure]


# --- MIQP vs heuristics -----------------------------------------------------------------------
def _gap_panel(ax: Axes, subset: pd.DataFrame, styles: dict[str, SolverStyle]) -> None:
    solvers = sorted(set(subset["solver"]))
    reference = subset["reference_objective"].to_numpy(float)
    gaps = (subset["objective"].to_numpy(float) - reference) / np.maximum(1.0, np.abs(
        reference))
    labels = []
    for i, solver in enumerate(solvers):
        mask = (subset["solver"] == solver).to_numpy()
        gap, ok = gaps[mask], subset["success"].to_numpy(bool)[mask]
        jitter = np.linspace(-0.15, 0.15, len(gap)) if len(gap) > 1 else np.zeros(1)
        style = styles[solver]
        ax.scatter(i + jitter[ok], gap[ok], color=style.color, marker=style.marker, s=22)
        ax.scatter(i + jitter[~ok], gap[~ok], facecolors="none", edgecolors=style.color,
                   marker=style.marker, s=22)
        labels.append(f"{solver} (n={len(gap)})")
    ax.axhline(0.0, color="black", linewidth=0.8)
    ax.set_yscale("symlog", linthresh=1e-6)
    top = max(1e-5, float(np.nanmax(np.abs(gaps))) if gaps.size else 1e-5)
    ax.set_ylim(-10 * top, 10 * top)
    ax.set_xticks(range(len(solvers)), labels, rotation=60, ha="right", fontsize=7)
    ax.set_ylabel("relative cost gap (f - f*) / max(1, |f*|) (-)")
    ax.grid(True, axis="y", alpha=0.3)


def miqp_gap(frame: pd.DataFrame, paths: store.SuitePaths) -> list[base.Figure]:
    """Signed relative cost gap of each backend vs the MIQP optimum (projection, mpcc)."""
    figure = base.Figure(
        "miqp_gap", "MIQP vs heuristic cost gap",
        "projection and mpcc: (f - f*) / max(1, |f*|) of each backend's answer against the "
        "MIQP reference optimum f* (y: relative cost gap, -, symmetric log scale; positive = "
        "worse than the MIQP; markers filled where the cell succeeded, hollow where it did "
        "not; n per solver in its label); cold start, float64; one panel per family and "
        "variant.")
    rows = base.baseline(frame)
    rows = rows[rows["family"].isin(MIQP_FAMILIES)]
    rows = rows[np.isfinite(rows["objective"].to_numpy(float))
                & np.isfinite(rows["reference_objective"].to_numpy(float))]
    if rows.empty:
        figure.note = ("no projection/mpcc cell has both an objective and an MIQP reference "
                       "optimum (is the MIQP reference backend available?)")
        return [figure]
    profile = str(base.preferred_settings(rows))
    rows = with_variants(rows[rows["settings"] == profile])
    figure.caption += f" Settings: {profile}."
    keys = sorted(set(zip(rows["family"], rows["variant"], strict=True)))
    styles = palette(set(rows["solver"]))
    fig, axes = base.new_figure(len(keys), 4.8, 4.4)
    for ax, (family, variant) in zip(axes, keys, strict=True):
        subset = rows[(rows["family"] == family) & (rows["variant"] == variant)]
        _gap_panel(ax, subset, styles)
        family_rows = rows[rows["family"] == family]
        panel_title(ax, family_label(family, variant), int(subset["instance"].nunique()),
                    not_run=set(family_rows["solver"]) - set(subset["solver"]))
    kinds = [Line2D([], [], color="grey", marker="o", linestyle="none", label="succeeded"),
             Line2D([], [], color="grey", marker="o", markerfacecolor="none",
                    linestyle="none", label="failed")]
    legend_outside(fig, [*solver_handles(styles, lines=False), *kinds])
    figure.path = base.save(fig, paths, figure.key)
    return [figure]
