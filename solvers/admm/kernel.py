"""What the one ADMM loop (:mod:`.loop`) asks of a kernel, and how a kernel fails.

A kernel owns the arithmetic of one control step's QP step and projection for ``S`` samples
in its own precision and on its own device; the loop owns everything else (dual update,
residuals, rho schedule, stopping, output). Kernels: the reference (:mod:`.stacked`: the QP
step through any registry backend, C3's projection by MIQP or enumeration), the numpy Riccati
kernel (:class:`c3bench.solvers.fast.FastC3Plus`), the compiled kernel
(:mod:`.compiled`, numba) and the JAX kernel (:mod:`c3bench.solvers.fast_jax`).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from c3bench.problems.errors import C3BenchError
from c3bench.problems.mpc import HorizonLayout
from c3bench.solvers.admm.solution import FastTimings


class KernelFailure(C3BenchError, RuntimeError):
    """A kernel could not complete an iteration (the step fails with the last safe input).

    ``kind`` names what failed (``"QP failed"``, ``"projection failed"``, ...), ``reason``
    the backend's or the arithmetic's explanation, ``non_finite`` whether a non-finite value
    caused it, ``info`` trace fields measured before the failure.
    """

    def __init__(self, kind: str, reason: str = "", non_finite: bool = False,
                 info: Mapping[str, Any] | None = None) -> None:
        super().__init__(f"{kind}: {reason}" if reason else kind)
        self.kind = kind
        self.reason = reason
        self.non_finite = non_finite
        self.info = dict(info or {})


@dataclass
class StepInputs:
    """What a kernel gets once per control step.

    ``weights`` are the normalised sample weights ``p`` (sum 1); ``shared_inputs`` whether the
    samples share ``u``; ``plan`` every iteration's rho when the schedule is data independent
    (so all factorisations can be computed at once), else ``None``.
    """

    x0: np.ndarray
    weights: np.ndarray
    shared_inputs: bool
    plan: Sequence[Mapping[str, float]] | None = None
    extra: dict[str, Any] = field(default_factory=dict)


@dataclass
class PlanRun:
    """What a kernel's ``run_plan`` returns (a whole planned schedule in one call,
    :func:`c3bench.solvers.admm.loop.run_admm`): the iterations completed, the iterates after
    the last of them (``w`` rescaled for the next when there is one; ``z_steps`` ``None`` when
    none completed) and, when iteration ``completed`` failed, why."""

    completed: int
    delta: Any
    w: Any
    z_steps: Any
    z_terminal: Any
    failure: KernelFailure | None = None


class Kernel(Protocol):
    """The per-iteration arithmetic the loop calls (module docstring)."""

    name: str
    layout: HorizonLayout
    timings: FastTimings

    def start(self, inputs: StepInputs) -> None:
        """Prepare one control step (conversions, factorisations of a planned schedule)."""

    def iterate(self, rho: Mapping[str, float], delta: Any, w: Any
                ) -> tuple[Any, Any, Any]:
        """QP step and projection: ``(z_steps, z_terminal, projection of z_steps + w)``.

        Raises :class:`KernelFailure`. May leave trace fields in ``self.info``.
        """
        ...
