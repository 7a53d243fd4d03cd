"""Machine code generated for one LCS structure: the compiled factorisation's backward step.

:func:`c3bench.solvers.admm.compiled_kernels.factorize_batch` runs the backward Riccati step
(:func:`~c3bench.solvers.admm.compiled_kernels._riccati_lanes`: ``S [A B_v d]``, ``Q_v``,
Cholesky ``Q_vv = L L^T``, ``Y = L^-1 Q_vx``, ``S_k = H_xx + A^T S A - Y^T Y``) as loops over
vector lanes, every multiply-add a short loop that loads and stores its accumulator. That
kernel is the readable one. This module writes the same step out for one structure of
``[A B_v d]`` (:class:`~c3bench.solvers.admm.compiled_kernels.Structure`), one lane stride
and one precision as LLVM IR:

* every product over the structural nonzeros is unrolled at generation time;
* the lanes are worked ``width`` at a time as LLVM vectors;
* the whole step for those lanes is straight-line code, so the accumulators live in
  registers instead of memory, written in an order that keeps few values alive at once
  (:mod:`.compiled_ir`, which writes the IR; this module compiles, caches and calls it).

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
bit equal to the lane loops, with the step written product by product (before the
column-by-column order of :mod:`.compiled_ir`):

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

from c3bench.solvers.admm.compiled_ir import FUNCTION, step_ir

__all__ = ["CODEGEN", "ENV_SWITCH", "call_step", "call_through_address", "enabled",
           "generated", "step_ir", "step_table", "vector_width"]

ENV_SWITCH = "C3BENCH_CODEGEN"
"""Environment variable: ``0``, ``off`` or ``false`` switches the generated code off."""
FORMAT = 3
"""Version of the generator, part of the disk cache's key (raise it when the IR or the calling
convention changes; 2: the passes take ``delta`` and ``w`` instead of their difference; 3: the
step column by column, :mod:`.compiled_ir`)."""


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
