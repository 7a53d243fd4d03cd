"""The batched C3+ control step compiled with JAX (optional: ``pip install c3bench[jax]``).

A kernel of the one ADMM (:mod:`c3bench.solvers.admm.loop` drives it): the QP step of
:mod:`solvers.fast` (read its docstring for the formulas: ``eta`` eliminated, a Riccati
recursion over ``T`` steps for every sample) and the projection
(:func:`c3bench.solvers.admm.projection.make_step_projection` in ``jax.numpy``: pairs, box
limits, shared-input mean) fused into **one** ``jax.jit`` compiled call per ADMM iteration,
so one iteration is one XLA executable whatever the number of samples (the ``T`` time steps
of the Riccati recursion and of the rollout are ``lax.scan`` loops, ``unroll`` sets their
unrolling; every operation acts on all samples at once). The arrays stay on the device
between iterations; the loop's dual update is one more device operation. With a geometric
schedule, ``fixed`` stopping and nothing recorded per iteration, the loop hands the kernel
the whole plan (:meth:`JaxC3Plus.run_plan`): the iterations and the loop's dual rescaling
run as one ``lax.scan``, ONE device call per control step instead of one per iteration
(meant for GPUs, where each call costs a launch; CPU timings in ``docs/admm.md``).

Differences from the numpy path (same mathematics, different arrangement):

* the factorisation and the linear passes are fused per iteration (rho is a traced value, so
  a new rho costs no recompilation);
* the gains are kept factored: ``Q_vv = L L^T`` by an unrolled Cholesky factorisation
  (``nv = 8``: straight-line code in which every scalar operation acts on the vector of one
  entry over all samples; a non-positive pivot gives NaN, which fails the step instead of
  returning a wrong answer), ``[W | w] = L^-1 [Q_vx | q_v]`` by forward substitution, the
  cost-to-go ``S = Q_xx - W^T W``, ``s = q_x - W^T w``, and the forward pass applies
  ``v = -L^-T (W x + w)`` (the same ``K = -Q_vv^-1 Q_vx``, ``kk = -Q_vv^-1 q_v`` without the
  back substitution of the 11 right-hand sides in the backward pass; this arrangement, and
  dividing in a way that XLA does not fuse and recompute (:func:`forward_substitution`),
  made the control step 1.2 to 1.7 times faster on one CPU core than the former ``vmap``
  of a per-sample Cholesky solve, most at 256 samples);
* timings cannot be split inside a compiled call: :class:`solvers.fast.FastTimings` reports
  the QP step and projection as ``qp_solve``;
* non-finite values are checked once, after the last iteration (a check per iteration would
  synchronise the device every iteration).

Precision: ``float32`` or ``float64``; the first use of JAX here (:func:`jax_modules`, called
by the constructor) turns on ``jax_enable_x64`` (process-wide, needed for float64 arrays;
float32 runs keep float32 arrays explicitly). JAX is imported only inside this module's
functions, so importing the module and the default install never need it; without JAX the
constructor raises :class:`JaxUnavailable`.

Devices: ``device="cpu"`` (default) or ``"gpu"``; :func:`gpu_available` tells whether JAX sees
a GPU (a GPU request without one raises :class:`JaxUnavailable` with "no GPU visible").
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np

from c3bench.problems.errors import BackendUnavailable
from c3bench.problems.lcs import LCSBatch
from c3bench.problems.mpc import MPC, HorizonLayout
from c3bench.problems.names import Precision
from c3bench.solvers.admm.controller import solve_batched
from c3bench.solvers.admm.kernel import PlanRun, StepInputs
from c3bench.solvers.admm.loop import admm_iteration, scale_dual
from c3bench.solvers.admm.options import C3Options
from c3bench.solvers.admm.projection import make_step_projection
from c3bench.solvers.admm.solution import FastSolution, FastTimings
from c3bench.solvers.admm.stacked import box_of_step, projection_weight_vector


class JaxUnavailable(BackendUnavailable):
    """JAX is not installed, or the requested device is not visible."""


def jax_ready(values: Any) -> None:
    """Wait until the device has computed ``values`` (a pytree of arrays): JAX dispatches
    asynchronously, and a timer stopped before this measures the dispatch only."""
    import jax

    jax.block_until_ready(values)  # type: ignore[no-untyped-call]


def jax_modules() -> tuple[Any, Any, Any]:
    """``(jax, jax.numpy, jax.lax)`` with x64 enabled; ``JaxUnavailable`` without JAX."""
    try:
        import jax
        import jax.numpy as jnp
        from jax import lax
    except ImportError as error:  # pragma: no cover - depends on the install
        raise JaxUnavailable(f"JAX is not installed ({error}); pip install 'c3bench[jax]'"
                             ) from error
    # jax.config.update is untyped in jax's stubs
    jax.config.update("jax_enable_x64", True)  # type: ignore[no-untyped-call]
    return jax, jnp, lax


def jax_available() -> bool:
    """Whether JAX imports."""
    try:
        jax_modules()
    except JaxUnavailable:
        return False
    return True


def gpu_available() -> bool:
    """Whether JAX sees at least one GPU."""
    try:
        jax, _, _ = jax_modules()
        return len(jax.devices("gpu")) > 0
    except (JaxUnavailable, RuntimeError):
        return False


def jax_version() -> str:
    try:
        jax, _, _ = jax_modules()
    except JaxUnavailable:
        return "-"
    return str(jax.__version__)


def cholesky_solve(jnp: Any, Q: Any, R: Any) -> Any:
    """``Q^-1 R`` for SPD ``Q`` (..., m, m) and ``R`` (..., m, r) by the unrolled Cholesky
    factorisation ``Q = L L^T`` (:func:`cholesky_factor`) and forward and back substitution
    (straight-line code)."""
    L = cholesky_factor(jnp, Q)
    Y = forward_substitution(jnp, L, R)
    X = back_substitution(jnp, L[..., None, :, :], jnp.swapaxes(Y, -1, -2))
    return jnp.swapaxes(X, -1, -2)


def cholesky_factor(jnp: Any, Q: Any) -> Any:
    """The lower Cholesky factor ``L`` (..., m, m) of SPD ``Q`` (..., m, m), unrolled entry
    by entry: every scalar operation acts on the vector of one entry over all samples, which
    XLA vectorises; a non-positive pivot gives NaN."""
    m = Q.shape[-1]
    zero = jnp.zeros_like(Q[..., 0, 0])
    L: list[list[Any]] = [[zero] * m for _ in range(m)]
    for j in range(m):
        diagonal = Q[..., j, j]
        for k in range(j):
            diagonal = diagonal - L[j][k] * L[j][k]
        pivot = jnp.sqrt(diagonal)
        L[j][j] = pivot
        for i in range(j + 1, m):
            entry = Q[..., i, j]
            for k in range(j):
                entry = entry - L[i][k] * L[j][k]
            L[i][j] = entry / pivot
    return jnp.stack([jnp.stack(row, axis=-1) for row in L], axis=-2)


def forward_substitution(jnp: Any, L: Any, R: Any) -> Any:
    """``L^-1 R`` for the factor ``L`` (..., m, m) of :func:`cholesky_factor` and ``R``
    (..., m, r), row by row.

    Each row ends in a division by its pivot, which XLA does not duplicate into the
    consumers of the row (a division counts as expensive), so every row is computed once.
    The divisor is written ``pivot + 0 * row`` (same values; a NaN or infinity stays
    non-finite): XLA rewrites a division by a broadcast pivot into a multiplication by its
    reciprocal, which it then fuses into every later row and into the final stack and
    recomputes there (measured 2 to 4 times slower in the compiled step)."""
    m = R.shape[-2]
    Y: list[Any] = []
    for i in range(m):
        row = R[..., i, :]
        for k in range(i):
            row = row - L[..., i, k, None] * Y[k]
        Y.append(row / (L[..., i, i, None] + 0 * row))
    return jnp.stack(Y, axis=-2)


def back_substitution(jnp: Any, L: Any, y: Any) -> Any:
    """``L^-T y`` for the factor ``L`` (..., m, m) and ``y`` (..., m), entry by entry."""
    m = L.shape[-1]
    x: list[Any] = [None] * m
    for i in range(m - 1, -1, -1):
        entry = y[..., i]
        for k in range(i + 1, m):
            entry = entry - L[..., k, i] * x[k]
        x[i] = entry / L[..., i, i]
    return jnp.stack(x, axis=-1)


class JaxC3Plus:
    """Batched C3+ control step compiled with JAX (module docstring).

    Parameters
    ----------
    mpc
        Cost, goal, horizon and force limit.
    options
        :class:`solvers.c3.C3Options` (variant ``c3plus``, stopping ``fixed``, no bounds).
    precision
        ``float64`` or ``float32``.
    shared_inputs
        Robust variant (consensus on ``u`` in the projection) or independent samples.
    jacobi, ridge, symmetrize, rollout
        As :class:`solvers.fast.RiccatiOptions`.
    device
        ``cpu`` or ``gpu``.
    unroll
        ``lax.scan`` unrolling of the time-step loops (1: compact graph, fast compilation;
        ``T``: straight-line code).
    """

    def __init__(self, mpc: MPC, options: C3Options | None = None,
                 precision: str = Precision.FLOAT64,
                 shared_inputs: bool = True, jacobi: bool = True, ridge: float = 0.0,
                 symmetrize: bool = True, rollout: bool = False, device: str = "cpu",
                 unroll: int = 1) -> None:
        jax, _, _ = jax_modules()
        options = options or C3Options(keep_iterates=False)
        options.check_batched_c3plus("JaxC3Plus")
        if precision not in tuple(Precision):
            raise ValueError(f"precision must be one of {tuple(map(str, Precision))}, got "
                             f"{precision!r}")
        if device not in ("cpu", "gpu"):
            raise ValueError(f"device must be 'cpu' or 'gpu', got {device!r}")
        if device == "gpu" and not gpu_available():
            raise JaxUnavailable("no GPU visible to JAX")
        self.jax = jax
        self.device = jax.devices(device)[0]
        self.mpc = mpc
        self.options = options
        self.precision = precision
        self.dtype = Precision(precision).dtype.type
        self.shared_inputs = shared_inputs
        self.jacobi = jacobi
        self.ridge = float(ridge)
        self.symmetrize = symmetrize
        self.rollout = rollout
        self.unroll = int(unroll)
        self._compiled: dict[tuple[int, ...],
                             tuple[Callable[..., Any], Callable[..., Any]]] = {}
        self.timings = FastTimings()
        self.info: dict[str, Any] = {}
        self._constants: dict[int, tuple[np.ndarray, Any]] = {}
        self._plans: dict[tuple[Any, ...], tuple[np.ndarray, tuple[Any, Any, Any]]] = {}

    name = "jax"

    # -- the compiled iteration --------------------------------------------------------------
    def _build(self, n: int, nx: int, nlam: int, nu: int
               ) -> tuple[Callable[..., Any], Callable[..., Any]]:
        jax, jnp, lax = jax_modules()
        mpc, dtype = self.mpc, self.dtype
        nv = nlam + nu
        ny = nx + nv
        Q = np.asarray(mpc.Q, dtype=np.float64)
        R = np.asarray(mpc.R, dtype=np.float64)
        base = np.zeros((ny, ny))
        base[:nx, :nx] = 2 * Q
        base[nx + nlam:, nx + nlam:] = 2 * R
        base_j = jnp.asarray(base, dtype=dtype)
        PT = jnp.asarray(2 * np.asarray(mpc.Q_f, dtype=np.float64), dtype=dtype)
        gx = jnp.asarray(-2 * Q @ mpc.x_target, dtype=dtype)
        gT = jnp.asarray(-2 * np.asarray(mpc.Q_f) @ mpc.x_target, dtype=dtype)
        # block membership of the step vector (x, lam, u, eta) and of y = (x, lam, u)
        block_of_step = np.concatenate([np.full(nx, 0), np.full(nlam, 1), np.full(nu, 2),
                                        np.full(nlam, 3)])
        onehot_step = jnp.asarray(np.eye(4)[block_of_step], dtype=dtype)  # (ns, 4)
        onehot_y = onehot_step[:ny]
        ridge_v = np.zeros(ny)
        ridge_v[nx:] = self.ridge
        ridge_j = jnp.asarray(np.diag(ridge_v), dtype=dtype)
        jacobi, symmetrize, rollout = self.jacobi, self.symmetrize, self.rollout
        unroll = self.unroll
        shared = self.shared_inputs and n > 1

        def swap(a: Any) -> Any:
            return jnp.swapaxes(a, -1, -2)

        def mv(X: Any, y: Any) -> Any:
            """``X @ y`` for every sample: ``X`` (n, a, b), ``y`` (n, b) -> (n, a)."""
            return jnp.einsum("nab,nb->na", X, y)

        def qp(A: Any, Bv: Any, d: Any, M: Any, MtM: Any, c: Any, x0: Any, rho: Any,
               anchor: Any) -> tuple[Any, Any]:
            """The QP step of all samples (leading sample axis)."""
            r = rho.astype(dtype)
            rho_y = onehot_y @ r  # per-entry rho of (x, lam, u)
            Hy = base_j + jnp.diag(2 * rho_y) + 2 * r[3] * MtM  # (n, ny, ny)
            gy = anchor[..., :ny] * (-2 * rho_y)
            gy = gy.at[..., :nx].add(gx)
            gy = gy + 2 * r[3] * ((c[:, None, :] - anchor[..., ny:]) @ M)  # (n, T, ny)
            if jacobi:
                D = 1.0 / jnp.sqrt(jnp.diagonal(Hy, axis1=-2, axis2=-1))  # (n, ny)
            else:
                D = jnp.ones((n, ny), dtype=dtype)
            Dx, Dv = D[:, :nx], D[:, nx:]
            Hs = Hy * D[:, :, None] * D[:, None, :] + ridge_j
            As = A / Dx[:, :, None] * Dx[:, None, :]
            Bs = Bv / Dx[:, :, None] * Dv[:, None, :]
            ds = d / Dx
            ABs = jnp.concatenate([As, Bs], axis=-1)  # (n, nx, ny)
            ABsT = swap(ABs)

            def backward(carry: tuple[Any, Any], g: Any) -> tuple[tuple[Any, Any], Any]:
                # Q_vv = L L^T (unrolled); with W = L^-1 Q_vx and w = L^-1 q_v the gains are
                # K = -L^-T W, kk = -L^-T w, the cost-to-go S = Q_xx - W^T W,
                # s = q_x - W^T w; the forward pass applies L^-T (module docstring)
                S, s = carry
                Qyy = Hs + ABsT @ (S @ ABs)
                qy = g + mv(ABsT, mv(S, ds) + s)
                rhs = jnp.concatenate([Qyy[:, nx:, :nx], qy[:, nx:, None]], axis=-1)
                L = cholesky_factor(jnp, Qyy[:, nx:, nx:])
                Y = forward_substitution(jnp, L, rhs)  # (n, nv, nx + 1)
                W, wv = Y[..., :nx], Y[..., nx]
                S = Qyy[:, :nx, :nx] - swap(W) @ W
                if symmetrize:
                    S = 0.5 * (S + swap(S))
                return (S, qy[:, :nx] - mv(swap(W), wv)), (L, W, wv)

            PTs = PT * Dx[:, :, None] * Dx[:, None, :]
            _, gains = lax.scan(backward, (PTs, gT * Dx),
                                jnp.moveaxis(gy * D[:, None, :], 1, 0), reverse=True,
                                unroll=unroll)

            def forward(x: Any, gains: tuple[Any, Any, Any]) -> tuple[Any, tuple[Any, Any]]:
                L, W, wv = gains
                v = -back_substitution(jnp, L, mv(W, x) + wv)  # (n, nv)
                x = mv(As, x) + mv(Bs, v) + ds
                return x, (v, x)

            _, (vs, xs_s) = lax.scan(forward, x0 / Dx, gains, unroll=unroll)
            vs = jnp.moveaxis(vs, 0, 1) * Dv[:, None, :]  # (n, T, nv)
            if rollout:
                def roll(x: Any, v: Any) -> tuple[Any, Any]:
                    x = mv(A, x) + mv(Bv, v) + d
                    return x, x

                _, xs_next = lax.scan(roll, x0, jnp.moveaxis(vs, 1, 0), unroll=unroll)
                xs_next = jnp.moveaxis(xs_next, 0, 1)
            else:
                xs_next = jnp.moveaxis(xs_s, 0, 1) * Dx[:, None, :]
            xs = jnp.concatenate([x0[:, None, :], xs_next], axis=1)  # (n, T + 1, nx)
            ys = jnp.concatenate([xs[:, :-1], vs], axis=-1)
            eta = ys @ swap(M) + c[:, None, :]
            return jnp.concatenate([ys, eta], axis=-1), xs[:, -1]

        project = make_step_projection(jnp, nx, nlam, nu)

        def iterate(A: Any, Bv: Any, d: Any, M: Any, MtM: Any, c: Any, x0: Any, rho: Any,
                    sqrt_u: Any, lower: Any, upper: Any, p: Any, delta: Any, w: Any
                    ) -> tuple[Any, Any, Any]:
            """QP step and projection of ``z + w`` (one ADMM iteration but the dual update)."""
            z, terminal = qp(A, Bv, d, M, MtM, c, x0, rho, delta - w)
            new_delta = project(z + w, sqrt_u[0], sqrt_u[1], lower, upper, p.astype(dtype),
                                shared)
            return z, terminal, new_delta

        def fused(A: Any, Bv: Any, d: Any, M: Any, MtM: Any, c: Any, x0: Any, rho: Any,
                  sqrt_u: Any, lower: Any, upper: Any, p: Any, delta: Any, w: Any
                  ) -> tuple[Any, Any, Any, Any]:
            """The loop's :func:`admm_iteration` (kernel step and dual update) traced whole."""
            traced = _TracedKernel(lambda r, dl, wl: iterate(
                A, Bv, d, M, MtM, c, x0, r[0], r[1], lower, upper, p, dl, wl))
            return admm_iteration(traced, (rho, sqrt_u), delta, w)

        def run_plan(A: Any, Bv: Any, d: Any, M: Any, MtM: Any, c: Any, x0: Any, rhos: Any,
                     sqrt_us: Any, ratios: Any, lower: Any, upper: Any, p: Any, delta: Any,
                     w: Any) -> tuple[Any, Any, Any, Any]:
            """A whole plan: ``fused`` with ``rhos[i]``, then the loop's :func:`scale_dual` by
            ``ratios[i]`` (the last row ones), as one ``lax.scan``; returns the last
            ``z_steps``, ``z_terminal``, ``delta`` and ``w``."""
            def body(carry: tuple[Any, Any, Any, Any], step: tuple[Any, Any, Any]
                     ) -> tuple[tuple[Any, Any, Any, Any], None]:
                delta_i, w_i = carry[2], carry[3]
                z, terminal, new_delta, new_w = fused(A, Bv, d, M, MtM, c, x0, step[0],
                                                      step[1], lower, upper, p, delta_i, w_i)
                return (z, terminal, new_delta, scale_dual(new_w, step[2])), None

            start = (jnp.zeros_like(delta), jnp.zeros((delta.shape[0], nx), delta.dtype),
                     delta, w)
            out: tuple[Any, Any, Any, Any] = lax.scan(body, start, (rhos, sqrt_us, ratios))[0]
            return out

        return jax.jit(fused), jax.jit(run_plan)

    def compiled(self, n: int, nx: int, nlam: int, nu: int
                 ) -> tuple[Callable[..., Any], Callable[..., Any]]:
        """The compiled iteration and plan run for these sizes (built and cached on first
        use)."""
        key = (n, nx, nlam, nu)
        if key not in self._compiled:
            self._compiled[key] = self._build(n, nx, nlam, nu)
        return self._compiled[key]

    # -- the kernel of the one ADMM ----------------------------------------------------------
    def bind(self, lcs: LCSBatch) -> None:
        """Move ``lcs`` to the device for the next control step."""
        if lcs.nx != self.mpc.nx or lcs.nu != self.mpc.nu:
            raise ValueError("LCS and MPC dimensions disagree")
        jax, jnp, _ = jax_modules()
        dtype = self.dtype
        self.lcs = lcs
        self.layout = HorizonLayout(lcs.nx, lcs.nlam, lcs.nu, lcs.nlam, self.mpc.horizon)
        arrays = [lcs.A, np.concatenate([lcs.D, lcs.B], axis=2), lcs.d,
                  np.concatenate([lcs.E, lcs.F, lcs.H], axis=2)]
        A, Bv, d, M = (jax.device_put(np.asarray(a, dtype=dtype), self.device) for a in arrays)
        MtM = jnp.swapaxes(M, -1, -2) @ M
        c = jax.device_put(np.asarray(lcs.c, dtype=dtype), self.device)
        self._lcs_arrays = (A, Bv, d, M, MtM, c)
        self._step, self._plan_step = self.compiled(lcs.n_samples, lcs.nx, lcs.nlam,
                                                    lcs.nu)

    def start(self, inputs: StepInputs) -> None:
        """Per step: ``x0``, sample weights and the box on the device."""
        jax = self.jax
        n = self.lcs.n_samples
        x0 = np.broadcast_to(np.asarray(inputs.x0, dtype=self.dtype), (n, self.lcs.nx))
        lower, upper = box_of_step(self.mpc, self.layout, self.options.use_limits)
        self._step_arrays = tuple(jax.device_put(np.asarray(a, dtype=self.dtype), self.device)
                                  for a in (x0, lower, upper))
        self._p = jax.device_put(np.asarray(inputs.weights, dtype=np.float64), self.device)

    def fused(self, kernel: Any, rho: dict[str, float], delta: Any, w: Any
              ) -> tuple[Any, Any, Any, Any]:
        """One ADMM iteration (:func:`admm_iteration`: QP step, projection, dual update) as
        one compiled device call; the loop calls this instead of ``admm_iteration``."""
        t0 = time.perf_counter()
        rho_vec, sqrt_u = self._rho_arrays(rho)
        x0, lower, upper = self._step_arrays
        out: tuple[Any, Any, Any, Any] = self._step(*self._lcs_arrays, x0, rho_vec, sqrt_u,
                                                    lower, upper, self._p, delta, w)
        jax_ready(out)  # time the device's work, not its dispatch
        self.timings.qp_solve += time.perf_counter() - t0
        return out

    def run_plan(self, plan: Sequence[Mapping[str, float]], ratios: np.ndarray, delta: Any,
                 w: Any) -> PlanRun:
        """A whole planned schedule as ONE device call (a ``lax.scan`` of :meth:`fused`'s
        iteration and the loop's dual rescaling by ``ratios``; the loop calls this for a
        geometric schedule with ``fixed`` stopping and nothing recorded). As with
        :meth:`fused`, non-finite values are found by :meth:`solve` after the last
        iteration."""
        t0 = time.perf_counter()
        rhos, sqrt_us, padded = self._plan_inputs(plan, ratios)
        x0, lower, upper = self._step_arrays
        z, terminal, delta, w = self._plan_step(*self._lcs_arrays, x0, rhos, sqrt_us, padded,
                                                lower, upper, self._p, delta, w)
        # JAX dispatches asynchronously: wait, so that qp_solve is the device's work and not
        # just its dispatch (which left the work to the caller's first read, as "overhead")
        jax_ready((z, terminal, delta, w))
        self.timings.qp_solve += time.perf_counter() - t0
        return PlanRun(len(plan), delta, w, z, terminal)

    def _plan_inputs(self, plan: Sequence[Mapping[str, float]], ratios: np.ndarray
                     ) -> tuple[Any, Any, Any]:
        """The plan's stacked :meth:`_rho_arrays` and ``ratios`` with a ones row appended (no
        rescaling after the last iteration), on the device; memoised by the layout, the
        plan's items and the (memoised) ratio array, since a controller repeats them every
        control step (about 0.16 ms of numpy to rebuild)."""
        key = (self.layout, tuple(tuple(rho.items()) for rho in plan))
        cached = self._plans.get(key)
        if cached is None or cached[0] is not ratios:
            pairs = [self._rho_arrays(rho) for rho in plan]
            padded = np.ones((len(plan), self.layout.step_size), dtype=self.dtype)
            padded[:len(plan) - 1] = ratios
            arrays = tuple(self.jax.device_put(a, self.device) for a in (
                np.stack([rho_vec for rho_vec, _ in pairs]),
                np.stack([sqrt_u for _, sqrt_u in pairs]), padded))
            if len(self._plans) > 16:
                self._plans.clear()
            cached = self._plans[key] = (ratios, arrays)
        return cached[1]

    def _rho_arrays(self, rho: Mapping[str, float]) -> tuple[np.ndarray, np.ndarray]:
        """``(rho_x, rho_lam, rho_u, rho_eta)`` (float64) and ``(sqrt U_lam, sqrt U_eta)`` in
        the working precision (the compiled iteration's rho inputs)."""
        U = projection_weight_vector(self.options, self.layout, rho)
        lam_s, eta_s = self.layout.index(0, "lam"), self.layout.index(0, "eta")
        sqrt_u = np.stack([np.sqrt(U[lam_s]), np.sqrt(U[eta_s])]).astype(self.dtype)
        rho_vec = np.asarray([rho[key] for key in ("x", "lam", "u", "eta")], dtype=np.float64)
        return rho_vec, sqrt_u

    def iterate(self, rho: dict[str, float], delta: Any, w: Any) -> tuple[Any, Any, Any]:
        """QP step and projection (the fused call's first three outputs)."""
        z, terminal, new_delta, _ = self.fused(self, rho, delta, w)
        return z, terminal, new_delta

    def constant(self, array: np.ndarray) -> Any:
        """``array`` on the device, memoised by identity (the loop's memoised ratios)."""
        key = id(array)
        cached = self._constants.get(key)
        if cached is None or cached[0] is not array:
            cached = (array, self.jax.device_put(array, self.device))
            if len(self._constants) > 256:
                self._constants.clear()
            self._constants[key] = cached
        return cached[1]

    def solve(self, lcs: LCSBatch, x0: np.ndarray, weights: Sequence[float] | None = None,
              delta: np.ndarray | None = None, w: np.ndarray | None = None,
              fallback_input: np.ndarray | None = None, trusted_iterates: bool = False
              ) -> FastSolution:
        """One control step of the one ADMM on the device (returns numpy arrays;
        ``trusted_iterates`` as :meth:`c3bench.solvers.fast.FastC3Plus.solve`)."""
        solution = solve_batched(self, lcs, self.mpc, x0, self.options, weights, delta, w,
                                 fallback_input, self.shared_inputs, record_residuals=False,
                                 trusted_iterates=trusted_iterates)
        solution.delta, solution.w = np.asarray(solution.delta), np.asarray(solution.w)
        if solution.z_steps is not None and solution.z_terminal is not None:
            solution.z_steps = np.asarray(solution.z_steps)
            solution.z_terminal = np.asarray(solution.z_terminal)
        arrays = [a for a in (solution.delta, solution.w, solution.z_steps, solution.z_terminal)
                  if a is not None]
        if solution.ok and not all(np.all(np.isfinite(a)) for a in arrays):
            solution.ok, solution.status, solution.u_raw = False, \
                "non-finite values in the compiled step", None
            solution.u = np.zeros(lcs.nu) if fallback_input is None else \
                np.asarray(fallback_input, dtype=float).copy()
        return solution


class _TracedKernel:
    """A kernel whose ``iterate`` is a traced function (inside :func:`jax.jit`)."""

    def __init__(self, iterate: Callable[[Any, Any, Any], tuple[Any, Any, Any]]) -> None:
        self.iterate = iterate

