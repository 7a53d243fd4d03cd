"""What a benchmark run does: its cells, the ADMM sequences behind warm starts, its options.

Unit of work: one **cell** = (instance, solver, settings profile, precision, start). A cell
exists only when the backend accepts the instance (``backend.accepts``) and runs in that
precision; ``warm`` cells exist only for instances with a predecessor in their ADMM sequence
(same family and metadata except ``admm_iteration``/``rho``, the largest earlier iteration
present in the suite): the warm start is the predecessor's reference solution, as a controller
reuses its last answer. A warm cell is timed by the warm contract of
:mod:`c3bench.solvers.timing`: the solver object is set up on the instance untimed, then its
own update API (OSQP, ProxQP, Clarabel, PIQP) takes the instance's vectors and it solves from
that warm start; ``setup_time`` is the update, ``total_time`` update + solve. Backends
without an update API pay setup + solve (their ``warm_support`` says so).
"""

from __future__ import annotations

import itertools
import json
from collections.abc import Sequence
from dataclasses import dataclass

from c3bench.bench import store
from c3bench.problems.errors import InputError
from c3bench.problems.instance import Problem
from c3bench.problems.names import Precision, Profile, Start
from c3bench.solvers import registry
from c3bench.solvers.child_process import STARTUP_SECONDS

STARTS: tuple[Start, ...] = (Start.COLD, Start.WARM)
"""The starts of a run unless chosen otherwise, cold first."""
DEFAULT_PRECISIONS: tuple[Precision, ...] = tuple(Precision)
"""Both precisions, float64 first (float32 cells only where a backend runs in it)."""
DEFAULT_SETTINGS: tuple[Profile, ...] = (Profile.DEFAULT,)
"""Settings profiles of a run unless chosen otherwise."""
ITERATION_KEYS: tuple[str, ...] = ("admm_iteration", "rho")
"""Instance metadata that changes along one ADMM sequence."""


@dataclass(frozen=True)
class Cell:
    """One unit of work (see the module docstring)."""

    instance: str
    family: str
    solver: str
    settings: str
    precision: str
    start: str

    @property
    def id(self) -> str:
        """File-safe id (:func:`bench.store.cell_id`)."""
        return store.cell_id(self.instance, self.solver, self.settings, self.precision,
                             self.start)

    @property
    def key(self) -> tuple[str, ...]:
        """Identity of the cell: the values of :data:`bench.store.KEY_COLUMNS`."""
        return (self.instance, self.solver, self.settings, self.precision, self.start)


@dataclass(frozen=True)
class RunOptions:
    """How each cell is solved.

    Attributes
    ----------
    repeats
        Timed repeats (median reported) after one untimed warm-up.
    time_limit
        Seconds per solve (the registry kills the solve after it).
    reference_time_limit
        Seconds per reference solve.
    preload
        Plugins loaded in every worker before a cell runs, ``module`` or
        ``module:function`` (to register extra backends; see
        :func:`c3bench.solvers.registry.import_plugins`).
    suite
        Suite name written into each row.
    """

    repeats: int = 3
    time_limit: float = 10.0
    reference_time_limit: float = 60.0
    preload: tuple[str, ...] = ()
    suite: str = ""

    def cell_budget(self) -> float:
        """Watchdog for one cell in the pool: beyond the isolated solve's own bounds (its
        child's start-up allowances and ``(repeats + 1) * time_limit``), so that a watchdog
        overrun means a stuck worker, never a slow solve."""
        return 2.0 * self.time_limit * (self.repeats + 1) + 2.0 * STARTUP_SECONDS + 60.0

    def reference_budget(self) -> float:
        """Watchdog for one reference (two isolated solves: the reference and its
        cross-check, each with its child's start-up allowances)."""
        return 4.0 * self.reference_time_limit + 4.0 * STARTUP_SECONDS + 60.0


def sequence_key(problem: Problem) -> str:
    """Identity of an ADMM sequence: family and all metadata but the iteration and rho."""
    meta = {k: v for k, v in problem.meta.items() if k not in ITERATION_KEYS}
    return json.dumps([str(problem.family), problem.n, meta], sort_keys=True, default=str)


def predecessors(problems: Sequence[Problem]) -> dict[str, str]:
    """``instance -> previous instance of its ADMM sequence`` (absent for the first)."""
    sequences: dict[str, list[tuple[int, str]]] = {}
    for problem in problems:
        iteration = problem.meta.get("admm_iteration")
        if iteration is None:
            continue
        sequences.setdefault(sequence_key(problem), []).append((int(iteration), problem.name))
    out: dict[str, str] = {}
    for members in sequences.values():
        members.sort()
        for (_, before), (_, after) in itertools.pairwise(members):
            out[after] = before
    return out


@dataclass
class Plan:
    """The cells of a run and what was left out.

    Attributes
    ----------
    cells
        Every cell, in instance, solver, precision, settings, start order.
    solvers
        ``name -> version`` of the backends that run.
    skipped_solvers
        ``name -> reason`` of the chosen backends that are not available here.
    """

    cells: list[Cell]
    solvers: dict[str, str]
    skipped_solvers: dict[str, str]


def _check_names(kind: str, names: Sequence[str], known: Sequence[str]) -> None:
    unknown = [name for name in names if name not in known]
    if unknown:
        raise InputError(f"unknown {kind} {', '.join(map(repr, unknown))}; known: "
                         f"{', '.join(known)}")


def plan_cells(problems: Sequence[Problem], solvers: Sequence[str] | None,
               settings: Sequence[str], precisions: Sequence[str],
               starts: Sequence[str], previous: dict[str, str]) -> Plan:
    """Every cell a backend can take; warm cells only where a predecessor exists.

    A backend whose ``accepts()`` raises is planned: its solve then records the error
    (``accepts() raised ...``) instead of the cells silently missing.

    ``solvers=None`` means every available backend. Unknown names raise
    :class:`~c3bench.problems.errors.InputError`; unavailable backends are skipped (listed in
    ``skipped_solvers`` with the reason).
    """
    _check_names("settings", settings, tuple(Profile))
    _check_names("precision", precisions, tuple(Precision))
    _check_names("start", starts, tuple(Start))
    infos = {info.name: info for info in registry.available()}
    if solvers is not None:
        _check_names("solver", solvers, tuple(infos))
    names = list(infos) if solvers is None else list(dict.fromkeys(solvers))
    chosen = {n: infos[n].version for n in names if infos[n].available}
    skipped = {n: infos[n].reason for n in names if not infos[n].available}
    cells = []
    for problem in problems:
        for name in chosen:
            backend = registry.get(name)
            try:
                accepted, _ = backend.accepts(problem)
            except Exception:  # noqa: BLE001 - planned: the solve records "accepts() raised"
                accepted = True
            if not accepted:
                continue
            for precision in precisions:
                if precision not in backend.precisions:
                    continue
                for profile in settings:
                    for start in starts:
                        if start == Start.WARM and problem.name not in previous:
                            continue
                        cells.append(Cell(problem.name, str(problem.family), name,
                                          str(profile), str(precision), str(start)))
    return Plan(cells, chosen, skipped)
