"""The arithmetic of one C3+ control step's ADMM, and the machine's dense matmul rate.

**Flop model** (:func:`admm_flops`). Floating-point operations of the batched Riccati C3+
ADMM of :mod:`solvers.fast` (:func:`solvers.fast.factorize`, :func:`solvers.fast.solve_lq`,
``FastC3Plus._qp_solve``, :func:`solvers.fast.project_c3plus_batch`, the dual update), counted
operation by operation from those functions. Conventions (the usual dense linear-algebra
ones, Golub and Van Loan, *Matrix Computations*, 4th ed., section 1.1.15): a product of an
``(m, k)`` by a ``(k, p)`` matrix costs ``2 m k p`` flops, an elementwise addition, scaling
or clamp one flop per entry, the inverse of an ``n x n`` matrix ``2 n^3`` (LU ``2/3 n^3`` plus
``getri``'s ``4/3 n^3``), a comparison one flop, copies and selections none. With
``nv = nlam + nu``, ``ny = nx + nv`` and ``ns = ny + nlam`` (``eta`` has ``nlam`` entries),
per sample:

* **Riccati factorisation**, per rho value and time step (``factorize``'s loop body)::

      S [A Bv d]                      2 nx^2 (ny + 1)
      Bv^T (S [A Bv]) + H_v           2 nv nx ny + nv ny
      Q_vv^-1                         2 nv^3
      G_v [Q_vx  Bv^T]                4 nv^2 nx
      K += G_v (Q_vv K + Q_vx)        4 nv^2 nx + 2 nv nx
      A_cl = A + Bv K                 2 nx^2 nv + nx^2
      S = A^T S A + H_xx + Q_vx^T K   2 nx^3 + 2 nx^2 nv + 2 nx^2
      symmetrise                      2 nx^2

  plus, once per rho value, the stage Hessian ``H_y(rho)`` (``2 ny^2``) and the Jacobi
  scaling (``2 ny`` for ``D``, ``2 ny^2 + 4 nx^2 + 2 nx nv + nx`` to scale ``H_y``, ``A``,
  ``P_T``, ``Bv``, ``d``); and once per control step ``M^T M`` (``2 ny^2 nlam``).
* **QP step**, per ADMM iteration: the gradient ``g_y`` (``T (ns + 3 ny + nx + nlam + 2 ny
  nlam)``), the linear passes of ``solve_lq`` (scaling ``T ny + 2 nx``, ``W_g g_v``
  ``2 T (nv + nx) nv``, shifts ``(2 T - 1) nx``, the backward and forward passes
  ``T (4 (nv + nx) nx + 2 (nv + nx))``, ``Bv kk + d`` ``T (2 nx nv + nx)``, unscaling
  ``T ny``, plus ``nx`` for ``e_T``) and ``eta = M y + c`` (``T (2 nlam ny + nlam)``).
* **Projection**, per iteration: ``v = z + w`` (``T ns``), per complementarity pair two
  clamps, two scalings and one comparison (``5 T nlam``), and with shared inputs over
  ``n > 1`` samples the weighted mean of ``u`` (``2 T nu`` per sample).
* **Dual update**, per iteration: ``z - delta`` and ``w + (z - delta)`` (``2 T ns``).

For the planar cube (``nx = 10``, ``nlam = 6``, ``nu = 2``, ``T = 7``, 10 iterations with 10
rho values) this is about 1.47 MFLOP per sample, 90 % of it in the factorisations (1.29 and
89 % before the numpy code refined its gains, :mod:`solvers.riccati`).

**Matmul rate** (:func:`matmul_rate`): the best of ``repeats`` timed ``numpy.matmul`` calls
of two ``size x size`` matrices (``2 size^3`` flops; 256 fits in a core's L2 cache),
BLAS pinned to one thread as the timed control steps are; :func:`machine_rates` measures
float64 and float32 at the start of a run: the machine's best. :class:`MatmulProbe` samples
the same product through the run, once per round of timed steps (the median of
:data:`MATMUL_PROBE_REPEATS` products after an untimed one, so the operands are in cache as
a warm step's are), and gives the median over the rounds: the rate the machine delivered
while the steps were timed, the statistic a median step time compares with (measured on the
2-core EPYC VM: 40-43 GFLOP/s through a run against a best of 49-52 at its start and end).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np

from c3bench.problems.errors import InputError
from c3bench.problems.names import Precision

MATMUL_SIZE = 256
"""Side of the matrices of :func:`matmul_rate`."""
MATMUL_REPEATS = 15
"""Timed products of :func:`matmul_rate` (the best counts)."""
MATMUL_PROBE_REPEATS = 3
"""Timed products of one :meth:`MatmulProbe.sample` (their median counts)."""


@dataclass(frozen=True)
class AdmmFlops:
    """Flops of one control step's ADMM, all samples together, by part (module docstring)."""

    factorisation: float
    """Riccati factorisations of every rho value (with ``M^T M``, stage Hessians, scaling)."""
    qp_passes: float
    """Gradients, backward and forward passes and ``eta`` of every iteration."""
    projection: float
    """Projections (with the shared-input mean) of every iteration."""
    dual: float
    """Dual updates of every iteration."""

    @property
    def total(self) -> float:
        return self.factorisation + self.qp_passes + self.projection + self.dual

    @property
    def factorisation_share(self) -> float:
        """Fraction of :attr:`total` in the factorisations."""
        return self.factorisation / self.total if self.total > 0 else math.nan


def riccati_step_flops(nx: int, nv: int) -> int:
    """Flops of one time step of :func:`solvers.fast.factorize`'s backward loop, one sample
    (with the gain's refinement ``K += G_v (Q_vv K + Q_vx)``: ``4 nv^2 nx + 2 nv nx``)."""
    ny = nx + nv
    return (2 * nx * nx * (ny + 1) + 2 * nv * nx * ny + nv * ny + 2 * nv ** 3
            + 4 * nv * nv * nx + 4 * nv * nv * nx + 2 * nv * nx + 2 * nx * nx * nv + nx * nx
            + 2 * nx ** 3 + 2 * nx * nx * nv + 2 * nx * nx + 2 * nx * nx)


def factorisation_flops(nx: int, nv: int, horizon: int) -> int:
    """Flops of one factorisation (one rho value, one sample): ``T`` loop steps plus the
    stage Hessian and the Jacobi scaling."""
    ny = nx + nv
    setup = 2 * ny * ny + 2 * ny + 2 * ny * ny + 4 * nx * nx + 2 * nx * nv + nx
    return horizon * riccati_step_flops(nx, nv) + setup


def qp_pass_flops(nx: int, nlam: int, nu: int, horizon: int) -> int:
    """Flops of one QP step after the factorisation (gradient, ``solve_lq``, ``eta``), one
    sample."""
    nv = nlam + nu
    ny, T = nx + nv, horizon
    ns = ny + nlam
    gradient = T * (ns + 3 * ny + nx + nlam + 2 * ny * nlam)
    passes = (T * ny + 2 * nx + 2 * T * (nv + nx) * nv + (2 * T - 1) * nx + nx
              + T * (4 * (nv + nx) * nx + 2 * (nv + nx)) + T * (2 * nx * nv + nx) + T * ny)
    eta = T * (2 * nlam * ny + nlam)
    return gradient + passes + eta


def projection_flops(nx: int, nlam: int, nu: int, horizon: int, shared_mean: bool) -> int:
    """Flops of one projection, one sample (``shared_mean``: the weighted mean of ``u``)."""
    ns = nx + 2 * nlam + nu
    return horizon * (ns + 5 * nlam + (2 * nu if shared_mean else 0))


def admm_flops(nx: int, nlam: int, nu: int, horizon: int, iterations: int, samples: int,
               rho_values: int | None = None, shared_inputs: bool = True) -> AdmmFlops:
    """Flops of one C3+ control step's ADMM over ``samples`` samples (module docstring).

    Parameters
    ----------
    nx, nlam, nu
        LCS dimensions (states, contact forces, inputs).
    horizon
        ``T``.
    iterations
        ADMM iterations.
    samples
        Model samples ``n``.
    rho_values
        Distinct rho values, i.e. factorisations per sample (default ``iterations``: the
        geometric schedule changes rho every iteration and each LCS is new each step).
    shared_inputs
        Whether the samples share ``u`` (the weighted mean in the projection when ``n > 1``).
    """
    values = iterations if rho_values is None else rho_values
    if min(nx, nu, horizon, iterations, samples) < 1 or nlam < 0 or values < 0:
        raise InputError(f"dimensions must be >= 1 (nlam, rho_values >= 0), got nx={nx}, "
                         f"nlam={nlam}, nu={nu}, T={horizon}, iterations={iterations}, "
                         f"samples={samples}, rho_values={values}")
    nv, n = nlam + nu, samples
    ny = nx + nv
    ns = ny + nlam
    prepare = 2 * ny * ny * nlam
    return AdmmFlops(
        factorisation=float(n * (prepare + values * factorisation_flops(nx, nv, horizon))),
        qp_passes=float(n * iterations * qp_pass_flops(nx, nlam, nu, horizon)),
        projection=float(n * iterations * projection_flops(
            nx, nlam, nu, horizon, shared_inputs and n > 1)),
        dual=float(n * iterations * 2 * horizon * ns))


# --- the machine's rate -----------------------------------------------------------------------
@dataclass(frozen=True)
class MachineRates:
    """Dense matmul rates (GFLOP/s, one BLAS thread): the best at the start of a perf run
    (:func:`machine_rates`) or the median through it (:meth:`MatmulProbe.rates`)."""

    float64: float
    float32: float

    def of(self, precision: str) -> float:
        """The rate of ``precision`` (float64 or float32)."""
        return self.float32 if str(precision) == Precision.FLOAT32 else self.float64


def matmul_rate(dtype: type[np.floating] = np.float64, size: int = MATMUL_SIZE,
                repeats: int = MATMUL_REPEATS) -> float:
    """GFLOP/s of ``size x size`` GEMM in ``dtype``: ``2 size^3 / best time``, best of
    ``repeats`` after one untimed product, BLAS on one thread."""
    from c3bench.solvers.timing import single_thread_blas

    if size < 1 or repeats < 1:
        raise InputError(f"size and repeats must be >= 1, got {size}, {repeats}")
    operands = _operands(dtype, size)
    with single_thread_blas():
        return max(_product_rates(operands, repeats))


def _operands(dtype: type[np.floating], size: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Two random ``size x size`` matrices in ``dtype`` and the product's output."""
    rng = np.random.default_rng(0)
    a = rng.standard_normal((size, size)).astype(dtype)
    b = rng.standard_normal((size, size)).astype(dtype)
    return a, b, np.empty((size, size), dtype=dtype)


def _product_rates(operands: tuple[np.ndarray, np.ndarray, np.ndarray], repeats: int
                   ) -> list[float]:
    """GFLOP/s of each of ``repeats`` timed products ``a b`` after one untimed product (BLAS
    threads as the caller set them)."""
    a, b, out = operands
    flops = 2.0 * a.shape[0] * a.shape[1] * b.shape[1]
    np.matmul(a, b, out=out)
    rates = []
    for _ in range(repeats):
        start = time.perf_counter()
        np.matmul(a, b, out=out)
        rates.append(flops / max(time.perf_counter() - start, 1e-12) / 1e9)
    return rates


def machine_rates(size: int = MATMUL_SIZE, repeats: int = MATMUL_REPEATS) -> MachineRates:
    """:func:`matmul_rate` in float64 and float32."""
    return MachineRates(float64=matmul_rate(np.float64, size, repeats),
                        float32=matmul_rate(np.float32, size, repeats))


class MatmulProbe:
    """The dense matmul rate sampled through a run (module docstring): :meth:`sample` once
    per round of timed steps, :meth:`rates` the median over the rounds, float64 and float32.

    Parameters
    ----------
    size
        Side of the matrices (:data:`MATMUL_SIZE`).
    repeats
        Timed products per sample (:data:`MATMUL_PROBE_REPEATS`), their median kept.
    """

    def __init__(self, size: int = MATMUL_SIZE, repeats: int = MATMUL_PROBE_REPEATS) -> None:
        if size < 1 or repeats < 1:
            raise InputError(f"size and repeats must be >= 1, got {size}, {repeats}")
        self.repeats = repeats
        self._operands = {precision: _operands(dtype, size) for precision, dtype in (
            (Precision.FLOAT64, np.float64), (Precision.FLOAT32, np.float32))}
        self.samples: dict[str, list[float]] = {precision: [] for precision in self._operands}
        """Per precision, each sample's median GFLOP/s."""

    def sample(self) -> None:
        """One sample per precision (BLAS threads as the caller set them: one, in a run)."""
        for precision, operands in self._operands.items():
            self.samples[precision].append(
                float(np.median(_product_rates(operands, self.repeats))))

    def rates(self) -> MachineRates:
        """The median of the samples per precision (NaN before the first sample)."""
        def median(values: list[float]) -> float:
            return float(np.median(values)) if values else math.nan

        return MachineRates(float64=median(self.samples[Precision.FLOAT64]),
                            float32=median(self.samples[Precision.FLOAT32]))
