"""Numba kernel of one compiled C3+ ADMM iteration: linear passes, projection, dual update.

:func:`iterate_in_lanes` (the one iteration; :func:`solve_project` calls it on iterates with
the samples first, :func:`c3bench.solvers.admm.compiled_plan.run_plan` keeps them samples last
throughout) takes the factors of :func:`c3bench.solvers.admm.compiled_kernels.
factorize_batch` (samples on their last axis) and does, for every sample, the gradient, the
backward and forward passes of the Riccati recursion (arithmetic of :mod:`solvers.fast`, the
rearrangements of :mod:`.compiled_kernels`: ``K`` applied through ``Y`` and ``L``,
products with ``[A B_v d]`` over its structural nonzeros), ``eta``, the C3+ projection (the
one closed form of :mod:`c3bench.solvers.admm.projection`, compiled) and the loop's dual update
(:func:`c3bench.solvers.admm.loop.dual_update`, compiled), in one call. From
:data:`LANE_SOLVE` samples on the samples are vector lanes (every innermost loop runs over
samples); below, one sample at a time. Where code was generated for the batch's structure
and sizes (:mod:`c3bench.solvers.admm.compiled_passes_codegen`: the same arithmetic in the
same order, unrolled and straight-line, bit for bit the same ``z``), it replaces both loops.

References: the Riccati recursion of the LQ problem (Rawlings, Mayne & Diehl, *Model Predictive
Control*, 2nd ed., section 1.3.3); triangular solves (Golub & Van Loan, *Matrix Computations*,
4th ed., algorithms 3.1.1-3.1.2); the consensus ADMM's dual update (Boyd et al. 2011,
section 3.1.1).
"""

from __future__ import annotations

import types
from typing import Any

import numba
import numpy as np

from c3bench.solvers.admm.compiled_kernels import Structure
from c3bench.solvers.admm.compiled_kernels import jit as _jit
from c3bench.solvers.admm.compiled_passes_codegen import call_passes
from c3bench.solvers.admm.loop import dual_update
from c3bench.solvers.admm.projection import make_c3plus_pairs

__all__ = ["LANE_SOLVE", "from_lanes", "iterate_in_lanes", "solve_flops", "solve_project",
           "to_lanes", "z_from_lanes"]

@numba.njit(fastmath=False)
def _maximum(a: Any, b: Any) -> Any:
    """``numpy.maximum`` of two scalars (a NaN ``a`` kept, as numpy keeps it)."""
    return a if (a >= b or a != a) else b


@numba.njit(fastmath=False)
def _where(condition: bool, a: Any, b: Any) -> Any:
    """``numpy.where`` of scalars."""
    return a if condition else b


_SCALARS = types.ModuleType("scalar_namespace")
"""The array namespace of :func:`make_c3plus_pairs` for one pair at a time in numba code:
``maximum`` and ``where`` of scalars. Scalars promote as numba's array functions do (a float32
entry against the literal ``0.0`` computes in float64), so the closed form gives the bits of
the array version (checked in tests/test_admm_compiled.py, NaN, infinities and signed zeros
included)."""
_SCALARS.maximum, _SCALARS.where = _maximum, _where  # type: ignore[attr-defined]
_c3plus_pair = numba.njit(fastmath=False)(make_c3plus_pairs(_SCALARS))
"""The one C3+ pair projection (:mod:`c3bench.solvers.admm.projection`) compiled by numba for
one pair (no temporary arrays)."""
_dual_update = numba.njit(fastmath=False)(dual_update)
"""The loop's one dual update (:func:`c3bench.solvers.admm.loop.dual_update`) compiled by
numba (called entry by entry: no temporary arrays)."""

LANE_SOLVE = 4
"""From this many samples on, :func:`solve_project` works the samples as vector lanes
(measured: about equal at 4 samples, lanes 1.2-1.5 times faster at 8, slower at 2-3)."""


def solve_flops(nx: int, nv: int, nlam: int, pattern: Structure | None = None) -> int:
    """Floating-point operations of :func:`solve_project` for one sample and step as it
    executes them: the gradient, the two passes over the structural nonzeros ``pattern`` of
    ``[A B_v d]`` (``None``: dense), ``eta``, the projection and the dual update (2 per
    multiply-add; a clamp, comparison or division 1; the shared-input mean not counted)."""
    ny = nx + nv
    ns = ny + nlam
    pattern = pattern or Structure.dense(nx, ny)
    counts = np.diff(pattern.column_start)
    nonzeros_x, nonzeros_v = int(counts[:nx].sum()), int(counts[nx:ny].sum())
    gradient = nlam + 2 * ny * nlam + 4 * ny + nx
    backward = 2 * nonzeros_v + nv * (nv - 1) + nv + nx + 2 * nonzeros_x + 2 * nv * nx
    forward = 2 * nv * nx + nv + nv * (nv - 1) + 3 * nv + 2 * (nonzeros_x + nonzeros_v) + nx
    eta = 2 * ny * nlam
    projection = ns + 2 * nx + 5 * nlam + 2 * (ns - nx - 2 * nlam)
    dual = 2 * ns
    return gradient + backward + forward + eta + projection + dual


@_jit
def solve_project(vectors: np.ndarray, delta: np.ndarray, w: np.ndarray, Mc: np.ndarray,
                  Mt: np.ndarray, consts: np.ndarray, Y: np.ndarray, L: np.ndarray,
                  Sd: np.ndarray, D: np.ndarray, ABd: np.ndarray, index: int,
                  column_start: np.ndarray,
                  column_rows: np.ndarray, row_start: np.ndarray, row_columns: np.ndarray,
                  p: np.ndarray, shared: bool, box: np.ndarray, zero: Any, z_steps: np.ndarray,
                  z_terminal: np.ndarray, new_delta: np.ndarray, new_w: np.ndarray,
                  generated: np.ndarray) -> bool:
    """:func:`iterate_in_lanes` on iterates with the samples first: ``delta``, ``w``,
    ``new_delta``, ``new_w`` and ``z_steps`` (n, T, ns), ``z_terminal`` (n, nx) (the
    iteration-by-iteration loop's arrays); ``False`` when the QP solution is not finite."""
    n, T, ns = delta.shape
    zt = np.empty((T + 1, ns, n), delta.dtype)
    finite = iterate_in_lanes(vectors, delta.transpose(1, 2, 0), w.transpose(1, 2, 0), Mc, Mt,
                              consts, Y, L, Sd, D, ABd, index, column_start, column_rows,
                              row_start, row_columns, p, shared, box, zero, zt,
                              new_delta.transpose(1, 2, 0), new_w.transpose(1, 2, 0),
                              generated)
    z_from_lanes(zt, z_steps, z_terminal)
    return finite


@_jit
def iterate_in_lanes(vectors: np.ndarray, delta: np.ndarray, w: np.ndarray, Mc: np.ndarray,
                     Mt: np.ndarray, consts: np.ndarray, Y: np.ndarray, L: np.ndarray,
                     Sd: np.ndarray, D: np.ndarray, ABd: np.ndarray, index: int,
                     column_start: np.ndarray, column_rows: np.ndarray, row_start: np.ndarray,
                     row_columns: np.ndarray, p: np.ndarray, shared: bool, box: np.ndarray,
                     zero: Any, zt: np.ndarray, new_delta: np.ndarray, new_w: np.ndarray,
                     generated: np.ndarray) -> bool:
    """One ADMM iteration for every sample, the iterates with the samples last: QP step
    (linear passes of factorisation slot ``index``: lanes ``index n .. index n + n`` of ``Y``
    (T, nv, nx, lanes) etc., :func:`c3bench.solvers.admm.compiled_kernels.factorize_batch`)
    into ``zt`` (T + 1, ns, n; row ``T``: the terminal ``x``), projection into ``new_delta``
    and dual update into ``new_w``; ``delta``, ``w``, ``new_delta``, ``new_w`` are (T, ns, n)
    (any strides: :func:`solve_project` passes transposed views). ``False`` when the QP
    solution is not finite. ``vectors`` = ``(x0, g_x, g_T)`` (3, nx), ``Mc`` = ``[M c]`` (n,
    nlam, ny + 1), ``Mt`` the same with the samples last (nlam, ny + 1, n), ``consts`` =
    ``(-2 G_y (ny,), 2 rho_eta, sqrt(rho_lam), sqrt(rho_eta))``; the structural nonzeros of
    ``[A B_v d]`` by column and by row
    (:class:`~c3bench.solvers.admm.compiled_kernels.Structure`): every product with it skips
    the rest.

    The passes (:func:`_passes_in_lanes`) run with the samples as vector lanes from
    :data:`LANE_SOLVE` samples on, below one sample at a time (:func:`_solve_sample`);
    ``generated`` = ``(address, width, factor lanes, samples)`` of the passes generated for
    this structure and these sizes
    (:func:`c3bench.solvers.admm.compiled_passes_codegen.passes_address`; address 0: none)
    replace the lane loops (bit for bit the same ``z``) when the sizes agree. Then
    :func:`_project_and_update`. Keeping the iterates in this layout across a planned
    schedule (:func:`c3bench.solvers.admm.compiled_plan.run_plan`) saves transposing them
    in and out of the passes' layout every iteration (measured at 16 samples: 9.4 -> 3 us of
    an iteration's 22 us).
    """
    T, n = delta.shape[0], delta.shape[2]
    nlam = Mt.shape[0]
    nx = Y.shape[2]
    if generated[0] != 0 and generated[2] == Y.shape[3] and generated[3] == n and \
            n % generated[1] == 0:
        o = index * n
        call_passes(generated[0], np.ascontiguousarray(delta), np.ascontiguousarray(w), Mt,
                    consts, vectors, Y[:, :, :, o:], L[:, :, :, o:], Sd[:, :, o:], D[:, o:],
                    ABd[:, :, o:], zt, n)
    elif n >= LANE_SOLVE:
        _passes_in_lanes(vectors, _difference(delta, w), Mt, consts, Y, L, Sd, D, ABd, index,
                         column_start, column_rows, row_start, row_columns, zero, zt)
    else:
        work = _Work(delta.dtype, T, nx, Y.shape[1], nlam)
        z_steps, z_terminal = zt[:T].transpose(2, 0, 1), zt[T].transpose()
        samples_delta, samples_w = delta.transpose(2, 0, 1), w.transpose(2, 0, 1)
        for j in range(n):
            lane = index * n + j
            _solve_sample(j, vectors, samples_delta, samples_w, Mc, consts, Y[:, :, :, lane],
                          L[:, :, :, lane], Sd[:, :, lane], D[:, lane], ABd[:, :, lane],
                          column_start, column_rows, row_start, row_columns, zero, z_steps,
                          z_terminal, work)
    return _project_and_update(zt, w, new_delta, new_w, nx, nlam, consts, p, shared, box,
                               zero)


@_jit
def _passes_in_lanes(vectors: np.ndarray, dw: np.ndarray, Mt: np.ndarray, consts: np.ndarray,
                     Y: np.ndarray, L: np.ndarray, Sd: np.ndarray, D: np.ndarray,
                     ABd: np.ndarray, index: int, column_start: np.ndarray,
                     column_rows: np.ndarray, row_start: np.ndarray, row_columns: np.ndarray,
                     zero: Any, zt: np.ndarray) -> None:
    """The linear passes of :func:`iterate_in_lanes` with every sample a lane (the innermost
    loops run over the samples, the last axis of the factors and of the local arrays), from
    ``dw = delta - w`` (T, ns, n) into ``zt`` (T + 1, ns, n).

    Gradient ``g_y = -2 G_y (delta - w)_y + (g_x, 0) + 2 rho_eta M^T (c - (delta - w)_eta)``,
    scaled by ``D``; backward ``r = g_v + B_v^T e``, ``t_k = L^-1 r``, ``e <- S_k d + g_x +
    A^T e - Y^T t_k`` (``K^T r = -Y^T L^-1 r``); forward ``v = -L^-T (Y x + t_k)`` (``K x +
    kk``), ``x <- A x + B_v v + d``; ``eta = M y + c``.
    """
    T, n = dw.shape[0], dw.shape[2]
    nx, nv = Y.shape[2], Y.shape[1]
    nlam = Mt.shape[0]
    ny = nx + nv
    dt = dw.dtype
    lanes = np.uint64(n)  # unsigned lane indices: numba adds no negative-index wraparound
    o = np.uint64(index) * lanes  # slot index's samples: lanes o .. o + n of the factors
    x0, gx, gT = vectors[0], vectors[1], vectors[2]
    g2 = consts[:ny]
    two_rho_eta = consts[ny]
    gy, tt = np.empty((T, ny, n), dt), np.empty((T, nv, n), dt)
    eta, e, r = np.empty((nlam, n), dt), np.empty((nx, n), dt), np.empty((nv, n), dt)
    v, x, xn = np.empty((nv, n), dt), np.empty((nx, n), dt), np.empty((nx, n), dt)
    for k in range(T):  # gradient
        for b in range(nlam):
            for j in range(lanes):
                eta[b, j] = Mt[b, ny, j] - dw[k, ny + b, j]
        for a in range(ny):  # M^T eta, summed over b in order, the rows a side by side
            for j in range(lanes):
                gy[k, a, j] = zero
        for b in range(nlam):
            for a in range(ny):
                for j in range(lanes):
                    gy[k, a, j] += Mt[b, a, j] * eta[b, j]
        for a in range(ny):
            for j in range(lanes):
                g = dw[k, a, j] * g2[a]
                if a < nx:
                    g += gx[a]
                gy[k, a, j] = (g + gy[k, a, j] * two_rho_eta) * D[a, o + j]
    for a in range(nx):
        for j in range(lanes):
            e[a, j] = Sd[T - 1, a, o + j] + gT[a] * D[a, o + j]
    for k in range(T - 1, -1, -1):  # backward pass
        for a in range(nv):  # r = g_v + B_v^T e
            for j in range(lanes):
                r[a, j] = gy[k, nx + a, j]
            for q in range(column_start[nx + a], column_start[nx + a + 1]):
                b = column_rows[q]
                for j in range(lanes):
                    r[a, j] += e[b, j] * ABd[b, nx + a, o + j]
        for a in range(nv):  # L t = r (L's diagonal holds 1 / L[a, a])
            for j in range(lanes):
                tt[k, a, j] = r[a, j]
            for b in range(a):
                for j in range(lanes):
                    tt[k, a, j] -= L[k, a, b, o + j] * tt[k, b, j]
            for j in range(lanes):
                tt[k, a, j] = tt[k, a, j] * L[k, a, a, o + j]
        if k > 0:
            for a in range(nx):  # e <- S_k d + g_x + A^T e - Y^T t
                for j in range(lanes):
                    xn[a, j] = gy[k, a, j] + Sd[k - 1, a, o + j]
                for q in range(column_start[a], column_start[a + 1]):
                    b = column_rows[q]
                    for j in range(lanes):
                        xn[a, j] += e[b, j] * ABd[b, a, o + j]
            for b in range(nv):  # - Y^T t, each row's terms in order, rows side by side
                for a in range(nx):
                    for j in range(lanes):
                        xn[a, j] -= tt[k, b, j] * Y[k, b, a, o + j]
            for a in range(nx):
                for j in range(lanes):
                    e[a, j] = xn[a, j]
    for a in range(nx):  # forward pass
        for j in range(lanes):
            x[a, j] = x0[a] / D[a, o + j]
            zt[0, a, j] = x0[a]
    for k in range(T):
        for a in range(nv):  # r = Y x + t, each row's terms in order, rows side by side
            for j in range(lanes):
                r[a, j] = tt[k, a, j]
        for b in range(nx):
            for a in range(nv):
                for j in range(lanes):
                    r[a, j] += Y[k, a, b, o + j] * x[b, j]
        for a in range(nv - 1, -1, -1):  # v = -L^-T r
            for j in range(lanes):
                v[a, j] = -r[a, j]
            for b in range(a + 1, nv):
                for j in range(lanes):
                    v[a, j] -= L[k, b, a, o + j] * v[b, j]
            for j in range(lanes):
                v[a, j] = v[a, j] * L[k, a, a, o + j]
                zt[k, nx + a, j] = v[a, j] * D[nx + a, o + j]
        for a in range(nx):  # x <- A x + B_v v + d
            for j in range(lanes):
                xn[a, j] = ABd[a, ny, o + j]
            for q in range(row_start[a], row_start[a + 1]):
                b = row_columns[q]
                if b < nx:
                    for j in range(lanes):
                        xn[a, j] += ABd[a, b, o + j] * x[b, j]
                else:
                    for j in range(lanes):
                        xn[a, j] += ABd[a, b, o + j] * v[b - nx, j]
        for a in range(nx):
            for j in range(lanes):
                x[a, j] = xn[a, j]
                zt[k + 1, a, j] = xn[a, j] * D[a, o + j]
    for k in range(T):  # eta = M y + c, each row's terms in order, rows side by side
        for b in range(nlam):
            for j in range(lanes):
                zt[k, ny + b, j] = Mt[b, ny, j]
        for a in range(ny):
            for b in range(nlam):
                for j in range(lanes):
                    zt[k, ny + b, j] += Mt[b, a, j] * zt[k, a, j]


@_jit
def _difference(delta: np.ndarray, w: np.ndarray) -> np.ndarray:
    """``delta - w`` (T, ns, n) into a new C-contiguous array (the passes' ``dw``)."""
    T, ns, n = delta.shape
    dw = np.empty((T, ns, n), delta.dtype)
    for k in range(T):
        for a in range(ns):
            for j in range(n):
                dw[k, a, j] = delta[k, a, j] - w[k, a, j]
    return dw


@_jit
def to_lanes(samples_first: np.ndarray, samples_last: np.ndarray) -> None:
    """Iterates ``(n, T, ns)`` into the passes' layout ``(T, ns, n)``."""
    n, T, ns = samples_first.shape
    for j in range(n):
        for k in range(T):
            for a in range(ns):
                samples_last[k, a, j] = samples_first[j, k, a]


@_jit
def from_lanes(samples_last: np.ndarray, samples_first: np.ndarray) -> None:
    """Iterates ``(T, ns, n)`` back into ``(n, T, ns)``."""
    n, T, ns = samples_first.shape
    for j in range(n):
        for k in range(T):
            for a in range(ns):
                samples_first[j, k, a] = samples_last[k, a, j]


@_jit
def z_from_lanes(zt: np.ndarray, z_steps: np.ndarray, z_terminal: np.ndarray) -> None:
    """``z`` of the passes' lanes, ``zt`` (T + 1, ns, n), into ``z_steps`` (n, T, ns) and
    ``z_terminal`` (n, nx) (row ``T`` of ``zt``)."""
    T = z_steps.shape[1]
    from_lanes(zt[:T], z_steps)
    for j in range(z_terminal.shape[0]):
        for a in range(z_terminal.shape[1]):
            z_terminal[j, a] = zt[T, a, j]


@_jit
def _project_and_update(zt: np.ndarray, w: np.ndarray, new_delta: np.ndarray,
                        new_w: np.ndarray, nx: int, nlam: int, consts: np.ndarray,
                        p: np.ndarray, shared: bool, box: np.ndarray, zero: Any) -> bool:
    """The end of every iteration of :func:`iterate_in_lanes` (samples last): the projection
    of ``z + w`` (:func:`_project`) into ``new_delta`` and the dual update ``new_w = w + z -
    new_delta`` (entry by entry), one time step at a time (its rows stay in the core's L1
    cache between the two: 4.3 -> 2.6 us at 16 samples); ``False`` when an entry of the QP
    solution ``zt`` (T + 1, ns, n; the terminal row's first ``nx``) is not finite (counted
    entry by entry: a running sum of the entries was a chain of dependent additions, a
    running ``and`` kept the loop from vectorising)."""
    T, ns, n = w.shape
    not_finite = 0
    for k in range(T):
        _project(k, zt, w, new_delta, nx, nlam, consts[-2], consts[-1], p, shared, box, zero)
        for a in range(ns):
            for j in range(n):
                not_finite += not abs(zt[k, a, j]) < np.inf  # NaN and infinities
                new_w[k, a, j] = _dual_update(w[k, a, j], zt[k, a, j], new_delta[k, a, j])
    for a in range(nx):
        for j in range(n):
            not_finite += not abs(zt[T, a, j]) < np.inf
    return not_finite == 0


@_jit
def _Work(dtype: Any, T: int, nx: int, nv: int, nlam: int) -> tuple[np.ndarray, ...]:
    """Scratch arrays of :func:`_solve_sample`: ``g_y`` (T, ny), ``t`` (T, nv), ``eta``,
    ``e``, ``r``, ``v``, ``x``, ``x_next``."""
    ny = nx + nv
    return (np.empty((T, ny), dtype), np.empty((T, nv), dtype), np.empty(nlam, dtype),
            np.empty(nx, dtype), np.empty(nv, dtype), np.empty(nv, dtype),
            np.empty(nx, dtype), np.empty(nx, dtype))


@_jit
def _solve_sample(j: int, vectors: np.ndarray, delta: np.ndarray, w: np.ndarray,
                  Mc: np.ndarray, consts: np.ndarray, Y: np.ndarray, L: np.ndarray,
                  Sd: np.ndarray, D: np.ndarray, ABd: np.ndarray, column_start: np.ndarray,
                  column_rows: np.ndarray, row_start: np.ndarray, row_columns: np.ndarray,
                  zero: Any, z_steps: np.ndarray, z_terminal: np.ndarray, work: Any) -> None:
    """Gradient, backward and forward passes and ``eta`` of sample ``j``, whose factors are
    ``Y`` (T, nv, nx), ``L`` (T, nv, nv), ``Sd`` (T, nx), ``D`` (ny,) and ``ABd`` (nx, ny + 1)
    (:func:`solve_project`)."""
    T = delta.shape[1]
    nx, nv = Y.shape[2], Y.shape[1]
    nlam = Mc.shape[1]
    ny = nx + nv
    x0, gx, gT = vectors[0], vectors[1], vectors[2]
    g2 = consts[:ny]
    two_rho_eta = consts[ny]
    gy, tt, eta, e, r, v, x, xn = work
    for k in range(T):
        for b in range(nlam):
            eta[b] = Mc[j, b, ny] - (delta[j, k, ny + b] - w[j, k, ny + b])
        for a in range(ny):
            g = (delta[j, k, a] - w[j, k, a]) * g2[a]
            if a < nx:
                g += gx[a]
            s = zero
            for b in range(nlam):
                s += Mc[j, b, a] * eta[b]
            gy[k, a] = (g + s * two_rho_eta) * D[a]
    for a in range(nx):
        e[a] = Sd[T - 1, a] + gT[a] * D[a]
    for k in range(T - 1, -1, -1):
        for a in range(nv):  # r = g_v + B_v^T e
            s = gy[k, nx + a]
            for q in range(column_start[nx + a], column_start[nx + a + 1]):
                b = column_rows[q]
                s += e[b] * ABd[b, nx + a]
            r[a] = s
        for a in range(nv):  # L t = r
            s = r[a]
            for b in range(a):
                s -= L[k, a, b] * tt[k, b]
            tt[k, a] = s * L[k, a, a]
        if k > 0:
            for a in range(nx):  # e <- S_k d + g_x + A^T e - Y^T t
                s = gy[k, a] + Sd[k - 1, a]
                for q in range(column_start[a], column_start[a + 1]):
                    b = column_rows[q]
                    s += e[b] * ABd[b, a]
                for b in range(nv):
                    s -= tt[k, b] * Y[k, b, a]
                xn[a] = s
            for a in range(nx):
                e[a] = xn[a]
    for a in range(nx):
        x[a] = x0[a] / D[a]
        z_steps[j, 0, a] = x0[a]
    for k in range(T):
        for a in range(nv - 1, -1, -1):  # v = -L^-T (Y x + t)
            s = tt[k, a]
            for b in range(nx):
                s += Y[k, a, b] * x[b]
            s = -s
            for b in range(a + 1, nv):
                s -= L[k, b, a] * v[b]
            v[a] = s * L[k, a, a]
            z_steps[j, k, nx + a] = v[a] * D[nx + a]
        for a in range(nx):  # x <- A x + B_v v + d
            s = ABd[a, ny]
            for q in range(row_start[a], row_start[a + 1]):
                b = row_columns[q]
                s += ABd[a, b] * (x[b] if b < nx else v[b - nx])
            xn[a] = s
        for a in range(nx):
            x[a] = xn[a]
            if k + 1 < T:
                z_steps[j, k + 1, a] = xn[a] * D[a]
            else:
                z_terminal[j, a] = xn[a] * D[a]
    for k in range(T):
        for b in range(nlam):
            s = Mc[j, b, ny]
            for a in range(ny):
                s += Mc[j, b, a] * z_steps[j, k, a]
            z_steps[j, k, ny + b] = s


@_jit
def _project(k: int, z: np.ndarray, w: np.ndarray, out: np.ndarray, nx: int, nlam: int,
             sqrt_lam: Any, sqrt_eta: Any, p: np.ndarray, shared: bool, box: np.ndarray,
             zero: Any) -> None:
    """C3+ projection of time step ``k`` of ``v = z + w`` (samples last: ``z``, ``w`` and
    ``out`` (T, ns, n)) into ``out``: ``x`` clipped to the box ``box`` (2, nx + nu) = (lower,
    upper) of one step's ``(x, u)`` (``+-inf`` where unbounded); every pair by the one closed
    form (:func:`c3bench.solvers.admm.projection.make_c3plus_pairs`, compiled for scalars);
    ``u`` replaced, when ``shared`` and ``n > 1``, by the weighted mean ``sum_j p_j v_{j,u}``
    (summed in sample order), then clipped to the box."""
    ns, n = w.shape[1], w.shape[2]
    nu = ns - nx - 2 * nlam
    for a in range(ns):
        for j in range(n):
            out[k, a, j] = z[k, a, j] + w[k, a, j]
    for a in range(nx):
        lower, upper = box[0, a], box[1, a]
        for j in range(n):
            out[k, a, j] = min(max(out[k, a, j], lower), upper)
    for b in range(nlam):
        for j in range(n):
            out[k, nx + b, j], out[k, ns - nlam + b, j] = _c3plus_pair(
                out[k, nx + b, j], out[k, ns - nlam + b, j], sqrt_lam, sqrt_eta)
    for a in range(nx + nlam, nx + nlam + nu):
        lower, upper = box[0, a - nlam], box[1, a - nlam]
        if shared and n > 1:
            s = zero
            for j in range(n):
                s += p[j] * out[k, a, j]
            s = min(max(s, lower), upper)
            for j in range(n):
                out[k, a, j] = s
        else:
            for j in range(n):
                out[k, a, j] = min(max(out[k, a, j], lower), upper)
