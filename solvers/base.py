"""The solver contract: settings profiles, ``Result`` and the ``Backend`` base class.

Conventions follow qpsolvers (Caron et al., *qpsolvers: Quadratic Programming Solvers in
Python*, 2024): for ``min 1/2 x^T P x + q^T x`` s.t. ``A x = b``, ``G x <= h``,
``lb <= x <= ub`` a solution carries the primal ``x``, the equality duals ``y``, the inequality
duals ``z >= 0`` and the box duals ``z_box`` (negative where a lower bound is active, positive
where an upper bound is), so that the dual residual is ``P x + q + A^T y + G^T z + z_box``.

Names are types (:mod:`c3bench.problems.names`): families, profiles, precisions and failure
categories are :class:`enum.StrEnum` members, equal to (and stored as) their strings.
"""

from __future__ import annotations

import importlib
import importlib.metadata
from dataclasses import dataclass, field, replace
from types import ModuleType
from typing import Any, TypeVar

import numpy as np

from c3bench.problems.errors import BackendUnavailable, InputError
from c3bench.problems.instance import Problem
from c3bench.problems.names import PROFILE_TOLERANCE, Failure, Family, Precision, Profile
from c3bench.solvers.timing import total_time


@dataclass(frozen=True)
class Settings:
    """How to solve.

    Attributes
    ----------
    profile
        A :class:`~c3bench.problems.names.Profile`: ``default`` keeps each solver's own
        options (success is still judged at ``PROFILE_TOLERANCE[Profile.DEFAULT]``); the other
        profiles set the solver's absolute and relative tolerances to ``tolerance``.
    tolerance
        Target accuracy and success threshold for the residuals.
    time_limit
        Wall-clock seconds per solve; enforced by the registry even where a solver has none.
    precision
        A :class:`~c3bench.problems.names.Precision` (only backends listing it in
        ``precisions`` run float32).
    max_iterations
        Iteration cap passed to solvers that take one (``None``: solver default).
    options
        Extra solver-specific options, passed through unchanged.

    ``profile`` and ``precision`` may be given as strings; they are stored as the enum
    members (equal to those strings).
    """

    profile: str = Profile.DEFAULT
    tolerance: float = PROFILE_TOLERANCE[Profile.DEFAULT]
    time_limit: float = 10.0
    precision: str = Precision.FLOAT64
    max_iterations: int | None = None
    options: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        object.__setattr__(self, "profile", _member(Profile, self.profile, "profile"))
        object.__setattr__(self, "precision", _member(Precision, self.precision, "precision"))
        if not self.tolerance > 0:
            raise InputError(f"tolerance must be > 0, got {self.tolerance!r}")
        if not self.time_limit > 0:
            raise InputError(f"time_limit must be > 0, got {self.time_limit!r}")

    @property
    def sets_tolerance(self) -> bool:
        """Whether the backend should pass ``tolerance`` to the solver."""
        return self.profile != Profile.DEFAULT

    @property
    def dtype(self) -> np.dtype[np.floating]:
        """The numpy dtype of ``precision``."""
        return Precision(self.precision).dtype

    def with_(self, **changes: Any) -> Settings:
        """A copy with ``changes`` applied (``dataclasses.replace``)."""
        return replace(self, **changes)


_E = TypeVar("_E", Profile, Precision)


def _member(kind: type[_E], value: str, what: str) -> _E:
    """``kind(value)``; an :class:`InputError` listing the choices when it is none of them."""
    try:
        return kind(value)
    except ValueError:
        choices = tuple(str(member) for member in kind)
        raise InputError(f"{what} must be one of {choices}, got {value!r}") from None


def settings_for(profile: str, **changes: Any) -> Settings:
    """The settings of a named profile (its tolerance from ``PROFILE_TOLERANCE``), with
    optional overrides."""
    member = _member(Profile, profile, "profile")
    return Settings(profile=member, tolerance=PROFILE_TOLERANCE[member], **changes)


@dataclass
class WarmStart:
    """An initial guess: primal ``x`` and, where known, duals ``y``, ``z`` and the box duals
    ``z_box`` (the sign convention of :class:`Result`)."""

    x: np.ndarray | None = None
    y: np.ndarray | None = None
    z: np.ndarray | None = None
    z_box: np.ndarray | None = None


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
    setup_time, solve_time
        Seconds of setup (conversion, structure analysis, factorisation, solver object
        construction), then of the solve proper: the one timing contract of
        :mod:`c3bench.solvers.timing`; a caller pays their sum, :attr:`total_time`.
    objective
        ``1/2 x P x + q x + objective_offset`` at ``x``.
    trace
        Per-iteration series by name (e.g. ``primal_residual``), where available.
    diagnostics
        Scalars a backend measures about itself (e.g. ``cond_schur_raw``).
    failure
        A :class:`~c3bench.problems.names.Failure`: always ``Failure.NONE`` (``""``) when the
        solver claims a solution; otherwise the category of the failure, or ``Failure.NONE``
        when the solver returned without claiming one and without an error (reported as
        "not found").
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
    setup_time: float = 0.0
    solve_time: float = 0.0
    objective: float | None = None
    trace: dict[str, list[float]] = field(default_factory=dict)
    diagnostics: dict[str, float] = field(default_factory=dict)
    failure: str = Failure.NONE

    @property
    def total_time(self) -> float:
        """``setup_time + solve_time``: what the caller pays for this solve."""
        return total_time(self.setup_time, self.solve_time)

    @classmethod
    def failed(cls, solver: str, problem: str, failure: Failure, status: str,
               **extra: Any) -> Result:
        """A failure record with a category and a reason."""
        return cls(solver=solver, problem=problem, found=False, status=status,
                   failure=Failure(failure), **extra)


def require_module(name: str) -> ModuleType:
    """Import the module ``name``; :class:`BackendUnavailable` (with the reason) when it is
    missing or fails to load."""
    try:
        return importlib.import_module(name)
    except Exception as error:  # any import failure (not only ImportError) means unavailable
        raise BackendUnavailable(f"cannot import {name}: {error}") from error


class Backend:
    """Base class of every solver adapter.

    Subclasses set ``name``, ``families`` (what they accept), ``package`` (the import name
    whose version is reported), optionally ``precisions`` and ``description``, and implement
    :meth:`solve`. They measure ``setup_time`` and ``solve_time`` with
    :class:`c3bench.solvers.timing.Stopwatch` as the timing contract of
    :mod:`c3bench.solvers.timing` defines them (their docstring states the split) and leave
    time limits and error capture to the registry.

    A backend that cannot run here (package missing, plugin absent, no licence) raises
    :class:`~c3bench.problems.errors.BackendUnavailable` from :meth:`require` (or from
    :meth:`solve`, when that is only found out while solving); the registry lists it as
    unavailable and records such a solve as ``Failure.UNAVAILABLE``.
    """

    name: str = ""
    families: tuple[Family, ...] = ()
    package: str = ""
    precisions: tuple[Precision, ...] = (Precision.FLOAT64,)
    description: str = ""
    warm_support: str = ""
    """What a warm cell measures for this backend (:mod:`c3bench.solvers.timing`): its own
    update API, or "" (a full solve: the warm cell is emulated)."""

    def require(self) -> None:
        """Raise :class:`BackendUnavailable` when the backend cannot run in this process.

        Default: ``package`` (when set) imports. Subclasses extend it with plugin or licence
        checks.
        """
        if self.package:
            require_module(self.package)

    def availability(self) -> tuple[bool, str]:
        """``(True, "")`` or ``(False, reason)``, from :meth:`require`."""
        try:
            self.require()
        except BackendUnavailable as error:
            return False, str(error)
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
        """Solve ``problem``; failures are returned as a :class:`Result`, not raised."""
        raise NotImplementedError
