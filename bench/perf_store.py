"""The stored history of ``c3bench perf``: its schema and files under ``ROOT/perf/``.

``ROOT/perf/runs/<run_id>.parquet`` holds the control-step times of one run
(:data:`PERF_SCHEMA`, one row per timed step; a run never overwrites another),
``ROOT/perf/perf.parquet`` and ``perf.csv`` every run together, and
``figures/perf_time_vs_samples.png`` the latest run of each machine. Versions, atomic writes and
Parquet helpers are those of :mod:`bench.store`.
"""

from __future__ import annotations

import re
from pathlib import Path

import pandas as pd

from c3bench.bench.store import (
    PERF_RUNS,
    SCHEMA_VERSION,
    Column,
    check_frame_version,
    parquet_bytes,
    perf_dir,
    read_parquet,
)
from c3bench.problems.instance import atomic_write_bytes

# --- perf: control-step times -----------------------------------------------------------------
PERF_SCHEMA: tuple[Column, ...] = (
    Column("schema_version", "int64", ":data:`SCHEMA_VERSION`."),
    Column("run_id", "str", "UTC time stamp of the run."),
    Column("backend", "str", "c3plus-riccati, c3plus-jax, c3-osqp or c3-clarabel."),
    Column("precision", "str", "float64 or float32 (the reference controller runs float64)."),
    Column("device", "str", "cpu or gpu."),
    Column("samples", "int64", "Number of model samples n."),
    Column("repeat", "int64", "Index of the timed step (-1 on a skipped row)."),
    Column("state_index", "int64", "Step index of the state along the scripted push."),
    Column("total_ms", "float64", "Control-step time (wall)."),
    Column("lcs_ms", "float64", "LCS build."),
    Column("qp_ms", "float64", "QP steps (factorisations, gradients, linear passes)."),
    Column("proj_ms", "float64", "Projections (NaN for c3plus-jax)."),
    Column("overhead_ms", "float64", "total - lcs - qp - proj (total - lcs - qp for JAX)."),
    Column("cpu_ms", "float64", "Process CPU time of the step."),
    Column("iterations", "int64", "ADMM iterations."),
    Column("horizon", "int64", "Horizon T."),
    Column("ok", "bool", "The controller returned a finite input without falling back."),
    Column("cache_hits", "int64", "Factorisation cache hits in the step (-1: not applicable)."),
    Column("cache_misses", "int64", "Factorisation cache misses in the step (-1: not "
           "applicable)."),
    Column("skipped", "bool", "Configuration not measured (see note)."),
    Column("note", "str", "Why skipped, or what was cut."),
    Column("blas_threads", "int64", "BLAS threads during the measurement."),
    Column("affinity", "str", "CPU cores the process may run on (--cpu pins it to one)."),
    Column("load_avg", "float64", "1-minute load average when the configuration started."),
    Column("host", "str", "Machine name, processor and cores."),
)
PERF_COLUMNS: tuple[str, ...] = tuple(column.name for column in PERF_SCHEMA)
PERF_READABLE: tuple[int, ...] = (1, SCHEMA_VERSION)
"""Schema versions whose perf tables this c3bench reads: :data:`PERF_SCHEMA` is unchanged
since version 1 (version 2 changed the results table only), so stored perf runs are kept."""




def perf_files(results_dir: str | Path) -> tuple[Path, Path]:
    """The consolidated ``perf.parquet`` and ``perf.csv`` (every run) under :func:`perf_dir`."""
    directory = perf_dir(results_dir)
    return directory / "perf.parquet", directory / "perf.csv"


def perf_run_files(results_dir: str | Path) -> list[Path]:
    """The file of each stored run, ``perf/runs/<run_id>.parquet``, oldest first."""
    return sorted((perf_dir(results_dir) / PERF_RUNS).glob("*.parquet"))


def write_perf(frame: pd.DataFrame, results_dir: str | Path) -> tuple[Path, Path]:
    """Store the rows of one or more runs, keeping every earlier run; return the
    consolidated ``perf.parquet`` and ``perf.csv``.

    Each run (``run_id``) goes to its own ``perf/runs/<run_id>.parquet`` (a new id when that
    file exists: a run never overwrites another), then ``perf.parquet`` and ``perf.csv`` are
    rewritten atomically with every stored run. The first write beside a table of the
    layout before per-run files turns its runs into run files, so they are kept too.
    """
    runs = perf_dir(results_dir) / PERF_RUNS
    if not runs.is_dir():
        _adopt_perf_table(results_dir)
    for run_id, rows in frame.groupby("run_id", sort=False):
        stem, suffix = _file_safe(str(run_id)), 1
        while (runs / f"{stem}.parquet").exists():
            suffix += 1
            stem = f"{_file_safe(str(run_id))}.{suffix}"
        if suffix > 1:
            rows = rows.assign(run_id=stem)
        atomic_write_bytes(runs / f"{stem}.parquet", parquet_bytes(rows))
    return consolidate_perf(results_dir)


def _file_safe(text: str) -> str:
    """``text`` with every character but letters, digits, ``.``, ``_`` and ``-`` as ``_``."""
    return re.sub(r"[^A-Za-z0-9._-]", "_", text) or "run"


def _adopt_perf_table(results_dir: str | Path) -> None:
    """Write one run file per run of an existing consolidated table (when there is one)."""
    parquet, csv = perf_files(results_dir)
    if not (parquet.exists() or csv.exists()):
        return
    old = read_perf(results_dir)
    runs = perf_dir(results_dir) / PERF_RUNS
    for run_id, rows in old.groupby("run_id", sort=False):
        atomic_write_bytes(runs / f"{_file_safe(str(run_id))}.parquet",
                           parquet_bytes(rows.reset_index(drop=True)))


def consolidate_perf(results_dir: str | Path) -> tuple[Path, Path]:
    """Rewrite ``perf.parquet`` and ``perf.csv`` with every run file, oldest run first."""
    frames = [read_parquet(path, PERF_READABLE).to_pandas()
              for path in perf_run_files(results_dir)]
    frame = pd.concat(frames, ignore_index=True) if frames else \
        pd.DataFrame(columns=list(PERF_COLUMNS))
    parquet, csv = perf_files(results_dir)
    atomic_write_bytes(parquet, parquet_bytes(frame))
    atomic_write_bytes(csv, frame.to_csv(index=False).encode())
    return parquet, csv


def read_perf(results_dir: str | Path) -> pd.DataFrame:
    """Read ``<results_dir>/perf/perf.parquet`` (or the CSV), every stored run; reject
    another schema version.

    Raises ``FileNotFoundError`` when there is no measurement.
    """
    parquet, csv = perf_files(results_dir)
    if parquet.exists():
        frame = read_parquet(parquet, PERF_READABLE).to_pandas()
    elif csv.exists():
        frame = pd.read_csv(csv, keep_default_na=False, na_values=["nan", "NaN", ""])
        check_frame_version(frame, csv, PERF_READABLE)
    else:
        raise FileNotFoundError(f"no perf results under {parquet.parent}; run `c3bench perf`")
    return frame


def latest_perf_runs(frame: pd.DataFrame) -> pd.DataFrame:
    """The rows of the latest run (largest ``run_id``) of each machine (``host``)."""
    if frame.empty:
        return frame
    ids = frame["run_id"].astype(str)
    latest = ids.groupby(frame["host"].astype(str)).transform("max")
    return frame[ids == latest].reset_index(drop=True)
