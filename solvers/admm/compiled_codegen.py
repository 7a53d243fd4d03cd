"""Machine code generated for one LCS structure: the compiled factorisation's backward step.

:func:`c3bench.solvers.admm.compiled_kernels.factorize_batch` runs the backward Riccati step
(:func:`~c3bench.solvers.admm.compiled_kernels._riccati_lanes`: ``S [A B_v d]``, ``Q_v``,
Cholesky ``Q_vv = L L^T``, ``Y = L^-1 Q_vx``, ``S_k = H_xx + A^T S A - Y^T Y``) as loops over
vector lanes, every multiply-add a short loop that loads and stores its accumulator. That
kernel is the readable one. This module writes the same step out for one structure of
``[A B_v d]`` (:class:`~c3bench.solvers.admm.compiled_kernels.Structure`), one lane stride
and one precision as LLVM IR:

* every product over the structural nonzeros is unrolled at generation time;
* the lanes are worked ``width`` at a time as LLVM vectors, each value loaded once;
* the whole step for those lanes is straight-line code, so the accumulators live in
  registers instead of memory.

The IR is compiled by LLVM through llvmlite (numba's own code generator, installed with it,
no C compiler needed) and called from the numba kernel through its address
(:func:`call_step`). The linear passes of each iteration are generated the same way
(:mod:`.compiled_passes_codegen`), through :func:`generated` here.

**Exactness.** The generated code performs the lane loops' operations in the same order:
the same sums from ``+0.0`` or from the same first entry, ``fsub`` where they subtract, the
pivot test ``Q_vv[a, a] > 0`` with a failed lane continuing on a unit pivot, ``1 /
sqrt``. It has no fast-math flags and no fused multiply-adds (LLVM fuses ``fmul`` and
``fadd`` only when asked). Its results are therefore the lane loops' bit for bit; the tests
compare them on random structures.

**Cost.** Generating and compiling the planar cube's step (``nx = nv = 10``, 77 structural
nonzeros, about 7,000 LLVM values) takes 0.4-0.6 s per (structure, lane stride, precision),
once per machine: the object code is kept on disk, where numba keeps its cache
(``NUMBA_CACHE_DIR``, else ``__pycache__`` beside this file), keyed by the IR, the CPU (its
name and instruction-set features) and LLVM's version. A later process loads it in about 2
ms. The seconds spent (:data:`CODEGEN`) count as compile time, like numba's JIT.
``C3BENCH_CODEGEN=0`` in the environment switches the generated code off; the lane loops
then run everything. A failure to generate or compile does the same and is recorded in
``CODEGEN.failures``. It never changes a result.

Measured on the 2-core EPYC VM (znver4, load average below 1), seven backward steps, bit for
bit equal to the lane loops:

* 12 lanes (one sample's 10 rho values): 72 -> 34 us;
* 32 lanes (16 samples, 2 rho values): 157 -> 60 us (eight-wide vectors on AVX-512).

References: Lattner & Adve, "LLVM: a compilation framework for lifelong program analysis &
transformation", CGO 2004 (the IR and code generator); specialising small dense kernels to
their sizes at run time, as in libxsmm (Heinecke et al., "LIBXSMM: accelerating small matrix
multiplications by runtime code generation", SC 2016).
"""

from __future__ import annotations

import hashlib
import os
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import Any, cast

import llvmlite.binding as llvm
import numpy as np
from llvmlite import ir
from numba import types
from numba.extending import intrinsic

__all__ = ["CODEGEN", "ENV_SWITCH", "Emitter", "call_step", "call_through_address", "enabled",
           "generated", "step_ir", "step_table", "vector_width"]

ENV_SWITCH = "C3BENCH_CODEGEN"
"""Environment variable: ``0``, ``off`` or ``false`` switches the generated code off."""
FORMAT = 2
"""Version of the generator, part of the disk cache's key (raise it when the IR or the calling
convention changes; 2: the passes take ``delta`` and ``w`` instead of their difference)."""
FUNCTION = "c3bench_riccati_step"


@dataclass
class CodegenRecord:
    """What generation cost in this process: seconds (generation, compilation, loading),
    functions compiled and loaded from the disk cache, and why any failed."""

    seconds: float = 0.0
    compiled: int = 0
    loaded: int = 0
    failures: list[str] = field(default_factory=list)


CODEGEN = CodegenRecord()


def enabled() -> bool:
    """Whether generated code is used (:data:`ENV_SWITCH` is not ``0``, ``off`` or ``false``)."""
    return os.environ.get(ENV_SWITCH, "1").strip().lower() not in ("0", "off", "false")


def _host_vector_bits() -> int:
    """The widest vector register of this CPU in bits (512 with AVX-512, 256 with AVX)."""
    try:
        features = llvm.get_host_cpu_features()
    except RuntimeError:
        return 128
    if features.get("avx512f", False):
        return 512
    return 256 if features.get("avx", False) else 128


def vector_width(lanes: int, dtype: Any) -> int:
    """Lanes per LLVM vector: the widest of 16, 8 and 4 that divides ``lanes`` and fits this
    CPU's registers (4 at least; LLVM splits a wider vector into registers)."""
    bits = _host_vector_bits()
    size = 8 * np.dtype(dtype).itemsize
    for width in (16, 8):
        if lanes % width == 0 and width * size <= bits:
            return width
    return 4


class Emitter:
    """Straight-line IR of one chunk of ``width`` lanes (``width`` 1: scalars): numbered
    values, each input loaded once."""

    def __init__(self, scalar: str, width: int) -> None:
        self.scalar = scalar
        self.vector = f"<{width} x {scalar}>" if width > 1 else scalar
        self.width = width
        self.zero = "zeroinitializer" if width > 1 else "0.0"
        self.one = _splat(scalar, width, "1.0") if width > 1 else "1.0"
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
    return "<" + ", ".join([f"{scalar} {value}"] * width) + ">"


def _columns(column_start: np.ndarray, column_rows: np.ndarray) -> list[list[int]]:
    return [[int(c) for c in column_rows[column_start[b]:column_start[b + 1]]]
            for b in range(len(column_start) - 1)]


def _products(e: Emitter, nx: int, nv: int, columns: list[list[int]], lanes: int
              ) -> tuple[dict[tuple[int, int], str], dict[tuple[int, int], str]]:
    """``S [A B_v]`` (``SAB``), ``S d`` (stored) and ``[Q_vx Q_vv]`` (lower part, ``Qv``)."""
    ny, zero = nx + nv, e.zero
    SAB: dict[tuple[int, int], str] = {}
    for b in range(ny):
        for a in range(nx):
            acc = zero
            for c in columns[b]:
                acc = e.multiply_add(acc, e.load("%S", (a * nx + c) * lanes),
                                     e.load("%AB", (c * (ny + 1) + b) * lanes))
            SAB[a, b] = acc
    for a in range(nx):
        acc = zero
        for c in columns[ny]:
            acc = e.multiply_add(acc, e.load("%S", (a * nx + c) * lanes),
                                 e.load("%AB", (c * (ny + 1) + ny) * lanes))
        e.store("%Sd", a * lanes, acc)
    Qv: dict[tuple[int, int], str] = {}
    for a in range(nv):
        for b in range(nx + a + 1):
            acc = e.load("%Hy", ((nx + a) * ny + b) * lanes)
            for c in columns[nx + a]:
                acc = e.multiply_add(acc, e.load("%AB", (c * (ny + 1) + nx + a) * lanes),
                                     SAB[c, b])
            Qv[a, b] = acc
    return SAB, Qv


def _cholesky(e: Emitter, nx: int, nv: int, Qv: dict[tuple[int, int], str], lanes: int
              ) -> tuple[dict[tuple[int, int], str], dict[int, str]]:
    """``Q_vv = L L^T`` with ``1 / L[a, a]`` on the diagonal; a lane whose pivot is not
    positive records ``k`` in ``fb`` (first failure) and continues on a unit pivot."""
    w, vector, one = e.width, e.vector, e.one
    bits = 64 if e.scalar == "double" else 32
    failed = e.emit(f"load <{w} x i64>, ptr %fb, align 8")
    k = e.emit(f"insertelement <{w} x i64> poison, i64 %k, i64 0")
    k = e.emit(f"shufflevector <{w} x i64> {k}, <{w} x i64> poison, <{w} x i32> zeroinitializer")
    L: dict[tuple[int, int], str] = {}
    inverse: dict[int, str] = {}
    for a in range(nv):
        for b in range(a + 1):
            sv = Qv[a, nx + b]
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
    e.lines.append(f"  store <{w} x i64> {failed}, ptr %fb, align 8")
    for a in range(nv):
        for b in range(a + 1):
            e.store("%L", (a * nv + b) * lanes, L[a, b])
    return L, inverse


def _update(e: Emitter, nx: int, nv: int, columns: list[list[int]], lanes: int,
            SAB: dict[tuple[int, int], str], Qv: dict[tuple[int, int], str],
            L: dict[tuple[int, int], str], inverse: dict[int, str]) -> None:
    """``Y = L^-1 Q_vx`` and ``S_k = H_xx + A^T S A - Y^T Y`` (upper triangle, mirrored)."""
    ny = nx + nv
    Y: dict[tuple[int, int], str] = {}
    for a in range(nv):
        for b in range(nx):
            acc = Qv[a, b]
            for c in range(a):
                acc = e.multiply_add(acc, L[a, c], Y[c, b], subtract=True)
            Y[a, b] = e.op("fmul", acc, inverse[a])
            e.store("%Y", (a * nx + b) * lanes, Y[a, b])
    for a in range(nx):
        for b in range(a, nx):
            acc = e.load("%Hy", (a * ny + b) * lanes)
            for c in columns[a]:
                acc = e.multiply_add(acc, e.load("%AB", (c * (ny + 1) + a) * lanes), SAB[c, b])
            for c in range(nv):
                acc = e.multiply_add(acc, Y[c, a], Y[c, b], subtract=True)
            e.store("%S", (a * nx + b) * lanes, acc)
            if b != a:
                e.store("%S", (b * nx + a) * lanes, acc)


def step_ir(nx: int, nv: int, column_start: np.ndarray, column_rows: np.ndarray, lanes: int,
            dtype: Any, width: int) -> str:
    """LLVM IR of ``void c3bench_riccati_step(S, ABd, Hy, Y, L, Sd, fb, k, count)``: the
    backward step of :func:`~c3bench.solvers.admm.compiled_kernels._riccati_lanes` for lanes
    ``0 .. count`` (a multiple of ``width``) of arrays whose lane axis has ``lanes`` entries
    (``S`` (nx, nx), ``ABd`` (nx, ny + 1), ``Hy`` (ny, ny), ``Y`` (nv, nx), ``L`` (nv, nv),
    ``Sd`` (nx,), lanes last, C order; ``fb`` (count,) int64), over the structural nonzeros
    ``column_start``, ``column_rows`` of ``[A B_v d]``."""
    scalar = "double" if np.dtype(dtype) == np.float64 else "float"
    e = Emitter(scalar, width)
    columns = _columns(column_start, column_rows)
    SAB, Qv = _products(e, nx, nv, columns, lanes)
    L, inverse = _cholesky(e, nx, nv, Qv, lanes)
    _update(e, nx, nv, columns, lanes, SAB, Qv, L, inverse)
    bits = 64 if scalar == "double" else 32
    vector = e.vector
    arrays = ("S", "AB", "Hy", "Y", "L", "Sd")
    chunk = "\n".join(f"  %{name} = getelementptr inbounds {scalar}, ptr %{name}0, i64 %lane"
                      for name in arrays)
    parameters = ", ".join(f"ptr noalias %{name}0" for name in arrays)
    return f"""declare {vector} @llvm.sqrt.v{width}f{bits}({vector})

define void @{FUNCTION}({parameters}, ptr noalias %fb0, i64 %k, i64 %count) {{
entry:
  %empty = icmp sle i64 %count, 0
  br i1 %empty, label %exit, label %chunk
chunk:
  %lane = phi i64 [0, %entry], [%next, %chunk]
{chunk}
  %fb = getelementptr inbounds i64, ptr %fb0, i64 %lane
{chr(10).join(e.lines)}
  %next = add i64 %lane, {width}
  %more = icmp slt i64 %next, %count
  br i1 %more, label %chunk, label %exit
exit:
  ret void
}}
"""


# --- compilation -------------------------------------------------------------------------------
_TARGET: list[tuple[Any, str]] = []
_ENGINES: list[Any] = []
"""The execution engines holding the loaded code (alive as long as the process)."""
_GENERATED: dict[tuple[Any, ...], tuple[int, int]] = {}
"""``(address, width)`` by what was generated (:func:`generated`)."""


def _target_machine() -> tuple[Any, str]:
    """LLVM's target machine for this CPU and the CPU's description (name and features: a
    cached object is only loaded on a CPU that has every instruction it may use)."""
    if not _TARGET:
        try:
            cpu, features = llvm.get_host_cpu_name(), llvm.get_host_cpu_features().flatten()
        except RuntimeError:
            cpu, features = "", ""
        target = llvm.Target.from_triple(llvm.get_process_triple())
        _TARGET.append((target.create_target_machine(cpu=cpu, features=features, opt=2,
                                                     reloc="pic", codemodel="jitdefault",
                                                     jit=True), f"{cpu} {features}"))
    return _TARGET[0]


def _cache_dir() -> Path:
    root = os.environ.get("NUMBA_CACHE_DIR")
    return (Path(root) if root else Path(__file__).parent / "__pycache__") / "c3bench_codegen"


def _object_code(ir_text: str) -> bytes:
    """The object code of ``ir_text`` for this CPU: from the disk cache, or compiled (and
    kept there when the directory is writable)."""
    machine, cpu = _target_machine()
    key = hashlib.sha256("\0".join((str(FORMAT), str(llvm.llvm_version_info),
                                    str(machine.triple), cpu, str(machine.target_data),
                                    ir_text)).encode()).hexdigest()
    path = _cache_dir() / f"{key}.o"
    if path.is_file():
        CODEGEN.loaded += 1
        return path.read_bytes()
    module = llvm.parse_assembly(ir_text)
    module.triple, module.data_layout = machine.triple, str(machine.target_data)
    module.verify()
    passes = llvm.create_pass_builder(machine, llvm.create_pipeline_tuning_options(speed_level=2))
    passes.getModulePassManager().run(module, passes)
    code = bytes(machine.emit_object(module))
    CODEGEN.compiled += 1
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        partial = path.with_suffix(f".{os.getpid()}.tmp")
        partial.write_bytes(code)
        os.replace(partial, path)
    except OSError:
        pass  # a read-only installation: compiled again by the next process
    return code


def _address(ir_text: str, function: str) -> int:
    """Load the object code of ``ir_text`` into an execution engine; ``function``'s address."""
    engine = llvm.create_mcjit_compiler(llvm.parse_assembly(""), _target_machine()[0])
    engine.add_object_file(llvm.ObjectFileRef.from_data(_object_code(ir_text)))
    engine.finalize_object()
    _ENGINES.append(engine)
    return int(engine.get_function_address(function))


def generated(key: tuple[Any, ...], build: Callable[[], str], function: str, width: int
              ) -> tuple[int, int]:
    """``(address, width)`` of ``function`` in the IR ``build()`` returns, compiled (or
    loaded from disk) once per process and ``key``; ``(0, 0)`` when :func:`enabled` is off
    or generating or compiling fails (recorded in :data:`CODEGEN`: the numba loops run)."""
    if not enabled():
        return 0, 0
    known = _GENERATED.get(key)
    if known is None:
        started = time.perf_counter()
        try:
            known = (_address(build(), function), width)
        except Exception as error:  # noqa: BLE001 (any LLVM failure: the numba loops run)
            CODEGEN.failures.append(f"{type(error).__name__}: {error}")
            known = (0, 0)
        _GENERATED[key] = known
        CODEGEN.seconds += time.perf_counter() - started
    return known


def step_table(column_start: np.ndarray, column_rows: np.ndarray, nx: int, nv: int,
               dtype: Any, lane_counts: Iterable[int], size: int) -> np.ndarray:
    """The generated steps for a structure and precision: an int64 table (size, 2) whose row
    ``lanes`` holds ``(address, width)`` of the step for arrays with ``lanes`` lanes
    (:func:`step_ir`), ``(0, 0)`` where none is generated. Rows for ``lane_counts`` are
    generated now (or loaded once per process, :func:`generated`). With :func:`enabled` off:
    a table of zeros."""
    table = np.zeros((size, 2), np.int64)
    if not enabled():
        return table
    key = (nx, nv, np.dtype(dtype).char, column_start.tobytes(), column_rows.tobytes())
    for lanes in lane_counts:
        if lanes % 4 == 0:
            width = vector_width(lanes, dtype)
            table[lanes] = generated(
                ("step", lanes, width, *key),
                partial(step_ir, nx, nv, column_start, column_rows, lanes, dtype, width),
                FUNCTION, width)
    return table


def call_through_address(context: Any, builder: Any, sig: Any, args: Any) -> Any:
    """numba intrinsic code of ``call(address, *operands)``: call the ``void`` function at the
    run-time ``address`` with each array operand's data pointer and each scalar operand as an
    int64 (the calling convention of :func:`step_ir` and of
    :func:`~c3bench.solvers.admm.compiled_passes_codegen.passes_ir`)."""
    opaque = ir.IntType(8).as_pointer()
    operands = []
    for kind, value in zip(sig.args[1:], args[1:], strict=True):
        if isinstance(kind, types.Array):
            data = context.make_array(kind)(context, builder, value).data
            operands.append(builder.bitcast(data, opaque))
        else:
            operands.append(context.cast(builder, value, kind, types.int64))
    function = ir.FunctionType(ir.VoidType(), [operand.type for operand in operands])
    builder.call(builder.inttoptr(args[0], function.as_pointer()), operands)
    return context.get_dummy_value()


@intrinsic
def _call_step(typingctx: Any, address: Any, S: Any, ABd: Any, Hy: Any, Y: Any, L: Any,
               Sd: Any, fb: Any, k: Any, count: Any) -> Any:
    """Call the generated step at ``address`` (:func:`step_ir`) on the arrays' data for
    lanes ``0 .. count`` (numba intrinsic: the address is a run-time value)."""
    return types.void(address, S, ABd, Hy, Y, L, Sd, fb, k, count), call_through_address


call_step = cast(Callable[..., None], _call_step)
"""``call_step(address, S, ABd, Hy, Y, L, Sd, fb, k, count)`` in numba code (the intrinsic
above, typed for its callers)."""
