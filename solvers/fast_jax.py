"""The batched C3+ control step compiled with JAX (optional: ``pip install c3bench[jax]``).

The same algorithm as :mod:`solvers.fast` (read its docstring for the formulas): ``eta``
eliminated, a Riccati recursion over ``T`` steps for every sample, the closed-form projection,
the dual update and the rho schedule, for ``n`` samples at once, inside **one** ``jax.jit``
compiled function per (shapes, options): the ADMM iterations are a ``lax.scan``, the ``T``
time steps of the Riccati recursion and of the rollout are ``lax.scan`` loops (``unroll``
sets their unrolling), and every operation acts on all samples at once (arrays with a leading
sample axis: the matrix products are batched dots, the projection, the shared-input mean and
the dual update act on the (n, T, ns) arrays).

Differences from the numpy path (same mathematics, different arrangement):

* the factorisation and the linear passes are fused per iteration (the rho of the next
  iteration is a traced value, so the ``adaptive`` and ``residual_balancing`` schedules run
  inside the compiled loop too);
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
* the stopping rule is ``fixed`` only (``residual`` raises ``ValueError``);
* timings cannot be split inside a compiled call: :class:`solvers.fast.FastTimings` reports
  the whole ADMM as ``qp_solve`` and zero for the parts.

Precision: ``float32`` or ``float64``; the first use of JAX here (:func:`jax_modules`, called
by the constructor) turns on ``jax_enable_x64`` (process-wide, needed for float64 arrays;
float32 runs keep float32 arrays explicitly). JAX is imported only inside this module's
functions, so importing the module and the default install never need it; without JAX the
constructor raises :class:`JaxUnavailable`.

Devices: ``device="cpu"`` (default) or ``"gpu"``; :func:`gpu_available` tells whether JAX sees
a GPU (a GPU request without one raises :class:`JaxUnavailable` with "no GPU visible").
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from c3bench.problems.errors import BackendUnavailable
from c3bench.problems.lcs import LCSBatch
from c3bench.problems.mpc import MPC
from c3bench.problems.names import Precision, Variant
from c3bench.solvers.c3 import C3Options
from c3bench.solvers.fast import FastSolution, FastTimings


class JaxUnavailable(BackendUnavailable):
    """JAX is not installed, or the requested device is not visible."""


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
        if options.variant != Variant.C3PLUS:
            raise ValueError("JaxC3Plus runs the c3plus variant only")
        if options.input_bounds:
            raise ValueError("JaxC3Plus does not take input bounds")
        if options.stopping != "fixed":
            raise ValueError("JaxC3Plus runs a fixed number of iterations (stopping='fixed')")
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
        self._compiled: dict[tuple[int, ...], Callable[..., Any]] = {}

    # -- the compiled step -------------------------------------------------------------------
    def _build(self, n: int, nx: int, nlam: int, nu: int) -> Callable[..., Any]:
        jax, jnp, lax = jax_modules()
        options, mpc, dtype = self.options, self.mpc, self.dtype
        iterations = int(options.admm_iterations)
        nv = nlam + nu
        ny = nx + nv
        ns = ny + nlam
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
        scheduled = jnp.asarray([1.0 if key in options.rho_blocks else 0.0
                                 for key in ("x", "lam", "u", "eta")], dtype=dtype)
        rho0 = jnp.asarray([options.rho0[key] for key in ("x", "lam", "u", "eta")],
                           dtype=np.float64)
        schedule = options.rho_schedule
        ridge_v = np.zeros(ny)
        ridge_v[nx:] = self.ridge
        ridge_j = jnp.asarray(np.diag(ridge_v), dtype=dtype)
        jacobi, symmetrize, rollout = self.jacobi, self.symmetrize, self.rollout
        unroll = self.unroll
        shared = self.shared_inputs and n > 1
        limit = float(mpc.force_limit)
        lam_s = slice(nx, nx + nlam)
        u_s = slice(nx + nlam, ny)
        eta_s = slice(ny, ns)

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

        def project(v: Any, rho: Any) -> Any:
            a = jnp.maximum(v[..., lam_s], 0)
            b = jnp.maximum(v[..., eta_s], 0)
            keep = jnp.sqrt(rho[1]).astype(dtype) * a >= jnp.sqrt(rho[3]).astype(dtype) * b
            out = v.at[..., lam_s].set(jnp.where(keep, a, 0))
            return out.at[..., eta_s].set(jnp.where(keep, 0, b))

        def weighted_norm(values: Any, p: Any) -> Any:
            flat = values.astype(jnp.float64).reshape(n, -1)
            # row sums as a matrix-vector product (faster than XLA's CPU reduction here)
            squares = (flat * flat) @ jnp.ones(flat.shape[1], dtype=jnp.float64)
            return jnp.sqrt(jnp.dot(p, squares))

        def multiplier(consensus: Any, previous: Any, dual: Any, i: Any) -> Any:
            if schedule == "geometric":
                return jnp.asarray(float(options.rho_factor), dtype=jnp.float64)
            if schedule == "adaptive":
                grow = consensus >= options.adaptive_gamma * previous
                return jnp.where((i > 0) & grow, float(options.adaptive_beta), 1.0)
            up = consensus > options.balance_mu * dual
            down = dual > options.balance_mu * consensus
            return jnp.where(up, float(options.balance_tau),
                             jnp.where(down, 1.0 / float(options.balance_tau), 1.0))

        def step(A: Any, Bv: Any, d: Any, M: Any, c: Any, x0: Any, delta: Any, w: Any,
                 p: Any) -> tuple[Any, ...]:
            MtM = swap(M) @ M
            x0 = jnp.broadcast_to(x0, (n, nx))
            p_work = p.astype(dtype)

            def body(carry: tuple[Any, ...], i: Any) -> tuple[tuple[Any, ...], Any]:
                delta, w, rho, previous, _, _, _ = carry
                z, terminal = qp(A, Bv, d, M, MtM, c, x0, rho, delta - w)
                v = z + w
                new_delta = project(v, rho)
                if shared:
                    mean = jnp.einsum("n,ntu->tu", p_work, v[..., u_s])
                    new_delta = new_delta.at[..., u_s].set(
                        jnp.broadcast_to(mean, new_delta[..., u_s].shape))
                difference = z - new_delta
                new_w = w + difference
                G = onehot_step @ rho.astype(dtype)
                consensus = weighted_norm(difference, p)
                dual = weighted_norm(2.0 * G * (new_delta - delta), p)
                factor = multiplier(consensus, previous, dual, i)
                updated = rho * jnp.where(scheduled > 0, factor, 1.0)
                last = i + 1 >= iterations
                updated = jnp.where(last, rho, updated)
                if options.rescale_dual:
                    ratio = (onehot_step @ rho) / (onehot_step @ updated)
                    new_w = new_w * ratio.astype(dtype)
                carry = (new_delta, new_w, updated, consensus, z, terminal, rho)
                return carry, (consensus, dual)

            z0 = jnp.zeros_like(delta)
            init = (delta, w, rho0, jnp.asarray(math.inf, dtype=jnp.float64), z0,
                    jnp.zeros((n, nx), dtype=dtype), rho0)
            carry, (consensus, dual) = lax.scan(body, init, jnp.arange(iterations))
            delta, w, _, _, z, terminal, rho_used = carry
            first = delta[:, 0, u_s] if options.output == "delta" else z[:, 0, u_s]
            u_raw = jnp.einsum("n,nu->u", p, first.astype(jnp.float64)) if \
                self.shared_inputs else first.astype(jnp.float64)
            finite = jnp.all(jnp.isfinite(z)) & jnp.all(jnp.isfinite(delta)) & \
                jnp.all(jnp.isfinite(u_raw))
            return (u_raw, jnp.clip(u_raw, -limit, limit), delta, w, z, terminal, rho_used,
                    consensus, dual, finite)

        compiled: Callable[..., Any] = jax.jit(step)
        return compiled

    def compiled(self, n: int, nx: int, nlam: int, nu: int) -> Callable[..., Any]:
        """The compiled step for these sizes (built and cached on first use)."""
        key = (n, nx, nlam, nu)
        if key not in self._compiled:
            self._compiled[key] = self._build(n, nx, nlam, nu)
        return self._compiled[key]

    def solve(self, lcs: LCSBatch, x0: np.ndarray, weights: Sequence[float] | None = None,
              delta: np.ndarray | None = None, w: np.ndarray | None = None,
              fallback_input: np.ndarray | None = None) -> FastSolution:
        """One control step, as :meth:`solvers.fast.FastC3Plus.solve` (returns numpy)."""
        jax = self.jax
        started = time.perf_counter()
        n, nx, nlam, nu = lcs.n_samples, lcs.nx, lcs.nlam, lcs.nu
        if nx != self.mpc.nx or nu != self.mpc.nu:
            raise ValueError("LCS and MPC dimensions disagree")
        T = self.mpc.horizon
        ns = nx + 2 * nlam + nu
        dtype = self.dtype
        p = _weights(weights, n)
        if delta is None:
            delta = np.zeros((n, T, ns), dtype=dtype)
            delta[:, :, :nx] = np.asarray(x0, dtype=dtype)
        if w is None:
            w = np.zeros((n, T, ns), dtype=dtype)
        delta = np.array(np.broadcast_to(delta, (n, T, ns)), dtype=dtype)
        w = np.array(np.broadcast_to(w, (n, T, ns)), dtype=dtype)
        fallback = np.zeros(nu) if fallback_input is None else np.asarray(fallback_input,
                                                                          dtype=float)
        step = self.compiled(n, nx, nlam, nu)
        arrays = [lcs.A, np.concatenate([lcs.D, lcs.B], axis=2), lcs.d,
                  np.concatenate([lcs.E, lcs.F, lcs.H], axis=2), lcs.c]
        inputs = [jax.device_put(np.asarray(a, dtype=dtype), self.device) for a in arrays]
        inputs += [jax.device_put(np.asarray(x0, dtype=dtype), self.device),
                   jax.device_put(delta, self.device), jax.device_put(w, self.device),
                   jax.device_put(p, self.device)]
        outputs = jax.block_until_ready(step(*inputs))
        (u_raw, u, delta_out, w_out, z, terminal, rho_used, consensus, dual,
         finite) = (np.asarray(o) for o in outputs)
        ok = bool(finite)
        elapsed = time.perf_counter() - started
        rho = {key: float(value) for key, value in zip(("x", "lam", "u", "eta"), rho_used,
                                                       strict=True)}
        return FastSolution(
            u=u.astype(np.float64) if ok else fallback, u_raw=u_raw if ok else None, ok=ok,
            status=f"{self.options.admm_iterations} iterations" if ok else
            "non-finite values in the compiled step",
            iterations=self.options.admm_iterations, delta=delta_out, w=w_out, z_steps=z,
            z_terminal=terminal, rho=rho, weights=p,
            consensus_residual=[float(v) for v in consensus],
            dual_residual=[float(v) for v in dual],
            timings=FastTimings(qp_solve=elapsed, total=elapsed))


def _weights(weights: Sequence[float] | None, n: int) -> np.ndarray:
    """Normalised, floored sample weights (as :func:`solvers.c3.solve_robust`)."""
    if weights is None:
        return np.full(n, 1.0 / n)
    array = np.asarray(weights, dtype=float)
    if array.shape != (n,) or not np.all(np.isfinite(array)) or np.any(array < 0) \
            or array.sum() <= 0:
        raise ValueError(f"weights must be {n} finite values >= 0, not all zero")
    array = array / array.sum()
    array = np.maximum(array, 1e-6 * array.max())
    normalised: np.ndarray = array / array.sum()
    return normalised
