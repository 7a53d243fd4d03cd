"""The compiled (numba) C3+ kernel: QP step and projection of one ADMM iteration.

One ADMM loop (dual update, residuals, rho schedule, stopping, output) calls a *kernel* per
iteration; :class:`CompiledC3PlusKernel` is the compiled one for the C3+ variant. Its maths is
:class:`solvers.fast.FastC3Plus`'s (eliminate ``eta``, Jacobi-scaled Riccati recursion split
into a factorisation and linear passes, closed-form projection, shared-input mean; see the
module docstrings of :mod:`solvers.fast`, :mod:`solvers.admm.compiled_kernels` and
:mod:`solvers.admm.compiled_passes`), compiled
with numba (Lam, Pitrou & Seibert, "Numba: a LLVM-based Python JIT compiler", LLVM-HPC 2015):

* :meth:`CompiledC3PlusKernel.start` assembles the LCS batch in the working precision into
  preallocated arrays (one compiled call, :func:`kernels.assemble`) and takes a geometric
  schedule's plan (``planned_rhos``, known before the first iteration);
* the first iteration of each *group* of the plan (:func:`plan_group` rho values: at most
  :data:`~c3bench.solvers.admm.compiled_factors.GROUP_LANES` lanes, rho x sample pairs)
  factorises the whole group for every sample in ONE compiled call, in place in a
  preallocated buffer (lanes last), which stays in the core's cache for the group's
  iterations; its backward steps run as code generated for the batch's
  structure (:mod:`.compiled_codegen`, bit for bit the lane loops' results) where there is
  some;
* :meth:`CompiledC3PlusKernel.step` runs the gradient, both linear passes, ``eta``, the
  projection of ``v = z + w``, (shared inputs, ``n > 1``) ``delta_u = sum_j p_j v_{j,u}``
  and the loop's dual update (:func:`c3bench.solvers.admm.loop.dual_update`, compiled) in
  ONE compiled call (:meth:`~CompiledC3PlusKernel.iterate` is the same call without the
  dual); a rho outside the plan is factorised on the fly (one call) and kept in a small
  cache keyed by the rho values;
* :meth:`CompiledC3PlusKernel.run_plan` runs a whole plan (every group's factorisation, every
  iteration and the loop's dual rescaling between them) in ONE compiled call
  (:mod:`.compiled_plan`), which the loop uses for a geometric schedule with ``fixed``
  stopping and nothing recorded per iteration.

JIT compilation happens once per process, cached on disk (43-53 s from scratch on 2 cores,
0.3-0.4 s from the cache; :func:`c3bench.solvers.admm.compiled_solver.warm_up` compiles every
signature), the generated code once per structure and machine; ``compile_seconds`` is the time
both took in this process, so that step timings can exclude it. numba checks a cached function
against its own source file only: after editing one kernel module, clear
``__pycache__/*.nb[ic]`` so that the functions calling it from other modules compile again.

Differences from :class:`solvers.fast.FastC3Plus`: ``Q_vv`` is factorised by Cholesky (a
``Q_vv`` that is not positive definite raises :class:`KernelFailure`; numpy's inverse would
accept an indefinite one); results agree to rounding (tested to 1e-9 relative in float64).
"""

from __future__ import annotations

import math
import time
from collections import OrderedDict
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, NamedTuple

import numpy as np

from c3bench.problems.errors import InputError
from c3bench.problems.lcs import LCSBatch
from c3bench.problems.mpc import MPC
from c3bench.problems.names import Block, Precision
from c3bench.solvers.admm import compiled_codegen as codegen
from c3bench.solvers.admm import compiled_kernels as kernels
from c3bench.solvers.admm import compiled_passes as passes
from c3bench.solvers.admm import compiled_plan
from c3bench.solvers.admm.compiled_factors import (
    CompiledFactors,
    aligned_empty,
    factor_failure,
    plan_group,
    rho_key,
)
from c3bench.solvers.admm.compiled_generated import GeneratedCode
from c3bench.solvers.admm.kernel import KernelFailure, PlanRun
from c3bench.solvers.admm.schedules import is_frozen
from c3bench.solvers.fast import RiccatiOptions

__all__ = ["CompiledC3PlusKernel", "KernelFailure"]

OFF_PLAN_CACHE = 4
"""How many off-plan factorisations :class:`CompiledC3PlusKernel` keeps (by rho values)."""
STRUCTURE_CACHE = 16
"""How many structures of ``[A B_v d]`` (:func:`kernels.structure`, about 0.2 ms to build
with its flop counts) :class:`CompiledC3PlusKernel` keeps, by mask: along a push the
contacts switch a few entries on and off, so the same masks come back."""


class _Entry(NamedTuple):
    """One factorised rho: where its factors are, its constants and, when its factorisation
    failed, why (raised by :meth:`CompiledC3PlusKernel.step` and ``iterate``)."""

    factors: CompiledFactors
    slot: int
    consts: np.ndarray
    failure: str | None


class CompiledC3PlusKernel:
    """C3+ QP step, projection and dual update compiled with numba (module docstring).

    Parameters
    ----------
    mpc
        Cost, goal and horizon.
    precision
        Working precision of every array and of the arithmetic (overrides ``riccati``'s).
    riccati
        ``jacobi`` (default on) and ``ridge`` are honoured; ``S_k`` is symmetric by
        construction (``symmetrize`` has no effect); ``rollout=True`` is not supported.
    box
        ``(lower, upper)`` box of one step's ``(x, u)`` (length ``nx + nu`` each, ``+-inf``
        where unbounded) that the projection clips to (e.g.
        :func:`c3bench.solvers.admm.stacked.box_of_step`); ``None``: no box.
    """

    name = "compiled"

    def __init__(self, mpc: MPC, precision: Precision = Precision.FLOAT64,
                 riccati: RiccatiOptions | None = None,
                 box: tuple[np.ndarray, np.ndarray] | None = None) -> None:
        riccati = riccati or RiccatiOptions()
        if riccati.rollout:
            raise InputError("the compiled kernel does not support RiccatiOptions(rollout=True)")
        self.mpc = mpc
        self.precision = Precision(precision)
        self.riccati = riccati
        self.dtype: np.dtype[Any] = self.precision.dtype
        self.nx, self.nu = int(mpc.nx), int(mpc.nu)
        scalar = self.dtype.type
        self._zero, self._one = scalar(0), scalar(1)
        self._ridge = scalar(riccati.ridge)
        Q, R, Qf = (np.asarray(a, dtype=np.float64) for a in (mpc.Q, mpc.R, mpc.Q_f))
        self._Q2, self._R2 = 2 * Q, 2 * R
        self._PT = np.ascontiguousarray(2 * Qf, dtype=self.dtype)
        self._vectors = np.zeros((3, self.nx), self.dtype)  # x0, g_x = -2 Q x*, g_T
        self._vectors[1] = -2 * Q @ mpc.x_target
        self._vectors[2] = -2 * Qf @ mpc.x_target
        self._box = np.empty((2, self.nx + self.nu), self.dtype)
        self.set_box(box)
        self.projection_weights: Mapping[str, float] | None = None
        """``U`` by block for the pairs' closed form (``None``: ``G(rho)``)."""
        self._shape: tuple[int, ...] = ()
        self._step_shape: tuple[int, ...] = ()
        self._arrays: dict[str, np.ndarray] = {}
        self._planned: CompiledFactors | None = None
        """Buffer of one group of the plan (:func:`plan_group` rho values)."""
        self._plan: Sequence[Mapping[str, float]] = ()
        self._plan_index: dict[tuple[float, ...], int] = {}
        self._plan_keys: list[tuple[float, ...]] = []
        self._entries: dict[tuple[float, ...], _Entry] = {}
        """The rho values whose factors are in the group buffer now."""
        self.factor_seconds = 0.0
        """Seconds spent in factorisations so far (compile time included)."""
        self._off_plan: OrderedDict[tuple[float, ...], _Entry] = OrderedDict()
        self._rho_constants: dict[tuple[float, ...], tuple[np.ndarray, np.ndarray]] = {}
        self._stacked: dict[tuple[tuple[float, ...], ...],
                            tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
        self._p = np.ones(1, self.dtype)
        self._structure_key: tuple[Any, ...] | None = None
        self._structures: OrderedDict[tuple[Any, ...], tuple[kernels.Structure, int, int]] = \
            OrderedDict()
        """Recent structures with their flop counts, by mask (:data:`STRUCTURE_CACHE`)."""
        self._structure: kernels.Structure | None = None  # the batch's, set by start()
        self._lane_flops = self._sample_flops = 0
        self.flops = 0.0
        """Floating-point operations executed since the last :meth:`start` (the batch's
        :func:`kernels.assemble_flops` per sample; factorisations: :func:`kernels.factor_flops`
        and :func:`kernels.setup_flops` per rho value and sample; iterations:
        :func:`passes.solve_flops` per sample, with shared inputs ``2 nu`` more per sample and
        step for the weighted mean; a planned run's dual rescalings, one product per entry),
        over the structural nonzeros."""
        self._shared = False
        self._generated = GeneratedCode()
        self._plan_stacked: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
        self._called: set[Any] = set()
        """Compiled functions this kernel has called (compiled for its precision by then)."""
        self._plan_args: tuple[tuple[Any, ...], tuple[Any, ...], tuple[Any, ...]] | None = None
        """The objects :meth:`_plan_arguments` last gathered its arguments from, and those."""

    def set_box(self, box: tuple[np.ndarray, np.ndarray] | None) -> None:
        """The ``(lower, upper)`` box of one step's ``(x, u)`` (``None``: unbounded)."""
        self._box[0], self._box[1] = (-np.inf, np.inf) if box is None else box
        if np.any(np.isnan(self._box)) or np.any(self._box[0] > self._box[1]):
            raise InputError("box must have lower <= upper and no NaN")

    # -- per control step ----------------------------------------------------------------------
    def start(self, lcs: LCSBatch, x0: np.ndarray, weights: np.ndarray, shared_inputs: bool,
              planned_rhos: Sequence[Mapping[str, float]] | None) -> None:
        """Take the control step's LCS batch, state, weights and plan (factorised a group at
        a time by :meth:`step`).

        Raises :class:`KernelFailure` on a non-finite ``x0`` and :class:`InputError` on
        dimensions that disagree with the MPC or weights of the wrong shape. A planned rho
        whose factorisation fails raises when :meth:`iterate` reaches it.
        """
        if lcs.nx != self.nx or lcs.nu != self.nu:
            raise InputError(f"LCS (nx={lcs.nx}, nu={lcs.nu}) and MPC (nx={self.nx}, "
                             f"nu={self.nu}) disagree")
        x0 = np.asarray(x0, dtype=np.float64)
        if x0.shape != (self.nx,):
            raise InputError(f"x0 must have shape ({self.nx},), got {x0.shape}")
        if not all(map(math.isfinite, x0.tolist())):  # nx entries: cheaper than numpy's
            raise KernelFailure("invalid input", "x0 has non-finite entries", True)
        n = lcs.n_samples
        p = np.asarray(weights, dtype=np.float64)
        if p.shape != (n,):
            raise InputError(f"weights must have shape ({n},), got {p.shape}")
        self._entries = {}
        self._off_plan.clear()
        self.flops = 0.0
        self._convert(lcs)
        self._vectors[0] = x0
        self._p = p if p.dtype == self.dtype and p.flags.c_contiguous else \
            np.ascontiguousarray(p, dtype=self.dtype)  # read, never written
        self._shared = bool(shared_inputs)
        plan = planned_rhos or ()
        if plan is not self._plan or not is_frozen(plan):  # a frozen plan's keys are known
            self._plan_stacked = None
            self._plan_keys = [rho_key(rho) for rho in plan]
            self._plan_index = {}
            for i in range(len(plan) - 1, -1, -1):  # a repeated rho: its first place
                self._plan_index[self._plan_keys[i]] = i
        self._plan = plan  # as given: run_plan knows it by identity
        if self._plan:
            group = plan_group(n, len(self._plan))
            if self._planned is None or self._planned.shape != (group, n, self.mpc.horizon):
                self._planned = self._allocate(group)

    def iterate(self, rho: Mapping[str, float], delta: np.ndarray, w: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """One QP step and projection: ``(z_steps (n, T, ns), z_terminal (n, nx), new_delta
        (n, T, ns))``, new arrays; :class:`KernelFailure` when the factorisation of ``rho``
        failed or the QP solution is not finite."""
        z_steps, z_terminal, new_delta, _ = self.step(rho, delta, w)
        return z_steps, z_terminal, new_delta

    def step(self, rho: Mapping[str, float], delta: np.ndarray, w: np.ndarray
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """One whole ADMM iteration in one compiled call: :meth:`iterate`'s three arrays and
        the dual update ``new_w = w + z_steps - new_delta`` (the loop's
        :func:`c3bench.solvers.admm.loop.dual_update`, compiled); new arrays every call."""
        pattern = self.structure  # raises before start()
        key = rho_key(rho)
        entry = self._entries.get(key)
        if entry is None:
            index = self._plan_index.get(key)
            entry = self._off_plan_entry(key, rho) if index is None else \
                self._planned_entry(key, index)
        if entry.failure is not None:
            raise KernelFailure("QP factorisation failed", entry.failure)
        dtype, shape = self.dtype, self._step_shape
        delta, w = self._checked(delta), self._checked(w)
        out = np.empty((3, *shape), dtype)  # z_steps, new_delta, new_w
        z_terminal = np.empty((shape[0], self.nx), dtype)
        f = entry.factors
        args = (self._vectors, delta, w, self._arrays["Mc"], self._arrays["Mt"], entry.consts,
                f.Y, f.L, f.Sd, f.D, f.ABd, entry.slot, pattern.column_start, pattern.column_rows,
                pattern.row_start, pattern.row_columns, self._p, self._shared, self._box,
                self._zero, out[0], z_terminal, out[1], out[2], self._passes(f))
        ok = self._timed(passes.solve_project, *args)
        self.flops += shape[0] * self._iteration_flops()
        if not ok:
            raise KernelFailure("non-finite QP solution", f"rho={dict(rho)}", True)
        return out[0], z_terminal, out[1], out[2]

    def run_plan(self, plan: Sequence[Mapping[str, float]], ratios: np.ndarray,
                 delta: np.ndarray, w: np.ndarray) -> PlanRun:
        """Every iteration of the plan given to :meth:`start` in ONE compiled call
        (:func:`compiled_plan.run_plan`: the group factorisations, :meth:`step`'s iteration
        with ``plan[i]``, then the loop's rescaling by ``ratios[i]``); the iterates are new
        arrays. A failed iteration ends the run with the last completed one's iterates and
        the :class:`KernelFailure` :meth:`step` would raise."""
        pattern = self.structure  # raises before start()
        if self._planned is None or (plan is not self._plan and
                                     [rho_key(rho) for rho in plan] != self._plan_keys):
            raise InputError("run_plan needs the plan given to start()")
        delta, w = self._checked(delta), self._checked(w)
        if self._plan_stacked is None:  # known while the same frozen plan comes back
            self._plan_stacked = self._stack(self._plan, self._plan_keys)[1]
        shape = self._step_shape  # new arrays every step: the PlanRun's arrays are views
        iterates = np.empty((3, *shape), self.dtype)
        terminal = np.empty((shape[0], self.nx), self.dtype)
        f = self._planned
        self._entries = {}  # the group buffer is overwritten
        head, tail = self._plan_arguments(pattern, len(plan))
        completed, code = self._timed(compiled_plan.run_plan, *head, self._p, self._shared,
                                      self._box, ratios, delta, w, iterates, terminal, *tail)
        group, n = f.shape[0], len(self._p)
        attempted = min(completed + (code != 0), len(plan))  # the failed one included
        factorised = min(-(-attempted // group) * group, len(plan))  # whole groups
        solved = completed + (code == compiled_plan.NON_FINITE)
        rescaled = min(completed, len(plan) - 1)  # run_plan rescales after all but the last
        self.flops += n * (factorised * self._lane_flops + solved * self._iteration_flops()
                           + rescaled * shape[1] * shape[2])
        failure = None
        if code == compiled_plan.FACTORISATION_FAILED:
            failure = KernelFailure("QP factorisation failed",
                                    factor_failure(f, completed % group, plan[completed]) or "")
        elif code == compiled_plan.NON_FINITE:
            failure = KernelFailure("non-finite QP solution", f"rho={dict(plan[completed])}",
                                    True)
        done = completed > 0
        return PlanRun(completed, iterates[0], iterates[1], iterates[2] if done else None,
                       terminal if done else None, failure)

    # -- internals -----------------------------------------------------------------------------
    def _plan_arguments(self, pattern: kernels.Structure, planned: int
                        ) -> tuple[tuple[Any, ...], tuple[Any, ...]]:
        """The arguments of :func:`compiled_plan.run_plan` before ``p`` and after ``terminal``:
        the same objects while the shapes, the plan, the structure and the group buffer stay
        (remembered with the objects they were made from, compared by identity, the planned
        count by value), so that a control step does not gather them again."""
        assert self._planned is not None and self._plan_stacked is not None
        f, a = self._planned, self._arrays
        jacobi = bool(self.riccati.jacobi)
        known = self._plan_args
        if known is not None:  # element by element, written out: this runs every step
            was = known[0]
            if was[0] is a and was[1] is self._plan_stacked and was[2] is pattern and \
                    was[3] is f and was[4] is self._structure_key and was[5] == planned and \
                    was[6] is jacobi:
                return known[1], known[2]
        sources = (a, self._plan_stacked, pattern, f, self._structure_key, planned, jacobi)
        bases, two_rho_eta, consts = self._plan_stacked
        head = (a["A"], a["Bv"], a["d"], a["MtM"], bases, two_rho_eta, self._PT, self._ridge,
                jacobi, self._zero, self._one, pattern.column_start,
                pattern.column_rows, pattern.row_start, pattern.row_columns, f.Y, f.L, f.Sd,
                f.D, f.ABd, f.failed, self._vectors, a["Mc"], a["Mt"], consts)
        tail = (self._steps(f.shape[0], planned % f.shape[0] or f.shape[0]), self._passes(f))
        self._plan_args = (sources, head, tail)
        return head, tail

    def _iteration_flops(self) -> int:
        """Flops of one iteration per sample: :func:`passes.solve_flops` (in
        ``_sample_flops``) and, with shared inputs over several samples, the weighted mean of
        ``u``: a multiply-add per sample, input and step."""
        n, _, _, nu = self._shape
        mean = 2 * nu * self.mpc.horizon if self._shared and n > 1 else 0
        return self._sample_flops + mean

    def _checked(self, array: np.ndarray) -> np.ndarray:
        """``delta`` or ``w`` in the working precision, C-contiguous, of the step's shape."""
        if array.dtype != self.dtype or not array.flags.c_contiguous:
            array = np.ascontiguousarray(array, dtype=self.dtype)
        if array.shape != self._step_shape:
            raise InputError(f"delta and w must have shape {self._step_shape}, got "
                             f"{array.shape}")
        return array

    def _convert(self, lcs: LCSBatch) -> None:
        """LCS data in the working precision, into buffers reused when the shapes repeat."""
        n, nx, nlam, nu = lcs.n_samples, self.nx, lcs.nlam, self.nu
        nv = nlam + nu
        ny = nx + nv
        shape = (n, nx, nlam, nu)
        if shape != self._shape:
            dt = self.dtype
            self._arrays = {"A": np.empty((nx, nx, n), dt), "Bv": np.empty((nx, nv, n), dt),
                            "d": np.empty((nx, n), dt), "Mc": np.empty((n, nlam, ny + 1), dt),
                            "Mt": aligned_empty((nlam, ny + 1, n), dt),  # the passes read it
                            "MtM": np.empty((ny, ny, n), dt)}  # samples last but Mc
            self._shape = shape
            self._step_shape = (n, self.mpc.horizon, ny + nlam)
            self._planned = None
            self._rho_constants.clear()
            self._stacked.clear()
            self._plan_stacked = None
        a = self._arrays
        self.flops += n * kernels.assemble_flops(nx, nlam, nu)
        mask = np.empty((nx, ny + 1), dtype=np.bool_)
        self._timed(kernels.assemble, lcs.A, lcs.B, lcs.D, lcs.d, lcs.E, lcs.F, lcs.H, lcs.c,
                    self._zero, a["A"], a["Bv"], a["d"], a["Mc"], a["Mt"], a["MtM"], mask)
        key = (mask.shape, mask.tobytes(), self.mpc.horizon)
        if key != self._structure_key:  # contacts switch entries on and off: keep a few
            known = self._structures.get(key)
            if known is None:
                T = self.mpc.horizon
                pattern = kernels.structure(mask)
                known = (pattern, T * kernels.factor_flops(nx, nv, pattern)
                         + kernels.setup_flops(nx, nv),
                         T * passes.solve_flops(nx, nv, nlam, pattern))
                self._structures[key] = known
                while len(self._structures) > STRUCTURE_CACHE:
                    self._structures.popitem(last=False)
            else:
                self._structures.move_to_end(key)
            self._structure_key = key
            self._structure, self._lane_flops, self._sample_flops = known

    def _allocate(self, m: int) -> CompiledFactors:
        n, nx, nlam, nu = self._shape
        return CompiledFactors.empty(m, n, self.mpc.horizon, nx, nlam + nu, self.dtype)

    def _entry(self, rho: Mapping[str, float], key: tuple[float, ...],
               factors: CompiledFactors, slot: int) -> _Entry:
        """The entry of ``rho``, factorised in ``slot`` of ``factors``: its constants and, when
        a sample's factorisation failed, why."""
        return _Entry(factors, slot, self._constants(rho, key)[1],
                      factor_failure(factors, slot, rho))

    def _planned_entry(self, key: tuple[float, ...], index: int) -> _Entry:
        """Factorise the plan's group holding place ``index`` into the group buffer (one
        compiled call) and make its rho values the current entries."""
        assert self._planned is not None
        size = self._planned.shape[0]
        first = index // size * size
        rhos = self._plan[first:first + size]
        keys = self._factorize(rhos, self._planned)
        self._entries = {}
        for i in range(len(keys) - 1, -1, -1):
            self._entries[keys[i]] = self._entry(rhos[i], keys[i], self._planned, i)
        return self._entries[key]

    def _off_plan_entry(self, key: tuple[float, ...], rho: Mapping[str, float]) -> _Entry:
        """A rho outside the plan: factorised now, or from the small cache."""
        entry = self._off_plan.get(key)
        if entry is None:
            factors = self._allocate(1)
            self._factorize([rho], factors)
            entry = self._entry(rho, key, factors, 0)
            self._off_plan[key] = entry
            while len(self._off_plan) > OFF_PLAN_CACHE:
                self._off_plan.popitem(last=False)
        else:
            self._off_plan.move_to_end(key)
        return entry

    def _base(self, rho: Mapping[str, float]) -> np.ndarray:
        """``blockdiag(2Q + 2 rho_x I, 2 rho_lam I, 2R + 2 rho_u I)`` (float64)."""
        nx, nlam, nu = self.nx, self._shape[2], self.nu
        ny = nx + nlam + nu
        base = np.zeros((ny, ny))
        base[:nx, :nx] = self._Q2 + 2 * rho[Block.X] * np.eye(nx)
        base[nx:nx + nlam, nx:nx + nlam] = 2 * rho[Block.LAM] * np.eye(nlam)
        base[nx + nlam:, nx + nlam:] = self._R2 + 2 * rho[Block.U] * np.eye(nu)
        return base

    def _factorize(self, rhos: Sequence[Mapping[str, float]], out: CompiledFactors
                   ) -> list[tuple[float, ...]]:
        """Factorise ``rhos`` for every sample into ``out`` (one compiled call); returns the
        rho keys."""
        keys, stacked = self._stack(rhos)
        a = self._arrays
        started = time.perf_counter()
        self._timed(kernels.factorize_batch, a["A"], a["Bv"], a["d"], a["MtM"], stacked[0],
                    stacked[1], self._PT, self._ridge, bool(self.riccati.jacobi), self._zero,
                    self._one, self.structure.column_start, self.structure.column_rows, out.Y,
                    out.L, out.Sd, out.D, out.ABd, out.failed, self._steps(len(rhos)))
        self.factor_seconds += time.perf_counter() - started
        self.flops += len(rhos) * a["A"].shape[2] * self._lane_flops
        return keys

    def _stack(self, rhos: Sequence[Mapping[str, float]],
               keys: list[tuple[float, ...]] | None = None
               ) -> tuple[list[tuple[float, ...]], tuple[np.ndarray, np.ndarray, np.ndarray]]:
        """The rho keys (given, or computed) and, stacked over ``rhos`` in the working
        precision (memoised), ``(bases (m, ny, ny), 2 rho_eta (m,), consts (m, ny + 3))``
        (:meth:`_constants`)."""
        keys = keys if keys is not None else [rho_key(rho) for rho in rhos]
        key = tuple(keys)
        stacked = self._stacked.get(key)
        if stacked is None:
            pairs = [self._constants(rho, k) for rho, k in zip(rhos, keys, strict=True)]
            stacked = (np.stack([base for base, _ in pairs]).astype(self.dtype),
                       np.array([2 * rho[Block.ETA] for rho in rhos], dtype=self.dtype),
                       np.stack([consts for _, consts in pairs]))
            if len(self._stacked) >= 8:
                self._stacked.clear()
            self._stacked[key] = stacked
        return keys, stacked

    def _constants(self, rho: Mapping[str, float], key: tuple[float, ...]
                   ) -> tuple[np.ndarray, np.ndarray]:
        """``(base (ny, ny) float64, consts)`` of ``rho`` (memoised by the rho values for the
        current shapes): ``consts = (-2 G_y (ny,), 2 rho_eta, sqrt(rho_lam), sqrt(rho_eta))`` in the
        working precision (:func:`passes.solve_project`)."""
        entry = self._rho_constants.get(key)
        if entry is None:
            nx, nlam = self.nx, self._shape[2]
            ny = nx + nlam + self.nu
            consts = np.empty(ny + 3, dtype=self.dtype)
            consts[:nx] = -2 * rho[Block.X]
            consts[nx:nx + nlam] = -2 * rho[Block.LAM]
            consts[nx + nlam:ny] = -2 * rho[Block.U]
            U = self.projection_weights if self.projection_weights is not None else rho
            consts[ny:] = (2 * rho[Block.ETA], math.sqrt(U[Block.LAM]), math.sqrt(U[Block.ETA]))
            entry = (self._base(rho), consts)
            if len(self._rho_constants) >= 64:
                self._rho_constants.clear()
            self._rho_constants[key] = entry
        return entry

    def _steps(self, *slots: int) -> np.ndarray:
        """:meth:`GeneratedCode.steps` for ``slots`` rho values at a time."""
        n, nx, nlam, nu = self._shape
        return self._generated.steps(self._structure_key, self.structure, n, nx, nlam + nu,
                                     self.dtype, slots)

    def _passes(self, factors: CompiledFactors) -> np.ndarray:
        """:meth:`GeneratedCode.passes` for ``factors``."""
        n, nx, nlam, nu = self._shape
        return self._generated.passes(self._structure_key, self.structure, n, nx, nlam + nu,
                                      nlam, self.mpc.horizon, factors.Y.shape[3], self.dtype)

    @property
    def structure(self) -> kernels.Structure:
        """The structural nonzeros of the current batch's ``[A B_v d]`` (after :meth:`start`;
        every product with it skips the rest)."""
        if self._structure is None:
            raise InputError("call start() before iterate()")
        return self._structure

    @property
    def compile_seconds(self) -> float:
        """JIT and code-generation time spent in this process so far (every kernel instance,
        :func:`warm_up` and :data:`codegen.CODEGEN` together; exclude it from step timings)."""
        return _JIT.seconds + codegen.CODEGEN.seconds

    def _timed(self, function: Any, *args: Any) -> Any:
        """Call a compiled function; its first call in this process for this precision
        counts as compile time (numba compiles, or loads from its disk cache, inside it)."""
        if function in self._called:  # known compiled: no key to build and hash
            return function(*args)
        key = (function.__name__, self.precision)
        if key in _JIT.compiled:
            self._called.add(function)
            return function(*args)
        started = time.perf_counter()
        result = function(*args)
        _JIT.seconds += time.perf_counter() - started
        _JIT.compiled.add(key)
        self._called.add(function)
        return result


@dataclass
class _JitRecord:
    """Kernels (name, precision) compiled in this process and their first calls' seconds."""

    compiled: set[tuple[str, Precision]] = field(default_factory=set)
    seconds: float = 0.0


_JIT = _JitRecord()
