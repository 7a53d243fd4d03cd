"""Reference optima: which backend gives ``f*`` for which family, and the cache of them.

:data:`REFERENCE_PLANS` is the one place in ``bench/`` that names solvers. Each family's
reference backend solves every instance at ``high_accuracy``; a second backend cross-checks
it and their relative disagreement

    spread = |f*_ref - f*_check| / max(1, |f*_ref|)

is recorded as the reference's own uncertainty (:mod:`bench.metrics` judges cost errors
against ``max(tolerance, spread)``). A solve *passes* when its solver reports a solution whose
relative primal residual and complementarity violation are at most :data:`ACCEPT_RESIDUAL`
(for ``lcp`` and ``lcp_general`` the complementarity figure is the relative natural residual
``||min(lam, F lam + q)||``, so a point with ``lam`` or ``w`` negative is refused, and an LCP
without a solution never gets a reference). For ``lcp_general`` every solution has the same
objective (0: the family has none), so the cross-check (the MIQP ``scip_lcp``, or PGS where
SCIP is missing) confirms that the LCP is solvable rather than a value of ``f*``.

A reference is **accepted** (``available``: the instance has a verified ``f*``) only when the
reference solve passes and either carries a global optimality certificate
(:func:`optimality_certificate`: a branch-and-bound MIQP solve of an exact complementarity model
closed to a gap of at most :data:`AGREE_COST`; the check is then not run and ``check_status``
records the certificate) or the cross-check passes too and they agree: ``spread <=``
:data:`AGREE_COST`. Otherwise ``f*`` is NaN, every cost error of that instance is NaN, its
rows are marked ``verified = False`` and the ``reason`` column (listed in the report) says
why: the reference failed, the check failed, or they disagree. A check never stands in for a
failed reference, and a plan without a check gives no verified ``f*``. The solution of a
passing reference solve is kept even when unverified: it only warm-starts the next ADMM
iterate.

The cache ``results/<suite>/references.parquet`` holds one row per instance (with the
reference's ``x, y, z, z_box`` for warm starts), keyed by the instance's content hash and the
plan, so a regenerated instance or a changed plan is recomputed.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pyarrow as pa

from c3bench.bench.store import atomic_write_bytes, parquet_bytes, read_parquet
from c3bench.problems.instance import Problem
from c3bench.problems.names import Failure, Family, Profile
from c3bench.solvers.base import Result, Settings, WarmStart, settings_for
from c3bench.solvers.isolation import solve_isolated
from c3bench.solvers.residuals import cost_error, residuals


@dataclass(frozen=True)
class ReferencePlan:
    """Reference backend of a family, its cross-check, and the profile they run at.

    ``fallback_check`` cross-checks instead of ``check`` when ``check`` is unavailable here
    (its package is missing); a ``check`` that runs and fails is never replaced.
    """

    solver: str
    check: str | None
    settings: str = Profile.HIGH_ACCURACY
    fallback_check: str | None = None


# The only solver names in bench/: the reference of each family and its cross-check.
REFERENCE_PLANS: dict[str, ReferencePlan] = {
    Family.C3PLUS_QP: ReferencePlan("clarabel", "proxqp_dense"),
    Family.C3_QP: ReferencePlan("clarabel", "proxqp_dense"),
    Family.LCP: ReferencePlan("lemke", "clarabel"),
    Family.PROJECTION: ReferencePlan("scip", "bonmin"),
    Family.MPCC: ReferencePlan("scip", "bonmin"),
    Family.QP: ReferencePlan("clarabel", "proxqp_dense"),
    # any solution of an LCP is as good as another (the family's objective is 0): the check
    # confirms that the LCP is solvable, by an independent method
    Family.LCP_GENERAL: ReferencePlan("lemke", "scip_lcp", fallback_check="pgs"),
}

ACCEPT_RESIDUAL = 1e-6
AGREE_COST = 1e-6
"""Largest relative disagreement ``|f*_ref - f*_check| / max(1, |f*_ref|)`` of an accepted
reference."""
REFERENCE_COLUMNS: tuple[str, ...] = (
    "instance", "family", "instance_hash", "planned_solver", "planned_check", "settings",
    "available", "solver", "reason", "failure", "status", "objective", "primal_residual",
    "complementarity_violation", "solve_time", "check_solver", "check_status",
    "check_objective", "spread", "x", "y", "z", "z_box",
)


@dataclass
class Reference:
    """The reference optimum of one instance (see the module docstring).

    Attributes
    ----------
    available
        Whether ``objective`` is a verified ``f*`` (reference and cross-check passed and
        agree; see the module docstring).
    solver
        Backend that gave ``f*`` (``""`` when none).
    reason
        Why there is no verified ``f*`` (``""`` when there is one).
    objective
        ``f*``; for an unverified reference the objective of the reference solve when it
        passed its own residual test (NaN otherwise), shown but never used.
    spread
        Relative disagreement with the cross-check (NaN when it could not be computed).
    x, y, z, z_box
        The reference solve's solution when it passed its own residual test (``None``
        otherwise), used to warm-start the next ADMM iterate.
    """

    instance: str
    family: str
    instance_hash: str
    planned_solver: str
    planned_check: str
    settings: str
    available: bool = False
    solver: str = ""
    reason: str = ""
    failure: str = ""
    status: str = ""
    objective: float = float("nan")
    primal_residual: float = float("nan")
    complementarity_violation: float = float("nan")
    solve_time: float = float("nan")
    check_solver: str = ""
    check_status: str = ""
    check_objective: float = float("nan")
    spread: float = float("nan")
    x: np.ndarray | None = None
    y: np.ndarray | None = None
    z: np.ndarray | None = None
    z_box: np.ndarray | None = None

    def value(self) -> ReferenceValue:
        """What a cell needs: ``f*``, its solver and spread."""
        if not self.available:
            return ReferenceValue("", float("nan"), float("nan"))
        return ReferenceValue(self.solver, self.objective, self.spread)

    def warm_start(self) -> WarmStart | None:
        """The reference solution as a warm start (``None`` without one; an unverified
        solution that passed its own residual test still serves as an initial guess)."""
        if self.x is None:
            return None
        return WarmStart(x=self.x, y=self.y, z=self.z, z_box=self.z_box)


@dataclass(frozen=True)
class ReferenceValue:
    """``f*`` of an instance as a cell sees it."""

    solver: str
    objective: float
    spread: float


def plan_for(family: str) -> ReferencePlan | None:
    """The reference plan of a family (``None`` when it has none)."""
    return REFERENCE_PLANS.get(family)


def _accept(problem: Problem, result: Any) -> tuple[bool, str, float, float]:
    """Whether a solve is good enough to be a reference; reason; primal and compl. residual."""
    if not result.found or result.x is None:
        return False, f"{result.solver}: {result.failure or 'not found'}: {result.status}", \
            float("nan"), float("nan")
    figures = residuals(problem, result.x)
    worst = float(np.max([figures.primal_relative, figures.complementarity]))  # NaN fails
    if not worst <= ACCEPT_RESIDUAL:
        return False, (f"{result.solver}: residual {worst:.2e} above {ACCEPT_RESIDUAL:.0e} "
                       f"({result.status})"), figures.primal, figures.complementarity
    return True, "", figures.primal, figures.complementarity


def compute_reference(problem: Problem, digest: str, plan: ReferencePlan | None,
                      time_limit: float = 60.0, preload: tuple[str, ...] = ()) -> Reference:
    """Solve ``problem`` with the plan's reference and check backends.

    ``plan`` is decided by the caller (``plan_for(problem.family)``), so workers need no
    copy of the table. Runs through :func:`c3bench.solvers.isolation.solve_isolated` (a
    child killed on overrun), so a failing reference costs only this instance's ``f*``; a
    child that cannot be started raises
    :class:`~c3bench.solvers.isolation.IsolationFailed` (nothing to cache).
    """
    from c3bench.solvers.registry import import_plugins

    import_plugins(preload)
    ref = Reference(problem.name, str(problem.family), digest, plan.solver if plan else "",
                    (plan.check or "") if plan else "", plan.settings if plan else "")
    if plan is None:
        ref.reason = f"no reference plan for family {problem.family!r}"
        return ref
    settings = settings_for(plan.settings, time_limit=time_limit)
    main = solve_isolated(plan.solver, problem, settings)
    ok, reason, primal, compl = _accept(problem, main)
    ref.status, ref.solve_time = main.status, float(main.solve_time)
    ref.failure = str(Failure.NONE) if ok else (str(main.failure) or "inaccurate")
    if ok:
        _keep_solution(ref, problem, main, primal, compl)
    certificate = optimality_certificate(main) if ok else ""
    if certificate:  # a global solver's proof stands on its own: no second solve needed
        ref.check_status, ref.spread = certificate, 0.0
        ref.reason, ref.available, ref.solver = "", True, plan.solver
        return ref
    check_ok, check_reason = _cross_check(ref, problem, plan, settings)
    if ok and check_ok:
        ref.spread = cost_error(ref.check_objective, ref.objective)
    ref.reason = _verdict(ok, reason, plan, ref.check_solver or plan.check or "-", check_ok,
                          check_reason, ref.spread)
    ref.available = not ref.reason
    ref.solver = plan.solver if ref.available else ""
    return ref


def optimality_certificate(result: Result) -> str:
    """A global optimality proof in ``result``, described, or ``""`` when it has none.

    A branch-and-bound MIQP solve of a complementarity family (SCIP, Gurobi) that ends
    ``optimal`` with an exact complementarity model (SOS1 or indicator constraints:
    ``diagnostics["big_m"] == 0``; a big-M model is exact only if M bounds every optimum)
    and a relative gap between its incumbent and its dual bound of at most
    :data:`AGREE_COST` proves ``f*`` to that gap (Achterberg, "SCIP: solving constraint
    integer programs", Mathematical Programming Computation 1, 2009). The bound, not a
    second solver, is the check: a local MINLP solver (Bonmin on these nonconvex instances)
    cannot confirm a global optimum and often fails first.
    """
    diagnostics = result.diagnostics or {}
    gap = diagnostics.get("mip_gap")
    status = str(result.status).lower()
    proved = "optimal" in status or "gaplimit" in status
    if gap is None or diagnostics.get("big_m", math.nan) != 0.0 or not proved:
        return ""
    if not (math.isfinite(gap) and gap <= AGREE_COST):
        return ""
    bound = diagnostics.get("dual_bound", math.nan)
    return f"certificate: {result.solver} optimal, gap {gap:.1e}, dual bound {bound:.6g}"


def _keep_solution(ref: Reference, problem: Problem, result: Result, primal: float,
                   compl: float) -> None:
    """Store a passing reference solve's point, objective and residuals in ``ref``."""
    ref.x = np.asarray(result.x, dtype=float)
    ref.objective = float(problem.objective(ref.x))
    ref.primal_residual, ref.complementarity_violation = primal, compl
    for name in ("y", "z", "z_box"):
        value = getattr(result, name)
        setattr(ref, name, None if value is None else np.asarray(value, dtype=float))


def _cross_check(ref: Reference, problem: Problem, plan: ReferencePlan,
                 settings: Settings) -> tuple[bool, str]:
    """Solve with the plan's check (when it has one) and record it in ``ref``; whether it
    passed and why not."""
    if not plan.check:
        return False, "no cross-check planned"
    check = solve_isolated(plan.check, problem, settings)
    if check.failure == Failure.UNAVAILABLE and plan.fallback_check:
        check = solve_isolated(plan.fallback_check, problem, settings)
    check_ok, check_reason, _, _ = _accept(problem, check)
    ref.check_solver = check.solver
    ref.check_status = check.status if check_ok else check_reason
    if check_ok:
        ref.check_objective = float(problem.objective(np.asarray(check.x, dtype=float)))
    return check_ok, check_reason


def _verdict(ok: bool, reason: str, plan: ReferencePlan, check_name: str, check_ok: bool,
             check_reason: str, spread: float) -> str:
    """``""`` when the reference is verified, else why not (the references table shows it);
    ``check_name`` is the cross-check that ran (the plan's, or its fallback)."""
    if not ok:
        return f"{reason}; no verified f*"
    if not check_ok:
        return f"cross-check {check_name} failed ({check_reason}); f* not verified"
    if not spread <= AGREE_COST:
        return (f"{plan.solver} and cross-check {check_name} disagree: cost spread "
                f"{spread:.2e} > {AGREE_COST:.0e}; f* not verified")
    return ""


# --- cache --------------------------------------------------------------------------------------
def _to_list(value: np.ndarray | None) -> list[float] | None:
    return None if value is None else [float(v) for v in np.asarray(value).ravel()]


def save_references(path: Path, references: dict[str, Reference]) -> None:
    """Write the cache atomically (rows sorted by instance; schema version in the metadata)."""
    records = []
    for name in sorted(references):
        record = asdict(references[name])
        for key in ("x", "y", "z", "z_box"):
            record[key] = _to_list(getattr(references[name], key))
        records.append(record)
    frame = pd.DataFrame(records, columns=list(REFERENCE_COLUMNS))
    list_type = pa.list_(pa.float64())
    fields = []
    for column in REFERENCE_COLUMNS:
        if column in ("x", "y", "z", "z_box"):
            fields.append(pa.field(column, list_type))
        elif column == "available":
            fields.append(pa.field(column, pa.bool_()))
        elif column in ("objective", "primal_residual", "complementarity_violation",
                        "solve_time", "check_objective", "spread"):
            fields.append(pa.field(column, pa.float64()))
        else:
            fields.append(pa.field(column, pa.string()))
    table = pa.Table.from_pydict({c: frame[c].tolist() for c in REFERENCE_COLUMNS},
                                 schema=pa.schema(fields))
    atomic_write_bytes(path, parquet_bytes(table))


def load_references(path: str | Path) -> dict[str, Reference]:
    """Read the cache (``{}`` when absent); reject another schema version."""
    path = Path(path)
    if not path.exists():
        return {}
    table = read_parquet(path)
    out: dict[str, Reference] = {}
    for record in table.to_pylist():
        values = {key: record.get(key) for key in REFERENCE_COLUMNS}
        for key in ("x", "y", "z", "z_box"):
            values[key] = None if values[key] is None else np.asarray(values[key], dtype=float)
        for key in ("objective", "primal_residual", "complementarity_violation", "solve_time",
                    "check_objective", "spread"):
            values[key] = float("nan") if values[key] is None else float(values[key])
        for key in REFERENCE_COLUMNS:
            if values[key] is None and key not in ("x", "y", "z", "z_box"):
                values[key] = ""
        out[str(values["instance"])] = Reference(**values)
    return out


def reusable(ref: Reference | None, digest: str, plan: ReferencePlan | None) -> bool:
    """Whether a cached reference still holds: same instance content and plan, and it did not
    fail only because a backend was unavailable (which a later install may fix)."""
    if ref is None or plan is None:
        return False
    return (ref.instance_hash == digest and ref.planned_solver == plan.solver
            and ref.planned_check == (plan.check or "") and ref.settings == plan.settings
            and ref.failure != Failure.UNAVAILABLE)


@dataclass
class ReferenceSummary:
    """Per family: how many instances have ``f*`` and why the others do not."""

    family: str
    plan: str
    instances: int
    available: int
    max_spread: float
    reasons: list[str] = field(default_factory=list)


def summarise(references: dict[str, Reference]) -> list[ReferenceSummary]:
    """One :class:`ReferenceSummary` per family, sorted by family."""
    by_family: dict[str, list[Reference]] = {}
    for ref in references.values():
        by_family.setdefault(ref.family, []).append(ref)
    out = []
    for family in sorted(by_family):
        refs = sorted(by_family[family], key=lambda r: r.instance)
        plan = plan_for(family)
        label = "-" if plan is None else (plan.solver + (f" (checked by {plan.check})"
                                                         if plan.check else ""))
        spreads = [r.spread for r in refs if r.available and math.isfinite(r.spread)]
        reasons = sorted({r.reason for r in refs if r.reason})
        out.append(ReferenceSummary(family, label, len(refs), sum(r.available for r in refs),
                                    max(spreads) if spreads else float("nan"), reasons))
    return out
