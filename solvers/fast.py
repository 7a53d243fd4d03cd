"""Structure-exploiting, batched C3+: the ADMM around the Riccati QP step of :mod:`solvers.riccati`.

The QP step (``eta`` eliminated, Jacobi-scaled Riccati recursion split into a factorisation per
``rho`` and linear passes, the factor cache and the conditioning safeguards) is derived and
implemented in :mod:`c3bench.solvers.riccati`; its names are re-exported here.

**ADMM** (:class:`FastC3Plus`): the semantics of :mod:`solvers.c3`'s C3+ (``variant
"c3plus"``): QP step, closed-form projection of ``z + w`` (``x`` and ``u`` copied, each pair
``(lam_i, eta_i)`` keeps the larger of ``sqrt(rho_lam) [v_lam]_+`` and ``sqrt(rho_eta)
[v_eta]_+``, ties keep ``lam``), dual update ``w <- w + z - delta``, the rho schedule
(``geometric``, ``adaptive`` or ``residual_balancing`` via :func:`solvers.c3.rho_multiplier`)
with the scaled dual rescaled by ``rho_old / rho_new``, fixed iterations (or the residual
stopping rule), output ``u_0`` of ``delta`` clipped to the force limit, warm start by
:func:`solvers.c3.shift_warm_start` (:class:`FastC3PlusController`).

**Robust variant with shared inputs: a different splitting.** :func:`solvers.c3.solve_robust`
solves one stacked QP in which the samples share ``u_k``. Here the samples' QPs stay
decoupled and the consensus on ``u`` moves into the projection, which is still separable:

    delta = argmin sum_j p_j ||delta_j - (z_j + w_j)||^2_G  s.t.  delta_j in C_j,
            delta_{j,u} = u_bar  for every j,

gives the per-sample closed form for ``(lam, eta)``, ``delta_{j,x} = z_{j,x} + w_{j,x}`` and
``u_bar_k = sum_j p_j (z_{j,u_k} + w_{j,u_k})`` (a weighted mean; ``rho_u`` cancels); the
dual ``w_j <- w_j + z_j - delta_j`` then carries each sample's disagreement with ``u_bar``.
Both are consensus ADMM for the same robust problem; the iterates differ, but with ``n``
identical samples both reduce to the nominal controller (tested), and with ``n = 1`` this is
exactly :func:`solvers.c3.solve_c3`'s C3+ (tested against a high-accuracy QP backend).
With ``shared_inputs=False`` the samples are ``n`` independent C3+ problems (shared ``rho``).
"""

from __future__ import annotations

import math
import time
from collections.abc import Hashable, Mapping, Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from c3bench.problems.lcs import LCSBatch
from c3bench.problems.mpc import MPC, HorizonLayout
from c3bench.problems.names import BLOCKS, Block
from c3bench.solvers.admm.controller import FastC3PlusController, solve_batched
from c3bench.solvers.admm.kernel import KernelFailure, StepInputs
from c3bench.solvers.admm.options import C3Options
from c3bench.solvers.admm.projection import make_step_projection
from c3bench.solvers.admm.schedules import schedule_for
from c3bench.solvers.admm.solution import FastSolution, FastTimings
from c3bench.solvers.admm.stacked import box_of_step, projection_weight_vector
from c3bench.solvers.riccati import (
    FactorCache,
    RiccatiFactor,
    RiccatiOptions,
    factorize,
    solve_lq,
    swap_last,
)

__all__ = [
    "FactorCache",
    "FastC3Plus",
    "FastC3PlusController",
    "FastSolution",
    "FastTimings",
    "RiccatiFactor",
    "RiccatiOptions",
    "factorize",
    "fast_options",
    "project_c3plus_batch",
    "solve_lq",
]


# --- batched C3+ ADMM -------------------------------------------------------------------------
def project_c3plus_batch(v: np.ndarray, nx: int, nlam: int, nu: int, rho_lam: float,
                         rho_eta: float) -> np.ndarray:
    """C3+'s projection of steps ``v`` (..., ns) with scalar weights (no validation; any dtype).

    :func:`c3bench.solvers.admm.projection.make_step_projection` without limits or shared inputs.
    """
    project = make_step_projection(np, nx, nlam, nu)
    inf = np.full(nx + nu, np.inf, dtype=v.dtype)
    out: np.ndarray = project(v, np.sqrt(v.dtype.type(rho_lam)), np.sqrt(v.dtype.type(rho_eta)),
                              -inf, inf, None, False)
    return out


@dataclass
class _Prepared:
    """Per-LCS data in the working precision (independent of rho, x0, delta, w)."""

    uid: int
    A: np.ndarray
    Bv: np.ndarray
    d: np.ndarray
    M: np.ndarray  # (n, nlam, ny)
    MT: np.ndarray  # (n, 1, ny, nlam)
    c: np.ndarray  # (n, nlam)
    MtM: np.ndarray  # (n, ny, ny)


class FastC3Plus:
    """Batched C3+ ADMM for ``n`` LCS samples with a Riccati QP step (module docstring).

    Parameters
    ----------
    mpc
        Cost, goal, horizon and force limit (shared by all samples).
    options
        The controller options of :class:`solvers.c3.C3Options` (variant must be
        ``c3plus``; ``qp_backend`` and ``projection_backend`` are ignored; no input bounds).
    riccati
        Precision and safeguards of the QP step.
    shared_inputs
        Robust variant (samples share ``u``; consensus in the projection) or independent
        problems.
    cache
        Factorisation cache (a new one with 16 entries when ``None``).
    record_residuals
        Compute the consensus and dual residuals every iteration (always done when the
        schedule or the stopping rule needs them).
    prefactorize
        With the geometric schedule the rho of every iteration is known before the first
        one, so all iterations' factorisations are computed up front in one batched call
        over (iterations x samples) (:meth:`factors`): the same arithmetic, a tenth of the
        numpy calls. Other schedules factorise (or hit the cache) iteration by iteration.
    chunk_bytes
        Largest size of the factors computed by one batched call.
    """

    def __init__(self, mpc: MPC, options: C3Options | None = None,
                 riccati: RiccatiOptions | None = None, shared_inputs: bool = True,
                 cache: FactorCache | None = None, record_residuals: bool = False,
                 prefactorize: bool = True, chunk_bytes: int = 64 * 2**20) -> None:
        options = options or C3Options(keep_iterates=False)
        options.check_batched_c3plus("FastC3Plus")
        self.mpc = mpc
        self.options = options
        self.riccati = riccati or RiccatiOptions()
        self.shared_inputs = shared_inputs
        self.cache = cache if cache is not None else FactorCache()
        self.record_residuals = record_residuals
        self.prefactorize = prefactorize
        self.chunk_bytes = int(chunk_bytes)
        nx, nu = mpc.nx, mpc.nu
        self.nx, self.nu = nx, nu
        self._prepared: _Prepared | None = None
        self._vectors: dict[tuple[Any, ...], np.ndarray] = {}
        dtype = self.riccati.dtype
        Q, R, Qf = (np.asarray(m, dtype=np.float64) for m in (mpc.Q, mpc.R, mpc.Q_f))
        self._Q2 = 2 * Q
        self._R2 = 2 * R
        self._PT = (2 * Qf).astype(dtype)
        self._gx = (-2 * Q @ mpc.x_target).astype(dtype)
        self._gT = (-2 * Qf @ mpc.x_target).astype(dtype)
        self.timings = FastTimings()
        self.info: dict[str, Any] = {}
        self._hits0 = self._misses0 = 0

    # -- per LCS / per rho ---------------------------------------------------------------------
    def prepare(self, lcs: LCSBatch) -> _Prepared:
        """Working-precision LCS data, kept until another batch is given."""
        if self._prepared is not None and self._prepared.uid == lcs.uid:
            return self._prepared
        if lcs.nx != self.nx or lcs.nu != self.nu:
            raise ValueError(f"LCS (nx={lcs.nx}, nu={lcs.nu}) and MPC (nx={self.nx}, "
                             f"nu={self.nu}) disagree")
        dtype = self.riccati.dtype
        M = np.concatenate([lcs.E, lcs.F, lcs.H], axis=2).astype(dtype)
        prepared = _Prepared(
            uid=lcs.uid, A=lcs.A.astype(dtype),
            Bv=np.concatenate([lcs.D, lcs.B], axis=2).astype(dtype),
            d=lcs.d.astype(dtype), M=M, MT=np.ascontiguousarray(swap_last(M))[:, None],
            c=lcs.c.astype(dtype), MtM=swap_last(M) @ M)
        self._prepared = prepared
        return prepared

    def factor_key(self, lcs: LCSBatch, rho: Mapping[str, float]) -> tuple[Hashable, ...]:
        """Cache key: LCS identity, the four rho values, the horizon and the options."""
        return (lcs.uid, *(float(rho[key]) for key in BLOCKS), self.mpc.horizon,
                id(self.mpc), *self.riccati.key())

    def stage_hessian(self, prepared: _Prepared, rho: Mapping[str, float]) -> np.ndarray:
        """``H_y(rho)`` (n, ny, ny) of the C3+ stage cost (module docstring, step 1)."""
        nx, nlam, nu = self.nx, prepared.M.shape[1], self.nu
        ny = nx + nlam + nu
        base = np.zeros((ny, ny))
        base[:nx, :nx] = self._Q2 + 2 * rho[Block.X] * np.eye(nx)
        base[nx:nx + nlam, nx:nx + nlam] = 2 * rho[Block.LAM] * np.eye(nlam)
        base[nx + nlam:, nx + nlam:] = self._R2 + 2 * rho[Block.U] * np.eye(nu)
        Hy = prepared.MtM * (2 * rho[Block.ETA])
        Hy += base.astype(self.riccati.dtype)
        return Hy

    def factor(self, lcs: LCSBatch, rho: Mapping[str, float]) -> tuple[RiccatiFactor, bool]:
        """The factorisation for ``(lcs, rho)`` from the cache or new; ``(factor, hit)``."""
        return self.factors(lcs, [rho])[0]

    def factors(self, lcs: LCSBatch, rhos: Sequence[Mapping[str, float]]
                ) -> list[tuple[RiccatiFactor, bool]]:
        """Factorisations for several rho values: cached ones reused, the others computed in
        batched calls over (rho values x samples), at most ``chunk_bytes`` of factors per
        call; each new one is put into the cache. Returns ``(factor, hit)`` per rho."""
        keys = [self.factor_key(lcs, rho) for rho in rhos]
        out: list[tuple[RiccatiFactor, bool] | None] = []
        missing: list[int] = []
        for index, key in enumerate(keys):
            cached = self.cache.get(key)
            out.append(None if cached is None else (cached, True))
            if cached is None:
                missing.append(index)
        if missing:
            prepared = self.prepare(lcs)
            n = prepared.A.shape[0]
            itemsize = np.dtype(self.riccati.dtype).itemsize
            nv = prepared.Bv.shape[-1]
            per_rho = n * self.mpc.horizon * itemsize * (
                (nv + self.nx) * (2 * self.nx + nv) + self.nx)
            chunk = max(1, int(self.chunk_bytes // max(per_rho, 1)))
            for start in range(0, len(missing), chunk):
                part = missing[start:start + chunk]
                Hy = np.stack([self.stage_hessian(prepared, rhos[i]) for i in part])
                batched = factorize(prepared.A, prepared.Bv, prepared.d, Hy, self._PT,
                                    self.mpc.horizon, self.riccati)
                for j, index in enumerate(part):
                    factor = batched.take(j)
                    self.cache.put(keys[index], factor)
                    out[index] = (factor, False)
        return [entry for entry in out if entry is not None]

    def planned_rhos(self) -> Sequence[Mapping[str, float]] | None:
        """Every iteration's rho when the schedule does not depend on the data (geometric)."""
        return schedule_for(self.options).plan(self.options.rho0, self.options.admm_iterations)

    def layout_of(self, lcs: LCSBatch) -> HorizonLayout:
        """The C3+ step layout ``(x, lam, u, eta)`` of ``lcs``."""
        return HorizonLayout(lcs.nx, lcs.nlam, lcs.nu, lcs.nlam, self.mpc.horizon)

    def qp_step(self, lcs: LCSBatch, rho: Mapping[str, float], x0: np.ndarray,
                delta: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The QP step for every sample: ``(z_steps (n, T, ns), z_terminal (n, nx))``."""
        factor, _ = self.factor(lcs, rho)
        return self._qp_solve(self.prepare(lcs), factor, rho, x0, delta, w)

    def _qp_solve(self, prepared: _Prepared, factor: RiccatiFactor, rho: Mapping[str, float],
                  x0: np.ndarray, delta: np.ndarray, w: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray]:
        nx = self.nx
        nlam = prepared.M.shape[1]
        ny = nx + nlam + self.nu
        anchor = delta - w
        g2 = self._g2(rho, ny, nlam)
        gy = anchor[:, :, :ny] * g2
        gy[:, :, :nx] += self._gx
        eta_term = prepared.c[:, None, :] - anchor[:, :, ny:]
        gy += (prepared.MT @ eta_term[..., None])[..., 0] * (2 * rho[Block.ETA])
        xs, vs = solve_lq(factor, x0, gy, np.broadcast_to(self._gT, (gy.shape[0], nx)))
        ys = np.concatenate([xs[:, :-1], vs], axis=2)  # (n, T, ny)
        eta = (prepared.M[:, None] @ ys[..., None])[..., 0]
        eta += prepared.c[:, None, :]
        return np.concatenate([ys, eta], axis=2), xs[:, -1]

    def _g2(self, rho: Mapping[str, float], ny: int, nlam: int) -> np.ndarray:
        """``-2 G_y`` as a (ny,) vector in the working precision (memoised)."""
        key = ("g2", ny, nlam, rho[Block.X], rho[Block.LAM], rho[Block.U])
        out = self._vectors.get(key)
        if out is None:
            nx = self.nx
            out = np.empty(ny, dtype=self.riccati.dtype)
            out[:nx] = -2 * rho[Block.X]
            out[nx:nx + nlam] = -2 * rho[Block.LAM]
            out[nx + nlam:] = -2 * rho[Block.U]
            self._vectors[key] = out
        return out

    # -- the kernel of the one ADMM (solvers/admm/loop.py) -----------------------------------
    name = "riccati"

    @property
    def dtype(self) -> Any:
        return self.riccati.dtype

    def bind(self, lcs: LCSBatch) -> None:
        """Use ``lcs`` for the next control step (:func:`solvers.admm.solve_batched`)."""
        self.lcs = lcs
        self.layout = self.layout_of(lcs)
        self._project = make_step_projection(np, lcs.nx, lcs.nlam, lcs.nu)

    def start(self, inputs: StepInputs) -> None:
        """Per step: working-precision data, the box, and the planned factorisations."""
        lcs = self.lcs
        self.info = {}
        self._hits0, self._misses0 = self.cache.hits, self.cache.misses
        self._prepared_step = self.prepare(lcs)
        x0 = np.asarray(inputs.x0, dtype=np.float64)
        if not np.all(np.isfinite(x0)):
            raise KernelFailure("invalid input", "x0 has non-finite entries", True)
        self._x0 = x0.astype(self.dtype)
        self._p = np.asarray(inputs.weights).astype(self.dtype)
        self._shared = bool(inputs.shared_inputs and lcs.n_samples > 1)
        lower, upper = box_of_step(self.mpc, self.layout, self.options.use_limits)
        self._lower, self._upper = lower.astype(self.dtype), upper.astype(self.dtype)
        self._planned: dict[tuple[float, ...], RiccatiFactor] = {}
        plan = inputs.plan if self.prefactorize else None
        if plan:
            t0 = time.perf_counter()
            try:
                factors = self.factors(lcs, plan)
            except np.linalg.LinAlgError:
                factors = []  # factorise one by one to find the failing iteration
            for rho, (factor, _) in zip(plan, factors, strict=False):
                self._planned[tuple(float(rho[k]) for k in BLOCKS)] = factor
            self.timings.factor += time.perf_counter() - t0

    @property
    def step_cache_hits(self) -> int:
        return self.cache.hits - self._hits0

    @property
    def step_cache_misses(self) -> int:
        return self.cache.misses - self._misses0

    def iterate(self, rho: Mapping[str, float], delta: np.ndarray, w: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """QP step by the Riccati recursion, then the projection (box, pairs, shared mean)."""
        t0 = time.perf_counter()
        key = tuple(float(rho[k]) for k in BLOCKS)
        factor = self._planned.get(key)
        if factor is None:
            try:
                factor, _ = self.factor(self.lcs, rho)
            except np.linalg.LinAlgError as error:
                raise KernelFailure("QP factorisation failed", str(error)) from None
        t1 = time.perf_counter()
        steps, terminal = self._qp_solve(self._prepared_step, factor, rho, self._x0, delta, w)
        t2 = time.perf_counter()
        self.timings.factor += t1 - t0
        self.timings.qp_solve += t2 - t1
        if not (math.isfinite(float(steps.sum())) and math.isfinite(float(terminal.sum()))):
            raise KernelFailure("non-finite QP solution", "", True)
        U = projection_weight_vector(self.options, self.layout, rho).astype(self.dtype)
        lam_s, eta_s = self.layout.index(0, Block.LAM), self.layout.index(0, Block.ETA)
        new_delta = self._project(steps + w, np.sqrt(U[lam_s]), np.sqrt(U[eta_s]), self._lower,
                                  self._upper, self._p, self._shared)
        self.timings.projection += time.perf_counter() - t2
        return steps, terminal, new_delta

    def solve(self, lcs: LCSBatch, x0: np.ndarray, weights: Sequence[float] | None = None,
              delta: np.ndarray | None = None, w: np.ndarray | None = None,
              fallback_input: np.ndarray | None = None, trusted_iterates: bool = False
              ) -> FastSolution:
        """One control step of the one ADMM (:func:`c3bench.solvers.admm.solve_batched`).

        Parameters
        ----------
        lcs
            The samples' LCS, linearised at ``x0``.
        x0
            Measured state (nx,).
        weights
            Sample weights (normalised and floored); uniform when ``None``.
        delta, w
            Initial iterates (n, T, ns) or (T, ns); cold start when ``None``.
        fallback_input
            Returned with ``ok=False`` when the step fails (zero when ``None``).
        trusted_iterates
            ``delta`` and ``w`` are a controller's own warm start, used unchecked
            (:func:`c3bench.solvers.admm.loop.initial_iterates`).
        """
        return solve_batched(self, lcs, self.mpc, x0, self.options, weights, delta, w,
                             fallback_input, self.shared_inputs, self.record_residuals,
                             trusted_iterates)


def fast_options(**changes: Any) -> C3Options:
    """The reference study's C3+ options for :class:`FastC3Plus` (no iterate keeping)."""
    return replace(C3Options(keep_iterates=False), **changes)
