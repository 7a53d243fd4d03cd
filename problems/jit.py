"""The one numba decorator of every compiled kernel (the LCS build here, the ADMM kernels in
``solvers/admm``): machine code cached on disk, no reassociated sums, IEEE division.

It lives in the plant-free core so that both the core's compiled LCS build and the solvers'
kernels (which may import the core, not the reverse) use the same options.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, TypeVar, cast

import numba

__all__ = ["jit"]

F = TypeVar("F", bound=Callable[..., Any])


def jit(function: F) -> F:
    """``numba.njit(cache=True, fastmath=False, error_model="numpy")`` with the function's own
    type for mypy (Lam, Pitrou & Seibert, "Numba: a LLVM-based Python JIT compiler",
    LLVM-HPC 2015). ``cache=True`` keeps the machine code on disk; ``fastmath=False`` keeps
    every sum in its written order (results reproducible bit for bit); the numpy error model
    divides by IEEE rules instead of testing every divisor for zero (a branch that keeps a loop
    from vectorising): every divisor in these kernels is a positive pivot or scale."""
    return cast(F, numba.njit(cache=True, fastmath=False, error_model="numpy")(function))
