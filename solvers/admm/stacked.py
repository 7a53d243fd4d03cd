"""The reference kernel: the QP step as one (stacked) QP through any registry backend.

**QP step** (:func:`c3bench.problems.families.consensus_qp`, family ``c3plus_qp`` or
``c3_qp``) built explicitly and solved by the registry backend ``options.qp_backend`` called
directly (or the wrapper in ``options.backends``). With ``mpc.limits`` (and ``use_limits``)
the input and state boxes are bounds of this QP, where the C3 paper's method puts them.
For ``S > 1`` samples sharing the inputs (the robust controller) one stacked QP

    minimise  sum_j p_j [ J(z_j) + ||z_j - (delta_j - w_j)||^2_G ]   (u_k shared)

whose variables are sample 0's whole vector, then each further sample's without ``u``.

**Projection**: C3+ closed form (:mod:`.projection`) in ``U`` per sample; C3's per-step
projection ``min ||(x, lam, u) - v||^2_U`` s.t. ``0 <= lam perp E x + F lam + H u + c >= 0``
(:func:`c3bench.problems.families.projection`, variant ``c3``, zero weight on ``eta``) by an
MIQP registry backend, or exactly by enumerating contact modes
(``projection_backend="enumeration"``, :mod:`c3bench.solvers.projection_enum`).
"""

from __future__ import annotations

import math
import time
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from c3bench.problems import families
from c3bench.problems.instance import Problem
from c3bench.problems.lcs import LCS
from c3bench.problems.mpc import MPC, HorizonLayout
from c3bench.problems.names import Block, Variant
from c3bench.solvers import registry
from c3bench.solvers.admm.kernel import KernelFailure, StepInputs
from c3bench.solvers.admm.options import ENUMERATION, C3Options
from c3bench.solvers.admm.projection import make_step_projection
from c3bench.solvers.admm.solution import FastTimings
from c3bench.solvers.base import Backend, Result, Settings
from c3bench.solvers.isolation import IsolationFailed
from c3bench.solvers.residuals import complementarity_violation


def qp_layout(lcs: LCS, horizon: int, variant: str) -> HorizonLayout:
    """Layout of the QP step: with ``eta`` for C3+, without for C3."""
    return HorizonLayout(lcs.nx, lcs.nlam, lcs.nu, lcs.nlam if variant == Variant.C3PLUS else 0,
                         horizon)


def full_layout(lcs: LCS, horizon: int) -> HorizonLayout:
    """The C3+ / mpcc layout ``(x, lam, u, eta)``."""
    return HorizonLayout(lcs.nx, lcs.nlam, lcs.nu, lcs.nlam, horizon)


def to_full_steps(steps: np.ndarray, lcs: LCS, layout: HorizonLayout,
                  homogeneous: bool = False) -> np.ndarray:
    """Steps (T x step size) of ``layout`` in the C3+ layout.

    A C3 layout gets ``eta = E x + F lam + H u + c`` (the LCS gap), or without ``c`` when
    ``homogeneous`` (for a difference of points such as the scaled dual ``w``, so that
    ``(delta - w)`` keeps ``eta = gap``). A C3+ layout is returned as a copy.
    """
    steps = np.asarray(steps, dtype=float)
    if layout.n_eta:
        return steps.copy()
    x = steps[:, layout.index(0, "x")]
    lam = steps[:, layout.index(0, "lam")]
    u = steps[:, layout.index(0, "u")]
    eta = x @ lcs.E.T + lam @ lcs.F.T + u @ lcs.H.T
    if not homogeneous:
        eta = eta + lcs.c
    return np.hstack([steps, eta])


def mpcc_vector(full_steps: np.ndarray, x_terminal: np.ndarray) -> np.ndarray:
    """The mpcc family's variable vector: the steps, then the terminal state."""
    return np.concatenate([np.asarray(full_steps).ravel(), np.asarray(x_terminal)])


def projection_weight_vector(options: C3Options, layout: HorizonLayout,
                             rho: Mapping[str, float]) -> np.ndarray:
    """``diag U`` of one step of ``layout``: ``projection_weights`` if given, else ``G(rho)``."""
    weights = options.projection_weights if options.projection_weights is not None else rho
    return families.weight_vector(layout, weights)


def box_of_step(mpc: MPC, layout: HorizonLayout, use: bool) -> tuple[np.ndarray, np.ndarray]:
    """Lower and upper box of one step's ``(x, u)`` from ``mpc.limits`` (``+-inf`` if none)."""
    lower = np.full(layout.nx + layout.nu, -np.inf)
    upper = np.full(layout.nx + layout.nu, np.inf)
    limits = getattr(mpc, "limits", None)
    if use and limits is not None:
        lower[:layout.nx], upper[:layout.nx] = limits.x_lower, limits.x_upper
        lower[layout.nx:], upper[layout.nx:] = limits.u_lower, limits.u_upper
    return lower, upper


def kkt_condition(problem: Problem) -> float:
    """``cond_2`` of ``[[P, A^T], [A, 0]]`` (an SVD)."""
    n, m = problem.n, problem.n_eq
    K = np.zeros((n + m, n + m))
    K[:n, :n] = problem.P
    if m and problem.A is not None:
        K[:n, n:] = problem.A.T
        K[n:, :n] = problem.A
    return float(np.linalg.cond(K))


def solve_qp(backend: Backend, problem: Problem, settings: Settings
             ) -> tuple[np.ndarray | None, Result | None, str]:
    """Call the backend directly; ``(x, result, "")`` or ``(None, result, reason)``.

    :class:`~c3bench.solvers.isolation.IsolationFailed` (a time-limited backend could not
    start its process) is raised: an infrastructure fault, not a failed solve.
    """
    accepted, reason = backend.accepts(problem)
    if not accepted:
        return None, None, f"{backend.name} rejects the QP: {reason}"
    try:
        result = backend.solve(problem, settings)
    except IsolationFailed:
        raise
    except Exception as error:  # noqa: BLE001 - any backend error is a recorded failure
        return None, None, f"{backend.name} raised {type(error).__name__}: {error}"
    x = result.x
    if x is None or np.shape(x) != (problem.n,):
        why = f"{result.failure}: {result.status}" if result.failure else result.status
        return None, result, f"{backend.name} returned no solution ({why})"
    x = np.asarray(x, dtype=float)
    if not np.all(np.isfinite(x)):
        return None, result, f"{backend.name} returned non-finite values ({result.status})"
    return x, result, ""


def project_step_c3(v: np.ndarray, lcs: LCS, U: np.ndarray, backend: Backend | None,
                    settings: Settings, name: str = "c3-projection") -> np.ndarray:
    """C3's projection of one step ``v = (x, lam, u)`` with weight ``diag U`` (length ``nx +
    nlam + nu``): ``min ||d - v||^2_U`` s.t. ``0 <= lam perp E x + F lam + H u + c >= 0``.

    ``backend=None`` enumerates the contact modes (exact); otherwise the MIQP
    :func:`c3bench.problems.families.projection` (variant ``c3``) is solved by ``backend``.
    Raises ``RuntimeError`` when the backend finds no finite point.
    """
    if backend is None:
        from c3bench.solvers.projection_enum import project_c3_enumerated

        projected: np.ndarray = project_c3_enumerated(np.asarray(v, dtype=float)[None, :], lcs,
                                                       U)[0]
        return projected
    layout1 = HorizonLayout(lcs.nx, lcs.nlam, lcs.nu, lcs.nlam, 1)
    v_full = to_full_steps(np.asarray(v, dtype=float)[None, :], lcs,
                           HorizonLayout(lcs.nx, lcs.nlam, lcs.nu, 0, 1))[0]
    U_full = np.concatenate([np.asarray(U, dtype=float), np.zeros(lcs.nlam)])
    problem = families.projection(name, lcs, v_full, U_full, Variant.C3)
    result = backend.solve(problem, settings)
    x = result.x
    if x is None or np.shape(x) != (problem.n,) or not np.all(np.isfinite(x)):
        raise RuntimeError(f"projection backend {backend.name} failed: {result.status}")
    keep = np.ones(layout1.step_size, dtype=bool)
    keep[layout1.index(0, "eta")] = False
    return np.asarray(x, dtype=float)[keep]


class StackedKernel:
    """The reference kernel (module docstring) for ``S >= 1`` samples sharing the inputs."""

    name = "reference"

    def __init__(self, lcs_samples: Sequence[LCS], mpc: MPC, x0: np.ndarray,
                 options: C3Options) -> None:
        self.samples = list(lcs_samples)
        self.mpc = mpc
        self.x0 = np.asarray(x0, dtype=float)
        self.options = options
        self.weights = np.ones(len(self.samples)) / len(self.samples)
        first = self.samples[0]
        for lcs in self.samples[1:]:
            if (lcs.nx, lcs.nlam, lcs.nu) != (first.nx, first.nlam, first.nu):
                raise ValueError("all LCS samples must have the same dimensions")
        self.layout = qp_layout(first, mpc.horizon, options.variant)
        self.timings = FastTimings()
        self.info: dict[str, Any] = {}
        self._iteration = -1
        self.limits = getattr(mpc, "limits", None) if options.use_limits else None
        self.box_in_projection = False
        """Set when the QP backend takes no bounds: C3+ then clips ``delta`` to the box in
        its projection (the fast kernels' splitting), C3 runs without the limits."""
        self.mpccs = [families.mpcc(f"c3-mpcc-{j}", lcs, mpc, self.x0)
                      for j, lcs in enumerate(self.samples)]
        self._stack_index()
        self.qp_backend: Backend | None = None
        self.projection_backend: Backend | None = None
        self._project_c3plus = make_step_projection(np, first.nx, first.nlam, first.nu)

    def _stack_index(self) -> None:
        layout = self.layout
        self.n_qp = layout.size
        self.steps = layout.horizon * layout.step_size
        u_positions = np.concatenate([np.arange(layout.index(k, "u").start,
                                                layout.index(k, "u").stop)
                                      for k in range(layout.horizon)])
        others = np.setdiff1d(np.arange(self.n_qp), u_positions)
        self.index: list[np.ndarray] = [np.arange(self.n_qp)]
        size = self.n_qp
        for _ in self.samples[1:]:
            idx = np.empty(self.n_qp, dtype=np.int64)
            idx[u_positions] = u_positions
            idx[others] = size + np.arange(others.size)
            size += others.size
            self.index.append(idx)
        self.size = size

    @property
    def n_samples(self) -> int:
        return len(self.samples)

    def start(self, inputs: StepInputs) -> None:
        self.weights = np.asarray(inputs.weights, dtype=float)
        self._iteration = -1
        options = self.options
        try:
            self.qp_backend = options.backends.get(options.qp_backend) or \
                registry.get(options.qp_backend)
            if options.variant == Variant.C3 and options.projection_backend != ENUMERATION:
                self.projection_backend = options.backends.get(options.projection_backend) \
                    or registry.get(options.projection_backend)
        except KeyError as error:
            raise KernelFailure(str(error.args[0])) from None

    # -- QP step -------------------------------------------------------------------------------
    def build(self, rho: Mapping[str, float], delta: np.ndarray, w: np.ndarray,
              name: str) -> Problem:
        """The QP step: ``consensus_qp`` itself for one sample, else the stacked QP."""
        family = self.options.qp_family
        weights = {key: float(rho[key]) for key in self.layout.block_sizes()}
        extra: dict[str, Any] = {"limits": self.limits} if self.limits is not None else {}
        qps = [families.consensus_qp(family, f"{name}-s{j}" if self.n_samples > 1 else name,
                                     lcs, self.mpc, self.x0, weights, delta[j], w[j],
                                     input_bounds=self.options.input_bounds, **extra)
               for j, lcs in enumerate(self.samples)]
        if self.n_samples == 1:
            return qps[0]
        return self._stack(qps, weights, name)

    def _stack(self, qps: list[Problem], weights: dict[str, float], name: str) -> Problem:
        n = self.size
        P = np.zeros((n, n))
        q = np.zeros(n)
        offset = 0.0
        A_rows: list[np.ndarray] = []
        b_rows: list[np.ndarray] = []
        bounded = any(qp.lb is not None or qp.ub is not None for qp in qps)
        lb = np.full(n, -np.inf) if bounded else None
        ub = np.full(n, np.inf) if bounded else None
        for j, qp in enumerate(qps):
            idx = self.index[j]
            p = float(self.weights[j])
            P[np.ix_(idx, idx)] += p * qp.P
            q[idx] += p * qp.q
            offset += p * qp.objective_offset
            assert qp.A is not None and qp.b is not None  # consensus_qp always has A z = b
            rows = np.zeros((qp.n_eq, n))
            rows[:, idx] = qp.A
            A_rows.append(rows)
            b_rows.append(qp.b)
            if lb is not None and ub is not None:
                if qp.lb is not None:
                    lb[idx] = np.maximum(lb[idx], qp.lb)
                if qp.ub is not None:
                    ub[idx] = np.minimum(ub[idx], qp.ub)
        P = 0.5 * (P + P.T)
        return Problem(name=name, family=self.options.qp_family, P=P, q=q, A=np.vstack(A_rows),
                       b=np.concatenate(b_rows), lb=lb, ub=ub, objective_offset=offset,
                       lcs=self.samples[0], data={"x0": self.x0},
                       meta={"robust_samples": self.n_samples,
                             "sample_weights": [float(p) for p in self.weights],
                             "rho": weights, "sample_layout": self.layout.to_json(),
                             "input_bounds": self.options.input_bounds})

    def split(self, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Per-sample steps (S, T, step size) and terminal states (S, nx) of a QP solution."""
        zs = [np.asarray(y)[idx] for idx in self.index]
        steps = np.stack([z[:self.steps].reshape(self.layout.horizon, self.layout.step_size)
                          for z in zs])
        terminal = np.stack([z[self.steps:] for z in zs])
        return steps, terminal

    # -- the iteration -------------------------------------------------------------------------
    def iterate(self, rho: Mapping[str, float], delta: np.ndarray, w: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        self.info = {}
        self._iteration += 1
        build_start = time.perf_counter()
        try:
            problem = self.build(rho, delta, w, f"c3-qp-i{self._iteration:02d}")
        except ValueError as error:
            raise KernelFailure("QP build failed", str(error)) from None
        setup_time = time.perf_counter() - build_start
        qp_start = time.perf_counter()
        assert self.qp_backend is not None and self.options.qp_settings is not None
        if self.limits is not None and not self.qp_backend.accepts(problem)[0]:
            self.limits = None  # e.g. a KKT backend: the limits move to the projection
            self.box_in_projection = self.options.variant == Variant.C3PLUS
            problem = self.build(rho, delta, w, f"c3-qp-i{self._iteration:02d}")
        y, result, reason = solve_qp(self.qp_backend, problem, self.options.qp_settings)
        qp_time = time.perf_counter() - qp_start
        self.timings.qp_solve += qp_time + setup_time
        cond = kkt_condition(problem) if self.options.record_conditioning else math.nan
        timing = {"qp_setup_time": setup_time, "qp_time": qp_time, "cond_kkt": cond}
        if y is None:
            raise KernelFailure("QP failed", reason, "non-finite" in reason, timing)
        steps, terminal = self.split(y)
        projection_start = time.perf_counter()
        found = bool(result.found) if result else False
        try:
            new_delta = self.project(steps + w, rho)
        except Exception as error:  # noqa: BLE001 - a failed projection is recorded
            raise KernelFailure("projection failed", str(error), info={
                **timing, "qp_found": found,
                "projection_time": time.perf_counter() - projection_start}) from None
        projection_time = time.perf_counter() - projection_start
        self.timings.projection += projection_time
        if not np.all(np.isfinite(new_delta)):
            raise KernelFailure("non-finite projection", "", True,
                                {**timing, "projection_time": projection_time})
        cost_z, comp_z = self.measures(steps, terminal)
        cost_delta, comp_delta = self.measures(new_delta, terminal)
        self.info = {**timing, "projection_time": projection_time, "qp_found": found,
                     "message": result.status if result else "", "cost_z": cost_z,
                     "complementarity_z": comp_z, "cost_delta": cost_delta,
                     "complementarity_delta": comp_delta}
        return steps, terminal, new_delta

    def project(self, v: np.ndarray, rho: Mapping[str, float]) -> np.ndarray:
        """The projection of ``v = z + w`` (S, T, step size) in ``U``."""
        U = projection_weight_vector(self.options, self.layout, rho)
        if self.options.variant == Variant.C3PLUS:
            lam_s, eta_s = self.layout.index(0, Block.LAM), self.layout.index(0, Block.ETA)
            lower, upper = box_of_step(self.mpc, self.layout, use=self.box_in_projection)
            projected: np.ndarray = self._project_c3plus(
                v, np.sqrt(U[lam_s]), np.sqrt(U[eta_s]), lower, upper, self.weights, False)
            return projected
        return np.stack([np.stack([
            project_step_c3(v[j, k], self.samples[j], U, self.projection_backend,
                            self.options.projection_settings,
                            f"c3-projection-i{self._iteration:02d}-s{j}-k{k}")
            for k in range(self.layout.horizon)]) for j in range(self.n_samples)])

    # -- measures ------------------------------------------------------------------------------
    def full_vector(self, j: int, steps: np.ndarray, terminal: np.ndarray) -> np.ndarray:
        """Sample ``j``'s trajectory as an mpcc vector (``eta`` = LCS gap for C3)."""
        return mpcc_vector(to_full_steps(steps, self.samples[j], self.layout), terminal)

    def measures(self, steps: np.ndarray, terminal: np.ndarray) -> tuple[float, float]:
        """Weighted cost ``sum_j p_j J_j`` and worst complementarity violation."""
        cost, violation = 0.0, 0.0
        for j, problem in enumerate(self.mpccs):
            vector = self.full_vector(j, steps[j], terminal[j])
            cost += float(self.weights[j]) * problem.objective(vector)
            violation = max(violation, complementarity_violation(problem, vector))
        return cost, violation
