"""Results store: the schemas of every stored table, their paths, atomic and versioned files.

Every command writes under one results root (``--results ROOT``, default ``results``), each in
its own folder: ``ROOT/<suite>/`` (``run``, ``report``, ``compare``), ``ROOT/perf/``
(``perf``, :func:`perf_dir`), ``ROOT/closed_loop/<name>/`` (``closed-loop-suite``, ``sweep``
and ``closed-loop`` runs, :func:`closed_loop_dir`).

Layout of ``ROOT/<suite>/``::

    cells/<cell-id>.json      one small file per finished cell (the source of truth; written
                              through a temporary file and a rename as each cell finishes)
    traces/<cell-id>.json     per-iteration traces and every diagnostic of that cell
    results.parquet           all cells, consolidated (Parquet metadata ``c3bench_schema``)
    results.csv               the same table as CSV (first column ``schema_version``)
    references.parquet        reference optima (see :mod:`bench.reference`)
    run_info.json             machine, versions and options of the last run
    solver_output.log         what the solvers printed (local pool workers)
    instances/                the suite's instances (``problems.suites.generate_suite``)
    c3bench.lock              held (``flock``) while a run works here; names the holder
                              (:mod:`bench.lock`)

A cell is one (instance, solver, settings profile, precision, start) combination; its
identity is :data:`KEY_COLUMNS`.

``ROOT/perf/`` holds the history of ``c3bench perf``: one file per run under
``runs/``, every run together in ``perf.parquet`` (schema and files: :mod:`bench.perf_store`).

Schema versions: one :data:`SCHEMA_VERSION` for every table this module writes (results,
traces, references, perf), stored in Parquet metadata (:data:`PARQUET_METADATA_KEY`) and in a
``schema_version`` column or key; :func:`check_version` is the one check, and readers raise
:class:`~c3bench.problems.errors.SchemaVersionError` for any other version instead of guessing.
Changing any stored table's columns bumps :data:`SCHEMA_VERSION`; a table whose own columns
did not change across a bump keeps reading its older versions (``perf_store.PERF_READABLE``).
"""

from __future__ import annotations

import contextlib
import json
import math
import re
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq

from c3bench.problems.errors import SchemaVersionError
from c3bench.problems.instance import atomic_write_bytes

SCHEMA_VERSION = 2
"""Version 2: ``build_time`` renamed ``setup_time``; ``total_time`` and ``verified`` added."""
PARQUET_METADATA_KEY = b"c3bench_schema"


@dataclass(frozen=True)
class Column:
    """One column of the results table: name, pandas dtype and meaning (README copies it)."""

    name: str
    dtype: str
    meaning: str


# The results schema. dtypes: ``str``; ``int64``; ``Int64`` (nullable integer, empty when
# unknown); ``float64`` (NaN when unknown or not applicable); ``bool``.
SCHEMA: tuple[Column, ...] = (
    Column("schema_version", "int64", "Version of this schema (rows of another are rejected)."),
    Column("cell_id", "str", "File-safe id of the cell: instance--solver--settings--precision"
           "--start."),
    Column("suite", "str", "Suite name (quick, default, full or a custom spec)."),
    Column("instance", "str", "Instance name (unique within the suite)."),
    Column("instance_hash", "str", "Identity of the instance (problems.identity: its "
           "provenance and its arrays rounded to ~1e-9 of each array's largest entry); a "
           "cell of a changed instance is stale and rerun, one regenerated elsewhere with "
           "last-bit noise is not."),
    Column("family", "str", "Subproblem family: c3plus_qp, c3_qp, projection, mpcc, lcp."),
    Column("solver", "str", "Registry name of the backend."),
    Column("solver_version", "str", "Version of the backend's package ('-' for our own code)."),
    Column("settings", "str", "Settings profile: default, low_accuracy, mid_accuracy, "
           "high_accuracy."),
    Column("tolerance", "float64", "Tolerance of the profile: solver target and success "
           "threshold."),
    Column("time_limit", "float64", "Wall-clock limit per solve (s; a sequence cell: per "
           "ADMM run, 10 x the per-QP limit); failures count as this in time aggregates."),
    Column("precision", "str", "Floating-point precision the backend ran in: float64 or "
           "float32."),
    Column("start", "str", "cold (fresh solver object), or warm (solver object kept: update "
           "API with the new vectors, started from the reference solution of the previous "
           "ADMM iterate; solvers.timing), or sequence (the 10 QP steps of one ADMM run at "
           "the instance's state, the backend as its QP step; times summed over the steps, "
           "residuals of the worst step; bench.sequence)."),
    Column("repeats", "int64", "Timed repeats after one untimed warm-up; times are medians."),
    Column("state_index", "Int64", "Step of the scripted push the instance was linearised at."),
    Column("admm_iteration", "Int64", "ADMM iteration the instance was captured at (empty for "
           "mpcc, lcp)."),
    Column("rho_lam", "float64", "ADMM weight on lambda at that iteration (NaN when none)."),
    Column("n_variables", "int64", "Number of variables."),
    Column("n_constraints", "int64", "Equality + inequality rows + variables with a finite "
           "bound."),
    Column("found", "bool", "The solver claims a solution (never success on its own)."),
    Column("failure", "str", "Failure category from the registry: '', error, timeout, "
           "invalid_input, non_finite, unsupported, unavailable, infeasible."),
    Column("status", "str", "Solver's own status text, or the failure reason."),
    Column("success", "bool", "found and every residual of the family below tolerance and "
           "cost_error below tolerance where a verified reference exists; projection / mpcc "
           "also need that reference (bench.metrics)."),
    Column("verdict", "str", "Why success is False ('' when it is True); 'feasible, "
           "optimality not verified ...' for a projection / mpcc row without a verified "
           "reference optimum (counted apart as unverified)."),
    Column("verified", "bool", "Judged against a verified reference optimum f* (reference "
           "and cross-check passed and agree, bench.reference); projection / mpcc rows "
           "without one are never a success."),
    Column("iterations", "Int64", "Solver iterations (empty when not reported)."),
    Column("setup_time", "float64", "Median seconds of setup: conversion, structure analysis, "
           "factorisation, solver object construction (solvers.timing); in a warm cell the "
           "update call where the solver has an update API."),
    Column("solve_time", "float64", "Median seconds of the solve proper (iterations, back "
           "substitution, reading the solution out)."),
    Column("total_time", "float64", "setup_time + solve_time: what a caller pays per solve; "
           "every ranking reads it (bench.metrics.RANKED_TIME_COLUMN)."),
    Column("objective", "float64", "1/2 x^T P x + q^T x + offset at the returned x."),
    Column("primal_residual", "float64", "max(||Ax-b||, ||[Gx-h]+||, bound violation), inf-norm."),
    Column("dual_residual", "float64", "max(||Px + q + A^T y + G^T z + z_box||_inf, largest "
           "wrong-signed z or z_box) (NaN without duals)."),
    Column("duality_gap", "float64", "|x^T P x + q^T x + b^T y + h^T z + bound terms|."),
    Column("primal_residual_relative", "float64", "primal_residual / max(1, size of its terms: "
           "||Ax||, ||b||, ||Gx||, ||h||, bounds) (solvers.residuals); judged for success."),
    Column("dual_residual_relative", "float64", "dual_residual / max(1, ||Px||, ||q||, "
           "||A^T y||, ||G^T z||, ||z_box||); judged for success."),
    Column("duality_gap_relative", "float64", "duality_gap / max(1, largest term of the gap); "
           "judged for success."),
    Column("complementarity_violation", "float64", "max over pairs |min(x_i, x_j)| (0 without "
           "pairs); lcp: ||min(lam, P lam + q)||_inf / max(1, ||P lam||, ||q||)."),
    Column("cost_error", "float64", "|f - f*| / max(1, |f*|) against the reference optimum "
           "(NaN without one)."),
    Column("reference_solver", "str", "Backend that gave f* ('' when no reference)."),
    Column("reference_objective", "float64", "The reference optimum f* (NaN when none)."),
    Column("reference_spread", "float64", "Disagreement of f* with its cross-check, "
           "|f*_ref - f*_check| / max(1, |f*|); cost threshold is max(tolerance, this)."),
    Column("cond_kkt", "float64", "Condition number of the KKT matrix, where the backend "
           "reports it."),
    Column("cond_schur_raw", "float64", "cond(S = A Q^-1 A^T) before equilibration."),
    Column("cond_schur_equilibrated", "float64", "cond(S) after equilibration."),
    Column("violation_before_projection", "float64", "||Ax - b||_inf before the final "
           "projection step."),
    Column("violation_after_projection", "float64", "||Ax - b||_inf after it."),
    Column("trace_file", "str", "Path of the trace JSON relative to the suite directory ('' "
           "when none)."),
    Column("host", "str", "Host name of the worker that ran the cell."),
    Column("finished_at", "str", "UTC time the cell finished (ISO 8601)."),
)

COLUMNS: tuple[str, ...] = tuple(column.name for column in SCHEMA)
DTYPES: dict[str, str] = {column.name: column.dtype for column in SCHEMA}
KEY_COLUMNS: tuple[str, ...] = ("instance", "solver", "settings", "precision", "start")
SORT_COLUMNS: tuple[str, ...] = ("family", "instance", "solver", "settings", "precision",
                                 "start")
DIAGNOSTIC_COLUMNS: tuple[str, ...] = ("cond_kkt", "cond_schur_raw", "cond_schur_equilibrated",
                                       "violation_before_projection",
                                       "violation_after_projection")


def schema_markdown() -> str:
    """The schema as a Markdown table (for the README and the report)."""
    lines = ["| column | type | meaning |", "|---|---|---|"]
    lines += [f"| `{c.name}` | {c.dtype} | {c.meaning} |" for c in SCHEMA]
    return "\n".join(lines) + "\n"


# --- paths ------------------------------------------------------------------------------------
_UNSAFE = re.compile(r"[^A-Za-z0-9_.+-]")


def cell_id(instance: str, solver: str, settings: str, precision: str, start: str) -> str:
    """File-safe id of a cell (``instance--solver--settings--precision--start``)."""
    return "--".join(_UNSAFE.sub("_", part)
                     for part in (instance, solver, settings, precision, start))


@dataclass(frozen=True)
class SuitePaths:
    """Where a suite's results live."""

    root: Path

    @classmethod
    def of(cls, results_dir: str | Path, suite: str) -> SuitePaths:
        return cls(Path(results_dir) / suite)

    @property
    def cells(self) -> Path:
        return self.root / "cells"

    @property
    def traces(self) -> Path:
        return self.root / "traces"

    @property
    def instances(self) -> Path:
        return self.root / "instances"

    @property
    def figures(self) -> Path:
        return self.root / "figures"

    @property
    def parquet(self) -> Path:
        return self.root / "results.parquet"

    @property
    def csv(self) -> Path:
        return self.root / "results.csv"

    @property
    def references(self) -> Path:
        return self.root / "references.parquet"

    @property
    def run_info(self) -> Path:
        return self.root / "run_info.json"

    @property
    def identities(self) -> Path:
        """The identities of the instances the stored cells were run on
        (:mod:`c3bench.problems.identity`; beside the cells, so it travels with them)."""
        return self.root / "instance_identity.json"

    @property
    def report(self) -> Path:
        return self.root / "report.md"

    @property
    def summary(self) -> Path:
        return self.root / "summary.csv"

    @property
    def solver_log(self) -> Path:
        return self.root / "solver_output.log"


# --- atomic writes: problems.instance.atomic_write_bytes (temporary file, fsync, rename) ----


def _json_safe(value: Any) -> Any:
    """Convert numpy scalars and non-finite floats (-> ``None`` / strings) for strict JSON."""
    if isinstance(value, Mapping):
        return {str(k): _json_safe(v) for k, v in value.items()}
    if isinstance(value, list | tuple | np.ndarray):
        return [_json_safe(v) for v in (value.tolist() if isinstance(value, np.ndarray)
                                         else value)]
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None if math.isnan(value) else ("inf" if value > 0 else "-inf")
    if value is pd.NA:
        return None
    return value


def _from_json_float(value: Any) -> float:
    if value is None:
        return float("nan")
    if value == "inf":
        return float("inf")
    if value == "-inf":
        return float("-inf")
    return float(value)


def write_json(path: Path, payload: Mapping[str, Any]) -> None:
    """Atomically write strict JSON (sorted keys, NaN as ``null``, inf as ``"inf"``)."""
    text = json.dumps(_json_safe(payload), indent=1, sort_keys=True, allow_nan=False) + "\n"
    atomic_write_bytes(path, text.encode())


# --- rows -------------------------------------------------------------------------------------
def empty_row() -> dict[str, Any]:
    """A row with every column at its 'unknown' value."""
    row: dict[str, Any] = {}
    for column in SCHEMA:
        row[column.name] = {"str": "", "int64": 0, "Int64": None, "float64": float("nan"),
                            "bool": False}[column.dtype]
    row["schema_version"] = SCHEMA_VERSION
    return row


def normalise_row(row: Mapping[str, Any]) -> dict[str, Any]:
    """Coerce a row to the schema's Python types; ``ValueError`` names a missing column."""
    out: dict[str, Any] = {}
    for column in SCHEMA:
        if column.name not in row:
            raise ValueError(f"row is missing column {column.name!r}")
        value = row[column.name]
        if column.dtype == "str":
            out[column.name] = "" if value is None else str(value)
        elif column.dtype == "int64":
            out[column.name] = int(value)
        elif column.dtype == "Int64":
            out[column.name] = None if value is None or (
                isinstance(value, float) and math.isnan(value)) or value is pd.NA else int(value)
        elif column.dtype == "float64":
            out[column.name] = _from_json_float(value) if value is None or isinstance(
                value, str) else float(value)
        else:
            out[column.name] = bool(value)
    return out


def cell_key(row: Mapping[str, Any]) -> tuple[str, ...]:
    """Identity of a cell: :data:`KEY_COLUMNS` values."""
    return tuple(str(row[name]) for name in KEY_COLUMNS)


def write_cell(paths: SuitePaths, row: Mapping[str, Any],
               trace: Mapping[str, Any] | None = None) -> Path:
    """Store one finished cell (and its trace) atomically; return the cell file."""
    row = normalise_row(row)
    if trace:
        relative = f"traces/{row['cell_id']}.json"
        write_json(paths.root / relative, {"schema_version": SCHEMA_VERSION,
                                           "cell_id": row["cell_id"], **trace})
        row["trace_file"] = relative
    path = paths.cells / f"{row['cell_id']}.json"
    write_json(path, row)
    return path


def check_version(version: Any, source: Path,
                  readable: tuple[int, ...] = (SCHEMA_VERSION,)) -> None:
    """Raise :class:`SchemaVersionError` unless ``version`` is one of ``readable`` (by
    default :data:`SCHEMA_VERSION` only; see :data:`PERF_READABLE`)."""
    if version not in readable:
        raise SchemaVersionError(
            f"{source}: written with results schema version {version!r}, this c3bench reads "
            f"version {SCHEMA_VERSION} and cannot update it in place (`--rerun` reads it too); "
            f"delete or move {results_folder(source)} and run the command that wrote it again")


def results_folder(source: Path) -> Path:
    """The folder a command owns for a stored file: the suite directory for its cells,
    traces and tables, ``perf/`` for a perf run file."""
    parent = source.parent
    return parent.parent if parent.name in ("cells", "traces", PERF_RUNS) else parent


def check_frame_version(frame: pd.DataFrame, source: Path,
                        readable: tuple[int, ...] = (SCHEMA_VERSION,)) -> None:
    """Check the ``schema_version`` column of a table read from ``source`` (CSV files)."""
    if "schema_version" not in frame.columns:
        raise SchemaVersionError(f"{source}: no schema_version column; not a c3bench file")
    for version in set(frame["schema_version"].tolist()) or {SCHEMA_VERSION}:
        check_version(version, source, readable)


def parquet_bytes(table: pa.Table | pd.DataFrame) -> bytes:
    """A Parquet file of ``table`` with :data:`SCHEMA_VERSION` in its metadata."""
    if isinstance(table, pd.DataFrame):
        table = pa.Table.from_pandas(table, preserve_index=False)
    metadata = dict(table.schema.metadata or {})
    metadata[PARQUET_METADATA_KEY] = str(SCHEMA_VERSION).encode()
    sink = pa.BufferOutputStream()
    pq.write_table(table.replace_schema_metadata(metadata), sink)
    return bytes(sink.getvalue().to_pybytes())


def read_parquet(path: Path, readable: tuple[int, ...] = (SCHEMA_VERSION,)) -> pa.Table:
    """Read a Parquet file written by :func:`parquet_bytes`, checking its schema version
    (one of ``readable``).

    The version comes from the metadata, or, for files written before it was stored there,
    from a ``schema_version`` column.
    """
    try:
        table = pq.read_table(path)
    except (pa.ArrowInvalid, OSError) as error:
        raise SchemaVersionError(f"{path}: not a readable Parquet file ({error})") from error
    raw = (table.schema.metadata or {}).get(PARQUET_METADATA_KEY)
    if raw is None and "schema_version" in table.column_names:
        for version in set(table.column("schema_version").to_pylist()) or {SCHEMA_VERSION}:
            check_version(version, path, readable)
        return table
    check_version(int(raw) if raw is not None and raw.decode().isdigit() else raw, path,
                  readable)
    return table


def read_cell(path: Path) -> dict[str, Any]:
    """Read one cell file, rejecting another schema version."""
    try:
        payload = json.loads(path.read_text())
    except json.JSONDecodeError as error:
        raise SchemaVersionError(f"{path}: not a c3bench cell file ({error})") from error
    check_version(payload.get("schema_version"), path)
    try:
        return normalise_row(payload)
    except (TypeError, ValueError) as error:
        raise SchemaVersionError(f"{path}: {error}; not a valid schema version "
                                 f"{SCHEMA_VERSION} cell (delete or move "
                                 f"{results_folder(path)} and run again)") from error


def read_cells(paths: SuitePaths) -> list[dict[str, Any]]:
    """Every finished cell of a suite (sorted by file name)."""
    if not paths.cells.is_dir():
        return []
    return [read_cell(path) for path in sorted(paths.cells.glob("*.json"))]


def remove_cell(paths: SuitePaths, row: Mapping[str, Any]) -> None:
    """Delete a stored cell and its trace (used for stale cells of changed instances)."""
    (paths.cells / f"{row['cell_id']}.json").unlink(missing_ok=True)
    if row.get("trace_file"):
        (paths.root / str(row["trace_file"])).unlink(missing_ok=True)


def read_trace(paths: SuitePaths, relative: str) -> dict[str, Any]:
    """The trace file of a cell (``{}`` when there is none)."""
    if not relative:
        return {}
    path = paths.root / relative
    if not path.exists():
        return {}
    payload: dict[str, Any] = json.loads(path.read_text())
    check_version(payload.get("schema_version"), path)
    return payload


def rows_to_frame(rows: Iterable[Mapping[str, Any]]) -> pd.DataFrame:
    """A DataFrame with exactly the schema's columns, dtypes and the canonical row order."""
    rows = [normalise_row(row) for row in rows]
    frame = pd.DataFrame(rows, columns=list(COLUMNS))
    for column in SCHEMA:
        if column.dtype == "str":
            frame[column.name] = frame[column.name].astype(object).fillna("").astype(str)
        else:
            frame[column.name] = frame[column.name].astype(column.dtype)
    if len(frame):
        frame = frame.sort_values(list(SORT_COLUMNS), kind="mergesort").reset_index(drop=True)
    return frame


def consolidate(paths: SuitePaths) -> pd.DataFrame:
    """Gather every cell file into ``results.parquet`` and ``results.csv`` (atomically)."""
    frame = rows_to_frame(read_cells(paths))
    write_frame(paths, frame)
    return frame


def write_frame(paths: SuitePaths, frame: pd.DataFrame) -> None:
    """Write the results table as Parquet (schema version in its metadata) and CSV."""
    atomic_write_bytes(paths.parquet, parquet_bytes(frame))
    atomic_write_bytes(paths.csv, frame.to_csv(index=False).encode())


def read_results(source: str | Path) -> pd.DataFrame:
    """Read a results table (``results.parquet`` / ``results.csv`` or a suite directory).

    For a suite directory the cell files are the truth: when it has a ``cells/`` folder the
    table is gathered from it and ``results.parquet``/``.csv`` rewritten to match (kept as
    they are when the directory is read-only), so the table never disagrees with the cells
    (a run killed before its last consolidation, cells removed as stale). Raises
    :class:`SchemaVersionError` for another schema version and ``FileNotFoundError`` when
    there are no results.
    """
    source = Path(source)
    if not source.exists():
        raise FileNotFoundError(f"{source}: no results (run the benchmark first)")
    if source.is_dir():
        paths = SuitePaths(source)
        if paths.cells.is_dir() and (any(paths.cells.glob("*.json"))
                                     or paths.parquet.exists()):
            frame = rows_to_frame(read_cells(paths))
            with contextlib.suppress(OSError):
                write_frame(paths, frame)
            return frame
        if not paths.parquet.exists():
            raise FileNotFoundError(f"{source}: no results (run the benchmark first)")
        source = paths.parquet
    if source.suffix == ".csv":
        frame = pd.read_csv(source, keep_default_na=False, na_values={
            c.name: ["", "nan", "NaN"] for c in SCHEMA if c.dtype != "str"})
        check_frame_version(frame, source)
    else:
        frame = read_parquet(source).to_pandas()
    missing = [name for name in COLUMNS if name not in frame.columns]
    if missing:
        raise SchemaVersionError(f"{source}: columns {missing} missing for schema version "
                                 f"{SCHEMA_VERSION}")
    return rows_to_frame(frame[list(COLUMNS)].to_dict("records"))


# --- other folders of the results root ----------------------------------------------------------
PERF_DIR = "perf"
"""Folder of ``c3bench perf`` under the results root."""
PERF_RUNS = "runs"
"""Folder of one Parquet file per ``c3bench perf`` run under :func:`perf_dir`
(:mod:`bench.perf_store`)."""
CLOSED_LOOP_DIR = "closed_loop"
"""Folder of the closed-loop commands under the results root."""


def perf_dir(results_dir: str | Path) -> Path:
    """``<results_dir>/perf``: the files of ``c3bench perf``."""
    return Path(results_dir) / PERF_DIR


def closed_loop_dir(results_dir: str | Path, name: str) -> Path:
    """``<results_dir>/closed_loop/<name>``: a closed-loop suite, the sweep, or ``runs``."""
    return Path(results_dir) / CLOSED_LOOP_DIR / name
