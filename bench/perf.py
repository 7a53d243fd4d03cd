"""``c3bench perf``: the time of one C3+ control step, per backend and number of model samples.

**Control step** (what is timed, wall clock with ``time.perf_counter``; CPU time with
``time.process_time`` beside it), as the closed loop runs it
(:func:`bench.closed_loop_policy.make_policy`): the LCS build for all ``n`` samples at a
state along the scripted push (:func:`problems.suites.scripted_push`, states in the contact
band, visited in order, the controller warm-started from the previous step), for ``n > 1``
with ``weighting`` on (the default) the LCP-error sample weighting
(:func:`solvers.c3.lcp_prediction_weights` over the last five transitions of the push before
that state), then ``iterations`` ADMM iterations (default 10, geometric rho schedule, the
reference study's rho0), horizon ``T`` of the task config (7), planar scene. Samples have
cube sides ``l_j ~ U[0.27, 0.33]`` (seeded; ``n = 1`` uses the reference study's model side
0.29) and shared inputs.

**Backends**: the table :data:`bench.perf_backends.BACKEND_TABLE`, one factory each:
``c3plus-riccati`` (:class:`solvers.fast.FastC3Plus`, numpy), ``c3plus-compiled`` (the numba
kernel :class:`solvers.admm.compiled.CompiledC3PlusKernel` and the compiled per-sample LCS
build, :class:`problems.names.LcsKernel` ``COMPILED``, where the other batched
backends build it with numpy; a skipped row "compiled kernel
unavailable: ..." when it does not import; its JIT compile seconds are stored in
``compile_s``, the compilation happens in the warm-up steps), ``c3plus-jax``
(:class:`solvers.fast_jax.JaxC3Plus`, ``--device cpu`` with XLA pinned to one thread when
this module sets ``XLA_FLAGS`` before JAX is first imported, or ``gpu``: a row "no GPU
visible" when JAX sees none; nothing is faked), ``c3-osqp`` and ``c3-clarabel`` (the
reference controller :class:`solvers.c3.C3Controller`, C3+, with that registry QP backend,
``step`` at ``n = 1`` and ``step_robust`` at ``n = 16``, other ``n`` skipped; a
configuration whose first step takes longer than ``reference_budget`` seconds is skipped,
and the rounds are cut to fit the budget otherwise, noted).

**Split** of each step: ``lcs`` (LCS build), ``weighting`` (0 when not weighted), ``admm``
(the controller's call alone), inside it ``qp`` (factorisations, gradients and linear
passes; for the reference controller the QP build and the backend's solve) and ``proj``
(projections with the shared-input mean); ``total`` the whole step, ``total_no_weighting =
total - weighting``, ``overhead = total - lcs - weighting - qp - proj``. For
``c3plus-jax`` ``qp`` holds the whole compiled call and ``proj`` is ``nan``.

**Machine rate and flops.** Every run first measures the dense matmul rate in float64 and
float32 (:func:`bench.perf_flops.machine_rates`, one BLAS thread) and stores it in every
row; the flop model :func:`bench.perf_flops.admm_flops` gives each Riccati C3+ row's ADMM
MFLOP (``admm_mflop``: the work of the numpy algorithm), and ``admm_mflop_executed`` the
flops the backend executed (the compiled kernel counts its own, which are fewer: Cholesky
instead of an inverse, symmetric products, structural zeros of ``[A B_v d]`` skipped; the
model's for the numpy and JAX paths), so the summary shows the achieved GFLOP/s (executed
flops per second) and its share of the matmul rate. That rate is measured twice: the best of
15 products at the start (``matmul_gflops_*``, the machine's peak) and through the run
(:class:`bench.perf_flops.MatmulProbe`, ``matmul_run_gflops_*``: once per timed round of each
sample count, the median over its rounds), the statistic a median step time compares with;
the summary gives the share of each.
**Ratios** (:mod:`bench.perf_summary`): each configuration's median time over that of
``c3plus-riccati`` float64 and of ``c3-osqp`` at the same samples in the same run.

**Interleaved, in blocks.** For each sample count every backend is prepared, then the steps
go round-robin in *rounds*: in round ``r`` each backend in turn runs a block of
:data:`~bench.perf_backends.STEPS_PER_ROUND` (4) consecutive control steps (the next states
of its sequence, warm-started as ever), so that a slow phase of a shared machine falls on every
backend alike and the ratios compare like with like (measured: timing the backends one after
another, the first one ran in a slow phase and its LCS build, the same code for every backend,
took 1.4-2.2 times as long as the next backend's, which made the compiled kernel look 1.6
times faster than it is). The first step of a block is stored as ``cache = cold``: it follows
another backend's step, which has pushed this one's code and data out of the core's caches.
The other three are ``warm``: they follow its own steps, as in a closed loop, where only the
plant runs between two control steps. Four, because a step needs about three of its own
before it settles (measured on the 2-core EPYC VM, ADMM of the compiled one-sample step after a
reference controller's step: 0.45, 0.36, 0.35, 0.32, 0.32 ms; numpy 2.81, 2.70, 2.64, 2.60,
2.56 ms), and the settled time is what a controller pays in its loop (the same step with 50
plant steps before each: 0.29 and 2.59 ms). Cold and warm steps are summarised apart and every
ratio compares like with like (cold with cold, warm with warm). Before the blocks of each
timed round the matmul probe runs (below), so the first step of a block is cold with one
configuration at a sample count too. ``repeats`` is the number of timed rounds, after ``warmup``
rounds (default 1) that are not recorded. A progress bar (stderr) counts the steps of each
sample count.

**One process per configuration** (:mod:`bench.perf_workers`): each configuration is
prepared and stepped in a worker process of its own, forked from the run's process and driven
block by block, so that only one process computes at a time and no backend is timed in an
interpreter that another backend's runtime has changed (measured: the compiled ADMM 9 % slower,
its Python 50 %, when the JAX backend stepped in the same process; no change from another
process); ``--same-process`` measures all in the run's process. A lost worker is an
infrastructure failure: its configuration gets no row.

Warm-up rounds are excluded; BLAS is pinned to one thread (threadpoolctl)
during every measurement and the count is recorded; ``--cpu N`` pins the whole process (and
its workers) to core ``N``.

**Files** (written atomically under ``<results>/perf/`` by :func:`bench.perf_store.write_perf`;
every run is kept): ``runs/<run_id>.parquet``, one row per timed control step of that run
(plus one row per skipped configuration), columns :data:`bench.perf_store.PERF_SCHEMA`;
``perf.parquet`` and ``perf.csv``, every run together; and
``figures/perf_time_vs_samples.png`` (:func:`bench.plots_perf.plot_perf`).
:func:`bench.report.perf_report_section` renders the latest run of each machine.
"""

from __future__ import annotations

import gc
import math
import os
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from c3bench.bench import perf_store, store
from c3bench.bench.machine import affinity, host_label, load_average, utc_stamp
from c3bench.bench.perf_backends import (
    BACKEND_TABLE,
    REFERENCE_SAMPLES,
    STEPS_PER_ROUND,
    BackendUnavailable,
    Configuration,
    PerfContext,
    backend_spec,
    lcs_dimensions,
    pin_jax_threads,
    precisions_of,
    sample_sides,
)
from c3bench.bench.perf_flops import (
    MATMUL_REPEATS,
    MATMUL_SIZE,
    MachineRates,
    MatmulProbe,
    admm_flops,
    machine_rates,
)
from c3bench.bench.perf_store import CacheState
from c3bench.bench.perf_summary import format_line, format_ms, format_summary_line, summarize
from c3bench.bench.perf_workers import (
    BackendFailure,
    InProcessBackend,
    StepRecord,
    WorkerBackend,
    WorkerLost,
    process_mode,
    start_backend,
)
from c3bench.bench.progress import progress_bar
from c3bench.problems.errors import InputError
from c3bench.problems.names import Precision

__all__ = [
    "BACKENDS", "DEFAULT_SAMPLES", "DEVICES", "PERF_FIGURE", "REFERENCE_SAMPLES",
    "REFERENCE_STEP_MS", "TARGET_STEP_MS", "PerfSettings", "format_line", "format_ms",
    "pin_jax_threads", "run_perf", "sample_sides", "summarize",
]

BACKENDS: tuple[str, ...] = tuple(BACKEND_TABLE)
"""Every backend, in run order (all run by default)."""
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
BLOCK_STATES: tuple[CacheState, ...] = (CacheState.COLD,) + (CacheState.WARM,) * (
    STEPS_PER_ROUND - 1)
"""The cache state of each step of a block: cold (it follows another configuration's block or
the round's matmul probe), then warm."""


@dataclass
class PerfSettings:
    """What ``c3bench perf`` measures (module docstring)."""

    samples: tuple[int, ...] = DEFAULT_SAMPLES
    backends: tuple[str, ...] = BACKENDS
    precisions: tuple[str, ...] = (Precision.FLOAT64,)
    device: str = "cpu"
    repeats: int = 12
    warmup: int = 1
    iterations: int = 10
    reference_budget: float = 60.0
    seed: int = 0
    results_dir: Path = field(default_factory=lambda: Path("results"))
    cpu: int | None = None
    weighting: bool = True
    """LCP-error sample weighting in every step with ``n > 1`` samples."""
    worker_processes: bool = True
    """Each configuration in its own worker process (:mod:`bench.perf_workers`); ``False``:
    all in the run's process (``--same-process``)."""

    def __post_init__(self) -> None:
        self.samples = tuple(int(n) for n in self.samples)
        if not self.samples or min(self.samples) < 1:
            raise InputError(f"samples must be integers >= 1, got {self.samples}")
        unknown = [name for name in self.backends if backend_spec(name) is None]
        if unknown:
            raise InputError(f"--backend: unknown backends {sorted(unknown)}; known: "
                             f"{', '.join(BACKENDS)}, or c3-<any registry QP backend taking "
                             f"c3plus_qp>")
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
class _Run:
    """Identity and shared measurements of one run."""

    context: PerfContext
    run_id: str
    host: str
    rates: MachineRates
    dims: tuple[int, int, int]
    """``(nx, nlam, nu)`` of the LCS."""


def perf_context(settings: PerfSettings) -> PerfContext:
    """The shared inputs of a run: config, MPC, the scripted push and its visited states."""
    from c3bench.problems.config import load_config
    from c3bench.problems.scene import build_mpc, build_scene
    from c3bench.problems.suites import sample_states, scripted_push

    config = load_config()
    record = scripted_push(config)
    indices = sample_states(record, 24, 0.02)
    states = [(i, record.states[i], record.inputs[max(i - 1, 0)]) for i in indices]
    mpc = build_mpc(build_scene(l=0.29, config=config), config.mpc)
    return PerfContext(config=config, mpc=mpc, states=states,
                       push_states=np.asarray(record.states),
                       push_inputs=np.asarray(record.inputs), iterations=settings.iterations,
                       seed=settings.seed, weighting=settings.weighting,
                       reference_budget=settings.reference_budget, warmup=settings.warmup)


def _row(run: _Run, config: Configuration, **values: Any) -> dict[str, Any]:
    row: dict[str, Any] = {
        "schema_version": store.SCHEMA_VERSION, "run_id": run.run_id,
        "backend": config.backend, "precision": str(config.precision),
        "device": config.device, "samples": config.samples, "repeat": -1,
        "state_index": -1, "total_ms": math.nan, "lcs_ms": math.nan, "qp_ms": math.nan,
        "proj_ms": math.nan, "overhead_ms": math.nan, "cpu_ms": math.nan,
        "iterations": run.context.iterations, "horizon": int(run.context.mpc.horizon),
        "ok": False, "cache_hits": -1, "cache_misses": -1, "skipped": False, "note": "",
        "blas_threads": 1, "affinity": affinity(), "load_avg": math.nan, "host": run.host,
        "perf_schema_version": perf_store.PERF_SCHEMA_VERSION, "weighted": False,
        "weighting_ms": math.nan, "admm_ms": math.nan, "total_no_weighting_ms": math.nan,
        "admm_mflop": math.nan, "matmul_gflops_f64": run.rates.float64,
        "matmul_gflops_f32": run.rates.float32, "compile_s": math.nan,
        "admm_mflop_executed": math.nan, "cache": "", "matmul_run_gflops_f64": math.nan,
        "matmul_run_gflops_f32": math.nan, "process": "",
    }
    row.update(values)
    return row


def _mflop(run: _Run, config: Configuration, iterations: int) -> float:
    """The flop model's MFLOP of one step's ADMM (rho changes every iteration)."""
    nx, nlam, nu = run.dims
    flops = admm_flops(nx, nlam, nu, int(run.context.mpc.horizon), max(iterations, 1),
                       config.samples)
    return flops.total / 1e6


@dataclass
class _Measurement:
    """One configuration being timed: its backend, how many steps it takes, its rows."""

    config: Configuration
    backend: WorkerBackend | InProcessBackend
    repeats: int
    """Timed rounds (:data:`STEPS_PER_ROUND` steps each: the first cold, the others warm)."""
    note: str
    rows: list[dict[str, Any]] = field(default_factory=list)
    failure: str | None = None
    """Why it stopped (the skipped row's note), or ``None``."""
    lost: str | None = None
    """Why its worker process was lost (no row is stored), or ``None``."""


def _record_step(run: _Run, m: _Measurement, step: int, record: StepRecord, cache: CacheState,
                 load: float, threads: int) -> None:
    """The row of step ``step`` of ``m``'s sequence (from the first timed round on, with its
    ``cache`` state)."""
    context = run.context
    if step < STEPS_PER_ROUND * context.warmup:
        return
    index = context.states[step % len(context.states)][0]
    parts = record.parts
    total = 1e3 * record.wall
    lcs, weighting, qp, proj = (1e3 * value for value in (
        parts.lcs, parts.weighting, parts.qp, parts.proj))
    known = lcs + weighting + qp + (0.0 if math.isnan(proj) else proj)
    iterations = parts.iterations if parts.iterations >= 0 else context.iterations
    model = _mflop(run, m.config, iterations) if m.backend.traits.flop_model else math.nan
    executed = model if record.executed_mflop is None else record.executed_mflop
    m.rows.append(_row(
        run, m.config, repeat=step - STEPS_PER_ROUND * context.warmup, state_index=index,
        total_ms=total, lcs_ms=lcs, qp_ms=qp, proj_ms=proj,
        overhead_ms=max(total - known, 0.0), cpu_ms=1e3 * record.cpu, iterations=iterations,
        ok=parts.ok, cache_hits=parts.cache_hits, cache_misses=parts.cache_misses,
        note=m.note, blas_threads=threads, load_avg=load, weighted=parts.weighted,
        weighting_ms=weighting, admm_ms=1e3 * parts.admm,
        total_no_weighting_ms=total - weighting, admm_mflop=model,
        admm_mflop_executed=executed, cache=str(cache), process=str(m.backend.process)))


def _time_block(run: _Run, m: _Measurement, r: int, load: float, threads: int) -> None:
    """Round ``r``'s block of ``m`` (:data:`STEPS_PER_ROUND` steps; the first cold), its rows
    kept; a step that raises stops ``m`` (``failure``), a lost worker too (``lost``)."""
    first = STEPS_PER_ROUND * r
    try:
        records = m.backend.run_block(first, STEPS_PER_ROUND)
    except BackendFailure as failure:
        records, m.failure = failure.records, str(failure)
    except WorkerLost as error:
        records, m.lost = [], str(error)
    for offset, record in enumerate(records):
        _record_step(run, m, first + offset, record, BLOCK_STATES[offset], load, threads)


def _measure_interleaved(run: _Run, measurements: list[_Measurement], progress: bool = False
                         ) -> None:
    """Warm-up, then the timed rounds of every configuration of one sample count: in round
    ``r`` each configuration in turn runs a block of :data:`STEPS_PER_ROUND` consecutive steps
    (module docstring), so that a slow phase of a shared machine falls on every backend alike
    and each configuration has a cold and a warm step per round; each timed round starts with
    a sample of the matmul rate (:class:`bench.perf_flops.MatmulProbe`), stored in every row
    as the median over the rounds. A backend that raises stops (its ``failure`` says why), a
    configuration whose worker is lost too (``lost``); the others go on."""
    from c3bench.solvers.timing import blas_threads, single_thread_blas

    warmup = run.context.warmup
    samples = measurements[0].config.samples if measurements else 0
    bar = progress_bar(progress, STEPS_PER_ROUND * sum(warmup + m.repeats
                                                       for m in measurements),
                       f"perf samples={samples}", "step")
    probe = MatmulProbe()
    gc.collect()
    with single_thread_blas():
        threads, load = blas_threads(), load_average()
        for r in range(warmup + max((m.repeats for m in measurements), default=0)):
            if r >= warmup:
                probe.sample()
            for m in measurements:
                if m.failure is None and m.lost is None and r < warmup + m.repeats:
                    _time_block(run, m, r, load, threads)
                    bar.update(STEPS_PER_ROUND)
    bar.close()
    rates = probe.rates()
    for m in measurements:
        if m.failure is not None or m.lost is not None:
            continue
        try:
            compile_seconds = m.backend.compile_seconds()
        except BackendFailure as failure:
            m.failure = str(failure)
            continue
        except WorkerLost as error:
            m.lost = str(error)
            continue
        for row in m.rows:
            row.update(compile_s=compile_seconds, matmul_run_gflops_f64=rates.float64,
                       matmul_run_gflops_f32=rates.float32)


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


def _configurations(settings: PerfSettings) -> list[Configuration]:
    out: list[Configuration] = []
    for backend in settings.backends:
        spec = backend_spec(backend)
        assert spec is not None  # checked by PerfSettings
        device = settings.device if settings.device in spec.devices else "cpu"
        for precision in precisions_of(spec, settings.precisions):
            out.extend(Configuration(backend, str(precision), device, samples)
                       for samples in settings.samples)
    return out


def _run_perf(settings: PerfSettings, echo: Callable[[str], None] | None) -> pd.DataFrame:
    say = echo or (lambda _: None)
    if "c3plus-jax" in settings.backends and settings.device == "cpu":
        pin_jax_threads()
    context = perf_context(settings)
    from c3bench.solvers.timing import blas_threads, single_thread_blas

    with single_thread_blas():
        threads = blas_threads()
    run = _Run(context=context, run_id=utc_stamp(), host=host_label(), rates=machine_rates(),
               dims=lcs_dimensions(context))
    say(f"# c3bench perf  {run.run_id}  host {run.host}")
    say(f"# T={context.mpc.horizon}  ADMM iterations={settings.iterations}  "
        f"dt={context.config.mpc.dt}  planar  (nx, nlam, nu)={run.dims}  BLAS threads="
        f"{threads} (pinned)  cores {affinity()}  load average {load_average():.2f}  warm-up "
        f"{settings.warmup}  repeats {settings.repeats}  weighting "
        f"{'on (n > 1)' if settings.weighting else 'off'}")
    say(f"# dense matmul rate ({MATMUL_SIZE}x{MATMUL_SIZE}, one thread, best of "
        f"{MATMUL_REPEATS}): float64 "
        f"{run.rates.float64:.1f} GFLOP/s, float32 {run.rates.float32:.1f} GFLOP/s")
    rows: list[dict[str, Any]] = []
    configurations = _configurations(settings)
    for samples in settings.samples:
        group = [c for c in configurations if c.samples == samples]
        rows.extend(_run_group(run, settings, group, say, echo is not None))
        # with the ratios to what this run measured so far (skipped ones were said)
        summary = summarize(pd.DataFrame(rows, columns=list(perf_store.PERF_COLUMNS)))
        for _, line in summary[(summary["samples"] == samples)
                               & (summary["repeats"] > 0)].iterrows():
            say(format_summary_line(line))
    frame = pd.DataFrame(rows, columns=list(perf_store.PERF_COLUMNS))
    say(f"# summary (ratios t / t_ref within this run; load average now "
        f"{load_average():.2f})")
    say(format_line(frame))
    perf_store.write_perf(frame, settings.results_dir)
    from c3bench.bench.plots_perf import plot_perf  # matplotlib only once there is a figure

    plot_perf(perf_store.read_perf(settings.results_dir),
              store.perf_dir(settings.results_dir) / "figures" / PERF_FIGURE)
    return frame


def _run_group(run: _Run, settings: PerfSettings, group: list[Configuration],
               say: Callable[[str], None], progress: bool) -> list[dict[str, Any]]:
    """Prepare every configuration of one sample count, time them interleaved
    (:func:`_measure_interleaved`) and return their rows (a skipped row for each that could
    not run)."""
    rows: list[dict[str, Any]] = []

    def skip(config: Configuration, note: str) -> None:
        say(f"{_label(config)} skipped: {note}")
        rows.append(_row(run, config, skipped=True, note=note, load_avg=load_average(),
                         process=str(process_mode(settings.worker_processes))))

    measurements: list[_Measurement] = []
    try:
        for config in group:
            spec = backend_spec(config.backend)
            assert spec is not None  # checked by PerfSettings
            try:
                backend = start_backend(spec, run.context, config, settings.worker_processes,
                                        [m.backend for m in measurements])
            except BackendUnavailable as error:
                skip(config, str(error))
                continue
            except WorkerLost as error:
                say(f"{_label(config)} not measured: {error} (nothing stored)")
                continue
            repeats, note = settings.repeats, ""
            cut = backend.traits.repeats
            if cut is not None and cut < settings.repeats:
                repeats, note = cut, f"rounds cut to {cut} ({backend.traits.note})"
            measurements.append(_Measurement(config, backend, repeats, note))
        _measure_interleaved(run, measurements, progress)
    finally:
        for m in measurements:
            m.backend.close()
    for m in measurements:
        if m.lost is not None:
            say(f"{_label(m.config)} not measured: {m.lost} (nothing stored)")
        elif m.failure is None:
            rows.extend(m.rows)
        else:
            skip(m.config, m.failure)
    return rows


def _label(config: Configuration) -> str:
    """The configuration as the run's lines start."""
    return (f"{config.backend:<15} {config.precision:<8} {config.device:<4} "
            f"samples={config.samples:<5}")
