"""The stored history of ``c3bench perf``: its schema and files under ``ROOT/perf/``.

``ROOT/perf/runs/<run_id>.parquet`` holds the control-step times of one run
(:data:`PERF_SCHEMA`, one row per timed step; a run never overwrites another),
``ROOT/perf/perf.parquet`` and ``perf.csv`` every run together, and
``figures/perf_time_vs_samples.png`` the latest run of each machine. Versions, atomic writes and
Parquet helpers are those of :mod:`bench.store`; the perf table's own layout is versioned
beside them (:data:`PERF_SCHEMA_VERSION`: layout 2 added the weighting, ADMM-alone, flop-model,
matmul-rate and compile-time columns, layout 3 the executed flops, layout 4 the cache state
of each step, layout 5 the matmul rate through the run, layout 6 the process each
configuration ran in), and files of layouts 1 to 5 are still read, their missing columns NaN
(:func:`upgrade_perf_frame`).
"""

from __future__ import annotations

import math
import re
from enum import StrEnum
from pathlib import Path

import pandas as pd
import pyarrow as pa

from c3bench.bench.store import (
    PERF_RUNS,
    SCHEMA_VERSION,
    Column,
    check_frame_version,
    parquet_bytes,
    perf_dir,
    read_parquet,
    results_folder,
)
from c3bench.problems.errors import SchemaVersionError
from c3bench.problems.instance import atomic_write_bytes

# --- perf: control-step times -----------------------------------------------------------------
PERF_SCHEMA_VERSION = 6
"""Version of the perf table's own layout (beside :data:`SCHEMA_VERSION`, which every table
of :mod:`bench.store` carries): 1 without the columns of :data:`PERF_V2_COLUMNS`, 2 with
them but ``admm_mflop_executed``, ``cache``, ``matmul_run_gflops_*`` and ``process``, 3
without the last three, 4 without ``matmul_run_gflops_*`` and ``process``, 5 without
``process``, 6 with all of them. Stored in the ``perf_schema_version`` column and the Parquet
metadata key :data:`PERF_METADATA_KEY`; a file of layout 1 (neither) to 5 is read with the
columns it lacks NaN (``False`` for ``weighted``, ``cache`` by :func:`old_cache_states`,
``process`` ``shared``: those runs measured every configuration in one process)."""


class ProcessMode(StrEnum):
    """Where a configuration's steps ran (``process`` column; :mod:`bench.perf_workers`)."""

    WORKER = "worker"
    """A worker process of its own, forked from the run's process (the default)."""
    SHARED = "shared"
    """The run's own process, with the other configurations (``--same-process``)."""


class CacheState(StrEnum):
    """What ran on the core just before a timed control step (``cache`` column).

    ``c3bench perf`` times each configuration in blocks of consecutive steps per round
    (:mod:`bench.perf`): the first step of a block follows another configuration's step or
    the round's matmul probe, whose code and data have pushed this one's out of the core's
    caches (``COLD``; measured on the
    2-core EPYC VM: flushing 64 MB before the compiled one-sample step costs it 0.16 ms of
    ADMM and 0.4 ms of LCS build), the others follow this configuration's own steps
    (``WARM``, as a controller in its loop, where only the plant runs between its steps).
    Before layout 5, with one configuration per sample count every step was ``WARM`` (no
    probe ran between its blocks).
    """

    COLD = "cold"
    WARM = "warm"

PERF_METADATA_KEY = b"c3bench_perf_schema"
PERF_SCHEMA: tuple[Column, ...] = (
    Column("schema_version", "int64", ":data:`SCHEMA_VERSION`."),
    Column("run_id", "str", "UTC time stamp of the run."),
    Column("backend", "str", "c3plus-riccati, c3plus-compiled, c3plus-jax, c3-osqp or "
           "c3-clarabel."),
    Column("precision", "str", "float64 or float32 (the reference controller runs float64)."),
    Column("device", "str", "cpu or gpu."),
    Column("samples", "int64", "Number of model samples n."),
    Column("repeat", "int64", "Index of the timed step (-1 on a skipped row)."),
    Column("state_index", "int64", "Step index of the state along the scripted push."),
    Column("total_ms", "float64", "Whole control step (wall): LCS build + weighting + ADMM."),
    Column("lcs_ms", "float64", "LCS build."),
    Column("qp_ms", "float64", "QP steps (factorisations, gradients, linear passes)."),
    Column("proj_ms", "float64", "Projections (NaN for c3plus-jax)."),
    Column("overhead_ms", "float64", "total - lcs - weighting - qp - proj (total - lcs - "
           "weighting - qp for JAX)."),
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
    # layout 2
    Column("perf_schema_version", "int64", ":data:`PERF_SCHEMA_VERSION`."),
    Column("weighted", "bool", "The step weighted its samples by their LCP prediction error."),
    Column("weighting_ms", "float64", "LCP-error sample weighting (0 when not weighted)."),
    Column("admm_ms", "float64", "The controller's ADMM call alone (wall)."),
    Column("total_no_weighting_ms", "float64", "total - weighting: LCS build + ADMM."),
    Column("admm_mflop", "float64", "Flops of the step's ADMM by the flop model "
           "(bench/perf_flops.py), in millions; NaN for the reference controller."),
    Column("matmul_gflops_f64", "float64", "The run's dense float64 matmul rate, one thread."),
    Column("matmul_gflops_f32", "float64", "The run's dense float32 matmul rate, one thread."),
    Column("compile_s", "float64", "JIT compile seconds of the backend (in the warm-up, "
           "excluded from the step times; NaN when not compiled)."),
    # layout 3
    Column("admm_mflop_executed", "float64", "Flops the backend executed in the step's ADMM, "
           "in millions: the compiled kernel's own count (fewer than the model's: Cholesky, "
           "symmetric products, structural zeros skipped), the flop model's for the numpy and "
           "JAX paths; NaN for the reference controller and in layouts 1-2."),
    # layout 4
    Column("cache", "str", "cold: the step follows another configuration's step or the "
           "round's matmul probe; warm: it follows a step of its own configuration "
           "(:class:`CacheState`; layouts 1-3: cold when the run measured several "
           "configurations at that sample count)."),
    # layout 5
    Column("matmul_run_gflops_f64", "float64", "The dense float64 matmul rate through the "
           "run: the median over the timed rounds of this sample count of each round's "
           "median of 3 products (bench/perf_flops.py, MatmulProbe); NaN in layouts 1-4."),
    Column("matmul_run_gflops_f32", "float64", "The same in float32."),
    # layout 6
    Column("process", "str", "worker: the configuration was prepared and stepped in a "
           "worker process of its own; shared: in the run's process with the others "
           "(--same-process; every run of layouts 1-5) (:class:`ProcessMode`)."),
)
PERF_COLUMNS: tuple[str, ...] = tuple(column.name for column in PERF_SCHEMA)
PERF_V2_COLUMNS: tuple[str, ...] = PERF_COLUMNS[PERF_COLUMNS.index("perf_schema_version"):]
"""Columns added by perf layouts 2 to 6 (filled with NaN, ``weighted`` ``False``, ``cache`` by
:func:`old_cache_states`, ``process`` ``shared``, when an older file lacks them)."""
PERF_READABLE: tuple[int, ...] = (1, SCHEMA_VERSION)
"""Values of :data:`SCHEMA_VERSION` whose perf tables this c3bench reads (the perf table's own
changes are versioned by :data:`PERF_SCHEMA_VERSION`)."""


def old_cache_states(frame: pd.DataFrame) -> pd.Series:
    """The cache state of the rows of a table from before layout 4, which timed the
    configurations of one sample count round-robin one step at a time: ``cold`` where the run
    timed several configurations at that sample count (every step followed another one's),
    ``warm`` where it timed one, ``""`` on skipped rows (as layout 4 stores them)."""
    skipped = frame["skipped"].astype(bool)
    timed = frame[~skipped]
    configurations = timed.drop_duplicates(
        ["run_id", "samples", "backend", "precision", "device"]).groupby(
        ["run_id", "samples"]).size()
    several = set(configurations[configurations > 1].index)
    return pd.Series(["" if skip else CacheState.COLD.value if (run, samples) in several
                      else CacheState.WARM.value for run, samples, skip in zip(
                          frame["run_id"], frame["samples"], skipped, strict=True)],
                     index=frame.index, dtype=object)


_OLD_LAYOUT_VALUES: dict[str, object] = {"weighted": False, "process": ProcessMode.SHARED.value}
"""What a column of :data:`PERF_V2_COLUMNS` holds in a file of a layout before it (NaN for
the others; ``cache`` is filled by :func:`old_cache_states`)."""


def upgrade_perf_frame(frame: pd.DataFrame, source: Path | str) -> pd.DataFrame:
    """The rows of a stored perf table in the current layout: a table of layouts 1 to 5 gets
    the columns of :data:`PERF_V2_COLUMNS` it lacks (NaN, ``weighted`` ``False``, ``cache`` by
    :func:`old_cache_states`, ``process`` ``shared``; a file without a layout is version 1); a
    newer
    layout than :data:`PERF_SCHEMA_VERSION` raises :class:`SchemaVersionError`."""
    frame = frame.copy()
    if "perf_schema_version" not in frame.columns:
        frame["perf_schema_version"] = 1
    versions = set(pd.to_numeric(frame["perf_schema_version"]).astype(int).tolist())
    newer = sorted(v for v in versions if v > PERF_SCHEMA_VERSION or v < 1)
    if newer:
        raise SchemaVersionError(
            f"{source}: perf table layout {newer[0]}, this c3bench reads layouts 1 to "
            f"{PERF_SCHEMA_VERSION}; delete or move {results_folder(Path(source))}")
    for name in PERF_V2_COLUMNS:
        if name not in frame.columns:
            frame[name] = _OLD_LAYOUT_VALUES.get(name, math.nan)
    if "cache" in frame.columns and frame["cache"].isna().any():
        frame["cache"] = frame["cache"].astype(object).where(frame["cache"].notna(),
                                                            old_cache_states(frame))
    return frame


def _perf_parquet_bytes(frame: pd.DataFrame) -> bytes:
    """:func:`bench.store.parquet_bytes` with :data:`PERF_SCHEMA_VERSION` in the metadata."""
    table = pa.Table.from_pandas(frame, preserve_index=False)
    metadata = dict(table.schema.metadata or {})
    metadata[PERF_METADATA_KEY] = str(PERF_SCHEMA_VERSION).encode()
    return parquet_bytes(table.replace_schema_metadata(metadata))


def _read_perf_parquet(path: Path) -> pd.DataFrame:
    """A perf Parquet file in the current layout (both versions checked)."""
    table = read_parquet(path, PERF_READABLE)
    frame = table.to_pandas()
    raw = (table.schema.metadata or {}).get(PERF_METADATA_KEY)
    if raw is not None and "perf_schema_version" not in frame.columns:
        frame["perf_schema_version"] = int(raw) if raw.decode().isdigit() else -1
    return upgrade_perf_frame(frame, path)


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
        atomic_write_bytes(runs / f"{stem}.parquet", _perf_parquet_bytes(rows))
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
                           _perf_parquet_bytes(rows.reset_index(drop=True)))


def consolidate_perf(results_dir: str | Path) -> tuple[Path, Path]:
    """Rewrite ``perf.parquet`` and ``perf.csv`` with every run file, oldest run first."""
    frames = [_read_perf_parquet(path) for path in perf_run_files(results_dir)]
    frame = pd.concat(frames, ignore_index=True) if frames else \
        pd.DataFrame(columns=list(PERF_COLUMNS))
    parquet, csv = perf_files(results_dir)
    atomic_write_bytes(parquet, _perf_parquet_bytes(frame))
    atomic_write_bytes(csv, frame.to_csv(index=False).encode())
    return parquet, csv


def read_perf(results_dir: str | Path) -> pd.DataFrame:
    """Read ``<results_dir>/perf/perf.parquet`` (or the CSV), every stored run, in the
    current layout (:func:`upgrade_perf_frame`); reject another schema version.

    Raises ``FileNotFoundError`` when there is no measurement.
    """
    parquet, csv = perf_files(results_dir)
    if parquet.exists():
        frame = _read_perf_parquet(parquet)
    elif csv.exists():
        frame = pd.read_csv(csv, keep_default_na=False, na_values=["nan", "NaN", ""])
        check_frame_version(frame, csv, PERF_READABLE)
        frame = upgrade_perf_frame(frame, csv)
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
