"""Summaries of ``c3bench perf`` rows: medians per configuration, the achieved GFLOP/s and its
share of the run's matmul rate, and the ratios to other backends of the same run.

Configurations are summarised per cache state (``cache``, :class:`bench.perf_store.CacheState`:
``cold`` steps follow another configuration's, ``warm`` ones their own).

**Ratios** (:func:`add_ratios`): per run, host, cache state and number of samples,
``ratio_riccati = median / median(c3plus-riccati, float64)`` and ``ratio_osqp =
median / median(c3-osqp)`` of the whole step (``total_ms``), and ``admm_ratio_*`` the same of
the ADMM alone (``admm_ms``); below 1 is faster. NaN when the reference configuration was
not measured in that run: machines differ by 2-4x, so only ratios within one run compare.

**Rate**: ``gflops = admm_mflop_executed / median admm_ms`` (MFLOP per ms is GFLOP/s; the
flops the backend executed: the compiled kernel's own count, the flop model of
:mod:`bench.perf_flops` for the numpy and JAX paths; NaN in perf layouts before 3, which
stored the model's flops only), ``rate_share = gflops / matmul rate`` of the row's precision
measured at the start of the same run (its best of 15: the machine's peak) and
``rate_share_run = gflops / matmul_run_gflops``, the rate measured through the same run's
rounds (median over the rounds, :class:`bench.perf_flops.MatmulProbe`): median against
median, so a slow phase of the machine divides out (NaN in perf layouts before 5).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np
import pandas as pd

CONFIG_KEYS: tuple[str, ...] = ("backend", "precision", "device", "samples", "cache")
RUN_KEYS: tuple[str, ...] = ("run_id", "host")
RATIO_REFERENCES: dict[str, tuple[str, str]] = {"riccati": ("c3plus-riccati", "float64"),
                                                "osqp": ("c3-osqp", "float64")}
"""Name of each ratio: (backend, precision) of its denominator."""
MEDIAN_COLUMNS: tuple[str, ...] = (
    "lcs_ms", "weighting_ms", "admm_ms", "qp_ms", "proj_ms", "overhead_ms",
    "total_no_weighting_ms", "cpu_ms")


def _p95(values: Sequence[float]) -> float:
    """The 95th percentile (NaN for no values)."""
    return float(np.percentile(np.asarray(values, dtype=float), 95)) if len(values) else math.nan


def _median(series: pd.Series) -> float:
    values = pd.to_numeric(series, errors="coerce").astype(float)
    return float(values.median()) if values.notna().any() else math.nan


def _notes(group: pd.DataFrame) -> str:
    return "; ".join(sorted(set(group["note"].astype(str)) - {""}))


def _record(group: pd.DataFrame) -> dict[str, Any]:
    """The summary of one configuration's rows."""
    timed = group[~group["skipped"].astype(bool)]
    record: dict[str, Any] = {"repeats": len(timed), "note": _notes(timed if len(timed)
                                                                     else group)}
    record["load_avg"] = _median(group["load_avg"])
    suffix = "f32" if str(group["precision"].iloc[0]) == "float32" else "f64"
    for name in ("matmul_gflops", "matmul_run_gflops"):  # the row precision's rate
        record[name] = _median(group[f"{name}_{suffix}"])
    record["compile_s"] = _median(group["compile_s"])
    if timed.empty:
        record.update({name: math.nan for name in (
            "median_ms", "p95_ms", *MEDIAN_COLUMNS, "overhead_fraction", "admm_mflop",
            "admm_mflop_executed", "gflops", "rate_share", "rate_share_run")}, failed=0,
            weighted=False)
        return record
    median = _median(timed["total_ms"])
    record.update(median_ms=median, p95_ms=_p95(timed["total_ms"].astype(float).tolist()))
    record.update({name: _median(timed[name]) for name in MEDIAN_COLUMNS})
    record["overhead_fraction"] = record["overhead_ms"] / median if median > 0 else math.nan
    record["failed"] = int((~timed["ok"].astype(bool)).sum())
    record["weighted"] = bool(timed["weighted"].astype(bool).any())
    executed = _median(timed["admm_mflop_executed"])
    admm = record["admm_ms"]
    record["admm_mflop"] = _median(timed["admm_mflop"])
    record["admm_mflop_executed"] = executed
    record["gflops"] = executed / admm if admm > 0 else math.nan
    for share, rate in (("rate_share", record["matmul_gflops"]),
                        ("rate_share_run", record["matmul_run_gflops"])):
        record[share] = record["gflops"] / rate if rate > 0 else math.nan
    return record


def summarize(frame: pd.DataFrame) -> pd.DataFrame:
    """Per run, host and (backend, precision, device, samples): repeats, median and p95 of
    the whole step, medians of its parts (LCS build, weighting, ADMM, QP, projection,
    overhead, the step without weighting, CPU time), failed steps, the flop model's MFLOP,
    the achieved GFLOP/s, the matmul rate and share, the compile seconds, the load average
    and the ratios of :func:`add_ratios`."""
    keys = [*RUN_KEYS, *CONFIG_KEYS]
    out = []
    for key, group in frame.groupby(keys, sort=False):
        out.append({**dict(zip(keys, key, strict=True)), **_record(group)})
    if not out:
        return pd.DataFrame(columns=[*keys, "repeats", "median_ms", "admm_ms"])
    return add_ratios(pd.DataFrame(out))


def add_ratios(summary: pd.DataFrame) -> pd.DataFrame:
    """``summary`` with ``ratio_<name>`` (median / reference median) and
    ``admm_ratio_<name>`` (ADMM alone) for each of :data:`RATIO_REFERENCES`, within each run
    and host at the same number of samples and cache state; NaN where the reference was not
    measured."""
    summary = summary.copy()
    for name, (backend, precision) in RATIO_REFERENCES.items():
        for column, target in (("median_ms", f"ratio_{name}"), ("admm_ms", f"admm_ratio_{name}")):
            values = []
            for _, row in summary.iterrows():
                match = summary[(summary["run_id"] == row["run_id"])
                                & (summary["host"] == row["host"])
                                & (summary["backend"] == backend)
                                & (summary["precision"] == precision)
                                & (summary["samples"] == row["samples"])
                                & (summary["cache"] == row["cache"])
                                & (summary["repeats"] > 0)]
                reference = float(match[column].iloc[0]) if len(match) else math.nan
                mine = float(row[column]) if row["repeats"] > 0 else math.nan
                values.append(mine / reference if reference > 0 else math.nan)
            summary[target] = values
    return summary


# --- text -------------------------------------------------------------------------------------
def format_ms(value: float) -> str:
    """Milliseconds as text: one decimal from 10 ms, two below, ``-`` when not finite."""
    if not math.isfinite(value):
        return "-"
    return f"{value:.1f}" if value >= 10 else f"{value:.2f}"


def format_ratio(value: float) -> str:
    """A time ratio with three significant digits, ``-`` when not finite."""
    return f"{value:.3g}" if math.isfinite(value) else "-"


def format_rate(gflops: float, share: float, share_run: float = math.nan) -> str:
    """``1.23 GFLOP/s (5.2 % of matmul through the run, 4.5 % of its best)``, ``1.23 GFLOP/s
    (4.5 % of matmul)`` without the rate through the run, or ``-``."""
    if not math.isfinite(gflops):
        return "-"
    text = f"{gflops:.3g} GFLOP/s"
    if math.isfinite(share_run):
        best = f", {100 * share:.1f} % of its best" if math.isfinite(share) else ""
        return text + f" ({100 * share_run:.1f} % of matmul through the run{best})"
    return text + (f" ({100 * share:.1f} % of matmul)" if math.isfinite(share) else "")


def format_summary_line(s: pd.Series) -> str:
    """One printed line of a summary row."""
    head = f"{s['backend']:<15} {s['precision']:<8} {s['device']:<4} samples={s['samples']:<5}"
    if s["repeats"] == 0:
        return f"{head} skipped: {s['note']}"
    jax = s["backend"] == "c3plus-jax"
    weighting = f"weighting {format_ms(s['weighting_ms'])}  " if s["weighted"] else ""
    text = (f"{head} {s['cache']:<4} step median {format_ms(s['median_ms'])} ms (p95 "
            f"{format_ms(s['p95_ms'])})  "
            f"w/o weighting {format_ms(s['total_no_weighting_ms'])}  "
            f"lcs {format_ms(s['lcs_ms'])}  {weighting}admm {format_ms(s['admm_ms'])} "
            f"({'qp+proj' if jax else 'qp'} {format_ms(s['qp_ms'])}, proj "
            f"{'(compiled)' if jax else format_ms(s['proj_ms'])})  overhead "
            f"{format_ms(s['overhead_ms'])}  cpu {format_ms(s['cpu_ms'])}  "
            f"{format_rate(s['gflops'], s['rate_share'], s['rate_share_run'])}  "
            f"t/riccati {format_ratio(s['ratio_riccati'])} (admm "
            f"{format_ratio(s['admm_ratio_riccati'])})  t/osqp {format_ratio(s['ratio_osqp'])} "
            f"(admm {format_ratio(s['admm_ratio_osqp'])})  load {s['load_avg']:.2f}  "
            f"(n={s['repeats']}{', failed ' + str(s['failed']) if s['failed'] else ''})")
    if math.isfinite(s["compile_s"]):
        text += f"  [JIT compile {s['compile_s']:.2f} s, not timed]"
    if s["note"]:
        text += f"  [{s['note']}]"
    return text


def format_line(rows: pd.DataFrame) -> str:
    """The printed lines of the configurations in ``rows`` (:func:`format_summary_line`)."""
    return "\n".join(format_summary_line(s) for _, s in summarize(rows).iterrows())
