"""Results store: the stored tables' paths, atomic and versioned files (the results schema is
in :mod:`bench.store_schema`, re-exported here).

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

from c3bench.bench.store_schema import (  # re-exported: the schema
    COLUMNS,
    DIAGNOSTIC_COLUMNS,  # noqa: F401
    DTYPES,  # noqa: F401
    KEY_COLUMNS,
    PARQUET_METADATA_KEY,
    SCHEMA,
    SCHEMA_VERSION,
    SORT_COLUMNS,
    Column,  # noqa: F401
    schema_markdown,  # noqa: F401
)
from c3bench.problems.errors import SchemaVersionError
from c3bench.problems.instance import atomic_write_bytes

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
    """Coerce a row to the schema's Python types.

    Raises
    ------
    ValueError
        A column is missing, or holds a value of another type, on one line naming the column:
        text such as ``'False'`` in a ``bool`` column (``None``, NA and NaN are False there;
        a stored table's are checked by :func:`read_results`), NaN or a fraction in an
        ``int64`` one, a time that is not finite and ``>= 0`` in a row with ``found``.
    """
    out: dict[str, Any] = {}
    for column in SCHEMA:
        if column.name not in row:
            raise ValueError(f"row is missing column {column.name!r}")
        value = row[column.name]
        try:
            out[column.name] = _coerce(value, column.dtype)
        except (TypeError, ValueError, OverflowError) as error:
            shown = value.item() if isinstance(value, np.generic) else value
            raise ValueError(f"column {column.name!r} ({column.dtype}) holds {shown!r}: "
                             f"{error}") from None
    if out["found"]:  # a found solve's laps passed the timing contract when it was stored
        for name in TIME_COLUMNS:
            if not valid_time(out[name]):
                raise ValueError(f"column {name!r} holds {out[name]!r} in a row that found a "
                                 f"solution (its times are finite and >= 0)")
    return out


def valid_time(value: float) -> bool:
    """A time of the timing contract (:mod:`c3bench.solvers.timing`): finite and ``>= 0``."""
    return math.isfinite(value) and value >= 0.0


TIME_COLUMNS = ("setup_time", "solve_time", "total_time")
"""The time columns; finite and ``>= 0`` in every row with ``found`` (:func:`normalise_row`)."""


def _coerce(value: Any, dtype: str) -> Any:
    """``value`` as the Python type of a schema ``dtype`` (see :func:`normalise_row`)."""
    if dtype == "str":
        return "" if value is None else str(value)
    if dtype == "bool":
        if isinstance(value, str | bytes):
            raise TypeError("text, not a boolean")
        # missing (None, NA, a float NaN) is False: never a verdict nobody gave
        if value is None or value is pd.NA or (
                isinstance(value, float | np.floating) and math.isnan(value)):
            return False
        return bool(value)
    if dtype == "Int64" and (value is None or value is pd.NA or (
            isinstance(value, float) and math.isnan(value))):
        return None
    if dtype in ("int64", "Int64"):
        if isinstance(value, str | bytes):
            raise TypeError("not a whole number")
        number = int(value)
        if number != value:
            raise ValueError("not a whole number")
        return number
    return _from_json_float(value) if value is None or isinstance(value, str) else float(value)


def cell_key(row: Mapping[str, Any]) -> tuple[str, ...]:
    """Identity of a cell: :data:`KEY_COLUMNS` values."""
    return tuple(str(row[name]) for name in KEY_COLUMNS)


def write_cell(paths: SuitePaths, row: Mapping[str, Any],
               trace: Mapping[str, Any] | None = None, *, cells: Path | None = None) -> Path:
    """Store one finished cell (and its trace) atomically; return the cell file (in
    ``cells``, by default ``paths.cells``)."""
    row = normalise_row(row)
    if trace:
        relative = f"traces/{row['cell_id']}.json"
        write_json(paths.root / relative, {"schema_version": SCHEMA_VERSION,
                                           "cell_id": row["cell_id"], **trace})
        row["trace_file"] = relative
    path = (paths.cells if cells is None else cells) / f"{row['cell_id']}.json"
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
    # bytes.isdigit: ASCII digits only, so damaged metadata is a version error, never a
    # decode error without the file's name
    check_version(int(raw) if raw is not None and raw.isdigit() else raw, path, readable)
    return table


def read_json_object(path: Path, what: str) -> dict[str, Any]:
    """The JSON object stored in ``path`` (a c3bench ``what``: "cell file", ...).

    Raises
    ------
    SchemaVersionError
        The file is damaged: not UTF-8, not JSON (a truncated write) or not a JSON object;
        the one-line message names the file and what is wrong with it.
    """
    try:
        payload = json.loads(path.read_text())
    except ValueError as error:  # JSONDecodeError, UnicodeDecodeError
        raise SchemaVersionError(f"{path}: damaged, not a c3bench {what} ({error}); delete "
                                 f"it or run the command that wrote it again") from error
    if not isinstance(payload, dict):
        raise SchemaVersionError(f"{path}: damaged, not a c3bench {what} (a JSON "
                                 f"{type(payload).__name__}, expected an object); delete it "
                                 f"or run the command that wrote it again")
    return payload


def read_cell(path: Path) -> dict[str, Any]:
    """Read one cell file, rejecting another schema version or a damaged file."""
    payload = read_json_object(path, "cell file")
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
    payload = read_json_object(path, "trace file")
    check_version(payload.get("schema_version"), path)
    return payload


def absent_traces(paths: SuitePaths, relatives: Iterable[str]) -> int:
    """How many of the named trace files (non-empty names) are not on disk (``traces/`` is
    not committed with a suite's results: a fresh checkout has none)."""
    return sum(1 for relative in relatives
               if relative and not (paths.root / str(relative)).exists())


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
    (a run killed before its last consolidation, cells removed as stale).

    Raises
    ------
    SchemaVersionError
        Another schema version, a damaged file, or bad values: a column holding a value of
        another type (:func:`normalise_row`; a ``bool`` column anything but booleans) or two
        rows of one cell (:func:`cell_key`); the one-line message names the file and the
        column or the repeated cell.
    FileNotFoundError
        There are no results.
    """
    source = Path(source)
    if not source.exists():
        raise FileNotFoundError(f"{source}: no results (run the benchmark first)")
    if source.is_dir():
        paths = SuitePaths(source)
        if paths.cells.is_dir() and (any(paths.cells.glob("*.json"))
                                     or paths.parquet.exists()):
            frame = _unique(rows_to_frame(read_cells(paths)), paths.cells,
                            "delete the cell files of the repeated cell and run again")
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
    _check_booleans(frame, source)
    try:
        rows = rows_to_frame(frame[list(COLUMNS)].to_dict("records"))
    except ValueError as error:
        raise SchemaVersionError(f"{source}: {error}; {_REWRITE}") from error
    return _unique(rows, source, _REWRITE)


_REWRITE = (f"not a valid schema version {SCHEMA_VERSION} results table (delete it or run "
            "the command that wrote it again)")


def _check_booleans(frame: pd.DataFrame, source: Path) -> None:
    """:class:`SchemaVersionError` naming ``source`` and the column when a ``bool`` column of
    a stored table holds anything but booleans (text such as ``'False'``, numbers, empty
    values): ``bool('False')`` is True, so such a table would be misread."""
    for column in SCHEMA:
        values = frame[column.name]
        if column.dtype != "bool" or pd.api.types.is_bool_dtype(values.dtype):
            continue
        bad = [v for v in values if not isinstance(v, bool | np.bool_)]
        if bad:
            raise SchemaVersionError(f"{source}: column {column.name!r} (bool) holds "
                                     f"{bad[0]!r} ({len(bad)} of {len(values)} values are "
                                     f"not booleans); {_REWRITE}")


def _unique(frame: pd.DataFrame, source: Path, fix: str) -> pd.DataFrame:
    """``frame``, unless two of its rows share a cell key (:func:`cell_key`):
    :class:`SchemaVersionError` naming ``source``, the first repeated key and ``fix``."""
    repeated = frame.duplicated(list(KEY_COLUMNS), keep="first")
    if repeated.any():
        key = dict(zip(KEY_COLUMNS, cell_key(frame[repeated].iloc[0].to_dict()),
                       strict=True))
        raise SchemaVersionError(f"{source}: {int(repeated.sum())} rows repeat a cell, first "
                                 f"{key} (a cell is stored once); {fix}")
    return frame


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
