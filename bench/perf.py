"""``c3bench perf``: the time of one C3+ control step, per backend and number of model samples.

**Control step** (what is timed, wall clock with ``time.perf_counter``; CPU time with
``time.process_time`` beside it): the LCS build for all ``n`` samples at a state along the
scripted push (:func:`problems.suites.scripted_push`, states in the contact band, visited in
order, the controller warm-started from the previous step as in closed loop) plus
``iterations`` ADMM iterations (default 10, geometric rho schedule, the seed's rho0), horizon
``T`` of the task config (7), planar scene. Samples have cube sides ``l_j ~ U[0.27, 0.33]``
(seeded; ``n = 1`` uses the seed's model side 0.29) with uniform weights and shared inputs.

**Backends**

* ``c3plus-riccati``: :class:`solvers.fast.FastC3Plus` (numpy, batched Riccati) with
  :class:`problems.lcs_batch.BatchLinearizer`;
* ``c3plus-jax``: :class:`solvers.fast_jax.JaxC3Plus` (one compiled call per step) with the
  same LCS build; only when JAX imports, on ``--device cpu`` (XLA pinned to one thread when
  this module sets ``XLA_FLAGS`` before JAX is first imported) or ``gpu`` (a row
  "no GPU visible" when JAX sees none; nothing is faked);
* ``c3-osqp``, ``c3-clarabel``: the reference controller :mod:`solvers.c3` (C3+ variant,
  :class:`solvers.c3.C3Controller`) with that registry QP backend at its default settings and
  :func:`problems.lcs.linearize` per sample; ``n = 1`` through ``step`` and ``n = 16``
  through ``step_robust`` (one stacked QP), other ``n`` skipped; a configuration whose first
  (warm-up) step takes longer than ``reference_budget`` seconds is skipped with a note, and
  the repeats are cut to fit the budget otherwise (noted).

**Split** of each step: ``lcs`` (LCS build), ``qp`` (QP steps: factorisations, gradients and
linear passes; for the reference controller the QP build and the backend's solve), ``proj``
(projections, with the shared-input mean), ``overhead = total - lcs - qp - proj`` (Python,
dual updates, residual bookkeeping, warm start). For ``c3plus-jax`` the ADMM is one compiled
call: ``qp`` holds the whole call (projections included) and ``proj`` is ``nan``.
Warm-up steps (default 2; JAX compiles in them) are excluded; BLAS is pinned to one thread
(threadpoolctl) during every measurement and the count is recorded; ``--cpu N`` pins the
whole process to core ``N`` (XLA's CPU runtime may otherwise use a second core even with one
intra-op thread: its CPU time then exceeds the wall time).

**Files** (written atomically under ``<results>/perf/``): ``perf.parquet`` and ``perf.csv``,
one row per timed control step (plus one row per skipped configuration), schema version
:data:`SCHEMA_VERSION`:

==============  =======  ===========================================================
column          type     meaning
==============  =======  ===========================================================
schema_version  int      :data:`SCHEMA_VERSION`
run_id          str      UTC time stamp of the run
backend         str      ``c3plus-riccati``, ``c3plus-jax``, ``c3-osqp``, ``c3-clarabel``
precision       str      ``float64`` or ``float32`` (the reference runs float64)
device          str      ``cpu`` or ``gpu``
samples         int      number of model samples ``n``
repeat          int      index of the timed step (``-1`` on a skipped row)
state_index     int      step index of the state along the scripted push
total_ms        float    control-step time (wall)
lcs_ms          float    LCS build
qp_ms           float    QP steps (see above)
proj_ms         float    projections (``nan`` for c3plus-jax)
overhead_ms     float    ``total - lcs - qp - proj`` (``total - lcs - qp`` for JAX)
cpu_ms          float    process CPU time of the step
iterations      int      ADMM iterations
horizon         int      ``T``
ok              bool     the controller returned a finite input without falling back
cache_hits      int      factorisation cache hits in the step (``-1``: not applicable)
cache_misses    int      factorisation cache misses in the step (``-1``: not applicable)
skipped         bool     configuration not measured (see ``note``)
note            str      why skipped, or what was cut
blas_threads    int      BLAS threads during the measurement
affinity        str      CPU cores the process may run on (``--cpu`` pins it to one)
load_avg        float    1-minute load average when the configuration started
host            str      machine name and processor
==============  =======  ===========================================================

``results/perf/figures/perf_time_vs_samples.png``: median control-step time against the
number of samples (log-log, p95 as error bars), with the seed's 60 ms and the 6 ms target.
:func:`perf_report_section` renders the summary as Markdown for the report.
"""

from __future__ import annotations

import argparse
import gc
import io
import math
import os
import platform
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

SCHEMA_VERSION = 1
BACKENDS: tuple[str, ...] = ("c3plus-riccati", "c3plus-jax", "c3-osqp", "c3-clarabel")
REFERENCE_BACKENDS: dict[str, str] = {"c3-osqp": "osqp", "c3-clarabel": "clarabel"}
REFERENCE_SAMPLES: tuple[int, ...] = (1, 16)
SEED_STEP_MS = 60.0
"""The seed's control step (0.06 s with 16 samples, float32, including the LCS build)."""
TARGET_STEP_MS = 6.0
"""The issue's target for 16 samples on one core."""
COLUMNS: tuple[str, ...] = (
    "schema_version", "run_id", "backend", "precision", "device", "samples", "repeat",
    "state_index", "total_ms", "lcs_ms", "qp_ms", "proj_ms", "overhead_ms", "cpu_ms",
    "iterations", "horizon", "ok", "cache_hits", "cache_misses", "skipped", "note",
    "blas_threads", "affinity", "load_avg", "host",
)
XLA_ONE_THREAD = "--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1"


@dataclass
class PerfSettings:
    """What ``c3bench perf`` measures (module docstring)."""

    samples: tuple[int, ...] = (1, 16, 64, 256, 1024)
    backends: tuple[str, ...] = BACKENDS
    precisions: tuple[str, ...] = ("float64",)
    device: str = "cpu"
    repeats: int = 20
    warmup: int = 2
    iterations: int = 10
    reference_budget: float = 60.0
    seed: int = 0
    results_dir: Path = field(default_factory=lambda: Path("results"))
    cpu: int | None = None

    def __post_init__(self) -> None:
        self.samples = tuple(int(n) for n in self.samples)
        if not self.samples or min(self.samples) < 1:
            raise ValueError(f"samples must be integers >= 1, got {self.samples}")
        unknown = set(self.backends) - set(BACKENDS)
        if unknown:
            raise ValueError(f"unknown backends {sorted(unknown)}; known: {', '.join(BACKENDS)}")
        if set(self.precisions) - {"float64", "float32"}:
            raise ValueError(f"precisions must be float64 or float32, got {self.precisions}")
        if self.device not in ("cpu", "gpu"):
            raise ValueError(f"device must be cpu or gpu, got {self.device!r}")
        if self.repeats < 1 or self.warmup < 0 or self.iterations < 1:
            raise ValueError("repeats and iterations must be >= 1, warmup >= 0")
        if not self.reference_budget > 0:
            raise ValueError("reference_budget must be > 0")
        self.results_dir = Path(self.results_dir)


@dataclass
class _Context:
    """Shared inputs: config, MPC, the states visited, identity of the run."""

    config: Any
    mpc: Any
    states: list[tuple[int, np.ndarray, np.ndarray]]
    run_id: str
    host: str


def _host() -> str:
    processor = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as handle:
            for line in handle:
                if line.startswith("model name"):
                    processor = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    return f"{platform.node()} ({processor}, {os.cpu_count()} cores)"


def _affinity() -> str:
    """The CPU cores this process may run on, as text (``all`` when unknown)."""
    try:
        return ",".join(str(c) for c in sorted(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return "all"


def _load() -> float:
    try:
        return float(os.getloadavg()[0])
    except OSError:
        return math.nan


def pin_jax_threads() -> bool:
    """Put XLA's CPU backend on one thread (``XLA_FLAGS``) if JAX is not imported yet."""
    if "jax" in sys.modules:
        return XLA_ONE_THREAD in os.environ.get("XLA_FLAGS", "")
    flags = os.environ.get("XLA_FLAGS", "")
    if XLA_ONE_THREAD not in flags:
        os.environ["XLA_FLAGS"] = f"{flags} {XLA_ONE_THREAD}".strip()
    return True


def _context(settings: PerfSettings) -> _Context:
    from c3bench.problems.config import load_config
    from c3bench.problems.mpc import build_mpc
    from c3bench.problems.scene import build_scene
    from c3bench.problems.suites import sample_states, scripted_push

    config = load_config()
    record = scripted_push(config)
    indices = sample_states(record, 24, 0.02)
    states = [(i, record.states[i], record.inputs[max(i - 1, 0)]) for i in indices]
    mpc = build_mpc(build_scene(l=0.29, config=config), config.mpc)
    run_id = datetime.now(UTC).strftime("%Y%m%dT%H%M%SZ")
    return _Context(config=config, mpc=mpc, states=states, run_id=run_id, host=_host())


def sample_sides(samples: int, seed: int) -> np.ndarray:
    """Cube sides of the samples: ``[0.29]`` for one, else ``U[0.27, 0.33]`` (seeded)."""
    if samples == 1:
        return np.array([0.29])
    return np.random.default_rng([seed, samples]).uniform(0.27, 0.33, samples)


def _row(context: _Context, settings: PerfSettings, backend: str, precision: str,
         device: str, samples: int, **values: Any) -> dict[str, Any]:
    row: dict[str, Any] = {
        "schema_version": SCHEMA_VERSION, "run_id": context.run_id, "backend": backend,
        "precision": precision, "device": device, "samples": samples, "repeat": -1,
        "state_index": -1, "total_ms": math.nan, "lcs_ms": math.nan, "qp_ms": math.nan,
        "proj_ms": math.nan, "overhead_ms": math.nan, "cpu_ms": math.nan,
        "iterations": settings.iterations, "horizon": int(context.mpc.horizon), "ok": False,
        "cache_hits": -1, "cache_misses": -1, "skipped": False, "note": "",
        "blas_threads": 1, "affinity": _affinity(), "load_avg": math.nan,
        "host": context.host,
    }
    row.update(values)
    return row


Step = Callable[[int, np.ndarray, np.ndarray], dict[str, Any]]


def _measure(context: _Context, settings: PerfSettings, backend: str, precision: str,
             device: str, samples: int, step: Step, repeats: int, note: str = ""
             ) -> list[dict[str, Any]]:
    """Warm-up, then ``repeats`` timed steps of ``step(state_index, x, u_prev)``."""
    from c3bench.solvers.timing import blas_threads, single_thread_blas

    rows = []
    load = _load()
    gc.collect()
    with single_thread_blas():
        threads = blas_threads()
        for r in range(settings.warmup + repeats):
            index, x, u_prev = context.states[r % len(context.states)]
            wall, cpu = time.perf_counter(), time.process_time()
            parts = step(index, x, u_prev)
            cpu = time.process_time() - cpu
            wall = time.perf_counter() - wall
            if r < settings.warmup:
                continue
            total = 1e3 * wall
            lcs, qp, proj = (1e3 * parts.get(k, math.nan) for k in ("lcs", "qp", "proj"))
            known = lcs + qp + (0.0 if math.isnan(proj) else proj)
            rows.append(_row(context, settings, backend, precision, device, samples,
                             repeat=r - settings.warmup, state_index=index, total_ms=total,
                             lcs_ms=lcs, qp_ms=qp, proj_ms=proj,
                             overhead_ms=max(total - known, 0.0), cpu_ms=1e3 * cpu,
                             ok=bool(parts.get("ok", False)),
                             cache_hits=int(parts.get("cache_hits", -1)),
                             cache_misses=int(parts.get("cache_misses", -1)), note=note,
                             blas_threads=threads, load_avg=load))
    return rows


def _fast_step(context: _Context, settings: PerfSettings, samples: int, precision: str,
               backend: str, device: str) -> Step:
    from c3bench.problems.lcs_batch import BatchLinearizer
    from c3bench.solvers.c3 import C3Options
    from c3bench.solvers.fast import FastC3Plus, FastC3PlusController, RiccatiOptions

    options = C3Options(keep_iterates=False, admm_iterations=settings.iterations)
    linearizer = BatchLinearizer(sample_sides(samples, settings.seed), context.config)
    solver: Any
    if backend == "c3plus-jax":
        from c3bench.solvers.fast_jax import JaxC3Plus

        solver = JaxC3Plus(context.mpc, options, precision=precision, device=device)
    else:
        solver = FastC3Plus(context.mpc, options, RiccatiOptions(precision=precision))
    controller = FastC3PlusController(solver)
    dt = context.config.mpc.dt

    def step(index: int, x: np.ndarray, u_prev: np.ndarray) -> dict[str, Any]:
        start = time.perf_counter()
        lcs = linearizer.linearize(x, u_prev, dt)
        lcs_time = time.perf_counter() - start
        solution = controller.step(lcs, x)
        timings = solution.timings
        parts: dict[str, Any] = {"lcs": lcs_time, "ok": solution.ok}
        if backend == "c3plus-jax":
            parts.update(qp=timings.total, proj=math.nan)
        else:
            parts.update(qp=timings.qp, proj=timings.projection,
                         cache_hits=solution.cache_hits, cache_misses=solution.cache_misses)
        return parts

    return step


def _reference_step(context: _Context, settings: PerfSettings, samples: int, backend: str
                    ) -> Step:
    from c3bench.problems.lcs import linearize
    from c3bench.problems.scene import build_scene
    from c3bench.solvers.c3 import C3Controller, C3Options

    options = C3Options(qp_backend=REFERENCE_BACKENDS[backend], keep_iterates=False,
                        admm_iterations=settings.iterations)
    controller = C3Controller(options)
    scenes = [build_scene(l=float(side), config=context.config)
              for side in sample_sides(samples, settings.seed)]
    dt = context.config.mpc.dt

    def step(index: int, x: np.ndarray, u_prev: np.ndarray) -> dict[str, Any]:
        start = time.perf_counter()
        systems = [linearize(scene, x, u_prev, dt) for scene in scenes]
        lcs_time = time.perf_counter() - start
        if samples == 1:
            solution = controller.step(systems[0], context.mpc, x)
        else:
            solution = controller.step_robust(systems, None, context.mpc, x)
        trace = solution.trace
        return {"lcs": lcs_time, "qp": sum(trace.qp_build_time) + sum(trace.qp_time),
                "proj": sum(trace.projection_time), "ok": solution.ok}

    return step


def run_perf(settings: PerfSettings, echo: Callable[[str], None] | None = print
             ) -> pd.DataFrame:
    """Measure every configuration, write the files and the figure, return the rows."""
    if settings.cpu is None:
        return _run_perf(settings, echo)
    previous = os.sched_getaffinity(0)
    os.sched_setaffinity(0, {settings.cpu})
    try:
        return _run_perf(settings, echo)
    finally:
        os.sched_setaffinity(0, previous)


def _run_perf(settings: PerfSettings, echo: Callable[[str], None] | None) -> pd.DataFrame:
    say = echo or (lambda _: None)
    wants_jax = "c3plus-jax" in settings.backends
    if wants_jax and settings.device == "cpu":
        pin_jax_threads()
    context = _context(settings)
    from c3bench.solvers.timing import blas_threads, single_thread_blas

    with single_thread_blas():
        threads = blas_threads()
    say(f"# c3bench perf  {context.run_id}  host {context.host}")
    say(f"# T={context.mpc.horizon}  ADMM iterations={settings.iterations}  "
        f"dt={context.config.mpc.dt}  planar  BLAS threads={threads} (pinned)  cores "
        f"{_affinity()}  load average {_load():.2f}  warm-up {settings.warmup}  repeats "
        f"{settings.repeats}")
    rows: list[dict[str, Any]] = []
    for backend in settings.backends:
        precisions = ("float64",) if backend in REFERENCE_BACKENDS else settings.precisions
        device = settings.device if backend == "c3plus-jax" else "cpu"
        for precision in precisions:
            for samples in settings.samples:
                new = _run_one(context, settings, backend, precision, device, samples, say)
                rows.extend(new)
    frame = pd.DataFrame(rows, columns=list(COLUMNS))
    write_perf(frame, settings.results_dir)
    plot_perf(frame, settings.results_dir / "perf" / "figures" / "perf_time_vs_samples.png")
    return frame


def _run_one(context: _Context, settings: PerfSettings, backend: str, precision: str,
             device: str, samples: int, say: Callable[[str], None]) -> list[dict[str, Any]]:
    label = f"{backend:<15} {precision:<8} {device:<4} samples={samples:<5}"

    def skip(note: str) -> list[dict[str, Any]]:
        say(f"{label} skipped: {note}")
        return [_row(context, settings, backend, precision, device, samples, skipped=True,
                     note=note, load_avg=_load())]

    if backend == "c3plus-jax":
        from c3bench.solvers.fast_jax import JaxUnavailable, gpu_available, jax_available

        if not jax_available():
            return skip("JAX not installed (pip install 'c3bench[jax]')")
        if device == "gpu" and not gpu_available():
            return skip("no GPU visible")
        try:
            step = _fast_step(context, settings, samples, precision, backend, device)
        except JaxUnavailable as error:
            return skip(str(error))
        rows = _measure(context, settings, backend, precision, device, samples, step,
                        settings.repeats)
    elif backend == "c3plus-riccati":
        step = _fast_step(context, settings, samples, precision, backend, device)
        rows = _measure(context, settings, backend, precision, device, samples, step,
                        settings.repeats)
    else:
        if samples not in REFERENCE_SAMPLES:
            return skip(f"the reference controller is measured at samples "
                        f"{'/'.join(map(str, REFERENCE_SAMPLES))} only")
        from c3bench.solvers import registry

        if not registry.get(REFERENCE_BACKENDS[backend]).availability()[0]:
            return skip(f"{REFERENCE_BACKENDS[backend]} not available")
        step = _reference_step(context, settings, samples, backend)
        start = time.perf_counter()
        from c3bench.solvers.timing import single_thread_blas

        with single_thread_blas():
            index, x, u_prev = context.states[0]
            step(index, x, u_prev)
        first = time.perf_counter() - start
        if first > settings.reference_budget:
            return skip(f"one control step took {first:.1f} s > budget "
                        f"{settings.reference_budget:g} s")
        affordable = int(settings.reference_budget // max(first, 1e-9))
        repeats = max(1, min(settings.repeats, affordable - settings.warmup))
        note = "" if repeats == settings.repeats else \
            f"repeats cut to {repeats} (budget {settings.reference_budget:g} s)"
        rows = _measure(context, settings, backend, precision, device, samples, step,
                        repeats, note)
    say(format_line(pd.DataFrame(rows, columns=list(COLUMNS))))
    return rows


# --- summaries, files, figure, report -----------------------------------------------------------
def _p95(values: Sequence[float]) -> float:
    return float(np.percentile(np.asarray(values, dtype=float), 95)) if len(values) else math.nan


def summarize(frame: pd.DataFrame) -> pd.DataFrame:
    """Per (backend, precision, device, samples): repeats, median and p95 of the total,
    medians of the parts, the overhead fraction and the failed steps."""
    out = []
    keys = ["backend", "precision", "device", "samples"]
    for key, group in frame.groupby(keys, sort=False):
        timed = group[~group["skipped"].astype(bool)]
        record = dict(zip(keys, key, strict=True))
        if timed.empty:
            record.update(repeats=0, median_ms=math.nan, p95_ms=math.nan, lcs_ms=math.nan,
                          qp_ms=math.nan, proj_ms=math.nan, overhead_ms=math.nan,
                          cpu_ms=math.nan, overhead_fraction=math.nan, failed=0,
                          note="; ".join(sorted(set(group["note"].astype(str)) - {""})))
        else:
            median = float(timed["total_ms"].median())
            overhead = float(timed["overhead_ms"].median())
            record.update(
                repeats=len(timed), median_ms=median, p95_ms=_p95(timed["total_ms"].tolist()),
                lcs_ms=float(timed["lcs_ms"].median()), qp_ms=float(timed["qp_ms"].median()),
                proj_ms=float(timed["proj_ms"].median()), overhead_ms=overhead,
                cpu_ms=float(timed["cpu_ms"].median()),
                overhead_fraction=overhead / median if median > 0 else math.nan,
                failed=int((~timed["ok"].astype(bool)).sum()),
                note="; ".join(sorted(set(timed["note"].astype(str)) - {""})))
        out.append(record)
    return pd.DataFrame(out)


def _ms(value: float) -> str:
    if not math.isfinite(value):
        return "-"
    return f"{value:.1f}" if value >= 10 else f"{value:.2f}"


def format_line(rows: pd.DataFrame) -> str:
    """``backend  samples=n  median .. ms  p95 .. ms  lcs ..  qp ..  proj ..  overhead ..``."""
    lines = []
    for _, s in summarize(rows).iterrows():
        head = f"{s['backend']:<15} {s['precision']:<8} {s['device']:<4} samples={s['samples']:<5}"
        if s["repeats"] == 0:
            lines.append(f"{head} skipped: {s['note']}")
            continue
        proj = "(compiled)" if s["backend"] == "c3plus-jax" else _ms(s["proj_ms"])
        qp_label = "qp+proj" if s["backend"] == "c3plus-jax" else "qp"
        text = (f"{head} median {_ms(s['median_ms'])} ms  p95 {_ms(s['p95_ms'])} ms  "
                f"lcs {_ms(s['lcs_ms'])}  {qp_label} {_ms(s['qp_ms'])}  proj {proj}  "
                f"overhead {_ms(s['overhead_ms'])}  cpu {_ms(s['cpu_ms'])}  "
                f"(n={s['repeats']}{', failed ' + str(s['failed']) if s['failed'] else ''})")
        if s["note"]:
            text += f"  [{s['note']}]"
        lines.append(text)
    return "\n".join(lines)


def write_perf(frame: pd.DataFrame, results_dir: Path) -> tuple[Path, Path]:
    """Write ``<results_dir>/perf/perf.parquet`` and ``perf.csv`` atomically."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    from c3bench.problems.instance import atomic_write_bytes

    directory = Path(results_dir) / "perf"
    parquet, csv = directory / "perf.parquet", directory / "perf.csv"
    sink = io.BytesIO()
    pq.write_table(pa.Table.from_pandas(frame, preserve_index=False), sink)
    atomic_write_bytes(parquet, sink.getvalue())
    atomic_write_bytes(csv, frame.to_csv(index=False).encode())
    return parquet, csv


def read_perf(results_dir: str | Path) -> pd.DataFrame:
    """Read ``<results_dir>/perf/perf.parquet`` (or the CSV); reject another schema version."""
    directory = Path(results_dir) / "perf"
    parquet, csv = directory / "perf.parquet", directory / "perf.csv"
    if parquet.exists():
        frame = pd.read_parquet(parquet)
    elif csv.exists():
        frame = pd.read_csv(csv, keep_default_na=False, na_values=["nan", "NaN", ""])
    else:
        raise FileNotFoundError(f"no perf results under {directory}; run `c3bench perf`")
    versions = set(frame["schema_version"].astype(int)) if len(frame) else {SCHEMA_VERSION}
    if versions != {SCHEMA_VERSION}:
        raise ValueError(f"{directory}: perf schema version {sorted(versions)}, expected "
                         f"{SCHEMA_VERSION}")
    return frame


def plot_perf(frame: pd.DataFrame, path: Path) -> Path | None:
    """Log-log median control-step time vs samples (p95 as error bars); ``None`` when empty."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

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
    axes.axhline(SEED_STEP_MS, color="grey", linestyle="--", linewidth=1,
                 label=f"seed: {SEED_STEP_MS:g} ms (16 samples)")
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


def _lookup(summary: pd.DataFrame, backend: str, samples: int, precision: str = "float64"
            ) -> float:
    rows = summary[(summary["backend"] == backend) & (summary["samples"] == samples)
                   & (summary["precision"] == precision) & (summary["repeats"] > 0)]
    return float(rows["median_ms"].iloc[0]) if len(rows) else math.nan


def perf_report_section(results_dir: str | Path, figure_link: str | None = None) -> str:
    """A Markdown section on the control-step time (reads ``<results_dir>/perf/``).

    ``figure_link`` is the figure's path as the report should link it (default
    ``perf/figures/perf_time_vs_samples.png``, right for a report in ``results_dir``; a
    report in ``results/<suite>/`` passes ``../perf/figures/perf_time_vs_samples.png``).
    """
    try:
        frame = read_perf(results_dir)
    except FileNotFoundError as error:
        return f"## Control-step time\n\n_No measurement: {error}._\n"
    summary = summarize(frame)
    lines = ["## Control-step time", ""]
    if len(frame):
        first = frame.iloc[0]
        loads = frame["load_avg"].astype(float)
        lines.append(
            f"One C3+ control step (LCS build for all samples + {int(first['iterations'])} "
            f"ADMM iterations, T = {int(first['horizon'])}, planar, geometric rho), wall "
            f"clock, warm-up excluded, BLAS threads {int(frame['blas_threads'].max())}, cores "
            f"{first['affinity']}, host "
            f"{first['host']}, run {first['run_id']}, 1-minute load average "
            f"{np.nanmin(loads):.2f}-{np.nanmax(loads):.2f} during the run. `overhead` = "
            "total - lcs - qp - proj (Python, dual updates, warm start). The seed's step: "
            f"{SEED_STEP_MS:g} ms (16 samples).")
        lines.append("")
    header = ["backend", "precision", "device", "samples", "median ms", "p95 ms", "lcs",
              "qp", "proj", "overhead", "overhead %", "cpu ms", "seed / median", "note"]
    lines.append("| " + " | ".join(header) + " |")
    lines.append("|" + "|".join("---" for _ in header) + "|")
    measured = summary[summary["repeats"] > 0]
    for _, s in measured.iterrows():
        speedup = SEED_STEP_MS / s["median_ms"] if s["samples"] == 16 else math.nan
        fraction = 100 * s["overhead_fraction"]
        cells = [str(s["backend"]), str(s["precision"]), str(s["device"]), str(s["samples"]),
                 _ms(s["median_ms"]), _ms(s["p95_ms"]), _ms(s["lcs_ms"]), _ms(s["qp_ms"]),
                 "compiled" if s["backend"] == "c3plus-jax" else _ms(s["proj_ms"]),
                 _ms(s["overhead_ms"]), f"{fraction:.0f}" if math.isfinite(fraction) else "-",
                 _ms(s["cpu_ms"]), f"{speedup:.3g}x" if math.isfinite(speedup) else "-",
                 str(s["note"] or "")]
        lines.append("| " + " | ".join(cells) + " |")
    skipped = summary[summary["repeats"] == 0]
    if len(skipped):
        lines.append("")
        notes: dict[str, list[str]] = {}
        for _, s in skipped.iterrows():
            label = f"{s['backend']} ({s['precision']}, {s['device']})"
            notes.setdefault(f"{label}: {s['note']}", []).append(str(s["samples"]))
        lines.append("Not measured: " + "; ".join(
            f"{text} (samples {', '.join(counts)})" for text, counts in notes.items()) + ".")
    lines.append("")
    checks = []
    for backend in ("c3plus-riccati", "c3plus-jax"):
        for precision in ("float64", "float32"):
            at16 = _lookup(summary, backend, 16, precision)
            if not math.isfinite(at16):
                continue
            verdict = "met" if at16 <= TARGET_STEP_MS else "not met"
            text = f"- {backend} ({precision}), 16 samples: median {_ms(at16)} ms " \
                   f"(target <= {TARGET_STEP_MS:g} ms: {verdict})"
            osqp = _lookup(summary, "c3-osqp", 16)
            if math.isfinite(osqp):
                text += f"; {osqp / at16:.0f}x faster than c3-osqp at 16 samples (target >= 5x)"
            at256 = _lookup(summary, backend, 256, precision)
            if math.isfinite(at256):
                ratio = at256 / at16
                text += f"; 256 samples cost {ratio:.1f}x 16 samples (target < 8x: " \
                        f"{'met' if ratio < 8 else 'not met'})"
            checks.append(text + ".")
    if checks:
        lines.extend(["Targets:", "", *checks, ""])
    link = figure_link or "perf/figures/perf_time_vs_samples.png"
    lines.append(f"![control-step time vs samples]({link})")
    lines.append("")
    return "\n".join(lines)


# --- command line -------------------------------------------------------------------------------
def _ints(text: str) -> tuple[int, ...]:
    try:
        return tuple(int(part) for part in text.split(",") if part.strip())
    except ValueError as error:
        raise argparse.ArgumentTypeError(f"expected integers separated by commas: {text}"
                                         ) from error


def _names(text: str) -> tuple[str, ...]:
    return tuple(part.strip() for part in text.split(",") if part.strip())


def cmd_perf(args: argparse.Namespace) -> int:
    """Handler of ``c3bench perf``."""
    backends: list[str] = []
    for entry in args.backend or [",".join(BACKENDS)]:
        backends.extend(_names(entry))
    settings = PerfSettings(samples=args.samples, backends=tuple(dict.fromkeys(backends)),
                            precisions=_names(args.precision), device=args.device,
                            repeats=args.repeats, warmup=args.warmup,
                            iterations=args.iterations, reference_budget=args.reference_budget,
                            seed=args.seed, results_dir=Path(args.out), cpu=args.cpu)
    run_perf(settings)
    directory = settings.results_dir / "perf"
    written = [directory / "perf.parquet", directory / "perf.csv",
               directory / "figures" / "perf_time_vs_samples.png"]
    print("# wrote " + ", ".join(str(path) for path in written if path.exists()))
    return 0


def register_perf_command(subparsers: Any) -> argparse.ArgumentParser:
    """Add ``perf`` to an ``argparse`` sub-parser set (handler in ``handler``)."""
    parser = subparsers.add_parser(
        "perf", help="time one C3+ control step per backend and number of samples",
        description="Time the LCS build plus the ADMM of one C3+ control step (see "
                    "bench/perf.py).")
    parser.add_argument("--samples", type=_ints, default=(1, 16, 64, 256, 1024),
                        help="numbers of model samples, comma separated (default "
                             "1,16,64,256,1024)")
    parser.add_argument("--backend", action="append", default=None,
                        help=f"backends, comma separated or repeated (default all: "
                             f"{','.join(BACKENDS)})")
    parser.add_argument("--precision", default="float64",
                        help="float64 and/or float32 for the c3plus backends (comma separated)")
    parser.add_argument("--device", choices=("cpu", "gpu"), default="cpu",
                        help="device of the JAX backend (the others run on the CPU)")
    parser.add_argument("--repeats", type=int, default=20, help="timed control steps each")
    parser.add_argument("--warmup", type=int, default=2, help="untimed steps first")
    parser.add_argument("--iterations", type=int, default=10, help="ADMM iterations per step")
    parser.add_argument("--reference-budget", type=float, default=60.0,
                        help="seconds allowed per reference-controller configuration")
    parser.add_argument("--seed", type=int, default=0, help="seed of the sampled cube sides")
    parser.add_argument("--cpu", type=int, default=None,
                        help="pin the process to this CPU core (os.sched_setaffinity); XLA "
                             "may otherwise use a second core for the JAX backend")
    parser.add_argument("--out", default="results",
                        help="results directory (files go to <out>/perf/)")
    parser.set_defaults(handler=cmd_perf)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m bench.perf``: the same command without the rest of the CLI."""
    parser = argparse.ArgumentParser(prog="c3bench")
    register_perf_command(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args(["perf", *(argv if argv is not None else sys.argv[1:])])
    return int(args.handler(args))


if __name__ == "__main__":
    sys.exit(main())
