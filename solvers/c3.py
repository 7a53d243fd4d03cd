"""The C3 / C3+ controller: consensus ADMM for the MPC with complementarity (docs/admm.md).

The MPCC of one control step is

    minimise    J(x, u) = sum_{k<T} (x_k - x*)^T Q (x_k - x*) + u_k^T R u_k
                          + (x_T - x*)^T Q_f (x_T - x*)
    subject to  x_0 = x0,  x_{k+1} = A x_k + B u_k + D lam_k + d,
                eta_k = E x_k + F lam_k + H u_k + c,   0 <= lam_k  perp  eta_k >= 0.

Consensus ADMM splits it into a QP (dynamics, no complementarity) over ``z`` and a projection
onto complementarity over a copy ``delta`` of the horizon steps ``z_k`` (k < T; the terminal
state has no copy), with the scaled dual ``w`` and the block weights
``G = diag(rho_x, rho_lam, rho_u, rho_eta)``. Iteration ``i``:

1. **QP step** ``z = argmin J(z) + sum_k ||z_k - (delta_k - w_k)||^2_G`` s.t. the dynamics
   (and, for C3+, ``eta_k = E x_k + F lam_k + H u_k + c``), built by
   :func:`problems.families.consensus_qp` (family ``c3plus_qp`` or ``c3_qp``) and solved by the
   registry backend ``options.qp_backend`` called directly (in this process, unless
   ``options.backends`` supplies a wrapper: the closed loop kills a QP that overruns its
   per-step time limit, :mod:`bench.closed_loop_policy`);
2. **projection** ``delta_k = argmin_{delta in C_k} ||delta - (z_k + w_k)||^2_G`` per step:
   C3+ copies ``x`` and ``u`` and projects each pair ``(lam_i, eta_i)`` in closed form
   (:func:`solvers.projection.c3plus_projection`); C3 solves the MIQP
   :func:`problems.families.projection` (variant ``c3``, weights ``G``'s ``x, lam, u`` blocks
   and zero on ``eta``, which is tied to ``(x, lam, u)`` by the LCS) with the registry backend
   ``options.projection_backend``;
3. **dual update** ``w <- w + z - delta``;
4. **residuals** (Boyd et al. 2011, section 3.3, with Boyd's ``rho`` equal to ``2 G`` because
   our penalty ``||r||^2_G`` is Boyd's ``rho/2 ||r||^2``): consensus (primal) residual
   ``r = ||z - delta||_2`` and dual residual ``s = ||2 G (delta - delta_prev)||_2``, both over
   every horizon step (weighted over the samples of the robust variant, see below);
5. **rho update** (``options.rho_schedule``), applied to the blocks ``options.rho_blocks``
   (default ``lam`` and ``eta``, the reference study's):

   * ``geometric``: ``rho <- factor rho`` (factor 2: the reference study's ``50 * 2^i``);
   * ``adaptive`` (Bertsekas 2014, section 2.2.5): ``rho <- beta rho`` when
     ``r_i >= gamma r_{i-1}``, unchanged otherwise (and at ``i = 0``);
   * ``residual_balancing`` (Boyd et al. 2011, section 3.4.1): ``rho <- tau rho`` when
     ``r > mu s``, ``rho <- rho / tau`` when ``s > mu r``, unchanged otherwise
     (``mu = 10``, ``tau = 2``).

   When a block's weight changes by ``rho_new / rho_old`` its scaled dual is rescaled by
   ``rho_old / rho_new`` (``options.rescale_dual``, default on), so that the unscaled dual
   ``y = 2 G w`` is unchanged (Boyd et al. 2011, end of section 3.4.1).

Stopping: ``fixed`` runs ``admm_iterations`` iterations (seed: 10); ``residual`` stops early
when ``r <= eps_pri = sqrt(p) eps_abs + eps_rel max(||z||, ||delta||)`` and
``s <= eps_dual = sqrt(p) eps_abs + eps_rel ||2 G w||`` (Boyd et al. 2011, eq. 3.12), ``p``
the number of consensus entries.

**Output.** The input applied is ``u_0`` of the projected ``delta`` (``options.output =
"delta"``, the default): ``delta`` is the iterate that satisfies complementarity, so the
input belongs to a consistent contact mode. For C3+ ``delta_u = z_u + w_u`` (``u`` is copied
by the projection); for C3 the MIQP may move ``u``. ``output = "z"`` takes ``u_0`` of the QP
solution instead (dynamically consistent, not complementary). The robust variant returns the
weighted mean of the samples' ``delta u_0``. The input is clipped to
``|u_i| <= mpc.force_limit`` (what the actuator does); ``C3Solution.u_raw`` keeps the
unclipped value.

**Warm start** (:class:`C3Controller`): after a successful control step ``delta`` and ``w``
are shifted one step forward in time (``delta_k <- delta_{k+1}`` for ``k < T-1``, the last step
repeated), the rho schedule restarts from ``rho0``, and the scaled dual is kept as it is (a
choice: the unscaled dual ``2 G w`` therefore shrinks with the restarted, smaller ``rho``;
rescaling it would make the first QP of every step anchor hard on ``delta - w``). A cold
start uses ``delta_k = (x0, 0, 0, 0)`` and ``w = 0``.

**Failure.** A QP backend that raises, rejects the instance or returns a missing or
non-finite ``z`` (likewise a projection) marks the iteration failed in the trace, stops the
ADMM and returns ``ok=False`` with the last safe input (the previous successful control
step's input, zero at the start). Nothing non-finite is returned. A finite answer the backend
does not call solved (e.g. an iteration limit) is used, and flagged ``qp_found = False`` in
the trace.

**Robust variant** (:func:`solve_robust`): ``n`` LCS samples (e.g. cube side
``l ~ U[0.27, 0.33]``) share the inputs ``u_k``; each sample ``j`` has its own
``(x, lam, eta)``, projection, ``delta_j`` and ``w_j``. One stacked QP per iteration:

    minimise  sum_j p_j [ J(z_j) + ||z_j - (delta_j - w_j)||^2_G ]   (u_k shared)

with normalised weights ``p_j`` (sum 1; floored at ``1e-6 max p`` so the stacked KKT stays well
posed), i.e. sample ``j``'s consensus weight is ``G_j = p_j G``. The projection of each sample
is invariant to that factor. Residuals become weighted norms over samples,
``r = sqrt(sum_j p_j ||z_j - delta_j||^2)`` and likewise ``s``, so ``n`` identical samples
reproduce the nominal controller exactly (same QP optimum, same iterates, same residuals).
With ``n = 1`` the stacked QP is the ``consensus_qp`` instance itself.

**Sample weights** (:func:`lcp_prediction_weights`, seed 000 section 3.3): each sample
predicts every past observation ``(x, u, x_next)`` with its LCS, ``lam`` from the LCP
``0 <= lam perp F lam + E x + H u + c >= 0`` (the KKT system of
``min 1/2 lam^T F lam + q^T lam, lam >= 0``) solved by Lemke's method, and
``x_hat = A x + B u + D lam + d``; its error is ``e_j = sum_t ||x_next_t - x_hat_t||^2`` and
its weight ``p_j = exp(-(e_j - min e) / temperature) / sum``.
"""

from __future__ import annotations

import math
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from c3bench.problems import families
from c3bench.problems.capture import Capture, CaptureContext, CapturedIterate
from c3bench.problems.instance import Problem
from c3bench.problems.lcs import LCS
from c3bench.problems.mpc import MPC, HorizonLayout
from c3bench.problems.names import (
    BLOCKS,
    REFERENCE_ADMM_ITERATIONS,
    REFERENCE_RHO0,
    REFERENCE_RHO_BLOCKS,
    REFERENCE_RHO_FACTOR,
    Block,
    Family,
    Profile,
    Variant,
)
from c3bench.solvers import registry
from c3bench.solvers.base import Backend, Result, Settings, settings_for
from c3bench.solvers.isolation import IsolationFailed
from c3bench.solvers.lcp import lemke
from c3bench.solvers.residuals import complementarity_violation

VARIANTS: tuple[Variant, ...] = (Variant.C3PLUS, Variant.C3)
RHO_SCHEDULES: tuple[str, ...] = ("geometric", "adaptive", "residual_balancing")
STOPPING_RULES: tuple[str, ...] = ("fixed", "residual")
OUTPUTS: tuple[str, ...] = ("delta", "z")
WEIGHT_FLOOR = 1e-6
"""Smallest sample weight in the robust QP, relative to the largest."""


# --- options ----------------------------------------------------------------------------------
@dataclass
class C3Options:
    """Everything that configures the controller.

    Attributes
    ----------
    variant
        ``"c3plus"`` (QP over ``(x, lam, u, eta)``, closed-form projection) or ``"c3"`` (QP
        over ``(x, lam, u)``, per-step MIQP projection).
    qp_backend, qp_settings
        Registry name and settings of the QP step's solver. ``qp_settings=None`` (default)
        means the default profile, and for ``equilibrated_kkt`` also
        ``options={"diagnostics": False}`` (its per-solve condition-number SVDs are
        diagnostics, not part of the method, and cost more than the solve in a control loop).
    projection_backend, projection_settings
        Registry name and settings of C3's MIQP projection (unused by C3+).
    admm_iterations
        Iterations (the maximum with ``stopping="residual"``); seed: 10.
    rho0
        Initial weights by block ``x, lam, u, eta``; seed: 1, 50, 0.1, 50.
    rho_schedule
        ``geometric``, ``adaptive`` or ``residual_balancing`` (module docstring).
    rho_blocks
        Blocks whose weight the schedule changes (default ``lam`` and ``eta``).
    rho_factor
        Geometric growth factor (seed: 2).
    adaptive_beta, adaptive_gamma
        Bertsekas's ``beta`` (growth) and ``gamma`` (required decrease ratio); defaults
        ``gamma = 0.25`` and ``beta`` = the reference study's factor 2.
    balance_mu, balance_tau
        Residual balancing's ``mu`` and ``tau`` (Boyd et al.: 10 and 2).
    rescale_dual
        Rescale ``w`` by ``rho_old / rho_new`` when a weight changes.
    stopping
        ``fixed`` or ``residual``.
    eps_abs, eps_rel
        Tolerances of the residual stopping rule.
    input_bounds
        Put ``|u_k| <= force_limit`` into the QP (needs a backend that takes bounds).
    output
        ``delta`` (default) or ``z``: which iterate's ``u_0`` is applied.
    record_conditioning
        Compute ``cond_2`` of the QP's KKT matrix ``[[P, A^T], [A, 0]]`` every iteration (an
        SVD: about 10 ms at T = 7).
    keep_iterates
        Keep every iteration's ``(rho, delta, w, z)`` (for capture and plots).
    backends
        Backend instances used instead of the registry's for these names (e.g. an
        :class:`~c3bench.solvers.isolation.IsolatedBackend` that kills a solve at a per-step
        time limit, :mod:`bench.closed_loop_policy`); the caller owns and closes them. Empty
        (default): the registry's backends, called in this process.
    """

    variant: str = Variant.C3PLUS
    qp_backend: str = "equilibrated_kkt"
    qp_settings: Settings | None = None
    projection_backend: str = "scip"
    projection_settings: Settings = field(
        default_factory=lambda: settings_for(Profile.MID_ACCURACY, time_limit=5.0))
    admm_iterations: int = REFERENCE_ADMM_ITERATIONS
    rho0: dict[str, float] = field(default_factory=lambda: {
        str(block): value for block, value in REFERENCE_RHO0.items()})
    rho_schedule: str = "geometric"
    rho_blocks: tuple[str, ...] = REFERENCE_RHO_BLOCKS
    rho_factor: float = REFERENCE_RHO_FACTOR
    adaptive_beta: float = 2.0
    adaptive_gamma: float = 0.25
    balance_mu: float = 10.0
    balance_tau: float = 2.0
    rescale_dual: bool = True
    stopping: str = "fixed"
    eps_abs: float = 1e-4
    eps_rel: float = 1e-3
    input_bounds: bool = False
    output: str = "delta"
    record_conditioning: bool = False
    keep_iterates: bool = True
    backends: Mapping[str, Backend] = field(default_factory=dict)

    def __post_init__(self) -> None:
        for name, value, allowed in (("variant", self.variant, VARIANTS),
                                     ("rho_schedule", self.rho_schedule, RHO_SCHEDULES),
                                     ("stopping", self.stopping, STOPPING_RULES),
                                     ("output", self.output, OUTPUTS)):
            if value not in allowed:
                raise ValueError(f"{name} must be one of {allowed}, got {value!r}")
        if not isinstance(self.admm_iterations, int) or self.admm_iterations < 1:
            raise ValueError(f"admm_iterations must be an integer >= 1, got "
                             f"{self.admm_iterations!r}")
        if self.qp_settings is None:
            self.qp_settings = Settings(options={"diagnostics": False}) \
                if self.qp_backend == "equilibrated_kkt" else Settings()
        self.variant = Variant(self.variant)
        self.rho0 = families.check_rho(self.rho0, BLOCKS)
        self.rho_blocks = tuple(self.rho_blocks)
        unknown = set(self.rho_blocks) - set(BLOCKS)
        if unknown:
            raise ValueError(f"rho_blocks has unknown blocks {sorted(unknown)}")
        for name in ("rho_factor", "adaptive_beta", "adaptive_gamma", "balance_mu",
                     "balance_tau", "eps_abs", "eps_rel"):
            value = getattr(self, name)
            if not (isinstance(value, int | float) and math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be a finite number > 0, got {value!r}")

    @property
    def qp_family(self) -> Family:
        """The family of the QP step: ``c3plus_qp`` or ``c3_qp``."""
        return Family.C3PLUS_QP if self.variant == Variant.C3PLUS else Family.C3_QP

    @property
    def source(self) -> str:
        """``controller:<variant>/<qp_backend>``: the capture label."""
        return f"controller:{self.variant}/{self.qp_backend}"


# --- small pure pieces (tested one by one) ----------------------------------------------------
def rho_multiplier(options: C3Options, consensus: float, consensus_prev: float | None,
                   dual: float) -> float:
    """Factor applied to the scheduled blocks after an iteration with residuals ``r``, ``s``.

    * geometric: ``factor``;
    * adaptive: ``beta`` if ``r_i >= gamma r_{i-1}`` else 1 (1 without ``r_{i-1}``);
    * residual balancing: ``tau`` if ``r > mu s``, ``1/tau`` if ``s > mu r``, else 1.
    """
    if options.rho_schedule == "geometric":
        return float(options.rho_factor)
    if options.rho_schedule == "adaptive":
        if consensus_prev is None:
            return 1.0
        return float(options.adaptive_beta) if consensus >= options.adaptive_gamma * \
            consensus_prev else 1.0
    if consensus > options.balance_mu * dual:
        return float(options.balance_tau)
    if dual > options.balance_mu * consensus:
        return 1.0 / float(options.balance_tau)
    return 1.0


def next_rho(options: C3Options, rho: Mapping[str, float], consensus: float,
             consensus_prev: float | None, dual: float) -> dict[str, float]:
    """``rho_{i+1}``: the blocks in ``options.rho_blocks`` times :func:`rho_multiplier`."""
    factor = rho_multiplier(options, consensus, consensus_prev, dual)
    return {key: float(value) * factor if key in options.rho_blocks else float(value)
            for key, value in rho.items()}


def rescale_dual(w: np.ndarray, layout: HorizonLayout, rho_old: Mapping[str, float],
                 rho_new: Mapping[str, float]) -> np.ndarray:
    """``w * G_old / G_new`` blockwise (keeps ``y = 2 G w``); ``w`` is (..., T, step size)."""
    ratio = families.weight_vector(layout, rho_old) / families.weight_vector(layout, rho_new)
    rescaled: np.ndarray = np.asarray(w) * ratio
    return rescaled


def dual_update(w: np.ndarray, z_steps: np.ndarray, delta: np.ndarray) -> np.ndarray:
    """Scaled dual ascent ``w + z - delta`` (all (..., T, step size))."""
    updated: np.ndarray = np.asarray(w) + np.asarray(z_steps) - np.asarray(delta)
    return updated


def shift_warm_start(delta: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Shift ``delta`` and ``w`` one step forward in time: drop step 0, repeat the last.

    Arrays are (..., T, step size); ``out[..., k, :] = in[..., k + 1, :]`` for ``k < T - 1``
    and ``out[..., T - 1, :] = in[..., T - 1, :]``.
    """
    out = []
    for array in (np.asarray(delta, dtype=float), np.asarray(w, dtype=float)):
        shifted = array.copy()
        shifted[..., :-1, :] = array[..., 1:, :]
        out.append(shifted)
    return out[0], out[1]


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


def _mpcc_vector(full_steps: np.ndarray, x_terminal: np.ndarray) -> np.ndarray:
    return np.concatenate([np.asarray(full_steps).ravel(), np.asarray(x_terminal)])


def cold_start(lcs: LCS, x0: np.ndarray, horizon: int, variant: str
               ) -> tuple[np.ndarray, np.ndarray]:
    """``delta_k = (x0, 0, 0, 0)``, ``w = 0`` (T x step size of the QP layout)."""
    layout = qp_layout(lcs, horizon, variant)
    delta = np.zeros((horizon, layout.step_size))
    delta[:, layout.index(0, "x")] = np.asarray(x0, dtype=float)
    return delta, np.zeros_like(delta)


# --- records ----------------------------------------------------------------------------------
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
    ||2 G (delta_new - delta_old)||_2`` (module docstring; weighted over robust samples);
    ``consensus_residual_inf`` the infinity norm (worst sample); ``complementarity_delta`` /
    ``complementarity_z`` the natural-map violation ``max |min(lam, eta)|`` of
    :func:`solvers.residuals.complementarity_violation` on the mpcc instance (``eta`` of a C3
    ``z`` is its LCS gap); ``cost_z`` and ``cost_delta`` the MPC cost ``J`` (``delta`` closed
    with ``z``'s ``x_T``; robust: weighted over samples); ``rho_*`` the weights the
    iteration's QP used; times in seconds; ``cond_kkt`` is ``nan`` unless recorded;
    ``qp_found`` the backend's own claim; ``failed`` (QP or projection failed: the fallback)
    and ``non_finite`` (a non-finite answer caused it); ``message`` the backend's status or
    the failure reason.
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
class C3Solution:
    """Outcome of one control step.

    Attributes
    ----------
    u
        Input to apply (clipped to the force limit); the last safe input when ``ok`` is false.
    u_raw
        The unclipped ``u_0`` of the chosen iterate (``None`` when failed).
    ok
        Every iteration's QP and projection succeeded with finite values.
    status
        Why it stopped.
    iterations
        Completed ADMM iterations.
    delta, w
        Final projection iterate and scaled dual, (S, T, step size) in the QP layout (S = 1
        for the plain controller; see :attr:`delta0`).
    z_steps, z_terminal
        Last QP solution: steps (S, T, step size) and terminal states (S, nx).
    rho
        Weights of the last iteration's QP.
    weights
        Sample weights (``[1.0]`` for the plain controller).
    layout
        The QP layout of one sample.
    trace, iterates
        Per-iteration records.
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
    variant: str
    trace: C3Trace
    iterates: list[C3Iterate]

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


# --- the (possibly stacked) QP model ----------------------------------------------------------
class _Horizon:
    """The QP step's data for S >= 1 samples sharing the inputs.

    Variable order of the stacked QP: sample 0's whole ``consensus_qp`` vector, then for each
    further sample its variables without ``u`` (sample ``j``'s ``u_k`` is sample 0's). The
    stacked objective is ``sum_j p_j QP_j`` with ``QP_j`` sample ``j``'s ``consensus_qp``.
    """

    def __init__(self, lcs_samples: Sequence[LCS], weights: np.ndarray, mpc: MPC,
                 x0: np.ndarray, options: C3Options) -> None:
        self.samples = list(lcs_samples)
        self.weights = weights
        self.mpc = mpc
        self.x0 = np.asarray(x0, dtype=float)
        self.options = options
        first = self.samples[0]
        for lcs in self.samples[1:]:
            if (lcs.nx, lcs.nlam, lcs.nu) != (first.nx, first.nlam, first.nu):
                raise ValueError("all LCS samples must have the same dimensions")
        self.layout = qp_layout(first, mpc.horizon, options.variant)
        self.full = full_layout(first, mpc.horizon)
        self.mpccs = [families.mpcc(f"c3-mpcc-{j}", lcs, mpc, self.x0)
                      for j, lcs in enumerate(self.samples)]
        steps = self.layout.horizon * self.layout.step_size
        self.n_qp = self.layout.size
        u_positions = np.concatenate([np.arange(self.layout.index(k, "u").start,
                                                self.layout.index(k, "u").stop)
                                      for k in range(self.layout.horizon)])
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
        self.steps = steps

    @property
    def n_samples(self) -> int:
        return len(self.samples)

    def weight_vectors(self, rho: Mapping[str, float]) -> np.ndarray:
        """``diag G`` of the QP's blocks: (step size,)."""
        return families.weight_vector(self.layout, rho)

    def qp_rho(self, rho: Mapping[str, float]) -> dict[str, float]:
        """``rho`` restricted to the QP's blocks."""
        return {key: float(rho[key]) for key in self.layout.block_sizes()}

    def build(self, rho: Mapping[str, float], delta: np.ndarray, w: np.ndarray,
              name: str) -> Problem:
        """The QP step: ``consensus_qp`` itself for one sample, else the stacked QP
        ``sum_j p_j [J(z_j) + ||z_j - (delta_j - w_j)||^2_G]`` with shared ``u``."""
        family = self.options.qp_family
        weights = self.qp_rho(rho)
        qps = [families.consensus_qp(family, f"{name}-s{j}" if self.n_samples > 1 else name,
                                     lcs, self.mpc, self.x0, weights, delta[j], w[j],
                                     input_bounds=self.options.input_bounds)
               for j, lcs in enumerate(self.samples)]
        if self.n_samples == 1:
            return qps[0]
        n = self.size
        P = np.zeros((n, n))
        q = np.zeros(n)
        offset = 0.0
        A_rows: list[np.ndarray] = []
        b_rows: list[np.ndarray] = []
        lb = np.full(n, -np.inf) if self.options.input_bounds else None
        ub = np.full(n, np.inf) if self.options.input_bounds else None
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
            if lb is not None and ub is not None and qp.lb is not None and qp.ub is not None:
                lb[idx] = np.maximum(lb[idx], qp.lb)
                ub[idx] = np.minimum(ub[idx], qp.ub)
        P = 0.5 * (P + P.T)
        return Problem(name=name, family=family, P=P, q=q, A=np.vstack(A_rows),
                       b=np.concatenate(b_rows), lb=lb, ub=ub, objective_offset=offset,
                       lcs=self.samples[0], data={"x0": self.x0},
                       meta={"robust_samples": self.n_samples,
                             "sample_weights": [float(p) for p in self.weights],
                             "rho": weights, "sample_layout": self.layout.to_json(),
                             "input_bounds": self.options.input_bounds})

    def norm(self, values: np.ndarray) -> float:
        """Weighted norm over samples ``sqrt(sum_j p_j ||v_j||_2^2)`` of (S, ...) arrays."""
        squares = np.sum(np.reshape(values, (self.n_samples, -1)) ** 2, axis=1)
        return float(np.sqrt(np.dot(self.weights, squares)))

    def split(self, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Per-sample steps (S, T, step size) and terminal states (S, nx) of a QP solution."""
        zs = [np.asarray(y)[idx] for idx in self.index]
        steps = np.stack([z[:self.steps].reshape(self.layout.horizon, self.layout.step_size)
                          for z in zs])
        terminal = np.stack([z[self.steps:] for z in zs])
        return steps, terminal

    def full_vector(self, j: int, steps: np.ndarray, terminal: np.ndarray) -> np.ndarray:
        """Sample ``j``'s trajectory as an mpcc vector (``eta`` = LCS gap for C3)."""
        return _mpcc_vector(to_full_steps(steps, self.samples[j], self.layout), terminal)

    def measures(self, steps: np.ndarray, terminal: np.ndarray) -> tuple[float, float]:
        """Weighted cost ``sum_j p_j J_j`` and worst complementarity violation."""
        cost, violation = 0.0, 0.0
        for j, problem in enumerate(self.mpccs):
            vector = self.full_vector(j, steps[j], terminal[j])
            cost += float(self.weights[j]) * problem.objective(vector)
            violation = max(violation, complementarity_violation(problem, vector))
        return cost, violation


# --- projection -------------------------------------------------------------------------------
def project_step_c3plus(v: np.ndarray, layout: HorizonLayout, rho: Mapping[str, float]
                        ) -> np.ndarray:
    """C3+'s projection of steps ``v`` (..., step size): ``x, u`` copied, pairs in closed form
    with weights ``rho_lam``, ``rho_eta`` (:func:`solvers.projection.c3plus_projection`)."""
    from c3bench.solvers.projection import c3plus_projection

    out = np.array(v, dtype=float, copy=True)
    lam_s, eta_s = layout.index(0, "lam"), layout.index(0, "eta")
    lam, eta = c3plus_projection(out[..., lam_s], out[..., eta_s], rho[Block.LAM],
                                 rho[Block.ETA])
    out[..., lam_s] = lam
    out[..., eta_s] = eta
    return out


def project_step_c3(v: np.ndarray, lcs: LCS, rho: Mapping[str, float], backend: Backend,
                    settings: Settings, name: str = "c3-projection") -> np.ndarray:
    """C3's projection of one step ``v = (x, lam, u)`` by an MIQP backend.

    ``min (x - v_x)^T rho_x (x - v_x) + rho_lam ||lam - v_lam||^2 + rho_u ||u - v_u||^2`` s.t.
    ``0 <= lam perp E x + F lam + H u + c >= 0`` (:func:`problems.families.projection`,
    variant ``c3``); returns ``(x, lam, u)``. Raises ``RuntimeError`` when the backend finds
    no finite point.
    """
    layout1 = HorizonLayout(lcs.nx, lcs.nlam, lcs.nu, lcs.nlam, 1)
    v_full = to_full_steps(np.asarray(v, dtype=float)[None, :], lcs,
                           HorizonLayout(lcs.nx, lcs.nlam, lcs.nu, 0, 1))[0]
    U = families.weight_vector(layout1, {**{k: float(rho[k]) for k in (Block.X, Block.LAM,
                                                                         Block.U)},
                                         Block.ETA: 0.0})
    problem = families.projection(name, lcs, v_full, U, Variant.C3)
    result = backend.solve(problem, settings)
    x = result.x
    if x is None or np.shape(x) != (problem.n,) or not np.all(np.isfinite(x)):
        raise RuntimeError(f"projection backend {backend.name} failed: {result.status}")
    keep = np.ones(layout1.step_size, dtype=bool)
    keep[layout1.index(0, "eta")] = False
    return np.asarray(x, dtype=float)[keep]


# --- the ADMM loop ----------------------------------------------------------------------------
def _finite(*arrays: np.ndarray | None) -> bool:
    return all(a is not None and bool(np.all(np.isfinite(a))) for a in arrays)


def _kkt_condition(problem: Problem) -> float:
    n, m = problem.n, problem.n_eq
    K = np.zeros((n + m, n + m))
    K[:n, :n] = problem.P
    if m and problem.A is not None:
        K[:n, n:] = problem.A.T
        K[n:, :n] = problem.A
    return float(np.linalg.cond(K))


def _backend(options: C3Options, name: str) -> Backend:
    """``options.backends[name]`` when given, else the registry's backend (``KeyError``)."""
    return options.backends.get(name) or registry.get(name)


def _solve_qp(backend: Backend, problem: Problem, settings: Settings
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
    except IsolationFailed:  # no solver process could start: not the backend's failure
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


def _admm(model: _Horizon, options: C3Options, delta_init: np.ndarray, w_init: np.ndarray,
          fallback_input: np.ndarray) -> C3Solution:
    """Run the ADMM (module docstring); never raises for a solver's misbehaviour."""
    layout = model.layout
    S = model.n_samples
    trace = C3Trace()
    iterates: list[C3Iterate] = []
    rho = dict(options.rho0)
    delta = np.array(delta_init, dtype=float)
    w = np.array(w_init, dtype=float)
    z_steps: np.ndarray | None = None
    z_terminal: np.ndarray | None = None
    rho_used = dict(rho)
    consensus_prev: float | None = None
    status = f"{options.admm_iterations} iterations"
    ok = True
    completed = 0
    qp_backend: Backend | None = None
    projection_backend: Backend | None = None
    try:
        qp_backend = _backend(options, options.qp_backend)
        if options.variant == Variant.C3:
            projection_backend = _backend(options, options.projection_backend)
    except KeyError as error:
        status = str(error.args[0])
        ok = False
    for i in range(options.admm_iterations if ok else 0):
        started = time.perf_counter()
        rho_used = dict(rho)
        # 1. QP step
        build_start = time.perf_counter()
        try:
            problem = model.build(rho, delta, w, f"c3-qp-i{i:02d}")
        except ValueError as error:
            trace.append(i, rho, failed=True, message=f"QP build failed: {error}",
                          iteration_time=time.perf_counter() - started)
            status, ok = f"QP build failed at iteration {i}: {error}", False
            break
        setup_time = time.perf_counter() - build_start
        qp_start = time.perf_counter()
        assert qp_backend is not None
        assert options.qp_settings is not None
        y, result, reason = _solve_qp(qp_backend, problem, options.qp_settings)
        qp_time = time.perf_counter() - qp_start
        cond = _kkt_condition(problem) if options.record_conditioning else math.nan
        if y is None:
            trace.append(i, rho, failed=True, non_finite="non-finite" in reason,
                          message=reason, qp_setup_time=setup_time, qp_time=qp_time,
                          cond_kkt=cond, iteration_time=time.perf_counter() - started)
            status, ok = f"QP failed at iteration {i}: {reason}", False
            break
        steps_i, terminal_i = model.split(y)
        # 2. projection of z + w
        v = steps_i + w
        projection_start = time.perf_counter()
        try:
            if options.variant == Variant.C3PLUS:
                new_delta = project_step_c3plus(v, layout, rho)
            else:
                assert projection_backend is not None
                new_delta = np.stack([np.stack([
                    project_step_c3(v[j, k], model.samples[j], rho,
                                    projection_backend, options.projection_settings,
                                    f"c3-projection-i{i:02d}-s{j}-k{k}")
                    for k in range(layout.horizon)]) for j in range(S)])
        except Exception as error:  # noqa: BLE001 - a failed projection is recorded
            trace.append(i, rho, failed=True, message=f"projection failed: {error}",
                          qp_setup_time=setup_time, qp_time=qp_time, cond_kkt=cond,
                          projection_time=time.perf_counter() - projection_start,
                          qp_found=bool(result.found) if result else False,
                          iteration_time=time.perf_counter() - started)
            status, ok = f"projection failed at iteration {i}: {error}", False
            break
        projection_time = time.perf_counter() - projection_start
        if not _finite(new_delta):
            trace.append(i, rho, failed=True, non_finite=True,
                          message="non-finite projection", qp_setup_time=setup_time,
                          qp_time=qp_time, cond_kkt=cond, projection_time=projection_time,
                          iteration_time=time.perf_counter() - started)
            status, ok = f"non-finite projection at iteration {i}", False
            break
        # 3. dual update, 4. residuals
        new_w = dual_update(w, steps_i, new_delta)
        G = model.weight_vectors(rho)
        difference = steps_i - new_delta
        consensus = model.norm(difference)
        dual = model.norm(2.0 * G * (new_delta - delta))
        cost_z, comp_z = model.measures(steps_i, terminal_i)
        cost_delta, comp_delta = model.measures(new_delta, terminal_i)
        if options.keep_iterates:
            iterates.append(C3Iterate(i, dict(rho), delta.copy(), w.copy(), steps_i.copy(),
                                      terminal_i.copy()))
        trace.append(i, rho, consensus_residual=consensus,
                      consensus_residual_inf=float(np.max(np.abs(difference), initial=0.0)),
                      dual_residual=dual, complementarity_delta=comp_delta,
                      complementarity_z=comp_z, cost_z=cost_z, cost_delta=cost_delta,
                      qp_setup_time=setup_time, qp_time=qp_time,
                      projection_time=projection_time, cond_kkt=cond,
                      qp_found=bool(result.found) if result else False,
                      message=result.status if result else "",
                      iteration_time=time.perf_counter() - started)
        delta, w, z_steps, z_terminal = new_delta, new_w, steps_i, terminal_i
        completed = i + 1
        if options.stopping == "residual":
            p = difference[0].size
            eps_pri = math.sqrt(p) * options.eps_abs + options.eps_rel * max(
                model.norm(steps_i), model.norm(new_delta))
            eps_dual = math.sqrt(p) * options.eps_abs + options.eps_rel * model.norm(
                2.0 * G * new_w)
            if consensus <= eps_pri and dual <= eps_dual:
                status = f"converged in {completed} iterations (r={consensus:.3g}, " \
                         f"s={dual:.3g})"
                break
        # 5. rho update (and scaled-dual rescaling)
        if i + 1 < options.admm_iterations:
            updated = next_rho(options, rho, consensus, consensus_prev, dual)
            if options.rescale_dual and updated != rho:
                w = rescale_dual(w, layout, rho, updated)
            rho = updated
        consensus_prev = consensus
    else:
        if ok and options.stopping == "residual":
            status = f"iteration limit {options.admm_iterations} reached"
    u_raw: np.ndarray | None = None
    u = np.asarray(fallback_input, dtype=float).copy()
    if ok and z_steps is not None:
        u_slice = layout.index(0, "u")
        if options.output == "delta":
            u_raw = np.einsum("j,ji->i", model.weights, delta[:, 0, u_slice])
        else:
            u_raw = z_steps[0, 0, u_slice].copy()
        if _finite(u_raw):
            limit = float(model.mpc.force_limit)
            u = np.clip(u_raw, -limit, limit)
        else:
            ok, status, u_raw = False, "non-finite input", None
    return C3Solution(u=u, u_raw=u_raw, ok=ok, status=status, iterations=completed,
                      delta=delta, w=w, z_steps=z_steps, z_terminal=z_terminal,
                      rho=rho_used, weights=model.weights.copy(), layout=layout,
                      variant=options.variant, trace=trace, iterates=iterates)


def _initial(lcs: LCS, x0: np.ndarray, horizon: int, options: C3Options, samples: int,
             delta: np.ndarray | None, w: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    cold_delta, cold_w = cold_start(lcs, x0, horizon, options.variant)
    shape = (samples, *cold_delta.shape)
    out = []
    for name, given, cold in (("delta", delta, cold_delta), ("w", w, cold_w)):
        if given is None:
            out.append(np.broadcast_to(cold, shape).copy())
            continue
        array = np.asarray(given, dtype=float)
        if array.shape == cold.shape:
            array = np.broadcast_to(array, shape)
        if array.shape != shape:
            raise ValueError(f"{name} must have shape {cold.shape} or {shape}, got "
                             f"{array.shape}")
        if not np.all(np.isfinite(array)):
            raise ValueError(f"{name} has non-finite entries")
        out.append(np.array(array, dtype=float))
    return out[0], out[1]


def solve_c3(lcs: LCS, mpc: MPC, x0: np.ndarray, options: C3Options | None = None,
             delta: np.ndarray | None = None, w: np.ndarray | None = None,
             fallback_input: np.ndarray | None = None) -> C3Solution:
    """One control step of C3 / C3+ from state ``x0``.

    Parameters
    ----------
    lcs, mpc
        Model and cost.
    x0
        Measured state.
    options
        Controller options (defaults: the reference study's C3+).
    delta, w
        Initial projection iterate and scaled dual (T x step size of the QP layout); a cold
        start (:func:`cold_start`) when ``None``.
    fallback_input
        Returned (with ``ok=False``) when the step fails; zero when ``None``.
    """
    options = options or C3Options()
    x0 = np.asarray(x0, dtype=float)
    fallback = np.zeros(lcs.nu) if fallback_input is None else np.asarray(fallback_input,
                                                                          dtype=float)
    delta_init, w_init = _initial(lcs, x0 if np.all(np.isfinite(x0)) else np.zeros(lcs.nx),
                                  mpc.horizon, options, 1, delta, w)
    try:
        model = _Horizon([lcs], np.ones(1), mpc, x0, options)
    except ValueError as error:
        return _failed_before_start(lcs, mpc, options, delta_init, w_init, fallback,
                                    f"invalid input: {error}")
    return _admm(model, options, delta_init, w_init, fallback)


def _failed_before_start(lcs: LCS, mpc: MPC, options: C3Options, delta: np.ndarray,
                         w: np.ndarray, fallback: np.ndarray, status: str) -> C3Solution:
    return C3Solution(u=np.asarray(fallback, dtype=float).copy(), u_raw=None, ok=False,
                      status=status, iterations=0, delta=delta, w=w, z_steps=None,
                      z_terminal=None, rho=dict(options.rho0),
                      weights=np.ones(delta.shape[0]) / delta.shape[0],
                      layout=qp_layout(lcs, mpc.horizon, options.variant),
                      variant=options.variant, trace=C3Trace(), iterates=[])


def normalise_weights(weights: Sequence[float] | np.ndarray, samples: int) -> np.ndarray:
    """Finite, non-negative weights with a positive sum, scaled to sum 1."""
    array = np.asarray(weights, dtype=float)
    if array.shape != (samples,):
        raise ValueError(f"weights must have shape ({samples},), got {array.shape}")
    if not np.all(np.isfinite(array)) or np.any(array < 0) or array.sum() <= 0:
        raise ValueError("weights must be finite, >= 0 and not all zero")
    normalised: np.ndarray = array / array.sum()
    return normalised


def solve_robust(lcs_samples: Sequence[LCS], weights: Sequence[float] | np.ndarray | None,
                 mpc: MPC, x0: np.ndarray, options: C3Options | None = None,
                 delta: np.ndarray | None = None, w: np.ndarray | None = None,
                 fallback_input: np.ndarray | None = None) -> C3Solution:
    """The robust controller: ``n`` LCS samples with shared inputs (module docstring).

    Parameters
    ----------
    lcs_samples
        The samples' LCS (built by the caller, e.g. with ``l ~ U[0.27, 0.33]``), all
        linearised at ``x0``.
    weights
        Sample weights (normalised here, floored at ``WEIGHT_FLOOR`` times the largest and
        renormalised); uniform when ``None``.
    mpc, x0, options, fallback_input
        As in :func:`solve_c3`.
    delta, w
        Initial iterates, (S, T, step size) or (T, step size) for all samples alike.

    Returns
    -------
    C3Solution
        ``delta``, ``w``, ``z_steps`` have a leading sample axis; ``u`` is
        ``sum_j p_j delta_j u_0`` (or the shared ``z u_0`` with ``output="z"``).
    """
    options = options or C3Options()
    if len(lcs_samples) < 1:
        raise ValueError("solve_robust needs at least one LCS sample")
    S = len(lcs_samples)
    p = np.full(S, 1.0 / S) if weights is None else normalise_weights(weights, S)
    p = np.maximum(p, WEIGHT_FLOOR * p.max())
    p = p / p.sum()
    first = lcs_samples[0]
    x0 = np.asarray(x0, dtype=float)
    fallback = np.zeros(first.nu) if fallback_input is None else np.asarray(fallback_input,
                                                                            dtype=float)
    delta_init, w_init = _initial(first, x0 if np.all(np.isfinite(x0)) else np.zeros(first.nx),
                                  mpc.horizon, options, S, delta, w)
    try:
        model = _Horizon(lcs_samples, p, mpc, x0, options)
    except ValueError as error:
        return _failed_before_start(first, mpc, options, delta_init, w_init, fallback,
                                    f"invalid input: {error}")
    return _admm(model, options, delta_init, w_init, fallback)


class C3Controller:
    """A C3 / C3+ controller with warm start and a last-safe-input fallback.

    ``step`` (one LCS) and ``step_robust`` (samples) warm-start from the previous successful
    step's shifted ``delta`` and ``w`` (:func:`shift_warm_start`) when the shapes agree; a
    failed step drops the warm start (the next step cold-starts) and returns the last safe
    input.
    """

    def __init__(self, options: C3Options | None = None,
                 initial_input: np.ndarray | None = None) -> None:
        self.options = options or C3Options()
        self.last_safe_input = None if initial_input is None else np.asarray(initial_input,
                                                                             dtype=float)
        self.delta: np.ndarray | None = None
        self.w: np.ndarray | None = None
        self.failures = 0

    def reset(self) -> None:
        """Forget the warm start, the last safe input and the failure count."""
        self.delta = self.w = self.last_safe_input = None
        self.failures = 0

    def _warm(self, samples: int) -> tuple[np.ndarray | None, np.ndarray | None]:
        if self.delta is None or self.w is None or self.delta.shape[0] != samples:
            return None, None
        return shift_warm_start(self.delta, self.w)

    def _record(self, solution: C3Solution) -> C3Solution:
        if solution.ok:
            self.delta, self.w = solution.delta, solution.w
            self.last_safe_input = solution.u.copy()
        else:
            self.delta = self.w = None
            self.failures += 1
        return solution

    def step(self, lcs: LCS, mpc: MPC, x0: np.ndarray) -> C3Solution:
        """One control step with the single model ``lcs``."""
        delta, w = self._warm(1)
        if delta is not None and delta.shape[1:] != cold_start(lcs, x0, mpc.horizon,
                                                             self.options.variant)[0].shape:
            delta = w = None
        return self._record(solve_c3(lcs, mpc, x0, self.options, delta, w,
                                     self.last_safe_input))

    def step_robust(self, lcs_samples: Sequence[LCS], weights: Sequence[float] | None,
                    mpc: MPC, x0: np.ndarray) -> C3Solution:
        """One control step of the robust variant."""
        delta, w = self._warm(len(lcs_samples))
        if delta is not None and delta.shape[1:] != cold_start(
                lcs_samples[0], x0, mpc.horizon, self.options.variant)[0].shape:
            delta = w = None
        return self._record(solve_robust(lcs_samples, weights, mpc, x0, self.options, delta,
                                         w, self.last_safe_input))


# --- LCS rollout and sample scoring -----------------------------------------------------------
def lcp_step(lcs: LCS, x: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """One LCS step with ``lam`` from Lemke: ``(x_next, lam)``, or ``None`` when Lemke fails."""
    solution = lemke(lcs.F, lcs.lcp_offset(x, u))
    if not solution.found or solution.z is None:
        return None
    lam = solution.z
    return lcs.next_state(x, u, lam), lam


def rollout(lcs: LCS, x0: np.ndarray, inputs: np.ndarray
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """Simulate the LCS from ``x0`` under ``inputs`` (T x nu) with Lemke's ``lam``.

    Returns ``(xs (T+1 x nx), lams (T x nlam), etas (T x nlam))``, a point that satisfies the
    dynamics and complementarity of the mpcc exactly (to Lemke's precision), or ``None`` when
    an LCP has no solution found.
    """
    xs = [np.asarray(x0, dtype=float)]
    lams, etas = [], []
    for u in np.asarray(inputs, dtype=float):
        step = lcp_step(lcs, xs[-1], u)
        if step is None:
            return None
        x_next, lam = step
        lams.append(lam)
        etas.append(lcs.gap(xs[-1], u, lam))
        xs.append(x_next)
    return np.array(xs), np.array(lams), np.array(etas)


def rollout_vector(lcs: LCS, mpc: MPC, x0: np.ndarray, inputs: np.ndarray
                   ) -> np.ndarray | None:
    """:func:`rollout` of the inputs clipped to the force limit, as an mpcc vector."""
    layout = full_layout(lcs, mpc.horizon)
    us = np.clip(np.asarray(inputs, dtype=float), -mpc.force_limit, mpc.force_limit)
    simulated = rollout(lcs, x0, us)
    if simulated is None:
        return None
    xs, lams, etas = simulated
    steps = np.zeros((mpc.horizon, layout.step_size))
    steps[:, layout.index(0, "x")] = xs[:-1]
    steps[:, layout.index(0, "lam")] = lams
    steps[:, layout.index(0, "u")] = us
    steps[:, layout.index(0, "eta")] = etas
    return _mpcc_vector(steps, xs[-1])


Observation = tuple[np.ndarray, np.ndarray, np.ndarray]


def lcp_prediction_errors(lcs_samples: Sequence[LCS], observations: Sequence[Observation]
                          ) -> np.ndarray:
    """``e_j = sum_t ||x_next_t - x_hat_j(x_t, u_t)||_2^2`` per sample (``inf`` when Lemke
    fails on one of its LCPs); ``x_hat`` from :func:`lcp_step`."""
    errors = np.zeros(len(lcs_samples))
    for j, lcs in enumerate(lcs_samples):
        for x, u, x_next in observations:
            step = lcp_step(lcs, np.asarray(x, dtype=float), np.asarray(u, dtype=float))
            if step is None:
                errors[j] = math.inf
                break
            errors[j] += float(np.sum((np.asarray(x_next, dtype=float) - step[0]) ** 2))
    return errors


def lcp_prediction_weights(lcs_samples: Sequence[LCS], observations: Sequence[Observation],
                           temperature: float | None = None) -> np.ndarray:
    """Sample weights from one-step LCP prediction errors (seed 000, section 3.3).

    ``p_j = exp(-(e_j - min_i e_i) / temperature) / sum`` with ``e_j`` from
    :func:`lcp_prediction_errors`. ``temperature=None`` takes the median finite error (floored
    at 1e-12): a sample with a median error gets ``e^-1`` of the best sample's weight, whatever
    the units. A sample whose prediction failed gets weight 0; with no observations, or when
    every prediction failed, the weights are uniform (nothing to judge by).
    """
    S = len(lcs_samples)
    if S == 0:
        raise ValueError("need at least one sample")
    if len(observations) == 0:
        return np.full(S, 1.0 / S)
    errors = lcp_prediction_errors(lcs_samples, observations)
    finite = np.isfinite(errors)
    if not np.any(finite):
        return np.full(S, 1.0 / S)
    if temperature is None:
        temperature = max(float(np.median(errors[finite])), 1e-12)
    if not (math.isfinite(temperature) and temperature > 0):
        raise ValueError(f"temperature must be a finite number > 0, got {temperature!r}")
    logits = np.where(finite, -(errors - errors[finite].min()) / temperature, -np.inf)
    weights = np.exp(logits)
    normalised: np.ndarray = weights / weights.sum()
    return normalised


# --- capture for the suites -------------------------------------------------------------------
def iterate_to_capture(iterate: C3Iterate, lcs: LCS, layout: HorizonLayout, source: str,
                       sample: int = 0) -> CapturedIterate:
    """One iteration in the suites' C3+ layout.

    A C3 run's ``eta`` columns are filled from the LCS: ``delta_eta = E x + F lam + H u + c``
    of ``delta``, ``w_eta = E w_x + F w_lam + H w_u`` (no ``c``: ``w`` is a difference, so
    ``(delta - w)`` keeps ``eta`` equal to its gap) and ``v_eta`` the gap of ``v = z + w``.
    """
    delta = to_full_steps(iterate.delta[sample], lcs, layout)
    w = to_full_steps(iterate.w[sample], lcs, layout, homogeneous=True)
    v = to_full_steps(iterate.projection_v[sample], lcs, layout)
    return CapturedIterate(iteration=iterate.iteration,
                           rho={k: float(iterate.rho[k]) for k in BLOCKS},
                           delta=delta, w=w, projection_v=v, source=source)


def controller_capture(options: C3Options | None = None) -> Capture:
    """A capture function for :func:`problems.suites.generate_suite` that runs the controller.

    At each sampled state it runs :func:`solve_c3` from a cold start on the context's LCS and
    MPC, with a fixed iteration count covering every iteration the suite asks for (at least
    ``options.admm_iterations``), and yields every completed iteration as a
    :class:`c3bench.problems.capture.CapturedIterate` (C3+ layout, :func:`iterate_to_capture`) with
    ``source = "controller:<variant>/<qp_backend>"``. Deterministic when the backends are.
    Iterations after a QP failure do not exist and are not yielded.
    """
    base = options or C3Options()

    def capture(context: CaptureContext) -> list[CapturedIterate]:
        spec = context.spec
        needed = 1 + max((*spec.admm_iterations, *spec.projection_iterations), default=0)
        run = replace(base, admm_iterations=max(base.admm_iterations, needed),
                      stopping="fixed", keep_iterates=True)
        solution = solve_c3(context.lcs, context.mpc, context.x0, run,
                            fallback_input=context.u_prev)
        return [iterate_to_capture(it, context.lcs, solution.layout, run.source)
                for it in solution.iterates]

    return capture

