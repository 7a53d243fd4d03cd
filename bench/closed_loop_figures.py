"""Figures of a closed-loop suite's randomized trials: success rate with its 95 % interval per
configuration, success against the model's cube side ``l`` with an interval band, and the
distributions of the physical metrics per configuration.

Every figure follows the report conventions of :mod:`bench.palette`: one fixed colour per
configuration group (:data:`GROUP_ORDER`; not per configuration, so a group reads the same in
every figure), ``n`` in every panel, the legend outside the data. The intervals are Wilson's
score intervals (:func:`bench.trials.wilson_interval`).
"""

from __future__ import annotations

import math
import zlib
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
import pandas as pd
from matplotlib.axes import Axes
from matplotlib.figure import Figure as MplFigure
from matplotlib.lines import Line2D

from c3bench.bench.figure_base import DPI, new_figure
from c3bench.bench.palette import COLORS, legend_outside, n_text
from c3bench.bench.trials import TrialSummary

GROUP_ORDER: tuple[str, ...] = ("backends", "seed method", "robust", "ablation", "l-curve",
                                "c3")
"""The configuration groups of :class:`bench.closed_loop_suite.SuiteGroup`, in colour order:
group ``i`` is drawn in ``COLORS[i]``; another group gets a colour from its name's CRC."""


@dataclass(frozen=True)
class ConfigurationResult:
    """The episodes of one configuration, summarised.

    Attributes
    ----------
    name, title, group
        The configuration's file-safe name, display name and group.
    summary
        :func:`bench.trials.trial_summary` of its rows.
    rows
        Its rows of ``results.parquet``.
    """

    name: str
    title: str
    group: str
    summary: TrialSummary
    rows: pd.DataFrame


PLAN_CEILING = 10.0
"""Plan-consistency angle gaps above this (rad; a diverged plan) are drawn at it."""
DISTRIBUTIONS: tuple[tuple[str, str, float, bool, float], ...] = (
    ("peak_angle", "peak angle (rad)", 1.0, False, math.inf),
    ("hold_time", "hold time at the end (s)", 1.0, False, math.inf),
    ("plan_lcs_angle_median", "plan vs LCS angle, median (rad)", 1.0, True, PLAN_CEILING),
    ("plan_plant_angle_median", "plan vs plant angle, median (rad)", 1.0, True,
     PLAN_CEILING),
    ("median_step_time", "control step, median (ms)", 1e3, True, math.inf),
)
"""The per-episode metrics drawn as distributions: (column, axis label, scale, log axis,
ceiling: larger values are drawn at it)."""
HORIZONTAL: dict[str, Any] = (
    {"orientation": "horizontal"}
    if tuple(int(p) for p in matplotlib.__version__.split(".")[:2]) >= (3, 10)
    else {"vert": False})
"""``boxplot``'s keyword for horizontal boxes (``vert`` is deprecated from matplotlib 3.10)."""
LOG_FLOOR = 1e-6
"""On a log axis, smaller values (exact zeros) are drawn at this level."""


def group_color(group: str) -> str:
    """The fixed colour of a configuration group (:data:`GROUP_ORDER`)."""
    if group in GROUP_ORDER:
        return COLORS[GROUP_ORDER.index(group) % len(COLORS)]
    return COLORS[(len(GROUP_ORDER) + zlib.crc32(group.encode())) % len(COLORS)]


def group_handles(groups: Sequence[str]) -> list[Line2D]:
    """Legend proxies, one per group present, in :data:`GROUP_ORDER`."""
    present = [g for g in GROUP_ORDER if g in groups] + sorted(set(groups) - set(GROUP_ORDER))
    return [Line2D([], [], color=group_color(g), marker="s", linestyle="none", label=g)
            for g in present]


def _save(fig: MplFigure, path: Path) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=DPI, metadata={"Software": None})
    plt.close(fig)
    return path


def _n_range(results: Sequence[ConfigurationResult]) -> str:
    counts = sorted({r.summary.n for r in results})
    if not counts:
        return n_text(0, "episodes")
    shown = str(counts[0]) if len(counts) == 1 else f"{counts[0]}-{counts[-1]}"
    return f"n = {shown} episodes per configuration"


def plot_success_rates(results: Sequence[ConfigurationResult], path: Path) -> Path:
    """:func:`success_rate_figure` written to ``path``."""
    return _save(success_rate_figure(results), path)


def success_rate_figure(results: Sequence[ConfigurationResult],
                        title: str = "Success rate per configuration") -> MplFigure:
    """Success rate (dot) and its Wilson 95 % interval (bar) per configuration, one row each,
    coloured by group; ``k/n`` printed beside every bar."""
    fig, axes = new_figure(1, 6.5, 0.32 * len(results) + 1.4, max_columns=1)
    ax = axes[0]
    for row, result in enumerate(results):
        summary = result.summary
        low, high = summary.success_interval
        rate = summary.rate if summary.n else math.nan
        color = group_color(result.group)
        spread = [[max(0.0, rate - low)], [max(0.0, high - rate)]]  # rounding at 0 and 1
        ax.errorbar([rate], [row], xerr=spread if summary.n else None,
                    fmt="o", color=color, capsize=3, markersize=5)
        ax.text(1.02, row, f"{summary.successes}/{summary.n}", va="center", fontsize=7,
                transform=ax.get_yaxis_transform())
    ax.set_yticks(range(len(results)), [r.title for r in results], fontsize=7)
    ax.invert_yaxis()
    ax.set_xlim(-0.02, 1.02)
    ax.set_xlabel("success rate (Wilson 95 % interval)")
    ax.grid(axis="x", alpha=0.3)
    ax.set_title(f"{title}\n{_n_range(results)}", fontsize=8)
    legend_outside(fig, group_handles([r.group for r in results]), title="group")
    return fig


def plot_l_curve(points: Sequence[tuple[float, TrialSummary]], path: Path,
                 true_side: float, label: str) -> Path:
    """:func:`l_curve_figure` written to ``path``."""
    return _save(l_curve_figure(points, true_side, label), path)


def l_curve_figure(points: Sequence[tuple[float, TrialSummary]], true_side: float,
                   label: str) -> MplFigure:
    """Success rate against the model's cube side ``l`` with its Wilson 95 % band; the true
    side (nominal plant) dashed, the trials' range of plant sides shaded lightly."""
    fig, axes = new_figure(1, 5.0, 3.6, max_columns=1)
    ax = axes[0]
    sides = np.array([side for side, _ in points], dtype=float)
    rates = np.array([s.rate for _, s in points], dtype=float)
    low = np.array([s.success_interval[0] for _, s in points])
    high = np.array([s.success_interval[1] for _, s in points])
    color = group_color("l-curve")
    ax.fill_between(sides, low, high, color=color, alpha=0.25, linewidth=0)
    ax.plot(sides, rates, marker="o", color=color)
    for side, summary in points:
        ax.annotate(f"{summary.successes}/{summary.n}", (side, summary.rate),
                    textcoords="offset points", xytext=(0, 6), ha="center", fontsize=7)
    ax.axvline(true_side, color="k", linestyle="--", linewidth=0.8)
    ax.set_ylim(-0.02, 1.08)
    ax.set_xlabel("model cube side l (m)")
    ax.set_ylabel("success rate")
    counts = sorted({s.n for _, s in points})
    shown = str(counts[0]) if len(counts) == 1 else f"{counts[0]}-{counts[-1]}" if counts \
        else "0"
    ax.set_title(f"Success against the model's cube side: {label}\n"
                 f"n = {shown} episodes per point", fontsize=8)
    handles = [Line2D([], [], color=color, marker="o", label="success rate"),
               Line2D([], [], color=color, alpha=0.25, linewidth=6, label="Wilson 95 %"),
               Line2D([], [], color="k", linestyle="--", linewidth=0.8,
                      label=f"true side {true_side:g} m")]
    legend_outside(fig, handles)
    return fig


def _distribution_panel(ax: Axes, results: Sequence[ConfigurationResult], column: str,
                        label: str, scale: float, log: bool, ceiling: float,
                        seed: int) -> None:
    rng = np.random.default_rng(seed)
    drawn = 0
    for row, result in enumerate(results):
        values = scale * pd.to_numeric(result.rows.get(column, pd.Series(dtype=float)),
                                       errors="coerce").to_numpy(dtype=float)
        values = values[np.isfinite(values)]
        if not values.size:
            continue
        values = np.minimum(values, ceiling)
        if log:
            values = np.maximum(values, LOG_FLOOR)
        drawn += values.size
        color = group_color(result.group)
        ax.boxplot([values], positions=[row], **HORIZONTAL, widths=0.6, showfliers=False,
                   medianprops={"color": color}, boxprops={"color": color},
                   whiskerprops={"color": color}, capprops={"color": color})
        jitter = rng.uniform(-0.2, 0.2, values.size)
        ax.scatter(values, row + jitter, s=9, color=color, alpha=0.7, linewidths=0,
                   zorder=3)
    ax.set_yticks(range(len(results)), [r.title for r in results], fontsize=7)
    ax.set_ylim(len(results) - 0.5, -0.5)
    ax.set_xlabel(label, fontsize=8)
    if log:
        ax.set_xscale("log")
    ax.set_title(f"{label}\n{n_text(drawn, 'episodes')}", fontsize=8)


def plot_distributions(results: Sequence[ConfigurationResult], path: Path) -> Path:
    """:func:`distributions_figure` written to ``path``."""
    return _save(distributions_figure(results), path)


def distributions_figure(results: Sequence[ConfigurationResult]) -> MplFigure:
    """Box plots with the episodes as points of the metrics of :data:`DISTRIBUTIONS`, one
    row per configuration, one panel per metric (plan consistency and step time on log axes,
    values below :data:`LOG_FLOOR` drawn at it, plan gaps above :data:`PLAN_CEILING` at
    that)."""
    fig, axes = new_figure(len(DISTRIBUTIONS), 3.4, 0.3 * len(results) + 1.6,
                           max_columns=3)
    for index, (ax, (column, label, scale, log, ceiling)) in enumerate(
            zip(axes, DISTRIBUTIONS, strict=True)):
        _distribution_panel(ax, results, column, label, scale, log, ceiling, seed=index)
        if index % 3:
            ax.set_yticklabels([])
    legend_outside(fig, group_handles([r.group for r in results]), title="group")
    return fig
