"""The consensus ADMM of C3 / C3+, written once (docs/admm.md).

The MPCC of one control step (Aydinoglu and Posa, ICRA 2022; Bui et al. 2025 for C3+) is split
into a QP over ``z`` (dynamics, no complementarity) and a projection onto complementarity over
a copy ``delta`` of the horizon steps, with the scaled dual ``w`` and the consensus weight
``G = diag(rho_x, rho_lam, rho_u, rho_eta)`` (Boyd et al., "Distributed optimization and
statistical learning via ADMM", 2011, section 3.1.1, scaled form). Iteration ``i``
(:func:`admm_iteration`):

1. **QP step** ``z = argmin J(z) + sum_k ||z_k - (delta_k - w_k)||^2_G`` s.t. the dynamics
   (and the limits, where the kernel puts them there);
2. **projection** ``delta = argmin_{delta in C} ||delta - (z + w)||^2_U`` (``U = G`` unless
   ``projection_weights`` is given);
3. **dual update** ``w <- w + z - delta``.

The kernel (:mod:`.kernel`) does steps 1 and 2; this module does step 3 and the rest:

4. **residuals** (Boyd et al. 2011, section 3.3, Boyd's ``rho`` equal to ``2 G``): consensus
   ``r = ||z - delta||`` and dual ``s = ||2 G (delta - delta_prev)||``, weighted over samples,
   ``sqrt(sum_j p_j ||.||_j^2)``;
5. **stopping**: ``fixed`` iterations, or ``residual``: ``r <= sqrt(p) eps_abs + eps_rel
   max(||z||, ||delta||)`` and ``s <= sqrt(p) eps_abs + eps_rel ||2 G w||`` (Boyd eq. 3.12);
6. **rho update** by the schedule (:mod:`.schedules`; a data-independent schedule's values
   are read from its ``plan``, computed once per control step); when ``G`` changes by
   ``rho_new / rho_old`` the scaled dual is rescaled by ``rho_old / rho_new`` so that
   ``y = 2 G w`` is unchanged (Boyd et al. 2011, end of section 3.4.1).

**Output**: ``u_0`` of ``delta`` (default) or ``z``; with shared inputs the weighted mean over
samples; clipped to ``|u_i| <= force_limit`` (``u_raw`` keeps the unclipped value). A kernel
failure stops the loop and returns the fallback input with ``ok=False``; nothing non-finite is
returned.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from c3bench.problems.errors import InputError
from c3bench.problems.families import weight_vector
from c3bench.problems.mpc import HorizonLayout
from c3bench.solvers.admm.kernel import Kernel, KernelFailure, PlanRun, StepInputs
from c3bench.solvers.admm.options import WEIGHT_FLOOR, C3Options, Output, Stopping
from c3bench.solvers.admm.schedules import Schedule, is_frozen, schedule_for
from c3bench.solvers.admm.solution import C3Iterate, C3Solution, C3Trace, FastTimings


def dual_update(w: Any, z_steps: Any, delta: Any) -> Any:
    """Scaled dual ascent ``w + z - delta`` (any array type, (..., T, step size))."""
    return w + z_steps - delta


def admm_iteration(kernel: Any, rho: Any, delta: Any, w: Any) -> tuple[Any, Any, Any, Any]:
    """One iteration: ``z`` and ``delta_new`` from the kernel, then :func:`dual_update`.

    ``kernel`` is anything with ``iterate(rho, delta, w)`` (:class:`.kernel.Kernel`, or a
    traced stand-in: a kernel may run this very function inside its own compiled call,
    ``kernel.fused``, JAX: one device call per iteration; the loop then calls that instead).
    """
    z_steps, z_terminal, new_delta = kernel.iterate(rho, delta, w)
    return z_steps, z_terminal, new_delta, dual_update(w, z_steps, new_delta)


def weighted_norm(values: np.ndarray, p: np.ndarray) -> float:
    """``sqrt(sum_j p_j ||v_j||_2^2)`` over the leading sample axis (float64)."""
    flat = np.reshape(np.asarray(values), (np.shape(values)[0], -1)).astype(np.float64)
    return float(np.sqrt(np.dot(p, np.sum(flat * flat, axis=1))))


def normalise_weights(weights: Any, samples: int, floor: float = WEIGHT_FLOOR) -> np.ndarray:
    """Sample weights floored at ``floor`` times the largest and scaled to sum 1 (uniform if
    None): ``p_j = max(a_j / a_max, f) / sum_i max(a_i / a_max, f)``.

    The floor keeps every sample's QP well posed (a zero weight would remove its cost); it is
    relative, so scaling every weight leaves ``p`` unchanged up to rounding, and dividing by
    the largest first keeps every term in ``[f, 1]`` (no underflow of the floor for tiny
    weights, no overflow of the sum for huge ones). Weights of the wrong shape, negative,
    non-finite or all zero raise :class:`InputError` (a ``ValueError``), one line.
    """
    if weights is None:
        return np.full(samples, 1.0 / samples)
    try:
        array = np.asarray(weights, dtype=float)
    except (TypeError, ValueError) as error:  # text, ragged lists, objects
        raise InputError(f"weights must be numbers: {error}") from None
    if array.shape != (samples,):
        raise InputError(f"weights must have shape ({samples},), got {array.shape}")
    # the ufuncs' reductions directly (what ndarray.min/max call, without their Python
    # wrappers: this runs every control step)
    lowest, largest = np.minimum.reduce(array), np.maximum.reduce(array)
    if not (lowest >= 0 and 0 < largest < math.inf):  # a NaN fails lowest >= 0
        raise InputError("weights must be finite, >= 0 and not all zero")
    floored = np.maximum(array / largest, floor)
    normalised: np.ndarray = floored / np.add.reduce(floored)
    return normalised


def cold_iterates(layout: HorizonLayout, x0: np.ndarray, samples: int,
                  dtype: Any = np.float64) -> tuple[np.ndarray, np.ndarray]:
    """``delta_k = (x0, 0, 0, 0)`` and ``w = 0``: (S, T, step size) each."""
    delta = np.zeros((samples, layout.horizon, layout.step_size), dtype=dtype)
    delta[:, :, layout.index(0, "x")] = np.asarray(x0, dtype=dtype)
    return delta, np.zeros_like(delta)


def initial_iterates(layout: HorizonLayout, x0: np.ndarray, samples: int,
                     delta: np.ndarray | None, w: np.ndarray | None, dtype: Any = np.float64,
                     trusted: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """The given iterates ((S, T, ns) or (T, ns), checked) or a cold start.

    A given array of the full shape and ``dtype`` is used as it is, not copied: no kernel and
    nothing in the loop writes into its iterates (every update makes new arrays), and a
    warm-started controller hands over arrays it has just made (:func:`shift_in_time`).
    ``trusted``: ``delta`` and ``w`` are such a controller's own warm start, made from the
    iterates of a successful step of the same kernel, finite (every kernel fails a step
    whose iterates are not), so when they have the full shape and ``dtype`` they are used
    without scanning every entry."""
    shape = (samples, layout.horizon, layout.step_size)
    if trusted and delta is not None and w is not None and delta.shape == shape and \
            w.shape == shape and delta.dtype == dtype and w.dtype == dtype:
        return delta, w
    cold: tuple[np.ndarray, np.ndarray] | None = None
    if delta is None or w is None:  # a warm start (both given) builds no cold arrays
        start = x0 if np.isfinite(x0).all() else np.zeros(layout.nx)
        cold = cold_iterates(layout, start, samples, dtype)
    out = []
    for index, (name, given) in enumerate((("delta", delta), ("w", w))):
        if given is None:
            assert cold is not None
            out.append(cold[index])
            continue
        array = np.asarray(given)
        broadcast = array.shape == shape[1:]
        if broadcast:
            array = np.broadcast_to(array, shape)
        if array.shape != shape:
            raise InputError(f"{name} must have shape {shape[1:]} or {shape}, "
                             f"got {array.shape}")
        if not np.isfinite(array).all():
            raise InputError(f"{name} has non-finite entries")
        out.append(np.array(array, dtype=dtype) if broadcast or array.dtype != dtype
                   else array)
    return out[0], out[1]


def shift_warm_start(delta: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Shift ``delta`` and ``w`` one step forward in time: drop step 0, repeat the last.

    Arrays are (..., T, step size); ``out[..., k, :] = in[..., k + 1, :]`` for ``k < T - 1``
    and ``out[..., T - 1, :] = in[..., T - 1, :]``; the dtype is kept.
    """
    return shift_in_time(delta), shift_in_time(w)


def shift_in_time(array: np.ndarray) -> np.ndarray:
    """One array of :func:`shift_warm_start`, shifted (a new array)."""
    array = np.asarray(array)
    shifted = array.copy()
    shifted[..., :-1, :] = array[..., 1:, :]
    return shifted


_RATIOS: dict[tuple[Any, ...], np.ndarray] = {}
"""Memoised ratio vectors of :func:`dual_ratio`."""
_PLAN_RATIOS: dict[tuple[Any, ...], np.ndarray] = {}
"""Memoised ratio arrays of :func:`plan_ratios`."""
_LAST_PLAN_RATIOS: dict[tuple[Any, ...], tuple[Sequence[Mapping[str, float]], np.ndarray]] = {}
"""The last plan of :func:`plan_ratios` per sizes with its ratios (a frozen plan that comes
back is known by identity, without hashing its items)."""


def scale_dual(w: Any, ratio: Any) -> Any:
    """``w * ratio`` with ``ratio = G_old / G_new`` (:func:`dual_ratio`): the scaled dual after
    the consensus weight changes, so that ``y = 2 G w`` is unchanged (any array type; a
    compiled kernel applies it entry by entry)."""
    return w * ratio


def dual_ratio(layout: HorizonLayout, rho_old: Mapping[str, float],
               rho_new: Mapping[str, float], dtype: Any) -> np.ndarray:
    """``G_old / G_new`` blockwise (step size,) in ``dtype``; a block whose weight is 0 before
    and after keeps its dual (ratio 1). Memoised by (block sizes, dtype, rho items): a
    schedule repeats them every control step."""
    key = (layout.nx, layout.nlam, layout.nu, layout.n_eta, np.dtype(dtype).char,
           *rho_old.items(), None, *rho_new.items())
    ratio = _RATIOS.get(key)
    if ratio is None:
        old = weight_vector(layout, rho_old)
        new = weight_vector(layout, rho_new)
        ratio = np.divide(old, new, out=np.ones_like(old), where=new != 0).astype(dtype)
        if len(_RATIOS) > 256:
            _RATIOS.clear()
        _RATIOS[key] = ratio
    return ratio


def rescale_dual(w: Any, layout: HorizonLayout, rho_old: Mapping[str, float],
                 rho_new: Mapping[str, float],
                 constant: Callable[[np.ndarray], Any] | None = None) -> Any:
    """:func:`scale_dual` by :func:`dual_ratio`: ``w * G_old / G_new`` blockwise (keeps
    ``y = 2 G w``); ``w`` is (..., T, step size). ``constant`` moves the (memoised) ratio to
    the kernel's device once (JAX)."""
    ratio = dual_ratio(layout, rho_old, rho_new, w.dtype)
    return scale_dual(w, ratio if constant is None else constant(ratio))


def plan_ratios(layout: HorizonLayout, plan: Sequence[Mapping[str, float]], rescale: bool,
                dtype: Any) -> np.ndarray:
    """The rescaling the loop applies after each iteration of a planned schedule but the
    last: row ``i`` (len(plan) - 1, step size) is :func:`dual_ratio` from ``plan[i]`` to
    ``plan[i + 1]`` when ``rescale`` and they differ, else ones (multiplying by 1 is exact).
    Memoised by (block sizes, dtype, rescale, the plan's items): the same array comes back
    for the same plan (read it, do not change it)."""
    sizes = (layout.nx, layout.nlam, layout.nu, layout.n_eta, np.dtype(dtype).char, rescale)
    last = _LAST_PLAN_RATIOS.get(sizes)
    if last is not None and last[0] is plan and is_frozen(plan):
        return last[1]
    key = (*sizes, *(tuple(rho.items()) for rho in plan))
    ratios = _PLAN_RATIOS.get(key)
    if ratios is None:
        ratios = np.ones((max(len(plan) - 1, 0), layout.step_size), dtype=dtype)
        for i in range(len(plan) - 1):
            if rescale and plan[i + 1] != plan[i]:
                ratios[i] = dual_ratio(layout, plan[i], plan[i + 1], dtype)
        if len(_PLAN_RATIOS) > 64:
            _PLAN_RATIOS.clear()
        _PLAN_RATIOS[key] = ratios
    if len(_LAST_PLAN_RATIOS) > 16:
        _LAST_PLAN_RATIOS.clear()
    _LAST_PLAN_RATIOS[sizes] = (plan, ratios)
    return ratios


class _Loop:
    """The state of one control step's ADMM (:func:`run_admm`)."""

    def __init__(self, kernel: Kernel, options: C3Options, p: np.ndarray,
                 record_residuals: bool) -> None:
        self.kernel = kernel
        self.options = options
        self.p = p
        self.schedule: Schedule = schedule_for(options)
        self.need_residuals = (record_residuals or options.stopping == Stopping.RESIDUAL
                               or options.rho_schedule != "geometric")
        self.trace = C3Trace()
        self.iterates: list[C3Iterate] = []

    def residuals(self, rho: Mapping[str, float], z: Any, delta_old: Any, new_delta: Any
                  ) -> tuple[float, float, float]:
        if not self.need_residuals:
            return math.nan, math.nan, math.nan
        G = weight_vector(self.kernel.layout, rho)
        difference = np.asarray(z) - np.asarray(new_delta)
        consensus = weighted_norm(difference, self.p)
        dual = weighted_norm(2.0 * G * (np.asarray(new_delta) - np.asarray(delta_old)), self.p)
        return consensus, float(np.max(np.abs(difference), initial=0.0)), dual

    def converged(self, rho: Mapping[str, float], z: Any, new_delta: Any, new_w: Any,
                  consensus: float, dual: float) -> bool:
        options = self.options
        size = self.kernel.layout.horizon * self.kernel.layout.step_size
        G = weight_vector(self.kernel.layout, rho)
        eps_pri = math.sqrt(size) * options.eps_abs + options.eps_rel * max(
            weighted_norm(np.asarray(z), self.p), weighted_norm(np.asarray(new_delta), self.p))
        eps_dual = math.sqrt(size) * options.eps_abs + options.eps_rel * weighted_norm(
            2.0 * G * np.asarray(new_w), self.p)
        return consensus <= eps_pri and dual <= eps_dual


def run_admm(kernel: Kernel, options: C3Options, inputs: StepInputs, delta: Any, w: Any,
             fallback_input: np.ndarray, force_limit: float, record_residuals: bool = True
             ) -> C3Solution:
    """One control step of the ADMM (module docstring); never raises for a kernel failure.

    Parameters
    ----------
    kernel
        The arithmetic (QP step and projection).
    options
        Controller options (schedule, stopping, output, iterations).
    inputs
        Per-step data given to ``kernel.start`` (``plan`` is filled in here).
    delta, w
        Initial iterates (S, T, step size) in the kernel's array type.
    fallback_input
        Returned with ``ok=False`` when a step fails.
    force_limit
        ``|u_i|`` clip of the returned input.
    record_residuals
        Compute the residuals every iteration even when the schedule does not need them. The
        per-iteration trace is kept when residuals are computed or iterates kept (a failed
        iteration is always traced).

    A kernel with ``run_plan`` (the compiled one) runs a planned schedule with ``fixed``
    stopping, when nothing is recorded per iteration, in one call (:func:`_run_planned`:
    the iterations below, rescaling by :func:`plan_ratios`, compiled); else the loop calls
    the kernel once per iteration.
    """
    started = time.perf_counter()
    loop = _Loop(kernel, options, inputs.weights, record_residuals)
    kernel.timings = FastTimings()
    state = _State(delta, w, dict(options.rho0), status=f"{options.admm_iterations} iterations")
    inputs.plan = plan = loop.schedule.plan(state.rho, options.admm_iterations)
    try:
        kernel.start(inputs)
    except KernelFailure as failure:
        state.status = f"{failure.kind}: {failure.reason}" if failure.reason else failure.kind
        state.ok = False
    if state.ok and plan and getattr(kernel, "run_plan", None) is not None and \
            options.stopping == Stopping.FIXED and not loop.need_residuals and \
            not options.keep_iterates:
        _run_planned(kernel, options, loop, plan, state)
    elif state.ok:
        _run_iterations(kernel, options, loop, plan, state)
    u, u_raw, ok, status = _output(kernel, options, inputs, state.delta, state.z_steps,
                                   state.ok, state.status, fallback_input, force_limit)
    kernel.timings.total = time.perf_counter() - started
    return C3Solution(u=u, u_raw=u_raw, ok=ok, status=status, iterations=state.completed,
                      delta=state.delta, w=state.w, z_steps=state.z_steps,
                      z_terminal=state.z_terminal, rho=state.rho_used,
                      weights=inputs.weights, layout=kernel.layout, variant=options.variant,
                      trace=loop.trace, iterates=loop.iterates,
                      cache_hits=int(getattr(kernel, "step_cache_hits", 0)),
                      cache_misses=int(getattr(kernel, "step_cache_misses", 0)),
                      timings=kernel.timings, kernel=kernel.name)


@dataclass
class _State:
    """The iterates and outcome of one control step's loop (:func:`run_admm`)."""

    delta: Any
    w: Any
    rho: dict[str, float]
    rho_used: dict[str, float] = field(default_factory=dict)
    z_steps: Any = None
    z_terminal: Any = None
    completed: int = 0
    ok: bool = True
    status: str = ""

    def __post_init__(self) -> None:
        self.rho_used = dict(self.rho)


def _run_iterations(kernel: Kernel, options: C3Options, loop: _Loop,
                    plan: Sequence[Mapping[str, float]] | None, state: _State) -> None:
    """The iterations, one kernel call each (:func:`admm_iteration` or ``kernel.fused``),
    with residuals, trace, stopping and the rho update (module docstring)."""
    rho, delta, w = state.rho, state.delta, state.w
    previous: float | None = None
    step = getattr(kernel, "fused", None) or admm_iteration
    constant = getattr(kernel, "constant", None)
    for i in range(options.admm_iterations):
        iteration_start = time.perf_counter()
        state.rho_used = rho  # never changed in place: the schedule returns a new dict
        try:
            z, terminal, new_delta, new_w = step(kernel, rho, delta, w)
        except KernelFailure as failure:
            _fail(loop, state, i, rho, failure, time.perf_counter() - iteration_start)
            break
        consensus, consensus_inf, dual = loop.residuals(rho, z, delta, new_delta)
        if options.keep_iterates:
            loop.iterates.append(C3Iterate(i, dict(rho), np.array(delta), np.array(w),
                                           np.array(z), np.array(terminal)))
        if loop.need_residuals or options.keep_iterates:
            info = dict(getattr(kernel, "info", {}) or {})
            loop.trace.append(i, rho, consensus_residual=consensus,
                              consensus_residual_inf=consensus_inf, dual_residual=dual,
                              iteration_time=time.perf_counter() - iteration_start, **info)
        delta, w, state.z_steps, state.z_terminal = new_delta, new_w, z, terminal
        state.delta, state.w = delta, w
        state.completed = i + 1
        if options.stopping == Stopping.RESIDUAL and loop.converged(
                rho, z, new_delta, new_w, consensus, dual):
            state.status = (f"converged in {state.completed} iterations (r={consensus:.3g}, "
                            f"s={dual:.3g})")
            return
        if i + 1 < options.admm_iterations:
            updated = dict(plan[i + 1]) if plan else loop.schedule.next(rho, consensus,
                                                                        previous, dual)
            if options.rescale_dual and updated != rho:
                w = state.w = rescale_dual(w, kernel.layout, rho, updated, constant)
            rho = updated
        previous = consensus
    else:
        if options.stopping == Stopping.RESIDUAL:
            state.status = f"iteration limit {options.admm_iterations} reached"


def _run_planned(kernel: Any, options: C3Options, loop: _Loop,
                 plan: Sequence[Mapping[str, float]], state: _State) -> None:
    """The iterations of :func:`_run_iterations` for a planned schedule with ``fixed``
    stopping and nothing recorded, in one kernel call: ``kernel.run_plan(plan, ratios, delta,
    w)`` runs iteration ``i`` (QP step, projection, :func:`dual_update`) with ``plan[i]`` and
    then, before the next, :func:`scale_dual` by ``ratios[i]`` (:func:`plan_ratios`); it
    returns a :class:`PlanRun`. Same iterates, status and trace as the iteration-by-iteration
    loop."""
    ratios = plan_ratios(kernel.layout, plan, options.rescale_dual, kernel.dtype)
    started = time.perf_counter()
    run: PlanRun = kernel.run_plan(plan, ratios, state.delta, state.w)
    state.completed = run.completed
    state.delta, state.w, state.z_steps, state.z_terminal = run.delta, run.w, run.z_steps, \
        run.z_terminal
    last = min(run.completed, len(plan) - 1)
    state.rho_used = dict(plan[last])
    if run.failure is not None:
        _fail(loop, state, run.completed, plan[run.completed], run.failure,
              time.perf_counter() - started)


def _fail(loop: _Loop, state: _State, i: int, rho: Mapping[str, float],
          failure: KernelFailure, elapsed: float) -> None:
    """Trace the failed iteration ``i`` and set the step's status (the loop stops)."""
    message = failure.reason if failure.kind == "QP failed" else str(failure)
    loop.trace.append(i, rho, failed=True, non_finite=failure.non_finite, message=message,
                      **failure.info, iteration_time=elapsed)
    state.status = (f"{failure.kind} at iteration {i}: {failure.reason}" if failure.reason
                    else f"{failure.kind} at iteration {i}")
    state.ok = False
    state.rho_used = dict(rho)


def _output(kernel: Kernel, options: C3Options, inputs: StepInputs, delta: Any, z_steps: Any,
            ok: bool, status: str, fallback: np.ndarray, force_limit: float
            ) -> tuple[np.ndarray, np.ndarray | None, bool, str]:
    """The applied input: ``u_0`` of ``delta`` or ``z``, averaged over shared samples, clipped."""
    if not ok or z_steps is None:
        return np.array(fallback, dtype=float), None, ok, status
    u_slice = kernel.layout.index(0, "u")
    source = delta if options.output == Output.DELTA else z_steps
    first = np.asarray(source)[:, 0, u_slice]
    # the float64 weights' product promotes a float32 ``first`` exactly, as astype would
    u_raw = inputs.weights @ first if inputs.shared_inputs else first.astype(np.float64)
    # one shared input has a few entries: Python's check is cheaper than numpy's there
    finite = all(map(math.isfinite, u_raw.tolist())) if u_raw.ndim == 1 else \
        bool(np.isfinite(u_raw).all())
    if not finite:
        return np.array(fallback, dtype=float), None, False, "non-finite input"
    # np.clip's result, without its Python wrappers (no NaN gets here)
    return np.minimum(np.maximum(u_raw, -force_limit), force_limit), u_raw, ok, status
