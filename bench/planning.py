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

``sequence`` cells (:mod:`bench.sequence`) exist only for the *head* of each ADMM sequence
(:func:`sequence_heads`: the instance with the lowest ``admm_iteration`` of its sequence) of
a ``c3plus_qp`` / ``c3_qp`` family and QP variant in the run's sequence scope
(:data:`SEQUENCE_SCOPE` unless chosen otherwise), one per backend that accepts the head: the
whole ADMM run at that state with the backend as its QP step, timed end to end.
"""

from __future__ import annotations

import itertools
import json
from collections.abc import Sequence
from dataclasses import dataclass

from c3bench.bench import store
from c3bench.bench.sequence import SEQUENCE_FAMILIES, SEQUENCE_STEPS
from c3bench.problems.errors import InputError
from c3bench.problems.instance import Problem
from c3bench.problems.names import Family, Precision, Profile, QPVariant, Start
from c3bench.solvers import registry
from c3bench.solvers.child_process import STARTUP_SECONDS

STARTS: tuple[Start, ...] = (Start.COLD, Start.WARM, Start.SEQUENCE)
"""The starts of a run (``c3bench run``, :func:`bench.runner.run_suite`) unless chosen
otherwise, cold first; the controller sequence too, so the report has its table
(:data:`SEQUENCE_SCOPE` keeps it to one cell per state and backend)."""
SEQUENCE_SCOPE: tuple[tuple[str, str], ...] = ((Family.C3PLUS_QP, QPVariant.BOUNDED),)
"""``(family, QP variant)`` of the heads that get ``sequence`` cells unless chosen otherwise:
C3+ with the limits in its QP step, the controller the suites capture. C3's sequence
(``c3_qp``) projects by enumerating contact modes, some 4 s a run on the cube, and the
``equality`` variant doubles the cells; both run when the scope is ``None`` (every head)."""
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

    def sequence_budget(self) -> float:
        """Watchdog for one ``sequence`` cell: its child's runs (the untimed one, the timed
        ones and the reference, each bounded by ``SEQUENCE_STEPS`` times a per-QP limit),
        with the start-up allowances."""
        runs = self.time_limit * (self.repeats + 1) + self.reference_time_limit
        return 2.0 * SEQUENCE_STEPS * runs + 2.0 * STARTUP_SECONDS + 60.0

    def reference_budget(self) -> float:
        """Watchdog for one reference (two isolated solves: the reference and its
        cross-check, each with its child's start-up allowances)."""
        return 4.0 * self.reference_time_limit + 4.0 * STARTUP_SECONDS + 60.0


def sequence_key(problem: Problem) -> str:
    """Identity of an ADMM sequence: family and all metadata but the iteration and rho."""
    meta = {k: v for k, v in problem.meta.items() if k not in ITERATION_KEYS}
    return json.dumps([str(problem.family), problem.n, meta], sort_keys=True, default=str)


def sequence_heads(problems: Sequence[Problem],
                   scope: Sequence[tuple[str, str]] | None = None) -> set[str]:
    """Names of the instances that head their ADMM sequence: per :func:`sequence_key`, the
    ``c3plus_qp`` / ``c3_qp`` instance with the lowest ``admm_iteration``; only those whose
    ``(family, meta["variant"])`` is in ``scope`` (``None``: every one)."""
    allowed = None if scope is None else {(str(f), str(v)) for f, v in scope}
    heads: dict[str, tuple[int, str]] = {}
    for problem in problems:
        iteration = problem.meta.get("admm_iteration")
        if problem.family not in SEQUENCE_FAMILIES or iteration is None:
            continue
        if allowed is not None and (str(problem.family),
                                    str(problem.meta.get("variant", ""))) not in allowed:
            continue
        key = sequence_key(problem)
        heads[key] = min(heads.get(key, (int(iteration), problem.name)),
                         (int(iteration), problem.name))
    return {name for _, name in heads.values()}


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
               starts: Sequence[str], previous: dict[str, str],
               heads: set[str] | None = None) -> Plan:
    """Every cell a backend can take; warm cells only where a predecessor exists, sequence
    cells only for ``heads`` (default: :func:`sequence_heads` in :data:`SEQUENCE_SCOPE`).

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
    heads = sequence_heads(problems, SEQUENCE_SCOPE) if heads is None else heads
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
                        if start == Start.SEQUENCE and problem.name not in heads:
                            continue
                        cells.append(Cell(problem.name, str(problem.family), name,
                                          str(profile), str(precision), str(start)))
    return Plan(cells, chosen, skipped)
