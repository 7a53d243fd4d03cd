"""LLVM IR of the compiled factorisation's backward step, written out for one structure.

:func:`step_ir` writes :func:`~c3bench.solvers.admm.compiled_kernels._riccati_lanes` (``S [A
B_v d]``, ``Q_v``, Cholesky ``Q_vv = L L^T``, ``Y = L^-1 Q_vx``, ``S_k = H_xx + A^T S A - Y^T
Y``) as straight-line code over the structural nonzeros of ``[A B_v d]``, ``width`` lanes at
a time as LLVM vectors (:class:`Emitter`); :mod:`.compiled_codegen` compiles and calls it.

**Order of the work.** Every sum is the lane loops' sum, term by term; what is free is the
order in which the sums are written, and it decides how many values are alive at once. A
core has 16 vector registers without AVX-512 (32 with it), and the step's products have
about 3,000 multiply-adds over 180 entries of ``S [A B_v]``; written product by product (all
of ``S [A B_v]``, then all of ``Q_v``, then ``S_k``) most of those entries are spilled to the
stack and reloaded for every use. Here the step goes column by column: column ``b`` of ``S
[A B_v]`` (``nx`` values, kept in registers) is used at once by everything that needs it,
column ``b`` of ``Q_v = H_vy + B_v^T S [A B_v]`` and of ``H_xx + A^T S [A]`` (the part of
``S_k`` before ``Y^T Y``), and is then dead. The columns of ``B_v`` come first, so that the
Cholesky factorisation of ``Q_vv`` can start; its rows are interleaved with the columns of
``A``, so that the processor has independent work while a pivot's square root and division
are in flight. Each column reads ``S``, ``[A B_v d]`` and ``H_y`` through its own copy of
their pointers (:meth:`Emitter.launder`), so that LLVM loads them again from the cache
instead of keeping a load from an earlier column alive in a register or on the stack. Then
``Y`` column by column and ``S_k`` row by row, each row's ``Y`` column loaded once.

Measured on the 2-core EPYC VM (znver3, AVX2, load below 1), one backward step of 16 lanes,
the planar cube's structure, alternated with the product-by-product order in one process:
1.46 -> 1.23 and 1.55 -> 1.42 us per four lanes in two comparisons (stack accesses per four
lanes 3,550 -> 1,868), bit for bit the same results.

References: Lattner & Adve, "LLVM: a compilation framework for lifelong program analysis &
transformation", CGO 2004 (the IR); on ordering straight-line code for register pressure and
latency, Goodman & Hsu, "Code scheduling and register allocation in large basic blocks",
ICS 1988.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

__all__ = ["FUNCTION", "Emitter", "lane_loop", "step_ir", "structure_lists"]

FUNCTION = "c3bench_riccati_step"


class Emitter:
    """Straight-line IR of one chunk of ``width`` lanes (``width`` 1: scalars): numbered
    values, each input loaded once per pointer."""

    def __init__(self, dtype: Any, width: int) -> None:
        double = np.dtype(dtype) == np.float64
        self.scalar = "double" if double else "float"
        self.bits = 64 if double else 32
        self.vector = f"<{width} x {self.scalar}>" if width > 1 else self.scalar
        self.width = width
        self.zero = "zeroinitializer" if width > 1 else "0.0"
        self.one = _splat(self.scalar, width, "1.0") if width > 1 else "1.0"
        self.lines: list[str] = []
        self.count = 0
        self.loaded: dict[tuple[str, int], str] = {}

    def value(self) -> str:
        self.count += 1
        return f"%v{self.count}"

    def emit(self, text: str) -> str:
        """Emit ``<new value> = text``; returns the new value."""
        name = self.value()
        self.lines.append(f"  {name} = {text}")
        return name

    def launder(self, base: str) -> str:
        """A copy of the pointer ``base`` that LLVM cannot see through (an empty inline
        assembly statement): loads through it are not merged with loads through ``base`` or
        through other copies, so a value loaded again is read from the cache, not kept in a
        register across the code between. The statement captures ``base`` and may, for all
        LLVM knows, read or write through it: it is also an ordering barrier for every access
        through ``base`` and its copies (which is what keeps ``noalias`` true: loads through a
        copy are ordered against the stores through ``base`` in program order)."""
        return self.emit(f'call ptr asm sideeffect "", "=r,0"(ptr {base})')

    def load(self, base: str, offset: int) -> str:
        key = (base, offset)
        if key not in self.loaded:
            pointer = self.emit(f"getelementptr inbounds {self.scalar}, ptr {base}, i64 {offset}")
            self.loaded[key] = self.emit(f"load {self.vector}, ptr {pointer}, align 8")
        return self.loaded[key]

    def broadcast(self, base: str, offset: int) -> str:
        """The scalar ``base[offset]`` in every lane (loaded once)."""
        key = ("scalar " + base, offset)
        if key not in self.loaded:
            pointer = self.emit(f"getelementptr inbounds {self.scalar}, ptr {base}, i64 {offset}")
            value = self.emit(f"load {self.scalar}, ptr {pointer}, align 8")
            if self.width > 1:
                value = self.emit(f"insertelement {self.vector} poison, {self.scalar} {value}, "
                                  "i64 0")
                value = self.emit(f"shufflevector {self.vector} {value}, {self.vector} poison, "
                                  f"<{self.width} x i32> zeroinitializer")
            self.loaded[key] = value
        return self.loaded[key]

    def store(self, base: str, offset: int, value: str) -> None:
        pointer = self.emit(f"getelementptr inbounds {self.scalar}, ptr {base}, i64 {offset}")
        self.lines.append(f"  store {self.vector} {value}, ptr {pointer}, align 8")

    def op(self, name: str, left: str, right: str) -> str:
        return self.emit(f"{name} {self.vector} {left}, {right}")

    def multiply_add(self, accumulator: str, left: str, right: str, subtract: bool = False
                     ) -> str:
        """``accumulator + left right`` (or ``-``), rounded twice as the lane loops do."""
        return self.op("fsub" if subtract else "fadd", accumulator,
                       self.op("fmul", left, right))


def _splat(scalar: str, width: int, value: str) -> str:
    """The IR constant vector of ``width`` copies of ``value``."""
    return "<" + ", ".join([f"{scalar} {value}"] * width) + ">"


class _Step:
    """The backward step of one chunk of lanes (module docstring), emitted into ``e``."""

    def __init__(self, e: Emitter, nx: int, nv: int, columns: list[list[int]], lanes: int
                 ) -> None:
        self.e, self.nx, self.nv, self.columns, self.lanes = e, nx, nv, columns, lanes
        self.Qv: dict[tuple[int, int], str] = {}
        self.partial: dict[tuple[int, int], str] = {}
        """``H_xx + A^T S A`` (upper triangle): ``S_k`` before ``- Y^T Y``."""
        self.L: dict[tuple[int, int], str] = {}
        self.inverse: dict[int, str] = {}

    def column(self, b: int) -> None:
        """Column ``b`` of ``S [A B_v d]`` and, while it is in registers, column ``b`` of
        ``Q_v`` (``[Q_vx Q_vv]``, lower part) and of ``H_xx + A^T S A`` (upper triangle);
        column ``ny`` is ``S d``, stored."""
        e, nx, nv, lanes, columns = self.e, self.nx, self.nv, self.lanes, self.columns
        ny = nx + nv
        S, AB = e.launder("%S"), e.launder("%AB")
        SAB = []
        for a in range(nx):
            acc = e.zero
            for c in columns[b]:
                acc = e.multiply_add(acc, e.load(S, (a * nx + c) * lanes),
                                     e.load(AB, (c * (ny + 1) + b) * lanes))
            SAB.append(acc)
        if b == ny:
            for a in range(nx):
                e.store("%Sd", a * lanes, SAB[a])
            return
        Hy = e.launder("%Hy")
        for a in range(max(b - nx, 0), nv):
            acc = e.load(Hy, ((nx + a) * ny + b) * lanes)
            for c in columns[nx + a]:
                acc = e.multiply_add(acc, e.load(AB, (c * (ny + 1) + nx + a) * lanes), SAB[c])
            self.Qv[a, b] = acc
        for a in range(b + 1 if b < nx else 0):
            acc = e.load(Hy, (a * ny + b) * lanes)
            for c in columns[a]:
                acc = e.multiply_add(acc, e.load(AB, (c * (ny + 1) + a) * lanes), SAB[c])
            self.partial[a, b] = acc

    def cholesky_row(self, a: int, failed: str, k: str) -> str:
        """Row ``a`` of ``Q_vv = L L^T`` with ``1 / L[a, a]`` on the diagonal; a lane whose
        pivot is not positive records ``k`` in the failure vector ``failed`` (first failure
        only; the updated vector is returned) and continues on a unit pivot."""
        e, nx, L, inverse = self.e, self.nx, self.L, self.inverse
        w, vector, one, bits = e.width, e.vector, e.one, e.bits
        for b in range(a + 1):
            sv = self.Qv[a, nx + b]
            for c in range(b):
                sv = e.multiply_add(sv, L[a, c], L[b, c], subtract=True)
            if a != b:
                L[a, b] = e.op("fmul", sv, inverse[b])
                continue
            positive = e.emit(f"fcmp ogt {vector} {sv}, zeroinitializer")
            first = e.emit(f"icmp slt <{w} x i64> {failed}, zeroinitializer")
            fails = e.emit(f"xor <{w} x i1> {positive}, {_splat('i1', w, 'true')}")
            record = e.emit(f"and <{w} x i1> {fails}, {first}")
            failed = e.emit(f"select <{w} x i1> {record}, <{w} x i64> {k}, <{w} x i64> {failed}")
            pivot = e.emit(f"select <{w} x i1> {positive}, {vector} {sv}, {vector} {one}")
            root = e.emit(f"call {vector} @llvm.sqrt.v{w}f{bits}({vector} {pivot})")
            inverse[a] = L[a, a] = e.op("fdiv", one, root)
        return failed

    def products_and_cholesky(self) -> None:
        """The columns of ``B_v`` and ``d``, then the Cholesky rows interleaved with the
        columns of ``A``; ``L`` and the failures stored."""
        e, nx, nv, lanes = self.e, self.nx, self.nv, self.lanes
        w = e.width
        for b in range(nx, nx + nv + 1):
            self.column(b)
        failed = e.emit(f"load <{w} x i64>, ptr %fb, align 8")
        k = e.emit(f"insertelement <{w} x i64> poison, i64 %k, i64 0")
        k = e.emit(f"shufflevector <{w} x i64> {k}, <{w} x i64> poison, "
                   f"<{w} x i32> zeroinitializer")
        for i in range(max(nx, nv)):
            if i < nv:
                failed = self.cholesky_row(i, failed, k)
            if i < nx:
                self.column(i)
        e.lines.append(f"  store <{w} x i64> {failed}, ptr %fb, align 8")
        for a in range(nv):
            for b in range(a + 1):
                e.store("%L", (a * nv + b) * lanes, self.L[a, b])

    def update(self) -> None:
        """``Y = L^-1 Q_vx`` column by column (stored), then ``S_k = partial - Y^T Y`` row by
        row from the stored ``Y`` (mirrored into the lower triangle)."""
        e, nx, nv, lanes, L, inverse = self.e, self.nx, self.nv, self.lanes, self.L, self.inverse
        Y: dict[tuple[int, int], str] = {}
        for b in range(nx):
            for a in range(nv):
                acc = self.Qv[a, b]
                for c in range(a):
                    acc = e.multiply_add(acc, L[a, c], Y[c, b], subtract=True)
                Y[a, b] = e.op("fmul", acc, inverse[a])
                e.store("%Y", (a * nx + b) * lanes, Y[a, b])
        for a in range(nx):
            stored = e.launder("%Y")
            row = [e.load(stored, (c * nx + a) * lanes) for c in range(nv)]
            for b in range(a, nx):
                acc = self.partial[a, b]
                for c in range(nv):
                    acc = e.multiply_add(acc, row[c], e.load(stored, (c * nx + b) * lanes),
                                         subtract=True)
                e.store("%S", (a * nx + b) * lanes, acc)
                if b != a:
                    e.store("%S", (b * nx + a) * lanes, acc)


def structure_lists(start: np.ndarray, entries: np.ndarray) -> list[list[int]]:
    """The compressed lists ``entries[start[b]:start[b + 1]]`` of a structure (its rows by
    column, or columns by row) as Python lists."""
    return [[int(c) for c in entries[start[b]:start[b + 1]]] for b in range(len(start) - 1)]


def lane_loop(function: str, parameters: str, lane_arrays: Sequence[str], e: Emitter,
              prologue: str = "", declarations: str = "", chunk: str = "") -> str:
    """LLVM IR of ``void function(parameters, i64 %count)``: ``e``'s straight-line code run
    for lanes ``0, width, ... < count``, with ``%name`` the lane's element of each
    ``%name0`` of ``lane_arrays`` (``chunk``: more per-lane lines; ``prologue``: lines of
    the entry block; ``declarations``: before the function)."""
    pointers = "\n".join(f"  %{name} = getelementptr inbounds {e.scalar}, ptr %{name}0, i64 %lane"
                         for name in lane_arrays)
    body = "\n".join(e.lines)
    return f"""{declarations}
define void @{function}({parameters}, i64 %count) {{
entry:
{prologue}  %empty = icmp sle i64 %count, 0
  br i1 %empty, label %exit, label %chunk
chunk:
  %lane = phi i64 [0, %entry], [%next, %chunk]
{pointers}
{chunk}{body}
  %next = add i64 %lane, {e.width}
  %more = icmp slt i64 %next, %count
  br i1 %more, label %chunk, label %exit
exit:
  ret void
}}
"""


def step_ir(nx: int, nv: int, column_start: np.ndarray, column_rows: np.ndarray, lanes: int,
            dtype: Any, width: int) -> str:
    """LLVM IR of ``void c3bench_riccati_step(S, ABd, Hy, Y, L, Sd, fb, k, count)``: the
    backward step of :func:`~c3bench.solvers.admm.compiled_kernels._riccati_lanes` for lanes
    ``0 .. count`` (a multiple of ``width``) of arrays whose lane axis has ``lanes`` entries
    (``S`` (nx, nx), ``ABd`` (nx, ny + 1), ``Hy`` (ny, ny), ``Y`` (nv, nx), ``L`` (nv, nv),
    ``Sd`` (nx,), lanes last, C order; ``fb`` (count,) int64), over the structural nonzeros
    ``column_start``, ``column_rows`` of ``[A B_v d]``, in the order of the module
    docstring."""
    e = Emitter(dtype, width)
    step = _Step(e, nx, nv, structure_lists(column_start, column_rows), lanes)
    step.products_and_cholesky()
    step.update()
    arrays = ("S", "AB", "Hy", "Y", "L", "Sd")
    parameters = ", ".join(f"ptr noalias %{name}0" for name in arrays)
    return lane_loop(FUNCTION, f"{parameters}, ptr noalias %fb0, i64 %k", arrays, e,
                     declarations=f"declare {e.vector} @llvm.sqrt.v{width}f{e.bits}({e.vector})\n",
                     chunk="  %fb = getelementptr inbounds i64, ptr %fb0, i64 %lane\n")
