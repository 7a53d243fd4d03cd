"""Machine code generated for one LCS structure: the linear passes of a compiled ADMM iteration.

:func:`c3bench.solvers.admm.compiled_passes.iterate_in_lanes` computes, for every sample, the
gradient of the QP step, the backward and forward passes of the Riccati recursion and
``eta`` as numba loops (over samples as vector lanes from
:data:`~c3bench.solvers.admm.compiled_passes.LANE_SOLVE` samples on, a sample at a time
below). Those loops are the readable kernel. This module writes the same arithmetic out for
one structure of ``[A B_v d]``, horizon, batch size, factor lane stride and precision as LLVM
IR, the way :mod:`.compiled_ir` does for the factorisation's backward step:

* every product unrolled over its structural nonzeros and every time step unrolled;
* the samples worked ``width`` at a time as LLVM vectors (``width`` 1: scalar code);
* every factor entry loaded once.

It is compiled and cached by :mod:`.compiled_codegen`. It performs the numba loops' operations
in the same order (both of them share one order: the sums of the one-sample loops and of the
lane loops run over the same terms in the same sequence), without fast-math flags, so its
``z`` is theirs bit for bit. The projection and the dual update that follow stay numba code.

Inputs (lanes last, C order): ``delta`` and ``w`` (T, ns, n; ``dw = delta - w`` is formed
as each entry is loaded, rounded once as the lane loops' difference is), ``[M c]`` (nlam, ny
+ 1, n),
``consts`` (``-2 G_y``, ``2 rho_eta``, ...), ``vectors`` (``x0``, ``g_x``, ``g_T``), the
factors of one slot (``Y``, ``L``, ``Sd``, ``D``, ``ABd`` from their first lane, lane stride
``factor_lanes``); output ``zt`` (T + 1, ns, n): ``z`` of every step, row ``T`` the
terminal state.

References: as :mod:`c3bench.solvers.admm.compiled_passes` (the Riccati recursion's linear
passes, Rawlings, Mayne & Diehl, *Model Predictive Control*, 2nd ed., section 1.3.3) and
:mod:`.compiled_ir` (generated straight-line code).
"""

from __future__ import annotations

from collections.abc import Callable
from functools import partial
from typing import Any, cast

import numpy as np
from numba import types
from numba.extending import intrinsic

from c3bench.solvers.admm.compiled_codegen import call_through_address, generated, vector_width
from c3bench.solvers.admm.compiled_ir import Emitter, lane_loop, structure_lists

__all__ = ["FUNCTION", "call_passes", "passes_address", "passes_ir"]

FUNCTION = "c3bench_linear_passes"


class _Layout:
    """Offsets of the inputs and output in one chunk (``n`` the samples' stride, ``W`` the
    factors')."""

    def __init__(self, nx: int, nv: int, nlam: int, T: int, n: int, W: int) -> None:
        self.nx, self.nv, self.nlam, self.T, self.n, self.W = nx, nv, nlam, T, n, W
        self.ny = nx + nv
        self.ns = self.ny + nlam

    def iterate(self, k: int, a: int) -> int:
        return (k * self.ns + a) * self.n

    def M(self, b: int, a: int) -> int:
        return (b * (self.ny + 1) + a) * self.n

    def zt(self, k: int, a: int) -> int:
        return (k * self.ns + a) * self.n

    def Y(self, k: int, a: int, b: int) -> int:
        return ((k * self.nv + a) * self.nx + b) * self.W

    def L(self, k: int, a: int, b: int) -> int:
        return ((k * self.nv + a) * self.nv + b) * self.W

    def Sd(self, k: int, a: int) -> int:
        return (k * self.nx + a) * self.W

    def D(self, a: int) -> int:
        return a * self.W

    def AB(self, a: int, b: int) -> int:
        return (a * (self.ny + 1) + b) * self.W


def _difference(e: Emitter, s: _Layout, k: int, a: int) -> str:
    """``dw = delta - w`` of step ``k``, entry ``a`` (each is used once)."""
    return e.op("fsub", e.load("%delta", s.iterate(k, a)), e.load("%w", s.iterate(k, a)))


def _gradient(e: Emitter, s: _Layout, k: int) -> list[str]:
    """``g_y`` of step ``k``, scaled by ``D`` (``solve_project``'s gradient)."""
    ny, nx = s.ny, s.nx
    eta = [e.op("fsub", e.load("%M", s.M(b, ny)), _difference(e, s, k, ny + b))
           for b in range(s.nlam)]
    two_rho_eta = e.broadcast("%c", ny)
    gy = []
    for a in range(ny):
        acc = e.zero
        for b in range(s.nlam):
            acc = e.multiply_add(acc, e.load("%M", s.M(b, a)), eta[b])
        g = e.op("fmul", _difference(e, s, k, a), e.broadcast("%c", a))
        if a < nx:
            g = e.op("fadd", g, e.broadcast("%vec", nx + a))
        g = e.op("fadd", g, e.op("fmul", acc, two_rho_eta))
        gy.append(e.op("fmul", g, e.load("%D", s.D(a))))
    return gy


def _backward(e: Emitter, s: _Layout, gy: list[list[str]], columns: list[list[int]]
              ) -> list[list[str]]:
    """``t_k = L^-1 r`` of every step (the backward pass)."""
    nx, nv, T = s.nx, s.nv, s.T
    g_T = [e.op("fmul", e.broadcast("%vec", 2 * nx + a), e.load("%D", s.D(a)))
           for a in range(nx)]
    costate = [e.op("fadd", e.load("%Sd", s.Sd(T - 1, a)), g_T[a]) for a in range(nx)]
    tt: list[list[str]] = [[] for _ in range(T)]
    for k in range(T - 1, -1, -1):
        r = []
        for a in range(nv):
            acc = gy[k][nx + a]
            for b in columns[nx + a]:
                acc = e.multiply_add(acc, costate[b], e.load("%AB", s.AB(b, nx + a)))
            r.append(acc)
        for a in range(nv):
            acc = r[a]
            for b in range(a):
                acc = e.multiply_add(acc, e.load("%L", s.L(k, a, b)), tt[k][b], subtract=True)
            tt[k].append(e.op("fmul", acc, e.load("%L", s.L(k, a, a))))
        if k == 0:
            break
        following = []
        for a in range(nx):
            acc = e.op("fadd", gy[k][a], e.load("%Sd", s.Sd(k - 1, a)))
            for b in columns[a]:
                acc = e.multiply_add(acc, costate[b], e.load("%AB", s.AB(b, a)))
            for b in range(nv):
                acc = e.multiply_add(acc, tt[k][b], e.load("%Y", s.Y(k, b, a)), subtract=True)
            following.append(acc)
        costate = following
    return tt


def _forward(e: Emitter, s: _Layout, tt: list[list[str]], rows: list[list[int]]) -> None:
    """The rollout with ``v = -L^-T (Y x + t_k)``, ``z`` scaled back by ``D`` into ``zt`` and
    ``eta = M y + c``, step by step: each step's ``z`` is stored and its ``eta`` formed as soon
    as its ``v`` is known, so that no step's values stay alive to the end of the rollout
    (written after the whole rollout, they were spilled: the passes about 5 % faster on the
    AVX2 VM, 4.84-4.90 -> 4.57-4.66 us per four samples alternated, bit for bit the same)."""
    nx, nv, ny, T = s.nx, s.nv, s.ny, s.T
    x0 = [e.broadcast("%vec", a) for a in range(nx)]
    x = [e.op("fdiv", x0[a], e.load("%D", s.D(a))) for a in range(nx)]
    z_x = x0
    for k in range(T):
        r = []
        for a in range(nv):
            acc = tt[k][a]
            for b in range(nx):
                acc = e.multiply_add(acc, e.load("%Y", s.Y(k, a, b)), x[b])
            r.append(acc)
        v = [""] * nv
        for a in range(nv - 1, -1, -1):
            acc = e.emit(f"fneg {e.vector} {r[a]}")
            for b in range(a + 1, nv):
                acc = e.multiply_add(acc, e.load("%L", s.L(k, b, a)), v[b], subtract=True)
            v[a] = e.op("fmul", acc, e.load("%L", s.L(k, a, a)))
        z = z_x + [e.op("fmul", v[a], e.load("%D", s.D(nx + a))) for a in range(nv)]
        for a, value in enumerate(z):
            e.store("%zt", s.zt(k, a), value)
        for b in range(s.nlam):
            acc = e.load("%M", s.M(b, ny))
            for a in range(ny):
                acc = e.multiply_add(acc, e.load("%M", s.M(b, a)), z[a])
            e.store("%zt", s.zt(k, ny + b), acc)
        following = []
        for a in range(nx):
            acc = e.load("%AB", s.AB(a, ny))
            for b in rows[a]:
                acc = e.multiply_add(acc, e.load("%AB", s.AB(a, b)), x[b] if b < nx else v[b - nx])
            following.append(acc)
        x = following
        z_x = [e.op("fmul", x[a], e.load("%D", s.D(a))) for a in range(nx)]
    for a, value in enumerate(z_x):
        e.store("%zt", s.zt(T, a), value)


def passes_ir(nx: int, nv: int, nlam: int, T: int, column_start: np.ndarray,
              column_rows: np.ndarray, row_start: np.ndarray, row_columns: np.ndarray,
              samples: int, factor_lanes: int, dtype: Any, width: int) -> str:
    """LLVM IR of ``void c3bench_linear_passes(delta, w, M, consts, vectors, Y, L, Sd, D, ABd,
    zt, count)`` for samples ``0 .. count`` (a multiple of ``width``; module docstring)."""
    e = Emitter(dtype, width)
    s = _Layout(nx, nv, nlam, T, samples, factor_lanes)
    gy = [_gradient(e, s, k) for k in range(T)]
    tt = _backward(e, s, gy, structure_lists(column_start, column_rows))
    _forward(e, s, tt, structure_lists(row_start, row_columns))
    parameters = ", ".join(f"ptr noalias %{name}0" for name in
                           ("delta", "w", "M", "c", "vec", "Y", "L", "Sd", "D", "AB", "zt"))
    prologue = (f"  %c = getelementptr inbounds {e.scalar}, ptr %c0, i64 0\n"
                f"  %vec = getelementptr inbounds {e.scalar}, ptr %vec0, i64 0\n")
    return lane_loop(FUNCTION, parameters, ("delta", "w", "M", "zt", "Y", "L", "Sd", "D", "AB"),
                     e, prologue=prologue)


def passes_address(nx: int, nv: int, nlam: int, T: int, pattern: Any, samples: int,
                   factor_lanes: int, dtype: Any) -> tuple[int, int]:
    """``(address, width)`` of the passes generated for these sizes and structure
    (``pattern`` a :class:`~c3bench.solvers.admm.compiled_kernels.Structure`), ``(0, 0)``
    when generated code is off or failed (:func:`.compiled_codegen.generated`)."""
    width = vector_width(samples, dtype) if samples % 4 == 0 else 1
    arrays = (pattern.column_start, pattern.column_rows, pattern.row_start, pattern.row_columns)
    key = ("passes", nx, nv, nlam, T, samples, factor_lanes, np.dtype(dtype).char, width,
           *(np.asarray(a).tobytes() for a in arrays))
    return generated(key, partial(passes_ir, nx, nv, nlam, T, *arrays, samples, factor_lanes,
                                  dtype, width), FUNCTION, width)


@intrinsic
def _call_passes(typingctx: Any, address: Any, delta: Any, w: Any, M: Any, consts: Any,
                 vectors: Any, Y: Any, L: Any, Sd: Any, D: Any, ABd: Any, zt: Any, count: Any
                 ) -> Any:
    """Call the generated passes at ``address`` on the arrays' data (numba intrinsic)."""
    signature = types.void(address, delta, w, M, consts, vectors, Y, L, Sd, D, ABd, zt, count)
    return signature, call_through_address


call_passes = cast(Callable[..., None], _call_passes)
"""``call_passes(address, delta, w, M, consts, vectors, Y, L, Sd, D, ABd, zt, count)`` in numba
code (the intrinsic above, typed for its callers)."""
