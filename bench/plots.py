"""Figures of the report (matplotlib, Agg backend), each returned with its caption.

Every function takes the results table (and the suite paths where it reads traces) and
returns :class:`Figure` records; a figure without data is not drawn: its record has
``path=None`` and ``note`` says why, and the report prints that note instead.
Figures use cold-start float64 rows unless they are about precision or warm starts, and the
settings profile :func:`preferred_settings` picks when one profile is shown.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
import pandas as pd

from c3bench.bench import store
from c3bench.bench.metrics import performance_profile, performance_ratios
from c3bench.bench.perf import REFERENCE_STEP_MS, TARGET_STEP_MS, summarize
from c3bench.problems.names import COMPLEMENTARITY_FAMILIES, Precision, Profile, Start

DPI = 110
SETTINGS_ORDER: tuple[str, ...] = tuple(Profile)
"""Order of the settings profiles in figures and tables."""
MIQP_FAMILIES: tuple[str, ...] = tuple(COMPLEMENTARITY_FAMILIES)
"""Families whose reference is a mixed-integer optimum."""
PRECISION_ORDER: tuple[str, ...] = (Precision.FLOAT64, Precision.FLOAT32)


@dataclass
class Figure:
    """One figure of the report.

    Attributes
    ----------
    key
        Stable identifier (also the file stem).
    title
        Heading.
    caption
        One line describing axes and what is shown.
    path
        PNG path relative to the suite directory (``None`` when there was no data).
    note
        Why the figure is missing (``""`` when drawn).
    """

    key: str
    title: str
    caption: str
    path: str | None = None
    note: str = ""


def preferred_settings(frame: pd.DataFrame) -> str | None:
    """``default`` when present, else the first profile of :data:`SETTINGS_ORDER` present."""
    present = set(frame["settings"])
    for name in SETTINGS_ORDER:
        if name in present:
            return name
    return min(present) if present else None


def ordered_settings(frame: pd.DataFrame) -> list[str]:
    """The settings profiles present, in :data:`SETTINGS_ORDER` (unknown ones last)."""
    present = set(frame["settings"])
    return [s for s in SETTINGS_ORDER if s in present] + sorted(present - set(SETTINGS_ORDER))


def _baseline(frame: pd.DataFrame) -> pd.DataFrame:
    """The cold-start float64 rows."""
    return frame[(frame["precision"] == Precision.FLOAT64) & (frame["start"] == Start.COLD)]


def _save(fig: plt.Figure, paths: store.SuitePaths, key: str) -> str:
    paths.figures.mkdir(parents=True, exist_ok=True)
    relative = f"figures/{key}.png"
    fig.tight_layout()
    fig.savefig(paths.root / relative, dpi=DPI, metadata={"Software": None})
    plt.close(fig)
    return relative


def _colors(names: list[str]) -> dict[str, tuple[float, ...]]:
    cmap = plt.get_cmap("tab10")
    return {name: cmap(i % 10) for i, name in enumerate(sorted(names))}


def _styles(names: list[str]) -> dict[str, str]:
    """Line style per name: solid for the first ten, then dashed, dotted, dash-dot."""
    cycle = ("-", "--", ":", "-.")
    return {name: cycle[(i // 10) % 4] for i, name in enumerate(sorted(names))}


# --- performance profiles ---------------------------------------------------------------------
def performance_profiles(frame: pd.DataFrame, paths: store.SuitePaths) -> list[Figure]:
    """Dolan-More profiles per family, one panel per settings profile (cold, float64)."""
    out = []
    base = _baseline(frame)
    for family in sorted(set(frame["family"])):
        rows = base[base["family"] == family]
        figure = Figure(f"profile_{family}", f"Performance profile: {family}",
                        f"{family}: fraction of instances a solver solves (success as "
                        "defined above) within a factor tau of the fastest solver's time "
                        "(x: tau, log2 scale, dimensionless; y: fraction of instances); cold "
                        "start, float64, one panel per settings profile.")
        if rows.empty or not rows["success"].any():
            figure.note = "no cold-start float64 cell of this family succeeded"
            out.append(figure)
            continue
        profiles = ordered_settings(rows)
        fig, axes = plt.subplots(1, len(profiles), figsize=(5.2 * len(profiles), 3.8),
                                 squeeze=False)
        colors = _colors(list(set(rows["solver"])))
        styles = _styles(list(set(rows["solver"])))
        for ax, profile in zip(axes[0], profiles, strict=True):
            ratios = performance_ratios(rows[rows["settings"] == profile])
            finite = ratios.to_numpy()[np.isfinite(ratios.to_numpy())]
            top = max(2.0, float(finite.max()) * 1.5) if finite.size else 2.0
            taus = np.logspace(0, math.log10(top), 200)
            for solver, curve in sorted(performance_profile(ratios, taus).items()):
                ax.step(taus, curve, where="post", label=solver, color=colors[solver],
                        linestyle=styles[solver])
            ax.set_xscale("log", base=2)
            ax.set_ylim(-0.02, 1.02)
            ax.set_xlabel("tau = time / best time (-)")
            ax.set_ylabel("fraction of instances (-)")
            ax.set_title(f"{family}, {profile}")
            ax.grid(True, alpha=0.3)
        axes[0][-1].legend(fontsize=7, loc="lower right")
        figure.path = _save(fig, paths, figure.key)
        out.append(figure)
    return out


# --- solve-time distributions -----------------------------------------------------------------
def time_distributions(frame: pd.DataFrame, paths: store.SuitePaths) -> list[Figure]:
    """Box plots of successful solve times per solver, one figure per family."""
    out = []
    base = _baseline(frame)
    for family in sorted(set(frame["family"])):
        rows = base[(base["family"] == family) & base["success"]]
        figure = Figure(f"times_{family}", f"Solve-time distribution: {family}",
                        f"{family}: solve time of successful cold-start float64 cells per "
                        "solver (y: solve time in ms, log scale; box: quartiles, whiskers: "
                        "1.5 IQR), one panel per settings profile.")
        if rows.empty:
            figure.note = "no successful cold-start float64 cell in this family"
            out.append(figure)
            continue
        profiles = ordered_settings(rows)
        fig, axes = plt.subplots(1, len(profiles), figsize=(max(5.0, 0.55 * rows[
            "solver"].nunique() + 2) * len(profiles), 4.0), squeeze=False)
        for ax, profile in zip(axes[0], profiles, strict=True):
            subset = rows[rows["settings"] == profile]
            solvers = sorted(set(subset["solver"]))
            data = [1e3 * subset.loc[subset["solver"] == s, "solve_time"].to_numpy(float)
                    for s in solvers]
            ax.boxplot(data, tick_labels=solvers)
            ax.set_yscale("log")
            ax.set_ylabel("solve time (ms)")
            ax.set_xlabel("solver")
            ax.set_title(f"{family}, {profile}")
            ax.tick_params(axis="x", labelrotation=60, labelsize=7)
            ax.grid(True, axis="y", alpha=0.3)
        figure.path = _save(fig, paths, figure.key)
        out.append(figure)
    return out


# --- convergence traces -----------------------------------------------------------------------
def convergence_traces(frame: pd.DataFrame, paths: store.SuitePaths) -> list[Figure]:
    """Residual vs iteration for every solver with a trace, on one instance per family."""
    out = []
    base = _baseline(frame)
    base = base[base["trace_file"] != ""]
    for family in sorted(set(frame["family"])):
        rows = base[base["family"] == family]
        figure = Figure(f"traces_{family}", f"Convergence traces: {family}",
                        f"{family}: per-iteration residuals reported by each solver on one "
                        "instance (x: iteration, -; y: residual, log scale, units of the "
                        "problem data); cold start, float64.")
        series: dict[str, dict[str, list[float]]] = {}
        if not rows.empty:
            profile = preferred_settings(rows)
            rows = rows[rows["settings"] == profile]
            counts = rows.groupby("instance")["solver"].nunique()
            instance = sorted(counts[counts == counts.max()].index)[0]
            for _, row in rows[rows["instance"] == instance].sort_values("solver").iterrows():
                trace = store.read_trace(paths, row["trace_file"]).get("trace", {})
                keep = {k: v for k, v in trace.items() if "residual" in k and len(v) > 0}
                if keep:
                    series[row["solver"]] = keep
        if not series:
            figure.note = "no solver reported a per-iteration residual trace for this family"
            out.append(figure)
            continue
        figure.caption = figure.caption.replace("one instance", f"instance {instance} "
                                                f"({profile} settings)")
        keys = sorted({k for trace in series.values() for k in trace})
        fig, axes = plt.subplots(1, len(keys), figsize=(5.0 * len(keys), 3.8), squeeze=False)
        colors = _colors(list(series))
        styles = _styles(list(series))
        for ax, key in zip(axes[0], keys, strict=True):
            for solver in sorted(series):
                values = np.asarray(series[solver].get(key, []), dtype=float)
                if values.size:
                    ax.semilogy(np.arange(values.size), np.maximum(np.abs(values), 1e-300),
                                label=solver, color=colors[solver],
                                linestyle=styles[solver])
            ax.set_xlabel("iteration (-)")
            ax.set_ylabel(f"{key.replace('_', ' ')}")
            ax.set_title(key)
            ax.grid(True, alpha=0.3)
        axes[0][-1].legend(fontsize=7)
        figure.path = _save(fig, paths, figure.key)
        out.append(figure)
    return out


# --- cond(S) along ADMM ----------------------------------------------------------------------
def conditioning(frame: pd.DataFrame, paths: store.SuitePaths) -> list[Figure]:
    """cond(S) raw (dashed) and equilibrated (solid) vs ADMM iteration, median over states."""
    figure = Figure("conditioning_admm", "cond(S) along ADMM iterations",
                    "Condition number of the Schur complement S = A Q^-1 A^T before (dashed) "
                    "and after (solid) equilibration vs the ADMM iteration the QP was "
                    "captured at (x: ADMM iteration, -; y: cond(S), -, log scale; median "
                    "over states and settings), per backend that reports it; float64.")
    rows = frame[(frame["precision"] == Precision.FLOAT64) & frame["admm_iteration"].notna()]
    rows = rows[np.isfinite(rows["cond_schur_raw"].to_numpy(float))
                | np.isfinite(rows["cond_schur_equilibrated"].to_numpy(float))]
    if rows.empty:
        figure.note = ("no backend reported cond_schur_raw / cond_schur_equilibrated on an "
                       "instance with an ADMM iteration")
        return [figure]
    families = sorted(set(rows["family"]))
    fig, axes = plt.subplots(1, len(families), figsize=(5.5 * len(families), 4.0),
                             squeeze=False)
    colors = _colors(list(set(rows["solver"])))
    for ax, family in zip(axes[0], families, strict=True):
        subset = rows[rows["family"] == family]
        for solver in sorted(set(subset["solver"])):
            mine = subset[subset["solver"] == solver]
            medians = mine.groupby("admm_iteration")[["cond_schur_raw",
                                                      "cond_schur_equilibrated"]].median()
            x = medians.index.to_numpy(dtype=float)
            for column, style in (("cond_schur_raw", "--"), ("cond_schur_equilibrated", "-")):
                y = medians[column].to_numpy(dtype=float)
                if np.isfinite(y).any():
                    ax.semilogy(x, y, style, marker="o", color=colors[solver],
                                label=f"{solver} ({'raw' if column.endswith('raw') else 'eq.'})")
        ax.set_xlabel("ADMM iteration (-)")
        ax.set_ylabel("cond(S) (-)")
        ax.set_title(family)
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=7)
    figure.path = _save(fig, paths, figure.key)
    return [figure]


# --- float32 vs float64 -----------------------------------------------------------------------
def precision_accuracy(frame: pd.DataFrame, paths: store.SuitePaths) -> list[Figure]:
    """Primal residual (and projection violations) in float32 vs float64 per backend."""
    figure = Figure("precision_accuracy", "float32 vs float64 accuracy",
                    "Left: relative primal residual ||Ax - b||_inf / max(1, ||Ax||, ||b||) of "
                    "each backend that runs in both precisions (y: dimensionless, log scale); "
                    "right: constraint violation before and after the final projection step "
                    "(y: ||Ax - b||_inf, log scale), float32 and float64; cold start, all "
                    "settings.")
    cold = frame[frame["start"] == Start.COLD]
    both = [s for s in sorted(set(cold["solver"]))
            if set(PRECISION_ORDER) <= set(cold.loc[cold["solver"] == s, "precision"])]
    if not both:
        figure.note = "no backend ran in both float32 and float64"
        return [figure]
    rows = cold[cold["solver"].isin(both)]
    has_projection = np.isfinite(rows["violation_before_projection"].to_numpy(float)).any()
    panels = 2 if has_projection else 1
    fig, axes = plt.subplots(1, panels, figsize=(max(5.0, 1.4 * len(both) + 2) * panels, 5.0),
                             squeeze=False)
    ax = axes[0][0]
    positions, data, labels = [], [], []
    for i, solver in enumerate(both):
        for j, precision in enumerate(PRECISION_ORDER):
            values = rows.loc[(rows["solver"] == solver) & (rows["precision"] == precision),
                              "primal_residual_relative"].to_numpy(float)
            values = values[np.isfinite(values)]
            positions.append(3 * i + j)
            data.append(np.maximum(values, 1e-18) if values.size else [np.nan])
            labels.append(f"{solver} {precision}")
    ax.boxplot(data, positions=positions, tick_labels=labels)
    ax.set_yscale("log")
    ax.set_ylabel("relative primal residual (-)")
    ax.set_xlabel("backend / precision (residuals below 1e-18 drawn at 1e-18)")
    ax.tick_params(axis="x", labelsize=7, labelrotation=60)
    ax.grid(True, axis="y", alpha=0.3)
    if has_projection:
        ax = axes[0][1]
        positions, data, labels = [], [], []
        index = 0
        for solver in both:
            for precision in PRECISION_ORDER:
                mine = rows[(rows["solver"] == solver) & (rows["precision"] == precision)]
                for column, tag in (("violation_before_projection", "before"),
                                    ("violation_after_projection", "after")):
                    values = mine[column].to_numpy(float)
                    values = values[np.isfinite(values)]
                    if values.size:
                        positions.append(index)
                        data.append(np.maximum(values, 1e-18))
                        labels.append(f"{solver} {precision} {tag}")
                        index += 1
                index += 1
        ax.boxplot(data, positions=positions, tick_labels=labels)
        ax.set_yscale("log")
        ax.set_ylabel("constraint violation ||Ax - b||_inf (-)")
        ax.set_xlabel("backend / precision / projection")
        ax.tick_params(axis="x", labelsize=7, labelrotation=60)
        ax.grid(True, axis="y", alpha=0.3)
    figure.path = _save(fig, paths, figure.key)
    return [figure]


# --- MIQP vs heuristics -----------------------------------------------------------------------
def miqp_gap(frame: pd.DataFrame, paths: store.SuitePaths) -> list[Figure]:
    """Signed relative cost gap of each backend vs the MIQP optimum (projection, mpcc)."""
    figure = Figure("miqp_gap", "MIQP vs heuristic cost gap",
                    "projection and mpcc: (f - f*) / max(1, |f*|) of each backend's answer "
                    "against the MIQP reference optimum f* (y: relative cost gap, -, "
                    "symmetric log scale; positive = worse than the MIQP; markers filled "
                    "where the cell succeeded, hollow where it did not); cold start, "
                    "float64.")
    base = _baseline(frame)
    rows = base[base["family"].isin(MIQP_FAMILIES)]
    rows = rows[np.isfinite(rows["objective"].to_numpy(float))
                & np.isfinite(rows["reference_objective"].to_numpy(float))]
    if rows.empty:
        figure.note = ("no projection/mpcc cell has both an objective and an MIQP reference "
                       "optimum (is the MIQP reference backend available?)")
        return [figure]
    profile = preferred_settings(rows)
    rows = rows[rows["settings"] == profile]
    figure.caption += f" Settings: {profile}."
    families = sorted(set(rows["family"]))
    fig, axes = plt.subplots(1, len(families), figsize=(5.5 * len(families), 4.0),
                             squeeze=False)
    for ax, family in zip(axes[0], families, strict=True):
        subset = rows[rows["family"] == family]
        solvers = sorted(set(subset["solver"]))
        for i, solver in enumerate(solvers):
            mine = subset[subset["solver"] == solver]
            gap = (mine["objective"].to_numpy(float) - mine["reference_objective"].to_numpy(
                float)) / np.maximum(1.0, np.abs(mine["reference_objective"].to_numpy(float)))
            ok = mine["success"].to_numpy(bool)
            jitter = np.linspace(-0.15, 0.15, len(gap)) if len(gap) > 1 else np.zeros(1)
            ax.scatter(i + jitter[ok], gap[ok], color="tab:blue", s=18)
            ax.scatter(i + jitter[~ok], gap[~ok], facecolors="none", edgecolors="tab:red", s=18)
        ax.axhline(0.0, color="black", linewidth=0.8)
        ax.set_yscale("symlog", linthresh=1e-6)
        finite = np.abs(((subset["objective"] - subset["reference_objective"]) / np.maximum(
            1.0, subset["reference_objective"].abs())).to_numpy(float))
        top = max(1e-5, float(np.nanmax(finite)) if finite.size else 1e-5)
        ax.set_ylim(-10 * top, 10 * top)
        ax.set_xticks(range(len(solvers)), solvers, rotation=60, fontsize=7)
        ax.set_xlabel("backend")
        ax.set_ylabel("relative cost gap (f - f*) / max(1, |f*|) (-)")
        ax.set_title(family)
        ax.grid(True, axis="y", alpha=0.3)
    figure.path = _save(fig, paths, figure.key)
    return [figure]


def all_figures(frame: pd.DataFrame, paths: store.SuitePaths) -> list[Figure]:
    """Every figure of the report, in report order."""
    figures: list[Figure] = []
    for make in (performance_profiles, time_distributions, convergence_traces, conditioning,
                 precision_accuracy, miqp_gap):
        figures += make(frame, paths)
    return figures


# --- perf: control-step time ------------------------------------------------------------------
def plot_perf(frame: pd.DataFrame, path: Path) -> Path | None:
    """Log-log median control-step time vs samples (p95 as error bars); ``None`` when empty.

    ``frame`` holds the rows of ``c3bench perf`` (:data:`bench.store.PERF_SCHEMA`); the
    reference study's step time and the target are drawn as horizontal lines.
    """
    summary = summarize(frame)
    summary = summary[summary["repeats"] > 0]
    if summary.empty:
        return None
    figure, axes = plt.subplots(figsize=(7.0, 4.6))
    for (backend, precision, device), group in summary.groupby(
            ["backend", "precision", "device"], sort=False):
        group = group.sort_values("samples")
        medians = group["median_ms"].to_numpy(dtype=float)
        upper = group["p95_ms"].to_numpy(dtype=float) - medians
        axes.errorbar(group["samples"], medians, yerr=[np.zeros_like(upper), upper],
                      marker="o", capsize=3, label=f"{backend} ({precision}, {device})")
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
