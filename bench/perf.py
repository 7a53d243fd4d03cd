"""``c3bench perf``: the time of one C3+ control step, per backend and number of model samples.

**Control step** (what is timed, wall clock with ``time.perf_counter``; CPU time with
``time.process_time`` beside it): the LCS build for all ``n`` samples at a state along the
scripted push (:func:`problems.suites.scripted_push`, states in the contact band, visited in
order, the controller warm-started from the previous step as in closed loop) plus
``iterations`` ADMM iterations (default 10, geometric rho schedule, the reference study's rho0),
horizon ``T`` of the task config (7), planar scene. Samples have cube sides ``l_j ~ U[0.27, 0.33]``
(seeded; ``n = 1`` uses the reference study's model side 0.29) with uniform weights and shared
inputs.

**Backends**

* ``c3plus-riccati``: :class:`solvers.fast.FastC3Plus` (numpy, batched Riccati) with
  :class:`problems.linearize_batch.BatchLinearizer`;
* ``c3plus-jax``: :class:`solvers.fast_jax.JaxC3Plus` (one compiled call per step) with the
  same LCS build; only when JAX imports, on ``--device cpu`` (XLA pinned to one thread when
  this module sets ``XLA_FLAGS`` before JAX is first imported) or ``gpu`` (a row
  "no GPU visible" when JAX sees none; nothing is faked);
* ``c3-osqp``, ``c3-clarabel``: the reference controller :mod:`solvers.c3` (C3+ variant,
  :class:`solvers.c3.C3Controller`) with that registry QP backend at its default settings and
  :func:`problems.linearize.linearize` per sample; ``n = 1`` through ``step`` and ``n = 16``
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

**Files** (written atomically under ``<results>/perf/`` by :func:`bench.perf_store.write_perf`;
every run is kept): ``runs/<run_id>.parquet``, one row per timed control step of that run
(plus one row per skipped configuration), columns :data:`bench.perf_store.PERF_SCHEMA`;
``perf.parquet`` and ``perf.csv``, every run together; and
``figures/perf_time_vs_samples.png`` (:func:`bench.plots.plot_perf`): median control-step time
against the number of samples (log-log, p95 as error bars) of the latest run of each machine,
with the reference study's 60 ms and the 6 ms target. :func:`bench.report.perf_report_section`
renders the summary of the latest run of each machine for the report.
"""

from __future__ import annotations

import gc
import math
import os
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from c3bench.bench import perf_store, store
from c3bench.bench.machine import affinity, host_label, load_average, utc_stamp
from c3bench.problems.errors import InputError
from c3bench.problems.names import Precision

BACKENDS: tuple[str, ...] = ("c3plus-riccati", "c3plus-jax", "c3-osqp", "c3-clarabel")
REFERENCE_BACKENDS: dict[str, str] = {"c3-osqp": "osqp", "c3-clarabel": "clarabel"}
REFERENCE_SAMPLES: tuple[int, ...] = (1, 16)
REFERENCE_STEP_MS = 60.0
"""The reference study's control step (0.06 s with 16 samples, float32, including the LCS build)."""
TARGET_STEP_MS = 6.0
"""The issue's target for 16 samples on one core."""
DEVICES: tuple[str, ...] = ("cpu", "gpu")
"""Devices of the JAX backend (the others run on the CPU)."""
DEFAULT_SAMPLES: tuple[int, ...] = (1, 16, 64, 256, 1024)
"""Numbers of model samples measured unless chosen otherwise."""
PERF_FIGURE = "perf_time_vs_samples.png"
"""File name of the figure under ``<results>/perf/figures/``."""
XLA_ONE_THREAD = "--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1"


@dataclass
class PerfSettings:
    """What ``c3bench perf`` measures (module docstring)."""

    samples: tuple[int, ...] = DEFAULT_SAMPLES
    backends: tuple[str, ...] = BACKENDS
    precisions: tuple[str, ...] = (Precision.FLOAT64,)
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
            raise InputError(f"samples must be integers >= 1, got {self.samples}")
        unknown = set(self.backends) - set(BACKENDS)
        if unknown:
            raise InputError(f"unknown backends {sorted(unknown)}; known: {', '.join(BACKENDS)}")
        if set(self.precisions) - set(Precision):
            raise InputError(f"precisions must be float64 or float32, got {self.precisions}")
        if self.device not in DEVICES:
            raise InputError(f"device must be cpu or gpu, got {self.device!r}")
        if self.repeats < 1 or self.warmup < 0 or self.iterations < 1:
            raise InputError("repeats and iterations must be >= 1, warmup >= 0")
        if not self.reference_budget > 0:
            raise InputError("reference_budget must be > 0")
        self.results_dir = Path(self.results_dir)


@dataclass
class _Context:
    """Shared inputs: config, MPC, the states visited, identity of the run."""

    config: Any
    mpc: Any
    states: list[tuple[int, np.ndarray, np.ndarray]]
    run_id: str
    host: str


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
    from c3bench.problems.scene import build_mpc, build_scene
    from c3bench.problems.suites import sample_states, scripted_push

    config = load_config()
    record = scripted_push(config)
    indices = sample_states(record, 24, 0.02)
    states = [(i, record.states[i], record.inputs[max(i - 1, 0)]) for i in indices]
    mpc = build_mpc(build_scene(l=0.29, config=config), config.mpc)
    return _Context(config=config, mpc=mpc, states=states, run_id=utc_stamp(),
                    host=host_label())


def sample_sides(samples: int, seed: int) -> np.ndarray:
    """Cube sides of the samples: ``[0.29]`` for one, else ``U[0.27, 0.33]`` (seeded)."""
    if samples == 1:
        return np.array([0.29])
    return np.random.default_rng([seed, samples]).uniform(0.27, 0.33, samples)


def _row(context: _Context, settings: PerfSettings, backend: str, precision: str,
         device: str, samples: int, **values: Any) -> dict[str, Any]:
    row: dict[str, Any] = {
        "schema_version": store.SCHEMA_VERSION, "run_id": context.run_id, "backend": backend,
        "precision": str(precision), "device": device, "samples": samples, "repeat": -1,
        "state_index": -1, "total_ms": math.nan, "lcs_ms": math.nan, "qp_ms": math.nan,
        "proj_ms": math.nan, "overhead_ms": math.nan, "cpu_ms": math.nan,
        "iterations": settings.iterations, "horizon": int(context.mpc.horizon), "ok": False,
        "cache_hits": -1, "cache_misses": -1, "skipped": False, "note": "",
        "blas_threads": 1, "affinity": affinity(), "load_avg": math.nan,
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
    load = load_average()
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
    from c3bench.problems.linearize_batch import BatchLinearizer
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
    from c3bench.problems.linearize import linearize
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
        return {"lcs": lcs_time, "qp": sum(trace.qp_setup_time) + sum(trace.qp_time),
                "proj": sum(trace.projection_time), "ok": solution.ok}

    return step


def run_perf(settings: PerfSettings, echo: Callable[[str], None] | None = print
             ) -> pd.DataFrame:
    """Measure every configuration, write the files and the figure, return the rows."""
    if settings.cpu is None:
        return _run_perf(settings, echo)
    previous = os.sched_getaffinity(0)
    if settings.cpu not in previous:
        raise InputError(f"cannot pin to CPU core {settings.cpu}: this process may run on "
                         f"cores {affinity()}")
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
        f"{affinity()}  load average {load_average():.2f}  warm-up {settings.warmup}  repeats "
        f"{settings.repeats}")
    rows: list[dict[str, Any]] = []
    for backend in settings.backends:
        precisions = (Precision.FLOAT64,) if backend in REFERENCE_BACKENDS \
            else settings.precisions
        device = settings.device if backend == "c3plus-jax" else "cpu"
        for precision in precisions:
            for samples in settings.samples:
                new = _run_one(context, settings, backend, precision, device, samples, say)
                rows.extend(new)
    frame = pd.DataFrame(rows, columns=list(perf_store.PERF_COLUMNS))
    perf_store.write_perf(frame, settings.results_dir)
    from c3bench.bench.plots import plot_perf  # matplotlib only once there is something to draw

    plot_perf(perf_store.read_perf(settings.results_dir),
              store.perf_dir(settings.results_dir) / "figures" / PERF_FIGURE)
    return frame


def _run_one(context: _Context, settings: PerfSettings, backend: str, precision: str,
             device: str, samples: int, say: Callable[[str], None]) -> list[dict[str, Any]]:
    label = f"{backend:<15} {precision:<8} {device:<4} samples={samples:<5}"

    def skip(note: str) -> list[dict[str, Any]]:
        say(f"{label} skipped: {note}")
        return [_row(context, settings, backend, precision, device, samples, skipped=True,
                     note=note, load_avg=load_average())]

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
    say(format_line(pd.DataFrame(rows, columns=list(perf_store.PERF_COLUMNS))))
    return rows


# --- summaries ---------------------------------------------------------------------------------
def _p95(values: Sequence[float]) -> float:
    """The 95th percentile (NaN for no values)."""
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


def format_ms(value: float) -> str:
    """Milliseconds as text: one decimal from 10 ms, two below, ``-`` when not finite."""
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
        proj = "(compiled)" if s["backend"] == "c3plus-jax" else format_ms(s["proj_ms"])
        qp_label = "qp+proj" if s["backend"] == "c3plus-jax" else "qp"
        text = (f"{head} median {format_ms(s['median_ms'])} ms  p95 {format_ms(s['p95_ms'])} ms  "
                f"lcs {format_ms(s['lcs_ms'])}  {qp_label} {format_ms(s['qp_ms'])}  proj {proj}  "
                f"overhead {format_ms(s['overhead_ms'])}  cpu {format_ms(s['cpu_ms'])}  "
                f"(n={s['repeats']}{', failed ' + str(s['failed']) if s['failed'] else ''})")
        if s["note"]:
            text += f"  [{s['note']}]"
        lines.append(text)
    return "\n".join(lines)
