"""The backends of ``c3bench perf``: one small factory per backend in :data:`BACKEND_TABLE`.

A factory gets the run's :class:`PerfContext` and one :class:`Configuration` and returns a
:class:`PreparedBackend` whose ``step(state_index, x, u_prev)`` runs one closed-loop control
step as :func:`bench.closed_loop_policy.make_policy` does (LCS build at ``(x, u_prev)``; with
``n > 1`` samples and weighting on, the samples weighted by
:func:`solvers.c3.lcp_prediction_weights` over the last :data:`WEIGHTING_WINDOW` observed
transitions ``(x_t, u_t, x_{t+1})`` of the scripted push; the controller's warm-started
step) and returns the :class:`StepParts` it timed. A backend that cannot run raises
:class:`BackendUnavailable`; ``c3bench perf`` then stores a skipped row with its message.
Adding a backend is one entry in :data:`BACKEND_TABLE`.
"""

from __future__ import annotations

import math
import os
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from c3bench.problems.errors import C3BenchError
from c3bench.problems.names import LcsKernel, Precision

WEIGHTING_WINDOW = 5
"""Observed transitions the LCP-error weighting looks back on (as the robust closed loop)."""
REFERENCE_QP_BACKENDS: dict[str, str] = {"c3-osqp": "osqp", "c3-clarabel": "clarabel"}
"""Registry QP backend of each reference-controller row."""
STEPS_PER_ROUND = 4
"""Consecutive steps of one configuration per round of ``c3bench perf`` (the first cold, the
others warm: :mod:`bench.perf`)."""
REFERENCE_SAMPLES: tuple[int, ...] = (1, 16)
"""Sample counts the reference controller is measured at (``step`` and ``step_robust``)."""


class BackendUnavailable(C3BenchError):
    """A perf backend cannot run here; the message is the skipped row's note."""


@dataclass
class PerfContext:
    """What every backend of one run shares: config, MPC, the visited states and the
    scripted push they come from, and the run's settings the backends read."""

    config: Any
    mpc: Any
    states: list[tuple[int, np.ndarray, np.ndarray]]
    push_states: np.ndarray
    push_inputs: np.ndarray
    iterations: int
    seed: int
    weighting: bool
    reference_budget: float
    warmup: int

    def observations(self, index: int, window: int = WEIGHTING_WINDOW
                     ) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
        """The last ``window`` transitions ``(x_t, u_t, x_{t+1})`` before state ``index``."""
        return [(self.push_states[t], self.push_inputs[t], self.push_states[t + 1])
                for t in range(max(index - window, 0), index)]


@dataclass(frozen=True)
class Configuration:
    """One measured configuration."""

    backend: str
    precision: str
    device: str
    samples: int


@dataclass
class StepParts:
    """Seconds of the parts of one control step (``nan`` where the backend does not split)."""

    lcs: float
    weighting: float
    admm: float
    qp: float = math.nan
    proj: float = math.nan
    ok: bool = False
    weighted: bool = False
    iterations: int = -1
    cache_hits: int = -1
    cache_misses: int = -1


Step = Callable[[int, np.ndarray, np.ndarray], StepParts]


XLA_ONE_THREAD = "--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1"
"""XLA flags that keep its CPU backend on one thread (:func:`pin_jax_threads`)."""


def _no_compile() -> float:
    return math.nan


@dataclass
class PreparedBackend:
    """A backend ready to be timed."""

    step: Step
    repeats: int | None = None
    """At most this many timed rounds (``None``: the settings' count; a round is
    ``STEPS_PER_ROUND`` steps, :mod:`bench.perf`)."""
    note: str = ""
    """Noted on the rows when ``repeats`` cuts the settings' count."""
    compile_seconds: Callable[[], float] = field(default=_no_compile)
    """JIT compile seconds so far (read after the warm-up)."""
    flop_model: bool = True
    """Whether :func:`bench.perf_flops.admm_flops` describes its ADMM (the Riccati C3+)."""
    executed_flops: Callable[[], float] | None = None
    """Flops its arithmetic executed in the last step, when it counts them (the compiled
    kernel); ``None``: those of the flop model (which counts the numpy Riccati C3+ code)."""


Factory = Callable[[PerfContext, Configuration], PreparedBackend]


@dataclass(frozen=True)
class BackendSpec:
    """One row of :data:`BACKEND_TABLE`."""

    name: str
    make: Factory
    description: str
    reference: bool = False
    """The reference controller: float64 only, samples :data:`REFERENCE_SAMPLES` only."""
    devices: tuple[str, ...] = ("cpu",)
    failure: str = "step failed"
    """Start of the skipped row's note when a step raises (the error follows)."""


def sample_sides(samples: int, seed: int) -> np.ndarray:
    """Cube sides of the samples: ``[0.29]`` for one, else ``U[0.27, 0.33]`` (seeded)."""
    if samples == 1:
        return np.array([0.29])
    return np.random.default_rng([seed, samples]).uniform(0.27, 0.33, samples)


def pin_jax_threads() -> bool:
    """Put XLA's CPU backend on one thread (``XLA_FLAGS``) if JAX is not imported yet."""
    if "jax" in sys.modules:
        return XLA_ONE_THREAD in os.environ.get("XLA_FLAGS", "")
    flags = os.environ.get("XLA_FLAGS", "")
    if XLA_ONE_THREAD not in flags:
        os.environ["XLA_FLAGS"] = f"{flags} {XLA_ONE_THREAD}".strip()
    return True


def lcs_dimensions(context: PerfContext) -> tuple[int, int, int]:
    """``(nx, nlam, nu)`` of the LCS at the first visited state."""
    from c3bench.problems.linearize_batch import BatchLinearizer

    _, x, u_prev = context.states[0]
    lcs = BatchLinearizer(sample_sides(1, context.seed), context.config).linearize(
        x, u_prev, context.config.mpc.dt)
    return int(lcs.nx), int(lcs.nlam), int(lcs.nu)


def _weights(context: PerfContext, samples: Callable[[], Any], index: int,
             count: int) -> tuple[list[float] | None, float]:
    """The LCP-error weights (``None`` when not weighting) and the seconds they took."""
    if not (context.weighting and count > 1):
        return None, 0.0
    from c3bench.solvers.c3 import lcp_prediction_weights

    start = time.perf_counter()
    weights = lcp_prediction_weights(samples(), context.observations(index)).tolist()
    return weights, time.perf_counter() - start


def _options(context: PerfContext) -> Any:
    from c3bench.solvers.c3 import C3Options

    return C3Options(keep_iterates=False, admm_iterations=context.iterations)


def batched_step(context: PerfContext, config: Configuration, controller: Any,
                 whole_call: bool = False, lcs_kernel: LcsKernel = LcsKernel.NUMPY) -> Step:
    """A step of a batched controller (``step(lcs_batch, x0, weights)`` returning ``.u``,
    ``.ok``, ``.iterations``, ``.timings``) with :class:`problems.linearize_batch.
    BatchLinearizer` (its per-sample part by ``lcs_kernel``, :class:`problems.names.
    LcsKernel`); ``whole_call``: one compiled call, ``qp`` is its whole
    time."""
    from c3bench.problems.linearize_batch import BatchLinearizer

    linearizer = BatchLinearizer(sample_sides(config.samples, context.seed), context.config,
                                 kernel=lcs_kernel)
    dt = context.config.mpc.dt

    def step(index: int, x: np.ndarray, u_prev: np.ndarray) -> StepParts:
        start = time.perf_counter()
        lcs = linearizer.linearize(x, u_prev, dt)
        lcs_time = time.perf_counter() - start
        weights, weighting = _weights(context, lambda: lcs, index, config.samples)
        start = time.perf_counter()
        solution = controller.step(lcs, x, weights)
        admm = time.perf_counter() - start
        timings = solution.timings
        parts = StepParts(lcs=lcs_time, weighting=weighting, admm=admm, ok=bool(solution.ok),
                          weighted=weights is not None,
                          iterations=int(getattr(solution, "iterations", -1)))
        if whole_call:
            parts.qp = float(timings.total)
        else:
            parts.qp, parts.proj = float(timings.qp), float(timings.projection)
            parts.cache_hits = int(getattr(solution, "cache_hits", -1))
            parts.cache_misses = int(getattr(solution, "cache_misses", -1))
        return parts

    return step


# --- the factories ----------------------------------------------------------------------------
def make_riccati(context: PerfContext, config: Configuration) -> PreparedBackend:
    """``c3plus-riccati``: :class:`solvers.fast.FastC3Plus` (numpy, batched Riccati)."""
    from c3bench.solvers.fast import FastC3Plus, FastC3PlusController, RiccatiOptions

    solver = FastC3Plus(context.mpc, _options(context), RiccatiOptions(precision=config.precision))
    return PreparedBackend(batched_step(context, config, FastC3PlusController(solver)))


def make_compiled(context: PerfContext, config: Configuration) -> PreparedBackend:
    """``c3plus-compiled``: :class:`solvers.admm.compiled_solver.CompiledC3Plus` (numba
    kernel, the one ADMM loop) with the compiled LCS build (:class:`problems.names.LcsKernel`
    ``COMPILED``; the other batched backends build it with numpy); unavailable
    (with the import's reason) when it does not import. Its JIT compilation and the code
    generated for the push's structures happen before the timed steps
    (:func:`_meet_every_structure`, the warm-up steps); ``compile_seconds`` is read after them."""
    try:
        from c3bench.solvers.admm.compiled_solver import CompiledC3Plus
        from c3bench.solvers.fast import FastC3PlusController
    except Exception as error:  # any import failure: numba missing
        raise BackendUnavailable(f"compiled kernel unavailable: {type(error).__name__}: "
                                 f"{error}") from error
    solver = CompiledC3Plus(context.mpc, _options(context), precision=config.precision)
    _meet_every_structure(context, config, solver)

    def compile_seconds() -> float:
        return solver.compile_seconds

    def executed_flops() -> float:
        return solver.executed_flops

    return PreparedBackend(batched_step(context, config, FastC3PlusController(solver),
                                        lcs_kernel=LcsKernel.COMPILED),
                           compile_seconds=compile_seconds, executed_flops=executed_flops)


def _meet_every_structure(context: PerfContext, config: Configuration, solver: Any) -> None:
    """One untimed solve at every state of the sequence (a separate LCS build, no controller
    state kept), so that the code generated for each structure of ``[A B_v d]`` the push meets
    (:mod:`solvers.admm.compiled_codegen`: compiled once per machine, then loaded from disk) is
    ready before timing; its seconds count in ``compile_seconds``, like numba's JIT."""
    from c3bench.problems.linearize_batch import BatchLinearizer

    linearizer = BatchLinearizer(sample_sides(config.samples, context.seed), context.config,
                                 kernel=LcsKernel.COMPILED)
    for _, x, u_prev in context.states:
        solver.solve(linearizer.linearize(x, u_prev, context.config.mpc.dt), x)


def make_jax(context: PerfContext, config: Configuration) -> PreparedBackend:
    """``c3plus-jax``: :class:`solvers.fast_jax.JaxC3Plus` (one compiled call per ADMM
    iteration, driven by the one loop)."""
    from c3bench.solvers.fast import FastC3PlusController
    from c3bench.solvers.fast_jax import JaxUnavailable, gpu_available, jax_available

    if not jax_available():
        raise BackendUnavailable("JAX not installed (pip install 'c3bench[jax]')")
    if config.device == "gpu" and not gpu_available():
        raise BackendUnavailable("no GPU visible")
    from c3bench.solvers.fast_jax import JaxC3Plus

    try:
        solver = JaxC3Plus(context.mpc, _options(context), precision=config.precision,
                           device=config.device)
    except JaxUnavailable as error:
        raise BackendUnavailable(str(error)) from error
    return PreparedBackend(batched_step(context, config, FastC3PlusController(solver)))


def reference_step(context: PerfContext, config: Configuration) -> Step:
    """A step of the reference controller :class:`solvers.c3.C3Controller` (C3+) with the
    registry QP backend of ``config.backend``; ``step`` for one sample, ``step_robust``
    (one stacked QP) for more."""
    from c3bench.problems.linearize import linearize
    from c3bench.problems.scene import build_scene
    from c3bench.solvers.c3 import C3Controller, C3Options

    options = C3Options(qp_backend=reference_qp(config.backend), keep_iterates=False,
                        admm_iterations=context.iterations)
    controller = C3Controller(options)
    scenes = [build_scene(l=float(side), config=context.config)
              for side in sample_sides(config.samples, context.seed)]
    dt = context.config.mpc.dt

    def step(index: int, x: np.ndarray, u_prev: np.ndarray) -> StepParts:
        start = time.perf_counter()
        systems = [linearize(scene, x, u_prev, dt) for scene in scenes]
        lcs_time = time.perf_counter() - start
        weights, weighting = _weights(context, lambda: systems, index, config.samples)
        start = time.perf_counter()
        if config.samples == 1:
            solution = controller.step(systems[0], context.mpc, x)
        else:
            solution = controller.step_robust(systems, weights, context.mpc, x)
        admm = time.perf_counter() - start
        trace = solution.trace
        return StepParts(lcs=lcs_time, weighting=weighting, admm=admm,
                         qp=sum(trace.qp_setup_time) + sum(trace.qp_time),
                         proj=sum(trace.projection_time), ok=bool(solution.ok),
                         weighted=weights is not None, iterations=int(solution.iterations))

    return step


def make_reference(context: PerfContext, config: Configuration) -> PreparedBackend:
    """``c3-osqp`` / ``c3-clarabel``: the reference controller, its rounds (of
    :data:`STEPS_PER_ROUND` steps, warm-up rounds included) cut to fit ``reference_budget``
    seconds (one untimed step decides; a longer one skips)."""
    from c3bench.solvers import registry
    from c3bench.solvers.timing import single_thread_blas

    if config.samples not in REFERENCE_SAMPLES:
        raise BackendUnavailable(f"the reference controller is measured at samples "
                                 f"{'/'.join(map(str, REFERENCE_SAMPLES))} only")
    qp = reference_qp(config.backend)
    if not registry.get(qp).availability()[0]:
        raise BackendUnavailable(f"{qp} not available")
    step = reference_step(context, config)
    start = time.perf_counter()
    with single_thread_blas():
        index, x, u_prev = context.states[0]
        step(index, x, u_prev)
    first = time.perf_counter() - start
    budget = context.reference_budget
    if first > budget:
        raise BackendUnavailable(f"one control step took {first:.1f} s > budget {budget:g} s")
    affordable = int(budget // max(first, 1e-9)) // STEPS_PER_ROUND
    repeats = max(1, affordable - context.warmup)
    return PreparedBackend(step, repeats=repeats, flop_model=False,
                           note=f"budget {budget:g} s")


BACKEND_TABLE: dict[str, BackendSpec] = {spec.name: spec for spec in (
    BackendSpec("c3plus-riccati", make_riccati, "numpy batched Riccati C3+ (solvers/fast.py)"),
    BackendSpec("c3plus-compiled", make_compiled,
                "numba kernel of the batched Riccati C3+ (solvers/admm/compiled.py)",
                failure="compiled kernel unavailable"),
    BackendSpec("c3plus-jax", make_jax, "JAX C3+, one compiled call per step "
                "(solvers/fast_jax.py)", devices=("cpu", "gpu")),
    BackendSpec("c3-osqp", make_reference, "reference controller, OSQP inside",
                reference=True),
    BackendSpec("c3-clarabel", make_reference, "reference controller, Clarabel inside",
                reference=True),
)}
"""The default backends of ``c3bench perf``, in run order."""

REFERENCE_PREFIX = "c3-"


def reference_qp(name: str) -> str:
    """The registry QP backend of a reference-controller name ``c3-<backend>``."""
    return REFERENCE_QP_BACKENDS.get(name, name.removeprefix(REFERENCE_PREFIX))


def backend_spec(name: str) -> BackendSpec | None:
    """The table's entry, or, for ``c3-<QP backend>`` with any registry backend that takes the
    ``c3plus_qp`` family, the reference controller with that backend inside: its control step is
    the 10 QP steps of one real ADMM run (rho, hence P, changes every iteration), timed end to
    end, so a run answers which QP backend makes a C3+ step fastest; ``None`` when unknown."""
    if name in BACKEND_TABLE:
        return BACKEND_TABLE[name]
    if not name.startswith(REFERENCE_PREFIX):
        return None
    from c3bench.problems.names import Family
    from c3bench.solvers import registry

    try:
        backend = registry.get(reference_qp(name))
    except KeyError:
        return None
    if Family.C3PLUS_QP not in backend.families:
        return None
    return BackendSpec(name, make_reference, f"reference controller, {backend.name} inside",
                       reference=True)


def precisions_of(spec: BackendSpec, wanted: Sequence[str]) -> tuple[str, ...]:
    """The precisions a backend runs: float64 only for the reference controller."""
    return (Precision.FLOAT64,) if spec.reference else tuple(wanted)
