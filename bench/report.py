"""Markdown report of a suite: ``results/<suite>/report.md`` and ``figures/*.png``.

Layout (in the spirit of qpbenchmark's reports): header with the machine and versions; how
success and the aggregates are defined; the solver table; the references; a success overview;
one table per (family, variant, settings, precision, start); the controller-sequence tables
(:mod:`bench.report_sequence`: ``sequence`` cells are kept out of every other section); the
cells whose solver claimed a wrong solution; the share of QP cells within the control budget;
failures; figures with one caption line each (or a note saying why a figure has no data).
Tables are sorted and numbers formatted with fixed rules (:func:`bench.tables.fmt`) so the
file diffs well between runs.
"""

from __future__ import annotations

import datetime as dt
import re
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from c3bench.bench import store
from c3bench.bench.budgets import budget_seconds
from c3bench.bench.metrics import (
    DUAL_FAMILIES,
    LOG_FLOOR,
    TIME_SHIFT,
    aggregate,
    family_label,
    ranked_time_label,
    required_residuals,
    unverified_cells,
)
from c3bench.bench.perf import (
    PERF_FIGURE,
)
from c3bench.bench.plots import all_figures, ordered_settings
from c3bench.bench.reference import AGREE_COST, REFERENCE_PLANS, load_references, summarise
from c3bench.bench.report_accuracy import budget_section, claimed_wrong_section, unverified_note
from c3bench.bench.report_sequence import other_rows, sequence_section
from c3bench.bench.report_why import why_slow_section
from c3bench.bench.tables import NOT_RUN, fmt, fmt_accuracy, markdown_table
from c3bench.problems.errors import SchemaVersionError
from c3bench.problems.names import QP_FAMILIES, Precision, Start

__all__ = ["build_report", "family_table", "fmt", "markdown_table", "perf_report_section",
           "reason_kind", "write_report"]

# (header, aggregate column, format kind) of the per-family tables; kind "acc" is an accuracy
# mean shown in bold above the tolerance
TABLE_COLUMNS: tuple[tuple[str, str, str], ...] = (
    ("solver", "solver", "text"),
    ("cells", "cells", "int"),
    ("success", "success_rate", "percent"),
    ("unverified", "unverified", "int"),
    ("time sgm (ms)", "time_sgm", "ms"),
    ("time rel.", "time_rel", "rel"),
    ("setup sgm (ms)", "setup_sgm", "ms"),
    ("primal (rel.)", "primal_sgm", "acc"),
    ("dual (rel.)", "dual_sgm", "acc"),
    ("gap (rel.)", "gap_sgm", "acc"),
    ("compl.", "complementarity_sgm", "acc"),
    ("cost error", "cost_error_sgm", "acc"),
    ("worst (rel.)", "worst_sgm", "acc"),
    ("iters (median)", "iterations_median", "num"),
    ("time/iter (us)", "time_per_iteration", "us"),
    ("cond(S) raw", "cond_schur_raw_median", "sci"),
    ("cond(S) eq.", "cond_schur_equilibrated_median", "sci"),
)


def _cell(record: dict[str, Any], column: str, kind: str) -> str:
    if kind == "acc":
        return fmt_accuracy(record[column], float(record["tolerance"]))
    return fmt(record[column], kind)


def family_table(summary: pd.DataFrame, not_run: list[str] | None = None) -> str:
    """The aggregate table of one (family, variant, settings, precision, start) group, with
    a *not run* row for each solver in ``not_run``."""
    rows = [[_cell(record, column, kind) for _, column, kind in TABLE_COLUMNS]
            for record in summary.sort_values("solver").to_dict("records")]
    blank = ["-"] * (len(TABLE_COLUMNS) - 2)
    rows += [[fmt(solver, "text"), NOT_RUN, *blank] for solver in sorted(not_run or [])]
    rows.sort(key=lambda row: row[0])
    return markdown_table([header for header, _, _ in TABLE_COLUMNS], rows)


def _header(info: dict[str, Any], frame: pd.DataFrame) -> list[str]:
    packages = info.get("packages", {})
    rows = [
        ["last run started (UTC)", info.get("date", "-")],
        ["CPU", f"{info.get('cpu', '-')} ({info.get('cores', '-')} cores)"],
        ["host", info.get("host", "-")],
        ["platform", info.get("platform", "-")],
        ["Python", info.get("python", "-")],
        ["packages", ", ".join(f"{k} {v}" for k, v in sorted(packages.items())) or "-"],
        ["BLAS threads", f"{info.get('blas_threads_timed', 1)} during timed solves "
                         f"(pinned with threadpoolctl); library default "
                         f"{info.get('blas_threads_default', '-')}"],
        ["executor", _executor(info, frame)],
        ["timing", _timing(frame)],
        ["cells stored", str(len(frame))],
        ["hosts in rows", ", ".join(sorted(set(frame["host"]))) or "-"],
    ]
    return [markdown_table(["", ""], [[fmt(a, "text"), fmt(b, "text")] for a, b in rows],
                           "ll"),
            "Machine, versions and executor: `run_info.json`, which every run rewrites (even "
            "one that stores no cell); timing and hosts: the stored rows.\n"]


def _distinct(values: pd.Series, unit: str = "") -> str:
    """Every distinct value of ``values`` (ascending), with its cell count when they differ."""
    counts = values.value_counts().sort_index()
    return ", ".join(f"{value:g}{unit}" + (f" ({count} cells)" if len(counts) > 1 else "")
                     for value, count in counts.items())


def _timing(frame: pd.DataFrame) -> str:
    """Timed repeats and time limits of the stored rows (not of the last run: a run that
    stores nothing still rewrites ``run_info.json``)."""
    if frame.empty:
        return "-"
    sequence = frame["start"] == Start.SEQUENCE
    limits = []
    if (~sequence).any():
        limits.append(f"time limit {_distinct(frame.loc[~sequence, 'time_limit'], ' s')} per "
                      "solve")
    if sequence.any():
        limits.append(f"sequence cells: {_distinct(frame.loc[sequence, 'time_limit'], ' s')} "
                      "per ADMM run")
    return (f"{_distinct(frame['repeats'])} timed repeats after 1 untimed warm-up, median; "
            + "; ".join(limits))


def _executor(info: dict[str, Any], frame: pd.DataFrame) -> str:
    """The last run's executor (``run_info.json``), attributed to the stored rows only when
    every one of them finished during that run (just the executor when none is stored)."""
    if not info:
        return "-"
    what = (f"Dask scheduler {info['scheduler']}" if info.get("scheduler")
            else f"local process pool, {info.get('jobs', '-')} workers")
    if frame.empty:  # no stored cell to attribute
        return what
    started = pd.to_datetime(str(info.get("date", "")), utc=True, errors="coerce")
    if pd.isna(started):
        return f"{what} (the last run's; its start time is unknown)"
    finished = pd.to_datetime(frame["finished_at"], utc=True, errors="coerce", format="ISO8601")
    ours = int((finished >= started).sum())
    if ours == len(frame):
        return what
    return f"{what} (the last run's: {ours} of the {len(frame)} stored cells finished in it)"


def _method() -> str:
    dual = ", ".join(f"`{f}`" for f in DUAL_FAMILIES)
    families = sorted(set(REFERENCE_PLANS) | set(DUAL_FAMILIES))
    checks = "; ".join(f"`{f}`: " + ", ".join(required_residuals(f)) for f in families)
    time = ranked_time_label()
    return (
        "A cell is one (instance, solver, settings, precision, start). **Success** = the "
        "solver found a solution *and* every residual its family requires is at most the "
        f"profile's tolerance ({checks}); *relative* residuals are r / max(1, size of their "
        "terms) (solvers.residuals: the instances have gradients up to 4e5); duals are "
        f"checked only for {dual} (projection and mpcc are mixed-integer programs without a "
        "dual certificate); and, where a verified reference optimum f* exists, the cost error "
        "|f - f*| / max(1, |f*|) is at most max(tolerance, reference spread); projection "
        "and mpcc (no certificate of optimality) also need that verified f*, and a cell of "
        "theirs that passes every residual check without one is counted apart as "
        "*unverified*, never as a success. The solver's own status is never enough.\n\n"
        f"**Ranked time**: every ranking (time columns, performance profiles, Pareto plots, "
        f"budgets, `compare`) uses the {time} = setup + solve, which means what a caller "
        "pays in the cell's start mode: setup (conversion, structure analysis, "
        "factorisation, solver object construction) and solve are split by one contract for "
        "every backend (solvers.timing). `cold`: a fresh solver object, setup + solve (inside "
        "C3 / C3+ the QP matrices change with rho at every ADMM iteration, so a controller "
        "pays both). `warm`: what a solver pays when only the vectors change: the solver "
        "object is set up on the instance's matrices untimed, then the solver's own update "
        "API takes q, b, h and the bounds (the row's setup time) and it solves from the "
        "previous ADMM iterate's answer (solve time); a backend without an update API pays "
        "setup + solve with that guess (warm emulated). Which backend does what:\n\n"
        f"{_warm_lines()}\n\n"
        f"**Aggregates**: time is the shifted geometric mean exp(mean(log(t + s))) - s of the "
        f"{time} with shift s = {TIME_SHIFT:g} s ({TIME_SHIFT * 1e3:g} ms), failures counted "
        "at the time limit (as qpbenchmark does); *time rel.* divides by the best solver of "
        "the same table. *Setup* is the setup part of the ranked time alone, shifted "
        "geometric mean over all cells. Accuracy columns "
        "(primal, dual, gap: relative; compl.; cost error) are plain geometric means "
        "exp(mean(log(v))) of the **actual** values over the cells where they are finite, "
        f"not floored at the tolerance; only exact zeros are raised to {LOG_FLOOR:g} to take "
        "the logarithm (a column of zeros is shown as 0; a mean far below machine precision "
        "means some cells were exactly zero). Values above the table's tolerance are in "
        "**bold**. "
        "*worst* is the same mean of each cell's largest required figure (the accuracy of "
        "the accuracy profiles, Pareto plots and `compare`). Iterations and time per "
        "iteration are medians over successful cells; cond(S) columns are medians.\n\n"
        "**Variants**: projection instances belong to one ADMM variant (c3 or c3plus); "
        "tables and figures split them, and a solver that takes one variant only is "
        f"marked *{NOT_RUN}* on the other instead of failing there.\n"
    )


def _warm_lines() -> str:
    """One bullet per QP backend: what its warm cells measure (``warm_support``)."""
    from c3bench.solvers import registry
    from c3bench.solvers.timing import WARM_EMULATED, warm_support

    notes = {name: warm_support(backend) for name, backend in registry.backends().items()
             if set(backend.families) & set(QP_FAMILIES)}
    native = [f"- `{name}`: {note}" for name, note in sorted(notes.items())
              if note != WARM_EMULATED]
    emulated = sorted(name for name, note in notes.items() if note == WARM_EMULATED)
    if emulated:
        native.append(f"- warm emulated (no update API): {', '.join(emulated)}")
    return "\n".join(native)


def _solver_table(info: dict[str, Any], frame: pd.DataFrame) -> str:
    table = info.get("solver_table")
    if not table:
        from c3bench.solvers import registry

        table = [{"name": r.name, "available": r.available, "reason": r.reason,
                  "version": r.version, "families": list(r.families),
                  "precisions": list(r.precisions)} for r in registry.available()]
    counts = frame.groupby("solver").size().to_dict()
    notes = _solver_notes()
    rows = []
    for entry in sorted(table, key=lambda e: e["name"]):
        rows.append([fmt(entry["name"], "text"), fmt(entry["version"], "text"),
                     "yes" if entry["available"] else "no",
                     fmt(entry["reason"] or "-", "text"),
                     ", ".join(entry["families"]) or "-", ", ".join(entry["precisions"]),
                     str(counts.get(entry["name"], 0)),
                     fmt(notes.get(entry["name"], "") or "-", "text")])
    return markdown_table(["solver", "version", "available", "reason", "families",
                           "precisions", "cells", "note"], rows, "llllllrl")


def _solver_notes() -> dict[str, str]:
    """Each registered backend's one-line description (what it is and, where it stays slow
    or inaccurate, why)."""
    from c3bench.solvers import registry

    return {name: backend.description for name, backend in registry.backends().items()}


def _reference_table(paths: store.SuitePaths) -> str:
    references = load_references(paths.references)
    if not references:
        return "No references were computed (no cost errors: success by residuals only).\n"
    rows = []
    for entry in summarise(references):
        rows.append([entry.family, fmt(entry.plan, "text"), str(entry.instances),
                     str(entry.available), fmt(entry.max_spread, "sci"),
                     fmt("; ".join(entry.reasons) or "-", "text")])
    text = markdown_table(["family", "reference", "instances", "verified f*", "max spread",
                           "why not"], rows, "llrrrl")
    return text + ("\nA reference optimum f* is accepted only when the reference and its "
                   "cross-check (both at high_accuracy) pass their residual test and agree: "
                   "spread |f*_ref - f*_check| / max(1, |f*|) at most "
                   f"{AGREE_COST:g}. Instances without a verified f* have NaN cost errors and "
                   "`verified = False`; convex families are then judged by residuals, duals "
                   "and gap alone, while a projection / mpcc cell is never a success: passing "
                   "every residual check it is counted as *unverified* (feasible, optimality "
                   "not verified).\n")


def _overview(summary: pd.DataFrame) -> str:
    base = summary[(summary["precision"] == Precision.FLOAT64) & (summary["start"] == Start.COLD)]
    if base.empty:
        return "No cold-start float64 cells.\n"
    profiles = ordered_settings(base)
    parts = []
    for (family, variant), mine in base.groupby(["family", "variant"], sort=True):
        solvers = set(base.loc[base["family"] == family, "solver"])
        rows = []
        for solver in sorted(solvers):
            row = [solver]
            for profile in profiles:
                hit = mine[(mine["solver"] == solver) & (mine["settings"] == profile)]
                row.append(_rate_text(hit) if len(hit) else NOT_RUN)
            rows.append(row)
        parts.append(f"**{family_label(str(family), str(variant))}** (success rate, cold "
                     "start, float64; *+n unverified*: feasible cells without a verified "
                     "optimum, not counted as successes)\n\n"
                     + markdown_table(["solver", *profiles], rows))
    return "\n".join(parts)


def _rate_text(hit: pd.DataFrame) -> str:
    """Success rate of one aggregate row, with its unverified cells counted apart."""
    text = fmt(hit["success_rate"].iloc[0], "percent")
    unverified = int(hit["unverified"].iloc[0])
    return f"{text} (+{unverified} unverified)" if unverified else text


def reason_kind(verdict: str) -> list[str]:
    """The kinds of failure in a verdict, without numbers: ``dual_residual > tol`` for each
    residual over tolerance, ``X unavailable``, or the failure category of an unsolved cell."""
    parts = [part.strip() for part in str(verdict).split(";") if part.strip()]
    residual = re.compile(r"^(\w+) (\S+ > \S+|unavailable)$")
    if parts and all(residual.match(part) for part in parts):
        kinds = []
        for part in parts:
            name, rest = residual.match(part).groups()  # type: ignore[union-attr]
            kinds.append(f"{name} unavailable" if rest == "unavailable" else f"{name} > tol")
        return kinds
    return [str(verdict).split(":")[0].strip()[:60] or "unknown"]


def _failures(frame: pd.DataFrame) -> str:
    """Failed cells per family and solver; unverified cells (feasible, optimality not
    verified) are not failures and are counted apart below the table."""
    unverified = unverified_cells(frame)
    failed = frame[~frame["success"].to_numpy(dtype=bool) & ~unverified]
    apart = unverified_note(frame[unverified], "failures")
    if failed.empty:
        return f"No cell failed. {apart}" if apart else "Every cell succeeded.\n"
    rows = []
    for (family, solver), group in failed.groupby(["family", "solver"], sort=True):
        kinds = pd.Series([k for v in group["verdict"] for k in reason_kind(v)], dtype=str)
        counts = sorted(kinds.value_counts().items(), key=lambda item: (-item[1], item[0]))
        categories = pd.Series(np.where(group["failure"] != "", group["failure"],
                                        np.where(group["found"], "inaccurate", "not found")),
                               dtype=str).value_counts()
        rows.append([family, solver, str(len(group)),
                     ", ".join(f"{k} ({v})" for k, v in sorted(categories.items())),
                     fmt(", ".join(f"{k} ({v})" for k, v in counts[:4]), "text")])
    return (markdown_table(["family", "solver", "failed cells", "categories", "reasons (cells)"],
                           rows, "llrll")
            + "\nCategories: the registry's failure category; *inaccurate*: the solver "
              "claimed a solution but the residual check failed; *not found*: it returned "
              "without claiming one. The per-cell reason is the `verdict` column of the "
              "results.\n" + (f"\n{apart}" if apart else ""))


def _family_tables(frame: pd.DataFrame, summary: pd.DataFrame) -> list[str]:
    """One heading, caption and table per (family, variant, settings, precision, start)."""
    out = []
    keys = ["family", "settings", "precision", "start"]
    for key, group in summary.groupby(["family", "variant", *keys[1:]], sort=True):
        family, variant, profile, precision, start = (str(k) for k in key)
        peers = summary
        for column, value in zip(keys, (family, profile, precision, start), strict=True):
            peers = peers[peers[column] == value]
        cells = frame[(frame["family"] == family) & (frame["settings"] == profile)]
        out.append(f"### {family_label(family, variant)} / {profile} / {precision} / "
                   f"{start}\n")
        out.append(f"Tolerance {group['tolerance'].max():.0e} (accuracy in **bold** above "
                   f"it); residuals checked: {', '.join(required_residuals(family))}; time "
                   f"limit {cells['time_limit'].max():g} s (a failed cell counts at it in "
                   "the time columns, as qpbenchmark does).\n")
        out.append(family_table(group, sorted(set(peers["solver"]) - set(group["solver"]))))
    return out


SOLVER_TABLE_KEYS = frozenset({"name", "version", "available", "reason", "families",
                               "precisions"})
"""Keys of each entry of ``run_info.json``'s ``solver_table``."""


def read_run_info(path: Path) -> dict[str, Any]:
    """``run_info.json`` of a suite; :class:`~c3bench.problems.errors.SchemaVersionError`
    naming the file when it is damaged (not a JSON object, or its ``packages`` /
    ``solver_table`` not of the shape the report reads)."""
    info = store.read_json_object(path, "run_info.json")
    table = info.get("solver_table") or []
    if not isinstance(info.get("packages", {}), dict):
        wrong = "packages is not an object"
    elif not (isinstance(table, list) and all(
            isinstance(entry, dict) and entry.keys() >= SOLVER_TABLE_KEYS for entry in table)):
        wrong = (f"solver_table is not a list of objects with keys "
                 f"{', '.join(sorted(SOLVER_TABLE_KEYS))}")
    else:
        return info
    raise SchemaVersionError(f"{path}: damaged, not a c3bench run_info.json ({wrong}); delete "
                             f"it or run the command that wrote it again")


def build_report(paths: store.SuitePaths, frame: pd.DataFrame | None = None,
                 figures: bool = True, budget_ms: float | None = None) -> str:
    """The report's Markdown text (draws the figures into ``paths.figures``).

    ``budget_ms`` is the control budget of one QP solve in ms (default: control period /
    ADMM iterations, :data:`bench.budgets.DEFAULT_BUDGET_S`).
    """
    everything = store.read_results(paths.root) if frame is None else frame
    frame = other_rows(everything)  # the sequence cells have their own section
    info = read_run_info(paths.run_info) if paths.run_info.exists() else {}
    summary = aggregate(frame)
    suite = paths.root.name
    out = [f"# c3bench report: suite `{suite}`\n",
           f"Generated {dt.datetime.now(dt.UTC).strftime('%Y-%m-%d')} from "
           f"`{paths.parquet.name}` (schema version {store.SCHEMA_VERSION}).\n",
           "## Machine and versions\n", *_header(info, everything),
           "## Method\n", _method(),
           "## Solvers\n", _solver_table(info, everything),
           "## Reference optima\n", _reference_table(paths),
           "## Success overview\n", _overview(summary),
           "## Results by family and settings\n"]
    if summary.empty:
        out.append("No results.\n")
    out += _family_tables(frame, summary)
    out += ["## Controller sequence\n", sequence_section(everything, paths)]
    out += ["## Why slow\n", why_slow_section(frame),
            "## Claimed success but wrong\n", claimed_wrong_section(frame),
            "## Control budget\n", budget_section(frame, budget_seconds(budget_ms),
                                                  explicit=budget_ms is not None),
            "## Failures\n", _failures(frame)]
    out += _figure_sections(frame, paths) if figures else ["## Figures\n"]
    out += _linked_sections(paths)
    out += ["## Results schema\n", store.schema_markdown()]
    return "\n".join(out)


def _figure_sections(frame: pd.DataFrame, paths: store.SuitePaths) -> list[str]:
    """Draw every figure (old PNGs removed first) and return its heading and caption."""
    out = ["## Figures\n"]
    for old in sorted(paths.figures.glob("*.png")) if paths.figures.is_dir() else []:
        old.unlink()
    for number, figure in enumerate(all_figures(frame, paths), start=1):
        out.append(f"### Figure {number}: {figure.title}\n")
        if figure.path is None:
            out.append(f"*No figure: {figure.note}.*\n")
        else:
            out.append(f"![{figure.title}]({figure.path})\n")
            out.append(f"*Figure {number}: {figure.caption}*\n")
    return out


def _linked_sections(paths: store.SuitePaths) -> list[str]:
    """The ``perf`` section (from ``<root>/perf/``) and a pointer to the closed-loop report."""
    results_dir = paths.root.parent
    out = [perf_report_section(
        results_dir, figure_link=f"../{store.PERF_DIR}/figures/{PERF_FIGURE}")]
    closed_loop = store.closed_loop_dir(results_dir, "quick") / "report.md"
    link = f"{store.CLOSED_LOOP_DIR}/quick/report.md"
    out.append("## Closed loop\n")
    if closed_loop.exists():
        out.append("C3 / C3+ driving the MuJoCo cube with each backend inside: "
                   f"[{link}](../{link}) "
                   "(`c3bench closed-loop-suite --suite quick`).\n")
    else:
        out.append("_Not run: `c3bench closed-loop-suite --suite quick` writes it._\n")
    return out


def write_report(suite: str, results_dir: str | Path = "results", figures: bool = True,
                 budget_ms: float | None = None) -> Path:
    """Write ``results/<suite>/report.md`` (+ figures and ``summary.csv``); return its path.

    ``budget_ms``: the control budget of one QP solve in ms for the budget section (default
    control period / ADMM iterations = 5 ms).
    """
    paths = store.SuitePaths.of(results_dir, suite)
    frame = store.read_results(paths.root)
    text = build_report(paths, frame, figures=figures, budget_ms=budget_ms)
    store.atomic_write_bytes(paths.report, text.encode())
    store.atomic_write_bytes(paths.summary, aggregate(frame).to_csv(index=False).encode())
    return paths.report


# --- perf: control-step time ------------------------------------------------------------------
def perf_report_section(results_dir: str | Path, figure_link: str | None = None) -> str:
    """A Markdown section on the control-step time (reads ``<results_dir>/perf/``): the
    latest run of each machine, one table per machine, with the ratios to
    ``c3plus-riccati`` and ``c3-osqp`` of the same run, the achieved GFLOP/s, the run's matmul
    rate and the load average (:func:`bench.perf_report.perf_section`).

    ``figure_link`` is the figure's path as the report should link it (default
    ``perf/figures/perf_time_vs_samples.png``, right for a report in ``results_dir``; a
    report in ``results/<suite>/`` passes ``../perf/figures/perf_time_vs_samples.png``).
    """
    from c3bench.bench.perf_report import perf_section

    return perf_section(results_dir, figure_link)
