"""Registry adapters ``c3plus_admm`` and ``c3_admm``: the C3 / C3+ controller as an mpcc solver.

A thin layer over :mod:`c3bench.solvers.c3` (the ADMM lives there). From an ``mpcc`` instance
(built by :func:`c3bench.problems.families.mpcc`) the adapter recovers

* the LCS (``problem.lcs``) and ``x0`` (``problem.data["x0"]``);
* the MPC cost from ``P``, ``q``: ``Q = P_{x_0 x_0} / 2``, ``R = P_{u_0 u_0} / 2``,
  ``Q_f = P_{x_T x_T} / 2`` and ``x*`` the least-squares solution of ``2 Q_f x* = -q_{x_T}``
  (any ``x*`` component with zero weight is irrelevant to the cost); the force limit from
  ``ub`` on ``u`` and the input / state limits from ``meta["limits"]`` (a bounded mpcc), which
  the controller then enforces where its method puts them
  (:func:`c3bench.problems.recover.mpc_from_cost`). The instance is then rebuilt with
  :func:`c3bench.problems.families.mpcc` and must match ``P``, ``q``, ``A``, ``b``, the bounds
  and the offset (:func:`c3bench.problems.recover.mismatches`; else the backend declines: the
  instance was not an mpcc of this form);

and runs :func:`c3bench.solvers.c3.solve_c3` from a cold start (or from ``warm_start.x``, an mpcc
vector whose horizon steps become the initial ``delta``; ``w = 0``).

Weights and options: the instance's ``meta["c3_options"]`` (any
:class:`c3bench.solvers.admm.C3Options` field: ``rho0`` (G), ``projection_weights`` (U),
``admm_iterations``, ...) are the defaults, and ``settings.options`` keys that are such fields
(``qp_backend``, ``rho_schedule``, ``stopping``, ...) override them, so a user's LCS runs with
its own tuning rather than the cube's; ``settings.max_iterations`` caps the ADMM iterations;
the inner QP (and projection) run with the outer profile, tolerance, time limit and precision.
``options["solution"]`` picks the returned point:

* ``"delta"`` (default): the projected trajectory ``delta`` (complementary by construction)
  closed with the QP's terminal state ``x_T``; its dynamics residual is of the order of the
  consensus residual;
* ``"z"``: the last QP solution (dynamics exact, complementarity violated), with ``eta`` the
  LCS gap for C3;
* ``"rollout"``: the LCS simulated from ``x0`` under ``delta``'s inputs (clipped to the force
  limit) with Lemke's method: dynamics and complementarity hold, so its cost is an upper
  bound of the mpcc optimum.

``found`` is true when the run completed and the returned point's complementarity violation
and the final consensus residual ``||z - delta||_inf`` are at most ``settings.tolerance``.
``objective`` is the mpcc cost of the returned point. ``trace`` is the controller's
per-iteration record (:meth:`c3bench.solvers.c3.C3Trace.series`); ``diagnostics`` add the
costs of the other two candidate points.

Timing (the contract of :mod:`c3bench.solvers.timing`; rankings use setup + solve): setup is
turning the instance into the controller's MPC data and options; solve is the whole ADMM run
(its QP steps, their setups included, and projections), as a controller pays it.

References
----------
W. Aydinoglu and M. Posa, "Real-time multi-contact model predictive control via ADMM",
IEEE International Conference on Robotics and Automation (ICRA), 2022 (C3).

Bui et al., 2025: C3+, the variant with the slack ``eta`` and a closed-form projection.

S. Boyd, N. Parikh, E. Chu, B. Peleato and J. Eckstein, "Distributed optimization and
statistical learning via the alternating direction method of multipliers", Foundations and
Trends in Machine Learning 3(1), 1-122, 2011 (consensus ADMM, residuals, rho updates).
"""

from __future__ import annotations

import math
from dataclasses import fields
from typing import Any

import numpy as np

from c3bench.problems import families
from c3bench.problems.instance import Problem
from c3bench.problems.limits import Limits
from c3bench.problems.mpc import MPC, HorizonLayout
from c3bench.problems.names import Failure, Family, Precision, Variant
from c3bench.problems.recover import mismatches, mpc_from_cost
from c3bench.solvers.base import Backend, Result, Settings, WarmStart
from c3bench.solvers.c3 import C3Options, C3Solution, rollout_vector, solve_c3, to_full_steps
from c3bench.solvers.registry import register
from c3bench.solvers.residuals import complementarity_violation
from c3bench.solvers.timing import Stopwatch

SOLUTION_POINTS: tuple[str, ...] = ("delta", "z", "rollout")
_NOT_PASSED = {"variant", "qp_settings", "projection_settings"}


def mpc_from_mpcc(problem: Problem) -> MPC:
    """Recover the MPC of an ``mpcc`` instance (module docstring); ``ValueError`` when the
    instance is not reproduced by :func:`problems.families.mpcc` from it."""
    if problem.lcs is None or "x0" not in problem.data or "layout" not in problem.meta:
        raise ValueError("an mpcc instance needs lcs, data['x0'] and meta['layout']")
    layout = HorizonLayout.from_json(problem.meta["layout"])
    su = layout.index(0, "u")
    force_limit = float(np.max(np.inf if problem.ub is None else problem.ub[su]))
    limits = Limits.from_json(problem.meta["limits"]) if "limits" in problem.meta else None
    mpc = mpc_from_cost(problem, layout, force_limit, limits)
    rebuilt = families.mpcc(problem.name, problem.lcs, mpc, problem.data["x0"], limits=limits)
    wrong = mismatches(rebuilt, problem)
    if wrong:
        raise ValueError(f"not an mpcc of problems.families.mpcc's form (mismatch in "
                         f"{', '.join(wrong)})")
    return mpc


def options_for(variant: Variant, settings: Settings,
                meta: dict[str, Any] | None = None) -> tuple[C3Options, str]:
    """``C3Options`` and the solution point (module docstring).

    The instance's own ``meta["c3_options"]`` (e.g. ``rho0``, ``projection_weights``,
    ``admm_iterations`` a user stored with the problem) are the defaults; ``settings.options``
    override them; anything not given takes :class:`C3Options`' defaults.
    """
    allowed = {f.name for f in fields(C3Options)} - _NOT_PASSED
    stored = dict((meta or {}).get("c3_options", {}) or {})
    unknown = set(stored) - allowed
    if unknown:
        raise ValueError(f"meta['c3_options'] has unknown keys {sorted(unknown)}")
    chosen: dict[str, Any] = {**stored, **{k: v for k, v in settings.options.items()
                                           if k in allowed}}
    for key in ("rho0", "projection_weights"):
        if chosen.get(key) is not None:
            chosen[key] = {str(k): float(v) for k, v in dict(chosen[key]).items()}
    if "rho_blocks" in chosen:
        chosen["rho_blocks"] = tuple(chosen["rho_blocks"])
    if settings.max_iterations is not None and "admm_iterations" not in chosen:
        chosen["admm_iterations"] = int(settings.max_iterations)
    inner = Settings(profile=settings.profile, tolerance=settings.tolerance,
                     time_limit=settings.time_limit, precision=settings.precision)
    point = str(settings.options.get("solution", "delta"))
    if point not in SOLUTION_POINTS:
        raise ValueError(f"options['solution'] must be one of {SOLUTION_POINTS}, got {point!r}")
    return C3Options(variant=variant, qp_settings=inner, projection_settings=inner,
                     **chosen), point


def _points(problem: Problem, mpc: MPC, solution: C3Solution) -> dict[str, np.ndarray]:
    """The candidate mpcc vectors of a finished run."""
    lcs = problem.lcs
    assert lcs is not None
    layout = solution.layout
    out: dict[str, np.ndarray] = {}
    if solution.z_steps is None or solution.z_terminal is None:
        return out
    terminal = solution.z_terminal[0]
    out["delta"] = np.concatenate([to_full_steps(solution.delta0, lcs, layout).ravel(),
                                   terminal])
    out["z"] = np.concatenate([to_full_steps(solution.z_steps[0], lcs, layout).ravel(),
                               terminal])
    inputs = solution.delta0[:, layout.index(0, "u")]
    rolled = rollout_vector(lcs, mpc, problem.data["x0"], inputs)
    if rolled is not None:
        out["rollout"] = rolled
    return out


class C3Admm(Backend):
    """C3 / C3+ consensus ADMM on the ``mpcc`` family (see the module docstring)."""

    families = (Family.MPCC,)
    package = ""
    precisions = (Precision.FLOAT64,)

    def __init__(self, variant: Variant) -> None:
        self.variant = variant
        self.name = f"{variant}_admm"
        projection = ("closed-form projection" if variant == Variant.C3PLUS
                      else "MIQP projection per step")
        self.description = (f"{'C3+' if variant == Variant.C3PLUS else 'C3'} consensus ADMM "
                            f"(QP step by a registry backend, {projection})")

    def accepts(self, problem: Problem) -> tuple[bool, str]:
        """An ``mpcc`` instance carrying its LCS, ``data["x0"]`` and ``meta["layout"]``."""
        ok, reason = super().accepts(problem)
        if not ok:
            return ok, reason
        if problem.lcs is None or "x0" not in problem.data or "layout" not in problem.meta:
            return False, "the mpcc instance needs lcs, data['x0'] and meta['layout']"
        return True, ""

    def solve(self, problem: Problem, settings: Settings,
              warm_start: WarmStart | None = None) -> Result:
        """Recover the MPC, run the ADMM and return the chosen point (module docstring)."""
        watch = Stopwatch()
        with watch.lap("setup"):
            try:
                mpc = mpc_from_mpcc(problem)
                options, point = options_for(self.variant, settings, problem.meta)
            except (ValueError, TypeError) as error:
                return Result.failed(self.name, problem.name, Failure.UNSUPPORTED, str(error))
            lcs = problem.lcs
            assert lcs is not None
            delta0 = None
            if warm_start is not None and warm_start.x is not None:
                delta0 = self._warm_delta(problem, np.asarray(warm_start.x, dtype=float))
        with watch.lap("solve"):
            solution = solve_c3(lcs, mpc, problem.data["x0"], options, delta0)
        points = _points(problem, mpc, solution)
        diagnostics: dict[str, float] = {
            f"objective_{name}": problem.objective(vector) for name, vector in points.items()}
        trace = solution.trace
        consensus = trace.consensus_residual_inf[-1] if trace.consensus_residual_inf \
            else math.nan
        diagnostics["consensus_residual_inf"] = float(consensus)
        diagnostics["admm_iterations"] = float(solution.iterations)
        for key, value in solution.rho.items():
            diagnostics[f"rho_{key}_final"] = float(value)
        common: dict[str, Any] = {"iterations": solution.iterations,
                                  "setup_time": watch.get("setup"),
                                  "solve_time": watch.get("solve"),
                                  "trace": trace.series(), "diagnostics": diagnostics}
        if not solution.ok or point not in points:
            failure = Failure.NON_FINITE if any(trace.non_finite) else Failure.ERROR
            status = solution.status if not solution.ok else \
                f"{solution.status}; the {point} point is unavailable (Lemke failed)"
            return Result.failed(self.name, problem.name, failure, status, **common)
        x = points[point]
        violation = complementarity_violation(problem, x)
        found = violation <= settings.tolerance and consensus <= settings.tolerance
        status = (f"{solution.status}; complementarity {violation:.3g}, consensus residual "
                  f"{consensus:.3g} (tolerance {settings.tolerance:.3g})")
        return Result(solver=self.name, problem=problem.name, found=found, status=status,
                      x=x, objective=problem.objective(x), **common)

    def _warm_delta(self, problem: Problem, x: np.ndarray) -> np.ndarray | None:
        """Horizon steps of an mpcc vector in the QP layout (eta dropped for C3)."""
        layout = HorizonLayout.from_json(problem.meta["layout"])
        if x.shape != (layout.size,) or not np.all(np.isfinite(x)):
            return None
        steps = x[:layout.horizon * layout.step_size].reshape(layout.horizon,
                                                              layout.step_size)
        if self.variant == Variant.C3:
            keep = np.ones(layout.step_size, dtype=bool)
            keep[layout.index(0, "eta")] = False
            steps = steps[:, keep]
        return steps.copy()


register(C3Admm(Variant.C3PLUS))
register(C3Admm(Variant.C3))
