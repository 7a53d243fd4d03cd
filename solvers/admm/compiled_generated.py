"""Which generated code a compiled C3+ kernel hands to its numba calls, remembered per structure.

:class:`GeneratedCode` asks :mod:`.compiled_codegen` (the factorisation's backward step, a
table by lane count) and :mod:`.compiled_passes_codegen` (the linear passes) for the code of
the current batch's structure and sizes, and remembers the answers while they stay the same,
so that a control step pays a dictionary lookup, not a hash of the structure. Everything it
returns is a small int64 array in the layout the numba kernels read; zeros mean "run the numba
loops".
"""

from __future__ import annotations

from collections.abc import Hashable
from typing import Any

import numpy as np

from c3bench.solvers.admm import compiled_codegen as codegen
from c3bench.solvers.admm import compiled_kernels as kernels
from c3bench.solvers.admm.compiled_passes_codegen import passes_address

__all__ = ["GeneratedCode"]

_REMEMBERED = 16
"""Answers kept per kernel (structures x group sizes x factor widths of recent steps)."""


class GeneratedCode:
    """The generated code of one kernel's recent structures (module docstring)."""

    def __init__(self) -> None:
        self._memo: dict[tuple[Any, ...], np.ndarray] = {}

    def _remember(self, key: tuple[Any, ...], value: np.ndarray) -> np.ndarray:
        if len(self._memo) >= _REMEMBERED:
            self._memo.clear()
        self._memo[key] = value
        return value

    def steps(self, structure_key: Hashable, pattern: kernels.Structure, n: int, nx: int,
              nv: int, dtype: Any, slots: tuple[int, ...]) -> np.ndarray:
        """The ``steps`` table of :func:`kernels.factorize_batch` for factorising ``slots``
        rho values of ``n`` samples at a time (:func:`codegen.step_table`)."""
        key = ("steps", structure_key, n, slots)
        known = self._memo.get(key)
        if known is not None:
            return known
        lanes = [kernels.work_lanes(m * n) for m in slots]
        return self._remember(key, codegen.step_table(
            pattern.column_start, pattern.column_rows, nx, nv, dtype, lanes,
            kernels.LANE_BLOCK + 1))

    def passes(self, structure_key: Hashable, pattern: kernels.Structure, n: int, nx: int,
               nv: int, nlam: int, T: int, factor_lanes: int, dtype: Any) -> np.ndarray:
        """``generated`` of :func:`~c3bench.solvers.admm.compiled_passes.solve_project`:
        ``(address, width, factor_lanes, n)`` of the passes for factors with
        ``factor_lanes`` lanes (:func:`passes_address`)."""
        key = ("passes", structure_key, n, factor_lanes)
        known = self._memo.get(key)
        if known is not None:
            return known
        address, width = passes_address(nx, nv, nlam, T, pattern, n, factor_lanes, dtype)
        return self._remember(key, np.array([address, width, factor_lanes, n], np.int64))
