"""The controller's options: one dataclass for every kernel of the consensus ADMM.

The weights follow the C3 paper (Aydinoglu and Posa, "Real-time multi-contact model predictive
control via ADMM", ICRA 2022) and its reference implementation: ``Q, R, Q_f`` (the MPC cost, in
:class:`c3bench.problems.mpc.MPC`), ``G`` (the consensus weight of the QP step, here
``diag(rho_x, rho_lam, rho_u, rho_eta)`` per step, scaled by the rho schedule) and ``U`` (the
weight of the projection step). ``projection_weights=None`` projects in ``G`` (the reference
study's C3+, where the two coincide); a mapping gives ``U`` by block, constant over the
iterations as in the paper, and is used by both C3's projection and C3+'s closed form.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from enum import StrEnum
from typing import Any

from c3bench.problems.families import check_rho
from c3bench.problems.names import (
    BLOCKS,
    REFERENCE_ADMM_ITERATIONS,
    REFERENCE_RHO0,
    REFERENCE_RHO_BLOCKS,
    REFERENCE_RHO_FACTOR,
    Family,
    Profile,
    Variant,
)
from c3bench.solvers.base import Backend, Settings, settings_for


class RhoScheduleName(StrEnum):
    """How the consensus weight changes between iterations (:mod:`.schedules`)."""

    GEOMETRIC = "geometric"
    ADAPTIVE = "adaptive"
    RESIDUAL_BALANCING = "residual_balancing"


class Stopping(StrEnum):
    """``fixed``: run ``admm_iterations``; ``residual``: stop when Boyd's residuals are small."""

    FIXED = "fixed"
    RESIDUAL = "residual"


class Output(StrEnum):
    """Which iterate's ``u_0`` is applied: the projected ``delta`` or the QP's ``z``."""

    DELTA = "delta"
    Z = "z"


class DualWarmStart(StrEnum):
    """What the scaled dual ``w`` of a warm-started control step starts from.

    ``zero`` (default): ``w = 0`` at every control step, only ``delta`` is carried (the C3
    reference implementation's ``Solve``: ``w`` and ``G`` restart each call). ``scaled``: the
    previous step's ``w`` shifted one step, kept scaled as it is. Because rho restarts from
    ``rho0`` each step, a kept scaled dual means an unscaled multiplier ``2 G w`` changed by
    ``rho0 / rho_final``: harmless when the schedule ended above ``rho0`` (geometric), but it
    compounds from step to step when it ended below (residual balancing: measured plan errors
    of 1e51 within a second of closed loop on the cube).
    """

    ZERO = "zero"
    SCALED = "scaled"


ENUMERATION = "enumeration"
"""``projection_backend`` value of C3's exact projection by contact-mode enumeration."""
VARIANTS: tuple[Variant, ...] = (Variant.C3PLUS, Variant.C3)
RHO_SCHEDULES: tuple[str, ...] = tuple(RhoScheduleName)
STOPPING_RULES: tuple[str, ...] = tuple(Stopping)
DUAL_WARM_STARTS: tuple[str, ...] = tuple(DualWarmStart)
OUTPUTS: tuple[str, ...] = tuple(Output)
WEIGHT_FLOOR = 1e-6
"""Smallest sample weight of the robust controller, relative to the largest."""


def _settings(name: str, value: Any) -> Settings:
    """``value`` as :class:`Settings`: given, or the named profile's (``ValueError`` naming
    the option otherwise)."""
    if isinstance(value, Settings):
        return value
    if isinstance(value, str):
        try:
            return settings_for(value)
        except ValueError as error:
            raise ValueError(f"{name}: {error}") from error
    raise ValueError(f"{name} must be a Settings or a profile name, got {value!r}")


def check_weights(weights: Mapping[str, float], name: str,
                  positive: tuple[str, ...] | None = None) -> dict[str, float]:
    """Weights of every block (:func:`c3bench.problems.families.check_rho`: finite and
    ``>= 0``, ``> 0`` for the blocks in ``positive``, by default those not in
    :data:`~c3bench.problems.families.ZERO_WEIGHT_BLOCKS`, where the maths allows no zero)
    and no other block.
    """
    out = check_rho(weights, BLOCKS, name, positive)
    unknown = set(weights) - set(BLOCKS)
    if unknown:
        raise ValueError(f"{name} has unknown blocks {sorted(unknown)}")
    return out


@dataclass
class C3Options:
    """Everything that configures the controller (every kernel reads the same options).

    Attributes
    ----------
    variant
        ``"c3plus"`` (QP over ``(x, lam, u, eta)``, closed-form projection) or ``"c3"`` (QP
        over ``(x, lam, u)``, per-step MIQP projection).
    qp_backend, qp_settings
        Registry name and settings of the reference kernel's QP step (a :class:`Settings`
        or a profile name such as ``"high_accuracy"``). ``qp_settings=None`` means the default
        profile, and for ``equilibrated_kkt`` also ``options={"diagnostics": False}``.
    projection_backend, projection_settings
        C3's projection: a registry MIQP backend name, or ``"enumeration"`` (exact, by
        enumerating the contact modes of each step; :mod:`c3bench.solvers.projection_enum`).
    admm_iterations
        Iterations (the maximum with ``stopping="residual"``); seed: 10.
    rho0
        Initial consensus weights ``G`` by block ``x, lam, u, eta``; seed: 1, 50, 0.1, 50.
        ``x`` and ``u`` may be 0 (:func:`check_weights`).
    projection_weights
        ``U`` by block (constant); ``None`` projects in ``G`` (module docstring).
    rho_schedule, rho_blocks, rho_factor, adaptive_beta, adaptive_gamma, balance_mu, balance_tau
        The rho schedule (:mod:`c3bench.solvers.admm.schedules`) and the blocks it scales.
    rescale_dual
        Rescale ``w`` by ``rho_old / rho_new`` when a weight changes (keeps ``y = 2 G w``).
    stopping, eps_abs, eps_rel
        Stopping rule (:class:`Stopping`) and the tolerances of the residual rule.
    input_bounds
        Put ``|u_k| <= force_limit`` into the QP even without ``mpc.limits``.
    use_limits
        Enforce ``mpc.limits`` (input and state boxes) where the method puts them: bounds of
        the reference kernel's QP step, a box projection in the fast kernels.
    warm_start
        The controller starts each control step from the previous one's shifted ``delta``
        (``False``: every step cold-starts).
    warm_dual
        What ``w`` starts from in a warm-started step (:class:`DualWarmStart`): ``zero``
        (default) or the previous step's shifted ``w``.
    output
        ``delta`` (default) or ``z`` (:class:`Output`).
    record_conditioning, keep_iterates
        Reference kernel only: ``cond_2`` of the KKT matrix each iteration; keep every
        iteration's ``(rho, delta, w, z)``.
    backends
        Backend instances used instead of the registry's for these names.
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
    projection_weights: Mapping[str, float] | None = None
    rho_schedule: str = RhoScheduleName.GEOMETRIC
    rho_blocks: tuple[str, ...] = REFERENCE_RHO_BLOCKS
    rho_factor: float = REFERENCE_RHO_FACTOR
    adaptive_beta: float = 2.0
    adaptive_gamma: float = 0.25
    balance_mu: float = 10.0
    balance_tau: float = 2.0
    rescale_dual: bool = True
    stopping: str = Stopping.FIXED
    eps_abs: float = 1e-4
    eps_rel: float = 1e-3
    input_bounds: bool = False
    use_limits: bool = True
    warm_start: bool = True
    warm_dual: str = DualWarmStart.ZERO
    output: str = Output.DELTA
    record_conditioning: bool = False
    keep_iterates: bool = True
    backends: Mapping[str, Backend] = field(default_factory=dict)

    def __post_init__(self) -> None:
        for name, value, allowed in (("variant", self.variant, VARIANTS),
                                     ("rho_schedule", self.rho_schedule, RHO_SCHEDULES),
                                     ("stopping", self.stopping, STOPPING_RULES),
                                     ("output", self.output, OUTPUTS),
                                     ("warm_dual", self.warm_dual, DUAL_WARM_STARTS)):
            if value not in allowed:
                raise ValueError(f"{name} must be one of {allowed}, got {value!r}")
        if not isinstance(self.admm_iterations, int) or self.admm_iterations < 1:
            raise ValueError(f"admm_iterations must be an integer >= 1, got "
                             f"{self.admm_iterations!r}")
        if self.qp_settings is None:
            self.qp_settings = Settings(options={"diagnostics": False}) \
                if self.qp_backend == "equilibrated_kkt" else Settings()
        self.qp_settings = _settings("qp_settings", self.qp_settings)
        self.projection_settings = _settings("projection_settings", self.projection_settings)
        self.variant = Variant(self.variant)
        self.rho_schedule = RhoScheduleName(self.rho_schedule)
        self.stopping = Stopping(self.stopping)
        self.output = Output(self.output)
        self.rho0 = check_weights(self.rho0, "rho0")
        if self.projection_weights is not None:
            self.projection_weights = check_weights(self.projection_weights,
                                                    "projection_weights", positive=())
        self.rho_blocks = tuple(self.rho_blocks)
        unknown = set(self.rho_blocks) - set(BLOCKS)
        if unknown:
            raise ValueError(f"rho_blocks has unknown blocks {sorted(unknown)}")
        for name in ("rho_factor", "adaptive_beta", "adaptive_gamma", "balance_mu",
                     "balance_tau", "eps_abs", "eps_rel"):
            value = getattr(self, name)
            if not (isinstance(value, int | float) and math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be a finite number > 0, got {value!r}")

    def check_batched_c3plus(self, kernel: str) -> None:
        """``ValueError`` unless a batched C3+ kernel (numpy Riccati, compiled, JAX) can run
        these options: variant ``c3plus`` and no input bounds in the QP step (their QP step is
        an unconstrained LQ problem; the limits of ``mpc.limits`` go into their projection)."""
        if self.variant != Variant.C3PLUS:
            raise ValueError(f"{kernel} runs the c3plus variant only")
        if self.input_bounds:
            raise ValueError(f"{kernel} does not take input bounds in the QP step (the box "
                             f"limits of mpc.limits go into its projection)")

    @property
    def qp_family(self) -> Family:
        """The family of the QP step: ``c3plus_qp`` or ``c3_qp``."""
        return Family.C3PLUS_QP if self.variant == Variant.C3PLUS else Family.C3_QP

    @property
    def source(self) -> str:
        """``controller:<variant>/<qp_backend>``: the capture label."""
        return f"controller:{self.variant}/{self.qp_backend}"
