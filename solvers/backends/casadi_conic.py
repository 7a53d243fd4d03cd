"""``casadi_qpoases``, ``casadi_hpipm``: qpOASES and HPIPM through CasADi's ``conic`` interface.

The problem goes to ``casadi.conic`` as ``lba <= [A; G] z <= uba`` with native bounds
``lbx <= z <= ubx`` (:class:`TwoSidedForm` without bound rows). CasADi's multipliers satisfy
``H z + g + A^T lam_a + lam_x = 0`` with ``lam > 0`` at an active upper side, i.e. qpsolvers'
signs.

``casadi_qpoases``
    qpOASES' online active-set method: ``printLevel none``, ``CPUtime`` = time limit,
    ``enableEqualities`` on in every profile (equalities start in the working set: 62 instead
    of 364 iterations on a ``c3plus_qp`` instance); ``terminationTolerance = tolerance`` in
    non-default profiles; ``nWSR = max_iterations``.
``casadi_hpipm``
    HPIPM's interior point for optimal-control QPs: the rows are put in HPIPM's stage layout
    (:class:`OCPRows`, stages of ``meta["layout"]``; one stage for problems without one),
    ``mode robust``, ``res_g_max = res_b_max = res_d_max = res_m_max = tolerance`` in
    non-default profiles, ``iter_max = max_iterations``; infinite bounds become
    :data:`HPIPM_INFINITY`, and a solution reaching half of it is reported as not found.

``settings.options`` are passed last to ``casadi.conic``, so they win. A warm start sets
``x0`` and the row multiplier ``lam_a0`` (HPIPM: ``warm_start = 1``).

Timing (the contract of :mod:`c3bench.solvers.timing`; rankings use setup + solve): setup is
the two-sided form (and HPIPM's stage permutation), the conversion to ``casadi.DM`` and, when
it is built, the ``casadi.conic`` function (plugin loading, sparsity analysis;
``diagnostics['casadi_compiled']`` is 1 then); solve is the call of that function (CasADi's
copy of the data into the solver's structures, the solver's own initialisation and iterations).
The function depends only on the sparsity patterns and options, so, as a controller would,
``casadi_hpipm`` builds it once per pattern in the solver process (the cell's untimed warm-up
builds it; :data:`CACHE_FUNCTIONS` kept): CasADi's HPIPM call allocates and initialises HPIPM
afresh every time, so a reused function keeps no state and a cold solve stays cold.
``casadi_qpoases`` builds a new function for every solve: CasADi's qpOASES memory hot-starts
from its last active set once called, so a reused one would make a cold cell warm. **Artificial
bounds:** CasADi's HPIPM interface (``hpipm_interface.cpp``, CasADi 3.x) declares every
variable boxed (``nbx = nx``, ``nbu = nu``, ``idxb`` over all of them) and replaces infinite
bounds by its ``inf`` option; no option removes the boxes, so HPIPM runs its interior point on
``2 n`` extra (inactive) inequalities even for an equality-only QP (about 10 iterations instead
of one factorisation). :data:`HPIPM_INFINITY` keeps those boxes at +-1e6 (see its note); no
HPIPM binding without CasADi installs from the package registry here, so the report names this
as the reason HPIPM is slow.

Warm cells: neither plugin is an :class:`~c3bench.solvers.timing.UpdatableBackend`, so a
warm cell pays a full solve with the initial guess (``warm_support`` says why). qpOASES'
own hot start (``SQProblem::hotstart`` with new vectors) is reachable only through a reused
CasADi function, which hot-starts from its last active set, but CasADi exposes no call that
sets new vectors *without* solving nor one that reports the hot start apart from the solve,
and the ``qpoases`` Python package (which has ``hotstart``) is not installed here. HPIPM's
CasADi interface re-initialises HPIPM on every call: nothing to update.

References
----------
H. J. Ferreau, C. Kirches, A. Potschka, H. G. Bock and M. Diehl, "qpOASES: a parametric
active-set algorithm for quadratic programming", Mathematical Programming Computation 6(4),
327-363, 2014.

G. Frison and M. Diehl, "HPIPM: a high-performance quadratic programming framework for model
predictive control", IFAC-PapersOnLine 53(2), 6563-6569, 2020.

J. A. E. Andersson, J. Gillis, G. Horn, J. B. Rawlings and M. Diehl, "CasADi: a software
framework for nonlinear optimization and optimal control", Mathematical Programming
Computation 11(1), 1-36, 2019.
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass
from typing import Any

import numpy as np
import scipy.sparse as sp

from c3bench.problems.errors import BackendUnavailable
from c3bench.problems.instance import Problem
from c3bench.solvers.backends._qp_forms import (
    QPBackend,
    TwoSidedForm,
    failure_category,
    qp_result,
)
from c3bench.solvers.base import Result, Settings, WarmStart, require_module
from c3bench.solvers.output import quiet_stdout
from c3bench.solvers.registry import register
from c3bench.solvers.timing import Stopwatch

# HPIPM (through CasADi) replaces infinite bounds by a finite number (CasADi's default 1e8).
# Its slack ``1e8 - x`` then carries a rounding error of about 1e8 * 2.2e-16 = 2e-8, so a
# tolerance of 1e-9 can never be met; 1e6 keeps the floor at 2e-10. A solution reaching half
# of it is reported as a failure (the stand-in bound could be active).
HPIPM_INFINITY = 1e6
CACHE_FUNCTIONS = 16
"""Most HPIPM ``casadi.conic`` functions kept per process (least recently used dropped)."""
_FUNCTIONS: OrderedDict[tuple[Any, ...], Any] = OrderedDict()
"""HPIPM's conic functions by (sparsity patterns, options), see
:meth:`CasadiConicBackend._function`."""
# hpipm_common.h: enum hpipm_status
HPIPM_STATUS: dict[str, str] = {"0": "success", "1": "maximum iterations reached",
                                "2": "minimum step length reached", "3": "NaN in solution",
                                "4": "inconsistent equality constraints"}


@dataclass
class OCPRows:
    """Row order and signs that put ``[A; G]`` into HPIPM's optimal-control layout.

    HPIPM (through CasADi) wants the variables ordered ``[x_0 u_0 x_1 u_1 ... x_N]`` and the
    rows ordered ``[gap_0 lincon_0 gap_1 lincon_1 ... lincon_N]`` where a gap row of stage
    ``k`` reads ``A_k x_k + B_k u_k - x_{k+1} = -b`` (coefficient exactly ``-1`` on one
    component of ``x_{k+1}``, each component once) and a lincon row touches stage ``k`` only.
    Row ``i`` of the permuted matrix is ``signs[i]`` times row ``order[i]`` of ``[A; G]``.
    """

    order: np.ndarray
    signs: np.ndarray
    nx: list[int]
    nu: list[int]
    ng: list[int]
    gap_columns: np.ndarray | None = None
    """Per permuted row, the column of its ``x_{k+1}`` coefficient (-1 on lincon rows)."""

    def resigned(self, form: TwoSidedForm) -> OCPRows:
        """The same layout with the gap signs of ``form``'s values (a layout found for the
        same sparsity pattern, reused: :func:`stage_rows`)."""
        if self.gap_columns is None:
            return self
        signs = np.ones(self.order.size)
        gap = self.gap_columns >= 0
        values = np.asarray(sp.csr_matrix(form.matrix)[self.order[gap],
                                                       self.gap_columns[gap]]).ravel()
        signs[gap] = -1.0 / values
        return OCPRows(self.order, signs, self.nx, self.nu, self.ng, self.gap_columns)

    def apply(self, form: TwoSidedForm) -> tuple[sp.csc_matrix, np.ndarray, np.ndarray]:
        """Permuted and scaled ``(matrix, lower, upper)``."""
        matrix = sp.csc_matrix(sp.diags(self.signs) @ form.matrix[self.order])
        lower, upper = form.lower[self.order], form.upper[self.order]
        flip = self.signs < 0
        lower, upper = (np.where(flip, -upper, lower) * np.abs(self.signs),
                        np.where(flip, -lower, upper) * np.abs(self.signs))
        return matrix, lower, upper

    def restore(self, duals: np.ndarray) -> np.ndarray:
        """Multiplier of the original rows from that of the permuted rows."""
        original = np.zeros(self.order.size)
        original[self.order] = self.signs * np.asarray(duals, dtype=float).ravel()
        return original

    def permute(self, duals: np.ndarray) -> np.ndarray:
        """Inverse of :meth:`restore` (warm starts)."""
        permuted: np.ndarray = np.asarray(duals, dtype=float)[self.order] / self.signs
        return permuted

    @classmethod
    def one_stage(cls, form: TwoSidedForm) -> OCPRows:
        """No structure: every variable a state of stage 0, every row a lincon row."""
        rows = form.n_rows
        return cls(np.arange(rows), np.ones(rows), [form.n], [0], [rows])

    @classmethod
    def detect(cls, problem: Problem, form: TwoSidedForm) -> OCPRows | None:
        """The layout of a horizon problem (``meta["layout"]``), or ``None`` when the rows
        do not fit it (a row spanning non-adjacent stages, a gap that is no identity...)."""
        from c3bench.problems.mpc import HorizonLayout

        table = problem.meta.get("layout") if isinstance(problem.meta, dict) else None
        if not table:
            return None
        try:
            layout = HorizonLayout.from_json(table)
            if layout.offset("x") != 0 or layout.size != problem.n:
                return None
        except (KeyError, TypeError, ValueError):
            return None
        T, nx, step = layout.horizon, layout.nx, layout.step_size
        matrix = sp.csr_matrix(form.matrix)
        gaps: list[list[tuple[int, int, float]]] = [[] for _ in range(T + 1)]
        lincon: list[list[int]] = [[] for _ in range(T + 1)]
        for row in range(matrix.shape[0]):
            columns = matrix.indices[matrix.indptr[row]:matrix.indptr[row + 1]]
            values = matrix.data[matrix.indptr[row]:matrix.indptr[row + 1]]
            nonzero = values != 0
            columns, values = columns[nonzero], values[nonzero]
            stages = np.minimum(columns // step, T)
            first = int(stages.min()) if stages.size else 0
            if np.all(stages == first):
                lincon[first].append(row)
                continue
            later = stages == first + 1
            is_equality = form.lower[row] == form.upper[row]
            if (not is_equality or not np.all(stages[~later] == first)
                    or int(later.sum()) != 1):
                return None
            column = int(columns[later][0])
            if column - (first + 1) * step >= nx:
                return None  # the next stage enters through something other than its x
            gaps[first].append((column, row, -1.0 / float(values[later][0])))
        order: list[int] = []
        signs: list[float] = []
        gap_columns: list[int] = []
        for k in range(T + 1):
            if k < T:
                columns_k = sorted(item[0] for item in gaps[k])
                if columns_k != list(range((k + 1) * step, (k + 1) * step + nx)):
                    return None
            for column, row, sign in sorted(gaps[k]):
                order.append(row)
                signs.append(sign)
                gap_columns.append(column)
            order.extend(lincon[k])
            signs.extend([1.0] * len(lincon[k]))
            gap_columns.extend([-1] * len(lincon[k]))
        return cls(np.asarray(order, dtype=np.int64), np.asarray(signs), [nx] * (T + 1),
                   [step - nx] * T + [0], [len(rows) for rows in lincon],
                   np.asarray(gap_columns, dtype=np.int64))


_LAYOUTS: OrderedDict[tuple[Any, ...], OCPRows] = OrderedDict()
"""HPIPM stage layouts by sparsity pattern (see :func:`stage_rows`)."""


def stage_rows(problem: Problem, form: TwoSidedForm) -> OCPRows:
    """HPIPM's layout of ``form``: :meth:`OCPRows.detect` (or one stage), found once per
    sparsity pattern, equality mask and horizon layout and reused with the signs of the
    current values (a controller's pattern never changes; the values do)."""
    matrix = sp.csr_matrix(form.matrix, copy=True)
    matrix.eliminate_zeros()
    layout = problem.meta.get("layout") if isinstance(problem.meta, dict) else None
    key = (matrix.shape, matrix.indptr.tobytes(), matrix.indices.tobytes(),
           (form.lower == form.upper).tobytes(), repr(layout))
    found = _LAYOUTS.get(key)
    if found is not None:
        _LAYOUTS.move_to_end(key)
        return found.resigned(form)
    rows = OCPRows.detect(problem, form) or OCPRows.one_stage(form)
    _LAYOUTS[key] = rows
    while len(_LAYOUTS) > CACHE_FUNCTIONS:
        _LAYOUTS.popitem(last=False)
    return rows


def as_dm(matrix: Any) -> Any:
    """``casadi.DM`` of a sparse matrix from its CSC arrays (4x faster than ``DM(scipy)``)."""
    import casadi

    csc = sp.csc_matrix(matrix)
    return casadi.DM(casadi.Sparsity(csc.shape[0], csc.shape[1], csc.indptr.tolist(),
                                     csc.indices.tolist()), csc.data)


class CasadiConicBackend(QPBackend):
    """``casadi.conic`` (Andersson et al. 2019) with ``lba <= [A; G] z <= uba`` and native
    bounds ``lbx <= z <= ubx``; the plugin is qpOASES (Ferreau et al. 2014) or HPIPM (Frison
    and Diehl 2020).

    CasADi's multipliers satisfy ``H z + g + A^T lam_a + lam_x = 0`` with ``lam > 0`` at an
    active upper side, i.e. qpsolvers' signs. For HPIPM the rows are reordered into the
    optimal-control layout of :class:`OCPRows` when the problem carries a horizon layout
    (the ``c3plus_qp`` / ``c3_qp`` families), and given as one stage otherwise; the
    ``diagnostics`` entry ``ocp_stages`` says which (``N + 1``).
    """

    package = "casadi"

    def __init__(self, plugin: str, description: str) -> None:
        self.plugin = plugin
        self.warm_support = (
            "emulated: CasADi's qpOASES has no public hotstart (a reused conic function "
            "hot-starts but cannot take new vectors apart from solving), and the initial "
            "guess has no effect on it (the same iterations from no guess, the answer or a "
            "guess 1e4 away): a warm cell is a cold solve (fresh function + solve)"
            if plugin == "qpoases" else
            "emulated: CasADi's HPIPM call re-initialises HPIPM every time (no update API); "
            "a warm cell pays setup + solve from the initial guess")
        self.name = f"casadi_{plugin}"
        self.description = description

    def require(self) -> None:
        """CasADi imports and loads the conic plugin."""
        casadi = require_module("casadi")
        try:
            present = bool(casadi.has_conic(self.plugin))
        except Exception as error:  # plugin loading may raise anything
            raise BackendUnavailable(
                f"CasADi cannot load plugin {self.plugin!r}: {error}") from error
        if not present:
            raise BackendUnavailable(f"CasADi has no conic plugin {self.plugin!r}")

    def options(self, settings: Settings, rows: OCPRows | None,
                warm: bool = False) -> dict[str, Any]:
        """Options of ``casadi.conic`` for the profile (``rows``: HPIPM's stage layout;
        ``warm``: a warm start is given)."""
        options: dict[str, Any] = {"error_on_fail": False, "verbose": False}
        if self.plugin == "qpoases":
            options.update(printLevel="none", CPUtime=float(settings.time_limit),
                           enableEqualities=True)
            if settings.sets_tolerance:
                options["terminationTolerance"] = settings.tolerance
            if settings.max_iterations is not None:
                options["nWSR"] = int(settings.max_iterations)
        elif self.plugin == "hpipm" and rows is not None:
            options["inf"] = HPIPM_INFINITY
            hpipm: dict[str, Any] = {"mode": "robust"}
            if settings.sets_tolerance:
                hpipm.update({key: settings.tolerance for key in
                              ("res_g_max", "res_b_max", "res_d_max", "res_m_max")})
            if settings.max_iterations is not None:
                hpipm["iter_max"] = int(settings.max_iterations)
            if warm:
                hpipm["warm_start"] = 1
            options.update(N=len(rows.nx) - 1, nx=rows.nx, nu=rows.nu, ng=rows.ng,
                           hpipm=hpipm)
        options.update(settings.options)
        return options

    def _function(self, P: sp.csc_matrix, M: sp.csc_matrix, H_dm: Any, M_dm: Any,
                  options: dict[str, Any]) -> tuple[Any, bool]:
        """The ``casadi.conic`` function for these sparsity patterns and options, and whether
        it was built now. qpOASES: always a new one (a reused one hot-starts). HPIPM: cached
        per pattern and options in this process (CasADi's HPIPM call keeps no state)."""
        import casadi

        key = (self.plugin, P.shape, P.indptr.tobytes(), P.indices.tobytes(), M.shape,
               M.indptr.tobytes(), M.indices.tobytes(), repr(options))
        if self.plugin == "hpipm" and key in _FUNCTIONS:
            _FUNCTIONS.move_to_end(key)
            return _FUNCTIONS[key], False
        with quiet_stdout():  # qpOASES prints a banner
            solver = casadi.conic("qp", self.plugin, {"h": H_dm.sparsity(),
                                                      "a": M_dm.sparsity()}, options)
        if self.plugin == "hpipm":
            _FUNCTIONS[key] = solver
            while len(_FUNCTIONS) > CACHE_FUNCTIONS:
                _FUNCTIONS.popitem(last=False)
        return solver, True

    def solve(self, problem: Problem, settings: Settings,
              warm_start: WarmStart | None = None) -> Result:
        """Convert, get the conic function (built, or HPIPM's cached one) and solve once."""

        watch = Stopwatch()
        with watch.lap("setup"):
            form = TwoSidedForm.from_problem(problem, bounds_as_rows=False)
            rows = None
            if self.plugin == "hpipm":
                rows = stage_rows(problem, form)
                matrix, lower, upper = rows.apply(form)
            else:
                matrix, lower, upper = form.matrix, form.lower, form.upper
            P_csc, M_csc = sp.csc_matrix(problem.P), sp.csc_matrix(matrix)
            H, M = as_dm(P_csc), as_dm(M_csc)
            arguments: dict[str, Any] = {
                "h": H, "g": problem.q, "a": M, "lba": lower, "uba": upper,
                "lbx": form.lb, "ubx": form.ub}
            warm = warm_start is not None and warm_start.x is not None
            if warm:
                assert warm_start is not None
                lam_a0 = form.stack_duals(warm_start.y, warm_start.z, warm_start.z_box)
                arguments["x0"] = np.asarray(warm_start.x, dtype=float)
                arguments["lam_a0"] = lam_a0 if rows is None else rows.permute(lam_a0)
            options = self.options(settings, rows, warm)
            solver, compiled = self._function(P_csc, M_csc, H, M, options)
        with watch.lap("solve"):
            output = solver(**arguments)
        stats = solver.stats()
        found = bool(stats.get("success", False))
        status = str(stats.get("return_status", stats.get("unified_return_status", "")))
        if self.plugin == "hpipm":
            status = f"{status} ({HPIPM_STATUS.get(status, 'unknown code')})"
        elif not found and "unified_return_status" in stats:
            status = f"{status} ({stats['unified_return_status']})"
        lam_a = np.asarray(output["lam_a"]).ravel()
        duals = form.split_duals(lam_a if rows is None else rows.restore(lam_a),
                                 np.asarray(output["lam_x"]).ravel())
        iterations = stats.get("iter_count")
        diagnostics = {"casadi_compiled": float(compiled)}
        if rows is not None:
            diagnostics["ocp_stages"] = float(len(rows.nx))
        x = np.asarray(output["x"]).ravel()
        if found and rows is not None:
            infinity = float(self.options(settings, rows, warm).get("inf", HPIPM_INFINITY))
            values = np.concatenate([x, matrix @ x])
            open_side = np.concatenate([~(np.isfinite(form.lb) & np.isfinite(form.ub)),
                                        ~(np.isfinite(lower) & np.isfinite(upper))])
            reach = float(np.max(np.abs(values[open_side]), initial=0.0))
            if reach >= 0.5 * infinity:
                found = False
                status = (f"{status}; solution reaches {reach:.3g}, near the finite stand-in "
                          f"{infinity:.3g} for infinite bounds")
        return qp_result(self.name, problem, watch, found=found, status=status,
                         failure=failure_category(status), x=x, duals=duals,
                         iterations=None if iterations is None else int(iterations),
                         diagnostics=diagnostics)


register(CasadiConicBackend(
    "qpoases", "qpOASES online active set (CasADi conic interface); a fresh solver per solve "
    "(a reused one hot-starts), so a cold solve walks ~60 active-set changes from scratch"))
register(CasadiConicBackend(
    "hpipm", "HPIPM interior point (CasADi conic interface, OCP stages); CasADi boxes every "
    "variable (+-1e6 here), so HPIPM iterates (~10) even on an equality-only QP"))
