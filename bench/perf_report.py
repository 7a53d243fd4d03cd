"""The report's section on ``c3bench perf``: the latest run of each machine, with the ratios
to ``c3plus-riccati`` and ``c3-osqp`` of the same run, the achieved GFLOP/s, the run's
matmul rate and the load average, then the compiled backend's targets over that machine's
recent runs (:func:`history_lines`) (:func:`perf_section`, which
:func:`bench.report.perf_report_section` returns)."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from c3bench.bench import perf_store, store
from c3bench.bench.gpu_perf import GPU_FIELDS, GPU_NUMBERS
from c3bench.bench.perf import PERF_FIGURE, REFERENCE_STEP_MS, TARGET_STEP_MS
from c3bench.bench.perf_store import CacheState
from c3bench.bench.perf_summary import format_ms, format_ratio, summarize
from c3bench.problems.errors import SchemaVersionError

CACHE_ORDER: tuple[str, ...] = (CacheState.WARM.value, CacheState.COLD.value)
"""Order of the cache states in the table and the targets."""

FAST_BACKENDS: tuple[str, ...] = ("c3plus-riccati", "c3plus-compiled", "c3plus-jax")
TABLE_HEADER: tuple[str, ...] = (
    "backend", "precision", "device", "samples", "cache", "n", "step ms", "p95 ms", "w/o weighting",
    "lcs", "weighting", "admm", "qp", "proj", "overhead", "GFLOP/s", "% matmul (run, best)",
    "t / riccati (step, admm)", "t / osqp (step, admm)", "load", "note")


def _at(summary: pd.DataFrame, backend: str, samples: int, column: str,
        precision: str = "float64") -> float:
    """``column`` of one configuration in ``summary`` (one cache state), NaN if absent."""
    rows = summary[(summary["backend"] == backend) & (summary["samples"] == samples)
                   & (summary["precision"] == precision) & (summary["repeats"] > 0)]
    return float(rows[column].iloc[0]) if len(rows) else math.nan


def _factor(value: float) -> str:
    """A speed-up as text: three significant digits, whole numbers from 1000 (no exponent)."""
    return f"{value:.0f}" if value >= 1000 else f"{value:.3g}"


def _verdict(ok: bool) -> str:
    return "met" if ok else "not met"


SPEEDUP_TARGETS: tuple[tuple[str, int, str, float], ...] = (
    ("ADMM", 16, "admm_ratio_riccati", 6.0), ("whole step", 16, "ratio_riccati", 4.0),
    ("ADMM", 1, "admm_ratio_riccati", 10.0))
"""The fast backends' speed-ups over ``c3plus-riccati`` in the same run: ``(what, samples,
summary column, at least)``."""
SHARE_TARGET = 0.25
"""The compiled ADMM's share of the matmul rate at 16 samples (:func:`_judged_share`)."""


def _speedup(summary: pd.DataFrame, backend: str, samples: int, column: str) -> float:
    """``backend``'s speed-up over ``c3plus-riccati`` (1 / the ratio column), NaN if absent."""
    return 1 / _at(summary, backend, samples, column)


def _judged_share(summary: pd.DataFrame, backend: str) -> float:
    """The ADMM's share of the matmul rate at 16 samples that the 25 % target is judged on: of
    the rate through the run, or of the best at the start for runs before perf layout 5."""
    share_run = _at(summary, backend, 16, "rate_share_run")
    return share_run if math.isfinite(share_run) else _at(summary, backend, 16, "rate_share")


def target_lines(summary: pd.DataFrame) -> list[str]:
    """The issue's targets (ratios within the run) for each fast backend measured at 16, in
    each cache state measured (:class:`bench.perf_store.CacheState`)."""
    lines = []
    for cache in CACHE_ORDER:
        rows = summary[summary["cache"] == cache]
        if len(rows):
            lines += _target_lines(rows, f"{cache} cache, ")
    return lines


def _target_lines(summary: pd.DataFrame, label: str) -> list[str]:
    """:func:`target_lines` of one cache state, each line starting ``- <label><backend>``."""
    lines = []
    for backend in FAST_BACKENDS:
        step16 = _at(summary, backend, 16, "median_ms")
        if not math.isfinite(step16):
            continue
        parts = [f"16 samples: step {format_ms(step16)} ms (<= {TARGET_STEP_MS:g} ms: "
                 f"{_verdict(step16 <= TARGET_STEP_MS)})"]
        if backend != "c3plus-riccati":
            for what, samples, column, factor in SPEEDUP_TARGETS:
                speedup = _speedup(summary, backend, samples, column)
                if math.isfinite(speedup):
                    parts.append(f"{what} at {samples}: {_factor(speedup)}x riccati (>= "
                                 f"{factor:g}x: {_verdict(speedup >= factor)})")
        for column, what in (("ratio_osqp", "whole step"), ("admm_ratio_osqp", "ADMM")):
            osqp = _at(summary, backend, 16, column)
            if math.isfinite(osqp):
                parts.append(f"{what} {_factor(1 / osqp)}x faster than c3-osqp (>= 1000x: "
                             f"{_verdict(1 / osqp >= 1000)})")
        with_w = _at(summary, backend, 16, "median_ms")
        without = _at(summary, backend, 16, "total_no_weighting_ms")
        if bool(_at(summary, backend, 16, "weighted") == 1) and without > 0:
            parts.append(f"weighting costs {with_w / without:.2f}x the step without it "
                         f"(<= 1.5x: {_verdict(with_w / without <= 1.5)})")
        step256 = _at(summary, backend, 256, "median_ms")
        if math.isfinite(step256):
            parts.append(f"256 samples cost {step256 / step16:.1f}x 16 samples (< 8x: "
                         f"{_verdict(step256 / step16 < 8)})")
        parts.extend(_share_parts(summary, backend))
        lines.append(f"- {label}{backend}: " + "; ".join(parts) + ".")
    return lines


def _table_row(s: pd.Series) -> str:
    jax = s["backend"] == "c3plus-jax"
    shares = [100 * s["rate_share_run"], 100 * s["rate_share"]]
    cells = [
        str(s["backend"]), str(s["precision"]), str(s["device"]), str(s["samples"]),
        str(s["cache"]), str(s["repeats"]), format_ms(s["median_ms"]), format_ms(s["p95_ms"]),
        format_ms(s["total_no_weighting_ms"]), format_ms(s["lcs_ms"]),
        format_ms(s["weighting_ms"]) if s["weighted"] else "-", format_ms(s["admm_ms"]),
        format_ms(s["qp_ms"]), "compiled" if jax else format_ms(s["proj_ms"]),
        format_ms(s["overhead_ms"]),
        f"{s['gflops']:.3g}" if math.isfinite(s["gflops"]) else "-",
        ", ".join(f"{share:.1f}" if math.isfinite(share) else "-" for share in shares),
        f"{format_ratio(s['ratio_riccati'])}, {format_ratio(s['admm_ratio_riccati'])}",
        f"{format_ratio(s['ratio_osqp'])}, {format_ratio(s['admm_ratio_osqp'])}",
        f"{s['load_avg']:.2f}" if math.isfinite(s["load_avg"]) else "-",
        "; ".join(filter(None, [
            str(s["note"] or ""), f"{s['failed']} failed" if s["failed"] else "",
            f"JIT {s['compile_s']:.2f} s, not timed" if math.isfinite(s["compile_s"]) else ""])),
    ]
    return "| " + " | ".join(cells) + " |"


def run_lines(frame: pd.DataFrame) -> list[str]:
    """The description, table, skipped configurations and targets of one run."""
    summary = summarize(frame)
    lines: list[str] = []
    if len(frame):
        first = frame.iloc[0]
        loads = frame["load_avg"].astype(float)
        rates = [f"{name} {_first(frame, column):.1f}" for name, column in (
            ("float64", "matmul_gflops_f64"), ("float32", "matmul_gflops_f32"))]
        through = _run_rates(frame)
        lines += [
            f"One C3+ control step as the closed loop runs it: LCS build for all samples, "
            f"for n > 1 the LCP-error sample weighting over the last 5 observed transitions "
            f"(when weighted), then {int(first['iterations'])} ADMM iterations (T = "
            f"{int(first['horizon'])}, planar, geometric rho); wall clock, warm-up excluded, "
            f"BLAS threads {int(frame['blas_threads'].max())}, cores {first['affinity']}, "
            f"host {first['host']}, run {first['run_id']}, 1-minute load average "
            f"{np.nanmin(loads):.2f}-{np.nanmax(loads):.2f}. Dense matmul rate of this run "
            f"(256 x 256, one thread): best of 15 at the start {', '.join(rates)} GFLOP/s"
            f"{through}. `% matmul`: GFLOP/s over the rate through the run (median against "
            "median) and over the best. `step` = LCS build + "
            "weighting + ADMM; `admm` = the controller's call alone (`qp` + `proj` + its "
            "overhead); GFLOP/s = the flops the backend executed in its ADMM / `admm` (the "
            "compiled kernel counts its own, which skip structural zeros; the flop model of "
            "bench/perf_flops.py for the numpy and JAX paths); "
            "`t / riccati`, `t / osqp` = median time over that of c3plus-riccati float64 and "
            "c3-osqp at the same samples and cache state in this run (below 1 is faster). "
            "`cache`: each round runs four consecutive steps of each backend in turn; `cold` "
            "is the first (it follows another backend's step, which has pushed this one's "
            "code and data out of the core's caches), `warm` the other three (they follow "
            "its own steps, as in a closed loop, where only the plant runs between control "
            "steps); small fast steps lose most when cold. The reference "
            f"study's step: {REFERENCE_STEP_MS:g} ms (16 samples).", ""]
    lines.append("| " + " | ".join(TABLE_HEADER) + " |")
    lines.append("|" + "|".join("---" for _ in TABLE_HEADER) + "|")
    timed = summary[summary["repeats"] > 0]
    timed = timed.assign(_order=timed["cache"].map(CACHE_ORDER.index)).sort_values(
        ["samples", "_order"], kind="stable")
    lines += [_table_row(s) for _, s in timed.iterrows()]
    skipped = summary[summary["repeats"] == 0]
    if len(skipped):
        notes: dict[str, list[str]] = {}
        for _, s in skipped.iterrows():
            label = f"{s['backend']} ({s['precision']}, {s['device']})"
            notes.setdefault(f"{label}: {s['note']}", []).append(str(s["samples"]))
        lines += ["", "Not measured: " + "; ".join(
            f"{text} (samples {', '.join(counts)})" for text, counts in notes.items()) + "."]
    lines.append("")
    checks = target_lines(summary)
    if checks:
        lines.extend(["Targets (ratios within this run):", "", *checks, ""])
    return lines


def _share_parts(summary: pd.DataFrame, backend: str) -> list[str]:
    """The ADMM's share of the matmul rate at 16 samples: of the rate through the run (median
    against median; the 25 % target of the compiled kernel is judged on it) and of the best at
    the start; runs before perf layout 5 have the second only, and it is judged."""
    share_run = _at(summary, backend, 16, "rate_share_run")
    share = _at(summary, backend, 16, "rate_share")
    judged = _judged_share(summary, backend)
    if not math.isfinite(judged):
        return []
    text = f"ADMM at {100 * judged:.1f} % of the matmul rate"
    if math.isfinite(share_run):
        text += " through the run"
    if backend == "c3plus-compiled":
        text += f" (>= {100 * SHARE_TARGET:g} %: {_verdict(judged >= SHARE_TARGET)})"
    if math.isfinite(share_run) and math.isfinite(share):
        text += f", {100 * share:.1f} % of its best at the start"
    return [text]


def _run_rates(frame: pd.DataFrame) -> str:
    """``; through its rounds (median) float64 41.0 (n=1), 40.2 (n=16), float32 ...`` or
    nothing (perf layouts before 5)."""
    parts = []
    for name, column in (("float64", "matmul_run_gflops_f64"),
                         ("float32", "matmul_run_gflops_f32")):
        per_samples = pd.to_numeric(frame[column], errors="coerce").groupby(
            frame["samples"]).median()
        values = [f"{rate:.1f} (n={samples})" for samples, rate in per_samples.items()
                  if math.isfinite(float(rate))]
        if values:
            parts.append(f"{name} {', '.join(values)}")
    return f"; through its rounds (median) {'; '.join(parts)} GFLOP/s" if parts else ""


def _first(frame: pd.DataFrame, column: str) -> float:
    values = pd.to_numeric(frame[column], errors="coerce").dropna()
    return float(values.iloc[0]) if len(values) else math.nan


HISTORY_RUNS = 6
"""Runs of one machine that :func:`history_lines` shows."""
HISTORY_BACKEND = "c3plus-compiled"
"""The backend whose targets :func:`history_lines` follows over the runs."""


def history_lines(stored: pd.DataFrame, host: str, runs: int = HISTORY_RUNS) -> list[str]:
    """The targets of :data:`HISTORY_BACKEND` over the last ``runs`` runs of ``host`` that
    timed it at 16 samples (warm steps where the run stores the cache state): a table with
    each run's ratios to ``c3plus-riccati`` (ADMM and whole step at 16 samples, ADMM at one)
    and its share of the matmul rate, and how many runs met each target. On a shared machine
    one run's verdict can be the machine's phase rather than the code (docs/admm.md), so
    the latest run alone does not settle a target near its threshold. Nothing when fewer
    than two such runs are stored."""
    frame = stored[stored["host"].astype(str) == host]
    timed = frame[(frame["backend"] == HISTORY_BACKEND) & (frame["samples"] == 16)
                  & ~frame["skipped"].astype(bool)]
    ids = sorted(timed["run_id"].astype(str).unique())[-runs:]
    if len(ids) < 2:
        return []
    names = [f"{what} at {samples}" for what, samples, _, _ in SPEEDUP_TARGETS]
    met = {name: [0, 0] for name in [*names, "% matmul"]}
    lines = [f"Recent runs on this machine: the last {len(ids)} that timed {HISTORY_BACKEND} "
             "at 16 samples (warm cache; each run with the code current when it ran), its "
             "speed-ups over c3plus-riccati and its share of the matmul rate through the run "
             "(of the best at the start for runs stored before perf layout 5); `process`: "
             "each configuration in a worker process of its own, or all in one (`shared`):",
             "", "| run | process | load | " + " | ".join(names) + " | % matmul |",
             "|---|---|---|" + "---|" * (len(names) + 1)]
    for run_id in ids:
        rows = frame[frame["run_id"].astype(str) == run_id]
        summary = summarize(rows)
        process = "/".join(sorted({value for value in rows["process"]
                                    if isinstance(value, str) and value})) or "-"
        if (summary["cache"] == CacheState.WARM.value).any():
            summary = summary[summary["cache"] == CacheState.WARM.value]
        cells = []
        for name, (_, samples, column, factor) in zip(names, SPEEDUP_TARGETS, strict=True):
            speedup = _speedup(summary, HISTORY_BACKEND, samples, column)
            cells.append(_count(met[name], speedup, factor, f"{speedup:.1f}x"))
        share = _judged_share(summary, HISTORY_BACKEND)
        cells.append(_count(met["% matmul"], share, SHARE_TARGET, f"{100 * share:.1f}"))
        load = _at(summary, HISTORY_BACKEND, 16, "load_avg")
        lines.append(f"| {run_id} | {process} | "
                     + (f"{load:.2f}" if math.isfinite(load) else "-")
                     + " | " + " | ".join(cells) + " |")
    thresholds = [f"{factor:g}x" for *_, factor in SPEEDUP_TARGETS] + [
        f"{100 * SHARE_TARGET:g} %"]
    counts = [f"{name} >= {threshold} in {met[name][0]} of {met[name][1]}"
              for name, threshold in zip(met, thresholds, strict=True) if met[name][1]]
    lines += ["", f"{HISTORY_BACKEND} met its targets in these runs: " + "; ".join(counts)
              + ".", ""]
    return lines


def _count(tally: list[int], value: float, threshold: float, text: str) -> str:
    """Add a finite ``value`` to ``tally`` (met, measured) against ``threshold``; its cell."""
    if not math.isfinite(value):
        return "-"
    tally[0] += value >= threshold
    tally[1] += 1
    return text


def perf_section(results_dir: str | Path, figure_link: str | None = None) -> str:
    """A Markdown section on the control-step time (reads ``<results_dir>/perf/``): the
    latest run of each machine, one table per machine (module docstring)."""
    try:
        stored = perf_store.read_perf(results_dir)
    except FileNotFoundError as error:
        return f"## Control-step time\n\n_No measurement: {error}._\n"
    frame = perf_store.latest_perf_runs(stored)
    lines = ["## Control-step time", ""]
    earlier = stored["run_id"].nunique() - frame["run_id"].nunique()
    if earlier:
        lines += [f"The latest run of each machine; {earlier} earlier run(s) are kept in "
                  f"`{store.PERF_DIR}/{store.PERF_RUNS}/` and `{store.PERF_DIR}/perf.csv`.",
                  ""]
    hosts = list(dict.fromkeys(frame["host"].astype(str)))
    for host in hosts:
        if len(hosts) > 1:
            lines += [f"### {host}", ""]
        lines += run_lines(frame[frame["host"].astype(str) == host])
        lines += history_lines(stored, host)
    link = figure_link or f"{store.PERF_DIR}/figures/{PERF_FIGURE}"
    lines += [f"![control-step time vs samples]({link})", ""]
    lines += gpu_lines(Path(results_dir) / store.PERF_DIR / "gpu")
    return "\n".join(lines)


def _number(value: Any) -> bool:
    """Whether ``value`` is a JSON number (not a boolean)."""
    return isinstance(value, int | float) and not isinstance(value, bool)


def gpu_rows(path: Path) -> list[dict[str, Any]]:
    """The rows of one GPU run file (one JSON object per line, each with
    :data:`bench.gpu_perf.GPU_FIELDS`, numbers where :data:`bench.gpu_perf.GPU_NUMBERS`).

    Raises
    ------
    SchemaVersionError
        A line is not JSON (a truncated copy), not an object, lacks a field or has text where
        a number belongs; the one-line message names the file and the line.
    """
    rows = []
    try:
        lines = path.read_text().splitlines()
    except UnicodeDecodeError as error:
        raise SchemaVersionError(f"{path}: damaged, not a c3bench GPU run ({error}); delete "
                                 f"it or measure again") from error
    for number, line in enumerate(lines, 1):
        if not line.strip():
            continue
        try:
            row = json.loads(line)
        except ValueError as error:
            raise SchemaVersionError(f"{path}: line {number} damaged, not a c3bench GPU row "
                                     f"({error}); delete it or measure again") from error
        if not isinstance(row, dict):
            missing = list(GPU_FIELDS)
        else:
            missing = [name for name in GPU_FIELDS if name not in row
                       or (name in GPU_NUMBERS and not _number(row[name]))]
        if missing:
            raise SchemaVersionError(f"{path}: line {number} is not a c3bench GPU row "
                                     f"(missing or not a number: {', '.join(missing)}); "
                                     f"delete it or measure again")
        rows.append(row)
    return rows


def gpu_lines(directory: Path) -> list[str]:
    """The GPU runs of ``python -m c3bench.bench.gpu_perf`` stored under ``directory``
    (``*.jsonl``): ADMM time per backend, device and samples, with each row's ratio to the
    compiled CPU kernel of the same run, precision and samples."""
    runs = sorted(directory.glob("*.jsonl")) if directory.is_dir() else []
    if not runs:
        return []
    lines = ["### GPU", "",
             "ADMM of one control step (10 iterations, warm-started, LCS batches exported from "
             "this machine), measured on a lent GPU machine by `python -m c3bench.bench."
             "gpu_perf`; the CPU rows are that machine's cores (JAX multi-threaded, the compiled "
             "kernel on one thread), so compare within a run.", ""]
    for path in runs:
        rows = gpu_rows(path)
        compiled = {(r["precision"], r["samples"]): r["admm_ms_median"] for r in rows
                    if r["backend"] == "c3plus-compiled"}
        lines += [f"`{path.name}`", "",
                  "| backend | device | kind | precision | samples | ADMM ms (median) | p95 | "
                  "t / compiled CPU | load |", "|---|---|---|---|---|---|---|---|---|"]
        for r in rows:
            base = compiled.get((r["precision"], r["samples"]), math.nan)
            lines.append(f"| {r['backend']} | {r['device']} | {r['device_kind']} | "
                         f"{r['precision']} | {r['samples']} | {r['admm_ms_median']:.3g} | "
                         f"{r['admm_ms_p95']:.3g} | {r['admm_ms_median'] / base:.3g} | "
                         f"{r['load_avg']:.2f} |")
        lines.append("")
    return lines
