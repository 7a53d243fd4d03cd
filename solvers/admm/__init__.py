"""The consensus ADMM of C3 / C3+, defined once (docs/admm.md).

* :mod:`.options`: :class:`C3Options` (the weights ``G`` via ``rho0`` and the schedule, ``U``
  via ``projection_weights``) and the option names;
* :mod:`.schedules`: the rho schedules (geometric, adaptive, residual balancing);
* :mod:`.projection`: the C3+ closed form, the box limits and the shared-input mean, written
  once against an array namespace (numpy, JAX; numba compiles the numpy closure);
* :mod:`.loop`: the iteration (:func:`admm_iteration`), residuals, stopping, rho update,
  output (:func:`run_admm`);
* :mod:`.kernel`: what a kernel provides; kernels: :mod:`.stacked` (reference: the QP step
  through any registry backend, C3's projection by MIQP or mode enumeration),
  :class:`c3bench.solvers.fast.FastC3Plus` (numpy Riccati), :mod:`.compiled` (numba) and
  :class:`c3bench.solvers.fast_jax.JaxC3Plus` (JAX);
* :mod:`.controller`: the entry points and the warm-started controller.
"""

from c3bench.solvers.admm.controller import (
    C3Controller,
    FastC3PlusController,
    WarmStartController,
    solve_batched,
    solve_c3,
    solve_robust,
)
from c3bench.solvers.admm.kernel import Kernel, KernelFailure, StepInputs
from c3bench.solvers.admm.loop import admm_iteration, dual_update, run_admm
from c3bench.solvers.admm.options import (
    C3Options,
    DualWarmStart,
    Output,
    RhoScheduleName,
    Stopping,
)
from c3bench.solvers.admm.schedules import Adaptive, Geometric, ResidualBalancing, schedule_for
from c3bench.solvers.admm.solution import C3Iterate, C3Solution, C3Trace, FastTimings

__all__ = ["Adaptive", "C3Controller", "C3Iterate", "C3Options", "C3Solution", "C3Trace",
           "DualWarmStart",
           "FastC3PlusController", "FastTimings", "Geometric", "Kernel", "KernelFailure",
           "Output", "ResidualBalancing", "RhoScheduleName", "StepInputs", "Stopping",
           "WarmStartController", "admm_iteration", "dual_update", "run_admm", "schedule_for",
           "solve_batched", "solve_c3", "solve_robust"]
