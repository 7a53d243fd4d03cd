"""Entry points of the one ADMM: a control step from an LCS, and the warm-started controller.

* :func:`solve_c3` / :func:`solve_robust`: the reference kernel (:mod:`.stacked`), one LCS or
  ``S`` samples sharing the inputs;
* :func:`solve_batched`: any batched kernel (numpy Riccati, compiled, JAX) on an
  :class:`~c3bench.problems.lcs.LCSBatch`;
* :class:`WarmStartController`: the controller logic shared by every kernel. After a successful
  step ``delta`` is shifted one step forward in time (:func:`.loop.shift_warm_start`), the rho
  schedule restarts from ``rho0`` and the scaled dual ``w`` restarts from zero, as in the C3
  reference implementation (``options.warm_dual="scaled"`` keeps the shifted ``w`` instead:
  :class:`.options.DualWarmStart` says why that diverges under residual balancing); a failed
  step drops the warm start and returns the last safe input; ``options.warm_start=False``
  makes every step cold.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, Protocol

import numpy as np

from c3bench.problems.errors import InputError
from c3bench.problems.lcs import LCS, LCSBatch
from c3bench.problems.mpc import MPC
from c3bench.solvers.admm.kernel import StepInputs
from c3bench.solvers.admm.loop import (
    initial_iterates,
    normalise_weights,
    run_admm,
    shift_in_time,
    shift_warm_start,
)
from c3bench.solvers.admm.options import C3Options, DualWarmStart
from c3bench.solvers.admm.solution import C3Solution, C3Trace
from c3bench.solvers.admm.stacked import StackedKernel, qp_layout


def check_sizes(nx: int, nlam: int, nu: int, x0: np.ndarray) -> np.ndarray:
    """``x0`` as float64 after checking the LCS's sizes, for every kernel alike
    (:class:`InputError`, one line): C3 / C3+ need a contact pair (``nlam >= 1``; an LCS
    without one is a linear system, whose MPC is one QP) and an input (``nu >= 1``), and
    ``x0`` has ``nx`` entries."""
    if nlam < 1:
        raise InputError("the LCS has no complementarity pair (nlam = 0): C3 / C3+ need at "
                         "least one; without contacts the MPC is a single QP")
    if nu < 1:
        raise InputError("the LCS has no input (nu = 0): there is nothing to control")
    state = np.asarray(x0, dtype=np.float64)
    if state.shape != (nx,):
        raise InputError(f"x0 must have shape ({nx},), got {state.shape}")
    return state


def solve_c3(lcs: LCS, mpc: MPC, x0: np.ndarray, options: C3Options | None = None,
             delta: np.ndarray | None = None, w: np.ndarray | None = None,
             fallback_input: np.ndarray | None = None) -> C3Solution:
    """One control step of C3 / C3+ from state ``x0`` with the reference kernel.

    Parameters
    ----------
    lcs, mpc
        Model and cost (``mpc.limits`` are enforced unless ``options.use_limits`` is off).
    x0
        Measured state.
    options
        Controller options (defaults: the reference study's C3+).
    delta, w
        Initial projection iterate and scaled dual (T x step size of the QP layout); a cold
        start when ``None``.
    fallback_input
        Returned (with ``ok=False``) when the step fails; zero when ``None``.
    """
    return solve_robust([lcs], None, mpc, x0, options, delta, w, fallback_input)


def solve_robust(lcs_samples: Sequence[LCS], weights: Sequence[float] | np.ndarray | None,
                 mpc: MPC, x0: np.ndarray, options: C3Options | None = None,
                 delta: np.ndarray | None = None, w: np.ndarray | None = None,
                 fallback_input: np.ndarray | None = None) -> C3Solution:
    """The robust controller: ``S`` LCS samples with shared inputs, one stacked QP.

    ``weights`` are normalised and floored (:func:`.loop.normalise_weights`; uniform when
    ``None``); ``delta``, ``w`` are (S, T, step size) or (T, step size); ``u`` is
    ``sum_j p_j delta_j u_0`` (or of ``z`` with ``output="z"``).
    """
    options = options or C3Options()
    if len(lcs_samples) < 1:
        raise InputError("solve_robust needs at least one LCS sample")
    S = len(lcs_samples)
    p = normalise_weights(weights, S)
    first = lcs_samples[0]
    x0 = check_sizes(first.nx, first.nlam, first.nu, x0)
    fallback = np.zeros(first.nu) if fallback_input is None else np.asarray(fallback_input,
                                                                            dtype=float)
    layout = qp_layout(first, mpc.horizon, options.variant)
    delta_init, w_init = initial_iterates(layout, x0, S, delta, w)
    try:
        kernel = StackedKernel(lcs_samples, mpc, x0, options)
    except ValueError as error:
        return C3Solution(u=fallback.copy(), u_raw=None, ok=False,
                          status=f"invalid input: {error}", iterations=0, delta=delta_init,
                          w=w_init, z_steps=None, z_terminal=None, rho=dict(options.rho0),
                          weights=p, layout=layout, variant=options.variant, trace=C3Trace())
    return run_admm(kernel, options, StepInputs(x0, p, True), delta_init, w_init, fallback,
                    float(mpc.force_limit))


def solve_batched(kernel: Any, lcs: LCSBatch, mpc: MPC, x0: np.ndarray, options: C3Options,
                  weights: Sequence[float] | None = None, delta: np.ndarray | None = None,
                  w: np.ndarray | None = None, fallback_input: np.ndarray | None = None,
                  shared_inputs: bool = True, record_residuals: bool = False,
                  trusted_iterates: bool = False) -> C3Solution:
    """One control step of a batched kernel (numpy Riccati, compiled, JAX) on ``lcs``
    (``trusted_iterates``: ``delta`` and ``w`` are a controller's own warm start,
    :func:`.loop.initial_iterates`)."""
    n = lcs.n_samples
    x0 = check_sizes(lcs.nx, lcs.nlam, lcs.nu, x0)
    fallback = np.zeros(lcs.nu) if fallback_input is None else np.asarray(fallback_input,
                                                                          dtype=float)
    p = normalise_weights(weights, n)
    kernel.bind(lcs)
    delta_init, w_init = initial_iterates(kernel.layout, x0, n, delta, w, kernel.dtype,
                                          trusted_iterates)
    inputs = StepInputs(x0, p, shared_inputs)
    return run_admm(kernel, options, inputs, delta_init, w_init, fallback,
                    float(mpc.force_limit), record_residuals)


class WarmStartController:
    """Warm start, last safe input and failure count (module docstring), for any kernel."""

    def __init__(self, options: C3Options, initial_input: np.ndarray | None = None) -> None:
        self.options = options
        self.last_safe_input = None if initial_input is None else np.asarray(initial_input,
                                                                             dtype=float)
        self.delta: np.ndarray | None = None
        self.w: np.ndarray | None = None
        self.failures = 0

    def reset(self) -> None:
        """Forget the warm start, the last safe input and the failure count."""
        self.delta = self.w = self.last_safe_input = None
        self.failures = 0

    def warm(self, shape: tuple[int, ...]) -> tuple[np.ndarray | None, np.ndarray | None]:
        """The shifted previous iterates when warm starts are on and the shape agrees."""
        if not self.options.warm_start or self.delta is None or self.w is None or \
                self.delta.shape != shape:
            return None, None
        if self.options.warm_dual == DualWarmStart.ZERO:  # no shifted dual to throw away
            return shift_in_time(self.delta), np.zeros(self.w.shape, self.w.dtype)
        return shift_warm_start(self.delta, self.w)

    def record(self, solution: C3Solution) -> C3Solution:
        """Keep a successful step's iterates and input; drop them after a failure."""
        if solution.ok:
            self.delta, self.w = solution.delta, solution.w
            self.last_safe_input = np.array(solution.u, dtype=float)  # a copy
        else:
            self.delta = self.w = None
            self.failures += 1
        return solution


class C3Controller(WarmStartController):
    """A C3 / C3+ controller on the reference kernel (single model or robust samples)."""

    def __init__(self, options: C3Options | None = None,
                 initial_input: np.ndarray | None = None) -> None:
        super().__init__(options or C3Options(), initial_input)

    def _shape(self, lcs: LCS, mpc: MPC, samples: int) -> tuple[int, ...]:
        layout = qp_layout(lcs, mpc.horizon, self.options.variant)
        return (samples, layout.horizon, layout.step_size)

    def step(self, lcs: LCS, mpc: MPC, x0: np.ndarray) -> C3Solution:
        """One control step with the single model ``lcs``."""
        delta, w = self.warm(self._shape(lcs, mpc, 1))
        return self.record(solve_c3(lcs, mpc, x0, self.options, delta, w,
                                    self.last_safe_input))

    def step_robust(self, lcs_samples: Sequence[LCS], weights: Sequence[float] | None,
                    mpc: MPC, x0: np.ndarray) -> C3Solution:
        """One control step of the robust variant."""
        delta, w = self.warm(self._shape(lcs_samples[0], mpc, len(lcs_samples)))
        return self.record(solve_robust(lcs_samples, weights, mpc, x0, self.options, delta,
                                        w, self.last_safe_input))


class BatchedSolver(Protocol):
    """What :class:`FastC3PlusController` drives (``FastC3Plus``, ``JaxC3Plus``, ...)."""

    options: C3Options

    def solve(self, lcs: LCSBatch, x0: np.ndarray, weights: Sequence[float] | None = None,
              delta: np.ndarray | None = None, w: np.ndarray | None = None,
              fallback_input: np.ndarray | None = None, trusted_iterates: bool = False
              ) -> C3Solution: ...


class FastC3PlusController(WarmStartController):
    """The warm-started controller over a batched solver."""

    def __init__(self, solver: BatchedSolver, initial_input: np.ndarray | None = None) -> None:
        super().__init__(solver.options, initial_input)
        self.solver = solver

    def step(self, lcs: LCSBatch, x0: np.ndarray, weights: Sequence[float] | None = None
             ) -> C3Solution:
        """One control step on the LCS batch."""
        shape = None if self.delta is None else (lcs.n_samples, *self.delta.shape[1:])
        delta, w = self.warm(shape) if shape is not None else (None, None)
        # the shifted iterates of this solver's last successful step: used unchecked
        return self.record(self.solver.solve(lcs, x0, weights, delta, w, self.last_safe_input,
                                             trusted_iterates=delta is not None))
