"""Records of one control step of the consensus ADMM: the one solution type of every kernel."""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from c3bench.problems.mpc import HorizonLayout
from c3bench.problems.names import BLOCKS, Variant


@dataclass
class C3Iterate:
    """One ADMM iteration's data (arrays have a leading sample axis: (S, T, step size)).

    ``delta`` and ``w`` are the QP's inputs at this iteration (``z`` solves the QP built from
    them with weights ``rho``); ``projection_v = z + w`` is the point the projection received.
    """

    iteration: int
    rho: dict[str, float]
    delta: np.ndarray
    w: np.ndarray
    z_steps: np.ndarray
    z_terminal: np.ndarray

    @property
    def projection_v(self) -> np.ndarray:
        """``z + w``: the point the projection received."""
        point: np.ndarray = self.z_steps + self.w
        return point


@dataclass
class C3Trace:
    """Per-iteration series (one entry per attempted ADMM iteration).

    ``consensus_residual = ||z - delta_new||_2`` and ``dual_residual =
    ||2 G (delta_new - delta_old)||_2`` (weighted over robust samples; ``nan`` when the kernel
    did not compute them); ``consensus_residual_inf`` the infinity norm; ``complementarity_*``
    the natural-map violation ``max |min(lam, eta)|`` on the mpcc instance and ``cost_*`` the
    MPC cost (reference kernel only); ``rho_*`` the weights the iteration's QP used; times in
    seconds; ``cond_kkt`` is ``nan`` unless recorded; ``qp_found`` the QP backend's own claim;
    ``failed`` and ``non_finite`` mark the iteration that stopped the step; ``message`` the
    backend's status or the failure reason.
    """

    iteration: list[int] = field(default_factory=list)
    rho_x: list[float] = field(default_factory=list)
    rho_lam: list[float] = field(default_factory=list)
    rho_u: list[float] = field(default_factory=list)
    rho_eta: list[float] = field(default_factory=list)
    consensus_residual: list[float] = field(default_factory=list)
    consensus_residual_inf: list[float] = field(default_factory=list)
    dual_residual: list[float] = field(default_factory=list)
    complementarity_delta: list[float] = field(default_factory=list)
    complementarity_z: list[float] = field(default_factory=list)
    cost_z: list[float] = field(default_factory=list)
    cost_delta: list[float] = field(default_factory=list)
    qp_setup_time: list[float] = field(default_factory=list)
    qp_time: list[float] = field(default_factory=list)
    projection_time: list[float] = field(default_factory=list)
    iteration_time: list[float] = field(default_factory=list)
    cond_kkt: list[float] = field(default_factory=list)
    qp_found: list[bool] = field(default_factory=list)
    failed: list[bool] = field(default_factory=list)
    non_finite: list[bool] = field(default_factory=list)
    message: list[str] = field(default_factory=list)

    def series(self) -> dict[str, list[float]]:
        """The numeric series as floats (booleans as 0/1), for ``Result.trace``."""
        out: dict[str, list[float]] = {}
        for name, values in vars(self).items():
            if name == "message":
                continue
            out[name] = [float(v) for v in values]
        return out

    def append(self, iteration: int, rho: Mapping[str, float], **values: Any) -> None:
        """Record one iteration; fields not given take their "not measured" value."""
        self.iteration.append(iteration)
        for block in BLOCKS:
            getattr(self, f"rho_{block}").append(float(rho[block]))
        defaults: dict[str, Any] = {
            "consensus_residual": math.nan, "consensus_residual_inf": math.nan,
            "dual_residual": math.nan, "complementarity_delta": math.nan,
            "complementarity_z": math.nan, "cost_z": math.nan, "cost_delta": math.nan,
            "qp_setup_time": 0.0, "qp_time": 0.0, "projection_time": 0.0,
            "iteration_time": 0.0, "cond_kkt": math.nan, "qp_found": False,
            "failed": False, "non_finite": False, "message": "",
        }
        unknown = set(values) - set(defaults)
        if unknown:
            raise KeyError(f"unknown trace fields {sorted(unknown)}")
        defaults.update(values)
        for key, value in defaults.items():
            getattr(self, key).append(value)


@dataclass
class FastTimings:
    """Seconds spent in one control step (wall clock, ``time.perf_counter``).

    ``factor`` (factorisations of the QP step's matrix, cache misses only), ``qp_solve`` (the
    rest of the QP step), ``projection`` (projection and shared-input mean), ``total`` (the
    whole call); ``qp = factor + qp_solve``; everything else is ``overhead``. A kernel that
    fuses the QP step and the projection in one call reports it as ``qp_solve``.
    """

    factor: float = 0.0
    qp_solve: float = 0.0
    projection: float = 0.0
    total: float = 0.0

    @property
    def qp(self) -> float:
        return self.factor + self.qp_solve

    @property
    def overhead(self) -> float:
        return max(self.total - self.qp - self.projection, 0.0)


@dataclass
class C3Solution:
    """Outcome of one control step (every kernel returns this type).

    Attributes
    ----------
    u, u_raw
        Input to apply (clipped to the force limit; the last safe input when ``ok`` is false;
        per sample (S, nu) for independent samples) and before clipping (``None`` when failed).
    ok, status, iterations
        Every iteration succeeded with finite values; why it stopped; completed iterations.
    delta, w
        Final projection iterate and scaled dual, (S, T, step size) in the QP layout.
    z_steps, z_terminal
        Last QP solution: steps (S, T, step size) and terminal states (S, nx).
    rho
        Weights of the last iteration's QP.
    weights
        Sample weights (sum 1).
    layout, variant
        The QP layout of one sample; ``c3plus`` or ``c3``.
    trace, iterates
        Per-iteration records (``iterates`` only with ``keep_iterates``).
    cache_hits, cache_misses, timings
        Factorisation cache counts (kernels with a cache) and :class:`FastTimings`.
    kernel
        The kernel that ran the step (``reference``, ``riccati``, ``compiled``, ``jax``).
    """

    u: np.ndarray
    u_raw: np.ndarray | None
    ok: bool
    status: str
    iterations: int
    delta: np.ndarray
    w: np.ndarray
    z_steps: np.ndarray | None
    z_terminal: np.ndarray | None
    rho: dict[str, float]
    weights: np.ndarray
    layout: HorizonLayout
    variant: str = Variant.C3PLUS
    trace: C3Trace = field(default_factory=C3Trace)
    iterates: list[C3Iterate] = field(default_factory=list)
    cache_hits: int = 0
    cache_misses: int = 0
    timings: FastTimings = field(default_factory=FastTimings)
    kernel: str = "reference"

    @property
    def delta0(self) -> np.ndarray:
        """Sample 0's ``delta`` (T x step size)."""
        first: np.ndarray = self.delta[0]
        return first

    @property
    def w0(self) -> np.ndarray:
        """Sample 0's ``w`` (T x step size)."""
        first: np.ndarray = self.w[0]
        return first

    @property
    def consensus_residual(self) -> list[float]:
        """Per-iteration consensus residuals that were computed (``nan`` ones left out)."""
        return [v for v in self.trace.consensus_residual if not math.isnan(v)]

    @property
    def dual_residual(self) -> list[float]:
        """Per-iteration dual residuals that were computed (``nan`` ones left out)."""
        return [v for v in self.trace.dual_residual if not math.isnan(v)]


FastSolution = C3Solution
"""The batched kernels' name for :class:`C3Solution` (one type)."""
