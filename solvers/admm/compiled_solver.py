"""``c3plus-compiled``: the compiled (numba) kernel driven by the one ADMM loop.

:class:`CompiledC3Plus` has the interface of :class:`c3bench.solvers.fast.FastC3Plus`
(``solve(lcs, x0, weights, delta, w, fallback_input)``, usable by
:class:`c3bench.solvers.admm.FastC3PlusController`): the loop of :mod:`.loop` does the
residuals, rho schedule (with the dual rescaling), stopping and output;
:class:`.compiled.CompiledC3PlusKernel` does the QP step, the projection and the (compiled)
dual update in one compiled call per iteration (:meth:`CompiledC3Plus.fused`, which the loop
calls) and factorises a geometric schedule's rho values a group at a time; with a geometric
schedule, ``fixed`` stopping and nothing recorded, the loop hands it the whole plan instead
(:meth:`CompiledC3Plus.run_plan`, one compiled call per control step). The box limits of
``mpc.limits`` (``options.use_limits``) go into its projection,
``projection_weights`` (``U``) into the pairs' closed form.
"""

from __future__ import annotations

import time
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from c3bench.problems.lcs import LCSBatch
from c3bench.problems.mpc import MPC, HorizonLayout
from c3bench.problems.names import BLOCKS, Precision
from c3bench.solvers.admm.compiled import CompiledC3PlusKernel
from c3bench.solvers.admm.controller import solve_batched
from c3bench.solvers.admm.kernel import PlanRun, StepInputs
from c3bench.solvers.admm.options import C3Options
from c3bench.solvers.admm.solution import C3Solution, FastTimings
from c3bench.solvers.admm.stacked import box_of_step
from c3bench.solvers.fast import RiccatiOptions


class CompiledC3Plus:
    """Batched C3+ with the compiled kernel (module docstring).

    Parameters
    ----------
    mpc
        Cost, goal, horizon, force limit and (optionally) limits.
    options
        :class:`C3Options` (variant ``c3plus``; ``input_bounds`` off: limits go to the
        projection).
    precision
        ``float64`` or ``float32`` (every array and the arithmetic).
    riccati
        ``jacobi`` and ``ridge`` of :class:`c3bench.solvers.fast.RiccatiOptions`.
    shared_inputs
        Robust variant (consensus on ``u`` in the projection) or independent samples.
    record_residuals
        Compute the residuals every iteration even when the schedule does not need them.
    """

    name = "compiled"
    step_cache_hits = 0
    """No step cache: every rho value is factorised (the loop reads these counts)."""
    step_cache_misses = 0

    def __init__(self, mpc: MPC, options: C3Options | None = None,
                 precision: str = Precision.FLOAT64, riccati: RiccatiOptions | None = None,
                 shared_inputs: bool = True, record_residuals: bool = False) -> None:
        options = options or C3Options(keep_iterates=False)
        options.check_batched_c3plus("CompiledC3Plus")
        self.mpc = mpc
        self.options = options
        self.kernel = CompiledC3PlusKernel(mpc, Precision(precision), riccati)
        self.kernel.projection_weights = options.projection_weights
        self.shared_inputs = shared_inputs
        self.record_residuals = record_residuals
        self.timings = FastTimings()
        self.info: dict[str, Any] = {}
        self.layout = HorizonLayout(mpc.nx, 0, mpc.nu, 0, mpc.horizon)
        self._lcs: LCSBatch | None = None
        self._box_key: tuple[Any, ...] | None = None
        """Sizes, ``use_limits`` and the limits object (held, compared by identity) of the
        box last given to the kernel."""

    @property
    def dtype(self) -> Any:
        return self.kernel.dtype

    @property
    def compile_seconds(self) -> float:
        """JIT time spent in this process so far (excluded from step timings)."""
        return float(self.kernel.compile_seconds)

    @property
    def executed_flops(self) -> float:
        """Floating-point operations the kernel executed in the last control step
        (:attr:`CompiledC3PlusKernel.flops`)."""
        return float(self.kernel.flops)

    def bind(self, lcs: LCSBatch) -> None:
        """Use ``lcs`` for the next control step."""
        self._lcs = lcs
        layout = self.layout
        if (layout.nx, layout.nlam, layout.nu) != (lcs.nx, lcs.nlam, lcs.nu):  # else reused
            self.layout = HorizonLayout(lcs.nx, lcs.nlam, lcs.nu, lcs.nlam, self.mpc.horizon)

    def start(self, inputs: StepInputs) -> None:
        """Box, state, weights and the plan (converting the LCS counts as ``factor``)."""
        assert self._lcs is not None
        key = (self.layout.nx, self.layout.nu, self.options.use_limits,
               getattr(self.mpc, "limits", None))  # Limits compare by identity (eq=False)
        if key != self._box_key:
            self.kernel.set_box(box_of_step(self.mpc, self.layout, self.options.use_limits))
            self._box_key = key
        t0 = time.perf_counter()
        self.kernel.start(self._lcs, inputs.x0, inputs.weights, inputs.shared_inputs,
                          inputs.plan)
        self.timings.factor += time.perf_counter() - t0

    def iterate(self, rho: Mapping[str, float], delta: np.ndarray, w: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """QP step and projection of all samples in one compiled call."""
        z_steps, z_terminal, new_delta = self._timed_step(self.kernel.iterate, rho, delta, w)
        return z_steps, z_terminal, new_delta

    def fused(self, kernel: Any, rho: Mapping[str, float], delta: np.ndarray, w: np.ndarray
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """One ADMM iteration (:func:`c3bench.solvers.admm.loop.admm_iteration`: QP step,
        projection and the compiled :func:`~c3bench.solvers.admm.loop.dual_update`) in one
        compiled call; the loop calls this instead of ``admm_iteration``."""
        z_steps, z_terminal, new_delta, new_w = self._timed_step(self.kernel.step, rho, delta, w)
        return z_steps, z_terminal, new_delta, new_w

    def run_plan(self, plan: Sequence[Mapping[str, float]], ratios: np.ndarray,
                 delta: np.ndarray, w: np.ndarray) -> PlanRun:
        """A whole planned schedule in one compiled call (the loop calls this for a
        geometric schedule with ``fixed`` stopping and nothing recorded:
        :meth:`CompiledC3PlusKernel.run_plan`); its factorisations and iterations are one
        call, timed as ``qp_solve``."""
        t0 = time.perf_counter()
        run = self.kernel.run_plan(plan, ratios, delta, w)
        self.timings.qp_solve += time.perf_counter() - t0
        return run

    def _timed_step(self, step: Any, *args: Any) -> Any:
        """Call ``step``; its factorisations (a plan group's first iteration, an off-plan
        rho) count as ``factor``, the rest as ``qp_solve``."""
        t0, factored = time.perf_counter(), self.kernel.factor_seconds
        out = step(*args)
        factor = self.kernel.factor_seconds - factored
        self.timings.factor += factor
        self.timings.qp_solve += time.perf_counter() - t0 - factor
        return out

    def solve(self, lcs: LCSBatch, x0: np.ndarray, weights: Sequence[float] | None = None,
              delta: np.ndarray | None = None, w: np.ndarray | None = None,
              fallback_input: np.ndarray | None = None, trusted_iterates: bool = False
              ) -> C3Solution:
        """One control step of the one ADMM (:func:`c3bench.solvers.admm.solve_batched`;
        ``trusted_iterates`` as :meth:`c3bench.solvers.fast.FastC3Plus.solve`)."""
        return solve_batched(self, lcs, self.mpc, x0, self.options, weights, delta, w,
                             fallback_input, self.shared_inputs, self.record_residuals,
                             trusted_iterates)


def warm_up() -> float:
    """Compile (or load from numba's disk cache) every kernel signature, float64 and float32,
    on a tiny random problem (a whole planned control step and one iteration at a time);
    returns the seconds spent."""
    started = time.perf_counter()
    rng = np.random.default_rng(0)
    nx, nlam, nu, T = 2, 1, 1, 2
    mpc = MPC(Q=np.eye(nx), R=np.eye(nu), Q_f=np.eye(nx), x_target=np.zeros(nx), horizon=T,
              dt=0.1, force_limit=1.0)
    lcs = LCSBatch(A=rng.normal(size=(1, nx, nx)), B=rng.normal(size=(1, nx, nu)),
                   D=rng.normal(size=(1, nx, nlam)), d=np.zeros((1, nx)),
                   E=rng.normal(size=(1, nlam, nx)), F=np.eye(nlam)[None],
                   H=rng.normal(size=(1, nlam, nu)), c=np.zeros((1, nlam)), dt=0.1)
    rho: dict[str, float] = {block: 1.0 for block in BLOCKS}
    for precision in Precision:
        kernel = CompiledC3PlusKernel(mpc, precision)
        kernel.start(lcs, np.zeros(nx), np.ones(1), True, [rho])
        zeros = np.zeros((1, T, nx + 2 * nlam + nu))
        kernel.iterate(rho, zeros, zeros)
        CompiledC3Plus(mpc, C3Options(keep_iterates=False, admm_iterations=2),
                       precision).solve(lcs, np.zeros(nx))
    return time.perf_counter() - started
