"""``c3plus_riccati``: the C3+ QP step by ``eta`` elimination and a Riccati recursion.

A thin adapter over :mod:`c3bench.solvers.riccati_qp` and :mod:`c3bench.solvers.riccati` (the
algorithm and its derivation live there): it reads the per-step blocks of ``P`` and ``q`` of a
``c3plus_qp`` instance (declining a ``P`` that couples time steps), the attached LCS and
``x0``, checks that ``A z = b`` is the LCS's structure
(:func:`~c3bench.solvers.riccati_qp.structure_of`), solves
(:func:`~c3bench.solvers.riccati_qp.solve_structured`) and returns the equality duals from the
stationarity of the ``x`` and ``eta`` columns
(:func:`~c3bench.solvers.riccati_qp.equality_duals`).

``settings.options`` may set ``jacobi``, ``ridge``, ``symmetrize`` and ``rollout``
(:class:`~c3bench.solvers.riccati.RiccatiOptions`); ``settings.precision`` picks float64 or
float32. A direct method: ``iterations`` is 1.

Timing (the contract of :mod:`c3bench.solvers.timing`; rankings use setup + solve): setup is
reading the structure (:func:`~c3bench.solvers.riccati_qp.structure_of`: the per-step blocks of
the LCS and the cost); solve is :func:`~c3bench.solvers.riccati_qp.solve_structured`, whose
backward Riccati recursion factorises ``Q_vv`` step by step interleaved with the rollout (the
factorisations cannot be split from it), and the equality duals.

References
----------
B. D. O. Anderson and J. B. Moore, *Optimal Control: Linear Quadratic Methods*, Prentice
Hall, 1990 (the discrete-time Riccati recursion of the LQ problem).

Bui et al., 2025: C3+, whose slack ``eta`` this QP step eliminates.
"""

from __future__ import annotations

import numpy as np

from c3bench.problems.instance import Problem
from c3bench.problems.mpc import HorizonLayout
from c3bench.problems.names import Failure, Family, Precision
from c3bench.solvers.base import Backend, Result, Settings, WarmStart
from c3bench.solvers.registry import register
from c3bench.solvers.riccati import RiccatiOptions
from c3bench.solvers.riccati_qp import equality_duals, solve_structured, structure_of
from c3bench.solvers.timing import Stopwatch

RICCATI_OPTIONS: tuple[str, ...] = ("jacobi", "ridge", "symmetrize", "rollout")
"""Keys of ``settings.options`` passed on to :class:`RiccatiOptions`."""


class RiccatiBackend(Backend):
    """The C3+ QP step by eta elimination and a Riccati recursion (module docstring)."""

    name = "c3plus_riccati"
    families = (Family.C3PLUS_QP,)
    package = ""
    precisions = (Precision.FLOAT64, Precision.FLOAT32)
    description = ("C3+ QP step: eta eliminated, Riccati recursion + rollout (structure "
                   "exploiting, batched core)")

    def accepts(self, problem: Problem) -> tuple[bool, str]:
        """A ``c3plus_qp`` instance with its LCS, layout, no rows ``G`` and no finite bounds."""
        ok, reason = super().accepts(problem)
        if not ok:
            return ok, reason
        if problem.lcs is None:
            return False, "needs the LCS attached to the instance"
        if "layout" not in problem.meta:
            return False, "needs meta['layout']"
        if problem.G is not None:
            return False, "takes no inequality rows"
        for bound in (problem.lb, problem.ub):
            if bound is not None and np.any(np.isfinite(bound)):
                return False, "takes no finite bounds (input_bounds must be off)"
        layout = HorizonLayout.from_json(problem.meta["layout"])
        if layout.n_eta != layout.nlam or layout.size != problem.n:
            return False, "layout is not the C3+ layout of this instance"
        return True, ""

    def solve(self, problem: Problem, settings: Settings,
              warm_start: WarmStart | None = None) -> Result:
        """Read the structure, solve, recover the duals; a structure mismatch is
        ``Failure.UNSUPPORTED``, a singular ``Q_vv`` ``Failure.ERROR``."""
        watch = Stopwatch()
        extra = {k: v for k, v in settings.options.items() if k in RICCATI_OPTIONS}
        options = RiccatiOptions(precision=settings.precision, **extra)
        try:
            with watch.lap("setup"):
                structured = structure_of(problem)
            with watch.lap("solve"):
                z = solve_structured(structured, options)
                y = equality_duals(problem, z)
        except ValueError as error:
            return Result.failed(self.name, problem.name, Failure.UNSUPPORTED, str(error))
        except np.linalg.LinAlgError as error:
            return Result.failed(self.name, problem.name, Failure.ERROR,
                                 f"singular Q_vv in the Riccati recursion: {error}")
        finite = bool(np.all(np.isfinite(z)))
        return Result(solver=self.name, problem=problem.name, found=finite,
                      status="solved (Riccati)" if finite else "non-finite solution",
                      x=z, y=y if finite else None, iterations=1,
                      setup_time=watch.get("setup"), solve_time=watch.get("solve"),
                      objective=problem.objective(z) if finite else None,
                      failure=Failure.NONE if finite else Failure.NON_FINITE)


register(RiccatiBackend())
