"""The figure of ``c3bench perf``: control-step time and ratios against the number of samples.

Conventions of every figure (:mod:`bench.palette`): one fixed colour and marker per backend
(its position in :data:`bench.perf.BACKENDS`, so the colour never depends on which backends a
run measured), float32 dashed, cache-cold steps hollow and faded beside the warm ones, one
legend to the right of the panels (never on the data), ``n = ...`` timed steps in every
panel's title.
"""

from __future__ import annotations

import math
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
import pandas as pd
from matplotlib.axes import Axes
from matplotlib.lines import Line2D

from c3bench.bench import perf_store
from c3bench.bench.palette import legend_outside, solver_style
from c3bench.bench.perf import BACKENDS, REFERENCE_STEP_MS, TARGET_STEP_MS
from c3bench.bench.perf_store import CacheState
from c3bench.bench.perf_summary import summarize

PANELS: tuple[tuple[str, str], ...] = (
    ("median_ms", "whole control step [ms]\n(median; bar to p95)"),
    ("ratio_riccati", "whole step / c3plus-riccati float64"),
    ("admm_ratio_riccati", "ADMM alone / c3plus-riccati float64"),
)


def _summary(frame: pd.DataFrame) -> pd.DataFrame:
    """The measured configurations of the latest run of each machine."""
    latest = perf_store.latest_perf_runs(frame)
    if latest.empty:
        return pd.DataFrame()
    summary = summarize(latest)
    return summary[summary["repeats"] > 0].reset_index(drop=True)


def _n_range(summary: pd.DataFrame, column: str) -> str:
    counts = summary[np.isfinite(summary[column].astype(float))]["repeats"].astype(int)
    if counts.empty:
        return "0"
    low, high = int(counts.min()), int(counts.max())
    return str(low) if low == high else f"{low}-{high}"


COLD_ALPHA = 0.45
"""Opacity of the cache-cold curves (hollow markers); warm ones are opaque, filled."""


def _draw(ax: Axes, summary: pd.DataFrame, column: str, hosts: list[str]) -> None:
    for (host, backend, precision, device, cache), group in summary.groupby(
            ["host", "backend", "precision", "device", "cache"], sort=False):
        group = group.sort_values("samples")
        values = group[column].to_numpy(dtype=float)
        if not np.isfinite(values).any():
            continue
        style = solver_style(str(backend), BACKENDS)
        marker = style.marker if len(hosts) == 1 else "osD^v"[hosts.index(str(host)) % 5]
        linestyle = "--" if precision == "float32" else "-"
        if device == "gpu":
            linestyle = ":"
        errors = None
        if column == "median_ms":
            upper = group["p95_ms"].to_numpy(dtype=float) - values
            errors = [np.zeros_like(upper), upper]
        cold = cache == CacheState.COLD
        ax.errorbar(group["samples"], values, yerr=errors, color=style.color, marker=marker,
                    linestyle=linestyle, capsize=3, markersize=4, linewidth=1,
                    alpha=COLD_ALPHA if cold else 1.0,
                    markerfacecolor="none" if cold else style.color)


def _counts(group: pd.DataFrame) -> str:
    """Timed steps per point of one backend's curves, by cache state (``12 cold, 36 warm``)."""
    parts = []
    for cache in (CacheState.COLD, CacheState.WARM):
        rows = group[group["cache"] == cache]
        if len(rows):
            parts.append(f"{int(rows['repeats'].min())} {cache}")
    return ", ".join(parts) if parts else str(int(group["repeats"].min()))


def _handles(summary: pd.DataFrame, hosts: list[str]) -> list[Line2D]:
    handles = []
    for (host, backend, precision, device), group in summary.groupby(
            ["host", "backend", "precision", "device"], sort=False):
        style = solver_style(str(backend), BACKENDS)
        marker = style.marker if len(hosts) == 1 else "osD^v"[hosts.index(str(host)) % 5]
        machine = f", {str(host).split(' (')[0]}" if len(hosts) > 1 else ""
        handles.append(Line2D([], [], color=style.color, marker=marker, markersize=4,
                              linestyle="--" if precision == "float32" else "-",
                              label=f"{backend} ({precision}, {device}{machine}), "
                                    f"n = {_counts(group)}"))
    caches = set(summary["cache"].astype(str))
    if CacheState.WARM in caches:
        handles.append(Line2D([], [], color="grey", marker="o", linestyle="-", markersize=4,
                              label="warm cache (follows its own step): filled"))
    if CacheState.COLD in caches:
        handles.append(Line2D([], [], color="grey", marker="o", linestyle="-", markersize=4,
                              markerfacecolor="none", alpha=COLD_ALPHA,
                              label="cold cache (follows another backend's step): hollow"))
    handles.append(Line2D([], [], color="grey", linestyle="--", linewidth=1,
                          label=f"seed: {REFERENCE_STEP_MS:g} ms (16 samples)"))
    handles.append(Line2D([], [], color="grey", linestyle=":", linewidth=1,
                          label=f"target: {TARGET_STEP_MS:g} ms (16 samples)"))
    return handles


def plot_perf(frame: pd.DataFrame, path: Path) -> Path | None:
    """Median control-step time and its ratios to ``c3plus-riccati`` against the number of
    samples (log-log), latest run of each machine; ``None`` when nothing was measured.

    ``frame`` holds the rows of ``c3bench perf`` (:data:`bench.perf_store.PERF_SCHEMA`), of one
    or more runs. Panels: the whole step (LCS build + weighting + ADMM) with p95 bars and the
    reference study's 60 ms and the 6 ms target as lines; the whole step's and the ADMM's
    time over ``c3plus-riccati`` float64 at the same samples in the same run (1 = as fast).
    """
    summary = _summary(frame)
    if summary.empty:
        return None
    hosts = list(dict.fromkeys(summary["host"].astype(str)))
    figure, axes = plt.subplots(1, len(PANELS), figsize=(14.0, 4.4), layout="constrained")
    ticks = sorted(int(n) for n in summary["samples"].unique())
    for ax, (column, label) in zip(axes, PANELS, strict=True):
        _draw(ax, summary, column, hosts)
        if column == "median_ms":
            ax.axhline(REFERENCE_STEP_MS, color="grey", linestyle="--", linewidth=1)
            ax.axhline(TARGET_STEP_MS, color="grey", linestyle=":", linewidth=1)
            title = "C3+ control step"
        else:
            ax.axhline(1.0, color="black", linewidth=0.8)
            title = "ratio to c3plus-riccati (same run)"
        ax.set_xscale("log", base=2)
        ax.set_yscale("log")
        ax.set_xticks(ticks, [str(n) for n in ticks])
        ax.minorticks_off()
        ax.set_xlabel("model samples n (cube sides l ~ U[0.27, 0.33])")
        ax.set_ylabel(label)
        ax.grid(True, which="both", alpha=0.3)
        ax.set_title(f"{title}\nn = {_n_range(summary, column)} timed steps per point",
                     fontsize=8)
    first = summary.iloc[0]
    loads = summary["load_avg"].astype(float)
    load = f"{np.nanmax(loads):.2f}" if np.isfinite(loads).any() else "?"
    figure.suptitle(f"LCS build + weighting + {int(_first_int(frame, 'iterations'))} ADMM "
                    f"iterations, T = {_first_int(frame, 'horizon')}, one core; run "
                    f"{first['run_id']}, load <= {load}", fontsize=9)
    legend_outside(figure, _handles(summary, hosts))
    path.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(path, dpi=120)
    plt.close(figure)
    return path


def _first_int(frame: pd.DataFrame, column: str) -> int:
    values = pd.to_numeric(frame[column], errors="coerce").dropna()
    return int(values.iloc[0]) if len(values) and math.isfinite(values.iloc[0]) else 0
