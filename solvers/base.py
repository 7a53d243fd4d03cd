"""The solver contract: settings profiles, ``Result`` and the ``Backend`` base class.

Conventions follow qpsolvers: for ``min 1/2 x^T P x + q^T x`` s.t. ``A x = b``, ``G x <= h``,
``lb <= x <= ub`` a solution carries the primal ``x``, the equality duals ``y``, the inequality
duals ``z >= 0`` and the box duals ``z_box`` (negative where a lower bound is active, positive
where an upper bound is), so that the dual residual is ``P x + q + A^T y + G^T z + z_box``.
"""

from __future__ import annotations

import importlib
import importlib.metadata
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from c3bench.problems.instance import Problem

# name -> tolerance used both for the solver's options and for the success check.
PROFILES: dict[str, float] = {
    "default": 1e-3,
    "low_accuracy": 1e-3,
    "mid_accuracy": 1e-6,
    "high_accuracy": 1e-9,
}
PRECISIONS: tuple[str, ...] = ("float64", "float32")
QP_FAMILIES: tuple[str, ...] = ("c3plus_qp", "c3_qp", "lcp")
EQUALITY_QP_FAMILIES: tuple[str, ...] = ("c3plus_qp", "c3_qp")
COMPLEMENTARITY_FAMILIES: tuple[str, ...] = ("projection", "mpcc")


@dataclass(frozen=True)
class Settings:
    """How to solve.

    Attributes
    ----------
    profile
        ``default`` keeps each solver's own options (success is still judged at
        :data:`PROFILES` ``["default"]``); the other profiles set the solver's absolute and
        relative tolerances to ``tolerance``.
    tolerance
        Target accuracy and success threshold for the residuals.
    time_limit
        Wall-clock seconds per solve; enforced by the registry even where a solver has none.
    precision
        ``float64`` or ``float32`` (only backends listing it in ``precisions`` run float32).
    max_iterations
        Iteration cap passed to solvers that take one (``None``: solver default).
    options
        Extra solver-specific options, passed through unchanged.
    """

    profile: str = "default"
    tolerance: float = PROFILES["default"]
    time_limit: float = 10.0
    precision: str = "float64"
    max_iterations: int | None = None
    options: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.profile not in PROFILES:
            raise ValueError(f"profile must be one of {tuple(PROFILES)}, got {self.profile!r}")
        if self.precision not in PRECISIONS:
            raise ValueError(f"precision must be one of {PRECISIONS}, got {self.precision!r}")
        if not self.tolerance > 0:
            raise ValueError(f"tolerance must be > 0, got {self.tolerance!r}")
        if not self.time_limit > 0:
            raise ValueError(f"time_limit must be > 0, got {self.time_limit!r}")

    @property
    def sets_tolerance(self) -> bool:
        """Whether the backend should pass ``tolerance`` to the solver."""
        return self.profile != "default"

    def with_(self, **changes: Any) -> Settings:
        return replace(self, **changes)


def settings_for(profile: str, **changes: Any) -> Settings:
    """The settings of a named profile, with optional overrides."""
    if profile not in PROFILES:
        raise ValueError(f"profile must be one of {tuple(PROFILES)}, got {profile!r}")
    return Settings(profile=profile, tolerance=PROFILES[profile], **changes)


@dataclass
class WarmStart:
    """An initial guess: primal ``x`` and, where known, duals ``y`` and ``z``."""

    x: np.ndarray | None = None
    y: np.ndarray | None = None
    z: np.ndarray | None = None


@dataclass
class Result:
    """What a backend returns for one solve.

    Attributes
    ----------
    solver, problem
        Backend and instance names.
    found
        The solver claims a solution (judged by residuals later, never by this alone).
    status
        Solver's own status text, or the failure reason.
    x, y, z, z_box
        Primal, equality duals, inequality duals, box duals (``None`` when unknown).
    iterations
        Solver iterations (``None`` when not reported).
    build_time, solve_time
        Seconds spent converting and setting up, then solving.
    objective
        ``1/2 x P x + q x + objective_offset`` at ``x``.
    trace
        Per-iteration series by name (e.g. ``primal_residual``), where available.
    diagnostics
        Scalars a backend measures about itself (e.g. ``cond_schur_raw``).
    failure
        Category of a failure: ``""`` (none), ``error``, ``timeout``, ``invalid_input``,
        ``non_finite``, ``unsupported``, ``unavailable``, ``infeasible``.
    """

    solver: str
    problem: str
    found: bool
    status: str
    x: np.ndarray | None = None
    y: np.ndarray | None = None
    z: np.ndarray | None = None
    z_box: np.ndarray | None = None
    iterations: int | None = None
    build_time: float = 0.0
    solve_time: float = 0.0
    objective: float | None = None
    trace: dict[str, list[float]] = field(default_factory=dict)
    diagnostics: dict[str, float] = field(default_factory=dict)
    failure: str = ""

    @classmethod
    def failed(cls, solver: str, problem: str, failure: str, status: str,
               **extra: Any) -> Result:
        """A failure record with a category and a reason."""
        return cls(solver=solver, problem=problem, found=False, status=status,
                   failure=failure, **extra)


class Backend:
    """Base class of every solver adapter.

    Subclasses set ``name``, ``families`` (what they accept), ``package`` (the import name
    whose version is reported), optionally ``precisions`` and ``description``, and implement
    :meth:`solve`. They measure ``build_time`` and ``solve_time`` with
    :func:`solvers.timing.Stopwatch` and leave time limits and error capture to the registry.
    """

    name: str = ""
    families: tuple[str, ...] = ()
    package: str = ""
    precisions: tuple[str, ...] = ("float64",)
    description: str = ""

    def availability(self) -> tuple[bool, str]:
        """``(True, "")`` or ``(False, reason)``. Default: the package imports."""
        if not self.package:
            return True, ""
        try:
            importlib.import_module(self.package)
        except Exception as error:  # noqa: BLE001 - recorded, never raised
            return False, f"cannot import {self.package}: {error}"
        return True, ""

    def version(self) -> str:
        """Version of the underlying package (``"-"`` for our own code)."""
        if not self.package:
            return "-"
        for distribution in (self.package, self.package.replace("_", "-")):
            try:
                return importlib.metadata.version(distribution)
            except importlib.metadata.PackageNotFoundError:
                continue
        module = importlib.import_module(self.package)
        return str(getattr(module, "__version__", "unknown"))

    def accepts(self, problem: Problem) -> tuple[bool, str]:
        """Whether this backend can take ``problem``; the reason when not."""
        if problem.family not in self.families:
            return False, f"{self.name} does not take family {problem.family!r}"
        return True, ""

    def solve(self, problem: Problem, settings: Settings,
              warm_start: WarmStart | None = None) -> Result:
        raise NotImplementedError
