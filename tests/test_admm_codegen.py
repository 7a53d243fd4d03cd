"""Tests of the generated code (solvers/admm/compiled_ir.py and compiled_codegen.py, the
factorisation's backward step; compiled_passes_codegen.py, the linear passes): the backward
step is bit for bit the numba lane loops' step (the readable kernel) on random structures,
sizes, lane counts and precisions, failing pivots included; the whole compiled kernel with
and without generated code (step and passes) gives the same bits on random batches of 1 to 40
samples and on the cube's push; the disk cache and a failed compilation; the arrays the
generated code reads start on a cache line. No timing."""

from __future__ import annotations

import ctypes
from collections.abc import Callable
from typing import Any

import numpy as np
import pytest
from conftest import push_batches, random_lcs_problem

from c3bench.solvers.admm import compiled_codegen as codegen
from c3bench.solvers.admm import compiled_kernels as kernels
from c3bench.solvers.admm.compiled_solver import CompiledC3Plus
from c3bench.solvers.admm.options import C3Options

pytestmark = pytest.mark.usefixtures("compiled_kernels")

_SIGNATURE = ctypes.CFUNCTYPE(None, *([ctypes.c_void_p] * 7), ctypes.c_int64, ctypes.c_int64)


def _forget_generated(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(codegen, "_GENERATED", {})


def _bits(array: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(array).view(np.uint64 if array.itemsize == 8 else np.uint32)


def _step_inputs(nx: int, nv: int, lanes: int, density: float, dtype: Any, seed: int
                 ) -> tuple[kernels.Structure, np.ndarray, np.ndarray, np.ndarray]:
    """A random structure of ``[A B_v d]`` (an empty column and an empty ``d`` included
    when sparse), ``S`` (symmetric), the scaled ``[A B_v d]`` (zero off the structure) and
    ``H_y``; lane 1 gets an indefinite ``Q_vv`` (its pivots fail)."""
    rng = np.random.default_rng(seed)
    ny = nx + nv
    mask = rng.random((nx, ny + 1)) < density
    if density < 1:
        mask[:, ny] = False
        mask[:, rng.integers(ny)] = False
    pattern = kernels.structure(mask)
    S = rng.normal(size=(nx, nx, lanes))
    S = S + np.swapaxes(S, 0, 1)
    ABd = rng.normal(size=(nx, ny + 1, lanes)) * mask[:, :, None]
    Hy = rng.normal(size=(ny, ny, lanes))
    Hy = Hy + np.swapaxes(Hy, 0, 1) + 4 * ny * np.eye(ny)[:, :, None]
    Hy[nx:, nx:, 1] = -np.eye(nv)
    return pattern, S.astype(dtype), ABd.astype(dtype), Hy.astype(dtype)


def _lane_loop_step(k: int, nx: int, nv: int, pattern: kernels.Structure, S: np.ndarray,
                    ABd: np.ndarray, Hy: np.ndarray) -> tuple[np.ndarray, ...]:
    lanes, dtype = S.shape[2], S.dtype
    ny = nx + nv
    Y, L = np.zeros((nv, nx, lanes), dtype), np.zeros((nv, nv, lanes), dtype)
    Sd, fb = np.zeros((nx, lanes), dtype), np.full(lanes, -1, np.int64)
    kernels._riccati_lanes(k, lanes, nx, nv, dtype.type(0), dtype.type(1), S, ABd, Hy,
                           np.empty((nx, ny, lanes), dtype), np.empty((nv, ny, lanes), dtype),
                           np.empty(lanes, dtype), np.empty((nv, lanes), dtype), fb,
                           pattern.column_start, pattern.column_rows, Y, L, Sd)
    return S, Y, L, Sd, fb


def _generated_step(k: int, nx: int, nv: int, pattern: kernels.Structure, S: np.ndarray,
                    ABd: np.ndarray, Hy: np.ndarray) -> tuple[np.ndarray, ...]:
    lanes, dtype = S.shape[2], S.dtype
    table = codegen.step_table(pattern.column_start, pattern.column_rows, nx, nv, dtype,
                               [lanes], kernels.LANE_BLOCK + 1)
    address, width = table[lanes]
    assert address != 0 and lanes % width == 0, codegen.CODEGEN.failures
    Y, L = np.zeros((nv, nx, lanes), dtype), np.zeros((nv, nv, lanes), dtype)
    Sd, fb = np.zeros((nx, lanes), dtype), np.full(lanes, -1, np.int64)
    step: Callable[..., None] = _SIGNATURE(int(address))
    step(*(a.ctypes.data for a in (S, ABd, Hy, Y, L, Sd, fb)), k, lanes)
    return S, Y, L, Sd, fb


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
@pytest.mark.parametrize(("nx", "nv", "lanes", "density"), [
    (1, 1, 4, 1.0), (3, 2, 8, 0.5), (4, 5, 12, 0.4), (10, 10, 12, 0.35), (10, 10, 32, 0.35),
    (6, 3, 16, 1.0), (5, 7, 24, 0.2)])
def test_generated_step_is_the_lane_loops_bit_for_bit(nx: int, nv: int, lanes: int,
                                                     density: float, dtype: Any) -> None:
    pattern, S, ABd, Hy = _step_inputs(nx, nv, lanes, density, dtype, seed=nx * 100 + lanes)
    expected = _lane_loop_step(3, nx, nv, pattern, S.copy(), ABd, Hy)
    got = _generated_step(3, nx, nv, pattern, S.copy(), ABd, Hy)
    lower = np.tril(np.ones((nv, nv), dtype=bool))
    for name, a, b in zip(("S", "Y", "L", "Sd"), got[:4], expected[:4], strict=True):
        a, b = (a[lower], b[lower]) if name == "L" else (a, b)
        np.testing.assert_array_equal(_bits(a), _bits(b), err_msg=name)
    np.testing.assert_array_equal(got[4], expected[4])
    assert got[4][1] == 3 and expected[4][0] == -1  # lane 1's pivots failed at step 3


def _solve_all(n: int, precision: str, seed: int) -> list[tuple[np.ndarray, ...]]:
    mpc, lcs, x0 = random_lcs_problem(n, seed=seed)
    out = []
    for iterations in (10, 7):
        solver = CompiledC3Plus(mpc, C3Options(keep_iterates=False,
                                               admm_iterations=iterations), precision)
        solution = solver.solve(lcs, x0)
        out.append((solution.u, solution.delta, solution.w))
    return out


@pytest.mark.parametrize("precision", ["float64", "float32"])
@pytest.mark.parametrize("n", [1, 3, 16, 40])
def test_kernel_gives_the_same_bits_with_and_without_generated_code(
        n: int, precision: str, monkeypatch: pytest.MonkeyPatch) -> None:
    """Groups of one in-place block and, at 40 samples, blocks with a last one of 8 or 12
    lanes, both group sizes of a 10- and a 7-iteration plan."""
    generated = _solve_all(n, precision, seed=70 + n)
    monkeypatch.setenv(codegen.ENV_SWITCH, "0")
    assert not codegen.enabled()
    loops = _solve_all(n, precision, seed=70 + n)
    for a, b in zip(generated, loops, strict=True):
        for x, y in zip(a, b, strict=True):
            np.testing.assert_array_equal(_bits(x), _bits(y))


def test_cube_push_gives_the_same_bits_with_and_without_generated_code(
        monkeypatch: pytest.MonkeyPatch) -> None:
    push = push_batches(1, (1, 16))
    for lcs in push.batches.values():
        solutions = []
        for switch in ("1", "0"):
            monkeypatch.setenv(codegen.ENV_SWITCH, switch)
            solver = CompiledC3Plus(push.mpc, C3Options(keep_iterates=False))
            solutions.append(solver.solve(lcs, push.x0))
        for name in ("u", "delta", "w"):
            np.testing.assert_array_equal(_bits(getattr(solutions[0], name)),
                                          _bits(getattr(solutions[1], name)))


def test_object_code_is_kept_on_disk_and_loaded(tmp_path: Any,
                                                monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path))
    _forget_generated(monkeypatch)
    pattern, S, ABd, Hy = _step_inputs(3, 2, 8, 0.6, np.float64, seed=5)
    compiled, loaded = codegen.CODEGEN.compiled, codegen.CODEGEN.loaded
    first = _generated_step(2, 3, 2, pattern, S.copy(), ABd, Hy)
    assert codegen.CODEGEN.compiled == compiled + 1
    assert len(list((tmp_path / "c3bench_codegen").glob("*.o"))) == 1
    _forget_generated(monkeypatch)
    second = _generated_step(2, 3, 2, pattern, S.copy(), ABd, Hy)
    assert (codegen.CODEGEN.compiled, codegen.CODEGEN.loaded) == (compiled + 1, loaded + 1)
    for a, b in zip(first, second, strict=True):
        np.testing.assert_array_equal(a, b)


def test_a_failed_compilation_leaves_the_lane_loops(monkeypatch: pytest.MonkeyPatch) -> None:
    def broken(ir_text: str, function: str) -> int:
        raise RuntimeError("no code today")

    monkeypatch.setattr(codegen, "_address", broken)
    _forget_generated(monkeypatch)
    failures = len(codegen.CODEGEN.failures)
    pattern = kernels.structure(np.ones((2, 4), dtype=bool))
    table = codegen.step_table(pattern.column_start, pattern.column_rows, 2, 1, np.float64,
                               [4, 8], kernels.LANE_BLOCK + 1)
    assert not table.any()
    assert codegen.CODEGEN.failures[failures:] == ["RuntimeError: no code today"] * 2
    mpc, lcs, x0 = random_lcs_problem(3, seed=9)
    broken_run = CompiledC3Plus(mpc, C3Options(keep_iterates=False)).solve(lcs, x0)
    monkeypatch.setenv(codegen.ENV_SWITCH, "off")
    loops = CompiledC3Plus(mpc, C3Options(keep_iterates=False)).solve(lcs, x0)
    np.testing.assert_array_equal(broken_run.delta, loops.delta)


@pytest.mark.parametrize(("lanes", "dtype", "bits", "width"), [
    (12, np.float64, 512, 4), (32, np.float64, 512, 8), (32, np.float64, 256, 4),
    (16, np.float32, 512, 16), (24, np.float32, 256, 8), (4, np.float32, 128, 4)])
def test_vector_width(lanes: int, dtype: Any, bits: int, width: int,
                      monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(codegen, "_host_vector_bits", lambda: bits)
    assert codegen.vector_width(lanes, dtype) == width


def test_the_disk_cache_is_keyed_by_the_cpu(tmp_path: Any,
                                            monkeypatch: pytest.MonkeyPatch) -> None:
    """Object code compiled for one CPU (name and instruction-set features) is not loaded on
    another: it may use instructions the other lacks."""
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path))
    _forget_generated(monkeypatch)
    pattern, S, ABd, Hy = _step_inputs(2, 2, 4, 1.0, np.float64, seed=8)
    compiled = codegen.CODEGEN.compiled
    _generated_step(1, 2, 2, pattern, S.copy(), ABd, Hy)
    machine, cpu = codegen._target_machine()
    monkeypatch.setattr(codegen, "_TARGET", [(machine, cpu + " -avx512f")])
    _forget_generated(monkeypatch)
    _generated_step(1, 2, 2, pattern, S.copy(), ABd, Hy)
    assert codegen.CODEGEN.compiled == compiled + 2
    assert len(list((tmp_path / "c3bench_codegen").glob("*.o"))) == 2


@pytest.mark.parametrize("shape", [(7, 10, 10, 16), (10, 21, 16), (3,), (0, 4)])
@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_aligned_empty(shape: tuple[int, ...], dtype: Any) -> None:
    from c3bench.solvers.admm.compiled_factors import ALIGNMENT, aligned_empty

    for _ in range(5):
        array = aligned_empty(shape, dtype, 2.5)
        assert array.shape == shape and array.dtype == dtype and array.flags.c_contiguous
        assert array.ctypes.data % ALIGNMENT == 0 or array.size == 0
        assert np.all(array == 2.5)
        array[...] = 1.0  # writable, its own memory
        assert np.all(array == 1.0)


@pytest.mark.parametrize("samples", [1, 5, 16])
def test_arrays_the_generated_code_reads_start_on_a_cache_line(samples: int) -> None:
    from c3bench.solvers.admm.compiled_factors import ALIGNMENT, CompiledFactors

    factors = CompiledFactors.empty(2, samples, 5, 4, 3, np.dtype(np.float64))
    for array in (factors.Y, factors.L, factors.Sd, factors.D, factors.ABd):
        assert array.ctypes.data % ALIGNMENT == 0
    mpc, lcs, x0 = random_lcs_problem(samples, 7)
    solver = CompiledC3Plus(mpc, C3Options(keep_iterates=False, admm_iterations=3))
    assert solver.solve(lcs, x0).ok
    assert solver.kernel._arrays["Mt"].ctypes.data % ALIGNMENT == 0
