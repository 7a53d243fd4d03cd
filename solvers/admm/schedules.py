"""Rho schedules of the consensus ADMM: how ``G`` changes between iterations.

Each schedule gives a multiplier ``m_i`` applied to the scheduled blocks (``rho_blocks``, by
default ``lam`` and ``eta``) after iteration ``i`` with consensus residual ``r_i``, previous
residual ``r_{i-1}`` (``+inf`` before the first iteration) and dual residual ``s_i``:

* :class:`Geometric`: ``m = factor`` (the reference study's ``rho_i = 50 * 2^i``);
* :class:`Adaptive` (Bertsekas, *Convex Optimization Algorithms*, 2015, section 5.4.1; the
  increase rule of Bertsekas 2014, section 2.2.5): ``m = beta`` when ``r_i >= gamma r_{i-1}``,
  else 1;
* :class:`ResidualBalancing` (Boyd et al., "Distributed optimization and statistical learning
  via ADMM", 2011, section 3.4.1): ``m = tau`` when ``r > mu s``, ``1 / tau`` when
  ``s > mu r``, else 1.

``multiplier`` is written against an array namespace ``xp`` (numpy or ``jax.numpy``), so the
same rule runs in the Python loop and inside a compiled JAX loop. ``plan`` lists every
iteration's rho before the first one when the schedule does not depend on the data (geometric
only), so a kernel can factorise the whole schedule at once.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from types import MappingProxyType, ModuleType
from typing import Any

import numpy as np

from c3bench.solvers.admm.options import C3Options, RhoScheduleName

Rho = dict[str, float]


class Plan(tuple[Mapping[str, float], ...]):
    """A data-independent schedule's rho values, one read-only mapping per iteration (copies
    of the given ones). A plan never changes, so what is derived from one (rho keys, dual
    ratios, stacked constants) may be remembered by its identity (:func:`is_frozen`)."""

    __slots__ = ()

    def __new__(cls, rhos: Iterable[Mapping[str, float]]) -> Plan:
        return super().__new__(cls, (MappingProxyType(dict(rho)) for rho in rhos))


@dataclass(frozen=True)
class Schedule:
    """The base: scaling of the blocks ``blocks`` by :meth:`multiplier`."""

    blocks: tuple[str, ...]

    def multiplier(self, consensus: Any, previous: Any, dual: Any,
                   xp: ModuleType = np) -> Any:
        """The factor applied after an iteration (see the module docstring)."""
        raise NotImplementedError

    def scale(self, rho: Mapping[str, float], factor: float) -> Rho:
        """``rho`` with the scheduled blocks times ``factor``."""
        return {key: float(value) * factor if key in self.blocks else float(value)
                for key, value in rho.items()}

    def next(self, rho: Mapping[str, float], consensus: float, previous: float | None,
             dual: float) -> Rho:
        """``rho_{i+1}`` from ``rho_i`` and the residuals (``previous=None`` at ``i = 0``)."""
        prior = math.inf if previous is None else previous
        return self.scale(rho, float(self.multiplier(consensus, prior, dual)))

    def plan(self, rho0: Mapping[str, float], iterations: int) -> Plan | None:
        """Every iteration's rho when it does not depend on the data, else ``None``."""
        return None


@dataclass(frozen=True)
class Geometric(Schedule):
    """``rho <- factor rho`` every iteration."""

    factor: float = 2.0

    def multiplier(self, consensus: Any, previous: Any, dual: Any,
                   xp: ModuleType = np) -> Any:
        return self.factor

    def plan(self, rho0: Mapping[str, float], iterations: int) -> Plan | None:
        """``rho0 factor^i`` on the scheduled blocks for ``i < iterations``, memoised: a
        controller asks for the same plan every control step and gets the same read-only
        object back, so that what is derived from a plan (rho keys, dual ratios) can be
        remembered by identity."""
        key = (self, tuple(rho0.items()), iterations)
        plan = _PLANS.get(key)
        if plan is None:
            rho = {k: float(value) for k, value in rho0.items()}
            steps = []
            for _ in range(iterations):
                steps.append(rho)
                rho = self.scale(rho, self.factor)
            plan = Plan(steps)
            if len(_PLANS) > 64:
                _PLANS.clear()
            _PLANS[key] = plan
        return plan


_PLANS: dict[tuple[Any, ...], Plan] = {}
"""Memoised plans of :meth:`Geometric.plan`."""


def is_frozen(plan: Sequence[Mapping[str, float]] | None) -> bool:
    """Whether ``plan`` cannot change (a :class:`Plan`, as :meth:`Geometric.plan` returns), so
    that what is derived from it may be remembered by its identity."""
    return isinstance(plan, Plan)


@dataclass(frozen=True)
class Adaptive(Schedule):
    """Grow by ``beta`` unless the consensus residual fell below ``gamma`` times the last."""

    beta: float = 2.0
    gamma: float = 0.25

    def multiplier(self, consensus: Any, previous: Any, dual: Any,
                   xp: ModuleType = np) -> Any:
        return xp.where(consensus >= self.gamma * previous, self.beta, 1.0)


@dataclass(frozen=True)
class ResidualBalancing(Schedule):
    """Keep the consensus and dual residuals within a factor ``mu`` of each other."""

    mu: float = 10.0
    tau: float = 2.0

    def multiplier(self, consensus: Any, previous: Any, dual: Any,
                   xp: ModuleType = np) -> Any:
        return xp.where(consensus > self.mu * dual, self.tau,
                        xp.where(dual > self.mu * consensus, 1.0 / self.tau, 1.0))


def schedule_for(options: C3Options) -> Schedule:
    """The schedule object the options describe."""
    blocks = tuple(options.rho_blocks)
    if options.rho_schedule == RhoScheduleName.GEOMETRIC:
        return Geometric(blocks, float(options.rho_factor))
    if options.rho_schedule == RhoScheduleName.ADAPTIVE:
        return Adaptive(blocks, float(options.adaptive_beta), float(options.adaptive_gamma))
    return ResidualBalancing(blocks, float(options.balance_mu), float(options.balance_tau))
